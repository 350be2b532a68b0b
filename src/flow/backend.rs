//! Backend selection: which [`FlowEngine`] computes the flow (`flow.backend`,
//! `--flow-backend`).
//!
//! - `cpu`: the CPU engine.
//! - `gpu`: the wgpu engine on the best adapter found (hardware first, else a software one such
//!   as lavapipe/llvmpipe — that is how the parity tests run without a GPU); no adapter is an
//!   error naming what to install.
//! - `auto`: the GPU engine only on a hardware adapter (discrete or integrated GPU), where it is
//!   faster than the CPU; a software adapter is slower than the CPU engine and never chosen. No
//!   suitable adapter, or a GPU that fails to initialise, falls back to the CPU with a log line.

use super::gpu::{self, GpuContext, GpuFlow};
use super::{Backend, FlowEngine, FlowError, FlowParams, cpu::CpuFlow};
use std::sync::Arc;

/// What [`create_engine`] chose and why (for logs and `--json` outputs).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BackendReport {
    /// The engine's name: `"cpu"` or `"gpu"`.
    pub engine: &'static str,
    /// The adapter the GPU engine runs on ("NAME (TYPE, BACKEND, driver ...)"), if any.
    pub adapter: Option<String>,
    /// One sentence on why this engine was chosen.
    pub reason: String,
}

impl std::fmt::Display for BackendReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.adapter {
            Some(a) => write!(f, "flow backend {} on {a}: {}", self.engine, self.reason),
            None => write!(f, "flow backend {}: {}", self.engine, self.reason),
        }
    }
}

/// The engine for `params.backend`, and a report of the choice (also logged at info level).
pub fn create_engine(params: &FlowParams) -> Result<(Box<dyn FlowEngine>, BackendReport), FlowError> {
    params.validate()?;
    let (engine, report): (Box<dyn FlowEngine>, BackendReport) = match params.backend {
        Backend::Cpu => (
            Box::new(CpuFlow::new(params.clone())?),
            BackendReport { engine: "cpu", adapter: None, reason: "requested (flow.backend = \"cpu\")".into() },
        ),
        Backend::Gpu => {
            let ctx = Arc::new(GpuContext::any()?);
            let adapter = gpu::describe_adapter(ctx.info());
            let reason = if gpu::is_hardware(ctx.info()) {
                "requested (flow.backend = \"gpu\")".to_string()
            } else {
                "requested (flow.backend = \"gpu\"); this is a software adapter, slower than the CPU engine".to_string()
            };
            (
                Box::new(GpuFlow::new(ctx, params.clone())?),
                BackendReport { engine: "gpu", adapter: Some(adapter), reason },
            )
        }
        Backend::Auto => auto(params)?,
    };
    tracing::info!("{report}");
    Ok((engine, report))
}

fn cpu_fallback(params: &FlowParams, reason: String) -> Result<(Box<dyn FlowEngine>, BackendReport), FlowError> {
    Ok((Box::new(CpuFlow::new(params.clone())?), BackendReport { engine: "cpu", adapter: None, reason }))
}

fn auto(params: &FlowParams) -> Result<(Box<dyn FlowEngine>, BackendReport), FlowError> {
    let instance = gpu::instance();
    let list = gpu::adapters(&instance);
    let hardware: Vec<&wgpu::Adapter> = list.iter().filter(|a| gpu::is_hardware(&a.get_info())).collect();
    if hardware.is_empty() {
        let reason = if list.is_empty() {
            "auto: no GPU adapter found".to_string()
        } else {
            let names: Vec<String> = list.iter().map(|a| gpu::describe_adapter(&a.get_info())).collect();
            format!("auto: only software adapters found ({}), slower than the CPU engine", names.join("; "))
        };
        return cpu_fallback(params, reason);
    }
    let built = GpuContext::first_that_opens(hardware).and_then(|ctx| {
        let name = gpu::describe_adapter(ctx.info());
        GpuFlow::new(Arc::new(ctx), params.clone()).map(|engine| (engine, name))
    });
    match built {
        Ok((engine, name)) => Ok((
            Box::new(engine),
            BackendReport { engine: "gpu", adapter: Some(name), reason: "auto: hardware adapter found".into() },
        )),
        Err(e) => {
            tracing::warn!("the GPU failed to initialise ({e}); using the CPU engine");
            cpu_fallback(params, format!("auto: the GPU failed to initialise: {e}"))
        }
    }
}
