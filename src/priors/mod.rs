//! Priors from the photos themselves: an initial pose per photo from its GPS and gimbal attitude
//! (EXIF, DJI maker note, DJI XMP, or an exiftool CSV), in the local UTM frame the mesh is in, and
//! a first camera from EXIF's focal length, written as a COLMAP model (`asgreg priors`).
//!
//! | file | what |
//! |---|---|
//! | `jpeg.rs` | a JPEG's header: size, EXIF (GPS, focal, make/model), DJI maker note, XMP packet |
//! | `xmp.rs` | DJI's `drone-dji:` XMP attributes, by hand |
//! | `exif_csv.rs` | the same from an exiftool CSV, columns by header name |
//! | `utm.rs` | WGS84 → UTM (Krüger series), meridian convergence, the local frame and its offset file |
//! | `orientation.rs` | gimbal yaw/pitch/roll → `cam_from_world` (the convention, in its `//!`) |
//! | `intrinsics.rs` | a PINHOLE camera from the focal length (sensor table or 35 mm equivalent) |
//!
//! The centre is `C = (E − E0, N − N0, h − Z0)` with `h` the GPS altitude (EXIF `GPSAltitude`, not
//! the take-off-relative `RelativeAltitude`, which is read and reported but not used), and the
//! pose `cam_from_world = (R, −R·C)`.

pub mod exif_csv;
pub mod intrinsics;
pub mod jpeg;
pub mod orientation;
pub mod utm;
pub mod xmp;

use std::collections::BTreeMap;
use std::path::PathBuf;

use crate::core::camera::Camera;
use crate::core::rigid::Rigid3;
use crate::io::colmap::ImagePose;

use orientation::{cam_from_world_rotation, Attitude};
use utm::{to_utm, LocalFrame, UtmPoint, UtmZone};

/// Errors of reading the photos' metadata and making priors from it. Each names the file (or the
/// photo) and the field.
#[derive(Debug, thiserror::Error)]
pub enum PriorsError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: {why}", path.display())]
    Jpeg { path: PathBuf, why: String },
    #[error("{}: unreadable EXIF: {source}", path.display())]
    Exif {
        path: PathBuf,
        #[source]
        source: exif::Error,
    },
    #[error("{}: field {field}: found {found}; expected {expected}", path.display())]
    Field {
        path: PathBuf,
        field: String,
        found: String,
        expected: String,
    },
    #[error("{}: no {field}; {hint}", path.display())]
    MissingField {
        path: PathBuf,
        field: String,
        hint: String,
    },
    #[error("{}: no column {column} in the header line; write the file with `exiftool -csv -n` (DJI photos carry these tags) or add the column", path.display())]
    MissingColumn { path: PathBuf, column: String },
    #[error("{}: {why}", path.display())]
    Projection { path: PathBuf, why: String },
    #[error("{}: image size {width_px}×{height_px} px, but camera {camera_id} of {} is {camera_width_px}×{camera_height_px} px; give the calibration of this image size (scale f, cx, cy with the image)", path.display(), cameras.display())]
    CameraSize {
        path: PathBuf,
        width_px: u32,
        height_px: u32,
        camera_id: u32,
        cameras: PathBuf,
        camera_width_px: u32,
        camera_height_px: u32,
    },
    #[error("{}: none of the {count} cameras of {} has this image's size {width_px}×{height_px} px (or two do); give one camera, or one per image size", path.display(), cameras.display())]
    CameraChoice {
        path: PathBuf,
        cameras: PathBuf,
        count: usize,
        width_px: u32,
        height_px: u32,
    },
}

/// A GPS position (WGS84, altitude as the receiver gives it).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GpsPosition {
    pub latitude_deg: f64,
    pub longitude_deg: f64,
    pub altitude_m: f64,
}

/// Where a photo's gimbal attitude came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AttitudeSource {
    Xmp,
    MakerNote,
    Csv,
}

impl AttitudeSource {
    pub fn label(self) -> &'static str {
        match self {
            AttitudeSource::Xmp => "XMP",
            AttitudeSource::MakerNote => "maker note",
            AttitudeSource::Csv => "CSV",
        }
    }
}

/// What one photo says about itself. Every field is optional: which ones a prior needs is decided
/// by [`build_priors`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PhotoMetadata {
    /// File name (no directory), as in COLMAP's `images.txt`.
    pub name: String,
    pub gps: Option<GpsPosition>,
    /// DJI's altitude above the take-off point (reported, not used).
    pub relative_altitude_m: Option<f64>,
    pub gimbal: Option<Attitude>,
    /// The aircraft's attitude (reported, not used: see `orientation`).
    pub flight: Option<Attitude>,
    pub attitude_source: Option<AttitudeSource>,
    pub focal_length_mm: Option<f64>,
    pub focal_length_35mm: Option<f64>,
    pub make: Option<String>,
    pub model: Option<String>,
    /// From the JPEG's frame header.
    pub image_size_px: Option<(u32, u32)>,
}

/// How to build the priors.
#[derive(Clone, Debug, Default)]
pub struct PriorsOptions {
    /// The UTM zone; `None`: the zone of the photos' mean position.
    pub zone: Option<UtmZone>,
    /// The local frame's offset (easting, northing, altitude); `None`: the rounded minimum
    /// ([`LocalFrame::rounded_minimum`]).
    pub offset_m: Option<[f64; 3]>,
    /// Subtract the meridian convergence from the yaw (see `orientation`). `asgreg priors` does
    /// by default (the frame is UTM's grid); `false` reproduces priors made without it, such as
    /// the shared Brighton Beach set's `prior_pose_from_exif.txt`.
    pub correct_convergence: bool,
    /// A given calibration, and the file it came from (for errors); `None`: cameras from EXIF.
    pub cameras: Option<(BTreeMap<u32, Camera>, PathBuf)>,
}

/// One photo's prior, for the summary.
#[derive(Clone, Debug, PartialEq)]
pub struct ImagePrior {
    pub name: String,
    pub center_m: [f64; 3],
    pub gimbal: Attitude,
    pub source: Option<AttitudeSource>,
    pub relative_altitude_m: Option<f64>,
    /// The convergence at the photo, and what was subtracted from the yaw (0 or the same).
    pub convergence_deg: f64,
    pub applied_convergence_deg: f64,
    pub camera_id: u32,
}

/// The priors of a set of photos: the frame they are in, cameras, poses, and a summary per photo.
#[derive(Clone, Debug)]
pub struct Priors {
    pub frame: LocalFrame,
    pub cameras: BTreeMap<u32, Camera>,
    /// How each camera's focal length was found (given, or from which EXIF field).
    pub camera_sources: BTreeMap<u32, String>,
    pub images: Vec<ImagePose>,
    pub summary: Vec<ImagePrior>,
}

fn missing(name: &str, field: &str, hint: &str) -> PriorsError {
    PriorsError::MissingField {
        path: PathBuf::from(name),
        field: field.to_string(),
        hint: hint.to_string(),
    }
}

/// Makes the priors of the photos (in their order; image ids 1, 2, …). Every photo needs a GPS
/// position and a gimbal attitude, and an image size and focal length unless cameras are given.
pub fn build_priors(
    photos: &[PhotoMetadata],
    options: &PriorsOptions,
) -> Result<Priors, PriorsError> {
    let mut gps = Vec::with_capacity(photos.len());
    let mut gimbals = Vec::with_capacity(photos.len());
    for photo in photos {
        gps.push(photo.gps.ok_or_else(|| {
            missing(
                &photo.name,
                "GPS position (EXIF GPSLatitude/GPSLongitude/GPSAltitude)",
                "give an exiftool CSV with these columns (--exif-csv), or leave the photo out",
            )
        })?);
        gimbals.push(photo.gimbal.ok_or_else(|| {
            missing(
                &photo.name,
                "gimbal attitude (XMP drone-dji:GimbalYaw/Pitch/RollDegree or DJI maker note CameraYaw/Pitch/Roll)",
                "give an exiftool CSV with GimbalYawDegree, GimbalPitchDegree, GimbalRollDegree (--exif-csv), or leave the photo out",
            )
        })?);
    }
    let zone = match options.zone {
        Some(zone) => zone,
        None if gps.is_empty() => UtmZone {
            number: 31,
            north: true,
        },
        None => {
            let count = gps.len() as f64;
            let latitude = gps.iter().map(|g| g.latitude_deg).sum::<f64>() / count;
            // Mean of unit vectors: robust across the antimeridian.
            let (sin, cos) = gps.iter().fold((0.0, 0.0), |(s, c), g| {
                let lon = g.longitude_deg.to_radians();
                (s + lon.sin(), c + lon.cos())
            });
            UtmZone::of(latitude, f64::atan2(sin, cos).to_degrees())
        }
    };
    let projected: Vec<UtmPoint> = photos
        .iter()
        .zip(&gps)
        .map(|(photo, g)| {
            to_utm(g.latitude_deg, g.longitude_deg, zone).map_err(|why| PriorsError::Projection {
                path: PathBuf::from(&photo.name),
                why,
            })
        })
        .collect::<Result<_, _>>()?;
    let frame = match options.offset_m {
        Some([easting_m, northing_m, altitude_m]) => LocalFrame {
            zone,
            easting_m,
            northing_m,
            altitude_m,
        },
        None => LocalFrame::rounded_minimum(zone, &projected),
    };

    let mut cameras = BTreeMap::new();
    let mut camera_sources = BTreeMap::new();
    let mut camera_ids: Vec<((u32, u32, u64), u32)> = Vec::new();
    let mut images = Vec::with_capacity(photos.len());
    let mut summary = Vec::with_capacity(photos.len());
    for (index, photo) in photos.iter().enumerate() {
        let camera_id = match &options.cameras {
            Some((given, path)) => given_camera(photo, given, path)?,
            None => {
                let (width_px, height_px) = photo.image_size_px.ok_or_else(|| {
                    missing(
                        &photo.name,
                        "image size",
                        "the photo's JPEG frame header is needed (--images)",
                    )
                })?;
                let focal = intrinsics::focal_from_exif(photo, width_px).ok_or_else(|| {
                    missing(
                        &photo.name,
                        "focal length (EXIF FocalLength with a known camera Model, or FocalLengthIn35mmFormat)",
                        "give a calibration with --cameras FILE (COLMAP cameras.txt/.bin or a model folder)",
                    )
                })?;
                let key = (width_px, height_px, (focal.focal_px * 1e6).round() as u64);
                match camera_ids.iter().find(|(k, _)| *k == key) {
                    Some((_, id)) => *id,
                    None => {
                        let id = camera_ids.len() as u32 + 1;
                        camera_ids.push((key, id));
                        cameras.insert(
                            id,
                            intrinsics::camera_from_focal(width_px, height_px, focal.focal_px),
                        );
                        camera_sources.insert(id, focal.how);
                        id
                    }
                }
            }
        };
        let point = &projected[index];
        let center = frame.local(point, gps[index].altitude_m);
        let applied = if options.correct_convergence {
            point.convergence_deg
        } else {
            0.0
        };
        let rotation = cam_from_world_rotation(gimbals[index], applied);
        let translation = -(rotation * nalgebra::Vector3::from(center));
        images.push(ImagePose {
            image_id: index as u32 + 1,
            camera_id,
            name: photo.name.clone(),
            cam_from_world: Rigid3::new(rotation, translation),
        });
        summary.push(ImagePrior {
            name: photo.name.clone(),
            center_m: center,
            gimbal: gimbals[index],
            source: photo.attitude_source,
            relative_altitude_m: photo.relative_altitude_m,
            convergence_deg: point.convergence_deg,
            applied_convergence_deg: applied,
            camera_id,
        });
    }
    if let Some((given, path)) = &options.cameras {
        let used: std::collections::BTreeSet<u32> = images.iter().map(|i| i.camera_id).collect();
        for id in used {
            if let Some(camera) = given.get(&id) {
                cameras.insert(id, *camera);
                camera_sources.insert(id, format!("given ({})", path.display()));
            }
        }
    }
    Ok(Priors {
        frame,
        cameras,
        camera_sources,
        images,
        summary,
    })
}

/// The given camera for a photo: the only one, or the one of the photo's size.
fn given_camera(
    photo: &PhotoMetadata,
    given: &BTreeMap<u32, Camera>,
    cameras_path: &std::path::Path,
) -> Result<u32, PriorsError> {
    let path = PathBuf::from(&photo.name);
    if given.len() == 1 {
        let (id, camera) = given
            .iter()
            .next()
            .map(|(id, c)| (*id, c))
            .ok_or_else(|| missing(&photo.name, "camera", "the calibration file holds none"))?;
        if let Some((width_px, height_px)) = photo.image_size_px {
            if (width_px, height_px) != (camera.width_px, camera.height_px) {
                return Err(PriorsError::CameraSize {
                    path,
                    width_px,
                    height_px,
                    camera_id: id,
                    cameras: cameras_path.to_path_buf(),
                    camera_width_px: camera.width_px,
                    camera_height_px: camera.height_px,
                });
            }
        }
        return Ok(id);
    }
    let (width_px, height_px) = photo.image_size_px.unwrap_or((0, 0));
    let mut matching = given
        .iter()
        .filter(|(_, c)| (c.width_px, c.height_px) == (width_px, height_px));
    match (matching.next(), matching.next()) {
        (Some((id, _)), None) => Ok(*id),
        _ => Err(PriorsError::CameraChoice {
            path,
            cameras: cameras_path.to_path_buf(),
            count: given.len(),
            width_px,
            height_px,
        }),
    }
}

#[cfg(test)]
mod tests;
