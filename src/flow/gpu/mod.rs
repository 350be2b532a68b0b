//! The GPU block-matching engine: the algorithm contract of `docs/flow.md` as wgpu compute
//! shaders (Vulkan, Metal, DX12, GL), with the same integer results as [`super::cpu::CpuFlow`].
//!
//! Per frame pair, one command buffer:
//! 1. the two frames are uploaded once, packed 8-bit (4 pixels per `u32` word, rows padded to
//!    whole words); when frame A equals the previous pair's frame B (a video stream), A's
//!    buffers are reused and only B is uploaded and preprocessed;
//! 2. pyramid (2×2 average) and high-pass prefilter run on the GPU
//!    (`src/flow/shaders/prep.wgsl`, bit-identical to [`super::prefilter`]);
//! 3. block matching, coarsest level first (`src/flow/shaders/match.wgsl`): one workgroup per
//!    block, the reference block and the search window of B cached in workgroup memory, every
//!    candidate's exact SAD computed cooperatively, then workgroup reductions for the best
//!    candidate (contract tie-break), the ambiguity test and, at level 0, the texture energy and
//!    the five SSDs of the sub-pixel fit;
//! 4. the level-0 records (10 integers per block) are copied into one of two staging buffers and
//!    mapped; the CPU turns them into a [`FlowField`](super::FlowField) with the same f64 parabola as the CPU
//!    engine, so sub-pixel values are identical, not just close.
//!
//! Buffers, bind groups and pipelines are created once per frame size (pipelines once per
//! block/radius shape) and reused. [`GpuFlow::compute`](super::FlowEngine::compute) (the
//! [`FlowEngine`](super::FlowEngine) method) waits for its own result;
//! [`GpuFlow::compute_pipelined`] submits a pair and returns the previous pair's field, so the
//! GPU computes frame n+1 while the CPU consumes frame n (one frame of latency).
//!
//! | module | owns |
//! |---|---|
//! | `context` | [`GpuContext`]: adapter discovery and ranking, the shared device and queue |
//! | `plan` | the shapes of the matching kernels and the cost-volume plan (pure, tested without a GPU) |
//! | `pipelines` | the WGSL sources, their specialisation per shape, the cached pipelines and layouts |
//! | `buffers` | everything that depends on the frame size, frame upload and record readback |
//! | `engine` | [`GpuFlow`]: command recording, submission, pipelining and per-pass timing |

mod buffers;
mod context;
mod engine;
mod pipelines;
mod plan;

pub use context::{GpuContext, adapters, describe_adapter, instance, is_hardware, no_adapter_error};
pub use engine::GpuFlow;
