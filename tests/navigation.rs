//! Navigation: the shipped office map, PAFSIS following a plan from scripted landmarks and
//! odometry, and MOFIS behaviour.

use flownav::odometry_calibration::OdometryCalibration;
use flownav::pafsis::map::{Side, wrap_angle};
use flownav::pafsis::{GoalStatus, LegKind, Mission, Pafsis, PafsisEvent, PafsisParams, TopoMap, WallSighting};
use flownav::perception::{Obstacle, Perception, Tpo, TpoShape};
use hal::BodyVelocity;

fn office() -> TopoMap {
    TopoMap::load(concat!(env!("CARGO_MANIFEST_DIR"), "/maps/office.toml")).expect("maps/office.toml loads")
}

/// A robot in the office corridor (maps/office.toml geometry), driven by PAFSIS alone with an
/// ideal heading controller, whose perception is scripted from its true pose: the nearest door
/// 1–4 m ahead while in the corridor, else the end wall within 5 m, else "corridor".
struct Walk {
    x: f64,
    y: f64,
    heading: f64,
    /// Odometry reports this fraction of the true distance (wheel slip, wrong wheel radius).
    odo_scale: f64,
    /// Whether OFFIS reports landmarks at all.
    landmarks: bool,
    /// Odometry reports this much turn rate on top of the true one (unequal wheels), rad/s.
    omega_bias: f64,
    /// Whether OFFIS fits the corridor's side walls (y = ±1 m) when they are in view.
    walls: bool,
    /// The wall (y = +1 or −1 m) whose door openings (0.9 m wide, at [`DOOR_X`]) the fitted
    /// side walls show; `None`: no openings.
    openings_in: Option<f64>,
    /// The openings also show while their doors are 3.5–5 m ahead, placed this much nearer than
    /// they are (far away an opening spans about one profile bin and is placed short), m.
    far_openings_short_m: Option<f64>,
    /// Odometry reports this much turn per metre driven on top of the true one (unequal wheel
    /// radii), rad/m.
    bend_rad_m: f64,
    /// Whether the flow measures, every fourth step, the turn the odometry missed since the
    /// last measurement (as `Offis::measure_yaw` does for each keyframe pair), while driving,
    /// and the odometry is corrected by the errors learned from it.
    flow_yaw: bool,
    calibration: OdometryCalibration,
    /// OFFIS names no TPO but reports the end wall as the nearest obstacle when it is within
    /// 1 m ahead (close up, the wall fills the view).
    end_wall_as_obstacle: bool,
    /// Something in the corridor at this x (a box) that OFFIS reads as this shape when it is
    /// 0.3–0.8 m ahead.
    phantom: Option<(f64, TpoShape)>,
    /// Largest distance from the corridor's centre line while following it, m.
    max_off_centre_m: f64,
    path_m: f64,
}

/// Doors (both sides) and the end walls of the office corridor (mocks/worlds/office.toml).
const DOOR_X: [f64; 5] = [3.0, 9.0, 15.0, 21.0, 27.0];
const END_WALL_X: f64 = 30.0;

impl Walk {
    fn new(x: f64, y: f64, heading_deg: f64) -> Self {
        Self {
            x,
            y,
            heading: heading_deg.to_radians(),
            odo_scale: 1.0,
            landmarks: true,
            omega_bias: 0.0,
            walls: false,
            openings_in: None,
            far_openings_short_m: None,
            bend_rad_m: 0.0,
            flow_yaw: false,
            calibration: OdometryCalibration::default(),
            phantom: None,
            end_wall_as_obstacle: false,
            max_off_centre_m: 0.0,
            path_m: 0.0,
        }
    }

    /// The corridor's side walls from 1 m to 3 m ahead, in the robot's frame, while the robot
    /// is in the corridor and faces along it.
    fn side_walls(&self) -> Vec<WallSighting> {
        if !self.walls || self.y.abs() >= 1.0 || self.heading.sin().abs() > 0.5 {
            return Vec::new();
        }
        let (s, c) = self.heading.sin_cos();
        let to_robot = |x: f64, y: f64| {
            let (dx, dy) = (x - self.x, y - self.y);
            [c * dx + s * dy, -s * dx + c * dy]
        };
        let ahead = self.heading.cos().signum();
        [1.0, -1.0]
            .into_iter()
            .map(|wall_y| {
                let (a, b) = (to_robot(self.x + ahead, wall_y), to_robot(self.x + 3.0 * ahead, wall_y));
                let n = (b[0] - a[0]).hypot(b[1] - a[1]);
                let mut openings = [None; 2];
                let near = DOOR_X.iter().filter(|&&x| (1.5..=2.5).contains(&((x - self.x) * ahead))).copied();
                let far = self.far_openings_short_m.into_iter().flat_map(|short| {
                    let far = DOOR_X.iter().filter(|&&x| (3.5..=5.0).contains(&((x - self.x) * ahead)));
                    far.map(move |&x| x - short * ahead)
                });
                for (slot, x) in openings.iter_mut().zip(near.chain(far)).filter(|_| self.openings_in == Some(wall_y)) {
                    *slot = Some([to_robot(x + 0.45 * ahead, wall_y), to_robot(x - 0.45 * ahead, wall_y)]);
                }
                WallSighting { point_m: a, dir: [(b[0] - a[0]) / n, (b[1] - a[1]) / n], length_m: n, openings }
            })
            .collect()
    }

    fn perceive(&self) -> Perception {
        let mut p = Perception::default();
        let along_corridor = self.heading.sin().abs() < 0.2 && self.y.abs() < 1.0;
        if self.end_wall_as_obstacle && along_corridor {
            let dir = self.heading.cos().signum();
            let wall = if dir > 0.0 { END_WALL_X - self.x } else { self.x };
            if wall <= 1.0 {
                p.obstacle = Obstacle { present: true, distance_m: Some(wall), bearing_rad: Some(0.0), cell: None };
            }
        }
        if !self.landmarks || !along_corridor {
            return p;
        }
        let dir = self.heading.cos().signum();
        let door = DOOR_X.iter().map(|&dx| (dx - self.x) * dir).filter(|d| (1.0..=4.0).contains(d)).reduce(f64::min);
        let wall = if dir > 0.0 { END_WALL_X - self.x } else { self.x };
        let phantom =
            self.phantom.map(|(x, shape)| (shape, (x - self.x) * dir)).filter(|(_, d)| (0.3..=0.8).contains(d));
        p.tpo = match door {
            _ if phantom.is_some() => {
                let (shape, d) = phantom.unwrap_or((TpoShape::None, 0.0));
                Tpo { shape, confidence: 0.9, distance_m: Some(d) }
            }
            Some(d) => Tpo { shape: TpoShape::Door, confidence: 0.9, distance_m: Some(d) },
            None if wall <= 5.0 => Tpo { shape: TpoShape::Wall, confidence: 0.9, distance_m: Some(wall) },
            None => Tpo { shape: TpoShape::Corridor, confidence: 0.9, distance_m: None },
        };
        p
    }

    /// Runs the mission to its end (or `max_s` seconds); returns the final status and all events.
    fn run(&mut self, nav: &mut Pafsis, max_s: f64) -> (GoalStatus, Vec<PafsisEvent>) {
        let dt = 0.05;
        let mut odo = BodyVelocity::ZERO;
        let mut events = Vec::new();
        // true turn, odometry turn and odometry distance since the last flow measurement
        let mut pair = [0.0f64; 4];
        for k in 0..(max_s / dt) as usize {
            nav.observe_walls(&self.side_walls());
            let goal = nav.step(&self.perceive(), odo, dt);
            if k % 4 == 0 {
                let [truth, turned, raw, driven] = std::mem::take(&mut pair);
                if self.flow_yaw && driven > 0.005 {
                    // what the pipeline does with each keyframe pair's measured yaw; the flow's
                    // median carries matching noise: ±0.3 mrad, alternating
                    let residual = truth - turned + if k % 8 == 0 { 3e-4 } else { -3e-4 };
                    self.calibration.observe(raw, driven, residual + self.calibration.correction(raw, driven));
                    nav.correct_heading(residual);
                }
            }
            events.extend(nav.take_events());
            if goal.status != GoalStatus::Active {
                return (goal.status, events);
            }
            let omega = (1.5 * goal.angle_rad).clamp(-1.0, 1.0);
            // PAFSIS gives the leg's speed; this robot slows for the turn, as MOFIS does
            let speed = goal.velocity * goal.angle_rad.cos().max(0.0);
            self.heading += omega * dt;
            self.x += speed * dt * self.heading.cos();
            self.y += speed * dt * self.heading.sin();
            self.path_m += speed * dt;
            if self.y.abs() < 1.0 && self.heading.sin().abs() < 0.5 {
                self.max_off_centre_m = self.max_off_centre_m.max(self.y.abs());
            }
            let v = speed * self.odo_scale;
            let raw = BodyVelocity::new(v, omega + self.omega_bias + self.bend_rad_m * v);
            odo = if self.flow_yaw { self.calibration.apply(raw) } else { raw };
            pair[0] += omega * dt;
            pair[1] += odo.omega * dt;
            pair[2] += raw.omega * dt;
            pair[3] += odo.v * dt;
        }
        (nav.status(), events)
    }
}

fn mission(map: &TopoMap, m: &str) -> Pafsis {
    Pafsis::new(map.clone(), m.parse::<Mission>().unwrap(), PafsisParams::default()).unwrap()
}

#[test]
fn office_plan_r9_to_d2() {
    let map = office();
    let nav = mission(&map, "R9:D2");
    assert_eq!(nav.plan().waypoints, ["R9", "D9", "C4", "C3", "C2", "D2"]);
    assert_eq!(nav.plan().length_m, 15.5);
    // Exit R9 to the centre line, turn left into the corridor (facing west), one merged corridor
    // leg along the centre line, turn right to face D2, step up to it.
    let legs = nav.legs();
    assert_eq!(legs.len(), 6, "{legs:#?}");
    assert!(matches!(&legs[0].kind, LegKind::Doorway { door, .. } if door == "D9"));
    assert_eq!(legs[1].to_string(), "follow the corridor 0.5 m passing 0 doors left, 0 right");
    assert!(matches!(legs[2].kind, LegKind::Turn));
    assert!((legs[2].heading_rad.abs() - std::f64::consts::PI).abs() < 1e-9);
    // D3 and D2 are the places the edges stop at; D8 and D7 face them across the corridor
    assert_eq!(legs[3].to_string(), "follow the corridor 12.0 m passing 2 doors left, 1 right, stop at D2");
    assert!(matches!(legs[4].kind, LegKind::Turn));
    assert!((legs[4].heading_rad - std::f64::consts::FRAC_PI_2).abs() < 1e-9);
}

#[test]
fn office_mission_arrives_in_front_of_d2() {
    let map = office();
    let mut nav = mission(&map, "R9:D2");
    let mut walk = Walk::new(21.0, -3.0, 90.0);
    let (status, events) = walk.run(&mut nav, 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!((walk.x - 9.0).abs() < 0.3 && (walk.y - 0.5).abs() < 0.2, "stopped at ({:.2}, {:.2})", walk.x, walk.y);
    let matched = events.iter().filter(|e| matches!(e, PafsisEvent::DoorMatched { .. })).count();
    assert_eq!(matched, 2, "D3 passed and D2 sighted: {events:#?}");
    assert!(!events.iter().any(|e| matches!(e, PafsisEvent::LandmarkMissed { .. })));
}

#[test]
fn a_goal_behind_the_robot_keeps_the_legs_speed() {
    // two robots at R9, one turned on the spot 2.8 rad away from the doorway leg: PAFSIS gives
    // both the leg's speed: MOFIS turns, and slows for the turn
    let map = office();
    let (mut facing, mut turned) = (mission(&map, "R9:D2"), mission(&map, "R9:D2"));
    let p = Perception::default();
    let (mut ahead, mut behind) = (None, None);
    for _ in 0..10 {
        ahead = Some(facing.step(&p, BodyVelocity::ZERO, 0.05));
        behind = Some(turned.step(&p, BodyVelocity::new(0.0, 5.6), 0.05));
    }
    let (ahead, behind) = (ahead.unwrap(), behind.unwrap());
    assert!(ahead.angle_rad.abs() < 0.1 && ahead.velocity > 0.05, "{ahead:?}");
    assert!(behind.angle_rad.abs() > 2.5, "{behind:?}");
    assert_eq!(behind.velocity, ahead.velocity);
}

#[test]
fn door_sightings_correct_bad_odometry() {
    let map = office();
    // Odometry under-reports distance by 5% (worn tyres, a bad ticks-per-metre calibration):
    // 0.6 m short after the 12 m corridor leg. Door sightings are matched within
    // `landmark_gate_m` (0.5 m) of where the odometry expects the door, so each one, 6 m apart,
    // takes out the 0.3 m accumulated since the last.
    let mut with = Walk { odo_scale: 0.95, ..Walk::new(21.0, -3.0, 90.0) };
    let (status, _) = with.run(&mut mission(&map, "R9:D2"), 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!((with.x - 9.0).abs() < 0.25, "with landmarks stopped at x = {:.2}", with.x);

    let mut without = Walk { odo_scale: 0.95, landmarks: false, ..Walk::new(21.0, -3.0, 90.0) };
    let (status, events) = without.run(&mut mission(&map, "R9:D2"), 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!(without.x < 8.5, "odometry alone overshoots D2 by 0.6 m (x = {:.2})", without.x);
    let missed = events.iter().filter(|e| matches!(e, PafsisEvent::LandmarkMissed { .. })).count();
    assert_eq!(missed, 2, "every door the edges stop at reported missing (D3, D2)");
}

#[test]
fn doors_seen_in_the_side_wall_correct_the_progress_on_their_side_only() {
    // Odometry over-reports distance by 5 % (or the map's lengths are 5 % short): alone, the
    // robot stops 0.6 m before D2. OFFIS names no TPO; the fitted side walls show the doors'
    // openings, D3 and D2 in the north wall (on the right, heading west) or D8 and D7 facing
    // them in the south wall.
    let walk = |openings_in| Walk {
        odo_scale: 1.05,
        landmarks: false,
        walls: true,
        openings_in,
        ..Walk::new(21.0, -3.0, 90.0)
    };
    let matched = |events: &[PafsisEvent], side: Side| {
        events.iter().filter(|e| matches!(e, PafsisEvent::DoorMatched { side: Some(s), .. } if *s == side)).count()
    };
    for (wall_y, side) in [(1.0, Side::Right), (-1.0, Side::Left)] {
        let mut w = walk(Some(wall_y));
        let (status, events) = w.run(&mut mission(&office(), "R9:D2"), 120.0);
        assert_eq!(status, GoalStatus::Arrived);
        assert_eq!(matched(&events, side), 2, "two doors matched on the {side:?}: {events:#?}");
        assert!((w.x - 9.0).abs() < 0.25, "with the openings on the {side:?} stopped at x = {:.2}", w.x);
    }

    // A map that does not place the doors of the south wall: openings there match nothing.
    let mut north_only = office();
    for p in north_only.places.iter_mut().filter(|p| matches!(p.name.as_str(), "D6" | "D7" | "D8" | "D10")) {
        p.position_m = None;
    }
    for openings_in in [Some(-1.0), None] {
        let mut other = walk(openings_in);
        let (status, events) = other.run(&mut mission(&north_only, "R9:D2"), 120.0);
        assert_eq!(status, GoalStatus::Arrived);
        assert_eq!(matched(&events, Side::Left) + matched(&events, Side::Right), 0, "{openings_in:?}: {events:#?}");
        assert!(other.x > 9.45, "without openings on the doors' side stopped at x = {:.2}", other.x);
    }
}

#[test]
fn a_side_door_placed_short_from_afar_is_placed_again_from_near() {
    // The map's lengths are 5 % short of the odometry's. Each door's opening first shows 3.5–5 m
    // ahead placed 0.5 m short (those over about 4 m meet the wall too flat to count), then
    // 1.5–2.5 m ahead where it is: the near frames, though fewer and later, move the progress to
    // the door's true place (a rule that keeps the first frames' place stops 0.63 m short of D2).
    let mut w = Walk {
        odo_scale: 1.05,
        landmarks: false,
        walls: true,
        openings_in: Some(1.0),
        far_openings_short_m: Some(0.5),
        ..Walk::new(21.0, -3.0, 90.0)
    };
    let (status, events) = w.run(&mut mission(&office(), "R9:D2"), 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    let matched =
        events.iter().filter(|e| matches!(e, PafsisEvent::DoorMatched { side: Some(Side::Right), .. })).count();
    assert_eq!(matched, 2, "{events:#?}");
    assert!((w.x - 9.0).abs() < 0.25, "stopped at x = {:.2}", w.x);
}

#[test]
fn side_walls_correct_a_drifting_heading() {
    let map = office();
    // Odometry reports 0.01 rad/s of turn that is not there (unequal wheels): believing it
    // drifts left, the robot steers right, and down the 12 m corridor its heading goes 0.3 rad
    // wrong.
    let drifting = || Walk { omega_bias: 0.01, ..Walk::new(21.0, -3.0, 90.0) };
    let mut with = Walk { walls: true, ..drifting() };
    let (status, _) = with.run(&mut wall_mission(&map), 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!(with.max_off_centre_m < 0.25, "with side walls {:.2} m off the centre line", with.max_off_centre_m);
    assert!((with.x - 9.0).abs() < 0.3, "with side walls stopped at x = {:.2}", with.x);
    assert!(nav_fixes(&map, true) > 100, "side walls corrected the heading");

    let mut without = drifting();
    without.run(&mut wall_mission(&map), 120.0);
    assert!(without.max_off_centre_m > 0.9, "dead reckoning alone ran {:.2} m off", without.max_off_centre_m);
}

#[test]
fn the_flows_yaw_learns_the_odometrys_bend_and_keeps_the_heading() {
    let map = office();
    // Wheel radii 0.4 % unequal on a 0.3 m wheel base: the odometry reports 0.013 rad of turn
    // per metre that the robot does not make. (The turn scale, learned from arcs, has its own
    // test in odometry_calibration; this walk turns only on the spot.)
    let erring = || Walk { bend_rad_m: 0.013, ..Walk::new(21.0, -3.0, 90.0) };
    let heading_error = |w: &Walk, nav: &Pafsis| wrap_angle(nav.progress().heading_rad - w.heading).abs().to_degrees();

    let mut nav = mission(&map, "R9:D2");
    let mut with = Walk { flow_yaw: true, ..erring() };
    let (status, _) = with.run(&mut nav, 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    let cal = &with.calibration;
    assert!((cal.bend_rad_m() + 0.013).abs() < 0.002, "learned bend {} rad/m", cal.bend_rad_m());
    assert!(cal.pairs() > 100, "{} pairs", cal.pairs());
    assert!(heading_error(&with, &nav) < 1.0, "heading {:.2}° off", heading_error(&with, &nav));
    assert!((with.x - 9.0).abs() < 0.3, "stopped at x = {:.2}", with.x);
    assert!(with.max_off_centre_m < 0.3, "{:.2} m off the centre line", with.max_off_centre_m);

    let mut nav = mission(&map, "R9:D2");
    let mut without = erring();
    without.run(&mut nav, 120.0);
    assert!(heading_error(&without, &nav) > 5.0, "odometry alone {:.2}° off", heading_error(&without, &nav));
    assert!(without.max_off_centre_m > 0.5, "odometry alone {:.2} m off the centre line", without.max_off_centre_m);
}

#[test]
fn a_steady_drift_off_the_walls_corrects_a_start_heading_error() {
    let map = office();
    // The robot is put down 3° off the start place's heading. The flow's yaw measures only
    // changes and never sees it; the side walls show the robot drifting off the estimate.
    let heading_error = |w: &Walk, nav: &Pafsis| wrap_angle(nav.progress().heading_rad - w.heading).abs().to_degrees();
    let run = |drift: f64| {
        let params = PafsisParams { wall_drift_gain: drift, ..PafsisParams::default() };
        let mut nav = Pafsis::new(map.clone(), "R9:D2".parse::<Mission>().unwrap(), params).unwrap();
        let mut walk = Walk { walls: true, ..Walk::new(21.0, -3.0, 93.0) };
        let (status, _) = walk.run(&mut nav, 120.0);
        (status, heading_error(&walk, &nav), walk)
    };
    let (status, with, walk) = run(PafsisParams::default().wall_drift_gain);
    assert_eq!(status, GoalStatus::Arrived);
    assert!(with < 1.0, "with the drift term the heading ends {with:.2}° off");
    assert!((walk.x - 9.0).abs() < 0.3, "stopped at x = {:.2}", walk.x);
    let (_, without, _) = run(0.0);
    assert!(without > 2.5, "without it {without:.2}° off");
}

/// R9:D2 with the side walls pulling the heading (off by default: the flow's yaw keeps it).
fn wall_mission(map: &TopoMap) -> Pafsis {
    let params = PafsisParams { wall_heading_gain: 0.05, ..PafsisParams::default() };
    Pafsis::new(map.clone(), "R9:D2".parse::<Mission>().unwrap(), params).unwrap()
}

fn nav_fixes(map: &TopoMap, walls: bool) -> u64 {
    let mut nav = wall_mission(map);
    Walk { omega_bias: 0.01, walls, ..Walk::new(21.0, -3.0, 90.0) }.run(&mut nav, 120.0);
    nav.wall_fixes().frames
}

#[test]
fn missing_end_wall_relocalises_and_stops() {
    let map = office();
    let mut nav = mission(&map, "D3:J1");
    let mut walk = Walk { landmarks: false, ..Walk::new(15.0, 0.5, -90.0) };
    let (status, events) = walk.run(&mut nav, 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!(events.iter().any(|e| matches!(e, PafsisEvent::Replanned { from, .. } if from == "J1")), "{events:#?}");
    // The end wall at x = 0 was never reported; the robot gave up past the far edge of the
    // map's tolerance window round the 14 m leg's end (0.2 m + 5 %: 0.9 m), after the 0.5 m
    // step from D3 to the centre line.
    assert!((walk.path_m - 15.4).abs() < 0.1, "travelled {:.2} m", walk.path_m);

    let mut nav = mission(&map, "D3:J1");
    let mut walk = Walk::new(15.0, 0.5, -90.0);
    let (status, events) = walk.run(&mut nav, 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!(!events.iter().any(|e| matches!(e, PafsisEvent::Replanned { .. })));
    assert!((walk.x - 0.8).abs() < 0.1, "stops 0.8 m before the wall, at x = {:.2}", walk.x);

    // the end wall seen only as the nearest obstacle ahead ends the leg as well
    let mut nav = mission(&map, "D3:J1");
    let mut walk = Walk { landmarks: false, end_wall_as_obstacle: true, ..Walk::new(15.0, 0.5, -90.0) };
    let (status, events) = walk.run(&mut nav, 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!(!events.iter().any(|e| matches!(e, PafsisEvent::Replanned { .. })), "{events:#?}");
    assert!((walk.x - 0.8).abs() < 0.1, "stops 0.8 m before the wall, at x = {:.2}", walk.x);
}

#[test]
fn a_corner_or_wall_seen_far_from_where_the_map_ends_the_leg_does_not_end_it() {
    let map = office();
    // a box 0.6 m ahead at x = 11.5, 3 m into the 14 m leg to the end wall, read as a corner
    // or a wall: outside the map's window round the leg's end (±0.9 m), so the robot goes on
    for shape in [TpoShape::Corner, TpoShape::Wall] {
        let mut nav = mission(&map, "D3:J1");
        let mut walk = Walk { phantom: Some((11.5, shape)), ..Walk::new(15.0, 0.5, -90.0) };
        let (status, events) = walk.run(&mut nav, 120.0);
        assert_eq!(status, GoalStatus::Arrived);
        assert!((walk.x - 0.8).abs() < 0.1, "{shape:?}: stops 0.8 m before the end wall, at x = {:.2}", walk.x);
        assert!(!events.iter().any(|e| matches!(e, PafsisEvent::Replanned { .. })), "{events:#?}");
    }
    // the same box near the end of the leg ends it there: the end is where the map says,
    // within its tolerance
    let mut nav = mission(&map, "D3:J1");
    let mut walk = Walk { phantom: Some((0.9, TpoShape::Corner)), ..Walk::new(15.0, 0.5, -90.0) };
    let (status, _) = walk.run(&mut nav, 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!(walk.x > 0.9 && walk.x < 1.7, "ended at the corner seen 0.3–0.8 m ahead: x = {:.2}", walk.x);
}

#[test]
fn the_plan_says_how_far_ahead_it_stops_the_robot() {
    let map = office();
    let mut nav = mission(&map, "R9:D2");
    let none = Perception::default();
    // through D9 (2.5 m) and straight on to the centre line (0.5 m), then a turn on the spot
    assert_eq!(nav.stop_ahead_m(), Some(3.0));
    let forward = BodyVelocity::new(0.2, 0.0);
    for _ in 0..10 {
        nav.step(&none, forward, 0.1);
    }
    assert!((nav.stop_ahead_m().unwrap() - 2.8).abs() < 1e-9, "{:?}", nav.stop_ahead_m());
    while nav.progress().leg < 2 {
        nav.step(&none, forward, 0.1);
    }
    assert_eq!(nav.stop_ahead_m(), None, "turning on the spot: no stop ahead");
    let left = BodyVelocity::new(0.0, 0.5);
    while nav.progress().leg < 3 {
        nav.step(&none, left, 0.02);
    }
    // the 12 m corridor leg ends at D2, where the robot turns to face the door
    let ahead = nav.stop_ahead_m().expect("the corridor leg ends at a door, by odometry");
    assert!((ahead - 12.0).abs() < 0.05, "{ahead}");
}

#[test]
fn the_corridor_lane_comes_from_the_map_width_and_dead_reckoning() {
    let map = office();
    let mut nav = mission(&map, "R9:D2");
    let none = Perception::default();
    assert_eq!(nav.lane(), None, "leaving the room: the doorway leg has no lane");
    let forward = BodyVelocity::new(0.2, 0.0);
    while nav.progress().leg < 2 {
        nav.step(&none, forward, 0.1);
    }
    let left = BodyVelocity::new(0.0, 0.5);
    while nav.progress().leg < 3 {
        nav.step(&none, left, 0.02);
    }
    // on the centre line (y = 0) at x = 21 facing west along the 2 m corridor (width_m = 2.0)
    let lane = nav.lane().expect("the corridor leg has the map's width");
    assert!((lane.half_width_m - 1.0).abs() < 1e-12, "{lane:?}");
    // (the turn on the spot ends within its tolerance of the leg's heading)
    assert!(lane.left_m.abs() < 0.02 && lane.angle_rad.abs() < 0.06, "{lane:?}");
    let a0 = lane.angle_rad;
    // drift 0.3 m toward the south wall (the robot's left when facing west) and turn 0.2 rad
    // further left: the lane says so in the robot's frame
    let start = nav.position_m().unwrap();
    use std::f64::consts::FRAC_PI_2;
    nav.step(&none, BodyVelocity::new(0.0, FRAC_PI_2 / 0.5), 0.5);
    nav.step(&none, BodyVelocity::new(0.3, 0.0), 1.0);
    nav.step(&none, BodyVelocity::new(0.0, (0.2 - FRAC_PI_2) / 0.5), 0.5);
    let [x, y] = nav.position_m().unwrap();
    assert!((y - (start[1] - 0.3)).abs() < 0.02 && (x - start[0]).abs() < 0.02, "{x} {y}");
    let lane = nav.lane().unwrap();
    assert!((lane.left_m - 0.3).abs() < 0.02, "{lane:?}");
    assert!((lane.angle_rad - (a0 - 0.2)).abs() < 1e-9, "{lane:?}");
}

#[test]
fn the_door_of_a_doorway_leg_comes_from_the_map_opening_and_dead_reckoning() {
    let map = office();
    let mut nav = mission(&map, "R9:D2");
    let none = Perception::default();
    // in R9 at (21, -3) facing north: D9's opening (0.9 m, its wall 2 m along the 2.5 m exit)
    // is 2 m straight ahead
    let door = nav.doorway().expect("exit_room with width_m and door_at_m");
    assert!((door.centre_m[0] - 2.0).abs() < 1e-9 && door.centre_m[1].abs() < 1e-9, "{door:?}");
    assert!(door.angle_rad.abs() < 1e-12 && (door.half_width_m - 0.45).abs() < 1e-12, "{door:?}");
    // turned 0.3 rad left and driven 0.5 m that way: the door is right of ahead, turned right
    nav.step(&none, BodyVelocity::new(0.0, 0.3), 1.0);
    nav.step(&none, BodyVelocity::new(0.5, 0.0), 1.0);
    let door = nav.doorway().unwrap();
    let (x, y) = (21.0 - 0.5 * 0.3f64.sin(), -3.0 + 0.5 * 0.3f64.cos());
    let (dx, dy) = (21.0 - x, -1.0 - y);
    let (s, c) = (std::f64::consts::FRAC_PI_2 + 0.3).sin_cos();
    assert!((door.centre_m[0] - (c * dx + s * dy)).abs() < 1e-6, "{door:?}");
    assert!((door.centre_m[1] - (-s * dx + c * dy)).abs() < 1e-6, "{door:?}");
    assert!((door.angle_rad + 0.3).abs() < 1e-9, "{door:?}");
    // past the doorway leg (the turn into the corridor) there is none
    while nav.progress().leg < 1 {
        nav.step(&none, BodyVelocity::new(0.2, 0.0), 0.1);
    }
    assert_eq!(nav.doorway(), None);
    // nor where the map gives no opening
    let plain = TopoMap::parse(&flownav::sim::OFFICE_MAP_TOML.replace(", width_m = 0.9, door_at_m = 2.0", ""), "plain")
        .unwrap();
    assert_eq!(mission(&plain, "R9:D2").doorway(), None);
}

#[test]
fn a_doorway_leg_aims_onto_the_doors_axis() {
    use std::f64::consts::FRAC_PI_2;
    let plain = TopoMap::parse(&flownav::sim::OFFICE_MAP_TOML.replace(", width_m = 0.9, door_at_m = 2.0", ""), "plain")
        .unwrap();
    let none = Perception::default();
    // in R9, 0.5 m east of the door's axis (right of it), facing north again
    let aim = |map: &TopoMap| {
        let mut nav = mission(map, "R9:D2");
        nav.step(&none, BodyVelocity::new(0.0, -FRAC_PI_2), 1.0);
        nav.step(&none, BodyVelocity::new(0.5, 0.0), 1.0);
        nav.step(&none, BodyVelocity::new(0.0, FRAC_PI_2), 1.0);
        let goal = nav.step(&none, BodyVelocity::ZERO, 0.01);
        assert_eq!(nav.progress().leg, 0, "still leaving the room");
        goal.angle_rad
    };
    // with the opening: back onto the axis over 0.6 m, to meet the opening square on
    let a = aim(&office());
    assert!((a - 0.5f64.atan2(0.6)).abs() < 0.01, "{a}");
    // without: the corridor's cross-track pull over 1.5 m
    let a = aim(&plain);
    assert!((a - 0.5f64.atan2(1.5)).abs() < 0.01, "{a}");
}

/// R9:D2 with scripted odometry: out of R9 onto the corridor's centre line, a swerve 0.5 m
/// south, the corridor leg run out there, and the turn to face D2; returns at the last leg.
fn swerved_to_the_last_leg(params: PafsisParams) -> Pafsis {
    use std::f64::consts::{FRAC_PI_2, PI};
    let mut nav = Pafsis::new(office(), "R9:D2".parse::<Mission>().unwrap(), params).unwrap();
    let none = Perception::default();
    while nav.progress().leg < 2 {
        nav.step(&none, BodyVelocity::new(0.2, 0.0), 0.1);
    }
    while nav.progress().leg < 3 {
        nav.step(&none, BodyVelocity::new(0.0, 0.5), 0.02);
    }
    // face south, drive 0.5 m, face west again (exactly: the turn leg ends within its tolerance)
    let turn_to = |nav: &mut Pafsis, heading: f64| {
        let by = (heading - nav.progress().heading_rad + PI).rem_euclid(2.0 * PI) - PI;
        nav.step(&none, BodyVelocity::new(0.0, by / 0.5), 0.5);
    };
    turn_to(&mut nav, -FRAC_PI_2);
    nav.step(&none, BodyVelocity::new(0.5, 0.0), 1.0);
    turn_to(&mut nav, PI);
    while nav.progress().leg < 4 {
        nav.step(&none, BodyVelocity::new(0.3, 0.0), 0.1);
    }
    while nav.progress().leg < 5 {
        nav.step(&none, BodyVelocity::new(0.0, -0.5), 0.02);
    }
    turn_to(&mut nav, FRAC_PI_2);
    nav
}

#[test]
fn a_leg_to_a_place_starts_from_where_the_robot_already_is_along_it() {
    // the last leg goes 0.5 m north from the centre line to D2 (y = 0.5); from 0.5 m south of
    // the line it is 1 m long, so it starts 0.5 m before its start
    let mut nav = swerved_to_the_last_leg(PafsisParams::default());
    let [x, y] = nav.position_m().unwrap();
    assert!((x - 9.0).abs() < 0.05 && (y + 0.5).abs() < 0.03, "({x:.2}, {y:.2})");
    let along = nav.progress().along_m;
    assert!((along + 0.5).abs() < 0.03, "{along}");
    while nav.status() == GoalStatus::Active {
        nav.step(&Perception::default(), BodyVelocity::new(0.1, 0.0), 0.1);
    }
    let [_, y] = nav.position_m().unwrap();
    assert!((y - 0.5).abs() < 0.03, "arrived at y = {y:.2}, D2 is at 0.5");
    // without dead reckoning in the map frame, a leg is its length from wherever it starts
    let blind = swerved_to_the_last_leg(PafsisParams { cross_track_odometry: false, ..PafsisParams::default() });
    assert_eq!(blind.progress().leg, 5);
    assert_eq!(blind.progress().along_m, 0.0);
}

/// The office mission R9 → D2 driven 2 m into its corridor leg (D3 is expected 6 m along it),
/// its events taken.
fn two_metres_into_the_corridor() -> Pafsis {
    let map = office();
    let mut nav = mission(&map, "R9:D2");
    let none = Perception::default();
    let forward = BodyVelocity::new(0.2, 0.0);
    while nav.progress().leg < 2 {
        nav.step(&none, forward, 0.1);
    }
    while nav.progress().leg < 3 {
        nav.step(&none, BodyVelocity::new(0.0, 0.5), 0.02);
    }
    // 2 m along the corridor leg; D3 is expected 6 m along it
    for _ in 0..100 {
        nav.step(&none, forward, 0.1);
    }
    nav.take_events();
    nav
}

#[test]
fn doors_seen_obliquely_do_not_relocalise() {
    let mut nav = two_metres_into_the_corridor();
    let none = Perception::default();
    let door = Perception {
        tpo: Tpo { shape: TpoShape::Door, confidence: 0.9, distance_m: Some(3.7) },
        ..Perception::default()
    };
    let turn = |nav: &mut Pafsis, omega: f64| {
        for _ in 0..10 {
            nav.step(&none, BodyVelocity::new(0.0, omega), 0.1);
        }
    };
    // swerving 0.3 rad off the corridor: the 3.7 m is the range to the side wall, not to D3
    turn(&mut nav, 0.3);
    for _ in 0..5 {
        nav.step(&door, BodyVelocity::ZERO, 0.1);
    }
    let events = nav.take_events();
    assert!(!events.iter().any(|e| matches!(e, PafsisEvent::DoorMatched { .. })), "{events:#?}");
    assert!((nav.progress().along_m - 2.0).abs() < 0.01, "progress untouched: {}", nav.progress().along_m);
    // back on the corridor's axis the same sighting matches D3 and moves the progress 0.3 m on
    turn(&mut nav, -0.3);
    for _ in 0..5 {
        nav.step(&door, BodyVelocity::ZERO, 0.1);
    }
    let events = nav.take_events();
    let matched = events.iter().find_map(|e| match e {
        PafsisEvent::DoorMatched { door, correction_m, .. } => Some((door.clone(), *correction_m)),
        _ => None,
    });
    let (name, correction) = matched.expect("D3 matched");
    assert_eq!(name.as_deref(), Some("D3"));
    assert!((correction - 0.3).abs() < 0.01, "{correction}");
}

/// A door named ahead at ranges that jump from frame to frame (a plane fitted across an open
/// corridor) does not move the progress; the same door at ranges that agree does, by their median.
#[test]
fn a_door_ahead_relocalises_only_when_its_frames_agree() {
    let mut nav = two_metres_into_the_corridor();
    let before = nav.progress().along_m;
    let door = |d: f64| Perception {
        tpo: Tpo { shape: TpoShape::Door, confidence: 0.9, distance_m: Some(d) },
        ..Perception::default()
    };
    // no three frames in a row within 0.35 m of each other (and no jump up of a new door)
    for d in [4.5, 4.0, 3.4, 3.8, 3.3, 3.7, 3.25] {
        nav.step(&door(d), BodyVelocity::ZERO, 0.1);
    }
    let events = nav.take_events();
    assert!(!events.iter().any(|e| matches!(e, PafsisEvent::DoorMatched { .. })), "{events:#?}");
    assert_eq!(nav.progress().along_m, before, "progress untouched");
    // the older frames drop out of the window until the last three agree within the gate: D3
    // placed by their median, 3.7 m ahead (neither the first, the last nor the mean)
    for d in [3.6, 3.7, 3.85] {
        nav.step(&door(d), BodyVelocity::ZERO, 0.1);
    }
    let events = nav.take_events();
    let matched = events.iter().find_map(|e| match e {
        PafsisEvent::DoorMatched { door, correction_m, .. } => Some((door.clone(), *correction_m)),
        _ => None,
    });
    let (name, correction) = matched.expect("D3 matched");
    assert_eq!(name.as_deref(), Some("D3"));
    assert!((correction - (6.0 - (before + 3.7))).abs() < 1e-9, "{correction}");
    assert!((nav.progress().along_m - 2.3).abs() < 0.01, "{}", nav.progress().along_m);
}

mod mofis {
    use super::*;
    use flownav::control::ControlLimits;
    use flownav::fuzzy::FuzzySystem;
    use flownav::mofis::{Fusion, MofisError, MofisParams, load_default};
    use flownav::pafsis::Goal;
    use flownav::perception::Obstacle;

    fn mofis() -> Fusion {
        load_default(concat!(env!("CARGO_MANIFEST_DIR"), "/rules/mofis"), ControlLimits::default()).unwrap()
    }

    fn obstacle(distance: f64, bearing: f64) -> Perception {
        Perception {
            obstacle: Obstacle {
                present: true,
                distance_m: Some(distance),
                bearing_rad: Some(bearing),
                cell: Some([4, 3]),
            },
            ..Perception::default()
        }
    }

    fn goal(velocity: f64, angle_rad: f64) -> Goal {
        Goal { velocity, angle_rad, status: GoalStatus::Active }
    }

    /// A long `dt` so that the acceleration limits do not hide the fused command.
    const SETTLED: f64 = 10.0;

    #[test]
    fn obstacle_ahead_slows_and_turns_away() {
        for (bearing, turn_sign) in [(0.1, -1.0), (-0.1, 1.0), (0.25, -1.0), (-0.25, 1.0)] {
            let mut m = mofis();
            let out = m.step(&obstacle(0.5, bearing), &goal(0.35, 0.0), SETTLED).unwrap();
            assert!(out.setpoint.v < 0.1 * 0.35, "bearing {bearing}: v {}", out.setpoint.v);
            assert!(out.setpoint.omega * turn_sign > 0.5, "bearing {bearing}: omega {}", out.setpoint.omega);
            assert!(out.weight > 0.7, "avoidance dominates: {}", out.weight);
        }
    }

    #[test]
    fn obstacles_on_both_sides_are_avoided_together() {
        let o = |distance, bearing| Obstacle {
            present: true,
            distance_m: Some(distance),
            bearing_rad: Some(bearing),
            cell: None,
        };
        // the nearest alone, 0.8 m at 0.3 rad left: a firm turn right
        let mut m = mofis();
        let alone = m.step_sides(&obstacle(0.8, 0.3), None, None, &goal(0.35, 0.0), SETTLED).unwrap();
        assert!(alone.setpoint.omega < -0.3, "{alone:?}");
        // the same on both sides: the turns cancel, the robot goes down the middle, slowed
        let mut m = mofis();
        let both = m.step_sides(&obstacle(0.8, 0.3), Some(&o(0.8, -0.3)), None, &goal(0.35, 0.0), SETTLED).unwrap();
        assert!(both.setpoint.omega.abs() < 1e-9, "{both:?}");
        assert!(both.avoidance.speed <= alone.avoidance.speed + 1e-12 && both.setpoint.v < 0.35 * 0.5, "{both:?}");
        assert!((both.weight - alone.weight).abs() < 1e-12, "{both:?}");
        // a farther one on the right tempers the turn away from the near one without flipping it
        let mut m = mofis();
        let far = m.step_sides(&obstacle(0.8, 0.3), Some(&o(1.4, -0.25)), None, &goal(0.35, 0.0), SETTLED).unwrap();
        assert!(far.setpoint.omega < -1e-3 && far.setpoint.omega > alone.setpoint.omega, "{far:?} vs {alone:?}");
        // swapping which one is called the nearer changes nothing
        let mut m = mofis();
        let swapped = m.step_sides(&obstacle(1.4, -0.25), Some(&o(0.8, 0.3)), None, &goal(0.35, 0.0), SETTLED).unwrap();
        assert!((swapped.setpoint.omega - far.setpoint.omega).abs() < 1e-12, "{swapped:?} vs {far:?}");
    }

    #[test]
    fn dead_ahead_obstacle_is_passed_on_the_goal_side() {
        for goal_angle in [-0.3, 0.3] {
            let mut m = mofis();
            let out = m.step(&obstacle(0.6, 0.0), &goal(0.35, goal_angle), SETTLED).unwrap();
            assert!(out.setpoint.omega * goal_angle > 0.0, "goal {goal_angle}: omega {}", out.setpoint.omega);
            assert!(out.setpoint.v < 0.1);
        }
    }

    #[test]
    fn the_footprint_guard_bends_an_arc_off_what_lingers_beside_the_robot() {
        // the max turn rate is 1 rad/s, so the guard's candidates are ±0.1, ±0.2, ±0.35, ...
        let max_turn = ControlLimits::default().max_turn_rate;
        let clear = |_: f64, reach: f64, _: bool| reach;
        let straight = goal(0.35, 0.0);
        // the goal straight ahead, nothing lingering: the guard changes nothing
        let mut m = mofis();
        let free = m.step_guarded(&Perception::default(), None, None, &straight, SETTLED, Some(&clear)).unwrap();
        assert_eq!(free.fused, BodyVelocity { v: 0.35, omega: 0.0 }, "{free:?}");
        // something lingers ahead on the left: every arc that does not turn right by at least
        // 0.3 rad/s is blocked 5 cm out; the guard takes the nearest clear one, at full speed
        let left_blocked = |curvature: f64, reach: f64, _: bool| if curvature * 0.35 <= -0.3 { reach } else { 0.05 };
        let mut m = mofis();
        let bent = m.step_guarded(&Perception::default(), None, None, &straight, SETTLED, Some(&left_blocked)).unwrap();
        assert!((bent.fused.omega + 0.35 * max_turn).abs() < 1e-12, "{bent:?}");
        assert_eq!(bent.fused.v, 0.35, "a bend is enough, so it does not slow: {bent:?}");
        assert_eq!(bent.setpoint, bent.fused, "the limiter passes a settled command");
        // the reach it asks for is the horizon's travel plus the distance to stop:
        // 0.35 · 1.0 + 0.35² / (2 · 0.8)
        let asked = std::cell::Cell::new(0.0);
        let record = |_: f64, reach: f64, _: bool| {
            asked.set(reach);
            reach
        };
        mofis().step_guarded(&Perception::default(), None, None, &straight, SETTLED, Some(&record)).unwrap();
        assert!((asked.get() - (0.35 + 0.35 * 0.35 / 1.6)).abs() < 1e-12, "{}", asked.get());
        // it bends by at most guard_max_bend (0.5 rad/s): the arcs are clear only from a
        // curvature of 0.6 / 0.35 right on, out of the bend's reach at full speed, and a guard
        // that only bends passes the command unchanged
        let far_right = |curvature: f64, reach: f64, _: bool| if curvature * 0.35 <= -0.6 { reach } else { 0.05 };
        let bend_only = MofisParams { guard_slow: false, guard_brake: false, ..MofisParams::default() };
        let bend = || Fusion::load(bend_only.clone(), ControlLimits::default()).unwrap();
        let mut m = bend();
        let out = m.step_guarded(&Perception::default(), None, None, &straight, SETTLED, Some(&far_right)).unwrap();
        assert_eq!(out.fused, free.fused, "{out:?}");
        // with guard_slow, at 0.7 of the speed the same 0.5 rad/s turns tighter
        // (0.5 / 0.245 > 0.6 / 0.35), and that is the fastest clear arc (0.35 rad/s at
        // 0.245 m/s is not)
        let slower = MofisParams { guard_slow: true, ..bend_only.clone() };
        let mut m = Fusion::load(slower.clone(), ControlLimits::default()).unwrap();
        let slow = m.step_guarded(&Perception::default(), None, None, &straight, SETTLED, Some(&far_right)).unwrap();
        assert!((slow.fused.v - 0.7 * 0.35).abs() < 1e-12, "{slow:?}");
        assert!((slow.fused.omega + 0.5 * max_turn).abs() < 1e-12, "{slow:?}");
        // blocked whichever way and however slow, 5 cm out, by what is beside (out of view):
        // unchanged by a guard that only bends and with guard_slow alone; with guard_brake (the
        // default) it brakes to the speed that stops in 5 cm, √(2 · 0.8 · 0.05) = 0.283 m/s, on
        // the command's own arc (all equally free)
        let beside = |_: f64, _: f64, _: bool| 0.05;
        let mut m = bend();
        let out = m.step_guarded(&Perception::default(), None, None, &straight, SETTLED, Some(&beside)).unwrap();
        assert_eq!(out.fused, free.fused, "{out:?}");
        let mut m = Fusion::load(slower.clone(), ControlLimits::default()).unwrap();
        let out = m.step_guarded(&Perception::default(), None, None, &straight, SETTLED, Some(&beside)).unwrap();
        assert_eq!(out.fused, free.fused, "{out:?}");
        let braking = MofisParams { guard_brake: true, ..slower };
        assert_eq!(braking, MofisParams::default());
        let brake = mofis;
        let out = brake().step_guarded(&Perception::default(), None, None, &straight, SETTLED, Some(&beside)).unwrap();
        assert!((out.fused.v - (2.0f64 * 0.8 * 0.05).sqrt()).abs() < 1e-12, "{out:?}");
        assert_eq!(out.fused.omega, 0.0, "{out:?}");
        // nothing free at all beside: it stops, and still turns as it was told
        let touching = |_: f64, _: f64, _: bool| 0.0;
        let out = brake()
            .step_guarded(&Perception::default(), None, None, &goal(0.35, 0.1), SETTLED, Some(&touching))
            .unwrap();
        assert_eq!(out.fused.v, 0.0, "{out:?}");
        assert!((out.fused.omega - 1.5 * 0.1).abs() < 1e-12, "{out:?}");
        // the same cells in view (the out-of-view query finds the arc clear): unchanged, what
        // is ahead in view is the stopping gate's
        let in_view = |_: f64, reach: f64, aside: bool| if aside { reach } else { 0.0 };
        let out = brake().step_guarded(&Perception::default(), None, None, &straight, SETTLED, Some(&in_view)).unwrap();
        assert_eq!(out.fused, free.fused, "{out:?}");
        // turning on the spot and backing off are never checked
        let never = |_: f64, _: f64, _: bool| -> f64 { panic!("a turn on the spot has no arc to check") };
        let mut m = mofis();
        let spot = m.step_guarded(&Perception::default(), None, None, &goal(0.0, 0.5), SETTLED, Some(&never)).unwrap();
        assert!(spot.fused.v == 0.0 && spot.fused.omega > 0.0, "{spot:?}");
        let back = m.step_guarded(&Perception::default(), None, None, &goal(-0.1, 0.0), SETTLED, Some(&never)).unwrap();
        assert!(back.fused.v < 0.0, "{back:?}");
        // off (guard_evidence 0): never asked
        let params = MofisParams { guard_evidence: 0.0, ..MofisParams::default() };
        let mut off = Fusion::load(params, ControlLimits::default()).unwrap();
        let out = off.step_guarded(&Perception::default(), None, None, &straight, SETTLED, Some(&never)).unwrap();
        assert_eq!(out.fused, free.fused);
    }

    #[test]
    fn the_stopping_gate_caps_the_speed_whatever_the_rules_say() {
        use flownav::mofis::{Ahead, stop_speed};
        // √(2 · 0.8 · 0.1) = 0.4 m/s; nothing free: 0
        assert!((stop_speed(0.1, 0.8) - 0.4).abs() < 1e-12);
        assert_eq!(stop_speed(-0.05, 0.8), 0.0);
        // nothing seen, the goal dead ahead at 0.35 m/s: the gate alone slows the robot
        let mut m = mofis();
        let gate = |v| Some(Ahead { front_m: 5.0, stop_speed_mps: v });
        let out = m.step_sides(&Perception::default(), None, gate(0.2), &goal(0.35, 0.0), SETTLED).unwrap();
        assert!((out.setpoint.v - 0.2).abs() < 1e-9, "{out:?}");
        let out = m.step_sides(&Perception::default(), None, gate(0.0), &goal(0.35, 0.1), SETTLED).unwrap();
        assert_eq!(out.setpoint.v, 0.0, "{out:?}");
        assert!((out.setpoint.omega - 1.5 * 0.1).abs() < 1e-9, "still turns: {out:?}");
        // a gate above the goal speed changes nothing
        let out = m.step_sides(&Perception::default(), None, gate(1.0), &goal(0.35, 0.0), SETTLED).unwrap();
        assert!((out.setpoint.v - 0.35).abs() < 1e-9, "{out:?}");
    }

    #[test]
    fn no_obstacle_follows_the_goal() {
        let mut m = mofis();
        // (0.15 rad: within the look-before-driving band, so the goal's speed along the heading)
        let out = m.step(&Perception::default(), &goal(0.35, 0.15), SETTLED).unwrap();
        assert_eq!(out.avoidance.speed, 1.0);
        assert_eq!(out.weight, 0.0);
        assert!((out.setpoint.v - 0.35 * 0.15f64.cos()).abs() < 1e-9, "{:?}", out.setpoint);
        assert!((out.setpoint.omega - 1.5 * 0.15).abs() < 1e-9, "{:?}", out.setpoint);
        // A far obstacle aside changes nothing either.
        let out = m.step(&obstacle(4.0, 0.5), &goal(0.35, -0.2), SETTLED).unwrap();
        assert!(
            (out.setpoint.omega + 0.3).abs() < 1e-9 && (out.setpoint.v - 0.35 * 0.2f64.cos()).abs() < 1e-9,
            "{out:?}"
        );
    }

    #[test]
    fn wall_ahead_slows_but_lets_the_goal_turn() {
        let mut m = mofis();
        let p = Perception {
            tpo: Tpo { shape: TpoShape::Wall, confidence: 0.9, distance_m: Some(0.6) },
            ..Perception::default()
        };
        let out = m.step(&p, &goal(0.35, 1.0), SETTLED).unwrap();
        assert!(out.setpoint.v < 0.1, "{out:?}");
        assert!((out.setpoint.omega - 1.0).abs() < 1e-9, "turn rate clamped to the limit: {out:?}");
    }

    #[test]
    fn setpoints_obey_the_limits() {
        let mut m = mofis();
        // From rest, 0.1 s later: at most max_linear_accel · dt and max_angular_accel · dt.
        let out = m.step(&Perception::default(), &goal(5.0, 0.4), 0.1).unwrap();
        assert!((out.setpoint.v - 0.05).abs() < 1e-12 && (out.setpoint.omega - 0.15).abs() < 1e-12, "{out:?}");
        for _ in 0..100 {
            let out = m.step(&Perception::default(), &goal(5.0, 3.0), 0.1).unwrap();
            assert!(out.setpoint.v <= 0.5 && out.setpoint.omega <= 1.0);
        }
        let out = m.step(&Perception::default(), &goal(f64::NAN, 0.0), 0.1).unwrap();
        assert_eq!(out.setpoint, BodyVelocity::ZERO, "NaN goal: stop at once");
        m.step(&Perception::default(), &goal(0.3, 0.0), SETTLED).unwrap();
        assert_eq!(m.fallback(), BodyVelocity::ZERO, "no perception: stop at once");
        let arrived = Goal { status: GoalStatus::Arrived, ..goal(0.3, 0.5) };
        let out = m.step(&Perception::default(), &arrived, SETTLED).unwrap();
        assert_eq!(out.setpoint, BodyVelocity::ZERO);
    }

    #[test]
    fn sharp_turns_slow_down_and_a_turn_beyond_the_view_is_made_on_the_spot() {
        // settled at each goal: what the speed converges to for a goal angle (default
        // blind_turn_start_rad 0.2, blind_turn_stop_rad 0.6, heading gain 1.5, max turn 1 rad/s)
        let settle = |angle: f64| {
            let mut m = mofis();
            let mut out = None;
            for _ in 0..50 {
                out = Some(m.step(&Perception::default(), &goal(0.3, angle), 0.1).unwrap());
            }
            out.unwrap().setpoint
        };
        let straight = settle(0.0);
        assert!((straight.v - 0.3).abs() < 1e-9, "{straight:?}");
        // 0.15 rad: a 0.225 rad/s turn, which the obstacle memory still measures in: the speed
        // along the heading, cos 0.15 of it
        assert!((settle(0.15).v - 0.3 * 0.15f64.cos()).abs() < 1e-9);
        // 0.3 rad: 0.45 rad/s ÷ gain is 0.3 rad off → (0.6 − 0.3)/(0.6 − 0.2) = 3/4 of that
        let s = settle(-0.3);
        assert!((s.v - 0.225 * 0.3f64.cos()).abs() < 1e-9 && (s.omega + 0.45).abs() < 1e-9, "{s:?}");
        // beyond 0.6 rad: on the spot, at the turn-rate limit
        let s = settle(0.8);
        assert!(s.v.abs() < 1e-12 && (s.omega - 1.0).abs() < 1e-9, "{s:?}");
    }

    #[test]
    fn a_goal_far_off_is_turned_to_on_the_spot_until_nearly_ahead() {
        use flownav::mofis::SpotTurn;
        const FRAME_S: f64 = 1.0 / 30.0;
        // blind_turn_start_rad 0.2, blind_turn_stop_rad 0.6
        let mut spot = SpotTurn::new(&MofisParams::default(), 1.0);
        assert_eq!(spot.apply(goal(0.3, 0.5), FRAME_S, || true), goal(0.3, 0.5), "0.5 rad off: driving");
        assert_eq!(spot.apply(goal(0.3, -0.7), FRAME_S, || true), goal(0.0, -0.7), "0.7 rad off: on the spot");
        // the turn lasts until the goal is within 0.2 rad, where the same goal was driven before
        for angle in [-0.5, -0.3, -0.21] {
            assert_eq!(spot.apply(goal(0.3, angle), FRAME_S, || true), goal(0.0, angle), "{angle}");
        }
        assert_eq!(spot.apply(goal(0.3, -0.15), FRAME_S, || true), goal(0.3, -0.15));
        assert!(!spot.turning());
        assert_eq!(spot.apply(goal(0.3, 0.5), FRAME_S, || true), goal(0.3, 0.5), "a new turn starts only at 0.6 rad");
        // reversing (the stall recovery) and a finished mission pass unchanged and end the turn
        spot.apply(goal(0.3, 1.0), FRAME_S, || true);
        assert_eq!(spot.apply(goal(-0.1, 1.0), FRAME_S, || true), goal(-0.1, 1.0));
        assert!(!spot.turning());
        let done = Goal { status: GoalStatus::Arrived, ..goal(0.3, 1.0) };
        assert_eq!(spot.apply(done, FRAME_S, || true), done);
        // toward a blocked way no turn starts (it would undo the avoidance turn away from it);
        // a turn under way goes on, blocked or not
        assert_eq!(spot.apply(goal(0.3, 0.9), FRAME_S, || false), goal(0.3, 0.9), "blocked: no turn on the spot");
        assert!(!spot.turning());
        assert_eq!(spot.apply(goal(0.3, 0.9), FRAME_S, || true), goal(0.0, 0.9));
        assert_eq!(spot.apply(goal(0.3, 0.8), FRAME_S, || false), goal(0.0, 0.8), "under way: goes on");

        // through MOFIS: something 1.4 m away, 0.25 rad left, that avoidance would turn right
        // from; the turn on the spot has the goal's turn alone
        let mut m = mofis();
        let out = m
            .step(
                &obstacle(1.4, 0.25),
                &SpotTurn::new(&MofisParams::default(), 1.0).apply(goal(0.3, 0.7), FRAME_S, || true),
                SETTLED,
            )
            .unwrap();
        assert_eq!(out.weight, 0.0);
        assert!(out.setpoint.v == 0.0 && (out.setpoint.omega - 1.0).abs() < 1e-9, "{out:?}");
    }

    #[test]
    fn bad_perception_values_do_not_panic() {
        let mut m = mofis();
        let mut p = obstacle(f64::NAN, f64::INFINITY);
        p.tpo = Tpo { shape: TpoShape::Corner, confidence: f64::NAN, distance_m: Some(f64::NAN) };
        let out = m.step(&p, &goal(0.3, 0.0), SETTLED).unwrap();
        assert!(out.setpoint.v.is_finite() && out.setpoint.omega.is_finite());
        assert!(out.setpoint.v < 0.3, "an obstacle of unknown distance slows the robot: {out:?}");
    }

    #[test]
    fn rule_base_without_the_expected_variables_is_refused() {
        let text = r#"
            [[input]]
            name = "obstacle_distance"
            range = [0, 5]
            terms = { near = { tri = [0, 0, 5] } }
            [[input]]
            name = "obstacle_offset"
            range = [0, 1]
            terms = { ahead = { tri = [0, 0, 1] } }
            [[output]]
            name = "w"
            range = [0, 1]
            terms = { low = { tri = [0, 0, 1] } }
            [[rule]]
            if = "obstacle_distance is near"
            then = "w is low"
        "#;
        let fusion = FuzzySystem::from_toml_str(text, "myfusion.toml").unwrap();
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/rules/mofis/avoidance.toml");
        let avoidance = FuzzySystem::from_file(dir).unwrap();
        let e = Fusion::new(MofisParams::default(), ControlLimits::default(), avoidance, fusion).unwrap_err();
        assert!(matches!(e, MofisError::Missing { name: "weight", .. }), "{e}");
        assert!(e.to_string().contains("myfusion.toml") && e.to_string().contains("'weight'"), "{e}");
    }

    /// PAFSIS + MOFIS on the office mission with a person standing in the corridor: the robot
    /// swerves around it and still stops in front of D2.
    #[test]
    fn office_mission_around_an_obstacle() {
        for y in [-0.3, -0.15, 0.0, 0.15, 0.3] {
            around_a_person_at(y);
        }
    }

    fn around_a_person_at(person_y: f64) {
        let map = office();
        let mut nav = mission(&map, "R9:D2");
        let mut m = mofis();
        let mut walk = Walk::new(21.0, -3.0, 90.0);
        let person = (12.0, person_y, 0.25); // x, y, radius
        let dt = 0.05;
        let (mut odo, mut min_clearance, mut arrived) = (BodyVelocity::ZERO, f64::INFINITY, false);
        for _ in 0..(150.0 / dt) as usize {
            let mut p = walk.perceive();
            let (dx, dy) = (person.0 - walk.x, person.1 - walk.y);
            let range = (dx * dx + dy * dy).sqrt() - person.2;
            let bearing = flownav::pafsis::map::wrap_angle(dy.atan2(dx) - walk.heading);
            min_clearance = min_clearance.min(range);
            if range < 5.0 && bearing.abs() < 0.8 {
                p.obstacle =
                    Obstacle { present: true, distance_m: Some(range), bearing_rad: Some(bearing), cell: None };
            }
            let g = nav.step(&p, odo, dt);
            if g.status == GoalStatus::Arrived {
                arrived = true;
                break;
            }
            let sp = m.step(&p, &g, dt).unwrap().setpoint;
            walk.heading += sp.omega * dt;
            walk.x += sp.v * dt * walk.heading.cos();
            walk.y += sp.v * dt * walk.heading.sin();
            // The corridor walls are at y = ±1 (robot radius 0.2 m); beyond ±0.8 only in the
            // doorways of D9 (south, x = 21) and D2 (north, x = 9).
            let clear_of_walls =
                (walk.y < 0.8 || (walk.x - 9.0).abs() < 0.4) && (walk.y > -0.8 || (walk.x - 21.0).abs() < 0.4);
            assert!(clear_of_walls, "person at y {person_y}: hit a corridor wall at ({:.2}, {:.2})", walk.x, walk.y);
            odo = sp;
        }
        assert!(arrived, "stuck at ({:.2}, {:.2})", walk.x, walk.y);
        assert!(min_clearance > 0.3, "person at y {person_y}: came within {min_clearance:.2} m of the person");
        assert!((walk.x - 9.0).abs() < 0.5, "stopped at x = {:.2}", walk.x);
    }
}
