//! Change detection: what differs between a registered photo and the model. Per frame, under
//! its pose, the model's rendered depth is compared with the photo's depth (a given MVS depth
//! map, or one computed from neighbouring frames) pixel by pixel:
//! `added` (the photo sees a surface in front of the model: a new building, an extension),
//! `removed` (the photo sees through where the model has a surface: demolished), `unchanged`,
//! `unknown` (no photo depth, or no model surface on the ray). Changed pixels are grouped into
//! regions (connected components above a least area in m²) with their footprint in the model's
//! georeferenced frame; [`fusion`] merges the regions of many frames into objects.
//!
//! Noise model (what the threshold grows with): the depth difference of an unchanged surface has
//! a standard deviation `σ(d) = σ_model + σ_rel·d + σ_quad·d²` at depth `d`: the model's own
//! deviation from the world (smoothing, noise, warp), a relative depth error (MVS on a fixed
//! pixel grid: the error of a matched pixel scales with the depth), and the stereo term (depth
//! from disparity: `σ_d = d²·σ_disparity / (f·B)`), zero for a given MVS depth map and set by a
//! depth computed from a baseline. A pixel changes when `|Δ| > max(k·σ(d), Δ_min)`.
//!
//! The registered pose is not exact either: a pose whose image is `u` px off renders the model's
//! depth of a pixel up to `u` px away, which differs from the right one by about `|∇d|·u` where
//! the model's depth changes fast across the image (oblique surfaces, depth edges), and not at
//! all on a surface facing the camera. That is a per-pixel term ([`pose_error_sigma_m`], from
//! the model's rendered depth and the frame's `ChangeConfig::pose_sigma_px`), added in quadrature:
//! `σ(p) = √((σ_model + σ_rel·d + σ_quad·d²)² + σ_pose(p)²)`. It is zero for exact (ground-truth)
//! poses. A stereo depth map gets its own relative term ([`ChangeConfig::for_stereo`]): σ_rel is
//! the error of an MVS map on a fixed pixel grid, the stereo map's error is σ_quad's.
//! Under registered poses the stereo neighbours' poses are off too, which is a disparity error:
//! σ_quad becomes at least the stereo map's own spread against the model in inverse depth
//! ([`frame_quadratic_sigma_per_m`]).
//!
//! What the photo cannot see bounds what it may claim: a `removed` region most of whose photo
//! depth lies below the model's ground (the lowest model surface near it) is a wrong depth, not
//! a demolition, and is dropped as `unknown` ([`beyond_the_model`]): a demolished building
//! leaves the ground, and nothing is seen through the ground. An `added` object is bounded by
//! the other frames ([`free_space`]): a surface that more frames see past than agree with is
//! not a building, however many frames found it.
//!
//! Pure functions; [`ChangeWorkspace`] keeps the rasteriser, its buffers and the labels, so a
//! stream of frames allocates nothing per frame beyond the regions it returns.

pub mod free_space;
pub mod fusion;
pub mod polygon;
pub mod stereo;

use nalgebra::{Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::camera::{pixel_center, PinholeIntrinsics};
use super::image::{Image, ImageView};
use super::mesh::Mesh;
use super::raster::{Rasterizer, RenderBuffers, RenderOptions};
use super::rigid::Rigid3;

/// The class of one pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[repr(u8)]
pub enum ChangeClass {
    /// No photo depth, or no model surface on the ray: nothing can be said.
    Unknown = 0,
    Unchanged = 1,
    /// The photo sees something in front of the model.
    Added = 2,
    /// The photo sees through the model's surface.
    Removed = 3,
}

impl ChangeClass {
    /// The grey level of the class in mask images (one encoding for truth and detection masks).
    pub fn mask_value(self) -> u8 {
        match self {
            ChangeClass::Unknown => 0,
            ChangeClass::Unchanged => 80,
            ChangeClass::Removed => 160,
            ChangeClass::Added => 255,
        }
    }

    /// The class of a mask grey level (nearest of the four levels).
    pub fn from_mask_value(value: u8) -> Self {
        [
            ChangeClass::Unknown,
            ChangeClass::Unchanged,
            ChangeClass::Removed,
            ChangeClass::Added,
        ]
        .into_iter()
        .min_by_key(|c| (i16::from(c.mask_value()) - i16::from(value)).abs())
        .unwrap_or(ChangeClass::Unknown)
    }

    fn from_u8(value: u8) -> Self {
        match value {
            1 => ChangeClass::Unchanged,
            2 => ChangeClass::Added,
            3 => ChangeClass::Removed,
            _ => ChangeClass::Unknown,
        }
    }
}

/// The kind of a changed region or object.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ChangeKind {
    Added,
    Removed,
}

impl ChangeKind {
    pub fn class(self) -> ChangeClass {
        match self {
            ChangeKind::Added => ChangeClass::Added,
            ChangeKind::Removed => ChangeClass::Removed,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            ChangeKind::Added => "added",
            ChangeKind::Removed => "removed",
        }
    }
}

/// How changes are decided; `Default` suits a given MVS depth map (see the module's noise model).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ChangeConfig {
    /// The model's own deviation from the world, metres (σ_model).
    pub model_sigma_m: f32,
    /// Relative depth error of the photo's depth (σ_rel).
    pub relative_sigma: f32,
    /// Stereo term σ_quad, per metre (σ_disparity / (f·B)); 0 for a given MVS depth.
    pub quadratic_sigma_per_m: f32,
    /// Threshold in standard deviations (k).
    pub threshold_sigmas: f32,
    /// Depth differences below this are never a change, metres (Δ_min).
    pub min_difference_m: f32,
    /// Morphological opening of each changed class (removes thin bands along depth edges), px.
    pub opening_radius_px: usize,
    /// Least surface area of a region as seen from the camera, m².
    pub min_area_m2: f64,
    /// Least pixel count of a region.
    pub min_pixels: usize,
    /// A region must extend at least this far in two of its three extents (vertical extent,
    /// footprint width, footprint length), metres: a strip along a roof edge (a parapet, an
    /// eave the model rounded off) is long but neither high nor wide.
    pub min_extent_m: f64,
    /// An `added` pixel whose photo depth agrees (within its threshold) with the model's depth
    /// at a pixel this close is explained by the model's own foreground seen a few pixels off,
    /// px: MVS spreads foreground depth half a matching window across occlusion edges (edge
    /// fattening), which makes the photo nearer than the model there, never farther, so
    /// `removed` pixels are not touched. 0 compares pixel by pixel. 5 px: half a 7-px MVS
    /// window plus 2 px of edge noise, or the plane-sweep's 5-px window at half resolution
    /// (docs/measurements.md: 3 px left roof-edge bands on the block). Only pixels this close
    /// to a depth edge of the model ([`model_depth_edges`]: a step between neighbouring pixels
    /// larger than the change threshold) are explained so: fattening spreads a foreground over
    /// its occlusion edge, and away from one the model's depth a few pixels off is that of the
    /// same smooth surface, which says nothing about the photo's nearer surface (an extension
    /// against a wall, seen in front of the wall: docs/measurements.md, issue #13, branch
    /// `change33`).
    pub edge_tolerance_px: usize,
    /// The registered pose's error as an image displacement, px (u): each pixel's threshold
    /// gets the depth difference a pose `u` px off could cause, [`pose_error_sigma_m`], in
    /// quadrature. 0: the pose is exact (ground truth). Set per frame by the caller from the
    /// registration's own uncertainty (`asgreg changes --pose-sigma-px`, the pipeline's
    /// ChangeJob); at most [`MAX_POSE_SIGMA_PX`].
    pub pose_sigma_px: f32,
    /// σ_rel of a depth map computed by stereo ([`Self::for_stereo`]), in place of
    /// `relative_sigma` (which is an MVS map's). 0: the plane sweep's error is its stereo term
    /// σ_quad; under registered poses the pose term, not σ_rel, takes the pose's error
    /// (docs/measurements.md, branch `change14`: the block's extension, 1–3 m in front of a wall
    /// at 40 m, was under a 2.8 m threshold with σ_rel = 0.01).
    pub stereo_relative_sigma: f32,
    /// Under a registered pose (`pose_sigma_px` > 0), take u from the data instead: the image
    /// shift that best aligns the model's rendered depth with the photo's depth
    /// ([`depth_misalignment`]), its length. The registration's spread says 2–7 px on frames
    /// that are under 1 px off and 3–5 px on frames 15–17 px off (block seed 2,
    /// docs/measurements.md, branch `change13`); the depth maps themselves show how far the
    /// model lies from the photo. Ground-truth poses (u = 0) are not touched.
    pub pose_sigma_from_depth: bool,
    /// Under a registered pose (`pose_sigma_px` > 0) with a stereo depth map
    /// (`quadratic_sigma_per_m` > 0), raise σ_quad to the stereo map's own inverse-depth spread
    /// against the model ([`inverse_depth_spread_per_m`]): the neighbours' registered poses are
    /// off too, and their error relative to the frame's is a disparity error the prior σ_quad
    /// (σ_disparity / (f·B), ground-truth neighbours) does not hold (block seed 2,
    /// docs/measurements.md, branch `change15`: the false objects' frames all have a
    /// neighbour 3–11 px off there). Ground-truth poses and given depth maps are not touched.
    pub stereo_sigma_from_depth: bool,
    /// A `removed` region most of whose photo depth lies below the model's ground by more than
    /// the change threshold is a wrong depth, not a demolition ([`beyond_the_model`]): the
    /// ground is the lowest model surface within this horizontal distance of the region's
    /// footprint ([`model_ground_z_m`]), metres. A demolished building leaves the ground, and
    /// the photo cannot see below it; a stereo match on the wrong repeat of a roof's regular
    /// texture can (block seed 2 under registered poses: the false `removed` regions lay
    /// 3.6–10.4 m under the ground; docs/measurements.md, branch `change20`). Wide enough to
    /// reach the open ground beside a building's footprint (a street, a yard), narrow enough
    /// that a hillside's lower slope a block away is not this region's ground.
    /// 0: no such rule.
    pub ground_search_radius_m: f64,
}

/// The largest [`ChangeConfig::pose_sigma_px`]: a pose that far off is no registration to
/// detect changes under (the window of [`pose_error_sigma_m`] grows with it).
pub const MAX_POSE_SIGMA_PX: f32 = 16.0;

/// The default [`ChangeConfig::ground_search_radius_m`], metres: about a street's width plus a
/// yard's beside a building of the block scenes' size, so the open ground next to a region is
/// within reach whichever side the camera saw.
pub const DEFAULT_GROUND_SEARCH_RADIUS_M: f64 = 15.0;

/// The largest [`ChangeConfig::ground_search_radius_m`], metres: beyond a few blocks the lowest
/// surface says nothing about the ground under one region (terrain slopes, a river bed).
pub const MAX_GROUND_SEARCH_RADIUS_M: f64 = 200.0;

impl Default for ChangeConfig {
    fn default() -> Self {
        Self {
            model_sigma_m: 0.1,
            relative_sigma: 0.01,
            quadratic_sigma_per_m: 0.0,
            threshold_sigmas: 3.0,
            min_difference_m: 0.5,
            opening_radius_px: 1,
            min_area_m2: 4.0,
            min_pixels: 25,
            min_extent_m: 2.0,
            edge_tolerance_px: 5,
            pose_sigma_px: 0.0,
            stereo_relative_sigma: 0.0,
            pose_sigma_from_depth: true,
            stereo_sigma_from_depth: true,
            ground_search_radius_m: DEFAULT_GROUND_SEARCH_RADIUS_M,
        }
    }
}

/// Errors of change detection.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ChangeError {
    #[error("photo depth is {photo_width_px}×{photo_height_px} px but the model rendering is {model_width_px}×{model_height_px} px; give a depth map of the camera's size")]
    SizeMismatch {
        photo_width_px: usize,
        photo_height_px: usize,
        model_width_px: usize,
        model_height_px: usize,
    },
    #[error("invalid change config: {0}")]
    InvalidConfig(String),
}

impl ChangeConfig {
    pub fn validate(&self) -> Result<(), ChangeError> {
        let bad = |what: String| Err(ChangeError::InvalidConfig(what));
        if !(self.model_sigma_m >= 0.0
            && self.relative_sigma >= 0.0
            && self.stereo_relative_sigma >= 0.0
            && self.quadratic_sigma_per_m >= 0.0)
        {
            return bad("sigmas must be finite and ≥ 0".into());
        }
        if !(self.pose_sigma_px >= 0.0 && self.pose_sigma_px <= MAX_POSE_SIGMA_PX) {
            return bad(format!(
                "pose_sigma_px {} must be 0..={MAX_POSE_SIGMA_PX}",
                self.pose_sigma_px
            ));
        }
        if !(self.threshold_sigmas > 0.0 && self.min_difference_m >= 0.0) {
            return bad(format!(
                "threshold_sigmas {} must be > 0 and min_difference_m {} ≥ 0",
                self.threshold_sigmas, self.min_difference_m
            ));
        }
        if self.min_area_m2.is_nan()
            || self.min_area_m2 < 0.0
            || self.min_extent_m.is_nan()
            || self.opening_radius_px > 10
            || self.edge_tolerance_px > 10
        {
            return bad(format!(
                "min_area_m2 {} must be ≥ 0 and opening_radius_px {} ≤ 10",
                self.min_area_m2, self.opening_radius_px
            ));
        }
        if !(self.ground_search_radius_m >= 0.0
            && self.ground_search_radius_m <= MAX_GROUND_SEARCH_RADIUS_M)
        {
            return bad(format!(
                "ground_search_radius_m {} must be 0..={MAX_GROUND_SEARCH_RADIUS_M}",
                self.ground_search_radius_m
            ));
        }
        Ok(())
    }

    /// The depth difference above which a pixel at depth `depth_m` changes under an exact
    /// pose, metres.
    pub fn threshold_m(&self, depth_m: f32) -> f32 {
        self.threshold_with_pose_m(depth_m, 0.0)
    }

    /// The depth difference above which a pixel at depth `depth_m` changes when the pose's
    /// error alone could make its depths differ by `pose_sigma_m` ([`pose_error_sigma_m`]):
    /// the depth terms and the pose term in quadrature, metres.
    pub fn threshold_with_pose_m(&self, depth_m: f32, pose_sigma_m: f32) -> f32 {
        let sigma = self.model_sigma_m
            + self.relative_sigma * depth_m
            + self.quadratic_sigma_per_m * depth_m * depth_m;
        let sigma = sigma.hypot(pose_sigma_m);
        (self.threshold_sigmas * sigma).max(self.min_difference_m)
    }

    /// The settings for a depth map computed by stereo with the stereo term
    /// `quadratic_sigma_per_m` (σ_disparity / (f·B)): σ_rel becomes `stereo_relative_sigma`.
    pub fn for_stereo(&self, quadratic_sigma_per_m: f32) -> Self {
        Self {
            quadratic_sigma_per_m,
            relative_sigma: self.stereo_relative_sigma,
            ..*self
        }
    }
}

/// The image displacement u (px, [`ChangeConfig::pose_sigma_px`]) to expect of a registered
/// pose, from its registration's own evidence: verify's group spread, the mean δ between the
/// chosen pose and the other refined poses that agree with it (`mean_delta_to_chosen_px`, the
/// mean reprojection distance over the frame, the same unit as u). Each of those poses comes
/// from its own coarse start, so it is a repeat of the registration; two repeats with
/// independent errors of u each lie √2·u apart, so u = spread / √2. (Measured on `synth
/// --changes` block seed 1, 48 registered frames: spread / √2 median 2.0 px, the true δ median
/// 1.3 px, mean 1.7 px, correlation 0.70; the edge evidence's `image_uncertainty_px` is per px
/// of edge noise and 10× below the true δ, verify's compatibility threshold (25 px) is a bound,
/// not an error; docs/measurements.md, branch `change14`.) Clamped to 0..=[`MAX_POSE_SIGMA_PX`];
/// a spread that is not a number gives the largest.
pub fn pose_sigma_px_of_registration(mean_delta_to_chosen_px: f64) -> f32 {
    if mean_delta_to_chosen_px.is_nan() {
        return MAX_POSE_SIGMA_PX;
    }
    ((mean_delta_to_chosen_px / std::f64::consts::SQRT_2) as f32).clamp(0.0, MAX_POSE_SIGMA_PX)
}

/// Per pixel, the standard deviation (metres) of the model's rendered depth that a pose error
/// moving the image by `pose_sigma_px` (u) causes: the depth of a pixel u px away instead of
/// its own. Over the (2r+1)² window, r = ⌈u⌉, the largest difference between the pixel's model
/// depth and another of the window, times u / r: `|∇d|·u` on a smooth surface (a linear depth
/// changes by slope·r over r px), and the step (scaled by u / r) within u px of a depth edge.
/// Pixels without model depth get 0 and are not counted in their neighbours' windows (sky, no
/// surface: nothing to compare there). Written into `out` (resized); all zero when u = 0.
pub fn pose_error_sigma_m(
    model_depth_m: ImageView<'_, f32>,
    pose_sigma_px: f32,
    out: &mut Image<f32>,
    scratch: &mut Vec<f32>,
) {
    let (w, h) = model_depth_m.size();
    out.reset(w, h, 0.0);
    if pose_sigma_px.is_nan() || pose_sigma_px <= 0.0 || w == 0 || h == 0 {
        return;
    }
    let u = pose_sigma_px.min(MAX_POSE_SIGMA_PX);
    let r = u.ceil() as usize;
    let depth = model_depth_m.data();
    let valid = |d: f32| d.is_finite() && d > 0.0;
    // Separable window minimum and maximum of the valid depths (rows, then columns); `scratch`
    // holds the rows' minima then their maxima.
    scratch.clear();
    scratch.resize(2 * w * h, 0.0);
    let (row_min, row_max) = scratch.split_at_mut(w * h);
    for row in 0..h {
        for col in 0..w {
            let (mut lo, mut hi) = (f32::INFINITY, 0.0f32);
            for cc in col.saturating_sub(r)..(col + r + 1).min(w) {
                let d = depth[row * w + cc];
                if valid(d) {
                    lo = lo.min(d);
                    hi = hi.max(d);
                }
            }
            row_min[row * w + col] = lo;
            row_max[row * w + col] = hi;
        }
    }
    let scale = u / r as f32;
    let sigma = out.data_mut();
    for row in 0..h {
        for col in 0..w {
            let index = row * w + col;
            let d = depth[index];
            if !valid(d) {
                continue;
            }
            let (mut lo, mut hi) = (f32::INFINITY, 0.0f32);
            for rr in row.saturating_sub(r)..(row + r + 1).min(h) {
                lo = lo.min(row_min[rr * w + col]);
                hi = hi.max(row_max[rr * w + col]);
            }
            // The pixel itself is valid, so lo ≤ d ≤ hi.
            sigma[index] = scale * (hi - d).max(d - lo);
        }
    }
}

/// Relative depth difference at which [`depth_misalignment`]'s cost saturates: a depth edge
/// (a building against the ground behind it, 5–50 %) counts fully, and the gradual change of an
/// oblique surface (0.2–0.5 % per px at 40–100 m) in proportion.
const ALIGNMENT_TRUNCATION: f32 = 0.1;

/// Least share of the sampled photo depths a shift must still compare for
/// [`depth_misalignment`] to consider it (a shift that pushes most of the model out of the
/// image compares too little to be told from the others).
const ALIGNMENT_MIN_SHARE: f32 = 0.5;

/// How well the model's rendered depth lines up with the photo's depth under image shifts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DepthAlignment {
    /// The shift (col, row), px, at which the model's depth best matches the photo's: the
    /// photo's pixel x sees what the model renders at x + shift (sub-pixel by parabolas).
    pub shift_px: [f32; 2],
    /// Its mean truncated relative depth difference, and at no shift.
    pub cost: f32,
    pub cost_at_zero: f32,
    /// Photo depths compared at no shift.
    pub samples: usize,
    /// The best shift lies on the searched square's border: the misalignment may be larger.
    pub at_border: bool,
}

impl DepthAlignment {
    /// The shift's length, px.
    pub fn length_px(&self) -> f32 {
        self.shift_px[0].hypot(self.shift_px[1])
    }
}

/// The image shift within ±`max_shift_px` that best aligns `model_depth_m` (the model rendered
/// under the frame's pose) with `photo_depth_m` (0 = hole): on a grid of every `stride_px`-th
/// pixel with a photo depth, the mean of `min(|p − m| / m, 0.1)` between the photo's depth p at
/// x and the model's m at x + shift, shifts by 2 px over the square; then on every pixel the
/// best's eight neighbours and a parabola through each axis's neighbours. A pose a few pixels off moves the model's
/// depth edges that far from the photo's, so the shift measures the pose's error as an image
/// displacement where it matters for the comparison, independently of the registration's own
/// account of it; changed objects are a minority of the pixels and do not move the minimum.
/// A translation stands for the whole frame: a rotation about the optical axis or parallax
/// between near and far surfaces leaves part of the error unmeasured. `None` when fewer than 100
/// photo depths fall on the model.
pub fn depth_misalignment(
    model_depth_m: ImageView<'_, f32>,
    photo_depth_m: ImageView<'_, f32>,
    max_shift_px: usize,
    stride_px: usize,
) -> Option<DepthAlignment> {
    let (w, h) = photo_depth_m.size();
    if model_depth_m.size() != (w, h) || w == 0 || h == 0 {
        return None;
    }
    let (photo, model) = (photo_depth_m.data(), model_depth_m.data());
    let valid = |d: f32| d.is_finite() && d > 0.0;
    let samples_every = |stride: usize| -> Vec<(usize, usize, f32)> {
        (0..h)
            .step_by(stride)
            .flat_map(|row| (0..w).step_by(stride).map(move |col| (col, row)))
            .filter_map(|(col, row)| {
                let p = photo[row * w + col];
                valid(p).then_some((col, row, p))
            })
            .collect()
    };
    let on_model = |samples: &[(usize, usize, f32)]| {
        samples
            .iter()
            .filter(|(col, row, _)| valid(model[row * w + col]))
            .count()
    };
    let cost = |samples: &[(usize, usize, f32)], least: usize, dx: i64, dy: i64| -> f32 {
        let (mut sum, mut count) = (0.0f32, 0usize);
        for &(col, row, p) in samples {
            let (c, r) = (col as i64 + dx, row as i64 + dy);
            if c < 0 || r < 0 || c >= w as i64 || r >= h as i64 {
                continue;
            }
            let m = model[r as usize * w + c as usize];
            if valid(m) {
                sum += ((p - m).abs() / m).min(ALIGNMENT_TRUNCATION);
                count += 1;
            }
        }
        if count < least.max(1) {
            f32::INFINITY
        } else {
            sum / count as f32
        }
    };
    // The square by 2 px on a sparse grid (`stride_px`), then the best's neighbours and the
    // parabolas on every pixel: a grid of stride 2 cannot place an edge to better than 2 px.
    let coarse = samples_every(stride_px.max(1));
    let coarse_least = (on_model(&coarse) as f32 * ALIGNMENT_MIN_SHARE) as usize;
    let all = samples_every(1);
    let at_zero = on_model(&all);
    if at_zero < 100 {
        return None;
    }
    let least = (at_zero as f32 * ALIGNMENT_MIN_SHARE) as usize;
    let s = max_shift_px as i64;
    let mut coarse_best = (0i64, 0i64, cost(&coarse, coarse_least, 0, 0));
    for dy in (-s..=s).step_by(2) {
        for dx in (-s..=s).step_by(2) {
            let c = cost(&coarse, coarse_least, dx, dy);
            if c < coarse_best.2 {
                coarse_best = (dx, dy, c);
            }
        }
    }
    let fine = |dx: i64, dy: i64| cost(&all, least, dx, dy);
    let cost_at_zero = fine(0, 0);
    let (cx, cy) = (coarse_best.0, coarse_best.1);
    let mut best = (cx, cy, fine(cx, cy));
    for dy in (cy - 1).max(-s)..=(cy + 1).min(s) {
        for dx in (cx - 1).max(-s)..=(cx + 1).min(s) {
            let c = fine(dx, dy);
            if c < best.2 {
                best = (dx, dy, c);
            }
        }
    }
    let (bx, by, bc) = best;
    let refine = |before: f32, after: f32| -> f32 {
        let curvature = before + after - 2.0 * bc;
        if before.is_finite() && after.is_finite() && curvature > 0.0 {
            (0.5 * (before - after) / curvature).clamp(-0.5, 0.5)
        } else {
            0.0
        }
    };
    let ox = refine(fine(bx - 1, by), fine(bx + 1, by));
    let oy = refine(fine(bx, by - 1), fine(bx, by + 1));
    Some(DepthAlignment {
        shift_px: [bx as f32 + ox, by as f32 + oy],
        cost: bc.min(cost_at_zero),
        cost_at_zero,
        samples: at_zero,
        at_border: bx.abs() >= s || by.abs() >= s,
    })
}

/// The pose error u (px) a frame's change map allows for under [`ChangeConfig`]: the
/// registration's `pose_sigma_px` as given, or with `pose_sigma_from_depth` (and a registered
/// pose, u > 0) the length of [`depth_misalignment`]'s shift, searched up to
/// [`MAX_POSE_SIGMA_PX`] (the largest u where the best shift is at the border or cannot be
/// measured: the pose is at least that far off).
pub fn frame_pose_sigma_px(
    config: &ChangeConfig,
    model_depth_m: ImageView<'_, f32>,
    photo_depth_m: ImageView<'_, f32>,
) -> f32 {
    if !(config.pose_sigma_from_depth && config.pose_sigma_px > 0.0) {
        return config.pose_sigma_px;
    }
    match depth_misalignment(
        model_depth_m,
        photo_depth_m,
        MAX_POSE_SIGMA_PX as usize,
        ALIGNMENT_STRIDE_PX,
    ) {
        Some(alignment) if !alignment.at_border => alignment.length_px().min(MAX_POSE_SIGMA_PX),
        _ => MAX_POSE_SIGMA_PX,
    }
}

/// Sampling stride of [`frame_pose_sigma_px`]'s coarse search, px (a quarter of the pixels).
const ALIGNMENT_STRIDE_PX: usize = 2;

/// Median absolute deviation to the standard deviation of a normal distribution.
const MAD_TO_SIGMA: f32 = 1.4826;

/// The photo depth's spread against the model's in inverse depth, per metre: 1.4826 × the
/// median of `|1/p − 1/m|` over the pixels where both have a depth (about zero, so a bias
/// counts). A stereo depth's error is a disparity error, constant in inverse depth:
/// `1/p − 1/m = ε_disparity / (f·B)`, so this is σ_quad ([`ChangeConfig::quadratic_sigma_per_m`])
/// as the data show it, whatever makes the disparities wrong (matching noise, the neighbours'
/// pose errors) and without knowing f or B. Changed objects and the pose's misplaced depth
/// edges are a minority of the pixels and do not move the median. `None` when fewer than 100
/// pixels compare.
pub fn inverse_depth_spread_per_m(
    model_depth_m: ImageView<'_, f32>,
    photo_depth_m: ImageView<'_, f32>,
) -> Option<f32> {
    if model_depth_m.size() != photo_depth_m.size() {
        return None;
    }
    let valid = |d: f32| d.is_finite() && d > 0.0;
    let mut differences: Vec<f64> = model_depth_m
        .data()
        .iter()
        .zip(photo_depth_m.data())
        .filter(|(&m, &p)| valid(m) && valid(p))
        .map(|(&m, &p)| f64::from((1.0 / p - 1.0 / m).abs()))
        .collect();
    if differences.len() < 100 {
        return None;
    }
    Some(MAD_TO_SIGMA * quantile(&mut differences, 0.5) as f32)
}

/// The stereo term σ_quad a frame's change map uses under [`ChangeConfig`]: the configured one,
/// or with `stereo_sigma_from_depth` under a registered pose and a stereo depth map the larger
/// of it and [`inverse_depth_spread_per_m`].
pub fn frame_quadratic_sigma_per_m(
    config: &ChangeConfig,
    model_depth_m: ImageView<'_, f32>,
    photo_depth_m: ImageView<'_, f32>,
) -> f32 {
    let prior = config.quadratic_sigma_per_m;
    if !(config.stereo_sigma_from_depth && config.pose_sigma_px > 0.0 && prior > 0.0) {
        return prior;
    }
    inverse_depth_spread_per_m(model_depth_m, photo_depth_m).map_or(prior, |s| s.max(prior))
}

/// One changed region of one frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ChangeRegion {
    pub kind: ChangeKind,
    pub pixel_count: usize,
    /// Area of the changed surface as the camera sees it (sum of the pixels' footprints
    /// `d² / (fx·fy)`, with the hole pixels the region was grown across, see
    /// [`extract_regions`]), m².
    pub surface_area_m2: f64,
    /// Area of [`Self::footprint_m`], m².
    pub footprint_area_m2: f64,
    /// Vertical extent: the changed surface's top above the lowest surface at its pixels
    /// (the ground in front of which it stands or through which it is seen), metres.
    pub height_m: f64,
    /// Extent of the changed surface itself in z (2nd to 98th percentile), metres.
    pub vertical_extent_m: f64,
    /// Least width of [`Self::footprint_m`] (over its edge directions), metres.
    pub footprint_width_m: f64,
    /// Extent of [`Self::footprint_m`] across that least width, metres.
    pub footprint_length_m: f64,
    /// Median |photo depth − model depth| over the region, metres.
    pub depth_difference_m: f64,
    /// Mean of the changed surface's points (the photo's for `added`, the model's for
    /// `removed`), model frame with the georeferenced offset, metres.
    pub centroid_m: [f64; 3],
    /// Convex hull of the changed surface's points in x, y, counter-clockwise, metres.
    pub footprint_m: Vec<[f64; 2]>,
    /// 0..1: how far the differences exceed their thresholds (mean of min(1, |Δ|/τ − 1)).
    pub confidence: f64,
    /// Pixel bounding box: first column, first row, last column, last row.
    pub bbox_px: [usize; 4],
}

/// Pixel counts of one frame's classes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClassCounts {
    pub unknown: usize,
    pub unchanged: usize,
    pub added: usize,
    pub removed: usize,
}

/// One frame's result.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameChanges {
    pub counts: ClassCounts,
    pub regions: Vec<ChangeRegion>,
    /// The pose error u the threshold allowed for, px ([`frame_pose_sigma_px`]).
    pub pose_sigma_px: f32,
    /// The stereo term σ_quad the threshold used, per metre ([`frame_quadratic_sigma_per_m`]).
    pub quadratic_sigma_per_m: f32,
    /// `removed` regions dropped because the photo's depth lies below the model's ground
    /// ([`beyond_the_model`]); their pixels are `unknown`.
    #[serde(default)]
    pub beyond_the_model: Vec<BeyondTheModel>,
}

impl FrameChanges {
    /// The settings this frame's map was made with: `config` (what [`detect_changes`] was
    /// given) with the frame's own u and σ_quad.
    pub fn settings(&self, config: &ChangeConfig) -> ChangeConfig {
        ChangeConfig {
            pose_sigma_px: self.pose_sigma_px,
            quadratic_sigma_per_m: self.quadratic_sigma_per_m,
            ..*config
        }
    }
}

/// A `removed` region whose photo depth lies below the model's ground: a wrong depth (a stereo
/// match on the wrong repeat of a regular texture), not a demolition ([`beyond_the_model`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BeyondTheModel {
    pub pixel_count: usize,
    /// Mean of the model's surface points of the region (what it would have said was
    /// demolished), georeferenced, metres.
    pub centroid_m: [f64; 3],
    /// The model's ground there ([`model_ground_z_m`]), georeferenced z, metres.
    pub ground_z_m: f64,
    /// Share of the region's pixels whose photo depth lies beyond the ground by more than the
    /// change threshold.
    pub share_below: f64,
    /// Median over the region's pixels of how far the photo's point lies below the ground,
    /// vertically, metres (negative: above it).
    pub median_below_ground_m: f64,
    /// Median over the region's pixels of the photo's depth beyond the depth at which the ray
    /// crosses the ground, metres along the ray (the unit of the change threshold).
    pub median_beyond_ground_m: f64,
}

/// Reusable buffers of change detection.
#[derive(Default)]
pub struct ChangeWorkspace {
    rasterizer: Rasterizer,
    model: RenderBuffers,
    pose_sigma_m: Image<f32>,
    pose_scratch: Vec<f32>,
    scratch: Vec<u8>,
    labels: Vec<u32>,
    stack: Vec<usize>,
}

impl ChangeWorkspace {
    pub fn new() -> Self {
        Self::default()
    }

    /// The model rendering of the last [`detect_changes`] call (depth, face index).
    pub fn model_rendering(&self) -> &RenderBuffers {
        &self.model
    }
}

/// What the photo's depth rests on besides the depth values: where the photo's own data do not
/// contradict the model (a stereo depth's model test, [`stereo::StereoDepth::model_plausible`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct DepthEvidence<'a> {
    /// Pixels where the model's depth explains the photo as well as the photo's own depth
    /// (within the matching noise): never a change. `None` for a given (MVS) depth map.
    pub model_plausible: Option<ImageView<'a, bool>>,
}

/// Per pixel class of `photo_depth_m` against `model_depth_m` (both metres along the optical
/// axis, 0 = none), written into `classes` (resized), then each changed class opened by
/// `config.opening_radius_px` (pixels it drops become `unchanged`). `pose_sigma_m`: the pose
/// term of each pixel ([`pose_error_sigma_m`], same size); `None` for an exact pose. Pixels
/// `evidence` marks model-plausible are `unchanged` whatever their depth says.
pub fn classify_pixels(
    photo_depth_m: ImageView<'_, f32>,
    model_depth_m: ImageView<'_, f32>,
    pose_sigma_m: Option<ImageView<'_, f32>>,
    evidence: &DepthEvidence<'_>,
    config: &ChangeConfig,
    classes: &mut Image<ChangeClass>,
    scratch: &mut Vec<u8>,
) -> Result<(), ChangeError> {
    let (w, h) = model_depth_m.size();
    if photo_depth_m.size() != (w, h) {
        return Err(ChangeError::SizeMismatch {
            photo_width_px: photo_depth_m.width_px(),
            photo_height_px: photo_depth_m.height_px(),
            model_width_px: w,
            model_height_px: h,
        });
    }
    if let Some(pose_sigma_m) = pose_sigma_m {
        if pose_sigma_m.size() != (w, h) {
            return Err(ChangeError::SizeMismatch {
                photo_width_px: pose_sigma_m.width_px(),
                photo_height_px: pose_sigma_m.height_px(),
                model_width_px: w,
                model_height_px: h,
            });
        }
    }
    if let Some(plausible) = evidence.model_plausible {
        if plausible.size() != (w, h) {
            return Err(ChangeError::SizeMismatch {
                photo_width_px: plausible.width_px(),
                photo_height_px: plausible.height_px(),
                model_width_px: w,
                model_height_px: h,
            });
        }
    }
    let pose_sigma = |index: usize| pose_sigma_m.map_or(0.0, |s| s.data()[index]);
    classes.reset(w, h, ChangeClass::Unknown);
    for (index, ((class, &dp), &dm)) in classes
        .data_mut()
        .iter_mut()
        .zip(photo_depth_m.data())
        .zip(model_depth_m.data())
        .enumerate()
    {
        *class = pixel_class(dp, dm, pose_sigma(index), config);
    }
    if let Some(plausible) = evidence.model_plausible {
        for (class, &plausible) in classes.data_mut().iter_mut().zip(plausible.data()) {
            if plausible && matches!(*class, ChangeClass::Added | ChangeClass::Removed) {
                *class = ChangeClass::Unchanged;
            }
        }
    }
    if config.edge_tolerance_px > 0 {
        explain_by_nearby_model(classes, photo_depth_m, model_depth_m, &pose_sigma, config);
    }
    if config.opening_radius_px > 0 {
        for kind in [ChangeClass::Added, ChangeClass::Removed] {
            open_class(classes, kind, config.opening_radius_px, scratch);
        }
    }
    Ok(())
}

fn pixel_class(
    photo_m: f32,
    model_m: f32,
    pose_sigma_m: f32,
    config: &ChangeConfig,
) -> ChangeClass {
    if !(photo_m.is_finite() && photo_m > 0.0 && model_m.is_finite() && model_m > 0.0) {
        return ChangeClass::Unknown;
    }
    let difference = photo_m - model_m;
    let threshold = config.threshold_with_pose_m(photo_m.min(model_m), pose_sigma_m);
    if difference < -threshold {
        ChangeClass::Added
    } else if difference > threshold {
        ChangeClass::Removed
    } else {
        ChangeClass::Unchanged
    }
}

/// The model's depth edges: pixels whose model depth and an 8-neighbour's (both surfaces) differ
/// by more than the change threshold at the nearer of the two under an exact pose
/// ([`ChangeConfig::threshold_m`]): a step the depth comparison could mistake for a change when
/// the photo's depth spreads over it. A smooth surface's depth changes far less from one pixel
/// to the next (a plane seen 5° from grazing: 3 % of the depth per pixel at f = 360 px).
pub fn model_depth_edges(model_depth_m: ImageView<'_, f32>, config: &ChangeConfig) -> Vec<bool> {
    let (w, h) = model_depth_m.size();
    let model = model_depth_m.data();
    let surface = |d: f32| d.is_finite() && d > 0.0;
    let mut edges = vec![false; w * h];
    for row in 0..h {
        for col in 0..w {
            let a = model[row * w + col];
            if !surface(a) {
                continue;
            }
            // Each unordered pair once: right, and the three below.
            for (dr, dc) in [(0i64, 1i64), (1, -1), (1, 0), (1, 1)] {
                let (rr, cc) = (row as i64 + dr, col as i64 + dc);
                if rr >= h as i64 || cc < 0 || cc >= w as i64 {
                    continue;
                }
                let other = rr as usize * w + cc as usize;
                let b = model[other];
                if surface(b) && (a - b).abs() > config.threshold_m(a.min(b)) {
                    edges[row * w + col] = true;
                    edges[other] = true;
                }
            }
        }
    }
    edges
}

/// `mask` dilated by a square of side 2r+1 (separable: rows, then columns).
fn dilate(mask: &[bool], w: usize, h: usize, r: usize) -> Vec<bool> {
    let mut rows = vec![false; w * h];
    for row in 0..h {
        for col in 0..w {
            let (from, to) = (col.saturating_sub(r), (col + r + 1).min(w));
            rows[row * w + col] = mask[row * w + from..row * w + to].iter().any(|&m| m);
        }
    }
    let mut out = vec![false; w * h];
    for row in 0..h {
        for col in 0..w {
            out[row * w + col] =
                (row.saturating_sub(r)..(row + r + 1).min(h)).any(|rr| rows[rr * w + col]);
        }
    }
    out
}

/// `added` pixels within `config.edge_tolerance_px` of a depth edge of the model
/// ([`model_depth_edges`]) whose photo depth agrees (within its threshold) with the model's
/// depth that close become `unchanged` (see [`ChangeConfig::edge_tolerance_px`]).
fn explain_by_nearby_model(
    classes: &mut Image<ChangeClass>,
    photo_depth_m: ImageView<'_, f32>,
    model_depth_m: ImageView<'_, f32>,
    pose_sigma_m: &dyn Fn(usize) -> f32,
    config: &ChangeConfig,
) {
    let (w, h) = classes.size();
    let r = config.edge_tolerance_px;
    let near_edge = dilate(&model_depth_edges(model_depth_m, config), w, h, r);
    let (photo, model) = (photo_depth_m.data(), model_depth_m.data());
    for row in 0..h {
        for col in 0..w {
            let index = row * w + col;
            if classes.data()[index] != ChangeClass::Added || !near_edge[index] {
                continue;
            }
            let dp = photo[index];
            let pose_sigma = pose_sigma_m(index);
            let explained = (row.saturating_sub(r)..(row + r + 1).min(h)).any(|rr| {
                (col.saturating_sub(r)..(col + r + 1).min(w)).any(|cc| {
                    let dm = model[rr * w + cc];
                    dm.is_finite()
                        && dm > 0.0
                        && (dp - dm).abs() <= config.threshold_with_pose_m(dp.min(dm), pose_sigma)
                })
            });
            if explained {
                classes.data_mut()[index] = ChangeClass::Unchanged;
            }
        }
    }
}

/// Opening (erosion then dilation, square of side 2r+1) of one class; pixels of the class that
/// do not survive become `unchanged`. The erosion asks the square's pixels that have evidence:
/// an `unknown` pixel (no photo depth) neither keeps nor removes a changed pixel beside it, so a
/// sparse depth map's changed spots (MVS measures only textured spots of a plain surface, a few
/// pixels each between holes) survive as they would on a dense map; what removes a pixel is an
/// `unchanged` pixel, the other changed class or the image border.
fn open_class(
    classes: &mut Image<ChangeClass>,
    class: ChangeClass,
    radius: usize,
    scratch: &mut Vec<u8>,
) {
    let (w, h) = classes.size();
    let r = radius as i64;
    // Erosion: all of the square in the class or without evidence (outside the image counts
    // as not in the class).
    let data = classes.data();
    scratch.clear();
    scratch.resize(w * h, 0);
    for row in 0..h {
        for col in 0..w {
            if data[row * w + col] != class {
                continue;
            }
            let inside = (-r..=r).all(|dr| {
                (-r..=r).all(|dc| {
                    let (rr, cc) = (row as i64 + dr, col as i64 + dc);
                    rr >= 0
                        && cc >= 0
                        && rr < h as i64
                        && cc < w as i64
                        && matches!(
                            data[rr as usize * w + cc as usize],
                            c if c == class || c == ChangeClass::Unknown
                        )
                })
            });
            if inside {
                scratch[row * w + col] = 1;
            }
        }
    }
    // Dilation of the eroded set, kept within the class (a pixel's own class is read before it
    // changes).
    let data = classes.data_mut();
    for row in 0..h {
        for col in 0..w {
            let index = row * w + col;
            if data[index] != class {
                continue;
            }
            let kept = (-r..=r).any(|dr| {
                (-r..=r).any(|dc| {
                    let (rr, cc) = (row as i64 + dr, col as i64 + dc);
                    rr >= 0
                        && cc >= 0
                        && rr < h as i64
                        && cc < w as i64
                        && scratch[rr as usize * w + cc as usize] == 1
                })
            });
            if !kept {
                data[index] = ChangeClass::Unchanged;
            }
        }
    }
}

/// Neighbouring pixels of one region differ in depth by at most this fraction of the depth…
const CONTINUITY_RELATIVE: f32 = 0.04;
/// …plus this, metres.
const CONTINUITY_M: f32 = 0.3;

/// Whether two depths of one surface a pixel apart are continuous ([`CONTINUITY_RELATIVE`],
/// [`CONTINUITY_M`]).
fn continuous_m(a: f32, b: f32) -> bool {
    (a - b).abs() <= CONTINUITY_RELATIVE * a.min(b) + CONTINUITY_M
}

/// Widest run of `unknown` pixels (no depth: no evidence either way) a region grows across,
/// pixels of the depth map, along a row, a column or a diagonal: about the depth matcher's
/// window, the width of the holes it leaves between textured spots of a plain wall (MVS
/// 7 px; our plane-sweep stereo's 5-px window at half resolution, 10 px of the full-resolution
/// map). A sparse depth map splits a new wall into fragments across such bands, each under the
/// least area and extents, and the object was dropped whole (issue #13). `unchanged` pixels
/// (the photo's depth agrees with the model) and the other changed class are evidence and stop
/// the growth; the pixels on both sides must agree in depth within
/// [`BRIDGE_CONTINUITY_RELATIVE`].
pub const HOLE_BRIDGE_PX: usize = 10;

/// The two pixels a band of holes separates join when their depths differ by at most this
/// fraction of the depth plus [`CONTINUITY_M`]: half a neighbour's [`CONTINUITY_RELATIVE`]. A
/// neighbour's 4 % allows a steep surface one pixel on; across a band only its two ends are
/// measured, and the same 4 % let a far grazing view (block scene 1, view_041, 75 m) join a
/// rooftop box's front and top 2.3–3.3 m apart in depth into one region whose footprint
/// stretched 9 m along the ray; at 2 % (±1.8 m at 75 m, ±0.5 m at 10 m) the fragments of one
/// wall still join (docs/measurements.md, issue #13).
const BRIDGE_CONTINUITY_RELATIVE: f32 = 0.02;

/// The longest band of `unknown` pixels a `removed` region grows across, pixels, whatever its
/// length in metres: a bound on the work of one pixel's eight searches.
const MAX_SURFACE_BRIDGE_PX: usize = 64;

/// How far a region may grow across a band of `unknown` pixels from a pixel whose changed
/// surface lies `depth_m` away. An `added` region's surface is the photo's, unknown in the
/// holes: at most [`HOLE_BRIDGE_PX`], its two ends in depth within
/// [`BRIDGE_CONTINUITY_RELATIVE`]. A `removed` region's surface is the model's, which is
/// rendered in the holes too: the band may be as long as `min_extent_m` on that surface (two
/// pieces of evidence of one missing surface closer than the least extent of an object cannot
/// be told apart as two objects; a plain road seen through a demolished building gives only its
/// painted edges, 1–2 px lines 15–25 px apart at 20 m), at least [`HOLE_BRIDGE_PX`] and at most
/// [`MAX_SURFACE_BRIDGE_PX`], when every pixel of the band has a model depth continuous with the
/// one before it (one surface, no depth edge crossed).
#[derive(Clone, Copy)]
struct HoleBridge {
    /// The region's class: `removed`'s surface (the model's) is known in the holes.
    class: ChangeClass,
    /// `min_extent_m` × the focal length, metre·px: the band's limit in px at a depth.
    extent_px_m: f32,
}

impl HoleBridge {
    fn surface_in_holes(&self) -> bool {
        self.class == ChangeClass::Removed
    }

    fn max_band_px(&self, depth_m: f32) -> usize {
        if !self.surface_in_holes() || depth_m.is_nan() || depth_m <= 0.0 {
            return HOLE_BRIDGE_PX;
        }
        ((self.extent_px_m / depth_m) as usize).clamp(HOLE_BRIDGE_PX, MAX_SURFACE_BRIDGE_PX)
    }
}

/// Where a region grows from `index` across a band of `unknown` pixels in `classes`: in each of
/// the 8 directions, the first pixel past 1..=[`HoleBridge::max_band_px`] `unknown` pixels, if
/// it is of the region's class (`bridge.class`) and continuous in depth with `index`
/// (`changed_depth`; for a surface known in the holes, each pixel with the one before it);
/// `visit(target, gap)` with the pixels of the band (`gap`, in order from `index`).
fn across_holes(
    classes: &[ChangeClass],
    (w, h): (usize, usize),
    index: usize,
    changed_depth: &dyn Fn(usize) -> f32,
    bridge: HoleBridge,
    gap: &mut Vec<usize>,
    mut visit: impl FnMut(usize, &[usize]),
) {
    let (row, col) = ((index / w) as i64, (index % w) as i64);
    let (class, surface_in_holes) = (bridge.class, bridge.surface_in_holes());
    let origin = changed_depth(index);
    let max_band_px = bridge.max_band_px(origin);
    let surface = |d: f32| d.is_finite() && d > 0.0;
    let continuous_step = |a: f32, b: f32| surface(a) && surface(b) && continuous_m(a, b);
    for dr in -1..=1i64 {
        for dc in -1..=1i64 {
            if dr == 0 && dc == 0 {
                continue;
            }
            gap.clear();
            let mut previous = origin;
            for step in 1..=(max_band_px as i64 + 1) {
                let (rr, cc) = (row + step * dr, col + step * dc);
                if rr < 0 || cc < 0 || rr >= h as i64 || cc >= w as i64 {
                    break;
                }
                let target = rr as usize * w + cc as usize;
                let depth = changed_depth(target);
                if classes[target] == ChangeClass::Unknown {
                    // A known surface must continue through every hole of the band.
                    if surface_in_holes && !continuous_step(previous, depth) {
                        break;
                    }
                    previous = depth;
                    gap.push(target);
                    continue;
                }
                if !gap.is_empty() && classes[target] == class {
                    let joined = if surface_in_holes {
                        continuous_step(previous, depth)
                    } else {
                        (origin - depth).abs()
                            <= BRIDGE_CONTINUITY_RELATIVE * origin.min(depth) + CONTINUITY_M
                    };
                    if joined {
                        visit(target, gap);
                    }
                }
                break;
            }
        }
    }
}

/// The frame's changed regions: 8-connected components (continuous in depth) of each changed
/// class, also connected across bands of at most [`HOLE_BRIDGE_PX`] `unknown` pixels (holes of a
/// sparse depth map), with at least
/// `config.min_pixels` pixels and `config.min_area_m2` of surface, measured in the model's
/// frame through `cam_from_world` (world = the model's georeferenced frame) over the region's
/// pixels and the hole pixels it was grown across (each at the mean depth of the two pixels
/// its band joins: the holes are the region's surface the matcher could not measure). Pixels of regions
/// that are too small become `unchanged` in `classes`. `pose_sigma_m` as in [`classify_pixels`]
/// (the regions' confidence). With `config.ground_search_radius_m` > 0, a `removed` region whose photo depth lies below the model's ground ([`beyond_the_model`])
/// is dropped, its pixels become `unknown`, and it is listed in `beyond`.
#[allow(clippy::too_many_arguments)]
pub fn extract_regions(
    classes: &mut Image<ChangeClass>,
    photo_depth_m: ImageView<'_, f32>,
    model_depth_m: ImageView<'_, f32>,
    pose_sigma_m: Option<ImageView<'_, f32>>,
    intrinsics: &PinholeIntrinsics,
    cam_from_world: &Rigid3,
    model: &Mesh,
    config: &ChangeConfig,
    labels: &mut Vec<u32>,
    stack: &mut Vec<usize>,
    beyond: &mut Vec<BeyondTheModel>,
) -> Vec<ChangeRegion> {
    let (w, h) = classes.size();
    labels.clear();
    labels.resize(w * h, u32::MAX);
    let world_from_cam = cam_from_world.inverse();
    let pixels = FramePixels {
        width: w,
        photo_m: photo_depth_m.data(),
        model_m: model_depth_m.data(),
        pose_sigma_m: pose_sigma_m.map(|s| s.data()),
        intrinsics,
        world_from_cam: &world_from_cam,
    };
    let pixel_area = 1.0 / (intrinsics.fx_px * intrinsics.fy_px).abs().max(1e-12);
    let mut regions = Vec::new();
    let mut members: Vec<usize> = Vec::new();
    let mut gap: Vec<usize> = Vec::with_capacity(MAX_SURFACE_BRIDGE_PX);
    let mut next_label = 0u32;
    for seed in 0..w * h {
        let class = classes.data()[seed];
        let kind = match class {
            ChangeClass::Added => ChangeKind::Added,
            ChangeClass::Removed => ChangeKind::Removed,
            _ => continue,
        };
        if labels[seed] != u32::MAX {
            continue;
        }
        // Flood fill (8-connected, and continuous in depth: two objects that touch in the
        // image but stand metres apart are two regions).
        let changed_depth = |index: usize| match kind {
            ChangeKind::Added => photo_depth_m.data()[index],
            ChangeKind::Removed => model_depth_m.data()[index],
        };
        let bridge = HoleBridge {
            class,
            extent_px_m: (config.min_extent_m * intrinsics.fx_px.abs()) as f32,
        };
        members.clear();
        stack.clear();
        stack.push(seed);
        labels[seed] = next_label;
        let mut bridged_area_m2 = 0.0;
        while let Some(index) = stack.pop() {
            members.push(index);
            across_holes(
                classes.data(),
                (w, h),
                index,
                &changed_depth,
                bridge,
                &mut gap,
                |target, band| {
                    let depth_m = 0.5 * f64::from(changed_depth(index) + changed_depth(target));
                    for &hole in band {
                        // A hole counts once for the region (its label: no seed, not a member).
                        if labels[hole] != next_label {
                            labels[hole] = next_label;
                            bridged_area_m2 += depth_m * depth_m * pixel_area;
                        }
                    }
                    if labels[target] == u32::MAX {
                        labels[target] = next_label;
                        stack.push(target);
                    }
                },
            );
            let (row, col) = ((index / w) as i64, (index % w) as i64);
            for dr in -1..=1i64 {
                for dc in -1..=1i64 {
                    let (rr, cc) = (row + dr, col + dc);
                    if rr < 0 || cc < 0 || rr >= h as i64 || cc >= w as i64 {
                        continue;
                    }
                    let neighbour = rr as usize * w + cc as usize;
                    if labels[neighbour] == u32::MAX
                        && classes.data()[neighbour] == class
                        && continuous_m(changed_depth(index), changed_depth(neighbour))
                    {
                        labels[neighbour] = next_label;
                        stack.push(neighbour);
                    }
                }
            }
        }
        next_label += 1;
        let mut region = measure_region(kind, &members, &pixels, pixel_area, config);
        region.surface_area_m2 += bridged_area_m2;
        let extents = [
            region.vertical_extent_m,
            region.footprint_width_m,
            region.footprint_length_m,
        ];
        let large_extents = extents
            .iter()
            .filter(|e| **e >= config.min_extent_m)
            .count();
        if members.len() < config.min_pixels
            || region.surface_area_m2 < config.min_area_m2
            || large_extents < 2
        {
            for &index in &members {
                classes.data_mut()[index] = ChangeClass::Unchanged;
            }
            continue;
        }
        let ground_z_m = (kind == ChangeKind::Removed && config.ground_search_radius_m > 0.0)
            .then(|| model_ground_z_m(model, &region.footprint_m, config.ground_search_radius_m))
            .flatten();
        if let Some(dropped) = ground_z_m
            .and_then(|ground_z_m| beyond_the_model(&members, &pixels, ground_z_m, config))
        {
            for &index in &members {
                classes.data_mut()[index] = ChangeClass::Unknown;
            }
            beyond.push(dropped);
            continue;
        }
        regions.push(region);
    }
    regions
}

/// The model's ground near a footprint: the lowest model surface whose faces come within
/// `radius_m` horizontally of `footprint_m`'s bounding box (georeferenced x, y, metres), its z
/// (georeferenced, metres). Faces are taken whole (the lowest corner of a face reaching into the
/// square), so a large sloping face can only lower the ground: the rule it feeds
/// ([`beyond_the_model`]) only gets more reluctant. The mesh's face grid skips the cells outside
/// the square or above the lowest surface found so far. `None` when no face comes that close or
/// the footprint is empty.
pub fn model_ground_z_m(mesh: &Mesh, footprint_m: &[[f64; 2]], radius_m: f64) -> Option<f64> {
    if footprint_m.is_empty() || !radius_m.is_finite() {
        return None;
    }
    let origin = mesh.origin_m();
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for p in footprint_m {
        for axis in 0..2 {
            lo[axis] = lo[axis].min(p[axis]);
            hi[axis] = hi[axis].max(p[axis]);
        }
    }
    // The square in local coordinates (f32, as the mesh stores them).
    let lo = [
        (lo[0] - radius_m - origin.x) as f32,
        (lo[1] - radius_m - origin.y) as f32,
    ];
    let hi = [
        (hi[0] + radius_m - origin.x) as f32,
        (hi[1] + radius_m - origin.y) as f32,
    ];
    let overlaps = |min: [f32; 2], max: [f32; 2]| {
        min[0] <= hi[0] && max[0] >= lo[0] && min[1] <= hi[1] && max[1] >= lo[1]
    };
    let positions = mesh.positions_local_m();
    let grid = mesh.grid();
    let mut lowest = f32::INFINITY;
    for cell in grid.cells() {
        let (cmin, cmax) = (cell.min_local_m, cell.max_local_m);
        if cmin.z >= lowest || !overlaps([cmin.x, cmin.y], [cmax.x, cmax.y]) {
            continue;
        }
        let vertices = grid.cell_vertices(cell);
        for corners in grid.cell_corners(cell) {
            let mut min = [f32::INFINITY; 3];
            let mut max = [f32::NEG_INFINITY; 2];
            for &corner in corners {
                let Some(p) = vertices
                    .get(usize::from(corner))
                    .and_then(|&v| positions.get(v as usize))
                else {
                    continue;
                };
                min = [min[0].min(p.x), min[1].min(p.y), min[2].min(p.z)];
                max = [max[0].max(p.x), max[1].max(p.y)];
            }
            if min[2] < lowest && overlaps([min[0], min[1]], max) {
                lowest = min[2];
            }
        }
    }
    lowest.is_finite().then(|| origin.z + f64::from(lowest))
}

/// Whether a `removed` region is beyond the model: most of its pixels (`members`, indices into
/// the frame's depth maps in `pixels`) have a photo depth more than the pixel's change
/// threshold beyond the depth at which their ray crosses `ground_z_m` (the model's ground,
/// [`model_ground_z_m`]). A demolished building leaves the ground standing, so the photo of a
/// true demolition lands on the ground (or on what stood behind); the photo cannot see *below*
/// the ground, so a depth there is the depth's own error (a stereo match on the wrong repeat of
/// a roof's grid texture), and the region says nothing about the model. The margin is the
/// change threshold in the unit it is defined in, depth along the ray: the same test that made
/// the pixel `removed` (its depth beyond the model's surface), with the ground in place of that
/// surface. A ray that does not descend never crosses the ground. `Some` with the figures when
/// the region is beyond the model.
fn beyond_the_model(
    members: &[usize],
    pixels: &FramePixels<'_>,
    ground_z_m: f64,
    config: &ChangeConfig,
) -> Option<BeyondTheModel> {
    if members.is_empty() || pixels.width == 0 {
        return None;
    }
    let mut below = 0usize;
    let mut heights_below = Vec::with_capacity(members.len());
    let mut depths_beyond = Vec::with_capacity(members.len());
    let mut centroid = Vector3::zeros();
    for &index in members {
        let (Some(&dp), Some(&dm)) = (pixels.photo_m.get(index), pixels.model_m.get(index)) else {
            continue;
        };
        let n = pixels.normalized(index);
        centroid += pixels.point_at(n, dm);
        if !(dp.is_finite() && dp > 0.0) {
            continue;
        }
        let photo_z_m = pixels.point_at(n, dp).z;
        heights_below.push(ground_z_m - photo_z_m);
        // How far the ray descends per metre of depth.
        let drop_per_m = -(pixels.world_from_cam.rotation * Vector3::new(n.x, n.y, 1.0)).z;
        if drop_per_m <= 0.0 {
            continue;
        }
        let beyond_ground_m = (ground_z_m - photo_z_m) / drop_per_m;
        depths_beyond.push(beyond_ground_m);
        if beyond_ground_m > f64::from(pixels.threshold_m(index, config)) {
            below += 1;
        }
    }
    if 2 * below <= members.len() {
        return None;
    }
    let centroid = centroid / members.len() as f64;
    Some(BeyondTheModel {
        pixel_count: members.len(),
        centroid_m: [centroid.x, centroid.y, centroid.z],
        ground_z_m,
        share_below: below as f64 / members.len() as f64,
        median_below_ground_m: quantile(&mut heights_below, 0.5),
        median_beyond_ground_m: quantile(&mut depths_beyond, 0.5),
    })
}

/// Quantile (0..1) of a slice, which it reorders.
fn quantile(values: &mut [f64], q: f64) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let k = ((values.len() - 1) as f64 * q).round() as usize;
    let (_, v, _) = values.select_nth_unstable_by(k, f64::total_cmp);
    *v
}

/// The points without stragglers (mixed depths at a region's edge land far behind or in
/// front of it): those farther from the median than 1.5 × the 90th-percentile distance + 0.5 m.
fn trim_outliers(points: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    if points.len() < 10 {
        return points;
    }
    let mut xs: Vec<f64> = points.iter().map(|p| p[0]).collect();
    let mut ys: Vec<f64> = points.iter().map(|p| p[1]).collect();
    let centre = [quantile(&mut xs, 0.5), quantile(&mut ys, 0.5)];
    let distance = |p: &[f64; 2]| ((p[0] - centre[0]).powi(2) + (p[1] - centre[1]).powi(2)).sqrt();
    let mut distances: Vec<f64> = points.iter().map(distance).collect();
    let limit = 1.5 * quantile(&mut distances, 0.9) + 0.5;
    points
        .into_iter()
        .filter(|p| distance(p) <= limit)
        .collect()
}

/// A frame's per-pixel inputs as the region measurements read them: the `width`-wide photo and
/// model depth maps (camera z, metres), the pose term, and how a pixel lifts to the model's
/// (georeferenced) world frame.
struct FramePixels<'a> {
    width: usize,
    photo_m: &'a [f32],
    model_m: &'a [f32],
    pose_sigma_m: Option<&'a [f32]>,
    intrinsics: &'a PinholeIntrinsics,
    world_from_cam: &'a Rigid3,
}

impl FramePixels<'_> {
    /// Pixel `index`'s normalized image coordinates.
    fn normalized(&self, index: usize) -> Vector2<f64> {
        self.intrinsics
            .pixel_to_normalized(pixel_center(index % self.width, index / self.width))
    }

    /// The world point at `depth_m` (camera z) on the ray of normalized coordinates `n`.
    fn point_at(&self, n: Vector2<f64>, depth_m: f32) -> Vector3<f64> {
        let d = f64::from(depth_m);
        self.world_from_cam
            .transform_point(&Vector3::new(n.x * d, n.y * d, d))
    }

    /// Pixel `index`'s change threshold (metres, the shallower of its two depths, its pose term).
    fn threshold_m(&self, index: usize, config: &ChangeConfig) -> f32 {
        let (dp, dm) = (self.photo_m[index], self.model_m[index]);
        let pose_sigma = self.pose_sigma_m.and_then(|s| s.get(index)).copied();
        config.threshold_with_pose_m(dp.min(dm), pose_sigma.unwrap_or(0.0))
    }
}

fn measure_region(
    kind: ChangeKind,
    members: &[usize],
    pixels: &FramePixels<'_>,
    pixel_area: f64,
    config: &ChangeConfig,
) -> ChangeRegion {
    let mut surface_area = 0.0;
    let mut centroid = Vector3::zeros();
    let mut changed_z = Vec::with_capacity(members.len());
    let mut all_z = Vec::with_capacity(2 * members.len());
    let mut xy = Vec::with_capacity(members.len());
    let mut differences = Vec::with_capacity(members.len());
    let mut confidence = 0.0;
    let mut bbox = [usize::MAX, usize::MAX, 0, 0];
    let width = pixels.width;
    for &index in members {
        let (dp, dm) = (pixels.photo_m[index], pixels.model_m[index]);
        let (changed, other) = match kind {
            ChangeKind::Added => (dp, dm),
            ChangeKind::Removed => (dm, dp),
        };
        let n = pixels.normalized(index);
        let p = pixels.point_at(n, changed);
        let q = pixels.point_at(n, other);
        surface_area += f64::from(changed) * f64::from(changed) * pixel_area;
        centroid += p;
        changed_z.push(p.z);
        all_z.push(p.z);
        all_z.push(q.z);
        xy.push([p.x, p.y]);
        let difference = f64::from((dp - dm).abs());
        differences.push(difference);
        let threshold = f64::from(pixels.threshold_m(index, config));
        confidence += (difference / threshold - 1.0).clamp(0.0, 1.0);
        let (col, row) = (index % width, index / width);
        bbox = [
            bbox[0].min(col),
            bbox[1].min(row),
            bbox[2].max(col),
            bbox[3].max(row),
        ];
    }
    let n = members.len().max(1) as f64;
    let footprint = polygon::convex_hull(&trim_outliers(xy));
    let top = quantile(&mut changed_z, 0.98);
    let bottom = quantile(&mut changed_z, 0.02);
    let base = quantile(&mut all_z, 0.02);
    let (footprint_width_m, footprint_length_m) = polygon::width_and_length(&footprint);
    let centroid = centroid / n;
    ChangeRegion {
        kind,
        pixel_count: members.len(),
        surface_area_m2: surface_area,
        footprint_area_m2: polygon::polygon_area(&footprint),
        height_m: (top - base).max(0.0),
        vertical_extent_m: (top - bottom).max(0.0),
        footprint_width_m,
        footprint_length_m,
        depth_difference_m: quantile(&mut differences, 0.5),
        centroid_m: [centroid.x, centroid.y, centroid.z],
        footprint_m: footprint,
        confidence: confidence / n,
        bbox_px: bbox,
    }
}

/// One frame's changes: the model rendered under `cam_from_world` (world = the mesh's
/// georeferenced frame) through `intrinsics` at the photo depth's size, compared with
/// `photo_depth_m` (and what it rests on, `evidence`); per-pixel classes in `classes`, regions
/// in the result.
#[allow(clippy::too_many_arguments)]
pub fn detect_changes(
    mesh: &Mesh,
    intrinsics: &PinholeIntrinsics,
    cam_from_world: &Rigid3,
    photo_depth_m: ImageView<'_, f32>,
    evidence: &DepthEvidence<'_>,
    config: &ChangeConfig,
    workspace: &mut ChangeWorkspace,
    classes: &mut Image<ChangeClass>,
) -> Result<FrameChanges, ChangeError> {
    config.validate()?;
    let (w, h) = photo_depth_m.size();
    workspace.model.resize(w, h);
    workspace.rasterizer.render(
        mesh,
        intrinsics,
        cam_from_world,
        &RenderOptions::default(),
        &mut workspace.model,
    );
    let model_depth = workspace.model.depth_m().view();
    let pose_sigma_px = frame_pose_sigma_px(config, model_depth, photo_depth_m);
    let quadratic_sigma_per_m = frame_quadratic_sigma_per_m(config, model_depth, photo_depth_m);
    let config = &ChangeConfig {
        pose_sigma_px,
        quadratic_sigma_per_m,
        ..*config
    };
    pose_error_sigma_m(
        model_depth,
        pose_sigma_px,
        &mut workspace.pose_sigma_m,
        &mut workspace.pose_scratch,
    );
    let pose_sigma = (pose_sigma_px > 0.0).then(|| workspace.pose_sigma_m.view());
    classify_pixels(
        photo_depth_m,
        model_depth,
        pose_sigma,
        evidence,
        config,
        classes,
        &mut workspace.scratch,
    )?;
    let mut beyond = Vec::new();
    let regions = extract_regions(
        classes,
        photo_depth_m,
        model_depth,
        pose_sigma,
        intrinsics,
        cam_from_world,
        mesh,
        config,
        &mut workspace.labels,
        &mut workspace.stack,
        &mut beyond,
    );
    Ok(FrameChanges {
        counts: class_counts(classes.view()),
        regions,
        pose_sigma_px,
        quadratic_sigma_per_m,
        beyond_the_model: beyond,
    })
}

/// Pixel counts of each class.
pub fn class_counts(classes: ImageView<'_, ChangeClass>) -> ClassCounts {
    let mut counts = ClassCounts::default();
    for class in classes.data() {
        match class {
            ChangeClass::Unknown => counts.unknown += 1,
            ChangeClass::Unchanged => counts.unchanged += 1,
            ChangeClass::Added => counts.added += 1,
            ChangeClass::Removed => counts.removed += 1,
        }
    }
    counts
}

/// The classes as mask grey levels ([`ChangeClass::mask_value`]), written into `out`.
pub fn classes_to_mask(classes: ImageView<'_, ChangeClass>, out: &mut Image<u8>) {
    let (w, h) = classes.size();
    out.reset(w, h, 0);
    for (value, class) in out.data_mut().iter_mut().zip(classes.data()) {
        *value = class.mask_value();
    }
}

/// The classes of a mask image's grey levels.
pub fn mask_to_classes(mask: ImageView<'_, u8>) -> Image<ChangeClass> {
    mask.to_image().map(|v| ChangeClass::from_mask_value(*v))
}

impl From<ChangeClass> for u8 {
    fn from(class: ChangeClass) -> u8 {
        class as u8
    }
}

impl From<u8> for ChangeClass {
    fn from(value: u8) -> Self {
        ChangeClass::from_u8(value)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::core::camera::PinholeIntrinsics;

    /// A camera 20 m above the ground looking straight down (x right, y down in the image ↔
    /// world x, −y), 200×200 px, f = 200 px: a pixel is 0.1 m on the ground.
    fn nadir() -> (PinholeIntrinsics, Rigid3) {
        let intrinsics = PinholeIntrinsics::centered(200.0, 200, 200);
        let pose = Rigid3::look_at(
            &Vector3::new(0.0, 0.0, 20.0),
            &Vector3::new(0.0, 0.0, 0.0),
            &Vector3::y(),
        )
        .expect("a valid look-at");
        (intrinsics, pose)
    }

    /// Quads as two triangles each.
    pub(crate) fn mesh_of(quads: &[[[f64; 3]; 4]]) -> Mesh {
        let mut positions = Vec::new();
        let mut faces = Vec::new();
        for quad in quads {
            let base = positions.len() as u32;
            positions.extend(quad.iter().map(|p| Vector3::new(p[0], p[1], p[2])));
            faces.push([base, base + 1, base + 2]);
            faces.push([base, base + 2, base + 3]);
        }
        Mesh::from_world(&positions, faces, None).expect("a valid mesh")
    }

    fn ground(origin: [f64; 2]) -> [[f64; 3]; 4] {
        let [x, y] = origin;
        [
            [x - 50.0, y - 50.0, 0.0],
            [x + 50.0, y - 50.0, 0.0],
            [x + 50.0, y + 50.0, 0.0],
            [x - 50.0, y + 50.0, 0.0],
        ]
    }

    /// The top of a box: a 4 × 3 m roof at `height`, centred on (cx, cy).
    fn roof(cx: f64, cy: f64, height: f64) -> [[f64; 3]; 4] {
        [
            [cx - 2.0, cy - 1.5, height],
            [cx + 2.0, cy - 1.5, height],
            [cx + 2.0, cy + 1.5, height],
            [cx - 2.0, cy + 1.5, height],
        ]
    }

    fn depth_of(mesh: &Mesh, intrinsics: &PinholeIntrinsics, pose: &Rigid3) -> Image<f32> {
        let mut buffers = RenderBuffers::new(200, 200);
        Rasterizer::new().render(
            mesh,
            intrinsics,
            pose,
            &RenderOptions::default(),
            &mut buffers,
        );
        buffers.depth_m().clone()
    }

    /// [`detect_changes`] on a given depth map (no stereo evidence) with a fresh workspace: the
    /// frame's changes and its per-pixel classes.
    fn detect_on(
        model: &Mesh,
        intrinsics: &PinholeIntrinsics,
        pose: &Rigid3,
        photo_depth: &Image<f32>,
        config: &ChangeConfig,
    ) -> (FrameChanges, Image<ChangeClass>) {
        let mut classes = Image::default();
        let changes = detect_changes(
            model,
            intrinsics,
            pose,
            photo_depth.view(),
            &DepthEvidence::default(),
            config,
            &mut ChangeWorkspace::new(),
            &mut classes,
        )
        .expect("sizes match");
        (changes, classes)
    }

    /// [`classify_pixels`] of `photo` against `model` (given depth: no model-plausible pixels,
    /// exact pose).
    fn classified(
        photo: &Image<f32>,
        model: &Image<f32>,
        config: &ChangeConfig,
    ) -> Image<ChangeClass> {
        let mut classes = Image::from_fn(1, 1, |_, _| ChangeClass::Unknown);
        classify_pixels(
            photo.view(),
            model.view(),
            None,
            &DepthEvidence::default(),
            config,
            &mut classes,
            &mut Vec::new(),
        )
        .expect("same sizes");
        classes
    }

    #[test]
    fn a_box_in_the_photo_only_is_one_added_region_with_its_area_and_height() {
        let (intrinsics, pose) = nadir();
        let model = mesh_of(&[ground([0.0, 0.0])]);
        let world = mesh_of(&[ground([0.0, 0.0]), roof(3.0, 2.0, 4.0)]);
        let photo_depth = depth_of(&world, &intrinsics, &pose);
        let (changes, _) = detect_on(
            &model,
            &intrinsics,
            &pose,
            &photo_depth,
            &ChangeConfig::default(),
        );
        assert_eq!(changes.regions.len(), 1, "{:?}", changes.regions);
        let region = &changes.regions[0];
        assert_eq!(region.kind, ChangeKind::Added);
        // 4 × 3 m roof, pixel footprints at 16 m: the surface area is 12 m².
        assert!(
            (region.surface_area_m2 - 12.0).abs() < 0.6,
            "{}",
            region.surface_area_m2
        );
        assert!(
            (region.footprint_area_m2 - 12.0).abs() < 0.8,
            "{}",
            region.footprint_area_m2
        );
        assert!((region.height_m - 4.0).abs() < 0.2, "{}", region.height_m);
        assert!((region.centroid_m[0] - 3.0).abs() < 0.1);
        assert!((region.centroid_m[1] - 2.0).abs() < 0.1);
        assert!((region.centroid_m[2] - 4.0).abs() < 0.05);
        assert!(region.confidence > 0.9);
        assert_eq!(changes.counts.removed, 0);
        assert!(changes.counts.added > 1000);
    }

    #[test]
    fn a_box_in_the_model_only_is_one_removed_region_and_georeferencing_is_kept() {
        let (intrinsics, pose) = nadir();
        // A georeferenced scene: everything shifted by (500 000, 5 000 000) m.
        let offset = Vector3::new(500_000.0, 5_000_000.0, 0.0);
        let shifted = |quad: [[f64; 3]; 4]| quad.map(|p| [p[0] + offset.x, p[1] + offset.y, p[2]]);
        let model = mesh_of(&[ground([0.0, 0.0]), roof(-4.0, -3.0, 5.0)].map(shifted));
        let world = mesh_of(&[ground([0.0, 0.0])].map(shifted));
        let pose = pose.compose(&Rigid3::new(nalgebra::UnitQuaternion::identity(), -offset));
        let photo_depth = depth_of(&world, &intrinsics, &pose);
        let (changes, _) = detect_on(
            &model,
            &intrinsics,
            &pose,
            &photo_depth,
            &ChangeConfig::default(),
        );
        assert_eq!(changes.regions.len(), 1, "{:?}", changes.regions);
        let region = &changes.regions[0];
        assert_eq!(region.kind, ChangeKind::Removed);
        assert!((region.height_m - 5.0).abs() < 0.2, "{}", region.height_m);
        assert!((region.centroid_m[0] - (offset.x - 4.0)).abs() < 0.1);
        assert!((region.centroid_m[1] - (offset.y - 3.0)).abs() < 0.1);
        assert!((region.surface_area_m2 - 12.0).abs() < 0.6);
    }

    /// A flat roof `width` (x) × `length` (y) m at `height`, centred on (cx, cy).
    fn rect(cx: f64, cy: f64, width: f64, length: f64, height: f64) -> [[f64; 3]; 4] {
        let (hw, hl) = (0.5 * width, 0.5 * length);
        [
            [cx - hw, cy - hl, height],
            [cx + hw, cy - hl, height],
            [cx + hw, cy + hl, height],
            [cx - hw, cy + hl, height],
        ]
    }

    /// The added regions [`detect_on`] finds when the photo is the ground plus `roof`, seen
    /// through a sparse depth map: holes (depth 0) in vertical bands 6 px wide every 10 px (a
    /// plain surface a matcher measures only on textured spots), and the photo's depth set to
    /// the ground's (the model agrees: `unchanged`) on the columns `agree_cols`.
    /// Change detection with the default settings from the nadir camera on `model`, the photo's
    /// depth at each pixel `photo_m(col, world's depth, model's depth)` (0: a hole).
    fn detect_nadir(
        model: &Mesh,
        world: &Mesh,
        photo_m: impl Fn(usize, f32, f32) -> f32,
    ) -> (FrameChanges, Image<ChangeClass>) {
        let (intrinsics, pose) = nadir();
        let model_depth = depth_of(model, &intrinsics, &pose);
        let mut photo_depth = depth_of(world, &intrinsics, &pose);
        for (index, d) in photo_depth.data_mut().iter_mut().enumerate() {
            *d = photo_m(index % 200, *d, model_depth.data()[index]);
        }
        detect_on(
            model,
            &intrinsics,
            &pose,
            &photo_depth,
            &ChangeConfig::default(),
        )
    }

    fn added_regions_through_hole_bands(
        roof: [[f64; 3]; 4],
        agree_cols: std::ops::Range<usize>,
    ) -> (FrameChanges, Image<ChangeClass>) {
        let model = mesh_of(&[ground([0.0, 0.0])]);
        let world = mesh_of(&[ground([0.0, 0.0]), roof]);
        detect_nadir(&model, &world, |col, world_m, model_m| {
            if col % 10 < 6 {
                0.0
            } else if agree_cols.contains(&col) {
                model_m
            } else {
                world_m
            }
        })
    }

    #[test]
    fn an_object_split_by_hole_bands_is_one_region_unless_unchanged_pixels_split_it() {
        // A 4 × 3 m roof 16 m from the camera (0.08 m a pixel) seen as five strips 4 px
        // (0.32 m) wide across 6-px hole bands: each strip is ~1 m² with one extent over 2 m,
        // too small alone; across the holes it is one region of the roof's size, whose area
        // counts the holes it spans.
        let (changes, classes) =
            added_regions_through_hole_bands(rect(0.0, 0.0, 4.0, 3.0, 4.0), 0..0);
        assert_eq!(changes.regions.len(), 1, "{:?}", changes.regions);
        let region = &changes.regions[0];
        assert_eq!(region.kind, ChangeKind::Added);
        assert!(
            region.surface_area_m2 > 9.0 && region.surface_area_m2 < 12.5,
            "{}",
            region.surface_area_m2
        );
        assert!(region.footprint_width_m > 2.5 && region.footprint_length_m > 3.0);
        // The holes stay `unknown`: no evidence either way.
        assert_eq!(classes.data()[100 * 200 + 92], ChangeClass::Unknown);
        assert!(changes.counts.added > 600);

        // An 8 × 3 m roof whose middle the photo's depth agrees with the model on (cols
        // 96..100, between two hole bands): evidence against a change, so two regions.
        let (changes, _) = added_regions_through_hole_bands(rect(0.0, 0.0, 8.0, 3.0, 4.0), 96..100);
        assert_eq!(changes.regions.len(), 2, "{:?}", changes.regions);
        let left = changes
            .regions
            .iter()
            .filter(|r| r.centroid_m[0] < 0.0)
            .count();
        assert_eq!(left, 1, "{:?}", changes.regions);
    }

    /// An 8 × 8 m roof 4 m high in the model only (demolished), seen from the nadir camera: the
    /// photo's depth (the ground behind it) is measured only on 2-px columns every
    /// `line_every_px` px, as a plain surface's painted lines give it.
    fn removed_regions_through_lines(line_every_px: usize) -> (FrameChanges, Image<ChangeClass>) {
        let model = mesh_of(&[ground([0.0, 0.0]), rect(0.0, 0.0, 8.0, 8.0, 4.0)]);
        let world = mesh_of(&[ground([0.0, 0.0])]);
        detect_nadir(&model, &world, |col, world_m, _| {
            if col % line_every_px < 2 {
                world_m
            } else {
                0.0
            }
        })
    }

    #[test]
    fn a_removed_surface_seen_through_lines_is_one_region_across_holes_up_to_its_least_extent() {
        // Lines 18 px apart on the roof 16 m away (1.44 m at 0.08 m a pixel: under the least
        // extent, 2 m): the model's roof is continuous across the holes, one region of about
        // the roof's size. Each line alone (0.16 × 8 m) has one extent over 2 m.
        let (changes, _) = removed_regions_through_lines(20);
        assert_eq!(changes.regions.len(), 1, "{:?}", changes.regions);
        let region = &changes.regions[0];
        assert_eq!(region.kind, ChangeKind::Removed);
        assert!(
            region.footprint_width_m > 5.5 && region.footprint_length_m > 5.5,
            "{region:?}"
        );
        // Lines 38 px apart (3.04 m): pieces of evidence that far apart are not joined.
        let (changes, classes) = removed_regions_through_lines(40);
        assert!(changes.regions.is_empty(), "{:?}", changes.regions);
        assert!(!classes.data().contains(&ChangeClass::Removed));
    }

    #[test]
    fn a_small_object_split_by_hole_bands_is_still_dropped() {
        // A 1.2 × 1.2 m roof: two strips across a hole band, 1.2 × 1.0 m even with the holes.
        let (changes, classes) =
            added_regions_through_hole_bands(rect(0.0, 0.0, 1.2, 1.2, 4.0), 0..0);
        assert!(changes.regions.is_empty(), "{:?}", changes.regions);
        assert_eq!(changes.counts.added, 0);
        assert!(!classes.data().contains(&ChangeClass::Added));
    }

    #[test]
    fn the_opening_drops_a_changed_pixel_for_evidence_not_for_holes() {
        // Model 20 m away everywhere; the photo sees 25 m (through the model) only along
        // 2-px lines between holes, as a plain road's painted edges give an MVS depth map.
        let (w, h) = (40, 30);
        let model = Image::filled(w, h, 20.0f32);
        let mut photo = Image::filled(w, h, 0.0f32);
        for col in 5..35 {
            for row in [10, 11] {
                *photo.get_mut(col, row).expect("inside") = 25.0;
            }
        }
        // A single far pixel among pixels that agree with the model: noise.
        for row in 20..27 {
            for col in 10..17 {
                *photo.get_mut(col, row).expect("inside") = 20.0;
            }
        }
        *photo.get_mut(13, 23).expect("inside") = 25.0;
        let config = ChangeConfig::default();
        let mut classes = Image::default();
        classify_pixels(
            photo.view(),
            model.view(),
            None,
            &DepthEvidence::default(),
            &config,
            &mut classes,
            &mut Vec::new(),
        )
        .expect("same sizes");
        let class = |col: usize, row: usize| *classes.get(col, row).expect("inside");
        // The line survives: the holes around it are no evidence against it…
        for col in 6..34 {
            assert_eq!(class(col, 10), ChangeClass::Removed, "col {col}");
            assert_eq!(class(col, 11), ChangeClass::Removed, "col {col}");
        }
        assert_eq!(class(20, 12), ChangeClass::Unknown);
        // …while a pixel the photo's agreeing depths surround is dropped.
        assert_eq!(class(13, 23), ChangeClass::Unchanged);
        assert_eq!(class(12, 23), ChangeClass::Unchanged);
    }

    #[test]
    fn noise_within_the_threshold_and_holes_are_not_changes() {
        let (intrinsics, pose) = nadir();
        let model = mesh_of(&[ground([0.0, 0.0])]);
        let mut photo_depth = depth_of(&model, &intrinsics, &pose);
        for (index, d) in photo_depth.data_mut().iter_mut().enumerate() {
            // ±1.5 % of 20 m = 0.3 m, below 3 × (0.1 + 0.01 · 20) = 0.9 m.
            *d *= if index % 2 == 0 { 1.015 } else { 0.985 };
            if index % 7 == 0 {
                *d = 0.0;
            }
        }
        // The workspace and classes of a 200 × 200 frame serve a 10 × 10 one next.
        let mut workspace = ChangeWorkspace::new();
        let mut classes = Image::default();
        let changes = detect_changes(
            &model,
            &intrinsics,
            &pose,
            photo_depth.view(),
            &DepthEvidence::default(),
            &ChangeConfig::default(),
            &mut workspace,
            &mut classes,
        )
        .expect("sizes match");
        assert!(changes.regions.is_empty());
        assert_eq!(changes.counts.added + changes.counts.removed, 0);
        assert!(changes.counts.unknown >= 200 * 200 / 7);
        let wrong = Image::filled(10, 10, 1.0f32);
        assert!(detect_changes(
            &model,
            &intrinsics,
            &pose,
            wrong.view(),
            &DepthEvidence::default(),
            &ChangeConfig::default(),
            &mut workspace,
            &mut classes,
        )
        .is_ok());
        let model_depth = Image::filled(20, 20, 1.0f32);
        assert!(matches!(
            classify_pixels(
                wrong.view(),
                model_depth.view(),
                None,
                &DepthEvidence::default(),
                &ChangeConfig::default(),
                &mut classes,
                &mut Vec::new()
            ),
            Err(ChangeError::SizeMismatch { .. })
        ));
    }

    #[test]
    fn foreground_depth_spread_over_an_occlusion_edge_is_explained_but_a_new_object_is_not() {
        // Model: a building (10 m) on the left half, the ground (20 m) on the right. The photo's
        // depth spreads the building 3 px over the ground (MVS edge fattening), shows a new
        // object (15 m) in front of the ground far from the edge, and sees through the model at
        // a few pixels left of the edge (removed: never explained away).
        let (w, h) = (80usize, 40usize);
        let model = Image::from_fn(w, h, |col, _| if col < 40 { 10.0f32 } else { 20.0 });
        let photo = Image::from_fn(w, h, |col, row| match col {
            0..=35 => 10.0f32,
            36..=39 if row < 20 => 10.0,
            36..=39 => 20.0,
            40..=42 => 10.0,
            55..=70 if (10..30).contains(&row) => 15.0,
            _ => 20.0,
        });
        let classify = |edge_tolerance_px| {
            let config = ChangeConfig {
                opening_radius_px: 0,
                edge_tolerance_px,
                ..ChangeConfig::default()
            };
            classified(&photo, &model, &config)
        };
        let count = |classes: &Image<ChangeClass>, class, cols: std::ops::Range<usize>| {
            (0..h)
                .flat_map(|row| cols.clone().map(move |col| (col, row)))
                .filter(|&(col, row)| classes.data()[row * w + col] == class)
                .count()
        };
        let strict = classify(0);
        assert_eq!(count(&strict, ChangeClass::Added, 40..43), 3 * h);
        let tolerant = classify(3);
        assert_eq!(count(&tolerant, ChangeClass::Added, 40..43), 0);
        for classes in [&strict, &tolerant] {
            assert_eq!(count(classes, ChangeClass::Added, 55..71), 16 * 20);
            assert_eq!(count(classes, ChangeClass::Removed, 36..40), 4 * 20);
        }
        // Farther than the tolerance from the model's foreground, the spread depth is a change.
        assert_eq!(count(&classify(2), ChangeClass::Added, 42..43), h);
    }

    #[test]
    fn an_object_in_front_of_a_smooth_oblique_surface_is_not_explained_by_the_surface_nearby() {
        // Model: an oblique wall, 20 m + 0.5 m per column (no depth edge: each step is under the
        // threshold). The photo sees an extension 2 m in front of it (over the threshold,
        // 3 × (0.1 + 0.01 d) = 1.3–1.6 m); the wall 4 columns nearer has its depth, but
        // that is the same smooth surface seen a few pixels off, not a foreground spread over
        // an occlusion edge.
        let (w, h) = (80usize, 40usize);
        let model = Image::from_fn(w, h, |col, _| 20.0 + 0.5 * col as f32);
        let inside = |col: usize, row: usize| (30..50).contains(&col) && (10..30).contains(&row);
        let photo = Image::from_fn(w, h, |col, row| {
            let wall = 20.0 + 0.5 * col as f32;
            if inside(col, row) {
                wall - 2.0
            } else {
                wall
            }
        });
        let config = ChangeConfig {
            opening_radius_px: 0,
            edge_tolerance_px: 5,
            ..ChangeConfig::default()
        };
        assert!(!model_depth_edges(model.view(), &config).contains(&true));
        let classes = classified(&photo, &model, &config);
        let added = (0..h)
            .flat_map(|row| (0..w).map(move |col| (col, row)))
            .filter(|&(col, row)| classes.data()[row * w + col] == ChangeClass::Added)
            .collect::<Vec<_>>();
        assert_eq!(added.len(), 20 * 20);
        assert!(added.iter().all(|&(col, row)| inside(col, row)));
        // The building's edge of the fattening test is a model depth edge, on both sides.
        let step = Image::from_fn(w, h, |col, _| if col < 40 { 10.0f32 } else { 20.0 });
        let edges = model_depth_edges(step.view(), &config);
        assert!((0..h).all(|row| edges[row * w + 39] && edges[row * w + 40]));
        assert_eq!(edges.iter().filter(|&&e| e).count(), 2 * h);
    }

    #[test]
    fn the_pose_term_is_slope_times_u_on_a_ramp_and_the_step_near_an_edge() {
        // Columns 0..40: a ramp 10 m + 0.2 m per column; 40..: a wall at 5 m (a depth edge);
        // row 0: no surface.
        let (w, h) = (60usize, 20usize);
        let model = Image::from_fn(w, h, |col, row| match (col, row) {
            (_, 0) => 0.0f32,
            (0..=39, _) => 10.0 + 0.2 * col as f32,
            _ => 5.0,
        });
        let (mut sigma, mut scratch) = (Image::default(), Vec::new());
        pose_error_sigma_m(model.view(), 0.0, &mut sigma, &mut scratch);
        assert!(sigma.data().iter().all(|s| *s == 0.0));
        pose_error_sigma_m(model.view(), 1.5, &mut sigma, &mut scratch);
        let at = |col: usize, row: usize| sigma.data()[row * w + col];
        // On the ramp: 0.2 m/px × 1.5 px.
        assert!((at(20, 10) - 0.3).abs() < 1e-4, "{}", at(20, 10));
        // Within ⌈u⌉ = 2 px of the edge the step (to 5 m from ~17.6 m) counts, scaled by u / r.
        assert!(
            (at(38, 10) - 0.75 * (17.6 - 5.0)).abs() < 1e-3,
            "{}",
            at(38, 10)
        );
        assert!(
            (at(41, 10) - 0.75 * (17.8 - 5.0)).abs() < 1e-3,
            "{}",
            at(41, 10)
        );
        assert_eq!(at(43, 10), 0.0, "the wall faces the camera: no term");
        // No surface: no term, and the sky above does not count in its neighbours' windows.
        assert_eq!(at(20, 0), 0.0);
        assert!((at(20, 1) - 0.3).abs() < 1e-4, "{}", at(20, 1));
    }

    #[test]
    fn a_pose_a_few_pixels_off_along_a_depth_edge_is_no_change_with_the_pose_term() {
        // An oblique camera on a 12 m high building; the photo's depth is the world's under the
        // true pose (the model plus a new 4 × 3 × 5 m block on the ground), the
        // model is rendered under a pose turned so that the image moves 4 px sideways.
        let intrinsics = PinholeIntrinsics::centered(200.0, 200, 200);
        let truth = Rigid3::look_at(
            &Vector3::new(5.0, -30.0, 45.0),
            &Vector3::new(0.0, 0.0, 4.0),
            &Vector3::z(),
        )
        .expect("a valid look-at");
        // A box on the ground: its roof and a wall on every edge of its footprint.
        let building = |x0: f64, y0: f64, x1: f64, y1: f64, top: f64| {
            let footprint = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]];
            let mut quads = vec![footprint.map(|[x, y]| [x, y, top])];
            for (i, &[ax, ay]) in footprint.iter().enumerate() {
                let [bx, by] = footprint[(i + 1) % 4];
                quads.push([[ax, ay, 0.0], [bx, by, 0.0], [bx, by, top], [ax, ay, top]]);
            }
            quads
        };
        let mut model_quads = vec![ground([0.0, 0.0])];
        model_quads.extend(building(-6.0, -4.0, 6.0, 4.0, 12.0));
        let mut world_quads = model_quads.clone();
        world_quads.extend(building(-16.0, -16.0, -12.0, -13.0, 5.0));
        let (model, world) = (mesh_of(&model_quads), mesh_of(&world_quads));
        let photo_depth = depth_of(&world, &intrinsics, &truth);
        let shift_px = 4.0;
        let turn = nalgebra::UnitQuaternion::from_scaled_axis(Vector3::new(
            0.0,
            shift_px / intrinsics.fx_px,
            0.0,
        ));
        let registered = Rigid3::new(turn * truth.rotation, turn * truth.translation);
        let detect = |pose_sigma_px: f32| {
            let config = ChangeConfig {
                pose_sigma_px,
                ..ChangeConfig::default()
            };
            detect_on(&model, &intrinsics, &registered, &photo_depth, &config).0
        };
        let is_new_block = |r: &ChangeRegion| {
            r.kind == ChangeKind::Added
                && (r.centroid_m[0] + 14.0).abs() < 1.5
                && (r.centroid_m[1] + 14.5).abs() < 1.5
        };
        let without = detect(0.0);
        let false_without: Vec<_> = without
            .regions
            .iter()
            .filter(|r| !is_new_block(r))
            .collect();
        assert!(
            !false_without.is_empty(),
            "without the pose term the building's edges seen 4 px off are changes: {:?}",
            without.regions
        );
        let with = detect(shift_px as f32);
        let false_with: Vec<_> = with.regions.iter().filter(|r| !is_new_block(r)).collect();
        assert!(false_with.is_empty(), "{false_with:?}");
        assert_eq!(
            with.regions.iter().filter(|r| is_new_block(r)).count(),
            1,
            "the new block stays a change: {:?}",
            with.regions
        );
    }

    #[test]
    fn a_registrations_spread_of_two_repeats_is_root_two_times_its_error() {
        assert!((pose_sigma_px_of_registration(2.0 * std::f64::consts::SQRT_2) - 2.0).abs() < 1e-6);
        assert_eq!(pose_sigma_px_of_registration(0.0), 0.0);
        assert_eq!(pose_sigma_px_of_registration(1e9), MAX_POSE_SIGMA_PX);
        assert_eq!(pose_sigma_px_of_registration(f64::NAN), MAX_POSE_SIGMA_PX);
        assert!(ChangeConfig {
            pose_sigma_px: MAX_POSE_SIGMA_PX + 1.0,
            ..ChangeConfig::default()
        }
        .validate()
        .is_err());
    }

    #[test]
    fn mask_levels_round_trip() {
        for class in [
            ChangeClass::Unknown,
            ChangeClass::Unchanged,
            ChangeClass::Added,
            ChangeClass::Removed,
        ] {
            assert_eq!(ChangeClass::from_mask_value(class.mask_value()), class);
            assert_eq!(ChangeClass::from(u8::from(class)), class);
        }
    }

    /// A city-like model depth, 240×160 px: an oblique ground (60 m at the top row, 0.1 m
    /// nearer a row) with six buildings 8–20 m in front of it.
    fn city_depth(col: i64, row: i64) -> f32 {
        let ground = 60.0 - 0.1 * row as f32;
        let mut d = ground;
        for (k, (c0, r0)) in [
            (20, 20),
            (90, 30),
            (160, 15),
            (40, 100),
            (120, 90),
            (190, 110),
        ]
        .into_iter()
        .enumerate()
        {
            if (c0..c0 + 30).contains(&col) && (r0..r0 + 25).contains(&row) {
                d = ground - 8.0 - 2.0 * k as f32;
            }
        }
        d
    }

    #[test]
    fn the_depth_misalignment_is_the_shift_between_the_model_and_the_photo() {
        let (w, h) = (240usize, 160usize);
        let model = Image::from_fn(w, h, |col, row| city_depth(col as i64, row as i64));
        for shift in [(3i64, -2i64), (0, 0), (-7, 5)] {
            // The photo's pixel x sees what the model renders at x + shift, with a new
            // 25 × 25 px building the model lacks, holes on every 7th pixel and a 0.5 % error.
            let photo = Image::from_fn(w, h, |col, row| {
                if (col * 3 + row * 5) % 7 == 0 {
                    return 0.0;
                }
                let (c, r) = (col as i64 + shift.0, row as i64 + shift.1);
                let d = if (200..225).contains(&col) && (40..65).contains(&row) {
                    40.0
                } else {
                    city_depth(c, r)
                };
                d * (1.0 + 0.005 * (((col * 7 + row * 13) % 11) as f32 / 5.0 - 1.0))
            });
            let found = depth_misalignment(model.view(), photo.view(), 16, 2)
                .expect("enough depth to align");
            let [dx, dy] = found.shift_px;
            assert!(
                (dx - shift.0 as f32).abs() < 0.35 && (dy - shift.1 as f32).abs() < 0.35,
                "true {shift:?}, found ({dx}, {dy})"
            );
            assert!(!found.at_border);
            assert!(found.cost <= found.cost_at_zero);
        }
        // Beyond the search: the best shift lies on the border.
        let far = Image::from_fn(w, h, |col, row| city_depth(col as i64 + 20, row as i64));
        let found = depth_misalignment(model.view(), far.view(), 8, 2).expect("enough depth");
        assert!(found.at_border, "{found:?}");
        // No photo depth on the model: nothing to measure.
        let empty = Image::filled(w, h, 0.0f32);
        assert!(depth_misalignment(model.view(), empty.view(), 8, 2).is_none());
    }

    #[test]
    fn the_frame_pose_sigma_comes_from_the_depths_only_under_registered_poses() {
        let (w, h) = (240usize, 160usize);
        let model = Image::from_fn(w, h, |col, row| city_depth(col as i64, row as i64));
        let photo = Image::from_fn(w, h, |col, row| city_depth(col as i64 + 4, row as i64 - 3));
        let registered = ChangeConfig {
            pose_sigma_px: 9.0,
            ..ChangeConfig::default()
        };
        let u = frame_pose_sigma_px(&registered, model.view(), photo.view());
        assert!((u - 5.0).abs() < 0.3, "u {u}");
        let kept = ChangeConfig {
            pose_sigma_from_depth: false,
            ..registered
        };
        assert_eq!(frame_pose_sigma_px(&kept, model.view(), photo.view()), 9.0);
        // Ground truth (u = 0) stays exact whatever the depths say.
        let truth = ChangeConfig::default();
        assert_eq!(frame_pose_sigma_px(&truth, model.view(), photo.view()), 0.0);
        // Unmeasurable: the largest u.
        let empty = Image::filled(w, h, 0.0f32);
        assert_eq!(
            frame_pose_sigma_px(&registered, model.view(), empty.view()),
            MAX_POSE_SIGMA_PX
        );
    }

    #[test]
    fn the_stereo_term_is_the_inverse_depth_spread_under_registered_poses_with_stereo_depth() {
        let (w, h) = (240usize, 160usize);
        let model = Image::from_fn(w, h, |col, row| city_depth(col as i64, row as i64));
        // A disparity error: normal in inverse depth with σ = 4e-4 per metre (Box–Muller of a
        // fixed sequence), on a photo whose new 40 × 40 px building (7 % of the pixels) the
        // model lacks, with holes on every 5th pixel.
        let sigma = 4e-4f32;
        let mut state = 12345u64;
        let mut uniform = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let photo = Image::from_fn(w, h, |col, row| {
            let normal =
                (-2.0 * uniform().ln()).sqrt() * (2.0 * std::f64::consts::PI * uniform()).cos();
            if (col + 2 * row) % 5 == 0 {
                return 0.0;
            }
            let m = if (180..220).contains(&col) && (100..140).contains(&row) {
                30.0
            } else {
                city_depth(col as i64, row as i64)
            };
            1.0 / (1.0 / m + sigma * normal as f32)
        });
        let spread = inverse_depth_spread_per_m(model.view(), photo.view()).expect("depths");
        assert!(
            (spread / sigma - 1.0).abs() < 0.1,
            "spread {spread} for σ {sigma}"
        );
        // Registered pose and stereo depth: the larger of the prior and the measured spread.
        let registered_stereo = ChangeConfig {
            pose_sigma_px: 2.0,
            quadratic_sigma_per_m: 1e-4,
            ..ChangeConfig::default()
        };
        let used = frame_quadratic_sigma_per_m(&registered_stereo, model.view(), photo.view());
        assert_eq!(used, spread);
        let confident = ChangeConfig {
            quadratic_sigma_per_m: 1e-3,
            ..registered_stereo
        };
        assert_eq!(
            frame_quadratic_sigma_per_m(&confident, model.view(), photo.view()),
            1e-3
        );
        // Ground-truth poses, a given (MVS) depth map, the switch off: the prior as it is.
        for prior_only in [
            ChangeConfig {
                pose_sigma_px: 0.0,
                ..registered_stereo
            },
            ChangeConfig {
                quadratic_sigma_per_m: 0.0,
                ..registered_stereo
            },
            ChangeConfig {
                stereo_sigma_from_depth: false,
                ..registered_stereo
            },
        ] {
            assert_eq!(
                frame_quadratic_sigma_per_m(&prior_only, model.view(), photo.view()),
                prior_only.quadratic_sigma_per_m
            );
        }
        // Nothing to compare: the prior.
        let empty = Image::filled(w, h, 0.0f32);
        assert!(inverse_depth_spread_per_m(model.view(), empty.view()).is_none());
        assert_eq!(
            frame_quadratic_sigma_per_m(&registered_stereo, model.view(), empty.view()),
            1e-4
        );
    }

    #[test]
    fn a_removed_region_seen_below_the_ground_is_unknown_and_a_demolition_stays_removed() {
        // The model: the ground (z = 0) and two 4 × 3 m roofs at 5 m, A at x = −5 (left half
        // of the nadir image), B at x = +5 (right half). The world has neither: B was
        // demolished, so the photo sees the ground through it; at A the photo's depth is wrong
        // by 5 m beyond the ground (a stereo match on the wrong repeat of a roof's texture),
        // 5 m under the ground, which no photo can see.
        let (intrinsics, pose) = nadir();
        let model = mesh_of(&[
            ground([0.0, 0.0]),
            roof(-5.0, 0.0, 5.0),
            roof(5.0, 0.0, 5.0),
        ]);
        let world = mesh_of(&[ground([0.0, 0.0])]);
        let model_depth = depth_of(&model, &intrinsics, &pose);
        let mut photo_depth = depth_of(&world, &intrinsics, &pose);
        let width = photo_depth.width_px();
        for (index, (d, &m)) in photo_depth
            .data_mut()
            .iter_mut()
            .zip(model_depth.data())
            .enumerate()
        {
            // A's roof pixels: model depth 15 m, left half.
            if index % width < width / 2 && m > 0.0 && m < 16.0 {
                *d += 5.0;
            }
        }
        let detect = |config: &ChangeConfig| {
            let (changes, classes) = detect_on(&model, &intrinsics, &pose, &photo_depth, config);
            let count = |class, left: bool| {
                classes
                    .data()
                    .iter()
                    .enumerate()
                    .filter(|(index, c)| **c == class && (index % width < width / 2) == left)
                    .count()
            };
            let counts = [
                count(ChangeClass::Removed, true),
                count(ChangeClass::Unknown, true),
                count(ChangeClass::Removed, false),
            ];
            (changes, counts)
        };
        let (changes, [left_removed, left_unknown, right_removed]) =
            detect(&ChangeConfig::default());
        // B, the demolition, stays one removed region: its photo lands on the ground.
        assert_eq!(changes.regions.len(), 1, "{:?}", changes.regions);
        assert_eq!(changes.regions[0].kind, ChangeKind::Removed);
        assert!((changes.regions[0].centroid_m[0] - 5.0).abs() < 0.2);
        assert!(right_removed > 1000, "{right_removed}");
        // A is dropped, its pixels unknown, with where and how deep it was.
        assert_eq!(left_removed, 0);
        assert!(left_unknown > 1000, "{left_unknown}");
        assert_eq!(changes.beyond_the_model.len(), 1);
        let dropped = &changes.beyond_the_model[0];
        assert_eq!(dropped.pixel_count, left_unknown);
        assert!((dropped.centroid_m[0] + 5.0).abs() < 0.2, "{dropped:?}");
        assert!(dropped.ground_z_m.abs() < 1e-3, "{dropped:?}");
        assert!(
            (4.5..5.1).contains(&dropped.median_below_ground_m),
            "{dropped:?}"
        );
        assert!(
            (4.5..5.1).contains(&dropped.median_beyond_ground_m),
            "{dropped:?}"
        );
        assert!(dropped.share_below > 0.9, "{dropped:?}");
        // Without the rule both are removed regions.
        let (off, [left_removed, _, _]) = detect(&ChangeConfig {
            ground_search_radius_m: 0.0,
            ..ChangeConfig::default()
        });
        assert_eq!(off.regions.len(), 2, "{:?}", off.regions);
        assert!(off.beyond_the_model.is_empty());
        assert!(left_removed > 1000, "{left_removed}");
    }

    #[test]
    fn the_models_ground_is_its_lowest_surface_within_the_radius() {
        // The ground at z = 0 (one 100 m quad: its corners are 50 m away, its face is not), a
        // roof at 5 m and a pit floor at −10 m 30–35 m east of the footprint.
        let pit = [
            [30.0, -2.0, -10.0],
            [35.0, -2.0, -10.0],
            [35.0, 2.0, -10.0],
            [30.0, 2.0, -10.0],
        ];
        let mesh = mesh_of(&[ground([0.0, 0.0]), roof(0.0, 0.0, 5.0), pit]);
        let footprint = [[-2.0, -1.5], [2.0, -1.5], [2.0, 1.5], [-2.0, 1.5]];
        let ground_z = |radius_m| model_ground_z_m(&mesh, &footprint, radius_m);
        assert_eq!(ground_z(15.0), Some(0.0));
        assert_eq!(ground_z(0.0), Some(0.0));
        assert_eq!(ground_z(30.0), Some(-10.0));
        assert_eq!(model_ground_z_m(&mesh, &[], 15.0), None);
        // A mesh of the roof alone has the roof as its ground, and none far from it.
        let roof_only = mesh_of(&[roof(0.0, 0.0, 5.0)]);
        assert_eq!(model_ground_z_m(&roof_only, &footprint, 15.0), Some(5.0));
        let far = [[100.0, 100.0], [101.0, 100.0], [101.0, 101.0]];
        assert_eq!(model_ground_z_m(&roof_only, &far, 15.0), None);
        for bad in [-1.0, f64::NAN, MAX_GROUND_SEARCH_RADIUS_M + 1.0] {
            let config = ChangeConfig {
                ground_search_radius_m: bad,
                ..ChangeConfig::default()
            };
            assert!(config.validate().is_err(), "{bad}");
        }
    }
}
