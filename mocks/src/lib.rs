//! # flownav-mocks: the simulated world
//!
//! Everything flownav needs to be tested without hardware.
//!
//! | module | owns |
//! |---|---|
