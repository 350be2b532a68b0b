//! PAFSIS local planning (paper §2.2: "PAFSIS identifies a local goal and navigates the mobile
//! robot to the local goal"). The global plan is unrolled into *legs* (turn on the spot, drive
//! through a doorway, follow a corridor to a landmark); a state machine tracks progress along
//! the current leg from odometry (distance along the leg's direction, heading change) corrected
//! by recognised landmarks (OFFIS door sightings re-localise the robot along the corridor; a
//! corner or wall seen ahead ends a corridor), and outputs the goal-oriented velocity and angle.
//!
//! When a landmark does not show up where expected (the robot travelled past the map's
//! tolerance window around the leg's end, or `miss_factor` × the leg's length, without seeing
//! the corner/wall that ends it), the planner re-localises to the place the leg leads to and
//! replans from there; after `max_replans` it gives up (stop).
//!
//! Pure and deterministic: no clocks, no I/O; the same inputs give the same outputs.

use super::PafsisParams;
use super::global::{Mission, Plan, PlanError, plan};
use super::map::{Action, MapTolerance, PlaceKind, Side, TopoMap, Until, wrap_angle};
use super::side_doors::SideDoorTrack;
use super::walls::{self, WallGates, WallSighting};
use crate::perception::{Perception, TpoShape};
use hal::BodyVelocity;
use serde::Serialize;
use std::fmt;

/// Below this speed a lateral disagreement with the walls says nothing about the heading, m/s.
const DRIFT_MIN_SPEED_M_S: f64 = 0.1;
/// Within a streak of door frames, a door distance that grows by more than this is a new door.
const NEW_DOOR_JUMP_M: f64 = 0.5;

/// Something solid this near the heading, within `stop_distance_m`, is the end of a corner- or
/// wall-ended corridor where the map puts it (the end wall close up often reads as the nearest
/// obstacle rather than a TPO), rad.
const END_AHEAD_MAX_BEARING_RAD: f64 = 0.26;

/// Obstacles seen nearer than this pause the cross-track correction
/// (`PafsisParams::cross_track_hold_m`), m.
const HOLD_LINE_RANGE_M: f64 = 1.0;

/// Door sightings count only while the robot heads within this angle of the leg's direction,
/// rad (8.6°: 1 % error in the along-corridor distance).
const DOOR_MAX_OFF_AXIS_RAD: f64 = 0.15;

/// While the matched door stays in view, each frame moves the progress this fraction of the way
/// to where the frame's door distance puts it (about ten frames' average).
const DOOR_TRACK_GAIN: f64 = 0.1;
/// A door seen ahead is placed by the median of the places along the leg that the last this
/// many frames give it, once they agree within `landmark_gate_m`, not by the first frame: one
/// frame's door distance is off by 10–20 %, and a plane fitted across an open corridor (the
/// scattered depths of its far end) is named a door at a range that jumps by metres from frame
/// to frame. One such frame moved the progress 0.76 m back, and the robot stopped 0.94 m from
/// its goal.
const DOOR_AHEAD_FRAMES: usize = 3;
/// Doors are taken from the openings of walls whose fitted direction agrees with the estimated
/// heading within this, rad ([`WallSighting::door_openings`]): the openings of worse fits are
/// off by twice as much.
const SIDE_DOOR_WALL_GATE_RAD: f64 = 0.1;
/// The first this many frames that see an expected door in a side wall place it (one frame's
/// opening is off by a quarter metre, and one mis-binned jamb by more); later frames refine the
/// place ([`super::side_doors`]).
const SIDE_DOOR_FIRST_FRAMES: usize = 5;
/// Below this speed the side walls' openings are not taken, m/s.
const SIDE_DOOR_MIN_SPEED_M_S: f64 = 0.1;
/// The wall-ahead fix ([`Pafsis::wall_ahead`]) takes walls up to this far ahead: nearer, a
/// frontal plane's distance from the flow is good to a few per cent.
const WALL_AHEAD_MAX_RANGE_M: f64 = 3.0;
/// ... and no nearer than this: a door up to 1 m wide then takes at most ±18° of the C310's
/// ±27° view, and the wall beside it stays in the plane fit.
const WALL_AHEAD_MIN_RANGE_M: f64 = 1.5;
/// The first this many sightings of a leg place its end (their median) ...
const WALL_AHEAD_FIRST_FRAMES: usize = 2;
/// ... after which each frame moves the progress this fraction of the disagreement.
const WALL_AHEAD_GAIN: f64 = 0.25;

/// A straight leg that follows the current one within this angle continues it
/// ([`Pafsis::stop_ahead_m`]), rad.
const STRAIGHT_ON_RAD: f64 = 0.05;

/// Without the corridor's width, a door place this far from a leg's line is beside it, m.
const DOOR_PLACE_MAX_OFFSET_M: f64 = 1.0;

/// A door the robot expects to pass (or stop at) on a corridor leg.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ExpectedDoor {
    /// The door's place name, when the map names it.
    pub name: Option<String>,
    pub side: Option<Side>,
    /// Where it lies along the leg, m from the leg's start, when the map says so.
    pub at_m: Option<f64>,
    /// Whether the door is only beside the leg (a door place the leg's edges do not stop at,
    /// placed along the leg by its position on the map: `add_doors_beside`): it is matched only
    /// where it is seen in a side wall, whose side tells it from the door facing it.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub beside: bool,
}

/// What ends a corridor leg.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub enum LegEnd {
    /// The odometric length (corrected by door sightings).
    Distance,
    /// Abeam this door: the last entry of the leg's doors.
    Door,
    /// A corner seen ahead within the stop distance.
    Corner,
    /// A wall seen ahead within the stop distance.
    Wall,
}

/// One elementary motion of the plan.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub enum LegKind {
    /// Turn on the spot to `heading_rad` (map frame).
    Turn,
    /// Drive straight through `door` for `length_m`.
    Doorway { door: String, length_m: f64 },
    /// Follow a corridor for about `length_m`, passing `doors` (the target door last when the
    /// leg ends at a door).
    Corridor { length_m: f64, doors: Vec<ExpectedDoor>, end: LegEnd },
}

/// A leg: what to do, in which map direction, and which place it leads to.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Leg {
    pub kind: LegKind,
    /// Map-frame heading of the leg (the target heading for a turn), rad.
    pub heading_rad: f64,
    /// The place reached when the map edge this leg belongs to is done (used to re-localise).
    pub leads_to: String,
    /// A metric line the leg follows (a point and the heading), when the map has positions;
    /// used only with a pose hint.
    pub line_point_m: Option<[f64; 2]>,
    /// The corridor around that line, part by part along the leg (corridor legs; one part per
    /// map edge merged into the leg): a corridor of varied widths keeps each part's width.
    pub lane: Vec<LanePart>,
    /// A doorway leg's door where the map gives it: the opening's centre in the map frame
    /// (on the leg's line, [`Action::opening`]'s distance before its end) and its width, m.
    pub door_m: Option<([f64; 2], f64)>,
    /// A corridor leg that ends facing a door: how far beyond the leg's end the door's wall
    /// stands, m (the map's door place in front of a door, and the door's edge onward). The
    /// wall seen ahead then says how far the leg has left to go ([`Pafsis`]'s wall-ahead fix).
    pub wall_beyond_m: Option<f64>,
}

impl fmt::Display for Leg {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.kind {
            LegKind::Turn => write!(f, "turn to {:.0}°", self.heading_rad.to_degrees()),
            LegKind::Doorway { door, length_m } => write!(f, "go through {door} ({length_m:.1} m)"),
            LegKind::Corridor { length_m, doors, end } => {
                let count = |s: Side| doors.iter().filter(|d| d.side == Some(s)).count();
                let (mut l, mut r) = (count(Side::Left), count(Side::Right));
                let last = doors.last().filter(|_| *end == LegEnd::Door);
                if let Some(d) = last {
                    match d.side {
                        Some(Side::Left) => l -= 1,
                        Some(Side::Right) => r -= 1,
                        None => {}
                    }
                }
                write!(f, "follow the corridor {length_m:.1} m passing {l} doors left, {r} right")?;
                match (end, last) {
                    (LegEnd::Door, Some(d)) => write!(f, ", stop at {}", d.name.as_deref().unwrap_or("the door")),
                    (LegEnd::Corner, _) => write!(f, " until the corner"),
                    (LegEnd::Wall, _) => write!(f, " until the wall"),
                    _ => Ok(()),
                }
            }
        }
    }
}

/// One stretch of a corridor leg's lane: it ends `until_m` along the leg, with the width the map
/// gives it (`None`: the map gives none).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct LanePart {
    pub until_m: f64,
    pub width_m: Option<f64>,
}

impl Leg {
    /// The corridor's width around `along_m` along this leg, m: the narrowest part that lies
    /// within `slack_m` of it (progress is an estimate, and a robot believed past a step into a
    /// wider part may still be in the narrower one); `None` when any such part has no width.
    pub fn lane_width_at(&self, along_m: f64, slack_m: f64) -> Option<f64> {
        let (lo, hi) = (along_m - slack_m, along_m + slack_m);
        let mut start = 0.0;
        let mut width: Option<f64> = None;
        for (i, part) in self.lane.iter().enumerate() {
            let last = i + 1 == self.lane.len();
            // the first part reaches back before the leg's start, the last beyond its end
            let overlaps = (i == 0 || hi >= start) && (last || lo <= part.until_m);
            if overlaps {
                let w = part.width_m?;
                width = Some(width.map_or(w, |a: f64| a.min(w)));
            }
            start = part.until_m;
        }
        width
    }
}

/// Unrolls a plan into legs, starting with the robot facing `start_heading_rad` (map frame).
/// A turn on the spot is inserted wherever the robot would start an edge facing another way
/// than the edge's `heading_deg`; consecutive straight corridor edges merge into one leg whose
/// intermediate stops become doors to pass (with known positions).
pub fn unroll(map: &TopoMap, plan: &Plan, start_heading_rad: f64) -> Vec<Leg> {
    const ALIGN_TOLERANCE_RAD: f64 = 0.02;
    let mut legs: Vec<Leg> = Vec::new();
    let mut heading = start_heading_rad;
    for &k in &plan.edges {
        let edge = &map.edges[k];
        let edge_heading = wrap_angle(edge.heading_deg.to_radians());
        let point = map.place(&edge.to).and_then(|p| p.position_m);
        let mut turned = false;
        if wrap_angle(edge_heading - heading).abs() > ALIGN_TOLERANCE_RAD {
            legs.push(Leg {
                kind: LegKind::Turn,
                heading_rad: edge_heading,
                leads_to: edge.to.clone(),
                line_point_m: None,
                lane: Vec::new(),
                door_m: None,
                wall_beyond_m: None,
            });
            turned = true;
        }
        heading = edge_heading;
        for (i, action) in edge.actions.iter().enumerate() {
            let leg = |kind, heading_rad| Leg {
                kind,
                heading_rad,
                leads_to: edge.to.clone(),
                line_point_m: point,
                lane: Vec::new(),
                door_m: None,
                wall_beyond_m: None,
            };
            match action {
                Action::ExitRoom { door, length_m, .. }
                | Action::EnterRoom { door, length_m, .. }
                | Action::GoThroughDoor { door, length_m, .. } => {
                    // the door, placed back from the edge's end: for the edge's last action
                    let last = i + 1 == edge.actions.len();
                    let door_m = match (action.opening(), point, last) {
                        (Some((width, before)), Some([x, y]), true) => {
                            Some(([x - before * heading.cos(), y - before * heading.sin()], width))
                        }
                        _ => None,
                    };
                    legs.push(Leg {
                        door_m,
                        ..leg(LegKind::Doorway { door: door.clone(), length_m: *length_m }, heading)
                    });
                    turned = false;
                }
                Action::Turn { .. } => {
                    heading = wrap_angle(heading + action.turn_rad());
                    legs.push(Leg { line_point_m: None, ..leg(LegKind::Turn, heading) });
                    turned = true;
                }
                Action::FollowCorridor { length_m, doors_left, doors_right, until, width_m } => {
                    let unnamed = |n: u32, side| {
                        (0..n).map(move |_| ExpectedDoor { name: None, side: Some(side), at_m: None, beside: false })
                    };
                    let new_doors = unnamed(*doors_left, Side::Left).chain(unnamed(*doors_right, Side::Right));
                    let end = match until {
                        Until::Distance => LegEnd::Distance,
                        Until::Corner => LegEnd::Corner,
                        Until::Wall => LegEnd::Wall,
                    };
                    let mergeable = !turned
                        && legs.last().is_some_and(|l| {
                            matches!(&l.kind, LegKind::Corridor { end: LegEnd::Door | LegEnd::Distance, .. })
                                && wrap_angle(l.heading_rad - heading).abs() <= ALIGN_TOLERANCE_RAD
                        });
                    if mergeable && let Some(last) = legs.last_mut() {
                        if let LegKind::Corridor { length_m: l0, doors, end: e0 } = &mut last.kind {
                            *l0 += length_m;
                            doors.extend(new_doors);
                            *e0 = end;
                            last.lane.push(LanePart { until_m: *l0, width_m: *width_m });
                        }
                        last.leads_to = edge.to.clone();
                        last.line_point_m = point;
                    } else {
                        legs.push(Leg {
                            lane: vec![LanePart { until_m: *length_m, width_m: *width_m }],
                            ..leg(LegKind::Corridor { length_m: *length_m, doors: new_doors.collect(), end }, heading)
                        });
                    }
                    turned = false;
                }
                Action::StopAtDoor { door, side } => {
                    if let Some(Leg { kind: LegKind::Corridor { length_m, doors, end }, .. }) = legs.last_mut() {
                        doors.push(ExpectedDoor {
                            name: Some(door.clone()),
                            side: Some(*side),
                            at_m: Some(*length_m),
                            beside: false,
                        });
                        *end = LegEnd::Door;
                    }
                }
            }
        }
    }
    for leg in &mut legs {
        add_doors_beside(map, leg);
        if matches!(leg.kind, LegKind::Corridor { end: LegEnd::Distance, .. }) {
            leg.wall_beyond_m = door_wall_beyond(map, &leg.leads_to, leg.heading_rad);
        }
    }
    legs
}

/// The map's door places beside corridor leg `leg` that its actions do not name (doors on the
/// far side, doors between the places it stops at), placed along it by their positions: each
/// is one more landmark to correct the progress with (paper §2.2: doors on either side). Only
/// where the map gives positions and every door the leg expects has a place along it; not the
/// door the leg starts beside (the robot came out of it).
fn add_doors_beside(map: &TopoMap, leg: &mut Leg) {
    const MIN_ALONG_M: f64 = 0.5;
    let Some(end) = leg.line_point_m else { return };
    let half_width =
        leg.lane.iter().filter_map(|p| p.width_m).fold(None, |m: Option<f64>, w| Some(m.map_or(w, |m: f64| m.max(w))));
    let LegKind::Corridor { length_m, doors, end: leg_end } = &mut leg.kind else { return };
    if doors.iter().any(|d| d.at_m.is_none()) {
        return;
    }
    let half_width = half_width.map_or(DOOR_PLACE_MAX_OFFSET_M, |w| 0.5 * w);
    let stop = if *leg_end == LegEnd::Door { doors.pop() } else { None };
    let (s, c) = leg.heading_rad.sin_cos();
    for p in map.places.iter().filter(|p| p.kind == PlaceKind::Door) {
        let named = |d: &ExpectedDoor| d.name.as_deref() == Some(p.name.as_str());
        let Some([x, y]) = p.position_m.filter(|_| p.name != leg.leads_to && !doors.iter().chain(&stop).any(named))
        else {
            continue;
        };
        let (dx, dy) = (x - end[0], y - end[1]);
        let (at_m, left) = (*length_m + dx * c + dy * s, -dx * s + dy * c);
        if at_m < MIN_ALONG_M || at_m > *length_m || left.abs() > half_width {
            continue;
        }
        let side = if left > 0.0 { Side::Left } else { Side::Right };
        doors.push(ExpectedDoor { name: Some(p.name.clone()), side: Some(side), at_m: Some(at_m), beside: true });
    }
    doors.sort_by(|a, b| a.at_m.unwrap_or(0.0).total_cmp(&b.at_m.unwrap_or(0.0)));
    doors.extend(stop);
}

/// Where the map puts a door straight ahead of a robot that stops at `place` facing
/// `heading_rad`: an edge out of `place` along that heading whose first action goes through a
/// door with a known opening; how far beyond `place` the door's wall stands, m.
fn door_wall_beyond(map: &TopoMap, place: &str, heading_rad: f64) -> Option<f64> {
    const ALONG_RAD: f64 = 0.1;
    map.edges
        .iter()
        .filter(|e| e.from == place && wrap_angle(e.heading_deg.to_radians() - heading_rad).abs() <= ALONG_RAD)
        .find_map(|e| {
            let first = e.actions.first()?;
            let (_, before) = first.opening()?;
            Some(first.length_m() - before).filter(|b| b.is_finite() && *b >= 0.0)
        })
}

/// What the planner wants this step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Goal {
    /// Goal-oriented velocity: the leg's speed, m/s (≥ 0), whatever the goal angle (MOFIS turns
    /// toward the goal, or the way past what blocks it, and slows for the turn).
    pub velocity: f64,
    /// Goal-oriented angle: where the local goal lies relative to the heading, rad, + = left.
    pub angle_rad: f64,
    pub status: GoalStatus,
}

/// Where the mission stands.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum GoalStatus {
    #[default]
    Active,
    Arrived,
    /// Landmarks kept failing to appear; the robot must stop.
    Failed,
}

/// Notable things that happened during a step (for the terminal and the log).
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum PafsisEvent {
    LegStarted {
        index: usize,
        leg: String,
    },
    /// A door sighting matched an expected door; `correction_m` moved the progress estimate.
    /// `side` is where the door was seen: an opening in the left or right wall, or (`None`)
    /// the door's wall ahead.
    DoorMatched {
        door: Option<String>,
        at_m: Option<f64>,
        correction_m: f64,
        side: Option<Side>,
    },
    /// A wall or door seen straight ahead placed the end of leg `leg` ([`Leg::wall_beyond_m`]):
    /// first seen `distance_m` ahead, moving the progress by `correction_m` (later frames of
    /// the same leg move it further without an event).
    WallAheadMatched {
        leg: usize,
        distance_m: f64,
        correction_m: f64,
    },
    /// A door sighting that matched nothing expected.
    DoorIgnored {
        estimated_at_m: Option<f64>,
    },
    LandmarkMissed {
        leg: usize,
        what: String,
    },
    Replanned {
        from: String,
        waypoints: Vec<String>,
    },
    Arrived {
        place: String,
    },
    Failed {
        reason: String,
    },
}

/// An external, metric pose (the simulator's ground truth, or a future localiser): map-frame
/// position, m, and heading, rad. Optional: the planner works without it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PoseHint {
    pub x: f64,
    pub y: f64,
    pub heading_rad: f64,
}

/// The corridor the robot is in, in the robot's frame, from the map's width and the
/// dead-reckoned pose: the steering keeps inside it ([`crate::mofis::memory::ObstacleMemory::steer`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Lane {
    /// How far the robot's origin is left of the corridor's centre line, m.
    pub left_m: f64,
    /// Direction of the centre line (the leg's heading) relative to the robot's heading, rad,
    /// + left.
    pub angle_rad: f64,
    /// Half the corridor's width, m.
    pub half_width_m: f64,
}

impl Lane {
    /// How far a point of the robot's frame (ahead, left; m) is left of the corridor's centre
    /// line, m. The lane's left is (−sin, cos) of its angle; the returned function takes those
    /// once, for the many points of a grid.
    pub fn offset_of(&self) -> impl Fn([f64; 2]) -> f64 + Copy + use<> {
        let (s, c) = self.angle_rad.sin_cos();
        let left = self.left_m;
        move |[f, l]| left - f * s + l * c
    }
}

/// The door the robot is going through, in the robot's frame, from the map's opening
/// ([`crate::pafsis::map::Action::opening`]) and the dead-reckoned pose: the steering keeps the
/// robot's footprint off the wall either side of it
/// ([`crate::mofis::memory::ObstacleMemory::set_doorway`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Doorway {
    /// The opening's centre, m: ahead of and left of the robot's origin.
    pub centre_m: [f64; 2],
    /// Direction through the door (the leg's heading) relative to the robot's heading, rad,
    /// + left; the door's wall runs across it.
    pub angle_rad: f64,
    /// Half the opening, jamb to jamb, m.
    pub half_width_m: f64,
}

/// Progress along the plan, for display.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Progress {
    pub leg: usize,
    pub legs: usize,
    pub description: String,
    /// Distance along the current leg, m (landmark-corrected).
    pub along_m: f64,
    /// Doors of the current leg already passed (sighted or missed).
    pub doors_passed: usize,
    /// Of those, how many were actually sighted.
    pub doors_sighted: usize,
    pub replans: u32,
    /// Heading estimate, rad, map frame.
    pub heading_rad: f64,
}

/// The PAFSIS planner: global plan + local state machine.
#[derive(Clone, Debug)]
pub struct Pafsis {
    map: TopoMap,
    mission: Mission,
    params: PafsisParams,
    plan: Plan,
    legs: Vec<Leg>,
    leg: usize,
    /// Distance along the current leg, m.
    along_m: f64,
    /// Index of the next expected door in the current corridor leg.
    next_door: usize,
    doors_sighted: usize,
    heading_rad: f64,
    /// Dead-reckoned position in the map frame, m: from the start place's position and the
    /// odometry (`None` when the map gives the start place no position).
    position_m: Option<[f64; 2]>,
    /// Distance driven since the start (forward or back), m, and the last speed, m/s.
    odometer_m: f64,
    speed_m_s: f64,
    /// The cross-track correction pauses until the odometer reaches this (an obstacle is being
    /// passed), m.
    hold_line_until_m: f64,
    /// The TPO shape seen in the last consecutive frames, and how many.
    streak: (TpoShape, u32),
    /// Consecutive frames in which a corner, a wall or something solid was seen ahead within the
    /// stop distance (the end of a corner- or wall-ended corridor).
    end_streak: u32,
    door_sighting_reported: bool,
    /// Expected position of the door matched in the current streak of door frames.
    tracking: Option<f64>,
    /// The current leg's doors matched so far ([`door_bit`]).
    matched_doors: u64,
    /// The doors of the current leg seen in its side walls, and their sightings
    /// ([`side_doors`](super::side_doors)).
    side_door_tracks: Vec<SideDoorTrack>,
    /// Progress along the current leg from odometry alone, without the landmarks' corrections,
    /// m: the frame the side doors' sightings are placed in.
    dead_along_m: f64,
    last_door_distance: Option<f64>,
    /// Where the last frames of the current streak of door frames put the door along the leg,
    /// m, until [`DOOR_AHEAD_FRAMES`] of them agree ([`Pafsis::door_ahead_place`]).
    door_ahead_recent: Vec<f64>,
    replans: u32,
    status: GoalStatus,
    events: Vec<PafsisEvent>,
    /// Side walls of the current frame ([`Pafsis::observe_walls`]), taken by the next step.
    walls: Vec<WallSighting>,
    wall_fixes: WallFixes,
    flow_fixes: u64,
    /// Legs whose end was placed from the wall seen ahead ([`Leg::wall_beyond_m`]), and whether
    /// the current leg's was.
    walls_ahead_matched: u64,
    wall_ahead_seen: bool,
    /// The current leg's first wall-ahead disagreements, m, until there are
    /// [`WALL_AHEAD_FIRST_FRAMES`].
    wall_ahead_first: Vec<f64>,
}

/// How much the side walls have moved the estimate so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct WallFixes {
    /// Frames whose side walls corrected the heading or the offset from the centre line.
    pub frames: u64,
    /// Sum of the heading corrections' sizes, rad.
    pub heading_rad: f64,
    /// Sum of the lateral corrections' sizes, m.
    pub lateral_m: f64,
}

impl Pafsis {
    /// Plans `mission` on `map`. The robot starts at the mission's first place, facing that
    /// place's `heading_deg` (or the first edge's direction when the map gives none).
    pub fn new(map: TopoMap, mission: Mission, params: PafsisParams) -> Result<Self, PlanError> {
        let plan = plan(&map, &mission)?;
        let start_heading = map
            .place(&mission.from)
            .and_then(|p| p.heading_deg)
            .map(f64::to_radians)
            .or_else(|| plan.edges.first().map(|&k| map.edges[k].heading_deg.to_radians()))
            .unwrap_or(0.0);
        let legs = unroll(&map, &plan, start_heading);
        let position_m = map.place(&mission.from).and_then(|p| p.position_m);
        let mut me = Self {
            map,
            mission,
            params,
            plan,
            legs,
            leg: 0,
            along_m: 0.0,
            next_door: 0,
            doors_sighted: 0,
            heading_rad: wrap_angle(start_heading),
            position_m,
            odometer_m: 0.0,
            speed_m_s: 0.0,
            hold_line_until_m: 0.0,
            streak: (TpoShape::None, 0),
            end_streak: 0,
            door_sighting_reported: false,
            tracking: None,
            matched_doors: 0,
            side_door_tracks: Vec::new(),
            dead_along_m: 0.0,
            last_door_distance: None,
            door_ahead_recent: Vec::with_capacity(DOOR_AHEAD_FRAMES),
            replans: 0,
            status: GoalStatus::Active,
            events: Vec::new(),
            walls: Vec::new(),
            wall_fixes: WallFixes::default(),
            flow_fixes: 0,
            walls_ahead_matched: 0,
            wall_ahead_seen: false,
            wall_ahead_first: Vec::new(),
        };
        me.start_leg(0);
        Ok(me)
    }

    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    pub fn legs(&self) -> &[Leg] {
        &self.legs
    }

    pub fn mission(&self) -> &Mission {
        &self.mission
    }

    pub fn map(&self) -> &TopoMap {
        &self.map
    }

    pub fn status(&self) -> GoalStatus {
        self.status
    }

    /// Takes the events since the last call.
    pub fn take_events(&mut self) -> Vec<PafsisEvent> {
        std::mem::take(&mut self.events)
    }

    pub fn progress(&self) -> Progress {
        let (doors_passed, description) = match self.legs.get(self.leg) {
            Some(l) => (self.next_door, l.to_string()),
            None => (0, format!("at {}", self.mission.to)),
        };
        Progress {
            leg: self.leg,
            legs: self.legs.len(),
            description,
            along_m: self.along_m,
            doors_passed,
            doors_sighted: self.doors_sighted,
            replans: self.replans,
            heading_rad: self.heading_rad,
        }
    }

    /// How far ahead the plan stops the robot, m: the rest of the current leg plus the straight
    /// legs after it in the same direction, up to the next turn on the spot or the mission's end.
    /// `None` when the robot is not driving toward a stop it can measure by odometry (a turn, a
    /// leg that ends where a corner or wall is seen, a mission that is over).
    ///
    /// Nothing farther than this along the path is in the robot's way: a door's jambs or a wall
    /// beyond the place where it turns need no avoiding (they were what made it dither before
    /// every turn).
    pub fn stop_ahead_m(&self) -> Option<f64> {
        if self.status != GoalStatus::Active {
            return None;
        }
        let current = self.legs.get(self.leg)?;
        let straight = |leg: &Leg| match &leg.kind {
            LegKind::Doorway { length_m, .. } => Some(*length_m),
            LegKind::Corridor { length_m, end: LegEnd::Distance | LegEnd::Door, .. } => Some(*length_m),
            LegKind::Turn | LegKind::Corridor { .. } => None,
        };
        let mut ahead = (straight(current)? - self.along_m).max(0.0);
        for leg in &self.legs[self.leg + 1..] {
            if matches!(leg.kind, LegKind::Turn) {
                break;
            }
            if wrap_angle(leg.heading_rad - current.heading_rad).abs() > STRAIGHT_ON_RAD {
                return None;
            }
            ahead += straight(leg)?;
        }
        Some(ahead)
    }

    /// The straight walls OFFIS fitted in the frame the next [`Pafsis::step`] takes; on a
    /// corridor leg, side walls correct the heading and the offset from the centre line
    /// ([`super::walls`]).
    pub fn observe_walls(&mut self, walls: &[WallSighting]) {
        self.walls.clear();
        self.walls.extend_from_slice(walls);
    }

    /// How much side walls have corrected the estimate so far.
    pub fn wall_fixes(&self) -> WallFixes {
        self.wall_fixes
    }

    /// The flow of a keyframe pair says the robot turned `fix_rad` more than the odometry
    /// ([`crate::odometry_calibration`]): the heading takes it.
    pub fn correct_heading(&mut self, fix_rad: f64) {
        if self.status != GoalStatus::Active || !fix_rad.is_finite() {
            return;
        }
        self.heading_rad = wrap_angle(self.heading_rad + fix_rad);
        self.flow_fixes += 1;
    }

    /// How many keyframe pairs' flow corrected the heading so far.
    pub fn flow_fixes(&self) -> u64 {
        self.flow_fixes
    }

    /// Applies the side walls of the frame to the heading and the dead-reckoned offset.
    fn correct_from_walls(&mut self) {
        let Some(leg) = self.legs.get(self.leg) else { return };
        if !matches!(leg.kind, LegKind::Corridor { .. }) || self.walls.is_empty() {
            return;
        }
        let heading_rel = wrap_angle(self.heading_rad - leg.heading_rad);
        let width = leg.lane_width_at(self.along_m, self.map.tolerance.window_m(self.along_m));
        let lane = match (width, leg.line_point_m, self.position_m) {
            (Some(width), Some(point), Some(position)) => {
                Some((left_of_line(position, point, leg.heading_rad), 0.5 * width))
            }
            _ => None,
        };
        let leg_heading = leg.heading_rad;
        let innovation = walls::innovation(&self.walls, heading_rel, lane, &WallGates::default());
        let (heading_gain, lateral_gain) = (self.params.wall_heading_gain, self.params.wall_lateral_gain);
        let heading = innovation.heading_rad.filter(|_| heading_gain > 0.0).map(|d| heading_gain * d);
        let lateral = innovation.lateral_m.filter(|_| lateral_gain > 0.0).map(|d| lateral_gain * d);
        if let Some(fix) = heading {
            self.heading_rad = wrap_angle(self.heading_rad + fix);
            self.wall_fixes.heading_rad += fix.abs();
        }
        let drift = self.params.wall_drift_gain;
        if let (Some(d), true) = (innovation.lateral_m, drift > 0.0 && self.speed_m_s >= DRIFT_MIN_SPEED_M_S) {
            let fix = drift * d;
            self.heading_rad = wrap_angle(self.heading_rad + fix);
            self.wall_fixes.heading_rad += fix.abs();
        }
        if let (Some(fix), Some([x, y])) = (lateral, &mut self.position_m) {
            // Along the leg's left normal.
            *x -= fix * leg_heading.sin();
            *y += fix * leg_heading.cos();
            self.wall_fixes.lateral_m += fix.abs();
        }
        if heading.is_some() || lateral.is_some() || (drift > 0.0 && innovation.lateral_m.is_some()) {
            self.wall_fixes.frames += 1;
        }
    }

    /// Integrates odometry only: for steps without perception (the robot is being stopped),
    /// so that progress stays right.
    pub fn advance_odometry(&mut self, odo: BodyVelocity, dt: f64) {
        if !(dt.is_finite() && dt > 0.0 && odo.v.is_finite() && odo.omega.is_finite()) {
            return;
        }
        let mid = self.heading_rad + 0.5 * odo.omega * dt;
        if let Some([x, y]) = &mut self.position_m {
            *x += odo.v * dt * mid.cos();
            *y += odo.v * dt * mid.sin();
        }
        self.heading_rad = wrap_angle(self.heading_rad + odo.omega * dt);
        self.odometer_m += odo.v.abs() * dt;
        self.speed_m_s = odo.v;
        if let Some(leg) = self.legs.get(self.leg)
            && !matches!(leg.kind, LegKind::Turn)
        {
            let ds = odo.v * dt * (self.heading_rad - leg.heading_rad).cos();
            self.along_m += ds;
            self.dead_along_m += ds;
        }
    }

    /// One control step: integrate odometry (`odo` measured over the last `dt` seconds), take in
    /// the landmarks of `perception`, advance the state machine, and return the goal.
    pub fn step(&mut self, perception: &Perception, odo: BodyVelocity, dt: f64) -> Goal {
        self.step_with_hint(perception, odo, dt, None)
    }

    /// [`Pafsis::step`] with an optional metric pose. A hint replaces the odometric heading and
    /// adds a cross-track correction toward the leg's line when the map has positions; progress
    /// along legs, landmarks, arrival and replanning stay landmark + odometry based.
    pub fn step_with_hint(
        &mut self,
        perception: &Perception,
        odo: BodyVelocity,
        dt: f64,
        hint: Option<PoseHint>,
    ) -> Goal {
        self.advance_odometry(odo, dt);
        if let Some(h) = hint.filter(|h| h.heading_rad.is_finite()) {
            self.heading_rad = wrap_angle(h.heading_rad);
            self.position_m = Some([h.x, h.y]);
        }
        if self.status != GoalStatus::Active {
            return Goal { velocity: 0.0, angle_rad: 0.0, status: self.status };
        }
        self.side_doors();
        if hint.is_none() {
            self.correct_from_walls();
        }
        self.walls.clear();
        self.observe(perception);
        if let (true, Some(d)) = (perception.obstacle.present, perception.obstacle.distance_m)
            && d.is_finite()
            && d <= HOLD_LINE_RANGE_M
        {
            let until = self.odometer_m + d.max(0.0) + self.params.cross_track_hold_m;
            self.hold_line_until_m = self.hold_line_until_m.max(until);
        }
        // A leg may finish and the next one start within one step; bounded by the leg count.
        for _ in 0..=self.legs.len() {
            if self.status != GoalStatus::Active {
                break;
            }
            if !self.leg_done() {
                break;
            }
        }
        if self.status != GoalStatus::Active {
            return Goal { velocity: 0.0, angle_rad: 0.0, status: self.status };
        }
        let dead_reckoned = match (self.params.cross_track_odometry, self.position_m) {
            (true, Some([x, y])) => Some(PoseHint { x, y, heading_rad: self.heading_rad }),
            _ => None,
        };
        self.command(perception, hint.or(dead_reckoned))
    }

    /// The corridor lane of the current leg, where the map gives the corridor's width and the
    /// start place a position (so that the dead-reckoned position is in the map frame); `None`
    /// otherwise, and when no leg is active.
    pub fn lane(&self) -> Option<Lane> {
        if self.status != GoalStatus::Active {
            return None;
        }
        let leg = self.legs.get(self.leg)?;
        let width = leg.lane_width_at(self.along_m, self.map.tolerance.window_m(self.along_m))?;
        let (point, position) = (leg.line_point_m?, self.position_m?);
        Some(Lane {
            left_m: left_of_line(position, point, leg.heading_rad),
            angle_rad: wrap_angle(leg.heading_rad - self.heading_rad),
            half_width_m: 0.5 * width,
        })
    }

    /// The door of the current leg, where the map gives its opening and the start place a
    /// position; `None` otherwise, and when no leg is active.
    pub fn doorway(&self) -> Option<Doorway> {
        if self.status != GoalStatus::Active {
            return None;
        }
        let leg = self.legs.get(self.leg)?;
        let (([cx, cy], width), [x, y]) = (leg.door_m?, self.position_m?);
        let (s, c) = self.heading_rad.sin_cos();
        let (dx, dy) = (cx - x, cy - y);
        Some(Doorway {
            centre_m: [c * dx + s * dy, -s * dx + c * dy],
            angle_rad: wrap_angle(leg.heading_rad - self.heading_rad),
            half_width_m: 0.5 * width,
        })
    }

    /// The dead-reckoned position in the map frame, m (module doc of [`PafsisParams`]'s
    /// `cross_track_odometry`); `None` when the start place has no position.
    pub fn position_m(&self) -> Option<[f64; 2]> {
        self.position_m
    }

    /// Updates the shape streak and handles door sightings on corridor legs.
    fn observe(&mut self, p: &Perception) {
        let confident = p.tpo.confidence >= self.params.landmark_min_confidence;
        let shape = if confident { p.tpo.shape } else { TpoShape::None };
        if shape == self.streak.0 {
            self.streak.1 = self.streak.1.saturating_add(1);
        } else {
            self.streak = (shape, 1);
            self.door_sighting_reported = false;
            self.door_ahead_recent.clear();
        }
        let stop = self.params.stop_distance_m;
        let end_ahead = (matches!(shape, TpoShape::Corner | TpoShape::Wall)
            && p.tpo.distance_m.is_some_and(|d| d <= stop))
            || (p.obstacle.present
                && p.obstacle.distance_m.is_some_and(|d| d <= stop)
                && p.obstacle.bearing_rad.is_some_and(|b| b.abs() <= END_AHEAD_MAX_BEARING_RAD));
        self.end_streak = if end_ahead { self.end_streak.saturating_add(1) } else { 0 };
        self.wall_ahead(shape, p);
        if shape != TpoShape::Door {
            self.tracking = None;
            self.last_door_distance = None;
            return;
        }
        // A door's distance is measured along the optical axis: looking obliquely (swerving
        // round an obstacle), it is the range to some point of the side wall, not how far along
        // the corridor the door is. Such frames neither match nor pin.
        if let Some(leg) = self.legs.get(self.leg)
            && wrap_angle(self.heading_rad - leg.heading_rad).abs() > DOOR_MAX_OFF_AXIS_RAD
        {
            return;
        }
        if self.streak.1 < self.params.landmark_min_frames {
            return;
        }
        let distance = p.tpo.distance_m.filter(|d| d.is_finite() && *d >= 0.0 && *d <= self.params.door_max_range_m);
        // Within one streak of door frames, a distance that jumps up means the next door came
        // into view: a new sighting.
        let new_door = match (distance, self.last_door_distance) {
            (Some(d), Some(prev)) => d > prev + NEW_DOOR_JUMP_M,
            _ => false,
        };
        if let Some(d) = distance {
            self.last_door_distance = Some(d);
        }
        if new_door {
            // the next door: placed afresh from its own frames (the matched door's tracking
            // is not read again before a new sighting resets it)
            self.door_sighting_reported = false;
            self.door_ahead_recent.clear();
        }
        if !self.door_sighting_reported {
            let sighting = match distance {
                // without a distance the sighting says only that a door is passed
                None if self.door_ahead_recent.is_empty() => Some(None),
                None => None,
                Some(d) => self.door_ahead_place(self.along_m + d).map(Some),
            };
            if let Some(seen_at) = sighting {
                self.door_sighting_reported = true;
                self.tracking = None;
                self.door_sighted(seen_at);
            }
        } else if let (Some(at), Some(d)) = (self.tracking, distance) {
            // Still looking at the matched door: pull the progress toward what each frame says,
            // a little per frame (one frame's door distance is off by 10–20 %), and not at all
            // from a frame that disagrees by more than the gate (another surface, a mis-ranged
            // door; pinning to every frame moved the progress 0.74 m on from one such frame).
            let innovation = at - d - self.along_m;
            if innovation.abs() <= self.params.landmark_gate_m {
                self.along_m += DOOR_TRACK_GAIN * innovation;
            }
        }
    }

    /// The wall-ahead fix: on a leg that ends facing a door ([`Leg::wall_beyond_m`]), a wall or a
    /// door seen straight ahead for `landmark_min_frames` frames, between
    /// [`WALL_AHEAD_MIN_RANGE_M`] and [`WALL_AHEAD_MAX_RANGE_M`] away (and expected no nearer
    /// than the former), says how far the leg's end is. A robot that drifted sideways in a wide corridor turns into such a leg off its place
    /// by the drift (dead reckoning cannot see it), and the leg's length alone then ends it that
    /// far off. The median of the first [`WALL_AHEAD_FIRST_FRAMES`] sightings places the
    /// progress, each gated by what the robot can be off: the map's window round the leg's
    /// length plus half the corridor it came from. Later frames
    /// move it by [`WALL_AHEAD_GAIN`] of what they say, and only within `landmark_gate_m`: near
    /// the door the view goes through the opening, and the room's far wall must not pull the
    /// robot in.
    fn wall_ahead(&mut self, shape: TpoShape, p: &Perception) {
        let Some(leg) = self.legs.get(self.leg) else { return };
        let (LegKind::Corridor { length_m, .. }, Some(beyond)) = (&leg.kind, leg.wall_beyond_m) else {
            return;
        };
        if !matches!(shape, TpoShape::Wall | TpoShape::Door)
            || self.streak.1 < self.params.landmark_min_frames
            || wrap_angle(self.heading_rad - leg.heading_rad).abs() > DOOR_MAX_OFF_AXIS_RAD
        {
            return;
        }
        // where the wall should be: nearer, the door's opening fills much of the view, and what
        // is measured may be the room beyond it
        let expected = length_m + beyond - self.along_m;
        let in_range = |d: &f64| d.is_finite() && (WALL_AHEAD_MIN_RANGE_M..=WALL_AHEAD_MAX_RANGE_M).contains(d);
        let Some(d) = p.tpo.distance_m.filter(in_range).filter(|_| expected >= WALL_AHEAD_MIN_RANGE_M) else {
            return;
        };
        let innovation = expected - d;
        if self.wall_ahead_seen {
            if innovation.abs() <= self.params.landmark_gate_m {
                self.along_m += WALL_AHEAD_GAIN * innovation;
            }
            return;
        }
        if innovation.abs() > self.wall_ahead_gate(self.leg) {
            return;
        }
        // the disagreement stays put while the robot drives (both sides move with it): the
        // median of the first few places the leg's end without one mis-ranged frame's error
        self.wall_ahead_first.push(innovation);
        if self.wall_ahead_first.len() < WALL_AHEAD_FIRST_FRAMES {
            return;
        }
        self.wall_ahead_first.sort_by(f64::total_cmp);
        let correction = self.wall_ahead_first[self.wall_ahead_first.len() / 2];
        self.wall_ahead_first.clear();
        self.along_m += correction;
        self.wall_ahead_seen = true;
        self.walls_ahead_matched += 1;
        self.events.push(PafsisEvent::WallAheadMatched { leg: self.leg, distance_m: d, correction_m: correction });
    }

    /// How far the wall-ahead fix of leg `index` may move its progress, m: the map's window
    /// round the leg's length, plus half the width of the corridor leg before it (the robot
    /// may have been anywhere across it when it turned).
    fn wall_ahead_gate(&self, index: usize) -> f64 {
        let Some(leg) = self.legs.get(index) else { return 0.0 };
        let LegKind::Corridor { length_m, .. } = leg.kind else { return 0.0 };
        let came_from = self.legs[..index]
            .iter()
            .rev()
            .find(|l| !matches!(l.kind, LegKind::Turn))
            .filter(|l| matches!(l.kind, LegKind::Corridor { .. }))
            .and_then(|l| l.lane.last().and_then(|part| part.width_m));
        self.map.tolerance.window_m(length_m) + came_from.map_or(0.0, |w| 0.5 * w)
    }

    /// How many legs ended on the wall seen ahead so far (the wall-ahead fix,
    /// `Pafsis::wall_ahead`).
    pub fn walls_ahead_matched(&self) -> u64 {
        self.walls_ahead_matched
    }

    /// Doors seen as openings in the side walls of the frame ([`Pafsis::observe_walls`]): each
    /// door-like opening ([`WallSighting::door_openings`]) in a wall that runs along the leg
    /// says where along the leg a door on that side is.
    fn side_doors(&mut self) {
        let Some(leg) = self.legs.get(self.leg) else { return };
        let LegKind::Corridor { doors, .. } = &leg.kind else { return };
        // standing, the profile is the one carried from the last pairs that measured it
        if doors.is_empty() || self.speed_m_s.abs() < SIDE_DOOR_MIN_SPEED_M_S {
            return;
        }
        let heading_rel = wrap_angle(self.heading_rad - leg.heading_rad);
        let (s, c) = heading_rel.sin_cos();
        let min_length_m = WallGates::default().min_length_m;
        // each opening is placed from the progress as the frame's earlier openings left it
        // (`side_door_sighted`); the walls go back for the side-wall corrections after
        let walls = std::mem::take(&mut self.walls);
        for w in &walls {
            if w.length_m < min_length_m || w.heading_disagreement(heading_rel).abs() > SIDE_DOOR_WALL_GATE_RAD {
                continue;
            }
            let side = if w.offset_m() >= 0.0 { Side::Left } else { Side::Right };
            for [x, y] in w.door_openings() {
                // how far along the leg the opening's centre is ahead of the robot
                let ahead = c * x - s * y;
                tracing::trace!(target: "flownav::pafsis::doors", "door opening side={side:?} x={x:.2} y={y:.2} at={:.2} along={:.2}", self.along_m + ahead, self.along_m);
                self.side_door_sighted(side, ahead, x.hypot(y), w.sin_angle_to([x, y]));
            }
        }
        self.walls = walls;
    }

    /// Whether door `k` of the current leg has been matched.
    fn matched(&self, k: usize) -> bool {
        self.matched_doors & door_bit(k) != 0
    }

    /// Matches a door seen in the `side` wall `ahead_m` along the leg ahead of the robot, at
    /// range `range_m` by a ray meeting the wall with sine `sin_angle`, with the nearest
    /// expected door on that side within its gate, and adds it to that door's sightings
    /// ([`SideDoorTrack`]). The first [`SIDE_DOOR_FIRST_FRAMES`] sightings place the door and
    /// move the progress to agree with it; from then on the progress moves with the door's
    /// place as later, nearer frames refine it.
    fn side_door_sighted(&mut self, side: Side, ahead_m: f64, range_m: f64, sin_angle: f64) {
        // from the progress as it is now: an opening of another door earlier in the same frame
        // may have moved it
        let seen_at = self.along_m + ahead_m;
        let Some(Leg { kind: LegKind::Corridor { doors, .. }, .. }) = self.legs.get(self.leg) else {
            return;
        };
        let nearest = doors
            .iter()
            .enumerate()
            .filter(|(_, d)| d.side.is_none_or(|s| s == side))
            .filter_map(|(k, d)| {
                let innovation = d.at_m? - seen_at;
                (innovation.abs() <= door_gate(&self.params, &self.map.tolerance, d.at_m)).then_some((k, d.at_m?))
            })
            .min_by(|a, b| (a.1 - seen_at).abs().total_cmp(&(b.1 - seen_at).abs()));
        let Some((k, at_m)) = nearest else { return };
        let track = match self.side_door_tracks.iter().position(|t| t.door == k) {
            Some(i) => &mut self.side_door_tracks[i],
            None => {
                self.side_door_tracks.push(SideDoorTrack::new(k));
                self.side_door_tracks.last_mut().expect("just pushed")
            }
        };
        // where the door is in the dead-reckoned frame, which the corrections do not move
        track.add(self.dead_along_m + ahead_m, range_m, sin_angle);
        if track.len() < SIDE_DOOR_FIRST_FRAMES {
            return;
        }
        let Some(place) = track.place() else { return };
        let first = track.placed().is_none();
        let moved = track.apply(place);
        let correction = if first {
            // the door at `at_m` is `place − dead_along` ahead
            at_m - (place - self.dead_along_m) - self.along_m
        } else {
            // a door placed farther on means the robot is less far along
            -moved
        };
        self.along_m += correction;
        tracing::debug!(target: "flownav::pafsis::doors", "door {k} placed at {place:.2} (dead-reckoned), progress moved {correction:+.3} m");
        // a door the view ahead matched already (often without a distance, so without a
        // correction) is placed by its side sightings all the same, but matched only once
        if self.matched(k) {
            return;
        }
        self.matched_doors |= door_bit(k);
        self.doors_sighted += 1;
        let door = doors[k].name.clone();
        self.events.push(PafsisEvent::DoorMatched {
            door,
            at_m: Some(at_m),
            correction_m: correction,
            side: Some(side),
        });
    }

    /// The place along the leg of the door seen ahead, from the current streak's frames: `seen_at`
    /// is where this frame puts it; `Some` (their median) once the last
    /// [`DOOR_AHEAD_FRAMES`] places agree within `landmark_gate_m`.
    fn door_ahead_place(&mut self, seen_at: f64) -> Option<f64> {
        let recent = &mut self.door_ahead_recent;
        if recent.len() == DOOR_AHEAD_FRAMES {
            recent.remove(0);
        }
        recent.push(seen_at);
        if recent.len() < DOOR_AHEAD_FRAMES {
            return None;
        }
        let mut sorted = [0.0; DOOR_AHEAD_FRAMES];
        sorted.copy_from_slice(recent);
        sorted.sort_by(f64::total_cmp);
        let spread = sorted[DOOR_AHEAD_FRAMES - 1] - sorted[0];
        (spread <= self.params.landmark_gate_m).then(|| sorted[DOOR_AHEAD_FRAMES / 2])
    }

    /// Matches a door sighting against the next expected doors: `seen_at` is where along the
    /// leg it puts the door, when its distance is known.
    fn door_sighted(&mut self, seen_at: Option<f64>) {
        let Some(Leg { kind: LegKind::Corridor { doors, .. }, .. }) = self.legs.get(self.leg) else {
            return;
        };
        let mut i = self.next_door;
        while let Some(door) = doors.get(i) {
            if door.beside || self.matched(i) {
                i += 1;
                continue;
            }
            let gate = door_gate(&self.params, &self.map.tolerance, door.at_m);
            let window_ok = match (door.at_m, seen_at) {
                (Some(at), Some(e)) if e < at - gate => None,
                (Some(at), Some(e)) if e > at + gate => Some(false),
                (Some(at), None) if self.along_m < at - self.params.door_max_range_m - gate => None,
                _ => Some(true),
            };
            match window_ok {
                None => break,
                Some(false) => i += 1,
                Some(true) => {
                    let correction = match (door.at_m, seen_at) {
                        (Some(at), Some(e)) => at - e,
                        _ => 0.0,
                    };
                    let (name, at_m) = (door.name.clone(), door.at_m);
                    for (k, missed) in doors.iter().enumerate().take(i).skip(self.next_door) {
                        if missed.beside || self.matched(k) {
                            continue;
                        }
                        let what = describe_door(missed);
                        self.events.push(PafsisEvent::LandmarkMissed { leg: self.leg, what });
                    }
                    self.along_m += correction;
                    self.tracking = at_m.filter(|_| seen_at.is_some());
                    self.next_door = i + 1;
                    self.doors_sighted += 1;
                    self.matched_doors |= door_bit(i);
                    self.events.push(PafsisEvent::DoorMatched {
                        door: name,
                        at_m,
                        correction_m: correction,
                        side: None,
                    });
                    return;
                }
            }
        }
        self.events.push(PafsisEvent::DoorIgnored { estimated_at_m: seen_at });
    }

    /// Checks whether the current leg is complete; if so moves to the next (or arrives).
    /// Returns whether a leg was completed.
    fn leg_done(&mut self) -> bool {
        let Some(leg) = self.legs.get(self.leg) else {
            self.arrive();
            return false;
        };
        let done = match &leg.kind {
            LegKind::Turn => wrap_angle(leg.heading_rad - self.heading_rad).abs() <= self.params.turn_tolerance_rad,
            LegKind::Doorway { length_m, .. } => self.along_m >= *length_m,
            LegKind::Corridor { length_m, doors, end } => {
                // Doors whose window the robot has left without a sighting: missed.
                while let Some(d) = doors.get(self.next_door)
                    && d.at_m.is_some_and(|at| self.along_m > at + door_gate(&self.params, &self.map.tolerance, d.at_m))
                {
                    if !d.beside && !self.matched(self.next_door) {
                        let what = describe_door(d);
                        self.events.push(PafsisEvent::LandmarkMissed { leg: self.leg, what });
                    }
                    self.next_door += 1;
                }
                match end {
                    LegEnd::Distance | LegEnd::Door => {
                        let done = self.along_m >= *length_m;
                        if done {
                            // Arrived by odometry: whatever was still expected went unseen.
                            for (k, d) in doors.iter().enumerate().skip(self.next_door) {
                                if d.beside || self.matched(k) {
                                    continue;
                                }
                                let what = describe_door(d);
                                self.events.push(PafsisEvent::LandmarkMissed { leg: self.leg, what });
                            }
                        }
                        done
                    }
                    LegEnd::Corner | LegEnd::Wall => {
                        // The corridor's end: a corner, a wall or something solid ahead within
                        // the stop distance (at an L's corner the view holds the end wall and the
                        // corner beside the opening, and OFFIS may name either, or neither when
                        // the wall fills the view), counted only where the map puts
                        // the end, within its tolerance: a box in the corridor that looks like
                        // a corner must not end the leg halfway. Past the far edge of that
                        // window the end has gone unseen.
                        let window = self.map.tolerance.window_m(*length_m);
                        let seen =
                            self.end_streak >= self.params.landmark_min_frames && self.along_m >= length_m - window;
                        let missed_at = (self.params.miss_factor * length_m).min(length_m + window);
                        if !seen && self.along_m >= missed_at {
                            let what = format!("{:?} at the end of leg {}", end, self.leg).to_lowercase();
                            self.events.push(PafsisEvent::LandmarkMissed { leg: self.leg, what });
                            self.replan();
                            return true;
                        }
                        seen
                    }
                }
            }
        };
        if done {
            self.start_leg(self.leg + 1);
        }
        done
    }

    fn start_leg(&mut self, index: usize) {
        self.leg = index;
        self.along_m = self.already_along(index);
        self.next_door = 0;
        self.doors_sighted = 0;
        self.tracking = None;
        self.matched_doors = 0;
        self.side_door_tracks.clear();
        self.dead_along_m = self.along_m;
        self.wall_ahead_seen = false;
        self.wall_ahead_first.clear();
        // A door already in view when the leg starts counts for the new leg.
        self.door_sighting_reported = false;
        self.last_door_distance = None;
        self.door_ahead_recent.clear();
        match self.legs.get(index) {
            Some(leg) => self.events.push(PafsisEvent::LegStarted { index, leg: leg.to_string() }),
            None => self.arrive(),
        }
    }

    /// Where a new leg starts: 0, or with `cross_track_odometry`, for a straight leg of known
    /// length that ends at a place with a position (the last leg of its edge), how far along it
    /// the dead-reckoned position already is, `length − (end − position)·direction`, at least
    /// `−length` and at most `length`. A robot that swerved 0.5 m to one side of a corridor
    /// and then turns into a door 0.5 m ahead of the centre line must drive 1 m, not 0.5 m
    /// (counting only the leg's length, such runs arrived 0.53–0.57 m short in the simulator).
    fn already_along(&self, index: usize) -> f64 {
        let Some(leg) = self.legs.get(index) else { return 0.0 };
        let length = match &leg.kind {
            LegKind::Doorway { length_m, .. } => *length_m,
            LegKind::Corridor { length_m, end: LegEnd::Distance | LegEnd::Door, .. } => *length_m,
            LegKind::Turn | LegKind::Corridor { .. } => return 0.0,
        };
        let last_of_edge = self.legs.get(index + 1).is_none_or(|next| next.leads_to != leg.leads_to);
        match (self.params.cross_track_odometry && last_of_edge, leg.line_point_m, self.position_m) {
            (true, Some([ex, ey]), Some([x, y])) => {
                let (s, c) = leg.heading_rad.sin_cos();
                (length - ((ex - x) * c + (ey - y) * s)).clamp(-length, length)
            }
            _ => 0.0,
        }
    }

    fn arrive(&mut self) {
        if self.status == GoalStatus::Active {
            self.status = GoalStatus::Arrived;
            self.events.push(PafsisEvent::Arrived { place: self.mission.to.clone() });
        }
    }

    /// Re-localises to the place the current leg leads to and plans again from there.
    fn replan(&mut self) {
        self.replans += 1;
        let Some(from) = self.legs.get(self.leg).map(|l| l.leads_to.clone()) else { return };
        if self.replans > self.params.max_replans {
            self.fail(format!("{} landmarks failed to appear; giving up near {from}", self.replans));
            return;
        }
        let mission = Mission { from: from.clone(), to: self.mission.to.clone() };
        match plan(&self.map, &mission) {
            Ok(p) => {
                self.legs = unroll(&self.map, &p, self.legs[self.leg].heading_rad);
                self.events.push(PafsisEvent::Replanned { from, waypoints: p.waypoints.clone() });
                self.plan = p;
                self.start_leg(0);
            }
            Err(e) => self.fail(e.to_string()),
        }
    }

    fn fail(&mut self, reason: String) {
        self.status = GoalStatus::Failed;
        self.events.push(PafsisEvent::Failed { reason });
    }

    /// The goal-oriented velocity and angle for the current leg.
    fn command(&self, p: &Perception, hint: Option<PoseHint>) -> Goal {
        let Some(leg) = self.legs.get(self.leg) else {
            return Goal { velocity: 0.0, angle_rad: 0.0, status: self.status };
        };
        let mut angle = wrap_angle(leg.heading_rad - self.heading_rad);
        let holding = self.params.cross_track_hold_m > 0.0 && self.odometer_m < self.hold_line_until_m;
        if let (Some(h), Some([px, py]), false) = (hint, leg.line_point_m, matches!(leg.kind, LegKind::Turn) || holding)
        {
            // Signed distance of the robot left of the leg's line; steer back over a lookahead.
            let left = left_of_line([h.x, h.y], [px, py], leg.heading_rad);
            angle = wrap_angle(angle - left.atan2(self.params.lookahead_m));
        }
        // through a door whose opening the map gives: onto its axis over a short lookahead,
        // whatever holds the line elsewhere, so that the robot meets the opening square on
        if let (LegKind::Doorway { .. }, Some((door, _)), Some(at)) = (&leg.kind, leg.door_m, self.position_m) {
            let left = left_of_line(at, door, leg.heading_rad);
            angle = wrap_angle(leg.heading_rad - self.heading_rad - left.atan2(DOOR_LOOKAHEAD_M));
        }
        let (speed, remaining) = match &leg.kind {
            LegKind::Turn => (0.0, 0.0),
            LegKind::Doorway { length_m, .. } => (self.params.door_speed, length_m - self.along_m),
            LegKind::Corridor { length_m, end, .. } => {
                let remaining = match end {
                    LegEnd::Distance | LegEnd::Door => length_m - self.along_m,
                    LegEnd::Corner | LegEnd::Wall => {
                        let end_ahead = matches!(p.tpo.shape, TpoShape::Corner | TpoShape::Wall)
                            && self.along_m >= length_m - self.map.tolerance.window_m(*length_m);
                        match p.tpo.distance_m.filter(|_| end_ahead) {
                            Some(d) => d - self.params.stop_distance_m,
                            None => (length_m - self.along_m).max(self.params.slow_radius_m),
                        }
                    }
                };
                (self.params.cruise_speed, remaining)
            }
        };
        // constant deceleration: v ∝ √remaining (a linear ramp, v ∝ remaining, approaches the
        // end exponentially: 8 s for the last metre at 0.35 m/s, against 2.4 s)
        let ramp = (remaining.max(0.0) / self.params.slow_radius_m).sqrt().clamp(self.params.min_speed_fraction, 1.0);
        // the leg's speed whatever the heading: MOFIS turns to the goal, or to the way past what
        // blocks it, and slows for the turn. Scaled by the goal angle's cosine it fell to 0 for a
        // goal behind the robot, and a way past a box that first leads away from the goal could
        // not be driven: the robot stood turning between the two
        let velocity = if speed > 0.0 { speed * ramp } else { 0.0 };
        Goal { velocity, angle_rad: angle, status: self.status }
    }
}

/// How far ahead along a door's axis a doorway leg aims, m ([`Leg::door_m`]): short, so that
/// the robot is on the axis before it reaches the wall. With the corridor's 1.5 m lookahead,
/// and the line held while an obstacle was in sight, a robot 0.8 m beside the axis 1 m before
/// the wall stood turning there (the opening's wall blocked every heading within reach).
const DOOR_LOOKAHEAD_M: f64 = 0.6;

/// How far from where the map puts it a door may be sighted and still match, m: the
/// configured gate, or the map's tolerance where that is wider, which grows with the distance
/// along the leg (a length off by a few percent).
/// Door `k`'s bit among a leg's matched doors (legs with more than 64 doors share the last).
fn door_bit(k: usize) -> u64 {
    1 << k.min(63)
}

fn door_gate(params: &PafsisParams, tolerance: &MapTolerance, at_m: Option<f64>) -> f64 {
    at_m.map_or(params.landmark_gate_m, |at| params.landmark_gate_m.max(tolerance.window_m(at)))
}

/// Signed distance of `position` left of the line through `point` with heading `heading_rad`, m.
fn left_of_line(position: [f64; 2], point: [f64; 2], heading_rad: f64) -> f64 {
    let (s, c) = heading_rad.sin_cos();
    -(position[0] - point[0]) * s + (position[1] - point[1]) * c
}

fn describe_door(d: &ExpectedDoor) -> String {
    let side = d.side.map_or("", Side::name);
    match &d.name {
        Some(n) => format!("door {n} ({side})"),
        None => format!("a door ({side})"),
    }
}
