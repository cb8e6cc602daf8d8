//! Initial poses for the evaluation levels (docs/design.md §3): ground truth plus Gaussian noise on rotation
//! and translation, scaled so that the mean mutual reprojection error δ (paper eq. 5) over the
//! images hits each level.
//!
//! Each image's unit noise is drawn once from a fixed seed: a rotation vector `r ~ N(0, I₃)` rad
//! (applied in the camera frame: `R_in = exp(s·r) · R_gt`) and a camera-centre offset
//! `c ~ N(0, I₃) · metres_per_radian` (`C_in = C_gt + s·c`, like a GPS error). Only the common
//! factor `s` changes between levels, found by a secant iteration on log(mean δ) vs log(s) with a
//! bisection fallback. δ is measured on the degraded model at the written image size.
//!
//! The `heading` level is a drone's prior instead (issue #12 item 4): the heading (yaw about the
//! world's up, +z) off by ±U(10°, 40°) for most images and by 180° for every fourth, pitch and
//! roll off by about a degree (an IMU), the camera centre off by GPS-like noise of a metre or two.

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

/// How the `heading` level disturbs a pose (a drone's compass, IMU and GPS).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HeadingNoise {
    /// Heading error range, degrees: ±U(min, max).
    pub heading_min_deg: f64,
    pub heading_max_deg: f64,
    /// Every this many images (by index, the first of each group) the heading is 180° off instead.
    pub flip_every: usize,
    /// Pitch and roll error, degrees, uniform in ±this.
    pub tilt_max_deg: f64,
    /// Camera-centre error per horizontal axis, metres (standard deviation); vertical half of it.
    pub position_sigma_m: f64,
}

impl Default for HeadingNoise {
    fn default() -> Self {
        Self {
            heading_min_deg: 10.0,
            heading_max_deg: 40.0,
            flip_every: 4,
            tilt_max_deg: 1.0,
            position_sigma_m: 1.0,
        }
    }
}

/// The `heading` level's initial poses, one per ground-truth pose, drawn from `rng` in order.
/// The heading turns the camera about the world's up axis through its centre; pitch and roll turn
/// it about its own x and z axes.
pub fn heading_poses(
    ground_truth: &[Rigid3],
    noise: &HeadingNoise,
    rng: &mut ChaCha8Rng,
) -> Vec<Rigid3> {
    use rand::Rng;
    ground_truth
        .iter()
        .enumerate()
        .map(|(index, gt)| {
            let magnitude_deg = rng.random_range(noise.heading_min_deg..=noise.heading_max_deg);
            let sign = if rng.random_bool(0.5) { 1.0 } else { -1.0 };
            let flipped = noise.flip_every > 0 && index % noise.flip_every == 0;
            let heading_deg = if flipped { 180.0 } else { sign * magnitude_deg };
            let pitch_deg = rng.random_range(-noise.tilt_max_deg..=noise.tilt_max_deg);
            let roll_deg = rng.random_range(-noise.tilt_max_deg..=noise.tilt_max_deg);
            let mut normal = || -> f64 { StandardNormal.sample(rng) };
            let offset_m = Vector3::new(
                normal() * noise.position_sigma_m,
                normal() * noise.position_sigma_m,
                normal() * noise.position_sigma_m * 0.5,
            );
            let yaw = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), heading_deg.to_radians());
            let tilt = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), pitch_deg.to_radians())
                * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll_deg.to_radians());
            // cam_from_world' = tilt · R · yaw⁻¹: the world turned by the heading, then the
            // camera by its tilt.
            let rotation = tilt * gt.rotation * yaw.inverse();
            let centre = gt.camera_center() + offset_m;
            Rigid3::new(rotation, -(rotation * centre))
        })
        .collect()
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

    /// Heading poses keep the camera's tilt to gravity within the IMU's degree, turn the heading
    /// by 10–40° (180° for every fourth image), move the centre by GPS-like metres, and are the
    /// same for the same seed.
    #[test]
    fn heading_poses_are_a_drones_prior() {
        let gt: Vec<Rigid3> = (0..12)
            .map(|i| {
                let angle = f64::from(i) * 0.5;
                let eye = Vector3::new(30.0 * angle.cos(), 30.0 * angle.sin(), 25.0);
                Rigid3::look_at(&eye, &Vector3::zeros(), &Vector3::z()).unwrap()
            })
            .collect();
        let noise = HeadingNoise::default();
        let poses = heading_poses(&gt, &noise, &mut ChaCha8Rng::seed_from_u64(3));
        let again = heading_poses(&gt, &noise, &mut ChaCha8Rng::seed_from_u64(3));
        assert_eq!(poses, again);
        for (index, (pose, truth)) in poses.iter().zip(&gt).enumerate() {
            // The optical axis's horizontal direction and its elevation, in the world.
            let axis = |p: &Rigid3| p.inverse().transform_vector(&Vector3::z());
            let (a, b) = (axis(pose), axis(truth));
            let heading_deg = (a.y.atan2(a.x) - b.y.atan2(b.x)).to_degrees();
            let heading_deg = (heading_deg + 540.0).rem_euclid(360.0) - 180.0;
            let elevation = |v: Vector3<f64>| v.z.asin().to_degrees();
            assert!((elevation(a) - elevation(b)).abs() < 1.5, "frame {index}");
            if index % 4 == 0 {
                assert!(heading_deg.abs() > 177.0, "frame {index}: {heading_deg}");
            } else {
                assert!(
                    (9.0..=41.0).contains(&heading_deg.abs()),
                    "frame {index}: {heading_deg}"
                );
            }
            let moved_m = (pose.camera_center() - truth.camera_center()).norm();
            assert!(moved_m < 6.0, "frame {index}: {moved_m}");
        }
    }
}
