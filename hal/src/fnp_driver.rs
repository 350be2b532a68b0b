//! Host driver for FNP/1 bases (docs/protocol.md) over a serial port.
//!
//! [`FnpBase::connect`] opens the port, says HELLO (setting the base's watchdog) and waits for
//! INFO, then hands the port to the shared serial task ([`crate::serial_task`]), which
//! - sends the latest command at once and repeats it at `setpoint_rate_hz` (default 25 Hz),
//!   zeroing a non-zero command that was not refreshed within `command_timeout`;
//! - declares the link down when the port fails or nothing arrives for `silence_timeout`
//!   (500 ms), then reopens the port and repeats the handshake with exponential back-off;
//! - sends STOP when the driver is dropped (also synchronously from `Drop`, through a duplicate
//!   of the port's descriptor, so the STOP goes out even when the runtime is shutting down).
//!
//! This module decodes ODOM and STATUS into [`BaseEvent`]s, with device timestamps mapped to
//! host time ([`ClockMapper`]) and cumulative encoder counts unwrapped to `i64`.

use crate::base::{BaseEvent, BaseStatus, LinkStats, MotorBase};
use crate::fnp::{self, Decoder, Direction, Packet};
use crate::motion::{BodyVelocity, Odometry};
use crate::serial_task::{Protocol, SerialTask, Shared, TaskTiming, send_frame};
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite};
use tokio::time::Instant;

// The shared serial types, under the paths that callers of this driver use.
pub use crate::serial_task::{Backoff, ClockMapper, Connector, SerialBaseError, SerialConnector, TickUnwrapper};

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
    /// How often the current command is repeated (docs/protocol.md: ≥ 20 Hz).
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
                "setpoint_rate_hz = {} must be in 20..=1000 (docs/protocol.md asks for at least 20 Hz)",
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

/// An FNP/1 base: the [`MotorBase`] over a serial port. See the module docs.
pub struct FnpBase {
    link: SerialTask<Fnp>,
    info: DeviceInfo,
    decode: Arc<Mutex<fnp::DecodeStats>>,
}

impl FnpBase {
    /// Opens `cfg.port`, performs the HELLO/INFO handshake and starts the background task.
    /// Must be called inside a tokio runtime.
    pub async fn connect(cfg: FnpConfig) -> Result<Self, SerialBaseError> {
        let connector = SerialConnector::new(cfg.port.clone(), cfg.baud);
        Self::connect_with(cfg, connector).await
    }

    /// Like [`Self::connect`] over any [`Connector`] (tests use in-memory pipes).
    pub async fn connect_with<C: Connector>(cfg: FnpConfig, connector: C) -> Result<Self, SerialBaseError> {
        cfg.validate()?;
        let timing = TaskTiming {
            rate_hz: cfg.setpoint_rate_hz,
            silence_timeout: cfg.silence_timeout,
            command_timeout: cfg.command_timeout,
            backoff: cfg.backoff,
        };
        let decoder = Decoder::new(Direction::BaseToHost);
        let decode = Arc::new(Mutex::new(decoder.stats()));
        let protocol = Fnp {
            cfg,
            decoder,
            decode: decode.clone(),
            clock: ClockMapper::new(1 << 32, 1000),
            left: TickUnwrapper::default(),
            right: TickUnwrapper::default(),
        };
        let (link, info) = SerialTask::start(protocol, timing, connector).await?;
        Ok(Self { link, info, decode })
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
        self.link.close().await;
    }
}

impl MotorBase for FnpBase {
    type Error = SerialBaseError;

    /// Refuses a command that does not fit SETPOINT's fields (±32.767 m/s, ±32.767 rad/s, not
    /// NaN) with [`SerialBaseError::OutOfRange`], and stops the base: saturating it would send
    /// a different command than the caller's without telling anyone.
    fn set_velocity(&mut self, cmd: BodyVelocity) -> Result<(), SerialBaseError> {
        match fnp::setpoint_fields(cmd.v, cmd.omega) {
            Ok((v_mm_s, omega_mrad_s)) => self.link.command(Command::Drive { v_mm_s, omega_mrad_s }),
            Err(e) => {
                // The stop is recorded even while the link is down; the range error is the one to report.
                let _ = self.link.stop();
                Err(e.into())
            }
        }
    }

    fn stop(&mut self) -> Result<(), SerialBaseError> {
        self.link.stop()
    }

    async fn next_event(&mut self, timeout: Duration) -> Result<Option<BaseEvent>, SerialBaseError> {
        self.link.next_event(timeout).await
    }

    fn link_stats(&self) -> LinkStats {
        self.link.link_stats()
    }
}

/// FNP/1 as the serial task speaks it: SETPOINT/STOP out, ODOM and STATUS in.
struct Fnp {
    cfg: FnpConfig,
    decoder: Decoder,
    /// The decoder's counters, shared with [`FnpBase::decode_stats`].
    decode: Arc<Mutex<fnp::DecodeStats>>,
    clock: ClockMapper,
    left: TickUnwrapper,
    right: TickUnwrapper,
}

impl Protocol for Fnp {
    type Command = Command;
    type Hello = DeviceInfo;
    const IDLE: Command = Command::Stop;
    const NAME: &'static str = "base";

    fn is_moving(cmd: &Command) -> bool {
        matches!(*cmd, Command::Drive { v_mm_s, omega_mrad_s } if (v_mm_s, omega_mrad_s) != (0, 0))
    }

    fn command_frame(cmd: &Command, seq: u8) -> Vec<u8> {
        match *cmd {
            Command::Stop => fnp::encode(seq, &Packet::Stop).to_vec(),
            Command::Drive { v_mm_s, omega_mrad_s } => {
                fnp::encode(seq, &Packet::Setpoint { v_mm_s, omega_mrad_s }).to_vec()
            }
        }
    }

    fn stop_frame(seq: u8) -> Vec<u8> {
        fnp::encode(seq, &Packet::Stop).to_vec()
    }

    fn expired_frame(seq: u8) -> Vec<u8> {
        fnp::encode(seq, &Packet::Setpoint { v_mm_s: 0, omega_mrad_s: 0 }).to_vec()
    }

    async fn handshake<S: AsyncRead + AsyncWrite + Unpin + Send>(
        &mut self,
        s: &mut S,
        port: &str,
        shared: &Shared,
    ) -> Result<DeviceInfo, SerialBaseError> {
        // Bytes of a previous connection are not the start of this one's frames.
        self.decoder.resync();
        handshake(s, &self.cfg, port, shared, &mut self.decoder).await
    }

    fn on_connected(&mut self, info: &DeviceInfo, reconnect: bool, port: &str, _push: &mut impl FnMut(BaseEvent)) {
        if reconnect {
            self.left.rebase();
            self.right.rebase();
            tracing::info!(port, name = %info.name, "FNP/1 base reconnected");
        } else {
            *self.decode.lock().unwrap_or_else(|e| e.into_inner()) = self.decoder.stats();
            tracing::info!(port, name = %info.name, wheel_base_m = info.wheel_base_m, ticks_per_m = info.ticks_per_m, "FNP/1 base connected");
        }
    }

    fn on_bytes(&mut self, bytes: &[u8], host_ns: u64, port: &str, shared: &Shared, push: &mut impl FnMut(BaseEvent)) {
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
                    push(BaseEvent::Odometry(odom));
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
                    push(BaseEvent::Status(status));
                }
                Packet::Info { .. } => tracing::debug!(port, "unsolicited INFO ignored"),
                _ => {}
            }
        }
        let st = self.decoder.stats();
        shared.frames_rx.store(st.frames, Ordering::Relaxed);
        shared.dropped_rx.store(st.dropped(), Ordering::Relaxed);
        shared.lost_rx.store(st.lost, Ordering::Relaxed);
        *self.decode.lock().unwrap_or_else(|e| e.into_inner()) = st;
    }
}

/// HELLO, then wait for INFO; HELLO is repeated four times within `handshake_timeout`.
async fn handshake<S: AsyncRead + AsyncWrite + Unpin + Send>(
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
        let hello = fnp::encode(shared.take_seq(), &Packet::Hello { watchdog_ms: cfg.watchdog_ms });
        send_frame(s, shared, &hello, cfg.handshake_timeout).await.map_err(|(_, reason)| lost(reason))?;
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
                        name: name.to_string(),
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
                protocol: "FNP/1 (docs/protocol.md)",
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::{Error, ErrorKind};
    use tokio::io::AsyncWriteExt;
    use tokio::io::DuplexStream;
    use tokio::sync::mpsc;

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
                            let info = Packet::Info { version: 1, wheel_base_mm: 330, ticks_per_m: 10000, name: fnp::ascii_name("fake") };
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
    async fn setpoints_repeat_at_the_configured_rate() {
        let (conn, log) = pipes(1, None);
        let mut cfg = FnpConfig::new("pipe");
        cfg.command_timeout = None;
        let mut base = FnpBase::connect_with(cfg, conn).await.unwrap();
        assert_eq!(base.info().name, "fake");
        assert_eq!(base.info().wheel_base_m, 0.33);
        base.set_velocity(BodyVelocity::new(0.3, -0.15)).unwrap();
        let t0 = Instant::now();
        tokio::time::sleep(Duration::from_secs(2)).await;
        let sent = setpoints_between(&log.lock().unwrap(), t0, t0 + Duration::from_secs(2));
        // 25 Hz for 2 s: 50 repeats, plus the immediate send of the new command.
        assert!((50..=52).contains(&sent.len()), "{} set-points in 2 s", sent.len());
        assert!(sent.iter().all(|p| *p == Packet::Setpoint { v_mm_s: 300, omega_mrad_s: -150 }));
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
    async fn out_of_range_setpoint_is_refused_and_stops_the_base() {
        let (conn, log) = pipes(1, None);
        let mut cfg = FnpConfig::new("pipe");
        cfg.command_timeout = None;
        let mut base = FnpBase::connect_with(cfg, conn).await.unwrap();
        base.set_velocity(BodyVelocity::new(0.3, 0.0)).unwrap();
        tokio::time::sleep(Duration::from_millis(100)).await;
        let err = base.set_velocity(BodyVelocity::new(100.0, 0.0)).unwrap_err();
        assert_eq!(err.kind(), ErrorKind::Unsupported);
        assert!(
            err.to_string().starts_with("linear set-point 100 m/s does not fit FNP/1's ±32.767 m/s field"),
            "{err}"
        );
        let err = base.set_velocity(BodyVelocity::new(0.1, f64::NAN)).unwrap_err();
        assert!(err.to_string().starts_with("angular set-point NaN rad/s"), "{err}");
        let t0 = Instant::now();
        tokio::time::sleep(Duration::from_millis(500)).await;
        // Nothing saturated went out: after the refusal the base hears STOP, repeated.
        let after: Vec<Packet> = log.lock().unwrap().iter().filter(|(t, _)| *t >= t0).map(|(_, p)| p.clone()).collect();
        assert!(after.len() >= 10 && after.iter().all(|p| *p == Packet::Stop), "{after:?}");
        // The next command that fits drives again.
        base.set_velocity(BodyVelocity::new(-32.768, 32.767)).unwrap();
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert_eq!(
            log.lock().unwrap().last().unwrap().1,
            Packet::Setpoint { v_mm_s: i16::MIN, omega_mrad_s: i16::MAX }
        );
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
        assert_eq!((stats.disconnects_silence, stats.disconnects_os), (1, 0), "a pipe that stays open went silent");
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
}
