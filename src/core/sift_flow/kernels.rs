//! The L1 distance of two 128-byte descriptors, the innermost loop of the data term: a portable
//! loop and SSE2 / AVX2 versions (chosen at run time), which give identical results.

use super::L1Kernel;
use crate::core::dense_sift::DESCRIPTOR_LEN;

/// L1 distance of two 128-byte descriptors by a plain loop.
#[inline(always)]
pub(super) fn l1_distance_portable(a: &[u8], b: &[u8]) -> u32 {
    a.iter().zip(b).map(|(&x, &y)| x.abs_diff(y) as u32).sum()
}

#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) fn l1_distance_sse2(a: &[u8], b: &[u8]) -> u32 {
    use std::arch::x86_64::*;
    assert!(a.len() >= DESCRIPTOR_LEN && b.len() >= DESCRIPTOR_LEN);
    // SAFETY: SSE2 is part of the x86-64 baseline; both slices hold 128 bytes (checked above) and
    // the loads are unaligned.
    unsafe {
        let mut total = _mm_setzero_si128();
        for chunk in 0..DESCRIPTOR_LEN / 16 {
            let va = _mm_loadu_si128(a.as_ptr().add(chunk * 16) as *const __m128i);
            let vb = _mm_loadu_si128(b.as_ptr().add(chunk * 16) as *const __m128i);
            total = _mm_add_epi64(total, _mm_sad_epu8(va, vb));
        }
        (_mm_cvtsi128_si64(total) + _mm_cvtsi128_si64(_mm_unpackhi_epi64(total, total))) as u32
    }
}

/// AVX2 L1 distance; only called from functions compiled with AVX2 enabled after runtime detection.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) fn l1_distance_avx2(a: &[u8], b: &[u8]) -> u32 {
    use std::arch::x86_64::*;
    assert!(a.len() >= DESCRIPTOR_LEN && b.len() >= DESCRIPTOR_LEN);
    // SAFETY: callers run only after `is_x86_feature_detected!("avx2")`; both slices hold 128
    // bytes (checked above) and the loads are unaligned.
    unsafe {
        let mut total = _mm256_setzero_si256();
        for chunk in 0..DESCRIPTOR_LEN / 32 {
            let va = _mm256_loadu_si256(a.as_ptr().add(chunk * 32) as *const __m256i);
            let vb = _mm256_loadu_si256(b.as_ptr().add(chunk * 32) as *const __m256i);
            total = _mm256_add_epi64(total, _mm256_sad_epu8(va, vb));
        }
        let low = _mm256_castsi256_si128(total);
        let high = _mm256_extracti128_si256(total, 1);
        let sum = _mm_add_epi64(low, high);
        (_mm_cvtsi128_si64(sum) + _mm_cvtsi128_si64(_mm_unpackhi_epi64(sum, sum))) as u32
    }
}

/// The L1 distance of two descriptors with the chosen kernel (for tests and benchmarks; the data
/// term dispatches once per row, not per pair).
pub fn descriptor_l1_distance(a: &[u8], b: &[u8], kernel: L1Kernel) -> u32 {
    match resolve_kernel(kernel) {
        #[cfg(target_arch = "x86_64")]
        L1Kernel::Avx2 => {
            // SAFETY: `resolve_kernel` returns Avx2 only when the CPU has AVX2.
            unsafe { l1_avx2_entry(a, b) }
        }
        #[cfg(target_arch = "x86_64")]
        L1Kernel::Sse2 => l1_distance_sse2(a, b),
        _ => l1_distance_portable(a, b),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn l1_avx2_entry(a: &[u8], b: &[u8]) -> u32 {
    l1_distance_avx2(a, b)
}

pub(super) fn resolve_kernel(kernel: L1Kernel) -> L1Kernel {
    #[cfg(target_arch = "x86_64")]
    {
        let has_avx2 = std::arch::is_x86_feature_detected!("avx2");
        match kernel {
            L1Kernel::Auto | L1Kernel::Avx2 if has_avx2 => L1Kernel::Avx2,
            L1Kernel::Auto | L1Kernel::Avx2 | L1Kernel::Sse2 => L1Kernel::Sse2,
            L1Kernel::Portable => L1Kernel::Portable,
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = kernel;
        L1Kernel::Portable
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn l1_kernels_agree() {
        let a: Vec<u8> = (0..128).map(|index| (index * 37 % 256) as u8).collect();
        let b: Vec<u8> = (0..128)
            .map(|index| (255 - index * 11 % 256) as u8)
            .collect();
        let expected: u32 = a
            .iter()
            .zip(&b)
            .map(|(&x, &y)| (x as i32 - y as i32).unsigned_abs())
            .sum();
        for kernel in [
            L1Kernel::Auto,
            L1Kernel::Portable,
            L1Kernel::Sse2,
            L1Kernel::Avx2,
        ] {
            assert_eq!(
                descriptor_l1_distance(&a, &b, kernel),
                expected,
                "{kernel:?}"
            );
        }
    }
}
