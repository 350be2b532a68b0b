//! The GPU flow engine against the CPU engine (which `src/flow` tests against the literal
//! contract): identical integer displacements, validity flags and costs, sub-pixel within 1e-3
//! px, on random textures and motions, with borders, textureless blocks, pyramids, dense mode,
//! and the pipelined API. Runs on any wgpu adapter, including Mesa's software lavapipe/llvmpipe
//! (`WGPU_BACKEND=vulkan` or `gl`); skipped with a message only where no adapter exists.

use flownav::flow::gpu::{self, GpuContext, GpuFlow};
use flownav::flow::{Backend, FlowEngine, FlowField, FlowParams, Placement, cpu::CpuFlow, create_engine};
use hal::LumaImage;
use std::sync::{Arc, OnceLock};

/// The shared GPU context, or `None` (with a visible message) where wgpu finds no adapter.
fn context() -> Option<Arc<GpuContext>> {
    static CTX: OnceLock<Option<Arc<GpuContext>>> = OnceLock::new();
    let ctx = CTX.get_or_init(|| match GpuContext::any() {
        Ok(ctx) => {
            eprintln!("GPU flow tests on {}", gpu::describe_adapter(ctx.info()));
            Some(Arc::new(ctx))
        }
        Err(e) => {
            eprintln!("SKIPPED: no wgpu adapter on this machine ({e})");
            None
        }
    });
    ctx.clone()
}

/// xorshift64* — deterministic, no dependency.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// A random smooth texture: value noise on an 8 px lattice, bilinearly interpolated, plus fine
/// noise; a flat (textureless) rectangle when `flat` is set.
fn texture(w: usize, h: usize, seed: u64, flat: bool) -> Vec<f64> {
    let mut rng = Rng(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1);
    let (gw, gh) = (w / 8 + 2, h / 8 + 2);
    let lattice: Vec<f64> = (0..gw * gh).map(|_| rng.below(256) as f64).collect();
    let mut img = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let (fx, fy) = (x as f64 / 8.0, y as f64 / 8.0);
            let (ix, iy) = (fx as usize, fy as usize);
            let (tx, ty) = (fx - ix as f64, fy - iy as f64);
            let l = |xx: usize, yy: usize| lattice[yy * gw + xx];
            let v = l(ix, iy) * (1.0 - tx) * (1.0 - ty)
                + l(ix + 1, iy) * tx * (1.0 - ty)
                + l(ix, iy + 1) * (1.0 - tx) * ty
                + l(ix + 1, iy + 1) * tx * ty;
            img[y * w + x] = v * 0.8 + rng.below(40) as f64;
        }
    }
    if flat {
        for y in h / 3..h / 3 + h / 4 {
            for x in w / 4..w / 4 + w / 3 {
                img[y * w + x] = 100.0;
            }
        }
    }
    img
}

/// Samples `scene` (a `sw × sh` float image) at (x + dx, y + dy) for a `w × h` frame, bilinear,
/// edge-clamped, times `gain`.
fn warp(scene: (&[f64], usize, usize), (w, h): (usize, usize), (dx, dy): (f64, f64), gain: f64) -> LumaImage {
    let (src, sw, sh) = scene;
    LumaImage::from_fn(w, h, |x, y| {
        let (fx, fy) = ((x as f64 + dx).clamp(0.0, sw as f64 - 1.001), (y as f64 + dy).clamp(0.0, sh as f64 - 1.001));
        let (ix, iy) = (fx as usize, fy as usize);
        let (tx, ty) = (fx - ix as f64, fy - iy as f64);
        let p = |xx: usize, yy: usize| src[yy * sw + xx];
        let v = p(ix, iy) * (1.0 - tx) * (1.0 - ty)
            + p(ix + 1, iy) * tx * (1.0 - ty)
            + p(ix, iy + 1) * (1.0 - tx) * ty
            + p(ix + 1, iy + 1) * tx * ty;
        (v * gain).round().clamp(0.0, 255.0) as u8
    })
}

/// A frame pair: B shows the scene moved by (mx, my) px (B(x) = A(x − m)), with a brightness
/// gain, so the true flow is (mx, my).
fn pair(w: usize, h: usize, seed: u64, mx: f64, my: f64, flat: bool) -> (LumaImage, LumaImage) {
    let scene = texture(w + 64, h + 64, seed, flat);
    let (sw, sh) = (w + 64, h + 64);
    let a = warp((&scene, sw, sh), (w, h), (32.0, 32.0), 1.0);
    let b = warp((&scene, sw, sh), (w, h), (32.0 - mx, 32.0 - my), 1.05);
    (a, b)
}

fn assert_same(gpu: &FlowField, cpu: &FlowField, what: &str) {
    assert_eq!((gpu.rows, gpu.cols, gpu.width, gpu.height), (cpu.rows, cpu.cols, cpu.width, cpu.height), "{what}");
    assert_eq!(gpu.vectors.len(), cpu.vectors.len(), "{what}");
    for (i, (g, c)) in gpu.vectors.iter().zip(&cpu.vectors).enumerate() {
        let at = format!("{what}: block {i} at ({}, {})", c.x, c.y);
        assert_eq!((g.x, g.y), (c.x, c.y), "{at}");
        assert_eq!(g.validity, c.validity, "{at}: gpu {g:?} cpu {c:?}");
        assert_eq!(g.cost, c.cost, "{at}: gpu {g:?} cpu {c:?}");
        assert_eq!((g.u - c.u).round(), 0.0, "{at}: integer displacement differs: gpu {g:?} cpu {c:?}");
        assert!((g.u - c.u).abs() <= 1e-3 && (g.v - c.v).abs() <= 1e-3, "{at}: gpu {g:?} cpu {c:?}");
    }
}

/// GPU and CPU fields for `params` on (a, b).
fn both(ctx: &Arc<GpuContext>, params: &FlowParams, a: &LumaImage, b: &LumaImage) -> (FlowField, FlowField) {
    let mut g = GpuFlow::new(Arc::clone(ctx), params.clone()).expect("GPU engine");
    let mut c = CpuFlow::new(params.clone()).expect("CPU engine");
    let gf = g.compute(a, b).expect("GPU flow").clone();
    let cf = c.compute(a, b).expect("CPU flow").clone();
    (gf, cf)
}

fn small(rows: usize, cols: usize, block: usize, radius: usize) -> FlowParams {
    FlowParams { rows, cols, block, radius, backend: Backend::Gpu, ..FlowParams::default() }
}

#[test]
fn random_translations_match_the_cpu_engine() {
    let Some(ctx) = context() else { return };
    let params = small(5, 7, 16, 6);
    let mut rng = Rng(7);
    let mut valid = 0;
    for seed in 0..4 {
        let (mx, my) = (rng.below(1300) as f64 / 100.0 - 6.5, rng.below(1300) as f64 / 100.0 - 6.5);
        let (a, b) = pair(160, 120, seed, mx, my, seed % 2 == 1);
        let (g, c) = both(&ctx, &params, &a, &b);
        assert_same(&g, &c, &format!("seed {seed}, motion ({mx:.2}, {my:.2})"));
        valid += g.valid_count();
        // The engines agree with each other; check that they also measure the motion.
        for v in g.vectors.iter().filter(|v| v.valid()) {
            assert!(
                (v.u as f64 - mx).abs() < 0.6 && (v.v as f64 - my).abs() < 0.6,
                "seed {seed}: {v:?} vs ({mx}, {my})"
            );
        }
    }
    assert!(valid > 40, "only {valid} valid vectors over 4 pairs");
}

#[test]
fn borders_textureless_blocks_and_unrelated_frames_match() {
    let Some(ctx) = context() else { return };
    // Large motion: blocks at the borders lose their match (out_of_frame), the flat rectangle is
    // textureless, and B unrelated to A gives ambiguous blocks.
    let params = FlowParams { placement: Placement::Tile, ..small(6, 8, 16, 5) };
    let (a, b) = pair(128, 96, 11, 4.0, -3.0, true);
    let (g, c) = both(&ctx, &params, &a, &b);
    assert_same(&g, &c, "tiled, flat patch");
    let reasons = |f: &FlowField, r| f.vectors.iter().filter(|v| v.validity == r).count();
    assert!(reasons(&c, flownav::flow::Validity::Textureless) > 0, "the flat patch is textureless");
    assert!(reasons(&c, flownav::flow::Validity::OutOfFrame) > 0, "border blocks are out of frame");

    let (a2, _) = pair(128, 96, 12, 0.0, 0.0, false);
    let (_, b2) = pair(128, 96, 13, 0.0, 0.0, false);
    let (g, c) = both(&ctx, &small(4, 5, 16, 6), &a2, &b2);
    assert_same(&g, &c, "unrelated frames");
    assert!(reasons(&c, flownav::flow::Validity::Ambiguous) > 0, "unrelated frames give ambiguous blocks");
}

#[test]
fn pyramid_raw_intensities_and_odd_block_sides_match() {
    let Some(ctx) = context() else { return };
    let (a, b) = pair(256, 192, 21, 13.4, -9.7, false);
    // Coarse-to-fine: 3 levels (blocks 32, 16, 8), motion beyond the radius of one level.
    let pyr = FlowParams { pyramid_levels: 3, refine_radius: 2, ..small(4, 6, 32, 4) };
    let (g, c) = both(&ctx, &pyr, &a, &b);
    assert_same(&g, &c, "pyramid 3");
    assert!(c.valid_count() >= 12, "pyramid finds the motion: {} valid", c.valid_count());
    // No prefilter, a block side that is not a multiple of 4 (row tails), odd frame width.
    let (a, b) = pair(149, 101, 22, 2.3, 1.6, true);
    for (block, levels) in [(10, 1), (18, 2), (6, 1)] {
        let p = FlowParams { prefilter_radius: 0, pyramid_levels: levels, ..small(4, 5, block, 5) };
        let (g, c) = both(&ctx, &p, &a, &b);
        assert_same(&g, &c, &format!("raw, block {block}, {levels} level(s)"));
    }
    // Prefilter radius 7 (window 15×15) with a 2-level pyramid.
    let p = FlowParams { prefilter_radius: 7, pyramid_levels: 2, ..small(3, 4, 24, 3) };
    let (g, c) = both(&ctx, &p, &a, &b);
    assert_same(&g, &c, "prefilter 7, pyramid 2");
}

#[test]
fn large_windows_spill_costs_to_global_memory_and_match() {
    let Some(ctx) = context() else { return };
    // 2·40+1 = 81² candidate costs do not fit workgroup memory: banded window, global costs.
    let (a, b) = pair(128, 96, 31, -17.0, 12.0, false);
    let p = FlowParams { ambiguity_ratio: 0.5, ..small(2, 3, 8, 40) };
    let (g, c) = both(&ctx, &p, &a, &b);
    assert_same(&g, &c, "radius 40");
}

#[test]
fn dense_mode_grid_and_parity() {
    let Some(ctx) = context() else { return };
    let (a, b) = pair(136, 96, 41, 1.5, -2.5, false);
    let p = FlowParams { stride: Some(8), ..small(1, 1, 16, 4) };
    // 136/8 = 17 → 16 columns, 96/8 = 12 → 8 rows.
    assert_eq!(p.grid(136, 96), (8, 16));
    let (g, c) = both(&ctx, &p, &a, &b);
    assert_eq!((g.rows, g.cols), (8, 16));
    assert_same(&g, &c, "dense stride 8");
    let reference = flownav::flow::reference::reference_flow(&p, &a, &b).expect("reference");
    assert_same(&g, &reference, "dense stride 8 vs reference");
    // The rule at 720p, and the errors.
    assert_eq!(p.grid(1280, 720), (88, 160));
    let tiled = FlowParams { placement: Placement::Tile, ..p.clone() };
    assert!(tiled.validate().unwrap_err().to_string().contains("flow.stride"));
    let coarse = FlowParams { stride: Some(16), ..p.clone() };
    let err = CpuFlow::new(coarse.clone()).unwrap().compute(&a, &b).unwrap_err().to_string();
    assert!(err.contains("smaller flow.stride"), "{err}");
    let err = GpuFlow::new(Arc::clone(&ctx), coarse).unwrap().compute(&a, &b).unwrap_err().to_string();
    assert!(err.contains("smaller flow.stride"), "{err}");
}

#[test]
fn pipelined_stream_reuses_frames_and_matches() {
    let Some(ctx) = context() else { return };
    let params = small(4, 5, 16, 5);
    let scene = texture(224, 160, 51, false);
    let frames: Vec<LumaImage> = (0..4)
        .map(|i| warp((&scene, 224, 160), (128, 96), (40.0 - 2.5 * i as f64, 30.0 + 1.25 * i as f64), 1.0))
        .collect();
    let mut g = GpuFlow::new(Arc::clone(&ctx), params.clone()).expect("GPU engine");
    let mut c = CpuFlow::new(params).expect("CPU engine");
    let expected: Vec<FlowField> = frames.windows(2).map(|p| c.compute(&p[0], &p[1]).unwrap().clone()).collect();
    let mut got = Vec::new();
    for (i, p) in frames.windows(2).enumerate() {
        if let Some(f) = g.compute_pipelined(&p[0], &p[1]).expect("submit") {
            got.push(f.clone());
        }
        assert_eq!(g.reused_frame_a(), i > 0, "pair {i}: frame A is the previous B");
    }
    got.push(g.flush().expect("flush").expect("one pair in flight").clone());
    assert!(g.flush().unwrap().is_none());
    assert_eq!(got.len(), expected.len());
    for (i, (gf, cf)) in got.iter().zip(&expected).enumerate() {
        assert_same(gf, cf, &format!("stream pair {i}"));
    }
    // A different frame size on the same engine rebuilds its buffers.
    let (a, b) = pair(160, 112, 52, 3.0, 2.0, false);
    let gf = g.compute(&a, &b).expect("resized").clone();
    assert_same(&gf, c.compute(&a, &b).unwrap(), "after resize");
}

#[test]
fn every_adapter_backend_agrees() {
    // Vulkan (lavapipe) and GL (llvmpipe) here, whatever is installed elsewhere.
    let instance = gpu::instance();
    let adapters = gpu::adapters(&instance);
    if adapters.is_empty() {
        eprintln!("SKIPPED: no wgpu adapter on this machine");
        return;
    }
    let (a, b) = pair(128, 96, 61, -3.2, 2.7, true);
    let params = FlowParams { pyramid_levels: 2, ..small(3, 4, 16, 3) };
    let cpu = CpuFlow::new(params.clone()).unwrap().compute(&a, &b).unwrap().clone();
    // An adapter may be listed and yet refuse a device (on a headless NVIDIA server the GL one
    // does: "Parent device is lost"); that is the driver's, and is reported. Every adapter that
    // opens must agree, and at least one must open.
    let mut agreed = 0;
    for adapter in &adapters {
        let name = gpu::describe_adapter(&adapter.get_info());
        let ctx = match GpuContext::new(adapter) {
            Ok(ctx) => Arc::new(ctx),
            Err(e) => {
                eprintln!("adapter {name}: no device ({e}), not compared");
                continue;
            }
        };
        eprintln!("adapter {name}");
        let mut g = GpuFlow::new(ctx, params.clone()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_same(g.compute(&a, &b).unwrap_or_else(|e| panic!("{name}: {e}")), &cpu, &name);
        agreed += 1;
    }
    assert!(agreed > 0, "none of {} adapters opened a device", adapters.len());
}

#[test]
fn backend_selection() {
    let instance = gpu::instance();
    let adapters = gpu::adapters(&instance);
    let hardware = adapters.iter().any(|a| gpu::is_hardware(&a.get_info()));
    let (engine, report) = create_engine(&FlowParams { backend: Backend::Auto, ..FlowParams::default() }).unwrap();
    assert_eq!(engine.name(), if hardware { "gpu" } else { "cpu" }, "{report}");
    assert_eq!(report.engine, engine.name());
    let (engine, report) = create_engine(&FlowParams { backend: Backend::Cpu, ..FlowParams::default() }).unwrap();
    assert_eq!((engine.name(), report.adapter), ("cpu", None));
    match create_engine(&FlowParams { backend: Backend::Gpu, ..FlowParams::default() }) {
        Ok((engine, report)) => {
            assert_eq!(engine.name(), "gpu");
            assert!(report.adapter.is_some(), "{report}");
        }
        Err(e) => {
            assert!(adapters.is_empty(), "an adapter exists but gpu failed: {e}");
            assert!(e.to_string().contains("mesa-vulkan-drivers"), "{e}");
        }
    }
    // Software adapters are never chosen by auto.
    for a in &adapters {
        let info = a.get_info();
        if info.device_type == wgpu::DeviceType::Cpu || info.name.contains("llvmpipe") {
            assert!(!gpu::is_hardware(&info), "{info:?}");
        }
    }
}

#[test]
fn exact_ties_follow_the_contract_tie_break() {
    let Some(ctx) = context() else { return };
    // Periodic patterns make many candidates cost exactly the same: the winner is decided only
    // by the tie-break (distance to the window centre, then dy, then dx).
    let stripes = |shift: usize| LumaImage::from_fn(96, 64, move |x, _| [20u8, 200, 90, 160][(x + shift) % 4]);
    let checker = |shift: usize| {
        LumaImage::from_fn(96, 64, move |x, y| if ((x + shift) / 3 + y / 3).is_multiple_of(2) { 40 } else { 220 })
    };
    let flat = LumaImage::from_fn(96, 64, |_, _| 77);
    let p = small(3, 4, 16, 5);
    for (name, a, b) in
        [("stripes", stripes(0), stripes(1)), ("checker", checker(0), checker(2)), ("flat", flat.clone(), flat.clone())]
    {
        let (g, c) = both(&ctx, &p, &a, &b);
        assert_same(&g, &c, name);
        let reference = flownav::flow::reference::reference_flow(&p, &a, &b).expect("reference");
        assert_same(&g, &reference, &format!("{name} vs reference"));
    }
}

#[test]
fn cli_gpu_backend_runs_or_names_what_to_install() {
    let tmp = std::env::temp_dir().join(format!("flownav-gpu-cli-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    let (a, b) = pair(128, 96, 71, 2.0, -1.0, false);
    let (pa, pb) = (tmp.join("a.png"), tmp.join("b.png"));
    image::GrayImage::from_raw(128, 96, a.data().to_vec()).unwrap().save(&pa).unwrap();
    image::GrayImage::from_raw(128, 96, b.data().to_vec()).unwrap().save(&pb).unwrap();
    let run = |backend_env: Option<&str>| {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_flownav"));
        cmd.args([
            "flow",
            "--json",
            "--flow-backend",
            "gpu",
            "--rows",
            "2",
            "--cols",
            "3",
            "--block",
            "16",
            "--radius",
            "4",
        ]);
        cmd.args([&pa, &pb]);
        if let Some(b) = backend_env {
            cmd.env("WGPU_BACKEND", b);
        }
        cmd.output().unwrap()
    };
    // A wgpu backend that does not exist off Apple platforms: no adapter, a clear error.
    if !cfg!(target_vendor = "apple") {
        let out = run(Some("metal"));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && !err.contains("panicked"), "{err}");
        for needle in ["no GPU adapter", "mesa-vulkan-drivers", "--flow-backend cpu"] {
            assert!(err.contains(needle), "{err}");
        }
    }
    if context().is_some() {
        let out = run(None);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(json["backend"], "gpu");
        assert_eq!(json["vectors"].as_array().unwrap().len(), 6);
    }
    std::fs::remove_dir_all(&tmp).ok();
}

// ---- The dense fast path (cost volume, `costvol.wgsl`) ------------------------------------

/// GPU fields with the cost volume forced on and off, and the CPU field; asserts which path ran.
fn three_ways(
    ctx: &Arc<GpuContext>,
    params: &FlowParams,
    a: &LumaImage,
    b: &LumaImage,
) -> (FlowField, FlowField, FlowField) {
    let mut g = GpuFlow::new(Arc::clone(ctx), params.clone()).expect("GPU engine");
    g.set_cost_volume(Some(true));
    let new = g.compute(a, b).expect("GPU flow, cost volume").clone();
    assert!(g.uses_cost_volume(), "the cost volume applies to {params:?}");
    g.set_cost_volume(Some(false));
    let old = g.compute(a, b).expect("GPU flow, per-block kernel").clone();
    assert!(!g.uses_cost_volume());
    let cpu = CpuFlow::new(params.clone()).expect("CPU engine").compute(a, b).expect("CPU flow").clone();
    (new, old, cpu)
}

/// Bit-identical fields (integer displacement, flags, costs and the f32 sub-pixel values).
fn assert_identical(got: &FlowField, want: &FlowField, what: &str) {
    assert_same(got, want, what);
    for (i, (g, w)) in got.vectors.iter().zip(&want.vectors).enumerate() {
        assert!(
            g.u.to_bits() == w.u.to_bits() && g.v.to_bits() == w.v.to_bits(),
            "{what}: block {i}: sub-pixel values differ: {g:?} vs {w:?}"
        );
    }
}

/// The cost volume, the per-block kernel and the CPU engine agree bit for bit.
fn check_three(ctx: &Arc<GpuContext>, params: &FlowParams, a: &LumaImage, b: &LumaImage, what: &str) -> FlowField {
    let (new, old, cpu) = three_ways(ctx, params, a, b);
    assert_identical(&new, &cpu, &format!("{what}: cost volume vs CPU"));
    assert_identical(&old, &cpu, &format!("{what}: per-block GPU kernel vs CPU"));
    assert_identical(&new, &old, &format!("{what}: cost volume vs per-block GPU kernel"));
    cpu
}

fn dense(stride: usize, block: usize, radius: usize) -> FlowParams {
    FlowParams { stride: Some(stride), block, radius, backend: Backend::Gpu, ..FlowParams::default() }
}

fn count(f: &FlowField, v: flownav::flow::Validity) -> usize {
    f.vectors.iter().filter(|x| x.validity == v).count()
}

#[test]
fn cost_volume_random_subpixel_motion_with_gain_and_flat_patch() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(91);
    for seed in 0..3 {
        let (mx, my) = (rng.below(1100) as f64 / 100.0 - 5.5, rng.below(1100) as f64 / 100.0 - 5.5);
        let (a, b) = pair(160, 120, 100 + seed, mx, my, seed == 1);
        let p = dense(8, 32, 6);
        let c = check_three(&ctx, &p, &a, &b, &format!("seed {seed}, motion ({mx:.2}, {my:.2})"));
        assert!(c.valid_count() > 20, "seed {seed}: {} valid", c.valid_count());
        if seed == 1 {
            assert!(count(&c, flownav::flow::Validity::Textureless) > 0, "the flat patch is textureless");
        }
    }
}

#[test]
fn cost_volume_unrelated_and_periodic_frames() {
    let Some(ctx) = context() else { return };
    let p = dense(8, 16, 5);
    let (a, _) = pair(136, 96, 111, 0.0, 0.0, false);
    let (_, b) = pair(136, 96, 112, 0.0, 0.0, false);
    let c = check_three(&ctx, &p, &a, &b, "unrelated frames");
    assert!(count(&c, flownav::flow::Validity::Ambiguous) > 0, "unrelated frames give ambiguous blocks");
    // Only the tie-break decides between equal costs.
    let stripes = |shift: usize| LumaImage::from_fn(136, 96, move |x, _| [20u8, 200, 90, 160][(x + shift) % 4]);
    let checker = |shift: usize| {
        LumaImage::from_fn(136, 96, move |x, y| if ((x + shift) / 3 + y / 3).is_multiple_of(2) { 40 } else { 220 })
    };
    let flat = LumaImage::from_fn(136, 96, |_, _| 77);
    for (name, a, b) in
        [("stripes", stripes(0), stripes(1)), ("checker", checker(0), checker(2)), ("flat", flat.clone(), flat.clone())]
    {
        check_three(&ctx, &p, &a, &b, name);
        let reference = flownav::flow::reference::reference_flow(&p, &a, &b).expect("reference");
        let mut g = GpuFlow::new(Arc::clone(&ctx), p.clone()).unwrap();
        g.set_cost_volume(Some(true));
        assert_same(g.compute(&a, &b).unwrap(), &reference, &format!("{name}: cost volume vs reference"));
    }
}

#[test]
fn cost_volume_motion_at_and_beyond_the_radius_and_borders() {
    let Some(ctx) = context() else { return };
    // Radius 4: motion exactly at the radius, and beyond it (the best candidate sits on the
    // window's edge: out_of_frame); blocks at the frame borders have windows cut by the frame.
    for (mx, my) in [(4.0, -4.0), (6.0, 2.0), (-7.5, -5.0)] {
        let (a, b) = pair(136, 104, 121, mx, my, false);
        let p = dense(8, 16, 4);
        let c = check_three(&ctx, &p, &a, &b, &format!("motion ({mx}, {my})"));
        assert!(count(&c, flownav::flow::Validity::OutOfFrame) > 0, "({mx}, {my}): edge blocks");
    }
    // A tiled grid (blocks touching each other and the border, no overlap) with the path forced.
    let (a, b) = pair(128, 96, 122, 3.0, -2.0, true);
    let p = FlowParams { placement: Placement::Tile, ..small(6, 8, 16, 5) };
    check_three(&ctx, &p, &a, &b, "tiled grid, forced");
}

#[test]
fn cost_volume_odd_sizes_small_stride_and_large_radius() {
    let Some(ctx) = context() else { return };
    // Odd frame width and height, block sides that are not multiples of 4, raw intensities.
    let (a, b) = pair(149, 101, 131, 2.3, -1.6, true);
    for (stride, block, k) in [(8, 18, 4), (8, 10, 0), (4, 6, 4), (4, 14, 2)] {
        let p = FlowParams { prefilter_radius: k, ..dense(stride, block, 5) };
        check_three(&ctx, &p, &a, &b, &format!("149x101, stride {stride}, block {block}, prefilter {k}"));
    }
    // Radius 40 (81 × 81 candidates, cut by the 96×64 frame) at stride 4.
    let (a, b) = pair(96, 64, 132, -17.0, 12.0, false);
    let p = FlowParams { ambiguity_ratio: 0.5, ..dense(4, 8, 40) };
    check_three(&ctx, &p, &a, &b, "stride 4, radius 40");
}

#[test]
fn cost_volume_dispatch_and_fallback() {
    let Some(ctx) = context() else { return };
    let (a, b) = pair(136, 96, 141, 1.0, 2.0, false);
    let run = |p: &FlowParams, mode: Option<bool>| {
        let mut g = GpuFlow::new(Arc::clone(&ctx), p.clone()).unwrap();
        g.set_cost_volume(mode);
        let f = g.compute(&a, &b).unwrap().clone();
        (g.uses_cost_volume(), f)
    };
    // Default: dense grids (blocks overlapping ≥ 2× along both axes) take the cost volume...
    assert!(run(&dense(8, 32, 4), None).0, "dense stride 8, block 32");
    assert!(!run(&dense(8, 16, 4), None).0, "block 16 at steps of 9 and 12 px: overlap < 2");
    // ... sparse grids and pyramids the per-block kernel, even when forced.
    assert!(!run(&small(4, 5, 16, 4), None).0, "16 px blocks 27 px apart");
    let pyr = FlowParams { pyramid_levels: 2, refine_radius: 2, ..dense(8, 16, 3) };
    let (used, f) = run(&pyr, Some(true));
    assert!(!used, "pyramids never use the cost volume");
    let cpu = CpuFlow::new(pyr.clone()).unwrap().compute(&a, &b).unwrap().clone();
    assert_identical(&f, &cpu, "pyramid, forced: fell back");
    // The switch changes the path on a live engine, and the results stay identical.
    let p = dense(8, 32, 4);
    let mut g = GpuFlow::new(Arc::clone(&ctx), p.clone()).unwrap();
    let mut fields = Vec::new();
    for mode in [Some(true), Some(false), None, Some(true)] {
        g.set_cost_volume(mode);
        fields.push(g.compute(&a, &b).unwrap().clone());
        assert_eq!(g.uses_cost_volume(), mode != Some(false));
    }
    for f in &fields[1..] {
        assert_identical(f, &fields[0], "switching paths");
    }
}

#[test]
fn cost_volume_timing_information() {
    // Information only (no timed assertion): both GPU paths on one dense pair, printed.
    let Some(ctx) = context() else { return };
    let (a, b) = pair(256, 192, 151, 2.5, -1.5, false);
    let p = dense(8, 32, 8);
    let mut g = GpuFlow::new(Arc::clone(&ctx), p.clone()).unwrap();
    let mut fields = Vec::new();
    for mode in [Some(true), Some(false)] {
        g.set_cost_volume(mode);
        g.compute(&a, &b).unwrap(); // pipelines and buffers
        let t = std::time::Instant::now();
        let f = g.compute(&a, &b).unwrap().clone();
        eprintln!(
            "256x192 dense (stride 8, block 32, radius 8), cost volume {}: {:.1} ms per pair ({} absolute differences)",
            if g.uses_cost_volume() { "on" } else { "off" },
            t.elapsed().as_secs_f64() * 1e3,
            g.cost_volume_abs_diffs()
                .map_or(format!("at most {} per-block", f.vectors.len() * 17 * 17 * 32 * 32), |n| n.to_string()),
        );
        fields.push(f);
        // Per-pass GPU times (timestamp queries, where the device has them): one entry per
        // compute pass, then the total; the field is unchanged.
        if g.set_pass_timing(true) {
            let f = g.compute(&a, &b).unwrap().clone();
            let times = g.last_pass_times().expect("pass times after a timed pair");
            eprintln!("  pass times (ms): {times:?}");
            let labels: Vec<&str> = times.iter().map(|t| t.0).collect();
            // both frames are new: each is preprocessed in its own pass
            let want: &[&str] = if mode == Some(true) {
                &["prep A", "prep B", "costvol", "reduce", "total"]
            } else {
                &["prep A", "prep B", "match L0", "total"]
            };
            assert_eq!(labels, want);
            assert!(times.iter().all(|t| t.1.is_finite() && t.1 >= 0.0), "{times:?}");
            assert_identical(&f, &fields[fields.len() - 1], "timed pass");
            // pipelined pairs: timing stays consistent with two pairs in flight
            for _ in 0..3 {
                g.compute_pipelined(&a, &b).unwrap();
            }
            g.flush().unwrap();
            assert!(g.last_pass_times().is_some());
            assert!(!g.set_pass_timing(false));
            assert!(g.last_pass_times().is_none());
        } else {
            eprintln!("  no timestamp queries on this adapter: no pass times");
        }
    }
    assert_identical(&fields[0], &fields[1], "timed pair");
}

#[test]
fn cost_volume_forced_tile_shapes_match() {
    // Other tiles and dx groups than the planner's: one group per dx (33 groups, 66 barriers),
    // all 33 dx in one group (several rounds per phase), tiles of one block, odd tiles, a tile
    // wider than the grid. Each must equal the CPU engine bit for bit.
    let Some(ctx) = context() else { return };
    let (a, b) = pair(160, 120, 161, -3.3, 4.6, true);
    let p = dense(8, 32, 16);
    let cpu = CpuFlow::new(p.clone()).unwrap().compute(&a, &b).unwrap().clone();
    let mut g = GpuFlow::new(Arc::clone(&ctx), p.clone()).unwrap();
    g.set_cost_volume(Some(true));
    for tile in [(1, 1, 1), (4, 4, 1), (4, 4, 33), (16, 8, 3), (8, 4, 7), (3, 5, 4), (32, 2, 3)] {
        g.set_cost_volume_tile(Some(tile));
        let f = g.compute(&a, &b).unwrap().clone();
        let used = g.cost_volume_tile();
        eprintln!("forced tile {tile:?}: cost volume {used:?}");
        if tile != (4, 4, 33) {
            // (4, 4, 33) needs 29.5 KB of workgroup memory and may fall back
            assert_eq!(used, Some(tile), "{tile:?} fits 16 KiB of workgroup memory");
        }
        assert_identical(&f, &cpu, &format!("tile {tile:?}"));
    }
    // 128 px wide: cells of exactly 8 px, so the x origins are congruent mod 4 and the column
    // sums are kept per quad of 4 columns (160 px above: per column).
    let (a, b) = pair(128, 96, 162, 4.4, -2.7, false);
    let cpu = CpuFlow::new(p.clone()).unwrap().compute(&a, &b).unwrap().clone();
    for tile in [None, Some((1, 1, 1)), Some((16, 8, 3)), Some((3, 5, 4)), Some((4, 4, 33))] {
        g.set_cost_volume_tile(tile);
        let f = g.compute(&a, &b).unwrap().clone();
        eprintln!("128x96, tile {tile:?}: cost volume {:?}", g.cost_volume_tile());
        assert!(g.uses_cost_volume());
        assert_identical(&f, &cpu, &format!("128x96, tile {tile:?}"));
    }
}
