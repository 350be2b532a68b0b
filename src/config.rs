//! The TOML configuration file (`--config FILE`): one table per stage, every field optional
//! with a documented default, unknown fields rejected. Command-line flags override it.

use crate::control::ControlLimits;
use crate::flow::FlowParams;
use crate::mofis::MofisParams;
use crate::offis::OffisParams;
use crate::pafsis::PafsisParams;
use hal::v4l2::CameraConfig;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config file {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("config file {path} is not valid: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("config: {field} {problem}")]
    Invalid { field: String, problem: String },
}

/// The whole configuration.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub flow: FlowParams,
    /// `[pairing]`: which earlier frame each frame is paired with for the flow.
    pub pairing: crate::step::PairingParams,
    pub offis: OffisParams,
    pub pafsis: PafsisParams,
    pub mofis: MofisParams,
    pub control: ControlLimits,
    /// `[camera]`: the V4L2 device and the mode to negotiate (see docs/camera.md).
    pub camera: CameraConfig,
    /// `[base]`: the motor base's protocol, port and link settings (see docs/deploy.md).
    pub base: crate::runtime::config::BaseConfig,
    /// `[run]`: the runtime's stall time and run logs (see docs/deploy.md).
    pub run: crate::runtime::config::RunConfig,
}

impl Config {
    /// Reads, parses and validates a config file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.into(), source })?;
        let cfg: Self =
            toml::from_str(&text).map_err(|e| ConfigError::Parse { path: path.into(), message: e.to_string() })?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks ranges that serde cannot.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.flow.validate()?;
        self.pafsis.validate()?;
        self.pairing.validate()?;
        self.mofis.validate()?;
        self.control.validate()?;
        self.base.validate()?;
        self.run.validate()?;
        self.camera
            .validate()
            .map_err(|e| ConfigError::Invalid { field: format!("camera.{}", e.field), problem: e.problem })?;
        self.offis.check().map_err(|(field, problem)| ConfigError::Invalid { field, problem })
    }
}

impl FlowParams {
    /// Checks the parameters on their own (frame-size checks happen when a frame arrives).
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, problem: &str| {
            Err(ConfigError::Invalid { field: format!("flow.{field}"), problem: problem.into() })
        };
        if self.rows == 0 || self.cols == 0 {
            return bad("rows/cols", "must be at least 1");
        }
        if let Some(stride) = self.stride {
            if !(1..=256).contains(&stride) {
                return bad("stride", "must be in 1..=256 pixels (leave it out for the rows x cols grid)");
            }
            if self.placement != crate::flow::Placement::Spread {
                return bad("stride", "requires placement = \"spread\" (dense mode centres one block per stride cell)");
            }
        }
        if !(4..=256).contains(&self.block) || !self.block.is_multiple_of(2) {
            return bad("block", "must be an even number of pixels in 4..=256");
        }
        if !(1..=64).contains(&self.radius) {
            return bad("radius", "must be in 1..=64 pixels");
        }
        if self.prefilter_radius > crate::flow::prefilter::MAX_RADIUS {
            return bad("prefilter_radius", "must be in 0..=7 pixels (0 = match raw intensities)");
        }
        if self.pyramid_levels > 6 {
            return bad("pyramid_levels", "must be in 0..=6 (0 or 1 = single level, no coarse-to-fine)");
        }
        if !(1..=64).contains(&self.refine_radius) {
            return bad("refine_radius", "must be in 1..=64 pixels");
        }
        if !(self.min_texture.is_finite() && (0.0..=255.0).contains(&self.min_texture)) {
            return bad("min_texture", "must be a number of grey levels in 0..=255");
        }
        if !(self.ambiguity_ratio.is_finite() && (0.0..=16.0).contains(&self.ambiguity_ratio)) {
            return bad("ambiguity_ratio", "must be a number in 0..=16");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_and_overrides() {
        let cfg: Config = toml::from_str("[flow]\nradius = 8\n").unwrap();
        assert_eq!(cfg.flow.radius, 8);
        assert_eq!(cfg.flow.rows, 16);
        cfg.validate().unwrap();
    }

    #[test]
    fn bad_values_name_the_field() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.toml");
        std::fs::write(&p, "[flow]\nblock = 7\n").unwrap();
        assert!(Config::load(&p).unwrap_err().to_string().contains("flow.block"));
        std::fs::write(&p, "[flow]\nbogus = 1\n").unwrap();
        let e = Config::load(&p).unwrap_err().to_string();
        assert!(e.contains("bogus") && e.contains("c.toml"), "{e}");
        std::fs::write(&p, "[offis.plane]\nrel = 1.5\n").unwrap();
        assert!(Config::load(&p).unwrap_err().to_string().contains("offis.plane.rel"));
        std::fs::write(&p, "[offis.tilt]\nk_tilt = 0.5\n").unwrap();
        assert_eq!(Config::load(&p).unwrap().offis.tilt.k_tilt, 0.5);
    }

    #[test]
    fn camera_table() {
        let cfg: Config = toml::from_str("[camera]\ndevice = \"/dev/video2\"\nformat = \"yuyv\"\nfps = 7.5\n").unwrap();
        assert_eq!(cfg.camera.device, std::path::PathBuf::from("/dev/video2"));
        assert_eq!(cfg.camera.format, hal::v4l2::PixelFormat::Yuyv);
        assert_eq!((cfg.camera.width, cfg.camera.height), (1280, 720));
        cfg.validate().unwrap();
        let bad: Config = toml::from_str("[camera]\nstall_timeout_ms = 10\n").unwrap();
        assert!(bad.validate().unwrap_err().to_string().contains("camera.stall_timeout_ms"));
        assert!(toml::from_str::<Config>("[camera]\nformat = \"h264\"\n").is_err());
    }
}
