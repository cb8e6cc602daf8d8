//! The data term of SIFT flow: the matching cost of every source pixel against every candidate in
//! its search window, with the reference's median cost for candidates outside the target.

use rayon::prelude::*;

#[cfg(target_arch = "x86_64")]
use super::kernels::{l1_distance_avx2, l1_distance_sse2};
use super::kernels::{l1_distance_portable, resolve_kernel};
use super::L1Kernel;
use crate::core::dense_sift::DenseSiftImage;

/// The bin width of the matching-cost histogram used for the median (cost units).
const COST_HISTOGRAM_BIN: f32 = 32.0;
const COST_HISTOGRAM_BINS: usize = 1100;

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
pub(super) fn compute_data_cost(
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
