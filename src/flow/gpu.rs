//! The GPU block-matching engine: the algorithm contract of `docs/flow.md` as wgpu compute
//! shaders (Vulkan, Metal, DX12, GL), with the same integer results as [`super::cpu::CpuFlow`].
//!
//! Per frame pair, one command buffer:
//! 1. the two frames are uploaded once, packed 8-bit (4 pixels per `u32` word, rows padded to
//!    whole words); when frame A equals the previous pair's frame B (a video stream), A's
//!    buffers are reused and only B is uploaded and preprocessed;
//! 2. pyramid (2×2 average) and high-pass prefilter run on the GPU (`shaders/prep.wgsl`,
//!    bit-identical to [`super::prefilter`]);
//! 3. block matching, coarsest level first (`shaders/match.wgsl`): one workgroup per block, the
//!    reference block and the search window of B cached in workgroup memory, every candidate's
//!    exact SAD computed cooperatively, then workgroup reductions for the best candidate
//!    (contract tie-break), the ambiguity test and, at level 0, the texture energy and the five
//!    SSDs of the sub-pixel fit;
//! 4. the level-0 records (10 integers per block) are copied into one of two staging buffers and
//!    mapped; the CPU turns them into a [`FlowField`] with the same f64 parabola as the CPU
//!    engine, so sub-pixel values are identical, not just close.
//!
//! Buffers, bind groups and pipelines are created once per frame size (pipelines once per
//! block/radius shape) and reused. [`GpuFlow::compute`] (the [`FlowEngine`] method) waits for
//! its own result; [`GpuFlow::compute_pipelined`] submits a pair and returns the previous pair's
//! field, so the GPU computes frame n+1 while the CPU consumes frame n (one frame of latency).

use super::{FlowEngine, FlowError, FlowField, FlowParams, FlowVector, Validity};
use hal::LumaImage;
use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex, mpsc};

/// Prepended to every shader below: the level uniform and the pixel unpacking.
const COMMON_WGSL: &str = include_str!("shaders/common.wgsl");
const PREP_WGSL: &str = include_str!("shaders/prep.wgsl");
const MATCH_WGSL: &str = include_str!("shaders/match.wgsl");
const COSTVOL_WGSL: &str = include_str!("shaders/costvol.wgsl");
/// 32-bit words per block in the level-0 result record (see `match.wgsl`).
const RECORD: usize = 10;
/// Workgroup size of the matching shader (capped by the device limit).
const MATCH_WG: u32 = 256;
/// Workgroup size (x) of the preprocessing shaders.
const PREP_WG: u32 = 64;
/// Most candidates one invocation accumulates per band (registers).
const MAX_PER: u32 = 8;
/// Most timed passes per pair (preprocessing, cost volume, one per matching level).
const MAX_TIMED: u32 = 16;
/// Labels of the matching passes per level (`match L0` is the finest).
const MATCH_LABELS: [&str; 8] =
    ["match L0", "match L1", "match L2", "match L3", "match L4", "match L5", "match L6", "match L7"];

/// An adapter, its device and queue, shared by every GPU engine made from it.
pub struct GpuContext {
    info: wgpu::AdapterInfo,
    device: wgpu::Device,
    queue: wgpu::Queue,
    /// The first uncaptured wgpu error (validation, out of memory, device lost), if any.
    error: Arc<Mutex<Option<String>>>,
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuContext").field("adapter", &describe_adapter(&self.info)).finish()
    }
}

/// A wgpu instance honouring `WGPU_BACKEND` (e.g. `vulkan`, `gl`) and the other `WGPU_*`
/// environment variables.
pub fn instance() -> wgpu::Instance {
    wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env())
}

/// Every adapter the instance finds, hardware first (discrete, integrated, others).
pub fn adapters(instance: &wgpu::Instance) -> Vec<wgpu::Adapter> {
    let mut list = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
    list.sort_by_key(|a| adapter_rank(&a.get_info()));
    list
}

/// Whether an adapter is real GPU hardware (not a CPU rasteriser such as llvmpipe/lavapipe or
/// SwiftShader, which are far slower than the CPU engine).
pub fn is_hardware(info: &wgpu::AdapterInfo) -> bool {
    let name = info.name.to_ascii_lowercase();
    let software = ["llvmpipe", "lavapipe", "swiftshader", "softpipe", "warp"].iter().any(|s| name.contains(s));
    matches!(info.device_type, wgpu::DeviceType::DiscreteGpu | wgpu::DeviceType::IntegratedGpu) && !software
}

fn adapter_rank(info: &wgpu::AdapterInfo) -> u8 {
    match info.device_type {
        _ if !is_hardware(info) => 3,
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        _ => 2,
    }
}

/// "NAME (TYPE, BACKEND, driver DRIVER)" for logs and reports.
pub fn describe_adapter(info: &wgpu::AdapterInfo) -> String {
    let kind = match info.device_type {
        wgpu::DeviceType::DiscreteGpu => "discrete GPU",
        wgpu::DeviceType::IntegratedGpu => "integrated GPU",
        wgpu::DeviceType::VirtualGpu => "virtual GPU",
        wgpu::DeviceType::Cpu => "software (CPU)",
        wgpu::DeviceType::Other => "other",
    };
    let driver = if info.driver.is_empty() { String::new() } else { format!(", driver {}", info.driver) };
    format!("{} ({kind}, {:?}{driver})", info.name, info.backend)
}

impl GpuContext {
    /// Opens a device on `adapter` with the adapter's own limits.
    pub fn new(adapter: &wgpu::Adapter) -> Result<Self, FlowError> {
        let info = adapter.get_info();
        // Timestamp queries (per-pass GPU timing, `GpuFlow::set_pass_timing`) where the adapter
        // has them; nothing else depends on them.
        let desc = wgpu::DeviceDescriptor {
            label: Some("flownav flow"),
            required_limits: adapter.limits(),
            required_features: adapter.features() & wgpu::Features::TIMESTAMP_QUERY,
            ..Default::default()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&desc)).map_err(|e| {
            FlowError::BackendUnavailable("gpu", format!("cannot open a device on {}: {e}", describe_adapter(&info)))
        })?;
        let error = Arc::new(Mutex::new(None));
        let sink = Arc::clone(&error);
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            tracing::error!("wgpu error: {e}");
            let mut slot = sink.lock().unwrap_or_else(|p| p.into_inner());
            slot.get_or_insert_with(|| e.to_string());
        }));
        Ok(Self { info, device, queue, error })
    }

    /// The first adapter that opens (hardware preferred). Used by tests and `--flow-backend gpu`.
    /// An adapter can be listed and still fail to open (on a headless NVIDIA server the GL
    /// adapter does, with "Parent device is lost"), so each is tried in turn.
    pub fn any() -> Result<Self, FlowError> {
        let inst = instance();
        let list = adapters(&inst);
        if list.is_empty() {
            return Err(no_adapter_error());
        }
        Self::first_that_opens(&list)
    }

    /// The first of `list` on which a device opens; the error names every failure.
    pub fn first_that_opens<'a>(list: impl IntoIterator<Item = &'a wgpu::Adapter>) -> Result<Self, FlowError> {
        let mut failures = Vec::new();
        for adapter in list {
            match Self::new(adapter) {
                Ok(ctx) => return Ok(ctx),
                Err(e) => {
                    tracing::warn!("{e}; trying the next adapter");
                    failures.push(e.to_string());
                }
            }
        }
        Err(FlowError::BackendUnavailable("gpu", format!("no adapter could be opened: {}", failures.join("; "))))
    }

    pub fn info(&self) -> &wgpu::AdapterInfo {
        &self.info
    }

    fn take_error(&self) -> Option<String> {
        self.error.lock().unwrap_or_else(|p| p.into_inner()).take()
    }
}

/// The error for `--flow-backend gpu` when wgpu finds no adapter at all.
pub fn no_adapter_error() -> FlowError {
    let env = std::env::var("WGPU_BACKEND").map(|b| format!(" (WGPU_BACKEND={b})")).unwrap_or_default();
    FlowError::BackendUnavailable(
        "gpu",
        format!(
            "wgpu found no GPU adapter{env}; install your GPU's Vulkan/Metal/DX12 driver, or Mesa's software \
             Vulkan for testing (`apt-get install mesa-vulkan-drivers libvulkan1`), or use --flow-backend cpu"
        ),
    )
}

fn gpu_err(what: impl std::fmt::Display) -> FlowError {
    FlowError::BackendUnavailable("gpu", what.to_string())
}

/// `Lv` in the shaders: the dimensions and parameters of one pyramid level.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
struct LevelUniform {
    w: u32,
    h: u32,
    ws: u32,
    ws_src: u32,
    k: u32,
    n: u32,
    rows: u32,
    cols: u32,
    coarsest: u32,
    radius: u32,
    q: u32,
    level: u32,
}

/// The compile-time shape of a matching pipeline (constants prepended to `match.wgsl`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
struct MatchShape {
    wg: u32,
    block: u32,
    /// Largest window side, 2ρ+1.
    win: u32,
    /// Candidate rows per band and block rows per chunk.
    band: u32,
    chunk: u32,
    costs_in_workgroup: bool,
    level0: bool,
    /// Costs precomputed by the cost-volume kernel (`costvol.wgsl`): only the reductions run.
    pre: bool,
    /// (PRE) The block of A and the patch of B around the best candidate cached in workgroup
    /// memory for the texture energy and the SSDs.
    pcache: bool,
}

impl MatchShape {
    /// Chooses band and chunk so that the cached block rows and window fit `budget` bytes of
    /// workgroup memory, minimising the words loaded per block.
    fn plan(wg: u32, block: u32, radius: u32, level0: bool, budget: u32) -> Option<Self> {
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
    fn precomputed(wg: u32, block: u32, radius: u32, budget: u32) -> Self {
        let win = 2 * radius + 1;
        let costs_bytes = 4 * win * win;
        let costs_in_workgroup = costs_bytes <= budget / 2;
        let used = 64 + if costs_in_workgroup { costs_bytes } else { 4 };
        let pcache = used + 4 * (block * block + (block + 2) * (block + 2)) <= budget;
        Self { wg, block, win, band: 1, chunk: 1, costs_in_workgroup, level0: true, pre: true, pcache }
    }

    fn row_words(win: u32, block: u32) -> u32 {
        (3 + win - 1 + 4 * (block.div_ceil(4) - 1)) / 4 + 2
    }

    fn source(&self) -> String {
        let aw = self.block.div_ceil(4);
        let per = (self.band * self.win).div_ceil(self.wg);
        let rw = Self::row_words(self.win, self.block);
        format!(
            "const WG: u32 = {wg}u;\nconst BL: u32 = {bl}u;\nconst AW: u32 = {aw}u;\nconst AWF: u32 = {awf}u;\n\
             const TAIL: bool = {tail};\nconst NXM: u32 = {win}u;\nconst NYM: u32 = {win}u;\nconst TY: u32 = {ty}u;\n\
             const CH: u32 = {ch}u;\nconst NCH: u32 = {nch}u;\nconst RW: u32 = {rw}u;\nconst PER: u32 = {per}u;\n\
             const SAN: u32 = {san}u;\nconst SBN: u32 = {sbn}u;\nconst WCN: u32 = {wcn}u;\n\
             const COSTS_WG: bool = {cwg};\nconst IS_L0: bool = {l0};\nconst PRE: bool = {pre};\n\
             const PCACHE: bool = {pcache};\nconst PW: u32 = {pw}u;\n{common}{body}",
            wg = self.wg,
            bl = self.block,
            awf = self.block / 4,
            tail = !self.block.is_multiple_of(4),
            win = self.win,
            ty = self.band,
            ch = self.chunk,
            nch = self.block.div_ceil(self.chunk),
            san = if self.pcache { self.block * self.block } else { self.chunk * aw },
            sbn = if self.pcache { (self.block + 2) * (self.block + 2) } else { (self.chunk + self.band - 1) * rw },
            wcn = if self.costs_in_workgroup { self.win * self.win } else { 1 },
            cwg = self.costs_in_workgroup,
            l0 = self.level0,
            pre = self.pre,
            pcache = self.pcache,
            pw = self.block + 2,
            common = COMMON_WGSL,
            body = MATCH_WGSL,
        )
    }
}

/// The compile-time shape of the cost-volume kernel (`costvol.wgsl`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
struct CostVolShape {
    wg: u32,
    block: u32,
    radius: u32,
    /// Tile of blocks per workgroup: columns, rows.
    tc: u32,
    tr: u32,
    /// Displacement columns per group (workgroup memory: `g · vw · tr` words).
    g: u32,
    /// Widest tile region, pixels.
    rwm: u32,
    /// Column sums kept per 4 columns (one word per 4-column quad instead of one per column):
    /// every block starts a whole number of quads after its tile region's start (all x origins
    /// congruent mod 4) and the block side is a multiple of 4.
    quads: bool,
    /// Offset of the row-tile table in the tile table.
    rowbase: u32,
}

/// Words per column tile and per row tile in the tile table (see `costvol.wgsl`).
const CV_CST: u32 = 3;
fn cv_rst(tr: u32) -> u32 {
    4 + 2 * tr
}

fn cv_vw(rwm: u32, quads: bool) -> u32 {
    if quads { rwm.div_ceil(4) } else { rwm }
}

impl CostVolShape {
    /// Words of V per block row and dx (one per column, or per quad of 4 columns).
    fn vw(&self) -> u32 {
        cv_vw(self.rwm, self.quads)
    }

    fn source(&self) -> String {
        format!(
            "const WG: u32 = {wg}u;\nconst BL: u32 = {bl}u;\nconst R: u32 = {r}u;\nconst ND: u32 = {nd}u;\n\
             const TC: u32 = {tc}u;\nconst TR: u32 = {tr}u;\nconst G: u32 = {g}u;\nconst RWM: u32 = {rwm}u;\n\
             const RWQ: u32 = {rwq}u;\nconst QS: bool = {qs};\nconst VW: u32 = {vw}u;\n\
             const VSN: u32 = {vsn}u;\nconst CST: u32 = {cst}u;\nconst RST: u32 = {rst}u;\n\
             const ROWBASE: u32 = {rowbase}u;\n{common}{body}",
            wg = self.wg,
            bl = self.block,
            r = self.radius,
            nd = 2 * self.radius + 1,
            tc = self.tc,
            tr = self.tr,
            g = self.g,
            rwm = self.rwm,
            rwq = self.rwm.div_ceil(4),
            qs = self.quads,
            vw = self.vw(),
            vsn = self.g * self.vw() * self.tr,
            cst = CV_CST,
            rst = cv_rst(self.tr),
            rowbase = self.rowbase,
            common = COMMON_WGSL,
            body = COSTVOL_WGSL,
        )
    }
}

/// The cost-volume path for one frame size: kernel shape, tile table and dispatch size.
#[derive(Clone, Debug, PartialEq, Eq)]
struct CostVolPlan {
    shape: CostVolShape,
    /// Tiles across and down.
    ntc: u32,
    ntr: u32,
    table: Vec<u32>,
    /// Absolute differences computed per frame pair (Σ over tiles of region area × (2r+1)²).
    abs_diffs: u64,
}

/// Tiles of `t` consecutive positions out of `pos` (sorted block origins along one axis):
/// (region start, region length, positions in the tile) per tile.
fn cv_tiles(pos: &[u32], t: usize, block: u32) -> Vec<(u32, u32, usize)> {
    pos.chunks(t).map(|c| (c[0], c[c.len() - 1] + block - c[0], c.len())).collect()
}

/// Plans the cost-volume path for blocks at `origins` (a `rows × cols` grid, single level), or
/// `None` where it does not apply: origins not a product grid sorted along both axes, a
/// window wider than 255 candidates, or no tile whose workgroup memory fits `budget`.
/// `force` = (TC, TR, G) replaces the planner's choice (tests), still within `budget`.
fn plan_cost_volume(
    origins: &[(usize, usize)],
    (rows, cols): (usize, usize),
    block: usize,
    radius: usize,
    wg: u32,
    budget: u32,
    force: Option<(u32, u32, u32)>,
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
    let mut best: Option<(u64, CostVolShape)> = None;
    // The tiles in the order measured fastest on an H200 at 720p dense (docs/gpu.md): larger
    // tiles compute fewer absolute differences. The first whose largest dx group with one
    // phase-1 round (G · ⌈RWM/4⌉ ≤ WG) fits `budget` with G ≥ 4 is taken, the groups balanced
    // (G = ⌈ND / ⌈ND / G_max⌉⌉); if none does, the serial-step model below chooses.
    if force.is_none() {
        for (tc, tr) in [(16u32, 8u32), (16, 16), (8, 8), (8, 4), (4, 4)] {
            let ct = cv_tiles(&xs, tc as usize, block);
            let rwm = ct.iter().map(|t| t.1).max()?;
            let by_budget = u64::from(budget) / (4 * u64::from(cv_vw(rwm, quads)) * u64::from(tr));
            let gmax = by_budget.min(u64::from(wg / rwm.div_ceil(4))).min(nd);
            if gmax >= 4.min(nd) && gmax >= 1 {
                let g = nd.div_ceil(nd.div_ceil(gmax)) as u32;
                best = Some((0, CostVolShape { wg, block, radius: radius as u32, tc, tr, g, rwm, quads, rowbase: 0 }));
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
            let rounds1 = u64::from(g * rwm.div_ceil(4)).div_ceil(u64::from(wg));
            let rounds2 = u64::from(g * tr * tc).div_ceil(u64::from(wg));
            // Serial steps per workgroup (walks, block sums, barriers), times workgroups.
            let cost = ntiles * nd * groups * (rounds1 * rhm * 8 + rounds2 * u64::from(block) + 64);
            if best.is_none_or(|(c, _)| cost < c) {
                best =
                    Some((cost, CostVolShape { wg, block, radius: radius as u32, tc, tr, g, rwm, quads, rowbase: 0 }));
            }
        }
    }
    let (_, mut shape) = best?;
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

/// Pipelines and layouts that do not depend on the frame size.
struct Pipelines {
    prep_layout_colsum: wgpu::BindGroupLayout,
    prep_layout_highpass: wgpu::BindGroupLayout,
    prep_layout_down: wgpu::BindGroupLayout,
    colsum: wgpu::ComputePipeline,
    highpass: wgpu::ComputePipeline,
    downsample: wgpu::ComputePipeline,
    match_layout: wgpu::BindGroupLayout,
    match_pipeline_layout: wgpu::PipelineLayout,
    matchers: HashMap<MatchShape, wgpu::ComputePipeline>,
    costvol_layout: wgpu::BindGroupLayout,
    costvol_pipeline_layout: wgpu::PipelineLayout,
    costvols: HashMap<CostVolShape, wgpu::ComputePipeline>,
}

fn storage_entry(binding: u32, read_only: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

fn uniform_entry(binding: u32) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        },
        count: None,
    }
}

/// Runs `f` inside a validation error scope, turning a shader or pipeline error into a
/// [`FlowError`] instead of a panic.
fn checked<T>(device: &wgpu::Device, what: &str, f: impl FnOnce() -> T) -> Result<T, FlowError> {
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let out = f();
    match pollster::block_on(scope.pop()) {
        None => Ok(out),
        Some(e) => Err(gpu_err(format!("{what}: {e}"))),
    }
}

impl Pipelines {
    fn new(device: &wgpu::Device) -> Result<Self, FlowError> {
        checked(device, "building the preprocessing shaders", || {
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("flow prep"),
                source: wgpu::ShaderSource::Wgsl(format!("{COMMON_WGSL}{PREP_WGSL}").into()),
            });
            let layout = |label, entries: &[wgpu::BindGroupLayoutEntry]| {
                device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor { label: Some(label), entries })
            };
            let prep_layout_colsum =
                layout("flow colsum", &[uniform_entry(0), storage_entry(1, true), storage_entry(2, false)]);
            let prep_layout_highpass = layout(
                "flow highpass",
                &[uniform_entry(0), storage_entry(1, true), storage_entry(3, true), storage_entry(4, false)],
            );
            let prep_layout_down =
                layout("flow downsample", &[uniform_entry(0), storage_entry(1, true), storage_entry(4, false)]);
            let pipeline = |bgl: &wgpu::BindGroupLayout, entry: &str| {
                let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                    label: Some(entry),
                    bind_group_layouts: &[Some(bgl)],
                    immediate_size: 0,
                });
                device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                    label: Some(entry),
                    layout: Some(&pl),
                    module: &module,
                    entry_point: Some(entry),
                    compilation_options: Default::default(),
                    cache: None,
                })
            };
            let colsum = pipeline(&prep_layout_colsum, "colsum");
            let highpass = pipeline(&prep_layout_highpass, "highpass");
            let downsample = pipeline(&prep_layout_down, "downsample");
            let mut entries = vec![uniform_entry(0)];
            entries.extend((1..=4).map(|b| storage_entry(b, true)));
            entries.extend((5..=8).map(|b| storage_entry(b, false)));
            let match_layout = layout("flow match", &entries);
            let match_pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("flow match"),
                bind_group_layouts: &[Some(&match_layout)],
                immediate_size: 0,
            });
            let costvol_layout = layout(
                "flow costvol",
                &[
                    uniform_entry(0),
                    storage_entry(1, true),
                    storage_entry(2, true),
                    storage_entry(3, true),
                    storage_entry(4, true),
                    storage_entry(5, false),
                ],
            );
            let costvol_pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("flow costvol"),
                bind_group_layouts: &[Some(&costvol_layout)],
                immediate_size: 0,
            });
            Self {
                prep_layout_colsum,
                prep_layout_highpass,
                prep_layout_down,
                colsum,
                highpass,
                downsample,
                match_layout,
                match_pipeline_layout,
                matchers: HashMap::new(),
                costvol_layout,
                costvol_pipeline_layout,
                costvols: HashMap::new(),
            }
        })
    }

    fn matcher(&mut self, device: &wgpu::Device, shape: MatchShape) -> Result<(), FlowError> {
        let what = "building the block-matching shader";
        specialised(device, &mut self.matchers, &self.match_pipeline_layout, "flow match", what, shape, || {
            shape.source()
        })
    }

    fn costvol(&mut self, device: &wgpu::Device, shape: CostVolShape) -> Result<(), FlowError> {
        let what = "building the cost-volume shader";
        specialised(device, &mut self.costvols, &self.costvol_pipeline_layout, "flow costvol", what, shape, || {
            shape.source()
        })
    }
}

/// Compiles the pipeline of a shader specialised for `shape` (entry point `main`, the
/// constants in `source`) into `cache`, unless it is there. Workgroup memory is not
/// zero-initialised: every shader writes what it reads.
fn specialised<K: std::hash::Hash + Eq>(
    device: &wgpu::Device,
    cache: &mut HashMap<K, wgpu::ComputePipeline>,
    layout: &wgpu::PipelineLayout,
    label: &str,
    what: &str,
    shape: K,
    source: impl FnOnce() -> String,
) -> Result<(), FlowError> {
    if cache.contains_key(&shape) {
        return Ok(());
    }
    let pipeline = checked(device, what, || {
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(source().into()),
        });
        device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(label),
            layout: Some(layout),
            module: &module,
            entry_point: Some("main"),
            compilation_options: wgpu::PipelineCompilationOptions {
                zero_initialize_workgroup_memory: false,
                ..Default::default()
            },
            cache: None,
        })
    })?;
    cache.insert(shape, pipeline);
    Ok(())
}

/// Buffers of one frame slot at one pyramid level.
struct SlotLevel {
    raw: wgpu::Buffer,
    /// The prefiltered frame; `None` when `prefilter_radius` is 0 (matching reads `raw`).
    hp: Option<wgpu::Buffer>,
    down_bg: Option<wgpu::BindGroup>,
    colsum_bg: Option<wgpu::BindGroup>,
    highpass_bg: Option<wgpu::BindGroup>,
}

impl SlotLevel {
    fn matched(&self) -> &wgpu::Buffer {
        self.hp.as_ref().unwrap_or(&self.raw)
    }
}

/// Everything that depends on the frame size.
struct Sized {
    width: usize,
    height: usize,
    rows: usize,
    cols: usize,
    origins: Vec<(usize, usize)>,
    /// Per level: (width, height, words per row).
    dims: Vec<(usize, usize, usize)>,
    /// `slots[s][l]`: frame slot s (0/1) at level l.
    slots: [Vec<SlotLevel>; 2],
    /// `match_bgs[a][l]`: bind group for level l with frame A in slot a.
    match_bgs: [Vec<wgpu::BindGroup>; 2],
    shapes: Vec<MatchShape>,
    /// The dense fast path, when it runs: its plan and bind groups (`[a]`: frame A in slot a).
    cost_volume: Option<(CostVolPlan, [wgpu::BindGroup; 2])>,
    result: wgpu::Buffer,
    staging: [wgpu::Buffer; 2],
    record_bytes: u64,
}

/// A submitted frame pair whose result has not been read yet.
struct InFlight {
    staging: usize,
    submission: wgpu::SubmissionIndex,
    mapped: mpsc::Receiver<Result<(), wgpu::BufferAsyncError>>,
    /// Labels of the passes whose timestamps this pair wrote (`GpuFlow::set_pass_timing`).
    timed: Option<Vec<&'static str>>,
}

/// Timestamp queries of one pair: a begin and an end timestamp per compute pass, resolved and
/// copied into `readback` (read when the pair is received).
struct PassTiming {
    queries: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    readback: wgpu::Buffer,
    /// Whether a pair in flight owns `readback`.
    busy: bool,
    /// The last pair's (pass, milliseconds), and the whole span first begin → last end.
    last: Option<Vec<(&'static str, f64)>>,
}

/// The GPU engine. Construct once (per parameter set), then call [`FlowEngine::compute`] or
/// [`GpuFlow::compute_pipelined`] per frame pair.
pub struct GpuFlow {
    ctx: Arc<GpuContext>,
    params: FlowParams,
    pipes: Pipelines,
    sized: Option<Sized>,
    field: FlowField,
    pending: VecDeque<InFlight>,
    submitted: u64,
    /// Frame B of the last submitted pair and the slot it lives in (reused as the next A).
    last_b: Vec<u8>,
    last_b_slot: Option<usize>,
    pack: Vec<u8>,
    /// Whether the last pair reused the previous B as A (for tests and benchmarks).
    reused_a: bool,
    /// The dense fast path (cost volume): `None` = where it applies and pays, `Some(false)` =
    /// never, `Some(true)` = wherever it applies. From `FLOWNAV_GPU_COST_VOLUME` (`0`/`1`).
    cost_volume: Option<bool>,
    /// Forced (TC, TR, G) of the cost volume (tests).
    cost_volume_tile: Option<(u32, u32, u32)>,
    /// Per-pass GPU timing, when on (`set_pass_timing`, `FLOWNAV_GPU_TIMESTAMPS=1`) and the
    /// device has timestamp queries.
    timing: Option<PassTiming>,
}

impl std::fmt::Debug for GpuFlow {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuFlow").field("ctx", &self.ctx).field("params", &self.params).finish_non_exhaustive()
    }
}

impl GpuFlow {
    /// An engine for `params` (validated here) on a shared GPU context.
    pub fn new(ctx: Arc<GpuContext>, params: FlowParams) -> Result<Self, FlowError> {
        params.validate()?;
        let pipes = Pipelines::new(&ctx.device)?;
        Ok(Self {
            ctx,
            params,
            pipes,
            sized: None,
            field: FlowField::default(),
            pending: VecDeque::new(),
            submitted: 0,
            last_b: Vec::new(),
            last_b_slot: None,
            pack: Vec::new(),
            reused_a: false,
            cost_volume: match std::env::var("FLOWNAV_GPU_COST_VOLUME").as_deref() {
                Ok("0") => Some(false),
                Ok("1") => Some(true),
                _ => None,
            },
            cost_volume_tile: None,
            timing: None,
        }
        .with_pass_timing(std::env::var("FLOWNAV_GPU_TIMESTAMPS").as_deref() == Ok("1")))
    }

    fn with_pass_timing(mut self, on: bool) -> Self {
        self.set_pass_timing(on);
        self
    }

    /// Turns per-pass GPU timing on or off (also `FLOWNAV_GPU_TIMESTAMPS=1`): each pair then
    /// writes a timestamp before and after each of its compute passes (preprocessing, cost
    /// volume, matching per level) and [`GpuFlow::last_pass_times`] returns them. Returns whether
    /// timing is on: false where the device has no timestamp queries. For benchmarks.
    #[doc(hidden)]
    pub fn set_pass_timing(&mut self, on: bool) -> bool {
        let dev = &self.ctx.device;
        if !on || !dev.features().contains(wgpu::Features::TIMESTAMP_QUERY) {
            let _ = self.flush();
            self.timing = None;
            return false;
        }
        if self.timing.is_none() {
            let bytes = 8 * u64::from(2 * MAX_TIMED);
            let buf = |label, usage| {
                dev.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size: bytes,
                    usage,
                    mapped_at_creation: false,
                })
            };
            self.timing = Some(PassTiming {
                queries: dev.create_query_set(&wgpu::QuerySetDescriptor {
                    label: Some("flow pass times"),
                    ty: wgpu::QueryType::Timestamp,
                    count: 2 * MAX_TIMED,
                }),
                resolve: buf("flow pass times", wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC),
                readback: buf("flow pass times readback", wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST),
                busy: false,
                last: None,
            });
        }
        true
    }

    /// The GPU time of each compute pass of the last timed pair, in milliseconds (converted
    /// with the queue's timestamp period), then `("total", first begin → last end)`; `None`
    /// unless [`GpuFlow::set_pass_timing`] is on and a pair has been received since.
    #[doc(hidden)]
    pub fn last_pass_times(&self) -> Option<Vec<(&'static str, f64)>> {
        self.timing.as_ref().and_then(|t| t.last.clone())
    }

    /// Forces the dense fast path (the cost volume) off (`Some(false)`), on wherever it
    /// applies (`Some(true)`: a single level and a grid whose tiles fit the device), or back to
    /// the default (`None`: where it applies and blocks overlap at least twice in x and y).
    /// Overrides `FLOWNAV_GPU_COST_VOLUME`. For tests and benchmarks.
    #[doc(hidden)]
    pub fn set_cost_volume(&mut self, mode: Option<bool>) {
        if self.cost_volume != mode {
            self.cost_volume = mode;
            // rebuilt by the next pair (after the pairs in flight, which used the old buffers)
            let _ = self.flush();
            self.sized = None;
            self.last_b_slot = None;
        }
    }

    /// Whether the last submitted pair ran the dense fast path (cost volume).
    #[doc(hidden)]
    pub fn uses_cost_volume(&self) -> bool {
        self.sized.as_ref().is_some_and(|s| s.cost_volume.is_some())
    }

    /// Forces the cost volume's tile (TC × TR blocks) and its dx group G instead of the
    /// planner's choice (`None`: the planner's), to exercise other loop shapes in tests; a
    /// choice that does not fit the device's workgroup memory falls back to the per-block kernel.
    #[doc(hidden)]
    pub fn set_cost_volume_tile(&mut self, tile: Option<(u32, u32, u32)>) {
        if self.cost_volume_tile != tile {
            self.cost_volume_tile = tile;
            let _ = self.flush();
            self.sized = None;
            self.last_b_slot = None;
        }
    }

    /// The cost volume's (TC, TR, G) at the current frame size, when it runs.
    #[doc(hidden)]
    pub fn cost_volume_tile(&self) -> Option<(u32, u32, u32)> {
        self.sized.as_ref().and_then(|s| s.cost_volume.as_ref()).map(|(p, _)| (p.shape.tc, p.shape.tr, p.shape.g))
    }

    /// Absolute differences the cost volume computes per frame pair at the current frame size
    /// (`None` when the last pair did not use it).
    #[doc(hidden)]
    pub fn cost_volume_abs_diffs(&self) -> Option<u64> {
        self.sized.as_ref().and_then(|s| s.cost_volume.as_ref()).map(|(plan, _)| plan.abs_diffs)
    }

    /// The adapter this engine runs on.
    pub fn adapter(&self) -> &wgpu::AdapterInfo {
        self.ctx.info()
    }

    /// The shared context (to build more engines on the same device).
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// Whether the last submitted pair's frame A was recognised as the previous pair's frame B
    /// and not uploaded or preprocessed again.
    pub fn reused_frame_a(&self) -> bool {
        self.reused_a
    }

    /// Submits the pair (`a`, `b`) and returns the field of the pair submitted before it (`None`
    /// on the first call): the GPU computes this pair while the caller uses the previous one.
    /// Latency is one frame pair; call [`GpuFlow::flush`] to get the last one.
    pub fn compute_pipelined(&mut self, a: &LumaImage, b: &LumaImage) -> Result<Option<&FlowField>, FlowError> {
        self.submit(a, b)?;
        if self.pending.len() > 1 {
            self.receive()?;
            return Ok(Some(&self.field));
        }
        Ok(None)
    }

    /// Waits for the pair still in flight from [`GpuFlow::compute_pipelined`], if any, and
    /// returns its field.
    pub fn flush(&mut self) -> Result<Option<&FlowField>, FlowError> {
        if self.pending.is_empty() {
            return Ok(None);
        }
        while !self.pending.is_empty() {
            self.receive()?;
        }
        Ok(Some(&self.field))
    }

    fn submit(&mut self, a: &LumaImage, b: &LumaImage) -> Result<(), FlowError> {
        super::check_frames(&self.params, a, b)?;
        let (w, h) = (a.width(), a.height());
        if self.sized.as_ref().is_none_or(|s| (s.width, s.height) != (w, h)) {
            while !self.pending.is_empty() {
                self.receive()?;
            }
            self.sized = None;
            self.last_b_slot = None;
            self.sized = Some(self.build(w, h)?);
        }
        // Frame A is usually the previous pair's frame B: keep it on the GPU.
        let (slot_a, upload_a) = match self.last_b_slot {
            Some(s) if self.last_b.as_slice() == a.data() => (s, false),
            _ => (0, true),
        };
        let slot_b = 1 - slot_a;
        self.reused_a = !upload_a;
        let ctx = Arc::clone(&self.ctx);
        let sized = self.sized.as_ref().expect("built above");
        if upload_a {
            upload(&ctx.queue, &sized.slots[slot_a][0].raw, a, sized.dims[0].2, &mut self.pack);
        }
        upload(&ctx.queue, &sized.slots[slot_b][0].raw, b, sized.dims[0].2, &mut self.pack);
        self.last_b.clear();
        self.last_b.extend_from_slice(b.data());
        self.last_b_slot = Some(slot_b);

        let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("flow") });
        // One compute pass per stage (preprocessing, cost volume, matching per level), each
        // with a begin and an end timestamp when pass timing is on and free.
        let timing = self.timing.as_mut().filter(|t| !t.busy);
        let queries = timing.as_ref().map(|t| &t.queries);
        let mut labels: Vec<&'static str> = Vec::new();
        let mut begin = |enc: &mut wgpu::CommandEncoder, label: &'static str| {
            let writes = queries.filter(|_| labels.len() < MAX_TIMED as usize).map(|q| {
                let i = 2 * labels.len() as u32;
                labels.push(label);
                wgpu::ComputePassTimestampWrites {
                    query_set: q,
                    beginning_of_pass_write_index: Some(i),
                    end_of_pass_write_index: Some(i + 1),
                }
            });
            enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some(label), timestamp_writes: writes })
                .forget_lifetime()
        };
        let nlev = sized.dims.len();
        if nlev > 1 || sized.slots[slot_b][0].hp.is_some() {
            let mut pass = begin(&mut enc, "prep");
            for (s, upload) in [(slot_a, upload_a), (slot_b, true)] {
                if !upload {
                    continue;
                }
                for l in 0..nlev {
                    let sl = &sized.slots[s][l];
                    let (_, hl, ws) = sized.dims[l];
                    let groups = (ws as u32).div_ceil(PREP_WG);
                    if let Some(bg) = &sl.down_bg {
                        pass.set_pipeline(&self.pipes.downsample);
                        pass.set_bind_group(0, bg, &[]);
                        pass.dispatch_workgroups(groups, hl as u32, 1);
                    }
                    if let (Some(cbg), Some(hbg)) = (&sl.colsum_bg, &sl.highpass_bg) {
                        pass.set_pipeline(&self.pipes.colsum);
                        pass.set_bind_group(0, cbg, &[]);
                        pass.dispatch_workgroups(groups, hl as u32, 1);
                        pass.set_pipeline(&self.pipes.highpass);
                        pass.set_bind_group(0, hbg, &[]);
                        pass.dispatch_workgroups(groups, hl as u32, 1);
                    }
                }
            }
        }
        if let Some((plan, bgs)) = &sized.cost_volume {
            let mut pass = begin(&mut enc, "costvol");
            pass.set_pipeline(&self.pipes.costvols[&plan.shape]);
            pass.set_bind_group(0, &bgs[slot_a], &[]);
            pass.dispatch_workgroups(plan.ntc, plan.ntr, 2 * plan.shape.radius + 1);
        }
        for l in (0..nlev).rev() {
            let label = if sized.shapes[l].pre { "reduce" } else { MATCH_LABELS[l.min(MATCH_LABELS.len() - 1)] };
            let mut pass = begin(&mut enc, label);
            pass.set_pipeline(&self.pipes.matchers[&sized.shapes[l]]);
            pass.set_bind_group(0, &sized.match_bgs[slot_a][l], &[]);
            pass.dispatch_workgroups(sized.cols as u32, sized.rows as u32, 1);
        }
        let staging = (self.submitted % 2) as usize;
        enc.copy_buffer_to_buffer(&sized.result, 0, &sized.staging[staging], 0, sized.record_bytes);
        let timed = match timing {
            Some(t) if !labels.is_empty() => {
                let n = 2 * labels.len() as u32;
                enc.resolve_query_set(&t.queries, 0..n, &t.resolve, 0);
                enc.copy_buffer_to_buffer(&t.resolve, 0, &t.readback, 0, 8 * u64::from(n));
                t.busy = true;
                Some(labels)
            }
            _ => None,
        };
        let submission = ctx.queue.submit([enc.finish()]);
        let (tx, rx) = mpsc::channel();
        sized.staging[staging].map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        self.submitted += 1;
        self.pending.push_back(InFlight { staging, submission, mapped: rx, timed });
        Ok(())
    }

    /// Waits for the oldest pair in flight and converts its records into `self.field`.
    fn receive(&mut self) -> Result<(), FlowError> {
        let job = self.pending.pop_front().expect("receive with a pair in flight");
        let ctx = &self.ctx;
        ctx.device
            .poll(wgpu::PollType::Wait { submission_index: Some(job.submission), timeout: None })
            .map_err(|e| gpu_err(format!("waiting for the GPU: {e}")))?;
        if let Some(e) = ctx.take_error() {
            return Err(gpu_err(format!("the GPU flow computation failed: {e}")));
        }
        match wait_mapped(ctx, &job.mapped)? {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(gpu_err(format!("reading the flow results back: {e}"))),
            Err(_) => return Err(gpu_err("the GPU did not deliver the flow results")),
        }
        let sized = self.sized.as_ref().expect("pairs in flight imply buffers");
        let buf = &sized.staging[job.staging];
        {
            let view = buf.get_mapped_range(..).map_err(|e| gpu_err(format!("mapping the flow results: {e}")))?;
            let words: &[u32] = bytemuck::cast_slice(&view);
            fill_field(&self.params, sized, words, &mut self.field);
        }
        buf.unmap();
        if let (Some(labels), Some(t)) = (&job.timed, self.timing.as_mut()) {
            t.last = read_pass_times(ctx, &t.readback, labels)?;
            t.busy = false;
        }
        Ok(())
    }

    /// The cost-volume plan for this frame size, where the dense fast path is to run: a single
    /// level, allowed by `cost_volume`, blocks overlapping at least twice along both axes
    /// (unless forced), and cost grids and dispatch within the device's limits.
    fn plan_cost_volume(
        &self,
        origins: &[(usize, usize)],
        grid: (usize, usize),
        nlev: usize,
        wg: u32,
    ) -> Option<CostVolPlan> {
        let p = &self.params;
        if nlev != 1 || self.cost_volume == Some(false) {
            return None;
        }
        let limits = self.ctx.device.limits();
        let budget = limits.max_compute_workgroup_storage_size;
        let plan = plan_cost_volume(origins, grid, p.block, p.radius, wg, budget, self.cost_volume_tile)?;
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
        (fits && (dense || self.cost_volume == Some(true))).then_some(plan)
    }

    /// Creates every size-dependent buffer and bind group.
    fn build(&mut self, width: usize, height: usize) -> Result<Sized, FlowError> {
        let p = &self.params;
        let device = &self.ctx.device;
        let limits = device.limits();
        let (rows, cols) = p.grid(width, height);
        let max_dim = limits.max_compute_workgroups_per_dimension as usize;
        if rows > max_dim || cols > max_dim {
            return Err(gpu_err(format!(
                "a {rows}x{cols} grid exceeds this GPU's {max_dim} workgroups per dimension; use fewer rows/cols"
            )));
        }
        let origins = super::block_origins(p, width, height);
        let n = origins.len();
        let nlev = p.pyramid_levels.max(1);
        let k = p.prefilter_radius;
        let wg = MATCH_WG.min(limits.max_compute_invocations_per_workgroup).min(limits.max_compute_workgroup_size_x);
        let budget = limits.max_compute_workgroup_storage_size;
        if limits.max_storage_buffers_per_shader_stage < 8 {
            return Err(gpu_err(format!(
                "the adapter allows {} storage buffers per shader stage; the flow shaders need 8",
                limits.max_storage_buffers_per_shader_stage
            )));
        }

        let dims: Vec<(usize, usize, usize)> =
            (0..nlev).map(|l| ((width >> l), (height >> l), (width >> l).div_ceil(4))).collect();
        let cv_plan = self.plan_cost_volume(&origins, (rows, cols), nlev, wg);
        let mut shapes = Vec::with_capacity(nlev);
        if let Some(plan) = &cv_plan {
            self.pipes.costvol(device, plan.shape)?;
            let shape = MatchShape::precomputed(wg, p.block as u32, p.radius as u32, budget);
            self.pipes.matcher(device, shape)?;
            shapes.push(shape);
        }
        for l in shapes.len()..nlev {
            let bl = super::level_block(p.block, l) as u32;
            let radius = if l == nlev - 1 { p.radius } else { p.refine_radius } as u32;
            let shape = MatchShape::plan(wg, bl, radius, l == 0, budget).ok_or_else(|| {
                gpu_err(format!(
                    "{bl} px blocks at radius {radius} do not fit the GPU's {budget} bytes of workgroup memory"
                ))
            })?;
            self.pipes.matcher(device, shape)?;
            shapes.push(shape);
        }
        let gcost_words = shapes
            .iter()
            .filter(|s| !s.costs_in_workgroup || s.pre)
            .map(|s| (s.win * s.win) as u64 * n as u64)
            .max()
            .unwrap_or(1);
        if 4 * gcost_words > limits.max_storage_buffer_binding_size.min(limits.max_buffer_size) {
            return Err(gpu_err(format!(
                "the cost grids of {n} blocks at radius {} need {} MiB, more than this GPU's storage buffer limit; \
                 use a smaller radius (or a pyramid), fewer blocks, or --flow-backend cpu",
                p.radius.max(p.refine_radius),
                (4 * gcost_words) >> 20
            )));
        }

        let make = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: size.max(4).next_multiple_of(4),
                usage,
                mapped_at_creation: false,
            })
        };
        let st = wgpu::BufferUsages::STORAGE;
        let st_dst = st | wgpu::BufferUsages::COPY_DST;
        let uniforms: Vec<wgpu::Buffer> = (0..nlev)
            .map(|l| {
                let (wl, hl, ws) = dims[l];
                let u = LevelUniform {
                    w: wl as u32,
                    h: hl as u32,
                    ws: ws as u32,
                    ws_src: if l == 0 { 0 } else { dims[l - 1].2 as u32 },
                    k: k as u32,
                    n: ((2 * k + 1) * (2 * k + 1)) as u32,
                    rows: rows as u32,
                    cols: cols as u32,
                    coarsest: u32::from(l == nlev - 1),
                    radius: (if l == nlev - 1 { p.radius } else { p.refine_radius }) as u32,
                    q: p.ambiguity_q8() as u32,
                    level: l as u32,
                };
                let buf = make(
                    "flow level",
                    size_of::<LevelUniform>() as u64,
                    wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                );
                self.ctx.queue.write_buffer(&buf, 0, bytemuck::bytes_of(&u));
                buf
            })
            .collect();
        let frame_bytes = |l: usize| 4 * (dims[l].1 * dims[l].2 + 1) as u64;
        let colsum = make("flow colsum", 4 * (width * height) as u64, st);
        let bg = |layout: &wgpu::BindGroupLayout, entries: &[(u32, &wgpu::Buffer)]| {
            let entries: Vec<wgpu::BindGroupEntry> = entries
                .iter()
                .map(|&(binding, buf)| wgpu::BindGroupEntry { binding, resource: buf.as_entire_binding() })
                .collect();
            device.create_bind_group(&wgpu::BindGroupDescriptor { label: None, layout, entries: &entries })
        };
        let make_slot = |_s: usize| -> Vec<SlotLevel> {
            let mut levels: Vec<SlotLevel> = Vec::with_capacity(nlev);
            for l in 0..nlev {
                let raw = make("flow raw", frame_bytes(l), st_dst);
                let hp = (k > 0).then(|| make("flow highpass", frame_bytes(l), st));
                let down_bg = (l > 0).then(|| {
                    bg(&self.pipes.prep_layout_down, &[(0, &uniforms[l]), (1, &levels[l - 1].raw), (4, &raw)])
                });
                let (colsum_bg, highpass_bg) = match &hp {
                    Some(hp) => (
                        Some(bg(&self.pipes.prep_layout_colsum, &[(0, &uniforms[l]), (1, &raw), (2, &colsum)])),
                        Some(bg(
                            &self.pipes.prep_layout_highpass,
                            &[(0, &uniforms[l]), (1, &raw), (3, &colsum), (4, hp)],
                        )),
                    ),
                    None => (None, None),
                };
                levels.push(SlotLevel { raw, hp, down_bg, colsum_bg, highpass_bg });
            }
            levels
        };
        let slots = [make_slot(0), make_slot(1)];

        let orig_bufs: Vec<wgpu::Buffer> = (0..nlev)
            .map(|l| {
                let bl = super::level_block(p.block, l);
                let (wl, hl, _) = dims[l];
                let data: Vec<u32> = origins
                    .iter()
                    .flat_map(|&(ox, oy)| {
                        [
                            super::cpu::level_origin(ox, p.block, bl, l, wl) as u32,
                            super::cpu::level_origin(oy, p.block, bl, l, hl) as u32,
                        ]
                    })
                    .collect();
                let buf = make("flow origins", 4 * data.len() as u64, st_dst);
                self.ctx.queue.write_buffer(&buf, 0, bytemuck::cast_slice(&data));
                buf
            })
            .collect();
        let disp: Vec<wgpu::Buffer> = (0..nlev).map(|_| make("flow displacements", 8 * n as u64, st)).collect();
        let dummy = make("flow unused", 8, st);
        let flags = make("flow flags", 4 * n as u64, st);
        let record_bytes = (4 * RECORD * n) as u64;
        let result = make("flow records", record_bytes, st | wgpu::BufferUsages::COPY_SRC);
        let gcost = make("flow cost grids", 4 * gcost_words, st);
        let staging_buf =
            || make("flow readback", record_bytes, wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST);
        let staging = [staging_buf(), staging_buf()];
        let cost_volume = cv_plan.map(|plan| {
            let tiles = make("flow cost-volume tiles", 4 * plan.table.len() as u64, st_dst);
            self.ctx.queue.write_buffer(&tiles, 0, bytemuck::cast_slice(&plan.table));
            let bgs = [0usize, 1].map(|a| {
                bg(
                    &self.pipes.costvol_layout,
                    &[
                        (0, &uniforms[0]),
                        (1, slots[a][0].matched()),
                        (2, slots[1 - a][0].matched()),
                        (3, &orig_bufs[0]),
                        (4, &tiles),
                        (5, &gcost),
                    ],
                )
            });
            (plan, bgs)
        });
        let match_bgs = [0usize, 1].map(|a| {
            (0..nlev)
                .map(|l| {
                    let prev = if l == nlev - 1 { &dummy } else { &disp[l + 1] };
                    bg(
                        &self.pipes.match_layout,
                        &[
                            (0, &uniforms[l]),
                            (1, slots[a][l].matched()),
                            (2, slots[1 - a][l].matched()),
                            (3, &orig_bufs[l]),
                            (4, prev),
                            (5, &disp[l]),
                            (6, &flags),
                            (7, &result),
                            (8, &gcost),
                        ],
                    )
                })
                .collect()
        });
        if let Some(e) = self.ctx.take_error() {
            return Err(gpu_err(format!("allocating GPU buffers for {width}x{height} frames: {e}")));
        }
        Ok(Sized {
            width,
            height,
            rows,
            cols,
            origins,
            dims,
            slots,
            match_bgs,
            shapes,
            cost_volume,
            result,
            staging,
            record_bytes,
        })
    }
}

/// The result of a `map_async` whose submission has been waited for. Its callback fires in
/// some poll after the submission is done, possibly one running on another thread that shares
/// the device (seen on lavapipe under load), so wait for everything and give that poll up to
/// 10 s to deliver it before calling it missing.
fn wait_mapped<T>(ctx: &GpuContext, rx: &mpsc::Receiver<T>) -> Result<Result<T, ()>, FlowError> {
    for _ in 0..1000 {
        if let Ok(r) = rx.try_recv() {
            return Ok(Ok(r));
        }
        ctx.device
            .poll(wgpu::PollType::Wait { submission_index: None, timeout: None })
            .map_err(|e| gpu_err(format!("waiting for the GPU: {e}")))?;
        if let Ok(r) = rx.recv_timeout(std::time::Duration::from_millis(10)) {
            return Ok(Ok(r));
        }
    }
    Ok(Err(()))
}

/// Maps the resolved timestamps of a received pair (begin and end per pass, in ticks) and
/// converts them into milliseconds per pass, then the total span; `None` if any is missing.
fn read_pass_times(
    ctx: &GpuContext,
    readback: &wgpu::Buffer,
    labels: &[&'static str],
) -> Result<Option<Vec<(&'static str, f64)>>, FlowError> {
    let (tx, rx) = mpsc::channel();
    readback.map_async(wgpu::MapMode::Read, .., move |r| {
        let _ = tx.send(r);
    });
    match wait_mapped(ctx, &rx)? {
        Ok(Ok(())) => {}
        Ok(Err(e)) => return Err(gpu_err(format!("reading the pass times back: {e}"))),
        Err(_) => return Err(gpu_err("the GPU did not deliver the pass times")),
    }
    let ticks: Vec<u64> = {
        let view = readback.get_mapped_range(..).map_err(|e| gpu_err(format!("mapping the pass times: {e}")))?;
        bytemuck::cast_slice::<u8, u64>(&view)[..2 * labels.len()].to_vec()
    };
    readback.unmap();
    let ms_per_tick = f64::from(ctx.queue.get_timestamp_period()) * 1e-6;
    let span = |a: u64, b: u64| b.checked_sub(a).map(|t| t as f64 * ms_per_tick);
    let mut out = Vec::with_capacity(labels.len() + 1);
    for (i, &label) in labels.iter().enumerate() {
        let Some(ms) = span(ticks[2 * i], ticks[2 * i + 1]) else { return Ok(None) };
        out.push((label, ms));
    }
    let (first, last) = (ticks[0], ticks[2 * labels.len() - 1]);
    let Some(total) = span(first, last) else { return Ok(None) };
    out.push(("total", total));
    Ok(Some(out))
}

/// Writes frame `img` into a packed buffer of `ws` words per row (rows padded with zeros).
fn upload(queue: &wgpu::Queue, buf: &wgpu::Buffer, img: &LumaImage, ws: usize, pack: &mut Vec<u8>) {
    let (w, h) = (img.width(), img.height());
    if w == 4 * ws {
        queue.write_buffer(buf, 0, img.data());
        return;
    }
    pack.clear();
    pack.resize(4 * ws * h, 0);
    for (y, dst) in pack.chunks_exact_mut(4 * ws).enumerate() {
        dst[..w].copy_from_slice(img.row(y));
    }
    queue.write_buffer(buf, 0, pack);
}

/// Turns the level-0 records into the field, exactly as the CPU engine finishes a block.
fn fill_field(p: &FlowParams, sized: &Sized, words: &[u32], field: &mut FlowField) {
    let bs = p.block;
    field.rows = sized.rows;
    field.cols = sized.cols;
    field.width = sized.width;
    field.height = sized.height;
    field.vectors.clear();
    let tq = p.min_texture_q4();
    for (rec, &(ox, oy)) in words.chunks_exact(RECORD).zip(&sized.origins) {
        let d = (rec[0] as i32, rec[1] as i32);
        let (c1, f) = (rec[2], rec[3]);
        let s = |bit: u32, v: u32| (f & bit != 0).then_some(u64::from(v));
        let s0 = u64::from(rec[4]);
        let du = super::cpu::parabola(s(4, rec[5]), s0, s(8, rec[6]));
        let dv = super::cpu::parabola(s(16, rec[7]), s0, s(32, rec[8]));
        let textureless = 16 * u64::from(rec[9]) < tq * (2 * bs * (bs - 1)) as u64;
        let validity = if textureless {
            Validity::Textureless
        } else if f & 1 != 0 {
            Validity::OutOfFrame
        } else if f & 2 != 0 {
            Validity::Ambiguous
        } else {
            Validity::Valid
        };
        field.vectors.push(FlowVector {
            x: (ox + bs / 2) as f32,
            y: (oy + bs / 2) as f32,
            u: (f64::from(d.0) + du) as f32,
            v: (f64::from(d.1) + dv) as f32,
            validity,
            cost: c1 as f32 / (bs * bs) as f32,
        });
    }
}

impl FlowEngine for GpuFlow {
    fn name(&self) -> &'static str {
        "gpu"
    }

    fn params(&self) -> &FlowParams {
        &self.params
    }

    /// Submits the pair and waits for its field. A pair still in flight from
    /// [`GpuFlow::compute_pipelined`] is completed first (its field is superseded).
    fn compute(&mut self, a: &LumaImage, b: &LumaImage) -> Result<&FlowField, FlowError> {
        self.submit(a, b)?;
        while !self.pending.is_empty() {
            self.receive()?;
        }
        Ok(&self.field)
    }
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
                                let win = super::super::cpu::Window::new(ox, oy, s.block as usize, w, h, (0, 0), r);
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
            let origins = super::super::block_origins(&p, w, h);
            let a: Vec<u8> = (0..w * h).map(|_| rnd()).collect();
            let b: Vec<u8> = (0..w * h).map(|_| rnd()).collect();
            // A small budget forces small groups; the planner must still cover everything.
            let forced = [Some((1, 1, 1)), Some((3, 5, 2)), Some((16, 2, 4))];
            for (budget, force) in [(16384, None), (2048, None)].into_iter().chain(forced.map(|f| (16384, f))) {
                let plan = plan_cost_volume(&origins, (rows, cols), block, radius, 256, budget, force).expect("plan");
                let costs = simulate(&plan, &origins, cols, &a, &b, (w, h));
                for (bi, &(ox, oy)) in origins.iter().enumerate() {
                    let win = super::super::cpu::Window::new(ox, oy, block, w, h, (0, 0), radius as i32);
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
        let origins = super::super::block_origins(&p, 1280, 720);
        let plan = plan_cost_volume(&origins, (88, 160), 32, 16, 256, 49152, None).expect("plan");
        eprintln!(
            "720p dense plan (48 KiB workgroup memory): {:?}, {} x {} tiles, {} absolute differences per pair",
            plan.shape, plan.ntc, plan.ntr, plan.abs_diffs
        );
        // 16 × 8 blocks (the fastest measured on an H200), V per quad of columns, 6 dx per group
        // (6 · 38 invocations walk in phase 1)
        assert_eq!((plan.shape.tc, plan.shape.tr, plan.shape.g, plan.shape.quads), (16, 8, 6, true));
        // far below the per-block kernel's 14 080 · 1089 · 1024 = 15.7 G
        assert!(plan.abs_diffs < 2_500_000_000, "{}", plan.abs_diffs);
    }
}
