//! The algorithm contract of `docs/flow.md`, written as plainly as possible: every candidate's
//! full cost, no early termination, no SIMD. Slow (seconds per 720p frame). It exists so that
//! tests can check the fast engines against it, and as executable specification for the GPU
//! engine.

use super::prefilter::{self, Scratch};
use super::{FlowError, FlowField, FlowParams, FlowVector, Validity};
use hal::LumaImage;

/// The flow field the contract defines for `params` and the frame pair (`a`, `b`).
pub fn reference_flow(params: &FlowParams, a: &LumaImage, b: &LumaImage) -> Result<FlowField, FlowError> {
    params.validate()?;
    super::check_frames(params, a, b)?;
    let nlev = params.pyramid_levels.max(1);
    // raw[l] and hp[l] for frames A and B.
    let mut raw = vec![(a.clone(), b.clone())];
    for l in 1..nlev {
        let (mut da, mut db) = (LumaImage::default(), LumaImage::default());
        prefilter::downsample(&raw[l - 1].0, &mut da);
        prefilter::downsample(&raw[l - 1].1, &mut db);
        raw.push((da, db));
    }
    let mut scratch = Scratch::default();
    let hp: Vec<(LumaImage, LumaImage)> = raw
        .iter()
        .map(|(ra, rb)| {
            let (mut ha, mut hb) = (LumaImage::default(), LumaImage::default());
            prefilter::highpass(ra, params.prefilter_radius, &mut ha, &mut scratch);
            prefilter::highpass(rb, params.prefilter_radius, &mut hb, &mut scratch);
            (ha, hb)
        })
        .collect();

    let origins = super::block_origins(params, a.width(), a.height());
    let q8 = params.ambiguity_q8() as i64;
    let (rows, cols) = params.grid(a.width(), a.height());
    let mut field = FlowField { rows, cols, width: a.width(), height: a.height(), vectors: vec![] };
    let n = origins.len();
    let (mut d_all, mut edge_all, mut amb_all) = (vec![(0i64, 0i64); n], vec![false; n], vec![false; n]);
    let mut last = vec![None; n];
    for l in (0..nlev).rev() {
        let coarse = d_all.clone();
        for (i, &(ox, oy)) in origins.iter().enumerate() {
            let (ha, hb) = &hp[l];
            let (wl, hl) = (ha.width() as i64, ha.height() as i64);
            let b2 = params.block as i64 / 2;
            // The block side at this level (B at level 0).
            let bs = super::level_block(params.block, l);
            let x0 = (((ox as i64 + b2) >> l) - bs as i64 / 2).clamp(0, wl - bs as i64);
            let y0 = (((oy as i64 + b2) >> l) - bs as i64 / 2).clamp(0, hl - bs as i64);
            let (centre, r) = if l == nlev - 1 {
                ((0, 0), params.radius as i64)
            } else {
                // Lower median of the 3×3 grid neighbourhood at the coarser level, doubled.
                let (br, bc) = (i / cols, i % cols);
                let (mut xs, mut ys) = (vec![], vec![]);
                for rr in br.saturating_sub(1)..=(br + 1).min(rows - 1) {
                    for cc in bc.saturating_sub(1)..=(bc + 1).min(cols - 1) {
                        xs.push(coarse[rr * cols + cc].0);
                        ys.push(coarse[rr * cols + cc].1);
                    }
                }
                xs.sort();
                ys.sort();
                let m = (xs.len() - 1) / 2;
                ((2 * xs[m], 2 * ys[m]), params.refine_radius as i64)
            };
            let (fx0, fx1, fy0, fy1) = (-x0, wl - bs as i64 - x0, -y0, hl - bs as i64 - y0);
            let c = (centre.0.clamp(fx0, fx1), centre.1.clamp(fy0, fy1));
            let (lx, hx, ly, hy) = ((c.0 - r).max(fx0), (c.0 + r).min(fx1), (c.1 - r).max(fy0), (c.1 + r).min(fy1));
            let cost = |dx: i64, dy: i64| -> i64 {
                let mut s = 0i64;
                for y in 0..bs as i64 {
                    for x in 0..bs as i64 {
                        let p = ha.get((x0 + x) as usize, (y0 + y) as usize) as i64;
                        let q = hb.get((x0 + dx + x) as usize, (y0 + dy + y) as usize) as i64;
                        s += (p - q).abs();
                    }
                }
                s
            };
            let inside = |dx: i64, dy: i64| (lx..=hx).contains(&dx) && (ly..=hy).contains(&dy);
            let gw = (hx - lx + 1) as usize;
            let mut all = vec![0i64; gw * (hy - ly + 1) as usize];
            let at = |dx: i64, dy: i64| (dy - ly) as usize * gw + (dx - lx) as usize;
            // (cost, tie-break key, displacement) of the best candidate so far.
            type Best = (i64, (i64, i64, i64), (i64, i64));
            let mut best: Option<Best> = None;
            for dy in ly..=hy {
                for dx in lx..=hx {
                    let s = cost(dx, dy);
                    all[at(dx, dy)] = s;
                    let key = ((dx - c.0).pow(2) + (dy - c.1).pow(2), dy, dx);
                    if best.is_none_or(|(bc, bk, _)| (s, key) < (bc, bk)) {
                        best = Some((s, key, (dx, dy)));
                    }
                }
            }
            let (c1, _, d1) = best.expect("window never empty");
            d_all[i] = d1;
            edge_all[i] |= d1.0 == lx || d1.0 == hx || d1.1 == ly || d1.1 == hy;
            for dy in ly..=hy {
                for dx in lx..=hx {
                    let s = all[at(dx, dy)];
                    let far = (dx - d1.0).abs().max((dy - d1.1).abs()) >= 2;
                    let local_min = (-1..=1)
                        .all(|ny| (-1..=1).all(|nx| !inside(dx + nx, dy + ny) || all[at(dx + nx, dy + ny)] >= s));
                    amb_all[i] |= far && local_min && s * 256 <= c1 * (256 + q8);
                }
            }
            if l == 0 {
                let ssd = |dx: i64, dy: i64| -> i64 {
                    let mut s = 0i64;
                    for y in 0..bs as i64 {
                        for x in 0..bs as i64 {
                            let p = ha.get((x0 + x) as usize, (y0 + y) as usize) as i64;
                            let q = hb.get((x0 + dx + x) as usize, (y0 + dy + y) as usize) as i64;
                            s += (p - q).pow(2);
                        }
                    }
                    s
                };
                let s0 = ssd(d1.0, d1.1);
                let n = |dx: i64, dy: i64| inside(dx, dy).then(|| ssd(dx, dy));
                let sub = |m: Option<i64>, p: Option<i64>| match (m, p) {
                    (Some(m), Some(p)) if s0 > 0 && m - 2 * s0 + p > 0 => {
                        ((m - p) as f64 / (2 * (m - 2 * s0 + p)) as f64).clamp(-0.5, 0.5)
                    }
                    _ => 0.0,
                };
                let du = sub(n(d1.0 - 1, d1.1), n(d1.0 + 1, d1.1));
                let dv = sub(n(d1.0, d1.1 - 1), n(d1.0, d1.1 + 1));
                let mut g = 0i64;
                for y in 0..bs as i64 {
                    for x in 0..bs as i64 {
                        let p = ha.get((x0 + x) as usize, (y0 + y) as usize) as i64;
                        if x + 1 < bs as i64 {
                            g += (ha.get((x0 + x + 1) as usize, (y0 + y) as usize) as i64 - p).abs();
                        }
                        if y + 1 < bs as i64 {
                            g += (ha.get((x0 + x) as usize, (y0 + y + 1) as usize) as i64 - p).abs();
                        }
                    }
                }
                let textureless = 16 * g < params.min_texture_q4() as i64 * (2 * bs * (bs - 1)) as i64;
                let validity = match () {
                    _ if textureless => Validity::Textureless,
                    _ if edge_all[i] => Validity::OutOfFrame,
                    _ if amb_all[i] => Validity::Ambiguous,
                    _ => Validity::Valid,
                };
                last[i] = Some(FlowVector {
                    x: (ox + bs / 2) as f32,
                    y: (oy + bs / 2) as f32,
                    u: (d1.0 as f64 + du) as f32,
                    v: (d1.1 as f64 + dv) as f32,
                    validity,
                    cost: c1 as f32 / (bs * bs) as f32,
                });
            }
        }
    }
    field.vectors = last.into_iter().map(|v| v.expect("level 0 always runs")).collect();
    Ok(field)
}
