//! Re-runs the OFFIS plane fit, features and classifiers on the envelope profiles stored in
//! `flownav bench-offis --json` reports, without rendering: a quick check of a change to the
//! TPO model or the rule bases on scene sets already rendered.
//!
//! ```sh
//! flownav bench-offis --seed 1 --json > s1.json
//! cargo run --release --example offis_replay -- [--rules DIR] [--list [--details]] s1.json [s3.json ...]
//! ```
//!
//! Prints each file's TPO accuracy and confusion matrix (rows = truth, columns = predicted, in
//! wall, corner, door, corridor, none order); `--list` also every scene that is wrong or whose
//! class differs from the stored one, `--details` with its features and planes. `--rules DIR`
//! takes the rule bases from `DIR` instead of the built-in ones.
//!
//! The bench shows each scene as a short drive and reports the TPO decided over its last frame
//! pairs (`offis::temporal`); the report stores the *last* pair's profile only, so this replays
//! the last pair's own decision (`Attributes::decision`), not the filtered one: a class that
//! differs from the stored one may be the filter's doing, not a change. A change to the plane
//! fit or the rules is still measured on the single pairs here, then with `bench-offis`.
//!
//! Bin bearings are not stored in the report: each bin's bearing is the median bearing of its
//! envelope points over the file (the bench drives straight, so they do not change). Obstacle
//! figures need the flow field and are not replayed.

use clap::Parser;
use flownav::offis::classify::Classifier;
use flownav::offis::features::{Bin, Features, TpoModel};
use flownav::perception::TpoShape;
use serde::Deserialize;
use std::path::PathBuf;

#[derive(Parser)]
struct Args {
    /// Take the rule bases from this folder instead of the built-in ones.
    #[arg(long)]
    rules: Option<PathBuf>,
    /// List every scene that is wrong or whose class differs from the stored one.
    #[arg(long)]
    list: bool,
    /// ... with its features and planes.
    #[arg(long, requires = "list")]
    details: bool,
    /// `bench-offis --json` reports.
    #[arg(required = true)]
    files: Vec<PathBuf>,
}

/// The parts of a `bench-offis --json` report ([`flownav::sim::bench::Report`]) replayed.
#[derive(Deserialize)]
struct Report {
    samples: Vec<Sample>,
}

#[derive(Deserialize)]
struct Sample {
    index: usize,
    label: String,
    truth: TpoShape,
    predicted: TpoShape,
    profile: Vec<Option<[f64; 2]>>,
}

fn index(s: TpoShape) -> usize {
    TpoShape::ALL.iter().position(|&x| x == s).expect("ALL lists every shape")
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let mut classifier = Classifier::load(args.rules.as_deref())?;

    let (mut total, mut right) = (0, 0);
    for file in &args.files {
        let report: Report = serde_json::from_str(&std::fs::read_to_string(file)?)?;
        let samples = &report.samples;
        let nb = samples.first().map_or(0, |s| s.profile.len());
        let mut bearings = vec![Vec::new(); nb];
        for s in samples {
            for (b, p) in s.profile.iter().enumerate() {
                if let Some([x, y]) = p {
                    bearings[b].push(y.atan2(*x));
                }
            }
        }
        let bearing: Vec<f64> = bearings
            .iter_mut()
            .map(|v| {
                v.sort_by(f64::total_cmp);
                v.get(v.len() / 2).copied().unwrap_or(0.0)
            })
            .collect();
        let mut confusion = [[0usize; 5]; 5];
        for s in samples {
            let bins: Vec<Bin> =
                s.profile.iter().zip(&bearing).map(|(&point, &bearing)| Bin { point, bearing }).collect();
            let model = TpoModel::fit(&bins);
            let f = Features::compute(&bins, &model);
            let d = classifier.classify(&f)?;
            let (truth, got) = (index(s.truth), index(d.shape));
            confusion[truth][got] += 1;
            if args.list && (truth != got || s.predicted != d.shape) {
                println!(
                    "{} #{:<3} {:<8} -> {:<8} (bench: {:<8}) {:.2} | {}",
                    file.display(),
                    s.index,
                    s.truth.name(),
                    d.shape.name(),
                    s.predicted.name(),
                    d.confidence,
                    s.label
                );
                if args.details {
                    println!("    {f:?}");
                    for l in model.planes() {
                        println!(
                            "    plane: heading {:.1}° side {:+.2} centre ({:.2}, {:+.2}) extent {:.2} inliers {:016b}",
                            l.heading_angle_deg(),
                            l.side(),
                            l.centre[0],
                            l.centre[1],
                            l.extent[1] - l.extent[0],
                            l.inliers
                        );
                    }
                    println!("    occluded {:016b}", model.occluded);
                }
            }
        }
        let ok: usize = (0..5).map(|k| confusion[k][k]).sum();
        let n: usize = confusion.iter().flatten().sum();
        println!("{}: {:.1}% ({ok} of {n}) {confusion:?}", file.display(), 100.0 * ok as f64 / n.max(1) as f64);
        total += n;
        right += ok;
    }
    println!("all: {:.1}% ({right} of {total})", 100.0 * right as f64 / total.max(1) as f64);
    Ok(())
}
