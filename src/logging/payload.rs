//! flownav's own message types for the JSON-schema topics (`/flow/field`, `/offis/perception`,
//! `/pafsis/goal`, `/control/setpoint`, `/base/odometry`, `/base/status`, `/logger/stats`), the
//! inputs the sim passes in (robot pose, world geometry), and their JSON schemas.
//!
//! Kept generic on purpose: navigation fills [`GoalLog`] and [`SetpointLog`], the sim fills
//! [`WorldGeometry`], without the logger depending on their internals.

use hal::{BaseStatus, BodyVelocity};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::perception::Perception;

/// What PAFSIS asks for at one frame: the goal velocity and heading towards the current waypoint.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GoalLog {
    /// Goal forward speed, m/s.
    pub v: f64,
    /// Goal heading relative to the robot's, rad, positive to the left (REP-103).
    pub angle_rad: f64,
    /// Name of the waypoint being driven to (a node of the topological map), if any.
    pub waypoint: Option<String>,
    /// Index of that waypoint in the mission's path.
    pub waypoint_index: Option<u32>,
    /// Distance left to that waypoint, m, when known.
    pub remaining_m: Option<f64>,
}

/// The set-point sent to the base at one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SetpointLog {
    /// Forward speed sent, m/s.
    pub v: f64,
    /// Turn rate sent, rad/s, positive to the left.
    pub omega: f64,
    /// Whether a limit (speed, turn rate, acceleration) changed the requested command.
    pub clamped: bool,
    /// What MOFIS asked for before clamping, when it differs from what was sent.
    pub requested: Option<BodyVelocity>,
}

/// `/base/status`: the base's health flags exactly as [`hal::BaseStatus`] holds them.
pub type BaseStatusLog = BaseStatus;

/// `/offis/perception`: the [`Perception`] fields at the top level plus free-form `attributes`
/// (OFFIS intermediate values: plane/tilt matrices, classifier degrees, ...).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PerceptionLog {
    #[serde(flatten)]
    pub perception: Perception,
    #[serde(default)]
    pub attributes: Value,
}

/// `/step/input`: what one call of the per-frame pipeline consumed, so `flownav replay` can feed
/// the same inputs to a fresh [`crate::step::Pipeline`] (see docs/logging.md, "Replay").
///
/// `Step`: `Pipeline::step` gave an output for frame `seq` captured at `t_ns`, stepped right
/// after the frame captured at `prev_t_ns` (the flow's older frame is the pipeline's keyframe,
/// which replay reproduces by feeding the frames in order), with the odometry `v`, `omega` (bit-exact floats). `FailSafe`:
/// `Pipeline::fail_safe` was called at `t_ns` (the limiter stopped, the previous frame forgotten).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum StepInputLog {
    Step {
        seq: u64,
        t_ns: u64,
        prev_t_ns: u64,
        /// Forward speed fed to the step, m/s.
        v: f64,
        /// Turn rate fed to the step, rad/s, positive to the left.
        omega: f64,
        /// The learned odometry errors the step took out of `omega`
        /// ([`crate::odometry_calibration`]); 0 in logs written before they were learned.
        #[serde(default)]
        odometry_scale: f64,
        #[serde(default)]
        odometry_bend_rad_m: f64,
    },
    FailSafe {
        t_ns: u64,
        reason: String,
    },
}

impl StepInputLog {
    /// The time the entry is logged at, ns.
    pub fn t_ns(&self) -> u64 {
        match self {
            StepInputLog::Step { t_ns, .. } | StepInputLog::FailSafe { t_ns, .. } => *t_ns,
        }
    }
}

/// The robot's planar pose in the odometry frame (`odom` → `base_link`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose2D {
    pub x_m: f64,
    pub y_m: f64,
    /// Heading, rad, counter-clockwise from the odom x axis.
    pub theta_rad: f64,
}

/// A box standing on the floor: a wall segment or a box obstacle.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WorldBox {
    pub id: String,
    /// Centre of the footprint in the world (odom) frame, m.
    pub center_m: [f64; 2],
    /// Length along its own x axis, width, height, m.
    pub size_m: [f64; 3],
    /// Rotation of its x axis from the world x axis, rad.
    pub yaw_rad: f64,
    /// Walls are drawn grey, obstacles orange.
    pub wall: bool,
}

/// An upright cylinder standing on the floor (a person, a pillar).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WorldCylinder {
    pub id: String,
    pub center_m: [f64; 2],
    pub radius_m: f64,
    pub height_m: f64,
}

/// A simple description of the simulated world for `/sim/world`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WorldGeometry {
    pub boxes: Vec<WorldBox>,
    pub cylinders: Vec<WorldCylinder>,
}

/// Severity of a `/log` line (`foxglove.LogLevel` values).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub enum LogLevel {
    Debug = 1,
    Info = 2,
    Warning = 3,
    Error = 4,
    Fatal = 5,
}

impl LogLevel {
    pub fn from_u8(level: u8) -> Option<Self> {
        Some(match level {
            1 => LogLevel::Debug,
            2 => LogLevel::Info,
            3 => LogLevel::Warning,
            4 => LogLevel::Error,
            5 => LogLevel::Fatal,
            _ => return None,
        })
    }
}

/// `/logger/stats`, published at every flush and written as the `flownav.stats` metadata record
/// at close: how much the logger wrote and dropped so far.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct LoggerStats {
    /// Messages written to this file (all topics).
    pub written: u64,
    /// Images refused because the image queue was full (the writer fell behind).
    pub dropped_images: u64,
    /// Other data (flow, perception, goal, status, pose, world, log lines) refused.
    pub dropped_data: u64,
    /// Set-points and odometry refused: only when the critical queue's cap is reached.
    pub dropped_critical: u64,
    /// Messages refused after close or lost to a write error.
    pub lost: u64,
}

impl LoggerStats {
    /// All drops together.
    pub fn dropped(&self) -> u64 {
        self.dropped_images + self.dropped_data + self.dropped_critical + self.lost
    }
}

// ---- JSON schemas -------------------------------------------------------------------------------

fn nullable(t: &str) -> Value {
    json!({"type": [t, "null"]})
}

/// `/flow/field`: [`crate::flow::FlowField`].
pub fn flow_field_schema() -> Value {
    json!({
        "title": "flownav.FlowField",
        "description": "Block-matching optical flow between two frames (paper §2.2): rows × cols block vectors, row-major; (x, y) block centre in pixels of the older frame, (u, v) displacement in pixels per frame interval",
        "type": "object",
        "properties": {
            "rows": {"type": "integer"}, "cols": {"type": "integer"},
            "width": {"type": "integer"}, "height": {"type": "integer"},
            "vectors": {"type": "array", "items": {"type": "object", "properties": {
                "x": {"type": "number"}, "y": {"type": "number"},
                "u": {"type": "number"}, "v": {"type": "number"},
                "validity": {"type": "string", "enum": ["valid", "textureless", "ambiguous", "out_of_frame"]},
                "cost": {"type": "number"}},
                "required": ["x", "y", "u", "v", "validity", "cost"]}}
        },
        "required": ["rows", "cols", "width", "height", "vectors"]
    })
}

/// `/offis/perception`: [`PerceptionLog`].
pub fn perception_schema() -> Value {
    json!({
        "title": "flownav.Perception",
        "description": "OFFIS result for one frame pair: the two-plane object (TPO), the nearest obstacle, the rough (4×4, eq. 11) and fine (8×8, eq. 12) structure masks, and OFFIS attributes",
        "type": "object",
        "properties": {
            "tpo": {"type": "object", "properties": {
                "shape": {"type": "string", "enum": ["wall", "corner", "door", "corridor", "none"]},
                "confidence": {"type": "number"},
                "distance_m": nullable("number")}},
            "obstacle": {"type": "object", "properties": {
                "present": {"type": "boolean"},
                "distance_m": nullable("number"),
                "bearing_rad": nullable("number"),
                "cell": {"type": ["array", "null"], "items": {"type": "integer"}}}},
            "rough": {"type": "array", "items": {"type": "array", "items": {"type": "integer"}}},
            "fine": {"type": "array", "items": {"type": "array", "items": {"type": "integer"}}},
            "attributes": {"description": "OFFIS intermediate values (free-form)"}
        },
        "required": ["tpo", "obstacle", "rough", "fine"]
    })
}

/// `/pafsis/goal`: [`GoalLog`].
pub fn goal_schema() -> Value {
    json!({
        "title": "flownav.Goal",
        "description": "PAFSIS local goal: velocity m/s and heading rad (positive left) towards the current waypoint",
        "type": "object",
        "properties": {
            "v": {"type": "number"}, "angle_rad": {"type": "number"},
            "waypoint": nullable("string"), "waypoint_index": nullable("integer"),
            "remaining_m": nullable("number")},
        "required": ["v", "angle_rad"]
    })
}

/// `/control/setpoint`: [`SetpointLog`].
pub fn setpoint_schema() -> Value {
    json!({
        "title": "flownav.Setpoint",
        "description": "Body-velocity set-point sent to the base (v m/s, omega rad/s positive left), whether limits clamped it, and the request before clamping",
        "type": "object",
        "properties": {
            "v": {"type": "number"}, "omega": {"type": "number"}, "clamped": {"type": "boolean"},
            "requested": {"type": ["object", "null"], "properties": {"v": {"type": "number"}, "omega": {"type": "number"}}}},
        "required": ["v", "omega", "clamped"]
    })
}

/// `/base/odometry`: `hal::Odometry`.
pub fn odometry_schema() -> Value {
    json!({
        "title": "flownav.Odometry",
        "description": "What the base measured: body velocity (v m/s, omega rad/s) and cumulative encoder ticks; t_ns on the host monotonic clock",
        "type": "object",
        "properties": {
            "t_ns": {"type": "integer"},
            "velocity": {"type": "object", "properties": {"v": {"type": "number"}, "omega": {"type": "number"}}},
            "left_ticks": {"type": "integer"}, "right_ticks": {"type": "integer"}},
        "required": ["t_ns", "velocity", "left_ticks", "right_ticks"]
    })
}

/// `/base/status`: [`BaseStatusLog`].
pub fn base_status_schema() -> Value {
    json!({
        "title": "flownav.BaseStatus",
        "description": "Health flags reported by the base",
        "type": "object",
        "properties": {
            "t_ns": {"type": "integer"}, "battery_v": nullable("number"),
            "bumper": {"type": "boolean"}, "estop": {"type": "boolean"},
            "stopped_by_watchdog": {"type": "boolean"}, "motor_fault": {"type": "boolean"},
            "cliff": {"type": "boolean"}, "wheel_drop": {"type": "boolean"}},
        "required": ["t_ns", "bumper", "estop", "stopped_by_watchdog", "motor_fault", "cliff", "wheel_drop"]
    })
}

/// `/step/input`: [`StepInputLog`].
pub fn step_input_schema() -> Value {
    json!({
        "title": "flownav.StepInput",
        "description": "What the per-frame pipeline consumed, for replay: kind \"step\" (frame seq at t_ns stepped after the frame at prev_t_ns, odometry v m/s and omega rad/s as the base reported them, and the learned turn scale error and bend in rad/m that the step took out of omega) or \"fail_safe\" (the pipeline was stopped and reset at t_ns, with the reason)",
        "type": "object",
        "properties": {
            "kind": {"type": "string", "enum": ["step", "fail_safe"]},
            "seq": {"type": "integer"}, "t_ns": {"type": "integer"}, "prev_t_ns": {"type": "integer"},
            "v": {"type": "number"}, "omega": {"type": "number"},
            "odometry_scale": {"type": "number"}, "odometry_bend_rad_m": {"type": "number"},
            "reason": {"type": "string"}},
        "required": ["kind", "t_ns"]
    })
}

/// `/logger/stats`: [`LoggerStats`].
pub fn stats_schema() -> Value {
    json!({
        "title": "flownav.LoggerStats",
        "description": "Logger counters so far: messages written, drops per queue",
        "type": "object",
        "properties": {
            "written": {"type": "integer"}, "dropped_images": {"type": "integer"},
            "dropped_data": {"type": "integer"}, "dropped_critical": {"type": "integer"},
            "lost": {"type": "integer"}},
        "required": ["written", "dropped_images", "dropped_data", "dropped_critical", "lost"]
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::perception::{Obstacle, Tpo, TpoShape};

    #[test]
    fn perception_log_round_trips_with_attributes() {
        let mut fine = [[0u8; 8]; 8];
        fine[3][5] = 1;
        let p = PerceptionLog {
            perception: Perception {
                tpo: Tpo { shape: TpoShape::Corridor, confidence: 0.8125, distance_m: Some(2.1) },
                obstacle: Obstacle {
                    present: true,
                    distance_m: Some(1.3),
                    bearing_rad: Some(-0.2),
                    cell: Some([6, 3]),
                },
                rough: [[1, 0, 0, 1], [0; 4], [0; 4], [1; 4]],
                fine,
            },
            attributes: json!({"vplane_l2": [[0.5, 1.0]]}),
        };
        let text = serde_json::to_string(&p).unwrap();
        assert!(text.starts_with(r#"{"tpo":{"shape":"corridor""#), "{text}");
        assert_eq!(serde_json::from_str::<PerceptionLog>(&text).unwrap(), p);
    }
}
