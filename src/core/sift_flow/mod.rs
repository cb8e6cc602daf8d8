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
use data_cost::compute_data_cost;
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
    /// Masks per level (level 0 included); empty vectors mean "all pixels".
    source_masks: Vec<Vec<bool>>,
    target_masks: Vec<Vec<bool>>,
    offsets: [Vec<i32>; 2],
    /// The coarse flow's rows upsampled along x (scratch of [`upsample_flow`]).
    upsampled_rows: Vec<i32>,
    /// Integer flow (u, v) of the last level solved.
    flow: [Vec<i32>; 2],
    /// Chosen label per layer at the last level solved.
    labels: [Vec<u8>; 2],
    /// Matching costs of the last level solved.
    data_cost: CostVolume,
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
    (source, source_pyramid, source_participates): FlowInput,
    (target, target_pyramid, target_valid): FlowInput,
    config: &SiftFlowConfig,
    workspace: &mut SiftFlowWorkspace,
    flow: &mut FlowField,
    matching_cost: &mut Image<f32>,
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
    let mut timings = SiftFlowTimings::default();
    let ws = &mut workspace.buffers;
    let isa = Isa::detect();
    let level_count = config.pyramid_levels;
    let top_level = level_count - 1;

    // Mask pyramids.
    let pyramid_started = Instant::now();
    ws.source_masks.resize_with(level_count, Vec::new);
    ws.target_masks.resize_with(level_count, Vec::new);
    build_mask_pyramid(
        source_participates.map(|mask| mask.data()),
        source,
        &mut ws.source_masks,
    );
    build_mask_pyramid(
        target_valid.map(|mask| mask.data()),
        target,
        &mut ws.target_masks,
    );
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
                    &mut ws.upsampled_rows,
                    &mut ws.offsets[plane],
                );
            }
        }

        let data_started = Instant::now();
        let labels = 2 * radius + 1;
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
            radius,
            labels,
            flow_magnitude_weight: config.flow_magnitude_weight * (1u32 << level) as f32,
            smoothness_weight: config.smoothness_weight,
            smoothness_truncation: config.smoothness_truncation,
            offsets: [&ws.offsets[0], &ws.offsets[1]],
            data: &ws.data_cost,
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
        if ws.multigrid.len() < multigrid_depth {
            ws.multigrid
                .resize_with(multigrid_depth, MultigridGrid::default);
        }
        solve_with_multigrid(
            isa,
            &problem,
            iterations,
            config.multigrid_iterations,
            config.specialised_kernels,
            &mut ws.multigrid[..multigrid_depth],
            &mut ws.messages,
        );
        let want_beliefs = level == 0 && config.subpixel == SubpixelRefinement::BeliefParabola;
        choose_labels(
            isa,
            &problem,
            config.specialised_kernels,
            &ws.messages,
            &mut ws.labels,
            want_beliefs.then_some(&mut ws.beliefs),
        );
        for plane in 0..2 {
            ws.flow[plane].clear();
            ws.flow[plane].extend(
                ws.offsets[plane]
                    .iter()
                    .zip(&ws.labels[plane])
                    .map(|(&offset, &label)| offset + label as i32 - radius as i32),
            );
        }
        timings.belief_propagation += bp_started.elapsed();
    }

    // Finest level: integer flow, costs, optional sub-pixel refinement.
    let width = source.width_px;
    let height = source.height_px;
    let radius = config.level_radius(0, top_level);
    let labels = 2 * radius + 1;
    flow.reset(width, height);
    matching_cost.reset(width, height, 0.0);
    let (flow_u, flow_v) = flow.planes_mut();
    let matching_cost = matching_cost.data_mut();
    let source_mask = &ws.source_masks[0];
    let window = labels * labels;
    // Vector by vector (the 16 rows of a block at one position, then the next position), so that
    // each of the volume's cost vectors is fetched once for its 16 pixels; row order came back to
    // every vector once per row of its block, each time ~400 KB of other vectors later (505×275).
    // Every pixel's outputs depend only on its own inputs, so the order changes no value.
    ws.data_cost
        .layout
        .for_each_pixel_by_vector(|x, y, vector, lane| {
            let pixel = y * width + x;
            let label_u = ws.labels[0][pixel] as usize;
            let label_v = ws.labels[1][pixel] as usize;
            let costs = &ws.data_cost.costs()[vector * window..(vector + 1) * window];
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
                    let belief_u = &ws.beliefs[0][pixel * labels..(pixel + 1) * labels];
                    let belief_v = &ws.beliefs[1][pixel * labels..(pixel + 1) * labels];
                    (
                        parabola_vertex(|label| belief_u[label], label_u, labels),
                        parabola_vertex(|label| belief_v[label], label_v, labels),
                    )
                }
            };
            flow_u[pixel] = ws.flow[0][pixel] as f32 + delta_u;
            flow_v[pixel] = ws.flow[1][pixel] as f32 + delta_v;
        });
    timings.total = started.elapsed();
    Ok(timings)
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
