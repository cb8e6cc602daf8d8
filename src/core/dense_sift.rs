//! Dense SIFT: one 128-byte SIFT descriptor per pixel, the features SIFT flow matches (Liu, Yuen,
//! Torralba, "SIFT Flow: Dense Correspondence across Scenes and its Applications", TPAMI 2011, §3.1),
//! computed exactly as Ce Liu's reference `ImageFeature::imSIFT` does (cell size 3, step 1):
//!
//! 1. image derivatives by the 5-tap central difference `[1, -8, 0, 8, -1] / 12` (borders clamped);
//!    docs/design.md names 3×3 Sobel, which is offered as [`GradientFilter::Sobel`];
//! 2. 8 signed orientation bins `θ_k = 2πk/8`, soft assignment `max(cos(θ - θ_k), 0)^9 · |g|`;
//! 3. cell pooling by the reference's separable filter of half-width `cell_size` (taps
//!    `0.25` at `-cell_size` and `1` at `2 - cell_size ..= 1`, i.e. a box of about one cell);
//! 4. a 4×4 grid of cells sampled at offsets `{-1, 0, 1, 2} · cell_size` (clamped to the image),
//!    concatenated row by row (8 bins per cell) → 128 values;
//! 5. `v / (‖v‖₂ + ε) · 255`, saturated and truncated to `u8` (ε = 0.01).
//!
//! Preconditions: a grey, non-empty [`ImageView<f32>`]. The scale
//! matters only relative to ε and to the texture threshold: both are stated for intensities in
//! `0..=1` (multiply them by 255 for 0..255 images). Each pixel also gets the mean gradient
//! magnitude over its descriptor's support (`support_gradient`), which defines "textured".

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::core::image::{Image, ImageError, ImageView};

/// Errors of dense matching (dense SIFT, SIFT flow, consistency); defined here, in the lowest of
/// the three layers, so that none imports a layer above it.
#[derive(Debug, thiserror::Error)]
pub enum FlowError {
    #[error("invalid configuration: {field}: {reason}")]
    InvalidConfig { field: &'static str, reason: String },
    #[error("image of {width_px} x {height_px} px has no pixels")]
    EmptyImage { width_px: usize, height_px: usize },
    #[error(transparent)]
    Image(#[from] ImageError),
    #[error("{what}: expected {expected} entries, found {found}")]
    SizeMismatch {
        what: &'static str,
        expected: usize,
        found: usize,
    },
}

/// Bytes per descriptor: 4×4 cells × 8 orientation bins.
pub const DESCRIPTOR_LEN: usize = 128;
const ORIENTATION_BINS: usize = 8;
/// Channels of the per-pixel band image: the 8 orientation energies and the gradient magnitude.
const BAND_CHANNELS: usize = ORIENTATION_BINS + 1;
const CELL_OFFSETS: [isize; 4] = [-1, 0, 1, 2];

/// The derivative filter of step 1.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GradientFilter {
    /// `[1, -8, 0, 8, -1] / 12` along x (and y), no cross smoothing: Ce Liu's reference.
    CentralFivePoint,
    /// 3×3 Sobel, divided by 8 so that a unit ramp has a unit derivative.
    Sobel,
}

/// Parameters of dense SIFT. Defaults are the reference's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DenseSiftConfig {
    /// Side of one of the 4×4 cells, px. Reference: 3 (descriptor support ≈ 12 px).
    pub cell_size_px: usize,
    /// Exponent of the soft orientation assignment `max(cos, 0)^e`. Reference: 9.
    pub orientation_sharpness: i32,
    /// ε added to the descriptor's L2 norm before normalisation, in intensity units of a `0..=1`
    /// image (gradient magnitude × pooled pixels). Reference: 0.01.
    pub normalisation_floor: f32,
    /// Standard deviation of a Gaussian applied to the image first, px; 0 disables it. Ce Liu's demo
    /// smooths with `fspecial('gaussian', 7, 1)` (7 taps, σ = 1) before computing SIFT.
    pub presmoothing_sigma_px: f32,
    /// Derivative filter.
    pub gradient_filter: GradientFilter,
}

impl Default for DenseSiftConfig {
    fn default() -> Self {
        Self {
            cell_size_px: 3,
            orientation_sharpness: 9,
            normalisation_floor: 0.01,
            presmoothing_sigma_px: 1.0,
            gradient_filter: GradientFilter::CentralFivePoint,
        }
    }
}

impl DenseSiftConfig {
    /// Checks every field once; call before the hot path.
    pub fn validate(&self) -> Result<(), FlowError> {
        let bad =
            |field: &'static str, reason: String| Err(FlowError::InvalidConfig { field, reason });
        if !(1..=32).contains(&self.cell_size_px) {
            return bad(
                "cell_size_px",
                format!("{} is not in 1..=32", self.cell_size_px),
            );
        }
        if !(1..=64).contains(&self.orientation_sharpness) {
            return bad(
                "orientation_sharpness",
                format!("{} is not in 1..=64", self.orientation_sharpness),
            );
        }
        if !(self.normalisation_floor.is_finite() && self.normalisation_floor > 0.0) {
            return bad(
                "normalisation_floor",
                format!("{} is not > 0", self.normalisation_floor),
            );
        }
        if !(self.presmoothing_sigma_px.is_finite()
            && (0.0..=10.0).contains(&self.presmoothing_sigma_px))
        {
            return bad(
                "presmoothing_sigma_px",
                format!("{} is not in 0..=10", self.presmoothing_sigma_px),
            );
        }
        Ok(())
    }
}

/// A dense SIFT image: a descriptor for every pixel, row major.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DenseSiftImage {
    pub width_px: usize,
    pub height_px: usize,
    /// `width_px · height_px · 128` bytes; pixel `p`'s descriptor is `[p·128, (p+1)·128)`.
    pub descriptors: Vec<u8>,
    /// Mean gradient magnitude over each descriptor's 4×4-cell support, intensity units per px.
    /// Empty (0 × 0) for pyramid levels made by downsampling.
    pub support_gradient: Image<f32>,
}

impl DenseSiftImage {
    /// The descriptor of pixel `pixel` (row-major index).
    #[inline]
    pub fn descriptor(&self, pixel: usize) -> &[u8] {
        &self.descriptors[pixel * DESCRIPTOR_LEN..(pixel + 1) * DESCRIPTOR_LEN]
    }

    /// Writes `textured[p] = support_gradient[p] >= min_support_gradient` into the caller's
    /// image, made the size of `support_gradient`.
    pub fn textured_mask(&self, min_support_gradient: f32, textured: &mut Image<bool>) {
        let (width_px, height_px) = self.support_gradient.size();
        textured.resize(width_px, height_px, false);
        for (is_textured, &gradient) in textured
            .data_mut()
            .iter_mut()
            .zip(self.support_gradient.data())
        {
            *is_textured = gradient >= min_support_gradient;
        }
    }

    pub(crate) fn resize(&mut self, width_px: usize, height_px: usize, with_support: bool) {
        self.width_px = width_px;
        self.height_px = height_px;
        self.descriptors
            .resize(width_px * height_px * DESCRIPTOR_LEN, 0);
        if with_support {
            self.support_gradient.resize(width_px, height_px, 0.0);
        } else {
            self.support_gradient.resize(0, 0, 0.0);
        }
    }
}

/// Scratch buffers reused between calls (no allocation once they have grown to the image size).
#[derive(Debug, Default)]
pub struct DenseSiftWorkspace {
    smoothed: Vec<f32>,
    smoothing_scratch: Vec<f32>,
    gradient_x: Vec<f32>,
    gradient_y: Vec<f32>,
    bands: Vec<f32>,
    bands_pooled_rows: Vec<f32>,
    bands_pooled: Vec<f32>,
}

/// Computes the dense SIFT image of a grey `image` into `out`.
pub fn compute_dense_sift(
    image: ImageView<'_, f32>,
    config: &DenseSiftConfig,
    workspace: &mut DenseSiftWorkspace,
    out: &mut DenseSiftImage,
) -> Result<(), FlowError> {
    config.validate()?;
    let (width_px, height_px) = image.size();
    if image.is_empty() {
        return Err(FlowError::EmptyImage {
            width_px,
            height_px,
        });
    }
    let image = image.data();
    let pixel_count = width_px * height_px;
    let ws = workspace;

    // 0. Optional Gaussian presmoothing.
    let source: &[f32] = if config.presmoothing_sigma_px > 0.0 {
        let taps = gaussian_taps(config.presmoothing_sigma_px, 3);
        ws.smoothed.resize(pixel_count, 0.0);
        ws.smoothing_scratch.resize(pixel_count, 0.0);
        separable_filter_clamped(
            image,
            width_px,
            height_px,
            1,
            &taps,
            3,
            &mut ws.smoothing_scratch,
            &mut ws.smoothed,
        );
        &ws.smoothed
    } else {
        image
    };

    // 1. Derivatives.
    ws.gradient_x.resize(pixel_count, 0.0);
    ws.gradient_y.resize(pixel_count, 0.0);
    compute_gradients(
        source,
        width_px,
        height_px,
        config.gradient_filter,
        &mut ws.gradient_x,
        &mut ws.gradient_y,
    );

    // 2. Orientation bands (8 energies + magnitude per pixel).
    ws.bands.resize(pixel_count * BAND_CHANNELS, 0.0);
    let bin_directions: [(f32, f32); ORIENTATION_BINS] = std::array::from_fn(|bin| {
        let angle = std::f32::consts::TAU * bin as f32 / ORIENTATION_BINS as f32;
        (angle.cos(), angle.sin())
    });
    let sharpness = config.orientation_sharpness;
    ws.bands
        .par_chunks_mut(width_px * BAND_CHANNELS)
        .zip(
            ws.gradient_x
                .par_chunks(width_px)
                .zip(ws.gradient_y.par_chunks(width_px)),
        )
        .for_each(|(band_row, (gx_row, gy_row))| {
            for ((bands, &gx), &gy) in band_row
                .chunks_exact_mut(BAND_CHANNELS)
                .zip(gx_row)
                .zip(gy_row)
            {
                let magnitude = (gx * gx + gy * gy).sqrt();
                let inverse = if magnitude > 0.0 {
                    1.0 / magnitude
                } else {
                    0.0
                };
                for (band, &(cos_k, sin_k)) in bands.iter_mut().zip(&bin_directions) {
                    let cosine = ((gx * cos_k + gy * sin_k) * inverse).max(0.0);
                    *band = cosine.powi(sharpness) * magnitude;
                }
                bands[ORIENTATION_BINS] = magnitude;
            }
        });

    // 3. Cell pooling with the reference's filter.
    let cell = config.cell_size_px;
    let mut pooling_taps = vec![0.0f32; 2 * cell + 1];
    pooling_taps[0] = 0.25;
    for tap in pooling_taps.iter_mut().take(cell + 2).skip(2) {
        *tap = 1.0;
    }
    let pooling_weight_sum: f32 = pooling_taps.iter().sum();
    ws.bands_pooled_rows
        .resize(pixel_count * BAND_CHANNELS, 0.0);
    ws.bands_pooled.resize(pixel_count * BAND_CHANNELS, 0.0);
    separable_filter_clamped(
        &ws.bands,
        width_px,
        height_px,
        BAND_CHANNELS,
        &pooling_taps,
        cell,
        &mut ws.bands_pooled_rows,
        &mut ws.bands_pooled,
    );

    // 4–5. Sampling of the 4×4 cells and normalisation.
    out.resize(width_px, height_px, true);
    let pooled = &ws.bands_pooled;
    let floor = config.normalisation_floor;
    let support_scale = 1.0 / (16.0 * pooling_weight_sum * pooling_weight_sum);
    out.descriptors
        .par_chunks_mut(width_px * DESCRIPTOR_LEN)
        .zip(out.support_gradient.data_mut().par_chunks_mut(width_px))
        .enumerate()
        .for_each(|(y, (descriptor_row, support_row))| {
            let mut cells = [0.0f32; DESCRIPTOR_LEN];
            let sample_rows: [usize; 4] = CELL_OFFSETS
                .map(|offset| clamp_index(y as isize + offset * cell as isize, height_px));
            for x in 0..width_px {
                let sample_columns: [usize; 4] = CELL_OFFSETS
                    .map(|offset| clamp_index(x as isize + offset * cell as isize, width_px));
                let mut support = 0.0f32;
                for (cell_row, &sample_y) in sample_rows.iter().enumerate() {
                    for (cell_column, &sample_x) in sample_columns.iter().enumerate() {
                        let at = (sample_y * width_px + sample_x) * BAND_CHANNELS;
                        let cell_index = cell_row * 4 + cell_column;
                        cells[cell_index * ORIENTATION_BINS..(cell_index + 1) * ORIENTATION_BINS]
                            .copy_from_slice(&pooled[at..at + ORIENTATION_BINS]);
                        support += pooled[at + ORIENTATION_BINS];
                    }
                }
                let norm = cells.iter().map(|value| value * value).sum::<f32>().sqrt();
                let scale = 255.0 / (norm + floor);
                for (byte, value) in descriptor_row[x * DESCRIPTOR_LEN..(x + 1) * DESCRIPTOR_LEN]
                    .iter_mut()
                    .zip(&cells)
                {
                    *byte = (value * scale).min(255.0) as u8;
                }
                support_row[x] = support * support_scale;
            }
        });
    Ok(())
}

#[inline]
fn clamp_index(index: isize, len: usize) -> usize {
    index.clamp(0, len as isize - 1) as usize
}

/// Normalised Gaussian taps at offsets `-radius..=radius`.
pub(crate) fn gaussian_taps(sigma_px: f32, radius: usize) -> Vec<f32> {
    let mut taps: Vec<f32> = (0..=2 * radius)
        .map(|index| {
            let offset = index as f32 - radius as f32;
            (-offset * offset / (2.0 * sigma_px * sigma_px)).exp()
        })
        .collect();
    let sum: f32 = taps.iter().sum();
    taps.iter_mut().for_each(|tap| *tap /= sum);
    taps
}

/// Correlates a `channels`-interleaved image with `taps` (offsets `-radius..=radius`) along x and
/// then along y, clamping at the borders. `rows_scratch` receives the horizontal pass.
#[allow(clippy::too_many_arguments)]
pub(crate) fn separable_filter_clamped(
    input: &[f32],
    width_px: usize,
    height_px: usize,
    channels: usize,
    taps: &[f32],
    radius: usize,
    rows_scratch: &mut [f32],
    output: &mut [f32],
) {
    let row_len = width_px * channels;
    let nonzero_taps: Vec<(isize, f32)> = taps
        .iter()
        .enumerate()
        .filter(|(_, &weight)| weight != 0.0)
        .map(|(index, &weight)| (index as isize - radius as isize, weight))
        .collect();
    rows_scratch
        .par_chunks_mut(row_len)
        .zip(input.par_chunks(row_len))
        .for_each(|(out_row, in_row)| {
            for x in 0..width_px {
                let out = &mut out_row[x * channels..(x + 1) * channels];
                out.fill(0.0);
                for &(offset, weight) in &nonzero_taps {
                    let source_x = clamp_index(x as isize + offset, width_px);
                    let source = &in_row[source_x * channels..(source_x + 1) * channels];
                    for (value, &input_value) in out.iter_mut().zip(source) {
                        *value += input_value * weight;
                    }
                }
            }
        });
    let rows: &[f32] = rows_scratch;
    output
        .par_chunks_mut(row_len)
        .enumerate()
        .for_each(|(y, out_row)| {
            out_row.fill(0.0);
            for &(offset, weight) in &nonzero_taps {
                let source_y = clamp_index(y as isize + offset, height_px);
                let source = &rows[source_y * row_len..(source_y + 1) * row_len];
                for (value, &input_value) in out_row.iter_mut().zip(source) {
                    *value += input_value * weight;
                }
            }
        });
}

fn compute_gradients(
    image: &[f32],
    width_px: usize,
    height_px: usize,
    filter: GradientFilter,
    gradient_x: &mut [f32],
    gradient_y: &mut [f32],
) {
    let at =
        |x: isize, y: isize| image[clamp_index(y, height_px) * width_px + clamp_index(x, width_px)];
    gradient_x
        .par_chunks_mut(width_px)
        .zip(gradient_y.par_chunks_mut(width_px))
        .enumerate()
        .for_each(|(y, (gx_row, gy_row))| {
            let y = y as isize;
            for x in 0..width_px {
                let xi = x as isize;
                let (gx, gy) = match filter {
                    GradientFilter::CentralFivePoint => (
                        (at(xi - 2, y) - 8.0 * at(xi - 1, y) + 8.0 * at(xi + 1, y) - at(xi + 2, y))
                            / 12.0,
                        (at(xi, y - 2) - 8.0 * at(xi, y - 1) + 8.0 * at(xi, y + 1) - at(xi, y + 2))
                            / 12.0,
                    ),
                    GradientFilter::Sobel => {
                        let gx = (at(xi + 1, y - 1) + 2.0 * at(xi + 1, y) + at(xi + 1, y + 1))
                            - (at(xi - 1, y - 1) + 2.0 * at(xi - 1, y) + at(xi - 1, y + 1));
                        let gy = (at(xi - 1, y + 1) + 2.0 * at(xi, y + 1) + at(xi + 1, y + 1))
                            - (at(xi - 1, y - 1) + 2.0 * at(xi, y - 1) + at(xi + 1, y - 1));
                        (gx / 8.0, gy / 8.0)
                    }
                };
                gx_row[x] = gx;
                gy_row[x] = gy;
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp_image(width: usize, height: usize, slope_x: f32, slope_y: f32) -> Image<f32> {
        Image::from_fn(width, height, |col, row| {
            col as f32 * slope_x + row as f32 * slope_y
        })
    }

    #[test]
    fn horizontal_ramp_fills_only_the_zero_degree_bin() {
        let (width, height) = (40, 30);
        let image = ramp_image(width, height, 0.01, 0.0);
        let mut sift = DenseSiftImage::default();
        let config = DenseSiftConfig {
            presmoothing_sigma_px: 0.0,
            ..Default::default()
        };
        compute_dense_sift(
            image.view(),
            &config,
            &mut DenseSiftWorkspace::default(),
            &mut sift,
        )
        .unwrap();
        let centre = 15 * width + 20;
        let descriptor = sift.descriptor(centre);
        for (index, &value) in descriptor.iter().enumerate() {
            match index % ORIENTATION_BINS {
                // 16 equal cells: 255 / 4 each, minus the floor's share.
                0 => assert!((60..=64).contains(&value), "bin {index}: {value}"),
                // cos(45°)^9 ≈ 0.044 of the main bin.
                1 | 7 => assert!((1..=4).contains(&value), "bin {index}: {value}"),
                _ => assert_eq!(value, 0, "bin {index}"),
            }
        }
        // Mean gradient over the support is the slope (the 5-point filter is exact on ramps).
        assert!(
            (sift.support_gradient.data()[centre] - 0.01).abs() < 1e-4,
            "{}",
            sift.support_gradient.data()[centre]
        );
    }

    #[test]
    fn flat_image_gives_zero_descriptors_and_is_untextured() {
        let (width, height) = (20, 10);
        let image = Image::filled(width, height, 0.5f32);
        let mut sift = DenseSiftImage::default();
        compute_dense_sift(
            image.view(),
            &DenseSiftConfig::default(),
            &mut DenseSiftWorkspace::default(),
            &mut sift,
        )
        .unwrap();
        assert!(sift.descriptors.iter().all(|&byte| byte == 0));
        let mut textured = Image::default();
        sift.textured_mask(1e-3, &mut textured);
        assert_eq!(textured.size(), (width, height));
        assert!(textured.data().iter().all(|&is_textured| !is_textured));
    }

    #[test]
    fn vertical_ramp_uses_the_quarter_turn_bin_and_sobel_agrees() {
        let (width, height) = (30, 30);
        let image = ramp_image(width, height, 0.0, -0.02);
        for filter in [GradientFilter::CentralFivePoint, GradientFilter::Sobel] {
            let config = DenseSiftConfig {
                gradient_filter: filter,
                presmoothing_sigma_px: 0.0,
                ..Default::default()
            };
            let mut sift = DenseSiftImage::default();
            compute_dense_sift(
                image.view(),
                &config,
                &mut DenseSiftWorkspace::default(),
                &mut sift,
            )
            .unwrap();
            let descriptor = sift.descriptor(15 * width + 15);
            // Gradient points to -y: angle 3π/2, bin 6; the opposite half-plane (bins 1..=3) is empty.
            for cell in descriptor.chunks_exact(ORIENTATION_BINS) {
                let strongest = (0..ORIENTATION_BINS).max_by_key(|&bin| cell[bin]).unwrap();
                assert_eq!(strongest, 6, "{filter:?}: {cell:?}");
                assert!(
                    cell[1..=3].iter().all(|&value| value == 0),
                    "{filter:?}: {cell:?}"
                );
            }
        }
    }

    #[test]
    fn bad_inputs_are_rejected() {
        let mut sift = DenseSiftImage::default();
        let mut workspace = DenseSiftWorkspace::default();
        let empty = ImageView::new(0, 2, &[]).unwrap();
        let error = compute_dense_sift(
            empty,
            &DenseSiftConfig::default(),
            &mut workspace,
            &mut sift,
        );
        assert!(matches!(error, Err(FlowError::EmptyImage { .. })));
        let config = DenseSiftConfig {
            cell_size_px: 0,
            ..Default::default()
        };
        let image = ImageView::new(2, 2, &[0.0; 4]).unwrap();
        let error = compute_dense_sift(image, &config, &mut workspace, &mut sift);
        assert!(matches!(
            error,
            Err(FlowError::InvalidConfig {
                field: "cell_size_px",
                ..
            })
        ));
        let parsed: Result<DenseSiftConfig, _> = serde_json::from_str(r#"{"cell_size": 3}"#);
        assert!(parsed.is_err());
    }
}
