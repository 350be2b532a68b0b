//! The envelope profile carried over the last steps: a bin that this frame pair leaves empty
//! takes the newest envelope point of an earlier pair that now lies in it.
//!
//! One pair of a slow robot carries 1–3 cm of travel. At 320×180 its depth is matching noise
//! divided by that travel, and in most steps half of the profile's bins hold no reliable block:
//! the plane fit then finds no TPO at all, although the walls were measured a few pairs before
//! and have not moved. The robot's own motion since (the odometry of each frame) moves those
//! points into the current view, as the obstacle memory does with its cells
//! ([`crate::mofis::memory`]); here only the profile's envelope points are carried, for as long
//! as the temporal filter trusts a step's evidence ([`super::temporal::TemporalParams`]: the
//! robot has turned less than `max_turn_rad` and the point is younger than `max_age_s`) and
//! for at most `carry_m` of travel.
//!
//! A bin measured by this pair keeps its own point: carried points only fill gaps, so a pair
//! that measures the whole profile (the 720p bench's pairs mostly do) is unchanged.
//!
//! Pure and deterministic: the motion comes from the caller's odometry, never from a clock;
//! the store has a fixed capacity (no allocation per step once full).

use super::features::Bin;
use super::temporal::Motion;
use std::collections::VecDeque;

/// Points held: 16 bins × 8 steps.
const CAPACITY: usize = 128;

/// One carried envelope point, camera-centred in robot axes at the current frame, m.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Carried {
    point: [f64; 2],
    turned_rad: f64,
    age_s: f64,
    travel_m: f64,
}

/// Limits on how long a point is carried.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CarryLimits {
    pub max_turn_rad: f64,
    pub max_age_s: f64,
    /// 0: nothing is carried.
    pub max_travel_m: f64,
}

impl CarryLimits {
    /// `offis.temporal.carry_*`.
    pub fn from_temporal(t: &super::temporal::TemporalParams) -> Self {
        Self { max_turn_rad: t.carry_turn_rad, max_age_s: t.carry_age_s, max_travel_m: t.carry_m }
    }
}

/// The carried envelope points, newest last.
#[derive(Clone, Debug)]
pub struct ProfileCarry {
    limits: CarryLimits,
    points: VecDeque<Carried>,
}

impl ProfileCarry {
    pub fn new(limits: CarryLimits) -> Self {
        Self { limits, points: VecDeque::with_capacity(CAPACITY) }
    }

    /// Forgets every point.
    pub fn reset(&mut self) {
        self.points.clear();
    }

    /// Points held.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The robot moved by `m` since the last step, with the camera at `mount` (x ahead, y left
    /// of the robot's origin, m): every point is moved into the new camera position and axes,
    /// and those past the limits are forgotten. A motion that is not finite, or a gap longer
    /// than `max_age_s`, forgets all.
    pub fn advance(&mut self, m: Motion, mount: [f64; 2]) {
        let l = self.limits;
        if !(m.dt.is_finite() && m.yaw_rad.is_finite() && m.forward_m.is_finite() && m.dt >= 0.0) || m.dt > l.max_age_s
        {
            self.points.clear();
            return;
        }
        // the robot's displacement along the chord of its arc, in the previous robot axes
        let (half_s, half_c) = (0.5 * m.yaw_rad).sin_cos();
        let chord = match m.yaw_rad.abs() > 1e-9 {
            true => m.forward_m * half_s / (0.5 * m.yaw_rad),
            false => m.forward_m,
        };
        let d = [chord * half_c, chord * half_s];
        let (s, c) = m.yaw_rad.sin_cos();
        for q in &mut self.points {
            let r = [q.point[0] + mount[0] - d[0], q.point[1] + mount[1] - d[1]];
            q.point = [c * r[0] + s * r[1] - mount[0], -s * r[0] + c * r[1] - mount[1]];
            q.turned_rad += m.yaw_rad.abs();
            q.age_s += m.dt;
            q.travel_m += m.forward_m.abs();
        }
        self.points
            .retain(|q| q.turned_rad <= l.max_turn_rad && q.age_s <= l.max_age_s && q.travel_m <= l.max_travel_m);
    }

    /// Fills the empty bins of this pair's profile with the newest carried point whose bearing
    /// lies within the bin (between the midpoints to its neighbours' centres), then takes in
    /// this pair's own points. Returns how many bins were filled.
    pub fn fill_and_keep(&mut self, bins: &mut [Bin]) -> usize {
        if self.limits.max_travel_m <= 0.0 {
            return 0;
        }
        let own = measured(bins);
        let filled = self.fill_gaps(bins, own);
        for (b, bin) in bins.iter().enumerate().take(64) {
            if let Some(point) = bin.point.filter(|_| own >> b & 1 == 1) {
                if self.points.len() == CAPACITY {
                    self.points.pop_front();
                }
                self.points.push_back(Carried { point, turned_rad: 0.0, age_s: 0.0, travel_m: 0.0 });
            }
        }
        filled
    }

    /// Fills the empty bins as [`ProfileCarry::fill_and_keep`] does, taking nothing in.
    /// Returns how many bins were filled.
    pub fn fill(&self, bins: &mut [Bin]) -> usize {
        match self.limits.max_travel_m > 0.0 {
            true => self.fill_gaps(bins, measured(bins)),
            false => 0,
        }
    }

    /// Fills the bins not in `own` (bit `b` = bin `b` holds its own point).
    fn fill_gaps(&self, bins: &mut [Bin], own: u64) -> usize {
        let n = bins.len().min(64);
        let mut bearing = [0.0; 64];
        for (b, bin) in bearing.iter_mut().zip(bins.iter()) {
            *b = bin.bearing;
        }
        // the bins' bearings fall from left to right; a bin spans half-way to each neighbour
        let edge = |b: usize, toward: isize| -> f64 {
            match b.checked_add_signed(toward).filter(|&k| k < n) {
                Some(k) => 0.5 * (bearing[b] + bearing[k]),
                // the outer half of an edge bin mirrors its inner half
                None => match b.checked_add_signed(-toward).filter(|&k| k < n) {
                    Some(k) => bearing[b] + 0.5 * (bearing[b] - bearing[k]),
                    None => bearing[b],
                },
            }
        };
        let mut filled = 0;
        for (b, bin) in bins.iter_mut().enumerate().take(n) {
            if own >> b & 1 == 1 {
                continue;
            }
            let (a, z) = (edge(b, -1), edge(b, 1));
            let (lo, hi) = (a.min(z), a.max(z));
            let inside = |q: &&Carried| q.point[0] > 0.0 && (lo..hi).contains(&q.point[1].atan2(q.point[0]));
            if let Some(q) = self.points.iter().rev().find(inside) {
                bin.point = Some(q.point);
                filled += 1;
            }
        }
        filled
    }
}

/// The bins holding a point (bit `b` = bin `b`).
fn measured(bins: &[Bin]) -> u64 {
    bins.iter().take(64).enumerate().filter(|(_, b)| b.point.is_some()).fold(0, |m, (i, _)| m | 1 << i)
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: CarryLimits = CarryLimits { max_turn_rad: 0.25, max_age_s: 1.0, max_travel_m: 0.3 };

    /// Bins centred at `bearings` (left to right), with points at `range` along those bearings
    /// where `some` says so.
    fn bins(bearings: &[f64], range: f64, some: impl Fn(usize) -> bool) -> Vec<Bin> {
        bearings
            .iter()
            .enumerate()
            .map(|(i, &b)| Bin { point: some(i).then(|| [range * b.cos(), range * b.sin()]), bearing: b })
            .collect()
    }

    const BEARINGS: [f64; 4] = [0.3, 0.1, -0.1, -0.3];

    #[test]
    fn a_point_moves_with_the_robot_as_a_fixed_point_must() {
        let mut carry = ProfileCarry::new(LIMITS);
        let mount = [0.1, 0.0];
        // a point 2 m ahead and 0.5 m left of the camera
        let mut first = vec![Bin { point: Some([2.0, 0.5]), bearing: 0.24 }];
        carry.fill_and_keep(&mut first);
        // the robot drives 0.1 m along an arc turning 0.1 rad left
        let m = Motion { forward_m: 0.1, yaw_rad: 0.1, dt: 0.1 };
        carry.advance(m, mount);
        // closed form: the point in the old robot frame, the new robot pose on the arc
        let p = [2.0 + 0.1, 0.5];
        let radius = 0.1 / 0.1;
        let pose = [radius * 0.1f64.sin(), radius * (1.0 - 0.1f64.cos()), 0.1];
        let (s, c) = pose[2].sin_cos();
        let rel = [p[0] - pose[0], p[1] - pose[1]];
        let expect = [c * rel[0] + s * rel[1] - 0.1, -s * rel[0] + c * rel[1]];
        let got = carry.points[0].point;
        assert!((got[0] - expect[0]).abs() < 1e-9 && (got[1] - expect[1]).abs() < 1e-9, "{got:?} vs {expect:?}");
    }

    #[test]
    fn empty_bins_take_the_newest_carried_point_and_measured_bins_keep_their_own() {
        let mut carry = ProfileCarry::new(LIMITS);
        let mut old = bins(&BEARINGS, 3.0, |_| true);
        assert_eq!(carry.fill_and_keep(&mut old), 0);
        carry.advance(Motion { forward_m: 0.02, yaw_rad: 0.0, dt: 1.0 / 30.0 }, [0.0, 0.0]);
        let mut newer = bins(&BEARINGS, 2.0, |i| i == 0);
        carry.fill_and_keep(&mut newer);
        carry.advance(Motion { forward_m: 0.02, yaw_rad: 0.0, dt: 1.0 / 30.0 }, [0.0, 0.0]);
        // bin 0 is measured now; bins 1..3 are empty
        let mut now = bins(&BEARINGS, 1.5, |i| i == 0);
        assert_eq!(carry.fill_and_keep(&mut now), 3);
        assert_eq!(now[0].point, Some([1.5 * 0.3f64.cos(), 1.5 * 0.3f64.sin()]));
        for b in &now[1..] {
            let p = b.point.unwrap();
            // the 3 m points, moved 4 cm nearer
            assert!((p[0].hypot(p[1]) - 3.0).abs() < 0.05, "{p:?}");
        }
    }

    #[test]
    fn points_are_forgotten_past_the_travel_turn_and_age_limits_and_off_carries_nothing() {
        for (m, steps) in [
            (Motion { forward_m: 0.07, yaw_rad: 0.0, dt: 0.01 }, 5),
            (Motion { forward_m: 0.0, yaw_rad: 0.06, dt: 0.01 }, 5),
            (Motion { forward_m: 0.0, yaw_rad: 0.0, dt: 0.3 }, 4),
        ] {
            let mut carry = ProfileCarry::new(LIMITS);
            carry.fill_and_keep(&mut bins(&BEARINGS, 3.0, |_| true));
            for _ in 0..steps - 1 {
                carry.advance(m, [0.0, 0.0]);
            }
            assert_eq!(carry.len(), 4, "{m:?}");
            carry.advance(m, [0.0, 0.0]);
            assert!(carry.is_empty(), "{m:?}");
        }
        let mut off = ProfileCarry::new(CarryLimits { max_travel_m: 0.0, ..LIMITS });
        off.fill_and_keep(&mut bins(&BEARINGS, 3.0, |_| true));
        assert!(off.is_empty(), "nothing is kept when off");
        let mut empty = bins(&BEARINGS, 3.0, |_| false);
        assert_eq!(off.fill_and_keep(&mut empty), 0);
        assert!(empty.iter().all(|b| b.point.is_none()));
    }
}
