//! The per-frame step: frames and odometry in, perception and a set-point out.
//!
//! [`Pipeline::step`] is a pure, synchronous, deterministic function of (previous frame, frame,
//! odometry, state): no clocks, no I/O. `run`, `sim`, `analyze` and `replay` all call this one
//! function, so what is tested offline is what drives the robot, and replaying a log through it
//! reproduces the logged outputs bit for bit on the CPU backend.
//!
//! Order inside a step (paper Fig. 3): flow (frame pair) → OFFIS (perception) → obstacle memory
//! → PAFSIS (goal velocity and angle, or a constant cruise goal without a mission) → free-heading
//! steering → MOFIS (avoidance, fusion, limiter) → set-point.
//! Before all of it, a frame from a lens with distortion is undistorted to the pinhole frame
//! with the calibration's K ([`hal::Undistorter`]); a pinhole calibration leaves it untouched.
//!
//! **Pairing (keyframes).** Depth from flow needs the camera to have moved: at 30 fps a robot at
//! 0.1 m/s moves 3 mm between frames, and the flow of a wall 2 m away is a tenth of a pixel,
//! below the matching noise. So each frame is paired with a *keyframe*, the older frame of the
//! pair, which is kept until the robot has driven `pairing.min_baseline_m` since it (or
//! `pairing.max_span_s` passed); then the newest frame becomes the keyframe. Every frame still
//! gets a step and a set-point; OFFIS gets the pair's whole interval and the odometry averaged
//! over it, the obstacle memory and PAFSIS the per-frame odometry. At cruise speed (0.35 m/s)
//! a keyframe lasts four frames, when creeping every frame of the last `max_span_s`.
//! 4 cm rather than 2: the radial flow per pair doubles for the same depth, so the matching
//! error is half as large a part of it (in the office sim, surface points within 15 % of the
//! true range went from about half to about three quarters with `memory.min_radial_px` 1.2).

use crate::config::Config;
use crate::flow::{self, BackendReport, FlowEngine, FlowError, FlowField};
use crate::mofis::escape::Escape;
use crate::mofis::memory::ObstacleMemory;
use crate::mofis::stall::{Manoeuvre, StallRecovery};
use crate::mofis::{Ahead, Mofis, MofisError, MofisOutput, SpotTurn, stop_speed};
use crate::offis::points::SurfacePoint;
use crate::offis::temporal::Motion;
use crate::offis::{Offis, OffisError};
use crate::pafsis::{Goal, GoalStatus, Mission, Pafsis, PlanError, TopoMap};
use crate::perception::{Obstacle, Perception};
use crate::rotation::TurnCompensation;
use hal::{BodyVelocity, Calibration, Frame, LumaImage, Undistorter};

#[derive(Debug, thiserror::Error)]
pub enum StepError {
    #[error("optical flow failed: {0}")]
    Flow(#[from] FlowError),
    #[error("OFFIS failed: {0}")]
    Offis(#[from] OffisError),
    #[error("MOFIS failed: {0}")]
    Mofis(#[from] MofisError),
    #[error(
        "frame {seq} is not newer than the previous frame (t {t_ns} ns after {prev_ns} ns): timestamps must increase"
    )]
    Time { seq: u64, t_ns: u64, prev_ns: u64 },
    #[error("cannot undo the lens distortion: {0}")]
    Undistort(#[from] hal::UndistortError),
}

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(transparent)]
    Flow(#[from] FlowError),
    #[error(transparent)]
    Mofis(#[from] MofisError),
    #[error(transparent)]
    Plan(#[from] PlanError),
    #[error(transparent)]
    Offis(#[from] crate::offis::ClassifyError),
}

/// Steering around remembered obstacles ([`ObstacleMemory::steer`]): the path must be free
/// this far, m; candidate headings within this angle of the robot's heading, in these steps, rad.
const STEER_LOOKAHEAD_M: f64 = 1.5;
const STEER_MAX_RAD: f64 = 0.7;
const STEER_STEP_RAD: f64 = 0.05;
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

/// The `[pairing]` config table: how far back the older frame of each pair lies.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PairingParams {
    /// The keyframe is replaced once the robot has driven this far since it, m (0: pair
    /// consecutive frames, as the paper does).
    pub min_baseline_m: f64,
    /// ... or once it is this old, s.
    pub max_span_s: f64,
}

impl Default for PairingParams {
    fn default() -> Self {
        Self { min_baseline_m: 0.04, max_span_s: 0.4 }
    }
}

impl PairingParams {
    pub fn validate(&self) -> Result<(), crate::config::ConfigError> {
        let bad = |field: &str, problem: &str| {
            Err(crate::config::ConfigError::Invalid { field: format!("pairing.{field}"), problem: problem.into() })
        };
        if !(self.min_baseline_m.is_finite() && (0.0..=0.5).contains(&self.min_baseline_m)) {
            return bad("min_baseline_m", "must be in [0, 0.5] m");
        }
        if !(self.max_span_s.is_finite() && self.max_span_s > 0.0 && self.max_span_s <= 5.0) {
            return bad("max_span_s", "must be in (0, 5] s");
        }
        Ok(())
    }
}

/// The keyframe and the motion since it.
#[derive(Clone, Debug)]
struct Keyframe {
    frame: Frame,
    /// Capture time of the last frame stepped (for the per-frame interval), ns.
    last_ns: u64,
    /// Distance driven and yaw turned since the keyframe (odometry), m and rad.
    travel_m: f64,
    yaw_rad: f64,
    /// Largest change of the measured turn rate between two steps since the keyframe, rad/s.
    turn_change: f64,
    /// The turn rate of the last step (`None` for a priming frame: its odometry is not used,
    /// so a replay that primes with zero velocity computes the same).
    last_omega: Option<f64>,
}

/// What one step produced (the newer frame of the pair is `seq`, captured at `t_ns`).
#[derive(Clone, Debug)]
pub struct StepOutput {
    pub seq: u64,
    pub t_ns: u64,
    /// Interval of the pair (keyframe to this frame), s.
    pub dt: f64,
    /// Capture time of the frame stepped before this one, ns (the keyframe or a later frame).
    pub prev_t_ns: u64,
    pub flow: FlowField,
    pub perception: Perception,
    /// The obstacle MOFIS avoided: the nearer of the obstacle memory's threats on either side
    /// (solid things in or beside the robot's path, remembered over frames), not this frame's
    /// OFFIS obstacle. The other side's threat is avoided too (its share is in
    /// `mofis.avoidance`) but not kept here.
    pub avoided: Obstacle,
    pub goal: Goal,
    /// `goal` after steering around remembered obstacles: what MOFIS was given.
    pub steered: Goal,
    pub mofis: MofisOutput,
}

impl StepOutput {
    /// The set-point to send to the base.
    pub fn setpoint(&self) -> BodyVelocity {
        self.mofis.setpoint
    }
}

/// Where the goal comes from.
enum Navigator {
    /// PAFSIS on a topological map with a mission.
    Mission(Box<Pafsis>),
    /// No mission (`analyze`, `run` without a map): go straight ahead at this speed, avoiding.
    Cruise(f64),
}

/// The per-frame pipeline and its state.
pub struct Pipeline {
    calib: Calibration,
    /// `calib` scaled to the frame size actually received (set on the first frame).
    frame_calib: Option<Calibration>,
    /// The frame size and the undistorter for it (`None` inside for a pinhole lens), built on
    /// the first frame of each size; and the buffer it writes into.
    undistorter: Option<((usize, usize), Option<Undistorter>)>,
    undistorted: LumaImage,
    flow: Box<dyn FlowEngine>,
    /// Centres the block search on the turn ([`crate::rotation`]).
    turn: TurnCompensation,
    backend: BackendReport,
    offis: Offis,
    navigator: Navigator,
    mofis: Mofis,
    memory: ObstacleMemory,
    points: Vec<SurfacePoint>,
    pairing: PairingParams,
    key: Option<Keyframe>,
    /// MOFIS's sensing range (the free path is measured up to it), m.
    mofis_range: f64,
    stall: StallRecovery,
    /// The set-point of the previous step (what the odometry of this step should show).
    last_setpoint: BodyVelocity,
    spot_turn: SpotTurn,
    escape: Escape,
    /// The stopping gate's margin, m, and deceleration, m/s² ([`crate::mofis::Ahead`]).
    stop_gate: (f64, f64),
    /// The footprint guard's clearance (m) and evidence ([`crate::mofis::MofisParams::guard_evidence`]).
    guard: (f64, f64),
}

impl Pipeline {
    /// Builds the pipeline from the configuration; `mission` (map + FROM:TO) enables PAFSIS,
    /// otherwise the robot cruises straight ahead at `pafsis.cruise_speed` while avoiding.
    pub fn new(cfg: &Config, calib: Calibration, mission: Option<(TopoMap, Mission)>) -> Result<Self, PipelineError> {
        let (flow, backend) = flow::create_engine(&cfg.flow)?;
        let mofis = Mofis::load(cfg.mofis.clone(), cfg.control.clone())?;
        let navigator = match mission {
            Some((map, mission)) => Navigator::Mission(Box::new(Pafsis::new(map, mission, cfg.pafsis.clone())?)),
            None => Navigator::Cruise(cfg.pafsis.cruise_speed),
        };
        let half_fov = ((calib.camera.width as f64 / 2.0) / calib.camera.fx).atan();
        let memory = ObstacleMemory::new(cfg.mofis.memory, half_fov, calib.mount.z_m);
        Ok(Self {
            calib,
            frame_calib: None,
            undistorter: None,
            undistorted: LumaImage::default(),
            memory,
            points: Vec::new(),
            pairing: cfg.pairing,
            key: None,
            mofis_range: cfg.mofis.sensing_range_m,
            stall: StallRecovery::new(cfg.mofis.stall, cfg.control.max_reverse_speed > 0.0),
            last_setpoint: BodyVelocity::ZERO,
            spot_turn: SpotTurn::new(&cfg.mofis),
            escape: Escape::new(cfg.mofis.escape),
            stop_gate: (cfg.mofis.stop_margin_m, cfg.mofis.stop_decel_mps2),
            guard: (cfg.mofis.guard_clearance_m, cfg.mofis.guard_evidence),
            flow,
            turn: TurnCompensation::default(),
            backend,
            offis: Offis::new(cfg.offis.clone())?,
            navigator,
            mofis,
        })
    }

    /// Which flow engine runs, and why.
    pub fn backend(&self) -> &BackendReport {
        &self.backend
    }

    /// The OFFIS stage (its `attributes()` hold the matrices of the last step, for logging).
    pub fn offis(&self) -> &Offis {
        &self.offis
    }

    /// The solid surface points of the last step, robot frame (what the obstacle memory took in
    /// when the step was measurable).
    pub fn surface_points(&self) -> &[SurfacePoint] {
        &self.points
    }

    /// The obstacle memory.
    pub fn memory(&self) -> &ObstacleMemory {
        &self.memory
    }

    /// How many times the robot found itself pushing against something and turned away
    /// ([`crate::mofis::stall`]).
    pub fn stall_recoveries(&self) -> u32 {
        self.stall.recoveries()
    }

    /// How many times the robot stood still too long and turned to a free heading
    /// ([`crate::mofis::escape`]).
    pub fn escapes(&self) -> u32 {
        self.escape.escapes()
    }

    /// The PAFSIS planner, when running a mission.
    pub fn pafsis(&self) -> Option<&Pafsis> {
        match &self.navigator {
            Navigator::Mission(p) => Some(p),
            Navigator::Cruise(_) => None,
        }
    }

    pub fn pafsis_mut(&mut self) -> Option<&mut Pafsis> {
        match &mut self.navigator {
            Navigator::Mission(p) => Some(p),
            Navigator::Cruise(_) => None,
        }
    }

    /// The calibration in use for the current frame size.
    pub fn calibration(&self) -> &Calibration {
        self.frame_calib.as_ref().unwrap_or(&self.calib)
    }

    /// A zero set-point through the limiter's stop path (for stalls and failures); also forgets
    /// the previous frame so the next pair does not span the gap.
    pub fn fail_safe(&mut self) -> BodyVelocity {
        self.key = None;
        self.offis.reset_filter();
        self.memory.clear();
        self.stall.reset();
        self.escape.reset();
        self.spot_turn.reset();
        self.last_setpoint = BodyVelocity::ZERO;
        self.mofis.fallback()
    }

    /// One step. The first frame only primes the pipeline (`Ok(None)`); each later frame gives
    /// the flow from the previous frame to it, the perception, the goal and the set-point.
    /// On error the caller must command a stop (see [`Pipeline::fail_safe`]); the frame still
    /// becomes the previous frame so the next pair can succeed.
    pub fn step(&mut self, frame: Frame, odometry: BodyVelocity) -> Result<Option<StepOutput>, StepError> {
        let calib = self.calib_for(&frame);
        let frame = self.undistort(frame, &calib)?;
        let Some(key) = &mut self.key else {
            self.prime(frame);
            return Ok(None);
        };
        if frame.t_ns <= key.last_ns {
            let err = StepError::Time { seq: frame.seq, t_ns: frame.t_ns, prev_ns: key.last_ns };
            // the frame still becomes the start of the next pair
            self.prime(frame);
            return Err(err);
        }
        let prev_t_ns = key.last_ns;
        let frame_dt = (frame.t_ns - prev_t_ns) as f64 * 1e-9;
        key.last_ns = frame.t_ns;
        if odometry.v.is_finite() && odometry.omega.is_finite() {
            key.travel_m += odometry.v * frame_dt;
            key.yaw_rad += odometry.omega * frame_dt;
            if let Some(last) = key.last_omega {
                key.turn_change = key.turn_change.max((odometry.omega - last).abs());
            }
            key.last_omega = Some(odometry.omega);
        }
        let dt = (frame.t_ns - key.frame.t_ns) as f64 * 1e-9;
        // the pair's motion as one constant velocity over its interval
        let span = BodyVelocity::new(key.travel_m / dt, key.yaw_rad / dt);
        let flow = self.turn.flow(self.flow.as_mut(), &key.frame.image, &frame.image, &calib, span, dt)?;
        // the TPO is decided over the last steps: OFFIS needs the turn since its previous step
        let since = Motion { yaw_rad: odometry.omega * frame_dt, dt: frame_dt };
        let perception = self.offis.step_filtered(&flow, span, dt, &calib, since)?;
        let measured = self.memory.measurable(span, dt, key.turn_change);
        let (seq, t_ns) = (frame.seq, frame.t_ns);
        if key.travel_m.abs() >= self.pairing.min_baseline_m || dt >= self.pairing.max_span_s {
            *key = Keyframe {
                frame,
                last_ns: t_ns,
                travel_m: 0.0,
                yaw_rad: 0.0,
                turn_change: 0.0,
                last_omega: Some(odometry.omega),
            };
        }
        let goal = match &mut self.navigator {
            Navigator::Mission(pafsis) => pafsis.step(&perception, odometry, frame_dt),
            Navigator::Cruise(v) => Goal { velocity: *v, angle_rad: 0.0, status: GoalStatus::Active },
        };
        let m = &calib.mount;
        let mp = *self.memory.params();
        let (min_radial, max_tangential) = (mp.min_radial_px, mp.max_tangential);
        self.offis.surface_points([m.x_m, m.y_m, m.z_m], min_radial, max_tangential, &mut self.points);
        self.memory.update(odometry, frame_dt, &self.points, measured);
        // the corridor from the map: for the memory's queries, the escape and the steering
        self.memory.set_lane(self.pafsis().and_then(Pafsis::lane));
        self.memory.set_doorway(self.pafsis().and_then(Pafsis::doorway));
        // where the plan stops the robot (before a turn, at the goal): nothing beyond is in its way
        let stop_ahead = match &self.navigator {
            Navigator::Mission(pafsis) => pafsis.stop_ahead_m(),
            Navigator::Cruise(_) => None,
        };
        let stop_ahead = stop_ahead.unwrap_or(f64::INFINITY);
        self.memory.set_stop(stop_ahead);
        let horizon = self.memory.horizon(stop_ahead);
        // the nearest threat, and the nearest on the other side of the heading: MOFIS avoids both
        let (avoided, other) = crate::mofis::memory::nearer(self.memory.threat_sides(stop_ahead));
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
                self.escape.apply(goal, yaw, odometry.v * frame_dt, frame_dt, |h| memory.free_in_lane(h, look))
            }
            Some(_) => goal,
        };
        // a goal far off the heading is turned to on the spot first
        let memory = &self.memory;
        let goal = self.spot_turn.apply(goal, || memory.free_distance(goal.angle_rad, lookahead) >= lookahead);
        // turns on the spot keep their angle; driving picks a free heading
        let steered = match goal.velocity > 0.0 {
            true => {
                let centred = goal.angle_rad
                    + self.memory.centring(CENTRE_WINDOW_M, CENTRE_REACH_M, CENTRE_LOOKAHEAD_M, CENTRE_MAX_RAD);
                let angle_rad = self.memory.steer(centred, lookahead, STEER_MAX_RAD, STEER_STEP_RAD);
                Goal { angle_rad, ..goal }
            }
            false => goal,
        };
        // the distance ahead: the free path along the heading in the memory (the TPO's wall
        // distance is one frame's guess; the memory has what was seen solid, over frames), and
        // nothing there (the sensing range) when the path is free up to where the robot stops
        let free = self.memory.free_distance(0.0, self.mofis_range);
        let front = match free >= horizon {
            true => self.mofis_range,
            false => free - mp.robot_radius_m,
        };
        // the stopping gate: never faster than the robot can stop short of what is in its way
        let (margin, decel) = self.stop_gate;
        let in_way = self.memory.free_width(0.0, mp.robot_radius_m + margin, STOP_LOOKAHEAD_M);
        // and short of the door's wall, from the map, when going through a door
        let door = self.memory.door_free_ahead(STOP_LOOKAHEAD_M);
        let stop_speed_mps = stop_speed(in_way - mp.robot_radius_m - margin, decel).min(stop_speed(door, decel));
        let ahead = Ahead { front_m: front.max(0.0), stop_speed_mps };
        let view = Perception { obstacle: avoided, ..perception.clone() };
        // the footprint guard: the arcs against every remembered cell, faded ones included
        let (memory, guard) = (&self.memory, self.guard);
        let arc_free =
            move |curvature: f64, reach: f64, aside: bool| memory.arc_free(curvature, reach, guard.0, guard.1, aside);
        let mofis = self.mofis.step_guarded(&view, other.as_ref(), Some(ahead), &steered, frame_dt, Some(&arc_free))?;
        self.last_setpoint = mofis.setpoint;
        match turn_away {
            None => self.escape.observe(&goal, mofis.setpoint.v, frame_dt),
            Some(_) => self.escape.reset_standstill(),
        }
        Ok(Some(StepOutput { seq, t_ns, dt, prev_t_ns, flow, perception, avoided, goal, steered, mofis }))
    }

    /// The frame becomes the keyframe, with no motion since it.
    fn prime(&mut self, frame: Frame) {
        let last_ns = frame.t_ns;
        self.key = Some(Keyframe { frame, last_ns, travel_m: 0.0, yaw_rad: 0.0, turn_change: 0.0, last_omega: None });
    }

    /// The frame with its lens distortion undone ([`hal::undistort`]): the pinhole image with the
    /// calibration's K that the rest of the step assumes. A pinhole calibration (all distortion
    /// coefficients zero) returns the frame untouched.
    fn undistort(&mut self, mut frame: Frame, calib: &Calibration) -> Result<Frame, StepError> {
        let size = (frame.image.width(), frame.image.height());
        if self.undistorter.as_ref().is_none_or(|(built, _)| *built != size) {
            self.undistorter = Some((size, Undistorter::new(calib)?));
        }
        if let Some((_, Some(undistorter))) = &self.undistorter {
            undistorter.apply(&frame.image, &mut self.undistorted)?;
            std::mem::swap(&mut frame.image, &mut self.undistorted);
        }
        Ok(frame)
    }

    fn calib_for(&mut self, frame: &Frame) -> Calibration {
        let (w, h) = (frame.image.width() as u32, frame.image.height() as u32);
        match &self.frame_calib {
            Some(c) if c.camera.width == w && c.camera.height == h => c.clone(),
            _ => {
                let c = &self.calib.camera;
                if c.width != w || c.height != h {
                    tracing::warn!(
                        "frames are {w}x{h} but the calibration is for {}x{}: scaling the intrinsics",
                        c.width,
                        c.height
                    );
                }
                let scaled = self.calib.scaled_to(w, h);
                self.frame_calib = Some(scaled.clone());
                scaled
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flow::Backend;

    /// A textured frame shifted right by `shift` pixels (deterministic noise, smoothed).
    fn frame(seq: u64, t_ns: u64, shift: usize) -> Frame {
        let (w, h) = (320, 180);
        let mut data = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let u = (x + 400 - shift) as u64;
                let hash =
                    (u / 3).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ ((y as u64) / 3).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
                data[y * w + x] = (hash >> 56) as u8;
            }
        }
        Frame { seq, t_ns, image: LumaImage::from_vec(w, h, data).unwrap() }
    }

    fn pipeline() -> Pipeline {
        let mut cfg = Config::default();
        cfg.flow.backend = Backend::Cpu;
        let calib = hal::Calibration::nominal_c310();
        Pipeline::new(&cfg, calib, None).unwrap()
    }

    const FRAME_NS: u64 = 33_333_334;

    #[test]
    fn the_keyframe_is_kept_until_the_robot_has_driven_the_baseline() {
        let mut p = pipeline();
        let drive = BodyVelocity::new(0.33, 0.0); // 11 mm per frame: a new keyframe every 4th frame
        assert!(p.step(frame(0, 0, 0), drive).unwrap().is_none(), "the first frame primes");
        let dts: Vec<u64> = (1..=5u64)
            .map(|k| {
                let out = p.step(frame(k, k * FRAME_NS, 0), drive).unwrap().unwrap();
                assert_eq!(out.seq, k);
                (out.dt / (FRAME_NS as f64 * 1e-9)).round() as u64
            })
            .collect();
        assert_eq!(dts, [1, 2, 3, 4, 1], "pairs (0,1) (0,2) (0,3) (0,4) (4,5): 44 mm ≥ 40 mm at frame 4");
        // standing still: the keyframe (frame 4) ages out after max_span_s = 0.4 s (12 frames)
        let still = BodyVelocity::ZERO;
        let dts: Vec<u64> = (6..=19u64)
            .map(|k| {
                let out = p.step(frame(k, k * FRAME_NS, 0), still).unwrap().unwrap();
                (out.dt / (FRAME_NS as f64 * 1e-9)).round() as u64
            })
            .collect();
        assert_eq!(dts, [2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 1, 2, 3]);
    }

    #[test]
    fn consecutive_pairs_with_a_zero_baseline_and_the_flow_of_the_pair() {
        let mut cfg = Config::default();
        cfg.flow.backend = Backend::Cpu;
        cfg.pairing.min_baseline_m = 0.0;
        let mut p = Pipeline::new(&cfg, hal::Calibration::nominal_c310(), None).unwrap();
        let drive = BodyVelocity::new(0.33, 0.0);
        p.step(frame(0, 0, 0), drive).unwrap();
        let out = p.step(frame(1, FRAME_NS, 2), drive).unwrap().unwrap();
        assert!((out.dt - FRAME_NS as f64 * 1e-9).abs() < 1e-12);
        // the image moved 2 px right between the frames: the flow says so
        let inner: Vec<_> = out.flow.vectors.iter().filter(|v| v.valid()).collect();
        assert!(!inner.is_empty());
        let exact = inner.iter().filter(|v| (v.u - 2.0).abs() < 0.2 && v.v.abs() < 0.2).count();
        assert!(exact * 10 >= inner.len() * 9, "{exact} of {} vectors at (2, 0)", inner.len());
    }

    #[test]
    fn a_frame_that_is_not_newer_is_an_error_and_starts_the_next_pair() {
        let mut p = pipeline();
        let drive = BodyVelocity::new(0.33, 0.0);
        p.step(frame(0, 0, 0), drive).unwrap();
        p.step(frame(1, FRAME_NS, 0), drive).unwrap();
        assert!(matches!(p.step(frame(2, FRAME_NS, 0), drive), Err(StepError::Time { seq: 2, .. })));
        let out = p.step(frame(3, 2 * FRAME_NS, 0), drive).unwrap().unwrap();
        assert!((out.dt - FRAME_NS as f64 * 1e-9).abs() < 1e-12, "the rejected frame starts the next pair");
    }
}
