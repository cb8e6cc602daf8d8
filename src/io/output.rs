//! The output folder of a command, checked before any work: a run that registers for an hour and
//! then cannot write its results has wasted the hour. Errors name the folder and say what to do.

use std::io::Write as _;
use std::path::{Path, PathBuf};

/// The output folder (or another folder a command writes, e.g. the pipeline's state folder)
/// cannot be made or written.
#[derive(Debug, thiserror::Error)]
#[error("{}: the {what} cannot be {action}: {source}; {remedy}", .path.display())]
pub struct OutputDirError {
    pub path: PathBuf,
    /// Which folder, in words ("output folder").
    pub what: &'static str,
    pub action: &'static str,
    #[source]
    pub source: std::io::Error,
    /// What to do about it.
    pub remedy: &'static str,
}

/// Name of the probe file written (and removed) in the output folder.
const PROBE_FILE: &str = ".asgreg-write-probe";

/// Creates `dir` (and its parents) and proves that a file can be written in it, by writing and
/// removing a small probe file. A folder on a full disk usually fails here too (the probe's data
/// is flushed with `sync_all`); one that fills up later fails at the first output file, whose
/// error names that file.
pub fn prepare_output_dir(dir: &Path) -> Result<(), OutputDirError> {
    prepare_dir(
        dir,
        "output folder",
        "choose another output folder, or fix its permissions or free space",
    )
}

/// [`prepare_output_dir`] for any folder a command must write: `what` names it in the error,
/// `remedy` says what to do.
pub fn prepare_dir(
    dir: &Path,
    what: &'static str,
    remedy: &'static str,
) -> Result<(), OutputDirError> {
    let error = |action, source| OutputDirError {
        path: dir.to_path_buf(),
        what,
        action,
        source,
        remedy,
    };
    std::fs::create_dir_all(dir).map_err(|source| error("created", source))?;
    let probe = dir.join(PROBE_FILE);
    let written = std::fs::File::create(&probe).and_then(|mut file| {
        file.write_all(&[0; 4096])?;
        file.sync_all()
    });
    let removed = std::fs::remove_file(&probe);
    written.map_err(|source| error("written", source))?;
    removed.map_err(|source| error("written", source))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_folder_that_cannot_be_created_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a-file");
        std::fs::write(&file, "not a folder").unwrap();
        let out = file.join("out");
        let message = prepare_output_dir(&out).unwrap_err().to_string();
        assert!(
            message.starts_with(&format!(
                "{}: the output folder cannot be created",
                out.display()
            )),
            "{message}"
        );
        assert!(!message.contains('\n'), "{message}");
    }

    #[test]
    fn a_writable_folder_is_made_and_left_empty() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("a/b");
        prepare_output_dir(&out).unwrap();
        assert_eq!(std::fs::read_dir(&out).unwrap().count(), 0);
    }
}
