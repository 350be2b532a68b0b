//! MOFIS, the motion module of the paper (§2.2): from PAFSIS's goal to the set-point sent to
//! the base, avoiding what the robot has seen: the surface points OFFIS locates from the flow (per
//! block, not its obstacle or TPO decision) and the odometry feed the obstacle memory.
//!
//! [`Mofis::step`] runs, in this order:
//!
//! 1. the obstacle memory ([`memory`]) takes in OFFIS's surface points and the odometry, and
//!    names the nearest threat on either side of the heading;
//! 2. the stall recovery ([`stall`]) turns away when the wheels push against something unseen,
//!    and marks what they pushed against in the memory;
//! 3. the escape ([`escape`]) turns to a free heading after a standstill;
//! 4. the spot turn ([`SpotTurn`]) turns to a goal far off the heading on the spot;
//! 5. the steering keeps the goal's heading, kept off side surfaces
//!    ([`memory::ObstacleMemory::centring`]), while its straight path is free; where it is not,
//!    it follows the cheapest way the footprint fits through the memory's grid
//!    ([`memory::ObstacleMemory::plan_heading`]; with `planner` off, or where the way does not
//!    leave the robot's cell, the free heading nearest the goal, [`memory::ObstacleMemory::steer`]).
//!    With `planner` on, the way is found first and the spot turn turns to where it leads, so
//!    the two never turn the robot opposite ways;
//! 6. the stopping gate caps the speed to what stops short of the memory's cells ([`Ahead`]);
//! 7. the fuzzy core ([`fusion`]): `rules/mofis/avoidance.toml` turns the threats into a speed
//!    factor and an avoidance turn, `rules/mofis/fusion.toml` weighs avoidance against the goal,
//!
//!    ```text
//!    v     = goal_velocity · max(0, cos goal_angle) · speed
//!    omega = (1 − weight) · heading_gain · goal_angle + weight · turn · max_turn_rate
//!    ```
//!
//!    with the steered goal angle (PAFSIS gives the leg's speed; what is left of it along the
//!    heading the robot turns to is driven); the footprint guard ([`guard`]) bends a command
//!    whose arc meets a remembered cell, and the [`Limiter`](crate::control::Limiter) clamps the
//!    result to the configured speed, turn-rate and acceleration limits.
//!
//! Without perception ([`Mofis::fail_safe`]) the set-point is an immediate stop.

pub mod escape;
pub mod fusion;
pub mod guard;
pub mod memory;
pub mod spot;
pub mod stall;
#[cfg(test)]
mod tests;

pub use fusion::{Ahead, Avoidance, Fusion, MofisOutput, load_default, stop_speed};
pub use spot::SpotTurn;

use crate::config_error::ConfigError;
use crate::control::ControlLimits;
use crate::fuzzy::FuzzyError;
use crate::offis::points::SurfacePoint;
use crate::pafsis::{Doorway, Goal, GoalStatus, Lane};
use crate::perception::{Obstacle, Perception};
use escape::Escape;
use hal::{BodyVelocity, Calibration};
use memory::{ObstacleMemory, PlanTarget};
use serde::{Deserialize, Serialize};
use stall::{Manoeuvre, StallRecovery};
use std::path::PathBuf;

/// The `[mofis]` config table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MofisParams {
    /// Folder with `avoidance.toml` and `fusion.toml` (the rule bases); unset = the copies of
    /// `rules/mofis/` built into the binary, so flownav runs from any directory.
    pub rules_dir: Option<PathBuf>,
    /// Goal behaviour turn rate per radian of goal angle, 1/s (ω_goal = gain · angle).
    pub heading_gain: f64,
    /// Distance fed to the rule bases when nothing is seen (no obstacle, open ahead), m; the
    /// top of the distance universes.
    pub sensing_range_m: f64,
    /// Distance assumed for an obstacle that OFFIS reports without a distance (the robot is not
    /// translating, so depth is unknown), m. Medium by default: slow down and steer, don't stop.
    pub unknown_obstacle_distance_m: f64,
    /// An obstacle within this bearing of dead ahead is passed on the goal's side, rad.
    pub dead_ahead_rad: f64,
    /// Look before driving: the forward speed is full while the robot steers at most this far
    /// off its heading (the steered goal angle, or the fused turn rate ÷ `heading_gain`), rad.
    /// 0.2 rad × `heading_gain` 1.5 = 0.3 rad/s, `memory.max_turn_rate`: faster turns blind the
    /// obstacle memory (no depth is taken in), so full speed only while the camera still measures ...
    pub blind_turn_start_rad: f64,
    /// ... and falls linearly to nothing at this angle: a sharper turn is made on the spot (a
    /// round robot cannot hit anything turning on the spot), rad.
    pub blind_turn_stop_rad: f64,
    /// `[mofis.memory]`: the obstacle memory that turns OFFIS's surface points into the
    /// obstacle avoided ([`memory`]).
    pub memory: memory::MemoryParams,
    /// `[mofis.stall]`: turning away when the wheels push against something unseen
    /// ([`stall`]).
    pub stall: stall::StallParams,
    /// `[mofis.escape]`: turning to a free heading after a standstill ([`escape`]).
    pub escape: escape::EscapeParams,
    /// The stopping gate: the forward speed is at most the speed from which the robot stops,
    /// braking at `stop_decel_mps2`, `stop_margin_m` short of the nearest occupied cell in a band
    /// `robot_radius_m + stop_margin_m` either side of its heading in the obstacle memory
    /// ([`Ahead::stop_speed_mps`]), m ...
    pub stop_margin_m: f64,
    /// ... m/s² (below `control.max_linear_decel`, so the limiter can follow it).
    pub stop_decel_mps2: f64,
    /// The footprint guard, the last check before the limiter: a forward command whose arc
    /// would bring the robot's footprint (widened by `guard_clearance_m`) onto a confirmed
    /// cell of the memory that still has at least this evidence, within `guard_horizon_s` of
    /// travel plus the distance to stop (braking at `stop_decel_mps2`), is bent to the nearest
    /// turn rate whose arc is clear ([`fusion::Fusion`]'s guard). It counts the cells that have faded
    /// below the `memory.occupied` threshold too: an obstacle that has left the camera's view
    /// lingers there, and every side graze traced in the missions was of such an obstacle.
    /// 0: off.
    pub guard_evidence: f64,
    /// ... m beyond the robot's radius ...
    pub guard_clearance_m: f64,
    /// ... and the time of travel it looks ahead, s ...
    pub guard_horizon_s: f64,
    /// ... bending the turn rate by at most this, rad/s: the guard knows only what the memory
    /// holds, and a robot bent hard away from a lingering cell ran into an obstacle ahead that
    /// the memory did not hold when the bend had no limit.
    pub guard_max_bend: f64,
    /// ... and when no turn rate within that bend is clear, try the same at 0.7, 0.5, 0.35 and
    /// 0.25 of the speed, where the same bend turns tighter and the reach is shorter ...
    pub guard_slow: bool,
    /// ... and when none of those is clear either: brake to the speed from which the robot
    /// stops (at `stop_decel_mps2`) before its footprint reaches a cell out of the camera's
    /// view on the freest of the full-speed arcs within the bend, and take that arc. Bending
    /// only, the guard saw the traced contacts coming 1–1.5 s ahead and passed the command
    /// on at 0.35 m/s; braking removes those contacts. With it the standstill escape takes
    /// only headings free of the guard's cells too, or it turns the robot toward what the
    /// brake stands it in front of again (docs/navigation.md, *The footprint guard*).
    pub guard_brake: bool,
    /// The guard counts, besides the cells it holds, every confirmed cell joined to one of them
    /// (however faded): each cluster of cells is held as one obstacle while any of its cells
    /// is ([`memory::ObstacleMemory::arc_free`]): traced grazes touched a faded cell between
    /// two held ones.
    pub guard_cluster: bool,
    /// The guard counts only the cells of a cluster of at least this many confirmed cells
    /// (joined through confirmed 8-neighbours): a lone confirmed cell in free space is a
    /// mismatched block's depth seen twice, and with `guard_brake` one beside the robot, out
    /// of view where nothing clears it, stood the robot still. 1: every cell.
    pub guard_min_cells: usize,
    /// Where the straight path toward the goal is not free (of the cells the steering avoids,
    /// inside the lane, or of the cells the guard counts), drive along the cheapest way through
    /// the memory's grid that the footprint fits ([`memory::ObstacleMemory::plan_heading`])
    /// instead of the free straight ray nearest the goal ([`memory::ObstacleMemory::steer`]):
    /// the rays know no way round a box, and their longest one led into gaps the guard then
    /// stood the robot in front of.
    pub planner: bool,
}

impl Default for MofisParams {
    fn default() -> Self {
        Self {
            rules_dir: None,
            heading_gain: 1.5,
            sensing_range_m: 5.0,
            unknown_obstacle_distance_m: 1.5,
            dead_ahead_rad: 0.05,
            blind_turn_start_rad: 0.2,
            blind_turn_stop_rad: 0.6,
            memory: memory::MemoryParams::default(),
            stall: stall::StallParams::default(),
            escape: escape::EscapeParams::default(),
            stop_margin_m: 0.05,
            stop_decel_mps2: 0.8,
            guard_evidence: 0.3,
            guard_clearance_m: 0.04,
            guard_horizon_s: 1.0,
            guard_max_bend: 0.5,
            guard_slow: true,
            guard_brake: true,
            guard_cluster: true,
            guard_min_cells: 2,
            planner: true,
        }
    }
}

impl MofisParams {
    /// What the footprint guard counts in the memory, from the `guard_*` fields.
    pub fn guard_cells(&self) -> memory::GuardCells {
        memory::GuardCells {
            clearance_m: self.guard_clearance_m,
            min_evidence: self.guard_evidence,
            cluster: self.guard_cluster,
            min_cells: self.guard_min_cells,
        }
    }

    /// Checks ranges that serde cannot.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, problem: &str| {
            Err(ConfigError::Invalid { field: format!("mofis.{field}"), problem: problem.into() })
        };
        if !(self.heading_gain.is_finite() && self.heading_gain > 0.0) {
            return bad("heading_gain", "must be a positive finite number (1/s)");
        }
        if !(self.sensing_range_m.is_finite() && self.sensing_range_m > 0.0) {
            return bad("sensing_range_m", "must be a positive finite distance in m");
        }
        if !(self.unknown_obstacle_distance_m.is_finite() && self.unknown_obstacle_distance_m >= 0.0) {
            return bad("unknown_obstacle_distance_m", "must be a finite distance ≥ 0 in m");
        }
        if !(self.dead_ahead_rad.is_finite() && (0.0..0.5).contains(&self.dead_ahead_rad)) {
            return bad("dead_ahead_rad", "must be in [0, 0.5) rad");
        }
        if !(self.blind_turn_start_rad.is_finite() && self.blind_turn_start_rad >= 0.0) {
            return bad("blind_turn_start_rad", "must be an angle ≥ 0 in rad");
        }
        if !(self.blind_turn_stop_rad.is_finite() && self.blind_turn_stop_rad > self.blind_turn_start_rad) {
            return bad("blind_turn_stop_rad", "must be an angle in rad greater than blind_turn_start_rad");
        }
        if !(self.stop_margin_m.is_finite() && (0.0..=0.5).contains(&self.stop_margin_m)) {
            return bad("stop_margin_m", "must be in [0, 0.5] m");
        }
        if !(self.stop_decel_mps2.is_finite() && self.stop_decel_mps2 > 0.0) {
            return bad("stop_decel_mps2", "must be a positive deceleration in m/s²");
        }
        if !(self.guard_evidence.is_finite() && self.guard_evidence >= 0.0) {
            return bad("guard_evidence", "must be an evidence ≥ 0 (frames; 0: off)");
        }
        if !(self.guard_clearance_m.is_finite() && (0.0..=0.5).contains(&self.guard_clearance_m)) {
            return bad("guard_clearance_m", "must be in [0, 0.5] m");
        }
        if !(self.guard_horizon_s.is_finite() && (0.0..=5.0).contains(&self.guard_horizon_s)) {
            return bad("guard_horizon_s", "must be in [0, 5] s");
        }
        if !(self.guard_max_bend.is_finite() && self.guard_max_bend >= 0.0) {
            return bad("guard_max_bend", "must be a turn rate ≥ 0 in rad/s");
        }
        if !(1..=100).contains(&self.guard_min_cells) {
            return bad("guard_min_cells", "must be a number of cells in 1..=100 (1: every cell)");
        }
        self.memory.validate()?;
        self.stall.validate()?;
        self.escape.validate()
    }
}

/// Why MOFIS could not be built or evaluated.
#[derive(Debug, thiserror::Error)]
pub enum MofisError {
    #[error("MOFIS rule base {}: {source}", path.display())]
    Rules {
        path: PathBuf,
        #[source]
        source: FuzzyError,
    },
    #[error("MOFIS rule base {origin} lacks {what} '{name}', which MOFIS feeds/reads; see docs/navigation.md")]
    Missing { origin: String, what: &'static str, name: &'static str },
    #[error("MOFIS rule base {origin} has inputs {names:?}; MOFIS feeds exactly {expected}: {wanted}")]
    InputCount { origin: String, names: Vec<String>, expected: usize, wanted: &'static str },
    #[error("MOFIS evaluation failed: {0}")]
    Evaluate(#[from] FuzzyError),
}

/// Steering around remembered obstacles ([`ObstacleMemory::steer`]): the path must be free
/// this far, m; candidate headings within this angle of the robot's heading, in these steps, rad.
const STEER_LOOKAHEAD_M: f64 = 1.5;
const STEER_MAX_RAD: f64 = 0.7;
const STEER_STEP_RAD: f64 = 0.05;
/// Planning past what blocks the straight path ([`ObstacleMemory::plan_heading`]): the way ends
/// as near as it can to the goal's bearing this far ahead (or the stop, when nearer), m.
const PLAN_REACH_M: f64 = 3.0;
/// Keeping off side surfaces ([`ObstacleMemory::centring`]): cells up to this far ahead and this
/// far to the side count, m; the correction's lookahead, m, and its largest angle, rad.
const CENTRE_WINDOW_M: f64 = 1.5;
const CENTRE_REACH_M: f64 = 0.9;
const CENTRE_LOOKAHEAD_M: f64 = 1.5;
const CENTRE_MAX_RAD: f64 = 0.3;
/// A stalled robot compares the free path this far to either side, rad.
const STALL_PROBE_RAD: f64 = 0.8;
/// The stopping gate looks this far ahead of the robot's origin, m (at the top speed, 0.5 m/s,
/// braking at 0.8 m/s² takes 0.16 m).
const STOP_LOOKAHEAD_M: f64 = 1.0;
/// A stall marks the obstacle memory solid over this arc in front of the robot, rad.
const CONTACT_ARC_RAD: f64 = 0.5;

/// What the plan says about the way, beside its goal (nothing without a map).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Route {
    /// The corridor the robot is in ([`ObstacleMemory::set_lane`]).
    pub lane: Option<Lane>,
    /// The door the robot is going through ([`ObstacleMemory::set_doorway`]).
    pub doorway: Option<Doorway>,
    /// Where the plan stops the robot (before a turn, at the goal): nothing beyond is in its
    /// way, m ahead ([`ObstacleMemory::set_stop`]).
    pub stop_ahead_m: Option<f64>,
}

/// What MOFIS takes in each step.
#[derive(Clone, Copy, Debug)]
pub struct MofisInput<'a> {
    /// This step's perception (OFFIS).
    pub perception: &'a Perception,
    /// The solid surface points OFFIS located this step, robot frame.
    pub points: &'a [SurfacePoint],
    /// Whether the frame pair measured anything ([`Mofis::measurable`]): else the points are
    /// not taken in.
    pub measured: bool,
    /// The odometry of this frame ...
    pub odometry: BodyVelocity,
    /// ... and the time since the previous frame, s.
    pub dt: f64,
    /// PAFSIS's goal.
    pub goal: Goal,
    /// What the plan says about the way.
    pub route: Route,
}

/// What MOFIS decided in one step.
#[derive(Clone, Copy, Debug)]
pub struct MofisStep {
    /// The obstacle avoided: the nearer of the obstacle memory's threats on either side (solid
    /// things in or beside the robot's path, remembered over frames), not this frame's OFFIS
    /// obstacle. The other side's threat is avoided too (its share is in `output.avoidance`).
    pub avoided: Obstacle,
    /// PAFSIS's goal after the stall recovery, the escape and the spot turn.
    pub goal: Goal,
    /// `goal` after steering around remembered obstacles: what the fuzzy core was given.
    pub steered: Goal,
    /// The fuzzy core's decision and the set-point.
    pub output: MofisOutput,
}

/// The MOFIS stage: the obstacle memory, the manoeuvres, the steering, the stopping gate and the
/// fuzzy core with its footprint guard and limiter.
pub struct Mofis {
    params: MofisParams,
    fusion: Fusion,
    memory: ObstacleMemory,
    stall: StallRecovery,
    escape: Escape,
    spot_turn: SpotTurn,
    /// The set-point of the previous step (what the odometry of this step should show).
    last_setpoint: BodyVelocity,
}

impl Mofis {
    /// Builds MOFIS for a camera with calibration `calib` (its field of view and height bound
    /// what the obstacle memory sees) and a base with `limits`; loads the rule bases.
    pub fn new(params: MofisParams, limits: ControlLimits, calib: &Calibration) -> Result<Self, MofisError> {
        let half_fov = ((calib.camera.width as f64 / 2.0) / calib.camera.fx).atan();
        let can_reverse = limits.max_reverse_speed > 0.0;
        Ok(Self {
            memory: ObstacleMemory::new(params.memory, half_fov, calib.mount.z_m),
            stall: StallRecovery::new(params.stall, can_reverse),
            spot_turn: SpotTurn::new(&params, limits.max_turn_rate),
            escape: Escape::new(params.escape),
            last_setpoint: BodyVelocity::ZERO,
            fusion: Fusion::load(params.clone(), limits)?,
            params,
        })
    }

    /// The obstacle memory.
    pub fn memory(&self) -> &ObstacleMemory {
        &self.memory
    }

    /// The parameters it runs with.
    pub fn params(&self) -> &MofisParams {
        &self.params
    }

    /// The fuzzy core (rule bases, guard, limiter).
    pub fn fusion(&self) -> &Fusion {
        &self.fusion
    }

    /// How many times the robot found itself pushing against something and turned away
    /// ([`stall`]).
    pub fn stall_recoveries(&self) -> u32 {
        self.stall.recoveries()
    }

    /// How many times the robot stood still too long and turned to a free heading ([`escape`]).
    pub fn escapes(&self) -> u32 {
        self.escape.escapes()
    }

    /// Whether a frame pair over `dt` seconds with the mean velocity `span` and a turn-rate
    /// change of `turn_change` (rad/s) measures anything ([`ObstacleMemory::measurable`]).
    pub fn measurable(&self, span: BodyVelocity, dt: f64, turn_change: f64) -> bool {
        self.memory.measurable(span, dt, turn_change)
    }

    /// Perception is missing (camera stall, OFFIS failure): forgets the memory and the
    /// manoeuvres under way, and stops now through the limiter's stop path.
    pub fn fail_safe(&mut self) -> BodyVelocity {
        self.memory.clear();
        self.stall.reset();
        self.escape.reset();
        self.spot_turn.reset();
        self.last_setpoint = BodyVelocity::ZERO;
        self.fusion.fallback()
    }

    /// One step (module doc): the memory takes in the points, the manoeuvres and the steering
    /// turn the goal, and the fuzzy core gives the set-point.
    pub fn step(&mut self, input: MofisInput<'_>) -> Result<MofisStep, MofisError> {
        let MofisInput { perception, points, measured, odometry, dt: frame_dt, goal, route } = input;
        let mp = *self.memory.params();
        self.memory.update(odometry, frame_dt, points, measured);
        // the corridor from the map: for the memory's queries, the escape and the steering
        self.memory.set_lane(route.lane);
        self.memory.set_doorway(route.doorway);
        // where the plan stops the robot (before a turn, at the goal): nothing beyond is in its way
        let stop_ahead = route.stop_ahead_m.unwrap_or(f64::INFINITY);
        self.memory.set_stop(stop_ahead);
        let horizon = self.memory.horizon(stop_ahead);
        // the nearest threat, and the nearest on the other side of the heading: both are avoided
        let (avoided, other) = memory::nearer(self.memory.threat_sides(stop_ahead));
        // pushing against something unseen: turn away on the spot, to the freer side
        let memory = &self.memory;
        let recoveries_before = self.stall.recoveries();
        let turn_away = self.stall.update(self.last_setpoint, odometry, frame_dt, || {
            let (left, right) = (
                memory.free_distance(STALL_PROBE_RAD, STEER_LOOKAHEAD_M),
                memory.free_distance(-STALL_PROBE_RAD, STEER_LOOKAHEAD_M),
            );
            match left - right {
                d if d > memory.params().cell_m => 1.0,
                d if d < -memory.params().cell_m => -1.0,
                _ => goal.angle_rad.signum(),
            }
        });
        if self.stall.recoveries() > recoveries_before {
            // what the robot pushed against is there, whether the camera saw it or not
            self.memory.mark_contact(CONTACT_ARC_RAD);
        }
        let goal = match turn_away {
            Some(m) if goal.status == GoalStatus::Active => match m {
                Manoeuvre::Reverse(speed) => Goal { velocity: -speed, angle_rad: 0.0, ..goal },
                Manoeuvre::Turn(angle_rad) => Goal { velocity: 0.0, angle_rad, ..goal },
            },
            _ => goal,
        };
        let lookahead = STEER_LOOKAHEAD_M.min(horizon);
        // standing still too long: turn to the free heading nearest the goal, round the full
        // circle, and drive off that way (a stall recovery's manoeuvre goes first)
        let goal = match turn_away {
            None => {
                let (memory, yaw) = (&self.memory, self.memory.yaw());
                let look = self.escape.params().lookahead_m;
                let p = &self.params;
                // a guard that brakes stands the robot before the cells it counts: an escape
                // toward them would only stand it again
                let braking = p.guard_brake && p.guard_evidence > 0.0;
                let counted = p.guard_cells();
                let guarded = |h: f64| match braking {
                    true => memory.heading_free(h, look, &counted),
                    false => look,
                };
                self.escape
                    .apply(goal, yaw, odometry.v * frame_dt, frame_dt, |h| memory.free_in_lane(h, look).min(guarded(h)))
            }
            Some(_) => goal,
        };
        let memory = &self.memory;
        let counted = self.params.guard_cells();
        let centred =
            |angle: f64| angle + memory.centring(CENTRE_WINDOW_M, CENTRE_REACH_M, CENTRE_LOOKAHEAD_M, CENTRE_MAX_RAD);
        let steer = |angle: f64| memory.steer(angle, lookahead, STEER_MAX_RAD, STEER_STEP_RAD);
        // what PAFSIS asked for, before any turn on the spot
        let asked_mps = goal.velocity;
        let (goal, steered) = match self.params.planner {
            false => {
                // a goal far off the heading is turned to on the spot first; turns on the spot
                // keep their angle, driving picks a free heading
                let goal = self
                    .spot_turn
                    .apply(goal, frame_dt, || memory.free_distance(goal.angle_rad, lookahead) >= lookahead);
                let steered = match goal.velocity > 0.0 {
                    true => Goal { angle_rad: steer(centred(goal.angle_rad)), ..goal },
                    false => goal,
                };
                (goal, steered)
            }
            true => {
                // the way first, then the spot turn to where it leads: turning on the spot to
                // the goal while the way led elsewhere turned the robot back and forth in front
                // of a box. The straight path is taken where it is free of what the steering
                // avoids and of what the guard counts (the wall band's cells and faded ones too)
                let aim = |angle: f64| match memory.free_in_lane(angle, lookahead) >= lookahead
                    && memory.heading_free(angle, lookahead, &counted) >= lookahead
                {
                    true => angle,
                    false => {
                        let target = PlanTarget { bearing_rad: angle, distance_m: PLAN_REACH_M.min(stop_ahead) };
                        memory.plan_heading(target, &counted).unwrap_or_else(|| steer(angle))
                    }
                };
                // the spot turn is decided on the goal's own bearing: the centring is measured
                // across the robot's heading, and swung as much as the turn while it turned
                let aimed = match goal.velocity > 0.0 {
                    true => Goal { angle_rad: aim(goal.angle_rad), ..goal },
                    false => goal,
                };
                let goal = Goal { velocity: self.spot_turn.apply(aimed, frame_dt, || true).velocity, ..goal };
                // driving: the way again from the centred bearing, where the centring moves it
                // (a search is 0.5 ms)
                let angle_rad = match goal.velocity > 0.0 {
                    true => match centred(goal.angle_rad) {
                        c if c != goal.angle_rad => aim(c),
                        _ => aimed.angle_rad,
                    },
                    false => aimed.angle_rad,
                };
                (goal, Goal { angle_rad, ..goal })
            }
        };
        // the distance ahead: the free path along the heading in the memory (the TPO's wall
        // distance is one frame's guess; the memory has what was seen solid, over frames), and
        // nothing there (the sensing range) when the path is free up to where the robot stops
        let range = self.params.sensing_range_m;
        let free = self.memory.free_distance(0.0, range);
        let front = match free >= horizon {
            true => range,
            false => free - mp.robot_radius_m,
        };
        // the stopping gate: never faster than the robot can stop short of what is in its way
        let (margin, decel) = (self.params.stop_margin_m, self.params.stop_decel_mps2);
        let in_way = self.memory.free_width(0.0, mp.robot_radius_m + margin, STOP_LOOKAHEAD_M);
        // and short of the door's wall, from the map, when going through a door
        let door = self.memory.door_free_ahead(STOP_LOOKAHEAD_M);
        let stop_speed_mps = stop_speed(in_way - mp.robot_radius_m - margin, decel).min(stop_speed(door, decel));
        let ahead = Ahead { front_m: front.max(0.0), stop_speed_mps };
        let view = Perception { obstacle: avoided, ..perception.clone() };
        // the footprint guard: the arcs against every remembered cell, faded ones included
        let memory = &self.memory;
        let counted = self.params.guard_cells();
        let arc_free =
            move |curvature: f64, reach: f64, aside: bool| memory.arc_free(curvature, reach, &counted, aside);
        let output =
            self.fusion.step_guarded(&view, other.as_ref(), Some(ahead), &steered, frame_dt, Some(&arc_free))?;
        self.last_setpoint = output.setpoint;
        match turn_away {
            // with the planner, a turn on the spot longer than a full circle is a standstill:
            // where no way leads on, the way's first step swings as the robot turns, and turns
            // that undo each other would hold it there
            None if self.params.planner && self.spot_turn.overlong() => {
                self.escape.observe(&Goal { velocity: asked_mps, ..goal }, output.setpoint.v, frame_dt)
            }
            None => self.escape.observe(&goal, output.setpoint.v, frame_dt),
            Some(_) => self.escape.reset_standstill(),
        }
        Ok(MofisStep { avoided, goal, steered, output })
    }
}
