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
//!
//! | module | owns |
//! |---|---|
//! | `config` | [`CameraConfig`], the `[camera]` table, and [`PixelFormat`] |
//! | `probe` | [`DeviceInfo`] and [`FormatInfo`]: what a device offers, device listing, [`check_supported`] |
//! | `capture` | [`V4l2Camera`]: negotiation, the mmap buffer ring, capture and decoding |
//! | `error` | [`V4l2Error`] and the [`ErrorKind`](crate::ErrorKind) of each failure |

mod capture;
mod config;
mod error;
mod probe;

pub use capture::V4l2Camera;
pub use config::{CameraConfig, InvalidCameraConfig, PixelFormat};
pub use error::V4l2Error;
pub use probe::{
    DeviceInfo, FormatInfo, Rates, Sizes, check_supported, describe_device, list_devices, list_devices_in,
};
