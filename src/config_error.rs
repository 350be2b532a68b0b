//! The error every stage's parameters give when they are out of range, and that reading the
//! configuration file gives: the one shape of validation, `validate(&self) -> Result<(),
//! ConfigError>`, whose message names the offending key as it is written in the TOML file
//! (`flow.block`, `mofis.memory.cell_m`).
//!
//! A leaf: it imports nothing of the crate, so each stage can validate its own table without
//! importing the aggregate [`crate::config::Config`], which sits above them all.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config file {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("config file {path} is not valid: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("config: {field} {problem}")]
    Invalid { field: String, problem: String },
}

impl ConfigError {
    /// The key `field` (its whole dotted path) has a value that `problem` describes.
    pub fn invalid(field: impl Into<String>, problem: impl Into<String>) -> Self {
        Self::Invalid { field: field.into(), problem: problem.into() }
    }
}
