//! How close a set of 3D points is to a plane (or a line).
//!
//! The paper's main failure is a view in which all visible points lie at similar depth: for such
//! (near-)planar points the 11-DoF DLT is singular (every `P + v·πᵀ`, π the plane, projects the
//! points the same way), so intrinsics cannot be recovered and the pose it gives is noise. The
//! measures here let the estimator refuse or switch solver, and let the verification report why a
//! frame failed.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use super::{exceeds, PoseError};
use crate::core::rigid::Rigid3;

/// The spread of a point cloud along its principal axes.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PointCloudShape {
    /// Standard deviations along the principal axes, largest first, in metres.
    pub principal_std_m: [f64; 3],
    /// Principal axes (unit vectors, world frame), in the order of `principal_std_m`; the last is
    /// the normal of the best-fitting plane.
    pub principal_axes: [Vector3<f64>; 3],
    /// Centroid of the points, world frame, metres.
    pub centroid_m: Vector3<f64>,
    /// `principal_std_m[2] / principal_std_m[0]`: 0 for exactly coplanar points, about 0.3–0.6 for
    /// a well spread 3D cloud. Thin = small.
    pub planarity_ratio: f64,
    /// `principal_std_m[1] / principal_std_m[0]`: 0 for collinear points.
    pub collinearity_ratio: f64,
}

/// Principal spread of `world_points`. Errors for fewer than 3 points, non-finite coordinates, or
/// points that all coincide.
pub fn point_cloud_shape(world_points: &[Vector3<f64>]) -> Result<PointCloudShape, PoseError> {
    if world_points.len() < 3 {
        return Err(PoseError::TooFewPoints {
            solver: "point cloud shape",
            needed: 3,
            got: world_points.len(),
        });
    }
    if let Some(index) = world_points
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(PoseError::NonFinite { index });
    }
    let count = world_points.len() as f64;
    let centroid_m = world_points.iter().sum::<Vector3<f64>>() / count;
    let mut covariance_m2 = Matrix3::zeros();
    for point in world_points {
        let centred = point - centroid_m;
        covariance_m2 += centred * centred.transpose();
    }
    covariance_m2 /= count;
    if !covariance_m2.iter().all(|v| v.is_finite()) {
        return Err(PoseError::Degenerate {
            why: "the spread of the 3D points overflows",
        });
    }
    let eigen =
        SymmetricEigen::try_new(covariance_m2, f64::EPSILON, 100).ok_or(PoseError::Degenerate {
            why: "the covariance of the 3D points did not diagonalise",
        })?;
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eigen.eigenvalues[b].total_cmp(&eigen.eigenvalues[a]));
    let principal_std_m = order.map(|i| eigen.eigenvalues[i].max(0.0).sqrt());
    let principal_axes = order.map(|i| eigen.eigenvectors.column(i).into_owned());
    if !exceeds(principal_std_m[0], 0.0) {
        return Err(PoseError::Degenerate {
            why: "all 3D points coincide",
        });
    }
    Ok(PointCloudShape {
        principal_std_m,
        principal_axes,
        centroid_m,
        planarity_ratio: principal_std_m[2] / principal_std_m[0],
        collinearity_ratio: principal_std_m[1] / principal_std_m[0],
    })
}

/// The points' spread in depth relative to their lateral spread, seen from a camera: the standard
/// deviation of the camera-frame z over the RMS distance from the mean in x and y. Small values
/// mean "everything at similar depth" (the paper's failure). Points behind the camera count too;
/// `None` for an empty set or when there is no lateral spread.
pub fn depth_relief_ratio(cam_from_world: &Rigid3, world_points: &[Vector3<f64>]) -> Option<f64> {
    if world_points.is_empty() {
        return None;
    }
    let count = world_points.len() as f64;
    let camera_points: Vec<Vector3<f64>> = world_points
        .iter()
        .map(|p| cam_from_world.transform_point(p))
        .collect();
    let mean = camera_points.iter().sum::<Vector3<f64>>() / count;
    let (mut depth_var, mut lateral_var) = (0.0, 0.0);
    for point in &camera_points {
        let d = point - mean;
        depth_var += d.z * d.z;
        lateral_var += d.x * d.x + d.y * d.y;
    }
    let ratio = (depth_var / lateral_var).sqrt();
    (lateral_var > 0.0 && ratio.is_finite()).then_some(ratio)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn planar_collinear_and_spread_clouds_are_told_apart() {
        let grid: Vec<Vector3<f64>> = (0..25)
            .map(|i| Vector3::new((i % 5) as f64, (i / 5) as f64, 0.0))
            .collect();
        let planar = point_cloud_shape(&grid).unwrap();
        assert!(planar.planarity_ratio < 1e-12);
        assert!(planar.collinearity_ratio > 0.9);
        assert!(
            planar.principal_axes[2].z.abs() > 1.0 - 1e-12,
            "normal is z"
        );

        let line: Vec<Vector3<f64>> = (0..10)
            .map(|i| Vector3::new(1.0, 2.0, 3.0) * i as f64)
            .collect();
        assert!(point_cloud_shape(&line).unwrap().collinearity_ratio < 1e-7);

        let cube: Vec<Vector3<f64>> = (0..27)
            .map(|i| Vector3::new((i % 3) as f64, ((i / 3) % 3) as f64, (i / 9) as f64))
            .collect();
        let spread = point_cloud_shape(&cube).unwrap();
        assert!((spread.planarity_ratio - 1.0).abs() < 1e-9);

        assert!(point_cloud_shape(&[Vector3::zeros(); 4]).is_err());
        assert_eq!(
            point_cloud_shape(&[
                Vector3::zeros(),
                Vector3::x(),
                Vector3::new(f64::NAN, 0.0, 0.0)
            ]),
            Err(PoseError::NonFinite { index: 2 })
        );
    }

    #[test]
    fn depth_relief_is_small_for_a_plane_facing_the_camera() {
        let grid: Vec<Vector3<f64>> = (0..25)
            .map(|i| Vector3::new((i % 5) as f64, (i / 5) as f64, 0.0))
            .collect();
        let nadir = Rigid3::look_at(
            &Vector3::new(2.0, 2.0, 50.0),
            &Vector3::new(2.0, 2.0, 0.0),
            &Vector3::y(),
        )
        .unwrap();
        assert!(depth_relief_ratio(&nadir, &grid).unwrap() < 1e-12);
        let oblique = Rigid3::look_at(
            &Vector3::new(40.0, 2.0, 30.0),
            &Vector3::new(2.0, 2.0, 0.0),
            &Vector3::z(),
        )
        .unwrap();
        assert!(depth_relief_ratio(&oblique, &grid).unwrap() > 0.3);
    }
}
