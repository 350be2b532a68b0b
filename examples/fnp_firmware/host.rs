//! The part that stands in for the microcontroller: a pseudo-terminal as the UART, wheels that
//! follow their speed targets at once with ideal encoders, the wall clock as the hardware timer,
//! and a superloop that polls the UART every millisecond. On a real board this file is replaced
//! by the HAL's UART, timer, PWM and encoder drivers; `firmware.rs` stays as it is.

use crate::firmware::{Board, Firmware, Params};
use nix::sys::termios::{SetArg, cfmakeraw, tcgetattr, tcsetattr};
use std::fs::File;
use std::io::{self, Read, Write};
use std::os::fd::OwnedFd;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// A raw-mode pty: the firmware reads and writes the master, the host opens the slave's path.
pub struct PtyUart {
    master: File,
    // Held open so that the master never sees a hang-up while the host closes and reopens the port.
    _slave: OwnedFd,
    path: PathBuf,
}

impl PtyUart {
    pub fn open() -> io::Result<Self> {
        let pair = nix::pty::openpty(None, None)?;
        let mut t = tcgetattr(&pair.slave)?;
        cfmakeraw(&mut t);
        tcsetattr(&pair.slave, SetArg::TCSANOW, &t)?;
        let path = nix::unistd::ttyname(&pair.slave)?;
        let flags = nix::fcntl::fcntl(&pair.master, nix::fcntl::FcntlArg::F_GETFL)?;
        let flags = nix::fcntl::OFlag::from_bits_truncate(flags) | nix::fcntl::OFlag::O_NONBLOCK;
        nix::fcntl::fcntl(&pair.master, nix::fcntl::FcntlArg::F_SETFL(flags))?;
        Ok(Self { master: File::from(pair.master), _slave: pair.slave, path })
    }

    /// The path the host opens (`/dev/pts/N`).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The bytes received so far, without waiting (0 when there are none).
    fn read(&mut self, buf: &mut [u8]) -> usize {
        self.master.read(buf).unwrap_or(0)
    }

    fn write(&mut self, bytes: &[u8]) {
        // Like a UART nobody listens to: when the host does not read, the pty's buffer fills
        // and the bytes are lost.
        let _ = self.master.write_all(bytes);
    }
}

/// The simulated drive train, shared with whoever watches it (the example's log, the tests).
#[derive(Debug)]
pub struct Motors {
    /// The wheel speed targets the firmware set, mm/s.
    pub target_mm_s: (i32, i32),
    ticks: (f64, f64),
    at: Instant,
}

impl Motors {
    pub fn new() -> Arc<Mutex<Self>> {
        Arc::new(Mutex::new(Self { target_mm_s: (0, 0), ticks: (0.0, 0.0), at: Instant::now() }))
    }

    /// Integrates the encoder counts up to now.
    fn update(&mut self, ticks_per_m: u32) {
        let now = Instant::now();
        let dt = now.duration_since(self.at).as_secs_f64();
        let ticks_per_mm = f64::from(ticks_per_m) / 1000.0;
        self.ticks.0 += f64::from(self.target_mm_s.0) * ticks_per_mm * dt;
        self.ticks.1 += f64::from(self.target_mm_s.1) * ticks_per_mm * dt;
        self.at = now;
    }
}

fn lock(m: &Mutex<Motors>) -> std::sync::MutexGuard<'_, Motors> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

struct SimBoard {
    start: Instant,
    uart: PtyUart,
    motors: Arc<Mutex<Motors>>,
    ticks_per_m: u32,
}

impl Board for SimBoard {
    fn now_us(&self) -> u32 {
        // Wraps after 71.6 minutes, like the hardware timer it stands in for.
        self.start.elapsed().as_micros() as u32
    }

    fn set_wheel_speeds(&mut self, left_mm_s: i32, right_mm_s: i32) {
        let mut m = lock(&self.motors);
        m.update(self.ticks_per_m);
        m.target_mm_s = (left_mm_s, right_mm_s);
    }

    fn encoders(&self) -> (i32, i32) {
        let mut m = lock(&self.motors);
        m.update(self.ticks_per_m);
        // Cumulative counts wrap like a hardware counter.
        (m.ticks.0.round() as i64 as i32, m.ticks.1.round() as i64 as i32)
    }

    fn battery_mv(&self) -> u16 {
        12_600
    }

    fn alarms(&self) -> u8 {
        0
    }

    fn uart_write(&mut self, bytes: &[u8]) {
        self.uart.write(bytes);
    }
}

/// The firmware's main loop on the pty, until `stop` is set.
pub fn run(params: Params, uart: PtyUart, motors: Arc<Mutex<Motors>>, stop: &AtomicBool) {
    let mut board = SimBoard { start: Instant::now(), uart, motors, ticks_per_m: params.ticks_per_m };
    let mut firmware = Firmware::new(params, &board);
    let mut rx = [0u8; 256];
    let mut was_stopped = false;
    while !stop.load(Ordering::Relaxed) {
        let n = board.uart.read(&mut rx);
        firmware.poll(&mut board, &rx[..n]);
        if firmware.stopped_by_watchdog() != was_stopped {
            was_stopped = !was_stopped;
            eprintln!("{}", if was_stopped { "watchdog: wheels stopped" } else { "watchdog: set-points again" });
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}
