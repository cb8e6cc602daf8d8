//! Belief propagation of SIFT flow on one level: multigrid start, sweeps over the two flow layers,
//! truncated-L1 messages by distance transforms, and the chosen labels.
//!
//! Integer arithmetic on 16 rows at a time ([`super::layout`]): costs and messages are `u16`
//! (saturating), the range term `γ|w|` is rounded to whole cost units, and the sweeps visit the
//! pixels in a wavefront that gives exactly the messages of the reference's raster order (each
//! pixel needs only its left and upper neighbours' messages of the same sweep, both computed one
//! step earlier). Multigrid grids keep their costs as block means (the reference sums them) with α,
//! d and γ scaled to match, so that they fit 16 bits: a grid `k` levels down has energy
//! `1/4^k` of the reference's, and its messages are multiplied by 4 per level when they start the
//! finer grid.

use super::config::MAX_LABELS;
use super::layout::{grown, CostVolume, Layout};
#[cfg(target_arch = "x86_64")]
use super::simd::Avx2;
use super::simd::{Lanes, Portable, Simd, LANES};

/// Message slots per pixel: where the message came from.
const FROM_LEFT: usize = 0;
const FROM_RIGHT: usize = 1;
const FROM_ABOVE: usize = 2;
const FROM_BELOW: usize = 3;

/// `[0, 1, …, 15]`.
static LANE_INDEX: Lanes = Lanes([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15]);

/// Largest flow magnitude the range term distinguishes, px (larger ones cost as much).
const MAX_RANGE_FLOW: u16 = 2047;

/// The instruction set the kernels run with, chosen once per flow.
#[derive(Clone, Copy, Debug)]
pub(super) enum Isa {
    Portable,
    #[cfg(target_arch = "x86_64")]
    Avx2(Avx2),
}

#[cfg(test)]
thread_local! {
    /// Tests set this to run the plain-Rust kernels on a CPU that has AVX2.
    pub(super) static FORCE_PORTABLE: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

impl Isa {
    pub(super) fn detect() -> Self {
        #[cfg(test)]
        if FORCE_PORTABLE.with(std::cell::Cell::get) {
            return Self::Portable;
        }
        #[cfg(target_arch = "x86_64")]
        if let Some(avx2) = Avx2::detect() {
            return Self::Avx2(avx2);
        }
        Self::Portable
    }
}

/// One level's discrete problem: labels `0..labels` of layer `plane` at pixel `p` stand for the
/// flow `offsets[plane][p] + label − radius`.
#[derive(Clone, Copy)]
pub(super) struct LevelProblem<'a> {
    pub(super) radius: usize,
    pub(super) labels: usize,
    /// γ of this level, cost units per px.
    pub(super) flow_magnitude_weight: f32,
    pub(super) smoothness_weight: f32,
    pub(super) smoothness_truncation: f32,
    /// Row-major, the volume's size.
    pub(super) offsets: [&'a [i32]; 2],
    pub(super) data: &'a CostVolume,
    /// Horizontal bands of rows (`⌈height / bands⌉` rows each, at least 2) that every sweep treats
    /// as separate images; the messages across a band's seam are sent after the sweep, from the
    /// state it left (the schedule of the reference's parallel sweeps, here run one after the
    /// other). 1: one band.
    pub(super) bands: usize,
}

/// Messages and offsets of one grid, in the layout. The message buffers only grow (see
/// [`grown`]): their first `layout.vectors() · …` vectors are this grid's.
#[derive(Debug, Default)]
pub(super) struct GridState {
    layout: Layout,
    /// Offsets as `i16`.
    offsets: [Vec<Lanes>; 2],
    /// `4 · labels` vectors per position: slot `FROM_*`, then label.
    spatial: [Vec<Lanes>; 2],
    /// `labels` vectors per position: the message from the other layer.
    dual: [Vec<Lanes>; 2],
    /// Messages that cross from one block of rows to the next, per position and label (two, so
    /// that a block reads its neighbour's while writing its own).
    halo: [Vec<Lanes>; 2],
}

/// One coarser grid of multigrid belief propagation: pixels are 2×2 blocks of the finer grid.
#[derive(Debug, Default)]
pub(super) struct MultigridGrid {
    offsets: [Vec<i32>; 2],
    data: CostVolume,
    state: GridState,
}

/// The integer parameters of one grid.
#[derive(Clone, Copy, Debug)]
struct GridParams {
    labels: usize,
    radius: usize,
    alpha: u16,
    truncation: u16,
    /// `round(γ · 2¹¹)`: the range term is `round(16|w| · gamma_q15 / 2¹⁵) = round(γ|w|)`.
    gamma_q15: u16,
    /// Steps after which a shifted message is flat (`labels + ⌈d/α⌉`).
    max_shift: usize,
    /// Rows per band (see [`LevelProblem::bands`]); at least the grid's height for one band.
    band_rows: usize,
}

impl GridParams {
    /// The parameters of a grid `depth` multigrid levels below the problem's (energy `1/4^depth`).
    fn new(problem: &LevelProblem, depth: u32, height: usize) -> Self {
        let scale = 4f32.powi(depth as i32);
        let to_cost = |value: f32| (value / scale).round().clamp(0.0, u16::MAX as f32) as u16;
        let alpha = to_cost(problem.smoothness_weight);
        let truncation = to_cost(problem.smoothness_truncation);
        let gamma = problem.flow_magnitude_weight / (2f32.powi(depth as i32) * scale);
        let max_shift = problem.labels
            + if alpha == 0 {
                0
            } else {
                (truncation as usize).div_ceil(alpha as usize)
            };
        Self {
            labels: problem.labels,
            radius: problem.radius,
            alpha,
            truncation,
            gamma_q15: (gamma * 2048.0).round().clamp(0.0, i16::MAX as f32) as u16,
            max_shift,
            band_rows: height.div_ceil(problem.bands.max(1)).max(2),
        }
    }
}

/// Multigrid belief propagation as the reference's `MessagePassing(nIterations, nHierarchy)`: with
/// `grids` non-empty, first solve the problem on 2×2 blocks (costs averaged per label, offsets
/// averaged, energy scaled as the module comment says) for `coarse_iterations`, recursively, and
/// start this grid's messages from the coarse ones; otherwise start from zero spatial messages and
/// data-marginal dual messages. Leaves the messages in `state`.
#[allow(clippy::too_many_arguments)]
pub(super) fn solve_with_multigrid(
    isa: Isa,
    problem: &LevelProblem,
    iterations: usize,
    coarse_iterations: usize,
    specialised: bool,
    grids: &mut [MultigridGrid],
    state: &mut GridState,
) {
    solve_grid(
        isa,
        problem,
        problem.offsets,
        problem.data,
        0,
        iterations,
        coarse_iterations,
        specialised,
        grids,
        state,
    );
}

#[allow(clippy::too_many_arguments)]
fn solve_grid(
    isa: Isa,
    problem: &LevelProblem,
    offsets: [&[i32]; 2],
    data: &CostVolume,
    depth: u32,
    iterations: usize,
    coarse_iterations: usize,
    specialised: bool,
    grids: &mut [MultigridGrid],
    state: &mut GridState,
) {
    let layout = data.layout;
    let labels = problem.labels;
    state.layout = layout;
    for (plane, plane_offsets) in offsets.iter().enumerate() {
        layout.skew(
            plane_offsets,
            |offset| offset as i16 as u16,
            &mut state.offsets[plane],
        );
        grown(&mut state.spatial[plane], layout.vectors() * 4 * labels);
        grown(&mut state.dual[plane], layout.vectors() * labels);
        grown(&mut state.halo[plane], layout.positions * labels);
    }
    let params = GridParams::new(problem, depth, layout.height);
    let (width, height) = (layout.width, layout.height);
    let coarse = match grids.split_first_mut() {
        Some((coarse, coarser_grids)) if width > 1 && height > 1 => {
            let coarse_layout = Layout::new(width.div_ceil(2), height.div_ceil(2));
            for (fine, out) in offsets.iter().zip(&mut coarse.offsets) {
                average_offsets(fine, layout, coarse_layout, out);
            }
            coarse.data.reset(coarse_layout, labels);
            run_kernel(
                isa,
                labels,
                specialised,
                Kernel::CoarseData(data, &mut coarse.data),
            );
            solve_grid(
                isa,
                problem,
                [&coarse.offsets[0], &coarse.offsets[1]],
                &coarse.data,
                depth + 1,
                coarse_iterations,
                coarse_iterations,
                specialised,
                coarser_grids,
                &mut coarse.state,
            );
            Some(&coarse.state)
        }
        _ => None,
    };
    run_kernel(
        isa,
        labels,
        specialised,
        Kernel::Solve {
            params,
            data,
            coarse,
            state,
            iterations,
        },
    );
}

/// Offsets of the 2×2 blocks: the mean of the (up to four) fine offsets, truncated toward zero.
fn average_offsets(fine: &[i32], layout: Layout, coarse_layout: Layout, out: &mut Vec<i32>) {
    let (width, height) = (layout.width, layout.height);
    out.clear();
    for coarse_y in 0..coarse_layout.height {
        for coarse_x in 0..coarse_layout.width {
            let (mut sum, mut count) = (0i32, 0i32);
            for y in 2 * coarse_y..(2 * coarse_y + 2).min(height) {
                for x in 2 * coarse_x..(2 * coarse_x + 2).min(width) {
                    sum += fine[y * width + x];
                    count += 1;
                }
            }
            out.push(sum / count);
        }
    }
}

/// The labels (row-major, per layer) minimising each pixel's belief, and optionally the beliefs
/// themselves (row-major, `labels` per pixel).
pub(super) fn choose_labels(
    isa: Isa,
    problem: &LevelProblem,
    specialised: bool,
    state: &GridState,
    labels_out: &mut [Vec<u8>; 2],
    beliefs_out: Option<&mut [Vec<f32>; 2]>,
) {
    let params = GridParams::new(problem, 0, problem.data.layout.height);
    run_kernel(
        isa,
        problem.labels,
        specialised,
        Kernel::Choose {
            params,
            state,
            labels_out,
            beliefs_out,
        },
    );
}

/// The hot loops, run by [`run_kernel`] with the instruction set and label count fixed.
enum Kernel<'a> {
    CoarseData(&'a CostVolume, &'a mut CostVolume),
    Solve {
        params: GridParams,
        data: &'a CostVolume,
        coarse: Option<&'a GridState>,
        state: &'a mut GridState,
        iterations: usize,
    },
    Choose {
        params: GridParams,
        state: &'a GridState,
        labels_out: &'a mut [Vec<u8>; 2],
        beliefs_out: Option<&'a mut [Vec<f32>; 2]>,
    },
}

/// Runs `kernel` with the code specialised for `labels` (the label counts of the default schedule:
/// 5, 7, 9 at the lower levels, 21 at the top; and 3, 11) or the generic code.
fn run_kernel(isa: Isa, labels: usize, specialised: bool, kernel: Kernel) {
    match isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `Isa::Avx2` holds a token that exists only when the CPU has AVX2.
        Isa::Avx2(avx2) => unsafe { run_kernel_avx2(avx2, labels, specialised, kernel) },
        Isa::Portable => run_kernel_generic(Portable, labels, specialised, kernel),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn run_kernel_avx2(avx2: Avx2, labels: usize, specialised: bool, kernel: Kernel) {
    run_kernel_generic(avx2, labels, specialised, kernel)
}

#[inline(always)]
fn run_kernel_generic<S: Simd>(s: S, labels: usize, specialised: bool, kernel: Kernel) {
    match (specialised, labels) {
        (true, 3) => run_kernel_fixed::<S, 3>(s, kernel),
        (true, 5) => run_kernel_fixed::<S, 5>(s, kernel),
        (true, 7) => run_kernel_fixed::<S, 7>(s, kernel),
        (true, 9) => run_kernel_fixed::<S, 9>(s, kernel),
        (true, 11) => run_kernel_fixed::<S, 11>(s, kernel),
        (true, 21) => run_kernel_fixed::<S, 21>(s, kernel),
        _ => run_kernel_fixed::<S, MAX_LABELS>(s, kernel),
    }
}

/// `N` is the label count, or `MAX_LABELS` for the generic code (the label count then comes from
/// the parameters).
#[inline(always)]
fn run_kernel_fixed<S: Simd, const N: usize>(s: S, kernel: Kernel) {
    match kernel {
        Kernel::CoarseData(fine, coarse) => coarse_data(s, fine, coarse),
        Kernel::Solve {
            params,
            data,
            coarse,
            state,
            iterations,
        } => {
            let labels = label_count::<N>(params.labels);
            match coarse {
                Some(coarse) => start_from_coarse(s, labels, coarse, state),
                None => start_from_data::<S, N>(s, &params, data, state),
            }
            for iteration in 0..iterations {
                let plane = iteration % 2;
                let forward = iteration % 4 < 2;
                let update_dual = iteration % 8 < 4;
                if forward {
                    sweep_forward::<S, N>(s, &params, data, plane, update_dual, state);
                } else {
                    sweep_backward::<S, N>(s, &params, data, plane, update_dual, state);
                }
                send_across_seams(&params, plane, forward, state);
            }
        }
        Kernel::Choose {
            params,
            state,
            labels_out,
            beliefs_out,
        } => choose::<S, N>(s, &params, state, labels_out, beliefs_out),
    }
}

#[inline(always)]
fn label_count<const N: usize>(runtime: usize) -> usize {
    if N == MAX_LABELS {
        runtime
    } else {
        debug_assert_eq!(N, runtime);
        N
    }
}

/// The coarse grid's costs: per label, the rounded quarter of the 2×2 block's sum (out-of-image
/// pixels are padding, 0).
#[inline(always)]
fn coarse_data<S: Simd>(s: S, fine: &CostVolume, coarse: &mut CostVolume) {
    let window = fine.labels * fine.labels;
    let (fine_layout, coarse_layout) = (fine.layout, coarse.layout);
    let zero = s.splat(0);
    let fine_costs = fine.costs();
    let coarse_costs = coarse.costs_mut();
    let fine_vector = |block: usize, position: isize, entry: usize| {
        if block < fine_layout.blocks && (0..fine_layout.positions as isize).contains(&position) {
            s.load(
                &fine_costs[(block * fine_layout.positions + position as usize) * window + entry],
            )
        } else {
            zero
        }
    };
    for block in 0..coarse_layout.blocks {
        for position in 0..coarse_layout.positions {
            let out = (block * coarse_layout.positions + position) * window;
            for entry in 0..window {
                // Lanes 8h + i come from fine block 2·block + h, positions 2·position − 16h + {0, 1, 2}.
                let mut halves = [[zero; 3]; 2];
                for (half, vectors) in halves.iter_mut().enumerate() {
                    let first = 2 * position as isize - 16 * half as isize;
                    for (step, vector) in vectors.iter_mut().enumerate() {
                        *vector = fine_vector(2 * block + half, first + step as isize, entry);
                    }
                }
                s.store(&mut coarse_costs[out + entry], s.quarter_block_sums(halves));
            }
        }
    }
}

/// Starts every pixel's messages at its 2×2 block's (times 4: the coarse grid's energy unit is a
/// quarter of this one's).
#[inline(always)]
fn start_from_coarse<S: Simd>(s: S, labels: usize, coarse: &GridState, state: &mut GridState) {
    let (layout, coarse_layout) = (state.layout, coarse.layout);
    let times_4 = |value: S::V| {
        let doubled = s.adds(value, value);
        s.adds(doubled, doubled)
    };
    for plane in 0..2 {
        for (per_position, coarse_messages, messages) in [
            (
                4 * labels,
                &coarse.spatial[plane],
                &mut state.spatial[plane],
            ),
            (labels, &coarse.dual[plane], &mut state.dual[plane]),
        ] {
            for block in 0..layout.blocks {
                let (coarse_block, half) = (block / 2, block % 2);
                for position in 0..layout.positions {
                    // Even lanes (rows 2i) sit over coarse position ⌊t/2⌋ + 8h, odd lanes over
                    // ⌊(t − 1)/2⌋ + 8h, both in lane 8h + i.
                    let coarse_position = |t: usize| {
                        (t / 2 + 8 * half).min(coarse_layout.positions - 1)
                            + coarse_block * coarse_layout.positions
                    };
                    let even = coarse_position(position);
                    let odd = coarse_position(position.saturating_sub(1));
                    let out = (block * layout.positions + position) * per_position;
                    for entry in 0..per_position {
                        let value = s.interleave_half(
                            s.load(&coarse_messages[even * per_position + entry]),
                            s.load(&coarse_messages[odd * per_position + entry]),
                            half,
                        );
                        s.store(&mut messages[out + entry], times_4(value));
                    }
                }
            }
        }
    }
}

/// The range term `round(γ|offset + label − radius|)` of every label at one position.
#[inline(always)]
fn range_terms<S: Simd, const N: usize>(
    s: S,
    params: &GridParams,
    labels: usize,
    offsets: S::V,
) -> [S::V; N] {
    let gamma = s.splat(params.gamma_q15);
    let largest = s.splat(MAX_RANGE_FLOW);
    let mut terms = [s.splat(0); N];
    for (label, term) in terms.iter_mut().enumerate().take(labels) {
        let flow = s.add_i16(
            offsets,
            s.splat((label as i32 - params.radius as i32) as i16 as u16),
        );
        let magnitude = s.min(s.abs_i16(flow), largest);
        *term = s.mul_round_q15(s.times_16(magnitude), gamma);
    }
    terms
}

/// Zero spatial messages; inter-layer messages at the data term's marginals (`min` over the other
/// layer's labels of data + range), so that the first spatial sweeps carry the data rather than
/// only the range term: without this, the range term alone spreads through the first sweep and
/// locks the flow at zero.
#[inline(always)]
fn start_from_data<S: Simd, const N: usize>(
    s: S,
    params: &GridParams,
    data: &CostVolume,
    state: &mut GridState,
) {
    let labels = label_count::<N>(params.labels);
    let window = labels * labels;
    let spatial_len = state.layout.vectors() * 4 * labels;
    state
        .spatial
        .iter_mut()
        .for_each(|messages| messages[..spatial_len].fill(Lanes::default()));
    let [to_u, to_v] = &mut state.dual;
    for vector in 0..state.layout.vectors() {
        let range_u = range_terms::<S, N>(s, params, labels, s.load(&state.offsets[0][vector]));
        let range_v = range_terms::<S, N>(s, params, labels, s.load(&state.offsets[1][vector]));
        let costs = &data.costs()[vector * window..(vector + 1) * window];
        let mut message_u = [s.splat(u16::MAX); N];
        let mut message_v = [s.splat(u16::MAX); N];
        for label_v in 0..labels {
            for label_u in 0..labels {
                let cost = s.load(&costs[label_v * labels + label_u]);
                message_u[label_u] = s.min(message_u[label_u], s.adds(cost, range_v[label_v]));
                message_v[label_v] = s.min(message_v[label_v], s.adds(cost, range_u[label_u]));
            }
        }
        for (message, out) in [(message_u, &mut *to_u), (message_v, &mut *to_v)] {
            let message = normalised::<S, N>(s, labels, message);
            for (label, value) in message.iter().enumerate().take(labels) {
                s.store(&mut out[vector * labels + label], *value);
            }
        }
    }
}

/// `message − min(message)`.
#[inline(always)]
fn normalised<S: Simd, const N: usize>(s: S, labels: usize, mut message: [S::V; N]) -> [S::V; N] {
    let mut minimum = message[0];
    for value in &message[1..labels] {
        minimum = s.min(minimum, *value);
    }
    for value in &mut message[..labels] {
        *value = s.subs(*value, minimum);
    }
    message
}

/// The message over the receiver's labels for the truncated-L1 pairwise cost `min(α|Δ|, d)`, from
/// `h` (the sender's costs over its labels), by a distance transform. `shift` is the receiver's
/// offset minus the sender's, per lane (`i16`). Normalised to minimum 0.
#[inline(always)]
fn truncated_l1_message<S: Simd, const N: usize>(
    s: S,
    params: &GridParams,
    labels: usize,
    mut h: [S::V; N],
    shift: S::V,
) -> [S::V; N] {
    let alpha = s.splat(params.alpha);
    let mut minimum = h[0];
    for label in 1..labels {
        minimum = s.min(minimum, h[label]);
        h[label] = s.min(h[label], s.adds(h[label - 1], alpha));
    }
    for label in (0..labels - 1).rev() {
        h[label] = s.min(h[label], s.adds(h[label + 1], alpha));
    }
    // The receiver's label l sees the sender's label l + shift; past the window the transformed
    // costs grow by α per label. One step moves the lanes that still have to move by one label.
    let mut step = 1usize;
    loop {
        let up = s.greater_i16(shift, s.splat((step - 1) as u16));
        let down = s.greater_i16(s.splat((1 - step as i32) as i16 as u16), shift);
        let moving = s.or(up, down);
        if !s.any(moving) {
            break;
        }
        if step > params.max_shift {
            // Every transformed cost of these lanes is past the truncation: a flat message.
            for value in &mut h[..labels] {
                *value = s.select(moving, s.splat(u16::MAX), *value);
            }
            break;
        }
        let previous = h;
        let beyond_last = s.adds(previous[labels - 1], alpha);
        let beyond_first = s.adds(previous[0], alpha);
        for label in 0..labels {
            let above = if label + 1 < labels {
                previous[label + 1]
            } else {
                beyond_last
            };
            let below = if label > 0 {
                previous[label - 1]
            } else {
                beyond_first
            };
            h[label] = s.select(up, above, s.select(down, below, previous[label]));
        }
        step += 1;
    }
    let ceiling = s.adds(minimum, s.splat(params.truncation));
    for value in &mut h[..labels] {
        *value = s.min(*value, ceiling);
    }
    normalised::<S, N>(s, labels, h)
}

/// The lanes of block `block` at position `position` that are pixels.
/// The lanes of block `block` whose row `r` has `(r + row_offset) mod band_rows = 0` and
/// `0 < r + row_offset < height`: rows that start a band (`row_offset = 0`) or end one (1).
#[inline(always)]
fn seam_lanes<S: Simd>(
    s: S,
    params: &GridParams,
    layout: Layout,
    block: usize,
    row_offset: usize,
) -> S::V {
    let mut mask = Lanes::default();
    for (lane, value) in mask.0.iter_mut().enumerate() {
        let row = block * LANES + lane + row_offset;
        if row > 0 && row < layout.height && row % params.band_rows == 0 {
            *value = u16::MAX;
        }
    }
    s.load(&mask)
}

#[inline(always)]
fn valid_lanes<S: Simd>(s: S, layout: Layout, block: usize, position: usize) -> S::V {
    let lane_index = s.load(&LANE_INDEX);
    let x = s.sub_i16(s.splat(position as u16), lane_index);
    let rows_left = layout.height - block * LANES;
    let row_valid = s.greater_i16(s.splat(rows_left.min(LANES) as u16), lane_index);
    s.and(
        row_valid,
        s.and(
            s.greater_i16(x, s.splat(u16::MAX)),
            s.greater_i16(s.splat(layout.width as u16), x),
        ),
    )
}

/// The inter-layer message from layer `plane` (computed from `outgoing = base − dual_in`) into
/// `dual_other` at `vector`: from u to v, `min_u (cost + outgoing_u)` per v; from v to u,
/// `min_v (cost + outgoing_v)` per u.
#[inline(always)]
fn send_dual<S: Simd, const N: usize>(
    s: S,
    labels: usize,
    plane: usize,
    costs: &[Lanes],
    outgoing: [S::V; N],
    out: &mut [Lanes],
) {
    let mut message = [s.splat(u16::MAX); N];
    for label_v in 0..labels {
        for label_u in 0..labels {
            let cost = s.load(&costs[label_v * labels + label_u]);
            if plane == 0 {
                message[label_v] = s.min(message[label_v], s.adds(cost, outgoing[label_u]));
            } else {
                message[label_u] = s.min(message[label_u], s.adds(cost, outgoing[label_v]));
            }
        }
    }
    let message = normalised::<S, N>(s, labels, message);
    for (label, value) in message.iter().enumerate().take(labels) {
        s.store(&mut out[label], *value);
    }
}

/// One forward sweep over layer `plane`: every pixel, in raster order, sends to its right and lower
/// neighbours (and, with `update_dual`, to the other layer).
#[inline(always)]
fn sweep_forward<S: Simd, const N: usize>(
    s: S,
    params: &GridParams,
    data: &CostVolume,
    plane: usize,
    update_dual: bool,
    state: &mut GridState,
) {
    let labels = label_count::<N>(params.labels);
    let layout = state.layout;
    let positions = layout.positions;
    let window = labels * labels;
    let zero = s.splat(0);
    let offsets = &state.offsets[plane];
    let [dual_u, dual_v] = &mut state.dual;
    let (dual_this, dual_other) = if plane == 0 {
        (&*dual_u, dual_v)
    } else {
        (&*dual_v, dual_u)
    };
    let spatial = &mut state.spatial[plane];
    let [halo_even, halo_odd] = &mut state.halo;
    let all_costs = data.costs();
    for block in 0..layout.blocks {
        // The block above wrote its messages into the lanes of this block's first row.
        let (halo_in, halo_out) = if block % 2 == 0 {
            (&*halo_odd, &mut *halo_even)
        } else {
            (&*halo_even, &mut *halo_odd)
        };
        let mut from_left = [zero; N];
        let mut sent_down = [zero; N];
        // First rows of bands keep their message from above until the seams are sent.
        let band_starts = seam_lanes(s, params, layout, block, 0);
        let banded = s.any(band_starts);
        for position in 0..positions {
            let vector = block * positions + position;
            let offset = s.load(&offsets[vector]);
            let cell = &mut spatial[vector * 4 * labels..(vector + 1) * 4 * labels];
            let mut from_above = [zero; N];
            let mut base = range_terms::<S, N>(s, params, labels, offset);
            let mut from_right = [zero; N];
            let mut from_below = [zero; N];
            let mut dual_in = [zero; N];
            for (label, value) in dual_in.iter_mut().enumerate().take(labels) {
                *value = s.load(&dual_this[vector * labels + label]);
            }
            for label in 0..labels {
                let fill = if block > 0 && position + LANES - 1 < positions {
                    s.load(&halo_in[(position + LANES - 1) * labels + label])
                } else {
                    zero
                };
                from_above[label] = s.lanes_up(sent_down[label], fill);
                if banded {
                    let kept = s.load(&cell[FROM_ABOVE * labels + label]);
                    from_above[label] = s.select(band_starts, kept, from_above[label]);
                }
                from_right[label] = s.load(&cell[FROM_RIGHT * labels + label]);
                from_below[label] = s.load(&cell[FROM_BELOW * labels + label]);
                s.store(&mut cell[FROM_LEFT * labels + label], from_left[label]);
                s.store(&mut cell[FROM_ABOVE * labels + label], from_above[label]);
                base[label] = s.adds(
                    s.adds(
                        s.adds(base[label], dual_in[label]),
                        s.adds(from_left[label], from_above[label]),
                    ),
                    s.adds(from_right[label], from_below[label]),
                );
            }
            let valid = valid_lanes(s, layout, block, position);
            // Right: the receiver is the next position, same lane.
            let next_offset = if position + 1 < positions {
                s.load(&offsets[vector + 1])
            } else {
                offset
            };
            let mut h = [zero; N];
            for label in 0..labels {
                h[label] = s.subs(base[label], from_right[label]);
            }
            let to_right =
                truncated_l1_message::<S, N>(s, params, labels, h, s.sub_i16(next_offset, offset));
            // Down: the receiver is the next position, next lane (lane 15: the next block's lane 0).
            let below_fill = if block + 1 < layout.blocks && position + 1 >= LANES {
                s.load(&offsets[(block + 1) * positions + position + 1 - LANES])
            } else {
                zero
            };
            let below_offset = s.lanes_down(next_offset, below_fill);
            let mut h = [zero; N];
            for label in 0..labels {
                h[label] = s.subs(base[label], from_below[label]);
            }
            sent_down =
                truncated_l1_message::<S, N>(s, params, labels, h, s.sub_i16(below_offset, offset));
            for label in 0..labels {
                from_left[label] = s.and(to_right[label], valid);
                s.store(&mut halo_out[position * labels + label], sent_down[label]);
            }
            if update_dual {
                let mut outgoing = [zero; N];
                for label in 0..labels {
                    outgoing[label] = s.subs(base[label], dual_in[label]);
                }
                send_dual::<S, N>(
                    s,
                    labels,
                    plane,
                    &all_costs[vector * window..(vector + 1) * window],
                    outgoing,
                    &mut dual_other[vector * labels..(vector + 1) * labels],
                );
            }
        }
    }
}

/// One backward sweep over layer `plane`: every pixel, in reverse raster order, sends to its left
/// and upper neighbours (and, with `update_dual`, to the other layer).
#[inline(always)]
fn sweep_backward<S: Simd, const N: usize>(
    s: S,
    params: &GridParams,
    data: &CostVolume,
    plane: usize,
    update_dual: bool,
    state: &mut GridState,
) {
    let labels = label_count::<N>(params.labels);
    let layout = state.layout;
    let positions = layout.positions;
    let window = labels * labels;
    let zero = s.splat(0);
    let offsets = &state.offsets[plane];
    let [dual_u, dual_v] = &mut state.dual;
    let (dual_this, dual_other) = if plane == 0 {
        (&*dual_u, dual_v)
    } else {
        (&*dual_v, dual_u)
    };
    let spatial = &mut state.spatial[plane];
    let [halo_even, halo_odd] = &mut state.halo;
    let all_costs = data.costs();
    for block in (0..layout.blocks).rev() {
        // The block below wrote its messages into the lanes of this block's last row.
        let (halo_in, halo_out) = if block % 2 == 0 {
            (&*halo_odd, &mut *halo_even)
        } else {
            (&*halo_even, &mut *halo_odd)
        };
        let mut from_right = [zero; N];
        let mut sent_up = [zero; N];
        // Last rows of bands keep their message from below until the seams are sent.
        let band_ends = seam_lanes(s, params, layout, block, 1);
        let banded = s.any(band_ends);
        for position in (0..positions).rev() {
            let vector = block * positions + position;
            let offset = s.load(&offsets[vector]);
            let cell = &mut spatial[vector * 4 * labels..(vector + 1) * 4 * labels];
            let mut from_below = [zero; N];
            let mut base = range_terms::<S, N>(s, params, labels, offset);
            let mut from_left = [zero; N];
            let mut from_above = [zero; N];
            let mut dual_in = [zero; N];
            for (label, value) in dual_in.iter_mut().enumerate().take(labels) {
                *value = s.load(&dual_this[vector * labels + label]);
            }
            for label in 0..labels {
                let fill = if block + 1 < layout.blocks && position + 1 >= LANES {
                    s.load(&halo_in[(position + 1 - LANES) * labels + label])
                } else {
                    zero
                };
                from_below[label] = s.lanes_down(sent_up[label], fill);
                if banded {
                    let kept = s.load(&cell[FROM_BELOW * labels + label]);
                    from_below[label] = s.select(band_ends, kept, from_below[label]);
                }
                from_left[label] = s.load(&cell[FROM_LEFT * labels + label]);
                from_above[label] = s.load(&cell[FROM_ABOVE * labels + label]);
                s.store(&mut cell[FROM_RIGHT * labels + label], from_right[label]);
                s.store(&mut cell[FROM_BELOW * labels + label], from_below[label]);
                base[label] = s.adds(
                    s.adds(
                        s.adds(base[label], dual_in[label]),
                        s.adds(from_left[label], from_above[label]),
                    ),
                    s.adds(from_right[label], from_below[label]),
                );
            }
            let valid = valid_lanes(s, layout, block, position);
            // Left: the receiver is the previous position, same lane.
            let previous_offset = if position > 0 {
                s.load(&offsets[vector - 1])
            } else {
                offset
            };
            let mut h = [zero; N];
            for label in 0..labels {
                h[label] = s.subs(base[label], from_left[label]);
            }
            let to_left = truncated_l1_message::<S, N>(
                s,
                params,
                labels,
                h,
                s.sub_i16(previous_offset, offset),
            );
            // Up: the receiver is the previous position, previous lane (lane 0: the previous
            // block's lane 15).
            let above_fill = if block > 0 && position + LANES - 1 < positions {
                s.load(&offsets[(block - 1) * positions + position + LANES - 1])
            } else {
                zero
            };
            let above_offset = s.lanes_up(previous_offset, above_fill);
            let mut h = [zero; N];
            for label in 0..labels {
                h[label] = s.subs(base[label], from_above[label]);
            }
            let to_above =
                truncated_l1_message::<S, N>(s, params, labels, h, s.sub_i16(above_offset, offset));
            for label in 0..labels {
                from_right[label] = s.and(to_left[label], valid);
                sent_up[label] = s.and(to_above[label], valid);
                s.store(&mut halo_out[position * labels + label], sent_up[label]);
            }
            if update_dual {
                let mut outgoing = [zero; N];
                for label in 0..labels {
                    outgoing[label] = s.subs(base[label], dual_in[label]);
                }
                send_dual::<S, N>(
                    s,
                    labels,
                    plane,
                    &all_costs[vector * window..(vector + 1) * window],
                    outgoing,
                    &mut dual_other[vector * labels..(vector + 1) * labels],
                );
            }
        }
    }
}

/// The messages a banded sweep left out: from every pixel of the last row of each band down
/// (forward) or of the first row of the next band up (backward), from the state after the sweep.
/// Plain Rust on one row at a time (the same for every instruction set).
fn send_across_seams(params: &GridParams, plane: usize, forward: bool, state: &mut GridState) {
    let layout = state.layout;
    let labels = params.labels;
    let mut seam = params.band_rows;
    while seam < layout.height {
        let (sender_row, receiver_row) = if forward {
            (seam - 1, seam)
        } else {
            (seam, seam - 1)
        };
        let (slot_at_receiver, excluded_slot) = if forward {
            (FROM_ABOVE, FROM_BELOW)
        } else {
            (FROM_BELOW, FROM_ABOVE)
        };
        let mut h = [0u16; MAX_LABELS];
        for x in 0..layout.width {
            let (sender, sender_lane) = layout.locate(x, sender_row);
            let (receiver, receiver_lane) = layout.locate(x, receiver_row);
            let offset = state.offsets[plane][sender].0[sender_lane] as i16 as i32;
            let receiver_offset = state.offsets[plane][receiver].0[receiver_lane] as i16 as i32;
            for (label, value) in h[..labels].iter_mut().enumerate() {
                let mut sum = range_term(params, offset + label as i32 - params.radius as i32)
                    .saturating_add(state.dual[plane][sender * labels + label].0[sender_lane]);
                for slot in (0..4).filter(|&slot| slot != excluded_slot) {
                    sum = sum.saturating_add(
                        state.spatial[plane][(sender * 4 + slot) * labels + label].0[sender_lane],
                    );
                }
                *value = sum;
            }
            let message = scalar_message(params, &mut h[..labels], receiver_offset - offset);
            for (label, &value) in message[..labels].iter().enumerate() {
                state.spatial[plane][(receiver * 4 + slot_at_receiver) * labels + label].0
                    [receiver_lane] = value;
            }
        }
        seam += params.band_rows;
    }
}

/// The range term `round(γ|flow|)` of one label, as [`range_terms`] computes it per lane.
fn range_term(params: &GridParams, flow: i32) -> u16 {
    let magnitude = (flow.unsigned_abs().min(MAX_RANGE_FLOW as u32) * 16) as i32;
    ((magnitude * params.gamma_q15 as i32 + (1 << 14)) >> 15) as u16
}

/// [`truncated_l1_message`] for one pixel (`h` is overwritten by its distance transform).
fn scalar_message(params: &GridParams, h: &mut [u16], shift: i32) -> [u16; MAX_LABELS] {
    let labels = h.len();
    let minimum = *h.iter().min().expect("labels");
    for label in 1..labels {
        h[label] = h[label].min(h[label - 1].saturating_add(params.alpha));
    }
    for label in (0..labels - 1).rev() {
        h[label] = h[label].min(h[label + 1].saturating_add(params.alpha));
    }
    let ceiling = minimum.saturating_add(params.truncation);
    let mut message = [0u16; MAX_LABELS];
    for (label, value) in message[..labels].iter_mut().enumerate() {
        let source = label as i32 + shift;
        let transformed = if shift.unsigned_abs() as usize > params.max_shift {
            u16::MAX
        } else if source < 0 {
            (0..-source).fold(h[0], |value, _| value.saturating_add(params.alpha))
        } else if source >= labels as i32 {
            (0..source - labels as i32 + 1)
                .fold(h[labels - 1], |value, _| value.saturating_add(params.alpha))
        } else {
            h[source as usize]
        };
        *value = transformed.min(ceiling);
    }
    let least = *message[..labels].iter().min().expect("labels");
    for value in &mut message[..labels] {
        *value -= least;
    }
    message
}

/// Belief of each layer (range term + inter-layer message + the four spatial messages), its first
/// minimum, written row-major.
#[inline(always)]
fn choose<S: Simd, const N: usize>(
    s: S,
    params: &GridParams,
    state: &GridState,
    labels_out: &mut [Vec<u8>; 2],
    mut beliefs_out: Option<&mut [Vec<f32>; 2]>,
) {
    let labels = label_count::<N>(params.labels);
    let layout = state.layout;
    let pixel_count = layout.width * layout.height;
    for plane in 0..2 {
        labels_out[plane].clear();
        labels_out[plane].resize(pixel_count, 0);
        if let Some(beliefs) = beliefs_out.as_deref_mut() {
            beliefs[plane].clear();
            beliefs[plane].resize(pixel_count * labels, 0.0);
        }
        let mut chosen = vec![Lanes::default(); layout.vectors()];
        let mut belief_lanes = match beliefs_out {
            Some(_) => vec![Lanes::default(); layout.vectors() * labels],
            None => Vec::new(),
        };
        for (vector, chosen) in chosen.iter_mut().enumerate() {
            let base =
                range_terms::<S, N>(s, params, labels, s.load(&state.offsets[plane][vector]));
            let cell = &state.spatial[plane][vector * 4 * labels..(vector + 1) * 4 * labels];
            let mut best = s.splat(u16::MAX);
            let mut best_label = s.splat(0);
            for label in 0..labels {
                let mut belief = s.adds(
                    base[label],
                    s.load(&state.dual[plane][vector * labels + label]),
                );
                for slot in 0..4 {
                    belief = s.adds(belief, s.load(&cell[slot * labels + label]));
                }
                if !belief_lanes.is_empty() {
                    s.store(&mut belief_lanes[vector * labels + label], belief);
                }
                let better = if label == 0 {
                    s.splat(u16::MAX)
                } else {
                    s.less_u16(belief, best)
                };
                best = s.min(best, belief);
                best_label = s.select(better, s.splat(label as u16), best_label);
            }
            s.store(chosen, best_label);
        }
        let out = &mut labels_out[plane];
        layout.for_each_pixel(|x, y, vector, lane| {
            out[y * layout.width + x] = chosen[vector].0[lane] as u8;
        });
        if let Some(beliefs) = beliefs_out.as_deref_mut() {
            let out = &mut beliefs[plane];
            layout.for_each_pixel(|x, y, vector, lane| {
                let pixel = y * layout.width + x;
                for label in 0..labels {
                    out[pixel * labels + label] =
                        belief_lanes[vector * labels + label].0[lane] as f32;
                }
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reference_message(params: &GridParams, h: &[u16], shift: i32) -> Vec<u16> {
        let mut h = h.to_vec();
        scalar_message(params, &mut h, shift)[..params.labels].to_vec()
    }

    /// Belief propagation on one grid pixel by pixel in raster order, as the reference's code is
    /// written, with the kernels' integer arithmetic: the labels it chooses.
    fn reference_solve(
        params: &GridParams,
        width: usize,
        height: usize,
        offsets: [&[i32]; 2],
        costs: &[u16],
        iterations: usize,
    ) -> [Vec<u8>; 2] {
        let labels = params.labels;
        let window = labels * labels;
        let pixels = width * height;
        let range = |plane: usize, pixel: usize, label: usize| {
            range_term(
                params,
                offsets[plane][pixel] + label as i32 - params.radius as i32,
            )
        };
        let mut spatial = [
            vec![0u16; pixels * 4 * labels],
            vec![0u16; pixels * 4 * labels],
        ];
        let mut dual = [vec![0u16; pixels * labels], vec![0u16; pixels * labels]];
        for pixel in 0..pixels {
            let cost = |u: usize, v: usize| costs[pixel * window + v * labels + u];
            let to_u: Vec<u16> = (0..labels)
                .map(|u| {
                    (0..labels)
                        .map(|v| cost(u, v).saturating_add(range(1, pixel, v)))
                        .min()
                        .unwrap()
                })
                .collect();
            let to_v: Vec<u16> = (0..labels)
                .map(|v| {
                    (0..labels)
                        .map(|u| cost(u, v).saturating_add(range(0, pixel, u)))
                        .min()
                        .unwrap()
                })
                .collect();
            for (plane, message) in [to_u, to_v].into_iter().enumerate() {
                let least = *message.iter().min().unwrap();
                for (label, value) in message.iter().enumerate() {
                    dual[plane][pixel * labels + label] = value - least;
                }
            }
        }
        for iteration in 0..iterations {
            let plane = iteration % 2;
            let forward = iteration % 4 < 2;
            let update_dual = iteration % 8 < 4;
            for step in 0..pixels {
                let pixel = if forward { step } else { pixels - 1 - step };
                let (x, y) = (pixel % width, pixel / width);
                let incoming = |slot: usize, label: usize, spatial: &[u16]| {
                    spatial[(pixel * 4 + slot) * labels + label]
                };
                let base: Vec<u16> = (0..labels)
                    .map(|label| {
                        (0..4).fold(
                            range(plane, pixel, label)
                                .saturating_add(dual[plane][pixel * labels + label]),
                            |sum, slot| sum.saturating_add(incoming(slot, label, &spatial[plane])),
                        )
                    })
                    .collect();
                let neighbours = if forward {
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
                for (exists, neighbour, slot_at_neighbour, excluded) in neighbours {
                    // No message crosses a band's seam during the sweep.
                    let crosses_seam = neighbour / width != y
                        && (y.max(neighbour / width)) % params.band_rows == 0;
                    if !exists || crosses_seam {
                        continue;
                    }
                    let h: Vec<u16> = (0..labels)
                        .map(|label| {
                            base[label].saturating_sub(incoming(excluded, label, &spatial[plane]))
                        })
                        .collect();
                    let shift = offsets[plane][neighbour] - offsets[plane][pixel];
                    let message = reference_message(params, &h, shift);
                    spatial[plane][(neighbour * 4 + slot_at_neighbour) * labels..][..labels]
                        .copy_from_slice(&message);
                }
                if update_dual {
                    let outgoing: Vec<u16> = (0..labels)
                        .map(|label| {
                            base[label].saturating_sub(dual[plane][pixel * labels + label])
                        })
                        .collect();
                    let cost = |u: usize, v: usize| costs[pixel * window + v * labels + u];
                    let message: Vec<u16> = (0..labels)
                        .map(|other| {
                            (0..labels)
                                .map(|this| {
                                    let (u, v) = if plane == 0 {
                                        (this, other)
                                    } else {
                                        (other, this)
                                    };
                                    cost(u, v).saturating_add(outgoing[this])
                                })
                                .min()
                                .unwrap()
                        })
                        .collect();
                    let least = *message.iter().min().unwrap();
                    for (label, value) in message.iter().enumerate() {
                        dual[1 - plane][pixel * labels + label] = value - least;
                    }
                }
            }
            // The seams, from the state the sweep left.
            let mut seam = params.band_rows;
            while seam < height {
                let (sender_row, receiver_row, slot_at_receiver, excluded) = if forward {
                    (seam - 1, seam, FROM_ABOVE, FROM_BELOW)
                } else {
                    (seam, seam - 1, FROM_BELOW, FROM_ABOVE)
                };
                for x in 0..width {
                    let (pixel, receiver) = (sender_row * width + x, receiver_row * width + x);
                    let h: Vec<u16> = (0..labels)
                        .map(|label| {
                            (0..4).filter(|&slot| slot != excluded).fold(
                                range(plane, pixel, label)
                                    .saturating_add(dual[plane][pixel * labels + label]),
                                |sum, slot| {
                                    sum.saturating_add(
                                        spatial[plane][(pixel * 4 + slot) * labels + label],
                                    )
                                },
                            )
                        })
                        .collect();
                    let shift = offsets[plane][receiver] - offsets[plane][pixel];
                    let message = reference_message(params, &h, shift);
                    spatial[plane][(receiver * 4 + slot_at_receiver) * labels..][..labels]
                        .copy_from_slice(&message);
                }
                seam += params.band_rows;
            }
        }
        std::array::from_fn(|plane| {
            (0..pixels)
                .map(|pixel| {
                    let belief = |label: usize| {
                        (0..4).fold(
                            range(plane, pixel, label)
                                .saturating_add(dual[plane][pixel * labels + label]),
                            |sum, slot| {
                                sum.saturating_add(
                                    spatial[plane][(pixel * 4 + slot) * labels + label],
                                )
                            },
                        )
                    };
                    (0..labels)
                        .min_by_key(|&label| (belief(label), label))
                        .unwrap() as u8
                })
                .collect()
        })
    }

    /// A small problem with costs that favour a smooth flow, noise, and offsets that jump.
    fn test_problem(
        width: usize,
        height: usize,
        labels: usize,
    ) -> ([Vec<i32>; 2], CostVolume, Vec<u16>) {
        let hash = |a: usize, b: usize| ((a * 2_654_435_761 + b * 40_503) >> 7) % 1000;
        let offsets: [Vec<i32>; 2] = std::array::from_fn(|plane| {
            (0..width * height)
                .map(|pixel| {
                    let (x, y) = (pixel % width, pixel / width);
                    (x / 5 + plane * y / 7) as i32 - 3 + (hash(pixel, plane) % 10 == 0) as i32 * 4
                })
                .collect()
        });
        let window = labels * labels;
        let costs: Vec<u16> = (0..width * height * window)
            .map(|index| {
                let (pixel, entry) = (index / window, index % window);
                let (u, v) = (entry % labels, entry / labels);
                let (x, y) = (pixel % width, pixel / width);
                let ideal = ((x + y) % labels, (x * 3 / 4) % labels);
                let distance = u.abs_diff(ideal.0) + v.abs_diff(ideal.1);
                (distance * 700 + hash(index, 1)) as u16
            })
            .collect();
        let layout = Layout::new(width, height);
        let mut volume = CostVolume::default();
        volume.reset(layout, labels);
        let all = volume.costs_mut();
        layout.for_each_pixel(|x, y, vector, lane| {
            for entry in 0..window {
                all[vector * window + entry].0[lane] = costs[(y * width + x) * window + entry];
            }
        });
        (offsets, volume, costs)
    }

    #[test]
    fn wavefront_sweeps_equal_raster_order() {
        for (width, height, labels, specialised, bands) in [
            (37, 21, 5, true, 1),
            (37, 21, 5, true, 2),
            (9, 16, 7, true, 3),
            (20, 35, 3, false, 2),
            (5, 40, 5, true, 5),
            (11, 64, 5, true, 2),
        ] {
            let (offsets, volume, costs) = test_problem(width, height, labels);
            let problem = LevelProblem {
                radius: labels / 2,
                labels,
                flow_magnitude_weight: 9.5,
                smoothness_weight: 300.0,
                smoothness_truncation: 2000.0,
                offsets: [&offsets[0], &offsets[1]],
                data: &volume,
                bands,
            };
            let params = GridParams::new(&problem, 0, height);
            let expected = reference_solve(&params, width, height, problem.offsets, &costs, 10);
            for isa in [Isa::detect(), Isa::Portable] {
                let mut state = GridState::default();
                solve_with_multigrid(isa, &problem, 10, 4, specialised, &mut [], &mut state);
                let mut labels_out = [Vec::new(), Vec::new()];
                choose_labels(isa, &problem, specialised, &state, &mut labels_out, None);
                assert_eq!(
                    labels_out, expected,
                    "{width}x{height}, {labels} labels, {bands} bands, {isa:?}"
                );
            }
        }
    }

    #[test]
    fn multigrid_grids_sum_blocks_and_start_from_them() {
        let (width, height, labels) = (23, 37, 3);
        let (offsets, fine, costs) = test_problem(width, height, labels);
        let window = labels * labels;
        let coarse_layout = Layout::new(width.div_ceil(2), height.div_ceil(2));
        let mut coarse = CostVolume::default();
        coarse.reset(coarse_layout, labels);
        let mut coarse_state = GridState {
            layout: coarse_layout,
            ..Default::default()
        };
        for plane in 0..2 {
            grown(
                &mut coarse_state.spatial[plane],
                coarse_layout.vectors() * 4 * labels,
            );
            grown(
                &mut coarse_state.dual[plane],
                coarse_layout.vectors() * labels,
            );
        }
        // Coarse messages that name their pixel, slot and label.
        let code = |x: usize, y: usize, entry: usize| (x * 7 + y * 131 + entry * 3) as u16;
        coarse_layout.for_each_pixel(|x, y, vector, lane| {
            for plane in 0..2 {
                for entry in 0..4 * labels {
                    coarse_state.spatial[plane][vector * 4 * labels + entry].0[lane] =
                        code(x, y, entry);
                }
                for entry in 0..labels {
                    coarse_state.dual[plane][vector * labels + entry].0[lane] =
                        code(x, y, entry + 50);
                }
            }
        });
        let mut state = GridState {
            layout: fine.layout,
            ..Default::default()
        };
        for plane in 0..2 {
            grown(
                &mut state.spatial[plane],
                fine.layout.vectors() * 4 * labels,
            );
            grown(&mut state.dual[plane], fine.layout.vectors() * labels);
        }
        for isa in [Isa::detect(), Isa::Portable] {
            run_kernel(isa, labels, true, Kernel::CoarseData(&fine, &mut coarse));
            for coarse_y in 0..coarse_layout.height {
                for coarse_x in 0..coarse_layout.width {
                    for entry in 0..window {
                        let mut sum = 0u32;
                        for y in 2 * coarse_y..(2 * coarse_y + 2).min(height) {
                            for x in 2 * coarse_x..(2 * coarse_x + 2).min(width) {
                                sum += costs[(y * width + x) * window + entry] as u32;
                            }
                        }
                        let (u, v) = (entry % labels, entry / labels);
                        assert_eq!(
                            coarse.cost(coarse_x, coarse_y, u, v) as u32,
                            (sum + 2) / 4,
                            "({coarse_x}, {coarse_y}) {entry}"
                        );
                    }
                }
            }
            match isa {
                #[cfg(target_arch = "x86_64")]
                Isa::Avx2(avx2) => start_from_coarse(avx2, labels, &coarse_state, &mut state),
                Isa::Portable => start_from_coarse(Portable, labels, &coarse_state, &mut state),
            }
            fine.layout.for_each_pixel(|x, y, vector, lane| {
                for plane in 0..2 {
                    for entry in 0..4 * labels {
                        assert_eq!(
                            state.spatial[plane][vector * 4 * labels + entry].0[lane],
                            4 * code(x / 2, y / 2, entry),
                            "({x}, {y}) {entry}"
                        );
                    }
                    for entry in 0..labels {
                        assert_eq!(
                            state.dual[plane][vector * labels + entry].0[lane],
                            4 * code(x / 2, y / 2, entry + 50)
                        );
                    }
                }
            });
        }
        let _ = offsets;
    }

    #[test]
    fn distance_transform_matches_brute_force() {
        let (alpha, truncation) = (3u16, 7u16);
        let costs = [5u16, 1, 9, 0, 12];
        let params = GridParams {
            labels: 5,
            radius: 2,
            alpha,
            truncation,
            gamma_q15: 0,
            max_shift: 5 + 3,
            band_rows: 100,
        };
        let s = Portable;
        // One lane per shift, -7..=7 (past max_shift too), plus a lane of saturated costs.
        let shifts: [i16; LANES] = std::array::from_fn(|lane| lane as i16 - 7);
        let h: [Lanes; 5] = std::array::from_fn(|label| {
            Lanes(std::array::from_fn(|lane| {
                if lane == 15 {
                    u16::MAX
                } else {
                    costs[label]
                }
            }))
        });
        let message = truncated_l1_message::<Portable, 5>(
            s,
            &params,
            5,
            h,
            Lanes(shifts.map(|shift| shift as u16)),
        );
        for (lane, &shift) in shifts.iter().enumerate().take(15) {
            let brute: Vec<u32> = (0..5)
                .map(|receiver| {
                    costs
                        .iter()
                        .enumerate()
                        .map(|(sender, &cost)| {
                            let difference =
                                (receiver + shift as i32 - sender as i32).unsigned_abs();
                            cost as u32 + (alpha as u32 * difference).min(truncation as u32)
                        })
                        .min()
                        .unwrap()
                })
                .collect();
            let minimum = *brute.iter().min().unwrap();
            for (label, want) in brute.iter().enumerate() {
                assert_eq!(
                    message[label].0[lane] as u32,
                    want - minimum,
                    "shift {shift}, label {label}"
                );
            }
        }
        assert!(message.iter().all(|value| value.0[15] == 0));
        for (lane, &shift) in shifts.iter().enumerate() {
            let mut h: Vec<u16> = (0..5)
                .map(|label| if lane == 15 { u16::MAX } else { costs[label] })
                .collect();
            let scalar = scalar_message(&params, &mut h, shift as i32);
            for label in 0..5 {
                assert_eq!(scalar[label], message[label].0[lane], "shift {shift}");
            }
        }
    }
}
