//! Closed-form flow fields of scenes made of planar rectangles, for tests and benchmarks of
//! OFFIS without images: every block centre's ray is cast into the scene at frame A, the hit
//! point is re-projected from the camera's pose at frame B, and the difference is the exact
//! motion field (no noise, no matching). Rays that hit nothing see a point at infinity, which
//! moves only with the rotation. The robot's motion between the frames is integrated
//! numerically here, independently of [`super::geometry::FrameMotion`], so that tests compare
//! two derivations.

use super::geometry::{PinholeCamera, robot_from_optical, rot_z};
use crate::flow::{FlowField, FlowVector, Validity};
use hal::{BodyVelocity, Calibration};

/// A planar rectangle in the robot frame at frame A (x ahead, y left, z up; origin on the floor
/// between the wheels): the points of the plane through `point` with normal `normal` that lie
/// inside the axis-aligned box `[min, max]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rect {
    pub point: [f64; 3],
    pub normal: [f64; 3],
    pub min: [f64; 3],
    pub max: [f64; 3],
}

const BIG: f64 = 1e6;

impl Rect {
    /// A plane facing the robot at `x`, spanning `y` (left..right as min..max) and `z`.
    pub fn frontal(x: f64, y: [f64; 2], z: [f64; 2]) -> Self {
        Self { point: [x, 0.0, 0.0], normal: [1.0, 0.0, 0.0], min: [x - 1e-9, y[0], z[0]], max: [x + 1e-9, y[1], z[1]] }
    }

    /// A plane parallel to the heading at lateral offset `y`, spanning `x` and `z`.
    pub fn side(y: f64, x: [f64; 2], z: [f64; 2]) -> Self {
        Self { point: [0.0, y, 0.0], normal: [0.0, 1.0, 0.0], min: [x[0], y - 1e-9, z[0]], max: [x[1], y + 1e-9, z[1]] }
    }

    /// The floor (z = 0), unbounded.
    pub fn floor() -> Self {
        Self { point: [0.0; 3], normal: [0.0, 0.0, 1.0], min: [-BIG, -BIG, -1e-9], max: [BIG, BIG, 1e-9] }
    }

    /// A vertical plane through `(x, y)` turned by `yaw` from frontal (positive: its left part
    /// is nearer), bounded by `box_min`, `box_max`.
    pub fn vertical(x: f64, y: f64, yaw: f64, box_min: [f64; 3], box_max: [f64; 3]) -> Self {
        Self { point: [x, y, 0.0], normal: [yaw.cos(), yaw.sin(), 0.0], min: box_min, max: box_max }
    }

    fn hit(&self, origin: [f64; 3], dir: [f64; 3]) -> Option<f64> {
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let den = dot(self.normal, dir);
        if den.abs() < 1e-12 {
            return None;
        }
        let s = dot(self.normal, [0, 1, 2].map(|i| self.point[i] - origin[i])) / den;
        let p = [0, 1, 2].map(|i| origin[i] + s * dir[i]);
        (s > 1e-9 && (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])).then_some(s)
    }
}

/// A scene: the rectangles in view.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Scene {
    pub rects: Vec<Rect>,
}

/// One synthetic frame pair.
#[derive(Clone, Debug)]
pub struct SyntheticPair {
    pub field: FlowField,
    /// Per block: the point its ray hits, relative to camera B's optical centre in the robot
    /// axes at frame B (forward, left, up), m; `None` where the ray hits nothing.
    pub truth: Vec<Option<[f64; 3]>>,
}

/// Robot pose `(x, y, yaw)` after driving at `vel` for `dt` from the origin, by 10 000 midpoint steps.
fn integrate(vel: BodyVelocity, dt: f64) -> (f64, f64, f64) {
    let n = 10_000;
    let h = dt / n as f64;
    let (mut x, mut y, mut yaw) = (0.0f64, 0.0f64, 0.0f64);
    for _ in 0..n {
        let mid = yaw + 0.5 * vel.omega * h;
        x += vel.v * h * mid.cos();
        y += vel.v * h * mid.sin();
        yaw += vel.omega * h;
    }
    (x, y, yaw)
}

impl Scene {
    /// The nearest hit of the ray from `origin` along `dir` (robot frame), as the ray parameter.
    fn cast(&self, origin: [f64; 3], dir: [f64; 3]) -> Option<f64> {
        self.rects.iter().filter_map(|r| r.hit(origin, dir)).min_by(f64::total_cmp)
    }

    /// The exact flow field on a `rows × cols` grid of blocks (centres spread uniformly over
    /// the calibration's image) for the robot driving at `vel` for `dt`.
    pub fn flow(&self, calib: &Calibration, rows: usize, cols: usize, vel: BodyVelocity, dt: f64) -> SyntheticPair {
        let (w, h) = (calib.camera.width as usize, calib.camera.height as usize);
        let cam = PinholeCamera::new(calib, w, h);
        let c = robot_from_optical(cam.pitch_rad);
        let to_robot = |v: [f64; 3]| [0, 1, 2].map(|i| c[i][0] * v[0] + c[i][1] * v[1] + c[i][2] * v[2]);
        let to_optical = |v: [f64; 3]| [0, 1, 2].map(|i| c[0][i] * v[0] + c[1][i] * v[1] + c[2][i] * v[2]);
        let m = cam.mount_m;
        let (bx, by, byaw) = integrate(vel, dt);
        let rb = rot_z(byaw);
        let rbm = [0, 1, 2].map(|i| rb[i][0] * m[0] + rb[i][1] * m[1] + rb[i][2] * m[2]);
        let cam_b = [bx + rbm[0], by + rbm[1], rbm[2]];
        // world (robot-A) vector → robot-B axes: Rz(−yaw)
        let world_to_b = |v: [f64; 3]| [0, 1, 2].map(|i| rb[0][i] * v[0] + rb[1][i] * v[1] + rb[2][i] * v[2]);
        let mut vectors = Vec::with_capacity(rows * cols);
        let mut truth = Vec::with_capacity(rows * cols);
        for r in 0..rows {
            for col in 0..cols {
                let x = (col as f64 + 0.5) * w as f64 / cols as f64 - 0.5;
                let y = (r as f64 + 0.5) * h as f64 / rows as f64 - 0.5;
                let dir = to_robot(cam.ray(x, y));
                let (end, t) = match self.cast(m, dir) {
                    Some(s) => {
                        let p = [0, 1, 2].map(|i| m[i] + s * dir[i]);
                        let rel_b = world_to_b([0, 1, 2].map(|i| p[i] - cam_b[i]));
                        (cam.project(to_optical(rel_b)), Some(rel_b))
                    }
                    None => (cam.project(to_optical(world_to_b(dir))), None),
                };
                let (u, v, validity) = match end {
                    Some([ex, ey]) => ((ex - x) as f32, (ey - y) as f32, Validity::Valid),
                    None => (0.0, 0.0, Validity::OutOfFrame),
                };
                vectors.push(FlowVector { x: x as f32, y: y as f32, u, v, validity, cost: 0.0 });
                truth.push(t);
            }
        }
        SyntheticPair { field: FlowField { rows, cols, width: w, height: h, vectors }, truth }
    }
}
