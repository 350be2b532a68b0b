//! The `[camera]` config table: device node, mode (format, size, rate) and stall timeout, with
//! the range checks serde cannot make.

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

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

#[cfg(test)]
mod tests {
    use super::*;

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
}
