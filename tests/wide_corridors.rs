//! Navigation in a corridor of varied widths: each stretch of a merged corridor leg keeps the
//! map's width, and a leg that ends facing a door ends where the wall seen ahead puts it, not
//! where dead reckoning does.

use flownav::pafsis::{GoalStatus, Mission, Pafsis, PafsisEvent, PafsisParams, TopoMap};
use flownav::perception::{Perception, Tpo, TpoShape};
use hal::BodyVelocity;

/// A corridor along y = 0: 1.8 m wide for x = 0..4, then a 3.5 m hall to x = 10. C0, C1 and C2
/// lie on the centre line at x = 0, 4 and 8; D2 0.5 m in front of a door in the hall's south
/// wall (y = −1.75), the door leading into room R2. With `door_edge` false the map lacks the
/// edge through the door, so nothing says a wall faces the robot at D2.
fn hall_map(door_edge: bool) -> TopoMap {
    let mut text = String::from(
        r#"
name = "test hall"
[[place]]
name = "C0"
kind = "junction"
position_m = [0.0, 0.0]
heading_deg = 0
[[place]]
name = "C1"
kind = "junction"
position_m = [4.0, 0.0]
[[place]]
name = "C2"
kind = "junction"
position_m = [8.0, 0.0]
[[place]]
name = "D2"
kind = "door"
position_m = [8.0, -1.25]
[[place]]
name = "R2"
kind = "room"
position_m = [8.0, -3.75]
[[edge]]
from = "C0"
to = "C1"
heading_deg = 0
actions = [{ do = "follow_corridor", length_m = 4.0, width_m = 1.8 }]
[[edge]]
from = "C1"
to = "C2"
heading_deg = 0
actions = [{ do = "follow_corridor", length_m = 4.0, width_m = 3.5 }]
[[edge]]
from = "C2"
to = "D2"
heading_deg = -90
actions = [{ do = "follow_corridor", length_m = 1.25 }]
"#,
    );
    if door_edge {
        text.push_str(
            r#"
[[edge]]
from = "D2"
to = "R2"
heading_deg = -90
actions = [{ do = "enter_room", door = "D2", length_m = 2.5, width_m = 0.8, door_at_m = 0.5 }]
"#,
        );
    }
    TopoMap::parse(&text, "test-hall.toml").expect("the test map parses")
}

fn nav(map: TopoMap, mission: &str) -> Pafsis {
    Pafsis::new(map, mission.parse::<Mission>().unwrap(), PafsisParams::default()).unwrap()
}

#[test]
fn a_merged_leg_keeps_each_stretchs_width() {
    let mut nav = nav(hall_map(true), "C0:C2");
    let none = Perception::default();
    let half_width = |nav: &Pafsis| nav.lane().expect("the corridor leg has a lane").half_width_m;
    assert!((half_width(&nav) - 0.9).abs() < 1e-12);
    // 3.2 m in: the narrow part, and within the map's tolerance of its end, still narrow
    for _ in 0..32 {
        nav.step(&none, BodyVelocity::new(1.0, 0.0), 0.1);
    }
    assert!((half_width(&nav) - 0.9).abs() < 1e-12);
    // 5 m in: the hall (before, a merged leg took the narrowest width throughout)
    for _ in 0..18 {
        nav.step(&none, BodyVelocity::new(1.0, 0.0), 0.1);
    }
    assert!((half_width(&nav) - 1.75).abs() < 1e-12, "{:?}", nav.lane());
}

/// A robot that drives C1 → D2 (east through the hall, a right turn at C2, the last leg to D2
/// facing the door's wall) truly `true_y` m off where PAFSIS believes it is across the
/// corridor (sideways drift dead reckoning cannot see), with perfect odometry and an ideal
/// steering. Facing south, OFFIS reports the wall ahead (the door's wall at y = −1.75) while it
/// is 1.5 m away or more, and nearer than that the room's far wall seen through the opening
/// (y = −5.2). Returns where the robot stops (true y), the final status and the events.
fn last_leg(map: TopoMap, true_y: f64) -> (f64, GoalStatus, Vec<PafsisEvent>) {
    let mut nav = nav(map, "C1:D2");
    let (mut y, mut heading) = (true_y, 0.0f64);
    let dt = 0.05;
    let mut odo = BodyVelocity::ZERO;
    let mut events = Vec::new();
    for _ in 0..4000 {
        let facing_south = (heading + std::f64::consts::FRAC_PI_2).abs() < 0.1;
        let wall = y + 1.75;
        let p = if facing_south {
            let d = if wall >= 1.5 { wall } else { y + 5.2 };
            Perception {
                tpo: Tpo { shape: TpoShape::Wall, confidence: 0.9, distance_m: Some(d) },
                ..Perception::default()
            }
        } else {
            Perception::default()
        };
        let goal = nav.step(&p, odo, dt);
        events.extend(nav.take_events());
        if goal.status != GoalStatus::Active {
            return (y, goal.status, events);
        }
        let omega = (2.0 * goal.angle_rad).clamp(-1.0, 1.0);
        let v = if goal.angle_rad.abs() < 0.2 { goal.velocity } else { 0.0 };
        odo = BodyVelocity::new(v, omega);
        heading += omega * dt;
        y += v * dt * heading.sin();
    }
    (y, nav.status(), events)
}

#[test]
fn the_wall_ahead_ends_a_leg_that_faces_a_door() {
    // 0.6 m north of where dead reckoning puts it (drift in the hall): the wall ahead places
    // the leg's end, and the room's far wall seen through the door does not pull it in
    for true_y in [0.6, 0.3, 0.0] {
        let (y, status, events) = last_leg(hall_map(true), true_y);
        assert_eq!(status, GoalStatus::Arrived);
        assert!((y + 1.25).abs() < 0.05, "started {true_y:+.1} m off: stopped at y = {y:.3}, D2 at −1.25");
        let matched: Vec<_> = events.iter().filter(|e| matches!(e, PafsisEvent::WallAheadMatched { .. })).collect();
        assert_eq!(matched.len(), 1, "{events:#?}");
        if let PafsisEvent::WallAheadMatched { correction_m, .. } = matched[0] {
            assert!((correction_m + true_y).abs() < 0.05, "moved the progress by {correction_m:.3} m");
        }
    }
    // 0.3 m south of where it believes, the robot turns in with the wall already nearer than
    // the fix looks (1.5 m): the leg's length ends it, 0.3 m past D2
    let (y, status, events) = last_leg(hall_map(true), -0.3);
    assert_eq!(status, GoalStatus::Arrived);
    assert!((y - (-0.3 - 1.25)).abs() < 0.05, "stopped at y = {y:.3}");
    assert!(!events.iter().any(|e| matches!(e, PafsisEvent::WallAheadMatched { .. })));
    // without the door in the map nothing faces the robot: the leg's length alone ends it,
    // 0.6 m off
    let (y, status, events) = last_leg(hall_map(false), 0.6);
    assert_eq!(status, GoalStatus::Arrived);
    assert!((y - (0.6 - 1.25)).abs() < 0.05, "stopped at y = {y:.3}");
    assert!(!events.iter().any(|e| matches!(e, PafsisEvent::WallAheadMatched { .. })));
}
