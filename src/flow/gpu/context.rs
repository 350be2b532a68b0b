//! Where the GPU engine runs: adapter discovery (hardware first), the device and queue every
//! engine made from one context shares, and the errors when no adapter opens.

use crate::flow::FlowError;
use std::sync::{Arc, Mutex};

/// An adapter, its device and queue, shared by every GPU engine made from it.
pub struct GpuContext {
    info: wgpu::AdapterInfo,
    pub(super) device: wgpu::Device,
    pub(super) queue: wgpu::Queue,
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

    pub(super) fn take_error(&self) -> Option<String> {
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

/// A GPU failure as the engine reports it: the backend is unavailable for the reason given.
pub(super) fn gpu_err(what: impl std::fmt::Display) -> FlowError {
    FlowError::BackendUnavailable("gpu", what.to_string())
}
