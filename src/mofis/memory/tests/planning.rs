//! The planner: a way the footprint fits, inside the lane, short of what blocks it.

use super::*;

/// The default guard: confirmed cells with 0.3 of evidence, clusters of two or more.
fn counted() -> GuardCells {
    GuardCells { clearance_m: 0.04, min_evidence: 0.3, cluster: true, min_cells: 2 }
}

/// A box seen three times, `forward` m ahead across `left_from..=left_to` m, 0.1 m deep.
fn boxed(m: &mut ObstacleMemory, forward: f64, left_from: f64, left_to: f64) {
    let n = ((left_to - left_from) / 0.1).round() as usize;
    let seen: Vec<SurfacePoint> = (0..=n)
        .flat_map(|k| [pt(forward, left_from + 0.1 * k as f64), pt(forward + 0.1, left_from + 0.1 * k as f64)])
        .collect();
    for _ in 0..3 {
        step(m, STILL, 0.1, &seen);
    }
}

/// The least distance from the way's points to the occupied cells' centres, m.
fn clearance(m: &ObstacleMemory, way: &[[f64; 2]]) -> f64 {
    let cells = m.occupied();
    way.iter().flat_map(|w| cells.iter().map(move |c| (w[0] - c[0]).hypot(w[1] - c[1]))).fold(f64::INFINITY, f64::min)
}

#[test]
fn the_way_takes_the_gap_the_footprint_fits_not_the_nearer_one() {
    // a 2 m corridor, the robot on its centre line; a box 1.5 m ahead from 0.55 m right to
    // 0.25 m left of the line. Right of it 0.45 m to the wall: no room for the footprint
    // (0.36 m) and the lane margin; left of it 0.75 m: room. The straight rays take the
    // right gap, the shorter turn; the way goes left
    let mut m = memory();
    boxed(&mut m, 1.5, -0.55, 0.25);
    let lane = Lane { left_m: 0.0, angle_rad: 0.0, half_width_m: 1.0 };
    m.set_lane(Some(lane));
    let target = PlanTarget { bearing_rad: 0.0, distance_m: 3.0 };
    let way = m.plan_way(target, &counted()).cells;
    let end = *way.last().expect("a way");
    assert!(end[0] > 2.5 && end[1].abs() < 0.6, "the way passes the box: {end:?}");
    let beside = way.iter().find(|w| (1.4..=1.7).contains(&w[0])).expect("a point beside the box");
    assert!(beside[1] > 0.5, "left of the box: {way:?}");
    // it never brings the footprint and the guard's clearance onto a cell, nor leaves the lane
    let hard = 0.18 + 0.04 + 0.05;
    assert!(clearance(&m, &way) >= hard - 1e-9, "{}", clearance(&m, &way));
    assert!(way.iter().all(|w| w[1].abs() <= 1.0 - 0.18 - 0.1 + 1e-9), "{way:?}");
    let h = m.plan_heading(target, &counted()).unwrap();
    assert!(h > 0.0, "{h}");
}

#[test]
fn with_no_way_through_the_way_ends_short_of_what_blocks_it() {
    // the box fills the corridor: the way ends in front of it, the footprint clear of it
    let mut m = memory();
    boxed(&mut m, 1.5, -0.9, 0.9);
    m.set_lane(Some(Lane { left_m: 0.0, angle_rad: 0.0, half_width_m: 1.0 }));
    let way = m.plan_way(PlanTarget { bearing_rad: 0.0, distance_m: 3.0 }, &counted()).cells;
    let end = *way.last().expect("a way toward the box");
    assert!((1.0..=1.3).contains(&end[0]), "{end:?}");
    assert!(clearance(&m, &way) >= 0.18 + 0.04 + 0.05 - 1e-9);
}

#[test]
fn a_way_that_leads_no_nearer_the_target_has_no_heading() {
    // the box fills the corridor 0.6 m ahead: the footprint and its clearance fit 0.2 m
    // further at most, less than the progress a way must make to be followed
    let mut m = memory();
    boxed(&mut m, 0.6, -0.9, 0.9);
    m.set_lane(Some(Lane { left_m: 0.0, angle_rad: 0.0, half_width_m: 1.0 }));
    let target = PlanTarget { bearing_rad: 0.0, distance_m: 3.0 };
    let way = m.plan_way(target, &counted());
    let end = *way.cells.last().expect("a way toward the box");
    assert!(end[0] < 0.3, "{end:?}");
    assert_eq!((way.aim, m.plan_heading(target, &counted())), (None, None));
    // with the box 1.5 m ahead the way makes progress, and is followed
    let mut m = memory();
    boxed(&mut m, 1.5, -0.9, 0.9);
    m.set_lane(Some(Lane { left_m: 0.0, angle_rad: 0.0, half_width_m: 1.0 }));
    assert!(m.plan_heading(target, &counted()).is_some_and(|h| h.abs() < 0.1));
}

#[test]
fn a_robot_inside_the_clearance_still_finds_its_way_out() {
    // a box 0.2 m ahead, across the heading: every cell near the robot is blocked, and the
    // way still leaves, back and round
    let mut m = memory();
    boxed(&mut m, 0.3, -0.2, 0.2);
    let way = m.plan_way(PlanTarget { bearing_rad: 0.0, distance_m: 3.0 }, &counted()).cells;
    let end = *way.last().expect("a way");
    assert!(end[0] > 0.5, "past the box: {way:?}");
    // and an empty memory goes straight to the target
    let m = memory();
    let way = m.plan_way(PlanTarget { bearing_rad: 0.3, distance_m: 2.0 }, &counted()).cells;
    let end = *way.last().unwrap();
    assert!((end[0] - 2.0 * 0.3f64.cos()).abs() < 0.1 && (end[1] - 2.0 * 0.3f64.sin()).abs() < 0.1, "{end:?}");
    let h = m.plan_heading(PlanTarget { bearing_rad: 0.3, distance_m: 2.0 }, &counted()).unwrap();
    assert!((h - 0.3).abs() < 0.1, "{h}");
}

#[test]
fn the_way_keeps_off_what_the_guard_holds_and_off_the_doors_wall() {
    // a box beside the robot's path, faded below the occupied threshold (as out of view): the
    // straight rays no longer see it, the guard still counts it, and so does the way
    let mut m = memory();
    for (f, l) in [(0.5, 0.3), (0.6, 0.3), (0.7, 0.3), (0.5, 0.2), (0.6, 0.2), (0.7, 0.2)] {
        put(&mut m, f, l, 0.5, true);
    }
    assert!(m.occupied().is_empty(), "faded below occupied");
    let target = PlanTarget { bearing_rad: 0.2, distance_m: 3.0 };
    let way = m.plan_way(target, &counted()).cells;
    let cells: Vec<[f64; 2]> = m.cells_above(0.0).into_iter().map(|c| c.0).collect();
    let near = way
        .iter()
        .flat_map(|w| cells.iter().map(move |c| (w[0] - c[0]).hypot(w[1] - c[1])))
        .fold(f64::INFINITY, f64::min);
    assert!(near >= 0.18 + 0.04 + 0.05 - 1e-9, "{near} {way:?}");
    // a door 1 m ahead, 0.8 m wide, centred 0.3 m left: the way goes through the opening,
    // its footprint and the lane margin inside the jambs
    let mut m = memory();
    m.set_doorway(Some(Doorway { centre_m: [1.0, 0.3], angle_rad: 0.0, half_width_m: 0.4 }));
    let way = m.plan_way(PlanTarget { bearing_rad: 0.0, distance_m: 2.5 }, &counted()).cells;
    let at_door = way.iter().find(|w| (w[0] - 1.0).abs() < 0.05).expect("through the door");
    assert!((at_door[1] - 0.3).abs() <= 0.4 - 0.28 + 1e-9, "{at_door:?}");
    assert!(way.last().unwrap()[0] > 2.0, "{way:?}");
}
