//! Worlds: floor plans of walls (with door openings), box and cylinder obstacles, named places
//! and a start pose, loaded from TOML (`mocks/worlds/*.toml`) or built in code.
//!
//! Coordinates are a right-handed floor plan in metres: x east, y north, z up; a yaw of 0 faces
//! +x and grows counter-clockwise (REP-103). A [`World`] is always validated: [`World::from_toml`]
//! reports syntax errors with line and column and semantic errors (a zero-length wall, a door
//! wider than its wall, overlapping obstacles...) with the line and the field.
//!
//! The renderer and the ground truth see walls as vertical [`Face`]s: each wall segment is split at
//! its door openings into solid pieces, plus a lintel piece above every door.

use hal::motion::wrap_angle;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::OnceLock;
use toml::Spanned;

/// The built-in office world (`mocks/worlds/office.toml`), modelled on the paper's §5 experiment.
pub const OFFICE_TOML: &str = include_str!("../worlds/office.toml");

/// A robot pose on the floor plan: position in m, yaw in rad (counter-clockwise from +x).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub x: f64,
    pub y: f64,
    pub yaw: f64,
}

impl Pose {
    pub fn new(x: f64, y: f64, yaw: f64) -> Self {
        Self { x, y, yaw }
    }

    /// The pose reached by driving at `v` (m/s) and `omega` (rad/s) for `dt` s (exact arc).
    pub fn advance(&self, v: f64, omega: f64, dt: f64) -> Pose {
        let dyaw = omega * dt;
        let (dx, dy) = if dyaw.abs() < 1e-9 {
            (v * dt * self.yaw.cos(), v * dt * self.yaw.sin())
        } else {
            let r = v / omega;
            (r * ((self.yaw + dyaw).sin() - self.yaw.sin()), -r * ((self.yaw + dyaw).cos() - self.yaw.cos()))
        };
        Pose { x: self.x + dx, y: self.y + dy, yaw: wrap_angle(self.yaw + dyaw) }
    }

    /// Linear interpolation of position and shortest-way interpolation of yaw (`f` in [0, 1]).
    pub fn lerp(&self, other: &Pose, f: f64) -> Pose {
        Pose {
            x: self.x + (other.x - self.x) * f,
            y: self.y + (other.y - self.y) * f,
            yaw: wrap_angle(self.yaw + wrap_angle(other.yaw - self.yaw) * f),
        }
    }

    /// A point given in this pose's body frame (x forward, y left), in plan coordinates.
    pub fn transform(&self, p: [f64; 2]) -> [f64; 2] {
        let (s, c) = self.yaw.sin_cos();
        [self.x + c * p[0] - s * p[1], self.y + s * p[0] + c * p[1]]
    }

    /// A plan point in this pose's body frame (x forward, y left).
    pub fn inverse_transform(&self, p: [f64; 2]) -> [f64; 2] {
        let (s, c) = self.yaw.sin_cos();
        let (dx, dy) = (p[0] - self.x, p[1] - self.y);
        [c * dx + s * dy, -s * dx + c * dy]
    }
}

/// A wall: a polyline on the floor plan, extruded from the floor to `height`.
#[derive(Clone, Debug, PartialEq)]
pub struct Wall {
    pub name: String,
    pub points: Vec<[f64; 2]>,
    pub height: f64,
    pub doors: Vec<Door>,
}

/// A door opening in a wall: from the floor to `height`, centred `at` metres along the wall's
/// polyline from its first point; it must lie within one segment.
#[derive(Clone, Debug, PartialEq)]
pub struct Door {
    pub name: String,
    pub at: f64,
    pub width: f64,
    pub height: f64,
}

/// A box obstacle standing on the floor: centre, size `[length, width, height]` (along its own
/// x and y after `yaw`).
#[derive(Clone, Debug, PartialEq)]
pub struct BoxObstacle {
    pub name: String,
    pub center: [f64; 2],
    pub size: [f64; 3],
    pub yaw: f64,
}

/// A vertical cylinder standing on the floor (a person is ≈ 0.25 m radius, 1.7 m high).
#[derive(Clone, Debug, PartialEq)]
pub struct Cylinder {
    pub name: String,
    pub center: [f64; 2],
    pub radius: f64,
    pub height: f64,
}

/// Where [`World::with_random_obstacles`] may place obstacles: a straight corridor lane.
///
/// The placement rule keeps the lane passable: every obstacle leaves a free width of at least
/// `min_gap_m` between itself and one side of the lane, the footprints of any two obstacles are
/// at least `min_spacing_m` apart along the lane (room to swerve from one side to the other), and
/// no obstacle comes within `keep_clear_radius_m` (along the lane) of a `keep_clear` place.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RandomSpec {
    /// Lane centre line, from and to (plan coordinates, m).
    pub from: [f64; 2],
    pub to: [f64; 2],
    /// Half the lane width (wall to centre line), m.
    pub half_width_m: f64,
    /// How many boxes and cylinders (people) to place.
    #[serde(default)]
    pub boxes: usize,
    #[serde(default)]
    pub people: usize,
    #[serde(default = "default_min_gap")]
    pub min_gap_m: f64,
    #[serde(default = "default_min_spacing")]
    pub min_spacing_m: f64,
    #[serde(default)]
    pub keep_clear: Vec<String>,
    #[serde(default = "default_keep_clear_radius")]
    pub keep_clear_radius_m: f64,
}

fn default_min_gap() -> f64 {
    0.8
}
fn default_min_spacing() -> f64 {
    1.5
}
fn default_keep_clear_radius() -> f64 {
    1.0
}

/// A validated world.
#[derive(Clone, Debug, PartialEq)]
pub struct World {
    pub name: String,
    /// Height of the ceiling, m; `None` for an open sky (scenes without a room).
    pub ceiling_height: Option<f64>,
    pub walls: Vec<Wall>,
    pub boxes: Vec<BoxObstacle>,
    pub cylinders: Vec<Cylinder>,
    /// Named places (rooms R1…, doors D1…, junctions J1…) for the topological map.
    pub places: BTreeMap<String, [f64; 2]>,
    pub start: Pose,
    pub random: Option<RandomSpec>,
    /// The faces [`World::clearance`] measures against, worked out on first use.
    pub(crate) low_faces: LowFaces,
}

/// The wall faces reaching below 0.5 m, kept with the walls they were worked out from: the
/// simulator asks for the clearance at every drive substep, and building the faces each time
/// (allocations, a square root per segment) cost several percent of a run. A world whose
/// walls were changed after the first use gets fresh faces, worked out again at every call (as
/// before the cache). It is a cache, not part of the world: any two compare equal.
#[derive(Clone, Default)]
pub(crate) struct LowFaces(OnceLock<(Vec<Wall>, Vec<Face>)>);

impl std::fmt::Debug for LowFaces {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("LowFaces")
    }
}

impl PartialEq for LowFaces {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

/// What went wrong with a world.
#[derive(Debug, thiserror::Error)]
pub enum WorldError {
    #[error("cannot read world file {path} (pass --world FILE, or leave it out for the built-in office)")]
    Read { path: String, source: std::io::Error },
    #[error("world {origin}, line {line}, column {column}: {message}")]
    Syntax { origin: String, line: usize, column: usize, message: String },
    #[error("world {origin}{}: {field}: {problem}", line.map(|l| format!(", line {l}")).unwrap_or_default())]
    Invalid { origin: String, line: Option<usize>, field: String, problem: String },
    #[error("world {origin}: cannot place the random obstacles: {problem}")]
    Placement { origin: String, problem: String },
}

/// Which element of a world a semantic error is about (mapped to a line when parsed from TOML).
#[derive(Clone, Debug, PartialEq)]
enum Item {
    Top,
    Start,
    Wall(usize),
    Door(usize, usize),
    Box(usize),
    Cylinder(usize),
    Place(String),
    Random,
}

struct Problem {
    item: Item,
    field: String,
    problem: String,
}

fn problem(item: Item, field: impl Into<String>, problem: impl Into<String>) -> Problem {
    Problem { item, field: field.into(), problem: problem.into() }
}

// ---- TOML format ---------------------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawWorld {
    #[serde(default)]
    name: String,
    #[serde(default = "default_wall_height")]
    wall_height: f64,
    ceiling_height: Option<f64>,
    #[serde(default = "default_door_height")]
    door_height: f64,
    start: RawPose,
    #[serde(default)]
    walls: Vec<Spanned<RawWall>>,
    #[serde(default)]
    boxes: Vec<Spanned<RawBox>>,
    #[serde(default)]
    cylinders: Vec<Spanned<RawCylinder>>,
    #[serde(default)]
    places: BTreeMap<String, Spanned<[f64; 2]>>,
    random: Option<Spanned<RandomSpec>>,
}

fn default_wall_height() -> f64 {
    2.6
}
fn default_door_height() -> f64 {
    2.0
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPose {
    x: f64,
    y: f64,
    #[serde(default)]
    yaw_deg: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawWall {
    #[serde(default)]
    name: String,
    points: Vec<[f64; 2]>,
    height: Option<f64>,
    #[serde(default)]
    doors: Vec<Spanned<RawDoor>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDoor {
    #[serde(default)]
    name: String,
    at: f64,
    width: f64,
    height: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawBox {
    #[serde(default)]
    name: String,
    center: [f64; 2],
    size: [f64; 3],
    #[serde(default)]
    yaw_deg: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCylinder {
    #[serde(default)]
    name: String,
    center: [f64; 2],
    radius: f64,
    height: f64,
}

/// 1-based line and column of byte offset `at` in `text`.
fn line_col(text: &str, at: usize) -> (usize, usize) {
    let before = &text[..at.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
    (line, column)
}

impl World {
    /// Loads and validates a world file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, WorldError> {
        let path = path.as_ref();
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| WorldError::Read { path: name.clone(), source })?;
        Self::from_toml(&text, &name)
    }

    /// The built-in office world (see [`OFFICE_TOML`]).
    pub fn office() -> Self {
        Self::from_toml(OFFICE_TOML, "office.toml (built in)").expect("the built-in office world is valid")
    }

    /// Parses and validates world TOML; `origin` names the source in errors.
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, WorldError> {
        let raw: RawWorld = toml::from_str(text).map_err(|e| {
            let (line, column) = e.span().map_or((0, 0), |s| line_col(text, s.start));
            WorldError::Syntax { origin: origin.into(), line, column, message: e.message().trim().to_string() }
        })?;
        let line_of = |span: std::ops::Range<usize>| Some(line_col(text, span.start).0);
        let mut world = World {
            name: raw.name.clone(),
            ceiling_height: raw.ceiling_height,
            walls: Vec::new(),
            boxes: Vec::new(),
            cylinders: Vec::new(),
            places: raw.places.iter().map(|(k, v)| (k.clone(), *v.get_ref())).collect(),
            start: Pose::new(raw.start.x, raw.start.y, raw.start.yaw_deg.to_radians()),
            random: raw.random.as_ref().map(|r| r.get_ref().clone()),
            low_faces: LowFaces::default(),
        };
        for w in &raw.walls {
            let w = w.get_ref();
            let height = w.height.unwrap_or(raw.wall_height);
            let doors = w
                .doors
                .iter()
                .map(|d| {
                    let d = d.get_ref();
                    Door {
                        name: d.name.clone(),
                        at: d.at,
                        width: d.width,
                        height: d.height.unwrap_or(raw.door_height.min(height)),
                    }
                })
                .collect();
            world.walls.push(Wall { name: w.name.clone(), points: w.points.clone(), height, doors });
        }
        for b in &raw.boxes {
            let b = b.get_ref();
            world.boxes.push(BoxObstacle {
                name: b.name.clone(),
                center: b.center,
                size: b.size,
                yaw: b.yaw_deg.to_radians(),
            });
        }
        for c in &raw.cylinders {
            let c = c.get_ref();
            world.cylinders.push(Cylinder {
                name: c.name.clone(),
                center: c.center,
                radius: c.radius,
                height: c.height,
            });
        }
        world.check().map_err(|p| {
            let line = match &p.item {
                Item::Top | Item::Start => None,
                Item::Wall(i) => line_of(raw.walls[*i].span()),
                Item::Door(i, j) => line_of(raw.walls[*i].get_ref().doors[*j].span()),
                Item::Box(i) => line_of(raw.boxes[*i].span()),
                Item::Cylinder(i) => line_of(raw.cylinders[*i].span()),
                Item::Place(name) => raw.places.get(name).and_then(|s| line_of(s.span())),
                Item::Random => raw.random.as_ref().and_then(|r| line_of(r.span())),
            };
            WorldError::Invalid { origin: origin.into(), line, field: p.field, problem: p.problem }
        })?;
        Ok(world)
    }

    /// Validates a world built in code; `origin` names it in errors.
    pub fn validate(&self, origin: &str) -> Result<(), WorldError> {
        self.check().map_err(|p| WorldError::Invalid {
            origin: origin.into(),
            line: None,
            field: p.field,
            problem: p.problem,
        })
    }

    fn check(&self) -> Result<(), Problem> {
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        let mut max_wall = 0.0f64;
        for (i, w) in self.walls.iter().enumerate() {
            let item = || Item::Wall(i);
            let label = wall_label(i, w);
            if w.points.len() < 2 {
                return Err(problem(item(), format!("{label}.points"), "needs at least two points [x, y]"));
            }
            if !w.points.iter().all(|p| finite(p)) {
                return Err(problem(item(), format!("{label}.points"), "must be finite numbers"));
            }
            for (k, s) in w.points.windows(2).enumerate() {
                if dist(s[0], s[1]) < 0.01 {
                    return Err(problem(
                        item(),
                        format!("{label}.points"),
                        format!("segment {k} from {:?} to {:?} has zero length; remove the repeated point", s[0], s[1]),
                    ));
                }
            }
            if !(w.height.is_finite() && w.height > 0.0) {
                return Err(problem(item(), format!("{label}.height"), "must be a positive height in metres"));
            }
            max_wall = max_wall.max(w.height);
            let lengths: Vec<f64> = w.points.windows(2).map(|s| dist(s[0], s[1])).collect();
            let mut spans: Vec<(f64, f64, usize)> = Vec::new();
            for (j, d) in w.doors.iter().enumerate() {
                let ditem = || Item::Door(i, j);
                let dl = format!("{label}.doors[{j}]");
                if !(d.width.is_finite() && d.width >= 0.7) {
                    return Err(problem(
                        ditem(),
                        format!("{dl}.width"),
                        format!("{} m is not a door: openings are at least 0.7 m wide (DESIGN.md)", d.width),
                    ));
                }
                if !(d.height.is_finite() && d.height > 0.0 && d.height <= w.height) {
                    return Err(problem(
                        ditem(),
                        format!("{dl}.height"),
                        format!("{} m must be positive and at most the wall height {} m", d.height, w.height),
                    ));
                }
                if !d.at.is_finite() {
                    return Err(problem(ditem(), format!("{dl}.at"), "must be a finite distance along the wall"));
                }
                let (a, b) = (d.at - d.width / 2.0, d.at + d.width / 2.0);
                let mut start = 0.0;
                let mut inside = None;
                for (k, len) in lengths.iter().enumerate() {
                    if a >= start - 1e-9 && b <= start + len + 1e-9 {
                        inside = Some(k);
                    }
                    start += len;
                }
                if inside.is_none() {
                    let longest = lengths.iter().cloned().fold(0.0, f64::max);
                    let why = if d.width > longest {
                        format!(
                            "the {} m door is wider than its wall (longest segment {longest:.2} m); make it narrower or the wall longer",
                            d.width
                        )
                    } else {
                        format!(
                            "the opening from {a:.2} m to {b:.2} m along the wall does not lie within one segment (segment lengths {lengths:.2?})"
                        )
                    };
                    return Err(problem(ditem(), format!("{dl}.at/width"), why));
                }
                if let Some(&(pa, pb, pj)) = spans.iter().find(|(pa, pb, _)| a < *pb && b > *pa) {
                    return Err(problem(
                        ditem(),
                        format!("{dl}.at"),
                        format!("overlaps door {pj} of the same wall ({pa:.2}..{pb:.2} m along it)"),
                    ));
                }
                spans.push((a, b, j));
            }
        }
        if let Some(h) = self.ceiling_height
            && !(h.is_finite() && h > 0.0 && h >= max_wall - 1e-9)
        {
            return Err(problem(
                Item::Top,
                "ceiling_height",
                format!("{h} m must be positive and at least the highest wall ({max_wall} m)"),
            ));
        }
        for (i, b) in self.boxes.iter().enumerate() {
            let l = format!("boxes[{i}]");
            if !(finite(&b.center) && b.yaw.is_finite()) {
                return Err(problem(Item::Box(i), format!("{l}.center"), "must be finite numbers"));
            }
            if !b.size.iter().all(|s| s.is_finite() && *s > 0.0) {
                return Err(problem(Item::Box(i), format!("{l}.size"), "[length, width, height] must be positive"));
            }
        }
        for (i, c) in self.cylinders.iter().enumerate() {
            let l = format!("cylinders[{i}]");
            if !finite(&c.center) {
                return Err(problem(Item::Cylinder(i), format!("{l}.center"), "must be finite numbers"));
            }
            if !(c.radius.is_finite() && c.radius > 0.0 && c.height.is_finite() && c.height > 0.0) {
                return Err(problem(Item::Cylinder(i), format!("{l}.radius/height"), "must be positive"));
            }
        }
        // Overlaps: obstacles with each other and with walls.
        let shapes = self.obstacle_shapes();
        let faces = self.faces();
        for (k, s) in shapes.iter().enumerate() {
            for f in &faces {
                if f.z0 < s.height() && s.distance_to_segment(f.a, f.b) <= 0.0 {
                    return Err(problem(
                        s.item(),
                        format!("{}.center", s.label()),
                        format!("{} overlaps wall {}", s.label(), wall_label(f.wall, &self.walls[f.wall])),
                    ));
                }
            }
            for o in &shapes[..k] {
                if s.overlaps(o) {
                    return Err(problem(
                        s.item(),
                        format!("{}.center", s.label()),
                        format!("{} overlaps {}", s.label(), o.label()),
                    ));
                }
            }
        }
        for (name, p) in &self.places {
            if !finite(p) {
                return Err(problem(Item::Place(name.clone()), format!("places.{name}"), "must be finite numbers"));
            }
        }
        let s = self.start;
        if !(s.x.is_finite() && s.y.is_finite() && s.yaw.is_finite()) {
            return Err(problem(Item::Start, "start", "x, y and yaw_deg must be finite numbers"));
        }
        let c = self.clearance(s.x, s.y);
        if c.distance_m < 0.05 {
            return Err(problem(
                Item::Start,
                "start",
                format!("({}, {}) is inside or touching {}; move the robot to free floor", s.x, s.y, c.object),
            ));
        }
        if let Some(r) = &self.random {
            let bad = |f: &str, why: String| Err(problem(Item::Random, format!("random.{f}"), why));
            if !(finite(&r.from) && finite(&r.to) && dist(r.from, r.to) > 1.0) {
                return bad("from/to", "the lane must be longer than 1 m".into());
            }
            if !(r.half_width_m.is_finite() && r.half_width_m > 0.0) {
                return bad("half_width_m", "must be positive".into());
            }
            if !(r.min_gap_m.is_finite() && r.min_gap_m > 0.0 && r.min_gap_m < 2.0 * r.half_width_m - 0.2) {
                return bad(
                    "min_gap_m",
                    format!("must be positive and leave room for an obstacle in a {} m lane", 2.0 * r.half_width_m),
                );
            }
            if !(r.min_spacing_m.is_finite() && r.min_spacing_m >= 0.0) {
                return bad("min_spacing_m", "must be zero or positive".into());
            }
            if !(r.keep_clear_radius_m.is_finite() && r.keep_clear_radius_m >= 0.0) {
                return bad("keep_clear_radius_m", "must be zero or positive".into());
            }
            if let Some(n) = r.keep_clear.iter().find(|n| !self.places.contains_key(*n)) {
                return bad("keep_clear", format!("`{n}` is not one of the [places]"));
            }
        }
        Ok(())
    }

    /// The vertical faces of all walls: every segment split at its door openings, plus a lintel
    /// above each door lower than the wall.
    pub fn faces(&self) -> Vec<Face> {
        let mut out = Vec::new();
        for (wi, w) in self.walls.iter().enumerate() {
            let mut along0 = 0.0;
            for (si, s) in w.points.windows(2).enumerate() {
                let (a, b) = (s[0], s[1]);
                let len = dist(a, b);
                let at = |t: f64| [a[0] + (b[0] - a[0]) * t / len, a[1] + (b[1] - a[1]) * t / len];
                let mut openings: Vec<(f64, f64, f64)> = w
                    .doors
                    .iter()
                    .map(|d| (d.at - d.width / 2.0 - along0, d.at + d.width / 2.0 - along0, d.height))
                    .filter(|(da, db, _)| *da >= -1e-9 && *db <= len + 1e-9)
                    .collect();
                openings.sort_by(|x, y| x.0.total_cmp(&y.0));
                let mut cursor = 0.0;
                let mut push = |t0: f64, t1: f64, z0: f64, z1: f64| {
                    if t1 - t0 > 1e-6 && z1 - z0 > 1e-6 {
                        out.push(Face { a: at(t0), b: at(t1), z0, z1, wall: wi, segment: si, along0: along0 + t0 });
                    }
                };
                for &(da, db, dh) in &openings {
                    push(cursor, da.max(0.0), 0.0, w.height);
                    push(da.max(0.0), db.min(len), dh, w.height);
                    cursor = db.min(len);
                }
                push(cursor, len, 0.0, w.height);
                along0 += len;
            }
        }
        out
    }

    /// Distance from plan point (x, y) to the nearest thing a robot can bump into (wall pieces
    /// reaching below 0.5 m, boxes, cylinders); 0 inside an obstacle. For collision checks.
    pub fn clearance(&self, x: f64, y: f64) -> Clearance {
        // The simulator calls this at every drive substep and sphere-traces with it: the nearest
        // thing is found on distances alone (boxes and cylinders without copying them), and only
        // the winner is named.
        enum Nearest {
            Nothing,
            Wall(usize),
            Obstacle(usize),
        }
        let p = [x, y];
        let (mut best, mut nearest) = (f64::INFINITY, Nearest::Nothing);
        let low = || self.faces().into_iter().filter(|f| f.z0 < 0.5).collect::<Vec<_>>();
        let cached = self.low_faces.0.get_or_init(|| (self.walls.clone(), low()));
        let fresh;
        let faces = if cached.0 == self.walls {
            &cached.1
        } else {
            fresh = low();
            &fresh
        };
        for f in faces {
            let d = point_segment_distance(p, f.a, f.b);
            if d < best {
                (best, nearest) = (d, Nearest::Wall(f.wall));
            }
        }
        let boxes = self.boxes.iter().map(|b| box_distance(p, &box_corners(b)));
        let cylinders = self.cylinders.iter().map(|c| cylinder_distance(p, c));
        for (k, d) in boxes.chain(cylinders).enumerate() {
            if d < best {
                (best, nearest) = (d, Nearest::Obstacle(k));
            }
        }
        match nearest {
            Nearest::Nothing => Clearance { distance_m: best, object: "nothing".into(), obstacle: None },
            Nearest::Wall(w) => Clearance {
                distance_m: best,
                object: format!("wall {}", wall_label(w, &self.walls[w])),
                obstacle: None,
            },
            Nearest::Obstacle(k) => {
                Clearance { distance_m: best, object: self.obstacle_shapes()[k].label(), obstacle: Some(k) }
            }
        }
    }

    /// For each point on the floor, the distance to each obstacle's footprint (boxes, then cylinders, in
    /// the world's order); 0 inside one. For scoring perception per obstacle.
    pub fn obstacle_distances(&self, points: &[[f64; 2]]) -> Vec<Vec<f64>> {
        let shapes = self.obstacle_shapes();
        points.iter().map(|p| shapes.iter().map(|s| s.distance_to_point(*p)).collect()).collect()
    }

    /// A copy with the obstacles inside the [`RandomSpec`] lane replaced by `boxes` boxes and
    /// `people` cylinders placed at random (deterministic for a `seed`) by the rule documented on
    /// [`RandomSpec`]. Obstacles outside the lane stay.
    pub fn with_random_obstacles(&self, seed: u64) -> Result<World, WorldError> {
        let origin = if self.name.is_empty() { "(unnamed)".to_string() } else { self.name.clone() };
        let fail = |problem: String| WorldError::Placement { origin: origin.clone(), problem };
        let r =
            self.random.as_ref().ok_or_else(|| fail("the world has no [random] section describing the lane".into()))?;
        let len = dist(r.from, r.to);
        let u = [(r.to[0] - r.from[0]) / len, (r.to[1] - r.from[1]) / len];
        let n = [-u[1], u[0]];
        let lane = |p: [f64; 2]| {
            let d = [p[0] - r.from[0], p[1] - r.from[1]];
            (d[0] * u[0] + d[1] * u[1], d[0] * n[0] + d[1] * n[1])
        };
        let in_lane = |p: [f64; 2]| {
            let (s, l) = lane(p);
            (0.0..=len).contains(&s) && l.abs() <= r.half_width_m
        };
        let mut out = self.clone();
        out.boxes.retain(|b| !in_lane(b.center));
        out.cylinders.retain(|c| !in_lane(c.center));
        let forbidden: Vec<(f64, f64)> = r
            .keep_clear
            .iter()
            .filter_map(|name| self.places.get(name))
            .map(|p| lane(*p).0)
            .map(|s| (s - r.keep_clear_radius_m, s + r.keep_clear_radius_m))
            .collect();
        let mut rng = SplitMix64::new(seed);
        let mut taken: Vec<(f64, f64)> = Vec::new();
        let total = r.people + r.boxes;
        for k in 0..total {
            let person = k < r.people;
            let mut placed = false;
            for _ in 0..2000 {
                // Size and footprint half-extents along (a) and across (e) the lane.
                let (size, yaw, a, e) = if person {
                    let radius = rng.range(0.2, 0.3);
                    ([radius, rng.range(1.5, 1.9), 0.0], 0.0, radius, radius)
                } else {
                    let (lx, ly, h) = (rng.range(0.3, 0.6), rng.range(0.3, 0.6), rng.range(0.3, 0.9));
                    let yaw = rng.range(-0.6, 0.6);
                    let (s, c) = yaw.sin_cos();
                    let a = (lx * c).abs() / 2.0 + (ly * s).abs() / 2.0;
                    let e = (lx * s).abs() / 2.0 + (ly * c).abs() / 2.0;
                    ([lx, ly, h], yaw, a, e)
                };
                if len < 2.0 * a + 1.0 {
                    break;
                }
                let s = rng.range(a + 0.5, len - a - 0.5);
                let lat_max = r.half_width_m - e - 0.05;
                if lat_max <= -lat_max {
                    break;
                }
                let l = rng.range(-lat_max, lat_max);
                let gap_left = r.half_width_m - (l + e);
                let gap_right = (l - e) + r.half_width_m;
                if gap_left < r.min_gap_m && gap_right < r.min_gap_m {
                    continue;
                }
                let (s0, s1) = (s - a, s + a);
                if forbidden.iter().any(|(f0, f1)| s0 < *f1 && s1 > *f0) {
                    continue;
                }
                if taken.iter().any(|(t0, t1)| s0 < t1 + r.min_spacing_m && s1 > t0 - r.min_spacing_m) {
                    continue;
                }
                let center = [r.from[0] + u[0] * s + n[0] * l, r.from[1] + u[1] * s + n[1] * l];
                let mut candidate = out.clone();
                if person {
                    candidate.cylinders.push(Cylinder {
                        name: format!("person{}", k + 1),
                        center,
                        radius: size[0],
                        height: size[1],
                    });
                } else {
                    candidate.boxes.push(BoxObstacle {
                        name: format!("box{}", k + 1 - r.people),
                        center,
                        size,
                        yaw: wrap_angle(u[1].atan2(u[0]) + yaw),
                    });
                }
                if candidate.check().is_err() {
                    continue;
                }
                out = candidate;
                taken.push((s0, s1));
                placed = true;
                break;
            }
            if !placed {
                return Err(fail(format!(
                    "no room for obstacle {} of {total} in the {len:.1} m lane with min_spacing_m = {} and keep_clear {:?}; ask for fewer obstacles",
                    k + 1,
                    r.min_spacing_m,
                    r.keep_clear
                )));
            }
        }
        Ok(out)
    }

    pub(crate) fn obstacle_shapes(&self) -> Vec<Shape> {
        let boxes =
            self.boxes.iter().enumerate().map(|(i, b)| Shape::Box { index: i, corners: box_corners(b), b: b.clone() });
        let cyl = self.cylinders.iter().enumerate().map(|(i, c)| Shape::Cyl { index: i, c: c.clone() });
        boxes.chain(cyl).collect()
    }
}

/// How far a plan point is from the nearest obstacle or wall, and which one.
#[derive(Clone, Debug, PartialEq)]
pub struct Clearance {
    pub distance_m: f64,
    pub object: String,
    /// The obstacle's index in [`World::obstacle_distances`]' order (boxes, then cylinders);
    /// `None` for a wall or nothing.
    pub obstacle: Option<usize>,
}

/// A vertical rectangle of wall between plan points `a` and `b`, from height `z0` to `z1`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Face {
    pub a: [f64; 2],
    pub b: [f64; 2],
    pub z0: f64,
    pub z1: f64,
    /// Index of the wall and of its segment (pieces of one segment are coplanar).
    pub wall: usize,
    pub segment: usize,
    /// Distance along the wall's polyline of `a`, m (texture coordinate).
    pub along0: f64,
}

fn wall_label(i: usize, w: &Wall) -> String {
    if w.name.is_empty() { format!("walls[{i}]") } else { format!("walls[{i}] ({})", w.name) }
}

/// Distance from plan point `p` to a box's footprint (its corners in order); 0 inside.
fn box_distance(p: [f64; 2], corners: &[[f64; 2]; 4]) -> f64 {
    if point_in_convex(p, corners) {
        0.0
    } else {
        (0..4).map(|k| point_segment_distance(p, corners[k], corners[(k + 1) % 4])).fold(f64::INFINITY, f64::min)
    }
}

/// Distance from plan point `p` to a cylinder's footprint; 0 inside.
fn cylinder_distance(p: [f64; 2], c: &Cylinder) -> f64 {
    (dist(p, c.center) - c.radius).max(0.0)
}

/// Corners of a box's footprint, counter-clockwise.
pub(crate) fn box_corners(b: &BoxObstacle) -> [[f64; 2]; 4] {
    let (s, c) = b.yaw.sin_cos();
    let (hx, hy) = (b.size[0] / 2.0, b.size[1] / 2.0);
    let p = |x: f64, y: f64| [b.center[0] + c * x - s * y, b.center[1] + s * x + c * y];
    [p(-hx, -hy), p(hx, -hy), p(hx, hy), p(-hx, hy)]
}

/// An obstacle footprint for overlap and clearance tests.
pub(crate) enum Shape {
    Box { index: usize, corners: [[f64; 2]; 4], b: BoxObstacle },
    Cyl { index: usize, c: Cylinder },
}

impl Shape {
    fn item(&self) -> Item {
        match self {
            Shape::Box { index, .. } => Item::Box(*index),
            Shape::Cyl { index, .. } => Item::Cylinder(*index),
        }
    }

    fn label(&self) -> String {
        let (kind, i, name) = match self {
            Shape::Box { index, b, .. } => ("boxes", *index, &b.name),
            Shape::Cyl { index, c } => ("cylinders", *index, &c.name),
        };
        if name.is_empty() { format!("{kind}[{i}]") } else { format!("{kind}[{i}] ({name})") }
    }

    fn height(&self) -> f64 {
        match self {
            Shape::Box { b, .. } => b.size[2],
            Shape::Cyl { c, .. } => c.height,
        }
    }

    /// Distance from a point to the footprint; 0 inside.
    fn distance_to_point(&self, p: [f64; 2]) -> f64 {
        match self {
            Shape::Box { corners, .. } => box_distance(p, corners),
            Shape::Cyl { c, .. } => cylinder_distance(p, c),
        }
    }

    /// Distance from a segment to the footprint; 0 when they touch or cross.
    fn distance_to_segment(&self, a: [f64; 2], b: [f64; 2]) -> f64 {
        match self {
            Shape::Box { corners, .. } => {
                if point_in_convex(a, corners) || point_in_convex(b, corners) {
                    return 0.0;
                }
                let mut d = f64::INFINITY;
                for k in 0..4 {
                    d = d.min(segment_segment_distance(a, b, corners[k], corners[(k + 1) % 4]));
                }
                d
            }
            Shape::Cyl { c, .. } => (point_segment_distance(c.center, a, b) - c.radius).max(0.0),
        }
    }

    fn overlaps(&self, other: &Shape) -> bool {
        match (self, other) {
            (Shape::Cyl { c, .. }, o) | (o, Shape::Cyl { c, .. }) => o.distance_to_point(c.center) < c.radius,
            (Shape::Box { corners: p, .. }, Shape::Box { corners: q, .. }) => {
                p.iter().any(|x| point_in_convex(*x, q))
                    || q.iter().any(|x| point_in_convex(*x, p))
                    || (0..4).any(|i| {
                        (0..4).any(|j| segment_segment_distance(p[i], p[(i + 1) % 4], q[j], q[(j + 1) % 4]) <= 0.0)
                    })
            }
        }
    }
}

pub(crate) fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

pub(crate) fn cross(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[1] - a[1] * b[0]
}

fn point_in_convex(p: [f64; 2], poly: &[[f64; 2]; 4]) -> bool {
    (0..4).all(|k| {
        let (a, b) = (poly[k], poly[(k + 1) % 4]);
        cross([b[0] - a[0], b[1] - a[1]], [p[0] - a[0], p[1] - a[1]]) >= 0.0
    })
}

pub(crate) fn point_segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let ab = [b[0] - a[0], b[1] - a[1]];
    let len2 = ab[0] * ab[0] + ab[1] * ab[1];
    let t = if len2 > 0.0 { (((p[0] - a[0]) * ab[0] + (p[1] - a[1]) * ab[1]) / len2).clamp(0.0, 1.0) } else { 0.0 };
    dist(p, [a[0] + ab[0] * t, a[1] + ab[1] * t])
}

fn segment_segment_distance(a: [f64; 2], b: [f64; 2], c: [f64; 2], d: [f64; 2]) -> f64 {
    let r = [b[0] - a[0], b[1] - a[1]];
    let s = [d[0] - c[0], d[1] - c[1]];
    let den = cross(r, s);
    if den.abs() > 1e-12 {
        let ca = [c[0] - a[0], c[1] - a[1]];
        let t = cross(ca, s) / den;
        let u = cross(ca, r) / den;
        if (0.0..=1.0).contains(&t) && (0.0..=1.0).contains(&u) {
            return 0.0;
        }
    }
    point_segment_distance(a, c, d)
        .min(point_segment_distance(b, c, d))
        .min(point_segment_distance(c, a, b))
        .min(point_segment_distance(d, a, b))
}

/// A small deterministic generator (SplitMix64) so worlds and noise need no RNG crate.
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        Self(seed ^ 0x9E37_79B9_7F4A_7C15)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix64(self.0)
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }
}

/// The SplitMix64 finaliser: a good 64-bit hash.
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn office_parses_and_has_the_mission_places() {
        let w = World::office();
        for p in ["R9", "D2", "D9", "J1"] {
            assert!(w.places.contains_key(p), "{p}");
        }
        assert!(w.faces().len() > 20);
        assert_eq!(w.cylinders.len(), 1);
        assert!(w.boxes.len() >= 2);
    }

    #[test]
    fn doors_split_walls_with_lintels() {
        let w = World {
            name: "t".into(),
            ceiling_height: Some(2.6),
            walls: vec![Wall {
                name: String::new(),
                points: vec![[0.0, 0.0], [4.0, 0.0]],
                height: 2.6,
                doors: vec![Door { name: "D".into(), at: 2.0, width: 1.0, height: 2.0 }],
            }],
            boxes: vec![],
            cylinders: vec![],
            places: BTreeMap::new(),
            start: Pose::new(2.0, -2.0, 0.0),
            random: None,
            low_faces: LowFaces::default(),
        };
        w.validate("t").unwrap();
        let f = w.faces();
        assert_eq!(f.len(), 3);
        assert_eq!((f[0].a, f[0].b), ([0.0, 0.0], [1.5, 0.0]));
        assert_eq!((f[1].z0, f[1].z1), (2.0, 2.6));
        assert_eq!((f[2].a, f[2].b, f[2].along0), ([2.5, 0.0], [4.0, 0.0], 2.5));
    }

    #[test]
    fn clearance_follows_walls_moved_after_its_first_use() {
        let mut w = World::office();
        let (x, y) = (w.start.x, w.start.y);
        let before = w.clearance(x, y).distance_m;
        // Every wall 0.1 m further along +y: the same question must now get a fresh answer.
        for wall in &mut w.walls {
            wall.points.iter_mut().for_each(|p| p[1] += 0.1);
        }
        let moved = w.clearance(x, y).distance_m;
        let mut fresh = w.clone();
        fresh.low_faces = LowFaces::default();
        assert_eq!(moved, fresh.clearance(x, y).distance_m);
        assert_ne!(moved, before);
    }

    #[test]
    fn advance_follows_an_arc() {
        let p = Pose::new(0.0, 0.0, 0.0).advance(1.0, std::f64::consts::FRAC_PI_2, 1.0);
        let r = 2.0 / std::f64::consts::PI;
        assert!((p.x - r).abs() < 1e-12 && (p.y - r).abs() < 1e-12);
        assert!((p.yaw - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }

    #[test]
    fn random_obstacles_keep_the_lane_passable() {
        let w = World::office();
        let r = w.random.clone().unwrap();
        let len = dist(r.from, r.to);
        let u = [(r.to[0] - r.from[0]) / len, (r.to[1] - r.from[1]) / len];
        for seed in 0..20 {
            let v = w.with_random_obstacles(seed).unwrap();
            assert_eq!(v, w.with_random_obstacles(seed).unwrap());
            // Sweep along the lane: at every station a free interval of min_gap across it exists.
            let mut s = 0.0;
            while s < len {
                let p = [r.from[0] + u[0] * s, r.from[1] + u[1] * s];
                let n = [-u[1], u[0]];
                let mut free = 0.0f64;
                let mut run = 0.0f64;
                let steps = 80;
                for k in 0..=steps {
                    let l = -r.half_width_m + 2.0 * r.half_width_m * k as f64 / steps as f64;
                    let q = [p[0] + n[0] * l, p[1] + n[1] * l];
                    let blocked = v.obstacle_shapes().iter().any(|sh| sh.distance_to_point(q) <= 0.0);
                    run = if blocked { 0.0 } else { run + 2.0 * r.half_width_m / steps as f64 };
                    free = free.max(run);
                }
                assert!(free >= r.min_gap_m - 0.06, "seed {seed}: only {free:.2} m free at {s:.1} m");
                s += 0.1;
            }
        }
    }
}
