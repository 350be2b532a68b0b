//! Ground truth for a rendered frame: the TPO class in view by the geometric definitions of
//! DESIGN.md (all thresholds in [`tpo`]), the nearest obstacle in view, and the exact motion
//! field between two poses (from the depth map and the camera motion).
//!
//! All distances and bearings are measured from the camera's optical centre in the floor plane
//! (what the camera can measure), bearings in rad, positive to the left (REP-103).

use crate::camera::CameraPose;
use crate::render::{DepthMap, Renderer, SurfaceKind};
use crate::world::{Face, Pose, World, cross, dist};
use hal::Calibration;
use hal::motion::wrap_angle;
use serde::{Deserialize, Serialize};

/// The TPO definitions' thresholds (DESIGN.md, "Two-plane objects"), in one place.
///
/// - `wall`: the surface straight ahead (along the heading) is a wall plane within
///   [`RANGE_M`] whose normal is within [`WALL_FACING_MAX_RAD`] of the heading, and no door or
///   corner is in view.
/// - `corner`: a vertical edge where two wall planes meet at an angle (their directions differ
///   by at least [`CORNER_MIN_ANGLE_RAD`]; concave or convex, including T-junctions) is in the
///   field of view within [`RANGE_M`], unoccluded, with both planes visible.
/// - `door`: a door opening (≥ [`DOOR_MIN_WIDTH_M`]; world validation enforces it) has both
///   jambs in the field of view within [`RANGE_M`], unoccluded, in a wall facing the camera
///   within [`WALL_FACING_MAX_RAD`].
/// - `corridor`: nothing within [`CORRIDOR_OPEN_AHEAD_M`] along the heading (obstacles aside),
///   and visible wall planes within [`RANGE_M`] both left and right of the heading, each
///   parallel to it within [`CORRIDOR_PARALLEL_MAX_RAD`].
/// - `none`: none of these.
///
/// When several hold, the first of corridor, door, corner, wall wins. Planes are probed at the
/// camera's height, so a door's lintel does not close the opening and obstacles are ignored.
///
/// The distance reported (along the heading, from the optical centre): wall — to the wall
/// straight ahead; door — to the door's centre; corner — to the edge; corridor — to the
/// nearest visible point of its side walls.
///
/// [`RANGE_M`]: tpo::RANGE_M
/// [`WALL_FACING_MAX_RAD`]: tpo::WALL_FACING_MAX_RAD
/// [`CORNER_MIN_ANGLE_RAD`]: tpo::CORNER_MIN_ANGLE_RAD
/// [`DOOR_MIN_WIDTH_M`]: tpo::DOOR_MIN_WIDTH_M
/// [`CORRIDOR_OPEN_AHEAD_M`]: tpo::CORRIDOR_OPEN_AHEAD_M
/// [`CORRIDOR_PARALLEL_MAX_RAD`]: tpo::CORRIDOR_PARALLEL_MAX_RAD
pub mod tpo {
    /// A wall or door faces the camera when its normal is within ±45° of the heading.
    pub const WALL_FACING_MAX_RAD: f64 = std::f64::consts::FRAC_PI_4;
    /// Corridor walls are parallel to the heading within ±15°.
    pub const CORRIDOR_PARALLEL_MAX_RAD: f64 = 15.0 * std::f64::consts::PI / 180.0;
    /// A corridor is open ahead: no wall within 3 m along the heading.
    pub const CORRIDOR_OPEN_AHEAD_M: f64 = 3.0;
    /// Nothing beyond 5 m counts.
    pub const RANGE_M: f64 = 5.0;
    /// A door opening is at least 0.7 m wide.
    pub const DOOR_MIN_WIDTH_M: f64 = 0.7;
    /// Two wall segments whose directions differ by less than this are one plane (not a corner).
    pub const CORNER_MIN_ANGLE_RAD: f64 = 20.0 * std::f64::consts::PI / 180.0;
    /// Rays of the horizontal probe fan across the field of view.
    pub const FAN_RAYS: usize = 241;
}

/// The TPO classes (same names as `flownav::perception::TpoShape`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TpoClass {
    Wall,
    Corner,
    Door,
    Corridor,
    #[default]
    None,
}

/// The TPO in view.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TpoTruth {
    pub shape: TpoClass,
    /// Distance along the heading to it (see [`tpo`]), m; `None` for `none`.
    pub distance_m: Option<f64>,
    /// Free distance along the heading to the first wall (obstacles aside), m; `None` when
    /// no wall is on the heading line at all.
    pub ahead_m: Option<f64>,
    /// Name of the door when the shape is `door`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub door: Option<String>,
}

/// The nearest obstacle (box, cylinder) visible in the image.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ObstacleTruth {
    pub present: bool,
    /// Horizontal distance from the optical centre to its nearest visible point, m.
    pub distance_m: Option<f64>,
    /// Bearing of that point, rad, positive to the left.
    pub bearing_rad: Option<f64>,
    /// Its name in the world file.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
}

/// Everything known about one frame.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameTruth {
    pub pose: Pose,
    pub tpo: TpoTruth,
    pub obstacle: ObstacleTruth,
}

/// Computes ground truth for one world and camera.
pub struct GroundTruth {
    world: World,
    calib: Calibration,
    faces: Vec<Face>,
    corners: Vec<CornerVertex>,
    /// A low-resolution renderer for the surface-id image the obstacle truth comes from.
    ids: Renderer,
    ids_calib: Calibration,
}

#[derive(Clone, Copy, Debug)]
struct CornerVertex {
    p: [f64; 2],
    planes: [(usize, usize); 2],
}

impl GroundTruth {
    pub fn new(world: &World, calib: &Calibration) -> Self {
        let w = calib.camera.width.min(320);
        let h = ((calib.camera.height as f64 * w as f64 / calib.camera.width as f64).round() as u32).max(1);
        let ids_calib = calib.scaled_to(w, h);
        Self {
            world: world.clone(),
            calib: calib.clone(),
            faces: world.faces(),
            corners: corner_vertices(world),
            ids: Renderer::new(world, &ids_calib),
            ids_calib,
        }
    }

    /// TPO and nearest obstacle for a robot at `pose`.
    pub fn frame(&self, pose: Pose) -> FrameTruth {
        FrameTruth { pose, tpo: self.tpo(pose), obstacle: self.obstacle(pose) }
    }

    /// The nearest visible obstacle, from a low-resolution surface-id render.
    pub fn obstacle(&self, pose: Pose) -> ObstacleTruth {
        let (ids, depth) = self.ids.render_surfaces(pose);
        let cam = CameraPose::of_robot(pose, &self.ids_calib);
        let c = self.ids_calib.camera;
        let mut best: Option<(f64, f64, SurfaceKind)> = None;
        for v in 0..depth.height {
            for u in 0..depth.width {
                let kind = self.ids.surface_kind(ids[v * depth.width + u]);
                if !kind.is_obstacle() {
                    continue;
                }
                let z = depth.at(u, v) as f64;
                let p = cam.world_from_optical([(u as f64 - c.cx) / c.fx * z, (v as f64 - c.cy) / c.fy * z, z]);
                let d = [p[0] - cam.position[0], p[1] - cam.position[1]];
                let range = d[0].hypot(d[1]);
                if best.is_none_or(|b| range < b.0) {
                    best = Some((range, wrap_angle(d[1].atan2(d[0]) - pose.yaw), kind));
                }
            }
        }
        match best {
            None => ObstacleTruth::default(),
            Some((range, bearing, kind)) => {
                let name = match kind {
                    SurfaceKind::Box(i) => self.world.boxes[i].name.clone(),
                    SurfaceKind::Cylinder(i) => self.world.cylinders[i].name.clone(),
                    _ => String::new(),
                };
                ObstacleTruth {
                    present: true,
                    distance_m: Some(range),
                    bearing_rad: Some(bearing),
                    name: Some(name).filter(|n| !n.is_empty()),
                }
            }
        }
    }

    /// The TPO class in view by the definitions in [`tpo`].
    pub fn tpo(&self, pose: Pose) -> TpoTruth {
        let cam = CameraPose::of_robot(pose, &self.calib);
        let c = [cam.position[0], cam.position[1]];
        let probe = cam.position[2];
        let faces: Vec<&Face> = self.faces.iter().filter(|f| f.z0 <= probe && probe <= f.z1).collect();
        let heading = [pose.yaw.cos(), pose.yaw.sin()];
        let forward = |p: [f64; 2]| (p[0] - c[0]) * heading[0] + (p[1] - c[1]) * heading[1];
        let cast = |b: f64| cast(c, pose.yaw + b, &faces);
        let left_edge = self.calib.bearing_of_column(-0.5);
        let right_edge = self.calib.bearing_of_column(self.calib.camera.width as f64 - 0.5);
        let in_fov = |p: [f64; 2]| {
            let b = wrap_angle((p[1] - c[1]).atan2(p[0] - c[0]) - pose.yaw);
            b <= left_edge && b >= right_edge
        };
        let visible = |p: [f64; 2]| {
            let d = dist(c, p);
            d <= tpo::RANGE_M
                && in_fov(p)
                && cast(wrap_angle((p[1] - c[1]).atan2(p[0] - c[0]) - pose.yaw)).is_none_or(|(r, _)| r >= d - 0.02)
        };
        let ahead = cast(0.0);
        let ahead_m = ahead.map(|(r, _)| r);
        // The probe fan.
        let n = tpo::FAN_RAYS;
        let hits: Vec<(f64, f64, &Face)> = (0..n)
            .filter_map(|k| {
                let b = right_edge + (left_edge - right_edge) * k as f64 / (n - 1) as f64;
                cast(b).filter(|(r, _)| *r <= tpo::RANGE_M).map(|(r, f)| (b, r, f))
            })
            .collect();
        let plane_dir = |f: &Face| {
            let e = [f.b[0] - f.a[0], f.b[1] - f.a[1]];
            let l = e[0].hypot(e[1]);
            [e[0] / l, e[1] / l]
        };
        let facing = |f: &Face| {
            // Angle between the heading and the wall's normal: |sin| of heading vs wall direction.
            let d = plane_dir(f);
            cross(d, heading).abs() >= tpo::WALL_FACING_MAX_RAD.cos()
        };
        let mut out = TpoTruth { ahead_m, ..TpoTruth::default() };

        // Corridor.
        if ahead_m.is_none_or(|a| a > tpo::CORRIDOR_OPEN_AHEAD_M) {
            let parallel = |f: &Face| cross(plane_dir(f), heading).abs() <= tpo::CORRIDOR_PARALLEL_MAX_RAD.sin();
            let side = |left: bool| {
                hits.iter()
                    .filter(|(b, _, f)| (*b > 0.0) == left && parallel(f))
                    .map(|(b, r, _)| r * b.cos())
                    .fold(None, |m: Option<f64>, x| Some(m.map_or(x, |m| m.min(x))))
            };
            if let (Some(l), Some(r)) = (side(true), side(false)) {
                out.shape = TpoClass::Corridor;
                out.distance_m = Some(l.min(r));
                return out;
            }
        }
        // Door.
        let mut best_door: Option<(f64, String)> = None;
        for w in &self.world.walls {
            let mut along0 = 0.0;
            for s in w.points.windows(2) {
                let len = dist(s[0], s[1]);
                let at = |t: f64| [s[0][0] + (s[1][0] - s[0][0]) * t / len, s[0][1] + (s[1][1] - s[0][1]) * t / len];
                let e = [(s[1][0] - s[0][0]) / len, (s[1][1] - s[0][1]) / len];
                for d in &w.doors {
                    let (t0, t1) = (d.at - d.width / 2.0 - along0, d.at + d.width / 2.0 - along0);
                    if t0 < -1e-9 || t1 > len + 1e-9 || d.width < tpo::DOOR_MIN_WIDTH_M || d.height < probe {
                        continue;
                    }
                    let (j0, j1) = (at(t0), at(t1));
                    let facing_ok = cross(e, heading).abs() >= tpo::WALL_FACING_MAX_RAD.cos();
                    if facing_ok && visible(j0) && visible(j1) {
                        let centre = at((t0 + t1) / 2.0);
                        let fwd = forward(centre);
                        if fwd > 0.0 && best_door.as_ref().is_none_or(|(b, _)| fwd < *b) {
                            best_door = Some((fwd, d.name.clone()));
                        }
                    }
                }
                along0 += len;
            }
        }
        if let Some((fwd, name)) = best_door {
            out.shape = TpoClass::Door;
            out.distance_m = Some(fwd);
            out.door = Some(name).filter(|n| !n.is_empty());
            return out;
        }
        // Corner.
        let plane_seen = |plane: (usize, usize)| hits.iter().any(|(_, _, f)| (f.wall, f.segment) == plane);
        let corner = self
            .corners
            .iter()
            .filter(|v| visible(v.p) && plane_seen(v.planes[0]) && plane_seen(v.planes[1]))
            .map(|v| forward(v.p))
            .filter(|f| *f > 0.0)
            .fold(None, |m: Option<f64>, x| Some(m.map_or(x, |m| m.min(x))));
        if let Some(fwd) = corner {
            out.shape = TpoClass::Corner;
            out.distance_m = Some(fwd);
            return out;
        }
        // Wall.
        if let Some((r, f)) = ahead
            && r <= tpo::RANGE_M
            && facing(f)
        {
            out.shape = TpoClass::Wall;
            out.distance_m = Some(r);
        }
        out
    }
}

/// The nearest face hit by the horizontal ray from `c` at plan angle `angle`.
fn cast<'a>(c: [f64; 2], angle: f64, faces: &[&'a Face]) -> Option<(f64, &'a Face)> {
    let d = [angle.cos(), angle.sin()];
    let mut best: Option<(f64, &Face)> = None;
    for f in faces {
        let e = [f.b[0] - f.a[0], f.b[1] - f.a[1]];
        let den = cross(d, e);
        if den.abs() < 1e-12 {
            continue;
        }
        let ac = [f.a[0] - c[0], f.a[1] - c[1]];
        let s = cross(ac, e) / den;
        let t = cross(ac, d) / den;
        if s > 1e-9 && (-1e-9..=1.0 + 1e-9).contains(&t) && best.is_none_or(|(b, _)| s < b) {
            best = Some((s, *f));
        }
    }
    best
}

/// Where two wall planes meet at an angle: interior polyline vertices, and polyline ends that
/// touch another wall (L- and T-junctions).
fn corner_vertices(world: &World) -> Vec<CornerVertex> {
    let min_sin = tpo::CORNER_MIN_ANGLE_RAD.sin();
    let dir = |a: [f64; 2], b: [f64; 2]| {
        let l = dist(a, b);
        [(b[0] - a[0]) / l, (b[1] - a[1]) / l]
    };
    let mut out = Vec::new();
    for (wi, w) in world.walls.iter().enumerate() {
        let p = &w.points;
        let nseg = p.len() - 1;
        for k in 1..nseg {
            if cross(dir(p[k - 1], p[k]), dir(p[k], p[k + 1])).abs() >= min_sin
                || dir(p[k - 1], p[k]).iter().zip(dir(p[k], p[k + 1])).map(|(a, b)| a * b).sum::<f64>() < 0.0
            {
                out.push(CornerVertex { p: p[k], planes: [(wi, k - 1), (wi, k)] });
            }
        }
        // Closed polyline: the first point is also a vertex.
        if nseg >= 2 && dist(p[0], p[nseg]) < 0.01 && cross(dir(p[nseg - 1], p[nseg]), dir(p[0], p[1])).abs() >= min_sin
        {
            out.push(CornerVertex { p: p[0], planes: [(wi, nseg - 1), (wi, 0)] });
        }
        // Open ends touching another wall.
        if dist(p[0], p[nseg]) >= 0.01 {
            for (end, seg) in [(p[0], 0usize), (p[nseg], nseg - 1)] {
                let my = dir(p[seg], p[seg + 1]);
                for (wj, other) in world.walls.iter().enumerate() {
                    for (sj, s) in other.points.windows(2).enumerate() {
                        if wj == wi && sj == seg {
                            continue;
                        }
                        if crate::world::point_segment_distance(end, s[0], s[1]) < 0.01
                            && cross(my, dir(s[0], s[1])).abs() >= min_sin
                        {
                            out.push(CornerVertex { p: end, planes: [(wi, seg), (wj, sj)] });
                        }
                    }
                }
            }
        }
    }
    out
}

/// The exact image motion of every pixel of frame A into frame B: pixel (u, v) of A, back-
/// projected with its depth, moved with the camera from pose A to pose B, re-projected.
/// Pixels without depth (sky) or that end behind camera B hold `NaN`.
#[derive(Clone, Debug, PartialEq)]
pub struct MotionField {
    pub width: usize,
    pub height: usize,
    /// (Δu, Δv) per pixel, row-major, pixels.
    pub data: Vec<[f32; 2]>,
}

/// The motion field from robot pose `from` (whose depth map is `depth_from`) to `to`.
pub fn motion_field(calib: &Calibration, depth_from: &DepthMap, from: Pose, to: Pose) -> MotionField {
    let a = CameraPose::of_robot(from, calib);
    let b = CameraPose::of_robot(to, calib);
    let c = calib.camera;
    let mut data = vec![[f32::NAN; 2]; depth_from.width * depth_from.height];
    for v in 0..depth_from.height {
        for u in 0..depth_from.width {
            let z = depth_from.at(u, v) as f64;
            if !z.is_finite() {
                continue;
            }
            let pa = [(u as f64 - c.cx) / c.fx * z, (v as f64 - c.cy) / c.fy * z, z];
            let pb = b.optical_from_world(a.world_from_optical(pa));
            if let Some([ub, vb]) = calib.project(pb) {
                data[v * depth_from.width + u] = [(ub - u as f64) as f32, (vb - v as f64) as f32];
            }
        }
    }
    MotionField { width: depth_from.width, height: depth_from.height, data }
}

impl MotionField {
    /// The motion of pixel (u, v), `None` where unknown.
    pub fn at(&self, u: usize, v: usize) -> Option<[f64; 2]> {
        let m = self.data[v * self.width + u];
        (m[0].is_finite() && m[1].is_finite()).then_some([m[0] as f64, m[1] as f64])
    }

    /// Bilinear sample at sub-pixel (x, y); `None` when any of the four pixels is unknown or
    /// outside.
    pub fn sample(&self, x: f64, y: f64) -> Option<[f64; 2]> {
        if !(x >= 0.0 && y >= 0.0 && x <= (self.width - 1) as f64 && y <= (self.height - 1) as f64) {
            return None;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let (a, b, c, d) = (self.at(x0, y0)?, self.at(x1, y0)?, self.at(x0, y1)?, self.at(x1, y1)?);
        let lerp = |p: f64, q: f64, t: f64| p + (q - p) * t;
        Some([0, 1].map(|k| lerp(lerp(a[k], b[k], fx), lerp(c[k], d[k], fx), fy)))
    }

    /// Mean motion over the `block × block` pixels centred at (cx, cy): what a block matcher
    /// measures for a smooth field. `None` when under half of the block is known.
    pub fn block_mean(&self, cx: f64, cy: f64, block: usize) -> Option<[f64; 2]> {
        let x0 = (cx - block as f64 / 2.0 + 0.5).round() as isize;
        let y0 = (cy - block as f64 / 2.0 + 0.5).round() as isize;
        let (mut sum, mut n) = ([0.0; 2], 0usize);
        for y in y0..y0 + block as isize {
            for x in x0..x0 + block as isize {
                if x < 0 || y < 0 || x as usize >= self.width || y as usize >= self.height {
                    continue;
                }
                if let Some(m) = self.at(x as usize, y as usize) {
                    sum[0] += m[0];
                    sum[1] += m[1];
                    n += 1;
                }
            }
        }
        (n * 2 >= block * block).then(|| [sum[0] / n as f64, sum[1] / n as f64])
    }
}

/// Centres of a `rows × cols` grid of equal cells over a `width × height` image (pixel-centre
/// coordinates: cell c spans columns [c·W/cols, (c+1)·W/cols), its centre is the middle).
pub fn block_centres(width: usize, height: usize, rows: usize, cols: usize) -> Vec<[f64; 2]> {
    let mut out = Vec::with_capacity(rows * cols);
    for r in 0..rows {
        for c in 0..cols {
            out.push([
                (c as f64 + 0.5) * width as f64 / cols as f64 - 0.5,
                (r as f64 + 0.5) * height as f64 / rows as f64 - 0.5,
            ]);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn office_start_sees_door_d9() {
        let w = World::office();
        let calib = Calibration::nominal_c310();
        let t = GroundTruth::new(&w, &calib).tpo(w.start);
        assert_eq!(t.shape, TpoClass::Door, "{t:?}");
        assert_eq!(t.door.as_deref(), Some("D9"));
        // The door plane is 2.5 m ahead of the robot, 2.4 m of the camera.
        assert!((t.distance_m.unwrap() - 2.4).abs() < 1e-9);
    }

    #[test]
    fn office_corridor_is_a_corridor_and_obstacles_are_seen() {
        let w = World::office();
        let calib = Calibration::nominal_c310();
        let gt = GroundTruth::new(&w, &calib);
        // In the corridor at x = 20 facing west towards the boxes and the person.
        let f = gt.frame(Pose::new(20.0, 0.0, std::f64::consts::PI));
        assert_eq!(f.tpo.shape, TpoClass::Corridor, "{f:?}");
        assert!(f.obstacle.present);
        // The nearest is box1 at x = 17 (its near face at x = 17.25; camera at x = 19.9).
        assert_eq!(f.obstacle.name.as_deref(), Some("box1"));
        let d = f.obstacle.distance_m.unwrap();
        assert!((2.6..2.8).contains(&d), "{d}");
        // box1 sits north of the centre line: to the robot's right when facing west.
        assert!(f.obstacle.bearing_rad.unwrap() < 0.0);
    }

    #[test]
    fn block_centres_are_cell_middles() {
        let c = block_centres(512, 512, 16, 16);
        assert_eq!(c[0], [15.5, 15.5]);
        assert_eq!(c[17], [47.5, 47.5]);
    }
}
