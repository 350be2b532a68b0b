//! The simulated Kobuki (TurtleBot 2) base: Base Control in, Basic Sensor Data out at 50 Hz,
//! over the same [`SimServer`](crate::sim_base::SimServer) as the FNP/1 base.
//!
//! Like the real firmware it has no command watchdog: it drives at the last Base Control command
//! until told otherwise, which is what the host-side watchdog of `hal::kobuki` is tested against.
//! Its drive train uses the Kobuki's geometry (wheel base 0.230 m, 11724.41 ticks/m); encoders
//! and the millisecond timestamp are 16-bit and wrap as on the robot. Cliff and wheel-drop
//! sensors can be set by a test or raised on schedule ([`SimKobukiConfig::alarms`]: bumper,
//! cliff, wheel-drop, motor-fault as over-current; the Kobuki has no e-stop); the bumper also
//! comes from the collision hook.

use crate::faults::{AlarmKind, AlarmWindow};
use crate::kinematics::{DiffDrive, DiffDriveParams, DriveLimits, Pose};
use crate::odometry_error::OdometryError;
use crate::sim_base::SimDevice;
use hal::BodyVelocity;
use hal::kobuki::{self, CoreSensors, KobukiDecoder, KobukiStats};

/// Settings of the simulated Kobuki.
#[derive(Clone, Debug)]
pub struct SimKobukiConfig {
    pub drive: DiffDriveParams,
    pub feedback_period_s: f64,
    /// Battery voltage, 0.1 V.
    pub battery_dv: u8,
    /// Timestamp (ms) at simulated time 0.
    pub clock_start_ms: u16,
    /// Encoder counts at start (set near 65535 to exercise the wrap).
    pub encoder_start: u16,
    /// Alarms raised on schedule; see [`SimKobukiConfig::check_alarms`].
    pub alarms: Vec<AlarmWindow>,
}

impl SimKobukiConfig {
    /// Refuses the alarm the Kobuki cannot report (it has no e-stop).
    pub fn check_alarms(&self) -> Result<(), String> {
        if self.alarms.iter().any(|w| w.kind == AlarmKind::Estop) {
            return Err("--alarm estop: the Kobuki's sensor data has no e-stop (bumper, cliff, wheel-drop and motor-fault only)".into());
        }
        Ok(())
    }
}

impl Default for SimKobukiConfig {
    fn default() -> Self {
        Self {
            drive: DiffDriveParams {
                wheel_base_m: kobuki::WHEEL_BASE_M,
                ticks_per_m: kobuki::TICKS_PER_M,
                limits: DriveLimits { max_v: 0.7, max_omega: std::f64::consts::PI, max_accel: 1.0, max_alpha: 6.0 },
                error: OdometryError { noise: 0.005, ..OdometryError::NONE },
                seed: 1,
            },
            feedback_period_s: 0.02,
            battery_dv: 165,
            clock_start_ms: 0,
            encoder_start: 0,
            alarms: Vec::new(),
        }
    }
}

/// The simulated Kobuki firmware.
#[derive(Debug)]
pub struct SimKobuki {
    cfg: SimKobukiConfig,
    drive: DiffDrive,
    decoder: KobukiDecoder,
    t_s: f64,
    next_feedback_s: f64,
    cmd: BodyVelocity,
    /// The last (speed mm/s, radius mm) received.
    pub last_command: Option<(i16, i16)>,
    pub commands: u64,
    pub feedback_sent: u64,
    /// Sensor bits a test may set.
    pub cliff: u8,
    pub wheel_drop: u8,
}

impl SimKobuki {
    pub fn new(cfg: SimKobukiConfig) -> Self {
        Self {
            drive: DiffDrive::new(cfg.drive),
            decoder: KobukiDecoder::new(),
            t_s: 0.0,
            next_feedback_s: 0.0,
            cmd: BodyVelocity::ZERO,
            last_command: None,
            commands: 0,
            feedback_sent: 0,
            cliff: 0,
            wheel_drop: 0,
            cfg,
        }
    }

    /// The body velocity the last command asks for.
    pub fn commanded(&self) -> BodyVelocity {
        self.cmd
    }

    pub fn decode_stats(&self) -> KobukiStats {
        self.decoder.stats()
    }

    pub fn time_s(&self) -> f64 {
        self.t_s
    }

    fn alarm(&self, kind: AlarmKind) -> bool {
        AlarmWindow::any(&self.cfg.alarms, kind, self.t_s)
    }

    /// The cliff and wheel-drop bits now: those a test set, or a scheduled alarm's.
    fn cliff_bits(&self) -> (u8, u8) {
        let cliff = if self.alarm(AlarmKind::Cliff) { kobuki::mask::CLIFF_CENTRE } else { self.cliff };
        let drop = if self.alarm(AlarmKind::WheelDrop) { kobuki::mask::WHEEL_DROP_LEFT } else { self.wheel_drop };
        (cliff, drop)
    }

    fn feedback(&mut self, out: &mut Vec<u8>) {
        let (l, r) = self.drive.ticks();
        let pwm = |v: f64| (v / self.cfg.drive.limits.max_v * 100.0).clamp(-100.0, 100.0) as i8;
        let half = 0.5 * self.cfg.drive.wheel_base_m * self.drive.velocity().omega;
        let cs = CoreSensors {
            timestamp_ms: self.cfg.clock_start_ms.wrapping_add((self.t_s * 1000.0).round() as u64 as u16),
            bumper: if self.drive.bumper() || self.alarm(AlarmKind::Bumper) { kobuki::mask::BUMPER_CENTRE } else { 0 },
            wheel_drop: self.cliff_bits().1,
            cliff: self.cliff_bits().0,
            left_encoder: self.cfg.encoder_start.wrapping_add(l as u16),
            right_encoder: self.cfg.encoder_start.wrapping_add(r as u16),
            left_pwm: pwm(self.drive.velocity().v - half),
            right_pwm: pwm(self.drive.velocity().v + half),
            buttons: 0,
            charger: 0,
            battery_dv: self.cfg.battery_dv,
            over_current: if self.alarm(AlarmKind::MotorFault) { 1 } else { 0 },
        };
        out.extend(kobuki::encode_frame(&cs.to_subpayload()));
        self.feedback_sent += 1;
    }
}

impl SimDevice for SimKobuki {
    fn receive(&mut self, bytes: &[u8], _out: &mut Vec<u8>) {
        for payload in self.decoder.feed(bytes) {
            if let Some((speed, radius)) = self.decoder.base_control(&payload) {
                self.commands += 1;
                self.last_command = Some((speed, radius));
                self.cmd = kobuki::body_velocity(speed, radius, self.cfg.drive.wheel_base_m);
            }
        }
    }

    fn advance(&mut self, dt: f64, out: &mut Vec<u8>) {
        if !(dt > 0.0 && dt.is_finite()) {
            return;
        }
        let end = self.t_s + dt;
        while self.t_s < end {
            let next = end.min(self.t_s + 0.005).min(self.next_feedback_s.max(self.t_s));
            // Cliff or wheel drop: the firmware cuts the motors.
            let (cliff, drop) = self.cliff_bits();
            let cmd = if cliff != 0 || drop != 0 { BodyVelocity::ZERO } else { self.cmd };
            if next > self.t_s {
                self.drive.step(cmd, next - self.t_s);
                self.t_s = next;
            }
            if self.t_s >= self.next_feedback_s - 1e-12 {
                self.feedback(out);
                self.next_feedback_s += self.cfg.feedback_period_s;
            } else if next >= end {
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
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base_control_drives_and_feedback_wraps() {
        let cfg = SimKobukiConfig {
            clock_start_ms: 65_500,
            encoder_start: 65_000,
            drive: DiffDriveParams { error: OdometryError::NONE, ..SimKobukiConfig::default().drive },
            ..Default::default()
        };
        let mut k = SimKobuki::new(cfg);
        let mut out = Vec::new();
        let (speed, radius) = kobuki::velocity_command(0.2, 0.0, kobuki::WHEEL_BASE_M);
        k.receive(&kobuki::encode_base_control(speed, radius), &mut out);
        assert_eq!(k.commanded(), BodyVelocity::new(0.2, 0.0));
        k.advance(1.0, &mut out);
        let mut d = KobukiDecoder::new();
        let sensors: Vec<CoreSensors> = d.feed(&out).iter().filter_map(|p| d.core_sensors(p)).collect();
        assert_eq!(sensors.len(), 51);
        let last = sensors.last().unwrap();
        assert_eq!(last.timestamp_ms, 964, "65500 + 1000 wraps to 964");
        // 1 s at 0.2 m/s after a 0.2 s ramp: 0.18 m = 2110 ticks, wrapped past 65535.
        let travelled = last.left_encoder.wrapping_sub(65_000);
        assert!((i32::from(travelled) - 2110).abs() <= 2, "{travelled}");
        assert_eq!(last.battery_dv, 165);
    }

    #[test]
    fn no_firmware_watchdog_and_cliff_stops() {
        let mut k = SimKobuki::new(SimKobukiConfig::default());
        let mut out = Vec::new();
        k.receive(&kobuki::encode_base_control(100, 0), &mut out);
        k.advance(5.0, &mut out);
        assert_eq!(k.drive().velocity().v, 0.1, "still driving after 5 s without a command");
        k.cliff = kobuki::mask::CLIFF_CENTRE;
        k.advance(1.0, &mut out);
        assert_eq!(k.drive().velocity().v, 0.0);
    }

    #[test]
    fn scheduled_alarms_show_in_the_sensor_data() {
        // Edges off the 20 ms feedback grid.
        let alarms = ["cliff@0.11+0.1", "wheel-drop@0.31+0.1", "motor-fault@0.51+0.1", "bumper@0.71+0.1"]
            .map(|s| s.parse().unwrap())
            .to_vec();
        let cfg = SimKobukiConfig { alarms, ..Default::default() };
        assert!(cfg.check_alarms().is_ok());
        let mut k = SimKobuki::new(cfg);
        let mut out = Vec::new();
        k.advance(1.0, &mut out);
        let mut d = KobukiDecoder::new();
        let sensors: Vec<CoreSensors> = d.feed(&out).iter().filter_map(|p| d.core_sensors(p)).collect();
        let count = |f: fn(&CoreSensors) -> bool| sensors.iter().filter(|s| f(s)).count();
        // 50 Hz feedback: 0.1 s windows hold 5 samples each.
        assert_eq!(count(|s| s.cliff != 0), 5);
        assert_eq!(count(|s| s.wheel_drop != 0), 5);
        assert_eq!(count(|s| s.over_current != 0), 5);
        assert_eq!(count(|s| s.bumper != 0), 5);
        let estop = SimKobukiConfig { alarms: vec!["estop@0+1".parse().unwrap()], ..Default::default() };
        assert!(estop.check_alarms().unwrap_err().contains("no e-stop"));
    }
}
