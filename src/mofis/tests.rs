//! One MOFIS step: where the spot turn and the steering turn the robot.

use super::*;

fn mofis(planner: bool) -> Mofis {
    let params = MofisParams { planner, ..MofisParams::default() };
    Mofis::new(params, ControlLimits::default(), &Calibration::nominal_c310()).unwrap()
}

/// One step at a standstill with nothing seen, toward a goal that asks to drive `goal_rad` off
/// the heading, in `lane`.
fn step(m: &mut Mofis, goal_rad: f64, lane: Option<Lane>) -> MofisStep {
    step_to(m, Goal { velocity: 0.3, angle_rad: goal_rad, status: GoalStatus::Active }, lane)
}

/// One step at a standstill with nothing seen, toward `goal`, in `lane`.
fn step_to(m: &mut Mofis, goal: Goal, lane: Option<Lane>) -> MofisStep {
    let route = Route { lane, doorway: None, stop_ahead_m: None };
    let perception = Perception::default();
    let input = MofisInput {
        perception: &perception,
        points: &[],
        measured: true,
        odometry: BodyVelocity::ZERO,
        dt: 1.0 / 30.0,
        goal,
        route,
    };
    m.step(input).unwrap()
}

#[test]
fn a_goal_far_off_the_heading_with_a_free_path_is_turned_to_on_the_spot() {
    for planner in [false, true] {
        let mut m = mofis(planner);
        let out = step(&mut m, -0.9, None);
        assert_eq!(out.steered.velocity, 0.0, "planner {planner}: a turn on the spot");
        assert_eq!(out.steered.angle_rad, -0.9, "planner {planner}: toward the goal");
        assert_eq!(out.goal.velocity, 0.0);
        assert!(out.output.setpoint.v.abs() < 1e-9 && out.output.setpoint.omega < 0.0, "{:?}", out.output.setpoint);
    }
}

#[test]
fn with_the_planner_the_spot_turn_turns_where_the_way_leads_not_across_the_corridor() {
    // a 2 m corridor, the robot 0.4 m right of its centre line and heading along it; the goal
    // 0.9 rad to the right, across the right wall 0.6 m away. The goal's ray leaves the lane
    // within 0.3 m: the straight-ray steering's spot turn faces the wall, and the planner, turning
    // the robot back along the corridor, undid it: the two turned it back and forth on the spot
    let lane = Some(Lane { left_m: -0.4, angle_rad: 0.0, half_width_m: 1.0 });
    let mut m = mofis(false);
    let out = step(&mut m, -0.9, lane);
    assert_eq!((out.steered.velocity, out.steered.angle_rad), (0.0, -0.9), "without the planner: toward the wall");
    // with it: no turn on the spot; the robot drives on its way, inside the corridor
    let mut m = mofis(true);
    let out = step(&mut m, -0.9, lane);
    assert!(!m.spot_turn.turning());
    assert_eq!(out.goal.velocity, 0.3);
    let aim = out.steered.angle_rad;
    assert!(out.steered.velocity > 0.0 && (-0.6..0.0).contains(&aim), "{:?}", out.steered);
    // the aim keeps the footprint and the lane margin inside the corridor for a metre
    let (sin, cos) = aim.sin_cos();
    let edge = 1.0 - 0.18 - 0.1;
    assert!((1..=10).all(|k| (-0.4 + 0.1 * k as f64 * sin).abs() <= edge + 1e-9 && cos > 0.0), "{aim}");
}

#[test]
fn a_way_that_first_leads_away_from_a_goal_behind_is_driven() {
    // a wall of cells 0.5 m left of the robot from 0.5 m behind to 1 m ahead; the goal 1.9 rad
    // to the left, behind the wall. The way goes round the wall's front end: a goal that asks
    // to drive (PAFSIS's leg speed) is followed along it, forward; a turn (no speed) is turned
    // to on the spot, into the wall's side
    let wall: Vec<SurfacePoint> =
        (0..=15).map(|k| SurfacePoint { forward: -0.5 + 0.1 * k as f64, left: 0.5, up: 0.5, radial_px: 3.0 }).collect();
    let walled = || {
        let mut m = mofis(true);
        for _ in 0..3 {
            m.memory.update(BodyVelocity::ZERO, 0.1, &wall, true);
        }
        m
    };
    let out = step(&mut walled(), 1.9, None);
    assert!(out.steered.velocity > 0.0 && (-0.2..0.6).contains(&out.steered.angle_rad), "{:?}", out.steered);
    let mut m = walled();
    let out = step_to(&mut m, Goal { velocity: 0.0, angle_rad: 1.9, status: GoalStatus::Active }, None);
    assert_eq!((out.steered.velocity, out.steered.angle_rad), (0.0, 1.9));
    assert!(out.output.setpoint.omega > 0.0);
}
