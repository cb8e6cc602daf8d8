//! SIFT flow: dense correspondence between two dense SIFT images by coarse-to-fine, dual-layer loopy
//! belief propagation (Liu, Yuen, Torralba, "SIFT Flow: Dense Correspondence across Scenes and its
//! Applications", TPAMI 2011, §3.2–3.3), following Ce Liu's reference (`BPFlow`, `SIFTflowc2f`).
//!
//! Energy over the flow `w = (u, v)` of every source pixel `p` (integer, px):
//! `E(w) = Σ_p ‖s1(p) − s2(p + w(p))‖₁ + Σ_p γ(|u| + |v|) + Σ_{p~q} min(α|u_p − u_q|, d) + min(α|v_p − v_q|, d)`.
//! `u` and `v` live on two coupled 4-connected layers (the data term couples them per pixel), so
//! every message has `2r + 1` entries and the truncated-L1 messages take linear time (distance
//! transform). Schedule as the reference's `BP_S`: iteration `k` updates layer `k mod 2`, sweeps
//! forward (messages right and down) when `k mod 4 < 2` and backward otherwise, and refreshes the
//! inter-layer messages when `k mod 8 < 4`. Candidates outside the target (or on invalid target
//! pixels) cost the median of all matching costs, as in the reference.
//!
//! Coarse to fine: a descriptor pyramid (Gaussian 5 taps, σ 0.67, then 2× downsampling), search
//! radius `top_search_radius_px` around zero at the top, and `search_radius_px + level` around the
//! doubled, rounded flow of the level above elsewhere; γ doubles per coarser level. Within each
//! level, multigrid BP as the reference's `nHierarchy`: the same problem on 2×2, 4×4, … blocks
//! (costs summed per label, γ halved) is solved first and its messages start the finer grid.
//!
//! Departures from the reference, each measured on the shared 505×275 pair: the coarsest grid
//! starts its inter-layer messages at the data term's marginals instead of zero (from zero, the
//! range term alone spreads through the first sweep and can lock the flow at 0: EPE 7.7 px
//! instead of 0.57 px without multigrid); the integer flow is refined below a pixel by a parabola
//! through the matching costs (0.445 → 0.277 px; the reference's integer flow scores 0.440 px);
//! beliefs are computed once at the end
//! of a level, not after every iteration. `SiftFlowConfig::fast` cuts the iterations to a third of
//! the time at the same error.
//!
//! Preconditions: dense SIFT images from [`crate::core::dense_sift`]; masks, when given, have one
//! entry per pixel. Flow convention: `source(x, y) ≈ target(x + u, y + v)`, 0-based pixels.

use std::time::{Duration, Instant};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::core::dense_sift::{DenseSiftImage, DESCRIPTOR_LEN};

/// Largest number of labels per layer (search window side) the fixed-size buffers allow.
const MAX_LABELS: usize = 64;
/// The bin width of the matching-cost histogram used for the median (cost units).
const COST_HISTOGRAM_BIN: f32 = 32.0;
const COST_HISTOGRAM_BINS: usize = 1100;

/// Errors of dense correspondence (dense SIFT, SIFT flow, consistency).
#[derive(Debug, thiserror::Error)]
pub enum FlowError {
    #[error("invalid configuration: {field}: {reason}")]
    InvalidConfig { field: &'static str, reason: String },
    #[error("image of {width_px} x {height_px} px given {values} values")]
    ImageSize {
        width_px: usize,
        height_px: usize,
        values: usize,
    },
    #[error("{what}: expected {expected} entries, found {found}")]
    SizeMismatch {
        what: &'static str,
        expected: usize,
        found: usize,
    },
}

/// A dense flow field, row major: `source(x, y) ≈ target(x + u, y + v)`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FlowField {
    pub width_px: usize,
    pub height_px: usize,
    pub u_px: Vec<f32>,
    pub v_px: Vec<f32>,
}

impl FlowField {
    pub fn zeros(width_px: usize, height_px: usize) -> Self {
        let mut field = Self::default();
        field.resize(width_px, height_px);
        field
    }

    /// Resizes (keeping capacity) and zeroes the field.
    pub fn resize(&mut self, width_px: usize, height_px: usize) {
        self.width_px = width_px;
        self.height_px = height_px;
        self.u_px.clear();
        self.u_px.resize(width_px * height_px, 0.0);
        self.v_px.clear();
        self.v_px.resize(width_px * height_px, 0.0);
    }
}

/// How the integer flow of the finest level is refined below a pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SubpixelRefinement {
    /// Integer flow, as the reference.
    None,
    /// Parabola through the matching cost at the chosen label and its two neighbours, per axis.
    DataCostParabola,
    /// Parabola through the final belief (data + smoothness messages) of each layer.
    BeliefParabola,
}

/// Which implementation computes the L1 distance of two 128-byte descriptors. `Auto` picks the
/// fastest the CPU has; the others exist to measure the difference.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum L1Kernel {
    Auto,
    /// Plain Rust loop over bytes.
    Portable,
    /// x86-64 `psadbw` on 16-byte lanes (baseline on every x86-64 CPU).
    Sse2,
    /// x86-64 AVX2 `vpsadbw` on 32-byte lanes (falls back to `Sse2` when absent).
    Avx2,
}

/// Parameters of coarse-to-fine SIFT flow. Defaults are Ce Liu's reference (`SIFTflowc2f` demo):
/// costs are in units of summed absolute byte differences of the 128-byte descriptors.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SiftFlowConfig {
    /// Pyramid levels including full resolution. Reference: 4.
    pub pyramid_levels: usize,
    /// Search half-window at the coarsest level, px of that level (21×21 candidates). Reference: 10.
    pub top_search_radius_px: usize,
    /// Search half-window around the propagated flow at the finest level, px; level `i` (0 = finest)
    /// uses `search_radius_px + i`. Reference: 2.
    pub search_radius_px: usize,
    /// Belief-propagation iterations at the coarsest level. Reference: 60.
    pub top_iterations: usize,
    /// Belief-propagation iterations at every other level. Reference: 30.
    pub iterations: usize,
    /// α: smoothness cost per px of flow difference between 4-neighbours. Reference: 2·255.
    pub smoothness_weight: f32,
    /// d: truncation of the smoothness cost. Reference: 40·255.
    pub smoothness_truncation: f32,
    /// γ: cost per px of flow magnitude (|u| + |v|) at full resolution, doubled per coarser level.
    /// Reference: 0.005·255.
    pub flow_magnitude_weight: f32,
    /// Truncate matching costs at their median (the reference's `IsDataTermTruncated`, off there).
    pub truncate_data_cost: bool,
    /// σ of the 5-tap Gaussian applied before each 2× downsampling of the descriptors, px.
    /// Reference: 0.67.
    pub pyramid_sigma_px: f32,
    /// Sub-pixel refinement of the finest level's integer flow. Default: `DataCostParabola` (our
    /// addition; the reference's flow is integer): on the 505×275 shared pair it lowers the
    /// end-point error from 0.445 px (integer, as the reference's 0.440) to 0.277 px.
    pub subpixel: SubpixelRefinement,
    /// Implementation of the descriptor L1 distance (results are identical).
    pub l1_kernel: L1Kernel,
    /// Multigrid belief propagation as the reference (`nHierarchy`): before each pyramid level's
    /// iterations, solve the same problem on 2×2, 4×4, … blocks (depth 2 at the top, `levels − 1 −
    /// level` below) and start from their messages.
    pub multigrid: bool,
    /// Iterations on each multigrid block level. Reference: 20.
    pub multigrid_iterations: usize,
    /// Cap on the multigrid depth (the reference's depth is at most `pyramid_levels − 1`).
    pub max_multigrid_depth: usize,
    /// Horizontal bands of rows swept in parallel (rayon) in every belief-propagation iteration;
    /// messages across band boundaries are sent after each sweep. 1 is the reference's sequential
    /// schedule; more bands change the result slightly (a different message order) but not with
    /// the thread count, so results stay reproducible.
    pub bp_bands: usize,
    /// Use the message-passing code specialised for the default window sizes; `false` runs the
    /// generic code (identical results; exists to measure the difference).
    pub specialised_kernels: bool,
}

impl Default for SiftFlowConfig {
    fn default() -> Self {
        Self {
            pyramid_levels: 4,
            top_search_radius_px: 10,
            search_radius_px: 2,
            top_iterations: 60,
            iterations: 30,
            smoothness_weight: 2.0 * 255.0,
            smoothness_truncation: 40.0 * 255.0,
            flow_magnitude_weight: 0.005 * 255.0,
            truncate_data_cost: false,
            pyramid_sigma_px: 0.67,
            subpixel: SubpixelRefinement::DataCostParabola,
            l1_kernel: L1Kernel::Auto,
            specialised_kernels: true,
            multigrid: true,
            multigrid_iterations: 20,
            max_multigrid_depth: 8,
            bp_bands: 1,
        }
    }
}

impl SiftFlowConfig {
    /// The reference's parameters with far fewer belief-propagation iterations (4 per level, 20 at
    /// the top, 4 per multigrid block level): the multigrid start makes the extra iterations of the
    /// reference nearly useless. Two bands of rows let two threads share each sweep. Measured on the
    /// shared pairs: EPE 0.278 px (505×275) and 0.271 px (1010×550) against 0.277 and 0.270 with
    /// the defaults, at about a third of the CPU time.
    pub fn fast() -> Self {
        Self {
            iterations: 4,
            top_iterations: 20,
            multigrid_iterations: 4,
            bp_bands: 2,
            ..Self::default()
        }
    }

    /// Checks every field once; call before the hot path.
    pub fn validate(&self) -> Result<(), FlowError> {
        let bad =
            |field: &'static str, reason: String| Err(FlowError::InvalidConfig { field, reason });
        if !(1..=8).contains(&self.pyramid_levels) {
            return bad(
                "pyramid_levels",
                format!("{} is not in 1..=8", self.pyramid_levels),
            );
        }
        let largest_radius = self
            .top_search_radius_px
            .max(self.search_radius_px + self.pyramid_levels);
        if self.top_search_radius_px == 0 || 2 * largest_radius + 1 > MAX_LABELS {
            return bad(
                "top_search_radius_px",
                format!(
                    "search windows must have 1..={} px half-width",
                    (MAX_LABELS - 1) / 2 - 8
                ),
            );
        }
        for (field, value) in [
            ("smoothness_weight", self.smoothness_weight),
            ("smoothness_truncation", self.smoothness_truncation),
            ("flow_magnitude_weight", self.flow_magnitude_weight),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return bad(field, format!("{value} is not a finite value >= 0"));
            }
        }
        if !(1..=64).contains(&self.bp_bands) {
            return bad("bp_bands", format!("{} is not in 1..=64", self.bp_bands));
        }
        if !(self.pyramid_sigma_px.is_finite() && self.pyramid_sigma_px > 0.0) {
            return bad(
                "pyramid_sigma_px",
                format!("{} is not > 0", self.pyramid_sigma_px),
            );
        }
        Ok(())
    }

    fn level_radius(&self, level: usize, top_level: usize) -> usize {
        if level == top_level {
            self.top_search_radius_px
        } else {
            self.search_radius_px + level
        }
    }
}

/// Time spent in each step of one SIFT flow.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SiftFlowTimings {
    pub pyramid: Duration,
    pub data_cost: Duration,
    pub belief_propagation: Duration,
    pub total: Duration,
}

/// Buffers reused between flows; grows to the largest problem seen and then stops allocating.
#[derive(Debug, Default)]
pub struct SiftFlowWorkspace {
    /// Pyramids built by [`compute_sift_flow`].
    source_pyramid: SiftPyramid,
    target_pyramid: SiftPyramid,
    /// Masks per level (level 0 included); empty vectors mean "all pixels".
    source_masks: Vec<Vec<bool>>,
    target_masks: Vec<Vec<bool>>,
    offsets: [Vec<i32>; 2],
    /// Integer flow (u, v) of the last level solved.
    flow: [Vec<i32>; 2],
    /// Chosen label per layer at the last level solved.
    labels: [Vec<u8>; 2],
    data_cost: Vec<f32>,
    spatial_messages: [Vec<f32>; 2],
    dual_messages: [Vec<f32>; 2],
    beliefs: [Vec<f32>; 2],
    /// Coarser grids of the multigrid belief propagation (reference `nHierarchy`).
    multigrid: Vec<MultigridGrid>,
}

/// One coarser grid of multigrid belief propagation: pixels are 2×2 blocks of the finer grid.
#[derive(Debug, Default)]
struct MultigridGrid {
    width: usize,
    height: usize,
    offsets: [Vec<i32>; 2],
    data_cost: Vec<f32>,
    spatial_messages: [Vec<f32>; 2],
    dual_messages: [Vec<f32>; 2],
}

/// The coarser levels (1..) of a dense SIFT image's pyramid (level 0 is the image itself). Build it
/// once per image and reuse it for every flow that image takes part in.
#[derive(Debug, Default)]
pub struct SiftPyramid {
    coarser_levels: Vec<DenseSiftImage>,
    row_buffer: Vec<f32>,
}

impl SiftPyramid {
    /// Builds levels `1..config.pyramid_levels` of `base` (blur by `pyramid_sigma_px`, halve).
    pub fn build(
        &mut self,
        base: &DenseSiftImage,
        config: &SiftFlowConfig,
    ) -> Result<(), FlowError> {
        config.validate()?;
        check_sift_image(base, "pyramid base")?;
        self.coarser_levels
            .resize_with(config.pyramid_levels - 1, DenseSiftImage::default);
        let taps = downsampling_taps(config.pyramid_sigma_px);
        build_pyramid(base, &mut self.coarser_levels, &taps, &mut self.row_buffer);
        Ok(())
    }

    /// Level `level` (≥ 1) of the pyramid.
    fn level(&self, level: usize) -> Option<&DenseSiftImage> {
        self.coarser_levels.get(level.checked_sub(1)?)
    }
}

/// Computes the SIFT flow from `source` to `target` into `flow` (source size) and the matching cost
/// of each pixel's chosen integer candidate into `matching_cost` (0 where the source pixel takes no
/// part). `source_participates[p] == false` removes pixel `p`'s data term (it follows its
/// neighbours); `target_valid[q] == false` makes target pixel `q` cost as much as an outside one.
/// Builds both pyramids in the workspace; see [`compute_sift_flow_on_pyramids`] to reuse them.
#[allow(clippy::too_many_arguments)]
pub fn compute_sift_flow(
    source: &DenseSiftImage,
    source_participates: Option<&[bool]>,
    target: &DenseSiftImage,
    target_valid: Option<&[bool]>,
    config: &SiftFlowConfig,
    workspace: &mut SiftFlowWorkspace,
    flow: &mut FlowField,
    matching_cost: &mut Vec<f32>,
) -> Result<SiftFlowTimings, FlowError> {
    let started = Instant::now();
    let mut source_pyramid = std::mem::take(&mut workspace.source_pyramid);
    let mut target_pyramid = std::mem::take(&mut workspace.target_pyramid);
    let (source_built, target_built) = rayon::join(
        || source_pyramid.build(source, config),
        || target_pyramid.build(target, config),
    );
    let pyramid_time = started.elapsed();
    let result = source_built.and(target_built).and_then(|()| {
        compute_sift_flow_on_pyramids(
            (source, &source_pyramid, source_participates),
            (target, &target_pyramid, target_valid),
            config,
            workspace,
            flow,
            matching_cost,
        )
    });
    workspace.source_pyramid = source_pyramid;
    workspace.target_pyramid = target_pyramid;
    let mut timings = result?;
    timings.pyramid += pyramid_time;
    timings.total = started.elapsed();
    Ok(timings)
}

/// A flow endpoint: the dense SIFT image, its pyramid (built with the same config) and its mask.
pub type FlowInput<'a> = (&'a DenseSiftImage, &'a SiftPyramid, Option<&'a [bool]>);

/// [`compute_sift_flow`] on pyramids the caller built (and may reuse) with [`SiftPyramid::build`].
pub fn compute_sift_flow_on_pyramids(
    (source, source_pyramid, source_participates): FlowInput,
    (target, target_pyramid, target_valid): FlowInput,
    config: &SiftFlowConfig,
    workspace: &mut SiftFlowWorkspace,
    flow: &mut FlowField,
    matching_cost: &mut Vec<f32>,
) -> Result<SiftFlowTimings, FlowError> {
    let started = Instant::now();
    config.validate()?;
    check_sift_image(source, "source descriptors")?;
    check_sift_image(target, "target descriptors")?;
    for (mask, image, what) in [
        (source_participates, source, "source mask"),
        (target_valid, target, "target mask"),
    ] {
        if let Some(mask) = mask {
            let expected = image.width_px * image.height_px;
            if mask.len() != expected {
                return Err(FlowError::SizeMismatch {
                    what,
                    expected,
                    found: mask.len(),
                });
            }
        }
    }
    for (pyramid, image, what) in [
        (source_pyramid, source, "source pyramid"),
        (target_pyramid, target, "target pyramid"),
    ] {
        let expected_width = image.width_px.div_ceil(1 << (config.pyramid_levels - 1));
        let top_width = pyramid
            .level(config.pyramid_levels - 1)
            .map_or(image.width_px, |top| top.width_px);
        match pyramid.coarser_levels.len() == config.pyramid_levels - 1
            && top_width == expected_width
        {
            true => {}
            false => {
                return Err(FlowError::SizeMismatch {
                    what,
                    expected: config.pyramid_levels - 1,
                    found: pyramid.coarser_levels.len(),
                })
            }
        }
    }
    let mut timings = SiftFlowTimings::default();
    let ws = workspace;
    let level_count = config.pyramid_levels;
    let top_level = level_count - 1;

    // Mask pyramids.
    let pyramid_started = Instant::now();
    ws.source_masks.resize_with(level_count, Vec::new);
    ws.target_masks.resize_with(level_count, Vec::new);
    build_mask_pyramid(source_participates, source, &mut ws.source_masks);
    build_mask_pyramid(target_valid, target, &mut ws.target_masks);
    timings.pyramid = pyramid_started.elapsed();

    for level in (0..level_count).rev() {
        let (source_level, target_level) =
            match (source_pyramid.level(level), target_pyramid.level(level)) {
                (Some(source_level), Some(target_level)) => (source_level, target_level),
                _ => (source, target),
            };
        let radius = config.level_radius(level, top_level);
        let width = source_level.width_px;
        let height = source_level.height_px;
        let pixel_count = width * height;

        // Offsets: zero at the top, the doubled and rounded flow of the level above elsewhere.
        for offsets in &mut ws.offsets {
            offsets.clear();
            offsets.resize(pixel_count, 0);
        }
        if level != top_level {
            let (coarse_width, coarse_height) = source_pyramid
                .level(level + 1)
                .map_or((1, 1), |coarse| (coarse.width_px, coarse.height_px));
            for plane in 0..2 {
                upsample_flow(
                    &ws.flow[plane],
                    coarse_width,
                    coarse_height,
                    width,
                    height,
                    &mut ws.offsets[plane],
                );
            }
        }

        let data_started = Instant::now();
        let labels = 2 * radius + 1;
        ws.data_cost.resize(pixel_count * labels * labels, 0.0);
        compute_data_cost(
            source_level,
            level_mask(&ws.source_masks, level),
            target_level,
            level_mask(&ws.target_masks, level),
            [&ws.offsets[0], &ws.offsets[1]],
            radius,
            config.truncate_data_cost,
            config.l1_kernel,
            &mut ws.data_cost,
        );
        timings.data_cost += data_started.elapsed();

        let bp_started = Instant::now();
        let problem = LevelProblem {
            width,
            height,
            radius,
            labels,
            flow_magnitude_weight: config.flow_magnitude_weight * (1u32 << level) as f32,
            smoothness_weight: config.smoothness_weight,
            smoothness_truncation: config.smoothness_truncation,
            offsets: [&ws.offsets[0], &ws.offsets[1]],
            data_cost: &ws.data_cost,
        };
        let iterations = if level == top_level {
            config.top_iterations
        } else {
            config.iterations
        };
        // The reference's multigrid depth: 2 at the top, `levels - 1 - level` elsewhere.
        let multigrid_depth = if !config.multigrid {
            0
        } else if level == top_level {
            2.min(config.max_multigrid_depth)
        } else {
            (top_level - level).min(config.max_multigrid_depth)
        };
        if ws.multigrid.len() < multigrid_depth {
            ws.multigrid
                .resize_with(multigrid_depth, MultigridGrid::default);
        }
        solve_with_multigrid(
            &problem,
            iterations,
            config.multigrid_iterations,
            config.specialised_kernels,
            config.bp_bands,
            &mut ws.multigrid[..multigrid_depth],
            &mut ws.spatial_messages,
            &mut ws.dual_messages,
        );
        compute_beliefs(
            &problem,
            &ws.spatial_messages,
            &ws.dual_messages,
            &mut ws.beliefs,
        );
        for plane in 0..2 {
            ws.flow[plane].resize(pixel_count, 0);
            ws.labels[plane].resize(pixel_count, 0);
            let beliefs = &ws.beliefs[plane];
            let offsets = &ws.offsets[plane];
            for (pixel, (flow_value, label_out)) in ws.flow[plane]
                .iter_mut()
                .zip(ws.labels[plane].iter_mut())
                .enumerate()
            {
                let belief = &beliefs[pixel * labels..(pixel + 1) * labels];
                let label = argmin(belief);
                *label_out = label as u8;
                *flow_value = offsets[pixel] + label as i32 - radius as i32;
            }
        }
        timings.belief_propagation += bp_started.elapsed();
    }

    // Finest level: integer flow, costs, optional sub-pixel refinement.
    let width = source.width_px;
    let height = source.height_px;
    let pixel_count = width * height;
    let radius = config.level_radius(0, top_level);
    let labels = 2 * radius + 1;
    flow.resize(width, height);
    matching_cost.clear();
    matching_cost.resize(pixel_count, 0.0);
    let source_mask = &ws.source_masks[0];
    for pixel in 0..pixel_count {
        let label_u = ws.labels[0][pixel] as usize;
        let label_v = ws.labels[1][pixel] as usize;
        let costs = &ws.data_cost[pixel * labels * labels..(pixel + 1) * labels * labels];
        let participates = source_mask.is_empty() || source_mask[pixel];
        if participates {
            matching_cost[pixel] = costs[label_v * labels + label_u];
        }
        let (delta_u, delta_v) = match config.subpixel {
            SubpixelRefinement::None => (0.0, 0.0),
            SubpixelRefinement::DataCostParabola if participates => {
                let along_u = |label: usize| costs[label_v * labels + label];
                let along_v = |label: usize| costs[label * labels + label_u];
                (
                    parabola_vertex(along_u, label_u, labels),
                    parabola_vertex(along_v, label_v, labels),
                )
            }
            SubpixelRefinement::DataCostParabola => (0.0, 0.0),
            SubpixelRefinement::BeliefParabola => {
                let belief_u = &ws.beliefs[0][pixel * labels..(pixel + 1) * labels];
                let belief_v = &ws.beliefs[1][pixel * labels..(pixel + 1) * labels];
                (
                    parabola_vertex(|label| belief_u[label], label_u, labels),
                    parabola_vertex(|label| belief_v[label], label_v, labels),
                )
            }
        };
        flow.u_px[pixel] = ws.flow[0][pixel] as f32 + delta_u;
        flow.v_px[pixel] = ws.flow[1][pixel] as f32 + delta_v;
    }
    timings.total = started.elapsed();
    Ok(timings)
}

fn level_mask(masks: &[Vec<bool>], level: usize) -> Option<&[bool]> {
    let mask = &masks[level];
    (!mask.is_empty()).then_some(mask.as_slice())
}

fn check_sift_image(image: &DenseSiftImage, what: &'static str) -> Result<(), FlowError> {
    let expected = image.width_px * image.height_px * DESCRIPTOR_LEN;
    if image.width_px == 0 || image.height_px == 0 || image.descriptors.len() != expected {
        return Err(FlowError::SizeMismatch {
            what,
            expected,
            found: image.descriptors.len(),
        });
    }
    Ok(())
}

/// Offset of the minimum of the parabola through `cost(label - 1), cost(label), cost(label + 1)`,
/// in `[-0.5, 0.5]`; 0 at the window's edge or where the parabola is not convex.
fn parabola_vertex(cost: impl Fn(usize) -> f32, label: usize, labels: usize) -> f32 {
    if label == 0 || label + 1 >= labels {
        return 0.0;
    }
    let (before, at, after) = (cost(label - 1), cost(label), cost(label + 1));
    let curvature = before - 2.0 * at + after;
    if curvature <= 0.0 || !curvature.is_finite() {
        return 0.0;
    }
    (0.5 * (before - after) / curvature).clamp(-0.5, 0.5)
}

#[inline]
fn argmin(values: &[f32]) -> usize {
    let mut best = 0;
    for (index, &value) in values.iter().enumerate().skip(1) {
        if value < values[best] {
            best = index;
        }
    }
    best
}

// ---------------------------------------------------------------------------------------------
// Pyramid
// ---------------------------------------------------------------------------------------------

/// The 6 taps (offsets -2..=3 around `2·X`) of "5-tap Gaussian, then average the 2×2 block", the
/// 1-D factor of the reference's blur-then-halve.
fn downsampling_taps(sigma_px: f32) -> [f32; 6] {
    let gaussian = crate::core::dense_sift::gaussian_taps(sigma_px, 2);
    let mut taps = [0.0f32; 6];
    for (index, tap) in taps.iter_mut().enumerate() {
        let left = if index < 5 { gaussian[index] } else { 0.0 };
        let right = if index >= 1 { gaussian[index - 1] } else { 0.0 };
        *tap = 0.5 * (left + right);
    }
    taps
}

fn build_pyramid(
    base: &DenseSiftImage,
    pyramid: &mut [DenseSiftImage],
    taps: &[f32; 6],
    row_buffer: &mut Vec<f32>,
) {
    for level in 0..pyramid.len() {
        let (finer, coarser) = pyramid.split_at_mut(level);
        let input = if level == 0 { base } else { &finer[level - 1] };
        downsample_descriptors(input, taps, row_buffer, &mut coarser[0]);
    }
}

fn downsample_descriptors(
    input: &DenseSiftImage,
    taps: &[f32; 6],
    row_buffer: &mut Vec<f32>,
    output: &mut DenseSiftImage,
) {
    let (width, height) = (input.width_px, input.height_px);
    let out_width = width.div_ceil(2);
    let out_height = height.div_ceil(2);
    output.resize(out_width, out_height, false);
    row_buffer.resize(width * DESCRIPTOR_LEN, 0.0);
    let row_len = width * DESCRIPTOR_LEN;
    for out_y in 0..out_height {
        row_buffer.fill(0.0);
        for (tap_index, &weight) in taps.iter().enumerate() {
            let source_y = (2 * out_y + tap_index).saturating_sub(2).min(height - 1);
            let source_row = &input.descriptors[source_y * row_len..(source_y + 1) * row_len];
            for (accumulator, &byte) in row_buffer.iter_mut().zip(source_row) {
                *accumulator += weight * byte as f32;
            }
        }
        let out_row = &mut output.descriptors
            [out_y * out_width * DESCRIPTOR_LEN..(out_y + 1) * out_width * DESCRIPTOR_LEN];
        for out_x in 0..out_width {
            let mut accumulated = [0.0f32; DESCRIPTOR_LEN];
            for (tap_index, &weight) in taps.iter().enumerate() {
                let source_x = (2 * out_x + tap_index).saturating_sub(2).min(width - 1);
                let source =
                    &row_buffer[source_x * DESCRIPTOR_LEN..(source_x + 1) * DESCRIPTOR_LEN];
                for (accumulator, &value) in accumulated.iter_mut().zip(source) {
                    *accumulator += weight * value;
                }
            }
            for (byte, value) in out_row[out_x * DESCRIPTOR_LEN..(out_x + 1) * DESCRIPTOR_LEN]
                .iter_mut()
                .zip(&accumulated)
            {
                *byte = (value + 0.5).min(255.0) as u8;
            }
        }
    }
}

/// Level 0 is the given mask (or empty: all pixels); a coarser pixel is set when at least two of
/// its (up to four) children are.
fn build_mask_pyramid(mask: Option<&[bool]>, base: &DenseSiftImage, levels: &mut [Vec<bool>]) {
    let Some(mask) = mask else {
        levels.iter_mut().for_each(Vec::clear);
        return;
    };
    levels[0].clear();
    levels[0].extend_from_slice(mask);
    let (mut width, mut height) = (base.width_px, base.height_px);
    for level in 1..levels.len() {
        let (finer, coarser) = levels.split_at_mut(level);
        let finer = &finer[level - 1];
        let out = &mut coarser[0];
        let (out_width, out_height) = (width.div_ceil(2), height.div_ceil(2));
        out.clear();
        for out_y in 0..out_height {
            for out_x in 0..out_width {
                let mut set = 0;
                for y in 2 * out_y..(2 * out_y + 2).min(height) {
                    for x in 2 * out_x..(2 * out_x + 2).min(width) {
                        set += finer[y * width + x] as usize;
                    }
                }
                out.push(set >= 2);
            }
        }
        (width, height) = (out_width, out_height);
    }
}

/// Bilinear 2× upsampling of an integer flow, doubled and rounded: the offsets of the finer level.
fn upsample_flow(
    coarse: &[i32],
    coarse_width: usize,
    coarse_height: usize,
    width: usize,
    height: usize,
    fine: &mut [i32],
) {
    for y in 0..height {
        let coarse_y = ((y as f32 + 0.5) * 0.5 - 0.5).clamp(0.0, (coarse_height - 1) as f32);
        let y0 = coarse_y.floor() as usize;
        let y1 = (y0 + 1).min(coarse_height - 1);
        let fy = coarse_y - y0 as f32;
        for x in 0..width {
            let coarse_x = ((x as f32 + 0.5) * 0.5 - 0.5).clamp(0.0, (coarse_width - 1) as f32);
            let x0 = coarse_x.floor() as usize;
            let x1 = (x0 + 1).min(coarse_width - 1);
            let fx = coarse_x - x0 as f32;
            let at = |xx: usize, yy: usize| coarse[yy * coarse_width + xx] as f32;
            let value = (at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx) * (1.0 - fy)
                + (at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx) * fy;
            fine[y * width + x] = (2.0 * value).round() as i32;
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Data term
// ---------------------------------------------------------------------------------------------

/// L1 distance of two 128-byte descriptors by a plain loop.
#[inline(always)]
fn l1_distance_portable(a: &[u8], b: &[u8]) -> u32 {
    a.iter().zip(b).map(|(&x, &y)| x.abs_diff(y) as u32).sum()
}

#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn l1_distance_sse2(a: &[u8], b: &[u8]) -> u32 {
    use std::arch::x86_64::*;
    assert!(a.len() >= DESCRIPTOR_LEN && b.len() >= DESCRIPTOR_LEN);
    // SAFETY: SSE2 is part of the x86-64 baseline; both slices hold 128 bytes (checked above) and
    // the loads are unaligned.
    unsafe {
        let mut total = _mm_setzero_si128();
        for chunk in 0..DESCRIPTOR_LEN / 16 {
            let va = _mm_loadu_si128(a.as_ptr().add(chunk * 16) as *const __m128i);
            let vb = _mm_loadu_si128(b.as_ptr().add(chunk * 16) as *const __m128i);
            total = _mm_add_epi64(total, _mm_sad_epu8(va, vb));
        }
        (_mm_cvtsi128_si64(total) + _mm_cvtsi128_si64(_mm_unpackhi_epi64(total, total))) as u32
    }
}

/// AVX2 L1 distance; only called from functions compiled with AVX2 enabled after runtime detection.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn l1_distance_avx2(a: &[u8], b: &[u8]) -> u32 {
    use std::arch::x86_64::*;
    assert!(a.len() >= DESCRIPTOR_LEN && b.len() >= DESCRIPTOR_LEN);
    // SAFETY: callers run only after `is_x86_feature_detected!("avx2")`; both slices hold 128
    // bytes (checked above) and the loads are unaligned.
    unsafe {
        let mut total = _mm256_setzero_si256();
        for chunk in 0..DESCRIPTOR_LEN / 32 {
            let va = _mm256_loadu_si256(a.as_ptr().add(chunk * 32) as *const __m256i);
            let vb = _mm256_loadu_si256(b.as_ptr().add(chunk * 32) as *const __m256i);
            total = _mm256_add_epi64(total, _mm256_sad_epu8(va, vb));
        }
        let low = _mm256_castsi256_si128(total);
        let high = _mm256_extracti128_si256(total, 1);
        let sum = _mm_add_epi64(low, high);
        (_mm_cvtsi128_si64(sum) + _mm_cvtsi128_si64(_mm_unpackhi_epi64(sum, sum))) as u32
    }
}

/// The L1 distance of two descriptors with the chosen kernel (for tests and benchmarks; the data
/// term dispatches once per row, not per pair).
pub fn descriptor_l1_distance(a: &[u8], b: &[u8], kernel: L1Kernel) -> u32 {
    match resolve_kernel(kernel) {
        #[cfg(target_arch = "x86_64")]
        L1Kernel::Avx2 => {
            // SAFETY: `resolve_kernel` returns Avx2 only when the CPU has AVX2.
            unsafe { l1_avx2_entry(a, b) }
        }
        #[cfg(target_arch = "x86_64")]
        L1Kernel::Sse2 => l1_distance_sse2(a, b),
        _ => l1_distance_portable(a, b),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn l1_avx2_entry(a: &[u8], b: &[u8]) -> u32 {
    l1_distance_avx2(a, b)
}

fn resolve_kernel(kernel: L1Kernel) -> L1Kernel {
    #[cfg(target_arch = "x86_64")]
    {
        let has_avx2 = std::arch::is_x86_feature_detected!("avx2");
        match kernel {
            L1Kernel::Auto | L1Kernel::Avx2 if has_avx2 => L1Kernel::Avx2,
            L1Kernel::Auto | L1Kernel::Avx2 | L1Kernel::Sse2 => L1Kernel::Sse2,
            L1Kernel::Portable => L1Kernel::Portable,
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = kernel;
        L1Kernel::Portable
    }
}

/// Marks a candidate outside the target (or on an invalid target pixel) until the median is known.
const OUTSIDE_COST: f32 = f32::INFINITY;

struct DataRowContext<'a> {
    source: &'a DenseSiftImage,
    source_mask: Option<&'a [bool]>,
    target: &'a DenseSiftImage,
    target_mask: Option<&'a [bool]>,
    offsets: [&'a [i32]; 2],
    radius: usize,
}

#[inline(always)]
fn fill_data_row(
    context: &DataRowContext,
    y: usize,
    row: &mut [f32],
    distance: impl Fn(&[u8], &[u8]) -> u32,
) {
    let labels = 2 * context.radius + 1;
    let window = labels * labels;
    let width = context.source.width_px;
    let (target_width, target_height) = (
        context.target.width_px as i32,
        context.target.height_px as i32,
    );
    for x in 0..width {
        let pixel = y * width + x;
        let costs = &mut row[x * window..(x + 1) * window];
        if context.source_mask.is_some_and(|mask| !mask[pixel]) {
            costs.fill(0.0);
            continue;
        }
        let descriptor = context.source.descriptor(pixel);
        let start_x = x as i32 + context.offsets[0][pixel] - context.radius as i32;
        let start_y = y as i32 + context.offsets[1][pixel] - context.radius as i32;
        for label_v in 0..labels {
            let target_y = start_y + label_v as i32;
            let cost_row = &mut costs[label_v * labels..(label_v + 1) * labels];
            if target_y < 0 || target_y >= target_height {
                cost_row.fill(OUTSIDE_COST);
                continue;
            }
            for (label_u, cost) in cost_row.iter_mut().enumerate() {
                let target_x = start_x + label_u as i32;
                if target_x < 0 || target_x >= target_width {
                    *cost = OUTSIDE_COST;
                    continue;
                }
                let target_pixel = (target_y * target_width + target_x) as usize;
                if context.target_mask.is_some_and(|mask| !mask[target_pixel]) {
                    *cost = OUTSIDE_COST;
                    continue;
                }
                *cost = distance(descriptor, context.target.descriptor(target_pixel)) as f32;
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn fill_data_row_avx2(context: &DataRowContext, y: usize, row: &mut [f32]) {
    fill_data_row(context, y, row, l1_distance_avx2)
}

#[allow(clippy::too_many_arguments)]
fn compute_data_cost(
    source: &DenseSiftImage,
    source_mask: Option<&[bool]>,
    target: &DenseSiftImage,
    target_mask: Option<&[bool]>,
    offsets: [&[i32]; 2],
    radius: usize,
    truncate: bool,
    kernel: L1Kernel,
    data_cost: &mut [f32],
) {
    let labels = 2 * radius + 1;
    let row_len = source.width_px * labels * labels;
    let context = DataRowContext {
        source,
        source_mask,
        target,
        target_mask,
        offsets,
        radius,
    };
    let kernel = resolve_kernel(kernel);
    data_cost
        .par_chunks_mut(row_len)
        .enumerate()
        .for_each(|(y, row)| match kernel {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `resolve_kernel` returns Avx2 only when the CPU has AVX2.
            L1Kernel::Avx2 => unsafe { fill_data_row_avx2(&context, y, row) },
            #[cfg(target_arch = "x86_64")]
            L1Kernel::Sse2 => fill_data_row(&context, y, row, l1_distance_sse2),
            _ => fill_data_row(&context, y, row, l1_distance_portable),
        });

    // The reference's default score: the median of all inside costs.
    let mut histogram = [0u32; COST_HISTOGRAM_BINS];
    let mut total = 0u64;
    for &cost in data_cost.iter().step_by(3) {
        if cost.is_finite() {
            histogram[((cost / COST_HISTOGRAM_BIN) as usize).min(COST_HISTOGRAM_BINS - 1)] += 1;
            total += 1;
        }
    }
    let mut default_cost = 0.0;
    let mut cumulative = 0u64;
    for (bin, &count) in histogram.iter().enumerate() {
        cumulative += count as u64;
        if 2 * cumulative >= total {
            default_cost = (bin.max(1) as f32) * COST_HISTOGRAM_BIN;
            break;
        }
    }
    data_cost.par_chunks_mut(row_len).for_each(|row| {
        for cost in row.iter_mut() {
            if *cost == OUTSIDE_COST || (truncate && *cost > default_cost) {
                *cost = default_cost;
            }
        }
    });
}

// ---------------------------------------------------------------------------------------------
// Belief propagation
// ---------------------------------------------------------------------------------------------

/// One level's discrete problem: labels `0..labels` of layer `plane` at pixel `p` stand for the
/// flow `offsets[plane][p] + label - radius`.
#[derive(Clone, Copy)]
struct LevelProblem<'a> {
    width: usize,
    height: usize,
    radius: usize,
    labels: usize,
    flow_magnitude_weight: f32,
    smoothness_weight: f32,
    smoothness_truncation: f32,
    offsets: [&'a [i32]; 2],
    /// Per pixel `labels × labels` costs, index `label_v · labels + label_u`.
    data_cost: &'a [f32],
}

/// Message slots per pixel: where the message came from.
const FROM_LEFT: usize = 0;
const FROM_RIGHT: usize = 1;
const FROM_ABOVE: usize = 2;
const FROM_BELOW: usize = 3;

/// Multigrid belief propagation as the reference's `MessagePassing(nIterations, nHierarchy)`: with
/// `grids` non-empty, first solve the problem on 2×2 blocks (data costs summed per label, offsets
/// averaged, γ halved) for `coarse_iterations`, recursively, and start this grid's messages from
/// the coarse ones; otherwise start from zero spatial messages and data-marginal dual messages.
#[allow(clippy::too_many_arguments)]
fn solve_with_multigrid(
    problem: &LevelProblem,
    iterations: usize,
    coarse_iterations: usize,
    specialised: bool,
    bands: usize,
    grids: &mut [MultigridGrid],
    spatial_messages: &mut [Vec<f32>; 2],
    dual_messages: &mut [Vec<f32>; 2],
) {
    let (width, height, labels) = (problem.width, problem.height, problem.labels);
    let pixel_count = width * height;
    // Sized here; every entry is then written below (copied from the coarse grid, or zeroed and
    // initialised from the data), so no separate clearing pass.
    for plane in 0..2 {
        spatial_messages[plane].resize(pixel_count * 4 * labels, 0.0);
        dual_messages[plane].resize(pixel_count * labels, 0.0);
    }
    match grids.split_first_mut() {
        Some((coarse, coarser_grids)) if width > 1 && height > 1 => {
            coarse.width = width.div_ceil(2);
            coarse.height = height.div_ceil(2);
            let coarse_pixels = coarse.width * coarse.height;
            let window = labels * labels;
            for plane in 0..2 {
                let offsets = &mut coarse.offsets[plane];
                offsets.clear();
                offsets.resize(coarse_pixels, 0);
                for coarse_y in 0..coarse.height {
                    for coarse_x in 0..coarse.width {
                        let (mut sum, mut count) = (0i32, 0i32);
                        for y in 2 * coarse_y..(2 * coarse_y + 2).min(height) {
                            for x in 2 * coarse_x..(2 * coarse_x + 2).min(width) {
                                sum += problem.offsets[plane][y * width + x];
                                count += 1;
                            }
                        }
                        offsets[coarse_y * coarse.width + coarse_x] = sum / count;
                    }
                }
            }
            coarse.data_cost.clear();
            coarse.data_cost.resize(coarse_pixels * window, 0.0);
            let coarse_width = coarse.width;
            coarse
                .data_cost
                .par_chunks_mut(coarse_width * window)
                .enumerate()
                .for_each(|(coarse_y, row)| {
                    for y in 2 * coarse_y..(2 * coarse_y + 2).min(height) {
                        for x in 0..width {
                            let fine = &problem.data_cost
                                [(y * width + x) * window..(y * width + x + 1) * window];
                            let coarse_costs = &mut row[(x / 2) * window..(x / 2 + 1) * window];
                            for (sum, &cost) in coarse_costs.iter_mut().zip(fine) {
                                *sum += cost;
                            }
                        }
                    }
                });
            let coarse_problem = LevelProblem {
                width: coarse.width,
                height: coarse.height,
                radius: problem.radius,
                labels,
                flow_magnitude_weight: problem.flow_magnitude_weight / 2.0,
                smoothness_weight: problem.smoothness_weight,
                smoothness_truncation: problem.smoothness_truncation,
                offsets: [&coarse.offsets[0], &coarse.offsets[1]],
                data_cost: &coarse.data_cost,
            };
            solve_with_multigrid(
                &coarse_problem,
                coarse_iterations,
                coarse_iterations,
                specialised,
                bands,
                coarser_grids,
                &mut coarse.spatial_messages,
                &mut coarse.dual_messages,
            );
            // Every fine pixel starts from its block's messages.
            for plane in 0..2 {
                let coarse_spatial = &coarse.spatial_messages[plane];
                let coarse_dual = &coarse.dual_messages[plane];
                spatial_messages[plane]
                    .par_chunks_mut(width * 4 * labels)
                    .enumerate()
                    .for_each(|(y, row)| {
                        for x in 0..width {
                            let block = (y / 2) * coarse_width + x / 2;
                            row[x * 4 * labels..(x + 1) * 4 * labels].copy_from_slice(
                                &coarse_spatial[block * 4 * labels..(block + 1) * 4 * labels],
                            );
                        }
                    });
                dual_messages[plane]
                    .par_chunks_mut(width * labels)
                    .enumerate()
                    .for_each(|(y, row)| {
                        for x in 0..width {
                            let block = (y / 2) * coarse_width + x / 2;
                            row[x * labels..(x + 1) * labels].copy_from_slice(
                                &coarse_dual[block * labels..(block + 1) * labels],
                            );
                        }
                    });
            }
        }
        _ => {
            spatial_messages
                .iter_mut()
                .for_each(|messages| messages.fill(0.0));
            initialise_dual_messages_from_data(problem, dual_messages);
        }
    }
    for iteration in 0..iterations {
        let plane = iteration % 2;
        let forward = iteration % 4 < 2;
        let update_dual = iteration % 8 < 4;
        let (dual_this, dual_other) = {
            let [first, second] = dual_messages;
            if plane == 0 {
                (&*first, second)
            } else {
                (&*second, first)
            }
        };
        let spatial = &mut spatial_messages[plane];
        let band_rows = problem.height.div_ceil(bands.max(1)).max(2);
        if band_rows >= problem.height {
            sweep_dispatch(
                problem,
                plane,
                forward,
                update_dual,
                specialised,
                spatial,
                dual_this,
                dual_other,
            );
            continue;
        }
        // Bands of rows swept in parallel, each as a separate image; the messages that cross
        // a band boundary are sent afterwards, from the state the sweep left.
        let labels = problem.labels;
        let band_pixels = band_rows * problem.width;
        let band_problems: Vec<LevelProblem> = (0..problem.height.div_ceil(band_rows))
            .map(|band| {
                let first_pixel = band * band_pixels;
                let end_pixel = (first_pixel + band_pixels).min(problem.width * problem.height);
                LevelProblem {
                    height: (end_pixel - first_pixel) / problem.width,
                    offsets: [
                        &problem.offsets[0][first_pixel..end_pixel],
                        &problem.offsets[1][first_pixel..end_pixel],
                    ],
                    data_cost: &problem.data_cost
                        [first_pixel * labels * labels..end_pixel * labels * labels],
                    ..*problem
                }
            })
            .collect();
        band_problems
            .par_iter()
            .zip(spatial.par_chunks_mut(band_pixels * 4 * labels))
            .zip(
                dual_this
                    .par_chunks(band_pixels * labels)
                    .zip(dual_other.par_chunks_mut(band_pixels * labels)),
            )
            .for_each(
                |((band_problem, band_spatial), (band_dual_this, band_dual_other))| {
                    sweep_dispatch(
                        band_problem,
                        plane,
                        forward,
                        update_dual,
                        specialised,
                        band_spatial,
                        band_dual_this,
                        band_dual_other,
                    );
                },
            );
        for band in 1..band_problems.len() {
            let seam_row = band * band_rows;
            let sender_row = if forward { seam_row - 1 } else { seam_row };
            send_across_seam(problem, plane, sender_row, forward, spatial, dual_this);
        }
    }
}

/// One sweep on the whole of `problem` with the fastest code for its label count.
#[allow(clippy::too_many_arguments)]
fn sweep_dispatch(
    problem: &LevelProblem,
    plane: usize,
    forward: bool,
    update_dual: bool,
    specialised: bool,
    spatial: &mut [f32],
    dual_this: &[f32],
    dual_other: &mut [f32],
) {
    let arguments = (problem, plane, forward, update_dual);
    // Specialised copies for the label counts of the default schedule (5, 7, 9 at the lower
    // levels, 21 at the top): fixed-size arrays, no bounds checks in the loops, constant loop
    // bounds the compiler unrolls and vectorises.
    match (specialised, problem.labels) {
        (true, 3) => sweep_fixed::<3>(arguments, spatial, dual_this, dual_other),
        (true, 5) => sweep_fixed::<5>(arguments, spatial, dual_this, dual_other),
        (true, 7) => sweep_fixed::<7>(arguments, spatial, dual_this, dual_other),
        (true, 9) => sweep_fixed::<9>(arguments, spatial, dual_this, dual_other),
        (true, 11) => sweep_fixed::<11>(arguments, spatial, dual_this, dual_other),
        (true, 21) => sweep_fixed::<21>(arguments, spatial, dual_this, dual_other),
        _ => sweep::<0>(arguments, spatial, dual_this, dual_other),
    }
}

/// The messages a banded sweep left out: from every pixel of `sender_row` down (forward) or up
/// (backward) into the neighbouring band.
fn send_across_seam(
    problem: &LevelProblem,
    plane: usize,
    sender_row: usize,
    forward: bool,
    spatial: &mut [f32],
    dual_this: &[f32],
) {
    let (width, labels) = (problem.width, problem.labels);
    let radius = problem.radius as i32;
    let offsets = problem.offsets[plane];
    let (slot_at_receiver, excluded_slot) = if forward {
        (FROM_ABOVE, FROM_BELOW)
    } else {
        (FROM_BELOW, FROM_ABOVE)
    };
    let mut outgoing = [0.0f32; MAX_LABELS];
    for x in 0..width {
        let pixel = sender_row * width + x;
        let receiver = if forward {
            pixel + width
        } else {
            pixel - width
        };
        let messages_in = &spatial[pixel * 4 * labels..(pixel + 1) * 4 * labels];
        for (label, value) in outgoing[..labels].iter_mut().enumerate() {
            let flow = offsets[pixel] + label as i32 - radius;
            *value = problem.flow_magnitude_weight * flow.unsigned_abs() as f32
                + dual_this[pixel * labels + label]
                + (0..4)
                    .filter(|&slot| slot != excluded_slot)
                    .map(|slot| messages_in[slot * labels + label])
                    .sum::<f32>();
        }
        let shift = offsets[receiver] - offsets[pixel];
        let message = &mut spatial[(receiver * 4 + slot_at_receiver) * labels..][..labels];
        truncated_l1_message(
            &mut outgoing[..labels],
            shift,
            problem.smoothness_weight,
            problem.smoothness_truncation,
            message,
        );
    }
}

/// `min` without NaN handling (one `minss`); the messages never hold NaN.
#[inline(always)]
fn fast_min(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

#[inline(always)]
fn load_labels<const L: usize>(buffer: &[f32], start: usize) -> [f32; L] {
    let mut values = [0.0f32; L];
    values.copy_from_slice(&buffer[start..start + L]);
    values
}

/// [`truncated_l1_message`] on fixed-size arrays, with a fast path for equal offsets.
#[inline(always)]
fn truncated_l1_message_fixed<const L: usize>(
    mut h: [f32; L],
    shift: i32,
    alpha: f32,
    truncation: f32,
) -> [f32; L] {
    let mut minimum = h[0];
    for label in 1..L {
        minimum = fast_min(minimum, h[label]);
        h[label] = fast_min(h[label], h[label - 1] + alpha);
    }
    for label in (0..L - 1).rev() {
        h[label] = fast_min(h[label], h[label + 1] + alpha);
    }
    let ceiling = minimum + truncation;
    let mut message = [0.0f32; L];
    if shift == 0 {
        // The distance transform keeps the minimum, so after the ceiling it is still `minimum`.
        for label in 0..L {
            message[label] = fast_min(h[label], ceiling) - minimum;
        }
        return message;
    }
    let last = L as i32 - 1;
    for (label, value) in message.iter_mut().enumerate() {
        let source_label = label as i32 + shift;
        let transformed = if source_label < 0 {
            h[0] + alpha * (-source_label) as f32
        } else if source_label > last {
            h[L - 1] + alpha * (source_label - last) as f32
        } else {
            h[source_label as usize]
        };
        *value = fast_min(transformed, ceiling);
    }
    let message_minimum = message.iter().copied().fold(f32::INFINITY, fast_min);
    for value in &mut message {
        *value -= message_minimum;
    }
    message
}

/// [`sweep`] for a label count fixed at compile time.
#[inline(never)]
fn sweep_fixed<const L: usize>(
    (problem, plane, forward, update_dual): (&LevelProblem, usize, bool, bool),
    spatial: &mut [f32],
    dual_this: &[f32],
    dual_other: &mut [f32],
) {
    let (width, height) = (problem.width, problem.height);
    let pixel_count = width * height;
    let offsets = problem.offsets[plane];
    let radius = problem.radius as i32;
    let gamma = problem.flow_magnitude_weight;
    let (alpha, truncation) = (problem.smoothness_weight, problem.smoothness_truncation);
    let slot = |pixel: usize, from: usize| (pixel * 4 + from) * L;
    for step in 0..pixel_count {
        let pixel = if forward {
            step
        } else {
            pixel_count - 1 - step
        };
        let (x, y) = (pixel % width, pixel / width);
        let offset = offsets[pixel];
        let from_left = load_labels::<L>(spatial, slot(pixel, FROM_LEFT));
        let from_right = load_labels::<L>(spatial, slot(pixel, FROM_RIGHT));
        let from_above = load_labels::<L>(spatial, slot(pixel, FROM_ABOVE));
        let from_below = load_labels::<L>(spatial, slot(pixel, FROM_BELOW));
        let dual_in = load_labels::<L>(dual_this, pixel * L);
        let mut base = [0.0f32; L];
        for label in 0..L {
            let flow = offset + label as i32 - radius;
            base[label] = gamma * flow.unsigned_abs() as f32
                + dual_in[label]
                + from_left[label]
                + from_right[label]
                + from_above[label]
                + from_below[label];
        }
        let mut send = |neighbour: usize, excluded: &[f32; L], slot_at_neighbour: usize| {
            let mut h = [0.0f32; L];
            for label in 0..L {
                h[label] = base[label] - excluded[label];
            }
            let message =
                truncated_l1_message_fixed::<L>(h, offsets[neighbour] - offset, alpha, truncation);
            spatial[slot(neighbour, slot_at_neighbour)..slot(neighbour, slot_at_neighbour) + L]
                .copy_from_slice(&message);
        };
        if forward {
            if x + 1 < width {
                send(pixel + 1, &from_right, FROM_LEFT);
            }
            if y + 1 < height {
                send(pixel + width, &from_below, FROM_ABOVE);
            }
        } else {
            if x > 0 {
                send(pixel - 1, &from_left, FROM_RIGHT);
            }
            if y > 0 {
                send(pixel - width, &from_above, FROM_BELOW);
            }
        }
        if update_dual {
            let mut outgoing = [0.0f32; L];
            for label in 0..L {
                outgoing[label] = base[label] - dual_in[label];
            }
            let costs = &problem.data_cost[pixel * L * L..(pixel + 1) * L * L];
            let mut message = [f32::INFINITY; L];
            if plane == 0 {
                for (value, row) in message.iter_mut().zip(costs.chunks_exact(L)) {
                    for label_u in 0..L {
                        *value = fast_min(*value, row[label_u] + outgoing[label_u]);
                    }
                }
            } else {
                for (row, &from_v) in costs.chunks_exact(L).zip(&outgoing) {
                    for label_u in 0..L {
                        message[label_u] = fast_min(message[label_u], row[label_u] + from_v);
                    }
                }
            }
            let minimum = message.iter().copied().fold(f32::INFINITY, fast_min);
            let out = &mut dual_other[pixel * L..(pixel + 1) * L];
            for (value, computed) in out.iter_mut().zip(&message) {
                *value = computed - minimum;
            }
        }
    }
}

/// One sweep over layer `plane`. `CONST_LABELS` is the label count when known at compile time, 0
/// for the generic version.
#[inline(never)]
fn sweep<const CONST_LABELS: usize>(
    (problem, plane, forward, update_dual): (&LevelProblem, usize, bool, bool),
    spatial: &mut [f32],
    dual_this: &[f32],
    dual_other: &mut [f32],
) {
    let labels = if CONST_LABELS == 0 {
        problem.labels
    } else {
        CONST_LABELS
    };
    let (width, height) = (problem.width, problem.height);
    let pixel_count = width * height;
    let offsets = problem.offsets[plane];
    let radius = problem.radius as i32;
    let gamma = problem.flow_magnitude_weight;
    let mut base = [0.0f32; MAX_LABELS];
    let mut outgoing = [0.0f32; MAX_LABELS];
    for step in 0..pixel_count {
        let pixel = if forward {
            step
        } else {
            pixel_count - 1 - step
        };
        let x = pixel % width;
        let y = pixel / width;
        let offset = offsets[pixel];
        let messages_in = &spatial[pixel * 4 * labels..(pixel + 1) * 4 * labels];
        let dual_in = &dual_this[pixel * labels..(pixel + 1) * labels];
        for label in 0..labels {
            let flow = offset + label as i32 - radius;
            base[label] = gamma * flow.unsigned_abs() as f32
                + dual_in[label]
                + messages_in[label]
                + messages_in[labels + label]
                + messages_in[2 * labels + label]
                + messages_in[3 * labels + label];
        }
        let neighbours: [(bool, usize, usize, usize); 2] = if forward {
            [
                (x + 1 < width, pixel + 1, FROM_LEFT, FROM_RIGHT),
                (y + 1 < height, pixel + width, FROM_ABOVE, FROM_BELOW),
            ]
        } else {
            [
                (x > 0, pixel.wrapping_sub(1), FROM_RIGHT, FROM_LEFT),
                (y > 0, pixel.wrapping_sub(width), FROM_BELOW, FROM_ABOVE),
            ]
        };
        for (exists, neighbour, slot_at_neighbour, slot_from_neighbour) in neighbours {
            if !exists {
                continue;
            }
            let from_neighbour = &spatial[(pixel * 4 + slot_from_neighbour) * labels..][..labels];
            for label in 0..labels {
                outgoing[label] = base[label] - from_neighbour[label];
            }
            let shift = offsets[neighbour] - offset;
            let message = &mut spatial[(neighbour * 4 + slot_at_neighbour) * labels..][..labels];
            truncated_l1_message(
                &mut outgoing[..labels],
                shift,
                problem.smoothness_weight,
                problem.smoothness_truncation,
                message,
            );
        }
        if update_dual {
            for label in 0..labels {
                outgoing[label] = base[label] - dual_in[label];
            }
            let costs = &problem.data_cost[pixel * labels * labels..(pixel + 1) * labels * labels];
            let message = &mut dual_other[pixel * labels..(pixel + 1) * labels];
            if plane == 0 {
                // From the u layer to the v layer: minimise over u for each v.
                for (label_v, value) in message.iter_mut().enumerate() {
                    let row = &costs[label_v * labels..(label_v + 1) * labels];
                    let mut best = f32::INFINITY;
                    for (cost, from_u) in row.iter().zip(&outgoing[..labels]) {
                        best = best.min(cost + from_u);
                    }
                    *value = best;
                }
            } else {
                // From the v layer to the u layer: minimise over v for each u.
                message.fill(f32::INFINITY);
                for (label_v, &from_v) in outgoing[..labels].iter().enumerate() {
                    let row = &costs[label_v * labels..(label_v + 1) * labels];
                    for (value, cost) in message.iter_mut().zip(row) {
                        *value = value.min(cost + from_v);
                    }
                }
            }
            let minimum = message.iter().copied().fold(f32::INFINITY, f32::min);
            message.iter_mut().for_each(|value| *value -= minimum);
        }
    }
}

/// Starts both inter-layer messages at the data term's marginals (`min` over the other layer's
/// labels of data + range), so that the first spatial sweeps carry the data rather than only the
/// range term: without this, the range term alone spreads through the first sweep and locks the
/// flow at zero.
fn initialise_dual_messages_from_data(problem: &LevelProblem, dual_messages: &mut [Vec<f32>; 2]) {
    let labels = problem.labels;
    let radius = problem.radius as i32;
    let gamma = problem.flow_magnitude_weight;
    let [to_u, to_v] = dual_messages;
    to_u.par_chunks_mut(labels)
        .zip(to_v.par_chunks_mut(labels))
        .enumerate()
        .for_each(|(pixel, (message_u, message_v))| {
            let costs = &problem.data_cost[pixel * labels * labels..(pixel + 1) * labels * labels];
            let offset_u = problem.offsets[0][pixel];
            let offset_v = problem.offsets[1][pixel];
            message_u.fill(f32::INFINITY);
            message_v.fill(f32::INFINITY);
            for label_v in 0..labels {
                let range_v = gamma * (offset_v + label_v as i32 - radius).unsigned_abs() as f32;
                for label_u in 0..labels {
                    let range_u =
                        gamma * (offset_u + label_u as i32 - radius).unsigned_abs() as f32;
                    let cost = costs[label_v * labels + label_u];
                    message_u[label_u] = message_u[label_u].min(cost + range_v);
                    message_v[label_v] = message_v[label_v].min(cost + range_u);
                }
            }
            for message in [message_u, message_v] {
                let minimum = message.iter().copied().fold(f32::INFINITY, f32::min);
                message.iter_mut().for_each(|value| *value -= minimum);
            }
        });
}

/// Turns `h` (the sender's costs over its labels) into the message over the receiver's labels for
/// the truncated-L1 pairwise cost `min(α|Δ|, d)`, by a distance transform. `shift` is the receiver's
/// offset minus the sender's. The message is normalised to minimum 0.
#[inline(always)]
fn truncated_l1_message(
    h: &mut [f32],
    shift: i32,
    alpha: f32,
    truncation: f32,
    message: &mut [f32],
) {
    let labels = h.len();
    let mut minimum = h[0];
    for label in 1..labels {
        minimum = minimum.min(h[label]);
        h[label] = h[label].min(h[label - 1] + alpha);
    }
    for label in (0..labels - 1).rev() {
        h[label] = h[label].min(h[label + 1] + alpha);
    }
    let ceiling = minimum + truncation;
    let last = labels as i32 - 1;
    let mut message_minimum = f32::INFINITY;
    for (label, value) in message.iter_mut().enumerate() {
        let source_label = label as i32 + shift;
        let transformed = if source_label < 0 {
            h[0] + alpha * (-source_label) as f32
        } else if source_label > last {
            h[labels - 1] + alpha * (source_label - last) as f32
        } else {
            h[source_label as usize]
        };
        *value = transformed.min(ceiling);
        message_minimum = message_minimum.min(*value);
    }
    message
        .iter_mut()
        .for_each(|value| *value -= message_minimum);
}

/// Belief of each layer: range term + inter-layer message + the four spatial messages.
fn compute_beliefs(
    problem: &LevelProblem,
    spatial_messages: &[Vec<f32>; 2],
    dual_messages: &[Vec<f32>; 2],
    beliefs: &mut [Vec<f32>; 2],
) {
    let labels = problem.labels;
    let radius = problem.radius as i32;
    let gamma = problem.flow_magnitude_weight;
    for plane in 0..2 {
        beliefs[plane].resize(problem.width * problem.height * labels, 0.0);
        let spatial = &spatial_messages[plane];
        let dual = &dual_messages[plane];
        let offsets = problem.offsets[plane];
        beliefs[plane]
            .par_chunks_mut(labels)
            .enumerate()
            .for_each(|(pixel, belief)| {
                let messages_in = &spatial[pixel * 4 * labels..(pixel + 1) * 4 * labels];
                for (label, value) in belief.iter_mut().enumerate() {
                    let flow = offsets[pixel] + label as i32 - radius;
                    *value = gamma * flow.unsigned_abs() as f32
                        + dual[pixel * labels + label]
                        + messages_in[label]
                        + messages_in[labels + label]
                        + messages_in[2 * labels + label]
                        + messages_in[3 * labels + label];
                }
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn l1_kernels_agree() {
        let a: Vec<u8> = (0..128).map(|index| (index * 37 % 256) as u8).collect();
        let b: Vec<u8> = (0..128)
            .map(|index| (255 - index * 11 % 256) as u8)
            .collect();
        let expected: u32 = a
            .iter()
            .zip(&b)
            .map(|(&x, &y)| (x as i32 - y as i32).unsigned_abs())
            .sum();
        for kernel in [
            L1Kernel::Auto,
            L1Kernel::Portable,
            L1Kernel::Sse2,
            L1Kernel::Avx2,
        ] {
            assert_eq!(
                descriptor_l1_distance(&a, &b, kernel),
                expected,
                "{kernel:?}"
            );
        }
    }

    #[test]
    fn distance_transform_matches_brute_force() {
        let alpha = 3.0;
        let truncation = 7.0;
        let costs = [5.0f32, 1.0, 9.0, 0.5, 12.0];
        for shift in -6..=6 {
            let mut h = costs;
            let mut message = [0.0f32; 5];
            truncated_l1_message(&mut h, shift, alpha, truncation, &mut message);
            let mut brute = [0.0f32; 5];
            for (receiver, value) in brute.iter_mut().enumerate() {
                *value = costs
                    .iter()
                    .enumerate()
                    .map(|(sender, &cost)| {
                        let difference = (receiver as i32 + shift - sender as i32).abs() as f32;
                        cost + (alpha * difference).min(truncation)
                    })
                    .fold(f32::INFINITY, f32::min);
            }
            let minimum = brute.iter().copied().fold(f32::INFINITY, f32::min);
            for (got, want) in message.iter().zip(&brute) {
                assert!(
                    (got - (want - minimum)).abs() < 1e-5,
                    "shift {shift}: {message:?} vs {brute:?}"
                );
            }
        }
    }

    #[test]
    fn parabola_vertex_finds_the_minimum() {
        // (x - 0.3)^2 sampled at -1, 0, 1.
        let samples = [1.69f32, 0.09, 0.49];
        let vertex = parabola_vertex(|label| samples[label], 1, 3);
        assert!((vertex - 0.3).abs() < 1e-5, "{vertex}");
        assert_eq!(parabola_vertex(|label| samples[label], 0, 3), 0.0);
    }

    #[test]
    fn config_rejects_unknown_fields_and_bad_values() {
        assert!(serde_json::from_str::<SiftFlowConfig>(r#"{"alpha": 1.0}"#).is_err());
        let parsed: SiftFlowConfig = serde_json::from_str(r#"{"iterations": 5}"#).unwrap();
        assert_eq!(parsed.iterations, 5);
        assert_eq!(parsed.top_search_radius_px, 10);
        let bad = SiftFlowConfig {
            top_search_radius_px: 40,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
        let bad = SiftFlowConfig {
            smoothness_weight: f32::NAN,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
    }
}

/// Helpers shared by the tests of the dense-correspondence modules.
#[cfg(test)]
pub(crate) mod test_support {
    use super::*;
    use crate::core::dense_sift::{compute_dense_sift, DenseSiftConfig, DenseSiftWorkspace};

    pub(crate) struct SharedPair {
        pub width: usize,
        pub height: usize,
        pub first: Vec<f32>,
        pub second: Vec<f32>,
        pub truth: FlowField,
    }

    fn load_grey(path: &std::path::Path) -> (usize, usize, Vec<f32>) {
        let image = image::open(path).unwrap().to_luma8();
        let (width, height) = image.dimensions();
        (
            width as usize,
            height as usize,
            image
                .pixels()
                .map(|pixel| pixel.0[0] as f32 / 255.0)
                .collect(),
        )
    }

    /// Loads `NAME_im1.png`, `NAME_im2.png`, `NAME_gt.flo` from the shared flow pairs, or `None`
    /// (with a printed note) when they are absent.
    pub(crate) fn load_shared_pair(name: &str) -> Option<SharedPair> {
        let directory = std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../shared/data/flow-pairs"
        ));
        let first_path = directory.join(format!("{name}_im1.png"));
        if !first_path.exists() {
            eprintln!("skipped: {} not found", first_path.display());
            return None;
        }
        let (width, height, first) = load_grey(&first_path);
        let (_, _, second) = load_grey(&directory.join(format!("{name}_im2.png")));
        let truth = crate::io::flo::read_flo(&directory.join(format!("{name}_gt.flo"))).unwrap();
        Some(SharedPair {
            width,
            height,
            first,
            second,
            truth,
        })
    }

    /// End-point error and fraction of pixels under 1 px, over pixels at least `border` px inside.
    pub(crate) fn score_flow(flow: &FlowField, truth: &FlowField, border: usize) -> (f64, f64) {
        let (mut sum, mut under_one, mut count) = (0.0f64, 0usize, 0usize);
        for y in border..flow.height_px - border {
            for x in border..flow.width_px - border {
                let pixel = y * flow.width_px + x;
                let error = ((flow.u_px[pixel] - truth.u_px[pixel]) as f64)
                    .hypot((flow.v_px[pixel] - truth.v_px[pixel]) as f64);
                sum += error;
                under_one += (error < 1.0) as usize;
                count += 1;
            }
        }
        (sum / count as f64, under_one as f64 / count as f64)
    }

    pub(crate) fn sift_of(
        image: &[f32],
        width: usize,
        height: usize,
        config: &DenseSiftConfig,
    ) -> DenseSiftImage {
        let mut sift = DenseSiftImage::default();
        compute_dense_sift(
            image,
            width,
            height,
            config,
            &mut DenseSiftWorkspace::default(),
            &mut sift,
        )
        .unwrap();
        sift
    }
}
