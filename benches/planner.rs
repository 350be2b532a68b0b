//! Speed of one search for a way past a blocked path ([`ObstacleMemory::plan_way`]) in a 2 m
//! corridor with a box across most of it and the walls seen along 4 m. `cargo bench --bench
//! planner`.
//!
//! Besides criterion's wall-clock times, it prints the on-CPU time per search (from
//! `/proc/thread-self/schedstat`, Linux), which stays meaningful on a loaded machine.

use criterion::{Criterion, criterion_group, criterion_main};
use flownav::mofis::memory::{GuardCells, MemoryParams, ObstacleMemory, PlanTarget};
use flownav::offis::points::SurfacePoint;
use flownav::pafsis::Lane;
use hal::BodyVelocity;
use std::hint::black_box;

/// Nanoseconds this thread has run on a CPU, or `None` off Linux.
fn thread_cpu_ns() -> Option<u64> {
    std::fs::read_to_string("/proc/thread-self/schedstat").ok()?.split_whitespace().next()?.parse().ok()
}

/// A memory that has seen a box 1.5 m ahead from 0.55 m right to 0.25 m left of the corridor's
/// centre line, and both walls 1 m to either side from 0 to 4 m ahead.
fn scene() -> ObstacleMemory {
    let p = MemoryParams { min_travel_m: 0.0, ..MemoryParams::default() };
    let mut m = ObstacleMemory::new(p, 26.7f64.to_radians(), 0.4);
    let pt = |forward: f64, left: f64| SurfacePoint { forward, left, up: 0.5, radial_px: 3.0 };
    let mut seen: Vec<SurfacePoint> =
        (0..=8).flat_map(|k| [pt(1.5, -0.55 + 0.1 * k as f64), pt(1.6, -0.55 + 0.1 * k as f64)]).collect();
    seen.extend((0..40).flat_map(|k| [pt(0.1 * k as f64, 1.0), pt(0.1 * k as f64, -1.0)]));
    for _ in 0..3 {
        m.update(BodyVelocity { v: 0.0, omega: 0.0 }, 0.1, &seen, true);
    }
    m.set_lane(Some(Lane { left_m: 0.0, angle_rad: 0.0, half_width_m: 1.0 }));
    m
}

fn bench(c: &mut Criterion) {
    let m = scene();
    let guard = GuardCells { clearance_m: 0.04, min_evidence: 0.3, cluster: true, min_cells: 2 };
    let target = PlanTarget { bearing_rad: 0.0, distance_m: 3.0 };
    assert!(m.plan_way(target, &guard).aim.is_some_and(|[_, l]| l > 0.0), "the way passes left");
    const N: u64 = 2000;
    if let Some(start) = thread_cpu_ns() {
        for _ in 0..N {
            black_box(m.plan_way(black_box(target), &guard));
        }
        if let Some(end) = thread_cpu_ns() {
            println!("plan_way: {:.1} µs on-CPU per search", (end - start) as f64 / N as f64 / 1e3);
        }
    }
    c.bench_function("plan_way/corridor_box", |b| b.iter(|| black_box(m.plan_way(black_box(target), &guard))));
}

criterion_group!(benches, bench);
criterion_main!(benches);
