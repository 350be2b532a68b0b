//! The fuzzy core of MOFIS (§2.2): the avoidance rule base, its fusion with the goal orientation,
//! the footprint guard ([`guard`](super::guard)) and the safety limiter that turns the fused command into
//! the set-point.
//!
//! ```text
//! v     = goal_velocity · speed
//! omega = (1 − weight) · heading_gain · goal_angle + weight · turn · max_turn_rate
//! ```

use super::{MofisError, MofisParams};
use crate::control::{ControlLimits, Limiter};
use crate::fuzzy::{Evaluation, FuzzySystem, InputId, OutputId};
use crate::pafsis::{Goal, GoalStatus};
use crate::perception::{Obstacle, Perception, TpoShape};
use hal::BodyVelocity;
use serde::Serialize;
use std::path::{Path, PathBuf};

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

/// The way ahead as the obstacle memory has it ([`Fusion::step_sides`]).
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
pub struct Fusion {
    pub(super) params: MofisParams,
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
    pub(super) limiter: Limiter,
    /// The side (+1 left, −1 right) chosen to pass the current dead-ahead obstacle.
    pass_side: Option<f64>,
}

impl Fusion {
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

    /// [`Fusion::step`] with a second obstacle on the other side of the heading and the distance
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

    /// [`Fusion::step_sides`] with the footprint guard ([`MofisParams::guard_evidence`]):
    /// `arc_free(curvature, reach, aside)` is how far the robot can drive along an arc of that
    /// curvature (1/m, + = left) before its footprint meets something, up to `reach` m,
    /// counting only what is out of the camera's view when `aside`
    /// ([`ObstacleMemory::arc_free`](super::memory::ObstacleMemory::arc_free)).
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
                    // slowed by the cosine of the steered angle: what is left of the speed
                    // along the heading the robot turns to (the goal's, or the way's)
                    let along = goal.angle_rad.cos().max(0.0);
                    (goal.velocity * along * avoidance.speed * self.look_factor(off)).min(cap)
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

/// The shipped rule bases, compiled in.
const BUILTIN_AVOIDANCE: &str = include_str!("../../rules/mofis/avoidance.toml");
const BUILTIN_FUSION: &str = include_str!("../../rules/mofis/fusion.toml");

/// Loads both rule bases from `dir` with default parameters (for tools and tests).
pub fn load_default(dir: impl AsRef<Path>, limits: ControlLimits) -> Result<Fusion, MofisError> {
    Fusion::load(MofisParams { rules_dir: Some(dir.as_ref().to_path_buf()), ..MofisParams::default() }, limits)
}
