//! The simulated world against closed forms: renderer geometry and motion field, TPO ground
//! truth on canonical scenes, world-file errors, determinism.

use hal::{Calibration, LumaImage};
use mocks::scene;
use mocks::truth::{GroundTruth, TpoClass, motion_field};
use mocks::{Effects, Pose, Renderer, World, WorldError};
use std::f64::consts::FRAC_PI_2;

fn c310() -> Calibration {
    Calibration::nominal_c310()
}

mod geometry {
    use super::*;

    /// A frontal wall at Z, camera moving forward by d: every pixel on the wall moves by
    /// (u − cx, v − cy) · d / (Z − d), and its depth is Z.
    #[test]
    fn frontal_wall_motion_field_matches_closed_form() {
        let calib = c310();
        let (z, d) = (3.0, 0.1);
        let sc = scene::wall(z, 0.0);
        let from = sc.start(&calib);
        let to = from.advance(d, 0.0, 1.0);
        let depth = Renderer::new(&sc.world, &calib).depth(from);
        let field = motion_field(&calib, &depth, from, to);
        let c = calib.camera;
        for (u, v) in [(0usize, 0usize), (100, 50), (639, 359), (640, 360), (1279, 400), (900, 200), (10, 415)] {
            assert!((depth.at(u, v) as f64 - z).abs() < 1e-5, "depth at ({u},{v}) = {}", depth.at(u, v));
            let expect = [(u as f64 - c.cx) * d / (z - d), (v as f64 - c.cy) * d / (z - d)];
            let got = field.at(u, v).unwrap();
            assert!(
                (got[0] - expect[0]).abs() < 0.05 && (got[1] - expect[1]).abs() < 0.05,
                "({u},{v}): {got:?} vs {expect:?}"
            );
        }
    }

    /// The rendered texture is anchored to the wall: a 32×32 block of frame A is found in frame B
    /// at the closed-form displacement (to the nearest pixel).
    #[test]
    fn rendered_images_move_with_the_motion_field() {
        let calib = c310();
        let (z, d) = (2.0, 0.1);
        let sc = scene::wall(z, 0.0);
        let r = Renderer::new(&sc.world, &calib);
        let from = sc.start(&calib);
        let a = r.render(from);
        let b = r.render(from.advance(d, 0.0, 1.0));
        let c = calib.camera;
        for (u0, v0) in [(200usize, 120usize), (1000, 150), (600, 300)] {
            let (cu, cv) = (u0 as f64 + 15.5, v0 as f64 + 15.5);
            let expect = [(cu - c.cx) * d / (z - d), (cv - c.cy) * d / (z - d)];
            let best = best_match(&a, &b, u0, v0, 40);
            assert!(
                (best[0] as f64 - expect[0]).abs() <= 1.0 && (best[1] as f64 - expect[1]).abs() <= 1.0,
                "block at ({u0},{v0}) found at {best:?}, expected {expect:?}"
            );
        }
    }

    fn best_match(a: &LumaImage, b: &LumaImage, u0: usize, v0: usize, r: isize) -> [isize; 2] {
        let mut best = (u64::MAX, [0, 0]);
        for dy in -r..=r {
            for dx in -r..=r {
                let mut sad = 0u64;
                for y in 0..32 {
                    for x in 0..32 {
                        let pa = a.get(u0 + x, v0 + y) as i64;
                        let pb = b.get(((u0 + x) as isize + dx) as usize, ((v0 + y) as isize + dy) as usize) as i64;
                        sad += (pa - pb).unsigned_abs();
                    }
                }
                if sad < best.0 {
                    best = (sad, [dx, dy]);
                }
            }
        }
        best.1
    }

    /// A floor pixel at row v (below the horizon) has depth h · fy / (v − cy).
    #[test]
    fn floor_pixel_depth() {
        let calib = c310();
        let sc = scene::empty();
        let depth = Renderer::new(&sc.world, &calib).depth(sc.start(&calib));
        let c = calib.camera;
        for v in [400usize, 500, 719] {
            let expect = calib.mount.z_m * c.fy / (v as f64 - c.cy);
            for u in [0usize, 640, 1279] {
                assert!((depth.at(u, v) as f64 - expect).abs() < 1e-5 * expect, "({u},{v}) {}", depth.at(u, v));
            }
        }
    }

    /// A pitched camera: the floor depth follows from the tilted ray.
    #[test]
    fn pitched_floor_pixel_depth() {
        let mut calib = c310().scaled_to(320, 180);
        calib.mount.pitch_rad = 0.2;
        let sc = scene::empty();
        let depth = Renderer::new(&sc.world, &calib).depth(sc.start(&calib));
        let c = calib.camera;
        let v = 120usize;
        let yn = (v as f64 - c.cy) / c.fy;
        // Ray (x_n, y_n, 1) descends by sin p + y_n cos p per unit depth.
        let expect = calib.mount.z_m / (0.2f64.sin() + yn * 0.2f64.cos());
        assert!((depth.at(50, v) as f64 - expect).abs() < 1e-5 * expect, "{} vs {expect}", depth.at(50, v));
    }
}

mod ground_truth {
    use super::*;

    fn tpo(sc: &scene::Scene) -> mocks::truth::TpoTruth {
        let calib = c310();
        GroundTruth::new(&sc.world, &calib).tpo(sc.start(&calib))
    }

    #[test]
    fn canonical_scenes_have_their_class() {
        let t = tpo(&scene::wall(2.5, 0.0));
        assert_eq!(t.shape, TpoClass::Wall);
        assert!((t.distance_m.unwrap() - 2.5).abs() < 1e-9);
        let t = tpo(&scene::wall(2.5, 0.5));
        assert_eq!(t.shape, TpoClass::Wall, "turned 29°: still facing within ±45°");
        assert_eq!(tpo(&scene::wall(2.5, 1.0)).shape, TpoClass::None, "turned 57°: not facing");
        assert_eq!(tpo(&scene::wall(6.0, 0.0)).shape, TpoClass::None, "beyond 5 m");

        let t = tpo(&scene::corner(2.5, FRAC_PI_2));
        assert_eq!(t.shape, TpoClass::Corner);
        assert!((t.distance_m.unwrap() - 2.5).abs() < 1e-9);
        assert_eq!(tpo(&scene::corner(2.5, 3.0 * FRAC_PI_2)).shape, TpoClass::Corner, "convex");

        let t = tpo(&scene::corridor(2.0, 10.0));
        assert_eq!(t.shape, TpoClass::Corridor);
        // The side walls (±1 m) enter the view where the half field of view (26.7°) meets them.
        let half_fov = (640.0f64 / 1272.0).atan();
        assert!((t.distance_m.unwrap() - 1.0 / half_fov.tan()).abs() < 0.05, "{t:?}");
        assert_eq!(tpo(&scene::corridor(2.0, 2.5)).shape, TpoClass::Corner, "end within 3 m, its corners in view");
        assert_eq!(tpo(&scene::corridor(4.0, 2.5)).shape, TpoClass::Wall, "end within 3 m, corners out of view");

        let t = tpo(&scene::door(0.9, 2.5));
        assert_eq!(t.shape, TpoClass::Door);
        assert!((t.distance_m.unwrap() - 2.5).abs() < 1e-9);

        let t = tpo(&scene::empty());
        assert_eq!((t.shape, t.distance_m), (TpoClass::None, None));
    }

    #[test]
    fn nearest_obstacle_distance_and_bearing() {
        let calib = c310();
        let sc = scene::empty().with_obstacle(1.5, 0.2).with_person(3.0, -0.25);
        let o = GroundTruth::new(&sc.world, &calib).obstacle(sc.start(&calib));
        assert!(o.present);
        assert_eq!(o.name.as_deref(), Some("box1"));
        assert!((o.distance_m.unwrap() - 1.5).abs() < 0.01, "{o:?}");
        assert!((o.bearing_rad.unwrap() - 0.2).abs() < 0.01, "{o:?}");
        // Out of the field of view (60° left) it is not reported.
        let sc = scene::empty().with_obstacle(1.5, 1.05);
        assert!(!GroundTruth::new(&sc.world, &calib).obstacle(sc.start(&calib)).present);
    }
}

mod world_files {
    use super::*;

    const GOOD: &str = r#"
name = "t"
start = { x = 0.0, y = 0.0 }

[[walls]]
points = [[2.0, -3.0], [2.0, 3.0]]
doors = [{ name = "D1", at = 3.0, width = 0.9 }]
"#;

    fn err(text: &str) -> String {
        World::from_toml(text, "t.toml").unwrap_err().to_string()
    }

    #[test]
    fn good_file_parses() {
        let w = World::from_toml(GOOD, "t.toml").unwrap();
        assert_eq!(w.faces().len(), 3);
    }

    #[test]
    fn semantic_errors_name_line_and_field() {
        // The door table is on line 7.
        let e = err(&GOOD.replace("width = 0.9", "width = 7.5"));
        assert!(e.contains("line 7") && e.contains("walls[0].doors[0]") && e.contains("wider than its wall"), "{e}");
        let e = err(&GOOD.replace("width = 0.9", "width = 0.5"));
        assert!(e.contains("line 7") && e.contains("doors[0].width") && e.contains("0.7"), "{e}");
        let e = err(&GOOD.replace("[[2.0, -3.0], [2.0, 3.0]]", "[[2.0, -3.0], [2.0, -3.0], [2.0, 3.0]]"));
        assert!(e.contains("line 5") && e.contains("walls[0].points") && e.contains("zero length"), "{e}");
        let boxes = "\n[[boxes]]\ncenter = [1.0, 1.0]\nsize = [0.5, 0.5, 0.5]\n\n[[boxes]]\ncenter = [1.2, 1.2]\nsize = [0.5, 0.5, 0.5]\n";
        let e = err(&format!("{GOOD}{boxes}"));
        assert!(e.contains("line 13") && e.contains("boxes[1]") && e.contains("overlaps boxes[0]"), "{e}");
        let e = err(&format!("{GOOD}\n[[cylinders]]\ncenter = [2.1, 1.5]\nradius = 0.25\nheight = 1.7\n"));
        assert!(e.contains("cylinders[0]") && e.contains("overlaps wall"), "{e}");
    }

    #[test]
    fn syntax_errors_name_line_and_field() {
        let e = err(&GOOD.replace("width = 0.9", "widht = 0.9"));
        assert!(e.contains("line 7") && e.contains("widht"), "{e}");
        let e = err(&GOOD.replace("points = ", "points = 3 #"));
        assert!(e.contains("line 6"), "{e}");
        let e = err("name = \"x\"\n");
        assert!(e.contains("start"), "{e}");
        assert!(matches!(World::load("/nonexistent/w.toml"), Err(WorldError::Read { .. })));
    }

    #[test]
    fn random_placement_is_seeded() {
        let w = World::office();
        let a = w.with_random_obstacles(1).unwrap();
        assert_eq!(a, w.with_random_obstacles(1).unwrap());
        assert_ne!(a.boxes, w.with_random_obstacles(2).unwrap().boxes);
        assert_eq!((a.boxes.len(), a.cylinders.len()), (2, 1));
        let e = scene::empty().world.with_random_obstacles(1).unwrap_err().to_string();
        assert!(e.contains("[random]"), "{e}");
    }
}

mod determinism {
    use super::*;

    #[test]
    fn same_seed_same_bytes() {
        let calib = c310().scaled_to(640, 360);
        let w = World::office();
        let fx = Effects { noise_sigma: 2.0, seed: 42, gain: 0.9, offset: 5.0, blur_samples: 3 };
        let to = Pose { x: w.start.x, y: w.start.y + 0.05, yaw: w.start.yaw + 0.02 };
        let render = || {
            let mut img = LumaImage::default();
            Renderer::new(&w, &calib).render_frame(w.start, to, &fx, 9, &mut img);
            img
        };
        assert_eq!(render(), render());
    }
}
