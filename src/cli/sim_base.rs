//! `flownav sim-base`: a simulated motor base on a pseudo-terminal, for developing host or
//! firmware code without hardware. Prints the pty path (`/dev/pts/N`) as the first line of
//! stdout, then serves FNP/1 (or, with `--kobuki`, the Kobuki protocol) until Ctrl-C/SIGTERM.
//! `--alarm KIND@START+FOR` raises one of the base's alarms on its own clock (see docs/sim.md).
//! When it stops, an FNP/1 base prints one JSON line: the faults it injected, what its decoder
//! counted, and its fault → stop gaps (docs/serial.md).

use super::Common;
use anyhow::Context;
use clap::Args as ClapArgs;
use mocks::OdometryError;
use mocks::faults::{AlarmWindow, FaultConfig, FaultStats};
use mocks::sim_base::{
    LinkFaultStats, ServeOptions, SimBase, SimBaseConfig, SimBaseCounters, SimClock, SimDevice, SimServer,
};
use mocks::sim_kobuki::{SimKobuki, SimKobukiConfig};
use mocks::stop_gaps::StopGapSummary;
use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

#[derive(Debug, Clone, ClapArgs)]
pub struct Args {
    /// Baud rate a driver should use. A pty has no line rate, so this only documents the
    /// setting; the simulated base accepts any.
    #[arg(long, default_value_t = 115_200)]
    pub baud: u32,
    /// The base's watchdog until a HELLO sets it, ms (FNP/1).
    #[arg(long, default_value_t = 250, value_parser = clap::value_parser!(u16).range(1..))]
    pub watchdog_ms: u16,
    /// Link faults, e.g. "drop=0.01,corrupt=0.005,delay=0.05:20ms,disconnect=0.02:1s,seed=7".
    #[arg(long, value_name = "SPEC", default_value = "")]
    pub faults: FaultConfig,
    /// Raise one of the base's alarms, KIND@START+FOR in seconds since the base started, e.g.
    /// `estop@2+1.5`; KIND: bumper, estop, cliff, wheel-drop, motor-fault. Repeatable.
    #[arg(long, value_name = "KIND@START+FOR")]
    pub alarm: Vec<AlarmWindow>,
    /// Simulate a Kobuki (TurtleBot 2) instead of an FNP/1 base.
    #[arg(long)]
    pub kobuki: bool,
    /// Keep a symlink here pointing at the current pty (it changes after a simulated disconnect).
    #[arg(long, value_name = "PATH")]
    pub link: Option<PathBuf>,
    /// Seed of the encoder noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// How the simulated wheels differ from the nominal ones the firmware reports with:
    /// `left=F,right=F,wheelbase=F,noise=F,slip=F` (any subset) or `none` (docs/sim.md).
    #[arg(long, value_name = "SPEC", default_value_t = OdometryError::UNCALIBRATED)]
    pub odometry_error: OdometryError,
}

pub fn run(args: Args, _common: &Common) -> anyhow::Result<()> {
    let rt =
        tokio::runtime::Builder::new_current_thread().enable_all().build().context("starting the tokio runtime")?;
    rt.block_on(serve(args))
}

async fn serve(args: Args) -> anyhow::Result<()> {
    let opts = ServeOptions {
        clock: SimClock::RealTime { tick: Duration::from_millis(2) },
        faults: args.faults.clone(),
        link: args.link.clone(),
    };
    if args.kobuki {
        let mut cfg = SimKobukiConfig { alarms: args.alarm.clone(), ..Default::default() };
        cfg.check_alarms().map_err(anyhow::Error::msg)?;
        cfg.drive.seed = args.seed;
        cfg.drive.error = args.odometry_error;
        let server = SimServer::start(SimKobuki::new(cfg), opts).context("opening a pseudo-terminal")?;
        announce(&server, &args)?;
        wait_for_signal().await?;
        let (commands, feedback) = server.with_device(|k| (k.commands, k.feedback_sent));
        tracing::info!(commands, feedback, faults = ?server.fault_stats(), pose = ?server.pose(), "simulated Kobuki stopped");
    } else {
        let mut cfg = SimBaseConfig { watchdog_ms: args.watchdog_ms, alarms: args.alarm.clone(), ..Default::default() };
        cfg.check_alarms().map_err(anyhow::Error::msg)?;
        cfg.drive.seed = args.seed;
        cfg.drive.error = args.odometry_error;
        let server = SimServer::start(SimBase::new(cfg), opts).context("opening a pseudo-terminal")?;
        announce(&server, &args)?;
        wait_for_signal().await?;
        let (counters, gaps, time_s) = server.with_device(|b| (b.counters(), b.stop_gaps().summary(), b.time_s()));
        let faults = server.fault_stats();
        tracing::info!(?counters, ?faults, pose = ?server.pose(), "simulated FNP/1 base stopped");
        let summary = fnp_summary(time_s, &counters, &faults, &gaps);
        let mut out = std::io::stdout().lock();
        writeln!(out, "{summary}")?;
        out.flush()?;
    }
    Ok(())
}

/// The JSON line an FNP/1 base prints when it stops.
fn fnp_summary(
    time_s: f64,
    counters: &SimBaseCounters,
    faults: &LinkFaultStats,
    gaps: &StopGapSummary,
) -> serde_json::Value {
    let direction = |f: &FaultStats| {
        serde_json::json!({
            "bytes_dropped": f.bytes_dropped,
            "bytes_corrupted": f.bytes_corrupted,
            "chunks_delayed": f.chunks_delayed,
            "frames_hit": f.frames_hit,
            "frames_hit_unseen": f.frames_hit_unseen,
        })
    };
    serde_json::json!({
        "time_s": time_s,
        "faults": {
            "to_host": direction(&faults.to_host),
            "to_base": direction(&faults.to_device),
            "disconnects": faults.disconnects,
            "unread_dropped_bytes": faults.unread_dropped,
        },
        "base": {
            "setpoints": counters.setpoints,
            "stops": counters.stops,
            "hellos": counters.hellos,
            "watchdog_trips": counters.watchdog_trips,
            "frames_dropped": counters.decode.dropped(),
            "frames_lost": counters.decode.lost,
        },
        "stop_gaps": gaps,
    })
}

fn announce<D: SimDevice>(server: &SimServer<D>, args: &Args) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    writeln!(out, "{}", server.pty_path().display())?;
    out.flush()?;
    let protocol = if args.kobuki { "Kobuki" } else { "FNP/1" };
    tracing::info!(port = %server.port_path().display(), baud = args.baud, protocol, "serving a simulated base; Ctrl-C to stop");
    Ok(())
}

async fn wait_for_signal() -> anyhow::Result<()> {
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .context("installing the SIGTERM handler")?;
    tokio::select! {
        r = tokio::signal::ctrl_c() => r.context("waiting for Ctrl-C")?,
        _ = term.recv() => {}
    }
    Ok(())
}
