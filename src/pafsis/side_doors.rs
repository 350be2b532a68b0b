//! Where a door in a side wall is, from all the frames that saw its opening.
//!
//! One frame places an opening by the bearings of its jambs, and one profile bin (3.4° of the
//! C310's view) moves a jamb along the wall by `r / sin g` × 0.06 m, where `r` is the range to
//! the opening and `g` the angle at which the ray meets the wall. A door first comes into view
//! far ahead, where its 0.9 m opening spans about one bin: there its width is not resolved,
//! and the first frames of a door placed it 0.37 m short in the median of the office's tuning
//! runs (likely because only the bins that make it look no wider than a door pass as one, and
//! those lie nearer than the door). Nearer, it spans several bins and is placed to a decimetre.
//!
//! So a door's place is the weighted median of every sighting of it so far, each weighted by
//! the inverse square of its bin's along-wall extent, and it moves as nearer frames come: the
//! first frames place the door, the nearest ones end up deciding where it is.
//!
//! Places are kept in the leg's dead-reckoned frame (the odometry's distance along the leg,
//! without the landmarks' corrections of the progress), where a door stands still however the
//! progress is corrected meanwhile.

/// Below this, m, the bin's extent along the wall is no longer the larger error of a frame's
/// opening (the jambs' depth and the wall's fit are), and nearer frames weigh no more.
const RESOLVED_M: f64 = 4.0;

/// The sightings of one expected door of the current leg.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SideDoorTrack {
    /// The door's index among the leg's doors.
    pub door: usize,
    /// Each sighting's place of the door, in the leg's dead-reckoned frame, m, and its weight.
    sightings: Vec<(f64, f64)>,
    /// The place last applied to the progress, once the track has placed the door.
    placed: Option<f64>,
}

impl SideDoorTrack {
    pub fn new(door: usize) -> Self {
        Self { door, ..Self::default() }
    }

    /// Adds a sighting that puts the door at `place_m` (dead-reckoned frame), seen at range
    /// `range_m` by a ray that meets the wall with sine `sin_angle`.
    pub fn add(&mut self, place_m: f64, range_m: f64, sin_angle: f64) {
        if !(place_m.is_finite() && range_m.is_finite() && sin_angle.is_finite()) {
            return;
        }
        let extent = (range_m / sin_angle.max(f64::EPSILON)).max(RESOLVED_M);
        self.sightings.push((place_m, extent.powi(-2)));
    }

    pub fn len(&self) -> usize {
        self.sightings.len()
    }

    pub fn is_empty(&self) -> bool {
        self.sightings.is_empty()
    }

    /// The door's place from the sightings so far: their weighted median, m.
    pub fn place(&self) -> Option<f64> {
        weighted_median(&self.sightings)
    }

    /// The place applied to the progress so far, if any.
    pub fn placed(&self) -> Option<f64> {
        self.placed
    }

    /// Records the place applied to the progress; returns how far it moved since the last one.
    pub fn apply(&mut self, place_m: f64) -> f64 {
        let moved = self.placed.map_or(0.0, |p| place_m - p);
        self.placed = Some(place_m);
        moved
    }
}

/// The weighted median of `(value, weight)` pairs: the smallest value at which the cumulative
/// weight reaches half the total; `None` when there is no positive weight (NaN weights are
/// left out).
pub fn weighted_median(pairs: &[(f64, f64)]) -> Option<f64> {
    let total: f64 = pairs.iter().map(|p| p.1).filter(|w| *w > 0.0).sum();
    if total <= 0.0 {
        return None;
    }
    let mut sorted: Vec<(f64, f64)> = pairs.iter().copied().filter(|p| p.1 > 0.0).collect();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut acc = 0.0;
    sorted.into_iter().find_map(|(v, w)| {
        acc += w;
        (acc >= 0.5 * total).then_some(v)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_weighted_median_follows_the_weights() {
        assert_eq!(weighted_median(&[]), None);
        assert_eq!(weighted_median(&[(1.0, 0.0)]), None);
        assert_eq!(weighted_median(&[(3.0, 1.0), (1.0, 1.0), (2.0, 1.0)]), Some(2.0));
        // one heavy value outweighs two light ones on either side
        assert_eq!(weighted_median(&[(0.0, 1.0), (5.0, 3.0), (9.0, 1.0)]), Some(5.0));
        assert_eq!(weighted_median(&[(0.0, 1.0), (5.0, 1.0), (9.0, 3.0)]), Some(9.0));
    }

    #[test]
    fn near_sightings_outweigh_the_far_ones_that_came_first() {
        // a door 6 m along, 1 m to the side: five far frames put it 0.5 m short, then three
        // frames from 2.5 m put it right
        let mut t = SideDoorTrack::new(0);
        for _ in 0..5 {
            let (x, d) = (4.5_f64, 1.0_f64);
            let r = x.hypot(d);
            t.add(5.5, r, d / r);
        }
        assert_eq!(t.place(), Some(5.5));
        assert_eq!(t.apply(5.5), 0.0);
        for _ in 0..3 {
            let (x, d) = (2.5_f64, 1.0_f64);
            let r = x.hypot(d);
            t.add(6.0, r, d / r);
        }
        // r / sin g is 21.25 m for the far frames and 7.25 m for the near ones: each near frame
        // weighs 8.6 far ones
        assert_eq!(t.place(), Some(6.0));
        assert!((t.apply(6.0) - 0.5).abs() < 1e-12);
        assert_eq!((t.len(), t.placed()), (8, Some(6.0)));
    }

    #[test]
    fn within_the_resolved_range_frames_weigh_the_same() {
        let mut t = SideDoorTrack::new(3);
        t.add(1.0, 1.0, 1.0);
        t.add(2.0, 2.0, 0.9);
        t.add(3.0, 3.0, 0.8);
        assert_eq!(t.place(), Some(2.0));
    }
}
