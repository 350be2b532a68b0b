//! `flownav analyze --frames DIR [--calib FILE] [--velocity V --fps F]`: runs the per-frame
//! pipeline ([`crate::step::Pipeline`]: flow → OFFIS → cruise goal → MOFIS) over a frame folder
//! and prints one JSON object per frame pair (JSON Lines, the DESIGN.md contract):
//!
//! ```json
//! {"seq":1,"t":0.1,"tpo":{"shape":"corridor","confidence":0.8,"distance_m":2.1},
//!  "obstacle":{"present":true,"distance_m":1.3,"direction_deg":-12.0,"cell":[6,3]},
//!  "rough":[[...]],"fine":[[...]],"setpoint":{"v":0.2,"omega":-0.1}}
//! ```
//!
//! `seq` is the index of the newer frame of the pair in the folder, `t` its time (from
//! `odometry.csv`, else `seq / fps`); distances are `null` where they cannot be estimated (the
//! robot is not translating), `direction_deg` and `cell` are `null` without an obstacle.

use super::Common;
use crate::frames::{FrameFolder, load_luma};
use crate::perception::Perception;
use crate::step::Pipeline;
use anyhow::{Context, bail};
use hal::{BodyVelocity, Frame};
use serde::Serialize;
use std::io::Write;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Frame folder: PNG/JPEG images in file-name order, optionally `odometry.csv` (t,v,omega).
    #[arg(long, value_name = "DIR")]
    pub frames: PathBuf,
    /// Forward speed when the folder has no odometry.csv, m/s (0: distances are null).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub velocity: f64,
    /// Frame rate when the folder has no odometry.csv, frames/s.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
}

#[derive(Serialize)]
struct TpoOut {
    shape: &'static str,
    confidence: f64,
    distance_m: Option<f64>,
}

#[derive(Serialize)]
struct ObstacleOut {
    present: bool,
    distance_m: Option<f64>,
    direction_deg: Option<f64>,
    cell: Option<[usize; 2]>,
}

#[derive(Serialize)]
struct SetpointOut {
    v: f64,
    omega: f64,
}

/// One line of output (DESIGN.md `flownav analyze`).
#[derive(Serialize)]
struct Line {
    seq: u64,
    t: f64,
    tpo: TpoOut,
    obstacle: ObstacleOut,
    rough: [[u8; 4]; 4],
    fine: [[u8; 8]; 8],
    setpoint: SetpointOut,
}

impl Line {
    fn new(seq: u64, t: f64, p: &Perception, setpoint: BodyVelocity) -> Self {
        let o = &p.obstacle;
        Self {
            seq,
            t,
            tpo: TpoOut { shape: p.tpo.shape.name(), confidence: p.tpo.confidence, distance_m: p.tpo.distance_m },
            obstacle: ObstacleOut {
                present: o.present,
                distance_m: o.distance_m.filter(|_| o.present),
                direction_deg: o.bearing_rad.filter(|_| o.present).map(f64::to_degrees),
                cell: o.cell.filter(|_| o.present),
            },
            rough: p.rough,
            fine: p.fine,
            setpoint: SetpointOut { v: setpoint.v, omega: setpoint.omega },
        }
    }
}

pub fn run(args: Args, common: &Common) -> anyhow::Result<()> {
    if !(args.fps.is_finite() && args.fps > 0.0) {
        bail!("--fps {} must be a positive number of frames per second", args.fps);
    }
    if !args.velocity.is_finite() {
        bail!("--velocity {} must be a finite speed in m/s", args.velocity);
    }
    if !args.frames.is_dir() {
        bail!(
            "frame folder {} does not exist or is not a folder (pass --frames DIR with PNG/JPEG frames)",
            args.frames.display()
        );
    }
    let folder = FrameFolder::open(&args.frames)?;
    let cfg = common.config()?;
    let calib = common.calibration()?;
    let mut pipeline = Pipeline::new(&cfg, calib, None)?;
    let stdout = std::io::stdout();
    let mut out = std::io::BufWriter::new(stdout.lock());
    for (i, path) in folder.images.iter().enumerate() {
        let image = load_luma(path)?;
        let m = folder.motion(i, args.velocity, args.fps);
        if m.t < 0.0 {
            bail!(
                "{}: frame {} has a negative time {} s; times must start at 0 or later",
                folder.dir.display(),
                i,
                m.t
            );
        }
        let frame = Frame { seq: i as u64, t_ns: (m.t * 1e9).round() as u64, image };
        let odometry = BodyVelocity::new(m.v, m.omega);
        let step = pipeline.step(frame, odometry).with_context(|| format!("frame {}", path.display()))?;
        if let Some(s) = step {
            let line = Line::new(s.seq, m.t, &s.perception, s.setpoint());
            serde_json::to_writer(&mut out, &line)?;
            if let Err(e) = out.write_all(b"\n") {
                if e.kind() == std::io::ErrorKind::BrokenPipe {
                    return Ok(());
                }
                return Err(e.into());
            }
        }
    }
    match out.flush() {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e.into()),
        _ => Ok(()),
    }
}
