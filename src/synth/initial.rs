//! Initial poses for the evaluation levels (docs/design.md §3): ground truth plus Gaussian noise on rotation
//! and translation, scaled so that the mean mutual reprojection error δ (paper eq. 5) over the
//! images hits each level.
//!
//! Each image's unit noise is drawn once from a fixed seed: a rotation vector `r ~ N(0, I₃)` rad
//! (applied in the camera frame: `R_in = exp(s·r) · R_gt`) and a camera-centre offset
//! `c ~ N(0, I₃) · metres_per_radian` (`C_in = C_gt + s·c`, like a GPS error). Only the common
//! factor `s` changes between levels, found by a secant iteration on log(mean δ) vs log(s) with a
//! bisection fallback. δ is measured on the degraded model at the written image size.

use nalgebra::{UnitQuaternion, Vector3};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::core::camera::Camera;
use crate::core::mesh::Mesh;
use crate::core::reprojection::{mutual_reprojection_error_px, ReprojectionWorkspace};
use crate::core::rigid::Rigid3;

/// One image's noise direction, before scaling.
#[derive(Clone, Copy, Debug)]
pub struct UnitNoise {
    pub rotation_rad: Vector3<f64>,
    pub centre_offset_m: Vector3<f64>,
}

/// Draws the unit noise of `count` images.
pub fn draw_unit_noise(
    count: usize,
    metres_per_radian: f64,
    rng: &mut ChaCha8Rng,
) -> Vec<UnitNoise> {
    let mut normal = || -> f64 { StandardNormal.sample(rng) };
    (0..count)
        .map(|_| {
            let rotation_rad = Vector3::new(normal(), normal(), normal());
            let centre_offset_m = Vector3::new(normal(), normal(), normal()) * metres_per_radian;
            UnitNoise {
                rotation_rad,
                centre_offset_m,
            }
        })
        .collect()
}

/// The ground-truth pose disturbed by `scale` times the unit noise.
pub fn perturb(ground_truth: &Rigid3, noise: &UnitNoise, scale: f64) -> Rigid3 {
    let rotation =
        UnitQuaternion::from_scaled_axis(noise.rotation_rad * scale) * ground_truth.rotation;
    let centre = ground_truth.camera_center() + noise.centre_offset_m * scale;
    Rigid3::new(rotation, -(rotation * centre))
}

/// The outcome of calibrating one level.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LevelCalibration {
    pub target_px: f64,
    /// The common noise factor `s` (radians of rotation noise per unit).
    pub scale: f64,
    pub mean_px: f64,
    pub min_px: f64,
    pub max_px: f64,
    /// `|mean - target| / target`.
    pub relative_error: f64,
    /// Evaluations of the mean δ it took.
    pub evaluations: u32,
    /// Images where δ could not be measured (no model point visible); left out of the mean.
    pub unmeasurable_images: usize,
    /// The per-image initial poses.
    #[serde(skip)]
    pub poses: Vec<Rigid3>,
}

/// Mean, min, max δ over the images for one scale and the poses; `None` entries are unmeasurable.
fn evaluate(
    model: &Mesh,
    camera: &Camera,
    ground_truth: &[Rigid3],
    noise: &[UnitNoise],
    scale: f64,
    workspace: &mut ReprojectionWorkspace,
) -> (f64, f64, f64, usize, Vec<Rigid3>) {
    let mut sum = 0.0;
    let mut count = 0usize;
    let mut min = f64::INFINITY;
    let mut max = 0.0f64;
    let mut poses = Vec::with_capacity(ground_truth.len());
    for (gt, n) in ground_truth.iter().zip(noise) {
        let pose = perturb(gt, n, scale);
        if let Some(delta) =
            mutual_reprojection_error_px(model, camera, &pose, camera, gt, workspace)
        {
            sum += delta;
            count += 1;
            min = min.min(delta);
            max = max.max(delta);
        }
        poses.push(pose);
    }
    let mean = if count > 0 {
        sum / count as f64
    } else {
        f64::NAN
    };
    (mean, min, max, ground_truth.len() - count, poses)
}

/// Finds the scale whose mean δ is `target_px` within `tolerance` (relative), or the closest found.
pub fn calibrate_level(
    model: &Mesh,
    camera: &Camera,
    ground_truth: &[Rigid3],
    noise: &[UnitNoise],
    target_px: f64,
    tolerance: f64,
    workspace: &mut ReprojectionWorkspace,
) -> LevelCalibration {
    // Rough start: a rotation of s rad moves the image by about f·s·|r| px.
    let focal = camera.intrinsics.fx_px.max(1.0);
    let mut scale = target_px / focal / 1.6;
    let mut best: Option<LevelCalibration> = None;
    // Bracket in log space for the fallback.
    let mut low: Option<(f64, f64)> = None;
    let mut high: Option<(f64, f64)> = None;
    let mut previous: Option<(f64, f64)> = None;
    for evaluation in 1..=40u32 {
        let (mean, min, max, unmeasurable, poses) =
            evaluate(model, camera, ground_truth, noise, scale, workspace);
        let relative_error = if mean.is_finite() {
            (mean - target_px).abs() / target_px
        } else {
            f64::INFINITY
        };
        let candidate = LevelCalibration {
            target_px,
            scale,
            mean_px: mean,
            min_px: min,
            max_px: max,
            relative_error,
            evaluations: evaluation,
            unmeasurable_images: unmeasurable,
            poses,
        };
        let better = best
            .as_ref()
            .is_none_or(|b| relative_error < b.relative_error);
        if better {
            best = Some(candidate);
        } else if let Some(b) = best.as_mut() {
            b.evaluations = evaluation;
        }
        if relative_error <= tolerance {
            break;
        }
        if !mean.is_finite() || mean <= 0.0 {
            scale *= 0.5;
            continue;
        }
        if mean < target_px {
            low = Some((scale, mean));
        } else {
            high = Some((scale, mean));
        }
        // Secant on log-log (δ grows about linearly with s), bisection inside the bracket when
        // the secant leaves it.
        let mut next = match previous {
            Some((s0, m0)) if (m0 - mean).abs() > 1e-9 && (s0 - scale).abs() > 1e-12 => {
                let slope = (mean.ln() - m0.ln()) / (scale.ln() - s0.ln());
                let slope = if slope.is_finite() && slope > 0.1 {
                    slope
                } else {
                    1.0
                };
                (scale.ln() + (target_px.ln() - mean.ln()) / slope).exp()
            }
            _ => scale * target_px / mean,
        };
        if let (Some((sl, _)), Some((sh, _))) = (low, high) {
            if !(next > sl.min(sh) && next < sl.max(sh)) || evaluation > 8 {
                next = (sl * sh).sqrt();
            }
        }
        previous = Some((scale, mean));
        scale = next;
    }
    best.unwrap_or(LevelCalibration {
        target_px,
        scale,
        mean_px: f64::NAN,
        min_px: f64::NAN,
        max_px: f64::NAN,
        relative_error: f64::INFINITY,
        evaluations: 0,
        unmeasurable_images: ground_truth.len(),
        poses: ground_truth.to_vec(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn perturbation_scales_linearly_and_zero_is_identity() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let noise = draw_unit_noise(3, 10.0, &mut rng);
        let gt = Rigid3::look_at(
            &Vector3::new(10.0, 0.0, 5.0),
            &Vector3::zeros(),
            &Vector3::z(),
        )
        .unwrap();
        let same = perturb(&gt, &noise[0], 0.0);
        assert!((same.translation - gt.translation).norm() < 1e-12);
        let a = perturb(&gt, &noise[0], 0.01);
        let b = perturb(&gt, &noise[0], 0.02);
        let da = (a.camera_center() - gt.camera_center()).norm();
        let db = (b.camera_center() - gt.camera_center()).norm();
        assert!((db / da - 2.0).abs() < 1e-9);
        assert!((b.rotation_angle_to_rad(&gt) / a.rotation_angle_to_rad(&gt) - 2.0).abs() < 1e-6);
    }
}
