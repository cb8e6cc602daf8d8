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
//! A last line cut short by a crash mid-write is tolerated: readers leave it out, and the writer
//! that reopens the journal cuts it off (with a warning). Any other line that is not a journal
//! line (a corrupt file), or a journal its permissions forbid reading, is an error that names the
//! file and the line and says what to do ([`JournalError::needs_operator`]): the stage exits with
//! [`super::EXIT_NEEDS_OPERATOR`] and `launch` gives up on it at once, naming the journal, instead
//! of restarting it into the same error.
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
    #[error(
        "{path}: cannot {action} the results journal: {source} ({})",
        io_hint(action, source)
    )]
    Io {
        path: PathBuf,
        action: &'static str,
        source: std::io::Error,
    },
    /// A complete line that is not a journal line (a corrupt file, not a crash mid-write:
    /// that leaves only the last line cut short, which is tolerated).
    #[error("{path}: the results journal is damaged at line {line} ({detail}); a restart cannot mend it: move the file aside (or delete it) to replay the source from the start, which publishes its frames' results again")]
    Damaged {
        path: PathBuf,
        line: usize,
        detail: String,
    },
}

impl JournalError {
    /// True when restarting the stage cannot help: the journal is damaged or its permissions
    /// forbid reading it; the operator has to act (the launcher then gives up on the stage at
    /// once instead of restarting it into the same error).
    pub fn needs_operator(&self) -> bool {
        match self {
            JournalError::Damaged { .. } => true,
            JournalError::Io { source, .. } => {
                source.kind() == std::io::ErrorKind::PermissionDenied
            }
        }
    }
}

/// What to do about an I/O error on a journal.
fn io_hint(action: &str, source: &std::io::Error) -> &'static str {
    if source.kind() == std::io::ErrorKind::PermissionDenied {
        "give the stages' user read and write permission on it, or move it aside to replay the source from the start"
    } else if action == "read" {
        "move it aside to replay the source from the start, or set `state_dir` in the pipeline config to another folder"
    } else {
        "free space there, or set `state_dir` in the pipeline config to a writable folder"
    }
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

/// What a journal's bytes say.
#[derive(Debug, Default)]
struct Parsed {
    /// The frames listed, each with its payload (empty when the line has none; the first line
    /// of a frame wins); `None` when the file is empty or its header is another run's.
    entries: Option<BTreeMap<u64, String>>,
    /// Bytes up to the end of the last complete line: a last line not ended by a newline (a
    /// crash mid-write) is left out, and a writer cuts the file back to here.
    good_len: usize,
}

/// Parses a journal's bytes under `header`: a header line, then one `<frame id>[ <hex
/// payload>]` line per result (empty lines are skipped). A last line without its newline (a
/// crash mid-write, or mid-header) is left out; any other line that is not one is
/// [`JournalError::Damaged`] (returned as line number and what is wrong).
fn parse(bytes: &[u8], header: &str) -> Result<Parsed, (usize, String)> {
    let good_len = bytes
        .iter()
        .rposition(|&byte| byte == b'\n')
        .map_or(0, |at| at + 1);
    let mut lines = bytes[..good_len].split_inclusive(|&byte| byte == b'\n');
    let Some(first) = lines.next() else {
        // Empty, or a header cut short by a crash: nothing listed yet.
        if header.as_bytes().starts_with(bytes) {
            return Ok(Parsed::default());
        }
        return Err((1, "the first line is not a journal header".to_string()));
    };
    let first = std::str::from_utf8(first)
        .map_err(|_| (1, "the header is not text".to_string()))?
        .trim_end();
    if first != header {
        if first.starts_with("# ") {
            // Another run's journal.
            return Ok(Parsed {
                entries: None,
                good_len,
            });
        }
        return Err((1, "the first line is not a journal header".to_string()));
    }
    let mut entries = BTreeMap::new();
    for (index, line) in lines.enumerate() {
        let number = index + 2;
        let line = std::str::from_utf8(line)
            .map_err(|_| (number, "the line is not text".to_string()))?
            .trim();
        if line.is_empty() {
            continue;
        }
        let (id, payload) = line.split_once(' ').unwrap_or((line, ""));
        let frame_id = id
            .parse::<u64>()
            .map_err(|_| (number, format!("`{}` is not a frame id", clip(id))))?;
        if payload.len() % 2 != 0 || !payload.bytes().all(|byte| byte.is_ascii_hexdigit()) {
            return Err((number, format!("frame {frame_id}'s payload is not hex")));
        }
        entries
            .entry(frame_id)
            .or_insert_with(|| payload.to_string());
    }
    Ok(Parsed {
        entries: Some(entries),
        good_len,
    })
}

/// At most 24 characters of a damaged field, for an error message.
fn clip(text: &str) -> String {
    let mut clipped: String = text.chars().take(24).collect();
    if clipped.len() < text.len() {
        clipped.push('…');
    }
    clipped
}

/// The bytes of an open journal, at most its length when opened: a path that is not a regular
/// file (e.g. `/dev/full`, which reads as endless zeros) reads as empty instead of forever; a
/// folder is an error (it would read as an empty journal: every frame replayed).
fn read_bytes(file: &mut std::fs::File) -> std::io::Result<Vec<u8>> {
    let metadata = file.metadata()?;
    if metadata.is_dir() {
        return Err(std::io::Error::other("it is a folder, not a journal file"));
    }
    let length = if metadata.is_file() {
        metadata.len()
    } else {
        0
    };
    let mut bytes = Vec::new();
    file.take(length).read_to_end(&mut bytes)?;
    Ok(bytes)
}

/// The bytes of the open journal at `path` and what they say under `header`.
fn read_parsed(
    file: &mut std::fs::File,
    path: &Path,
    header: &str,
) -> Result<(Vec<u8>, Parsed), JournalError> {
    let bytes = read_bytes(file).map_err(|source| JournalError::Io {
        path: path.to_path_buf(),
        action: "read",
        source,
    })?;
    let parsed = parse(&bytes, header).map_err(|(line, detail)| JournalError::Damaged {
        path: path.to_path_buf(),
        line,
        detail,
    })?;
    Ok((bytes, parsed))
}

/// What a journal file holds (a reader's view).
#[derive(Debug, Default)]
pub struct Contents {
    /// The frames listed under the run's header, with their payloads.
    pub entries: BTreeMap<u64, String>,
    /// Bytes of a last line cut short by a crash mid-write (left out; 0 when none).
    pub cut_bytes: usize,
}

/// Reads the journal at `path` under `header`: empty when there is no journal or it belongs
/// to another run; a damaged one is an error naming the line.
pub fn read(path: &Path, header: &str) -> Result<Contents, JournalError> {
    let io = |action: &'static str| {
        move |source| JournalError::Io {
            path: path.to_path_buf(),
            action,
            source,
        }
    };
    let mut file = match std::fs::File::open(path) {
        Ok(file) => file,
        Err(error) if error.kind() == std::io::ErrorKind::NotFound => {
            return Ok(Contents::default())
        }
        Err(source) => return Err(io("read")(source)),
    };
    let (bytes, parsed) = read_parsed(&mut file, path, header)?;
    Ok(Contents {
        entries: parsed.entries.unwrap_or_default(),
        cut_bytes: bytes.len() - parsed.good_len,
    })
}

/// The frames a journal at `path` lists under `header`, with their payloads (see [`read`]).
pub fn read_entries(path: &Path, header: &str) -> Result<BTreeMap<u64, String>, JournalError> {
    Ok(read(path, header)?.entries)
}

/// The frames that have a published result, as the journal at `path` says (ingest's view);
/// empty when there is no journal or it belongs to another run.
pub fn read_published(path: &Path, header: &str) -> Result<BTreeSet<u64>, JournalError> {
    Ok(read_entries(path, header)?.into_keys().collect())
}

/// Reads every results journal of a configuration (the pose journal, and the change journal
/// with change detection) and returns the first error: what the launcher names when a stage
/// gave up on a journal.
pub fn check(config: &PipelineConfig) -> Result<(), JournalError> {
    let kinds: &[Kind] = if config.changes_enabled() {
        &[Kind::Pose, Kind::Change]
    } else {
        &[Kind::Pose]
    };
    for &kind in kinds {
        read(&path(config, kind), &header(config, kind))?;
    }
    Ok(())
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
        let (bytes, parsed) = read_parsed(&mut file, path, header)?;
        let published = match parsed.entries {
            Some(published) => {
                // Cut off a last line cut short by a crash, so the next id starts a line of
                // its own (a cut `12 ab` finished with a newline would read as a damaged line).
                if parsed.good_len < bytes.len() {
                    tracing::warn!(
                        "{}: the last line ({} bytes) was cut short by a crash mid-write; kept the {} complete lines before it",
                        path.display(),
                        bytes.len() - parsed.good_len,
                        published.len()
                    );
                    file.set_len(parsed.good_len as u64)
                        .map_err(io("truncate"))?;
                }
                published
            }
            None => {
                if parsed.good_len > 0 {
                    tracing::warn!(
                        "{}: results journal of another run (header differs); starting it over",
                        path.display()
                    );
                }
                if !bytes.is_empty() {
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

    #[test]
    fn a_last_line_cut_by_a_crash_is_left_out_and_cut_off_by_the_writer() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.change-journal");
        std::fs::write(&path, "# h\n3 ab01\n5\n12 ab0").unwrap();
        // The reader keeps the good prefix and says how much it left out.
        let contents = read(&path, "# h").unwrap();
        assert_eq!(contents.entries.keys().copied().collect::<Vec<_>>(), [3, 5]);
        assert_eq!(contents.cut_bytes, 6);
        // The writer cuts the partial line off (finishing it would make `12 ab0` a damaged
        // line) and appends after the good prefix.
        let (mut journal, entries) = Journal::open_with_payloads(&path, "# h").unwrap();
        assert_eq!(entries.len(), 2);
        journal.append_with(12, "ab01").unwrap();
        drop(journal);
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "# h\n3 ab01\n5\n12 ab01\n"
        );
        assert_eq!(read(&path, "# h").unwrap().cut_bytes, 0);
        // A header cut short (a crash right after creating the journal) lists nothing.
        std::fs::write(&path, "# ").unwrap();
        assert!(read(&path, "# h").unwrap().entries.is_empty());
        let (_, entries) = Journal::open(&path, "# h").unwrap();
        assert!(entries.is_empty());
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "# h\n");
    }

    #[test]
    fn a_damaged_journal_is_an_error_naming_the_file_and_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.results-journal");
        let cases: [(&[u8], usize, &str); 5] = [
            (b"# h\n1\nseven\n3\n", 3, "`seven` is not a frame id"),
            (b"# h\n1 ab\n2 xyz1\n", 3, "payload is not hex"),
            (b"# h\n1\n\xff\xfe2\n", 3, "not text"),
            (b"\x00\x00\x00\n1\n", 1, "not a journal header"),
            (b"\x00garbage", 1, "not a journal header"),
        ];
        for (bytes, line, detail) in cases {
            std::fs::write(&path, bytes).unwrap();
            for error in [
                read(&path, "# h").unwrap_err(),
                Journal::open(&path, "# h").err().unwrap(),
            ] {
                let message = error.to_string();
                assert!(error.needs_operator(), "{message}");
                assert!(
                    message.contains(&path.display().to_string())
                        && message.contains(&format!("at line {line} "))
                        && message.contains(detail)
                        && message.contains("move the file aside"),
                    "{message}"
                );
            }
            // The writer that could not open it left it as it was, for the operator.
            assert_eq!(std::fs::read(&path).unwrap(), bytes);
        }
        // Another run's journal (a header of its own) is no damage: it is not this run's.
        std::fs::write(&path, "# other run\nanything\n").unwrap();
        assert!(read(&path, "# h").unwrap().entries.is_empty());
    }

    #[test]
    fn an_unreadable_journal_is_an_error_naming_the_file_and_what_to_do() {
        let dir = tempfile::tempdir().unwrap();
        // A folder where the journal should be: it opens but cannot be read.
        let path = dir.path().join("p.results-journal");
        std::fs::create_dir(&path).unwrap();
        let message = read(&path, "# h").unwrap_err().to_string();
        assert!(
            message.contains("p.results-journal")
                && message.contains("cannot read")
                && message.contains("move it aside"),
            "{message}"
        );
        // Without read permission (only where permissions bind: not as root).
        let path = dir.path().join("q.results-journal");
        std::fs::write(&path, "# h\n1\n").unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o000)).unwrap();
        if std::fs::File::open(&path).is_err() {
            let error = read(&path, "# h").unwrap_err();
            let message = error.to_string();
            assert!(error.needs_operator(), "{message}");
            assert!(
                message.contains("q.results-journal") && message.contains("permission"),
                "{message}"
            );
        }
    }
}
