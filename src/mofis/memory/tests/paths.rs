//! The queries: threats, free paths, steering, the lane and the door.

use super::*;

/// The distance [`ObstacleMemory::threat_within`] reports for a cell `along`, `across` of
/// the path of [`memory`] (path 0.38 m, side band 0.3 m).
fn faded(along: f64, across: f64) -> f64 {
    let band = 0.3 * (1.0 - along / SIDE_REACH_M);
    along.hypot(across) - 0.18 + SIDE_FADE_M * (across.abs() - 0.38).max(0.0) / band
}

#[test]
fn beside_the_path_counts_farther_away_and_walls_aside_are_ignored() {
    // a corridor wall 1 m to the left, a box 0.45 m right of the heading at 0.45 m (outside
    // the path's 0.18 + 0.2 m, inside the side band), and a box in the path at 1.55 m
    let frame = [pt(0.5, 1.0), pt(1.0, 1.0), pt(0.4, -0.45), pt(1.5, 0.1)];
    let run = |points: &[SurfacePoint]| {
        let mut m = memory();
        for _ in 0..3 {
            step(&mut m, STILL, 0.1, points);
        }
        m.threat()
    };
    // the box beside counts 0.07 m beyond the path, 3 m × 0.07 / 0.19 farther than it is, so
    // the box in the path, farther away but in the way, is the threat
    let beside = faded(0.45, -0.45);
    assert!(beside > 1.55f64.hypot(0.15) - 0.18 && beside < 2.0, "{beside}");
    let o = run(&frame);
    assert!((o.bearing_rad.unwrap() - 0.15f64.atan2(1.55)).abs() < 1e-9, "the in-path box: {o:?}");
    assert!((o.distance_m.unwrap() - (1.55f64.hypot(0.15) - 0.18)).abs() < 1e-9, "{o:?}");
    // without the in-path box: the one beside the path, to the right, at its faded distance
    let o = run(&frame[..3]);
    assert!(o.bearing_rad.unwrap() < 0.0 && (o.distance_m.unwrap() - beside).abs() < 1e-9, "{o:?}");
    // the wall alone is no threat
    assert!(!run(&frame[..2]).present);
    // nor is the box beside the path when it is 1.2 m ahead, where the band has narrowed to
    // nothing
    assert!(!run(&[pt(1.2, -0.45)]).present);
}

#[test]
fn each_side_has_its_own_threat() {
    let mut m = memory();
    // a box 0.9 m ahead, 0.25 m left, and another 1.0 m ahead, 0.3 m right
    for _ in 0..2 {
        step(&mut m, STILL, 0.1, &[pt(0.9, 0.25), pt(1.0, -0.3)]);
    }
    let [left, right] = m.threat_sides(f64::INFINITY);
    let (l, r) = (left.bearing_rad.unwrap(), right.bearing_rad.unwrap());
    assert!(l > 0.2 && r < -0.2, "{left:?} {right:?}");
    assert!(left.distance_m.unwrap() < right.distance_m.unwrap());
    assert_eq!(m.threat(), left, "the nearer of the two");
    // with the left one gone only the right one is left, on its side
    let mut m = memory();
    for _ in 0..2 {
        step(&mut m, STILL, 0.1, &[pt(1.0, -0.3)]);
    }
    let [left, right] = m.threat_sides(f64::INFINITY);
    assert!(!left.present && right.present && m.threat() == right, "{left:?} {right:?}");
}

#[test]
fn a_cell_leaving_the_path_fades_out_of_the_threat() {
    // one cell 0.55 m ahead, seen from headings that put it ever farther to the side: the
    // threat's distance grows without a jump at the path's edge (0.38 m) or anywhere after
    let mut m = memory();
    for _ in 0..4 {
        step(&mut m, STILL, 0.1, &[pt(0.5, 0.0)]);
    }
    let (f0, l0) = (0.55f64, 0.05f64);
    let mut last: Option<f64> = None;
    let mut yaw = 0.0;
    while yaw < 1.2 {
        let o = m.threat();
        let (r, b) = (f0.hypot(l0), l0.atan2(f0) - yaw);
        let (along, across) = (r * b.cos(), (r * b.sin()).abs());
        let d = o.distance_m.unwrap_or_else(|| panic!("still ahead in the band at {along:.3}, {across:.3}"));
        assert!((d - faded(along, across)).abs() < 1e-9, "{d} at {along:.3}, {across:.3}");
        if let Some(prev) = last {
            assert!((d - prev).abs() < 0.6, "no jump at {across:.3} m beside: {prev} → {d}");
        }
        last = Some(d);
        step(&mut m, BodyVelocity { v: 0.0, omega: 0.4 }, 0.1, &[]);
        yaw += 0.04;
    }
    assert!(last.is_some_and(|d| d > 1.5), "faded to far: {last:?}");
}

#[test]
fn nothing_beyond_the_stop_is_a_threat() {
    let mut m = memory();
    for _ in 0..2 {
        step(&mut m, STILL, 0.1, &[pt(1.0, 0.05)]);
    }
    assert!(m.threat().present);
    // path half width 0.38 m: a robot that stops 0.3 m on never comes within it of the cell
    assert!(!m.threat_within(0.3).present, "1.0 m ahead is beyond 0.3 + 0.38 m");
    let o = m.threat_within(0.7);
    assert!(o.present && (o.distance_m.unwrap() - (1.0f64.hypot(0.05) - 0.18)).abs() < 0.08, "{o:?}");
}

#[test]
fn the_path_ends_in_a_half_disc_at_the_stop() {
    // a door's jambs as the memory places them, cell centres 0.65 m ahead and 0.35 m to
    // either side, and a robot that stops 0.3 m on: 0.49 m from where it will stand,
    // beyond its 0.38 m half-width, but inside the square end the path had before
    let mut m = memory();
    put(&mut m, 0.62, 0.35, 2.0, true);
    put(&mut m, 0.62, -0.35, 2.0, true);
    assert!(m.threat_within(0.3).present);
    assert!((m.free_distance(0.0, 1.0) - 0.65).abs() < 1e-9);
    m.set_stop(0.3);
    // (the test memory's wide side band still has them, faded out to far)
    let beside = m.threat_within(0.3);
    assert!(beside.distance_m.is_none_or(|d| d > 2.5), "{beside:?}");
    assert_eq!(m.free_distance(0.0, 1.0), 1.0);
    // a path turned by a right angle never reaches the stop line: a cell 0.9 m to the left
    // blocks it as before
    put(&mut m, 0.02, 0.92, 2.0, true);
    assert!(
        (m.free_distance(std::f64::consts::FRAC_PI_2, 1.0) - 0.95).abs() < 1e-6,
        "{}",
        m.free_distance(std::f64::consts::FRAC_PI_2, 1.0)
    );
    // a cell 0.35 m past the stop point and 0.05 m aside is where the robot will stand
    put(&mut m, 0.62, 0.05, 2.0, true);
    let o = m.threat_within(0.3);
    assert!(o.present && (o.distance_m.unwrap() - (0.65f64.hypot(0.05) - 0.18)).abs() < 1e-6, "{o:?}");
    assert!((m.free_distance(0.0, 1.0) - 0.65).abs() < 1e-9);
    // no stop: the jambs block the path again
    m.cells.remove(&m.cell_at(0.62, 0.05));
    m.set_stop(f64::INFINITY);
    assert!((m.free_distance(0.0, 1.0) - 0.65).abs() < 1e-9);
}

#[test]
fn steers_to_the_nearest_free_heading() {
    let mut m = memory();
    // a 0.6 m wide box 1 m ahead, from 0.1 m left to 0.5 m right of the heading
    let bx: Vec<SurfacePoint> = (0..7).map(|k| pt(1.0, 0.1 - 0.1 * k as f64)).collect();
    for _ in 0..3 {
        step(&mut m, STILL, 0.1, &bx);
    }
    assert!((m.free_distance(0.0, 1.5) - 1.05).abs() < 1e-9, "the box's cells start at 1.0 m");
    let h = m.steer(0.0, 1.5, 0.7, 0.05);
    assert!(h > 0.0, "pass on the left, the short way round: {h}");
    assert!(m.free_distance(h, 1.5) >= 1.5);
    // a free goal direction is kept
    assert_eq!(m.steer(0.6, 1.5, 0.7, 0.05), 0.6);
}

#[test]
fn the_lane_bounds_how_far_a_heading_is_free() {
    let m = memory();
    // a 2 m corridor, the robot 0.3 m left of its centre line and parallel to it: the
    // footprint (0.18) plus the lane margin (0.1) may come to 0.72 m off the line
    let lane = Lane { left_m: 0.3, angle_rad: 0.0, half_width_m: 1.0 };
    assert_eq!(m.lane_free_distance(&lane, 0.0, 1.5), 1.5, "along the corridor");
    let h = 0.5f64;
    let d = m.lane_free_distance(&lane, h, 5.0);
    assert!((d - (0.72 - 0.3) / h.sin()).abs() < 1e-9, "out to the left wall: {d}");
    let d = m.lane_free_distance(&lane, -h, 5.0);
    assert!((d - (0.72 + 0.3) / h.sin()).abs() < 1e-9, "across to the right wall: {d}");
    // outside the band: driving further out is blocked at once, driving back in is free
    let out = Lane { left_m: 0.9, ..lane };
    assert_eq!(m.lane_free_distance(&out, 0.2, 1.5), 0.0);
    assert_eq!(m.lane_free_distance(&out, -0.2, 1.5), 1.5);
    // the robot turned 0.4 rad left of the corridor: its own heading leaves the lane
    let turned = Lane { left_m: 0.0, angle_rad: -0.4, half_width_m: 1.0 };
    let d = m.lane_free_distance(&turned, 0.0, 5.0);
    assert!((d - 0.72 / 0.4f64.sin()).abs() < 1e-9, "{d}");
}

#[test]
fn steering_keeps_inside_the_corridor_from_the_map() {
    let mut m = memory();
    // a box 1 m ahead from 0.25 m right to 0.15 m left of the heading; the robot 0.4 m left
    // of the centre line of a 2 m corridor. Seen alone, the short way round is left (where
    // a doorway, or a wall not yet seen, reads free); inside the corridor only the right
    // gap is wide enough
    let bx: Vec<SurfacePoint> = (0..5).map(|k| pt(1.0, 0.15 - 0.1 * k as f64)).collect();
    for _ in 0..3 {
        step(&mut m, STILL, 0.1, &bx);
    }
    let free = m.steer(0.0, 1.5, 0.7, 0.05);
    assert!(free > 0.0, "without the lane: left, through the door: {free}");
    let lane = Lane { left_m: 0.4, angle_rad: 0.0, half_width_m: 1.0 };
    m.set_lane(Some(lane));
    let h = m.steer(0.0, 1.5, 0.7, 0.05);
    assert!(h < 0.0, "with the lane: right, the way inside the corridor: {h}");
    assert!(m.free_distance(h, 1.5) >= 1.5 && m.lane_free_distance(&lane, h, 1.5) >= 1.5, "{h}");
}

#[test]
fn with_the_wall_band_cells_at_the_corridors_walls_are_left_to_the_lane() {
    // a 2 m corridor, the robot on its centre line; a box 0.35–0.55 m left of the line, 1 m
    // ahead, and a door jamb's phantom 0.85 m right (0.15 m inside the wall) 0.75 m ahead
    let band = MemoryParams { wall_band_m: 0.25, ..memory().params };
    let mut m = ObstacleMemory::new(band, 26.7f64.to_radians(), 0.4);
    let seen = [pt(1.0, 0.35), pt(1.0, 0.45), pt(1.0, 0.55), pt(0.72, -0.83)];
    for _ in 0..3 {
        step(&mut m, STILL, 0.1, &seen);
    }
    assert_eq!(m.occupied().len(), 4, "the memory holds all it saw");
    // the heading straight at the phantom's cell (centre 0.75, −0.85)
    let at_phantom = (-0.85f64).atan2(0.75);
    assert!(m.free_distance(at_phantom, 1.5) < 1.2, "without a lane the phantom is an obstacle");
    let lane = Lane { left_m: 0.0, angle_rad: 0.0, half_width_m: 1.0 };
    m.set_lane(Some(lane));
    assert!(m.free_distance(at_phantom, 1.5) >= 1.5, "with it, the phantom is the lane's wall");
    assert!(m.free_distance(0.45f64.atan2(1.0), 1.5) < 1.2, "the box still blocks");
    let [left, right] = m.threat_sides(f64::INFINITY);
    assert!(left.present && !right.present, "{left:?} {right:?}");
    // the lane's walls centre the robot: a box 0.35 m left, the right wall 1 m away
    assert!(m.centring(1.5, 0.9, 1.5, 0.3) < 0.0);
    // turned 0.3 rad right of the corridor, 0.5 m right of its centre line: the cells are
    // judged by where they are across the corridor, not across the robot's heading
    let mut turned = ObstacleMemory::new(band, 26.7f64.to_radians(), 0.4);
    turned.set_lane(Some(Lane { left_m: -0.5, angle_rad: 0.3, half_width_m: 1.0 }));
    let (s, c) = 0.3f64.sin_cos();
    // points 0.35 m (a box) and 0.85 m (at the wall) right of the centre line, 1 m along it
    let at = |across: f64| {
        let (f, l) = (1.0, across + 0.5); // corridor frame relative to the robot
        pt(f * c - l * s, f * s + l * c)
    };
    for _ in 0..3 {
        step(&mut turned, STILL, 0.1, &[at(-0.35), at(-0.85)]);
    }
    assert_eq!(turned.occupied().len(), 2);
    assert_eq!(turned.banded_cells().filter(|c| c.1).count(), 1, "{:?}", turned.occupied());
    let off = ObstacleMemory { params: MemoryParams { wall_band_m: 0.0, ..band }, ..turned.clone() };
    assert_eq!(off.banded_cells().filter(|c| c.1).count(), 0, "band off: no cell is the wall's");
    // a contact at the wall is no depth error: it still blocks the way ahead
    let mut touched = ObstacleMemory::new(band, 26.7f64.to_radians(), 0.4);
    // (0.95 m left of the centre line: the whole arc lies in the band)
    touched.set_lane(Some(Lane { left_m: 0.95, angle_rad: 0.0, half_width_m: 1.0 }));
    touched.mark_contact(0.5);
    assert!(touched.banded_cells().all(|(_, banded)| !banded));
    assert!(touched.free_distance(0.0, 1.5) < 0.35, "{}", touched.free_distance(0.0, 1.5));
}

#[test]
fn a_lane_wall_inside_the_robots_margin_is_a_threat_on_its_side() {
    use std::f64::consts::FRAC_PI_2;
    // nothing seen: only the lane's walls can be threats (the band leaves them to it)
    let band = MemoryParams { wall_band_m: 0.25, ..memory().params };
    let near = band.robot_radius_m + band.wall_threat_m;
    let mut m = ObstacleMemory::new(band, 26.7f64.to_radians(), 0.4);
    let lane = |left_m: f64, angle_rad: f64| Some(Lane { left_m, angle_rad, half_width_m: 0.6 });
    // on the centre line: both walls 0.6 m away, beyond the margin
    m.set_lane(lane(0.0, 0.0));
    assert_eq!(m.threat_sides(f64::INFINITY), [Obstacle::default(), Obstacle::default()]);
    // 0.4 m left of the line, parallel to it: the left wall is 0.2 m away, abeam
    m.set_lane(lane(0.4, 0.0));
    let [left, right] = m.threat_sides(f64::INFINITY);
    assert!(left.present && !right.present, "{left:?} {right:?}");
    assert!((left.distance_m.unwrap() - (0.2 - band.robot_radius_m)).abs() < 1e-9, "{left:?}");
    assert!((left.bearing_rad.unwrap() - FRAC_PI_2).abs() < 1e-9, "{left:?}");
    // heading 0.3 rad into the right wall, 0.15 m from it: the wall's nearest point is ahead
    // on the right, at the perpendicular distance
    m.set_lane(lane(-0.45, 0.3));
    let [left, right] = m.threat_sides(f64::INFINITY);
    assert!(!left.present && right.present, "{left:?} {right:?}");
    assert!((right.distance_m.unwrap() - 0.0).abs() < 1e-9, "inside the footprint: {right:?}");
    let bearing = right.bearing_rad.unwrap();
    assert!((-FRAC_PI_2..0.0).contains(&bearing) && (bearing + FRAC_PI_2 - 0.3).abs() < 1e-9, "{right:?}");
    // heading away from the left wall, 0.25 m from it: its nearest point not behind is abeam
    m.set_lane(lane(0.35, 0.4));
    let [left, _] = m.threat_sides(f64::INFINITY);
    let gap = 0.25 / 0.4f64.cos();
    assert!((left.distance_m.unwrap() - (gap - band.robot_radius_m)).abs() < 1e-9, "{left:?}");
    // just outside the margin: none
    m.set_lane(lane(0.6 - near - 0.01, 0.0));
    assert!(!m.threat_sides(f64::INFINITY)[0].present);
    // the band off: the walls are the cells', not the lane's
    let mut off = ObstacleMemory { params: MemoryParams { wall_band_m: 0.0, ..band }, ..m.clone() };
    off.set_lane(lane(0.4, 0.0));
    assert!(!off.threat_sides(f64::INFINITY)[0].present);
    // the threat off, the band on
    let mut off = ObstacleMemory { params: MemoryParams { wall_threat_m: 0.0, ..band }, ..m.clone() };
    off.set_lane(lane(0.4, 0.0));
    assert!(!off.threat_sides(f64::INFINITY)[0].present);
    // a wider margin (to cover dead-reckoning drift) reaches farther: 0.35 m from the wall
    let mut wide = ObstacleMemory { params: MemoryParams { wall_threat_m: 0.2, ..band }, ..m.clone() };
    wide.set_lane(lane(0.25, 0.0));
    assert!(wide.threat_sides(f64::INFINITY)[0].present);
    m.set_lane(lane(0.25, 0.0));
    assert!(!m.threat_sides(f64::INFINITY)[0].present);
}

#[test]
fn the_doors_wall_from_the_map_bounds_the_steering_the_guard_and_the_stop() {
    use crate::pafsis::Doorway;
    let mut m = memory();
    let (body, step) = (m.params.robot_radius_m + m.params.lane_margin_m, ARC_STEP_M);
    // no door: nothing bounds the path
    assert_eq!(m.free_in_lane(0.0, 1.5), 1.5);
    // a 0.9 m opening 1 m ahead, the robot on its axis: straight through is free
    m.set_doorway(Some(Doorway { centre_m: [1.0, 0.0], angle_rad: 0.0, half_width_m: 0.45 }));
    assert_eq!(m.free_in_lane(0.0, 1.5), 1.5);
    assert_eq!(m.door_free_ahead(1.5), 1.5);
    assert_eq!(m.arc_free(0.0, 1.5, &super::guard(0.3, false), false), 1.5);
    // 0.35 m left of the axis: the footprint meets the left jamb's edge, 0.1 m beside the
    // path, sqrt(body² − 0.1²) before the wall
    m.set_doorway(Some(Doorway { centre_m: [1.0, -0.35], angle_rad: 0.0, half_width_m: 0.45 }));
    let jamb = 1.0 - (body * body - 0.1f64 * 0.1).sqrt();
    for free in
        [m.free_in_lane(0.0, 1.5), m.door_free_ahead(1.5), m.arc_free(0.0, 1.5, &super::guard(0.3, false), false)]
    {
        assert!(free <= jamb && free > jamb - step - 1e-9, "{free} vs {jamb}");
    }
    // the steering turns toward the opening's middle
    let h = m.steer(0.0, 1.5, 0.7, 0.05);
    assert!(h < 0.0 && m.free_in_lane(h, 1.5) == 1.5, "{h}");
    // a wall straight ahead (the robot 1 m beside the opening): the footprint meets it
    m.set_doorway(Some(Doorway { centre_m: [1.0, 1.0], angle_rad: 0.0, half_width_m: 0.45 }));
    assert!((m.door_free_ahead(1.5) - (1.0 - body)).abs() <= step + 1e-9);
    // in the doorway beside a jamb, nearer than the footprint: free to drive on through,
    // not to turn into it
    m.set_doorway(Some(Doorway { centre_m: [0.0, -0.3], angle_rad: 0.0, half_width_m: 0.45 }));
    assert_eq!(m.free_in_lane(0.0, 1.0), 1.0);
    assert!(m.free_in_lane(0.5, 1.0) < 0.2);
}

#[test]
fn centring_steers_away_from_the_nearer_side() {
    let mut m = memory();
    // walls 0.35 m left and 0.95 m right, 0.5..1.5 m ahead
    let walls: Vec<SurfacePoint> =
        (0..10).flat_map(|k| [pt(0.5 + 0.1 * k as f64, 0.35), pt(0.5 + 0.1 * k as f64, -0.95)]).collect();
    for _ in 0..3 {
        step(&mut m, STILL, 0.1, &walls);
    }
    // cell centres at 0.35 left and 0.95 right: (0.35 − 0.95) / 2 = −0.3 m off the middle
    let c = m.centring(1.5, 1.0, 2.0, 0.3);
    assert!((c - (-0.3f64).atan2(2.0)).abs() < 1e-9, "{c}");
    // nothing within reach: no correction
    assert_eq!(m.centring(1.5, 0.3, 2.0, 0.3), 0.0);
}
