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
