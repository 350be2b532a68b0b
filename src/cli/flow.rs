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
}

/// The JSON text of a field (the `flownav flow --json` contract).
pub fn to_json(field: &FlowField, backend: &str) -> String {
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
    };
    serde_json::to_string(&out).expect("flow field serialises")
}

pub fn run(args: Args, common: &Common) -> anyhow::Result<()> {
    let mut cfg = common.config()?;
    args.apply(&mut cfg.flow);
    cfg.validate().context("after applying the flow command's flags")?;
    let a = frames::load_luma(&args.a)?;
    let b = frames::load_luma(&args.b)?;
    let mut engine = flow::engine(&cfg.flow)?;
    let backend = engine.name();
    let t0 = Instant::now();
    let field = engine
        .compute(&a, &b)
        .with_context(|| format!("computing flow from {} to {}", args.a.display(), args.b.display()))?;
    let elapsed = t0.elapsed();
    if args.json {
        println!("{}", to_json(field, backend));
    } else {
        print!("{}", summary(field, &cfg.flow, backend, elapsed.as_secs_f64() * 1e3, &args));
    }
    if let Some(out) = &args.png {
        draw::save_overlay(&a, field, out).with_context(|| format!("writing {}", out.display()))?;
        if !args.json {
            println!("vectors drawn over frame A into {}", out.display());
        }
    }
    Ok(())
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
