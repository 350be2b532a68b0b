//! Turning on the spot to a goal far off the heading.

use super::MofisParams;
use crate::pafsis::{Goal, GoalStatus};

/// PAFSIS's goal turned on the spot when it lies far off the heading: from
/// `blind_turn_stop_rad` off (where MOFIS's look factor stops the robot anyway) until it is
/// within `blind_turn_start_rad`, the goal's velocity is 0, so the robot turns toward it with
/// the goal's turn alone (MOFIS gives a turn on the spot no avoidance turn, which a round robot
/// does not need). Decided from PAFSIS's own goal, before the steering around the obstacle
/// memory: a free heading far off the goal is steered with avoidance as before (doing the same
/// for it drove the robot into the jambs of D9). Without this, a robot that avoidance had
/// turned 1.2 rad away from its goal stood still in a cycle: a cell entered the avoidance band
/// whenever it turned toward the goal, and the avoidance turned it back. With MOFIS's planner
/// the goal it is given is the way's heading instead, which keeps the footprint clear of the
/// jambs (`Mofis::step`).
#[derive(Clone, Copy, Debug)]
pub struct SpotTurn {
    start_rad: f64,
    stop_rad: f64,
    turning: bool,
    /// How long the turns on the spot have gone on without a break, s ...
    turning_s: f64,
    /// ... and how long a full circle takes at the base's top turn rate, s.
    full_circle_s: f64,
}

impl SpotTurn {
    /// For a base that turns at most `max_turn_rate` rad/s.
    pub fn new(params: &MofisParams, max_turn_rate: f64) -> Self {
        Self {
            start_rad: params.blind_turn_start_rad,
            stop_rad: params.blind_turn_stop_rad,
            turning: false,
            turning_s: 0.0,
            full_circle_s: std::f64::consts::TAU / max_turn_rate,
        }
    }

    /// Whether the last goal was turned to on the spot.
    pub fn turning(&self) -> bool {
        self.turning
    }

    /// Whether the turn on the spot has gone on longer than a full circle takes: it is not
    /// turning to anything any more.
    pub fn overlong(&self) -> bool {
        self.turning_s > self.full_circle_s
    }

    pub fn reset(&mut self) {
        self.turning = false;
        self.turning_s = 0.0;
    }

    /// `goal`, or `goal` with velocity 0 while the turn on the spot lasts. Goals that do not
    /// drive forward (turns, reversing, arrived) pass unchanged and end the turn. A turn starts
    /// only when the way toward the goal is free (`goal_way_free`, asked only then): turning on
    /// the spot toward an obstacle only undoes the avoidance turn that led away from it, and the
    /// two made a stationary limit cycle in front of it; a turn under way goes on. `dt`: the
    /// time since the last call, s.
    pub fn apply(&mut self, goal: Goal, dt: f64, goal_way_free: impl FnOnce() -> bool) -> Goal {
        let off = goal.angle_rad.abs();
        self.turning = goal.status == GoalStatus::Active
            && goal.velocity > 0.0
            && match self.turning {
                true => off > self.start_rad,
                false => off >= self.stop_rad && goal_way_free(),
            };
        self.turning_s = match self.turning {
            true => self.turning_s + dt,
            false => 0.0,
        };
        match self.turning {
            true => Goal { velocity: 0.0, ..goal },
            false => goal,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_turn_on_the_spot_longer_than_a_full_circle_is_overlong() {
        // at 1 rad/s a full circle takes 2π s: 30 frames a second for 6.2 s is not overlong, 6.4 s is
        let mut s = SpotTurn::new(&MofisParams::default(), 1.0);
        let far = Goal { velocity: 0.3, angle_rad: 1.5, status: GoalStatus::Active };
        let dt = 1.0 / 30.0;
        for _ in 0..186 {
            assert_eq!(s.apply(far, dt, || true).velocity, 0.0);
        }
        assert!(s.turning() && !s.overlong());
        for _ in 0..6 {
            s.apply(far, dt, || true);
        }
        assert!(s.overlong());
        // a goal near the heading ends the turn, and the time with it
        let near = Goal { angle_rad: 0.1, ..far };
        assert_eq!(s.apply(near, dt, || true).velocity, 0.3);
        assert!(!s.turning() && !s.overlong());
        // a goal far off whose way is not free starts no turn
        assert_eq!(s.apply(far, dt, || false).velocity, 0.3);
    }
}
