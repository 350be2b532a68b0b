//! `flownav render`: views of a simulated world (mocks), for a person to look at or as a labelled
//! frame folder.
//!
//! - `--pose x,y,yaw_deg --png OUT` writes one PNG and prints its ground truth as one JSON line.
//! - `--out DIR [--start x,y,yaw_deg] [--velocity V] [--omega W] [--fps F] [--frames N]` drives
//!   a constant-velocity arc and writes a frame folder (DESIGN.md): `0000.png`…, `odometry.csv`
//!   (`t,v,omega`), `calib.toml` (the calibration used) and `truth.json` (per-frame ground truth
//!   and the exact block motion field from the previous frame).

use super::Common;
use anyhow::{Context, bail};
use hal::{Calibration, LumaImage};
use mocks::truth::{GroundTruth, block_centres, motion_field};
use mocks::{Effects, Pose, Renderer, World};
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// World file (TOML, see docs/sim-world.md); default: the built-in office.
    #[arg(long, value_name = "FILE")]
    pub world: Option<PathBuf>,
    /// Replace the corridor obstacles by a random placement with this seed (the world's
    /// `[random]`).
    #[arg(long, value_name = "SEED")]
    pub obstacle_seed: Option<u64>,
    /// Single view: robot pose `x,y,yaw_deg` (default: the world's start).
    #[arg(long, value_name = "X,Y,YAW_DEG", value_parser = parse_pose, allow_hyphen_values = true)]
    pub pose: Option<Pose>,
    /// Single view: write it to this PNG.
    #[arg(long, value_name = "OUT", conflicts_with = "out")]
    pub png: Option<PathBuf>,
    /// Trajectory: write a frame folder here.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Trajectory start pose `x,y,yaw_deg` (default: the world's start).
    #[arg(long, value_name = "X,Y,YAW_DEG", value_parser = parse_pose, allow_hyphen_values = true)]
    pub start: Option<Pose>,
    /// Trajectory forward speed, m/s.
    #[arg(long, default_value_t = 0.3, allow_hyphen_values = true)]
    pub velocity: f64,
    /// Trajectory turn rate, rad/s (positive = left).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub omega: f64,
    /// Trajectory frame rate, frames/s.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// Trajectory length in frames.
    #[arg(long, default_value_t = 30)]
    pub frames: usize,
    /// Render at this size instead of the calibration's (`WxH`, intrinsics scaled).
    #[arg(long, value_name = "WxH", value_parser = |s: &str| super::parse_size(s, 16..))]
    pub size: Option<(u32, u32)>,
    /// Sensor noise, standard deviation in grey levels.
    #[arg(long, default_value_t = 0.0)]
    pub noise: f64,
    /// Seed of the sensor noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Exposure gain (output = gain · image + offset).
    #[arg(long, default_value_t = 1.0)]
    pub gain: f64,
    /// Exposure offset, grey levels.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub offset: f64,
    /// Motion blur: sub-frame renders averaged over each frame interval (1 = off).
    #[arg(long, default_value_t = 1)]
    pub blur: usize,
}

fn parse_pose(s: &str) -> Result<Pose, String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|_| format!("`{p}` is not a number")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [x, y, yaw_deg] if v.iter().all(|x| x.is_finite()) => Ok(Pose::new(x, y, yaw_deg.to_radians())),
        _ => Err(format!("expected x,y,yaw_deg (metres, metres, degrees), got `{s}`")),
    }
}

/// One frame of `truth.json`.
#[derive(Serialize)]
struct TruthRow {
    index: usize,
    t: f64,
    pose: Pose,
    tpo: mocks::truth::TpoTruth,
    obstacle: mocks::truth::ObstacleTruth,
    /// Exact block motion from the previous frame (absent for frame 0).
    #[serde(skip_serializing_if = "Option::is_none")]
    flow: Option<TruthFlow>,
}

#[derive(Serialize)]
struct TruthFlow {
    rows: usize,
    cols: usize,
    block: usize,
    vectors: Vec<TruthVector>,
}

#[derive(Serialize)]
struct TruthVector {
    x: f64,
    y: f64,
    u: Option<f64>,
    v: Option<f64>,
}

#[derive(Serialize)]
struct TruthFile<'a> {
    world: &'a str,
    fps: f64,
    velocity: f64,
    omega: f64,
    noise: f64,
    seed: u64,
    frames: Vec<TruthRow>,
}

pub fn run(args: Args, common: &Common) -> anyhow::Result<()> {
    let calib = common.calibration()?;
    let calib = match args.size {
        Some((w, h)) => calib.scaled_to(w, h),
        None => calib,
    };
    let mut world = match &args.world {
        Some(path) => World::load(path)?,
        None => World::office(),
    };
    if let Some(seed) = args.obstacle_seed {
        world = world.with_random_obstacles(seed)?;
    }
    if !(args.gain.is_finite() && args.gain > 0.0) {
        bail!("--gain {} must be a positive number", args.gain);
    }
    if !(args.noise.is_finite() && args.noise >= 0.0) {
        bail!("--noise {} must be zero or a positive number of grey levels", args.noise);
    }
    if !args.offset.is_finite() || args.blur == 0 || args.blur > 64 {
        bail!("--offset must be finite and --blur between 1 and 64");
    }
    let effects = Effects {
        gain: args.gain,
        offset: args.offset,
        noise_sigma: args.noise,
        seed: args.seed,
        blur_samples: args.blur,
    };
    let renderer = Renderer::new(&world, &calib);
    let truth = GroundTruth::new(&world, &calib);
    match (&args.png, &args.out) {
        (Some(png), None) => {
            let pose = args.pose.unwrap_or(world.start);
            let mut img = LumaImage::default();
            renderer.render_frame(pose, pose, &effects, 0, &mut img);
            crate::frames::save_png(&img, png).with_context(|| format!("writing {}", png.display()))?;
            println!("{}", serde_json::to_string(&truth.frame(pose))?);
            Ok(())
        }
        (None, Some(dir)) => {
            if args.pose.is_some() {
                bail!("--pose is for a single view with --png; a trajectory starts at --start");
            }
            write_folder(&args, dir, &world, &calib, &renderer, &truth, &effects)
        }
        _ => bail!("say what to write: --png OUT for one view, or --out DIR for a trajectory frame folder"),
    }
}

fn write_folder(
    args: &Args,
    dir: &Path,
    world: &World,
    calib: &Calibration,
    renderer: &Renderer,
    truth: &GroundTruth,
    effects: &Effects,
) -> anyhow::Result<()> {
    if !(args.fps.is_finite() && args.fps > 0.0) {
        bail!("--fps {} must be positive", args.fps);
    }
    if !(args.velocity.is_finite() && args.omega.is_finite()) {
        bail!("--velocity and --omega must be finite numbers");
    }
    if args.frames < 2 {
        bail!("--frames {} is too few: a frame folder needs at least 2", args.frames);
    }
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let dt = 1.0 / args.fps;
    let start = args.start.unwrap_or(world.start);
    let (rows, cols, block) = (16usize, 16usize, 32usize);
    let (w, h) = (calib.camera.width as usize, calib.camera.height as usize);
    let centres = block_centres(w, h, rows, cols);
    let mut odo = String::from("t,v,omega\n");
    let mut frames = Vec::with_capacity(args.frames);
    let mut prev: Option<(Pose, mocks::DepthMap)> = None;
    let mut warned = false;
    let mut img = LumaImage::default();
    for i in 0..args.frames {
        let t = i as f64 * dt;
        let pose = start.advance(args.velocity, args.omega, t);
        let clearance = world.clearance(pose.x, pose.y);
        if clearance.distance_m < 0.15 && !warned {
            tracing::warn!(
                "frame {i}: the robot at ({:.2}, {:.2}) is {:.2} m from {} (the camera may be inside it)",
                pose.x,
                pose.y,
                clearance.distance_m,
                clearance.object
            );
            warned = true;
        }
        let from = prev.as_ref().map_or(pose, |(p, _)| *p);
        renderer.render_frame(from, pose, effects, i as u64, &mut img);
        let path = dir.join(format!("{i:04}.png"));
        crate::frames::save_png(&img, &path).with_context(|| format!("writing {}", path.display()))?;
        odo.push_str(&format!("{t:.6},{},{}\n", args.velocity, args.omega));
        let depth = renderer.depth(pose);
        let flow = prev.as_ref().map(|(p, d)| {
            let field = motion_field(calib, d, *p, pose);
            TruthFlow {
                rows,
                cols,
                block,
                vectors: centres
                    .iter()
                    .map(|c| {
                        let m = field.block_mean(c[0], c[1], block);
                        TruthVector { x: c[0], y: c[1], u: m.map(|m| m[0]), v: m.map(|m| m[1]) }
                    })
                    .collect(),
            }
        });
        let ft = truth.frame(pose);
        frames.push(TruthRow { index: i, t, pose, tpo: ft.tpo, obstacle: ft.obstacle, flow });
        prev = Some((pose, depth));
    }
    std::fs::write(dir.join("odometry.csv"), odo).context("writing odometry.csv")?;
    std::fs::write(dir.join("calib.toml"), toml::to_string(calib).context("serialising the calibration")?)
        .context("writing calib.toml")?;
    let file = TruthFile {
        world: &world.name,
        fps: args.fps,
        velocity: args.velocity,
        omega: args.omega,
        noise: args.noise,
        seed: args.seed,
        frames,
    };
    let mut out =
        std::io::BufWriter::new(std::fs::File::create(dir.join("truth.json")).context("creating truth.json")?);
    serde_json::to_writer(&mut out, &file).context("writing truth.json")?;
    out.flush().context("writing truth.json")?;
    println!("{}", dir.display());
    Ok(())
}
