//! The `[pairing]` table: how far back the older frame of each flow pair lies (the keyframe,
//! [`crate::step`]).

use crate::config_error::ConfigError;

/// The `[pairing]` config table: how far back the older frame of each pair lies.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PairingParams {
    /// The keyframe is replaced once the robot has driven this far since it, m (0: pair
    /// consecutive frames, as the paper does).
    pub min_baseline_m: f64,
    /// ... or once it is this old, s.
    pub max_span_s: f64,
}

impl Default for PairingParams {
    fn default() -> Self {
        Self { min_baseline_m: 0.04, max_span_s: 0.4 }
    }
}

impl PairingParams {
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, problem: &str| {
            Err(ConfigError::Invalid { field: format!("pairing.{field}"), problem: problem.into() })
        };
        if !(self.min_baseline_m.is_finite() && (0.0..=0.5).contains(&self.min_baseline_m)) {
            return bad("min_baseline_m", "must be in [0, 0.5] m");
        }
        if !(self.max_span_s.is_finite() && self.max_span_s > 0.0 && self.max_span_s <= 5.0) {
            return bad("max_span_s", "must be in (0, 5] s");
        }
        Ok(())
    }
}
