//! Block-matching optical flow (paper §2.2, §5): a grid of blocks spread uniformly over frame A,
//! each searched for in frame B within a radius, with sub-pixel refinement.
//!
//! [`FlowParams`] configures it; [`FlowField`] is what every later stage consumes. The CPU
//! engine is the reference; the GPU engine must give the same answers.

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
    /// The block or its best match touches the frame border (the true match may lie outside).
    OutOfFrame,
}

impl Validity {
    pub fn is_valid(self) -> bool {
        self == Validity::Valid
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

/// Block-matching parameters (the `[flow]` table of the config file).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FlowParams {
    /// Grid rows × cols of blocks spread uniformly over the frame (paper: 16 × 16).
    pub rows: usize,
    pub cols: usize,
    /// Block side, pixels (paper: 32).
    pub block: usize,
    /// Search radius, pixels: displacements in [-radius, radius]² are tried.
    pub radius: usize,
    pub backend: Backend,
}

impl Default for FlowParams {
    fn default() -> Self {
        Self { rows: 16, cols: 16, block: 32, radius: 16, backend: Backend::Auto }
    }
}
