//! Tests of `build_priors` on small made-up photos, and against the shared Brighton Beach set
//! (`shared_data_priors_*`, `#[ignore]`d: see `src/test_data.rs`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use super::*;
use crate::core::camera::PinholeIntrinsics;
use crate::io::colmap::{read_cameras_txt, read_images_txt};
use crate::test_data::shared_data;

/// Brighton Beach's local frame: UTM 15N − (576700, 5188100), Z = GPS altitude.
const BRIGHTON_OFFSET_M: [f64; 3] = [576_700.0, 5_188_100.0, 0.0];

fn photo(name: &str, lat: f64, lon: f64, yaw: f64) -> PhotoMetadata {
    PhotoMetadata {
        name: name.to_string(),
        gps: Some(GpsPosition {
            latitude_deg: lat,
            longitude_deg: lon,
            altitude_m: 198.5,
        }),
        gimbal: Some(Attitude {
            yaw_deg: yaw,
            pitch_deg: -90.0,
            roll_deg: 0.0,
        }),
        attitude_source: Some(AttitudeSource::Csv),
        focal_length_mm: Some(3.61),
        model: Some("FC300S".to_string()),
        image_size_px: Some((1000, 562)),
        ..PhotoMetadata::default()
    }
}

#[test]
fn poses_put_the_camera_at_the_gps_centre_and_share_cameras() {
    let photos = [
        photo("a.jpg", 46.8426070833333, -91.9945598888889, 45.0),
        photo("b.jpg", 46.8427775833333, -91.9942993888889, -132.0),
    ];
    let options = PriorsOptions {
        offset_m: Some(BRIGHTON_OFFSET_M),
        ..PriorsOptions::default()
    };
    let priors = build_priors(&photos, &options).unwrap();
    assert_eq!(priors.frame.zone.to_string(), "15N");
    assert_eq!(priors.cameras.len(), 1, "same size and focal: one camera");
    assert!((priors.cameras[&1].intrinsics.fx_px - 585.089).abs() < 1e-3);
    let centre = priors.images[0].cam_from_world.camera_center();
    // gps_ref_utm_local.txt: DJI_0018.JPG -36.902 64.556 (altitude given here as 198.5).
    assert!(
        (centre - Vector3::new(-36.902, 64.556, 198.5)).norm() < 1e-3,
        "{centre:?}"
    );
    assert_eq!(priors.images[1].image_id, 2);
    assert_eq!(priors.summary[0].applied_convergence_deg, 0.0);
    assert!((priors.summary[0].convergence_deg - 0.7335).abs() < 1e-3);

    // Without an offset: the rounded minimum, written so that the mesh can follow.
    let auto = build_priors(&photos, &PriorsOptions::default()).unwrap();
    assert_eq!(
        (auto.frame.easting_m, auto.frame.northing_m),
        (576_600.0, 5_188_100.0)
    );

    // With the convergence corrected, the yaw turns by γ about the vertical and nothing else.
    let corrected = build_priors(
        &photos,
        &PriorsOptions {
            correct_convergence: true,
            ..options.clone()
        },
    )
    .unwrap();
    let angle = priors.images[0]
        .cam_from_world
        .rotation_angle_to_rad(&corrected.images[0].cam_from_world)
        .to_degrees();
    assert!(
        (angle - corrected.summary[0].convergence_deg).abs() < 1e-9,
        "{angle}"
    );
    let moved = corrected.images[0].cam_from_world.camera_center() - centre;
    assert!(moved.norm() < 1e-9);
}

#[test]
fn a_photo_without_gps_gimbal_or_focal_is_named() {
    let mut no_gps = photo("no_gps.jpg", 46.8, -92.0, 0.0);
    no_gps.gps = None;
    let error = build_priors(&[no_gps], &PriorsOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("no_gps.jpg") && error.contains("GPS") && error.contains("--exif-csv"),
        "{error}"
    );

    let mut no_gimbal = photo("no_gimbal.jpg", 46.8, -92.0, 0.0);
    no_gimbal.gimbal = None;
    let error = build_priors(&[no_gimbal], &PriorsOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("no_gimbal.jpg") && error.contains("GimbalYaw"),
        "{error}"
    );

    let mut no_focal = photo("no_focal.jpg", 46.8, -92.0, 0.0);
    no_focal.focal_length_mm = None;
    let error = build_priors(&[no_focal], &PriorsOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("no_focal.jpg") && error.contains("--cameras"),
        "{error}"
    );
}

#[test]
fn given_cameras_are_matched_by_size() {
    let camera = |w, h| intrinsics::camera_from_focal(w, h, 500.0);
    let mut given = BTreeMap::new();
    given.insert(7, camera(1000, 562));
    let options = PriorsOptions {
        cameras: Some((given.clone(), PathBuf::from("cams.txt"))),
        ..PriorsOptions::default()
    };
    let photos = [photo("a.jpg", 46.8, -92.0, 0.0)];
    let priors = build_priors(&photos, &options).unwrap();
    assert_eq!(priors.images[0].camera_id, 7);
    assert_eq!(priors.cameras.keys().copied().collect::<Vec<_>>(), [7]);

    let mut other_size = photos[0].clone();
    other_size.image_size_px = Some((995, 558));
    let error = build_priors(&[other_size.clone()], &options)
        .unwrap_err()
        .to_string();
    assert!(
        error.contains("995×558") && error.contains("cams.txt"),
        "{error}"
    );

    given.insert(8, camera(995, 558));
    let two = PriorsOptions {
        cameras: Some((given, PathBuf::from("cams.txt"))),
        ..PriorsOptions::default()
    };
    let priors = build_priors(&[photos[0].clone(), other_size], &two).unwrap();
    assert_eq!(
        priors
            .images
            .iter()
            .map(|i| i.camera_id)
            .collect::<Vec<_>>(),
        [7, 8]
    );
}

/// `NAME QW QX QY QZ TX TY TZ` lines (comments skipped).
fn read_prior_file(path: &Path) -> BTreeMap<String, Rigid3> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|line| {
            let words: Vec<&str> = line.split_whitespace().collect();
            let v: Vec<f64> = words[1..].iter().map(|w| w.parse().unwrap()).collect();
            let q = UnitQuaternion::from_quaternion(Quaternion::new(v[0], v[1], v[2], v[3]));
            (
                words[0].to_string(),
                Rigid3::new(q, Vector3::new(v[4], v[5], v[6])),
            )
        })
        .collect()
}

/// `NAME X Y Z` lines.
fn read_centres(path: &Path) -> BTreeMap<String, Vector3<f64>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|line| {
            let words: Vec<&str> = line.split_whitespace().collect();
            let v: Vec<f64> = words[1..4].iter().map(|w| w.parse().unwrap()).collect();
            (words[0].to_string(), Vector3::new(v[0], v[1], v[2]))
        })
        .collect()
}

/// Largest rotation angle (degrees) and centre distance (m) between our priors and a reference.
fn compare(priors: &Priors, reference: &BTreeMap<String, Rigid3>) -> (f64, f64) {
    let mut worst = (0.0f64, 0.0f64);
    for image in &priors.images {
        let theirs = reference
            .get(&image.name)
            .unwrap_or_else(|| panic!("{} not in the reference", image.name));
        let angle = image
            .cam_from_world
            .rotation_angle_to_rad(theirs)
            .to_degrees();
        let distance = (image.cam_from_world.camera_center() - theirs.camera_center()).norm();
        worst = (worst.0.max(angle), worst.1.max(distance));
    }
    assert_eq!(
        priors.images.len(),
        reference.len(),
        "every reference image"
    );
    worst
}

fn brighton_csv_priors(correct_convergence: bool) -> Priors {
    let dir = shared_data("brighton_beach");
    let photos = exif_csv::read_exif_csv(&dir.join("exif_gps_imu.csv")).unwrap();
    let cameras = read_cameras_txt(&dir.join("gt_undistorted/cameras.txt")).unwrap();
    let options = PriorsOptions {
        offset_m: Some(BRIGHTON_OFFSET_M),
        correct_convergence,
        cameras: Some((cameras, PathBuf::from("cameras.txt"))),
        ..PriorsOptions::default()
    };
    build_priors(&photos, &options).unwrap()
}

/// The gimbal convention, documented in `orientation`, checked on the shared set: from its
/// exiftool CSV, without the convergence correction, the priors equal the set's
/// `prior_pose_from_exif.txt` (rotations and centres) and its GPS centres `gps_ref_utm_local.txt`.
#[test]
#[ignore = "needs ../shared/data/brighton_beach (exif_gps_imu.csv, prior_pose_from_exif.txt, gps_ref_utm_local.txt)"]
fn shared_data_priors_from_csv_equal_prior_pose_from_exif() {
    let dir = shared_data("brighton_beach");
    let priors = brighton_csv_priors(false);
    let reference = read_prior_file(&dir.join("prior_pose_from_exif.txt"));
    let (angle_deg, distance_m) = compare(&priors, &reference);
    println!(
        "vs prior_pose_from_exif.txt: max rotation {angle_deg:.5}°, max centre {distance_m:.5} m"
    );
    assert!(angle_deg < 0.01, "rotations differ by up to {angle_deg}°");
    assert!(distance_m < 0.01, "centres differ by up to {distance_m} m");

    let centres = read_centres(&dir.join("gps_ref_utm_local.txt"));
    assert_eq!(centres.len(), priors.summary.len());
    let worst = priors
        .summary
        .iter()
        .map(|s| (Vector3::from(s.center_m) - centres[&s.name]).norm())
        .fold(0.0f64, f64::max);
    println!("vs gps_ref_utm_local.txt: max centre {worst:.5} m");
    assert!(
        worst < 0.01,
        "centres differ from gps_ref_utm_local.txt by up to {worst} m"
    );

    // With the correction, every rotation differs from the file's by the convergence (0.73°).
    let corrected = brighton_csv_priors(true);
    let (angle_deg, _) = compare(&corrected, &reference);
    let gamma = corrected.summary[0].convergence_deg;
    println!("with --meridian-convergence: max rotation {angle_deg:.4}°, γ = {gamma:.4}°");
    assert!((0.72..0.75).contains(&gamma), "{gamma}");
    assert!((angle_deg - gamma).abs() < 0.02, "{angle_deg} vs γ {gamma}");
}

/// Whether correcting the convergence brings the priors closer to the ground truth, measured
/// on the 12 photos whose gimbal yaw is right (DJI_0024–0029 are 180° off, see the set's README).
#[test]
#[ignore = "needs ../shared/data/brighton_beach (exif_gps_imu.csv, gt_undistorted)"]
fn shared_data_priors_against_ground_truth_with_and_without_convergence() {
    let dir = shared_data("brighton_beach");
    let truth: BTreeMap<String, Rigid3> = read_images_txt(&dir.join("gt_undistorted/images.txt"))
        .unwrap()
        .into_iter()
        .map(|image| (image.name, image.cam_from_world))
        .collect();
    let mut means = Vec::new();
    for correct in [false, true] {
        let priors = brighton_csv_priors(correct);
        let errors: Vec<f64> = priors
            .images
            .iter()
            .filter(|image| !(24..=29).any(|n| image.name == format!("DJI_00{n}.JPG")))
            .map(|image| {
                image
                    .cam_from_world
                    .rotation_angle_to_rad(&truth[&image.name])
                    .to_degrees()
            })
            .collect();
        assert_eq!(errors.len(), 12);
        let mean = errors.iter().sum::<f64>() / errors.len() as f64;
        let max = errors.iter().copied().fold(0.0, f64::max);
        println!("convergence corrected: {correct}: rotation error vs ground truth mean {mean:.3}°, max {max:.3}°");
        means.push(mean);
    }
    // The correction is 0.73° about the vertical; the priors are 2–5° off anyway. Only sanity:
    // both are in the README's 2.3–4.6° range.
    for mean in means {
        assert!((2.0..5.0).contains(&mean), "{mean}");
    }
}

/// The JPEG path on the shared set's 1000×562 photos, which keep EXIF and the DJI maker note (no
/// XMP): the same priors as from the CSV, and the ground truth's focal length from EXIF.
#[test]
#[ignore = "needs ../shared/data/brighton_beach (images_distorted, prior_pose_from_exif.txt)"]
fn shared_data_priors_from_jpeg_maker_notes_equal_prior_pose_from_exif() {
    let dir = shared_data("brighton_beach");
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir.join("images_distorted"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    paths.sort();
    let photos: Vec<PhotoMetadata> = paths.iter().map(|p| jpeg::read_photo(p).unwrap()).collect();
    assert_eq!(photos.len(), 18);
    assert!(photos
        .iter()
        .all(|p| p.attitude_source == Some(AttitudeSource::MakerNote)));
    let options = PriorsOptions {
        offset_m: Some(BRIGHTON_OFFSET_M),
        ..PriorsOptions::default()
    };
    let priors = build_priors(&photos, &options).unwrap();
    let (angle_deg, distance_m) = compare(
        &priors,
        &read_prior_file(&dir.join("prior_pose_from_exif.txt")),
    );
    println!("JPEG maker notes vs prior_pose_from_exif.txt: max rotation {angle_deg:.5}°, max centre {distance_m:.5} m");
    assert!(
        angle_deg < 0.01 && distance_m < 0.01,
        "{angle_deg}° {distance_m} m"
    );
    // gt_simple_radial: SIMPLE_RADIAL 1000×562, f = 585.089 px (fixed from EXIF).
    assert_eq!(priors.cameras.len(), 1);
    let camera = &priors.cameras[&1];
    assert_eq!((camera.width_px, camera.height_px), (1000, 562));
    assert_eq!(
        camera.intrinsics,
        PinholeIntrinsics {
            fx_px: camera.intrinsics.fx_px,
            fy_px: camera.intrinsics.fx_px,
            cx_px: 500.0,
            cy_px: 281.0,
            skew_px: 0.0
        }
    );
    assert!(
        (camera.intrinsics.fx_px - 585.089).abs() < 0.001,
        "{:?}",
        camera.intrinsics
    );
}
