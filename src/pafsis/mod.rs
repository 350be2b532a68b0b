//! PAFSIS, the path-planning module of the paper (§2.2): global planning on a topological map
//! ([`map`], [`global`]) and local planning that follows the plan by landmarks and odometry
//! ([`local`]), producing the goal-oriented velocity and angle that MOFIS fuses with collision
//! avoidance.

pub mod global;
pub mod local;
pub mod map;
pub mod side_doors;
pub mod walls;

pub use global::{Mission, Plan, PlanError, plan};
pub use local::{
    Doorway, Goal, GoalStatus, Lane, LanePart, Leg, LegKind, Pafsis, PafsisEvent, PoseHint, Progress, WallFixes,
};
pub use map::{Action, MapError, MapTolerance, PlaceKind, Side, TopoMap, Until};
pub use walls::WallSighting;

use crate::config_error::ConfigError;
use serde::{Deserialize, Serialize};

/// The `[pafsis]` config table: speeds of the goal behaviour and how landmarks are trusted.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PafsisParams {
    /// Goal velocity along corridors, m/s.
    pub cruise_speed: f64,
    /// Goal velocity through doorways, m/s.
    pub door_speed: f64,
    /// Distance before a leg's end over which the goal velocity comes down, m: as
    /// `√(remaining / slow_radius_m)`, the profile of a constant deceleration (the leg's speed²
    /// ÷ 2 · `slow_radius_m`: 0.12 m/s² at 0.35 m/s over 0.5 m), so the robot brakes late
    /// and firmly instead of creeping for seconds.
    pub slow_radius_m: f64,
    /// The ramp never goes below this fraction of the leg's speed (so the robot gets there).
    pub min_speed_fraction: f64,
    /// A turn on the spot is done within this angle, rad.
    pub turn_tolerance_rad: f64,
    /// A corner/wall that ends a corridor is reached at this distance ahead, m.
    pub stop_distance_m: f64,
    /// Minimum TPO confidence for a landmark to count.
    pub landmark_min_confidence: f64,
    /// Consecutive frames a landmark must be seen to count (debounce).
    pub landmark_min_frames: u32,
    /// A door sighting matches an expected door within this distance of its expected place, m;
    /// also the largest disagreement a later frame of the same door may have to move the
    /// progress. 0.35 m admits 5 % odometry error over the office's 6 m between doors and
    /// rejects the 0.47 m mismatches of mis-ranged door frames seen in the simulated missions.
    pub landmark_gate_m: f64,
    /// Door sightings farther than this are not used for position correction, m.
    pub door_max_range_m: f64,
    /// A landmark that ends a leg is declared missing after this multiple of the leg's length,
    /// or past the far edge of the map's tolerance window round the leg's end if that comes first.
    pub miss_factor: f64,
    /// Replans allowed before the mission fails.
    pub max_replans: u32,
    /// Lookahead of the cross-track correction, m.
    pub lookahead_m: f64,
    /// Steer back to the leg's line from the odometry alone (dead reckoning from the start
    /// place's position) when the map has positions and no pose hint is given: after passing
    /// an obstacle the robot returns to the corridor's centre line instead of running on along
    /// whatever side it swerved to.
    pub cross_track_odometry: bool,
    /// After an obstacle is seen within 1 m at distance d, the cross-track correction pauses
    /// until the robot has driven d plus this far, m: it passes the obstacle on the side it
    /// swerved to and returns to the line behind it (0: never pause).
    pub cross_track_hold_m: f64,
    /// On corridor legs, each frame's side walls ([`walls`]) move the heading estimate this
    /// fraction of the way to what they say (0, the default: the flow's yaw keeps the heading
    /// better; the fitted walls' directions scatter by degrees at 320×180).
    pub wall_heading_gain: f64,
    /// ... and the dead-reckoned offset from the centre line, where the map gives the
    /// corridor's width (0: never).
    pub wall_lateral_gain: f64,
    /// ... and, while driving, the heading turns by this many radians per metre of that
    /// lateral disagreement, each frame: the robot drifting steadily off the estimate is what a
    /// wrong heading does (a start turned off the map's heading, which the flow's yaw, measuring
    /// only changes, never sees) (0: never).
    pub wall_drift_gain: f64,
}

impl Default for PafsisParams {
    fn default() -> Self {
        Self {
            cruise_speed: 0.35,
            door_speed: 0.2,
            slow_radius_m: 0.5,
            min_speed_fraction: 0.15,
            turn_tolerance_rad: 0.05,
            stop_distance_m: 0.8,
            landmark_min_confidence: 0.5,
            landmark_min_frames: 2,
            landmark_gate_m: 0.35,
            door_max_range_m: 5.0,
            miss_factor: 1.5,
            max_replans: 3,
            lookahead_m: 1.5,
            cross_track_odometry: true,
            cross_track_hold_m: 1.0,
            wall_heading_gain: 0.0,
            wall_lateral_gain: 0.03,
            wall_drift_gain: 0.01,
        }
    }
}

impl PafsisParams {
    /// Checks ranges that serde cannot.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, problem: &str| {
            Err(ConfigError::Invalid { field: format!("pafsis.{field}"), problem: problem.into() })
        };
        let positive = [
            ("cruise_speed", self.cruise_speed),
            ("door_speed", self.door_speed),
            ("slow_radius_m", self.slow_radius_m),
            ("turn_tolerance_rad", self.turn_tolerance_rad),
            ("stop_distance_m", self.stop_distance_m),
            ("landmark_gate_m", self.landmark_gate_m),
            ("door_max_range_m", self.door_max_range_m),
            ("lookahead_m", self.lookahead_m),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return bad(field, "must be a positive finite number");
            }
        }
        if !(self.cross_track_hold_m.is_finite() && self.cross_track_hold_m >= 0.0) {
            return bad("cross_track_hold_m", "must be a finite distance >= 0 m");
        }
        if !(0.0..=1.0).contains(&self.wall_heading_gain) {
            return bad("wall_heading_gain", "must be in [0, 1]");
        }
        if !(0.0..=1.0).contains(&self.wall_lateral_gain) {
            return bad("wall_lateral_gain", "must be in [0, 1]");
        }
        if !(0.0..=1.0).contains(&self.wall_drift_gain) {
            return bad("wall_drift_gain", "must be in [0, 1] rad/m");
        }
        if !(0.0..=1.0).contains(&self.min_speed_fraction) {
            return bad("min_speed_fraction", "must be in [0, 1]");
        }
        if !(0.0..=1.0).contains(&self.landmark_min_confidence) {
            return bad("landmark_min_confidence", "must be in [0, 1]");
        }
        if self.landmark_min_frames == 0 {
            return bad("landmark_min_frames", "must be at least 1");
        }
        if !(self.miss_factor.is_finite() && self.miss_factor > 1.0) {
            return bad("miss_factor", "must be a finite number > 1 (e.g. 1.5 = 150% of the leg)");
        }
        Ok(())
    }
}
