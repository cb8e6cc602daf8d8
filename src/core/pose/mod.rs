//! Pose solving (docs/design.md §2 step 6): from 2D–3D correspondences (a photo pixel and the model
//! point a rendering put there) to a camera, robustly.
//!
//! - [`dlt`]: normalised DLT on ≥ 6 points, decomposed into `K` and `cam_from_world` (unknown
//!   intrinsics, the paper's solver);
//! - [`epnp`]: EPnP on ≥ 4 points (known intrinsics), with its planar three-control-point variant;
//! - [`epnpf`]: EPnP with unknown focal length on ≥ 6 points (UPnP's linear case; principal point
//!   known, no skew: a drone's EXIF camera);
//! - [`p3p`]: Grunert's P3P (known intrinsics), the minimal alternative inside RANSAC;
//! - [`refine`]: Levenberg–Marquardt on the reprojection error of the inliers;
//! - [`ransac`]: the generic RANSAC loop (estimator / sampler / consensus, seeded RNG passed in)
//!   with the paper's stopping rule, and the DLT, EPnP and P3P estimators;
//! - [`planarity`]: how close the 3D points are to a plane (the paper's main failure case);
//! - [`estimate`]: the whole step for one coarse pose — RANSAC, refinement, planar policy.
//!
//! Conventions: image points in pixels with the centre of pixel `(col, row)` at
//! `(col + 0.5, row + 0.5)` (COLMAP), world points in the mesh's local frame (metres), poses
//! `cam_from_world`. Distortion is not modelled here: undistort image points first.

pub mod dlt;
pub mod epnp;
pub mod epnpf;
pub mod estimate;
pub mod p3p;
pub mod planarity;
pub mod ransac;
pub mod refine;

pub use estimate::{
    estimate_pose, FixedIntrinsicsSolver, IntrinsicsPrior, IntrinsicsSource, PoseEstimate,
    PoseEstimationConfig, RansacSummary, SolverKind,
};
pub use planarity::{depth_relief_ratio, point_cloud_shape, PointCloudShape};
pub use ransac::{
    ransac_camera, DltEstimator, EpnpEstimator, EpnpFocalEstimator, P3pEstimator, RansacConfig,
    RansacOutput,
};
pub use refine::{refine_camera, RefineConfig, RefineStop, RefinedParameters, RefinementSummary};

use nalgebra::{Matrix3, Matrix3x4, Rotation3, UnitQuaternion, Vector2, Vector3, Vector4};

use crate::core::camera::{CameraError, PinholeIntrinsics, MIN_DEPTH_M};
use crate::core::rigid::Rigid3;

/// Errors of pose solving. Solvers return these instead of panicking, whatever the input.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum PoseError {
    #[error("{solver} needs at least {needed} correspondences, got {got}")]
    TooFewPoints {
        solver: &'static str,
        needed: usize,
        got: usize,
    },
    #[error("{image_points} image points but {world_points} world points")]
    LengthMismatch {
        image_points: usize,
        world_points: usize,
    },
    #[error("correspondence {index} has a non-finite coordinate")]
    NonFinite { index: usize },
    #[error("degenerate configuration: {why}")]
    Degenerate { why: &'static str },
    #[error(
        "the 3D points are near-planar (planarity ratio {planarity_ratio:.3e} < {min_ratio:.3e}): \
         a DLT cannot recover the intrinsics; pass fallback intrinsics to solve with them fixed"
    )]
    NearPlanar {
        planarity_ratio: f64,
        min_ratio: f64,
    },
    #[error("invalid configuration: {field} {why}")]
    InvalidConfig {
        field: &'static str,
        why: &'static str,
    },
    #[error("invalid intrinsics: {0}")]
    Intrinsics(#[from] CameraError),
    #[error("RANSAC found no model in {iterations} iterations ({degenerate_samples} degenerate samples)")]
    NoModel {
        iterations: usize,
        degenerate_samples: usize,
    },
}

/// Matched image and world points, checked once: equal lengths, all coordinates finite.
#[derive(Clone, Copy, Debug)]
pub struct Correspondences<'a> {
    image_points_px: &'a [Vector2<f64>],
    world_points: &'a [Vector3<f64>],
}

impl<'a> Correspondences<'a> {
    pub fn new(
        image_points_px: &'a [Vector2<f64>],
        world_points: &'a [Vector3<f64>],
    ) -> Result<Self, PoseError> {
        check_correspondences(image_points_px, world_points)?;
        Ok(Self {
            image_points_px,
            world_points,
        })
    }

    pub fn image_points_px(&self) -> &'a [Vector2<f64>] {
        self.image_points_px
    }

    pub fn world_points(&self) -> &'a [Vector3<f64>] {
        self.world_points
    }

    pub fn len(&self) -> usize {
        self.image_points_px.len()
    }

    pub fn is_empty(&self) -> bool {
        self.image_points_px.is_empty()
    }
}

/// `value > bound`, false when either is NaN: solvers write `!exceeds(..)` to reject NaN with the
/// failing case.
#[inline]
pub(crate) fn exceeds(value: f64, bound: f64) -> bool {
    value > bound
}

/// Lengths equal and every coordinate finite (what every solver checks first).
pub(crate) fn check_correspondences(
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
) -> Result<(), PoseError> {
    if image_points_px.len() != world_points.len() {
        return Err(PoseError::LengthMismatch {
            image_points: image_points_px.len(),
            world_points: world_points.len(),
        });
    }
    for (index, (image_point, world_point)) in image_points_px.iter().zip(world_points).enumerate()
    {
        if !image_point
            .iter()
            .chain(world_point.iter())
            .all(|v| v.is_finite())
        {
            return Err(PoseError::NonFinite { index });
        }
    }
    Ok(())
}

/// `check_correspondences` plus a minimum count.
pub(crate) fn check_solver_input(
    solver: &'static str,
    needed: usize,
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
) -> Result<(), PoseError> {
    check_correspondences(image_points_px, world_points)?;
    if image_points_px.len() < needed {
        return Err(PoseError::TooFewPoints {
            solver,
            needed,
            got: image_points_px.len(),
        });
    }
    Ok(())
}

/// A pinhole camera placed in the world: what a solver returns and RANSAC scores.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CameraPose {
    pub intrinsics: PinholeIntrinsics,
    pub cam_from_world: Rigid3,
}

impl CameraPose {
    /// `P = K [R | t]`, with the third row giving the depth of a point (positive in front).
    pub fn projection_matrix(&self) -> Matrix3x4<f64> {
        let mut rt = Matrix3x4::zeros();
        rt.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&self.cam_from_world.rotation_matrix());
        rt.set_column(3, &self.cam_from_world.translation);
        self.intrinsics.k_matrix() * rt
    }

    /// Pixel position of a world point; `None` behind the camera.
    pub fn project(&self, world_point: &Vector3<f64>) -> Option<Vector2<f64>> {
        self.intrinsics
            .project(&self.cam_from_world.transform_point(world_point))
    }

    pub fn is_finite(&self) -> bool {
        self.cam_from_world.is_finite() && self.intrinsics.validate().is_ok()
    }
}

/// A pose from a rotation matrix that is orthonormal to rounding (from an SVD or QR), without the
/// iterative re-orthonormalisation of `Rotation3::from_matrix` (a sixth of EPnP's time).
pub(crate) fn rigid_from_orthonormal(rotation: &Matrix3<f64>, translation: Vector3<f64>) -> Rigid3 {
    Rigid3::new(
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*rotation)),
        translation,
    )
}

/// Projects with a precomputed `P = K [R | t]`; `None` when the point is not in front of the
/// camera.
#[inline]
pub(crate) fn project_with_matrix(
    projection: &Matrix3x4<f64>,
    world_point: &Vector3<f64>,
) -> Option<Vector2<f64>> {
    let homogeneous = projection * Vector4::new(world_point.x, world_point.y, world_point.z, 1.0);
    (homogeneous.z > MIN_DEPTH_M)
        .then(|| Vector2::new(homogeneous.x / homogeneous.z, homogeneous.y / homogeneous.z))
}

/// Root mean square of the pixel distance between projected world points and image points;
/// `None` when any point is behind the camera or the set is empty.
pub fn reprojection_rms_px(
    camera: &CameraPose,
    image_points_px: &[Vector2<f64>],
    world_points: &[Vector3<f64>],
) -> Option<f64> {
    if image_points_px.is_empty() || image_points_px.len() != world_points.len() {
        return None;
    }
    let projection = camera.projection_matrix();
    let mut sum_squared_px2 = 0.0;
    for (image_point, world_point) in image_points_px.iter().zip(world_points) {
        let projected = project_with_matrix(&projection, world_point)?;
        sum_squared_px2 += (projected - image_point).norm_squared();
    }
    Some((sum_squared_px2 / image_points_px.len() as f64).sqrt())
}

#[cfg(test)]
pub(crate) mod test_scenes {
    //! Synthetic correspondences with a known camera, shared by the solver tests.

    use super::*;
    use nalgebra::UnitQuaternion;
    use rand::Rng;
    use rand_distr::{Distribution, Normal};

    pub struct Scene {
        pub camera: CameraPose,
        pub world_points: Vec<Vector3<f64>>,
        pub image_points_px: Vec<Vector2<f64>>,
    }

    pub fn test_intrinsics() -> PinholeIntrinsics {
        PinholeIntrinsics {
            fx_px: 820.0,
            fy_px: 790.0,
            cx_px: 330.0,
            cy_px: 235.0,
            skew_px: 0.0,
        }
    }

    /// A camera at a random position about 60 m from the origin looking roughly at it, and
    /// `count` points in a 40 m × 40 m area whose height spread is `relief_m` (0: planar).
    pub fn random_scene<R: Rng>(
        rng: &mut R,
        intrinsics: PinholeIntrinsics,
        count: usize,
        relief_m: f64,
    ) -> Scene {
        let rotation = UnitQuaternion::from_euler_angles(
            rng.random_range(-0.3..0.3),
            rng.random_range(-0.3..0.3),
            rng.random_range(-3.0..3.0),
        );
        let eye = Vector3::new(
            rng.random_range(-20.0..20.0),
            rng.random_range(-20.0..20.0),
            rng.random_range(50.0..70.0),
        );
        let target = Vector3::new(
            rng.random_range(-3.0..3.0),
            rng.random_range(-3.0..3.0),
            0.0,
        );
        let look = Rigid3::look_at(&eye, &target, &(rotation * Vector3::y()))
            .unwrap_or_else(|| Rigid3::look_at(&eye, &target, &Vector3::x()).unwrap());
        let camera = CameraPose {
            intrinsics,
            cam_from_world: look,
        };
        let mut world_points = Vec::with_capacity(count);
        let mut image_points_px = Vec::with_capacity(count);
        while world_points.len() < count {
            let world_point = Vector3::new(
                rng.random_range(-20.0..20.0),
                rng.random_range(-20.0..20.0),
                rng.random_range(-0.5..0.5) * relief_m,
            );
            if let Some(pixel) = camera.project(&world_point) {
                world_points.push(world_point);
                image_points_px.push(pixel);
            }
        }
        Scene {
            camera,
            world_points,
            image_points_px,
        }
    }

    /// Adds Gaussian noise of `sigma_px` to every image point and replaces the first
    /// `outlier_count` with uniformly random pixels in a 660 × 470 image.
    pub fn corrupt<R: Rng>(scene: &mut Scene, rng: &mut R, sigma_px: f64, outlier_count: usize) {
        let noise = Normal::new(0.0, sigma_px).unwrap();
        for pixel in &mut scene.image_points_px {
            pixel.x += noise.sample(rng);
            pixel.y += noise.sample(rng);
        }
        for pixel in scene.image_points_px.iter_mut().take(outlier_count) {
            *pixel = Vector2::new(rng.random_range(0.0..660.0), rng.random_range(0.0..470.0));
        }
    }

    /// Angle between two rotations in degrees.
    pub fn rotation_error_deg(a: &Rigid3, b: &Rigid3) -> f64 {
        a.rotation_angle_to_rad(b).to_degrees()
    }
}

#[cfg(test)]
mod robustness_tests {
    //! Hostile input: every solver returns (an error or a model), none panics.

    use super::test_scenes::{random_scene, test_intrinsics};
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn hostile_value<R: Rng>(rng: &mut R) -> f64 {
        const SPECIAL: [f64; 8] = [
            0.0,
            -0.0,
            1e300,
            -1e300,
            1e-300,
            f64::MIN_POSITIVE,
            1.0,
            1e8,
        ];
        if rng.random_bool(0.3) {
            SPECIAL[rng.random_range(0..SPECIAL.len())]
        } else {
            rng.random_range(-100.0..100.0)
        }
    }

    #[test]
    fn no_solver_panics_on_extreme_or_repeated_values() {
        let mut rng = ChaCha8Rng::seed_from_u64(77);
        let intrinsics = test_intrinsics();
        let ransac_config = RansacConfig {
            max_iterations: 20,
            ..RansacConfig::default()
        };
        for trial in 0..3000 {
            let count = rng.random_range(0..16);
            let mut image_points_px: Vec<Vector2<f64>> = (0..count)
                .map(|_| Vector2::new(hostile_value(&mut rng), hostile_value(&mut rng)))
                .collect();
            let world_points: Vec<Vector3<f64>> = (0..count)
                .map(|_| {
                    Vector3::new(
                        hostile_value(&mut rng),
                        hostile_value(&mut rng),
                        hostile_value(&mut rng),
                    )
                })
                .collect();
            if trial % 3 == 0 && count > 1 {
                let first = image_points_px[0];
                image_points_px.iter_mut().for_each(|p| *p = first);
            }
            let _ = dlt::solve(&image_points_px, &world_points);
            let _ = epnp::solve(&intrinsics, &image_points_px, &world_points);
            let _ = p3p::solve(&intrinsics, &image_points_px, &world_points);
            let _ = planarity::point_cloud_shape(&world_points);
            if let Ok(data) = Correspondences::new(&image_points_px, &world_points) {
                for prior in [
                    IntrinsicsPrior::Known(intrinsics),
                    IntrinsicsPrior::Unknown {
                        planar_fallback: Some(intrinsics),
                    },
                ] {
                    let config = PoseEstimationConfig {
                        ransac: ransac_config,
                        ..PoseEstimationConfig::default()
                    };
                    let _ = estimate_pose(&data, &prior, &config, &mut rng);
                }
            }
            let camera = CameraPose {
                intrinsics,
                cam_from_world: Rigid3::identity(),
            };
            for parameters in [
                RefinedParameters::Pose,
                RefinedParameters::IntrinsicsAndPose,
            ] {
                let _ = refine_camera(
                    &camera,
                    &image_points_px,
                    &world_points,
                    parameters,
                    &RefineConfig::default(),
                );
            }
        }
    }

    #[test]
    fn solvers_work_far_from_the_origin() {
        // World coordinates near a UTM origin (should have been shifted, but must still work).
        let mut rng = ChaCha8Rng::seed_from_u64(78);
        let scene = random_scene(&mut rng, test_intrinsics(), 50, 15.0);
        let offset = Vector3::new(5e5, 5e6, 300.0);
        let world_points: Vec<Vector3<f64>> =
            scene.world_points.iter().map(|p| p + offset).collect();
        let truth = scene
            .camera
            .cam_from_world
            .compose(&Rigid3::new(nalgebra::UnitQuaternion::identity(), -offset));
        let (_, pose) = dlt::solve(&scene.image_points_px, &world_points).unwrap();
        assert!(pose.rotation_angle_to_rad(&truth).to_degrees() < 1e-4);
        assert!((pose.camera_center() - truth.camera_center()).norm() < 1e-3);
        let pose = epnp::solve(
            &scene.camera.intrinsics,
            &scene.image_points_px,
            &world_points,
        )
        .unwrap();
        assert!(pose.rotation_angle_to_rad(&truth).to_degrees() < 1e-4);
        assert!((pose.camera_center() - truth.camera_center()).norm() < 1e-3);
    }
}
