//! `flownav log`: inspect MCAP run logs.
//!
//! - `flownav log info LOG`: topics with schema, counts, first/last time, duration, drops, and
//!   whether the file was closed cleanly (a crashed run's file says how much was recovered).
//! - `flownav log sample OUT` (hidden): writes a synthetic log with every topic, for CI's
//!   independent check with the Python `mcap` package (`bench/check_mcap.py`).

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args as ClapArgs, Subcommand, ValueEnum};

use super::Common;
use crate::logging::sample::{self, SampleImages};
use crate::logging::{LogInfo, LogOptions};

#[derive(Debug, ClapArgs)]
pub struct Args {
    #[command(subcommand)]
    pub command: LogCommand,
}

#[derive(Debug, Subcommand)]
pub enum LogCommand {
    /// Topics, message counts, time span, drops and truncation status of a log.
    Info {
        /// The MCAP file (`logs/flownav-*.mcap`).
        log: PathBuf,
        /// Print the numbers as one JSON object instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Write a synthetic log with every topic (for checks with other MCAP readers).
    #[command(hide = true)]
    Sample {
        /// Output file; never overwritten.
        out: PathBuf,
        /// Number of frames (30 fps).
        #[arg(long, default_value_t = 90)]
        frames: u64,
        /// How frames are stored.
        #[arg(long, value_enum, default_value_t = Images::Mono8)]
        images: Images,
        /// Split into files of this many MB.
        #[arg(long, value_name = "MB")]
        log_split_mb: Option<f64>,
    },
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum Images {
    Mono8,
    Jpeg,
}

pub fn run(args: Args, _common: &Common) -> anyhow::Result<()> {
    match args.command {
        LogCommand::Info { log, json } => {
            let info = LogInfo::read(&log)?;
            let text = if json { format!("{}\n", info_json(&info)) } else { info.render() };
            print_stdout(&text)
        }
        LogCommand::Sample { out, frames, images, log_split_mb } => {
            let images = match images {
                Images::Mono8 => SampleImages::Mono8,
                Images::Jpeg => SampleImages::Jpeg,
            };
            let mut options = LogOptions::new("sample");
            if let Some(mb) = log_split_mb {
                options = options.split_mb(mb);
            }
            let summary = sample::write_sample(&out, frames, images, options)?;
            let files: String = summary.files.iter().map(|f| format!("{}\n", f.display())).collect();
            print_stdout(&files)
        }
    }
}

/// Prints to stdout; a closed pipe (`| head`) ends the output quietly.
fn print_stdout(text: &str) -> anyhow::Result<()> {
    use std::io::Write;
    match std::io::stdout().lock().write_all(text.as_bytes()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e).context("writing to stdout"),
        _ => Ok(()),
    }
}

fn info_json(info: &LogInfo) -> serde_json::Value {
    let topics: Vec<_> = info
        .topics
        .iter()
        .map(|t| {
            serde_json::json!({"topic": t.topic, "schema": t.schema, "encoding": t.encoding, "count": t.count,
                "first_ns": t.first_ns, "last_ns": t.last_ns, "out_of_order": t.out_of_order})
        })
        .collect();
    serde_json::json!({
        "path": info.path, "bytes": info.bytes, "complete": info.complete, "truncation": info.truncation,
        "messages": info.messages, "first_ns": info.first_ns, "last_ns": info.last_ns,
        "duration_s": info.duration_s(), "stats": info.stats, "stats_final": info.stats_final,
        "header": info.header, "topics": topics,
    })
}
