//! How good the obstacle perception is, scored against the simulated world (diagnosis only:
//! nothing here reaches the pipeline).
//!
//! - **Surface points** ([`SurfacePoint`], what the obstacle memory takes in): a
//!   point's range is compared with the true range along its bearing, found by sphere tracing
//!   the world's clearance from the robot's true pose. The ray is 2-D (it ignores height), so a
//!   point on a wall seen over a low box counts as wrong. A point is *good* when its range is
//!   within [`RANGE_TOLERANCE`] of the true one.
//! - **Occupied cells** of the obstacle memory within [`CELL_REACH_M`]: a cell is a *ghost* when
//!   its centre, placed with the true pose, is farther than [`GHOST_M`] from every surface (the
//!   odometry's drift counts against the memory too).
//! - **Obstacles held**: in each step where the robot's origin is within [`HELD_NEAR_M`] of an
//!   obstacle (box, person), whether the memory holds an occupied cell within [`GHOST_M`] of
//!   that obstacle. The faces a robot passes leave the camera's view; this says how often the
//!   memory still has them when it matters.
//! - **TPO seen**: in each step where the ground truth in front of the camera is a TPO (wall,
//!   corner, door, corridor), whether OFFIS said `none` there: landmarks the planner could not
//!   use, e.g. while the robot turns or stands.

use crate::offis::points::SurfacePoint;
use mocks::{Pose, World};
use serde::Serialize;

/// A point is good when `|measured / true − 1|` is at most this.
pub const RANGE_TOLERANCE: f64 = 0.15;
/// Only points whose true range is at most this count, m (the memory's reach).
pub const POINT_REACH_M: f64 = 4.0;
/// Occupied cells within this range of the robot are scored, m.
pub const CELL_REACH_M: f64 = 2.0;
/// A cell centre farther than this from every surface is a ghost, m (a cell is 0.1 m).
pub const GHOST_M: f64 = 0.15;
/// An obstacle counts for [`Quality`]'s held score while the robot's origin is this near, m (the
/// robot's radius, 0.18 m, plus half a metre).
pub const HELD_NEAR_M: f64 = 0.68;

/// Counts over a run; the fractions go into the summary.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Quality {
    points: u64,
    points_good: u64,
    cells: u64,
    ghosts: u64,
    near: u64,
    held: u64,
    tpo_truth: u64,
    tpo_none: u64,
    none_truth: u64,
    none_named: u64,
}

/// The fractions, for the JSON summary (`None` when nothing was scored).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct QualitySummary {
    /// Surface points whose range is within 15 % of the true range along their bearing.
    pub points_range_ok: Option<f64>,
    /// Occupied cells within 2 m farther than 0.15 m from every surface (cell-frames).
    pub cells_ghost: Option<f64>,
    /// Steps with an obstacle within 0.68 m of the robot's origin in which the memory held an
    /// occupied cell on it (obstacle-steps).
    pub obstacles_held: Option<f64>,
    /// Steps whose ground truth is a TPO (wall, corner, door, corridor) in which OFFIS said
    /// `none`, as a share of those steps.
    pub tpo_none_share: Option<f64>,
    /// Steps whose ground truth is `none` in which OFFIS named a TPO, as a share of those steps
    /// (the price of holding a TPO through pairs that cannot see it).
    pub none_named_share: Option<f64>,
}

impl Quality {
    /// Scores one step: the robot's true pose, the step's surface points and the memory's
    /// occupied cells, both in the robot frame (forward, left).
    pub fn observe(&mut self, world: &World, pose: &Pose, points: &[SurfacePoint], cells: &[[f64; 2]]) {
        for p in points {
            let bearing = pose.yaw + p.left.atan2(p.forward);
            let Some(truth) = true_range(world, [pose.x, pose.y], bearing) else { continue };
            if truth > POINT_REACH_M {
                continue;
            }
            self.points += 1;
            let measured = p.forward.hypot(p.left);
            self.points_good += u64::from((measured / truth - 1.0).abs() <= RANGE_TOLERANCE);
        }
        for c in cells.iter().filter(|c| c[0].hypot(c[1]) <= CELL_REACH_M) {
            let [cx, cy] = pose.transform(*c);
            self.cells += 1;
            self.ghosts += u64::from(world.clearance(cx, cy).distance_m > GHOST_M);
        }
        // the robot first, then the occupied cells, placed with the true pose
        let at: Vec<[f64; 2]> =
            std::iter::once([pose.x, pose.y]).chain(cells.iter().map(|c| pose.transform(*c))).collect();
        let d = world.obstacle_distances(&at);
        for (i, _) in d[0].iter().enumerate().filter(|(_, d)| **d <= HELD_NEAR_M) {
            self.near += 1;
            self.held += u64::from(d[1..].iter().any(|cell| cell[i] <= GHOST_M));
        }
    }

    /// Scores one step's TPO: whether the truth is one (not `none`), and whether OFFIS said `none`.
    pub fn observe_tpo(&mut self, truth_is_tpo: bool, said_none: bool) {
        if truth_is_tpo {
            self.tpo_truth += 1;
            self.tpo_none += u64::from(said_none);
        } else {
            self.none_truth += 1;
            self.none_named += u64::from(!said_none);
        }
    }

    pub fn summary(&self) -> QualitySummary {
        let frac = |n: u64, d: u64| (d > 0).then(|| (n as f64 / d as f64 * 1000.0).round() / 1000.0);
        QualitySummary {
            points_range_ok: frac(self.points_good, self.points),
            cells_ghost: frac(self.ghosts, self.cells),
            obstacles_held: frac(self.held, self.near),
            tpo_none_share: frac(self.tpo_none, self.tpo_truth),
            none_named_share: frac(self.none_named, self.none_truth),
        }
    }
}

/// Distance from `from` along `bearing` to the first surface (sphere tracing the clearance),
/// `None` beyond 8 m.
fn true_range(world: &World, from: [f64; 2], bearing: f64) -> Option<f64> {
    let (s, c) = bearing.sin_cos();
    let mut d = 0.0;
    for _ in 0..256 {
        let step = world.clearance(from[0] + d * c, from[1] + d * s).distance_m;
        if step < 0.005 {
            return Some(d);
        }
        d += step;
        if d > 8.0 {
            return None;
        }
    }
    Some(d)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_are_scored_against_the_true_range_and_cells_against_the_surfaces() {
        // a corridor along +x with walls 1 m either side of y = 0; the robot in its middle
        let world = mocks::scene::corridor(2.0, 10.0).world;
        let pose = Pose::new(2.0, 0.0, 0.0);
        assert!((world.clearance(pose.x, pose.y).distance_m - 1.0).abs() < 1e-9);
        let wall = |left: f64| SurfacePoint { forward: 0.0, left, up: 0.5, radial_px: 3.0 };
        let mut q = Quality::default();
        // 1.0 m to the left wall: 1.05 is good, 1.3 is not
        q.observe(&world, &pose, &[wall(1.05), wall(1.3)], &[[0.0, 0.95], [0.5, 0.0]]);
        let s = q.summary();
        assert_eq!(s.points_range_ok, Some(0.5), "{s:?}");
        assert_eq!(s.cells_ghost, Some(0.5), "the cell in mid-corridor is a ghost: {s:?}");
        assert_eq!(
            Quality::default().summary(),
            QualitySummary {
                points_range_ok: None,
                cells_ghost: None,
                obstacles_held: None,
                tpo_none_share: None,
                none_named_share: None
            }
        );
    }

    #[test]
    fn the_tpo_share_counts_none_only_where_the_truth_is_a_tpo() {
        let mut q = Quality::default();
        q.observe_tpo(true, true);
        q.observe_tpo(true, false);
        q.observe_tpo(true, false);
        q.observe_tpo(true, false);
        q.observe_tpo(false, true);
        q.observe_tpo(false, false);
        assert_eq!(q.summary().tpo_none_share, Some(0.25));
        assert_eq!(q.summary().none_named_share, Some(0.5), "one of the two steps without a TPO named one");
    }

    #[test]
    fn an_obstacle_beside_the_robot_is_held_while_a_cell_lies_on_it() {
        // a person (r 0.3 m) 0.6 m left of the robot's centre in the corridor: within 0.68 m
        let mut world = mocks::scene::corridor(2.0, 10.0).world;
        world.cylinders.push(mocks::world::Cylinder { name: "p".into(), center: [2.0, 0.6], radius: 0.3, height: 1.7 });
        let pose = Pose::new(2.0, 0.0, 0.0);
        let mut q = Quality::default();
        // a cell on its near face (0.3 m left), then only a cell in mid-corridor ahead
        q.observe(&world, &pose, &[], &[[0.0, 0.32]]);
        q.observe(&world, &pose, &[], &[[0.5, -0.4]]);
        assert_eq!(q.summary().obstacles_held, Some(0.5), "{:?}", q.summary());
        // 1 m away the person does not count
        let mut far = Quality::default();
        far.observe(&world, &Pose::new(2.0, -0.5, 0.0), &[], &[]);
        assert_eq!(far.summary().obstacles_held, None);
    }
}
