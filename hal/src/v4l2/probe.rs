//! What a device offers: its identity and capture formats, sizes and rates as the driver lists
//! them, the device listing under `/dev`, and the check that a configured mode is among them.

use super::config::CameraConfig;
use super::error::{V4l2Error, io_error};
use std::fmt;
use std::io;
use std::os::raw::c_void;
use std::path::{Path, PathBuf};
use v4l::frameinterval::FrameIntervalEnum;
use v4l::framesize::FrameSizeEnum;
use v4l::v4l_sys;
use v4l::video::Capture;
use v4l::{Device, FourCC, Fraction};

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

pub(super) fn fps_of(interval: Fraction) -> f64 {
    if interval.numerator == 0 { 0.0 } else { f64::from(interval.denominator) / f64::from(interval.numerator) }
}

pub(super) fn fmt_fps(fps: f64) -> String {
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

pub(super) fn supported_list(formats: &[FormatInfo]) -> String {
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
pub(super) fn fourcc_text(fourcc: FourCC) -> String {
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

/// The frame interval of `fps` frames per second, as the driver is asked for it.
pub(super) fn fps_fraction(fps: f64) -> Fraction {
    // 30 → 1/30, 7.5 → 2/15, 29.97 → 100/2997: exact enough for any listed rate.
    for num in [1u32, 2, 4, 5, 10, 100, 1000] {
        let den = fps * f64::from(num);
        if (den - den.round()).abs() < 1e-6 {
            return Fraction::new(num, den.round() as u32);
        }
    }
    Fraction::new(1000, (fps * 1000.0).round() as u32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::{Error, ErrorKind};
    use crate::v4l2::PixelFormat;

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
    fn frame_rates_become_exact_intervals() {
        let pair = |f: Fraction| (f.numerator, f.denominator);
        assert_eq!(pair(fps_fraction(30.0)), (1, 30));
        assert_eq!(pair(fps_fraction(7.5)), (2, 15));
        assert!((fps_of(fps_fraction(29.97)) - 29.97).abs() < 1e-9);
    }
}
