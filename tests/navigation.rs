//! Navigation: the shipped office map, PAFSIS following a plan from scripted landmarks and
//! odometry, and MOFIS behaviour.

use flownav::pafsis::{GoalStatus, LegKind, Mission, Pafsis, PafsisEvent, PafsisParams, TopoMap};
use flownav::perception::{Perception, Tpo, TpoShape};
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
    path_m: f64,
}

const DOOR_X: [f64; 10] = [3.0, 5.0, 7.0, 9.0, 11.0, 13.0, 15.0, 17.0, 19.0, 21.0];

impl Walk {
    fn new(x: f64, y: f64, heading_deg: f64) -> Self {
        Self { x, y, heading: heading_deg.to_radians(), odo_scale: 1.0, landmarks: true, path_m: 0.0 }
    }

    fn perceive(&self) -> Perception {
        let mut p = Perception::default();
        let along_corridor = self.heading.sin().abs() < 0.2 && self.y.abs() < 1.0;
        if !self.landmarks || !along_corridor {
            return p;
        }
        let dir = self.heading.cos().signum();
        let door = DOOR_X.iter().map(|&dx| (dx - self.x) * dir).filter(|d| (1.0..=4.0).contains(d)).reduce(f64::min);
        let wall = if dir > 0.0 { 24.0 - self.x } else { self.x };
        p.tpo = match door {
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
        for _ in 0..(max_s / dt) as usize {
            let goal = nav.step(&self.perceive(), odo, dt);
            events.extend(nav.take_events());
            if goal.status != GoalStatus::Active {
                return (goal.status, events);
            }
            let omega = (1.5 * goal.angle_rad).clamp(-1.0, 1.0);
            self.heading += omega * dt;
            self.x += goal.velocity * dt * self.heading.cos();
            self.y += goal.velocity * dt * self.heading.sin();
            self.path_m += goal.velocity * dt;
            odo = BodyVelocity::new(goal.velocity * self.odo_scale, omega);
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
    assert_eq!(nav.plan().waypoints, ["R9", "D9", "D8", "D7", "D6", "D5", "D4", "D3", "D2"]);
    assert_eq!(nav.plan().length_m, 17.0);
    // Exit R9, turn right into the corridor (facing west), one merged corridor leg.
    let legs = nav.legs();
    assert_eq!(legs.len(), 3, "{legs:#?}");
    assert!(matches!(&legs[0].kind, LegKind::Doorway { door, .. } if door == "D9"));
    assert!(matches!(legs[1].kind, LegKind::Turn));
    assert!((legs[1].heading_rad.abs() - std::f64::consts::PI).abs() < 1e-9);
    assert_eq!(legs[2].to_string(), "follow the corridor 14.0 m passing 3 doors left, 3 right, stop at D2");
}

#[test]
fn office_mission_arrives_in_front_of_d2() {
    let map = office();
    let mut nav = mission(&map, "R9:D2");
    let mut walk = Walk::new(19.0, 3.0, -90.0);
    let (status, events) = walk.run(&mut nav, 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!((walk.x - 5.0).abs() < 0.3 && walk.y.abs() < 0.2, "stopped at ({:.2}, {:.2})", walk.x, walk.y);
    let matched = events.iter().filter(|e| matches!(e, PafsisEvent::DoorMatched { .. })).count();
    assert_eq!(matched, 7, "D8..D3 passed and D2 sighted: {events:#?}");
    assert!(!events.iter().any(|e| matches!(e, PafsisEvent::LandmarkMissed { .. })));
}

#[test]
fn door_sightings_correct_bad_odometry() {
    let map = office();
    // Odometry under-reports distance by 20%.
    let mut with = Walk { odo_scale: 0.8, ..Walk::new(19.0, 3.0, -90.0) };
    let (status, _) = with.run(&mut mission(&map, "R9:D2"), 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!((with.x - 5.0).abs() < 0.4, "with landmarks stopped at x = {:.2}", with.x);

    let mut without = Walk { odo_scale: 0.8, landmarks: false, ..Walk::new(19.0, 3.0, -90.0) };
    let (status, events) = without.run(&mut mission(&map, "R9:D2"), 120.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!(without.x < 2.0, "odometry alone overshoots D2 (x = {:.2})", without.x);
    let missed = events.iter().filter(|e| matches!(e, PafsisEvent::LandmarkMissed { .. })).count();
    assert_eq!(missed, 7, "every door reported missing");
}

#[test]
fn missing_end_wall_relocalises_and_stops() {
    let map = office();
    let mut nav = mission(&map, "D3:J1");
    let mut walk = Walk { landmarks: false, ..Walk::new(7.0, 0.0, 180.0) };
    let (status, events) = walk.run(&mut nav, 60.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!(events.iter().any(|e| matches!(e, PafsisEvent::Replanned { from, .. } if from == "J1")), "{events:#?}");
    // The end wall at x = 0 was never reported; the robot gave up after 150% of the 6 m leg.
    assert!((walk.path_m - 9.0).abs() < 0.3, "travelled {:.2} m", walk.path_m);

    let mut nav = mission(&map, "D3:J1");
    let mut walk = Walk::new(7.0, 0.0, 180.0);
    let (status, events) = walk.run(&mut nav, 60.0);
    assert_eq!(status, GoalStatus::Arrived);
    assert!(!events.iter().any(|e| matches!(e, PafsisEvent::Replanned { .. })));
    assert!((walk.x - 0.8).abs() < 0.1, "stops 0.8 m before the wall, at x = {:.2}", walk.x);
}
