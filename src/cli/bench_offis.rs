//! `flownav bench-offis`: the OFFIS accuracy benchmark on a labelled scene set rendered by the
//! simulator (see `flownav::sim::bench` and docs/offis.md). Prints the confusion matrix and
//! the error figures, or the whole report as one JSON object with `--json`; with
//! `--classifier both`, the flownav and the paper classifier on the same rendered frames, side
//! by side.

use super::Common;
use crate::offis::ClassifierKind;
use crate::sim::bench::{self, BenchOptions, Report};
use anyhow::bail;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Number of scenes (they cycle wall, corner, door, corridor, none).
    #[arg(long, default_value_t = 200)]
    pub scenes: usize,
    /// Seed of the scene set (docs/results.md says which seeds tuned the rules and which report).
    #[arg(long, default_value_t = 2)]
    pub seed: u64,
    /// Render at this size instead of the calibration's (`WxH`, intrinsics scaled).
    #[arg(long, value_name = "WxH", value_parser = |s: &str| super::parse_size(s, 64..))]
    pub size: Option<(u32, u32)>,
    /// Sensor noise, standard deviation in grey levels.
    #[arg(long, default_value_t = 2.0)]
    pub noise: f64,
    /// Forward speed of the camera while it drives through each scene's frames, m/s.
    #[arg(long, default_value_t = 0.3)]
    pub velocity: f64,
    /// Turning scenes: each scene's turn rate is drawn from ±this, rad/s, while the camera
    /// drives through it (0: straight ahead).
    #[arg(long, default_value_t = 0.0, value_name = "RAD_S")]
    pub omega_max: f64,
    /// Which classifier decides (`offis.classifier`): paper, flownav, or both on the same
    /// frames, side by side (default: the config's, flownav unless set).
    #[arg(long, value_parser = ["paper", "flownav", "both"])]
    pub classifier: Option<String>,
    /// Print one line per scene (truth, prediction, obstacle) to stderr while running.
    #[arg(long)]
    pub verbose_scenes: bool,
    /// Print the report (with every scene) as one JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args, common: &Common) -> anyhow::Result<()> {
    if !(args.noise.is_finite() && args.noise >= 0.0) {
        bail!("--noise {} must be zero or a positive number of grey levels", args.noise);
    }
    let cfg = common.config()?;
    let calib = common.calibration()?;
    let calib = match args.size {
        Some((w, h)) => calib.scaled_to(w, h),
        None => calib,
    };
    let opts = BenchOptions {
        scenes: args.scenes,
        seed: args.seed,
        noise: args.noise,
        velocity: args.velocity,
        omega_max: args.omega_max,
        ..Default::default()
    };
    let started = std::time::Instant::now();
    let kinds = match args.classifier.as_deref() {
        None => vec![cfg.offis.classifier],
        Some("both") => vec![ClassifierKind::Flownav, ClassifierKind::Paper],
        Some(k) => vec![k.parse().map_err(anyhow::Error::msg)?],
    };
    let cfgs: Vec<_> = kinds
        .iter()
        .map(|&k| {
            let mut c = cfg.clone();
            c.offis.classifier = k;
            c
        })
        .collect();
    let progress = super::output::bar((args.scenes * kinds.len()) as u64, "scenes");
    let mut correct = 0u64;
    let reports = bench::run_each(&cfgs, &calib, &opts, |i, k, s| {
        correct += (s.truth == s.predicted) as u64;
        progress.set_message(format!("{correct} classified right"));
        progress.inc(1);
        if args.verbose_scenes {
            let obstacle =
                |o: Option<(f64, f64)>| o.map_or("-".to_string(), |(d, b)| format!("{d:.2} m {:+.1}°", b.to_degrees()));
            let got = s.obstacle.map(|(d, b)| (d.unwrap_or(f64::NAN), b.unwrap_or(f64::NAN)));
            let line = format!(
                "{i:4} {:<7} {:<9} -> {:<9} {:.2} | obstacle {} -> {} | {}",
                kinds[k].name(),
                s.truth.name(),
                s.predicted.name(),
                s.confidence,
                obstacle(s.truth_obstacle),
                obstacle(got),
                s.label
            );
            super::output::eprintln_above(&progress, &line);
        }
    })?;
    progress.finish_and_clear();
    // the first report keeps the JSON contract; with both, the paper's report is its field `paper`
    #[derive(serde::Serialize)]
    struct Both<'a> {
        #[serde(flatten)]
        first: &'a Report,
        paper: &'a Report,
    }
    if args.json {
        let line = match &reports[..] {
            [first, paper] => serde_json::to_string(&Both { first, paper })?,
            one => serde_json::to_string(&one[0])?,
        };
        println!("{line}");
    } else {
        match &reports[..] {
            [first, paper] => print!("{}", bench::side_by_side(first, paper)),
            one => print!("{}", one[0].table()),
        }
        println!(
            "({:.1} s; command: flownav bench-offis --scenes {} --seed {}{}{}{})",
            started.elapsed().as_secs_f64(),
            args.scenes,
            args.seed,
            args.classifier.as_deref().map_or(String::new(), |k| format!(" --classifier {k}")),
            if args.omega_max > 0.0 { format!(" --omega-max {}", args.omega_max) } else { String::new() },
            args.size.map_or(String::new(), |(w, h)| format!(" --size {w}x{h}"))
        );
    }
    Ok(())
}
