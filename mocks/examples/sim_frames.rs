//! Renders the views `flownav sim` renders along a path through the office (room, doorway,
//! corridor) and prints fingerprints of everything the renderer outputs, and the CPU time per
//! frame. For measuring the renderer (`valgrind --tool=callgrind`, `perf record`) and for
//! checking that a change to it leaves every output bit for bit the same:
//!
//! ```sh
//! cargo run --release -p flownav-mocks --example sim_frames -- [FRAMES] [SEED] [all]
//! ```
//!
//! Without `all` only the simulator's frames are rendered (320×180, sensor noise σ = 2, level
//! camera): the workload to time. With `all` it also fingerprints clean frames, depth and surface
//! ids, a pitched camera, a distorted lens, motion blur with exposure, and the ground truth's
//! surface-id renders.

use hal::{Calibration, LumaImage};
use mocks::{Effects, Pose, Renderer, World};
use std::time::Instant;

/// FNV-1a over bytes.
fn fnv(h: u64, bytes: impl IntoIterator<Item = u8>) -> u64 {
    bytes.into_iter().fold(h, |h, b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3))
}

const FNV0: u64 = 0xcbf2_9ce4_8422_2325;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let frames: usize = args.first().and_then(|s| s.parse().ok()).unwrap_or(300);
    let seed: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let all = args.iter().any(|a| a == "all");
    let world = World::office().with_random_obstacles(seed).expect("the office has a [random] section");
    let calib = Calibration::nominal_c310().scaled_to(320, 180);
    let waypoints = [
        world.start,
        world.start.advance(0.4, 0.3, 1.0),
        Pose::new(5.0, -0.5, 0.2),
        Pose::new(9.0, 0.4, 1.5),
        Pose::new(14.0, 0.3, 3.0),
        Pose::new(20.0, 0.0, std::f64::consts::PI),
    ];
    let path: Vec<Pose> = (0..frames)
        .map(|i| {
            let f = i as f64 / frames.max(2).saturating_sub(1) as f64 * (waypoints.len() - 1) as f64;
            let k = (f.floor() as usize).min(waypoints.len() - 2);
            waypoints[k].lerp(&waypoints[k + 1], f - k as f64)
        })
        .collect();

    let renderer = Renderer::new(&world, &calib);
    let fx = Effects { noise_sigma: 2.0, seed, ..Effects::default() };
    let mut img = LumaImage::default();
    let mut h = FNV0;
    let t0 = Instant::now();
    let cpu0 = cpu_seconds();
    for (seq, p) in path.iter().enumerate() {
        let from = if seq == 0 { *p } else { path[seq - 1] };
        renderer.render_frame(from, *p, &fx, seq as u64, &mut img);
        h = fnv(h, img.data().iter().copied());
    }
    let (wall, cpu) = (t0.elapsed().as_secs_f64(), cpu_seconds() - cpu0);
    println!(
        "sim frames: {frames} at 320x180, fingerprint {h}, {:.3} ms CPU per frame ({:.3} ms wall)",
        cpu * 1e3 / frames as f64,
        wall * 1e3 / frames as f64
    );
    if !all {
        return;
    }
    let every = |step: usize| path.iter().step_by(step).copied();
    let h = every(7).fold(FNV0, |h, p| fnv(h, renderer.render(p).data().iter().copied()));
    println!("clean frames: {h}");
    let h = every(7).fold(FNV0, |h, p| {
        let (ids, depth) = renderer.render_surfaces(p);
        let h = fnv(h, ids.iter().flat_map(|i| i.to_le_bytes()));
        fnv(h, depth.data.iter().flat_map(|d| d.to_le_bytes()))
    });
    println!("surface ids and depth: {h}");
    let h = every(7).fold(FNV0, |h, p| {
        let (img, depth) = renderer.render_with_depth(p);
        let h = fnv(h, img.data().iter().copied());
        let h = fnv(h, renderer.depth(p).data.iter().flat_map(|d| d.to_le_bytes()));
        fnv(h, depth.data.iter().flat_map(|d| d.to_le_bytes()))
    });
    println!("frames with depth, depth alone: {h}");
    let blur = Effects { noise_sigma: 3.0, seed: seed + 1, blur_samples: 3, gain: 1.1, offset: -4.0 };
    let h = every(7).enumerate().fold(FNV0, |h, (i, p)| {
        renderer.render_frame(p.advance(-0.3, 0.2, 0.1), p, &blur, i as u64, &mut img);
        fnv(h, img.data().iter().copied())
    });
    println!("blur and exposure: {h}");

    let mut pitched = calib.clone();
    pitched.mount.pitch_rad = 0.1;
    let pitched = Renderer::new(&world, &pitched);
    let h = every(11).enumerate().fold(FNV0, |h, (i, p)| {
        pitched.render_frame(p, p, &fx, i as u64, &mut img);
        let (ids, depth) = pitched.render_surfaces(p);
        let h = fnv(h, img.data().iter().copied());
        let h = fnv(h, ids.iter().flat_map(|i| i.to_le_bytes()));
        fnv(h, depth.data.iter().flat_map(|d| d.to_le_bytes()))
    });
    println!("pitched camera: {h}");

    let mut wide = Calibration::nominal_c310();
    wide.camera.fx = 640.0;
    wide.camera.fy = 640.0;
    wide.camera.distortion = [-0.25, 0.06, 0.0005, -0.0003, 0.0];
    let lens = Renderer::new(&world, &wide.scaled_to(320, 180));
    let h = every(11).enumerate().fold(FNV0, |h, (i, p)| {
        lens.render_frame(p, p, &fx, i as u64, &mut img);
        let h = fnv(h, img.data().iter().copied());
        let h = fnv(h, lens.render(p).data().iter().copied());
        let (ids, depth) = lens.render_surfaces(p);
        let h = fnv(h, ids.iter().flat_map(|i| i.to_le_bytes()));
        fnv(h, depth.data.iter().flat_map(|d| d.to_le_bytes()))
    });
    println!("distorted lens: {h}");

    let truth = mocks::GroundTruth::new(&world, &calib);
    let h = every(5).fold(FNV0, |h, p| fnv(h, format!("{:?}", truth.frame(p)).bytes()));
    println!("ground truth: {h}");
}

/// CPU time of the process (user + system, every thread), s.
fn cpu_seconds() -> f64 {
    let t = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // after the command name's closing parenthesis: state, ppid, …; utime and stime are 12th and 13th
    let rest: Vec<&str> = t.rsplit_once(')').map_or("", |(_, r)| r).split_whitespace().collect();
    let field = |i: usize| rest.get(i).and_then(|s| s.parse::<f64>().ok()).unwrap_or(0.0);
    (field(11) + field(12)) / 100.0 // USER_HZ on Linux
}
