//! The `flownav` command line (clap derive). Each subcommand lives in its own module and
//! exposes `Args` and `run(args, &Common)`.
//! `render`, `sim`, `sim-base` and `bench-offis` need the simulator (feature `sim`).

use crate::config::Config;
use crate::flow::Backend;
use anyhow::Context;
use clap::{Args, Parser, Subcommand};
use hal::Calibration;
use std::fmt::Debug;
use std::ops::RangeBounds;
use std::path::PathBuf;

pub use output::init_tracing;

pub mod analyze;
#[cfg(feature = "sim")]
pub mod bench_offis;
pub mod calib;
pub mod devices;
pub mod flow;
pub mod log;
pub mod output;
#[cfg(feature = "sim")]
pub mod render;
pub mod replay;
pub mod run;
#[cfg(feature = "sim")]
pub mod sim;
#[cfg(feature = "sim")]
pub mod sim_base;

/// Exit status of a `sim` with a run that did not reach its goal or touched something.
pub const EXIT_MISSION_FAILED: u8 = 3;
/// Exit status of `replay --check` when the results differ from the log.
pub const EXIT_MISMATCH: u8 = 1;
/// Exit status when an input cannot be read (as for usage errors, which clap exits with 2).
pub const EXIT_UNREADABLE: u8 = 2;

/// An error that ends the program with its own exit status (README, "Exit codes"); any other
/// error exits 1.
#[derive(Debug, thiserror::Error)]
#[error("{message}")]
pub struct Exit {
    pub code: u8,
    pub message: String,
}

/// The exit status for an error out of [`run`](fn@run).
pub fn exit_code(err: &anyhow::Error) -> u8 {
    err.downcast_ref::<Exit>().map_or(1, |e| e.code)
}

#[derive(Debug, Parser)]
#[command(name = "flownav", version, about = "Optical-flow navigation for indoor robots with one webcam", long_about = None)]
pub struct Cli {
    #[command(flatten)]
    pub common: Common,
    /// More log output (-v debug, -vv trace); RUST_LOG overrides.
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    pub verbose: u8,
    #[command(subcommand)]
    pub command: Command,
}

/// Flags shared by every command that sees frames.
#[derive(Debug, Clone, Args)]
pub struct Common {
    /// TOML configuration file; flags given on the command line override it.
    #[arg(long, global = true, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Camera calibration file (flownav TOML; `calib import` converts OpenCV/ROS files).
    /// Without it: the built-in nominal C310 (`calib/c310.toml`), from any folder.
    #[arg(long, global = true, value_name = "FILE")]
    pub calib: Option<PathBuf>,
    /// Optical-flow backend (overrides `flow.backend`).
    #[arg(long, global = true, value_enum, value_name = "BACKEND")]
    pub flow_backend: Option<Backend>,
}

impl Common {
    /// The configuration: the file when given (validated), else defaults; then the flags.
    pub fn config(&self) -> anyhow::Result<Config> {
        let mut cfg = match &self.config {
            Some(path) => Config::load(path)?,
            None => Config::default(),
        };
        if let Some(b) = self.flow_backend {
            cfg.flow.backend = b;
        }
        cfg.validate().context("after applying command-line flags")?;
        Ok(cfg)
    }

    /// The `--calib` file, else the built-in nominal C310 calibration.
    pub fn calibration(&self) -> anyhow::Result<Calibration> {
        match &self.calib {
            Some(path) => {
                Calibration::load(path).with_context(|| format!("loading the calibration {} (--calib)", path.display()))
            }
            None => Ok(Calibration::nominal_c310()),
        }
    }
}

/// A `--size WxH` flag: width and height, each a whole number of pixels within `sides`.
pub fn parse_size(s: &str, sides: impl RangeBounds<u32> + Debug) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| format!("size {s:?} must be WxH, e.g. 640x360"))?;
    let p = |v: &str| v.trim().parse::<u32>().ok().filter(|n| sides.contains(n));
    match (p(w), p(h)) {
        (Some(w), Some(h)) => Ok((w, h)),
        _ => Err(format!("size {s:?}: width and height must be whole numbers of pixels in {sides:?}")),
    }
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Block optical flow between two images (DESIGN.md output contract with --json).
    Flow(flow::Args),
    #[cfg(feature = "sim")]
    /// Render views of a simulated world: one PNG for a pose, or a labelled frame folder for a trajectory.
    Render(render::Args),
    /// List V4L2 cameras with their formats, sizes and frame rates.
    Devices(devices::Args),
    /// Camera calibrations: import OpenCV/ROS files (`calib import`), show one (`calib show`).
    Calib(calib::Args),
    /// Inspect MCAP run logs (`log info LOG`).
    Log(log::Args),
    /// Drive a robot: camera → optical flow → OFFIS/PAFSIS/MOFIS → serial motor base (docs/deploy.md).
    Run(run::Args),
    #[cfg(feature = "sim")]
    /// Serve a simulated motor base on a pseudo-terminal; prints its path (/dev/pts/N) first.
    SimBase(sim_base::Args),
    /// Re-run the pipeline on a run log's frames and odometry; --check compares with the logged outputs.
    Replay(replay::Args),
    #[cfg(feature = "sim")]
    /// Closed loop in a simulated world: rendered camera, the pipeline, a simulated base over a pty; ends with a JSON summary.
    Sim(sim::Args),
    /// Run OFFIS over a frame folder: one JSON line per frame pair (perception and set-point).
    Analyze(analyze::Args),
    #[cfg(feature = "sim")]
    /// OFFIS accuracy on a labelled simulated scene set: confusion matrix, obstacle errors.
    BenchOffis(bench_offis::Args),
}

/// Runs one parsed command line.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Flow(args) => flow::run(args, &cli.common),
        #[cfg(feature = "sim")]
        Command::Render(args) => render::run(args, &cli.common),
        Command::Devices(args) => devices::run(args, &cli.common),
        Command::Calib(args) => calib::run(args, &cli.common),
        Command::Log(args) => log::run(args, &cli.common),
        #[cfg(feature = "sim")]
        Command::SimBase(args) => sim_base::run(args, &cli.common),
        Command::Run(args) => run::run(args, &cli.common),
        Command::Replay(args) => replay::run(args, &cli.common),
        #[cfg(feature = "sim")]
        Command::Sim(args) => sim::run(args, &cli.common),
        Command::Analyze(args) => analyze::run(args, &cli.common),
        #[cfg(feature = "sim")]
        Command::BenchOffis(args) => bench_offis::run(args, &cli.common),
    }
}
