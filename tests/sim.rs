//! `flownav sim` in closed loop on a small world: rendered frames → the pipeline → the real
//! FNP/1 driver over a pty → the simulated base, to the goal without collisions.

use flownav::config::Config;
use flownav::pafsis::{GoalStatus, Mission, TopoMap};
use flownav::sim::{self, Progress, SimSetup, SimSummary};
use hal::{BodyVelocity, Calibration, Camera, ErrorKind, Frame, LumaImage};
use mocks::{RenderedCamera, World};

/// A 3 m wide, 8 m long empty hall; the robot starts at A facing east and must stop at B, 3 m on.
const HALL: &str = r#"
name = "hall"
wall_height = 2.6
ceiling_height = 2.6
start = { x = 1.0, y = 0.0, yaw_deg = 0.0 }

[[walls]]
name = "outer"
points = [[0.0, -1.5], [8.0, -1.5], [8.0, 1.5], [0.0, 1.5], [0.0, -1.5]]

[places]
A = [1.0, 0.0]
B = [4.0, 0.0]
"#;

const HALL_MAP: &str = r#"
name = "hall"

[[place]]
name = "A"
kind = "junction"
position_m = [1.0, 0.0]
heading_deg = 0

[[place]]
name = "B"
kind = "junction"
position_m = [4.0, 0.0]

[[edge]]
from = "A"
to = "B"
heading_deg = 0
actions = [{ do = "follow_corridor", length_m = 3.0 }]
"#;

fn hall_setup() -> SimSetup {
    let world = World::from_toml(HALL, "hall.toml").unwrap();
    let map = TopoMap::parse(HALL_MAP, "hall-map.toml").unwrap();
    let calib = Calibration::nominal_c310().scaled_to(320, 180);
    let mut setup = SimSetup::new(world, map, "A:B".parse::<Mission>().unwrap(), Config::default(), calib);
    setup.noise_sigma = 2.0;
    setup.max_time_s = 40.0;
    setup
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn closed_loop_reaches_the_goal_without_collisions() {
    let setup = hall_setup();
    let mut seconds = 0;
    let s = sim::run(&setup, None, |_| seconds += 1).await.expect("the simulation runs");
    assert!(s.reached, "{}", s.to_json_line());
    assert_eq!(s.status, GoalStatus::Arrived);
    assert_eq!(s.collisions, 0, "{}", s.to_json_line());
    assert_eq!(s.first_contact, None);
    assert!(s.goal_error_m <= 0.5, "{}", s.to_json_line());
    // 3 m of leg: the true path is at least that and not much more.
    assert!(s.path_m > 2.5 && s.path_m < 4.0, "{}", s.to_json_line());
    // The hall is 3 m wide: the robot centre never came within 0.5 m of a wall.
    assert!(s.min_clearance_m > 0.5, "{}", s.to_json_line());
    assert_eq!(s.frames as f64, (s.time_s * setup.fps).round() + 1.0);
    assert!(seconds >= s.time_s.floor() as usize, "one progress line per simulated second");
    assert_eq!(s.failsafe_stops, 0);
    assert!(!s.pose_hint);
}

/// What the rendered camera does from frame `at` on.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Fault {
    /// Frame `at` has half the size (the step fails on it), then no frame comes any more.
    BadFrameThenStall,
    /// No frame comes any more (stall timeouts).
    Stall,
}

#[derive(Debug, thiserror::Error)]
#[error("test camera: no frame")]
struct NoFrame;
impl hal::Error for NoFrame {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Timeout
    }
}

/// The simulator's rendered camera with a fault from frame `at` on.
struct Faulty {
    inner: RenderedCamera,
    at: u64,
    fault: Fault,
    seq: u64,
}

impl Camera for Faulty {
    type Error = NoFrame;

    fn capture(&mut self) -> Result<Frame, NoFrame> {
        let seq = self.seq;
        self.seq += 1;
        if seq > self.at || (seq == self.at && self.fault == Fault::Stall) {
            return Err(NoFrame);
        }
        let mut frame = self.inner.capture().map_err(|_| NoFrame)?;
        if seq == self.at {
            let (w, h) = (frame.image.width(), frame.image.height());
            frame.image = LumaImage::new(w / 2, h / 2);
        }
        Ok(frame)
    }
}

/// The hall mission for 3 s with `fault` from frame 40 (1.33 s) on: the summary and the
/// progress reports (one per simulated second, each with the set-point the simulated firmware
/// was seen to hold before time moved on).
async fn faulty_run(fault: Fault) -> (SimSummary, Vec<Progress>) {
    let mut setup = hall_setup();
    setup.max_time_s = 3.0;
    let mut reports = Vec::new();
    let camera = |inner| Faulty { inner, at: 40, fault, seq: 0 };
    let s = sim::run_with_camera(&setup, None, |p| reports.push(p.clone()), camera).await.expect("the simulation runs");
    (s, reports)
}

fn setpoint_at(reports: &[Progress], t_s: f64) -> BodyVelocity {
    reports.iter().find(|p| (p.t_s - t_s).abs() < 1e-9).unwrap_or_else(|| panic!("no report at {t_s} s")).setpoint
}

/// A failed step in the simulator goes through the runtime's fail-safe: a zero at once, and the
/// base stays stopped while no frame comes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_step_error_in_sim_stops_the_base() {
    let (s, reports) = faulty_run(Fault::BadFrameThenStall).await;
    assert!(setpoint_at(&reports, 1.0).v > 0.0, "driving before the bad frame: {reports:?}");
    assert_eq!(s.failsafe_stops, 1, "{}", s.to_json_line());
    assert_eq!(s.frames, 41, "{}", s.to_json_line());
    assert_eq!(setpoint_at(&reports, 2.0), BodyVelocity::ZERO);
    assert_eq!(setpoint_at(&reports, 3.0), BodyVelocity::ZERO);
}

/// When the rendered camera stalls, the last set-point expires through the runtime's rule
/// (`stall` after its frame's capture, simulated time) and the base is stopped.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_camera_stall_in_sim_expires_the_last_setpoint() {
    let (s, reports) = faulty_run(Fault::Stall).await;
    assert!(setpoint_at(&reports, 1.0).v > 0.0, "driving before the stall: {reports:?}");
    assert_eq!(s.failsafe_stops, 1, "one expiry: {}", s.to_json_line());
    assert_eq!(s.frames, 40, "{}", s.to_json_line());
    assert_eq!(setpoint_at(&reports, 2.0), BodyVelocity::ZERO);
    assert_eq!(setpoint_at(&reports, 3.0), BodyVelocity::ZERO);
}

/// An e-stop the simulated base raises from 1 s to 3 s stops the robot in the closed loop and
/// keeps it stopped while it is set.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_estop_in_sim_stops_the_robot_until_the_hold_has_passed() {
    let mut setup = hall_setup();
    setup.alarms = vec!["estop@1+2".parse().unwrap()];
    setup.max_time_s = 3.5;
    let mut reports = Vec::new();
    let s = sim::run(&setup, None, |p| reports.push(p.clone())).await.expect("the simulation runs");
    for t in [2.0, 3.0] {
        assert_eq!(setpoint_at(&reports, t), BodyVelocity::ZERO, "at {t} s: {reports:?}");
    }
    let moved = |a: f64, b: f64| {
        let (p, q) =
            (reports.iter().find(|r| r.t_s == a).unwrap().pose, reports.iter().find(|r| r.t_s == b).unwrap().pose);
        (q.x - p.x).hypot(q.y - p.y)
    };
    assert!(moved(2.0, 3.0) < 0.01, "no motion under the e-stop: {}", s.to_json_line());
    assert!(moved(0.0, 1.0) > 0.05, "driving before it: {reports:?}");
}

#[test]
fn summary_json_starts_with_the_contract_fields() {
    let s = SimSummary {
        reached: true,
        collisions: 0,
        time_s: 41.5,
        path_m: 15.25,
        min_clearance_m: 0.375,
        seed: 3,
        mission: "R9:D2".into(),
        status: GoalStatus::Arrived,
        goal_error_m: 0.25,
        frames: 1246,
        failsafe_stops: 0,
        stall_recoveries: 0,
        escapes: 0,
        first_contact: None,
        tpo_frames: [1, 2, 3, 4, 5],
        doors_matched: 0,
        walls_ahead_matched: 0,
        landmarks_missed: 0,
        replans: 0,
        wall_fixes: 12,
        flow_yaw_fixes: 30,
        odometry_scale: -0.04,
        odometry_bend_rad_m: 0.01,
        mean_heading_error_deg: 1.5,
        final_heading_error_deg: 0.5,
        odometry_error: "none".into(),
        start_error: [0.0, 0.0, 0.0],
        wall_s: 20.75,
        realtime_factor: 2.0,
        size: [640, 360],
        fps: 30.0,
        noise: 2.0,
        pose_hint: false,
        quality: sim::quality::QualitySummary {
            points_range_ok: Some(0.8),
            cells_ghost: None,
            obstacles_held: Some(0.5),
            tpo_none_share: Some(0.1),
            none_named_share: Some(0.02),
        },
    };
    let line = s.to_json_line();
    assert!(
        line.starts_with(r#"{"reached":true,"collisions":0,"time_s":41.5,"path_m":15.25,"min_clearance_m":0.375,"#),
        "{line}"
    );
    assert!(!line.contains('\n'));
    let v: serde_json::Value = serde_json::from_str(&line).unwrap();
    assert_eq!(v["status"], "arrived");
    assert_eq!(v["seed"], 3);
    assert_eq!((v["points_range_ok"].as_f64(), v["cells_ghost"].is_null()), (Some(0.8), true), "flattened: {line}");
    assert_eq!(v["obstacles_held"].as_f64(), Some(0.5), "flattened: {line}");
    assert_eq!(v["tpo_none_share"].as_f64(), Some(0.1), "flattened: {line}");
    assert_eq!(v["none_named_share"].as_f64(), Some(0.02), "flattened: {line}");
}

#[test]
fn start_pose_and_world_geometry_come_from_the_files() {
    let setup = hall_setup();
    let start = setup.start_pose().unwrap();
    assert_eq!((start.x, start.y, start.yaw), (1.0, 0.0, 0.0));
    assert_eq!(setup.place_position("B").unwrap(), [4.0, 0.0]);
    assert!(setup.place_position("C").unwrap_err().to_string().contains("\"C\""));
    let g = sim::world_geometry(&setup.world);
    // The outer wall: four full-height segments, no obstacles.
    assert_eq!(g.boxes.len(), 4);
    assert!(g.boxes.iter().all(|b| b.wall && (b.size_m[2] - 2.6).abs() < 1e-9));
    let total: f64 = g.boxes.iter().map(|b| b.size_m[0]).sum();
    assert!((total - 22.0).abs() < 1e-9, "perimeter {total}");
    assert!(g.cylinders.is_empty());

    // The built-in office map and world agree on every place they share; the map's own corridor
    // junctions C1..C5 lie on the centre line between opposite doors.
    let office = World::office();
    let map = TopoMap::parse(sim::OFFICE_MAP_TOML, "maps/office.toml").unwrap();
    for name in office.places.keys() {
        assert!(map.place(name).is_some(), "world place {name} missing from the map");
    }
    for p in &map.places {
        match office.places.get(&p.name) {
            Some(world_xy) => assert_eq!(p.position_m, Some(*world_xy), "{}", p.name),
            None => {
                let [x, y] = p.position_m.unwrap();
                let k: usize = p.name.strip_prefix('C').and_then(|k| k.parse().ok()).expect("only C* are map-only");
                let (north, south) = (office.places[&format!("D{k}")], office.places[&format!("D{}", k + 5)]);
                assert_eq!([x, y], [north[0], (north[1] + south[1]) / 2.0], "{}", p.name);
            }
        }
    }
}

#[test]
fn the_start_error_moves_the_true_start_and_not_the_plan() {
    let mut setup = hall_setup();
    setup.start_error = mocks::Pose::new(0.2, -0.1, 5f64.to_radians());
    let (planned, truth) = (setup.start_pose().unwrap(), setup.true_start_pose().unwrap());
    assert_eq!((planned.x, planned.y, planned.yaw), (1.0, 0.0, 0.0));
    assert!((truth.x - 1.2).abs() < 1e-12 && (truth.y + 0.1).abs() < 1e-12, "{truth:?}");
    assert!((truth.yaw - 5f64.to_radians()).abs() < 1e-12);
}

/// Bad `--odometry-error` and `--start-error` values are refused before anything runs, naming
/// the key or the part that is wrong.
#[test]
fn bad_odometry_and_start_errors_name_what_is_wrong() {
    let run = |flag: &str, value: &str| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_flownav"))
            .args(["sim", "--no-log", "--quiet", flag, value])
            .output()
            .expect("flownav runs");
        assert_eq!(out.status.code(), Some(2), "a usage error");
        String::from_utf8(out.stderr).unwrap()
    };
    assert!(run("--odometry-error", "left=0.01,whelbase=0.02").contains("unknown key \"whelbase\""));
    assert!(run("--odometry-error", "slip=lots").contains("slip=\"lots\" is not a number"));
    assert!(run("--odometry-error", "noise=-1").contains("noise=-1 is outside"));
    assert!(run("--start-error", "0.1,0.2").contains("DX,DY,DYAW_DEG"));
    assert!(run("--start-error", "0.1,x,3").contains("DY \"x\" is not a number"));
}

/// `--seeds A..B --jobs N` runs the missions side by side and prints what one at a time prints:
/// the same summaries (but for the wall-clock fields), in seed order, then the aggregate.
#[test]
fn parallel_seeds_print_the_same_summaries_in_seed_order() {
    let dir = tempfile::tempdir().unwrap();
    let (world, map) = (dir.path().join("hall.toml"), dir.path().join("hall-map.toml"));
    std::fs::write(&world, HALL).unwrap();
    std::fs::write(&map, HALL_MAP).unwrap();
    let run = |jobs: &str| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_flownav"))
            .args(["sim", "--world", world.to_str().unwrap(), "--map", map.to_str().unwrap(), "--mission", "A:B"])
            .args(["--seeds", "3..6", "--jobs", jobs, "--max-time", "3", "--size", "320x180", "--no-log", "--quiet"])
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .output()
            .expect("flownav runs");
        // Exit status 3 exactly when a run did not reach or touched something (3 s is short).
        let agg: serde_json::Value =
            serde_json::from_str(String::from_utf8_lossy(&out.stdout).lines().last().unwrap()).unwrap();
        let failed = !agg["failed_seeds"].as_array().unwrap().is_empty();
        assert_eq!(out.status.code(), Some(if failed { 3 } else { 0 }), "{}", String::from_utf8_lossy(&out.stderr));
        // the lines, less what depends on the wall clock
        String::from_utf8(out.stdout)
            .unwrap()
            .lines()
            .map(|l| {
                let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
                let o = v.as_object_mut().unwrap();
                o.remove("wall_s");
                o.remove("realtime_factor");
                v
            })
            .collect::<Vec<_>>()
    };
    let (one, three) = (run("1"), run("3"));
    assert_eq!(one.len(), 4, "three summaries and the aggregate");
    let seeds: Vec<u64> = three[..3].iter().map(|v| v["seed"].as_u64().unwrap()).collect();
    assert_eq!(seeds, [3, 4, 5]);
    assert_eq!(one, three);
}
