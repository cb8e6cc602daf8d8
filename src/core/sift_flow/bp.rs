//! Belief propagation of SIFT flow on one level: multigrid start, sweeps over the two flow layers
//! (optionally in bands of rows), truncated-L1 messages by distance transforms, and the beliefs.

use rayon::prelude::*;

use super::config::MAX_LABELS;

/// One coarser grid of multigrid belief propagation: pixels are 2×2 blocks of the finer grid.
#[derive(Debug, Default)]
pub(super) struct MultigridGrid {
    width: usize,
    height: usize,
    offsets: [Vec<i32>; 2],
    data_cost: Vec<f32>,
    spatial_messages: [Vec<f32>; 2],
    dual_messages: [Vec<f32>; 2],
}

/// One level's discrete problem: labels `0..labels` of layer `plane` at pixel `p` stand for the
/// flow `offsets[plane][p] + label - radius`.
#[derive(Clone, Copy)]
pub(super) struct LevelProblem<'a> {
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) radius: usize,
    pub(super) labels: usize,
    pub(super) flow_magnitude_weight: f32,
    pub(super) smoothness_weight: f32,
    pub(super) smoothness_truncation: f32,
    pub(super) offsets: [&'a [i32]; 2],
    /// Per pixel `labels × labels` costs, index `label_v · labels + label_u`.
    pub(super) data_cost: &'a [f32],
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
pub(super) fn solve_with_multigrid(
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
pub(super) fn compute_beliefs(
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
}
