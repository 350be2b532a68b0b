//! The `[odometry]` table and the odometry's systematic turn errors, learned while driving from
//! the yaw the flow measures.
//!
//! A differential-drive base that counts its wheels' ticks with slightly wrong wheel radii and
//! wheel base reports a turn rate that is off in two ways (Borenstein's systematic errors):
//! unequal wheel radii bend a straight drive by a fixed angle per metre, and a wrong wheel base
//! (or slip while turning) scales every turn. So the true turn over an interval is
//! `ψ_true = (1 + a)·ψ + b·s` with `ψ` the odometry's turn and `s` the distance it drove.
//!
//! Each keyframe pair driven forward gives the flow's measurement of `ψ_true − ψ`
//! ([`crate::offis::Offis::measure_yaw`]); `a` and `b` are its least-squares fit over all the
//! pairs so far, pulled toward 0 by a prior worth `PRIOR_PAIRS` pairs. The pipeline
//! applies the fit to every odometry sample before anything uses it ([`crate::step`]): de-rotation,
//! the obstacle memory's motion and dead reckoning all see the corrected turn, and turns on the
//! spot, whose flow cannot be measured as well (the camera swings round the axle), get the
//! learned scale too. What the fit does not explain of a pair's measured yaw moves PAFSIS's
//! heading directly (`heading_gain`).

use crate::config_error::ConfigError;
use hal::BodyVelocity;

/// The `[odometry]` config table.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OdometryParams {
    /// Learn the turn scale and the bend from the flow and correct every odometry sample with
    /// them (false: the odometry as the base reports it).
    pub learn: bool,
    /// PAFSIS's heading takes this fraction of what a pair's measured yaw leaves unexplained
    /// (0: only the learned errors correct it).
    pub heading_gain: f64,
    /// A pair whose measured yaw error exceeds this plus a tenth of its turn is not used, rad
    /// (a changing turn rate gives up to about 1 mrad per pair; a wrong match more).
    pub max_residual_rad: f64,
}

impl Default for OdometryParams {
    fn default() -> Self {
        Self { learn: true, heading_gain: 1.0, max_residual_rad: 0.01 }
    }
}

impl OdometryParams {
    pub fn validate(&self) -> Result<(), ConfigError> {
        if !(0.0..=1.0).contains(&self.heading_gain) {
            return Err(ConfigError::invalid("odometry.heading_gain", "must be in [0, 1]"));
        }
        if !(self.max_residual_rad.is_finite() && self.max_residual_rad >= 0.0) {
            return Err(ConfigError::invalid("odometry.max_residual_rad", "must be a finite angle >= 0 rad"));
        }
        Ok(())
    }

    /// Whether a pair that turned `turn_rad` by the odometry may use a measured yaw error of
    /// `residual_rad`.
    pub fn admits(&self, residual_rad: f64, turn_rad: f64) -> bool {
        residual_rad.is_finite() && residual_rad.abs() <= self.max_residual_rad + 0.1 * turn_rad.abs()
    }
}

/// The fitted `a` (turn scale error) and `b` (bend per metre, rad/m), and the sums they come from.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OdometryCalibration {
    /// Σψ², Σψs, Σs², Σψr, Σsr over the pairs.
    sums: [f64; 5],
    pairs: u64,
    scale: f64,
    bend_rad_m: f64,
}

/// The prior's weight in pairs of typical motion, and what that motion is: the fit moves away
/// from 0 once the pairs' evidence outweighs this many pairs of 0.02 rad and 0.04 m.
const PRIOR_PAIRS: f64 = 50.0;
const TYPICAL_TURN_RAD: f64 = 0.02;
const TYPICAL_DRIVE_M: f64 = 0.04;
/// Fits beyond these are clamped: a base off by more needs calibrating, not learning. The bend
/// covers wheel radii 3 % off in opposite directions on a 0.3 m wheel base (0.2 rad/m): an
/// uncalibrated base's radii are within that, and a bend clamped short of the truth leaves
/// the rest in the de-rotation and the obstacle memory's motion (twice the ghost cells).
pub const MAX_SCALE: f64 = 0.15;
pub const MAX_BEND_RAD_M: f64 = 0.2;

impl OdometryCalibration {
    /// Takes one pair: the odometry turned `turn_rad` and drove `drive_m`, and the flow says it
    /// turned `residual_rad` more than that.
    pub fn observe(&mut self, turn_rad: f64, drive_m: f64, residual_rad: f64) {
        if !(turn_rad.is_finite() && drive_m.is_finite() && residual_rad.is_finite()) {
            return;
        }
        let (p, s, r) = (turn_rad, drive_m, residual_rad);
        for (sum, x) in self.sums.iter_mut().zip([p * p, p * s, s * s, p * r, s * r]) {
            *sum += x;
        }
        self.pairs += 1;
        let [pp, ps, ss, pr, sr] = self.sums;
        let (pp, ss) = (pp + PRIOR_PAIRS * TYPICAL_TURN_RAD.powi(2), ss + PRIOR_PAIRS * TYPICAL_DRIVE_M.powi(2));
        let det = pp * ss - ps * ps;
        if det > 0.0 {
            self.scale = ((ss * pr - ps * sr) / det).clamp(-MAX_SCALE, MAX_SCALE);
            self.bend_rad_m = ((pp * sr - ps * pr) / det).clamp(-MAX_BEND_RAD_M, MAX_BEND_RAD_M);
        }
    }

    /// What the fit adds to an odometry turn of `turn_rad` over `drive_m`, rad.
    pub fn correction(&self, turn_rad: f64, drive_m: f64) -> f64 {
        self.scale * turn_rad + self.bend_rad_m * drive_m
    }

    /// An odometry sample with the fitted errors taken out of its turn rate.
    pub fn apply(&self, odo: BodyVelocity) -> BodyVelocity {
        BodyVelocity::new(odo.v, odo.omega + self.correction(odo.omega, odo.v))
    }

    /// Replaces the fit by `scale` and `bend_rad_m` (replay: the values a logged step used).
    pub fn set_fit(&mut self, scale: f64, bend_rad_m: f64) {
        self.scale = scale;
        self.bend_rad_m = bend_rad_m;
    }

    /// The fitted turn scale error `a` (−0.04: the odometry reports 4 % more turn than the
    /// robot makes).
    pub fn scale(&self) -> f64 {
        self.scale
    }

    /// The fitted bend `b`, rad per metre driven (positive: the robot curves left).
    pub fn bend_rad_m(&self) -> f64 {
        self.bend_rad_m
    }

    /// Pairs taken so far.
    pub fn pairs(&self) -> u64 {
        self.pairs
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fit after 600 pairs of varying turns and drives (24 m) on a base with turn scale
    /// error `a` and bend `b`, each pair's measured yaw error carrying `noise()`.
    fn fitted(a: f64, b: f64, mut noise: impl FnMut() -> f64) -> OdometryCalibration {
        let mut cal = OdometryCalibration::default();
        for k in 0..600 {
            let turn = 0.05 * ((k as f64) * 0.37).sin();
            let drive = 0.04 + 0.01 * ((k as f64) * 0.11).cos();
            cal.observe(turn, drive, a * turn + b * drive + noise());
        }
        cal
    }

    #[test]
    fn the_fit_recovers_a_wheel_base_error_and_a_bend_from_noisy_pairs() {
        // a base that turns 4 % less than it reports and bends 0.013 rad/m (0.2 % radius
        // difference on a 0.3 m wheel base), seen through ±1 mrad of measurement noise
        let (a, b) = (-0.04, 0.013);
        let mut state = 12345u64;
        let cal = fitted(a, b, || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2e-3
        });
        assert!((cal.scale() - a).abs() < 0.01, "scale {} want {a}", cal.scale());
        assert!((cal.bend_rad_m() - b).abs() < 0.002, "bend {} want {b}", cal.bend_rad_m());
        assert_eq!(cal.pairs(), 600);
        assert!((cal.correction(1.0, 0.0) - cal.scale()).abs() < 1e-12);
    }

    #[test]
    fn a_wheel_two_percent_large_and_the_other_two_percent_small_is_learned_not_clamped() {
        // straight ticks on such a base curve it right by 0.04 / 0.33 m = 0.12 rad/m, and a
        // 3 % wheel base error with slip shortens every turn by 5 %: within what is learned
        let (a, b) = (-0.05, -0.04 / 0.33);
        let cal = fitted(a, b, || 0.0);
        // after 24 m the prior still holds the fit a few per cent short of the truth
        assert!((cal.scale() - a).abs() < 0.1 * a.abs(), "scale {} want {a}", cal.scale());
        assert!((cal.bend_rad_m() - b).abs() < 0.1 * b.abs(), "bend {} want {b}", cal.bend_rad_m());
        assert!(cal.bend_rad_m().abs() < b.abs());
    }

    #[test]
    fn without_evidence_nothing_is_corrected_and_fits_are_clamped() {
        let mut cal = OdometryCalibration::default();
        assert_eq!(cal.correction(1.0, 1.0), 0.0);
        cal.observe(0.0, 0.0, 0.5);
        cal.observe(f64::NAN, 0.04, 0.0);
        assert_eq!((cal.scale(), cal.bend_rad_m(), cal.pairs()), (0.0, 0.0, 1));
        for _ in 0..1000 {
            cal.observe(0.05, 0.0, 0.05);
        }
        assert_eq!(cal.scale(), MAX_SCALE);
    }
}
