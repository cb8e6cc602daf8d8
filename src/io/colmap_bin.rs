//! COLMAP binary models (`cameras.bin`, `images.bin`, `points3D.bin`), read and written byte for
//! byte the way COLMAP writes them (`src/colmap/scene/reconstruction_io_binary.cc`), so that
//! models from COLMAP, pycolmap, hloc or Metashape's COLMAP export load without conversion and
//! asgreg's results open in them.
//!
//! Layout (little-endian throughout; ids are COLMAP's unsigned types, which its Python reader reads
//! as signed `int32`/`int64` with the same bytes):
//!
//! ```text
//! cameras.bin   u64 count, then per camera: u32 CAMERA_ID, i32 MODEL_ID, u64 WIDTH, u64 HEIGHT,
//!               f64 PARAMS[n(MODEL_ID)]
//! images.bin    u64 count, then per image: u32 IMAGE_ID, f64 QW QX QY QZ, f64 TX TY TZ,
//!               u32 CAMERA_ID, NAME bytes ending in NUL, u64 NUM_POINTS2D,
//!               then per point: f64 X, f64 Y, u64 POINT3D_ID (u64::MAX, i.e. -1: none)
//! points3D.bin  u64 count, then per point: u64 POINT3D_ID, f64 X Y Z, u8 R G B, f64 ERROR,
//!               u64 TRACK_LENGTH, then per element: u32 IMAGE_ID, u32 POINT2D_IDX
//! ```
//!
//! Newer COLMAP versions also write `rigs.bin` and `frames.bin`; `images.bin` still holds every
//! image's `cam_from_world`, which is all asgreg needs, and COLMAP reads a model without the two
//! files as one rig per camera, so they are neither read nor written.
//!
//! Reading is defensive: every count is checked against the bytes left in the file before anything
//! is allocated for it (a count of 10¹² is refused, not allocated), a file that ends early or has
//! bytes after its last record is refused, and every error names the file, the record (1-based,
//! of how many), the byte offset and the field, says what was found and what to do. The checks are
//! those of the text reader ([`crate::io::colmap`]): known camera models with valid parameters,
//! finite poses, non-zero quaternions, unique ids and names. A quaternion whose norm is 1 to within
//! 1e-12 (every one COLMAP writes) is kept bit for bit, as COLMAP reads it; others are normalised
//! like the text reader normalises them. Observation
//! coordinates (`X`, `Y` of points2D) are carried through unchecked, as COLMAP does.
//!
//! Writing reproduces COLMAP's bytes: cameras sorted by id, images and 3D points in the order given
//! (COLMAP's own files list them in its order, so reading a COLMAP model and writing it back gives
//! the same bytes), quaternions written as stored (`QW` may be negative, as in COLMAP's binary
//! files; the text writer makes it non-negative).

use std::collections::{BTreeMap, HashMap, HashSet};
use std::fmt;
use std::fs;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::core::camera::{Camera, CameraError, CameraModelId};
use crate::core::rigid::Rigid3;
use crate::io::colmap::{
    check_representable, pose_from_colmap, ColmapError, ColmapModel, ImagePose,
};

/// File names of a COLMAP binary model inside its directory.
pub const CAMERAS_BIN: &str = "cameras.bin";
pub const IMAGES_BIN: &str = "images.bin";
pub const POINTS3D_BIN: &str = "points3D.bin";

/// COLMAP's "no 3D point" (`kInvalidPoint3DId`, the largest `u64`; `-1` in its Python reader).
pub const INVALID_POINT3D_ID: u64 = u64::MAX;

/// Smallest record sizes in bytes (camera without its parameters, image with a one-byte name and
/// no observations, 3D point with an empty track), used to bound counts before allocating.
const CAMERA_MIN_BYTES: usize = 4 + 4 + 8 + 8;
const IMAGE_MIN_BYTES: usize = 4 + 7 * 8 + 4 + 1 + 8;
const POINT2D_BYTES: usize = 8 + 8 + 8;
const POINT3D_MIN_BYTES: usize = 8 + 3 * 8 + 3 + 8 + 8;
const TRACK_ELEMENT_BYTES: usize = 4 + 4;

/// COLMAP's camera model names by `MODEL_ID` (`src/colmap/sensor/models.h`), to name the models
/// asgreg does not support in errors.
const COLMAP_MODEL_NAMES: [&str; 18] = [
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "OPENCV_FISHEYE",
    "FULL_OPENCV",
    "FOV",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "THIN_PRISM_FISHEYE",
    "RAD_TAN_THIN_PRISM_FISHEYE",
    "SIMPLE_DIVISION",
    "DIVISION",
    "SIMPLE_FISHEYE",
    "FISHEYE",
    "EUCM",
    "EQUIRECTANGULAR",
];

/// COLMAP's `MODEL_ID` of a camera model.
pub fn colmap_model_id(model: CameraModelId) -> i32 {
    match model {
        CameraModelId::SimplePinhole => 0,
        CameraModelId::Pinhole => 1,
        CameraModelId::SimpleRadial => 2,
        CameraModelId::Radial => 3,
        CameraModelId::OpenCv => 4,
    }
}

/// The camera model of a COLMAP `MODEL_ID`, or what to say about an id asgreg cannot use.
fn model_from_colmap_id(model_id: i32) -> Result<CameraModelId, String> {
    if let Some(model) = CameraModelId::ALL
        .into_iter()
        .find(|model| colmap_model_id(*model) == model_id)
    {
        return Ok(model);
    }
    let known = usize::try_from(model_id)
        .ok()
        .and_then(|index| COLMAP_MODEL_NAMES.get(index));
    Err(match known {
        Some(name) => format!(
            "COLMAP's {name}, which asgreg does not support (supported: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV); undistort the images to PINHOLE, e.g. with COLMAP's image_undistorter"
        ),
        None => format!(
            "no COLMAP camera model has this id (0 to {}); the file is damaged or is not a COLMAP cameras.bin",
            COLMAP_MODEL_NAMES.len() - 1
        ),
    })
}

/// Which of the three files a record belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RecordKind {
    Camera,
    Image,
    Point3D,
}

impl RecordKind {
    fn name(self) -> &'static str {
        match self {
            RecordKind::Camera => "camera",
            RecordKind::Image => "image",
            RecordKind::Point3D => "point3D",
        }
    }

    fn file_name(self) -> &'static str {
        match self {
            RecordKind::Camera => CAMERAS_BIN,
            RecordKind::Image => IMAGES_BIN,
            RecordKind::Point3D => POINTS3D_BIN,
        }
    }
}

/// Where in a binary model file something is: the file, the record and the byte offset.
#[derive(Clone, Debug, PartialEq)]
pub struct Location {
    pub path: PathBuf,
    pub kind: RecordKind,
    /// 1-based record number; 0 for the count at the start of the file.
    pub record: u64,
    /// Number of records the file announces (0 while the count itself is read).
    pub count: u64,
    /// Byte offset in the file.
    pub offset: usize,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.record == 0 {
            write!(f, "{}: byte {}", self.path.display(), self.offset)
        } else {
            write!(
                f,
                "{}: {} record {} of {} (byte {})",
                self.path.display(),
                self.kind.name(),
                self.record,
                self.count,
                self.offset
            )
        }
    }
}

/// Errors of reading and writing COLMAP binary models. Each names the file it is about.
#[derive(Debug, thiserror::Error)]
pub enum ColmapBinError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{location}, field {field}: the file ends {left} bytes after this point, but the field takes {needed}; the file is cut short (an interrupted copy or write?) or is not a COLMAP {}: write or copy it again",
        location.kind.file_name()
    )]
    Truncated {
        location: Box<Location>,
        field: String,
        needed: usize,
        left: usize,
    },
    #[error(
        "{location}, field {field}: {count} {items} take at least {needed} bytes, but only {left} are left in the file; the file is damaged or is not a COLMAP {}",
        location.kind.file_name()
    )]
    Count {
        location: Box<Location>,
        field: &'static str,
        items: &'static str,
        count: u64,
        needed: u128,
        left: usize,
    },
    #[error("{location}, field {field}: found {found}; {expected}")]
    Field {
        location: Box<Location>,
        field: String,
        found: String,
        expected: String,
    },
    #[error(
        "{location}, camera {camera_id}, field {field}: {source}; fix this camera (other models: undistort the images to PINHOLE, e.g. with COLMAP's image_undistorter)"
    )]
    Camera {
        location: Box<Location>,
        camera_id: u32,
        field: &'static str,
        #[source]
        source: CameraError,
    },
    #[error(
        "{location}: duplicate {field} {value}: already used by record {first_record}; every {field} must be unique"
    )]
    Duplicate {
        location: Box<Location>,
        field: &'static str,
        value: String,
        first_record: u64,
    },
    #[error(
        "{}: {extra} bytes follow the last of the {count} records (from byte {offset}); the file is damaged or is not a COLMAP {}",
        path.display(), kind.file_name()
    )]
    TrailingBytes {
        path: PathBuf,
        kind: RecordKind,
        count: u64,
        offset: usize,
        extra: usize,
    },
    #[error(
        "{location}: image '{image_name}' (IMAGE_ID {image_id}) uses CAMERA_ID {camera_id}, which {} does not define; add the camera there or fix the image's CAMERA_ID",
        cameras_path.display()
    )]
    MissingCamera {
        location: Box<Location>,
        image_id: u32,
        image_name: String,
        camera_id: u32,
        cameras_path: PathBuf,
    },
    #[error("{}: {why}", path.display())]
    Inconsistent { path: PathBuf, why: String },
    #[error("{}: image {image_id}: {why}", path.display())]
    InvalidImage {
        path: PathBuf,
        image_id: u32,
        why: String,
    },
    /// A check shared with the text format (camera representable, model consistent).
    #[error(transparent)]
    Model(#[from] ColmapError),
}

/// One 2D observation of an image: a keypoint and the 3D point it sees, if any.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Point2D {
    /// Pixel coordinates (COLMAP convention: the upper-left corner of the image is (0, 0)).
    pub xy_px: [f64; 2],
    /// The 3D point this keypoint observes (`None` is written as [`INVALID_POINT3D_ID`]).
    pub point3d_id: Option<u64>,
}

/// An image record of `images.bin`: its pose and its 2D observations.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageRecord {
    pub pose: ImagePose,
    pub points2d: Vec<Point2D>,
}

/// One observation of a 3D point: image and index into that image's points2D.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct TrackElement {
    pub image_id: u32,
    pub point2d_index: u32,
}

/// A 3D point of `points3D.bin`.
#[derive(Clone, Debug, PartialEq)]
pub struct Point3D {
    pub point3d_id: u64,
    pub xyz: Vector3<f64>,
    pub rgb: [u8; 3],
    /// Mean reprojection error in pixels (COLMAP writes -1 when it is unknown).
    pub error_px: f64,
    pub track: Vec<TrackElement>,
}

/// Everything a COLMAP binary model holds that asgreg keeps: cameras, images with their
/// observations, 3D points with their tracks (rigs and frames are not kept; see the module docs).
#[derive(Clone, Debug, PartialEq, Default)]
pub struct ColmapReconstruction {
    pub cameras: BTreeMap<u32, Camera>,
    pub images: Vec<ImageRecord>,
    pub points3d: Vec<Point3D>,
}

impl ColmapReconstruction {
    /// Cameras and poses without observations or points.
    pub fn from_model(model: ColmapModel) -> Self {
        Self {
            cameras: model.cameras,
            images: model
                .images
                .into_iter()
                .map(|pose| ImageRecord {
                    pose,
                    points2d: Vec::new(),
                })
                .collect(),
            points3d: Vec::new(),
        }
    }

    /// The cameras and poses (observations and points dropped).
    pub fn to_model(&self) -> ColmapModel {
        ColmapModel {
            cameras: self.cameras.clone(),
            images: self.images.iter().map(|image| image.pose.clone()).collect(),
        }
    }

    /// Reads `cameras.bin`, `images.bin` and `points3D.bin` from `dir` and checks that they agree
    /// ([`Self::validate`]).
    pub fn read_bin(dir: &Path) -> Result<Self, ColmapBinError> {
        let cameras_path = dir.join(CAMERAS_BIN);
        let images_path = dir.join(IMAGES_BIN);
        let points_path = dir.join(POINTS3D_BIN);
        let cameras = read_cameras_bin(&cameras_path)?;
        let images = decode_images(&images_path, &read_file(&images_path)?, true)?;
        check_cameras_exist(&cameras, &cameras_path, &images_path, &images)?;
        let points3d = read_points3d_bin(&points_path)?;
        let reconstruction = Self {
            cameras,
            images: images
                .into_iter()
                .map(|image| ImageRecord {
                    pose: image.pose,
                    points2d: image.points2d,
                })
                .collect(),
            points3d,
        };
        reconstruction.check_observations(&images_path, &points_path)?;
        Ok(reconstruction)
    }

    /// Writes `cameras.bin`, `images.bin` and `points3D.bin` into `dir` (which must exist), after
    /// [`Self::validate`].
    pub fn write_bin(&self, dir: &Path) -> Result<(), ColmapBinError> {
        let images_path = dir.join(IMAGES_BIN);
        let points_path = dir.join(POINTS3D_BIN);
        self.to_model().validate(&images_path)?;
        self.check_observations(&images_path, &points_path)?;
        write_cameras_bin(&dir.join(CAMERAS_BIN), &self.cameras)?;
        let records: Vec<(&ImagePose, &[Point2D])> = self
            .images
            .iter()
            .map(|image| (&image.pose, image.points2d.as_slice()))
            .collect();
        create_file(&images_path, &encode_images(&images_path, &records)?)?;
        write_points3d_bin(&points_path, &self.points3d)
    }

    /// Checks the whole model: what [`ColmapModel::validate`] checks (cameras exist, unique image
    /// ids and names, finite poses), finite and unique 3D points, and observations and tracks that
    /// refer to each other (every point2D's 3D point lists it in its track, and every track element
    /// names an existing image, a point2D of it and that point2D sees this 3D point). `dir` is only
    /// used to name the files in errors.
    pub fn validate(&self, dir: &Path) -> Result<(), ColmapBinError> {
        let images_path = dir.join(IMAGES_BIN);
        self.to_model().validate(&images_path)?;
        self.check_observations(&images_path, &dir.join(POINTS3D_BIN))
    }

    fn check_observations(
        &self,
        images_path: &Path,
        points_path: &Path,
    ) -> Result<(), ColmapBinError> {
        let inconsistent = |path: &Path, why: String| ColmapBinError::Inconsistent {
            path: path.to_path_buf(),
            why,
        };
        let mut tracks: HashMap<u64, HashSet<TrackElement>> = HashMap::new();
        for (index, point) in self.points3d.iter().enumerate() {
            if point.point3d_id == INVALID_POINT3D_ID {
                return Err(inconsistent(
                    points_path,
                    format!(
                        "3D point #{index} has id {INVALID_POINT3D_ID}, COLMAP's 'no point' marker; give it another id"
                    ),
                ));
            }
            if !point.xyz.iter().all(|v| v.is_finite()) {
                return Err(inconsistent(
                    points_path,
                    format!(
                        "3D point {} has a non-finite position {:?}",
                        point.point3d_id, point.xyz
                    ),
                ));
            }
            if tracks
                .insert(point.point3d_id, point.track.iter().copied().collect())
                .is_some()
            {
                return Err(inconsistent(
                    points_path,
                    format!("3D point id {} is used twice", point.point3d_id),
                ));
            }
        }
        let images: HashMap<u32, &ImageRecord> = self
            .images
            .iter()
            .map(|image| (image.pose.image_id, image))
            .collect();
        for image in &self.images {
            for (index, point2d) in image.points2d.iter().enumerate() {
                let Some(point3d_id) = point2d.point3d_id else {
                    continue;
                };
                let element = TrackElement {
                    image_id: image.pose.image_id,
                    point2d_index: u32::try_from(index).unwrap_or(u32::MAX),
                };
                match tracks.get(&point3d_id) {
                    None => {
                        return Err(inconsistent(
                            images_path,
                            format!(
                                "image '{}' (IMAGE_ID {}), point2D {index} sees 3D point {point3d_id}, which {} does not hold; the two files are from different models",
                                image.pose.name,
                                image.pose.image_id,
                                points_path.display()
                            ),
                        ))
                    }
                    Some(track) if !track.contains(&element) => {
                        return Err(inconsistent(
                            points_path,
                            format!(
                                "the track of 3D point {point3d_id} lacks (IMAGE_ID {}, POINT2D_IDX {index}), which sees it in {}; the two files are from different models",
                                image.pose.image_id,
                                images_path.display()
                            ),
                        ))
                    }
                    Some(_) => {}
                }
            }
        }
        for point in &self.points3d {
            for element in &point.track {
                let seen = images.get(&element.image_id).and_then(|image| {
                    image
                        .points2d
                        .get(element.point2d_index as usize)
                        .map(|point2d| point2d.point3d_id)
                });
                if seen != Some(Some(point.point3d_id)) {
                    return Err(inconsistent(
                        points_path,
                        format!(
                            "3D point {} lists (IMAGE_ID {}, POINT2D_IDX {}) in its track, but {} has no such observation of it; the two files are from different models",
                            point.point3d_id,
                            element.image_id,
                            element.point2d_index,
                            images_path.display()
                        ),
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Reads `cameras.bin` and `images.bin` from `dir` (observations skipped, `points3D.bin` not
/// read) and checks that every image's camera exists.
pub fn read_model_bin(dir: &Path) -> Result<ColmapModel, ColmapBinError> {
    let cameras_path = dir.join(CAMERAS_BIN);
    let images_path = dir.join(IMAGES_BIN);
    let cameras = read_cameras_bin(&cameras_path)?;
    let images = decode_images(&images_path, &read_file(&images_path)?, false)?;
    check_cameras_exist(&cameras, &cameras_path, &images_path, &images)?;
    Ok(ColmapModel {
        cameras,
        images: images.into_iter().map(|image| image.pose).collect(),
    })
}

/// Writes `cameras.bin`, `images.bin` (without observations) and an empty `points3D.bin` into
/// `dir` (which must exist), after [`ColmapModel::validate`].
pub fn write_model_bin(dir: &Path, model: &ColmapModel) -> Result<(), ColmapBinError> {
    let images_path = dir.join(IMAGES_BIN);
    model.validate(&images_path)?;
    write_cameras_bin(&dir.join(CAMERAS_BIN), &model.cameras)?;
    write_images_bin(&images_path, &model.images)?;
    write_points3d_bin(&dir.join(POINTS3D_BIN), &[])
}

/// Reads `cameras.bin`: camera ids must be unique, every model one asgreg supports.
pub fn read_cameras_bin(path: &Path) -> Result<BTreeMap<u32, Camera>, ColmapBinError> {
    decode_cameras(path, &read_file(path)?)
}

/// Reads the poses of `images.bin` (observations are checked for length and skipped). Image ids
/// and names must be unique, poses finite, quaternions non-zero (they are normalised). Does not
/// check that the cameras exist: [`read_model_bin`] does.
pub fn read_images_bin(path: &Path) -> Result<Vec<ImagePose>, ColmapBinError> {
    Ok(decode_images(path, &read_file(path)?, false)?
        .into_iter()
        .map(|image| image.pose)
        .collect())
}

/// Reads `images.bin` with every image's observations.
pub fn read_image_records_bin(path: &Path) -> Result<Vec<ImageRecord>, ColmapBinError> {
    Ok(decode_images(path, &read_file(path)?, true)?
        .into_iter()
        .map(|image| ImageRecord {
            pose: image.pose,
            points2d: image.points2d,
        })
        .collect())
}

/// Reads `points3D.bin`: ids must be unique, positions finite.
pub fn read_points3d_bin(path: &Path) -> Result<Vec<Point3D>, ColmapBinError> {
    decode_points3d(path, &read_file(path)?)
}

/// Writes `cameras.bin` as COLMAP does (sorted by id). Fails, naming the camera, for a camera
/// COLMAP cannot store (skew, or intrinsics that do not fit its model).
pub fn write_cameras_bin(
    path: &Path,
    cameras: &BTreeMap<u32, Camera>,
) -> Result<(), ColmapBinError> {
    create_file(path, &encode_cameras(path, cameras)?)
}

/// Writes `images.bin` as COLMAP does, in the order given, without observations. Names must be
/// non-empty and free of NUL bytes, poses finite.
pub fn write_images_bin(path: &Path, images: &[ImagePose]) -> Result<(), ColmapBinError> {
    let records: Vec<(&ImagePose, &[Point2D])> =
        images.iter().map(|image| (image, &[][..])).collect();
    create_file(path, &encode_images(path, &records)?)
}

/// Writes `images.bin` with observations, as COLMAP does, in the order given.
pub fn write_image_records_bin(path: &Path, images: &[ImageRecord]) -> Result<(), ColmapBinError> {
    let records: Vec<(&ImagePose, &[Point2D])> = images
        .iter()
        .map(|image| (&image.pose, image.points2d.as_slice()))
        .collect();
    create_file(path, &encode_images(path, &records)?)
}

/// Writes `points3D.bin` as COLMAP does, in the order given (COLMAP sorts by id).
pub fn write_points3d_bin(path: &Path, points: &[Point3D]) -> Result<(), ColmapBinError> {
    create_file(path, &encode_points3d(path, points)?)
}

fn read_file(path: &Path) -> Result<Vec<u8>, ColmapBinError> {
    fs::read(path).map_err(|source| ColmapBinError::Io {
        path: path.to_path_buf(),
        source,
    })
}

fn create_file(path: &Path, bytes: &[u8]) -> Result<(), ColmapBinError> {
    let io_error = |source| ColmapBinError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut file = fs::File::create(path).map_err(io_error)?;
    file.write_all(bytes).map_err(io_error)?;
    file.sync_all().map_err(io_error)
}

/// An image as decoded, with where its `CAMERA_ID` is (for errors about a missing camera).
struct DecodedImage {
    pose: ImagePose,
    points2d: Vec<Point2D>,
    record: u64,
    count: u64,
    camera_id_offset: usize,
}

fn check_cameras_exist(
    cameras: &BTreeMap<u32, Camera>,
    cameras_path: &Path,
    images_path: &Path,
    images: &[DecodedImage],
) -> Result<(), ColmapBinError> {
    for image in images {
        if !cameras.contains_key(&image.pose.camera_id) {
            return Err(ColmapBinError::MissingCamera {
                location: Box::new(Location {
                    path: images_path.to_path_buf(),
                    kind: RecordKind::Image,
                    record: image.record,
                    count: image.count,
                    offset: image.camera_id_offset,
                }),
                image_id: image.pose.image_id,
                image_name: image.pose.name.clone(),
                camera_id: image.pose.camera_id,
                cameras_path: cameras_path.to_path_buf(),
            });
        }
    }
    Ok(())
}

/// Reads little-endian fields from a whole file in memory, knowing which record it is in.
struct Cursor<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
    kind: RecordKind,
    record: u64,
    count: u64,
}

impl<'a> Cursor<'a> {
    fn new(path: &'a Path, bytes: &'a [u8], kind: RecordKind) -> Self {
        Self {
            path,
            bytes,
            pos: 0,
            kind,
            record: 0,
            count: 0,
        }
    }

    fn left(&self) -> usize {
        self.bytes.len() - self.pos
    }

    fn location_at(&self, offset: usize) -> Box<Location> {
        Box::new(Location {
            path: self.path.to_path_buf(),
            kind: self.kind,
            record: self.record,
            count: self.count,
            offset,
        })
    }

    fn field_error(
        &self,
        offset: usize,
        field: &str,
        found: String,
        expected: impl Into<String>,
    ) -> ColmapBinError {
        ColmapBinError::Field {
            location: self.location_at(offset),
            field: field.to_string(),
            found,
            expected: expected.into(),
        }
    }

    fn take(&mut self, n: usize, field: &str) -> Result<&'a [u8], ColmapBinError> {
        if self.left() < n {
            return Err(ColmapBinError::Truncated {
                location: self.location_at(self.pos),
                field: field.to_string(),
                needed: n,
                left: self.left(),
            });
        }
        let bytes = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(bytes)
    }

    fn array<const N: usize>(&mut self, field: &str) -> Result<[u8; N], ColmapBinError> {
        let mut array = [0u8; N];
        array.copy_from_slice(self.take(N, field)?);
        Ok(array)
    }

    fn u8(&mut self, field: &str) -> Result<u8, ColmapBinError> {
        Ok(self.array::<1>(field)?[0])
    }

    fn u32(&mut self, field: &str) -> Result<u32, ColmapBinError> {
        Ok(u32::from_le_bytes(self.array(field)?))
    }

    fn i32(&mut self, field: &str) -> Result<i32, ColmapBinError> {
        Ok(i32::from_le_bytes(self.array(field)?))
    }

    fn u64(&mut self, field: &str) -> Result<u64, ColmapBinError> {
        Ok(u64::from_le_bytes(self.array(field)?))
    }

    fn f64(&mut self, field: &str) -> Result<f64, ColmapBinError> {
        Ok(f64::from_le_bytes(self.array(field)?))
    }

    fn finite_f64(&mut self, field: &str) -> Result<f64, ColmapBinError> {
        let offset = self.pos;
        let value = self.f64(field)?;
        if value.is_finite() {
            Ok(value)
        } else {
            Err(self.field_error(
                offset,
                field,
                format!("{value}"),
                "expected a finite number (NaN and infinity are not valid here); fix or remove this entry",
            ))
        }
    }

    /// A `u64` count of items of at least `item_bytes` each, refused unless the bytes left can
    /// hold them (so that no count makes the reader allocate more than the file's size).
    fn count(
        &mut self,
        field: &'static str,
        items: &'static str,
        item_bytes: usize,
    ) -> Result<usize, ColmapBinError> {
        let offset = self.pos;
        let count = self.u64(field)?;
        let needed = u128::from(count) * item_bytes as u128;
        if needed > self.left() as u128 {
            return Err(ColmapBinError::Count {
                location: self.location_at(offset),
                field,
                items,
                count,
                needed,
                left: self.left(),
            });
        }
        // needed <= left, so the count fits in usize.
        Ok(count as usize)
    }

    /// A pixel size stored as `u64`: positive and at most `u32::MAX`.
    fn dimension(&mut self, field: &str) -> Result<u32, ColmapBinError> {
        let offset = self.pos;
        let value = self.u64(field)?;
        match u32::try_from(value) {
            Ok(value) if value > 0 => Ok(value),
            _ => Err(self.field_error(
                offset,
                field,
                value.to_string(),
                "expected a positive number of pixels below 2^32",
            )),
        }
    }

    /// A NUL-terminated UTF-8 name, non-empty.
    fn name(&mut self, field: &str) -> Result<String, ColmapBinError> {
        let offset = self.pos;
        let rest = &self.bytes[self.pos..];
        let Some(length) = rest.iter().position(|&byte| byte == 0) else {
            return Err(self.field_error(
                offset,
                field,
                format!("no NUL byte in the {} bytes left", rest.len()),
                format!(
                    "every NAME ends in a NUL byte; the file is cut short or is not a COLMAP {}",
                    self.kind.file_name()
                ),
            ));
        };
        let name = std::str::from_utf8(&rest[..length]).map_err(|error| {
            self.field_error(
                offset,
                field,
                format!("{:?}", String::from_utf8_lossy(&rest[..length])),
                format!("expected UTF-8 text ({error}); rename the image"),
            )
        })?;
        if name.is_empty() {
            return Err(self.field_error(
                offset,
                field,
                "an empty name".to_string(),
                "every image needs the file name of its photo",
            ));
        }
        self.pos += length + 1;
        Ok(name.to_string())
    }

    /// Refuses bytes after the last record.
    fn finish(&self) -> Result<(), ColmapBinError> {
        if self.left() > 0 {
            return Err(ColmapBinError::TrailingBytes {
                path: self.path.to_path_buf(),
                kind: self.kind,
                count: self.count,
                offset: self.pos,
                extra: self.left(),
            });
        }
        Ok(())
    }
}

fn decode_cameras(path: &Path, bytes: &[u8]) -> Result<BTreeMap<u32, Camera>, ColmapBinError> {
    let mut cursor = Cursor::new(path, bytes, RecordKind::Camera);
    let count = cursor.count("number of cameras", "cameras", CAMERA_MIN_BYTES)?;
    cursor.count = count as u64;
    let mut cameras = BTreeMap::new();
    let mut first_record = HashMap::new();
    for index in 0..count {
        cursor.record = index as u64 + 1;
        let start = cursor.pos;
        let camera_id = cursor.u32("CAMERA_ID")?;
        let model_offset = cursor.pos;
        let model_id = cursor.i32("MODEL_ID")?;
        let model = model_from_colmap_id(model_id).map_err(|expected| {
            cursor.field_error(model_offset, "MODEL_ID", model_id.to_string(), expected)
        })?;
        let width_px = cursor.dimension("WIDTH")?;
        let height_px = cursor.dimension("HEIGHT")?;
        let params_offset = cursor.pos;
        let mut params = Vec::with_capacity(model.param_count());
        for param in 0..model.param_count() {
            params.push(cursor.finite_f64(&format!("PARAMS[{param}]"))?);
        }
        let camera =
            Camera::from_colmap_params(model, width_px, height_px, &params).map_err(|source| {
                ColmapBinError::Camera {
                    location: cursor.location_at(params_offset),
                    camera_id,
                    field: "PARAMS[]",
                    source,
                }
            })?;
        if let Some(first_record) = first_record.insert(camera_id, cursor.record) {
            return Err(ColmapBinError::Duplicate {
                location: cursor.location_at(start),
                field: "CAMERA_ID",
                value: camera_id.to_string(),
                first_record,
            });
        }
        cameras.insert(camera_id, camera);
    }
    cursor.finish()?;
    Ok(cameras)
}

fn decode_images(
    path: &Path,
    bytes: &[u8],
    keep_points: bool,
) -> Result<Vec<DecodedImage>, ColmapBinError> {
    let mut cursor = Cursor::new(path, bytes, RecordKind::Image);
    let count = cursor.count("number of images", "images", IMAGE_MIN_BYTES)?;
    cursor.count = count as u64;
    let mut images = Vec::with_capacity(count);
    let mut first_record_of_id = HashMap::new();
    let mut first_record_of_name: HashMap<String, u64> = HashMap::new();
    for index in 0..count {
        cursor.record = index as u64 + 1;
        let start = cursor.pos;
        let image_id = cursor.u32("IMAGE_ID")?;
        let qvec_offset = cursor.pos;
        let mut qvec_wxyz = [0.0; 4];
        for (value, field) in qvec_wxyz.iter_mut().zip(["QW", "QX", "QY", "QZ"]) {
            *value = cursor.finite_f64(field)?;
        }
        let mut tvec = [0.0; 3];
        for (value, field) in tvec.iter_mut().zip(["TX", "TY", "TZ"]) {
            *value = cursor.finite_f64(field)?;
        }
        let norm = qvec_wxyz.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm <= 1e-12 {
            return Err(cursor.field_error(
                qvec_offset,
                "QW QX QY QZ",
                format!("{qvec_wxyz:?}"),
                "the quaternion has (almost) zero length and is no rotation; fix the pose",
            ));
        }
        let camera_id_offset = cursor.pos;
        let camera_id = cursor.u32("CAMERA_ID")?;
        let name = cursor.name("NAME")?;
        let num_points = cursor.count("NUM_POINTS2D", "points2D", POINT2D_BYTES)?;
        let points2d = if keep_points {
            let mut points2d = Vec::with_capacity(num_points);
            for point in 0..num_points {
                let field = |what: &str| format!("POINTS2D[{point}].{what}");
                let x = cursor.f64(&field("X"))?;
                let y = cursor.f64(&field("Y"))?;
                let id = cursor.u64(&field("POINT3D_ID"))?;
                points2d.push(Point2D {
                    xy_px: [x, y],
                    point3d_id: (id != INVALID_POINT3D_ID).then_some(id),
                });
            }
            points2d
        } else {
            cursor.take(num_points * POINT2D_BYTES, "POINTS2D[]")?;
            Vec::new()
        };
        if let Some(first_record) = first_record_of_id.insert(image_id, cursor.record) {
            return Err(ColmapBinError::Duplicate {
                location: cursor.location_at(start),
                field: "IMAGE_ID",
                value: image_id.to_string(),
                first_record,
            });
        }
        if let Some(&first_record) = first_record_of_name.get(&name) {
            return Err(ColmapBinError::Duplicate {
                location: cursor.location_at(start),
                field: "NAME",
                value: format!("'{name}'"),
                first_record,
            });
        }
        first_record_of_name.insert(name.clone(), cursor.record);
        images.push(DecodedImage {
            pose: ImagePose {
                image_id,
                camera_id,
                name,
                cam_from_world: pose_from_qvec(qvec_wxyz, norm, tvec),
            },
            points2d,
            record: cursor.record,
            count: count as u64,
            camera_id_offset,
        });
    }
    cursor.finish()?;
    Ok(images)
}

/// A quaternion whose norm is 1 to within this is kept bit for bit (COLMAP's are: it writes
/// normalised quaternions); others are normalised.
const UNIT_NORM_TOLERANCE: f64 = 1e-12;

/// The pose of an image record: the quaternion as stored when it is a unit quaternion already, so
/// that reading and writing a COLMAP file reproduces it byte for byte (COLMAP itself reads the
/// values as they are); otherwise normalised as the text reader does.
fn pose_from_qvec(qvec_wxyz: [f64; 4], norm: f64, tvec: [f64; 3]) -> Rigid3 {
    if (norm - 1.0).abs() <= UNIT_NORM_TOLERANCE {
        let [w, x, y, z] = qvec_wxyz;
        Rigid3::new(
            UnitQuaternion::new_unchecked(Quaternion::new(w, x, y, z)),
            Vector3::from(tvec),
        )
    } else {
        pose_from_colmap(qvec_wxyz, tvec)
    }
}

fn decode_points3d(path: &Path, bytes: &[u8]) -> Result<Vec<Point3D>, ColmapBinError> {
    let mut cursor = Cursor::new(path, bytes, RecordKind::Point3D);
    let count = cursor.count("number of points3D", "points3D", POINT3D_MIN_BYTES)?;
    cursor.count = count as u64;
    let mut points = Vec::with_capacity(count);
    let mut first_record = HashMap::new();
    for index in 0..count {
        cursor.record = index as u64 + 1;
        let start = cursor.pos;
        let point3d_id = cursor.u64("POINT3D_ID")?;
        if point3d_id == INVALID_POINT3D_ID {
            return Err(cursor.field_error(
                start,
                "POINT3D_ID",
                point3d_id.to_string(),
                "this is COLMAP's 'no point' marker, not a point id; the file is damaged",
            ));
        }
        let mut xyz = Vector3::zeros();
        for (axis, field) in ["X", "Y", "Z"].into_iter().enumerate() {
            xyz[axis] = cursor.finite_f64(field)?;
        }
        let rgb = [cursor.u8("R")?, cursor.u8("G")?, cursor.u8("B")?];
        let error_px = cursor.f64("ERROR")?;
        let track_length = cursor.count("TRACK_LENGTH", "track elements", TRACK_ELEMENT_BYTES)?;
        let mut track = Vec::with_capacity(track_length);
        for element in 0..track_length {
            let image_id = cursor.u32(&format!("TRACK[{element}].IMAGE_ID"))?;
            let point2d_index = cursor.u32(&format!("TRACK[{element}].POINT2D_IDX"))?;
            track.push(TrackElement {
                image_id,
                point2d_index,
            });
        }
        if let Some(first_record) = first_record.insert(point3d_id, cursor.record) {
            return Err(ColmapBinError::Duplicate {
                location: cursor.location_at(start),
                field: "POINT3D_ID",
                value: point3d_id.to_string(),
                first_record,
            });
        }
        points.push(Point3D {
            point3d_id,
            xyz,
            rgb,
            error_px,
            track,
        });
    }
    cursor.finish()?;
    Ok(points)
}

fn encode_cameras(path: &Path, cameras: &BTreeMap<u32, Camera>) -> Result<Vec<u8>, ColmapBinError> {
    let mut bytes = Vec::with_capacity(8 + cameras.len() * (CAMERA_MIN_BYTES + 8 * 8));
    bytes.extend_from_slice(&(cameras.len() as u64).to_le_bytes());
    for (&camera_id, camera) in cameras {
        check_representable(path, camera_id, camera)?;
        bytes.extend_from_slice(&camera_id.to_le_bytes());
        bytes.extend_from_slice(&colmap_model_id(camera.model).to_le_bytes());
        bytes.extend_from_slice(&u64::from(camera.width_px).to_le_bytes());
        bytes.extend_from_slice(&u64::from(camera.height_px).to_le_bytes());
        for param in camera.colmap_params() {
            bytes.extend_from_slice(&param.to_le_bytes());
        }
    }
    Ok(bytes)
}

fn encode_images(
    path: &Path,
    images: &[(&ImagePose, &[Point2D])],
) -> Result<Vec<u8>, ColmapBinError> {
    let mut bytes = Vec::new();
    bytes.extend_from_slice(&(images.len() as u64).to_le_bytes());
    for (image, points2d) in images {
        let invalid = |why: String| ColmapBinError::InvalidImage {
            path: path.to_path_buf(),
            image_id: image.image_id,
            why,
        };
        if image.name.is_empty() || image.name.contains('\0') {
            return Err(invalid(format!(
                "name {:?} cannot be stored: it must be non-empty and free of NUL characters",
                image.name
            )));
        }
        if !image.cam_from_world.is_finite() {
            return Err(invalid(format!("pose of '{}' is not finite", image.name)));
        }
        bytes.extend_from_slice(&image.image_id.to_le_bytes());
        let q = image.cam_from_world.rotation.quaternion();
        let t = image.cam_from_world.translation;
        for value in [q.w, q.i, q.j, q.k, t.x, t.y, t.z] {
            bytes.extend_from_slice(&value.to_le_bytes());
        }
        bytes.extend_from_slice(&image.camera_id.to_le_bytes());
        bytes.extend_from_slice(image.name.as_bytes());
        bytes.push(0);
        bytes.extend_from_slice(&(points2d.len() as u64).to_le_bytes());
        for point in *points2d {
            bytes.extend_from_slice(&point.xy_px[0].to_le_bytes());
            bytes.extend_from_slice(&point.xy_px[1].to_le_bytes());
            let id = point.point3d_id.unwrap_or(INVALID_POINT3D_ID);
            bytes.extend_from_slice(&id.to_le_bytes());
        }
    }
    Ok(bytes)
}

fn encode_points3d(path: &Path, points: &[Point3D]) -> Result<Vec<u8>, ColmapBinError> {
    let mut bytes = Vec::new();
    bytes.extend_from_slice(&(points.len() as u64).to_le_bytes());
    for point in points {
        if point.point3d_id == INVALID_POINT3D_ID || !point.xyz.iter().all(|v| v.is_finite()) {
            return Err(ColmapBinError::Inconsistent {
                path: path.to_path_buf(),
                why: format!(
                    "3D point {} cannot be stored: its id must not be {INVALID_POINT3D_ID} and its position must be finite ({:?})",
                    point.point3d_id, point.xyz
                ),
            });
        }
        bytes.extend_from_slice(&point.point3d_id.to_le_bytes());
        for value in point.xyz.iter() {
            bytes.extend_from_slice(&value.to_le_bytes());
        }
        bytes.extend_from_slice(&point.rgb);
        bytes.extend_from_slice(&point.error_px.to_le_bytes());
        bytes.extend_from_slice(&(point.track.len() as u64).to_le_bytes());
        for element in &point.track {
            bytes.extend_from_slice(&element.image_id.to_le_bytes());
            bytes.extend_from_slice(&element.point2d_index.to_le_bytes());
        }
    }
    Ok(bytes)
}

#[cfg(test)]
#[path = "colmap_bin_tests.rs"]
mod tests;
