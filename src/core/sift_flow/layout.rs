//! The row-block layout that belief propagation and the cost volume share: 16 image rows side by
//! side in the 16 lanes of a vector, each row shifted one position right of the row above, so that
//! one step of a raster sweep updates 16 pixels whose left and upper neighbours were updated in
//! the steps before (a wavefront).
//!
//! Pixel `(x, y)` of a `width × height` grid lives in lane `y mod 16` of vector
//! `(y div 16) · positions + x + y mod 16`, `positions = width + 15`. The other lanes (`x` outside
//! the image, rows past the bottom) are padding.

use super::simd::{Lanes, LANES};

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) struct Layout {
    pub(super) width: usize,
    pub(super) height: usize,
    /// Blocks of 16 rows.
    pub(super) blocks: usize,
    /// Vectors per block.
    pub(super) positions: usize,
}

impl Layout {
    pub(super) fn new(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            blocks: height.div_ceil(LANES),
            positions: width + LANES - 1,
        }
    }

    /// Vectors in the whole grid.
    pub(super) fn vectors(&self) -> usize {
        self.blocks * self.positions
    }

    /// `(vector, lane)` of pixel `(x, y)`.
    #[inline(always)]
    pub(super) fn locate(&self, x: usize, y: usize) -> (usize, usize) {
        let lane = y % LANES;
        ((y / LANES) * self.positions + x + lane, lane)
    }

    /// Writes a row-major image into the layout (`to_lanes(value)` per pixel), padding zero.
    pub(super) fn skew<T: Copy>(
        &self,
        rows: &[T],
        to_lane: impl Fn(T) -> u16,
        out: &mut Vec<Lanes>,
    ) {
        debug_assert_eq!(rows.len(), self.width * self.height);
        out.clear();
        out.resize(self.vectors(), Lanes::default());
        for (y, row) in rows.chunks_exact(self.width).enumerate() {
            let (first, lane) = self.locate(0, y);
            for (vector, &value) in out[first..first + self.width].iter_mut().zip(row) {
                vector.0[lane] = to_lane(value);
            }
        }
    }

    /// Calls `visit(x, y, vector, lane)` for every pixel, vector by vector: block by block, within
    /// a block position by position, within a position its pixels' lanes in order. Reads of
    /// per-vector data (the cost volume) then touch each vector once.
    #[inline(always)]
    pub(super) fn for_each_pixel_by_vector(
        &self,
        mut visit: impl FnMut(usize, usize, usize, usize),
    ) {
        for block in 0..self.blocks {
            let rows = LANES.min(self.height - block * LANES);
            for position in 0..self.positions {
                // Lane `lane` holds pixel `x = position − lane`, inside when `x < width`.
                let first_lane = (position + 1).saturating_sub(self.width);
                let last_lane = rows.min(position + 1);
                for lane in first_lane..last_lane {
                    visit(
                        position - lane,
                        block * LANES + lane,
                        block * self.positions + position,
                        lane,
                    );
                }
            }
        }
    }

    /// Calls `visit(x, y, vector, lane)` for every pixel, row by row.
    #[inline(always)]
    pub(super) fn for_each_pixel(&self, mut visit: impl FnMut(usize, usize, usize, usize)) {
        for y in 0..self.height {
            let (first, lane) = self.locate(0, y);
            for x in 0..self.width {
                visit(x, y, first + x, lane);
            }
        }
    }
}

/// Grows `buffer` to at least `len` values (never shrinks it, so that buffers reused for grids of
/// different sizes are zero-filled only once) and returns its first `len`.
pub(super) fn grown(buffer: &mut Vec<Lanes>, len: usize) -> &mut [Lanes] {
    if buffer.len() < len {
        buffer.resize(len, Lanes::default());
    }
    &mut buffer[..len]
}

/// Matching costs in the layout: `labels²` vectors per position, index `label_v · labels +
/// label_u` within a position; padding lanes hold 0.
#[derive(Debug, Default)]
pub(super) struct CostVolume {
    pub(super) layout: Layout,
    pub(super) labels: usize,
    /// At least `layout.vectors() · labels²` (see [`CostVolume::costs`]).
    storage: Vec<Lanes>,
}

impl CostVolume {
    /// Sizes the volume; the contents are then undefined until every pixel is written, except the
    /// padding, which this sets to 0.
    pub(super) fn reset(&mut self, layout: Layout, labels: usize) {
        self.layout = layout;
        self.labels = labels;
        let window = labels * labels;
        let costs = grown(&mut self.storage, layout.vectors() * window);
        // Padding: the first and last 15 positions of every block, and whole blocks' lanes past
        // the bottom (zeroed as whole blocks; the pixels are written afterwards).
        for block in costs.chunks_exact_mut(layout.positions * window) {
            let padding = (LANES - 1).min(layout.positions) * window;
            block[..padding].fill(Lanes::default());
            let tail = block.len() - padding;
            block[tail..].fill(Lanes::default());
        }
        if layout.height % LANES != 0 {
            if let Some(last) = costs.chunks_exact_mut(layout.positions * window).last() {
                last.fill(Lanes::default());
            }
        }
    }

    /// The costs, `labels²` vectors per position.
    #[inline(always)]
    pub(super) fn costs(&self) -> &[Lanes] {
        &self.storage[..self.layout.vectors() * self.labels * self.labels]
    }

    /// The cost of pixel `(x, y)` at labels `(label_u, label_v)`.
    #[cfg(test)]
    pub(super) fn cost(&self, x: usize, y: usize, label_u: usize, label_v: usize) -> u16 {
        let (vector, lane) = self.layout.locate(x, y);
        self.costs()[vector * self.labels * self.labels + label_v * self.labels + label_u].0[lane]
    }

    pub(super) fn costs_mut(&mut self) -> &mut [Lanes] {
        let len = self.layout.vectors() * self.labels * self.labels;
        &mut self.storage[..len]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixels_and_padding_do_not_overlap() {
        let layout = Layout::new(7, 19);
        let mut seen = vec![false; layout.vectors() * LANES];
        layout.for_each_pixel(|x, y, vector, lane| {
            assert_eq!(layout.locate(x, y), (vector, lane));
            assert!(!seen[vector * LANES + lane], "({x}, {y})");
            seen[vector * LANES + lane] = true;
        });
        assert_eq!(seen.iter().filter(|&&used| used).count(), 7 * 19);
        // Vector by vector: the same pixels at the same places, each once, vectors in order.
        for (width, height) in [(7, 19), (1, 1), (20, 16), (3, 33), (16, 5)] {
            let layout = Layout::new(width, height);
            let mut visits = vec![0usize; width * height];
            let mut last_vector = 0;
            layout.for_each_pixel_by_vector(|x, y, vector, lane| {
                assert!(x < width && y < height, "({x}, {y}) in {width}x{height}");
                assert_eq!(layout.locate(x, y), (vector, lane), "({x}, {y})");
                assert!(vector >= last_vector, "vector {vector} after {last_vector}");
                last_vector = vector;
                visits[y * width + x] += 1;
            });
            assert!(
                visits.iter().all(|&count| count == 1),
                "{width}x{height}: {visits:?}"
            );
        }
        let rows: Vec<i32> = (0..7 * 19).collect();
        let mut skewed = Vec::new();
        layout.skew(&rows, |value| value as u16 + 1, &mut skewed);
        layout.for_each_pixel(|x, y, vector, lane| {
            assert_eq!(skewed[vector].0[lane], (y * 7 + x) as u16 + 1)
        });
        let written: usize = skewed
            .iter()
            .map(|lanes| lanes.0.iter().filter(|&&v| v != 0).count())
            .sum();
        assert_eq!(written, 7 * 19);
    }
}
