//! `flownav analyze`: the DESIGN.md JSON Lines contract on a rendered frame folder (with
//! odometry.csv and a --calib file) and on the vendored graf pair (no odometry: distances
//! null), and its error messages.

use hal::{Calibration, LumaImage};
use serde_json::Value;
use std::path::Path;
use std::process::Command;

fn flownav(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_flownav"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("flownav runs")
}

fn keys(v: &Value) -> Vec<&str> {
    let mut k: Vec<&str> = v.as_object().expect("an object").keys().map(String::as_str).collect();
    k.sort_unstable();
    k
}

fn is_num_or_null(v: &Value) -> bool {
    v.is_null() || v.as_f64().is_some_and(f64::is_finite)
}

/// Checks one line against the contract; returns it parsed.
fn check_line(line: &str) -> Value {
    let v: Value = serde_json::from_str(line).unwrap_or_else(|e| panic!("not JSON ({e}): {line}"));
    assert_eq!(keys(&v), ["fine", "obstacle", "rough", "seq", "setpoint", "t", "tpo"], "{line}");
    assert!(v["seq"].as_u64().is_some() && v["t"].as_f64().is_some(), "{line}");
    let tpo = &v["tpo"];
    assert_eq!(keys(tpo), ["confidence", "distance_m", "shape"], "{line}");
    let shape = tpo["shape"].as_str().unwrap();
    assert!(["wall", "corner", "door", "corridor", "none"].contains(&shape), "{line}");
    let conf = tpo["confidence"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&conf) && is_num_or_null(&tpo["distance_m"]), "{line}");
    let o = &v["obstacle"];
    assert_eq!(keys(o), ["cell", "direction_deg", "distance_m", "present"], "{line}");
    let present = o["present"].as_bool().unwrap();
    assert!(is_num_or_null(&o["distance_m"]) && is_num_or_null(&o["direction_deg"]), "{line}");
    if present {
        let cell = o["cell"].as_array().expect("cell [row, col] when present");
        assert!(cell.len() == 2 && cell.iter().all(|c| c.as_u64().is_some_and(|c| c < 8)), "{line}");
        assert!(o["direction_deg"].is_number(), "{line}");
    } else {
        assert!(o["cell"].is_null() && o["direction_deg"].is_null() && o["distance_m"].is_null(), "{line}");
    }
    for (name, n) in [("rough", 4), ("fine", 8)] {
        let m = v[name].as_array().unwrap();
        assert_eq!(m.len(), n, "{line}");
        for row in m {
            let row = row.as_array().unwrap();
            assert!(row.len() == n && row.iter().all(|x| x == 0 || x == 1), "{line}");
        }
    }
    assert_eq!(keys(&v["setpoint"]), ["omega", "v"], "{line}");
    assert!(v["setpoint"]["v"].as_f64().is_some() && v["setpoint"]["omega"].as_f64().is_some(), "{line}");
    v
}

/// A frontal wall `distance_m` ahead, driven towards at 0.3 m/s, 15 fps, 640×360.
fn render_wall(dir: &Path, distance_m: f64, frames: usize) -> Calibration {
    let calib = Calibration::nominal_c310().scaled_to(640, 360);
    let scene = mocks::scene::wall(distance_m, 0.0);
    let renderer = mocks::Renderer::new(&scene.world, &calib);
    let start = scene.start(&calib);
    let (v, dt) = (0.3, 1.0 / 15.0);
    let mut odo = String::from("t,v,omega\n");
    let mut img = LumaImage::default();
    let mut prev = None;
    for i in 0..frames {
        // start far enough back that the last frame is at `start`
        let back = v * dt * (frames - 1 - i) as f64;
        let pose = mocks::Pose::new(start.x - back, start.y, start.yaw);
        let effects = mocks::Effects { noise_sigma: 1.0, seed: 3, ..Default::default() };
        renderer.render_frame(prev.unwrap_or(pose), pose, &effects, i as u64, &mut img);
        flownav::frames::save_png(&img, dir.join(format!("{i:04}.png"))).unwrap();
        odo.push_str(&format!("{},{v},0\n", 0.5 + i as f64 * dt));
        prev = Some(pose);
    }
    std::fs::write(dir.join("odometry.csv"), odo).unwrap();
    calib
}

#[test]
fn a_rendered_folder_gives_one_line_per_pair_with_the_wall_and_its_distance() {
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    std::fs::create_dir(&frames).unwrap();
    let calib = render_wall(&frames, 2.0, 4);
    let calib_path = dir.path().join("calib.toml");
    std::fs::write(&calib_path, toml::to_string(&calib).unwrap()).unwrap();
    let out = flownav(&["analyze", "--frames", frames.to_str().unwrap(), "--calib", calib_path.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8(out.stdout).unwrap();
    let lines: Vec<Value> = text.lines().map(check_line).collect();
    assert_eq!(lines.len(), 3, "{text}");
    for (k, v) in lines.iter().enumerate() {
        let seq = k as u64 + 1;
        assert_eq!(v["seq"], seq);
        assert!((v["t"].as_f64().unwrap() - (0.5 + seq as f64 / 15.0)).abs() < 1e-9, "{v}");
        // the newer frame of the last pair is 2 m from the wall, earlier ones 2 cm further each
        let want = 2.0 + 0.02 * (3 - seq) as f64;
        assert_eq!(v["tpo"]["shape"], "wall", "{v}");
        let d = v["tpo"]["distance_m"].as_f64().unwrap();
        assert!((d - want).abs() < 0.15 * want, "{d} vs {want}");
        assert_eq!(v["obstacle"]["present"], false, "a bare wall is the TPO, not an obstacle: {v}");
        // cruising towards a wall 2 m ahead: MOFIS slows down, does not stop, does not reverse
        let sp = v["setpoint"]["v"].as_f64().unwrap();
        assert!(sp >= 0.0, "{v}");
    }
}

#[test]
fn the_graf_pair_without_odometry_has_null_distances() {
    let out = flownav(&["analyze", "--frames", "data/graf_shift_512"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8(out.stdout).unwrap();
    let lines: Vec<Value> = text.lines().map(check_line).collect();
    assert_eq!(lines.len(), 1, "{text}");
    let v = &lines[0];
    assert_eq!(v["seq"], 1);
    assert!((v["t"].as_f64().unwrap() - 1.0 / 30.0).abs() < 1e-9, "{v}");
    assert!(v["tpo"]["distance_m"].is_null() && v["obstacle"]["distance_m"].is_null(), "{v}");
    // --fps sets t
    let out = flownav(&["analyze", "--frames", "data/graf_shift_512", "--fps", "10", "--velocity", "0"]);
    let v = check_line(String::from_utf8(out.stdout).unwrap().lines().next().unwrap());
    assert!((v["t"].as_f64().unwrap() - 0.1).abs() < 1e-9, "{v}");
}

#[test]
fn bad_folders_give_clear_errors() {
    let stderr = |args: &[&str]| {
        let out = flownav(args);
        assert!(!out.status.success(), "{args:?} should fail");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let e = stderr(&["analyze", "--frames", "/no/such/folder"]);
    assert!(e.contains("/no/such/folder") && e.contains("does not exist"), "{e}");

    let dir = tempfile::tempdir().unwrap();
    let d = dir.path().to_str().unwrap();
    flownav::frames::save_png(&LumaImage::new(64, 64), dir.path().join("0000.png")).unwrap();
    let e = stderr(&["analyze", "--frames", d]);
    assert!(e.contains("at least 2"), "{e}");

    std::fs::write(dir.path().join("0001.png"), b"not a png").unwrap();
    let e = stderr(&["analyze", "--frames", d]);
    assert!(e.contains("0001.png"), "{e}");

    flownav::frames::save_png(&LumaImage::new(64, 64), dir.path().join("0001.png")).unwrap();
    std::fs::write(dir.path().join("odometry.csv"), "t,v,omega\n0,0.2,0\nzero,0.2,0\n").unwrap();
    let e = stderr(&["analyze", "--frames", d]);
    assert!(e.contains("odometry.csv") && e.contains("line 3"), "{e}");
}

/// The office corridor driven at 0.3 m/s while turning at ±0.12 rad/s (7°/s), 720p at 10 fps:
/// the view moves 15–30 px sideways per pair, beyond the block search's radius of 16 px, and
/// OFFIS must still see the corridor on every pair.
#[test]
fn a_turning_drive_down_the_corridor_is_seen_as_a_corridor() {
    for omega in ["0.12", "-0.12"] {
        let dir = tempfile::tempdir().unwrap();
        let frames = dir.path().join("turn");
        let out = flownav(&[
            "render",
            "--start",
            "2,0,0",
            "--velocity",
            "0.3",
            "--omega",
            omega,
            "--fps",
            "10",
            "--frames",
            "9",
            "--size",
            "1280x720",
            "--out",
            frames.to_str().unwrap(),
        ]);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let calib = frames.join("calib.toml");
        let out = flownav(&["analyze", "--frames", frames.to_str().unwrap(), "--calib", calib.to_str().unwrap()]);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let text = String::from_utf8(out.stdout).unwrap();
        let shapes: Vec<String> =
            text.lines().map(check_line).map(|v| v["tpo"]["shape"].as_str().unwrap().to_string()).collect();
        assert_eq!(shapes, vec!["corridor"; 8], "omega {omega}: {text}");
    }
}
