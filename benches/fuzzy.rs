//! Speed of one fuzzy evaluation (fuzzify, rules, aggregation, centroid) on the shipped
//! example systems. `cargo bench --bench fuzzy`.
//!
//! Besides criterion's wall-clock times, it prints the on-CPU time per evaluation (from
//! `/proc/thread-self/schedstat`, Linux), which stays meaningful on a loaded machine where
//! wall-clock times include waiting for a core.

use criterion::{Criterion, criterion_group, criterion_main};
use flownav::fuzzy::FuzzySystem;
use std::hint::black_box;

/// Nanoseconds this thread has run on a CPU, or `None` off Linux.
fn thread_cpu_ns() -> Option<u64> {
    std::fs::read_to_string("/proc/thread-self/schedstat").ok()?.split_whitespace().next()?.parse().ok()
}

fn cpu_ns_per_eval(sys: &FuzzySystem, points: &[Vec<f64>]) -> Option<f64> {
    const N: usize = 1_000_000;
    let mut ev = sys.evaluation();
    let start = thread_cpu_ns()?;
    for k in 0..N {
        sys.evaluate_into(black_box(&points[k & 63]), &mut ev).expect("evaluates");
        black_box(ev.values()[0]);
    }
    Some((thread_cpu_ns()? - start) as f64 / N as f64)
}

fn bench(c: &mut Criterion) {
    let reference = include_str!("../rules/examples/reference.toml").to_string();
    let variants = [
        ("reference/exact", reference.clone()),
        ("reference/sampled101", reference.replace("centroid = \"exact\"", "centroid = \"sampled\"\nresolution = 101")),
        (
            "reference/sampled1001",
            reference.replace("centroid = \"exact\"", "centroid = \"sampled\"\nresolution = 1001"),
        ),
        ("avoid", include_str!("../rules/examples/avoid.toml").to_string()),
    ];
    for (name, text) in variants {
        let sys = FuzzySystem::from_toml_str(&text, name).expect("valid system");
        let n = sys.inputs().len();
        // A fixed sweep of inputs across each universe, so every rule and branch is exercised.
        let points: Vec<Vec<f64>> = (0..64)
            .map(|k| {
                sys.inputs()
                    .iter()
                    .enumerate()
                    .map(|(i, v)| v.min + (v.max - v.min) * (((k * (7 + 3 * i)) % 64) as f64 / 63.0))
                    .collect()
            })
            .collect();
        assert!(points.iter().all(|p| p.len() == n));
        let mut ev = sys.evaluation();
        if let Some(ns) = cpu_ns_per_eval(&sys, &points) {
            println!("fuzzy/{name}: {ns:.0} ns on-CPU per evaluation");
        }
        let mut k = 0;
        c.bench_function(&format!("fuzzy/{name}"), |b| {
            b.iter(|| {
                k = (k + 1) & 63;
                sys.evaluate_into(black_box(&points[k]), &mut ev).expect("evaluates");
                black_box(ev.values()[0])
            })
        });
    }
    c.bench_function("fuzzy/load_reference", |b| {
        b.iter(|| FuzzySystem::from_toml_str(black_box(&reference), "reference.toml").expect("valid"))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
