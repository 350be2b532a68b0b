//! Logging overhead on the control path: what one frame's logging calls cost the caller
//! (budget: ≤ 1 ms per frame), and what the writer thread spends per frame in the background.
//!
//! `cargo bench --bench logging`

use std::hint::black_box;
use std::sync::Arc;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use flownav::logging::sample::{self, FRAME_NS};
use flownav::logging::{LogHandle, LogOptions, LogWriter};
use serde_json::json;

/// One frame's calls, as the runtime makes them: image, flow, perception, set-point, odometry.
fn log_frame(log: &LogHandle, i: u64, image: &Frame, field: &flownav::flow::FlowField) -> bool {
    let t = i * FRAME_NS;
    let image_ok = match image {
        Frame::Mono8(img) => log.image_mono8(t, img),
        Frame::Jpeg(bytes) => log.image_jpeg(t, Arc::clone(bytes)),
    };
    log.flow(t, field);
    log.perception(t, &sample::perception(i), serde_json::Value::Null);
    log.setpoint(t, &sample::setpoint(i));
    log.odometry(&sample::odometry(2 * i));
    image_ok
}

enum Frame {
    Mono8(hal::LumaImage),
    Jpeg(Arc<[u8]>),
}

/// Times the calls of `iters` frames; between frames (untimed) waits until the writer has
/// drained its queue, as it does between real frames 33 ms apart, so every image is really
/// queued (not dropped, which would be cheaper).
fn timed_frames(log: &LogHandle, image: &Frame, iters: u64) -> Duration {
    let field = sample::flow_field(1, 1280, 720);
    let mut total = Duration::ZERO;
    for i in 0..iters {
        while log.waiting().iter().sum::<usize>() > 0 {
            std::thread::yield_now();
        }
        let start = Instant::now();
        let queued = log_frame(log, i, image, black_box(&field));
        total += start.elapsed();
        assert!(queued, "image dropped: the measurement would be optimistic");
    }
    total
}

fn control_path(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let mut group = c.benchmark_group("logging_control_path_per_frame");
    group.sample_size(20).warm_up_time(Duration::from_secs(1)).measurement_time(Duration::from_secs(6));
    let cases = [
        ("sim_mono8_1280x720", Frame::Mono8(sample::frame(3, 1280, 720))),
        ("robot_jpeg_1280x720", Frame::Jpeg(sample::jpeg_frame(3, 1280, 720).into())),
    ];
    for (name, image) in cases {
        let writer = LogWriter::create_at(&dir.path().join(format!("{name}.mcap")), LogOptions::new("bench")).unwrap();
        let handle = writer.handle();
        group.bench_function(name, |b| b.iter_custom(|iters| timed_frames(&handle, &image, iters)));
        let summary = writer.close().unwrap();
        assert_eq!(summary.stats.dropped(), 0);
    }
    group.finish();
}

/// Background cost: frames per second the writer thread sustains (encode, compress, write).
fn writer_thread(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let mut group = c.benchmark_group("logging_writer_thread_per_frame");
    group.sample_size(10).warm_up_time(Duration::from_secs(1)).measurement_time(Duration::from_secs(8));
    let field = sample::flow_field(1, 1280, 720);
    let cases = [
        ("sim_mono8_1280x720", Frame::Mono8(sample::frame(3, 1280, 720))),
        ("robot_jpeg_1280x720", Frame::Jpeg(sample::jpeg_frame(3, 1280, 720).into())),
    ];
    let mut n = 0;
    for (name, image) in cases {
        group.bench_function(name, |b| {
            b.iter_custom(|iters| {
                n += 1;
                let mut options = LogOptions::new("bench");
                options.image_queue = iters as usize + 1;
                let writer = LogWriter::create_at(&dir.path().join(format!("w{n}.mcap")), options).unwrap();
                let start = Instant::now();
                for i in 0..iters {
                    log_frame(&writer, i, &image, &field);
                }
                writer.log(iters * FRAME_NS, flownav::logging::LogLevel::Info, json!({"frames": iters}).to_string());
                writer.close().unwrap();
                start.elapsed()
            })
        });
    }
    group.finish();
}

/// `logging::record::record_step` (what `run` and `sim` call after each step: `/step/input`, flow,
/// perception with the OFFIS attributes converted to JSON, goal, set-point), on a real step's
/// output (CPU flow on two 640×360 sample frames, the office mission).
fn record_step(c: &mut Criterion) {
    use flownav::logging::record;
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = flownav::config::Config::default();
    cfg.flow.backend = flownav::flow::Backend::Cpu;
    let calib = hal::Calibration::nominal_c310().scaled_to(640, 360);
    let map = flownav::pafsis::TopoMap::load(concat!(env!("CARGO_MANIFEST_DIR"), "/maps/office.toml")).unwrap();
    let mission: flownav::pafsis::Mission = "R9:D2".parse().unwrap();
    let mut pipeline = flownav::step::Pipeline::new(&cfg, calib, Some((map, mission))).unwrap();
    let odo = hal::BodyVelocity { v: 0.3, omega: 0.1 };
    let frame = |i: u64| hal::Frame { seq: i, t_ns: i * FRAME_NS, image: sample::frame(i, 640, 360) };
    pipeline.step(frame(0), odo).unwrap();
    let out = pipeline.step(frame(1), odo).unwrap().unwrap();
    let writer = LogWriter::create_at(&dir.path().join("record.mcap"), LogOptions::new("bench")).unwrap();
    let handle = writer.handle();
    let mut group = c.benchmark_group("logging_record_step");
    group.sample_size(20).warm_up_time(Duration::from_secs(1)).measurement_time(Duration::from_secs(4));
    group.bench_function("record_step", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                while handle.waiting().iter().sum::<usize>() > 0 {
                    std::thread::yield_now();
                }
                let start = Instant::now();
                record::record_step(&handle, odo, black_box(&out), &pipeline);
                total += start.elapsed();
            }
            total
        })
    });
    group.finish();
    let summary = writer.close().unwrap();
    assert_eq!(summary.stats.dropped(), 0);
}

criterion_group!(benches, control_path, writer_thread, record_step);
criterion_main!(benches);
