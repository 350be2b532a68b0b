//! The obstacles handed to MOFIS: the most threatening cell on each side of the heading.

use super::*;

impl ObstacleMemory {
    /// The most threatening occupied cell as an obstacle for MOFIS (module doc); `present:
    /// false` when none is in or beside the path.
    pub fn threat(&self) -> Obstacle {
        self.threat_within(f64::INFINITY)
    }

    /// [`threat`](Self::threat) for a robot that will stop before its origin has driven
    /// `reach_m` further: its path ends in a half-disc of radius `robot_radius_m +
    /// path_margin_m` around the stop point, and what lies beyond it is not in its way.
    ///
    /// Cells ahead of the robot's origin count within the path (`robot_radius_m +
    /// path_margin_m` of the heading line) at their distance, and in a side band beyond it
    /// (`side_margin_m` wide beside the robot, narrowing to nothing [`SIDE_REACH_M`] ahead) at
    /// a distance that grows with how far into the band: by [`SIDE_FADE_M`] at its outer
    /// edge, where MOFIS's rules call an obstacle far. The nearest by that distance is the
    /// threat. So a box that a small turn takes out of the path fades out of MOFIS's view
    /// instead of vanishing, and the threat does not jump to a wall behind it and back while
    /// the robot's heading jitters (each jump flipped the avoidance turn).
    pub fn threat_within(&self, reach_m: f64) -> Obstacle {
        nearer(self.threat_sides(reach_m)).0
    }

    /// [`threat_within`](Self::threat_within) on each side of the robot's heading: `[left,
    /// right]`, a cell dead ahead (across ≥ 0) counting as left. MOFIS avoids both
    /// ([`crate::mofis::Fusion::step_sides`]).
    pub fn threat_sides(&self, reach_m: f64) -> [Obstacle; 2] {
        let p = &self.params;
        let path = p.robot_radius_m + p.path_margin_m;
        let horizon = self.horizon(reach_m);
        let mut best: [Option<(f64, [f64; 2])>; 2] = [None, None];
        for ([along, across], banded) in self.banded_cells() {
            // a round robot driving forward never meets what is beside or behind its origin; the
            // walls are the lane's (what the memory has of them is depth error)
            if along <= -p.behind_m || along > horizon || banded {
                continue;
            }
            // the side band narrows to nothing at SIDE_REACH_M ahead: far cells count only in
            // the path, as before, and a cell fades out continuously wherever it leaves the band
            // past the stop point the path ends in a half-disc: the distance to the swept
            // segment, not the distance across it
            let past = (along - reach_m).max(0.0);
            let beyond = past.hypot(across) - path;
            let band = p.side_margin_m * (1.0 - along / SIDE_REACH_M).max(0.0);
            let fade = match beyond <= 0.0 {
                true => 0.0,
                false if beyond < band => SIDE_FADE_M * beyond / band,
                false => continue,
            };
            let d = (along.hypot(across) - p.robot_radius_m).max(0.0) + fade;
            let side = &mut best[usize::from(across < 0.0)];
            if side.is_none_or(|(bd, _)| d < bd) {
                *side = Some((d, [along, across]));
            }
        }
        // a robot already closer to a lane's wall than its footprint plus `wall_threat_m` has
        // that wall as a threat on its side (the band leaves the walls to the lane, and the lane
        // alone only keeps the steering from heading out: nothing turned a robot that drifted
        // outside its margin back in before it scraped), at the wall's nearest point not behind
        // its origin
        for (side, [along, across]) in self.lane_walls_near(horizon) {
            let d = (along.hypot(across) - p.robot_radius_m).max(0.0);
            if best[side].is_none_or(|(bd, _)| d < bd) {
                best[side] = Some((d, [along, across]));
            }
        }
        best.map(|b| match b {
            Some((d, [f, l])) => {
                Obstacle { present: true, distance_m: Some(d), bearing_rad: Some(l.atan2(f)), cell: None }
            }
            None => Obstacle::default(),
        })
    }

    /// The walls of the lane ([`walled_lane`](Self::walled_lane)) nearer to the robot's origin
    /// than `robot_radius_m + wall_threat_m`, each as its nearest point not behind the origin
    /// and at most `horizon` ahead, robot frame, with the side of the heading it is on (0 left,
    /// 1 right). A robot outside its lane has the wall it crossed 1 cm away.
    fn lane_walls_near(&self, horizon: f64) -> impl Iterator<Item = (usize, [f64; 2])> + '_ {
        let near = self.params.robot_radius_m + self.params.wall_threat_m;
        let lane = self.walled_lane().filter(|_| self.params.wall_threat_m > 0.0);
        [0, 1].into_iter().filter_map(move |side| {
            let l = lane?;
            let (s, c) = l.angle_rad.sin_cos();
            // distance to the wall and the unit normal toward it (the lane's left is (−s, c))
            let (gap, n) = match side {
                0 => (l.half_width_m - l.left_m, [-s, c]),
                _ => (l.half_width_m + l.left_m, [s, -c]),
            };
            if gap >= near {
                return None;
            }
            let gap = gap.max(0.01);
            let mut at = [gap * n[0], gap * n[1]];
            if at[0] < 0.0 {
                // the foot of the perpendicular is behind: the wall's point abeam of the origin
                if c.abs() < 1e-6 {
                    return None;
                }
                let t = -at[0] / c;
                at = [0.0, at[1] + t * s];
            }
            (at[0] <= horizon).then_some((usize::from(at[1] < 0.0), at))
        })
    }

    /// How far ahead of its origin the path of a robot that stops after `reach_m` matters:
    /// `reach_m + robot_radius_m + path_margin_m`, m (a cell farther along is never within the
    /// margin of its footprint).
    pub fn horizon(&self, reach_m: f64) -> f64 {
        reach_m + self.params.robot_radius_m + self.params.path_margin_m
    }
}

/// The nearer of the `[left, right]` threats ([`ObstacleMemory::threat_sides`]; left on a tie),
/// and the other one when it is present too.
pub fn nearer([left, right]: [Obstacle; 2]) -> (Obstacle, Option<Obstacle>) {
    match (left.distance_m, right.distance_m) {
        (Some(l), Some(r)) if r < l => (right, Some(left)),
        (Some(_), Some(_)) => (left, Some(right)),
        (Some(_), None) => (left, None),
        _ => (right, None),
    }
}
