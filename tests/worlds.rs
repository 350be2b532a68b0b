//! The shipped worlds (`mocks/worlds/*.toml`) and maps (`maps/*.toml`): every file loads, each
//! world's map agrees with its geometry, the missions documented in docs/sim-world.md plan, and
//! the random obstacles of every seed leave the mission's way passable for the robot.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};

use flownav::pafsis::local::unroll;
use flownav::pafsis::{Action, LegKind, Mission, Side, TopoMap, plan};
use mocks::World;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The robot's radius (flownav sim) plus the margin the navigation keeps to a wall of its lane
/// (`lane_margin_m`), and to an obstacle (its path margin), m.
const WALL_CLEARANCE_M: f64 = 0.18 + 0.1;
const OBSTACLE_CLEARANCE_M: f64 = 0.18 + 0.2;

fn files(dir: &str) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(Path::new(ROOT).join(dir))
        .unwrap_or_else(|e| panic!("{dir}: {e}"))
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .collect();
    v.sort();
    v
}

fn world(name: &str) -> World {
    World::load(Path::new(ROOT).join("mocks/worlds").join(format!("{name}.toml"))).unwrap()
}

fn map(name: &str) -> TopoMap {
    TopoMap::load(Path::new(ROOT).join("maps").join(format!("{name}.toml"))).unwrap()
}

/// A place's position: the world's `[places]`, else the map's (as `flownav sim` takes it).
fn position(w: &World, m: &TopoMap, place: &str) -> Option<[f64; 2]> {
    w.places.get(place).copied().or_else(|| m.place(place).and_then(|p| p.position_m))
}

/// The default missions as docs/sim-world.md gives them: (world, mission) from each
/// `flownav sim --world mocks/worlds/W.toml --map maps/W.toml --mission A:B` line.
fn documented_missions() -> Vec<(String, String)> {
    let doc = std::fs::read_to_string(Path::new(ROOT).join("docs/sim-world.md")).unwrap();
    let arg = |line: &str, flag: &str| {
        let rest = &line[line.find(flag)? + flag.len()..];
        rest.split_whitespace().next().map(str::to_string)
    };
    doc.lines()
        .filter(|l| l.contains("flownav sim ") && l.contains("--world mocks/worlds/"))
        .map(|l| {
            let w = arg(l, "--world").unwrap();
            let m = arg(l, "--map").unwrap_or_else(|| panic!("docs/sim-world.md: no --map in {l:?}"));
            let stem = |p: &str| Path::new(p).file_stem().unwrap().to_string_lossy().into_owned();
            assert_eq!(stem(&w), stem(&m), "docs/sim-world.md: world and map differ in {l:?}");
            (stem(&w), arg(l, "--mission").unwrap_or_else(|| panic!("docs/sim-world.md: no --mission in {l:?}")))
        })
        .collect()
}

#[test]
fn every_world_and_map_loads_and_each_map_matches_its_world() {
    let worlds = files("mocks/worlds");
    assert!(worlds.len() >= 4, "{worlds:?}");
    for path in &worlds {
        let w = World::load(path).unwrap_or_else(|e| panic!("{e}"));
        assert!(!w.places.is_empty(), "{}: no [places]", path.display());
    }
    for path in files("maps") {
        let m = TopoMap::load(&path).unwrap_or_else(|e| panic!("{e}"));
        // A map named after a world describes that world exactly: its positions are the world's
        // places, and every edge is a straight run of its actions' length in its heading.
        let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
        let Some(w) = worlds.iter().find(|p| p.file_stem().unwrap().to_string_lossy() == stem) else { continue };
        let w = World::load(w).unwrap();
        let mut walls = w.clone();
        (walls.boxes, walls.cylinders) = (vec![], vec![]);
        for p in &m.places {
            let Some(pos) = p.position_m else { continue };
            if let Some(q) = w.places.get(&p.name) {
                assert!(
                    (pos[0] - q[0]).hypot(pos[1] - q[1]) < 1e-6,
                    "{stem}: {} at {pos:?} in the map, {q:?} in the world",
                    p.name
                );
            }
            let c = walls.clearance(pos[0], pos[1]);
            assert!(c.distance_m >= 0.25, "{stem}: place {} is {:.2} m from {}", p.name, c.distance_m, c.object);
        }
        for e in &m.edges {
            let (a, b) = (m.place(&e.from).unwrap(), m.place(&e.to).unwrap());
            let (Some(a), Some(b)) = (a.position_m, b.position_m) else { continue };
            let length: f64 = e
                .actions
                .iter()
                .map(|act| match act {
                    Action::ExitRoom { length_m, .. }
                    | Action::EnterRoom { length_m, .. }
                    | Action::GoThroughDoor { length_m, .. }
                    | Action::FollowCorridor { length_m, .. } => *length_m,
                    _ => 0.0,
                })
                .sum();
            let d = (b[0] - a[0]).hypot(b[1] - a[1]);
            assert!(
                (length - d).abs() < 0.01,
                "{stem}: edge {} -> {} is {length} m long, its places {d:.3} m apart",
                e.from,
                e.to
            );
            let heading = (b[1] - a[1]).atan2(b[0] - a[0]).to_degrees();
            let off = (heading - e.heading_deg + 540.0).rem_euclid(360.0) - 180.0;
            assert!(
                off.abs() < 0.5,
                "{stem}: edge {} -> {} heads {} deg, its places lie {heading:.1} deg",
                e.from,
                e.to,
                e.heading_deg
            );
        }
    }
}

#[test]
fn the_crowded_office_is_the_office_but_for_its_random_obstacles() {
    // office-dense.toml copies the office's geometry, places and fixed obstacles, and runs with
    // its map: a change to office.toml must be made there too
    let (office, mut dense) = (world("office"), world("office-dense"));
    let (a, b) = (office.random.clone().unwrap(), dense.random.clone().unwrap());
    assert!(b.people + b.boxes > a.people + a.boxes && b.min_spacing_m < a.min_spacing_m, "{b:?}");
    (dense.name, dense.random) = (office.name.clone(), office.random.clone());
    assert!(dense == office, "mocks/worlds/office-dense.toml differs from office.toml beyond [random] and its name");
}

#[test]
fn the_documented_missions_plan_with_corner_turns_and_doors_on_both_sides() {
    let missions = documented_missions();
    for name in ["lshape", "narrow", "hall"] {
        assert!(missions.iter().any(|(w, _)| w == name), "docs/sim-world.md gives no mission for {name}: {missions:?}");
    }
    for (name, mission) in &missions {
        let (w, m) = (world(name), map(name));
        let mission: Mission = mission.parse().unwrap();
        let p = plan(&m, &mission).unwrap_or_else(|e| panic!("{name}: {e}"));
        for place in [&mission.from, &mission.to] {
            assert!(w.places.contains_key(place), "{name}: {place} has no position in the world's [places]");
        }
        for place in &p.waypoints {
            assert!(position(&w, &m, place).is_some(), "{name}: waypoint {place} has no position");
        }
        let start = m.place(&mission.from).and_then(|p| p.heading_deg).unwrap_or(0.0).to_radians();
        let legs = unroll(&m, &p, start);
        let sides: Vec<Side> = legs
            .iter()
            .filter_map(|l| match &l.kind {
                LegKind::Corridor { doors, .. } => Some(doors.iter().filter_map(|d| d.side)),
                _ => None,
            })
            .flatten()
            .collect();
        if name == "office" {
            continue;
        }
        assert!(p.length_m >= 10.0, "{name}: {mission} is only {:.1} m", p.length_m);
        assert!(
            sides.contains(&Side::Left) && sides.contains(&Side::Right),
            "{name}: {mission} passes doors on one side only: {sides:?}"
        );
        assert!(sides.len() >= 4, "{name}: {mission} passes {} doors", sides.len());
        if name == "lshape" {
            // The corner: a turn on the spot between two corridor legs.
            let corner = legs.windows(3).any(|w| {
                matches!(w[0].kind, LegKind::Corridor { .. })
                    && w[1].kind == LegKind::Turn
                    && matches!(w[2].kind, LegKind::Corridor { .. })
            });
            assert!(corner, "lshape: {mission} turns at no corner: {legs:?}");
        }
    }
}

/// A grid over the world where the robot's centre may be: far enough from every wall (plan
/// coordinates, `STEP_M` cells).
struct Free {
    x0: f64,
    y0: f64,
    nx: usize,
    ny: usize,
    walls_ok: Vec<bool>,
}

const STEP_M: f64 = 0.05;

impl Free {
    /// The grid over the box round `places` (with 1 m to spare).
    fn new(w: &World, places: &[[f64; 2]]) -> Free {
        let mut walls_only = w.clone();
        (walls_only.boxes, walls_only.cylinders) = (vec![], vec![]);
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for p in places {
            (x0, y0, x1, y1) = (x0.min(p[0]), y0.min(p[1]), x1.max(p[0]), y1.max(p[1]));
        }
        let (x0, y0) = (x0 - 1.0, y0 - 1.0);
        let (nx, ny) = (((x1 + 1.0 - x0) / STEP_M) as usize + 1, ((y1 + 1.0 - y0) / STEP_M) as usize + 1);
        let walls_ok = (0..nx * ny)
            .map(|k| {
                let (x, y) = (x0 + (k % nx) as f64 * STEP_M, y0 + (k / nx) as f64 * STEP_M);
                walls_only.clearance(x, y).distance_m >= WALL_CLEARANCE_M
            })
            .collect();
        Free { x0, y0, nx, ny, walls_ok }
    }

    fn point(&self, k: usize) -> [f64; 2] {
        [self.x0 + (k % self.nx) as f64 * STEP_M, self.y0 + (k / self.nx) as f64 * STEP_M]
    }

    fn cell(&self, p: [f64; 2]) -> usize {
        let i = ((p[0] - self.x0) / STEP_M).round() as usize;
        let j = ((p[1] - self.y0) / STEP_M).round() as usize;
        j * self.nx + i
    }

    /// Whether the robot can get from `a` to `b` keeping its clearances, among the walls of the
    /// world this grid was made for and the obstacles of `w`.
    fn connects(&self, w: &World, a: [f64; 2], b: [f64; 2]) -> bool {
        let cells: Vec<usize> = (0..self.walls_ok.len()).filter(|&k| self.walls_ok[k]).collect();
        let points: Vec<[f64; 2]> = cells.iter().map(|&k| self.point(k)).collect();
        let mut ok = vec![false; self.walls_ok.len()];
        for (&k, d) in cells.iter().zip(w.obstacle_distances(&points)) {
            ok[k] = d.iter().all(|&d| d >= OBSTACLE_CLEARANCE_M);
        }
        let (start, goal) = (self.cell(a), self.cell(b));
        let mut seen = vec![false; ok.len()];
        let mut queue = VecDeque::from([start]);
        seen[start] = true;
        while let Some(k) = queue.pop_front() {
            if k == goal {
                return true;
            }
            let (i, j) = (k % self.nx, k / self.nx);
            let next = [
                (i > 0).then(|| k - 1),
                (i + 1 < self.nx).then(|| k + 1),
                (j > 0).then(|| k - self.nx),
                (j + 1 < self.ny).then(|| k + self.nx),
            ];
            for n in next.into_iter().flatten() {
                if ok[n] && !seen[n] {
                    seen[n] = true;
                    queue.push_back(n);
                }
            }
        }
        false
    }
}

#[test]
fn random_obstacles_leave_every_documented_mission_passable() {
    // the documented missions, each in its world with its map, and the crowded office's
    // (a stress world with the office's map)
    let missions = documented_missions().into_iter().map(|(w, mission)| (w.clone(), w, mission));
    let stress = [("office-dense".to_string(), "office".to_string(), "R9:D2".to_string())];
    for (name, map_name, mission) in missions.chain(stress) {
        let w = world(&name);
        let mission: Mission = mission.parse().unwrap();
        let (a, b) = (w.places[&mission.from], w.places[&mission.to]);
        let m = map(&map_name);
        let route = plan(&m, &mission).unwrap();
        let places: Vec<[f64; 2]> = route.waypoints.iter().filter_map(|p| position(&w, &m, p)).collect();
        let free = Free::new(&w, &places);
        assert!(free.connects(&w, a, b), "{name}: {mission} is blocked without random obstacles");
        if w.random.is_none() {
            continue;
        }
        // Every seed of the tuning and reporting ranges places its obstacles ...
        for seed in 0..200 {
            w.with_random_obstacles(seed).unwrap_or_else(|e| panic!("{name}, seed {seed}: {e}"));
        }
        // ... and a few of them, checked cell by cell, leave a way through.
        for seed in [0, 1, 2, 100, 101, 102] {
            let v = w.with_random_obstacles(seed).unwrap();
            assert!(free.connects(&v, a, b), "{name}, seed {seed}: the obstacles block {mission}");
        }
    }
}
