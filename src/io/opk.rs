//! Omega-phi-kappa export: camera positions and orientations as GIS and photogrammetry packages
//! (Pix4D, Agisoft Metashape, ArcGIS ortho mapping, PATB-style bundle adjusters) import them.
//!
//! The file is CSV with the header `name,X,Y,Z,omega_deg,phi_deg,kappa_deg` and one row per image:
//! `X, Y, Z` the projection centre in the world frame of the poses, which in asgreg is the frame of
//! the mesh file (georeferenced meshes, e.g. UTM, keep their coordinates: the mesh's f64 local
//! origin is internal to rendering and poses never hold it), and the angles in degrees.
//!
//! Convention (the photogrammetric one of PATB, Pix4D and Metashape): the world frame is
//! right-handed with Z up (X east, Y north for a projected CRS). The image frame has x to the
//! right of the image, y towards its top and z backwards, so the camera looks along −z. The
//! rotation `R = R_x(ω) · R_y(φ) · R_z(κ)` takes image-frame vectors to the world frame
//! (`v_world = R · v_image`, its columns are the image axes in world coordinates); equivalently,
//! the world axes rotated by ω about X, then φ about the new Y, then κ about the newest Z, become
//! the image axes. A point projects as `x_image = Rᵀ · (X_world − C)`. A nadir photo whose top
//! points north has ω = φ = κ = 0; positive ω tilts the view towards north (the image top),
//! positive φ towards west, positive κ turns the image counter-clockwise seen from above (its
//! top towards west). COLMAP's camera frame (x right, y down, z forward) is the image frame with
//! y and z flipped, so `R = R_colmapᵀ · diag(1, −1, −1)` with `R_colmap` the rotation of
//! `cam_from_world`. Ranges: ω, κ in (−180°, 180°], φ in [−90°, 90°]; at φ = ±90° (the optical axis
//! horizontal along X) ω and κ are not separable and ω is reported as 0.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};

use crate::core::rigid::Rigid3;
use crate::io::colmap::ImagePose;

/// File name of the export in `asgreg register`'s output folder.
pub const OPK_FILE: &str = "poses_opk.csv";

/// The CSV header.
pub const OPK_HEADER: &str = "name,X,Y,Z,omega_deg,phi_deg,kappa_deg";

/// `diag(1, −1, −1)`: COLMAP camera axes ↔ photogrammetric image axes (its own inverse).
fn flip_yz() -> Matrix3<f64> {
    Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))
}

/// Errors of writing the export.
#[derive(Debug, thiserror::Error)]
pub enum OpkError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: image {image_id} ('{name}'): {why}", path.display())]
    InvalidImage {
        path: PathBuf,
        image_id: u32,
        name: String,
        why: String,
    },
}

/// Omega, phi, kappa in degrees (see the module docs for the convention).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Opk {
    pub omega_deg: f64,
    pub phi_deg: f64,
    pub kappa_deg: f64,
}

/// `R = R_x(ω) · R_y(φ) · R_z(κ)`, image frame → world frame.
pub fn rotation_from_opk(opk: &Opk) -> Matrix3<f64> {
    let axis = |axis: Vector3<f64>, angle_deg: f64| {
        Rotation3::from_axis_angle(&nalgebra::Unit::new_unchecked(axis), angle_deg.to_radians())
            .into_inner()
    };
    axis(Vector3::x(), opk.omega_deg)
        * axis(Vector3::y(), opk.phi_deg)
        * axis(Vector3::z(), opk.kappa_deg)
}

/// The angles of an image → world rotation `R = R_x(ω) · R_y(φ) · R_z(κ)`.
pub fn opk_from_rotation(world_from_image: &Matrix3<f64>) -> Opk {
    let r = world_from_image;
    // R = [[cφcκ, −cφsκ, sφ], [cωsκ + sωsφcκ, cωcκ − sωsφsκ, −sωcφ],
    //      [sωsκ − cωsφcκ, sωcκ + cωsφsκ, cωcφ]]
    let cos_phi = r[(1, 2)].hypot(r[(2, 2)]);
    let phi = r[(0, 2)].atan2(cos_phi);
    let (omega, kappa) = if cos_phi > 1e-12 {
        ((-r[(1, 2)]).atan2(r[(2, 2)]), (-r[(0, 1)]).atan2(r[(0, 0)]))
    } else {
        // φ = ±90°: only κ ± ω is determined; with ω = 0, R[1][0] = sin κ, R[1][1] = cos κ.
        (0.0, r[(1, 0)].atan2(r[(1, 1)]))
    };
    Opk {
        omega_deg: normalised_deg(omega.to_degrees()),
        phi_deg: phi.to_degrees(),
        kappa_deg: normalised_deg(kappa.to_degrees()),
    }
}

/// An angle in (−180°, 180°], without a negative zero.
fn normalised_deg(angle_deg: f64) -> f64 {
    let angle = if angle_deg <= -180.0 {
        angle_deg + 360.0
    } else {
        angle_deg
    };
    if angle == 0.0 {
        0.0
    } else {
        angle
    }
}

/// Omega, phi, kappa of a COLMAP `cam_from_world` pose.
pub fn opk_from_cam_from_world(cam_from_world: &Rigid3) -> Opk {
    opk_from_rotation(&(cam_from_world.rotation_matrix().transpose() * flip_yz()))
}

/// The COLMAP `cam_from_world` pose of a camera at `centre` with orientation `opk`.
pub fn cam_from_world_from_opk(centre: &Vector3<f64>, opk: &Opk) -> Rigid3 {
    let cam_from_world = flip_yz() * rotation_from_opk(opk).transpose();
    let rotation =
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(cam_from_world));
    Rigid3::new(rotation, -(rotation * centre))
}

/// The export as text: the header and one row per image, in the order given. Numbers are written
/// in Rust's shortest form that reads back to the same `f64` (never in exponent notation); names
/// are quoted as RFC 4180 says when they hold a comma, a quote or a line break.
pub fn format_opk_csv(path: &Path, images: &[ImagePose]) -> Result<String, OpkError> {
    let mut text = String::with_capacity(64 * (images.len() + 1));
    text.push_str(OPK_HEADER);
    text.push('\n');
    for image in images {
        if !image.cam_from_world.is_finite() {
            return Err(OpkError::InvalidImage {
                path: path.to_path_buf(),
                image_id: image.image_id,
                name: image.name.clone(),
                why: "the pose is not finite".to_string(),
            });
        }
        let centre = image.cam_from_world.camera_center();
        let opk = opk_from_cam_from_world(&image.cam_from_world);
        let _ = writeln!(
            text,
            "{},{},{},{},{},{},{}",
            csv_field(&image.name),
            plain(centre.x),
            plain(centre.y),
            plain(centre.z),
            plain(opk.omega_deg),
            plain(opk.phi_deg),
            plain(opk.kappa_deg)
        );
    }
    Ok(text)
}

/// Writes the export to `path` ([`format_opk_csv`]).
pub fn write_opk_csv(path: &Path, images: &[ImagePose]) -> Result<(), OpkError> {
    let text = format_opk_csv(path, images)?;
    std::fs::write(path, text).map_err(|source| OpkError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// A number without a negative zero.
fn plain(value: f64) -> f64 {
    if value == 0.0 {
        0.0
    } else {
        value
    }
}

fn csv_field(text: &str) -> String {
    if text.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", text.replace('"', "\"\""))
    } else {
        text.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EPS_DEG: f64 = 1e-9;

    fn assert_opk(opk: Opk, omega_deg: f64, phi_deg: f64, kappa_deg: f64) {
        // Compared on the circle: 180° and −179.999999999998° are the same angle.
        let close = |a: f64, b: f64| {
            let difference = (a - b).rem_euclid(360.0);
            difference.min(360.0 - difference) < EPS_DEG
        };
        assert!(
            close(opk.omega_deg, omega_deg)
                && close(opk.phi_deg, phi_deg)
                && close(opk.kappa_deg, kappa_deg),
            "got {opk:?}, expected ({omega_deg}, {phi_deg}, {kappa_deg})"
        );
    }

    /// A camera 300 m above a UTM point looking at `target_offset` from the point below it, image
    /// top towards `up` (COLMAP's look-at).
    fn camera(target_offset: Vector3<f64>, up: Vector3<f64>) -> Rigid3 {
        let eye = Vector3::new(576_700.0, 5_188_100.0, 500.0);
        let target = eye + Vector3::new(0.0, 0.0, -300.0) + target_offset;
        Rigid3::look_at(&eye, &target, &up).unwrap()
    }

    #[test]
    fn nadir_image_with_top_north_is_zero() {
        let pose = camera(Vector3::zeros(), Vector3::y());
        let opk = opk_from_cam_from_world(&pose);
        assert_opk(opk, 0.0, 0.0, 0.0);
        // Exactly zero, without a negative zero, as written.
        let images = [ImagePose {
            image_id: 1,
            camera_id: 1,
            name: "nadir.jpg".to_string(),
            // COLMAP's rotation diag(1, −1, −1): 180° about x.
            cam_from_world: Rigid3::from_colmap(
                [0.0, 1.0, 0.0, 0.0],
                [-576_700.0, 5_188_100.0, 500.0],
            ),
        }];
        let text = format_opk_csv(Path::new("poses_opk.csv"), &images).unwrap();
        assert_eq!(
            text,
            "name,X,Y,Z,omega_deg,phi_deg,kappa_deg\nnadir.jpg,576700,5188100,500,0,0,0\n"
        );
    }

    /// The sign of each angle, one at a time: the sense the module docs state.
    #[test]
    fn each_angle_has_the_documented_sense() {
        let tilt = 10f64.to_radians().tan() * 300.0;
        // Image top towards east: the image turned clockwise seen from above, κ = −90°.
        assert_opk(
            opk_from_cam_from_world(&camera(Vector3::zeros(), Vector3::x())),
            0.0,
            0.0,
            -90.0,
        );
        // Image top towards west: κ = +90°; towards south: κ = 180°.
        assert_opk(
            opk_from_cam_from_world(&camera(Vector3::zeros(), -Vector3::x())),
            0.0,
            0.0,
            90.0,
        );
        assert_opk(
            opk_from_cam_from_world(&camera(Vector3::zeros(), -Vector3::y())),
            0.0,
            0.0,
            180.0,
        );
        // Looking 10° north of nadir, top north: ω = +10°.
        assert_opk(
            opk_from_cam_from_world(&camera(Vector3::new(0.0, tilt, 0.0), Vector3::y())),
            10.0,
            0.0,
            0.0,
        );
        // Looking 10° west of nadir, top north: φ = +10°.
        assert_opk(
            opk_from_cam_from_world(&camera(Vector3::new(-tilt, 0.0, 0.0), Vector3::y())),
            0.0,
            10.0,
            0.0,
        );
    }

    #[test]
    fn rotation_is_rx_ry_rz_in_closed_form() {
        let opk = Opk {
            omega_deg: 12.0,
            phi_deg: -7.5,
            kappa_deg: 133.0,
        };
        let (sw, cw) = opk.omega_deg.to_radians().sin_cos();
        let (sp, cp) = opk.phi_deg.to_radians().sin_cos();
        let (sk, ck) = opk.kappa_deg.to_radians().sin_cos();
        #[rustfmt::skip]
        let expected = Matrix3::new(
            cp * ck,                -cp * sk,                sp,
            cw * sk + sw * sp * ck, cw * ck - sw * sp * sk,  -sw * cp,
            sw * sk - cw * sp * ck, sw * ck + cw * sp * sk,  cw * cp,
        );
        assert!((rotation_from_opk(&opk) - expected).amax() < 1e-15);
    }

    #[test]
    fn angles_and_poses_round_trip() {
        let centre = Vector3::new(576_712.25, 5_188_163.5, 198.5);
        for omega_deg in [-179.0, -60.0, -1.0, 0.0, 2.5, 45.0, 170.0] {
            for phi_deg in [-89.0, -30.0, 0.0, 0.5, 60.0, 89.9] {
                for kappa_deg in [-179.9, -90.0, -45.0, 0.0, 30.0, 135.0, 180.0] {
                    let opk = Opk {
                        omega_deg,
                        phi_deg,
                        kappa_deg,
                    };
                    let again = opk_from_rotation(&rotation_from_opk(&opk));
                    assert_opk(again, omega_deg, phi_deg, kappa_deg);

                    let pose = cam_from_world_from_opk(&centre, &opk);
                    assert!((pose.camera_center() - centre).amax() < 1e-7);
                    assert_opk(
                        opk_from_cam_from_world(&pose),
                        omega_deg,
                        phi_deg,
                        kappa_deg,
                    );
                }
            }
        }
        // Gimbal lock: the rotation is still reproduced, with ω = 0.
        for phi_deg in [90.0, -90.0] {
            let opk = Opk {
                omega_deg: 20.0,
                phi_deg,
                kappa_deg: 30.0,
            };
            let rotation = rotation_from_opk(&opk);
            let again = opk_from_rotation(&rotation);
            assert_eq!(again.omega_deg, 0.0);
            assert!((again.phi_deg - phi_deg).abs() < 1e-6);
            assert!((rotation_from_opk(&again) - rotation).amax() < 1e-12);
        }
    }

    /// The real Brighton Beach ground truth: 18 nadir photos (gimbal pitch −89.9° to −90°) whose
    /// top points along the gimbal yaw of their EXIF, except DJI_0024–0029, whose recorded yaw is
    /// 180° off (the photos keep the outbound heading; `tests/data/brighton_beach/README.md`).
    /// So ω and φ are small and κ = −yaw (yaw clockwise from north, κ counter-clockwise), within
    /// the 2.3–4.6° the EXIF attitude is off by and the 0.7° grid convergence.
    #[test]
    fn brighton_beach_ground_truth_matches_the_gimbal_yaw() {
        // GimbalYawDegree from the photos' EXIF (../shared/data/brighton_beach/exif_gps_imu.csv).
        const YAW_DEG: [(&str, f64); 18] = [
            ("DJI_0018.JPG", 45.0),
            ("DJI_0019.JPG", 42.8),
            ("DJI_0020.JPG", 44.2),
            ("DJI_0021.JPG", 45.0),
            ("DJI_0022.JPG", 45.3),
            ("DJI_0023.JPG", 43.8),
            ("DJI_0024.JPG", -140.0),
            ("DJI_0025.JPG", -132.0),
            ("DJI_0026.JPG", -132.0),
            ("DJI_0027.JPG", -131.3),
            ("DJI_0028.JPG", -133.5),
            ("DJI_0029.JPG", -131.4),
            ("DJI_0030.JPG", 44.2),
            ("DJI_0031.JPG", 41.4),
            ("DJI_0032.JPG", 42.0),
            ("DJI_0033.JPG", 42.9),
            ("DJI_0034.JPG", 44.7),
            ("DJI_0035.JPG", 45.3),
        ];
        let model = crate::io::colmap::read_model(&crate::test_data::repo_data(
            "brighton_beach/gt_undistorted",
        ))
        .unwrap();
        let text = format_opk_csv(Path::new("poses_opk.csv"), &model.images).unwrap();
        let rows: Vec<&str> = text.lines().skip(1).collect();
        assert_eq!(rows.len(), 18);
        for (name, yaw_deg) in YAW_DEG {
            let row = rows
                .iter()
                .find(|row| row.starts_with(&format!("{name},")))
                .unwrap();
            let values: Vec<f64> = row.split(',').skip(1).map(|v| v.parse().unwrap()).collect();
            let [x, y, z, omega, phi, kappa] = values[..] else {
                panic!("{row}")
            };
            let heading_flipped = (24..=29).contains(&name[4..8].parse::<u32>().unwrap());
            let true_yaw = if heading_flipped {
                yaw_deg + 180.0
            } else {
                yaw_deg
            };
            let kappa_error = normalised_deg(kappa + true_yaw).abs();
            println!(
                "{name}: ω {omega:.2} φ {phi:.2} κ {kappa:.2} (−yaw {:.1}): {kappa_error:.2}°",
                -true_yaw
            );
            assert!(omega.abs() < 5.0 && phi.abs() < 5.0, "{row}");
            assert!(kappa_error < 6.0, "{row}: κ {kappa_error:.2}° from −yaw");
            // The centres are ~40 m above the ground, in the file's UTM-minus-offset frame.
            assert!(
                x.abs() < 100.0 && y.abs() < 150.0 && z > 180.0 && z < 220.0,
                "{row}"
            );
        }
        // DJI_0025's GPS centre (gps_ref_utm_local.txt: 18.822 83.806 198.509), 0.5 m residual.
        let row = rows
            .iter()
            .find(|row| row.starts_with("DJI_0025.JPG,"))
            .unwrap();
        let values: Vec<f64> = row
            .split(',')
            .skip(1)
            .take(3)
            .map(|v| v.parse().unwrap())
            .collect();
        let gps = [18.822, 83.806, 198.509];
        let distance = values
            .iter()
            .zip(gps)
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            .sqrt();
        assert!(distance < 2.0, "{row}: {distance:.2} m from GPS");
    }

    #[test]
    fn names_are_quoted_and_bad_poses_refused() {
        let mut image = ImagePose {
            image_id: 3,
            camera_id: 1,
            name: "flight \"A\", 2/img.jpg".to_string(),
            cam_from_world: Rigid3::identity(),
        };
        let text = format_opk_csv(Path::new("o.csv"), std::slice::from_ref(&image)).unwrap();
        assert!(
            text.lines()
                .nth(1)
                .unwrap()
                .starts_with("\"flight \"\"A\"\", 2/img.jpg\",0,0,0,"),
            "{text}"
        );
        image.cam_from_world.translation.x = f64::NAN;
        let error = format_opk_csv(Path::new("o.csv"), &[image]).unwrap_err();
        assert!(error.to_string().contains("o.csv: image 3"), "{error}");

        let dir = tempfile::tempdir().unwrap();
        let error = write_opk_csv(&dir.path().join("no/such/dir.csv"), &[]).unwrap_err();
        assert!(error.to_string().contains("dir.csv"), "{error}");
    }
}
