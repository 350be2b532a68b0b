//! Planning a way past what blocks the straight path: a shortest-path search over a small grid
//! around the robot, in the robot's frame, with the footprint's clearance built in.
//!
//! Straight-ray steering ([`ObstacleMemory::steer`]) picks the free ray nearest the goal, and
//! when none is free it takes the longest: into a gap the footprint guard then stands the robot
//! in front of, with a standstill escape that turns back and returns. The planner instead
//! searches for a way the footprint fits through, against the same cells the guard counts, the
//! lane and the door's wall: where no way fits it stays short of the gap instead of driving
//! into it.

use super::*;
use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// The planning grid reaches this far behind, ahead and to each side of the robot's origin, m.
const PLAN_BEHIND_M: f64 = 0.6;
const PLAN_AHEAD_M: f64 = 4.0;
const PLAN_SIDE_M: f64 = 2.6;
/// Cost of a metre through a cell the footprint does not fit in (against the guard's cells, the
/// lane's band or the door's wall), in metres of free travel: no way worth taking crosses one.
const BLOCKED_COST: f64 = 100.0;
/// Cost of a metre through a cell with no clearance to spare, falling linearly to nothing at the
/// path margin: a way past a box keeps to the middle of its gap.
const NEAR_COST: f64 = 3.0;
/// A metre left between the way's end and the target costs this many metres of free travel: a
/// detour up to this many times the progress it makes is worth taking.
const LEFT_WEIGHT: f64 = 2.0;
/// A way that brings the robot less than this much nearer the target (or half the distance to
/// it, when nearer) leads nowhere: it has no heading. Its first steps only pick among the cells
/// around the robot, and they swing from one side to the other as the robot turns.
const MIN_PROGRESS_M: f64 = 0.3;

/// Where the way should end, for [`ObstacleMemory::plan_heading`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlanTarget {
    /// The goal's bearing, rad, robot frame (+ left) ...
    pub bearing_rad: f64,
    /// ... and its distance, m: the way ends as near to that point as it can.
    pub distance_m: f64,
}

impl ObstacleMemory {
    /// The heading to drive to follow the cheapest way toward `target` (rad, robot frame, +
    /// left), or `None` when the way does not leave the robot's cell or leads no nearer the
    /// target ([`plan_way`](Self::plan_way)).
    pub fn plan_heading(&self, target: PlanTarget, guard: &GuardCells) -> Option<f64> {
        self.plan_way(target, guard).aim.map(|[f, l]| l.atan2(f))
    }

    /// The cheapest way toward `target` for [`plan_heading`](Self::plan_heading), and the
    /// point of it the robot aims at: the farthest it sees in a straight line, through cells
    /// that cost no more than the way's own up to there (the grid's steps of 45° pulled straight).
    ///
    /// The grid has the memory's cell size, in the robot's frame. A cell is blocked where the
    /// footprint, widened by `guard.clearance_m` and half a cell, would reach a cell the guard
    /// counts ([`GuardCells`]), where it would leave the lane's band
    /// ([`lane_free_distance`](Self::lane_free_distance)'s) or meet the door's wall; what the
    /// robot is already that near blocks only the cells nearer to it still, so the robot can
    /// always drive away from what it is beside. Blocked cells cost `BLOCKED_COST` (metres of
    /// free travel) a metre. A cell nearer an occupied cell than the path margin
    /// (`robot_radius_m + path_margin_m`) costs more the nearer. The way ends at the cell that
    /// minimises its cost plus `LEFT_WEIGHT` times the straight distance from there to the
    /// target, so a target with no way to it is approached as near as the cells let.
    pub fn plan_way(&self, target: PlanTarget, guard: &GuardCells) -> Way {
        let p = &self.params;
        let h = p.cell_m;
        let (i0, i1) = (-(PLAN_BEHIND_M / h).ceil() as i32, (PLAN_AHEAD_M / h).ceil() as i32);
        let j1 = (PLAN_SIDE_M / h).ceil() as i32;
        let (ni, nj) = ((i1 - i0 + 1) as usize, (2 * j1 + 1) as usize);
        let index = |i: i32, j: i32| (i - i0) as usize * nj + (j + j1) as usize;
        let at = |i: i32, j: i32| [i as f64 * h, j as f64 * h];
        // the cost of a metre through each cell: 1, plus nearness, or blocked
        let mut cost = vec![1.0f64; ni * nj];
        let hard = p.robot_radius_m + guard.clearance_m + 0.5 * h;
        let soft = p.robot_radius_m + p.path_margin_m;
        let stamp = |cost: &mut Vec<f64>, [f, l]: [f64; 2], radius: f64, near: bool| {
            let r = (radius / h).ceil() as i32 + 1;
            let (ci, cj) = ((f / h).round() as i32, (l / h).round() as i32);
            for i in (ci - r).max(i0)..=(ci + r).min(i1) {
                for j in (cj - r).max(-j1)..=(cj + r).min(j1) {
                    let [x, y] = at(i, j);
                    let d = (x - f).hypot(y - l);
                    let c = &mut cost[index(i, j)];
                    match near {
                        false if d < radius => *c = BLOCKED_COST,
                        true if d < radius && *c < BLOCKED_COST => {
                            *c = c.max(1.0 + NEAR_COST * (1.0 - (d - hard).max(0.0) / (radius - hard)))
                        }
                        _ => {}
                    }
                }
            }
        };
        let near = PLAN_AHEAD_M.hypot(PLAN_SIDE_M) + hard;
        // what the robot is already nearer than that blocks only the cells nearer still: it
        // may drive away from what it is beside (as the guard lets it)
        let within = |d0: f64, radius: f64| radius.min(d0 - 0.5 * h);
        for cell in self.guard_cells(guard, near) {
            stamp(&mut cost, cell, within(cell[0].hypot(cell[1]), hard), false);
        }
        for (cell, banded) in self.banded_cells() {
            if !banded {
                stamp(&mut cost, cell, soft, true);
            }
        }
        // the lane's band (or as far out as the robot already is) and the door's wall, from the map
        let lane = self.lane.as_ref().map(|lane| (lane.offset_of(), self.lane_band(lane).max(lane.left_m.abs())));
        let door = within(self.door_wall_distance([0.0, 0.0]), p.robot_radius_m + p.lane_margin_m);
        for i in i0..=i1 {
            for j in -j1..=j1 {
                let cell = at(i, j);
                let outside = lane.is_some_and(|(offset, band)| offset(cell).abs() > band);
                if outside || self.door_wall_distance(cell) < door {
                    cost[index(i, j)] = BLOCKED_COST;
                }
            }
        }
        // Dijkstra from the robot's cell over 8-neighbours; costs in µm keep the heap's order total
        let mut dist = vec![u64::MAX; ni * nj];
        let mut from = vec![usize::MAX; ni * nj];
        let start = index(0, 0);
        dist[start] = 0;
        let mut heap = BinaryHeap::from([Reverse((0u64, 0i32, 0i32))]);
        while let Some(Reverse((d, i, j))) = heap.pop() {
            let k = index(i, j);
            if d > dist[k] {
                continue;
            }
            for (di, dj) in [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1)] {
                let (a, b) = (i + di, j + dj);
                if !(i0..=i1).contains(&a) || !(-j1..=j1).contains(&b) {
                    continue;
                }
                let n = index(a, b);
                let step = h * f64::from(di * di + dj * dj).sqrt() * 0.5 * (cost[k] + cost[n]);
                let nd = d + (step * 1e6) as u64;
                if nd < dist[n] {
                    dist[n] = nd;
                    from[n] = k;
                    heap.push(Reverse((nd, a, b)));
                }
            }
        }
        // the end: the cheapest way plus the straight distance left to the target, weighed
        // more than the way's own metres so that getting nearer pays
        let (ts, tc) = target.bearing_rad.sin_cos();
        let goal = [target.distance_m * tc, target.distance_m * ts];
        let mut end = start;
        let mut best = f64::INFINITY;
        for i in i0..=i1 {
            for j in -j1..=j1 {
                let k = index(i, j);
                if dist[k] == u64::MAX {
                    continue;
                }
                let [f, l] = at(i, j);
                let total = dist[k] as f64 * 1e-6 + LEFT_WEIGHT * (goal[0] - f).hypot(goal[1] - l);
                if total < best - 1e-9 {
                    best = total;
                    end = k;
                }
            }
        }
        let cell = |k: usize| ((k / nj) as i32 + i0, (k % nj) as i32 - j1);
        // the robot's own cell is at the origin, the target's distance from it
        let (i, j) = cell(end);
        let [f, l] = at(i, j);
        let leads = target.distance_m - (goal[0] - f).hypot(goal[1] - l) >= MIN_PROGRESS_M.min(0.5 * target.distance_m);
        let mut way = Vec::new();
        let mut k = end;
        while k != start {
            way.push(k);
            k = from[k];
        }
        way.reverse();
        // the straight segment from the robot to a cell of the way, in half-cell steps, costs
        // no more anywhere than the way does up to that cell (none is aimed at on a way that
        // leads nowhere)
        let mut dearest = cost[start];
        let mut aim = None;
        for &k in way.iter().filter(|_| leads) {
            dearest = dearest.max(cost[k]);
            let (i, j) = cell(k);
            let n = 2 * i.abs().max(j.abs());
            let seen = (1..=n).all(|m| {
                let t = m as f64 / n as f64;
                let (a, b) = ((i as f64 * t).round() as i32, (j as f64 * t).round() as i32);
                cost[index(a, b)] <= dearest + 1e-9
            });
            if seen {
                aim = Some(at(i, j));
            }
        }
        Way {
            cells: way
                .into_iter()
                .map(|k| {
                    let (i, j) = cell(k);
                    at(i, j)
                })
                .collect(),
            aim,
        }
    }
}

/// A way through the planning grid ([`ObstacleMemory::plan_way`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Way {
    /// The centres of its cells after the robot's own, in order, robot frame (forward, left),
    /// m; empty when it does not leave the robot's cell.
    pub cells: Vec<[f64; 2]>,
    /// The point the robot aims at; `None` when the way is empty or leads no nearer the target.
    pub aim: Option<[f64; 2]>,
}
