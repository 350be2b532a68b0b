//! The camera in the world: where the optical centre is for a robot pose (from the
//! calibration's mount) and the optical-frame ↔ world transforms.

use crate::world::Pose;
use hal::Calibration;

/// The camera's pose in the world: optical centre (plan x, y and height z, m), heading (the
/// robot's yaw) and downward pitch. The optical frame is x right, y down, z forward.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraPose {
    pub position: [f64; 3],
    pub yaw: f64,
    pub pitch: f64,
    fwd: [f64; 2],
    left: [f64; 2],
    cos_p: f64,
    sin_p: f64,
}

impl CameraPose {
    /// `world_from_camera` for a robot at `pose` with the calibration's mount
    /// (`robot_from_camera`: x_m ahead, y_m left, z_m up, pitch down).
    pub fn of_robot(pose: Pose, calib: &Calibration) -> Self {
        let m = calib.mount;
        let p = pose.transform([m.x_m, m.y_m]);
        Self::new([p[0], p[1], m.z_m], pose.yaw, m.pitch_rad)
    }

    pub fn new(position: [f64; 3], yaw: f64, pitch: f64) -> Self {
        let (s, c) = yaw.sin_cos();
        let (sin_p, cos_p) = pitch.sin_cos();
        Self { position, yaw, pitch, fwd: [c, s], left: [-s, c], cos_p, sin_p }
    }

    /// Exactly level (pitch 0): every pixel column has one horizontal direction.
    pub fn is_level(&self) -> bool {
        self.pitch == 0.0
    }

    /// World direction of the optical ray `(x_n, y_n, 1)`: its plan part and its vertical part.
    #[inline]
    pub fn direction(&self, xn: f64, yn: f64) -> ([f64; 2], f64) {
        let k = self.cos_p - yn * self.sin_p;
        ([-xn * self.left[0] + k * self.fwd[0], -xn * self.left[1] + k * self.fwd[1]], -self.sin_p - yn * self.cos_p)
    }

    /// A point in the optical frame → world (x, y, z).
    pub fn world_from_optical(&self, p: [f64; 3]) -> [f64; 3] {
        let (dh, dz) = self.direction(p[0] / p[2], p[1] / p[2]);
        [self.position[0] + p[2] * dh[0], self.position[1] + p[2] * dh[1], self.position[2] + p[2] * dz]
    }

    /// A world point → optical frame (x right, y down, z forward).
    pub fn optical_from_world(&self, w: [f64; 3]) -> [f64; 3] {
        let d = [w[0] - self.position[0], w[1] - self.position[1], w[2] - self.position[2]];
        let f = d[0] * self.fwd[0] + d[1] * self.fwd[1];
        let l = d[0] * self.left[0] + d[1] * self.left[1];
        // Optical axes in (forward, left, up) coordinates.
        let z = [self.cos_p, 0.0, -self.sin_p];
        let y = [-self.sin_p, 0.0, -self.cos_p];
        let v = [f, l, d[2]];
        [-l, y[0] * v[0] + y[2] * v[2], z[0] * v[0] + z[2] * v[2]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn optical_round_trip() {
        let cam = CameraPose::new([1.0, 2.0, 0.4], 0.7, 0.2);
        let p = [0.3, -0.2, 2.5];
        let w = cam.world_from_optical(p);
        let q = cam.optical_from_world(w);
        for k in 0..3 {
            assert!((p[k] - q[k]).abs() < 1e-12, "{p:?} {q:?}");
        }
        // Level camera facing +y: a point ahead and to the right (+x in the plan).
        let cam = CameraPose::new([0.0, 0.0, 0.4], std::f64::consts::FRAC_PI_2, 0.0);
        let o = cam.optical_from_world([1.0, 3.0, 0.4]);
        assert!((o[0] - 1.0).abs() < 1e-12 && o[1].abs() < 1e-12 && (o[2] - 3.0).abs() < 1e-12);
    }
}
