//! EPnP: the camera pose from ≥ 4 correspondences when the intrinsics are known (docs/design.md §2
//! step 6, the paper's known-intrinsics case).
//!
//! Reference: V. Lepetit, F. Moreno-Noguer, P. Fua, "EPnP: An Accurate O(n) Solution to the PnP
//! Problem", IJCV 81(2), 2009. Every world point is written as a barycentric combination of a few
//! control points (centroid plus the principal directions of the points, scaled by their standard
//! deviations, as in the authors' and OpenCV's code). Each image point gives two linear equations
//! in the control points' camera coordinates (`M x = 0`); `x` lies in the span of the `N` right
//! singular vectors of `M` with the smallest singular values, `x = Σ βₖ vₖ`. The βs come from the
//! preserved distances between control points (linearised for `N = 1, 2, 3`, the "β₁βₖ"
//! approximation where there are more products than distances, as for `N = 4`), refined by
//! Gauss–Newton on those distances; each candidate gives camera-frame points, the pose follows by
//! absolute orientation (Horn/Umeyama), and the candidate with the lowest reprojection error wins.
//!
//! Preconditions:
//! - known intrinsics (skew allowed: image points are mapped to normalised coordinates by `K⁻¹`);
//!   undistorted pixels; at least [`EPNP_MIN_POINTS`] = 4 finite correspondences;
//! - the world points must not be collinear (or coincide): [`PoseError::Degenerate`];
//! - **planar scenes**: when the points' planarity ratio (smallest over largest principal standard
//!   deviation) is below [`EPNP_PLANAR_RATIO`], the paper's planar variant is used: three control
//!   points spanning the plane, `M` is `2n × 9`, `N = 1..3`. Otherwise four control points,
//!   `N = 1..4`;
//! - with exactly 4 non-planar points the kernel is 4-dimensional and the `N = 4` approximation
//!   starts Gauss–Newton in a wrong basin on about 15 % of exact samples; for 4 points the P3P
//!   solutions of the first three ([`super::p3p`]) are added as candidates, so the 4-point case
//!   recovers exact poses too. RANSAC samples 5 points by default (see [`super::ransac`]).

use nalgebra::{DMatrix, DVector, Matrix3, Matrix4, SymmetricEigen, Vector2, Vector3, Vector4};

use super::planarity::point_cloud_shape;
use super::{check_solver_input, exceeds, CameraPose, PoseError};
use crate::core::camera::PinholeIntrinsics;
use crate::core::rigid::Rigid3;

/// Correspondences EPnP needs (6 DoF; with 4 the `N = 4` case of the paper).
pub const EPNP_MIN_POINTS: usize = 4;

/// Planarity ratio (see [`super::PointCloudShape::planarity_ratio`]) below which the three-control-
/// point (planar) variant is used. Control points are scaled by the points' spread, so the
/// four-point variant stays well conditioned down to very thin clouds; it breaks only when the
/// third spread is numerically zero (exactly planar points, ratio ~1e-8). Measured at 0.5 px noise
/// (200 scenes per row, ratios 1e-8 to 5e-3): both variants give the same rotation error within
/// about 10 % — the planar one slightly better on 5–6-point samples, the general one on 200
/// points — so the switch sits well above numerical zero and well below real relief.
pub const EPNP_PLANAR_RATIO: f64 = 1e-4;

/// Gauss–Newton iterations on the betas (the authors' code uses 5; it converges in 2–3).
const BETA_GAUSS_NEWTON_ITERATIONS: usize = 30;

/// Which EPnP variant ran, for callers that report it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EpnpVariant {
    /// Four control points: general 3D point sets.
    General,
    /// Three control points spanning the plane of (near-)coplanar points.
    Planar,
}

/// The pose `cam_from_world` from ≥ 4 correspondences with known intrinsics.
pub fn solve(
    intrinsics: &PinholeIntrinsics,
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
) -> Result<Rigid3, PoseError> {
    solve_with_variant(intrinsics, image_points_px, world_points).map(|(pose, _)| pose)
}

/// [`solve`], also saying which variant ran.
pub fn solve_with_variant(
    intrinsics: &PinholeIntrinsics,
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
) -> Result<(Rigid3, EpnpVariant), PoseError> {
    check_solver_input("EPnP", EPNP_MIN_POINTS, image_points_px, world_points)?;
    intrinsics.validate()?;
    let shape = point_cloud_shape(world_points)?;
    if !exceeds(shape.collinearity_ratio, 1e-6) {
        return Err(PoseError::Degenerate {
            why: "the world points are collinear",
        });
    }
    let variant = if shape.planarity_ratio < EPNP_PLANAR_RATIO {
        EpnpVariant::Planar
    } else {
        EpnpVariant::General
    };
    solve_variant(intrinsics, image_points_px, world_points, &shape, variant)
        .map(|pose| (pose, variant))
}

/// The EPnP core for a chosen variant (inputs already checked).
fn solve_variant(
    intrinsics: &PinholeIntrinsics,
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
    shape: &super::PointCloudShape,
    variant: EpnpVariant,
) -> Result<Rigid3, PoseError> {
    let control_count = match variant {
        EpnpVariant::Planar => 3,
        EpnpVariant::General => 4,
    };

    let (world_controls, alphas) = control_points(shape, control_count, world_points);
    let normalized_points: Vec<Vector2<f64>> = image_points_px
        .iter()
        .map(|p| intrinsics.pixel_to_normalized(*p))
        .collect();
    let dimension = 3 * control_count;
    let normal_matrix = normal_matrix(&alphas, &normalized_points, control_count);
    let eigen = SymmetricEigen::try_new(normal_matrix, f64::EPSILON, 1000).ok_or(
        PoseError::Degenerate {
            why: "the EPnP system did not diagonalise",
        },
    )?;
    let mut order: Vec<usize> = (0..dimension).collect();
    order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
    let max_betas = control_count; // 4 for the general case, 3 for the planar one
    let kernel: Vec<DVector<f64>> = order[..max_betas]
        .iter()
        .map(|&i| eigen.eigenvectors.column(i).into_owned())
        .collect();

    let pairs: Vec<(usize, usize)> = (0..control_count)
        .flat_map(|a| (a + 1..control_count).map(move |b| (a, b)))
        .collect();
    let squared_distances: Vec<f64> = pairs
        .iter()
        .map(|&(a, b)| (world_controls[a] - world_controls[b]).norm_squared())
        .collect();
    // dots[p][k][l] = (vₖ[a] - vₖ[b]) · (vₗ[a] - vₗ[b]) for pair p = (a, b).
    let dots: Vec<[[f64; 4]; 4]> = pairs
        .iter()
        .map(|&(a, b)| {
            let differences: Vec<Vector3<f64>> = kernel
                .iter()
                .map(|v| {
                    Vector3::new(
                        v[3 * a] - v[3 * b],
                        v[3 * a + 1] - v[3 * b + 1],
                        v[3 * a + 2] - v[3 * b + 2],
                    )
                })
                .collect();
            let mut table = [[0.0; 4]; 4];
            for k in 0..max_betas {
                for l in 0..max_betas {
                    table[k][l] = differences[k].dot(&differences[l]);
                }
            }
            table
        })
        .collect();

    // Candidates: each N's linearised βs refined over N kernel vectors, and that result refined
    // again over all of them (as OpenCV does), which rescues the N = 4 approximation.
    let mut candidates: Vec<[f64; 4]> = Vec::with_capacity(2 * max_betas);
    for beta_count in 1..=max_betas {
        let Some(mut betas) = initial_betas(beta_count, &dots, &squared_distances) else {
            continue;
        };
        refine_betas(&mut betas[..beta_count], &dots, &squared_distances);
        candidates.push(betas);
        if beta_count < max_betas {
            refine_betas(&mut betas[..max_betas], &dots, &squared_distances);
            candidates.push(betas);
        }
    }
    let mut poses: Vec<Rigid3> = candidates
        .iter()
        .filter_map(|betas| pose_from_betas(&betas[..max_betas], &kernel, &alphas, world_points))
        .collect();
    if image_points_px.len() == EPNP_MIN_POINTS {
        // Four points: the N = 4 approximation can miss (about 15 % of exact samples); P3P on
        // three of them always has the true pose among its solutions, and the error on all
        // four decides. Degenerate triples simply add nothing.
        poses.extend(
            super::p3p::solve(intrinsics, image_points_px, world_points).unwrap_or_default(),
        );
    }
    let mut best: Option<(f64, Rigid3)> = None;
    for pose in poses {
        let camera = CameraPose {
            intrinsics: *intrinsics,
            cam_from_world: pose,
        };
        let Some(error) = super::reprojection_rms_px(&camera, image_points_px, world_points) else {
            continue;
        };
        if best
            .as_ref()
            .is_none_or(|(best_error, _)| error < *best_error)
        {
            best = Some((error, pose));
        }
    }
    best.map(|(_, pose)| pose).ok_or(PoseError::Degenerate {
        why: "no EPnP candidate put the points in front of the camera",
    })
}

/// The world control points (the centroid, then centroid + σₖ·axisₖ for `control_count − 1`
/// principal axes of `shape`) and each world point's barycentric coordinates in them (the axes
/// are orthonormal, so they come by projection).
pub(super) fn control_points(
    shape: &super::PointCloudShape,
    control_count: usize,
    world_points: &[Vector3<f64>],
) -> (Vec<Vector3<f64>>, Vec<[f64; 4]>) {
    let mut world_controls = vec![shape.centroid_m];
    for axis in 0..control_count - 1 {
        world_controls
            .push(shape.centroid_m + shape.principal_axes[axis] * shape.principal_std_m[axis]);
    }
    let alphas = world_points
        .iter()
        .map(|point| {
            let centred = point - shape.centroid_m;
            let mut alpha = [0.0; 4];
            for axis in 0..control_count - 1 {
                alpha[axis + 1] =
                    centred.dot(&shape.principal_axes[axis]) / shape.principal_std_m[axis];
            }
            alpha[0] = 1.0 - alpha[1..].iter().sum::<f64>();
            alpha
        })
        .collect();
    (world_controls, alphas)
}

/// `MᵀM` of EPnP's system `M x = 0` in the control points' camera coordinates, accumulated row by
/// row: per control point j, each point gives the rows [αⱼ, 0, -αⱼ x] and [0, αⱼ, -αⱼ y]
/// (`x`, `y` its normalised image coordinates).
pub(super) fn normal_matrix(
    alphas: &[[f64; 4]],
    normalized_points: &[Vector2<f64>],
    control_count: usize,
) -> DMatrix<f64> {
    let dimension = 3 * control_count;
    let mut normal_matrix = DMatrix::<f64>::zeros(dimension, dimension);
    let mut row_u = [0.0; 12];
    let mut row_v = [0.0; 12];
    for (alpha, point) in alphas.iter().zip(normalized_points) {
        for j in 0..control_count {
            row_u[3 * j] = alpha[j];
            row_u[3 * j + 1] = 0.0;
            row_u[3 * j + 2] = -alpha[j] * point.x;
            row_v[3 * j] = 0.0;
            row_v[3 * j + 1] = alpha[j];
            row_v[3 * j + 2] = -alpha[j] * point.y;
        }
        for a in 0..dimension {
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
    normal_matrix
}

/// The βs for `beta_count` kernel vectors from the linearised distance constraints.
fn initial_betas(
    beta_count: usize,
    dots: &[[[f64; 4]; 4]],
    squared_distances: &[f64],
) -> Option<[f64; 4]> {
    let mut betas = [0.0; 4];
    if beta_count == 1 {
        // Closed form of the paper: β = Σ ‖vᵢ−vⱼ‖·‖cᵢ−cⱼ‖ / Σ ‖vᵢ−vⱼ‖².
        let (numerator, denominator) = dots.iter().zip(squared_distances).fold(
            (0.0, 0.0),
            |(num, den), (table, distance2)| {
                (
                    num + table[0][0].sqrt() * distance2.sqrt(),
                    den + table[0][0],
                )
            },
        );
        betas[0] = numerator / denominator;
        return betas[0].is_finite().then_some(betas);
    }
    // Unknowns: all products βₖβₗ (k ≤ l) when the distances determine them, else only β₁βₗ.
    let all_products = beta_count * (beta_count + 1) / 2 <= squared_distances.len();
    let products: Vec<(usize, usize)> = if all_products {
        (0..beta_count)
            .flat_map(|k| (k..beta_count).map(move |l| (k, l)))
            .collect()
    } else {
        (0..beta_count).map(|l| (0, l)).collect()
    };
    let system = DMatrix::from_fn(squared_distances.len(), products.len(), |p, c| {
        let (k, l) = products[c];
        if k == l {
            dots[p][k][k]
        } else {
            2.0 * dots[p][k][l]
        }
    });
    let rhs = DVector::from_column_slice(squared_distances);
    if !system.iter().all(|v| v.is_finite()) {
        return None;
    }
    let solution = system
        .try_svd(true, true, f64::EPSILON, 1000)?
        .solve(&rhs, 1e-12)
        .ok()?;
    let b11 = solution[0];
    let beta1 = b11.abs().sqrt();
    if !exceeds(beta1, 0.0) {
        return None;
    }
    let sign = if b11 < 0.0 { -1.0 } else { 1.0 };
    betas[0] = beta1;
    for (l, beta) in betas.iter_mut().enumerate().take(beta_count).skip(1) {
        let column = products.iter().position(|&product| product == (0, l))?;
        *beta = sign * solution[column] / beta1;
    }
    betas.iter().all(|b| b.is_finite()).then_some(betas)
}

/// Gauss–Newton on `Σ_p (Σₖₗ βₖβₗ dots[p][k][l] − d_p²)²`, by its normal equations (at most 4×4;
/// unused dimensions are padded with the identity).
fn refine_betas(betas: &mut [f64], dots: &[[[f64; 4]; 4]], squared_distances: &[f64]) {
    let count = betas.len();
    for _ in 0..BETA_GAUSS_NEWTON_ITERATIONS {
        let mut normal_matrix = Matrix4::<f64>::identity();
        for k in 0..count {
            normal_matrix[(k, k)] = 0.0;
        }
        let mut gradient = Vector4::<f64>::zeros();
        let mut cost = 0.0;
        for (table, distance2) in dots.iter().zip(squared_distances) {
            let mut value = 0.0;
            let mut row = [0.0; 4];
            for k in 0..count {
                for l in 0..count {
                    value += betas[k] * betas[l] * table[k][l];
                    row[k] += 2.0 * table[k][l] * betas[l];
                }
            }
            let residual = value - distance2;
            cost += residual * residual;
            for k in 0..count {
                gradient[k] += row[k] * residual;
                for l in 0..count {
                    normal_matrix[(k, l)] += row[k] * row[l];
                }
            }
        }
        if cost == 0.0 {
            return;
        }
        let Some(step) = normal_matrix.lu().solve(&(-gradient)) else {
            return;
        };
        if !step.iter().all(|v| v.is_finite()) {
            return;
        }
        for (beta, delta) in betas.iter_mut().zip(step.iter()) {
            *beta += delta;
        }
        if step.norm() < 1e-10 * (1.0 + betas.iter().map(|b| b * b).sum::<f64>().sqrt()) {
            return;
        }
    }
}

/// Camera-frame control points `Σ βₖ vₖ`, the points from their alphas, and the pose by absolute
/// orientation. The βs' overall sign is chosen so that the points are in front of the camera.
fn pose_from_betas(
    betas: &[f64],
    kernel: &[DVector<f64>],
    alphas: &[[f64; 4]],
    world_points: &[Vector3<f64>],
) -> Option<Rigid3> {
    let control_count = kernel[0].len() / 3;
    let mut camera_controls = [Vector3::zeros(); 4];
    for (j, control) in camera_controls.iter_mut().enumerate().take(control_count) {
        for (beta, vector) in betas.iter().zip(kernel) {
            *control += Vector3::new(vector[3 * j], vector[3 * j + 1], vector[3 * j + 2]) * *beta;
        }
    }
    let mut camera_points: Vec<Vector3<f64>> = alphas
        .iter()
        .map(|alpha| {
            (0..control_count)
                .map(|j| camera_controls[j] * alpha[j])
                .sum()
        })
        .collect();
    if camera_points.iter().map(|p| p.z).sum::<f64>() < 0.0 {
        camera_points.iter_mut().for_each(|p| *p = -*p);
    }
    rigid_from_point_pairs(world_points, &camera_points)
}

/// The rigid transform `b_from_a` minimising `Σ ‖b − (R a + t)‖²` (Umeyama 1991 without scale).
/// `None` for fewer than 3 points, non-finite input or a collinear configuration.
pub fn rigid_from_point_pairs(
    points_a: &[Vector3<f64>],
    points_b: &[Vector3<f64>],
) -> Option<Rigid3> {
    if points_a.len() < 3 || points_a.len() != points_b.len() {
        return None;
    }
    let count = points_a.len() as f64;
    let centroid_a = points_a.iter().sum::<Vector3<f64>>() / count;
    let centroid_b = points_b.iter().sum::<Vector3<f64>>() / count;
    let mut cross_covariance = Matrix3::zeros();
    for (a, b) in points_a.iter().zip(points_b) {
        cross_covariance += (b - centroid_b) * (a - centroid_a).transpose();
    }
    if !cross_covariance.iter().all(|v| v.is_finite()) {
        return None;
    }
    let svd = cross_covariance.try_svd(true, true, f64::EPSILON, 1000)?;
    let (u, v_t) = (svd.u?, svd.v_t?);
    if !exceeds(svd.singular_values[1], 1e-12 * svd.singular_values[0]) {
        return None;
    }
    let mut correction = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        correction[(2, 2)] = -1.0;
    }
    let rotation = u * correction * v_t;
    let translation = centroid_b - rotation * centroid_a;
    let pose = super::rigid_from_orthonormal(&rotation, translation);
    pose.is_finite().then_some(pose)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::pose::test_scenes::{
        corrupt, random_scene, rotation_error_deg, test_intrinsics,
    };
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn recovers_a_known_pose_from_exact_data() {
        for seed in 0..10 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            for count in [4, 5, 6, 30, 500] {
                let scene = random_scene(&mut rng, test_intrinsics(), count, 20.0);
                let (pose, variant) = solve_with_variant(
                    &scene.camera.intrinsics,
                    &scene.image_points_px,
                    &scene.world_points,
                )
                .unwrap_or_else(|e| panic!("seed {seed}, {count} points: {e}"));
                assert_eq!(variant, EpnpVariant::General);
                let truth = &scene.camera.cam_from_world;
                assert!(
                    rotation_error_deg(&pose, truth) < 1e-6,
                    "seed {seed}, {count} points: {} deg",
                    rotation_error_deg(&pose, truth)
                );
                assert!(
                    (pose.translation - truth.translation).norm() < 1e-6,
                    "seed {seed}, {count} points: {}",
                    (pose.translation - truth.translation).norm()
                );
            }
        }
    }

    #[test]
    fn exactly_four_points_recover_the_pose() {
        // With four non-coplanar points the kernel is 4-dimensional and the N = 4 approximation can
        // start Gauss–Newton in a wrong basin; the P3P candidates cover those cases.
        let trials = 200;
        let mut recovered = 0;
        for seed in 0..trials {
            let mut rng = ChaCha8Rng::seed_from_u64(1000 + seed);
            let scene = random_scene(&mut rng, test_intrinsics(), 4, 20.0);
            if let Ok(pose) = solve(
                &scene.camera.intrinsics,
                &scene.image_points_px,
                &scene.world_points,
            ) {
                let truth = &scene.camera.cam_from_world;
                if rotation_error_deg(&pose, truth) < 1e-4
                    && (pose.translation - truth.translation).norm() < 1e-4
                {
                    recovered += 1;
                }
            }
        }
        assert_eq!(recovered, trials);
    }

    #[test]
    fn planar_points_use_the_three_control_point_variant_and_recover_the_pose() {
        for seed in 0..10 {
            let mut rng = ChaCha8Rng::seed_from_u64(100 + seed);
            for count in [4, 6, 100] {
                let scene = random_scene(&mut rng, test_intrinsics(), count, 0.0);
                let (pose, variant) = solve_with_variant(
                    &scene.camera.intrinsics,
                    &scene.image_points_px,
                    &scene.world_points,
                )
                .unwrap_or_else(|e| panic!("seed {seed}, {count} points: {e}"));
                assert_eq!(variant, EpnpVariant::Planar);
                let truth = &scene.camera.cam_from_world;
                assert!(
                    rotation_error_deg(&pose, truth) < 1e-6,
                    "seed {seed}, {count}"
                );
                assert!(
                    (pose.translation - truth.translation).norm() < 1e-6,
                    "seed {seed}, {count}"
                );
            }
        }
    }

    #[test]
    fn noisy_data_gives_a_close_pose() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for relief_m in [0.0, 0.05, 20.0] {
            let mut scene = random_scene(&mut rng, test_intrinsics(), 200, relief_m);
            corrupt(&mut scene, &mut rng, 0.5, 0);
            let pose = solve(
                &scene.camera.intrinsics,
                &scene.image_points_px,
                &scene.world_points,
            )
            .unwrap();
            let truth = &scene.camera.cam_from_world;
            assert!(rotation_error_deg(&pose, truth) < 0.2, "relief {relief_m}");
            assert!(
                (pose.camera_center() - truth.camera_center()).norm() < 0.3,
                "relief {relief_m}: {}",
                (pose.camera_center() - truth.camera_center()).norm()
            );
        }
    }

    #[test]
    fn collinear_and_bad_input_give_errors_not_panics() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let scene = random_scene(&mut rng, test_intrinsics(), 10, 10.0);
        let intrinsics = scene.camera.intrinsics;
        let line: Vec<Vector3<f64>> = (0..6)
            .map(|i| Vector3::new(2.0, 1.0, 0.3) * i as f64)
            .collect();
        let line_px: Vec<Vector2<f64>> = line
            .iter()
            .map(|p| scene.camera.project(p).unwrap())
            .collect();
        assert!(matches!(
            solve(&intrinsics, &line_px, &line),
            Err(PoseError::Degenerate { .. })
        ));
        assert!(matches!(
            solve(
                &intrinsics,
                &scene.image_points_px[..3],
                &scene.world_points[..3]
            ),
            Err(PoseError::TooFewPoints { .. })
        ));
        let mut nan_image = scene.image_points_px.clone();
        nan_image[9].y = f64::NAN;
        assert_eq!(
            solve(&intrinsics, &nan_image, &scene.world_points),
            Err(PoseError::NonFinite { index: 9 })
        );
        let bad_intrinsics = PinholeIntrinsics {
            fx_px: f64::NAN,
            ..intrinsics
        };
        assert!(matches!(
            solve(&bad_intrinsics, &scene.image_points_px, &scene.world_points),
            Err(PoseError::Intrinsics(_))
        ));
        let same = vec![Vector3::new(1.0, 1.0, 1.0); 5];
        assert!(solve(&intrinsics, &scene.image_points_px[..5], &same).is_err());
    }

    #[test]
    fn absolute_orientation_recovers_a_transform() {
        let transform = Rigid3::new(
            nalgebra::UnitQuaternion::from_euler_angles(0.4, 2.0, -1.0),
            Vector3::new(5.0, -3.0, 2.0),
        );
        let points: Vec<Vector3<f64>> = (0..5)
            .map(|i| Vector3::new(i as f64, (i * i) as f64 * 0.3, 1.0 - i as f64 * 0.7))
            .collect();
        let moved: Vec<Vector3<f64>> = points
            .iter()
            .map(|p| transform.transform_point(p))
            .collect();
        let recovered = rigid_from_point_pairs(&points, &moved).unwrap();
        assert!(rotation_error_deg(&recovered, &transform) < 1e-9);
        assert!((recovered.translation - transform.translation).norm() < 1e-9);
    }
}
