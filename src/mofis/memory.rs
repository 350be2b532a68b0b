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
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The `[mofis.memory]` config table.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MemoryParams {
    /// Side of a grid cell, m.
    pub cell_m: f64,
    /// Evidence half-life of a cell in the camera's view, s.
    pub half_life_view_s: f64,
    /// Evidence half-life of a cell in view that the step did not measure (a close textureless
    /// face, a bearing without reliable flow, a robot not driving forward), s.
    pub half_life_aside_s: f64,
    /// Evidence half-life of a cell out of view (beside or behind the robot), per distance
    /// driven, m ...
    pub out_half_life_m: f64,
    /// ... per angle turned, rad ...
    pub out_half_life_rad: f64,
    /// ... and over time, s: nothing can confirm or clear it there, and what makes it wrong is
    /// the dead-reckoning drift, which grows with the motion; a robot standing beside an
    /// obstacle keeps it.
    pub out_half_life_s: f64,
    /// Evidence half-life of a cell marked by a contact, per distance driven, m ...
    pub contact_half_life_m: f64,
    /// ... and over time, s: what the robot touched is certain, unlike a flow point, and the
    /// robot is still beside it when it turns back toward its goal.
    pub contact_half_life_s: f64,
    /// Evidence at which a cell is occupied (1 per frame that saw it).
    pub occupied: f64,
    /// Evidence cap (how long a solid thing is remembered once out of view).
    pub max_evidence: f64,
    /// Cells farther than this from the robot are forgotten, m; also the range within which the
    /// camera is taken to see a cell in its field of view.
    pub max_range_m: f64,
    /// The robot's radius (circumscribed), m.
    pub robot_radius_m: f64,
    /// Clearance kept to either side of the robot's path, m.
    pub path_margin_m: f64,
    /// Width of the side band beyond the path, beside the robot (it narrows to nothing
    /// [`SIDE_REACH_M`] ahead), m: occupied cells in it are a threat too, reported farther away
    /// the farther into it (by [`SIDE_FADE_M`] at its outer edge), so the threat fades instead
    /// of switching off when a cell leaves the path. 0: the path alone.
    pub side_margin_m: f64,
    /// Cells behind the robot's origin by more than this are ignored for the threat, m.
    pub behind_m: f64,
    /// Clearance kept to the corridor's walls as the map gives them ([`crate::pafsis::Lane`]),
    /// m: less than `path_margin_m`, since the dead-reckoned position drifts.
    pub lane_margin_m: f64,
    /// With the corridor from the map ([`ObstacleMemory::set_lane`]), occupied cells less than
    /// this far inside its walls (or beyond them) are taken for the walls, which the lane
    /// already keeps the robot from: they neither block a heading, nor count as a threat, nor
    /// centre the robot (the lane's walls do that). Block-matching depth at a door jamb's edge
    /// or a wall seen at a grazing angle puts such cells 0.1–0.26 m inside the corridor, where,
    /// with the path margin, they narrowed the gap beside an obstacle until the robot crept
    /// (seed 16). The price: in a corridor, something that stands out of a wall by less than
    /// this is not seen (set 0 where such things are; docs/navigation.md). 0: off.
    pub wall_band_m: f64,
    /// With the wall band on, a lane's wall closer than this to the robot's footprint (by dead
    /// reckoning) is a threat on its side ([`ObstacleMemory::threat_sides`]), so MOFIS turns
    /// the robot back in, m; it also has to cover the dead-reckoned position's lateral drift.
    /// 0: off.
    pub wall_threat_m: f64,
    /// Points are taken in only when the robot travelled at least this far forward over the
    /// frame interval, m: with less, the flow of anything but the nearest surfaces is below the
    /// matching noise, and a noise vector reads as a surface close by.
    pub min_travel_m: f64,
    /// Points nearer than this to the robot's origin are ignored, m: the camera cannot see
    /// there (a fixed-focus webcam, a surface inside the robot's footprint), so such a point is
    /// a mismatched block.
    pub min_range_m: f64,
    /// Points are taken from blocks with at least this much radial flow, pixels per frame
    /// interval ([`crate::offis::Offis::surface_points`]).
    pub min_radial_px: f64,
    /// ... and tangential flow at most this fraction of the radial flow.
    pub max_tangential: f64,
    /// ... and turned slower than this, rad/s: the odometry's yaw-rate error, left in the flow
    /// by the de-rotation, grows with the turn rate.
    pub max_turn_rate: f64,
    /// ... and with a turn rate that changed by at most this since the previous step, rad/s:
    /// odometry samples never cover a frame interval exactly, and while the turn rate changes
    /// the difference is a yaw error (0.1 rad/s over 33 ms is 1 px at 320 px wide).
    pub max_turn_change: f64,
    /// A point votes for its cell in proportion to its radial flow up to this, pixels (a cell's
    /// vote in a step is the sum over its points, at most 1): the depth from `ρ` px of flow is
    /// off by about `σ/ρ`, and a lone weak point is how a phantom cell starts (on seeds 3 and
    /// 16, 11–24 % of the points of 1.2–2 px fell in free space, under 6 % of those from
    /// 2.5 px). 0 (the default): every point votes 1. At 2.5 px, over seeds 0..99, the occupied
    /// cells in free space fell from 20 % to 17.5 % and the missions were 7 % faster, but as
    /// many runs touched something and fewer arrived (README, tenth session), so it is off.
    pub vote_full_radial_px: f64,
}

impl Default for MemoryParams {
    fn default() -> Self {
        Self {
            cell_m: 0.1,
            half_life_view_s: 0.5,
            half_life_aside_s: 4.0,
            out_half_life_m: 1.5,
            out_half_life_rad: 6.0,
            out_half_life_s: 12.0,
            contact_half_life_m: 1.0,
            contact_half_life_s: 15.0,
            occupied: 1.5,
            max_evidence: 4.0,
            max_range_m: 4.0,
            robot_radius_m: 0.18,
            path_margin_m: 0.2,
            side_margin_m: 0.15,
            behind_m: 0.0,
            lane_margin_m: 0.1,
            wall_band_m: 0.25,
            wall_threat_m: 0.1,
            min_travel_m: 0.006,
            min_range_m: 0.22,
            min_radial_px: 1.2,
            max_tangential: 0.5,
            vote_full_radial_px: 0.0,
            max_turn_rate: 0.3,
            max_turn_change: 0.05,
        }
    }
}

impl MemoryParams {
    /// Range checks; `Err((field, problem))` names the field under `mofis.memory.`.
    pub fn check(&self) -> Result<(), (&'static str, &'static str)> {
        let pos = |v: f64| v.is_finite() && v > 0.0;
        let nonneg = |v: f64| v.is_finite() && v >= 0.0;
        let checks = [
            ("cell_m", pos(self.cell_m) && self.cell_m <= 1.0, "must be in (0, 1] m"),
            ("half_life_view_s", pos(self.half_life_view_s), "must be a positive time in s"),
            ("half_life_aside_s", pos(self.half_life_aside_s), "must be a positive time in s"),
            ("out_half_life_m", pos(self.out_half_life_m), "must be a positive distance in m"),
            ("out_half_life_rad", pos(self.out_half_life_rad), "must be a positive angle in rad"),
            ("out_half_life_s", pos(self.out_half_life_s), "must be a positive time in s"),
            ("contact_half_life_m", pos(self.contact_half_life_m), "must be a positive distance in m"),
            ("contact_half_life_s", pos(self.contact_half_life_s), "must be a positive time in s"),
            ("occupied", pos(self.occupied), "must be a positive evidence (frames)"),
            ("max_evidence", self.max_evidence.is_finite() && self.max_evidence >= self.occupied, "must be ≥ occupied"),
            ("max_range_m", pos(self.max_range_m), "must be a positive distance in m"),
            ("robot_radius_m", pos(self.robot_radius_m), "must be a positive distance in m"),
            ("path_margin_m", nonneg(self.path_margin_m), "must be a distance ≥ 0 in m"),
            ("side_margin_m", nonneg(self.side_margin_m), "must be a distance ≥ 0 in m"),
            ("behind_m", nonneg(self.behind_m), "must be a distance ≥ 0 in m"),
            ("lane_margin_m", nonneg(self.lane_margin_m), "must be a distance ≥ 0 in m"),
            (
                "wall_band_m",
                nonneg(self.wall_band_m) && self.wall_band_m <= 0.5,
                "must be a distance in [0, 0.5] m (0: off)",
            ),
            ("wall_threat_m", nonneg(self.wall_threat_m), "must be a distance ≥ 0 in m (0: off)"),
            ("min_travel_m", nonneg(self.min_travel_m), "must be a distance ≥ 0 in m"),
            ("min_radial_px", nonneg(self.min_radial_px), "must be ≥ 0 pixels"),
            ("max_tangential", pos(self.max_tangential), "must be a positive fraction"),
            ("vote_full_radial_px", nonneg(self.vote_full_radial_px), "must be ≥ 0 pixels (0: off)"),
            ("min_range_m", nonneg(self.min_range_m), "must be a distance ≥ 0 in m"),
            ("max_turn_rate", pos(self.max_turn_rate), "must be a positive turn rate in rad/s"),
            ("max_turn_change", pos(self.max_turn_change), "must be a positive turn rate in rad/s"),
        ];
        match checks.iter().find(|(_, ok, _)| !ok) {
            Some((field, _, problem)) => Err((field, problem)),
            None => Ok(()),
        }
    }
}

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
        let wall = self.walled_lane().map(|l| {
            let (s, c) = l.angle_rad.sin_cos();
            (l, s, c, l.half_width_m - self.params.wall_band_m)
        });
        self.occupied_entries().map(move |([f, l], cell)| {
            // the cell's offset left of the corridor's centre line
            let banded =
                !cell.contact && wall.is_some_and(|(lane, s, c, inner)| (lane.left_m - f * s + l * c).abs() >= inner);
            ([f, l], banded)
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

    /// How far the robot's origin at `p` (robot frame, m) is from the door's wall either side
    /// of the opening ([`set_doorway`](Self::set_doorway)); infinite without a door.
    fn door_wall_distance(&self, [f, l]: [f64; 2]) -> f64 {
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

    /// One step: move by the odometry `odo` held over `dt` seconds, decay, then add the `points`
    /// seen at the new pose (robot frame). In a step whose pair was not
    /// [`measurable`](Self::measurable) the points are ignored, so nothing is seen through: the
    /// cells in view fade at the `half_life_aside_s` rate, those out of view at theirs. (Fading
    /// the cells in view at the slower out-of-view rate too, or holding them down to a lower
    /// threshold, kept phantoms in front of a robot that stands or turns: fewer missions
    /// arrived; README, ninth session.)
    pub fn update(&mut self, odo: BodyVelocity, dt: f64, points: &[SurfacePoint], measurable: bool) {
        if dt.is_finite() && dt > 0.0 && odo.v.is_finite() && odo.omega.is_finite() {
            let mid = self.pose.yaw + 0.5 * odo.omega * dt;
            self.pose.x += odo.v * dt * mid.cos();
            self.pose.y += odo.v * dt * mid.sin();
            self.pose.yaw = crate::pafsis::map::wrap_angle(self.pose.yaw + odo.omega * dt);
            let p = self.params;
            let (k_view, k_aside) = (0.5f64.powf(dt / p.half_life_view_s), 0.5f64.powf(dt / p.half_life_aside_s));
            let driven = (odo.v * dt).abs();
            let k_contact = 0.5f64.powf(driven / p.contact_half_life_m + dt / p.contact_half_life_s);
            // out of view nothing can confirm or clear a cell: it fades as the dead-reckoned pose
            // drifts (with the motion), and slowly over time, not while the robot stands beside it
            let turned = (odo.omega * dt).abs();
            let k_out = 0.5f64.powf(driven / p.out_half_life_m + turned / p.out_half_life_rad + dt / p.out_half_life_s);
            let (half_fov, cell) = (self.half_fov_rad, p.cell_m);
            // what the camera measured along each bearing sector this step
            self.seen.resize_with(SECTORS, Vec::new);
            self.seen.iter_mut().for_each(Vec::clear);
            if measurable {
                for pt in points {
                    if let Some(k) = sector(pt.left.atan2(pt.forward), half_fov) {
                        self.seen[k].push((pt.forward.hypot(pt.left), pt.up));
                    }
                }
            }
            let (pose, seen, h) = (self.pose, &self.seen, self.camera_height_m);
            self.cells.retain(|&(i, j), c| {
                let [f, l] = robot_frame(pose, cell, (i, j));
                let range = f.hypot(l);
                // seen through: the camera measured a surface beyond the cell on its bearing, by a
                // ray that passes over the cell lower than the top of what is remembered there (a
                // ray to the far wall above a low box says nothing about the box)
                let in_view = view_sector(f, l, half_fov);
                let through = in_view.is_some_and(|k| {
                    seen[k].iter().any(|&(r, up)| r > range + p.cell_m * 2.0 && h + (up - h) * range / r < c.top_m)
                });
                let out_of_view = in_view.is_none();
                c.evidence *= match (c.contact, through) {
                    (true, _) => k_contact,
                    (false, true) => k_view,
                    (false, false) if out_of_view => k_out,
                    (false, false) => k_aside,
                };
                range <= p.max_range_m && c.evidence >= 0.05
            });
        }
        self.touched.clear();
        let full_px = self.params.vote_full_radial_px;
        for pt in points.iter().filter(|_| measurable) {
            let range = pt.forward.hypot(pt.left);
            if !(range >= self.params.min_range_m && range <= self.params.max_range_m) {
                continue;
            }
            let key = self.cell_at(pt.forward, pt.left);
            let vote = if full_px > 0.0 { (pt.radial_px / full_px).clamp(0.0, 1.0) } else { 1.0 };
            self.touched.push((key, pt.up, vote));
        }
        // one vote per cell (its points' votes summed, at most 1), with its highest point; a
        // total order, so the sums are added in the same order on every run
        self.touched.sort_unstable_by(|a, b| a.0.cmp(&b.0).then(b.1.total_cmp(&a.1)).then(a.2.total_cmp(&b.2)));
        for cell in self.touched.chunk_by(|a, b| a.0 == b.0) {
            let (key, up, _) = cell[0];
            let vote: f64 = cell.iter().map(|t| t.2).sum();
            let c =
                self.cells.entry(key).or_insert(Cell { evidence: 0.0, contact: false, confirmed: false, top_m: up });
            c.evidence = (c.evidence + vote.min(1.0)).min(self.params.max_evidence);
            c.confirmed |= c.evidence >= self.params.occupied;
            c.top_m = c.top_m.max(up);
        }
    }

    /// Records a contact the camera could not see (the robot stalled while driving forward):
    /// the cells on an arc of `±half_arc_rad` just in front of the robot's footprint become
    /// solid, so that the path ahead reads blocked and the robot steers around what it touched.
    /// They fade with the distance driven (`contact_half_life_m`) and slowly with time
    /// (`contact_half_life_s`), not like what the camera saw: the robot is still beside what it
    /// touched when it turns back toward the goal, and turning back into it again and again
    /// was the stall loop.
    pub fn mark_contact(&mut self, half_arc_rad: f64) {
        let p = self.params;
        let r = p.robot_radius_m + 0.5 * p.cell_m;
        // one point per half cell along the arc
        let n = ((half_arc_rad.abs() * r) / (0.5 * p.cell_m)).ceil() as i32;
        for k in -n..=n {
            let b = if n == 0 { 0.0 } else { half_arc_rad.abs() * k as f64 / n as f64 };
            let key = self.cell_at(r * b.cos(), r * b.sin());
            // as tall as anything: no ray clears a contact
            self.cells
                .insert(key, Cell { evidence: p.max_evidence, contact: true, confirmed: true, top_m: f64::INFINITY });
        }
    }

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
    /// ([`crate::mofis::Mofis::step_sides`]).
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

    /// How far the robot can drive along `heading` (rad, robot frame, + left) before its
    /// footprint widened by `path_margin_m` meets an occupied cell, up to `lookahead_m`.
    pub fn free_distance(&self, heading: f64, lookahead_m: f64) -> f64 {
        self.free_width(heading, self.params.robot_radius_m + self.params.path_margin_m, lookahead_m)
    }

    /// The footprint guard's query ([`crate::mofis::MofisParams::guard_evidence`]): how far
    /// the robot's origin can drive along an arc of `curvature` (1/m, + = left) before its
    /// footprint, widened by `clearance_m`, reaches the centre of a confirmed cell (one that
    /// was occupied once) that still has at least `min_evidence` (occupied or fading, wall
    /// band or not) and that the motion brings nearer; up to `reach_m`. A cell already inside
    /// the widened footprint stops only motion toward it, so the robot can always drive away
    /// from what it is beside. `aside`: only the cells out of the camera's field of view count
    /// (the guard's brake: what is in view is measured again, and the stopping gate's).
    pub fn arc_free(&self, curvature: f64, reach_m: f64, clearance_m: f64, min_evidence: f64, aside: bool) -> f64 {
        if reach_m.is_nan() || reach_m <= 0.0 {
            return 0.0;
        }
        let half_fov = self.half_fov_rad;
        let body = self.params.robot_radius_m + clearance_m;
        let near = reach_m + body;
        let steps = (reach_m / ARC_STEP_M).ceil().max(1.0) as usize;
        let arc = |s: f64| match curvature.abs() < 1e-6 {
            true => [s, 0.0],
            false => [(curvature * s).sin() / curvature, (1.0 - (curvature * s).cos()) / curvature],
        };
        // the door's wall, from the map, counts wherever it is
        let mut free = self.door_free(reach_m, arc);
        for (key, _) in self.cells.iter().filter(|(_, c)| c.confirmed && c.evidence >= min_evidence) {
            let [f, l] = self.to_robot(*key);
            let d0 = f.hypot(l);
            if d0 > near || (aside && view_sector(f, l, half_fov).is_some()) {
                continue;
            }
            for k in 1..=steps {
                let s = reach_m * k as f64 / steps as f64;
                if s >= free {
                    break;
                }
                let [x, y] = arc(s);
                let d = (f - x).hypot(l - y);
                if d < body && d < d0 - 1e-3 {
                    free = free.min(reach_m * (k - 1) as f64 / steps as f64);
                    break;
                }
            }
        }
        free
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
        let band = (lane.half_width_m - self.params.robot_radius_m - self.params.lane_margin_m).max(0.0);
        let rate = (heading - lane.angle_rad).sin();
        let exit = match rate {
            r if r > 1e-9 => (band - lane.left_m) / r,
            r if r < -1e-9 => (band + lane.left_m) / -r,
            _ => f64::INFINITY,
        };
        exit.clamp(0.0, lookahead_m)
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

fn robot_frame(pose: Pose, cell: f64, (i, j): (i32, i32)) -> [f64; 2] {
    let (x, y) = ((i as f64 + 0.5) * cell - pose.x, (j as f64 + 0.5) * cell - pose.y);
    let (s, c) = pose.yaw.sin_cos();
    [c * x + s * y, -s * x + c * y]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pt(forward: f64, left: f64) -> SurfacePoint {
        SurfacePoint { forward, left, up: 0.5, radial_px: 3.0 }
    }

    /// The default memory, except that standing still counts as measurable (so the geometry
    /// below is exact) and cells up to 0.48 m beside the heading count as beside the path.
    fn memory() -> ObstacleMemory {
        let p = MemoryParams { min_travel_m: 0.0, side_margin_m: 0.3, ..MemoryParams::default() };
        ObstacleMemory::new(p, 26.7f64.to_radians(), 0.4)
    }

    const STILL: BodyVelocity = BodyVelocity { v: 0.0, omega: 0.0 };

    /// `update` for a pair measured as the memory's own test says.
    fn step(m: &mut ObstacleMemory, odo: BodyVelocity, dt: f64, points: &[SurfacePoint]) {
        let measured = m.measurable(odo, dt, 0.0);
        m.update(odo, dt, points, measured);
    }

    /// Puts a cell at (`forward`, `left`) of the robot with `evidence`, confirmed or not.
    fn put(m: &mut ObstacleMemory, forward: f64, left: f64, evidence: f64, confirmed: bool) {
        let key = m.cell_at(forward, left);
        m.cells.insert(key, Cell { evidence, contact: false, confirmed, top_m: 0.5 });
    }

    #[test]
    fn the_guard_sees_an_arc_reach_a_lingering_cell() {
        let (reach, clear, min) = (0.4, 0.04, 0.3);
        let mut m = memory();
        // a faded cell ahead on the left, its centre at (0.35, 0.15): below the occupied
        // threshold, so no threat and no stop, but it was confirmed once
        put(&mut m, 0.35, 0.15, 0.5, true);
        assert!(!m.threat().present);
        // straight on, the footprint (0.18 + 0.04 m) reaches the centre when the origin is
        // √(0.22² − 0.15²) = 0.161 m short of it: after 0.189 m, in steps of 2 cm
        let straight = m.arc_free(0.0, reach, clear, min, false);
        assert!((straight - 0.18).abs() < 1e-9, "{straight}");
        // turning left toward it is blocked sooner, turning right (radius 0.33 m) bends clear
        assert!(m.arc_free(1.0, reach, clear, min, false) < straight);
        assert_eq!(m.arc_free(-3.0, reach, clear, min, false), reach);
        // one that has faded below the guard's evidence, or was never confirmed (one noisy
        // point), does not count
        let mut m = memory();
        put(&mut m, 0.35, 0.15, 0.25, true);
        put(&mut m, 0.35, 0.05, 1.0, false);
        assert_eq!(m.arc_free(0.0, reach, clear, min, false), reach);
        // a cell already inside the footprint blocks only the motion toward it
        let mut m = memory();
        put(&mut m, -0.05, 0.15, 2.0, true);
        assert_eq!(m.arc_free(0.0, reach, clear, min, false), reach, "driving away from what is beside");
        put(&mut m, 0.1, -0.1, 2.0, true);
        assert_eq!(m.arc_free(0.0, reach, clear, min, false), 0.0, "driving into what is ahead inside it");
        // two votes confirm a cell, and it stays confirmed as it fades
        let mut m = memory();
        step(&mut m, STILL, 0.0, &[pt(0.35, 0.15)]);
        assert!(!m.cells.values().any(|c| c.confirmed), "one vote");
        step(&mut m, STILL, 0.0, &[pt(0.35, 0.15)]);
        assert!(m.cells.values().all(|c| c.confirmed));
        m.cells.values_mut().for_each(|c| c.evidence = 0.4);
        assert!(m.arc_free(0.0, reach, clear, min, false) < reach);
        // `aside`: only the cells out of the camera's view count, the brake's query. The cell at
        // (0.35, 0.15) is 0.41 rad off the heading, in view (±0.47 rad); one at (0.25, 0.15),
        // 0.54 rad off, is out of it, and the footprint reaches its centre after
        // 0.25 − √(0.22² − 0.15²) = 0.089 m: at the fifth 2 cm step
        let mut m = memory();
        put(&mut m, 0.35, 0.15, 0.5, true);
        assert!(m.arc_free(0.0, reach, clear, min, false) < reach);
        assert_eq!(m.arc_free(0.0, reach, clear, min, true), reach, "in view");
        put(&mut m, 0.25, 0.15, 0.5, true);
        let aside = m.arc_free(0.0, reach, clear, min, true);
        assert!((aside - 0.08).abs() < 1e-9, "{aside}");
    }

    #[test]
    fn one_frame_is_not_enough_two_are() {
        let mut m = memory();
        step(&mut m, STILL, 0.1, &[pt(1.0, 0.05), pt(1.01, 0.04)]);
        assert!(!m.threat().present, "a single frame (two blocks in one cell) must not make an obstacle");
        step(&mut m, STILL, 0.1, &[pt(1.0, 0.05)]);
        let o = m.threat();
        assert!(o.present);
        // cell centre (1.05, 0.05): its range minus the 0.18 m radius
        assert!((o.distance_m.unwrap() - (1.05f64.hypot(0.05) - 0.18)).abs() < 1e-9, "{o:?}");
        assert!((o.bearing_rad.unwrap() - 0.05f64.atan2(1.05)).abs() < 1e-9);
    }

    #[test]
    fn weak_flow_votes_less_and_a_cell_of_many_points_votes_once() {
        let base = MemoryParams { min_travel_m: 0.0, vote_full_radial_px: 0.0, ..MemoryParams::default() };
        let weak = |px: f64| SurfacePoint { radial_px: px, ..pt(1.0, 0.05) };
        let evidence_after = |params: MemoryParams, frame: &[SurfacePoint], frames: usize| {
            let mut m = ObstacleMemory::new(params, 26.7f64.to_radians(), 0.4);
            for _ in 0..frames {
                // dt 0: no decay, the evidence is the sum of the votes
                m.update(STILL, 0.0, frame, true);
            }
            m.cells.values().map(|c| c.evidence).sum::<f64>()
        };
        let weighted = MemoryParams { vote_full_radial_px: 2.5, ..base };
        // off: any point votes 1 per frame, two frames make an obstacle
        assert_eq!(evidence_after(base, &[weak(1.25)], 2), 2.0);
        // on: a lone 1.25 px point votes 0.5, so the same two frames do not ...
        assert!((evidence_after(weighted, &[weak(1.25)], 2) - 1.0).abs() < 1e-12);
        // ... three of them do (occupied at 1.5)
        assert!((evidence_after(weighted, &[weak(1.25)], 3) - 1.5).abs() < 1e-12);
        // a strong point votes 1, and three weak points in one cell vote 1 together, not 1.5
        assert_eq!(evidence_after(weighted, &[weak(4.0)], 1), 1.0);
        assert_eq!(evidence_after(weighted, &[weak(1.25), weak(1.25), weak(1.25)], 1), 1.0);
    }

    #[test]
    fn a_contact_blocks_the_path_ahead_until_the_robot_turns_away() {
        let mut m = memory();
        m.mark_contact(0.5);
        // the arc sits just beyond the footprint, ±0.5 rad: straight on is blocked at once
        assert!(m.free_distance(0.0, 1.5) < 0.35, "{}", m.free_distance(0.0, 1.5));
        let o = m.threat();
        assert!(o.present && o.distance_m.unwrap() < 0.15, "{o:?}");
        // the stall recovery: back off 0.15 m, then turn on the spot; 46° is not enough to
        // drive straight on, 90° is
        step(&mut m, BodyVelocity { v: -0.15, omega: 0.0 }, 1.0, &[]);
        step(&mut m, BodyVelocity { v: 0.0, omega: 0.8 }, 1.0, &[]);
        assert!(m.free_distance(0.0, 1.5) < 0.5, "{}", m.free_distance(0.0, 1.5));
        assert!(m.free_distance(0.8, 1.5) >= 1.5, "{}", m.free_distance(0.8, 1.5));
        step(&mut m, BodyVelocity { v: 0.0, omega: std::f64::consts::FRAC_PI_2 - 0.8 }, 1.0, &[]);
        assert!(m.free_distance(0.0, 1.5) >= 1.5, "{}", m.free_distance(0.0, 1.5));
        // and it is remembered on the right, where it was
        assert!(!m.occupied().is_empty() && m.occupied().iter().all(|[_, l]| *l < 0.0), "{:?}", m.occupied());
    }

    #[test]
    fn a_contact_is_remembered_while_the_robot_stays_and_fades_as_it_drives_away() {
        let mut m = memory();
        // something seen 0.35 m to the left, and a contact ahead
        for _ in 0..4 {
            step(&mut m, STILL, 0.1, &[pt(1.0, 0.35)]);
        }
        m.mark_contact(0.5);
        // 10 s turning to and fro on the spot (a stall loop's time scale): the seen cell fades
        // out (half-life 4 s), the contact stays (15 s: 4 → 2.5)
        for k in 0..100 {
            let omega = if k % 20 < 10 { 0.5 } else { -0.5 };
            step(&mut m, BodyVelocity { v: 0.0, omega }, 0.1, &[]);
        }
        let left = m.occupied();
        assert!(!left.is_empty() && left.iter().all(|[f, _]| *f < 0.35), "only the contact arc: {left:?}");
        // driving 1.5 m on (half-life 1 m), it is forgotten
        for _ in 0..15 {
            step(&mut m, BodyVelocity { v: -1.0, omega: 0.0 }, 0.1, &[]);
        }
        assert!(m.occupied().is_empty(), "{:?}", m.occupied());
    }

    #[test]
    fn nothing_is_taken_in_while_creeping_or_turning_fast() {
        let mut m = ObstacleMemory::new(MemoryParams::default(), 0.47, 0.4);
        let creep = BodyVelocity { v: 0.05, omega: 0.0 }; // 5 mm in 0.1 s < 6 mm
        let spin = BodyVelocity { v: 0.3, omega: 0.5 };
        assert!(!m.measurable(creep, 0.1, 0.0) && !m.measurable(spin, 0.1, 0.0));
        assert!(m.measurable(BodyVelocity { v: 0.3, omega: 0.1 }, 0.1, 0.0));
        // a turn rate that changed by 0.1 rad/s within the pair is not trusted
        assert!(!m.measurable(BodyVelocity { v: 0.3, omega: 0.1 }, 0.1, 0.1));
        for odo in [creep, spin, creep] {
            step(&mut m, odo, 0.1, &[pt(1.0, 0.0)]);
        }
        assert!(m.occupied().is_empty());
    }

    /// The distance [`ObstacleMemory::threat_within`] reports for a cell `along`, `across` of
    /// the path of [`memory`] (path 0.38 m, side band 0.3 m).
    fn faded(along: f64, across: f64) -> f64 {
        let band = 0.3 * (1.0 - along / SIDE_REACH_M);
        along.hypot(across) - 0.18 + SIDE_FADE_M * (across.abs() - 0.38).max(0.0) / band
    }

    #[test]
    fn beside_the_path_counts_farther_away_and_walls_aside_are_ignored() {
        // a corridor wall 1 m to the left, a box 0.45 m right of the heading at 0.45 m (outside
        // the path's 0.18 + 0.2 m, inside the side band), and a box in the path at 1.55 m
        let frame = [pt(0.5, 1.0), pt(1.0, 1.0), pt(0.4, -0.45), pt(1.5, 0.1)];
        let run = |points: &[SurfacePoint]| {
            let mut m = memory();
            for _ in 0..3 {
                step(&mut m, STILL, 0.1, points);
            }
            m.threat()
        };
        // the box beside counts 0.07 m beyond the path, 3 m × 0.07 / 0.19 farther than it is, so
        // the box in the path, farther away but in the way, is the threat
        let beside = faded(0.45, -0.45);
        assert!(beside > 1.55f64.hypot(0.15) - 0.18 && beside < 2.0, "{beside}");
        let o = run(&frame);
        assert!((o.bearing_rad.unwrap() - 0.15f64.atan2(1.55)).abs() < 1e-9, "the in-path box: {o:?}");
        assert!((o.distance_m.unwrap() - (1.55f64.hypot(0.15) - 0.18)).abs() < 1e-9, "{o:?}");
        // without the in-path box: the one beside the path, to the right, at its faded distance
        let o = run(&frame[..3]);
        assert!(o.bearing_rad.unwrap() < 0.0 && (o.distance_m.unwrap() - beside).abs() < 1e-9, "{o:?}");
        // the wall alone is no threat
        assert!(!run(&frame[..2]).present);
        // nor is the box beside the path when it is 1.2 m ahead, where the band has narrowed to
        // nothing
        assert!(!run(&[pt(1.2, -0.45)]).present);
    }

    #[test]
    fn each_side_has_its_own_threat() {
        let mut m = memory();
        // a box 0.9 m ahead, 0.25 m left, and another 1.0 m ahead, 0.3 m right
        for _ in 0..2 {
            step(&mut m, STILL, 0.1, &[pt(0.9, 0.25), pt(1.0, -0.3)]);
        }
        let [left, right] = m.threat_sides(f64::INFINITY);
        let (l, r) = (left.bearing_rad.unwrap(), right.bearing_rad.unwrap());
        assert!(l > 0.2 && r < -0.2, "{left:?} {right:?}");
        assert!(left.distance_m.unwrap() < right.distance_m.unwrap());
        assert_eq!(m.threat(), left, "the nearer of the two");
        // with the left one gone only the right one is left, on its side
        let mut m = memory();
        for _ in 0..2 {
            step(&mut m, STILL, 0.1, &[pt(1.0, -0.3)]);
        }
        let [left, right] = m.threat_sides(f64::INFINITY);
        assert!(!left.present && right.present && m.threat() == right, "{left:?} {right:?}");
    }

    #[test]
    fn a_cell_leaving_the_path_fades_out_of_the_threat() {
        // one cell 0.55 m ahead, seen from headings that put it ever farther to the side: the
        // threat's distance grows without a jump at the path's edge (0.38 m) or anywhere after
        let mut m = memory();
        for _ in 0..4 {
            step(&mut m, STILL, 0.1, &[pt(0.5, 0.0)]);
        }
        let (f0, l0) = (0.55f64, 0.05f64);
        let mut last: Option<f64> = None;
        let mut yaw = 0.0;
        while yaw < 1.2 {
            let o = m.threat();
            let (r, b) = (f0.hypot(l0), l0.atan2(f0) - yaw);
            let (along, across) = (r * b.cos(), (r * b.sin()).abs());
            let d = o.distance_m.unwrap_or_else(|| panic!("still ahead in the band at {along:.3}, {across:.3}"));
            assert!((d - faded(along, across)).abs() < 1e-9, "{d} at {along:.3}, {across:.3}");
            if let Some(prev) = last {
                assert!((d - prev).abs() < 0.6, "no jump at {across:.3} m beside: {prev} → {d}");
            }
            last = Some(d);
            step(&mut m, BodyVelocity { v: 0.0, omega: 0.4 }, 0.1, &[]);
            yaw += 0.04;
        }
        assert!(last.is_some_and(|d| d > 1.5), "faded to far: {last:?}");
    }

    #[test]
    fn nothing_beyond_the_stop_is_a_threat() {
        let mut m = memory();
        for _ in 0..2 {
            step(&mut m, STILL, 0.1, &[pt(1.0, 0.05)]);
        }
        assert!(m.threat().present);
        // path half width 0.38 m: a robot that stops 0.3 m on never comes within it of the cell
        assert!(!m.threat_within(0.3).present, "1.0 m ahead is beyond 0.3 + 0.38 m");
        let o = m.threat_within(0.7);
        assert!(o.present && (o.distance_m.unwrap() - (1.0f64.hypot(0.05) - 0.18)).abs() < 0.08, "{o:?}");
    }

    #[test]
    fn the_path_ends_in_a_half_disc_at_the_stop() {
        // a door's jambs as the memory places them, cell centres 0.65 m ahead and 0.35 m to
        // either side, and a robot that stops 0.3 m on: 0.49 m from where it will stand,
        // beyond its 0.38 m half-width, but inside the square end the path had before
        let mut m = memory();
        put(&mut m, 0.62, 0.35, 2.0, true);
        put(&mut m, 0.62, -0.35, 2.0, true);
        assert!(m.threat_within(0.3).present);
        assert!((m.free_distance(0.0, 1.0) - 0.65).abs() < 1e-9);
        m.set_stop(0.3);
        // (the test memory's wide side band still has them, faded out to far)
        let beside = m.threat_within(0.3);
        assert!(beside.distance_m.is_none_or(|d| d > 2.5), "{beside:?}");
        assert_eq!(m.free_distance(0.0, 1.0), 1.0);
        // a path turned by a right angle never reaches the stop line: a cell 0.9 m to the left
        // blocks it as before
        put(&mut m, 0.02, 0.92, 2.0, true);
        assert!(
            (m.free_distance(std::f64::consts::FRAC_PI_2, 1.0) - 0.95).abs() < 1e-6,
            "{}",
            m.free_distance(std::f64::consts::FRAC_PI_2, 1.0)
        );
        // a cell 0.35 m past the stop point and 0.05 m aside is where the robot will stand
        put(&mut m, 0.62, 0.05, 2.0, true);
        let o = m.threat_within(0.3);
        assert!(o.present && (o.distance_m.unwrap() - (0.65f64.hypot(0.05) - 0.18)).abs() < 1e-6, "{o:?}");
        assert!((m.free_distance(0.0, 1.0) - 0.65).abs() < 1e-9);
        // no stop: the jambs block the path again
        m.cells.remove(&m.cell_at(0.62, 0.05));
        m.set_stop(f64::INFINITY);
        assert!((m.free_distance(0.0, 1.0) - 0.65).abs() < 1e-9);
    }

    #[test]
    fn steers_to_the_nearest_free_heading() {
        let mut m = memory();
        // a 0.6 m wide box 1 m ahead, from 0.1 m left to 0.5 m right of the heading
        let bx: Vec<SurfacePoint> = (0..7).map(|k| pt(1.0, 0.1 - 0.1 * k as f64)).collect();
        for _ in 0..3 {
            step(&mut m, STILL, 0.1, &bx);
        }
        assert!((m.free_distance(0.0, 1.5) - 1.05).abs() < 1e-9, "the box's cells start at 1.0 m");
        let h = m.steer(0.0, 1.5, 0.7, 0.05);
        assert!(h > 0.0, "pass on the left, the short way round: {h}");
        assert!(m.free_distance(h, 1.5) >= 1.5);
        // a free goal direction is kept
        assert_eq!(m.steer(0.6, 1.5, 0.7, 0.05), 0.6);
    }

    #[test]
    fn the_lane_bounds_how_far_a_heading_is_free() {
        let m = memory();
        // a 2 m corridor, the robot 0.3 m left of its centre line and parallel to it: the
        // footprint (0.18) plus the lane margin (0.1) may come to 0.72 m off the line
        let lane = Lane { left_m: 0.3, angle_rad: 0.0, half_width_m: 1.0 };
        assert_eq!(m.lane_free_distance(&lane, 0.0, 1.5), 1.5, "along the corridor");
        let h = 0.5f64;
        let d = m.lane_free_distance(&lane, h, 5.0);
        assert!((d - (0.72 - 0.3) / h.sin()).abs() < 1e-9, "out to the left wall: {d}");
        let d = m.lane_free_distance(&lane, -h, 5.0);
        assert!((d - (0.72 + 0.3) / h.sin()).abs() < 1e-9, "across to the right wall: {d}");
        // outside the band: driving further out is blocked at once, driving back in is free
        let out = Lane { left_m: 0.9, ..lane };
        assert_eq!(m.lane_free_distance(&out, 0.2, 1.5), 0.0);
        assert_eq!(m.lane_free_distance(&out, -0.2, 1.5), 1.5);
        // the robot turned 0.4 rad left of the corridor: its own heading leaves the lane
        let turned = Lane { left_m: 0.0, angle_rad: -0.4, half_width_m: 1.0 };
        let d = m.lane_free_distance(&turned, 0.0, 5.0);
        assert!((d - 0.72 / 0.4f64.sin()).abs() < 1e-9, "{d}");
    }

    #[test]
    fn steering_keeps_inside_the_corridor_from_the_map() {
        let mut m = memory();
        // a box 1 m ahead from 0.25 m right to 0.15 m left of the heading; the robot 0.4 m left
        // of the centre line of a 2 m corridor. Seen alone, the short way round is left (where
        // a doorway, or a wall not yet seen, reads free); inside the corridor only the right
        // gap is wide enough
        let bx: Vec<SurfacePoint> = (0..5).map(|k| pt(1.0, 0.15 - 0.1 * k as f64)).collect();
        for _ in 0..3 {
            step(&mut m, STILL, 0.1, &bx);
        }
        let free = m.steer(0.0, 1.5, 0.7, 0.05);
        assert!(free > 0.0, "without the lane: left, through the door: {free}");
        let lane = Lane { left_m: 0.4, angle_rad: 0.0, half_width_m: 1.0 };
        m.set_lane(Some(lane));
        let h = m.steer(0.0, 1.5, 0.7, 0.05);
        assert!(h < 0.0, "with the lane: right, the way inside the corridor: {h}");
        assert!(m.free_distance(h, 1.5) >= 1.5 && m.lane_free_distance(&lane, h, 1.5) >= 1.5, "{h}");
    }

    #[test]
    fn with_the_wall_band_cells_at_the_corridors_walls_are_left_to_the_lane() {
        // a 2 m corridor, the robot on its centre line; a box 0.35–0.55 m left of the line, 1 m
        // ahead, and a door jamb's phantom 0.85 m right (0.15 m inside the wall) 0.75 m ahead
        let band = MemoryParams { wall_band_m: 0.25, ..memory().params };
        let mut m = ObstacleMemory::new(band, 26.7f64.to_radians(), 0.4);
        let seen = [pt(1.0, 0.35), pt(1.0, 0.45), pt(1.0, 0.55), pt(0.72, -0.83)];
        for _ in 0..3 {
            step(&mut m, STILL, 0.1, &seen);
        }
        assert_eq!(m.occupied().len(), 4, "the memory holds all it saw");
        // the heading straight at the phantom's cell (centre 0.75, −0.85)
        let at_phantom = (-0.85f64).atan2(0.75);
        assert!(m.free_distance(at_phantom, 1.5) < 1.2, "without a lane the phantom is an obstacle");
        let lane = Lane { left_m: 0.0, angle_rad: 0.0, half_width_m: 1.0 };
        m.set_lane(Some(lane));
        assert!(m.free_distance(at_phantom, 1.5) >= 1.5, "with it, the phantom is the lane's wall");
        assert!(m.free_distance(0.45f64.atan2(1.0), 1.5) < 1.2, "the box still blocks");
        let [left, right] = m.threat_sides(f64::INFINITY);
        assert!(left.present && !right.present, "{left:?} {right:?}");
        // the lane's walls centre the robot: a box 0.35 m left, the right wall 1 m away
        assert!(m.centring(1.5, 0.9, 1.5, 0.3) < 0.0);
        // turned 0.3 rad right of the corridor, 0.5 m right of its centre line: the cells are
        // judged by where they are across the corridor, not across the robot's heading
        let mut turned = ObstacleMemory::new(band, 26.7f64.to_radians(), 0.4);
        turned.set_lane(Some(Lane { left_m: -0.5, angle_rad: 0.3, half_width_m: 1.0 }));
        let (s, c) = 0.3f64.sin_cos();
        // points 0.35 m (a box) and 0.85 m (at the wall) right of the centre line, 1 m along it
        let at = |across: f64| {
            let (f, l) = (1.0, across + 0.5); // corridor frame relative to the robot
            pt(f * c - l * s, f * s + l * c)
        };
        for _ in 0..3 {
            step(&mut turned, STILL, 0.1, &[at(-0.35), at(-0.85)]);
        }
        assert_eq!(turned.occupied().len(), 2);
        assert_eq!(turned.banded_cells().filter(|c| c.1).count(), 1, "{:?}", turned.occupied());
        let off = ObstacleMemory { params: MemoryParams { wall_band_m: 0.0, ..band }, ..turned.clone() };
        assert_eq!(off.banded_cells().filter(|c| c.1).count(), 0, "band off: no cell is the wall's");
        // a contact at the wall is no depth error: it still blocks the way ahead
        let mut touched = ObstacleMemory::new(band, 26.7f64.to_radians(), 0.4);
        // (0.95 m left of the centre line: the whole arc lies in the band)
        touched.set_lane(Some(Lane { left_m: 0.95, angle_rad: 0.0, half_width_m: 1.0 }));
        touched.mark_contact(0.5);
        assert!(touched.banded_cells().all(|(_, banded)| !banded));
        assert!(touched.free_distance(0.0, 1.5) < 0.35, "{}", touched.free_distance(0.0, 1.5));
    }

    #[test]
    fn a_lane_wall_inside_the_robots_margin_is_a_threat_on_its_side() {
        use std::f64::consts::FRAC_PI_2;
        // nothing seen: only the lane's walls can be threats (the band leaves them to it)
        let band = MemoryParams { wall_band_m: 0.25, ..memory().params };
        let near = band.robot_radius_m + band.wall_threat_m;
        let mut m = ObstacleMemory::new(band, 26.7f64.to_radians(), 0.4);
        let lane = |left_m: f64, angle_rad: f64| Some(Lane { left_m, angle_rad, half_width_m: 0.6 });
        // on the centre line: both walls 0.6 m away, beyond the margin
        m.set_lane(lane(0.0, 0.0));
        assert_eq!(m.threat_sides(f64::INFINITY), [Obstacle::default(), Obstacle::default()]);
        // 0.4 m left of the line, parallel to it: the left wall is 0.2 m away, abeam
        m.set_lane(lane(0.4, 0.0));
        let [left, right] = m.threat_sides(f64::INFINITY);
        assert!(left.present && !right.present, "{left:?} {right:?}");
        assert!((left.distance_m.unwrap() - (0.2 - band.robot_radius_m)).abs() < 1e-9, "{left:?}");
        assert!((left.bearing_rad.unwrap() - FRAC_PI_2).abs() < 1e-9, "{left:?}");
        // heading 0.3 rad into the right wall, 0.15 m from it: the wall's nearest point is ahead
        // on the right, at the perpendicular distance
        m.set_lane(lane(-0.45, 0.3));
        let [left, right] = m.threat_sides(f64::INFINITY);
        assert!(!left.present && right.present, "{left:?} {right:?}");
        assert!((right.distance_m.unwrap() - 0.0).abs() < 1e-9, "inside the footprint: {right:?}");
        let bearing = right.bearing_rad.unwrap();
        assert!((-FRAC_PI_2..0.0).contains(&bearing) && (bearing + FRAC_PI_2 - 0.3).abs() < 1e-9, "{right:?}");
        // heading away from the left wall, 0.25 m from it: its nearest point not behind is abeam
        m.set_lane(lane(0.35, 0.4));
        let [left, _] = m.threat_sides(f64::INFINITY);
        let gap = 0.25 / 0.4f64.cos();
        assert!((left.distance_m.unwrap() - (gap - band.robot_radius_m)).abs() < 1e-9, "{left:?}");
        // just outside the margin: none
        m.set_lane(lane(0.6 - near - 0.01, 0.0));
        assert!(!m.threat_sides(f64::INFINITY)[0].present);
        // the band off: the walls are the cells', not the lane's
        let mut off = ObstacleMemory { params: MemoryParams { wall_band_m: 0.0, ..band }, ..m.clone() };
        off.set_lane(lane(0.4, 0.0));
        assert!(!off.threat_sides(f64::INFINITY)[0].present);
        // the threat off, the band on
        let mut off = ObstacleMemory { params: MemoryParams { wall_threat_m: 0.0, ..band }, ..m.clone() };
        off.set_lane(lane(0.4, 0.0));
        assert!(!off.threat_sides(f64::INFINITY)[0].present);
        // a wider margin (to cover dead-reckoning drift) reaches farther: 0.35 m from the wall
        let mut wide = ObstacleMemory { params: MemoryParams { wall_threat_m: 0.2, ..band }, ..m.clone() };
        wide.set_lane(lane(0.25, 0.0));
        assert!(wide.threat_sides(f64::INFINITY)[0].present);
        m.set_lane(lane(0.25, 0.0));
        assert!(!m.threat_sides(f64::INFINITY)[0].present);
    }

    #[test]
    fn the_doors_wall_from_the_map_bounds_the_steering_the_guard_and_the_stop() {
        use crate::pafsis::Doorway;
        let mut m = memory();
        let (body, step) = (m.params.robot_radius_m + m.params.lane_margin_m, ARC_STEP_M);
        // no door: nothing bounds the path
        assert_eq!(m.free_in_lane(0.0, 1.5), 1.5);
        // a 0.9 m opening 1 m ahead, the robot on its axis: straight through is free
        m.set_doorway(Some(Doorway { centre_m: [1.0, 0.0], angle_rad: 0.0, half_width_m: 0.45 }));
        assert_eq!(m.free_in_lane(0.0, 1.5), 1.5);
        assert_eq!(m.door_free_ahead(1.5), 1.5);
        assert_eq!(m.arc_free(0.0, 1.5, 0.04, 0.3, false), 1.5);
        // 0.35 m left of the axis: the footprint meets the left jamb's edge, 0.1 m beside the
        // path, sqrt(body² − 0.1²) before the wall
        m.set_doorway(Some(Doorway { centre_m: [1.0, -0.35], angle_rad: 0.0, half_width_m: 0.45 }));
        let jamb = 1.0 - (body * body - 0.1f64 * 0.1).sqrt();
        for free in [m.free_in_lane(0.0, 1.5), m.door_free_ahead(1.5), m.arc_free(0.0, 1.5, 0.04, 0.3, false)] {
            assert!(free <= jamb && free > jamb - step - 1e-9, "{free} vs {jamb}");
        }
        // the steering turns toward the opening's middle
        let h = m.steer(0.0, 1.5, 0.7, 0.05);
        assert!(h < 0.0 && m.free_in_lane(h, 1.5) == 1.5, "{h}");
        // a wall straight ahead (the robot 1 m beside the opening): the footprint meets it
        m.set_doorway(Some(Doorway { centre_m: [1.0, 1.0], angle_rad: 0.0, half_width_m: 0.45 }));
        assert!((m.door_free_ahead(1.5) - (1.0 - body)).abs() <= step + 1e-9);
        // in the doorway beside a jamb, nearer than the footprint: free to drive on through,
        // not to turn into it
        m.set_doorway(Some(Doorway { centre_m: [0.0, -0.3], angle_rad: 0.0, half_width_m: 0.45 }));
        assert_eq!(m.free_in_lane(0.0, 1.0), 1.0);
        assert!(m.free_in_lane(0.5, 1.0) < 0.2);
    }

    #[test]
    fn centring_steers_away_from_the_nearer_side() {
        let mut m = memory();
        // walls 0.35 m left and 0.95 m right, 0.5..1.5 m ahead
        let walls: Vec<SurfacePoint> =
            (0..10).flat_map(|k| [pt(0.5 + 0.1 * k as f64, 0.35), pt(0.5 + 0.1 * k as f64, -0.95)]).collect();
        for _ in 0..3 {
            step(&mut m, STILL, 0.1, &walls);
        }
        // cell centres at 0.35 left and 0.95 right: (0.35 − 0.95) / 2 = −0.3 m off the middle
        let c = m.centring(1.5, 1.0, 2.0, 0.3);
        assert!((c - (-0.3f64).atan2(2.0)).abs() < 1e-9, "{c}");
        // nothing within reach: no correction
        assert_eq!(m.centring(1.5, 0.3, 2.0, 0.3), 0.0);
    }

    #[test]
    fn remembers_an_obstacle_out_of_view_and_moves_it_with_the_robot() {
        let mut m = memory();
        for _ in 0..4 {
            step(&mut m, STILL, 0.1, &[pt(1.0, 0.35)]);
        }
        // drive 1 m straight in 10 steps seeing nothing: the box is now beside the robot, out of
        // view (90°), still remembered, 0.35 m to the left
        let v = BodyVelocity { v: 1.0, omega: 0.0 };
        for _ in 0..10 {
            step(&mut m, v, 0.1, &[]);
        }
        let cells = m.occupied();
        assert_eq!(cells.len(), 1);
        assert!((cells[0][0] - 0.05).abs() < 1e-9 && (cells[0][1] - 0.35).abs() < 1e-9, "{cells:?}");
        let o = m.threat();
        assert!(o.present && o.bearing_rad.unwrap() > 1.0, "beside the path, to the left: {o:?}");
        // turning left 90° on the spot puts it ahead, in the path
        let turn = BodyVelocity { v: 0.0, omega: std::f64::consts::FRAC_PI_2 };
        step(&mut m, turn, 1.0, &[]);
        let o = m.threat();
        assert!(o.bearing_rad.unwrap().abs() < 0.2, "{o:?}");
    }

    #[test]
    fn out_of_view_a_cell_fades_with_the_motion_not_while_the_robot_stands_beside_it() {
        let p = MemoryParams::default();
        let mut m = memory();
        // seen in four frames 0.4 m to the left, 0.5 m ahead: out of view (39°)
        for _ in 0..4 {
            step(&mut m, STILL, 0.1, &[pt(0.5, 0.4)]);
        }
        assert_eq!(m.occupied().len(), 1);
        let before = m.cells.values().next().unwrap().evidence;
        // standing beside it for 10 s: 0.5^(10 / 12) of the evidence stays (the 4 s half-life
        // of a cell in view would leave 0.18 of it, below `occupied`)
        for _ in 0..100 {
            step(&mut m, STILL, 0.1, &[]);
        }
        let after = m.cells.values().next().unwrap().evidence;
        assert!((after / before - 0.5f64.powf(10.0 / p.out_half_life_s)).abs() < 1e-9, "{before} → {after}");
        assert_eq!(m.occupied().len(), 1, "still there after 10 s standing beside it");
        // driving on 1.5 m (it stays out of view, beside and then behind) halves it once more
        let v = BodyVelocity { v: 1.5, omega: 0.0 };
        step(&mut m, v, 1.0, &[]);
        let driven = m.cells.values().next().unwrap().evidence;
        let k = 0.5f64.powf(1.5 / p.out_half_life_m + 1.0 / p.out_half_life_s);
        assert!((driven / after - k).abs() < 1e-9, "{after} → {driven}");
        assert!(m.occupied().is_empty());
    }

    #[test]
    fn standing_still_a_cell_in_view_fades_at_the_aside_rate() {
        let p = MemoryParams::default();
        // the default memory: standing still measures nothing (less than 6 mm travelled)
        let mut m = ObstacleMemory::new(p, 26.7f64.to_radians(), 0.4);
        let drive = BodyVelocity { v: 0.1, omega: 0.0 };
        for k in 0..4 {
            let measured = m.measurable(drive, 0.1, 0.0);
            assert!(measured);
            m.update(drive, 0.1, &[pt(1.0 - 0.01 * k as f64, 0.0)], measured);
        }
        assert_eq!(m.cells.len(), 1);
        let before = m.cells.values().next().unwrap().evidence;
        // 4 s standing in front of it, nothing measured: one `half_life_aside_s`
        for _ in 0..40 {
            let measured = m.measurable(STILL, 0.1, 0.0);
            assert!(!measured);
            m.update(STILL, 0.1, &[], measured);
        }
        let after = m.cells.values().next().unwrap().evidence;
        assert!((after / before - 0.5f64.powf(4.0 / p.half_life_aside_s)).abs() < 1e-9, "{before} → {after}");
    }

    #[test]
    fn the_band_ahead_is_free_up_to_the_nearest_cell_in_it() {
        let mut m = memory();
        for _ in 0..2 {
            step(&mut m, STILL, 0.1, &[pt(0.8, 0.15), pt(0.5, 0.45)]);
        }
        // the cell 0.15 m left (centre 0.85, 0.15) is in a 0.23 m band; the one 0.45 m left is not
        assert!((m.free_width(0.0, 0.23, 2.0) - 0.85).abs() < 1e-9);
        assert!((m.free_width(0.0, 0.1, 2.0) - 2.0).abs() < 1e-9);
        assert!((m.free_width(0.0, 0.5, 2.0) - 0.55).abs() < 1e-9);
    }

    #[test]
    fn a_cell_seen_through_fades_fast_one_not_seen_slowly() {
        let p = MemoryParams::default();
        let mut m = memory();
        for _ in 0..4 {
            step(&mut m, STILL, 0.1, &[pt(1.0, 0.0), pt(1.0, 0.35)]);
        }
        // 1 s in which the camera sees a wall 3 m away behind the first cell only (same bearing
        // sector as the cell centre (1.05, 0.05)): that cell
        // loses 2 half-lives of evidence, the other a quarter of one
        for _ in 0..10 {
            step(&mut m, STILL, 0.1, &[pt(3.0, 0.15)]);
        }
        let near: Vec<[f64; 2]> = m.occupied().into_iter().filter(|c| c[0] < 2.0).collect();
        assert_eq!(near.len(), 1, "{near:?}");
        assert!(near[0][1] > 0.25, "the cell not seen through survives: {near:?}");
        assert!(p.check().is_ok());
        assert_eq!(MemoryParams { occupied: 5.0, ..p }.check(), Err(("max_evidence", "must be ≥ occupied")));
    }

    #[test]
    fn a_ray_over_a_low_box_does_not_clear_it() {
        // the camera is 0.4 m up; a box 1 m ahead, seen up to 0.25 m (`top`), and a wall 3 m
        // away on the same bearing, seen at `wall_up`; then 1 s in which only the wall is
        // measured (the box's flow is too weak to locate, say)
        let remains = |top: f64, wall_up: f64| {
            let mut m = memory();
            let b = |up| SurfacePoint { forward: 1.0, left: 0.0, up, radial_px: 3.0 };
            for _ in 0..4 {
                step(&mut m, STILL, 0.1, &[b(0.1), b(top)]);
            }
            for _ in 0..10 {
                step(&mut m, STILL, 0.1, &[SurfacePoint { forward: 3.0, left: 0.15, up: wall_up, radial_px: 3.0 }]);
            }
            m.occupied().iter().any(|c| c[0] < 2.0)
        };
        // the ray to the wall at 1.0 m passes over the box at 0.4 + 0.6/3 ≈ 0.6 m: it says
        // nothing about the box, which stays
        assert!(remains(0.25, 1.0));
        // a ray to the wall's foot (0.15 m) passes the box at ≈ 0.32 m: still above a 0.25 m box,
        // but through a 0.5 m one, which is cleared
        assert!(remains(0.25, 0.15));
        assert!(!remains(0.5, 0.15));
    }
}
