//! The MVS-like depth map of a synthetic photo: what multi-view stereo would give for it, not the
//! exact depth (issue #11 item 5). Real MVS depth is sparse and noisy for reasons that follow from
//! how stereo matches a window of the photo against its neighbours, and each is modelled from the
//! photo's own appearance or the surface's geometry, never from a per-scene constant:
//! - no depth where the window has no texture: its luma standard deviation is below a few times
//!   the photo's own noise (estimated from the photo, Immerkær 1996), so the match is noise;
//! - no depth on surfaces that look different from each viewpoint (vegetation: grass and leaves
//!   are 3-D and move; glass mirrors the sky), so no view agrees with another;
//! - no depth at grazing incidence (the window's foreshortening differs between views), with a
//!   ramp from an onset angle so that the border is ragged, as in real maps;
//! - foreground depth spreads half a window into the background at occlusion edges (edge
//!   fattening: the window straddling the edge is dominated by the foreground's texture);
//! - noise of a disparity error: σ_d = σ_disp · d² / (f · B), growing with the square of depth
//!   for the neighbours' baseline B, and σ_disp growing as the texture weakens;
//! - random blob-shaped holes for everything else (occlusion in the neighbours, failed checks).

use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::texture::{fbm, hash_u64, value_noise};
use crate::core::image::Image;

/// Parameters of the MVS-like depth (the stereo the maps imitate, not the scene).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DepthParams {
    /// Side of the stereo matching window, px (odd): texture is judged over it and foreground
    /// depth spreads half of it across occlusion edges.
    pub window_px: usize,
    /// Least ratio of the window's luma standard deviation to the photo's noise for a match.
    pub min_texture_snr: f32,
    /// Incidence angle (view ray to surface normal) where matches start to fail, degrees.
    pub grazing_onset_deg: f32,
    /// Incidence angle beyond which no match survives, degrees.
    pub grazing_max_deg: f32,
    /// Standard deviation of the matched disparity on well-textured surfaces, px.
    pub disparity_noise_px: f32,
    /// Texture-to-noise ratio at or above which the disparity noise is `disparity_noise_px`
    /// (weaker texture: proportionally more).
    pub good_texture_snr: f32,
    /// Baseline to the neighbouring views as a fraction of the photo's median depth.
    pub baseline_ratio: f32,
    /// Share of view-dependent surfaces (vegetation, glass) without depth.
    pub view_dependent_loss: f32,
    /// Fraction of the image removed as random blob-shaped holes.
    pub hole_fraction: f32,
    /// Depths beyond this are background (no MVS depth), metres.
    pub max_depth_m: f32,
    /// Neighbouring depths nearer by more than this fraction are foreground (fattening).
    pub occlusion_step: f32,
}

impl Default for DepthParams {
    fn default() -> Self {
        Self {
            window_px: 7,
            min_texture_snr: 2.5,
            grazing_onset_deg: 65.0,
            grazing_max_deg: 80.0,
            disparity_noise_px: 0.3,
            good_texture_snr: 8.0,
            baseline_ratio: 0.15,
            view_dependent_loss: 0.85,
            hole_fraction: 0.05,
            max_depth_m: 150.0,
            occlusion_step: 0.05,
        }
    }
}

impl DepthParams {
    /// Why the parameters cannot make a depth map, if they cannot.
    pub fn validate(&self) -> Result<(), String> {
        if self.window_px % 2 == 0 || self.window_px < 3 {
            return Err(format!(
                "depth.window_px {} must be odd and at least 3",
                self.window_px
            ));
        }
        if !(0.0..0.9).contains(&self.hole_fraction) {
            return Err(format!(
                "depth.hole_fraction {} is outside [0, 0.9)",
                self.hole_fraction
            ));
        }
        if !(0.0..=1.0).contains(&self.view_dependent_loss) {
            return Err(format!(
                "depth.view_dependent_loss {} is outside [0, 1]",
                self.view_dependent_loss
            ));
        }
        if !(self.grazing_onset_deg < self.grazing_max_deg && self.grazing_max_deg <= 90.0) {
            return Err(format!(
                "depth.grazing_onset_deg {} must be below grazing_max_deg {} (at most 90)",
                self.grazing_onset_deg, self.grazing_max_deg
            ));
        }
        for (field, value) in [
            ("min_texture_snr", self.min_texture_snr),
            ("disparity_noise_px", self.disparity_noise_px),
            ("good_texture_snr", self.good_texture_snr),
            ("baseline_ratio", self.baseline_ratio),
            ("max_depth_m", self.max_depth_m),
            ("occlusion_step", self.occlusion_step),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(format!(
                    "depth.{field} {value} is not a non-negative number"
                ));
            }
        }
        if self.baseline_ratio <= 0.0 {
            return Err("depth.baseline_ratio must be positive".into());
        }
        Ok(())
    }
}

/// The true surface behind each pixel, row-major at the photo's size.
pub struct TrueSurfaces<'a> {
    /// Exact depth along the optical axis, metres (0: nothing, e.g. sky).
    pub depth_m: &'a [f32],
    /// |cos| of the angle between the view ray and the surface normal.
    pub cos_incidence: &'a [f32],
    /// The surface looks different from each viewpoint (vegetation, glass).
    pub view_dependent: &'a [bool],
}

/// The MVS-like depth map (holes 0.0) of a photo with luma `luma` (0..255, row-major, `w`×`h`)
/// whose true surfaces are `truth`, seen with focal length `focal_px`.
pub fn mvs_like_depth(
    luma: &[f32],
    w: usize,
    h: usize,
    truth: &TrueSurfaces<'_>,
    focal_px: f32,
    params: &DepthParams,
    image_seed: u64,
) -> Image<f32> {
    let radius = params.window_px / 2;
    let noise_dn = noise_sigma_immerkaer(luma, w, h).max(0.5);
    let texture_snr: Vec<f32> = local_std_dev(luma, w, h, radius)
        .into_iter()
        .map(|s| s / noise_dn)
        .collect();
    let blob_threshold = hole_threshold(params.hole_fraction);
    let blob = |seed: u64, col: usize, row: usize, scale_px: f32| {
        let p = Vec3::new(col as f32 / scale_px, row as f32 / scale_px, 0.0);
        0.65 * value_noise(seed, p) + 0.35 * value_noise(seed ^ 0x55, p * 2.7)
    };
    let cos_onset = params.grazing_onset_deg.to_radians().cos();
    let cos_max = params.grazing_max_deg.to_radians().cos();
    // 1. Which pixels a stereo match would find (before occlusion edges).
    let matched: Vec<bool> = (0..w * h)
        .into_par_iter()
        .map(|index| {
            let (row, col) = (index / w, index % w);
            let d = truth.depth_m[index];
            if !(d > 0.0 && d <= params.max_depth_m) || texture_snr[index] < params.min_texture_snr
            {
                return false;
            }
            // Grazing: lost with a probability ramping from the onset to the maximum angle.
            let cos = truth.cos_incidence[index];
            if cos < cos_onset {
                let loss = ((cos_onset - cos) / (cos_onset - cos_max).max(1e-6)).clamp(0.0, 1.0);
                if blob(image_seed ^ 311, col, row, 6.0) < loss {
                    return false;
                }
            }
            if truth.view_dependent[index]
                && blob(image_seed ^ 312, col, row, 5.0) < params.view_dependent_loss
            {
                return false;
            }
            blob(image_seed ^ 301, col, row, 14.0) <= blob_threshold
        })
        .collect();
    // The neighbours' baseline: a fixed fraction of this photo's median matched depth.
    let mut matched_depths: Vec<f32> = (0..w * h)
        .filter(|&i| matched[i])
        .map(|i| truth.depth_m[i])
        .collect();
    let median_depth_m = if matched_depths.is_empty() {
        1.0
    } else {
        let mid = matched_depths.len() / 2;
        *matched_depths.select_nth_unstable_by(mid, f32::total_cmp).1
    };
    let baseline_m = params.baseline_ratio * median_depth_m;
    // 2. Edge fattening and noise.
    Image::from_fn(w, h, |col, row| {
        let index = row * w + col;
        let own = truth.depth_m[index];
        // The nearest matched foreground within half a window.
        let mut foreground: Option<(f32, usize)> = None;
        for r in row.saturating_sub(radius)..(row + radius + 1).min(h) {
            for c in col.saturating_sub(radius)..(col + radius + 1).min(w) {
                let j = r * w + c;
                let dj = truth.depth_m[j];
                let in_front = own <= 0.0 || dj < own * (1.0 - params.occlusion_step);
                if matched[j] && in_front && foreground.is_none_or(|(best, _)| dj < best) {
                    foreground = Some((dj, j));
                }
            }
        }
        let (d, source) = match foreground {
            Some(found) => found,
            None if matched[index] => (own, index),
            None => return 0.0,
        };
        let snr = texture_snr[source].max(params.min_texture_snr).max(1e-3);
        let disparity_px = params.disparity_noise_px * (params.good_texture_snr / snr).max(1.0);
        let sigma_m = disparity_px * d * d / (focal_px.max(1e-3) * baseline_m.max(1e-6));
        // Part per pixel, part shared over about a window (the window's matching error).
        let correlated = fbm(
            image_seed ^ 303,
            Vec3::new(col as f32, row as f32, 0.0),
            params.window_px as f32 * 2.0,
            3,
            0.0,
        );
        let white = gaussian_from_hash(hash_u64(image_seed ^ 0xD1 ^ index as u64));
        (d + sigma_m * (0.6 * white + 2.4 * correlated)).max(0.0)
    })
}

/// The photo's noise standard deviation (Immerkær, "Fast noise variance estimation", CVIU 1996):
/// mean absolute response to the Laplacian difference mask, which cancels smooth structure.
pub fn noise_sigma_immerkaer(luma: &[f32], w: usize, h: usize) -> f32 {
    if w < 3 || h < 3 {
        return 0.0;
    }
    let sum: f64 = (1..h - 1)
        .into_par_iter()
        .map(|row| {
            let mut line = 0.0f64;
            for col in 1..w - 1 {
                let at = |dr: isize, dc: isize| {
                    luma[(row as isize + dr) as usize * w + (col as isize + dc) as usize]
                };
                let response = at(-1, -1) - 2.0 * at(-1, 0) + at(-1, 1) - 2.0 * at(0, -1)
                    + 4.0 * at(0, 0)
                    - 2.0 * at(0, 1)
                    + at(1, -1)
                    - 2.0 * at(1, 0)
                    + at(1, 1);
                line += f64::from(response.abs());
            }
            line
        })
        .sum();
    let n = ((w - 2) * (h - 2)) as f64;
    ((std::f64::consts::PI / 2.0).sqrt() * sum / (6.0 * n)) as f32
}

/// Threshold on the blob noise (≈ uniform-ish around 0.5) giving the wanted hole fraction.
pub fn hole_threshold(hole_fraction: f32) -> f32 {
    // The sum of two value noises concentrates around 0.5 with std ≈ 0.12; map the fraction
    // through an approximation of that distribution's upper tail.
    let f = hole_fraction.clamp(0.0, 0.99);
    if f <= 0.0 {
        return f32::INFINITY;
    }
    let z = inverse_normal_upper_tail(f);
    0.5 + 0.12 * z
}

fn inverse_normal_upper_tail(p: f32) -> f32 {
    // Bisection on the complementary error function approximation.
    let tail = |z: f32| 0.5 * erfc_approx(z / std::f32::consts::SQRT_2);
    let (mut lo, mut hi) = (-6.0f32, 6.0f32);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if tail(mid) > p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

fn erfc_approx(x: f32) -> f32 {
    // Abramowitz–Stegun 7.1.26.
    let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
    let y = t
        * (0.254_829_6
            + t * (-0.284_496_7 + t * (1.421_413_7 + t * (-1.453_152 + t * 1.061_405_4))));
    let erfc = y * (-x * x).exp();
    if x >= 0.0 {
        erfc
    } else {
        2.0 - erfc
    }
}

/// A standard normal number from a hash (Box–Muller on two 24-bit uniforms).
pub fn gaussian_from_hash(key: u64) -> f32 {
    let u1 = ((key >> 40) as f32 + 0.5) / (1u64 << 24) as f32;
    let u2 = (((key >> 8) & 0xFF_FFFF) as f32 + 0.5) / (1u64 << 24) as f32;
    (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
}

/// Standard deviation over a `(2r+1)²` window (clamped at the border).
pub fn local_std_dev(values: &[f32], w: usize, h: usize, r: usize) -> Vec<f32> {
    (0..w * h)
        .into_par_iter()
        .map(|index| {
            let (row, col) = (index / w, index % w);
            let (mut sum, mut sum_sq, mut n) = (0.0f32, 0.0f32, 0.0f32);
            for rr in row.saturating_sub(r)..(row + r + 1).min(h) {
                for cc in col.saturating_sub(r)..(col + r + 1).min(w) {
                    let v = values[rr * w + cc];
                    sum += v;
                    sum_sq += v * v;
                    n += 1.0;
                }
            }
            let mean = sum / n;
            (sum_sq / n - mean * mean).max(0.0).sqrt()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat scene at `depth_m` facing the camera, `w`×`h`, with luma from `luma_at`.
    fn run(
        w: usize,
        h: usize,
        depth_at: impl Fn(usize, usize) -> f32,
        luma_at: impl Fn(usize, usize) -> f32,
        cos: f32,
        view_dependent: bool,
        params: &DepthParams,
    ) -> Image<f32> {
        let depth: Vec<f32> = (0..w * h).map(|i| depth_at(i % w, i / w)).collect();
        let luma: Vec<f32> = (0..w * h).map(|i| luma_at(i % w, i / w)).collect();
        let cos = vec![cos; w * h];
        let vd = vec![view_dependent; w * h];
        let truth = TrueSurfaces {
            depth_m: &depth,
            cos_incidence: &cos,
            view_dependent: &vd,
        };
        mvs_like_depth(&luma, w, h, &truth, 300.0, params, 7)
    }

    fn textured(col: usize, row: usize) -> f32 {
        // Strong texture plus a little per-pixel noise.
        let n = gaussian_from_hash(hash_u64((row * 1000 + col) as u64));
        128.0 + 40.0 * value_noise(3, Vec3::new(col as f32 / 3.0, row as f32 / 3.0, 0.0)) + 2.0 * n
    }

    fn plain(col: usize, row: usize) -> f32 {
        128.0 + 2.0 * gaussian_from_hash(hash_u64((row * 1000 + col) as u64))
    }

    fn valid_fraction(depth: &Image<f32>) -> f64 {
        depth.data().iter().filter(|d| **d > 0.0).count() as f64 / depth.data().len() as f64
    }

    #[test]
    fn immerkaer_recovers_the_noise_of_a_smooth_image() {
        let (w, h) = (200, 150);
        let luma: Vec<f32> = (0..w * h)
            .map(|i| {
                let (c, r) = ((i % w) as f32, (i / w) as f32);
                100.0 + 0.3 * c + 0.1 * r + 3.0 * gaussian_from_hash(hash_u64(i as u64))
            })
            .collect();
        let sigma = noise_sigma_immerkaer(&luma, w, h);
        assert!((sigma - 3.0).abs() < 0.3, "estimated {sigma}, true 3.0");
    }

    #[test]
    fn texture_grazing_and_view_dependence_decide_where_depth_is() {
        let params = DepthParams {
            hole_fraction: 0.0,
            ..DepthParams::default()
        };
        let flat = |_: usize, _: usize| 20.0;
        let textured_front = run(120, 90, flat, textured, 1.0, false, &params);
        let plain_front = run(120, 90, flat, plain, 1.0, false, &params);
        let textured_grazing = run(120, 90, flat, textured, 0.1, false, &params);
        let grass = run(120, 90, flat, textured, 1.0, true, &params);
        let (t, p, g, v) = (
            valid_fraction(&textured_front),
            valid_fraction(&plain_front),
            valid_fraction(&textured_grazing),
            valid_fraction(&grass),
        );
        assert!(t > 0.9, "textured, facing the camera: {t}");
        assert!(p < 0.05, "untextured: {p}");
        assert!(g < 0.05, "grazing (84°): {g}");
        assert!(v < 0.4, "view-dependent: {v}");
    }

    #[test]
    fn foreground_spreads_half_a_window_and_noise_grows_with_depth() {
        let params = DepthParams {
            hole_fraction: 0.0,
            ..DepthParams::default()
        };
        // Left half at 10 m, right half at 40 m; both textured.
        let step = |col: usize, _: usize| if col < 60 { 10.0 } else { 40.0 };
        let depth = run(120, 90, step, textured, 1.0, false, &params);
        let row = 45;
        let at = |col: usize| depth.data()[row * 120 + col];
        // Within half a window (3 px) right of the edge the foreground's depth is reported.
        assert!(at(61) < 15.0 && at(62) < 15.0, "{} {}", at(61), at(62));
        assert!(at(60 + params.window_px) > 30.0, "{}", at(67));
        // Noise: relative error grows with depth (σ_d ∝ d²).
        let rel_error = |lo: usize, hi: usize, truth: f32| {
            let mut sum = 0.0f64;
            let mut n = 0;
            for r in 0..90 {
                for c in lo..hi {
                    let d = depth.data()[r * 120 + c];
                    if d > 0.0 {
                        sum += f64::from(((d - truth) / truth).abs());
                        n += 1;
                    }
                }
            }
            sum / f64::from(n.max(1))
        };
        let near = rel_error(0, 55, 10.0);
        let far = rel_error(70, 120, 40.0);
        assert!(
            far > 2.0 * near,
            "mean relative error near {near}, far {far}"
        );
    }

    #[test]
    fn hole_threshold_removes_about_the_requested_fraction() {
        let threshold = hole_threshold(0.1);
        let mut removed = 0;
        let n = 200 * 200;
        for row in 0..200 {
            for col in 0..200 {
                let p = Vec3::new(col as f32 / 14.0, row as f32 / 14.0, 0.0);
                let blob =
                    0.65 * value_noise(9 ^ 301, p) + 0.35 * value_noise(9 ^ 301 ^ 0x55, p * 2.7);
                if blob > threshold {
                    removed += 1;
                }
            }
        }
        let fraction = removed as f64 / n as f64;
        assert!((0.03..0.25).contains(&fraction), "{fraction}");
    }

    #[test]
    fn gaussian_from_hash_has_unit_variance() {
        let n = 20_000;
        let values: Vec<f32> = (0..n).map(|i| gaussian_from_hash(hash_u64(i))).collect();
        let mean = values.iter().sum::<f32>() / n as f32;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / n as f32;
        assert!(
            mean.abs() < 0.05 && (var - 1.0).abs() < 0.08,
            "{mean} {var}"
        );
    }
}
