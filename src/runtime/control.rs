//! The logic between a frame and a set-point, apart from threads and clocks: the one control loop
//! that `flownav run` ([`super::run`]) and `flownav sim` ([`crate::sim`]) both go through.
//!
//! - [`Stepper`]: a frame and its velocity → the step's outcome. Picks the velocity that goes
//!   with the frame ([`Stepper::velocity_for`], the mean odometry over the frame interval),
//!   records the frame and the step, catches a panic, and calls [`Pipeline::fail_safe`] after a
//!   failed step or when no frame came within the stall time.
//! - [`Setpoints`]: outcomes and time → what the base is told. A new set-point goes out at once;
//!   it expires `stall` after the capture of its frame; a failed step, a camera that went away or
//!   an expiry gives a zero at once; between frames the command in force is repeated.
//! - [`camera_trouble`]: what a camera error means for the run (skip, fail-safe, end, fatal).
//! - [`Alarms`] (in [`super::alarms`]): the base's alarms, the last filter on what goes out.
//! - [`ControlLoop`]: all of it on one thread, with the [`FrameSlot`] (latest frame wins) and the
//!   odometry history, driven by the caller's clock. `sim` calls it once per simulated tick.
//!
//! Time is always an argument (`now_ns`, on the clock frames are stamped with), never read here:
//! `run` passes the host's monotonic clock, `sim` its simulated time. So the safety rules live in
//! one place and the simulator exercises the code a robot runs; only the threads differ. `run`
//! spreads the same pieces over its threads (see [`super`]): the camera thread fills the slot and
//! reacts by [`camera_trouble`], the step thread owns the `Stepper`, the control task owns the
//! `Setpoints` and wakes at the refresh period and at the expiry. In `sim` a step takes no
//! simulated time, so the slot never holds a stale frame and set-points expire only when frames
//! stop coming.

use super::RuntimeError;
use super::alarms::Alarms;
use super::odometry::OdometryHistory;
use super::slot::{FrameSlot, Taken};
use crate::logging::record::{RecordImage, record_failsafe, record_frame, record_step};
use crate::logging::{LogHandle, LogLevel};
use crate::step::{Pipeline, StepOutput};
use hal::camera::monotonic_ns;
use hal::{BaseStatus, BodyVelocity, ErrorKind, Frame, Odometry};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::Arc;
use std::time::Duration;

/// Why the control loop forced a zero set-point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Failsafe {
    /// No new set-point within the stall time of the last one's frame (camera stall, slow step).
    Expired,
    StepFailed,
    CameraDown,
}

/// What one frame gave.
#[derive(Debug)]
pub enum Stepped {
    /// The step's output for the frame captured at `t_ns`, stepped with `velocity`.
    Output { seq: u64, t_ns: u64, velocity: BodyVelocity, output: Box<StepOutput> },
    /// The first frame of a pair (after the start or a fail-safe): no set-point yet.
    Primed,
    /// The step failed; `Pipeline::fail_safe` has been called.
    Failed { seq: u64, t_ns: u64, error: String },
    /// The step panicked: a bug; the run must stop the robot and end.
    Panicked(String),
}

/// The per-frame step with its odometry pick, recording and failure handling; see the module docs.
pub struct Stepper {
    pipeline: Pipeline,
    logger: Option<LogHandle>,
    /// The capture time of the last frame stepped: the older frame of the next pair.
    prev_t_ns: Option<u64>,
    stalled: bool,
    /// Wall-clock and thread CPU time of the last `Pipeline::step`, ns.
    last_step_ns: (u64, u64),
    /// Steps begun (frames handed to `Pipeline::step`).
    steps: u64,
    /// The test hook of the stop-path tests: panic in this step (see [`test_panic_at_step`]).
    panic_at: Option<u64>,
}

/// Debug builds only: `FLOWNAV_TEST_PANIC_AT_STEP=N` makes the `N`th step (from 0) panic, so the
/// tests can prove on the real binary that a panic in the step stops the robot. Read once per
/// run; release builds (what a robot runs) never look.
fn test_panic_at_step() -> Option<u64> {
    if !cfg!(debug_assertions) {
        return None;
    }
    std::env::var("FLOWNAV_TEST_PANIC_AT_STEP").ok()?.trim().parse().ok()
}

impl Stepper {
    /// With a logger, every frame's image, every step and every `fail_safe` call are recorded
    /// through [`crate::logging::record`], so `flownav replay` can re-run the log bit for bit.
    pub fn new(pipeline: Pipeline, logger: Option<LogHandle>) -> Self {
        Self {
            pipeline,
            logger,
            prev_t_ns: None,
            stalled: false,
            last_step_ns: (0, 0),
            steps: 0,
            panic_at: test_panic_at_step(),
        }
    }

    pub fn pipeline(&self) -> &Pipeline {
        &self.pipeline
    }

    pub fn pipeline_mut(&mut self) -> &mut Pipeline {
        &mut self.pipeline
    }

    /// The velocity for the frame captured at `t_ns`: the mean odometry since the last frame
    /// stepped, else the latest sample at or before the frame, else zero (base silent).
    pub fn velocity_for(&self, odometry: &OdometryHistory, t_ns: u64) -> BodyVelocity {
        match self.prev_t_ns {
            Some(t0) if t0 < t_ns => odometry.mean_over(t0, t_ns),
            _ => odometry.for_frame(t_ns).map(|o| o.velocity),
        }
        .unwrap_or(BodyVelocity::ZERO)
    }

    /// Wall-clock and thread CPU time of the last step, ns.
    pub fn last_step_ns(&self) -> (u64, u64) {
        self.last_step_ns
    }

    /// Steps `frame` with `velocity`. `encoded` is the camera's own bytes of the frame (MJPEG),
    /// logged instead of the luma when present.
    pub fn step(&mut self, frame: Frame, velocity: BodyVelocity, encoded: Option<Arc<[u8]>>) -> Stepped {
        self.stalled = false;
        self.prev_t_ns = Some(frame.t_ns);
        let (seq, t_ns) = (frame.seq, frame.t_ns);
        if let Some(h) = &self.logger {
            match encoded {
                Some(jpeg) => record_frame(h, &frame, RecordImage::Jpeg(jpeg)),
                None => record_frame(h, &frame, RecordImage::Mono8(&frame.image)),
            };
        }
        let (wall0, cpu0) = (monotonic_ns(), thread_cpu_ns());
        let (step, panic_at) = (self.steps, self.panic_at);
        self.steps += 1;
        let outcome = catch_unwind(AssertUnwindSafe(|| {
            if panic_at == Some(step) {
                panic!("FLOWNAV_TEST_PANIC_AT_STEP={step}: the test hook's panic");
            }
            self.pipeline.step(frame, velocity)
        }));
        self.last_step_ns = (monotonic_ns().saturating_sub(wall0), thread_cpu_ns().saturating_sub(cpu0));
        match outcome {
            Ok(Ok(Some(output))) => {
                if let Some(h) = &self.logger {
                    record_step(h, velocity, &output, &self.pipeline);
                }
                Stepped::Output { seq, t_ns, velocity, output: Box::new(output) }
            }
            Ok(Ok(None)) => Stepped::Primed,
            Ok(Err(e)) => {
                self.pipeline.fail_safe();
                let error = e.to_string();
                if let Some(h) = &self.logger {
                    record_failsafe(h, t_ns, &format!("step failed on frame {seq}: {error}"));
                }
                Stepped::Failed { seq, t_ns, error }
            }
            Err(p) => Stepped::Panicked(panic_message(p.as_ref())),
        }
    }

    /// No frame came within the stall time: the pipeline forgets its previous frame (the next
    /// pair must not span the gap). Once per stall; returns whether this call began it.
    pub fn stall(&mut self, now_ns: u64) -> bool {
        if self.stalled {
            return false;
        }
        self.stalled = true;
        self.pipeline.fail_safe();
        if let Some(h) = &self.logger {
            record_failsafe(h, now_ns, "no frame within the stall time");
        }
        true
    }
}

/// What to send the base after a set-point arrived.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Order {
    /// The new command, valid until its expiry.
    Drive(BodyVelocity),
    /// It came too late: a fail-safe zero.
    Stop,
}

impl Order {
    pub fn velocity(self) -> BodyVelocity {
        match self {
            Order::Drive(v) => v,
            Order::Stop => BodyVelocity::ZERO,
        }
    }
}

/// The command in force and the moment it stops being valid.
#[derive(Clone, Copy, Debug)]
struct Command {
    setpoint: BodyVelocity,
    expires_ns: u64,
}

/// The set-point rules; see the module docs. Every method takes the time it happens at.
pub struct Setpoints {
    stall_ns: u64,
    command: Option<Command>,
    failsafe_stops: u64,
    logger: Option<LogHandle>,
}

impl Setpoints {
    /// A set-point expires `stall` after the capture of its frame.
    pub fn new(stall: Duration, logger: Option<LogHandle>) -> Self {
        Self { stall_ns: stall.as_nanos() as u64, command: None, failsafe_stops: 0, logger }
    }

    /// The set-point computed from frame `seq` captured at `t_ns`, arriving at `now_ns`.
    pub fn on_setpoint(&mut self, seq: u64, t_ns: u64, setpoint: BodyVelocity, now_ns: u64) -> Order {
        let expires_ns = t_ns.saturating_add(self.stall_ns);
        if expires_ns <= now_ns {
            let detail = format!("the set-point of frame {seq} is older than the stall time");
            self.failsafe(Failsafe::Expired, &detail, now_ns);
            return Order::Stop;
        }
        self.command = Some(Command { setpoint, expires_ns });
        Order::Drive(setpoint)
    }

    /// Forces a zero set-point now and returns it. Counted when it replaces a valid command.
    pub fn failsafe(&mut self, why: Failsafe, detail: &str, now_ns: u64) -> BodyVelocity {
        if self.command.take().is_some() {
            self.failsafe_stops += 1;
            tracing::warn!("fail-safe stop ({why:?}): {detail}");
            if let Some(log) = &self.logger {
                log.log(now_ns, LogLevel::Warning, format!("runtime: zero set-point sent ({why:?}): {detail}"));
            }
        }
        BodyVelocity::ZERO
    }

    /// What the base gets at `now_ns` without a new set-point: the command in force, or zero
    /// (none yet, or it expired: then a fail-safe stop).
    pub fn on_tick(&mut self, now_ns: u64) -> BodyVelocity {
        match self.command {
            Some(c) if c.expires_ns <= now_ns => {
                self.failsafe(Failsafe::Expired, "no new set-point within the stall time", now_ns)
            }
            Some(c) => c.setpoint,
            None => BodyVelocity::ZERO,
        }
    }

    /// When the command in force expires, ns.
    pub fn expires_ns(&self) -> Option<u64> {
        self.command.map(|c| c.expires_ns)
    }

    /// Zero set-points forced while a valid command was in force.
    pub fn failsafe_stops(&self) -> u64 {
        self.failsafe_stops
    }
}

/// What a camera error means for the run (the safety rules of [`super`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraTrouble {
    /// No frame this time (stall timeout, corrupt frame): try again; the set-point expires if
    /// frames stay away.
    Skip,
    /// The device went away: a zero at once, then capture again with back-off.
    Down,
    /// The source ended (a frame folder played to its end): stop, end the run normally.
    End,
    /// A human must fix it (permission, unsupported mode): stop, end the run with an error.
    Fatal,
}

pub fn camera_trouble(kind: ErrorKind) -> CameraTrouble {
    match kind {
        ErrorKind::Timeout | ErrorKind::BadData => CameraTrouble::Skip,
        ErrorKind::Disconnected => CameraTrouble::Down,
        ErrorKind::EndOfStream => CameraTrouble::End,
        ErrorKind::Unsupported | ErrorKind::Other => CameraTrouble::Fatal,
    }
}

/// The control loop on one thread, on the caller's clock; see the module docs.
pub struct ControlLoop {
    slot: FrameSlot,
    stepper: Stepper,
    setpoints: Setpoints,
    alarms: Alarms,
    odometry: OdometryHistory,
    stall_ns: u64,
    /// The capture time of the last frame (or the start): a stall is counted from it.
    last_frame_ns: u64,
    camera_down: bool,
    step_failures: u64,
}

impl ControlLoop {
    /// A loop that starts at `start_ns`; `opts` as for [`super::run`] (only `stall` matters here:
    /// the caller sends at its own rate).
    pub fn new(
        pipeline: Pipeline,
        opts: &super::RuntimeOptions,
        logger: Option<LogHandle>,
        start_ns: u64,
    ) -> Result<Self, RuntimeError> {
        opts.validate()?;
        Ok(Self {
            slot: FrameSlot::new(),
            stepper: Stepper::new(pipeline, logger.clone()),
            setpoints: Setpoints::new(opts.stall, logger.clone()),
            alarms: Alarms::new(opts.alarm_hold, logger),
            odometry: OdometryHistory::new(128),
            stall_ns: opts.stall.as_nanos() as u64,
            last_frame_ns: start_ns,
            camera_down: false,
            step_failures: 0,
        })
    }

    pub fn pipeline(&self) -> &Pipeline {
        self.stepper.pipeline()
    }

    pub fn pipeline_mut(&mut self) -> &mut Pipeline {
        self.stepper.pipeline_mut()
    }

    /// An odometry sample from the base, stamped on the loop's clock.
    pub fn on_odometry(&mut self, odometry: Odometry) {
        self.odometry.push(odometry);
    }

    /// A status from the base at `now_ns`. Returns the set-point to send now when an alarm was
    /// raised (a zero), else `None` (the next frame or tick says what to send).
    pub fn on_status(&mut self, status: &BaseStatus, now_ns: u64) -> Option<BodyVelocity> {
        self.alarms.on_status(status, now_ns).then_some(BodyVelocity::ZERO)
    }

    /// Stops the base's alarms caused (halts and bumper presses).
    pub fn alarm_stops(&self) -> u64 {
        self.alarms.stops()
    }

    /// The velocity the step would get for a frame captured at `t_ns`.
    pub fn velocity_for(&self, t_ns: u64) -> BodyVelocity {
        self.stepper.velocity_for(&self.odometry, t_ns)
    }

    /// A frame from the camera at `now_ns`: through the slot (latest wins), the step and the
    /// set-point rules. Returns what the step gave (`None`: no frame reached the step) and the
    /// set-point to send now. A panic in the step is an error: stop the robot and end.
    pub fn on_frame(
        &mut self,
        frame: Frame,
        encoded: Option<Arc<[u8]>>,
        now_ns: u64,
    ) -> Result<(Option<Stepped>, BodyVelocity), RuntimeError> {
        self.camera_down = false;
        self.last_frame_ns = frame.t_ns;
        self.slot.put(frame);
        let Taken::Frame(frame) = self.slot.take(Duration::ZERO) else {
            return Ok((None, self.on_tick(now_ns)));
        };
        let velocity = self.velocity_for(frame.t_ns);
        let stepped = self.stepper.step(frame, velocity, encoded);
        let send = match &stepped {
            Stepped::Output { seq, t_ns, output, .. } => {
                self.setpoints.on_setpoint(*seq, *t_ns, output.setpoint(), now_ns).velocity()
            }
            Stepped::Primed => self.command_now(now_ns),
            Stepped::Failed { seq, error, .. } => {
                self.step_failures += 1;
                let detail = format!("step failed on frame {seq}: {error}");
                self.setpoints.failsafe(Failsafe::StepFailed, &detail, now_ns)
            }
            Stepped::Panicked(message) => return Err(RuntimeError::StepPanicked(message.clone())),
        };
        Ok((Some(stepped), self.alarms.gate(send, now_ns)))
    }

    /// A camera error at `now_ns`. `Ok(true)`: the source ended, stop and end the run normally;
    /// `Ok(false)`: go on (send [`Self::on_tick`]'s set-point); an error: stop and end.
    pub fn on_camera_error<E: hal::Error>(&mut self, error: &E, now_ns: u64) -> Result<bool, RuntimeError> {
        match camera_trouble(error.kind()) {
            CameraTrouble::Skip => Ok(false),
            CameraTrouble::Down => {
                if !self.camera_down {
                    self.camera_down = true;
                    self.setpoints.failsafe(Failsafe::CameraDown, &error.to_string(), now_ns);
                }
                Ok(false)
            }
            CameraTrouble::End => Ok(true),
            CameraTrouble::Fatal => Err(RuntimeError::Camera(format!("camera: {error}"))),
        }
    }

    /// What the base gets at `now_ns` when no frame was stepped: the command in force, or a
    /// fail-safe zero once no frame came within the stall time or the command expired.
    pub fn on_tick(&mut self, now_ns: u64) -> BodyVelocity {
        let cmd = self.command_now(now_ns);
        self.alarms.gate(cmd, now_ns)
    }

    /// [`Self::on_tick`] before the alarms.
    fn command_now(&mut self, now_ns: u64) -> BodyVelocity {
        if now_ns.saturating_sub(self.last_frame_ns) >= self.stall_ns && self.stepper.stall(now_ns) {
            self.setpoints.failsafe(Failsafe::Expired, "no frame within the stall time", now_ns);
        }
        self.setpoints.on_tick(now_ns)
    }

    /// Zero set-points forced while a valid command was in force (expiry, step failure, camera
    /// down).
    pub fn failsafe_stops(&self) -> u64 {
        self.setpoints.failsafe_stops()
    }

    /// Steps that failed.
    pub fn step_failures(&self) -> u64 {
        self.step_failures
    }

    /// Frames replaced in the slot before the step took them.
    pub fn frames_dropped(&self) -> u64 {
        self.slot.dropped()
    }
}

pub(super) fn panic_message(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic payload".into())
}

/// CPU time of the calling thread, ns (0 if the clock cannot be read).
fn thread_cpu_ns() -> u64 {
    match nix::time::clock_gettime(nix::time::ClockId::CLOCK_THREAD_CPUTIME_ID) {
        Ok(ts) => ts.tv_sec() as u64 * 1_000_000_000 + ts.tv_nsec() as u64,
        Err(_) => 0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn v(v: f64) -> BodyVelocity {
        BodyVelocity::new(v, 0.0)
    }

    #[test]
    fn a_setpoint_holds_until_stall_after_its_frame_then_stops() {
        let mut s = Setpoints::new(Duration::from_millis(150), None);
        assert_eq!(s.on_tick(0), BodyVelocity::ZERO, "standing still before the first set-point");
        assert_eq!(s.on_setpoint(1, 100 * MS, v(0.3), 105 * MS), Order::Drive(v(0.3)));
        assert_eq!(s.expires_ns(), Some(250 * MS));
        assert_eq!(s.on_tick(249 * MS), v(0.3), "refreshed while valid");
        assert_eq!(s.on_tick(250 * MS), BodyVelocity::ZERO, "expired");
        assert_eq!((s.failsafe_stops(), s.expires_ns()), (1, None));
        assert_eq!(s.on_tick(400 * MS), BodyVelocity::ZERO, "stays stopped, counted once");
        assert_eq!(s.failsafe_stops(), 1);
    }

    #[test]
    fn a_late_setpoint_and_a_failure_give_a_zero_at_once() {
        let mut s = Setpoints::new(Duration::from_millis(150), None);
        assert_eq!(s.on_setpoint(1, 0, v(0.3), 150 * MS), Order::Stop, "older than the stall time");
        assert_eq!(s.failsafe_stops(), 0, "no valid command was replaced");
        assert_eq!(s.on_setpoint(2, 160 * MS, v(0.2), 170 * MS), Order::Drive(v(0.2)));
        assert_eq!(s.failsafe(Failsafe::StepFailed, "bad frame", 200 * MS), BodyVelocity::ZERO);
        assert_eq!(s.on_tick(201 * MS), BodyVelocity::ZERO);
        assert_eq!(s.failsafe_stops(), 1);
    }

    #[test]
    fn camera_errors_map_to_the_safety_rules() {
        assert_eq!(camera_trouble(ErrorKind::Timeout), CameraTrouble::Skip);
        assert_eq!(camera_trouble(ErrorKind::BadData), CameraTrouble::Skip);
        assert_eq!(camera_trouble(ErrorKind::Disconnected), CameraTrouble::Down);
        assert_eq!(camera_trouble(ErrorKind::EndOfStream), CameraTrouble::End);
        assert_eq!(camera_trouble(ErrorKind::Unsupported), CameraTrouble::Fatal);
        assert_eq!(camera_trouble(ErrorKind::Other), CameraTrouble::Fatal);
    }
}
