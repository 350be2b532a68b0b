//! Foxglove's well-known message types, JSON-encoded, and their JSON schemas.
//!
//! Foxglove recognises a channel by its schema *name* (`foxglove.CompressedImage`, ...) in any of
//! its supported encodings; with JSON, `bytes` fields are base64 strings and time is
//! `{"sec", "nsec"}`. The schemas written here describe the fields flownav emits (a subset of
//! each type where it has optional parts flownav never fills), so a reader that validates
//! against them accepts our messages, and Foxglove's message-path autocompletion works.

use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

/// A point in time as Foxglove's JSON encoding writes it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    pub sec: u32,
    pub nsec: u32,
}

impl Time {
    /// Splits nanoseconds since the epoch (or any origin) into seconds and nanoseconds.
    pub fn from_ns(ns: u64) -> Self {
        Self { sec: (ns / 1_000_000_000).min(u32::MAX as u64) as u32, nsec: (ns % 1_000_000_000) as u32 }
    }

    pub fn to_ns(self) -> u64 {
        self.sec as u64 * 1_000_000_000 + self.nsec as u64
    }
}

/// A duration (`SceneEntity.lifetime`); zero means "until replaced".
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Duration {
    pub sec: i32,
    pub nsec: u32,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Color {
    pub r: f64,
    pub g: f64,
    pub b: f64,
    pub a: f64,
}

impl Color {
    pub const fn rgba(r: f64, g: f64, b: f64, a: f64) -> Self {
        Self { r, g, b, a }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Point2 {
    pub x: f64,
    pub y: f64,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Quaternion {
    pub const IDENTITY: Self = Self { x: 0.0, y: 0.0, z: 0.0, w: 1.0 };

    /// A rotation by `yaw` rad about +z (REP-103: counter-clockwise seen from above).
    pub fn from_yaw(yaw: f64) -> Self {
        let (s, c) = (yaw / 2.0).sin_cos();
        Self { x: 0.0, y: 0.0, z: s, w: c }
    }

    /// The rotation whose matrix is `m` (row-major, proper orthonormal), by Shepperd's method.
    pub fn from_matrix(m: [[f64; 3]; 3]) -> Self {
        let trace = m[0][0] + m[1][1] + m[2][2];
        if trace > 0.0 {
            let s = (trace + 1.0).sqrt() * 2.0;
            Self { w: 0.25 * s, x: (m[2][1] - m[1][2]) / s, y: (m[0][2] - m[2][0]) / s, z: (m[1][0] - m[0][1]) / s }
        } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
            let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
            Self { w: (m[2][1] - m[1][2]) / s, x: 0.25 * s, y: (m[0][1] + m[1][0]) / s, z: (m[0][2] + m[2][0]) / s }
        } else if m[1][1] > m[2][2] {
            let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
            Self { w: (m[0][2] - m[2][0]) / s, x: (m[0][1] + m[1][0]) / s, y: 0.25 * s, z: (m[1][2] + m[2][1]) / s }
        } else {
            let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
            Self { w: (m[1][0] - m[0][1]) / s, x: (m[0][2] + m[2][0]) / s, y: (m[1][2] + m[2][1]) / s, z: 0.25 * s }
        }
    }

    /// Rotates vector `v`.
    pub fn rotate(&self, v: [f64; 3]) -> [f64; 3] {
        let (x, y, z, w) = (self.x, self.y, self.z, self.w);
        // v + 2w(q×v) + 2q×(q×v)
        let t = [2.0 * (y * v[2] - z * v[1]), 2.0 * (z * v[0] - x * v[2]), 2.0 * (x * v[1] - y * v[0])];
        [
            v[0] + w * t[0] + (y * t[2] - z * t[1]),
            v[1] + w * t[1] + (z * t[0] - x * t[2]),
            v[2] + w * t[2] + (x * t[1] - y * t[0]),
        ]
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: Vector3,
    pub orientation: Quaternion,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct KeyValuePair {
    pub key: String,
    pub value: String,
}

/// `foxglove.CompressedImage`; `data` is base64 (the writer builds this JSON by hand, straight
/// from the JPEG bytes, to avoid a copy; this type is for reading it back).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    pub timestamp: Time,
    pub frame_id: String,
    pub data: String,
    pub format: String,
}

/// `foxglove.RawImage`; `data` is base64.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RawImage {
    pub timestamp: Time,
    pub frame_id: String,
    pub width: u32,
    pub height: u32,
    pub encoding: String,
    pub step: u32,
    pub data: String,
}

/// `foxglove.CameraCalibration` (pinhole, "plumb_bob" distortion), plus `flownav_calibration`: the
/// full `calib/*.toml` content (model, mount), so a replay gets the exact calibration back.
/// Foxglove ignores the extra field.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[allow(non_snake_case)]
pub struct CameraCalibration {
    pub timestamp: Time,
    pub frame_id: String,
    pub width: u32,
    pub height: u32,
    pub distortion_model: String,
    pub D: Vec<f64>,
    pub K: [f64; 9],
    pub R: [f64; 9],
    pub P: [f64; 12],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flownav_calibration: Option<hal::Calibration>,
}

/// `foxglove.PointsAnnotationType`.
pub mod points_type {
    pub const POINTS: u8 = 1;
    pub const LINE_LOOP: u8 = 2;
    pub const LINE_STRIP: u8 = 3;
    pub const LINE_LIST: u8 = 4;
}

/// `foxglove.PointsAnnotation`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PointsAnnotation {
    pub timestamp: Time,
    #[serde(rename = "type")]
    pub kind: u8,
    pub points: Vec<Point2>,
    pub outline_color: Color,
    pub outline_colors: Vec<Color>,
    pub fill_color: Color,
    pub thickness: f64,
    pub metadata: Vec<KeyValuePair>,
}

/// `foxglove.TextAnnotation`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TextAnnotation {
    pub timestamp: Time,
    pub position: Point2,
    pub text: String,
    pub font_size: f64,
    pub text_color: Color,
    pub background_color: Color,
    pub metadata: Vec<KeyValuePair>,
}

/// `foxglove.ImageAnnotations` (flownav draws no circles; the field is kept empty).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ImageAnnotations {
    pub circles: Vec<Value>,
    pub points: Vec<PointsAnnotation>,
    pub texts: Vec<TextAnnotation>,
}

/// `foxglove.FrameTransform`: the pose of `child_frame_id` in `parent_frame_id`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameTransform {
    pub timestamp: Time,
    pub parent_frame_id: String,
    pub child_frame_id: String,
    pub translation: Vector3,
    pub rotation: Quaternion,
}

/// `foxglove.CubePrimitive`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CubePrimitive {
    pub pose: Pose,
    pub size: Vector3,
    pub color: Color,
}

/// `foxglove.CylinderPrimitive` (flat faces perpendicular to z).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CylinderPrimitive {
    pub pose: Pose,
    pub size: Vector3,
    pub bottom_scale: f64,
    pub top_scale: f64,
    pub color: Color,
}

/// `foxglove.SceneEntity` (flownav uses cubes and cylinders; the other primitive lists stay empty).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SceneEntity {
    pub timestamp: Time,
    pub frame_id: String,
    pub id: String,
    pub lifetime: Duration,
    pub frame_locked: bool,
    pub metadata: Vec<KeyValuePair>,
    pub arrows: Vec<Value>,
    pub cubes: Vec<CubePrimitive>,
    pub spheres: Vec<Value>,
    pub cylinders: Vec<CylinderPrimitive>,
    pub lines: Vec<Value>,
    pub triangles: Vec<Value>,
    pub texts: Vec<Value>,
    pub models: Vec<Value>,
}

/// `foxglove.SceneEntityDeletion`; `kind` 1 = delete all entities on the topic.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SceneEntityDeletion {
    pub timestamp: Time,
    #[serde(rename = "type")]
    pub kind: u8,
    pub id: String,
}

/// `foxglove.SceneUpdate`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SceneUpdate {
    pub deletions: Vec<SceneEntityDeletion>,
    pub entities: Vec<SceneEntity>,
}

/// `foxglove.Log`; `level` is a `foxglove.LogLevel` (1 debug … 5 fatal).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Log {
    pub timestamp: Time,
    pub level: u8,
    pub message: String,
    pub name: String,
    pub file: String,
    pub line: u32,
}

// ---- JSON schemas -------------------------------------------------------------------------------

fn object(title: &str, description: &str, props: &[(&str, Value)]) -> Value {
    let mut properties = serde_json::Map::new();
    let mut required = Vec::new();
    for (name, schema) in props {
        properties.insert((*name).to_string(), schema.clone());
        required.push(Value::from(*name));
    }
    json!({"title": title, "description": description, "type": "object", "properties": properties, "required": required})
}

fn time() -> Value {
    json!({"type": "object", "title": "time", "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}})
}

fn duration() -> Value {
    json!({"type": "object", "title": "duration", "properties": {
        "sec": {"type": "integer"},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}})
}

fn number() -> Value {
    json!({"type": "number"})
}

fn string() -> Value {
    json!({"type": "string"})
}

fn uint() -> Value {
    json!({"type": "integer", "minimum": 0})
}

fn bytes() -> Value {
    json!({"type": "string", "contentEncoding": "base64"})
}

fn array(items: Value) -> Value {
    json!({"type": "array", "items": items})
}

fn fixed_array(n: usize) -> Value {
    json!({"type": "array", "items": {"type": "number"}, "minItems": n, "maxItems": n})
}

fn color() -> Value {
    object(
        "foxglove.Color",
        "RGBA, each in [0, 1]",
        &[("r", number()), ("g", number()), ("b", number()), ("a", number())],
    )
}

fn point2() -> Value {
    object("foxglove.Point2", "Image point, pixels from the top-left corner", &[("x", number()), ("y", number())])
}

fn vector3() -> Value {
    object("foxglove.Vector3", "3D vector, m", &[("x", number()), ("y", number()), ("z", number())])
}

fn quaternion() -> Value {
    object("foxglove.Quaternion", "Rotation", &[("x", number()), ("y", number()), ("z", number()), ("w", number())])
}

fn pose() -> Value {
    object("foxglove.Pose", "Position and orientation", &[("position", vector3()), ("orientation", quaternion())])
}

fn key_values() -> Value {
    array(object("foxglove.KeyValuePair", "A key with its value", &[("key", string()), ("value", string())]))
}

fn enumeration(title: &str, values: &[(&str, u8)]) -> Value {
    let one_of: Vec<Value> = values.iter().map(|(name, v)| json!({"title": name, "const": v})).collect();
    json!({"title": title, "oneOf": one_of})
}

fn any_array() -> Value {
    json!({"type": "array"})
}

/// `foxglove.CompressedImage`.
pub fn compressed_image_schema() -> Value {
    object(
        "foxglove.CompressedImage",
        "A compressed image",
        &[("timestamp", time()), ("frame_id", string()), ("data", bytes()), ("format", string())],
    )
}

/// `foxglove.RawImage`.
pub fn raw_image_schema() -> Value {
    object(
        "foxglove.RawImage",
        "A raw image",
        &[
            ("timestamp", time()),
            ("frame_id", string()),
            ("width", uint()),
            ("height", uint()),
            ("encoding", string()),
            ("step", uint()),
            ("data", bytes()),
        ],
    )
}

/// `foxglove.CameraCalibration` (with flownav's optional `flownav_calibration` extension).
pub fn camera_calibration_schema() -> Value {
    let mut schema = object(
        "foxglove.CameraCalibration",
        "Camera calibration parameters",
        &[
            ("timestamp", time()),
            ("frame_id", string()),
            ("width", uint()),
            ("height", uint()),
            ("distortion_model", string()),
            ("D", array(number())),
            ("K", fixed_array(9)),
            ("R", fixed_array(9)),
            ("P", fixed_array(12)),
        ],
    );
    schema["properties"]["flownav_calibration"] = json!({"type": "object",
        "description": "flownav extension: the calib/*.toml content (model, camera, mount)"});
    schema
}

/// `foxglove.ImageAnnotations`.
pub fn image_annotations_schema() -> Value {
    let points = object(
        "foxglove.PointsAnnotation",
        "An array of points on a 2D image",
        &[
            ("timestamp", time()),
            (
                "type",
                enumeration(
                    "foxglove.PointsAnnotationType",
                    &[("UNKNOWN", 0), ("POINTS", 1), ("LINE_LOOP", 2), ("LINE_STRIP", 3), ("LINE_LIST", 4)],
                ),
            ),
            ("points", array(point2())),
            ("outline_color", color()),
            ("outline_colors", array(color())),
            ("fill_color", color()),
            ("thickness", number()),
            ("metadata", key_values()),
        ],
    );
    let texts = object(
        "foxglove.TextAnnotation",
        "A text label on a 2D image",
        &[
            ("timestamp", time()),
            ("position", point2()),
            ("text", string()),
            ("font_size", number()),
            ("text_color", color()),
            ("background_color", color()),
            ("metadata", key_values()),
        ],
    );
    object(
        "foxglove.ImageAnnotations",
        "Array of annotations for a 2D image",
        &[("circles", any_array()), ("points", array(points)), ("texts", array(texts))],
    )
}

/// `foxglove.FrameTransform`.
pub fn frame_transform_schema() -> Value {
    object(
        "foxglove.FrameTransform",
        "A transform between two reference frames in 3D space",
        &[
            ("timestamp", time()),
            ("parent_frame_id", string()),
            ("child_frame_id", string()),
            ("translation", vector3()),
            ("rotation", quaternion()),
        ],
    )
}

/// `foxglove.SceneUpdate` (cubes and cylinders described; other primitive lists are empty arrays).
pub fn scene_update_schema() -> Value {
    let cube = object(
        "foxglove.CubePrimitive",
        "A cube or rectangular prism",
        &[("pose", pose()), ("size", vector3()), ("color", color())],
    );
    let cylinder = object(
        "foxglove.CylinderPrimitive",
        "A cylinder",
        &[
            ("pose", pose()),
            ("size", vector3()),
            ("bottom_scale", number()),
            ("top_scale", number()),
            ("color", color()),
        ],
    );
    let entity = object(
        "foxglove.SceneEntity",
        "A visual element in a 3D scene",
        &[
            ("timestamp", time()),
            ("frame_id", string()),
            ("id", string()),
            ("lifetime", duration()),
            ("frame_locked", json!({"type": "boolean"})),
            ("metadata", key_values()),
            ("arrows", any_array()),
            ("cubes", array(cube)),
            ("spheres", any_array()),
            ("cylinders", array(cylinder)),
            ("lines", any_array()),
            ("triangles", any_array()),
            ("texts", any_array()),
            ("models", any_array()),
        ],
    );
    let deletion = object(
        "foxglove.SceneEntityDeletion",
        "Command to remove previously published entities",
        &[
            ("timestamp", time()),
            ("type", enumeration("foxglove.SceneEntityDeletionType", &[("MATCHING_ID", 0), ("ALL", 1)])),
            ("id", string()),
        ],
    );
    object(
        "foxglove.SceneUpdate",
        "An update to the entities displayed in a 3D scene",
        &[("deletions", array(deletion)), ("entities", array(entity))],
    )
}

/// `foxglove.Log`.
pub fn log_schema() -> Value {
    object(
        "foxglove.Log",
        "A log message",
        &[
            ("timestamp", time()),
            (
                "level",
                enumeration(
                    "foxglove.LogLevel",
                    &[("UNKNOWN", 0), ("DEBUG", 1), ("INFO", 2), ("WARNING", 3), ("ERROR", 4), ("FATAL", 5)],
                ),
            ),
            ("message", string()),
            ("name", string()),
            ("file", string()),
            ("line", uint()),
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quaternion_from_matrix_matches_yaw_and_rotates_axes() {
        for yaw in [-3.0, -1.0, 0.0, 0.5, 2.9] {
            let (s, c) = f64::sin_cos(yaw);
            let q = Quaternion::from_matrix([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]);
            let r = Quaternion::from_yaw(yaw);
            let sign = if q.w * r.w < 0.0 { -1.0 } else { 1.0 };
            assert!((q.z - sign * r.z).abs() < 1e-12 && (q.w - sign * r.w).abs() < 1e-12, "{yaw}: {q:?} vs {r:?}");
        }
        // Optical (x right, y down, z forward) into REP-103 robot axes.
        let q = Quaternion::from_matrix([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]);
        let close = |a: [f64; 3], b: [f64; 3]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12);
        assert!(close(q.rotate([0.0, 0.0, 1.0]), [1.0, 0.0, 0.0]));
        assert!(close(q.rotate([1.0, 0.0, 0.0]), [0.0, -1.0, 0.0]));
        assert!(close(q.rotate([0.0, 1.0, 0.0]), [0.0, 0.0, -1.0]));
    }

    #[test]
    fn schemas_require_every_field_the_messages_emit() {
        let log = Log { level: 2, message: "hi".into(), ..Default::default() };
        let emitted = serde_json::to_value(&log).unwrap();
        let schema = log_schema();
        let required: Vec<&str> = schema["required"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
        let fields: Vec<&str> = emitted.as_object().unwrap().keys().map(String::as_str).collect();
        for f in &fields {
            assert!(required.contains(f), "{f} missing from the schema");
        }
        let update =
            serde_json::to_value(SceneUpdate { entities: vec![SceneEntity::default()], ..Default::default() }).unwrap();
        let entity_schema = &scene_update_schema()["properties"]["entities"]["items"];
        for f in update["entities"][0].as_object().unwrap().keys() {
            assert!(entity_schema["properties"].get(f).is_some(), "SceneEntity.{f} missing from the schema");
        }
    }

    #[test]
    fn time_splits_nanoseconds() {
        let t = Time::from_ns(1_700_000_000_123_456_789);
        assert_eq!(t, Time { sec: 1_700_000_000, nsec: 123_456_789 });
        assert_eq!(t.to_ns(), 1_700_000_000_123_456_789);
    }
}
