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

/// Bilinear 2× upsampling of an integer flow, doubled and rounded: the offsets of the finer level.
pub(super) fn upsample_flow(
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

pub(super) fn level_mask(masks: &[Vec<bool>], level: usize) -> Option<&[bool]> {
    let mask = &masks[level];
    (!mask.is_empty()).then_some(mask.as_slice())
}
