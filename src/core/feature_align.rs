//! Dense feature-metric alignment of the model with the photo: the second final-refinement
//! approach issue #11 item 3 names (PixLoc's idea — P.-E. Sarlin et al., "Back to the Feature:
//! Learning Robust Camera Localization from Pixels to Pose", CVPR 2021 — with a hand-made feature
//! instead of a learned one), measured against the edge alignment of [`crate::core::edge_align`].
//!
//! The feature is the edge-strength map both sides already have: the ASG rendering (0..1) on the
//! model's side, the query image (the photo's gradient magnitude, 0..1) on the photo's. Both are
//! blurred with the level's σ, so that a pose a few σ off still sees the slope towards the truth.
//! Every pixel of the rendering with a surface and a slope becomes a sample: its 3D point (the
//! rendering's depth) and its template value. The pose, with a gain and an offset between the two
//! modalities, minimises the robust (Tukey, MAD scale) residuals `Q(π(X)) − (a·T + b)` by
//! Gauss–Newton; coarse to fine, re-rendered per level by the caller (visibility moves with the
//! pose). Unlike the edge alignment, which uses only ridge positions, every pixel near an edge
//! votes with its whole profile, and interior shading edges count as much as contours.
//!
//! Preconditions: a pinhole camera on the query's pixel grid (COLMAP convention), known
//! intrinsics (the pose alone is aligned).

use nalgebra::{SMatrix, SVector, Vector2, Vector3, Vector6};
use serde::{Deserialize, Serialize};

use super::camera::{pixel_center, Camera};
use super::edge_align::{apply_pose_step, bilinear, pose_jacobian_rows};
use super::image::ImageView;
use super::raster::RenderBuffers;
use super::rigid::Rigid3;

/// Settings of the dense feature-metric alignment.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DenseAlignConfig {
    /// Blur of the first (coarsest) level, px; levels halve it down to `final_sigma_px`.
    pub initial_sigma_px: f64,
    pub final_sigma_px: f64,
    /// Gauss–Newton steps per level.
    pub iterations_per_level: usize,
    /// One sample per square cell of this side, px.
    pub sample_spacing_px: usize,
    /// A sample's template slope (blurred ASG per px) must reach this.
    pub min_template_slope: f32,
    /// Fewer usable samples than this: no step is taken.
    pub min_samples: usize,
}

impl Default for DenseAlignConfig {
    fn default() -> Self {
        Self {
            initial_sigma_px: 4.0,
            final_sigma_px: 1.0,
            iterations_per_level: 6,
            sample_spacing_px: 2,
            min_template_slope: 0.004,
            min_samples: 200,
        }
    }
}

impl DenseAlignConfig {
    /// The blur of each level, coarse to fine.
    pub fn level_sigmas_px(&self) -> Vec<f64> {
        let mut sigmas = Vec::new();
        let mut sigma = self.initial_sigma_px.max(self.final_sigma_px);
        loop {
            sigmas.push(sigma);
            if sigma <= self.final_sigma_px * 1.0001 {
                break;
            }
            sigma = (sigma / 2.0).max(self.final_sigma_px);
        }
        sigmas
    }
}

/// One sample: a model point and the blurred rendering's value where it was seen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DenseSample {
    pub world_m: Vector3<f64>,
    pub template: f32,
}

/// The samples of a rendering at `cam_from_world`: pixels with a surface whose blurred ASG
/// (`blurred_asg`) has a slope, one per cell, lifted with the rendering's depth.
pub fn dense_samples(
    blurred_asg: ImageView<'_, f32>,
    render: &RenderBuffers,
    camera: &Camera,
    cam_from_world: &Rigid3,
    config: &DenseAlignConfig,
    out: &mut Vec<DenseSample>,
) {
    out.clear();
    let (width_px, height_px) = blurred_asg.size();
    let spacing = config.sample_spacing_px.max(1);
    let data = blurred_asg.data();
    let depth = render.depth_m();
    let depth_data = depth.data();
    let world_from_cam = cam_from_world.inverse();
    for cell_row in (1..height_px.saturating_sub(1)).step_by(spacing) {
        for cell_col in (1..width_px.saturating_sub(1)).step_by(spacing) {
            // The strongest slope of the cell.
            let mut best: Option<(f32, usize, usize)> = None;
            for row in cell_row..(cell_row + spacing).min(height_px - 1) {
                for col in cell_col..(cell_col + spacing).min(width_px - 1) {
                    if depth_data[row * width_px + col] <= 0.0 {
                        continue;
                    }
                    let gx =
                        0.5 * (data[row * width_px + col + 1] - data[row * width_px + col - 1]);
                    let gy =
                        0.5 * (data[(row + 1) * width_px + col] - data[(row - 1) * width_px + col]);
                    let slope = (gx * gx + gy * gy).sqrt();
                    if slope >= config.min_template_slope && best.is_none_or(|b| slope > b.0) {
                        best = Some((slope, col, row));
                    }
                }
            }
            let Some((_, col, row)) = best else { continue };
            let Some(ray) = camera.unproject(pixel_center(col, row)) else {
                continue;
            };
            let point_cam = ray * f64::from(depth_data[row * width_px + col]);
            out.push(DenseSample {
                world_m: world_from_cam.transform_point(&point_cam),
                template: data[row * width_px + col],
            });
        }
    }
}

/// What one level did.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DenseLevelSummary {
    pub sigma_px: f64,
    pub steps: usize,
    /// Samples inside the image at the last step.
    pub used: usize,
    /// Robust scale of the residuals at the last step, relative to the gain (template units).
    pub scale: f64,
}

type Matrix8 = SMatrix<f64, 8, 8>;
type Vector8 = SVector<f64, 8>;

/// Tukey's biweight constant (95 % efficiency under Gaussian noise), in robust scales.
const TUKEY_C: f64 = 4.685;

/// One level: `iterations_per_level` robust Gauss–Newton steps of the pose (and the gain and
/// offset between the template and `blurred_query`) from `cam_from_world`. Returns the new pose
/// and what happened; the pose is unchanged when too few samples project into the image.
pub fn align_dense_level(
    samples: &[DenseSample],
    blurred_query: &ImageView<'_, f32>,
    camera: &Camera,
    cam_from_world: &Rigid3,
    sigma_px: f64,
    config: &DenseAlignConfig,
) -> (Rigid3, DenseLevelSummary) {
    let mut pose = *cam_from_world;
    let mut summary = DenseLevelSummary {
        sigma_px,
        ..Default::default()
    };
    // Gain and offset: least squares of the query against the template at the start.
    let (mut gain, mut offset) = photometric_fit(samples, blurred_query, camera, &pose);
    let mut rows: Vec<(Vector8, f64)> = Vec::with_capacity(samples.len());
    for _ in 0..config.iterations_per_level {
        rows.clear();
        for sample in samples {
            let point_cam = pose.transform_point(&sample.world_m);
            let Some(at_px) = camera.project(&point_cam) else {
                continue;
            };
            let Some((value, slope)) = value_and_slope(blurred_query, at_px) else {
                continue;
            };
            let (row_u, row_v) = pose_jacobian_rows(&camera.intrinsics, &point_cam);
            let pose_row: Vector6<f64> = row_u * slope.x + row_v * slope.y;
            let mut row = Vector8::zeros();
            row.fixed_rows_mut::<6>(0).copy_from(&pose_row);
            row[6] = -f64::from(sample.template);
            row[7] = -1.0;
            let residual = f64::from(value) - (gain * f64::from(sample.template) + offset);
            rows.push((row, residual));
        }
        summary.used = rows.len();
        if rows.len() < config.min_samples {
            break;
        }
        let scale = robust_scale(rows.iter().map(|(_, r)| *r));
        summary.scale = scale / gain.abs().max(1e-9);
        if scale <= 0.0 {
            break;
        }
        let c = TUKEY_C * scale;
        let mut normal = Matrix8::zeros();
        let mut gradient = Vector8::zeros();
        for (row, residual) in &rows {
            let u = residual / c;
            if u.abs() >= 1.0 {
                continue;
            }
            let weight = (1.0 - u * u).powi(2);
            normal += *row * row.transpose() * weight;
            gradient += *row * (residual * weight);
        }
        // A little damping keeps a step of a weakly constrained direction (a wall seen head on)
        // from running away.
        for i in 0..8 {
            normal[(i, i)] *= 1.0 + 1e-3;
        }
        let Some(step) = normal.cholesky().map(|c| -c.solve(&gradient)) else {
            break;
        };
        if !step.iter().all(|v| v.is_finite()) {
            break;
        }
        let pose_step: Vector6<f64> = step.fixed_rows::<6>(0).into();
        pose = apply_pose_step(&pose, &pose_step);
        gain += step[6];
        offset += step[7];
        summary.steps += 1;
    }
    (pose, summary)
}

/// The query's value and its slope (central differences, bilinear) at `at_px`.
fn value_and_slope(query: &ImageView<'_, f32>, at_px: Vector2<f64>) -> Option<(f32, Vector2<f64>)> {
    let value = bilinear(query, at_px)?;
    let dx = Vector2::new(1.0, 0.0);
    let dy = Vector2::new(0.0, 1.0);
    let gx = 0.5 * f64::from(bilinear(query, at_px + dx)? - bilinear(query, at_px - dx)?);
    let gy = 0.5 * f64::from(bilinear(query, at_px + dy)? - bilinear(query, at_px - dy)?);
    Some((value, Vector2::new(gx, gy)))
}

/// Least-squares gain and offset of the query's values at the samples' projections against the
/// samples' templates; (1, 0) when they cannot be fitted.
fn photometric_fit(
    samples: &[DenseSample],
    query: &ImageView<'_, f32>,
    camera: &Camera,
    pose: &Rigid3,
) -> (f64, f64) {
    let (mut n, mut st, mut sq, mut stt, mut stq) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for sample in samples {
        let Some(at_px) = camera.project(&pose.transform_point(&sample.world_m)) else {
            continue;
        };
        let Some(value) = bilinear(query, at_px) else {
            continue;
        };
        let (t, q) = (f64::from(sample.template), f64::from(value));
        n += 1.0;
        st += t;
        sq += q;
        stt += t * t;
        stq += t * q;
    }
    let variance = n * stt - st * st;
    if n < 2.0 || variance <= 1e-12 {
        return (1.0, 0.0);
    }
    let gain = (n * stq - st * sq) / variance;
    let gain = if gain > 1e-3 { gain } else { 1e-3 };
    (gain, (sq - gain * st) / n)
}

/// 1.4826 × the median absolute residual.
fn robust_scale(residuals: impl Iterator<Item = f64>) -> f64 {
    let mut magnitudes: Vec<f64> = residuals.map(f64::abs).collect();
    if magnitudes.is_empty() {
        return 0.0;
    }
    let middle = magnitudes.len() / 2;
    let (_, median, _) = magnitudes.select_nth_unstable_by(middle, |a, b| a.total_cmp(b));
    1.4826 * *median
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_halve_down_to_the_final_blur() {
        let config = DenseAlignConfig::default();
        assert_eq!(config.level_sigmas_px(), vec![4.0, 2.0, 1.0]);
        let one = DenseAlignConfig {
            initial_sigma_px: 1.0,
            ..config
        };
        assert_eq!(one.level_sigmas_px(), vec![1.0]);
    }

    #[test]
    fn the_robust_scale_ignores_a_few_outliers() {
        let residuals = [0.1, -0.1, 0.1, -0.1, 0.1, 50.0];
        let scale = robust_scale(residuals.into_iter());
        assert!((scale - 0.14826).abs() < 1e-9, "{scale}");
    }
}
