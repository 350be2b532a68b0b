//! The per-frame step: frames and odometry in, perception and a set-point out.
//!
//! [`Pipeline::step`] is a pure, synchronous, deterministic function of (previous frame, frame,
//! odometry, state): no clocks, no I/O. `run`, `sim`, `analyze` and `replay` all call this one
//! function, so what is tested offline is what drives the robot, and replaying a log through it
//! reproduces the logged outputs bit for bit on the CPU backend.
//!
//! Order inside a step (paper Fig. 3): pairing (keyframe) → flow (frame pair) → OFFIS
//! (perception) → PAFSIS (goal velocity and angle, or a constant cruise goal without a mission)
//! → MOFIS (obstacle memory, manoeuvres, steering, avoidance, fusion, limiter) → set-point.
//! Before all of it, a frame from a lens with distortion is undistorted to the pinhole frame
//! with the calibration's K ([`hal::Undistorter`]); a pinhole calibration leaves it untouched.
//!
//! **Pairing (keyframes).** Depth from flow needs the camera to have moved: at 30 fps a robot at
//! 0.1 m/s moves 3 mm between frames, and the flow of a wall 2 m away is a tenth of a pixel,
//! below the matching noise. So each frame is paired with a *keyframe*, the older frame of the
//! pair, which is kept until the robot has driven `pairing.min_baseline_m` since it (or
//! `pairing.max_span_s` passed); then the newest frame becomes the keyframe. Every frame still
//! gets a step and a set-point; OFFIS gets the pair's whole interval and the odometry averaged
//! over it, MOFIS and PAFSIS the per-frame odometry. At cruise speed (0.35 m/s)
//! a keyframe lasts four frames, when creeping every frame of the last `max_span_s`.
//! 4 cm rather than 2: the radial flow per pair doubles for the same depth, so the matching
//! error is half as large a part of it (in the office sim, surface points within 15 % of the
//! true range went from about half to about three quarters with `memory.min_radial_px` 1.2).

use crate::config::Config;
use crate::flow::{self, BackendReport, FlowEngine, FlowError, FlowField};
use crate::mofis::memory::ObstacleMemory;
use crate::mofis::{Mofis, MofisError, MofisInput, MofisOutput, MofisStep, Route};
use crate::odometry_calibration::{OdometryCalibration, OdometryParams};
use crate::offis::features;
use crate::offis::points::SurfacePoint;
use crate::offis::temporal::Motion;
use crate::offis::{Attributes, Offis, OffisError};
use crate::pafsis::{Goal, GoalStatus, Mission, Pafsis, PlanError, TopoMap, WallSighting};
pub use crate::pairing::PairingParams;
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

/// The keyframe and the motion since it.
#[derive(Clone, Debug)]
struct Keyframe {
    frame: Frame,
    /// Capture time of the last frame stepped (for the per-frame interval), ns.
    last_ns: u64,
    /// Distance driven and yaw turned since the keyframe (odometry, the turn corrected by the
    /// learned errors and as the base reported it), m and rad.
    travel_m: f64,
    yaw_rad: f64,
    raw_yaw_rad: f64,
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
    /// PAFSIS's goal after MOFIS's manoeuvres (stall recovery, escape, spot turn).
    pub goal: Goal,
    /// `goal` after steering around remembered obstacles: what MOFIS's fuzzy core was given.
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

impl Navigator {
    /// The goal for this frame; `walls` are the straight walls OFFIS fitted in it.
    fn goal(&mut self, perception: &Perception, walls: &[WallSighting], odometry: BodyVelocity, frame_dt: f64) -> Goal {
        match self {
            Navigator::Mission(pafsis) => {
                pafsis.observe_walls(walls);
                pafsis.step(perception, odometry, frame_dt)
            }
            Navigator::Cruise(v) => Goal { velocity: *v, angle_rad: 0.0, status: GoalStatus::Active },
        }
    }

    /// What the plan says about the way (nothing when cruising).
    fn route(&self) -> Route {
        match self {
            Navigator::Mission(pafsis) => {
                Route { lane: pafsis.lane(), doorway: pafsis.doorway(), stop_ahead_m: pafsis.stop_ahead_m() }
            }
            Navigator::Cruise(_) => Route::default(),
        }
    }
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
    points: Vec<SurfacePoint>,
    /// The straight walls OFFIS fitted in the current frame, robot frame.
    walls: Vec<WallSighting>,
    pairing: PairingParams,
    key: Option<Keyframe>,
    odometry: OdometryParams,
    /// The odometry's turn errors learned from the flow ([`crate::odometry_calibration`]),
    /// and the ones the last step applied.
    calibration: OdometryCalibration,
    applied: [f64; 2],
}

impl Pipeline {
    /// Builds the pipeline from the configuration; `mission` (map + FROM:TO) enables PAFSIS,
    /// otherwise the robot cruises straight ahead at `pafsis.cruise_speed` while avoiding.
    pub fn new(cfg: &Config, calib: Calibration, mission: Option<(TopoMap, Mission)>) -> Result<Self, PipelineError> {
        let (flow, backend) = flow::create_engine(&cfg.flow)?;
        let mofis = Mofis::new(cfg.mofis.clone(), cfg.control.clone(), &calib)?;
        let navigator = match mission {
            Some((map, mission)) => Navigator::Mission(Box::new(Pafsis::new(map, mission, cfg.pafsis.clone())?)),
            None => Navigator::Cruise(cfg.pafsis.cruise_speed),
        };
        Ok(Self {
            calib,
            frame_calib: None,
            undistorter: None,
            undistorted: LumaImage::default(),
            points: Vec::new(),
            walls: Vec::new(),
            pairing: cfg.pairing,
            key: None,
            odometry: cfg.odometry,
            calibration: OdometryCalibration::default(),
            applied: [0.0; 2],
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

    /// The odometry's turn errors learned so far from the flow.
    pub fn odometry_calibration(&self) -> &OdometryCalibration {
        &self.calibration
    }

    /// The turn scale error and bend (rad/m) the last step took out of its odometry (zeros when
    /// `[odometry] learn` is off); logged with each step for replay.
    pub fn applied_calibration(&self) -> [f64; 2] {
        self.applied
    }

    /// Makes the next step take these errors out of its odometry, as a logged step did
    /// (replay; the fit goes on learning from there).
    pub fn set_odometry_calibration(&mut self, scale: f64, bend_rad_m: f64) {
        self.calibration.set_fit(scale, bend_rad_m);
    }

    /// The MOFIS stage.
    pub fn mofis(&self) -> &Mofis {
        &self.mofis
    }

    /// MOFIS's obstacle memory.
    pub fn memory(&self) -> &ObstacleMemory {
        self.mofis.memory()
    }

    /// How many times the robot found itself pushing against something and turned away
    /// ([`crate::mofis::stall`]).
    pub fn stall_recoveries(&self) -> u32 {
        self.mofis.stall_recoveries()
    }

    /// How many times the robot stood still too long and turned to a free heading
    /// ([`crate::mofis::escape`]).
    pub fn escapes(&self) -> u32 {
        self.mofis.escapes()
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
        self.mofis.fail_safe()
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
        let raw = odometry;
        // everything downstream sees the turn with the learned errors taken out
        let cal = &self.calibration;
        self.applied = if self.odometry.learn { [cal.scale(), cal.bend_rad_m()] } else { [0.0; 2] };
        let odometry = if self.odometry.learn { cal.apply(raw) } else { raw };
        if odometry.v.is_finite() && odometry.omega.is_finite() {
            key.travel_m += odometry.v * frame_dt;
            key.yaw_rad += odometry.omega * frame_dt;
            key.raw_yaw_rad += raw.omega * frame_dt;
            if let Some(last) = key.last_omega {
                key.turn_change = key.turn_change.max((odometry.omega - last).abs());
            }
            key.last_omega = Some(odometry.omega);
        }
        let dt = (frame.t_ns - key.frame.t_ns) as f64 * 1e-9;
        // the pair's motion as one constant velocity over its interval
        let span = BodyVelocity::new(key.travel_m / dt, key.yaw_rad / dt);
        let flow = self.turn.flow(self.flow.as_mut(), &key.frame.image, &frame.image, &calib, span, dt)?;
        // the TPO is decided over the last steps: OFFIS needs the motion since its previous step
        let since = Motion { yaw_rad: odometry.omega * frame_dt, dt: frame_dt, forward_m: odometry.v * frame_dt };
        let perception = self.offis.step_filtered(&flow, span, dt, &calib, since)?;
        let measured = self.mofis.measurable(span, dt, key.turn_change);
        let (seq, t_ns) = (frame.seq, frame.t_ns);
        if key.travel_m.abs() >= self.pairing.min_baseline_m || dt >= self.pairing.max_span_s {
            // Consecutive keyframe pairs tile the drive, so the yaw their flow measures adds up
            // to the camera's turn; the pairs in between overlap them and would count it twice.
            let odo = self.odometry;
            if let Some(residual) =
                self.offis.measure_yaw(&flow, span, dt, &calib).filter(|r| odo.admits(*r, key.yaw_rad))
            {
                if odo.learn {
                    let (turn, drive) = (key.raw_yaw_rad, key.travel_m);
                    self.calibration.observe(turn, drive, residual + self.calibration.correction(turn, drive));
                }
                if let Navigator::Mission(pafsis) = &mut self.navigator {
                    pafsis.correct_heading(odo.heading_gain * residual);
                }
            }
            *key = Keyframe {
                frame,
                last_ns: t_ns,
                travel_m: 0.0,
                yaw_rad: 0.0,
                raw_yaw_rad: 0.0,
                turn_change: 0.0,
                last_omega: Some(odometry.omega),
            };
        }
        wall_sightings(self.offis.attributes(), [calib.mount.x_m, calib.mount.y_m], &mut self.walls);
        let goal = self.navigator.goal(&perception, &self.walls, odometry, frame_dt);
        // the solid surface points, filtered as MOFIS's obstacle memory takes them in
        let (m, mp) = (&calib.mount, self.mofis.memory().params());
        let (min_radial, max_tangential) = (mp.min_radial_px, mp.max_tangential);
        self.offis.surface_points([m.x_m, m.y_m, m.z_m], min_radial, max_tangential, &mut self.points);
        let route = self.navigator.route();
        let input =
            MofisInput { perception: &perception, points: &self.points, measured, odometry, dt: frame_dt, goal, route };
        let MofisStep { avoided, goal, steered, output: mofis } = self.mofis.step(input)?;
        Ok(Some(StepOutput { seq, t_ns, dt, prev_t_ns, flow, perception, avoided, goal, steered, mofis }))
    }

    /// The frame becomes the keyframe, with no motion since it.
    fn prime(&mut self, frame: Frame) {
        let last_ns = frame.t_ns;
        self.key = Some(Keyframe {
            frame,
            last_ns,
            travel_m: 0.0,
            yaw_rad: 0.0,
            raw_yaw_rad: 0.0,
            turn_change: 0.0,
            last_omega: None,
        });
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

/// OFFIS's fitted planes as walls in the robot's frame, with their openings, written into
/// `out` (reused from frame to frame): the fit is made from the camera, which sits at the
/// mount's offset from the robot's reference point.
fn wall_sightings(attributes: &Attributes, mount_m: [f64; 2], out: &mut Vec<WallSighting>) {
    let shift = |p: [f64; 2]| [p[0] + mount_m[0], p[1] + mount_m[1]];
    let (model, bins) = (&attributes.model, &attributes.bins);
    out.clear();
    out.extend(model.planes().map(|l| {
        // the two nearest, nearest first
        let mut openings: [Option<(f64, [[f64; 2]; 2])>; 2] = [None; 2];
        for o in features::openings(bins, l, model.occluded) {
            let [a, b] = o.jambs_m;
            let opening = (0.5 * (a[0] + b[0])).hypot(0.5 * (a[1] + b[1]));
            let here = (opening, o.jambs_m.map(shift));
            match openings {
                [None, _] => openings[0] = Some(here),
                [Some((r, _)), _] if opening < r => openings = [Some(here), openings[0]],
                [_, None] => openings[1] = Some(here),
                [_, Some((r, _))] if opening < r => openings[1] = Some(here),
                _ => {}
            }
        }
        let openings = openings.map(|o| o.map(|(_, jambs)| jambs));
        WallSighting { point_m: shift(l.centre), dir: l.dir, length_m: l.extent[1] - l.extent[0], openings }
    }));
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
