//! [`RenderedCamera`], the simulated camera: it implements `hal::Camera` by rendering the world
//! from a pose source.

use crate::render::{Effects, Renderer};
use crate::world::Pose;
use hal::{Calibration, Frame, LumaImage};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

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
