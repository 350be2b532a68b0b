//! The `[mofis.memory]` table: the grid, its decay and the queries' margins.

use crate::config_error::ConfigError;
use serde::{Deserialize, Serialize};

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
    /// [`SIDE_REACH_M`](super::SIDE_REACH_M) ahead), m: occupied cells in it are a threat too,
    /// reported farther away the farther into it (by [`SIDE_FADE_M`](super::SIDE_FADE_M) at
    /// its outer edge), so the threat fades instead of switching off when a cell leaves the
    /// path. 0: the path alone.
    pub side_margin_m: f64,
    /// Cells behind the robot's origin by more than this are ignored for the threat, m.
    pub behind_m: f64,
    /// Clearance kept to the corridor's walls as the map gives them ([`crate::pafsis::Lane`]),
    /// m: less than `path_margin_m`, since the dead-reckoned position drifts.
    pub lane_margin_m: f64,
    /// With the corridor from the map
    /// ([`ObstacleMemory::set_lane`](super::ObstacleMemory::set_lane)), occupied cells less
    /// than this far inside its walls (or beyond them) are taken for the walls, which the lane
    /// already keeps the robot from: they neither block a heading, nor count as a threat, nor
    /// centre the robot (the lane's walls do that). Block-matching depth at a door jamb's edge
    /// or a wall seen at a grazing angle puts such cells 0.1–0.26 m inside the corridor, where,
    /// with the path margin, they narrowed the gap beside an obstacle until the robot crept.
    /// The price: in a corridor, something that stands out of a wall by less than
    /// this is not seen (set 0 where such things are; docs/navigation.md). 0: off.
    pub wall_band_m: f64,
    /// With the wall band on, a lane's wall closer than this to the robot's footprint (by dead
    /// reckoning) is a threat on its side
    /// ([`ObstacleMemory::threat_sides`](super::ObstacleMemory::threat_sides)), so MOFIS turns
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
    /// off by about `σ/ρ`, and a lone weak point is how a phantom cell starts (in the office
    /// sim, 11–24 % of the points of 1.2–2 px fell in free space, under 6 % of those from
    /// 2.5 px). 0 (the default): every point votes 1. At 2.5 px the occupied cells in free
    /// space fell from 20 % to 17.5 % and the simulated missions were 7 % faster, but as many
    /// runs touched something and fewer arrived, so it is off.
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
            out_half_life_s: 60.0,
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
    /// Range checks; the error names the field under `mofis.memory.`.
    pub fn validate(&self) -> Result<(), ConfigError> {
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
            Some((field, _, problem)) => Err(ConfigError::invalid(format!("mofis.memory.{field}"), *problem)),
            None => Ok(()),
        }
    }
}
