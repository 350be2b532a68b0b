//! The shaders and their pipelines: the WGSL sources, the level uniform they share, the
//! specialisation of the matching and cost-volume kernels for a planned shape, and the bind
//! group layouts. Pipelines are compiled once per shape and cached.

use super::context::gpu_err;
use super::plan::{CV_CST, CostVolShape, MatchShape, cv_rst, swar_enabled};
use crate::flow::FlowError;
use std::collections::HashMap;

/// Prepended to every shader below: the level uniform and the pixel unpacking.
const COMMON_WGSL: &str = include_str!("../shaders/common.wgsl");
const PREP_WGSL: &str = include_str!("../shaders/prep.wgsl");
const MATCH_WGSL: &str = include_str!("../shaders/match.wgsl");
const COSTVOL_WGSL: &str = include_str!("../shaders/costvol.wgsl");
/// Workgroup size (x) of the preprocessing shaders.
pub(super) const PREP_WG: u32 = 64;

/// `Lv` in the shaders: the dimensions and parameters of one pyramid level.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct LevelUniform {
    pub(super) w: u32,
    pub(super) h: u32,
    pub(super) ws: u32,
    pub(super) ws_src: u32,
    pub(super) k: u32,
    pub(super) n: u32,
    pub(super) rows: u32,
    pub(super) cols: u32,
    pub(super) coarsest: u32,
    pub(super) radius: u32,
    pub(super) q: u32,
    pub(super) level: u32,
}

impl MatchShape {
    /// The WGSL of this shape: its constants, then the common part and `match.wgsl`.
    pub(super) fn source(&self) -> String {
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

impl CostVolShape {
    /// The WGSL of this shape: its constants, then the common part and `costvol.wgsl`.
    pub(super) fn source(&self) -> String {
        format!(
            "const WG: u32 = {wg}u;\nconst BL: u32 = {bl}u;\nconst R: u32 = {r}u;\nconst ND: u32 = {nd}u;\n\
             const TC: u32 = {tc}u;\nconst TR: u32 = {tr}u;\nconst G: u32 = {g}u;\nconst RWM: u32 = {rwm}u;\n\
             const RWQ: u32 = {rwq}u;\nconst QS: bool = {qs};\nconst VW: u32 = {vw}u;\n\
             const VSN: u32 = {vsn}u;\nconst CST: u32 = {cst}u;\nconst RST: u32 = {rst}u;\n\
             const ROWBASE: u32 = {rowbase}u;\nconst SWAR: bool = {swar};\nconst DQ: bool = {dq};\n\
             {common}{body}",
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
            swar = swar_enabled(),
            dq = self.dx_quads,
            common = COMMON_WGSL,
            body = COSTVOL_WGSL,
        )
    }
}

/// Pipelines and layouts that do not depend on the frame size.
pub(super) struct Pipelines {
    pub(super) prep_layout_colsum: wgpu::BindGroupLayout,
    pub(super) prep_layout_highpass: wgpu::BindGroupLayout,
    pub(super) prep_layout_down: wgpu::BindGroupLayout,
    pub(super) colsum: wgpu::ComputePipeline,
    pub(super) highpass: wgpu::ComputePipeline,
    pub(super) downsample: wgpu::ComputePipeline,
    pub(super) match_layout: wgpu::BindGroupLayout,
    pub(super) match_pipeline_layout: wgpu::PipelineLayout,
    pub(super) matchers: HashMap<MatchShape, wgpu::ComputePipeline>,
    pub(super) costvol_layout: wgpu::BindGroupLayout,
    pub(super) costvol_pipeline_layout: wgpu::PipelineLayout,
    pub(super) costvols: HashMap<CostVolShape, wgpu::ComputePipeline>,
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
    pub(super) fn new(device: &wgpu::Device) -> Result<Self, FlowError> {
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

    pub(super) fn matcher(&mut self, device: &wgpu::Device, shape: MatchShape) -> Result<(), FlowError> {
        let what = "building the block-matching shader";
        specialised(device, &mut self.matchers, &self.match_pipeline_layout, "flow match", what, shape, || {
            shape.source()
        })
    }

    pub(super) fn costvol(&mut self, device: &wgpu::Device, shape: CostVolShape) -> Result<(), FlowError> {
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
