//! Levenberg–Marquardt refinement of a camera on its inliers (docs/design.md §2 step 6, "refine on the
//! inliers"): the minimal solvers fit 4–6 points exactly, so the consensus set's information is
//! only used once the reprojection error over all inliers is minimised.
//!
//! Method: K. Levenberg (1944), D. Marquardt (1963), with Marquardt's diagonal scaling
//! (`(JᵀJ + λ diag JᵀJ) δ = −Jᵀr`), as in Hartley & Zisserman 2003, Appendix A6.2. The residuals
//! are the pixel differences between projected world points and image points; the Jacobian is
//! analytic. The rotation is updated by an axis-angle increment about the camera centre
//! (`R ← exp([ω]×) R`, `t ← exp([ω]×) t + δt`), so the parameterisation has no singularity.
//!
//! Preconditions: every given point is in front of the start camera (inliers are), at least 3
//! points for the pose alone, 4 with the focal length and 5 with the intrinsics, finite input. Steps that raise the cost,
//! put a point behind the camera or make a focal length non-positive are rejected (the damping
//! grows), so a bad start never gets worse. Skew is kept at its starting value (0 for a physical
//! camera, the DLT's value otherwise); distortion is not modelled.

use nalgebra::{DMatrix, DVector, Rotation3, UnitQuaternion, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::{check_correspondences, CameraPose, PoseError};
use crate::core::camera::MIN_DEPTH_M;
use crate::core::rigid::Rigid3;

/// Settings of the Levenberg–Marquardt refinement.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RefineConfig {
    /// Most trial steps (accepted or rejected) before giving up; 0 disables refinement.
    pub max_iterations: usize,
    /// Starting damping λ, relative to the diagonal of `JᵀJ` (dimensionless, > 0).
    pub initial_damping: f64,
    /// Stop when an accepted step lowers the sum of squared errors by less than this fraction.
    pub cost_tolerance: f64,
    /// Stop when the step is shorter than this fraction of the parameters' size.
    pub step_tolerance: f64,
}

impl Default for RefineConfig {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            initial_damping: 1e-3,
            cost_tolerance: 1e-10,
            step_tolerance: 1e-12,
        }
    }
}

impl RefineConfig {
    pub fn validate(&self) -> Result<(), PoseError> {
        if !(self.initial_damping.is_finite() && self.initial_damping > 0.0) {
            return Err(PoseError::InvalidConfig {
                field: "refinement.initial_damping",
                why: "must be a positive number",
            });
        }
        for (field, value) in [
            ("refinement.cost_tolerance", self.cost_tolerance),
            ("refinement.step_tolerance", self.step_tolerance),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(PoseError::InvalidConfig {
                    field,
                    why: "must be a non-negative number",
                });
            }
        }
        Ok(())
    }
}

/// What the refinement may change.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum RefinedParameters {
    /// Rotation and translation (6 DoF): known intrinsics.
    Pose,
    /// `fx, fy, cx, cy` and the pose (10 DoF); skew stays as it is.
    IntrinsicsAndPose,
    /// One focal length (`fx` and `fy` change together, keeping `fy / fx`) and the pose
    /// (7 DoF); principal point and skew stay as they are.
    FocalAndPose,
}

impl RefinedParameters {
    fn dimension(self) -> usize {
        match self {
            RefinedParameters::Pose => 6,
            RefinedParameters::IntrinsicsAndPose => 10,
            RefinedParameters::FocalAndPose => 7,
        }
    }
}

/// Why the refinement stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum RefineStop {
    /// An accepted step changed the cost by less than `cost_tolerance`.
    CostConverged,
    /// The step became shorter than `step_tolerance`.
    StepConverged,
    /// The residuals are (numerically) zero.
    ZeroCost,
    /// No step lowers the cost any more (damping at its limit).
    DampingLimit,
    /// `max_iterations` trial steps were taken.
    MaxIterations,
}

/// What the refinement did.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RefinementSummary {
    /// RMS pixel distance over the points at the start.
    pub initial_rms_px: f64,
    /// RMS pixel distance over the points at the end (never above `initial_rms_px`).
    pub final_rms_px: f64,
    /// Trial steps taken.
    pub iterations: usize,
    /// Trial steps that lowered the cost and were kept.
    pub accepted_steps: usize,
    pub stop: RefineStop,
}

const MAX_DAMPING: f64 = 1e12;

/// Minimises the reprojection error of `camera` over the given correspondences.
pub fn refine_camera(
    camera: &CameraPose,
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
    parameters: RefinedParameters,
    config: &RefineConfig,
) -> Result<(CameraPose, RefinementSummary), PoseError> {
    config.validate()?;
    check_correspondences(image_points_px, world_points)?;
    let needed = parameters.dimension().div_ceil(2);
    if image_points_px.len() < needed {
        return Err(PoseError::TooFewPoints {
            solver: "Levenberg-Marquardt refinement",
            needed,
            got: image_points_px.len(),
        });
    }
    if !camera.is_finite() {
        return Err(PoseError::Degenerate {
            why: "the start camera is not finite or has non-positive focal lengths",
        });
    }
    let count = image_points_px.len() as f64;
    let mut current = *camera;
    let mut cost = squared_error_sum(&current, image_points_px, world_points).ok_or(
        PoseError::Degenerate {
            why: "a point is behind the start camera",
        },
    )?;
    let initial_rms_px = (cost / count).sqrt();
    let dimension = parameters.dimension();
    let mut damping = config.initial_damping;
    let mut accepted_steps = 0;
    let mut iterations = 0;
    let mut stop = RefineStop::MaxIterations;
    let mut normal_matrix = DMatrix::<f64>::zeros(dimension, dimension);
    let mut gradient = DVector::<f64>::zeros(dimension);
    let mut linearisation_stale = true;

    while iterations < config.max_iterations {
        if cost <= f64::MIN_POSITIVE {
            stop = RefineStop::ZeroCost;
            break;
        }
        if linearisation_stale {
            linearise(
                &current,
                image_points_px,
                world_points,
                parameters,
                &mut normal_matrix,
                &mut gradient,
            );
            linearisation_stale = false;
        }
        iterations += 1;
        let mut damped = normal_matrix.clone();
        for i in 0..dimension {
            damped[(i, i)] += damping * normal_matrix[(i, i)].max(1e-12);
        }
        let step = damped.cholesky().map(|c| c.solve(&(-&gradient)));
        let Some(step) = step.filter(|s| s.iter().all(|v| v.is_finite())) else {
            damping *= 10.0;
            if damping > MAX_DAMPING {
                stop = RefineStop::DampingLimit;
                break;
            }
            continue;
        };
        let candidate = apply_step(&current, &step, parameters);
        let candidate_cost = candidate
            .filter(|c| c.intrinsics.fx_px > 0.0 && c.intrinsics.fy_px > 0.0)
            .and_then(|c| squared_error_sum(&c, image_points_px, world_points).map(|e| (c, e)));
        match candidate_cost {
            Some((candidate, candidate_cost)) if candidate_cost < cost => {
                let relative_decrease = (cost - candidate_cost) / cost;
                current = candidate;
                cost = candidate_cost;
                accepted_steps += 1;
                linearisation_stale = true;
                damping = (damping / 10.0).max(1e-15);
                if relative_decrease < config.cost_tolerance {
                    stop = RefineStop::CostConverged;
                    break;
                }
                if step.norm() < config.step_tolerance * (parameter_scale(&current) + 1.0) {
                    stop = RefineStop::StepConverged;
                    break;
                }
            }
            _ => {
                damping *= 10.0;
                if damping > MAX_DAMPING {
                    stop = RefineStop::DampingLimit;
                    break;
                }
            }
        }
    }
    Ok((
        current,
        RefinementSummary {
            initial_rms_px,
            final_rms_px: (cost / count).sqrt(),
            iterations,
            accepted_steps,
            stop,
        },
    ))
}

/// Size of the translation and intrinsics, for the relative step test.
fn parameter_scale(camera: &CameraPose) -> f64 {
    let k = &camera.intrinsics;
    (camera.cam_from_world.translation.norm_squared()
        + k.fx_px * k.fx_px
        + k.fy_px * k.fy_px
        + k.cx_px * k.cx_px
        + k.cy_px * k.cy_px)
        .sqrt()
}

/// Sum of squared pixel distances; `None` when a point is not in front of the camera.
fn squared_error_sum(
    camera: &CameraPose,
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
) -> Option<f64> {
    let projection = camera.projection_matrix();
    image_points_px
        .iter()
        .zip(world_points)
        .try_fold(0.0, |sum, (image_point, world_point)| {
            super::project_with_matrix(&projection, world_point)
                .map(|projected| sum + (projected - image_point).norm_squared())
        })
        .filter(|sum| sum.is_finite())
}

/// Accumulates `JᵀJ` and `Jᵀr` at `camera` (points behind the camera are skipped; the cost check
/// keeps them from occurring at accepted cameras).
fn linearise(
    camera: &CameraPose,
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
    parameters: RefinedParameters,
    normal_matrix: &mut DMatrix<f64>,
    gradient: &mut DVector<f64>,
) {
    let dimension = parameters.dimension();
    normal_matrix.fill(0.0);
    gradient.fill(0.0);
    let rotation = camera.cam_from_world.rotation_matrix();
    let translation = camera.cam_from_world.translation;
    let k = &camera.intrinsics;
    let mut row_u = [0.0; 10];
    let mut row_v = [0.0; 10];
    for (image_point, world_point) in image_points_px.iter().zip(world_points) {
        let point_cam = rotation * world_point + translation;
        if point_cam.z <= MIN_DEPTH_M {
            continue;
        }
        let inverse_depth = 1.0 / point_cam.z;
        let x = point_cam.x * inverse_depth;
        let y = point_cam.y * inverse_depth;
        let residual_u = k.fx_px * x + k.skew_px * y + k.cx_px - image_point.x;
        let residual_v = k.fy_px * y + k.cy_px - image_point.y;
        // d(u, v) / d(point_cam).
        let du = Vector3::new(
            k.fx_px * inverse_depth,
            k.skew_px * inverse_depth,
            -(k.fx_px * x + k.skew_px * y) * inverse_depth,
        );
        let dv = Vector3::new(0.0, k.fy_px * inverse_depth, -k.fy_px * y * inverse_depth);
        // point_cam' = exp([ω]×) point_cam + δt: d/dωⱼ = eⱼ × point_cam, d/dδt = I.
        for axis in 0..3 {
            let derivative = Vector3::ith(axis, 1.0).cross(&point_cam);
            row_u[axis] = du.dot(&derivative);
            row_v[axis] = dv.dot(&derivative);
            row_u[3 + axis] = du[axis];
            row_v[3 + axis] = dv[axis];
        }
        match parameters {
            RefinedParameters::Pose => {}
            RefinedParameters::IntrinsicsAndPose => {
                // fx, fy, cx, cy.
                row_u[6..10].copy_from_slice(&[x, 0.0, 1.0, 0.0]);
                row_v[6..10].copy_from_slice(&[0.0, y, 0.0, 1.0]);
            }
            RefinedParameters::FocalAndPose => {
                // f = fx, with fy = f · (fy / fx) and skew fixed.
                row_u[6] = x;
                row_v[6] = y * k.fy_px / k.fx_px;
            }
        }
        for a in 0..dimension {
            gradient[a] += row_u[a] * residual_u + row_v[a] * residual_v;
            for b in a..dimension {
                normal_matrix[(a, b)] += row_u[a] * row_u[b] + row_v[a] * row_v[b];
            }
        }
    }
    for a in 0..dimension {
        for b in 0..a {
            normal_matrix[(a, b)] = normal_matrix[(b, a)];
        }
    }
}

/// The camera after a parameter step; `None` if it is not finite.
fn apply_step(
    camera: &CameraPose,
    step: &DVector<f64>,
    parameters: RefinedParameters,
) -> Option<CameraPose> {
    let rotation_step = UnitQuaternion::from_rotation_matrix(&Rotation3::new(Vector3::new(
        step[0], step[1], step[2],
    )));
    let pose = &camera.cam_from_world;
    let cam_from_world = Rigid3::new(
        rotation_step * pose.rotation,
        rotation_step * pose.translation + Vector3::new(step[3], step[4], step[5]),
    );
    let mut intrinsics = camera.intrinsics;
    match parameters {
        RefinedParameters::Pose => {}
        RefinedParameters::IntrinsicsAndPose => {
            intrinsics.fx_px += step[6];
            intrinsics.fy_px += step[7];
            intrinsics.cx_px += step[8];
            intrinsics.cy_px += step[9];
        }
        RefinedParameters::FocalAndPose => {
            let aspect = intrinsics.fy_px / intrinsics.fx_px;
            intrinsics.fx_px += step[6];
            intrinsics.fy_px = intrinsics.fx_px * aspect;
        }
    }
    let refined = CameraPose {
        intrinsics,
        cam_from_world,
    };
    refined.cam_from_world.is_finite().then_some(refined)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::pose::test_scenes::{
        corrupt, random_scene, rotation_error_deg, test_intrinsics,
    };
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn perturbed(
        camera: &CameraPose,
        angle_rad: f64,
        shift_m: f64,
        focal_factor: f64,
    ) -> CameraPose {
        let rotation =
            UnitQuaternion::from_scaled_axis(Vector3::new(angle_rad, -angle_rad, 0.5 * angle_rad));
        CameraPose {
            intrinsics: crate::core::camera::PinholeIntrinsics {
                fx_px: camera.intrinsics.fx_px * focal_factor,
                fy_px: camera.intrinsics.fy_px * focal_factor,
                cx_px: camera.intrinsics.cx_px + 8.0,
                cy_px: camera.intrinsics.cy_px - 5.0,
                ..camera.intrinsics
            },
            cam_from_world: Rigid3::new(
                rotation * camera.cam_from_world.rotation,
                camera.cam_from_world.translation + Vector3::new(shift_m, -shift_m, 0.5 * shift_m),
            ),
        }
    }

    #[test]
    fn pose_refinement_converges_to_the_truth_on_exact_data() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let scene = random_scene(&mut rng, test_intrinsics(), 100, 15.0);
        let mut start = perturbed(&scene.camera, 0.02, 1.0, 1.0);
        start.intrinsics = scene.camera.intrinsics;
        let (refined, summary) = refine_camera(
            &start,
            &scene.image_points_px,
            &scene.world_points,
            RefinedParameters::Pose,
            &RefineConfig::default(),
        )
        .unwrap();
        assert!(summary.initial_rms_px > 10.0, "{summary:?}");
        assert!(summary.final_rms_px < 1e-6, "{summary:?}");
        assert!(rotation_error_deg(&refined.cam_from_world, &scene.camera.cam_from_world) < 1e-7);
        assert!(
            (refined.cam_from_world.translation - scene.camera.cam_from_world.translation).norm()
                < 1e-6
        );
    }

    #[test]
    fn intrinsics_and_pose_refinement_reaches_the_noise_floor() {
        let sigma_px = 0.5;
        for seed in 0..3 {
            let mut rng = ChaCha8Rng::seed_from_u64(30 + seed);
            let mut scene = random_scene(&mut rng, test_intrinsics(), 400, 15.0);
            let truth = scene.camera;
            corrupt(&mut scene, &mut rng, sigma_px, 0);
            let start = perturbed(&truth, 0.03, 1.5, 1.1);
            let (refined, summary) = refine_camera(
                &start,
                &scene.image_points_px,
                &scene.world_points,
                RefinedParameters::IntrinsicsAndPose,
                &RefineConfig::default(),
            )
            .unwrap();
            // Noise floor: RMS of a 2D Gaussian with σ per axis is σ√2, less the fitted DoF.
            let floor_px = sigma_px * 2f64.sqrt();
            assert!(summary.initial_rms_px > 20.0, "{summary:?}");
            assert!(summary.final_rms_px < 1.05 * floor_px, "{summary:?}");
            assert!(summary.final_rms_px > 0.85 * floor_px, "{summary:?}");
            let truth_rms = crate::core::pose::reprojection_rms_px(
                &truth,
                &scene.image_points_px,
                &scene.world_points,
            )
            .unwrap();
            assert!(
                summary.final_rms_px <= truth_rms,
                "the optimum is at least as good as the truth"
            );
            assert!(
                (refined.intrinsics.fx_px - truth.intrinsics.fx_px).abs()
                    < 0.02 * truth.intrinsics.fx_px
            );
            assert!(rotation_error_deg(&refined.cam_from_world, &truth.cam_from_world) < 0.5);
        }
    }

    #[test]
    fn a_hopeless_start_never_gets_worse_and_bad_input_is_rejected() {
        let mut rng = ChaCha8Rng::seed_from_u64(40);
        let scene = random_scene(&mut rng, test_intrinsics(), 50, 15.0);
        let start = perturbed(&scene.camera, 0.3, 10.0, 0.5);
        let (_, summary) = refine_camera(
            &start,
            &scene.image_points_px,
            &scene.world_points,
            RefinedParameters::IntrinsicsAndPose,
            &RefineConfig {
                max_iterations: 5,
                ..RefineConfig::default()
            },
        )
        .unwrap();
        assert!(summary.final_rms_px <= summary.initial_rms_px);
        assert_eq!(summary.iterations, 5);

        // Turned half around the camera's x axis: every point ends up behind it.
        let half_turn = Rigid3::new(
            UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.0),
            Vector3::zeros(),
        );
        let behind = CameraPose {
            cam_from_world: half_turn.compose(&scene.camera.cam_from_world),
            ..scene.camera
        };
        assert!(refine_camera(
            &behind,
            &scene.image_points_px,
            &scene.world_points,
            RefinedParameters::Pose,
            &RefineConfig::default()
        )
        .is_err());
        let mut nan_points = scene.world_points.clone();
        nan_points[3].x = f64::NAN;
        assert_eq!(
            refine_camera(
                &scene.camera,
                &scene.image_points_px,
                &nan_points,
                RefinedParameters::Pose,
                &RefineConfig::default()
            )
            .unwrap_err(),
            PoseError::NonFinite { index: 3 }
        );
        assert!(matches!(
            refine_camera(
                &scene.camera,
                &scene.image_points_px[..4],
                &scene.world_points[..4],
                RefinedParameters::IntrinsicsAndPose,
                &RefineConfig::default()
            ),
            Err(PoseError::TooFewPoints { needed: 5, .. })
        ));
        let bad_config = RefineConfig {
            initial_damping: -1.0,
            ..RefineConfig::default()
        };
        assert!(matches!(
            refine_camera(
                &scene.camera,
                &scene.image_points_px,
                &scene.world_points,
                RefinedParameters::Pose,
                &bad_config
            ),
            Err(PoseError::InvalidConfig { .. })
        ));
    }

    #[test]
    fn unknown_config_fields_are_rejected() {
        assert!(
            serde_json::from_str::<RefineConfig>(r#"{"max_iterations": 3, "lambda": 1}"#).is_err()
        );
        let parsed: RefineConfig = serde_json::from_str(r#"{"max_iterations": 3}"#).unwrap();
        assert_eq!(
            parsed,
            RefineConfig {
                max_iterations: 3,
                ..RefineConfig::default()
            }
        );
    }
}
