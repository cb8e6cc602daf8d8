//! `asgreg priors` on the repository's Brighton Beach crop (EXIF with GPS and the DJI maker note,
//! no XMP) and on made-up photos: the model it writes, the offset file round trip, and errors that
//! name the file and the field.

use std::path::Path;

use asgreg::core::rigid::Rigid3;
use asgreg::io::colmap::read_model;
use nalgebra::Vector3;

use crate::util::*;

/// The shared set's `prior_pose_from_exif.txt` line and `gps_ref_utm_local.txt` centre of
/// DJI_0025 (the crop's photo): no convergence correction, frame UTM 15N − (576700, 5188100).
const PRIOR_0025: ([f64; 4], [f64; 3]) = (
    [0.000354945, 0.406736488, 0.913545110, -0.000797219],
    [-49.6856, -69.7181, 198.6310],
);
const CENTRE_0025_M: [f64; 3] = [18.822, 83.806, 198.509];

fn crop_folder(dir: &Path) -> std::path::PathBuf {
    let images = dir.join("images");
    std::fs::create_dir(&images).unwrap();
    std::fs::copy(
        repo_data("brighton_beach/DJI_0025_crop.jpg"),
        images.join("DJI_0025_crop.jpg"),
    )
    .unwrap();
    images
}

/// A small grey JPEG without any metadata.
fn write_bare_jpeg(path: &Path) {
    let pixels = vec![128u8; 32 * 16];
    let mut bytes = Vec::new();
    image::codecs::jpeg::JpegEncoder::new(&mut bytes)
        .encode(&pixels, 32, 16, image::ExtendedColorType::L8)
        .unwrap();
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn priors_of_the_crop_equal_the_shared_sets_prior_and_the_offset_file_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let images = crop_folder(dir.path());
    let out = dir.path().join("out");
    let output = asgreg(&[
        "priors",
        "--images",
        path_str(&images),
        "--out",
        path_str(&out),
        "--offset-e",
        "576700",
        "--offset-n",
        "5188100",
        "--no-meridian-convergence",
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let printed = stdout(&output);
    assert!(
        printed.contains("DJI_0025_crop.jpg") && printed.contains("maker note"),
        "{printed}"
    );
    assert!(printed.contains("-132.00"), "{printed}");

    let model = read_model(&out).unwrap();
    assert_eq!(model.images.len(), 1);
    let pose = &model.images[0].cam_from_world;
    let (q, t) = PRIOR_0025;
    let reference = Rigid3::from_colmap(q, t);
    let angle_deg = pose.rotation_angle_to_rad(&reference).to_degrees();
    assert!(
        angle_deg < 0.01,
        "rotation {angle_deg}° from prior_pose_from_exif.txt"
    );
    let centre = pose.camera_center();
    assert!(
        (centre - Vector3::from(CENTRE_0025_M)).norm() < 0.01,
        "{centre:?}"
    );
    assert!(
        (centre - reference.camera_center()).norm() < 0.01,
        "{centre:?}"
    );
    // The crop is 240×136; EXIF's 3.61 mm on the FC300S's 6.17 mm sensor, scaled to that width.
    let camera = &model.cameras[&model.images[0].camera_id];
    assert_eq!((camera.width_px, camera.height_px), (240, 136));
    assert!((camera.intrinsics.fx_px - 3.61 / 6.17 * 240.0).abs() < 1e-9);

    let offset = std::fs::read_to_string(out.join("utm_offset.txt")).unwrap();
    assert!(
        offset.contains("zone 15N") && offset.contains("easting_m 576700"),
        "{offset}"
    );

    // Default: the convergence is corrected (0.73° about the vertical), and the offset file of the
    // first run gives the same frame.
    let again = dir.path().join("again");
    let offset_file = out.join("utm_offset.txt");
    let output = asgreg(&[
        "priors",
        "--images",
        path_str(&images),
        "--out",
        path_str(&again),
        "--offset-file",
        path_str(&offset_file),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let corrected = read_model(&again).unwrap();
    let turned = &corrected.images[0].cam_from_world;
    let angle_deg = turned.rotation_angle_to_rad(pose).to_degrees();
    assert!((0.73..0.74).contains(&angle_deg), "{angle_deg}");
    assert!((turned.camera_center() - centre).norm() < 1e-6);
}

#[test]
fn photos_without_metadata_need_a_csv_and_bad_csvs_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let images = dir.path().join("images");
    std::fs::create_dir(&images).unwrap();
    write_bare_jpeg(&images.join("bare.jpg"));
    let out = dir.path().join("out");
    let output = asgreg(&[
        "priors",
        "--images",
        path_str(&images),
        "--out",
        path_str(&out),
    ]);
    assert_fails_naming(&output, &["bare.jpg", "GPS", "--exif-csv"]);

    let csv = dir.path().join("exif.csv");
    std::fs::write(
        &csv,
        "FileName,GPSLatitude,GPSLongitude,GPSAltitude,GimbalPitchDegree,GimbalRollDegree\n",
    )
    .unwrap();
    let output = asgreg(&[
        "priors",
        "--images",
        path_str(&images),
        "--out",
        path_str(&out),
        "--exif-csv",
        path_str(&csv),
    ]);
    assert_fails_naming(&output, &["exif.csv", "GimbalYawDegree"]);

    std::fs::write(
        &csv,
        "FileName,GPSLatitude,GPSLongitude,GPSAltitude,GimbalYawDegree,GimbalPitchDegree,GimbalRollDegree,FocalLengthIn35mmFormat\n\
         other.jpg,46.84,-91.99,198,0,-90,0,20\n",
    )
    .unwrap();
    let output = asgreg(&[
        "priors",
        "--images",
        path_str(&images),
        "--out",
        path_str(&out),
        "--exif-csv",
        path_str(&csv),
    ]);
    assert_fails_naming(&output, &["bare.jpg", "no row", "exif.csv"]);

    std::fs::write(
        &csv,
        "FileName,GPSLatitude,GPSLongitude,GPSAltitude,GimbalYawDegree,GimbalPitchDegree,GimbalRollDegree,FocalLengthIn35mmFormat\n\
         bare.jpg,46.84,-91.99,198,0,-90,0,twenty\n",
    )
    .unwrap();
    let output = asgreg(&[
        "priors",
        "--images",
        path_str(&images),
        "--out",
        path_str(&out),
        "--exif-csv",
        path_str(&csv),
    ]);
    assert_fails_naming(
        &output,
        &["exif.csv", "line 2", "FocalLengthIn35mmFormat", "twenty"],
    );

    std::fs::write(
        &csv,
        std::fs::read_to_string(&csv)
            .unwrap()
            .replace("twenty", "36"),
    )
    .unwrap();
    let output = asgreg(&[
        "priors",
        "--images",
        path_str(&images),
        "--out",
        path_str(&out),
        "--exif-csv",
        path_str(&csv),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let model = read_model(&out).unwrap();
    // 35 mm equivalent 36 mm: f = width.
    assert_eq!(model.cameras[&1].intrinsics.fx_px, 32.0);
    let offset = std::fs::read_to_string(out.join("utm_offset.txt")).unwrap();
    assert!(offset.contains("zone 15N"), "{offset}");
}
