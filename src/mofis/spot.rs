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
/// whenever it turned toward the goal, and the avoidance turned it back.
#[derive(Clone, Copy, Debug)]
pub struct SpotTurn {
    start_rad: f64,
    stop_rad: f64,
    turning: bool,
}

impl SpotTurn {
    pub fn new(params: &MofisParams) -> Self {
        Self { start_rad: params.blind_turn_start_rad, stop_rad: params.blind_turn_stop_rad, turning: false }
    }

    /// Whether the last goal was turned to on the spot.
    pub fn turning(&self) -> bool {
        self.turning
    }

    pub fn reset(&mut self) {
        self.turning = false;
    }

    /// `goal`, or `goal` with velocity 0 while the turn on the spot lasts. Goals that do not
    /// drive forward (turns, reversing, arrived) pass unchanged and end the turn. A turn starts
    /// only when the way toward the goal is free (`goal_way_free`, asked only then): turning on
    /// the spot toward an obstacle only undoes the avoidance turn that led away from it, and the
    /// two made a stationary limit cycle in front of it; a turn under way goes on.
    pub fn apply(&mut self, goal: Goal, goal_way_free: impl FnOnce() -> bool) -> Goal {
        let off = goal.angle_rad.abs();
        self.turning = goal.status == GoalStatus::Active
            && goal.velocity > 0.0
            && match self.turning {
                true => off > self.start_rad,
                false => off >= self.stop_rad && goal_way_free(),
            };
        match self.turning {
            true => Goal { velocity: 0.0, ..goal },
            false => goal,
        }
    }
}
