//! OpenCV's "plumb_bob" lens model (`[k1, k2, p1, p2, k3]`, radial-tangential) on normalized
//! coordinates, its inverse, and the check that coefficients are a lens over an image. Pure
//! arithmetic: the calibration checks its coefficients with it, the [`crate::undistort`] remap
//! and the simulator's renderer use the model.

/// Newton iterations of [`undistort_normalized`] before it gives up (it needs 5 or 6 at a
/// 90° lens's corners).
const MAX_ITERATIONS: usize = 20;
/// [`undistort_normalized`] has converged when the model maps its answer this close to the
/// distorted point (normalized units; a 1280-px-wide image spans about 2).
const TOLERANCE: f64 = 1e-13;
/// The validity check ([`check_model`]) samples the interior of the image every this many
/// pixels (and every border pixel).
const CHECK_STRIDE: u32 = 8;

/// All five coefficients zero: the lens is an ideal pinhole and undistortion is the identity.
pub fn is_identity(distortion: &[f64; 5]) -> bool {
    distortion.iter().all(|&k| k == 0.0)
}

/// The plumb_bob forward model: where the lens puts the ideal normalized point `p`.
pub fn distort_normalized(distortion: &[f64; 5], p: [f64; 2]) -> [f64; 2] {
    let [k1, k2, p1, p2, k3] = *distortion;
    let [x, y] = p;
    let r2 = x * x + y * y;
    let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    [x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x), y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y]
}

/// The model at `p` with its derivatives: the distorted point, the Jacobian (row-major
/// `[[∂x_d/∂x, ∂x_d/∂y], [∂y_d/∂x, ∂y_d/∂y]]`) and the radial factor `1 + k1 r² + k2 r⁴ + k3 r⁶`.
pub(crate) fn model(distortion: &[f64; 5], p: [f64; 2]) -> ([f64; 2], [[f64; 2]; 2], f64) {
    let [k1, k2, p1, p2, k3] = *distortion;
    let [x, y] = p;
    let r2 = x * x + y * y;
    let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    // d(radial)/d(r²)
    let slope = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3);
    let cross = 2.0 * x * y * slope + 2.0 * p1 * x + 2.0 * p2 * y;
    let jacobian = [
        [radial + 2.0 * x * x * slope + 2.0 * p1 * y + 6.0 * p2 * x, cross],
        [cross, radial + 2.0 * y * y * slope + 6.0 * p1 * y + 2.0 * p2 * x],
    ];
    (distort_normalized(distortion, p), jacobian, radial)
}

/// Where the lens model is a lens: it neither folds over (Jacobian determinant > 0) nor turns
/// points through the centre (radial factor > 0), and is finite.
pub(crate) fn regular(jacobian: &[[f64; 2]; 2], radial: f64) -> bool {
    let det = jacobian[0][0] * jacobian[1][1] - jacobian[0][1] * jacobian[1][0];
    det.is_finite() && det > 0.0 && radial > 0.0
}

/// The inverse of [`distort_normalized`]: the ideal normalized point the lens put at `pd`.
///
/// Newton's method from `pd`. OpenCV's `undistortPoints` uses a fixed-point iteration; Newton
/// converges quadratically: at the corner of a 90° lens with k1 = −0.3, k2 = 0.1 it takes 5
/// steps to 1e-13, where the fixed point is 4e-7 off after 20 and needs about 40 for 1e-12.
/// `None` when it does not converge within 20 steps, or steps where the model is not a lens
/// (folds over, or turns points through the centre): the coefficients then are not a lens
/// model at `pd`.
pub fn undistort_normalized(distortion: &[f64; 5], pd: [f64; 2]) -> Option<[f64; 2]> {
    let mut p = pd;
    for _ in 0..MAX_ITERATIONS {
        let (d, j, radial) = model(distortion, p);
        if !regular(&j, radial) {
            return None;
        }
        let e = [d[0] - pd[0], d[1] - pd[1]];
        if e[0].hypot(e[1]) <= TOLERANCE {
            return Some(p);
        }
        let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
        p = [p[0] - (j[1][1] * e[0] - j[0][1] * e[1]) / det, p[1] - (j[0][0] * e[1] - j[1][0] * e[0]) / det];
    }
    None
}

/// Checks that the distortion `k` (with K = `[fx, fy, cx, cy]`) is a lens model over a `w × h` image: the forward model is
/// regular (does not fold over, positive radial factor) at the ideal points of the pixels, and
/// every pixel of the distorted image has a regular ideal point ([`undistort_normalized`]
/// converges there). Sampled at every border pixel, where a polynomial fit fails first, and
/// every 8th pixel of every 8th row inside. `Err` says where it fails.
pub fn check_model(k: &[f64; 5], [fx, fy, cx, cy]: [f64; 4], (w, h): (u32, u32)) -> Result<(), String> {
    if is_identity(k) {
        return Ok(());
    }
    let border = (0..w).flat_map(|u| [(u, 0), (u, h.saturating_sub(1))]);
    let border = border.chain((0..h).flat_map(|v| [(0, v), (w.saturating_sub(1), v)]));
    let inside =
        (0..h).step_by(CHECK_STRIDE as usize).flat_map(|v| (0..w).step_by(CHECK_STRIDE as usize).map(move |u| (u, v)));
    for (u, v) in border.chain(inside) {
        let p = [(u as f64 - cx) / fx, (v as f64 - cy) / fy];
        let (_, j, radial) = model(k, p);
        if !regular(&j, radial) {
            return Err(format!("is not one-to-one at the ideal point of pixel ({u}, {v})"));
        }
        if undistort_normalized(k, p).is_none() {
            return Err(format!("cannot be inverted at pixel ({u}, {v}) of the distorted image"));
        }
    }
    Ok(())
}
