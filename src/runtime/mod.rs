//! The async runtime of `flownav run`: camera → step → base, and the safety rules around it.
//!
//! [`run`] takes its world as arguments (STYLE.md "pass the world in"): a camera, a motor base,
//! the per-frame [`Pipeline`], an optional MCAP logger and a shutdown future. Tests hand in a
//! simulated base on a pseudo-terminal and an in-test camera; the CLI hands in the real ones.
//!
//! ```text
//!  camera thread ──put──▶ FrameSlot ──take──▶ step thread ──msg──▶ control task (async) ──▶ MotorBase
//!  (blocking capture)   (latest wins,         (Pipeline::step,     (set-points, expiry,      (driver task
//!                        stale dropped)        catch_unwind)        odometry, shutdown)        writes bytes)
//! ```
//!
//! The rules between a frame and a set-point live in [`control`], with the clock as an argument,
//! and `flownav sim` runs the same code on simulated time ([`control::ControlLoop`]); this module
//! adds the threads and the real clock around them:
//!
//! - **Camera** on a dedicated thread (`capture` blocks). Frames go through a one-frame
//!   [`slot::FrameSlot`]: a frame the step has not taken yet is replaced by the newer one and
//!   counted as dropped, so a slow step never builds a queue. Errors are sorted by
//!   [`control::camera_trouble`].
//! - **Step** on a second dedicated thread, never on the async threads, through
//!   [`control::Stepper`]: each frame is stepped with the measured velocity of the odometry
//!   stamped over the frame interval ([`odometry::OdometryHistory`]). A panic in the step is
//!   caught: the robot is stopped and the run ends with [`RuntimeError::StepPanicked`].
//! - **Control** in the caller's task, through [`control::Setpoints`] on the monotonic clock:
//!   sends each new set-point at once, refreshes the current command at `setpoint_rate_hz`
//!   (≥ 20 Hz; drivers zero commands that are not refreshed), wakes at the command's expiry, and
//!   enforces the safety rules below. Base events (odometry, status, link loss) are read here.
//!
//! Safety rules (DESIGN.md "Safety is a feature with tests"):
//! - A set-point **expires `stall` after the capture of the frame it was computed from**
//!   (default 150 ms). At expiry a zero set-point goes out at once, so a camera stall or a step
//!   slower than `stall` stops the robot within `stall` (< 200 ms) of the last frame.
//! - A step error (bad frame, flow failure) → zero set-point at once ([`Pipeline::fail_safe`]).
//! - Camera `Disconnected` → zero at once; the camera thread calls `capture` again with
//!   exponential back-off (wrap the camera in [`reopen::ReopeningCamera`] to reopen the device).
//! - Camera `EndOfStream` (a frame folder played to its end) → STOP, the run ends normally.
//! - Camera `Unsupported`/`Other` (a human must fix it) → STOP, the run ends with an error.
//! - Base `Disconnected` → the driver reconnects on its own; the runtime keeps refreshing and
//!   commands resume when the link is back.
//! - Base alarms ([`alarms`]): e-stop, cliff, wheel drop or motor fault → zero at once when the
//!   status arrives, zero while set and for `alarm_hold` after it clears; bumper → zero at once,
//!   then no forward speed while pressed (reversing and turning pass, for the stall recovery).
//! - The shutdown future (Ctrl-C, SIGTERM, `--duration`) → STOP, the run ends normally.
//! - On every exit path the base gets `stop()` and is then dropped (drivers write STOP on drop,
//!   also while a panic unwinds).

pub mod alarms;
pub mod config;
pub mod control;
pub mod latency;
pub mod odometry;
pub mod reopen;
pub mod slot;

use crate::logging::{LogHandle, LogLevel};
use crate::step::Pipeline;
use alarms::Alarms;
use control::{CameraTrouble, Failsafe, Order, Setpoints, Stepped, Stepper, camera_trouble, panic_message};
use hal::camera::monotonic_ns;
use hal::{BaseEvent, BodyVelocity, Camera, Error, ErrorKind, LinkStats, MotorBase};
use latency::{LatencyBins, LatencyHistogram, LatencySummary};
use odometry::OdometryHistory;
use serde::Serialize;
use slot::{Closed, FrameSlot, Taken};
use std::future::Future;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::mpsc;
use tokio::time::{Instant, MissedTickBehavior};

/// How the runtime behaves; [`RuntimeOptions::default`] is what `flownav run` uses without a
/// config file.
#[derive(Clone, Debug, PartialEq)]
pub struct RuntimeOptions {
    /// How often the current command is refreshed when no new set-point came, Hz (20..=1000).
    pub setpoint_rate_hz: f64,
    /// A set-point expires this long after its frame's capture (40..=190 ms).
    pub stall: Duration,
    /// First wait before calling `capture` again after the camera disconnected.
    pub camera_backoff_initial: Duration,
    /// The wait doubles after each failed attempt up to this.
    pub camera_backoff_max: Duration,
    /// After the base's halting alarms (e-stop, cliff, wheel drop, motor fault) clear, the robot
    /// stays stopped this long (100 ms..=60 s); see [`alarms`].
    pub alarm_hold: Duration,
}

impl Default for RuntimeOptions {
    fn default() -> Self {
        Self {
            setpoint_rate_hz: 25.0,
            stall: Duration::from_millis(150),
            camera_backoff_initial: Duration::from_millis(100),
            camera_backoff_max: Duration::from_millis(3200),
            alarm_hold: Duration::from_millis(1000),
        }
    }
}

impl RuntimeOptions {
    /// The options the `[base]` and `[run]` config tables give.
    pub fn from_config(cfg: &crate::config::Config) -> Self {
        Self {
            setpoint_rate_hz: cfg.base.setpoint_rate_hz,
            stall: Duration::from_millis(cfg.run.stall_ms),
            alarm_hold: Duration::from_millis(cfg.run.alarm_hold_ms),
            ..Self::default()
        }
    }

    pub(crate) fn validate(&self) -> Result<(), RuntimeError> {
        if !(self.setpoint_rate_hz.is_finite() && (20.0..=1000.0).contains(&self.setpoint_rate_hz)) {
            return Err(RuntimeError::Options(format!(
                "setpoint_rate_hz = {} must be in 20..=1000 Hz",
                self.setpoint_rate_hz
            )));
        }
        if !(Duration::from_millis(40)..=Duration::from_millis(190)).contains(&self.stall) {
            return Err(RuntimeError::Options(format!(
                "stall = {} ms must be in 40..=190 ms (the robot must stop within 200 ms of the last frame)",
                self.stall.as_millis()
            )));
        }
        if self.camera_backoff_initial.is_zero() || self.camera_backoff_max < self.camera_backoff_initial {
            return Err(RuntimeError::Options("camera back-off: need 0 < initial ≤ max".into()));
        }
        if !(Duration::from_millis(100)..=Duration::from_secs(60)).contains(&self.alarm_hold) {
            return Err(RuntimeError::Options(format!(
                "alarm_hold = {} ms must be in 100..=60000 ms",
                self.alarm_hold.as_millis()
            )));
        }
        Ok(())
    }
}

/// Why a run ended normally.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EndReason {
    /// The camera's source ended (`frames:DIR` played to its end).
    EndOfStream,
    /// The shutdown future completed (Ctrl-C, SIGTERM, `--duration`).
    Shutdown,
}

/// What a run did; logged at exit and returned by [`run`].
#[derive(Clone, Debug, Serialize)]
pub struct RunReport {
    pub ended: EndReason,
    pub duration_s: f64,
    /// Frames the camera delivered.
    pub frames_captured: u64,
    /// Frames that went through the step.
    pub frames_processed: u64,
    /// Frames replaced in the slot before the step took them (latest-frame-wins).
    pub frames_dropped: u64,
    /// Corrupt frames the camera skipped (`BadData`).
    pub frames_bad: u64,
    /// Stall timeouts the camera reported (no frame within its stall timeout).
    pub camera_timeouts: u64,
    /// Times the camera went away.
    pub camera_disconnects: u64,
    /// Steps that failed (each gave a zero set-point).
    pub step_failures: u64,
    /// Times the runtime forced a zero set-point while it had a valid command: expiry (stall or
    /// slow step), step failure, camera disconnect.
    pub failsafe_stops: u64,
    /// Stops the base's alarms caused: halts (e-stop, cliff, wheel drop, motor fault) and
    /// bumper presses.
    pub alarm_stops: u64,
    /// `set_velocity` calls that succeeded (new set-points, refreshes and zeros).
    pub setpoints_sent: u64,
    /// `set_velocity` calls the driver refused (link down).
    pub setpoints_refused: u64,
    pub odometry_events: u64,
    pub status_events: u64,
    /// Capture → `set_velocity` returned, for every set-point computed from a frame.
    pub latency: LatencySummary,
    /// The latency's distribution: the count of set-points per `bin_ms` bin from 0 ms.
    pub latency_histogram: LatencyBins,
    /// The first part of the latency: capture stamp → the step thread takes the frame (for a
    /// camera, decoding; then the hand-over and any wait for the step thread).
    pub latency_wait: LatencySummary,
    /// Wall-clock time of `Pipeline::step` per frame (the part of the latency that is the step).
    pub step_wall: LatencySummary,
    /// The last part of the latency: the step's end → `set_velocity` returned (the channel to
    /// the control task, its wake-up, the alarm gate and the driver).
    pub latency_deliver: LatencySummary,
    /// CPU time of the step thread per step (`CLOCK_THREAD_CPUTIME_ID`): what the step costs on
    /// an idle core, where `step_wall` also counts waiting for a core on a loaded machine.
    pub step_cpu: LatencySummary,
    /// The driver's link counters at the end: frames received, dropped as malformed and lost
    /// (sequence gaps), disconnects and reconnects, command timeouts.
    pub link: LinkStats,
    /// `link.disconnects`, for the JSON summary.
    pub base_disconnects: u64,
    /// The live view's messages sent and dropped (`run --live`; filled in by the caller, which
    /// owns the server).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub live: Option<crate::logging::LiveStats>,
}

/// Why a run failed. In every case the base was told to stop before `run` returned.
#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    #[error("runtime options: {0}")]
    Options(String),
    #[error("{0} (the robot was stopped)")]
    Camera(String),
    #[error("the per-frame step panicked: {0} (the robot was stopped); this is a bug, please report it")]
    StepPanicked(String),
    #[error("cannot start the {what} thread: {source}")]
    Thread { what: &'static str, source: std::io::Error },
    #[error("the step thread ended unexpectedly (the robot was stopped)")]
    StepThreadLost,
}

/// From the camera and step threads to the control task.
#[derive(Debug)]
enum Msg {
    /// A set-point computed from the frame captured at `t_ns`.
    Setpoint {
        seq: u64,
        t_ns: u64,
        /// When the step thread took the frame and when its step ended (monotonic ns).
        taken_ns: u64,
        stepped_ns: u64,
        setpoint: BodyVelocity,
    },
    StepFailed {
        seq: u64,
        error: String,
    },
    /// No frame within `stall` (the step thread's view).
    Stalled,
    CameraDown(String),
    CameraUp,
    Ended(Closed),
    StepPanicked(String),
}

#[derive(Debug, Default)]
struct Counters {
    captured: AtomicU64,
    processed: AtomicU64,
    bad: AtomicU64,
    timeouts: AtomicU64,
    camera_disconnects: AtomicU64,
    step_failures: AtomicU64,
}

/// What the threads share with the control task.
struct Shared {
    slot: FrameSlot,
    counters: Counters,
    odometry: Mutex<OdometryHistory>,
    /// Step durations: (wall, thread CPU).
    step_times: Mutex<(LatencyHistogram, LatencyHistogram)>,
    stop: AtomicBool,
    /// The encoded bytes (MJPEG) of the latest frame put in the slot, with its `seq`, so the step
    /// thread logs the camera's bytes as they came instead of the decoded luma.
    encoded: Mutex<Option<(u64, std::sync::Arc<[u8]>)>>,
}

/// Runs the robot until the camera's source ends, `shutdown` completes, or a fatal error.
///
/// Must be called inside a tokio runtime (the base drivers need one). See the module docs for
/// the threads and the safety rules; `opts` must be valid (`setpoint_rate_hz` 20..=1000,
/// `stall` 40..=190 ms). `base.next_event` must be cancel-safe (the hal drivers' are).
pub async fn run<C, B>(
    camera: C,
    mut base: B,
    pipeline: Pipeline,
    logger: Option<LogHandle>,
    shutdown: impl Future<Output = ()>,
    opts: RuntimeOptions,
) -> Result<RunReport, RuntimeError>
where
    C: Camera + 'static,
    B: MotorBase + 'static,
{
    let started = Instant::now();
    if let Err(e) = opts.validate() {
        let _ = base.stop();
        return Err(e);
    }
    let shared = Arc::new(Shared {
        slot: FrameSlot::new(),
        encoded: Mutex::new(None),
        counters: Counters::default(),
        odometry: Mutex::new(OdometryHistory::new(128)),
        step_times: Mutex::new((LatencyHistogram::new(), LatencyHistogram::new())),
        stop: AtomicBool::new(false),
    });
    let (tx, mut rx) = mpsc::unbounded_channel();

    let step_thread = {
        let (shared, tx, stall, logger) = (shared.clone(), tx.clone(), opts.stall, logger.clone());
        std::thread::Builder::new()
            .name("flownav-step".into())
            .spawn(move || step_loop(pipeline, &shared, &tx, stall, logger))
    };
    let step_thread = match step_thread {
        Ok(t) => t,
        Err(source) => {
            let _ = base.stop();
            return Err(RuntimeError::Thread { what: "step", source });
        }
    };
    let camera_thread = {
        let (shared, tx, opts) = (shared.clone(), tx.clone(), opts.clone());
        std::thread::Builder::new()
            .name("flownav-camera".into())
            .spawn(move || camera_loop(camera, &shared, &tx, &opts))
    };
    drop(tx);
    if let Err(source) = camera_thread {
        shared.slot.close(Closed::Shutdown);
        let _ = base.stop();
        return Err(RuntimeError::Thread { what: "camera", source });
    }

    let mut control = Control::new(&opts, shared.clone(), logger);
    let result = control.run(&mut base, &mut rx, shutdown).await;

    // Stop first, then tidy up: the camera thread ends after its current capture (it is not
    // joined: a capture may block up to the camera's stall timeout), the step thread after its
    // current step.
    let _ = base.stop();
    shared.stop.store(true, Ordering::Relaxed);
    shared.slot.close(Closed::Shutdown);
    let joined = tokio::task::spawn_blocking(move || step_thread.join());
    if tokio::time::timeout(Duration::from_secs(2), joined).await.is_err() {
        tracing::warn!("the step thread did not end within 2 s; leaving it behind");
    }

    let c = &shared.counters;
    let step_times = shared.step_times.lock().unwrap_or_else(|e| e.into_inner()).clone();
    let link = base.link_stats();
    let report = |ended| RunReport {
        ended,
        duration_s: started.elapsed().as_secs_f64(),
        frames_captured: c.captured.load(Ordering::Relaxed),
        frames_processed: c.processed.load(Ordering::Relaxed),
        frames_dropped: shared.slot.dropped(),
        frames_bad: c.bad.load(Ordering::Relaxed),
        camera_timeouts: c.timeouts.load(Ordering::Relaxed),
        camera_disconnects: c.camera_disconnects.load(Ordering::Relaxed),
        step_failures: c.step_failures.load(Ordering::Relaxed),
        failsafe_stops: control.setpoints.failsafe_stops(),
        alarm_stops: control.alarms.stops(),
        setpoints_sent: control.sent,
        setpoints_refused: control.refused,
        odometry_events: control.odometry_events,
        status_events: control.status_events,
        latency: control.latency.summary(),
        latency_histogram: control.latency.bins(LATENCY_BIN_NS),
        latency_wait: control.wait.summary(),
        latency_deliver: control.deliver.summary(),
        step_wall: step_times.0.summary(),
        step_cpu: step_times.1.summary(),
        link,
        base_disconnects: link.disconnects,
        live: None,
    };
    let ended = match &result {
        Ok(e) => *e,
        Err(_) => EndReason::Shutdown,
    };
    let r = report(ended);
    tracing::info!(
        wait_median_ms = r.latency_wait.median_ms,
        step_wall_median_ms = r.step_wall.median_ms,
        deliver_median_ms = r.latency_deliver.median_ms,
        step_cpu_median_ms = r.step_cpu.median_ms,
        frames = r.frames_processed,
        dropped = r.frames_dropped,
        failsafe_stops = r.failsafe_stops,
        "latency capture → set-point: median {:.2} ms, p90 {:.2} ms, max {:.2} ms over {} set-points",
        r.latency.median_ms,
        r.latency.p90_ms,
        r.latency.max_ms,
        r.latency.count
    );
    if let Some(log) = &control.logger {
        log.log(
            monotonic_ns(),
            LogLevel::Info,
            format!(
                "run ended: {} frames, {} dropped, {} fail-safe stops; latency median {:.2} ms p90 {:.2} ms max {:.2} ms",
                r.frames_processed,
                r.frames_dropped,
                r.failsafe_stops,
                r.latency.median_ms,
                r.latency.p90_ms,
                r.latency.max_ms
            ),
        );
    }
    // Dropping the driver writes one more STOP, synchronously.
    drop(base);
    result.map(|_| r)
}

/// The control task: the [`Setpoints`] rules on the monotonic clock, the base's events.
struct Control {
    period: Duration,
    shared: Arc<Shared>,
    logger: Option<LogHandle>,
    setpoints: Setpoints,
    alarms: Alarms,
    latency: LatencyHistogram,
    /// The parts of the latency before and after the step ([`RunReport::latency_wait`],
    /// [`RunReport::latency_deliver`]).
    wait: LatencyHistogram,
    deliver: LatencyHistogram,
    sent: u64,
    refused: u64,
    odometry_events: u64,
    status_events: u64,
    base_down: bool,
    events_failing: bool,
    last_status: Option<hal::BaseStatus>,
}

/// Bin width of the latency histogram in the run report: fine enough to show a 1 ms budget's
/// share, coarse enough to stay a short line.
const LATENCY_BIN_NS: u64 = 500_000;

/// A tokio instant for a time on the monotonic clock frames are stamped with.
fn instant_at(t_ns: u64) -> Instant {
    let (now, now_ns) = (Instant::now(), monotonic_ns());
    if t_ns >= now_ns {
        now + Duration::from_nanos(t_ns - now_ns)
    } else {
        now.checked_sub(Duration::from_nanos(now_ns - t_ns)).unwrap_or(now)
    }
}

impl Control {
    fn new(opts: &RuntimeOptions, shared: Arc<Shared>, logger: Option<LogHandle>) -> Self {
        Self {
            period: Duration::from_secs_f64(1.0 / opts.setpoint_rate_hz),
            shared,
            setpoints: Setpoints::new(opts.stall, logger.clone()),
            alarms: Alarms::new(opts.alarm_hold, logger.clone()),
            logger,
            latency: LatencyHistogram::new(),
            wait: LatencyHistogram::new(),
            deliver: LatencyHistogram::new(),
            sent: 0,
            refused: 0,
            odometry_events: 0,
            status_events: 0,
            base_down: false,
            events_failing: false,
            last_status: None,
        }
    }

    async fn run<B: MotorBase>(
        &mut self,
        base: &mut B,
        rx: &mut mpsc::UnboundedReceiver<Msg>,
        shutdown: impl Future<Output = ()>,
    ) -> Result<EndReason, RuntimeError> {
        tokio::pin!(shutdown);
        let mut tick = tokio::time::interval(self.period);
        tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
        // The robot stands still until the first set-point.
        self.send(base, BodyVelocity::ZERO);
        tick.reset();
        loop {
            let expires_ns = self.setpoints.expires_ns();
            let events_pause = self.events_failing;
            tokio::select! {
                biased;
                () = &mut shutdown => {
                    tracing::info!("shutdown requested: stopping the robot");
                    return Ok(EndReason::Shutdown);
                }
                // Before the set-points: a status that raises an alarm must be read before the
                // next command goes out.
                ev = next_event(base, events_pause) => self.on_event(base, ev),
                msg = rx.recv() => {
                    let Some(msg) = msg else { return Err(RuntimeError::StepThreadLost) };
                    if let Some(end) = self.on_msg(base, msg) {
                        return end;
                    }
                    tick.reset();
                }
                () = tokio::time::sleep_until(expires_ns.map_or_else(Instant::now, instant_at)), if expires_ns.is_some() => {
                    // The timer fired for the expiry: judge at that moment, whatever the two
                    // clocks' last microseconds say.
                    let now_ns = monotonic_ns().max(expires_ns.unwrap_or(0));
                    let cmd = self.setpoints.on_tick(now_ns);
                    self.send(base, cmd);
                    tick.reset();
                }
                _ = tick.tick() => {
                    let cmd = self.setpoints.on_tick(monotonic_ns());
                    self.send(base, cmd);
                }
            }
        }
    }

    /// Sends `cmd` through the alarm rules; returns whether the driver took it.
    fn send<B: MotorBase>(&mut self, base: &mut B, cmd: BodyVelocity) -> bool {
        let cmd = self.alarms.gate(cmd, monotonic_ns());
        match base.set_velocity(cmd) {
            Ok(()) => {
                self.sent += 1;
                if self.base_down {
                    self.base_down = false;
                    tracing::info!("base link is back: set-points resume");
                }
                true
            }
            Err(e) => {
                self.refused += 1;
                if !self.base_down {
                    self.base_down = true;
                    tracing::warn!("base refuses set-points: {e}; retrying at the set-point rate");
                }
                false
            }
        }
    }

    /// Forces a zero set-point now ([`Setpoints::failsafe`]) and sends it.
    fn failsafe<B: MotorBase>(&mut self, base: &mut B, why: Failsafe, detail: &str) {
        let zero = self.setpoints.failsafe(why, detail, monotonic_ns());
        self.send(base, zero);
    }

    fn on_msg<B: MotorBase>(&mut self, base: &mut B, msg: Msg) -> Option<Result<EndReason, RuntimeError>> {
        match msg {
            Msg::Setpoint { seq, t_ns, taken_ns, stepped_ns, setpoint } => {
                if self.setpoints.on_setpoint(seq, t_ns, setpoint, monotonic_ns()) == Order::Stop {
                    self.send(base, BodyVelocity::ZERO);
                    return None;
                }
                if self.send(base, setpoint) {
                    let now = monotonic_ns();
                    let latency = now.saturating_sub(t_ns);
                    self.latency.record(latency);
                    self.wait.record(taken_ns.saturating_sub(t_ns));
                    self.deliver.record(now.saturating_sub(stepped_ns));
                    tracing::debug!(
                        seq,
                        v = setpoint.v,
                        omega = setpoint.omega,
                        latency_us = latency / 1000,
                        "set-point"
                    );
                }
            }
            Msg::StepFailed { seq, error } => {
                self.failsafe(base, Failsafe::StepFailed, &format!("step failed on frame {seq}: {error}"));
            }
            Msg::Stalled => self.failsafe(base, Failsafe::Expired, "no frame within the stall time"),
            Msg::CameraDown(error) => self.failsafe(base, Failsafe::CameraDown, &error),
            Msg::CameraUp => tracing::info!("camera delivers frames again"),
            Msg::StepPanicked(message) => return Some(Err(RuntimeError::StepPanicked(message))),
            Msg::Ended(Closed::EndOfStream(message)) => {
                tracing::info!("{message}: stopping the robot, ending the run");
                return Some(Ok(EndReason::EndOfStream));
            }
            Msg::Ended(Closed::Fatal(message)) => return Some(Err(RuntimeError::Camera(message))),
            Msg::Ended(Closed::Shutdown) => return Some(Ok(EndReason::Shutdown)),
        }
        None
    }

    fn on_event<B: MotorBase>(&mut self, base: &mut B, ev: Result<Option<BaseEvent>, B::Error>) {
        match ev {
            Ok(None) => {}
            Ok(Some(ev)) => {
                if self.events_failing {
                    self.events_failing = false;
                    tracing::info!("base events arrive again");
                }
                match ev {
                    BaseEvent::Odometry(o) => {
                        self.odometry_events += 1;
                        self.shared.odometry.lock().unwrap_or_else(|e| e.into_inner()).push(o);
                        if let Some(log) = &self.logger {
                            log.odometry(&o);
                        }
                    }
                    BaseEvent::Status(s) => {
                        self.status_events += 1;
                        // An alarm raised: a zero now, not at the next refresh.
                        if self.alarms.on_status(&s, monotonic_ns()) {
                            self.send(base, BodyVelocity::ZERO);
                        }
                        if s.stopped_by_watchdog && !self.last_status.is_some_and(|p| p.stopped_by_watchdog) {
                            tracing::warn!("base status: the base's watchdog stopped it");
                        }
                        self.last_status = Some(s);
                        if let Some(log) = &self.logger {
                            log.base_status(&s);
                        }
                    }
                }
            }
            Err(e) => {
                if !self.events_failing {
                    self.events_failing = true;
                    match e.kind() {
                        ErrorKind::Disconnected => tracing::warn!("base link lost: {e}; the driver reconnects"),
                        _ => tracing::warn!("base: {e}"),
                    }
                }
            }
        }
    }
}

/// The next base event; after an error, waits 100 ms first so a driver that keeps failing
/// (its task ended) cannot spin the loop.
async fn next_event<B: MotorBase>(base: &mut B, pause: bool) -> Result<Option<BaseEvent>, B::Error> {
    if pause {
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    base.next_event(Duration::from_millis(200)).await
}

/// The step thread: takes the newest frame, steps it ([`Stepper`]), reports to the control task.
fn step_loop(
    pipeline: Pipeline,
    shared: &Shared,
    tx: &mpsc::UnboundedSender<Msg>,
    stall: Duration,
    logger: Option<LogHandle>,
) {
    let mut stepper = Stepper::new(pipeline, logger);
    loop {
        let frame = match shared.slot.take(stall) {
            Taken::Frame(f) => f,
            Taken::TimedOut => {
                if stepper.stall(monotonic_ns()) {
                    let _ = tx.send(Msg::Stalled);
                }
                continue;
            }
            Taken::Closed(why) => {
                let _ = tx.send(Msg::Ended(why));
                return;
            }
        };
        let taken_ns = monotonic_ns();
        let velocity = stepper.velocity_for(&shared.odometry.lock().unwrap_or_else(|e| e.into_inner()), frame.t_ns);
        let encoded = match shared.encoded.lock().unwrap_or_else(|e| e.into_inner()).take() {
            Some((s, jpeg)) if s == frame.seq => Some(jpeg),
            _ => None,
        };
        let stepped = stepper.step(frame, velocity, encoded);
        {
            let (wall, cpu) = stepper.last_step_ns();
            let mut times = shared.step_times.lock().unwrap_or_else(|e| e.into_inner());
            times.0.record(wall);
            times.1.record(cpu);
        }
        shared.counters.processed.fetch_add(1, Ordering::Relaxed);
        let msg = match stepped {
            Stepped::Output { seq, t_ns, output, .. } => {
                Msg::Setpoint { seq, t_ns, taken_ns, stepped_ns: monotonic_ns(), setpoint: output.setpoint() }
            }
            Stepped::Primed => continue,
            Stepped::Failed { seq, error, .. } => {
                shared.counters.step_failures.fetch_add(1, Ordering::Relaxed);
                Msg::StepFailed { seq, error }
            }
            Stepped::Panicked(message) => {
                let _ = tx.send(Msg::StepPanicked(message));
                return;
            }
        };
        if tx.send(msg).is_err() {
            return;
        }
    }
}

/// The camera thread: captures in a loop, hands frames to the slot, reports trouble.
fn camera_loop<C: Camera>(mut camera: C, shared: &Shared, tx: &mpsc::UnboundedSender<Msg>, opts: &RuntimeOptions) {
    let c = &shared.counters;
    let mut backoff = opts.camera_backoff_initial;
    let mut down = false;
    while !shared.stop.load(Ordering::Relaxed) {
        match catch_unwind(AssertUnwindSafe(|| camera.capture())) {
            Ok(Ok(frame)) => {
                c.captured.fetch_add(1, Ordering::Relaxed);
                if down {
                    down = false;
                    backoff = opts.camera_backoff_initial;
                    let _ = tx.send(Msg::CameraUp);
                }
                let encoded = camera.take_encoded().map(|bytes| (frame.seq, bytes));
                *shared.encoded.lock().unwrap_or_else(|e| e.into_inner()) = encoded;
                shared.slot.put(frame);
            }
            Ok(Err(e)) => match camera_trouble(e.kind()) {
                CameraTrouble::Skip if e.kind() == ErrorKind::Timeout => {
                    c.timeouts.fetch_add(1, Ordering::Relaxed);
                    tracing::debug!("camera: {e}");
                }
                CameraTrouble::Skip => {
                    if c.bad.fetch_add(1, Ordering::Relaxed) < 10 {
                        tracing::warn!("camera: {e}");
                    }
                }
                CameraTrouble::Down => {
                    if !down {
                        down = true;
                        c.camera_disconnects.fetch_add(1, Ordering::Relaxed);
                        tracing::warn!("camera: {e}; retrying with back-off");
                        let _ = tx.send(Msg::CameraDown(e.to_string()));
                    }
                    sleep_unless_stopped(backoff, &shared.stop);
                    backoff = (backoff * 2).min(opts.camera_backoff_max);
                }
                CameraTrouble::End => {
                    shared.slot.close(Closed::EndOfStream(e.to_string()));
                    return;
                }
                CameraTrouble::Fatal => {
                    shared.slot.close(Closed::Fatal(format!("camera: {e}")));
                    return;
                }
            },
            Err(p) => {
                shared.slot.close(Closed::Fatal(format!("the camera panicked: {}", panic_message(p.as_ref()))));
                return;
            }
        }
    }
}

fn sleep_unless_stopped(d: Duration, stop: &AtomicBool) {
    let end = std::time::Instant::now() + d;
    while !stop.load(Ordering::Relaxed) {
        let now = std::time::Instant::now();
        if now >= end {
            return;
        }
        std::thread::sleep((end - now).min(Duration::from_millis(20)));
    }
}
