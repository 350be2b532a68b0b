//! How `run` and `sim` log the pipeline: one place that decides what a run log holds, so that
//! every log can be replayed through [`crate::step::Pipeline`] by `flownav replay`.
//!
//! - [`run_options`] (+ [`add_map`]): the log options, with everything needed to rebuild the
//!   pipeline stored as the `flownav.config` metadata record (configuration as TOML, calibration
//!   as TOML, mission, map, flownav version).
//! - [`record_frame`]: the camera image of every frame given to `Pipeline::step`, at its capture time.
//! - [`record_step`]: what one step consumed (`/step/input`: seq, times, odometry, bit-exact) and
//!   produced (flow, annotations, perception with the OFFIS attributes, goal, set-point).
//! - [`record_failsafe`]: `Pipeline::fail_safe` was called (a `/log` warning, a zero set-point and
//!   a `fail_safe` entry on `/step/input`, so replay resets its pipeline at the same point).
//!
//! All calls are non-blocking (see [`LogHandle`]); the costliest part on the control path is
//! converting the OFFIS attributes to JSON (tens of µs), the rest is copies into the queue.

use std::collections::BTreeMap;
use std::sync::Arc;

use hal::{BodyVelocity, Calibration, Frame, LumaImage};
use serde::Serialize;

use super::payload::{GoalLog, LogLevel, SetpointLog, StepInputLog};
use super::{LogHandle, LogOptions};
use crate::config::Config;
use crate::pafsis::map::{Edge, Place};
use crate::pafsis::{LegKind, TopoMap};
use crate::step::{Pipeline, StepOutput};

/// Name of the metadata record that holds what replay needs.
pub const CONFIG_METADATA: &str = "flownav.config";
/// Keys of the [`CONFIG_METADATA`] record.
pub const KEY_CONFIG: &str = "config_toml";
pub const KEY_CALIBRATION: &str = "calibration_toml";
pub const KEY_MISSION: &str = "mission";
pub const KEY_MAP: &str = "map_toml";
pub const KEY_VERSION: &str = "flownav_version";
pub const KEY_KIND: &str = "kind";

/// The log options of a run of `kind` (`run`, `sim`), split at `split_mb` MB when given, with
/// the `flownav.config` metadata record: the configuration and calibration as TOML, the mission
/// `FROM:TO` (if any) and the flownav version. A run with a mission must also call [`add_map`],
/// or its log cannot be replayed.
///
/// Serialising the configuration cannot fail for a valid [`Config`]; should it ever, the record
/// carries the error under `config_error` and replay names it.
pub fn run_options(
    kind: &str,
    cfg: &Config,
    calib: &Calibration,
    mission: Option<&str>,
    split_mb: Option<f64>,
) -> LogOptions {
    let mut options = LogOptions::new(kind);
    if let Some(mb) = split_mb {
        options = options.split_mb(mb);
    }
    let mut m = BTreeMap::new();
    m.insert(KEY_KIND.to_string(), kind.to_string());
    m.insert(KEY_VERSION.to_string(), env!("CARGO_PKG_VERSION").to_string());
    match toml::to_string(cfg) {
        Ok(text) => m.insert(KEY_CONFIG.to_string(), text),
        Err(e) => m.insert("config_error".to_string(), e.to_string()),
    };
    match toml::to_string(calib) {
        Ok(text) => m.insert(KEY_CALIBRATION.to_string(), text),
        Err(e) => m.insert("calibration_error".to_string(), e.to_string()),
    };
    if let Some(mission) = mission {
        m.insert(KEY_MISSION.to_string(), mission.to_string());
    }
    options.metadata.push((CONFIG_METADATA.to_string(), m));
    options
}

/// Adds the topological map of the mission to the `flownav.config` record of `options` (made by
/// [`run_options`]), as TOML that [`TopoMap::parse`] reads back to the same map.
pub fn add_map(options: &mut LogOptions, map: &TopoMap) {
    let text = map_toml(map);
    match options.metadata.iter_mut().find(|(name, _)| name == CONFIG_METADATA) {
        Some((_, m)) => {
            m.insert(KEY_MAP.to_string(), text);
        }
        None => {
            options.metadata.push((CONFIG_METADATA.to_string(), BTreeMap::from([(KEY_MAP.to_string(), text)])));
        }
    }
}

/// A map as the TOML text of a map file (`name`, `[[place]]`, `[[edge]]`).
pub fn map_toml(map: &TopoMap) -> String {
    #[derive(Serialize)]
    struct MapFile<'a> {
        name: &'a str,
        place: &'a [Place],
        edge: &'a [Edge],
    }
    let file = MapFile { name: &map.name, place: &map.places, edge: &map.edges };
    toml::to_string(&file).unwrap_or_else(|e| format!("# map could not be serialised: {e}\n"))
}

/// The camera image of a frame, as the logger stores it.
pub enum RecordImage<'a> {
    /// A decoded or rendered 8-bit grey frame (`foxglove.RawImage` mono8; the sim).
    Mono8(&'a LumaImage),
    /// The camera's MJPEG bytes, stored as they came (`foxglove.CompressedImage`; the robot).
    /// Replay decodes them with [`hal::mjpeg::MjpegDecoder`], as `run` does.
    Jpeg(Arc<[u8]>),
}

/// Logs the image of `frame` at its capture time. Call it for every frame passed to
/// `Pipeline::step`, before the step (replay pairs frames by capture time). Returns whether the
/// image was queued (images are the first thing dropped when the writer falls behind).
pub fn record_frame(h: &LogHandle, frame: &Frame, image: RecordImage) -> bool {
    match image {
        RecordImage::Mono8(img) => h.image_mono8(frame.t_ns, img),
        RecordImage::Jpeg(bytes) => h.image_jpeg(frame.t_ns, bytes),
    }
}

/// The set-point as logged: what was sent, and what MOFIS asked for when the limiter changed it.
pub fn setpoint_log(out: &StepOutput) -> SetpointLog {
    let (fused, sent) = (out.mofis.fused, out.mofis.setpoint);
    let clamped = fused != sent;
    SetpointLog { v: sent.v, omega: sent.omega, clamped, requested: clamped.then_some(fused) }
}

/// The goal as logged, with the current leg of the mission (when PAFSIS runs).
pub fn goal_log(out: &StepOutput, pipeline: &Pipeline) -> GoalLog {
    let mut goal = GoalLog { v: out.goal.velocity, angle_rad: out.goal.angle_rad, ..GoalLog::default() };
    if let Some(p) = pipeline.pafsis() {
        let progress = p.progress();
        if let Some(leg) = p.legs().get(progress.leg) {
            goal.waypoint = Some(leg.leads_to.clone());
            goal.waypoint_index = u32::try_from(progress.leg).ok();
            let length = match &leg.kind {
                LegKind::Corridor { length_m, .. } | LegKind::Doorway { length_m, .. } => Some(*length_m),
                LegKind::Turn => None,
            };
            goal.remaining_m = length.map(|l| (l - progress.along_m).max(0.0));
        }
    }
    goal
}

/// The OFFIS attributes of the last step as JSON (`Value::Null` if they cannot be converted).
pub fn attributes_json(pipeline: &Pipeline) -> serde_json::Value {
    serde_json::to_value(pipeline.offis().attributes()).unwrap_or(serde_json::Value::Null)
}

/// Logs one step, all at `out.t_ns`: `/step/input` (frame `out.seq`, the previous frame's time,
/// the odometry `input_odometry` exactly as passed to `Pipeline::step`), `/flow/field` and
/// `/flow/annotations`, `/offis/perception` (with the OFFIS attributes), `/pafsis/goal` and
/// `/control/setpoint`. Call it right after a step that returned `Ok(Some(out))`, before the next
/// step (the attributes and the PAFSIS progress are read from `pipeline`).
pub fn record_step(h: &LogHandle, input_odometry: BodyVelocity, out: &StepOutput, pipeline: &Pipeline) {
    let t = out.t_ns;
    // the frame stepped before this one (the replay feeds frames in the same order; the pair's
    // older frame, the keyframe, may lie further back)
    h.step_input(&StepInputLog::Step {
        seq: out.seq,
        t_ns: t,
        prev_t_ns: out.prev_t_ns,
        v: input_odometry.v,
        omega: input_odometry.omega,
        odometry_scale: pipeline.applied_calibration()[0],
        odometry_bend_rad_m: pipeline.applied_calibration()[1],
    });
    h.flow(t, &out.flow);
    h.perception(t, &out.perception, attributes_json(pipeline));
    h.goal(t, &goal_log(out, pipeline));
    h.setpoint(t, &setpoint_log(out));
}

/// Logs a call of `Pipeline::fail_safe` at `t_ns` (camera stall, a failed step, exit): a `/log`
/// warning with `reason`, the zero set-point on `/control/setpoint`, and a `fail_safe` entry on
/// `/step/input` so replay resets its pipeline at the same point. Call it whenever the pipeline's
/// `fail_safe` is called, with the same clock as the frames' capture times.
pub fn record_failsafe(h: &LogHandle, t_ns: u64, reason: &str) {
    h.log(t_ns, LogLevel::Warning, format!("fail-safe stop: {reason}"));
    h.step_input(&StepInputLog::FailSafe { t_ns, reason: reason.to_string() });
    h.setpoint(t_ns, &SetpointLog { v: 0.0, omega: 0.0, clamped: false, requested: None });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_carry_config_calibration_and_mission_that_parse_back() {
        let mut cfg = Config::default();
        cfg.pafsis.cruise_speed = 0.123_456_789_012_345_6;
        let calib = Calibration::nominal_c310();
        let options = run_options("sim", &cfg, &calib, Some("R1:R2"), Some(100.0));
        assert_eq!(options.kind, "sim");
        assert_eq!(options.split_bytes, Some(100_000_000));
        let (name, m) = &options.metadata[0];
        assert_eq!(name, CONFIG_METADATA);
        let back: Config = toml::from_str(&m[KEY_CONFIG]).unwrap();
        assert_eq!(back, cfg);
        assert_eq!(Calibration::from_toml(&m[KEY_CALIBRATION], "log").unwrap(), calib);
        assert_eq!(m[KEY_MISSION], "R1:R2");
        assert_eq!(m[KEY_VERSION], env!("CARGO_PKG_VERSION"));
    }

    #[test]
    fn a_map_round_trips_through_its_toml() {
        let map = TopoMap::parse(include_str!("../../maps/office.toml"), "maps/office.toml").unwrap();
        let mut options = run_options("run", &Config::default(), &Calibration::nominal_c310(), Some("R1:R2"), None);
        add_map(&mut options, &map);
        let text = &options.metadata[0].1[KEY_MAP];
        let back = TopoMap::parse(text, "test").unwrap();
        assert_eq!((back.name.as_str(), &back.places, &back.edges), (map.name.as_str(), &map.places, &map.edges));
    }
}
