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

/// Bytes that start on a 64-byte boundary (a cache line) and come in whole lines: with 128-byte
/// descriptors every descriptor then fills two lines and no 32-byte load of one crosses a line.
/// glibc gives a `Vec<u8>` of this size 16 bytes past a page (from `mmap`), or 16-byte alignment
/// (from the heap), where half of those loads cross one: measured −7.5 % of the data term's CPU time with aligned descriptors
/// (docs/measurements.md, branch `speed24`). Reads and writes as a byte slice.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct DescriptorBytes {
    lines: Vec<CacheLine>,
}

/// One 64-byte line of [`DescriptorBytes`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(C, align(64))]
struct CacheLine([u8; 64]);

// SAFETY: `CacheLine` is 64 bytes of `u8` with alignment 64: no padding, every bit pattern valid,
// all zeros valid.
unsafe impl bytemuck::Zeroable for CacheLine {}
// SAFETY: as above; `Copy` and `'static`.
unsafe impl bytemuck::Pod for CacheLine {}

impl DescriptorBytes {
    /// Bytes of `len` (a multiple of 64), each set to `value` where the storage grows.
    pub fn resize(&mut self, len: usize, value: u8) {
        assert!(len % 64 == 0, "{len} bytes are not whole 64-byte lines");
        self.lines.resize(len / 64, CacheLine([value; 64]));
    }

    /// Bytes made of `bytes` (a multiple of 64 of them).
    pub fn from_bytes(bytes: &[u8]) -> Self {
        let mut out = Self::default();
        out.resize(bytes.len(), 0);
        out.copy_from_slice(bytes);
        out
    }
}

impl std::ops::Deref for DescriptorBytes {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        bytemuck::cast_slice(&self.lines)
    }
}

impl std::ops::DerefMut for DescriptorBytes {
    fn deref_mut(&mut self) -> &mut [u8] {
        bytemuck::cast_slice_mut(&mut self.lines)
    }
}

/// A dense SIFT image: a descriptor for every pixel, row major.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DenseSiftImage {
    pub width_px: usize,
    pub height_px: usize,
    /// `width_px · height_px · 128` bytes; pixel `p`'s descriptor is `[p·128, (p+1)·128)`.
    pub descriptors: DescriptorBytes,
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

/// Compiles `fn $name` twice, for the x86-64 baseline and for AVX2, and picks the AVX2 copy at run
/// time when the CPU has it (the detection is cached). The body is plain Rust that the compiler
/// vectorises; both copies perform the same operations in the same order, so they give identical
/// results.
macro_rules! multiversioned {
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $body:block) => {
        $(#[$meta])*
        $vis fn $name($($arg: $ty),*) {
            #[inline(always)]
            fn generic($($arg: $ty),*) $body
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2")]
            unsafe fn avx2($($arg: $ty),*) {
                generic($($arg),*)
            }
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2 (checked just above).
                return unsafe { avx2($($arg),*) };
            }
            generic($($arg),*)
        }
    };
}
pub(crate) use multiversioned;

/// Scratch buffers reused between calls (no allocation once they have grown to the image size).
#[derive(Debug, Default)]
pub struct DenseSiftWorkspace {
    smoothed: Vec<f32>,
    smoothing_scratch: Vec<f32>,
    /// Orientation energies pooled along x, 8 per pixel (pixel-major).
    bands_pooled_rows: Vec<f32>,
    /// Gradient magnitude pooled along x.
    magnitude_pooled_rows: Vec<f32>,
    /// Both passes of the pooling: 8 energies per pixel, and the magnitude.
    bands_pooled: Vec<f32>,
    magnitude_pooled: Vec<f32>,
    /// Per pooled pixel, the sum of its 8 squared energies.
    squares: Vec<f32>,
    /// Per pixel, the sum of `squares` over its 4 sample columns.
    sample_squares: Vec<f32>,
}

/// Rows per parallel task of the band step (its per-task scratch is a few rows long).
const BAND_ROWS_PER_TASK: usize = 16;

/// Computes the dense SIFT image of a grey `image` into `out`.
///
/// The steps run as separable row passes over planar (one value per pixel) and pixel-major
/// 8-band images that the compiler vectorises, each pass with the operations of the definition
/// in their order (so the pooled energies are exactly those of a straightforward implementation);
/// only the descriptor's norm sums its 128 squares in a different order (8 partial sums), which
/// can move a byte by one where `v · 255 / ‖v‖` falls within a rounding error of an integer.
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

    // 1–3a. Per row: derivatives, orientation energies, pooling along x.
    let bin_directions: [(f32, f32); ORIENTATION_BINS] = std::array::from_fn(|bin| {
        let angle = std::f32::consts::TAU * bin as f32 / ORIENTATION_BINS as f32;
        (angle.cos(), angle.sin())
    });
    let directions = BinDirections {
        cos: bin_directions.map(|(cos, _)| cos),
        sin: bin_directions.map(|(_, sin)| sin),
    };
    let sharpness = config.orientation_sharpness as u32;
    let cell = config.cell_size_px;
    let mut pooling_taps = vec![0.0f32; 2 * cell + 1];
    pooling_taps[0] = 0.25;
    for tap in pooling_taps.iter_mut().take(cell + 2).skip(2) {
        *tap = 1.0;
    }
    let pooling_weight_sum: f32 = pooling_taps.iter().sum();
    let pooling = nonzero_taps(&pooling_taps, cell);
    let band_row_len = width_px * ORIENTATION_BINS;
    ws.bands_pooled_rows
        .resize(pixel_count * ORIENTATION_BINS, 0.0);
    ws.magnitude_pooled_rows.resize(pixel_count, 0.0);
    let filter = config.gradient_filter;
    ws.bands_pooled_rows
        .par_chunks_mut(BAND_ROWS_PER_TASK * band_row_len)
        .zip(
            ws.magnitude_pooled_rows
                .par_chunks_mut(BAND_ROWS_PER_TASK * width_px),
        )
        .enumerate()
        .for_each(|(task, (bands_rows, magnitude_rows))| {
            let mut scratch = vec![0.0f32; width_px * (2 + ORIENTATION_BINS + 1)];
            let (gradients, rest) = scratch.split_at_mut(2 * width_px);
            let (gradient_x, gradient_y) = gradients.split_at_mut(width_px);
            let (band_row, magnitude_row) = rest.split_at_mut(band_row_len);
            for (row_in_task, (bands_out, magnitude_out)) in bands_rows
                .chunks_exact_mut(band_row_len)
                .zip(magnitude_rows.chunks_exact_mut(width_px))
                .enumerate()
            {
                let y = task * BAND_ROWS_PER_TASK + row_in_task;
                gradient_row(
                    source, width_px, height_px, y, filter, gradient_x, gradient_y,
                );
                orientation_band_row(
                    gradient_x,
                    gradient_y,
                    &directions,
                    sharpness,
                    band_row,
                    magnitude_row,
                );
                filter_row_clamped(band_row, ORIENTATION_BINS, &pooling, cell, bands_out);
                filter_row_clamped(magnitude_row, 1, &pooling, cell, magnitude_out);
            }
        });

    // 3b. Pooling along y.
    ws.bands_pooled.resize(pixel_count * ORIENTATION_BINS, 0.0);
    ws.magnitude_pooled.resize(pixel_count, 0.0);
    filter_columns_clamped(
        &ws.bands_pooled_rows,
        band_row_len,
        height_px,
        &pooling,
        cell,
        &mut ws.bands_pooled,
    );
    filter_columns_clamped(
        &ws.magnitude_pooled_rows,
        width_px,
        height_px,
        &pooling,
        cell,
        &mut ws.magnitude_pooled,
    );

    // 4. Per pooled pixel the sum of its 8 squared energies, then per pixel the sums of those over
    //    its 4 sample columns: the norm of a descriptor is the sum of 4 such values.
    ws.squares.resize(pixel_count, 0.0);
    ws.sample_squares.resize(pixel_count, 0.0);
    ws.squares
        .par_chunks_mut(width_px)
        .zip(ws.sample_squares.par_chunks_mut(width_px))
        .zip(ws.bands_pooled.par_chunks(band_row_len))
        .for_each(|((squares, sample_squares), bands)| {
            squares_row(bands, squares);
            sample_sums_row(squares, cell, sample_squares);
        });

    // 5. Sampling of the 4×4 cells and normalisation.
    out.resize(width_px, height_px, true);
    let (bands, magnitudes, sample_squares) =
        (&ws.bands_pooled, &ws.magnitude_pooled, &ws.sample_squares);
    let normalisation = Normalisation {
        floor: config.normalisation_floor,
        support_scale: 1.0 / (16.0 * pooling_weight_sum * pooling_weight_sum),
    };
    out.descriptors
        .par_chunks_mut(width_px * DESCRIPTOR_LEN)
        .zip(out.support_gradient.data_mut().par_chunks_mut(width_px))
        .enumerate()
        .for_each(|(y, (descriptor_row, support_row))| {
            let sample_rows: [usize; 4] = CELL_OFFSETS
                .map(|offset| clamp_index(y as isize + offset * cell as isize, height_px));
            support_sums_row(
                sample_rows.map(|row| &magnitudes[row * width_px..(row + 1) * width_px]),
                cell,
                normalisation.support_scale,
                support_row,
            );
            descriptor_row_kernel(
                sample_rows.map(|row| &bands[row * band_row_len..(row + 1) * band_row_len]),
                sample_rows.map(|row| &sample_squares[row * width_px..(row + 1) * width_px]),
                cell,
                normalisation.floor,
                descriptor_row,
            );
        });
    Ok(())
}

/// `cos θ_k`, `sin θ_k` of the 8 bins.
struct BinDirections {
    cos: [f32; ORIENTATION_BINS],
    sin: [f32; ORIENTATION_BINS],
}

#[derive(Clone, Copy)]
struct Normalisation {
    floor: f32,
    support_scale: f32,
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

/// The non-zero taps as `(index, weight)`, index `0..=2·radius` standing for offset `index − radius`.
fn nonzero_taps(taps: &[f32], radius: usize) -> Vec<(usize, f32)> {
    debug_assert_eq!(taps.len(), 2 * radius + 1);
    taps.iter()
        .enumerate()
        .filter(|(_, &weight)| weight != 0.0)
        .map(|(index, &weight)| (index, weight))
        .collect()
}

/// Correlates a `channels`-interleaved image with `taps` (offsets `-radius..=radius`) along x and
/// then along y, clamping at the borders. `rows_scratch` receives the horizontal pass. Each output
/// value is `((0 + v₀·w₀) + v₁·w₁) + …` over the non-zero taps in order.
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
    let nonzero = nonzero_taps(taps, radius);
    rows_scratch
        .par_chunks_mut(row_len)
        .zip(input.par_chunks(row_len))
        .for_each(|(out_row, in_row)| {
            filter_row_clamped(in_row, channels, &nonzero, radius, out_row)
        });
    filter_columns_clamped(rows_scratch, row_len, height_px, &nonzero, radius, output);
}

/// `out[x] = Σ_k in[clamp(x + index_k − radius)] · w_k` on one row of `channels`-interleaved
/// pixels: shifted whole-slice passes inside, clamped reads at the two ends.
fn filter_row_clamped(
    input: &[f32],
    channels: usize,
    taps: &[(usize, f32)],
    radius: usize,
    out: &mut [f32],
) {
    filter_row_kernel(input, channels, taps, radius, out)
}

multiversioned! {
    fn filter_row_kernel(
        input: &[f32],
        channels: usize,
        taps: &[(usize, f32)],
        radius: usize,
        out: &mut [f32],
    ) {
        let width = input.len() / channels;
        let interior = radius..width.saturating_sub(radius).max(radius);
        out.fill(0.0);
        if !interior.is_empty() {
            let interior_len = interior.len() * channels;
            let out_interior = &mut out[interior.start * channels..interior.end * channels];
            for &(index, weight) in taps {
                let source = &input[index * channels..index * channels + interior_len];
                for (value, &input_value) in out_interior.iter_mut().zip(source) {
                    *value += input_value * weight;
                }
            }
        }
        for x in (0..width).filter(|x| !interior.contains(x)) {
            let out = &mut out[x * channels..(x + 1) * channels];
            for &(index, weight) in taps {
                let source_x = clamp_index(x as isize + index as isize - radius as isize, width);
                let source = &input[source_x * channels..(source_x + 1) * channels];
                for (value, &input_value) in out.iter_mut().zip(source) {
                    *value += input_value * weight;
                }
            }
        }
    }
}

/// The vertical pass: `out[y] = Σ_k rows[clamp(y + index_k − radius)] · w_k`, row by row.
fn filter_columns_clamped(
    rows: &[f32],
    row_len: usize,
    height_px: usize,
    taps: &[(usize, f32)],
    radius: usize,
    output: &mut [f32],
) {
    output
        .par_chunks_mut(row_len)
        .enumerate()
        .for_each(|(y, out_row)| {
            let sources: Vec<(&[f32], f32)> = taps
                .iter()
                .map(|&(index, weight)| {
                    let source_y =
                        clamp_index(y as isize + index as isize - radius as isize, height_px);
                    (&rows[source_y * row_len..(source_y + 1) * row_len], weight)
                })
                .collect();
            weighted_row_sum(&sources, out_row);
        });
}

multiversioned! {
    fn weighted_row_sum(sources: &[(&[f32], f32)], out: &mut [f32]) {
        out.fill(0.0);
        for &(source, weight) in sources {
            for (value, &input_value) in out.iter_mut().zip(source) {
                *value += input_value * weight;
            }
        }
    }
}

/// The derivatives of row `y` of `image` (clamped borders).
fn gradient_row(
    image: &[f32],
    width_px: usize,
    height_px: usize,
    y: usize,
    filter: GradientFilter,
    gradient_x: &mut [f32],
    gradient_y: &mut [f32],
) {
    let row = |offset: isize| {
        let source_y = clamp_index(y as isize + offset, height_px);
        &image[source_y * width_px..(source_y + 1) * width_px]
    };
    match filter {
        GradientFilter::CentralFivePoint => {
            central_five_point_rows(
                row(0),
                [row(-2), row(-1), row(1), row(2)],
                gradient_x,
                gradient_y,
            );
        }
        GradientFilter::Sobel => {
            let rows = [row(-1), row(0), row(1)];
            for x in 0..width_px {
                let at = |dx: isize, row: usize| rows[row][clamp_index(x as isize + dx, width_px)];
                let gx = (at(1, 0) + 2.0 * at(1, 1) + at(1, 2))
                    - (at(-1, 0) + 2.0 * at(-1, 1) + at(-1, 2));
                let gy = (at(-1, 2) + 2.0 * at(0, 2) + at(1, 2))
                    - (at(-1, 0) + 2.0 * at(0, 0) + at(1, 0));
                gradient_x[x] = gx / 8.0;
                gradient_y[x] = gy / 8.0;
            }
        }
    }
}

multiversioned! {
    /// `[1, -8, 0, 8, -1] / 12` along the row (`centre`) and across `rows` (y − 2, y − 1, y + 1,
    /// y + 2), as `(((a − 8b) + 8c) − d) / 12`.
    fn central_five_point_rows(
        centre: &[f32],
        rows: [&[f32]; 4],
        gradient_x: &mut [f32],
        gradient_y: &mut [f32],
    ) {
        let five_point = |a: f32, b: f32, c: f32, d: f32| (a - 8.0 * b + 8.0 * c - d) / 12.0;
        let width = centre.len();
        if width > 4 {
            for (x, value) in gradient_x[2..width - 2].iter_mut().enumerate() {
                *value = five_point(centre[x], centre[x + 1], centre[x + 3], centre[x + 4]);
            }
        }
        for x in (0..width).filter(|&x| x < 2 || x + 2 >= width) {
            let at = |dx: isize| centre[clamp_index(x as isize + dx, width)];
            gradient_x[x] = five_point(at(-2), at(-1), at(1), at(2));
        }
        let [above2, above1, below1, below2] = rows;
        for ((((value, &a), &b), &c), &d) in gradient_y
            .iter_mut()
            .zip(above2)
            .zip(above1)
            .zip(below1)
            .zip(below2)
        {
            *value = five_point(a, b, c, d);
        }
    }
}

multiversioned! {
    /// Per pixel: the gradient magnitude and the 8 energies `max(cos(θ − θ_k), 0)^e · |g|`
    /// (pixel-major), with `x^e` by the same square-and-multiply as `f32::powi`.
    fn orientation_band_row(
        gradient_x: &[f32],
        gradient_y: &[f32],
        directions: &BinDirections,
        sharpness: u32,
        bands: &mut [f32],
        magnitudes: &mut [f32],
    ) {
        for (((&gx, &gy), bands), magnitude_out) in gradient_x
            .iter()
            .zip(gradient_y)
            .zip(bands.chunks_exact_mut(ORIENTATION_BINS))
            .zip(magnitudes.iter_mut())
        {
            let magnitude = (gx * gx + gy * gy).sqrt();
            let inverse = if magnitude > 0.0 { 1.0 / magnitude } else { 0.0 };
            let mut base = [0.0f32; ORIENTATION_BINS];
            for (bin, value) in base.iter_mut().enumerate() {
                let cosine = (gx * directions.cos[bin] + gy * directions.sin[bin]) * inverse;
                *value = if cosine > 0.0 { cosine } else { 0.0 };
            }
            // compiler-builtins' `__powisf2` (what `powi` with a run-time exponent calls).
            let mut power = [1.0f32; ORIENTATION_BINS];
            let mut exponent = sharpness;
            loop {
                if exponent & 1 != 0 {
                    for bin in 0..ORIENTATION_BINS {
                        power[bin] *= base[bin];
                    }
                }
                exponent >>= 1;
                if exponent == 0 {
                    break;
                }
                for value in &mut base {
                    *value *= *value;
                }
            }
            for (band, &value) in bands.iter_mut().zip(&power) {
                *band = value * magnitude;
            }
            *magnitude_out = magnitude;
        }
    }
}

multiversioned! {
    /// `Σ_b v_b²` of each pixel's 8 pooled energies, as `((v0² + v1²) + (v2² + v3²)) + ((v4² +
    /// v5²) + (v6² + v7²))`.
    fn squares_row(bands: &[f32], squares: &mut [f32]) {
        for (square, values) in squares.iter_mut().zip(bands.chunks_exact(ORIENTATION_BINS)) {
            let v: [f32; ORIENTATION_BINS] = values.try_into().expect("8 bins");
            *square = ((v[0] * v[0] + v[1] * v[1]) + (v[2] * v[2] + v[3] * v[3]))
                + ((v[4] * v[4] + v[5] * v[5]) + (v[6] * v[6] + v[7] * v[7]));
        }
    }
}

multiversioned! {
    /// `out[x] = ((v[x − c] + v[x]) + v[x + c]) + v[x + 2c]` (clamped): a row's values summed over
    /// each pixel's 4 sample columns.
    fn sample_sums_row(values: &[f32], cell: usize, out: &mut [f32]) {
        let width = values.len();
        let interior = cell..width.saturating_sub(2 * cell).max(cell);
        for (x, value) in out.iter_mut().enumerate().take(interior.end).skip(interior.start) {
            *value = ((values[x - cell] + values[x]) + values[x + cell]) + values[x + 2 * cell];
        }
        for x in (0..width).filter(|x| !interior.contains(x)) {
            let at = |offset: isize| values[clamp_index(x as isize + offset * cell as isize, width)];
            out[x] = ((at(-1) + at(0)) + at(1)) + at(2);
        }
    }
}

multiversioned! {
    /// The support of each pixel of a row: the 16 pooled magnitudes of its cells summed in order
    /// (rows outer, columns inner, from 0), times `scale`.
    fn support_sums_row(rows: [&[f32]; 4], cell: usize, scale: f32, out: &mut [f32]) {
        let width = out.len();
        let interior = cell..width.saturating_sub(2 * cell).max(cell);
        for (x, value) in out.iter_mut().enumerate().take(interior.end).skip(interior.start) {
            let mut sum = 0.0f32;
            for row in &rows {
                sum += row[x - cell];
                sum += row[x];
                sum += row[x + cell];
                sum += row[x + 2 * cell];
            }
            *value = sum * scale;
        }
        for x in (0..width).filter(|x| !interior.contains(x)) {
            let mut sum = 0.0f32;
            for row in &rows {
                for offset in CELL_OFFSETS {
                    sum += row[clamp_index(x as isize + offset * cell as isize, width)];
                }
            }
            out[x] = sum * scale;
        }
    }
}

/// One row of descriptors from the pooled energies of its 4 sample rows (pixel-major, 8 per pixel)
/// and their per-pixel sums of squares over the sample columns: explicit AVX2 where the CPU has it
/// (the compiler turns the float-to-byte conversion into scalar code), the same arithmetic in
/// plain Rust elsewhere.
fn descriptor_row_kernel(
    band_rows: [&[f32]; 4],
    sample_square_rows: [&[f32]; 4],
    cell: usize,
    floor: f32,
    descriptors: &mut [u8],
) {
    let width = descriptors.len() / DESCRIPTOR_LEN;
    assert!(band_rows
        .iter()
        .all(|row| row.len() == width * ORIENTATION_BINS));
    assert!(sample_square_rows.iter().all(|row| row.len() == width));
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just above); the slice lengths are checked above.
        unsafe { descriptor_row_avx2(band_rows, sample_square_rows, cell, floor, descriptors) };
        return;
    }
    descriptor_row_portable(band_rows, sample_square_rows, cell, floor, descriptors);
}

/// `255 / (‖v‖ + floor)` of pixel `x`, from its sample rows' sums of squares (added in row order).
#[inline(always)]
fn descriptor_scale(sample_square_rows: &[&[f32]; 4], x: usize, floor: f32) -> f32 {
    let [a, b, c, d] = sample_square_rows;
    255.0 / ((((a[x] + b[x]) + c[x]) + d[x]).sqrt() + floor)
}

/// The 4 sample columns of pixel `x`'s cells.
#[inline(always)]
fn sample_columns(x: usize, width: usize, cell: usize) -> [usize; 4] {
    CELL_OFFSETS.map(|offset| clamp_index(x as isize + offset * cell as isize, width))
}

/// The descriptor kernel in plain Rust. `v · scale < 255` for every energy `v` (each is at most the
/// norm), so the conversion needs no clamping.
fn descriptor_row_portable(
    band_rows: [&[f32]; 4],
    sample_square_rows: [&[f32]; 4],
    cell: usize,
    floor: f32,
    descriptors: &mut [u8],
) {
    let width = descriptors.len() / DESCRIPTOR_LEN;
    for (x, descriptor) in descriptors.chunks_exact_mut(DESCRIPTOR_LEN).enumerate() {
        let scale = descriptor_scale(&sample_square_rows, x, floor);
        let columns = sample_columns(x, width, cell);
        let mut bytes = descriptor.chunks_exact_mut(ORIENTATION_BINS);
        for bands in &band_rows {
            for &sample_x in &columns {
                let values = &bands[sample_x * ORIENTATION_BINS..(sample_x + 1) * ORIENTATION_BINS];
                for (byte, &value) in bytes.next().expect("16 cells").iter_mut().zip(values) {
                    *byte = (value * scale) as u8;
                }
            }
        }
    }
}

/// [`descriptor_row_portable`] in AVX2: one register per cell, four cells packed into 32 bytes.
///
/// # Safety
/// The CPU must have AVX2; every band row holds `8 · width` values and every sample-squares row
/// `width`, `width = descriptors.len() / 128` (as [`descriptor_row_kernel`] checks).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn descriptor_row_avx2(
    band_rows: [&[f32]; 4],
    sample_square_rows: [&[f32]; 4],
    cell: usize,
    floor: f32,
    descriptors: &mut [u8],
) {
    use std::arch::x86_64::*;
    let width = descriptors.len() / DESCRIPTOR_LEN;
    // packs/packus leave 32-bit groups in the order a0 b0 c0 d0 | a1 b1 c1 d1.
    let unshuffle = _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
    for x in 0..width {
        let scale = _mm256_set1_ps(descriptor_scale(&sample_square_rows, x, floor));
        let columns = sample_columns(x, width, cell);
        let out = descriptors.as_mut_ptr().add(x * DESCRIPTOR_LEN);
        for (quad, bands) in band_rows.iter().enumerate() {
            // SAFETY: every column is below `width` and the row holds 8 · width values.
            let bytes: [__m256i; 4] = std::array::from_fn(|index| unsafe {
                let value = _mm256_loadu_ps(bands.as_ptr().add(columns[index] * ORIENTATION_BINS));
                _mm256_cvttps_epi32(_mm256_mul_ps(value, scale))
            });
            let low = _mm256_packs_epi32(bytes[0], bytes[1]);
            let high = _mm256_packs_epi32(bytes[2], bytes[3]);
            let packed = _mm256_permutevar8x32_epi32(_mm256_packus_epi16(low, high), unshuffle);
            // SAFETY: the row holds 128 · width bytes; this writes bytes 32·quad.. of pixel x.
            _mm256_storeu_si256(out.add(quad * 32) as *mut __m256i, packed);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp_image(width: usize, height: usize, slope_x: f32, slope_y: f32) -> Image<f32> {
        Image::from_fn(width, height, |col, row| {
            col as f32 * slope_x + row as f32 * slope_y
        })
    }

    /// The definition, computed the straightforward way (the code before the vectorised passes):
    /// 9-channel interleaved bands, clamped reads everywhere, the norm summed in order.
    fn reference_dense_sift(image: &Image<f32>, config: &DenseSiftConfig) -> DenseSiftImage {
        let (width, height) = image.size();
        let filter = |input: &[f32], channels: usize, taps: &[f32], radius: usize| {
            let taps: Vec<(isize, f32)> = taps
                .iter()
                .enumerate()
                .filter(|(_, &weight)| weight != 0.0)
                .map(|(index, &weight)| (index as isize - radius as isize, weight))
                .collect();
            let mut rows = vec![0.0f32; input.len()];
            for y in 0..height {
                for x in 0..width {
                    for (offset, weight) in &taps {
                        let source = clamp_index(x as isize + offset, width);
                        for channel in 0..channels {
                            rows[(y * width + x) * channels + channel] +=
                                input[(y * width + source) * channels + channel] * weight;
                        }
                    }
                }
            }
            let mut out = vec![0.0f32; input.len()];
            for y in 0..height {
                for (offset, weight) in &taps {
                    let source = clamp_index(y as isize + offset, height);
                    for index in 0..width * channels {
                        out[y * width * channels + index] +=
                            rows[source * width * channels + index] * weight;
                    }
                }
            }
            out
        };
        let smoothed = filter(
            image.data(),
            1,
            &gaussian_taps(config.presmoothing_sigma_px, 3),
            3,
        );
        let at =
            |x: isize, y: isize| smoothed[clamp_index(y, height) * width + clamp_index(x, width)];
        let mut bands = vec![0.0f32; width * height * 9];
        for y in 0..height as isize {
            for x in 0..width as isize {
                let gx =
                    (at(x - 2, y) - 8.0 * at(x - 1, y) + 8.0 * at(x + 1, y) - at(x + 2, y)) / 12.0;
                let gy =
                    (at(x, y - 2) - 8.0 * at(x, y - 1) + 8.0 * at(x, y + 1) - at(x, y + 2)) / 12.0;
                let magnitude = (gx * gx + gy * gy).sqrt();
                let inverse = if magnitude > 0.0 {
                    1.0 / magnitude
                } else {
                    0.0
                };
                let pixel = (y as usize * width + x as usize) * 9;
                for bin in 0..8 {
                    let angle = std::f32::consts::TAU * bin as f32 / 8.0;
                    let cosine = ((gx * angle.cos() + gy * angle.sin()) * inverse).max(0.0);
                    bands[pixel + bin] = cosine.powi(config.orientation_sharpness) * magnitude;
                }
                bands[pixel + 8] = magnitude;
            }
        }
        let cell = config.cell_size_px;
        let mut taps = vec![0.0f32; 2 * cell + 1];
        taps[0] = 0.25;
        taps[2..cell + 2].fill(1.0);
        let weight_sum: f32 = taps.iter().sum();
        let pooled = filter(&bands, 9, &taps, cell);
        let mut out = DenseSiftImage::default();
        out.resize(width, height, true);
        for y in 0..height {
            for x in 0..width {
                let mut cells = [0.0f32; DESCRIPTOR_LEN];
                let mut support = 0.0f32;
                for (row, &dy) in CELL_OFFSETS.iter().enumerate() {
                    for (column, &dx) in CELL_OFFSETS.iter().enumerate() {
                        let sample_y = clamp_index(y as isize + dy * cell as isize, height);
                        let sample_x = clamp_index(x as isize + dx * cell as isize, width);
                        let at = (sample_y * width + sample_x) * 9;
                        cells[(row * 4 + column) * 8..(row * 4 + column + 1) * 8]
                            .copy_from_slice(&pooled[at..at + 8]);
                        support += pooled[at + 8];
                    }
                }
                let norm = cells.iter().map(|value| value * value).sum::<f32>().sqrt();
                let scale = 255.0 / (norm + config.normalisation_floor);
                let pixel = y * width + x;
                for (byte, value) in out.descriptors[pixel * 128..(pixel + 1) * 128]
                    .iter_mut()
                    .zip(&cells)
                {
                    *byte = (value * scale).min(255.0) as u8;
                }
                out.support_gradient.data_mut()[pixel] =
                    support * (1.0 / (16.0 * weight_sum * weight_sum));
            }
        }
        out
    }

    #[test]
    fn descriptor_bytes_start_on_a_cache_line() {
        let mut bytes = DescriptorBytes::default();
        for len in [128, 64 * 1001, 505 * 275 * 128, 0, 256] {
            bytes.resize(len, 7);
            assert_eq!(bytes.len(), len);
            assert_eq!(bytes.as_ptr() as usize % 64, 0, "{len} bytes");
        }
        assert_eq!(&*bytes, &[7u8; 256][..]);
        bytes[3] = 9;
        let copy = DescriptorBytes::from_bytes(&bytes);
        assert_eq!(copy, bytes);
        assert_eq!(copy[3], 9);
        let mut image = DenseSiftImage::default();
        image.resize(37, 5, false);
        assert_eq!(image.descriptors.as_ptr() as usize % 64, 0);
    }

    #[test]
    fn vectorised_passes_match_the_definition() {
        // Odd sizes (and one narrower than the filters' reach) exercise the clamped borders.
        let config = DenseSiftConfig::default();
        let pair = crate::core::sift_flow::test_support::load_pair(
            &crate::test_data::repo_data("flow-pairs"),
            "dji0024_505x275",
        );
        let crop = |width: usize, height: usize| {
            Image::from_fn(width, height, |x, y| pair.first.data()[y * 505 + x + 40])
        };
        let mut workspace = DenseSiftWorkspace::default();
        for image in [pair.first.clone(), crop(101, 57), crop(5, 9)] {
            let expected = reference_dense_sift(&image, &config);
            let mut got = DenseSiftImage::default();
            compute_dense_sift(image.view(), &config, &mut workspace, &mut got).unwrap();
            assert!(
                got.support_gradient == expected.support_gradient,
                "support gradients differ"
            );
            // Only the norm's summation order differs: a byte may move by one.
            let differing = got
                .descriptors
                .iter()
                .zip(expected.descriptors.iter())
                .filter(|(a, b)| a != b)
                .count();
            assert!(got
                .descriptors
                .iter()
                .zip(expected.descriptors.iter())
                .all(|(&a, &b)| a.abs_diff(b) <= 1));
            println!(
                "{}x{}: {differing} of {} bytes differ by one",
                image.width_px(),
                image.height_px(),
                got.descriptors.len()
            );
            assert!(
                differing * 10_000 <= got.descriptors.len(),
                "{differing} of {} bytes differ",
                got.descriptors.len()
            );
            // The plain-Rust descriptor kernel gives the bytes of the dispatched (AVX2) one.
            let (width, height) = image.size();
            let cell = config.cell_size_px;
            for y in 0..height {
                let rows = CELL_OFFSETS
                    .map(|offset| clamp_index(y as isize + offset * cell as isize, height));
                let mut descriptors = vec![0u8; width * DESCRIPTOR_LEN];
                descriptor_row_portable(
                    rows.map(|row| &workspace.bands_pooled[row * width * 8..(row + 1) * width * 8]),
                    rows.map(|row| &workspace.sample_squares[row * width..(row + 1) * width]),
                    cell,
                    config.normalisation_floor,
                    &mut descriptors,
                );
                assert!(
                    descriptors == got.descriptors[y * width * 128..(y + 1) * width * 128],
                    "row {y}"
                );
            }
        }
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
