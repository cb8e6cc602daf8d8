//! The results journals: what has a published result survives a crash. Four journals per
//! pipeline, one implementation ([`Journal`]), under `state_dir`: a header line naming the run's
//! pipeline, source and kind, then one line per published frame, `<frame id>[ <payload>]`.
//! - the pose journal ([`Kind::Pose`]): verify appends each frame id with its published
//!   PoseResult (hex of the encoded message) right after it publishes it; a restarted verify
//!   publishes none of those again (it only sends the unacknowledged ones again, see below);
//! - the change journal ([`Kind::Change`]): fusion appends each frame id with its published
//!   ChangeResult (hex of the encoded message) right after publishing it; a restarted fusion
//!   reads them back, publishes none of them again and fuses them with the rest.
//! - the acknowledgement journals ([`Kind::PoseAcked`], [`Kind::ChangeAcked`], ids only):
//!   verify and fusion append each frame whose result the collector acknowledged
//!   (`runtime::ack`); a restarted verify or fusion sends the journaled results that are not
//!   acknowledged again (the same message, so consumers see a re-delivery).
//!
//! A restarted ingest reads the first two and resumes instead of replaying the source: it sends only the
//! frames without a published result (with change detection: without both results).
//! `asgreg launch` starts each run with empty journals and removes them when the run is complete;
//! `asgreg run` (threads, which never restart) keeps its own in a folder of its own under
//! `state_dir`; stages started by hand continue the ones they find (delete them to start over).
//! A line cut short by a crash is ignored.
//!
//! The pose and change journals are written ahead: a result's line is appended before the
//! result is published, so a crash between the two leaves a journaled result that the restarted
//! verify or fusion sends (the same bytes: a re-delivery, never a second result). When the line
//! cannot be written (a full disk, a state folder gone read-only), the frame's result becomes a
//! failed one whose reason names the journal and the cause (a result the station cannot record is
//! not given out as accepted); the stage goes on, and a journal that cannot even be opened is
//! tried again at each append ([`Journal::open_or_retry`]), so a full disk never makes a stage
//! crash-loop and the journal resumes once there is room. A line cut short by a failed write is
//! cut off again. Appends are not fsync'ed: the journals survive a process crash, not a power
//! cut.

use std::collections::{BTreeMap, BTreeSet};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use super::config::PipelineConfig;

#[derive(Debug, thiserror::Error)]
pub enum JournalError {
    #[error("{path}: cannot {action} the results journal: {source} (free space there, or set `state_dir` in the pipeline config to a writable folder)")]
    Io {
        path: PathBuf,
        action: &'static str,
        source: std::io::Error,
    },
}

/// Which results a journal lists.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// Published PoseResults (verify writes it), frame ids only.
    Pose,
    /// Published ChangeResults (fusion writes it), each with its encoded result.
    Change,
    /// PoseResults the collector acknowledged (verify writes it), frame ids only.
    PoseAcked,
    /// ChangeResults the collector acknowledged (fusion writes it), frame ids only.
    ChangeAcked,
}

impl Kind {
    fn file_suffix(self) -> &'static str {
        match self {
            Kind::Pose => "results-journal",
            Kind::Change => "change-journal",
            Kind::PoseAcked => "results-acked",
            Kind::ChangeAcked => "change-acked",
        }
    }
}

/// The header that ties a journal to a run's pipeline and source: a journal with another
/// header (an earlier run over other photos) is not read.
pub fn header(config: &PipelineConfig, kind: Kind) -> String {
    let what = match kind {
        Kind::Pose => "results",
        Kind::Change => "change results",
        Kind::PoseAcked => "acknowledged results",
        Kind::ChangeAcked => "acknowledged change results",
    };
    format!(
        "# asgreg {what} journal v1 pipeline={} poses={} max_frames={}",
        config.transport.pipeline,
        config.source.poses.display(),
        config.source.max_frames
    )
}

/// The folder of a configuration's journals: `state_dir`, or `asgreg-state` in the system's
/// temporary folder.
pub fn state_dir(config: &PipelineConfig) -> PathBuf {
    config
        .state_dir
        .clone()
        .unwrap_or_else(|| std::env::temp_dir().join("asgreg-state"))
}

/// Proves, before a run, that `dir` (a state folder) can be made and written; the error names
/// it and says what to do.
pub fn prepare_state_dir(dir: &Path) -> Result<(), crate::io::output::OutputDirError> {
    crate::io::output::prepare_dir(
        dir,
        "state folder (the results journals)",
        "set `state_dir` in the pipeline config to a writable folder, or fix its permissions or free space",
    )
}

/// Where a configuration keeps its journal of `kind`.
pub fn path(config: &PipelineConfig, kind: Kind) -> PathBuf {
    state_dir(config).join(format!(
        "{}.{}",
        config.transport.pipeline,
        kind.file_suffix()
    ))
}

/// Starts a run over: removes every journal of a configuration (none is fine).
pub fn reset_all(config: &PipelineConfig) -> Result<(), JournalError> {
    for kind in [Kind::Pose, Kind::Change, Kind::PoseAcked, Kind::ChangeAcked] {
        reset(&path(config, kind))?;
    }
    Ok(())
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

/// The frame ids a journal text lists under `header`, each with its payload (empty when the
/// line has none; the first line of a frame wins); `None` when its header is another. Lines not
/// ended by a newline (cut short by a crash) and unreadable lines are left out.
fn parse(text: &str, header: &str) -> Option<BTreeMap<u64, String>> {
    let mut lines = text.split_inclusive('\n');
    if lines.next().map(str::trim_end) != Some(header) {
        return None;
    }
    let mut entries = BTreeMap::new();
    for line in lines.filter(|line| line.ends_with('\n')) {
        let line = line.trim();
        let (id, payload) = line.split_once(' ').unwrap_or((line, ""));
        if let Ok(frame_id) = id.parse::<u64>() {
            entries
                .entry(frame_id)
                .or_insert_with(|| payload.to_string());
        }
    }
    Some(entries)
}

/// The text of an open journal, at most its length when opened: a path that is not a regular
/// file (e.g. `/dev/full`, which reads as endless zeros) reads as empty instead of forever.
fn read_text(file: &mut std::fs::File) -> std::io::Result<String> {
    let metadata = file.metadata()?;
    let length = if metadata.is_file() {
        metadata.len()
    } else {
        0
    };
    let mut text = String::new();
    file.take(length).read_to_string(&mut text)?;
    Ok(text)
}

/// The frames a journal at `path` lists under `header`, with their payloads; empty when there is
/// no journal or it belongs to another run.
pub fn read_entries(path: &Path, header: &str) -> Result<BTreeMap<u64, String>, JournalError> {
    let io = |action: &'static str| {
        move |source| JournalError::Io {
            path: path.to_path_buf(),
            action,
            source,
        }
    };
    let mut file = match std::fs::File::open(path) {
        Ok(file) => file,
        Err(error) if error.kind() == std::io::ErrorKind::NotFound => return Ok(BTreeMap::new()),
        Err(source) => return Err(io("read")(source)),
    };
    let text = read_text(&mut file).map_err(io("read"))?;
    Ok(parse(&text, header).unwrap_or_default())
}

/// The frames that have a published result, as the journal at `path` says (ingest's view);
/// empty when there is no journal or it belongs to another run.
pub fn read_published(path: &Path, header: &str) -> Result<BTreeSet<u64>, JournalError> {
    Ok(read_entries(path, header)?.into_keys().collect())
}

/// The writer's side (verify for poses, fusion for change results).
pub struct Journal {
    path: PathBuf,
    header: String,
    /// `None` while the journal cannot be opened: the next append tries again.
    file: Option<std::fs::File>,
}

impl Journal {
    /// Opens the journal for appending and returns the frames it already lists: continues a
    /// journal with this header, starts one (over one of another run) otherwise.
    pub fn open(path: &Path, header: &str) -> Result<(Self, BTreeSet<u64>), JournalError> {
        let (journal, entries) = Self::open_with_payloads(path, header)?;
        Ok((journal, entries.into_keys().collect()))
    }

    /// As [`Journal::open`], with each listed frame's payload.
    pub fn open_with_payloads(
        path: &Path,
        header: &str,
    ) -> Result<(Self, BTreeMap<u64, String>), JournalError> {
        let (file, entries) = Self::open_file(path, header)?;
        Ok((
            Self {
                path: path.to_path_buf(),
                header: header.to_string(),
                file: Some(file),
            },
            entries,
        ))
    }

    /// As [`Journal::open_with_payloads`], but a journal that cannot be opened (a full disk, a
    /// read-only state folder) is no error that stops the stage: the entries are read as far as
    /// they can be, the error is returned beside them, and each append tries to open it again
    /// (and fails with the cause while it cannot).
    pub fn open_or_retry(
        path: &Path,
        header: &str,
    ) -> (Self, BTreeMap<u64, String>, Option<JournalError>) {
        match Self::open_with_payloads(path, header) {
            Ok((journal, entries)) => (journal, entries, None),
            Err(error) => {
                let entries = read_entries(path, header).unwrap_or_default();
                let journal = Self {
                    path: path.to_path_buf(),
                    header: header.to_string(),
                    file: None,
                };
                (journal, entries, Some(error))
            }
        }
    }

    fn open_file(
        path: &Path,
        header: &str,
    ) -> Result<(std::fs::File, BTreeMap<u64, String>), JournalError> {
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
        let text = read_text(&mut file).map_err(io("read"))?;
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
                    file.set_len(0).map_err(io("truncate"))?;
                    file.seek(SeekFrom::Start(0)).map_err(io("rewind"))?;
                }
                file.write_all(format!("{header}\n").as_bytes())
                    .map_err(io("write"))?;
                BTreeMap::new()
            }
        };
        Ok((file, published))
    }

    /// Records that `frame_id`'s result is published (one `write` call).
    pub fn append(&mut self, frame_id: u64) -> Result<(), JournalError> {
        self.append_with(frame_id, "")
    }

    /// Records that `frame_id`'s result is published, with `payload` (no spaces or newlines:
    /// e.g. hex) that a restart gets back from [`Journal::open_with_payloads`]. A journal that
    /// could not be opened is opened first; a line only partly written (a disk that filled
    /// mid-line) is cut off again, so the next line starts clean.
    pub fn append_with(&mut self, frame_id: u64, payload: &str) -> Result<(), JournalError> {
        let file = match &mut self.file {
            Some(file) => file,
            None => {
                let (file, _) = Self::open_file(&self.path, &self.header)?;
                self.file.insert(file)
            }
        };
        let line = if payload.is_empty() {
            format!("{frame_id}\n")
        } else {
            format!("{frame_id} {payload}\n")
        };
        let length_before = file.metadata().map(|m| m.len()).ok();
        file.write_all(line.as_bytes()).map_err(|source| {
            if let Some(length) = length_before {
                // Shrinking needs no free space; on a file that cannot be cut (a device) the
                // partial line stays, and a reader leaves out what does not parse.
                let _ = file.set_len(length);
            }
            JournalError::Io {
                path: self.path.clone(),
                action: "append to",
                source,
            }
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Bytes as a journal payload (lower-case hex).
pub fn to_hex(bytes: &[u8]) -> String {
    use std::fmt::Write as _;
    let mut text = String::with_capacity(bytes.len() * 2);
    for byte in bytes {
        // Writing to a String cannot fail.
        let _ = write!(text, "{byte:02x}");
    }
    text
}

/// A journal payload back as bytes; `None` when it is not hex (a damaged line).
pub fn from_hex(text: &str) -> Option<Vec<u8>> {
    if text.len() % 2 != 0 {
        return None;
    }
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(text.get(i..i + 2)?, 16).ok())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_journal_is_continued_by_its_run_and_started_over_by_another() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state").join("p.results-journal");
        assert!(read_published(&path, "# run a").unwrap().is_empty());
        let (mut journal, published) = Journal::open(&path, "# run a").unwrap();
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
        let (mut journal, published) = Journal::open(&path, "# run a").unwrap();
        assert_eq!(published, expected);
        journal.append(7).unwrap();
        let expected: BTreeSet<u64> = [0, 1, 3, 7].into();
        assert_eq!(read_published(&path, "# run a").unwrap(), expected);
        // Another run's reader sees nothing; its writer starts the file over.
        assert!(read_published(&path, "# run b").unwrap().is_empty());
        let (_, published) = Journal::open(&path, "# run b").unwrap();
        assert!(published.is_empty());
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "# run b\n");
        reset(&path).unwrap();
        reset(&path).unwrap();
        assert!(!path.exists());
    }

    #[test]
    fn payloads_come_back_with_their_frames_and_the_first_line_of_a_frame_wins() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.change-journal");
        let (mut journal, entries) = Journal::open_with_payloads(&path, "# c").unwrap();
        assert!(entries.is_empty());
        let bytes = [0u8, 1, 0xab, 0xff];
        journal.append_with(4, &to_hex(&bytes)).unwrap();
        journal.append_with(4, "00").unwrap();
        journal.append(2).unwrap();
        drop(journal);
        let (_, entries) = Journal::open_with_payloads(&path, "# c").unwrap();
        assert_eq!(entries.len(), 2);
        assert_eq!(from_hex(&entries[&4]).unwrap(), bytes);
        assert_eq!(entries[&2], "");
        assert_eq!(read_published(&path, "# c").unwrap(), [2, 4].into());
        assert_eq!(from_hex("0g"), None);
        assert_eq!(from_hex("abc"), None);
    }

    #[test]
    fn an_unwritable_state_dir_is_named_in_the_error() {
        let dir = tempfile::tempdir().unwrap();
        let blocker = dir.path().join("not-a-dir");
        std::fs::write(&blocker, b"").unwrap();
        let path = blocker.join("p.results-journal");
        let error = Journal::open(&path, "# h").err().unwrap().to_string();
        assert!(
            error.contains("not-a-dir") && error.contains("state_dir"),
            "{error}"
        );
    }
}
