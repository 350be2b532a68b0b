//! The example firmware (examples/fnp_firmware) against the real host driver over a pty:
//! HELLO/INFO, set-points in, ODOM and STATUS out, STOP on close, and the firmware's watchdog
//! stopping the wheels when the host goes silent.
//!
//! Timing: nothing here asserts how fast anything happens; each wait is "until it happens",
//! bounded by a 10 s deadline that only a hung firmware or driver reaches.

#[allow(dead_code)]
#[path = "../examples/fnp_firmware/firmware.rs"]
mod firmware;
#[allow(dead_code)]
#[path = "../examples/fnp_firmware/host.rs"]
mod host;

use fnp::{Decoder, Direction, Packet, flags};
use hal::fnp_driver::{FnpBase, FnpConfig};
use hal::{BaseEvent, BodyVelocity, MotorBase};
use std::io::{Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const PARAMS: firmware::Params = firmware::Params { wheel_base_mm: 330, ticks_per_m: 10_000, name: "fw-test" };
const DEADLINE: Duration = Duration::from_secs(10);

struct Running {
    path: String,
    motors: Arc<Mutex<host::Motors>>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Running {
    fn start() -> Self {
        let uart = host::PtyUart::open().expect("a pseudo-terminal");
        let path = uart.path().to_string_lossy().into_owned();
        let motors = host::Motors::new();
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let (motors, stop) = (motors.clone(), stop.clone());
            std::thread::spawn(move || host::run(PARAMS, uart, motors, &stop))
        };
        Self { path, motors, stop, thread: Some(thread) }
    }

    fn wheels(&self) -> (i32, i32) {
        self.motors.lock().unwrap().target_mm_s
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[test]
fn host_driver_drives_the_example_firmware() {
    let fw = Running::start();
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        let mut base = FnpBase::connect(FnpConfig::new(fw.path.clone())).await.expect("HELLO/INFO handshake");
        let info = base.info().clone();
        assert_eq!(
            (info.version, info.wheel_base_m, info.ticks_per_m, info.name.as_str()),
            (1, 0.33, 10_000, "fw-test")
        );

        // Set-point in: the wheels get v ∓ ω·b/2 = 300 ∓ 200·330/2000 = 300 ∓ 33 mm/s.
        base.set_velocity(BodyVelocity::new(0.3, 0.2)).unwrap();
        let t0 = Instant::now();
        let (mut moving, mut statuses) = (Vec::new(), 0);
        while t0.elapsed() < DEADLINE && (moving.len() < 10 || statuses < 3) {
            match base.next_event(Duration::from_millis(100)).await {
                Ok(Some(BaseEvent::Odometry(o))) if o.velocity.v > 0.2 => moving.push(o),
                Ok(Some(BaseEvent::Status(s))) if !moving.is_empty() => {
                    assert!(!s.stopped_by_watchdog, "the watchdog tripped while the host refreshed the set-point");
                    assert_eq!(s.battery_v, Some(12.6));
                    statuses += 1;
                }
                Ok(_) => {}
                Err(e) => panic!("link error: {e}"),
            }
        }
        assert_eq!(fw.wheels(), (267, 333));
        // ODOM out: the velocity measured from the encoders over each 20 ms (wheels at 267 and
        // 333 mm/s: 300 mm/s and (333 − 267)/0.33 = 200 mrad/s). The median, because a loop
        // preempted between reading the timer and the encoders measures one period wrong.
        assert!(moving.len() >= 10, "{} ODOMs with the wheels turning", moving.len());
        let median = |f: fn(&hal::Odometry) -> f64| {
            let mut x: Vec<f64> = moving.iter().map(f).collect();
            x.sort_by(f64::total_cmp);
            x[x.len() / 2]
        };
        let (v, omega) = (median(|o| o.velocity.v), median(|o| o.velocity.omega));
        assert!((v - 0.3).abs() <= 0.01, "v = {v}");
        assert!((omega - 0.2).abs() <= 0.02, "omega = {omega}");
        let last = moving.last().unwrap();
        assert!(last.left_ticks > 0 && last.right_ticks > last.left_ticks, "{last:?}");

        // STOP on close stops the wheels.
        base.close().await;
        let t0 = Instant::now();
        while fw.wheels() != (0, 0) && t0.elapsed() < DEADLINE {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        assert_eq!(fw.wheels(), (0, 0));
    });
}

#[test]
fn watchdog_stops_the_wheels_when_the_host_goes_silent() {
    let fw = Running::start();
    // A host that says HELLO (100 ms watchdog), sends one SETPOINT, then nothing.
    let mut port = std::fs::OpenOptions::new().read(true).write(true).open(&fw.path).unwrap();
    port.write_all(&fnp::encode(0, &Packet::Hello { watchdog_ms: 100 })).unwrap();
    port.write_all(&fnp::encode(1, &Packet::Setpoint { v_mm_s: 200, omega_mrad_s: 0 })).unwrap();

    // Read until a STATUS says "stopped by the watchdog", seeing INFO and a moving ODOM first.
    let (reader_tx, frames) = std::sync::mpsc::channel();
    let mut reader = port.try_clone().unwrap();
    std::thread::spawn(move || {
        let mut dec = Decoder::new(Direction::BaseToHost);
        let mut buf = [0u8; 256];
        while let Ok(n) = reader.read(&mut buf) {
            if n == 0 {
                return;
            }
            for &b in &buf[..n] {
                if let Some(f) = dec.push(b)
                    && reader_tx.send(f.packet).is_err()
                {
                    return;
                }
            }
        }
    });
    let (mut info, mut moved, mut tripped) = (false, false, None);
    let t0 = Instant::now();
    while tripped.is_none() && t0.elapsed() < DEADLINE {
        match frames.recv_timeout(Duration::from_millis(100)) {
            Ok(Packet::Info { .. }) => info = true,
            Ok(Packet::Odom { v_mm_s: 150..=250, .. }) => moved = true,
            Ok(Packet::Status { flags: f, last_seq, .. }) if f & flags::WATCHDOG_STOP != 0 && moved => {
                tripped = Some(last_seq)
            }
            _ => {}
        }
    }
    assert!(info, "no INFO after HELLO");
    assert!(moved, "no ODOM at about 200 mm/s after the SETPOINT");
    assert_eq!(tripped, Some(1), "no STATUS with the watchdog bit after the host went silent");
    assert_eq!(fw.wheels(), (0, 0));
    // ODOM after the trip reports the wheels standing.
    let t0 = Instant::now();
    let mut standing = false;
    while !standing && t0.elapsed() < DEADLINE {
        standing = matches!(
            frames.recv_timeout(Duration::from_millis(100)),
            Ok(Packet::Odom { v_mm_s: 0, omega_mrad_s: 0, .. })
        );
    }
    assert!(standing);
    // SETPOINTs again (every 20 ms, as a host does) drive again and clear the bit.
    let t0 = Instant::now();
    let (mut seq, mut cleared) = (2u8, false);
    while !cleared && t0.elapsed() < DEADLINE {
        port.write_all(&fnp::encode(seq, &Packet::Setpoint { v_mm_s: 100, omega_mrad_s: 0 })).unwrap();
        seq = seq.wrapping_add(1);
        let until = Instant::now() + Duration::from_millis(20);
        while let Some(left) = until.checked_duration_since(Instant::now()) {
            if let Ok(Packet::Status { flags: f, last_seq, .. }) = frames.recv_timeout(left) {
                cleared |= last_seq >= 2 && f & flags::WATCHDOG_STOP == 0;
            }
        }
    }
    assert!(cleared, "the watchdog bit stayed set after new SETPOINTs");
}
