//! What the base's own alarms do to the set-points: the last filter before a command goes out.
//!
//! A base reports its alarms in its status (FNP/1 STATUS flags, Kobuki sensor data; see
//! [`hal::BaseStatus`]). [`Alarms`] turns them into a rule on the command, apart from threads
//! and clocks like the rest of [`super::control`]:
//!
//! - **Emergency stop, cliff, wheel drop, motor fault** (a *halt*): the command is zero while any
//!   of them is set, and stays zero until all have been clear for `hold` (default 1 s,
//!   `[run] alarm_hold_ms`), so a flickering sensor or a released e-stop button cannot jerk the
//!   robot back into motion. Only a status that says "clear" starts the hold: a base that goes
//!   silent while halted keeps the robot halted.
//! - **Bumper**: a zero at once, then forward motion (`v > 0`) is refused while it stays pressed;
//!   reversing and turning on the spot pass, so MOFIS's stall recovery (which notices that the
//!   wheels do not move as commanded) can back the robot off what it touched.
//!
//! [`Alarms::on_status`] says when a zero must go out *now* (an alarm was raised), so the caller
//! reacts to the status that raised it, not at its next refresh. Raising, clearing and resuming
//! are logged on `/log`. The base's own watchdog stop is not an alarm: the next set-point clears it.

use crate::logging::{LogHandle, LogLevel};
use hal::{BaseStatus, BodyVelocity};
use std::time::Duration;

/// The halting alarms of a status, with their names for the log.
fn halting(s: &BaseStatus) -> Vec<&'static str> {
    [(s.estop, "emergency stop"), (s.cliff, "cliff"), (s.wheel_drop, "wheel drop"), (s.motor_fault, "motor fault")]
        .into_iter()
        .filter_map(|(set, name)| set.then_some(name))
        .collect()
}

/// A halt in force.
#[derive(Clone, Debug)]
struct Halt {
    /// The halting alarms of the last status.
    raised: Vec<&'static str>,
    /// When a status first said all clear (the hold runs from here), ns.
    clear_since: Option<u64>,
}

/// The alarm rules; see the module docs. Every method takes the time it happens at.
pub struct Alarms {
    hold_ns: u64,
    logger: Option<LogHandle>,
    halt: Option<Halt>,
    bumper: bool,
    stops: u64,
}

impl Alarms {
    /// Resume `hold` after the last halting alarm cleared.
    pub fn new(hold: Duration, logger: Option<LogHandle>) -> Self {
        Self { hold_ns: hold.as_nanos() as u64, logger, halt: None, bumper: false, stops: 0 }
    }

    /// A status from the base at `now_ns`. Returns whether a zero must be sent now: an alarm was
    /// raised (a halting one, or the bumper pressed).
    pub fn on_status(&mut self, s: &BaseStatus, now_ns: u64) -> bool {
        let mut stop_now = false;
        let raised = halting(s);
        if raised.is_empty() {
            if let Some(h) = &mut self.halt
                && h.clear_since.is_none()
            {
                h.clear_since = Some(now_ns);
                let message = format!(
                    "base alarm cleared ({}): set-points resume after {} ms clear",
                    h.raised.join(", "),
                    self.hold_ns / 1_000_000
                );
                self.note(now_ns, LogLevel::Info, message);
            }
        } else {
            let before = self.halt.as_ref().map_or(&[][..], |h| &h.raised[..]);
            let new: Vec<&str> = raised.iter().copied().filter(|n| !before.contains(n)).collect();
            let was_clearing = self.halt.as_ref().is_some_and(|h| h.clear_since.is_some());
            if self.halt.is_none() {
                self.stops += 1;
            }
            if !new.is_empty() || was_clearing {
                stop_now = true;
                let message = format!("base alarm: {}: robot stopped until it clears", raised.join(", "));
                self.note(now_ns, LogLevel::Warning, message);
            }
            self.halt = Some(Halt { raised, clear_since: None });
        }
        if s.bumper != self.bumper {
            self.bumper = s.bumper;
            if s.bumper {
                stop_now = true;
                self.stops += 1;
                self.note(
                    now_ns,
                    LogLevel::Warning,
                    "base alarm: bumper pressed: robot stopped, forward motion refused while pressed".into(),
                );
            } else {
                self.note(now_ns, LogLevel::Info, "bumper released: forward motion allowed".into());
            }
        }
        stop_now
    }

    /// The command to send at `now_ns` instead of `cmd`: zero during a halt and its hold, no
    /// forward speed while the bumper is pressed, else `cmd`.
    pub fn gate(&mut self, cmd: BodyVelocity, now_ns: u64) -> BodyVelocity {
        if let Some(clear_since) = self.halt.as_ref().map(|h| h.clear_since) {
            match clear_since {
                Some(t) if now_ns >= t.saturating_add(self.hold_ns) => {
                    self.halt = None;
                    let message = format!("base alarms clear for {} ms: set-points resume", self.hold_ns / 1_000_000);
                    self.note(now_ns, LogLevel::Info, message);
                }
                _ => return BodyVelocity::ZERO,
            }
        }
        if self.bumper && cmd.v > 0.0 {
            return BodyVelocity::new(0.0, cmd.omega);
        }
        cmd
    }

    /// Whether a halt (or its hold) is in force.
    pub fn halted(&self) -> bool {
        self.halt.is_some()
    }

    /// Whether the last status said the bumper is pressed.
    pub fn bumper(&self) -> bool {
        self.bumper
    }

    /// Stops the alarms caused: each halt and each bumper press counts once.
    pub fn stops(&self) -> u64 {
        self.stops
    }

    fn note(&self, now_ns: u64, level: LogLevel, message: String) {
        match level {
            LogLevel::Warning | LogLevel::Error | LogLevel::Fatal => tracing::warn!("{message}"),
            _ => tracing::info!("{message}"),
        }
        if let Some(log) = &self.logger {
            log.log(now_ns, level, message);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn status(f: impl FnOnce(&mut BaseStatus)) -> BaseStatus {
        let mut s = BaseStatus::default();
        f(&mut s);
        s
    }

    fn fwd() -> BodyVelocity {
        BodyVelocity::new(0.3, 0.1)
    }

    #[test]
    fn each_halting_alarm_stops_at_once_and_holds_after_it_clears() {
        type Set = fn(&mut BaseStatus);
        let flags: [(&str, Set); 4] = [
            ("estop", |s| s.estop = true),
            ("cliff", |s| s.cliff = true),
            ("wheel drop", |s| s.wheel_drop = true),
            ("motor fault", |s| s.motor_fault = true),
        ];
        for (name, set) in flags {
            let mut a = Alarms::new(Duration::from_millis(1000), None);
            assert!(!a.on_status(&BaseStatus::default(), 0), "{name}");
            assert_eq!(a.gate(fwd(), 10 * MS), fwd(), "{name}: no alarm, the command passes");
            assert!(a.on_status(&status(set), 100 * MS), "{name}: a zero goes out with the status");
            assert_eq!(a.gate(fwd(), 100 * MS), BodyVelocity::ZERO, "{name}");
            // Still set: no new zero is due, the command stays zero however long it lasts.
            assert!(!a.on_status(&status(set), 200 * MS), "{name}");
            assert_eq!(a.gate(fwd(), 5_000 * MS), BodyVelocity::ZERO, "{name}");
            // Clear at 5.1 s: still zero until 6.1 s.
            assert!(!a.on_status(&BaseStatus::default(), 5_100 * MS));
            assert_eq!(a.gate(fwd(), 6_099 * MS), BodyVelocity::ZERO, "{name}: within the hold");
            assert!(a.halted());
            assert_eq!(a.gate(fwd(), 6_100 * MS), fwd(), "{name}: resumes after the hold");
            assert!(!a.halted());
            assert_eq!(a.stops(), 1, "{name}");
        }
    }

    #[test]
    fn a_flag_that_returns_during_the_hold_restarts_it() {
        let mut a = Alarms::new(Duration::from_millis(1000), None);
        let estop = status(|s| s.estop = true);
        assert!(a.on_status(&estop, 0));
        a.on_status(&BaseStatus::default(), 100 * MS);
        assert!(a.on_status(&estop, 900 * MS), "raised again: a zero at once");
        a.on_status(&BaseStatus::default(), 1_000 * MS);
        assert_eq!(a.gate(fwd(), 1_500 * MS), BodyVelocity::ZERO, "the hold counts from the last clear");
        assert_eq!(a.gate(fwd(), 1_999 * MS), BodyVelocity::ZERO);
        assert_eq!(a.gate(fwd(), 2_000 * MS), fwd());
        assert_eq!(a.stops(), 1, "one halt, raised twice");
    }

    #[test]
    fn silence_keeps_a_halt() {
        let mut a = Alarms::new(Duration::from_millis(1000), None);
        a.on_status(&status(|s| s.motor_fault = true), 0);
        // No status says clear: an hour later the robot still stands.
        assert_eq!(a.gate(fwd(), 3_600_000 * MS), BodyVelocity::ZERO);
    }

    #[test]
    fn a_second_flag_during_a_halt_sends_another_zero_and_both_must_clear() {
        let mut a = Alarms::new(Duration::from_millis(500), None);
        assert!(a.on_status(&status(|s| s.cliff = true), 0));
        assert!(a.on_status(&status(|s| (s.cliff, s.wheel_drop) = (true, true)), 20 * MS));
        assert!(!a.on_status(&status(|s| s.wheel_drop = true), 40 * MS), "one cleared, one still set");
        assert_eq!(a.gate(fwd(), 2_000 * MS), BodyVelocity::ZERO);
        a.on_status(&BaseStatus::default(), 2_000 * MS);
        assert_eq!(a.gate(fwd(), 2_499 * MS), BodyVelocity::ZERO);
        assert_eq!(a.gate(fwd(), 2_500 * MS), fwd());
    }

    #[test]
    fn the_bumper_stops_then_refuses_only_forward_motion() {
        let mut a = Alarms::new(Duration::from_millis(1000), None);
        let pressed = status(|s| s.bumper = true);
        assert!(a.on_status(&pressed, 0), "a zero at once");
        assert!(!a.on_status(&pressed, 100 * MS), "once per press");
        assert_eq!(a.gate(fwd(), 100 * MS), BodyVelocity::new(0.0, 0.1), "forward refused, the turn passes");
        let back = BodyVelocity::new(-0.1, 0.0);
        assert_eq!(a.gate(back, 200 * MS), back, "the stall recovery may back off");
        let spin = BodyVelocity::new(0.0, -0.5);
        assert_eq!(a.gate(spin, 300 * MS), spin);
        assert!(!a.on_status(&BaseStatus::default(), 400 * MS));
        assert_eq!(a.gate(fwd(), 400 * MS), fwd(), "released: forward again, no hold");
        assert!(a.on_status(&pressed, 500 * MS), "a second press");
        assert_eq!(a.stops(), 2);
    }

    #[test]
    fn the_watchdog_flag_is_not_an_alarm() {
        let mut a = Alarms::new(Duration::from_millis(1000), None);
        assert!(!a.on_status(&status(|s| s.stopped_by_watchdog = true), 0));
        assert_eq!(a.gate(fwd(), 0), fwd());
        assert_eq!(a.stops(), 0);
    }
}
