//! Normalised Direct Linear Transform for a full projective camera, and its decomposition into
//! intrinsics and pose: the paper's solver for unknown intrinsics (docs/design.md §2 step 6).
//!
//! Reference: R. Hartley, A. Zisserman, *Multiple View Geometry in Computer Vision*, 2nd ed., 2003:
//! Algorithm 7.1 (normalised DLT for `P`: 2D points to centroid 0 and mean distance √2, 3D points
//! to centroid 0 and mean distance √3, `P` = the right singular vector of the smallest singular
//! value of the stacked `2n × 12` system, then de-normalised), and §6.2.4 (decomposition
//! `P = K [R | t]` by RQ decomposition of the left 3×3 block).
//!
//! Preconditions:
//! - at least [`DLT_MIN_POINTS`] = 6 correspondences (11 DoF, two equations each), all finite;
//! - the 3D points must **not** be coplanar (nor collinear): for points on a plane `π` every
//!   `P + v πᵀ` fits them as well, the system has a ≥ 4-dimensional null space and the solver
//!   returns [`PoseError::Degenerate`]. Near-planar points give a finite but noise-dominated `P`;
//!   callers check [`super::planarity::point_cloud_shape`] first (see [`super::estimate`]);
//! - image points are undistorted pixels; the camera centre is not at infinity (`det M ≠ 0`).
//!
//! The returned `K` is upper triangular with positive focal lengths and a free skew; `R` is a
//! proper rotation (the sign of `P`, which the DLT leaves open, is fixed so that `det M > 0`, which
//! puts the observed points in front of the camera when the fit is right).

use nalgebra::{DMatrix, Matrix3, Matrix3x4, Matrix4, Vector2, Vector3};

use super::{check_solver_input, exceeds, PoseError};
use crate::core::camera::PinholeIntrinsics;
use crate::core::rigid::Rigid3;

/// Correspondences a DLT needs: 11 unknowns, two equations per point.
pub const DLT_MIN_POINTS: usize = 6;

/// Second-smallest over largest singular value of the normalised DLT system below which the
/// solution is not unique (a ≥ 2-dimensional null space: coplanar or collinear points, repeated
/// points). Exact data in general position is many orders of magnitude above it.
pub const DLT_NULL_SPACE_RATIO: f64 = 1e-9;

/// Estimates `P` (3×4, `x ~ P X`) from ≥ 6 correspondences by the normalised DLT. `P` is scaled so
/// that `‖P‖_F = 1` in normalised coordinates and its sign is not fixed.
pub fn solve_projection_matrix(
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
) -> Result<Matrix3x4<f64>, PoseError> {
    check_solver_input("DLT", DLT_MIN_POINTS, image_points_px, world_points)?;
    let (image_from_px, image_points) =
        normalize_image_points(image_points_px).ok_or(PoseError::Degenerate {
            why: "all image points coincide",
        })?;
    let (normalized_from_world, normalized_world) =
        normalize_world_points(world_points).ok_or(PoseError::Degenerate {
            why: "all world points coincide",
        })?;

    let count = image_points.len();
    let mut system = DMatrix::<f64>::zeros(2 * count, 12);
    for (i, (x, world)) in image_points.iter().zip(&normalized_world).enumerate() {
        let homogeneous = [world.x, world.y, world.z, 1.0];
        for (j, w) in homogeneous.iter().enumerate() {
            // x = P₁·X / P₃·X and y = P₂·X / P₃·X, multiplied out.
            system[(2 * i, j)] = *w;
            system[(2 * i, 8 + j)] = -x.x * w;
            system[(2 * i + 1, 4 + j)] = *w;
            system[(2 * i + 1, 8 + j)] = -x.y * w;
        }
    }
    let svd = system
        .try_svd(false, true, f64::EPSILON, 1000)
        .ok_or(PoseError::Degenerate {
            why: "the SVD of the DLT system did not converge",
        })?;
    let v_t = svd.v_t.as_ref().ok_or(PoseError::Degenerate {
        why: "the SVD of the DLT system returned no right singular vectors",
    })?;
    let singular_values = &svd.singular_values; // sorted, largest first
    if singular_values.len() < 12
        || !exceeds(
            singular_values[10],
            DLT_NULL_SPACE_RATIO * singular_values[0],
        )
    {
        return Err(PoseError::Degenerate {
            why: "the DLT has no unique solution (coplanar, collinear or repeated points)",
        });
    }
    let solution = v_t.row(11);
    let normalized_projection = Matrix3x4::from_fn(|r, c| solution[4 * r + c]);
    let projection = image_from_px.try_inverse().ok_or(PoseError::Degenerate {
        why: "image normalisation is not invertible",
    })? * normalized_projection
        * normalized_from_world;
    let norm = projection.norm();
    if !(norm.is_finite() && norm > 0.0) {
        return Err(PoseError::Degenerate {
            why: "the DLT solution is not finite",
        });
    }
    Ok(projection / norm)
}

/// Splits `P = λ K [R | t]` into intrinsics (positive focal lengths, free skew, `K₃₃ = 1`) and a
/// proper rotation and translation, whatever the sign and scale `λ` of `P`.
pub fn decompose_projection_matrix(
    projection: &Matrix3x4<f64>,
) -> Result<(PinholeIntrinsics, Rigid3), PoseError> {
    if !projection.iter().all(|v| v.is_finite()) {
        return Err(PoseError::Degenerate {
            why: "the projection matrix is not finite",
        });
    }
    let left = projection.fixed_view::<3, 3>(0, 0).into_owned();
    let determinant = left.determinant();
    let scale = left.norm();
    if !exceeds(determinant.abs(), 1e-12 * scale * scale * scale) {
        return Err(PoseError::Degenerate {
            why: "the left 3x3 block of P is singular (camera centre at infinity)",
        });
    }
    // With a positive-diagonal K, det M = det K · det R has the sign of det R: make it +1.
    let sign = determinant.signum();
    let left = left * sign;
    let last_column = projection.column(3) * sign;

    let (upper, rotation) = rq_decomposition(&left);
    // Make the diagonal of K positive; D² = I keeps the product, and det R stays +1 since
    // det M > 0 and det K > 0 afterwards.
    let signs = Matrix3::from_diagonal(&Vector3::new(
        upper[(0, 0)].signum(),
        upper[(1, 1)].signum(),
        upper[(2, 2)].signum(),
    ));
    let upper = upper * signs;
    let rotation = signs * rotation;
    if (0..3).any(|i| !exceeds(upper[(i, i)], 0.0)) {
        return Err(PoseError::Degenerate {
            why: "K has a zero on its diagonal",
        });
    }
    let translation = upper
        .solve_upper_triangular(&last_column.into_owned())
        .ok_or(PoseError::Degenerate {
            why: "K is not invertible",
        })?;
    let intrinsics = PinholeIntrinsics::from_k_matrix(&upper);
    intrinsics.validate()?;
    let cam_from_world = super::rigid_from_orthonormal(&rotation, translation);
    if !cam_from_world.is_finite() {
        return Err(PoseError::Degenerate {
            why: "the decomposed pose is not finite",
        });
    }
    Ok((intrinsics, cam_from_world))
}

/// Normalised DLT followed by [`decompose_projection_matrix`].
pub fn solve(
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
) -> Result<(PinholeIntrinsics, Rigid3), PoseError> {
    decompose_projection_matrix(&solve_projection_matrix(image_points_px, world_points)?)
}

/// `M = U Q` with `U` upper triangular and `Q` orthogonal (signs not fixed), from the QR
/// decomposition of the row-reversed transpose: with `J` the exchange matrix,
/// `(J M)ᵀ = Q' R'` gives `M = (J R'ᵀ J)(J Q'ᵀ)`.
fn rq_decomposition(matrix: &Matrix3<f64>) -> (Matrix3<f64>, Matrix3<f64>) {
    let exchange = Matrix3::new(0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0);
    let qr = (exchange * matrix).transpose().qr();
    let upper = exchange * qr.r().transpose() * exchange;
    let orthogonal = exchange * qr.q().transpose();
    (upper, orthogonal)
}

/// Hartley normalisation of 2D points: centroid to the origin, mean distance √2. Returns the
/// similarity (normalised ← pixels) and the normalised points; `None` when all points coincide.
fn normalize_image_points(points_px: &[Vector2<f64>]) -> Option<(Matrix3<f64>, Vec<Vector2<f64>>)> {
    let count = points_px.len() as f64;
    let centroid = points_px.iter().sum::<Vector2<f64>>() / count;
    let mean_distance = points_px.iter().map(|p| (p - centroid).norm()).sum::<f64>() / count;
    if !exceeds(mean_distance, 1e-12 * (1.0 + centroid.norm())) {
        return None;
    }
    let scale = std::f64::consts::SQRT_2 / mean_distance;
    let transform = Matrix3::new(
        scale,
        0.0,
        -scale * centroid.x,
        0.0,
        scale,
        -scale * centroid.y,
        0.0,
        0.0,
        1.0,
    );
    let normalized = points_px.iter().map(|p| (p - centroid) * scale).collect();
    Some((transform, normalized))
}

/// Hartley normalisation of 3D points: centroid to the origin, mean distance √3.
fn normalize_world_points(points: &[Vector3<f64>]) -> Option<(Matrix4<f64>, Vec<Vector3<f64>>)> {
    let count = points.len() as f64;
    let centroid = points.iter().sum::<Vector3<f64>>() / count;
    let mean_distance = points.iter().map(|p| (p - centroid).norm()).sum::<f64>() / count;
    if !exceeds(mean_distance, 1e-12 * (1.0 + centroid.norm())) {
        return None;
    }
    let scale = 3f64.sqrt() / mean_distance;
    let mut transform = Matrix4::identity() * scale;
    transform[(3, 3)] = 1.0;
    transform
        .fixed_view_mut::<3, 1>(0, 3)
        .copy_from(&(-centroid * scale));
    let normalized = points.iter().map(|p| (p - centroid) * scale).collect();
    Some((transform, normalized))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::pose::test_scenes::{random_scene, rotation_error_deg, test_intrinsics};
    use crate::core::pose::CameraPose;
    use nalgebra::UnitQuaternion;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn skewed_intrinsics() -> PinholeIntrinsics {
        PinholeIntrinsics {
            skew_px: 2.5,
            ..test_intrinsics()
        }
    }

    #[test]
    fn recovers_intrinsics_and_pose_from_exact_data() {
        for seed in 0..10 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            for count in [6, 7, 50] {
                let scene = random_scene(&mut rng, skewed_intrinsics(), count, 15.0);
                let (intrinsics, pose) = solve(&scene.image_points_px, &scene.world_points)
                    .unwrap_or_else(|e| panic!("seed {seed}, {count} points: {e}"));
                let truth = &scene.camera;
                for (got, want) in [
                    (intrinsics.fx_px, truth.intrinsics.fx_px),
                    (intrinsics.fy_px, truth.intrinsics.fy_px),
                    (intrinsics.cx_px, truth.intrinsics.cx_px),
                    (intrinsics.cy_px, truth.intrinsics.cy_px),
                    (intrinsics.skew_px, truth.intrinsics.skew_px),
                ] {
                    assert!((got - want).abs() < 1e-6, "seed {seed}: {got} vs {want}");
                }
                assert!(rotation_error_deg(&pose, &truth.cam_from_world) < 1e-6);
                assert!(
                    (pose.translation - truth.cam_from_world.translation).norm() < 1e-6,
                    "seed {seed}: {:?}",
                    pose.translation - truth.cam_from_world.translation
                );
            }
        }
    }

    #[test]
    fn rq_gives_positive_focal_lengths_and_a_proper_rotation_for_any_sign_and_scale() {
        let truth = CameraPose {
            intrinsics: skewed_intrinsics(),
            cam_from_world: Rigid3::new(
                UnitQuaternion::from_euler_angles(2.9, -0.4, 1.3),
                Vector3::new(3.0, -1.0, 40.0),
            ),
        };
        let projection = truth.projection_matrix();
        for scale in [1.0, -1.0, 1e-4, -3e5] {
            let (intrinsics, pose) = decompose_projection_matrix(&(projection * scale)).unwrap();
            assert!(intrinsics.fx_px > 0.0 && intrinsics.fy_px > 0.0);
            assert!((pose.rotation_matrix().determinant() - 1.0).abs() < 1e-12);
            assert!((intrinsics.fx_px - truth.intrinsics.fx_px).abs() < 1e-8);
            assert!((intrinsics.skew_px - truth.intrinsics.skew_px).abs() < 1e-8);
            assert!(rotation_error_deg(&pose, &truth.cam_from_world) < 1e-9);
            assert!((pose.translation - truth.cam_from_world.translation).norm() < 1e-9);
        }
        assert!(decompose_projection_matrix(&Matrix3x4::zeros()).is_err());
        assert!(decompose_projection_matrix(&(projection * f64::NAN)).is_err());
    }

    #[test]
    fn coplanar_collinear_and_repeated_points_give_no_model() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let planar = random_scene(&mut rng, test_intrinsics(), 20, 0.0);
        assert!(matches!(
            solve(&planar.image_points_px, &planar.world_points),
            Err(PoseError::Degenerate { .. })
        ));

        let camera = random_scene(&mut rng, test_intrinsics(), 6, 10.0).camera;
        let line: Vec<Vector3<f64>> = (0..8)
            .map(|i| Vector3::new(1.0, -2.0, 0.5) * i as f64 + Vector3::new(0.0, 0.0, 1.0))
            .collect();
        let line_px: Vec<Vector2<f64>> = line.iter().map(|p| camera.project(p).unwrap()).collect();
        assert!(solve(&line_px, &line).is_err());

        let repeated = vec![Vector3::new(1.0, 2.0, 3.0); 6];
        let repeated_px = vec![Vector2::new(10.0, 20.0); 6];
        assert!(solve(&repeated_px, &repeated).is_err());
    }

    #[test]
    fn bad_input_is_rejected_without_panicking() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let scene = random_scene(&mut rng, test_intrinsics(), 8, 10.0);
        assert_eq!(
            solve(&scene.image_points_px[..5], &scene.world_points[..5]),
            Err(PoseError::TooFewPoints {
                solver: "DLT",
                needed: 6,
                got: 5
            })
        );
        assert!(matches!(
            solve(&scene.image_points_px, &scene.world_points[..7]),
            Err(PoseError::LengthMismatch { .. })
        ));
        let mut nan_world = scene.world_points.clone();
        nan_world[4].y = f64::NAN;
        assert_eq!(
            solve(&scene.image_points_px, &nan_world),
            Err(PoseError::NonFinite { index: 4 })
        );
        let mut inf_image = scene.image_points_px.clone();
        inf_image[0].x = f64::INFINITY;
        assert_eq!(
            solve(&inf_image, &scene.world_points),
            Err(PoseError::NonFinite { index: 0 })
        );
    }
}
