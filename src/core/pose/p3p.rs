//! P3P: the camera poses (up to four) that put three world points on three image rays — a minimal
//! alternative to EPnP inside RANSAC for known intrinsics (a sample of 4: three to solve, one to
//! choose among the solutions).
//!
//! Reference: J. A. Grunert, "Das Pothenotische Problem in erweiterter Gestalt nebst über seine
//! Anwendungen in der Geodäsie", Grunerts Archiv für Mathematik und Physik 1, 1841, in the notation
//! and with the quartic of R. Haralick, C. Lee, K. Ottenberg, M. Nölle, "Review and Analysis of
//! Solutions of the Three Point Perspective Pose Estimation Problem", IJCV 13(3), 1994, §2.1.
//! With `s₁, s₂, s₃` the distances of the points along their unit rays, the law of cosines gives
//! three equations; `s₂ = u s₁`, `s₃ = v s₁` turn them into a quartic in `v`. Its real roots
//! (companion-matrix eigenvalues, polished by Newton) give `u`, `s₁`, the camera-frame points, and
//! the pose by absolute orientation.
//!
//! Preconditions: known intrinsics, undistorted pixels, exactly three finite correspondences (the
//! others are ignored by [`solve`]; [`solve_with_check`] uses a fourth to pick one solution), world
//! points not collinear, rays distinct. Grunert's elimination loses accuracy when the roots
//! nearly coincide (the "danger cylinder"); RANSAC's consensus absorbs that.

use nalgebra::{Matrix4, Schur, Vector2, Vector3};

use super::epnp::rigid_from_point_pairs;
use super::{check_solver_input, exceeds, CameraPose, PoseError};
use crate::core::camera::PinholeIntrinsics;
use crate::core::rigid::Rigid3;

/// All poses (0 to 4) consistent with the first three correspondences.
pub fn solve(
    intrinsics: &PinholeIntrinsics,
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
) -> Result<Vec<Rigid3>, PoseError> {
    check_solver_input("P3P", 3, image_points_px, world_points)?;
    intrinsics.validate()?;
    let rays: Vec<Vector3<f64>> = image_points_px[..3]
        .iter()
        .map(|p| {
            let normalized = intrinsics.pixel_to_normalized(*p);
            Vector3::new(normalized.x, normalized.y, 1.0).normalize()
        })
        .collect();
    let points = &world_points[..3];
    let a2 = (points[1] - points[2]).norm_squared();
    let b2 = (points[0] - points[2]).norm_squared();
    let c2 = (points[0] - points[1]).norm_squared();
    let cross = (points[1] - points[0])
        .cross(&(points[2] - points[0]))
        .norm();
    if !exceeds(cross, 1e-12 * (a2 + b2 + c2)) {
        return Err(PoseError::Degenerate {
            why: "the three world points are collinear",
        });
    }
    let cos_alpha = rays[1].dot(&rays[2]);
    let cos_beta = rays[0].dot(&rays[2]);
    let cos_gamma = rays[0].dot(&rays[1]);
    if [cos_alpha, cos_beta, cos_gamma]
        .iter()
        .any(|c| !exceeds(1.0 - c.abs(), 1e-12))
    {
        return Err(PoseError::Degenerate {
            why: "two image rays coincide",
        });
    }

    // Haralick et al. 1994, eq. (8)-(9), with p = (a² − c²)/b².
    let p = (a2 - c2) / b2;
    let q = (a2 + c2) / b2;
    let (ca, cb, cg) = (cos_alpha, cos_beta, cos_gamma);
    let coefficients = [
        // v⁰ … v⁴
        (1.0 + p).powi(2) - 4.0 * a2 / b2 * cg * cg,
        4.0 * (-p * (1.0 + p) * cb + 2.0 * a2 / b2 * cg * cg * cb - (1.0 - q) * ca * cg),
        2.0 * (p * p - 1.0 + 2.0 * p * p * cb * cb + 2.0 * (b2 - c2) / b2 * ca * ca
            - 4.0 * q * ca * cb * cg
            + 2.0 * (b2 - a2) / b2 * cg * cg),
        4.0 * (p * (1.0 - p) * cb - (1.0 - q) * ca * cg + 2.0 * c2 / b2 * ca * ca * cb),
        (p - 1.0).powi(2) - 4.0 * c2 / b2 * ca * ca,
    ];
    let mut poses = Vec::with_capacity(4);
    for v in real_quartic_roots(&coefficients) {
        let denominator = 2.0 * (cg - v * ca);
        if !exceeds(denominator.abs(), 1e-12) {
            continue;
        }
        let u = ((p - 1.0) * v * v - 2.0 * p * cb * v + 1.0 + p) / denominator;
        let s1_squared = b2 / (1.0 + v * v - 2.0 * v * cb);
        if !(u > 0.0 && v > 0.0 && s1_squared > 0.0 && s1_squared.is_finite()) {
            continue;
        }
        let s1 = s1_squared.sqrt();
        let camera_points = [rays[0] * s1, rays[1] * (u * s1), rays[2] * (v * s1)];
        if let Some(pose) = rigid_from_point_pairs(points, &camera_points) {
            poses.push(pose);
        }
    }
    Ok(poses)
}

/// Solves on the first three correspondences and keeps the solution that reprojects the others
/// (at least one more) best.
pub fn solve_with_check(
    intrinsics: &PinholeIntrinsics,
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
) -> Result<Rigid3, PoseError> {
    check_solver_input("P3P with a check point", 4, image_points_px, world_points)?;
    solve(intrinsics, image_points_px, world_points)?
        .into_iter()
        .filter_map(|pose| {
            let camera = CameraPose {
                intrinsics: *intrinsics,
                cam_from_world: pose,
            };
            super::reprojection_rms_px(&camera, &image_points_px[3..], &world_points[3..])
                .map(|error| (error, pose))
        })
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, pose)| pose)
        .ok_or(PoseError::Degenerate {
            why: "no P3P solution puts the check points in front of the camera",
        })
}

/// Real roots of `Σ cᵢ vⁱ` (degree 4), from the eigenvalues of the companion matrix, each polished
/// by two Newton steps.
fn real_quartic_roots(coefficients: &[f64; 5]) -> Vec<f64> {
    let leading = coefficients[4];
    let scale = coefficients.iter().fold(0.0f64, |m, c| m.max(c.abs()));
    if !exceeds(leading.abs(), 1e-14 * scale) {
        return Vec::new();
    }
    let mut companion = Matrix4::zeros();
    for i in 0..3 {
        companion[(i + 1, i)] = 1.0;
    }
    for i in 0..4 {
        companion[(i, 3)] = -coefficients[i] / leading;
    }
    let Some(schur) = Schur::try_new(companion, f64::EPSILON, 1000) else {
        return Vec::new();
    };
    let evaluate = |v: f64| {
        coefficients
            .iter()
            .rev()
            .fold((0.0, 0.0), |(value, derivative), c| {
                (value * v + c, derivative * v + value)
            })
    };
    schur
        .complex_eigenvalues()
        .iter()
        .filter(|root| root.im.abs() <= 1e-6 * (1.0 + root.re.abs()))
        .map(|root| {
            let mut v = root.re;
            for _ in 0..2 {
                let (value, derivative) = evaluate(v);
                if derivative != 0.0 {
                    let step = value / derivative;
                    if step.is_finite() {
                        v -= step;
                    }
                }
            }
            v
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::pose::test_scenes::{random_scene, rotation_error_deg, test_intrinsics};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn one_of_the_solutions_is_the_true_pose() {
        let mut solved = 0;
        let trials = 200;
        for seed in 0..trials {
            let mut rng = ChaCha8Rng::seed_from_u64(500 + seed);
            let scene = random_scene(&mut rng, test_intrinsics(), 4, 20.0);
            let poses = solve(
                &scene.camera.intrinsics,
                &scene.image_points_px,
                &scene.world_points,
            )
            .unwrap();
            assert!(poses.len() <= 4);
            let truth = &scene.camera.cam_from_world;
            if poses.iter().any(|pose| {
                rotation_error_deg(pose, truth) < 1e-6
                    && (pose.translation - truth.translation).norm() < 1e-6
            }) {
                solved += 1;
            }
            let checked = solve_with_check(
                &scene.camera.intrinsics,
                &scene.image_points_px,
                &scene.world_points,
            );
            if let Ok(pose) = checked {
                assert!(poses.contains(&pose));
            }
        }
        println!("P3P: true pose among the solutions in {solved}/{trials} trials");
        assert!(solved * 100 >= trials * 97, "{solved}/{trials}");
    }

    #[test]
    fn the_check_point_picks_the_true_pose_and_degenerate_input_is_rejected() {
        let mut rng = ChaCha8Rng::seed_from_u64(42);
        let scene = random_scene(&mut rng, test_intrinsics(), 6, 20.0);
        let pose = solve_with_check(
            &scene.camera.intrinsics,
            &scene.image_points_px,
            &scene.world_points,
        )
        .unwrap();
        assert!(rotation_error_deg(&pose, &scene.camera.cam_from_world) < 1e-6);

        let line: Vec<Vector3<f64>> = (0..4)
            .map(|i| Vector3::new(1.0, 2.0, 0.5) * i as f64)
            .collect();
        assert!(solve(&scene.camera.intrinsics, &scene.image_points_px[..4], &line).is_err());
        let same_pixel = vec![Vector2::new(100.0, 100.0); 4];
        assert!(solve(
            &scene.camera.intrinsics,
            &same_pixel,
            &scene.world_points[..4]
        )
        .is_err());
        let mut nan_pixels = scene.image_points_px.clone();
        nan_pixels[1].x = f64::NAN;
        assert_eq!(
            solve(&scene.camera.intrinsics, &nan_pixels, &scene.world_points),
            Err(PoseError::NonFinite { index: 1 })
        );
        assert!(matches!(
            solve_with_check(
                &scene.camera.intrinsics,
                &scene.image_points_px[..3],
                &scene.world_points[..3]
            ),
            Err(PoseError::TooFewPoints { needed: 4, .. })
        ));
    }
}
