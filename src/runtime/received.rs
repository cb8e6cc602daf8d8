//! Verify's received messages made durable: each frame's query (`FrameQuery`) and coarse poses'
//! hypotheses (`Hypothesis`) as verify receives them, written to the state folder (one file per
//! message, the frame's parts) until the frame's result is published, so that a restarted verify
//! decides the frames it had instead of waiting for the pipeline to render, match and solve
//! them again. With step "neighbour" verify holds every frame until the frames of its window
//! have their results and the frames of its look-ahead their own decisions; without this store a
//! restart lost all of them at once, and a verify killed more often than those frames took to
//! come round again never published another result (a CI zenoh soak: 18 of 40 results in 462 s
//! with a kill a second, docs/measurements.md, thirty-fifth session).
//!
//! Files: `<state_dir>/<pipeline>.verify-received/<frame id>.<part>.msg` (a `frame_folder`:
//! written whole or not at all, tied to its run by a header, another run's files removed), part
//! `query` or `h<coarse index>`, in the one wire encoding. Writing is best effort: a message that
//! cannot be written costs only its redo after a restart (ingest sends a frame again when verify
//! restarts), so it is a warning, not a failed frame.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;

use crate::msg::Body;
use crate::stage::verify::VerifyStage;

use super::config::PipelineConfig;
use super::frame_folder::{self, FolderKind, FrameFolder};

const RECEIVED: FolderKind = FolderKind {
    stage: "verify",
    name: "verify-received",
    extension: "msg",
    what: "received message",
    loss: "the message (the frame is sent through the pipeline again)",
};

/// The folder of a configuration's received messages.
pub fn dir(config: &PipelineConfig) -> PathBuf {
    frame_folder::dir_of(config, RECEIVED.name)
}

/// Starts a run over: removes the folder (none is fine).
pub fn reset(config: &PipelineConfig) -> std::io::Result<()> {
    frame_folder::reset(config, &RECEIVED)
}

/// The part a message is stored as; `None`: verify does not keep it.
fn part_of(body: &Body<'_>) -> Option<String> {
    match body {
        Body::FrameQuery(_) => Some("query".to_string()),
        Body::Hypothesis(hypothesis) => Some(format!("h{}", hypothesis.meta.outcome.coarse_index)),
        _ => None,
    }
}

/// Verify's durable received messages.
pub struct ReceivedStore {
    folder: FrameFolder,
    /// The parts on disk, by frame (restored or written), so that a published frame's files are
    /// removed without listing the folder.
    on_disk: BTreeMap<u64, BTreeSet<String>>,
}

impl ReceivedStore {
    /// Opens the configuration's folder and hands this run's messages to `stage` as if they had
    /// just arrived, but those of the frames in `published` (their files are removed): returns
    /// the store with how many frames got messages back. Another run's files are removed.
    pub fn open_and_restore(
        config: &PipelineConfig,
        stage: &mut VerifyStage<'_>,
        published: &BTreeSet<u64>,
    ) -> (Self, usize) {
        let mut on_disk: BTreeMap<u64, BTreeSet<String>> = BTreeMap::new();
        let folder = FrameFolder::open_and_restore(config, RECEIVED, &mut |frame_id, body| {
            let part =
                part_of(body).ok_or_else(|| format!("it holds a {:?} message", body.kind()))?;
            if !published.contains(&frame_id) {
                match body {
                    Body::FrameQuery(query) => stage.on_query(frame_id, query),
                    Body::Hypothesis(hypothesis) => stage.on_hypothesis(frame_id, hypothesis),
                    _ => {}
                }
            }
            on_disk.entry(frame_id).or_default().insert(part);
            Ok(())
        });
        let mut store = Self { folder, on_disk };
        let restored = store
            .on_disk
            .keys()
            .filter(|frame_id| !published.contains(frame_id))
            .count();
        for frame_id in published {
            store.forget(*frame_id);
        }
        (store, restored)
    }

    /// Keeps `body`, a message verify received for `frame_id` and took in
    /// ([`VerifyStage::takes_messages_of`] before it was handed over), when it is one verify keeps
    /// (a query or a hypothesis).
    pub fn keep(&mut self, frame_id: u64, body: Body<'_>) {
        if let Some(part) = part_of(&body) {
            if self.folder.write_part(frame_id, &part, body) {
                self.on_disk.entry(frame_id).or_default().insert(part);
            }
        }
    }

    /// Drops `frame_id`'s messages: its result is out.
    pub fn forget(&mut self, frame_id: u64) {
        for part in self.on_disk.remove(&frame_id).unwrap_or_default() {
            if let Err(error) = self.folder.remove_part(frame_id, &part) {
                tracing::debug!(
                    "verify: received message {part} of frame {frame_id} not removed from {}: {error}",
                    self.folder.dir().display()
                );
            }
        }
    }
}
