//! The topological map (paper §2.2: "a topological map and mission objective"): named places
//! (rooms, doors, junctions, corners) joined by directed edges, each edge annotated with the
//! actions that traverse it ("exit the room through D9", "follow the corridor passing 3 doors on
//! the left, stop in front of D2"). Loaded from TOML; every problem is reported with the file and
//! the entry it concerns. The format is documented in `docs/navigation.md`.

use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::fmt;
use std::path::{Path, PathBuf};

/// Why a map could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum MapError {
    #[error("cannot read map file {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("map file {path} is not valid: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("map file {path}: {entry}: {problem}")]
    Invalid { path: PathBuf, entry: String, problem: String },
}

/// What kind of place a node is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PlaceKind {
    /// Inside a room.
    Room,
    /// In the corridor, in front of (abeam) a door.
    Door,
    /// Where corridors meet.
    Junction,
    /// Where a corridor turns.
    Corner,
}

/// A side of the robot (REP-103: left is +y).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Side {
    Left,
    Right,
}

impl Side {
    /// +1 for left, −1 for right: the sign of a turn or bearing to that side.
    pub fn sign(self) -> f64 {
        match self {
            Side::Left => 1.0,
            Side::Right => -1.0,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Side::Left => "left",
            Side::Right => "right",
        }
    }
}

/// The landmark that ends a `follow_corridor` action.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Until {
    /// Odometry only: stop after `length_m` (or at a following `stop_at_door`).
    #[default]
    Distance,
    /// A corner seen ahead (TPO `corner`) within the stop distance.
    Corner,
    /// A wall seen ahead (TPO `wall`) within the stop distance: the corridor's end.
    Wall,
}

/// One step of traversing an edge, in the order the robot performs them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "do", rename_all = "snake_case", deny_unknown_fields)]
pub enum Action {
    /// Leave a room straight through its door into the corridor (`length_m` from the room
    /// place to the corridor place in front of the door). With the door's opening
    /// ([`Action::opening`]), the robot keeps its footprint inside it while it steers.
    ExitRoom {
        door: String,
        length_m: f64,
        /// The door's opening, jamb to jamb, m (with `door_at_m`).
        #[serde(default)]
        width_m: Option<f64>,
        /// How far from the action's start the robot crosses the door's wall, m (with `width_m`).
        #[serde(default)]
        door_at_m: Option<f64>,
    },
    /// Enter a room straight through its door.
    EnterRoom {
        door: String,
        length_m: f64,
        /// The door's opening, jamb to jamb, m (with `door_at_m`).
        #[serde(default)]
        width_m: Option<f64>,
        /// How far from the action's start the robot crosses the door's wall, m (with `width_m`).
        #[serde(default)]
        door_at_m: Option<f64>,
    },
    /// Drive straight through a doorway between two places that are not both rooms/corridor.
    GoThroughDoor {
        door: String,
        length_m: f64,
        /// The door's opening, jamb to jamb, m (with `door_at_m`).
        #[serde(default)]
        width_m: Option<f64>,
        /// How far from the action's start the robot crosses the door's wall, m (with `width_m`).
        #[serde(default)]
        door_at_m: Option<f64>,
    },
    /// Turn in place (into the corridor, at a corner), by `angle_deg` (default 90) to `side`.
    Turn {
        side: Side,
        #[serde(default = "default_turn_deg")]
        angle_deg: f64,
    },
    /// Follow the corridor straight for about `length_m`, passing `doors_left` doors on the
    /// left and `doors_right` on the right, until `until` (default: the distance).
    FollowCorridor {
        length_m: f64,
        #[serde(default)]
        doors_left: u32,
        #[serde(default)]
        doors_right: u32,
        #[serde(default)]
        until: Until,
        /// The corridor's width wall to wall, m, where the map knows it: the robot keeps
        /// inside it while it steers around obstacles (an open door or a wall it has not seen
        /// does not read as a way out); absent, only what the camera saw bounds the steering.
        #[serde(default)]
        width_m: Option<f64>,
    },
    /// Stop in front of door `door`, which is on `side`: ends a `follow_corridor`.
    StopAtDoor { door: String, side: Side },
}

fn default_turn_deg() -> f64 {
    90.0
}

impl Action {
    /// Distance driven by this action, m (0 for turns and stops).
    pub fn length_m(&self) -> f64 {
        match self {
            Action::ExitRoom { length_m, .. }
            | Action::EnterRoom { length_m, .. }
            | Action::GoThroughDoor { length_m, .. }
            | Action::FollowCorridor { length_m, .. } => *length_m,
            Action::Turn { .. } | Action::StopAtDoor { .. } => 0.0,
        }
    }

    /// A doorway action's opening where the map gives it: its width and how far before the
    /// action's end the door's wall is, m. The robot keeps its footprint inside the opening
    /// while it steers, as it keeps inside a corridor's width.
    pub fn opening(&self) -> Option<(f64, f64)> {
        match self {
            Action::ExitRoom { length_m, width_m, door_at_m, .. }
            | Action::EnterRoom { length_m, width_m, door_at_m, .. }
            | Action::GoThroughDoor { length_m, width_m, door_at_m, .. } => {
                Some(((*width_m)?, length_m - (*door_at_m)?))
            }
            _ => None,
        }
    }

    /// Heading change of this action, rad (+ = left).
    pub fn turn_rad(&self) -> f64 {
        match self {
            Action::Turn { side, angle_deg } => side.sign() * angle_deg.to_radians(),
            _ => 0.0,
        }
    }
}

impl fmt::Display for Action {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Action::ExitRoom { door, length_m, .. } => write!(f, "exit the room through {door} ({length_m} m)"),
            Action::EnterRoom { door, length_m, .. } => write!(f, "enter the room through {door} ({length_m} m)"),
            Action::GoThroughDoor { door, length_m, .. } => write!(f, "go through door {door} ({length_m} m)"),
            Action::Turn { side, angle_deg } => write!(f, "turn {} {angle_deg}°", side.name()),
            Action::FollowCorridor { length_m, doors_left, doors_right, until, width_m } => {
                write!(f, "follow the corridor {length_m} m passing {doors_left} doors left, {doors_right} right")?;
                if let Some(w) = width_m {
                    write!(f, " ({w} m wide)")?;
                }
                match until {
                    Until::Distance => Ok(()),
                    Until::Corner => write!(f, " until the corner"),
                    Until::Wall => write!(f, " until the wall"),
                }
            }
            Action::StopAtDoor { door, side } => write!(f, "stop in front of door {door} on the {}", side.name()),
        }
    }
}

/// A place as written in the file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Place {
    pub name: String,
    pub kind: PlaceKind,
    /// Optional metric position `[x, y]` in the world frame, m. Without positions the planner
    /// works from the edges alone; with them it also keeps the robot on the corridor's line and
    /// expects the door places beside a corridor leg as landmarks.
    #[serde(default)]
    pub position_m: Option<[f64; 2]>,
    /// Heading the robot has when a mission starts here, degrees in the map frame (+ = left of
    /// the map x axis). Without it the robot is assumed to face its first edge's direction.
    #[serde(default)]
    pub heading_deg: Option<f64>,
}

/// A directed edge as written in the file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Edge {
    pub from: String,
    pub to: String,
    /// Direction the robot must face when it begins the first action, degrees in the map
    /// frame. The local planner inserts a turn on the spot when it arrives facing elsewhere;
    /// this is what makes edges composable.
    pub heading_deg: f64,
    /// Planning cost, m. Default: the sum of the actions' lengths.
    #[serde(default)]
    pub length_m: Option<f64>,
    pub actions: Vec<Action>,
}

impl Edge {
    /// Planning cost: the declared length or the driven distance.
    pub fn cost_m(&self) -> f64 {
        self.length_m.unwrap_or_else(|| self.actions.iter().map(Action::length_m).sum())
    }

    /// Heading at the end of the edge, rad in the map frame.
    pub fn arrival_heading_rad(&self) -> f64 {
        wrap_angle(self.heading_deg.to_radians() + self.actions.iter().map(Action::turn_rad).sum::<f64>())
    }
}

/// How far the map's figures may be off the building (`[tolerance]` in a map file): a map drawn
/// from plans or with a tape measure. The planner matches landmarks within it and says it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MapTolerance {
    /// Lengths along a leg (`length_m`, the distances between places) are within this fraction
    /// of the building's.
    pub length_frac: f64,
    /// Places (a door's place along its corridor) are within this distance of where the map
    /// puts them, m.
    pub position_m: f64,
}

impl Default for MapTolerance {
    /// ±5 % on lengths, ±0.2 m on places: what a tape-measured corridor and door places marked
    /// by eye give.
    fn default() -> Self {
        Self { length_frac: 0.05, position_m: 0.2 }
    }
}

impl MapTolerance {
    /// How far from its mapped place a landmark `at_m` along a leg may be found, m.
    pub fn window_m(&self, at_m: f64) -> f64 {
        self.position_m + self.length_frac * at_m.abs()
    }
}

impl std::fmt::Display for MapTolerance {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "±{:.0} % on lengths, ±{:.2} m on places", self.length_frac * 100.0, self.position_m)
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct MapFile {
    #[serde(default)]
    name: Option<String>,
    #[serde(default)]
    tolerance: MapTolerance,
    #[serde(default)]
    place: Vec<Place>,
    #[serde(default)]
    edge: Vec<Edge>,
}

/// A validated topological map.
#[derive(Clone, Debug, PartialEq)]
pub struct TopoMap {
    /// Where it was loaded from (`<string>` when parsed from text), for error messages.
    pub source: PathBuf,
    pub name: String,
    pub places: Vec<Place>,
    pub edges: Vec<Edge>,
    /// How far its figures may be off the building.
    pub tolerance: MapTolerance,
    index: HashMap<String, usize>,
}

impl TopoMap {
    /// Reads and validates a map file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, MapError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| MapError::Read { path: path.into(), source })?;
        Self::parse(&text, path)
    }

    /// Parses and validates map text; `source` names it in errors.
    pub fn parse(text: &str, source: impl AsRef<Path>) -> Result<Self, MapError> {
        let source = source.as_ref().to_path_buf();
        let file: MapFile =
            toml::from_str(text).map_err(|e| MapError::Parse { path: source.clone(), message: e.to_string() })?;
        let invalid = |entry: String, problem: String| MapError::Invalid { path: source.clone(), entry, problem };

        let mut index = HashMap::new();
        for (i, p) in file.place.iter().enumerate() {
            let entry = format!("place #{} \"{}\"", i + 1, p.name);
            if p.name.trim().is_empty() || p.name.contains(':') || p.name.chars().any(char::is_whitespace) {
                return Err(invalid(entry, "a place name must be non-empty, without spaces or ':'".into()));
            }
            if index.insert(p.name.clone(), i).is_some() {
                return Err(invalid(entry, "duplicate place name; every place needs its own name".into()));
            }
            if p.position_m.is_some_and(|xy| !xy.iter().all(|v| v.is_finite())) {
                return Err(invalid(entry, "position_m must be two finite numbers".into()));
            }
            if p.heading_deg.is_some_and(|h| !h.is_finite()) {
                return Err(invalid(entry, "heading_deg must be finite".into()));
            }
        }
        let tol = file.tolerance;
        if !(tol.length_frac.is_finite() && (0.0..=0.5).contains(&tol.length_frac)) {
            return Err(invalid("[tolerance]".into(), "length_frac must be a fraction in 0..=0.5, e.g. 0.05".into()));
        }
        if !(tol.position_m.is_finite() && (0.0..=2.0).contains(&tol.position_m)) {
            return Err(invalid("[tolerance]".into(), "position_m must be a distance in 0..=2 m, e.g. 0.2".into()));
        }
        if file.place.is_empty() {
            return Err(invalid("[[place]]".into(), "the map has no places".into()));
        }

        let mut seen_edges = HashMap::new();
        for (i, e) in file.edge.iter().enumerate() {
            let entry = format!("edge #{} ({} -> {})", i + 1, e.from, e.to);
            for end in [&e.from, &e.to] {
                if !index.contains_key(end) {
                    return Err(invalid(entry, format!("unknown place \"{end}\"; declare it as a [[place]] first")));
                }
            }
            if e.from == e.to {
                return Err(invalid(entry, "an edge must join two different places".into()));
            }
            if seen_edges.insert((e.from.clone(), e.to.clone()), i).is_some() {
                return Err(invalid(entry, "duplicate edge: this direction is already declared".into()));
            }
            if !e.heading_deg.is_finite() {
                return Err(invalid(entry, "heading_deg must be finite".into()));
            }
            if let Some(l) = e.length_m
                && !(l.is_finite() && l >= 0.0)
            {
                return Err(invalid(entry, "length_m must be a finite length ≥ 0".into()));
            }
            if e.actions.is_empty() {
                return Err(invalid(entry, "an edge needs at least one action".into()));
            }
            for (k, a) in e.actions.iter().enumerate() {
                check_action(a, k, &e.actions, &file.place, &index)
                    .map_err(|problem| invalid(format!("{entry}, action {} ({a})", k + 1), problem))?;
            }
        }

        Ok(Self {
            name: file.name.unwrap_or_else(|| source.display().to_string()),
            source,
            places: file.place,
            edges: file.edge,
            tolerance: file.tolerance,
            index,
        })
    }

    /// Index of a place by name.
    pub fn place_index(&self, name: &str) -> Option<usize> {
        self.index.get(name).copied()
    }

    /// The place called `name`.
    pub fn place(&self, name: &str) -> Option<&Place> {
        self.place_index(name).map(|i| &self.places[i])
    }
}

/// Checks one action against the map; returns the problem in words.
fn check_action(
    a: &Action,
    k: usize,
    actions: &[Action],
    places: &[Place],
    index: &HashMap<String, usize>,
) -> Result<(), String> {
    let door_check = |door: &str| match index.get(door) {
        None => Err(format!("unknown place \"{door}\"")),
        Some(&i) if places[i].kind != PlaceKind::Door => {
            Err(format!("\"{door}\" is a {}, not a door", format!("{:?}", places[i].kind).to_lowercase()))
        }
        Some(_) => Ok(()),
    };
    let length_check = |l: f64| {
        if l.is_finite() && l > 0.0 {
            Ok(())
        } else {
            Err(format!("length_m must be a positive finite length, not {l}"))
        }
    };
    match a {
        Action::ExitRoom { door, length_m, width_m, door_at_m }
        | Action::EnterRoom { door, length_m, width_m, door_at_m }
        | Action::GoThroughDoor { door, length_m, width_m, door_at_m } => {
            door_check(door)?;
            length_check(*length_m)?;
            match (*width_m, *door_at_m) {
                (None, None) => Ok(()),
                (Some(w), Some(_)) if !(w.is_finite() && w > 0.0) => {
                    Err(format!("width_m must be a positive finite width, not {w}"))
                }
                (Some(_), Some(at)) if !(at.is_finite() && (0.0..=*length_m).contains(&at)) => {
                    Err(format!("door_at_m must be between 0 and length_m ({length_m}), not {at}"))
                }
                (Some(_), Some(_)) => Ok(()),
                _ => Err("width_m and door_at_m go together: give both (the door's opening) or neither".into()),
            }
        }
        Action::Turn { angle_deg, .. } => {
            if angle_deg.is_finite() && *angle_deg > 0.0 && *angle_deg <= 180.0 {
                Ok(())
            } else {
                Err(format!("angle_deg must be in (0, 180], not {angle_deg}"))
            }
        }
        Action::FollowCorridor { length_m, width_m, .. } => {
            length_check(*length_m)?;
            match width_m {
                Some(w) if !(w.is_finite() && *w > 0.0) => {
                    Err(format!("width_m must be a positive finite width, not {w}"))
                }
                _ => Ok(()),
            }
        }
        Action::StopAtDoor { door, .. } => {
            door_check(door)?;
            match k.checked_sub(1).map(|j| &actions[j]) {
                Some(Action::FollowCorridor { until: Until::Distance, .. }) => Ok(()),
                _ => Err("stop_at_door must directly follow a follow_corridor that ends by distance".into()),
            }
        }
    }
}

pub use hal::motion::wrap_angle;

#[cfg(test)]
mod tests {
    use super::*;

    const TINY: &str = r#"
        name = "tiny"
        [[place]]
        name = "R1"
        kind = "room"
        [[place]]
        name = "D1"
        kind = "door"
        [[edge]]
        from = "R1"
        to = "D1"
        heading_deg = -90
        actions = [{ do = "exit_room", door = "D1", length_m = 2.0 }, { do = "turn", side = "left" }]
    "#;

    #[test]
    fn parses_a_small_map() {
        let m = TopoMap::parse(TINY, "tiny.toml").unwrap();
        assert_eq!(m.name, "tiny");
        assert_eq!(m.places.len(), 2);
        assert_eq!(m.edges[0].cost_m(), 2.0);
        assert!((m.edges[0].arrival_heading_rad() - 0.0).abs() < 1e-12);
        assert_eq!(m.place("D1").unwrap().kind, PlaceKind::Door);
    }

    #[test]
    fn a_doorways_opening_is_both_its_width_and_where_its_wall_is() {
        let with = |extra: &str| TINY.replace("length_m = 2.0 }", &format!("length_m = 2.0{extra} }}"));
        let m = TopoMap::parse(&with(", width_m = 0.9, door_at_m = 1.5"), "tiny.toml").unwrap();
        assert_eq!(m.edges[0].actions[0].opening(), Some((0.9, 0.5)));
        assert_eq!(m.edges[0].actions[1].opening(), None);
        assert_eq!(TopoMap::parse(TINY, "tiny.toml").unwrap().edges[0].actions[0].opening(), None);
        for (extra, says) in [
            (", width_m = 0.9", "go together"),
            (", door_at_m = 1.0", "go together"),
            (", width_m = 0.0, door_at_m = 1.0", "width_m must be a positive"),
            (", width_m = 0.9, door_at_m = 2.5", "door_at_m must be between 0 and length_m"),
        ] {
            let e = err(&with(extra));
            assert!(e.contains("edge #1") && e.contains("action 1") && e.contains(says), "{extra}: {e}");
        }
    }

    fn err(text: &str) -> String {
        TopoMap::parse(text, "bad.toml").unwrap_err().to_string()
    }

    #[test]
    fn the_tolerance_defaults_parses_and_is_checked() {
        let m = TopoMap::parse(TINY, "tiny.toml").unwrap();
        assert_eq!(m.tolerance, MapTolerance { length_frac: 0.05, position_m: 0.2 });
        assert_eq!(m.tolerance.to_string(), "±5 % on lengths, ±0.20 m on places");
        // 12 m along a leg: 0.2 m + 5 % of 12 m.
        assert!((m.tolerance.window_m(12.0) - 0.8).abs() < 1e-12);
        let with = format!("{TINY}\n[tolerance]\nlength_frac = 0.1\nposition_m = 0.5\n");
        let m = TopoMap::parse(&with, "tiny.toml").unwrap();
        assert_eq!(m.tolerance, MapTolerance { length_frac: 0.1, position_m: 0.5 });
        for (bad, named) in [("length_frac = 0.9", "length_frac"), ("position_m = -1", "position_m")] {
            let text = format!("{TINY}\n[tolerance]\n{bad}\n");
            let err = TopoMap::parse(&text, "tiny.toml").unwrap_err().to_string();
            assert!(err.contains("[tolerance]") && err.contains(named), "{err}");
        }
        let typo = format!("{TINY}\n[tolerance]\nlenght_frac = 0.1\n");
        assert!(TopoMap::parse(&typo, "tiny.toml").unwrap_err().to_string().contains("lenght_frac"));
    }

    #[test]
    fn errors_name_the_file_and_entry() {
        let e = err(&TINY.replace("name = \"D1\"", "name = \"R1\""));
        assert!(e.contains("bad.toml") && e.contains("place #2") && e.contains("duplicate"), "{e}");

        let e = err(&TINY.replace("to = \"D1\"", "to = \"D7\""));
        assert!(e.contains("edge #1") && e.contains("unknown place \"D7\""), "{e}");

        let e = err(&TINY.replace("do = \"turn\"", "do = \"jump\""));
        assert!(e.contains("bad.toml") && e.contains("jump"), "{e}");

        let e = err(&TINY.replace("door = \"D1\"", "door = \"R1\""));
        assert!(e.contains("action 1") && e.contains("\"R1\" is a room, not a door"), "{e}");

        let e = err(&TINY.replace("length_m = 2.0", "length_m = -2.0"));
        assert!(e.contains("length_m must be a positive"), "{e}");

        let narrow = TINY.replace(
            r#"{ do = "exit_room", door = "D1", length_m = 2.0 }"#,
            r#"{ do = "follow_corridor", length_m = 2.0, width_m = 0.0 }"#,
        );
        let e = err(&narrow);
        assert!(e.contains("action 1") && e.contains("width_m must be a positive"), "{e}");
        let wide = narrow.replace("width_m = 0.0", "width_m = 2.0");
        assert!(TopoMap::parse(&wide, "ok.toml").is_ok());

        let e = err(&TINY.replace("side = \"left\"", "side = \"up\""));
        assert!(e.contains("bad.toml") && e.contains("up"), "{e}");

        let e = err(&TINY.replace("kind = \"door\"", "kind = \"hall\""));
        assert!(e.contains("hall"), "{e}");

        let stop_first = TINY.replace(
            r#"{ do = "exit_room", door = "D1", length_m = 2.0 }"#,
            r#"{ do = "stop_at_door", door = "D1", side = "left" }"#,
        );
        assert!(err(&stop_first).contains("must directly follow a follow_corridor"));
    }
}
