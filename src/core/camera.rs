//! Camera models: pinhole intrinsics (with the skew a DLT result has) and COLMAP's distortion models.
//!
//! Everything registration measures is in pixels, so one place defines how a point in the camera
//! frame becomes a pixel. Conventions (COLMAP's):
//! - camera frame: x right, y down, z forward (the optical axis);
//! - image coordinates in pixels with the **upper-left corner of the upper-left pixel at (0, 0)**, so
//!   the centre of pixel `(col, row)` is `(col + 0.5, row + 0.5)` — see [`pixel_center`];
//! - projection: normalised `(x/z, y/z)` → distortion (in normalised coordinates) → `K`.

use nalgebra::{Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Points closer to the image plane than this (in the camera frame's z, metres) do not project.
pub const MIN_DEPTH_M: f64 = 1e-6;

/// Errors of camera construction and validation.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CameraError {
    #[error("unknown camera model '{0}' (supported: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV)")]
    UnknownModel(String),
    #[error("camera model {model} takes {expected} parameters, got {got}")]
    ParamCount {
        model: &'static str,
        expected: usize,
        got: usize,
    },
    #[error("camera parameter {field} is {value}: {why}")]
    BadParameter {
        field: &'static str,
        value: f64,
        why: &'static str,
    },
    #[error("camera size {width_px}x{height_px} px is empty")]
    EmptySize { width_px: u32, height_px: u32 },
}

/// The centre of pixel `(col, row)` in image coordinates (COLMAP convention).
pub fn pixel_center(col: usize, row: usize) -> Vector2<f64> {
    Vector2::new(col as f64 + 0.5, row as f64 + 0.5)
}

/// The pixel `(col, row)` whose centre is nearest `point_px` (COLMAP convention, the inverse of
/// [`pixel_center`]); `None` outside a `width_px × height_px` image.
pub fn nearest_pixel(
    point_px: Vector2<f64>,
    width_px: usize,
    height_px: usize,
) -> Option<(usize, usize)> {
    let col = (point_px.x - 0.5).round();
    let row = (point_px.y - 0.5).round();
    (col >= 0.0 && row >= 0.0 && col < width_px as f64 && row < height_px as f64)
        .then_some((col as usize, row as usize))
}

/// The linear part of a camera: `K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]`, all in pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PinholeIntrinsics {
    pub fx_px: f64,
    pub fy_px: f64,
    pub cx_px: f64,
    pub cy_px: f64,
    /// Zero for every physical camera; non-zero only in intrinsics recovered by a DLT.
    pub skew_px: f64,
}

impl PinholeIntrinsics {
    /// Square pixels, no skew, principal point at the image centre.
    pub fn centered(focal_px: f64, width_px: u32, height_px: u32) -> Self {
        Self {
            fx_px: focal_px,
            fy_px: focal_px,
            cx_px: f64::from(width_px) / 2.0,
            cy_px: f64::from(height_px) / 2.0,
            skew_px: 0.0,
        }
    }

    pub fn k_matrix(&self) -> Matrix3<f64> {
        Matrix3::new(
            self.fx_px,
            self.skew_px,
            self.cx_px,
            0.0,
            self.fy_px,
            self.cy_px,
            0.0,
            0.0,
            1.0,
        )
    }

    /// Reads `K` back from an upper-triangular matrix (normalised so that `K[2][2] = 1`).
    pub fn from_k_matrix(k: &Matrix3<f64>) -> Self {
        let s = k[(2, 2)];
        Self {
            fx_px: k[(0, 0)] / s,
            fy_px: k[(1, 1)] / s,
            cx_px: k[(0, 2)] / s,
            cy_px: k[(1, 2)] / s,
            skew_px: k[(0, 1)] / s,
        }
    }

    /// Normalised image coordinates (x/z, y/z) → pixels.
    pub fn normalized_to_pixel(&self, normalized: Vector2<f64>) -> Vector2<f64> {
        Vector2::new(
            self.fx_px * normalized.x + self.skew_px * normalized.y + self.cx_px,
            self.fy_px * normalized.y + self.cy_px,
        )
    }

    /// Pixels → normalised image coordinates (inverse of [`Self::normalized_to_pixel`]).
    pub fn pixel_to_normalized(&self, pixel: Vector2<f64>) -> Vector2<f64> {
        let y = (pixel.y - self.cy_px) / self.fy_px;
        let x = (pixel.x - self.cx_px - self.skew_px * y) / self.fx_px;
        Vector2::new(x, y)
    }

    /// Projects a camera-frame point without distortion; `None` when it is not in front of the camera.
    pub fn project(&self, point_cam: &Vector3<f64>) -> Option<Vector2<f64>> {
        (point_cam.z > MIN_DEPTH_M).then(|| {
            self.normalized_to_pixel(Vector2::new(
                point_cam.x / point_cam.z,
                point_cam.y / point_cam.z,
            ))
        })
    }

    /// The same intrinsics for an image resized by `scale` (both axes).
    pub fn scaled(&self, scale: f64) -> Self {
        Self {
            fx_px: self.fx_px * scale,
            fy_px: self.fy_px * scale,
            cx_px: self.cx_px * scale,
            cy_px: self.cy_px * scale,
            skew_px: self.skew_px * scale,
        }
    }

    pub fn validate(&self) -> Result<(), CameraError> {
        for (field, value) in [
            ("fx", self.fx_px),
            ("fy", self.fy_px),
            ("cx", self.cx_px),
            ("cy", self.cy_px),
            ("skew", self.skew_px),
        ] {
            if !value.is_finite() {
                return Err(CameraError::BadParameter {
                    field,
                    value,
                    why: "not a finite number",
                });
            }
        }
        for (field, value) in [("fx", self.fx_px), ("fy", self.fy_px)] {
            if value <= 0.0 {
                return Err(CameraError::BadParameter {
                    field,
                    value,
                    why: "focal lengths must be positive",
                });
            }
        }
        Ok(())
    }
}

/// Lens distortion in normalised image coordinates, exactly as COLMAP applies it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Distortion {
    None,
    /// COLMAP SIMPLE_RADIAL: `k * r²`.
    Radial1 {
        k1: f64,
    },
    /// COLMAP RADIAL: `k1 * r² + k2 * r⁴`.
    Radial2 {
        k1: f64,
        k2: f64,
    },
    /// COLMAP OPENCV: two radial and two tangential terms.
    OpenCv {
        k1: f64,
        k2: f64,
        p1: f64,
        p2: f64,
    },
}

impl Distortion {
    /// The offset COLMAP adds to an undistorted normalised point.
    fn offset(&self, u: f64, v: f64) -> Vector2<f64> {
        let r2 = u * u + v * v;
        match *self {
            Distortion::None => Vector2::zeros(),
            Distortion::Radial1 { k1 } => Vector2::new(u, v) * (k1 * r2),
            Distortion::Radial2 { k1, k2 } => Vector2::new(u, v) * (k1 * r2 + k2 * r2 * r2),
            Distortion::OpenCv { k1, k2, p1, p2 } => {
                let radial = k1 * r2 + k2 * r2 * r2;
                let uv = u * v;
                Vector2::new(
                    u * radial + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u * u),
                    v * radial + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v * v),
                )
            }
        }
    }

    /// Undistorted → distorted normalised coordinates.
    pub fn distort(&self, undistorted: Vector2<f64>) -> Vector2<f64> {
        undistorted + self.offset(undistorted.x, undistorted.y)
    }

    /// Distorted → undistorted normalised coordinates by Newton's method with a numeric Jacobian
    /// (COLMAP's `IterativeUndistortion`). `None` when it does not converge.
    pub fn undistort(&self, distorted: Vector2<f64>) -> Option<Vector2<f64>> {
        if matches!(self, Distortion::None) {
            return Some(distorted);
        }
        const MAX_ITERATIONS: usize = 100;
        const STEP: f64 = 1e-7;
        let mut x = distorted;
        for _ in 0..MAX_ITERATIONS {
            let residual = self.distort(x) - distorted;
            if residual.norm() < 1e-14 {
                return Some(x);
            }
            let dx = (self.distort(x + Vector2::new(STEP, 0.0)) - self.distort(x)) / STEP;
            let dy = (self.distort(x + Vector2::new(0.0, STEP)) - self.distort(x)) / STEP;
            let jacobian = nalgebra::Matrix2::from_columns(&[dx, dy]);
            let step = jacobian.try_inverse()? * residual;
            x -= step;
            if !x.x.is_finite() || !x.y.is_finite() {
                return None;
            }
        }
        let residual = self.distort(x) - distorted;
        (residual.norm() < 1e-9).then_some(x)
    }

    fn coefficients(&self) -> Vec<(&'static str, f64)> {
        match *self {
            Distortion::None => vec![],
            Distortion::Radial1 { k1 } => vec![("k", k1)],
            Distortion::Radial2 { k1, k2 } => vec![("k1", k1), ("k2", k2)],
            Distortion::OpenCv { k1, k2, p1, p2 } => {
                vec![("k1", k1), ("k2", k2), ("p1", p1), ("p2", p2)]
            }
        }
    }
}

/// COLMAP's camera model names, for the models asgreg reads and writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum CameraModelId {
    SimplePinhole,
    Pinhole,
    SimpleRadial,
    Radial,
    OpenCv,
}

impl CameraModelId {
    pub const ALL: [CameraModelId; 5] = [
        CameraModelId::SimplePinhole,
        CameraModelId::Pinhole,
        CameraModelId::SimpleRadial,
        CameraModelId::Radial,
        CameraModelId::OpenCv,
    ];

    pub fn colmap_name(self) -> &'static str {
        match self {
            CameraModelId::SimplePinhole => "SIMPLE_PINHOLE",
            CameraModelId::Pinhole => "PINHOLE",
            CameraModelId::SimpleRadial => "SIMPLE_RADIAL",
            CameraModelId::Radial => "RADIAL",
            CameraModelId::OpenCv => "OPENCV",
        }
    }

    pub fn from_colmap_name(name: &str) -> Result<Self, CameraError> {
        Self::ALL
            .into_iter()
            .find(|model| model.colmap_name() == name)
            .ok_or_else(|| CameraError::UnknownModel(name.to_string()))
    }

    /// Number of parameters COLMAP stores for the model, in its order.
    pub fn param_count(self) -> usize {
        match self {
            CameraModelId::SimplePinhole => 3,
            CameraModelId::Pinhole => 4,
            CameraModelId::SimpleRadial => 4,
            CameraModelId::Radial => 5,
            CameraModelId::OpenCv => 8,
        }
    }
}

/// A camera: image size, linear intrinsics and distortion.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub model: CameraModelId,
    pub width_px: u32,
    pub height_px: u32,
    pub intrinsics: PinholeIntrinsics,
    pub distortion: Distortion,
}

impl Camera {
    /// An undistorted PINHOLE camera (skew allowed: it is kept in memory but COLMAP cannot store it).
    pub fn pinhole(width_px: u32, height_px: u32, intrinsics: PinholeIntrinsics) -> Self {
        Self {
            model: CameraModelId::Pinhole,
            width_px,
            height_px,
            intrinsics,
            distortion: Distortion::None,
        }
    }

    /// Builds a camera from COLMAP's parameter list (the order of `cameras.txt`), validated.
    pub fn from_colmap_params(
        model: CameraModelId,
        width_px: u32,
        height_px: u32,
        params: &[f64],
    ) -> Result<Self, CameraError> {
        if params.len() != model.param_count() {
            return Err(CameraError::ParamCount {
                model: model.colmap_name(),
                expected: model.param_count(),
                got: params.len(),
            });
        }
        let p = params;
        let simple = |f: f64, cx: f64, cy: f64| PinholeIntrinsics {
            fx_px: f,
            fy_px: f,
            cx_px: cx,
            cy_px: cy,
            skew_px: 0.0,
        };
        let (intrinsics, distortion) = match model {
            CameraModelId::SimplePinhole => (simple(p[0], p[1], p[2]), Distortion::None),
            CameraModelId::Pinhole => (
                PinholeIntrinsics {
                    fx_px: p[0],
                    fy_px: p[1],
                    cx_px: p[2],
                    cy_px: p[3],
                    skew_px: 0.0,
                },
                Distortion::None,
            ),
            CameraModelId::SimpleRadial => {
                (simple(p[0], p[1], p[2]), Distortion::Radial1 { k1: p[3] })
            }
            CameraModelId::Radial => (
                simple(p[0], p[1], p[2]),
                Distortion::Radial2 { k1: p[3], k2: p[4] },
            ),
            CameraModelId::OpenCv => (
                PinholeIntrinsics {
                    fx_px: p[0],
                    fy_px: p[1],
                    cx_px: p[2],
                    cy_px: p[3],
                    skew_px: 0.0,
                },
                Distortion::OpenCv {
                    k1: p[4],
                    k2: p[5],
                    p1: p[6],
                    p2: p[7],
                },
            ),
        };
        let camera = Self {
            model,
            width_px,
            height_px,
            intrinsics,
            distortion,
        };
        camera.validate()?;
        Ok(camera)
    }

    /// COLMAP's parameter list for this camera (the inverse of [`Self::from_colmap_params`]).
    pub fn colmap_params(&self) -> Vec<f64> {
        let k = &self.intrinsics;
        let mut params = match self.model {
            CameraModelId::SimplePinhole | CameraModelId::SimpleRadial | CameraModelId::Radial => {
                vec![k.fx_px, k.cx_px, k.cy_px]
            }
            CameraModelId::Pinhole | CameraModelId::OpenCv => {
                vec![k.fx_px, k.fy_px, k.cx_px, k.cy_px]
            }
        };
        params.extend(self.distortion.coefficients().into_iter().map(|(_, v)| v));
        params
    }

    /// Checks size, finiteness and that the model, intrinsics and distortion agree.
    pub fn validate(&self) -> Result<(), CameraError> {
        if self.width_px == 0 || self.height_px == 0 {
            return Err(CameraError::EmptySize {
                width_px: self.width_px,
                height_px: self.height_px,
            });
        }
        self.intrinsics.validate()?;
        for (field, value) in self.distortion.coefficients() {
            if !value.is_finite() {
                return Err(CameraError::BadParameter {
                    field,
                    value,
                    why: "not a finite number",
                });
            }
        }
        Ok(())
    }

    pub fn longest_side_px(&self) -> u32 {
        self.width_px.max(self.height_px)
    }

    /// Projects a camera-frame point to pixels with distortion; `None` behind the camera.
    pub fn project(&self, point_cam: &Vector3<f64>) -> Option<Vector2<f64>> {
        if point_cam.z <= MIN_DEPTH_M {
            return None;
        }
        let normalized = Vector2::new(point_cam.x / point_cam.z, point_cam.y / point_cam.z);
        Some(
            self.intrinsics
                .normalized_to_pixel(self.distortion.distort(normalized)),
        )
    }

    /// The ray through a pixel, in the camera frame, scaled so that `z = 1`.
    /// `None` when the distortion cannot be inverted there.
    pub fn unproject(&self, pixel: Vector2<f64>) -> Option<Vector3<f64>> {
        let distorted = self.intrinsics.pixel_to_normalized(pixel);
        let normalized = self.distortion.undistort(distorted)?;
        Some(Vector3::new(normalized.x, normalized.y, 1.0))
    }

    /// Whether a pixel position lies inside the image.
    pub fn contains(&self, pixel: &Vector2<f64>) -> bool {
        pixel.x >= 0.0
            && pixel.y >= 0.0
            && pixel.x < f64::from(self.width_px)
            && pixel.y < f64::from(self.height_px)
    }

    /// The same camera for the image resized to `width_px` × `height_px` (distortion is unchanged:
    /// it lives in normalised coordinates).
    pub fn resized(&self, width_px: u32, height_px: u32) -> Self {
        let sx = f64::from(width_px) / f64::from(self.width_px);
        let sy = f64::from(height_px) / f64::from(self.height_px);
        let k = &self.intrinsics;
        Self {
            width_px,
            height_px,
            intrinsics: PinholeIntrinsics {
                fx_px: k.fx_px * sx,
                fy_px: k.fy_px * sy,
                cx_px: k.cx_px * sx,
                cy_px: k.cy_px * sy,
                skew_px: k.skew_px * sx,
            },
            ..*self
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_model_round_trips_its_colmap_params() {
        let params: [&[f64]; 5] = [
            &[500.0, 320.0, 240.0],
            &[500.0, 510.0, 320.0, 240.0],
            &[500.0, 320.0, 240.0, 0.01],
            &[500.0, 320.0, 240.0, 0.01, -0.002],
            &[500.0, 510.0, 320.0, 240.0, 0.01, -0.002, 0.001, -0.0005],
        ];
        for (model, params) in CameraModelId::ALL.into_iter().zip(params) {
            let camera = Camera::from_colmap_params(model, 640, 480, params).unwrap();
            assert_eq!(camera.colmap_params(), params.to_vec(), "{model:?}");
            assert_eq!(
                CameraModelId::from_colmap_name(model.colmap_name()).unwrap(),
                model
            );
        }
    }

    #[test]
    fn wrong_param_count_and_nan_are_rejected() {
        assert_eq!(
            Camera::from_colmap_params(CameraModelId::Pinhole, 10, 10, &[1.0, 2.0, 3.0]),
            Err(CameraError::ParamCount {
                model: "PINHOLE",
                expected: 4,
                got: 3
            })
        );
        let err =
            Camera::from_colmap_params(CameraModelId::SimplePinhole, 10, 10, &[f64::NAN, 5.0, 5.0])
                .unwrap_err();
        assert!(err.to_string().contains("fx"), "{err}");
        assert!(CameraModelId::from_colmap_name("FISHEYE").is_err());
    }

    #[test]
    fn projection_applies_distortion_and_unproject_inverts_it() {
        let camera = Camera::from_colmap_params(
            CameraModelId::OpenCv,
            1000,
            600,
            &[800.0, 790.0, 500.0, 300.0, -0.1, 0.02, 0.001, -0.002],
        )
        .unwrap();
        let point = Vector3::new(1.2, -0.7, 4.0);
        let pixel = camera.project(&point).unwrap();
        let undistorted = camera.intrinsics.project(&point).unwrap();
        assert!(
            (pixel - undistorted).norm() > 1.0,
            "distortion must move the point"
        );
        let ray = camera.unproject(pixel).unwrap();
        assert!((ray * 4.0 - point).norm() < 1e-9);
        assert!(camera.project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn simple_radial_matches_colmap_formula() {
        // COLMAP: u' = u (1 + k r²); x = f u' + cx.
        let camera = Camera::from_colmap_params(
            CameraModelId::SimpleRadial,
            100,
            100,
            &[100.0, 50.0, 50.0, 0.1],
        )
        .unwrap();
        let pixel = camera.project(&Vector3::new(0.5, 0.0, 1.0)).unwrap();
        assert!((pixel.x - (50.0 + 100.0 * 0.5 * (1.0 + 0.1 * 0.25))).abs() < 1e-12);
        assert!((pixel.y - 50.0).abs() < 1e-12);
    }

    #[test]
    fn skew_round_trips_through_k() {
        let intrinsics = PinholeIntrinsics {
            fx_px: 400.0,
            fy_px: 410.0,
            cx_px: 200.0,
            cy_px: 150.0,
            skew_px: 1.5,
        };
        assert_eq!(
            PinholeIntrinsics::from_k_matrix(&(intrinsics.k_matrix() * 2.0)),
            intrinsics
        );
        let pixel = Vector2::new(13.0, 77.0);
        let back = intrinsics.normalized_to_pixel(intrinsics.pixel_to_normalized(pixel));
        assert!((back - pixel).norm() < 1e-12);
    }
}
