//! MOFIS, the motion module of the paper (§2.2): a Mamdani collision-avoidance behaviour, a
//! fuzzy fusion of avoidance with PAFSIS's goal orientation, and the safety limiter that turns
//! the fused command into the set-point sent to the base.
//!
//! Per step: OFFIS's perception gives the avoidance inputs (obstacle distance and bearing, the
//! distance to a wall/corner ahead); `rules/mofis/avoidance.toml` turns them into a speed factor
//! and an avoidance turn; `rules/mofis/fusion.toml` weighs avoidance against the goal from the
//! obstacle's distance and offset; then
//!
//! ```text
//! v     = goal_velocity · speed
//! omega = (1 − weight) · heading_gain · goal_angle + weight · turn · max_turn_rate
//! ```
//!
//! and the [`Limiter`] clamps the result to the configured speed, turn-rate and acceleration
//! limits. Without perception ([`Mofis::fallback`]) the set-point is an immediate stop.

pub mod escape;
pub mod memory;
pub mod stall;

use crate::config::ConfigError;
use crate::control::{ControlLimits, Limiter};
use crate::fuzzy::{Evaluation, FuzzyError, FuzzySystem, InputId, OutputId};
use crate::pafsis::{Goal, GoalStatus};
use crate::perception::{Obstacle, Perception, TpoShape};
use hal::BodyVelocity;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

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
    /// turn rate whose arc is clear ([`Mofis::guard`]). It counts the cells that have faded
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
    /// the memory did not hold (seeds 9 and 15, with no limit).
    pub guard_max_bend: f64,
    /// ... and when no turn rate within that bend is clear, try the same at 0.7, 0.5, 0.35 and
    /// 0.25 of the speed, where the same bend turns tighter and the reach is shorter. Off by
    /// default: on seeds 0..39 it left 1 run unarrived and 3 with contact, against none and 2
    /// without it (docs/missions-history.md, sixteenth session) ...
    pub guard_slow: bool,
    /// ... and when none of those is clear either: brake to the speed from which the robot
    /// stops (at `stop_decel_mps2`) before its footprint reaches a cell out of the camera's
    /// view on the freest of the full-speed arcs within the bend, and take that arc. Off by
    /// default: the guard saw the 4 traced contacts (seeds 34, 81, 83, 105) coming 1–1.5 s
    /// ahead and passed the command on at 0.35 m/s, and braking (with `guard_slow`) removed
    /// those contacts and all on seeds 0..19, but on seeds 20..39 it left 2 runs unarrived and
    /// 2 with contact, against none and 1 without it: the robot stood in front of faded cells
    /// beside it (docs/missions-history.md, sixteenth session).
    pub guard_brake: bool,
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
            guard_slow: false,
            guard_brake: false,
        }
    }
}

impl MofisParams {
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
        if let Err((field, problem)) = self.memory.check() {
            return bad(&format!("memory.{field}"), problem);
        }
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

/// The avoidance behaviour's crisp outputs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Avoidance {
    /// Fraction of the goal velocity the situation allows, [0, 1].
    pub speed: f64,
    /// Avoidance turn as a fraction of the maximum turn rate, [−1, 1], + = left.
    pub turn: f64,
}

/// Everything MOFIS decided in one step (for the log and the terminal).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct MofisOutput {
    /// What the avoidance rule base saw: obstacle distance, bearing, front distance (m, rad, m).
    pub inputs: [f64; 3],
    pub avoidance: Avoidance,
    /// Weight of avoidance against goal orientation, [0, 1].
    pub weight: f64,
    /// The fused command before the limiter.
    pub fused: BodyVelocity,
    /// The set-point to send: `fused` after the limiter.
    pub setpoint: BodyVelocity,
}

/// The way ahead as the obstacle memory has it ([`Mofis::step_sides`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ahead {
    /// The free distance ahead, m (the `front_distance` input of the avoidance rule base).
    pub front_m: f64,
    /// The stopping gate: the fastest forward speed from which the robot still stops short of
    /// the nearest occupied cell in its way, m/s ([`stop_speed`]).
    pub stop_speed_mps: f64,
}

/// The speed (m/s) from which a robot braking at `decel_mps2` stops within `free_m` metres:
/// √(2 · decel · free), 0 when nothing is free.
pub fn stop_speed(free_m: f64, decel_mps2: f64) -> f64 {
    (2.0 * decel_mps2 * free_m.max(0.0)).sqrt()
}

/// The rule bases, their variable ids, and the limiter state.
#[derive(Clone, Debug)]
pub struct Mofis {
    params: MofisParams,
    avoidance: FuzzySystem,
    fusion: FuzzySystem,
    avoid_in: [InputId; 3],
    avoid_out: [OutputId; 2],
    fusion_in: [InputId; 2],
    fusion_out: OutputId,
    avoid_ev: Evaluation,
    fusion_ev: Evaluation,
    avoid_buf: Vec<f64>,
    fusion_buf: Vec<f64>,
    limiter: Limiter,
    /// The side (+1 left, −1 right) chosen to pass the current dead-ahead obstacle.
    pass_side: Option<f64>,
}

impl Mofis {
    /// Loads `avoidance.toml` and `fusion.toml` from `params.rules_dir`.
    pub fn load(params: MofisParams, limits: ControlLimits) -> Result<Self, MofisError> {
        let read = |name: &str| match &params.rules_dir {
            Some(dir) => {
                let path = dir.join(name);
                FuzzySystem::from_file(&path).map_err(|source| MofisError::Rules { path, source })
            }
            None => {
                let text = match name {
                    "avoidance.toml" => BUILTIN_AVOIDANCE,
                    _ => BUILTIN_FUSION,
                };
                let origin = format!("(built-in) rules/mofis/{name}");
                FuzzySystem::from_toml_str(text, &origin)
                    .map_err(|source| MofisError::Rules { path: PathBuf::from(origin), source })
            }
        };
        let avoidance = read("avoidance.toml")?;
        let fusion = read("fusion.toml")?;
        Self::new(params, limits, avoidance, fusion)
    }

    /// Builds MOFIS from already loaded rule bases; checks that they have the variables MOFIS
    /// feeds and reads.
    pub fn new(
        params: MofisParams,
        limits: ControlLimits,
        avoidance: FuzzySystem,
        fusion: FuzzySystem,
    ) -> Result<Self, MofisError> {
        let input = |sys: &FuzzySystem, name: &'static str| {
            sys.input(name).map_err(|_| MofisError::Missing { origin: sys.origin().into(), what: "input", name })
        };
        let output = |sys: &FuzzySystem, name: &'static str| {
            sys.output(name).map_err(|_| MofisError::Missing { origin: sys.origin().into(), what: "output", name })
        };
        let avoid_in = [
            input(&avoidance, "obstacle_distance")?,
            input(&avoidance, "obstacle_bearing")?,
            input(&avoidance, "front_distance")?,
        ];
        let avoid_out = [output(&avoidance, "speed")?, output(&avoidance, "turn")?];
        let fusion_in = [input(&fusion, "obstacle_distance")?, input(&fusion, "obstacle_offset")?];
        let fusion_out = output(&fusion, "weight")?;
        let wanted = [
            (&avoidance, 3, "obstacle_distance, obstacle_bearing, front_distance"),
            (&fusion, 2, "obstacle_distance, obstacle_offset"),
        ];
        for (sys, expected, wanted) in wanted {
            if sys.inputs().len() != expected {
                return Err(MofisError::InputCount {
                    origin: sys.origin().into(),
                    names: sys.inputs().iter().map(|v| v.name.clone()).collect(),
                    expected,
                    wanted,
                });
            }
        }
        Ok(Self {
            avoid_ev: avoidance.evaluation(),
            fusion_ev: fusion.evaluation(),
            avoid_buf: vec![0.0; 3],
            fusion_buf: vec![0.0; 2],
            params,
            avoidance,
            fusion,
            avoid_in,
            avoid_out,
            fusion_in,
            fusion_out,
            limiter: Limiter::new(limits),
            pass_side: None,
        })
    }

    pub fn limiter(&self) -> &Limiter {
        &self.limiter
    }

    /// Perception is missing (camera stall, OFFIS failure): stop now.
    pub fn fallback(&mut self) -> BodyVelocity {
        self.limiter.stop()
    }

    /// The avoidance inputs for `p`: obstacle distance and bearing, and the distance to a wall
    /// or corner ahead. Unknown or absent values become the sensing range (nothing there) —
    /// except a present obstacle without a distance, which is assumed at
    /// `unknown_obstacle_distance_m`, and without a bearing, dead ahead.
    pub fn inputs(&self, p: &Perception) -> [f64; 3] {
        let range = self.params.sensing_range_m;
        let finite = |x: Option<f64>| x.filter(|v| v.is_finite());
        let [dist, bearing] = self.obstacle_inputs(&p.obstacle);
        let front = match p.tpo.shape {
            TpoShape::Wall | TpoShape::Corner => finite(p.tpo.distance_m).map_or(range, |d| d.clamp(0.0, range)),
            TpoShape::Door | TpoShape::Corridor | TpoShape::None => range,
        };
        [dist, bearing, front]
    }

    /// The obstacle's distance and bearing as the rule bases take them ([`inputs`](Self::inputs)).
    fn obstacle_inputs(&self, o: &Obstacle) -> [f64; 2] {
        let range = self.params.sensing_range_m;
        let finite = |x: Option<f64>| x.filter(|v| v.is_finite());
        match o.present {
            true => [
                finite(o.distance_m).unwrap_or(self.params.unknown_obstacle_distance_m).clamp(0.0, range),
                finite(o.bearing_rad).unwrap_or(0.0),
            ],
            false => [range, 0.0],
        }
    }

    /// Both rule bases for one obstacle at `dist`, `bearing` with `front` free ahead: the
    /// avoidance behaviour and its fusion weight.
    fn avoid(&mut self, dist: f64, bearing: f64, front: f64) -> Result<(Avoidance, f64), MofisError> {
        for (id, v) in self.avoid_in.iter().zip([dist, bearing, front]) {
            self.avoid_buf[id.0] = v;
        }
        self.avoidance.evaluate_into(&self.avoid_buf, &mut self.avoid_ev)?;
        let avoidance = Avoidance {
            speed: self.avoid_ev.value(self.avoid_out[0]).clamp(0.0, 1.0),
            turn: self.avoid_ev.value(self.avoid_out[1]).clamp(-1.0, 1.0),
        };
        for (id, v) in self.fusion_in.iter().zip([dist, bearing.abs()]) {
            self.fusion_buf[id.0] = v;
        }
        self.fusion.evaluate_into(&self.fusion_buf, &mut self.fusion_ev)?;
        Ok((avoidance, self.fusion_ev.value(self.fusion_out).clamp(0.0, 1.0)))
    }

    /// The fraction of the forward speed allowed while steering `off` rad off the heading
    /// (`blind_turn_start_rad` → 1, `blind_turn_stop_rad` and beyond → 0). The camera sees
    /// ±27° (C310) and the memory takes nothing in while turning faster than its
    /// `max_turn_rate`; an arc driven fast through such a turn sweeps the robot through floor it
    /// has not measured, which is where the simulated missions clipped boxes and walls.
    fn look_factor(&self, off: f64) -> f64 {
        let (a, b) = (self.params.blind_turn_start_rad, self.params.blind_turn_stop_rad);
        ((b - off) / (b - a)).clamp(0.0, 1.0)
    }

    /// One step: fuse collision avoidance for `perception` with PAFSIS's `goal`, and limit the
    /// result for a step `dt` seconds after the previous one. A goal that is not active (arrived,
    /// failed) brings the robot to a stop within the deceleration limits.
    pub fn step(&mut self, perception: &Perception, goal: &Goal, dt: f64) -> Result<MofisOutput, MofisError> {
        self.step_sides(perception, None, None, goal, dt)
    }

    /// [`Mofis::step`] with a second obstacle on the other side of the heading and the distance
    /// ahead measured otherwise.
    ///
    /// `ahead`: what the obstacle memory says about the way ahead: the free distance fed to the
    /// rule bases instead of the TPO's wall/corner distance, and the stopping gate's speed
    /// limit; `None` = the distance from the TPO and no gate.
    ///
    /// `other`: the second obstacle (`perception.obstacle` is the nearer). Each is avoided by
    /// the rule bases on its own, and their turns are averaged weighted by fusion weight ÷
    /// distance (a far cell on one side does not cancel a near one on the other), with the
    /// slower speed and the larger weight. Avoiding only the nearest of two cells on either
    /// side flipped the turn whenever the nearest changed sides; the sum changes continuously,
    /// and in a gap it centres the robot.
    pub fn step_sides(
        &mut self,
        perception: &Perception,
        other: Option<&Obstacle>,
        ahead: Option<Ahead>,
        goal: &Goal,
        dt: f64,
    ) -> Result<MofisOutput, MofisError> {
        self.step_guarded(perception, other, ahead, goal, dt, None)
    }

    /// [`Mofis::step_sides`] with the footprint guard ([`MofisParams::guard_evidence`]):
    /// `arc_free(curvature, reach, aside)` is how far the robot can drive along an arc of that
    /// curvature (1/m, + = left) before its footprint meets something, up to `reach` m,
    /// counting only what is out of the camera's view when `aside`
    /// ([`memory::ObstacleMemory::arc_free`]).
    pub fn step_guarded(
        &mut self,
        perception: &Perception,
        other: Option<&Obstacle>,
        ahead: Option<Ahead>,
        goal: &Goal,
        dt: f64,
        arc_free: Option<&dyn Fn(f64, f64, bool) -> f64>,
    ) -> Result<MofisOutput, MofisError> {
        let mut inputs = self.inputs(perception);
        if let Some(f) = ahead.map(|a| a.front_m).filter(|f| f.is_finite()) {
            inputs[2] = f.clamp(0.0, self.params.sensing_range_m);
        }
        let [dist, mut bearing, front] = inputs;
        // A dead-ahead obstacle gives the symmetric rule base no side: pass it on the goal's
        // side, and keep that side while the obstacle stays in view (no dithering).
        if !perception.obstacle.present {
            self.pass_side = None;
        } else if bearing.abs() < self.params.dead_ahead_rad {
            let goal_side = if goal.angle_rad < 0.0 { -1.0 } else { 1.0 };
            let side = *self.pass_side.get_or_insert(goal_side);
            bearing = -side * self.params.dead_ahead_rad;
        }
        let (mut avoidance, mut weight) = self.avoid(dist, bearing, front)?;
        if let Some(o) = other.filter(|o| o.present && perception.obstacle.present) {
            let [d2, b2] = self.obstacle_inputs(o);
            let (second, w2) = self.avoid(d2, b2, front)?;
            // each side's share: its fusion weight over its distance, so that a far cell on one
            // side does not cancel a near one on the other
            let (a1, a2) = (weight / dist.max(0.1), w2 / d2.max(0.1));
            if a1 + a2 > 1e-9 {
                avoidance.turn = ((a1 * avoidance.turn + a2 * second.turn) / (a1 + a2)).clamp(-1.0, 1.0);
            }
            avoidance.speed = avoidance.speed.min(second.speed);
            weight = weight.max(w2);
        }
        // a turn on the spot (goal velocity 0) cannot run the round robot into anything: the
        // goal's turn alone
        if goal.velocity <= 0.0 {
            weight = 0.0;
        }

        let fused = if goal.status == GoalStatus::Active {
            let max_turn = self.limiter.limits().max_turn_rate;
            let goal_omega = (self.params.heading_gain * goal.angle_rad).clamp(-max_turn, max_turn);
            let omega = (1.0 - weight) * goal_omega + weight * avoidance.turn * max_turn;
            // backing off (stall recovery, the way it came): the camera sees nothing behind, so
            // avoidance has nothing to say about it
            let v = match goal.velocity < 0.0 {
                true => goal.velocity,
                false => {
                    let off = goal.angle_rad.abs().max(omega.abs() / self.params.heading_gain);
                    let cap = ahead.map_or(f64::INFINITY, |a| a.stop_speed_mps);
                    (goal.velocity * avoidance.speed * self.look_factor(off)).min(cap)
                }
            };
            BodyVelocity { v, omega }
        } else {
            BodyVelocity::ZERO
        };
        let fused = match arc_free {
            Some(free) if self.params.guard_evidence > 0.0 => self.guard(fused, free),
            _ => fused,
        };
        let setpoint = self.limiter.limit(fused, dt);
        Ok(MofisOutput { inputs, avoidance, weight, fused, setpoint })
    }
}

impl Mofis {
    /// How far ahead the footprint guard checks an arc driven at `v` m/s: `guard_horizon_s` of
    /// travel, then the distance to stop braking at `stop_decel_mps2`, m.
    fn guard_reach(&self, v: f64) -> f64 {
        v * self.params.guard_horizon_s + v * v / (2.0 * self.params.stop_decel_mps2)
    }

    /// The footprint guard ([`MofisParams::guard_evidence`]) on a command `cmd`: unchanged when
    /// its arc is clear for [`guard_reach`](Self::guard_reach); else, at the same speed, the
    /// turn rate nearest its own, among [`GUARD_TURNS`] fractions of the maximum and within
    /// `guard_max_bend` of it, whose arc is clear; else (with `guard_slow`) the same at the
    /// fastest of the [`GUARD_SLOWER`] speeds, where the same bend turns tighter and the reach
    /// is shorter; else (with `guard_brake`) the freest of those arcs at the full speed's
    /// reach, counting only the cells out of the camera's view, at the speed that stops short
    /// on it (unchanged when that arc is clear: what is in view is the stopping gate's); else
    /// unchanged. It never slows for what is in view alone: braking for every cell, down to a
    /// stop, left the robot standing in front of lingering phantom cells that nothing could
    /// clear (mean mission time 91 → 110–132 s on seeds 0..5; docs/missions-history.md).
    /// Turning on the spot and backing off pass: a round robot turning on the spot touches
    /// nothing, and backing off is the stall recovery's way out. `arc_free(curvature, reach,
    /// aside)` is [`memory::ObstacleMemory::arc_free`].
    fn guard(&self, cmd: BodyVelocity, arc_free: &dyn Fn(f64, f64, bool) -> f64) -> BodyVelocity {
        if cmd.v.is_nan() || cmd.v <= 0.0 {
            return cmd;
        }
        let reach = self.guard_reach(cmd.v);
        let free = arc_free(cmd.omega / cmd.v, reach, false);
        if free >= reach {
            return cmd;
        }
        let max_turn = self.limiter.limits().max_turn_rate;
        let bend = self.params.guard_max_bend;
        let mut turns: Vec<f64> =
            GUARD_TURNS.iter().map(|f| f * max_turn).filter(|w| (w - cmd.omega).abs() <= bend).collect();
        turns.sort_by(|a, b| (a - cmd.omega).abs().total_cmp(&(b - cmd.omega).abs()));
        // the nearest clear turn within the bend at the commanded speed, then (`guard_slow`) at
        // the fastest slower speed with one: slower, the same bend turns tighter and the
        // look-ahead is shorter
        let slower: &[f64] = if self.params.guard_slow { &GUARD_SLOWER } else { &[] };
        for frac in std::iter::once(1.0).chain(slower.iter().copied()) {
            let v = cmd.v * frac;
            let reach_v = self.guard_reach(v);
            if let Some(&omega) = turns.iter().find(|&&w| arc_free(w / v, reach_v, false) >= reach_v) {
                tracing::trace!(
                    target: "flownav::mofis::guard",
                    "{} v={:.2} w={:.2} -> v={v:.2} w={omega:.2}: free {free:.2} of {reach:.2} m",
                    if frac == 1.0 { "bend" } else { "slow" },
                    cmd.v,
                    cmd.omega
                );
                return BodyVelocity { v, omega };
            }
        }
        if self.params.guard_brake
            && let Some(braked) = self.guard_brake(cmd, &turns, reach, arc_free)
        {
            return braked;
        }
        // every candidate's free run, beyond the bend too: `turn:free/free out of view`, m
        if tracing::enabled!(target: "flownav::mofis::arcs", tracing::Level::TRACE) {
            let arcs: Vec<String> = GUARD_TURNS
                .iter()
                .map(|f| f * max_turn)
                .map(|w| {
                    format!("{w:.2}:{:.2}/{:.2}", arc_free(w / cmd.v, reach, false), arc_free(w / cmd.v, reach, true))
                })
                .collect();
            tracing::trace!(target: "flownav::mofis::arcs", "v={:.2} reach {reach:.2} m: {}", cmd.v, arcs.join(" "));
        }
        tracing::trace!(
            target: "flownav::mofis::guard",
            "blocked v={:.2} w={:.2}: free {free:.2} of {reach:.2} m, no clear turn within {bend:.2} rad/s",
            cmd.v,
            cmd.omega
        );
        cmd
    }

    /// The guard's brake (`guard_brake`) for a command `cmd` whose arcs at the candidate turn
    /// rates `turns` are all blocked within `reach`: counting only the cells out of the
    /// camera's view (what is in view and still there is seen again, and is the stopping
    /// gate's), the freest of those arcs (the command's own first, then the nearest turns; the
    /// first of equals wins), at the speed from which the robot stops short on it; `None`
    /// when that arc is clear.
    fn guard_brake(
        &self,
        cmd: BodyVelocity,
        turns: &[f64],
        reach: f64,
        arc_free: &dyn Fn(f64, f64, bool) -> f64,
    ) -> Option<BodyVelocity> {
        let (omega, most) = std::iter::once(cmd.omega)
            .chain(turns.iter().copied().filter(|&w| w != cmd.omega))
            .map(|w| (w, arc_free(w / cmd.v, reach, true)))
            .fold((cmd.omega, f64::NEG_INFINITY), |best, (w, f)| if f > best.1 + 1e-9 { (w, f) } else { best });
        if most >= reach {
            return None;
        }
        let v = cmd.v.min(stop_speed(most, self.params.stop_decel_mps2));
        tracing::trace!(
            target: "flownav::mofis::guard",
            "brake v={:.2} w={:.2} -> v={v:.2} w={omega:.2}: free {most:.2} of {reach:.2} m",
            cmd.v,
            cmd.omega
        );
        Some(BodyVelocity { v, omega })
    }
}

/// The slower speeds the footprint guard tries when no turn clears the arc, as fractions of the
/// commanded speed.
const GUARD_SLOWER: [f64; 4] = [0.7, 0.5, 0.35, 0.25];

/// The turn rates the footprint guard tries, as fractions of the maximum turn rate.
const GUARD_TURNS: [f64; 13] = [-1.0, -0.75, -0.5, -0.35, -0.2, -0.1, 0.0, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0];

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

/// The shipped rule bases, compiled in.
const BUILTIN_AVOIDANCE: &str = include_str!("../../rules/mofis/avoidance.toml");
const BUILTIN_FUSION: &str = include_str!("../../rules/mofis/fusion.toml");

/// Loads both rule bases from `dir` with default parameters (for tools and tests).
pub fn load_default(dir: impl AsRef<Path>, limits: ControlLimits) -> Result<Mofis, MofisError> {
    Mofis::load(MofisParams { rules_dir: Some(dir.as_ref().to_path_buf()), ..MofisParams::default() }, limits)
}
