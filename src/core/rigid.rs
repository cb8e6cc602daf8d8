//! Rigid transforms in f64: camera poses are `cam_from_world` (COLMAP's convention,
//! `x_cam = R · x_world + t`), and every pose in asgreg is one of these.

use nalgebra::{Matrix3, Rotation3, Unit, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// A rotation followed by a translation: `b_from_a · x_a = R · x_a + t`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Rigid3 {
    pub rotation: UnitQuaternion<f64>,
    pub translation: Vector3<f64>,
}

impl Default for Rigid3 {
    fn default() -> Self {
        Self::identity()
    }
}

impl Rigid3 {
    pub fn identity() -> Self {
        Self {
            rotation: UnitQuaternion::identity(),
            translation: Vector3::zeros(),
        }
    }

    pub fn new(rotation: UnitQuaternion<f64>, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
        }
    }

    /// From COLMAP's `QW QX QY QZ TX TY TZ` (the quaternion is normalised here).
    pub fn from_colmap(qvec_wxyz: [f64; 4], tvec: [f64; 3]) -> Self {
        let [w, x, y, z] = qvec_wxyz;
        Self {
            rotation: UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z)),
            translation: Vector3::from(tvec),
        }
    }

    /// COLMAP's `(QW, QX, QY, QZ)`, with `QW >= 0` as COLMAP writes it.
    pub fn colmap_qvec(&self) -> [f64; 4] {
        let q = self.rotation.quaternion();
        let sign = if q.w < 0.0 { -1.0 } else { 1.0 };
        [sign * q.w, sign * q.i, sign * q.j, sign * q.k]
    }

    pub fn from_rotation_matrix(rotation: &Matrix3<f64>, translation: Vector3<f64>) -> Self {
        Self {
            rotation: UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(rotation)),
            translation,
        }
    }

    pub fn rotation_matrix(&self) -> Matrix3<f64> {
        self.rotation.to_rotation_matrix().into_inner()
    }

    pub fn transform_point(&self, point: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * point + self.translation
    }

    pub fn transform_vector(&self, vector: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * vector
    }

    pub fn inverse(&self) -> Self {
        let rotation = self.rotation.inverse();
        Self {
            rotation,
            translation: -(rotation * self.translation),
        }
    }

    /// `self ∘ other`: first `other`, then `self` (`c_from_a = c_from_b.compose(&b_from_a)`).
    pub fn compose(&self, other: &Rigid3) -> Self {
        Self {
            rotation: self.rotation * other.rotation,
            translation: self.rotation * other.translation + self.translation,
        }
    }

    /// For a `cam_from_world` pose: the camera centre in world coordinates, `-Rᵀ t`.
    pub fn camera_center(&self) -> Vector3<f64> {
        -(self.rotation.inverse() * self.translation)
    }

    /// A `cam_from_world` pose for a camera at `eye` looking at `target`, image "up" towards
    /// `world_up` (camera y points down, so it is `-world_up` projected onto the image plane).
    /// `None` when the view direction is parallel to `world_up` or `eye == target`.
    pub fn look_at(
        eye: &Vector3<f64>,
        target: &Vector3<f64>,
        world_up: &Vector3<f64>,
    ) -> Option<Self> {
        let forward = Unit::try_new(target - eye, 1e-12)?;
        let right = Unit::try_new(forward.cross(world_up), 1e-9)?;
        let down = forward.cross(&right);
        // Rows of R are the camera axes expressed in world coordinates.
        let rotation =
            Matrix3::from_rows(&[right.transpose(), down.transpose(), forward.transpose()]);
        let rotation =
            UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rotation));
        Some(Self {
            rotation,
            translation: -(rotation * eye),
        })
    }

    pub fn is_finite(&self) -> bool {
        let q = self.rotation.quaternion();
        q.coords.iter().all(|v| v.is_finite()) && self.translation.iter().all(|v| v.is_finite())
    }

    /// The angle of the relative rotation between two poses, in radians.
    pub fn rotation_angle_to_rad(&self, other: &Rigid3) -> f64 {
        self.rotation.angle_to(&other.rotation)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_and_compose_agree() {
        let pose = Rigid3::new(
            UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1),
            Vector3::new(1.0, -2.0, 3.0),
        );
        let point = Vector3::new(0.4, 5.0, -7.0);
        let identity = pose.compose(&pose.inverse());
        assert!((identity.transform_point(&point) - point).norm() < 1e-12);
        assert!(
            (pose
                .inverse()
                .transform_point(&pose.transform_point(&point))
                - point)
                .norm()
                < 1e-12
        );
    }

    #[test]
    fn look_at_puts_target_on_the_optical_axis_with_y_down() {
        let eye = Vector3::new(10.0, -5.0, 8.0);
        let target = Vector3::new(0.0, 0.0, 0.0);
        let up = Vector3::z();
        let pose = Rigid3::look_at(&eye, &target, &up).unwrap();
        let target_cam = pose.transform_point(&target);
        assert!(target_cam.x.abs() < 1e-12 && target_cam.y.abs() < 1e-12 && target_cam.z > 0.0);
        // A point above the target appears higher in the image: smaller y.
        let above_cam = pose.transform_point(&Vector3::new(0.0, 0.0, 1.0));
        assert!(above_cam.y < 0.0);
        assert!((pose.camera_center() - eye).norm() < 1e-12);
        assert!(Rigid3::look_at(&eye, &eye, &up).is_none());
    }

    #[test]
    fn colmap_quaternion_round_trips_with_positive_w() {
        let pose = Rigid3::from_colmap([-0.5, 0.5, -0.5, 0.5], [1.0, 2.0, 3.0]);
        let q = pose.colmap_qvec();
        assert!(q[0] >= 0.0);
        let again = Rigid3::from_colmap(q, [1.0, 2.0, 3.0]);
        assert!(again.rotation.angle_to(&pose.rotation) < 1e-12);
    }
}
