//! Sum of absolute differences between a contiguous block and a window of a frame, with early
//! termination: the sum is checked against a limit every [`CHECK_ROWS`] rows and the candidate
//! is abandoned as soon as it exceeds it.
//!
//! Kernels: AVX2 (`vpsadbw` on 32 bytes, chosen at run time when the CPU has it and the block
//! width is a multiple of 32), SSE2 (16 bytes, always present on x86-64, widths that are a
//! multiple of 16) and portable scalar code. All return the same integers.

/// Rows between two checks of the partial sum against the limit.
pub const CHECK_ROWS: usize = 8;

/// Which SAD implementation runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    Avx2,
    Sse2,
    Scalar,
}

impl Kernel {
    /// The fastest kernel this CPU supports for blocks `block` pixels wide.
    pub fn detect(block: usize) -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            if block.is_multiple_of(32) && std::arch::is_x86_feature_detected!("avx2") {
                return Kernel::Avx2;
            }
            if block.is_multiple_of(16) {
                return Kernel::Sse2;
            }
        }
        let _ = block;
        Kernel::Scalar
    }

    /// `self` unless `other` is slower (used to force a slower kernel everywhere in tests).
    pub fn min_with(self, other: Kernel) -> Kernel {
        let rank = |k: Kernel| match k {
            Kernel::Scalar => 0,
            Kernel::Sse2 => 1,
            Kernel::Avx2 => 2,
        };
        if rank(other) < rank(self) { other } else { self }
    }

    /// Whether this kernel can run blocks `block` pixels wide on this CPU.
    pub fn supports(self, block: usize) -> bool {
        match self {
            Kernel::Scalar => true,
            #[cfg(target_arch = "x86_64")]
            Kernel::Sse2 => block.is_multiple_of(16),
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx2 => block.is_multiple_of(32) && std::arch::is_x86_feature_detected!("avx2"),
            #[cfg(not(target_arch = "x86_64"))]
            Kernel::Sse2 | Kernel::Avx2 => false,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Kernel::Avx2 => "avx2",
            Kernel::Sse2 => "sse2",
            Kernel::Scalar => "scalar",
        }
    }

    /// SAD between `a` (a `block`×`block` block, rows contiguous) and the `block`×`block` window
    /// of `img` (rows `stride` bytes apart) whose top-left byte is `img[off]`. Returns `None` as
    /// soon as the partial sum after a multiple of [`CHECK_ROWS`] rows (or at the end) exceeds
    /// `limit`; otherwise the exact sum.
    ///
    /// Panics when the window or the block does not fit in its slice, or when the kernel does
    /// not support `block` (use [`Kernel::detect`]).
    #[inline]
    pub fn sad(self, a: &[u8], img: &[u8], off: usize, stride: usize, block: usize, limit: u32) -> Option<u32> {
        assert!(block > 0 && a.len() >= block * block, "SAD block buffer too small");
        assert!(stride >= block && off + (block - 1) * stride + block <= img.len(), "SAD window outside the frame");
        match self {
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx2 => {
                assert!(block.is_multiple_of(32) && std::arch::is_x86_feature_detected!("avx2"));
                // SAFETY: AVX2 is present (checked above) and every row read lies inside `a`
                // and `img` (asserted above).
                unsafe { x86::sad_avx2(a.as_ptr(), img.as_ptr().add(off), stride, block, limit) }
            }
            #[cfg(target_arch = "x86_64")]
            Kernel::Sse2 => {
                assert!(block.is_multiple_of(16));
                // SAFETY: SSE2 is part of x86-64; bounds asserted above.
                unsafe { x86::sad_sse2(a.as_ptr(), img.as_ptr().add(off), stride, block, limit) }
            }
            #[cfg(not(target_arch = "x86_64"))]
            Kernel::Avx2 | Kernel::Sse2 => sad_scalar(a, img, off, stride, block, limit),
            Kernel::Scalar => sad_scalar(a, img, off, stride, block, limit),
        }
    }
}

/// A SAD kernel as a type, so that a search loop can be compiled once per kernel with the
/// kernel inlined (the AVX2 instance inside an AVX2-enabled function).
pub trait SadFn {
    /// SAD of the `block`×`block` block at `a` (rows `block` bytes apart) and the window at `b`
    /// (rows `stride` bytes apart), with early termination as in [`Kernel::sad`].
    ///
    /// # Safety
    /// Both regions must be readable; the CPU must support the kernel and the block width
    /// ([`Kernel::supports`]).
    unsafe fn sad(a: *const u8, b: *const u8, stride: usize, block: usize, limit: u32) -> Option<u32>;
}

/// [`Kernel::Avx2`] as a type.
#[cfg(target_arch = "x86_64")]
pub struct Avx2Sad;
/// [`Kernel::Sse2`] as a type.
#[cfg(target_arch = "x86_64")]
pub struct Sse2Sad;
/// [`Kernel::Scalar`] as a type.
pub struct ScalarSad;

#[cfg(target_arch = "x86_64")]
impl SadFn for Avx2Sad {
    #[inline(always)]
    unsafe fn sad(a: *const u8, b: *const u8, stride: usize, block: usize, limit: u32) -> Option<u32> {
        // SAFETY: forwarded caller contract.
        unsafe { x86::sad_avx2_inl(a, b, stride, block, limit) }
    }
}

#[cfg(target_arch = "x86_64")]
impl SadFn for Sse2Sad {
    #[inline(always)]
    unsafe fn sad(a: *const u8, b: *const u8, stride: usize, block: usize, limit: u32) -> Option<u32> {
        // SAFETY: forwarded caller contract.
        unsafe { x86::sad_sse2(a, b, stride, block, limit) }
    }
}

impl SadFn for ScalarSad {
    #[inline(always)]
    unsafe fn sad(a: *const u8, b: *const u8, stride: usize, block: usize, limit: u32) -> Option<u32> {
        // SAFETY: the caller guarantees block*block bytes at `a` and the window at `b`.
        let (a, img) = unsafe {
            (std::slice::from_raw_parts(a, block * block), std::slice::from_raw_parts(b, (block - 1) * stride + block))
        };
        sad_scalar(a, img, 0, stride, block, limit)
    }
}

/// Portable SAD with the same early-termination checkpoints as the SIMD kernels.
pub fn sad_scalar(a: &[u8], img: &[u8], off: usize, stride: usize, block: usize, limit: u32) -> Option<u32> {
    let mut total = 0u32;
    for y in 0..block {
        let ar = &a[y * block..(y + 1) * block];
        let br = &img[off + y * stride..off + y * stride + block];
        total += ar.iter().zip(br).map(|(&p, &q)| u32::from(p.abs_diff(q))).sum::<u32>();
        if ((y + 1) % CHECK_ROWS == 0 || y + 1 == block) && total > limit {
            return None;
        }
    }
    Some(total)
}

/// Sum of squared differences between the `block`×`block` block `a` (rows contiguous) and the
/// window of `img` (rows `stride` bytes apart) whose top-left byte is `img[off]`.
pub fn ssd_scalar(a: &[u8], img: &[u8], off: usize, stride: usize, block: usize) -> u64 {
    let mut s = 0u64;
    for (y, ar) in a.chunks_exact(block).take(block).enumerate() {
        let br = &img[off + y * stride..off + y * stride + block];
        s += u64::from(ar.iter().zip(br).map(|(&p, &q)| u32::from(p.abs_diff(q)).pow(2)).sum::<u32>());
    }
    s
}

/// Gradient energy of the `block`×`block` block `a` (rows contiguous):
/// Σ|a(x+1,y) − a(x,y)| + Σ|a(x,y+1) − a(x,y)|.
pub fn texture_scalar(a: &[u8], block: usize) -> u64 {
    let mut g = 0u64;
    for y in 0..block {
        let row = &a[y * block..(y + 1) * block];
        g += u64::from(row.windows(2).map(|p| u32::from(p[0].abs_diff(p[1]))).sum::<u32>());
        if y + 1 < block {
            let next = &a[(y + 1) * block..(y + 2) * block];
            g += u64::from(row.iter().zip(next).map(|(&p, &q)| u32::from(p.abs_diff(q))).sum::<u32>());
        }
    }
    g
}

/// [`ssd_scalar`] and [`texture_scalar`] on 256-bit vectors, for blocks whose width is a multiple
/// of 32 on CPUs with AVX2 (the same integers).
#[cfg(target_arch = "x86_64")]
pub mod avx2 {
    /// # Safety
    /// AVX2 must be available; `block.is_multiple_of(32)`; `a` must point at `block*block`
    /// readable bytes and `b` at `block` rows of `block` readable bytes, `stride` apart.
    #[inline(always)]
    pub unsafe fn ssd(a: *const u8, b: *const u8, stride: usize, block: usize) -> u64 {
        // SAFETY: forwarded caller contract.
        unsafe { super::x86::ssd_avx2_inl(a, b, stride, block) }
    }

    /// # Safety
    /// AVX2 must be available; `block.is_multiple_of(32)`; `a` must point at `block*block`
    /// readable bytes.
    #[inline(always)]
    pub unsafe fn texture(a: *const u8, block: usize) -> u64 {
        // SAFETY: forwarded caller contract.
        unsafe { super::x86::texture_avx2_inl(a, block) }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::CHECK_ROWS;
    use std::arch::x86_64::*;

    // The `#[inline(always)]` helpers below carry no `target_feature` themselves: they are
    // inlined into AVX2-enabled callers (`sad_avx2`, `cpu::search_avx2`), where the intrinsics
    // then inline too. Callers must ensure AVX2 is present.

    /// # Safety
    /// AVX2 must be available.
    #[inline(always)]
    unsafe fn hsum256(v: __m256i) -> u32 {
        // SAFETY: caller guarantees AVX2.
        unsafe {
            let s = _mm_add_epi64(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
            let s = _mm_add_epi64(s, _mm_unpackhi_epi64(s, s));
            _mm_cvtsi128_si32(s) as u32
        }
    }

    /// # Safety
    /// AVX2 must be available; `a` must point at `block*block` readable bytes and `b` at
    /// `block` rows of `block` readable bytes, `stride` apart. `block.is_multiple_of(32)`.
    #[target_feature(enable = "avx2")]
    pub unsafe fn sad_avx2(a: *const u8, b: *const u8, stride: usize, block: usize, limit: u32) -> Option<u32> {
        // SAFETY: same contract.
        unsafe { sad_avx2_inl(a, b, stride, block, limit) }
    }

    /// [`sad_avx2`] for inlining into AVX2-enabled callers.
    ///
    /// # Safety
    /// As [`sad_avx2`].
    #[inline(always)]
    pub unsafe fn sad_avx2_inl(a: *const u8, b: *const u8, stride: usize, block: usize, limit: u32) -> Option<u32> {
        // SAFETY (whole body): the caller guarantees AVX2 and that every address read is in bounds.
        unsafe {
            if block == 32 {
                return sad_avx2_32(a, b, stride, limit);
            }
            let mut total = 0u32;
            let mut y = 0;
            while y < block {
                let end = (y + CHECK_ROWS).min(block);
                let mut acc = _mm256_setzero_si256();
                for r in y..end {
                    let (ar, br) = (a.add(r * block), b.add(r * stride));
                    let mut x = 0;
                    while x < block {
                        let va = _mm256_loadu_si256(ar.add(x) as *const __m256i);
                        let vb = _mm256_loadu_si256(br.add(x) as *const __m256i);
                        acc = _mm256_add_epi64(acc, _mm256_sad_epu8(va, vb));
                        x += 32;
                    }
                }
                total += hsum256(acc);
                if total > limit {
                    return None;
                }
                y = end;
            }
            Some(total)
        }
    }

    /// The default 32-pixel block: one `vpsadbw` per row, two accumulators, fully unrolled
    /// between checkpoints.
    ///
    /// # Safety
    /// As [`sad_avx2`] with `block == 32`.
    #[inline(always)]
    unsafe fn sad_avx2_32(a: *const u8, b: *const u8, stride: usize, limit: u32) -> Option<u32> {
        // SAFETY (whole body): 32 rows of 32 bytes at `a` (stride 32) and `b` (stride `stride`).
        unsafe {
            let mut total = 0u32;
            // Checkpoints after 4, 8, 16, 24 and 32 rows: most wrong candidates are abandoned
            // after the first 4 or 8 rows. (Where the checks fall never changes the result:
            // `None` exactly when the full sum exceeds `limit`.)
            let mut r0 = 0;
            for end in [4usize, 8, 16, 24, 32] {
                let mut acc0 = _mm256_setzero_si256();
                let mut acc1 = _mm256_setzero_si256();
                let mut r = r0;
                while r < end {
                    let a0 = _mm256_loadu_si256(a.add(r * 32) as *const __m256i);
                    let b0 = _mm256_loadu_si256(b.add(r * stride) as *const __m256i);
                    let a1 = _mm256_loadu_si256(a.add((r + 1) * 32) as *const __m256i);
                    let b1 = _mm256_loadu_si256(b.add((r + 1) * stride) as *const __m256i);
                    acc0 = _mm256_add_epi64(acc0, _mm256_sad_epu8(a0, b0));
                    acc1 = _mm256_add_epi64(acc1, _mm256_sad_epu8(a1, b1));
                    r += 2;
                }
                total += hsum256(_mm256_add_epi64(acc0, acc1));
                if total > limit {
                    return None;
                }
                r0 = end;
            }
            Some(total)
        }
    }

    /// Σ (a − b)² with 16-bit products summed in 32-bit lanes: a lane takes at most
    /// 2 × 255² per 32 bytes of a row, so blocks up to 256 px stay far below 2³¹.
    ///
    /// # Safety
    /// As [`sad_avx2`]; inlined into AVX2-enabled callers only.
    #[inline(always)]
    pub unsafe fn ssd_avx2_inl(a: *const u8, b: *const u8, stride: usize, block: usize) -> u64 {
        // SAFETY (whole body): the caller guarantees AVX2 and that every address read is in bounds.
        unsafe {
            let zero = _mm256_setzero_si256();
            let mut acc = _mm256_setzero_si256();
            for r in 0..block {
                let (ar, br) = (a.add(r * block), b.add(r * stride));
                let mut x = 0;
                while x < block {
                    let va = _mm256_loadu_si256(ar.add(x) as *const __m256i);
                    let vb = _mm256_loadu_si256(br.add(x) as *const __m256i);
                    let d = _mm256_or_si256(_mm256_subs_epu8(va, vb), _mm256_subs_epu8(vb, va));
                    let (lo, hi) = (_mm256_unpacklo_epi8(d, zero), _mm256_unpackhi_epi8(d, zero));
                    acc = _mm256_add_epi32(acc, _mm256_madd_epi16(lo, lo));
                    acc = _mm256_add_epi32(acc, _mm256_madd_epi16(hi, hi));
                    x += 32;
                }
            }
            // the 8 lanes as 64-bit sums
            let wide = _mm256_add_epi64(_mm256_unpacklo_epi32(acc, zero), _mm256_unpackhi_epi32(acc, zero));
            hsum256_u64(wide)
        }
    }

    /// Gradient energy: vertical differences as a SAD of consecutive rows; horizontal ones as a
    /// SAD of each 32-byte chunk against itself moved one byte along (whose first lane then
    /// pairs the chunk's first byte with 0, taken out again), plus the pairs across chunks.
    ///
    /// # Safety
    /// As [`ssd_avx2_inl`] for the block `a`.
    #[inline(always)]
    pub unsafe fn texture_avx2_inl(a: *const u8, block: usize) -> u64 {
        // SAFETY (whole body): the caller guarantees AVX2 and `block*block` bytes at `a`.
        unsafe {
            let mut acc = _mm256_setzero_si256();
            let mut fix = 0u64;
            let mut across = 0u64;
            for r in 0..block {
                let row = a.add(r * block);
                let mut x = 0;
                while x < block {
                    let v = _mm256_loadu_si256(row.add(x) as *const __m256i);
                    // w[i] = v[i − 1], w[0] = 0
                    let t = _mm256_permute2x128_si256::<0x08>(v, v);
                    let w = _mm256_alignr_epi8::<15>(v, t);
                    acc = _mm256_add_epi64(acc, _mm256_sad_epu8(v, w));
                    fix += u64::from(*row.add(x));
                    if x > 0 {
                        across += u64::from((*row.add(x)).abs_diff(*row.add(x - 1)));
                    }
                    if r + 1 < block {
                        let below = _mm256_loadu_si256(row.add(block + x) as *const __m256i);
                        acc = _mm256_add_epi64(acc, _mm256_sad_epu8(v, below));
                    }
                    x += 32;
                }
            }
            hsum256_u64(acc) - fix + across
        }
    }

    /// # Safety
    /// AVX2 must be available.
    #[inline(always)]
    unsafe fn hsum256_u64(v: __m256i) -> u64 {
        // SAFETY: caller guarantees AVX2.
        unsafe {
            let s = _mm_add_epi64(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
            let s = _mm_add_epi64(s, _mm_unpackhi_epi64(s, s));
            _mm_cvtsi128_si64(s) as u64
        }
    }

    /// # Safety
    /// As [`sad_avx2`] with `block.is_multiple_of(16)`; SSE2 is always present on x86-64.
    #[inline]
    pub unsafe fn sad_sse2(a: *const u8, b: *const u8, stride: usize, block: usize, limit: u32) -> Option<u32> {
        // SAFETY (whole body): the caller guarantees every address read here is in bounds.
        unsafe {
            let mut total = 0u32;
            let mut y = 0;
            while y < block {
                let end = (y + CHECK_ROWS).min(block);
                let mut acc = _mm_setzero_si128();
                for r in y..end {
                    let (ar, br) = (a.add(r * block), b.add(r * stride));
                    let mut x = 0;
                    while x < block {
                        let va = _mm_loadu_si128(ar.add(x) as *const __m128i);
                        let vb = _mm_loadu_si128(br.add(x) as *const __m128i);
                        acc = _mm_add_epi64(acc, _mm_sad_epu8(va, vb));
                        x += 16;
                    }
                }
                let s = _mm_add_epi64(acc, _mm_unpackhi_epi64(acc, acc));
                total += _mm_cvtsi128_si32(s) as u32;
                if total > limit {
                    return None;
                }
                y = end;
            }
            Some(total)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn kernels_agree(seed in any::<u64>(), bsel in 0usize..4, off in 0usize..40, limit in prop_oneof![Just(u32::MAX), 0u32..200_000]) {
            let block = [16usize, 32, 48, 64][bsel];
            let stride = block + 45;
            let mut s = seed | 1;
            let mut rnd = || { s ^= s << 13; s ^= s >> 7; s ^= s << 17; (s >> 24) as u8 };
            let a: Vec<u8> = (0..block * block).map(|_| rnd()).collect();
            let img: Vec<u8> = (0..stride * (block + 2)).map(|_| rnd()).collect();
            let want = sad_scalar(&a, &img, off, stride, block, limit);
            let got = Kernel::detect(block).sad(&a, &img, off, stride, block, limit);
            prop_assert_eq!(got, want);
            if block.is_multiple_of(16) {
                prop_assert_eq!(Kernel::Sse2.sad(&a, &img, off, stride, block, limit), want);
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    proptest! {
        #[test]
        fn vector_ssd_and_texture_equal_scalar(seed in any::<u64>(), wide in any::<bool>(), off in 0usize..40, flat in 0u8..3) {
            if !std::arch::is_x86_feature_detected!("avx2") {
                return Ok(());
            }
            let block = if wide { 64 } else { 32 };
            let stride = block + 45;
            let mut s = seed | 1;
            // flat = 0: noise; 1: all 255 against all 0 (the largest sums); 2: smooth ramps
            let mut rnd = |i: usize| { s ^= s << 13; s ^= s >> 7; s ^= s << 17; match flat { 0 => (s >> 24) as u8, 1 => 255, _ => (i % 251) as u8 } };
            let a: Vec<u8> = (0..block * block).map(&mut rnd).collect();
            let img: Vec<u8> = (0..stride * (block + 2)).map(|i| if flat == 1 { 0 } else { rnd(i * 7) }).collect();
            // SAFETY: AVX2 checked above; the block and the window lie inside the slices.
            let (ssd, texture) = unsafe {
                (avx2::ssd(a.as_ptr(), img.as_ptr().add(off), stride, block), avx2::texture(a.as_ptr(), block))
            };
            prop_assert_eq!(ssd, ssd_scalar(&a, &img, off, stride, block));
            prop_assert_eq!(texture, texture_scalar(&a, block));
        }
    }

    #[test]
    fn early_termination_only_above_limit() {
        let a = vec![10u8; 32 * 32];
        let img = vec![12u8; 32 * 40];
        let k = Kernel::detect(32);
        assert_eq!(k.sad(&a, &img, 0, 40, 32, 2048), Some(2048));
        assert_eq!(k.sad(&a, &img, 0, 40, 32, 2047), None);
        assert_eq!(k.sad(&a, &img, 0, 40, 32, 0), None);
    }
}
