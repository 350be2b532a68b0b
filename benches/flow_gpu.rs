//! CPU and GPU flow engines at 1280×720 (C310 resolution) on the same frame pair: the graf
//! texture (shared/data/graf_shift_512) mirrored-tiled to 1280×720, frame B translated by
//! (5, −3) px. Two grids: the default (16×16 blocks of 32 px, radius 16) and dense mode
//! (`stride = 8`: 88×160 blocks of 32 px, radius 16).
//!
//! GPU timings include upload, preprocessing and readback. `gpu` calls `compute` (waits for its
//! result) with both frames new each time; `gpu_stream_wait` calls `compute` on a video-like
//! stream (frame A = previous frame B, kept on the GPU: one upload and one prefilter per pair),
//! as `run` does; `gpu_stream` uses `compute_pipelined` on that stream (the result of pair n is
//! read while pair n+1 runs, one pair of latency).
//!
//! Before timing, each GPU engine's field on the benchmark frames must equal the CPU engine's
//! exactly (panics otherwise), and it prints whether the dense fast path (cost volume) ran;
//! after each `gpu/…` benchmark it prints the mean GPU time of each compute pass over 50 more
//! pairs ("pass times", where the device has timestamp queries);
//! `FLOWNAV_GPU_COST_VOLUME=0` benchmarks the per-block kernel instead.
//!
//! `cargo bench --bench flow_gpu` — the GPU is the first adapter wgpu finds (hardware first;
//! `WGPU_BACKEND=vulkan|metal|dx12|gl` to choose). On a software adapter (lavapipe/llvmpipe)
//! dense mode takes tens of seconds per frame, so it is only run there with
//! `FLOWNAV_BENCH_SOFTWARE_DENSE=1`. Set FLOWNAV_DATA if the data folder is not found.

use criterion::{Criterion, criterion_group, criterion_main};
use flownav::flow::cpu::CpuFlow;
use flownav::flow::gpu::{self, GpuContext, GpuFlow};
use flownav::flow::{FlowEngine, FlowParams};
use hal::LumaImage;
use std::hint::black_box;
use std::sync::Arc;
use std::time::{Duration, Instant};

fn graf() -> LumaImage {
    let path = flownav::frames::reference_data_dir().join("graf_shift_512/0000.png");
    flownav::frames::load_luma(&path).unwrap_or_else(|e| panic!("{e} (set FLOWNAV_DATA to the reference data folder)"))
}

/// `src` mirrored-tiled to 1280×720 and shifted by (dx, dy).
fn tiled(src: &LumaImage, dx: i64, dy: i64) -> LumaImage {
    let (w, h) = (src.width() as i64, src.height() as i64);
    let mirror = |i: i64, n: i64| {
        let m = i.rem_euclid(2 * n);
        (if m < n { m } else { 2 * n - 1 - m }) as usize
    };
    LumaImage::from_fn(1280, 720, |x, y| src.get(mirror(x as i64 - dx, w), mirror(y as i64 - dy, h)))
}

/// Mean GPU time per compute pass over 50 more `compute` calls (timestamp queries), printed as
/// "LABEL: pass times (ms, mean of 50): prep …, costvol …, reduce …, total …"; nothing where
/// the device has no timestamp queries.
fn pass_times(engine: &mut GpuFlow, a: &LumaImage, b: &LumaImage, label: &str) {
    if !engine.set_pass_timing(true) {
        return;
    }
    let mut sums: Vec<(&'static str, f64)> = Vec::new();
    let mut n = 0u32;
    for _ in 0..50 {
        engine.compute(a, b).unwrap();
        let Some(times) = engine.last_pass_times() else { continue };
        if sums.is_empty() {
            sums = times.iter().map(|&(l, _)| (l, 0.0)).collect();
        }
        if sums.len() == times.len() {
            sums.iter_mut().zip(&times).for_each(|(s, t)| s.1 += t.1);
            n += 1;
        }
    }
    engine.set_pass_timing(false);
    if n > 0 {
        let list: Vec<String> = sums.iter().map(|(l, s)| format!("{l} {:.3}", s / f64::from(n))).collect();
        eprintln!("{label}: pass times (ms, mean of {n}): {}", list.join(", "));
    }
}

/// Where the host's time of a waiting `compute` goes, over 50 pairs: `submit` is
/// `compute_pipelined` with nothing in flight (upload and submission only), `wait` the `flush`
/// that follows (waiting for the GPU, readback, the CPU's finishing). Printed as
/// "LABEL: host split (ms, mean of 50): submit …, wait …"; `stream` alternates the frames so that
/// frame A is the previous pair's B (not uploaded again).
fn host_split(engine: &mut GpuFlow, a: &LumaImage, b: &LumaImage, label: &str) {
    for stream in [false, true] {
        let (mut submit, mut wait) = (0.0, 0.0);
        for i in 0..50 {
            let (fa, fb) = if stream && i % 2 == 1 { (b, a) } else { (a, b) };
            let t0 = Instant::now();
            assert!(engine.compute_pipelined(fa, fb).unwrap().is_none());
            let t1 = Instant::now();
            engine.flush().unwrap();
            submit += (t1 - t0).as_secs_f64() * 1e3;
            wait += t1.elapsed().as_secs_f64() * 1e3;
        }
        let what = if stream { "stream" } else { "both new" };
        eprintln!("{label}: host split, {what} (ms, mean of 50): submit {:.3}, wait {:.3}", submit / 50.0, wait / 50.0);
    }
}

fn bench(c: &mut Criterion) {
    let src = graf();
    let (a, b) = (tiled(&src, 0, 0), tiled(&src, 5, -3));
    let ctx = match GpuContext::any() {
        Ok(ctx) => Some(Arc::new(ctx)),
        Err(e) => {
            eprintln!("no GPU adapter, benchmarking the CPU engine only: {e}");
            None
        }
    };
    let software = ctx.as_ref().is_some_and(|c| !gpu::is_hardware(c.info()));
    if let Some(ctx) = &ctx {
        eprintln!("GPU: {}", gpu::describe_adapter(ctx.info()));
    }
    let default = FlowParams::default();
    let dense = FlowParams { stride: Some(8), ..FlowParams::default() };
    assert_eq!(dense.grid(1280, 720), (88, 160));

    let mut g = c.benchmark_group("flow_gpu_720p");
    g.sample_size(10).warm_up_time(Duration::from_secs(1));
    for (name, params) in [("default", &default), ("dense", &dense)] {
        let mut cpu = CpuFlow::new(params.clone()).unwrap();
        g.bench_function(format!("cpu/{name}"), |bch| {
            bch.iter(|| black_box(cpu.compute(&a, &b).unwrap().valid_count()))
        });
        let Some(ctx) = &ctx else { continue };
        if name == "dense" && software && std::env::var_os("FLOWNAV_BENCH_SOFTWARE_DENSE").is_none() {
            eprintln!("skipping gpu/dense on a software adapter (set FLOWNAV_BENCH_SOFTWARE_DENSE=1 to run it)");
            continue;
        }
        let mut engine = GpuFlow::new(Arc::clone(ctx), params.clone()).unwrap();
        // Parity on the benchmark frames (exact: same vectors, flags, costs and bit-identical
        // sub-pixel values as the CPU engine), and the warm-up that compiles the pipelines.
        let expected = cpu.compute(&a, &b).unwrap().clone();
        let got = engine.compute(&a, &b).unwrap().clone();
        eprintln!(
            "gpu/{name}: cost volume {} (FLOWNAV_GPU_COST_VOLUME={:?}), {} absolute differences per pair",
            if engine.uses_cost_volume() { "on" } else { "off" },
            std::env::var("FLOWNAV_GPU_COST_VOLUME").ok(),
            engine.cost_volume_abs_diffs().map_or("per-block kernel".to_string(), |n| n.to_string()),
        );
        assert_eq!(got.vectors.len(), expected.vectors.len());
        let differing = got.vectors.iter().zip(&expected.vectors).filter(|(g, c)| {
            (g.x, g.y, g.validity, g.cost.to_bits(), g.u.to_bits(), g.v.to_bits())
                != (c.x, c.y, c.validity, c.cost.to_bits(), c.u.to_bits(), c.v.to_bits())
        });
        let n_diff = differing.clone().count();
        if let Some((g, c)) = differing.clone().next() {
            panic!(
                "gpu/{name}: {n_diff} of {} vectors differ from the CPU engine's, e.g. gpu {g:?} cpu {c:?}",
                got.vectors.len()
            );
        }
        eprintln!("gpu/{name}: field identical to the CPU engine's ({} vectors)", got.vectors.len());
        g.bench_function(format!("gpu/{name}"), |bch| {
            bch.iter(|| black_box(engine.compute(&a, &b).unwrap().valid_count()))
        });
        pass_times(&mut engine, &a, &b, &format!("gpu/{name}"));
        host_split(&mut engine, &a, &b, &format!("gpu/{name}"));
        // A stream alternating a, b, a, b: each pair's A is the previous pair's B, so only B is
        // uploaded and preprocessed. `compute` waits for its own result (what `run` does);
        // `compute_pipelined` returns the previous pair's.
        let frames = [&a, &b];
        let mut i = 0usize;
        g.bench_function(format!("gpu_stream_wait/{name}"), |bch| {
            bch.iter(|| {
                let (fa, fb) = (frames[i % 2], frames[(i + 1) % 2]);
                i += 1;
                black_box(engine.compute(fa, fb).unwrap().valid_count())
            })
        });
        g.bench_function(format!("gpu_stream/{name}"), |bch| {
            bch.iter(|| {
                let (fa, fb) = (frames[i % 2], frames[(i + 1) % 2]);
                i += 1;
                black_box(engine.compute_pipelined(fa, fb).unwrap().map(|f| f.valid_count()))
            })
        });
        engine.flush().unwrap();
        // FLOWNAV_BENCH_CV_TILES="TC,TR,G;..." also times the dense cost volume with those
        // forced tile shapes (to tune the planner on a real GPU), each checked against the CPU.
        let tiles = std::env::var("FLOWNAV_BENCH_CV_TILES").unwrap_or_default();
        for shape in tiles.split(';').filter(|_| name == "dense").filter_map(|t| {
            let v: Vec<u32> = t.split(',').filter_map(|n| n.trim().parse().ok()).collect();
            (v.len() == 3).then(|| (v[0], v[1], v[2]))
        }) {
            engine.set_cost_volume(Some(true));
            engine.set_cost_volume_tile(Some(shape));
            let got = engine.compute(&a, &b).unwrap().clone();
            if engine.cost_volume_tile() != Some(shape) {
                eprintln!("gpu/dense tile {shape:?}: not usable here (plan {:?})", engine.cost_volume_tile());
                continue;
            }
            let same = got.vectors.iter().zip(&expected.vectors).all(|(g, c)| {
                (g.x, g.y, g.validity, g.cost.to_bits(), g.u.to_bits(), g.v.to_bits())
                    == (c.x, c.y, c.validity, c.cost.to_bits(), c.u.to_bits(), c.v.to_bits())
            });
            assert!(same, "gpu/dense tile {shape:?}: field differs from the CPU engine's");
            eprintln!(
                "gpu/dense tile {shape:?}: identical to the CPU engine's, {:?} absolute differences",
                engine.cost_volume_abs_diffs()
            );
            let (tc, tr, gg) = shape;
            g.bench_function(format!("gpu/dense_tile_{tc}x{tr}_g{gg}"), |bch| {
                bch.iter(|| black_box(engine.compute(&a, &b).unwrap().valid_count()))
            });
            pass_times(&mut engine, &a, &b, &format!("gpu/dense tile {shape:?}"));
        }
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
