//! Canonical scenes built in code for labelled benchmarks (OFFIS accuracy): one TPO in front of
//! the camera at a chosen distance and angle, optionally with an obstacle.
//!
//! Geometry is given relative to the camera: its optical centre sits at the plan origin looking
//! along +x (`Scene::camera`), so "a wall at 2 m" means 2 m in front of the lens. Use
//! [`Scene::start`] to get the robot pose that puts the camera there for a calibration's mount.
//! Walls are 2.6 m high under a 2.6 m ceiling; `empty` has neither (open floor, sky).

use crate::world::{BoxObstacle, Cylinder, Door, Pose, Wall, World};
use hal::Calibration;
use std::collections::BTreeMap;

const HEIGHT: f64 = 2.6;
/// Length of the walls, m: long enough that their ends stay out of view.
const LONG: f64 = 20.0;

/// A world and where the camera stands in it.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    pub world: World,
    /// The camera's optical centre and heading on the plan (always the origin, facing +x).
    pub camera: Pose,
}

impl Scene {
    fn new(name: &str, walls: Vec<Wall>, ceiling: bool) -> Self {
        let world = World {
            name: name.into(),
            ceiling_height: ceiling.then_some(HEIGHT),
            walls,
            boxes: Vec::new(),
            cylinders: Vec::new(),
            places: BTreeMap::new(),
            start: Pose::default(),
            random: None,
            low_faces: Default::default(),
        };
        Self { world, camera: Pose::default() }
    }

    /// The robot pose that puts the camera (mount offset of `calib`) at [`Scene::camera`].
    pub fn start(&self, calib: &Calibration) -> Pose {
        let m = calib.mount;
        let p = self.camera.transform([-m.x_m, -m.y_m]);
        Pose::new(p[0], p[1], self.camera.yaw)
    }

    /// Adds a 0.4 × 0.4 × 0.5 m box whose nearest face centre is `distance_m` from the camera at
    /// `bearing_rad` (positive left), turned to face the camera.
    pub fn with_obstacle(mut self, distance_m: f64, bearing_rad: f64) -> Self {
        let r = distance_m + 0.2;
        self.world.boxes.push(BoxObstacle {
            name: format!("box{}", self.world.boxes.len() + 1),
            center: [r * bearing_rad.cos(), r * bearing_rad.sin()],
            size: [0.4, 0.4, 0.5],
            yaw: bearing_rad,
        });
        self
    }

    /// Adds a person (cylinder of radius 0.25 m, 1.7 m high) whose nearest point is
    /// `distance_m` from the camera at `bearing_rad`.
    pub fn with_person(mut self, distance_m: f64, bearing_rad: f64) -> Self {
        let r = distance_m + 0.25;
        self.world.cylinders.push(Cylinder {
            name: format!("person{}", self.world.cylinders.len() + 1),
            center: [r * bearing_rad.cos(), r * bearing_rad.sin()],
            radius: 0.25,
            height: 1.7,
        });
        self
    }
}

fn plain_wall(name: &str, points: Vec<[f64; 2]>) -> Wall {
    Wall { name: name.into(), points, height: HEIGHT, doors: Vec::new() }
}

/// A straight wall crossing the heading `distance_m` ahead, turned by `angle_rad` from frontal
/// (0 = facing the camera; positive turns its left end away).
pub fn wall(distance_m: f64, angle_rad: f64) -> Scene {
    let (s, c) = angle_rad.sin_cos();
    // Direction along the wall (from right to left as seen by the camera).
    let d = [-s, c];
    let p = [distance_m, 0.0];
    let a = [p[0] - d[0] * LONG / 2.0, p[1] - d[1] * LONG / 2.0];
    let b = [p[0] + d[0] * LONG / 2.0, p[1] + d[1] * LONG / 2.0];
    Scene::new("wall", vec![plain_wall("wall", vec![a, b])], true)
}

/// Two walls meeting at a vertical edge `distance_m` ahead on the heading. `angle_rad` is the
/// angle between them on the camera's side: below π a concave (inside) corner, above π a
/// convex (outside) corner; the corner's bisector points at the camera.
pub fn corner(distance_m: f64, angle_rad: f64) -> Scene {
    let v = [distance_m, 0.0];
    let half = angle_rad / 2.0;
    let len = 8.0;
    // Directions from the vertex: rotate "back towards the camera" (−x) by ±half.
    let l = [v[0] - len * half.cos(), v[1] + len * half.sin()];
    let r = [v[0] - len * half.cos(), v[1] - len * half.sin()];
    Scene::new("corner", vec![plain_wall("corner", vec![r, v, l])], true)
}

/// A frontal wall `distance_m` ahead with a centred door opening `width_m` wide (2 m high) and a
/// room behind it (back wall 3 m further).
pub fn door(width_m: f64, distance_m: f64) -> Scene {
    let front = Wall {
        name: "door wall".into(),
        points: vec![[distance_m, -LONG / 2.0], [distance_m, LONG / 2.0]],
        height: HEIGHT,
        doors: vec![Door { name: "D1".into(), at: LONG / 2.0, width: width_m, height: 2.0 }],
    };
    let back = plain_wall("room back", vec![[distance_m + 3.0, -LONG / 2.0], [distance_m + 3.0, LONG / 2.0]]);
    Scene::new("door", vec![front, back], true)
}

/// A corridor `width_m` wide along the heading, centred on the camera, starting 1 m behind it
/// and closed by an end wall `length_m` ahead.
pub fn corridor(width_m: f64, length_m: f64) -> Scene {
    let h = width_m / 2.0;
    Scene::new(
        "corridor",
        vec![
            plain_wall("left", vec![[-1.0, h], [length_m, h]]),
            plain_wall("right", vec![[-1.0, -h], [length_m, -h]]),
            plain_wall("end", vec![[length_m, -h], [length_m, h]]),
        ],
        true,
    )
}

/// Open floor, no walls, no ceiling.
pub fn empty() -> Scene {
    Scene::new("empty", Vec::new(), false)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scenes_are_valid_worlds() {
        for s in [
            wall(2.0, 0.3),
            corner(3.0, 1.5),
            corner(3.0, 4.5),
            door(0.9, 2.5),
            corridor(2.0, 8.0),
            empty().with_obstacle(1.5, 0.2).with_person(3.0, -0.3),
        ] {
            s.world.validate(&s.world.name).unwrap();
        }
    }

    #[test]
    fn start_puts_the_camera_at_the_origin() {
        let calib = Calibration::nominal_c310();
        let p = empty().start(&calib);
        let cam = crate::camera::CameraPose::of_robot(p, &calib);
        assert!(cam.position[0].abs() < 1e-12 && cam.position[1].abs() < 1e-12);
    }
}
