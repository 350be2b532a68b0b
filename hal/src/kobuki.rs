//! The Kobuki (TurtleBot 2) base: its serial protocol and a [`MotorBase`] driver for it.
//!
//! Protocol (yujinrobot/kobuki-base `kobuki_core`: `command.cpp`, `core_sensors.cpp`,
//! `packet_finder.cpp`, `diff_drive.cpp`), 115200 8N1:
//! - frame: `AA 55 | len u8 | payload (len bytes) | checksum u8`, checksum = XOR of `len` and
//!   every payload byte; the payload is a sequence of sub-payloads `id u8 | sublen u8 | data`.
//! - host → base, Base Control (id 1, 4 bytes): `speed i16` mm/s, `radius i16` mm. radius 0 is
//!   straight; radius 1 is a pure rotation where `speed` is the wheel speed (`b·ω/2`); otherwise
//!   `speed` is the outer wheel's speed `(radius ± b/2)·ω` ([`velocity_command`]).
//! - base → host, Basic Sensor Data (id 1, 15 bytes, streamed at 50 Hz): `timestamp u16` ms,
//!   `bumper u8`, `wheel_drop u8`, `cliff u8`, `left_encoder u16`, `right_encoder u16`,
//!   `left_pwm i8`, `right_pwm i8`, `buttons u8`, `charger u8`, `battery u8` (0.1 V),
//!   `over_current u8`. Other sub-payloads (gyro, docking IR, …) are skipped by their length.
//! - geometry: wheel base 0.230 m, wheel radius 0.035 m, `tick_to_rad` 0.0024369 rad (2578.33
//!   ticks per wheel turn), so [`TICKS_PER_M`] = 2578.33 / (2π·0.035) ≈ 11724.41.
//!
//! The firmware has no command watchdog: it keeps driving at the last command forever. The
//! driver therefore repeats the command at a fixed rate, sends zero when the caller has not
//! refreshed a non-zero command within `command_timeout`, and sends zero on drop and on exit
//! (the shared serial task, [`crate::serial_task`], does all three).

use crate::base::{BaseEvent, BaseStatus, LinkStats, MotorBase};
use crate::camera::monotonic_ns;
use crate::motion::{BodyVelocity, Odometry};
use crate::serial_task::{
    Backoff, ClockMapper, Connector, Protocol, SerialBaseError, SerialConnector, SerialTask, Shared, TaskTiming,
    TickUnwrapper,
};
use std::sync::atomic::Ordering;
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite};
use tokio::time::Instant;

/// Distance between the wheels, m (`bias` in kobuki_core).
pub const WHEEL_BASE_M: f64 = 0.23;
pub const WHEEL_RADIUS_M: f64 = 0.035;
/// Wheel rotation per encoder tick, rad (kobuki_core's `tick_to_rad`).
pub const TICK_TO_RAD: f64 = 0.002_436_916_871_363_93;
/// Encoder ticks per wheel revolution (2578.33).
pub const TICKS_PER_REV: f64 = std::f64::consts::TAU / TICK_TO_RAD;
/// Encoder ticks per metre of wheel travel.
pub const TICKS_PER_M: f64 = TICKS_PER_REV / (std::f64::consts::TAU * WHEEL_RADIUS_M);

/// Sub-payload id of Base Control (host → base) and of Basic Sensor Data (base → host).
pub const BASE_CONTROL: u8 = 0x01;
pub const CORE_SENSORS: u8 = 0x01;
const CORE_SENSORS_LEN: usize = 15;

/// Bit masks of the Basic Sensor Data fields.
pub mod mask {
    pub const BUMPER_RIGHT: u8 = 0x01;
    pub const BUMPER_CENTRE: u8 = 0x02;
    pub const BUMPER_LEFT: u8 = 0x04;
    pub const WHEEL_DROP_RIGHT: u8 = 0x01;
    pub const WHEEL_DROP_LEFT: u8 = 0x02;
    pub const CLIFF_RIGHT: u8 = 0x01;
    pub const CLIFF_CENTRE: u8 = 0x02;
    pub const CLIFF_LEFT: u8 = 0x04;
    pub const OVERCURRENT_LEFT: u8 = 0x01;
    pub const OVERCURRENT_RIGHT: u8 = 0x02;
}

/// Basic Sensor Data, as on the wire.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CoreSensors {
    pub timestamp_ms: u16,
    pub bumper: u8,
    pub wheel_drop: u8,
    pub cliff: u8,
    pub left_encoder: u16,
    pub right_encoder: u16,
    pub left_pwm: i8,
    pub right_pwm: i8,
    pub buttons: u8,
    pub charger: u8,
    /// Battery voltage in 0.1 V.
    pub battery_dv: u8,
    pub over_current: u8,
}

impl CoreSensors {
    /// The sub-payload bytes (id, length, data).
    pub fn to_subpayload(&self) -> Vec<u8> {
        let mut p = vec![CORE_SENSORS, CORE_SENSORS_LEN as u8];
        p.extend_from_slice(&self.timestamp_ms.to_le_bytes());
        p.extend_from_slice(&[self.bumper, self.wheel_drop, self.cliff]);
        p.extend_from_slice(&self.left_encoder.to_le_bytes());
        p.extend_from_slice(&self.right_encoder.to_le_bytes());
        p.extend_from_slice(&[
            self.left_pwm as u8,
            self.right_pwm as u8,
            self.buttons,
            self.charger,
            self.battery_dv,
            self.over_current,
        ]);
        p
    }

    fn parse(d: &[u8]) -> Self {
        Self {
            timestamp_ms: u16::from_le_bytes([d[0], d[1]]),
            bumper: d[2],
            wheel_drop: d[3],
            cliff: d[4],
            left_encoder: u16::from_le_bytes([d[5], d[6]]),
            right_encoder: u16::from_le_bytes([d[7], d[8]]),
            left_pwm: d[9] as i8,
            right_pwm: d[10] as i8,
            buttons: d[11],
            charger: d[12],
            battery_dv: d[13],
            over_current: d[14],
        }
    }
}

/// Wraps a payload into a frame: `AA 55 len payload xor`. Payloads over 255 bytes are cut.
pub fn encode_frame(payload: &[u8]) -> Vec<u8> {
    let payload = &payload[..payload.len().min(255)];
    let mut out = Vec::with_capacity(payload.len() + 4);
    out.extend_from_slice(&[0xAA, 0x55, payload.len() as u8]);
    out.extend_from_slice(payload);
    let cs = out[2..].iter().fold(0u8, |a, &b| a ^ b);
    out.push(cs);
    out
}

/// The Base Control frame.
pub fn encode_base_control(speed_mm_s: i16, radius_mm: i16) -> Vec<u8> {
    let mut p = vec![BASE_CONTROL, 4];
    p.extend_from_slice(&speed_mm_s.to_le_bytes());
    p.extend_from_slice(&radius_mm.to_le_bytes());
    encode_frame(&p)
}

fn bound(x: f64) -> i16 {
    if x.is_nan() { 0 } else { x.clamp(f64::from(i16::MIN), f64::from(i16::MAX)) as i16 }
}

/// (speed mm/s, radius mm) for a body velocity, as kobuki_core's `DiffDrive::velocityCommands`.
pub fn velocity_command(v: f64, omega: f64, wheel_base_m: f64) -> (i16, i16) {
    const EPS: f64 = 1e-4;
    if omega.abs() < EPS || !omega.is_finite() {
        return (bound(1000.0 * v), 0);
    }
    let radius = v * 1000.0 / omega;
    if v.abs() < EPS || radius.abs() <= 1.0 {
        return (bound(1000.0 * wheel_base_m * omega / 2.0), 1);
    }
    let half = 1000.0 * wheel_base_m / 2.0;
    let speed = if radius > 0.0 { (radius + half) * omega } else { (radius - half) * omega };
    (bound(speed), bound(radius))
}

/// The body velocity a Base Control command asks for (the inverse of [`velocity_command`]).
pub fn body_velocity(speed_mm_s: i16, radius_mm: i16, wheel_base_m: f64) -> BodyVelocity {
    let speed = f64::from(speed_mm_s) / 1000.0;
    match radius_mm {
        0 => BodyVelocity::new(speed, 0.0),
        1 => BodyVelocity::new(0.0, 2.0 * speed / wheel_base_m),
        r => {
            let r = f64::from(r) / 1000.0;
            let outer = if r > 0.0 { r + wheel_base_m / 2.0 } else { r - wheel_base_m / 2.0 };
            let omega = speed / outer;
            BodyVelocity::new(r * omega, omega)
        }
    }
}

/// What a [`KobukiDecoder`] has seen.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct KobukiStats {
    pub frames: u64,
    pub bad_checksum: u64,
    /// Bytes skipped while hunting for `AA 55`.
    pub garbage_bytes: u64,
    /// Frames whose sub-payloads did not add up, or a Basic Sensor Data of the wrong length.
    pub malformed: u64,
    /// Sub-payloads of other kinds (gyro, docking IR, …), skipped.
    pub skipped_subpayloads: u64,
}

/// An incremental Kobuki frame decoder; on a bad checksum it resynchronises on the next `AA 55`
/// after the failed header. Never panics.
#[derive(Clone, Debug, Default)]
pub struct KobukiDecoder {
    buf: Vec<u8>,
    stats: KobukiStats,
}

impl KobukiDecoder {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn stats(&self) -> KobukiStats {
        self.stats
    }

    /// Feeds bytes; returns the payloads of the valid frames they completed.
    pub fn feed(&mut self, bytes: &[u8]) -> Vec<Vec<u8>> {
        self.buf.extend_from_slice(bytes);
        let mut out = Vec::new();
        loop {
            let Some(start) = self.buf.windows(2).position(|w| w == [0xAA, 0x55]) else {
                // Keep a trailing 0xAA: it may be the start of a header.
                let keep = usize::from(self.buf.last() == Some(&0xAA));
                self.stats.garbage_bytes += (self.buf.len() - keep) as u64;
                self.buf.drain(..self.buf.len() - keep);
                return out;
            };
            self.stats.garbage_bytes += start as u64;
            self.buf.drain(..start);
            if self.buf.len() < 3 {
                return out;
            }
            let len = self.buf[2] as usize;
            if self.buf.len() < len + 4 {
                return out;
            }
            let cs = self.buf[2..len + 4].iter().fold(0u8, |a, &b| a ^ b);
            if cs != 0 {
                self.stats.bad_checksum += 1;
                self.buf.drain(..2);
                continue;
            }
            out.push(self.buf[3..3 + len].to_vec());
            self.stats.frames += 1;
            self.buf.drain(..len + 4);
        }
    }

    /// The Basic Sensor Data in a feedback payload, if any (other sub-payloads are skipped).
    pub fn core_sensors(&mut self, payload: &[u8]) -> Option<CoreSensors> {
        let mut i = 0;
        let mut found = None;
        while i + 2 <= payload.len() {
            let (id, n) = (payload[i], payload[i + 1] as usize);
            let Some(data) = payload.get(i + 2..i + 2 + n) else {
                self.stats.malformed += 1;
                return found;
            };
            if id == CORE_SENSORS {
                if n == CORE_SENSORS_LEN {
                    found = Some(CoreSensors::parse(data));
                } else {
                    self.stats.malformed += 1;
                }
            } else {
                self.stats.skipped_subpayloads += 1;
            }
            i += 2 + n;
        }
        found
    }

    /// The Base Control command in a command payload, if any (what the base side decodes).
    pub fn base_control(&mut self, payload: &[u8]) -> Option<(i16, i16)> {
        let mut i = 0;
        let mut found = None;
        while i + 2 <= payload.len() {
            let (id, n) = (payload[i], payload[i + 1] as usize);
            let Some(d) = payload.get(i + 2..i + 2 + n) else {
                self.stats.malformed += 1;
                return found;
            };
            if id == BASE_CONTROL && n == 4 {
                found = Some((i16::from_le_bytes([d[0], d[1]]), i16::from_le_bytes([d[2], d[3]])));
            } else {
                self.stats.skipped_subpayloads += 1;
            }
            i += 2 + n;
        }
        found
    }
}

/// Settings of the Kobuki driver.
#[derive(Clone, Debug)]
pub struct KobukiConfig {
    pub port: String,
    pub baud: u32,
    /// How often the current command is repeated.
    pub command_rate_hz: f64,
    /// A non-zero command not refreshed for this long is replaced by zero (the host watchdog).
    pub command_timeout: Duration,
    /// How long to wait for the first sensor frame.
    pub connect_timeout: Duration,
    /// Nothing received for this long: the link is down.
    pub silence_timeout: Duration,
    /// Status events are sent when something changes, and at least this often.
    pub status_period: Duration,
    pub backoff: Backoff,
}

impl KobukiConfig {
    pub fn new(port: impl Into<String>) -> Self {
        Self {
            port: port.into(),
            baud: 115_200,
            command_rate_hz: 25.0,
            command_timeout: Duration::from_millis(500),
            connect_timeout: Duration::from_secs(1),
            silence_timeout: Duration::from_millis(500),
            status_period: Duration::from_millis(200),
            backoff: Backoff::default(),
        }
    }
}

/// A Kobuki base: the [`MotorBase`] over its serial port. See the module docs.
pub struct KobukiBase {
    link: SerialTask<Kobuki>,
}

impl KobukiBase {
    /// Opens the port, waits for the first sensor frame and starts the background task.
    pub async fn connect(cfg: KobukiConfig) -> Result<Self, SerialBaseError> {
        let connector = SerialConnector::new(cfg.port.clone(), cfg.baud);
        Self::connect_with(cfg, connector).await
    }

    /// Like [`Self::connect`] over any [`Connector`].
    pub async fn connect_with<C: Connector>(cfg: KobukiConfig, connector: C) -> Result<Self, SerialBaseError> {
        if !(10.0..=1000.0).contains(&cfg.command_rate_hz) {
            return Err(SerialBaseError::Config(format!(
                "command_rate_hz = {} must be in 10..=1000",
                cfg.command_rate_hz
            )));
        }
        let timing = TaskTiming {
            rate_hz: cfg.command_rate_hz,
            silence_timeout: cfg.silence_timeout,
            command_timeout: Some(cfg.command_timeout),
            backoff: cfg.backoff,
        };
        let protocol = Kobuki {
            cfg,
            decoder: KobukiDecoder::new(),
            clock: ClockMapper::new(1 << 16, 1_000_000),
            left: TickUnwrapper::default(),
            right: TickUnwrapper::default(),
            last: None,
            last_status: None,
        };
        let (link, _) = SerialTask::start(protocol, timing, connector).await?;
        Ok(Self { link })
    }

    /// Sends a zero command and waits until the background task has written it and ended.
    pub async fn close(mut self) {
        self.link.close().await;
    }
}

impl MotorBase for KobukiBase {
    type Error = SerialBaseError;

    fn set_velocity(&mut self, cmd: BodyVelocity) -> Result<(), SerialBaseError> {
        self.link.command(cmd)
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

/// The Kobuki protocol as the serial task speaks it: Base Control out, Basic Sensor Data in.
struct Kobuki {
    cfg: KobukiConfig,
    decoder: KobukiDecoder,
    clock: ClockMapper,
    left: TickUnwrapper,
    right: TickUnwrapper,
    /// Previous sample (device ms, left, right ticks) for the velocity estimate.
    last: Option<(u16, i64, i64)>,
    last_status: Option<(BaseStatus, u64)>,
}

impl Kobuki {
    fn on_sensors(&mut self, cs: CoreSensors, host_ns: u64, push: &mut impl FnMut(BaseEvent)) {
        let t_ns = self.clock.map(u64::from(cs.timestamp_ms), host_ns);
        let l = self.left.update(u32::from(cs.left_encoder), 16);
        let r = self.right.update(u32::from(cs.right_encoder), 16);
        let mut velocity = BodyVelocity::ZERO;
        if let Some((t0, l0, r0)) = self.last {
            let dt = f64::from(cs.timestamp_ms.wrapping_sub(t0)) / 1000.0;
            if dt > 0.0 {
                let dl = (l - l0) as f64 / TICKS_PER_M / dt;
                let dr = (r - r0) as f64 / TICKS_PER_M / dt;
                velocity = BodyVelocity::new(0.5 * (dl + dr), (dr - dl) / WHEEL_BASE_M);
            }
        }
        if self.last.is_none_or(|(t0, ..)| t0 != cs.timestamp_ms) {
            self.last = Some((cs.timestamp_ms, l, r));
        }
        push(BaseEvent::Odometry(Odometry { t_ns, velocity, left_ticks: l, right_ticks: r }));
        let status = BaseStatus {
            t_ns: host_ns,
            battery_v: Some(f64::from(cs.battery_dv) / 10.0),
            bumper: cs.bumper != 0,
            estop: false,
            stopped_by_watchdog: false,
            motor_fault: cs.over_current != 0,
            cliff: cs.cliff != 0,
            wheel_drop: cs.wheel_drop != 0,
        };
        let due = match self.last_status {
            None => true,
            Some((prev, at)) => {
                let same = BaseStatus { t_ns: prev.t_ns, ..status } == prev;
                !same || host_ns.saturating_sub(at) >= self.cfg.status_period.as_nanos() as u64
            }
        };
        if due {
            self.last_status = Some((status, host_ns));
            push(BaseEvent::Status(status));
        }
    }
}

impl Protocol for Kobuki {
    type Command = BodyVelocity;
    type Hello = CoreSensors;
    const IDLE: BodyVelocity = BodyVelocity::ZERO;
    const NAME: &'static str = "Kobuki";

    fn is_moving(v: &BodyVelocity) -> bool {
        *v != BodyVelocity::ZERO
    }

    fn command_frame(v: &BodyVelocity, _seq: u8) -> Vec<u8> {
        let (speed, radius) = velocity_command(v.v, v.omega, WHEEL_BASE_M);
        encode_base_control(speed, radius)
    }

    fn stop_frame(_seq: u8) -> Vec<u8> {
        encode_base_control(0, 0)
    }

    fn expired_frame(_seq: u8) -> Vec<u8> {
        encode_base_control(0, 0)
    }

    async fn handshake<S: AsyncRead + AsyncWrite + Unpin + Send>(
        &mut self,
        s: &mut S,
        port: &str,
        _shared: &Shared,
    ) -> Result<CoreSensors, SerialBaseError> {
        wait_for_sensors(s, &self.cfg, port, &mut self.decoder).await
    }

    fn on_connected(&mut self, cs: &CoreSensors, reconnect: bool, port: &str, push: &mut impl FnMut(BaseEvent)) {
        if reconnect {
            self.left.rebase();
            self.right.rebase();
            self.last = None;
            self.on_sensors(*cs, monotonic_ns(), push);
            tracing::info!(port, "Kobuki base reconnected");
        } else {
            tracing::info!(port, "Kobuki base connected");
            self.on_sensors(*cs, monotonic_ns(), push);
        }
    }

    fn on_bytes(&mut self, bytes: &[u8], host_ns: u64, _port: &str, shared: &Shared, push: &mut impl FnMut(BaseEvent)) {
        for payload in self.decoder.feed(bytes) {
            if let Some(cs) = self.decoder.core_sensors(&payload) {
                self.on_sensors(cs, host_ns, push);
            }
        }
        let st = self.decoder.stats();
        shared.frames_rx.store(st.frames, Ordering::Relaxed);
        shared.dropped_rx.store(st.bad_checksum + st.malformed, Ordering::Relaxed);
    }
}

/// Reads until the first Basic Sensor Data arrives.
async fn wait_for_sensors<S: AsyncRead + Unpin>(
    s: &mut S,
    cfg: &KobukiConfig,
    port: &str,
    decoder: &mut KobukiDecoder,
) -> Result<CoreSensors, SerialBaseError> {
    let deadline = Instant::now() + cfg.connect_timeout;
    let mut buf = [0u8; 256];
    let lost = |reason: String| SerialBaseError::Disconnected { port: port.to_string(), reason };
    loop {
        match tokio::time::timeout_at(deadline, s.read(&mut buf)).await {
            Err(_) => {
                return Err(SerialBaseError::NoAnswer {
                    port: port.to_string(),
                    timeout_ms: cfg.connect_timeout.as_millis() as u64,
                    baud: cfg.baud,
                    protocol: "the Kobuki protocol (is the base switched on?)",
                });
            }
            Ok(Ok(0)) => return Err(lost("port closed".into())),
            Ok(Err(e)) => return Err(lost(format!("read failed: {e}"))),
            Ok(Ok(n)) => {
                for payload in decoder.feed(&buf[..n]) {
                    if let Some(cs) = decoder.core_sensors(&payload) {
                        return Ok(cs);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn ticks_per_metre_matches_kobuki_core() {
        // The figures usually quoted for the Kobuki: 2578.33 ticks/rev, 11724.41 ticks/m.
        assert!((TICKS_PER_REV - 2578.33).abs() < 0.005, "{TICKS_PER_REV}");
        assert!((TICKS_PER_M - 11_724.41).abs() < 0.01, "{TICKS_PER_M}");
    }

    #[test]
    fn frame_layout_and_checksum() {
        // speed 100 mm/s = 0x0064, radius 0: AA 55 06 01 04 64 00 00 00 cs; cs = 06^01^04^64 = 0x67.
        assert_eq!(encode_base_control(100, 0), vec![0xAA, 0x55, 0x06, 0x01, 0x04, 0x64, 0x00, 0x00, 0x00, 0x67]);
        let mut d = KobukiDecoder::new();
        let p = d.feed(&encode_base_control(-300, 1));
        assert_eq!(d.base_control(&p[0]), Some((-300, 1)));
    }

    #[test]
    fn velocity_commands_follow_kobuki_core() {
        let b = WHEEL_BASE_M;
        assert_eq!(velocity_command(0.3, 0.0, b), (300, 0));
        // Pure rotation: radius 1, speed = b·ω/2 in mm/s.
        assert_eq!(velocity_command(0.0, 1.0, b), (115, 1));
        assert_eq!(velocity_command(0.0, -1.0, b), (-115, 1));
        // Arc: radius 500 mm, speed = (500 + 115)·0.4 = 246 mm/s.
        assert_eq!(velocity_command(0.2, 0.4, b), (246, 500));
        // Right turn backwards: radius = -0.2/0.4 m = -500 mm... v<0, ω>0.
        assert_eq!(velocity_command(-0.2, 0.4, b), (-246, -500));
        // Round trips through the inverse within the mm quantisation.
        for (v, w) in [(0.3, 0.0), (0.0, 1.0), (0.2, 0.4), (-0.2, 0.4), (0.25, -0.8)] {
            let (s, r) = velocity_command(v, w, b);
            let back = body_velocity(s, r, b);
            assert!((back.v - v).abs() < 0.003 && (back.omega - w).abs() < 0.01, "{v} {w} -> {back:?}");
        }
    }

    #[test]
    fn sensor_data_round_trips_and_other_subpayloads_are_skipped() {
        let cs = CoreSensors {
            timestamp_ms: 65_000,
            bumper: mask::BUMPER_CENTRE,
            wheel_drop: 0,
            cliff: mask::CLIFF_LEFT,
            left_encoder: 65_535,
            right_encoder: 3,
            left_pwm: -20,
            right_pwm: 20,
            buttons: 0,
            charger: 0,
            battery_dv: 165,
            over_current: 0,
        };
        let mut payload = vec![0x04, 7, 1, 2, 3, 4, 5, 6, 7]; // an inertia sub-payload
        payload.extend(cs.to_subpayload());
        let mut bytes = vec![0x13, 0xAA, 0x00]; // garbage first
        bytes.extend(encode_frame(&payload));
        let mut d = KobukiDecoder::new();
        let frames = d.feed(&bytes);
        assert_eq!(frames.len(), 1);
        assert_eq!(d.core_sensors(&frames[0]), Some(cs));
        assert_eq!((d.stats().garbage_bytes, d.stats().skipped_subpayloads), (3, 1));
    }

    #[test]
    fn bad_checksum_resyncs_on_the_next_header() {
        let mut bad = encode_base_control(5, 0);
        *bad.last_mut().unwrap() ^= 0xFF;
        bad.extend(encode_base_control(7, 0));
        let mut d = KobukiDecoder::new();
        let frames = d.feed(&bad);
        assert_eq!(frames.len(), 1);
        assert_eq!(d.base_control(&frames[0]), Some((7, 0)));
        assert_eq!(d.stats().bad_checksum, 1);
    }

    proptest! {
        #[test]
        fn decoder_never_panics_and_recovers(garbage in proptest::collection::vec(any::<u8>(), 0..600),
                                             speed in any::<i16>(), radius in any::<i16>()) {
            let mut d = KobukiDecoder::new();
            for p in d.feed(&garbage) {
                let _ = d.core_sensors(&p);
                let _ = d.base_control(&p);
            }
            // A valid frame after garbage is found, possibly after a frame hidden in the garbage's
            // tail (a false AA 55 header with a length that swallows it) is flushed by a gap of
            // 256 zero bytes.
            let mut tail = vec![0u8; 300];
            tail.extend(encode_base_control(speed, radius));
            let got: Vec<Option<(i16, i16)>> = d.feed(&tail).iter().map(|p| d.base_control(p)).collect();
            prop_assert_eq!(got.last().copied().flatten(), Some((speed, radius)));
        }
    }
}
