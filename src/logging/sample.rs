//! A synthetic run written through the real logger: every topic, deterministic content. Used by
//! `flownav log sample` (CI's independent check with the Python `mcap` package), the tests and
//! the benchmark.

use std::path::Path;

use hal::{BaseStatus, BodyVelocity, Calibration, LumaImage, Odometry};
use serde_json::json;

use super::payload::{GoalLog, LogLevel, Pose2D, SetpointLog, WorldBox, WorldCylinder, WorldGeometry};
use super::{LogError, LogHandle, LogOptions, LogSummary, LogWriter};
use crate::flow::{FlowField, FlowVector, Validity};
use crate::perception::{Obstacle, Perception, Tpo, TpoShape};

/// Frame interval of the sample, ns (30 fps).
pub const FRAME_NS: u64 = 33_333_333;

/// How frames are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SampleImages {
    /// `foxglove.RawImage` mono8, as `sim` logs them.
    Mono8,
    /// `foxglove.CompressedImage`, JPEG bytes, as `run` logs a camera's MJPEG.
    Jpeg,
}

/// Frame `i` of the sample: a textured pattern moving 2 px right per frame.
pub fn frame(i: u64, width: usize, height: usize) -> LumaImage {
    let shift = 2 * i as usize;
    LumaImage::from_fn(width, height, |x, y| {
        let u = x + 10_000 - shift;
        (((u * 37) ^ (y * 91)) % 251) as u8 ^ if (u / 16 + y / 16).is_multiple_of(2) { 0 } else { 0x80 }
    })
}

/// JPEG bytes of frame `i` (quality 80).
pub fn jpeg_frame(i: u64, width: usize, height: usize) -> Vec<u8> {
    let img = frame(i, width, height);
    let mut out = Vec::new();
    let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 80);
    // Encoding an in-memory 8-bit grey image of valid size cannot fail.
    let _ = enc.encode(img.data(), width as u32, height as u32, image::ExtendedColorType::L8);
    out
}

/// The flow field of frame `i`: 16×16 vectors of (2, 0) px, a textureless corner.
pub fn flow_field(i: u64, width: usize, height: usize) -> FlowField {
    let (rows, cols) = (16, 16);
    let mut vectors = Vec::with_capacity(rows * cols);
    for r in 0..rows {
        for c in 0..cols {
            let validity = match (r, c) {
                (0, 0) => Validity::Textureless,
                (0, 15) => Validity::OutOfFrame,
                (15, _) if (c + i as usize).is_multiple_of(5) => Validity::Ambiguous,
                _ => Validity::Valid,
            };
            vectors.push(FlowVector {
                x: (c as f32 + 0.5) * width as f32 / cols as f32 - 0.5,
                y: (r as f32 + 0.5) * height as f32 / rows as f32 - 0.5,
                u: 2.0 + 0.01 * r as f32,
                v: 0.1 * (c as f32 - 7.5) / 7.5,
                validity,
                cost: 3.0 + (r * c) as f32 * 0.125,
            });
        }
    }
    FlowField { rows, cols, width, height, vectors }
}

/// The perception of frame `i`.
pub fn perception(i: u64) -> Perception {
    let mut fine = [[0u8; 8]; 8];
    for (r, row) in fine.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = u8::from(c == 0 || c == 7 || (r + c + i as usize).is_multiple_of(9));
        }
    }
    Perception {
        tpo: Tpo {
            shape: TpoShape::ALL[(i / 10) as usize % 5],
            confidence: 0.5 + 0.4 * ((i as f64) * 0.1).sin().abs(),
            distance_m: (!i.is_multiple_of(7)).then_some(3.0 - 0.01 * i as f64),
        },
        obstacle: Obstacle {
            present: i.is_multiple_of(3),
            distance_m: (i.is_multiple_of(3)).then_some(1.2 + 0.001 * i as f64),
            bearing_rad: (i.is_multiple_of(3)).then_some(-0.1),
            cell: (i.is_multiple_of(3)).then_some([5, 3]),
        },
        rough: [[1, 0, 0, 1], [1, 0, 0, 1], [1, 0, 0, 1], [1, 1, 1, 1]],
        fine,
    }
}

/// The set-point of frame `i` (every 4th is clamped).
pub fn setpoint(i: u64) -> SetpointLog {
    let omega = 0.3 * ((i as f64) * 0.05).sin();
    SetpointLog {
        v: 0.25,
        omega,
        clamped: i.is_multiple_of(4),
        requested: (i.is_multiple_of(4)).then_some(BodyVelocity { v: 0.4, omega }),
    }
}

/// Odometry sample `k` (twice the frame rate).
pub fn odometry(k: u64) -> Odometry {
    Odometry {
        t_ns: k * FRAME_NS / 2 + 1_000,
        velocity: BodyVelocity::new(0.25, 0.3 * ((k as f64) * 0.025).sin()),
        left_ticks: 10 * k as i64,
        right_ticks: 11 * k as i64,
    }
}

/// The sample world: a corridor of two walls, a box and a person.
pub fn world() -> WorldGeometry {
    WorldGeometry {
        boxes: vec![
            WorldBox {
                id: "wall_left".into(),
                center_m: [5.0, 1.0],
                size_m: [10.0, 0.1, 2.5],
                yaw_rad: 0.0,
                wall: true,
            },
            WorldBox {
                id: "wall_right".into(),
                center_m: [5.0, -1.0],
                size_m: [10.0, 0.1, 2.5],
                yaw_rad: 0.0,
                wall: true,
            },
            WorldBox { id: "box".into(), center_m: [3.0, 0.4], size_m: [0.4, 0.4, 0.5], yaw_rad: 0.3, wall: false },
        ],
        cylinders: vec![WorldCylinder { id: "person".into(), center_m: [6.0, -0.3], radius_m: 0.25, height_m: 1.7 }],
    }
}

/// Logs frame `i` of the sample (all per-frame topics) through `log`.
pub fn log_frame(log: &LogHandle, i: u64, images: SampleImages, width: usize, height: usize) {
    let t = i * FRAME_NS;
    match images {
        SampleImages::Mono8 => log.image_mono8(t, &frame(i, width, height)),
        SampleImages::Jpeg => log.image_jpeg(t, jpeg_frame(i, width, height)),
    };
    log.odometry(&odometry(2 * i));
    log.odometry(&odometry(2 * i + 1));
    if i > 0 {
        log.flow(t, &flow_field(i, width, height));
        log.perception(t, &perception(i), json!({"frame": i, "vplane_l2": [[0.5, 0.25], [1.0, 0.125]]}));
        log.goal(
            t,
            &GoalLog {
                v: 0.3,
                angle_rad: 0.05,
                waypoint: Some("door_a".into()),
                waypoint_index: Some(1),
                remaining_m: Some(4.0),
            },
        );
        log.setpoint(t, &setpoint(i));
    }
    let x = 0.25 * t as f64 * 1e-9;
    log.pose(t, &Pose2D { x_m: x, y_m: 0.0, theta_rad: 0.01 * i as f64 });
    if i.is_multiple_of(10) {
        log.base_status(&BaseStatus { t_ns: t, battery_v: Some(12.1), ..Default::default() });
        log.log(t, LogLevel::Info, format!("frame {i}"));
    }
}

/// Writes a sample run of `frames` frames at `path` (refuses an existing file).
pub fn write_sample(
    path: &Path,
    frames: u64,
    images: SampleImages,
    options: LogOptions,
) -> Result<LogSummary, LogError> {
    let (w, h) = (320, 240);
    // The sample is produced far faster than real time: let the image queue hold all of it, so
    // the file is complete whatever the machine's speed (a real run keeps the small default).
    let mut options = options;
    options.image_queue = options.image_queue.max(frames as usize + 1);
    let writer = LogWriter::create_at(path, options)?;
    writer.calibration(0, &Calibration::nominal_c310().scaled_to(w as u32, h as u32));
    writer.world(0, &world());
    for i in 0..frames {
        log_frame(&writer, i, images, w, h);
    }
    writer.close()
}
