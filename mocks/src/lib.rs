//! # flownav-mocks: the simulated world
//!
//! Everything flownav needs to be tested without hardware.
//!
//! | module | owns |
//! |---|---|
//! | [`world`] | worlds as TOML floor plans (walls, doors, boxes, cylinders, named places, start), validation, random obstacle placement |
//! | [`render`] | the CPU ray caster: camera view (8-bit luma), depth map, surface ids, noise/exposure/motion blur |
//! | [`texture`] | the world-anchored procedural texture with its mip pyramid |
//! | [`camera`] | camera pose from robot pose + mount, optical ↔ world transforms |
//! | [`rendered_camera`] | [`RenderedCamera`], the simulated `hal::Camera` that renders from a pose source |
//! | [`truth`] | ground truth: TPO class by DESIGN.md geometry ([`truth::tpo`] thresholds), nearest obstacle, exact motion field |
//! | [`scene`] | canonical scenes built in code (wall, corner, door, corridor, empty) for labelled benchmarks |
//! | [`pty`] | raw-mode pseudo-terminals that stand in for serial ports |
//! | [`faults`] | seeded link faults (dropped, corrupted, delayed bytes, disconnects) and the simulation RNG |
//! | [`kinematics`] | differential-drive kinematics: limits, exact arcs, noisy encoders, collision hook |
//! | [`odometry_error`] | how a base's wheels differ from its firmware's nominal ones: radius, wheel base, noise, slip; the `--odometry-error` spec |
//! | [`sim_base`] | the simulated FNP/1 base and the pty server ([`sim_base::SimServer`]) for any simulated device |
//! | [`sim_kobuki`] | the simulated Kobuki (TurtleBot 2) base |

pub mod camera;
pub mod faults;
pub mod kinematics;
pub mod odometry_error;
pub mod pty;
pub mod render;
pub mod rendered_camera;
pub mod scene;
pub mod sim_base;
pub mod sim_kobuki;
pub mod spec;
pub mod stop_gaps;
pub mod texture;
pub mod truth;
pub mod world;

pub use camera::CameraPose;
pub use odometry_error::OdometryError;
pub use render::{DepthMap, Effects, Renderer};
pub use rendered_camera::{Pacing, RenderedCamera};
pub use truth::{FrameTruth, GroundTruth, MotionField, TpoClass};
pub use world::{Pose, World, WorldError};
