//! Verify's stereo views made durable: the accepted frames that verify keeps as stereo
//! references and neighbours (`stage::verify`, their registered camera, pose and grey photo)
//! written to the state folder, one file per frame, so that a restarted verify still has the
//! frames accepted before the restart as neighbours. Without it, the frames whose pose and change
//! results were both out before a restart are not sent again, their photos are gone, and the next
//! `stereo.window_frames` frames lose their stereo neighbours (a change result "no depth"
//! instead of a change map).
//!
//! Each view is a `ChangeJob` without neighbours in the one wire encoding (`msg`), in
//! `<state_dir>/<pipeline>.stereo-views/<frame id>.view` (a `frame_folder`: written whole or not
//! at all, tied to its run by a header, another run's views removed), and removed once verify no
//! longer keeps the frame: the folder holds at most the frames within the window of those still
//! waiting. Writing is best effort: a view that cannot be written costs
//! only stereo neighbours after a restart, so it is a warning, not a failed frame.

use std::path::PathBuf;

use crate::msg::Body;
use crate::stage::verify::VerifyStage;

use super::config::PipelineConfig;
use super::frame_folder::{self, FolderKind, MirrorFolder};

const VIEWS: FolderKind = FolderKind {
    stage: "verify",
    name: "stereo-views",
    extension: "view",
    what: "stereo view",
    loss: "the frame as a stereo neighbour",
};

/// The folder of a configuration's stereo views.
pub fn dir(config: &PipelineConfig) -> PathBuf {
    frame_folder::dir_of(config, VIEWS.name)
}

/// Starts a run over: removes the views folder (none is fine).
pub fn reset(config: &PipelineConfig) -> std::io::Result<()> {
    frame_folder::reset(config, &VIEWS)
}

/// Verify's durable stereo views.
pub struct ViewStore {
    folder: MirrorFolder,
}

impl ViewStore {
    /// Opens the configuration's views folder, restores the views of this run into `stage`
    /// (as neighbours; a view that cannot be read is removed with a warning) and returns the
    /// store with how many were restored. Another run's views are removed.
    pub fn open_and_restore(config: &PipelineConfig, stage: &mut VerifyStage<'_>) -> (Self, usize) {
        let (folder, restored) =
            MirrorFolder::open_and_restore(config, VIEWS, &mut |frame_id, body| match body {
                Body::ChangeJob(job) => stage.restore_stereo_view(frame_id, job),
                other => Err(format!("it holds a {:?} message", other.kind())),
            });
        (Self { folder }, restored)
    }

    /// Makes the folder hold the views `stage` keeps ([`MirrorFolder::sync`]).
    pub fn sync(&mut self, stage: &VerifyStage<'_>) {
        self.folder
            .sync(stage.stereo_view_ids().collect(), &mut |frame_id| {
                stage.stereo_view(frame_id).map(Body::ChangeJob)
            });
    }
}
