//! SIFT flow: dense matching of two dense SIFT images by coarse-to-fine, dual-layer loopy
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
//! Departures from the reference (the coarsest grid's inter-layer messages start at the data
//! term's marginals; the integer flow is refined below a pixel; beliefs are computed once per
//! level) and what each bought: docs/measurements.md#coresift_flow. Costs and messages are 16-bit
//! integers (the range term rounded to whole cost units, multigrid grids in scaled units: see
//! `bp`), computed 16 rows at a time in the order of the reference's sweeps.
//!
//! Preconditions: dense SIFT images from [`crate::core::dense_sift`]; masks, when given, are
//! images of the same size. Flow convention: `source(x, y) ≈ target(x + u, y + v)`, 0-based
//! pixels.

mod bp;
mod config;
mod data_cost;
mod kernels;
mod layout;
mod pyramid;
mod simd;

use std::time::{Duration, Instant};

use bp::{choose_labels, solve_with_multigrid, GridState, Isa, LevelProblem, MultigridGrid};
pub use config::{L1Kernel, SiftFlowConfig, SubpixelRefinement};
use data_cost::{compute_data_cost, Mirror};
pub use kernels::descriptor_l1_distance;
use layout::CostVolume;
pub use pyramid::SiftPyramid;
use pyramid::{build_mask_pyramid, level_mask, upsample_flow};

use crate::core::dense_sift::{DenseSiftImage, DESCRIPTOR_LEN};
use crate::core::image::{Image, ImageError, ImageView};

pub use crate::core::dense_sift::FlowError;

/// A dense flow field, `source(x, y) ≈ target(x + u, y + v)`: two planes (u, v) of the same size.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FlowField {
    u_px: Image<f32>,
    v_px: Image<f32>,
}

impl FlowField {
    /// A zero flow of the given size.
    pub fn zeros(width_px: usize, height_px: usize) -> Self {
        let mut field = Self::default();
        field.reset(width_px, height_px);
        field
    }

    /// The flow of two planes, which must have the same size.
    pub fn new(u_px: Image<f32>, v_px: Image<f32>) -> Result<Self, ImageError> {
        v_px.check_size("the v plane of a flow", u_px.width_px(), u_px.height_px())?;
        Ok(Self { u_px, v_px })
    }

    /// Resizes (keeping capacity) and zeroes the field.
    pub fn reset(&mut self, width_px: usize, height_px: usize) {
        self.u_px.reset(width_px, height_px, 0.0);
        self.v_px.reset(width_px, height_px, 0.0);
    }

    pub fn width_px(&self) -> usize {
        self.u_px.width_px()
    }

    pub fn height_px(&self) -> usize {
        self.u_px.height_px()
    }

    /// `(width_px, height_px)`.
    pub fn size(&self) -> (usize, usize) {
        self.u_px.size()
    }

    /// Horizontal flow, px.
    pub fn u_px(&self) -> &Image<f32> {
        &self.u_px
    }

    /// Vertical flow, px.
    pub fn v_px(&self) -> &Image<f32> {
        &self.v_px
    }

    /// Both planes' pixels to write in place, `(u, v)` (the size cannot change through this).
    pub fn planes_mut(&mut self) -> (&mut [f32], &mut [f32]) {
        (self.u_px.data_mut(), self.v_px.data_mut())
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
///
/// A dropped workspace leaves its buffers for the next one made (up to [`SPARE_WORKSPACES`]
/// of them kept, process-wide): callers that make a workspace per parallel job (a frame's views
/// under rayon's `map_init`) then reuse grown, already touched buffers instead of paying page
/// faults and the growth copies level by level (measured +10–15 ms CPU per 505×275 flow, a third
/// of it). Results never depend on what a buffer held.
#[derive(Debug)]
pub struct SiftFlowWorkspace {
    buffers: FlowBuffers,
}

/// How many dropped workspaces' buffers are kept for reuse (about 25 MB each at 505×275): the
/// two directions of a pair on each of a few threads.
const SPARE_WORKSPACES: usize = 4;

static SPARE_BUFFERS: std::sync::Mutex<Vec<FlowBuffers>> = std::sync::Mutex::new(Vec::new());

impl Default for SiftFlowWorkspace {
    fn default() -> Self {
        let spare = SPARE_BUFFERS.lock().ok().and_then(|mut spare| spare.pop());
        Self {
            buffers: spare.unwrap_or_default(),
        }
    }
}

impl Drop for SiftFlowWorkspace {
    fn drop(&mut self) {
        if let Ok(mut spare) = SPARE_BUFFERS.lock() {
            if spare.len() < SPARE_WORKSPACES {
                spare.push(std::mem::take(&mut self.buffers));
            }
        }
    }
}

#[derive(Debug, Default)]
struct FlowBuffers {
    /// Pyramids built by [`compute_sift_flow`].
    source_pyramid: SiftPyramid,
    target_pyramid: SiftPyramid,
    level: LevelBuffers,
    solver: SolverBuffers,
}

/// What a level's data term writes and its belief propagation reads.
#[derive(Debug, Default)]
struct LevelBuffers {
    /// Masks per level (level 0 included); empty vectors mean "all pixels".
    source_masks: Vec<Vec<bool>>,
    target_masks: Vec<Vec<bool>>,
    offsets: [Vec<i32>; 2],
    /// Matching costs of the last level solved.
    data_cost: CostVolume,
}

/// What belief propagation writes.
#[derive(Debug, Default)]
struct SolverBuffers {
    /// Integer flow (u, v) of the last level solved.
    flow: [Vec<i32>; 2],
    /// Chosen label per layer at the last level solved.
    labels: [Vec<u8>; 2],
    /// Messages of the last level solved.
    messages: GridState,
    /// Beliefs of the finest level (only for [`SubpixelRefinement::BeliefParabola`]).
    beliefs: [Vec<f32>; 2],
    /// Coarser grids of the multigrid belief propagation (reference `nHierarchy`).
    multigrid: Vec<MultigridGrid>,
}

/// Computes the SIFT flow from `source` to `target` into `flow` (source size) and the matching cost
/// of each pixel's chosen integer candidate into `matching_cost` (source size; 0 where the source
/// pixel takes no part). `source_participates[p] == false` removes pixel `p`'s data term (it
/// follows its neighbours); `target_valid[q] == false` makes target pixel `q` cost as much as an
/// outside one. Builds both pyramids in the workspace; see [`compute_sift_flow_on_pyramids`] to
/// reuse them.
#[allow(clippy::too_many_arguments)]
pub fn compute_sift_flow(
    source: &DenseSiftImage,
    source_participates: Option<ImageView<'_, bool>>,
    target: &DenseSiftImage,
    target_valid: Option<ImageView<'_, bool>>,
    config: &SiftFlowConfig,
    workspace: &mut SiftFlowWorkspace,
    flow: &mut FlowField,
    matching_cost: &mut Image<f32>,
) -> Result<SiftFlowTimings, FlowError> {
    let started = Instant::now();
    let mut source_pyramid = std::mem::take(&mut workspace.buffers.source_pyramid);
    let mut target_pyramid = std::mem::take(&mut workspace.buffers.target_pyramid);
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
    workspace.buffers.source_pyramid = source_pyramid;
    workspace.buffers.target_pyramid = target_pyramid;
    let mut timings = result?;
    timings.pyramid += pyramid_time;
    timings.total = started.elapsed();
    Ok(timings)
}

/// A flow endpoint: the dense SIFT image, its pyramid (built with the same config) and its mask.
pub type FlowInput<'a> = (
    &'a DenseSiftImage,
    &'a SiftPyramid,
    Option<ImageView<'a, bool>>,
);

/// [`compute_sift_flow`] on pyramids the caller built (and may reuse) with [`SiftPyramid::build`].
pub fn compute_sift_flow_on_pyramids(
    source: FlowInput,
    target: FlowInput,
    config: &SiftFlowConfig,
    workspace: &mut SiftFlowWorkspace,
    flow: &mut FlowField,
    matching_cost: &mut Image<f32>,
) -> Result<SiftFlowTimings, FlowError> {
    let started = Instant::now();
    check_inputs(source, target, config)?;
    let mut timings = SiftFlowTimings::default();
    let FlowBuffers { level, solver, .. } = &mut workspace.buffers;
    let isa = Isa::detect();
    let top_level = config.pyramid_levels - 1;
    let pyramid_started = Instant::now();
    build_masks(level, source, target, config);
    timings.pyramid = pyramid_started.elapsed();
    for level_index in (0..=top_level).rev() {
        let (source_level, target_level) = level_images(source, target, level_index);
        set_offsets(level, solver, source, source_level, level_index, top_level);
        let data_started = Instant::now();
        compute_level_cost(level, source_level, target_level, level_index, config, None);
        timings.data_cost += data_started.elapsed();
        let bp_started = Instant::now();
        solve_level(isa, config, level_index, top_level, level, solver);
        timings.belief_propagation += bp_started.elapsed();
    }
    write_finest_flow(config, source.0, level, solver, flow, matching_cost);
    timings.total = started.elapsed();
    Ok(timings)
}

/// One image of a two-way flow: its dense SIFT image, its pyramid (built with the same config),
/// where it takes part as the source (`participates`) and where it is a valid target (`valid`).
#[derive(Clone, Copy, Debug)]
pub struct PairInput<'a> {
    pub sift: &'a DenseSiftImage,
    pub pyramid: &'a SiftPyramid,
    pub participates: Option<ImageView<'a, bool>>,
    pub valid: Option<ImageView<'a, bool>>,
}

/// The flows of both directions of a pair, `first → second` (written to `flows[0]`,
/// `matching_costs[0]`, timings `[0]`) and `second → first` (`[1]`), bit for bit the two calls of
/// [`compute_sift_flow_on_pyramids`] `(first, participates) → (second, valid)` and `(second,
/// participates) → (first, valid)`, with less work: the matching cost of `first`'s pixel `p` at
/// `second`'s pixel `q` is the cost of `q` at `p` (the L1 distance is symmetric), so the second
/// direction's data term reads every candidate the first direction's volume already holds at the
/// same level (all of them at the top, where both windows are centred at zero; elsewhere where
/// the two flows of the level above agree) and computes only the others. The levels of the two
/// directions run in step: the first direction's costs, then its belief propagation side by side
/// with the second direction's costs and belief propagation.
pub fn compute_sift_flow_pair_on_pyramids(
    first: PairInput,
    second: PairInput,
    config: &SiftFlowConfig,
    workspaces: [&mut SiftFlowWorkspace; 2],
    flows: [&mut FlowField; 2],
    matching_costs: [&mut Image<f32>; 2],
) -> Result<[SiftFlowTimings; 2], FlowError> {
    let started = Instant::now();
    let forward_source = (first.sift, first.pyramid, first.participates);
    let forward_target = (second.sift, second.pyramid, second.valid);
    let backward_source = (second.sift, second.pyramid, second.participates);
    let backward_target = (first.sift, first.pyramid, first.valid);
    check_inputs(forward_source, forward_target, config)?;
    check_inputs(backward_source, backward_target, config)?;
    let mut timings = [SiftFlowTimings::default(); 2];
    let [forward_workspace, backward_workspace] = workspaces;
    let FlowBuffers {
        level: forward_level,
        solver: forward_solver,
        ..
    } = &mut forward_workspace.buffers;
    let FlowBuffers {
        level: backward_level,
        solver: backward_solver,
        ..
    } = &mut backward_workspace.buffers;
    let isa = Isa::detect();
    let top_level = config.pyramid_levels - 1;
    let pyramid_started = Instant::now();
    build_masks(forward_level, forward_source, forward_target, config);
    build_masks(backward_level, backward_source, backward_target, config);
    timings[0].pyramid = pyramid_started.elapsed();
    for level_index in (0..=top_level).rev() {
        let (forward_source_level, forward_target_level) =
            level_images(forward_source, forward_target, level_index);
        let (backward_source_level, backward_target_level) =
            level_images(backward_source, backward_target, level_index);
        set_offsets(
            forward_level,
            forward_solver,
            forward_source,
            forward_source_level,
            level_index,
            top_level,
        );
        set_offsets(
            backward_level,
            backward_solver,
            backward_source,
            backward_source_level,
            level_index,
            top_level,
        );
        let data_started = Instant::now();
        compute_level_cost(
            forward_level,
            forward_source_level,
            forward_target_level,
            level_index,
            config,
            None,
        );
        timings[0].data_cost += data_started.elapsed();
        // Truncated costs are capped at the median, which loses the distances above it.
        let forward_level = &*forward_level;
        let mirror = (!config.truncate_data_cost).then(|| Mirror {
            volume: &forward_level.data_cost,
            offsets: [&forward_level.offsets[0], &forward_level.offsets[1]],
            source_mask: level_mask(&forward_level.source_masks, level_index),
            target_mask: level_mask(&forward_level.target_masks, level_index),
        });
        let (forward_bp, (backward_data, backward_bp)) = rayon::join(
            || {
                let bp_started = Instant::now();
                solve_level(
                    isa,
                    config,
                    level_index,
                    top_level,
                    forward_level,
                    forward_solver,
                );
                bp_started.elapsed()
            },
            || {
                let data_started = Instant::now();
                compute_level_cost(
                    backward_level,
                    backward_source_level,
                    backward_target_level,
                    level_index,
                    config,
                    mirror,
                );
                let bp_started = Instant::now();
                solve_level(
                    isa,
                    config,
                    level_index,
                    top_level,
                    backward_level,
                    backward_solver,
                );
                (bp_started - data_started, bp_started.elapsed())
            },
        );
        timings[0].belief_propagation += forward_bp;
        timings[1].data_cost += backward_data;
        timings[1].belief_propagation += backward_bp;
    }
    let [forward_flow, backward_flow] = flows;
    let [forward_cost, backward_cost] = matching_costs;
    write_finest_flow(
        config,
        first.sift,
        forward_level,
        forward_solver,
        forward_flow,
        forward_cost,
    );
    write_finest_flow(
        config,
        second.sift,
        backward_level,
        backward_solver,
        backward_flow,
        backward_cost,
    );
    let total = started.elapsed();
    timings[0].total = total;
    timings[1].total = total;
    Ok(timings)
}

/// Checks a flow's inputs: descriptor images, mask and pyramid sizes, the config.
fn check_inputs(
    (source, source_pyramid, source_participates): FlowInput,
    (target, target_pyramid, target_valid): FlowInput,
    config: &SiftFlowConfig,
) -> Result<(), FlowError> {
    config.validate()?;
    check_sift_image(source, "source descriptors")?;
    check_sift_image(target, "target descriptors")?;
    for (mask, image, what) in [
        (source_participates, source, "source mask"),
        (target_valid, target, "target mask"),
    ] {
        if let Some(mask) = mask {
            mask.check_size(what, image.width_px, image.height_px)?;
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
    Ok(())
}

/// The mask pyramids of both images.
fn build_masks(
    buffers: &mut LevelBuffers,
    (source, _, source_participates): FlowInput,
    (target, _, target_valid): FlowInput,
    config: &SiftFlowConfig,
) {
    buffers
        .source_masks
        .resize_with(config.pyramid_levels, Vec::new);
    buffers
        .target_masks
        .resize_with(config.pyramid_levels, Vec::new);
    build_mask_pyramid(
        source_participates.map(|mask| mask.data()),
        source,
        &mut buffers.source_masks,
    );
    build_mask_pyramid(
        target_valid.map(|mask| mask.data()),
        target,
        &mut buffers.target_masks,
    );
}

/// The source's and target's descriptor images at `level`.
fn level_images<'a>(
    (source, source_pyramid, _): FlowInput<'a>,
    (target, target_pyramid, _): FlowInput<'a>,
    level: usize,
) -> (&'a DenseSiftImage, &'a DenseSiftImage) {
    match (source_pyramid.level(level), target_pyramid.level(level)) {
        (Some(source_level), Some(target_level)) => (source_level, target_level),
        _ => (source, target),
    }
}

/// Offsets of `level`: zero at the top, the doubled and rounded flow of the level above elsewhere.
fn set_offsets(
    buffers: &mut LevelBuffers,
    solver: &SolverBuffers,
    (_, source_pyramid, _): FlowInput,
    source_level: &DenseSiftImage,
    level: usize,
    top_level: usize,
) {
    let (width, height) = (source_level.width_px, source_level.height_px);
    for offsets in &mut buffers.offsets {
        offsets.clear();
        offsets.resize(width * height, 0);
    }
    if level != top_level {
        let (coarse_width, coarse_height) = source_pyramid
            .level(level + 1)
            .map_or((1, 1), |coarse| (coarse.width_px, coarse.height_px));
        for plane in 0..2 {
            upsample_flow(
                &solver.flow[plane],
                coarse_width,
                coarse_height,
                width,
                height,
                &mut buffers.offsets[plane],
            );
        }
    }
}

/// The data term of `level` into the buffers' volume (see [`compute_data_cost`]).
fn compute_level_cost(
    buffers: &mut LevelBuffers,
    source_level: &DenseSiftImage,
    target_level: &DenseSiftImage,
    level: usize,
    config: &SiftFlowConfig,
    mirror: Option<Mirror>,
) {
    let LevelBuffers {
        source_masks,
        target_masks,
        offsets,
        data_cost,
    } = buffers;
    compute_data_cost(
        source_level,
        level_mask(source_masks, level),
        target_level,
        level_mask(target_masks, level),
        [&offsets[0], &offsets[1]],
        config.level_radius(level, config.pyramid_levels - 1),
        config.truncate_data_cost,
        config.l1_kernel,
        mirror,
        data_cost,
    );
}

/// Belief propagation of `level` on its data term, and the integer flow it chooses.
fn solve_level(
    isa: Isa,
    config: &SiftFlowConfig,
    level: usize,
    top_level: usize,
    buffers: &LevelBuffers,
    solver: &mut SolverBuffers,
) {
    let radius = config.level_radius(level, top_level);
    let problem = LevelProblem {
        radius,
        labels: 2 * radius + 1,
        flow_magnitude_weight: config.flow_magnitude_weight * (1u32 << level) as f32,
        smoothness_weight: config.smoothness_weight,
        smoothness_truncation: config.smoothness_truncation,
        offsets: [&buffers.offsets[0], &buffers.offsets[1]],
        data: &buffers.data_cost,
        bands: config.bp_bands,
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
    if solver.multigrid.len() < multigrid_depth {
        solver
            .multigrid
            .resize_with(multigrid_depth, MultigridGrid::default);
    }
    solve_with_multigrid(
        isa,
        &problem,
        iterations,
        config.multigrid_iterations,
        config.specialised_kernels,
        &mut solver.multigrid[..multigrid_depth],
        &mut solver.messages,
    );
    let want_beliefs = level == 0 && config.subpixel == SubpixelRefinement::BeliefParabola;
    choose_labels(
        isa,
        &problem,
        config.specialised_kernels,
        &solver.messages,
        &mut solver.labels,
        want_beliefs.then_some(&mut solver.beliefs),
    );
    for plane in 0..2 {
        solver.flow[plane].clear();
        solver.flow[plane].extend(
            buffers.offsets[plane]
                .iter()
                .zip(&solver.labels[plane])
                .map(|(&offset, &label)| offset + label as i32 - radius as i32),
        );
    }
}

/// Finest level: integer flow, costs, optional sub-pixel refinement.
fn write_finest_flow(
    config: &SiftFlowConfig,
    source: &DenseSiftImage,
    buffers: &LevelBuffers,
    solver: &SolverBuffers,
    flow: &mut FlowField,
    matching_cost: &mut Image<f32>,
) {
    let width = source.width_px;
    let height = source.height_px;
    let radius = config.level_radius(0, config.pyramid_levels - 1);
    let labels = 2 * radius + 1;
    flow.reset(width, height);
    matching_cost.reset(width, height, 0.0);
    let (flow_u, flow_v) = flow.planes_mut();
    let matching_cost = matching_cost.data_mut();
    let source_mask = &buffers.source_masks[0];
    let window = labels * labels;
    for y in 0..height {
        let (first_vector, lane) = buffers.data_cost.layout.locate(0, y);
        for x in 0..width {
            let pixel = y * width + x;
            let label_u = solver.labels[0][pixel] as usize;
            let label_v = solver.labels[1][pixel] as usize;
            let costs = &buffers.data_cost.costs()
                [(first_vector + x) * window..(first_vector + x + 1) * window];
            let cost =
                |label_u: usize, label_v: usize| costs[label_v * labels + label_u].0[lane] as f32;
            let participates = source_mask.is_empty() || source_mask[pixel];
            if participates {
                matching_cost[pixel] = cost(label_u, label_v);
            }
            let (delta_u, delta_v) = match config.subpixel {
                SubpixelRefinement::None => (0.0, 0.0),
                SubpixelRefinement::DataCostParabola if participates => {
                    let along_u = |label: usize| cost(label, label_v);
                    let along_v = |label: usize| cost(label_u, label);
                    (
                        parabola_vertex(along_u, label_u, labels),
                        parabola_vertex(along_v, label_v, labels),
                    )
                }
                SubpixelRefinement::DataCostParabola => (0.0, 0.0),
                SubpixelRefinement::BeliefParabola => {
                    let belief_u = &solver.beliefs[0][pixel * labels..(pixel + 1) * labels];
                    let belief_v = &solver.beliefs[1][pixel * labels..(pixel + 1) * labels];
                    (
                        parabola_vertex(|label| belief_u[label], label_u, labels),
                        parabola_vertex(|label| belief_v[label], label_v, labels),
                    )
                }
            };
            flow_u[pixel] = solver.flow[0][pixel] as f32 + delta_u;
            flow_v[pixel] = solver.flow[1][pixel] as f32 + delta_v;
        }
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A crop of the repository's real pair (odd sizes: partial blocks of rows, padding).
    fn crop_pair(width: usize, height: usize) -> (DenseSiftImage, DenseSiftImage) {
        use test_support::{load_pair, sift_of};
        let pair = load_pair(
            &crate::test_data::repo_data("flow-pairs"),
            "dji0024_505x275",
        );
        let crop = |image: &Image<f32>| {
            Image::from_fn(width, height, |x, y| image.data()[(y + 30) * 505 + x + 60])
        };
        let config = crate::core::dense_sift::DenseSiftConfig::default();
        (
            sift_of(crop(&pair.first).view(), &config),
            sift_of(crop(&pair.second).view(), &config),
        )
    }

    fn flow_of(
        first: &DenseSiftImage,
        second: &DenseSiftImage,
        config: &SiftFlowConfig,
        portable: bool,
    ) -> (FlowField, Image<f32>) {
        bp::FORCE_PORTABLE.with(|force| force.set(portable));
        let mut flow = FlowField::default();
        let mut cost = Image::default();
        let mask = Image::from_fn(first.width_px, first.height_px, |x, y| {
            (x * 7 + y * 3) % 11 != 0
        });
        compute_sift_flow(
            first,
            Some(mask.view()),
            second,
            None,
            config,
            &mut SiftFlowWorkspace::default(),
            &mut flow,
            &mut cost,
        )
        .unwrap();
        bp::FORCE_PORTABLE.with(|force| force.set(false));
        (flow, cost)
    }

    #[test]
    fn kernels_give_identical_flows() {
        let (first, second) = crop_pair(83, 41);
        for config in [
            SiftFlowConfig::fast(),
            SiftFlowConfig {
                subpixel: SubpixelRefinement::BeliefParabola,
                search_radius_px: 3,
                top_search_radius_px: 7,
                pyramid_levels: 3,
                iterations: 9,
                ..SiftFlowConfig::fast()
            },
        ] {
            let reference = flow_of(&first, &second, &config, false);
            let generic = SiftFlowConfig {
                specialised_kernels: false,
                l1_kernel: L1Kernel::Portable,
                ..config.clone()
            };
            assert!(
                flow_of(&first, &second, &generic, false) == reference,
                "generic"
            );
            for l1_kernel in [L1Kernel::Avx2, L1Kernel::Sse2] {
                let kernel = SiftFlowConfig {
                    l1_kernel,
                    ..config.clone()
                };
                assert!(
                    flow_of(&first, &second, &kernel, false) == reference,
                    "{l1_kernel:?}"
                );
            }
            assert!(
                flow_of(&first, &second, &config, true) == reference,
                "portable"
            );
            assert!(
                flow_of(&first, &second, &generic, true) == reference,
                "portable generic"
            );
        }
    }

    /// The two directions of a pair computed together (the backward data term reading the forward
    /// volume) give the bits of two separate flows: masks on both sides, both subpixel modes, a
    /// truncated data term, every L1 kernel, images of different sizes, reused workspaces.
    #[test]
    fn pair_flows_are_the_separate_flows() {
        let (first, second) = crop_pair(83, 41);
        let (_, other_second) = crop_pair(77, 45);
        let mask = |image: &DenseSiftImage, seed: usize| {
            Image::from_fn(image.width_px, image.height_px, |x, y| {
                (x * 7 + y * 3 + seed) % 11 != 0 && (x / 9 + y / 5 + seed) % 4 != 0
            })
        };
        let configs = [
            SiftFlowConfig::fast(),
            SiftFlowConfig {
                subpixel: SubpixelRefinement::BeliefParabola,
                search_radius_px: 3,
                top_search_radius_px: 7,
                pyramid_levels: 3,
                iterations: 9,
                ..SiftFlowConfig::fast()
            },
            SiftFlowConfig {
                truncate_data_cost: true,
                ..SiftFlowConfig::fast()
            },
            SiftFlowConfig {
                l1_kernel: L1Kernel::Portable,
                ..SiftFlowConfig::fast()
            },
            SiftFlowConfig {
                l1_kernel: L1Kernel::Sse2,
                ..SiftFlowConfig::fast()
            },
        ];
        let mut workspaces = [SiftFlowWorkspace::default(), SiftFlowWorkspace::default()];
        let mut checked_backward_pixels = 0;
        for config in &configs {
            for (second, masked) in [(&second, true), (&other_second, true), (&second, false)] {
                let (first_participates, first_valid) = (mask(&first, 0), mask(&first, 1));
                let (second_participates, second_valid) = (mask(second, 2), mask(second, 3));
                let [first_pyramid, second_pyramid] = [&first, second].map(|image| {
                    let mut pyramid = SiftPyramid::default();
                    pyramid.build(image, config).unwrap();
                    pyramid
                });
                fn view(image: &Image<bool>, masked: bool) -> Option<ImageView<'_, bool>> {
                    masked.then(|| image.view())
                }
                let separate = |source: FlowInput, target: FlowInput| {
                    let (mut flow, mut cost) = (FlowField::default(), Image::default());
                    compute_sift_flow_on_pyramids(
                        source,
                        target,
                        config,
                        &mut SiftFlowWorkspace::default(),
                        &mut flow,
                        &mut cost,
                    )
                    .unwrap();
                    (flow, cost)
                };
                let forward = separate(
                    (&first, &first_pyramid, view(&first_participates, masked)),
                    (second, &second_pyramid, view(&second_valid, masked)),
                );
                let backward = separate(
                    (second, &second_pyramid, view(&second_participates, masked)),
                    (&first, &first_pyramid, view(&first_valid, masked)),
                );
                let mut flows = [FlowField::default(), FlowField::default()];
                let mut costs = [Image::default(), Image::default()];
                let [forward_workspace, backward_workspace] = &mut workspaces;
                let [forward_flow, backward_flow] = &mut flows;
                let [forward_cost, backward_cost] = &mut costs;
                compute_sift_flow_pair_on_pyramids(
                    PairInput {
                        sift: &first,
                        pyramid: &first_pyramid,
                        participates: view(&first_participates, masked),
                        valid: view(&first_valid, masked),
                    },
                    PairInput {
                        sift: second,
                        pyramid: &second_pyramid,
                        participates: view(&second_participates, masked),
                        valid: view(&second_valid, masked),
                    },
                    config,
                    [forward_workspace, backward_workspace],
                    [forward_flow, backward_flow],
                    [forward_cost, backward_cost],
                )
                .unwrap();
                let [forward_flow, backward_flow] = flows;
                let [forward_cost, backward_cost] = costs;
                assert!(
                    (forward_flow, forward_cost) == forward,
                    "forward {config:?}"
                );
                assert!(
                    (backward_flow, backward_cost) == backward,
                    "backward {config:?}"
                );
                checked_backward_pixels += backward.0.width_px() * backward.0.height_px();
            }
        }
        assert!(checked_backward_pixels > 0);
    }

    /// A workspace that served other problems (larger, smaller, other schedules), or one taken
    /// from the spare buffers, gives the bits of a never-used one.
    #[test]
    fn reused_and_spare_buffers_give_the_flow_of_fresh_ones() {
        let (first, second) = crop_pair(83, 41);
        let (large_first, large_second) = crop_pair(121, 67);
        let (small_first, small_second) = crop_pair(40, 23);
        let config = SiftFlowConfig::fast();
        let other = SiftFlowConfig {
            subpixel: SubpixelRefinement::BeliefParabola,
            search_radius_px: 3,
            top_search_radius_px: 7,
            pyramid_levels: 3,
            iterations: 9,
            ..SiftFlowConfig::fast()
        };
        let run = |source: &DenseSiftImage,
                   target: &DenseSiftImage,
                   config: &SiftFlowConfig,
                   masked: bool,
                   workspace: &mut SiftFlowWorkspace| {
            let mut flow = FlowField::default();
            let mut cost = Image::default();
            let mask = Image::from_fn(source.width_px, source.height_px, |x, y| {
                (x * 5 + y * 3) % 7 != 0
            });
            compute_sift_flow(
                source,
                masked.then(|| mask.view()),
                target,
                None,
                config,
                workspace,
                &mut flow,
                &mut cost,
            )
            .unwrap();
            (flow, cost)
        };
        let never_used = || SiftFlowWorkspace {
            buffers: FlowBuffers::default(),
        };
        let expected = run(&first, &second, &config, true, &mut never_used());
        let mut workspace = never_used();
        run(&large_first, &large_second, &other, false, &mut workspace);
        assert!(run(&first, &second, &config, true, &mut workspace) == expected);
        run(&small_second, &small_first, &config, false, &mut workspace);
        assert!(run(&first, &second, &config, true, &mut workspace) == expected);
        // Dropped workspaces' buffers serve the next workspaces made.
        for _ in 0..SPARE_WORKSPACES + 1 {
            let mut used = never_used();
            run(&large_second, &large_first, &other, true, &mut used);
        }
        for _ in 0..SPARE_WORKSPACES + 1 {
            assert!(
                run(
                    &first,
                    &second,
                    &config,
                    true,
                    &mut SiftFlowWorkspace::default()
                ) == expected
            );
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
}

/// Helpers shared by the tests of the dense-matching modules.
#[cfg(test)]
pub(crate) mod test_support {
    use super::*;
    use crate::core::dense_sift::{compute_dense_sift, DenseSiftConfig, DenseSiftWorkspace};

    pub(crate) struct SharedPair {
        pub first: Image<f32>,
        pub second: Image<f32>,
        pub truth: FlowField,
    }

    fn load_grey(path: &std::path::Path) -> Image<f32> {
        let image = image::open(path)
            .unwrap_or_else(|error| panic!("{}: {error}", path.display()))
            .to_luma8();
        let (width, height) = image.dimensions();
        Image::new(
            width as usize,
            height as usize,
            image
                .pixels()
                .map(|pixel| pixel.0[0] as f32 / 255.0)
                .collect(),
        )
        .unwrap()
    }

    /// Loads `NAME_im1.png`, `NAME_im2.png`, `NAME_gt.flo` from `directory` (panics, naming
    /// the file, when one is missing).
    pub(crate) fn load_pair(directory: &std::path::Path, name: &str) -> SharedPair {
        let first = load_grey(&directory.join(format!("{name}_im1.png")));
        let second = load_grey(&directory.join(format!("{name}_im2.png")));
        let truth = crate::io::flo::read_flo(&directory.join(format!("{name}_gt.flo")))
            .unwrap_or_else(|error| panic!("{error}"));
        SharedPair {
            first,
            second,
            truth,
        }
    }

    /// End-point error and fraction of pixels under 1 px, over pixels at least `border` px inside.
    pub(crate) fn score_flow(flow: &FlowField, truth: &FlowField, border: usize) -> (f64, f64) {
        let (mut sum, mut under_one, mut count) = (0.0f64, 0usize, 0usize);
        let (u, v) = (flow.u_px().data(), flow.v_px().data());
        let (true_u, true_v) = (truth.u_px().data(), truth.v_px().data());
        for y in border..flow.height_px() - border {
            for x in border..flow.width_px() - border {
                let pixel = y * flow.width_px() + x;
                let error =
                    ((u[pixel] - true_u[pixel]) as f64).hypot((v[pixel] - true_v[pixel]) as f64);
                sum += error;
                under_one += (error < 1.0) as usize;
                count += 1;
            }
        }
        (sum / count as f64, under_one as f64 / count as f64)
    }

    pub(crate) fn sift_of(image: ImageView<'_, f32>, config: &DenseSiftConfig) -> DenseSiftImage {
        let mut sift = DenseSiftImage::default();
        compute_dense_sift(image, config, &mut DenseSiftWorkspace::default(), &mut sift).unwrap();
        sift
    }
}
