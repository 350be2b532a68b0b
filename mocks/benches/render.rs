//! Render speed of the simulated camera at the C310's 1280×720 (target: ≥ 30 frames/s on a
//! 2-core machine), and of the simulator's 320×180 views. `cargo bench -p flownav-mocks --bench render`

use criterion::{Criterion, criterion_group, criterion_main};
use hal::{Calibration, LumaImage};
use mocks::{Effects, Pose, Renderer, World};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let world = World::office();
    let calib = Calibration::nominal_c310();
    let level = Renderer::new(&world, &calib);
    // In the corridor looking west past the boxes and the person, and the start view in R9.
    let corridor = Pose::new(20.0, 0.0, std::f64::consts::PI);
    let mut img = LumaImage::default();
    let mut g = c.benchmark_group("render_720p");
    g.sample_size(20);
    g.bench_function("corridor", |b| {
        b.iter(|| level.render_frame(corridor, black_box(corridor), &Effects::default(), 0, &mut img))
    });
    g.bench_function("start_room", |b| {
        b.iter(|| level.render_frame(world.start, black_box(world.start), &Effects::default(), 0, &mut img))
    });
    let noisy = Effects { noise_sigma: 2.0, gain: 1.1, offset: -4.0, ..Effects::default() };
    g.bench_function("corridor_noise_exposure", |b| {
        b.iter(|| level.render_frame(corridor, black_box(corridor), &noisy, 1, &mut img))
    });
    g.bench_function("corridor_with_depth", |b| b.iter(|| level.render_with_depth(black_box(corridor))));
    let mut pitched_calib = calib.clone();
    pitched_calib.mount.pitch_rad = 0.1;
    let pitched = Renderer::new(&world, &pitched_calib);
    g.bench_function("corridor_pitched_0.1rad", |b| {
        b.iter(|| pitched.render_frame(corridor, black_box(corridor), &Effects::default(), 0, &mut img))
    });
    g.finish();
    // The views `flownav sim` renders: 320×180 with sensor noise.
    let sim = Renderer::new(&world, &calib.scaled_to(320, 180));
    let noise = Effects { noise_sigma: 2.0, seed: 0, ..Effects::default() };
    let mut g = c.benchmark_group("render_sim");
    g.bench_function("corridor_320x180_noise", |b| {
        b.iter(|| sim.render_frame(corridor, black_box(corridor), &noise, 1, &mut img))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
