//! The simulated FNP/1 base (docs/protocol.md), and the pty server that runs any simulated device.
//!
//! [`SimBase`] is the firmware, as a pure state machine in simulated time: feed it the bytes the
//! host sent ([`SimDevice::receive`]) and step it ([`SimDevice::advance`]); it answers HELLO with
//! INFO, drives a [`DiffDrive`], sends ODOM every 20 ms (50 Hz) and STATUS every 100 ms (10 Hz),
//! and stops the motors when no SETPOINT or STOP arrived for the watchdog time (default 250 ms,
//! set by HELLO), setting STATUS bit 2 until the next SETPOINT. The bumper (bit 0) is pressed
//! while the drive train touches something; [`SimBaseConfig::alarms`] raise the bumper, the
//! e-stop (bit 1) or a motor fault (bit 3) for a while, and like firmware the base cuts its
//! motors during an e-stop or a motor fault, whatever the host commands.
//!
//! [`SimServer`] puts a [`SimDevice`] on a pseudo-terminal (see [`crate::pty`]) with optional
//! [`crate::faults`] on both directions. Its clock is either
//! - [`SimClock::RealTime`]: a tokio interval advances the device by the elapsed tokio time
//!   (what `flownav sim-base` and the driver tests use), or
//! - [`SimClock::Manual`]: simulated time moves only when the owner calls
//!   [`SimServer::advance`], so a closed-loop simulation can run faster (or slower) than real time.
//!   Bytes from the host are still processed as they arrive, at the current simulated time.
//!
//! The true pose and all counters are readable at any time ([`SimServer::pose`],
//! [`SimServer::with_device`]).

use crate::faults::{AlarmKind, AlarmWindow, FaultConfig, FaultInjector, FaultStats};
use crate::kinematics::{CollisionFn, DiffDrive, DiffDriveParams, Pose};
use crate::pty::Pty;
use crate::stop_gaps::{LinkFault, StopGaps};
use hal::BodyVelocity;
use hal::fnp::{self, DecodeStats, Decoder, Direction, Packet};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::{Notify, mpsc, watch};

/// A simulated device behind a serial port: bytes in, bytes out, in simulated time.
pub trait SimDevice: Send + 'static {
    /// Handles bytes from the host at the current simulated time, appending any reply to `out`.
    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>);
    /// Advances simulated time by `dt` seconds, appending what the device sends meanwhile.
    fn advance(&mut self, dt: f64, out: &mut Vec<u8>);
    /// The true pose.
    fn pose(&self) -> Pose;
    /// The drive train (collision hook, true velocity, ticks).
    fn drive(&mut self) -> &mut DiffDrive;
    /// The link just suffered `kind` (the server calls this as it injects the fault), for
    /// devices that measure how long they run on after one ([`crate::stop_gaps`]).
    fn link_fault(&mut self, _kind: LinkFault) {}
}

/// Settings of the simulated FNP/1 base.
#[derive(Clone, Debug)]
pub struct SimBaseConfig {
    pub drive: DiffDriveParams,
    /// Name reported in INFO (ASCII, ≤ 16 bytes).
    pub name: String,
    pub odom_period_s: f64,
    pub status_period_s: f64,
    /// Watchdog before any HELLO sets it.
    pub watchdog_ms: u16,
    pub battery_mv: u16,
    /// Device clock at simulated time 0, µs (set near 2^32 to exercise the wrap).
    pub clock_start_us: u32,
    /// Longest kinematics step inside one `advance`.
    pub max_substep_s: f64,
    /// Alarms raised on schedule (bumper, estop, motor-fault; FNP/1 has no cliff or wheel-drop
    /// flag, see [`SimBaseConfig::check_alarms`]).
    pub alarms: Vec<AlarmWindow>,
}

impl SimBaseConfig {
    /// Refuses alarms FNP/1 cannot report.
    pub fn check_alarms(&self) -> Result<(), String> {
        match self.alarms.iter().find(|w| matches!(w.kind, AlarmKind::Cliff | AlarmKind::WheelDrop)) {
            Some(w) => Err(format!(
                "--alarm {}: FNP/1 STATUS has no {} flag (bumper, estop and motor-fault only; use --kobuki for cliff and wheel-drop)",
                w.kind.name(),
                w.kind.name()
            )),
            None => Ok(()),
        }
    }
}

impl Default for SimBaseConfig {
    fn default() -> Self {
        Self {
            drive: DiffDriveParams::default(),
            name: "flownav-sim".into(),
            odom_period_s: 0.02,
            status_period_s: 0.1,
            watchdog_ms: 250,
            battery_mv: 12_600,
            clock_start_us: 0,
            max_substep_s: 0.005,
            alarms: Vec::new(),
        }
    }
}

/// What the simulated base has seen and done.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SimBaseCounters {
    pub setpoints: u64,
    pub stops: u64,
    pub hellos: u64,
    pub watchdog_trips: u64,
    pub odom_sent: u64,
    pub status_sent: u64,
    pub info_sent: u64,
    /// Host frames dropped by the base's decoder, by kind, and host packets lost (seq gaps).
    pub decode: DecodeStats,
}

/// The simulated FNP/1 firmware. See the module docs.
#[derive(Debug)]
pub struct SimBase {
    cfg: SimBaseConfig,
    drive: DiffDrive,
    decoder: Decoder,
    tx_seq: u8,
    t_s: f64,
    cmd: BodyVelocity,
    watchdog_s: f64,
    last_cmd_s: f64,
    watchdog_stopped: bool,
    next_odom_s: f64,
    next_status_s: f64,
    last_host_seq: u8,
    /// Time and ticks of the previous ODOM: the velocities are derived from the tick increments.
    last_odom: Option<(f64, i64, i64)>,
    counters: SimBaseCounters,
    gaps: StopGaps,
}

impl SimBase {
    pub fn new(cfg: SimBaseConfig) -> Self {
        Self {
            drive: DiffDrive::new(cfg.drive),
            decoder: Decoder::new(Direction::HostToBase),
            tx_seq: 0,
            t_s: 0.0,
            cmd: BodyVelocity::ZERO,
            watchdog_s: f64::from(cfg.watchdog_ms) / 1000.0,
            last_cmd_s: 0.0,
            watchdog_stopped: false,
            next_odom_s: 0.0,
            next_status_s: 0.0,
            last_host_seq: 0,
            last_odom: None,
            counters: SimBaseCounters::default(),
            gaps: StopGaps::default(),
            cfg,
        }
    }

    /// Simulated time since start, s.
    pub fn time_s(&self) -> f64 {
        self.t_s
    }

    /// The velocity the host commanded (zero after STOP or a watchdog stop).
    pub fn commanded(&self) -> BodyVelocity {
        self.cmd
    }

    pub fn watchdog_ms(&self) -> f64 {
        self.watchdog_s * 1000.0
    }

    pub fn stopped_by_watchdog(&self) -> bool {
        self.watchdog_stopped
    }

    pub fn counters(&self) -> SimBaseCounters {
        SimBaseCounters { decode: self.decoder.stats(), ..self.counters }
    }

    /// How long the motors ran on a command the host may no longer mean after each link fault
    /// ([`crate::stop_gaps`]).
    pub fn stop_gaps(&self) -> &StopGaps {
        &self.gaps
    }

    fn alarm(&self, kind: AlarmKind) -> bool {
        AlarmWindow::any(&self.cfg.alarms, kind, self.t_s)
    }

    /// STATUS flags now.
    pub fn flags(&self) -> u8 {
        let mut f = 0;
        if self.drive.bumper() || self.alarm(AlarmKind::Bumper) {
            f |= fnp::flags::BUMPER;
        }
        if self.alarm(AlarmKind::Estop) {
            f |= fnp::flags::ESTOP;
        }
        if self.alarm(AlarmKind::MotorFault) {
            f |= fnp::flags::MOTOR_FAULT;
        }
        if self.watchdog_stopped {
            f |= fnp::flags::WATCHDOG_STOP;
        }
        f
    }

    pub fn set_collision(&mut self, collision: Option<CollisionFn>) {
        self.drive.set_collision(collision);
    }

    fn send(&mut self, packet: &Packet, out: &mut Vec<u8>) {
        fnp::encode_into(self.tx_seq, packet, out);
        self.tx_seq = self.tx_seq.wrapping_add(1);
    }

    fn odom(&mut self, out: &mut Vec<u8>) {
        let t_us = (self.cfg.clock_start_us as u64).wrapping_add((self.t_s * 1e6).round() as u64) as u32;
        let (l, r) = self.drive.ticks();
        // As firmware does: the velocities are the tick increments since the previous ODOM over
        // its period, with the nominal ticks/m and wheel base (the true wheels may differ).
        let vel = match self.last_odom {
            Some((t0, l0, r0)) if self.t_s > t0 => {
                let (dt, k) = (self.t_s - t0, self.cfg.drive.ticks_per_m);
                let (dl, dr) = ((l - l0) as f64 / k, (r - r0) as f64 / k);
                BodyVelocity::new(0.5 * (dl + dr) / dt, (dr - dl) / self.cfg.drive.wheel_base_m / dt)
            }
            _ => BodyVelocity::ZERO,
        };
        self.last_odom = Some((self.t_s, l, r));
        let packet = Packet::Odom {
            t_us,
            left_ticks: l as i32,
            right_ticks: r as i32,
            v_mm_s: fnp::to_i16_clamped(vel.v, 1000.0),
            omega_mrad_s: fnp::to_i16_clamped(vel.omega, 1000.0),
        };
        self.send(&packet, out);
        self.counters.odom_sent += 1;
    }

    fn status(&mut self, out: &mut Vec<u8>) {
        let packet =
            Packet::Status { battery_mv: self.cfg.battery_mv, flags: self.flags(), last_seq: self.last_host_seq };
        self.send(&packet, out);
        self.counters.status_sent += 1;
    }
}

impl SimDevice for SimBase {
    fn receive(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        let mut frames = Vec::new();
        self.decoder.feed(bytes, |f| frames.push(f));
        for f in frames {
            self.last_host_seq = f.seq;
            match f.packet {
                Packet::Setpoint { v_mm_s, omega_mrad_s } => {
                    self.counters.setpoints += 1;
                    self.cmd = BodyVelocity::new(f64::from(v_mm_s) / 1000.0, f64::from(omega_mrad_s) / 1000.0);
                    self.last_cmd_s = self.t_s;
                    self.watchdog_stopped = false;
                    self.gaps.settle(self.t_s);
                }
                Packet::Stop => {
                    self.counters.stops += 1;
                    self.cmd = BodyVelocity::ZERO;
                    self.last_cmd_s = self.t_s;
                    self.gaps.settle(self.t_s);
                }
                Packet::Hello { watchdog_ms } => {
                    self.counters.hellos += 1;
                    if watchdog_ms > 0 {
                        self.watchdog_s = f64::from(watchdog_ms) / 1000.0;
                    }
                    let info = Packet::Info {
                        version: fnp::VERSION,
                        wheel_base_mm: (self.cfg.drive.wheel_base_m * 1000.0).round() as u16,
                        ticks_per_m: self.cfg.drive.ticks_per_m.round() as u32,
                        name: self.cfg.name.chars().filter(char::is_ascii).take(fnp::MAX_NAME).collect(),
                    };
                    self.send(&info, out);
                    self.counters.info_sent += 1;
                }
                _ => {}
            }
        }
    }

    fn advance(&mut self, dt: f64, out: &mut Vec<u8>) {
        if !(dt > 0.0 && dt.is_finite()) {
            return;
        }
        let end = self.t_s + dt;
        while self.t_s < end {
            // Step to the next event (ODOM, STATUS, watchdog expiry) or the substep limit.
            let wd_at = self.last_cmd_s + self.watchdog_s;
            let mut next = (self.t_s + self.cfg.max_substep_s).min(end).min(self.next_odom_s.max(self.t_s));
            next = next.min(self.next_status_s.max(self.t_s));
            if !self.watchdog_stopped && wd_at > self.t_s {
                next = next.min(wd_at);
            }
            // An alarm window's edges are events too: the flags and the motor cut-off change there.
            for w in &self.cfg.alarms {
                for edge in [w.start.as_secs_f64(), (w.start + w.duration).as_secs_f64()] {
                    if edge > self.t_s {
                        next = next.min(edge);
                    }
                }
            }
            let h = next - self.t_s;
            if h > 0.0 {
                // E-stop and motor fault: the firmware cuts the motors.
                let cut = self.alarm(AlarmKind::Estop) || self.alarm(AlarmKind::MotorFault);
                self.drive.step(if cut { BodyVelocity::ZERO } else { self.cmd }, h);
                self.t_s = next;
            }
            if !self.watchdog_stopped && self.t_s >= wd_at - 1e-12 {
                self.watchdog_stopped = true;
                self.counters.watchdog_trips += 1;
                self.cmd = BodyVelocity::ZERO;
                self.gaps.settle(self.t_s);
            }
            if self.t_s >= self.next_odom_s - 1e-12 {
                self.odom(out);
                self.next_odom_s += self.cfg.odom_period_s;
            }
            if self.t_s >= self.next_status_s - 1e-12 {
                self.status(out);
                self.next_status_s += self.cfg.status_period_s;
            }
            if h <= 0.0 && self.t_s >= end {
                break;
            }
        }
    }

    fn pose(&self) -> Pose {
        self.drive.pose()
    }

    fn drive(&mut self) -> &mut DiffDrive {
        &mut self.drive
    }

    fn link_fault(&mut self, kind: LinkFault) {
        let stopped = self.cmd == BodyVelocity::ZERO;
        self.gaps.fault(kind, self.t_s, stopped);
    }
}

/// How a [`SimServer`]'s simulated time moves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimClock {
    /// Advanced by elapsed tokio time every `tick`.
    RealTime { tick: Duration },
    /// Advanced only by [`SimServer::advance`].
    Manual,
}

/// How to serve a device.
#[derive(Clone, Debug)]
pub struct ServeOptions {
    pub clock: SimClock,
    /// Faults on both directions (independent draws, same rates).
    pub faults: FaultConfig,
    /// A stable symlink kept pointing at the current pty (for reconnects after a disconnect).
    pub link: Option<PathBuf>,
}

impl Default for ServeOptions {
    fn default() -> Self {
        Self {
            clock: SimClock::RealTime { tick: Duration::from_millis(2) },
            faults: FaultConfig::default(),
            link: None,
        }
    }
}

enum Control {
    Write(Vec<u8>),
    Disconnect(Duration),
    Shutdown,
}

/// Faults injected so far, per direction, and pty-level counts.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LinkFaultStats {
    /// Faults on bytes the device sent.
    pub to_host: FaultStats,
    /// Faults on bytes the host sent.
    pub to_device: FaultStats,
    /// Disconnects (drawn or asked for).
    pub disconnects: u64,
    /// Bytes the device sent while nobody read the port.
    pub unread_dropped: u64,
}

/// A simulated device served on a pseudo-terminal. See the module docs.
pub struct SimServer<D: SimDevice> {
    device: Arc<Mutex<D>>,
    ctl: mpsc::UnboundedSender<Control>,
    path: watch::Receiver<(u64, PathBuf)>,
    link: Option<PathBuf>,
    manual: bool,
    stats: Arc<Mutex<LinkFaultStats>>,
    /// Woken each time the device has taken in bytes from the host ([`SimServer::received`]).
    received: Arc<Notify>,
    task: Option<tokio::task::JoinHandle<()>>,
}

impl<D: SimDevice> SimServer<D> {
    /// Opens a pty and serves `device` on it (inside a tokio runtime).
    pub fn start(device: D, opts: ServeOptions) -> std::io::Result<Self> {
        let pty = Pty::open()?;
        if let Some(link) = &opts.link {
            pty.link_at(link)?;
        }
        let device = Arc::new(Mutex::new(device));
        let (ctl, ctl_rx) = mpsc::unbounded_channel();
        let (path_tx, path) = watch::channel((0, pty.path().to_path_buf()));
        let stats = Arc::new(Mutex::new(LinkFaultStats::default()));
        let manual = opts.clock == SimClock::Manual;
        let link = opts.link.clone();
        let received = Arc::new(Notify::new());
        let task = tokio::spawn(serve(pty, device.clone(), opts, ctl_rx, path_tx, stats.clone(), received.clone()));
        Ok(Self { device, ctl, path, link, manual, stats, received, task: Some(task) })
    }

    /// The current pty slave path (`/dev/pts/N`; may change after a disconnect).
    pub fn pty_path(&self) -> PathBuf {
        self.path.borrow().1.clone()
    }

    /// How many times the pty was reopened after a disconnect.
    pub fn pty_generation(&self) -> u64 {
        self.path.borrow().0
    }

    /// What a driver should open: the stable link if there is one, else the pty path.
    pub fn port_path(&self) -> PathBuf {
        self.link.clone().unwrap_or_else(|| self.pty_path())
    }

    /// Waits until the pty has been reopened more than `generation` times; returns its path.
    pub async fn wait_reopened(&mut self, generation: u64) -> PathBuf {
        let _ = self.path.wait_for(|(g, _)| *g > generation).await;
        self.pty_path()
    }

    /// Runs `f` on the device (e.g. counters, pose, the collision hook).
    pub fn with_device<R>(&self, f: impl FnOnce(&mut D) -> R) -> R {
        f(&mut lock(&self.device))
    }

    /// Returns once the device has taken in bytes from the host since the last call returned
    /// (at once if it has already): a caller waiting for a command to arrive checks the device
    /// after each wake-up instead of polling on a timer.
    pub async fn received(&self) {
        self.received.notified().await;
    }

    /// The true pose.
    pub fn pose(&self) -> Pose {
        lock(&self.device).pose()
    }

    /// Advances simulated time by `dt` ([`SimClock::Manual`] only; ignored otherwise) and
    /// queues what the device sent meanwhile for the pty.
    pub fn advance(&self, dt: Duration) {
        if !self.manual {
            return;
        }
        let mut out = Vec::new();
        lock(&self.device).advance(dt.as_secs_f64(), &mut out);
        if !out.is_empty() {
            let _ = self.ctl.send(Control::Write(out));
        }
    }

    /// Closes the pty (the driver sees a hang-up), and opens a new one after `down_for`.
    pub fn disconnect(&self, down_for: Duration) {
        let _ = self.ctl.send(Control::Disconnect(down_for));
    }

    pub fn fault_stats(&self) -> LinkFaultStats {
        *lock(&self.stats)
    }

    /// Stops serving and closes the pty.
    pub async fn shutdown(mut self) {
        let _ = self.ctl.send(Control::Shutdown);
        if let Some(task) = self.task.take() {
            let _ = task.await;
        }
    }
}

impl<D: SimDevice> Drop for SimServer<D> {
    fn drop(&mut self) {
        if let Some(task) = self.task.take() {
            task.abort();
        }
        if let Some(link) = &self.link {
            let _ = std::fs::remove_file(link);
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Tells `device` which byte faults `apply` injected (`before` is the injector's count before).
fn note_byte_faults<D: SimDevice>(device: &Mutex<D>, before: FaultStats, after: FaultStats) {
    if after.bytes_dropped > before.bytes_dropped {
        lock(device).link_fault(LinkFault::Drop);
    }
    if after.bytes_corrupted > before.bytes_corrupted {
        lock(device).link_fault(LinkFault::Corrupt);
    }
}

async fn write_out<D: SimDevice>(pty: &mut Pty, device: &Mutex<D>, faults: &mut FaultInjector, bytes: &[u8]) {
    let before = faults.stats();
    let (bytes, delay) = if faults.is_clean() { (bytes.to_vec(), None) } else { faults.apply(bytes) };
    note_byte_faults(device, before, faults.stats());
    if let Some(d) = delay {
        tokio::time::sleep(d).await;
    }
    // The pty never blocks (unread bytes are dropped and counted), so an error means it is gone.
    let _ = pty.write_all(&bytes).await;
}

async fn serve<D: SimDevice>(
    mut pty: Pty,
    device: Arc<Mutex<D>>,
    opts: ServeOptions,
    mut ctl: mpsc::UnboundedReceiver<Control>,
    path_tx: watch::Sender<(u64, PathBuf)>,
    stats: Arc<Mutex<LinkFaultStats>>,
    received: Arc<Notify>,
) {
    let mut tx_faults = FaultInjector::new(opts.faults.clone());
    let mut rx_faults = FaultInjector::new(FaultConfig { seed: opts.faults.seed ^ 0x5EED, ..opts.faults.clone() });
    let tick_period = match opts.clock {
        SimClock::RealTime { tick } => tick,
        SimClock::Manual => Duration::from_millis(10),
    };
    let mut tick = tokio::time::interval(tick_period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut last = tokio::time::Instant::now();
    let mut buf = [0u8; 1024];
    let mut unread_before = 0;
    loop {
        let mut out = Vec::new();
        let mut down_for = None;
        tokio::select! {
            n = pty.read(&mut buf) => match n {
                Ok(n) if n > 0 => {
                    let before = rx_faults.stats();
                    let (bytes, _) = if rx_faults.is_clean() { (buf[..n].to_vec(), None) } else { rx_faults.apply(&buf[..n]) };
                    note_byte_faults(&device, before, rx_faults.stats());
                    lock(&device).receive(&bytes, &mut out);
                    received.notify_one();
                }
                // No driver has the port open (the read fails) and the master gets no event
                // when one opens it, so look again in a while: one read per 10 ms.
                _ => tokio::time::sleep(Duration::from_millis(10)).await,
            },
            _ = tick.tick() => {
                let now = tokio::time::Instant::now();
                let dt = now - last;
                last = now;
                if let SimClock::RealTime { .. } = opts.clock {
                    lock(&device).advance(dt.as_secs_f64(), &mut out);
                }
                // A drawn disconnect only hits a link a driver holds: one that hits a closed port
                // (a driver backing off between reconnects) is a fault no host can see or count.
                if pty.peer_open() && tx_faults.disconnect_now(dt) {
                    down_for = Some(opts.faults.disconnect_for);
                }
            }
            c = ctl.recv() => match c {
                Some(Control::Write(bytes)) => out = bytes,
                Some(Control::Disconnect(d)) => {
                    tx_faults.count_disconnect();
                    down_for = Some(d);
                }
                Some(Control::Shutdown) | None => return,
            }
        }
        if !out.is_empty() {
            write_out(&mut pty, &device, &mut tx_faults, &out).await;
        }
        if let Some(d) = down_for {
            unread_before += pty.unread_dropped();
            drop(pty);
            lock(&device).link_fault(LinkFault::Disconnect);
            tracing::info!("simulated link down for {} ms", d.as_millis());
            // The firmware runs on while its wire is cut (its watchdog stops the motors); what it
            // sends meanwhile goes nowhere.
            let up_at = tokio::time::Instant::now() + d;
            loop {
                let now = tokio::time::Instant::now();
                if let SimClock::RealTime { .. } = opts.clock {
                    let mut lost = Vec::new();
                    lock(&device).advance((now - last).as_secs_f64(), &mut lost);
                }
                last = now;
                if now >= up_at {
                    break;
                }
                tokio::time::sleep(tick_period.min(up_at - now)).await;
            }
            pty = loop {
                match Pty::open() {
                    Ok(p) => break p,
                    Err(e) => {
                        tracing::warn!("cannot reopen the pty: {e}");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                }
            };
            if let Some(link) = &opts.link
                && let Err(e) = pty.link_at(link)
            {
                tracing::warn!("cannot update the link {}: {e}", link.display());
            }
            path_tx.send_modify(|(g, p)| {
                *g += 1;
                *p = pty.path().to_path_buf();
            });
        }
        let mut s = lock(&stats);
        s.to_host = tx_faults.stats();
        s.to_device = rx_faults.stats();
        s.disconnects = tx_faults.stats().disconnects;
        s.unread_dropped = unread_before + pty.unread_dropped();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frames(bytes: &[u8]) -> Vec<fnp::Frame> {
        Decoder::new(Direction::BaseToHost).feed_collect(bytes)
    }

    fn quiet() -> SimBaseConfig {
        SimBaseConfig {
            drive: DiffDriveParams { error: crate::OdometryError::NONE, ..Default::default() },
            ..Default::default()
        }
    }

    #[test]
    fn hello_gets_info_and_sets_the_watchdog() {
        let mut b = SimBase::new(SimBaseConfig { name: "sim".into(), ..quiet() });
        let mut out = Vec::new();
        b.receive(&fnp::encode(1, &Packet::Hello { watchdog_ms: 400 }), &mut out);
        // The docs/protocol.md INFO vector, byte for byte (wheel base 0.330 m, 10000 ticks/m, "sim", seq 0).
        assert_eq!(
            out,
            vec![0x02, 0x83, 0x06, 0x01, 0x4a, 0x01, 0x10, 0x27, 0x01, 0x06, 0x73, 0x69, 0x6d, 0xc3, 0xf4, 0x00]
        );
        assert_eq!(b.watchdog_ms(), 400.0);
    }

    #[test]
    fn odom_at_50_hz_and_status_at_10_hz_in_simulated_time() {
        let mut b = SimBase::new(quiet());
        let mut out = Vec::new();
        for _ in 0..100 {
            b.advance(0.01, &mut out);
        }
        let f = frames(&out);
        let odoms = f.iter().filter(|f| matches!(f.packet, Packet::Odom { .. })).count();
        let status = f.iter().filter(|f| matches!(f.packet, Packet::Status { .. })).count();
        // t = 0, 0.02, ..., 1.0 and t = 0, 0.1, ..., 1.0.
        assert_eq!((odoms, status), (51, 11));
        let Packet::Odom { t_us, .. } =
            f.iter().rev().find(|f| matches!(f.packet, Packet::Odom { .. })).unwrap().packet
        else {
            unreachable!()
        };
        assert_eq!(t_us, 1_000_000);
    }

    #[test]
    fn watchdog_stops_after_exactly_its_time_and_sets_bit2() {
        let mut b = SimBase::new(quiet());
        let mut out = Vec::new();
        b.receive(&fnp::encode(0, &Packet::Hello { watchdog_ms: 250 }), &mut out);
        b.receive(&fnp::encode(1, &Packet::Setpoint { v_mm_s: 300, omega_mrad_s: 0 }), &mut out);
        b.advance(0.249, &mut out);
        assert!(!b.stopped_by_watchdog());
        assert_eq!(b.commanded(), BodyVelocity::new(0.3, 0.0));
        b.advance(0.002, &mut out);
        assert!(b.stopped_by_watchdog());
        assert_eq!(b.commanded(), BodyVelocity::ZERO);
        assert_eq!(b.counters().watchdog_trips, 1);
        out.clear();
        b.advance(0.1, &mut out);
        let last_status = frames(&out).into_iter().rev().find_map(|f| match f.packet {
            Packet::Status { flags, last_seq, .. } => Some((flags, last_seq)),
            _ => None,
        });
        assert_eq!(last_status, Some((fnp::flags::WATCHDOG_STOP, 1)));
        // The base decelerates to rest at its acceleration limit.
        b.advance(1.0, &mut out);
        assert_eq!(b.drive().velocity(), BodyVelocity::ZERO);
        // The next SETPOINT drives again and clears bit 2.
        b.receive(&fnp::encode(2, &Packet::Setpoint { v_mm_s: 100, omega_mrad_s: 0 }), &mut out);
        assert!(!b.stopped_by_watchdog());
        assert_eq!(b.flags() & fnp::flags::WATCHDOG_STOP, 0);
    }

    #[test]
    fn stop_keeps_the_watchdog_fed_without_moving() {
        let mut b = SimBase::new(quiet());
        let mut out = Vec::new();
        for i in 0..20u8 {
            b.receive(&fnp::encode(i, &Packet::Stop), &mut out);
            b.advance(0.05, &mut out);
        }
        assert!(!b.stopped_by_watchdog());
        assert_eq!(b.pose(), Pose::default());
    }

    #[test]
    fn driving_moves_the_true_pose_and_the_encoders() {
        let mut b = SimBase::new(quiet());
        let mut out = Vec::new();
        for i in 0..200u32 {
            b.receive(&fnp::encode(i as u8, &Packet::Setpoint { v_mm_s: 200, omega_mrad_s: 0 }), &mut out);
            b.advance(0.01, &mut out);
        }
        // 2 s at 0.2 m/s after a 0.2 s ramp at 1 m/s²: 0.4 - 0.02 = 0.38 m.
        assert!((b.pose().x - 0.38).abs() < 1e-6, "{:?}", b.pose());
        let last_odom = frames(&out).into_iter().rev().find_map(|f| match f.packet {
            Packet::Odom { left_ticks, v_mm_s, .. } => Some((left_ticks, v_mm_s)),
            _ => None,
        });
        let (ticks, v) = last_odom.unwrap();
        // Derived from 20 ms of ticks at 10000 ticks/m: one tick is 5 mm/s.
        assert!((v - 200).abs() <= 5, "{v}");
        assert!((ticks - 3800).abs() <= 2, "{ticks}");
    }

    #[test]
    fn collision_sets_the_bumper_flag() {
        let mut b = SimBase::new(quiet());
        b.set_collision(Some(Arc::new(|p: &Pose| p.x > 0.05)));
        let mut out = Vec::new();
        for i in 0..100u8 {
            b.receive(&fnp::encode(i, &Packet::Setpoint { v_mm_s: 300, omega_mrad_s: 0 }), &mut out);
            b.advance(0.01, &mut out);
        }
        assert_eq!(b.flags() & fnp::flags::BUMPER, fnp::flags::BUMPER);
        assert_eq!(b.drive().collisions(), 1);
        assert!(b.pose().x <= 0.05);
    }

    #[test]
    fn scheduled_alarms_set_their_flags_and_estop_cuts_the_motors() {
        // Edges off the 100 ms STATUS grid, so which STATUS carries a flag is not a rounding matter.
        let alarms = ["estop@0.25+0.4", "motor-fault@0.95+0.1", "bumper@1.45+0.1"].map(|s| s.parse().unwrap()).to_vec();
        let mut b = SimBase::new(SimBaseConfig { alarms, ..quiet() });
        assert!(b.cfg.check_alarms().is_ok());
        let mut out = Vec::new();
        let mut flags_at = Vec::new();
        for i in 0..200u32 {
            b.receive(&fnp::encode(i as u8, &Packet::Setpoint { v_mm_s: 200, omega_mrad_s: 0 }), &mut out);
            out.clear();
            b.advance(0.01, &mut out);
            for f in frames(&out) {
                if let Packet::Status { flags, .. } = f.packet {
                    flags_at.push((b.time_s(), flags));
                }
            }
            // Cut at 0.25 s, the wheels ramp down from 0.2 m/s at 1 m/s²: still by 0.45 s.
            if (0.5..0.65).contains(&b.time_s()) {
                assert_eq!(b.drive().velocity().v, 0.0, "no motion during the e-stop at {}", b.time_s());
            }
        }
        let set = |flag: u8| -> Vec<f64> {
            flags_at.iter().filter(|(_, f)| f & flag != 0).map(|(t, _)| (t * 10.0).round() / 10.0).collect()
        };
        assert_eq!(set(fnp::flags::ESTOP), vec![0.3, 0.4, 0.5, 0.6]);
        assert_eq!(set(fnp::flags::MOTOR_FAULT), vec![1.0]);
        assert_eq!(set(fnp::flags::BUMPER), vec![1.5]);
        assert!(b.drive().velocity().v > 0.19, "driving again after the alarms");
        let cliff = SimBaseConfig { alarms: vec!["cliff@0+1".parse().unwrap()], ..quiet() };
        assert!(cliff.check_alarms().unwrap_err().contains("no cliff flag"));
    }

    #[test]
    fn fault_to_stop_gaps_are_measured_on_the_simulated_clock() {
        use crate::stop_gaps::LinkFault;
        let mut b = SimBase::new(quiet());
        let mut out = Vec::new();
        let setpoint = |seq: u8| fnp::encode(seq, &Packet::Setpoint { v_mm_s: 200, omega_mrad_s: 0 });
        b.receive(&fnp::encode(0, &Packet::Hello { watchdog_ms: 150 }), &mut out);
        // Stopped: a fault costs nothing.
        b.link_fault(LinkFault::Corrupt);
        b.receive(&setpoint(1), &mut out);
        b.advance(0.040, &mut out);
        // A damaged frame at 40 ms; the next intact SETPOINT, 40 ms later, settles it.
        b.link_fault(LinkFault::Drop);
        b.advance(0.040, &mut out);
        b.receive(&setpoint(2), &mut out);
        // The link goes down 30 ms after that SETPOINT: the watchdog (150 ms) stops the motors
        // 120 ms after the fault, with a byte fault of the same moment pending too.
        b.advance(0.030, &mut out);
        b.link_fault(LinkFault::Disconnect);
        b.link_fault(LinkFault::Corrupt);
        b.advance(0.119, &mut out);
        assert_eq!(b.stop_gaps().pending(), 2, "not stopped yet");
        b.advance(0.002, &mut out);
        assert!(b.stopped_by_watchdog());
        let s = b.stop_gaps().summary();
        assert_eq!((s.drop.count, s.corrupt.count, s.disconnect.count, s.pending), (1, 2, 1, 0));
        assert!((s.drop.max_ms - 40.0).abs() < 1e-6, "{s:?}");
        assert!((s.disconnect.max_ms - 120.0).abs() < 1e-6, "{s:?}");
        assert!((s.corrupt.max_ms - 120.0).abs() < 1e-6, "{s:?}");
        assert!((s.disconnect.p99_ms - 120.0).abs() < 1e-6, "{s:?}");
    }

    #[test]
    fn clock_wraps_like_a_u32() {
        let mut b = SimBase::new(SimBaseConfig { clock_start_us: u32::MAX - 5_000, ..quiet() });
        let mut out = Vec::new();
        b.advance(0.021, &mut out);
        let ts: Vec<u32> = frames(&out)
            .into_iter()
            .filter_map(|f| match f.packet {
                Packet::Odom { t_us, .. } => Some(t_us),
                _ => None,
            })
            .collect();
        assert_eq!(ts, vec![u32::MAX - 5_000, 14_999]);
    }
}
