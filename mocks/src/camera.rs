//! The camera in the world: where the optical centre is for a robot pose (from the
//! calibration's mount), the optical-frame ↔ world transforms, and [`RenderedCamera`], the
//! simulated camera that implements `hal::Camera` by rendering from a pose source.

use crate::render::{Effects, Renderer};
use crate::world::Pose;
use hal::{Calibration, Frame, LumaImage};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

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

/// Why a [`RenderedCamera`] cannot deliver a frame.
#[derive(Debug, thiserror::Error)]
pub enum RenderedCameraError {
    #[error("the simulated camera's pose source has ended (the simulation stopped)")]
    PoseSourceEnded,
}

impl hal::Error for RenderedCameraError {
    fn kind(&self) -> hal::ErrorKind {
        hal::ErrorKind::Disconnected
    }
}

/// How a [`RenderedCamera`] paces and stamps its frames.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Pacing {
    /// Wait for the wall clock like a real webcam; stamps are monotonic ns since creation
    /// (or from the clock given with [`RenderedCamera::with_clock`]).
    RealTime,
    /// Deliver at once; stamps are `seq / fps` seconds (offline rendering, tests).
    Simulated,
}

/// A simulated camera: renders the world from the pose its source reports at each capture.
/// `flownav sim` drives the runtime's control loop with it (simulated pacing, frames stamped
/// with the simulation's clock through [`RenderedCamera::with_clock`]).
///
/// Motion blur (see [`Effects::blur_samples`]) spans the pose of the previous capture to the
/// current one, i.e. a shutter open for the whole frame interval.
pub struct RenderedCamera {
    renderer: Arc<Renderer>,
    pose: Box<dyn FnMut() -> Option<Pose> + Send>,
    clock: Option<Box<dyn FnMut() -> u64 + Send>>,
    effects: Effects,
    fps: f64,
    pacing: Pacing,
    seq: u64,
    last_pose: Option<Pose>,
    started: Instant,
    next_due: Instant,
}

impl RenderedCamera {
    /// A camera at `fps` frames/s whose pose comes from `pose` (`None` ends the stream).
    pub fn new(
        renderer: Arc<Renderer>,
        fps: f64,
        pacing: Pacing,
        effects: Effects,
        pose: impl FnMut() -> Option<Pose> + Send + 'static,
    ) -> Self {
        let now = Instant::now();
        Self {
            renderer,
            pose: Box::new(pose),
            clock: None,
            effects,
            fps: if fps.is_finite() && fps > 0.0 { fps } else { 30.0 },
            pacing,
            seq: 0,
            last_pose: None,
            started: now,
            next_due: now,
        }
    }

    /// A camera that follows a pose shared with the simulated base.
    pub fn with_shared_pose(
        renderer: Arc<Renderer>,
        fps: f64,
        pacing: Pacing,
        effects: Effects,
        pose: Arc<Mutex<Pose>>,
    ) -> Self {
        Self::new(renderer, fps, pacing, effects, move || Some(*pose.lock().unwrap_or_else(|e| e.into_inner())))
    }

    /// Stamps frames with this clock (ns) instead of the camera's own, e.g. the runtime's
    /// monotonic control clock.
    pub fn with_clock(mut self, clock: impl FnMut() -> u64 + Send + 'static) -> Self {
        self.clock = Some(Box::new(clock));
        self
    }

    pub fn calibration(&self) -> &Calibration {
        self.renderer.calibration()
    }
}

impl hal::Camera for RenderedCamera {
    type Error = RenderedCameraError;

    fn capture(&mut self) -> Result<Frame, Self::Error> {
        let period = Duration::from_secs_f64(1.0 / self.fps);
        if self.pacing == Pacing::RealTime {
            let now = Instant::now();
            if self.next_due > now {
                std::thread::sleep(self.next_due - now);
            }
            self.next_due = self.next_due.max(now) + period;
        }
        let pose = (self.pose)().ok_or(RenderedCameraError::PoseSourceEnded)?;
        let from = self.last_pose.unwrap_or(pose);
        let mut image = LumaImage::default();
        self.renderer.render_frame(from, pose, &self.effects, self.seq, &mut image);
        let t_ns = match (&mut self.clock, self.pacing) {
            (Some(clock), _) => clock(),
            (None, Pacing::RealTime) => self.started.elapsed().as_nanos() as u64,
            (None, Pacing::Simulated) => (self.seq as f64 * 1e9 / self.fps).round() as u64,
        };
        let frame = Frame { seq: self.seq, t_ns, image };
        self.seq += 1;
        self.last_pose = Some(pose);
        Ok(frame)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hal::Camera;

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

    #[test]
    fn rendered_camera_follows_the_shared_pose() {
        let calib = Calibration::nominal_c310().scaled_to(160, 90);
        let world = crate::World::office();
        let renderer = Arc::new(Renderer::new(&world, &calib));
        let pose = Arc::new(Mutex::new(world.start));
        let mut cam = RenderedCamera::with_shared_pose(
            renderer.clone(),
            10.0,
            Pacing::Simulated,
            Effects::default(),
            pose.clone(),
        );
        let f0 = cam.capture().unwrap();
        assert_eq!((f0.seq, f0.t_ns), (0, 0));
        assert_eq!(f0.image, renderer.render(world.start));
        let moved = world.start.advance(0.5, 0.0, 1.0);
        *pose.lock().unwrap() = moved;
        let f1 = cam.capture().unwrap();
        assert_eq!((f1.seq, f1.t_ns), (1, 100_000_000));
        assert_eq!(f1.image, renderer.render(moved));
        let mut ended = RenderedCamera::new(renderer, 10.0, Pacing::Simulated, Effects::default(), || None);
        assert!(matches!(ended.capture(), Err(RenderedCameraError::PoseSourceEnded)));
    }
}
