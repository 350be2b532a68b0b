//! How far a path is free: straight bands, the footprint's arcs, the lane and the door's wall.

use super::*;
use std::collections::BTreeSet;

impl ObstacleMemory {
    /// How far the robot's origin at `p` (robot frame, m) is from the door's wall either side
    /// of the opening ([`set_doorway`](Self::set_doorway)); infinite without a door.
    pub(super) fn door_wall_distance(&self, [f, l]: [f64; 2]) -> f64 {
        let Some(door) = &self.doorway else { return f64::INFINITY };
        let (s, c) = door.angle_rad.sin_cos();
        let (df, dl) = (f - door.centre_m[0], l - door.centre_m[1]);
        // along the way through the door (0 at its wall) and across it
        let (along, across) = (df * c + dl * s, (-df * s + dl * c).abs());
        match across >= door.half_width_m {
            true => along.abs(),
            false => along.hypot(door.half_width_m - across),
        }
    }

    /// How far the robot can drive along a path `at(s)` (its origin after `s` m, robot frame)
    /// before its footprint, widened by `lane_margin_m`, meets the door's wall, in steps of
    /// [`ARC_STEP_M`] up to `reach_m`. A robot already that near is free to drive away from it.
    fn door_free(&self, reach_m: f64, at: impl Fn(f64) -> [f64; 2]) -> f64 {
        if self.doorway.is_none() || reach_m.is_nan() || reach_m <= 0.0 {
            return reach_m.max(0.0);
        }
        let body = self.params.robot_radius_m + self.params.lane_margin_m;
        let d0 = self.door_wall_distance([0.0, 0.0]);
        let steps = (reach_m / ARC_STEP_M).ceil().max(1.0) as usize;
        for k in 1..=steps {
            let s = reach_m * k as f64 / steps as f64;
            let d = self.door_wall_distance(at(s));
            if d < body && d < d0 - 1e-3 {
                return reach_m * (k - 1) as f64 / steps as f64;
            }
        }
        reach_m
    }

    /// How far the robot can drive straight ahead before its footprint, widened by
    /// `lane_margin_m`, meets the door's wall ([`set_doorway`](Self::set_doorway)), up to
    /// `lookahead_m`: for the stopping gate.
    pub fn door_free_ahead(&self, lookahead_m: f64) -> f64 {
        self.door_free(lookahead_m, |d| [d, 0.0])
    }

    /// How far the robot can drive along `heading` (rad, robot frame, + left) before its
    /// footprint widened by `path_margin_m` meets an occupied cell, up to `lookahead_m`.
    pub fn free_distance(&self, heading: f64, lookahead_m: f64) -> f64 {
        self.free_width(heading, self.params.robot_radius_m + self.params.path_margin_m, lookahead_m)
    }

    /// The footprint guard's query ([`crate::mofis::MofisParams::guard_evidence`]): how far
    /// the robot's origin can drive along an arc of `curvature` (1/m, + = left) before its
    /// footprint, widened by `guard.clearance_m`, reaches the centre of a cell the guard counts
    /// ([`GuardCells`]: confirmed once, still with at least `guard.min_evidence`, occupied or
    /// fading, wall band or not) that the motion brings nearer; up to `reach_m`. A cell already
    /// inside the widened footprint stops only motion toward it, so the robot can always drive
    /// away from what it is beside. `aside`: only the cells out of the camera's field of view
    /// count (the guard's brake: what is in view is measured again, and the stopping gate's).
    pub fn arc_free(&self, curvature: f64, reach_m: f64, guard: &GuardCells, aside: bool) -> f64 {
        let arc = |s: f64| match curvature.abs() < 1e-6 {
            true => [s, 0.0],
            false => [(curvature * s).sin() / curvature, (1.0 - (curvature * s).cos()) / curvature],
        };
        self.path_free(reach_m, arc, guard, aside)
    }

    /// [`arc_free`](Self::arc_free) for a straight path along `heading` (rad, robot frame, +
    /// left) after turning to it on the spot, every cell counted, in view or not: where a
    /// standstill escape may drive without the guard stopping it again.
    pub fn heading_free(&self, heading: f64, reach_m: f64, guard: &GuardCells) -> f64 {
        let (sin, cos) = heading.sin_cos();
        self.path_free(reach_m, |s| [s * cos, s * sin], guard, false)
    }

    /// How far the robot's origin can drive along the path `at(s)` (its origin after `s` m,
    /// robot frame) before its footprint meets a cell the guard counts or the door's wall
    /// ([`arc_free`](Self::arc_free)).
    fn path_free(&self, reach_m: f64, at: impl Fn(f64) -> [f64; 2], guard: &GuardCells, aside: bool) -> f64 {
        if reach_m.is_nan() || reach_m <= 0.0 {
            return 0.0;
        }
        let half_fov = self.half_fov_rad;
        let body = self.params.robot_radius_m + guard.clearance_m;
        let near = reach_m + body;
        let steps = (reach_m / ARC_STEP_M).ceil().max(1.0) as usize;
        // the door's wall, from the map, counts wherever it is
        let mut free = self.door_free(reach_m, &at);
        for [f, l] in self.guard_cells(guard, near) {
            let d0 = f.hypot(l);
            if aside && view_sector(f, l, half_fov).is_some() {
                continue;
            }
            for k in 1..=steps {
                let s = reach_m * k as f64 / steps as f64;
                if s >= free {
                    break;
                }
                let [x, y] = at(s);
                let d = (f - x).hypot(l - y);
                if d < body && d < d0 - 1e-3 {
                    free = free.min(reach_m * (k - 1) as f64 / steps as f64);
                    break;
                }
            }
        }
        free
    }

    /// The cells the footprint guard counts within `near` m of the robot, robot frame: the
    /// confirmed ones with at least `min_evidence`; with `cluster`, also every confirmed cell
    /// joined to one of them through confirmed cells (8-neighbours, within `near`), however
    /// faded. An obstacle out of view fades cell by cell, and the traced grazes touched a faded
    /// cell between two held ones: the cluster is held as one shape while any of its cells is.
    /// With `min_cells` above 1, only the cells of a cluster of at least that many confirmed
    /// cells (near or not) count: a lone confirmed cell in free space is a mismatched block's
    /// depth seen twice, and one beside the robot, out of view where nothing clears it, stood
    /// a braking robot still.
    pub(super) fn guard_cells(&self, guard: &GuardCells, near: f64) -> Vec<[f64; 2]> {
        let close = |key: (i32, i32)| {
            let [f, l] = self.to_robot(key);
            f.hypot(l) <= near
        };
        let solid = |key: (i32, i32)| self.cluster_reaches(key, guard.min_cells);
        let held: Vec<(i32, i32)> = self
            .cells
            .iter()
            .filter(|&(&key, c)| c.confirmed && c.evidence >= guard.min_evidence && close(key))
            .map(|(&key, _)| key)
            .filter(|&key| solid(key))
            .collect();
        if !guard.cluster {
            return held.into_iter().map(|key| self.to_robot(key)).collect();
        }
        let mut joined: BTreeSet<(i32, i32)> = held.iter().copied().collect();
        let mut stack = held;
        while let Some(key) = stack.pop() {
            for next in neighbours(key) {
                if !joined.contains(&next) && self.cells.get(&next).is_some_and(|c| c.confirmed) && close(next) {
                    joined.insert(next);
                    stack.push(next);
                }
            }
        }
        joined.into_iter().map(|key| self.to_robot(key)).collect()
    }

    /// Whether the confirmed cell `key` is one of a cluster (joined through confirmed
    /// 8-neighbours) of at least `n` confirmed cells.
    fn cluster_reaches(&self, key: (i32, i32), n: usize) -> bool {
        if n <= 1 {
            return true;
        }
        let mut seen = BTreeSet::from([key]);
        let mut stack = vec![key];
        while let Some(at) = stack.pop() {
            for next in neighbours(at) {
                if self.cells.get(&next).is_some_and(|c| c.confirmed) && seen.insert(next) {
                    if seen.len() >= n {
                        return true;
                    }
                    stack.push(next);
                }
            }
        }
        false
    }

    /// How far a band `half` wide (m) either side of `heading` (rad, robot frame) is free of
    /// occupied cells ahead of the robot's origin, up to `lookahead_m`; measured from the origin.
    /// Past the stop ([`set_stop`](Self::set_stop)) the band ends in a half-disc of radius
    /// `half` around the point where it crosses the stop line (across the current heading).
    pub fn free_width(&self, heading: f64, half: f64, lookahead_m: f64) -> f64 {
        let p = &self.params;
        let (s, c) = heading.sin_cos();
        let mut free = lookahead_m;
        // the stop is a line across the current heading: a path turned by `heading` meets it
        // 1 / cos(heading) farther (and a path turned by a right angle or more never)
        let stop = if c > 0.05 { self.stop_m / c } else { f64::INFINITY };
        for ([f, l], banded) in self.banded_cells() {
            let along = f * c + l * s;
            let across = (-f * s + l * c).abs();
            let past = (along - stop).max(0.0);
            // within `half` of the path: across it, or past the stop within `half` of its end
            if past.hypot(across) <= half && along > -p.behind_m && !banded {
                free = free.min(along.max(0.0));
            }
        }
        free
    }

    /// How far the robot can drive along `heading` (rad, robot frame) before its footprint,
    /// widened by `lane_margin_m`, leaves `lane` going outward, up to `lookahead_m`. A robot
    /// already outside is free to drive back in.
    pub fn lane_free_distance(&self, lane: &Lane, heading: f64, lookahead_m: f64) -> f64 {
        let band = self.lane_band(lane);
        let rate = (heading - lane.angle_rad).sin();
        let exit = match rate {
            r if r > 1e-9 => (band - lane.left_m) / r,
            r if r < -1e-9 => (band + lane.left_m) / -r,
            _ => f64::INFINITY,
        };
        exit.clamp(0.0, lookahead_m)
    }

    /// How far either side of `lane`'s centre line the robot's origin may go: the footprint,
    /// widened by `lane_margin_m`, stays inside the corridor, m.
    pub(super) fn lane_band(&self, lane: &Lane) -> f64 {
        (lane.half_width_m - self.params.robot_radius_m - self.params.lane_margin_m).max(0.0)
    }

    /// How far the path along `heading` (rad, robot frame) is free, up to `lookahead_m`: of
    /// occupied cells ([`free_distance`](Self::free_distance)) and, in a lane
    /// ([`set_lane`](Self::set_lane)), inside it ([`lane_free_distance`](Self::lane_free_distance)).
    pub fn free_in_lane(&self, heading: f64, lookahead_m: f64) -> f64 {
        let seen = self.free_distance(heading, lookahead_m);
        let seen = self.lane.as_ref().map_or(seen, |l| seen.min(self.lane_free_distance(l, heading, lookahead_m)));
        let (s, c) = heading.sin_cos();
        seen.min(self.door_free(lookahead_m, |d| [d * c, d * s]))
    }
}

/// The eight cells around `(i, j)`.
fn neighbours((i, j): (i32, i32)) -> impl Iterator<Item = (i32, i32)> {
    (-1..=1).flat_map(move |di| (-1..=1).map(move |dj| (i + di, j + dj))).filter(move |&k| k != (i, j))
}

/// What the footprint guard counts, and how close it lets the robot come
/// ([`ObstacleMemory::arc_free`]; the `guard_*` fields of [`crate::mofis::MofisParams`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GuardCells {
    /// Kept beyond the robot's radius, m.
    pub clearance_m: f64,
    /// The confirmed cells with at least this evidence are held.
    pub min_evidence: f64,
    /// Also every confirmed cell joined to a held one, however faded.
    pub cluster: bool,
    /// Only cells of a cluster of at least this many confirmed cells count (1: every cell).
    pub min_cells: usize,
}
