//! The serial drivers against the simulated bases, over real pseudo-terminals.
//!
//! Time limits here only guard against hangs; no test asserts how fast anything is.

use hal::fnp::{self, Decoder, Direction, Packet};
use hal::fnp_driver::{FnpBase, FnpConfig, SerialBaseError};
use hal::{BaseEvent, BodyVelocity, Error, ErrorKind, MotorBase};
use mocks::faults::FaultConfig;
use mocks::sim_base::{ServeOptions, SimBase, SimBaseConfig, SimClock, SimServer};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::time::timeout;
use tokio_serial::SerialPortBuilderExt;

const GUARD: Duration = Duration::from_secs(10);

fn hex(s: &str) -> Vec<u8> {
    s.split_whitespace().map(|h| u8::from_str_radix(h, 16).unwrap()).collect()
}

fn sim(clock: SimClock) -> SimServer<SimBase> {
    let cfg = SimBaseConfig { name: "sim".into(), ..Default::default() };
    SimServer::start(SimBase::new(cfg), ServeOptions { clock, ..Default::default() }).unwrap()
}

fn real_time() -> SimClock {
    SimClock::RealTime { tick: Duration::from_millis(2) }
}

fn raw_port(path: &std::path::Path) -> tokio_serial::SerialStream {
    tokio_serial::new(path.to_string_lossy(), 115_200).open_native_async().unwrap()
}

/// Reads frames from a raw port until `pred` accepts one.
async fn read_until(
    port: &mut tokio_serial::SerialStream,
    dec: &mut Decoder,
    mut pred: impl FnMut(&fnp::Frame) -> bool,
) -> fnp::Frame {
    let mut buf = [0u8; 256];
    loop {
        let n = AsyncReadExt::read(port, &mut buf).await.unwrap();
        for f in dec.feed_collect(&buf[..n]) {
            if pred(&f) {
                return f;
            }
        }
    }
}

/// Polls the driver until it reports an error (the link lost).
async fn first_error(base: &mut FnpBase) -> SerialBaseError {
    loop {
        if let Err(e) = base.next_event(Duration::from_secs(1)).await {
            return e;
        }
    }
}

/// Polls the driver until its link is up again.
async fn until_connected(base: &mut FnpBase) {
    while !base.link_stats().connected {
        let _ = base.next_event(Duration::from_millis(50)).await;
    }
}

#[tokio::test]
async fn protocol_vectors_against_the_simulated_base() {
    let server = sim(SimClock::Manual);
    let mut port = raw_port(&server.pty_path());
    // HELLO (seq 1, 250 ms) is answered by the INFO vector, byte for byte.
    port.write_all(&hex("04 03 01 fa 03 26 d4 00")).await.unwrap();
    let want = hex("02 83 06 01 4a 01 10 27 01 06 73 69 6d c3 f4 00");
    let mut got = vec![0u8; want.len()];
    timeout(GUARD, port.read_exact(&mut got)).await.unwrap().unwrap();
    assert_eq!(got, want);
    // SETPOINT vector (seq 7): the base drives at 0.300 m/s, -0.150 rad/s; seqs 2..6 were lost.
    port.write_all(&hex("09 01 07 2c 01 6a ff 39 99 00")).await.unwrap();
    timeout(GUARD, async {
        while server.with_device(|b| b.counters().setpoints) < 1 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .unwrap();
    server.with_device(|b| {
        assert_eq!(b.commanded(), BodyVelocity::new(0.3, -0.15));
        assert_eq!(b.counters().decode.lost, 5);
    });
    // 100 ms of simulated time: the base moves and reports it.
    server.advance(Duration::from_millis(100));
    let mut dec = Decoder::new(Direction::BaseToHost);
    let odom =
        timeout(GUARD, read_until(&mut port, &mut dec, |f| matches!(f.packet, Packet::Odom { t_us: 100_000, .. })))
            .await
            .unwrap();
    let Packet::Odom { v_mm_s, omega_mrad_s, left_ticks, right_ticks, .. } = odom.packet else { unreachable!() };
    // Derived from the ticks of the last 20 ms, as firmware does: ramping at 1 m/s² the mean
    // speed over 80..100 ms is 0.09 m/s; the turn (limited by 4 rad/s²) is at -0.15 rad/s since
    // 37.5 ms. One tick is 5 mm/s of speed and 15 mrad/s of turn over 20 ms (10,000 ticks/m).
    assert!((v_mm_s - 90).abs() <= 6, "ramping at 1 m/s²: {v_mm_s} mm/s");
    assert!((omega_mrad_s + 150).abs() <= 16, "limited by 4 rad/s²: {omega_mrad_s} mrad/s");
    assert!(right_ticks < left_ticks, "turning right: {left_ticks} {right_ticks}");
    // STOP vector (seq 8).
    port.write_all(&hex("05 02 08 65 fa 00")).await.unwrap();
    timeout(GUARD, async {
        while server.with_device(|b| b.counters().stops) < 1 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .unwrap();
    assert_eq!(server.with_device(|b| b.commanded()), BodyVelocity::ZERO);
    assert!(server.pose().x > 0.0 && server.pose().theta < 0.0, "{:?}", server.pose());
}

#[tokio::test]
async fn watchdog_stops_a_silent_host_and_the_next_setpoint_resumes() {
    let server = sim(real_time());
    let mut port = raw_port(&server.pty_path());
    port.write_all(&fnp::encode(0, &Packet::Hello { watchdog_ms: 250 })).await.unwrap();
    port.write_all(&fnp::encode(1, &Packet::Setpoint { v_mm_s: 200, omega_mrad_s: 0 })).await.unwrap();
    let mut dec = Decoder::new(Direction::BaseToHost);
    // Silence: the base stops itself and says so in STATUS bit 2.
    let status = timeout(
        GUARD,
        read_until(
            &mut port,
            &mut dec,
            |f| matches!(f.packet, Packet::Status { flags, .. } if flags & fnp::flags::WATCHDOG_STOP != 0),
        ),
    )
    .await
    .unwrap();
    assert!(matches!(status.packet, Packet::Status { last_seq: 1, .. }));
    server.with_device(|b| {
        assert_eq!(b.counters().watchdog_trips, 1);
        assert_eq!(b.commanded(), BodyVelocity::ZERO);
    });
    port.write_all(&fnp::encode(2, &Packet::Setpoint { v_mm_s: 200, omega_mrad_s: 0 })).await.unwrap();
    timeout(
        GUARD,
        read_until(
            &mut port,
            &mut dec,
            |f| matches!(f.packet, Packet::Status { flags, last_seq: 2, .. } if flags & fnp::flags::WATCHDOG_STOP == 0),
        ),
    )
    .await
    .unwrap();
}

#[tokio::test]
async fn driver_handshakes_drives_and_stops_on_drop() {
    let server = sim(real_time());
    let cfg = FnpConfig::new(server.pty_path().to_string_lossy());
    let mut base = timeout(GUARD, FnpBase::connect(cfg)).await.unwrap().unwrap();
    assert_eq!((base.info().name.as_str(), base.info().wheel_base_m, base.info().ticks_per_m), ("sim", 0.33, 10_000));
    base.set_velocity(BodyVelocity::new(0.2, 0.0)).unwrap();
    let odom = timeout(GUARD, async {
        loop {
            base.set_velocity(BodyVelocity::new(0.2, 0.0)).unwrap();
            if let Some(BaseEvent::Odometry(o)) = base.next_event(Duration::from_secs(1)).await.unwrap()
                && o.velocity.v >= 0.2
            {
                return o;
            }
        }
    })
    .await
    .unwrap();
    assert!(odom.left_ticks > 0 && odom.t_ns <= hal::camera::monotonic_ns());
    let stats = base.link_stats();
    assert!(stats.connected && stats.frames_rx > 0 && stats.dropped_rx == 0, "{stats:?}");
    let stops_before = server.with_device(|b| b.counters().stops);
    drop(base);
    timeout(GUARD, async {
        while server.with_device(|b| b.counters().stops) == stops_before {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    })
    .await
    .unwrap();
    assert_eq!(server.with_device(|b| b.commanded()), BodyVelocity::ZERO);
}

#[tokio::test]
async fn driver_reconnects_after_the_port_vanishes() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyBASE");
    let opts = ServeOptions { link: Some(link.clone()), ..Default::default() };
    let mut server = SimServer::start(SimBase::new(SimBaseConfig::default()), opts).unwrap();
    let mut base = timeout(GUARD, FnpBase::connect(FnpConfig::new(link.to_string_lossy()))).await.unwrap().unwrap();
    server.disconnect(Duration::from_millis(300));
    let err = timeout(GUARD, first_error(&mut base)).await.unwrap();
    assert_eq!(err.kind(), ErrorKind::Disconnected);
    assert!(base.set_velocity(BodyVelocity::new(0.1, 0.0)).is_err(), "commands are refused while the link is down");
    timeout(GUARD, server.wait_reopened(0)).await.unwrap();
    timeout(GUARD, until_connected(&mut base)).await.unwrap();
    let stats = base.link_stats();
    assert_eq!((stats.disconnects, stats.reconnects), (1, 1));
    // Closing the pty hangs the port up: a loss the OS reported, whatever the silence timer did.
    assert_eq!((stats.disconnects_os, stats.disconnects_silence, stats.hangups_reconnecting), (1, 0, 0), "{stats:?}");
    assert_eq!(server.with_device(|b| b.counters().hellos), 2, "the handshake was repeated on the new pty");
    base.set_velocity(BodyVelocity::new(0.1, 0.0)).unwrap();
    assert!(matches!(base.next_event(GUARD).await, Ok(Some(_))));
}

#[tokio::test]
async fn a_silent_base_is_a_loss_declared_by_the_silence_timeout() {
    // A manual clock: the base answers HELLO but sends nothing on its own, and its pty stays.
    let server = sim(SimClock::Manual);
    let mut cfg = FnpConfig::new(server.pty_path().to_string_lossy());
    cfg.silence_timeout = Duration::from_millis(100);
    let mut base = timeout(GUARD, FnpBase::connect(cfg)).await.unwrap().unwrap();
    let err = timeout(GUARD, first_error(&mut base)).await.unwrap();
    assert!(err.to_string().contains("nothing received for 100 ms"), "{err}");
    let stats = base.link_stats();
    // The port is still there, so every loss (the driver may have reconnected and gone silent
    // again meanwhile) is the timer's.
    assert!(stats.disconnects >= 1, "{stats:?}");
    assert_eq!(
        (stats.disconnects_silence, stats.disconnects_os, stats.hangups_reconnecting),
        (stats.disconnects, 0, 0)
    );
}

/// Plays the base on `pty`: reads until HELLO arrives, then answers INFO unless `answer` is false.
async fn await_hello(pty: &mut mocks::pty::Pty, answer: bool) {
    let mut dec = Decoder::new(Direction::HostToBase);
    let mut buf = [0u8; 256];
    loop {
        // The master's reads fail until the driver has opened the port.
        let Ok(n) = AsyncReadExt::read(pty, &mut buf).await else {
            tokio::time::sleep(Duration::from_millis(5)).await;
            continue;
        };
        if dec.feed_collect(&buf[..n]).iter().any(|f| matches!(f.packet, Packet::Hello { .. })) {
            break;
        }
    }
    if answer {
        let info = Packet::Info { version: 1, wheel_base_mm: 330, ticks_per_m: 10_000, name: fnp::ascii_name("pty") };
        pty.write_all(&fnp::encode(0, &info)).await.unwrap();
    }
}

#[tokio::test]
async fn a_hang_up_during_a_reconnect_is_counted_apart() {
    use mocks::pty::Pty;
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyBASE");
    let mut first = Pty::open().unwrap();
    first.link_at(&link).unwrap();
    let connect = tokio::spawn(FnpBase::connect(FnpConfig::new(link.to_string_lossy())));
    timeout(GUARD, await_hello(&mut first, true)).await.unwrap();
    let mut base = timeout(GUARD, connect).await.unwrap().unwrap().unwrap();
    // The port goes away with the link up; the next one hangs up in the middle of the handshake;
    // the third answers.
    let mut second = Pty::open().unwrap();
    second.link_at(&link).unwrap();
    drop(first);
    timeout(GUARD, await_hello(&mut second, false)).await.unwrap();
    let mut third = Pty::open().unwrap();
    third.link_at(&link).unwrap();
    drop(second);
    timeout(GUARD, await_hello(&mut third, true)).await.unwrap();
    timeout(GUARD, until_connected(&mut base)).await.unwrap();
    let stats = base.link_stats();
    assert_eq!((stats.disconnects, stats.reconnects), (1, 1), "{stats:?}");
    assert_eq!((stats.disconnects_os, stats.disconnects_silence, stats.hangups_reconnecting), (1, 0, 1), "{stats:?}");
}

#[tokio::test]
async fn garbled_bytes_are_survived_and_counted() {
    let faults: FaultConfig = "drop=0.002,corrupt=0.002,delay=0.01:5ms,seed=11".parse().unwrap();
    let opts = ServeOptions { faults, ..Default::default() };
    let server = SimServer::start(SimBase::new(SimBaseConfig::default()), opts).unwrap();
    let mut cfg = FnpConfig::new(server.pty_path().to_string_lossy());
    cfg.handshake_timeout = Duration::from_secs(2);
    let mut base = timeout(GUARD, FnpBase::connect(cfg)).await.unwrap().unwrap();
    let mut odoms = 0;
    timeout(GUARD * 3, async {
        while base.decode_stats().dropped() + base.decode_stats().lost < 3 || odoms < 200 {
            base.set_velocity(BodyVelocity::new(0.1, 0.1)).unwrap();
            if let Ok(Some(BaseEvent::Odometry(_))) = base.next_event(Duration::from_secs(1)).await {
                odoms += 1;
            }
        }
    })
    .await
    .unwrap();
    let st = base.decode_stats();
    let injected = server.fault_stats();
    assert!(injected.to_host.bytes_dropped + injected.to_host.bytes_corrupted > 0, "{injected:?}");
    assert!(st.bad_crc + st.bad_cobs + st.bad_length + st.unknown_type + st.lost > 0, "{st:?}");
    assert!(base.link_stats().connected);
    // The base's side survived the host's garbled bytes too, and kept obeying set-points.
    assert!(server.with_device(|b| b.counters().setpoints) > 0);
}

mod kobuki {
    use super::*;
    use hal::kobuki::{KobukiBase, KobukiConfig};
    use mocks::sim_kobuki::{SimKobuki, SimKobukiConfig};

    fn kobuki_sim() -> SimServer<SimKobuki> {
        let cfg = SimKobukiConfig { clock_start_ms: 65_000, encoder_start: 65_400, ..Default::default() };
        SimServer::start(SimKobuki::new(cfg), ServeOptions::default()).unwrap()
    }

    async fn wait_until(server: &SimServer<SimKobuki>, mut pred: impl FnMut(&mut SimKobuki) -> bool) {
        timeout(GUARD, async {
            while !server.with_device(&mut pred) {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
        .await
        .unwrap();
    }

    #[tokio::test]
    async fn kobuki_driver_drives_measures_and_its_host_watchdog_stops_the_base() {
        let server = kobuki_sim();
        let mut base = timeout(GUARD, KobukiBase::connect(KobukiConfig::new(server.pty_path().to_string_lossy())))
            .await
            .unwrap()
            .unwrap();
        // An arc: the sim decodes (speed, radius) back to the same body velocity.
        base.set_velocity(BodyVelocity::new(0.2, 0.4)).unwrap();
        wait_until(&server, |k| k.last_command == Some((246, 500))).await;
        let cmd = server.with_device(|k| k.commanded());
        assert!((cmd.v - 0.2).abs() < 1e-3 && (cmd.omega - 0.4).abs() < 2e-3, "{cmd:?}");
        // Odometry from 16-bit wrapping encoders and timestamps converges to the command.
        let odom = timeout(GUARD, async {
            loop {
                base.set_velocity(BodyVelocity::new(0.2, 0.4)).unwrap();
                if let Some(BaseEvent::Odometry(o)) = base.next_event(Duration::from_secs(1)).await.unwrap()
                    && (o.velocity.v - 0.2).abs() < 0.02
                    && (o.velocity.omega - 0.4).abs() < 0.1
                    && o.right_ticks > 1000
                {
                    return o;
                }
            }
        })
        .await
        .unwrap();
        assert!(odom.right_ticks > odom.left_ticks && odom.left_ticks > 0, "{odom:?}");
        // Silence from the caller: the driver zeroes the command (the firmware would not).
        wait_until(&server, |k| k.last_command == Some((0, 0))).await;
        assert_eq!(base.link_stats().command_timeouts, 1);
        // Cliff sensor → status event; dropping the driver sends zero.
        server.with_device(|k| k.cliff = hal::kobuki::mask::CLIFF_LEFT);
        let status = timeout(GUARD, async {
            loop {
                if let Some(BaseEvent::Status(s)) = base.next_event(Duration::from_secs(1)).await.unwrap()
                    && s.cliff
                {
                    return s;
                }
            }
        })
        .await
        .unwrap();
        assert_eq!(status.battery_v, Some(16.5));
        base.set_velocity(BodyVelocity::new(0.1, 0.0)).unwrap();
        wait_until(&server, |k| k.last_command == Some((100, 0))).await;
        drop(base);
        wait_until(&server, |k| k.last_command == Some((0, 0))).await;
    }

    #[tokio::test]
    async fn kobuki_silent_port_is_a_clear_error() {
        let pty = mocks::pty::Pty::open().unwrap();
        let err = KobukiBase::connect(KobukiConfig::new(pty.path().to_string_lossy())).await.err().unwrap();
        assert_eq!(err.kind(), ErrorKind::Timeout);
        assert!(err.to_string().contains("Kobuki protocol"), "{err}");
    }
}
