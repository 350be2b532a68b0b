//! Camera intrinsics from the files standard calibration tools write, for `flownav calib import`:
//!
//! - OpenCV `calibrateCamera` results saved with `cv::FileStorage`, as YAML (`%YAML:1.0`,
//!   matrices tagged `!!opencv-matrix` with `rows`, `cols`, `dt`, `data`) or as XML
//!   (`<opencv_storage>`, the same matrices as elements);
//! - ROS `camera_info` YAML, as `camera_calibration` (`cameracalibrator`) and
//!   `camera_info_manager` write it (`camera_matrix`, `distortion_model`,
//!   `distortion_coefficients`, `rectification_matrix`, `projection_matrix`), and the ROS 2
//!   message as `ros2 topic echo --once` prints it (`width`, `height`, `k`, `d`).
//!
//! Only the raw image's model is read: K and the plumb_bob coefficients D, which is what the
//! camera delivers and what flownav undistorts. R and P describe a rectified (stereo) image and
//! are ignored.
//!
//! Pure functions over text: the CLI reads the file and writes the TOML.

use hal::calib::Intrinsics;
use std::collections::BTreeMap;
use yaml_rust2::{Yaml, YamlLoader};

/// The file formats [`import`] reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SourceFormat {
    OpenCvYaml,
    OpenCvXml,
    RosYaml,
}

impl std::fmt::Display for SourceFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::OpenCvYaml => "OpenCV FileStorage YAML",
            Self::OpenCvXml => "OpenCV FileStorage XML",
            Self::RosYaml => "ROS camera_info YAML",
        })
    }
}

/// What a calibration file holds that flownav uses.
#[derive(Clone, Debug, PartialEq)]
pub struct Imported {
    pub format: SourceFormat,
    pub camera: Intrinsics,
    /// ROS `camera_name`, when the file has one.
    pub camera_name: Option<String>,
}

/// Why a calibration file cannot be imported; the message names the field.
#[derive(Debug, thiserror::Error)]
#[error("{origin}: {message}")]
pub struct ImportError {
    pub origin: String,
    pub message: String,
}

// Names each field goes by: OpenCV's tutorial (`camera_calibration.cpp`) and ROS write the first;
// the others are what `cv2.FileStorage` scripts and the ROS 2 message use.
const WIDTH: &[&str] = &["image_width", "width"];
const HEIGHT: &[&str] = &["image_height", "height"];
const CAMERA_MATRIX: &[&str] = &["camera_matrix", "cameraMatrix", "K", "k", "mtx"];
const DISTORTION: &[&str] = &["distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "d", "dist"];
const DISTORTION_MODEL: &[&str] = &["distortion_model"];

/// Reads a calibration file's text; `origin` (the path) names it in errors. The format is told
/// from the text: XML starts with `<`, anything else is read as YAML.
pub fn import(text: &str, origin: &str) -> Result<Imported, ImportError> {
    let fail = |message: String| ImportError { origin: origin.into(), message };
    let fields = if text.trim_start().starts_with('<') { xml_fields(text) } else { yaml_fields(text) };
    let fields = fields.map_err(fail)?;
    fields.intrinsics().map_err(fail)
}

/// The top-level values of one file, whatever its syntax: scalars as text, and matrices (or why
/// a value that looks like one cannot be read).
struct Fields {
    format: SourceFormat,
    scalars: BTreeMap<String, String>,
    matrices: BTreeMap<String, Result<Matrix, String>>,
}

/// A matrix as written: its shape (when the file gives one) and its numbers, row-major.
#[derive(Clone)]
struct Matrix {
    shape: Option<(usize, usize)>,
    data: Vec<f64>,
}

impl Fields {
    fn find_scalar<'n>(&self, names: &[&'n str]) -> Option<(&'n str, &str)> {
        names.iter().find_map(|&n| self.scalars.get(n).map(|v| (n, v.as_str())))
    }

    fn find_matrix<'n>(&self, names: &[&'n str], what: &str) -> Result<(&'n str, &Matrix), String> {
        for &n in names {
            if let Some(m) = self.matrices.get(n) {
                return m.as_ref().map(|m| (n, m)).map_err(|e| format!("{n}: {e}"));
            }
        }
        Err(format!("missing field `{}` ({what}; also read as {})", names[0], names[1..].join(", ")))
    }

    fn size(&self, names: &[&str]) -> Result<u32, String> {
        let (name, text) = self
            .find_scalar(names)
            .ok_or_else(|| format!("missing field `{}` (the image size in pixels that was calibrated)", names[0]))?;
        text.trim()
            .parse::<u32>()
            .ok()
            .filter(|&v| v > 0)
            .ok_or_else(|| format!("{name}: {text:?} is not a positive whole number of pixels"))
    }

    fn intrinsics(&self) -> Result<Imported, String> {
        let width = self.size(WIDTH)?;
        let height = self.size(HEIGHT)?;
        if let Some((_, fisheye)) = self.find_scalar(&["fisheye_model"])
            && fisheye.trim() != "0"
        {
            return Err("fisheye_model: the file holds OpenCV's fisheye (equidistant) model; flownav uses \
                        plumb_bob: calibrate with cv::calibrateCamera instead of cv::fisheye::calibrate"
                .into());
        }
        if let Some((name, model)) = self.find_scalar(DISTORTION_MODEL) {
            let model = model.trim();
            if !matches!(model, "plumb_bob" | "rational_polynomial") {
                return Err(format!(
                    "{name}: {model:?} is not supported; flownav's lens model is plumb_bob (k1, k2, p1, p2, k3)"
                ));
            }
        }
        let (k_name, k) = self.find_matrix(CAMERA_MATRIX, "the 3x3 camera matrix")?;
        if k.data.len() != 9 || k.shape.is_some_and(|s| s != (3, 3)) {
            return Err(format!("{k_name}: must be 3x3 (9 numbers), found {}", k.describe()));
        }
        let m = k.data.as_slice();
        if m.iter().any(|v| !v.is_finite()) {
            return Err(format!("{k_name}: holds a value that is not a finite number"));
        }
        if m[1] != 0.0 {
            return Err(format!("{k_name}: skew {} is not zero; flownav's pinhole model has no skew", m[1]));
        }
        if m[3] != 0.0 || m[6] != 0.0 || m[7] != 0.0 || m[8] != 1.0 {
            return Err(format!("{k_name}: is not a camera matrix [fx 0 cx; 0 fy cy; 0 0 1]: {m:?}"));
        }
        let (d_name, d) = self.find_matrix(DISTORTION, "the distortion coefficients k1, k2, p1, p2[, k3]")?;
        if d.data.iter().any(|v| !v.is_finite()) {
            return Err(format!("{d_name}: holds a value that is not a finite number"));
        }
        let distortion = match d.data.len() {
            0 => [0.0; 5],
            4 => [d.data[0], d.data[1], d.data[2], d.data[3], 0.0],
            // The rational (8), thin-prism (12) and tilted (14) models extend plumb_bob: with their
            // extra terms zero, they are plumb_bob.
            5 | 8 | 12 | 14 if d.data[5..].iter().all(|&v| v == 0.0) => {
                [d.data[0], d.data[1], d.data[2], d.data[3], d.data[4]]
            }
            5 | 8 | 12 | 14 => {
                return Err(format!(
                    "{d_name}: coefficients beyond k3 ({:?}) are not zero; flownav's lens model is plumb_bob \
                     (k1, k2, p1, p2, k3): calibrate without CALIB_RATIONAL_MODEL, CALIB_THIN_PRISM_MODEL \
                     or CALIB_TILTED_MODEL",
                    &d.data[5..]
                ));
            }
            n => return Err(format!("{d_name}: {n} coefficients; expected 4, 5, 8, 12 or 14 (OpenCV's layouts)")),
        };
        let camera_name = self.find_scalar(&["camera_name"]).map(|(_, v)| v.trim().to_string());
        Ok(Imported {
            format: self.format,
            camera: Intrinsics { width, height, fx: m[0], fy: m[4], cx: m[2], cy: m[5], distortion },
            camera_name: camera_name.filter(|n| !n.is_empty()),
        })
    }
}

impl Matrix {
    fn describe(&self) -> String {
        match self.shape {
            Some((r, c)) => format!("{r}x{c} with {} numbers", self.data.len()),
            None => format!("{} numbers", self.data.len()),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// YAML (OpenCV FileStorage and ROS)

/// OpenCV writes `%YAML:1.0` (a colon where YAML has a space, and a version YAML 1.2 parsers
/// refuse) as its first line. The directive carries nothing flownav needs, so a leading `%YAML`
/// line is dropped before parsing; the `!!opencv-matrix` tags the parser reads and ignores.
fn without_yaml_directive(text: &str) -> (&str, bool) {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    match text.strip_prefix("%YAML") {
        Some(rest) => (rest.split_once('\n').map_or("", |(_, body)| body), true),
        None => (text, false),
    }
}

fn yaml_fields(text: &str) -> Result<Fields, String> {
    let (body, had_directive) = without_yaml_directive(text);
    let docs = YamlLoader::load_from_str(body).map_err(|e| format!("not valid YAML: {e}"))?;
    let root = docs.into_iter().next().unwrap_or(Yaml::BadValue);
    let Some(map) = root.as_hash() else {
        return Err("not a calibration: expected a YAML mapping with image_width, camera_matrix, ...".into());
    };
    let ros = root["distortion_model"].as_str().is_some() || root["camera_name"].as_str().is_some();
    let format = if had_directive || text.contains("!!opencv-matrix") || !ros {
        SourceFormat::OpenCvYaml
    } else {
        SourceFormat::RosYaml
    };
    let mut fields = Fields { format, scalars: BTreeMap::new(), matrices: BTreeMap::new() };
    for (key, value) in map {
        let Some(key) = key.as_str() else { continue };
        match value {
            Yaml::String(s) | Yaml::Real(s) => _ = fields.scalars.insert(key.into(), s.clone()),
            Yaml::Integer(i) => _ = fields.scalars.insert(key.into(), i.to_string()),
            Yaml::Array(_) | Yaml::Hash(_) => _ = fields.matrices.insert(key.into(), yaml_matrix(value)),
            _ => {}
        }
    }
    Ok(fields)
}

fn yaml_number(v: &Yaml) -> Option<f64> {
    match v {
        Yaml::Integer(i) => Some(*i as f64),
        Yaml::Real(s) => parse_number(s),
        _ => None,
    }
}

fn yaml_matrix(node: &Yaml) -> Result<Matrix, String> {
    let numbers = |seq: &Yaml| -> Result<Vec<f64>, String> {
        let items = seq.as_vec().ok_or("`data` must be a list of numbers")?;
        items
            .iter()
            .enumerate()
            .map(|(i, v)| yaml_number(v).ok_or_else(|| format!("entry {i} of `data` ({v:?}) is not a number")))
            .collect()
    };
    match node {
        // A bare list (the ROS 2 message's `k`, `d`, or a hand-written file).
        Yaml::Array(_) => Ok(Matrix { shape: None, data: numbers(node)? }),
        Yaml::Hash(_) => {
            let dim = |key: &str| -> Result<usize, String> {
                match &node[key] {
                    Yaml::Integer(n) if *n >= 0 => Ok(*n as usize),
                    Yaml::BadValue => Err(format!("missing field `{key}`")),
                    other => Err(format!("`{key}` ({other:?}) is not a whole number")),
                }
            };
            let (rows, cols) = (dim("rows")?, dim("cols")?);
            if matches!(node["data"], Yaml::BadValue) {
                return Err("missing field `data`".into());
            }
            let data = numbers(&node["data"])?;
            if data.len() != rows * cols {
                return Err(format!("rows × cols = {rows} × {cols} but `data` has {} numbers", data.len()));
            }
            Ok(Matrix { shape: Some((rows, cols)), data })
        }
        _ => Err("must be a matrix (rows, cols, data) or a list of numbers".into()),
    }
}

/// A number as OpenCV writes it: Rust's float syntax covers `0.`, `1e+03` and `-2.5e-01`;
/// OpenCV's own `.Nan` and `.Inf` are read as the non-finite values they are (and refused later).
fn parse_number(s: &str) -> Option<f64> {
    let s = s.trim();
    match s {
        ".nan" | ".NaN" | ".NAN" | ".Nan" => Some(f64::NAN),
        ".inf" | ".Inf" | ".INF" | "+.inf" | "+.Inf" => Some(f64::INFINITY),
        "-.inf" | "-.Inf" | "-.INF" => Some(f64::NEG_INFINITY),
        _ => s.parse().ok(),
    }
}

// ---------------------------------------------------------------------------------------------
// XML (OpenCV FileStorage)

fn xml_fields(text: &str) -> Result<Fields, String> {
    let doc = roxmltree::Document::parse(text).map_err(|e| format!("not valid XML: {e}"))?;
    let root = doc.root_element();
    if root.tag_name().name() != "opencv_storage" {
        return Err(format!(
            "the XML root element is <{}>; OpenCV FileStorage files have <opencv_storage>",
            root.tag_name().name()
        ));
    }
    let mut fields = Fields { format: SourceFormat::OpenCvXml, scalars: BTreeMap::new(), matrices: BTreeMap::new() };
    for el in root.children().filter(|n| n.is_element()) {
        let name = el.tag_name().name().to_string();
        let child = |tag: &str| el.children().find(|c| c.has_tag_name(tag)).map(|c| c.text().unwrap_or(""));
        match child("data") {
            None => _ = fields.scalars.insert(name, el.text().unwrap_or("").trim().to_string()),
            Some(data) => _ = fields.matrices.insert(name, xml_matrix(child("rows"), child("cols"), data)),
        }
    }
    Ok(fields)
}

fn xml_matrix(rows: Option<&str>, cols: Option<&str>, data: &str) -> Result<Matrix, String> {
    let dim = |key: &str, v: Option<&str>| -> Result<usize, String> {
        let v = v.ok_or_else(|| format!("missing element <{key}>"))?;
        v.trim().parse().map_err(|_| format!("<{key}> {v:?} is not a whole number"))
    };
    let (rows, cols) = (dim("rows", rows)?, dim("cols", cols)?);
    let data = data
        .split_whitespace()
        .enumerate()
        .map(|(i, s)| parse_number(s).ok_or_else(|| format!("entry {i} of <data> ({s:?}) is not a number")))
        .collect::<Result<Vec<f64>, String>>()?;
    if data.len() != rows * cols {
        return Err(format!("rows × cols = {rows} × {cols} but <data> has {} numbers", data.len()));
    }
    Ok(Matrix { shape: Some((rows, cols)), data })
}

#[cfg(test)]
mod tests {
    use super::*;

    const OPENCV_YAML: &str = include_str!("../calib/examples/opencv-c310.yaml");
    const OPENCV_XML: &str = include_str!("../calib/examples/opencv-c310.xml");
    const ROS_YAML: &str = include_str!("../calib/examples/ros-c310.yaml");

    fn message(text: &str) -> String {
        import(text, "f.yaml").unwrap_err().to_string()
    }

    #[test]
    fn the_three_formats_are_told_apart_and_agree() {
        let yaml = import(OPENCV_YAML, "a").unwrap();
        let xml = import(OPENCV_XML, "b").unwrap();
        let ros = import(ROS_YAML, "c").unwrap();
        assert_eq!(
            (yaml.format, xml.format, ros.format),
            (SourceFormat::OpenCvYaml, SourceFormat::OpenCvXml, SourceFormat::RosYaml)
        );
        assert_eq!(yaml.camera, xml.camera);
        assert_eq!(ros.camera_name.as_deref(), Some("c310"));
        // ROS rounds to 16 significant digits; the values agree to that.
        assert!(
            (ros.camera.fx - yaml.camera.fx).abs() < 1e-9
                && (ros.camera.distortion[4] - yaml.camera.distortion[4]).abs() < 1e-15
        );
    }

    #[test]
    fn ros2_message_fields_and_four_coefficients_are_read() {
        let text = "height: 480\nwidth: 640\ndistortion_model: plumb_bob\nd: [-0.1, 0.02, 0.001, -0.002]\n\
                    k: [500.0, 0.0, 320.0, 0.0, 501.0, 240.0, 0.0, 0.0, 1.0]\n";
        let c = import(text, "info.yaml").unwrap().camera;
        assert_eq!((c.width, c.height, c.fx, c.fy, c.cx, c.cy), (640, 480, 500.0, 501.0, 320.0, 240.0));
        assert_eq!(c.distortion, [-0.1, 0.02, 0.001, -0.002, 0.0]);
    }

    #[test]
    fn bad_files_say_which_field_and_why() {
        assert!(message(&OPENCV_YAML.replace("image_height: 720", "")).contains("missing field `image_height`"));
        assert!(
            message(&ROS_YAML.replace("rows: 3\n  cols: 3\n  data: [1268", "rows: 2\n  cols: 3\n  data: [1268"))
                .contains("camera_matrix: rows × cols = 2 × 3 but `data` has 9 numbers")
        );
        assert!(message(&OPENCV_YAML.replace("fisheye_model: 0", "fisheye_model: 1")).contains("fisheye_model"));
        assert!(message(&ROS_YAML.replace("plumb_bob", "equidistant")).contains("distortion_model: \"equidistant\""));
        let rational =
            ROS_YAML.replace("cols: 5", "cols: 8").replace("-0.0538209518433001]", "-0.0538209518433001, 0.1, 0, 0]");
        assert!(message(&rational).contains("coefficients beyond k3"));
        let zero_extra =
            ROS_YAML.replace("cols: 5", "cols: 8").replace("-0.0538209518433001]", "-0.0538209518433001, 0, 0, 0]");
        assert_eq!(import(&zero_extra, "z").unwrap().camera.distortion[4], -0.0538209518433001);
        assert!(message(&OPENCV_XML.replace("<rows>3</rows>", "")).contains("missing element <rows>"));
        assert!(message("<calibration/>").contains("<opencv_storage>"));
        assert!(message("just text").contains("expected a YAML mapping"));
        assert!(message(&ROS_YAML.replace("1268.314725930633, 0,", "1268.314725930633, 0.5,")).contains("skew 0.5"));
    }
}
