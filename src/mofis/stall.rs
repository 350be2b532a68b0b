//! Stall recovery: the robot notices that it is pushing against something and turns away.
//!
//! One webcam cannot see what is beside the robot, so a surface can still be touched: a box
//! corner that left the field of view while the robot passed it, a door jamb. A robot pushing
//! against it gets nowhere: its wheel encoders measure (almost) no motion while the set-point
//! asks for speed. Left alone it would push until the mission times out.
//!
//! [`StallRecovery`] compares the forward speed *commanded* in the previous step with the speed
//! the odometry *measured* over this one. When the command was at least `min_command_mps` and the
//! measurement stayed below `max_ratio` of it for `after_s`, the robot is stalled. It then backs
//! off `reverse_m` the way it came (only where `control.max_reverse_speed` allows reversing: the
//! camera cannot see behind, but the robot has just driven through there), turns on the spot by
//! `turn_rad` towards the side whose path is freer (in the obstacle memory; the goal's side on a
//! tie) and resumes; a turn on the spot cannot run a round robot into anything.
//! Each recovery is counted ([`StallRecovery::recoveries`]) so a run shows how often it happened.
//!
//! A phase that gets nothing done within `phase_timeout_s` (wheels blocked outright) gives up,
//! so the caller's own safety paths (stop on failure) stay in charge.

use crate::config_error::ConfigError;
use hal::BodyVelocity;
use serde::{Deserialize, Serialize};

/// The `[mofis.stall]` config table.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StallParams {
    /// Recovery on (true) or off.
    pub enabled: bool,
    /// A commanded forward speed below this never counts as pushing, m/s.
    pub min_command_mps: f64,
    /// Stalled while the measured speed is below this fraction of the commanded speed.
    pub max_ratio: f64,
    /// ... for this long, s.
    pub after_s: f64,
    /// How far to back off before turning, m (0: never; also skipped where the control limits
    /// forbid reversing).
    pub reverse_m: f64,
    /// ... at this speed, m/s.
    pub reverse_speed_mps: f64,
    /// How far to turn away on the spot, rad.
    pub turn_rad: f64,
    /// Give a phase (backing off, turning) up after this long, s.
    pub phase_timeout_s: f64,
    /// A stall within this long after the last recovery ended turns to the same side again
    /// (instead of back toward what was just escaped), s.
    pub repeat_window_s: f64,
}

impl Default for StallParams {
    fn default() -> Self {
        Self {
            enabled: true,
            min_command_mps: 0.08,
            max_ratio: 0.25,
            after_s: 0.5,
            reverse_m: 0.15,
            reverse_speed_mps: 0.1,
            turn_rad: 0.8,
            phase_timeout_s: 4.0,
            repeat_window_s: 5.0,
        }
    }
}

impl StallParams {
    /// Range checks.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, problem: &str| {
            Err(ConfigError::Invalid { field: format!("mofis.stall.{field}"), problem: problem.into() })
        };
        if !(self.min_command_mps.is_finite() && self.min_command_mps > 0.0) {
            return bad("min_command_mps", "must be a positive speed in m/s");
        }
        if !(self.max_ratio.is_finite() && self.max_ratio > 0.0 && self.max_ratio < 1.0) {
            return bad("max_ratio", "must be in (0, 1)");
        }
        if !(self.after_s.is_finite() && self.after_s > 0.0) {
            return bad("after_s", "must be a positive time in s");
        }
        if !(self.turn_rad.is_finite() && self.turn_rad > 0.0 && self.turn_rad <= std::f64::consts::PI) {
            return bad("turn_rad", "must be in (0, π] rad");
        }
        if !(self.reverse_m.is_finite() && (0.0..=1.0).contains(&self.reverse_m)) {
            return bad("reverse_m", "must be in [0, 1] m");
        }
        if !(self.reverse_speed_mps.is_finite() && self.reverse_speed_mps > 0.0) {
            return bad("reverse_speed_mps", "must be a positive speed in m/s");
        }
        if !(self.phase_timeout_s.is_finite() && self.phase_timeout_s > 0.0) {
            return bad("phase_timeout_s", "must be a positive time in s");
        }
        if !(self.repeat_window_s.is_finite() && self.repeat_window_s >= 0.0) {
            return bad("repeat_window_s", "must be a time >= 0 in s");
        }
        Ok(())
    }
}

/// A repeat stall backs off at most (1 + this) × `reverse_m`.
const MAX_REPEAT_SCALE: u32 = 2;

#[derive(Clone, Copy, Debug, PartialEq)]
enum Phase {
    /// Driving normally; stalled for this long so far, s.
    Watching { stalled_s: f64 },
    /// Backing off: this far left to go, m, then turn to `side` (+1 left, −1 right).
    Reversing { left_m: f64, side: f64, time_left_s: f64 },
    /// Turning on the spot: this much turn left to do (signed, + = left), rad, for at most this
    /// much longer, s.
    Turning { left_rad: f64, time_left_s: f64 },
}

/// What the recovery asks for instead of the goal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Manoeuvre {
    /// Drive straight back at this speed, m/s (positive).
    Reverse(f64),
    /// Turn on the spot by this much more, rad (+ left).
    Turn(f64),
}

/// The stall detector and its back-off-and-turn manoeuvre (module doc).
#[derive(Clone, Debug)]
pub struct StallRecovery {
    params: StallParams,
    can_reverse: bool,
    phase: Phase,
    recoveries: u32,
    /// The side of the last recovery (+1 left, −1 right) and the time since it ended, s.
    last: Option<(f64, f64)>,
    /// Recoveries in a row, each within `repeat_window_s` of the one before (0 for a first).
    repeats: u32,
}

impl StallRecovery {
    /// `can_reverse`: the control limits allow driving backwards (else no backing off).
    pub fn new(params: StallParams, can_reverse: bool) -> Self {
        Self { params, can_reverse, phase: Phase::Watching { stalled_s: 0.0 }, recoveries: 0, last: None, repeats: 0 }
    }

    /// How many recoveries were started.
    pub fn recoveries(&self) -> u32 {
        self.recoveries
    }

    /// True while a manoeuvre is under way.
    pub fn recovering(&self) -> bool {
        !matches!(self.phase, Phase::Watching { .. })
    }

    /// Forgets a stall in progress (after a fail-safe stop).
    pub fn reset(&mut self) {
        self.phase = Phase::Watching { stalled_s: 0.0 };
        self.last = None;
        self.repeats = 0;
    }

    /// One step of `dt` s: `commanded` is the set-point sent before this step, `measured` the
    /// odometry over it. `free_side` says which way to turn when a stall is found (+1 left, −1
    /// right); it is asked only then. Returns the manoeuvre to drive instead of the goal while
    /// recovering, `None` while driving normally.
    pub fn update(
        &mut self,
        commanded: BodyVelocity,
        measured: BodyVelocity,
        dt: f64,
        free_side: impl FnOnce() -> f64,
    ) -> Option<Manoeuvre> {
        let p = self.params;
        if !(p.enabled && dt.is_finite() && dt > 0.0) {
            return None;
        }
        let measured = if measured.v.is_finite() && measured.omega.is_finite() { Some(measured) } else { None };
        match self.phase {
            Phase::Watching { stalled_s } => {
                if let Some((_, since_s)) = &mut self.last {
                    *since_s += dt;
                }
                let pushing =
                    commanded.v >= p.min_command_mps && measured.is_some_and(|m| m.v.abs() < p.max_ratio * commanded.v);
                let stalled_s = if pushing { stalled_s + dt } else { 0.0 };
                self.phase = Phase::Watching { stalled_s };
                // (a tolerance so that 15 steps of 1/30 s make the 0.5 s they should)
                if stalled_s < p.after_s - 1e-9 {
                    return None;
                }
                // a repeat stall soon after a recovery turns the same way again (further from what
                // was escaped, not back toward it) and backs off further each time, up to
                // (1 + MAX_REPEAT_SCALE) × reverse_m: 0.15 m did not clear a door jamb met 1 m off
                // the doorway's centre
                let side = match self.last {
                    Some((side, since_s)) if since_s <= p.repeat_window_s => {
                        self.repeats = (self.repeats + 1).min(MAX_REPEAT_SCALE);
                        side
                    }
                    _ => {
                        self.repeats = 0;
                        if free_side() < 0.0 { -1.0 } else { 1.0 }
                    }
                };
                let scale = (1 + self.repeats) as f64;
                self.last = Some((side, 0.0));
                self.recoveries += 1;
                tracing::warn!(
                    recovery = self.recoveries,
                    "stalled: commanded {:.2} m/s, measured {:.2} m/s for {:.1} s; backing off and turning {:.0}° {}",
                    commanded.v,
                    measured.map_or(f64::NAN, |m| m.v),
                    p.after_s,
                    p.turn_rad.to_degrees(),
                    if side > 0.0 { "left" } else { "right" }
                );
                self.phase = match self.can_reverse && p.reverse_m > 0.0 {
                    true => {
                        Phase::Reversing { left_m: scale * p.reverse_m, side, time_left_s: scale * p.phase_timeout_s }
                    }
                    false => Phase::Turning { left_rad: side * p.turn_rad, time_left_s: p.phase_timeout_s },
                };
                self.manoeuvre()
            }
            Phase::Reversing { left_m, side, time_left_s } => {
                let left_m = left_m + measured.map_or(0.0, |m| m.v * dt).min(0.0);
                let time_left_s = time_left_s - dt;
                self.phase = match left_m <= 0.0 || time_left_s <= 0.0 {
                    true => Phase::Turning { left_rad: side * p.turn_rad, time_left_s: p.phase_timeout_s },
                    false => Phase::Reversing { left_m, side, time_left_s },
                };
                self.manoeuvre()
            }
            Phase::Turning { left_rad, time_left_s } => {
                let rest = left_rad - measured.map_or(0.0, |m| m.omega * dt);
                let time_left_s = time_left_s - dt;
                // done once the remaining angle reached or crossed zero
                if rest * left_rad <= 0.0 || rest.abs() < 0.02 || time_left_s <= 0.0 {
                    if time_left_s <= 0.0 {
                        tracing::warn!("stall recovery: the turn did not complete; resuming");
                    }
                    self.phase = Phase::Watching { stalled_s: 0.0 };
                    return None;
                }
                self.phase = Phase::Turning { left_rad: rest, time_left_s };
                self.manoeuvre()
            }
        }
    }

    fn manoeuvre(&self) -> Option<Manoeuvre> {
        match self.phase {
            Phase::Watching { .. } => None,
            Phase::Reversing { .. } => Some(Manoeuvre::Reverse(self.params.reverse_speed_mps)),
            Phase::Turning { left_rad, .. } => Some(Manoeuvre::Turn(left_rad)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DT: f64 = 1.0 / 30.0;

    fn v(v: f64, omega: f64) -> BodyVelocity {
        BodyVelocity { v, omega }
    }

    /// Pushes against a wall until the recovery starts; the number of steps and its manoeuvre.
    fn stall(s: &mut StallRecovery, side: f64) -> (usize, Manoeuvre) {
        for n in 1..100 {
            if let Some(m) = s.update(v(0.3, 0.0), v(0.0, 0.0), DT, || side) {
                return (n, m);
            }
        }
        panic!("no stall detected");
    }

    #[test]
    fn driving_freely_never_triggers() {
        let mut s = StallRecovery::new(StallParams::default(), true);
        for _ in 0..300 {
            // the measured speed lags the command a little, as a real base does
            assert_eq!(s.update(v(0.3, 0.0), v(0.27, 0.0), DT, || panic!("not asked")), None);
        }
        // creeping below the minimum command is not pushing either
        for _ in 0..300 {
            assert_eq!(s.update(v(0.05, 0.0), v(0.0, 0.0), DT, || panic!("not asked")), None);
        }
        assert_eq!(s.recoveries(), 0);
    }

    #[test]
    fn a_stall_backs_off_then_turns_towards_the_free_side_then_resumes() {
        let p = StallParams::default();
        let mut s = StallRecovery::new(p, true);
        let (steps, first) = stall(&mut s, -1.0);
        assert_eq!(steps, (p.after_s / DT).ceil() as usize);
        assert_eq!(first, Manoeuvre::Reverse(p.reverse_speed_mps));
        assert!(s.recovering());
        assert_eq!(s.recoveries(), 1);
        // backing off at the asked speed until reverse_m is covered
        let mut n = 1;
        while let Some(Manoeuvre::Reverse(_)) = s.update(v(-0.1, 0.0), v(-0.1, 0.0), DT, || panic!()) {
            n += 1;
        }
        let expected = (p.reverse_m / (0.1 * DT)).ceil() as i32;
        assert!((n - expected).abs() <= 1, "{n} reversing steps, expected about {expected}");
        // then the turn, to the right (the free side): the angle left shrinks by what the
        // odometry measured
        let mut left = -p.turn_rad;
        let mut n = 0;
        while let Some(m) = s.update(v(0.0, -0.6), v(0.0, -0.6), DT, || panic!("not asked")) {
            let Manoeuvre::Turn(a) = m else { panic!("{m:?}") };
            assert!(a < 0.0 && a > left, "{a} after {left}");
            left = a;
            n += 1;
        }
        // it stops once less than 0.02 rad (one step here) is left
        let turned = n as f64 * 0.6 * DT;
        assert!((turned - p.turn_rad).abs() <= 0.05, "turned {turned} rad in {n} steps, asked {}", p.turn_rad);
        assert!(!s.recovering());
        // driving again: a new stall needs the full time again
        assert_eq!(s.update(v(0.3, 0.0), v(0.0, 0.0), DT, || 1.0), None);
    }

    #[test]
    fn without_reversing_it_only_turns() {
        let p = StallParams::default();
        let mut s = StallRecovery::new(p, false);
        assert_eq!(stall(&mut s, 1.0).1, Manoeuvre::Turn(p.turn_rad));
        let mut s = StallRecovery::new(StallParams { reverse_m: 0.0, ..p }, true);
        assert_eq!(stall(&mut s, 1.0).1, Manoeuvre::Turn(p.turn_rad));
    }

    #[test]
    fn blocked_manoeuvres_give_up_and_disabled_does_nothing() {
        let p = StallParams { phase_timeout_s: 1.0, ..StallParams::default() };
        let mut s = StallRecovery::new(p, true);
        stall(&mut s, 1.0);
        // neither backing off nor turning gets anywhere: each phase ends after 1 s
        let mut n = 0;
        while s.update(v(0.0, 0.6), v(0.0, 0.0), DT, || 1.0).is_some() {
            n += 1;
            assert!(n < 200);
        }
        assert!((58..=62).contains(&n), "{n}");
        let mut off = StallRecovery::new(StallParams { enabled: false, ..p }, true);
        for _ in 0..100 {
            assert_eq!(off.update(v(0.3, 0.0), v(0.0, 0.0), DT, || 1.0), None);
        }
    }

    /// Runs a whole recovery (backing off, then turning as asked) and returns its turn's sign.
    fn recover(s: &mut StallRecovery, free_side: f64) -> f64 {
        recover_and_back_off(s, free_side).0
    }

    /// ... and how far it backed off, m.
    fn recover_and_back_off(s: &mut StallRecovery, free_side: f64) -> (f64, f64) {
        let (_, mut m) = stall(s, free_side);
        let (mut sign, mut back) = (0.0, 0.0);
        loop {
            let odo = match m {
                Manoeuvre::Reverse(speed) => {
                    back += speed * DT;
                    v(-speed, 0.0)
                }
                Manoeuvre::Turn(a) => {
                    sign = a.signum();
                    v(0.0, 0.6 * a.signum())
                }
            };
            match s.update(odo, odo, DT, || panic!("asked mid-recovery")) {
                Some(next) => m = next,
                None => return (sign, back),
            }
        }
    }

    #[test]
    fn repeat_stalls_back_off_further_up_to_three_times_as_far() {
        let p = StallParams::default();
        let mut s = StallRecovery::new(p, true);
        // each back-off ends within one step (0.1 m/s × 1/30 s) past its distance
        let step_m = p.reverse_speed_mps * DT + 1e-9;
        let backs: Vec<f64> = (0..4).map(|_| recover_and_back_off(&mut s, 1.0).1).collect();
        for (b, k) in backs.iter().zip([1.0, 2.0, 3.0, 3.0]) {
            assert!(*b >= k * p.reverse_m - 1e-9 && *b <= k * p.reverse_m + step_m, "{backs:?}");
        }
        // long after the last one: back to the first distance
        for _ in 0..(p.repeat_window_s / DT) as usize + 5 {
            assert_eq!(s.update(v(0.3, 0.0), v(0.3, 0.0), DT, || panic!()), None);
        }
        let b = recover_and_back_off(&mut s, 1.0).1;
        assert!(b >= p.reverse_m - 1e-9 && b <= p.reverse_m + step_m, "{b}");
    }

    #[test]
    fn a_repeat_stall_turns_the_same_way_again() {
        let p = StallParams::default();
        let mut s = StallRecovery::new(p, true);
        assert_eq!(recover(&mut s, 1.0), 1.0);
        // stuck again 1 s later: the right now looks freer, but turning back right would face
        // what was just escaped
        for _ in 0..30 {
            assert_eq!(s.update(v(0.3, 0.0), v(0.3, 0.0), DT, || panic!()), None);
        }
        assert_eq!(recover(&mut s, -1.0), 1.0);
        // long after: the free side decides again
        for _ in 0..(p.repeat_window_s / DT) as usize + 5 {
            assert_eq!(s.update(v(0.3, 0.0), v(0.3, 0.0), DT, || panic!()), None);
        }
        assert_eq!(recover(&mut s, -1.0), -1.0);
        // straight into another stall: still that way; a reset (fail-safe stop) forgets it
        assert_eq!(recover(&mut s, 1.0), -1.0);
        s.reset();
        assert_eq!(recover(&mut s, 1.0), 1.0);
        assert_eq!(s.recoveries(), 5);
    }

    #[test]
    fn bad_parameters_are_named() {
        let e = StallParams { max_ratio: 1.5, ..StallParams::default() }.validate().unwrap_err();
        assert!(e.to_string().contains("mofis.stall.max_ratio"), "{e}");
        let e = StallParams { reverse_m: -0.1, ..StallParams::default() }.validate().unwrap_err();
        assert!(e.to_string().contains("mofis.stall.reverse_m"), "{e}");
        assert!(StallParams::default().validate().is_ok());
    }
}
