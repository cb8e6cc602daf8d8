//! COLMAP text models (`cameras.txt`, `images.txt`, `points3D.txt`): the format ground truth comes
//! in and registered poses go out in, so that asgreg's results open in COLMAP and its tools.
//!
//! Only what registration needs is kept: cameras, and per image its id, camera, name and
//! `cam_from_world` pose. The 2D observations of `images.txt` are skipped on reading (their line is
//! checked for shape only) and written empty; `points3D.txt` is written empty.
//!
//! Files are written exactly the way COLMAP 3.x writes them (same header comments, one space between
//! fields, quaternion with `QW >= 0`). Floats use Rust's shortest representation that reads back to
//! the same `f64`, so a write → read round trip is exact. Every reading error names the file, the
//! 1-based line number and the field (`QW`, `WIDTH`, `PARAMS[2]`, …), says what was found and what
//! to do about it.

use std::collections::BTreeMap;
use std::collections::HashMap;
use std::fmt::Write as _;
use std::fs;
use std::io::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::core::camera::{Camera, CameraError, CameraModelId};
use crate::core::rigid::Rigid3;

/// File names of a COLMAP text model inside its directory.
pub const CAMERAS_FILE: &str = "cameras.txt";
pub const IMAGES_FILE: &str = "images.txt";
pub const POINTS3D_FILE: &str = "points3D.txt";

/// Errors of reading and writing COLMAP text models. Each names the file it is about.
#[derive(Debug, thiserror::Error)]
pub enum ColmapError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}:{line}: field {field}: found {found}; {expected}", path.display())]
    Parse {
        path: PathBuf,
        /// 1-based line number in the file.
        line: usize,
        /// The COLMAP column name, e.g. `QW`, `WIDTH`, `PARAMS[2]`.
        field: String,
        /// What the line holds there (quoted), or `end of line`.
        found: String,
        /// What was expected and how to fix it.
        expected: String,
    },
    #[error(
        "{}:{line}: camera {camera_id}, field {field}: {source}; fix this camera line (other models: undistort the images to PINHOLE, e.g. with COLMAP's image_undistorter)",
        path.display()
    )]
    Camera {
        path: PathBuf,
        line: usize,
        camera_id: u32,
        field: &'static str,
        #[source]
        source: CameraError,
    },
    #[error(
        "{}:{line}: duplicate {field} {value}: already used on line {first_line}; every {field} must be unique",
        path.display()
    )]
    Duplicate {
        path: PathBuf,
        line: usize,
        field: &'static str,
        value: String,
        first_line: usize,
    },
    #[error(
        "{}:{line}: image '{image_name}' (IMAGE_ID {image_id}) uses CAMERA_ID {camera_id}, which {} does not define; add the camera there or fix the image's CAMERA_ID",
        path.display(), cameras_path.display()
    )]
    MissingCamera {
        path: PathBuf,
        line: usize,
        image_id: u32,
        image_name: String,
        camera_id: u32,
        cameras_path: PathBuf,
    },
    #[error(
        "{}: camera {camera_id} has skew {skew_px} px, which no COLMAP camera model can store; refine the camera without skew (or drop the skew) before writing it",
        path.display()
    )]
    SkewNotRepresentable {
        path: PathBuf,
        camera_id: u32,
        skew_px: f64,
    },
    #[error(
        "{}: camera {camera_id} cannot be written as {model}: {why}",
        path.display()
    )]
    NotRepresentable {
        path: PathBuf,
        camera_id: u32,
        model: &'static str,
        why: String,
    },
    #[error("{}: image {image_id}: {why}", path.display())]
    InvalidImage {
        path: PathBuf,
        image_id: u32,
        why: String,
    },
}

/// One registered image of a COLMAP model: which camera took it and its pose.
#[derive(Clone, Debug, PartialEq)]
pub struct ImagePose {
    pub image_id: u32,
    pub camera_id: u32,
    /// File name relative to the image directory, as in COLMAP (`DJI_0025.JPG`).
    pub name: String,
    /// `x_cam = R · x_world + t` (COLMAP's convention).
    pub cam_from_world: Rigid3,
}

/// Cameras and image poses of a COLMAP text model (3D points are not kept).
#[derive(Clone, Debug, PartialEq, Default)]
pub struct ColmapModel {
    pub cameras: BTreeMap<u32, Camera>,
    pub images: Vec<ImagePose>,
}

impl ColmapModel {
    /// Reads `cameras.txt` and `images.txt` from `dir` and checks that they agree (every image's
    /// camera exists). `points3D.txt` is neither needed nor read.
    pub fn read_model(dir: &Path) -> Result<Self, ColmapError> {
        let cameras_path = dir.join(CAMERAS_FILE);
        let images_path = dir.join(IMAGES_FILE);
        let cameras = read_cameras_txt(&cameras_path)?;
        let images = read_images_with_lines(&images_path)?;
        for (image, line) in &images {
            if !cameras.contains_key(&image.camera_id) {
                return Err(ColmapError::MissingCamera {
                    path: images_path.clone(),
                    line: *line,
                    image_id: image.image_id,
                    image_name: image.name.clone(),
                    camera_id: image.camera_id,
                    cameras_path: cameras_path.clone(),
                });
            }
        }
        Ok(Self {
            cameras,
            images: images.into_iter().map(|(image, _)| image).collect(),
        })
    }

    /// Writes `cameras.txt`, `images.txt` and an empty `points3D.txt` into `dir` (which must
    /// exist), after [`Self::validate`].
    pub fn write_model(&self, dir: &Path) -> Result<(), ColmapError> {
        self.validate(&dir.join(IMAGES_FILE))?;
        write_cameras_txt(&dir.join(CAMERAS_FILE), &self.cameras)?;
        write_images_txt(&dir.join(IMAGES_FILE), &self.images)?;
        write_empty_points3d_txt(&dir.join(POINTS3D_FILE))
    }

    /// Checks an in-memory model: every image's camera exists, image ids and names are unique,
    /// poses are finite. `images_path` is only used to name the file in errors.
    pub fn validate(&self, images_path: &Path) -> Result<(), ColmapError> {
        let mut ids = HashMap::new();
        let mut names = HashMap::new();
        for (index, image) in self.images.iter().enumerate() {
            let invalid = |why: String| ColmapError::InvalidImage {
                path: images_path.to_path_buf(),
                image_id: image.image_id,
                why,
            };
            if !self.cameras.contains_key(&image.camera_id) {
                return Err(invalid(format!(
                    "'{}' uses camera {}, which the model does not have",
                    image.name, image.camera_id
                )));
            }
            if let Some(first) = ids.insert(image.image_id, index) {
                return Err(invalid(format!(
                    "IMAGE_ID used by images #{first} and #{index} of the list"
                )));
            }
            if let Some(first) = names.insert(image.name.as_str(), index) {
                return Err(invalid(format!(
                    "name '{}' used by images #{first} and #{index} of the list",
                    image.name
                )));
            }
            if !image.cam_from_world.is_finite() {
                return Err(invalid(format!("pose of '{}' is not finite", image.name)));
            }
        }
        Ok(())
    }

    /// The camera that took `image`, if the model has it.
    pub fn camera_of(&self, image: &ImagePose) -> Option<&Camera> {
        self.cameras.get(&image.camera_id)
    }

    /// The image with this file name.
    pub fn image_by_name(&self, name: &str) -> Option<&ImagePose> {
        self.images.iter().find(|image| image.name == name)
    }
}

/// Reads a COLMAP text model from `dir` (same as [`ColmapModel::read_model`]).
pub fn read_model(dir: &Path) -> Result<ColmapModel, ColmapError> {
    ColmapModel::read_model(dir)
}

/// Writes a COLMAP text model into `dir` (same as [`ColmapModel::write_model`]).
pub fn write_model(dir: &Path, model: &ColmapModel) -> Result<(), ColmapError> {
    model.write_model(dir)
}

/// The data lines of a text file: `(1-based line number, trimmed text)`, comments and blank
/// lines included (callers decide what to skip).
fn read_lines(path: &Path) -> Result<Vec<(usize, String)>, ColmapError> {
    let text = crate::io::text::read_utf8(path).map_err(|source| ColmapError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    // A byte-order mark (some Windows editors add one) is no part of the first field.
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    Ok(text
        .lines()
        .enumerate()
        .map(|(index, line)| (index + 1, line.trim().to_string()))
        .collect())
}

fn is_skipped(line: &str) -> bool {
    line.is_empty() || line.starts_with('#')
}

/// Splits one data line into fields and parses them by COLMAP column name.
struct FieldReader<'a> {
    path: &'a Path,
    line: usize,
    fields: std::iter::Peekable<std::str::SplitWhitespace<'a>>,
}

impl<'a> FieldReader<'a> {
    fn new(path: &'a Path, line: usize, text: &'a str) -> Self {
        Self {
            path,
            line,
            fields: text.split_whitespace().peekable(),
        }
    }

    fn error(&self, field: &str, found: String, expected: impl Into<String>) -> ColmapError {
        ColmapError::Parse {
            path: self.path.to_path_buf(),
            line: self.line,
            field: field.to_string(),
            found,
            expected: expected.into(),
        }
    }

    fn next_str(&mut self, field: &str, line_format: &str) -> Result<&'a str, ColmapError> {
        match self.fields.next() {
            Some(text) => Ok(text),
            None => Err(self.error(
                field,
                "end of line".to_string(),
                format!("the line has too few fields; the format is: {line_format}"),
            )),
        }
    }

    fn next_u32(&mut self, field: &str, line_format: &str) -> Result<u32, ColmapError> {
        let text = self.next_str(field, line_format)?;
        text.parse::<u32>().map_err(|_| {
            self.error(
                field,
                format!("'{text}'"),
                "expected a whole number from 0 to 4294967295",
            )
        })
    }

    fn next_positive_u32(&mut self, field: &str, line_format: &str) -> Result<u32, ColmapError> {
        let text = self.next_str(field, line_format)?;
        match text.parse::<u32>() {
            Ok(value) if value > 0 => Ok(value),
            _ => Err(self.error(
                field,
                format!("'{text}'"),
                "expected a positive whole number of pixels",
            )),
        }
    }

    fn next_f64(&mut self, field: &str, line_format: &str) -> Result<f64, ColmapError> {
        let text = self.next_str(field, line_format)?;
        match text.parse::<f64>() {
            Ok(value) if value.is_finite() => Ok(value),
            Ok(_) => Err(self.error(
                field,
                format!("'{text}'"),
                "expected a finite number (NaN and infinity are not valid here); fix or remove this entry",
            )),
            Err(_) => Err(self.error(field, format!("'{text}'"), "expected a number")),
        }
    }

    /// The rest of the line, joined by single spaces (`None` when nothing is left).
    fn rest(&mut self) -> Option<String> {
        self.fields.peek()?;
        Some(self.fields.by_ref().collect::<Vec<_>>().join(" "))
    }
}

const CAMERA_LINE_FORMAT: &str = "CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]";
const IMAGE_LINE_FORMAT: &str = "IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME";

/// Reads `cameras.txt`. Camera ids must be unique; every model must be one asgreg supports.
pub fn read_cameras_txt(path: &Path) -> Result<BTreeMap<u32, Camera>, ColmapError> {
    let mut cameras = BTreeMap::new();
    let mut first_lines = HashMap::new();
    for (line, text) in read_lines(path)? {
        if is_skipped(&text) {
            continue;
        }
        let mut fields = FieldReader::new(path, line, &text);
        let camera_id = fields.next_u32("CAMERA_ID", CAMERA_LINE_FORMAT)?;
        let model_name = fields.next_str("MODEL", CAMERA_LINE_FORMAT)?;
        let model =
            CameraModelId::from_colmap_name(model_name).map_err(|source| ColmapError::Camera {
                path: path.to_path_buf(),
                line,
                camera_id,
                field: "MODEL",
                source,
            })?;
        let width_px = fields.next_positive_u32("WIDTH", CAMERA_LINE_FORMAT)?;
        let height_px = fields.next_positive_u32("HEIGHT", CAMERA_LINE_FORMAT)?;
        let mut params = Vec::with_capacity(model.param_count());
        while fields.fields.peek().is_some() {
            let field = format!("PARAMS[{}]", params.len());
            params.push(fields.next_f64(&field, CAMERA_LINE_FORMAT)?);
        }
        let camera =
            Camera::from_colmap_params(model, width_px, height_px, &params).map_err(|source| {
                ColmapError::Camera {
                    path: path.to_path_buf(),
                    line,
                    camera_id,
                    field: "PARAMS[]",
                    source,
                }
            })?;
        if let Some(first_line) = first_lines.insert(camera_id, line) {
            return Err(ColmapError::Duplicate {
                path: path.to_path_buf(),
                line,
                field: "CAMERA_ID",
                value: camera_id.to_string(),
                first_line,
            });
        }
        cameras.insert(camera_id, camera);
    }
    Ok(cameras)
}

/// Reads `images.txt`: image id, pose, camera id and name per image; the POINTS2D lines are
/// skipped. Image ids and names must be unique, poses finite, quaternions non-zero (they are
/// normalised). Does not check that the cameras exist: [`read_model`] does.
pub fn read_images_txt(path: &Path) -> Result<Vec<ImagePose>, ColmapError> {
    Ok(read_images_with_lines(path)?
        .into_iter()
        .map(|(image, _)| image)
        .collect())
}

/// [`read_images_txt`] with the line number of each image's first line.
fn read_images_with_lines(path: &Path) -> Result<Vec<(ImagePose, usize)>, ColmapError> {
    let lines = read_lines(path)?;
    let mut images = Vec::new();
    let mut first_line_of_id = HashMap::new();
    let mut first_line_of_name: HashMap<String, usize> = HashMap::new();
    let mut remaining = lines.iter();
    while let Some((line, text)) = remaining.next() {
        let (line, text) = (*line, text.as_str());
        if is_skipped(text) {
            continue;
        }
        let mut fields = FieldReader::new(path, line, text);
        let image_id = fields.next_u32("IMAGE_ID", IMAGE_LINE_FORMAT)?;
        let mut qvec_wxyz = [0.0; 4];
        for (value, field) in qvec_wxyz.iter_mut().zip(["QW", "QX", "QY", "QZ"]) {
            *value = fields.next_f64(field, IMAGE_LINE_FORMAT)?;
        }
        let mut tvec = [0.0; 3];
        for (value, field) in tvec.iter_mut().zip(["TX", "TY", "TZ"]) {
            *value = fields.next_f64(field, IMAGE_LINE_FORMAT)?;
        }
        let camera_id = fields.next_u32("CAMERA_ID", IMAGE_LINE_FORMAT)?;
        let name = fields.rest().ok_or_else(|| {
            fields.error(
                "NAME",
                "end of line".to_string(),
                format!("the line has too few fields; the format is: {IMAGE_LINE_FORMAT}"),
            )
        })?;
        let norm = qvec_wxyz.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm <= 1e-12 {
            return Err(fields.error(
                "QW QX QY QZ",
                format!("{qvec_wxyz:?}"),
                "the quaternion has (almost) zero length and is no rotation; fix the pose",
            ));
        }
        let cam_from_world = pose_from_colmap(qvec_wxyz, tvec);

        // The second line of the record: POINTS2D as (X, Y, POINT3D_ID) triples, possibly empty.
        // COLMAP reads it whatever it holds; a count that is no multiple of three usually means
        // that a writer left the empty line out and this is already the next image.
        if let Some((points_line, points_text)) = remaining.next() {
            let field_count = points_text.split_whitespace().count();
            if field_count % 3 != 0 {
                return Err(ColmapError::Parse {
                    path: path.to_path_buf(),
                    line: *points_line,
                    field: "POINTS2D[]".to_string(),
                    found: format!("{field_count} fields"),
                    expected: format!(
                        "the line after image {image_id} must hold (X, Y, POINT3D_ID) triples or be empty; every image takes two lines (is the empty second line missing?)"
                    ),
                });
            }
        }

        if let Some(first_line) = first_line_of_id.insert(image_id, line) {
            return Err(ColmapError::Duplicate {
                path: path.to_path_buf(),
                line,
                field: "IMAGE_ID",
                value: image_id.to_string(),
                first_line,
            });
        }
        if let Some(&first_line) = first_line_of_name.get(&name) {
            return Err(ColmapError::Duplicate {
                path: path.to_path_buf(),
                line,
                field: "NAME",
                value: format!("'{name}'"),
                first_line,
            });
        }
        first_line_of_name.insert(name.clone(), line);
        images.push((
            ImagePose {
                image_id,
                camera_id,
                name,
                cam_from_world,
            },
            line,
        ));
    }
    Ok(images)
}

/// Builds a pose from COLMAP's fields. The quaternion (non-zero, finite) is normalised until its
/// norm is exactly 1.0 in floating point (one division can leave it an ulp off), so that a
/// normalised quaternion written by [`write_images_txt`] reads back bit for bit.
pub(crate) fn pose_from_colmap(qvec_wxyz: [f64; 4], tvec: [f64; 3]) -> Rigid3 {
    let [w, x, y, z] = qvec_wxyz;
    let mut quaternion = Quaternion::new(w, x, y, z);
    for _ in 0..4 {
        let norm = quaternion.norm();
        if norm == 1.0 {
            break;
        }
        quaternion /= norm;
    }
    Rigid3::new(
        UnitQuaternion::new_unchecked(quaternion),
        Vector3::from(tvec),
    )
}

/// Formats an `f64` so that it reads back to the same value: shortest decimal form, switching to
/// exponent notation for very large or small magnitudes (as C++ streams do).
fn format_f64(value: f64) -> String {
    let magnitude = value.abs();
    if value != 0.0 && !(1e-5..1e16).contains(&magnitude) {
        format!("{value:e}")
    } else {
        format!("{value}")
    }
}

fn create_file(path: &Path, contents: &str) -> Result<(), ColmapError> {
    let io_error = |source| ColmapError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut file = fs::File::create(path).map_err(io_error)?;
    file.write_all(contents.as_bytes()).map_err(io_error)?;
    file.sync_all().map_err(io_error)
}

/// Checks that COLMAP can store `camera` exactly: no skew, and intrinsics and distortion that fit
/// its model (e.g. `fx == fy` for SIMPLE_PINHOLE).
pub(crate) fn check_representable(
    path: &Path,
    camera_id: u32,
    camera: &Camera,
) -> Result<(), ColmapError> {
    if camera.intrinsics.skew_px != 0.0 {
        return Err(ColmapError::SkewNotRepresentable {
            path: path.to_path_buf(),
            camera_id,
            skew_px: camera.intrinsics.skew_px,
        });
    }
    let model = camera.model.colmap_name();
    let params = camera.colmap_params();
    let rebuilt =
        Camera::from_colmap_params(camera.model, camera.width_px, camera.height_px, &params)
            .map_err(|error| ColmapError::NotRepresentable {
                path: path.to_path_buf(),
                camera_id,
                model,
                why: error.to_string(),
            })?;
    if rebuilt != *camera {
        return Err(ColmapError::NotRepresentable {
            path: path.to_path_buf(),
            camera_id,
            model,
            why: format!(
                "its intrinsics or distortion ({:?}, {:?}) do not fit the model; choose a model that has them",
                camera.intrinsics, camera.distortion
            ),
        });
    }
    Ok(())
}

/// Writes `cameras.txt` as COLMAP does. Fails, naming the camera, for a camera COLMAP cannot
/// store (skew, or intrinsics that do not fit its model).
pub fn write_cameras_txt(path: &Path, cameras: &BTreeMap<u32, Camera>) -> Result<(), ColmapError> {
    let mut text = String::new();
    text.push_str("# Camera list with one line of data per camera:\n");
    text.push_str("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    let _ = writeln!(text, "# Number of cameras: {}", cameras.len());
    for (&camera_id, camera) in cameras {
        check_representable(path, camera_id, camera)?;
        let _ = write!(
            text,
            "{camera_id} {} {} {}",
            camera.model.colmap_name(),
            camera.width_px,
            camera.height_px
        );
        for param in camera.colmap_params() {
            let _ = write!(text, " {}", format_f64(param));
        }
        text.push('\n');
    }
    create_file(path, &text)
}

/// Writes `images.txt` as COLMAP does, with empty POINTS2D lines. Names must be non-empty, one
/// line, without leading or trailing spaces; poses finite.
pub fn write_images_txt(path: &Path, images: &[ImagePose]) -> Result<(), ColmapError> {
    let mut text = String::new();
    text.push_str("# Image list with two lines of data per image:\n");
    text.push_str("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n");
    text.push_str("#   POINTS2D[] as (X, Y, POINT3D_ID)\n");
    let _ = writeln!(
        text,
        "# Number of images: {}, mean observations per image: 0",
        images.len()
    );
    for image in images {
        let invalid = |why: String| ColmapError::InvalidImage {
            path: path.to_path_buf(),
            image_id: image.image_id,
            why,
        };
        if image.name.is_empty()
            || image.name.trim() != image.name
            || image.name.contains(['\n', '\r'])
        {
            return Err(invalid(format!(
                "name {:?} cannot be stored: it must be non-empty, on one line, without leading or trailing spaces",
                image.name
            )));
        }
        if !image.cam_from_world.is_finite() {
            return Err(invalid(format!("pose of '{}' is not finite", image.name)));
        }
        let qvec = image.cam_from_world.colmap_qvec();
        let tvec = image.cam_from_world.translation;
        let _ = write!(text, "{}", image.image_id);
        for value in qvec.iter().chain(tvec.iter()) {
            let _ = write!(text, " {}", format_f64(*value));
        }
        let _ = writeln!(text, " {} {}", image.camera_id, image.name);
        text.push('\n');
    }
    create_file(path, &text)
}

/// Writes a `points3D.txt` with COLMAP's header and no points.
pub fn write_empty_points3d_txt(path: &Path) -> Result<(), ColmapError> {
    create_file(
        path,
        "# 3D point list with one line of data per point:\n\
         #   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n\
         # Number of points: 0, mean track length: 0\n",
    )
}

#[cfg(test)]
// The fixtures hold COLMAP's 17-significant-digit output verbatim.
#[allow(clippy::excessive_precision)]
mod tests {
    use super::*;
    use crate::core::camera::{Distortion, PinholeIntrinsics};

    /// Cameras of all five models, written the way COLMAP 3.x writes them.
    const CAMERAS_ALL_MODELS: &str = "\
# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
# Number of cameras: 5
1 SIMPLE_PINHOLE 3072 2304 2559.6815 1536 1152
2 PINHOLE 995 558 585.0891410048622 585.0891410048622 497.5 279
3 SIMPLE_RADIAL 1000 562 585.0891410048622 500 281 0.0039516009400160541
4 RADIAL 4000 2250 3117.9437234659488 2000 1125 -0.0071306374447154245 0.0061437563612768283
5 OPENCV 640 480 510.37196300742402 511.00812435627587 320.82103468749449 241.11993497802327 -0.1197540364968431 0.07231869282474148 0.00041362101048640215 -0.00073622473498651839
";

    const CAMERAS_TWO: &str = "\
# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
# Number of cameras: 2
1 PINHOLE 995 558 585.0891410048622 585.0891410048622 497.5 279
2 SIMPLE_RADIAL 1000 562 585.0891410048622 500 281 0.0039516009400160541
";

    /// Two images; the first has observations on its second line, the second none.
    const IMAGES_TWO: &str = "\
# Image list with two lines of data per image:
#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME
#   POINTS2D[] as (X, Y, POINT3D_ID)
# Number of images: 2, mean observations per image: 0
8 -0.0072468788108332235 0.90829910395762736 -0.41822536525984444 0.0052691887935615743 47.619659086469667 66.549995206692913 199.77647057617861 1 DJI_0025.JPG
649.86280281923757 -0.79892520219783592 -1 61.893204289686878 0.9591013736212517 2469
3 0.70710678118654757 0 0 0.70710678118654746 -1.5 2.25 -1e-20 2 DJI_0020.JPG

";

    fn temp_dir() -> tempfile::TempDir {
        tempfile::tempdir().unwrap()
    }

    fn write(dir: &Path, name: &str, contents: &str) -> PathBuf {
        let path = dir.join(name);
        fs::write(&path, contents).unwrap();
        path
    }

    /// Asserts that an error message names the file, `path:line` and the field.
    fn assert_names(error: &ColmapError, path: &Path, line: usize, field: &str) {
        let message = error.to_string();
        println!("{message}");
        let location = format!("{}:{line}:", path.display());
        assert!(message.contains(&location), "no '{location}' in: {message}");
        assert!(message.contains(field), "no field '{field}' in: {message}");
    }

    #[test]
    fn all_five_models_round_trip_exactly() {
        let dir = temp_dir();
        let path = write(dir.path(), CAMERAS_FILE, CAMERAS_ALL_MODELS);
        let cameras = read_cameras_txt(&path).unwrap();
        assert_eq!(cameras.len(), 5);
        let models: Vec<_> = cameras.values().map(|camera| camera.model).collect();
        assert_eq!(models, CameraModelId::ALL.to_vec());
        assert_eq!(
            cameras[&3].distortion,
            Distortion::Radial1 {
                k1: 0.0039516009400160541
            }
        );
        assert_eq!(cameras[&5].intrinsics.fy_px, 511.00812435627587);

        let written = dir.path().join("again.txt");
        write_cameras_txt(&written, &cameras).unwrap();
        assert_eq!(read_cameras_txt(&written).unwrap(), cameras);
        // COLMAP-written values that are already shortest print identically.
        let text = fs::read_to_string(&written).unwrap();
        assert!(text.starts_with(
            "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 5\n"
        ));
        assert!(
            text.contains("\n2 PINHOLE 995 558 585.0891410048622 585.0891410048622 497.5 279\n")
        );
    }

    #[test]
    fn images_read_with_points2d_line_and_round_trip() {
        let dir = temp_dir();
        write(dir.path(), CAMERAS_FILE, CAMERAS_TWO);
        let images_path = write(dir.path(), IMAGES_FILE, IMAGES_TWO);
        let images = read_images_txt(&images_path).unwrap();
        assert_eq!(images.len(), 2);
        assert_eq!((images[0].image_id, images[0].camera_id), (8, 1));
        assert_eq!(images[0].name, "DJI_0025.JPG");
        assert_eq!(images[1].name, "DJI_0020.JPG");
        assert_eq!(
            images[1].cam_from_world.translation,
            Vector3::new(-1.5, 2.25, -1e-20)
        );
        let expected = Rigid3::from_colmap(
            [
                -0.0072468788108332235,
                0.90829910395762736,
                -0.41822536525984444,
                0.0052691887935615743,
            ],
            [47.619659086469667, 66.549995206692913, 199.77647057617861],
        );
        assert!(
            images[0]
                .cam_from_world
                .rotation
                .angle_to(&expected.rotation)
                < 1e-15
        );

        let model = read_model(dir.path()).unwrap();
        let out = temp_dir();
        write_model(out.path(), &model).unwrap();
        let again = read_model(out.path()).unwrap();
        assert_eq!(again, model);
        for (a, b) in again.images.iter().zip(&model.images) {
            // Exact, not just up to the quaternion's sign (which PartialEq forgives).
            assert_eq!(
                a.cam_from_world.colmap_qvec(),
                b.cam_from_world.colmap_qvec()
            );
        }
        let text = fs::read_to_string(out.path().join(IMAGES_FILE)).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(
            &lines[..4],
            &[
                "# Image list with two lines of data per image:",
                "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                "#   POINTS2D[] as (X, Y, POINT3D_ID)",
                "# Number of images: 2, mean observations per image: 0",
            ]
        );
        assert!(
            lines[4].starts_with("8 0.00724687881083"),
            "QW >= 0: {}",
            lines[4]
        );
        assert!(lines[4].ends_with(" 1 DJI_0025.JPG"));
        assert_eq!(lines[5], "");
        assert_eq!(lines.len(), 8);
        let points = fs::read_to_string(out.path().join(POINTS3D_FILE)).unwrap();
        assert!(points.ends_with("# Number of points: 0, mean track length: 0\n"));
        assert_eq!(
            points.lines().filter(|line| !line.starts_with('#')).count(),
            0
        );
    }

    #[test]
    fn last_points2d_line_may_be_missing_and_names_may_have_spaces() {
        let dir = temp_dir();
        let path = write(
            dir.path(),
            IMAGES_FILE,
            "1 1 0 0 0 0 0 0 1 flight 2/img 001.jpg\n\n2 1 0 0 0 1 2 3 1 b.jpg",
        );
        let images = read_images_txt(&path).unwrap();
        assert_eq!(images[0].name, "flight 2/img 001.jpg");
        // Windows line endings and a byte-order mark are accepted too.
        let windows = write(
            dir.path(),
            CAMERAS_FILE,
            "\u{feff}# Camera list with one line of data per camera:\r\n1 SIMPLE_PINHOLE 10 8 5 5 4\r\n",
        );
        assert_eq!(read_cameras_txt(&windows).unwrap()[&1].height_px, 8);
        assert_eq!(
            images[1].cam_from_world.translation,
            Vector3::new(1.0, 2.0, 3.0)
        );
    }

    /// Checks the two real Brighton Beach models under `data` (the undistorted PINHOLE one and the
    /// SIMPLE_RADIAL one): 18 nadir photos, one camera, and an unchanged write–read round trip.
    fn check_brighton_beach_models(data: &Path) {
        for (name, model_id) in [
            ("gt_undistorted", CameraModelId::Pinhole),
            ("gt_simple_radial", CameraModelId::SimpleRadial),
        ] {
            let model = read_model(&data.join(name)).unwrap();
            assert_eq!(model.cameras.len(), 1, "{name}");
            assert_eq!(model.cameras[&1].model, model_id);
            assert_eq!(model.images.len(), 18, "{name}");
            let image = model.image_by_name("DJI_0025.JPG").unwrap();
            assert_eq!(model.camera_of(image).unwrap().model, model_id);
            // Nadir photos from about 40 m above a ground near Z = 160.
            for image in &model.images {
                let centre = image.cam_from_world.camera_center();
                assert!(
                    centre.z > 180.0 && centre.z < 220.0,
                    "{name} {}: {centre}",
                    image.name
                );
            }
            let out = temp_dir();
            model.write_model(out.path()).unwrap();
            let again = ColmapModel::read_model(out.path()).unwrap();
            assert_eq!(again, model, "{name}");
        }
    }

    /// The models cut to 3 observations per image (`tests/data/brighton_beach/README.md`).
    #[test]
    fn brighton_beach_model_excerpts_read_and_round_trip() {
        check_brighton_beach_models(&crate::test_data::repo_data("brighton_beach"));
    }

    /// The whole models: about 7,500 keypoints per image, observation lines of up to 390 kB.
    #[test]
    #[ignore = "needs ../shared/data/brighton_beach (the shared data set beside the repo)"]
    fn shared_data_brighton_beach_models_read_and_round_trip() {
        check_brighton_beach_models(&crate::test_data::shared_data("brighton_beach"));
    }

    #[test]
    fn skew_and_unfitting_intrinsics_cannot_be_written() {
        let dir = temp_dir();
        let path = dir.path().join(CAMERAS_FILE);
        let mut intrinsics = PinholeIntrinsics::centered(500.0, 640, 480);
        intrinsics.skew_px = 0.5;
        let cameras = BTreeMap::from([(7, Camera::pinhole(640, 480, intrinsics))]);
        let error = write_cameras_txt(&path, &cameras).unwrap_err();
        assert!(matches!(
            error,
            ColmapError::SkewNotRepresentable { camera_id: 7, .. }
        ));
        assert!(error.to_string().contains("camera 7"), "{error}");

        let mut camera = Camera::pinhole(640, 480, PinholeIntrinsics::centered(500.0, 640, 480));
        camera.model = CameraModelId::SimplePinhole;
        camera.intrinsics.fy_px = 510.0;
        let error = write_cameras_txt(&path, &BTreeMap::from([(3, camera)])).unwrap_err();
        assert!(error.to_string().contains("camera 3"), "{error}");
        assert!(error.to_string().contains("SIMPLE_PINHOLE"), "{error}");
    }

    #[test]
    fn writing_rejects_bad_images() {
        let dir = temp_dir();
        let path = dir.path().join(IMAGES_FILE);
        let mut image = ImagePose {
            image_id: 4,
            camera_id: 1,
            name: "a b.jpg ".to_string(),
            cam_from_world: Rigid3::identity(),
        };
        let error = write_images_txt(&path, std::slice::from_ref(&image)).unwrap_err();
        assert!(error.to_string().contains("image 4"), "{error}");
        image.name = "ok.jpg".to_string();
        image.cam_from_world.translation.x = f64::NAN;
        let error = write_images_txt(&path, std::slice::from_ref(&image)).unwrap_err();
        assert!(error.to_string().contains("not finite"), "{error}");

        image.cam_from_world = Rigid3::identity();
        let model = ColmapModel {
            cameras: BTreeMap::new(),
            images: vec![image],
        };
        let error = model.write_model(dir.path()).unwrap_err();
        assert!(error.to_string().contains("uses camera 1"), "{error}");
    }

    #[test]
    fn floats_are_written_to_read_back_exactly() {
        for value in [
            0.1,
            -0.0,
            279.0,
            1e-20,
            -3.3e-7,
            1e300,
            123456789012345680.0,
            f64::MIN_POSITIVE,
            0.0039516009400160541,
        ] {
            let text = format_f64(value);
            assert_eq!(
                text.parse::<f64>().unwrap().to_bits(),
                value.to_bits(),
                "{text}"
            );
        }
        assert_eq!(format_f64(279.0), "279");
        assert_eq!(format_f64(1e-20), "1e-20");
    }

    #[test]
    fn bad_camera_lines_name_file_line_and_field() {
        let dir = temp_dir();
        let header = "# Camera list with one line of data per camera:\n";
        let cases: &[(&str, &str)] = &[
            ("1 PINHOLE 995", "HEIGHT"),
            ("1 PINHOLE 995 558 585 585 497.5 2x79", "PARAMS[3]"),
            ("1 PINHOLE 995 558 585 nan 497.5 279", "PARAMS[1]"),
            ("1 PINHOLE 0 558 585 585 497.5 279", "WIDTH"),
            ("one PINHOLE 995 558 585 585 497.5 279", "CAMERA_ID"),
            ("1 FISHEYE 995 558 585 585 497.5 279", "MODEL"),
            ("1 PINHOLE 995 558 585 585 497.5", "PARAMS[]"),
            ("1 PINHOLE 995 558 -585 585 497.5 279", "PARAMS[]"),
        ];
        for (line, field) in cases {
            let path = write(dir.path(), CAMERAS_FILE, &format!("{header}{line}\n"));
            let error = read_cameras_txt(&path).unwrap_err();
            assert_names(&error, &path, 2, field);
        }
        let error = read_cameras_txt(&dir.path().join("absent.txt")).unwrap_err();
        assert!(matches!(error, ColmapError::Io { .. }));
        assert!(error.to_string().contains("absent.txt"), "{error}");

        let wrong_count = write(dir.path(), CAMERAS_FILE, "1 SIMPLE_RADIAL 10 10 5 5 5\n");
        let message = read_cameras_txt(&wrong_count).unwrap_err().to_string();
        assert!(message.contains("takes 4 parameters, got 3"), "{message}");

        let duplicate = write(
            dir.path(),
            CAMERAS_FILE,
            &format!("{header}1 SIMPLE_PINHOLE 10 10 5 5 5\n\n2 SIMPLE_PINHOLE 10 10 5 5 5\n1 SIMPLE_PINHOLE 10 10 5 5 5\n"),
        );
        let error = read_cameras_txt(&duplicate).unwrap_err();
        assert_names(&error, &duplicate, 5, "CAMERA_ID");
        assert!(error.to_string().contains("line 2"), "{error}");
    }

    #[test]
    fn bad_image_lines_name_file_line_and_field() {
        let dir = temp_dir();
        let header = "# Image list with two lines of data per image:\n# Number of images: 1\n";
        let cases: &[(&str, &str)] = &[
            ("1 1 0 0 0 0 0 0 1", "NAME"),
            ("1 1 0 0", "QZ"),
            ("1 1 0 0 0 0 0 nan 1 a.jpg", "TZ"),
            ("1 1 0 0 0 NaN 0 0 1 a.jpg", "TX"),
            ("1 1 0 0 0 0 0 0 -1 a.jpg", "CAMERA_ID"),
            ("1 x 0 0 0 0 0 0 1 a.jpg", "QW"),
            ("1 0 0 0 0 0 0 0 1 a.jpg", "QW QX QY QZ"),
            ("1.5 1 0 0 0 0 0 0 1 a.jpg", "IMAGE_ID"),
        ];
        for (line, field) in cases {
            let path = write(dir.path(), IMAGES_FILE, &format!("{header}{line}\n\n"));
            let error = read_images_txt(&path).unwrap_err();
            assert_names(&error, &path, 3, field);
        }

        // The empty second line left out: the next image is taken for POINTS2D and rejected.
        let path = write(
            dir.path(),
            IMAGES_FILE,
            &format!("{header}1 1 0 0 0 0 0 0 1 a.jpg\n2 1 0 0 0 0 0 0 1 b.jpg\n"),
        );
        assert_names(&read_images_txt(&path).unwrap_err(), &path, 4, "POINTS2D[]");

        let path = write(
            dir.path(),
            IMAGES_FILE,
            &format!("{header}1 1 0 0 0 0 0 0 1 a.jpg\n\n1 1 0 0 0 0 0 0 1 b.jpg\n\n"),
        );
        assert_names(&read_images_txt(&path).unwrap_err(), &path, 5, "IMAGE_ID");
        let path = write(
            dir.path(),
            IMAGES_FILE,
            &format!("{header}1 1 0 0 0 0 0 0 1 a.jpg\n\n2 1 0 0 0 0 0 0 1 a.jpg\n\n"),
        );
        let error = read_images_txt(&path).unwrap_err();
        assert_names(&error, &path, 5, "NAME");
        assert!(error.to_string().contains("'a.jpg'"), "{error}");
    }

    #[test]
    fn image_with_missing_camera_names_image_and_camera() {
        let dir = temp_dir();
        write(dir.path(), CAMERAS_FILE, CAMERAS_TWO);
        let images_path = write(
            dir.path(),
            IMAGES_FILE,
            "# header\n1 1 0 0 0 0 0 0 1 a.jpg\n\n2 1 0 0 0 0 0 0 9 b.jpg\n\n",
        );
        let error = read_model(dir.path()).unwrap_err();
        assert_names(&error, &images_path, 4, "CAMERA_ID 9");
        let message = error.to_string();
        assert!(message.contains("'b.jpg'"), "{message}");
        assert!(message.contains(CAMERAS_FILE), "{message}");
    }
}
