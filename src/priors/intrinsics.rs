//! A first camera from EXIF when no calibration is given: PINHOLE, square pixels, principal point
//! at the image centre, focal length in pixels from
//!
//! 1. the focal length in mm and the sensor's width for a few DJI cameras whose sensor is known
//!    (`f_px = f_mm / sensor_width_mm × width_px`): FC300S, Phantom 3 Standard: 3.61 mm on a
//!    6.17 mm wide sensor, 4000 px → 2340.4 px, 585.09 px at 1000 px, which is the Brighton Beach
//!    ground truth's 585.089 (SfM with the focal fixed from EXIF);
//! 2. else the 35 mm equivalent (`f_px = f35 / 36 mm × width_px`), which is only as good as the
//!    camera's rounding of it and exact only for a 3:2 frame whose width is the equivalent's 36 mm
//!    (the FC300S writes 20 mm, which gives 555.6 px at 1000 px, 5 % short).
//!
//! Both assume the photo is the whole sensor's width, resized (a crop keeps the focal length in
//! pixels but not the width). No distortion: for a calibrated camera give `--cameras`.

use crate::core::camera::{Camera, PinholeIntrinsics};

use super::PhotoMetadata;

/// Sensor widths of DJI cameras, by EXIF `Model` (1/2.3" sensors 6.17 mm, 1" sensors 13.2 mm).
const SENSOR_WIDTHS_MM: &[(&str, f64)] = &[
    ("FC300S", 6.17),  // Phantom 3 Standard
    ("FC300X", 6.17),  // Phantom 3 Professional / Advanced
    ("FC330", 6.17),   // Phantom 4
    ("FC220", 6.17),   // Mavic Pro
    ("FC6310", 13.2),  // Phantom 4 Pro
    ("FC6310S", 13.2), // Phantom 4 Pro V2
    ("L1D-20c", 13.2), // Mavic 2 Pro
];

/// The sensor width of a known camera model.
pub fn sensor_width_mm(model: &str) -> Option<f64> {
    SENSOR_WIDTHS_MM
        .iter()
        .find(|(name, _)| name.eq_ignore_ascii_case(model.trim()))
        .map(|(_, width)| *width)
}

/// A focal length in pixels and how it was found (for the summary).
#[derive(Clone, Debug, PartialEq)]
pub struct FocalEstimate {
    pub focal_px: f64,
    pub how: String,
}

/// The focal length in pixels for an image `width_px` wide, or `None` when EXIF has neither a
/// focal length of a known camera nor a 35 mm equivalent.
pub fn focal_from_exif(meta: &PhotoMetadata, width_px: u32) -> Option<FocalEstimate> {
    let width = f64::from(width_px);
    if let (Some(f_mm), Some(model)) = (meta.focal_length_mm, meta.model.as_deref()) {
        if let Some(sensor_mm) = sensor_width_mm(model) {
            if f_mm > 0.0 {
                return Some(FocalEstimate {
                    focal_px: f_mm / sensor_mm * width,
                    how: format!("{f_mm} mm on the {model}'s {sensor_mm} mm sensor"),
                });
            }
        }
    }
    let f35 = meta.focal_length_35mm.filter(|f| *f > 0.0)?;
    Some(FocalEstimate {
        focal_px: f35 / 36.0 * width,
        how: format!("35 mm equivalent {f35} mm"),
    })
}

/// The PINHOLE camera of an image of this size with this focal length.
pub fn camera_from_focal(width_px: u32, height_px: u32, focal_px: f64) -> Camera {
    Camera::pinhole(
        width_px,
        height_px,
        PinholeIntrinsics::centered(focal_px, width_px, height_px),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_sensor_first_then_35mm_equivalent() {
        let mut meta = PhotoMetadata {
            focal_length_mm: Some(3.61),
            focal_length_35mm: Some(20.0),
            model: Some("FC300S".to_string()),
            ..PhotoMetadata::default()
        };
        let f = focal_from_exif(&meta, 1000).unwrap();
        // The Brighton Beach ground truth: 585.089 px at 1000 px.
        assert!((f.focal_px - 585.089).abs() < 0.001, "{f:?}");
        meta.model = Some("Unknown".to_string());
        let f = focal_from_exif(&meta, 1000).unwrap();
        assert!((f.focal_px - 20.0 / 36.0 * 1000.0).abs() < 1e-9, "{f:?}");
        assert!(f.how.contains("35 mm"));
        meta.focal_length_35mm = None;
        assert_eq!(focal_from_exif(&meta, 1000), None);
        let camera = camera_from_focal(995, 558, 585.089);
        assert_eq!(
            (camera.intrinsics.cx_px, camera.intrinsics.cy_px),
            (497.5, 279.0)
        );
    }
}
