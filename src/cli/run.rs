//! `flownav run --camera /dev/videoN|frames:DIR --base fnp:PORT|kobuki:PORT [--map FILE --mission
//! FROM:TO] [--log DIR | --no-log] [--log-split-mb MB] [--live [ADDR]] [--duration S] [--loop]`:
//! drives a robot.
//!
//! Opens the pieces in an order that never leaves a base running unattended: the pipeline
//! (config, calibration, map), the camera and the live view first, then the base, then the log; any failure
//! after the base is open drops it, and dropping a driver sends STOP. Then hands everything to
//! [`crate::runtime::run`] with a shutdown future that completes on Ctrl-C, SIGTERM or after
//! `--duration`. At the end it prints one JSON line (the [`RunReport`]) to stdout; the latency
//! figure is also logged. See docs/deploy.md.

use super::Common;
use crate::config::Config;
use crate::logging::live::{self, LiveServer};
use crate::logging::record::{add_map, run_options};
use crate::logging::{LiveImages, LiveSink, LogWriter};
use crate::pafsis::{Mission, TopoMap};
use crate::runtime::config::{BaseKind, BaseSpec};
use crate::runtime::reopen::ReopeningCamera;
use crate::runtime::{RunReport, RuntimeOptions};
use crate::sources::{CameraSpec, open_camera};
use crate::step::Pipeline;
use anyhow::{Context, bail};
use clap::Args as ClapArgs;
use hal::camera::monotonic_ns;
use hal::fnp_driver::{FnpBase, FnpConfig};
use hal::kobuki::{KobukiBase, KobukiConfig};
use hal::{Calibration, Camera, MotorBase};
use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

#[derive(Debug, Clone, ClapArgs)]
pub struct Args {
    /// The camera: a V4L2 device (`/dev/video0`) or a frame folder played as a camera
    /// (`frames:DIR`). Default: `[camera] device` from the config.
    #[arg(long, value_name = "SPEC")]
    pub camera: Option<CameraSpec>,
    /// The motor base: `fnp:PORT` (FNP/1) or `kobuki:PORT` (TurtleBot 2). Default: `[base] kind`
    /// and `port` from the config.
    #[arg(long, value_name = "KIND:PORT")]
    pub base: Option<BaseSpec>,
    /// Topological map for PAFSIS (with --mission); without one the robot cruises ahead, avoiding.
    #[arg(long, value_name = "FILE", requires = "mission")]
    pub map: Option<PathBuf>,
    /// Mission on the map, `FROM:TO` place names.
    #[arg(long, value_name = "FROM:TO", requires = "map")]
    pub mission: Option<String>,
    /// Write the MCAP log under this folder (default: `[run] log_dir`, `logs/`).
    #[arg(long, value_name = "DIR")]
    pub log: Option<PathBuf>,
    /// Do not write a log.
    #[arg(long, conflicts_with_all = ["log", "log_split_mb"])]
    pub no_log: bool,
    /// Split the log into parts of this many MB.
    #[arg(long, value_name = "MB")]
    pub log_split_mb: Option<f64>,
    /// Stop the robot and end the run after this many seconds.
    #[arg(long, value_name = "S")]
    pub duration: Option<f64>,
    /// Play the `frames:DIR` folder over and over (stamps keep increasing) instead of ending the
    /// run after its last frame; for soak tests. End the run with --duration or Ctrl-C.
    #[arg(long = "loop")]
    pub loop_frames: bool,
    /// Serve the logged topics live to Foxglove (WebSocket) on IP:PORT; without a value
    /// 127.0.0.1:8765 (this machine only; 0.0.0.0:8765 to watch from another computer).
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = live::DEFAULT_ADDR,
          value_parser = live::parse_addr)]
    pub live: Option<std::net::SocketAddr>,
}

pub fn run(args: Args, common: &Common) -> anyhow::Result<()> {
    let cfg = common.config()?;
    if let Some(d) = args.duration
        && !(d.is_finite() && d > 0.0 && Duration::try_from_secs_f64(d).is_ok())
    {
        bail!("--duration {d}: must be a positive number of seconds");
    }
    if let Some(mb) = args.log_split_mb
        && !(mb.is_finite() && mb > 0.0)
    {
        bail!("--log-split-mb {mb}: must be a positive number of MB");
    }
    let camera_spec = args.camera.clone().unwrap_or_else(|| CameraSpec::from_config(&cfg.camera));
    let base_spec = args.base.clone().unwrap_or_else(|| BaseSpec::from_config(&cfg.base));
    if args.loop_frames && !matches!(camera_spec, CameraSpec::Frames(_)) {
        bail!("--loop plays a frame folder over and over: it needs --camera frames:DIR (the camera is {camera_spec})");
    }
    let looping = args.loop_frames;

    let calib = common.calibration()?;
    let mission = match (&args.map, &args.mission) {
        (Some(map_path), Some(mission)) => {
            let map = TopoMap::load(map_path).with_context(|| format!("loading the map {}", map_path.display()))?;
            let m: Mission = mission.parse().with_context(|| format!("--mission {mission}"))?;
            Some((map, m))
        }
        _ => None,
    };
    let map_for_log = mission.as_ref().map(|(map, _)| map.clone());
    let pipeline = Pipeline::new(&cfg, calib.clone(), mission).context("building the pipeline")?;
    let backend = pipeline.backend();
    tracing::info!("flow backend {}: {}", backend.engine, backend.reason);

    // The source errors name the camera and the fix; their text already includes their causes.
    let camera = open_camera(&camera_spec, &cfg.camera, looping)
        .map_err(|e| anyhow::anyhow!("opening the camera {camera_spec}: {e}"))?;
    let reopen = {
        let (spec, cam_cfg) = (camera_spec.clone(), cfg.camera.clone());
        move || open_camera(&spec, &cam_cfg, looping)
    };
    let camera = ReopeningCamera::new(camera, reopen);
    warn_if_stall_too_short(&cfg, &camera_spec);
    // Before the base: a live view that cannot start refuses the run while nothing moves.
    // An MJPEG camera's frames are logged as the JPEG bytes it sent; others as mono8.
    let images = match (&camera_spec, cfg.camera.format) {
        (CameraSpec::Device(_), hal::v4l2::PixelFormat::Mjpeg) => LiveImages::Jpeg,
        _ => LiveImages::Mono8,
    };
    let live = args.live.map(|addr| start_live(addr, images)).transpose()?;

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    let logging =
        LogSetup { cfg: &cfg, calib: &calib, args: &args, map: map_for_log, live: live.as_ref().map(LiveServer::sink) };
    let mut report = rt.block_on(async {
        match base_spec.kind {
            BaseKind::Fnp => {
                let fnp = FnpConfig {
                    baud: cfg.base.baud,
                    setpoint_rate_hz: cfg.base.setpoint_rate_hz,
                    watchdog_ms: cfg.base.watchdog_ms,
                    ..FnpConfig::new(base_spec.port.clone())
                };
                let base =
                    FnpBase::connect(fnp).await.with_context(|| format!("connecting to the base {base_spec}"))?;
                drive(camera, base, pipeline, &cfg, logging, args.duration).await
            }
            BaseKind::Kobuki => {
                let kobuki = KobukiConfig {
                    baud: cfg.base.baud,
                    command_rate_hz: cfg.base.setpoint_rate_hz,
                    ..KobukiConfig::new(base_spec.port.clone())
                };
                let base =
                    KobukiBase::connect(kobuki).await.with_context(|| format!("connecting to the base {base_spec}"))?;
                drive(camera, base, pipeline, &cfg, logging, args.duration).await
            }
        }
    })?;
    if let Some(server) = live {
        let stats = server.close();
        tracing::info!(sent = stats.sent, dropped = stats.dropped, clients = stats.clients, "live view closed");
        report.live = Some(stats);
    }
    let mut out = std::io::stdout().lock();
    writeln!(out, "{}", serde_json::to_string(&report).context("serialising the run report")?)?;
    out.flush()?;
    Ok(())
}

/// What the log needs besides the run itself.
struct LogSetup<'a> {
    cfg: &'a Config,
    calib: &'a Calibration,
    args: &'a Args,
    map: Option<TopoMap>,
    live: Option<LiveSink>,
}

impl LogSetup<'_> {
    fn open(self) -> anyhow::Result<Option<LogWriter>> {
        if self.args.no_log || (!self.cfg.run.log && self.args.log.is_none()) {
            // No file; with --live the logger still encodes for the viewer.
            let Some(live) = self.live else { return Ok(None) };
            let mut options = run_options("run", self.cfg, self.calib, self.args.mission.as_deref(), None);
            options.time_offset_ns = crate::logging::wall_clock_offset_ns(monotonic_ns());
            options.live = Some(live);
            let log = LogWriter::live_only(options).context("starting the live view's encoder")?;
            log.handle().calibration(monotonic_ns(), self.calib);
            return Ok(Some(log));
        }
        let dir = self.args.log.clone().unwrap_or_else(|| self.cfg.run.log_dir.clone());
        let split_mb = self.args.log_split_mb.or(self.cfg.run.log_split_mb.map(|mb| mb as f64));
        let mut options = run_options("run", self.cfg, self.calib, self.args.mission.as_deref(), split_mb);
        if let Some(map) = &self.map {
            add_map(&mut options, map);
        }
        options.time_offset_ns = crate::logging::wall_clock_offset_ns(monotonic_ns());
        options.live = self.live;
        std::fs::create_dir_all(&dir).with_context(|| format!("creating the log folder {}", dir.display()))?;
        let log = LogWriter::create(&dir, options).with_context(|| format!("opening a log in {}", dir.display()))?;
        log.handle().calibration(monotonic_ns(), self.calib);
        tracing::info!(path = %log.path().display(), "logging the run");
        Ok(Some(log))
    }
}

/// Runs with an open base; the base is stopped (dropped) on every path out of here.
async fn drive<C, B>(
    camera: C,
    base: B,
    pipeline: Pipeline,
    cfg: &Config,
    logging: LogSetup<'_>,
    duration: Option<f64>,
) -> anyhow::Result<RunReport>
where
    C: Camera + 'static,
    B: MotorBase + 'static,
{
    let log = logging.open()?;
    let handle = log.as_ref().map(LogWriter::handle);
    let shutdown = shutdown_signal(duration.and_then(|d| Duration::try_from_secs_f64(d).ok()))?;
    let result = crate::runtime::run(camera, base, pipeline, handle, shutdown, RuntimeOptions::from_config(cfg)).await;
    if let Some(log) = log {
        let path = log.path().to_path_buf();
        match log.close() {
            // The live view's encoder (--no-log --live): no file to report.
            Ok(_) if path.as_os_str().is_empty() => {}
            Ok(summary) => tracing::info!(path = %path.display(), stats = ?summary.stats, "log closed"),
            Err(e) => tracing::error!(path = %path.display(), "the log could not be finished: {e}"),
        }
    }
    Ok(result?)
}

/// Starts the live view and says where to connect (stderr, one line: `live view on ws://ADDR`).
fn start_live(addr: std::net::SocketAddr, images: LiveImages) -> anyhow::Result<LiveServer> {
    let server = LiveServer::start(addr, images)?;
    eprintln!("live view on {} (Foxglove: Open connection, Foxglove WebSocket)", server.url());
    Ok(server)
}

/// Completes on Ctrl-C, SIGTERM, or after `duration`.
fn shutdown_signal(duration: Option<Duration>) -> anyhow::Result<impl Future<Output = ()>> {
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .context("installing the SIGTERM handler")?;
    Ok(async move {
        let timer = async {
            match duration {
                Some(d) => tokio::time::sleep(d).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            r = tokio::signal::ctrl_c() => {
                if let Err(e) = r {
                    tracing::error!("cannot wait for Ctrl-C: {e}; stopping");
                } else {
                    tracing::info!("Ctrl-C");
                }
            }
            _ = term.recv() => tracing::info!("SIGTERM"),
            () = timer => tracing::info!("--duration reached"),
        }
    })
}

/// A set-point expires `[run] stall_ms` after its frame: frames must come faster than that.
fn warn_if_stall_too_short(cfg: &Config, spec: &CameraSpec) {
    if let CameraSpec::Device(_) = spec {
        let period_ms = 1000.0 / cfg.camera.fps;
        if (cfg.run.stall_ms as f64) < 2.0 * period_ms {
            tracing::warn!(
                "run.stall_ms = {} is less than two frame periods at {} fps ({:.0} ms): one late frame will stop the robot",
                cfg.run.stall_ms,
                cfg.camera.fps,
                2.0 * period_ms
            );
        }
    }
}
