//! The recent odometry, for picking the measured velocity that goes with a frame.
//!
//! The base reports odometry at 50 Hz (FNP/1) with device stamps mapped to the host's monotonic
//! clock, the clock frames are stamped with. The step for a frame pair uses the **mean of the
//! samples stamped within the pair's interval** (`(t_A, t_B]`, [`OdometryHistory::mean_over`]):
//! each sample is the mean velocity over its own 20 ms period, so their mean is the motion the
//! camera made between the two pictures. This matters when the robot turns: a yaw-rate error of
//! 0.1 rad/s left in the flow by the de-rotation is 0.4 px per 30 fps frame at 1280 px, more than
//! the translational flow of a wall 3 m away. When no sample falls in the interval, the latest
//! sample stamped at or before the newer frame is used ([`OdometryHistory::for_frame`]), never a
//! measurement from after the picture was taken; when every stored sample is newer (the frame is
//! older than the history), the oldest one; with no odometry at all (base silent) the step gets
//! zero velocity, so OFFIS reports no distances rather than invented ones.

use hal::{BodyVelocity, Odometry};
use std::collections::VecDeque;

/// The last `capacity` odometry samples, in arrival order.
#[derive(Clone, Debug)]
pub struct OdometryHistory {
    samples: VecDeque<Odometry>,
    capacity: usize,
}

impl OdometryHistory {
    /// Keeps `capacity` samples (128 ≈ 2.5 s at 50 Hz covers any frame the step still takes).
    pub fn new(capacity: usize) -> Self {
        let capacity = capacity.max(1);
        Self { samples: VecDeque::with_capacity(capacity), capacity }
    }

    pub fn push(&mut self, odometry: Odometry) {
        if self.samples.len() == self.capacity {
            self.samples.pop_front();
        }
        self.samples.push_back(odometry);
    }

    /// The sample to use for a frame captured at `t_ns` (see the module docs).
    pub fn for_frame(&self, t_ns: u64) -> Option<Odometry> {
        self.samples.iter().rev().find(|o| o.t_ns <= t_ns).or_else(|| self.samples.front()).copied()
    }

    /// The mean velocity of the samples stamped in `(t0_ns, t1_ns]`, else [`Self::for_frame`]`(t1_ns)`.
    pub fn mean_over(&self, t0_ns: u64, t1_ns: u64) -> Option<BodyVelocity> {
        let (mut v, mut omega, mut n) = (0.0, 0.0, 0u32);
        for o in self.samples.iter().filter(|o| o.t_ns > t0_ns && o.t_ns <= t1_ns) {
            v += o.velocity.v;
            omega += o.velocity.omega;
            n += 1;
        }
        match n {
            0 => self.for_frame(t1_ns).map(|o| o.velocity),
            n => Some(BodyVelocity::new(v / f64::from(n), omega / f64::from(n))),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_mean_over_the_frame_interval() {
        let mut h = OdometryHistory::new(8);
        assert_eq!(h.mean_over(0, 50), None);
        for (t, v) in [(10, 0.1), (20, 0.2), (30, 0.3), (40, 0.6)] {
            h.push(odo(t, v));
        }
        // (15, 40]: the samples at 20, 30 and 40
        let m = h.mean_over(15, 40).unwrap();
        assert!((m.v - (0.2 + 0.3 + 0.6) / 3.0).abs() < 1e-12, "{m:?}");
        // an interval without samples: the latest one at or before its end
        assert_eq!(h.mean_over(41, 45).unwrap().v, 0.6);
        assert_eq!(h.mean_over(21, 25).unwrap().v, 0.2);
    }

    fn odo(t_ns: u64, v: f64) -> Odometry {
        Odometry { t_ns, velocity: BodyVelocity::new(v, 0.0), left_ticks: 0, right_ticks: 0 }
    }

    #[test]
    fn picks_the_latest_sample_not_after_the_frame() {
        let mut h = OdometryHistory::new(3);
        assert_eq!(h.for_frame(5), None);
        for (t, v) in [(10, 0.1), (20, 0.2), (30, 0.3), (40, 0.4)] {
            h.push(odo(t, v));
        }
        assert_eq!(h.for_frame(35).unwrap().velocity.v, 0.3);
        assert_eq!(h.for_frame(40).unwrap().velocity.v, 0.4);
        assert_eq!(h.for_frame(1000).unwrap().velocity.v, 0.4);
        // 10 fell out (capacity 3): older frames get the oldest sample kept.
        assert_eq!(h.for_frame(15).unwrap().velocity.v, 0.2);
    }
}
