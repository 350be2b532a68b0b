//! The portable part of the example firmware: an FNP/1 base's main loop over the `no_std`
//! `flownav-fnp` crate. It uses `core` and `fnp` only (no allocator, no floating point), so it
//! compiles as it is on a microcontroller; the board behind it is the [`Board`] trait.
//!
//! Each pass of the main loop ([`Firmware::poll`]):
//! 1. takes the bytes the UART received since the last pass and feeds them to the decoder, one
//!    byte at a time, acting on each complete packet: SETPOINT drives, STOP stops, HELLO sets
//!    the watchdog and is answered with INFO;
//! 2. runs the watchdog: no SETPOINT or STOP for `watchdog_ms` stops the wheels and sets STATUS
//!    bit 2 until the next SETPOINT;
//! 3. sends what is due: ODOM every 20 ms (50 Hz), STATUS every 100 ms (10 Hz), from power-up.

use fnp::{Decoder, Direction, Frame, Packet, flags};

/// ODOM period (docs/protocol.md asks for at least 50 Hz).
pub const ODOM_PERIOD_US: u32 = 20_000;
/// STATUS period (at least 5 Hz).
pub const STATUS_PERIOD_US: u32 = 100_000;
/// The watchdog until a HELLO sets it.
pub const DEFAULT_WATCHDOG_MS: u16 = 250;

/// What the firmware needs from the hardware; implement it on the target board.
pub trait Board {
    /// Microseconds since power-up, wrapping at 2^32 like a free-running hardware timer.
    fn now_us(&self) -> u32;
    /// The wheel speed targets at the rim, mm/s, + forward; the motor controller follows them.
    fn set_wheel_speeds(&mut self, left_mm_s: i32, right_mm_s: i32);
    /// Cumulative encoder counts, wrapping.
    fn encoders(&self) -> (i32, i32);
    fn battery_mv(&self) -> u16;
    /// The STATUS bits the board raises itself: [`flags::BUMPER`], [`flags::ESTOP`],
    /// [`flags::MOTOR_FAULT`].
    fn alarms(&self) -> u8;
    /// Queues bytes for the UART (a TX ring buffer drained by an interrupt or DMA).
    fn uart_write(&mut self, bytes: &[u8]);
}

/// The base's geometry and name, reported in INFO.
#[derive(Clone, Copy, Debug)]
pub struct Params {
    pub wheel_base_mm: u16,
    pub ticks_per_m: u32,
    /// ASCII, at most 16 bytes.
    pub name: &'static str,
}

/// The firmware's state; one instance, owned by the main loop.
pub struct Firmware {
    params: Params,
    decoder: Decoder,
    tx_seq: u8,
    last_host_seq: u8,
    watchdog_us: u32,
    last_cmd_us: u32,
    watchdog_stopped: bool,
    next_odom_us: u32,
    next_status_us: u32,
    /// Encoder counts and time at the last ODOM, for the measured velocity.
    last_ticks: (i32, i32),
    last_odom_us: u32,
}

/// Whether the wrapping timer `now` has reached `at` (valid for deadlines < 2^31 µs away).
fn reached(now: u32, at: u32) -> bool {
    now.wrapping_sub(at) as i32 >= 0
}

fn saturate_i16(x: i64) -> i16 {
    x.clamp(i64::from(i16::MIN), i64::from(i16::MAX)) as i16
}

impl Firmware {
    /// The state at power-up: wheels stopped, ODOM and STATUS due at once.
    pub fn new(params: Params, board: &impl Board) -> Self {
        let now = board.now_us();
        Self {
            params,
            decoder: Decoder::new(Direction::HostToBase),
            tx_seq: 0,
            last_host_seq: 0,
            watchdog_us: u32::from(DEFAULT_WATCHDOG_MS) * 1000,
            last_cmd_us: now,
            watchdog_stopped: false,
            next_odom_us: now,
            next_status_us: now,
            last_ticks: board.encoders(),
            last_odom_us: now,
        }
    }

    /// One pass of the main loop, with the bytes received since the last pass.
    pub fn poll(&mut self, board: &mut impl Board, rx: &[u8]) {
        for &byte in rx {
            if let Some(frame) = self.decoder.push(byte) {
                self.handle(board, frame);
            }
        }
        let now = board.now_us();
        if !self.watchdog_stopped && reached(now, self.last_cmd_us.wrapping_add(self.watchdog_us)) {
            self.watchdog_stopped = true;
            self.drive(board, 0, 0);
        }
        if reached(now, self.next_odom_us) {
            self.send_odom(board, now);
            self.next_odom_us = next_deadline(self.next_odom_us, ODOM_PERIOD_US, now);
        }
        if reached(now, self.next_status_us) {
            self.send_status(board);
            self.next_status_us = next_deadline(self.next_status_us, STATUS_PERIOD_US, now);
        }
    }

    /// Whether the watchdog has stopped the wheels (STATUS bit 2).
    pub fn stopped_by_watchdog(&self) -> bool {
        self.watchdog_stopped
    }

    fn handle(&mut self, board: &mut impl Board, frame: Frame) {
        self.last_host_seq = frame.seq;
        let now = board.now_us();
        match frame.packet {
            Packet::Setpoint { v_mm_s, omega_mrad_s } => {
                self.last_cmd_us = now;
                self.watchdog_stopped = false;
                self.drive(board, v_mm_s, omega_mrad_s);
            }
            Packet::Stop => {
                self.last_cmd_us = now;
                self.drive(board, 0, 0);
            }
            Packet::Hello { watchdog_ms } => {
                // 0 keeps the current watchdog: a base never runs without one.
                if watchdog_ms > 0 {
                    self.watchdog_us = u32::from(watchdog_ms) * 1000;
                }
                let info = Packet::Info {
                    version: fnp::VERSION,
                    wheel_base_mm: self.params.wheel_base_mm,
                    ticks_per_m: self.params.ticks_per_m,
                    name: fnp::ascii_name(self.params.name),
                };
                self.send(board, &info);
            }
            // The decoder listens to host packets only; base packets never get here.
            Packet::Odom { .. } | Packet::Status { .. } | Packet::Info { .. } => {}
        }
    }

    /// Body velocity → wheel rim speeds (differential drive, REP-103: + omega turns left).
    fn drive(&mut self, board: &mut impl Board, v_mm_s: i16, omega_mrad_s: i16) {
        let half_track = i32::from(omega_mrad_s) * i32::from(self.params.wheel_base_mm) / 2000;
        board.set_wheel_speeds(i32::from(v_mm_s) - half_track, i32::from(v_mm_s) + half_track);
    }

    fn send(&mut self, board: &mut impl Board, packet: &Packet) {
        board.uart_write(&fnp::encode(self.tx_seq, packet));
        self.tx_seq = self.tx_seq.wrapping_add(1);
    }

    /// ODOM with the velocity measured from the encoder counts since the last ODOM.
    fn send_odom(&mut self, board: &mut impl Board, now: u32) {
        let (left, right) = board.encoders();
        let dl = i64::from(left.wrapping_sub(self.last_ticks.0));
        let dr = i64::from(right.wrapping_sub(self.last_ticks.1));
        let dt_us = i64::from(now.wrapping_sub(self.last_odom_us));
        let tpm = i64::from(self.params.ticks_per_m.max(1));
        let (v_mm_s, omega_mrad_s) = if dt_us > 0 {
            // v = (dl + dr) / 2 / tpm / dt; omega = (dr - dl) / tpm / wheel_base / dt.
            let v = (dl + dr) * 500_000_000 / (tpm * dt_us);
            let omega = (dr - dl) * 1_000_000_000_000 / (tpm * i64::from(self.params.wheel_base_mm.max(1)) * dt_us);
            (saturate_i16(v), saturate_i16(omega))
        } else {
            (0, 0)
        };
        self.last_ticks = (left, right);
        self.last_odom_us = now;
        let odom = Packet::Odom { t_us: now, left_ticks: left, right_ticks: right, v_mm_s, omega_mrad_s };
        self.send(board, &odom);
    }

    fn send_status(&mut self, board: &mut impl Board) {
        let mut status_flags = board.alarms() & (flags::BUMPER | flags::ESTOP | flags::MOTOR_FAULT);
        if self.watchdog_stopped {
            status_flags |= flags::WATCHDOG_STOP;
        }
        let status =
            Packet::Status { battery_mv: board.battery_mv(), flags: status_flags, last_seq: self.last_host_seq };
        self.send(board, &status);
    }
}

/// The next periodic deadline; a loop that fell more than a period behind skips the missed ones
/// instead of sending a burst.
fn next_deadline(at: u32, period: u32, now: u32) -> u32 {
    let next = at.wrapping_add(period);
    if reached(now, next) { now.wrapping_add(period) } else { next }
}
