//! Block-matching optical flow (paper §2.2, §5): a grid of blocks spread uniformly over frame A,
//! each searched for in frame B within a radius, with sub-pixel refinement.
//!
//! [`FlowParams`] configures it; [`FlowField`] is what every later stage consumes; a
//! [`FlowEngine`] computes it. The CPU engine ([`cpu::CpuFlow`]) is the reference; the GPU engine
//! must give the same answers. The exact algorithm (block placement, prefilter, cost, candidate
//! order, tie-break, validity thresholds, sub-pixel formula) is the "Algorithm contract" in
//! `docs/flow.md`; [`reference`] implements it literally, without any speed tricks.
//!
//! | module | owns |
//! |---|---|
//! | [`prefilter`] | the local-mean high-pass that makes SAD tolerant to exposure changes; 2×2 pyramid |
//! | [`sad`] | sum-of-absolute-differences kernels (AVX2 / SSE2 / scalar) with early termination |
//! | [`cpu`] | [`cpu::CpuFlow`], the fast CPU engine |
//! | [`gpu`] | [`gpu::GpuFlow`], the wgpu compute-shader engine (same results as the CPU engine) |
//! | `backend` | [`create_engine`]: `flow.backend` = auto / cpu / gpu, with a [`BackendReport`] |
//! | [`reference`] | [`reference::reference_flow`], the contract written as plainly as possible |
//!
//! [`reference`]: mod@reference

mod backend;
pub mod cpu;
pub mod gpu;
pub mod prefilter;
pub mod reference;
pub mod sad;
pub mod sea;

pub use backend::{BackendReport, create_engine};

use crate::config_error::ConfigError;
use hal::LumaImage;
use serde::{Deserialize, Serialize};

/// Why a vector is not trusted.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Validity {
    Valid,
    /// The block has too little texture for any match to mean something.
    Textureless,
    /// The best match is not clearly better than another, distant candidate.
    Ambiguous,
    /// The best match lies on the edge of the searched window (cut by the frame border of B, or
    /// at the search radius), so the true match may lie outside what was searched.
    OutOfFrame,
}

impl Validity {
    pub fn is_valid(self) -> bool {
        self == Validity::Valid
    }

    /// The verdict on a block from its three findings, in the contract's order of precedence:
    /// no texture, then a match on the window's edge, then an ambiguous one.
    pub(crate) fn of(textureless: bool, out_of_frame: bool, ambiguous: bool) -> Self {
        if textureless {
            Validity::Textureless
        } else if out_of_frame {
            Validity::OutOfFrame
        } else if ambiguous {
            Validity::Ambiguous
        } else {
            Validity::Valid
        }
    }

    /// The snake_case name used in JSON output (`"valid"`, `"textureless"`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Validity::Valid => "valid",
            Validity::Textureless => "textureless",
            Validity::Ambiguous => "ambiguous",
            Validity::OutOfFrame => "out_of_frame",
        }
    }
}

/// One block's displacement from frame A into frame B, in pixels per frame interval.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FlowVector {
    /// Block centre in frame A, pixels (u right, v down, origin top-left pixel centre).
    pub x: f32,
    pub y: f32,
    /// Displacement into frame B, pixels.
    pub u: f32,
    pub v: f32,
    pub validity: Validity,
    /// Matching cost at the best integer displacement (per pixel, the engine's cost measure).
    pub cost: f32,
}

impl FlowVector {
    pub fn valid(&self) -> bool {
        self.validity.is_valid()
    }

    /// A block's vector as both engines finish it: the block of side `block` at level-0 origin
    /// `origin`, its best integer displacement `d` with the sub-pixel offsets `sub`, and the
    /// block's SAD `cost` at `d`.
    pub(crate) fn from_match(
        origin: (usize, usize),
        block: usize,
        d: (i32, i32),
        sub: (f64, f64),
        validity: Validity,
        cost: u32,
    ) -> Self {
        Self {
            x: (origin.0 + block / 2) as f32,
            y: (origin.1 + block / 2) as f32,
            u: (f64::from(d.0) + sub.0) as f32,
            v: (f64::from(d.1) + sub.1) as f32,
            validity,
            cost: cost as f32 / (block * block) as f32,
        }
    }
}

/// A `rows × cols` field of block vectors over a `width × height` frame, row-major.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FlowField {
    pub rows: usize,
    pub cols: usize,
    pub width: usize,
    pub height: usize,
    pub vectors: Vec<FlowVector>,
}

impl FlowField {
    /// Vector at grid row `r`, column `c`.
    pub fn at(&self, r: usize, c: usize) -> &FlowVector {
        &self.vectors[r * self.cols + c]
    }

    /// Number of valid vectors.
    pub fn valid_count(&self) -> usize {
        self.vectors.iter().filter(|v| v.valid()).count()
    }
}

/// Which implementation computes the flow.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// The GPU where a hardware adapter exists and is faster, else the CPU.
    #[default]
    Auto,
    Cpu,
    Gpu,
}

/// Where the blocks of the grid sit in the frame (see [`block_origins`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Placement {
    /// Block `c` is centred in cell `c` of `cols` equal cells across the frame (same for rows).
    #[default]
    Spread,
    /// Non-overlapping blocks tiled from the top-left pixel: block `c` starts at `c * block`.
    Tile,
}

/// Block-matching parameters (the `[flow]` table of the config file).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FlowParams {
    /// Grid rows × cols of blocks spread uniformly over the frame (paper: 16 × 16). Ignored
    /// when `stride` is set.
    pub rows: usize,
    pub cols: usize,
    /// Dense mode: when set, the grid is derived from the frame size instead of `rows`/`cols`:
    /// one block per `stride` px, rounded down to a multiple of 8 in each direction (see
    /// [`FlowParams::grid`]), so the OFFIS 8×8 matrices aggregate it. E.g. 8 at 1280×720 gives
    /// 88 × 160 blocks. Requires `placement = "spread"`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stride: Option<usize>,
    /// Block side, pixels (paper: 32).
    pub block: usize,
    /// Search radius, pixels: displacements in [-radius, radius]² are tried.
    pub radius: usize,
    pub backend: Backend,
    /// Block placement: `spread` (default) or `tile`.
    pub placement: Placement,
    /// Half-width k of the (2k+1)² local-mean window subtracted from each frame before matching
    /// (the exposure-tolerant high-pass). 0 matches raw intensities (plain SAD).
    pub prefilter_radius: usize,
    /// Pyramid levels for coarse-to-fine search: 1 = off (single level). With L levels the
    /// coarsest level (1/2^(L-1) resolution) is searched over ±radius and each finer level over
    /// ±refine_radius around twice the coarser result, so motions up to radius·2^(L-1) are found.
    pub pyramid_levels: usize,
    /// Search radius at the finer pyramid levels, pixels (only used when pyramid_levels > 1).
    pub refine_radius: usize,
    /// Minimum texture: mean absolute difference between neighbouring prefiltered pixels of the
    /// block, grey levels. Blocks below it are `textureless`. Quantised to 1/16.
    pub min_texture: f32,
    /// A block is `ambiguous` when another local minimum of the cost, at least 2 px away from the
    /// best, costs at most (1 + ambiguity_ratio) × the best cost. Quantised to 1/256.
    pub ambiguity_ratio: f32,
    /// Threads the CPU engine shares a frame pair's block rows among (the result is the same
    /// for any count). 0 = one per core, up to 4. The GPU engine ignores it.
    pub cpu_threads: usize,
}

impl Default for FlowParams {
    fn default() -> Self {
        Self {
            rows: 16,
            cols: 16,
            stride: None,
            block: 32,
            radius: 16,
            backend: Backend::Auto,
            placement: Placement::Spread,
            prefilter_radius: 4,
            pyramid_levels: 1,
            refine_radius: 4,
            min_texture: 2.0,
            ambiguity_ratio: 0.1,
            cpu_threads: 0,
        }
    }
}

impl FlowParams {
    /// The grid (rows, cols) for a `width × height` frame: `(rows, cols)` as configured, or in
    /// dense mode (`stride = Some(s)`) rows = 8·⌊⌊H/s⌋/8⌋ and cols = 8·⌊⌊W/s⌋/8⌋ (0 when the
    /// frame holds fewer than 8 cells of `s` px; [`check_frames`] rejects that).
    pub fn grid(&self, width: usize, height: usize) -> (usize, usize) {
        match self.stride {
            Some(s) if s > 0 => (height / s / 8 * 8, width / s / 8 * 8),
            _ => (self.rows, self.cols),
        }
    }

    /// `min_texture` in sixteenths of a grey level, as the contract compares it.
    pub fn min_texture_q4(&self) -> u64 {
        (f64::from(self.min_texture) * 16.0).round().max(0.0) as u64
    }

    /// `ambiguity_ratio` in 1/256 units, as the contract compares it.
    pub fn ambiguity_q8(&self) -> u64 {
        (f64::from(self.ambiguity_ratio) * 256.0).round().max(0.0) as u64
    }

    /// Checks the parameters on their own (frame-size checks happen when a frame arrives).
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, problem: &str| {
            Err(ConfigError::Invalid { field: format!("flow.{field}"), problem: problem.into() })
        };
        if self.rows == 0 || self.cols == 0 {
            return bad("rows/cols", "must be at least 1");
        }
        if self.cpu_threads > 64 {
            return bad("cpu_threads", "must be in 0..=64 (0 = one per core, up to 4)");
        }
        if let Some(stride) = self.stride {
            if !(1..=256).contains(&stride) {
                return bad("stride", "must be in 1..=256 pixels (leave it out for the rows x cols grid)");
            }
            if self.placement != Placement::Spread {
                return bad("stride", "requires placement = \"spread\" (dense mode centres one block per stride cell)");
            }
        }
        if !(4..=256).contains(&self.block) || !self.block.is_multiple_of(2) {
            return bad("block", "must be an even number of pixels in 4..=256");
        }
        if !(1..=64).contains(&self.radius) {
            return bad("radius", "must be in 1..=64 pixels");
        }
        if self.prefilter_radius > prefilter::MAX_RADIUS {
            return bad("prefilter_radius", "must be in 0..=7 pixels (0 = match raw intensities)");
        }
        if self.pyramid_levels > 6 {
            return bad("pyramid_levels", "must be in 0..=6 (0 or 1 = single level, no coarse-to-fine)");
        }
        if !(1..=64).contains(&self.refine_radius) {
            return bad("refine_radius", "must be in 1..=64 pixels");
        }
        if !(self.min_texture.is_finite() && (0.0..=255.0).contains(&self.min_texture)) {
            return bad("min_texture", "must be a number of grey levels in 0..=255");
        }
        if !(self.ambiguity_ratio.is_finite() && (0.0..=16.0).contains(&self.ambiguity_ratio)) {
            return bad("ambiguity_ratio", "must be a number in 0..=16");
        }
        Ok(())
    }
}

/// Why a flow field cannot be computed.
#[derive(Debug, thiserror::Error)]
pub enum FlowError {
    #[error(
        "frames differ in size: A is {a_width}x{a_height}, B is {b_width}x{b_height}; flow needs two frames of the same size"
    )]
    SizeMismatch { a_width: usize, a_height: usize, b_width: usize, b_height: usize },
    #[error(
        "frame {width}x{height} is too small for {block}x{block} blocks{level_note}; use a smaller flow.block{pyr_hint}"
    )]
    FrameTooSmall { width: usize, height: usize, block: usize, level_note: String, pyr_hint: &'static str },
    #[error(
        "a tiled grid of {rows}x{cols} blocks of {block} px needs {need_w}x{need_h} px but the frame is {width}x{height}; use fewer rows/cols or flow.placement = \"spread\""
    )]
    TileGridTooLarge {
        rows: usize,
        cols: usize,
        block: usize,
        need_w: usize,
        need_h: usize,
        width: usize,
        height: usize,
    },
    #[error(
        "dense mode with flow.stride = {stride} gives fewer than 8 blocks per row or column on a {width}x{height} frame; use a smaller flow.stride (at most {max_stride})"
    )]
    StrideTooLarge { stride: usize, width: usize, height: usize, max_stride: usize },
    #[error("invalid flow parameters: {0}")]
    Params(#[from] ConfigError),
    #[error("flow backend {0} is not available: {1}")]
    BackendUnavailable(&'static str, String),
    #[error("cannot start {threads} CPU flow threads: {message}; set flow.cpu_threads = 1")]
    Threads { threads: usize, message: String },
}

/// A flow engine: computes the block flow field of a frame pair into a field it owns and reuses
/// (no allocation per frame once the frame size is fixed).
pub trait FlowEngine: Send {
    /// Short name for logs and JSON (`"cpu"`, `"gpu"`).
    fn name(&self) -> &'static str;
    /// The parameters the engine was built with.
    fn params(&self) -> &FlowParams;
    /// Flow from frame `a` to frame `b` (same size), following the algorithm contract.
    fn compute(&mut self, a: &LumaImage, b: &LumaImage) -> Result<&FlowField, FlowError>;
    /// CPU threads a pair is computed on.
    fn threads(&self) -> usize {
        1
    }
}

/// The engine for `params.backend` ([`create_engine`] without the report, which it logs).
pub fn engine(params: &FlowParams) -> Result<Box<dyn FlowEngine>, FlowError> {
    create_engine(params).map(|(engine, _)| engine)
}

/// Checks that a frame pair can be processed with `params`: same size, large enough for the
/// blocks at every pyramid level, and for a tiled grid.
pub fn check_frames(params: &FlowParams, a: &LumaImage, b: &LumaImage) -> Result<(), FlowError> {
    if (a.width(), a.height()) != (b.width(), b.height()) {
        return Err(FlowError::SizeMismatch {
            a_width: a.width(),
            a_height: a.height(),
            b_width: b.width(),
            b_height: b.height(),
        });
    }
    let (w, h) = (a.width(), a.height());
    if let Some(stride) = params.stride {
        let (rows, cols) = params.grid(w, h);
        if rows == 0 || cols == 0 {
            return Err(FlowError::StrideTooLarge { stride, width: w, height: h, max_stride: (w.min(h) / 8).max(1) });
        }
    }
    let levels = params.pyramid_levels.max(1);
    for l in 0..levels {
        let (wl, hl) = (w >> l, h >> l);
        if wl < level_block(params.block, l) || hl < level_block(params.block, l) {
            let level_note = if l == 0 {
                String::new()
            } else {
                format!(" at pyramid level {l} ({wl}x{hl} after halving {l} times)")
            };
            let pyr_hint = if l == 0 { "" } else { " or fewer flow.pyramid_levels" };
            return Err(FlowError::FrameTooSmall { width: w, height: h, block: params.block, level_note, pyr_hint });
        }
    }
    if params.placement == Placement::Tile && (params.cols * params.block > w || params.rows * params.block > h) {
        return Err(FlowError::TileGridTooLarge {
            rows: params.rows,
            cols: params.cols,
            block: params.block,
            need_w: params.cols * params.block,
            need_h: params.rows * params.block,
            width: w,
            height: h,
        });
    }
    Ok(())
}

/// Block side at pyramid level `l`: B halved `l` times, but not below 8 px (nor above B), so
/// that a block covers the same part of the scene at every level.
pub fn level_block(block: usize, l: usize) -> usize {
    (block >> l).max(block.min(8))
}

/// Top-left pixel (x0, y0) in frame A of every block, row-major (`rows × cols` of
/// [`FlowParams::grid`]).
///
/// `Spread`: x0 = clamp(floor((2c+1)·W / (2·cols)) − B/2, 0, W − B), likewise y0 with rows
/// and H: each block is centred on the centre pixel of its cell, pushed inside the frame when
/// the cell is narrower than the block. At 512×512 with 16×16 blocks of 32 this tiles the
/// frame exactly (x0 = 32c). `Tile`: x0 = c·B, y0 = r·B. The vector's (x, y) is the block's
/// centre pixel (x0 + B/2, y0 + B/2), as in the data sets' `blocks32_tile.csv`.
pub fn block_origins(params: &FlowParams, width: usize, height: usize) -> Vec<(usize, usize)> {
    let b = params.block;
    let (rows, cols) = params.grid(width, height);
    let spread = |i: usize, n: usize, len: usize| ((2 * i + 1) * len / (2 * n)).saturating_sub(b / 2).min(len - b);
    let mut out = Vec::with_capacity(rows * cols);
    for r in 0..rows {
        for c in 0..cols {
            out.push(match params.placement {
                Placement::Spread => (spread(c, cols, width), spread(r, rows, height)),
                Placement::Tile => (c * b, r * b),
            });
        }
    }
    out
}
