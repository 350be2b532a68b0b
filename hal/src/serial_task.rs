//! The serial skeleton both base drivers (FNP/1 and Kobuki) share; the protocol-specific part
//! is a `Protocol` (frames out, bytes in, the handshake), everything else is said once here:
//!
//! - opening the port ([`Connector`], [`SerialConnector`]) with errors a user can act on
//!   ([`SerialBaseError`]);
//! - a background tokio task that sends the latest command at once and repeats it at a fixed
//!   rate, replacing a non-zero command that was not refreshed within the command timeout by the
//!   protocol's zero command;
//! - decoded events queued for [`MotorBase::next_event`](crate::MotorBase::next_event), link
//!   counters in `Shared` (read out as [`LinkStats`]);
//! - declaring the link down when the port fails or nothing arrives for the silence timeout,
//!   then reopening it with exponential [`Backoff`] and repeating the handshake, the base kept
//!   stopped until the caller commands again;
//! - stopping the base on close and on drop (also synchronously, through a duplicate of the
//!   port's descriptor, so the stop goes out even when the runtime is shutting down);
//! - mapping a device clock to the host's ([`ClockMapper`]) and unwrapping encoder counts
//!   ([`TickUnwrapper`]).

use crate::base::{BaseEvent, LinkStats};
use crate::error::{Error, ErrorKind};
use std::future::Future;
use std::io::Write;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::sync::{mpsc, watch};
use tokio::time::{Instant, MissedTickBehavior};

/// Errors of the serial base drivers (FNP/1 and Kobuki).
#[derive(Debug, thiserror::Error)]
pub enum SerialBaseError {
    #[error("{port}: no such device; is the base plugged in? see README 'udev'")]
    NoSuchPort { port: String },
    #[error(
        "{port}: permission denied; add your user to the 'dialout' group or install the udev rule (see README 'udev')"
    )]
    PermissionDenied { port: String },
    #[error("{port}: cannot open the port: {message}")]
    Open { port: String, message: String },
    #[error(
        "{port}: the base did not answer within {timeout_ms} ms at {baud} baud; check the baud rate, the cable \
         (TX/RX crossed, common ground), that nothing else holds the port, and that the firmware speaks {protocol}"
    )]
    NoAnswer { port: String, timeout_ms: u64, baud: u32, protocol: &'static str },
    #[error("{port}: the base speaks FNP/{version}, this driver FNP/{}", crate::fnp::VERSION)]
    Incompatible { port: String, version: u8 },
    #[error("{port}: link lost ({reason}); reconnecting")]
    Disconnected { port: String, reason: String },
    #[error("{port}: the driver's background task has ended")]
    Closed { port: String },
    #[error("base configuration: {0}")]
    Config(String),
    /// A command that the protocol's fields cannot carry; the driver stopped the base instead.
    #[error(transparent)]
    OutOfRange(#[from] crate::fnp::OutOfRange),
}

impl Error for SerialBaseError {
    fn kind(&self) -> ErrorKind {
        match self {
            SerialBaseError::NoSuchPort { .. } | SerialBaseError::Disconnected { .. } => ErrorKind::Disconnected,
            SerialBaseError::Closed { .. } => ErrorKind::Disconnected,
            SerialBaseError::NoAnswer { .. } => ErrorKind::Timeout,
            SerialBaseError::Incompatible { .. } | SerialBaseError::Config(_) | SerialBaseError::OutOfRange(_) => {
                ErrorKind::Unsupported
            }
            SerialBaseError::PermissionDenied { .. } | SerialBaseError::Open { .. } => ErrorKind::Other,
        }
    }
}

/// Opens the byte stream a driver talks over: a serial port, or an in-memory pipe in tests.
pub trait Connector: Send + 'static {
    type Stream: AsyncRead + AsyncWrite + Unpin + Send + 'static;

    /// Opens the stream (called again on every reconnect).
    fn connect(&mut self) -> impl Future<Output = Result<Self::Stream, SerialBaseError>> + Send;

    /// The port's name for messages.
    fn port_name(&self) -> &str;

    /// A blocking writer on the same device, used to send STOP from `Drop`.
    fn emergency_writer(&self, _stream: &Self::Stream) -> Option<std::fs::File> {
        None
    }

    /// Whether the operating system reports the stream hung up (the device went away). Asked
    /// when the driver's own timer gives up on a link, so that a loss the OS reported is counted
    /// as such even when the timer fired first (a host too loaded to read the hang-up in time).
    fn hung_up(&self, _stream: &Self::Stream) -> bool {
        false
    }
}

/// A serial port (or pseudo-terminal) by path, via tokio-serial, 8N1.
#[derive(Clone, Debug)]
pub struct SerialConnector {
    pub port: String,
    pub baud: u32,
}

impl SerialConnector {
    pub fn new(port: impl Into<String>, baud: u32) -> Self {
        Self { port: port.into(), baud }
    }
}

impl Connector for SerialConnector {
    type Stream = tokio_serial::SerialStream;

    async fn connect(&mut self) -> Result<Self::Stream, SerialBaseError> {
        use tokio_serial::{SerialPort, SerialPortBuilderExt};
        let port = self.port.clone();
        if !std::path::Path::new(&port).exists() {
            return Err(SerialBaseError::NoSuchPort { port });
        }
        let stream = tokio_serial::new(&port, self.baud).timeout(Duration::from_millis(100)).open_native_async();
        let stream = stream.map_err(|e| match e.kind {
            tokio_serial::ErrorKind::Io(std::io::ErrorKind::NotFound) => {
                SerialBaseError::NoSuchPort { port: port.clone() }
            }
            tokio_serial::ErrorKind::Io(std::io::ErrorKind::PermissionDenied) => {
                SerialBaseError::PermissionDenied { port: port.clone() }
            }
            tokio_serial::ErrorKind::NoDevice => {
                SerialBaseError::Open { port: port.clone(), message: format!("{} (is another program using it?)", e) }
            }
            _ => SerialBaseError::Open { port: port.clone(), message: e.to_string() },
        })?;
        // Bytes the base sent before we opened are stale.
        let _ = stream.clear(tokio_serial::ClearBuffer::Input);
        Ok(stream)
    }

    fn port_name(&self) -> &str {
        &self.port
    }

    fn emergency_writer(&self, stream: &Self::Stream) -> Option<std::fs::File> {
        use std::os::fd::{AsRawFd, BorrowedFd};
        // SAFETY: the descriptor belongs to `stream`, which is alive for the duration of this
        // call; `try_clone_to_owned` duplicates it (dup(2)), so the returned file owns its own
        // descriptor and stays valid after `stream` is closed.
        let fd = unsafe { BorrowedFd::borrow_raw(stream.as_raw_fd()) };
        fd.try_clone_to_owned().ok().map(std::fs::File::from)
    }

    fn hung_up(&self, stream: &Self::Stream) -> bool {
        use std::os::fd::AsRawFd;
        let mut fd = libc::pollfd { fd: stream.as_raw_fd(), events: libc::POLLIN, revents: 0 };
        // SAFETY: one valid pollfd for the duration of the call; the descriptor belongs to
        // `stream`, which is alive. A zero timeout only reads the current state.
        let n = unsafe { libc::poll(&mut fd, 1, 0) };
        n > 0 && fd.revents & (libc::POLLHUP | libc::POLLERR | libc::POLLNVAL) != 0
    }
}

/// Exponential back-off between reconnect attempts.
#[derive(Clone, Copy, Debug)]
pub struct Backoff {
    pub initial: Duration,
    pub max: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Self { initial: Duration::from_millis(100), max: Duration::from_millis(3200) }
    }
}

/// Maps a device clock (a wrapping counter) to the host's monotonic clock.
///
/// Each sample pairs a device time with the host time its frame arrived. The transport only
/// ever delays a frame, so `host_rx - device_t` is the clock offset plus a non-negative latency;
/// its minimum over the samples is the best offset estimate (the frame that was delayed least).
/// The estimate may rise by at most `drift_ppm` of elapsed host time per sample, so it follows a
/// device clock that runs slower than the host's; a faster device clock lowers the minimum by
/// itself. The mapped time is `device_t + offset`, never later than the arrival time. A device
/// clock that jumps back by more than half its wrap period (a reboot) restarts the estimate.
#[derive(Clone, Debug)]
pub struct ClockMapper {
    modulus: u64,
    unit_ns: u64,
    drift_ppm: f64,
    last_raw: Option<u64>,
    device_ns: i128,
    offset_ns: i128,
    last_host_ns: u64,
}

impl ClockMapper {
    /// `modulus`: the counter's wrap (2^32 for FNP/1 µs); `unit_ns`: ns per count (1000).
    pub fn new(modulus: u64, unit_ns: u64) -> Self {
        Self { modulus, unit_ns, drift_ppm: 200.0, last_raw: None, device_ns: 0, offset_ns: 0, last_host_ns: 0 }
    }

    /// The host time (ns) of device time `raw`, received at host time `host_rx_ns`.
    pub fn map(&mut self, raw: u64, host_rx_ns: u64) -> u64 {
        let raw = raw % self.modulus;
        let sample_restart = match self.last_raw {
            None => true,
            Some(last) => {
                let diff = (raw + self.modulus - last) % self.modulus;
                if diff > self.modulus / 2 {
                    true
                } else {
                    self.device_ns += i128::from(diff * self.unit_ns);
                    false
                }
            }
        };
        self.last_raw = Some(raw);
        let sample = i128::from(host_rx_ns) - self.device_ns;
        if sample_restart {
            self.device_ns = i128::from(raw * self.unit_ns);
            self.offset_ns = i128::from(host_rx_ns) - self.device_ns;
        } else {
            let elapsed = host_rx_ns.saturating_sub(self.last_host_ns) as f64;
            let allowed = self.offset_ns + (elapsed * self.drift_ppm * 1e-6) as i128;
            self.offset_ns = sample.min(allowed);
        }
        self.last_host_ns = host_rx_ns;
        (self.device_ns + self.offset_ns).clamp(0, i128::from(host_rx_ns)) as u64
    }

    /// The current offset estimate, host minus device, ns.
    pub fn offset_ns(&self) -> i128 {
        self.offset_ns
    }
}

/// Unwraps a cumulative encoder count of `bits` bits into an `i64`.
#[derive(Clone, Copy, Debug, Default)]
pub struct TickUnwrapper {
    last: Option<u32>,
    total: i64,
}

impl TickUnwrapper {
    /// Adds the reading `raw` (the low `bits` bits count); the first reading after
    /// [`Self::rebase`] sets the baseline and adds nothing.
    pub fn update(&mut self, raw: u32, bits: u32) -> i64 {
        let mask = if bits >= 32 { u32::MAX } else { (1u32 << bits) - 1 };
        let raw = raw & mask;
        if let Some(last) = self.last {
            let diff = raw.wrapping_sub(last) & mask;
            // Sign-extend the `bits`-bit difference.
            let shift = 32 - bits.min(32);
            self.total += i64::from(((diff << shift) as i32) >> shift);
        }
        self.last = Some(raw);
        self.total
    }

    /// Forgets the last reading (after a reconnect the device may have restarted its counters).
    pub fn rebase(&mut self) {
        self.last = None;
    }
}

/// Counters shared between a driver handle and its task.
#[derive(Debug, Default)]
pub(crate) struct Shared {
    pub connected: AtomicBool,
    pub frames_rx: AtomicU64,
    pub frames_tx: AtomicU64,
    pub dropped_rx: AtomicU64,
    pub lost_rx: AtomicU64,
    pub disconnects: AtomicU64,
    pub disconnects_os: AtomicU64,
    pub disconnects_silence: AtomicU64,
    pub hangups_reconnecting: AtomicU64,
    pub reconnects: AtomicU64,
    pub command_timeouts: AtomicU64,
    pub events_dropped: AtomicU64,
    pub next_seq: AtomicU8,
    pub emergency: Mutex<Option<std::fs::File>>,
}

impl Shared {
    /// The next frame sequence number (protocols without one ignore it).
    pub fn take_seq(&self) -> u8 {
        self.next_seq.fetch_add(1, Ordering::Relaxed)
    }

    /// `Ok` while the link is up; while the task reconnects, commands fail with `Disconnected`.
    pub fn check_connected(&self, port: &str) -> Result<(), SerialBaseError> {
        if self.connected.load(Ordering::Relaxed) {
            Ok(())
        } else {
            Err(SerialBaseError::Disconnected { port: port.into(), reason: "reconnecting".into() })
        }
    }

    pub fn stats(&self) -> LinkStats {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        LinkStats {
            connected: self.connected.load(Ordering::Relaxed),
            frames_rx: g(&self.frames_rx),
            frames_tx: g(&self.frames_tx),
            dropped_rx: g(&self.dropped_rx),
            lost_rx: g(&self.lost_rx),
            disconnects: g(&self.disconnects),
            disconnects_os: g(&self.disconnects_os),
            disconnects_silence: g(&self.disconnects_silence),
            hangups_reconnecting: g(&self.hangups_reconnecting),
            reconnects: g(&self.reconnects),
            command_timeouts: g(&self.command_timeouts),
            events_dropped: g(&self.events_dropped),
        }
    }

    /// Writes `bytes` through the emergency descriptor, if there is one (best effort).
    pub fn emergency_write(&self, bytes: &[u8]) {
        if let Ok(mut guard) = self.emergency.lock()
            && let Some(file) = guard.as_mut()
        {
            let _ = file.write_all(bytes);
        }
    }
}

/// The protocol side of a serial base driver: how commands become frames, what the handshake
/// is, and how received bytes become events. Encoding and decoding themselves are pure
/// functions of the protocol's codec module; an implementation holds the decoder state.
pub(crate) trait Protocol: Send + 'static {
    /// A set-point as the driver's caller gives it.
    type Command: Copy + Send + Sync + 'static;
    /// What the handshake learns from the base.
    type Hello: Send;
    /// The command a link starts with, and the one `stop` and `close` send.
    const IDLE: Self::Command;
    /// What the command-timeout warning calls the base.
    const NAME: &'static str;

    /// Whether `cmd` moves the base (only a moving command expires).
    fn is_moving(cmd: &Self::Command) -> bool;
    /// The frame for `cmd`; `seq` is the frame's sequence number where the protocol has one.
    fn command_frame(cmd: &Self::Command, seq: u8) -> Vec<u8>;
    /// The frame that stops the base (shutdown, drop, and after a reconnect until commanded).
    fn stop_frame(seq: u8) -> Vec<u8>;
    /// The frame sent instead of a moving command that has expired.
    fn expired_frame(seq: u8) -> Vec<u8>;
    /// Brings a freshly opened port up (or says why not); called on every (re)connect.
    fn handshake<S: AsyncRead + AsyncWrite + Unpin + Send>(
        &mut self,
        s: &mut S,
        port: &str,
        shared: &Shared,
    ) -> impl Future<Output = Result<Self::Hello, SerialBaseError>> + Send;
    /// The link is up after a handshake (`reconnect`: not the first time).
    fn on_connected(&mut self, hello: &Self::Hello, reconnect: bool, port: &str, push: &mut impl FnMut(BaseEvent));
    /// Bytes arrived at host time `host_ns`: decode them, push the events, update the counters.
    fn on_bytes(&mut self, bytes: &[u8], host_ns: u64, port: &str, shared: &Shared, push: &mut impl FnMut(BaseEvent));
}

/// The timing of a driver's task.
#[derive(Clone, Copy, Debug)]
pub(crate) struct TaskTiming {
    /// How often the current command is repeated.
    pub rate_hz: f64,
    /// Nothing received for this long: the link is down. Also the limit on one write.
    pub silence_timeout: Duration,
    /// A moving command not refreshed for this long expires (`None`: never).
    pub command_timeout: Option<Duration>,
    pub backoff: Backoff,
}

#[derive(Clone, Copy, Debug)]
struct CommandMsg<C> {
    cmd: C,
    at: Instant,
}

type EventMsg = Result<BaseEvent, SerialBaseError>;
/// Events queued for the caller; when it falls this far behind, new events are dropped and
/// counted.
const EVENT_QUEUE: usize = 1024;

/// The caller's end of a running driver: commands in, events out, counters, and the stop on
/// close and drop.
pub(crate) struct SerialTask<P: Protocol> {
    port: String,
    cmd_tx: watch::Sender<CommandMsg<P::Command>>,
    events_rx: mpsc::Receiver<EventMsg>,
    shared: Arc<Shared>,
    task: Option<tokio::task::JoinHandle<()>>,
}

impl<P: Protocol> SerialTask<P> {
    /// Opens the port, runs the handshake and starts the background task; returns the handle
    /// and what the handshake learnt. Must be called inside a tokio runtime.
    pub async fn start<C: Connector>(
        mut protocol: P,
        timing: TaskTiming,
        mut connector: C,
    ) -> Result<(Self, P::Hello), SerialBaseError> {
        let port = connector.port_name().to_string();
        let shared = Arc::new(Shared::default());
        let mut stream = connector.connect().await?;
        let hello = protocol.handshake(&mut stream, &port, &shared).await?;
        *shared.emergency.lock().unwrap_or_else(|e| e.into_inner()) = connector.emergency_writer(&stream);
        shared.connected.store(true, Ordering::Relaxed);
        let (cmd_tx, cmd_rx) = watch::channel(CommandMsg { cmd: P::IDLE, at: Instant::now() });
        let (events_tx, events_rx) = mpsc::channel(EVENT_QUEUE);
        let mut link = Link {
            protocol,
            timing,
            connector,
            port: port.clone(),
            shared: shared.clone(),
            cmd_rx,
            events_tx,
            fresh_required: false,
            timed_out_at: None,
        };
        link.connected(&hello, false);
        let task = tokio::spawn(link.run(stream));
        Ok((Self { port, cmd_tx, events_rx, shared, task: Some(task) }, hello))
    }

    /// Makes `cmd` the current command; fails with `Disconnected` while the task reconnects.
    pub fn command(&self, cmd: P::Command) -> Result<(), SerialBaseError> {
        self.shared.check_connected(&self.port)?;
        self.send(cmd);
        Ok(())
    }

    /// Makes [`Protocol::IDLE`] the current command (also while reconnecting, which it reports).
    pub fn stop(&self) -> Result<(), SerialBaseError> {
        self.send(P::IDLE);
        self.shared.check_connected(&self.port)
    }

    fn send(&self, cmd: P::Command) {
        self.cmd_tx.send_replace(CommandMsg { cmd, at: Instant::now() });
    }

    /// The next event within `timeout` (see [`MotorBase::next_event`](crate::MotorBase::next_event)).
    pub async fn next_event(&mut self, timeout: Duration) -> Result<Option<BaseEvent>, SerialBaseError> {
        match tokio::time::timeout(timeout, self.events_rx.recv()).await {
            Err(_) => Ok(None),
            Ok(Some(Ok(ev))) => Ok(Some(ev)),
            Ok(Some(Err(e))) => Err(e),
            Ok(None) => Err(SerialBaseError::Closed { port: self.port.clone() }),
        }
    }

    pub fn link_stats(&self) -> LinkStats {
        self.shared.stats()
    }

    /// Sends the stop and waits until the background task has written it and ended.
    pub async fn close(&mut self) {
        self.send(P::IDLE);
        if let Some(task) = self.task.take() {
            // Replacing the sender closes the channel: the task sends the stop frame and ends.
            let (dummy, _) = watch::channel(CommandMsg { cmd: P::IDLE, at: Instant::now() });
            drop(std::mem::replace(&mut self.cmd_tx, dummy));
            let _ = task.await;
        }
    }
}

impl<P: Protocol> Drop for SerialTask<P> {
    fn drop(&mut self) {
        // The task sends the stop when it sees the command channel close; this synchronous one
        // covers a runtime that is shutting down and will not run the task again.
        self.shared.emergency_write(&P::stop_frame(self.shared.take_seq()));
    }
}

/// Who declared a link down.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum LossCause {
    /// The operating system: end of file, a read or write error, a hang-up.
    Os,
    /// The driver's own timer: nothing received, or a write blocked, for the silence timeout.
    Silence,
}

/// Writes one frame within `limit`, counting it; the error is who declared the link down and why.
pub(crate) async fn send_frame<S: AsyncWrite + Unpin>(
    s: &mut S,
    shared: &Shared,
    frame: &[u8],
    limit: Duration,
) -> Result<(), (LossCause, String)> {
    match tokio::time::timeout(limit, async {
        s.write_all(frame).await?;
        s.flush().await
    })
    .await
    {
        Ok(Ok(())) => {
            shared.frames_tx.fetch_add(1, Ordering::Relaxed);
            Ok(())
        }
        Ok(Err(e)) => Err((LossCause::Os, format!("write failed: {e}"))),
        Err(_) => Err((LossCause::Silence, format!("write blocked for {} ms", limit.as_millis()))),
    }
}

fn push(events_tx: &mpsc::Sender<EventMsg>, shared: &Shared, ev: EventMsg) {
    if let Err(mpsc::error::TrySendError::Full(_)) = events_tx.try_send(ev) {
        shared.events_dropped.fetch_add(1, Ordering::Relaxed);
    }
}

enum SessionEnd {
    Shutdown,
    Lost(LossCause, String),
}

/// The background task's state.
struct Link<P: Protocol, C: Connector> {
    protocol: P,
    timing: TaskTiming,
    connector: C,
    port: String,
    shared: Arc<Shared>,
    cmd_rx: watch::Receiver<CommandMsg<P::Command>>,
    events_tx: mpsc::Sender<EventMsg>,
    /// After a reconnect: send the stop frame until the caller commands again.
    fresh_required: bool,
    /// The command whose expiry was last counted.
    timed_out_at: Option<Instant>,
}

impl<P: Protocol, C: Connector> Link<P, C> {
    async fn run(mut self, first: C::Stream) {
        let mut stream = first;
        loop {
            match self.session(&mut stream).await {
                SessionEnd::Shutdown => return,
                SessionEnd::Lost(cause, mut reason) => {
                    self.shared.connected.store(false, Ordering::Relaxed);
                    self.shared.disconnects.fetch_add(1, Ordering::Relaxed);
                    // The timer may fire before the hang-up is read (a starved task wakes to both at
                    // once): the OS has the last word on whether the port went away.
                    let cause = if cause == LossCause::Silence && self.connector.hung_up(&stream) {
                        reason.push_str("; the port has hung up");
                        LossCause::Os
                    } else {
                        cause
                    };
                    match cause {
                        LossCause::Os => &self.shared.disconnects_os,
                        LossCause::Silence => &self.shared.disconnects_silence,
                    }
                    .fetch_add(1, Ordering::Relaxed);
                    *self.shared.emergency.lock().unwrap_or_else(|e| e.into_inner()) = None;
                    let err = SerialBaseError::Disconnected { port: self.port.clone(), reason };
                    tracing::warn!("{err}");
                    push(&self.events_tx, &self.shared, Err(err));
                }
            }
            drop(stream);
            match self.reconnect().await {
                Some(s) => stream = s,
                None => return,
            }
        }
    }

    fn connected(&mut self, hello: &P::Hello, reconnect: bool) {
        let (events_tx, shared) = (&self.events_tx, &self.shared);
        self.protocol.on_connected(hello, reconnect, &self.port, &mut |ev| push(events_tx, shared, Ok(ev)));
    }

    fn current_frame(&mut self) -> Vec<u8> {
        let seq = self.shared.take_seq();
        if self.fresh_required {
            return P::stop_frame(seq);
        }
        let msg = *self.cmd_rx.borrow();
        let expired = self.timing.command_timeout.is_some_and(|t| msg.at.elapsed() > t);
        if expired && P::is_moving(&msg.cmd) {
            if self.timed_out_at != Some(msg.at) {
                self.timed_out_at = Some(msg.at);
                self.shared.command_timeouts.fetch_add(1, Ordering::Relaxed);
                tracing::warn!(port = self.port, "no new command within the command timeout: stopping the {}", P::NAME);
            }
            return P::expired_frame(seq);
        }
        P::command_frame(&msg.cmd, seq)
    }

    async fn session(&mut self, s: &mut C::Stream) -> SessionEnd {
        let period = Duration::from_secs_f64(1.0 / self.timing.rate_hz);
        let mut tick = tokio::time::interval(period);
        tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
        let silence = self.timing.silence_timeout;
        let mut last_rx = Instant::now();
        let mut buf = [0u8; 512];
        loop {
            tokio::select! {
                biased;
                changed = self.cmd_rx.changed() => {
                    if changed.is_err() {
                        let _ = send_frame(s, &self.shared, &P::stop_frame(self.shared.take_seq()), silence).await;
                        return SessionEnd::Shutdown;
                    }
                    self.fresh_required = false;
                    let f = self.current_frame();
                    if let Err((cause, reason)) = send_frame(s, &self.shared, &f, silence).await {
                        return SessionEnd::Lost(cause, reason);
                    }
                    tick.reset();
                }
                n = s.read(&mut buf) => match n {
                    Ok(0) => return SessionEnd::Lost(LossCause::Os, "the port was closed".into()),
                    Err(e) => return SessionEnd::Lost(LossCause::Os, format!("read failed: {e}")),
                    Ok(n) => {
                        last_rx = Instant::now();
                        let (events_tx, shared) = (&self.events_tx, &self.shared);
                        let host_ns = crate::camera::monotonic_ns();
                        self.protocol.on_bytes(&buf[..n], host_ns, &self.port, shared, &mut |ev| {
                            push(events_tx, shared, Ok(ev))
                        });
                    }
                },
                _ = tick.tick() => {
                    let f = self.current_frame();
                    if let Err((cause, reason)) = send_frame(s, &self.shared, &f, silence).await {
                        return SessionEnd::Lost(cause, reason);
                    }
                }
                _ = tokio::time::sleep_until(last_rx + silence) => {
                    return SessionEnd::Lost(LossCause::Silence, format!("nothing received for {} ms", silence.as_millis()));
                }
            }
        }
    }

    /// Reopens the port with exponential back-off until the handshake succeeds; `None` when the
    /// driver was dropped meanwhile.
    async fn reconnect(&mut self) -> Option<C::Stream> {
        let mut delay = self.timing.backoff.initial;
        loop {
            let sleep = tokio::time::sleep(delay);
            tokio::pin!(sleep);
            loop {
                tokio::select! {
                    _ = &mut sleep => break,
                    changed = self.cmd_rx.changed() => if changed.is_err() { return None },
                }
            }
            match self.connector.connect().await {
                Ok(mut s) => match self.protocol.handshake(&mut s, &self.port, &self.shared).await {
                    Ok(hello) => {
                        *self.shared.emergency.lock().unwrap_or_else(|e| e.into_inner()) =
                            self.connector.emergency_writer(&s);
                        self.shared.connected.store(true, Ordering::Relaxed);
                        self.shared.reconnects.fetch_add(1, Ordering::Relaxed);
                        self.fresh_required = true;
                        self.connected(&hello, true);
                        return Some(s);
                    }
                    Err(e) => {
                        // The port went away again before the link was up: a loss the OS
                        // reported, though not of a link that was up.
                        if self.connector.hung_up(&s) {
                            self.shared.hangups_reconnecting.fetch_add(1, Ordering::Relaxed);
                        }
                        tracing::debug!("reconnect: {e}");
                    }
                },
                Err(e) => tracing::debug!("reconnect: {e}"),
            }
            delay = (delay * 2).min(self.timing.backoff.max);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clock_mapper_takes_the_least_delayed_sample_and_unwraps() {
        let mut m = ClockMapper::new(1 << 32, 1000);
        // Device clock = host clock - 5 s; latencies 3, 1, 2 ms.
        let host = |dev_us: u64, lat_ms: u64| dev_us * 1000 + 5_000_000_000 + lat_ms * 1_000_000;
        assert_eq!(m.map(1_000_000, host(1_000_000, 3)), host(1_000_000, 3));
        assert_eq!(m.map(1_020_000, host(1_020_000, 1)), host(1_020_000, 1));
        // A later, more delayed sample keeps the 1 ms estimate (plus the 200 ppm drift allowance).
        assert_eq!(m.map(1_040_000, host(1_040_000, 2)), host(1_040_000, 1) + 4_200);
        // Wrap of the u32 µs counter: device time continues past 2^32 µs.
        let before = (1u64 << 32) - 10_000;
        let mut m = ClockMapper::new(1 << 32, 1000);
        let a = m.map(before, 10_000_000_000);
        let b = m.map(10_000, 10_000_000_000 + 20_000_000);
        assert_eq!(b - a, 20_000_000);
        // A reboot (clock far back) restarts the estimate.
        let c = m.map(5, 10_100_000_000);
        assert_eq!(c, 10_100_000_000);
    }

    #[test]
    fn tick_unwrapper_handles_wrap() {
        let mut u = TickUnwrapper::default();
        assert_eq!(u.update(65_530, 16), 0);
        assert_eq!(u.update(4, 16), 10);
        assert_eq!(u.update(65_534, 16), 4);
        let mut u = TickUnwrapper::default();
        u.update(i32::MAX as u32, 32);
        assert_eq!(u.update(i32::MIN as u32, 32), 1);
    }
}
