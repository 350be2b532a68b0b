//! Reading logs back: a record scanner tolerant of truncated files, and [`LogReader`], which
//! yields decoded messages in log-time order for replay.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BinaryHeap, HashMap, VecDeque};
use std::fs::File;
use std::io::{Read, Seek};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use hal::{Calibration, LumaImage, Odometry};
use mcap::records::Record;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

use super::foxglove::{CameraCalibration, CompressedImage, FrameTransform, Log, RawImage};
use super::payload::{BaseStatusLog, GoalLog, LogLevel, LoggerStats, PerceptionLog, Pose2D, SetpointLog, StepInputLog};
use super::{FRAME_BASE, FRAME_ODOM, LogError};
use crate::flow::FlowField;
use base64::Engine as _;
use base64::engine::general_purpose::STANDARD as BASE64;

/// A channel as the file declares it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct ChannelInfo {
    pub id: u16,
    pub topic: String,
    pub schema: String,
    pub schema_encoding: String,
    pub message_encoding: String,
}

/// What [`Scan`] yields.
pub(crate) enum Scanned {
    Message { channel: Arc<ChannelInfo>, sequence: u32, log_time: u64, data: Vec<u8> },
    Metadata { name: String, metadata: BTreeMap<String, String> },
}

/// Walks one MCAP file's records from the start, reading chunks as they come. Stops at the first
/// record it cannot read (a crash mid-chunk) and remembers why, instead of failing: everything
/// before that point is delivered.
pub(crate) struct Scan {
    path: PathBuf,
    file: File,
    reader: LinearReader,
    schemas: HashMap<u16, (String, String)>,
    channels: HashMap<u16, Arc<ChannelInfo>>,
    /// The footer was read: the file was closed cleanly.
    pub complete: bool,
    /// Why reading stopped early, when it did.
    pub stopped: Option<String>,
    /// Records read so far (any kind).
    pub records: u64,
    done: bool,
}

impl Scan {
    pub fn open(path: &Path) -> Result<Self, LogError> {
        let mut file = File::open(path).map_err(|error| LogError::Read { path: path.to_path_buf(), error })?;
        let mut magic = [0u8; 8];
        let n = file.read(&mut magic).map_err(|error| LogError::Read { path: path.to_path_buf(), error })?;
        if magic[..n] != mcap::MAGIC[..n] || n < mcap::MAGIC.len() {
            let message = "it does not start with the MCAP magic bytes (not an MCAP file, or empty)".to_string();
            return Err(LogError::NotMcap { path: path.to_path_buf(), message });
        }
        file.rewind().map_err(|error| LogError::Read { path: path.to_path_buf(), error })?;
        let len = file.metadata().map(|m| m.len()).unwrap_or(u64::MAX);
        // A chunk cut off by a crash still has its placeholder length (2^64 - 1): the limit turns
        // that into an error instead of an attempt to buffer it. Records inside chunks may be
        // larger than the (compressed) file, hence the 1 GiB floor.
        let limit = usize::try_from(len).unwrap_or(usize::MAX).max(1 << 30);
        let options = LinearReaderOptions::default().with_record_length_limit(limit);
        Ok(Self {
            path: path.to_path_buf(),
            file,
            reader: LinearReader::new_with_options(options),
            schemas: HashMap::new(),
            channels: HashMap::new(),
            complete: false,
            stopped: None,
            records: 0,
            done: false,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn stop(&mut self, why: String) -> Result<Option<Scanned>, LogError> {
        self.done = true;
        if self.records == 0 {
            return Err(LogError::NotMcap { path: self.path.clone(), message: why });
        }
        self.stopped = Some(why);
        Ok(None)
    }

    /// The next message or metadata record; `Ok(None)` at the end of the file or where it is cut
    /// off (see [`Scan::stopped`]); an error only when the file is not MCAP at all or unreadable.
    pub fn next_item(&mut self) -> Result<Option<Scanned>, LogError> {
        if self.done {
            return Ok(None);
        }
        loop {
            let event = match self.reader.next_event() {
                None => {
                    self.done = true;
                    return Ok(None);
                }
                Some(Err(e)) => return self.stop(e.to_string()),
                Some(Ok(event)) => event,
            };
            let item = match event {
                LinearReadEvent::ReadRequest(need) => {
                    let n = match self.file.read(self.reader.insert(need)) {
                        Ok(n) => n,
                        Err(error) => return Err(LogError::Read { path: self.path.clone(), error }),
                    };
                    self.reader.notify_read(n);
                    continue;
                }
                LinearReadEvent::Record { opcode, data } => match mcap::parse_record(opcode, data) {
                    Ok(record) => Self::convert(record, &mut self.schemas, &mut self.channels, &mut self.complete),
                    Err(e) => Err(e.to_string()),
                },
            };
            match item {
                Ok(found) => {
                    self.records += 1;
                    if let Some(found) = found {
                        return Ok(Some(found));
                    }
                }
                Err(why) => return self.stop(why),
            }
        }
    }

    fn convert(
        record: Record<'_>,
        schemas: &mut HashMap<u16, (String, String)>,
        channels: &mut HashMap<u16, Arc<ChannelInfo>>,
        complete: &mut bool,
    ) -> Result<Option<Scanned>, String> {
        Ok(match record {
            Record::Schema { header, .. } => {
                schemas.insert(header.id, (header.name, header.encoding));
                None
            }
            Record::Channel(c) => {
                let (schema, schema_encoding) = schemas.get(&c.schema_id).cloned().unwrap_or_default();
                let info = ChannelInfo {
                    id: c.id,
                    topic: c.topic,
                    schema,
                    schema_encoding,
                    message_encoding: c.message_encoding,
                };
                channels.entry(c.id).or_insert_with(|| Arc::new(info));
                None
            }
            Record::Message { header, data } => {
                let channel = channels
                    .get(&header.channel_id)
                    .cloned()
                    .ok_or_else(|| format!("message on undeclared channel {}", header.channel_id))?;
                Some(Scanned::Message {
                    channel,
                    sequence: header.sequence,
                    log_time: header.log_time,
                    data: data.into_owned(),
                })
            }
            Record::Metadata(m) => Some(Scanned::Metadata { name: m.name, metadata: m.metadata }),
            Record::Footer(_) => {
                *complete = true;
                None
            }
            _ => None,
        })
    }
}

/// An image as logged.
#[derive(Clone, Debug, PartialEq)]
pub enum LoggedImage {
    /// `foxglove.RawImage` mono8 (the sim), decoded back to the exact frame.
    Mono8(LumaImage),
    /// `foxglove.CompressedImage`: the camera's JPEG bytes, as they came.
    Jpeg(Vec<u8>),
}

/// One logged message, decoded to flownav's types where the topic is one of flownav's.
#[derive(Clone, Debug, PartialEq)]
pub enum LogEvent {
    /// `/camera/image`.
    Image(LoggedImage),
    /// `/camera/calibration`, when written by flownav (it carries the full calibration).
    Calibration(Box<Calibration>),
    /// `/flow/field`.
    Flow(FlowField),
    /// `/offis/perception`.
    Perception(Box<PerceptionLog>),
    /// `/pafsis/goal`.
    Goal(GoalLog),
    /// `/control/setpoint`.
    Setpoint(SetpointLog),
    /// `/step/input`: what the pipeline consumed (for replay).
    StepInput(StepInputLog),
    /// `/base/odometry`.
    Odometry(Odometry),
    /// `/base/status`.
    BaseStatus(BaseStatusLog),
    /// `/tf` `odom → base_link`: the robot pose.
    Pose(Pose2D),
    /// `/log`.
    Log { level: Option<LogLevel>, message: String },
    /// `/logger/stats`.
    Stats(LoggerStats),
    /// Anything else (`/flow/annotations`, `/sim/world`, the camera mount on `/tf`, foreign
    /// topics): see [`LogEntry::topic`] and [`LogEntry::data`].
    Other,
}

/// One message of a log.
#[derive(Clone, Debug, PartialEq)]
pub struct LogEntry {
    /// Capture time on the logging program's clock (log time minus `time_offset_ns`), ns.
    pub t_ns: u64,
    /// The MCAP log time, ns.
    pub log_time_ns: u64,
    pub topic: String,
    /// Schema name, e.g. `foxglove.RawImage`.
    pub schema: String,
    /// Per-channel sequence number.
    pub sequence: u32,
    /// The message bytes (JSON). Compare these with [`super::encode`]'s output for a bit-exact
    /// replay check.
    pub data: Vec<u8>,
    pub event: LogEvent,
}

/// Reads one log (or the parts of a split log, in order) and yields its messages in log-time
/// order, decoded ([`LogEntry::event`]).
///
/// Messages are written in call order, which can differ slightly from capture-time order between
/// topics (odometry and frames come from different tasks); the reader re-sorts within a window
/// ([`LogReader::with_window_ns`], default 2 s of log time): the output is exactly sorted by
/// (log time, file order) as long as no message was logged more than the window after a later
/// one. A file cut off by a crash ends early without error: see [`LogReader::truncated`].
///
/// ```no_run
/// use flownav::logging::{LogEvent, LogReader, LoggedImage};
/// for entry in LogReader::open("logs/flownav-20260101-120000-sim.mcap")? {
///     let entry = entry?;
///     match entry.event {
///         LogEvent::Image(LoggedImage::Mono8(frame)) => { /* run the step on (entry.t_ns, frame) */ }
///         LogEvent::Odometry(odometry) => { /* feed it to the step's state */ }
///         LogEvent::Setpoint(logged) => { /* compare with the recomputed set-point */ }
///         _ => {}
///     }
/// }
/// # Ok::<(), flownav::logging::LogError>(())
/// ```
pub struct LogReader {
    pending_files: VecDeque<PathBuf>,
    scan: Option<Scan>,
    offset_ns: u64,
    heap: BinaryHeap<Reverse<Queued>>,
    order: u64,
    max_seen: u64,
    window_ns: u64,
    truncated: Vec<(PathBuf, String)>,
    metadata: Vec<(String, BTreeMap<String, String>)>,
}

struct Queued {
    log_time: u64,
    order: u64,
    entry: LogEntry,
}

impl PartialEq for Queued {
    fn eq(&self, other: &Self) -> bool {
        (self.log_time, self.order) == (other.log_time, other.order)
    }
}
impl Eq for Queued {}
impl PartialOrd for Queued {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Queued {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (self.log_time, self.order).cmp(&(other.log_time, other.order))
    }
}

impl LogReader {
    /// Opens one file.
    pub fn open(path: impl AsRef<Path>) -> Result<Self, LogError> {
        Self::open_parts([path.as_ref().to_path_buf()])
    }

    /// Opens the parts of a split log, read one after the other in the given order.
    pub fn open_parts(paths: impl IntoIterator<Item = PathBuf>) -> Result<Self, LogError> {
        let mut pending_files: VecDeque<PathBuf> = paths.into_iter().collect();
        let first = pending_files
            .pop_front()
            .ok_or_else(|| LogError::Option { name: "log files", problem: "must name at least one file".into() })?;
        Ok(Self {
            pending_files,
            scan: Some(Scan::open(&first)?),
            offset_ns: 0,
            heap: BinaryHeap::new(),
            order: 0,
            max_seen: 0,
            window_ns: 2_000_000_000,
            truncated: Vec::new(),
            metadata: Vec::new(),
        })
    }

    /// Sets the re-sorting window, ns of log time (0 = file order).
    pub fn with_window_ns(mut self, window_ns: u64) -> Self {
        self.window_ns = window_ns;
        self
    }

    /// Files that ended without their footer (a crash), with the reason reading stopped. Complete
    /// once the iterator is exhausted.
    pub fn truncated(&self) -> &[(PathBuf, String)] {
        &self.truncated
    }

    /// Metadata records seen so far (`flownav.header`, `flownav.config`, `flownav.stats`, ...).
    pub fn metadata(&self) -> &[(String, BTreeMap<String, String>)] {
        &self.metadata
    }

    /// Reads the next message from the files into the heap; `false` when all are exhausted.
    fn fill_one(&mut self) -> Result<bool, LogError> {
        loop {
            let Some(scan) = self.scan.as_mut() else { return Ok(false) };
            match scan.next_item()? {
                Some(Scanned::Metadata { name, metadata }) => {
                    if name == "flownav.header" {
                        self.offset_ns = metadata.get("time_offset_ns").and_then(|v| v.parse().ok()).unwrap_or(0);
                    }
                    self.metadata.push((name, metadata));
                }
                Some(Scanned::Message { channel, sequence, log_time, data }) => {
                    let path = scan.path().to_path_buf();
                    let event = decode(&channel, &data).map_err(|message| LogError::Decode {
                        path,
                        topic: channel.topic.clone(),
                        log_time_ns: log_time,
                        message,
                    })?;
                    let entry = LogEntry {
                        t_ns: log_time.saturating_sub(self.offset_ns),
                        log_time_ns: log_time,
                        topic: channel.topic.clone(),
                        schema: channel.schema.clone(),
                        sequence,
                        data,
                        event,
                    };
                    self.max_seen = self.max_seen.max(log_time);
                    self.heap.push(Reverse(Queued { log_time, order: self.order, entry }));
                    self.order += 1;
                    return Ok(true);
                }
                None => {
                    if !scan.complete {
                        let why = scan.stopped.clone().unwrap_or_else(|| "no footer".into());
                        self.truncated.push((scan.path().to_path_buf(), why));
                    }
                    self.scan = match self.pending_files.pop_front() {
                        Some(next) => Some(Scan::open(&next)?),
                        None => None,
                    };
                    self.offset_ns = 0;
                }
            }
        }
    }
}

impl Iterator for LogReader {
    type Item = Result<LogEntry, LogError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(Reverse(top)) = self.heap.peek()
                && top.log_time.saturating_add(self.window_ns) <= self.max_seen
            {
                return self.heap.pop().map(|Reverse(q)| Ok(q.entry));
            }
            match self.fill_one() {
                Ok(true) => continue,
                Ok(false) => return self.heap.pop().map(|Reverse(q)| Ok(q.entry)),
                Err(e) => {
                    self.scan = None;
                    self.pending_files.clear();
                    return Some(Err(e));
                }
            }
        }
    }
}

fn parse<'a, T: serde::Deserialize<'a>>(data: &'a [u8]) -> Result<T, String> {
    serde_json::from_slice(data).map_err(|e| e.to_string())
}

/// Decodes one message by its schema name; foreign or decorative topics give [`LogEvent::Other`].
fn decode(channel: &ChannelInfo, data: &[u8]) -> Result<LogEvent, String> {
    if channel.message_encoding != "json" {
        return Ok(LogEvent::Other);
    }
    Ok(match channel.schema.as_str() {
        "foxglove.RawImage" => {
            let m: RawImage = parse(data)?;
            if m.encoding != "mono8" {
                return Ok(LogEvent::Other);
            }
            let bytes = BASE64.decode(&m.data).map_err(|e| format!("image data is not valid base64: {e}"))?;
            let (w, h, step) = (m.width as usize, m.height as usize, m.step as usize);
            if step < w || bytes.len() < step * h.saturating_sub(1) + w {
                return Err(format!("mono8 image {w}x{h} step {step} has only {} bytes", bytes.len()));
            }
            let mut pixels = Vec::with_capacity(w * h);
            for row in 0..h {
                pixels.extend_from_slice(&bytes[row * step..row * step + w]);
            }
            let image = LumaImage::from_vec(w, h, pixels).ok_or("image size mismatch")?;
            LogEvent::Image(LoggedImage::Mono8(image))
        }
        "foxglove.CompressedImage" => {
            let m: CompressedImage = parse(data)?;
            if m.format != "jpeg" {
                return Ok(LogEvent::Other);
            }
            LogEvent::Image(LoggedImage::Jpeg(
                BASE64.decode(&m.data).map_err(|e| format!("image data is not valid base64: {e}"))?,
            ))
        }
        "foxglove.CameraCalibration" => match parse::<CameraCalibration>(data)?.flownav_calibration {
            Some(c) => LogEvent::Calibration(Box::new(c)),
            None => LogEvent::Other,
        },
        "foxglove.FrameTransform" => {
            let tf: FrameTransform = parse(data)?;
            if tf.parent_frame_id == FRAME_ODOM && tf.child_frame_id == FRAME_BASE {
                let q = tf.rotation;
                LogEvent::Pose(Pose2D { x_m: tf.translation.x, y_m: tf.translation.y, theta_rad: 2.0 * q.z.atan2(q.w) })
            } else {
                LogEvent::Other
            }
        }
        "foxglove.Log" => {
            let m: Log = parse(data)?;
            LogEvent::Log { level: LogLevel::from_u8(m.level), message: m.message }
        }
        "flownav.FlowField" => LogEvent::Flow(parse(data)?),
        "flownav.Perception" => LogEvent::Perception(Box::new(parse(data)?)),
        "flownav.Goal" => LogEvent::Goal(parse(data)?),
        "flownav.Setpoint" => LogEvent::Setpoint(parse(data)?),
        "flownav.StepInput" => LogEvent::StepInput(parse(data)?),
        "flownav.Odometry" => LogEvent::Odometry(parse(data)?),
        "flownav.BaseStatus" => LogEvent::BaseStatus(parse(data)?),
        "flownav.LoggerStats" => LogEvent::Stats(parse(data)?),
        _ => LogEvent::Other,
    })
}
