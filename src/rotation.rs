//! Block matching through a turn: the search is centred on where the robot's rotation moved
//! the view.
//!
//! The block matcher searches each block within `flow.radius` pixels of where it was. A turn
//! moves the whole view sideways by about `f · ω · dt` pixels: at 720p (f ≈ 1270 px) a pair
//! spanning 0.2 s at 0.12 rad/s shifts it by 30 px, twice the default radius, so nearly every
//! block's best match lies on the edge of its window or is a wrong one, and OFFIS, which
//! de-rotates the flow exactly, gets nothing to de-rotate. Widening the radius would cost every
//! straight pair the same; a pyramid blurs the texture the depth needs.
//!
//! Instead frame B is handed to the matcher shifted by the whole pixels that the rotation
//! predicted from the odometry moves the centre of the view ([`predicted_shift`]), so the
//! search window of every block sits around its rotated position and the radius covers the
//! translational flow and the rest of the rotation (up to a quarter more at the frame's sides,
//! and whatever the odometry got wrong). The shift is then added back to every vector
//! ([`unshift`]), so what leaves here is the flow from A to the real frame B, exactly as the
//! matcher would have measured it with a window wide enough: OFFIS, the obstacle memory and
//! the logs see no difference, and a straight pair (no shift) is untouched, bit for bit.
//! Both engines get the same shifted frame, so CPU/GPU parity is kept.
//!
//! The shifted frame repeats B's border pixels where it has no data; a match that falls on them
//! (the matched block not wholly inside the real frame B) is marked
//! [`Validity::OutOfFrame`], as the matcher marks a window cut by the frame border.

use crate::flow::{FlowEngine, FlowError, FlowField, Validity};
use crate::offis::geometry::{FrameMotion, PinholeCamera};
use hal::{BodyVelocity, Calibration, LumaImage};

/// The flow of frame pairs with the search centred on the turn; holds the shifted frame's
/// buffer between pairs.
#[derive(Debug, Default)]
pub struct TurnCompensation {
    shifted: LumaImage,
}

impl TurnCompensation {
    /// The flow from `a` to `b`, over a pair of `dt` s during which the robot moved at `span`
    /// (the pair's mean velocity), searched around the rotation's shift.
    pub fn flow(
        &mut self,
        engine: &mut dyn FlowEngine,
        a: &LumaImage,
        b: &LumaImage,
        calib: &Calibration,
        span: BodyVelocity,
        dt: f64,
    ) -> Result<FlowField, FlowError> {
        let cam = PinholeCamera::new(calib, b.width(), b.height());
        let shift = predicted_shift(&cam, &FrameMotion::from_odometry(&cam, span, dt));
        if shift == [0, 0] {
            return Ok(engine.compute(a, b)?.clone());
        }
        shift_frame(b, shift, &mut self.shifted);
        let mut flow = engine.compute(a, &self.shifted)?.clone();
        unshift(&mut flow, shift, engine.params().block);
        Ok(flow)
    }
}

/// The whole-pixel shift `[dx, dy]` by which the camera's rotation over the pair moves a
/// distant point seen at the centre of frame A (its principal point) in frame B: the
/// translational flow vanishes there for a straight drive, so this is the turn alone.
pub fn predicted_shift(cam: &PinholeCamera, motion: &FrameMotion) -> [i32; 2] {
    motion
        .rotated(cam, cam.cx, cam.cy)
        .map_or([0, 0], |[x, y]| [(x - cam.cx).round() as i32, (y - cam.cy).round() as i32])
}

/// Writes `b` moved by `-shift` into `out`: `out(x, y) = b(x + dx, y + dy)`, with B's nearest
/// border pixel where that lies outside B. The block matcher then finds in `out` a displacement
/// `shift` smaller than in `b`.
pub fn shift_frame(b: &LumaImage, [dx, dy]: [i32; 2], out: &mut LumaImage) {
    let (w, h) = (b.width(), b.height());
    out.resize(w, h);
    let src = b.data();
    // the columns that come from inside B, the same on every row; the rest repeat its border
    let lo = (-(dx as i64)).clamp(0, w as i64) as usize;
    let hi = (w as i64 - dx as i64).clamp(lo as i64, w as i64) as usize;
    for (y, row) in out.data_mut().chunks_exact_mut(w).enumerate() {
        let sy = (y as i64 + dy as i64).clamp(0, h as i64 - 1) as usize;
        let src_row = &src[sy * w..(sy + 1) * w];
        if lo < hi {
            let from = (lo as i64 + dx as i64) as usize;
            row[lo..hi].copy_from_slice(&src_row[from..from + (hi - lo)]);
        }
        let (first, last) = (src_row[0], src_row[w - 1]);
        row[..lo].fill(first);
        row[hi..].fill(last);
    }
}

/// Turns the flow measured against the shifted frame into the flow against frame B: adds
/// `shift` to every vector, and marks [`Validity::OutOfFrame`] the matches whose block
/// (`block` pixels square, centred on the vector's end) is not wholly inside frame B.
pub fn unshift(flow: &mut FlowField, [dx, dy]: [i32; 2], block: usize) {
    let (w, h) = (flow.width as f32, flow.height as f32);
    let half = block as f32 / 2.0;
    for f in &mut flow.vectors {
        f.u += dx as f32;
        f.v += dy as f32;
        let (x0, y0) = (f.x + f.u - half, f.y + f.v - half);
        let inside = x0 >= 0.5 && y0 >= 0.5 && x0 + block as f32 <= w - 0.5 && y0 + block as f32 <= h - 0.5;
        if !inside && f.validity != Validity::Textureless {
            f.validity = Validity::OutOfFrame;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flow::{Backend, FlowParams, create_engine};
    use hal::{BodyVelocity, Calibration};

    fn textured(w: usize, h: usize, offset: i64) -> LumaImage {
        let data = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as i64 + offset, (i / w) as i64);
                let hash = ((x / 3) as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                    ^ ((y / 3) as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
                (hash >> 56) as u8
            })
            .collect();
        LumaImage::from_vec(w, h, data).unwrap()
    }

    #[test]
    fn the_shift_moves_the_frame_and_repeats_its_border() {
        let b = LumaImage::from_vec(4, 2, vec![1, 2, 3, 4, 5, 6, 7, 8]).unwrap();
        let mut out = LumaImage::default();
        shift_frame(&b, [1, 0], &mut out);
        assert_eq!(out.data(), &[2, 3, 4, 4, 6, 7, 8, 8]);
        shift_frame(&b, [-2, 1], &mut out);
        assert_eq!(out.data(), &[5, 5, 5, 6, 5, 5, 5, 6]);
        shift_frame(&b, [0, 0], &mut out);
        assert_eq!(out.data(), b.data());
        shift_frame(&b, [9, 0], &mut out);
        assert_eq!(out.data(), &[4, 4, 4, 4, 8, 8, 8, 8]);
    }

    #[test]
    fn a_turn_predicts_the_shift_of_the_view_centre() {
        let calib = Calibration::nominal_c310();
        let cam = PinholeCamera::new(&calib, 1280, 720);
        // 0.12 rad/s over 0.2 s turns the view left: the scene moves right by f·tan(0.024)
        let motion = FrameMotion::from_odometry(&cam, BodyVelocity::new(0.3, 0.12), 0.2);
        let expected = (cam.fx * 0.024f64.tan()).round() as i32;
        assert_eq!(predicted_shift(&cam, &motion), [expected, 0]);
        assert_eq!(expected, 31);
        let straight = FrameMotion::from_odometry(&cam, BodyVelocity::new(0.3, 0.0), 0.2);
        assert_eq!(predicted_shift(&cam, &straight), [0, 0]);
    }

    #[test]
    fn the_rotational_flow_is_the_closed_form_and_de_rotates_to_nothing() {
        // camera level and on the turning axis: a pure turn ψ to the left moves the ray at
        // horizontal angle α (right of the axis) to α + ψ; x' = cx + f·tan(α + ψ) and
        // y' = cy + (y − cy)·cos α / cos(α + ψ)
        let mut calib = Calibration::nominal_c310();
        calib.mount.x_m = 0.0;
        let cam = PinholeCamera::new(&calib, 1280, 720);
        for psi in [0.004, -0.02, 0.06] {
            let motion = FrameMotion::from_odometry(&cam, BodyVelocity::new(0.0, psi / 0.1), 0.1);
            for (x, y) in [(0.0, 0.0), (639.5, 359.5), (1279.0, 100.0), (300.0, 700.0)] {
                let alpha = ((x - cam.cx) / cam.fx).atan();
                let want =
                    [cam.cx + cam.fx * (alpha + psi).tan(), cam.cy + (y - cam.cy) * alpha.cos() / (alpha + psi).cos()];
                let got = motion.rotated(&cam, x, y).unwrap();
                assert!(
                    (got[0] - want[0]).abs() < 1e-9 && (got[1] - want[1]).abs() < 1e-9,
                    "ψ {psi} at ({x}, {y}): {got:?} vs {want:?}"
                );
                let [u, v] = motion.derotate(&cam, x, y, got[0] - x, got[1] - y).unwrap();
                assert!(u.abs() < 1e-9 && v.abs() < 1e-9, "de-rotated ({u}, {v})");
            }
        }
    }

    #[test]
    fn a_view_moved_past_the_search_radius_is_found_around_the_shift() {
        // frame B is frame A moved 29 px right: beyond the radius of 16, found with the shift
        let (w, h) = (320, 180);
        let (a, b) = (textured(w, h, 0), textured(w, h, -29));
        let mut params = FlowParams { backend: Backend::Cpu, ..FlowParams::default() };
        params.radius = 16;
        let (mut engine, _) = create_engine(&params).unwrap();
        let plain = engine.compute(&a, &b).unwrap().clone();
        let right = |f: &FlowField| {
            f.vectors.iter().filter(|v| v.valid() && (v.u - 29.0).abs() < 0.3 && v.v.abs() < 0.3).count()
        };
        assert_eq!(right(&plain), 0, "without the shift no block can be found");
        let mut shifted = LumaImage::default();
        shift_frame(&b, [28, 0], &mut shifted);
        let mut flow = engine.compute(&a, &shifted).unwrap().clone();
        unshift(&mut flow, [28, 0], params.block);
        let valid = flow.valid_count();
        assert!(
            right(&flow) == valid && valid * 10 >= flow.vectors.len() * 7,
            "{} of {valid} valid of {}",
            right(&flow),
            flow.vectors.len()
        );
        // the rightmost blocks would match beyond B's edge: they are out of frame, not wrong
        for f in flow.vectors.iter().filter(|f| f.x + 29.0 + 16.0 > w as f32) {
            assert_eq!(f.validity, Validity::OutOfFrame, "{f:?}");
        }
    }
}
