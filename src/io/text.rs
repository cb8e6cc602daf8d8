//! Text files read whole, with the place of the first byte that is not UTF-8: "stream did not
//! contain valid UTF-8" alone does not say where a COLMAP model, a CSV or a config went wrong.

use std::path::Path;

/// Reads `path` as UTF-8 text. A file that is not UTF-8 is an `InvalidData` error whose message
/// gives the line and column (1-based) of the first bad byte and what to do; callers put the path
/// in front, as for any other read error.
pub fn read_utf8(path: &Path) -> std::io::Result<String> {
    let bytes = std::fs::read(path)?;
    String::from_utf8(bytes).map_err(|error| {
        let valid = &error.as_bytes()[..error.utf8_error().valid_up_to()];
        let line = valid.iter().filter(|&&byte| byte == b'\n').count() + 1;
        let column = valid.len() - valid.iter().rposition(|&byte| byte == b'\n').map_or(0, |at| at + 1) + 1;
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!(
                "line {line}, column {column}: byte 0x{:02X} is not UTF-8 text (a binary file, or text in another encoding: save it as UTF-8)",
                error.as_bytes()[valid.len()]
            ),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_byte_that_is_not_utf8_is_placed() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cameras.txt");
        std::fs::write(&path, b"# comment\n1 PINHOLE 64 \xff8 60 60 32 24\n").unwrap();
        let message = read_utf8(&path).unwrap_err().to_string();
        assert!(
            message.starts_with("line 2, column 14: byte 0xFF is not UTF-8"),
            "{message}"
        );
        std::fs::write(&path, "é\n").unwrap();
        assert_eq!(read_utf8(&path).unwrap(), "é\n");
    }
}
