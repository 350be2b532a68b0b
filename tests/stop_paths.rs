//! Every way the real `flownav` binary can be stopped, and what the base received last.
//!
//! `flownav run` plays a frame folder against the simulated FNP/1 base on a pseudo-terminal
//! served by this test (so the test sees every packet): SIGINT and SIGTERM end the run with
//! STOP as the last packet and exit status 0; a panic in the step (the debug-build hook
//! `FLOWNAV_TEST_PANIC_AT_STEP`) ends it with STOP and a non-zero status. A `flownav sim --log`
//! killed with SIGKILL leaves a log that `flownav log info` reads up to its last complete chunk.
//!
//! No assertion is on elapsed time: the test waits (up to a guard of 60 s for a debug build on
//! a loaded machine) for the base to be driven, delivers the signal, and checks what happened.

use hal::BodyVelocity;
use hal::fnp::{Decoder, Direction, Packet};
use mocks::kinematics::{DiffDrive, Pose};
use mocks::sim_base::{ServeOptions, SimBase, SimBaseConfig, SimDevice, SimServer};
use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

const GUARD: Duration = Duration::from_secs(60);

/// The simulated base, keeping every packet the host sent, in order.
struct Recording {
    base: SimBase,
    decoder: Decoder,
    packets: Vec<Packet>,
}

impl SimDevice for Recording {
    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        self.packets.extend(self.decoder.feed_collect(bytes).into_iter().map(|f| f.packet));
        self.base.receive(bytes, out);
    }
    fn advance(&mut self, dt: f64, out: &mut Vec<u8>) {
        self.base.advance(dt, out)
    }
    fn pose(&self) -> Pose {
        self.base.pose()
    }
    fn drive(&mut self) -> &mut DiffDrive {
        self.base.drive()
    }
}

type Server = SimServer<Recording>;

fn serve() -> Server {
    let device = Recording {
        base: SimBase::new(SimBaseConfig::default()),
        decoder: Decoder::new(Direction::HostToBase),
        packets: Vec::new(),
    };
    SimServer::start(device, ServeOptions::default()).unwrap()
}

fn packets(server: &Server) -> Vec<Packet> {
    server.with_device(|d| d.packets.clone())
}

fn moving(p: &Packet) -> bool {
    matches!(p, Packet::Setpoint { v_mm_s, omega_mrad_s } if (*v_mm_s, *omega_mrad_s) != (0, 0))
}

/// A textured scene panning 2 px per frame: real flow everywhere.
fn frames(dir: &Path, n: usize) {
    for i in 0..n {
        let shift = i as f64 * 2.0;
        let img = hal::LumaImage::from_fn(320, 240, |x, y| {
            let (x, y) = (x as f64 + shift, y as f64);
            let v = 128.0 + 45.0 * (0.31 * x + 0.17 * y).sin() + 35.0 * (0.11 * x - 0.23 * y).sin();
            v.clamp(0.0, 255.0) as u8
        });
        flownav::frames::save_png(&img, dir.join(format!("{i:04}.png"))).unwrap();
    }
}

fn flownav() -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_flownav"));
    cmd.arg("--calib").arg(concat!(env!("CARGO_MANIFEST_DIR"), "/calib/c310.toml"));
    cmd.args(["--flow-backend", "cpu"]).env_remove("FLOWNAV_TEST_PANIC_AT_STEP");
    cmd
}

/// `flownav run` on a 300-frame folder (10 s at 30 fps: longer than any test waits).
fn spawn_run(server: &Server, frames_dir: &Path, out: &Path, panic_at: Option<u64>) -> Child {
    let mut cmd = flownav();
    cmd.arg("run")
        .arg("--camera")
        .arg(format!("frames:{}", frames_dir.display()))
        .arg("--base")
        .arg(format!("fnp:{}", server.pty_path().display()))
        .arg("--no-log")
        .stdout(std::fs::File::create(out.join("stdout")).unwrap())
        .stderr(std::fs::File::create(out.join("stderr")).unwrap());
    if let Some(n) = panic_at {
        cmd.env("FLOWNAV_TEST_PANIC_AT_STEP", n.to_string());
    }
    cmd.spawn().unwrap()
}

/// Polls `ready` every 20 ms until it holds; panics (killing `child`) after the guard.
async fn wait_for(child: &mut Child, what: &str, mut ready: impl FnMut() -> bool) {
    let start = Instant::now();
    while !ready() {
        if start.elapsed() > GUARD {
            let _ = child.kill();
            panic!("timed out waiting for {what}");
        }
        if let Some(status) = child.try_wait().unwrap() {
            panic!("flownav exited ({status}) before {what}");
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

async fn wait_exit(child: &mut Child) -> ExitStatus {
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        if start.elapsed() > GUARD {
            let _ = child.kill();
            panic!("flownav did not exit");
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Runs `flownav run` until it drives the base, sends `signal`, and returns the exit status, the
/// packets the base received and stdout/stderr.
async fn run_and_signal(signal: Signal) -> (ExitStatus, Vec<Packet>, String, String) {
    let dir = tempfile::tempdir().unwrap();
    frames(dir.path(), 300);
    let server = serve();
    let mut child = spawn_run(&server, dir.path(), dir.path(), None);
    wait_for(&mut child, "a moving set-point", || packets(&server).iter().any(moving)).await;
    kill(Pid::from_raw(child.id() as i32), signal).unwrap();
    let status = wait_exit(&mut child).await;
    // The pty may still hold the driver's last bytes: let the server read them.
    tokio::time::sleep(Duration::from_millis(200)).await;
    let read = |name: &str| std::fs::read_to_string(dir.path().join(name)).unwrap();
    (status, packets(&server), read("stdout"), read("stderr"))
}

fn assert_stop_is_last(packets: &[Packet], stderr: &str) {
    assert!(packets.iter().any(moving), "it drove first; stderr:\n{stderr}");
    let last_command = packets.iter().rev().find(|p| matches!(p, Packet::Setpoint { .. } | Packet::Stop));
    assert_eq!(last_command, Some(&Packet::Stop), "STOP is the last command; stderr:\n{stderr}");
    assert_eq!(packets.last(), Some(&Packet::Stop), "nothing after it");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_stops_the_base_and_exits_0() {
    let (status, packets, stdout, stderr) = run_and_signal(Signal::SIGTERM).await;
    assert_eq!(status.code(), Some(0), "stderr:\n{stderr}");
    assert_stop_is_last(&packets, &stderr);
    assert!(stdout.contains("\"ended\":\"shutdown\""), "the run report: {stdout}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigint_stops_the_base_and_exits_0() {
    let (status, packets, stdout, stderr) = run_and_signal(Signal::SIGINT).await;
    assert_eq!(status.code(), Some(0), "stderr:\n{stderr}");
    assert_stop_is_last(&packets, &stderr);
    assert!(stdout.contains("\"ended\":\"shutdown\""), "the run report: {stdout}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panic_in_the_step_stops_the_base_and_exits_non_zero() {
    let dir = tempfile::tempdir().unwrap();
    frames(dir.path(), 300);
    let server = serve();
    // Step 0 primes the pair; steps 1..=7 drive; step 8 panics.
    let mut child = spawn_run(&server, dir.path(), dir.path(), Some(8));
    let status = wait_exit(&mut child).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let stderr = std::fs::read_to_string(dir.path().join("stderr")).unwrap();
    assert!(!status.success() && status.code().is_some(), "{status}; stderr:\n{stderr}");
    assert!(stderr.contains("FLOWNAV_TEST_PANIC_AT_STEP=8"), "the panic was the hook's: {stderr}");
    assert!(stderr.contains("the robot was stopped"), "{stderr}");
    assert_stop_is_last(&packets(&server), &stderr);
    assert_eq!(server.with_device(|d| d.base.commanded()), BodyVelocity::ZERO);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sim_killed_while_logging_leaves_a_readable_log() {
    let dir = tempfile::tempdir().unwrap();
    let logs = dir.path().join("logs");
    let mut child = flownav()
        .args(["sim", "--quiet", "--size", "320x180", "--max-time", "600", "--log"])
        .arg(&logs)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let log_file = || {
        let dir = std::fs::read_dir(&logs).ok()?;
        dir.filter_map(Result::ok).map(|e| e.path()).find(|p| p.extension().is_some_and(|x| x == "mcap"))
    };
    // Kill once the file on disk holds complete chunks with set-points (the writer finishes a
    // chunk at least every second), so there is something to recover.
    let flushed = || {
        let info = log_file().and_then(|p| flownav::logging::LogInfo::read(&p).ok());
        info.is_some_and(|i| i.topics.iter().any(|t| t.topic == "/control/setpoint" && t.count > 0))
    };
    wait_for(&mut child, "complete chunks in the log", flushed).await;
    child.kill().unwrap(); // SIGKILL: no destructor, no footer
    let status = wait_exit(&mut child).await;
    assert_eq!(status.code(), None, "killed by a signal");
    let path = log_file().unwrap();
    let out = flownav().args(["log", "info", "--json"]).arg(&path).output().unwrap();
    assert!(out.status.success(), "log info: {}", String::from_utf8_lossy(&out.stderr));
    let info: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(info["complete"], false, "{info}");
    assert!(info["truncation"].is_string(), "why it stopped is reported: {info}");
    let count = |topic: &str| {
        info["topics"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["topic"] == topic)
            .map_or(0, |t| t["count"].as_u64().unwrap())
    };
    assert!(count("/camera/image") > 0 && count("/control/setpoint") > 0, "{info}");
}
