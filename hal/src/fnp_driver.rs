//! Host driver for FNP/1 bases (`PROTOCOL.md`) over a serial port, and the serial plumbing the
//! Kobuki driver shares: opening a port with clear errors, back-off, device-clock mapping.
//!
//! [`FnpBase::connect`] opens the port, says HELLO (setting the base's watchdog) and waits for
//! INFO, then hands the port to a background tokio task that
//! - sends the latest command at once and repeats it at `setpoint_rate_hz` (default 25 Hz),
//!   zeroing a non-zero command that was not refreshed within `command_timeout`;
//! - decodes ODOM and STATUS into [`BaseEvent`]s, with device timestamps mapped to host time
//!   ([`ClockMapper`]) and cumulative encoder counts unwrapped to `i64`;
//! - declares the link down when the port fails or nothing arrives for `silence_timeout`
//!   (500 ms), then reopens the port and repeats the handshake with exponential back-off;
//! - sends STOP when the driver is dropped (also synchronously from `Drop`, through a duplicate
//!   of the port's descriptor, so the STOP goes out even when the runtime is shutting down).

use crate::base::{BaseEvent, BaseStatus, LinkStats, MotorBase, host_now_ns};
use crate::error::{Error, ErrorKind};
use crate::fnp::{self, Decoder, Direction, Packet};
use crate::motion::{BodyVelocity, Odometry};
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
    #[error("{port}: the base speaks FNP/{version}, this driver FNP/{}", fnp::VERSION)]
    Incompatible { port: String, version: u8 },
    #[error("{port}: link lost ({reason}); reconnecting")]
    Disconnected { port: String, reason: String },
    #[error("{port}: the driver's background task has ended")]
    Closed { port: String },
    #[error("base configuration: {0}")]
    Config(String),
}

impl Error for SerialBaseError {
    fn kind(&self) -> ErrorKind {
        match self {
            SerialBaseError::NoSuchPort { .. } | SerialBaseError::Disconnected { .. } => ErrorKind::Disconnected,
            SerialBaseError::Closed { .. } => ErrorKind::Disconnected,
            SerialBaseError::NoAnswer { .. } => ErrorKind::Timeout,
            SerialBaseError::Incompatible { .. } | SerialBaseError::Config(_) => ErrorKind::Unsupported,
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

/// What the base said about itself in INFO.
#[derive(Clone, Debug, PartialEq)]
pub struct DeviceInfo {
    pub version: u8,
    pub wheel_base_m: f64,
    pub ticks_per_m: u32,
    pub name: String,
}

/// Settings of the FNP/1 driver.
#[derive(Clone, Debug)]
pub struct FnpConfig {
    pub port: String,
    pub baud: u32,
    /// How often the current command is repeated (PROTOCOL.md: ≥ 20 Hz).
    pub setpoint_rate_hz: f64,
    /// The base's watchdog, sent in HELLO.
    pub watchdog_ms: u16,
    /// How long to wait for INFO after HELLO (HELLO is repeated 4 times in that window).
    pub handshake_timeout: Duration,
    /// Nothing received for this long: the link is down.
    pub silence_timeout: Duration,
    /// A non-zero command not refreshed for this long is replaced by zero (`None`: never).
    pub command_timeout: Option<Duration>,
    pub backoff: Backoff,
}

impl FnpConfig {
    pub fn new(port: impl Into<String>) -> Self {
        Self {
            port: port.into(),
            baud: 115_200,
            setpoint_rate_hz: 25.0,
            watchdog_ms: 250,
            handshake_timeout: Duration::from_secs(1),
            silence_timeout: Duration::from_millis(500),
            command_timeout: Some(Duration::from_millis(500)),
            backoff: Backoff::default(),
        }
    }

    fn validate(&self) -> Result<(), SerialBaseError> {
        if !(20.0..=1000.0).contains(&self.setpoint_rate_hz) {
            return Err(SerialBaseError::Config(format!(
                "setpoint_rate_hz = {} must be in 20..=1000 (PROTOCOL.md asks for at least 20 Hz)",
                self.setpoint_rate_hz
            )));
        }
        if self.watchdog_ms == 0 {
            return Err(SerialBaseError::Config("watchdog_ms must be at least 1".into()));
        }
        if self.silence_timeout.is_zero() || self.handshake_timeout.is_zero() {
            return Err(SerialBaseError::Config("silence_timeout and handshake_timeout must be positive".into()));
        }
        Ok(())
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Command {
    Stop,
    Drive { v_mm_s: i16, omega_mrad_s: i16 },
}

#[derive(Clone, Copy, Debug)]
struct CommandMsg {
    cmd: Command,
    at: Instant,
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
    pub reconnects: AtomicU64,
    pub command_timeouts: AtomicU64,
    pub events_dropped: AtomicU64,
    pub next_seq: AtomicU8,
    pub emergency: Mutex<Option<std::fs::File>>,
}

impl Shared {
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

type EventMsg = Result<BaseEvent, SerialBaseError>;
const EVENT_QUEUE: usize = 1024;

/// An FNP/1 base: the [`MotorBase`] over a serial port. See the module docs.
pub struct FnpBase {
    port: String,
    info: DeviceInfo,
    cmd_tx: watch::Sender<CommandMsg>,
    events_rx: mpsc::Receiver<EventMsg>,
    shared: Arc<Shared>,
    decode: Arc<Mutex<fnp::DecodeStats>>,
    task: Option<tokio::task::JoinHandle<()>>,
}

impl FnpBase {
    /// Opens `cfg.port`, performs the HELLO/INFO handshake and starts the background task.
    /// Must be called inside a tokio runtime.
    pub async fn connect(cfg: FnpConfig) -> Result<Self, SerialBaseError> {
        let connector = SerialConnector::new(cfg.port.clone(), cfg.baud);
        Self::connect_with(cfg, connector).await
    }

    /// Like [`Self::connect`] over any [`Connector`] (tests use in-memory pipes).
    pub async fn connect_with<C: Connector>(cfg: FnpConfig, mut connector: C) -> Result<Self, SerialBaseError> {
        cfg.validate()?;
        let port = connector.port_name().to_string();
        let shared = Arc::new(Shared::default());
        let mut decoder = Decoder::new(Direction::BaseToHost);
        let mut stream = connector.connect().await?;
        let info = handshake(&mut stream, &cfg, &port, &shared, &mut decoder).await?;
        *shared.emergency.lock().unwrap_or_else(|e| e.into_inner()) = connector.emergency_writer(&stream);
        shared.connected.store(true, Ordering::Relaxed);
        tracing::info!(port, name = %info.name, wheel_base_m = info.wheel_base_m, ticks_per_m = info.ticks_per_m, "FNP/1 base connected");

        let (cmd_tx, cmd_rx) = watch::channel(CommandMsg { cmd: Command::Stop, at: Instant::now() });
        let (events_tx, events_rx) = mpsc::channel(EVENT_QUEUE);
        let decode = Arc::new(Mutex::new(decoder.stats()));
        let link = Link {
            cfg,
            connector,
            port: port.clone(),
            shared: shared.clone(),
            decode: decode.clone(),
            cmd_rx,
            events_tx,
            decoder,
            clock: ClockMapper::new(1 << 32, 1000),
            left: TickUnwrapper::default(),
            right: TickUnwrapper::default(),
            fresh_required: false,
            timed_out_at: None,
        };
        let task = tokio::spawn(link.run(stream));
        Ok(Self { port, info, cmd_tx, events_rx, shared, decode, task: Some(task) })
    }

    /// What the base reported in INFO at the last handshake.
    pub fn info(&self) -> &DeviceInfo {
        &self.info
    }

    /// Dropped-frame counters by kind, as seen by the FNP/1 decoder.
    pub fn decode_stats(&self) -> fnp::DecodeStats {
        *self.decode.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Sends STOP and waits until the background task has written it and ended.
    pub async fn close(mut self) {
        self.send_command(Command::Stop);
        if let Some(task) = self.task.take() {
            // Replacing the sender closes the channel: the task sends STOP and ends.
            let (dummy, _) = watch::channel(CommandMsg { cmd: Command::Stop, at: Instant::now() });
            drop(std::mem::replace(&mut self.cmd_tx, dummy));
            let _ = task.await;
        }
    }

    fn send_command(&self, cmd: Command) {
        self.cmd_tx.send_replace(CommandMsg { cmd, at: Instant::now() });
    }
}

impl MotorBase for FnpBase {
    type Error = SerialBaseError;

    fn set_velocity(&mut self, cmd: BodyVelocity) -> Result<(), SerialBaseError> {
        self.shared.check_connected(&self.port)?;
        let v_mm_s = fnp::to_i16_clamped(cmd.v, 1000.0);
        let omega_mrad_s = fnp::to_i16_clamped(cmd.omega, 1000.0);
        self.send_command(Command::Drive { v_mm_s, omega_mrad_s });
        Ok(())
    }

    fn stop(&mut self) -> Result<(), SerialBaseError> {
        self.send_command(Command::Stop);
        self.shared.check_connected(&self.port)
    }

    async fn next_event(&mut self, timeout: Duration) -> Result<Option<BaseEvent>, SerialBaseError> {
        next_event(&mut self.events_rx, timeout, &self.port).await
    }

    fn link_stats(&self) -> LinkStats {
        self.shared.stats()
    }
}

pub(crate) async fn next_event(
    rx: &mut mpsc::Receiver<EventMsg>,
    timeout: Duration,
    port: &str,
) -> Result<Option<BaseEvent>, SerialBaseError> {
    match tokio::time::timeout(timeout, rx.recv()).await {
        Err(_) => Ok(None),
        Ok(Some(Ok(ev))) => Ok(Some(ev)),
        Ok(Some(Err(e))) => Err(e),
        Ok(None) => Err(SerialBaseError::Closed { port: port.to_string() }),
    }
}

impl Drop for FnpBase {
    fn drop(&mut self) {
        // The task sends STOP when it sees the command channel close; this synchronous STOP covers
        // a runtime that is shutting down and will not run the task again.
        let seq = self.shared.next_seq.fetch_add(1, Ordering::Relaxed);
        self.shared.emergency_write(&fnp::encode(seq, &Packet::Stop));
    }
}

async fn send_packet<S: AsyncWrite + Unpin>(
    s: &mut S,
    shared: &Shared,
    packet: &Packet,
    limit: Duration,
) -> Result<(), String> {
    let seq = shared.next_seq.fetch_add(1, Ordering::Relaxed);
    let bytes = fnp::encode(seq, packet);
    match tokio::time::timeout(limit, async {
        s.write_all(&bytes).await?;
        s.flush().await
    })
    .await
    {
        Ok(Ok(())) => {
            shared.frames_tx.fetch_add(1, Ordering::Relaxed);
            Ok(())
        }
        Ok(Err(e)) => Err(format!("write failed: {e}")),
        Err(_) => Err(format!("write blocked for {} ms", limit.as_millis())),
    }
}

/// HELLO, then wait for INFO; HELLO is repeated four times within `handshake_timeout`.
async fn handshake<S: AsyncRead + AsyncWrite + Unpin>(
    s: &mut S,
    cfg: &FnpConfig,
    port: &str,
    shared: &Shared,
    decoder: &mut Decoder,
) -> Result<DeviceInfo, SerialBaseError> {
    let deadline = Instant::now() + cfg.handshake_timeout;
    let resend = cfg.handshake_timeout / 4;
    let mut buf = [0u8; 256];
    let lost = |reason: String| SerialBaseError::Disconnected { port: port.to_string(), reason };
    loop {
        send_packet(s, shared, &Packet::Hello { watchdog_ms: cfg.watchdog_ms }, cfg.handshake_timeout)
            .await
            .map_err(lost)?;
        let until = (Instant::now() + resend).min(deadline);
        loop {
            let n = match tokio::time::timeout_at(until, s.read(&mut buf)).await {
                Err(_) => break,
                Ok(Ok(0)) => return Err(lost("port closed during the handshake".into())),
                Ok(Ok(n)) => n,
                Ok(Err(e)) => return Err(lost(format!("read failed during the handshake: {e}"))),
            };
            let mut info = None;
            decoder.feed(&buf[..n], |f| {
                if let Packet::Info { version, wheel_base_mm, ticks_per_m, name } = f.packet {
                    info = Some(DeviceInfo {
                        version,
                        wheel_base_m: f64::from(wheel_base_mm) / 1000.0,
                        ticks_per_m,
                        name,
                    });
                }
            });
            if let Some(info) = info {
                if info.version != fnp::VERSION {
                    return Err(SerialBaseError::Incompatible { port: port.to_string(), version: info.version });
                }
                return Ok(info);
            }
        }
        if Instant::now() >= deadline {
            return Err(SerialBaseError::NoAnswer {
                port: port.to_string(),
                timeout_ms: cfg.handshake_timeout.as_millis() as u64,
                baud: cfg.baud,
                protocol: "FNP/1 (PROTOCOL.md)",
            });
        }
    }
}

enum SessionEnd {
    Shutdown,
    Lost(String),
}

/// The background task's state.
struct Link<C: Connector> {
    cfg: FnpConfig,
    connector: C,
    port: String,
    shared: Arc<Shared>,
    decode: Arc<Mutex<fnp::DecodeStats>>,
    cmd_rx: watch::Receiver<CommandMsg>,
    events_tx: mpsc::Sender<EventMsg>,
    decoder: Decoder,
    clock: ClockMapper,
    left: TickUnwrapper,
    right: TickUnwrapper,
    /// After a reconnect: send STOP until the caller commands again.
    fresh_required: bool,
    /// The command whose staleness was last counted.
    timed_out_at: Option<Instant>,
}

impl<C: Connector> Link<C> {
    async fn run(mut self, first: C::Stream) {
        let mut stream = first;
        loop {
            match self.session(&mut stream).await {
                SessionEnd::Shutdown => return,
                SessionEnd::Lost(reason) => {
                    self.shared.connected.store(false, Ordering::Relaxed);
                    self.shared.disconnects.fetch_add(1, Ordering::Relaxed);
                    *self.shared.emergency.lock().unwrap_or_else(|e| e.into_inner()) = None;
                    let err = SerialBaseError::Disconnected { port: self.port.clone(), reason };
                    tracing::warn!("{err}");
                    self.push(Err(err));
                }
            }
            drop(stream);
            match self.reconnect().await {
                Some(s) => stream = s,
                None => return,
            }
        }
    }

    fn push(&self, ev: EventMsg) {
        if let Err(mpsc::error::TrySendError::Full(_)) = self.events_tx.try_send(ev) {
            self.shared.events_dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    fn current_packet(&mut self) -> Packet {
        if self.fresh_required {
            return Packet::Stop;
        }
        let msg = *self.cmd_rx.borrow();
        match msg.cmd {
            Command::Stop => Packet::Stop,
            Command::Drive { v_mm_s, omega_mrad_s } => {
                let stale = self.cfg.command_timeout.is_some_and(|t| msg.at.elapsed() > t);
                if stale && (v_mm_s, omega_mrad_s) != (0, 0) {
                    if self.timed_out_at != Some(msg.at) {
                        self.timed_out_at = Some(msg.at);
                        self.shared.command_timeouts.fetch_add(1, Ordering::Relaxed);
                        tracing::warn!(
                            port = self.port,
                            "no new command within the command timeout: stopping the base"
                        );
                    }
                    Packet::Setpoint { v_mm_s: 0, omega_mrad_s: 0 }
                } else {
                    Packet::Setpoint { v_mm_s, omega_mrad_s }
                }
            }
        }
    }

    async fn session(&mut self, s: &mut C::Stream) -> SessionEnd {
        let period = Duration::from_secs_f64(1.0 / self.cfg.setpoint_rate_hz);
        let mut tick = tokio::time::interval(period);
        tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
        let silence = self.cfg.silence_timeout;
        let mut last_rx = Instant::now();
        let mut buf = [0u8; 512];
        loop {
            tokio::select! {
                biased;
                changed = self.cmd_rx.changed() => {
                    if changed.is_err() {
                        let _ = send_packet(s, &self.shared, &Packet::Stop, silence).await;
                        return SessionEnd::Shutdown;
                    }
                    self.fresh_required = false;
                    let p = self.current_packet();
                    if let Err(reason) = send_packet(s, &self.shared, &p, silence).await {
                        return SessionEnd::Lost(reason);
                    }
                    tick.reset();
                }
                n = s.read(&mut buf) => match n {
                    Ok(0) => return SessionEnd::Lost("the port was closed".into()),
                    Err(e) => return SessionEnd::Lost(format!("read failed: {e}")),
                    Ok(n) => {
                        last_rx = Instant::now();
                        self.on_bytes(&buf[..n]);
                    }
                },
                _ = tick.tick() => {
                    let p = self.current_packet();
                    if let Err(reason) = send_packet(s, &self.shared, &p, silence).await {
                        return SessionEnd::Lost(reason);
                    }
                }
                _ = tokio::time::sleep_until(last_rx + silence) => {
                    return SessionEnd::Lost(format!("nothing received for {} ms", silence.as_millis()));
                }
            }
        }
    }

    fn on_bytes(&mut self, bytes: &[u8]) {
        let host_ns = host_now_ns();
        let mut frames = Vec::new();
        self.decoder.feed(bytes, |f| frames.push(f));
        for f in frames {
            match f.packet {
                Packet::Odom { t_us, left_ticks, right_ticks, v_mm_s, omega_mrad_s } => {
                    let t_ns = self.clock.map(u64::from(t_us), host_ns);
                    let odom = Odometry {
                        t_ns,
                        velocity: BodyVelocity::new(f64::from(v_mm_s) / 1000.0, f64::from(omega_mrad_s) / 1000.0),
                        left_ticks: self.left.update(left_ticks as u32, 32),
                        right_ticks: self.right.update(right_ticks as u32, 32),
                    };
                    self.push(Ok(BaseEvent::Odometry(odom)));
                }
                Packet::Status { battery_mv, flags, .. } => {
                    let status = BaseStatus {
                        t_ns: host_ns,
                        battery_v: Some(f64::from(battery_mv) / 1000.0),
                        bumper: flags & fnp::flags::BUMPER != 0,
                        estop: flags & fnp::flags::ESTOP != 0,
                        stopped_by_watchdog: flags & fnp::flags::WATCHDOG_STOP != 0,
                        motor_fault: flags & fnp::flags::MOTOR_FAULT != 0,
                        cliff: false,
                        wheel_drop: false,
                    };
                    self.push(Ok(BaseEvent::Status(status)));
                }
                Packet::Info { .. } => tracing::debug!(port = self.port, "unsolicited INFO ignored"),
                _ => {}
            }
        }
        let st = self.decoder.stats();
        self.shared.frames_rx.store(st.frames, Ordering::Relaxed);
        self.shared.dropped_rx.store(st.dropped(), Ordering::Relaxed);
        self.shared.lost_rx.store(st.lost, Ordering::Relaxed);
        *self.decode.lock().unwrap_or_else(|e| e.into_inner()) = st;
    }

    /// Reopens the port with exponential back-off until the handshake succeeds; `None` when the
    /// driver was dropped meanwhile.
    async fn reconnect(&mut self) -> Option<C::Stream> {
        let mut delay = self.cfg.backoff.initial;
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
                Ok(mut s) => {
                    self.decoder.resync();
                    match handshake(&mut s, &self.cfg, &self.port, &self.shared, &mut self.decoder).await {
                        Ok(info) => {
                            *self.shared.emergency.lock().unwrap_or_else(|e| e.into_inner()) =
                                self.connector.emergency_writer(&s);
                            self.shared.connected.store(true, Ordering::Relaxed);
                            self.shared.reconnects.fetch_add(1, Ordering::Relaxed);
                            self.left.rebase();
                            self.right.rebase();
                            self.fresh_required = true;
                            tracing::info!(port = self.port, name = %info.name, "FNP/1 base reconnected");
                            return Some(s);
                        }
                        Err(e) => tracing::debug!("reconnect: {e}"),
                    }
                }
                Err(e) => tracing::debug!("reconnect: {e}"),
            }
            delay = (delay * 2).min(self.cfg.backoff.max);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::DuplexStream;

    /// Hands out pre-made in-memory pipes, one per connect; fails like a missing port when empty.
    struct PipeConnector(mpsc::UnboundedReceiver<DuplexStream>);

    impl Connector for PipeConnector {
        type Stream = DuplexStream;
        async fn connect(&mut self) -> Result<DuplexStream, SerialBaseError> {
            self.0.try_recv().map_err(|_| SerialBaseError::NoSuchPort { port: "pipe".into() })
        }
        fn port_name(&self) -> &str {
            "pipe"
        }
    }

    type PacketLog = Arc<Mutex<Vec<(Instant, Packet)>>>;

    /// A minimal scripted base on the other end of a pipe: answers HELLO, sends ODOM every
    /// 20 ms (device clock = tokio time), records every packet it receives.
    async fn fake_base(mut s: DuplexStream, log: PacketLog, mute_after: Option<Duration>) {
        let t0 = Instant::now();
        let mut dec = Decoder::new(Direction::HostToBase);
        let mut tick = tokio::time::interval(Duration::from_millis(20));
        let mut seq = 0u8;
        let mut buf = [0u8; 256];
        loop {
            tokio::select! {
                n = s.read(&mut buf) => {
                    let Ok(n) = n else { return };
                    if n == 0 { return; }
                    for f in dec.feed_collect(&buf[..n]) {
                        if let Packet::Hello { .. } = f.packet {
                            let info = Packet::Info { version: 1, wheel_base_mm: 330, ticks_per_m: 10000, name: "fake".into() };
                            if s.write_all(&fnp::encode(seq, &info)).await.is_err() { return; }
                            seq = seq.wrapping_add(1);
                        }
                        log.lock().unwrap().push((Instant::now(), f.packet));
                    }
                }
                _ = tick.tick() => {
                    if mute_after.is_some_and(|m| t0.elapsed() >= m) { continue; }
                    let t_us = t0.elapsed().as_micros() as u32;
                    let odom = Packet::Odom { t_us, left_ticks: 0, right_ticks: 0, v_mm_s: 0, omega_mrad_s: 0 };
                    if s.write_all(&fnp::encode(seq, &odom)).await.is_err() { return; }
                    seq = seq.wrapping_add(1);
                }
            }
        }
    }

    fn pipes(n: usize, mute_first_after: Option<Duration>) -> (PipeConnector, PacketLog) {
        let (tx, rx) = mpsc::unbounded_channel();
        let log = Arc::new(Mutex::new(Vec::new()));
        for i in 0..n {
            let (host, dev) = tokio::io::duplex(4096);
            tx.send(host).unwrap();
            tokio::spawn(fake_base(dev, log.clone(), if i == 0 { mute_first_after } else { None }));
        }
        (PipeConnector(rx), log)
    }

    fn setpoints_between(log: &[(Instant, Packet)], from: Instant, to: Instant) -> Vec<Packet> {
        log.iter()
            .filter(|(t, p)| *t >= from && *t < to && matches!(p, Packet::Setpoint { .. }))
            .map(|(_, p)| p.clone())
            .collect()
    }

    #[tokio::test(start_paused = true)]
    async fn setpoints_repeat_at_the_configured_rate_and_clamp() {
        let (conn, log) = pipes(1, None);
        let mut cfg = FnpConfig::new("pipe");
        cfg.command_timeout = None;
        let mut base = FnpBase::connect_with(cfg, conn).await.unwrap();
        assert_eq!(base.info().name, "fake");
        assert_eq!(base.info().wheel_base_m, 0.33);
        base.set_velocity(BodyVelocity::new(100.0, -0.15)).unwrap();
        let t0 = Instant::now();
        tokio::time::sleep(Duration::from_secs(2)).await;
        let sent = setpoints_between(&log.lock().unwrap(), t0, t0 + Duration::from_secs(2));
        // 25 Hz for 2 s: 50 repeats, plus the immediate send of the new command.
        assert!((50..=52).contains(&sent.len()), "{} set-points in 2 s", sent.len());
        assert!(sent.iter().all(|p| *p == Packet::Setpoint { v_mm_s: i16::MAX, omega_mrad_s: -150 }));
        // Odometry flowed meanwhile.
        let mut odoms = 0;
        while let Ok(Some(ev)) = base.next_event(Duration::from_millis(1)).await {
            odoms += matches!(ev, BaseEvent::Odometry(_)) as usize;
        }
        assert!(odoms >= 90, "{odoms} odometry events");
        base.close().await;
        assert_eq!(log.lock().unwrap().last().unwrap().1, Packet::Stop);
    }

    #[tokio::test(start_paused = true)]
    async fn stale_command_is_zeroed_by_the_host_watchdog() {
        let (conn, log) = pipes(1, None);
        let mut base = FnpBase::connect_with(FnpConfig::new("pipe"), conn).await.unwrap();
        base.set_velocity(BodyVelocity::new(0.3, 0.0)).unwrap();
        let t0 = Instant::now();
        tokio::time::sleep(Duration::from_secs(1)).await;
        let sent = setpoints_between(&log.lock().unwrap(), t0, t0 + Duration::from_secs(1));
        let moving = sent.iter().filter(|p| **p == Packet::Setpoint { v_mm_s: 300, omega_mrad_s: 0 }).count();
        let zero = sent.iter().filter(|p| **p == Packet::Setpoint { v_mm_s: 0, omega_mrad_s: 0 }).count();
        assert!((12..=14).contains(&moving), "{moving} moving set-points in the 500 ms command timeout");
        assert!(zero >= 11, "{zero}");
        assert_eq!(base.link_stats().command_timeouts, 1);
    }

    #[tokio::test(start_paused = true)]
    async fn silent_base_is_a_clear_timeout() {
        let (tx, rx) = mpsc::unbounded_channel();
        let (host, _dev) = tokio::io::duplex(4096);
        tx.send(host).unwrap();
        let err = FnpBase::connect_with(FnpConfig::new("pipe"), PipeConnector(rx)).await.err().unwrap();
        assert_eq!(err.kind(), ErrorKind::Timeout);
        let msg = err.to_string();
        assert!(msg.starts_with("pipe: the base did not answer within 1000 ms at 115200 baud"), "{msg}");
        assert!(msg.contains("cable"), "{msg}");
    }

    #[tokio::test]
    async fn missing_port_names_the_port() {
        let err = FnpBase::connect(FnpConfig::new("/dev/ttyUSB_flownav_missing")).await.err().unwrap();
        assert_eq!(
            err.to_string(),
            "/dev/ttyUSB_flownav_missing: no such device; is the base plugged in? see README 'udev'"
        );
        assert_eq!(err.kind(), ErrorKind::Disconnected);
    }

    #[tokio::test(start_paused = true)]
    async fn silence_disconnects_and_the_driver_reconnects_with_a_fresh_stop() {
        let (conn, log) = pipes(2, Some(Duration::from_millis(300)));
        let mut base = FnpBase::connect_with(FnpConfig::new("pipe"), conn).await.unwrap();
        base.set_velocity(BodyVelocity::new(0.2, 0.0)).unwrap();
        let mut saw_disconnect = false;
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(3) {
            match base.next_event(Duration::from_millis(100)).await {
                Err(e) => {
                    assert_eq!(e.kind(), ErrorKind::Disconnected);
                    assert!(e.to_string().contains("nothing received for 500 ms"), "{e}");
                    saw_disconnect = true;
                }
                Ok(_) if saw_disconnect && base.link_stats().connected => break,
                Ok(_) => {}
            }
        }
        let stats = base.link_stats();
        assert!(saw_disconnect);
        assert_eq!((stats.disconnects, stats.reconnects, stats.connected), (1, 1, true));
        // After the reconnect the driver sends STOP until commanded again.
        let hello_at = log.lock().unwrap().iter().filter(|(_, p)| matches!(p, Packet::Hello { .. })).nth(1).unwrap().0;
        tokio::time::sleep(Duration::from_millis(200)).await;
        let after: Vec<Packet> =
            log.lock().unwrap().iter().filter(|(t, _)| *t > hello_at).map(|(_, p)| p.clone()).collect();
        assert!(!after.is_empty() && after.iter().all(|p| *p == Packet::Stop), "{after:?}");
        base.set_velocity(BodyVelocity::new(0.2, 0.0)).unwrap();
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert_eq!(log.lock().unwrap().last().unwrap().1, Packet::Setpoint { v_mm_s: 200, omega_mrad_s: 0 });
    }

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
