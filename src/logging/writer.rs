//! The MCAP writer: a dedicated thread fed through per-class bounded queues, so the control
//! path never blocks on disk, compression or encoding.
//!
//! Queue classes (each with its own cap on messages waiting):
//! - **images** (`/camera/image`), small cap: dropped first when the writer falls behind;
//! - **data** (flow, perception, goal, status, pose, world, calibration, log lines);
//! - **critical** (set-points, odometry, `/step/input`), a large cap that a healthy writer never reaches.
//!
//! All classes share one FIFO channel, so the file keeps the order of the calls; the caps are
//! enforced with counters, which is what makes a full class drop its own messages only.

use std::cell::Cell;
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::rc::Rc;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, RecvTimeoutError, Sender};
use hal::{BaseStatus, Calibration, LumaImage, Odometry};
use serde_json::Value;

use super::encode;
use super::payload::{BaseStatusLog, GoalLog, LogLevel, LoggerStats, Pose2D, SetpointLog, StepInputLog, WorldGeometry};
use super::{LiveSink, LogError, LogOptions, SCHEMA_ENCODING, Topic, default_file_name, open_new};
use crate::flow::FlowField;
use crate::perception::Perception;

const IMAGES: usize = 0;
const DATA: usize = 1;
const CRITICAL: usize = 2;

/// One call of the handle, on its way to the writer thread.
enum Item {
    Jpeg { t: u64, data: Arc<[u8]> },
    Mono8 { t: u64, image: LumaImage },
    Calibration { t: u64, calibration: Box<Calibration> },
    Flow { t: u64, field: FlowField },
    Perception { t: u64, perception: Box<Perception>, attributes: Value },
    Goal { t: u64, goal: Box<GoalLog> },
    Setpoint { t: u64, setpoint: SetpointLog },
    StepInput(Box<StepInputLog>),
    Odometry(Odometry),
    Status(BaseStatusLog),
    Pose { t: u64, pose: Pose2D },
    World { t: u64, world: Box<WorldGeometry> },
    Log { t: u64, level: LogLevel, message: String },
    Close,
}

impl Item {
    fn class(&self) -> usize {
        match self {
            Item::Jpeg { .. } | Item::Mono8 { .. } => IMAGES,
            Item::Setpoint { .. } | Item::StepInput(_) | Item::Odometry(_) => CRITICAL,
            _ => DATA,
        }
    }
}

struct Shared {
    caps: [usize; 3],
    pending: [AtomicUsize; 3],
    dropped: [AtomicU64; 3],
    lost: AtomicU64,
    closed: AtomicBool,
}

impl Shared {
    fn stats(&self) -> LoggerStats {
        LoggerStats {
            written: 0,
            dropped_images: self.dropped[IMAGES].load(Ordering::Relaxed),
            dropped_data: self.dropped[DATA].load(Ordering::Relaxed),
            dropped_critical: self.dropped[CRITICAL].load(Ordering::Relaxed),
            lost: self.lost.load(Ordering::Relaxed),
        }
    }
}

/// A cheap, cloneable sender for every topic: hand one to each task that logs.
///
/// Every method takes the capture time `t_ns` of the data (the caller's clock, ns; the file's
/// log and publish times are `t_ns + LogOptions::time_offset_ns`), never blocks, allocates at
/// most a copy of its argument, and returns whether the message was queued (`false`: dropped and
/// counted, see [`LoggerStats`]).
#[derive(Clone)]
pub struct LogHandle {
    tx: Sender<Item>,
    shared: Arc<Shared>,
}

impl LogHandle {
    fn push(&self, item: Item) -> bool {
        let class = item.class();
        if self.shared.closed.load(Ordering::Relaxed) {
            self.shared.lost.fetch_add(1, Ordering::Relaxed);
            return false;
        }
        let waiting = self.shared.pending[class].fetch_add(1, Ordering::AcqRel);
        if waiting >= self.shared.caps[class] {
            self.shared.pending[class].fetch_sub(1, Ordering::AcqRel);
            self.shared.dropped[class].fetch_add(1, Ordering::Relaxed);
            return false;
        }
        if self.tx.send(item).is_err() {
            self.shared.pending[class].fetch_sub(1, Ordering::AcqRel);
            self.shared.lost.fetch_add(1, Ordering::Relaxed);
            return false;
        }
        true
    }

    fn image_queue_full(&self) -> bool {
        if self.shared.pending[IMAGES].load(Ordering::Acquire) >= self.shared.caps[IMAGES] {
            self.shared.dropped[IMAGES].fetch_add(1, Ordering::Relaxed);
            return true;
        }
        false
    }

    /// `/camera/image` as `foxglove.CompressedImage`: the camera's MJPEG frame, stored as is.
    /// Pass an `Arc<[u8]>` to share the buffer with the decoder without a copy.
    pub fn image_jpeg(&self, t_ns: u64, jpeg: impl Into<Arc<[u8]>>) -> bool {
        if self.image_queue_full() {
            return false;
        }
        self.push(Item::Jpeg { t: t_ns, data: jpeg.into() })
    }

    /// `/camera/image` as `foxglove.RawImage` `mono8` (the sim's rendered frames). Copies the
    /// image only when the image queue has room.
    pub fn image_mono8(&self, t_ns: u64, image: &LumaImage) -> bool {
        if self.image_queue_full() {
            return false;
        }
        self.push(Item::Mono8 { t: t_ns, image: image.clone() })
    }

    /// `/camera/calibration` (`foxglove.CameraCalibration`) and the camera mount on `/tf`
    /// (`base_link → camera`). Log it once at start; it is repeated at the start of every split part.
    pub fn calibration(&self, t_ns: u64, calibration: &Calibration) -> bool {
        self.push(Item::Calibration { t: t_ns, calibration: Box::new(calibration.clone()) })
    }

    /// `/flow/field` (JSON) and `/flow/annotations` (arrows; with the masks when
    /// [`perception`](Self::perception) is logged with the same `t_ns`). `t_ns` is the capture
    /// time of the newer frame of the pair, so the arrows overlay that image.
    pub fn flow(&self, t_ns: u64, field: &FlowField) -> bool {
        self.push(Item::Flow { t: t_ns, field: field.clone() })
    }

    /// `/offis/perception` (JSON): the OFFIS result plus free-form `attributes`
    /// (`Value::Null` when there are none).
    pub fn perception(&self, t_ns: u64, perception: &Perception, attributes: Value) -> bool {
        self.push(Item::Perception { t: t_ns, perception: Box::new(perception.clone()), attributes })
    }

    /// `/pafsis/goal` (JSON).
    pub fn goal(&self, t_ns: u64, goal: &GoalLog) -> bool {
        self.push(Item::Goal { t: t_ns, goal: Box::new(goal.clone()) })
    }

    /// `/control/setpoint` (JSON). Never dropped below the critical cap.
    pub fn setpoint(&self, t_ns: u64, setpoint: &SetpointLog) -> bool {
        self.push(Item::Setpoint { t: t_ns, setpoint: *setpoint })
    }

    /// `/step/input` (JSON), stamped with the entry's `t_ns`: what the pipeline consumed, for
    /// replay. Critical class, like set-points: a replay needs every one.
    pub fn step_input(&self, input: &StepInputLog) -> bool {
        self.push(Item::StepInput(Box::new(input.clone())))
    }

    /// `/base/odometry` (JSON), stamped with `odometry.t_ns`. Never dropped below the critical cap.
    pub fn odometry(&self, odometry: &Odometry) -> bool {
        self.push(Item::Odometry(*odometry))
    }

    /// `/base/status` (JSON), stamped with `status.t_ns`.
    pub fn base_status(&self, status: &BaseStatus) -> bool {
        self.push(Item::Status(*status))
    }

    /// `/tf` (`foxglove.FrameTransform`): the robot pose, `odom → base_link`.
    pub fn pose(&self, t_ns: u64, pose: &Pose2D) -> bool {
        self.push(Item::Pose { t: t_ns, pose: *pose })
    }

    /// `/sim/world` (`foxglove.SceneUpdate`): walls and box obstacles as cubes, cylinders as
    /// cylinders. Log it at start and whenever the world changes; repeated in every split part.
    pub fn world(&self, t_ns: u64, world: &WorldGeometry) -> bool {
        self.push(Item::World { t: t_ns, world: Box::new(world.clone()) })
    }

    /// `/log` (`foxglove.Log`): one line for the Log panel.
    pub fn log(&self, t_ns: u64, level: LogLevel, message: impl Into<String>) -> bool {
        self.push(Item::Log { t: t_ns, level, message: message.into() })
    }

    /// Drops and losses so far (the `written` field is only known to the writer; it is 0 here).
    pub fn drops(&self) -> LoggerStats {
        self.shared.stats()
    }

    /// Messages queued and not yet written: images, data, critical.
    pub fn waiting(&self) -> [usize; 3] {
        let n = |c: usize| self.shared.pending[c].load(Ordering::Acquire);
        [n(IMAGES), n(DATA), n(CRITICAL)]
    }
}

/// What a closed logger wrote.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LogSummary {
    /// The files written, in order (more than one when split).
    pub files: Vec<PathBuf>,
    /// Totals over all files.
    pub stats: LoggerStats,
    /// Messages written per topic, over all files.
    pub per_topic: BTreeMap<String, u64>,
}

impl std::fmt::Display for LogSummary {
    /// One line: "1 file, 5123 messages on 14 topics, nothing dropped", or with the drops by kind.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let s = &self.stats;
        let files = self.files.len();
        let plural = if files == 1 { "" } else { "s" };
        write!(f, "{files} file{plural}, {} messages on {} topics, ", s.written, self.per_topic.len())?;
        if s.dropped() == 0 {
            return f.write_str("nothing dropped");
        }
        write!(
            f,
            "dropped {} images, {} other data, {} set-points/odometry; {} lost",
            s.dropped_images, s.dropped_data, s.dropped_critical, s.lost
        )
    }
}

/// Owns the writer thread. Dereferences to a [`LogHandle`]; [`LogWriter::handle`] gives clones
/// for other tasks. [`LogWriter::close`] (or dropping it) drains the queue, writes the summary and
/// footer, and joins the thread.
pub struct LogWriter {
    handle: LogHandle,
    path: PathBuf,
    thread: Option<JoinHandle<Result<LogSummary, LogError>>>,
}

impl std::ops::Deref for LogWriter {
    type Target = LogHandle;
    fn deref(&self) -> &LogHandle {
        &self.handle
    }
}

impl LogWriter {
    /// Starts a log in `dir` (created when missing) named
    /// `flownav-<YYYYmmdd-HHMMSS>-<kind>.mcap` (UTC; `-2`, `-3`, ... appended rather than
    /// overwrite; `-p001`, `-p002`, ... parts when splitting).
    pub fn create(dir: &Path, options: LogOptions) -> Result<Self, LogError> {
        options.validate()?;
        std::fs::create_dir_all(dir).map_err(|error| LogError::CreateDir { path: dir.to_path_buf(), error })?;
        let base = default_file_name(std::time::SystemTime::now(), &options.kind);
        let split = options.split_bytes.is_some();
        for attempt in 1..1000u32 {
            let stem = if attempt == 1 { base.clone() } else { format!("{base}-{attempt}") };
            let path = dir.join(part_name(&stem, split.then_some(1)));
            match open_new(&path) {
                Ok(file) => return Self::start(file, path, stem, dir.to_path_buf(), options),
                Err(LogError::Exists { .. }) => continue,
                Err(e) => return Err(e),
            }
        }
        Err(LogError::Exists { path: dir.join(format!("{base}.mcap")) })
    }

    /// Starts a log at exactly `path`; refuses an existing file. With splitting, later parts are
    /// named `<stem>-p002.mcap`, ... beside it.
    pub fn create_at(path: &Path, options: LogOptions) -> Result<Self, LogError> {
        options.validate()?;
        let file = open_new(path)?;
        let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "flownav".into());
        Self::start(file, path.to_path_buf(), stem, dir, options)
    }

    /// A logger that writes no file and only feeds the live view ([`LogOptions::live`], `--live`
    /// with `--no-log`): the same encoding on the same thread, without the disk. While no
    /// viewer is connected it encodes only what it keeps for later viewers (calibration, world).
    /// [`LogWriter::path`] is empty.
    pub fn live_only(options: LogOptions) -> Result<Self, LogError> {
        options.validate()?;
        if options.live.is_none() {
            return Err(LogError::Option { name: "live", problem: "is needed by a logger without a file".into() });
        }
        let kind = options.kind.clone();
        Self::spawn(None, PathBuf::new(), kind, PathBuf::new(), options)
    }

    fn start(file: File, path: PathBuf, stem: String, dir: PathBuf, options: LogOptions) -> Result<Self, LogError> {
        Self::spawn(Some(file), path, stem, dir, options)
    }

    fn spawn(
        file: Option<File>,
        path: PathBuf,
        stem: String,
        dir: PathBuf,
        options: LogOptions,
    ) -> Result<Self, LogError> {
        let (tx, rx) = crossbeam_channel::unbounded();
        let shared = Arc::new(Shared {
            caps: [options.image_queue, options.data_queue, options.critical_queue],
            pending: Default::default(),
            dropped: Default::default(),
            lost: AtomicU64::new(0),
            closed: AtomicBool::new(false),
        });
        let worker_shared = Arc::clone(&shared);
        let first = path.clone();
        let thread = std::thread::Builder::new()
            .name("flownav-log".into())
            .spawn(move || {
                let naming = Naming { dir, stem, split: options.split_bytes.is_some() };
                Worker::run(file, first, naming, options, rx, worker_shared)
            })
            .map_err(|e| LogError::Write {
                path: path.clone(),
                message: format!("cannot start the writer thread: {e}"),
            })?;
        Ok(Self { handle: LogHandle { tx, shared }, path, thread: Some(thread) })
    }

    /// A clone of the handle, for another task or thread.
    pub fn handle(&self) -> LogHandle {
        self.handle.clone()
    }

    /// The first (or only) file of this log (empty for [`LogWriter::live_only`]).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Drains what is queued, writes the `flownav.stats` metadata, the summary and the footer,
    /// and reports what was written and dropped. Calls on handles after this are counted as lost.
    pub fn close(mut self) -> Result<LogSummary, LogError> {
        self.finish()
    }

    fn finish(&mut self) -> Result<LogSummary, LogError> {
        let Some(thread) = self.thread.take() else {
            return Ok(LogSummary::default());
        };
        // The Close item goes through whatever the caps say: it must always arrive.
        let _ = self.handle.tx.send(Item::Close);
        let result = thread.join().map_err(|_| LogError::Panicked)?;
        self.handle.shared.closed.store(true, Ordering::Relaxed);
        result
    }
}

impl Drop for LogWriter {
    fn drop(&mut self) {
        if self.thread.is_some() {
            match self.finish() {
                Ok(s) => tracing::info!(files = ?s.files, dropped = s.stats.dropped(), "log closed"),
                Err(e) => tracing::error!("{e}"),
            }
        }
    }
}

fn part_name(stem: &str, part: Option<u32>) -> String {
    match part {
        Some(n) => format!("{stem}-p{n:03}.mcap"),
        None => format!("{stem}.mcap"),
    }
}

struct Naming {
    dir: PathBuf,
    stem: String,
    split: bool,
}

/// `Write + Seek` that tracks the file size, for size-based splitting.
struct Counting {
    inner: BufWriter<File>,
    pos: u64,
    size: Rc<Cell<u64>>,
}

impl Write for Counting {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.pos += n as u64;
        if self.pos > self.size.get() {
            self.size.set(self.pos);
        }
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

impl Seek for Counting {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.pos = self.inner.seek(pos)?;
        Ok(self.pos)
    }
}

/// One open MCAP file and its channel registrations.
struct Part {
    mcap: mcap::Writer<Counting>,
    path: PathBuf,
    size: Rc<Cell<u64>>,
    channels: [Option<u16>; Topic::COUNT],
    /// Next sequence number per channel id (two topics kinds can share one channel: `/tf`).
    sequence: std::collections::HashMap<u16, u32>,
    written: u64,
    unflushed: bool,
}

impl Part {
    fn open(file: File, path: PathBuf, options: &LogOptions, number: u32) -> Result<Self, LogError> {
        let size = Rc::new(Cell::new(0));
        let sink = Counting { inner: BufWriter::with_capacity(256 * 1024, file), pos: 0, size: Rc::clone(&size) };
        let write_err = |e: mcap::McapError| LogError::Write { path: path.clone(), message: e.to_string() };
        let mut mcap = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(options.compression_level)
            .compression_threads(0)
            .chunk_size(Some(options.chunk_bytes))
            .library(format!("flownav {} (mcap-rs 0.26)", env!("CARGO_PKG_VERSION")))
            .create(sink)
            .map_err(write_err)?;
        let mut header = BTreeMap::new();
        header.insert("kind".to_string(), options.kind.clone());
        header.insert("part".to_string(), number.to_string());
        header.insert("time_offset_ns".to_string(), options.time_offset_ns.to_string());
        header.insert("flownav_version".to_string(), env!("CARGO_PKG_VERSION").to_string());
        mcap.write_metadata(&mcap::records::Metadata { name: "flownav.header".into(), metadata: header })
            .map_err(write_err)?;
        for (name, metadata) in &options.metadata {
            mcap.write_metadata(&mcap::records::Metadata { name: name.clone(), metadata: metadata.clone() })
                .map_err(write_err)?;
        }
        // Get the header onto the disk now: a run killed early still leaves a valid MCAP start.
        mcap.flush().map_err(write_err)?;
        Ok(Self {
            mcap,
            path,
            size,
            channels: [None; Topic::COUNT],
            sequence: Default::default(),
            written: 0,
            unflushed: false,
        })
    }

    fn err(&self, e: impl std::fmt::Display) -> LogError {
        LogError::Write { path: self.path.clone(), message: e.to_string() }
    }

    fn write(&mut self, topic: Topic, log_time: u64, data: &[u8]) -> Result<(), LogError> {
        let channel = match self.channels[topic as usize] {
            Some(id) => id,
            None => {
                let schema = serde_json::to_vec(&topic.schema()).map_err(|e| self.err(e))?;
                let schema_id =
                    self.mcap.add_schema(topic.schema_name(), SCHEMA_ENCODING, &schema).map_err(|e| self.err(e))?;
                let id = self
                    .mcap
                    .add_channel(schema_id, topic.name(), "json", &BTreeMap::new())
                    .map_err(|e| self.err(e))?;
                self.channels[topic as usize] = Some(id);
                id
            }
        };
        let next = self.sequence.entry(channel).or_insert(0);
        let sequence = *next;
        *next = next.wrapping_add(1);
        let header = mcap::records::MessageHeader { channel_id: channel, sequence, log_time, publish_time: log_time };
        self.mcap.write_to_known_channel(&header, data).map_err(|e| self.err(e))?;
        self.written += 1;
        self.unflushed = true;
        Ok(())
    }

    fn flush(&mut self) -> Result<(), LogError> {
        if self.unflushed {
            self.mcap.flush().map_err(|e| self.err(e))?;
            self.unflushed = false;
        }
        Ok(())
    }

    fn finish(mut self, stats: &LoggerStats, per_topic: &BTreeMap<String, u64>) -> Result<PathBuf, LogError> {
        let mut m = BTreeMap::new();
        m.insert("written".to_string(), stats.written.to_string());
        m.insert("dropped_images".to_string(), stats.dropped_images.to_string());
        m.insert("dropped_data".to_string(), stats.dropped_data.to_string());
        m.insert("dropped_critical".to_string(), stats.dropped_critical.to_string());
        m.insert("lost".to_string(), stats.lost.to_string());
        for (topic, n) in per_topic {
            m.insert(format!("count:{topic}"), n.to_string());
        }
        self.mcap
            .write_metadata(&mcap::records::Metadata { name: "flownav.stats".into(), metadata: m })
            .map_err(|e| self.err(e))?;
        self.mcap.finish().map_err(|e| self.err(e))?;
        let path = self.path;
        // `finish` wrote the summary and footer; push them out of the buffer to the file.
        self.mcap.into_inner().flush().map_err(|e| LogError::Write { path: path.clone(), message: e.to_string() })?;
        Ok(path)
    }
}

/// The writer thread's state.
struct Worker {
    options: LogOptions,
    naming: Naming,
    shared: Arc<Shared>,
    part: Option<Part>,
    part_number: u32,
    files: Vec<PathBuf>,
    per_topic_part: BTreeMap<String, u64>,
    per_topic: BTreeMap<String, u64>,
    written: u64,
    /// The last flow field, held until the same frame's perception arrives to draw the masks.
    pending_flow: Option<(u64, FlowField)>,
    /// Messages repeated at the start of every split part (calibration, camera mount, world).
    latched: Vec<(Topic, u64, Vec<u8>)>,
    last_log_time: Option<u64>,
    error: Option<LogError>,
    buf: Vec<u8>,
    /// No file: the messages only go to the live view.
    live_only: bool,
}

impl Worker {
    fn run(
        file: Option<File>,
        path: PathBuf,
        naming: Naming,
        options: LogOptions,
        rx: Receiver<Item>,
        shared: Arc<Shared>,
    ) -> Result<LogSummary, LogError> {
        let mut w = Worker {
            naming,
            shared,
            part: None,
            part_number: 1,
            files: Vec::new(),
            per_topic_part: BTreeMap::new(),
            per_topic: BTreeMap::new(),
            written: 0,
            pending_flow: None,
            latched: Vec::new(),
            last_log_time: None,
            error: None,
            buf: Vec::new(),
            live_only: false,
            options,
        };
        match file.map(|file| Part::open(file, path.clone(), &w.options, 1)) {
            Some(Ok(p)) => {
                w.files.push(path);
                w.part = Some(p);
            }
            Some(Err(e)) => w.fail(e),
            None => w.live_only = true,
        }
        let mut next_flush = Instant::now() + w.options.flush_interval;
        loop {
            let timeout = next_flush.saturating_duration_since(Instant::now());
            match rx.recv_timeout(timeout) {
                Ok(Item::Close) | Err(RecvTimeoutError::Disconnected) => break,
                Ok(item) => {
                    w.shared.pending[item.class()].fetch_sub(1, Ordering::AcqRel);
                    w.handle(item);
                }
                Err(RecvTimeoutError::Timeout) => {}
            }
            if Instant::now() >= next_flush {
                w.periodic_flush();
                next_flush = Instant::now() + w.options.flush_interval;
            }
        }
        w.shared.closed.store(true, Ordering::Relaxed);
        // Anything sent between Close and `closed` is counted as lost.
        while let Ok(item) = rx.try_recv() {
            if !matches!(item, Item::Close) {
                w.shared.pending[item.class()].fetch_sub(1, Ordering::AcqRel);
                w.shared.lost.fetch_add(1, Ordering::Relaxed);
            }
        }
        w.close()
    }

    fn fail(&mut self, e: LogError) {
        tracing::error!("{e}; logging stops, the run goes on");
        self.part = None;
        if self.error.is_none() {
            self.error = Some(e);
        }
    }

    fn stats(&self) -> LoggerStats {
        LoggerStats { written: self.written, ..self.shared.stats() }
    }

    /// Writes one message to the file and offers it to the live view.
    fn emit(&mut self, topic: Topic, t_ns: u64, data: &[u8]) {
        self.write(topic, t_ns, data);
        if let Some(live) = &self.options.live {
            live.offer(topic, t_ns.saturating_add(self.options.time_offset_ns), data, false);
        }
    }

    fn write(&mut self, topic: Topic, t_ns: u64, data: &[u8]) {
        if self.live_only {
            return;
        }
        let log_time = t_ns.saturating_add(self.options.time_offset_ns);
        let Some(part) = self.part.as_mut() else {
            self.shared.lost.fetch_add(1, Ordering::Relaxed);
            return;
        };
        if let Err(e) = part.write(topic, log_time, data) {
            self.shared.lost.fetch_add(1, Ordering::Relaxed);
            self.fail(e);
            return;
        }
        self.written += 1;
        self.last_log_time = Some(self.last_log_time.map_or(log_time, |t| t.max(log_time)));
        *self.per_topic_part.entry(topic.name().to_string()).or_default() += 1;
        *self.per_topic.entry(topic.name().to_string()).or_default() += 1;
    }

    fn latch(&mut self, topic: Topic, t_ns: u64, data: Vec<u8>) {
        self.latched.retain(|(tp, _, _)| *tp != topic);
        self.write(topic, t_ns, &data);
        if let Some(live) = &self.options.live {
            live.offer(topic, t_ns.saturating_add(self.options.time_offset_ns), &data, true);
        }
        self.latched.push((topic, t_ns, data));
    }

    fn handle(&mut self, item: Item) {
        let kept = matches!(item, Item::Calibration { .. } | Item::World { .. });
        if self.live_only && !kept && !self.options.live.as_ref().is_some_and(LiveSink::has_clients) {
            // Nobody to show it to and no file: skip the encoding.
            return;
        }
        let offset = self.options.time_offset_ns;
        match item {
            Item::Jpeg { t, data } => {
                let mut buf = std::mem::take(&mut self.buf);
                encode::compressed_image(t.saturating_add(offset), &data, &mut buf);
                self.emit(Topic::ImageCompressed, t, &buf);
                self.buf = buf;
            }
            Item::Mono8 { t, image } => {
                let mut buf = std::mem::take(&mut self.buf);
                encode::raw_image(t.saturating_add(offset), &image, &mut buf);
                self.emit(Topic::ImageRaw, t, &buf);
                self.buf = buf;
            }
            Item::Calibration { t, calibration } => {
                self.latch(Topic::Calibration, t, encode::camera_calibration(t.saturating_add(offset), &calibration));
                self.latch(
                    Topic::CameraMount,
                    t,
                    encode::camera_mount_transform(t.saturating_add(offset), &calibration),
                );
            }
            Item::Flow { t, field } => {
                self.flush_pending_flow();
                self.emit(Topic::FlowField, t, &encode::flow_field(&field));
                self.pending_flow = Some((t, field));
            }
            Item::Perception { t, perception, attributes } => {
                if let Some((ft, field)) = self.pending_flow.take() {
                    let masks = (ft == t).then_some(&*perception);
                    self.emit(
                        Topic::FlowAnnotations,
                        ft,
                        &encode::flow_annotations(ft.saturating_add(offset), &field, masks),
                    );
                }
                self.emit(Topic::Perception, t, &encode::perception(&perception, &attributes));
            }
            Item::Goal { t, goal } => self.emit(Topic::Goal, t, &encode::goal(&goal)),
            Item::Setpoint { t, setpoint } => self.emit(Topic::Setpoint, t, &encode::setpoint(&setpoint)),
            Item::StepInput(input) => self.emit(Topic::StepInput, input.t_ns(), &encode::step_input(&input)),
            Item::Odometry(o) => self.emit(Topic::Odometry, o.t_ns, &encode::odometry(&o)),
            Item::Status(s) => {
                let data = serde_json::to_vec(&s).unwrap_or_default();
                self.emit(Topic::BaseStatus, s.t_ns, &data);
            }
            Item::Pose { t, pose } => {
                self.emit(Topic::RobotPose, t, &encode::robot_pose(t.saturating_add(offset), &pose))
            }
            Item::World { t, world } => self.latch(Topic::World, t, encode::world(t.saturating_add(offset), &world)),
            Item::Log { t, level, message } => {
                self.emit(Topic::Log, t, &encode::log_line(t.saturating_add(offset), level, &message))
            }
            Item::Close => {}
        }
        self.maybe_split();
    }

    fn flush_pending_flow(&mut self) {
        if let Some((t, field)) = self.pending_flow.take() {
            let data = encode::flow_annotations(t.saturating_add(self.options.time_offset_ns), &field, None);
            self.emit(Topic::FlowAnnotations, t, &data);
        }
    }

    /// Finishes the current chunk and pushes it to the OS: after this, a SIGKILL loses nothing
    /// written so far. Publishes `/logger/stats` first so drop counts survive a crash too.
    fn periodic_flush(&mut self) {
        if !self.part.as_ref().is_some_and(|p| p.unflushed) {
            return;
        }
        if let Some(t) = self.last_log_time {
            let stats = self.stats();
            let data = serde_json::to_vec(&stats).unwrap_or_default();
            // last_log_time already includes the offset.
            self.emit(Topic::Stats, t.saturating_sub(self.options.time_offset_ns), &data);
        }
        if let Some(part) = self.part.as_mut()
            && let Err(e) = part.flush()
        {
            self.fail(e);
        }
    }

    fn maybe_split(&mut self) {
        let (Some(limit), Some(part)) = (self.options.split_bytes, self.part.as_ref()) else {
            return;
        };
        if part.size.get() < limit {
            return;
        }
        // Flush what is buffered into the compressor so the size is real before deciding.
        if let Err(e) = self.part.as_mut().map_or(Ok(()), Part::flush) {
            self.fail(e);
            return;
        }
        if self.part.as_ref().is_some_and(|p| p.size.get() < limit) {
            return;
        }
        self.flush_pending_flow();
        if let Err(e) = self.finish_part() {
            self.fail(e);
            return;
        }
        self.part_number += 1;
        let path = self.naming.dir.join(part_name(&self.naming.stem, self.naming.split.then_some(self.part_number)));
        match open_new(&path).and_then(|file| Part::open(file, path.clone(), &self.options, self.part_number)) {
            Ok(p) => {
                tracing::debug!(path = %path.display(), "log split");
                self.files.push(path);
                self.part = Some(p);
                for (topic, t, data) in std::mem::take(&mut self.latched) {
                    self.write(topic, t, &data);
                    self.latched.push((topic, t, data));
                }
            }
            Err(e) => self.fail(e),
        }
    }

    fn finish_part(&mut self) -> Result<(), LogError> {
        let Some(part) = self.part.take() else { return Ok(()) };
        let stats = LoggerStats { written: part.written, ..self.shared.stats() };
        let per_topic = std::mem::take(&mut self.per_topic_part);
        part.finish(&stats, &per_topic)?;
        Ok(())
    }

    fn close(mut self) -> Result<LogSummary, LogError> {
        self.flush_pending_flow();
        if let Some(t) = self.last_log_time {
            let s = self.stats();
            let mut line = format!(
                "logger closed: {} messages written, dropped {} images, {} data, {} critical, {} lost",
                s.written + 1,
                s.dropped_images,
                s.dropped_data,
                s.dropped_critical,
                s.lost
            );
            if let Some(live) = &self.options.live {
                let l = live.stats();
                line.push_str(&format!("; live view: {} sent, {} dropped", l.sent, l.dropped));
            }
            let level = if s.dropped() > 0 { LogLevel::Warning } else { LogLevel::Info };
            let data = encode::log_line(t, level, &line);
            self.emit(Topic::Log, t.saturating_sub(self.options.time_offset_ns), &data);
        }
        if let Err(e) = self.finish_part() {
            self.fail(e);
        }
        if let Some(e) = self.error.take() {
            return Err(e);
        }
        Ok(LogSummary { files: self.files.clone(), stats: self.stats(), per_topic: self.per_topic.clone() })
    }
}

/// Upper bound the writer waits before pushing a partial chunk to disk, exposed for docs/tests.
pub const DEFAULT_FLUSH_INTERVAL: Duration = Duration::from_secs(1);

#[cfg(test)]
mod tests {
    use super::*;

    /// A handle whose queue nobody drains: the writer "has fallen behind" for good.
    fn stalled(caps: [usize; 3]) -> (LogHandle, Receiver<Item>) {
        let (tx, rx) = crossbeam_channel::unbounded();
        let shared = Arc::new(Shared {
            caps,
            pending: Default::default(),
            dropped: Default::default(),
            lost: AtomicU64::new(0),
            closed: AtomicBool::new(false),
        });
        (LogHandle { tx, shared }, rx)
    }

    #[test]
    fn a_stalled_writer_drops_images_first_and_never_blocks_setpoints() {
        let (log, rx) = stalled([2, 3, 100]);
        let img = LumaImage::new(4, 4);
        let accepted_images = (0..10).filter(|&i| log.image_mono8(i, &img)).count();
        let accepted_data = (0..10).filter(|&i| log.pose(i, &Pose2D::default())).count();
        let accepted_setpoints = (0..50).filter(|&i| log.setpoint(i, &SetpointLog::default())).count();
        let accepted_odometry = (0..50).filter(|&i| log.odometry(&Odometry { t_ns: i, ..Default::default() })).count();
        assert_eq!((accepted_images, accepted_data, accepted_setpoints, accepted_odometry), (2, 3, 50, 50));
        let d = log.drops();
        assert_eq!((d.dropped_images, d.dropped_data, d.dropped_critical, d.lost), (8, 7, 0, 0));
        // The critical cap is a cap too: past it, set-points are refused and counted, not queued.
        assert!(!log.setpoint(0, &SetpointLog::default()));
        assert_eq!(log.drops().dropped_critical, 1);
        assert_eq!(rx.len(), 2 + 3 + 100);
    }

    #[test]
    fn draining_the_queue_makes_room_again() {
        let (log, rx) = stalled([1, 1, 1]);
        let img = LumaImage::new(2, 2);
        assert!(log.image_mono8(0, &img));
        assert!(!log.image_mono8(1, &img));
        let item = rx.try_recv().unwrap();
        log.shared.pending[item.class()].fetch_sub(1, Ordering::AcqRel);
        assert!(log.image_mono8(2, &img));
        assert_eq!(log.drops().dropped_images, 1);
    }
}
