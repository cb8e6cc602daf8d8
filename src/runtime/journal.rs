//! The results journal: what has a published result survives a crash. Verify appends each frame
//! id right after it publishes the frame's PoseResult; a restarted verify reads it and publishes
//! none of those again, and a restarted ingest reads it and resumes instead of replaying the
//! source (it sends only the frames without a result). One text file per pipeline under
//! `state_dir`: a header line naming the run's pipeline and source, then one frame id per line.
//! `asgreg launch` starts each run with an empty journal and removes it when the run is
//! complete; `asgreg run` (threads, which never restart) keeps one of its own in a temporary
//! folder; stages started by hand continue the one they find (delete it to start over). A line
//! cut short by a crash is ignored. The one window left for a repeated result is a crash of
//! verify between publishing a result and appending its id (the JSON send and one `write`
//! call). Appends are not fsync'ed: the journal survives a process crash, not a power cut.

use std::collections::BTreeSet;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::config::PipelineConfig;

#[derive(Debug, thiserror::Error)]
pub enum JournalError {
    #[error("{path}: cannot {action} the results journal: {source} (set `state_dir` in the pipeline config to a writable folder)")]
    Io {
        path: PathBuf,
        action: &'static str,
        source: std::io::Error,
    },
}

/// The header that ties a journal to a run's pipeline and source: a journal with another
/// header (an earlier run over other photos) is not read.
pub fn header(config: &PipelineConfig) -> String {
    format!(
        "# asgreg results journal v1 pipeline={} poses={} max_frames={}",
        config.transport.pipeline,
        config.source.poses.display(),
        config.source.max_frames
    )
}

/// Where a configuration keeps its results journal.
pub fn path(config: &PipelineConfig) -> PathBuf {
    let dir = config
        .state_dir
        .clone()
        .unwrap_or_else(|| std::env::temp_dir().join("asgreg-state"));
    dir.join(format!("{}.results-journal", config.transport.pipeline))
}

/// Starts a run over: removes the journal (none is fine).
pub fn reset(path: &Path) -> Result<(), JournalError> {
    match std::fs::remove_file(path) {
        Ok(()) => Ok(()),
        Err(error) if error.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(source) => Err(JournalError::Io {
            path: path.to_path_buf(),
            action: "remove",
            source,
        }),
    }
}

/// The frame ids a journal text lists under `header`; `None` when its header is another.
/// Lines not ended by a newline (cut short by a crash) and unreadable lines are left out.
fn parse(text: &str, header: &str) -> Option<BTreeSet<u64>> {
    let mut lines = text.split_inclusive('\n');
    if lines.next().map(str::trim_end) != Some(header) {
        return None;
    }
    Some(
        lines
            .filter(|line| line.ends_with('\n'))
            .filter_map(|line| line.trim().parse().ok())
            .collect(),
    )
}

/// The frames that have a published result, as the journal at `path` says (ingest's view);
/// empty when there is no journal or it belongs to another run.
pub fn read_published(path: &Path, header: &str) -> Result<BTreeSet<u64>, JournalError> {
    match std::fs::read_to_string(path) {
        Ok(text) => Ok(parse(&text, header).unwrap_or_default()),
        Err(error) if error.kind() == std::io::ErrorKind::NotFound => Ok(BTreeSet::new()),
        Err(source) => Err(JournalError::Io {
            path: path.to_path_buf(),
            action: "read",
            source,
        }),
    }
}

/// The writer's side (verify).
pub struct ResultsJournal {
    path: PathBuf,
    file: std::fs::File,
}

impl ResultsJournal {
    /// Opens the journal for appending and returns the frames it already lists: continues a
    /// journal with this header, starts one (over one of another run) otherwise.
    pub fn open(path: &Path, header: &str) -> Result<(Self, BTreeSet<u64>), JournalError> {
        let io = |action: &'static str| {
            move |source| JournalError::Io {
                path: path.to_path_buf(),
                action,
                source,
            }
        };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(io("create the folder of"))?;
        }
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .append(true)
            .create(true)
            .open(path)
            .map_err(io("open"))?;
        let mut text = String::new();
        file.read_to_string(&mut text).map_err(io("read"))?;
        let published = match parse(&text, header) {
            Some(published) => {
                // Finish a line cut short by a crash, so the next id starts a line of its own.
                if !text.ends_with('\n') {
                    file.write_all(b"\n").map_err(io("append to"))?;
                }
                published
            }
            None => {
                if !text.is_empty() {
                    tracing::warn!(
                        "{}: results journal of another run (header differs); starting it over",
                        path.display()
                    );
                }
                file.set_len(0).map_err(io("truncate"))?;
                file.seek(SeekFrom::Start(0)).map_err(io("rewind"))?;
                file.write_all(format!("{header}\n").as_bytes())
                    .map_err(io("write"))?;
                BTreeSet::new()
            }
        };
        Ok((
            Self {
                path: path.to_path_buf(),
                file,
            },
            published,
        ))
    }

    /// Records that `frame_id`'s result is published (one `write` call).
    pub fn append(&mut self, frame_id: u64) -> Result<(), JournalError> {
        self.file
            .write_all(format!("{frame_id}\n").as_bytes())
            .map_err(|source| JournalError::Io {
                path: self.path.clone(),
                action: "append to",
                source,
            })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_journal_is_continued_by_its_run_and_started_over_by_another() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state").join("p.results-journal");
        assert!(read_published(&path, "# run a").unwrap().is_empty());
        let (mut journal, published) = ResultsJournal::open(&path, "# run a").unwrap();
        assert!(published.is_empty());
        for frame_id in [0, 3, 1] {
            journal.append(frame_id).unwrap();
        }
        drop(journal);
        let expected: BTreeSet<u64> = [0, 1, 3].into();
        assert_eq!(read_published(&path, "# run a").unwrap(), expected);
        // A crash mid-line: the cut line is not counted, and the next append starts a new line.
        std::fs::OpenOptions::new()
            .append(true)
            .open(&path)
            .unwrap()
            .write_all(b"1")
            .unwrap();
        assert_eq!(read_published(&path, "# run a").unwrap(), expected);
        let (mut journal, published) = ResultsJournal::open(&path, "# run a").unwrap();
        assert_eq!(published, expected);
        journal.append(7).unwrap();
        let expected: BTreeSet<u64> = [0, 1, 3, 7].into();
        assert_eq!(read_published(&path, "# run a").unwrap(), expected);
        // Another run's reader sees nothing; its writer starts the file over.
        assert!(read_published(&path, "# run b").unwrap().is_empty());
        let (_, published) = ResultsJournal::open(&path, "# run b").unwrap();
        assert!(published.is_empty());
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "# run b\n");
        reset(&path).unwrap();
        reset(&path).unwrap();
        assert!(!path.exists());
    }

    #[test]
    fn an_unwritable_state_dir_is_named_in_the_error() {
        let dir = tempfile::tempdir().unwrap();
        let blocker = dir.path().join("not-a-dir");
        std::fs::write(&blocker, b"").unwrap();
        let path = blocker.join("p.results-journal");
        let error = ResultsJournal::open(&path, "# h")
            .err()
            .unwrap()
            .to_string();
        assert!(
            error.contains("not-a-dir") && error.contains("state_dir"),
            "{error}"
        );
    }
}
