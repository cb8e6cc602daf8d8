//! The camera's orientation from a DJI gimbal's yaw, pitch and roll.
//!
//! **Convention.** DJI records the gimbal's attitude as Tait–Bryan angles in the local NED frame
//! (x north, y east, z down), applied yaw → pitch → roll: `R_ned_from_gimbal = Rz(yaw) · Ry(pitch)
//! · Rx(roll)`, with the gimbal frame x forward (the optical axis), y right, z down. Yaw is the
//! bearing of the optical axis from **true** north, clockwise (east = +90°); pitch is the axis's
//! elevation, −90° = nadir; roll turns about the axis, clockwise seen from behind. At yaw = pitch
//! = roll = 0 the camera looks north, level, its image x pointing east and y down. The camera frame
//! is COLMAP's (x right, y down, z forward), so `x_cam = y_gimbal`, `y_cam = z_gimbal`,
//! `z_cam = x_gimbal`. The world is the local UTM frame (X east, Y north, Z up), so
//! `X = y_ned`, `Y = x_ned`, `Z = −z_ned`, and `cam_from_world` is the transpose of
//! `P_enu_from_ned · R_ned_from_gimbal · P_gimbal_from_cam`.
//!
//! UTM's Y axis is grid north, which differs from true north by the meridian convergence γ
//! (`utm::UtmPoint::convergence_deg`, 0.73° at Brighton Beach): a bearing α from true north is
//! α − γ from grid north. `asgreg priors` corrects it by default; without the correction
//! (`convergence_deg` = 0, `--no-meridian-convergence`) the priors equal the shared Brighton Beach
//! set's `prior_pose_from_exif.txt` (< 0.00001°), with it they differ from that file by γ and are
//! closer to its ground truth: mean rotation error over the 12 photos with a right yaw
//! 3.66° → 3.11°, max 4.62° → 3.95° (`shared_data_priors_against_ground_truth_…`).
//!
//! **Why the gimbal angles and not the flight angles.** The camera hangs on a 3-axis stabilised
//! gimbal: its attitude is what the gimbal reports, while the aircraft's (`FlightYaw/Pitch/Roll`)
//! tilts several degrees with wind and acceleration, which the gimbal takes out. The flight yaw is
//! also only the body's heading; a gimbal may yaw relative to it. (Neither is reliable on every
//! drone: on the Brighton set's return leg both yaws are 180° off the image's heading.)

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};

/// Yaw, pitch, roll in degrees (DJI's gimbal or flight attitude, NED, yaw from true north).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Attitude {
    pub yaw_deg: f64,
    pub pitch_deg: f64,
    pub roll_deg: f64,
}

/// `cam_from_world` rotation of a camera with the given gimbal attitude, in the local frame
/// (X east, Y north, Z up; see the module's convention). `convergence_deg` is the meridian
/// convergence to subtract from the yaw (grid bearing = true bearing − γ), or 0 for none.
pub fn cam_from_world_rotation(gimbal: Attitude, convergence_deg: f64) -> UnitQuaternion<f64> {
    let yaw = (gimbal.yaw_deg - convergence_deg).to_radians();
    let ned_from_gimbal = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw)
        * Rotation3::from_axis_angle(&Vector3::y_axis(), gimbal.pitch_deg.to_radians())
        * Rotation3::from_axis_angle(&Vector3::x_axis(), gimbal.roll_deg.to_radians());
    // Columns: the camera's x, y, z axes in gimbal coordinates (right, down, forward).
    let gimbal_from_cam = Matrix3::new(0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0);
    // Rows: east, north, up from NED.
    let enu_from_ned = Matrix3::new(0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, -1.0);
    let world_from_cam = enu_from_ned * ned_from_gimbal.matrix() * gimbal_from_cam;
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
        world_from_cam.transpose(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn world_from_cam(yaw: f64, pitch: f64, roll: f64) -> Matrix3<f64> {
        let attitude = Attitude {
            yaw_deg: yaw,
            pitch_deg: pitch,
            roll_deg: roll,
        };
        cam_from_world_rotation(attitude, 0.0)
            .to_rotation_matrix()
            .matrix()
            .transpose()
    }

    fn assert_axis(actual: Vector3<f64>, expected: [f64; 3], what: &str) {
        assert!(
            (actual - Vector3::from(expected)).norm() < 1e-12,
            "{what}: {actual:?} vs {expected:?}"
        );
    }

    /// The convention spelled out on the axes: where the optical axis (z) and the image's right
    /// (x) and down (y) point in the world (X east, Y north, Z up).
    #[test]
    fn gimbal_angles_point_the_camera_as_documented() {
        // Level, looking north: right = east, down = down.
        let r = world_from_cam(0.0, 0.0, 0.0);
        assert_axis(r.column(2).into(), [0.0, 1.0, 0.0], "level north: forward");
        assert_axis(r.column(0).into(), [1.0, 0.0, 0.0], "level north: right");
        assert_axis(r.column(1).into(), [0.0, 0.0, -1.0], "level north: down");
        // Yaw 90: looking east, right = south.
        let r = world_from_cam(90.0, 0.0, 0.0);
        assert_axis(r.column(2).into(), [1.0, 0.0, 0.0], "yaw 90: forward");
        assert_axis(r.column(0).into(), [0.0, -1.0, 0.0], "yaw 90: right");
        // Pitch −90 (nadir) at yaw 0: looking down, the image's top (−y) points north, right east.
        let r = world_from_cam(0.0, -90.0, 0.0);
        assert_axis(r.column(2).into(), [0.0, 0.0, -1.0], "nadir: forward");
        assert_axis(r.column(0).into(), [1.0, 0.0, 0.0], "nadir: right");
        assert_axis(
            r.column(1).into(),
            [0.0, -1.0, 0.0],
            "nadir: down (image top = north)",
        );
        // Pitch +30: looking up, north.
        let r = world_from_cam(0.0, 30.0, 0.0);
        let s = 30f64.to_radians();
        assert_axis(
            r.column(2).into(),
            [0.0, s.cos(), s.sin()],
            "pitch 30: forward",
        );
        // Roll +90 at level north: clockwise seen from behind, the image's right turns down.
        let r = world_from_cam(0.0, 0.0, 90.0);
        assert_axis(r.column(0).into(), [0.0, 0.0, -1.0], "roll 90: right");
        assert_axis(r.column(2).into(), [0.0, 1.0, 0.0], "roll 90: forward");
    }

    /// The convergence only turns the yaw: correcting by γ equals a yaw of yaw − γ, i.e. a
    /// rotation by +γ about the world's up axis (counter-clockwise seen from above).
    #[test]
    fn convergence_turns_the_camera_about_the_vertical() {
        let gimbal = Attitude {
            yaw_deg: 45.0,
            pitch_deg: -89.9,
            roll_deg: 0.3,
        };
        let corrected = cam_from_world_rotation(gimbal, 0.73);
        let plain = cam_from_world_rotation(
            Attitude {
                yaw_deg: 44.27,
                ..gimbal
            },
            0.0,
        );
        assert!(corrected.angle_to(&plain) < 1e-12);
        let about_up = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.73_f64.to_radians());
        // world_from_cam' = Rz(γ) · world_from_cam, so cam_from_world' = cam_from_world · Rz(−γ).
        let turned = cam_from_world_rotation(gimbal, 0.0) * about_up.inverse();
        assert!(corrected.angle_to(&turned) < 1e-12);
    }
}
