//! EPnP with an unknown focal length: the pose and one focal length from ≥ 6 correspondences when
//! the principal point is known (the image centre), the pixels square up to a known aspect ratio
//! and there is no skew — what a drone's EXIF gives (issue #11 item 6, `--intrinsics focal`).
//!
//! Reference: A. Penate-Sanchez, J. Andrade-Cetto, F. Moreno-Noguer, "Exhaustive Linearization
//! for Robust Camera Pose and Focal Length Estimation", IEEE TPAMI 35(10), 2013 (UPnP), its
//! `N = 1` case. As in EPnP (Lepetit et al. 2009, [`super::epnp`]) every world point is a
//! barycentric combination of four control points; with the image coordinates taken relative to
//! the principal point and divided by a nominal focal length `f₀` only, the unknowns of EPnP's
//! linear system `M x = 0` become `(g·xⱼ, g·yⱼ, zⱼ)` of each control point, with `g = f / f₀`.
//! Its kernel vector `v` (the eigenvector of `MᵀM` with the smallest eigenvalue; one-dimensional
//! for ≥ 6 points in general position) holds them up to a scale `β`. The preserved distances
//! between control points, `β²/g² (Δvₓ² + Δv_y²) + β² Δv_z² = ‖Δcʷ‖²` for the six pairs, are
//! linear in `β²/g²` and `β²`: least squares gives both, hence `g`, `β`, the control points in
//! the camera frame, and the pose by absolute orientation (Umeyama).
//!
//! Preconditions: ≥ [`EPNPF_MIN_POINTS`] finite correspondences; 3-D points with relief (planarity
//! ratio at least [`super::epnp::EPNP_PLANAR_RATIO`]; a plane does not fix the fourth control
//! point) and not collinear: [`PoseError::Degenerate`] otherwise. The solution is linear and
//! noise-sensitive; the caller refines pose and focal length on the inliers (Levenberg–Marquardt,
//! [`super::refine::RefinedParameters::FocalAndPose`]).

use nalgebra::{Matrix2, SymmetricEigen, Vector2, Vector3};

use super::epnp::{control_points, normal_matrix, rigid_from_point_pairs, EPNP_PLANAR_RATIO};
use super::planarity::point_cloud_shape;
use super::{check_solver_input, exceeds, CameraPose, PoseError};
use crate::core::camera::PinholeIntrinsics;

/// Correspondences the solver needs (12 unknowns up to scale: 2 equations per point, ≥ 11).
pub const EPNPF_MIN_POINTS: usize = 6;

/// What is known of the camera: everything but the focal length.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FocalPrior {
    /// Principal point, px.
    pub principal_point_px: Vector2<f64>,
    /// `fy / fx` (1 for square pixels).
    pub aspect_ratio: f64,
    /// A focal length of the right order (e.g. from EXIF), px: it only conditions the system.
    pub nominal_focal_px: f64,
}

impl FocalPrior {
    /// The prior of a camera's nominal intrinsics with the principal point moved to `centre_px`.
    pub fn centred(nominal: &PinholeIntrinsics, centre_px: Vector2<f64>) -> Self {
        Self {
            principal_point_px: centre_px,
            aspect_ratio: nominal.fy_px / nominal.fx_px,
            nominal_focal_px: nominal.fx_px,
        }
    }

    /// The intrinsics with focal length `fx_px` (skew 0).
    pub fn intrinsics(&self, fx_px: f64) -> PinholeIntrinsics {
        PinholeIntrinsics {
            fx_px,
            fy_px: fx_px * self.aspect_ratio,
            cx_px: self.principal_point_px.x,
            cy_px: self.principal_point_px.y,
            skew_px: 0.0,
        }
    }

    pub fn validate(&self) -> Result<(), PoseError> {
        let finite = self.principal_point_px.iter().all(|v| v.is_finite());
        if !(finite
            && self.aspect_ratio.is_finite()
            && self.aspect_ratio > 0.0
            && self.nominal_focal_px.is_finite()
            && self.nominal_focal_px > 0.0)
        {
            return Err(PoseError::InvalidConfig {
                field: "focal prior",
                why: "principal point, aspect ratio and nominal focal length must be finite, the last two positive",
            });
        }
        Ok(())
    }
}

/// The camera (focal length and `cam_from_world`) from ≥ 6 correspondences.
pub fn solve(
    prior: &FocalPrior,
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
) -> Result<CameraPose, PoseError> {
    check_solver_input(
        "EPnP with unknown focal length",
        EPNPF_MIN_POINTS,
        image_points_px,
        world_points,
    )?;
    prior.validate()?;
    let shape = point_cloud_shape(world_points)?;
    if !exceeds(shape.collinearity_ratio, 1e-6) {
        return Err(PoseError::Degenerate {
            why: "the world points are collinear",
        });
    }
    if shape.planarity_ratio < EPNP_PLANAR_RATIO {
        return Err(PoseError::Degenerate {
            why: "the world points are planar: the focal length solver needs relief",
        });
    }
    let (world_controls, alphas) = control_points(&shape, 4, world_points);
    let f0 = prior.nominal_focal_px;
    let scaled: Vec<Vector2<f64>> = image_points_px
        .iter()
        .map(|p| {
            let centred = p - prior.principal_point_px;
            Vector2::new(centred.x / f0, centred.y / (f0 * prior.aspect_ratio))
        })
        .collect();
    let eigen = SymmetricEigen::try_new(normal_matrix(&alphas, &scaled, 4), f64::EPSILON, 1000)
        .ok_or(PoseError::Degenerate {
            why: "the focal-length EPnP system did not diagonalise",
        })?;
    let smallest = (0..12)
        .min_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]))
        .ok_or(PoseError::Degenerate {
            why: "empty focal-length EPnP system",
        })?;
    let kernel = eigen.eigenvectors.column(smallest).into_owned();
    let control = |j: usize| Vector3::new(kernel[3 * j], kernel[3 * j + 1], kernel[3 * j + 2]);
    // Least squares on [Δvₓ² + Δv_y², Δv_z²] · [β²/g², β²]ᵀ = ‖Δcʷ‖² over the six pairs.
    let mut normal = Matrix2::zeros();
    let mut right = Vector2::zeros();
    for a in 0..4 {
        for b in a + 1..4 {
            let difference = control(a) - control(b);
            let row = Vector2::new(
                difference.x * difference.x + difference.y * difference.y,
                difference.z * difference.z,
            );
            let distance_sq = (world_controls[a] - world_controls[b]).norm_squared();
            normal += row * row.transpose();
            right += row * distance_sq;
        }
    }
    let solution =
        normal
            .try_inverse()
            .map(|inverse| inverse * right)
            .ok_or(PoseError::Degenerate {
                why: "the control-point distances do not fix the focal length",
            })?;
    let (beta_sq_over_g_sq, beta_sq) = (solution.x, solution.y);
    if !(exceeds(beta_sq_over_g_sq, 0.0) && exceeds(beta_sq, 0.0)) {
        return Err(PoseError::Degenerate {
            why: "no positive focal length fits the control-point distances",
        });
    }
    let g = (beta_sq / beta_sq_over_g_sq).sqrt();
    let beta = beta_sq.sqrt();
    let camera_controls: Vec<Vector3<f64>> = (0..4)
        .map(|j| {
            let v = control(j);
            Vector3::new(v.x / g, v.y / g, v.z) * beta
        })
        .collect();
    let mut camera_points: Vec<Vector3<f64>> = alphas
        .iter()
        .map(|alpha| (0..4).map(|j| camera_controls[j] * alpha[j]).sum())
        .collect();
    if camera_points.iter().map(|p| p.z).sum::<f64>() < 0.0 {
        camera_points.iter_mut().for_each(|p| *p = -*p);
    }
    let cam_from_world =
        rigid_from_point_pairs(world_points, &camera_points).ok_or(PoseError::Degenerate {
            why: "no rigid transform maps the world points onto the camera-frame points",
        })?;
    let camera = CameraPose {
        intrinsics: prior.intrinsics(g * f0),
        cam_from_world,
    };
    if !camera.is_finite() {
        return Err(PoseError::Degenerate {
            why: "the focal-length EPnP camera is not finite",
        });
    }
    Ok(camera)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::pose::refine::{refine_camera, RefineConfig, RefinedParameters};
    use crate::core::pose::test_scenes::{corrupt, random_scene, rotation_error_deg};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn square_intrinsics(focal_px: f64) -> PinholeIntrinsics {
        PinholeIntrinsics {
            fx_px: focal_px,
            fy_px: focal_px,
            cx_px: 320.0,
            cy_px: 240.0,
            skew_px: 0.0,
        }
    }

    fn prior(nominal_focal_px: f64) -> FocalPrior {
        FocalPrior {
            principal_point_px: Vector2::new(320.0, 240.0),
            aspect_ratio: 1.0,
            nominal_focal_px,
        }
    }

    #[test]
    fn recovers_a_known_pose_and_focal_length_from_exact_points() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for (trial, true_focal_px) in [450.0, 800.0, 1500.0, 2400.0].into_iter().enumerate() {
            for count in [6, 7, 50] {
                let scene = random_scene(&mut rng, square_intrinsics(true_focal_px), count, 12.0);
                // The nominal focal length is 30 % off: it only conditions the system.
                let camera = solve(
                    &prior(true_focal_px * 1.3),
                    &scene.image_points_px,
                    &scene.world_points,
                )
                .unwrap_or_else(|e| panic!("trial {trial}, {count} points: {e}"));
                let focal_error = (camera.intrinsics.fx_px - true_focal_px).abs() / true_focal_px;
                let rotation_error =
                    rotation_error_deg(&camera.cam_from_world, &scene.camera.cam_from_world);
                let centre_error_m = (camera.cam_from_world.camera_center()
                    - scene.camera.cam_from_world.camera_center())
                .norm();
                assert!(
                    focal_error < 1e-6 && rotation_error < 1e-5 && centre_error_m < 1e-4,
                    "f {true_focal_px}, {count} points: focal {focal_error:.2e}, rotation {rotation_error:.2e}°, centre {centre_error_m:.2e} m"
                );
            }
        }
    }

    #[test]
    fn noisy_points_then_refinement_recover_pose_and_focal() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let true_focal_px = 900.0;
        let mut scene = random_scene(&mut rng, square_intrinsics(true_focal_px), 200, 12.0);
        corrupt(&mut scene, &mut rng, 0.5, 0);
        let start = solve(&prior(700.0), &scene.image_points_px, &scene.world_points).unwrap();
        let (refined, summary) = refine_camera(
            &start,
            &scene.image_points_px,
            &scene.world_points,
            RefinedParameters::FocalAndPose,
            &RefineConfig::default(),
        )
        .unwrap();
        let focal_error = (refined.intrinsics.fx_px - true_focal_px).abs() / true_focal_px;
        let rotation_error =
            rotation_error_deg(&refined.cam_from_world, &scene.camera.cam_from_world);
        assert_eq!(refined.intrinsics.fx_px, refined.intrinsics.fy_px);
        assert_eq!(refined.intrinsics.cx_px, 320.0);
        assert!(
            focal_error < 0.01 && rotation_error < 0.05 && summary.final_rms_px < 0.75,
            "start focal {:.1} px; refined: focal error {focal_error:.4}, rotation {rotation_error:.4}°, rms {:.3} px",
            start.intrinsics.fx_px,
            summary.final_rms_px
        );
    }

    #[test]
    fn planar_and_too_few_points_are_refused() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let planar = random_scene(&mut rng, square_intrinsics(800.0), 30, 0.0);
        assert!(matches!(
            solve(&prior(800.0), &planar.image_points_px, &planar.world_points),
            Err(PoseError::Degenerate { .. })
        ));
        let scene = random_scene(&mut rng, square_intrinsics(800.0), 5, 12.0);
        assert!(matches!(
            solve(&prior(800.0), &scene.image_points_px, &scene.world_points),
            Err(PoseError::TooFewPoints { .. })
        ));
    }
}
