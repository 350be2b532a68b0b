//! Run logs as MCAP files that open in Foxglove, survive a crash, and can be read back for replay.
//!
//! - [`LogWriter`] / [`LogHandle`] (writer side): typed methods per topic, called from the
//!   control path; a dedicated thread encodes (JSON), compresses (zstd chunks) and writes. The
//!   control path never blocks: when the writer falls behind, images are dropped first, and
//!   set-points and odometry only past a large cap; every drop is counted and written to the file.
//! - [`LogReader`] (reading side): the messages back in log-time order, decoded to flownav types
//!   (frames as [`hal::LumaImage`] or JPEG bytes, odometry, perception, set-points, ...),
//!   tolerant of a file cut short by a crash.
//! - [`LogInfo`]: what `flownav log info` prints (topics, counts, times, drops, truncation).
//! - [`LiveServer`] / [`LiveSink`] (`--live`): the same messages, as the writer thread encodes
//!   them, served to Foxglove over WebSocket; dropped and counted when the viewer side falls behind.
//!
//! Encoding: every channel is JSON with a JSON schema (`jsonschema`). Foxglove's own types
//! (`foxglove.CompressedImage`, `RawImage`, `CameraCalibration`, `ImageAnnotations`,
//! `FrameTransform`, `SceneUpdate`, `Log`) are recognised by schema name in JSON just as in
//! protobuf; flownav's own types (`flownav.*`) are plain JSON. docs/logging.md says why JSON and
//! not the `foxglove` crate's protobuf.

pub mod encode;
pub mod foxglove;
mod info;
pub mod live;
pub mod payload;
mod reader;
pub mod record;
pub mod sample;
mod writer;

use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

pub use info::{LogInfo, TopicInfo};
pub use live::{LiveImages, LiveServer, LiveSink, LiveStats};
pub use payload::{
    BaseStatusLog, GoalLog, LogLevel, LoggerStats, PerceptionLog, Pose2D, SetpointLog, StepInputLog, WorldBox,
    WorldCylinder, WorldGeometry,
};
pub use reader::{LogEntry, LogEvent, LogReader, LoggedImage};
pub use writer::{LogHandle, LogSummary, LogWriter};

/// Schema encoding of every channel.
pub const SCHEMA_ENCODING: &str = "jsonschema";
/// The odometry (world) frame.
pub const FRAME_ODOM: &str = "odom";
/// The robot frame (REP-103).
pub const FRAME_BASE: &str = "base_link";
/// The camera's optical frame (x right, y down, z forward), named as ROS names optical frames
/// (REP-103's `_optical_frame` suffix), so a flownav log's TF tree lines up with a ROS robot's.
pub const FRAME_CAMERA: &str = "camera_optical_frame";

/// Errors of the logger and the log reader.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("cannot create log directory {}: {error} (pass --log DIR with a writable directory)", path.display())]
    CreateDir { path: PathBuf, error: std::io::Error },
    #[error("log file {} already exists; flownav never overwrites a log (remove it or choose another name)", path.display())]
    Exists { path: PathBuf },
    #[error("cannot create log file {}: {error} (pass --log DIR with a writable directory)", path.display())]
    Create { path: PathBuf, error: std::io::Error },
    #[error("cannot write log file {}: {message} (disk full or file removed? logging stopped, the run went on)", path.display())]
    Write { path: PathBuf, message: String },
    #[error("cannot read log file {}: {error}", path.display())]
    Read { path: PathBuf, error: std::io::Error },
    #[error("{} is not a flownav MCAP log: {message}", path.display())]
    NotMcap { path: PathBuf, message: String },
    #[error("{}: message on {topic} at {log_time_ns} ns cannot be decoded: {message}", path.display())]
    Decode { path: PathBuf, topic: String, log_time_ns: u64, message: String },
    #[error("logging option {name} {problem}")]
    Option { name: &'static str, problem: String },
    #[error("the log writer thread panicked; the file may lack its summary (flownav log info still reads it)")]
    Panicked,
}

/// How a log is written. `Default` gives the values documented in docs/logging.md.
#[derive(Clone, Debug)]
pub struct LogOptions {
    /// `run` or `sim` (any short word): the last part of the default file name.
    pub kind: String,
    /// Start a new file when the current one reaches this many bytes (`--log-split-mb`).
    pub split_bytes: Option<u64>,
    /// Target uncompressed chunk size, bytes (MCAP `chunk_size`).
    pub chunk_bytes: u64,
    /// Longest time data waits before its chunk is finished and handed to the OS: a SIGKILL
    /// loses at most this much.
    pub flush_interval: Duration,
    /// Images waiting at most; more are dropped (the writer is behind).
    pub image_queue: usize,
    /// Flow, perception, goal, status, pose, world and log messages waiting at most.
    pub data_queue: usize,
    /// Set-points and odometry waiting at most (never reached unless the disk stalls for minutes).
    pub critical_queue: usize,
    /// Added to every `t_ns` to form the file's log time (e.g. monotonic → wall clock, see
    /// [`wall_clock_offset_ns`]); recorded in the `flownav.header` metadata and subtracted again
    /// by [`LogReader`], so replay sees the original capture times.
    pub time_offset_ns: u64,
    /// zstd level (0 = zstd's default, 3).
    pub compression_level: u32,
    /// Extra metadata records written at the start of every file (e.g. `flownav.config` with the
    /// configuration, so a replay can rebuild it).
    pub metadata: Vec<(String, BTreeMap<String, String>)>,
    /// The live view (`--live`): every message written to the file is offered to it too.
    pub live: Option<LiveSink>,
}

impl Default for LogOptions {
    fn default() -> Self {
        Self {
            kind: "run".into(),
            split_bytes: None,
            chunk_bytes: 1024 * 1024,
            flush_interval: writer::DEFAULT_FLUSH_INTERVAL,
            image_queue: 8,
            data_queue: 4096,
            critical_queue: 1 << 18,
            time_offset_ns: 0,
            compression_level: 0,
            metadata: Vec::new(),
            live: None,
        }
    }
}

impl LogOptions {
    /// Defaults for a run of the given kind (`run`, `sim`).
    pub fn new(kind: &str) -> Self {
        Self { kind: kind.into(), ..Self::default() }
    }

    /// Splits files at `mb` MB (10^6 bytes), as `--log-split-mb` takes it.
    pub fn split_mb(mut self, mb: f64) -> Self {
        self.split_bytes = Some((mb * 1e6).max(0.0) as u64);
        self
    }

    fn validate(&self) -> Result<(), LogError> {
        let bad = |name, problem: &str| Err(LogError::Option { name, problem: problem.into() });
        if self.kind.is_empty() || !self.kind.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-') {
            return bad("kind", "must be a short word of letters, digits, '-' or '_' (it goes into the file name)");
        }
        if self.split_bytes.is_some_and(|b| b < 64 * 1024) {
            return bad("--log-split-mb", "must be at least 0.065 MB (64 KiB), or left out to write one file");
        }
        if self.chunk_bytes == 0 {
            return bad("chunk_bytes", "must be positive");
        }
        if self.flush_interval.is_zero() {
            return bad("flush_interval", "must be positive");
        }
        if self.image_queue == 0 || self.data_queue == 0 || self.critical_queue == 0 {
            return bad("queue caps", "must be positive");
        }
        if self.compression_level > 22 {
            return bad("compression_level", "must be 0 (default) to 22");
        }
        Ok(())
    }
}

/// The offset that turns a monotonic capture time into wall-clock time: call it once at start
/// with the current monotonic time `now_t_ns`, put it in [`LogOptions::time_offset_ns`], and
/// Foxglove shows real dates.
pub fn wall_clock_offset_ns(now_t_ns: u64) -> u64 {
    let wall = SystemTime::now().duration_since(SystemTime::UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0);
    wall.saturating_sub(now_t_ns)
}

/// The channels flownav writes: topic name, schema name and JSON schema.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(crate) enum Topic {
    ImageCompressed,
    ImageRaw,
    Calibration,
    CameraMount,
    FlowAnnotations,
    FlowField,
    Perception,
    Goal,
    Setpoint,
    Odometry,
    BaseStatus,
    RobotPose,
    World,
    Log,
    Stats,
    StepInput,
}

impl Topic {
    pub(crate) const COUNT: usize = 16;

    pub(crate) const ALL: [Topic; Topic::COUNT] = [
        Topic::ImageCompressed,
        Topic::ImageRaw,
        Topic::Calibration,
        Topic::CameraMount,
        Topic::FlowAnnotations,
        Topic::FlowField,
        Topic::Perception,
        Topic::Goal,
        Topic::Setpoint,
        Topic::Odometry,
        Topic::BaseStatus,
        Topic::RobotPose,
        Topic::World,
        Topic::Log,
        Topic::Stats,
        Topic::StepInput,
    ];

    pub(crate) fn name(self) -> &'static str {
        match self {
            Topic::ImageCompressed | Topic::ImageRaw => "/camera/image",
            Topic::Calibration => "/camera/calibration",
            Topic::CameraMount | Topic::RobotPose => "/tf",
            Topic::FlowAnnotations => "/flow/annotations",
            Topic::FlowField => "/flow/field",
            Topic::Perception => "/offis/perception",
            Topic::Goal => "/pafsis/goal",
            Topic::Setpoint => "/control/setpoint",
            Topic::Odometry => "/base/odometry",
            Topic::BaseStatus => "/base/status",
            Topic::World => "/sim/world",
            Topic::Log => "/log",
            Topic::Stats => "/logger/stats",
            Topic::StepInput => "/step/input",
        }
    }

    pub(crate) fn schema_name(self) -> &'static str {
        match self {
            Topic::ImageCompressed => "foxglove.CompressedImage",
            Topic::ImageRaw => "foxglove.RawImage",
            Topic::Calibration => "foxglove.CameraCalibration",
            Topic::CameraMount | Topic::RobotPose => "foxglove.FrameTransform",
            Topic::FlowAnnotations => "foxglove.ImageAnnotations",
            Topic::FlowField => "flownav.FlowField",
            Topic::Perception => "flownav.Perception",
            Topic::Goal => "flownav.Goal",
            Topic::Setpoint => "flownav.Setpoint",
            Topic::Odometry => "flownav.Odometry",
            Topic::BaseStatus => "flownav.BaseStatus",
            Topic::World => "foxglove.SceneUpdate",
            Topic::Log => "foxglove.Log",
            Topic::Stats => "flownav.LoggerStats",
            Topic::StepInput => "flownav.StepInput",
        }
    }

    pub(crate) fn schema(self) -> serde_json::Value {
        match self {
            Topic::ImageCompressed => foxglove::compressed_image_schema(),
            Topic::ImageRaw => foxglove::raw_image_schema(),
            Topic::Calibration => foxglove::camera_calibration_schema(),
            Topic::CameraMount | Topic::RobotPose => foxglove::frame_transform_schema(),
            Topic::FlowAnnotations => foxglove::image_annotations_schema(),
            Topic::FlowField => payload::flow_field_schema(),
            Topic::Perception => payload::perception_schema(),
            Topic::Goal => payload::goal_schema(),
            Topic::Setpoint => payload::setpoint_schema(),
            Topic::Odometry => payload::odometry_schema(),
            Topic::BaseStatus => payload::base_status_schema(),
            Topic::World => foxglove::scene_update_schema(),
            Topic::Log => foxglove::log_schema(),
            Topic::Stats => payload::stats_schema(),
            Topic::StepInput => payload::step_input_schema(),
        }
    }
}

/// `flownav-<YYYYmmdd-HHMMSS>-<kind>` for a UTC time.
pub fn default_file_name(now: SystemTime, kind: &str) -> String {
    let secs = now.duration_since(SystemTime::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    let (days, rem) = (secs / 86_400, secs % 86_400);
    let (y, m, d) = civil_from_days(days as i64);
    format!("flownav-{y:04}{m:02}{d:02}-{:02}{:02}{:02}-{kind}", rem / 3600, rem % 3600 / 60, rem % 60)
}

/// Days since 1970-01-01 → (year, month, day), proleptic Gregorian (H. Hinnant's algorithm).
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    (yoe + era * 400 + i64::from(m <= 2), m, d)
}

/// Creates `path`, refusing to overwrite an existing file.
fn open_new(path: &Path) -> Result<File, LogError> {
    File::options().write(true).create_new(true).open(path).map_err(|error| {
        if error.kind() == std::io::ErrorKind::AlreadyExists {
            LogError::Exists { path: path.to_path_buf() }
        } else {
            LogError::Create { path: path.to_path_buf(), error }
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names_use_utc_calendar_dates() {
        let at = |s: u64| SystemTime::UNIX_EPOCH + Duration::from_secs(s);
        assert_eq!(default_file_name(at(0), "sim"), "flownav-19700101-000000-sim");
        // 2024-02-29 23:59:59 UTC (a leap day).
        assert_eq!(default_file_name(at(1_709_251_199), "run"), "flownav-20240229-235959-run");
        assert_eq!(default_file_name(at(1_709_251_200), "run"), "flownav-20240301-000000-run");
    }

    #[test]
    fn topics_are_absolute_and_schemas_named_consistently() {
        use Topic::*;
        let all = [
            ImageCompressed,
            ImageRaw,
            Calibration,
            CameraMount,
            FlowAnnotations,
            FlowField,
            Perception,
            Goal,
            Setpoint,
            Odometry,
            BaseStatus,
            RobotPose,
            World,
            Log,
            Stats,
            StepInput,
        ];
        assert_eq!(all.len(), Topic::COUNT);
        for t in all {
            assert!(t.name().starts_with('/'));
            assert_eq!(t.schema()["title"], t.schema_name(), "{t:?}");
        }
    }

    #[test]
    fn bad_options_are_named() {
        let e = LogOptions::new("sim").split_mb(0.001).validate().unwrap_err();
        assert!(e.to_string().contains("--log-split-mb"), "{e}");
        let e = LogOptions::new("a b").validate().unwrap_err();
        assert!(e.to_string().contains("kind"), "{e}");
    }
}
