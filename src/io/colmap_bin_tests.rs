// The tests of `io::colmap_bin` (a file of its own: the byte fixtures are long).

use super::*;
use crate::core::camera::{Distortion, PinholeIntrinsics};
use crate::core::rigid::Rigid3;
use crate::io::colmap::read_model;
use nalgebra::{Quaternion, UnitQuaternion};

fn temp_dir() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

/// Builds a byte sequence field by field, little-endian, as the format in the module docs says.
#[derive(Default)]
struct Bytes(Vec<u8>);

impl Bytes {
    fn u8(mut self, value: u8) -> Self {
        self.0.push(value);
        self
    }
    fn u32(mut self, value: u32) -> Self {
        self.0.extend_from_slice(&value.to_le_bytes());
        self
    }
    fn i32(mut self, value: i32) -> Self {
        self.0.extend_from_slice(&value.to_le_bytes());
        self
    }
    fn u64(mut self, value: u64) -> Self {
        self.0.extend_from_slice(&value.to_le_bytes());
        self
    }
    fn i64(mut self, value: i64) -> Self {
        self.0.extend_from_slice(&value.to_le_bytes());
        self
    }
    fn f64(mut self, value: f64) -> Self {
        self.0.extend_from_slice(&value.to_le_bytes());
        self
    }
    fn name(mut self, name: &str) -> Self {
        self.0.extend_from_slice(name.as_bytes());
        self.0.push(0);
        self
    }
}

/// `cameras.bin` of the tiny model, spelled out byte by byte: 2 cameras,
/// 1 PINHOLE 640x480 (500, 500, 320, 240) and 2 SIMPLE_RADIAL 1000x562 (585, 500, 281, 0.25).
#[rustfmt::skip]
const TINY_CAMERAS_BIN: [u8; 120] = [
    2, 0, 0, 0, 0, 0, 0, 0,                 // number of cameras (u64)
    1, 0, 0, 0,                             // CAMERA_ID 1 (u32)
    1, 0, 0, 0,                             // MODEL_ID 1 = PINHOLE (i32)
    0x80, 0x02, 0, 0, 0, 0, 0, 0,           // WIDTH 640 (u64)
    0xe0, 0x01, 0, 0, 0, 0, 0, 0,           // HEIGHT 480 (u64)
    0, 0, 0, 0, 0, 0x40, 0x7f, 0x40,        // fx 500.0 (f64 0x407f400000000000)
    0, 0, 0, 0, 0, 0x40, 0x7f, 0x40,        // fy 500.0
    0, 0, 0, 0, 0, 0, 0x74, 0x40,           // cx 320.0 (0x4074000000000000)
    0, 0, 0, 0, 0, 0, 0x6e, 0x40,           // cy 240.0 (0x406e000000000000)
    2, 0, 0, 0,                             // CAMERA_ID 2
    2, 0, 0, 0,                             // MODEL_ID 2 = SIMPLE_RADIAL
    0xe8, 0x03, 0, 0, 0, 0, 0, 0,           // WIDTH 1000
    0x32, 0x02, 0, 0, 0, 0, 0, 0,           // HEIGHT 562
    0, 0, 0, 0, 0, 0x48, 0x82, 0x40,        // f 585.0 (0x4082480000000000)
    0, 0, 0, 0, 0, 0x40, 0x7f, 0x40,        // cx 500.0
    0, 0, 0, 0, 0, 0x90, 0x71, 0x40,        // cy 281.0 (0x4071900000000000)
    0, 0, 0, 0, 0, 0, 0xd0, 0x3f,           // k 0.25 (0x3fd0000000000000)
];

/// `images.bin` of the tiny model: image 5 (nadir, camera 1) and image 9 (QW < 0, camera 2, a
/// name with a space and a folder), two observations each; both see 3D point 7.
fn tiny_images_bin() -> Vec<u8> {
    Bytes::default()
        .u64(2) // number of images
        .u32(5) // IMAGE_ID
        .f64(0.0) // QW
        .f64(1.0) // QX
        .f64(0.0) // QY
        .f64(0.0) // QZ
        .f64(-10.0) // TX
        .f64(20.0) // TY
        .f64(100.0) // TZ
        .u32(1) // CAMERA_ID
        .name("DJI_0001.JPG")
        .u64(2) // NUM_POINTS2D
        .f64(100.5)
        .f64(200.25)
        .i64(7) // sees 3D point 7
        .f64(10.0)
        .f64(20.0)
        .i64(-1) // sees nothing (COLMAP's kInvalidPoint3DId)
        .u32(9)
        .f64(-0.5)
        .f64(0.5)
        .f64(0.5)
        .f64(0.5)
        .f64(1.5)
        .f64(-2.25)
        .f64(3.0)
        .u32(2)
        .name("flight 2/img 002.jpg")
        .u64(2)
        .f64(1.0)
        .f64(2.0)
        .i64(-1)
        .f64(300.75)
        .f64(150.125)
        .i64(7)
        .0
}

/// `points3D.bin` of the tiny model: point 7, seen by image 5's point2D 0 and image 9's point2D 1.
fn tiny_points3d_bin() -> Vec<u8> {
    Bytes::default()
        .u64(1) // number of points
        .u64(7) // POINT3D_ID
        .f64(512345.25)
        .f64(5401234.5)
        .f64(250.125)
        .u8(200)
        .u8(100)
        .u8(50)
        .f64(0.5) // ERROR
        .u64(2) // TRACK_LENGTH
        .u32(5)
        .u32(0)
        .u32(9)
        .u32(1)
        .0
}

/// The tiny model as structs: what the three byte sequences above must decode to.
fn tiny_reconstruction() -> ColmapReconstruction {
    let pose = |w, x, y, z, t: [f64; 3]| {
        Rigid3::new(
            UnitQuaternion::new_unchecked(Quaternion::new(w, x, y, z)),
            Vector3::from(t),
        )
    };
    ColmapReconstruction {
        cameras: BTreeMap::from([
            (
                1,
                Camera::pinhole(
                    640,
                    480,
                    PinholeIntrinsics {
                        fx_px: 500.0,
                        fy_px: 500.0,
                        cx_px: 320.0,
                        cy_px: 240.0,
                        skew_px: 0.0,
                    },
                ),
            ),
            (
                2,
                Camera::from_colmap_params(
                    CameraModelId::SimpleRadial,
                    1000,
                    562,
                    &[585.0, 500.0, 281.0, 0.25],
                )
                .unwrap(),
            ),
        ]),
        images: vec![
            ImageRecord {
                pose: ImagePose {
                    image_id: 5,
                    camera_id: 1,
                    name: "DJI_0001.JPG".to_string(),
                    cam_from_world: pose(0.0, 1.0, 0.0, 0.0, [-10.0, 20.0, 100.0]),
                },
                points2d: vec![
                    Point2D {
                        xy_px: [100.5, 200.25],
                        point3d_id: Some(7),
                    },
                    Point2D {
                        xy_px: [10.0, 20.0],
                        point3d_id: None,
                    },
                ],
            },
            ImageRecord {
                pose: ImagePose {
                    image_id: 9,
                    camera_id: 2,
                    name: "flight 2/img 002.jpg".to_string(),
                    cam_from_world: pose(-0.5, 0.5, 0.5, 0.5, [1.5, -2.25, 3.0]),
                },
                points2d: vec![
                    Point2D {
                        xy_px: [1.0, 2.0],
                        point3d_id: None,
                    },
                    Point2D {
                        xy_px: [300.75, 150.125],
                        point3d_id: Some(7),
                    },
                ],
            },
        ],
        points3d: vec![Point3D {
            point3d_id: 7,
            xyz: Vector3::new(512345.25, 5401234.5, 250.125),
            rgb: [200, 100, 50],
            error_px: 0.5,
            track: vec![
                TrackElement {
                    image_id: 5,
                    point2d_index: 0,
                },
                TrackElement {
                    image_id: 9,
                    point2d_index: 1,
                },
            ],
        }],
    }
}

/// Writes the tiny model's hand-made bytes into `dir`.
fn write_tiny_files(dir: &Path) {
    fs::write(dir.join(CAMERAS_BIN), TINY_CAMERAS_BIN).unwrap();
    fs::write(dir.join(IMAGES_BIN), tiny_images_bin()).unwrap();
    fs::write(dir.join(POINTS3D_BIN), tiny_points3d_bin()).unwrap();
}

#[test]
fn hand_made_colmap_bytes_decode_and_are_reproduced_exactly() {
    let expected = tiny_reconstruction();
    let dir = temp_dir();
    write_tiny_files(dir.path());

    let read = ColmapReconstruction::read_bin(dir.path()).unwrap();
    assert_eq!(read, expected);
    // The quaternion's sign is kept (QW = -0.5 as written).
    assert_eq!(read.images[1].pose.cam_from_world.rotation.w, -0.5);

    let out = temp_dir();
    expected.write_bin(out.path()).unwrap();
    assert_eq!(
        fs::read(out.path().join(CAMERAS_BIN)).unwrap(),
        TINY_CAMERAS_BIN
    );
    assert_eq!(
        fs::read(out.path().join(IMAGES_BIN)).unwrap(),
        tiny_images_bin()
    );
    assert_eq!(
        fs::read(out.path().join(POINTS3D_BIN)).unwrap(),
        tiny_points3d_bin()
    );
}

#[test]
fn poses_only_reading_skips_observations() {
    let dir = temp_dir();
    write_tiny_files(dir.path());
    let model = read_model_bin(dir.path()).unwrap();
    assert_eq!(model, tiny_reconstruction().to_model());
    let records = read_image_records_bin(&dir.path().join(IMAGES_BIN)).unwrap();
    assert_eq!(records, tiny_reconstruction().images);

    // Without observations: NUM_POINTS2D 0 per image, an empty points3D.bin (8 zero bytes).
    let out = temp_dir();
    write_model_bin(out.path(), &model).unwrap();
    assert_eq!(fs::read(out.path().join(POINTS3D_BIN)).unwrap(), [0u8; 8]);
    let images = fs::read(out.path().join(IMAGES_BIN)).unwrap();
    // 8 (count) + per image 4 + 56 + 4 + name + NUL + 8.
    let names = "DJI_0001.JPG".len() + "flight 2/img 002.jpg".len();
    assert_eq!(images.len(), 8 + 2 * (4 + 56 + 4 + 1 + 8) + names);
    assert_eq!(read_model_bin(out.path()).unwrap(), model);
}

/// A quaternion that is not of unit length (a hand-written file) is normalised like the text
/// reader does; a unit one is kept bit for bit (checked by the hand-made bytes above).
#[test]
fn non_unit_quaternions_are_normalised() {
    let dir = temp_dir();
    let path = dir.path().join(IMAGES_BIN);
    let bytes = Bytes::default()
        .u64(1)
        .u32(1)
        .f64(0.0)
        .f64(0.0)
        .f64(0.0)
        .f64(-2.0)
        .f64(1.0)
        .f64(2.0)
        .f64(3.0)
        .u32(1)
        .name("a.jpg")
        .u64(0)
        .0;
    fs::write(&path, bytes).unwrap();
    let image = &read_images_bin(&path).unwrap()[0];
    let q = image.cam_from_world.rotation.quaternion();
    assert_eq!([q.w, q.i, q.j, q.k], [0.0, 0.0, 0.0, -1.0]);
}

/// The real Brighton Beach models (PINHOLE and SIMPLE_RADIAL, 18 images each) from text to
/// binary and back, unchanged.
#[test]
fn brighton_beach_text_models_round_trip_through_binary() {
    let data = crate::test_data::repo_data("brighton_beach");
    for name in ["gt_undistorted", "gt_simple_radial"] {
        let model = read_model(&data.join(name)).unwrap();
        let out = temp_dir();
        write_model_bin(out.path(), &model).unwrap();
        assert_eq!(read_model_bin(out.path()).unwrap(), model, "{name}");
        let full = ColmapReconstruction::read_bin(out.path()).unwrap();
        assert_eq!(full, ColmapReconstruction::from_model(model), "{name}");
    }
}

/// Random models of all five camera models, georeferenced translations and non-ASCII names:
/// write → read gives the same model, bit for bit.
#[test]
fn random_models_round_trip() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(16);
    for trial in 0..20 {
        let mut cameras = BTreeMap::new();
        for (index, model) in CameraModelId::ALL.into_iter().enumerate() {
            let mut params: Vec<f64> = (0..model.param_count())
                .map(|_| rng.random_range(0.001..1.0))
                .collect();
            params[0] = rng.random_range(100.0..5000.0);
            if matches!(model, CameraModelId::Pinhole | CameraModelId::OpenCv) {
                params[1] = rng.random_range(100.0..5000.0);
            }
            let camera_id = rng.random_range(0..u32::MAX / 8) * 5 + index as u32;
            let camera = Camera::from_colmap_params(model, 4000, 2250, &params).unwrap();
            cameras.insert(camera_id, camera);
        }
        let camera_ids: Vec<u32> = cameras.keys().copied().collect();
        let images = (0..10)
            .map(|index| {
                let q: [f64; 4] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
                let t: [f64; 3] = std::array::from_fn(|_| rng.random_range(-6e6..6e6));
                ImagePose {
                    image_id: index * 1000 + trial,
                    camera_id: camera_ids[index as usize % camera_ids.len()],
                    name: format!("dir {trial}/ïmage_{index}.jpg"),
                    cam_from_world: Rigid3::from_colmap(q, t),
                }
            })
            .collect();
        let model = ColmapModel { cameras, images };
        let dir = temp_dir();
        write_model_bin(dir.path(), &model).unwrap();
        assert_eq!(read_model_bin(dir.path()).unwrap(), model);
    }
}

/// Every cut of every file fails with an error that names the file: no panic, no partial model.
#[test]
fn every_truncation_is_refused_and_names_the_file() {
    let dir = temp_dir();
    let files: [(&str, Vec<u8>); 3] = [
        (CAMERAS_BIN, TINY_CAMERAS_BIN.to_vec()),
        (IMAGES_BIN, tiny_images_bin()),
        (POINTS3D_BIN, tiny_points3d_bin()),
    ];
    for (name, bytes) in &files {
        let path = dir.path().join(name);
        for length in 0..bytes.len() {
            fs::write(&path, &bytes[..length]).unwrap();
            let message = match *name {
                CAMERAS_BIN => read_cameras_bin(&path).unwrap_err().to_string(),
                IMAGES_BIN => read_image_records_bin(&path).unwrap_err().to_string(),
                _ => read_points3d_bin(&path).unwrap_err().to_string(),
            };
            assert!(message.contains(&path.display().to_string()), "{message}");
            if *name == IMAGES_BIN {
                let poses_only = read_images_bin(&path).unwrap_err().to_string();
                assert!(poses_only.contains(name), "{poses_only}");
            }
        }
    }

    // A cut inside image 2's TZ names the record and the field.
    let path = dir.path().join(IMAGES_BIN);
    let images = tiny_images_bin();
    let image2 = 8 + (4 + 56 + 4 + "DJI_0001.JPG".len() + 1 + 8 + 2 * 24);
    fs::write(&path, &images[..image2 + 4 + 6 * 8 + 3]).unwrap();
    let message = read_images_bin(&path).unwrap_err().to_string();
    println!("{message}");
    assert!(message.contains("image record 2 of 2"), "{message}");
    assert!(message.contains("field TZ"), "{message}");
    assert!(message.contains("cut short"), "{message}");

    // A name without its NUL at the end of the file.
    fs::write(&path, &images[..image2 + 4 + 7 * 8 + 4 + 5]).unwrap();
    let message = read_images_bin(&path).unwrap_err().to_string();
    assert!(message.contains("field NAME"), "{message}");
    assert!(message.contains("no NUL byte"), "{message}");
}

#[test]
fn huge_counts_are_refused_before_allocating() {
    let dir = temp_dir();
    let path = dir.path().join(CAMERAS_BIN);
    fs::write(&path, Bytes::default().u64(1_000_000_000_000).0).unwrap();
    let error = read_cameras_bin(&path).unwrap_err();
    let message = error.to_string();
    println!("{message}");
    assert!(matches!(error, ColmapBinError::Count { .. }), "{message}");
    assert!(message.contains("1000000000000 cameras"), "{message}");
    assert!(message.contains("number of cameras"), "{message}");

    for count in [u64::MAX, 1 << 40, 3] {
        let path = dir.path().join(IMAGES_BIN);
        let bytes = Bytes::default()
            .u64(1)
            .u32(1)
            .f64(1.0)
            .f64(0.0)
            .f64(0.0)
            .f64(0.0)
            .f64(0.0)
            .f64(0.0)
            .f64(0.0)
            .u32(1)
            .name("a.jpg")
            .u64(count)
            .f64(1.0)
            .f64(2.0)
            .i64(-1)
            .0;
        fs::write(&path, bytes).unwrap();
        for message in [
            read_images_bin(&path).unwrap_err().to_string(),
            read_image_records_bin(&path).unwrap_err().to_string(),
        ] {
            assert!(message.contains("image record 1 of 1"), "{message}");
            assert!(message.contains("field NUM_POINTS2D"), "{message}");
            assert!(message.contains(&format!("{count} points2D")), "{message}");
        }
    }

    let path = dir.path().join(POINTS3D_BIN);
    let mut bytes = tiny_points3d_bin();
    bytes.truncate(8 + 8 + 24 + 3 + 8);
    bytes.extend_from_slice(&u64::MAX.to_le_bytes());
    fs::write(&path, bytes).unwrap();
    let message = read_points3d_bin(&path).unwrap_err().to_string();
    assert!(message.contains("point3D record 1 of 1"), "{message}");
    assert!(message.contains("TRACK_LENGTH"), "{message}");
}

#[test]
fn bad_camera_records_name_record_and_field() {
    let dir = temp_dir();
    let path = dir.path().join(CAMERAS_BIN);
    let camera = |model_id: i32, width: u64, params: &[f64]| {
        let mut bytes = Bytes::default()
            .u64(1)
            .u32(3)
            .i32(model_id)
            .u64(width)
            .u64(480);
        for &param in params {
            bytes = bytes.f64(param);
        }
        bytes.0
    };
    let cases: Vec<(Vec<u8>, &str, &str)> = vec![
        (camera(5, 640, &[1.0; 8]), "MODEL_ID", "OPENCV_FISHEYE"),
        (camera(99, 640, &[]), "MODEL_ID", "no COLMAP camera model"),
        (camera(-1, 640, &[]), "MODEL_ID", "no COLMAP camera model"),
        (
            camera(1, 0, &[500.0, 500.0, 320.0, 240.0]),
            "WIDTH",
            "positive",
        ),
        (camera(1, 1 << 32, &[500.0; 4]), "WIDTH", "below 2^32"),
        (
            camera(1, 640, &[500.0, f64::NAN, 320.0, 240.0]),
            "PARAMS[1]",
            "finite",
        ),
        (
            camera(1, 640, &[-500.0, 500.0, 320.0, 240.0]),
            "PARAMS[]",
            "camera 3",
        ),
        (
            camera(1, 640, &[500.0, 500.0, 320.0]),
            "PARAMS[3]",
            "cut short",
        ),
    ];
    for (bytes, field, says) in cases {
        fs::write(&path, bytes).unwrap();
        let message = read_cameras_bin(&path).unwrap_err().to_string();
        println!("{message}");
        assert!(message.contains("camera record 1 of 1"), "{message}");
        assert!(message.contains(field), "no {field} in: {message}");
        assert!(message.contains(says), "no '{says}' in: {message}");
    }

    let mut bytes = TINY_CAMERAS_BIN.to_vec();
    bytes[8 + 24 + 32] = 1; // the second camera's id becomes 1
    fs::write(&path, bytes).unwrap();
    let message = read_cameras_bin(&path).unwrap_err().to_string();
    assert!(message.contains("camera record 2 of 2"), "{message}");
    assert!(message.contains("duplicate CAMERA_ID 1"), "{message}");

    let mut bytes = TINY_CAMERAS_BIN.to_vec();
    bytes.push(0);
    fs::write(&path, bytes).unwrap();
    let message = read_cameras_bin(&path).unwrap_err().to_string();
    assert!(
        message.contains("1 bytes follow the last of the 2 records"),
        "{message}"
    );
}

#[test]
fn bad_image_records_name_record_and_field() {
    let dir = temp_dir();
    let path = dir.path().join(IMAGES_BIN);
    let image = |id: u32, q: [f64; 4], tz: f64, name: &[u8]| {
        let mut bytes = Bytes::default().u32(id);
        for value in q {
            bytes = bytes.f64(value);
        }
        let mut bytes = bytes.f64(0.0).f64(0.0).f64(tz).u32(1).0;
        bytes.extend_from_slice(name);
        bytes.push(0);
        bytes.extend_from_slice(&0u64.to_le_bytes());
        bytes
    };
    let file = |records: &[Vec<u8>]| {
        let mut bytes = (records.len() as u64).to_le_bytes().to_vec();
        for record in records {
            bytes.extend_from_slice(record);
        }
        bytes
    };
    let good = image(1, [1.0, 0.0, 0.0, 0.0], 0.0, b"a.jpg");
    let cases: Vec<(Vec<u8>, &str, &str)> = vec![
        (
            file(&[good.clone(), image(2, [0.0; 4], 0.0, b"b.jpg")]),
            "QW QX QY QZ",
            "zero length",
        ),
        (
            file(&[
                good.clone(),
                image(2, [1.0, 0.0, 0.0, 0.0], f64::NAN, b"b.jpg"),
            ]),
            "TZ",
            "finite",
        ),
        (
            file(&[good.clone(), image(2, [1.0, 0.0, 0.0, 0.0], 0.0, b"")]),
            "NAME",
            "empty",
        ),
        (
            file(&[
                good.clone(),
                image(2, [1.0, 0.0, 0.0, 0.0], 0.0, b"\xff.jpg"),
            ]),
            "NAME",
            "UTF-8",
        ),
        (
            file(&[good.clone(), image(1, [1.0, 0.0, 0.0, 0.0], 0.0, b"b.jpg")]),
            "duplicate IMAGE_ID 1",
            "record 1",
        ),
        (
            file(&[good.clone(), image(2, [1.0, 0.0, 0.0, 0.0], 0.0, b"a.jpg")]),
            "duplicate NAME 'a.jpg'",
            "record 1",
        ),
    ];
    for (bytes, field, says) in cases {
        fs::write(&path, bytes).unwrap();
        let message = read_images_bin(&path).unwrap_err().to_string();
        println!("{message}");
        assert!(message.contains("image record 2 of 2"), "{message}");
        assert!(message.contains(field), "no {field} in: {message}");
        assert!(message.contains(says), "no '{says}' in: {message}");
    }
}

#[test]
fn models_whose_files_disagree_are_refused() {
    // An image whose camera cameras.bin lacks: named with its record and both files.
    let dir = temp_dir();
    write_tiny_files(dir.path());
    let mut cameras = TINY_CAMERAS_BIN.to_vec();
    cameras[0] = 1;
    cameras.truncate(8 + 24 + 32);
    fs::write(dir.path().join(CAMERAS_BIN), cameras).unwrap();
    for error in [
        read_model_bin(dir.path()).unwrap_err(),
        ColmapReconstruction::read_bin(dir.path()).unwrap_err(),
    ] {
        let message = error.to_string();
        println!("{message}");
        assert!(message.contains("image record 2 of 2"), "{message}");
        assert!(message.contains("'flight 2/img 002.jpg'"), "{message}");
        assert!(message.contains("CAMERA_ID 2"), "{message}");
        assert!(message.contains(CAMERAS_BIN), "{message}");
    }

    // A track that names an observation the image does not have.
    let dir = temp_dir();
    write_tiny_files(dir.path());
    let mut points = tiny_points3d_bin();
    let last = points.len() - 4;
    points[last] = 0; // (9, 1) becomes (9, 0), which sees no point
    fs::write(dir.path().join(POINTS3D_BIN), points).unwrap();
    let message = ColmapReconstruction::read_bin(dir.path())
        .unwrap_err()
        .to_string();
    println!("{message}");
    assert!(message.contains("different models"), "{message}");
    // Poses alone do not need points3D.bin.
    assert_eq!(
        read_model_bin(dir.path()).unwrap(),
        tiny_reconstruction().to_model()
    );

    let mut broken = tiny_reconstruction();
    broken.points3d.clear();
    let error = broken.write_bin(temp_dir().path()).unwrap_err();
    assert!(error.to_string().contains("3D point 7"), "{error}");
}

#[test]
fn unwritable_models_are_refused_naming_what() {
    let dir = temp_dir();
    let mut intrinsics = PinholeIntrinsics::centered(500.0, 640, 480);
    intrinsics.skew_px = 0.5;
    let cameras = BTreeMap::from([(7, Camera::pinhole(640, 480, intrinsics))]);
    let error = write_cameras_bin(&dir.path().join(CAMERAS_BIN), &cameras).unwrap_err();
    assert!(error.to_string().contains("camera 7"), "{error}");
    assert!(error.to_string().contains(CAMERAS_BIN), "{error}");

    let mut image = ImagePose {
        image_id: 4,
        camera_id: 1,
        name: "a\0b.jpg".to_string(),
        cam_from_world: Rigid3::identity(),
    };
    let path = dir.path().join(IMAGES_BIN);
    let error = write_images_bin(&path, std::slice::from_ref(&image)).unwrap_err();
    assert!(error.to_string().contains("image 4"), "{error}");
    assert!(error.to_string().contains("NUL"), "{error}");
    image.name = "a.jpg".to_string();
    image.cam_from_world.translation.z = f64::INFINITY;
    let error = write_images_bin(&path, std::slice::from_ref(&image)).unwrap_err();
    assert!(error.to_string().contains("not finite"), "{error}");

    let model = ColmapModel {
        cameras: BTreeMap::from([(
            1,
            Camera {
                distortion: Distortion::Radial1 { k1: 0.1 },
                ..Camera::pinhole(640, 480, PinholeIntrinsics::centered(500.0, 640, 480))
            },
        )]),
        images: Vec::new(),
    };
    let error = write_model_bin(dir.path(), &model).unwrap_err();
    assert!(error.to_string().contains("PINHOLE"), "{error}");
}

/// Runs COLMAP's own Python reader and writer (`scripts/python/read_write_model.py`, vendored in
/// `tests/data/colmap/`) on the binary model in `ours`: it reads it and writes it into `theirs`.
/// Returns what it read, as JSON.
fn python_read_and_write_back(ours: &Path, theirs: &Path) -> serde_json::Value {
    let script_dir = crate::test_data::repo_data("colmap");
    let program = format!(
        r#"
import sys, json
sys.path.insert(0, {script_dir:?})
import read_write_model as rwm
cameras, images, points3D = rwm.read_model({ours:?}, ext=".bin")
rwm.write_model(cameras, images, points3D, {theirs:?}, ext=".bin")
print(json.dumps({{
    "cameras": {{str(k): [c.model, c.width, c.height, list(c.params)] for k, c in cameras.items()}},
    "images": {{str(k): [list(i.qvec), list(i.tvec), i.camera_id, i.name, i.xys.tolist(), i.point3D_ids.tolist()] for k, i in images.items()}},
    "points3D": {{str(k): [list(p.xyz), p.rgb.tolist(), float(p.error), p.image_ids.tolist(), p.point2D_idxs.tolist()] for k, p in points3D.items()}},
}}))
"#,
        script_dir = script_dir.display().to_string(),
        ours = ours.display().to_string(),
        theirs = theirs.display().to_string(),
    );
    let output = std::process::Command::new("python3")
        .arg("-c")
        .arg(&program)
        .output()
        .expect("python3 could not be started");
    assert!(
        output.status.success(),
        "python3 failed (is numpy installed? `python3 -m pip install numpy`): {}",
        String::from_utf8_lossy(&output.stderr)
    );
    let stdout = String::from_utf8_lossy(&output.stdout);
    serde_json::from_str(stdout.lines().last().unwrap_or_default()).unwrap()
}

/// COLMAP's own Python reader decodes the binary files we write to the values we wrote, and its
/// writer, writing them back, produces the same bytes: for the tiny model (observations, a 3D
/// point, QW < 0) and for the real Brighton Beach model.
#[test]
#[ignore = "needs python3 with numpy"]
fn python_colmap_read_write_model_reads_our_files_and_writes_the_same_bytes() {
    let ours = temp_dir();
    let theirs = temp_dir();
    tiny_reconstruction().write_bin(ours.path()).unwrap();
    let json = python_read_and_write_back(ours.path(), theirs.path());
    assert_eq!(
        json["cameras"]["1"],
        serde_json::json!(["PINHOLE", 640, 480, [500.0, 500.0, 320.0, 240.0]])
    );
    assert_eq!(
        json["cameras"]["2"],
        serde_json::json!(["SIMPLE_RADIAL", 1000, 562, [585.0, 500.0, 281.0, 0.25]])
    );
    assert_eq!(
        json["images"]["9"],
        serde_json::json!([
            [-0.5, 0.5, 0.5, 0.5],
            [1.5, -2.25, 3.0],
            2,
            "flight 2/img 002.jpg",
            [[1.0, 2.0], [300.75, 150.125]],
            [-1, 7]
        ])
    );
    assert_eq!(
        json["points3D"]["7"],
        serde_json::json!([
            [512345.25, 5401234.5, 250.125],
            [200, 100, 50],
            0.5,
            [5, 9],
            [0, 1]
        ])
    );
    let same_bytes = |ours: &Path, theirs: &Path| {
        for name in [CAMERAS_BIN, IMAGES_BIN, POINTS3D_BIN] {
            assert_eq!(
                fs::read(theirs.join(name)).unwrap(),
                fs::read(ours.join(name)).unwrap(),
                "{name}"
            );
        }
    };
    same_bytes(ours.path(), theirs.path());

    let model = read_model(&crate::test_data::repo_data(
        "brighton_beach/gt_simple_radial",
    ))
    .unwrap();
    let ours = temp_dir();
    let theirs = temp_dir();
    write_model_bin(ours.path(), &model).unwrap();
    let json = python_read_and_write_back(ours.path(), theirs.path());
    assert_eq!(
        json["images"].as_object().map(|images| images.len()),
        Some(18)
    );
    assert_eq!(json["cameras"]["1"][0], "SIMPLE_RADIAL");
    same_bytes(ours.path(), theirs.path());
}
