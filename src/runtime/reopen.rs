//! A camera that reopens its device after an unplug.
//!
//! A V4L2 camera that was unplugged reports `Disconnected` on every later call; the device has
//! to be opened anew once it is back. [`ReopeningCamera`] wraps an `open` function: after a
//! `Disconnected` error it drops the dead camera, and the next `capture` tries to open a fresh
//! one. The runtime's camera thread waits with exponential back-off between those calls, and the
//! robot stays stopped meanwhile (no frames → no set-points but zero).

use hal::{Camera, Error, ErrorKind, Frame};

/// See the module docs.
pub struct ReopeningCamera<C: Camera, F> {
    camera: Option<C>,
    open: F,
    reopened: u64,
}

impl<C, F> ReopeningCamera<C, F>
where
    C: Camera,
    F: FnMut() -> Result<C, C::Error> + Send,
{
    /// Wraps an open camera; `open` makes a new one after a disconnect.
    pub fn new(camera: C, open: F) -> Self {
        Self { camera: Some(camera), open, reopened: 0 }
    }

    /// How many times the camera was opened again.
    pub fn reopened(&self) -> u64 {
        self.reopened
    }
}

impl<C, F> Camera for ReopeningCamera<C, F>
where
    C: Camera,
    F: FnMut() -> Result<C, C::Error> + Send,
{
    type Error = C::Error;

    fn capture(&mut self) -> Result<Frame, C::Error> {
        let camera = match &mut self.camera {
            Some(c) => c,
            None => {
                let c = (self.open)()?;
                self.reopened += 1;
                tracing::info!("camera reopened");
                self.camera.insert(c)
            }
        };
        let result = camera.capture();
        if let Err(e) = &result
            && e.kind() == ErrorKind::Disconnected
        {
            self.camera = None;
        }
        result
    }

    fn take_encoded(&mut self) -> Option<std::sync::Arc<[u8]>> {
        self.camera.as_mut().and_then(Camera::take_encoded)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hal::LumaImage;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicU32, Ordering};

    #[derive(Debug, thiserror::Error)]
    #[error("{0:?}")]
    struct E(ErrorKind);
    impl Error for E {
        fn kind(&self) -> ErrorKind {
            self.0
        }
    }

    /// Delivers `frames` frames, then is unplugged.
    struct Flaky {
        frames: u32,
    }
    impl Camera for Flaky {
        type Error = E;
        fn capture(&mut self) -> Result<Frame, E> {
            if self.frames == 0 {
                return Err(E(ErrorKind::Disconnected));
            }
            self.frames -= 1;
            Ok(Frame { seq: 0, t_ns: 1, image: LumaImage::new(2, 2) })
        }
    }

    #[test]
    fn reopens_after_a_disconnect_and_passes_open_errors_on() {
        let opens = Arc::new(AtomicU32::new(0));
        let o = opens.clone();
        let mut cam = ReopeningCamera::new(Flaky { frames: 1 }, move || match o.fetch_add(1, Ordering::Relaxed) {
            0 => Err(E(ErrorKind::Disconnected)),
            _ => Ok(Flaky { frames: 2 }),
        });
        assert!(cam.capture().is_ok());
        assert_eq!(cam.capture().unwrap_err().kind(), ErrorKind::Disconnected);
        assert_eq!(cam.capture().unwrap_err().kind(), ErrorKind::Disconnected, "still unplugged");
        assert!(cam.capture().is_ok(), "back");
        assert!(cam.capture().is_ok());
        assert_eq!(cam.reopened(), 1);
        assert_eq!(opens.load(Ordering::Relaxed), 2);
    }
}
