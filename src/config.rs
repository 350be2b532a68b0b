//! The TOML configuration file (`--config FILE`): one table per stage, every field optional
//! with a documented default, unknown fields rejected. Command-line flags override it.
//!
//! The aggregate on top: each table is its stage's own params type, with its defaults and its
//! `validate`; this module only gathers them, and nothing it gathers imports it (their shared
//! error is the leaf [`crate::config_error`]).

pub use crate::config_error::ConfigError;
use crate::control::ControlLimits;
use crate::flow::FlowParams;
use crate::mofis::MofisParams;
use crate::odometry_calibration::OdometryParams;
use crate::offis::OffisParams;
use crate::pafsis::PafsisParams;
use crate::pairing::PairingParams;
use crate::runtime::config::{BaseConfig, RunConfig};
use hal::v4l2::CameraConfig;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The whole configuration.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub flow: FlowParams,
    /// `[pairing]`: which earlier frame each frame is paired with for the flow.
    pub pairing: PairingParams,
    pub odometry: OdometryParams,
    pub offis: OffisParams,
    pub pafsis: PafsisParams,
    pub mofis: MofisParams,
    pub control: ControlLimits,
    /// `[camera]`: the V4L2 device and the mode to negotiate (see docs/camera.md).
    pub camera: CameraConfig,
    /// `[base]`: the motor base's protocol, port and link settings (see docs/deploy.md).
    pub base: BaseConfig,
    /// `[run]`: the runtime's stall time and run logs (see docs/deploy.md).
    pub run: RunConfig,
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
        self.odometry.validate()?;
        self.mofis.validate()?;
        self.control.validate()?;
        self.base.validate()?;
        self.run.validate()?;
        // the camera's table is the hal crate's, with its own error
        self.camera.validate().map_err(|e| ConfigError::invalid(format!("camera.{}", e.field), e.problem))?;
        self.offis.validate()
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
