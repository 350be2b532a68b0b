//! The CPU block-matching engine: exact results of the algorithm contract (`docs/flow.md`,
//! written out literally in [`super::reference`]) at a fraction of the exhaustive cost.
//!
//! Where the speed comes from, without shrinking the work the contract defines:
//! - each frame is prefiltered once ([`super::prefilter::highpass`]), so the per-candidate cost
//!   is a byte SAD that runs on `vpsadbw` ([`super::sad`]);
//! - the block of A is copied into a contiguous buffer, the window of B is read in place;
//! - early termination: a candidate is abandoned as soon as its partial SAD exceeds
//!   (1 + ambiguity_ratio) × the best full cost so far. Before the raster scan, the window
//!   centre and the results of the left and upper neighbour blocks are evaluated, so the bound
//!   is tight from the start (flow is smooth). Abandoned candidates provably cannot be the best,
//!   tie with it, or be an ambiguity competitor, so the result equals the exhaustive search;
//! - before its SAD, each candidate's lower bound from 4×4 cell sums ([`super::sea`]) is
//!   compared with the same limit, sixteen candidates at a time: most are abandoned there.

use super::prefilter::{self, Scratch};
use super::sad::{self, Kernel};
use super::sea::{self, CellSums};
use super::{FlowEngine, FlowError, FlowField, FlowParams, FlowVector, Validity};
use hal::LumaImage;
use std::sync::atomic::{AtomicUsize, Ordering};

/// A candidate that was abandoned by early termination: its cost exceeds the bound.
const ABANDONED: u32 = u32::MAX;
/// A candidate not evaluated yet.
const PENDING: u32 = u32::MAX - 1;

/// Buffers of one pyramid level (level 0 = full resolution; its raw frames are the inputs).
#[derive(Debug, Default)]
struct Level {
    raw_a: LumaImage,
    raw_b: LumaImage,
    hp_a: LumaImage,
    hp_b: LumaImage,
    /// The 4×4 cell sums of `hp_b`, for the SAD lower bound ([`super::sea`]); empty when the
    /// level's block is not a multiple of 4 pixels.
    cells_b: CellSums,
}

/// The CPU engine. Construct once, call [`FlowEngine::compute`] per frame pair; all buffers are
/// kept and reused while the frame size stays the same.
#[derive(Debug)]
pub struct CpuFlow {
    params: FlowParams,
    kernel: Kernel,
    /// SAD kernel per pyramid level (the block shrinks at coarser levels).
    kernels: Vec<Kernel>,
    levels: Vec<Level>,
    scratch: Scratch,
    origins: Vec<(usize, usize)>,
    /// The frame size `origins` was placed for.
    origins_size: Option<(usize, usize)>,
    disp: Vec<(i32, i32)>,
    flags: Vec<(bool, bool)>,
    /// One per thread ([`Sweeps`]): thread 0 is the calling thread.
    bufs: Vec<ThreadBufs>,
    sweeps: Sweeps,
    /// The worker threads for more than one thread (`FlowParams::cpu_threads`).
    pool: Option<rayon::ThreadPool>,
    field: FlowField,
}

/// One thread's buffers.
#[derive(Debug, Default)]
struct ThreadBufs {
    block_buf: Vec<u8>,
    /// The cell sums of the block in `block_buf`.
    block_cells: Vec<u16>,
    costs: Vec<u32>,
    out: RowsOut,
}

/// The block rows one thread searched at the level in progress, in the order it claimed them;
/// copied into the engine's level-wide buffers once every thread is done, so that no thread
/// writes where another reads.
#[derive(Debug, Default)]
struct RowsOut {
    rows: Vec<usize>,
    /// `cols` entries per claimed row.
    disp: Vec<(i32, i32)>,
    flags: Vec<(bool, bool)>,
    /// Level 0 only.
    vectors: Vec<FlowVector>,
}

impl RowsOut {
    fn clear(&mut self) {
        self.rows.clear();
        self.disp.clear();
        self.flags.clear();
        self.vectors.clear();
    }

    /// Writes the claimed rows into the level-wide buffers.
    fn scatter(&self, cols: usize, disp: &mut [(i32, i32)], flags: &mut [(bool, bool)], vectors: &mut [FlowVector]) {
        for (k, &r) in self.rows.iter().enumerate() {
            let (src, dst) = (k * cols..(k + 1) * cols, r * cols..(r + 1) * cols);
            disp[dst.clone()].copy_from_slice(&self.disp[src.clone()]);
            flags[dst.clone()].copy_from_slice(&self.flags[src.clone()]);
            if !self.vectors.is_empty() {
                vectors[dst].clone_from_slice(&self.vectors[src]);
            }
        }
    }
}

/// What every block of one pyramid level shares.
struct LevelJob<'a> {
    params: &'a FlowParams,
    lev: &'a Level,
    l: usize,
    coarsest: bool,
    kernel: Kernel,
    origins: &'a [(usize, usize)],
    /// The coarser level's displacements (all blocks).
    prev: &'a [(i32, i32)],
    /// The edge and ambiguity flags of the coarser levels (all blocks).
    flags: &'a [(bool, bool)],
    rows: usize,
    cols: usize,
}

impl CpuFlow {
    /// An engine for `params` (validated here).
    pub fn new(params: FlowParams) -> Result<Self, FlowError> {
        params.validate()?;
        let kernel = Kernel::detect(params.block);
        let mut engine = Self::with_kernel(params, kernel);
        engine.set_threads(engine.params.cpu_threads)?;
        Ok(engine)
    }

    /// Splits each frame pair over `threads` threads (0 = one per core, up to 4): the calling
    /// thread and `threads − 1` workers. The result is the same for any count. Errors only when
    /// the workers cannot be started.
    pub fn set_threads(&mut self, threads: usize) -> Result<(), FlowError> {
        let n = if threads == 0 { std::thread::available_parallelism().map_or(1, |n| n.get().min(4)) } else { threads };
        self.pool = if n > 1 {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(n - 1)
                .thread_name(|i| format!("flownav-flow-{i}"))
                .build()
                .map_err(|e| FlowError::Threads { threads: n, message: e.to_string() })?;
            Some(pool)
        } else {
            None
        };
        self.bufs.resize_with(n, ThreadBufs::default);
        Ok(())
    }

    /// Like [`CpuFlow::new`] with an explicit SAD kernel (tests and benchmarks compare them).
    /// Panics when `kernel` cannot run blocks of `params.block` on this CPU.
    pub fn with_kernel(params: FlowParams, kernel: Kernel) -> Self {
        assert!(kernel.supports(params.block), "SAD kernel {kernel:?} cannot run {} px blocks here", params.block);
        let nlev = params.pyramid_levels.max(1);
        let levels = (0..nlev).map(|_| Level::default()).collect();
        let kernels = (0..nlev)
            .map(|l| {
                let b = super::level_block(params.block, l);
                if kernel.supports(b) { kernel } else { Kernel::detect(b).min_with(kernel) }
            })
            .collect();
        Self {
            params,
            kernel,
            kernels,
            levels,
            scratch: Scratch::default(),
            origins: Vec::new(),
            origins_size: None,
            disp: Vec::new(),
            flags: Vec::new(),
            bufs: vec![ThreadBufs::default()],
            sweeps: Sweeps::default(),
            pool: None,
            field: FlowField::default(),
        }
    }

    /// The SAD kernel in use.
    pub fn kernel(&self) -> Kernel {
        self.kernel
    }

    /// The last computed field.
    pub fn field(&self) -> &FlowField {
        &self.field
    }
}

impl FlowEngine for CpuFlow {
    fn name(&self) -> &'static str {
        "cpu"
    }

    fn params(&self) -> &FlowParams {
        &self.params
    }

    fn threads(&self) -> usize {
        self.bufs.len()
    }

    fn compute(&mut self, a: &LumaImage, b: &LumaImage) -> Result<&FlowField, FlowError> {
        super::check_frames(&self.params, a, b)?;
        let p = &self.params;
        let (w, h) = (a.width(), a.height());
        let nlev = self.levels.len();

        // Pyramid and prefilter: each frame once per level.
        for l in 0..nlev {
            let (done, rest) = self.levels.split_at_mut(l);
            let lev = &mut rest[0];
            let (src_a, src_b) = if l == 0 {
                (a, b)
            } else {
                let prev = &done[l - 1];
                let (ra, rb) = if l == 1 { (a, b) } else { (&prev.raw_a, &prev.raw_b) };
                prefilter::downsample(ra, &mut lev.raw_a);
                prefilter::downsample(rb, &mut lev.raw_b);
                (&lev.raw_a, &lev.raw_b)
            };
            prefilter::highpass(src_a, p.prefilter_radius, &mut lev.hp_a, &mut self.scratch);
            prefilter::highpass(src_b, p.prefilter_radius, &mut lev.hp_b, &mut self.scratch);
            if super::level_block(p.block, l).is_multiple_of(sea::CELL) {
                lev.cells_b.compute(&lev.hp_b);
            }
        }

        if self.origins_size != Some((w, h)) {
            self.origins = super::block_origins(p, w, h);
            self.origins_size = Some((w, h));
        }
        let n = self.origins.len();
        self.disp.clear();
        self.disp.resize(n, (0, 0));
        self.flags.clear();
        self.flags.resize(n, (false, false));
        let (rows, cols) = p.grid(w, h);
        self.field.rows = rows;
        self.field.cols = cols;
        self.field.width = w;
        self.field.height = h;
        // Every entry is written at level 0; this only sets the length.
        self.field.vectors.resize(n, FlowVector::from_match((0, 0), p.block, (0, 0), (0.0, 0.0), Validity::Valid, 0));
        for l in (0..nlev).rev() {
            self.sweeps.reset(rows, self.bufs.len());
            let job = LevelJob {
                params: p,
                lev: &self.levels[l],
                l,
                coarsest: l == nlev - 1,
                kernel: self.kernels[l],
                origins: &self.origins,
                // The threads write into their own buffers, so the coarser level's result
                // stays in place until the level is done.
                prev: &self.disp,
                flags: &self.flags,
                rows,
                cols,
            };
            let sweeps = &self.sweeps;
            match &self.pool {
                // The first sweep on this thread, the others on the workers.
                Some(pool) => pool.in_place_scope(|scope| {
                    let mut all = self.bufs.iter_mut().enumerate();
                    let mine = all.next();
                    for (t, bufs) in all {
                        let job = &job;
                        scope.spawn(move |_| sweeps.run(t, job, bufs));
                    }
                    if let Some((t, bufs)) = mine {
                        sweeps.run(t, &job, bufs);
                    }
                }),
                None => sweeps.run(0, &job, &mut self.bufs[0]),
            }
            for bufs in &self.bufs {
                bufs.out.scatter(cols, &mut self.disp, &mut self.flags, &mut self.field.vectors);
            }
        }
        Ok(&self.field)
    }
}

/// How the block rows of one level are shared among the threads. The rows are cut into
/// segments, one per pair of threads; in each segment one thread claims rows from the top down
/// and the other from the bottom up until they meet. A thread that starts late (a worker woken
/// from sleep when frames come 33 ms apart can take milliseconds) leaves its rows to its partner
/// instead of making it wait, and each thread takes its predictor from the row it searched
/// before, so only a segment's first row on each side searches without one.
#[derive(Debug, Default)]
struct Sweeps {
    /// Per segment: its first row, its row count, and how many rows were claimed.
    segments: Vec<(usize, usize, AtomicUsize)>,
}

impl Sweeps {
    /// Cuts `rows` into segments for `threads` threads, none claimed yet (allocates only when
    /// the thread count changes).
    fn reset(&mut self, rows: usize, threads: usize) {
        let count = threads.div_ceil(2).max(1);
        self.segments.resize_with(count, || (0, 0, AtomicUsize::new(0)));
        let bounds = |k: usize| k * rows / count;
        for (k, (first, len, claimed)) in self.segments.iter_mut().enumerate() {
            (*first, *len) = (bounds(k), bounds(k + 1) - bounds(k));
            *claimed.get_mut() = 0;
        }
    }

    /// Thread `t`'s share: the rows it claims in its segment, from its end, until none is left.
    fn run(&self, t: usize, job: &LevelJob, bufs: &mut ThreadBufs) {
        let (first, len, claimed) = &self.segments[t / 2];
        let down = t.is_multiple_of(2);
        let cols = job.cols;
        let ThreadBufs { block_buf, block_cells, costs, out } = bufs;
        out.clear();
        for k in 0..*len {
            if claimed.fetch_add(1, Ordering::Relaxed) >= *len {
                break;
            }
            let r = if down { first + k } else { first + len - 1 - k };
            out.rows.push(r);
            out.flags.extend_from_slice(&job.flags[r * cols..(r + 1) * cols]);
            let start = out.disp.len();
            out.disp.resize(start + cols, (0, 0));
            let (before, row_disp) = out.disp.split_at_mut(start);
            // The row this thread searched just before is adjacent to this one.
            let adjacent = (k > 0).then(|| &before[start - cols..]);
            let row_flags = &mut out.flags[start..];
            let vectors = if job.l == 0 {
                out.vectors
                    .resize(start + cols, FlowVector::from_match((0, 0), 0, (0, 0), (0.0, 0.0), Validity::Valid, 0));
                Some(&mut out.vectors[start..])
            } else {
                None
            };
            job.run(
                r,
                RowSlices { disp: row_disp, flags: row_flags, vectors },
                adjacent,
                block_buf,
                block_cells,
                costs,
            );
        }
    }
}

/// The outputs of one block row at the level being searched.
struct RowSlices<'a> {
    disp: &'a mut [(i32, i32)],
    /// The coarser levels' flags on entry.
    flags: &'a mut [(bool, bool)],
    /// Level 0 only.
    vectors: Option<&'a mut [FlowVector]>,
}

impl LevelJob<'_> {
    /// Searches the blocks of row `r` at this level; `adjacent` holds the displacements of the
    /// row above or below, when this thread searched it just before.
    fn run(
        &self,
        r: usize,
        row: RowSlices,
        adjacent: Option<&[(i32, i32)]>,
        block_buf: &mut Vec<u8>,
        block_cells: &mut Vec<u16>,
        costs: &mut Vec<u32>,
    ) {
        let (p, lev, l, cols) = (self.params, self.lev, self.l, self.cols);
        let bs = p.block;
        let (wl, hl) = (lev.hp_a.width(), lev.hp_a.height());
        let radius = if self.coarsest { p.radius } else { p.refine_radius } as i32;
        let bl = super::level_block(bs, l);
        let kernel = self.kernel;
        let amb_q8 = p.ambiguity_q8();
        block_buf.resize(bs * bs, 0);
        let RowSlices { disp, flags: row_flags, mut vectors } = row;
        for c in 0..cols {
            let i = r * cols + c;
            let (ox, oy) = self.origins[i];
            let x0 = level_origin(ox, bs, bl, l, wl);
            let y0 = level_origin(oy, bs, bl, l, hl);
            let centre = if self.coarsest {
                (0, 0)
            } else {
                let m = median3x3(self.prev, self.rows, cols, r, c);
                (2 * m.0, 2 * m.1)
            };
            let win = Window::new(x0, y0, bl, wl, hl, centre, radius);
            let blk = &mut block_buf[..bl * bl];
            copy_block(&lev.hp_a, x0, y0, bl, blk);
            let mut preds = [None; 3];
            preds[0] = Some(win.centre);
            if c > 0 {
                preds[1] = Some(disp[c - 1]);
            }
            if let Some(adjacent) = adjacent {
                preds[2] = Some(adjacent[c]);
            }
            // The sums exist only for levels whose block is a whole number of cells.
            let cells = if lev.cells_b.width() > 0 {
                sea::block_cells(blk, bl, block_cells);
                Some((&lev.cells_b, &block_cells[..]))
            } else {
                None
            };
            let query = Query { a: blk, b: &lev.hp_b, x0, y0, block: bl, win, preds, amb_q8, cells };
            let found = search(kernel, &query, costs);
            disp[c] = found.d;
            let flags = &mut row_flags[c];
            flags.0 |= found.edge;
            flags.1 |= found.ambiguous;
            if let Some(vectors) = vectors.as_deref_mut() {
                let st = level0_stats(kernel, block_buf, &lev.hp_b, x0, y0, bs, &win, found.d);
                let textureless = 16 * st.texture < p.min_texture_q4() * (2 * bs * (bs - 1)) as u64;
                let [xm, xp, ym, yp] = st.ssd_neighbours;
                let sub = (parabola(xm, st.ssd, xp), parabola(ym, st.ssd, yp));
                let validity = Validity::of(textureless, flags.0, flags.1);
                vectors[c] = FlowVector::from_match((ox, oy), bs, found.d, sub, validity, found.cost);
            }
        }
    }
}

/// Top-left coordinate of a block at pyramid level `l`: its level-0 centre pixel (o + B/2)
/// halved `l` times, minus B_l/2, clamped into [0, len_l − B_l].
pub(crate) fn level_origin(o: usize, block: usize, block_l: usize, l: usize, len_l: usize) -> usize {
    ((o + block / 2) >> l).saturating_sub(block_l / 2).min(len_l - block_l)
}

/// Component-wise median of the displacements of block (r, c) and its grid neighbours
/// (3×3, cut at the grid edge: 4, 6 or 9 values; the lower median for an even count).
pub(crate) fn median3x3(d: &[(i32, i32)], rows: usize, cols: usize, r: usize, c: usize) -> (i32, i32) {
    let (mut xs, mut ys) = ([0i32; 9], [0i32; 9]);
    let mut n = 0;
    for rr in r.saturating_sub(1)..=(r + 1).min(rows - 1) {
        for cc in c.saturating_sub(1)..=(c + 1).min(cols - 1) {
            (xs[n], ys[n]) = d[rr * cols + cc];
            n += 1;
        }
    }
    xs[..n].sort_unstable();
    ys[..n].sort_unstable();
    (xs[(n - 1) / 2], ys[(n - 1) / 2])
}

/// The candidate displacements of one block at one level: [lo, hi] in x and y.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Window {
    /// The window centre after clamping into the feasible displacements (tie-break origin).
    pub centre: (i32, i32),
    pub lo: (i32, i32),
    pub hi: (i32, i32),
}

impl Window {
    /// Displacements d with |d − centre|∞ ≤ radius whose block at (x0+dx, y0+dy) lies inside
    /// the `w`×`h` frame B; `centre` is first clamped to the feasible range so the window is never
    /// empty.
    pub fn new(x0: usize, y0: usize, block: usize, w: usize, h: usize, centre: (i32, i32), radius: i32) -> Self {
        let fmin = (-(x0 as i32), -(y0 as i32));
        let fmax = ((w - block - x0) as i32, (h - block - y0) as i32);
        let cx = centre.0.clamp(fmin.0, fmax.0);
        let cy = centre.1.clamp(fmin.1, fmax.1);
        Self {
            centre: (cx, cy),
            lo: ((cx - radius).max(fmin.0), (cy - radius).max(fmin.1)),
            hi: ((cx + radius).min(fmax.0), (cy + radius).min(fmax.1)),
        }
    }

    pub fn width(&self) -> usize {
        (self.hi.0 - self.lo.0 + 1) as usize
    }

    pub fn contains(&self, d: (i32, i32)) -> bool {
        (self.lo.0..=self.hi.0).contains(&d.0) && (self.lo.1..=self.hi.1).contains(&d.1)
    }

    fn index(&self, d: (i32, i32)) -> usize {
        (d.1 - self.lo.1) as usize * self.width() + (d.0 - self.lo.0) as usize
    }

    /// Tie-break key: smaller squared distance to the centre, then smaller dy, then smaller dx.
    pub fn key(&self, d: (i32, i32)) -> (i32, i32, i32) {
        let (ex, ey) = (d.0 - self.centre.0, d.1 - self.centre.1);
        (ex * ex + ey * ey, d.1, d.0)
    }
}

/// Result of one block's search at one level.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Found {
    pub d: (i32, i32),
    pub cost: u32,
    pub edge: bool,
    pub ambiguous: bool,
}

/// Copies the `block`×`block` block at (x0, y0) of `img` into `out` (rows contiguous).
pub(crate) fn copy_block(img: &LumaImage, x0: usize, y0: usize, block: usize, out: &mut [u8]) {
    // The common sides as constants: a row is then a few register moves, not a call to memcpy
    // (one per row of every block, thousands per frame pair).
    match block {
        32 => copy_rows::<32>(img, x0, y0, out),
        16 => copy_rows::<16>(img, x0, y0, out),
        _ => {
            for (y, dst) in out.chunks_exact_mut(block).take(block).enumerate() {
                dst.copy_from_slice(&img.row(y0 + y)[x0..x0 + block]);
            }
        }
    }
}

fn copy_rows<const B: usize>(img: &LumaImage, x0: usize, y0: usize, out: &mut [u8]) {
    for (y, dst) in out.chunks_exact_mut(B).take(B).enumerate() {
        dst[..B].copy_from_slice(&img.row(y0 + y)[x0..x0 + B]);
    }
}

/// Level-0 block statistics: texture (gradient energy) and the SSDs for the sub-pixel fit.
pub(crate) struct Stats {
    pub texture: u64,
    /// SSD at the best displacement.
    pub ssd: u64,
    /// SSD at d − (1,0), d + (1,0), d − (0,1), d + (0,1); `None` outside the window.
    pub ssd_neighbours: [Option<u64>; 4],
}

/// [`Stats`] of the block `a` at (x0, y0) matched at `d` in `b`; on 256-bit vectors when the
/// search kernel is AVX2 (the same integers).
#[allow(clippy::too_many_arguments)]
fn level0_stats(
    kernel: Kernel,
    a: &[u8],
    b: &LumaImage,
    x0: usize,
    y0: usize,
    block: usize,
    win: &Window,
    d: (i32, i32),
) -> Stats {
    #[cfg(target_arch = "x86_64")]
    if kernel == Kernel::Avx2 {
        // SAFETY: an AVX2 kernel is only constructed where the CPU supports AVX2, for blocks
        // whose width is a multiple of 32.
        return unsafe { level0_stats_avx2(a, b, x0, y0, block, win, d) };
    }
    let _ = kernel;
    let (stride, data) = (b.width(), b.data());
    let ssd_at = |e: (i32, i32)| sad::ssd_scalar(a, data, window_offset(x0, y0, stride, e), stride, block);
    Stats {
        texture: sad::texture_scalar(a, block),
        ssd: ssd_at(d),
        ssd_neighbours: neighbours(win, d).map(|e| e.map(ssd_at)),
    }
}

/// # Safety
/// The CPU must support AVX2 and `block.is_multiple_of(32)`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn level0_stats_avx2(
    a: &[u8],
    b: &LumaImage,
    x0: usize,
    y0: usize,
    block: usize,
    win: &Window,
    d: (i32, i32),
) -> Stats {
    let (stride, data) = (b.width(), b.data());
    assert!(a.len() >= block * block, "block buffer too small");
    // Every displacement asked for lies in the window, whose blocks are all inside frame B.
    assert!(window_offset(x0, y0, stride, win.hi) + (block - 1) * stride + block <= data.len());
    // A macro, not a closure, so that the vector code inlines into this AVX2-enabled function.
    macro_rules! ssd_at {
        ($e:expr) => {
            // SAFETY: AVX2 and the block width are the caller's contract; the reads lie inside
            // `a` and `data` (asserted above; only displacements in the window are asked for).
            unsafe { sad::avx2::ssd(a.as_ptr(), data.as_ptr().add(window_offset(x0, y0, stride, $e)), stride, block) }
        };
    }
    let mut ssd_neighbours = [None; 4];
    for (out, e) in ssd_neighbours.iter_mut().zip(neighbours(win, d)) {
        if let Some(e) = e {
            *out = Some(ssd_at!(e));
        }
    }
    // SAFETY: as above, for the block `a`.
    let texture = unsafe { sad::avx2::texture(a.as_ptr(), block) };
    Stats { texture, ssd: ssd_at!(d), ssd_neighbours }
}

/// Byte offset in frame B (rows `stride` apart) of the block at (x0, y0) moved by `d`.
#[inline(always)]
fn window_offset(x0: usize, y0: usize, stride: usize, d: (i32, i32)) -> usize {
    (y0 as i32 + d.1) as usize * stride + (x0 as i32 + d.0) as usize
}

/// d − (1,0), d + (1,0), d − (0,1), d + (0,1) where they lie in the window.
#[inline(always)]
fn neighbours(win: &Window, d: (i32, i32)) -> [Option<(i32, i32)>; 4] {
    [(d.0 - 1, d.1), (d.0 + 1, d.1), (d.0, d.1 - 1), (d.0, d.1 + 1)].map(|e| win.contains(e).then_some(e))
}

/// Sub-pixel offset along one axis by a parabola through the SSD at −1, 0, +1:
/// δ = (s₋ − s₊) / (2 (s₋ − 2s₀ + s₊)) when both neighbours lie in the window, s₀ > 0 (zero is
/// an exact match: the blocks are identical) and the denominator is positive, else 0;
/// clamped to [−0.5, 0.5].
pub(crate) fn parabola(sm: Option<u64>, s0: u64, sp: Option<u64>) -> f64 {
    match (sm, sp) {
        (Some(m), Some(p)) if s0 > 0 => {
            let (m, s0, p) = (m as i64, s0 as i64, p as i64);
            let den = m - 2 * s0 + p;
            if den > 0 { ((m - p) as f64 / (2 * den) as f64).clamp(-0.5, 0.5) } else { 0.0 }
        }
        _ => 0.0,
    }
}

/// One block's search at one level: the block `a` (prefiltered, rows contiguous) at (x0, y0)
/// in frame A, searched for in `b` (prefiltered frame B of the same level) over `win`.
pub(crate) struct Query<'a> {
    pub a: &'a [u8],
    pub b: &'a LumaImage,
    pub x0: usize,
    pub y0: usize,
    pub block: usize,
    pub win: Window,
    /// Displacements evaluated first to tighten the early-termination bound.
    pub preds: [Option<(i32, i32)>; 3],
    pub amb_q8: u64,
    /// Frame B's cell sums and the block's, for the lower bound that skips candidates.
    pub cells: Option<(&'a CellSums, &'a [u16])>,
}

/// Searches with the given kernel; see the module docs for why early termination gives the
/// exhaustive answer.
fn search(kernel: Kernel, q: &Query, costs: &mut Vec<u32>) -> Found {
    assert!(kernel.supports(q.block), "kernel {kernel:?} cannot run {} px blocks", q.block);
    match kernel {
        // SAFETY: AVX2 support was checked just above.
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx2 => unsafe { search_avx2(q, costs) },
        // SAFETY: AVX2 support is checked in the condition.
        #[cfg(target_arch = "x86_64")]
        Kernel::Sse2 if std::arch::is_x86_feature_detected!("avx2") => unsafe { search_sse2_avx2_bound(q, costs) },
        #[cfg(target_arch = "x86_64")]
        Kernel::Sse2 => search_with::<sad::Sse2Sad, sea::ScalarBound>(q, costs),
        _ => search_with::<sad::ScalarSad, sea::ScalarBound>(q, costs),
    }
}

/// [`search_with`] compiled with AVX2 enabled, so that the AVX2 kernel inlines into the loop.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn search_avx2(q: &Query, costs: &mut Vec<u32>) -> Found {
    search_with::<sad::Avx2Sad, sea::Avx2Bound>(q, costs)
}

/// The SSE2 SAD (blocks a multiple of 16 but not of 32 px, such as a 32 px block's coarser
/// pyramid level) with the AVX2 lower bound, on CPUs that have AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn search_sse2_avx2_bound(q: &Query, costs: &mut Vec<u32>) -> Found {
    search_with::<sad::Sse2Sad, sea::Avx2Bound>(q, costs)
}

#[inline(always)]
fn search_with<S: sad::SadFn, L: sea::Bound16>(q: &Query, costs: &mut Vec<u32>) -> Found {
    let (a, b, x0, y0, block, win) = (q.a, q.b, q.x0, q.y0, q.block, &q.win);
    let stride = b.width();
    let data = b.data();
    let gw = win.width();
    let gh = (win.hi.1 - win.lo.1 + 1) as usize;
    costs.clear();
    costs.resize(gw * gh, PENDING);
    // Candidates whose full cost is known, in evaluation order (the rest were abandoned).
    let mut done: [(i32, i32); 64] = [(0, 0); 64];
    let mut ndone = 0usize;
    let mut overflow = false;
    let mut note = |d: (i32, i32)| {
        if ndone < done.len() {
            done[ndone] = d;
            ndone += 1;
        } else {
            overflow = true;
        }
    };
    let offset = |d: (i32, i32)| (y0 as i32 + d.1) as usize * stride + (x0 as i32 + d.0) as usize;
    // Every candidate window lies between these two, all inside frame B.
    assert!(a.len() >= block * block && y0 as i32 + win.lo.1 >= 0 && x0 as i32 + win.lo.0 >= 0);
    assert!(offset(win.hi) + (block - 1) * stride + block <= data.len(), "search window outside frame B");
    // A macro, not a closure: closures do not inherit `search_avx2`'s target features, so the
    // AVX2 kernel would not inline into one.
    macro_rules! sad {
        ($d:expr, $limit:expr) => {
            // SAFETY: the displacement lies in the window, whose blocks are all inside `data`
            // (asserted above), and `search` checked that the CPU supports the kernel.
            unsafe { S::sad(a.as_ptr(), data.as_ptr().add(offset($d)), stride, block, $limit) }
        };
    }
    let bound = |best: u32| (u64::from(best) * (256 + q.amb_q8) / 256).min(u64::from(PENDING - 1)) as u32;

    let mut best = (u32::MAX, (i32::MAX, i32::MAX, i32::MAX), (0, 0));
    let consider = |d: (i32, i32), c: u32, best: &mut (u32, (i32, i32, i32), (i32, i32))| {
        let cand = (c, win.key(d), d);
        if (cand.0, cand.1) < (best.0, best.1) {
            *best = cand;
        }
    };
    for d in q.preds.iter().flatten().copied() {
        if win.contains(d) && costs[win.index(d)] == PENDING {
            let c = sad!(d, u32::MAX).expect("no limit");
            costs[win.index(d)] = c;
            note(d);
            consider(d, c, &mut best);
        }
    }
    // Then the 3×3 neighbourhood of the best predictor: flow varies smoothly, so the minimum is
    // usually there, and a tight bound early lets the lower bound and early termination rule
    // out most of the raster scan.
    let centre = best.2;
    for ny in -1..=1 {
        for nx in -1..=1 {
            let d = (centre.0 + nx, centre.1 + ny);
            if win.contains(d) && costs[win.index(d)] == PENDING {
                let c = sad!(d, u32::MAX).expect("no limit");
                costs[win.index(d)] = c;
                note(d);
                consider(d, c, &mut best);
            }
        }
    }
    let mut limit = bound(best.0);
    // Sixteen candidates of a row at a time are first tested against the cell-sum lower bound:
    // those it rules out are abandoned without a SAD.
    let n = block / sea::CELL;
    // `over16` reads n² cell sums of the block unchecked.
    assert!(q.cells.is_none_or(|(_, cells)| cells.len() >= n * n), "block cell sums missing");
    for dy in win.lo.1..=win.hi.1 {
        let row = (dy - win.lo.1) as usize * gw;
        let mut dx = win.lo.0;
        while dx <= win.hi.0 {
            // The row's last group may be shorter: it is bounded (sixteen lanes, those past the
            // window ignored) when it holds at least 8 candidates and the cell sums extend that
            // far; a shorter remainder costs less as plain SADs (measured: bounding the single
            // 33rd column of each row made the search slower).
            let group = (win.hi.0 - dx + 1).min(16) as usize;
            let over = match q.cells {
                Some((sums, cells)) if group >= 8 => {
                    let at = sums.index((x0 as i32 + dx) as usize, (y0 as i32 + dy) as usize);
                    if sums.holds16(at, n) {
                        // SAFETY: every cell sum read lies in `sums` (checked just above); the
                        // kernel's CPU features were checked with the SAD kernel's.
                        unsafe { L::over16(sums, at, cells, n, limit) }
                    } else {
                        0
                    }
                }
                _ => 0,
            };
            for k in 0..group {
                let (gi, d) = (row + (dx - win.lo.0) as usize + k, (dx + k as i32, dy));
                if costs[gi] != PENDING {
                    continue;
                }
                if over & (1 << k) != 0 {
                    costs[gi] = ABANDONED;
                    continue;
                }
                match sad!(d, limit) {
                    Some(c) => {
                        costs[gi] = c;
                        note(d);
                        consider(d, c, &mut best);
                        limit = bound(best.0);
                    }
                    None => costs[gi] = ABANDONED,
                }
            }
            dx += group as i32;
        }
    }
    let (c1, _, d1) = best;

    let edge = d1.0 == win.lo.0 || d1.0 == win.hi.0 || d1.1 == win.lo.1 || d1.1 == win.hi.1;
    let thr = u64::from(c1) * (256 + q.amb_q8);
    let is_competitor = |d: (i32, i32)| {
        let c = costs[win.index(d)];
        if c == ABANDONED || u64::from(c) * 256 > thr || (d.0 - d1.0).abs().max((d.1 - d1.1).abs()) < 2 {
            return false;
        }
        (-1..=1).all(|ny: i32| {
            (-1..=1).all(|nx: i32| {
                let e = (d.0 + nx, d.1 + ny);
                !win.contains(e) || costs[win.index(e)] >= c
            })
        })
    };
    let ambiguous = if overflow {
        (win.lo.1..=win.hi.1).any(|dy| (win.lo.0..=win.hi.0).any(|dx| is_competitor((dx, dy))))
    } else {
        done[..ndone].iter().any(|&d| is_competitor(d))
    };
    Found { d: d1, cost: c1, edge, ambiguous }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flow::reference::reference_flow;
    use proptest::prelude::*;

    /// Deterministic white-ish noise texture, blurred by a 3×3 box so that it is not pure noise.
    fn texture_fn(seed: u64) -> impl Fn(i64, i64) -> u8 {
        move |x: i64, y: i64| {
            let h = |x: i64, y: i64| {
                let mut v = (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                    ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
                    ^ seed;
                v ^= v >> 29;
                v = v.wrapping_mul(0xBF58_476D_1CE4_E5B9);
                v ^= v >> 32;
                (v & 255) as u32
            };
            let mut s = 0;
            for j in -1..=1 {
                for i in -1..=1 {
                    s += h(x + i, y + j);
                }
            }
            (s / 9) as u8
        }
    }

    /// Frames A and B of a texture translated by (dx, dy): A(x, y) = B(x + dx, y + dy).
    fn translated(w: usize, h: usize, dx: i64, dy: i64, seed: u64) -> (LumaImage, LumaImage) {
        let t = texture_fn(seed);
        let a = LumaImage::from_fn(w, h, |x, y| t(x as i64, y as i64));
        let b = LumaImage::from_fn(w, h, |x, y| t(x as i64 - dx, y as i64 - dy));
        (a, b)
    }

    fn small_params() -> FlowParams {
        FlowParams { rows: 3, cols: 4, block: 16, radius: 6, ..FlowParams::default() }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]

        /// The fast engine (early termination, predictors, SIMD) gives exactly the exhaustive
        /// contract, on translated and on unrelated frames, with and without the pyramid.
        #[test]
        fn equals_reference(seed in any::<u64>(), dx in -9i64..=9, dy in -9i64..=9, k in 0usize..=4,
                            levels in 1usize..=2, unrelated in any::<bool>(), amb in 0u32..3, wide in any::<bool>(),
                            rsel in 0usize..3, refine in 2usize..=8) {
            // 32 px blocks take the AVX2 SAD, 16 px the SSE2 SAD; with AVX2 both take the
            // vector lower bound. Radii up to 16 give rows of several groups of sixteen.
            let block = if wide { 32 } else { 16 };
            let params = FlowParams { prefilter_radius: k, pyramid_levels: levels, refine_radius: refine,
                                      radius: [6, 12, 16][rsel], ambiguity_ratio: [0.0, 0.1, 0.5][amb as usize],
                                      block, ..small_params() };
            let (a, mut b) = translated(96, 72, dx, dy, seed);
            if unrelated {
                b = translated(96, 72, 0, 0, seed ^ 0x55).0;
            }
            let want = reference_flow(&params, &a, &b).unwrap();
            for kernel in [Kernel::detect(block), Kernel::Scalar] {
                let mut eng = CpuFlow::with_kernel(params.clone(), kernel);
                let got = eng.compute(&a, &b).unwrap();
                prop_assert_eq!(got, &want);
            }
        }

        /// An exact integer translation within the radius is recovered exactly (no sub-pixel
        /// residue) by every block whose match lies inside frame B.
        #[test]
        fn integer_translation_is_exact(seed in any::<u64>(), dx in -6i64..=6, dy in -6i64..=6) {
            let params = small_params();
            let (a, b) = translated(96, 72, dx, dy, seed);
            let mut eng = CpuFlow::new(params.clone()).unwrap();
            let f = eng.compute(&a, &b).unwrap();
            let k = params.prefilter_radius as i64;
            for v in &f.vectors {
                let (x0, y0) = (v.x as i64 - 8, v.y as i64 - 8);
                // Inside B, and far enough from both frames' borders that the prefilter window
                // saw the same pixels in A and B (edge replication differs otherwise).
                let inside = |m: i64| x0 + dx >= m && y0 + dy >= m && x0 + dx + 16 + m <= 96 && y0 + dy + 16 + m <= 72;
                let clear = inside(k) && x0 >= k && y0 >= k && x0 + 16 + k <= 96 && y0 + 16 + k <= 72;
                if clear {
                    prop_assert_eq!((v.u, v.v), (dx as f32, dy as f32), "block at {:?}", (v.x, v.y));
                } else if inside(0) {
                    prop_assert_eq!((v.u.round(), v.v.round()), (dx as f32, dy as f32), "block at {:?}", (v.x, v.y));
                }
            }
        }
    }

    /// A smooth texture (sum of sinusoids, sampled exactly) moved by a sub-pixel amount: every
    /// interior block recovers it within 0.1 px.
    #[test]
    fn subpixel_translation_within_tenth_of_pixel() {
        let t = |x: f64, y: f64| {
            128.0
                + 40.0 * (0.42 * x + 0.15 * y).sin()
                + 35.0 * (-0.15 * x + 0.43 * y + 1.0).sin()
                + 25.0 * (0.33 * x - 0.32 * y + 2.0).cos()
        };
        let params = FlowParams { rows: 4, cols: 4, block: 32, radius: 4, ..FlowParams::default() };
        let mut eng = CpuFlow::new(params).unwrap();
        let mut worst = 0.0f64;
        for &(u, v) in &[(0.3, -0.2), (1.45, 0.7), (-2.25, 0.5), (0.1, 0.9), (-0.6, -1.35)] {
            let a = LumaImage::from_fn(192, 192, |x, y| t(x as f64, y as f64).round() as u8);
            let b = LumaImage::from_fn(192, 192, |x, y| t(x as f64 - u, y as f64 - v).round() as u8);
            let f = eng.compute(&a, &b).unwrap().clone();
            for vec in &f.vectors {
                assert!(vec.valid(), "{vec:?}");
                let e = ((f64::from(vec.u) - u).powi(2) + (f64::from(vec.v) - v).powi(2)).sqrt();
                worst = worst.max(e);
                assert!(e < 0.1, "motion ({u}, {v}) estimated ({}, {}), error {e:.3}", vec.u, vec.v);
            }
        }
        eprintln!("worst sub-pixel endpoint error {worst:.3} px");
    }

    /// A flat block (and one with only faint noise) is textureless; a textured one is not.
    #[test]
    fn textureless_block_is_invalid() {
        let tex = texture_fn(7);
        let noise = texture_fn(8);
        let params = FlowParams { rows: 1, cols: 3, block: 32, radius: 4, ..FlowParams::default() };
        // Left third flat, middle third faint noise (±1 grey level), right third textured.
        let img = |shift: i64| {
            let (tex, noise) = (&tex, &noise);
            LumaImage::from_fn(120, 40, move |x, y| match x {
                0..40 => 90,
                40..80 => 90 + (noise(x as i64, y as i64) % 3),
                _ => tex(x as i64 - shift, y as i64),
            })
        };
        let (a, b) = (img(0), img(2));
        let mut eng = CpuFlow::new(params).unwrap();
        let f = eng.compute(&a, &b).unwrap();
        assert_eq!(f.at(0, 0).validity, Validity::Textureless);
        assert_eq!(f.at(0, 1).validity, Validity::Textureless);
        assert_eq!(f.at(0, 2).validity, Validity::Valid);
        assert!((f.at(0, 2).u - 2.0).abs() < 0.05 && f.at(0, 2).v.abs() < 0.05, "{:?}", f.at(0, 2));
    }

    /// A periodic texture whose period is inside the search window is ambiguous.
    #[test]
    fn periodic_texture_is_ambiguous() {
        let params = FlowParams { rows: 1, cols: 1, block: 32, radius: 12, ..FlowParams::default() };
        let a = LumaImage::from_fn(96, 96, |x, y| if (x / 4 + y / 4) % 2 == 0 { 40 } else { 200 });
        let mut eng = CpuFlow::new(params).unwrap();
        assert_eq!(eng.compute(&a, &a).unwrap().at(0, 0).validity, Validity::Ambiguous);
    }

    /// Motion beyond the radius is found with the pyramid; without it the block is flagged.
    /// Bands of block rows on several threads give the field of one thread, bit for bit, with
    /// and without the pyramid (including more threads than rows).
    #[test]
    fn threads_do_not_change_the_field() {
        let t = texture_fn(11);
        let a = LumaImage::from_fn(320, 240, |x, y| t(x as i64, y as i64));
        let b = LumaImage::from_fn(320, 240, |x, y| t(x as i64 - 5 + (y as i64 / 60), y as i64 + 2 - (x as i64 / 100)));
        for levels in [1, 2] {
            let params =
                FlowParams { rows: 7, cols: 5, block: 32, radius: 8, pyramid_levels: levels, ..FlowParams::default() };
            let mut one = CpuFlow::new(FlowParams { cpu_threads: 1, ..params.clone() }).unwrap();
            let want = one.compute(&a, &b).unwrap().clone();
            for threads in [2, 3, 9] {
                let mut many = CpuFlow::new(FlowParams { cpu_threads: threads, ..params.clone() }).unwrap();
                assert_eq!(many.threads(), threads);
                assert_eq!(many.compute(&a, &b).unwrap(), &want, "{threads} threads, {levels} levels");
                // and again with the buffers reused
                assert_eq!(many.compute(&a, &b).unwrap(), &want, "{threads} threads, second pair");
            }
        }
    }

    #[test]
    fn pyramid_finds_motion_beyond_radius() {
        let (a, b) = translated(512, 384, 27, -11, 3);
        let base = FlowParams { rows: 2, cols: 2, block: 32, radius: 8, ..FlowParams::default() };
        let mut single = CpuFlow::new(base.clone()).unwrap();
        let f = single.compute(&a, &b).unwrap();
        assert!(f.vectors.iter().all(|v| v.validity != Validity::Valid || (v.u, v.v) != (27.0, -11.0)));
        let mut pyr = CpuFlow::new(FlowParams { pyramid_levels: 3, ..base }).unwrap();
        let f = pyr.compute(&a, &b).unwrap();
        for v in &f.vectors {
            assert_eq!((v.u, v.v, v.validity), (27.0, -11.0, Validity::Valid), "{v:?}");
        }
    }

    #[test]
    fn bad_frames_give_clear_errors() {
        let mut eng = CpuFlow::new(FlowParams::default()).unwrap();
        let e = eng.compute(&LumaImage::new(640, 480), &LumaImage::new(640, 360)).map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("640x480") && e.contains("640x360"), "{e}");
        let e = eng.compute(&LumaImage::new(20, 20), &LumaImage::new(20, 20)).map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("too small") && e.contains("flow.block"), "{e}");
        let e = eng.compute(&LumaImage::new(0, 0), &LumaImage::new(0, 0)).map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("too small"), "{e}");
        let mut pyr = CpuFlow::new(FlowParams { pyramid_levels: 6, ..FlowParams::default() }).unwrap();
        let e = pyr.compute(&LumaImage::new(200, 200), &LumaImage::new(200, 200)).map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("pyramid level 5") && e.contains("pyramid_levels"), "{e}");
        let tile = FlowParams { placement: crate::flow::Placement::Tile, ..FlowParams::default() };
        let mut eng = CpuFlow::new(tile).unwrap();
        let e = eng.compute(&LumaImage::new(500, 600), &LumaImage::new(500, 600)).map(|_| ()).unwrap_err().to_string();
        assert!(e.contains("512x512") && e.contains("500x600"), "{e}");
        assert!(CpuFlow::new(FlowParams { radius: 0, ..FlowParams::default() }).is_err());
    }

    #[test]
    fn spread_placement_tiles_512_exactly() {
        let o = crate::flow::block_origins(&FlowParams::default(), 512, 512);
        assert_eq!(o.len(), 256);
        for (i, &(x0, y0)) in o.iter().enumerate() {
            assert_eq!((x0, y0), (32 * (i % 16), 32 * (i / 16)));
        }
        let o = crate::flow::block_origins(&FlowParams::default(), 1280, 720);
        assert_eq!((o[0], o[255]), ((24, 6), (1224, 681)));
    }
}
