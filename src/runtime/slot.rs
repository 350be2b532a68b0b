//! The latest-frame-wins hand-off between the camera thread and the step thread.
//!
//! One slot holds at most one frame. The camera overwrites a frame the step has not taken yet
//! (the stale frame is dropped and counted), so a slow step never builds a queue and always works
//! on the newest picture (DESIGN.md, "Latest-frame-wins"). The slot can be closed with a reason
//! (end of stream, a fatal camera error, shutdown); a frame already in the slot is still handed
//! out before the close is reported, so the last frame of a folder is processed.

use hal::Frame;
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// Why no more frames will come.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Closed {
    /// The source has ended (a frame folder played to its end); the message names it.
    EndOfStream(String),
    /// The camera failed in a way a human must fix (permission, unsupported mode) or panicked.
    Fatal(String),
    /// The runtime is shutting down.
    Shutdown,
}

/// What [`FrameSlot::take`] found.
#[derive(Debug)]
pub enum Taken {
    Frame(Frame),
    /// No frame arrived within the timeout.
    TimedOut,
    Closed(Closed),
}

#[derive(Debug, Default)]
struct State {
    frame: Option<Frame>,
    closed: Option<Closed>,
    dropped: u64,
}

/// A one-frame mailbox; see the module docs.
#[derive(Debug, Default)]
pub struct FrameSlot {
    state: Mutex<State>,
    ready: Condvar,
}

impl FrameSlot {
    pub fn new() -> Self {
        Self::default()
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Puts `frame` in the slot, replacing (dropping) a frame nobody took; returns whether one
    /// was dropped. After [`close`](Self::close) the frame is discarded.
    pub fn put(&self, frame: Frame) -> bool {
        let mut s = self.lock();
        if s.closed.is_some() {
            return false;
        }
        let dropped = s.frame.replace(frame).is_some();
        if dropped {
            s.dropped += 1;
        }
        drop(s);
        self.ready.notify_one();
        dropped
    }

    /// Closes the slot; the first reason wins.
    pub fn close(&self, why: Closed) {
        let mut s = self.lock();
        if s.closed.is_none() {
            s.closed = Some(why);
        }
        drop(s);
        self.ready.notify_all();
    }

    /// Whether the slot has been closed.
    pub fn is_closed(&self) -> bool {
        self.lock().closed.is_some()
    }

    /// Frames replaced before anyone took them.
    pub fn dropped(&self) -> u64 {
        self.lock().dropped
    }

    /// The newest frame, waiting at most `timeout` for one. A frame in the slot is returned
    /// even when the slot is closed, except after [`Closed::Shutdown`].
    pub fn take(&self, timeout: Duration) -> Taken {
        let deadline = Instant::now() + timeout;
        let mut s = self.lock();
        loop {
            if s.closed == Some(Closed::Shutdown) {
                return Taken::Closed(Closed::Shutdown);
            }
            if let Some(frame) = s.frame.take() {
                return Taken::Frame(frame);
            }
            if let Some(why) = &s.closed {
                return Taken::Closed(why.clone());
            }
            let now = Instant::now();
            if now >= deadline {
                return Taken::TimedOut;
            }
            s = self.ready.wait_timeout(s, deadline - now).unwrap_or_else(|e| e.into_inner()).0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hal::LumaImage;
    use std::sync::Arc;

    fn frame(seq: u64) -> Frame {
        Frame { seq, t_ns: seq * 1000, image: LumaImage::new(4, 4) }
    }

    fn seq(t: Taken) -> u64 {
        match t {
            Taken::Frame(f) => f.seq,
            other => panic!("expected a frame, got {other:?}"),
        }
    }

    #[test]
    fn newest_frame_wins_and_stale_ones_are_counted() {
        let slot = FrameSlot::new();
        assert!(!slot.put(frame(1)));
        assert!(slot.put(frame(2)));
        assert!(slot.put(frame(3)));
        assert_eq!(seq(slot.take(Duration::ZERO)), 3);
        assert_eq!(slot.dropped(), 2);
        assert!(matches!(slot.take(Duration::from_millis(1)), Taken::TimedOut));
    }

    #[test]
    fn the_last_frame_is_handed_out_before_the_end() {
        let slot = FrameSlot::new();
        slot.put(frame(7));
        slot.close(Closed::EndOfStream("done".into()));
        slot.close(Closed::Fatal("later reasons do not replace the first".into()));
        assert!(!slot.put(frame(8)), "frames after the close are discarded");
        assert_eq!(seq(slot.take(Duration::ZERO)), 7);
        assert!(matches!(slot.take(Duration::ZERO), Taken::Closed(Closed::EndOfStream(m)) if m == "done"));
    }

    #[test]
    fn shutdown_wins_over_a_waiting_frame() {
        let slot = FrameSlot::new();
        slot.put(frame(1));
        slot.close(Closed::Shutdown);
        assert!(matches!(slot.take(Duration::ZERO), Taken::Closed(Closed::Shutdown)));
    }

    #[test]
    fn a_waiting_taker_wakes_on_put_and_on_close() {
        let slot = Arc::new(FrameSlot::new());
        let s = slot.clone();
        let t = std::thread::spawn(move || seq(s.take(Duration::from_secs(30))));
        std::thread::sleep(Duration::from_millis(5));
        slot.put(frame(4));
        assert_eq!(t.join().unwrap(), 4);
        let s = slot.clone();
        let t = std::thread::spawn(move || s.take(Duration::from_secs(30)));
        slot.close(Closed::Shutdown);
        assert!(matches!(t.join().unwrap(), Taken::Closed(Closed::Shutdown)));
    }
}
