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

#[cfg(test)]
mod tests {
    use super::super::kernels::l1_distance_portable;
    use super::*;

    /// A pseudo-random sequence (an LCG) for test data.
    struct Sequence(u64);

    impl Sequence {
        fn next(&mut self, modulus: u64) -> u64 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (self.0 >> 33) % modulus
        }
    }

    fn descriptors(width: usize, height: usize, sequence: &mut Sequence) -> DenseSiftImage {
        DenseSiftImage {
            width_px: width,
            height_px: height,
            descriptors: crate::core::dense_sift::DescriptorBytes::from_bytes(
                &(0..width * height * DESCRIPTOR_LEN)
                    .map(|_| sequence.next(256) as u8)
                    .collect::<Vec<u8>>(),
            ),
            ..Default::default()
        }
    }

    /// The data term computed the straightforward way, pixel by pixel in row-major order: costs,
    /// the median of every third cost binned by 32, outside candidates (and with `truncate` costs
    /// above it) set to it. Index `pixel · labels² + label_v · labels + label_u`.
    #[allow(clippy::too_many_arguments)]
    fn straightforward_costs(
        source: &DenseSiftImage,
        source_mask: Option<&[bool]>,
        target: &DenseSiftImage,
        target_mask: Option<&[bool]>,
        offsets: [&[i32]; 2],
        radius: usize,
        truncate: bool,
    ) -> Vec<u16> {
        let labels = 2 * radius + 1;
        let mut costs = Vec::new();
        for y in 0..source.height_px {
            for x in 0..source.width_px {
                let pixel = y * source.width_px + x;
                for label_v in 0..labels {
                    for label_u in 0..labels {
                        if source_mask.is_some_and(|mask| !mask[pixel]) {
                            costs.push(0);
                            continue;
                        }
                        let target_x =
                            (x + label_u) as isize + offsets[0][pixel] as isize - radius as isize;
                        let target_y =
                            (y + label_v) as isize + offsets[1][pixel] as isize - radius as isize;
                        let inside = (0..target.width_px as isize).contains(&target_x)
                            && (0..target.height_px as isize).contains(&target_y);
                        let target_pixel = inside
                            .then(|| target_y as usize * target.width_px + target_x as usize)
                            .filter(|&pixel| target_mask.is_none_or(|mask| mask[pixel]));
                        let Some(target_pixel) = target_pixel else {
                            costs.push(OUTSIDE_COST);
                            continue;
                        };
                        costs.push(l1_distance_portable(
                            source.descriptor(pixel),
                            target.descriptor(target_pixel),
                        ) as u16);
                    }
                }
            }
        }
        let mut bins = vec![0u64; COST_HISTOGRAM_BINS];
        for &cost in costs
            .iter()
            .step_by(3)
            .filter(|&&cost| cost != OUTSIDE_COST)
        {
            bins[((cost / COST_HISTOGRAM_BIN) as usize).min(COST_HISTOGRAM_BINS - 1)] += 1;
        }
        let total: u64 = bins.iter().sum();
        let mut cumulative = 0;
        let median_bin = bins
            .iter()
            .position(|&count| {
                cumulative += count;
                2 * cumulative >= total
            })
            .unwrap_or(0);
        let default_cost = median_bin.max(1) as u16 * COST_HISTOGRAM_BIN;
        for cost in &mut costs {
            if *cost == OUTSIDE_COST || (truncate && *cost > default_cost) {
                *cost = default_cost;
            }
        }
        costs
    }

    /// Every kernel's volume holds the straightforward costs at every pixel's lanes and 0 in every
    /// padding lane: widths under and over 16, heights with a partial block of rows, windows
    /// reaching outside the target, masks on both sides, truncated or not. It fails when a pixel is
    /// skipped or written to another lane, or a sample of the median is lost.
    #[test]
    fn the_volume_is_the_straightforward_costs_and_median() {
        let mut sequence = Sequence(17);
        let mut volume = CostVolume::default();
        for (width, height, radius) in
            [(37, 21, 2), (5, 40, 1), (20, 16, 4), (1, 3, 2), (70, 33, 3)]
        {
            let source = descriptors(width, height, &mut sequence);
            let target = descriptors(width + 3, height.saturating_sub(2).max(1), &mut sequence);
            let offsets: [Vec<i32>; 2] = std::array::from_fn(|_| {
                (0..width * height)
                    .map(|_| sequence.next(13) as i32 - 6)
                    .collect()
            });
            let source_mask: Vec<bool> =
                (0..width * height).map(|_| sequence.next(9) != 0).collect();
            let target_mask: Vec<bool> = (0..target.width_px * target.height_px)
                .map(|_| sequence.next(7) != 0)
                .collect();
            for masked in [false, true] {
                for truncate in [false, true] {
                    let (source_mask, target_mask) = if masked {
                        (Some(&source_mask[..]), Some(&target_mask[..]))
                    } else {
                        (None, None)
                    };
                    let offsets = [&offsets[0][..], &offsets[1][..]];
                    let expected = straightforward_costs(
                        &source,
                        source_mask,
                        &target,
                        target_mask,
                        offsets,
                        radius,
                        truncate,
                    );
                    for kernel in [L1Kernel::Portable, L1Kernel::Sse2, L1Kernel::Avx2] {
                        compute_data_cost(
                            &source,
                            source_mask,
                            &target,
                            target_mask,
                            offsets,
                            radius,
                            truncate,
                            kernel,
                            &mut volume,
                        );
                        let labels = 2 * radius + 1;
                        let case = format!(
                            "{width}x{height}, radius {radius}, masked {masked}, truncate {truncate}, {kernel:?}"
                        );
                        let layout = volume.layout;
                        let mut pixel_lanes = vec![false; layout.vectors() * LANES];
                        layout.for_each_pixel(|x, y, vector, lane| {
                            pixel_lanes[vector * LANES + lane] = true;
                            let pixel = y * width + x;
                            for label in 0..labels * labels {
                                assert_eq!(
                                    volume.cost(x, y, label % labels, label / labels),
                                    expected[pixel * labels * labels + label],
                                    "{case}: pixel ({x}, {y}), label {label}"
                                );
                            }
                        });
                        for (index, costs) in
                            volume.costs().chunks_exact(labels * labels).enumerate()
                        {
                            for (lane, &is_pixel) in
                                pixel_lanes[index * LANES..][..LANES].iter().enumerate()
                            {
                                if !is_pixel {
                                    assert!(
                                        costs.iter().all(|vector| vector.0[lane] == 0),
                                        "{case}: padding lane {lane} of position {index}"
                                    );
                                }
                            }
                        }
                    }
                }
            }
        }
    }
}
