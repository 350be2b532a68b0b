//! The camera trait: a source of timestamped 8-bit luma frames, and the clock its stamps use.

use crate::error::Error;
use crate::image::Frame;

/// A camera delivers frames, oldest first, each stamped with its capture time.
///
/// `capture` blocks until the next frame arrives or the driver's stall timeout passes (then it
/// returns an error whose kind is `Timeout`); it never blocks forever. The runtime calls it from
/// a dedicated thread, never from an async task; decoding happens inside `capture`, on that
/// thread.
///
/// What the error kinds mean for a camera:
/// - `Timeout`: no frame within the stall timeout; the camera is still open, call again.
/// - `BadData`: one frame was corrupt (the driver flagged it, or it does not decode); it was
///   skipped, call again.
/// - `Disconnected`: the device went away (unplug); drop the camera and reopen it with back-off.
/// - `Unsupported`/`Other`: configuration or permission problems a human must fix.
/// - `EndOfStream`: a finite source (a frame folder) has no more frames; stop and end the run.
pub trait Camera: Send {
    type Error: Error;

    /// The next frame.
    fn capture(&mut self) -> Result<Frame, Self::Error>;

    /// The encoded bytes (an MJPEG frame) the last `capture` decoded, if the source had any:
    /// the runtime logs them as they came, without re-encoding. Taken once; later calls give
    /// `None` until the next capture.
    fn take_encoded(&mut self) -> Option<std::sync::Arc<[u8]>> {
        None
    }
}

/// Now on the host's monotonic clock (`CLOCK_MONOTONIC`), in nanoseconds.
///
/// This is the clock of [`Frame::t_ns`]: V4L2 stamps buffers with `CLOCK_MONOTONIC`, so frame
/// stamps and this value compare directly (capture → set-point latency = `monotonic_ns() - t_ns`).
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `ts` is a valid, writable timespec; CLOCK_MONOTONIC always exists on Linux.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    debug_assert_eq!(rc, 0, "clock_gettime(CLOCK_MONOTONIC) cannot fail");
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn monotonic_clock_does_not_go_back() {
        let a = monotonic_ns();
        let b = monotonic_ns();
        assert!(b >= a);
        assert!(a > 0);
    }
}
