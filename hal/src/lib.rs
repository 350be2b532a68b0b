//! # flownav-hal: the hardware boundary
//!
//! Everything that crosses between flownav's pure core and the hardware is defined here, so that
//! real drivers and the simulated ones in `mocks/` are interchangeable.
//!
//! | module | owns |
//! |---|---|
//! | [`image`] | [`LumaImage`], the 8-bit grey frame every stage works on, and [`Frame`] (image + capture time) |
//! | [`calib`] | [`Calibration`]: pinhole intrinsics, distortion, and where the camera sits on the robot (`calib/*.toml`) |
//! | [`lens`] | the plumb_bob lens model on normalized coordinates, its inverse, and the check that coefficients are a lens over an image |
//! | [`undistort`] | the plumb_bob lens model and its inverse, [`Undistorter`]: a distorted frame → the pinhole frame with the same K |
//! | [`motion`] | [`BodyVelocity`] (a set-point or a measurement, REP-103), [`Odometry`], [`motion::wrap_angle`] |
//! | [`error`] | [`ErrorKind`]: what the runtime does about a hardware error (reconnect, stop, skip, report) |
//! | [`camera`] | the [`Camera`] trait and the monotonic clock frames are stamped with |
//! | [`v4l2`] | the V4L2 camera (`/dev/videoN`): the `[camera]` config table, device probing and listing, capture |
//! | [`mjpeg`] | MJPEG → luma (zune-jpeg), inserting the standard Huffman tables UVC frames omit |
//! | [`yuyv`] | YUYV 4:2:2 → luma |
//! | [`base`] | the [`MotorBase`] trait, [`BaseEvent`], [`BaseStatus`], [`LinkStats`] |
//! | [`serial_task`] | the serial skeleton both base drivers share: opening the port, the command task, expiry, reconnect/back-off, link counters, device-clock mapping |
//! | [`fnp`] | the FNP/1 codec (docs/protocol.md), re-exported from the no_std `flownav-fnp` crate, and the host's unit conversions |
//! | [`fnp_driver`] | the FNP/1 host driver: HELLO/INFO handshake, set-points out, odometry and status in |
//! | [`kobuki`] | the Kobuki (TurtleBot 2) protocol and its driver |

pub mod base;
pub mod calib;
pub mod camera;
pub mod error;
pub mod fnp;
pub mod fnp_driver;
pub mod image;
pub mod kobuki;
pub mod lens;
pub mod mjpeg;
pub mod motion;
pub mod serial_task;
pub mod undistort;
pub mod v4l2;
pub mod yuyv;

pub use base::{BaseEvent, BaseStatus, LinkStats, MotorBase};
pub use calib::{CalibError, Calibration};
pub use camera::Camera;
pub use error::{Error, ErrorKind};
pub use image::{Frame, LumaImage};
pub use motion::{BodyVelocity, Odometry};
pub use undistort::{UndistortError, Undistorter};
