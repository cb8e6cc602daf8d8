//! The coarse-to-fine inputs of SIFT flow: the descriptor pyramid (blur, then halve), the mask
//! pyramid, and the upsampling of a level's flow into the next finer level's search offsets.

use super::{check_sift_image, FlowError, SiftFlowConfig};
use crate::core::dense_sift::{DenseSiftImage, DESCRIPTOR_LEN};

/// The coarser levels (1..) of a dense SIFT image's pyramid (level 0 is the image itself). Build it
/// once per image and reuse it for every flow that image takes part in.
#[derive(Debug, Default)]
pub struct SiftPyramid {
    pub(super) coarser_levels: Vec<DenseSiftImage>,
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

crate::core::dense_sift::multiversioned! {
    /// The vertical pass for one output row: `((0 + w₀·r₀) + w₁·r₁) + …` per byte, all six taps
    /// in one pass.
    fn blur_rows(rows: [&[u8]; 6], taps: &[f32; 6], out: &mut [f32]) {
        let [r0, r1, r2, r3, r4, r5] = rows;
        for (index, value) in out.iter_mut().enumerate() {
            let mut sum = 0.0f32;
            sum += taps[0] * r0[index] as f32;
            sum += taps[1] * r1[index] as f32;
            sum += taps[2] * r2[index] as f32;
            sum += taps[3] * r3[index] as f32;
            sum += taps[4] * r4[index] as f32;
            sum += taps[5] * r5[index] as f32;
            *value = sum;
        }
    }
}

crate::core::dense_sift::multiversioned! {
    /// The horizontal pass and the halving: output pixel `X` takes the six columns around `2X`
    /// (clamped), rounds and saturates to a byte.
    fn blur_and_halve_row(row: &[f32], taps: &[f32; 6], out: &mut [u8]) {
        let width = row.len() / DESCRIPTOR_LEN;
        for (out_x, bytes) in out.chunks_exact_mut(DESCRIPTOR_LEN).enumerate() {
            let columns: [&[f32]; 6] = std::array::from_fn(|tap_index| {
                let source_x = (2 * out_x + tap_index).saturating_sub(2).min(width - 1);
                &row[source_x * DESCRIPTOR_LEN..(source_x + 1) * DESCRIPTOR_LEN]
            });
            for (index, byte) in bytes.iter_mut().enumerate() {
                let mut sum = 0.0f32;
                for (column, &weight) in columns.iter().zip(taps) {
                    sum += weight * column[index];
                }
                let rounded = sum + 0.5;
                let clamped = if rounded < 255.0 { rounded } else { 255.0 };
                // SAFETY: `clamped` is finite and in 0..=255 (non-negative taps and bytes), so
                // the conversion is exact truncation; `as` would add a saturation that keeps the
                // loop from vectorising.
                *byte = unsafe { clamped.to_int_unchecked::<i32>() } as u8;
            }
        }
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
pub(super) fn upsample_flow(
    coarse: &[i32],
    coarse_width: usize,
    coarse_height: usize,
    width: usize,
    height: usize,
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
    for (y, fine_row) in fine.chunks_exact_mut(width).take(height).enumerate() {
        let (y0, y1, wy) = taps(y, coarse_height);
        let (row0, row1) = (
            &coarse[y0 * coarse_width..(y0 + 1) * coarse_width],
            &coarse[y1 * coarse_width..(y1 + 1) * coarse_width],
        );
        for (x, value) in fine_row.iter_mut().enumerate() {
            let (x0, x1, wx) = taps(x, coarse_width);
            let along = |row: &[i32]| row[x0] * (4 - wx) + row[x1] * wx;
            // 16 · the bilinear value; the doubled value is sixteenths / 8.
            let sixteenths = along(row0) * (4 - wy) + along(row1) * wy;
            *value = if sixteenths >= 0 {
                (sixteenths + 4) / 8
            } else {
                -((4 - sixteenths) / 8)
            };
        }
    }
}

pub(super) fn level_mask(masks: &[Vec<bool>], level: usize) -> Option<&[bool]> {
    let mask = &masks[level];
    (!mask.is_empty()).then_some(mask.as_slice())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The blur-then-halve of the definition, one byte at a time (the code before the
    /// vectorised passes).
    fn reference_downsample(input: &DenseSiftImage, taps: &[f32; 6]) -> Vec<u8> {
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

    #[test]
    fn integer_upsampling_equals_the_bilinear_definition() {
        for (coarse_width, coarse_height, width, height) in [(5, 4, 9, 8), (5, 4, 10, 7), (1, 1, 2, 1)] {
            let coarse: Vec<i32> = (0..coarse_width * coarse_height)
                .map(|index| ((index * 2_654_435_761usize) >> 20) as i32 % 41 - 20)
                .collect();
            let mut fine = vec![0; width * height];
            upsample_flow(&coarse, coarse_width, coarse_height, width, height, &mut fine);
            for y in 0..height {
                let coarse_y = ((y as f32 + 0.5) * 0.5 - 0.5).clamp(0.0, (coarse_height - 1) as f32);
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
                    assert_eq!(fine[y * width + x], (2.0 * value).round() as i32, "({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn pyramid_levels_equal_the_definition() {
        for (width, height) in [(37, 21), (8, 5), (1, 3)] {
            let mut base = DenseSiftImage::default();
            base.resize(width, height, true);
            for (index, byte) in base.descriptors.iter_mut().enumerate() {
                *byte = (index.wrapping_mul(2_654_435_761) >> 7) as u8;
            }
            let config = SiftFlowConfig::default();
            let mut pyramid = SiftPyramid::default();
            pyramid.build(&base, &config).unwrap();
            let taps = downsampling_taps(config.pyramid_sigma_px);
            let mut finer = &base;
            for level in 1..config.pyramid_levels {
                let coarser = pyramid.level(level).unwrap();
                assert_eq!(
                    coarser.descriptors,
                    reference_downsample(finer, &taps),
                    "{width}x{height} level {level}"
                );
                finer = coarser;
            }
        }
    }
}
