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

/// L1 distances of `source` to `out.len()` consecutive descriptors of `targets`, by a plain loop.
#[inline(always)]
pub(super) fn l1_row_portable(source: &[u8], targets: &[u8], out: &mut [u16]) {
    for (distance, target) in out.iter_mut().zip(targets.chunks_exact(DESCRIPTOR_LEN)) {
        *distance = l1_distance_portable(source, target) as u16;
    }
}

#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) fn l1_row_sse2(source: &[u8], targets: &[u8], out: &mut [u16]) {
    for (distance, target) in out.iter_mut().zip(targets.chunks_exact(DESCRIPTOR_LEN)) {
        *distance = l1_distance_sse2(source, target) as u16;
    }
}

/// [`l1_row_portable`] in AVX2: the source in four registers, and four candidates' partial sums
/// packed into the 16-bit fields of one register before the horizontal sum (each partial sum is at
/// most 32 · 255, each total at most 128 · 255 < 2¹⁶).
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn l1_row_avx2(source: &[u8], targets: &[u8], out: &mut [u16]) {
    use std::arch::x86_64::*;
    assert!(source.len() >= DESCRIPTOR_LEN && targets.len() >= out.len() * DESCRIPTOR_LEN);
    // SAFETY (loads and stores): the lengths are checked above; all accesses are unaligned.
    let source: [__m256i; 4] = std::array::from_fn(|chunk| unsafe {
        _mm256_loadu_si256(source.as_ptr().add(32 * chunk) as *const __m256i)
    });
    let partial_sums = |candidate: usize| {
        let target = unsafe { targets.as_ptr().add(candidate * DESCRIPTOR_LEN) };
        let sad = |chunk: usize| unsafe {
            _mm256_sad_epu8(
                source[chunk],
                _mm256_loadu_si256(target.add(32 * chunk) as *const __m256i),
            )
        };
        _mm256_add_epi64(
            _mm256_add_epi64(sad(0), sad(1)),
            _mm256_add_epi64(sad(2), sad(3)),
        )
    };
    let mut candidate = 0;
    while candidate + 4 <= out.len() {
        let sums: [__m256i; 4] = std::array::from_fn(|index| partial_sums(candidate + index));
        let packed = _mm256_or_si256(
            _mm256_or_si256(sums[0], _mm256_slli_epi64(sums[1], 16)),
            _mm256_or_si256(
                _mm256_slli_epi64(sums[2], 32),
                _mm256_slli_epi64(sums[3], 48),
            ),
        );
        let folded = _mm_add_epi16(
            _mm256_castsi256_si128(packed),
            _mm256_extracti128_si256(packed, 1),
        );
        let folded = _mm_add_epi16(folded, _mm_unpackhi_epi64(folded, folded));
        unsafe { _mm_storel_epi64(out.as_mut_ptr().add(candidate) as *mut __m128i, folded) };
        candidate += 4;
    }
    for (index, distance) in out.iter_mut().enumerate().skip(candidate) {
        let sums = partial_sums(index);
        let folded = _mm_add_epi64(
            _mm256_castsi256_si128(sums),
            _mm256_extracti128_si256(sums, 1),
        );
        *distance = (_mm_cvtsi128_si64(folded)
            + _mm_cvtsi128_si64(_mm_unpackhi_epi64(folded, folded))) as u16;
    }
}

/// L1 distances of `source` to a whole `labels × labels` window of target descriptors that lies
/// inside the target: candidate `(label_u, label_v)` is the descriptor at `first + label_v · row_len
/// + label_u · 128` of `targets`, written to `out[label_v · labels + label_u]`. As
/// [`l1_row_avx2`], four candidates per horizontal sum, across the window's rows.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn l1_window_avx2(
    source: &[u8],
    targets: &[u8],
    first: usize,
    row_len: usize,
    labels: usize,
    out: &mut [u16],
) {
    use std::arch::x86_64::*;
    let count = labels * labels;
    assert!(source.len() >= DESCRIPTOR_LEN && out.len() >= count && labels > 0);
    assert!(first + (labels - 1) * (row_len + DESCRIPTOR_LEN) + DESCRIPTOR_LEN <= targets.len());
    // SAFETY (loads and stores): every candidate lies in `targets` (checked above: the last one
    // ends there at the latest) and `out` holds `count` values; all accesses are unaligned.
    let source: [__m256i; 4] = std::array::from_fn(|chunk| unsafe {
        _mm256_loadu_si256(source.as_ptr().add(32 * chunk) as *const __m256i)
    });
    let partial_sums = |target: *const u8| {
        let sad = |chunk: usize| unsafe {
            _mm256_sad_epu8(
                source[chunk],
                _mm256_loadu_si256(target.add(32 * chunk) as *const __m256i),
            )
        };
        _mm256_add_epi64(
            _mm256_add_epi64(sad(0), sad(1)),
            _mm256_add_epi64(sad(2), sad(3)),
        )
    };
    let base = unsafe { targets.as_ptr().add(first) };
    let mut label_u = 0usize;
    // Candidates in order, row by row: the next one is one descriptor further, or the start of
    // the next row.
    let row_step = row_len - (labels - 1) * DESCRIPTOR_LEN;
    let mut target = base;
    let mut next = || {
        let current = target;
        label_u += 1;
        if label_u == labels {
            label_u = 0;
            target = target.wrapping_add(row_step);
        } else {
            target = target.wrapping_add(DESCRIPTOR_LEN);
        }
        current
    };
    let mut candidate = 0;
    while candidate + 4 <= count {
        let sums: [__m256i; 4] = std::array::from_fn(|_| partial_sums(next()));
        let packed = _mm256_or_si256(
            _mm256_or_si256(sums[0], _mm256_slli_epi64(sums[1], 16)),
            _mm256_or_si256(
                _mm256_slli_epi64(sums[2], 32),
                _mm256_slli_epi64(sums[3], 48),
            ),
        );
        let folded = _mm_add_epi16(
            _mm256_castsi256_si128(packed),
            _mm256_extracti128_si256(packed, 1),
        );
        let folded = _mm_add_epi16(folded, _mm_unpackhi_epi64(folded, folded));
        unsafe { _mm_storel_epi64(out.as_mut_ptr().add(candidate) as *mut __m128i, folded) };
        candidate += 4;
    }
    for distance in &mut out[candidate..count] {
        let sums = partial_sums(next());
        let folded = _mm_add_epi64(
            _mm256_castsi256_si128(sums),
            _mm256_extracti128_si256(sums, 1),
        );
        *distance = (_mm_cvtsi128_si64(folded)
            + _mm_cvtsi128_si64(_mm_unpackhi_epi64(folded, folded))) as u16;
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
    fn row_kernels_agree() {
        let source: Vec<u8> = (0..128).map(|index| (index * 91 % 256) as u8).collect();
        let targets: Vec<u8> = (0..128 * 7).map(|index| (index * 13 % 251) as u8).collect();
        for count in 0..=7 {
            let mut portable = vec![0u16; count];
            l1_row_portable(&source, &targets, &mut portable);
            for (candidate, &distance) in portable.iter().enumerate() {
                let target = &targets[candidate * 128..(candidate + 1) * 128];
                assert_eq!(distance as u32, l1_distance_portable(&source, target));
            }
            #[cfg(target_arch = "x86_64")]
            {
                let mut sse2 = vec![0u16; count];
                l1_row_sse2(&source, &targets, &mut sse2);
                assert_eq!(sse2, portable);
                if std::arch::is_x86_feature_detected!("avx2") {
                    let mut avx2 = vec![0u16; count];
                    // SAFETY: the CPU has AVX2.
                    unsafe { l1_row_avx2(&source, &targets, &mut avx2) };
                    assert_eq!(avx2, portable, "{count}");
                }
            }
        }
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // A 3x3 window in an image 4 descriptors wide, starting at its second column.
            let image: Vec<u8> = (0..128 * 4 * 3)
                .map(|index| (index * 29 % 253) as u8)
                .collect();
            let mut window = [0u16; 9];
            // SAFETY: the CPU has AVX2.
            unsafe { l1_window_avx2(&source, &image, 128, 4 * 128, 3, &mut window) };
            for label_v in 0..3 {
                for label_u in 0..3 {
                    let at = 128 + label_v * 4 * 128 + label_u * 128;
                    assert_eq!(
                        window[label_v * 3 + label_u] as u32,
                        l1_distance_portable(&source, &image[at..at + 128])
                    );
                }
            }
        }
        // The largest distance fits the 16-bit fields.
        let zeros = vec![0u8; 128 * 4];
        let mut distances = [0u16; 4];
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2.
            unsafe { l1_row_avx2(&[255u8; 128], &zeros, &mut distances) };
            assert_eq!(distances, [128 * 255; 4]);
        }
    }

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
