//! Body velocities and odometry, in SI units and REP-103 axes (x forward, y left, z up).

use serde::{Deserialize, Serialize};

/// A planar body velocity: `v` forward in m/s, `omega` counter-clockwise (left) in rad/s.
/// Used both as a set-point for the base and as a measured velocity.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BodyVelocity {
    pub v: f64,
    pub omega: f64,
}

impl BodyVelocity {
    pub const ZERO: Self = Self { v: 0.0, omega: 0.0 };

    pub fn new(v: f64, omega: f64) -> Self {
        Self { v, omega }
    }
}

/// What the base measured at time `t_ns` (host monotonic clock, nanoseconds).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    pub t_ns: u64,
    pub velocity: BodyVelocity,
    /// Cumulative encoder counts (wrap handled by the driver).
    pub left_ticks: i64,
    pub right_ticks: i64,
}

/// Wraps an angle to (−π, π]: headings and bearings compare across the ±π seam.
pub fn wrap_angle(a: f64) -> f64 {
    let w = a.rem_euclid(std::f64::consts::TAU);
    if w > std::f64::consts::PI { w - std::f64::consts::TAU } else { w }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::{FRAC_PI_2, PI};

    #[test]
    fn wrap_angle_range() {
        assert!((wrap_angle(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(-FRAC_PI_2 * 3.0) - FRAC_PI_2).abs() < 1e-12);
        assert!((wrap_angle(-PI) - PI).abs() < 1e-12);
        assert!(wrap_angle(-0.5) < 0.0);
    }
}
