//! Lens distortion: OpenCV's "plumb_bob" model (`[k1, k2, p1, p2, k3]`, radial-tangential) and
//! the [`Undistorter`] that turns a distorted camera frame into the pinhole frame every later
//! stage assumes (OFFIS depth, bearings, [`Calibration::ray`], [`Calibration::bearing_of_column`]).
//!
//! Coordinates are *normalized*: `x = (u - cx) / fx`, `y = (v - cy) / fy`. The model maps an
//! ideal (pinhole) point to where the lens puts it, with `r² = x² + y²`:
//!
//! ```text
//! x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)
//! y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y
//! ```
//!
//! The undistorted frame keeps the calibration's size and K (fx, fy, cx, cy): pixel (u, v) of
//! it shows what an ideal pinhole camera with that K would, so the calibration needs no change
//! downstream. With barrel distortion (k1 < 0) its corners come from inside the distorted frame
//! and the distorted frame's outermost field is cropped; with pincushion distortion some of its
//! pixels lie outside the distorted frame and repeat the nearest edge pixel.

use crate::calib::Calibration;
use crate::image::LumaImage;
pub use crate::lens::{distort_normalized, is_identity, undistort_normalized};

#[derive(Debug, thiserror::Error)]
pub enum UndistortError {
    #[error(
        "camera.distortion {coefficients:?} {problem}: it is not a lens model for this {width}x{height} image; recalibrate the camera (calib/c310.toml's comments), or set distortion = [0.0, 0.0, 0.0, 0.0, 0.0] for an ideal pinhole"
    )]
    Model { coefficients: [f64; 5], width: u32, height: u32, problem: String },
    #[error("an image of {width}x{height} pixels is too small to undistort (at least 2x2)")]
    TooSmall { width: u32, height: u32 },
    #[error("frame is {got_width}x{got_height} but the undistorter was built for {width}x{height}")]
    Size { width: usize, height: usize, got_width: usize, got_height: usize },
}

/// One output pixel's bilinear source: the top-left input pixel and the weights of the right
/// and lower neighbours, in 1/256.
#[derive(Clone, Copy, Debug)]
struct Tap {
    index: u32,
    wx: u16,
    wy: u16,
}

/// Undoes the lens distortion of frames of one size: a remap table built once from the
/// calibration, applied per frame with fixed-point bilinear interpolation (8-bit fractional
/// weights: a source position is kept to 1/256 px).
///
/// Output pixel (u, v) is the pinhole image with the calibration's own K and size; its value is
/// the distorted frame at `K · distort(K⁻¹ (u, v))`. A source position outside the distorted
/// frame is clamped to its edge, so such pixels repeat the nearest edge pixel (pincushion
/// distortion, k1 > 0, near the corners; with barrel distortion the sources lie inside).
#[derive(Clone, Debug)]
pub struct Undistorter {
    width: usize,
    height: usize,
    taps: Vec<Tap>,
}

impl Undistorter {
    /// The undistorter for frames of `calib`'s size (scale the calibration to the frame size
    /// first, [`Calibration::scaled_to`]). `Ok(None)` for a pinhole (all coefficients zero):
    /// nothing to do, frames stay bit-identical. `Err` when the coefficients are not a lens model
    /// over the image ([`crate::calib::Intrinsics::check_lens`]) or the image is smaller than 2×2.
    pub fn new(calib: &Calibration) -> Result<Option<Self>, UndistortError> {
        let c = &calib.camera;
        if is_identity(&c.distortion) {
            return Ok(None);
        }
        if c.width < 2 || c.height < 2 {
            return Err(UndistortError::TooSmall { width: c.width, height: c.height });
        }
        c.check_lens().map_err(|problem| UndistortError::Model {
            coefficients: c.distortion,
            width: c.width,
            height: c.height,
            problem,
        })?;
        let (width, height) = (c.width as usize, c.height as usize);
        let mut taps = Vec::with_capacity(width * height);
        for v in 0..height {
            for u in 0..width {
                let p = [(u as f64 - c.cx) / c.fx, (v as f64 - c.cy) / c.fy];
                let [xd, yd] = distort_normalized(&c.distortion, p);
                let (x0, wx) = split(c.fx * xd + c.cx, width);
                let (y0, wy) = split(c.fy * yd + c.cy, height);
                taps.push(Tap { index: (y0 * width + x0) as u32, wx, wy });
            }
        }
        Ok(Some(Self { width, height, taps }))
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// Writes the undistorted `src` into `dst` (resized to the undistorter's size, reusing its
    /// allocation). `Err` when `src` is not the size the undistorter was built for.
    pub fn apply(&self, src: &LumaImage, dst: &mut LumaImage) -> Result<(), UndistortError> {
        if (src.width(), src.height()) != (self.width, self.height) {
            return Err(UndistortError::Size {
                width: self.width,
                height: self.height,
                got_width: src.width(),
                got_height: src.height(),
            });
        }
        dst.resize(self.width, self.height);
        let (s, w) = (src.data(), self.width);
        for (d, t) in dst.data_mut().iter_mut().zip(&self.taps) {
            let i = t.index as usize;
            let (wx, wy) = (u32::from(t.wx), u32::from(t.wy));
            let top = u32::from(s[i]) * (256 - wx) + u32::from(s[i + 1]) * wx;
            let bottom = u32::from(s[i + w]) * (256 - wx) + u32::from(s[i + w + 1]) * wx;
            *d = ((top * (256 - wy) + bottom * wy + (1 << 15)) >> 16) as u8;
        }
        Ok(())
    }

    /// The undistorted `src` as a new image.
    pub fn undistort(&self, src: &LumaImage) -> Result<LumaImage, UndistortError> {
        let mut dst = LumaImage::default();
        self.apply(src, &mut dst)?;
        Ok(dst)
    }
}

/// A source coordinate clamped to `[0, n - 1]` as the lower pixel of its bilinear pair (at most
/// `n - 2`) and the upper pixel's weight in 1/256 (0..=256).
fn split(x: f64, n: usize) -> (usize, u16) {
    let x = if x.is_finite() { x.clamp(0.0, (n - 1) as f64) } else { 0.0 };
    let lower = (x.floor() as usize).min(n - 2);
    (lower, ((x - lower as f64) * 256.0).round() as u16)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lens::model;

    /// A 90° lens (OpenCV fits of such webcams look like this).
    const WIDE: [f64; 5] = [-0.3, 0.1, 0.001, -0.0005, 0.0];
    /// A mild webcam lens like the C310's.
    const MILD: [f64; 5] = [-0.05, 0.01, 0.0005, 0.0003, -0.002];

    fn wide_calib(width: u32, height: u32, distortion: [f64; 5]) -> Calibration {
        let mut c = Calibration::nominal_c310();
        c.camera.fx = 640.0;
        c.camera.fy = 640.0;
        c.camera.distortion = distortion;
        c.scaled_to(width, height)
    }

    /// Normalized coordinates of a grid over the 90° 1280×720 image, corners included.
    fn grid() -> impl Iterator<Item = [f64; 2]> {
        (0..=36)
            .flat_map(|j| (0..=64).map(move |i| [(i as f64 * 20.0 - 639.5) / 640.0, (j as f64 * 20.0 - 359.5) / 640.0]))
    }

    #[test]
    fn forward_model_by_hand() {
        // r² = 0.3² + 0.4² = 0.25; radial = 1 - 0.3·0.25 + 0.1·0.0625 + 0.02·0.015625 = 0.9315625
        let k = [-0.3, 0.1, 0.001, -0.0005, 0.02];
        let [x, y] = distort_normalized(&k, [0.3, 0.4]);
        // x: 0.3·radial + 2·0.001·0.12 + (-0.0005)(0.25 + 0.18); y: 0.4·radial + 0.001(0.25 + 0.32) + 2(-0.0005)(0.12)
        let (ex, ey) = (0.27946875 + 0.00024 - 0.000215, 0.372625 + 0.00057 - 0.00012);
        assert!((x - ex).abs() < 1e-14 && (y - ey).abs() < 1e-14, "({x}, {y}) vs ({ex}, {ey})");
        assert_eq!(distort_normalized(&[0.0; 5], [0.3, 0.4]), [0.3, 0.4]);
    }

    #[test]
    fn round_trips_over_the_image() {
        for k in [WIDE, MILD] {
            let mut worst = 0f64;
            for p in grid() {
                // ideal → distorted → ideal, and distorted → ideal → distorted
                let q = undistort_normalized(&k, distort_normalized(&k, p)).unwrap();
                let d = distort_normalized(&k, undistort_normalized(&k, p).unwrap());
                worst = worst.max((q[0] - p[0]).hypot(q[1] - p[1])).max((d[0] - p[0]).hypot(d[1] - p[1]));
            }
            assert!(worst < 1e-9, "{k:?}: {worst:e}");
        }
    }

    #[test]
    fn the_jacobian_is_the_models_derivative() {
        let k = [-0.3, 0.1, 0.001, -0.0005, 0.02];
        let (p, h) = ([0.7, -0.4], 1e-6);
        let (_, j, _) = model(&k, p);
        for axis in 0..2 {
            let (mut a, mut b) = (p, p);
            a[axis] += h;
            b[axis] -= h;
            let (fa, fb) = (distort_normalized(&k, a), distort_normalized(&k, b));
            for row in 0..2 {
                let numeric = (fa[row] - fb[row]) / (2.0 * h);
                assert!((numeric - j[row][axis]).abs() < 1e-8, "∂{row}/∂{axis}: {numeric} vs {}", j[row][axis]);
            }
        }
    }

    #[test]
    fn absurd_coefficients_are_refused_with_the_field_and_the_fix() {
        // k1 = -2: the radius peaks at r = 0.41 and the 90° image's corners have no ideal point
        let err = Undistorter::new(&wide_calib(320, 180, [-2.0, 0.0, 0.0, 0.0, 0.0])).unwrap_err();
        let text = err.to_string();
        assert!(text.contains("camera.distortion") && text.contains("recalibrate"), "{text}");
        assert!(undistort_normalized(&[-2.0, 0.0, 0.0, 0.0, 0.0], [0.9, 0.5]).is_none());
        assert!(Undistorter::new(&wide_calib(320, 180, [f64::NAN, 0.0, 0.0, 0.0, 0.0])).is_err());
        assert!(Undistorter::new(&wide_calib(320, 180, WIDE)).unwrap().is_some());
    }

    #[test]
    fn a_pinhole_needs_no_undistorter() {
        assert!(Undistorter::new(&Calibration::nominal_c310()).unwrap().is_none());
    }

    #[test]
    fn a_wrong_size_is_an_error() {
        let u = Undistorter::new(&wide_calib(64, 36, WIDE)).unwrap().unwrap();
        let mut out = LumaImage::default();
        assert!(matches!(u.apply(&LumaImage::new(32, 18), &mut out), Err(UndistortError::Size { .. })));
        u.apply(&LumaImage::new(64, 36), &mut out).unwrap();
        assert_eq!((out.width(), out.height()), (64, 36));
    }

    /// A smooth pattern over normalized coordinates, grey levels: periods of 33 to 40 px at
    /// 320×180 and a 90° lens, short enough for interpolation error to show.
    fn pattern(p: [f64; 2]) -> f64 {
        127.5 + 60.0 * (25.0 * p[0]).sin() * (30.0 * p[1]).cos() + 40.0 * (5.0 * p[0] + 7.0 * p[1]).sin()
    }

    /// The pattern as the lens sees it and as a pinhole sees it, and the mean absolute grey
    /// difference of the undistorted view from the pinhole one and of the raw view from it.
    fn remap_errors(k: [f64; 5]) -> (f64, f64) {
        let calib = wide_calib(320, 180, k);
        let c = calib.camera;
        let normalized = |u: usize, v: usize| [(u as f64 - c.cx) / c.fx, (v as f64 - c.cy) / c.fy];
        let grey = |g: f64| (g + 0.5).clamp(0.0, 255.0) as u8;
        // pixel (u, v) of the distorted image sees the ideal point undistort(K⁻¹ (u, v))
        let distorted =
            LumaImage::from_fn(320, 180, |u, v| grey(pattern(undistort_normalized(&k, normalized(u, v)).unwrap())));
        let pinhole = LumaImage::from_fn(320, 180, |u, v| grey(pattern(normalized(u, v))));
        let undistorted = Undistorter::new(&calib).unwrap().unwrap().undistort(&distorted).unwrap();
        let mae = |a: &LumaImage, b: &LumaImage| {
            a.data().iter().zip(b.data()).map(|(x, y)| (*x as f64 - *y as f64).abs()).sum::<f64>()
                / a.data().len() as f64
        };
        (mae(&undistorted, &pinhole), mae(&distorted, &pinhole))
    }

    #[test]
    fn remap_restores_the_pinhole_image() {
        // measured: 0.25 grey levels after undistortion against 31.1 without (wide), 0.20 against
        // 11.1 (mild); most of what is left is the two images' rounding to whole grey levels
        let (after, before) = remap_errors(WIDE);
        assert!(after < 0.5 && before > 20.0, "wide: {after} after, {before} before");
        let (after, before) = remap_errors(MILD);
        assert!(after < 0.5 && before > 5.0, "mild: {after} after, {before} before");
    }

    #[test]
    fn sources_outside_the_frame_take_the_edge() {
        // pincushion: the corners of the pinhole view lie outside the distorted frame
        let calib = wide_calib(64, 36, [0.2, 0.0, 0.0, 0.0, 0.0]);
        let src = LumaImage::from_fn(64, 36, |u, v| (u + 3 * v) as u8);
        let out = Undistorter::new(&calib).unwrap().unwrap().undistort(&src).unwrap();
        assert_eq!(out.get(0, 0), src.get(0, 0));
        assert_eq!(out.get(63, 35), src.get(63, 35));
    }

    #[test]
    #[ignore = "timing, run by hand: cargo test --release -p flownav-hal -- --ignored remap_time --nocapture"]
    fn remap_time() {
        for (w, h) in [(1280u32, 720u32), (640, 360), (320, 180)] {
            let u = Undistorter::new(&wide_calib(w, h, WIDE)).unwrap().unwrap();
            let src = LumaImage::from_fn(w as usize, h as usize, |x, y| (x ^ y) as u8);
            let mut dst = LumaImage::default();
            u.apply(&src, &mut dst).unwrap();
            let n = 200;
            let t = std::time::Instant::now();
            for _ in 0..n {
                u.apply(std::hint::black_box(&src), &mut dst).unwrap();
            }
            let remap_ms = t.elapsed().as_secs_f64() * 1e3 / n as f64;
            let t = std::time::Instant::now();
            std::hint::black_box(Undistorter::new(&wide_calib(w, h, WIDE)).unwrap());
            let build_ms = t.elapsed().as_secs_f64() * 1e3;
            println!("{w}x{h}: remap {remap_ms:.3} ms per frame, table built in {build_ms:.1} ms");
        }
    }
}
