//! World-anchored procedural texture: one tileable multi-octave value-noise image with a
//! box-filtered mip pyramid, sampled trilinearly in surface coordinates (metres).
//!
//! Why this shape: block matching (32×32 blocks, paper §5) needs texture at every scale a block
//! can see, from 5 mm at 0.5 m to decimetres at 10 m, and the texture must stick to the surface
//! (world-anchored) so the image motion is exactly the geometric motion field. Every surface
//! samples the same tile at its own offset, so neighbouring surfaces differ and their edges show.
//! The mip pyramid removes aliasing where a pixel covers many texels (far floor, grazing walls).

use std::sync::OnceLock;

/// Side of the finest level, texels (a power of two).
const SIZE: usize = 2048;
/// Size of one finest texel on the surface, m (the tile repeats every `SIZE * TEXEL_M` = 8.19 m).
pub const TEXEL_M: f32 = 0.004;

/// How much finer the detail band of [`Texture::sample_detailed`] is than the tile.
pub const DETAIL_SCALE: f32 = 4.0;
/// Gain of the detail band.
pub const DETAIL_GAIN: f32 = 1.0;

/// The shared texture (built once per process, ~0.2 s in release).
pub fn shared() -> &'static Texture {
    static TEX: OnceLock<Texture> = OnceLock::new();
    TEX.get_or_init(|| Texture::generate(0x0FF1_5EED))
}

/// Mip levels of the tile: `SIZE`, `SIZE / 2`, …, 1 texels square.
const LEVELS: usize = SIZE.trailing_zeros() as usize + 1;

/// Texels of all levels together: `SIZE² · (1 + 1/4 + …)`.
const PYRAMID: usize = (SIZE * SIZE * 4 - 1) / 3;

/// Length of the texel buffer: a power of two, so that an index masked with `TEXELS − 1` is
/// known to be within it and the sampler's texel reads need no bounds checks. The pages past
/// the pyramid are never written (nor touched).
const TEXELS: usize = PYRAMID.next_power_of_two();

/// A tileable grey texture and its mip pyramid, values 0..=255.
pub struct Texture {
    /// Every level in one buffer: level `l` is `(SIZE >> l)²` texels, row-major, from `offsets[l]`.
    texels: Box<[u8; TEXELS]>,
    offsets: [usize; LEVELS],
    /// `offsets` as the lanes of [`avx2`] index them (the pyramid has fewer than 2³¹ texels).
    lane_offsets: [i32; LEVELS],
    /// Texels per metre of each level, `1 / (TEXEL_M · 2^l)`, computed once rather than per sample.
    scales: [f32; LEVELS],
}

impl Texture {
    /// Sums value-noise octaves of wavelength 2…512 texels (8 mm … 2 m) with equal amplitude,
    /// then stretches the sum to mean 128 and standard deviation 48.
    pub fn generate(seed: u64) -> Self {
        let mut acc = vec![0f32; SIZE * SIZE];
        let mut wavelength = 2usize;
        let mut octave = 0u64;
        while wavelength <= 512 {
            let cells = SIZE / wavelength;
            let lattice: Vec<f32> = (0..cells * cells)
                .map(|i| {
                    let h = crate::world::mix64(seed ^ (octave << 40) ^ i as u64);
                    (h >> 40) as f32 / (1u64 << 24) as f32
                })
                .collect();
            let inv = 1.0 / wavelength as f32;
            // The lattice cell and weight of a coordinate are the same for rows and columns:
            // computed once per octave instead of once per texel.
            let taps: Vec<(usize, usize, f32)> = (0..SIZE)
                .map(|x| {
                    let fx = (x as f32 + 0.5) * inv - 0.5;
                    let x0 = fx.floor();
                    let i0 = (x0 as isize).rem_euclid(cells as isize) as usize;
                    (i0, (i0 + 1) % cells, smooth(fx - x0))
                })
                .collect();
            for (row, &(iy0, iy1, ty)) in acc.chunks_exact_mut(SIZE).zip(&taps) {
                let (l0, l1) = (&lattice[iy0 * cells..][..cells], &lattice[iy1 * cells..][..cells]);
                for (out, &(ix0, ix1, tx)) in row.iter_mut().zip(&taps) {
                    let a = l0[ix0] + (l0[ix1] - l0[ix0]) * tx;
                    let b = l1[ix0] + (l1[ix1] - l1[ix0]) * tx;
                    *out += a + (b - a) * ty;
                }
            }
            wavelength *= 2;
            octave += 1;
        }
        let n = acc.len() as f64;
        let mean = acc.iter().map(|&v| v as f64).sum::<f64>() / n;
        let sd = (acc.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n).sqrt().max(1e-9);
        let base: Vec<u8> =
            acc.iter().map(|&v| (128.0 + 48.0 * (v as f64 - mean) / sd).round().clamp(0.0, 255.0) as u8).collect();
        let mut levels = vec![base];
        let mut size = SIZE;
        while size > 1 {
            let prev = levels.last().expect("at least the base level");
            let half = size / 2;
            let mut next = vec![0u8; half * half];
            for y in 0..half {
                for x in 0..half {
                    let s = prev[2 * y * size + 2 * x] as u32
                        + prev[2 * y * size + 2 * x + 1] as u32
                        + prev[(2 * y + 1) * size + 2 * x] as u32
                        + prev[(2 * y + 1) * size + 2 * x + 1] as u32;
                    next[y * half + x] = ((s + 2) / 4) as u8;
                }
            }
            levels.push(next);
            size = half;
        }
        let mut offsets = [0; LEVELS];
        let mut scales = [0.0; LEVELS];
        let mut texels = vec![0u8; TEXELS].into_boxed_slice();
        let mut at = 0;
        for (l, level) in levels.iter().enumerate() {
            offsets[l] = at;
            scales[l] = 1.0 / (TEXEL_M * (1 << l) as f32);
            texels[at..at + level.len()].copy_from_slice(level);
            at += level.len();
        }
        debug_assert_eq!(at, PYRAMID);
        let Ok(texels) = texels.try_into() else { unreachable!("the buffer was made TEXELS long") };
        let lane_offsets = offsets.map(|o| o as i32);
        Self { texels, offsets, lane_offsets, scales }
    }

    /// Mip level `l`: `(SIZE >> l)²` texels, row-major.
    #[cfg(test)]
    fn level(&self, l: usize) -> &[u8] {
        let size = SIZE >> l;
        &self.texels[self.offsets[l]..][..size * size]
    }

    /// The texture at surface point (u, v) in metres, for a pixel footprint of `footprint_m`
    /// metres on the surface: trilinear between the two mip levels around the footprint.
    /// Returns 0..=1 (mean 0.5).
    #[inline(always)]
    pub fn sample(&self, u: f32, v: f32, footprint_m: f32) -> f32 {
        let lod = fast_log2(footprint_m / TEXEL_M).max(0.0);
        let max = (LEVELS - 1) as f32;
        if lod >= max {
            return self.texels[self.offsets[LEVELS - 1]] as f32 / 255.0;
        }
        // 0 ≤ lod < LEVELS − 1 here: through i32 the conversions are exact and cheaper than
        // the saturating float ↔ usize ones
        let l0 = lod as i32 as usize;
        let f = lod - l0 as i32 as f32;
        let a = self.bilinear(l0, u, v);
        if f < 0.01 {
            return a / 255.0;
        }
        let b = self.bilinear(l0 + 1, u, v);
        (a + (b - a) * f) / 255.0
    }

    /// [`Texture::sample`] plus fine print: the band of the tile shrunk [`DETAIL_SCALE`] times
    /// between one and four of its texels (1–4 mm on the surface at the default scale) added
    /// with gain [`DETAIL_GAIN`]. For obstacles (a cardboard box's print and edges, the folds of
    /// clothes): the shared tile's finest wavelength is 8 mm, 5–10 px within 2 m of the camera,
    /// too smooth for a 32 px block to match on a small near object. The band is filtered by the
    /// footprint like the rest: once a pixel covers 4 mm (5 m away at 1272 px focal length) it
    /// averages out.
    #[inline]
    pub fn sample_detailed(&self, u: f32, v: f32, footprint_m: f32) -> f32 {
        let base = self.sample(u, v, footprint_m);
        let fine_m = footprint_m * DETAIL_SCALE;
        let coarse_m = fine_m.max(4.0 * TEXEL_M);
        if coarse_m == fine_m {
            // the band is empty (the two samples would be the same): `fine − coarse` is 0
            return base + DETAIL_GAIN * 0.0;
        }
        let (du, dv) = (u * DETAIL_SCALE + 0.37, v * DETAIL_SCALE + 0.61);
        let fine = self.sample(du, dv, fine_m);
        let coarse = self.sample(du, dv, coarse_m);
        base + DETAIL_GAIN * (fine - coarse)
    }

    // Always inlined: two to six calls per pixel, and the caller's level and coordinates let
    // the compiler keep everything in registers.
    #[inline(always)]
    fn bilinear(&self, level: usize, u: f32, v: f32) -> f32 {
        let shift = SIZE.trailing_zeros() - level as u32;
        let size = 1usize << shift;
        let mask = size as i32 - 1;
        let scale = self.scales[level];
        let x = u * scale - 0.5;
        let y = v * scale - 0.5;
        let (ix, fx) = floor_frac(x);
        let (iy, fy) = floor_frac(y);
        let x0 = (ix & mask) as usize;
        let x1 = ((ix + 1) & mask) as usize;
        let base = self.offsets[level];
        let row0 = base + (((iy & mask) as usize) << shift);
        let row1 = base + ((((iy + 1) & mask) as usize) << shift);
        // every index is below the pyramid's size: the mask changes none, it only shows the
        // compiler that they are in bounds
        let t = |i: usize| self.texels[i & (TEXELS - 1)] as f32;
        let (a, b, c, d) = (t(row0 + x0), t(row0 + x1), t(row1 + x0), t(row1 + x1));
        let top = a + (b - a) * fx;
        let bot = c + (d - c) * fx;
        top + (bot - top) * fy
    }
}

fn smooth(t: f32) -> f32 {
    t * t * (3.0 - 2.0 * t)
}

/// Floor as an integer and the fractional part, without a libm call. Coordinates beyond ±2³¹
/// texels (8.6 Mm) do not occur.
#[inline]
fn floor_frac(x: f32) -> (i32, f32) {
    let i = x as i32;
    let i = if (i as f32) > x { i - 1 } else { i };
    (i, x - i as f32)
}

/// log2 to about 0.09 accuracy (exponent plus linear mantissa), enough to pick mip levels.
#[inline]
fn fast_log2(x: f32) -> f32 {
    if x <= 0.0 || !x.is_finite() {
        return if x.is_finite() { -126.0 } else { 126.0 };
    }
    let bits = x.to_bits();
    let exp = ((bits >> 23) & 0xff) as f32 - 127.0;
    let mant = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    exp + (mant - 1.0)
}

/// Eight samples at once with AVX2, bit for bit those of [`Texture::sample`] and
/// [`Texture::sample_detailed`]: the same IEEE operations in the same order per lane (no fused
/// multiply-add: only `avx2` is enabled, so none can be formed), and the float ↔ integer
/// conversions only where they agree with Rust's `as` (see [`avx2::floor_frac`]).
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2 {
    use super::{DETAIL_GAIN, DETAIL_SCALE, LEVELS, SIZE, TEXEL_M, Texture};
    use std::arch::x86_64::*;

    // The `#[inline(always)]` functions here carry no `target_feature` themselves: they are
    // inlined into the renderer's AVX2-enabled shading loop. Callers must ensure AVX2 is present.

    /// Per lane [`Texture::sample`] where `detailed` is clear and [`Texture::sample_detailed`]
    /// where it is set (all ones). Lanes whose coordinates a lane conversion would not treat like
    /// `as i32` (beyond ±2³¹ texels, NaN) set `bad`: the caller takes the scalar path for them.
    ///
    /// # Safety
    /// AVX2 must be available.
    #[inline(always)]
    pub(crate) unsafe fn sample(
        tex: &Texture,
        u: __m256,
        v: __m256,
        footprint_m: __m256,
        detailed: __m256,
        bad: &mut __m256,
    ) -> __m256 {
        // SAFETY (whole body): the caller guarantees AVX2; `plain` reads only in-bounds texels.
        unsafe {
            let base = plain(tex, u, v, footprint_m, bad);
            if _mm256_movemask_ps(detailed) == 0 {
                return base;
            }
            let fine_m = _mm256_mul_ps(footprint_m, _mm256_set1_ps(DETAIL_SCALE));
            // `maxps` returns its second operand for a NaN first one, as `f32::max` does
            let coarse_m = _mm256_max_ps(fine_m, _mm256_set1_ps(4.0 * TEXEL_M));
            let empty = _mm256_cmp_ps::<_CMP_EQ_OQ>(coarse_m, fine_m);
            let gain = _mm256_set1_ps(DETAIL_GAIN);
            let out = _mm256_blendv_ps(base, _mm256_add_ps(base, _mm256_mul_ps(gain, _mm256_setzero_ps())), detailed);
            let band = _mm256_andnot_ps(empty, detailed);
            if _mm256_movemask_ps(band) == 0 {
                return out;
            }
            let du = _mm256_add_ps(_mm256_mul_ps(u, _mm256_set1_ps(DETAIL_SCALE)), _mm256_set1_ps(0.37));
            let dv = _mm256_add_ps(_mm256_mul_ps(v, _mm256_set1_ps(DETAIL_SCALE)), _mm256_set1_ps(0.61));
            let fine = plain(tex, du, dv, fine_m, bad);
            let coarse = plain(tex, du, dv, coarse_m, bad);
            let with_band = _mm256_add_ps(base, _mm256_mul_ps(gain, _mm256_sub_ps(fine, coarse)));
            _mm256_blendv_ps(out, with_band, band)
        }
    }

    /// [`Texture::sample`] per lane.
    ///
    /// # Safety
    /// AVX2 must be available.
    #[inline(always)]
    unsafe fn plain(tex: &Texture, u: __m256, v: __m256, footprint_m: __m256, bad: &mut __m256) -> __m256 {
        // SAFETY (whole body): the caller guarantees AVX2; levels are clamped to the pyramid.
        unsafe {
            let lod =
                _mm256_max_ps(fast_log2(_mm256_div_ps(footprint_m, _mm256_set1_ps(TEXEL_M))), _mm256_setzero_ps());
            let coarsest = _mm256_cmp_ps::<_CMP_GE_OQ>(lod, _mm256_set1_ps((LEVELS - 1) as f32));
            // below the coarsest level 0 ≤ lod < LEVELS − 1 and the conversion is exact; the
            // coarsest lanes are overwritten at the end, their level only has to stay in range
            let l0 = _mm256_min_epi32(_mm256_cvttps_epi32(lod), _mm256_set1_epi32(LEVELS as i32 - 2));
            let f = _mm256_sub_ps(lod, _mm256_cvtepi32_ps(l0));
            let a = bilinear(tex, l0, u, v, bad);
            let k = _mm256_set1_ps(255.0);
            let mut out = _mm256_div_ps(a, k);
            let near = _mm256_cmp_ps::<_CMP_LT_OQ>(f, _mm256_set1_ps(0.01));
            let tri = _mm256_andnot_ps(_mm256_or_ps(near, coarsest), _mm256_castsi256_ps(_mm256_set1_epi32(-1)));
            if _mm256_movemask_ps(tri) != 0 {
                let b = bilinear(tex, _mm256_add_epi32(l0, _mm256_set1_epi32(1)), u, v, bad);
                let mixed = _mm256_div_ps(_mm256_add_ps(a, _mm256_mul_ps(_mm256_sub_ps(b, a), f)), k);
                out = _mm256_blendv_ps(out, mixed, tri);
            }
            let last = tex.texels[tex.offsets[LEVELS - 1]] as f32 / 255.0;
            _mm256_blendv_ps(out, _mm256_set1_ps(last), coarsest)
        }
    }

    /// [`super::fast_log2`] per lane, its special cases included.
    ///
    /// # Safety
    /// AVX2 must be available.
    #[inline(always)]
    unsafe fn fast_log2(x: __m256) -> __m256 {
        // SAFETY (whole body): the caller guarantees AVX2.
        unsafe {
            let bits = _mm256_castps_si256(x);
            let exp = _mm256_and_si256(_mm256_srli_epi32::<23>(bits), _mm256_set1_epi32(0xff));
            let exp = _mm256_sub_ps(_mm256_cvtepi32_ps(exp), _mm256_set1_ps(127.0));
            let mant =
                _mm256_or_si256(_mm256_and_si256(bits, _mm256_set1_epi32(0x007f_ffff)), _mm256_set1_epi32(0x3f80_0000));
            let r = _mm256_add_ps(exp, _mm256_sub_ps(_mm256_castsi256_ps(mant), _mm256_set1_ps(1.0)));
            let nonpositive = _mm256_cmp_ps::<_CMP_LE_OQ>(x, _mm256_setzero_ps());
            let abs = _mm256_and_ps(x, _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff)));
            let not_finite = _mm256_cmp_ps::<_CMP_NLT_UQ>(abs, _mm256_set1_ps(f32::INFINITY));
            let r = _mm256_blendv_ps(r, _mm256_set1_ps(-126.0), nonpositive);
            _mm256_blendv_ps(r, _mm256_set1_ps(126.0), not_finite)
        }
    }

    /// [`super::floor_frac`] per lane. `cvttps2dq` truncates like `as i32` for |x| < 2³¹ and
    /// differs beyond and for NaN (where `as` saturates or gives 0): such lanes set `bad`.
    ///
    /// # Safety
    /// AVX2 must be available.
    #[inline(always)]
    unsafe fn floor_frac(x: __m256, bad: &mut __m256) -> (__m256i, __m256) {
        // SAFETY (whole body): the caller guarantees AVX2.
        unsafe {
            let abs = _mm256_and_ps(x, _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff)));
            *bad = _mm256_or_ps(*bad, _mm256_cmp_ps::<_CMP_NLT_UQ>(abs, _mm256_set1_ps(2_147_483_648.0)));
            let i = _mm256_cvttps_epi32(x);
            // a comparison's true lanes are −1: added, they take one off where i > x
            let above = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_GT_OQ>(_mm256_cvtepi32_ps(i), x));
            let i = _mm256_add_epi32(i, above);
            (i, _mm256_sub_ps(x, _mm256_cvtepi32_ps(i)))
        }
    }

    /// [`Texture::bilinear`] per lane, each at its own `level` (0 ≤ level < LEVELS).
    ///
    /// # Safety
    /// AVX2 must be available; every lane of `level` is below `LEVELS`.
    #[inline(always)]
    unsafe fn bilinear(tex: &Texture, level: __m256i, u: __m256, v: __m256, bad: &mut __m256) -> __m256 {
        // SAFETY (whole body): the caller guarantees AVX2 and the levels. Each texel index is
        // below the pyramid's size (masked within its level), and a gather reads 4 bytes from
        // it: within the `TEXELS`-long buffer, which is longer than the pyramid by far more
        // than 3 bytes.
        unsafe {
            let one = _mm256_set1_epi32(1);
            let shift = _mm256_sub_epi32(_mm256_set1_epi32(SIZE.trailing_zeros() as i32), level);
            let mask = _mm256_sub_epi32(_mm256_sllv_epi32(one, shift), one);
            let scale = _mm256_i32gather_ps::<4>(tex.scales.as_ptr(), level);
            let half = _mm256_set1_ps(0.5);
            let x = _mm256_sub_ps(_mm256_mul_ps(u, scale), half);
            let y = _mm256_sub_ps(_mm256_mul_ps(v, scale), half);
            let (ix, fx) = floor_frac(x, bad);
            let (iy, fy) = floor_frac(y, bad);
            let x0 = _mm256_and_si256(ix, mask);
            let x1 = _mm256_and_si256(_mm256_add_epi32(ix, one), mask);
            let base = _mm256_i32gather_epi32::<4>(tex.lane_offsets.as_ptr(), level);
            let row0 = _mm256_add_epi32(base, _mm256_sllv_epi32(_mm256_and_si256(iy, mask), shift));
            let row1 =
                _mm256_add_epi32(base, _mm256_sllv_epi32(_mm256_and_si256(_mm256_add_epi32(iy, one), mask), shift));
            let (a, b) = (texel(tex, _mm256_add_epi32(row0, x0)), texel(tex, _mm256_add_epi32(row0, x1)));
            let (c, d) = (texel(tex, _mm256_add_epi32(row1, x0)), texel(tex, _mm256_add_epi32(row1, x1)));
            let top = _mm256_add_ps(a, _mm256_mul_ps(_mm256_sub_ps(b, a), fx));
            let bot = _mm256_add_ps(c, _mm256_mul_ps(_mm256_sub_ps(d, c), fx));
            _mm256_add_ps(top, _mm256_mul_ps(_mm256_sub_ps(bot, top), fy))
        }
    }

    /// The texels at pyramid indices `i`, as floats.
    ///
    /// # Safety
    /// AVX2 must be available; every lane of `i` is below the pyramid's size.
    #[inline(always)]
    unsafe fn texel(tex: &Texture, i: __m256i) -> __m256 {
        // SAFETY: the caller guarantees AVX2 and the indices; a gather reads 4 bytes at each,
        // within the `TEXELS`-long buffer (longer than the pyramid by far more than 3 bytes).
        unsafe {
            let word = _mm256_i32gather_epi32::<1>(tex.texels.as_ptr() as *const i32, i);
            _mm256_cvtepi32_ps(_mm256_and_si256(word, _mm256_set1_epi32(0xff)))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_has_contrast_and_mips_average() {
        let t = shared();
        let base = t.level(0);
        let mean = base.iter().map(|&v| v as f64).sum::<f64>() / base.len() as f64;
        assert!((mean - 128.0).abs() < 2.0, "{mean}");
        // Fine detail: neighbouring texels differ.
        let diff: f64 = base[..SIZE].windows(2).map(|w| (w[0] as f64 - w[1] as f64).abs()).sum::<f64>() / SIZE as f64;
        assert!(diff > 3.0, "{diff}");
        // Far away (huge footprint) the texture fades to its mean: no aliasing.
        assert!((t.sample(1.234, 5.678, 100.0) - 0.5).abs() < 0.02);
        // The tile repeats every SIZE texels.
        let p = SIZE as f32 * TEXEL_M;
        assert!((t.sample(0.3, 0.7, 0.001) - t.sample(0.3 + p, 0.7 - p, 0.001)).abs() < 1e-3);
    }

    #[test]
    fn detailed_sampling_adds_fine_print_that_averages_out_far_away() {
        let t = shared();
        // mean difference between samples 1 mm apart on the surface, seen with a 1 mm footprint
        let step = |f: &dyn Fn(f32) -> f32| {
            (0..400).map(|i| (f(i as f32 * 0.001) - f((i + 1) as f32 * 0.001)).abs()).sum::<f32>() / 400.0
        };
        let plain = step(&|u| t.sample(u, 0.3, 0.001));
        let print = step(&|u| t.sample_detailed(u, 0.3, 0.001));
        assert!(print > 2.0 * plain, "plain {plain}, with print {print}");
        // half a metre per pixel: the print band is averaged away
        assert!((t.sample_detailed(1.2, 3.4, 0.5) - t.sample(1.2, 3.4, 0.5)).abs() < 0.02);
    }

    /// The generated tile and its mips, and samples at every footprint, pinned bit for bit (the
    /// simulated missions depend on every grey level).
    #[test]
    fn texture_and_samples_are_pinned_bit_for_bit() {
        let t = shared();
        let fnv = |h: u64, b: u8| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3);
        let levels = (0..LEVELS).flat_map(|l| t.level(l)).fold(0xcbf2_9ce4_8422_2325u64, |h, &b| fnv(h, b));
        assert_eq!(levels, 3_950_121_686_610_735_151, "texture levels");
        let mut h = 0xcbf2_9ce4_8422_2325u64;
        for i in 0..4000 {
            let (u, v) = (i as f32 * 0.0137 - 9.0, (i * 7 % 1000) as f32 * 0.0091 - 3.0);
            let footprint = 0.0005 * 1.0021f32.powi(i);
            for s in [t.sample(u, v, footprint), t.sample_detailed(u, v, footprint)] {
                h = s.to_le_bytes().iter().fold(h, |h, &b| fnv(h, b));
            }
        }
        assert_eq!(h, 2_912_503_261_308_889_843, "samples");
    }

    /// Eight points through [`avx2::sample`]: the values and which lanes it flagged.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn lanes(t: &Texture, u: [f32; 8], v: [f32; 8], footprint: [f32; 8], detailed: [bool; 8]) -> ([f32; 8], [bool; 8]) {
        use std::arch::x86_64::*;
        let mask = detailed.map(|d| if d { -1i32 } else { 0 });
        let (mut values, mut flags) = ([0f32; 8], [0i32; 8]);
        // SAFETY: AVX2 is enabled here; the loads and stores are of eight-element arrays.
        unsafe {
            let mut bad = _mm256_setzero_ps();
            let out = avx2::sample(
                t,
                _mm256_loadu_ps(u.as_ptr()),
                _mm256_loadu_ps(v.as_ptr()),
                _mm256_loadu_ps(footprint.as_ptr()),
                _mm256_castsi256_ps(_mm256_loadu_si256(mask.as_ptr() as *const __m256i)),
                &mut bad,
            );
            _mm256_storeu_ps(values.as_mut_ptr(), out);
            _mm256_storeu_si256(flags.as_mut_ptr() as *mut __m256i, _mm256_castps_si256(bad));
        }
        (values, flags.map(|f| f != 0))
    }

    /// The renderer shades eight pixels at once through `avx2::sample`: it must give the scalar
    /// samples bit for bit at every footprint (mip levels, the trilinear cut-off, the coarsest
    /// level, the special cases of `fast_log2`) and coordinate, and flag the lanes whose
    /// coordinates it cannot convert like `as i32`, which the renderer then samples one by one.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn lanes_sample_bit_for_bit_like_the_scalar_code() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let t = shared();
        let mut points = Vec::new();
        for i in 0..40_000 {
            let (u, v) = (i as f32 * 0.0137 - 90.0, (i * 7 % 1000) as f32 * -0.0091 + 3.0);
            points.push((u, v, 0.0001 * 1.0006f32.powi(i)));
        }
        for l in 0..LEVELS as i32 + 2 {
            let exact = TEXEL_M * 2f32.powi(l);
            for f in [exact, exact * 1.0069, exact * 1.0070, exact * 1.0071, exact * 0.9999] {
                points.push((1.7, -2.3, f));
            }
        }
        for f in [0.0, -0.0, -1.0, 1e-30, f32::MIN_POSITIVE, 1e30, f32::INFINITY, f32::NEG_INFINITY, f32::NAN] {
            points.push((0.3, 0.4, f));
        }
        let far = [8e6, -8e6, 8.6e6, -8.6e6, 9e6, 1e12, -1e12, f32::NAN, f32::INFINITY];
        for &x in &far {
            points.push((x, 0.2, 0.001));
            points.push((0.2, x, 0.01));
        }
        let mut flagged = 0;
        for (k, chunk) in points.chunks(8).enumerate() {
            let mut p = [(0.0, 0.0, 1.0); 8];
            p[..chunk.len()].copy_from_slice(chunk);
            for detailed in [[false; 8], [true; 8], std::array::from_fn(|i| (i + k) % 3 == 0)] {
                // SAFETY: AVX2 was detected above.
                let (values, bad) = unsafe { lanes(t, p.map(|q| q.0), p.map(|q| q.1), p.map(|q| q.2), detailed) };
                for (i, &(u, v, f)) in p.iter().enumerate() {
                    let convertible = |x: f32| x.abs() < 2e6;
                    if bad[i] {
                        flagged += 1;
                        assert!(!(convertible(u) && convertible(v)), "({u}, {v}, {f}) flagged");
                    } else {
                        // (the scalar code is only asked where the lanes converted everything:
                        // beyond, its `ix + 1` may overflow)
                        let want = if detailed[i] { t.sample_detailed(u, v, f) } else { t.sample(u, v, f) };
                        assert_eq!(values[i].to_bits(), want.to_bits(), "({u}, {v}, {f}) detailed {}", detailed[i]);
                    }
                }
            }
        }
        assert!(flagged > 0, "far coordinates are flagged");
    }

    #[test]
    fn fast_log2_is_close() {
        for x in [0.3f32, 1.0, 1.5, 7.0, 1000.0] {
            assert!((fast_log2(x) - x.log2()).abs() < 0.1, "{x}");
        }
        assert_eq!(floor_frac(-1.25), (-2, 0.75));
    }
}
