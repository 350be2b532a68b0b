//! Record → replay: a short run of the pipeline on rendered office frames is logged through
//! `logging::record` into an MCAP file; `flownav replay --check` must reproduce every logged
//! step bit for bit on the CPU backend, fail on a tampered log, and report (not fail on) steps
//! whose frames the logger dropped.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::str::FromStr;

use flownav::config::Config;
use flownav::flow::Backend;
use flownav::logging::record::{self, RecordImage};
use flownav::logging::{LogOptions, LogWriter};
use flownav::pafsis::{Mission, TopoMap};
use flownav::replay::{self, Check, ReplayOptions, ReplaySummary};
use flownav::step::Pipeline;
use hal::mjpeg::MjpegDecoder;
use hal::{BodyVelocity, Calibration, Frame, LumaImage};
use mocks::{Pose, Renderer, World};

const FRAME_NS: u64 = 33_333_333;
const FRAMES: u64 = 12;
/// The frame after which the run calls `fail_safe` (a simulated camera stall).
const STALL_AFTER: u64 = 6;

#[derive(Clone, Copy, Default)]
struct Variant {
    jpeg: bool,
    /// Replace the logged set-point of this seq by a value 1 ulp off in omega.
    tamper_seq: Option<u64>,
    /// Do not log the image of this seq (as the logger does when it falls behind).
    drop_image_seq: Option<u64>,
    /// Cruise straight ahead instead of the office mission.
    no_mission: bool,
}

fn calibration() -> Calibration {
    Calibration::nominal_c310().scaled_to(640, 360)
}

fn config() -> Config {
    let mut cfg = Config::default();
    cfg.flow.backend = Backend::Cpu;
    cfg
}

fn office_mission() -> (TopoMap, Mission) {
    let map = TopoMap::load(concat!(env!("CARGO_MANIFEST_DIR"), "/maps/office.toml")).unwrap();
    (map, Mission::from_str("R9:D2").unwrap())
}

/// The rendered frames: the office world's start pose, driving forward 1 cm and turning 0.2° per frame.
fn frames() -> Vec<LumaImage> {
    let world = World::office();
    let renderer = Renderer::new(&world, &calibration());
    let s = world.start;
    (0..FRAMES)
        .map(|i| {
            let (d, yaw) = (0.01 * i as f64, s.yaw + 0.0035 * i as f64);
            renderer.render(Pose::new(s.x + d * s.yaw.cos(), s.y + d * s.yaw.sin(), yaw))
        })
        .collect()
}

fn jpeg(img: &LumaImage) -> Vec<u8> {
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 85)
        .encode(img.data(), img.width() as u32, img.height() as u32, image::ExtendedColorType::L8)
        .unwrap();
    out
}

/// Runs the pipeline over `images` as `run`/`sim` do and logs it at `path`.
fn record_run(path: &Path, images: &[LumaImage], v: Variant) {
    let cfg = config();
    let calib = calibration();
    let mission = (!v.no_mission).then(office_mission);
    let name = mission.as_ref().map(|(_, m)| m.to_string());
    let mut options: LogOptions = record::run_options("sim", &cfg, &calib, name.as_deref(), None);
    if let Some((map, _)) = &mission {
        record::add_map(&mut options, map);
    }
    options.image_queue = images.len() + 1;
    let writer = LogWriter::create_at(path, options).unwrap();
    let h = writer.handle();
    h.calibration(0, &calib);
    let mut pipeline = Pipeline::new(&cfg, calib, mission).unwrap();
    let mut decoder = MjpegDecoder::new();
    for (i, img) in images.iter().enumerate() {
        let seq = i as u64;
        let t_ns = 5_000 + seq * FRAME_NS;
        let (image, logged) = if v.jpeg {
            let bytes: std::sync::Arc<[u8]> = jpeg(img).into();
            (decoder.decode(&bytes).unwrap(), RecordImage::Jpeg(bytes))
        } else {
            (img.clone(), RecordImage::Mono8(img))
        };
        let frame = Frame { seq, t_ns, image: image.clone() };
        if v.drop_image_seq != Some(seq) {
            assert!(record::record_frame(&h, &frame, logged));
        }
        let odometry = BodyVelocity { v: 0.3 + 1e-3 * seq as f64, omega: 0.105 };
        match pipeline.step(frame, odometry) {
            Ok(Some(mut out)) => {
                if v.tamper_seq == Some(seq) {
                    let sp = &mut out.mofis.setpoint;
                    sp.omega = f64::from_bits(sp.omega.to_bits() + 1);
                }
                record::record_step(&h, odometry, &out, &pipeline);
            }
            Ok(None) => {}
            Err(e) => {
                pipeline.fail_safe();
                record::record_failsafe(&h, t_ns, &e.to_string());
            }
        }
        if seq == STALL_AFTER {
            pipeline.fail_safe();
            record::record_failsafe(&h, t_ns + FRAME_NS / 2, "camera stalled (test)");
        }
    }
    let summary = writer.close().unwrap();
    assert_eq!(summary.stats.dropped(), 0);
}

fn replay_lib(path: &Path) -> (ReplaySummary, Vec<(u64, Check, bool)>) {
    let mut steps = Vec::new();
    let options = ReplayOptions { backend: Some(Backend::Cpu), config: None };
    let summary =
        replay::replay(&[path.to_path_buf()], &options, |r| steps.push((r.seq, r.check.clone(), r.after_gap))).unwrap();
    (summary, steps)
}

fn replay_cli(path: &Path) -> (bool, String, String) {
    let (code, stdout, stderr) = replay_cli_code(path);
    (code == Some(0), stdout, stderr)
}

fn replay_cli_code(path: &Path) -> (Option<i32>, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_flownav")).arg("replay").arg(path).arg("--check").output().unwrap();
    (out.status.code(), String::from_utf8_lossy(&out.stdout).into(), String::from_utf8_lossy(&out.stderr).into())
}

/// Steps: frames 1..=STALL_AFTER pair with their predecessor; STALL_AFTER+1 only primes again.
fn expected_steps() -> u64 {
    (FRAMES - 1) - 1
}

#[test]
fn replay_check_exits_2_when_it_cannot_read_the_log() {
    let dir = tempfile::tempdir().unwrap();
    let junk = dir.path().join("junk.mcap");
    std::fs::write(&junk, b"not an MCAP file at all").unwrap();
    for path in [junk, dir.path().join("missing.mcap")] {
        let (code, _, stderr) = replay_cli_code(&path);
        assert_eq!(code, Some(2), "{}: {stderr}", path.display());
        assert!(stderr.contains(&*path.to_string_lossy()), "the error names the file: {stderr}");
    }
}

#[test]
fn a_recorded_run_replays_bit_for_bit_and_a_tampered_one_fails() {
    let dir = tempfile::tempdir().unwrap();
    let images = frames();
    let good: PathBuf = dir.path().join("good.mcap");
    record_run(&good, &images, Variant::default());

    let (summary, steps) = replay_lib(&good);
    assert_eq!(summary.backend, "cpu");
    assert_eq!(summary.frames, FRAMES);
    assert_eq!(summary.steps, expected_steps(), "{summary:?}");
    assert_eq!((summary.checked, summary.matched, summary.mismatched), (expected_steps(), expected_steps(), 0));
    assert_eq!((summary.unchecked, summary.after_gap, summary.fail_safes), (0, 0, 1), "{summary:?}");
    assert!(steps.iter().all(|(_, c, gap)| *c == Check::Match && !gap));
    // After the fail-safe, frame STALL_AFTER+1 primes and STALL_AFTER+2 is the next step.
    let seqs: Vec<u64> = steps.iter().map(|s| s.0).collect();
    let want: Vec<u64> = (1..=STALL_AFTER).chain(STALL_AFTER + 2..FRAMES).collect();
    assert_eq!(seqs, want);

    let (ok, stdout, stderr) = replay_cli(&good);
    eprint!("{stderr}");
    assert!(ok, "replay --check failed on a faithful log:\n{stderr}");
    assert_eq!(stdout.lines().count() as u64, expected_steps());
    let first: serde_json::Value = serde_json::from_str(stdout.lines().next().unwrap()).unwrap();
    assert_eq!((first["seq"].as_u64(), first["check"].as_str()), (Some(1), Some("match")));
    assert!(first["setpoint"]["v"].is_number() && first["tpo"]["shape"].is_string(), "{first}");
    assert!(stderr.contains(&format!("{} identical, 0 differ", expected_steps())), "{stderr}");

    // The same run with one set-point changed by one ulp of omega.
    let tampered = dir.path().join("tampered.mcap");
    let seq = 4;
    record_run(&tampered, &images, Variant { tamper_seq: Some(seq), ..Variant::default() });
    let (summary, _) = replay_lib(&tampered);
    assert_eq!(summary.mismatched, 1, "{summary:?}");
    let first = summary.first_mismatch.as_ref().unwrap();
    assert_eq!(first.seq, seq);
    assert_eq!(first.diffs.len(), 1, "{:?}", first.diffs);
    assert_eq!((first.diffs[0].topic.as_str(), first.diffs[0].field.as_str()), ("/control/setpoint", "omega"));
    let (code, _, stderr) = replay_cli_code(&tampered);
    eprint!("{stderr}");
    assert_eq!(code, Some(1), "replay --check exits 1 on a mismatch");
    assert!(stderr.contains("1 of 10 checked steps differ") && stderr.contains("omega"), "{stderr}");
}

#[test]
fn jpeg_frames_replay_through_the_decoder_and_dropped_images_are_reported_not_failed() {
    let dir = tempfile::tempdir().unwrap();
    let images = frames();
    let path = dir.path().join("jpeg.mcap");
    record_run(&path, &images, Variant { jpeg: true, ..Variant::default() });
    let (summary, _) = replay_lib(&path);
    assert_eq!((summary.checked, summary.mismatched, summary.unchecked), (expected_steps(), 0, 0), "{summary:?}");

    // The logger dropped frame 3's image: step 3 (its frame) and step 4 (its previous frame)
    // cannot be checked; steps 5.. run on a pipeline whose limiter and PAFSIS state may differ.
    let path = dir.path().join("dropped.mcap");
    record_run(&path, &images, Variant { drop_image_seq: Some(3), ..Variant::default() });
    let (summary, steps) = replay_lib(&path);
    assert_eq!(summary.frames, FRAMES - 1);
    assert_eq!(summary.unchecked, 2, "{summary:?}");
    assert_eq!((summary.checked, summary.matched, summary.mismatched), (2, 2, 0), "{summary:?}");
    assert_eq!(summary.after_gap, expected_steps() - 4, "{summary:?}");
    assert!(summary.passed());
    let unchecked: Vec<u64> =
        steps.iter().filter(|(_, c, _)| matches!(c, Check::Unchecked { .. })).map(|s| s.0).collect();
    assert_eq!(unchecked, [3, 4]);
    // Flow keeps no state between steps: after the gap it still matches exactly; only what
    // depends on history may differ: PAFSIS progress → goal, the limiter → set-point, the TPO
    // that OFFIS decides over its last steps (offis::temporal) and what follows from the profile
    // whose empty bins take earlier pairs' points (offis::carry): the planes, the features, the
    // pair's class and the obstacle measured against the planes; never the pair's flow or masks.
    let carried = ["tpo", "obstacle", "attributes.bins", "attributes.carried_bins", "attributes.model"];
    let carried_too = ["attributes.features", "attributes.decision", "attributes.obstacle_"];
    for (seq, check, after_gap) in &steps {
        if let Check::Mismatch { diffs } = check {
            assert!(after_gap, "seq {seq} differs before the gap: {diffs:?}");
            for d in diffs {
                let history = carried.iter().chain(&carried_too).any(|p| d.field.starts_with(p));
                let tpo = d.topic == "/offis/perception" && (history || d.field.contains("filtered"));
                assert!(tpo || ["/pafsis/goal", "/control/setpoint"].contains(&d.topic.as_str()), "seq {seq}: {d}");
            }
        }
    }
    assert!(summary.first_unchecked.as_deref().unwrap().contains("not logged"), "{summary:?}");
    let (ok, _, stderr) = replay_cli(&path);
    eprint!("{stderr}");
    assert!(ok, "{stderr}");
    assert!(stderr.contains("unchecked: 2 steps"), "{stderr}");
}

#[test]
fn a_log_without_the_run_setup_is_refused_with_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sample.mcap");
    flownav::logging::sample::write_sample(
        &path,
        3,
        flownav::logging::sample::SampleImages::Mono8,
        LogOptions::new("sample"),
    )
    .unwrap();
    let e = replay::replay(&[path], &ReplayOptions::default(), |_| {}).unwrap_err();
    assert!(e.to_string().contains("no flownav.config metadata record"), "{e}");
}

#[test]
fn without_a_mission_a_logged_fail_safe_resynchronises_the_check() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cruise.mcap");
    record_run(&path, &frames(), Variant { no_mission: true, drop_image_seq: Some(2), ..Variant::default() });
    let (summary, steps) = replay_lib(&path);
    // Step 1 checked; 2 and 3 unchecked; 4..=6 after the gap; the fail-safe after 6 resets the
    // limiter and the pairing (all the state there is without PAFSIS): 8..=11 checked again.
    assert_eq!((summary.unchecked, summary.after_gap, summary.fail_safes), (2, 3, 1), "{summary:?}");
    assert_eq!((summary.checked, summary.matched, summary.mismatched), (5, 5, 0), "{summary:?}");
    let checked: Vec<u64> = steps.iter().filter(|(_, c, gap)| *c == Check::Match && !gap).map(|s| s.0).collect();
    assert_eq!(checked, [1, 8, 9, 10, 11]);
}
