//! # flownav: optical-flow navigation for indoor robots with one webcam
//!
//! One pipeline, three ways to run it (`run` on a robot, `sim` in a simulated world,
//! `analyze`/`replay` offline). The per-frame step is pure; I/O lives at the edges.
//!
//! | module | owns | paper |
//! |---|---|---|
//! | [`frames`] | reading images and frame folders (PNG/JPEG → 8-bit luma, `odometry.csv`) | |
//! | [`flow`] | block-matching optical flow: parameters, the flow field, CPU and GPU engines | §2.2, §5 |
//! | [`offis`] | OFFIS: quadrant attributes, structure masks, obstacle zoom-in, distances from flow | §2.3–§5 |
//! | [`fuzzy`] | Mamdani fuzzy inference: TOML rule files, validation, compiled fast evaluation | §5 |
//! | [`perception`] | the OFFIS output: TPO shape/distance, nearest obstacle, structure masks | §2.2 |
//! | [`pafsis`] | topological map, global plan (mission → waypoints), local plan (landmarks + odometry → goal velocity/angle) | §2.2 |
//! | [`mofis`] | MOFIS: obstacle memory, stall recovery and escape, steering, fuzzy avoidance and fusion, footprint guard → set-point | §2.2 |
//! | [`control`] | set-point safety limiter: speed, turn rate, acceleration | |
//! | [`sources`] | where `run` gets frames: `--camera /dev/videoN` (V4L2) or `frames:DIR` played as a camera | |
//! | [`logging`] | MCAP run logs for Foxglove: the non-blocking writer, the replay reader, `log info` | |
//! | [`replay`] | `flownav replay`: a run log's frames and odometry through a fresh pipeline, compared with the logged outputs bit for bit | |
//! | [`runtime`] | `flownav run`: camera thread → step thread → base, latest-frame-wins, set-point expiry and stops, latency | |
//! | [`step`] | the pure per-frame step: flow → OFFIS → PAFSIS → MOFIS → set-point (shared by run, sim, analyze, replay) | Fig. 3 |
//! | [`rotation`] | the block search centred on the turn: frame B shifted by the rotation the odometry predicts, the shift added back to the flow | |
//! | [`sim`] | the closed loop of `flownav sim`: rendered camera → pipeline → FNP/1 driver → simulated base over a pty; the OFFIS accuracy bench (feature `sim`) | |
//! | [`pairing`] | the `[pairing]` table: which earlier frame (the keyframe) each frame is paired with | |
//! | [`config`] | the TOML configuration file: the aggregate of every stage's own params | |
//! | [`config_error`] | the one validation error of every stage's params (a leaf: imports nothing of the crate) | |
//! | [`calib_import`] | camera intrinsics from OpenCV `FileStorage` (YAML/XML) and ROS `camera_info` files, for `flownav calib import` | |
//! | [`cli`] | the `flownav` command line: one module per subcommand | |
//!
//! Hardware types and traits are in the `hal` crate (`hal/`), the simulated world in `mocks`.
//! Only [`sim`] and the simulator's subcommands reach `mocks`, behind the default feature `sim`;
//! a robot build (`--no-default-features`) leaves the renderer and the simulated bases out.

pub mod calib_import;
pub mod cli;
pub mod config;
pub mod config_error;
pub mod control;
pub mod flow;
pub mod frames;
pub mod fuzzy;
pub mod logging;
pub mod mofis;
pub mod odometry_calibration;
pub mod offis;
pub mod pafsis;
pub mod pairing;
pub mod perception;
pub mod replay;
pub mod rotation;
pub mod runtime;
#[cfg(feature = "sim")]
pub mod sim;
pub mod sources;
pub mod step;
