//! A lower bound on a block's SAD from sums of 4×4 cells (successive elimination): for any
//! split of the block into cells, Σ_cells |Σ_cell A − Σ_cell B| ≤ Σ |A − B|, since the absolute
//! value of a sum is at most the sum of the absolute values. The search skips a candidate whose
//! bound already exceeds its early-termination limit: its SAD would have been abandoned anyway,
//! so the result is unchanged and only the work shrinks.
//!
//! The cell sums of frame B are computed once per frame for every pixel position
//! ([`CellSums::compute`]); a candidate's bound then reads one sum per cell instead of the
//! cell's 16 pixels. On AVX2 the bound of 16 horizontally adjacent candidates is one 256-bit
//! load, subtraction and saturating addition per cell. The sums are 16-bit and saturate, so
//! the bound rules nothing out once the limit reaches 65,535 (blocks of 64 px, or a 32 px block
//! whose best match is poor).
//!
//! On rendered frames with smooth motion the bound rules out most candidates before any SAD;
//! on strongly textured frames with large motion, fewer.

use hal::LumaImage;

/// The cell side, pixels.
pub const CELL: usize = 4;

/// 4×4 box sums of a frame at every pixel position: `at(x, y)` = Σ of the pixels in
/// `[x, x + 4) × [y, y + 4)`, for `x ≤ width − 4`, `y ≤ height − 4`. Each sum is at most
/// 16 × 255 = 4080.
#[derive(Debug, Default)]
pub struct CellSums {
    sums: Vec<u16>,
    width: usize,
    /// Horizontal 4-sums of the last four rows, a ring (scratch).
    rows: Vec<u16>,
}

impl CellSums {
    /// Recomputes the sums for `img` (allocates only when the size grows).
    pub fn compute(&mut self, img: &LumaImage) {
        let (w, h) = (img.width(), img.height());
        if w < CELL || h < CELL {
            self.sums.clear();
            self.width = 0;
            return;
        }
        let (sw, sh) = (w - CELL + 1, h - CELL + 1);
        self.width = sw;
        // Every entry is written below: resizing only sets the length.
        self.sums.resize(sw * sh, 0);
        self.rows.resize(CELL * sw, 0);
        // The horizontal sums of each row go into a ring of four rows; once four are in, their
        // sum is the output row that starts at the oldest.
        for y in 0..h {
            let src = img.row(y);
            let dst = &mut self.rows[(y % CELL) * sw..(y % CELL + 1) * sw];
            // Four shifted slices rather than `windows`, so that the loop vectorises.
            let (s0, s1, s2, s3) = (&src[..sw], &src[1..sw + 1], &src[2..sw + 2], &src[3..sw + 3]);
            for (((d, &p0), (&p1, &p2)), &p3) in dst.iter_mut().zip(s0).zip(s1.iter().zip(s2)).zip(s3) {
                *d = u16::from(p0) + u16::from(p1) + u16::from(p2) + u16::from(p3);
            }
            if y + 1 >= CELL {
                let out = &mut self.sums[(y + 1 - CELL) * sw..(y + 2 - CELL) * sw];
                let (r0, rest) = self.rows.split_at(sw);
                let (r1, rest) = rest.split_at(sw);
                let (r2, r3) = rest.split_at(sw);
                for ((o, (p0, p1)), (p2, p3)) in out.iter_mut().zip(r0.iter().zip(r1)).zip(r2.iter().zip(r3)) {
                    *o = p0 + p1 + p2 + p3;
                }
            }
        }
    }

    /// Where the sum of the cell whose top-left pixel is `(x, y)` lies in [`CellSums::data`].
    pub fn index(&self, x: usize, y: usize) -> usize {
        y * self.width + x
    }

    /// Whether the sums hold every cell that [`Bound16::over16`] reads for sixteen candidates
    /// from `at` with `n` × `n` cells.
    pub fn holds16(&self, at: usize, n: usize) -> bool {
        at + 15 + (n - 1) * CELL * (self.width + 1) < self.sums.len()
    }

    /// Row stride of [`CellSums::data`].
    pub fn width(&self) -> usize {
        self.width
    }

    pub fn data(&self) -> &[u16] {
        &self.sums
    }
}

/// The cell sums of a contiguous `block`×`block` block (`block` a multiple of [`CELL`]), row
/// by row of cells, into `out`.
pub fn block_cells(a: &[u8], block: usize, out: &mut Vec<u16>) {
    let n = block / CELL;
    out.clear();
    out.resize(n * n, 0);
    assert!(a.len() >= block * block, "block buffer too small");
    #[cfg(target_arch = "x86_64")]
    if block == 32 && std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 checked just above; 32 rows of 32 bytes at `a` (asserted) and 64 sums
        // in `out`.
        unsafe { block_cells_avx2_32(a.as_ptr(), out.as_mut_ptr()) };
        return;
    }
    for (y, row) in a.chunks_exact(block).take(block).enumerate() {
        let cells = &mut out[(y / CELL) * n..(y / CELL + 1) * n];
        for (c, px) in cells.iter_mut().zip(row.chunks_exact(CELL)) {
            *c += px.iter().map(|&p| u16::from(p)).sum::<u16>();
        }
    }
}

/// [`block_cells`] of a 32-pixel block: each row's eight 4-byte sums in one multiply-add pair,
/// four rows added, packed to 16 bits.
///
/// # Safety
/// AVX2 must be available; `a` must point at 32 × 32 readable bytes and `out` at 64 writable
/// sums.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn block_cells_avx2_32(a: *const u8, out: *mut u16) {
    use std::arch::x86_64::*;
    // SAFETY (whole body): the reads and writes stay within the caller's regions.
    unsafe {
        let (ones8, ones16) = (_mm256_set1_epi8(1), _mm256_set1_epi16(1));
        for cy in 0..8 {
            let mut acc = _mm256_setzero_si256();
            for r in 0..CELL {
                let row = _mm256_loadu_si256(a.add((cy * CELL + r) * 32) as *const __m256i);
                // byte pairs → 16 bits, then pairs of those → the eight 4-byte sums in 32 bits
                let quads = _mm256_madd_epi16(_mm256_maddubs_epi16(row, ones8), ones16);
                acc = _mm256_add_epi32(acc, quads);
            }
            // Eight sums below 2^12, in order across the two halves: pack to 16 bits.
            let packed = _mm_packus_epi32(_mm256_castsi256_si128(acc), _mm256_extracti128_si256::<1>(acc));
            _mm_storeu_si128(out.add(cy * 8) as *mut __m128i, packed);
        }
    }
}

/// The bound of one candidate whose window's top-left pixel is at `at` in `sums`
/// ([`CellSums::index`]), saturated at `u16::MAX` (still a lower bound of the SAD).
pub fn bound_scalar(sums: &CellSums, at: usize, cells: &[u16], n: usize) -> u16 {
    let mut acc = 0u16;
    for cy in 0..n {
        for cx in 0..n {
            let b = sums.sums[at + cy * CELL * sums.width + cx * CELL];
            acc = acc.saturating_add(b.abs_diff(cells[cy * n + cx]));
        }
    }
    acc
}

/// The lower bound of sixteen horizontally adjacent candidates as a type, so that the search
/// loop is compiled once per kernel with the bound inlined.
pub trait Bound16 {
    /// Bit k set: the candidate at `at + k` (k < 16) has a bound above `limit`, so its SAD
    /// exceeds `limit`. No bit is set when `limit` is at least `u16::MAX` (the saturated bound
    /// cannot exceed it).
    ///
    /// # Safety
    /// `sums.holds16(at, n)`; `cells` must hold `n²` sums; the CPU must support the kernel's
    /// instructions (the portable one needs none).
    unsafe fn over16(sums: &CellSums, at: usize, cells: &[u16], n: usize, limit: u32) -> u32;
}

/// The bound computed candidate by candidate.
pub struct ScalarBound;

impl Bound16 for ScalarBound {
    #[inline(always)]
    unsafe fn over16(sums: &CellSums, at: usize, cells: &[u16], n: usize, limit: u32) -> u32 {
        if limit >= u32::from(u16::MAX) {
            return 0;
        }
        (0..16).filter(|&k| u32::from(bound_scalar(sums, at + k, cells, n)) > limit).fold(0, |m, k| m | (1 << k))
    }
}

/// Sixteen candidates per 256-bit vector.
#[cfg(target_arch = "x86_64")]
pub struct Avx2Bound;

#[cfg(target_arch = "x86_64")]
impl Bound16 for Avx2Bound {
    #[inline(always)]
    unsafe fn over16(sums: &CellSums, at: usize, cells: &[u16], n: usize, limit: u32) -> u32 {
        use std::arch::x86_64::*;
        if limit >= u32::from(u16::MAX) {
            return 0;
        }
        debug_assert!(sums.holds16(at, n) && cells.len() >= n * n);
        let stride = sums.width;
        // SAFETY (whole body): AVX2 is guaranteed by the caller; every 16-lane load starts at a
        // cell's sum and ends within `sums` (caller contract, checked above in debug builds).
        unsafe {
            let base = sums.sums.as_ptr().add(at);
            let lim = _mm256_set1_epi16(limit as u16 as i16);
            let ones = _mm256_set1_epi8(-1);
            let zero16 = _mm256_setzero_si256();
            let mut acc = _mm256_setzero_si256();
            for cy in 0..n {
                let row = base.add(cy * CELL * stride);
                for cx in 0..n {
                    let b = _mm256_loadu_si256(row.add(cx * CELL) as *const __m256i);
                    let a = _mm256_set1_epi16(*cells.get_unchecked(cy * n + cx) as i16);
                    // Both below 4096: the signed difference is exact.
                    acc = _mm256_adds_epu16(acc, _mm256_abs_epi16(_mm256_sub_epi16(b, a)));
                }
                // Where texture is strong, the first rows of cells already put every lane over
                // the limit; the remaining cells could only add to it.
                if cy == 1 && _mm256_testz_si256(_mm256_cmpeq_epi16(_mm256_subs_epu16(acc, lim), zero16), ones) != 0 {
                    return 0xffff;
                }
            }
            // acc > limit exactly where the saturating acc − limit is non-zero. Two mask bits
            // per 16-bit lane; keep the even ones and pack them.
            let excess = _mm256_subs_epu16(acc, lim);
            let within = _mm256_cmpeq_epi16(excess, zero16);
            // Words to bytes: the halves become [w0..w7, w0..w7] and [w8..w15, w8..w15]; their
            // first quadwords then hold the 16 lanes in order.
            let packed = _mm256_permute4x64_epi64::<0b11_01_10_00>(_mm256_packs_epi16(within, within));
            !(_mm256_movemask_epi8(packed) as u32) & 0xffff
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flow::sad::sad_scalar;
    use proptest::prelude::*;

    fn noise(w: usize, h: usize, seed: u64) -> LumaImage {
        let mut s = seed | 1;
        let data = (0..w * h)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 24) as u8
            })
            .collect();
        LumaImage::from_vec(w, h, data).unwrap()
    }

    proptest! {
        #[test]
        fn the_bound_never_exceeds_the_sad_and_the_kernels_agree(seed in any::<u64>(), bsel in 0usize..3, x in 0usize..24, y in 0usize..8, limit in 0u32..80_000) {
            let block = [8usize, 16, 32][bsel];
            let (w, h) = (block + 48, block + 12);
            let (a_img, b_img) = (noise(w, h, seed), noise(w, h, seed ^ 0x9e37));
            let mut a = vec![0u8; block * block];
            for r in 0..block {
                a[r * block..(r + 1) * block].copy_from_slice(&a_img.row(r)[..block]);
            }
            let mut sums = CellSums::default();
            sums.compute(&b_img);
            let mut cells = Vec::new();
            block_cells(&a, block, &mut cells);
            let n = block / CELL;
            let at = sums.index(x, y);
            for k in 0..16 {
                let bound = bound_scalar(&sums, at + k, &cells, n);
                let sad = sad_scalar(&a, b_img.data(), y * w + x + k, w, block, u32::MAX).unwrap();
                prop_assert!(u32::from(bound) <= sad, "bound {} above the SAD {}", bound, sad);
            }
            // SAFETY: the portable kernel needs no CPU feature; the 16 windows fit in `sums`.
            let scalar = unsafe { ScalarBound::over16(&sums, at, &cells, n, limit) };
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: AVX2 checked just above.
                let avx2 = unsafe { Avx2Bound::over16(&sums, at, &cells, n, limit) };
                prop_assert_eq!(avx2, scalar);
            }
        }
    }

    #[test]
    fn block_cells_are_the_sums_of_their_pixels() {
        for seed in 1..20 {
            let img = noise(32, 32, seed);
            let mut got = Vec::new();
            block_cells(img.data(), 32, &mut got);
            for (i, &c) in got.iter().enumerate() {
                let (cy, cx) = (i / 8, i % 8);
                let want: u16 = (0..4)
                    .flat_map(|y| (0..4).map(move |x| (x, y)))
                    .map(|(x, y)| u16::from(img.row(cy * 4 + y)[cx * 4 + x]))
                    .sum();
                assert_eq!(c, want, "cell {i}");
            }
        }
    }

    #[test]
    fn cell_sums_are_box_sums() {
        let img = noise(13, 9, 7);
        let mut sums = CellSums::default();
        sums.compute(&img);
        assert_eq!(sums.width(), 10);
        for y in 0..6 {
            for x in 0..10 {
                let want: u16 = (y..y + 4)
                    .flat_map(|yy| (x..x + 4).map(move |xx| (xx, yy)))
                    .map(|(xx, yy)| u16::from(img.row(yy)[xx]))
                    .sum();
                assert_eq!(sums.data()[y * 10 + x], want);
            }
        }
    }

    #[test]
    fn a_limit_beyond_the_saturated_bound_prunes_nothing() {
        let a = vec![255u8; 32 * 32];
        let img = LumaImage::from_vec(64, 40, vec![0u8; 64 * 40]).unwrap();
        let mut sums = CellSums::default();
        sums.compute(&img);
        let mut cells = Vec::new();
        block_cells(&a, 32, &mut cells);
        // SAFETY: no CPU feature needed; the 16 windows fit.
        let over = |limit| unsafe { ScalarBound::over16(&sums, 0, &cells, 8, limit) };
        // The true SAD is 261,120; the bound saturates at 65,535.
        assert_eq!(over(65_534), 0xffff);
        assert_eq!(over(65_535), 0);
        assert_eq!(over(200_000), 0);
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 checked just above; the 16 windows fit.
            let avx2 = |limit| unsafe { Avx2Bound::over16(&sums, 0, &cells, 8, limit) };
            assert_eq!((avx2(65_534), avx2(65_535), avx2(200_000)), (0xffff, 0, 0));
        }
    }
}
