//! CPU block flow at 1280×720 (C310 resolution), default parameters (16×16 blocks of 32 px,
//! radius 16), on a real texture: the graf image (shared/data/graf_shift_512) mirrored-tiled to
//! 1280×720. Frame B is frame A warped by a forward-motion zoom (1.5 % expansion about the
//! centre: flow grows from 0 to ~11 px at the corners) or by the (5, −3) translation.
//!
//! `cargo bench --bench flow` (set FLOWNAV_DATA if the data folder is not found).
//!
//! Measured as the benchmark thread's CPU time (`CLOCK_THREAD_CPUTIME_ID`), not wall time: on a
//! shared 2-core machine wall time mostly measures the other processes. The engine is
//! single-threaded, so CPU time is the time one core spends per frame pair.

use criterion::measurement::{Measurement, ValueFormatter, WallTime};
use criterion::{Criterion, criterion_group, criterion_main};
use flownav::flow::cpu::CpuFlow;
use flownav::flow::prefilter::{Scratch, highpass};
use flownav::flow::sad::Kernel;
use flownav::flow::{FlowEngine, FlowParams};
use hal::LumaImage;
use std::hint::black_box;
use std::time::Duration;

fn graf() -> LumaImage {
    let path = flownav::frames::reference_data_dir().join("graf_shift_512/0000.png");
    flownav::frames::load_luma(&path).unwrap_or_else(|e| panic!("{e} (set FLOWNAV_DATA to the reference data folder)"))
}

/// Bilinear sample of `src` mirrored infinitely in both directions.
fn sample(src: &LumaImage, x: f64, y: f64) -> f64 {
    let (w, h) = (src.width() as i64, src.height() as i64);
    let mirror = |i: i64, n: i64| {
        let m = i.rem_euclid(2 * n);
        (if m < n { m } else { 2 * n - 1 - m }) as usize
    };
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let p = |dx: i64, dy: i64| f64::from(src.get(mirror(x0 as i64 + dx, w), mirror(y0 as i64 + dy, h)));
    (1.0 - fy) * ((1.0 - fx) * p(0, 0) + fx * p(1, 0)) + fy * ((1.0 - fx) * p(0, 1) + fx * p(1, 1))
}

/// Frames A and B where A(x, y) = B(x + u, y + v) for the flow `motion(x, y) = (u, v)`
/// (B sampled by inverting the motion, which is exact for the affine motions used here).
fn pair(src: &LumaImage, inverse: impl Fn(f64, f64) -> (f64, f64)) -> (LumaImage, LumaImage) {
    let (w, h) = (1280, 720);
    let a = LumaImage::from_fn(w, h, |x, y| sample(src, x as f64, y as f64).round() as u8);
    let b = LumaImage::from_fn(w, h, |x, y| {
        let (sx, sy) = inverse(x as f64, y as f64);
        sample(src, sx, sy).round() as u8
    });
    (a, b)
}

/// CPU time consumed by the calling thread.
fn thread_cpu() -> Duration {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `ts` is a valid, writable timespec; the clock id is a Linux constant.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    assert_eq!(rc, 0, "clock_gettime(CLOCK_THREAD_CPUTIME_ID) failed");
    Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32)
}

/// Criterion measurement: thread CPU time, formatted like wall time.
struct ThreadCpu;

static WALL: WallTime = WallTime;

impl Measurement for ThreadCpu {
    type Intermediate = Duration;
    type Value = Duration;
    fn start(&self) -> Duration {
        thread_cpu()
    }
    fn end(&self, start: Duration) -> Duration {
        thread_cpu().saturating_sub(start)
    }
    fn add(&self, a: &Duration, b: &Duration) -> Duration {
        *a + *b
    }
    fn zero(&self) -> Duration {
        Duration::ZERO
    }
    fn to_f64(&self, v: &Duration) -> f64 {
        v.as_nanos() as f64
    }
    fn formatter(&self) -> &dyn ValueFormatter {
        WALL.formatter()
    }
}

fn bench(c: &mut Criterion<ThreadCpu>) {
    let src = graf();
    let (cx, cy, s) = (640.0, 360.0, 1.015);
    let zoom = pair(&src, |x, y| (cx + (x - cx) / s, cy + (y - cy) / s));
    let shift = pair(&src, |x, y| (x - 5.0, y + 3.0));
    let params = FlowParams::default();
    let kernel = Kernel::detect(params.block);

    let mut g = c.benchmark_group("flow_1280x720");
    g.sample_size(40);
    let mut eng = CpuFlow::new(params.clone()).unwrap();
    eprintln!("SAD kernel: {}", eng.kernel().name());
    let f = eng.compute(&zoom.0, &zoom.1).unwrap();
    eprintln!("zoom pair: {}/{} vectors valid", f.valid_count(), f.vectors.len());
    g.bench_function(format!("cpu_{}_zoom", kernel.name()), |bch| {
        bch.iter(|| black_box(eng.compute(black_box(&zoom.0), black_box(&zoom.1)).unwrap().vectors.len()))
    });
    g.bench_function(format!("cpu_{}_shift", kernel.name()), |bch| {
        bch.iter(|| black_box(eng.compute(black_box(&shift.0), black_box(&shift.1)).unwrap().vectors.len()))
    });
    let mut pyr = CpuFlow::new(FlowParams { pyramid_levels: 3, ..params.clone() }).unwrap();
    g.bench_function(format!("cpu_{}_zoom_pyramid3", kernel.name()), |bch| {
        bch.iter(|| black_box(pyr.compute(black_box(&zoom.0), black_box(&zoom.1)).unwrap().vectors.len()))
    });
    let mut scalar = CpuFlow::with_kernel(params.clone(), Kernel::Scalar);
    g.sample_size(10);
    g.bench_function("cpu_scalar_zoom", |bch| {
        bch.iter(|| black_box(scalar.compute(black_box(&zoom.0), black_box(&zoom.1)).unwrap().vectors.len()))
    });
    g.sample_size(40);
    let (mut out, mut scratch) = (LumaImage::default(), Scratch::default());
    g.bench_function("prefilter_one_frame", |bch| {
        bch.iter(|| {
            highpass(black_box(&zoom.0), params.prefilter_radius, &mut out, &mut scratch);
            black_box(out.data()[0])
        })
    });
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().with_measurement(ThreadCpu);
    targets = bench
}
criterion_main!(benches);
