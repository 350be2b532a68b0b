//! Standstill escape: a robot that stands still while its goal asks it to drive turns to the
//! free heading nearest its goal, over the full circle, and drives that way for a while.
//!
//! The avoidance behaviour, the steering around the obstacle memory and the speed gate all look
//! forward, within the camera's view: between two obstacles they can cancel out, the avoidance
//! turn undoing the steered heading, or the gate holding the robot in front of a surface that
//! the steering keeps pointing it at. Earlier versions of flownav then stood next to the
//! obstacle for seconds, forgot it, and drove into it. [`Escape`] notices the standstill (the
//! set-point's speed below `still_mps` for `after_s` while PAFSIS's goal asks to drive),
//! searches the whole circle in steps of `step_rad` for the heading nearest the goal whose path
//! is free for `lookahead_m` in the obstacle memory (and inside the corridor, when the map gives
//! one), and replaces the goal's heading by it, in the odometry frame, until the robot has
//! driven `drive_m` or `timeout_s` has passed. A heading behind the robot is what it drove
//! through: the memory holds what it saw there, and the turn to it is on the spot
//! ([`crate::mofis::SpotTurn`]), which cannot run a round robot into anything.
//! This is the rotate-and-go recovery of a ROS navigation stack, driven by the memory.

use crate::config_error::ConfigError;
use crate::pafsis::map::wrap_angle;
use crate::pafsis::{Goal, GoalStatus};
use serde::{Deserialize, Serialize};

/// The `[mofis.escape]` config table.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EscapeParams {
    /// Escape on (true) or off.
    pub enabled: bool,
    /// A set-point slower than this counts as standing still, m/s.
    pub still_mps: f64,
    /// ... for this long, s, while the goal asks to drive.
    pub after_s: f64,
    /// A heading is free when its path is free this far, m.
    pub lookahead_m: f64,
    /// Headings are tried in steps of this, rad, round the full circle.
    pub step_rad: f64,
    /// The escape heading holds until the robot has driven this far, m ...
    pub drive_m: f64,
    /// ... or for at most this long, s.
    pub timeout_s: f64,
    /// The goal speed while escaping, at least, m/s (PAFSIS's leg speed comes down to a crawl
    /// near the leg's end).
    pub speed_mps: f64,
}

impl Default for EscapeParams {
    fn default() -> Self {
        Self {
            enabled: true,
            still_mps: 0.02,
            after_s: 1.5,
            lookahead_m: 1.0,
            step_rad: 0.1,
            drive_m: 0.6,
            timeout_s: 10.0,
            speed_mps: 0.15,
        }
    }
}

impl EscapeParams {
    /// Range checks.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let pos = |v: f64| v.is_finite() && v > 0.0;
        let checks = [
            ("still_mps", pos(self.still_mps), "must be a positive speed in m/s"),
            ("after_s", pos(self.after_s), "must be a positive time in s"),
            ("lookahead_m", pos(self.lookahead_m), "must be a positive distance in m"),
            ("step_rad", pos(self.step_rad) && self.step_rad <= 1.0, "must be in (0, 1] rad"),
            ("drive_m", pos(self.drive_m), "must be a positive distance in m"),
            ("timeout_s", pos(self.timeout_s), "must be a positive time in s"),
            ("speed_mps", pos(self.speed_mps), "must be a positive speed in m/s"),
        ];
        match checks.into_iter().find(|c| !c.1) {
            Some((field, _, problem)) => {
                Err(ConfigError::Invalid { field: format!("mofis.escape.{field}"), problem: problem.into() })
            }
            None => Ok(()),
        }
    }
}

/// An escape under way.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Active {
    /// The heading to hold, odometry frame, rad.
    heading: f64,
    /// Distance left to drive, m, and time left, s.
    left_m: f64,
    left_s: f64,
}

/// The standstill detector and its escape heading (module doc).
#[derive(Clone, Debug)]
pub struct Escape {
    params: EscapeParams,
    still_s: f64,
    active: Option<Active>,
    escapes: u32,
}

impl Escape {
    pub fn new(params: EscapeParams) -> Self {
        Self { params, still_s: 0.0, active: None, escapes: 0 }
    }

    pub fn params(&self) -> &EscapeParams {
        &self.params
    }

    /// How many escapes started.
    pub fn escapes(&self) -> u32 {
        self.escapes
    }

    /// Whether an escape is under way.
    pub fn active(&self) -> bool {
        self.active.is_some()
    }

    /// Forgets the standstill and any escape (after a stop or failure).
    pub fn reset(&mut self) {
        self.still_s = 0.0;
        self.active = None;
    }

    /// The goal to follow for PAFSIS's `goal`: unchanged unless an escape is under way, then
    /// toward its heading at `speed_mps` at least. `yaw` is the robot's heading in the odometry
    /// frame (rad), `driven_m` the distance driven since the last call, `dt` its time (s);
    /// `free(h)` how far the path along heading `h` (robot frame, rad) is free, up to
    /// `lookahead_m`. A standstill of `after_s` starts a new escape here.
    pub fn apply(&mut self, goal: Goal, yaw: f64, driven_m: f64, dt: f64, free: impl Fn(f64) -> f64) -> Goal {
        if !self.params.enabled || goal.status != GoalStatus::Active {
            return goal;
        }
        if let Some(a) = &mut self.active {
            a.left_m -= driven_m.abs();
            a.left_s -= dt;
            if a.left_m <= 0.0 || a.left_s <= 0.0 {
                self.active = None;
            }
        }
        if self.still_s >= self.params.after_s {
            self.still_s = 0.0;
            let h = free_heading(goal.angle_rad, self.params.lookahead_m, self.params.step_rad, free);
            let heading = wrap_angle(yaw + h);
            self.active = Some(Active { heading, left_m: self.params.drive_m, left_s: self.params.timeout_s });
            self.escapes += 1;
            tracing::info!(
                "standing still for {:.1} s: escaping toward {:.0}° (goal {:.0}°)",
                self.params.after_s,
                h.to_degrees(),
                goal.angle_rad.to_degrees()
            );
        }
        match self.active {
            Some(a) => Goal {
                angle_rad: wrap_angle(a.heading - yaw),
                velocity: goal.velocity.max(self.params.speed_mps),
                ..goal
            },
            None => goal,
        }
    }

    /// Forgets the standstill (the stall recovery is in charge); an escape under way goes on.
    pub fn reset_standstill(&mut self) {
        self.still_s = 0.0;
    }

    /// Records the step's outcome: the `goal` that was followed and the speed `v` sent (m/s),
    /// over `dt` seconds. Standing still counts only while the goal asks to drive.
    pub fn observe(&mut self, goal: &Goal, v: f64, dt: f64) {
        let still = goal.status == GoalStatus::Active && goal.velocity > 0.0 && v.abs() < self.params.still_mps;
        self.still_s = if still { self.still_s + dt } else { 0.0 };
    }
}

/// The heading (robot frame, rad, in `(−π, π]`) nearest to `goal_rad` whose path is free for
/// `lookahead_m` (`free(h) ≥ lookahead_m`), trying the full circle in steps of `step_rad`;
/// with none free, the one with the longest free path (the first found on a tie).
pub fn free_heading(goal_rad: f64, lookahead_m: f64, step_rad: f64, free: impl Fn(f64) -> f64) -> f64 {
    let n = (std::f64::consts::PI / step_rad).floor() as i32;
    let mut best: Option<(bool, f64, f64, f64)> = None; // (free enough, free distance, off goal, heading)
    for k in -n..=n {
        let h = k as f64 * step_rad;
        let f = free(h);
        let ok = f >= lookahead_m;
        let off = wrap_angle(h - goal_rad).abs();
        let better = match best {
            None => true,
            Some((bok, bf, boff, _)) => match (ok, bok) {
                (true, false) => true,
                (false, true) => false,
                (true, true) => off < boff,
                (false, false) => f > bf + 1e-9,
            },
        };
        if better {
            best = Some((ok, f, off, h));
        }
    }
    best.map_or(goal_rad, |b| b.3)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn goal(angle_rad: f64, velocity: f64) -> Goal {
        Goal { velocity, angle_rad, status: GoalStatus::Active }
    }

    /// Everything free except headings within 0.5 rad of `blocked` (robot frame).
    fn free_except(blocked: f64) -> impl Fn(f64) -> f64 {
        move |h: f64| if wrap_angle(h - blocked).abs() < 0.5 { 0.2 } else { 10.0 }
    }

    #[test]
    fn the_free_heading_nearest_the_goal_wins_round_the_full_circle() {
        // goal dead ahead, blocked ahead: the nearest free headings are ±0.5 rad; the first
        // found (right) wins the tie
        let h = free_heading(0.0, 1.0, 0.1, free_except(0.0));
        assert!((h.abs() - 0.5).abs() < 1e-9, "{h}");
        // goal on the left, blocked ahead: the free heading on the left
        let h = free_heading(0.3, 1.0, 0.1, free_except(0.0));
        assert!((h - 0.5).abs() < 1e-9, "{h}");
        // only the way back is free: it is found, behind the robot
        let h = free_heading(0.0, 1.0, 0.1, |h: f64| if h.abs() > 2.9 { 5.0 } else { 0.1 });
        assert!(h.abs() > 2.9, "{h}");
        // nothing free: the longest free path
        let h = free_heading(0.0, 1.0, 0.1, |h: f64| 0.5 - 0.1 * (h - 1.0).abs());
        assert!((h - 1.0).abs() < 1e-9, "{h}");
    }

    #[test]
    fn a_standstill_turns_the_goal_to_a_free_heading_until_the_robot_has_driven() {
        let p = EscapeParams::default();
        let mut e = Escape::new(p);
        let dt = 1.0 / 30.0;
        let g = goal(0.0, 0.3);
        // standing still, but not yet long enough: the goal passes unchanged
        let steps = (p.after_s / dt).ceil() as usize;
        for _ in 0..steps - 2 {
            assert_eq!(e.apply(g, 0.0, 0.0, dt, free_except(0.0)), g);
            e.observe(&g, 0.0, dt);
        }
        assert_eq!(e.escapes(), 0);
        e.observe(&g, 0.0, dt);
        e.observe(&g, 0.0, dt);
        // now the escape starts: the goal's heading is the free one at 0.5 rad
        let out = e.apply(g, 0.0, 0.0, dt, free_except(0.0));
        assert_eq!(e.escapes(), 1);
        assert!((out.angle_rad.abs() - 0.5).abs() < 1e-9, "{out:?}");
        let side = out.angle_rad.signum();
        // the robot turns toward it on the spot: the heading is held in the odometry frame
        let out = e.apply(g, side * 0.3, 0.0, dt, free_except(0.0));
        assert!((out.angle_rad - side * 0.2).abs() < 1e-9, "{out:?}");
        // PAFSIS asking for no speed (goal behind) still drives the escape
        let out = e.apply(goal(PI, 0.0), side * 0.5, 0.0, dt, free_except(0.0));
        assert_eq!(out.velocity, p.speed_mps);
        // driving it through ends it
        e.observe(&out, 0.2, dt);
        let out = e.apply(g, side * 0.5, p.drive_m, dt, free_except(0.0));
        assert!(!e.active());
        assert_eq!(out, g);
    }

    #[test]
    fn bad_parameters_are_named() {
        assert!(EscapeParams::default().validate().is_ok());
        let bad = EscapeParams { step_rad: 1.5, ..EscapeParams::default() }.validate().unwrap_err();
        assert!(matches!(&bad, ConfigError::Invalid { field, .. } if field == "mofis.escape.step_rad"), "{bad:?}");
        let bad = EscapeParams { speed_mps: f64::NAN, ..EscapeParams::default() }.validate().unwrap_err();
        assert!(matches!(&bad, ConfigError::Invalid { field, .. } if field == "mofis.escape.speed_mps"), "{bad:?}");
    }

    #[test]
    fn driving_or_arriving_is_no_standstill() {
        let p = EscapeParams::default();
        let mut e = Escape::new(p);
        let dt = 0.1;
        for _ in 0..100 {
            // slow but moving
            let g = goal(0.0, 0.3);
            assert_eq!(e.apply(g, 0.0, 0.01, dt, free_except(0.0)), g);
            e.observe(&g, 0.05, dt);
            // PAFSIS's goal asks for no speed (arrived, or a turn on the spot)
            let g = goal(1.0, 0.0);
            assert_eq!(e.apply(g, 0.0, 0.0, dt, free_except(0.0)), g);
            e.observe(&g, 0.0, dt);
        }
        assert_eq!(e.escapes(), 0);
        let arrived = Goal { status: GoalStatus::Arrived, ..goal(0.0, 0.0) };
        for _ in 0..100 {
            e.observe(&arrived, 0.0, dt);
            assert_eq!(e.apply(arrived, 0.0, 0.0, dt, free_except(0.0)), arrived);
        }
        assert_eq!(e.escapes(), 0);
    }
}
