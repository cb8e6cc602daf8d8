//! The coarse-to-fine inputs of SIFT flow: the descriptor pyramid (blur, then halve), the mask
//! pyramid, and the upsampling of a level's flow into the next finer level's search offsets.

use super::{check_sift_image, FlowError, SiftFlowConfig};
use crate::core::dense_sift::{DenseSiftImage, DESCRIPTOR_LEN};

/// The coarser levels (1..) of a dense SIFT image's pyramid (level 0 is the image itself). Build it
/// once per image and reuse it for every flow that image takes part in.
#[derive(Debug, Default)]
pub struct SiftPyramid {
    pub(super) coarser_levels: Vec<DenseSiftImage>,
    row_buffer: Vec<i16>,
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
    pub(super) fn level(&self, level: usize) -> Option<&DenseSiftImage> {
        self.coarser_levels.get(level.checked_sub(1)?)
    }
}

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
    row_buffer: &mut Vec<i16>,
) {
    for level in 0..pyramid.len() {
        let (finer, coarser) = pyramid.split_at_mut(level);
        let input = if level == 0 { base } else { &finer[level - 1] };
        downsample_descriptors(input, taps, row_buffer, &mut coarser[0]);
    }
}

/// The 1-D taps in 15-bit fixed point (`round(t · 2¹⁵)`).
fn fixed_point_taps(taps: &[f32; 6]) -> [i16; 6] {
    taps.map(|tap| (tap * 32768.0).round() as i16)
}

fn downsample_descriptors(
    input: &DenseSiftImage,
    taps: &[f32; 6],
    row_buffer: &mut Vec<i16>,
    output: &mut DenseSiftImage,
) {
    let (width, height) = (input.width_px, input.height_px);
    let out_width = width.div_ceil(2);
    let out_height = height.div_ceil(2);
    output.resize(out_width, out_height, false);
    row_buffer.resize(width * DESCRIPTOR_LEN, 0);
    let row_len = width * DESCRIPTOR_LEN;
    let taps = fixed_point_taps(taps);
    let source_row = |y: usize| &input.descriptors[y * row_len..(y + 1) * row_len];
    for (out_y, out_row) in output
        .descriptors
        .chunks_exact_mut(out_width * DESCRIPTOR_LEN)
        .enumerate()
    {
        let rows: [&[u8]; 6] = std::array::from_fn(|tap_index| {
            source_row((2 * out_y + tap_index).saturating_sub(2).min(height - 1))
        });
        blur_rows(rows, taps, row_buffer);
        blur_and_halve_row(row_buffer, taps, out_row);
    }
}

/// `(Σ_j w_j · r_j[i] + 2⁷) >> 8`: the vertical pass in 7-bit fixed point (at most 255 · 2⁷).
#[inline(always)]
fn vertical_sum(rows: &[&[u8]; 6], taps: &[i16; 6], index: usize) -> i16 {
    let sum: i32 = rows
        .iter()
        .zip(taps)
        .map(|(row, &tap)| row[index] as i32 * tap as i32)
        .sum();
    ((sum + (1 << 7)) >> 8) as i16
}

/// `min((Σ_i w_i · v_i + 2²¹) >> 22, 255)`: the horizontal pass, rounded to a byte.
#[inline(always)]
fn horizontal_byte(columns: &[&[i16]; 6], taps: &[i16; 6], index: usize) -> u8 {
    let sum: i32 = columns
        .iter()
        .zip(taps)
        .map(|(column, &tap)| column[index] as i32 * tap as i32)
        .sum();
    ((sum + (1 << 21)) >> 22).min(255) as u8
}

/// The vertical pass for one output row (all six taps in one pass), in integers: the same
/// results with AVX2 (`pmaddwd` on pairs of rows) and without.
fn blur_rows(rows: [&[u8]; 6], taps: [i16; 6], out: &mut [i16]) {
    assert!(rows.iter().all(|row| row.len() == out.len()) && out.len() % 16 == 0);
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2; the lengths are checked above.
        unsafe { blur_rows_avx2(rows, taps, out) };
        return;
    }
    for (index, value) in out.iter_mut().enumerate() {
        *value = vertical_sum(&rows, &taps, index);
    }
}

/// The horizontal pass and the halving: output pixel `X` takes the six columns around `2X`
/// (clamped), rounded to a byte.
fn blur_and_halve_row(row: &[i16], taps: [i16; 6], out: &mut [u8]) {
    let width = row.len() / DESCRIPTOR_LEN;
    #[cfg(target_arch = "x86_64")]
    let avx2 = std::arch::is_x86_feature_detected!("avx2");
    for (out_x, bytes) in out.chunks_exact_mut(DESCRIPTOR_LEN).enumerate() {
        let columns: [&[i16]; 6] = std::array::from_fn(|tap_index| {
            let source_x = (2 * out_x + tap_index).saturating_sub(2).min(width - 1);
            &row[source_x * DESCRIPTOR_LEN..(source_x + 1) * DESCRIPTOR_LEN]
        });
        #[cfg(target_arch = "x86_64")]
        if avx2 {
            // SAFETY: the CPU has AVX2; every column and `bytes` hold 128 values.
            unsafe { blur_and_halve_pixel_avx2(columns, taps, bytes) };
            continue;
        }
        for (index, byte) in bytes.iter_mut().enumerate() {
            *byte = horizontal_byte(&columns, &taps, index);
        }
    }
}

/// Pairs of taps `(w_a, w_b)` as the 32-bit lanes `pmaddwd` multiplies interleaved pairs by.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn tap_pairs(taps: [i16; 6]) -> [i32; 3] {
    std::array::from_fn(|pair| {
        (taps[2 * pair] as u16 as i32) | ((taps[2 * pair + 1] as u16 as i32) << 16)
    })
}

/// [`blur_rows`] in AVX2.
///
/// # Safety
/// The CPU must have AVX2; every row holds `out.len()` bytes, a multiple of 16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn blur_rows_avx2(rows: [&[u8]; 6], taps: [i16; 6], out: &mut [i16]) {
    use std::arch::x86_64::*;
    let pairs = tap_pairs(taps).map(|pair| _mm256_set1_epi32(pair));
    let half = _mm256_set1_epi32(1 << 7);
    for chunk in 0..out.len() / 16 {
        let words: [__m256i; 6] = std::array::from_fn(|tap| unsafe {
            _mm256_cvtepu8_epi16(_mm_loadu_si128(
                rows[tap].as_ptr().add(16 * chunk) as *const __m128i
            ))
        });
        // Elements 0–3 and 8–11 (low), 4–7 and 12–15 (high), as 32-bit sums.
        let mut low = half;
        let mut high = half;
        for pair in 0..3 {
            let (a, b) = (words[2 * pair], words[2 * pair + 1]);
            low = _mm256_add_epi32(
                low,
                _mm256_madd_epi16(_mm256_unpacklo_epi16(a, b), pairs[pair]),
            );
            high = _mm256_add_epi32(
                high,
                _mm256_madd_epi16(_mm256_unpackhi_epi16(a, b), pairs[pair]),
            );
        }
        // packs puts the halves back in order: 0–3, 4–7 | 8–11, 12–15.
        let packed = _mm256_packs_epi32(_mm256_srai_epi32(low, 8), _mm256_srai_epi32(high, 8));
        unsafe { _mm256_storeu_si256(out.as_mut_ptr().add(16 * chunk) as *mut __m256i, packed) };
    }
}

/// One output pixel of [`blur_and_halve_row`] in AVX2.
///
/// # Safety
/// The CPU must have AVX2; every column and `bytes` hold 128 values.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn blur_and_halve_pixel_avx2(columns: [&[i16]; 6], taps: [i16; 6], bytes: &mut [u8]) {
    use std::arch::x86_64::*;
    let pairs = tap_pairs(taps).map(|pair| _mm256_set1_epi32(pair));
    let half = _mm256_set1_epi32(1 << 21);
    let sixteen = |chunk: usize| {
        let words: [__m256i; 6] = std::array::from_fn(|tap| unsafe {
            _mm256_loadu_si256(columns[tap].as_ptr().add(16 * chunk) as *const __m256i)
        });
        let mut low = half;
        let mut high = half;
        for pair in 0..3 {
            let (a, b) = (words[2 * pair], words[2 * pair + 1]);
            low = _mm256_add_epi32(
                low,
                _mm256_madd_epi16(_mm256_unpacklo_epi16(a, b), pairs[pair]),
            );
            high = _mm256_add_epi32(
                high,
                _mm256_madd_epi16(_mm256_unpackhi_epi16(a, b), pairs[pair]),
            );
        }
        _mm256_packs_epi32(_mm256_srai_epi32(low, 22), _mm256_srai_epi32(high, 22))
    };
    for chunk in 0..DESCRIPTOR_LEN / 32 {
        // packus saturates to 0..=255 and interleaves the 128-bit lanes: put them back in order.
        let packed = _mm256_packus_epi16(sixteen(2 * chunk), sixteen(2 * chunk + 1));
        let ordered = _mm256_permute4x64_epi64(packed, 0xd8);
        unsafe { _mm256_storeu_si256(bytes.as_mut_ptr().add(32 * chunk) as *mut __m256i, ordered) };
    }
}

/// Level 0 is the given mask (or empty: all pixels); a coarser pixel is set when at least two of
/// its (up to four) children are.
pub(super) fn build_mask_pyramid(
    mask: Option<&[bool]>,
    base: &DenseSiftImage,
    levels: &mut [Vec<bool>],
) {
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

/// Bilinear 2× upsampling of an integer flow, doubled and rounded (halves away from zero): the
/// offsets of the finer level. Fine pixel `x` samples the coarse grid at `x/2 − 1/4` (clamped), so
/// every weight is a multiple of 1/4 and the arithmetic is exact in integers.
///
/// Separable, in two passes that the compiler vectorises: every coarse row upsampled along x once
/// (into `rows_scratch`, four times the value), then each fine row from its two rows. The same
/// integer sums as the definition (exact, so identical), without per-pixel tap arithmetic.
pub(super) fn upsample_flow(
    coarse: &[i32],
    coarse_width: usize,
    coarse_height: usize,
    width: usize,
    height: usize,
    rows_scratch: &mut Vec<i32>,
    fine: &mut [i32],
) {
    // (first sample, second sample, weight of the second in quarters).
    let taps = |fine: usize, coarse_len: usize| {
        let half = fine / 2;
        let (first, weight) = match (fine % 2, half) {
            (0, 0) => (0, 0),
            (0, _) => (half - 1, 3),
            _ => (half, 1),
        };
        let first = first.min(coarse_len - 1);
        (first, (first + 1).min(coarse_len - 1), weight)
    };
    rows_scratch.clear();
    rows_scratch.resize(coarse_height * width, 0);
    for (coarse_row, along) in coarse
        .chunks_exact(coarse_width)
        .take(coarse_height)
        .zip(rows_scratch.chunks_exact_mut(width))
    {
        upsample_row(coarse_row, &taps, along);
    }
    for (y, fine_row) in fine.chunks_exact_mut(width).take(height).enumerate() {
        let (y0, y1, wy) = taps(y, coarse_height);
        let (row0, row1) = (
            &rows_scratch[y0 * width..(y0 + 1) * width],
            &rows_scratch[y1 * width..(y1 + 1) * width],
        );
        let (w0, w1) = (4 - wy as i32, wy as i32);
        for ((value, &along0), &along1) in fine_row.iter_mut().zip(row0).zip(row1) {
            // 16 · the bilinear value; the doubled value is sixteenths / 8.
            let sixteenths = along0 * w0 + along1 * w1;
            *value = if sixteenths >= 0 {
                (sixteenths + 4) >> 3
            } else {
                -((4 - sixteenths) >> 3)
            };
        }
    }
}

/// One coarse row along x, four times the bilinear value at each fine `x`: `r[x0]·(4 − w) +
/// r[x1]·w` with the taps of [`upsample_flow`]. Where the fine row is twice the coarse one (or
/// one less), the taps are fixed: `4r[0]`, then `3r[k] + r[k+1]` and `r[k] + 3r[k+1]` for each
/// pair of neighbours, and `4r[last]` at an even width's end; other widths take the taps one by
/// one.
fn upsample_row(
    coarse_row: &[i32],
    taps: &impl Fn(usize, usize) -> (usize, usize, usize),
    along: &mut [i32],
) {
    let (coarse_width, width) = (coarse_row.len(), along.len());
    if width + 1 == 2 * coarse_width || width == 2 * coarse_width {
        along[0] = 4 * coarse_row[0];
        for (pair, neighbours) in along[1..].chunks_exact_mut(2).zip(coarse_row.windows(2)) {
            pair[0] = neighbours[0] * 3 + neighbours[1];
            pair[1] = neighbours[0] + neighbours[1] * 3;
        }
        if width == 2 * coarse_width {
            along[width - 1] = 4 * coarse_row[coarse_width - 1];
        }
        return;
    }
    for (x, value) in along.iter_mut().enumerate() {
        let (x0, x1, wx) = taps(x, coarse_width);
        *value = coarse_row[x0] * (4 - wx as i32) + coarse_row[x1] * wx as i32;
    }
}

pub(super) fn level_mask(masks: &[Vec<bool>], level: usize) -> Option<&[bool]> {
    let mask = &masks[level];
    (!mask.is_empty()).then_some(mask.as_slice())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The blur-then-halve in floating point, one byte at a time (the code before the
    /// fixed-point passes).
    fn float_downsample(input: &DenseSiftImage, taps: &[f32; 6]) -> Vec<u8> {
        let (width, height) = (input.width_px, input.height_px);
        let (out_width, out_height) = (width.div_ceil(2), height.div_ceil(2));
        let mut out = vec![0u8; out_width * out_height * DESCRIPTOR_LEN];
        let mut row = vec![0.0f32; width * DESCRIPTOR_LEN];
        for out_y in 0..out_height {
            row.fill(0.0);
            for (tap_index, &weight) in taps.iter().enumerate() {
                let y = (2 * out_y + tap_index).saturating_sub(2).min(height - 1);
                for (index, value) in row.iter_mut().enumerate() {
                    *value += weight * input.descriptors[y * width * DESCRIPTOR_LEN + index] as f32;
                }
            }
            for out_x in 0..out_width {
                for element in 0..DESCRIPTOR_LEN {
                    let mut sum = 0.0f32;
                    for (tap_index, &weight) in taps.iter().enumerate() {
                        let x = (2 * out_x + tap_index).saturating_sub(2).min(width - 1);
                        sum += weight * row[x * DESCRIPTOR_LEN + element];
                    }
                    out[(out_y * out_width + out_x) * DESCRIPTOR_LEN + element] =
                        (sum + 0.5).min(255.0) as u8;
                }
            }
        }
        out
    }

    /// The fixed-point blur-then-halve one byte at a time, with the plain-Rust sums.
    fn fixed_point_downsample(input: &DenseSiftImage, taps: &[f32; 6]) -> Vec<u8> {
        let taps = fixed_point_taps(taps);
        let (width, height) = (input.width_px, input.height_px);
        let (out_width, out_height) = (width.div_ceil(2), height.div_ceil(2));
        let row_len = width * DESCRIPTOR_LEN;
        let mut out = vec![0u8; out_width * out_height * DESCRIPTOR_LEN];
        let mut row = vec![0i16; row_len];
        for out_y in 0..out_height {
            let rows: [&[u8]; 6] = std::array::from_fn(|tap| {
                let y = (2 * out_y + tap).saturating_sub(2).min(height - 1);
                &input.descriptors[y * row_len..(y + 1) * row_len]
            });
            for (index, value) in row.iter_mut().enumerate() {
                *value = vertical_sum(&rows, &taps, index);
            }
            for out_x in 0..out_width {
                let columns: [&[i16]; 6] = std::array::from_fn(|tap| {
                    let x = (2 * out_x + tap).saturating_sub(2).min(width - 1);
                    &row[x * DESCRIPTOR_LEN..(x + 1) * DESCRIPTOR_LEN]
                });
                for element in 0..DESCRIPTOR_LEN {
                    out[(out_y * out_width + out_x) * DESCRIPTOR_LEN + element] =
                        horizontal_byte(&columns, &taps, element);
                }
            }
        }
        out
    }

    #[test]
    fn integer_upsampling_equals_the_bilinear_definition() {
        // Fine sizes twice the coarse or one less (the pyramid's), and others (taps one by one).
        for (coarse_width, coarse_height, width, height) in [
            (5, 4, 9, 8),
            (5, 4, 10, 7),
            (1, 1, 2, 1),
            (1, 1, 1, 1),
            (2, 3, 4, 5),
            (5, 4, 7, 3),
            (3, 2, 12, 9),
        ] {
            let coarse: Vec<i32> = (0..coarse_width * coarse_height)
                .map(|index| ((index * 2_654_435_761usize) >> 20) as i32 % 41 - 20)
                .collect();
            let mut fine = vec![0; width * height];
            upsample_flow(
                &coarse,
                coarse_width,
                coarse_height,
                width,
                height,
                &mut Vec::new(),
                &mut fine,
            );
            for y in 0..height {
                let coarse_y =
                    ((y as f32 + 0.5) * 0.5 - 0.5).clamp(0.0, (coarse_height - 1) as f32);
                let y0 = coarse_y.floor() as usize;
                let y1 = (y0 + 1).min(coarse_height - 1);
                let fy = coarse_y - y0 as f32;
                for x in 0..width {
                    let coarse_x =
                        ((x as f32 + 0.5) * 0.5 - 0.5).clamp(0.0, (coarse_width - 1) as f32);
                    let x0 = coarse_x.floor() as usize;
                    let x1 = (x0 + 1).min(coarse_width - 1);
                    let fx = coarse_x - x0 as f32;
                    let at = |xx: usize, yy: usize| coarse[yy * coarse_width + xx] as f32;
                    let value = (at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx) * (1.0 - fy)
                        + (at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx) * fy;
                    assert_eq!(
                        fine[y * width + x],
                        (2.0 * value).round() as i32,
                        "({x}, {y})"
                    );
                }
            }
        }
    }

    #[test]
    fn pyramid_levels_are_the_fixed_point_blur_and_near_the_float_one() {
        let (mut differing, mut total) = (0usize, 0usize);
        for (width, height) in [(37, 21), (8, 5), (1, 3), (120, 61)] {
            let mut base = DenseSiftImage::default();
            base.resize(width, height, true);
            for (index, byte) in base.descriptors.iter_mut().enumerate() {
                // Smooth in x and y with some noise, the full byte range.
                let (pixel, element) = (index / DESCRIPTOR_LEN, index % DESCRIPTOR_LEN);
                let (x, y) = (pixel % width, pixel / width);
                let wave = ((x as f32 * 0.3 + element as f32).sin() * (y as f32 * 0.2).cos() + 1.0)
                    * 120.0;
                *byte = (wave as usize + (index.wrapping_mul(2_654_435_761) >> 28)).min(255) as u8;
            }
            let config = SiftFlowConfig::default();
            let mut pyramid = SiftPyramid::default();
            pyramid.build(&base, &config).unwrap();
            let taps = downsampling_taps(config.pyramid_sigma_px);
            let mut finer = &base;
            for level in 1..config.pyramid_levels {
                let coarser = pyramid.level(level).unwrap();
                assert_eq!(
                    &*coarser.descriptors,
                    fixed_point_downsample(finer, &taps).as_slice(),
                    "{width}x{height} level {level}"
                );
                let float = float_downsample(finer, &taps);
                for (&got, &want) in coarser.descriptors.iter().zip(&float) {
                    assert!(
                        got.abs_diff(want) <= 1,
                        "{width}x{height} level {level}: {got} vs {want}"
                    );
                    differing += (got != want) as usize;
                }
                total += float.len();
                finer = coarser;
            }
        }
        println!("fixed point against float: {differing} of {total} bytes differ by one");
        assert!(differing * 50 <= total, "{differing} of {total}");
    }
}
