//! The V4L2 camera (`/dev/videoN`): device listing, strict format negotiation, mmap streaming
//! with the driver's timestamps, MJPEG/YUYV → luma, unplug and stall detection.
//!
//! Format, size and frame rate are negotiated exactly as configured in [`CameraConfig`]: when
//! the device does not offer them the camera refuses to open and the error lists what it does
//! offer. There is no silent fallback — flow magnitudes, calibration and timing all depend on
//! the negotiated mode.
//!
//! Streaming uses its own small mmap buffer ring on top of the `v4l` crate's device handle and
//! ioctl bindings rather than `v4l::io::mmap::Stream`: in v4l 0.14 `Stream::next` re-queues its
//! last buffer on every call, even when the previous call timed out without dequeuing one, so the
//! call after a timeout fails with `EINVAL` (the kernel still owns that buffer); its arena is
//! private, so a wrapper cannot avoid it. Here a buffer is re-queued only after a successful
//! `VIDIOC_DQBUF`, and `capture` waits with `poll(2)` for at most the stall timeout.

use crate::camera::{Camera, monotonic_ns};
use crate::error::{Error, ErrorKind};
use crate::image::{Frame, LumaImage};
use crate::mjpeg::{MjpegDecoder, MjpegError};
use crate::yuyv::{YuyvError, yuyv_to_luma};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::io;
use std::os::raw::c_void;
use std::path::{Path, PathBuf};
use v4l::frameinterval::FrameIntervalEnum;
use v4l::framesize::FrameSizeEnum;
use v4l::v4l_sys;
use v4l::video::Capture;
use v4l::{Device, FourCC, Fraction};

/// Number of mmap buffers requested from the driver: enough to absorb a slow frame without the
/// driver dropping one, few enough that a dequeued frame is at most ~3 frame periods old.
const BUFFER_COUNT: u32 = 4;

/// Pixel format requested from the camera.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PixelFormat {
    /// Motion-JPEG (`MJPG`): compressed, full frame rate at 1280×720 over USB 2.
    #[default]
    Mjpeg,
    /// YUYV 4:2:2 (`YUYV`): uncompressed, no decode cost, bandwidth-limited at high resolution.
    Yuyv,
}

impl PixelFormat {
    /// The V4L2 four-character code.
    pub fn fourcc(self) -> [u8; 4] {
        match self {
            PixelFormat::Mjpeg => *b"MJPG",
            PixelFormat::Yuyv => *b"YUYV",
        }
    }

    /// The name used in the config file.
    pub fn name(self) -> &'static str {
        match self {
            PixelFormat::Mjpeg => "mjpeg",
            PixelFormat::Yuyv => "yuyv",
        }
    }
}

/// The `[camera]` table of the config file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraConfig {
    /// Device node, default `/dev/video0` (`--camera` overrides it).
    pub device: PathBuf,
    /// Frame width in pixels, default 1280.
    pub width: u32,
    /// Frame height in pixels, default 720.
    pub height: u32,
    /// Frame rate in frames per second, default 30; must be one the device lists for this
    /// format and size (within 1 %). Also the playback rate of a frame folder without
    /// `odometry.csv`.
    pub fps: f64,
    /// `mjpeg` (default) or `yuyv`.
    pub format: PixelFormat,
    /// A capture that waits longer than this for a frame fails with a `Timeout` error, default
    /// 500 ms.
    pub stall_timeout_ms: u64,
}

impl Default for CameraConfig {
    fn default() -> Self {
        Self {
            device: PathBuf::from("/dev/video0"),
            width: 1280,
            height: 720,
            fps: 30.0,
            format: PixelFormat::Mjpeg,
            stall_timeout_ms: 500,
        }
    }
}

/// A `[camera]` field out of range: `field` is the key inside the table.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("camera.{field} {problem}")]
pub struct InvalidCameraConfig {
    pub field: &'static str,
    pub problem: String,
}

impl CameraConfig {
    /// Checks ranges serde cannot.
    pub fn validate(&self) -> Result<(), InvalidCameraConfig> {
        let bad = |field, problem: String| Err(InvalidCameraConfig { field, problem });
        if self.device.as_os_str().is_empty() {
            return bad("device", "must name a device node such as /dev/video0".into());
        }
        for (field, v) in [("width", self.width), ("height", self.height)] {
            if !(16..=8192).contains(&v) {
                return bad(field, format!("is {v}; must be in 16..=8192 pixels"));
            }
        }
        if self.format == PixelFormat::Yuyv && !self.width.is_multiple_of(2) {
            return bad("width", format!("is {}; YUYV packs pixel pairs, so it must be even", self.width));
        }
        if !(self.fps.is_finite() && self.fps > 0.0 && self.fps <= 240.0) {
            return bad("fps", format!("is {}; must be in (0, 240] frames per second", self.fps));
        }
        let frame_ms = 1000.0 / self.fps;
        if (self.stall_timeout_ms as f64) < 2.0 * frame_ms || self.stall_timeout_ms > 60_000 {
            return bad(
                "stall_timeout_ms",
                format!(
                    "is {}; must be at least two frame periods ({:.0} ms at {} fps) and at most 60000",
                    self.stall_timeout_ms,
                    (2.0 * frame_ms).ceil(),
                    self.fps
                ),
            );
        }
        Ok(())
    }
}

/// What went wrong with a V4L2 camera; [`Error::kind`] tells the runtime what to do.
#[derive(Debug, thiserror::Error)]
pub enum V4l2Error {
    #[error(
        "camera {path} does not exist: is it plugged in? `flownav devices` lists the cameras present \
         (or pass --camera frames:DIR to play a frame folder)"
    )]
    NotFound { path: PathBuf },
    #[error(
        "no permission to open camera {path}: add your user to the `video` group \
         (`sudo usermod -aG video $USER`, then log in again) or install the udev rule in docs/camera.md"
    )]
    PermissionDenied { path: PathBuf },
    #[error("camera {path} is busy: another program is streaming from it (close it, or check `fuser {path}`)")]
    Busy { path: PathBuf },
    #[error("{path} is not a V4L2 video device ({detail}); `flownav devices` lists the cameras present")]
    NotVideoDevice { path: PathBuf, detail: String },
    #[error("camera {path} was disconnected (unplugged or USB reset) during {op}: {source}")]
    Disconnected { path: PathBuf, op: &'static str, source: io::Error },
    #[error("camera {path} cannot do {wanted}: {problem}. It supports:\n{supported}")]
    Unsupported { path: PathBuf, wanted: String, problem: String, supported: String },
    #[error(
        "camera {path}: no frame within {timeout_ms} ms (stalled camera, too dark for the frame rate, or USB bandwidth)"
    )]
    Stall { path: PathBuf, timeout_ms: u64 },
    #[error("camera {path}: the driver flagged frame {driver_seq} as corrupt; skipped")]
    CorruptFrame { path: PathBuf, driver_seq: u32 },
    #[error("camera {path}: frame is {width}x{height}, but {want_width}x{want_height} was negotiated")]
    FrameSize { path: PathBuf, width: usize, height: usize, want_width: u32, want_height: u32 },
    #[error("camera {path}: {source}")]
    Mjpeg { path: PathBuf, source: MjpegError },
    #[error("camera {path}: {source}")]
    Yuyv { path: PathBuf, source: YuyvError },
    #[error("camera {path}: {op} failed: {source}")]
    Io { path: PathBuf, op: &'static str, source: io::Error },
}

impl Error for V4l2Error {
    fn kind(&self) -> ErrorKind {
        match self {
            V4l2Error::NotFound { .. } | V4l2Error::Disconnected { .. } => ErrorKind::Disconnected,
            V4l2Error::Stall { .. } => ErrorKind::Timeout,
            V4l2Error::CorruptFrame { .. }
            | V4l2Error::FrameSize { .. }
            | V4l2Error::Mjpeg { .. }
            | V4l2Error::Yuyv { .. } => ErrorKind::BadData,
            V4l2Error::Unsupported { .. } | V4l2Error::NotVideoDevice { .. } => ErrorKind::Unsupported,
            V4l2Error::PermissionDenied { .. } | V4l2Error::Busy { .. } | V4l2Error::Io { .. } => ErrorKind::Other,
        }
    }
}

/// Whether an errno means the device node is gone (USB unplug, hub reset).
fn is_gone(e: &io::Error) -> bool {
    matches!(e.raw_os_error(), Some(libc::ENODEV | libc::ENXIO | libc::ESHUTDOWN | libc::EIO))
}

/// Maps an I/O error of operation `op` on `path` to the error a user can act on.
fn io_error(path: &Path, op: &'static str, e: io::Error) -> V4l2Error {
    let path = path.to_path_buf();
    match e.raw_os_error() {
        Some(libc::ENOENT) => V4l2Error::NotFound { path },
        Some(libc::EACCES | libc::EPERM) => V4l2Error::PermissionDenied { path },
        Some(libc::EBUSY) => V4l2Error::Busy { path },
        Some(libc::ENOTTY) => V4l2Error::NotVideoDevice { path, detail: format!("{op}: {e}") },
        _ if is_gone(&e) => V4l2Error::Disconnected { path, op, source: e },
        _ => V4l2Error::Io { path, op, source: e },
    }
}

/// Frame rates offered for one size.
#[derive(Clone, Debug, PartialEq)]
pub enum Rates {
    /// Discrete rates, frames per second.
    Discrete(Vec<f64>),
    /// Any rate in `min_fps..=max_fps`.
    Range { min_fps: f64, max_fps: f64 },
}

/// Frame sizes offered for one format.
#[derive(Clone, Debug, PartialEq)]
pub enum Sizes {
    /// Discrete sizes, each with its rates.
    Discrete(Vec<(u32, u32, Rates)>),
    /// Any size in a range, with a step (rates are then per size; see `v4l2-ctl --list-formats-ext`).
    Stepwise { min: (u32, u32), max: (u32, u32), step: (u32, u32) },
}

/// One pixel format a device offers.
#[derive(Clone, Debug, PartialEq)]
pub struct FormatInfo {
    /// Four-character code, e.g. `MJPG`, `YUYV`.
    pub fourcc: String,
    /// The driver's description, e.g. `Motion-JPEG`.
    pub description: String,
    pub sizes: Sizes,
}

/// A V4L2 device node and what it can capture.
#[derive(Clone, Debug, PartialEq)]
pub struct DeviceInfo {
    pub path: PathBuf,
    pub driver: String,
    pub card: String,
    pub bus: String,
    /// Whether the node captures video (UVC cameras also expose a metadata-only node).
    pub capture: bool,
    pub formats: Vec<FormatInfo>,
}

fn fps_of(interval: Fraction) -> f64 {
    if interval.numerator == 0 { 0.0 } else { f64::from(interval.denominator) / f64::from(interval.numerator) }
}

fn fmt_fps(fps: f64) -> String {
    let s = format!("{fps:.3}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

impl fmt::Display for Rates {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Rates::Discrete(r) if r.is_empty() => write!(f, "(no frame rates listed)"),
            Rates::Discrete(r) => write!(f, "{} fps", r.iter().map(|&x| fmt_fps(x)).collect::<Vec<_>>().join(", ")),
            Rates::Range { min_fps, max_fps } => write!(f, "{}–{} fps", fmt_fps(*min_fps), fmt_fps(*max_fps)),
        }
    }
}

impl fmt::Display for FormatInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "  {} ({})", self.fourcc, self.description)?;
        match &self.sizes {
            Sizes::Discrete(sizes) if sizes.is_empty() => writeln!(f, "    (no frame sizes listed)"),
            Sizes::Discrete(sizes) => {
                for (w, h, rates) in sizes {
                    writeln!(f, "    {w}x{h} @ {rates}")?;
                }
                Ok(())
            }
            Sizes::Stepwise { min, max, step } => {
                writeln!(f, "    {}x{} to {}x{} in steps of {}x{}", min.0, min.1, max.0, max.1, step.0, step.1)
            }
        }
    }
}

impl fmt::Display for DeviceInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "{}: {} (driver {}, bus {})", self.path.display(), self.card, self.driver, self.bus)?;
        if !self.capture {
            return writeln!(f, "  (no video capture: a metadata or output node; use another /dev/video*)");
        }
        for format in &self.formats {
            write!(f, "{format}")?;
        }
        Ok(())
    }
}

fn supported_list(formats: &[FormatInfo]) -> String {
    if formats.is_empty() {
        return "  (no capture formats)\n".into();
    }
    formats.iter().map(ToString::to_string).collect()
}

/// Device capabilities read with our own `VIDIOC_QUERYCAP` (the v4l crate's conversion panics on
/// names that are not UTF-8; this one never does).
fn query_caps(dev: &Device) -> io::Result<(String, String, String, u32)> {
    // SAFETY: v4l2_capability is plain old data; zero is a valid bit pattern.
    let mut caps: v4l_sys::v4l2_capability = unsafe { std::mem::zeroed() };
    // SAFETY: VIDIOC_QUERYCAP writes one v4l2_capability into the pointed-to struct.
    unsafe {
        v4l::v4l2::ioctl(dev.handle().fd(), v4l::v4l2::vidioc::VIDIOC_QUERYCAP, &mut caps as *mut _ as *mut c_void)?;
    }
    let text = c_text;
    let flags =
        if caps.capabilities & v4l_sys::V4L2_CAP_DEVICE_CAPS != 0 { caps.device_caps } else { caps.capabilities };
    Ok((text(&caps.driver), text(&caps.card), text(&caps.bus_info), flags))
}

fn is_capture(flags: u32) -> bool {
    flags & v4l_sys::V4L2_CAP_VIDEO_CAPTURE != 0 && flags & v4l_sys::V4L2_CAP_STREAMING != 0
}

/// Whether an enumeration ioctl failing at index 0 just means "nothing listed" (the driver does
/// not enumerate this), rather than a real error.
fn nothing_listed(e: &io::Error) -> bool {
    matches!(e.raw_os_error(), Some(libc::EINVAL | libc::ENOTTY))
}

/// Pixel formats of a capture device, with our own `VIDIOC_ENUM_FMT` loop (the v4l crate's
/// conversion panics on descriptions that are not UTF-8).
fn enum_formats(dev: &Device) -> io::Result<Vec<(FourCC, String)>> {
    let mut out = Vec::new();
    for index in 0.. {
        // SAFETY: v4l2_fmtdesc is plain old data; zero is a valid bit pattern.
        let mut desc: v4l_sys::v4l2_fmtdesc = unsafe { std::mem::zeroed() };
        desc.index = index;
        desc.type_ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
        // SAFETY: VIDIOC_ENUM_FMT reads the index/type and fills one v4l2_fmtdesc.
        let r = unsafe {
            v4l::v4l2::ioctl(dev.handle().fd(), v4l::v4l2::vidioc::VIDIOC_ENUM_FMT, &mut desc as *mut _ as *mut c_void)
        };
        match r {
            Ok(()) => out.push((FourCC::from(desc.pixelformat), c_text(&desc.description))),
            Err(e) if index > 0 || nothing_listed(&e) => break,
            Err(e) => return Err(e),
        }
    }
    Ok(out)
}

/// A NUL-terminated byte array from the kernel as text, lossily.
fn c_text(b: &[u8]) -> String {
    String::from_utf8_lossy(b.split(|&c| c == 0).next().unwrap_or(&[])).into_owned()
}

/// A fourcc as text (`MJPG`), or its hex value when it is not printable.
fn fourcc_text(fourcc: FourCC) -> String {
    match fourcc.str() {
        Ok(s) if s.chars().all(|c| c.is_ascii_graphic() || c == ' ') => s.trim_end().to_string(),
        _ => format!("0x{:08x}", u32::from_le_bytes(fourcc.repr)),
    }
}

/// Formats, sizes and rates a capture device offers.
fn probe_formats(dev: &Device) -> io::Result<Vec<FormatInfo>> {
    let mut out = Vec::new();
    for (fourcc, description) in enum_formats(dev)? {
        let mut discrete = Vec::new();
        let mut stepwise = None;
        let sizes = match dev.enum_framesizes(fourcc) {
            Ok(sizes) => sizes,
            Err(e) if nothing_listed(&e) => vec![],
            Err(e) => return Err(e),
        };
        for size in sizes {
            match size.size {
                FrameSizeEnum::Discrete(d) => {
                    let rates = probe_rates(dev, fourcc, d.width, d.height)?;
                    discrete.push((d.width, d.height, rates));
                }
                FrameSizeEnum::Stepwise(s) => {
                    stepwise = Some(Sizes::Stepwise {
                        min: (s.min_width, s.min_height),
                        max: (s.max_width, s.max_height),
                        step: (s.step_width.max(1), s.step_height.max(1)),
                    });
                }
            }
        }
        let sizes = stepwise.unwrap_or(Sizes::Discrete(discrete));
        out.push(FormatInfo { fourcc: fourcc_text(fourcc), description, sizes });
    }
    Ok(out)
}

fn probe_rates(dev: &Device, fourcc: FourCC, width: u32, height: u32) -> io::Result<Rates> {
    let intervals = match dev.enum_frameintervals(fourcc, width, height) {
        Ok(v) => v,
        Err(e) if nothing_listed(&e) => vec![],
        Err(e) => return Err(e),
    };
    let mut rates = Vec::new();
    for ival in intervals {
        match ival.interval {
            FrameIntervalEnum::Discrete(f) => rates.push(fps_of(f)),
            // The slowest rate is the longest interval.
            FrameIntervalEnum::Stepwise(s) => {
                return Ok(Rates::Range { min_fps: fps_of(s.max), max_fps: fps_of(s.min) });
            }
        }
    }
    Ok(Rates::Discrete(rates))
}

/// Opens `path` and describes it.
pub fn describe_device(path: &Path) -> Result<DeviceInfo, V4l2Error> {
    let dev = Device::with_path(path).map_err(|e| io_error(path, "open", e))?;
    let (driver, card, bus, flags) = query_caps(&dev).map_err(|e| io_error(path, "VIDIOC_QUERYCAP", e))?;
    let capture = is_capture(flags);
    let formats = if capture { probe_formats(&dev).map_err(|e| io_error(path, "listing formats", e))? } else { vec![] };
    Ok(DeviceInfo { path: path.to_path_buf(), driver, card, bus, capture, formats })
}

/// The `video<N>` nodes of `dir`, in numeric order, each described or with the reason it could
/// not be (e.g. no permission). Empty when there are none (no camera plugged in).
pub fn list_devices_in(dir: &Path) -> Vec<(PathBuf, Result<DeviceInfo, V4l2Error>)> {
    let Ok(entries) = std::fs::read_dir(dir) else { return vec![] };
    let mut nodes: Vec<(u32, PathBuf)> = entries
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name();
            let n = name.to_str()?.strip_prefix("video")?.parse::<u32>().ok()?;
            Some((n, e.path()))
        })
        .collect();
    nodes.sort();
    nodes.into_iter().map(|(_, p)| (p.clone(), describe_device(&p))).collect()
}

/// All V4L2 devices under `/dev`.
pub fn list_devices() -> Vec<(PathBuf, Result<DeviceInfo, V4l2Error>)> {
    list_devices_in(Path::new("/dev"))
}

/// Checks that `formats` offers `cfg`'s format, size and rate; the error says which is missing.
pub fn check_supported(formats: &[FormatInfo], cfg: &CameraConfig) -> Result<(), (String, String)> {
    let want = String::from_utf8_lossy(&cfg.format.fourcc()).into_owned();
    let wanted = format!("{} {}x{} at {} fps", want, cfg.width, cfg.height, fmt_fps(cfg.fps));
    let missing = |problem: String| Err((wanted.clone(), problem));
    let Some(format) = formats.iter().find(|f| f.fourcc == want) else {
        return missing(format!("it has no {want} format (config `camera.format = \"{}\"`)", cfg.format.name()));
    };
    // A driver that lists no rates is checked by reading back what VIDIOC_S_PARM set.
    let rate_ok = |r: &Rates| match r {
        Rates::Discrete(v) if v.is_empty() => true,
        Rates::Discrete(v) => v.iter().any(|&x| (x - cfg.fps).abs() <= 0.01 * cfg.fps),
        Rates::Range { min_fps, max_fps } => (min_fps * 0.99..=max_fps * 1.01).contains(&cfg.fps),
    };
    match &format.sizes {
        // A driver that lists no sizes is checked by reading back what VIDIOC_S_FMT set.
        Sizes::Discrete(sizes) if sizes.is_empty() => {}
        Sizes::Discrete(sizes) => {
            let Some((_, _, rates)) = sizes.iter().find(|(w, h, _)| (*w, *h) == (cfg.width, cfg.height)) else {
                return missing(format!("{want} has no {}x{} frame size", cfg.width, cfg.height));
            };
            if !rate_ok(rates) {
                return missing(format!(
                    "{want} {}x{} runs at {rates}, not {} fps",
                    cfg.width,
                    cfg.height,
                    fmt_fps(cfg.fps)
                ));
            }
        }
        Sizes::Stepwise { min, max, step } => {
            let fits = |v: u32, lo: u32, hi: u32, st: u32| (lo..=hi).contains(&v) && (v - lo).is_multiple_of(st);
            if !fits(cfg.width, min.0, max.0, step.0) || !fits(cfg.height, min.1, max.1, step.1) {
                return missing(format!("{want} has no {}x{} frame size", cfg.width, cfg.height));
            }
        }
    }
    Ok(())
}

/// One mmap'ed driver buffer.
struct Mapping {
    ptr: *mut c_void,
    len: usize,
}

/// A V4L2 camera streaming through mmap buffers. Implements [`Camera`]; see the module docs.
pub struct V4l2Camera {
    device: Device,
    cfg: CameraConfig,
    /// Row pitch of YUYV frames (V4L2 `bytesperline`).
    stride: usize,
    buffers: Vec<Mapping>,
    streaming: bool,
    /// Set once the device reported it is gone: every later capture says so again.
    gone: bool,
    decoder: MjpegDecoder,
    /// The MJPEG bytes of the last decoded frame (for logging as captured).
    last_jpeg: Option<std::sync::Arc<[u8]>>,
    seq: u64,
    last_driver_seq: Option<u32>,
    dropped: u64,
    warned_clock: bool,
}

// SAFETY: the raw pointers are private mmap'ed regions owned by this value, only touched through
// `&mut self` and unmapped in `Drop`; moving the owner to another thread is sound.
unsafe impl Send for V4l2Camera {}

fn zeroed_buffer() -> v4l_sys::v4l2_buffer {
    // SAFETY: v4l2_buffer is plain old data; zero is a valid bit pattern.
    let mut buf: v4l_sys::v4l2_buffer = unsafe { std::mem::zeroed() };
    buf.type_ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
    buf.memory = v4l_sys::v4l2_memory_V4L2_MEMORY_MMAP;
    buf
}

impl V4l2Camera {
    /// Opens `cfg.device`, negotiates exactly `cfg`'s format, size and rate (or fails with an
    /// [`ErrorKind::Unsupported`] error listing what the device offers), maps the buffers and
    /// starts streaming.
    pub fn open(cfg: &CameraConfig) -> Result<Self, V4l2Error> {
        let path = cfg.device.as_path();
        let info = describe_device(path)?;
        if !info.capture {
            return Err(V4l2Error::NotVideoDevice {
                path: path.into(),
                detail: format!(
                    "{} ({}) has no video capture with streaming: a metadata node?",
                    info.card, info.driver
                ),
            });
        }
        let unsupported = |wanted: String, problem: String| V4l2Error::Unsupported {
            path: path.into(),
            wanted,
            problem,
            supported: supported_list(&info.formats),
        };
        check_supported(&info.formats, cfg).map_err(|(w, p)| unsupported(w, p))?;
        let wanted = format!(
            "{} {}x{} at {} fps",
            String::from_utf8_lossy(&cfg.format.fourcc()),
            cfg.width,
            cfg.height,
            fmt_fps(cfg.fps)
        );

        let device = Device::with_path(path).map_err(|e| io_error(path, "open", e))?;
        let (got_fourcc, got_w, got_h, bytesperline) =
            set_format(&device, cfg).map_err(|e| io_error(path, "VIDIOC_S_FMT", e))?;
        if got_fourcc != cfg.format.fourcc() || (got_w, got_h) != (cfg.width, cfg.height) {
            return Err(unsupported(
                wanted,
                format!(
                    "the driver answered with {} {}x{} instead",
                    fourcc_text(FourCC::new(&got_fourcc)),
                    got_w,
                    got_h
                ),
            ));
        }
        let interval = fps_fraction(cfg.fps);
        let got_interval = set_interval(&device, interval).map_err(|e| io_error(path, "VIDIOC_S_PARM", e))?;
        let got_fps = fps_of(got_interval);
        if (got_fps - cfg.fps).abs() > 0.01 * cfg.fps {
            return Err(unsupported(wanted, format!("the driver set {} fps instead", fmt_fps(got_fps))));
        }
        let stride = if bytesperline == 0 { 2 * cfg.width as usize } else { bytesperline as usize };

        let mut cam = Self {
            device,
            cfg: cfg.clone(),
            stride,
            buffers: Vec::new(),
            streaming: false,
            gone: false,
            decoder: MjpegDecoder::with_max_size(cfg.width as usize, cfg.height as usize),
            last_jpeg: None,
            seq: 0,
            last_driver_seq: None,
            dropped: 0,
            warned_clock: false,
        };
        cam.start_streaming()?;
        tracing::info!(
            device = %path.display(),
            card = %info.card,
            "camera streaming {}x{} {} at {} fps",
            cfg.width,
            cfg.height,
            cfg.format.name(),
            fmt_fps(cfg.fps)
        );
        Ok(cam)
    }

    /// The configuration it was opened with.
    pub fn config(&self) -> &CameraConfig {
        &self.cfg
    }

    /// Frames the driver captured but this camera never delivered (gaps in the driver's sequence
    /// numbers: the consumer was slower than the camera and all buffers were full).
    pub fn dropped_frames(&self) -> u64 {
        self.dropped
    }

    fn fd(&self) -> i32 {
        self.device.handle().fd()
    }

    fn path(&self) -> &Path {
        &self.cfg.device
    }

    fn ioctl<T>(&self, op: &'static str, request: v4l::v4l2::vidioc::_IOC_TYPE, arg: &mut T) -> Result<(), V4l2Error> {
        // SAFETY: every caller passes the struct type that `request` reads and writes.
        unsafe { v4l::v4l2::ioctl(self.fd(), request, arg as *mut T as *mut c_void) }
            .map_err(|e| io_error(self.path(), op, e))
    }

    fn start_streaming(&mut self) -> Result<(), V4l2Error> {
        use v4l::v4l2::vidioc;
        // SAFETY: plain old data, zero is valid.
        let mut req: v4l_sys::v4l2_requestbuffers = unsafe { std::mem::zeroed() };
        req.count = BUFFER_COUNT;
        req.type_ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
        req.memory = v4l_sys::v4l2_memory_V4L2_MEMORY_MMAP;
        self.ioctl("VIDIOC_REQBUFS", vidioc::VIDIOC_REQBUFS, &mut req)?;
        if req.count == 0 {
            return Err(V4l2Error::Io {
                path: self.path().into(),
                op: "VIDIOC_REQBUFS",
                source: io::Error::other("the driver granted no mmap buffers"),
            });
        }
        for index in 0..req.count {
            let mut buf = zeroed_buffer();
            buf.index = index;
            self.ioctl("VIDIOC_QUERYBUF", vidioc::VIDIOC_QUERYBUF, &mut buf)?;
            // SAFETY: the union member `offset` is the one the driver fills for MMAP buffers.
            let offset = unsafe { buf.m.offset };
            let len = buf.length as usize;
            // SAFETY: maps the driver buffer `index` (offset/length from QUERYBUF) read-only.
            let ptr = unsafe {
                v4l::v4l2::mmap(
                    std::ptr::null_mut(),
                    len,
                    libc::PROT_READ,
                    libc::MAP_SHARED,
                    self.fd(),
                    offset as libc::off_t,
                )
            }
            .map_err(|e| io_error(self.path(), "mmap", e))?;
            self.buffers.push(Mapping { ptr, len });
        }
        for index in 0..req.count {
            self.queue(index)?;
        }
        let mut typ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
        self.ioctl("VIDIOC_STREAMON", vidioc::VIDIOC_STREAMON, &mut typ)?;
        self.streaming = true;
        Ok(())
    }

    fn queue(&self, index: u32) -> Result<(), V4l2Error> {
        let mut buf = zeroed_buffer();
        buf.index = index;
        self.ioctl("VIDIOC_QBUF", v4l::v4l2::vidioc::VIDIOC_QBUF, &mut buf)
    }

    /// Marks the camera gone when `e` says so.
    fn note(&mut self, e: V4l2Error) -> V4l2Error {
        if e.kind() == ErrorKind::Disconnected {
            self.gone = true;
        }
        e
    }

    /// Waits for a filled buffer (at most the stall timeout) and dequeues it.
    fn dequeue(&mut self) -> Result<v4l_sys::v4l2_buffer, V4l2Error> {
        let timeout_ms = self.cfg.stall_timeout_ms;
        let deadline = monotonic_ns() + timeout_ms * 1_000_000;
        loop {
            let now = monotonic_ns();
            if now >= deadline {
                return Err(V4l2Error::Stall { path: self.path().into(), timeout_ms });
            }
            let left_ms = (deadline - now).div_ceil(1_000_000).min(i32::MAX as u64) as i32;
            match self.device.handle().poll(libc::POLLIN, left_ms) {
                Ok(0) => continue,
                Ok(_) => {}
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(self.note(io_error(self.path(), "poll", e))),
            }
            let mut buf = zeroed_buffer();
            // SAFETY: VIDIOC_DQBUF fills one v4l2_buffer.
            let r = unsafe {
                v4l::v4l2::ioctl(self.fd(), v4l::v4l2::vidioc::VIDIOC_DQBUF, &mut buf as *mut _ as *mut c_void)
            };
            match r {
                Ok(()) if (buf.index as usize) < self.buffers.len() => return Ok(buf),
                Ok(()) => {
                    return Err(V4l2Error::Io {
                        path: self.path().into(),
                        op: "VIDIOC_DQBUF",
                        source: io::Error::other(format!("driver returned unknown buffer index {}", buf.index)),
                    });
                }
                Err(e) if matches!(e.kind(), io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted) => continue,
                Err(e) => return Err(self.note(io_error(self.path(), "VIDIOC_DQBUF", e))),
            }
        }
    }

    /// Converts the driver timestamp to ns on the monotonic clock; falls back to the dequeue
    /// time (with one warning) for drivers that do not stamp with `CLOCK_MONOTONIC`.
    fn timestamp_ns(&mut self, buf: &v4l_sys::v4l2_buffer) -> u64 {
        let ts_type = buf.flags & v4l_sys::V4L2_BUF_FLAG_TIMESTAMP_MASK;
        let (sec, usec) = (buf.timestamp.tv_sec, buf.timestamp.tv_usec);
        if ts_type == v4l_sys::V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC && sec >= 0 && usec >= 0 && (sec, usec) != (0, 0) {
            return sec as u64 * 1_000_000_000 + usec as u64 * 1_000;
        }
        if !self.warned_clock {
            self.warned_clock = true;
            tracing::warn!(
                device = %self.path().display(),
                "driver timestamps are not CLOCK_MONOTONIC (flags {:#x}); using dequeue time, latency figures include queueing",
                buf.flags
            );
        }
        monotonic_ns()
    }

    fn decode(&mut self, index: usize, bytesused: usize) -> Result<LumaImage, V4l2Error> {
        let m = &self.buffers[index];
        // SAFETY: the buffer is dequeued (owned by us until re-queued) and `bytesused` is clamped
        // to its mapped length.
        let data = unsafe { std::slice::from_raw_parts(m.ptr as *const u8, bytesused.min(m.len)) };
        let (w, h) = (self.cfg.width as usize, self.cfg.height as usize);
        let mut img = LumaImage::default();
        match self.cfg.format {
            PixelFormat::Mjpeg => {
                self.decoder
                    .decode_into(data, &mut img)
                    .map_err(|source| V4l2Error::Mjpeg { path: self.cfg.device.clone(), source })?;
                self.last_jpeg = Some(std::sync::Arc::from(data));
                if (img.width(), img.height()) != (w, h) {
                    return Err(V4l2Error::FrameSize {
                        path: self.cfg.device.clone(),
                        width: img.width(),
                        height: img.height(),
                        want_width: self.cfg.width,
                        want_height: self.cfg.height,
                    });
                }
            }
            PixelFormat::Yuyv => yuyv_to_luma(data, w, h, self.stride, &mut img)
                .map_err(|source| V4l2Error::Yuyv { path: self.cfg.device.clone(), source })?,
        }
        Ok(img)
    }
}

/// `VIDIOC_S_FMT` for `cfg`'s format and size; returns what the driver set: fourcc, width,
/// height, bytes per line.
fn set_format(dev: &Device, cfg: &CameraConfig) -> io::Result<([u8; 4], u32, u32, u32)> {
    // SAFETY: v4l2_format is plain old data; zero is a valid bit pattern.
    let mut fmt: v4l_sys::v4l2_format = unsafe { std::mem::zeroed() };
    fmt.type_ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
    // SAFETY: `pix` is the union member for VIDEO_CAPTURE formats.
    unsafe {
        fmt.fmt.pix.width = cfg.width;
        fmt.fmt.pix.height = cfg.height;
        fmt.fmt.pix.pixelformat = u32::from_le_bytes(cfg.format.fourcc());
        fmt.fmt.pix.field = v4l_sys::v4l2_field_V4L2_FIELD_NONE;
        v4l::v4l2::ioctl(dev.handle().fd(), v4l::v4l2::vidioc::VIDIOC_S_FMT, &mut fmt as *mut _ as *mut c_void)?;
        let pix = fmt.fmt.pix;
        Ok((pix.pixelformat.to_le_bytes(), pix.width, pix.height, pix.bytesperline))
    }
}

/// `VIDIOC_S_PARM` with the frame interval; returns the interval the driver set.
fn set_interval(dev: &Device, interval: Fraction) -> io::Result<Fraction> {
    // SAFETY: v4l2_streamparm is plain old data; zero is a valid bit pattern.
    let mut parm: v4l_sys::v4l2_streamparm = unsafe { std::mem::zeroed() };
    parm.type_ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
    // SAFETY: `capture` is the union member for VIDEO_CAPTURE streams.
    unsafe {
        parm.parm.capture.timeperframe.numerator = interval.numerator;
        parm.parm.capture.timeperframe.denominator = interval.denominator;
        v4l::v4l2::ioctl(dev.handle().fd(), v4l::v4l2::vidioc::VIDIOC_S_PARM, &mut parm as *mut _ as *mut c_void)?;
        let t = parm.parm.capture.timeperframe;
        Ok(Fraction::new(t.numerator, t.denominator))
    }
}

fn fps_fraction(fps: f64) -> Fraction {
    // 30 → 1/30, 7.5 → 2/15, 29.97 → 100/2997: exact enough for any listed rate.
    for num in [1u32, 2, 4, 5, 10, 100, 1000] {
        let den = fps * f64::from(num);
        if (den - den.round()).abs() < 1e-6 {
            return Fraction::new(num, den.round() as u32);
        }
    }
    Fraction::new(1000, (fps * 1000.0).round() as u32)
}

impl Camera for V4l2Camera {
    type Error = V4l2Error;

    /// The next frame, decoded to luma on the calling thread. Errors: `Timeout` after
    /// `stall_timeout_ms` without a frame, `BadData` for a corrupt frame (skipped; its buffer is
    /// returned to the driver), `Disconnected` once the device is gone (reopen it).
    fn capture(&mut self) -> Result<Frame, V4l2Error> {
        if self.gone {
            return Err(V4l2Error::Disconnected {
                path: self.path().into(),
                op: "capture",
                source: io::Error::from_raw_os_error(libc::ENODEV),
            });
        }
        let buf = self.dequeue()?;
        let t_ns = self.timestamp_ns(&buf);
        if let Some(last) = self.last_driver_seq {
            self.dropped += u64::from(buf.sequence.wrapping_sub(last).saturating_sub(1));
        }
        self.last_driver_seq = Some(buf.sequence);
        let result = if buf.flags & v4l_sys::V4L2_BUF_FLAG_ERROR != 0 {
            Err(V4l2Error::CorruptFrame { path: self.path().into(), driver_seq: buf.sequence })
        } else {
            self.decode(buf.index as usize, buf.bytesused as usize)
        };
        // The buffer goes back to the driver whether or not its frame decoded.
        self.queue(buf.index).map_err(|e| self.note(e))?;
        let image = result?;
        let frame = Frame { seq: self.seq, t_ns, image };
        self.seq += 1;
        Ok(frame)
    }

    fn take_encoded(&mut self) -> Option<std::sync::Arc<[u8]>> {
        self.last_jpeg.take()
    }
}

impl Drop for V4l2Camera {
    fn drop(&mut self) {
        // Errors are ignored: the device may be gone, and there is nothing left to do about it.
        if self.streaming {
            let mut typ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
            let _ = self.ioctl("VIDIOC_STREAMOFF", v4l::v4l2::vidioc::VIDIOC_STREAMOFF, &mut typ);
        }
        for m in self.buffers.drain(..) {
            // SAFETY: each mapping came from a successful mmap of exactly `len` bytes.
            let _ = unsafe { v4l::v4l2::munmap(m.ptr, m.len) };
        }
        // SAFETY: plain old data, zero is valid.
        let mut req: v4l_sys::v4l2_requestbuffers = unsafe { std::mem::zeroed() };
        req.type_ = v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE;
        req.memory = v4l_sys::v4l2_memory_V4L2_MEMORY_MMAP;
        let _ = self.ioctl("VIDIOC_REQBUFS", v4l::v4l2::vidioc::VIDIOC_REQBUFS, &mut req);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn c310_mjpeg() -> Vec<FormatInfo> {
        let all = Rates::Discrete(vec![30.0, 25.0, 20.0, 15.0, 10.0, 7.5, 5.0]);
        vec![
            FormatInfo {
                fourcc: "YUYV".into(),
                description: "YUYV 4:2:2".into(),
                sizes: Sizes::Discrete(vec![(640, 480, all.clone()), (1280, 720, Rates::Discrete(vec![7.5, 5.0]))]),
            },
            FormatInfo {
                fourcc: "MJPG".into(),
                description: "Motion-JPEG".into(),
                sizes: Sizes::Discrete(vec![(640, 480, all.clone()), (1280, 720, all)]),
            },
        ]
    }

    #[test]
    fn negotiation_accepts_listed_modes_only() {
        let formats = c310_mjpeg();
        let cfg = CameraConfig::default();
        assert_eq!(check_supported(&formats, &cfg), Ok(()));
        let yuyv = CameraConfig { format: PixelFormat::Yuyv, ..cfg.clone() };
        let (wanted, problem) = check_supported(&formats, &yuyv).unwrap_err();
        assert_eq!(wanted, "YUYV 1280x720 at 30 fps");
        assert!(problem.contains("7.5, 5 fps"), "{problem}");
        let slow = CameraConfig { fps: 7.5, ..yuyv };
        assert_eq!(check_supported(&formats, &slow), Ok(()));
        let big = CameraConfig { width: 1920, height: 1080, ..cfg };
        assert!(check_supported(&formats, &big).unwrap_err().1.contains("1920x1080"));
    }

    #[test]
    fn unsupported_error_lists_what_the_device_offers() {
        let formats = c310_mjpeg();
        let e = V4l2Error::Unsupported {
            path: "/dev/video0".into(),
            wanted: "YUYV 1280x720 at 30 fps".into(),
            problem: "x".into(),
            supported: supported_list(&formats),
        };
        assert_eq!(e.kind(), ErrorKind::Unsupported);
        let s = e.to_string();
        assert!(s.contains("MJPG (Motion-JPEG)") && s.contains("1280x720 @ 30, 25, 20, 15, 10, 7.5, 5 fps"), "{s}");
    }

    #[test]
    fn config_validation_names_the_field() {
        CameraConfig::default().validate().unwrap();
        let e = CameraConfig { stall_timeout_ms: 40, ..Default::default() }.validate().unwrap_err();
        assert_eq!(e.field, "stall_timeout_ms");
        let e = CameraConfig { fps: f64::NAN, ..Default::default() }.validate().unwrap_err();
        assert_eq!(e.field, "fps");
        let e = CameraConfig { format: PixelFormat::Yuyv, width: 641, ..Default::default() }.validate().unwrap_err();
        assert!(e.to_string().starts_with("camera.width"), "{e}");
    }

    #[test]
    fn frame_rates_become_exact_intervals() {
        let pair = |f: Fraction| (f.numerator, f.denominator);
        assert_eq!(pair(fps_fraction(30.0)), (1, 30));
        assert_eq!(pair(fps_fraction(7.5)), (2, 15));
        assert!((fps_of(fps_fraction(29.97)) - 29.97).abs() < 1e-9);
    }

    #[test]
    fn errno_maps_to_actionable_errors() {
        let p = Path::new("/dev/video7");
        let e = io_error(p, "open", io::Error::from_raw_os_error(libc::ENOENT));
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        assert!(e.to_string().contains("/dev/video7") && e.to_string().contains("flownav devices"), "{e}");
        let e = io_error(p, "open", io::Error::from_raw_os_error(libc::EACCES));
        assert!(e.to_string().contains("video` group"), "{e}");
        let e = io_error(p, "VIDIOC_DQBUF", io::Error::from_raw_os_error(libc::ENODEV));
        assert_eq!(e.kind(), ErrorKind::Disconnected);
        let e = io_error(p, "VIDIOC_QUERYCAP", io::Error::from_raw_os_error(libc::ENOTTY));
        assert_eq!(e.kind(), ErrorKind::Unsupported);
    }
}
