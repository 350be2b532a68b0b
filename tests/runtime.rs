//! `flownav::runtime::run` over real pseudo-terminals: the FNP/1 driver talks to the simulated
//! base (`mocks::sim_base`, real-time clock), frames come from an in-test camera or a frame
//! folder, and every assertion is about what the base received.
//!
//! The base side records each chunk of bytes it received: its own simulated time, the host
//! monotonic time of arrival (the clock frames are stamped with) and the command in force after
//! it, and each STATUS it sent with its flags. The tests assert the order and the counts of what
//! the base received; where a bound on time cannot be avoided it is a stated, generous margin
//! (1 s for a rule of 150 ms or one control period). The real-time figures (stop delay,
//! set-point rate) are measured by `bench/runtime_timing.sh`, not asserted here.

use flownav::config::Config;
use flownav::runtime::{EndReason, RunReport, RuntimeError, RuntimeOptions, run};
use flownav::sources::{CameraSpec, open_camera};
use flownav::step::Pipeline;
use hal::camera::monotonic_ns;
use hal::fnp_driver::{FnpBase, FnpConfig};
use hal::{BodyVelocity, Calibration, Camera, Error, ErrorKind, Frame, LumaImage};
use mocks::kinematics::{DiffDrive, Pose};
use mocks::sim_base::{ServeOptions, SimBase, SimBaseConfig, SimDevice, SimServer};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::time::timeout;

const GUARD: Duration = Duration::from_secs(20);
const WIDTH: usize = 320;
const HEIGHT: usize = 240;

/// What the simulated base saw in one chunk of received bytes.
#[derive(Clone, Copy, Debug)]
struct Received {
    /// The base's simulated time, s.
    sim_s: f64,
    /// Host monotonic time of arrival, ns.
    host_ns: u64,
    setpoints: u64,
    stops: u64,
    /// The command in force afterwards.
    commanded: BodyVelocity,
}

/// The simulated FNP/1 base, recording what it receives and the flags of each STATUS it sends.
struct Recording {
    base: SimBase,
    received: Vec<Received>,
    /// (simulated time, flags) of each STATUS sent.
    statuses: Vec<(f64, u8)>,
}

impl SimDevice for Recording {
    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        let before = self.base.counters();
        self.base.receive(bytes, out);
        let after = self.base.counters();
        let (setpoints, stops) = (after.setpoints - before.setpoints, after.stops - before.stops);
        if setpoints + stops > 0 {
            self.received.push(Received {
                sim_s: self.base.time_s(),
                host_ns: monotonic_ns(),
                setpoints,
                stops,
                commanded: self.base.commanded(),
            });
        }
    }
    fn advance(&mut self, dt: f64, out: &mut Vec<u8>) {
        let before = self.base.counters().status_sent;
        self.base.advance(dt, out);
        if self.base.counters().status_sent > before {
            self.statuses.push((self.base.time_s(), self.base.flags()));
        }
    }
    fn pose(&self) -> Pose {
        self.base.pose()
    }
    fn drive(&mut self) -> &mut DiffDrive {
        self.base.drive()
    }
}

type Server = SimServer<Recording>;

fn serve(link: Option<std::path::PathBuf>) -> Server {
    serve_with(SimBaseConfig::default(), link)
}

fn serve_with(cfg: SimBaseConfig, link: Option<std::path::PathBuf>) -> Server {
    let device = Recording { base: SimBase::new(cfg), received: Vec::new(), statuses: Vec::new() };
    SimServer::start(device, ServeOptions { link, ..Default::default() }).unwrap()
}

async fn connect(port: &std::path::Path) -> FnpBase {
    timeout(GUARD, FnpBase::connect(FnpConfig::new(port.to_string_lossy()))).await.unwrap().unwrap()
}

fn received(server: &Server) -> Vec<Received> {
    server.with_device(|d| d.received.clone())
}

fn pipeline() -> Pipeline {
    let calib = Calibration::load(concat!(env!("CARGO_MANIFEST_DIR"), "/calib/c310.toml")).unwrap();
    let mut cfg = Config::default();
    cfg.flow.backend = flownav::flow::Backend::Cpu;
    Pipeline::new(&cfg, calib, None).unwrap()
}

/// A textured scene seen by a camera panning `shift` pixels per frame: real flow everywhere.
fn scene(width: usize, height: usize, shift: f64) -> LumaImage {
    LumaImage::from_fn(width, height, |x, y| {
        let (x, y) = (x as f64 + shift, y as f64);
        let v = 128.0
            + 45.0 * (0.31 * x + 0.17 * y).sin()
            + 35.0 * (0.11 * x - 0.23 * y).sin()
            + 25.0 * (0.53 * x * 0.7 + 0.41 * y).cos();
        v.clamp(0.0, 255.0) as u8
    })
}

/// What the in-test camera does after its frames.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Then {
    /// Report the end of the stream.
    End,
    /// Stop delivering: stall timeouts forever.
    Stall,
}

#[derive(Debug, thiserror::Error)]
#[error("test camera: {0:?}")]
struct CamError(ErrorKind);
impl Error for CamError {
    fn kind(&self) -> ErrorKind {
        self.0
    }
}

/// (capture stamp ns, width) of each delivered frame.
type Delivered = Arc<Mutex<Vec<(u64, usize)>>>;

/// Frames at `fps`, stamped on the monotonic clock when delivered; frame `odd_size_at` (if
/// any) is smaller than the rest. Records each delivered frame's stamp and size.
struct TestCamera {
    fps: f64,
    frames: u64,
    then: Then,
    odd_size_at: Option<u64>,
    seq: u64,
    next_ns: Option<u64>,
    delivered: Delivered,
}

impl TestCamera {
    fn new(fps: f64, frames: u64, then: Then) -> (Self, Delivered) {
        let delivered = Arc::new(Mutex::new(Vec::new()));
        let cam = Self { fps, frames, then, odd_size_at: None, seq: 0, next_ns: None, delivered: delivered.clone() };
        (cam, delivered)
    }
}

impl Camera for TestCamera {
    type Error = CamError;

    fn capture(&mut self) -> Result<Frame, CamError> {
        if self.seq >= self.frames {
            return match self.then {
                Then::End => Err(CamError(ErrorKind::EndOfStream)),
                Then::Stall => {
                    std::thread::sleep(Duration::from_millis(50));
                    Err(CamError(ErrorKind::Timeout))
                }
            };
        }
        let mut due = *self.next_ns.get_or_insert_with(monotonic_ns);
        if self.odd_size_at.is_some_and(|odd| self.seq == odd + 1) {
            // A pause after the odd frame, so that a step slowed by a loaded machine takes it
            // before a newer frame replaces it in the slot (latest wins).
            due += 500_000_000;
        }
        let now = monotonic_ns();
        if due > now {
            std::thread::sleep(Duration::from_nanos(due - now));
        }
        self.next_ns = Some(due + (1e9 / self.fps) as u64);
        let (w, h) = if self.odd_size_at == Some(self.seq) { (WIDTH / 2, HEIGHT / 2) } else { (WIDTH, HEIGHT) };
        let image = scene(w, h, self.seq as f64 * 2.0);
        let frame = Frame { seq: self.seq, t_ns: monotonic_ns(), image };
        self.delivered.lock().unwrap().push((frame.t_ns, w));
        self.seq += 1;
        Ok(frame)
    }
}

fn opts() -> RuntimeOptions {
    RuntimeOptions::default()
}

async fn run_until<C: Camera + 'static>(
    camera: C,
    base: FnpBase,
    shutdown_after: Duration,
) -> Result<RunReport, RuntimeError> {
    timeout(GUARD, run(camera, base, pipeline(), None, tokio::time::sleep(shutdown_after), opts())).await.unwrap()
}

fn is_moving(r: &Received) -> bool {
    r.commanded != BodyVelocity::ZERO
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_command_is_refreshed_between_frames_and_never_piles_up() {
    let server = serve(None);
    let base = connect(&server.pty_path()).await;
    // 10 fps: between frames only the runtime's refresh (25 Hz) keeps the base fed.
    let (camera, _) = TestCamera::new(10.0, 1000, Then::Stall);
    let report = run_until(camera, base, Duration::from_millis(1500)).await.unwrap();
    let (setpoints, sim_s) = server.with_device(|d| (d.base.counters().setpoints, d.base.time_s()));
    let first_s = received(&server).first().map_or(0.0, |r| r.sim_s);
    let rate = setpoints as f64 / (sim_s - first_s);
    eprintln!(
        "set-point rate: {rate:.1} per second of the base's clock ({setpoints} set-points, {} from frames); {report:?}",
        report.latency.count
    );
    assert!(report.latency.count > 3, "{report:?}");
    // Counts, not rates: more set-points than frames gave (the refresh ran), and never more than
    // a new one per frame plus one refresh per period plus the driver's own repeats (a bound a
    // slow machine can only stay further below).
    assert!(setpoints > report.latency.count + 1, "{setpoints} set-points for {} from frames", report.latency.count);
    let period_bound = (sim_s * (25.0 + 25.0)).ceil() as u64 + report.latency.count + 5;
    assert!(setpoints <= period_bound, "{setpoints} set-points > {period_bound}: refreshes pile up");
    assert_eq!(report.setpoints_refused, 0);
    assert!(received(&server).iter().any(is_moving), "the pipeline drove the robot");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_camera_stops_the_base_within_200_ms_of_its_last_frame() {
    let server = serve(None);
    let base = connect(&server.pty_path()).await;
    let (camera, delivered) = TestCamera::new(30.0, 20, Then::Stall);
    let report = run_until(camera, base, Duration::from_millis(1500)).await.unwrap();
    let last_frame_ns = delivered.lock().unwrap().last().unwrap().0;
    let rx = received(&server);
    let after: Vec<&Received> = rx.iter().filter(|r| r.host_ns > last_frame_ns).collect();
    assert!(after.first().is_some_and(|r| is_moving(r)), "the last frame's set-point drove the robot: {after:?}");
    let first_zero = after.iter().find(|r| !is_moving(r)).expect("a zero command after the stall");
    let delay_ms = (first_zero.host_ns - last_frame_ns) as f64 * 1e-6;
    eprintln!("stall: zero {delay_ms:.1} ms after the last frame; {report:?}");
    // The fail-safe's zero SETPOINT, not the shutdown's STOP (which comes at 1.5 s).
    assert!(first_zero.setpoints > 0 && first_zero.stops == 0, "{first_zero:?}");
    // The rule is 150 ms (measured by bench/runtime_timing.sh); the margin here is 1 s.
    assert!(delay_ms <= 1000.0, "zero {delay_ms:.0} ms after the last frame");
    let zero_sim_s = first_zero.sim_s;
    assert!(
        rx.iter().filter(|r| r.sim_s > zero_sim_s).all(|r| !is_moving(r)),
        "the base stays stopped while the camera stalls"
    );
    assert!(report.failsafe_stops >= 1, "{report:?}");
    assert_eq!(report.ended, EndReason::Shutdown);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_sends_stop_last() {
    let server = serve(None);
    let base = connect(&server.pty_path()).await;
    let (camera, _) = TestCamera::new(30.0, 10_000, Then::End);
    let report = run_until(camera, base, Duration::from_millis(1000)).await.unwrap();
    assert_eq!(report.ended, EndReason::Shutdown);
    tokio::time::sleep(Duration::from_millis(100)).await;
    let rx = received(&server);
    assert!(rx.iter().any(is_moving), "it drove before the shutdown");
    let last = rx.last().unwrap();
    assert!(last.stops > 0 && last.commanded == BodyVelocity::ZERO, "last received: {last:?}");
    assert_eq!(server.with_device(|d| d.base.commanded()), BodyVelocity::ZERO);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_step_sends_a_zero_setpoint_and_the_run_goes_on() {
    let server = serve(None);
    let base = connect(&server.pty_path()).await;
    let (mut camera, delivered) = TestCamera::new(30.0, 40, Then::End);
    camera.odd_size_at = Some(20);
    let report = run_until(camera, base, GUARD).await.unwrap();
    assert_eq!(report.ended, EndReason::EndOfStream);
    assert_eq!(report.step_failures, 1, "only the odd frame fails: {report:?}");
    let odd_ns = delivered.lock().unwrap()[20].0;
    let rx = received(&server);
    assert!(rx.iter().any(|r| r.host_ns < odd_ns && is_moving(r)), "moving before the bad frame");
    let zero = rx.iter().find(|r| r.host_ns > odd_ns && !is_moving(r)).expect("a zero after the bad frame");
    assert!(zero.setpoints > 0, "a zero set-point, the run goes on: {zero:?}");
    assert!(rx.iter().any(|r| r.host_ns > zero.host_ns && is_moving(r)), "set-points resume with the next good frames");
    assert!(report.failsafe_stops >= 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frame_folder_plays_to_its_end_then_the_base_is_stopped() {
    let dir = tempfile::tempdir().unwrap();
    for i in 0..12 {
        flownav::frames::save_png(&scene(WIDTH, HEIGHT, i as f64 * 2.0), dir.path().join(format!("{i:04}.png")))
            .unwrap();
    }
    let spec: CameraSpec = format!("frames:{}", dir.path().display()).parse().unwrap();
    let camera = open_camera(&spec, &Config::default().camera, false).unwrap();
    let server = serve(None);
    let base = connect(&server.pty_path()).await;
    let report = run_until(camera, base, GUARD).await.unwrap();
    assert_eq!(report.ended, EndReason::EndOfStream);
    assert_eq!(report.frames_captured, 12);
    assert_eq!(report.frames_processed + report.frames_dropped, 12, "{report:?}");
    tokio::time::sleep(Duration::from_millis(100)).await;
    let last = *received(&server).last().unwrap();
    assert!(last.stops > 0 && last.commanded == BodyVelocity::ZERO, "last received: {last:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn setpoints_resume_after_the_base_link_comes_back() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyBASE");
    let server = serve(Some(link.clone()));
    let base = connect(&link).await;
    let (camera, _) = TestCamera::new(30.0, 10_000, Then::End);
    let task = tokio::spawn(run_until(camera, base, Duration::from_millis(2500)));
    tokio::time::sleep(Duration::from_millis(600)).await;
    server.disconnect(Duration::from_millis(300));
    let reconnected_at = loop {
        tokio::time::sleep(Duration::from_millis(10)).await;
        if server.pty_generation() > 0 {
            break monotonic_ns();
        }
    };
    let report = task.await.unwrap().unwrap();
    let rx = received(&server);
    let resumed = rx.iter().filter(|r| r.host_ns > reconnected_at && r.setpoints > 0 && is_moving(r)).count();
    assert!(resumed >= 3, "{resumed} moving set-points after the reconnect; report {report:?}");
    assert!(report.base_disconnects >= 1 && report.link.reconnects >= 1, "{report:?}");
}

/// The first STATUS at or after `from_s` whose flags `want` (or, with `set == false`, lack) `flag`.
fn status_when(server: &Server, flag: u8, set: bool, from_s: f64) -> Option<f64> {
    server.with_device(|d| d.statuses.iter().find(|(t, f)| *t >= from_s && ((f & flag != 0) == set)).map(|(t, _)| *t))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_bases_bumper_and_estop_stop_the_robot() {
    use hal::fnp::flags::{BUMPER, ESTOP};
    let hold = Duration::from_millis(400);
    // The alarms are on the base's clock, which starts with the server: build the pipeline first.
    let pipeline = pipeline();
    let alarms = ["bumper@1.2+0.5", "estop@2.2+0.4"].map(|s| s.parse().unwrap()).to_vec();
    let server = serve_with(SimBaseConfig { alarms, ..Default::default() }, None);
    let base = connect(&server.pty_path()).await;
    let (camera, _) = TestCamera::new(30.0, 10_000, Then::End);
    let opts = RuntimeOptions { alarm_hold: hold, ..opts() };
    let shutdown = tokio::time::sleep(Duration::from_millis(3800));
    let report = timeout(GUARD, run(camera, base, pipeline, None, shutdown, opts)).await.unwrap().unwrap();
    let rx = received(&server);
    let forward = |r: &Received| r.commanded.v > 0.0;

    // Bumper: forward before; after the STATUS that reports it, a zero, then no forward speed
    // until a STATUS reports it released.
    let pressed = status_when(&server, BUMPER, true, 0.0).expect("a STATUS with the bumper");
    let released = status_when(&server, BUMPER, false, pressed).expect("a STATUS with the bumper released");
    assert!(rx.iter().any(|r| r.sim_s < pressed && forward(r)), "driving forward before the bumper");
    let zero =
        rx.iter().find(|r| r.sim_s >= pressed && r.commanded == BodyVelocity::ZERO).expect("a zero after the bumper");
    let in_flight: u64 = rx.iter().filter(|r| r.sim_s >= pressed && r.sim_s < zero.sim_s).map(|r| r.setpoints).sum();
    eprintln!("bumper: zero {:.0} ms after its STATUS, {in_flight} set-points before it", (zero.sim_s - pressed) * 1e3);
    // The rule is one control period (bench/runtime_timing.sh measures it); the margin is 1 s.
    assert!(zero.sim_s - pressed <= 1.0, "zero {:.3} s after the bumper", zero.sim_s - pressed);
    let pushed: Vec<&Received> =
        rx.iter().filter(|r| r.sim_s > zero.sim_s && r.sim_s < released && forward(r)).collect();
    assert!(pushed.is_empty(), "forward set-points while the bumper was pressed: {pushed:?}");

    // E-stop: a zero after its STATUS, then nothing but zeros while it is set and during the hold.
    let raised = status_when(&server, ESTOP, true, 0.0).expect("a STATUS with the e-stop");
    let cleared = status_when(&server, ESTOP, false, raised).expect("a STATUS with the e-stop cleared");
    let zero =
        rx.iter().find(|r| r.sim_s >= raised && r.commanded == BodyVelocity::ZERO).expect("a zero after the e-stop");
    eprintln!("e-stop: zero {:.0} ms after its STATUS", (zero.sim_s - raised) * 1e3);
    assert!(zero.sim_s - raised <= 1.0, "zero {:.3} s after the e-stop", zero.sim_s - raised);
    // Half the hold as margin between the base's clock and the host's.
    let quiet_until = cleared + hold.as_secs_f64() / 2.0;
    let moved: Vec<&Received> =
        rx.iter().filter(|r| r.sim_s > zero.sim_s && r.sim_s < quiet_until && is_moving(r)).collect();
    assert!(moved.is_empty(), "moving set-points during the e-stop or its hold: {moved:?}");
    let zeros = rx.iter().filter(|r| r.sim_s > zero.sim_s && r.sim_s < cleared).map(|r| r.setpoints).sum::<u64>();
    assert!(zeros >= 3, "the zero was refreshed during the e-stop ({zeros} set-points)");
    assert!(rx.iter().any(|r| r.sim_s > cleared + hold.as_secs_f64() && is_moving(r)), "driving again after the hold");
    assert_eq!(report.alarm_stops, 2, "{report:?}");
}

/// A camera that delivers MJPEG frames like a UVC webcam: the luma it returns is the decode of
/// the JPEG bytes it hands out through `take_encoded`.
struct JpegCamera {
    inner: TestCamera,
    decoder: hal::mjpeg::MjpegDecoder,
    last: Option<Arc<[u8]>>,
    sent: Arc<Mutex<Vec<Arc<[u8]>>>>,
}

impl Camera for JpegCamera {
    type Error = CamError;

    fn capture(&mut self) -> Result<Frame, CamError> {
        let mut frame = self.inner.capture()?;
        let mut jpeg = Vec::new();
        let img = &frame.image;
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90)
            .encode(img.data(), img.width() as u32, img.height() as u32, image::ExtendedColorType::L8)
            .map_err(|_| CamError(ErrorKind::BadData))?;
        self.decoder.decode_into(&jpeg, &mut frame.image).map_err(|_| CamError(ErrorKind::BadData))?;
        let jpeg: Arc<[u8]> = jpeg.into();
        self.sent.lock().unwrap().push(jpeg.clone());
        self.last = Some(jpeg);
        Ok(frame)
    }

    fn take_encoded(&mut self) -> Option<Arc<[u8]>> {
        self.last.take()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mjpeg_frames_are_logged_as_the_camera_sent_them() {
    use flownav::logging::{LogEvent, LogReader, LogWriter, LoggedImage, record};
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.mcap");
    let cfg = Config::default();
    let options = record::run_options("run", &cfg, &Calibration::nominal_c310(), None, None);
    let writer = LogWriter::create_at(&path, options).unwrap();
    let server = serve(None);
    let base = connect(&server.pty_path()).await;
    let (inner, _) = TestCamera::new(15.0, 12, Then::End);
    let sent = Arc::new(Mutex::new(Vec::new()));
    let camera = JpegCamera { inner, decoder: hal::mjpeg::MjpegDecoder::new(), last: None, sent: sent.clone() };
    let never = std::future::pending::<()>();
    let report = timeout(GUARD, run(camera, base, pipeline(), Some(writer.handle()), never, opts())).await.unwrap();
    assert_eq!(report.unwrap().ended, EndReason::EndOfStream);
    writer.close().unwrap();
    let sent = sent.lock().unwrap().clone();
    let mut jpegs = Vec::new();
    for entry in LogReader::open(&path).unwrap() {
        match entry.unwrap().event {
            LogEvent::Image(LoggedImage::Jpeg(bytes)) => jpegs.push(bytes),
            LogEvent::Image(other) => panic!("expected the camera's JPEG bytes, got {other:?}"),
            _ => {}
        }
    }
    assert!(!jpegs.is_empty(), "images were logged");
    for bytes in &jpegs {
        assert!(sent.iter().any(|s| s[..] == bytes[..]), "a logged image is byte-identical to one the camera sent");
    }
}
