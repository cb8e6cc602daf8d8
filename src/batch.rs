//! Batch registration of a folder of photos: loads each frame's inputs, registers it, and turns
//! every per-frame problem (a missing or corrupt photo, a size mismatch, an invisible model) into a
//! failed frame with its reason, so one bad frame never stops the others. `asgreg register` and
//! `asgreg eval` are built on this.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::core::camera::Camera;
use crate::core::frame::{
    register_frame, FrameInput, IntrinsicsMode, PoseRefinement, RegistrationConfig, StageTimings,
};
use crate::core::image::Image;
use crate::core::mesh::Mesh;
use crate::core::rigid::Rigid3;
use crate::frame_files::{frame_seed, load_frame_files, FrameFiles, FrameFilesError};

/// Where one frame's inputs are.
#[derive(Clone, Debug)]
pub struct BatchFrame {
    pub image_id: u32,
    pub camera_id: u32,
    pub name: String,
    pub image_path: PathBuf,
    /// The photo's depth map (PFM), when registering with [`crate::core::frame::QueryMode::DepthAsg`].
    pub depth_path: Option<PathBuf>,
    pub camera: Camera,
    /// Whether `camera`'s intrinsics are trusted or estimated.
    pub intrinsics: IntrinsicsMode,
    pub initial_cam_from_world: Rigid3,
}

/// What happened to one frame; exactly one per input frame.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FrameReport {
    pub image_id: u32,
    pub name: String,
    pub accepted: bool,
    /// Why the frame was not accepted (input problem, or the verification's reason).
    pub reason: Option<String>,
    pub confidence: f64,
    /// RANSAC consensus of the chosen pose.
    pub consensus: usize,
    /// Size of the largest group of compatible refined poses.
    pub component_size: usize,
    /// Refined poses directly compatible with the chosen one, itself included.
    pub direct_support: usize,
    /// Spread of the agreeing refined poses over the spread of their coarse poses (small:
    /// converged; near 1: they stayed where they started).
    pub convergence_ratio: Option<f64>,
    /// Refined poses obtained from the coarse poses.
    pub hypotheses: usize,
    /// Mean δ from the chosen pose to the rest of its group, px.
    pub mean_delta_to_chosen_px: f64,
    pub inlier_rms_px: Option<f64>,
    /// The refined camera (estimated intrinsics when unknown) and pose, when accepted.
    pub camera: Option<Camera>,
    pub cam_from_world: Option<Rigid3>,
    /// A rejected frame's would-be output (the verification's chosen hypothesis), kept as
    /// evidence for diagnosing the verification; never a result. None for accepted frames and
    /// for frames without hypotheses.
    pub rejected_candidate: Option<RejectedCandidate>,
    /// The final refinement of the chosen pose (already applied to `cam_from_world` when kept:
    /// its evidence before and after), or why there was none.
    pub refinement: Result<PoseRefinement, String>,
    pub timings: StageTimings,
}

/// The pose a rejected frame would have output.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub struct RejectedCandidate {
    pub camera: Camera,
    pub cam_from_world: Rigid3,
}

impl FrameReport {
    fn failed(frame: &BatchFrame, reason: String) -> Self {
        Self {
            image_id: frame.image_id,
            name: frame.name.clone(),
            accepted: false,
            reason: Some(reason),
            confidence: 0.0,
            consensus: 0,
            component_size: 0,
            direct_support: 0,
            convergence_ratio: None,
            hypotheses: 0,
            mean_delta_to_chosen_px: 0.0,
            inlier_rms_px: None,
            camera: None,
            cam_from_world: None,
            rejected_candidate: None,
            refinement: Err("the frame was not registered".to_string()),
            timings: StageTimings::default(),
        }
    }
}

impl BatchFrame {
    /// Reads the frame's photo and depth map, checked against its camera.
    pub fn load(&self) -> Result<FrameFiles, FrameFilesError> {
        load_frame_files(
            &self.image_path,
            self.camera_id,
            &self.camera,
            self.depth_path.as_deref(),
        )
    }

    /// The frame as registration's input, from its loaded files; `seed` is the run's seed (the
    /// frame's own is derived from it and the image id).
    pub fn input<'a>(&'a self, files: &'a FrameFiles, seed: u64) -> FrameInput<'a> {
        FrameInput {
            photo: files.photo.view(),
            depth_m: files.depth_m.as_ref().map(Image::view),
            camera: &self.camera,
            intrinsics: self.intrinsics,
            initial_cam_from_world: self.initial_cam_from_world,
            seed: frame_seed(seed, self.image_id),
        }
    }
}

/// Registers one frame; never fails: problems become a failed report naming the file or reason.
pub fn register_batch_frame(
    mesh: &Mesh,
    frame: &BatchFrame,
    config: &RegistrationConfig,
    seed: u64,
) -> FrameReport {
    let files = match frame.load() {
        Ok(files) => files,
        Err(error) => return FrameReport::failed(frame, error.to_string()),
    };
    match register_frame(mesh, &frame.input(&files, seed), config) {
        Ok(result) => {
            let verdict = &result.verdict;
            let chosen = verdict.chosen();
            let accepted = verdict.accepted_pose();
            FrameReport {
                image_id: frame.image_id,
                name: frame.name.clone(),
                accepted: verdict.accepted(),
                reason: verdict.rejection().map(|r| r.to_string()),
                confidence: verdict.confidence,
                consensus: chosen.map_or(0, |h| h.consensus),
                component_size: verdict.component.len(),
                direct_support: verdict.direct_support,
                convergence_ratio: verdict.convergence_ratio,
                hypotheses: verdict.hypothesis_count,
                mean_delta_to_chosen_px: verdict.mean_delta_to_chosen_px,
                inlier_rms_px: chosen.map(|h| h.inlier_rms_px),
                camera: accepted.map(|h| h.camera),
                cam_from_world: accepted.map(|h| h.cam_from_world),
                rejected_candidate: verdict
                    .decision
                    .as_ref()
                    .err()
                    .and_then(|rejection| rejection.candidate)
                    .map(|h| RejectedCandidate {
                        camera: h.camera,
                        cam_from_world: h.cam_from_world,
                    }),
                refinement: result.refinement,
                timings: result.timings,
            }
        }
        Err(error) => FrameReport::failed(frame, format!("{}: {error}", frame.name)),
    }
}
