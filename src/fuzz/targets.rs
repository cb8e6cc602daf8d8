//! The fuzz targets: every reader of a file a user hands us and every message decoder, each with
//! its valid seed inputs (the repository's real files under `tests/data` and `deploy/`, and files
//! written by our own writers for the formats the repository has no sample of).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use crate::core::image::Image;
use crate::core::mesh::Mesh;
use crate::core::sift_flow::FlowField;
use crate::io::colmap::{read_cameras_txt, read_images_txt, ImagePose};
use crate::io::colmap_bin::{
    read_cameras_bin, read_image_records_bin, read_points3d_bin, write_cameras_bin,
    write_image_records_bin, write_points3d_bin, ImageRecord, Point2D, Point3D, TrackElement,
};
use crate::io::ply::{write_ply, PlyEncoding};
use crate::msg::MessageKind;

/// Runs one input: `path` holds `bytes` (file targets read the path, message targets the bytes).
/// The error is the message a user would see.
pub type ParseFn = fn(&Path, &[u8]) -> Result<(), String>;

/// One reader under test.
pub struct Target {
    /// Its name on the command line and in reports (`ply-binary`, `msg-Frame` …).
    pub name: String,
    /// The name the input file is written as (the extension chooses the reader in some).
    pub file_name: &'static str,
    /// Valid inputs the mutations start from.
    pub seeds: Vec<Vec<u8>>,
    /// Text (or a text header): token and line mutations are used too.
    pub text: bool,
    /// Its errors must name the file (every file reader; not the message decoder, which has no file).
    pub names_file: bool,
    /// Its errors must also say where in the file: at least one of these words (lower case)
    /// outside the file's path, the units of its format (`line` of a text file, `element` or
    /// `property` of a PLY header, `record` of a binary COLMAP file …). Empty: not checked
    /// (message decoders).
    pub names_place: &'static [&'static str],
    /// Allocation allowed per input byte (beyond a fixed base) before an input is a blow-up: 64
    /// for plain formats, more for compressed images (whose pixels legitimately take up to
    /// thousands of times the file's bytes).
    pub allocation_per_input_byte: usize,
    /// Run on each mutated input before parsing (e.g. PNG chunk checksums recomputed, so the
    /// mutations reach the decoder instead of stopping at the checksum).
    pub fixup: Option<fn(&mut [u8])>,
    pub parse: ParseFn,
}

impl Target {
    fn with_fixup(mut self, fixup: fn(&mut [u8])) -> Self {
        self.fixup = Some(fixup);
        self
    }

    fn with_allocation_per_input_byte(mut self, bytes: usize) -> Self {
        self.allocation_per_input_byte = bytes;
        self
    }
}

// Where an error must say it is, per format (at least one of the words, in lower case, outside
// the file's path; `asgreg fuzz` counts the errors that say none as "errors without the line or
// field"). Text formats: the line. PLY: the header line, or the element, record and property of
// the data. Binary COLMAP: the record and its field or byte offset. PFM and .flo: the header
// (and its width/height/scale/tag field) or the byte offset of the data. EXIF of a photo: the tag, or the EXIF/XMP segment. CSV: the line and column.
// TOML configs: the line and column of a syntax error, or the key (`section.key`) of a value.
const TEXT_PLACES: &[&str] = &["line"];
// Meshes: checked after reading, a vertex or face is named by its index (the PLY element's
// record; in an OBJ the `v`/`f` line's number among its kind, from 0); "the mesh has no faces" is
// about the whole file and has no place.
const PLY_PLACES: &[&str] = &[
    "line", "header", "element", "property", "record", "vertex ", "face ", "no faces",
];
const OBJ_PLACES: &[&str] = &["line", "vertex ", "face ", "no faces"];
const BINARY_PLACES: &[&str] = &["record", "field", "byte"];
const RASTER_PLACES: &[&str] = &["header", "width", "height", "scale", "tag", "byte"];

const EXIF_PLACES: &[&str] = &["tag", "field", "exif", "xmp", "segment", "marker"];
const CSV_PLACES: &[&str] = &["line", "column"];
const CONFIG_PLACES: &[&str] = &["line", "column", "field", "`"];
// Compressed images (PNG, JPEG through the `image` crate): the decoders report no position
// ("Corrupt deflate stream", "Not enough bytes"), so their errors are not checked for a place;
// they name the file and the decoder.

/// Allocation per input byte of a compressed image: the loader's decoder limit (16384 bytes per
/// file byte, `io::images`) and the f32 grey copy (4 bytes per pixel).
const IMAGE_ALLOCATION_PER_INPUT_BYTE: usize = 4 * 16_384;

/// Recomputes the CRC of every complete PNG chunk, so that a mutated chunk reaches the decoder.
pub fn fix_png_checksums(data: &mut [u8]) {
    let mut at = 8;
    while at + 12 <= data.len() {
        let length =
            u32::from_be_bytes([data[at], data[at + 1], data[at + 2], data[at + 3]]) as usize;
        let Some(end) = (at + 8)
            .checked_add(length)
            .filter(|end| end + 4 <= data.len())
        else {
            return;
        };
        let crc = crc32(&data[at + 4..end]);
        data[end..end + 4].copy_from_slice(&crc.to_be_bytes());
        at = end + 4;
    }
}

/// CRC-32 (IEEE, as PNG uses), bit by bit: the inputs are small.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xffff_ffff_u32;
    for &byte in bytes {
        crc ^= u32::from(byte);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xedb8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// Seeds could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum SeedError {
    #[error("fuzz seed {}: {detail} (run from the repository root, or pass --repo)", path.display())]
    Missing { path: PathBuf, detail: String },
    #[error("fuzz seed {}: could not be written: {detail}", path.display())]
    Unwritable { path: PathBuf, detail: String },
}

fn read_seed(repo: &Path, relative: &str) -> Result<Vec<u8>, SeedError> {
    let path = repo.join(relative);
    std::fs::read(&path).map_err(|error| SeedError::Missing {
        path,
        detail: error.to_string(),
    })
}

/// Writes a seed with one of our writers and reads its bytes back.
fn written_seed<E: std::fmt::Display>(
    dir: &Path,
    file_name: &str,
    write: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<Vec<u8>, SeedError> {
    let path = dir.join(file_name);
    write(&path).map_err(|error| SeedError::Unwritable {
        path: path.clone(),
        detail: error.to_string(),
    })?;
    std::fs::read(&path).map_err(|error| SeedError::Unwritable {
        path,
        detail: error.to_string(),
    })
}

fn display_error<E: std::fmt::Display>(error: E) -> String {
    error.to_string()
}

/// A closed box of 8 vertices and 12 triangles with vertex normals.
fn small_mesh() -> Result<Mesh, SeedError> {
    let positions_m: Vec<Vector3<f64>> = (0..8)
        .map(|corner| {
            Vector3::new(
                f64::from(corner & 1) + 500_000.0,
                f64::from((corner >> 1) & 1) + 5_000_000.0,
                f64::from((corner >> 2) & 1) * 2.5,
            )
        })
        .collect();
    let faces = vec![
        [0, 2, 1],
        [1, 2, 3],
        [4, 5, 6],
        [5, 7, 6],
        [0, 1, 4],
        [1, 5, 4],
        [2, 6, 3],
        [3, 6, 7],
        [0, 4, 2],
        [2, 4, 6],
        [1, 3, 5],
        [3, 7, 5],
    ];
    let normals = positions_m
        .iter()
        .map(|p| {
            glam::Vec3::new(
                (p.x - 500_000.5) as f32,
                (p.y - 5_000_000.5) as f32,
                (p.z - 1.25) as f32,
            )
            .normalize()
        })
        .collect();
    Mesh::from_world(&positions_m, faces, Some(normals)).map_err(|error| SeedError::Unwritable {
        path: PathBuf::from("(the box mesh)"),
        detail: error.to_string(),
    })
}

const OBJ_SEED: &str = "# a box with normals, texture coordinates, a quad and two objects\n\
mtllib box.mtl\no box\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nv 0 0 1\nv 1 0 1\nv 0 1 1\nv 1 1 1\n\
vt 0 0\nvt 1 0\nvt 1 1\nvn 0 0 -1\nvn 0 0 1\nusemtl grey\ns off\n\
f 1/1/1 3/2/1 2/3/1\nf 2/1/1 3/2/1 4/3/1\nf 5//2 6//2 8//2 7//2\n\
g sides\nf 1 2 6\nf 1 6 5\nf 3 7 8\nf 3 8 4\no roof\nv 0.5 0.5 2\nf 5 6 9\nf -4 -1 -2\n";

const EXIF_CSV_SEED: &str = "SourceFile,FileName,GPSLatitude,GPSLongitude,GPSAltitude,\
RelativeAltitude,GimbalYawDegree,GimbalPitchDegree,GimbalRollDegree,FlightYawDegree,\
FlightPitchDegree,FlightRollDegree,Make,Model,FocalLength,FocalLengthIn35mmFormat,GPSLatitudeRef\n\
DJI_0018.JPG,DJI_0018.JPG,46.8426070833333,-91.9945598888889,198.309,+39.80,+45.00,-89.90,+0.00,+46.00,+1.80,+3.00,DJI,FC6310,8.8,24,N\n\
DJI_0019.JPG,\"DJI_0019.JPG\",46.8426906666667,-91.9944272777778,198.609,+40.10,+42.80,-89.90,+0.00,+40.10,+1.20,+0.40,DJI,\"FC6310, v2\",8.8,24,North\n\
images/DJI_0020.JPG,DJI_0020.JPG,\"46 deg 50' 33.62\"\" N\",-91.9943,198.1,+40.0,+41.0,-90.0,+0.00,,,,DJI,FC6310,,,\n";

/// Every target, with its seeds; `scratch` is a folder for the seeds our writers make.
pub fn all_targets(repo: &Path, scratch: &Path) -> Result<Vec<Target>, SeedError> {
    std::fs::create_dir_all(scratch).map_err(|error| SeedError::Unwritable {
        path: scratch.to_path_buf(),
        detail: error.to_string(),
    })?;
    let excerpt_ply = read_seed(repo, "tests/data/brighton_beach/mesh_excerpt.ply")?;
    let mesh = small_mesh()?;
    let box_ply_binary = written_seed(scratch, "box_binary.ply", |path| {
        write_ply(path, &mesh, PlyEncoding::BinaryLittleEndian)
    })?;
    let box_ply_ascii = written_seed(scratch, "box_ascii.ply", |path| {
        write_ply(path, &mesh, PlyEncoding::Ascii)
    })?;
    let cameras_txt = [
        read_seed(
            repo,
            "tests/data/brighton_beach/gt_simple_radial/cameras.txt",
        )?,
        read_seed(repo, "tests/data/brighton_beach/gt_undistorted/cameras.txt")?,
    ];
    let images_txt = [
        read_seed(
            repo,
            "tests/data/brighton_beach/gt_simple_radial/images.txt",
        )?,
        read_seed(repo, "tests/data/brighton_beach/gt_undistorted/images.txt")?,
    ];
    // The binary model: the text model written with our writer, images with observations and
    // 3D points with tracks.
    let model_dir = repo.join("tests/data/brighton_beach/gt_simple_radial");
    let cameras =
        read_cameras_txt(&model_dir.join("cameras.txt")).map_err(|error| SeedError::Missing {
            path: model_dir.join("cameras.txt"),
            detail: error.to_string(),
        })?;
    let images: Vec<ImagePose> = read_images_txt(&model_dir.join("images.txt"))
        .map_err(|error| SeedError::Missing {
            path: model_dir.join("images.txt"),
            detail: error.to_string(),
        })?
        .into_iter()
        .take(3)
        .collect();
    let cameras: BTreeMap<u32, _> = cameras
        .into_iter()
        .filter(|(id, _)| images.iter().any(|image| image.camera_id == *id))
        .collect();
    let cameras_bin = written_seed(scratch, "cameras.bin", |path| {
        write_cameras_bin(path, &cameras)
    })?;
    let records: Vec<ImageRecord> = images
        .iter()
        .enumerate()
        .map(|(index, pose)| ImageRecord {
            pose: pose.clone(),
            points2d: (0..3)
                .map(|k| Point2D {
                    xy_px: [10.0 * k as f64 + 0.5, 20.0 + index as f64],
                    point3d_id: if k == 2 { None } else { Some(k as u64 + 1) },
                })
                .collect(),
        })
        .collect();
    let images_bin = written_seed(scratch, "images.bin", |path| {
        write_image_records_bin(path, &records)
    })?;
    let points: Vec<Point3D> = (1..=3)
        .map(|id| Point3D {
            point3d_id: id,
            xyz: Vector3::new(id as f64, -2.0 * id as f64, 30.5),
            rgb: [200, 100, id as u8],
            error_px: 0.75,
            track: (0..2)
                .map(|image| TrackElement {
                    image_id: images.get(image).map_or(1, |pose| pose.image_id),
                    point2d_index: (id - 1) as u32 % 2,
                })
                .collect(),
        })
        .collect();
    let points3d_bin = written_seed(scratch, "points3D.bin", |path| {
        write_points3d_bin(path, &points)
    })?;

    let depth = Image::new(
        12,
        8,
        (0..96)
            .map(|i| {
                if i % 7 == 0 {
                    0.0
                } else {
                    20.0 + i as f32 * 0.25
                }
            })
            .collect(),
    )
    .map_err(|error| SeedError::Unwritable {
        path: PathBuf::from("(depth seed)"),
        detail: error.to_string(),
    })?;
    let pfm = written_seed(scratch, "depth.pfm", |path| {
        crate::io::pfm::write_pfm(path, depth.view())
    })?;
    let mut field = FlowField::zeros(12, 8);
    {
        let (u_px, v_px) = field.planes_mut();
        for (i, (u, v)) in u_px.iter_mut().zip(v_px.iter_mut()).enumerate() {
            *u = i as f32 * 0.5 - 3.0;
            *v = -(i as f32) * 0.125;
        }
    }
    let flo = written_seed(scratch, "flow.flo", |path| {
        crate::io::flo::write_flo(path, &field)
    })?;
    let grey = Image::new(
        24,
        16,
        (0..24 * 16)
            .map(|i| ((i * 37) % 256) as f32 / 255.0)
            .collect(),
    )
    .map_err(|error| SeedError::Unwritable {
        path: PathBuf::from("(image seed)"),
        detail: error.to_string(),
    })?;
    let png = written_seed(scratch, "grey.png", |path| {
        crate::io::images::save_gray_png(path, grey.view())
    })?;
    let rgb = Image::new(
        20,
        12,
        (0..20 * 12)
            .map(|i| [(i * 5) as u8, (i * 11) as u8, (255 - i) as u8])
            .collect(),
    )
    .map_err(|error| SeedError::Unwritable {
        path: PathBuf::from("(image seed)"),
        detail: error.to_string(),
    })?;
    let png_rgb = written_seed(scratch, "rgb.png", |path| {
        crate::io::images::save_rgb_png(path, rgb.view())
    })?;
    let photo_jpg = read_seed(repo, "tests/data/brighton_beach/DJI_0025_crop.jpg")?;
    let small_jpg = {
        let mut bytes = Vec::new();
        let buffer = image::RgbImage::from_fn(16, 16, |x, y| {
            image::Rgb([(x * 16) as u8, (y * 16) as u8, 128])
        });
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, 80)
            .encode_image(&buffer)
            .map_err(|error| SeedError::Unwritable {
                path: PathBuf::from("(jpeg seed)"),
                detail: error.to_string(),
            })?;
        bytes
    };
    let offset_txt = crate::priors::utm::LocalFrame {
        zone: crate::priors::utm::UtmZone::of(46.84, -91.99),
        easting_m: 596_400.0,
        northing_m: 5_188_300.0,
        altitude_m: 12.5,
    }
    .to_file_text()
    .into_bytes();
    let configs = vec![
        read_seed(repo, "deploy/ground-station.toml")?,
        read_seed(repo, "deploy/two-host/station.toml")?,
        read_seed(repo, "deploy/two-host/remote-flow.toml")?,
    ];

    let mut targets = vec![
        file_target(
            "ply-binary",
            "mesh.ply",
            vec![excerpt_ply, box_ply_binary],
            true,
            PLY_PLACES,
            |path, _| {
                crate::io::mesh_file::read_mesh(path)
                    .map(drop)
                    .map_err(display_error)
            },
        ),
        file_target(
            "ply-ascii",
            "mesh.ply",
            vec![box_ply_ascii],
            true,
            PLY_PLACES,
            |path, _| {
                crate::io::mesh_file::read_mesh(path)
                    .map(drop)
                    .map_err(display_error)
            },
        ),
        file_target(
            "obj",
            "mesh.obj",
            vec![OBJ_SEED.as_bytes().to_vec()],
            true,
            OBJ_PLACES,
            |path, _| {
                crate::io::mesh_file::read_mesh(path)
                    .map(drop)
                    .map_err(display_error)
            },
        ),
        file_target(
            "colmap-cameras-txt",
            "cameras.txt",
            cameras_txt.to_vec(),
            true,
            TEXT_PLACES,
            |path, _| read_cameras_txt(path).map(drop).map_err(display_error),
        ),
        file_target(
            "colmap-images-txt",
            "images.txt",
            images_txt.to_vec(),
            true,
            TEXT_PLACES,
            |path, _| read_images_txt(path).map(drop).map_err(display_error),
        ),
        file_target(
            "colmap-cameras-bin",
            "cameras.bin",
            vec![cameras_bin],
            false,
            BINARY_PLACES,
            |path, _| read_cameras_bin(path).map(drop).map_err(display_error),
        ),
        file_target(
            "colmap-images-bin",
            "images.bin",
            vec![images_bin],
            false,
            BINARY_PLACES,
            |path, _| {
                read_image_records_bin(path)
                    .map(drop)
                    .map_err(display_error)
            },
        ),
        file_target(
            "colmap-points3d-bin",
            "points3D.bin",
            vec![points3d_bin],
            false,
            BINARY_PLACES,
            |path, _| read_points3d_bin(path).map(drop).map_err(display_error),
        ),
        file_target(
            "pfm",
            "depth.pfm",
            vec![pfm],
            true,
            RASTER_PLACES,
            |path, _| {
                crate::io::pfm::read_pfm(path)
                    .map(drop)
                    .map_err(display_error)
            },
        ),
        file_target(
            "flo",
            "flow.flo",
            vec![flo],
            false,
            RASTER_PLACES,
            |path, _| {
                crate::io::flo::read_flo(path)
                    .map(drop)
                    .map_err(display_error)
            },
        ),
        file_target(
            "image-png",
            "photo.png",
            vec![png, png_rgb],
            false,
            &[],
            |path, _| {
                crate::io::images::read_image_size(path).map_err(display_error)?;
                crate::io::images::load_gray(path)
                    .map(drop)
                    .map_err(display_error)
            },
        )
        .with_fixup(fix_png_checksums)
        .with_allocation_per_input_byte(IMAGE_ALLOCATION_PER_INPUT_BYTE),
        file_target(
            "image-jpeg",
            "photo.jpg",
            vec![photo_jpg.clone(), small_jpg],
            false,
            &[],
            |path, _| {
                crate::io::images::read_image_size(path).map_err(display_error)?;
                crate::io::images::load_gray(path)
                    .map(drop)
                    .map_err(display_error)
            },
        )
        .with_allocation_per_input_byte(IMAGE_ALLOCATION_PER_INPUT_BYTE),
        file_target(
            "priors-jpeg",
            "DJI_0025.JPG",
            vec![photo_jpg],
            false,
            EXIF_PLACES,
            |path, _| {
                crate::priors::jpeg::read_photo(path)
                    .map(drop)
                    .map_err(display_error)
            },
        ),
        file_target(
            "priors-exif-csv",
            "exif.csv",
            vec![EXIF_CSV_SEED.as_bytes().to_vec()],
            true,
            CSV_PLACES,
            |path, _| {
                crate::priors::exif_csv::read_exif_csv(path)
                    .map(drop)
                    .map_err(display_error)
            },
        ),
        file_target(
            "priors-offset",
            "utm_offset.txt",
            vec![offset_txt],
            true,
            TEXT_PLACES,
            |path, _| {
                // As `asgreg priors --offset-file` reads it.
                let text = crate::io::text::read_utf8(path)
                    .map_err(|error| format!("{}: {error}", path.display()))?;
                crate::priors::utm::LocalFrame::parse_file(path, &text)
                    .map(drop)
                    .map_err(display_error)
            },
        ),
        file_target(
            "pipeline-config",
            "pipeline.toml",
            configs,
            true,
            CONFIG_PLACES,
            |path, _| {
                crate::runtime::config::PipelineConfig::read(path)
                    .map(drop)
                    .map_err(display_error)
            },
        ),
    ];
    for kind in MESSAGE_KINDS {
        let seeds = message_seeds(repo, kind)?;
        targets.push(Target {
            name: format!("msg-{kind:?}"),
            file_name: "message.bin",
            seeds,
            text: false,
            names_file: false,
            names_place: &[],
            allocation_per_input_byte: 64,
            fixup: None,
            parse: |_, bytes| decode_and_use(bytes),
        });
    }
    Ok(targets)
}

const MESSAGE_KINDS: [MessageKind; 15] = [
    MessageKind::Frame,
    MessageKind::FlowJob,
    MessageKind::Correspondences,
    MessageKind::Hypothesis,
    MessageKind::FrameFailed,
    MessageKind::PoseResult,
    MessageKind::Credit,
    MessageKind::Metrics,
    MessageKind::StreamEnd,
    MessageKind::FrameQuery,
    MessageKind::ChangeJob,
    MessageKind::ChangeResult,
    MessageKind::ChangeSet,
    MessageKind::ChangeSight,
    MessageKind::PoseLender,
];

/// The golden wire files of one kind (`tests/data/wire/v<SCHEMA_VERSION>/NN_<Kind>.bin`).
fn message_seeds(repo: &Path, kind: MessageKind) -> Result<Vec<Vec<u8>>, SeedError> {
    let dir = repo.join(format!("tests/data/wire/v{}", crate::msg::SCHEMA_VERSION));
    let suffix = format!("_{kind:?}.bin");
    let entries = std::fs::read_dir(&dir).map_err(|error| SeedError::Missing {
        path: dir.clone(),
        detail: error.to_string(),
    })?;
    let mut paths: Vec<PathBuf> = entries
        .filter_map(|entry| entry.ok().map(|entry| entry.path()))
        .filter(|path| {
            path.file_name()
                .is_some_and(|name| name.to_string_lossy().ends_with(&suffix))
        })
        .collect();
    paths.sort();
    if paths.is_empty() {
        return Err(SeedError::Missing {
            path: dir.join(format!("NN{suffix}")),
            detail: "no golden file of this message kind".to_string(),
        });
    }
    paths
        .iter()
        .map(|path| {
            std::fs::read(path).map_err(|error| SeedError::Missing {
                path: path.clone(),
                detail: error.to_string(),
            })
        })
        .collect()
}

/// Decodes a message and uses what a stage would use: its images and views, the JSON of a result.
fn decode_and_use(bytes: &[u8]) -> Result<(), String> {
    use crate::msg::Body;
    // Decoding reads arrays in place where they are aligned: give it an aligned copy, as the
    // transports do.
    let mut aligned = vec![0u64; bytes.len().div_ceil(8)];
    let aligned_bytes: &mut [u8] = bytemuck::cast_slice_mut(&mut aligned);
    aligned_bytes[..bytes.len()].copy_from_slice(bytes);
    let envelope = crate::msg::decode(&aligned_bytes[..bytes.len()]).map_err(display_error)?;
    match &envelope.body {
        Body::Frame(frame) => {
            frame.photo().map_err(display_error)?;
            frame.depth().map_err(display_error)?;
        }
        Body::FlowJob(job) => {
            job.query_image().map_err(display_error)?;
            job.view().map_err(display_error)?;
        }
        Body::Correspondences(correspondences) => {
            correspondences.to_view();
        }
        Body::FrameQuery(query) => {
            query.query_image().map_err(display_error)?;
            query.depth().map_err(display_error)?;
        }
        Body::ChangeJob(job) => {
            job.depth().map_err(display_error)?;
        }
        Body::PoseResult(result) => {
            crate::msg::pose_result_json(&envelope.header, result);
        }
        Body::ChangeResult(result) => {
            crate::msg::change_result_json(&envelope.header, result);
        }
        Body::ChangeSet(set) => {
            crate::msg::change_set_json(&envelope.header, set);
        }
        Body::ChangeSight(sight) => {
            crate::stage::fusion::seen_frame(sight)?;
        }
        Body::PoseLender(lender) => {
            lender.query().map_err(display_error)?;
        }
        Body::Hypothesis(_)
        | Body::FrameFailed(_)
        | Body::Credit(_)
        | Body::Metrics(_)
        | Body::StreamEnd(_) => {}
    }
    Ok(())
}

fn file_target(
    name: &str,
    file_name: &'static str,
    seeds: Vec<Vec<u8>>,
    text: bool,
    names_place: &'static [&'static str],
    parse: ParseFn,
) -> Target {
    Target {
        name: name.to_string(),
        file_name,
        seeds,
        text,
        names_file: true,
        names_place,
        allocation_per_input_byte: 64,
        fixup: None,
        parse,
    }
}
