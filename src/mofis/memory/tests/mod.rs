use super::*;
use crate::config_error::ConfigError;

fn pt(forward: f64, left: f64) -> SurfacePoint {
    SurfacePoint { forward, left, up: 0.5, radial_px: 3.0 }
}

/// The default memory, except that standing still counts as measurable (so the geometry
/// below is exact) and cells up to 0.48 m beside the heading count as beside the path.
fn memory() -> ObstacleMemory {
    let p = MemoryParams { min_travel_m: 0.0, side_margin_m: 0.3, ..MemoryParams::default() };
    ObstacleMemory::new(p, 26.7f64.to_radians(), 0.4)
}

const STILL: BodyVelocity = BodyVelocity { v: 0.0, omega: 0.0 };

/// `update` for a pair measured as the memory's own test says.
fn step(m: &mut ObstacleMemory, odo: BodyVelocity, dt: f64, points: &[SurfacePoint]) {
    let measured = m.measurable(odo, dt, 0.0);
    m.update(odo, dt, points, measured);
}

/// What the guard counts: the default clearance, `min_evidence`, clusters or not, every cell.
fn guard(min_evidence: f64, cluster: bool) -> GuardCells {
    GuardCells { clearance_m: 0.04, min_evidence, cluster, min_cells: 1 }
}

/// Puts a cell at (`forward`, `left`) of the robot with `evidence`, confirmed or not.
fn put(m: &mut ObstacleMemory, forward: f64, left: f64, evidence: f64, confirmed: bool) {
    let key = m.cell_at(forward, left);
    m.cells.insert(key, Cell { evidence, contact: false, confirmed, top_m: 0.5 });
}

#[test]
fn the_guard_sees_an_arc_reach_a_lingering_cell() {
    let (reach, min) = (0.4, 0.3);
    let mut m = memory();
    // a faded cell ahead on the left, its centre at (0.35, 0.15): below the occupied
    // threshold, so no threat and no stop, but it was confirmed once
    put(&mut m, 0.35, 0.15, 0.5, true);
    assert!(!m.threat().present);
    // straight on, the footprint (0.18 + 0.04 m) reaches the centre when the origin is
    // √(0.22² − 0.15²) = 0.161 m short of it: after 0.189 m, in steps of 2 cm
    let straight = m.arc_free(0.0, reach, &guard(min, false), false);
    assert!((straight - 0.18).abs() < 1e-9, "{straight}");
    // turning left toward it is blocked sooner, turning right (radius 0.33 m) bends clear
    assert!(m.arc_free(1.0, reach, &guard(min, false), false) < straight);
    assert_eq!(m.arc_free(-3.0, reach, &guard(min, false), false), reach);
    // one that has faded below the guard's evidence, or was never confirmed (one noisy
    // point), does not count
    let mut m = memory();
    put(&mut m, 0.35, 0.15, 0.25, true);
    put(&mut m, 0.35, 0.05, 1.0, false);
    assert_eq!(m.arc_free(0.0, reach, &guard(min, false), false), reach);
    // a cell already inside the footprint blocks only the motion toward it
    let mut m = memory();
    put(&mut m, -0.05, 0.15, 2.0, true);
    assert_eq!(m.arc_free(0.0, reach, &guard(min, false), false), reach, "driving away from what is beside");
    put(&mut m, 0.1, -0.1, 2.0, true);
    assert_eq!(m.arc_free(0.0, reach, &guard(min, false), false), 0.0, "driving into what is ahead inside it");
    // two votes confirm a cell, and it stays confirmed as it fades
    let mut m = memory();
    step(&mut m, STILL, 0.0, &[pt(0.35, 0.15)]);
    assert!(!m.cells.values().any(|c| c.confirmed), "one vote");
    step(&mut m, STILL, 0.0, &[pt(0.35, 0.15)]);
    assert!(m.cells.values().all(|c| c.confirmed));
    m.cells.values_mut().for_each(|c| c.evidence = 0.4);
    assert!(m.arc_free(0.0, reach, &guard(min, false), false) < reach);
    // `aside`: only the cells out of the camera's view count, the brake's query. The cell at
    // (0.35, 0.15) is 0.41 rad off the heading, in view (±0.47 rad); one at (0.25, 0.15),
    // 0.54 rad off, is out of it, and the footprint reaches its centre after
    // 0.25 − √(0.22² − 0.15²) = 0.089 m: at the fifth 2 cm step
    let mut m = memory();
    put(&mut m, 0.35, 0.15, 0.5, true);
    assert!(m.arc_free(0.0, reach, &guard(min, false), false) < reach);
    assert_eq!(m.arc_free(0.0, reach, &guard(min, false), true), reach, "in view");
    put(&mut m, 0.25, 0.15, 0.5, true);
    let aside = m.arc_free(0.0, reach, &guard(min, false), true);
    assert!((aside - 0.08).abs() < 1e-9, "{aside}");
}

#[test]
fn the_guard_holds_a_cluster_while_one_of_its_cells_is_held() {
    let (reach, min) = (0.4, 0.3);
    let mut m = memory();
    // a chain of neighbouring confirmed cells 0.35 m ahead, 0.05, 0.15 and 0.25 m left of the
    // heading, and one more at 0.45 m, not joined (a cell apart); all faded below the guard
    for left in [0.05, 0.15, 0.25, 0.45] {
        put(&mut m, 0.35, left, 0.1, true);
    }
    assert_eq!(m.arc_free(0.0, reach, &guard(min, false), false), reach, "all faded");
    assert_eq!(m.arc_free(0.0, reach, &guard(min, true), false), reach, "no cell of the cluster held");
    // the chain's outer end is held; 0.25 m left it is beside the footprint's path (0.22 m)
    put(&mut m, 0.35, 0.25, 1.0, true);
    assert_eq!(m.arc_free(0.0, reach, &guard(min, false), false), reach, "the held cell is off the path");
    // held as one cluster, the cell 0.05 m left blocks once the footprint reaches its centre:
    // after 0.35 − √(0.22² − 0.05²) = 0.136 m, at the seventh 2 cm step
    let held = m.arc_free(0.0, reach, &guard(min, true), false);
    assert!((held - 0.12).abs() < 1e-9, "{held}");
    // a cell never confirmed (one noisy point) joins no cluster: the held cell 0.15 m left
    // blocks after 0.35 − √(0.22² − 0.15²) = 0.189 m either way
    let mut m = memory();
    put(&mut m, 0.35, 0.05, 0.1, false);
    put(&mut m, 0.35, 0.15, 1.0, true);
    for cluster in [false, true] {
        let free = m.arc_free(0.0, reach, &guard(min, cluster), false);
        assert!((free - 0.18).abs() < 1e-9, "{cluster}: {free}");
    }
}

#[test]
fn the_guard_can_count_only_clusters_of_some_size() {
    let reach = 0.4;
    let guard = |min_cells| GuardCells { min_cells, ..guard(0.3, false) };
    let mut m = memory();
    // a lone confirmed cell ahead, 0.15 m left: the footprint reaches its centre after
    // 0.35 − √(0.22² − 0.15²) = 0.189 m, at the tenth 2 cm step, unless lone cells are left out
    put(&mut m, 0.35, 0.15, 1.0, true);
    let lone = m.arc_free(0.0, reach, &guard(1), false);
    assert!((lone - 0.18).abs() < 1e-9, "{lone}");
    assert_eq!(m.arc_free(0.0, reach, &guard(2), false), reach, "a lone cell");
    // a faded confirmed neighbour diagonally beyond it, off the path, makes a cluster of two
    put(&mut m, 0.45, 0.25, 0.1, true);
    assert_eq!(m.arc_free(0.0, reach, &guard(2), false), lone, "a cluster of two");
    assert_eq!(m.arc_free(0.0, reach, &guard(3), false), reach, "not of three");
    // a cell that was never confirmed (one noisy point) adds nothing to a cluster
    put(&mut m, 0.45, 0.35, 2.0, false);
    assert_eq!(m.arc_free(0.0, reach, &guard(3), false), reach, "unconfirmed");
    // the cluster counts however far it reaches: a chain of confirmed cells 2 m long behind it
    for k in 1..=20 {
        put(&mut m, 0.45 + 0.1 * k as f64, 0.25, 0.1, true);
    }
    assert_eq!(m.arc_free(0.0, reach, &guard(20), false), lone, "a wall's cluster");
}

#[test]
fn one_frame_is_not_enough_two_are() {
    let mut m = memory();
    step(&mut m, STILL, 0.1, &[pt(1.0, 0.05), pt(1.01, 0.04)]);
    assert!(!m.threat().present, "a single frame (two blocks in one cell) must not make an obstacle");
    step(&mut m, STILL, 0.1, &[pt(1.0, 0.05)]);
    let o = m.threat();
    assert!(o.present);
    // cell centre (1.05, 0.05): its range minus the 0.18 m radius
    assert!((o.distance_m.unwrap() - (1.05f64.hypot(0.05) - 0.18)).abs() < 1e-9, "{o:?}");
    assert!((o.bearing_rad.unwrap() - 0.05f64.atan2(1.05)).abs() < 1e-9);
}

#[test]
fn weak_flow_votes_less_and_a_cell_of_many_points_votes_once() {
    let base = MemoryParams { min_travel_m: 0.0, vote_full_radial_px: 0.0, ..MemoryParams::default() };
    let weak = |px: f64| SurfacePoint { radial_px: px, ..pt(1.0, 0.05) };
    let evidence_after = |params: MemoryParams, frame: &[SurfacePoint], frames: usize| {
        let mut m = ObstacleMemory::new(params, 26.7f64.to_radians(), 0.4);
        for _ in 0..frames {
            // dt 0: no decay, the evidence is the sum of the votes
            m.update(STILL, 0.0, frame, true);
        }
        m.cells.values().map(|c| c.evidence).sum::<f64>()
    };
    let weighted = MemoryParams { vote_full_radial_px: 2.5, ..base };
    // off: any point votes 1 per frame, two frames make an obstacle
    assert_eq!(evidence_after(base, &[weak(1.25)], 2), 2.0);
    // on: a lone 1.25 px point votes 0.5, so the same two frames do not ...
    assert!((evidence_after(weighted, &[weak(1.25)], 2) - 1.0).abs() < 1e-12);
    // ... three of them do (occupied at 1.5)
    assert!((evidence_after(weighted, &[weak(1.25)], 3) - 1.5).abs() < 1e-12);
    // a strong point votes 1, and three weak points in one cell vote 1 together, not 1.5
    assert_eq!(evidence_after(weighted, &[weak(4.0)], 1), 1.0);
    assert_eq!(evidence_after(weighted, &[weak(1.25), weak(1.25), weak(1.25)], 1), 1.0);
}

#[test]
fn a_contact_blocks_the_path_ahead_until_the_robot_turns_away() {
    let mut m = memory();
    m.mark_contact(0.5);
    // the arc sits just beyond the footprint, ±0.5 rad: straight on is blocked at once
    assert!(m.free_distance(0.0, 1.5) < 0.35, "{}", m.free_distance(0.0, 1.5));
    let o = m.threat();
    assert!(o.present && o.distance_m.unwrap() < 0.15, "{o:?}");
    // the stall recovery: back off 0.15 m, then turn on the spot; 46° is not enough to
    // drive straight on, 90° is
    step(&mut m, BodyVelocity { v: -0.15, omega: 0.0 }, 1.0, &[]);
    step(&mut m, BodyVelocity { v: 0.0, omega: 0.8 }, 1.0, &[]);
    assert!(m.free_distance(0.0, 1.5) < 0.5, "{}", m.free_distance(0.0, 1.5));
    assert!(m.free_distance(0.8, 1.5) >= 1.5, "{}", m.free_distance(0.8, 1.5));
    step(&mut m, BodyVelocity { v: 0.0, omega: std::f64::consts::FRAC_PI_2 - 0.8 }, 1.0, &[]);
    assert!(m.free_distance(0.0, 1.5) >= 1.5, "{}", m.free_distance(0.0, 1.5));
    // and it is remembered on the right, where it was
    assert!(!m.occupied().is_empty() && m.occupied().iter().all(|[_, l]| *l < 0.0), "{:?}", m.occupied());
}

#[test]
fn a_contact_is_remembered_while_the_robot_stays_and_fades_as_it_drives_away() {
    let mut m = memory();
    // something seen 0.35 m to the left, and a contact ahead
    for _ in 0..4 {
        step(&mut m, STILL, 0.1, &[pt(1.0, 0.35)]);
    }
    m.mark_contact(0.5);
    // 10 s turning to and fro on the spot (a stall loop's time scale): the seen cell fades
    // out (half-life 4 s), the contact stays (15 s: 4 → 2.5)
    for k in 0..100 {
        let omega = if k % 20 < 10 { 0.5 } else { -0.5 };
        step(&mut m, BodyVelocity { v: 0.0, omega }, 0.1, &[]);
    }
    let left = m.occupied();
    assert!(!left.is_empty() && left.iter().all(|[f, _]| *f < 0.35), "only the contact arc: {left:?}");
    // driving 1.5 m on (half-life 1 m), it is forgotten
    for _ in 0..15 {
        step(&mut m, BodyVelocity { v: -1.0, omega: 0.0 }, 0.1, &[]);
    }
    assert!(m.occupied().is_empty(), "{:?}", m.occupied());
}

#[test]
fn nothing_is_taken_in_while_creeping_or_turning_fast() {
    let mut m = ObstacleMemory::new(MemoryParams::default(), 0.47, 0.4);
    let creep = BodyVelocity { v: 0.05, omega: 0.0 }; // 5 mm in 0.1 s < 6 mm
    let spin = BodyVelocity { v: 0.3, omega: 0.5 };
    assert!(!m.measurable(creep, 0.1, 0.0) && !m.measurable(spin, 0.1, 0.0));
    assert!(m.measurable(BodyVelocity { v: 0.3, omega: 0.1 }, 0.1, 0.0));
    // a turn rate that changed by 0.1 rad/s within the pair is not trusted
    assert!(!m.measurable(BodyVelocity { v: 0.3, omega: 0.1 }, 0.1, 0.1));
    for odo in [creep, spin, creep] {
        step(&mut m, odo, 0.1, &[pt(1.0, 0.0)]);
    }
    assert!(m.occupied().is_empty());
}

#[test]
fn remembers_an_obstacle_out_of_view_and_moves_it_with_the_robot() {
    let mut m = memory();
    for _ in 0..4 {
        step(&mut m, STILL, 0.1, &[pt(1.0, 0.35)]);
    }
    // drive 1 m straight in 10 steps seeing nothing: the box is now beside the robot, out of
    // view (90°), still remembered, 0.35 m to the left
    let v = BodyVelocity { v: 1.0, omega: 0.0 };
    for _ in 0..10 {
        step(&mut m, v, 0.1, &[]);
    }
    let cells = m.occupied();
    assert_eq!(cells.len(), 1);
    assert!((cells[0][0] - 0.05).abs() < 1e-9 && (cells[0][1] - 0.35).abs() < 1e-9, "{cells:?}");
    let o = m.threat();
    assert!(o.present && o.bearing_rad.unwrap() > 1.0, "beside the path, to the left: {o:?}");
    // turning left 90° on the spot puts it ahead, in the path
    let turn = BodyVelocity { v: 0.0, omega: std::f64::consts::FRAC_PI_2 };
    step(&mut m, turn, 1.0, &[]);
    let o = m.threat();
    assert!(o.bearing_rad.unwrap().abs() < 0.2, "{o:?}");
}

#[test]
fn out_of_view_a_cell_fades_with_the_motion_not_while_the_robot_stands_beside_it() {
    let p = MemoryParams::default();
    let mut m = memory();
    // seen in four frames 0.4 m to the left, 0.5 m ahead: out of view (39°)
    for _ in 0..4 {
        step(&mut m, STILL, 0.1, &[pt(0.5, 0.4)]);
    }
    assert_eq!(m.occupied().len(), 1);
    let before = m.cells.values().next().unwrap().evidence;
    // standing beside it for 10 s: 0.5^(10 s / out_half_life_s) of the evidence stays (the
    // 4 s half-life of a cell in view would leave 0.18 of it, below `occupied`)
    for _ in 0..100 {
        step(&mut m, STILL, 0.1, &[]);
    }
    let after = m.cells.values().next().unwrap().evidence;
    assert!((after / before - 0.5f64.powf(10.0 / p.out_half_life_s)).abs() < 1e-9, "{before} → {after}");
    assert_eq!(m.occupied().len(), 1, "still there after 10 s standing beside it");
    // driving on 3 m in 1 s (it stays out of view, beside and then behind) halves it twice more
    let v = BodyVelocity { v: 3.0, omega: 0.0 };
    step(&mut m, v, 1.0, &[]);
    let driven = m.cells.values().next().unwrap().evidence;
    let k = 0.5f64.powf(3.0 / p.out_half_life_m + 1.0 / p.out_half_life_s);
    assert!((driven / after - k).abs() < 1e-9, "{after} → {driven}");
    assert!(m.occupied().is_empty());
}

#[test]
fn standing_still_a_cell_in_view_fades_at_the_aside_rate() {
    let p = MemoryParams::default();
    // the default memory: standing still measures nothing (less than 6 mm travelled)
    let mut m = ObstacleMemory::new(p, 26.7f64.to_radians(), 0.4);
    let drive = BodyVelocity { v: 0.1, omega: 0.0 };
    for k in 0..4 {
        let measured = m.measurable(drive, 0.1, 0.0);
        assert!(measured);
        m.update(drive, 0.1, &[pt(1.0 - 0.01 * k as f64, 0.0)], measured);
    }
    assert_eq!(m.cells.len(), 1);
    let before = m.cells.values().next().unwrap().evidence;
    // 4 s standing in front of it, nothing measured: one `half_life_aside_s`
    for _ in 0..40 {
        let measured = m.measurable(STILL, 0.1, 0.0);
        assert!(!measured);
        m.update(STILL, 0.1, &[], measured);
    }
    let after = m.cells.values().next().unwrap().evidence;
    assert!((after / before - 0.5f64.powf(4.0 / p.half_life_aside_s)).abs() < 1e-9, "{before} → {after}");
}

#[test]
fn the_band_ahead_is_free_up_to_the_nearest_cell_in_it() {
    let mut m = memory();
    for _ in 0..2 {
        step(&mut m, STILL, 0.1, &[pt(0.8, 0.15), pt(0.5, 0.45)]);
    }
    // the cell 0.15 m left (centre 0.85, 0.15) is in a 0.23 m band; the one 0.45 m left is not
    assert!((m.free_width(0.0, 0.23, 2.0) - 0.85).abs() < 1e-9);
    assert!((m.free_width(0.0, 0.1, 2.0) - 2.0).abs() < 1e-9);
    assert!((m.free_width(0.0, 0.5, 2.0) - 0.55).abs() < 1e-9);
}

#[test]
fn a_cell_seen_through_fades_fast_one_not_seen_slowly() {
    let p = MemoryParams::default();
    let mut m = memory();
    for _ in 0..4 {
        step(&mut m, STILL, 0.1, &[pt(1.0, 0.0), pt(1.0, 0.35)]);
    }
    // 1 s in which the camera sees a wall 3 m away behind the first cell only (same bearing
    // sector as the cell centre (1.05, 0.05)): that cell
    // loses 2 half-lives of evidence, the other a quarter of one
    for _ in 0..10 {
        step(&mut m, STILL, 0.1, &[pt(3.0, 0.15)]);
    }
    let near: Vec<[f64; 2]> = m.occupied().into_iter().filter(|c| c[0] < 2.0).collect();
    assert_eq!(near.len(), 1, "{near:?}");
    assert!(near[0][1] > 0.25, "the cell not seen through survives: {near:?}");
    assert!(p.validate().is_ok());
    let e = MemoryParams { occupied: 5.0, ..p }.validate().unwrap_err();
    assert!(
        matches!(&e, ConfigError::Invalid { field, problem } if field == "mofis.memory.max_evidence" && problem == "must be ≥ occupied"),
        "{e:?}"
    );
}

#[test]
fn a_ray_over_a_low_box_does_not_clear_it() {
    // the camera is 0.4 m up; a box 1 m ahead, seen up to 0.25 m (`top`), and a wall 3 m
    // away on the same bearing, seen at `wall_up`; then 1 s in which only the wall is
    // measured (the box's flow is too weak to locate, say)
    let remains = |top: f64, wall_up: f64| {
        let mut m = memory();
        let b = |up| SurfacePoint { forward: 1.0, left: 0.0, up, radial_px: 3.0 };
        for _ in 0..4 {
            step(&mut m, STILL, 0.1, &[b(0.1), b(top)]);
        }
        for _ in 0..10 {
            step(&mut m, STILL, 0.1, &[SurfacePoint { forward: 3.0, left: 0.15, up: wall_up, radial_px: 3.0 }]);
        }
        m.occupied().iter().any(|c| c[0] < 2.0)
    };
    // the ray to the wall at 1.0 m passes over the box at 0.4 + 0.6/3 ≈ 0.6 m: it says
    // nothing about the box, which stays
    assert!(remains(0.25, 1.0));
    // a ray to the wall's foot (0.15 m) passes the box at ≈ 0.32 m: still above a 0.25 m box,
    // but through a 0.5 m one, which is cleared
    assert!(remains(0.25, 0.15));
    assert!(!remains(0.5, 0.15));
}

#[test]
fn a_heading_is_free_as_the_straight_arc_turned_to_it() {
    let (reach, min) = (1.0, 0.3);
    let mut m = memory();
    // a faded but guard-strength cell 0.5 m to the left, and a phantom never confirmed ahead
    put(&mut m, 0.05, 0.55, 0.5, true);
    put(&mut m, 0.55, 0.05, 2.0, false);
    // straight ahead the path is free (the phantom joins nothing) and agrees with the arc
    assert_eq!(m.heading_free(0.0, reach, &guard(min, true)), m.arc_free(0.0, reach, &guard(min, true), false));
    assert_eq!(m.heading_free(0.0, reach, &guard(min, false)), reach);
    // turned left to face the cell, the footprint (0.22 m) reaches its centre after
    // 0.55 − √(0.22² − 0.05²) = 0.336 m: at the sixteenth 2 cm step; in view or not, it counts
    let left = m.heading_free(std::f64::consts::FRAC_PI_2, reach, &guard(min, false));
    assert!((left - 0.32).abs() < 1e-9, "{left}");
    // to the right, away from it, the way is free
    assert_eq!(m.heading_free(-std::f64::consts::FRAC_PI_2, reach, &guard(min, false)), reach);
}

mod paths;
mod planning;
