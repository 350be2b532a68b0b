//! [`GpuFlow`]: per frame pair, uploads the frames, records one command buffer (preprocessing,
//! cost volume, matching per level), submits it and reads the level-0 records back, waiting
//! for its own result or one pair behind (pipelined). Optional per-pass GPU timing.

use super::buffers::{Sized, fill_field, upload};
use super::context::{GpuContext, gpu_err, is_hardware};
use super::pipelines::{PREP_WG, Pipelines};
use super::plan::CostVolumeChoice;
use crate::flow::{FlowEngine, FlowError, FlowField, FlowParams};
use hal::LumaImage;
use std::collections::VecDeque;
use std::sync::{Arc, mpsc};
use std::time::{Duration, Instant};

/// Most timed passes per pair (preprocessing, cost volume, one per matching level).
const MAX_TIMED: u32 = 16;
/// How long [`GpuFlow`] polls a hardware device without blocking for a pair's result before it
/// sleeps in the driver's wait: a pair at the default grid takes a fraction of a millisecond,
/// less than the driver's wake-up after a blocking wait adds to it.
const SPIN: Duration = Duration::from_millis(2);
/// Labels of the matching passes per level (`match L0` is the finest).
const MATCH_LABELS: [&str; 8] =
    ["match L0", "match L1", "match L2", "match L3", "match L4", "match L5", "match L6", "match L7"];

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
    /// Whether and how the dense fast path (the cost volume) runs.
    cost_volume: CostVolumeChoice,
    /// Invocations per workgroup of the per-block matching kernel (`FLOWNAV_GPU_MATCH_WG`);
    /// `None`: the planner's.
    match_wg: Option<u32>,
    /// Whether `receive` polls without blocking first ([`SPIN`]): hardware adapters only (on a
    /// software rasteriser the polling thread would take a core from the rasteriser's own);
    /// `FLOWNAV_GPU_WAIT=block` turns it off.
    spin: bool,
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
        let spin = is_hardware(ctx.info()) && std::env::var("FLOWNAV_GPU_WAIT").as_deref() != Ok("block");
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
            cost_volume: CostVolumeChoice {
                mode: match std::env::var("FLOWNAV_GPU_COST_VOLUME").as_deref() {
                    Ok("0") => Some(false),
                    Ok("1") => Some(true),
                    _ => None,
                },
                tile: None,
            },
            match_wg: std::env::var("FLOWNAV_GPU_MATCH_WG").ok().and_then(|v| v.parse().ok()),
            spin,
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
        if self.cost_volume.mode != mode {
            self.cost_volume.mode = mode;
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
        if self.cost_volume.tile != tile {
            self.cost_volume.tile = tile;
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
        crate::flow::check_frames(&self.params, a, b)?;
        let (w, h) = (a.width(), a.height());
        if self.sized.as_ref().is_none_or(|s| (s.width, s.height) != (w, h)) {
            while !self.pending.is_empty() {
                self.receive()?;
            }
            self.sized = None;
            self.last_b_slot = None;
            self.sized =
                Some(Sized::new(&self.ctx, &mut self.pipes, &self.params, self.cost_volume, self.match_wg, w, h)?);
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
        let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("flow") });
        // One compute pass per stage (preprocessing of each new frame, cost volume, matching per
        // level), each with a begin and an end timestamp when pass timing is on and free.
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
        let prep = nlev > 1 || sized.slots[slot_b][0].hp.is_some();
        let pipes = &self.pipes;
        let prep_frame = |pass: &mut wgpu::ComputePass<'static>, s: usize| {
            for l in 0..nlev {
                let sl = &sized.slots[s][l];
                let (_, hl, ws) = sized.dims[l];
                let groups = (ws as u32).div_ceil(PREP_WG);
                if let Some(bg) = &sl.down_bg {
                    pass.set_pipeline(&pipes.downsample);
                    pass.set_bind_group(0, bg, &[]);
                    pass.dispatch_workgroups(groups, hl as u32, 1);
                }
                if let (Some(cbg), Some(hbg)) = (&sl.colsum_bg, &sl.highpass_bg) {
                    pass.set_pipeline(&pipes.colsum);
                    pass.set_bind_group(0, cbg, &[]);
                    pass.dispatch_workgroups(groups, hl as u32, 1);
                    pass.set_pipeline(&pipes.highpass);
                    pass.set_bind_group(0, hbg, &[]);
                    pass.dispatch_workgroups(groups, hl as u32, 1);
                }
            }
        };
        if upload_a {
            upload(&ctx.queue, &sized.slots[slot_a][0].raw, a, sized.dims[0].2, &mut self.pack);
            if prep {
                prep_frame(&mut begin(&mut enc, "prep A"), slot_a);
            }
        }
        upload(&ctx.queue, &sized.slots[slot_b][0].raw, b, sized.dims[0].2, &mut self.pack);
        self.last_b_slot = Some(slot_b);
        if prep {
            prep_frame(&mut begin(&mut enc, "prep B"), slot_b);
        }
        if let Some((plan, bgs)) = &sized.cost_volume {
            let mut pass = begin(&mut enc, "costvol");
            pass.set_pipeline(&pipes.costvols[&plan.shape]);
            pass.set_bind_group(0, &bgs[slot_a], &[]);
            pass.dispatch_workgroups(plan.ntc, plan.ntr, 2 * plan.shape.radius + 1);
        }
        for l in (0..nlev).rev() {
            let label = if sized.shapes[l].pre { "reduce" } else { MATCH_LABELS[l.min(MATCH_LABELS.len() - 1)] };
            let mut pass = begin(&mut enc, label);
            pass.set_pipeline(&pipes.matchers[&sized.shapes[l]]);
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
        // Kept to recognise the next pair's frame A; copied while the GPU runs.
        self.last_b.clear();
        self.last_b.extend_from_slice(b.data());
        Ok(())
    }

    /// Waits for the oldest pair in flight and converts its records into `self.field`.
    fn receive(&mut self) -> Result<(), FlowError> {
        let job = self.pending.pop_front().expect("receive with a pair in flight");
        let ctx = &self.ctx;
        // Polling until the map callback has run answers within microseconds of the GPU's end;
        // a blocking wait sleeps until the driver wakes the thread.
        let mut mapped = None;
        if self.spin {
            let t0 = Instant::now();
            while mapped.is_none() && t0.elapsed() < SPIN {
                ctx.device.poll(wgpu::PollType::Poll).map_err(|e| gpu_err(format!("waiting for the GPU: {e}")))?;
                mapped = job.mapped.try_recv().ok();
            }
        }
        if mapped.is_none() {
            ctx.device
                .poll(wgpu::PollType::Wait { submission_index: Some(job.submission), timeout: None })
                .map_err(|e| gpu_err(format!("waiting for the GPU: {e}")))?;
        }
        if let Some(e) = ctx.take_error() {
            return Err(gpu_err(format!("the GPU flow computation failed: {e}")));
        }
        let mapped = match mapped {
            Some(r) => Ok(r),
            None => wait_mapped(ctx, &job.mapped)?,
        };
        match mapped {
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
