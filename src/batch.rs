//! Batch registration of a folder of photos: loads each frame's inputs, registers it, and turns
//! every per-frame problem (a missing or corrupt photo, a size mismatch, an invisible model) into a
//! failed frame with its reason, so one bad frame never stops the others. `asgreg register` and
//! `asgreg eval` are built on this.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::core::camera::Camera;
use crate::core::flow_consistency::GreyImage;
use crate::core::mesh::Mesh;
use crate::core::register::{register_frame, FrameInput, RegistrationConfig, StageTimings};
use crate::core::rigid::Rigid3;
use crate::io::images::{check_image_matches_camera, load_gray};
use crate::io::pfm::read_pfm;

/// Where one frame's inputs are.
#[derive(Clone, Debug)]
pub struct BatchFrame {
    pub image_id: u32,
    pub camera_id: u32,
    pub name: String,
    pub image_path: PathBuf,
    /// The photo's depth map (PFM), when registering with [`crate::core::register::QueryMode::DepthAsg`].
    pub depth_path: Option<PathBuf>,
    pub camera: Camera,
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
            timings: StageTimings::default(),
        }
    }
}

/// The frame's depth file in `depth_dir`: `<stem of the image name>.pfm`.
pub fn depth_path_for(depth_dir: &Path, image_name: &str) -> PathBuf {
    let stem = Path::new(image_name)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| image_name.to_string());
    depth_dir.join(format!("{stem}.pfm"))
}

/// Registers one frame; never fails: problems become a failed report naming the file or reason.
pub fn register_batch_frame(
    mesh: &Mesh,
    frame: &BatchFrame,
    config: &RegistrationConfig,
    seed: u64,
) -> FrameReport {
    let photo = match load_gray(&frame.image_path) {
        Ok(photo) => photo,
        Err(error) => return FrameReport::failed(frame, error.to_string()),
    };
    if let Err(error) = check_image_matches_camera(
        &frame.image_path,
        photo.width_px,
        photo.height_px,
        frame.camera_id,
        &frame.camera,
    ) {
        return FrameReport::failed(frame, error.to_string());
    }
    let depth = match &frame.depth_path {
        Some(path) => match read_pfm(path) {
            Ok(depth) => Some(depth),
            Err(error) => return FrameReport::failed(frame, error.to_string()),
        },
        None => None,
    };
    let input = FrameInput {
        photo: GreyImage {
            width_px: photo.width_px,
            height_px: photo.height_px,
            pixels: &photo.pixels,
        },
        depth_m: depth.as_ref().map(|d| GreyImage {
            width_px: d.width_px,
            height_px: d.height_px,
            pixels: &d.depth_m,
        }),
        camera: &frame.camera,
        initial_cam_from_world: frame.initial_cam_from_world,
        seed: crate::stage::ingest::frame_seed(seed, frame.image_id),
    };
    match register_frame(mesh, &input, config) {
        Ok(result) => {
            let chosen = result
                .verdict
                .chosen
                .and_then(|i| result.coarse.iter().filter_map(|o| o.hypothesis).nth(i));
            FrameReport {
                image_id: frame.image_id,
                name: frame.name.clone(),
                accepted: result.accepted,
                reason: result.verdict.rejection.as_ref().map(|r| r.to_string()),
                confidence: result.verdict.confidence,
                consensus: chosen.map_or(0, |h| h.consensus),
                component_size: result.verdict.component.len(),
                direct_support: result.verdict.direct_support,
                convergence_ratio: result.verdict.convergence_ratio,
                hypotheses: result.verdict.hypothesis_count,
                mean_delta_to_chosen_px: result.verdict.mean_delta_to_chosen_px,
                inlier_rms_px: chosen.map(|h| h.inlier_rms_px),
                camera: result.camera,
                cam_from_world: result.cam_from_world,
                rejected_candidate: chosen.filter(|_| !result.accepted).map(|h| {
                    RejectedCandidate {
                        camera: h.camera,
                        cam_from_world: h.cam_from_world,
                    }
                }),
                timings: result.timings,
            }
        }
        Err(error) => FrameReport::failed(frame, format!("{}: {error}", frame.name)),
    }
}
