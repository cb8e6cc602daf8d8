//! The data term of SIFT flow: the matching cost of every source pixel against every candidate in
//! its search window, with the reference's median cost for candidates outside the target. Costs are
//! whole numbers (sums of absolute byte differences, at most 128 · 255), kept as `u16` in the
//! belief propagation's layout.

use rayon::prelude::*;

#[cfg(target_arch = "x86_64")]
use super::kernels::{l1_row_avx2, l1_row_sse2, l1_window_avx2};
use super::kernels::{l1_row_portable, resolve_kernel};
use super::layout::{CostVolume, Layout};
use super::simd::LANES;
use super::L1Kernel;
use crate::core::dense_sift::{DenseSiftImage, DESCRIPTOR_LEN};

/// The bin width of the matching-cost histogram used for the median (cost units), and the
/// reference's bin count (the last bin takes every larger cost; no cost reaches it: 128 · 255 / 32
/// = 1020).
const COST_HISTOGRAM_BIN: u16 = 32;
const COST_HISTOGRAM_BINS: usize = 1100;
/// Bins of the histogram as counted: one per value of `cost / 32`, so that counting needs no
/// branch; [`OUTSIDE_COST`] falls in the last, which is not counted.
const COUNTED_BINS: usize = (u16::MAX / COST_HISTOGRAM_BIN) as usize + 1;

/// Marks a candidate outside the target (or on an invalid target pixel) until the median is known
/// (real costs are at most 128 · 255).
const OUTSIDE_COST: u16 = u16::MAX;

struct DataRowContext<'a> {
    source: &'a DenseSiftImage,
    source_mask: Option<&'a [bool]>,
    target: &'a DenseSiftImage,
    target_mask: Option<&'a [bool]>,
    offsets: [&'a [i32]; 2],
    radius: usize,
}

/// The costs of pixel `(x, y)`, index `label_v · labels + label_u`.
#[inline(always)]
fn fill_pixel(
    context: &DataRowContext,
    x: usize,
    y: usize,
    costs: &mut [u16],
    distances: impl Fn(&[u8], &[u8], &mut [u16]),
    window_distances: Option<WindowKernel>,
) {
    let labels = 2 * context.radius + 1;
    let width = context.source.width_px;
    let pixel = y * width + x;
    if context.source_mask.is_some_and(|mask| !mask[pixel]) {
        costs.fill(0);
        return;
    }
    let (target_width, target_height) = (
        context.target.width_px as isize,
        context.target.height_px as isize,
    );
    let descriptor = context.source.descriptor(pixel);
    let start_x = x as isize + context.offsets[0][pixel] as isize - context.radius as isize;
    let start_y = y as isize + context.offsets[1][pixel] as isize - context.radius as isize;
    if let Some(window_distances) = window_distances {
        let inside = start_x >= 0
            && start_y >= 0
            && start_x + labels as isize <= target_width
            && start_y + labels as isize <= target_height;
        if inside {
            let row_len = target_width as usize * DESCRIPTOR_LEN;
            let first = start_y as usize * row_len + start_x as usize * DESCRIPTOR_LEN;
            window_distances(
                descriptor,
                &context.target.descriptors,
                first,
                row_len,
                labels,
                costs,
            );
            if let Some(mask) = context.target_mask {
                let first_target = start_y as usize * target_width as usize + start_x as usize;
                for (label_v, cost_row) in costs.chunks_exact_mut(labels).enumerate() {
                    let row = &mask[first_target + label_v * target_width as usize..][..labels];
                    for (cost, &valid) in cost_row.iter_mut().zip(row) {
                        if !valid {
                            *cost = OUTSIDE_COST;
                        }
                    }
                }
            }
            return;
        }
    }
    // Candidates inside the target: label_u in first..last.
    let first = (-start_x).clamp(0, labels as isize) as usize;
    let last = (target_width - start_x).clamp(first as isize, labels as isize) as usize;
    for (label_v, cost_row) in costs.chunks_exact_mut(labels).enumerate() {
        let target_y = start_y + label_v as isize;
        if target_y < 0 || target_y >= target_height || first == last {
            cost_row.fill(OUTSIDE_COST);
            continue;
        }
        cost_row[..first].fill(OUTSIDE_COST);
        cost_row[last..].fill(OUTSIDE_COST);
        let first_target =
            target_y as usize * target_width as usize + (start_x + first as isize) as usize;
        distances(
            descriptor,
            &context.target.descriptors
                [first_target * DESCRIPTOR_LEN..(first_target + last - first) * DESCRIPTOR_LEN],
            &mut cost_row[first..last],
        );
        if let Some(mask) = context.target_mask {
            for (target, cost) in (first_target..).zip(&mut cost_row[first..last]) {
                if !mask[target] {
                    *cost = OUTSIDE_COST;
                }
            }
        }
    }
}

/// One block of 16 rows into its part of the volume; returns the histogram of the sampled costs.
#[inline(always)]
fn fill_block(
    context: &DataRowContext,
    layout: Layout,
    block: usize,
    out: &mut [super::simd::Lanes],
    distances: impl Fn(&[u8], &[u8], &mut [u16]) + Copy,
    window_distances: Option<WindowKernel>,
) -> Box<[u32; COUNTED_BINS]> {
    let labels = 2 * context.radius + 1;
    let window = labels * labels;
    let mut histogram = Box::new([0u32; COUNTED_BINS]);
    let mut costs = [0u16; super::config::MAX_LABELS * super::config::MAX_LABELS];
    let costs = &mut costs[..window];
    for lane in 0..LANES.min(layout.height - block * LANES) {
        let y = block * LANES + lane;
        for x in 0..layout.width {
            fill_pixel(context, x, y, costs, distances, window_distances);
            let position = x + lane;
            for (vector, &cost) in out[position * window..(position + 1) * window]
                .iter_mut()
                .zip(costs.iter())
            {
                vector.0[lane] = cost;
            }
            // The reference's median samples every third cost of the row-major volume.
            let first = (y * layout.width + x) * window;
            for &cost in costs.iter().skip((3 - first % 3) % 3).step_by(3) {
                histogram[(cost / COST_HISTOGRAM_BIN) as usize] += 1;
            }
        }
    }
    histogram
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn fill_block_avx2(
    context: &DataRowContext,
    layout: Layout,
    block: usize,
    out: &mut [super::simd::Lanes],
) -> Box<[u32; COUNTED_BINS]> {
    // SAFETY: this function runs only where the CPU has AVX2.
    fill_block(
        context,
        layout,
        block,
        out,
        |source, targets, out| unsafe { l1_row_avx2(source, targets, out) },
        Some(
            |source: &[u8], targets: &[u8], first, row_len, labels, out: &mut [u16]| unsafe {
                l1_window_avx2(source, targets, first, row_len, labels, out)
            },
        ),
    )
}

/// A kernel for whole windows inside the target: `(source, targets, first byte, bytes per target
/// row, labels, out)`.
type WindowKernel = fn(&[u8], &[u8], usize, usize, usize, &mut [u16]);

/// Fills `volume` (resized to the source's size and `2 · radius + 1` labels per layer) with the
/// costs of every source pixel against its window around `offsets`; candidates outside the target
/// or on invalid target pixels cost the median of all matching costs (binned as the reference),
/// and with `truncate` no cost exceeds it. Masked source pixels cost 0 everywhere.
#[allow(clippy::too_many_arguments)]
pub(super) fn compute_data_cost(
    source: &DenseSiftImage,
    source_mask: Option<&[bool]>,
    target: &DenseSiftImage,
    target_mask: Option<&[bool]>,
    offsets: [&[i32]; 2],
    radius: usize,
    truncate: bool,
    kernel: L1Kernel,
    volume: &mut CostVolume,
) {
    let labels = 2 * radius + 1;
    let window = labels * labels;
    let layout = Layout::new(source.width_px, source.height_px);
    volume.reset(layout, labels);
    let context = DataRowContext {
        source,
        source_mask,
        target,
        target_mask,
        offsets,
        radius,
    };
    let kernel = resolve_kernel(kernel);
    let histogram = volume
        .costs_mut()
        .par_chunks_mut(layout.positions * window)
        .enumerate()
        .map(|(block, out)| match kernel {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: `resolve_kernel` returns Avx2 only when the CPU has AVX2.
            L1Kernel::Avx2 => unsafe { fill_block_avx2(&context, layout, block, out) },
            #[cfg(target_arch = "x86_64")]
            L1Kernel::Sse2 => fill_block(&context, layout, block, out, l1_row_sse2, None),
            _ => fill_block(&context, layout, block, out, l1_row_portable, None),
        })
        .reduce(
            || Box::new([0u32; COUNTED_BINS]),
            |mut total, part| {
                for (sum, count) in total.iter_mut().zip(part.iter()) {
                    *sum += count;
                }
                total
            },
        );

    // The reference's default score: the median of all inside costs.
    let mut bins = [0u32; COST_HISTOGRAM_BINS];
    for (bin, &count) in histogram[..COUNTED_BINS - 1].iter().enumerate() {
        bins[bin.min(COST_HISTOGRAM_BINS - 1)] += count;
    }
    let total: u64 = bins.iter().map(|&count| count as u64).sum();
    let mut default_cost = 0u16;
    let mut cumulative = 0u64;
    for (bin, &count) in bins.iter().enumerate() {
        cumulative += count as u64;
        if 2 * cumulative >= total {
            default_cost = bin.max(1) as u16 * COST_HISTOGRAM_BIN;
            break;
        }
    }
    volume
        .costs_mut()
        .par_chunks_mut(layout.positions * window)
        .for_each(|block| replace_outside(block, default_cost, truncate));
}

crate::core::dense_sift::multiversioned! {
    /// Outside candidates (and, with `truncate`, costs above it) cost `default_cost`; branch-free,
    /// so that it vectorises.
    fn replace_outside(block: &mut [super::simd::Lanes], default_cost: u16, truncate: bool) {
        let ceiling = if truncate { default_cost } else { OUTSIDE_COST - 1 };
        for vector in block {
            for cost in &mut vector.0 {
                let outside = *cost == OUTSIDE_COST;
                let capped = (*cost).min(ceiling);
                *cost = if outside { default_cost } else { capped };
            }
        }
    }
}
