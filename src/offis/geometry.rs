//! Camera geometry for OFFIS: removing the rotational flow of the robot's turn, the focus of
//! expansion, and depth from the translational flow (paper §2.2, "distance calculation").
//!
//! Frames: the optical frame (x right, y down, z forward) of the camera at the older frame A
//! is the reference; `R` is the orientation of the camera at the newer frame B in it and `t`
//! B's optical centre in it. The robot moves on the floor as a unicycle (odometry `v`, `omega`
//! held over the frame interval `dt`), the camera sits at the calibration's mount, pitched down
//! by `pitch_rad`; both are exact here, not small-angle approximations.
//!
//! De-rotation is exact for any rotation: the end point of a flow vector is a ray in B; turning
//! that ray by `R` expresses it in A's axes, and its projection is where the point would have
//! appeared had the camera only translated. What is left is the translational flow, radial
//! from the focus of expansion `e` (the projection of `t`). For a point at depth `Z` (along A's
//! axis) the translational flow is `Δp = (p − e) · t_z / (Z − t_z)`, so with `r = |p − e|`,
//! `ṙ = Δp · (p − e)/r` per frame interval, the time to contact in frame intervals is
//! `τ = r / ṙ = (Z − t_z) / t_z` and the depth *at the newer frame* is `Z_B = t_z · τ` where
//! `t_z ≈ v · dt` is the forward travel over the interval (`v · dt · cos(pitch)` for a straight
//! drive). This is exact for discrete motion, not only in the small-motion limit.

use hal::{BodyVelocity, Calibration};

type Mat3 = [[f64; 3]; 3];

fn mat_vec(m: &Mat3, x: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| m[i][0] * x[0] + m[i][1] * x[1] + m[i][2] * x[2])
}

fn mat_t_vec(m: &Mat3, x: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| m[0][i] * x[0] + m[1][i] * x[1] + m[2][i] * x[2])
}

fn mat_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut m = [[0.0; 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, x) in row.iter_mut().enumerate() {
            *x = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    m
}

fn transpose(a: &Mat3) -> Mat3 {
    let mut m = [[0.0; 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, x) in row.iter_mut().enumerate() {
            *x = a[j][i];
        }
    }
    m
}

/// The rotation about the robot's z axis (up) by `yaw`, in robot coordinates.
pub(crate) fn rot_z(yaw: f64) -> Mat3 {
    let (s, c) = yaw.sin_cos();
    [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
}

/// `robot_from_optical`: the columns are the optical x (right), y (down) and z (forward) axes in
/// robot coordinates (REP-103) for a camera pitched down by `pitch`.
pub(crate) fn robot_from_optical(pitch: f64) -> Mat3 {
    let (s, c) = pitch.sin_cos();
    [[0.0, -s, c], [-1.0, 0.0, 0.0], [0.0, -c, -s]]
}

/// Pinhole intrinsics at the flow field's image size plus the mount, all that OFFIS needs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PinholeCamera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub pitch_rad: f64,
    /// Camera centre in the robot frame (x ahead, y left, z up), m.
    pub mount_m: [f64; 3],
}

impl PinholeCamera {
    /// The calibration's camera at `width × height` (intrinsics scaled as
    /// [`Calibration::scaled_to`] does when the flow's frames differ from the calibrated size).
    pub fn new(calib: &Calibration, width: usize, height: usize) -> Self {
        let c = &calib.camera;
        let sx = width as f64 / c.width as f64;
        let sy = height as f64 / c.height as f64;
        Self {
            fx: c.fx * sx,
            fy: c.fy * sy,
            cx: (c.cx + 0.5) * sx - 0.5,
            cy: (c.cy + 0.5) * sy - 0.5,
            pitch_rad: calib.mount.pitch_rad,
            mount_m: [calib.mount.x_m, calib.mount.y_m, calib.mount.z_m],
        }
    }

    /// The ray through pixel `(x, y)`, optical frame, normalised to z = 1.
    pub fn ray(&self, x: f64, y: f64) -> [f64; 3] {
        [(x - self.cx) / self.fx, (y - self.cy) / self.fy, 1.0]
    }

    /// Projects an optical-frame point; `None` at or behind the camera.
    pub fn project(&self, p: [f64; 3]) -> Option<[f64; 2]> {
        (p[2] > 1e-12).then(|| [self.fx * p[0] / p[2] + self.cx, self.fy * p[1] / p[2] + self.cy])
    }

    /// Bearing of the ray through pixel `(x, y)` in the robot frame, rad, positive to the left.
    pub fn bearing(&self, x: f64, y: f64) -> f64 {
        let d = mat_vec(&robot_from_optical(self.pitch_rad), self.ray(x, y));
        d[1].atan2(d[0])
    }
}

/// The camera's motion between frame A and frame B from the odometry.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameMotion {
    /// Orientation of camera B in A's optical frame (`a_from_b`).
    pub rot: Mat3,
    /// Optical centre of camera B in A's optical frame, m.
    pub t: [f64; 3],
    /// Yaw turned over the interval, rad (positive = left).
    pub yaw: f64,
}

impl FrameMotion {
    /// Unicycle motion at constant `vel` over `dt`: the robot origin follows the arc
    /// `(v·sin ψ / ω, v·(1 − cos ψ) / ω)` with `ψ = ω·dt` (a straight line when ω = 0); the
    /// camera, mounted off the turning axis, also swings by `Rz(ψ)·m − m`.
    pub fn from_odometry(cam: &PinholeCamera, vel: BodyVelocity, dt: f64) -> Self {
        let yaw = vel.omega * dt;
        let (dx, dy) = if yaw.abs() < 1e-6 {
            // series of the arc, exact to O(ψ³)
            (vel.v * dt * (1.0 - yaw * yaw / 6.0), vel.v * dt * yaw / 2.0)
        } else {
            (vel.v * yaw.sin() / vel.omega, vel.v * (1.0 - yaw.cos()) / vel.omega)
        };
        let rz = rot_z(yaw);
        let m = cam.mount_m;
        let swung = mat_vec(&rz, m);
        let t_robot = [dx + swung[0] - m[0], dy + swung[1] - m[1], swung[2] - m[2]];
        let c = robot_from_optical(cam.pitch_rad);
        Self { rot: mat_mul(&transpose(&c), &mat_mul(&rz, &c)), t: mat_t_vec(&c, t_robot), yaw }
    }

    /// The focus of expansion (projection of the translation), pixels; `None` when the camera
    /// barely moves along its axis (`|t_z|` below 1 µm), where every ratio below is unstable.
    pub fn foe(&self, cam: &PinholeCamera) -> Option<[f64; 2]> {
        let t = self.t;
        (t[2].abs() > 1e-6).then(|| [cam.cx + cam.fx * t[0] / t[2], cam.cy + cam.fy * t[1] / t[2]])
    }

    /// Where a distant point seen at pixel `(x, y)` in frame A appears in frame B: the end of
    /// its rotational flow. `None` if it lies behind camera B.
    pub fn rotated(&self, cam: &PinholeCamera, x: f64, y: f64) -> Option<[f64; 2]> {
        cam.project(mat_t_vec(&self.rot, cam.ray(x, y)))
    }

    /// The translational part of the flow vector `(u, v)` at block centre `(x, y)`: its end
    /// point's ray turned into A's axes and re-projected, minus the start. `None` if that ray
    /// points behind the camera.
    pub fn derotate(&self, cam: &PinholeCamera, x: f64, y: f64, u: f64, v: f64) -> Option<[f64; 2]> {
        let ray_a = mat_vec(&self.rot, cam.ray(x + u, y + v));
        cam.project(ray_a).map(|[px, py]| [px - x, py - y])
    }
}

/// At least this many blocks must show a yaw error for [`yaw_correction`] to measure one.
pub const MIN_YAW_BLOCKS: usize = 16;

/// The correction to the odometry's yaw over a frame pair that the flow itself measures, rad
/// (positive = the camera turned further left than `vel` says).
///
/// The translational flow points away from the focus of expansion whatever the depth, so the
/// de-rotated flow's component across that direction is rotation the odometry got wrong (its
/// samples never cover the frame interval exactly, and a changing turn rate makes that a yaw
/// error; wheel slip) plus matching noise. With `a` that component at a block and `b` its change
/// per radian of yaw, the block says `−a/b`; the correction is the median over the blocks
/// where a yaw error shows (`|b|` at least a third of the focal length, so not on the horizontal
/// line through the focus of expansion) and farther than a tenth of the focal length from it.
/// `blocks`: `[x, y, u, v]` of the valid flow vectors, pixels; `votes`: scratch space (cleared
/// first), so that a step allocates nothing. `None` with fewer than [`MIN_YAW_BLOCKS`] such
/// blocks, or when the camera barely moves along its axis.
pub fn yaw_correction(
    cam: &PinholeCamera,
    vel: BodyVelocity,
    dt: f64,
    blocks: impl Iterator<Item = [f64; 4]>,
    votes: &mut Vec<f64>,
) -> Option<f64> {
    const EPS: f64 = 1e-3;
    let m0 = FrameMotion::from_odometry(cam, vel, dt);
    let m1 = FrameMotion::from_odometry(cam, BodyVelocity::new(vel.v, vel.omega + EPS / dt), dt);
    let foe = m0.foe(cam)?;
    votes.clear();
    votes.extend(blocks.filter_map(|[x, y, u, v]| {
        let (rx, ry) = (x - foe[0], y - foe[1]);
        let r = rx.hypot(ry);
        if r < 0.1 * cam.fx {
            return None;
        }
        let across = [-ry / r, rx / r];
        let (d0, d1) = (m0.derotate(cam, x, y, u, v)?, m1.derotate(cam, x, y, u, v)?);
        let a = d0[0] * across[0] + d0[1] * across[1];
        let b = ((d1[0] - d0[0]) * across[0] + (d1[1] - d0[1]) * across[1]) / EPS;
        (b.abs() >= cam.fx / 3.0).then_some(-a / b).filter(|d| d.is_finite())
    }));
    if votes.len() < MIN_YAW_BLOCKS {
        return None;
    }
    let mid = votes.len() / 2;
    Some(*votes.select_nth_unstable_by(mid, f64::total_cmp).1)
}

/// Limits that keep depth-from-flow away from its ill-conditioned cases.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DepthParams {
    /// Below this speed (m/s) the robot is "not translating" and no distance is reported.
    pub min_speed_m_s: f64,
    /// Blocks closer to the focus of expansion than this fraction of the focal length are
    /// skipped (their radial flow vanishes and noise dominates τ).
    pub min_radius_frac: f64,
    /// Radial flow below this (pixels) means "too far to measure": no depth, not a guess.
    pub min_radial_px: f64,
    /// Depths beyond this (m) are dropped as unmeasurable.
    pub max_depth_m: f64,
    /// Located points lower than this above the floor (m) are floor, never an obstacle.
    pub floor_height_m: f64,
    /// The envelope profile, the plane fit and the obstacle decision use only blocks whose
    /// radial flow is at least this (pixels): with block-matching noise of ~0.1 px, depth is
    /// then good to ~30 %; below it, far floor near the horizon can pass for a near wall.
    /// They must also point away from the focus of expansion: the component across the radial
    /// direction at most half the radial one (random matches on noise, e.g. a bright sky, and
    /// aperture errors along stretched floor texture fail it).
    pub reliable_radial_px: f64,
    /// For the profile and the obstacle decision, blocks lower than `floor_rel · camera height`
    /// above the floor count as floor too: a floor block whose depth is off by a fraction `e`
    /// appears `e · camera height` above the floor, whatever its distance.
    pub floor_rel: f64,
    /// The odometry's yaw over a frame pair is corrected from the flow ([`yaw_correction`])
    /// when the correction is at most this, rad; 0: not corrected.
    pub yaw_fix_max_rad: f64,
}

impl Default for DepthParams {
    fn default() -> Self {
        Self {
            min_speed_m_s: 0.02,
            min_radius_frac: 0.02,
            min_radial_px: 0.05,
            max_depth_m: 30.0,
            floor_height_m: 0.1,
            reliable_radial_px: 0.3,
            floor_rel: 0.6,
            yaw_fix_max_rad: 0.005,
        }
    }
}

/// A point located from its flow, relative to camera B's optical centre in the robot frame at
/// the newer frame (REP-103), m.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Located {
    pub forward: f64,
    pub left: f64,
    pub up: f64,
    /// The radial (translational) flow it was located from, pixels per frame interval, and
    /// the size of the de-rotated flow's component across the radial direction (0 for a
    /// perfect measurement of a static point).
    pub radial_px: f64,
    pub tangential_px: f64,
}

impl Located {
    /// Horizontal range, m.
    pub fn range(&self) -> f64 {
        self.forward.hypot(self.left)
    }

    /// Bearing, rad, positive to the left.
    pub fn bearing(&self) -> f64 {
        self.left.atan2(self.forward)
    }
}

/// §2.2 distance from flow and velocity: time to contact `τ = r / ṙ` from the focus of expansion
/// `foe`, then depth `Z_B = t_z · τ` (module doc), then the 3D point in robot axes at frame B.
/// `(ut, vt)` is the *de-rotated* flow at block centre `(x, y)`. `None` when the block is within
/// `min_radius_frac · f` of the FOE, when the radial flow is below `min_radial_px` or points the
/// wrong way (contracting while driving forward), or when the depth exceeds `max_depth_m`.
pub fn locate(
    cam: &PinholeCamera,
    motion: &FrameMotion,
    foe: [f64; 2],
    p: &DepthParams,
    [x, y]: [f64; 2],
    [ut, vt]: [f64; 2],
) -> Option<Located> {
    let (rx, ry) = (x - foe[0], y - foe[1]);
    let r = rx.hypot(ry);
    if r < p.min_radius_frac * cam.fx.min(cam.fy) {
        return None;
    }
    let radial = (ut * rx + vt * ry) / r;
    if radial.abs() < p.min_radial_px {
        return None;
    }
    let depth = motion.t[2] * r / radial;
    if !(depth > 0.0 && depth <= p.max_depth_m) {
        return None;
    }
    // The point in (B's position, A's axes): depth along A's axis times the ray of the de-rotated end point.
    let ray = cam.ray(x + ut, y + vt);
    let in_b = mat_t_vec(&motion.rot, ray.map(|k| k * depth));
    let robot = mat_vec(&robot_from_optical(cam.pitch_rad), in_b);
    let tangential = ((ut * ry - vt * rx) / r).abs();
    Some(Located { forward: robot[0], left: robot[1], up: robot[2], radial_px: radial, tangential_px: tangential })
}
