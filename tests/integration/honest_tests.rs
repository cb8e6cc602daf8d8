//! No test passes by skipping itself. A test whose data or tool is missing either fails, naming
//! what is missing, or is `#[ignore]`d with the reason (`tests/data/README.md`); the old way, print
//! "skipped" and return early, shows a green test that tested nothing. This scans every `.rs`
//! file under `src/` and `tests/` for a print of "skip…".

use std::path::{Path, PathBuf};

/// Prints of "skip…" not converted yet, as the text from the macro's `(` on (the file may move in
/// the meantime). Each must still be found, so that an entry goes when its print does.
const NOT_YET_CONVERTED: &[&str] = &[];

/// Lower case, without any whitespace: a macro call that rustfmt broke over lines still matches.
fn normalised(text: &str) -> String {
    text.chars()
        .filter(|c| !c.is_whitespace())
        .flat_map(char::to_lowercase)
        .collect()
}

fn rust_files(directory: &Path, files: &mut Vec<PathBuf>) {
    let entries = std::fs::read_dir(directory)
        .unwrap_or_else(|error| panic!("{}: {error}", directory.display()));
    for entry in entries {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, files);
        } else if path.extension().is_some_and(|extension| extension == "rs") {
            files.push(path);
        }
    }
}

#[test]
fn no_test_prints_skipped_and_passes() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    rust_files(&root.join("src"), &mut files);
    rust_files(&root.join("tests"), &mut files);
    assert!(files.len() > 20, "only {} .rs files found", files.len());
    // Split so that this file does not match itself.
    let macros = [concat!("print", "ln!"), concat!("print", "!")];
    let exceptions: Vec<String> = NOT_YET_CONVERTED.iter().map(|t| normalised(t)).collect();
    let mut exceptions_found = vec![false; exceptions.len()];
    let mut offenders = Vec::new();
    for file in &files {
        let text = normalised(&std::fs::read_to_string(file).unwrap());
        for name in macros {
            let needle = format!("{name}(\"skip");
            for (start, _) in text.match_indices(&needle) {
                let call = &text[start + name.len()..];
                match exceptions
                    .iter()
                    .position(|allowed| call.starts_with(allowed))
                {
                    Some(index) => exceptions_found[index] = true,
                    None => offenders.push(format!(
                        "{}: {}",
                        file.strip_prefix(root).unwrap_or(file).display(),
                        call.chars().take(60).collect::<String>()
                    )),
                }
            }
        }
    }
    assert!(
        offenders.is_empty(),
        "tests that print \"skip…\" (fail instead, or #[ignore = \"reason\"]; see \
         tests/data/README.md):\n{}",
        offenders.join("\n")
    );
    for (allowed, found) in NOT_YET_CONVERTED.iter().zip(exceptions_found) {
        assert!(
            found,
            "{allowed} is gone: remove it from NOT_YET_CONVERTED in {}",
            file!()
        );
    }
}
