//! Verify's pose lenders made durable: the accepted frames that verify keeps to lend their
//! poses to the frames after them (step "neighbour", `stage::verify`: query image, registered
//! camera and pose, steps) written to the state folder, one file per frame, so that a restarted
//! verify still has the frames accepted before the restart as lenders. Without it, a frame whose
//! window reaches back before a restart would be tried against fewer neighbours than in a run
//! without the restart, and its result could differ from `register`'s.
//!
//! Each lender is a `PoseLender` message (kind 15, never on the bus) in the one wire encoding
//! (`msg`), in `<state_dir>/<pipeline>.pose-lenders/<frame id>.lender` (a `frame_folder`: written
//! whole or not at all, tied to its run by a header, another run's lenders removed), and removed
//! once no frame without its result can borrow it. Writing is best effort: a lender that cannot
//! be written costs only a neighbour after a restart, so it is a warning, not a failed frame.

use std::path::PathBuf;

use crate::msg::Body;
use crate::stage::verify::VerifyStage;

use super::config::PipelineConfig;
use super::frame_folder::{self, FolderKind, MirrorFolder};

const LENDERS: FolderKind = FolderKind {
    stage: "verify",
    name: "pose-lenders",
    extension: "lender",
    what: "pose lender",
    loss: "the frame as a lender of its pose (step \"neighbour\")",
};

/// The folder of a configuration's pose lenders.
pub fn dir(config: &PipelineConfig) -> PathBuf {
    frame_folder::dir_of(config, LENDERS.name)
}

/// Starts a run over: removes the lenders folder (none is fine).
pub fn reset(config: &PipelineConfig) -> std::io::Result<()> {
    frame_folder::reset(config, &LENDERS)
}

/// Verify's durable pose lenders.
pub struct LenderStore {
    folder: MirrorFolder,
}

impl LenderStore {
    /// Opens the configuration's lenders folder, restores this run's lenders into `stage` (a
    /// file that cannot be read is removed with a warning) and returns the store with how many
    /// were restored. Another run's lenders are removed.
    pub fn open_and_restore(config: &PipelineConfig, stage: &mut VerifyStage<'_>) -> (Self, usize) {
        let (folder, restored) =
            MirrorFolder::open_and_restore(config, LENDERS, &mut |frame_id, body| match body {
                Body::PoseLender(lender) => stage.restore_lender(frame_id, lender),
                other => Err(format!("it holds a {:?} message", other.kind())),
            });
        (Self { folder }, restored)
    }

    /// Makes the folder hold the lenders `stage` keeps ([`MirrorFolder::sync`]).
    pub fn sync(&mut self, stage: &VerifyStage<'_>) {
        self.folder
            .sync(stage.lender_ids().collect(), &mut |frame_id| {
                stage.lender(frame_id).map(Body::PoseLender)
            });
    }
}
