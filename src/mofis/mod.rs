//! MOFIS, the motion module of the paper (§2.2): a Mamdani collision-avoidance behaviour, a
//! fuzzy fusion of avoidance with PAFSIS's goal orientation, and the safety limiter that turns
//! the fused command into the set-point sent to the base.

use crate::config::ConfigError;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// The `[mofis]` config table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MofisParams {
    /// Folder with `avoidance.toml` and `fusion.toml` (the rule bases).
    pub rules_dir: PathBuf,
    /// Goal behaviour turn rate per radian of goal angle, 1/s (ω_goal = gain · angle).
    pub heading_gain: f64,
    /// Distance fed to the rule bases when nothing is seen (no obstacle, open ahead), m; the
    /// top of the distance universes.
    pub sensing_range_m: f64,
}

impl Default for MofisParams {
    fn default() -> Self {
        Self { rules_dir: PathBuf::from("rules/mofis"), heading_gain: 1.5, sensing_range_m: 5.0 }
    }
}

impl MofisParams {
    /// Checks ranges that serde cannot.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, problem: &str| {
            Err(ConfigError::Invalid { field: format!("mofis.{field}"), problem: problem.into() })
        };
        if !(self.heading_gain.is_finite() && self.heading_gain > 0.0) {
            return bad("heading_gain", "must be a positive finite number (1/s)");
        }
        if !(self.sensing_range_m.is_finite() && self.sensing_range_m > 0.0) {
            return bad("sensing_range_m", "must be a positive finite distance in m");
        }
        Ok(())
    }
}
