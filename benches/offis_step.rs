//! Criterion benchmark of one OFFIS step (after flow): de-rotation, outlier filter, quadrant
//! matrices, planes, tilt, masks, zoom-in, distances, the plane fit, the situation classifiers
//! the obstacle decision and the temporal filter of the TPO decision on a 16×16 field (DESIGN.md
//! budget: ≤ 0.2 ms), as the per-frame pipeline calls it ([`Offis::step_filtered`], its window
//! full after the first iterations). The field is the closed-form flow of a corridor with a box,
//! turning while driving.

use criterion::{Criterion, criterion_group, criterion_main};
use flownav::offis::synth::{Rect, Scene};
use flownav::offis::temporal::Motion;
use flownav::offis::{Offis, OffisParams};
use hal::{BodyVelocity, Calibration};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let calib = Calibration::nominal_c310();
    let z = [-10.0, 10.0];
    let scene = Scene {
        rects: vec![
            Rect::side(1.0, [0.0, 60.0], z),
            Rect::side(-1.0, [0.0, 60.0], z),
            Rect::frontal(60.0, [-1.0, 1.0], z),
            Rect::frontal(2.0, [0.3, 0.9], [-1.0, 0.5]),
            Rect::floor(),
        ],
    };
    let vel = BodyVelocity::new(0.3, 0.2);
    let dt = 1.0 / 30.0;
    let field = scene.flow(&calib, 16, 16, vel, dt).field;
    let mut offis = Offis::new(OffisParams::default()).expect("built-in rules");
    let since = Motion { yaw_rad: vel.omega * dt, dt, forward_m: vel.v * dt };
    c.bench_function("offis_step_16x16", |b| {
        b.iter(|| offis.step_filtered(black_box(&field), vel, dt, &calib, since).expect("valid field"))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
