//! 16 lanes of 16-bit integers, the vector belief propagation works in: [`Lanes`] in memory,
//! [`Simd`] for the operations, implemented with AVX2 ([`Avx2`], a token that exists only once the
//! CPU is known to have AVX2) and in plain Rust ([`Portable`], every other CPU). Both give
//! identical results: the integer operations are exact (saturating where named so).

/// Lanes per vector.
pub(super) const LANES: usize = 16;

/// One vector in memory: 16 `u16` (or `i16` where an operation says so), 32-byte aligned.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[repr(C, align(32))]
pub(super) struct Lanes(pub(super) [u16; LANES]);

/// The vector operations. Values are `u16` unless the name says `i16`; masks have all bits of a
/// lane set (true) or none (false).
pub(super) trait Simd: Copy {
    type V: Copy;
    fn load(self, lanes: &Lanes) -> Self::V;
    fn store(self, lanes: &mut Lanes, value: Self::V);
    fn splat(self, value: u16) -> Self::V;
    /// `min(a + b, 65535)`.
    fn adds(self, a: Self::V, b: Self::V) -> Self::V;
    /// `max(a − b, 0)`.
    fn subs(self, a: Self::V, b: Self::V) -> Self::V;
    fn min(self, a: Self::V, b: Self::V) -> Self::V;
    fn and(self, a: Self::V, b: Self::V) -> Self::V;
    fn or(self, a: Self::V, b: Self::V) -> Self::V;
    /// `mask ? a : b` per lane.
    fn select(self, mask: Self::V, a: Self::V, b: Self::V) -> Self::V;
    /// Wrapping `i16` addition and subtraction.
    fn add_i16(self, a: Self::V, b: Self::V) -> Self::V;
    fn sub_i16(self, a: Self::V, b: Self::V) -> Self::V;
    /// `a > b` as `i16`.
    fn greater_i16(self, a: Self::V, b: Self::V) -> Self::V;
    /// `a < b` as `u16`.
    fn less_u16(self, a: Self::V, b: Self::V) -> Self::V;
    /// `|a|` of an `i16` (as `u16`).
    fn abs_i16(self, a: Self::V) -> Self::V;
    /// `round(a · b / 2¹⁵)` of `i16`s, halves rounded up (`pmulhrsw`).
    fn mul_round_q15(self, a: Self::V, b: Self::V) -> Self::V;
    /// `a · 16` (wrapping).
    fn times_16(self, a: Self::V) -> Self::V;
    /// Whether any lane of the mask is set.
    fn any(self, mask: Self::V) -> bool;
    /// `[fill[15], a[0], …, a[14]]`: each lane takes the value of the lane below.
    fn lanes_up(self, a: Self::V, fill: Self::V) -> Self::V;
    /// `[a[1], …, a[15], fill[0]]`: each lane takes the value of the lane above.
    fn lanes_down(self, a: Self::V, fill: Self::V) -> Self::V;
    /// `[a[h], b[h], a[h+1], b[h+1], …, a[h+7], b[h+7]]` with `h = 8 · half`: lanes `h..h+8` of
    /// two vectors, each doubled, interleaved.
    fn interleave_half(self, a: Self::V, b: Self::V, half: usize) -> Self::V;
    /// The 2×2 block sums of the multigrid, rounded quarter: lane `8h + i` of the result is
    /// `(e[h][0][2i] + e[h][1][2i] + e[h][1][2i+1] + e[h][2][2i+1] + 2) / 4` (saturated).
    fn quarter_block_sums(self, e: [[Self::V; 3]; 2]) -> Self::V;
}

/// The plain-Rust implementation.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct Portable;

impl Portable {
    #[inline(always)]
    fn map(a: Lanes, f: impl Fn(u16) -> u16) -> Lanes {
        Lanes(a.0.map(f))
    }

    #[inline(always)]
    fn zip(a: Lanes, b: Lanes, f: impl Fn(u16, u16) -> u16) -> Lanes {
        Lanes(std::array::from_fn(|lane| f(a.0[lane], b.0[lane])))
    }

    #[inline(always)]
    fn mask(condition: bool) -> u16 {
        if condition {
            u16::MAX
        } else {
            0
        }
    }
}

impl Simd for Portable {
    type V = Lanes;

    #[inline(always)]
    fn load(self, lanes: &Lanes) -> Lanes {
        *lanes
    }

    #[inline(always)]
    fn store(self, lanes: &mut Lanes, value: Lanes) {
        *lanes = value;
    }

    #[inline(always)]
    fn splat(self, value: u16) -> Lanes {
        Lanes([value; LANES])
    }

    #[inline(always)]
    fn adds(self, a: Lanes, b: Lanes) -> Lanes {
        Self::zip(a, b, u16::saturating_add)
    }

    #[inline(always)]
    fn subs(self, a: Lanes, b: Lanes) -> Lanes {
        Self::zip(a, b, u16::saturating_sub)
    }

    #[inline(always)]
    fn min(self, a: Lanes, b: Lanes) -> Lanes {
        Self::zip(a, b, u16::min)
    }

    #[inline(always)]
    fn and(self, a: Lanes, b: Lanes) -> Lanes {
        Self::zip(a, b, |a, b| a & b)
    }

    #[inline(always)]
    fn or(self, a: Lanes, b: Lanes) -> Lanes {
        Self::zip(a, b, |a, b| a | b)
    }

    #[inline(always)]
    fn select(self, mask: Lanes, a: Lanes, b: Lanes) -> Lanes {
        Lanes(std::array::from_fn(|lane| {
            (a.0[lane] & mask.0[lane]) | (b.0[lane] & !mask.0[lane])
        }))
    }

    #[inline(always)]
    fn add_i16(self, a: Lanes, b: Lanes) -> Lanes {
        Self::zip(a, b, u16::wrapping_add)
    }

    #[inline(always)]
    fn sub_i16(self, a: Lanes, b: Lanes) -> Lanes {
        Self::zip(a, b, u16::wrapping_sub)
    }

    #[inline(always)]
    fn greater_i16(self, a: Lanes, b: Lanes) -> Lanes {
        Self::zip(a, b, |a, b| Self::mask(a as i16 > b as i16))
    }

    #[inline(always)]
    fn less_u16(self, a: Lanes, b: Lanes) -> Lanes {
        Self::zip(a, b, |a, b| Self::mask(a < b))
    }

    #[inline(always)]
    fn abs_i16(self, a: Lanes) -> Lanes {
        Self::map(a, |a| (a as i16).unsigned_abs())
    }

    #[inline(always)]
    fn mul_round_q15(self, a: Lanes, b: Lanes) -> Lanes {
        Self::zip(a, b, |a, b| {
            let product = a as i16 as i32 * b as i16 as i32;
            ((product + (1 << 14)) >> 15) as i16 as u16
        })
    }

    #[inline(always)]
    fn times_16(self, a: Lanes) -> Lanes {
        Self::map(a, |a| a.wrapping_mul(16))
    }

    #[inline(always)]
    fn any(self, mask: Lanes) -> bool {
        mask.0.iter().any(|&lane| lane != 0)
    }

    #[inline(always)]
    fn lanes_up(self, a: Lanes, fill: Lanes) -> Lanes {
        Lanes(std::array::from_fn(|lane| {
            if lane == 0 {
                fill.0[LANES - 1]
            } else {
                a.0[lane - 1]
            }
        }))
    }

    #[inline(always)]
    fn lanes_down(self, a: Lanes, fill: Lanes) -> Lanes {
        Lanes(std::array::from_fn(|lane| {
            if lane == LANES - 1 {
                fill.0[0]
            } else {
                a.0[lane + 1]
            }
        }))
    }

    #[inline(always)]
    fn interleave_half(self, a: Lanes, b: Lanes, half: usize) -> Lanes {
        Lanes(std::array::from_fn(|lane| {
            let source = 8 * half + lane / 2;
            if lane % 2 == 0 {
                a.0[source]
            } else {
                b.0[source]
            }
        }))
    }

    #[inline(always)]
    fn quarter_block_sums(self, e: [[Lanes; 3]; 2]) -> Lanes {
        Lanes(std::array::from_fn(|lane| {
            let (half, i) = (lane / 8, lane % 8);
            let [first, middle, last] = e[half];
            let sum = first.0[2 * i] as u32
                + middle.0[2 * i] as u32
                + middle.0[2 * i + 1] as u32
                + last.0[2 * i + 1] as u32;
            ((sum + 2) / 4).min(u16::MAX as u32) as u16
        }))
    }
}

#[cfg(target_arch = "x86_64")]
pub(super) use avx2::Avx2;

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{Lanes, Simd};

    /// Proof that the CPU has AVX2: only [`Avx2::detect`] makes one. Its operations are plain
    /// functions that the callers, compiled with AVX2 enabled, inline.
    #[derive(Clone, Copy, Debug)]
    pub(in crate::core::sift_flow) struct Avx2(());

    impl Avx2 {
        pub(in crate::core::sift_flow) fn detect() -> Option<Self> {
            std::arch::is_x86_feature_detected!("avx2").then_some(Self(()))
        }
    }

    // SAFETY (every `unsafe` block below): an `Avx2` value exists only when the CPU has AVX2
    // (`Avx2::detect`), and `Lanes` is 32 bytes, 32-byte aligned.
    impl Simd for Avx2 {
        type V = __m256i;

        #[inline(always)]
        fn load(self, lanes: &Lanes) -> __m256i {
            unsafe { _mm256_load_si256(lanes as *const Lanes as *const __m256i) }
        }

        #[inline(always)]
        fn store(self, lanes: &mut Lanes, value: __m256i) {
            unsafe { _mm256_store_si256(lanes as *mut Lanes as *mut __m256i, value) }
        }

        #[inline(always)]
        fn splat(self, value: u16) -> __m256i {
            unsafe { _mm256_set1_epi16(value as i16) }
        }

        #[inline(always)]
        fn adds(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_adds_epu16(a, b) }
        }

        #[inline(always)]
        fn subs(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_subs_epu16(a, b) }
        }

        #[inline(always)]
        fn min(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_min_epu16(a, b) }
        }

        #[inline(always)]
        fn and(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_and_si256(a, b) }
        }

        #[inline(always)]
        fn or(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_or_si256(a, b) }
        }

        #[inline(always)]
        fn select(self, mask: __m256i, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_blendv_epi8(b, a, mask) }
        }

        #[inline(always)]
        fn add_i16(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_add_epi16(a, b) }
        }

        #[inline(always)]
        fn sub_i16(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_sub_epi16(a, b) }
        }

        #[inline(always)]
        fn greater_i16(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_cmpgt_epi16(a, b) }
        }

        #[inline(always)]
        fn less_u16(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe {
                let flip = _mm256_set1_epi16(i16::MIN);
                _mm256_cmpgt_epi16(_mm256_xor_si256(b, flip), _mm256_xor_si256(a, flip))
            }
        }

        #[inline(always)]
        fn abs_i16(self, a: __m256i) -> __m256i {
            unsafe { _mm256_abs_epi16(a) }
        }

        #[inline(always)]
        fn mul_round_q15(self, a: __m256i, b: __m256i) -> __m256i {
            unsafe { _mm256_mulhrs_epi16(a, b) }
        }

        #[inline(always)]
        fn times_16(self, a: __m256i) -> __m256i {
            unsafe { _mm256_slli_epi16(a, 4) }
        }

        #[inline(always)]
        fn any(self, mask: __m256i) -> bool {
            unsafe { _mm256_testz_si256(mask, mask) == 0 }
        }

        #[inline(always)]
        fn lanes_up(self, a: __m256i, fill: __m256i) -> __m256i {
            unsafe { _mm256_alignr_epi8(a, _mm256_permute2x128_si256(a, fill, 0x03), 14) }
        }

        #[inline(always)]
        fn lanes_down(self, a: __m256i, fill: __m256i) -> __m256i {
            unsafe { _mm256_alignr_epi8(_mm256_permute2x128_si256(a, fill, 0x21), a, 2) }
        }

        #[inline(always)]
        fn interleave_half(self, a: __m256i, b: __m256i, half: usize) -> __m256i {
            unsafe {
                // Quadwords (2h, 2h+1) to the low halves of the two 128-bit lanes, then words
                // interleaved within each lane.
                let (a, b) = if half == 0 {
                    (
                        _mm256_permute4x64_epi64(a, 0x10),
                        _mm256_permute4x64_epi64(b, 0x10),
                    )
                } else {
                    (
                        _mm256_permute4x64_epi64(a, 0x32),
                        _mm256_permute4x64_epi64(b, 0x32),
                    )
                };
                _mm256_unpacklo_epi16(a, b)
            }
        }

        #[inline(always)]
        fn quarter_block_sums(self, e: [[__m256i; 3]; 2]) -> __m256i {
            unsafe {
                let low_words = _mm256_set1_epi32(0xffff);
                let quarter = |[first, middle, last]: [__m256i; 3]| {
                    let sum = _mm256_add_epi32(
                        _mm256_add_epi32(
                            _mm256_and_si256(first, low_words),
                            _mm256_and_si256(middle, low_words),
                        ),
                        _mm256_add_epi32(
                            _mm256_srli_epi32(middle, 16),
                            _mm256_srli_epi32(last, 16),
                        ),
                    );
                    _mm256_srli_epi32(_mm256_add_epi32(sum, _mm256_set1_epi32(2)), 2)
                };
                let (low, high) = (quarter(e[0]), quarter(e[1]));
                // packus interleaves the 128-bit lanes: put them back in order.
                _mm256_permute4x64_epi64(_mm256_packus_epi32(low, high), 0xd8)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(seed: u32) -> Lanes {
        Lanes(std::array::from_fn(|lane| {
            let value = (lane as u32 + 1)
                .wrapping_mul(2_654_435_761)
                .wrapping_add(seed.wrapping_mul(40_503));
            match lane % 4 {
                0 => (value >> 16) as u16,
                1 => (value >> 20) as u16,
                2 => u16::MAX - (value >> 24) as u16,
                _ => (value >> 25) as u16 | 0x8000,
            }
        }))
    }

    /// Every operation of the AVX2 implementation equals the plain-Rust one.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_operations_equal_the_portable_ones() {
        let Some(avx2) = Avx2::detect() else {
            return;
        };
        let portable = Portable;
        let out = |value| {
            let mut lanes = Lanes::default();
            avx2.store(&mut lanes, value);
            lanes
        };
        for seed in 0..50 {
            let (a, b, c) = (sample(seed), sample(seed + 100), sample(seed + 200));
            let (va, vb, vc) = (avx2.load(&a), avx2.load(&b), avx2.load(&c));
            let small = Lanes(a.0.map(|value| value >> 5));
            let vsmall = avx2.load(&small);
            assert_eq!(out(avx2.adds(va, vb)), portable.adds(a, b));
            assert_eq!(out(avx2.subs(va, vb)), portable.subs(a, b));
            assert_eq!(out(avx2.min(va, vb)), portable.min(a, b));
            assert_eq!(out(avx2.and(va, vb)), portable.and(a, b));
            assert_eq!(out(avx2.or(va, vb)), portable.or(a, b));
            let mask = portable.less_u16(a, b);
            assert_eq!(out(avx2.less_u16(va, vb)), mask);
            assert_eq!(
                out(avx2.select(avx2.load(&mask), vb, vc)),
                portable.select(mask, b, c)
            );
            assert_eq!(out(avx2.add_i16(va, vb)), portable.add_i16(a, b));
            assert_eq!(out(avx2.sub_i16(va, vb)), portable.sub_i16(a, b));
            assert_eq!(out(avx2.greater_i16(va, vb)), portable.greater_i16(a, b));
            assert_eq!(out(avx2.abs_i16(va)), portable.abs_i16(a));
            assert_eq!(
                out(avx2.mul_round_q15(vsmall, vb)),
                portable.mul_round_q15(small, b)
            );
            assert_eq!(out(avx2.times_16(va)), portable.times_16(a));
            assert_eq!(avx2.any(va), portable.any(a));
            assert!(!avx2.any(avx2.splat(0)));
            assert_eq!(out(avx2.lanes_up(va, vb)), portable.lanes_up(a, b));
            assert_eq!(out(avx2.lanes_down(va, vb)), portable.lanes_down(a, b));
            for half in 0..2 {
                assert_eq!(
                    out(avx2.interleave_half(va, vb, half)),
                    portable.interleave_half(a, b, half)
                );
            }
            let blocks = [[a, b, c], [c, a, b]];
            assert_eq!(
                out(avx2.quarter_block_sums(blocks.map(|row| row.map(|lanes| avx2.load(&lanes))))),
                portable.quarter_block_sums(blocks)
            );
        }
    }
}
