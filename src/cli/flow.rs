//! `flownav flow A B [--json] [--png OUT]`: the block flow field between two images.
//!
//! `--json` prints the DESIGN.md contract on one line:
//! `{"grid":[rows,cols],"width":W,"height":H,"vectors":[{"x":cx,"y":cy,"u":du,"v":dv,"valid":true,...},...],...}`
//! with extra fields `cost` and `reason` per vector and `backend` at the end. Without it, a
//! human-readable summary. `--png OUT` draws the vectors over frame A.

use super::Common;
use crate::flow::{self, FlowField, FlowParams, Placement, Validity};
use crate::frames;
use anyhow::Context;
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Frame A (PNG or JPEG; colour is converted to luma).
    pub a: PathBuf,
    /// Frame B, the same size as A.
    pub b: PathBuf,
    /// Print the flow field as one JSON object (the stable output contract).
    #[arg(long)]
    pub json: bool,
    /// Also draw the vectors over frame A into this PNG file.
    #[arg(long, value_name = "OUT")]
    pub png: Option<PathBuf>,
    /// Grid rows (overrides flow.rows).
    #[arg(long)]
    pub rows: Option<usize>,
    /// Grid columns (overrides flow.cols).
    #[arg(long)]
    pub cols: Option<usize>,
    /// Block side in pixels (overrides flow.block).
    #[arg(long)]
    pub block: Option<usize>,
    /// Search radius in pixels (overrides flow.radius).
    #[arg(long)]
    pub radius: Option<usize>,
    /// Pyramid levels for coarse-to-fine search, 1 = off (overrides flow.pyramid_levels).
    #[arg(long)]
    pub pyramid_levels: Option<usize>,
    /// Block placement (overrides flow.placement).
    #[arg(long, value_enum)]
    pub placement: Option<Placement>,
    /// Compute the pair N times (after one uncounted warm-up) and report the time per pair:
    /// min, median and p90 in milliseconds, with the engine and the adapter it ran on.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=100_000))]
    pub repeat: Option<u32>,
    /// Threads the CPU engine splits the pair over, 0 = one per core up to 4 (overrides
    /// flow.cpu_threads; 1 compares with single-threaded tools).
    #[arg(long, value_name = "N")]
    pub threads: Option<usize>,
}

impl Args {
    fn apply(&self, p: &mut FlowParams) {
        let set = |dst: &mut usize, v: Option<usize>| {
            if let Some(v) = v {
                *dst = v;
            }
        };
        set(&mut p.rows, self.rows);
        set(&mut p.cols, self.cols);
        set(&mut p.block, self.block);
        set(&mut p.cpu_threads, self.threads);
        set(&mut p.radius, self.radius);
        set(&mut p.pyramid_levels, self.pyramid_levels);
        if let Some(pl) = self.placement {
            p.placement = pl;
        }
    }
}

#[derive(Serialize)]
struct JsonVector {
    x: f32,
    y: f32,
    u: f32,
    v: f32,
    valid: bool,
    cost: f32,
    reason: &'static str,
}

#[derive(Serialize)]
struct JsonField<'a> {
    grid: [usize; 2],
    width: usize,
    height: usize,
    vectors: Vec<JsonVector>,
    backend: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    timing: Option<&'a Timing>,
}

/// Wall time per frame pair of `flownav flow --repeat N`: the `timing` object of `--json`.
/// Each figure is one `compute` call (frame upload, prefilter, matching, and for the GPU the
/// readback), images already decoded; one warm-up call before them is not counted (it allocates
/// the buffers and, on a GPU, compiles the shaders).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Timing {
    /// Counted calls.
    pub n: u32,
    /// Uncounted calls before them.
    pub warmup: u32,
    pub min_ms: f64,
    pub median_ms: f64,
    pub p90_ms: f64,
    pub mean_ms: f64,
    /// The same per-call figures in CPU time of the process (`CLOCK_PROCESS_CPUTIME_ID`, all
    /// the engine's threads together): what the cores spend per pair on the CPU engine,
    /// unaffected by other processes on a shared machine; for the GPU engine, the host's share.
    pub cpu_min_ms: f64,
    pub cpu_median_ms: f64,
    pub cpu_p90_ms: f64,
    /// `"cpu"` or `"gpu"`.
    pub engine: String,
    /// What the engine ran on: the GPU adapter, or the CPU model with its SAD kernel.
    pub adapter: String,
}

impl Timing {
    /// Statistics of `ms` (not empty): p90 is the nearest-rank percentile (the smallest value
    /// with at least 90 % of the values at or below it), the median the middle value (the mean
    /// of the two middle ones for an even count).
    /// `wall` and `cpu` are the per-call times in ms (the same count).
    pub fn new(wall: Vec<f64>, cpu: Vec<f64>, warmup: u32, engine: &str, adapter: String) -> Self {
        assert!(!wall.is_empty() && wall.len() == cpu.len(), "timing needs one wall and one CPU time per call");
        let n = wall.len();
        let mean_ms = wall.iter().sum::<f64>() / n as f64;
        let (min_ms, median_ms, p90_ms) = stats(wall);
        let (cpu_min_ms, cpu_median_ms, cpu_p90_ms) = stats(cpu);
        Self {
            n: n as u32,
            warmup,
            min_ms,
            median_ms,
            p90_ms,
            mean_ms,
            cpu_min_ms,
            cpu_median_ms,
            cpu_p90_ms,
            engine: engine.to_string(),
            adapter,
        }
    }
}

/// (min, median, p90) of a non-empty sample.
fn stats(mut v: Vec<f64>) -> (f64, f64, f64) {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    let p90 = v[(n * 9).div_ceil(10) - 1];
    (v[0], median(v).expect("not empty"), p90)
}

/// CPU time of the calling thread, ms.
fn process_cpu_ms() -> f64 {
    nix::time::clock_gettime(nix::time::ClockId::CLOCK_PROCESS_CPUTIME_ID)
        .map_or(0.0, |t| t.tv_sec() as f64 * 1e3 + t.tv_nsec() as f64 * 1e-6)
}

/// The JSON text of a field (the `flownav flow --json` contract).
pub fn to_json(field: &FlowField, backend: &str) -> String {
    to_json_timed(field, backend, None)
}

/// [`to_json`] with the `timing` object of `--repeat` appended.
pub fn to_json_timed(field: &FlowField, backend: &str, timing: Option<&Timing>) -> String {
    let out = JsonField {
        grid: [field.rows, field.cols],
        width: field.width,
        height: field.height,
        vectors: field
            .vectors
            .iter()
            .map(|v| JsonVector {
                x: v.x,
                y: v.y,
                u: v.u,
                v: v.v,
                valid: v.valid(),
                cost: v.cost,
                reason: v.validity.name(),
            })
            .collect(),
        backend,
        timing,
    };
    serde_json::to_string(&out).expect("flow field serialises")
}

pub fn run(args: Args, common: &Common) -> anyhow::Result<()> {
    let mut cfg = common.config()?;
    args.apply(&mut cfg.flow);
    cfg.validate().context("after applying the flow command's flags")?;
    let a = frames::load_luma(&args.a)?;
    let b = frames::load_luma(&args.b)?;
    let (mut engine, report) = flow::create_engine(&cfg.flow)?;
    let backend = engine.name();
    let context = || format!("computing flow from {} to {}", args.a.display(), args.b.display());
    let mut timing = None;
    if let Some(n) = args.repeat {
        const WARMUP: u32 = 1;
        for _ in 0..WARMUP {
            engine.compute(&a, &b).with_context(context)?;
        }
        let (mut wall, mut cpu) = (Vec::with_capacity(n as usize), Vec::with_capacity(n as usize));
        for _ in 0..n {
            let (t0, c0) = (Instant::now(), process_cpu_ms());
            engine.compute(&a, &b).with_context(context)?;
            cpu.push(process_cpu_ms() - c0);
            wall.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        let adapter = report.adapter.clone().unwrap_or_else(|| cpu_adapter(&cfg.flow, engine.threads()));
        timing = Some(Timing::new(wall, cpu, WARMUP, backend, adapter));
    }
    let t0 = Instant::now();
    let field = engine.compute(&a, &b).with_context(context)?;
    let elapsed = t0.elapsed();
    if args.json {
        println!("{}", to_json_timed(field, backend, timing.as_ref()));
    } else {
        print!("{}", summary(field, &cfg.flow, backend, elapsed.as_secs_f64() * 1e3, &args));
        if let Some(t) = &timing {
            println!(
                "{} repeats on {} ({}): min {:.3} ms, median {:.3} ms, p90 {:.3} ms per pair \
                 (process CPU time: min {:.3}, median {:.3}, p90 {:.3} ms)",
                t.n, t.engine, t.adapter, t.min_ms, t.median_ms, t.p90_ms, t.cpu_min_ms, t.cpu_median_ms, t.cpu_p90_ms
            );
        }
    }
    if let Some(out) = &args.png {
        draw::save_overlay(&a, field, out).with_context(|| format!("writing {}", out.display()))?;
        if !args.json {
            println!("vectors drawn over frame A into {}", out.display());
        }
    }
    Ok(())
}

/// The CPU the CPU engine runs on, its SAD kernel and threads: "MODEL (avx2 SAD, 1 thread)".
fn cpu_adapter(p: &FlowParams, threads: usize) -> String {
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, m)| m.trim().to_string())
        })
        .unwrap_or_else(|| std::env::consts::ARCH.to_string());
    let plural = if threads == 1 { "" } else { "s" };
    format!("{model} ({} SAD, {threads} thread{plural})", flow::sad::Kernel::detect(p.block).name())
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) })
}

fn summary(field: &FlowField, p: &FlowParams, backend: &str, ms: f64, args: &Args) -> String {
    let count = |r: Validity| field.vectors.iter().filter(|v| v.validity == r).count();
    let valid: Vec<_> = field.vectors.iter().filter(|v| v.valid()).collect();
    let mag = median(valid.iter().map(|v| f64::from(v.u).hypot(f64::from(v.v))).collect());
    let mu = median(valid.iter().map(|v| f64::from(v.u)).collect());
    let mv = median(valid.iter().map(|v| f64::from(v.v)).collect());
    let mut s = format!(
        "flow {} -> {}: {}x{} px, {}x{} blocks of {} px, radius {}, {} pyramid level(s), backend {backend}, {ms:.1} ms\n",
        args.a.display(),
        args.b.display(),
        field.width,
        field.height,
        field.rows,
        field.cols,
        p.block,
        p.radius,
        p.pyramid_levels.max(1),
    );
    s += &format!(
        "valid {}/{}; invalid: textureless {}, ambiguous {}, out_of_frame {}\n",
        valid.len(),
        field.vectors.len(),
        count(Validity::Textureless),
        count(Validity::Ambiguous),
        count(Validity::OutOfFrame)
    );
    match (mag, mu, mv) {
        (Some(m), Some(u), Some(v)) => {
            s += &format!("median |flow| of valid vectors {m:.2} px; median (u, v) = ({u:.2}, {v:.2}) px\n")
        }
        _ => s += "no valid vectors\n",
    }
    s
}

/// The `--png` overlay: frame A in grey, one arrow per block from its centre along its
/// displacement, coloured by validity.
mod draw {
    use crate::flow::{FlowField, Validity};
    use hal::LumaImage;
    use image::{Rgb, RgbImage};
    use std::path::Path;

    pub fn colour(v: Validity) -> Rgb<u8> {
        match v {
            Validity::Valid => Rgb([40, 230, 40]),
            Validity::Textureless => Rgb([150, 150, 150]),
            Validity::Ambiguous => Rgb([250, 210, 0]),
            Validity::OutOfFrame => Rgb([240, 40, 40]),
        }
    }

    /// Bresenham line, clipped to the image.
    fn line(img: &mut RgbImage, (x0, y0): (i64, i64), (x1, y1): (i64, i64), c: Rgb<u8>) {
        let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
        let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
        let (mut x, mut y, mut err) = (x0, y0, dx + dy);
        loop {
            if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
                img.put_pixel(x as u32, y as u32, c);
            }
            if x == x1 && y == y1 {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }

    /// Arrow length scale: the longest valid vector spans 80 % of the smaller grid spacing,
    /// but vectors are never drawn shorter than they are (scale ≥ 1) nor more than 10× longer.
    pub fn scale(field: &FlowField) -> f64 {
        let spacing = (field.width as f64 / field.cols as f64).min(field.height as f64 / field.rows as f64);
        let longest = field
            .vectors
            .iter()
            .filter(|v| v.valid())
            .map(|v| f64::from(v.u).hypot(f64::from(v.v)))
            .fold(0.0, f64::max);
        if longest > 0.0 { (0.8 * spacing / longest).clamp(1.0, 10.0) } else { 1.0 }
    }

    pub fn overlay(a: &LumaImage, field: &FlowField) -> RgbImage {
        let mut img = RgbImage::from_fn(a.width() as u32, a.height() as u32, |x, y| {
            let g = a.get(x as usize, y as usize) / 2 + 40;
            Rgb([g, g, g])
        });
        let s = scale(field);
        for v in &field.vectors {
            let c = colour(v.validity);
            let (x0, y0) = (f64::from(v.x), f64::from(v.y));
            let (ex, ey) = (x0 + s * f64::from(v.u), y0 + s * f64::from(v.v));
            let p0 = (x0.round() as i64, y0.round() as i64);
            let p1 = (ex.round() as i64, ey.round() as i64);
            for (ox, oy) in [(0, 0), (1, 0), (0, 1), (1, 1), (-1, 0), (0, -1)] {
                line(&mut img, (p0.0 + ox, p0.1 + oy), (p0.0 + ox, p0.1 + oy), c);
            }
            line(&mut img, p0, p1, c);
            let len = (ex - x0).hypot(ey - y0);
            if len >= 3.0 {
                let ang = (ey - y0).atan2(ex - x0);
                let head = (len * 0.3).clamp(3.0, 8.0);
                for side in [-0.45f64, 0.45] {
                    let a2 = ang + std::f64::consts::PI + side;
                    let tip = ((ex + head * a2.cos()).round() as i64, (ey + head * a2.sin()).round() as i64);
                    line(&mut img, p1, tip, c);
                }
            }
        }
        img
    }

    pub fn save_overlay(a: &LumaImage, field: &FlowField, out: &Path) -> Result<(), image::ImageError> {
        overlay(a, field).save_with_format(out, image::ImageFormat::Png)
    }

    #[cfg(test)]
    mod tests {
        use super::*;
        use crate::flow::FlowVector;

        #[test]
        fn arrows_are_drawn_in_validity_colours() {
            let a = LumaImage::new(64, 32);
            let vec = |x: f32, u: f32, validity| FlowVector { x, y: 16.0, u, v: 0.0, validity, cost: 0.0 };
            let field = FlowField {
                rows: 1,
                cols: 2,
                width: 64,
                height: 32,
                vectors: vec![vec(16.0, 5.0, Validity::Valid), vec(48.0, 0.0, Validity::OutOfFrame)],
            };
            let img = overlay(&a, &field);
            // Longest valid vector 5 px, spacing 32 px: scale 0.8 * 32 / 5 = 5.12, arrow ends at x ≈ 42.
            assert_eq!(*img.get_pixel(30, 16), colour(Validity::Valid));
            assert_eq!(*img.get_pixel(48, 16), colour(Validity::OutOfFrame));
            assert_eq!(*img.get_pixel(5, 5), Rgb([40, 40, 40]));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Timing;

    #[test]
    fn timing_statistics() {
        let wall: Vec<f64> = [7.0, 1.0, 3.0, 10.0, 2.0, 9.0, 4.0, 8.0, 6.0, 5.0].to_vec();
        let cpu: Vec<f64> = wall.iter().map(|w| w / 2.0).collect();
        let t = Timing::new(wall, cpu, 1, "cpu", "x".into());
        assert_eq!((t.n, t.min_ms, t.median_ms, t.p90_ms, t.mean_ms), (10, 1.0, 5.5, 9.0, 5.5));
        assert_eq!((t.cpu_min_ms, t.cpu_median_ms, t.cpu_p90_ms), (0.5, 2.75, 4.5));
        let one = Timing::new(vec![2.0], vec![1.0], 0, "gpu", "x".into());
        assert_eq!((one.min_ms, one.median_ms, one.p90_ms), (2.0, 2.0, 2.0));
    }
}
