//! The obstacle memory: a small evidence grid on the floor, in the odometry frame, that turns
//! OFFIS's per-frame surface points into the obstacle MOFIS avoids.
//!
//! One frame of block-matching flow locates an obstacle only where its flow is strong and clean
//! enough, so a single frame's obstacle flickers; and a camera with a 53° field of view loses an
//! obstacle from sight while the robot is still beside it, exactly when turning back to the goal
//! would clip it. The memory fixes both, the way a local costmap does on a ROS robot, from
//! nothing but the flow's located points and the odometry:
//!
//! - the robot's pose in its odometry frame is integrated from `(v, ω)` every step;
//! - each step's points ([`crate::offis::points`]) vote once per `cell_m` cell (several blocks in
//!   one cell count once), adding 1 to the cell's evidence (capped at `max_evidence`), or, with
//!   `vote_full_radial_px` set, the sum of its points' radial flow / `vote_full_radial_px`, at
//!   most 1 (a depth from weak flow is the least certain);
//! - evidence decays with a half-life of `half_life_view_s` where the camera *sees through* the
//!   cell now (a surface was measured farther away on the cell's bearing, by a ray that passes
//!   over the cell lower than the top of what was seen in it: the cell is free),
//!   `half_life_aside_s` where it is in view but not measured (a close textureless face, a
//!   bearing with no reliable flow, a robot not driving forward), and out of view (beside or
//!   behind the robot) per `out_half_life_m` driven, `out_half_life_rad` turned and
//!   `out_half_life_s` of time: there nothing confirms or clears it, and what makes it wrong
//!   is the dead-reckoning drift, so a robot that stands beside an obstacle keeps it (fading
//!   it with time alone made robots forget what they stood next to, then drive into it);
//!   cells beyond `max_range_m` are forgotten;
//! - a cell is *occupied* when its evidence reaches `occupied`: seen in at least two frames.
//!
//! The obstacles handed to MOFIS are the most threatening occupied cells ahead of the robot's
//! origin, one on each side of its heading: the nearest in its path (within `robot_radius_m +
//! path_margin_m` of the heading line), or just beside it (in a band `side_margin_m` wide that
//! narrows ahead), reported farther away the farther beyond the path it lies, with its bearing
//! from the robot's origin ([`ObstacleMemory::threat_sides`]). Walls and boxes alike: a wall
//! the robot drives at is in its path, a corridor wall beside it is not. In a corridor from the
//! map ([`ObstacleMemory::set_lane`]), cells within `wall_band_m` of its walls are the walls',
//! and the lane, not the cells, keeps the robot off the walls.
//!
//! Pure and deterministic: the cells live in a `BTreeMap`, so the same inputs give the same
//! outputs in the same order (replay is bit-exact).

use crate::offis::points::SurfacePoint;
use crate::pafsis::{Doorway, Lane};
use crate::perception::Obstacle;
use hal::BodyVelocity;
use std::collections::BTreeMap;

mod free;
mod grid;
mod params;
mod plan;
mod steer;
#[cfg(test)]
mod tests;
mod threats;

pub use free::GuardCells;
pub use params::MemoryParams;
pub use plan::{PlanTarget, Way};
pub use threats::nearer;

/// The robot's pose in the memory's (odometry) frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Pose {
    x: f64,
    y: f64,
    yaw: f64,
}

/// The evidence grid and the robot's pose in it.
#[derive(Clone, Debug)]
pub struct ObstacleMemory {
    params: MemoryParams,
    /// Half of the camera's horizontal field of view, rad.
    half_fov_rad: f64,
    /// Height of the camera's optical centre above the floor, m (for the rays over cells).
    camera_height_m: f64,
    pose: Pose,
    cells: BTreeMap<(i32, i32), Cell>,
    /// Cells voted for this step, per point: the height of the point, m, and its vote.
    touched: Vec<((i32, i32), f64, f64)>,
    /// The points measured this step per bearing sector: (range, height above the floor), m.
    seen: Vec<Vec<(f64, f64)>>,
    /// The corridor the robot is in, from the map ([`set_lane`](Self::set_lane)).
    lane: Option<Lane>,
    /// The door the robot is going through, from the map ([`set_doorway`](Self::set_doorway)).
    doorway: Option<Doorway>,
    /// How far ahead the plan stops the robot's origin, m ([`set_stop`](Self::set_stop)).
    stop_m: f64,
}

/// One grid cell: its evidence, and the top of what was seen in it.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Cell {
    evidence: f64,
    /// Marked by a contact ([`ObstacleMemory::mark_contact`]), not seen.
    contact: bool,
    /// Whether it was ever occupied (evidence at `occupied`): a cell of something seen over
    /// frames, not one noisy point; the footprint guard keeps such cells while they fade.
    confirmed: bool,
    /// The highest point that voted for the cell, m above the floor: a ray from the camera that
    /// passes over the cell lower than this would have hit what is there.
    top_m: f64,
}

/// A cell `side_margin_m` beyond the robot's path is reported this much farther away than it is,
/// m: far, for MOFIS's rule bases (their `far` starts at 2–3 m).
pub const SIDE_FADE_M: f64 = 3.0;

/// The side band is `side_margin_m` wide beside the robot and narrows linearly to nothing this
/// far ahead, m: the jitter of the heading moves near cells in and out of the path, and a wall
/// 2 m ahead half a metre beside the path is no reason to swerve.
pub const SIDE_REACH_M: f64 = 1.2;

/// Step along an arc in [`ObstacleMemory::arc_free`], m.
const ARC_STEP_M: f64 = 0.02;

/// Bearing sectors across the field of view for the seen-through test.
const SECTORS: usize = 24;

/// The sector of `bearing` within a field of view of `±half_fov`, if inside.
fn sector(bearing: f64, half_fov: f64) -> Option<usize> {
    let x = (bearing + half_fov) / (2.0 * half_fov) * SECTORS as f64;
    (x >= 0.0 && x < SECTORS as f64).then_some(x as usize)
}

/// The sector of a point (`f` forward, `l` left of the robot, m) in the camera's view, if it is
/// in view: ahead and within `±half_fov`.
fn view_sector(f: f64, l: f64, half_fov: f64) -> Option<usize> {
    if f > 0.0 { sector(l.atan2(f), half_fov) } else { None }
}

impl ObstacleMemory {
    /// A memory for a camera whose horizontal field of view is `2 · half_fov_rad`, mounted
    /// `camera_height_m` above the floor.
    pub fn new(params: MemoryParams, half_fov_rad: f64, camera_height_m: f64) -> Self {
        Self {
            params,
            half_fov_rad,
            camera_height_m,
            pose: Pose::default(),
            cells: BTreeMap::new(),
            touched: Vec::new(),
            seen: Vec::new(),
            lane: None,
            doorway: None,
            stop_m: f64::INFINITY,
        }
    }

    /// The robot's heading in the memory's (odometry) frame, rad.
    pub fn yaw(&self) -> f64 {
        self.pose.yaw
    }

    pub fn params(&self) -> &MemoryParams {
        &self.params
    }

    /// Forgets everything (a new mission, a gap in perception longer than the memory is good for),
    /// and starts a new odometry frame at the robot: a cleared memory then depends on nothing
    /// before the clear (the cells' grid alignment included), so a replay that resynchronises on
    /// a fail-safe computes the same cells.
    pub fn clear(&mut self) {
        self.cells.clear();
        self.pose = Pose::default();
    }

    /// The occupied cells (evidence at `occupied`): their centres, robot frame (forward, left),
    /// m, and the cells.
    fn occupied_entries(&self) -> impl Iterator<Item = ([f64; 2], &Cell)> + '_ {
        self.cells.iter().filter(|(_, c)| c.evidence >= self.params.occupied).map(|(k, c)| (self.to_robot(*k), c))
    }

    /// The occupied cells' centres, robot frame (forward, left), m.
    fn occupied_cells(&self) -> impl Iterator<Item = [f64; 2]> + '_ {
        self.occupied_entries().map(|(at, _)| at)
    }

    /// The current lane when the wall band is on: the walls are then its, not the cells'.
    fn walled_lane(&self) -> Option<Lane> {
        self.lane.filter(|_| self.params.wall_band_m > 0.0)
    }

    /// The occupied cells, each with whether it lies in the wall band: less than `wall_band_m`
    /// inside the walls of the current lane, or beyond them ([`MemoryParams::wall_band_m`]).
    /// A cell marked by a contact never does: what the robot touched is there, wall or not.
    fn banded_cells(&self) -> impl Iterator<Item = ([f64; 2], bool)> + '_ {
        let wall = self.walled_lane().map(|l| (l.offset_of(), l.half_width_m - self.params.wall_band_m));
        self.occupied_entries().map(move |(at, cell)| {
            let banded = !cell.contact && wall.is_some_and(|(offset, inner)| offset(at).abs() >= inner);
            (at, banded)
        })
    }

    /// The corridor the robot is in now, from the map (`None`: not in one, or no map): the
    /// steering and the escape keep inside it ([`free_in_lane`](Self::free_in_lane)), and the
    /// queries leave the walls to it ([`MemoryParams::wall_band_m`]). Set each step before the
    /// queries.
    pub fn set_lane(&mut self, lane: Option<Lane>) {
        self.lane = lane;
    }

    /// The door the robot is going through now, from the map (`None`: none, or no map): the
    /// steering, the escape ([`free_in_lane`](Self::free_in_lane)) and the footprint guard
    /// ([`arc_free`](Self::arc_free)) keep the robot's footprint, widened by `lane_margin_m`,
    /// off the door's wall either side of the opening. The camera does not see a jamb beside
    /// the robot, nor one it approaches at an angle, in time (a jamb of R9's door was the
    /// wide views' contacts). Set each step before the queries.
    pub fn set_doorway(&mut self, doorway: Option<Doorway>) {
        self.doorway = doorway;
    }

    /// How far ahead the plan stops the robot's origin (before a turn, at the goal), m;
    /// infinite when it does not. The paths of [`free_width`](Self::free_width) and its callers
    /// end there, rounded by their half-width: a cell past the stop point and farther than the
    /// half-width from it is beside where the robot will stand, not in its way (the jambs of the
    /// door the robot stops 0.5 m in front of, 0.35 m to either side, read as in its path and
    /// held it creeping short of the goal). Set each step before the queries.
    pub fn set_stop(&mut self, reach_m: f64) {
        self.stop_m = if reach_m.is_nan() { f64::INFINITY } else { reach_m.max(0.0) };
    }

    /// Cells with at least `min_evidence`, robot frame (forward, left), m, with their evidence
    /// and whether they were ever occupied (confirmed): for traces and tests.
    pub fn cells_above(&self, min_evidence: f64) -> Vec<([f64; 2], f64, bool)> {
        self.cells
            .iter()
            .filter(|(_, c)| c.evidence >= min_evidence)
            .map(|(k, c)| (self.to_robot(*k), c.evidence, c.confirmed))
            .collect()
    }

    /// Occupied cells, robot frame (forward, left), m: for logging and tests.
    pub fn occupied(&self) -> Vec<[f64; 2]> {
        self.occupied_cells().collect()
    }

    /// Whether a frame pair over `dt` seconds with the mean velocity `span` and a turn rate that
    /// changed by at most `turn_change` (rad/s) between steps measures anything: forward travel
    /// of at least `min_travel_m`, turn rate at most `max_turn_rate`, turn-rate change at most
    /// `max_turn_change`.
    pub fn measurable(&self, span: BodyVelocity, dt: f64, turn_change: f64) -> bool {
        let p = &self.params;
        span.v * dt >= p.min_travel_m && span.omega.abs() <= p.max_turn_rate && turn_change <= p.max_turn_change
    }

    /// The cell under a point `forward`, `left` of the robot, m.
    fn cell_at(&self, forward: f64, left: f64) -> (i32, i32) {
        let (s, c) = self.pose.yaw.sin_cos();
        let x = self.pose.x + c * forward - s * left;
        let y = self.pose.y + s * forward + c * left;
        ((x / self.params.cell_m).floor() as i32, (y / self.params.cell_m).floor() as i32)
    }

    /// Centre of cell `key`, robot frame.
    fn to_robot(&self, key: (i32, i32)) -> [f64; 2] {
        robot_frame(self.pose, self.params.cell_m, key)
    }
}

fn robot_frame(pose: Pose, cell: f64, (i, j): (i32, i32)) -> [f64; 2] {
    let (x, y) = ((i as f64 + 0.5) * cell - pose.x, (j as f64 + 0.5) * cell - pose.y);
    let (s, c) = pose.yaw.sin_cos();
    [c * x + s * y, -s * x + c * y]
}
