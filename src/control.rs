//! The last safety stage before the base: every set-point is clamped to the configured speed and
//! turn-rate limits and rate-limited by the acceleration limits (DESIGN.md, "Safety is a feature
//! with tests"). Anything non-finite becomes an immediate stop.

use crate::config_error::ConfigError;
use hal::BodyVelocity;
use serde::{Deserialize, Serialize};

/// The `[control]` config table: limits every set-point obeys.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ControlLimits {
    /// Maximum forward speed, m/s.
    pub max_speed: f64,
    /// Maximum backward speed, m/s. Only the stall recovery reverses, backing off a few cm the
    /// way the robot came (the camera cannot see behind); 0 forbids that too.
    pub max_reverse_speed: f64,
    /// Maximum turn rate, rad/s (either direction).
    pub max_turn_rate: f64,
    /// Maximum rise of |v|, m/s².
    pub max_linear_accel: f64,
    /// Maximum fall of |v| (braking), m/s²; braking may be harder than speeding up.
    pub max_linear_decel: f64,
    /// Maximum change of omega, rad/s². 1.5 by default: the obstacle memory takes in a frame
    /// pair only while the turn rate changed by at most `mofis.memory.max_turn_change`
    /// (0.05 rad/s) between steps; with 3 rad/s² an avoidance turn that flips side blinded the
    /// memory for seconds (13 % of the frames taken in while passing a person), and
    /// the robot forgot what it was passing. 1.5 rad/s² is 0.05 rad/s per 33 ms frame, but the
    /// base's odometry comes at 50 Hz, so the samples of two successive frames are often 40 ms
    /// apart: at this limit they differ by 0.06 rad/s (+ encoder noise), and such pairs are
    /// still not taken in (in a measured pass, 621 of 1419 moving pairs turning under
    /// 0.3 rad/s, nearly all at 0.0635). Lower limits measure more but turn slower: 1.1 rad/s²
    /// was slower without fewer contacts (docs/missions-history.md).
    pub max_angular_accel: f64,
}

impl Default for ControlLimits {
    fn default() -> Self {
        Self {
            max_speed: 0.5,
            max_reverse_speed: 0.1,
            max_turn_rate: 1.0,
            max_linear_accel: 0.5,
            max_linear_decel: 1.0,
            max_angular_accel: 1.5,
        }
    }
}

impl ControlLimits {
    /// Checks ranges that serde cannot.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let fields = [
            ("max_speed", self.max_speed, false),
            ("max_reverse_speed", self.max_reverse_speed, true),
            ("max_turn_rate", self.max_turn_rate, false),
            ("max_linear_accel", self.max_linear_accel, false),
            ("max_linear_decel", self.max_linear_decel, false),
            ("max_angular_accel", self.max_angular_accel, false),
        ];
        for (field, v, zero_ok) in fields {
            let ok = v.is_finite() && (v > 0.0 || (zero_ok && v == 0.0));
            if !ok {
                let problem =
                    if zero_ok { "must be a finite number ≥ 0" } else { "must be a positive finite number" };
                return Err(ConfigError::Invalid { field: format!("control.{field}"), problem: problem.into() });
            }
        }
        Ok(())
    }
}

/// Clamps and rate-limits set-points; remembers the last one it let through.
#[derive(Clone, Debug, PartialEq)]
pub struct Limiter {
    limits: ControlLimits,
    last: BodyVelocity,
}

impl Limiter {
    pub fn new(limits: ControlLimits) -> Self {
        Self { limits, last: BodyVelocity::ZERO }
    }

    pub fn limits(&self) -> &ControlLimits {
        &self.limits
    }

    /// The last set-point returned.
    pub fn last(&self) -> BodyVelocity {
        self.last
    }

    /// Stop now: zero, without acceleration limits (camera stall, perception failure, exit).
    pub fn stop(&mut self) -> BodyVelocity {
        self.last = BodyVelocity::ZERO;
        self.last
    }

    /// The set-point to send for `want`, `dt` seconds after the previous one: clamped to the
    /// speed and turn-rate limits, then moved from the previous set-point by at most the
    /// acceleration limits × `dt`. A non-finite `want` or a non-finite or negative `dt` gives
    /// an immediate stop.
    pub fn limit(&mut self, want: BodyVelocity, dt: f64) -> BodyVelocity {
        if !(want.v.is_finite() && want.omega.is_finite() && dt.is_finite() && dt >= 0.0) {
            return self.stop();
        }
        let l = &self.limits;
        let v = want.v.clamp(-l.max_reverse_speed, l.max_speed);
        let omega = want.omega.clamp(-l.max_turn_rate, l.max_turn_rate);
        let v = rate_limit_speed(self.last.v, v, l.max_linear_accel * dt, l.max_linear_decel * dt);
        let max_dw = l.max_angular_accel * dt;
        let omega = omega.clamp(self.last.omega - max_dw, self.last.omega + max_dw);
        self.last = BodyVelocity { v, omega };
        self.last
    }
}

/// Moves `from` toward `to` by at most `up` when |v| grows and `down` when it shrinks (a
/// change of sign brakes to zero first).
fn rate_limit_speed(from: f64, to: f64, up: f64, down: f64) -> f64 {
    if from * to < 0.0 {
        // Crossing zero: brake to zero first; the other direction starts next step.
        return from - from.signum() * down.min(from.abs());
    }
    let delta = to - from;
    let growing = to.abs() > from.abs();
    let max = if growing { up } else { down };
    from + delta.clamp(-max, max)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limiter() -> Limiter {
        Limiter::new(ControlLimits::default())
    }

    #[test]
    fn clamps_speed_and_turn_rate() {
        let mut l = limiter();
        // Long dt: acceleration does not bind, only the absolute limits.
        let out = l.limit(BodyVelocity::new(3.0, -5.0), 100.0);
        assert_eq!(out, BodyVelocity::new(0.5, -1.0));
        let out = l.limit(BodyVelocity::new(-1.0, 5.0), 100.0);
        assert_eq!(out, BodyVelocity::new(0.0, 1.0), "no reversing by default");
    }

    #[test]
    fn limits_acceleration_and_braking() {
        let mut l = limiter();
        let dt = 0.1;
        let out = l.limit(BodyVelocity::new(0.5, 1.0), dt);
        assert!((out.v - 0.05).abs() < 1e-12 && (out.omega - 0.15).abs() < 1e-12, "{out:?}");
        let mut v = out;
        for _ in 0..20 {
            v = l.limit(BodyVelocity::new(0.5, 1.0), dt);
        }
        assert_eq!(v, BodyVelocity::new(0.5, 1.0));
        let out = l.limit(BodyVelocity::new(0.0, 0.0), dt);
        assert!((out.v - 0.4).abs() < 1e-12, "braking at 1 m/s²: {out:?}");
        assert!((out.omega - 0.85).abs() < 1e-12, "{out:?}");
    }

    #[test]
    fn reverse_brakes_through_zero() {
        let mut l = Limiter::new(ControlLimits { max_reverse_speed: 0.2, ..ControlLimits::default() });
        l.limit(BodyVelocity::new(0.5, 0.0), 100.0);
        let mut prev = 0.5;
        for _ in 0..40 {
            let v = l.limit(BodyVelocity::new(-0.2, 0.0), 0.1).v;
            // Braking at ≤ 1 m/s² while moving forward, speeding up backward at ≤ 0.5 m/s².
            let max_step = if prev > 0.0 { 0.1 } else { 0.05 };
            assert!(v <= prev && prev - v <= max_step + 1e-12, "{prev} -> {v}");
            prev = v;
        }
        assert_eq!(prev, -0.2);
    }

    #[test]
    fn nan_and_bad_dt_stop_at_once() {
        for (want, dt) in [
            (BodyVelocity::new(f64::NAN, 0.0), 0.1),
            (BodyVelocity::new(0.2, f64::INFINITY), 0.1),
            (BodyVelocity::new(0.2, 0.1), f64::NAN),
            (BodyVelocity::new(0.2, 0.1), -0.1),
        ] {
            let mut l = limiter();
            l.limit(BodyVelocity::new(0.5, 0.5), 100.0);
            assert_eq!(l.limit(want, dt), BodyVelocity::ZERO, "{want:?} dt {dt}");
            assert_eq!(l.last(), BodyVelocity::ZERO);
        }
    }

    #[test]
    fn validation_names_the_field() {
        let bad = ControlLimits { max_turn_rate: f64::NAN, ..ControlLimits::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("control.max_turn_rate"));
        let bad = ControlLimits { max_speed: 0.0, ..ControlLimits::default() };
        assert!(bad.validate().unwrap_err().to_string().contains("control.max_speed"));
        ControlLimits::default().validate().unwrap();
    }
}
