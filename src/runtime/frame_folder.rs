//! A folder of one message per frame in the state folder, written so that a crash leaves the
//! old file or the new one, never half of one (a temporary name, then a rename), and tied to its
//! run by a `header` file (another run's files are removed). What a restarted stage needs back
//! that is too large for a results journal's line: verify's stereo views (`views`, the photos of
//! its stereo neighbours), pose lenders (`lenders`) and received messages (`received`, a frame's
//! query and hypotheses as parts of one frame) and fusion's sights (`sights`, the frames' depths
//! for the free-space test). One implementation, so all keep the same crash rules and the same warnings: writing
//! is best effort (a file that cannot be written costs only what a restart would get back, so it
//! is a warning, once until writing works again), and a file that cannot be read back is removed
//! with a warning.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use crate::msg::Body;

use super::config::PipelineConfig;
use super::journal;

/// What a folder holds and what losing a file costs, for its warnings.
#[derive(Clone, Copy, Debug)]
pub struct FolderKind {
    /// The stage that keeps the folder ("verify").
    pub stage: &'static str,
    /// The folder's name after the pipeline's (`<pipeline>.<name>`) and its files' extension.
    pub name: &'static str,
    pub extension: &'static str,
    /// One file's content, for the messages ("stereo view").
    pub what: &'static str,
    /// What a restart of the stage loses without a frame's file.
    pub loss: &'static str,
}

/// One frame's message per file: `<state_dir>/<pipeline>.<name>/<frame id>.<extension>`, in
/// the one wire encoding.
pub struct FrameFolder {
    kind: FolderKind,
    dir: PathBuf,
    /// Whether a write failed since the last success (warned once).
    failing: bool,
}

/// The folder `<state_dir>/<pipeline>.<name>` of a configuration.
pub fn dir_of(config: &PipelineConfig, name: &str) -> PathBuf {
    journal::state_dir(config).join(format!("{}.{name}", config.transport.pipeline))
}

/// Starts a run over: removes the folder (none is fine).
pub fn reset(config: &PipelineConfig, kind: &FolderKind) -> std::io::Result<()> {
    match std::fs::remove_dir_all(dir_of(config, kind.name)) {
        Err(error) if error.kind() != std::io::ErrorKind::NotFound => Err(error),
        _ => Ok(()),
    }
}

/// The file of `frame_id`'s message in the folder `dir` of `kind`.
pub fn path_in(dir: &Path, kind: &FolderKind, frame_id: u64) -> PathBuf {
    dir.join(format!("{frame_id}.{}", kind.extension))
}

/// Reads the file `path` and hands its message (`frame_id`'s, or an error saying whose it is)
/// to `take`: the error of the read, the decoding or `take`, without the path.
pub fn read_message(
    path: &Path,
    frame_id: u64,
    take: &mut dyn FnMut(u64, &Body<'_>) -> Result<(), String>,
) -> Result<(), String> {
    let bytes = std::fs::read(path).map_err(|error| error.to_string())?;
    let message = crate::msg::decode(&bytes).map_err(|error| error.to_string())?;
    if message.header.frame_id != frame_id {
        return Err(format!(
            "it holds a {:?} message of frame {}",
            message.body.kind(),
            message.header.frame_id
        ));
    }
    take(frame_id, &message.body)
}

/// Removes the file `path` (none is fine).
fn remove_file(path: &Path) -> std::io::Result<()> {
    match std::fs::remove_file(path) {
        Err(error) if error.kind() != std::io::ErrorKind::NotFound => Err(error),
        _ => Ok(()),
    }
}

impl FrameFolder {
    /// Opens the configuration's folder of `kind` and hands each message of this run to
    /// `restore` (frame id and body; an error: the file is removed with a warning). Another
    /// run's files are removed.
    pub fn open_and_restore(
        config: &PipelineConfig,
        kind: FolderKind,
        restore: &mut dyn FnMut(u64, &Body<'_>) -> Result<(), String>,
    ) -> Self {
        let mut folder = Self {
            kind,
            dir: dir_of(config, kind.name),
            failing: false,
        };
        let header = format!(
            "# asgreg {} v1 pipeline={} poses={} max_frames={}\n",
            kind.name,
            config.transport.pipeline,
            config.source.poses.display(),
            config.source.max_frames
        );
        match folder.claim(&header) {
            Ok(true) => {}
            Ok(false) => return folder,
            Err(error) => {
                tracing::warn!(
                    "{}: {}: cannot start the folder of each frame's {} ({error}); a restart of {} will lose {}",
                    kind.stage,
                    folder.dir.display(),
                    kind.what,
                    kind.stage,
                    kind.loss
                );
                folder.failing = true;
                return folder;
            }
        }
        for (frame_id, path) in folder.listed() {
            if let Err(error) = read_message(&path, frame_id, restore) {
                tracing::warn!(
                    "{}: {}: not a {} ({error}); removed (this restart loses {})",
                    kind.stage,
                    path.display(),
                    kind.what,
                    kind.loss
                );
                let _ = remove_file(&path);
            }
        }
        folder
    }

    /// The file of `frame_id`'s message.
    pub fn path(&self, frame_id: u64) -> PathBuf {
        path_in(&self.dir, &self.kind, frame_id)
    }

    /// The file of part `part` of `frame_id`'s messages.
    pub fn part_path(&self, frame_id: u64, part: &str) -> PathBuf {
        self.dir
            .join(format!("{frame_id}.{part}.{}", self.kind.extension))
    }

    /// The messages in the folder, frame by frame: each file's frame id and path (a frame's
    /// one message, `<frame id>.<extension>`, or its parts, `<frame id>.<part>.<extension>`).
    fn listed(&self) -> Vec<(u64, PathBuf)> {
        let Ok(entries) = std::fs::read_dir(&self.dir) else {
            return Vec::new();
        };
        let mut files: Vec<(u64, PathBuf)> = entries
            .filter_map(|entry| entry.ok())
            .filter_map(|entry| {
                let name = entry.file_name();
                let stem = name
                    .to_str()?
                    .strip_suffix(self.kind.extension)?
                    .strip_suffix('.')?;
                let frame = stem.split_once('.').map_or(stem, |(frame, _)| frame);
                Some((frame.parse::<u64>().ok()?, entry.path()))
            })
            .collect();
        files.sort();
        files
    }

    /// Whether the folder is this run's (its `header` file holds `header`). When it is not, its
    /// messages are removed and it is started for this run (the error: it cannot be).
    fn claim(&self, header: &str) -> std::io::Result<bool> {
        let header_path = self.dir.join("header");
        if std::fs::read_to_string(&header_path).is_ok_and(|found| found == header) {
            return Ok(true);
        }
        for (_, path) in self.listed() {
            let _ = std::fs::remove_file(path);
        }
        std::fs::create_dir_all(&self.dir)?;
        std::fs::write(&header_path, header.as_bytes())?;
        Ok(false)
    }

    /// Writes `body` as `frame_id`'s message (replacing any earlier one whole); best effort:
    /// whether it was written (a failure is warned once until a write works again).
    pub fn write(&mut self, frame_id: u64, body: Body<'_>) -> bool {
        self.write_to(frame_id, self.path(frame_id), body)
    }

    /// Writes `body` as part `part` (letters and digits) of `frame_id`'s messages, as
    /// [`FrameFolder::write`] does a frame's one message.
    pub fn write_part(&mut self, frame_id: u64, part: &str, body: Body<'_>) -> bool {
        self.write_to(frame_id, self.part_path(frame_id, part), body)
    }

    fn write_to(&mut self, frame_id: u64, path: PathBuf, body: Body<'_>) -> bool {
        let written = super::bus::encode_to_vec(frame_id, 0, body)
            .map_err(|error| error.to_string())
            .and_then(|bytes| {
                let mut partial = path.clone().into_os_string();
                partial.push(".partial");
                std::fs::create_dir_all(&self.dir)
                    .and_then(|()| std::fs::write(&partial, &bytes))
                    .and_then(|()| std::fs::rename(&partial, &path))
                    .map_err(|error| error.to_string())
            });
        let kind = &self.kind;
        match written {
            Ok(()) => {
                if self.failing {
                    tracing::info!(
                        "{}: each frame's {} is written again in {}",
                        kind.stage,
                        kind.what,
                        self.dir.display()
                    );
                    self.failing = false;
                }
                true
            }
            Err(error) => {
                if !self.failing {
                    tracing::warn!(
                        "{}: {}: cannot write the {} of frame {frame_id} ({error}); a restart of {} would lose {}",
                        kind.stage,
                        self.dir.display(),
                        kind.what,
                        kind.stage,
                        kind.loss
                    );
                }
                self.failing = true;
                false
            }
        }
    }

    /// Removes `frame_id`'s message (none is fine).
    pub fn remove(&self, frame_id: u64) -> std::io::Result<()> {
        remove_file(&self.path(frame_id))
    }

    /// Removes part `part` of `frame_id`'s messages (none is fine).
    pub fn remove_part(&self, frame_id: u64, part: &str) -> std::io::Result<()> {
        remove_file(&self.part_path(frame_id, part))
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }
}

/// A frame folder kept equal to the frames a stage keeps (verify's stereo views and pose
/// lenders): restored into the stage when a restarted stage opens it, then synced before each
/// batch of results goes out.
pub struct MirrorFolder {
    folder: FrameFolder,
    /// The frames written (or found) in the folder.
    on_disk: BTreeSet<u64>,
}

impl MirrorFolder {
    /// Opens the configuration's folder of `kind` and hands each message of this run to
    /// `restore` ([`FrameFolder::open_and_restore`]); returns the folder with how many were
    /// restored.
    pub fn open_and_restore(
        config: &PipelineConfig,
        kind: FolderKind,
        restore: &mut dyn FnMut(u64, &Body<'_>) -> Result<(), String>,
    ) -> (Self, usize) {
        let mut on_disk = BTreeSet::new();
        let folder = FrameFolder::open_and_restore(config, kind, &mut |frame_id, body| {
            restore(frame_id, body)?;
            on_disk.insert(frame_id);
            Ok(())
        });
        let restored = on_disk.len();
        (Self { folder, on_disk }, restored)
    }

    /// Makes the folder hold the frames `kept`: writes the new ones (`message` of each; `None`:
    /// skipped), removes those no longer kept. Call it before publishing the results of the
    /// frames concluded since the last call (a frame whose results are out is not sent again
    /// after a restart, so its file must be on disk by then).
    pub fn sync<'a>(
        &mut self,
        kept: BTreeSet<u64>,
        message: &mut dyn FnMut(u64) -> Option<Body<'a>>,
    ) {
        let new: Vec<u64> = kept.difference(&self.on_disk).copied().collect();
        for frame_id in new {
            let Some(body) = message(frame_id) else {
                continue;
            };
            if self.folder.write(frame_id, body) {
                self.on_disk.insert(frame_id);
            }
        }
        let gone: Vec<u64> = self.on_disk.difference(&kept).copied().collect();
        for frame_id in gone {
            match self.folder.remove(frame_id) {
                Err(error) => tracing::debug!(
                    "{}: {} of frame {frame_id} not removed: {error}",
                    self.folder.kind.stage,
                    self.folder.kind.what
                ),
                Ok(()) => {
                    self.on_disk.remove(&frame_id);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::StreamEnd;

    const KIND: FolderKind = FolderKind {
        stage: "test",
        name: "parts-test",
        extension: "msg",
        what: "test message",
        loss: "nothing",
    };

    fn end(frame_count: u64) -> Body<'static> {
        Body::StreamEnd(StreamEnd {
            frame_count,
            finished_frames: Vec::new(),
        })
    }

    fn restored(config: &PipelineConfig) -> (FrameFolder, Vec<(u64, u64)>) {
        let mut seen = Vec::new();
        let folder =
            FrameFolder::open_and_restore(config, KIND, &mut |frame_id, body| match body {
                Body::StreamEnd(end) => {
                    seen.push((frame_id, end.frame_count));
                    Ok(())
                }
                other => Err(format!("{:?}", other.kind())),
            });
        (folder, seen)
    }

    /// A frame's parts are restored with the frame's id beside a frame's one message, removed
    /// one by one (not another frame's), and another run's files are removed, not restored.
    #[test]
    fn parts_of_a_frame_are_restored_and_removed_together() {
        let state = tempfile::tempdir().unwrap();
        let mut config = PipelineConfig {
            state_dir: Some(state.path().to_path_buf()),
            ..PipelineConfig::default()
        };
        config.transport.pipeline = "parts-test".to_string();
        let (mut folder, seen) = restored(&config);
        assert!(seen.is_empty());
        assert!(folder.write_part(3, "query", end(30)));
        assert!(folder.write_part(3, "h1", end(31)));
        assert!(folder.write_part(12, "h0", end(120)));
        assert!(folder.write(4, end(40)));
        let (folder, mut seen) = restored(&config);
        seen.sort();
        assert_eq!(seen, vec![(3, 30), (3, 31), (4, 40), (12, 120)]);
        folder.remove_part(3, "query").unwrap();
        folder.remove_part(3, "h1").unwrap();
        let (_, mut seen) = restored(&config);
        seen.sort();
        assert_eq!(seen, vec![(4, 40), (12, 120)]);
        config.source.max_frames = 7;
        let (_, seen) = restored(&config);
        assert!(seen.is_empty(), "another run's files: {seen:?}");
    }
}
