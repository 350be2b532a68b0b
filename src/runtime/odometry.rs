//! The recent odometry, for picking the measured velocity that goes with a frame.
//!
//! The base reports odometry at 50 Hz (FNP/1) with device stamps mapped to the host's monotonic
//! clock, the clock frames are stamped with. The step for a frame pair uses the **latest odometry
//! stamped at or before the newer frame's capture time**: the velocity the robot had while the
//! camera moved between the two frames, and never a measurement from after the picture was
//! taken. When every stored sample is newer (the frame is older than the history), the oldest
//! sample is used; with no odometry at all (base silent) the step gets zero velocity, so OFFIS
//! reports no distances rather than invented ones.

use hal::Odometry;
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

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hal::BodyVelocity;

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
