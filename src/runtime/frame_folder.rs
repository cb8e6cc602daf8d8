//! A folder of one message per frame in the state folder, written so that a crash leaves the
//! old file or the new one, never half of one (a temporary name, then a rename), and tied to its
//! run by a `header` file (another run's files are removed). What a restarted stage needs back
//! that is too large for a results journal's line: verify's stereo views (`views`, the photos of
//! its stereo neighbours) and fusion's sights (`sights`, the frames' depths for the free-space
//! test). One implementation, so both keep the same crash rules.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use crate::msg::Body;

/// One frame's message per file: `<dir>/<frame id>.<extension>`, in the one wire encoding.
pub struct FrameFolder {
    dir: PathBuf,
    extension: &'static str,
}

impl FrameFolder {
    pub fn new(dir: PathBuf, extension: &'static str) -> Self {
        Self { dir, extension }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The file of `frame_id`'s message.
    pub fn path(&self, frame_id: u64) -> PathBuf {
        self.dir.join(format!("{frame_id}.{}", self.extension))
    }

    /// The frame ids of the messages in the folder.
    pub fn listed(&self) -> BTreeSet<u64> {
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return BTreeSet::new();
        };
        entries
            .filter_map(|entry| entry.ok())
            .filter_map(|entry| {
                let name = entry.file_name();
                name.to_str()?
                    .strip_suffix(self.extension)?
                    .strip_suffix('.')?
                    .parse::<u64>()
                    .ok()
            })
            .collect()
    }

    /// Whether the folder is this run's (its `header` file holds `header`). When it is not, its
    /// messages are removed and it is started for this run (the error: it cannot be).
    pub fn claim(&self, header: &str) -> std::io::Result<bool> {
        let header_path = self.dir.join("header");
        if std::fs::read_to_string(&header_path).is_ok_and(|found| found == header) {
            return Ok(true);
        }
        for frame_id in self.listed() {
            let _ = std::fs::remove_file(self.path(frame_id));
        }
        std::fs::create_dir_all(&self.dir)?;
        std::fs::write(&header_path, header.as_bytes())?;
        Ok(false)
    }

    /// Writes `body` as `frame_id`'s message (replacing any earlier one whole).
    pub fn write(&self, frame_id: u64, body: Body<'_>) -> Result<(), String> {
        let bytes =
            super::bus::encode_to_vec(frame_id, 0, body).map_err(|error| error.to_string())?;
        let partial = self
            .dir
            .join(format!("{frame_id}.{}.partial", self.extension));
        std::fs::create_dir_all(&self.dir)
            .and_then(|()| std::fs::write(&partial, &bytes))
            .and_then(|()| std::fs::rename(&partial, self.path(frame_id)))
            .map_err(|error| error.to_string())
    }

    /// The bytes of `frame_id`'s message.
    pub fn read(&self, frame_id: u64) -> Result<Vec<u8>, String> {
        std::fs::read(self.path(frame_id)).map_err(|error| error.to_string())
    }

    /// Removes `frame_id`'s message (none is fine).
    pub fn remove(&self, frame_id: u64) -> std::io::Result<()> {
        match std::fs::remove_file(self.path(frame_id)) {
            Err(error) if error.kind() != std::io::ErrorKind::NotFound => Err(error),
            _ => Ok(()),
        }
    }

    /// Starts a run over: removes the folder (none is fine).
    pub fn reset(dir: &Path) -> std::io::Result<()> {
        match std::fs::remove_dir_all(dir) {
            Err(error) if error.kind() != std::io::ErrorKind::NotFound => Err(error),
            _ => Ok(()),
        }
    }
}
