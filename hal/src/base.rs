//! The motor-base trait: body-velocity set-points in, odometry and status out.

use crate::error::Error;
use crate::motion::{BodyVelocity, Odometry};

/// Health flags a base reports (FNP/1 STATUS, Kobuki sensor data).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BaseStatus {
    /// Host monotonic time when the status arrived, ns.
    pub t_ns: u64,
    pub battery_v: Option<f64>,
    pub bumper: bool,
    pub estop: bool,
    pub stopped_by_watchdog: bool,
    pub motor_fault: bool,
    pub cliff: bool,
    pub wheel_drop: bool,
}

/// Something the base told the host.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum BaseEvent {
    Odometry(Odometry),
    Status(BaseStatus),
}

/// A differential-drive base.
///
/// `set_velocity` records the latest command: the driver itself repeats it to the hardware at
/// its fixed rate (≥ 20 Hz), so the caller only calls it when the command changes. `stop`
/// commands zero velocity at once. Dropping a driver stops the base.
pub trait MotorBase: Send {
    type Error: Error;

    fn set_velocity(&mut self, cmd: BodyVelocity) -> Result<(), Self::Error>;

    fn stop(&mut self) -> Result<(), Self::Error>;

    /// The next event, waiting at most `timeout`; `Ok(None)` when none arrived in time.
    fn next_event(&mut self, timeout: std::time::Duration) -> Result<Option<BaseEvent>, Self::Error>;
}
