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
//! Bin bearings are not stored in the report: each bin's bearing is the median bearing of its
//! envelope points over the file (the bench drives straight, so they do not change). Obstacle
//! figures need the flow field and are not replayed.

use flownav::offis::classify::Classifier;
use flownav::offis::features::{Bin, Features, TpoModel};
use flownav::perception::TpoShape;
use serde_json::Value;

fn shape(name: &str) -> usize {
    TpoShape::ALL.iter().position(|s| s.name() == name).unwrap_or_else(|| panic!("unknown shape {name}"))
}

fn main() -> anyhow::Result<()> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let mut rules = None;
    if let Some(k) = args.iter().position(|a| a == "--rules") {
        rules = Some(std::path::PathBuf::from(args.remove(k + 1)));
        args.remove(k);
    }
    let list = args.iter().any(|a| a == "--list");
    let details = args.iter().any(|a| a == "--details");
    args.retain(|a| a != "--details");
    args.retain(|a| a != "--list");
    let mut classifier = Classifier::load(rules.as_deref())?;

    let (mut total, mut right) = (0, 0);
    for file in &args {
        let report: Value = serde_json::from_str(&std::fs::read_to_string(file)?)?;
        let samples = report["samples"].as_array().expect("samples");
        let nb = samples[0]["profile"].as_array().expect("profile").len();
        let mut bearings = vec![Vec::new(); nb];
        for s in samples {
            for (b, p) in s["profile"].as_array().unwrap().iter().enumerate() {
                if let Some(p) = p.as_array() {
                    bearings[b].push(p[1].as_f64().unwrap().atan2(p[0].as_f64().unwrap()));
                }
            }
        }
        let bearing: Vec<f64> = bearings
            .iter_mut()
            .map(|v| {
                v.sort_by(f64::total_cmp);
                v[v.len() / 2]
            })
            .collect();
        let mut confusion = [[0usize; 5]; 5];
        for s in samples {
            let bins: Vec<Bin> = s["profile"]
                .as_array()
                .unwrap()
                .iter()
                .enumerate()
                .map(|(b, p)| Bin {
                    point: p.as_array().map(|p| [p[0].as_f64().unwrap(), p[1].as_f64().unwrap()]),
                    bearing: bearing[b],
                })
                .collect();
            let model = TpoModel::fit(&bins);
            let f = Features::compute(&bins, &model);
            let d = classifier.classify(&f)?;
            let truth = shape(s["truth"].as_str().unwrap());
            let got = shape(d.shape.name());
            confusion[truth][got] += 1;
            let was = s["predicted"].as_str().unwrap();
            if list && (truth != got || was != d.shape.name()) {
                println!(
                    "{file} #{:<3} {:<8} -> {:<8} (bench: {:<8}) {:.2} | {}",
                    s["index"],
                    TpoShape::ALL[truth].name(),
                    d.shape.name(),
                    was,
                    d.confidence,
                    s["label"].as_str().unwrap()
                );
                if details {
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
        println!("{file}: {:.1}% ({ok} of {n}) {confusion:?}", 100.0 * ok as f64 / n as f64);
        total += n;
        right += ok;
    }
    println!("all: {:.1}% ({right} of {total})", 100.0 * right as f64 / total.max(1) as f64);
    Ok(())
}
