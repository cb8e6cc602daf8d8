//! Step "solve": one coarse view's 2D–3D correspondences become a refined pose by RANSAC (EPnP
//! for known intrinsics, the 11-DoF DLT for unknown, EPnP with unknown focal length when only the
//! focal length is unknown) and Levenberg–Marquardt (paper §3.3,
//! docs/design.md §2 step 6), or the reason there is none.

use nalgebra::{Vector2, Vector3};

use super::{
    frame_rng, CoarseOutcome, IntrinsicsMode, RegistrationConfig, UnknownIntrinsics,
    ViewCorrespondences,
};
use crate::core::camera::Camera;
use crate::core::pose::epnpf::FocalPrior;
use crate::core::pose::estimate::{estimate_pose, IntrinsicsPrior};
use crate::core::pose::{Correspondences, PoseError};
use crate::core::verify::PoseHypothesis;

/// Step "solve": what becomes of one coarse view: its refined pose, or why there is none.
pub fn solve_view(
    correspondences: &ViewCorrespondences,
    camera: &Camera,
    intrinsics: IntrinsicsMode,
    config: &RegistrationConfig,
    seed: u64,
) -> CoarseOutcome {
    CoarseOutcome {
        coarse_index: correspondences.coarse_index,
        consistent_matches: correspondences.image_points_px.len(),
        hypothesis: solve_pose(correspondences, camera, intrinsics, config, seed)
            .map_err(|error| error.to_string()),
    }
}

/// RANSAC (EPnP or DLT) and refinement on one coarse view's correspondences.
fn solve_pose(
    correspondences: &ViewCorrespondences,
    camera: &Camera,
    intrinsics: IntrinsicsMode,
    config: &RegistrationConfig,
    seed: u64,
) -> Result<PoseHypothesis, PoseError> {
    let count = correspondences.image_points_px.len();
    if count < config.min_correspondences_per_pose {
        return Err(PoseError::TooFewPoints {
            solver: "consistent correspondences of a coarse pose",
            needed: config.min_correspondences_per_pose,
            got: count,
        });
    }
    // An even subsample keeps RANSAC's cost bounded without favouring any image region.
    let step = count.div_ceil(config.max_correspondences_per_pose).max(1);
    let image_points: Vec<Vector2<f64>> = correspondences
        .image_points_px
        .iter()
        .step_by(step)
        .copied()
        .collect();
    let world_points: Vec<Vector3<f64>> = correspondences
        .world_points_m
        .iter()
        .step_by(step)
        .copied()
        .collect();
    let data = Correspondences::new(&image_points, &world_points)?;
    let prior = match intrinsics {
        IntrinsicsMode::Known => IntrinsicsPrior::Known(camera.intrinsics),
        IntrinsicsMode::Unknown => match config.unknown_intrinsics {
            UnknownIntrinsics::Dlt => IntrinsicsPrior::Unknown {
                planar_fallback: Some(camera.intrinsics),
            },
            UnknownIntrinsics::Focal => IntrinsicsPrior::UnknownFocal {
                prior: FocalPrior::centred(
                    &camera.intrinsics,
                    Vector2::new(
                        0.5 * f64::from(camera.width_px),
                        0.5 * f64::from(camera.height_px),
                    ),
                ),
                planar_fallback: Some(camera.intrinsics),
            },
        },
    };
    let mut rng = frame_rng(seed, 100 + correspondences.coarse_index as u64);
    let estimate = estimate_pose(&data, &prior, &config.pose, &mut rng)?;
    let refined_camera = Camera {
        intrinsics: estimate.camera.intrinsics,
        ..Camera::pinhole(
            camera.width_px,
            camera.height_px,
            estimate.camera.intrinsics,
        )
    };
    let hypothesis = PoseHypothesis {
        camera: refined_camera,
        cam_from_world: estimate.camera.cam_from_world,
        consensus: estimate.inlier_count,
        inlier_rms_px: estimate.inlier_rms_px,
        correspondence_count: data.len(),
        coarse_cam_from_world: correspondences.coarse_cam_from_world,
    };
    Ok(hypothesis)
}
