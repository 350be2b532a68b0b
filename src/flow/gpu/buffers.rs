//! What depends on the frame size: the packed frame buffers of both slots at every pyramid
//! level, the bind groups that tie them to the pipelines, the result and staging buffers, and
//! the conversions at either end (frames in, level-0 records out).

use super::context::{GpuContext, gpu_err};
use super::pipelines::{LevelUniform, Pipelines};
use super::plan::{CostVolPlan, CostVolumeChoice, MatchShape, device_plan};
use crate::flow::{FlowError, FlowField, FlowParams, FlowVector, Validity};
use hal::LumaImage;

/// 32-bit words per block in the level-0 result record (see `match.wgsl`).
pub(super) const RECORD: usize = 10;
/// Workgroup size of the cost-volume and reductions shaders, and of the per-block matching
/// shader where [`match_wg`] does not choose another (capped by the device limit).
const MATCH_WG: u32 = 256;

/// Buffers of one frame slot at one pyramid level.
pub(super) struct SlotLevel {
    pub(super) raw: wgpu::Buffer,
    /// The prefiltered frame; `None` when `prefilter_radius` is 0 (matching reads `raw`).
    pub(super) hp: Option<wgpu::Buffer>,
    pub(super) down_bg: Option<wgpu::BindGroup>,
    pub(super) colsum_bg: Option<wgpu::BindGroup>,
    pub(super) highpass_bg: Option<wgpu::BindGroup>,
}

impl SlotLevel {
    pub(super) fn matched(&self) -> &wgpu::Buffer {
        self.hp.as_ref().unwrap_or(&self.raw)
    }
}

/// Everything that depends on the frame size.
pub(super) struct Sized {
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) rows: usize,
    pub(super) cols: usize,
    pub(super) origins: Vec<(usize, usize)>,
    /// Per level: (width, height, words per row).
    pub(super) dims: Vec<(usize, usize, usize)>,
    /// `slots[s][l]`: frame slot s (0/1) at level l.
    pub(super) slots: [Vec<SlotLevel>; 2],
    /// `match_bgs[a][l]`: bind group for level l with frame A in slot a.
    pub(super) match_bgs: [Vec<wgpu::BindGroup>; 2],
    pub(super) shapes: Vec<MatchShape>,
    /// The dense fast path, when it runs: its plan and bind groups (`[a]`: frame A in slot a).
    pub(super) cost_volume: Option<(CostVolPlan, [wgpu::BindGroup; 2])>,
    pub(super) result: wgpu::Buffer,
    pub(super) staging: [wgpu::Buffer; 2],
    pub(super) record_bytes: u64,
}

impl Sized {
    /// Creates every size-dependent buffer and bind group for `width × height` frames, and the
    /// pipelines of the planned shapes.
    pub(super) fn new(
        ctx: &GpuContext,
        pipes: &mut Pipelines,
        p: &FlowParams,
        cost_volume: CostVolumeChoice,
        match_wg: Option<u32>,
        width: usize,
        height: usize,
    ) -> Result<Self, FlowError> {
        let device = &ctx.device;
        let limits = device.limits();
        let (rows, cols) = p.grid(width, height);
        let max_dim = limits.max_compute_workgroups_per_dimension as usize;
        if rows > max_dim || cols > max_dim {
            return Err(gpu_err(format!(
                "a {rows}x{cols} grid exceeds this GPU's {max_dim} workgroups per dimension; use fewer rows/cols"
            )));
        }
        let origins = crate::flow::block_origins(p, width, height);
        let n = origins.len();
        let nlev = p.pyramid_levels.max(1);
        let k = p.prefilter_radius;
        let max_wg = limits.max_compute_invocations_per_workgroup.min(limits.max_compute_workgroup_size_x);
        let wg = MATCH_WG.min(max_wg);
        let budget = limits.max_compute_workgroup_storage_size;
        if limits.max_storage_buffers_per_shader_stage < 8 {
            return Err(gpu_err(format!(
                "the adapter allows {} storage buffers per shader stage; the flow shaders need 8",
                limits.max_storage_buffers_per_shader_stage
            )));
        }

        let dims: Vec<(usize, usize, usize)> =
            (0..nlev).map(|l| ((width >> l), (height >> l), (width >> l).div_ceil(4))).collect();
        let cv_plan = device_plan(&limits, p, cost_volume, &origins, (rows, cols), nlev, wg);
        let mut shapes = Vec::with_capacity(nlev);
        if let Some(plan) = &cv_plan {
            pipes.costvol(device, plan.shape)?;
            // FLOWNAV_GPU_REDUCE_WG sets the reductions' workgroup, for comparisons on a device
            let env_wg = std::env::var("FLOWNAV_GPU_REDUCE_WG").ok().and_then(|v| v.parse::<u32>().ok());
            let rwg = env_wg.unwrap_or(wg).clamp(1, max_wg);
            let shape = MatchShape::precomputed(rwg, p.block as u32, p.radius as u32, budget);
            pipes.matcher(device, shape)?;
            shapes.push(shape);
        }
        for l in shapes.len()..nlev {
            let bl = crate::flow::level_block(p.block, l) as u32;
            let radius = if l == nlev - 1 { p.radius } else { p.refine_radius } as u32;
            let mwg = match_wg.unwrap_or_else(|| self::match_wg(radius, n)).min(max_wg).max(1);
            let shape = MatchShape::plan(mwg, bl, radius, l == 0, budget).ok_or_else(|| {
                gpu_err(format!(
                    "{bl} px blocks at radius {radius} do not fit the GPU's {budget} bytes of workgroup memory"
                ))
            })?;
            pipes.matcher(device, shape)?;
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
                ctx.queue.write_buffer(&buf, 0, bytemuck::bytes_of(&u));
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
                let down_bg = (l > 0)
                    .then(|| bg(&pipes.prep_layout_down, &[(0, &uniforms[l]), (1, &levels[l - 1].raw), (4, &raw)]));
                let (colsum_bg, highpass_bg) = match &hp {
                    Some(hp) => (
                        Some(bg(&pipes.prep_layout_colsum, &[(0, &uniforms[l]), (1, &raw), (2, &colsum)])),
                        Some(bg(&pipes.prep_layout_highpass, &[(0, &uniforms[l]), (1, &raw), (3, &colsum), (4, hp)])),
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
                let bl = crate::flow::level_block(p.block, l);
                let (wl, hl, _) = dims[l];
                let data: Vec<u32> = origins
                    .iter()
                    .flat_map(|&(ox, oy)| {
                        [
                            crate::flow::cpu::level_origin(ox, p.block, bl, l, wl) as u32,
                            crate::flow::cpu::level_origin(oy, p.block, bl, l, hl) as u32,
                        ]
                    })
                    .collect();
                let buf = make("flow origins", 4 * data.len() as u64, st_dst);
                ctx.queue.write_buffer(&buf, 0, bytemuck::cast_slice(&data));
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
            ctx.queue.write_buffer(&tiles, 0, bytemuck::cast_slice(&plan.table));
            let bgs = [0usize, 1].map(|a| {
                bg(
                    &pipes.costvol_layout,
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
                        &pipes.match_layout,
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
        if let Some(e) = ctx.take_error() {
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

/// Invocations per workgroup of the per-block matching kernel at `radius` for `blocks` blocks.
/// One workgroup runs per block, so a sparse grid (the default 16 × 16 = 256 blocks) gives a
/// large GPU only one or two workgroups per multiprocessor: larger workgroups then keep more
/// warps in flight for the (2r+1)² candidates (on an H200 at the default grid the matching pass
/// takes 0.199 ms with 512 invocations, 0.211 ms with 256 and 0.212 ms with 1024; docs/gpu.md).
/// Dense grids fill the GPU with workgroups anyway.
fn match_wg(radius: u32, blocks: usize) -> u32 {
    let candidates = (2 * radius + 1) * (2 * radius + 1);
    if blocks <= 2048 && candidates >= 1024 { SPARSE_MATCH_WG } else { MATCH_WG }
}

/// [`match_wg`] for sparse grids with large windows.
const SPARSE_MATCH_WG: u32 = 512;

/// Writes frame `img` into a packed buffer of `ws` words per row (rows padded with zeros).
pub(super) fn upload(queue: &wgpu::Queue, buf: &wgpu::Buffer, img: &LumaImage, ws: usize, pack: &mut Vec<u8>) {
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
pub(super) fn fill_field(p: &FlowParams, sized: &Sized, words: &[u32], field: &mut FlowField) {
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
        let du = crate::flow::cpu::parabola(s(4, rec[5]), s0, s(8, rec[6]));
        let dv = crate::flow::cpu::parabola(s(16, rec[7]), s0, s(32, rec[8]));
        let textureless = 16 * u64::from(rec[9]) < tq * (2 * bs * (bs - 1)) as u64;
        let validity = Validity::of(textureless, f & 1 != 0, f & 2 != 0);
        field.vectors.push(FlowVector::from_match((ox, oy), bs, d, (du, dv), validity, c1));
    }
}
