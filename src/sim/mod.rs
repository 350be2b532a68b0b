//! The closed-loop simulation behind `flownav sim`: the control loop of `flownav run`
//! ([`ControlLoop`]: frame slot, step, set-point expiry, fail-safe) between a rendered camera
//! (`mocks::RenderedCamera`, a `hal::Camera`) and a simulated FNP/1 base reached over a
//! pseudo-terminal, on simulated time.
//!
//! One control tick of `dt = 1/fps` of simulated time:
//!
//! ```text
//! SimServer::advance(dt) ─▶ ODOM/STATUS bytes on the pty ─▶ FnpBase (real driver) ─▶ ControlLoop::on_odometry
//!        │ true pose                                                                    │
//!        ▼                                                                              ▼
//! RenderedCamera::capture ─▶ Frame { seq, t_ns = sim time } ─▶ ControlLoop::on_frame(frame, now = sim time)
//!   (no frame: ControlLoop::on_tick(now): refresh, stall, expiry)    (slot → Stepper → Setpoints) ─▶ set-point
//!                                                                                       │
//! FnpBase::set_velocity ─▶ SETPOINT bytes on the pty ─▶ SimBase applies it ◀────────────┘ (waited for)
//! ```
//!
//! `flownav run` spreads the same [`ControlLoop`] parts over its camera thread, step thread and
//! control task on the monotonic clock (see [`crate::runtime`]); here they run in order on one
//! task with the clock injected, which keeps a run deterministic. A step takes no simulated time,
//! so no frame is ever stale in the slot and a set-point is sent at its frame's time; it expires,
//! and a fail-safe zero goes out, when frames stop coming (a camera fault) or a step fails.
//!
//! Simulated time moves only in `advance` ([`SimClock::Manual`]), so the loop runs as fast as the
//! renderer and the pipeline allow, or paced to the wall clock (`realtime`). Each tick waits for
//! the events of the simulated interval to arrive through the driver and for its set-point to be
//! applied by the simulated firmware before time moves on, so a run is deterministic for a seed
//! even though the bytes cross a real pty and a real driver task.
//!
//! The driver's own timers (set-point repeat at 25 Hz, 500 ms silence, 500 ms command timeout)
//! run on tokio's real clock, not on simulated time. The repeats are harmless: every tick sends a
//! fresh set-point and a repeat only re-sends the same value, which the firmware applies again
//! unchanged. The silence and command timeouts would fire whenever one tick takes longer than
//! 500 ms of wall time (a loaded host, a slow render), although no simulated time passed; the
//! simulation widens both to the per-tick link timeout ([`SimSetup::link_timeout`], 30 s). The
//! firmware's 250 ms watchdog runs on simulated time and is fed by the per-tick set-point (a tick
//! is 33 ms), so it still stops the base if the loop stops sending.
//!
//! Honesty: no ground-truth pose enters the pipeline. PAFSIS sees only OFFIS's perception of the
//! rendered frames and the driver's odometry; the true pose is used to render, to detect
//! collisions, and to score the run.

pub mod bench;
mod contact;
pub use contact::ContactMemory;
pub mod quality;
pub mod stats;

use crate::config::Config;
use crate::logging::{LogHandle, LogLevel, Pose2D, WorldBox, WorldCylinder, WorldGeometry};
use crate::pafsis::{GoalStatus, Mission, TopoMap};
use crate::perception::TpoShape;
use crate::runtime::control::{ControlLoop, Stepped};
use crate::runtime::{RuntimeError, RuntimeOptions};
use crate::step::{Pipeline, PipelineError, StepOutput};
use hal::fnp::to_i16_clamped;
use hal::fnp_driver::{FnpBase, FnpConfig, SerialBaseError};
use hal::{BaseEvent, BodyVelocity, Calibration, Camera, MotorBase};
use mocks::kinematics::{CollisionFn, Pose as KPose};
use mocks::sim_base::{ServeOptions, SimBase, SimBaseConfig, SimClock, SimDevice, SimServer};
use mocks::{Effects, GroundTruth, OdometryError, Pacing, Pose, RenderedCamera, Renderer, TpoClass, World};
use serde::Serialize;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The built-in topological map of the built-in office world.
pub const OFFICE_MAP_TOML: &str = include_str!("../../maps/office.toml");

/// Errors of a simulation run.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("cannot build the pipeline: {0}")]
    Pipeline(#[from] PipelineError),
    #[error("mission place {place:?} has no position in the world file's [places] nor in the map; add it to [places]")]
    NoPosition { place: String },
    #[error("cannot open the simulated base's pseudo-terminal: {0}")]
    Pty(std::io::Error),
    #[error("the FNP/1 driver failed: {0}")]
    Driver(#[from] SerialBaseError),
    #[error(
        "simulated time {t_s:.3} s: {what} did not happen within {timeout_ms} ms of wall time (is the machine overloaded?)"
    )]
    Stalled { t_s: f64, what: &'static str, timeout_ms: u128 },
    #[error("bad simulation option {name}: {problem}")]
    Option { name: &'static str, problem: String },
    /// The control loop ended the run: a step panic, a camera that cannot go on, bad options.
    #[error(transparent)]
    Control(#[from] RuntimeError),
}

/// Everything a run needs. [`SimSetup::new`] gives the defaults of `flownav sim`.
pub struct SimSetup {
    /// The world, with its obstacles already placed (e.g. by `World::with_random_obstacles`).
    pub world: World,
    pub map: TopoMap,
    pub mission: Mission,
    pub config: Config,
    /// The calibration at the render size.
    pub calib: Calibration,
    /// Camera and control rate, frames per simulated second.
    pub fps: f64,
    /// Sensor noise, grey levels (standard deviation).
    pub noise_sigma: f64,
    /// Seed of the sensor noise and of the encoder noise.
    pub seed: u64,
    /// The run ends (not reached) after this much simulated time, s.
    pub max_time_s: f64,
    /// Pace ticks to the wall clock instead of running as fast as possible.
    pub realtime: bool,
    /// Robot footprint radius for collisions and clearance, m.
    pub robot_radius_m: f64,
    /// `reached` needs the true pose within this distance of the goal place, m.
    pub goal_tolerance_m: f64,
    /// How long (wall time) to wait for the driver/firmware in one tick before giving up.
    pub link_timeout: Duration,
    /// How the simulated base's wheels differ from its firmware's nominal ones
    /// (`--odometry-error`); [`OdometryError::UNCALIBRATED`] by default.
    pub odometry_error: OdometryError,
    /// The true start pose's offset from the mission's start place (`--start-error`): x and y in
    /// the map frame, m, and yaw, rad. PAFSIS still believes it starts on the place.
    pub start_error: Pose,
    /// Alarms the simulated base raises on its clock (`--alarm`, as `sim-base --alarm`).
    pub alarms: Vec<mocks::faults::AlarmWindow>,
}

impl SimSetup {
    /// The defaults of `flownav sim` for a world, map and mission.
    pub fn new(world: World, map: TopoMap, mission: Mission, config: Config, calib: Calibration) -> Self {
        Self {
            world,
            map,
            mission,
            config,
            calib,
            fps: 30.0,
            noise_sigma: 0.0,
            seed: 0,
            max_time_s: 180.0,
            realtime: false,
            robot_radius_m: ROBOT_RADIUS_M,
            goal_tolerance_m: GOAL_TOLERANCE_M,
            link_timeout: Duration::from_secs(30),
            odometry_error: OdometryError::UNCALIBRATED,
            start_error: Pose::new(0.0, 0.0, 0.0),
            alarms: Vec::new(),
        }
    }

    /// Where the robot truly starts: [`Self::start_pose`] moved by [`Self::start_error`].
    pub fn true_start_pose(&self) -> Result<Pose, SimError> {
        let p = self.start_pose()?;
        let e = self.start_error;
        Ok(Pose::new(p.x + e.x, p.y + e.y, hal::motion::wrap_angle(p.yaw + e.yaw)))
    }

    /// Where the robot starts: the mission's first place (world `[places]`, else the map's
    /// position), facing the map's `heading_deg` of that place.
    pub fn start_pose(&self) -> Result<Pose, SimError> {
        let [x, y] = self.place_position(&self.mission.from)?;
        // As PAFSIS assumes: the place's heading, else the first edge's direction of the plan.
        let first_edge = crate::pafsis::plan(&self.map, &self.mission)
            .ok()
            .and_then(|p| p.edges.first().map(|&k| self.map.edges[k].heading_deg.to_radians()));
        let yaw = self
            .map
            .place(&self.mission.from)
            .and_then(|p| p.heading_deg)
            .map(f64::to_radians)
            .or(first_edge)
            .unwrap_or(self.world.start.yaw);
        Ok(Pose::new(x, y, yaw))
    }

    /// A place's metric position: the world's `[places]` first (the ground truth), else the map's.
    pub fn place_position(&self, name: &str) -> Result<[f64; 2], SimError> {
        self.world
            .places
            .get(name)
            .copied()
            .or_else(|| self.map.place(name).and_then(|p| p.position_m))
            .ok_or_else(|| SimError::NoPosition { place: name.to_string() })
    }
}

/// Robot radius used by `flownav sim` for collisions and clearance, m.
pub const ROBOT_RADIUS_M: f64 = 0.18;
/// Distance from the goal place within which a run counts as reached, m.
pub const GOAL_TOLERANCE_M: f64 = 0.5;

/// The result of one run. Serialises to the one-line JSON of `flownav sim` (DESIGN.md): the five
/// contract fields first, then extras.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SimSummary {
    /// PAFSIS reported arrival and the true pose is within `goal_tolerance_m` of the goal place.
    pub reached: bool,
    /// Contacts counted by the simulated base's collision hook.
    pub collisions: u64,
    /// Simulated time of the run, s.
    pub time_s: f64,
    /// Integrated true path length, m.
    pub path_m: f64,
    /// Minimum over the run of (clearance of the robot centre − robot radius), m.
    pub min_clearance_m: f64,
    pub seed: u64,
    pub mission: String,
    /// PAFSIS status at the end: active (timed out), arrived, failed.
    pub status: GoalStatus,
    /// True distance from the goal place at the end, m.
    pub goal_error_m: f64,
    /// Frames rendered and stepped.
    pub frames: u64,
    /// Steps that failed and were answered with a zero set-point.
    pub failsafe_stops: u64,
    /// Times the robot found itself pushing against something and turned away.
    pub stall_recoveries: u32,
    /// Standstills that ended with a turn to a free heading ([`crate::mofis::escape`]).
    pub escapes: u32,
    /// The first contact, if any: when, where, and with what.
    pub first_contact: Option<Contact>,
    /// Frames in which OFFIS saw each TPO class, in `TpoShape::ALL` order (wall, corner, door,
    /// corridor, none).
    pub tpo_frames: [u64; 5],
    /// Landmark events of PAFSIS: doors matched, landmarks missed, replans.
    pub doors_matched: u64,
    /// Legs ending in front of a door whose end the wall seen ahead placed
    /// ([`crate::pafsis::PafsisEvent::WallAheadMatched`]).
    pub walls_ahead_matched: u64,
    pub landmarks_missed: u64,
    pub replans: u64,
    /// Frames whose side walls corrected PAFSIS's heading or offset ([`crate::pafsis::walls`]).
    pub wall_fixes: u64,
    /// Keyframe pairs whose flow corrected PAFSIS's heading, and the odometry's turn scale
    /// error and bend (rad per metre) learned from them ([`crate::odometry_calibration`]).
    pub flow_yaw_fixes: u64,
    pub odometry_scale: f64,
    pub odometry_bend_rad_m: f64,
    /// Mean over the stepped frames of |PAFSIS's heading estimate − the true heading|, degrees,
    /// and its value at the end: how far dead reckoning and the landmarks kept the heading.
    pub mean_heading_error_deg: f64,
    pub final_heading_error_deg: f64,
    /// The odometry error of the simulated base (`--odometry-error`) and the start error
    /// (`--start-error`: dx, dy in m, dyaw in degrees).
    pub odometry_error: String,
    pub start_error: [f64; 3],
    /// Wall-clock time of the run, s, and simulated seconds per wall second.
    pub wall_s: f64,
    pub realtime_factor: f64,
    /// Render size, px.
    pub size: [u32; 2],
    pub fps: f64,
    pub noise: f64,
    /// Whether the simulator's true pose was given to the planner (never, in this version).
    pub pose_hint: bool,
    /// The obstacle perception scored against the world ([`quality`]).
    #[serde(flatten)]
    pub quality: quality::QualitySummary,
}

/// Where and when the robot first touched something (true pose, for diagnosis).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Contact {
    /// Simulated time of the tick that detected it, s.
    pub t_s: f64,
    /// True pose at that tick: x, y (m) and heading (degrees).
    pub pose: [f64; 3],
    /// The nearest object (`World::clearance`'s label, e.g. `box box1` or `wall …`).
    pub object: String,
    /// Where on the rim it touched, rad from the heading (+ = left).
    pub at_rad: f64,
    /// What the obstacle memory held of the object then (`contact::classify`).
    pub memory: ContactMemory,
}

impl SimSummary {
    /// The summary as one JSON line.
    pub fn to_json_line(&self) -> String {
        serde_json::to_string(self).expect("summary serialises")
    }
}

/// What the terminal shows once per simulated second.
#[derive(Clone, Debug)]
pub struct Progress {
    pub t_s: f64,
    pub pose: Pose,
    pub tpo: TpoShape,
    pub tpo_confidence: f64,
    pub tpo_distance_m: Option<f64>,
    pub obstacle_m: Option<f64>,
    pub obstacle_bearing_rad: Option<f64>,
    /// Ground truth at this pose (for the display only; never given to the pipeline).
    pub truth: mocks::FrameTruth,
    pub setpoint: BodyVelocity,
    pub status: GoalStatus,
    pub leg: String,
    pub collisions: u64,
    pub clearance_m: f64,
}

impl std::fmt::Display for Progress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let opt = |d: Option<f64>| d.map_or("-".to_string(), |d| format!("{d:.1}"));
        let deg = |d: Option<f64>| d.map_or("-".to_string(), |d| format!("{:+.0}", d.to_degrees()));
        write!(
            f,
            "t {:5.1} s  pose ({:6.2}, {:5.2}, {:4.0}°)  TPO {:<8} {:.2} d {:>4} m (true {:<8} {:>4})  obstacle {:>4} m {:>4}° (true {:>4} m {:>4}°)  v {:.2} ω {:+.2}  clear {:.2} m  {:?}: {}",
            self.t_s,
            self.pose.x,
            self.pose.y,
            self.pose.yaw.to_degrees(),
            self.tpo.name(),
            self.tpo_confidence,
            opt(self.tpo_distance_m),
            format!("{:?}", self.truth.tpo.shape).to_lowercase(),
            opt(self.truth.tpo.distance_m),
            opt(self.obstacle_m),
            deg(self.obstacle_bearing_rad),
            opt(self.truth.obstacle.distance_m),
            deg(self.truth.obstacle.bearing_rad),
            self.setpoint.v,
            self.setpoint.omega,
            self.clearance_m,
            self.status,
            self.leg,
        )?;
        if self.collisions > 0 {
            write!(f, "  COLLISIONS {}", self.collisions)?;
        }
        Ok(())
    }
}

/// The world's walls and obstacles as boxes and cylinders for `/sim/world`.
pub fn world_geometry(world: &World) -> WorldGeometry {
    let mut g = WorldGeometry::default();
    const WALL_THICKNESS_M: f64 = 0.05;
    for (i, f) in world.faces().iter().enumerate() {
        let (dx, dy) = (f.b[0] - f.a[0], f.b[1] - f.a[1]);
        let len = dx.hypot(dy);
        if len < 1e-6 || f.z0 > 0.01 {
            // Lintels above doors would be drawn standing on the floor: leave them out.
            continue;
        }
        g.boxes.push(WorldBox {
            id: format!("wall{i}"),
            center_m: [(f.a[0] + f.b[0]) / 2.0, (f.a[1] + f.b[1]) / 2.0],
            size_m: [len, WALL_THICKNESS_M, f.z1 - f.z0],
            yaw_rad: dy.atan2(dx),
            wall: true,
        });
    }
    for b in &world.boxes {
        g.boxes.push(WorldBox { id: b.name.clone(), center_m: b.center, size_m: b.size, yaw_rad: b.yaw, wall: false });
    }
    for c in &world.cylinders {
        g.cylinders.push(WorldCylinder {
            id: c.name.clone(),
            center_m: c.center,
            radius_m: c.radius,
            height_m: c.height,
        });
    }
    g
}

/// A set-point as the firmware will hold it (FNP/1 carries mm/s and mrad/s).
fn quantised(cmd: BodyVelocity) -> BodyVelocity {
    BodyVelocity::new(
        f64::from(to_i16_clamped(cmd.v, 1000.0)) / 1000.0,
        f64::from(to_i16_clamped(cmd.omega, 1000.0)) / 1000.0,
    )
}

fn ns(t_s: f64) -> u64 {
    (t_s * 1e9).round() as u64
}

/// Runs one mission in closed loop with the rendered camera. `progress` is called once per
/// simulated second; `log` receives every frame, step, pose and base event. Must be called inside
/// a multi-threaded tokio runtime (the pty server and the driver run as tasks beside the loop).
pub async fn run(
    setup: &SimSetup,
    log: Option<&LogHandle>,
    progress: impl FnMut(&Progress),
) -> Result<SimSummary, SimError> {
    run_with_camera(setup, log, progress, |camera| camera).await
}

/// [`run`] with the rendered camera wrapped by `camera` (a test's fault injection: a bad frame,
/// a stall, the end of the stream). Whatever the wrapper returns goes through the runtime's
/// rules ([`ControlLoop`]).
pub async fn run_with_camera<C: Camera>(
    setup: &SimSetup,
    log: Option<&LogHandle>,
    mut progress: impl FnMut(&Progress),
    camera: impl FnOnce(RenderedCamera) -> C,
) -> Result<SimSummary, SimError> {
    if !(setup.fps.is_finite() && (1.0..=240.0).contains(&setup.fps)) {
        return Err(SimError::Option { name: "fps", problem: format!("{} must be in 1..=240", setup.fps) });
    }
    if !(setup.max_time_s.is_finite() && setup.max_time_s > 0.0) {
        return Err(SimError::Option { name: "max-time", problem: "must be a positive number of seconds".into() });
    }
    if let Err(e) = setup.odometry_error.validate() {
        return Err(SimError::Option { name: "odometry-error", problem: e.to_string() });
    }
    let wall_start = Instant::now();
    let start = setup.true_start_pose()?;
    let goal_xy = setup.place_position(&setup.mission.to)?;
    let pipeline = Pipeline::new(&setup.config, setup.calib.clone(), Some((setup.map.clone(), setup.mission.clone())))?;
    let mut control = ControlLoop::new(pipeline, &RuntimeOptions::from_config(&setup.config), log.cloned(), 0)?;
    let truth = GroundTruth::new(&setup.world, &setup.calib);
    let effects = Effects { noise_sigma: setup.noise_sigma, seed: setup.seed, ..Effects::default() };

    // The camera renders the true pose of the tick and stamps its frame with simulated time.
    let camera_pose = Arc::new(Mutex::new(start));
    let sim_ns = Arc::new(AtomicU64::new(0));
    let renderer = Arc::new(Renderer::new(&setup.world, &setup.calib));
    let clock = sim_ns.clone();
    let rendered =
        RenderedCamera::with_shared_pose(renderer, setup.fps, Pacing::Simulated, effects, camera_pose.clone())
            .with_clock(move || clock.load(Ordering::Relaxed));
    let mut camera = camera(rendered);

    // The simulated base: firmware state machine on a pty, time moved by hand.
    let world = Arc::new(setup.world.clone());
    let radius = setup.robot_radius_m;
    let hit_world = world.clone();
    let collision: CollisionFn = Arc::new(move |p: &KPose| hit_world.clearance(p.x, p.y).distance_m < radius);
    let mut base_cfg = SimBaseConfig::default();
    base_cfg.drive.seed = setup.seed.wrapping_add(1);
    base_cfg.drive.error = setup.odometry_error;
    base_cfg.alarms = setup.alarms.clone();
    base_cfg.check_alarms().map_err(|problem| SimError::Option { name: "alarm", problem })?;
    let server =
        SimServer::start(SimBase::new(base_cfg), ServeOptions { clock: SimClock::Manual, ..Default::default() })
            .map_err(SimError::Pty)?;
    server.with_device(|b| {
        b.drive().set_pose(KPose::new(start.x, start.y, start.yaw));
        b.set_collision(Some(collision));
    });
    // The driver's wall-clock timers must not fire because a tick took long on a loaded host
    // (simulated time only moves when the loop is ready): widen them to the per-tick link
    // timeout. The firmware's 250 ms watchdog, in simulated time, still guards every tick.
    let mut driver_cfg = FnpConfig::new(server.pty_path().to_string_lossy());
    driver_cfg.silence_timeout = driver_cfg.silence_timeout.max(setup.link_timeout);
    driver_cfg.command_timeout = driver_cfg.command_timeout.map(|t| t.max(setup.link_timeout));
    let mut base = FnpBase::connect(driver_cfg).await?;

    if let Some(log) = log {
        log.calibration(0, &setup.calib);
        log.world(0, &world_geometry(&setup.world));
        log.log(
            0,
            LogLevel::Info,
            format!("flownav sim: mission {} on world {}, seed {}", setup.mission, setup.world.name, setup.seed),
        );
    }

    let dt = 1.0 / setup.fps;
    let tick = Duration::from_secs_f64(dt);
    let max_ticks = (setup.max_time_s * setup.fps).ceil() as u64;
    let mut pose = start;
    let mut prev_pose = start;
    let (mut odom_seen, mut path_m, mut min_clear) = (0u64, 0.0f64, f64::INFINITY);
    let mut first_contact: Option<Contact> = None;
    let mut contact_trace = contact::ContactTrace::new(&setup.world);
    let (mut frames, mut tpo_frames) = (0u64, [0u64; 5]);
    let (mut doors_matched, mut landmarks_missed, mut replans) = (0u64, 0u64, 0u64);
    let mut status = GoalStatus::Active;
    let mut last_output: Option<StepOutput> = None;
    let mut scored = quality::Quality::default();
    let (mut heading_err_sum, mut heading_err_n, mut heading_err_last) = (0.0f64, 0u64, 0.0f64);
    let mut t_s = 0.0;

    for k in 0..=max_ticks {
        t_s = k as f64 * dt;
        let t_ns = ns(t_s);
        if k > 0 {
            if setup.realtime {
                let due = wall_start + Duration::from_secs_f64(t_s);
                tokio::time::sleep_until(due.into()).await;
            }
            server.advance(tick);
        }
        sim_ns.store(t_ns, Ordering::Relaxed);
        // Everything the base sent up to now must have come through the driver. Odometry is
        // stamped with the tick's time: the frame interval it arrived in is the one it measured.
        let sent = server.with_device(|b| b.counters().odom_sent);
        let deadline = Instant::now() + setup.link_timeout;
        while odom_seen < sent {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(stalled(t_s, "the simulated base's odometry reaching the driver", setup));
            }
            match base.next_event(left).await? {
                Some(BaseEvent::Odometry(o)) => {
                    odom_seen += 1;
                    let o = hal::Odometry { t_ns, ..o };
                    control.on_odometry(o);
                    if let Some(log) = log {
                        log.odometry(&o);
                    }
                }
                Some(BaseEvent::Status(s)) => {
                    // The set-point of this tick passes the alarm rules (bumper, e-stop, ...).
                    control.on_status(&s, t_ns);
                    if let Some(log) = log {
                        log.base_status(&hal::BaseStatus { t_ns, ..s });
                    }
                }
                None => {}
            }
        }

        let odometry = control.velocity_for(t_ns);
        let p = server.pose();
        pose = Pose::new(p.x, p.y, p.theta);
        let pose_w = pose;
        path_m += (pose.x - prev_pose.x).hypot(pose.y - prev_pose.y);
        prev_pose = pose;
        let near = setup.world.clearance(pose.x, pose.y);
        let clearance = near.distance_m - radius;
        min_clear = min_clear.min(clearance);
        let contacts = server.with_device(|b| b.drive().collisions());
        if let Some(trace) = &mut contact_trace {
            let scene = contact::Scene {
                t_s,
                pose,
                world: &setup.world,
                pipeline: control.pipeline(),
                last: last_output.as_ref(),
                odometry,
            };
            trace.check(contacts, &near, &scene);
        }
        if first_contact.is_none() && contacts > 0 {
            let (at_rad, memory) = contact::at_contact(control.pipeline(), &setup.world, pose, &near.object);
            first_contact = Some(Contact {
                t_s: round3(t_s),
                pose: [round3(pose.x), round3(pose.y), round3(pose.yaw.to_degrees())],
                memory,
                at_rad: round3(at_rad),
                object: near.object,
            });
        }

        // The frame of this tick through the runtime's control loop (slot, step, set-point rules).
        *camera_pose.lock().unwrap_or_else(|e| e.into_inner()) = pose_w;
        if let Some(log) = log {
            log.pose(t_ns, &Pose2D { x_m: pose.x, y_m: pose.y, theta_rad: pose.yaw });
        }
        let mut ended = false;
        let setpoint = match camera.capture() {
            Ok(frame) => {
                frames += 1;
                let encoded = camera.take_encoded();
                let (stepped, setpoint) = control.on_frame(frame, encoded, t_ns)?;
                if let Some(Stepped::Output { output, .. }) = stepped {
                    let out = *output;
                    tpo_frames[TpoShape::ALL.iter().position(|s| *s == out.perception.tpo.shape).unwrap_or(4)] += 1;
                    status = out.goal.status;
                    let pipeline = control.pipeline();
                    scored.observe(&setup.world, &pose, pipeline.surface_points(), &pipeline.memory().occupied());
                    let said_none = out.perception.tpo.shape == TpoShape::None;
                    scored.observe_tpo(truth.tpo(pose).shape != TpoClass::None, said_none);
                    if let Some(nav) = pipeline.pafsis() {
                        heading_err_last = hal::motion::wrap_angle(nav.progress().heading_rad - pose.yaw).abs();
                        heading_err_sum += heading_err_last;
                        heading_err_n += 1;
                    }
                    last_output = Some(out);
                }
                setpoint
            }
            Err(e) => {
                ended = control.on_camera_error(&e, t_ns)?;
                if ended {
                    tracing::info!("t {t_s:.2} s: the camera's stream ended ({e}); stopping the robot");
                    BodyVelocity::ZERO
                } else {
                    control.on_tick(t_ns)
                }
            }
        };
        let pipeline = control.pipeline();
        if tracing::enabled!(target: "flownav::sim::frames", tracing::Level::TRACE)
            && let Some(o) = &last_output
        {
            let t = truth.frame(pose);
            let ob = &o.perception.obstacle;
            let pts = pipeline.surface_points();
            let near = pts
                .iter()
                .map(|p| (p.forward.hypot(p.left), p.left.atan2(p.forward)))
                .fold((f64::INFINITY, 0.0), |a, b| if b.0 < a.0 { b } else { a });
            let odo = odometry;
            let lane = pipeline.pafsis().and_then(crate::pafsis::Pafsis::lane);
            // how much farther PAFSIS thinks the corridor leg's end is than it truly is, m
            // (the map's place of the leg's end taken as true: exact maps only)
            let to_go_err = pipeline.pafsis().map_or(f64::NAN, |nav| {
                let p = nav.progress();
                match nav.legs().get(p.leg) {
                    Some(crate::pafsis::Leg {
                        kind: crate::pafsis::LegKind::Corridor { length_m, .. },
                        line_point_m: Some([ex, ey]),
                        heading_rad,
                        ..
                    }) => {
                        (length_m - p.along_m) - ((ex - pose.x) * heading_rad.cos() + (ey - pose.y) * heading_rad.sin())
                    }
                    _ => f64::NAN,
                }
            });
            tracing::trace!(
                target: "flownav::sim::frames",
                "frame t={t_s:.3} x={:.3} y={:.3} yaw={:.3} tpo={:?} true_tpo={:?} obs_d={:?} obs_b={:?} true_d={:?} true_b={:?} avoid_d={:?} avoid_b={:?} v={:.3} w={:.3} clear={clearance:.3} npts={} near={:.2}@{:.2} odo_v={:.3} odo_w={:.3} goal_a={:.3} steer_a={:.3} weight={:.2} avoid_turn={:.2} est_yaw={:.3} leg={} lane_left={:.3} lane_a={:.3} est_xy={:?} to_go_err={to_go_err:.3}",
                pose.x, pose.y, pose.yaw, o.perception.tpo.shape, t.tpo.shape, ob.distance_m, ob.bearing_rad,
                t.obstacle.distance_m, t.obstacle.bearing_rad, o.avoided.distance_m, o.avoided.bearing_rad, setpoint.v, setpoint.omega, pts.len(), near.0, near.1, odo.v, odo.omega,
                o.goal.angle_rad, o.steered.angle_rad, o.mofis.weight, o.mofis.avoidance.turn, pipeline.pafsis().map_or(f64::NAN, |p| p.progress().heading_rad),
                pipeline.pafsis().map_or(0, |p| p.progress().leg),
                lane.map_or(f64::NAN, |l| l.left_m),
                lane.map_or(f64::NAN, |l| l.angle_rad),
                pipeline.pafsis().and_then(|p| p.position_m()).map(|[x, y]| [(x * 1e3).round() / 1e3, (y * 1e3).round() / 1e3])
            );
            let a = pipeline.offis().attributes();
            // a fit's planes: inlier bins (bit b = bin b), centre, direction
            let fitted = |m: &crate::offis::features::TpoModel| {
                m.planes()
                    .map(|l| {
                        format!("{:b}@{:.2},{:.2}/{:.2},{:.2}", l.inliers, l.centre[0], l.centre[1], l.dir[0], l.dir[1])
                    })
                    .collect::<Vec<_>>()
                    .join("|")
            };
            tracing::trace!(
                target: "flownav::sim::frames",
                "offis t={t_s:.3} pair_dt={:.3} foe={} bins_pts={} carried={} planes={} raw={:?} raw_conf={:.2} groups={:?} filt={:?} filt_steps={} filt_classes={:?} valid={} outliers={} feat={:?} profile={} planes_fit={} surfaces_fit={}",
                o.dt, a.foe.is_some(), a.bins.iter().filter(|b| b.point.is_some()).count(), a.carried_bins, a.shape_model.planes().count(), a.decision.shape, a.decision.confidence,
                a.decision.groups.map(|g| (g * 100.0).round() / 100.0), a.filtered.shape, a.filtered.steps,
                a.filtered.classes.map(|g| (g * 100.0).round() / 100.0), a.valid, a.outliers, a.features,
                // the envelope profile, left bin first (forward,left m; - for an empty bin); the
                // planes of the shape fit, which the classifier's features were computed from,
                // and of the surfaces fit, which the obstacle test and PAFSIS's walls use
                a.bins
                    .iter()
                    .map(|b| b.point.map_or("-".to_string(), |p| format!("{:.2},{:.2}", p[0], p[1])))
                    .collect::<Vec<_>>()
                    .join(";"),
                fitted(&a.shape_model),
                fitted(&a.model)
            );
        }
        if tracing::enabled!(target: "flownav::sim::cells", tracing::Level::TRACE) {
            // the obstacle memory's occupied cells and this step's surface points within 1.5 m,
            // placed in the world with the true pose (to compare with the world's obstacles)
            let world = |p: [f64; 2]| {
                let [x, y] = pose.transform(p);
                format!("({x:.2},{y:.2})")
            };
            let near = |p: &[f64; 2]| p[0].hypot(p[1]) <= 1.5;
            let cells: Vec<String> = pipeline.memory().occupied().into_iter().filter(near).map(world).collect();
            let pts: Vec<String> =
                pipeline.surface_points().iter().map(|p| [p.forward, p.left]).filter(near).map(world).collect();
            // the confirmed cells within 0.6 m that still hold evidence, with it: what the
            // footprint guard may count beside the robot
            let held: Vec<String> = pipeline
                .memory()
                .cells_above(0.05)
                .into_iter()
                .filter(|(p, _, confirmed)| *confirmed && p[0].hypot(p[1]) <= 0.6)
                .map(|(p, e, _)| format!("{}:{e:.2}", world(p)))
                .collect();
            tracing::trace!(target: "flownav::sim::cells", "cells t={t_s:.3} occupied=[{}] points=[{}] held=[{}]", cells.join(" "), pts.join(" "), held.join(" "));
        }
        if let Some(trace) = &mut contact_trace {
            trace.observe(t_s, pose, &setup.world, pipeline.memory());
        }
        if let Some(p) = control.pipeline_mut().pafsis_mut() {
            for ev in p.take_events() {
                use crate::pafsis::PafsisEvent as E;
                match &ev {
                    E::DoorMatched { .. } => doors_matched += 1,
                    E::LandmarkMissed { .. } => landmarks_missed += 1,
                    E::Replanned { .. } => replans += 1,
                    _ => {}
                }
                tracing::debug!("t {t_s:.2} s: {ev:?}");
                if let Some(log) = log {
                    log.log(t_ns, LogLevel::Info, serde_json::to_string(&ev).unwrap_or_default());
                }
            }
        }

        // Send the set-point through the driver and wait until the firmware holds it.
        let before = server.with_device(|b| b.counters().setpoints);
        base.set_velocity(setpoint)?;
        let want = quantised(setpoint);
        let deadline = Instant::now() + setup.link_timeout;
        loop {
            let (n, held) = server.with_device(|b| (b.counters().setpoints, b.commanded()));
            if n > before && held == want {
                break;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(stalled(t_s, "the set-point reaching the simulated base", setup));
            }
            // Woken when the firmware has read bytes from the pty (tokio's timers tick in whole
            // milliseconds, so polling on a timer cost a millisecond of wall time per tick).
            let _ = tokio::time::timeout(left, server.received()).await;
        }

        let report_every = setup.fps.round().max(1.0) as u64;
        let done = status != GoalStatus::Active || ended;
        if k % report_every == 0 || done {
            let collisions = server.with_device(|b| b.drive().collisions());
            let pipeline = control.pipeline();
            let (tpo, leg) = match &last_output {
                Some(o) => (o.perception.tpo, pipeline.pafsis().map(|p| p.progress().description).unwrap_or_default()),
                None => (Default::default(), String::new()),
            };
            progress(&Progress {
                t_s,
                pose: pose_w,
                tpo: tpo.shape,
                tpo_confidence: tpo.confidence,
                tpo_distance_m: tpo.distance_m,
                obstacle_m: last_output.as_ref().and_then(|o| o.perception.obstacle.distance_m),
                obstacle_bearing_rad: last_output.as_ref().and_then(|o| o.perception.obstacle.bearing_rad),
                truth: truth.frame(pose),
                setpoint,
                status,
                leg,
                collisions,
                clearance_m: clearance,
            });
        }
        if done {
            break;
        }
    }

    let collisions = server.with_device(|b| b.drive().collisions());
    base.close().await;
    server.shutdown().await;
    let goal_error_m = (pose.x - goal_xy[0]).hypot(pose.y - goal_xy[1]);
    let wall_s = wall_start.elapsed().as_secs_f64();
    let pipeline = control.pipeline();
    let summary = SimSummary {
        reached: status == GoalStatus::Arrived && goal_error_m <= setup.goal_tolerance_m,
        collisions,
        time_s: round3(t_s),
        path_m: round3(path_m),
        min_clearance_m: round3(min_clear),
        seed: setup.seed,
        mission: setup.mission.to_string(),
        status,
        goal_error_m: round3(goal_error_m),
        frames,
        failsafe_stops: control.failsafe_stops(),
        stall_recoveries: pipeline.stall_recoveries(),
        escapes: pipeline.escapes(),
        first_contact,
        tpo_frames,
        doors_matched,
        walls_ahead_matched: pipeline.pafsis().map_or(0, |p| p.walls_ahead_matched()),
        landmarks_missed,
        replans,
        wall_fixes: pipeline.pafsis().map_or(0, |p| p.wall_fixes().frames),
        flow_yaw_fixes: pipeline.pafsis().map_or(0, |p| p.flow_fixes()),
        odometry_scale: round4(pipeline.odometry_calibration().scale()),
        odometry_bend_rad_m: round4(pipeline.odometry_calibration().bend_rad_m()),
        mean_heading_error_deg: round3((heading_err_sum / heading_err_n.max(1) as f64).to_degrees()),
        final_heading_error_deg: round3(heading_err_last.to_degrees()),
        odometry_error: setup.odometry_error.to_string(),
        start_error: [
            round3(setup.start_error.x),
            round3(setup.start_error.y),
            round3(setup.start_error.yaw.to_degrees()),
        ],
        wall_s: round3(wall_s),
        realtime_factor: round3(t_s / wall_s.max(1e-9)),
        size: [setup.calib.camera.width, setup.calib.camera.height],
        fps: setup.fps,
        noise: setup.noise_sigma,
        pose_hint: false,
        quality: scored.summary(),
    };
    if let Some(log) = log {
        log.log(ns(t_s), LogLevel::Info, summary.to_json_line());
    }
    Ok(summary)
}

fn round3(x: f64) -> f64 {
    (x * 1000.0).round() / 1000.0
}

fn stalled(t_s: f64, what: &'static str, setup: &SimSetup) -> SimError {
    SimError::Stalled { t_s, what, timeout_ms: setup.link_timeout.as_millis() }
}

fn round4(x: f64) -> f64 {
    (x * 10_000.0).round() / 10_000.0
}
