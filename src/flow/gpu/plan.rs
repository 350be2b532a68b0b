//! Planning what the shaders compute: the shape of each matching pipeline and, for dense grids,
//! the cost-volume path (its tile, dx groups and tile table), all within the device's
//! workgroup memory and dispatch limits. Pure functions of the parameters and limits, so the
//! plans are checked here without a GPU.

use crate::flow::FlowParams;

/// Most candidates one invocation accumulates per band (registers).
const MAX_PER: u32 = 8;

/// How the dense fast path (the cost volume) is chosen: `mode` `None` = where it applies and
/// pays, `Some(false)` = never, `Some(true)` = wherever it applies (from
/// `FLOWNAV_GPU_COST_VOLUME`, `0`/`1`); `tile` forces its (TC, TR, G) instead of the planner's.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) struct CostVolumeChoice {
    pub(super) mode: Option<bool>,
    pub(super) tile: Option<(u32, u32, u32)>,
}

/// The compile-time shape of a matching pipeline (constants prepended to `match.wgsl`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(super) struct MatchShape {
    pub(super) wg: u32,
    pub(super) block: u32,
    /// Largest window side, 2ρ+1.
    pub(super) win: u32,
    /// Candidate rows per band and block rows per chunk.
    pub(super) band: u32,
    pub(super) chunk: u32,
    pub(super) costs_in_workgroup: bool,
    pub(super) level0: bool,
    /// Costs precomputed by the cost-volume kernel (`costvol.wgsl`): only the reductions run.
    pub(super) pre: bool,
    /// (PRE) The block of A and the patch of B around the best candidate cached in workgroup
    /// memory for the texture energy and the SSDs.
    pub(super) pcache: bool,
}

impl MatchShape {
    /// Chooses band and chunk so that the cached block rows and window fit `budget` bytes of
    /// workgroup memory, minimising the words loaded per block.
    pub(super) fn plan(wg: u32, block: u32, radius: u32, level0: bool, budget: u32) -> Option<Self> {
        let win = 2 * radius + 1;
        let costs_bytes = 4 * win * win;
        let costs_in_workgroup = costs_bytes <= budget / 2;
        let avail = budget.saturating_sub(64 + if costs_in_workgroup { costs_bytes } else { 4 });
        let aw = block.div_ceil(4);
        let rw = Self::row_words(win, block);
        let max_band = win.min(MAX_PER * wg / win).max(1);
        let mut best: Option<(u64, u32, u32)> = None;
        for band in 1..=max_band {
            for chunk in 1..=block {
                let words = chunk * aw + (chunk + band - 1) * rw;
                if 4 * words > avail {
                    continue;
                }
                let passes = u64::from(win.div_ceil(band) * block.div_ceil(chunk));
                let cost = passes * (u64::from(words) + 256);
                if best.is_none_or(|(c, _, _)| cost < c) {
                    best = Some((cost, band, chunk));
                }
            }
        }
        let (_, band, chunk) = best?;
        Some(Self { wg, block, win, band, chunk, costs_in_workgroup, level0, pre: false, pcache: false })
    }

    /// The reductions-only shape that reads the cost volume's global cost grids (level 0): the
    /// costs are copied into workgroup memory (read once from global memory) when they fit in
    /// half of `budget`, and the pixels of the texture energy and SSDs are cached when they fit
    /// in the rest.
    pub(super) fn precomputed(wg: u32, block: u32, radius: u32, budget: u32) -> Self {
        let win = 2 * radius + 1;
        let costs_bytes = 4 * win * win;
        let costs_in_workgroup = costs_bytes <= budget / 2;
        let used = 64 + if costs_in_workgroup { costs_bytes } else { 4 };
        let pcache = used + 4 * (block * block + (block + 2) * (block + 2)) <= budget;
        Self { wg, block, win, band: 1, chunk: 1, costs_in_workgroup, level0: true, pre: true, pcache }
    }

    pub(super) fn row_words(win: u32, block: u32) -> u32 {
        (3 + win - 1 + 4 * (block.div_ceil(4) - 1)) / 4 + 2
    }
}

/// The compile-time shape of the cost-volume kernel (`costvol.wgsl`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(super) struct CostVolShape {
    pub(super) wg: u32,
    pub(super) block: u32,
    pub(super) radius: u32,
    /// Tile of blocks per workgroup: columns, rows.
    pub(super) tc: u32,
    pub(super) tr: u32,
    /// Displacement columns per group (workgroup memory: `g · vw · tr` words).
    pub(super) g: u32,
    /// Widest tile region, pixels.
    pub(super) rwm: u32,
    /// Column sums kept per 4 columns (one word per 4-column quad instead of one per column):
    /// every block starts a whole number of quads after its tile region's start (all x origins
    /// congruent mod 4) and the block side is a multiple of 4.
    pub(super) quads: bool,
    /// (With `quads`) each phase-1 walk takes 4 consecutive dx for its 4 columns: one word of
    /// A and three of B per row serve 16 absolute differences (`costvol.wgsl`, `DQ`).
    pub(super) dx_quads: bool,
    /// Offset of the row-tile table in the tile table.
    pub(super) rowbase: u32,
}

/// Words per column tile and per row tile in the tile table (see `costvol.wgsl`).
pub(super) const CV_CST: u32 = 3;
pub(super) fn cv_rst(tr: u32) -> u32 {
    4 + 2 * tr
}

fn cv_vw(rwm: u32, quads: bool) -> u32 {
    if quads { rwm.div_ceil(4) } else { rwm }
}

/// Phase-1 walks per dx group of `g`: one per (dx, quad of columns), or per (quad of dx, quad
/// of columns) with `dx_quads`.
fn cv_walks(g: u32, rwm: u32, dx_quads: bool) -> u32 {
    if dx_quads { g.div_ceil(4) * rwm.div_ceil(4) } else { g * rwm.div_ceil(4) }
}

impl CostVolShape {
    /// Words of V per block row and dx (one per column, or per quad of 4 columns).
    pub(super) fn vw(&self) -> u32 {
        cv_vw(self.rwm, self.quads)
    }
}

/// Whether the cost volume's walks take 4 dx each where the column sums are kept per quad
/// (`FLOWNAV_GPU_CV_DQ=0` or `FLOWNAV_GPU_CV_SWAR=0` turn it off, for comparisons on a device).
pub(super) fn dx_quads_enabled() -> bool {
    std::env::var("FLOWNAV_GPU_CV_DQ").as_deref() != Ok("0") && swar_enabled()
}

/// Whether the cost volume sums a row's 4 differences in place (`FLOWNAV_GPU_CV_SWAR=0` unpacks
/// them, for comparisons on a device).
pub(super) fn swar_enabled() -> bool {
    std::env::var("FLOWNAV_GPU_CV_SWAR").as_deref() != Ok("0")
}

/// The cost-volume path for one frame size: kernel shape, tile table and dispatch size.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(super) struct CostVolPlan {
    pub(super) shape: CostVolShape,
    /// Tiles across and down.
    pub(super) ntc: u32,
    pub(super) ntr: u32,
    pub(super) table: Vec<u32>,
    /// Absolute differences computed per frame pair (Σ over tiles of region area × (2r+1)²).
    pub(super) abs_diffs: u64,
}

/// Tiles of `t` consecutive positions out of `pos` (sorted block origins along one axis):
/// (region start, region length, positions in the tile) per tile.
fn cv_tiles(pos: &[u32], t: usize, block: u32) -> Vec<(u32, u32, usize)> {
    pos.chunks(t).map(|c| (c[0], c[c.len() - 1] + block - c[0], c.len())).collect()
}

/// Plans the cost-volume path for blocks at `origins` (a `rows × cols` grid, single level), or
/// `None` where it does not apply: origins not a product grid sorted along both axes, a
/// window wider than 255 candidates, or no tile whose workgroup memory fits `budget`.
/// `force` = (TC, TR, G) replaces the planner's choice (tests), still within `budget`; `dx_quads`
/// lets the walks take 4 dx each where the column sums are kept per quad.
fn plan_cost_volume(
    origins: &[(usize, usize)],
    (rows, cols): (usize, usize),
    (block, radius): (usize, usize),
    wg: u32,
    budget: u32,
    force: Option<(u32, u32, u32)>,
    dx_quads: bool,
) -> Option<CostVolPlan> {
    if rows == 0 || cols == 0 || origins.len() != rows * cols || 2 * radius + 1 > 255 || block == 0 {
        return None;
    }
    if force.is_some_and(|(tc, tr, g)| !(1..=64).contains(&tc) || !(1..=64).contains(&tr) || g == 0) {
        return None;
    }
    let xs: Vec<u32> = (0..cols).map(|c| origins[c].0 as u32).collect();
    let ys: Vec<u32> = (0..rows).map(|r| origins[r * cols].1 as u32).collect();
    let grid = origins.iter().enumerate().all(|(i, &(x, y))| x as u32 == xs[i % cols] && y as u32 == ys[i / cols]);
    if !grid || !xs.is_sorted() || !ys.is_sorted() {
        return None;
    }
    let (block, nd) = (block as u32, (2 * radius + 1) as u64);
    let quads = block.is_multiple_of(4) && xs.iter().all(|x| (x - xs[0]).is_multiple_of(4));
    let dq = quads && dx_quads;
    let mut best: Option<(u64, CostVolShape)> = None;
    // The tiles in the order measured fastest on an H200 at 720p dense (docs/gpu.md): larger
    // tiles compute fewer absolute differences. The first whose largest dx group with one
    // phase-1 round (G · ⌈RWM/4⌉ ≤ WG walks, ⌈G/4⌉ · ⌈RWM/4⌉ with quads of dx) fits `budget`
    // with G ≥ 4 is taken, the groups balanced (G = ⌈ND / ⌈ND / G_max⌉⌉, in quads of dx with
    // them); if none does, the serial-step model below chooses.
    if force.is_none() {
        for (tc, tr) in [(16u32, 8u32), (16, 16), (8, 8), (8, 4), (4, 4)] {
            let ct = cv_tiles(&xs, tc as usize, block);
            let rwm = ct.iter().map(|t| t.1).max()?;
            let by_budget = u64::from(budget) / (4 * u64::from(cv_vw(rwm, quads)) * u64::from(tr));
            let unit = if dq { 4 } else { 1 };
            let per_walk = u64::from(rwm.div_ceil(4));
            let gmax = by_budget.min(u64::from(wg) / per_walk * unit).min(nd.next_multiple_of(unit));
            if gmax >= 4.min(nd) && gmax >= unit {
                let (n, m) = (nd.div_ceil(unit), gmax / unit);
                let g = (n.div_ceil(n.div_ceil(m)) * unit).min(nd) as u32;
                let shape =
                    CostVolShape { wg, block, radius: radius as u32, tc, tr, g, rwm, quads, dx_quads: dq, rowbase: 0 };
                best = Some((0, shape));
                break;
            }
        }
    }
    let tiles = [(4u32, 4u32), (8, 4), (4, 8), (8, 8), (16, 8), (8, 16), (16, 16)];
    let tiles = force.map_or(tiles.to_vec(), |(tc, tr, _)| vec![(tc, tr)]);
    let planned = best.is_some();
    for (tc, tr) in tiles.into_iter().filter(|_| !planned) {
        let ct = cv_tiles(&xs, tc as usize, block);
        let rt = cv_tiles(&ys, tr as usize, block);
        let rwm = ct.iter().map(|t| t.1).max()?;
        let rhm = u64::from(rt.iter().map(|t| t.1).max()?);
        let ntiles = (ct.len() * rt.len()) as u64;
        let gs = force.map_or(1..=nd as u32, |(_, _, g)| g..=g);
        for g in gs {
            if 4 * u64::from(g) * u64::from(cv_vw(rwm, quads)) * u64::from(tr) > u64::from(budget) {
                break;
            }
            let groups = nd.div_ceil(u64::from(g));
            let rounds1 = u64::from(cv_walks(g, rwm, dq)).div_ceil(u64::from(wg));
            let rounds2 = u64::from(g * tr * tc).div_ceil(u64::from(wg));
            // Serial steps per workgroup (walks, block sums, barriers), times workgroups.
            let cost = ntiles * nd * groups * (rounds1 * rhm * 8 + rounds2 * u64::from(block) + 64);
            if best.is_none_or(|(c, _)| cost < c) {
                let shape =
                    CostVolShape { wg, block, radius: radius as u32, tc, tr, g, rwm, quads, dx_quads: dq, rowbase: 0 };
                best = Some((cost, shape));
            }
        }
    }
    let (_, mut shape) = best?;
    if dq {
        // fewer walks than invocations with quads of dx: a workgroup of the walks, rounded up
        // to whole warps, keeps more workgroups resident
        shape.wg = shape.wg.min(cv_walks(shape.g, shape.rwm, true).next_multiple_of(32));
    }
    let ct = cv_tiles(&xs, shape.tc as usize, block);
    let rt = cv_tiles(&ys, shape.tr as usize, block);
    shape.rowbase = ct.len() as u32 * CV_CST;
    let mut table = Vec::with_capacity(ct.len() * CV_CST as usize + rt.len() * cv_rst(shape.tr) as usize);
    for &(x0, w, n) in &ct {
        table.extend([x0, w, n as u32]);
    }
    for (t, &(y0, h, n)) in rt.iter().enumerate() {
        let first = t * shape.tr as usize;
        let mut events: Vec<u32> = (0..n)
            .flat_map(|r| {
                let start = ys[first + r] - y0;
                [(start << 12) | ((r as u32) << 1), ((start + block) << 12) | ((r as u32) << 1) | 1]
            })
            .collect();
        events.sort_by_key(|e| e >> 12);
        events.resize(2 * shape.tr as usize, 0);
        table.extend([y0, h, n as u32, 2 * n as u32]);
        table.extend(events);
    }
    let area: u64 = ct.iter().map(|c| u64::from(c.1)).sum::<u64>() * rt.iter().map(|r| u64::from(r.1)).sum::<u64>();
    Some(CostVolPlan { shape, ntc: ct.len() as u32, ntr: rt.len() as u32, table, abs_diffs: area * nd * nd })
}

/// The cost-volume plan for this frame size, where the dense fast path is to run: a single
/// level, allowed by `cost_volume`, blocks overlapping at least twice along both axes
/// (unless forced), and cost grids and dispatch within the device's limits.
pub(super) fn device_plan(
    limits: &wgpu::Limits,
    p: &FlowParams,
    choice: CostVolumeChoice,
    origins: &[(usize, usize)],
    grid: (usize, usize),
    nlev: usize,
    wg: u32,
) -> Option<CostVolPlan> {
    if nlev != 1 || choice.mode == Some(false) {
        return None;
    }
    let budget = limits.max_compute_workgroup_storage_size;
    let plan = plan_cost_volume(origins, grid, (p.block, p.radius), wg, budget, choice.tile, dx_quads_enabled())?;
    let (rows, cols) = grid;
    let step = |pos: Vec<usize>| pos.windows(2).map(|w| w[1] - w[0]).max();
    let overlap = |s: Option<usize>| s.is_some_and(|s| p.block >= 2 * s.max(1));
    let dense = overlap(step((0..cols).map(|c| origins[c].0).collect()))
        && overlap(step((0..rows).map(|r| origins[r * cols].1).collect()));
    let nd = 2 * plan.shape.radius + 1;
    let bytes = 4 * u64::from(nd * nd) * origins.len() as u64;
    let max_dim = limits.max_compute_workgroups_per_dimension;
    let fits = bytes <= limits.max_storage_buffer_binding_size.min(limits.max_buffer_size)
        && plan.ntc <= max_dim
        && plan.ntr <= max_dim
        && nd <= max_dim;
    (fits && (dense || choice.mode == Some(true))).then_some(plan)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `costvol.wgsl` run on the CPU from a plan's tile table (phases 1 and 2, one tile and one
    /// dy at a time), for checking the table against direct SADs.
    fn simulate(
        plan: &CostVolPlan,
        origins: &[(usize, usize)],
        cols: usize,
        a: &[u8],
        b: &[u8],
        (w, h): (usize, usize),
    ) -> Vec<Vec<u32>> {
        let s = plan.shape;
        let (r, nd) = (s.radius as i32, 2 * s.radius + 1);
        let t = &plan.table;
        let mut costs = vec![vec![u32::MAX; (nd * nd) as usize]; origins.len()];
        for tr in 0..plan.ntr {
            for tc in 0..plan.ntc {
                let cb = (tc * CV_CST) as usize;
                let rb = (s.rowbase + tr * cv_rst(s.tr)) as usize;
                let (x0t, rw, ncv) = (t[cb], t[cb + 1], t[cb + 2]);
                let (y0t, rh, nrv, nev) = (t[rb], t[rb + 1], t[rb + 2], t[rb + 3]);
                for dy in -r..=r {
                    for dx in -r..=r {
                        // phase 1: V[x][r]
                        let mut v = vec![0u32; (rw * s.tr) as usize];
                        for xl in 0..rw {
                            let (ax, bx) = (x0t + xl, (x0t + xl) as i32 + dx);
                            let (mut sum, mut y) = (0u32, 0u32);
                            for e in 0..nev {
                                let ev = t[rb + 4 + e as usize];
                                while y < (ev >> 12).min(rh) {
                                    let ay = y0t + y;
                                    let by = ay as i32 + dy;
                                    let pa = a[ay as usize * w + ax as usize];
                                    let pb = if bx < 0 || by < 0 || bx >= w as i32 || by >= h as i32 {
                                        0
                                    } else {
                                        b[by as usize * w + bx as usize]
                                    };
                                    sum += u32::from(pa.abs_diff(pb));
                                    y += 1;
                                }
                                let k = (xl * s.tr + ((ev >> 1) & 2047)) as usize;
                                v[k] = if ev & 1 == 0 { sum } else { sum - v[k] };
                            }
                        }
                        // phase 2
                        for rr in 0..nrv {
                            for c in 0..ncv {
                                let bi = (tr * s.tr + rr) as usize * cols + (tc * s.tc + c) as usize;
                                let (ox, oy) = origins[bi];
                                let win = crate::flow::cpu::Window::new(ox, oy, s.block as usize, w, h, (0, 0), r);
                                if !win.contains((dx, dy)) {
                                    continue;
                                }
                                let xl = ox as u32 - x0t;
                                assert!(xl + s.block <= rw);
                                let sum = (0..s.block).map(|i| v[((xl + i) * s.tr + rr) as usize]).sum();
                                costs[bi][(dy - win.lo.1) as usize * win.width() + (dx - win.lo.0) as usize] = sum;
                            }
                        }
                    }
                }
            }
        }
        costs
    }

    #[test]
    fn cost_volume_plan_gives_the_direct_sads() {
        let mut seed = 12345u64;
        let mut rnd = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 24) as u8
        };
        for (w, h, stride, block, radius) in
            [(75usize, 67usize, 8usize, 18usize, 3usize), (64, 48, 4, 13, 2), (70, 67, 8, 32, 4)]
        {
            let p = FlowParams { stride: Some(stride), block, radius, ..FlowParams::default() };
            let (rows, cols) = p.grid(w, h);
            let origins = crate::flow::block_origins(&p, w, h);
            let a: Vec<u8> = (0..w * h).map(|_| rnd()).collect();
            let b: Vec<u8> = (0..w * h).map(|_| rnd()).collect();
            // A small budget forces small groups; the planner must still cover everything.
            let forced = [Some((1, 1, 1)), Some((3, 5, 2)), Some((16, 2, 4))];
            let budgets = [(16384, None), (2048, None)].into_iter().chain(forced.map(|f| (16384, f)));
            for ((budget, force), dq) in budgets.flat_map(|b| [(b, false), (b, true)]) {
                let plan =
                    plan_cost_volume(&origins, (rows, cols), (block, radius), 256, budget, force, dq).expect("plan");
                let costs = simulate(&plan, &origins, cols, &a, &b, (w, h));
                for (bi, &(ox, oy)) in origins.iter().enumerate() {
                    let win = crate::flow::cpu::Window::new(ox, oy, block, w, h, (0, 0), radius as i32);
                    for dy in win.lo.1..=win.hi.1 {
                        for dx in win.lo.0..=win.hi.0 {
                            let sad: u32 = (0..block)
                                .flat_map(|y| (0..block).map(move |x| (x, y)))
                                .map(|(x, y)| {
                                    let pa = a[(oy + y) * w + ox + x];
                                    let pb = b[((oy + y) as i32 + dy) as usize * w + ((ox + x) as i32 + dx) as usize];
                                    u32::from(pa.abs_diff(pb))
                                })
                                .sum();
                            assert_eq!(
                                costs[bi][(dy - win.lo.1) as usize * win.width() + (dx - win.lo.0) as usize],
                                sad,
                                "{w}x{h} block {bi} d ({dx}, {dy}) {plan:?}"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn cost_volume_plan_at_720p_dense() {
        let p = FlowParams { stride: Some(8), ..FlowParams::default() };
        let origins = crate::flow::block_origins(&p, 1280, 720);
        let plan = plan_cost_volume(&origins, (88, 160), (32, 16), 256, 49152, None, false).expect("plan");
        eprintln!(
            "720p dense plan (48 KiB workgroup memory): {:?}, {} x {} tiles, {} absolute differences per pair",
            plan.shape, plan.ntc, plan.ntr, plan.abs_diffs
        );
        // 16 × 8 blocks (the fastest measured on an H200), V per quad of columns, 6 dx per group
        // (6 · 38 invocations walk in phase 1)
        let s = plan.shape;
        assert_eq!((s.tc, s.tr, s.g, s.quads, s.wg), (16, 8, 6, true, 256));
        // far below the per-block kernel's 14 080 · 1089 · 1024 = 15.7 G
        assert!(plan.abs_diffs < 2_500_000_000, "{}", plan.abs_diffs);
        // a window of 3 candidates per side with quads of dx: no group of 4 fits in the
        // planner's first pass, and the serial-step model still plans it
        let small = FlowParams { stride: Some(8), radius: 1, ..FlowParams::default() };
        let o = crate::flow::block_origins(&small, 1280, 720);
        assert!(plan_cost_volume(&o, (88, 160), (32, 1), 256, 49152, None, true).is_some());
        // with quads of dx: 9 quads of dx in two groups of at most 5 (5 · 38 = 190 walks, in
        // workgroups of 192), the same tiles and absolute differences
        let dq = plan_cost_volume(&origins, (88, 160), (32, 16), 256, 49152, None, true).expect("plan");
        let s = dq.shape;
        assert_eq!((s.tc, s.tr, s.g, s.dx_quads, s.wg), (16, 8, 20, true, 192));
        assert_eq!(dq.abs_diffs, plan.abs_diffs);
    }
}
