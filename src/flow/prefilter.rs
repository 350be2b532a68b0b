//! Frame preprocessing for block matching: the local-mean high-pass and the 2×2 pyramid.
//!
//! Subtracting a local box mean removes the exposure level (and slow illumination gradients)
//! from each frame once, so that the per-candidate cost can stay a plain SAD of bytes, which
//! vectorises (`psadbw`). `docs/flow.md` measures this against SAD, zero-mean SAD and NCC.

use hal::LumaImage;

/// Largest supported prefilter radius k (window (2k+1)² = 225 px keeps box sums within u16).
pub const MAX_RADIUS: usize = 7;

/// Reusable buffers for [`highpass`].
#[derive(Debug, Default)]
pub struct Scratch {
    /// The column sums of the current row's window, with K copies of the first and of the
    /// last on either side (the edge replication in x), updated in place row by row.
    ext: Vec<u16>,
}

/// Writes the high-pass of `src` into `dst` (resized to match):
///
/// `hp(x, y) = clamp(128 + I(x, y) − floor((S(x, y) + (n − 1) / 2) / n), 0, 255)`
///
/// where `S` is the sum of `I` over the (2k+1)² window centred on (x, y), with coordinates
/// outside the frame clamped to the nearest edge pixel (edge replication), and n = (2k+1)².
/// `k = 0` copies `src` unchanged (raw intensities).
pub fn highpass(src: &LumaImage, k: usize, dst: &mut LumaImage, scratch: &mut Scratch) {
    dst.resize(src.width(), src.height());
    match k {
        0 => dst.data_mut().copy_from_slice(src.data()),
        1 => highpass_dispatch::<1>(src, dst, scratch),
        2 => highpass_dispatch::<2>(src, dst, scratch),
        3 => highpass_dispatch::<3>(src, dst, scratch),
        4 => highpass_dispatch::<4>(src, dst, scratch),
        5 => highpass_dispatch::<5>(src, dst, scratch),
        6 => highpass_dispatch::<6>(src, dst, scratch),
        7 => highpass_dispatch::<7>(src, dst, scratch),
        _ => panic!("prefilter radius {k} > {MAX_RADIUS}; FlowParams::validate rejects it"),
    }
}

/// Runs [`highpass_k`] compiled for AVX2 where the CPU has it (twice the vector width of the
/// x86-64 baseline), else for the baseline.
fn highpass_dispatch<const K: usize>(src: &LumaImage, dst: &mut LumaImage, scratch: &mut Scratch) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is present.
        return unsafe { highpass_k_avx2::<K>(src, dst, scratch) };
    }
    highpass_k::<K>(src, dst, scratch)
}

/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn highpass_k_avx2<const K: usize>(src: &LumaImage, dst: &mut LumaImage, scratch: &mut Scratch) {
    highpass_k::<K>(src, dst, scratch)
}

/// Monomorphised per radius so that the division by the constant window area compiles to a
/// vectorised multiply-high.
#[inline(always)]
fn highpass_k<const K: usize>(src: &LumaImage, dst: &mut LumaImage, scratch: &mut Scratch) {
    let (w, h) = (src.width(), src.height());
    if w == 0 || h == 0 {
        return;
    }
    let n = ((2 * K + 1) * (2 * K + 1)) as u16;
    let half = (n - 1) / 2;
    let row = |y: isize| src.row(y.clamp(0, h as isize - 1) as usize);
    let ext = &mut scratch.ext;
    ext.clear();
    ext.resize(w + 2 * K, 0);
    for j in -(K as isize)..=K as isize {
        for (s, &p) in ext[K..K + w].iter_mut().zip(row(j)) {
            *s += u16::from(p);
        }
    }
    for y in 0..h {
        let (first, last) = (ext[K], ext[K + w - 1]);
        ext[..K].fill(first);
        ext[K + w..].fill(last);
        let out = &mut dst.data_mut()[y * w..(y + 1) * w];
        for ((o, &p), win) in out.iter_mut().zip(src.row(y)).zip(ext.windows(2 * K + 1)) {
            let mut s = 0u16;
            for &v in win {
                s += v;
            }
            let mean = (s + half) / n;
            *o = (128 + i16::from(p) - mean as i16).clamp(0, 255) as u8;
        }
        let (add, sub) = (row(y as isize + K as isize + 1), row(y as isize - K as isize));
        for ((s, &a), &r) in ext[K..K + w].iter_mut().zip(add).zip(sub) {
            *s = *s + u16::from(a) - u16::from(r);
        }
    }
}

/// Halves `src` into `dst`: `dst(x, y) = (s(2x,2y) + s(2x+1,2y) + s(2x,2y+1) + s(2x+1,2y+1) + 2) >> 2`,
/// size floor(W/2) × floor(H/2) (an odd last row/column is dropped).
pub fn downsample(src: &LumaImage, dst: &mut LumaImage) {
    let (w, h) = (src.width() / 2, src.height() / 2);
    dst.resize(w, h);
    for y in 0..h {
        let (r0, r1) = (src.row(2 * y), src.row(2 * y + 1));
        let out = &mut dst.data_mut()[y * w..(y + 1) * w];
        for (x, o) in out.iter_mut().enumerate() {
            let s = u16::from(r0[2 * x]) + u16::from(r0[2 * x + 1]) + u16::from(r1[2 * x]) + u16::from(r1[2 * x + 1]);
            *o = ((s + 2) >> 2) as u8;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The formula written directly, for comparison with the sliding-window implementation.
    fn naive(src: &LumaImage, k: usize) -> LumaImage {
        let (w, h) = (src.width() as isize, src.height() as isize);
        let n = ((2 * k + 1) * (2 * k + 1)) as i32;
        LumaImage::from_fn(src.width(), src.height(), |x, y| {
            let mut s = 0i32;
            for dy in -(k as isize)..=k as isize {
                for dx in -(k as isize)..=k as isize {
                    let xx = (x as isize + dx).clamp(0, w - 1) as usize;
                    let yy = (y as isize + dy).clamp(0, h - 1) as usize;
                    s += i32::from(src.get(xx, yy));
                }
            }
            (128 + i32::from(src.get(x, y)) - (s + (n - 1) / 2) / n).clamp(0, 255) as u8
        })
    }

    #[test]
    fn highpass_matches_formula_for_every_radius() {
        let src = LumaImage::from_fn(23, 17, |x, y| ((x * 37 + y * 91 + x * y * 7) % 256) as u8);
        let mut dst = LumaImage::default();
        let mut scratch = Scratch::default();
        for k in 1..=MAX_RADIUS {
            highpass(&src, k, &mut dst, &mut scratch);
            assert_eq!(dst, naive(&src, k), "k = {k}");
        }
        highpass(&src, 0, &mut dst, &mut scratch);
        assert_eq!(dst, src);
    }

    #[test]
    fn highpass_removes_brightness_offset() {
        let src = LumaImage::from_fn(40, 30, |x, y| (60 + (x * 13 + y * 29) % 50) as u8);
        let brighter = LumaImage::from_fn(40, 30, |x, y| src.get(x, y) + 70);
        let (mut a, mut b, mut s) = (LumaImage::default(), LumaImage::default(), Scratch::default());
        highpass(&src, 4, &mut a, &mut s);
        highpass(&brighter, 4, &mut b, &mut s);
        assert_eq!(a, b);
    }

    #[test]
    fn downsample_averages_2x2() {
        let src = LumaImage::from_fn(5, 3, |x, y| (x * 10 + y * 100) as u8);
        let mut dst = LumaImage::default();
        downsample(&src, &mut dst);
        assert_eq!((dst.width(), dst.height()), (2, 1));
        assert_eq!(dst.get(0, 0), 55); // (0 + 10 + 100 + 110 + 2) / 4 = 55.5 -> 55
        assert_eq!(dst.get(1, 0), 75);
    }
}
