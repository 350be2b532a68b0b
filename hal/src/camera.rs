//! The camera trait: a source of timestamped 8-bit luma frames.

use crate::error::Error;
use crate::image::Frame;

/// A camera delivers frames, oldest first, each stamped with its capture time.
///
/// `capture` blocks until the next frame arrives or the driver's stall timeout passes (then it
/// returns an error whose kind is `Timeout`); it never blocks forever. The runtime calls it from
/// a dedicated thread, never from an async task.
pub trait Camera: Send {
    type Error: Error;

    /// The next frame.
    fn capture(&mut self) -> Result<Frame, Self::Error>;
}
