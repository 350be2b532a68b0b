//! The `[base]` and `[run]` config tables and the `--base` argument.
//!
//! `[base]` names the motor base (protocol and serial port) and its link settings; `[run]` holds
//! the runtime's own safety timing and where run logs go. `--base fnp:PORT|kobuki:PORT` overrides
//! `[base] kind` and `port`.

use crate::config_error::ConfigError;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::PathBuf;
use std::str::FromStr;

/// Which serial protocol the base speaks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BaseKind {
    /// flownav's own protocol (docs/protocol.md), driver `hal::fnp_driver::FnpBase`.
    #[default]
    Fnp,
    /// TurtleBot 2 / Kobuki, driver `hal::kobuki::KobukiBase`.
    Kobuki,
}

impl fmt::Display for BaseKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            BaseKind::Fnp => "fnp",
            BaseKind::Kobuki => "kobuki",
        })
    }
}

/// The `[base]` config table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BaseConfig {
    /// `"fnp"` or `"kobuki"`.
    pub kind: BaseKind,
    /// Serial port, e.g. `/dev/ttyUSB0` or a udev name such as `/dev/flownav-base`.
    pub port: String,
    /// Line rate (FNP/1 bases: what the firmware uses; Kobuki: 115200).
    pub baud: u32,
    /// How often the runtime refreshes the command, and the driver repeats it, Hz (≥ 20).
    pub setpoint_rate_hz: f64,
    /// FNP/1 only: the firmware watchdog sent in HELLO, ms (the base stops by itself when no
    /// command arrives for this long). The Kobuki has none; its driver zeroes stale commands.
    pub watchdog_ms: u16,
}

impl Default for BaseConfig {
    fn default() -> Self {
        Self {
            kind: BaseKind::Fnp,
            port: "/dev/ttyUSB0".into(),
            baud: 115_200,
            setpoint_rate_hz: 25.0,
            watchdog_ms: 150,
        }
    }
}

impl BaseConfig {
    /// Checks ranges that serde cannot.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, problem: &str| {
            Err(ConfigError::Invalid { field: format!("base.{field}"), problem: problem.into() })
        };
        if self.port.trim().is_empty() {
            return bad("port", "must name a serial port, e.g. \"/dev/ttyUSB0\"");
        }
        if self.baud == 0 {
            return bad("baud", "must be a positive line rate, e.g. 115200");
        }
        if !(self.setpoint_rate_hz.is_finite() && (20.0..=1000.0).contains(&self.setpoint_rate_hz)) {
            return bad("setpoint_rate_hz", "must be in 20..=1000 Hz (docs/protocol.md asks for at least 20 Hz)");
        }
        if !(20..=5000).contains(&self.watchdog_ms) {
            return bad("watchdog_ms", "must be in 20..=5000 ms");
        }
        if f64::from(self.watchdog_ms) <= 1000.0 / self.setpoint_rate_hz {
            return bad(
                "watchdog_ms",
                "must be longer than one set-point period (1000 / setpoint_rate_hz ms), or the base stops between commands",
            );
        }
        Ok(())
    }
}

/// The `[run]` config table: the runtime's safety timing and its log.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RunConfig {
    /// A set-point expires this long after the capture of the frame it was computed from; then
    /// a zero set-point goes out (camera stall, slow step). 40..=190 ms, so that the stop is
    /// commanded within 200 ms of the last frame (DESIGN.md).
    pub stall_ms: u64,
    /// After the base's e-stop, cliff, wheel-drop or motor-fault alarm clears, the robot stays
    /// stopped this long, ms (100..=60000).
    pub alarm_hold_ms: u64,
    /// Write an MCAP log of the run.
    pub log: bool,
    /// Where the logs go (one file per run).
    pub log_dir: PathBuf,
    /// Split the log into parts of this many MB (10^6 bytes); absent: one file.
    pub log_split_mb: Option<u64>,
}

impl Default for RunConfig {
    fn default() -> Self {
        Self { stall_ms: 150, alarm_hold_ms: 1000, log: true, log_dir: PathBuf::from("logs"), log_split_mb: None }
    }
}

impl RunConfig {
    /// Checks ranges that serde cannot.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &str, problem: &str| {
            Err(ConfigError::Invalid { field: format!("run.{field}"), problem: problem.into() })
        };
        if !(40..=190).contains(&self.stall_ms) {
            return bad(
                "stall_ms",
                "must be in 40..=190 ms: longer than a frame period, short enough to stop within 200 ms",
            );
        }
        if !(100..=60_000).contains(&self.alarm_hold_ms) {
            return bad(
                "alarm_hold_ms",
                "must be in 100..=60000 ms: how long a base alarm must stay clear before the robot moves again",
            );
        }
        if self.log_split_mb == Some(0) {
            return bad("log_split_mb", "must be at least 1 MB (leave it out for one file)");
        }
        Ok(())
    }
}

/// The `--base` argument: `fnp:PORT` or `kobuki:PORT`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BaseSpec {
    pub kind: BaseKind,
    pub port: String,
}

/// A `--base` value that does not parse.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum BaseSpecError {
    #[error("--base {0}: name the protocol before the port: fnp:{0} (flownav's FNP/1) or kobuki:{0} (TurtleBot 2)")]
    MissingKind(String),
    #[error("--base {0}: needs a serial port after the colon, e.g. {0}/dev/ttyUSB0")]
    EmptyPort(String),
    #[error("--base {spec}: unknown base kind {kind:?}; expected fnp:PORT or kobuki:PORT")]
    UnknownKind { spec: String, kind: String },
}

impl FromStr for BaseSpec {
    type Err = BaseSpecError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let Some((kind, port)) = s.split_once(':') else {
            return Err(BaseSpecError::MissingKind(s.into()));
        };
        let kind = match kind {
            "fnp" => BaseKind::Fnp,
            "kobuki" => BaseKind::Kobuki,
            _ if kind.starts_with('/') => return Err(BaseSpecError::MissingKind(s.into())),
            _ => return Err(BaseSpecError::UnknownKind { spec: s.into(), kind: kind.into() }),
        };
        if port.is_empty() {
            return Err(BaseSpecError::EmptyPort(format!("{kind}:")));
        }
        Ok(Self { kind, port: port.into() })
    }
}

impl fmt::Display for BaseSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.kind, self.port)
    }
}

impl BaseSpec {
    /// The base the config file names when `--base` is not given.
    pub fn from_config(cfg: &BaseConfig) -> Self {
        Self { kind: cfg.kind, port: cfg.port.clone() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    #[test]
    fn base_specs_parse_with_clear_errors() {
        assert_eq!("fnp:/dev/ttyUSB0".parse(), Ok(BaseSpec { kind: BaseKind::Fnp, port: "/dev/ttyUSB0".into() }));
        assert_eq!("kobuki:/dev/kobuki".parse::<BaseSpec>().unwrap().kind, BaseKind::Kobuki);
        let e = "/dev/ttyUSB0".parse::<BaseSpec>().unwrap_err().to_string();
        assert!(e.contains("fnp:/dev/ttyUSB0") && e.contains("kobuki:/dev/ttyUSB0"), "{e}");
        let e = "fnp:".parse::<BaseSpec>().unwrap_err().to_string();
        assert!(e.contains("fnp:/dev/ttyUSB0"), "{e}");
        let e = "roomba:/dev/ttyUSB0".parse::<BaseSpec>().unwrap_err().to_string();
        assert!(e.contains("roomba") && e.contains("kobuki:PORT"), "{e}");
        assert_eq!(BaseSpec { kind: BaseKind::Kobuki, port: "/dev/x".into() }.to_string(), "kobuki:/dev/x");
    }

    #[test]
    fn base_and_run_tables() {
        let cfg: Config = toml::from_str(
            "[base]\nkind = \"kobuki\"\nport = \"/dev/kobuki\"\nsetpoint_rate_hz = 50\n[run]\nstall_ms = 100\nlog = false\n",
        )
        .unwrap();
        cfg.validate().unwrap();
        assert_eq!(cfg.base.kind, BaseKind::Kobuki);
        assert_eq!(cfg.base.watchdog_ms, 150);
        assert_eq!(cfg.run.stall_ms, 100);
        assert!(!cfg.run.log);
        let err = |text: &str| toml::from_str::<Config>(text).unwrap().validate().unwrap_err().to_string();
        assert!(err("[base]\nsetpoint_rate_hz = 10\n").contains("base.setpoint_rate_hz"));
        assert!(err("[base]\nwatchdog_ms = 30\n").contains("base.watchdog_ms"));
        assert!(err("[run]\nstall_ms = 250\n").contains("run.stall_ms"));
        assert!(err("[run]\nlog_split_mb = 0\n").contains("run.log_split_mb"));
        assert!(err("[run]\nalarm_hold_ms = 50\n").contains("run.alarm_hold_ms"));
        assert_eq!(toml::from_str::<Config>("[run]\nalarm_hold_ms = 2500\n").unwrap().run.alarm_hold_ms, 2500);
        assert!(toml::from_str::<Config>("[base]\nkind = \"roomba\"\n").is_err());
        assert!(toml::from_str::<Config>("[run]\nbogus = 1\n").is_err());
    }

    #[test]
    fn the_example_config_loads_and_shows_the_defaults() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/config/robot.example.toml");
        let cfg = Config::load(path).unwrap();
        let text = std::fs::read_to_string(path).unwrap();
        for table in ["camera", "base", "run", "control", "flow", "offis.outlier", "offis.plane", "offis.tilt"] {
            assert!(text.contains(&format!("[{table}]")), "the example documents [{table}]");
        }
        // Everything is the default except the two udev names marked "robot".
        let mut expected = Config::default();
        expected.camera.device = "/dev/flownav-camera".into();
        expected.base.port = "/dev/flownav-base".into();
        assert_eq!(cfg, expected);
    }

    #[test]
    fn the_bend_only_guard_loads_and_changes_only_the_guard_and_the_fade() {
        let cfg = Config::load(concat!(env!("CARGO_MANIFEST_DIR"), "/config/guard-bend.toml")).unwrap();
        let mut expected = Config::default();
        let m = &mut expected.mofis;
        assert_ne!((m.guard_slow, m.guard_brake, m.guard_cluster, m.guard_min_cells), (false, false, false, 1));
        (m.guard_slow, m.guard_brake, m.guard_cluster, m.guard_min_cells) = (false, false, false, 1);
        m.memory.out_half_life_s = 12.0;
        assert_eq!(cfg, expected);
    }
}
