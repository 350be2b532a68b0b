//! # flownav-mocks: the simulated world
//!
//! Everything flownav needs to be tested without hardware.
//!
//! | module | owns |
//! |---|---|
//! | [`pty`] | raw-mode pseudo-terminals that stand in for serial ports |
//! | [`faults`] | seeded link faults (dropped, corrupted, delayed bytes, disconnects) and the simulation RNG |
//! | [`kinematics`] | differential-drive kinematics: limits, exact arcs, noisy encoders, collision hook |
//! | [`sim_base`] | the simulated FNP/1 base and the pty server ([`sim_base::SimServer`]) for any simulated device |
//! | [`sim_kobuki`] | the simulated Kobuki (TurtleBot 2) base |

pub mod faults;
pub mod kinematics;
pub mod pty;
pub mod sim_base;
pub mod sim_kobuki;
