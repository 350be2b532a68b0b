//! [`V4l2Error`]: what went wrong with a camera, said so that a user can act on it, and the
//! [`ErrorKind`] that tells the runtime what to do about it.

use crate::error::{Error, ErrorKind};
use crate::mjpeg::MjpegError;
use crate::yuyv::YuyvError;
use std::io;
use std::path::{Path, PathBuf};

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
pub(super) fn io_error(path: &Path, op: &'static str, e: io::Error) -> V4l2Error {
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

#[cfg(test)]
mod tests {
    use super::*;

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
