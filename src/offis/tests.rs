//! OFFIS on closed-form flow fields: geometry exact to rounding, the paper's eq. (11) and
//! eq. (12) masks from scenes of the kind the paper shows, other grid sizes, and errors.

use super::geometry::{DepthParams, FrameMotion, PinholeCamera, locate};
use super::synth::{Rect, Scene};
use super::*;

const DT: f64 = 0.1;

/// The nominal C310 mounted 1 m above the floor, optionally pitched.
fn calib(pitch: f64) -> Calibration {
    let mut c = Calibration::nominal_c310();
    c.mount.z_m = 1.0;
    c.mount.pitch_rad = pitch;
    c
}

const Z: [f64; 2] = [-10.0, 10.0];

fn wall() -> Scene {
    Scene { rects: vec![Rect::frontal(2.1, [-10.0, 10.0], Z)] }
}

/// Fig. 7: a wall 2 m ahead of the camera with a 1 m wide opening, a far wall behind it.
fn door() -> Scene {
    Scene {
        rects: vec![
            Rect::frontal(2.1, [0.5, 10.0], Z),
            Rect::frontal(2.1, [-10.0, -0.5], Z),
            Rect::frontal(8.0, [-10.0, 10.0], Z),
        ],
    }
}

/// A wall 3 m ahead, turned 0.4 rad, and the floor: the scene of the turning drives.
fn wall_3m_and_floor() -> Scene {
    Scene { rects: vec![Rect::vertical(3.0, 0.0, 0.4, [-10.0, -10.0, -10.0], [10.0, 10.0, 10.0]), Rect::floor()] }
}

/// Fig. 8: a 2 m wide corridor with a box against its left wall, low in the view.
fn corridor_with_box() -> Scene {
    Scene {
        rects: vec![
            Rect::side(1.0, [0.0, 60.0], Z),
            Rect::side(-1.0, [0.0, 60.0], Z),
            Rect::frontal(60.0, [-1.0, 1.0], Z),
            Rect::frontal(2.15, [0.5, 1.0], [-10.0, 0.72]),
        ],
    }
}

fn run(scene: &Scene, c: &Calibration, rows: usize, cols: usize, vel: BodyVelocity) -> (Perception, Attributes) {
    let pair = scene.flow(c, rows, cols, vel, DT);
    let mut offis = Offis::new(OffisParams::default()).unwrap();
    let p = offis.step(&pair.field, vel, DT, c).unwrap();
    (p, offis.attributes().clone())
}

#[test]
fn frontal_plane_depth_is_exact() {
    // Camera at x = 0.1, wall at x = 2.1, driving 0.5 m/s for 0.1 s: 1.95 m ahead at frame B.
    let c = calib(0.0);
    let vel = BodyVelocity::new(0.5, 0.0);
    let pair = wall().flow(&c, 16, 16, vel, DT);
    let cam = PinholeCamera::new(&c, 1280, 720);
    let m = FrameMotion::from_odometry(&cam, vel, DT);
    let foe = m.foe(&cam).unwrap();
    assert!((foe[0] - cam.cx).abs() < 1e-9 && (foe[1] - cam.cy).abs() < 1e-9, "FOE at the principal point");
    let mut n = 0;
    for f in &pair.field.vectors {
        let t = m.derotate(&cam, f.x as f64, f.y as f64, f.u as f64, f.v as f64).unwrap();
        if let Some(l) = locate(&cam, &m, foe, &DepthParams::default(), [f.x as f64, f.y as f64], t) {
            assert!((l.forward - 1.95).abs() < 1e-6, "{l:?}");
            n += 1;
        }
    }
    assert_eq!(n, 256, "every block is far enough from the FOE");
}

#[test]
fn plane_plus_rotation_locates_every_point() {
    // A turn of 0.3 rad/s while driving, camera off the turning axis, with and without pitch:
    // every block's located point equals the ray-cast truth at frame B.
    for pitch in [0.0, 0.15] {
        let c = calib(pitch);
        let vel = BodyVelocity::new(0.4, 0.3);
        let scene = wall_3m_and_floor();
        let pair = scene.flow(&c, 16, 16, vel, DT);
        let cam = PinholeCamera::new(&c, 1280, 720);
        let m = FrameMotion::from_odometry(&cam, vel, DT);
        let foe = m.foe(&cam).unwrap();
        let mut n = 0;
        for (f, truth) in pair.field.vectors.iter().zip(&pair.truth) {
            let t = m.derotate(&cam, f.x as f64, f.y as f64, f.u as f64, f.v as f64).unwrap();
            if let Some(l) = locate(&cam, &m, foe, &DepthParams::default(), [f.x as f64, f.y as f64], t) {
                let want = truth.unwrap();
                let err =
                    ((l.forward - want[0]).powi(2) + (l.left - want[1]).powi(2) + (l.up - want[2]).powi(2)).sqrt();
                assert!(err < 1e-5 * want[0].abs().max(1.0), "pitch {pitch}: got {l:?}, want {want:?}");
                n += 1;
            }
        }
        assert!(n > 200, "pitch {pitch}: only {n} blocks located");
    }
}

#[test]
fn pure_rotation_derotates_to_zero() {
    let c = calib(0.1);
    let vel = BodyVelocity::new(0.0, 0.8);
    let pair = wall().flow(&c, 16, 16, vel, DT);
    let cam = PinholeCamera::new(&c, 1280, 720);
    let m = FrameMotion::from_odometry(&cam, BodyVelocity::new(0.0, 0.8), DT);
    // The camera sits 0.1 m ahead of the axis, so a pure turn also translates it a little
    // (0.1·sin 0.08 ≈ 8 mm sideways); with the wall 2 m away the left-over flow is that parallax.
    for f in &pair.field.vectors {
        assert!(f.u > 30.0, "a left turn moves the image right: {f:?}");
        let [u, v] = m.derotate(&cam, f.x as f64, f.y as f64, f.u as f64, f.v as f64).unwrap();
        assert!(u.hypot(v) < 6.0, "{u} {v}");
    }
    let far = Scene::default().flow(&c, 16, 16, vel, DT);
    for f in &far.field.vectors {
        let [u, v] = m.derotate(&cam, f.x as f64, f.y as f64, f.u as f64, f.v as f64).unwrap();
        assert!(u.hypot(v) < 1e-3, "points at infinity have no translational flow: {u} {v}");
    }
}

#[test]
fn eq_11_door_rough_mask() {
    let ones_outside = [[1, 0, 0, 1]; 4];
    for vel in [BodyVelocity::new(0.5, 0.0), BodyVelocity::new(0.5, 0.25)] {
        let (p, a) = run(&door(), &calib(0.0), 16, 16, vel);
        assert_eq!(p.rough, ones_outside, "{vel:?}: {a:#?}");
    }
}

#[test]
fn a_plain_wall_is_one_plane_in_every_quadrant() {
    let (p, a) = run(&wall(), &calib(0.0), 16, 16, BodyVelocity::new(0.5, 0.0));
    assert_eq!(p.rough, [[1; 4]; 4]);
    assert_eq!(a.vplane_l2, [[1; 4]; 2]);
    assert_eq!(a.hplane_l2, [[1; 2]; 4]);
    // a frontal plane has no tilt: V depends on the row only (eq. 8 ratio 1)
    for row in a.tilt_l3 {
        for t in row {
            assert!((t - TiltParams::default().k_tilt).abs() < 1e-3, "{t}");
        }
    }
    // TPO distance: the wall at frame B, 2.1 − 0.1 − 0.05 m from the camera.
    assert!((p.tpo.distance_m.unwrap() - 1.95).abs() < 1e-3, "{:?}", p.tpo);
}

#[test]
fn eq_12_corridor_with_obstacle_fine_mask() {
    let mut want = [[1, 0, 0, 0, 0, 0, 0, 1]; 8];
    want[6][1] = 1;
    want[7][1] = 1;
    for vel in [BodyVelocity::new(0.5, 0.0), BodyVelocity::new(0.5, -0.2)] {
        let (p, a) = run(&corridor_with_box(), &calib(0.0), 16, 16, vel);
        assert_eq!(p.fine, want, "{vel:?}: rough {:?} {a:#?}", p.rough);
        assert_eq!(p.rough, [[1, 0, 0, 1]; 4]);
    }
}

#[test]
fn an_obstacle_is_what_stands_clearly_in_front_of_the_tpo() {
    // A wall 4 m ahead and a box face 1.6 m ahead on the right: the box is the obstacle, with
    // its distance and bearing; the wall alone is no obstacle (it is the TPO, a wall).
    let c = calib(0.0);
    let vel = BodyVelocity::new(0.5, 0.1);
    let wall_only = Scene { rects: vec![Rect::frontal(4.0, [-10.0, 10.0], Z), Rect::floor()] };
    let (p, _) = run(&wall_only, &c, 16, 16, vel);
    assert!(!p.obstacle.present && p.obstacle.cell.is_none(), "{:?}", p.obstacle);
    assert_eq!(p.tpo.shape, TpoShape::Wall, "{:?}", p.tpo);
    assert!((p.tpo.distance_m.unwrap() - 3.85).abs() < 0.02, "{:?}", p.tpo);
    let scene = Scene {
        rects: vec![Rect::frontal(4.0, [-10.0, 10.0], Z), Rect::frontal(1.6, [-0.6, -0.2], [0.0, 1.3]), Rect::floor()],
    };
    let (p, a) = run(&scene, &c, 16, 16, vel);
    assert!(p.obstacle.present, "{:?} {:?}", p.obstacle, a.features);
    // the box face is 1.45 m ahead of the camera at frame B, 0.2–0.6 m to the right
    let d = p.obstacle.distance_m.unwrap();
    assert!((1.45..1.6).contains(&d), "{d}");
    let b = p.obstacle.bearing_rad.unwrap().to_degrees();
    assert!((-22.0..-7.0).contains(&b), "{b}");
    let [_, col] = p.obstacle.cell.unwrap();
    assert!(col >= 4, "right half of the image: {:?}", p.obstacle.cell);
    assert_eq!(p.tpo.shape, TpoShape::Wall, "the box does not change the TPO: {:?}", a.features);
}

#[test]
fn no_distance_when_not_translating() {
    let c = calib(0.0);
    for vel in [BodyVelocity::new(0.0, 0.0), BodyVelocity::new(0.01, 0.5)] {
        let (p, a) = run(&door(), &c, 16, 16, vel);
        assert_eq!(p.tpo.distance_m, None);
        assert_eq!(p.obstacle.distance_m, None);
        assert!(a.foe.is_none() && a.range_l3.iter().flatten().all(Option::is_none));
    }
}

#[test]
fn other_grids_give_the_same_masks() {
    for (rows, cols) in [(8, 8), (24, 24), (16, 32)] {
        let (p, _) = run(&door(), &calib(0.0), rows, cols, BodyVelocity::new(0.5, 0.0));
        assert_eq!(p.rough, [[1, 0, 0, 1]; 4], "{rows}x{cols}");
        let (p, _) = run(&wall(), &calib(0.0), rows, cols, BodyVelocity::new(0.5, 0.0));
        assert_eq!(p.rough, [[1; 4]; 4], "{rows}x{cols}");
        assert!((p.tpo.distance_m.unwrap() - 1.95).abs() < 1e-3, "{rows}x{cols}");
    }
}

#[test]
fn calibration_is_scaled_to_the_flow_size() {
    // The same scene seen by a 640×360 stream of the camera calibrated at 1280×720.
    let c = calib(0.0);
    let small = {
        let mut s = c.scaled_to(640, 360);
        s.model = c.model.clone();
        s
    };
    let vel = BodyVelocity::new(0.5, 0.0);
    let pair = wall().flow(&small, 16, 16, vel, DT);
    let p = Offis::new(OffisParams::default()).unwrap().step(&pair.field, vel, DT, &c).unwrap();
    assert!((p.tpo.distance_m.unwrap() - 1.95).abs() < 1e-3);
}

#[test]
fn invalid_vectors_and_bad_inputs() {
    let c = calib(0.0);
    let vel = BodyVelocity::new(0.5, 0.0);
    let mut pair = wall().flow(&c, 16, 16, vel, DT);
    for f in pair.field.vectors.iter_mut().step_by(3) {
        f.validity = crate::flow::Validity::Textureless;
        f.u = 1e6;
    }
    let mut offis = Offis::new(OffisParams::default()).unwrap();
    let p = offis.step(&pair.field, vel, DT, &c).unwrap();
    assert_eq!(offis.attributes().valid, 256 - 86);
    assert_eq!(p.rough, [[1; 4]; 4], "invalid vectors do not enter the averages");
    assert!(matches!(offis.step(&pair.field, vel, 0.0, &c), Err(OffisError::Dt(_))));
    assert!(matches!(
        offis.step(&pair.field, BodyVelocity::new(f64::NAN, 0.0), DT, &c),
        Err(OffisError::Odometry { .. })
    ));
    let mut bad = pair.field.clone();
    bad.rows = 12;
    bad.cols = 12;
    let e = offis.step(&bad, vel, DT, &c).unwrap_err();
    assert!(e.to_string().contains("multiples of 8"), "{e}");
    bad.rows = 16;
    bad.cols = 8;
    assert!(matches!(offis.step(&bad, vel, DT, &c), Err(OffisError::Size { .. })));
}

#[test]
fn the_step_is_deterministic_and_reuses_its_buffers() {
    let c = calib(0.0);
    let vel = BodyVelocity::new(0.5, 0.1);
    let a = corridor_with_box().flow(&c, 16, 16, vel, DT);
    let b = door().flow(&c, 24, 24, vel, DT);
    let mut offis = Offis::new(OffisParams::default()).unwrap();
    let first = offis.step(&a.field, vel, DT, &c).unwrap();
    offis.step(&b.field, vel, DT, &c).unwrap();
    assert_eq!(offis.step(&a.field, vel, DT, &c).unwrap(), first);
}

fn classify(scene: &Scene) -> (Tpo, features::Features) {
    let c = Calibration::nominal_c310();
    let vel = BodyVelocity::new(0.5, 0.0);
    let pair = scene.flow(&c, 16, 16, vel, DT);
    let mut offis = Offis::new(OffisParams::default()).unwrap();
    let p = offis.step(&pair.field, vel, DT, &c).unwrap();
    (p.tpo, offis.attributes().features)
}

#[test]
fn the_classifiers_tell_the_four_shapes_apart() {
    let floor = Rect::floor();
    let (wall, f) = classify(&Scene { rects: vec![Rect::frontal(2.6, [-10.0, 10.0], Z), floor] });
    assert_eq!((wall.shape, f.planes), (TpoShape::Wall, 1.0), "{f:?}");
    assert!((wall.distance_m.unwrap() - 2.45).abs() < 0.02 && wall.confidence > 0.9, "{wall:?}");
    // a concave corner: two walls at ±45° meeting 3 m ahead
    let (corner, f) = classify(&Scene {
        rects: vec![
            Rect::vertical(3.1, 0.0, std::f64::consts::FRAC_PI_4, [-10.0, 0.0, -10.0], [10.0, 10.0, 10.0]),
            Rect::vertical(3.1, 0.0, -std::f64::consts::FRAC_PI_4, [-10.0, -10.0, -10.0], [10.0, 0.0, 10.0]),
            floor,
        ],
    });
    assert_eq!(corner.shape, TpoShape::Corner, "{f:?}");
    assert!(f.pair_angle_deg > 80.0 && (corner.distance_m.unwrap() - 2.95).abs() < 0.1, "{corner:?} {f:?}");
    let (corridor, f) =
        classify(&Scene { rects: vec![Rect::side(1.0, [0.0, 60.0], Z), Rect::side(-1.0, [0.0, 60.0], Z), floor] });
    assert_eq!(corridor.shape, TpoShape::Corridor, "{f:?}");
    assert!(f.side_angle_deg < 5.0 && f.open_ahead_m >= 7.9, "{f:?}");
    let (door, f) = classify(&Scene {
        rects: vec![
            Rect::frontal(2.6, [0.5, 10.0], Z),
            Rect::frontal(2.6, [-10.0, -0.5], Z),
            Rect::frontal(5.6, [-10.0, 10.0], Z),
            floor,
        ],
    });
    assert_eq!(door.shape, TpoShape::Door, "{f:?}");
    assert!((0.7..1.4).contains(&f.gap_m) && (door.distance_m.unwrap() - 2.45).abs() < 0.02, "{door:?} {f:?}");
    let (none, f) = classify(&Scene { rects: vec![floor] });
    assert_eq!((none.shape, none.distance_m), (TpoShape::None, None), "{f:?}");
}

#[test]
fn the_floor_is_never_the_obstacle() {
    // Level C310 0.4 m above the floor, a wall 4 m ahead and a box 1.8 m ahead on the right:
    // the floor's flow at the bottom corners is the biggest, but the obstacle is the box.
    let c = Calibration::nominal_c310();
    let scene = Scene {
        rects: vec![Rect::floor(), Rect::frontal(4.0, [-10.0, 10.0], Z), Rect::frontal(1.9, [-0.7, -0.2], [0.0, 0.6])],
    };
    let vel = BodyVelocity::new(0.5, 0.0);
    let pair = scene.flow(&c, 16, 16, vel, DT);
    let mut offis = Offis::new(OffisParams::default()).unwrap();
    let p = offis.step(&pair.field, vel, DT, &c).unwrap();
    let [r, col] = p.obstacle.cell.unwrap();
    let t = pair.truth[(2 * r) * 16 + 2 * col].unwrap();
    assert!(t[2] + 0.4 > 0.1, "block on the box, not the floor: {t:?} cell {r},{col}");
    assert!(p.obstacle.present && (p.obstacle.distance_m.unwrap() - 1.8).abs() < 0.1, "{:?}", p.obstacle);
    assert!(p.obstacle.bearing_rad.unwrap() < 0.0);
    // the floor alone: no obstacle
    let pair = Scene { rects: vec![Rect::floor()] }.flow(&c, 16, 16, vel, DT);
    assert!(!offis.step(&pair.field, vel, DT, &c).unwrap().obstacle.present);
}

/// The flow of a door 2.6 m ahead, the room's back wall 3 m beyond it.
fn door_ahead(c: &Calibration, vel: BodyVelocity) -> FlowField {
    let rects = vec![
        Rect::frontal(2.6, [0.5, 10.0], Z),
        Rect::frontal(2.6, [-10.0, -0.5], Z),
        Rect::frontal(5.6, [-10.0, 10.0], Z),
        Rect::floor(),
    ];
    Scene { rects }.flow(c, 16, 16, vel, DT).field
}

/// The same wall without its opening: what a pair sees when something hides the opening.
fn door_ahead_hidden(c: &Calibration, vel: BodyVelocity) -> FlowField {
    Scene { rects: vec![Rect::frontal(2.6, [-10.0, 10.0], Z), Rect::floor()] }.flow(c, 16, 16, vel, DT).field
}

#[test]
fn a_pair_with_too_short_a_baseline_adds_nothing_to_the_window() {
    // the nominal C310 at 1280x720: fx = 1272 px, so the default 8 px asks for 6.3 mm of travel
    let c = Calibration::nominal_c310();
    let (vel, slow) = (BodyVelocity::new(0.5, 0.0), BodyVelocity::new(0.05, 0.0));
    let ahead = temporal::Motion { yaw_rad: 0.0, dt: DT, forward_m: 0.0 };
    let mut offis = Offis::new(OffisParams::default()).unwrap();
    let door = door_ahead(&c, vel);
    for _ in 0..2 {
        assert_eq!(offis.step_filtered(&door, vel, DT, &c, ahead).unwrap().tpo.shape, TpoShape::Door);
    }
    // two pairs of 5 mm (6.4 px) of a wall: the door's evidence is all there is
    let short = door_ahead_hidden(&c, slow);
    for _ in 0..2 {
        let p = offis.step_filtered(&short, slow, DT, &c, ahead).unwrap();
        assert_eq!((p.tpo.shape, offis.attributes().filtered.steps), (TpoShape::Door, 2));
    }
    // the wall with a pair of 5 cm counts
    let long = door_ahead_hidden(&c, vel);
    offis.step_filtered(&long, vel, DT, &c, ahead).unwrap();
    assert_eq!(offis.attributes().filtered.steps, 3);
    // with the gate off the short pair counts too
    let mut params = OffisParams::default();
    params.temporal.min_baseline_px = 0.0;
    let mut open = Offis::new(params).unwrap();
    open.step_filtered(&door, vel, DT, &c, ahead).unwrap();
    open.step_filtered(&short, slow, DT, &c, ahead).unwrap();
    assert_eq!(open.attributes().filtered.steps, 2);
}

#[test]
fn the_baseline_gate_scales_with_the_resolution() {
    // 1 cm of travel: 12.7 px at 1280x720 (counts), 3.2 px at 320x180 (does not)
    let vel = BodyVelocity::new(0.1, 0.0);
    let ahead = temporal::Motion { yaw_rad: 0.0, dt: DT, forward_m: 0.0 };
    for (size, steps) in [((1280, 720), 1), ((320, 180), 0)] {
        let c = Calibration::nominal_c310().scaled_to(size.0, size.1);
        let mut offis = Offis::new(OffisParams::default()).unwrap();
        offis.step_filtered(&door_ahead(&c, vel), vel, DT, &c, ahead).unwrap();
        assert_eq!(offis.attributes().filtered.steps, steps, "{size:?}");
    }
}

#[test]
fn step_filtered_holds_the_class_through_one_odd_pair_and_forgets_it_after_a_turn() {
    let c = Calibration::nominal_c310();
    let vel = BodyVelocity::new(0.5, 0.0);
    let (door, hidden) = (door_ahead(&c, vel), door_ahead_hidden(&c, vel));
    let ahead = temporal::Motion { yaw_rad: 0.0, dt: DT, forward_m: 0.0 };
    let mut offis = Offis::new(OffisParams::default()).unwrap();
    for _ in 0..4 {
        assert_eq!(offis.step_filtered(&door, vel, DT, &c, ahead).unwrap().tpo.shape, TpoShape::Door);
    }
    let p = offis.step_filtered(&hidden, vel, DT, &c, ahead).unwrap();
    let a = offis.attributes();
    assert_eq!((a.decision.shape, a.filtered.steps), (TpoShape::Wall, 5), "this pair alone says wall");
    assert_eq!(p.tpo.shape, TpoShape::Door, "one odd pair does not flip the class: {:?}", a.filtered);
    assert!((p.tpo.distance_m.unwrap() - 2.45).abs() < 0.02, "the distance is this pair's wall: {:?}", p.tpo);
    // standing still measures nothing and adds nothing: the evidence of the view still holds
    let still = offis.step_filtered(&door, BodyVelocity::ZERO, DT, &c, ahead).unwrap();
    assert_eq!((still.tpo.shape, offis.attributes().filtered.steps), (TpoShape::Door, 5));
    // the pair alone measured nothing: its profile is the carried one, the last pair's wall
    let a = offis.attributes();
    assert_eq!((a.decision.shape, a.carried_bins), (TpoShape::Wall, 16), "{:?}", a.features);
    assert_eq!(offis.step_filtered(&door, vel, DT, &c, ahead).unwrap().tpo.shape, TpoShape::Door);
    assert_eq!(offis.attributes().filtered.steps, 6);
    // after a turn of 0.3 rad the wall in view decides alone
    let turned = temporal::Motion { yaw_rad: 0.3, dt: DT, forward_m: 0.0 };
    let p = offis.step_filtered(&hidden, vel, DT, &c, turned).unwrap();
    assert_eq!((p.tpo.shape, offis.attributes().filtered.steps), (TpoShape::Wall, 1));
    // Offis::step is the pair alone, whatever came before
    for _ in 0..4 {
        offis.step_filtered(&door, vel, DT, &c, ahead).unwrap();
    }
    assert_eq!(offis.step(&hidden, vel, DT, &c).unwrap().tpo.shape, TpoShape::Wall);
}

#[test]
fn a_turn_on_the_spot_sees_the_wall_through_the_carried_profile() {
    let c = Calibration::nominal_c310();
    let vel = BodyVelocity::new(0.5, 0.0);
    let wall = door_ahead_hidden(&c, vel);
    let ahead = temporal::Motion { yaw_rad: 0.0, dt: DT, forward_m: 0.0 };
    let turn = 0.3;
    let on_the_spot = temporal::Motion { yaw_rad: turn, dt: DT, forward_m: 0.0 };
    for carry_m in [0.6, 0.0] {
        let mut params = OffisParams::default();
        params.temporal.carry_m = carry_m;
        let mut offis = Offis::new(params).unwrap();
        let mut d0 = None;
        for _ in 0..3 {
            let p = offis.step_filtered(&wall, vel, DT, &c, ahead).unwrap();
            assert_eq!(p.tpo.shape, TpoShape::Wall);
            d0 = p.tpo.distance_m;
        }
        // no translation, and a turn past the window's 0.25 rad: the window has forgotten the view
        let p = offis.step_filtered(&wall, BodyVelocity::ZERO, DT, &c, on_the_spot).unwrap();
        let a = offis.attributes();
        assert_eq!(a.filtered.steps, 0);
        if carry_m == 0.0 {
            assert_eq!((p.tpo.shape, a.carried_bins), (TpoShape::None, 0), "nothing is carried when off");
            continue;
        }
        // the points turned 0.3 rad to the right: the bins left of 0.47 − 0.3 rad stay empty
        assert!((8..16).contains(&a.carried_bins), "{} bins carried", a.carried_bins);
        assert_eq!(p.tpo.shape, TpoShape::Wall, "{:?}", a.features);
        // closed form: the wall is d0 + mount x ahead of the robot's origin; the camera, turned
        // about the origin, meets it along its axis at (D − mount x · cos θ) / cos θ
        let (mx, d) = (c.mount.x_m, d0.unwrap() + c.mount.x_m);
        let expect = (d - mx * turn.cos()) / turn.cos();
        let got = p.tpo.distance_m.unwrap();
        assert!((got - expect).abs() < 0.03, "wall at {got:.3} m along the turned axis, expected {expect:.3}");
    }
    // the paper classifier decides from the flow's structures: nothing is decided on the spot
    let params = OffisParams { classifier: ClassifierKind::Paper, ..OffisParams::default() };
    let mut paper = Offis::new(params).unwrap();
    for _ in 0..3 {
        paper.step_filtered(&wall, vel, DT, &c, ahead).unwrap();
    }
    let p = paper.step_filtered(&wall, BodyVelocity::ZERO, DT, &c, on_the_spot).unwrap();
    assert_eq!((p.tpo.shape, paper.attributes().carried_bins), (TpoShape::None, 0));
}

#[test]
fn a_short_pair_after_a_turn_reports_the_carried_profile_not_its_own() {
    // 5 mm of travel at 1280x720 (6.4 px) is below the 8 px gate: the pair measures nothing
    let c = Calibration::nominal_c310();
    let (vel, slow) = (BodyVelocity::new(0.5, 0.0), BodyVelocity::new(0.05, 0.0));
    let ahead = temporal::Motion { yaw_rad: 0.0, dt: DT, forward_m: 0.0 };
    let turned = temporal::Motion { yaw_rad: 0.3, dt: DT, forward_m: 0.0 };
    for (carry_m, expect) in [(0.6, TpoShape::Wall), (0.0, TpoShape::None)] {
        let mut params = OffisParams::default();
        params.temporal.carry_m = carry_m;
        let mut offis = Offis::new(params).unwrap();
        for _ in 0..3 {
            offis.step_filtered(&door_ahead_hidden(&c, vel), vel, DT, &c, ahead).unwrap();
        }
        // the short pair sees the door's opening; the window forgot the wall in the turn
        let p = offis.step_filtered(&door_ahead(&c, slow), slow, DT, &c, turned).unwrap();
        let a = offis.attributes();
        assert_eq!((p.tpo.shape, a.filtered.steps), (expect, 0), "carry {carry_m}: {:?}", a.filtered);
        assert_eq!(a.carried_bins, 0, "the short pair's own profile is not filled");
    }
}

#[test]
fn the_temporal_table_is_range_checked() {
    let ok = OffisParams::default();
    assert!(ok.validate().is_ok());
    let bad = |temporal| match (OffisParams { temporal, ..OffisParams::default() }).validate().unwrap_err() {
        crate::config_error::ConfigError::Invalid { field, .. } => field,
        e => panic!("{e}"),
    };
    let t = temporal::TemporalParams::default();
    assert_eq!(bad(temporal::TemporalParams { window: 0, ..t }), "offis.temporal.window");
    assert_eq!(bad(temporal::TemporalParams { decay: 1.5, ..t }), "offis.temporal.decay");
    assert_eq!(bad(temporal::TemporalParams { max_age_s: 0.0, ..t }), "offis.temporal.max_turn_rad");
    assert_eq!(bad(temporal::TemporalParams { min_baseline_px: -1.0, ..t }), "offis.temporal.min_baseline_px");
    for none_weight in [0.0, 1.5, f64::NAN] {
        assert_eq!(bad(temporal::TemporalParams { none_weight, ..t }), "offis.temporal.none_weight");
    }
    let parsed: OffisParams = toml::from_str("[temporal]\nwindow = 1\n").unwrap();
    assert_eq!((parsed.temporal.window, parsed.temporal.decay), (1, 0.8));
}

#[test]
fn the_flow_measures_the_odometrys_yaw_error() {
    // driving 0.4 m/s while turning 0.3 rad/s, a wall 3 m ahead and the floor; the odometry
    // says the turn rate was off by ±0.02 rad/s (2 mrad over the pair, 0.7 px at 320 px wide)
    let c = calib(0.1);
    let truth = BodyVelocity::new(0.4, 0.3);
    let pair = wall_3m_and_floor().flow(&c, 16, 16, truth, DT);
    let cam = PinholeCamera::new(&c, 1280, 720);
    let blocks = || pair.field.vectors.iter().filter(|f| f.valid()).map(|f| [f.x, f.y, f.u, f.v].map(f64::from));
    for bias in [0.02, -0.02, 0.0] {
        let odo = BodyVelocity::new(0.4, 0.3 - bias);
        let fix = super::geometry::yaw_correction(&cam, odo, DT, blocks(), &mut Vec::new()).unwrap();
        assert!((fix - bias * DT).abs() < 1e-4, "bias {bias}: correction {fix}, want {}", bias * DT);
    }
    // standing still there is no focus of expansion to measure it against
    let still = Scene::default().flow(&c, 16, 16, BodyVelocity::new(0.0, 0.3), DT);
    let blocks = still.field.vectors.iter().map(|f| [f.x, f.y, f.u, f.v].map(f64::from));
    assert_eq!(super::geometry::yaw_correction(&cam, BodyVelocity::new(0.0, 0.3), DT, blocks, &mut Vec::new()), None);
}

#[test]
fn the_flow_takes_one_encoder_tick_of_turn_rate_out_of_the_depth() {
    // A base that derives its turn rate from encoder ticks over 20 ms reports it in steps of one
    // tick of difference between the wheels: 0.1 mm over a 0.33 m wheel base, 15 mrad/s, here
    // 1.5 mrad over the pair (1.9 px at 1280 px wide). Driving 0.3 m/s while turning 0.1 rad/s
    // past a wall 3 m ahead and the floor, the odometry says one such step too much.
    let c = calib(0.1);
    let truth = BodyVelocity::new(0.3, 0.1);
    let pair = wall_3m_and_floor().flow(&c, 16, 16, truth, DT);
    let odo = BodyVelocity::new(0.3, 0.1 + 1e-4 / 0.33 / 0.02);
    // the located points with the radial flow the obstacle memory takes (1.2 px), and how many
    // of them lie within 15 % of their true range
    let points = |yaw_fix_max_rad: f64| {
        let depth = DepthParams { yaw_fix_max_rad, ..DepthParams::default() };
        let mut offis = Offis::new(OffisParams { depth, ..OffisParams::default() }).unwrap();
        offis.step(&pair.field, odo, DT, &c).unwrap();
        let (mut n, mut good) = (0, 0);
        for (l, t) in offis.located.iter().zip(&pair.truth) {
            if let (Some(l), Some(t)) = (l, t)
                && l.radial_px >= 1.2
            {
                n += 1;
                good += usize::from((l.forward.hypot(l.left) / t[0].hypot(t[1]) - 1.0).abs() <= 0.15);
            }
        }
        (good, n)
    };
    let (good, n) = points(DepthParams::default().yaw_fix_max_rad);
    assert!(n >= 100 && good == n, "with the fix (the default): {good} of {n} within 15 %");
    let (good, n) = points(0.0);
    assert!(n >= 100 && 2 * good < n, "without the fix: {good} of {n} within 15 %");
}

fn run_paper(scene: &Scene, vel: BodyVelocity) -> (Perception, Attributes) {
    let c = calib(0.0);
    let pair = scene.flow(&c, 16, 16, vel, DT);
    let params = OffisParams { classifier: ClassifierKind::Paper, ..OffisParams::default() };
    let mut offis = Offis::new(params).unwrap();
    let p = offis.step(&pair.field, vel, DT, &c).unwrap();
    (p, offis.attributes().clone())
}

#[test]
fn the_paper_classifier_reads_fig_7_as_a_door() {
    // Fig. 7 ("coping with a door"), eq. (11): the outer columns marked; the walls beside the
    // opening face the camera (tilts 1), the opening is deeper than them
    for vel in [BodyVelocity::new(0.5, 0.0), BodyVelocity::new(0.5, 0.25)] {
        let (p, a) = run_paper(&door(), vel);
        assert_eq!(p.rough, [[1, 0, 0, 1]; 4], "{vel:?}");
        let f = a.paper;
        assert_eq!(f.rough_inner, 0.0, "{vel:?}: {f:?}");
        assert!((f.tilt_left - 1.0).abs() < 0.05 && (f.tilt_right - 1.0).abs() < 0.05, "{vel:?}: {f:?}");
        assert!(f.tilt_centre < 0.5, "{vel:?}: {f:?}");
        assert_eq!(p.tpo.shape, TpoShape::Door, "{vel:?}: {f:?} {:?}", a.decision);
        assert!(p.tpo.confidence > 0.9, "{:?}", p.tpo);
        assert!(!p.obstacle.present, "{:?}", p.obstacle);
    }
}

#[test]
fn the_paper_classifier_reads_fig_8_as_a_corridor_with_an_obstacle() {
    // Fig. 8, eq. (12): the side walls recede towards a far centre; the box low on the left is
    // the obstacle, located by the zoom of Fig. 6 in the bottom-left cells of the fine structure
    let mut want = [[1, 0, 0, 0, 0, 0, 0, 1]; 8];
    want[6][1] = 1;
    want[7][1] = 1;
    for vel in [BodyVelocity::new(0.5, 0.0), BodyVelocity::new(0.5, -0.2)] {
        let (p, a) = run_paper(&corridor_with_box(), vel);
        assert_eq!(p.fine, want, "{vel:?}: rough {:?}", p.rough);
        let f = a.paper;
        assert!(f.tilt_left > 1.2 && f.tilt_right > 1.2 && f.tilt_centre < 0.3, "{vel:?}: {f:?}");
        assert_eq!(p.tpo.shape, TpoShape::Corridor, "{vel:?}: {f:?} {:?}", a.decision);
        let o = p.obstacle;
        assert!(o.present, "{vel:?}: {o:?}");
        let [r, c] = o.cell.unwrap();
        assert!(r >= 5 && c <= 1, "{vel:?}: cell {r},{c}");
        // the box face is 2.0 m ahead of the camera at frame B, 0.5–1.0 m to the left
        let d = o.distance_m.unwrap();
        assert!((2.0..2.4).contains(&d), "{vel:?}: {d}");
        assert!(o.bearing_rad.unwrap() > 0.0, "{vel:?}: {o:?}");
    }
}

#[test]
fn the_classifier_is_a_config_value() {
    let p: OffisParams = toml::from_str("classifier = \"paper\"\n").unwrap();
    assert_eq!(p.classifier, ClassifierKind::Paper);
    assert_eq!(OffisParams::default().classifier, ClassifierKind::Flownav);
    let e = toml::from_str::<OffisParams>("classifier = \"papr\"\n").unwrap_err().to_string();
    assert!(e.contains("classifier") && e.contains("paper") && e.contains("flownav"), "{e}");
}
