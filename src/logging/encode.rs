//! Pure encoders: flownav values → the bytes of one MCAP message on one topic.
//!
//! The writer thread calls these; they are public so that `replay --check` can encode a
//! recomputed value exactly as the logger would and compare bytes with the logged message
//! (byte equality of the JSON is float equality, without relying on float parsing).

use hal::{Calibration, LumaImage, Odometry};
use serde_json::Value;

use super::foxglove::{
    CameraCalibration, Color, CubePrimitive, CylinderPrimitive, Duration, FrameTransform, ImageAnnotations,
    KeyValuePair, Log, Point2, PointsAnnotation, Pose, Quaternion, SceneEntity, SceneEntityDeletion, SceneUpdate,
    TextAnnotation, Time, Vector3, points_type,
};
use super::payload::{GoalLog, LogLevel, PerceptionLog, Pose2D, SetpointLog, StepInputLog, WorldGeometry};
use super::{FRAME_BASE, FRAME_CAMERA, FRAME_ODOM};
use crate::flow::{FlowField, Validity};
use crate::perception::Perception;
use base64::Engine as _;
use base64::engine::general_purpose::STANDARD as BASE64;

/// How much longer than the true displacement flow arrows are drawn (flow is a few pixels per
/// frame; at ×1 it would be invisible on a 1280-pixel-wide image).
pub const ARROW_SCALE: f64 = 4.0;

fn to_json<T: serde::Serialize>(value: &T) -> Vec<u8> {
    // Serialising plain data structs (no maps with non-string keys, no failing Serialize impls)
    // cannot fail; an empty object keeps the file valid should that ever change.
    serde_json::to_vec(value).unwrap_or_else(|_| b"{}".to_vec())
}

/// Appends the standard (RFC 4648, padded) base64 of `data` to `out`, the encoding Foxglove
/// expects for `bytes` fields of JSON messages; written in place, so a 1 MB image is one pass.
fn push_base64(data: &[u8], out: &mut Vec<u8>) {
    let start = out.len();
    out.resize(start + base64::encoded_len(data.len(), true).unwrap_or(0), 0);
    let written = BASE64.encode_slice(data, &mut out[start..]).unwrap_or(0);
    out.truncate(start + written);
}

fn push_time(out: &mut Vec<u8>, t: Time) {
    out.extend_from_slice(format!("{{\"sec\":{},\"nsec\":{}}}", t.sec, t.nsec).as_bytes());
}

/// `foxglove.CompressedImage` with the JPEG bytes as they came from the camera (no re-encoding).
pub fn compressed_image(log_time_ns: u64, jpeg: &[u8], out: &mut Vec<u8>) {
    out.clear();
    out.extend_from_slice(b"{\"timestamp\":");
    push_time(out, Time::from_ns(log_time_ns));
    out.extend_from_slice(format!(",\"frame_id\":\"{FRAME_CAMERA}\",\"format\":\"jpeg\",\"data\":\"").as_bytes());
    push_base64(jpeg, out);
    out.extend_from_slice(b"\"}");
}

/// `foxglove.RawImage`, `mono8`, rows packed (`step == width`).
pub fn raw_image(log_time_ns: u64, image: &LumaImage, out: &mut Vec<u8>) {
    out.clear();
    out.extend_from_slice(b"{\"timestamp\":");
    push_time(out, Time::from_ns(log_time_ns));
    out.extend_from_slice(
        format!(
            ",\"frame_id\":\"{FRAME_CAMERA}\",\"width\":{w},\"height\":{h},\"encoding\":\"mono8\",\"step\":{w},\"data\":\"",
            w = image.width(),
            h = image.height()
        )
        .as_bytes(),
    );
    push_base64(image.data(), out);
    out.extend_from_slice(b"\"}");
}

/// `foxglove.CameraCalibration` from the pinhole intrinsics (K, P, plumb_bob D, identity R).
pub fn camera_calibration(log_time_ns: u64, c: &Calibration) -> Vec<u8> {
    let i = &c.camera;
    to_json(&CameraCalibration {
        timestamp: Time::from_ns(log_time_ns),
        frame_id: FRAME_CAMERA.into(),
        width: i.width,
        height: i.height,
        distortion_model: "plumb_bob".into(),
        D: i.distortion.to_vec(),
        K: [i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0],
        R: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P: [i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        flownav_calibration: Some(c.clone()),
    })
}

/// The camera's optical frame (x right, y down, z forward) in the robot frame, from the mount:
/// `base_link → camera`, so the 3D panel can show the camera frustum on the robot.
pub fn camera_mount_transform(log_time_ns: u64, c: &Calibration) -> Vec<u8> {
    let m = &c.mount;
    // Optical axes in robot coordinates for a level camera: x_opt = -y, y_opt = -z, z_opt = x.
    let level = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]];
    // Pitch down by `pitch_rad`: rotation about the robot's +y axis.
    let (s, co) = m.pitch_rad.sin_cos();
    let pitch = [[co, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, co]];
    let mut r = [[0.0; 3]; 3];
    for (i, row) in r.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| pitch[i][k] * level[k][j]).sum();
        }
    }
    to_json(&FrameTransform {
        timestamp: Time::from_ns(log_time_ns),
        parent_frame_id: FRAME_BASE.into(),
        child_frame_id: FRAME_CAMERA.into(),
        translation: Vector3 { x: m.x_m, y: m.y_m, z: m.z_m },
        rotation: Quaternion::from_matrix(r),
    })
}

/// `/flow/field`: the flow field as JSON.
pub fn flow_field(field: &FlowField) -> Vec<u8> {
    to_json(field)
}

/// Colour of a flow arrow by validity: green valid, grey textureless, orange ambiguous, red at
/// the frame border.
pub fn validity_color(v: Validity) -> Color {
    match v {
        Validity::Valid => Color::rgba(0.1, 0.9, 0.2, 1.0),
        Validity::Textureless => Color::rgba(0.6, 0.6, 0.6, 0.8),
        Validity::Ambiguous => Color::rgba(1.0, 0.6, 0.0, 1.0),
        Validity::OutOfFrame => Color::rgba(0.9, 0.1, 0.1, 1.0),
    }
}

/// `/flow/annotations`: flow arrows (a `LINE_LIST`: shaft plus two head strokes per vector,
/// ×[`ARROW_SCALE`], coloured by validity) and, when the frame's perception is known, the fine
/// (8×8, eq. 12) and rough (4×4, eq. 11) structure masks as filled cells, the obstacle cell, and a
/// text label with the TPO.
pub fn flow_annotations(log_time_ns: u64, field: &FlowField, perception: Option<&Perception>) -> Vec<u8> {
    let t = Time::from_ns(log_time_ns);
    let mut arrows = PointsAnnotation {
        timestamp: t,
        kind: points_type::LINE_LIST,
        thickness: 2.0,
        outline_color: validity_color(Validity::Valid),
        ..Default::default()
    };
    for v in &field.vectors {
        // Block centres are in pixel-centre coordinates; Foxglove's origin is the corner.
        let (x0, y0) = (v.x as f64 + 0.5, v.y as f64 + 0.5);
        let (du, dv) = (v.u as f64 * ARROW_SCALE, v.v as f64 * ARROW_SCALE);
        let (x1, y1) = (x0 + du, y0 + dv);
        let color = validity_color(v.validity);
        let mut segment = |a: (f64, f64), b: (f64, f64)| {
            arrows.points.push(Point2 { x: a.0, y: a.1 });
            arrows.points.push(Point2 { x: b.0, y: b.1 });
            arrows.outline_colors.push(color);
        };
        let len = du.hypot(dv);
        if len < 1.0 {
            // No visible motion: a small cross marks the block.
            segment((x0 - 2.0, y0), (x0 + 2.0, y0));
            segment((x0, y0 - 2.0), (x0, y0 + 2.0));
            continue;
        }
        segment((x0, y0), (x1, y1));
        let head = (len * 0.3).min(6.0);
        let (ux, uy) = (du / len, dv / len);
        for side in [-1.0, 1.0] {
            // Head strokes at ±30° from the reversed shaft.
            let (c, s) = (0.866_025_403_784_438_6, 0.5 * side);
            let (hx, hy) = (-ux * c - -uy * s, -ux * s + -uy * c);
            segment((x1, y1), (x1 + hx * head, y1 + hy * head));
        }
    }
    let mut annotations = ImageAnnotations { points: vec![arrows], ..Default::default() };
    if let Some(p) = perception {
        let (w, h) = (field.width as f64, field.height as f64);
        let mut cells = |n: usize, mask: &dyn Fn(usize, usize) -> bool, outline: Color, fill: Color, thickness| {
            let (cw, ch) = (w / n as f64, h / n as f64);
            for r in 0..n {
                for c in 0..n {
                    if mask(r, c) {
                        annotations.points.push(rectangle(
                            t,
                            c as f64 * cw,
                            r as f64 * ch,
                            cw,
                            ch,
                            outline,
                            fill,
                            thickness,
                        ));
                    }
                }
            }
        };
        cells(8, &|r, c| p.fine[r][c] != 0, Color::rgba(0.2, 0.5, 1.0, 0.6), Color::rgba(0.2, 0.5, 1.0, 0.2), 1.0);
        cells(4, &|r, c| p.rough[r][c] != 0, Color::rgba(1.0, 1.0, 0.0, 0.9), Color::rgba(0.0, 0.0, 0.0, 0.0), 3.0);
        if let Some([r, c]) = p.obstacle.cell.filter(|_| p.obstacle.present) {
            let (cw, ch) = (w / 8.0, h / 8.0);
            let red = Color::rgba(1.0, 0.0, 0.0, 1.0);
            annotations.points.push(rectangle(
                t,
                c as f64 * cw,
                r as f64 * ch,
                cw,
                ch,
                red,
                Color::rgba(1.0, 0.0, 0.0, 0.3),
                4.0,
            ));
        }
        let distance = p.tpo.distance_m.map(|d| format!(" {d:.2} m")).unwrap_or_default();
        let obstacle = match (p.obstacle.present, p.obstacle.distance_m) {
            (true, Some(d)) => format!(" | obstacle {d:.2} m"),
            (true, None) => " | obstacle".to_string(),
            _ => String::new(),
        };
        annotations.texts.push(TextAnnotation {
            timestamp: t,
            position: Point2 { x: 8.0, y: 28.0 },
            text: format!("{} {:.2}{distance}{obstacle}", p.tpo.shape.name(), p.tpo.confidence),
            font_size: 24.0,
            text_color: Color::rgba(1.0, 1.0, 1.0, 1.0),
            background_color: Color::rgba(0.0, 0.0, 0.0, 0.6),
            metadata: Vec::new(),
        });
    }
    to_json(&annotations)
}

#[allow(clippy::too_many_arguments)]
fn rectangle(t: Time, x: f64, y: f64, w: f64, h: f64, outline: Color, fill: Color, thickness: f64) -> PointsAnnotation {
    PointsAnnotation {
        timestamp: t,
        kind: points_type::LINE_LOOP,
        points: vec![Point2 { x, y }, Point2 { x: x + w, y }, Point2 { x: x + w, y: y + h }, Point2 { x, y: y + h }],
        outline_color: outline,
        outline_colors: Vec::new(),
        fill_color: fill,
        thickness,
        metadata: Vec::new(),
    }
}

/// `/offis/perception`: the perception and its attributes.
pub fn perception(p: &Perception, attributes: &Value) -> Vec<u8> {
    to_json(&PerceptionLog { perception: p.clone(), attributes: attributes.clone() })
}

/// `/pafsis/goal`.
pub fn goal(g: &GoalLog) -> Vec<u8> {
    to_json(g)
}

/// `/control/setpoint`.
pub fn setpoint(s: &SetpointLog) -> Vec<u8> {
    to_json(s)
}

/// `/step/input`.
pub fn step_input(s: &StepInputLog) -> Vec<u8> {
    to_json(s)
}

/// `/base/odometry`.
pub fn odometry(o: &Odometry) -> Vec<u8> {
    to_json(o)
}

/// `/tf`: the robot pose, `odom → base_link`.
pub fn robot_pose(log_time_ns: u64, pose: &Pose2D) -> Vec<u8> {
    to_json(&FrameTransform {
        timestamp: Time::from_ns(log_time_ns),
        parent_frame_id: FRAME_ODOM.into(),
        child_frame_id: FRAME_BASE.into(),
        translation: Vector3 { x: pose.x_m, y: pose.y_m, z: 0.0 },
        rotation: Quaternion::from_yaw(pose.theta_rad),
    })
}

/// `/sim/world`: one entity per shape in the odom frame (the sim's world frame); the update first
/// deletes everything on the topic so a changed world replaces the old one.
pub fn world(log_time_ns: u64, world: &WorldGeometry) -> Vec<u8> {
    let t = Time::from_ns(log_time_ns);
    let entity = |id: &str| SceneEntity {
        timestamp: t,
        frame_id: FRAME_ODOM.into(),
        id: id.into(),
        lifetime: Duration::default(),
        frame_locked: false,
        ..Default::default()
    };
    let mut entities = Vec::new();
    for b in &world.boxes {
        let mut e = entity(&b.id);
        e.cubes.push(CubePrimitive {
            pose: Pose {
                position: Vector3 { x: b.center_m[0], y: b.center_m[1], z: b.size_m[2] / 2.0 },
                orientation: Quaternion::from_yaw(b.yaw_rad),
            },
            size: Vector3 { x: b.size_m[0], y: b.size_m[1], z: b.size_m[2] },
            color: if b.wall { Color::rgba(0.7, 0.7, 0.72, 0.9) } else { Color::rgba(1.0, 0.55, 0.1, 1.0) },
        });
        e.metadata.push(KeyValuePair { key: "kind".into(), value: if b.wall { "wall" } else { "obstacle" }.into() });
        entities.push(e);
    }
    for c in &world.cylinders {
        let mut e = entity(&c.id);
        e.cylinders.push(CylinderPrimitive {
            pose: Pose {
                position: Vector3 { x: c.center_m[0], y: c.center_m[1], z: c.height_m / 2.0 },
                orientation: Quaternion::IDENTITY,
            },
            size: Vector3 { x: 2.0 * c.radius_m, y: 2.0 * c.radius_m, z: c.height_m },
            bottom_scale: 1.0,
            top_scale: 1.0,
            color: Color::rgba(0.9, 0.3, 0.6, 1.0),
        });
        e.metadata.push(KeyValuePair { key: "kind".into(), value: "obstacle".into() });
        entities.push(e);
    }
    to_json(&SceneUpdate {
        deletions: vec![SceneEntityDeletion { timestamp: t, kind: 1, id: String::new() }],
        entities,
    })
}

/// `/log`.
pub fn log_line(log_time_ns: u64, level: LogLevel, message: &str) -> Vec<u8> {
    to_json(&Log {
        timestamp: Time::from_ns(log_time_ns),
        level: level as u8,
        message: message.into(),
        name: "flownav".into(),
        file: String::new(),
        line: 0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flow::FlowVector;
    use crate::logging::foxglove::{CompressedImage, RawImage};

    #[test]
    fn images_decode_back_to_their_bytes() {
        let jpeg: Vec<u8> = (0..1000u32).map(|i| (i * 7 % 251) as u8).collect();
        let mut out = Vec::new();
        compressed_image(1_500_000_001, &jpeg, &mut out);
        let msg: CompressedImage = serde_json::from_slice(&out).unwrap();
        assert_eq!((msg.timestamp.sec, msg.timestamp.nsec, msg.format.as_str()), (1, 500_000_001, "jpeg"));
        assert_eq!(BASE64.decode(&msg.data).unwrap(), jpeg);

        let img = LumaImage::from_fn(13, 7, |x, y| (x * 19 + y * 3) as u8);
        raw_image(42, &img, &mut out);
        let msg: RawImage = serde_json::from_slice(&out).unwrap();
        assert_eq!((msg.width, msg.height, msg.step, msg.encoding.as_str()), (13, 7, 13, "mono8"));
        assert_eq!(BASE64.decode(&msg.data).unwrap(), img.data());
    }

    #[test]
    fn calibration_matrices_follow_the_pinhole_model() {
        let c = Calibration::nominal_c310();
        let msg: CameraCalibration = serde_json::from_slice(&camera_calibration(0, &c)).unwrap();
        assert_eq!(msg.K, [1272.0, 0.0, 639.5, 0.0, 1272.0, 359.5, 0.0, 0.0, 1.0]);
        assert_eq!(msg.P[3], 0.0);
        assert_eq!(msg.flownav_calibration.as_ref(), Some(&c));
        // The optical axis of a camera pitched down looks forward and down in the robot frame.
        let mut pitched = c.clone();
        pitched.mount.pitch_rad = 0.3;
        let tf: FrameTransform = serde_json::from_slice(&camera_mount_transform(0, &pitched)).unwrap();
        let axis = tf.rotation.rotate([0.0, 0.0, 1.0]);
        assert!(
            (axis[0] - 0.3f64.cos()).abs() < 1e-12 && axis[1].abs() < 1e-12 && (axis[2] + 0.3f64.sin()).abs() < 1e-12
        );
        assert_eq!((tf.translation.x, tf.translation.z), (0.10, 0.40));
    }

    #[test]
    fn annotations_draw_one_coloured_arrow_per_vector_and_the_mask_cells() {
        let field = FlowField {
            rows: 1,
            cols: 2,
            width: 64,
            height: 32,
            vectors: vec![
                FlowVector { x: 15.5, y: 15.5, u: 2.0, v: 0.0, validity: Validity::Valid, cost: 1.0 },
                FlowVector { x: 47.5, y: 15.5, u: 0.0, v: 0.0, validity: Validity::Textureless, cost: 0.0 },
            ],
        };
        let msg: ImageAnnotations = serde_json::from_slice(&flow_annotations(0, &field, None)).unwrap();
        let arrows = &msg.points[0];
        assert_eq!(arrows.kind, points_type::LINE_LIST);
        assert_eq!(arrows.points.len(), 2 * arrows.outline_colors.len());
        assert_eq!(arrows.points[0], Point2 { x: 16.0, y: 16.0 });
        assert_eq!(arrows.points[1], Point2 { x: 16.0 + 2.0 * ARROW_SCALE, y: 16.0 });
        assert_eq!(arrows.outline_colors[0], validity_color(Validity::Valid));
        assert_eq!(*arrows.outline_colors.last().unwrap(), validity_color(Validity::Textureless));

        let mut p = Perception::default();
        p.fine[0][7] = 1;
        p.rough[1][0] = 1;
        let msg: ImageAnnotations = serde_json::from_slice(&flow_annotations(0, &field, Some(&p))).unwrap();
        assert_eq!(msg.points.len(), 3);
        assert_eq!(msg.points[1].points[0], Point2 { x: 56.0, y: 0.0 });
        assert_eq!(msg.points[2].points[2], Point2 { x: 16.0, y: 16.0 });
        assert!(msg.texts[0].text.starts_with("none"));
    }
}
