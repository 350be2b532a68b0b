//! `flownav replay LOG... [--check] [--flow-backend B] [--quiet] [--json-summary]`: re-runs the
//! pipeline on a run log (one file, or the parts of a split log in order) and prints one JSON
//! line per logged step (the perception, goal and set-point, and how it compared with the log),
//! then a summary on stderr. With `--check` the command fails when a step that could be
//! reproduced differs from the log (exit status 1), and exits 2 when the log cannot be read.
//! See docs/logging.md, "Replay".

use std::io::Write;
use std::path::PathBuf;

use anyhow::Context;
use clap::Args as ClapArgs;
use serde_json::json;

use super::{Common, EXIT_MISMATCH, EXIT_UNREADABLE, Exit};
use crate::config::Config;
use crate::replay::{self, Check, ReplayOptions, ReplaySummary, StepRecord};

#[derive(Debug, ClapArgs)]
pub struct Args {
    /// The MCAP log (`logs/flownav-*.mcap`); the parts of a split log in order (`-p001`, `-p002`, ...).
    #[arg(required = true, value_name = "LOG")]
    pub logs: Vec<PathBuf>,
    /// Compare every reproducible step with the log (flow, perception, goal, set-point, bit for
    /// bit) and exit with an error on any difference.
    #[arg(long)]
    pub check: bool,
    /// No per-step lines, only the summary.
    #[arg(short, long)]
    pub quiet: bool,
    /// Print the summary as one JSON object on stdout (after the step lines) instead of text on stderr.
    #[arg(long)]
    pub json_summary: bool,
}

pub fn run(args: Args, common: &Common) -> anyhow::Result<()> {
    // The log carries its configuration and calibration; --config replaces the configuration
    // (what-if replays), --flow-backend picks the engine (default cpu, the bit-exact reference).
    let config = match &common.config {
        Some(path) => {
            Some(Config::load(path).map_err(|e| unreadable(format!("loading --config {}: {e:#}", path.display())))?)
        }
        None => None,
    };
    let options = ReplayOptions { backend: common.flow_backend, config };
    let stdout = std::io::stdout();
    let mut out = std::io::BufWriter::new(stdout.lock());
    let mut write_error: Option<std::io::Error> = None;
    let quiet = args.quiet;
    let progress = super::output::counter("steps");
    let mut mismatched = 0u64;
    let summary = replay::replay(&args.logs, &options, |record| {
        mismatched += matches!(record.check, replay::Check::Mismatch { .. }) as u64;
        progress.set_message(format!("{mismatched} mismatched"));
        progress.inc(1);
        if quiet || write_error.is_some() {
            return;
        }
        if let Err(e) = writeln!(out, "{}", step_line(record)) {
            write_error = Some(e);
        }
    })
    .map_err(|e| unreadable(format!("replaying {}: {e:#}", args.logs[0].display())))?;
    progress.finish_and_clear();
    match write_error {
        Some(e) if e.kind() == std::io::ErrorKind::BrokenPipe => return Ok(()),
        Some(e) => return Err(e).context("writing to stdout"),
        None => {}
    }
    if args.json_summary {
        let _ = writeln!(out, "{}", serde_json::to_string(&summary).unwrap_or_default());
    }
    let _ = out.flush();
    if !args.json_summary {
        eprint!("{}", render(&summary));
    }
    if args.check && !summary.passed() {
        let first = summary.first_mismatch.as_ref().map(|m| {
            let diffs: Vec<String> = m.diffs.iter().map(ToString::to_string).collect();
            format!("; first at seq {} (t {} ns): {}", m.seq, m.t_ns, diffs.join("; "))
        });
        let message = format!(
            "replay check failed: {} of {} checked steps differ from the log{}",
            summary.mismatched,
            summary.checked,
            first.unwrap_or_default()
        );
        return Err(Exit { code: EXIT_MISMATCH, message }.into());
    }
    if args.check && summary.checked == 0 {
        let message = format!("replay check failed: no step of the log could be checked ({} logged)", summary.steps);
        return Err(Exit { code: EXIT_MISMATCH, message }.into());
    }
    Ok(())
}

/// The log (or `--config`) cannot be read: exit status 2, apart from a mismatch.
fn unreadable(message: String) -> anyhow::Error {
    Exit { code: EXIT_UNREADABLE, message }.into()
}

/// One step as a JSON line: the fields of `flownav analyze` (seq, t, tpo, obstacle, rough, fine,
/// setpoint), the goal, and the comparison with the log.
fn step_line(r: &StepRecord) -> serde_json::Value {
    let mut line = json!({"seq": r.seq, "t": r.t_ns as f64 * 1e-9});
    if let Some(out) = r.output {
        let p = &out.perception;
        line["tpo"] = json!(p.tpo);
        line["obstacle"] = json!({
            "present": p.obstacle.present,
            "distance_m": p.obstacle.distance_m,
            "direction_deg": p.obstacle.bearing_rad.map(f64::to_degrees),
            "cell": p.obstacle.cell,
        });
        line["rough"] = json!(p.rough);
        line["fine"] = json!(p.fine);
        line["goal"] = json!({"v": out.goal.velocity, "angle_rad": out.goal.angle_rad, "status": out.goal.status});
        let sp = out.setpoint();
        line["setpoint"] = json!({"v": sp.v, "omega": sp.omega});
    }
    match r.check {
        Check::Match => line["check"] = json!("match"),
        Check::Mismatch { diffs } => {
            line["check"] = json!("mismatch");
            line["diffs"] = json!(diffs);
        }
        Check::Unchecked { reason } => {
            line["check"] = json!("unchecked");
            line["reason"] = json!(reason);
        }
    }
    if r.after_gap {
        line["after_gap"] = json!(true);
    }
    line
}

fn render(s: &ReplaySummary) -> String {
    let mut t = format!(
        "replay: {} frames, {} steps logged, flow backend {}, {:.2} ms per step\n",
        s.frames, s.steps, s.backend, s.ms_per_step
    );
    t += &format!("checked:   {} steps: {} identical, {} differ\n", s.checked, s.matched, s.mismatched);
    if let Some(m) = &s.first_mismatch {
        t += &format!("first mismatch: seq {} (t {} ns):\n", m.seq, m.t_ns);
        for d in &m.diffs {
            t += &format!("  {d}\n");
        }
    }
    if s.unchecked > 0 {
        t += &format!(
            "unchecked: {} steps (cannot check steps whose frame or previous frame was not logged; the logger reported {} dropped images)\n",
            s.unchecked, s.dropped_images
        );
        if let Some(first) = &s.first_unchecked {
            t += &format!("  first: {first}\n");
        }
        t += &format!(
            "after gap: {} steps compared with a possibly different state, {} differ (not counted as failures)\n",
            s.after_gap, s.after_gap_mismatched
        );
    }
    if s.fail_safes > 0 || s.seq_gaps > 0 {
        t += &format!("fail-safes: {}, frames skipped by the run (seq gaps): {}\n", s.fail_safes, s.seq_gaps);
    }
    if let Some(why) = &s.truncated {
        t += &format!("log cut short (crash?): {why}\n");
    }
    t
}
