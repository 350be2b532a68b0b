//! Choosing a heading: the free heading nearest the goal, and keeping off side surfaces.

use super::*;

impl ObstacleMemory {
    /// The heading to drive instead of `goal_rad` (both rad, robot frame): `goal_rad` itself when
    /// its path is free for `lookahead_m`, else the candidate within `±max_rad` (steps of
    /// `step_rad`) nearest to the goal whose path is free that far, else the candidate with the
    /// longest free path (nearest to the goal on a tie). A vector-field-histogram-style
    /// choice of gap; MOFIS still slows and swerves for what is close. In a lane (the corridor
    /// from the map, [`set_lane`](Self::set_lane)), a path is free only as far as it stays inside it
    /// ([`lane_free_distance`](Self::lane_free_distance)): a doorway, or a wall not yet seen,
    /// is no gap to steer through.
    pub fn steer(&self, goal_rad: f64, lookahead_m: f64, max_rad: f64, step_rad: f64) -> f64 {
        let free_distance = |h: f64| self.free_in_lane(h, lookahead_m);
        if free_distance(goal_rad) >= lookahead_m {
            return goal_rad;
        }
        let n = (max_rad / step_rad).round() as i32;
        let mut best: Option<(bool, f64, f64)> = None; // (free enough, free distance, heading)
        for k in -n..=n {
            let h = k as f64 * step_rad;
            let free = free_distance(h);
            let ok = free >= lookahead_m;
            let better = match best {
                None => true,
                Some((bok, bfree, bh)) => match (ok, bok) {
                    (true, false) => true,
                    (false, true) => false,
                    (true, true) => (h - goal_rad).abs() < (bh - goal_rad).abs(),
                    (false, false) => {
                        free > bfree + 1e-9
                            || ((free - bfree).abs() <= 1e-9 && (h - goal_rad).abs() < (bh - goal_rad).abs())
                    }
                },
            };
            if better {
                best = Some((ok, free, h));
            }
        }
        best.map_or(goal_rad, |(_, _, h)| h)
    }

    /// A heading correction that keeps the robot off side surfaces, rad (+ left): the nearest
    /// occupied cells on each side from the robot's back (`robot_radius_m` behind its origin) to
    /// `window_m` ahead and within `reach_m` to the side give the
    /// clearances `l` and `r`; when the smaller is below `reach_m`, the robot steers toward the
    /// middle, `atan2((l − r) / 2, lookahead_m)`, at most `max_rad`. A side with nothing seen
    /// counts as `reach_m` away. In a corridor this centres the robot, in a doorway too.
    pub fn centring(&self, window_m: f64, reach_m: f64, lookahead_m: f64, max_rad: f64) -> f64 {
        let (mut left, mut right) = (reach_m, reach_m);
        // the lane's walls, where the wall band leaves the walls to it
        if let Some(lane) = self.walled_lane() {
            left = left.min((lane.half_width_m - lane.left_m).max(0.0));
            right = right.min((lane.half_width_m + lane.left_m).max(0.0));
        }
        for [f, l] in self.banded_cells().filter(|c| !c.1).map(|c| c.0) {
            // beside the robot (down to its back) counts too: that is where a wall it scrapes is
            if !(-self.params.robot_radius_m..=window_m).contains(&f) {
                continue;
            }
            if l > 0.0 {
                left = left.min(l);
            } else {
                right = right.min(-l);
            }
        }
        if left.min(right) >= reach_m {
            return 0.0;
        }
        (0.5 * (left - right)).atan2(lookahead_m).clamp(-max_rad, max_rad)
    }
}
