//! Stage "change": an accepted frame's ChangeJob (registered camera and pose, the photo's depth
//! map) becomes its ChangeResult by the change detection of one frame (`core::change::
//! detect_changes`, the same function `asgreg changes` calls). Runs as N workers, dispatched
//! like flow. [`photo_depth`] is the one place that decides where a frame's depth comes from.

use std::time::Instant;

use crate::core::change::{detect_changes, ChangeClass, ChangeConfig, ChangeWorkspace};
use crate::core::image::{Image, ImageView};
use crate::core::mesh::Mesh;
use crate::msg::{ChangeJob, ChangeResult};

use super::elapsed_ms;

/// Why a frame has no change map although it was registered.
pub const NO_DEPTH: &str = "no depth: the source has no depth map for this frame (set source.depth to a folder of <image stem>.pfm); depth computed in the pipeline from neighbouring frames is not built yet";

/// The depth map a frame's change map compares with the model: the given one (MVS, as
/// `asgreg changes --depth`) when the frame carries it. In-pipeline depth (plane-sweep stereo
/// from the frame and its registered neighbours) goes here, as the `None` branch.
pub fn photo_depth<'j>(job: &'j ChangeJob) -> Result<ImageView<'j, f32>, String> {
    match job.depth() {
        Ok(Some(depth)) => Ok(depth),
        Ok(None) => Err(NO_DEPTH.to_string()),
        Err(error) => Err(format!("depth map unusable: {error}")),
    }
}

pub struct ChangeStage<'m> {
    mesh: &'m Mesh,
    config: ChangeConfig,
    worker_index: u32,
    workspace: ChangeWorkspace,
    classes: Image<ChangeClass>,
}

impl<'m> ChangeStage<'m> {
    pub fn new(mesh: &'m Mesh, config: ChangeConfig, worker_index: u32) -> Self {
        Self {
            mesh,
            config,
            worker_index,
            workspace: ChangeWorkspace::new(),
            classes: Image::default(),
        }
    }

    /// The frame's change result; a frame without usable depth gets one saying why.
    pub fn process(&mut self, frame_id: u64, job: &ChangeJob) -> ChangeResult {
        let started = Instant::now();
        let meta = &job.meta;
        let mut result = ChangeResult {
            frame_id,
            name: meta.info.name.clone(),
            failure: None,
            counts: Default::default(),
            regions: Vec::new(),
            change_ms: 0.0,
            change_worker: Some(self.worker_index),
        };
        let detected = photo_depth(job).and_then(|depth| {
            detect_changes(
                self.mesh,
                &meta.camera.intrinsics,
                &meta.cam_from_world,
                depth,
                &self.config,
                &mut self.workspace,
                &mut self.classes,
            )
            .map_err(|error| error.to_string())
        });
        match detected {
            Ok(changes) => {
                result.counts = changes.counts;
                result.regions = changes.regions;
            }
            Err(why) => result.failure = Some(why),
        }
        result.change_ms = elapsed_ms(started);
        result
    }
}

/// The change result of a frame that has no pose: why there is no change map.
pub fn not_registered(frame_id: u64, name: &str, failure: Option<&str>) -> ChangeResult {
    ChangeResult {
        frame_id,
        name: name.to_string(),
        failure: Some(format!(
            "not registered: {}",
            failure.unwrap_or("the pose was rejected")
        )),
        counts: Default::default(),
        regions: Vec::new(),
        change_ms: 0.0,
        change_worker: None,
    }
}
