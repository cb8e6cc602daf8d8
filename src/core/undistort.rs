//! The working camera: a photo (and its depth map) resampled to an ideal pinhole camera at the
//! working resolution, because renderings are ideal pinhole images and registration is done at
//! about the paper's 505 px width.
//!
//! A camera with lens distortion (COLMAP SIMPLE_RADIAL, RADIAL, OPENCV) becomes a PINHOLE camera
//! chosen as COLMAP's `image_undistorter` chooses it with `blank_pixels = 0` (same focal lengths,
//! the largest image without blank pixels, principal point scaled with the size): the
//! Brighton Beach SIMPLE_RADIAL 1000×562 camera becomes exactly the shared PINHOLE 995×558 one.
//! The photo is undistorted at its own size (bilinear, as COLMAP does), then, when wider than
//! the working width, averaged down (area resampling) to it: the working camera is that PINHOLE
//! camera brought to the working width, the camera COLMAP's undistorted photo gets there too.
//! Poses do not change by either step (the camera frame is the same), so a pose found with the
//! working camera is a pose of the original camera; only the intrinsics differ, and
//! [`WorkingCamera::source_camera_for`] maps estimated ones back.
//!
//! Everything here is pure: the plan (cameras and a remap table, built once per camera) and the
//! resampling into caller buffers.

use nalgebra::{Matrix3, Vector2};

use crate::core::camera::{pixel_center, Camera, CameraModelId, Distortion, PinholeIntrinsics};
use crate::core::image::{Image, ImageView};

/// COLMAP's default bounds on the undistorted image's scale (`UndistortCameraOptions`).
const MIN_UNDISTORT_SCALE: f64 = 0.2;
const MAX_UNDISTORT_SCALE: f64 = 2.0;

/// Why a camera or image cannot be brought to the working camera.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum UndistortError {
    #[error("the {model} camera's distortion cannot be inverted at its image border (is it a real lens? check its parameters)")]
    NotInvertible { model: &'static str },
    #[error("the image is {found_width_px}x{found_height_px} px but its camera is {camera_width_px}x{camera_height_px} px")]
    SizeMismatch {
        found_width_px: usize,
        found_height_px: usize,
        camera_width_px: u32,
        camera_height_px: u32,
    },
    #[error("working width {width_px} px is not a positive number of pixels")]
    BadWorkingWidth { width_px: u32 },
}

/// The PINHOLE camera COLMAP's `image_undistorter` makes for `camera` (`blank_pixels = 0`:
/// every pixel of the undistorted image sees a pixel of the photo). Undistorted cameras come
/// back unchanged.
pub fn undistorted_camera(camera: &Camera) -> Result<Camera, UndistortError> {
    if matches!(camera.distortion, Distortion::None) {
        return Ok(*camera);
    }
    let k = camera.intrinsics;
    let (width, height) = (f64::from(camera.width_px), f64::from(camera.height_px));
    let not_invertible = || UndistortError::NotInvertible {
        model: camera.model.colmap_name(),
    };
    // Where the photo's border pixels land in a distortion-free camera with the same K.
    let undistorted_px = |x: f64, y: f64| -> Result<Vector2<f64>, UndistortError> {
        let ray = camera
            .unproject(Vector2::new(x, y))
            .ok_or_else(not_invertible)?;
        Ok(k.normalized_to_pixel(Vector2::new(ray.x, ray.y)))
    };
    let (mut left_max_x, mut right_min_x) = (f64::MIN, f64::MAX);
    for row in 0..camera.height_px {
        let y = f64::from(row) + 0.5;
        left_max_x = left_max_x.max(undistorted_px(0.5, y)?.x);
        right_min_x = right_min_x.min(undistorted_px(width - 0.5, y)?.x);
    }
    let (mut top_max_y, mut bottom_min_y) = (f64::MIN, f64::MAX);
    for col in 0..camera.width_px {
        let x = f64::from(col) + 0.5;
        top_max_y = top_max_y.max(undistorted_px(x, 0.5)?.y);
        bottom_min_y = bottom_min_y.min(undistorted_px(x, height - 0.5)?.y);
    }
    let (cx, cy) = (k.cx_px, k.cy_px);
    // The scale at which no blank pixel remains, per axis (COLMAP's `max_scale_x/y`).
    let max_scale_x = (cx / (cx - left_max_x)).max((width - 0.5 - cx) / (right_min_x - cx));
    let max_scale_y = (cy / (cy - top_max_y)).max((height - 0.5 - cy) / (bottom_min_y - cy));
    let scale_x = (1.0 / max_scale_x).clamp(MIN_UNDISTORT_SCALE, MAX_UNDISTORT_SCALE);
    let scale_y = (1.0 / max_scale_y).clamp(MIN_UNDISTORT_SCALE, MAX_UNDISTORT_SCALE);
    if !scale_x.is_finite() || !scale_y.is_finite() {
        return Err(not_invertible());
    }
    // COLMAP truncates the scaled size.
    let width_px = ((scale_x * width).max(1.0)) as u32;
    let height_px = ((scale_y * height).max(1.0)) as u32;
    Ok(Camera::pinhole(
        width_px,
        height_px,
        PinholeIntrinsics {
            cx_px: cx * f64::from(width_px) / width,
            cy_px: cy * f64::from(height_px) / height,
            ..k
        },
    ))
}

/// For every pixel of a target (pinhole) camera, the position in the source camera's image
/// that sees the same ray (image coordinates, pixel centres at `+0.5`).
#[derive(Clone, Debug)]
pub struct UndistortMap {
    source_px: Image<[f32; 2]>,
    source_width_px: usize,
    source_height_px: usize,
}

impl UndistortMap {
    /// The table from `target` (undistorted; its distortion is ignored) to `source`.
    pub fn new(source: &Camera, target: &Camera) -> Self {
        let source_px = Image::from_fn(
            target.width_px as usize,
            target.height_px as usize,
            |col, row| {
                let normalized = target
                    .intrinsics
                    .pixel_to_normalized(pixel_center(col, row));
                let pixel = source
                    .intrinsics
                    .normalized_to_pixel(source.distortion.distort(normalized));
                [pixel.x as f32, pixel.y as f32]
            },
        );
        Self {
            source_px,
            source_width_px: source.width_px as usize,
            source_height_px: source.height_px as usize,
        }
    }

    /// The target image's size `(width, height)`.
    pub fn target_size(&self) -> (usize, usize) {
        self.source_px.size()
    }

    /// Where target pixel `(col, row)` is read from in the source image.
    pub fn source_px(&self, col: usize, row: usize) -> Option<Vector2<f64>> {
        self.source_px
            .get(col, row)
            .map(|p| Vector2::new(f64::from(p[0]), f64::from(p[1])))
    }

    fn check_source(&self, image: &ImageView<'_, f32>) -> Result<(), UndistortError> {
        if image.size() == (self.source_width_px, self.source_height_px) {
            Ok(())
        } else {
            Err(UndistortError::SizeMismatch {
                found_width_px: image.width_px(),
                found_height_px: image.height_px(),
                camera_width_px: self.source_width_px as u32,
                camera_height_px: self.source_height_px as u32,
            })
        }
    }

    /// Resamples a photo (bilinear; positions outside it take the nearest border pixel, so the
    /// border makes no artificial edge) into `out`, which takes the target's size.
    pub fn remap_photo(
        &self,
        photo: ImageView<'_, f32>,
        out: &mut Image<f32>,
    ) -> Result<(), UndistortError> {
        self.check_source(&photo)?;
        let (width, height) = self.target_size();
        out.resize(width, height, 0.0);
        for (value, position) in out.data_mut().iter_mut().zip(self.source_px.data()) {
            let taps = bilinear_taps(position, photo.width_px(), photo.height_px());
            *value = taps
                .iter()
                .map(|&(index, weight)| photo.data()[index] * weight)
                .sum();
        }
        Ok(())
    }

    /// Resamples a depth map (metres along the optical axis, holes 0, which undistortion keeps:
    /// the camera frame is the same) into `out`: bilinear where the four neighbours are valid,
    /// else the nearest one (so a hole never bleeds into a depth and no depth is averaged with
    /// a hole); outside the map a hole.
    pub fn remap_depth(
        &self,
        depth_m: ImageView<'_, f32>,
        out: &mut Image<f32>,
    ) -> Result<(), UndistortError> {
        self.check_source(&depth_m)?;
        let (width, height) = self.target_size();
        out.resize(width, height, 0.0);
        let (source_width, source_height) = depth_m.size();
        for (value, position) in out.data_mut().iter_mut().zip(self.source_px.data()) {
            let inside = position[0] >= 0.0
                && position[1] >= 0.0
                && position[0] < source_width as f32
                && position[1] < source_height as f32;
            if !inside {
                *value = 0.0;
                continue;
            }
            let taps = bilinear_taps(position, source_width, source_height);
            let valid = |index: usize| depth_m.data()[index] > 0.0;
            *value = if taps.iter().all(|&(index, _)| valid(index)) {
                taps.iter()
                    .map(|&(index, weight)| depth_m.data()[index] * weight)
                    .sum()
            } else {
                let nearest = taps
                    .iter()
                    .max_by(|a, b| a.1.total_cmp(&b.1))
                    .map_or(0, |&(index, _)| index);
                depth_m.data()[nearest]
            };
        }
        Ok(())
    }
}

/// The four (index, weight) taps of bilinear interpolation at `position_px` (image coordinates),
/// clamped to the image.
fn bilinear_taps(position_px: &[f32; 2], width_px: usize, height_px: usize) -> [(usize, f32); 4] {
    let axis = |coordinate: f32, size: usize| -> (usize, usize, f32) {
        let last = size.saturating_sub(1) as f32;
        let c = (coordinate - 0.5).clamp(0.0, last);
        let lower = c.floor();
        let fraction = c - lower;
        let lower = lower as usize;
        (lower, (lower + 1).min(size.saturating_sub(1)), fraction)
    };
    let (x0, x1, fx) = axis(position_px[0], width_px);
    let (y0, y1, fy) = axis(position_px[1], height_px);
    [
        (y0 * width_px + x0, (1.0 - fx) * (1.0 - fy)),
        (y0 * width_px + x1, fx * (1.0 - fy)),
        (y1 * width_px + x0, (1.0 - fx) * fy),
        (y1 * width_px + x1, fx * fy),
    ]
}

/// Averages an image down to `width_px` × `height_px` (each output pixel is the mean of the
/// source area it covers, partial pixels weighted), into `out`. Sizes at or above the source's
/// are not downsizing: the caller does not resize then.
pub fn resize_area(
    image: ImageView<'_, f32>,
    width_px: usize,
    height_px: usize,
    out: &mut Image<f32>,
) {
    resize_area_with(image, width_px, height_px, out, |_| true);
}

/// [`resize_area`] for a depth map: holes (0) take no part in the mean; an output pixel whose
/// whole area is holes is a hole.
pub fn resize_depth_area(
    depth_m: ImageView<'_, f32>,
    width_px: usize,
    height_px: usize,
    out: &mut Image<f32>,
) {
    resize_area_with(depth_m, width_px, height_px, out, |value| value > 0.0);
}

fn resize_area_with(
    image: ImageView<'_, f32>,
    width_px: usize,
    height_px: usize,
    out: &mut Image<f32>,
    counts: impl Fn(f32) -> bool,
) {
    out.resize(width_px, height_px, 0.0);
    if width_px == 0 || height_px == 0 || image.is_empty() {
        return;
    }
    let columns = area_weights(image.width_px(), width_px);
    let rows = area_weights(image.height_px(), height_px);
    for (row, row_taps) in rows.iter().enumerate() {
        for (col, col_taps) in columns.iter().enumerate() {
            let (mut sum, mut weight_sum) = (0.0f64, 0.0f64);
            for &(source_row, row_weight) in row_taps {
                let source = image.row(source_row);
                for &(source_col, col_weight) in col_taps {
                    let value = source[source_col];
                    if counts(value) {
                        let weight = row_weight * col_weight;
                        sum += f64::from(value) * weight;
                        weight_sum += weight;
                    }
                }
            }
            out.data_mut()[row * width_px + col] = if weight_sum > 0.0 {
                (sum / weight_sum) as f32
            } else {
                0.0
            };
        }
    }
}

/// For each of `target` output cells along one axis, the source cells it covers and how much of
/// each (in source pixels).
fn area_weights(source: usize, target: usize) -> Vec<Vec<(usize, f64)>> {
    let step = source as f64 / target as f64;
    (0..target)
        .map(|cell| {
            let start = cell as f64 * step;
            let end = ((cell + 1) as f64 * step).min(source as f64);
            let first = start.floor() as usize;
            let last = (end.ceil() as usize).min(source);
            (first..last)
                .filter_map(|index| {
                    let overlap = (end.min(index as f64 + 1.0) - start.max(index as f64)).max(0.0);
                    (overlap > 1e-12).then_some((index, overlap))
                })
                .collect()
        })
        .collect()
}

/// `camera` brought to `max_width_px` when it is wider (height in proportion, rounded), else as
/// it is.
fn at_most_width(camera: &Camera, max_width_px: Option<u32>) -> Camera {
    match max_width_px {
        Some(width_px) if camera.width_px > width_px => {
            let height_px = (f64::from(camera.height_px) * f64::from(width_px)
                / f64::from(camera.width_px))
            .round()
            .max(1.0) as u32;
            camera.resized(width_px, height_px)
        }
        _ => *camera,
    }
}

/// One of [`UndistortMap`]'s resampling functions (photo or depth).
type Remap = fn(&UndistortMap, ImageView<'_, f32>, &mut Image<f32>) -> Result<(), UndistortError>;

/// How a photo of `source` becomes an image of the pinhole `working` camera: an area resize to
/// the working width (when the photo is wider), then an undistortion remap (when `source` has
/// distortion). Built once per camera; applying it allocates only the outputs.
#[derive(Clone, Debug)]
pub struct WorkingCamera {
    /// The camera of the photo as given.
    pub source: Camera,
    /// `source` without its lens distortion, at the photo's size: COLMAP's undistorted camera
    /// ([`undistorted_camera`]), what the remap makes (`source` itself when it has none).
    pub undistorted: Camera,
    /// The ideal pinhole camera registration uses: `undistorted` brought to the working width,
    /// so the same as the one of the photo COLMAP undistorted.
    pub working: Camera,
    /// `undistorted` ← `source`, at the photo's size (None without distortion).
    map: Option<UndistortMap>,
}

impl WorkingCamera {
    /// The plan for `source`: distortion is removed at the photo's size, as COLMAP's
    /// image_undistorter does it, then photos wider than `max_width_px` (None: any width) are
    /// averaged down to that width (height in proportion, rounded). A SIMPLE_RADIAL photo and
    /// the photo COLMAP undistorted from it get the same working camera and nearly the same
    /// pixels (undistorting after the resize instead gave the Brighton photos a 502×281 camera
    /// against 505×283, and a photo blurrier by the bilinear interpolation at the working
    /// width: mean difference from COLMAP's 0.0126 against 0.0053, docs/measurements.md).
    pub fn new(source: &Camera, max_width_px: Option<u32>) -> Result<Self, UndistortError> {
        if let Some(0) = max_width_px {
            return Err(UndistortError::BadWorkingWidth { width_px: 0 });
        }
        let undistorted = undistorted_camera(source)?;
        let working = at_most_width(&undistorted, max_width_px);
        let map = (!matches!(source.distortion, Distortion::None))
            .then(|| UndistortMap::new(source, &undistorted));
        Ok(Self {
            source: *source,
            undistorted,
            working,
            map,
        })
    }

    /// Whether the photo is used as it is.
    pub fn is_identity(&self) -> bool {
        self.map.is_none() && self.working == self.source
    }

    /// The photo (grey, of the source camera's size) as the working camera sees it.
    pub fn photo(&self, photo: ImageView<'_, f32>) -> Result<Image<f32>, UndistortError> {
        self.apply(photo, resize_area, UndistortMap::remap_photo)
    }

    /// The depth map (of the source camera's size) as the working camera sees it.
    pub fn depth(&self, depth_m: ImageView<'_, f32>) -> Result<Image<f32>, UndistortError> {
        self.apply(depth_m, resize_depth_area, UndistortMap::remap_depth)
    }

    fn apply(
        &self,
        image: ImageView<'_, f32>,
        resize: fn(ImageView<'_, f32>, usize, usize, &mut Image<f32>),
        remap: Remap,
    ) -> Result<Image<f32>, UndistortError> {
        let expected = (
            self.source.width_px as usize,
            self.source.height_px as usize,
        );
        if image.size() != expected {
            return Err(UndistortError::SizeMismatch {
                found_width_px: image.width_px(),
                found_height_px: image.height_px(),
                camera_width_px: self.source.width_px,
                camera_height_px: self.source.height_px,
            });
        }
        let remapped = match &self.map {
            Some(map) => {
                let mut out = Image::default();
                remap(map, image, &mut out)?;
                Some(out)
            }
            None => None,
        };
        if self.working == self.undistorted {
            return Ok(remapped.unwrap_or_else(|| image.to_image()));
        }
        let mut out = Image::default();
        resize(
            remapped.as_ref().map_or(image, Image::view),
            self.working.width_px as usize,
            self.working.height_px as usize,
            &mut out,
        );
        Ok(out)
    }

    /// `A = K_working · K_source⁻¹`: working pixels from the source's undistorted pixels (the
    /// resize and the principal-point shift of the undistortion).
    fn working_from_source(&self) -> Matrix3<f64> {
        let source_k = self.source.intrinsics.k_matrix();
        self.working.intrinsics.k_matrix()
            * source_k.try_inverse().unwrap_or_else(Matrix3::identity)
    }

    /// The working camera for a camera `estimated` of the original photo (the inverse of
    /// [`Self::source_camera_for`]): PINHOLE at the working size.
    pub fn working_camera_for(&self, estimated: &Camera) -> Camera {
        let k = self.working_from_source() * estimated.intrinsics.k_matrix();
        Camera::pinhole(
            self.working.width_px,
            self.working.height_px,
            PinholeIntrinsics::from_k_matrix(&k),
        )
    }

    /// The camera of the original photo for a camera `estimated` with the working camera (the
    /// intrinsics a DLT found at the working size): its `K` taken back through the resize and
    /// the principal-point shift of the undistortion, with the source's distortion. Models with
    /// one focal length become their two-focal counterpart (PINHOLE, OPENCV) so that `fx ≠ fy`
    /// is kept; the skew (which COLMAP cannot store) is kept in memory as it is.
    pub fn source_camera_for(&self, estimated: &Camera) -> Camera {
        let a_inverse = self
            .working_from_source()
            .try_inverse()
            .unwrap_or_else(Matrix3::identity);
        let intrinsics =
            PinholeIntrinsics::from_k_matrix(&(a_inverse * estimated.intrinsics.k_matrix()));
        let (model, distortion) = match self.source.distortion {
            Distortion::None => (CameraModelId::Pinhole, Distortion::None),
            Distortion::Radial1 { k1 } => (
                CameraModelId::OpenCv,
                Distortion::OpenCv {
                    k1,
                    k2: 0.0,
                    p1: 0.0,
                    p2: 0.0,
                },
            ),
            Distortion::Radial2 { k1, k2 } => (
                CameraModelId::OpenCv,
                Distortion::OpenCv {
                    k1,
                    k2,
                    p1: 0.0,
                    p2: 0.0,
                },
            ),
            opencv @ Distortion::OpenCv { .. } => (CameraModelId::OpenCv, opencv),
        };
        Camera {
            model,
            width_px: self.source.width_px,
            height_px: self.source.height_px,
            intrinsics,
            distortion,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    /// A strongly distorted OPENCV camera (barrel, a few pixels of tangential part).
    fn opencv_camera() -> Camera {
        Camera::from_colmap_params(
            CameraModelId::OpenCv,
            400,
            300,
            &[300.0, 310.0, 205.0, 148.0, -0.18, 0.04, 0.002, -0.001],
        )
        .unwrap()
    }

    #[test]
    fn points_round_trip_through_the_map_and_the_camera() {
        for source in [
            opencv_camera(),
            Camera::from_colmap_params(
                CameraModelId::SimpleRadial,
                1000,
                562,
                &[585.089, 500.0, 281.0, 0.00395],
            )
            .unwrap(),
        ] {
            let working = WorkingCamera::new(&source, None).unwrap();
            let map = working.map.as_ref().unwrap();
            let (width, height) = map.target_size();
            let mut worst_px: f64 = 0.0;
            for row in (0..height).step_by(7) {
                for col in (0..width).step_by(7) {
                    // The map's source position, undistorted back into the working camera.
                    let source_px = map.source_px(col, row).unwrap();
                    let ray = source.unproject(source_px).unwrap();
                    let back = working.working.intrinsics.project(&ray).unwrap();
                    worst_px = worst_px.max((back - pixel_center(col, row)).norm());
                    // Every working pixel sees the photo (no blank pixels).
                    assert!(
                        source.contains(&source_px),
                        "{source_px:?} outside the photo"
                    );
                }
            }
            assert!(
                worst_px < 0.05,
                "{:?}: round trip {worst_px} px",
                source.model
            );
        }
    }

    #[test]
    fn brighton_simple_radial_becomes_colmaps_undistorted_pinhole() {
        // The shared set's two cameras (tests/data/brighton_beach/gt_*/cameras.txt): COLMAP's
        // image_undistorter made the second from the first.
        let read = |folder: &str| {
            let path = crate::test_data::repo_data(&format!("brighton_beach/{folder}/cameras.txt"));
            *crate::io::colmap::read_cameras_txt(&path)
                .unwrap()
                .get(&1)
                .unwrap()
        };
        let distorted = read("gt_simple_radial");
        let expected = read("gt_undistorted");
        let working = undistorted_camera(&distorted).unwrap();
        assert_eq!((working.width_px, working.height_px), (995, 558));
        assert_eq!(working.model, CameraModelId::Pinhole);
        let (got, want) = (working.intrinsics, expected.intrinsics);
        for (a, b) in [
            (got.fx_px, want.fx_px),
            (got.fy_px, want.fy_px),
            (got.cx_px, want.cx_px),
            (got.cy_px, want.cy_px),
        ] {
            assert!((a - b).abs() < 1e-9, "{got:?} vs {want:?}");
        }
        // At a working width, the distorted photo and the photo COLMAP undistorted from it get
        // the same working camera (issue #16: their poses are compared pixel for pixel).
        for width_px in [505, 333, 995, 1000] {
            let from_distorted = WorkingCamera::new(&distorted, Some(width_px)).unwrap();
            let from_undistorted = WorkingCamera::new(&expected, Some(width_px)).unwrap();
            let (a, b) = (from_distorted.working, from_undistorted.working);
            assert_eq!(
                (a.width_px, a.height_px),
                (b.width_px, b.height_px),
                "{width_px}"
            );
            assert_eq!(a.model, b.model);
            let difference = (a.intrinsics.k_matrix() - b.intrinsics.k_matrix()).norm();
            assert!(difference < 1e-9, "{width_px}: {a:?} vs {b:?}");
        }
        let at_505 = WorkingCamera::new(&distorted, Some(505)).unwrap().working;
        assert_eq!((at_505.width_px, at_505.height_px), (505, 283));
    }

    /// Gaussian blobs at known working-camera pixels, drawn into the distorted photo through
    /// the camera model (each photo pixel's ray, undistorted analytically): after the remap each
    /// blob's centroid must be where it was put.
    #[test]
    fn undistorted_image_puts_features_where_the_pinhole_camera_projects_them() {
        let source = opencv_camera();
        let working = WorkingCamera::new(&source, None).unwrap();
        let pinhole = working.working;
        let blobs: Vec<Vector2<f64>> = [
            (0.15, 0.2),
            (0.5, 0.5),
            (0.85, 0.15),
            (0.2, 0.8),
            (0.8, 0.85),
        ]
        .iter()
        .map(|&(u, v)| {
            Vector2::new(
                u * f64::from(pinhole.width_px),
                v * f64::from(pinhole.height_px),
            )
        })
        .collect();
        let sigma_px = 2.5;
        let pattern = |at: Vector2<f64>| -> f32 {
            blobs
                .iter()
                .map(|b| (-(at - b).norm_squared() / (2.0 * sigma_px * sigma_px)).exp())
                .sum::<f64>() as f32
        };
        let photo = Image::from_fn(
            source.width_px as usize,
            source.height_px as usize,
            |c, r| {
                let ray = source.unproject(pixel_center(c, r)).unwrap();
                pattern(pinhole.intrinsics.project(&ray).unwrap())
            },
        );
        let undistorted = working.photo(photo.view()).unwrap();
        assert_eq!(
            undistorted.size(),
            (pinhole.width_px as usize, pinhole.height_px as usize)
        );
        // Without the remap the blobs are several pixels away (the test can fail).
        let mut worst_px: f64 = 0.0;
        for blob in &blobs {
            let (mut sum, mut weight) = (Vector2::zeros(), 0.0);
            for row in 0..undistorted.height_px() {
                for col in 0..undistorted.width_px() {
                    let centre = pixel_center(col, row);
                    if (centre - blob).norm() < 4.0 * sigma_px {
                        let value = f64::from(*undistorted.get(col, row).unwrap());
                        sum += centre * value;
                        weight += value;
                    }
                }
            }
            worst_px = worst_px.max((sum / weight - blob).norm());
            let distorted_at = source
                .project(&Vector3::new(
                    (blob.x - pinhole.intrinsics.cx_px) / pinhole.intrinsics.fx_px,
                    (blob.y - pinhole.intrinsics.cy_px) / pinhole.intrinsics.fy_px,
                    1.0,
                ))
                .unwrap();
            if blob.x < 100.0 {
                assert!(
                    (distorted_at - blob).norm() > 2.0,
                    "distortion too weak to test"
                );
            }
        }
        assert!(worst_px < 0.05, "blob centroids off by {worst_px} px");
    }

    #[test]
    fn depth_remap_keeps_holes_and_depths() {
        let source = opencv_camera();
        let working = WorkingCamera::new(&source, None).unwrap();
        // A plane at 10 m with a hole in the middle: z is unchanged by undistortion.
        let depth = Image::from_fn(400, 300, |c, r| {
            if (150..250).contains(&c) && (100..200).contains(&r) {
                0.0
            } else {
                10.0
            }
        });
        let out = working.depth(depth.view()).unwrap();
        assert!(out
            .data()
            .iter()
            .all(|&d| d == 0.0 || (d - 10.0).abs() < 1e-5));
        let holes = out.data().iter().filter(|&&d| d == 0.0).count();
        assert!(holes > 5000 && holes < 15000, "{holes} holes");
        let wrong_size = Image::filled(10, 10, 1.0f32);
        assert!(matches!(
            working.depth(wrong_size.view()),
            Err(UndistortError::SizeMismatch { .. })
        ));
    }

    #[test]
    fn area_resize_averages_and_is_exact_for_integer_factors() {
        let small = Image::from_fn(5, 3, |c, r| (c * 10 + r) as f32 / 50.0);
        let doubled = Image::from_fn(10, 6, |c, r| *small.get(c / 2, r / 2).unwrap());
        let mut out = Image::default();
        resize_area(doubled.view(), 5, 3, &mut out);
        assert_eq!(out, small);
        // 3 → 2: the middle pixel is split between both outputs.
        let row = Image::new(3, 1, vec![0.0f32, 3.0, 6.0]).unwrap();
        resize_area(row.view(), 2, 1, &mut out);
        assert_eq!(out.data(), &[1.0, 5.0]);
        // Depth: holes do not count.
        let depth = Image::new(4, 1, vec![0.0f32, 4.0, 0.0, 0.0]).unwrap();
        resize_depth_area(depth.view(), 2, 1, &mut out);
        assert_eq!(out.data(), &[4.0, 0.0]);
    }

    #[test]
    fn working_camera_resizes_wide_photos_and_maps_intrinsics_back() {
        let source = Camera::pinhole(4000, 2250, PinholeIntrinsics::centered(3000.0, 4000, 2250));
        let working = WorkingCamera::new(&source, Some(505)).unwrap();
        assert_eq!(
            (working.working.width_px, working.working.height_px),
            (505, 284)
        );
        assert!(!working.is_identity());
        assert!((working.working.intrinsics.fx_px - 3000.0 * 505.0 / 4000.0).abs() < 1e-9);
        let same = WorkingCamera::new(&source, Some(4000)).unwrap();
        assert!(same.is_identity());
        assert_eq!(
            WorkingCamera::new(&source, Some(0)).unwrap_err(),
            UndistortError::BadWorkingWidth { width_px: 0 }
        );
        // An estimate equal to the working camera maps back to the source camera.
        for source in [source, opencv_camera()] {
            let working = WorkingCamera::new(&source, Some(300)).unwrap();
            let back = working.source_camera_for(&working.working);
            assert_eq!(
                (back.width_px, back.height_px),
                (source.width_px, source.height_px)
            );
            let (got, want) = (back.intrinsics, source.intrinsics);
            assert!(
                (got.k_matrix() - want.k_matrix()).norm() < 1e-6,
                "{got:?} vs {want:?}"
            );
            assert_eq!(back.distortion, source.distortion);
            let again = working.working_camera_for(&back);
            let difference = again.intrinsics.k_matrix() - working.working.intrinsics.k_matrix();
            assert!(difference.norm() < 1e-6, "{again:?}");
            assert_eq!(again.width_px, working.working.width_px);
        }
    }
}
