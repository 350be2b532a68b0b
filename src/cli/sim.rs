//! `flownav sim`: the closed loop in the simulated world (see [`crate::sim`]). Prints progress
//! to stderr once per simulated second and ends with one JSON line on stdout:
//! `{"reached":true,"collisions":0,"time_s":..,"path_m":..,"min_clearance_m":..,...}`.
//! `--seeds A..B` runs one mission per seed and adds an aggregate line.

use super::Common;
use crate::logging::live::{self, LiveServer};
use crate::logging::record;
use crate::logging::{LiveImages, LiveSink, LogWriter};
use crate::pafsis::{Mission, TopoMap};
use crate::sim::{self, OFFICE_MAP_TOML, SimSetup, SimSummary};
use anyhow::Context;
use clap::Args as ClapArgs;
use hal::Calibration;
use mocks::{OdometryError, World};
use serde::Serialize;
use std::io::Write;
use std::path::PathBuf;

#[derive(Debug, Clone, ClapArgs)]
pub struct Args {
    /// World file (default: the built-in office, mocks/worlds/office.toml).
    #[arg(long, value_name = "FILE")]
    pub world: Option<PathBuf>,
    /// Topological map (default: the built-in maps/office.toml; needed with another world).
    #[arg(long, value_name = "FILE")]
    pub map: Option<PathBuf>,
    /// Mission FROM:TO (places of the map).
    #[arg(long, default_value = "R9:D2", value_name = "FROM:TO")]
    pub mission: String,
    /// Random obstacle placement (World::with_random_obstacles) and noise seed; without it the
    /// world file's own obstacles are used.
    #[arg(long, value_name = "N", conflicts_with = "seeds")]
    pub seed: Option<u64>,
    /// Run one mission per seed in A..B (B excluded) and print an aggregate line last.
    #[arg(long, value_name = "A..B", value_parser = parse_range)]
    pub seeds: Option<(u64, u64)>,
    /// With --seeds: run this many missions at a time (about one CPU core each). Every run is
    /// deterministic, so the summaries are those of one at a time, printed in seed order; only
    /// `wall_s` and `realtime_factor` depend on it.
    #[arg(long, default_value_t = 1, value_name = "N", requires = "seeds",
          value_parser = clap::value_parser!(u32).range(1..=256))]
    pub jobs: u32,
    /// Sensor noise, standard deviation in grey levels.
    #[arg(long, default_value_t = 2.0, value_name = "SIGMA")]
    pub noise: f64,
    /// Camera and control rate, frames per simulated second.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// Give up after this much simulated time, s.
    #[arg(long, default_value_t = 180.0, value_name = "S")]
    pub max_time: f64,
    /// Render size WxH (the calibration's intrinsics are scaled to it).
    #[arg(long, value_name = "WxH", value_parser = |s: &str| super::parse_size(s, 64..=4096), default_value = "640x360")]
    pub size: (u32, u32),
    /// Pace the loop to the wall clock (default: as fast as possible).
    #[arg(long)]
    pub realtime: bool,
    /// Directory for the MCAP log (default logs/; with --seeds, no log unless given).
    #[arg(long, value_name = "DIR", conflicts_with = "no_log")]
    pub log: Option<PathBuf>,
    /// Do not write a log.
    #[arg(long)]
    pub no_log: bool,
    /// No progress lines on stderr.
    #[arg(long, short)]
    pub quiet: bool,
    /// How the simulated base's true wheels differ from its firmware's nominal ones:
    /// `left=F,right=F,wheelbase=F,noise=F,slip=F` (fractions; any subset, the rest 0) or `none`.
    /// Default: an uncalibrated base (docs/sim.md says why these values).
    #[arg(long, value_name = "SPEC", default_value_t = OdometryError::UNCALIBRATED)]
    pub odometry_error: OdometryError,
    /// Put the true start pose off the mission's start place: DX,DY in metres (map frame) and
    /// DYAW in degrees. The navigation still believes it starts on the place.
    #[arg(long, value_name = "DX,DY,DYAW_DEG", value_parser = parse_start_error, allow_hyphen_values = true)]
    pub start_error: Option<mocks::Pose>,
    /// Raise one of the simulated base's alarms, KIND@START+FOR in simulated seconds, e.g.
    /// `estop@20+3` (bumper, estop, motor-fault; repeatable). Contacts press the bumper anyway.
    #[arg(long, value_name = "KIND@START+FOR")]
    pub alarm: Vec<mocks::faults::AlarmWindow>,
    /// Serve the logged topics live to Foxglove (WebSocket) on IP:PORT; without a value
    /// 127.0.0.1:8765. Paces the loop to the wall clock (as --realtime) so there is time to watch.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = live::DEFAULT_ADDR,
          value_parser = live::parse_addr, conflicts_with = "seeds")]
    pub live: Option<std::net::SocketAddr>,
}

/// `DX,DY,DYAW_DEG` → a pose offset (m, m, rad).
pub fn parse_start_error(s: &str) -> Result<mocks::Pose, String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [dx, dy, dyaw] = parts.as_slice() else {
        return Err(format!("start error {s:?} must be DX,DY,DYAW_DEG (metres, metres, degrees), e.g. 0.2,-0.1,5"));
    };
    let num = |name: &str, v: &str| -> Result<f64, String> {
        v.parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| format!("start error {name} {v:?} is not a number (DX,DY,DYAW_DEG, e.g. 0.2,-0.1,5)"))
    };
    let (dx, dy, dyaw) = (num("DX", dx)?, num("DY", dy)?, num("DYAW_DEG", dyaw)?);
    if dx.hypot(dy) > 5.0 || dyaw.abs() > 180.0 {
        return Err(format!("start error {s:?} is beyond 5 m or 180°; put the robot near its start place"));
    }
    Ok(mocks::Pose::new(dx, dy, dyaw.to_radians()))
}

fn parse_range(s: &str) -> Result<(u64, u64), String> {
    let bad = || format!("seed range {s:?} must be A..B with A < B, e.g. 0..20");
    let (a, b) = s.split_once("..").ok_or_else(bad)?;
    let (a, b) = (a.trim().parse::<u64>().map_err(|_| bad())?, b.trim().parse::<u64>().map_err(|_| bad())?);
    if a < b { Ok((a, b)) } else { Err(bad()) }
}

/// Aggregate of a `--seeds` run.
#[derive(Debug, Serialize)]
pub struct Aggregate {
    pub runs: usize,
    pub reached: usize,
    pub success_rate: f64,
    pub collisions: u64,
    pub runs_with_collisions: usize,
    pub mean_time_s: f64,
    pub max_time_s: f64,
    pub mean_path_m: f64,
    pub min_clearance_m: f64,
    pub mean_min_clearance_m: f64,
    pub mean_goal_error_m: f64,
    pub failsafe_stops: u64,
    pub wall_s: f64,
    pub realtime_factor: f64,
    pub failed_seeds: Vec<u64>,
    /// 95 % (Clopper–Pearson) intervals of the per-run rates of reaching the goal and of a run
    /// with a contact (`sim::stats`): what the counts above say about the next seeds.
    pub success_rate_ci95: [f64; 2],
    pub collision_run_rate_ci95: [f64; 2],
    /// Means over the runs of `points_range_ok`, `cells_ghost` and `obstacles_held`
    /// (`sim::quality`).
    pub mean_points_range_ok: Option<f64>,
    pub mean_cells_ghost: Option<f64>,
    pub mean_obstacles_held: Option<f64>,
}

impl Aggregate {
    pub fn of(runs: &[SimSummary]) -> Self {
        let n = runs.len().max(1) as f64;
        let sum = |f: fn(&SimSummary) -> f64| runs.iter().map(f).sum::<f64>();
        let sim_s = sum(|r| r.time_s);
        let wall_s = sum(|r| r.wall_s);
        let r3 = |x: f64| (x * 1000.0).round() / 1000.0;
        let ci95 = |k: usize| {
            let (lo, hi) = crate::sim::stats::clopper_pearson(k as u64, runs.len() as u64, 0.95);
            [r3(lo), r3(hi)]
        };
        let mean_of = |f: fn(&SimSummary) -> Option<f64>| {
            let v: Vec<f64> = runs.iter().filter_map(f).collect();
            (!v.is_empty()).then(|| r3(v.iter().sum::<f64>() / v.len() as f64))
        };
        Self {
            runs: runs.len(),
            reached: runs.iter().filter(|r| r.reached).count(),
            success_rate: r3(runs.iter().filter(|r| r.reached).count() as f64 / n),
            collisions: runs.iter().map(|r| r.collisions).sum(),
            runs_with_collisions: runs.iter().filter(|r| r.collisions > 0).count(),
            mean_time_s: r3(sim_s / n),
            max_time_s: runs.iter().map(|r| r.time_s).fold(0.0, f64::max),
            mean_path_m: r3(sum(|r| r.path_m) / n),
            min_clearance_m: runs.iter().map(|r| r.min_clearance_m).fold(f64::INFINITY, f64::min),
            mean_min_clearance_m: r3(sum(|r| r.min_clearance_m) / n),
            mean_goal_error_m: r3(sum(|r| r.goal_error_m) / n),
            failsafe_stops: runs.iter().map(|r| r.failsafe_stops).sum(),
            wall_s: r3(wall_s),
            realtime_factor: r3(sim_s / wall_s.max(1e-9)),
            failed_seeds: runs.iter().filter(|r| !r.reached || r.collisions > 0).map(|r| r.seed).collect(),
            success_rate_ci95: ci95(runs.iter().filter(|r| r.reached).count()),
            collision_run_rate_ci95: ci95(runs.iter().filter(|r| r.collisions > 0).count()),
            mean_points_range_ok: mean_of(|r| r.quality.points_range_ok),
            mean_cells_ghost: mean_of(|r| r.quality.cells_ghost),
            mean_obstacles_held: mean_of(|r| r.quality.obstacles_held),
        }
    }
}

pub fn run(args: Args, common: &Common) -> anyhow::Result<()> {
    let mut config = common.config()?;
    // With several runs at a time (`--jobs`) the parallelism is whole runs, one per core: each
    // run's flow stays on its own thread unless the config asks otherwise.
    if config.flow.cpu_threads == 0 && args.jobs > 1 {
        config.flow.cpu_threads = 1;
    }
    let calib = common.calibration()?.scaled_to(args.size.0, args.size.1);
    let world = match &args.world {
        Some(path) => World::load(path)?,
        None => World::office(),
    };
    let map = match (&args.map, &args.world) {
        (Some(path), _) => TopoMap::load(path)?,
        (None, None) => TopoMap::parse(OFFICE_MAP_TOML, "maps/office.toml (built in)")?,
        (None, Some(w)) => anyhow::bail!(
            "--world {} needs its topological map: pass --map FILE (the built-in map describes the built-in office only)",
            w.display()
        ),
    };
    let mission: Mission = args.mission.parse().with_context(|| format!("--mission {}", args.mission))?;
    let seeds: Vec<Option<u64>> = match (args.seeds, args.seed) {
        (Some((a, b)), _) => (a..b).map(Some).collect(),
        (None, s) => vec![s],
    };
    let log_dir = match (&args.log, args.no_log, args.seeds.is_some()) {
        (Some(dir), _, _) => Some(dir.clone()),
        (None, false, false) => Some(PathBuf::from("logs")),
        _ => None,
    };
    let live = match args.live {
        Some(addr) => {
            let server = LiveServer::start(addr, LiveImages::Mono8)?;
            eprintln!("live view on {} (Foxglove: Open connection, Foxglove WebSocket)", server.url());
            Some(server)
        }
        None => None,
    };
    // With --seeds on a terminal: "n of N runs [...] reached r, contacts c, ETA".
    let progress = match args.seeds {
        Some(_) => super::output::bar(seeds.len() as u64, "runs").with_message("reached 0, contacts 0"),
        None => indicatif::ProgressBar::hidden(),
    };
    let job = SeedJob {
        args: &args,
        world: &world,
        map: &map,
        mission: &mission,
        config: &config,
        calib: &calib,
        log_dir,
        live: live.as_ref().map(LiveServer::sink),
        progress: progress.clone(),
    };
    let results = run_missions(&job, &seeds, args.jobs as usize);
    if let Some(server) = live {
        let s = server.close();
        if !args.quiet {
            eprintln!("live view: {} messages sent, {} dropped, {} clients", s.sent, s.dropped, s.clients);
        }
    }
    let results = results?;
    progress.finish_and_clear();
    if args.seeds.is_some() {
        let agg = Aggregate::of(&results);
        let mut out = std::io::stdout().lock();
        writeln!(out, "{}", serde_json::to_string(&agg)?)?;
    }
    outcome(&results)
}

/// Exit status 3 when a run did not reach its goal or touched something (README, "Exit codes").
fn outcome(results: &[SimSummary]) -> anyhow::Result<()> {
    let failed: Vec<&SimSummary> = results.iter().filter(|r| !r.reached || r.collisions > 0).collect();
    if failed.is_empty() {
        return Ok(());
    }
    let seeds: Vec<String> = failed.iter().map(|r| r.seed.to_string()).collect();
    let message = format!(
        "{} of {} runs did not reach the goal or touched something (seeds {})",
        failed.len(),
        results.len(),
        seeds.join(", ")
    );
    Err(super::Exit { code: super::EXIT_MISSION_FAILED, message }.into())
}

/// The tokio runtime one mission runs on (the simulated base's pty and the pipeline).
fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the tokio runtime")
}

fn print_summary(summary: &SimSummary) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    writeln!(out, "{}", summary.to_json_line())?;
    out.flush()?;
    Ok(())
}

/// What every mission of a `flownav sim` call shares.
struct SeedJob<'a> {
    args: &'a Args,
    world: &'a World,
    map: &'a TopoMap,
    mission: &'a Mission,
    config: &'a crate::config::Config,
    calib: &'a Calibration,
    log_dir: Option<PathBuf>,
    live: Option<LiveSink>,
    progress: indicatif::ProgressBar,
}

impl SeedJob<'_> {
    /// A line on stderr, above the progress bar.
    fn say(&self, line: String) {
        super::output::eprintln_above(&self.progress, &line);
    }

    /// One mission: the world for `seed`, the run, its log; progress lines on stderr start with
    /// `tag`.
    fn run(&self, rt: &tokio::runtime::Runtime, seed: Option<u64>, tag: &str) -> anyhow::Result<SimSummary> {
        let args = self.args;
        let world = match seed {
            Some(s) if self.world.random.is_some() => {
                self.world.with_random_obstacles(s).with_context(|| format!("placing random obstacles for seed {s}"))?
            }
            Some(_) => {
                tracing::warn!("the world has no [random] section: --seed only seeds the noise");
                self.world.clone()
            }
            None => self.world.clone(),
        };
        let mut setup =
            SimSetup::new(world, self.map.clone(), self.mission.clone(), self.config.clone(), self.calib.clone());
        setup.fps = args.fps;
        setup.noise_sigma = args.noise;
        setup.seed = seed.unwrap_or(0);
        setup.max_time_s = args.max_time;
        // Watching live needs the simulated clock to run at the wall clock's pace.
        setup.realtime = args.realtime || self.live.is_some();
        setup.odometry_error = args.odometry_error;
        setup.alarms = args.alarm.clone();
        if let Some(e) = args.start_error {
            setup.start_error = e;
        }
        if !args.quiet {
            let start = setup.true_start_pose()?;
            self.say(format!(
                "{tag}flownav sim: mission {} on world {:?} (seed {}), {}x{} at {} fps, start ({:.2}, {:.2}, {:.0}°)",
                setup.mission,
                setup.world.name,
                seed.map_or("none (the file's obstacles)".to_string(), |s| s.to_string()),
                args.size.0,
                args.size.1,
                args.fps,
                start.x,
                start.y,
                start.yaw.to_degrees()
            ));
            let nav =
                crate::pafsis::Pafsis::new(setup.map.clone(), setup.mission.clone(), setup.config.pafsis.clone())?;
            let legs: Vec<String> = nav.legs().iter().map(|l| l.to_string()).collect();
            self.say(format!(
                "{tag}plan: {} ({:.1} m, map tolerance {}); legs: {}",
                nav.plan().waypoints.join(" → "),
                nav.plan().length_m,
                nav.map().tolerance,
                legs.join("; ")
            ));
            let world = &setup.world;
            let mut obstacles: Vec<String> = world
                .boxes
                .iter()
                .map(|b| {
                    let [l, w, h] = b.size;
                    let (x, y) = (b.center[0], b.center[1]);
                    let yaw = b.yaw.to_degrees();
                    format!("{} box {l:.2}x{w:.2}x{h:.2} m at ({x:.2}, {y:.2}) yaw {yaw:.0}°", b.name)
                })
                .collect();
            obstacles.extend(world.cylinders.iter().map(|c| {
                let (x, y) = (c.center[0], c.center[1]);
                format!("{} cylinder r {:.2} m at ({x:.2}, {y:.2})", c.name, c.radius)
            }));
            if !obstacles.is_empty() {
                self.say(format!("{tag}obstacles: {}", obstacles.join("; ")));
            }
        }
        let mission = setup.mission.to_string();
        let options = || {
            let mut options = record::run_options("sim", &setup.config, &setup.calib, Some(&mission), None);
            record::add_map(&mut options, &setup.map);
            options.live = self.live.clone();
            options
        };
        let log = match (&self.log_dir, &self.live) {
            (Some(dir), _) => Some(LogWriter::create(dir, options()).context("opening the MCAP log")?),
            (None, Some(_)) => Some(LogWriter::live_only(options()).context("starting the live view's encoder")?),
            (None, None) => None,
        };
        let handle = log.as_ref().map(|l| l.handle());
        let quiet = args.quiet;
        let summary = rt
            .block_on(sim::run(&setup, handle.as_ref(), |p| {
                if !quiet {
                    self.say(format!("{tag}{p}"));
                }
            }))
            .with_context(|| seed.map_or("the mission".to_string(), |s| format!("the mission of seed {s}")))?;
        if let Some(log) = log {
            let path = log.path().to_path_buf();
            let s = log.close().context("closing the MCAP log")?;
            if !args.quiet && self.log_dir.is_some() {
                self.say(format!("{tag}log: {} ({s})", path.display()));
            }
        }
        Ok(summary)
    }
}

/// The missions on `n` threads (`--jobs`, 1 by default), each with its own runtime; each summary
/// is printed as soon as those of all lower seeds are, so the output is that of one at a time
/// whatever `n`. With several threads, progress lines start with `[seed N]`. The first error
/// stops the threads from starting new missions and is returned.
fn run_missions(job: &SeedJob, seeds: &[Option<u64>], n: usize) -> anyhow::Result<Vec<SimSummary>> {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
    struct Done {
        results: Vec<Option<SimSummary>>,
        printed: usize,
        error: Option<anyhow::Error>,
    }
    let next = AtomicUsize::new(0);
    let stop = AtomicBool::new(false);
    let done = Mutex::new(Done { results: seeds.iter().map(|_| None).collect(), printed: 0, error: None });
    let worker = || -> anyhow::Result<()> {
        let rt = runtime()?;
        while !stop.load(Ordering::SeqCst) {
            let i = next.fetch_add(1, Ordering::SeqCst);
            let Some(seed) = seeds.get(i) else { break };
            let tag = match (n > 1, seed) {
                (true, Some(s)) => format!("[seed {s}] "),
                _ => String::new(),
            };
            let summary = job.run(&rt, *seed, &tag)?;
            let mut d = done.lock().map_err(|_| anyhow::anyhow!("a mission thread panicked"))?;
            d.results[i] = Some(summary);
            let finished = d.results.iter().flatten();
            let (reached, contacts) =
                finished.fold((0, 0), |(r, c), s| (r + s.reached as u32, c + (s.collisions > 0) as u32));
            job.progress.set_message(format!("reached {reached}, contacts {contacts}"));
            job.progress.inc(1);
            while let Some(Some(s)) = d.results.get(d.printed) {
                job.progress.suspend(|| print_summary(s))?;
                d.printed += 1;
            }
        }
        Ok(())
    };
    std::thread::scope(|scope| {
        for _ in 0..n.min(seeds.len()) {
            scope.spawn(|| {
                if let Err(e) = worker() {
                    stop.store(true, Ordering::SeqCst);
                    if let Ok(mut d) = done.lock() {
                        d.error.get_or_insert(e);
                    }
                }
            });
        }
    });
    let done = done.into_inner().map_err(|_| anyhow::anyhow!("a mission thread panicked"))?;
    match done.error {
        Some(e) => Err(e),
        None => Ok(done.results.into_iter().flatten().collect()),
    }
}
