//! The motor-base trait: body-velocity set-points in, odometry and status out.
//!
//! Drivers: [`crate::fnp_driver::FnpBase`] (FNP/1, docs/protocol.md) and
//! [`crate::kobuki::KobukiBase`] (TurtleBot 2). Both run a background tokio task that owns the
//! port, re-sends the latest command at a fixed rate, reconnects with back-off, and stops the base
//! when the driver is dropped; the trait methods only exchange data with that task.

use crate::error::Error;
use crate::motion::{BodyVelocity, Odometry};
use std::future::Future;
use std::time::Duration;

/// Health flags a base reports (FNP/1 STATUS, Kobuki sensor data). Serialised as is on the
/// `/base/status` log topic.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BaseStatus {
    /// Host monotonic time when the status arrived, ns.
    pub t_ns: u64,
    pub battery_v: Option<f64>,
    pub bumper: bool,
    pub estop: bool,
    pub stopped_by_watchdog: bool,
    pub motor_fault: bool,
    pub cliff: bool,
    pub wheel_drop: bool,
}

/// Something the base told the host.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BaseEvent {
    Odometry(Odometry),
    Status(BaseStatus),
}

/// Link health counters a driver keeps (all cumulative since construction).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct LinkStats {
    /// Whether the link is up now (handshake done, bytes arriving).
    pub connected: bool,
    /// Valid frames received / sent.
    pub frames_rx: u64,
    pub frames_tx: u64,
    /// Received frames dropped as malformed (bad framing, checksum, type or length).
    pub dropped_rx: u64,
    /// Frames the base sent that never arrived (sequence gaps), where the protocol can tell.
    pub lost_rx: u64,
    /// Times the link was declared down, and times it came back.
    pub disconnects: u64,
    pub reconnects: u64,
    /// Of `disconnects`, those the operating system reported: end of file, a read or write error,
    /// a hang-up (the port went away, as a USB adapter that is unplugged).
    pub disconnects_os: u64,
    /// Of `disconnects`, those the driver's silence timeout declared while the port was still
    /// there: nothing received (or a write blocked) for the silence timeout.
    pub disconnects_silence: u64,
    /// Times the port hung up while the driver was reconnecting (during the handshake on a
    /// reopened port): losses the OS reported while the link was already down, so not in
    /// `disconnects`.
    pub hangups_reconnecting: u64,
    /// Times the driver's own command watchdog zeroed a stale non-zero command.
    pub command_timeouts: u64,
    /// Events discarded because nobody read them (the event queue was full).
    pub events_dropped: u64,
}

/// A differential-drive base, used from async code (a tokio runtime must be running).
///
/// `set_velocity` and `stop` never block: they hand the command to the driver's background task,
/// which sends it at once and repeats it at its fixed rate (≥ 20 Hz). Callers refresh the
/// command at their control rate: a driver zeroes a non-zero command that was not refreshed
/// within its command timeout (a host-side watchdog; Kobuki firmware has none). While the link is
/// down, `set_velocity` fails with [`crate::ErrorKind::Disconnected`] and the driver reconnects on
/// its own; after a reconnect the base stays stopped until the next `set_velocity`.
/// Dropping a driver stops the base.
pub trait MotorBase: Send {
    type Error: Error;

    /// Drive at this body velocity (REP-103; clamped to what the protocol can carry).
    fn set_velocity(&mut self, cmd: BodyVelocity) -> Result<(), Self::Error>;

    /// Stop now.
    fn stop(&mut self) -> Result<(), Self::Error>;

    /// The next event, waiting at most `timeout`; `Ok(None)` when none arrived in time. An error
    /// of kind `Disconnected` is returned once each time the link goes down.
    fn next_event(&mut self, timeout: Duration) -> impl Future<Output = Result<Option<BaseEvent>, Self::Error>> + Send;

    /// Link counters, for logs and tests.
    fn link_stats(&self) -> LinkStats {
        LinkStats::default()
    }
}
