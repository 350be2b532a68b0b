//! The footprint guard, the last check before the limiter ([`super::MofisParams::guard_evidence`]).

use super::fusion::{Fusion, stop_speed};
use hal::BodyVelocity;

impl Fusion {
    /// How far ahead the footprint guard checks an arc driven at `v` m/s: `guard_horizon_s` of
    /// travel, then the distance to stop braking at `stop_decel_mps2`, m.
    fn guard_reach(&self, v: f64) -> f64 {
        v * self.params.guard_horizon_s + v * v / (2.0 * self.params.stop_decel_mps2)
    }

    /// The footprint guard ([`super::MofisParams::guard_evidence`]) on a command `cmd`: unchanged when
    /// its arc is clear for [`guard_reach`](Self::guard_reach); else, at the same speed, the
    /// turn rate nearest its own, among [`GUARD_TURNS`] fractions of the maximum and within
    /// `guard_max_bend` of it, whose arc is clear; else (with `guard_slow`) the same at the
    /// fastest of the [`GUARD_SLOWER`] speeds, where the same bend turns tighter and the reach
    /// is shorter; else (with `guard_brake`) the freest of those arcs at the full speed's
    /// reach, counting only the cells out of the camera's view, at the speed that stops short
    /// on it (unchanged when that arc is clear: what is in view is the stopping gate's); else
    /// unchanged. It never slows for what is in view alone: braking for every cell, down to a
    /// stop, left the robot standing in front of lingering phantom cells that nothing could
    /// clear (the mean simulated mission took 91 → 110–132 s; docs/missions-history.md).
    /// Turning on the spot and backing off pass: a round robot turning on the spot touches
    /// nothing, and backing off is the stall recovery's way out. `arc_free(curvature, reach,
    /// aside)` is [`super::memory::ObstacleMemory::arc_free`].
    pub(super) fn guard(&self, cmd: BodyVelocity, arc_free: &dyn Fn(f64, f64, bool) -> f64) -> BodyVelocity {
        if cmd.v.is_nan() || cmd.v <= 0.0 {
            return cmd;
        }
        let reach = self.guard_reach(cmd.v);
        let free = arc_free(cmd.omega / cmd.v, reach, false);
        if free >= reach {
            return cmd;
        }
        let max_turn = self.limiter.limits().max_turn_rate;
        let bend = self.params.guard_max_bend;
        let mut turns: Vec<f64> =
            GUARD_TURNS.iter().map(|f| f * max_turn).filter(|w| (w - cmd.omega).abs() <= bend).collect();
        turns.sort_by(|a, b| (a - cmd.omega).abs().total_cmp(&(b - cmd.omega).abs()));
        // the nearest clear turn within the bend at the commanded speed, then (`guard_slow`) at
        // the fastest slower speed with one: slower, the same bend turns tighter and the
        // look-ahead is shorter
        let slower: &[f64] = if self.params.guard_slow { &GUARD_SLOWER } else { &[] };
        for frac in std::iter::once(1.0).chain(slower.iter().copied()) {
            let v = cmd.v * frac;
            let reach_v = self.guard_reach(v);
            if let Some(&omega) = turns.iter().find(|&&w| arc_free(w / v, reach_v, false) >= reach_v) {
                tracing::trace!(
                    target: "flownav::mofis::guard",
                    "{} v={:.2} w={:.2} -> v={v:.2} w={omega:.2}: free {free:.2} of {reach:.2} m",
                    if frac == 1.0 { "bend" } else { "slow" },
                    cmd.v,
                    cmd.omega
                );
                return BodyVelocity { v, omega };
            }
        }
        if self.params.guard_brake
            && let Some(braked) = self.guard_brake(cmd, &turns, reach, arc_free)
        {
            return braked;
        }
        // every candidate's free run, beyond the bend too: `turn:free/free out of view`, m
        if tracing::enabled!(target: "flownav::mofis::arcs", tracing::Level::TRACE) {
            let arcs: Vec<String> = GUARD_TURNS
                .iter()
                .map(|f| f * max_turn)
                .map(|w| {
                    format!("{w:.2}:{:.2}/{:.2}", arc_free(w / cmd.v, reach, false), arc_free(w / cmd.v, reach, true))
                })
                .collect();
            tracing::trace!(target: "flownav::mofis::arcs", "v={:.2} reach {reach:.2} m: {}", cmd.v, arcs.join(" "));
        }
        tracing::trace!(
            target: "flownav::mofis::guard",
            "blocked v={:.2} w={:.2}: free {free:.2} of {reach:.2} m, no clear turn within {bend:.2} rad/s",
            cmd.v,
            cmd.omega
        );
        cmd
    }

    /// The guard's brake (`guard_brake`) for a command `cmd` whose arcs at the candidate turn
    /// rates `turns` are all blocked within `reach`: counting only the cells out of the
    /// camera's view (what is in view and still there is seen again, and is the stopping
    /// gate's), the freest of those arcs (the command's own first, then the nearest turns; the
    /// first of equals wins), at the speed from which the robot stops short on it; `None`
    /// when that arc is clear.
    fn guard_brake(
        &self,
        cmd: BodyVelocity,
        turns: &[f64],
        reach: f64,
        arc_free: &dyn Fn(f64, f64, bool) -> f64,
    ) -> Option<BodyVelocity> {
        let (omega, most) = std::iter::once(cmd.omega)
            .chain(turns.iter().copied().filter(|&w| w != cmd.omega))
            .map(|w| (w, arc_free(w / cmd.v, reach, true)))
            .fold((cmd.omega, f64::NEG_INFINITY), |best, (w, f)| if f > best.1 + 1e-9 { (w, f) } else { best });
        if most >= reach {
            return None;
        }
        let v = cmd.v.min(stop_speed(most, self.params.stop_decel_mps2));
        tracing::trace!(
            target: "flownav::mofis::guard",
            "brake v={:.2} w={:.2} -> v={v:.2} w={omega:.2}: free {most:.2} of {reach:.2} m",
            cmd.v,
            cmd.omega
        );
        Some(BodyVelocity { v, omega })
    }
}

/// The slower speeds the footprint guard tries when no turn clears the arc, as fractions of the
/// commanded speed.
const GUARD_SLOWER: [f64; 4] = [0.7, 0.5, 0.35, 0.25];

/// The turn rates the footprint guard tries, as fractions of the maximum turn rate.
const GUARD_TURNS: [f64; 13] = [-1.0, -0.75, -0.5, -0.35, -0.2, -0.1, 0.0, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0];
