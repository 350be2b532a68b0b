//! Differential-drive kinematics for the simulated bases: velocity and acceleration limits,
//! exact unicycle integration, wheel encoders with seeded noise, wheels that differ from their
//! nominal size ([`OdometryError`]), and a collision hook.
//!
//! The commanded body velocity is clamped to the limits, and the wheel-level velocity (what the
//! motor controller holds, in the firmware's nominal units) ramps towards it at the acceleration
//! limits. Encoders count that nominal wheel travel times `ticks_per_m`, each step's increment
//! scaled by `1 + noise·N(0,1)`. The true pose moves along the exact arc of the *true* body
//! velocity, which the odometry error derives from the wheel speeds, so dead reckoning from the
//! ticks drifts from the true pose as on a real base. Within a step the pose moves at the mean of
//! the old and new velocity, which is exact for a constant-acceleration straight ramp and for any
//! constant velocity.
//!
//! When the caller's collision test says the next pose is in collision, the base does not move,
//! its velocity drops to zero, its bumper is pressed and a new contact is counted. The bumper
//! stays pressed until the base has backed off [`BUMPER_TRAVEL_M`] from the obstacle.

use crate::faults::SimRng;
use crate::odometry_error::OdometryError;
use hal::BodyVelocity;
use hal::motion::wrap_angle;
use std::sync::Arc;

/// How far the base must move away from an obstacle before its bumper releases.
pub const BUMPER_TRAVEL_M: f64 = 0.01;

/// A planar pose in the world frame: metres, radians (counter-clockwise from +x).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pose {
    pub x: f64,
    pub y: f64,
    pub theta: f64,
}

impl Pose {
    pub fn new(x: f64, y: f64, theta: f64) -> Self {
        Self { x, y, theta }
    }
}

/// "Is the robot in collision at this pose?", supplied by whoever knows the world's geometry.
pub type CollisionFn = Arc<dyn Fn(&Pose) -> bool + Send + Sync>;

/// Velocity and acceleration limits of the base.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriveLimits {
    pub max_v: f64,
    pub max_omega: f64,
    pub max_accel: f64,
    pub max_alpha: f64,
}

impl Default for DriveLimits {
    fn default() -> Self {
        Self { max_v: 0.7, max_omega: 2.5, max_accel: 1.0, max_alpha: 4.0 }
    }
}

/// Geometry (nominal, as the firmware knows it), limits and odometry error of a simulated
/// differential-drive base.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DiffDriveParams {
    pub wheel_base_m: f64,
    pub ticks_per_m: f64,
    pub limits: DriveLimits,
    /// How the true wheels differ from the nominal ones, and the encoders' noise.
    pub error: OdometryError,
    pub seed: u64,
}

impl Default for DiffDriveParams {
    /// Exact wheels with 1 % encoder noise.
    fn default() -> Self {
        Self {
            wheel_base_m: 0.33,
            ticks_per_m: 10_000.0,
            limits: DriveLimits::default(),
            error: OdometryError { noise: 0.01, ..OdometryError::NONE },
            seed: 1,
        }
    }
}

/// Moves `pose` for `dt` seconds at constant body velocity (`v`, `omega`) along the exact arc.
pub fn integrate(pose: &Pose, v: f64, omega: f64, dt: f64) -> Pose {
    let th = pose.theta;
    let dth = omega * dt;
    let (dx, dy) = if dth.abs() < 1e-9 {
        // Second-order term keeps this consistent with the arc as omega -> 0.
        let c = v * dt;
        (c * (th + 0.5 * dth).cos(), c * (th + 0.5 * dth).sin())
    } else {
        let r = v / omega;
        (r * ((th + dth).sin() - th.sin()), -r * ((th + dth).cos() - th.cos()))
    };
    Pose { x: pose.x + dx, y: pose.y + dy, theta: wrap_angle(th + dth) }
}

/// The simulated drive train.
pub struct DiffDrive {
    params: DiffDriveParams,
    pose: Pose,
    velocity: BodyVelocity,
    left_ticks: f64,
    right_ticks: f64,
    rng: SimRng,
    collision: Option<CollisionFn>,
    bumper: bool,
    /// +1 when the contact is ahead, -1 behind.
    contact_dir: f64,
    collisions: u64,
}

impl std::fmt::Debug for DiffDrive {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DiffDrive")
            .field("pose", &self.pose)
            .field("velocity", &self.velocity)
            .field("bumper", &self.bumper)
            .field("collisions", &self.collisions)
            .finish_non_exhaustive()
    }
}

impl DiffDrive {
    pub fn new(params: DiffDriveParams) -> Self {
        Self {
            params,
            pose: Pose::default(),
            velocity: BodyVelocity::ZERO,
            left_ticks: 0.0,
            right_ticks: 0.0,
            rng: SimRng::new(params.seed),
            collision: None,
            bumper: false,
            contact_dir: 1.0,
            collisions: 0,
        }
    }

    pub fn params(&self) -> &DiffDriveParams {
        &self.params
    }

    /// The true pose (ground truth, for the renderer and for scoring).
    pub fn pose(&self) -> Pose {
        self.pose
    }

    pub fn set_pose(&mut self, pose: Pose) {
        self.pose = pose;
    }

    /// The wheel-level body velocity the motor controller holds (nominal units: what exact
    /// odometry would report; the true motion differs by the odometry error).
    pub fn velocity(&self) -> BodyVelocity {
        self.velocity
    }

    /// Cumulative encoder counts (left, right).
    pub fn ticks(&self) -> (i64, i64) {
        (self.left_ticks.floor() as i64, self.right_ticks.floor() as i64)
    }

    pub fn bumper(&self) -> bool {
        self.bumper
    }

    /// Contacts so far (each run of blocked steps counts once).
    pub fn collisions(&self) -> u64 {
        self.collisions
    }

    pub fn set_collision(&mut self, collision: Option<CollisionFn>) {
        self.collision = collision;
    }

    /// Advances `dt` seconds towards the commanded velocity.
    pub fn step(&mut self, cmd: BodyVelocity, dt: f64) {
        if dt <= 0.0 || !dt.is_finite() {
            return;
        }
        let lim = self.params.limits;
        let finite = |x: f64| if x.is_finite() { x } else { 0.0 };
        let v_cmd = finite(cmd.v).clamp(-lim.max_v, lim.max_v);
        let w_cmd = finite(cmd.omega).clamp(-lim.max_omega, lim.max_omega);
        let ramp = |cur: f64, target: f64, rate: f64| cur + (target - cur).clamp(-rate * dt, rate * dt);
        let v = ramp(self.velocity.v, v_cmd, lim.max_accel);
        let omega = ramp(self.velocity.omega, w_cmd, lim.max_alpha);
        let (v_mean, w_mean) = (0.5 * (self.velocity.v + v), 0.5 * (self.velocity.omega + omega));
        let half = 0.5 * self.params.wheel_base_m * w_mean;
        let (u_l, u_r) = (v_mean - half, v_mean + half);
        let (v_true, w_true) = self.params.error.true_body_velocity(u_l, u_r, self.params.wheel_base_m);
        let next = integrate(&self.pose, v_true, w_true, dt);
        if self.collision.as_ref().is_some_and(|hit| hit(&next)) {
            if !self.bumper {
                self.collisions += 1;
            }
            self.bumper = true;
            self.contact_dir = if v_mean < 0.0 { -1.0 } else { 1.0 };
            self.velocity = BodyVelocity::ZERO;
            return;
        }
        self.velocity = BodyVelocity::new(v, omega);
        self.pose = next;
        if self.bumper {
            let probe = integrate(&self.pose, self.contact_dir * BUMPER_TRAVEL_M, 0.0, 1.0);
            self.bumper = self.collision.as_ref().is_some_and(|hit| hit(&probe));
        }
        let sigma = self.params.error.noise;
        self.left_ticks += u_l * dt * self.params.ticks_per_m * (1.0 + sigma * self.rng.normal());
        self.right_ticks += u_r * dt * self.params.ticks_per_m * (1.0 + sigma * self.rng.normal());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn quiet() -> DiffDriveParams {
        DiffDriveParams {
            error: OdometryError::NONE,
            limits: DriveLimits { max_accel: 1e9, max_alpha: 1e9, ..Default::default() },
            ..Default::default()
        }
    }

    #[test]
    fn exact_arc_closes_a_circle() {
        // v = 0.5 m/s, omega = 0.5 rad/s: radius 1 m, a full circle in 4π s, any step size.
        let mut p = Pose::default();
        let steps = 1000;
        let dt = 4.0 * PI / steps as f64;
        for i in 0..steps {
            p = integrate(&p, 0.5, 0.5, dt);
            if i == steps / 4 - 1 {
                assert!((p.x - 1.0).abs() < 1e-9 && (p.y - 1.0).abs() < 1e-9, "{p:?}");
            }
        }
        assert!(p.x.abs() < 1e-9 && p.y.abs() < 1e-9 && p.theta.abs() < 1e-9, "{p:?}");
        // One big step equals many small ones.
        let one = integrate(&Pose::default(), 0.5, 0.5, 2.0 * PI);
        assert!((one.x - 0.0).abs() < 1e-12 && (one.y - 2.0).abs() < 1e-12);
    }

    #[test]
    fn straight_line_and_encoders() {
        let mut d = DiffDrive::new(quiet());
        for _ in 0..100 {
            d.step(BodyVelocity::new(0.3, 0.0), 0.01);
        }
        // The first step ramps from rest: it covers half a step's distance.
        assert!((d.pose().x - 0.2985).abs() < 1e-12 && d.pose().y.abs() < 1e-12, "{:?}", d.pose());
        let (l, r) = d.ticks();
        assert!((l - 2985).abs() <= 1 && (r - 2985).abs() <= 1, "{l} {r}");
    }

    #[test]
    fn turning_in_place_moves_the_wheels_opposite() {
        let mut d = DiffDrive::new(quiet());
        for _ in 0..100 {
            d.step(BodyVelocity::new(0.0, 1.0), 0.01);
        }
        assert!((d.pose().theta - 0.995).abs() < 1e-12);
        let (l, r) = d.ticks();
        // Each wheel travels theta * b/2 = 0.164175 m.
        assert!((l + 1642).abs() <= 1 && (r - 1641).abs() <= 1, "{l} {r}");
    }

    #[test]
    fn unequal_wheels_curve_a_straight_run_by_the_closed_form_radius() {
        let error = OdometryError { left: -0.01, right: 0.01, ..OdometryError::NONE };
        let mut d = DiffDrive::new(DiffDriveParams { error, ..quiet() });
        for _ in 0..1000 {
            d.step(BodyVelocity::new(0.5, 0.0), 0.01);
        }
        // Curvature (right − left)/b: an arc of radius 16.5 m to the left, centred on (0, R).
        let radius = 0.33 / 0.02;
        let p = d.pose();
        let arc = 0.5 * 10.0 - 0.5 * 0.5 * 0.01;
        assert!((p.theta - arc / radius).abs() < 1e-9, "{p:?}");
        assert!((p.x.hypot(p.y - radius) - radius).abs() < 1e-9, "{p:?}");
        assert!(p.y > 0.7, "{p:?}");
        // The encoders (nominal wheel travel) say the robot drove straight.
        let (l, r) = d.ticks();
        assert_eq!(l, r);
        assert!((l - 49_975).abs() <= 1, "{l}");
    }

    #[test]
    fn a_wide_wheel_base_and_slip_shorten_turns_the_encoders_do_not_see() {
        let error = OdometryError { wheelbase: 0.1, slip: 0.1, ..OdometryError::NONE };
        let mut d = DiffDrive::new(DiffDriveParams { error, ..quiet() });
        for _ in 0..100 {
            d.step(BodyVelocity::new(0.0, 1.0), 0.01);
        }
        // Nominal 0.995 rad; the wheels' arc spans a 10 % wider base and 10 % of it slips.
        assert!((d.pose().theta - 0.995 / 1.1 * 0.9).abs() < 1e-12, "{:?}", d.pose());
        let (l, r) = d.ticks();
        assert!((l + 1642).abs() <= 1 && (r - 1641).abs() <= 1, "{l} {r}");
    }

    #[test]
    fn limits_clamp_and_ramp() {
        let mut d = DiffDrive::new(DiffDriveParams { error: OdometryError::NONE, ..Default::default() });
        d.step(BodyVelocity::new(5.0, -10.0), 0.1);
        assert!((d.velocity().v - 0.1).abs() < 1e-12 && (d.velocity().omega + 0.4).abs() < 1e-12);
        for _ in 0..100 {
            d.step(BodyVelocity::new(5.0, -10.0), 0.1);
        }
        assert_eq!(d.velocity(), BodyVelocity::new(0.7, -2.5));
        d.step(BodyVelocity::new(f64::NAN, f64::INFINITY), 0.1);
        assert!(d.velocity().v.is_finite() && d.velocity().omega.is_finite());
    }

    #[test]
    fn encoder_noise_is_seeded_and_unbiased() {
        let run = |seed| {
            let mut d = DiffDrive::new(DiffDriveParams {
                seed,
                error: OdometryError { noise: 0.05, ..OdometryError::NONE },
                ..quiet()
            });
            for _ in 0..1000 {
                d.step(BodyVelocity::new(0.5, 0.0), 0.01);
            }
            d.ticks()
        };
        assert_eq!(run(7), run(7));
        assert_ne!(run(7), run(8));
        let (l, _) = run(7);
        // 5 m = 50000 ticks; 1000 increments of 5% noise: std ≈ 0.05·50/√1000·1000 ≈ 79 ticks.
        assert!((l - 50_000).abs() < 400, "{l}");
    }

    #[test]
    fn collision_stops_presses_bumper_and_counts_once() {
        let mut d = DiffDrive::new(quiet());
        d.set_collision(Some(Arc::new(|p: &Pose| p.x > 1.0)));
        for _ in 0..500 {
            d.step(BodyVelocity::new(0.5, 0.0), 0.01);
        }
        assert!(d.pose().x <= 1.0 && d.pose().x > 0.99);
        assert!(d.bumper());
        assert_eq!(d.velocity(), BodyVelocity::ZERO);
        assert_eq!(d.collisions(), 1);
        // Backing off more than the bumper travel releases it; driving in again is a second contact.
        d.step(BodyVelocity::new(-0.5, 0.0), 0.01);
        assert!(d.bumper());
        for _ in 0..10 {
            d.step(BodyVelocity::new(-0.5, 0.0), 0.01);
        }
        assert!(!d.bumper());
        for _ in 0..20 {
            d.step(BodyVelocity::new(0.5, 0.0), 0.01);
        }
        assert_eq!(d.collisions(), 2);
    }
}
