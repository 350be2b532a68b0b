//! Camera calibration: pinhole intrinsics, radial-tangential distortion and the camera's mount
//! on the robot, loaded from a TOML file (see `calib/c310.toml` for the format).
//!
//! Frames: the *optical* frame has x right, y down, z forward (pixel u grows with x, v with y).
//! The *robot* frame is REP-103 (x forward, y left, z up) with its origin on the floor between
//! the wheels. The mount gives `robot_from_camera`: the camera centre in robot coordinates and a
//! pitch (positive looks down).

use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum CalibError {
    #[error(
        "cannot read calibration file {path}: {source} (check the --calib path; without --calib the built-in nominal C310 is used)"
    )]
    Read { path: String, source: std::io::Error },
    #[error("calibration file {path} is not valid: {message}")]
    Parse { path: String, message: String },
    #[error("calibration file {path}: {field} {problem}")]
    Invalid { path: String, field: &'static str, problem: String },
}

/// The text of `calib/c310.toml`, the default calibration ([`Calibration::nominal_c310`]).
pub const NOMINAL_C310_TOML: &str = include_str!("../../calib/c310.toml");

/// Pinhole intrinsics for one image size, in pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// OpenCV "plumb_bob" coefficients `[k1, k2, p1, p2, k3]`.
    #[serde(default)]
    pub distortion: [f64; 5],
}

/// The angles an image spans ([`Calibration::field_of_view`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FieldOfView {
    pub horizontal_rad: f64,
    pub vertical_rad: f64,
    pub diagonal_rad: f64,
}

/// Where the camera sits on the robot (`robot_from_camera`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mount {
    /// Camera centre ahead of the robot origin, m.
    pub x_m: f64,
    /// Camera centre left of the robot origin, m.
    #[serde(default)]
    pub y_m: f64,
    /// Camera centre above the floor, m.
    pub z_m: f64,
    /// Downward tilt of the optical axis, rad (0 = horizontal).
    #[serde(default)]
    pub pitch_rad: f64,
}

/// A camera calibration: what a file in `calib/` holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    /// Free text: which camera, and whether the numbers are nominal or measured.
    #[serde(default)]
    pub model: String,
    pub camera: Intrinsics,
    pub mount: Mount,
}

impl Intrinsics {
    /// Checks that `distortion` is a lens model over this image ([`crate::lens::check_model`]).
    pub fn check_lens(&self) -> Result<(), String> {
        crate::lens::check_model(&self.distortion, [self.fx, self.fy, self.cx, self.cy], (self.width, self.height))
    }
}

impl Calibration {
    /// Nominal Logitech C310 at 1280×720: `calib/c310.toml`, built into the binary so that the
    /// default calibration does not depend on the working directory.
    pub fn nominal_c310() -> Self {
        // The text is fixed at compile time and its test parses it: this cannot fail at run time.
        Self::from_toml(NOMINAL_C310_TOML, "built-in calib/c310.toml").expect("the built-in calib/c310.toml is valid")
    }

    /// Loads and validates a calibration file.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, CalibError> {
        let path = path.as_ref();
        let name = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| CalibError::Read { path: name.clone(), source })?;
        Self::from_toml(&text, &name)
    }

    /// The calibration as a TOML file in the layout of `calib/c310.toml`, after `header` (comment
    /// lines, each starting with `#`). Numbers are written in Rust's shortest round-trip form, so
    /// [`Calibration::from_toml`] reads back exactly these values.
    pub fn to_toml(&self, header: &str) -> String {
        let c = &self.camera;
        let m = &self.mount;
        let [k1, k2, p1, p2, k3] = c.distortion;
        let model = toml::Value::String(self.model.clone());
        format!(
            "{header}model = {model}\n\n\
             [camera]\nwidth = {}\nheight = {}\nfx = {:?}\nfy = {:?}\ncx = {:?}\ncy = {:?}\n\
             distortion = [{k1:?}, {k2:?}, {p1:?}, {p2:?}, {k3:?}]   # k1, k2, p1, p2, k3 (OpenCV plumb_bob)\n\n\
             [mount]                # robot_from_camera, REP-103 robot frame with origin on the floor between the wheels\n\
             x_m = {:?}\ny_m = {:?}\nz_m = {:?}\npitch_rad = {:?}\n",
            c.width, c.height, c.fx, c.fy, c.cx, c.cy, m.x_m, m.y_m, m.z_m, m.pitch_rad
        )
    }

    /// Parses and validates calibration TOML; `origin` names the source in errors.
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, CalibError> {
        let calib: Self =
            toml::from_str(text).map_err(|e| CalibError::Parse { path: origin.into(), message: e.to_string() })?;
        calib.validate(origin)?;
        Ok(calib)
    }

    fn validate(&self, origin: &str) -> Result<(), CalibError> {
        let c = &self.camera;
        let bad =
            |field, problem: &str| Err(CalibError::Invalid { path: origin.into(), field, problem: problem.into() });
        if c.width == 0 || c.height == 0 {
            return bad("camera.width/height", "must be positive");
        }
        if !(c.fx.is_finite() && c.fx > 0.0 && c.fy.is_finite() && c.fy > 0.0) {
            return bad("camera.fx/fy", "must be positive focal lengths in pixels");
        }
        if !(c.cx.is_finite()
            && c.cy.is_finite()
            && c.cx > 0.0
            && c.cy > 0.0
            && c.cx < c.width as f64
            && c.cy < c.height as f64)
        {
            return bad("camera.cx/cy", "must lie inside the image");
        }
        if c.distortion.iter().any(|k| !k.is_finite()) {
            return bad("camera.distortion", "must be finite numbers");
        }
        if let Err(problem) = c.check_lens() {
            return bad(
                "camera.distortion",
                &format!(
                    "{problem}: it is not a lens model over the image; recalibrate, or set all five to 0.0 for an ideal pinhole"
                ),
            );
        }
        let m = &self.mount;
        if !(m.x_m.is_finite() && m.y_m.is_finite() && m.z_m.is_finite() && m.z_m > 0.0) {
            return bad("mount", "x_m/y_m must be finite and z_m (height above the floor) positive");
        }
        if !(m.pitch_rad.is_finite() && m.pitch_rad.abs() < 1.2) {
            return bad("mount.pitch_rad", "must be within ±1.2 rad");
        }
        Ok(())
    }

    /// The same camera at another image size (intrinsics scaled, e.g. a 640×360 stream of a
    /// camera calibrated at 1280×720). The aspect ratio may change only through cropping-free
    /// scaling, which is what UVC cameras do for their listed sizes.
    pub fn scaled_to(&self, width: u32, height: u32) -> Self {
        let sx = width as f64 / self.camera.width as f64;
        let sy = height as f64 / self.camera.height as f64;
        let c = self.camera;
        let mut out = self.clone();
        out.camera = Intrinsics {
            width,
            height,
            fx: c.fx * sx,
            fy: c.fy * sy,
            cx: (c.cx + 0.5) * sx - 0.5,
            cy: (c.cy + 0.5) * sy - 0.5,
            distortion: c.distortion,
        };
        out
    }

    /// Projects a point in the optical frame (x right, y down, z forward, m) to pixel (u, v) of
    /// the pinhole (undistorted, [`crate::undistort`]) image; `None` behind the camera.
    pub fn project(&self, p: [f64; 3]) -> Option<[f64; 2]> {
        if p[2] <= 1e-9 {
            return None;
        }
        let c = &self.camera;
        Some([c.fx * p[0] / p[2] + c.cx, c.fy * p[1] / p[2] + c.cy])
    }

    /// The viewing ray through pixel (u, v) in the optical frame, normalised to z = 1.
    pub fn ray(&self, u: f64, v: f64) -> [f64; 3] {
        let c = &self.camera;
        [(u - c.cx) / c.fx, (v - c.cy) / c.fy, 1.0]
    }

    /// The angles the image spans, rad: horizontal (across the centre row, from the left edge
    /// of pixel 0 to the right edge of pixel `width − 1`), vertical (down the centre column) and
    /// diagonal (corner to corner), through the lens model (the edges' ideal rays). `None` where
    /// the lens model cannot be inverted at an edge (a calibration that fails its check).
    pub fn field_of_view(&self) -> Option<FieldOfView> {
        let c = &self.camera;
        let (left, right) = (-0.5, c.width as f64 - 0.5);
        let (top, bottom) = (-0.5, c.height as f64 - 0.5);
        let angle = |a: [f64; 2], b: [f64; 2]| -> Option<f64> {
            let (ra, rb) = (self.ideal_ray(a)?, self.ideal_ray(b)?);
            let dot = ra[0] * rb[0] + ra[1] * rb[1] + 1.0;
            let cross = [ra[1] - rb[1], rb[0] - ra[0], ra[0] * rb[1] - ra[1] * rb[0]];
            Some((cross[0].hypot(cross[1]).hypot(cross[2])).atan2(dot))
        };
        Some(FieldOfView {
            horizontal_rad: angle([left, c.cy], [right, c.cy])?,
            vertical_rad: angle([c.cx, top], [c.cx, bottom])?,
            diagonal_rad: angle([left, top], [right, bottom])?,
        })
    }

    /// How far the lens moves the image at its corners, in pixels: for the corner pixels
    /// (top-left, top-right, bottom-left, bottom-right), the corner minus where an ideal pinhole
    /// would image the same ray. Zero without distortion; barrel distortion (k1 < 0) points
    /// towards the image centre, pincushion away from it. `None` where the model cannot be
    /// inverted at a corner.
    pub fn corner_displacements_px(&self) -> Option<[[f64; 2]; 4]> {
        let c = &self.camera;
        let (r, b) = (c.width.saturating_sub(1) as f64, c.height.saturating_sub(1) as f64);
        let mut out = [[0.0; 2]; 4];
        for (o, corner) in out.iter_mut().zip([[0.0, 0.0], [r, 0.0], [0.0, b], [r, b]]) {
            let ray = self.ideal_ray(corner)?;
            let ideal = [c.fx * ray[0] + c.cx, c.fy * ray[1] + c.cy];
            *o = [corner[0] - ideal[0], corner[1] - ideal[1]];
        }
        Some(out)
    }

    /// The ideal (undistorted) ray through pixel `[u, v]` of the camera's image, normalised to z = 1.
    fn ideal_ray(&self, [u, v]: [f64; 2]) -> Option<[f64; 2]> {
        let c = &self.camera;
        crate::lens::undistort_normalized(&c.distortion, [(u - c.cx) / c.fx, (v - c.cy) / c.fy])
    }

    /// Horizontal bearing of pixel column `u` in the robot frame, rad (positive = left).
    pub fn bearing_of_column(&self, u: f64) -> f64 {
        -((u - self.camera.cx) / self.camera.fx).atan()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn built_in_c310_is_the_60_degree_diagonal_pinhole() {
        let c = Calibration::nominal_c310();
        let i = c.camera;
        assert_eq!(
            (i.width, i.height, i.fx, i.fy, i.cx, i.cy, i.distortion),
            (1280, 720, 1272.0, 1272.0, 639.5, 359.5, [0.0; 5])
        );
        assert_eq!(c.mount, Mount { x_m: 0.10, y_m: 0.0, z_m: 0.40, pitch_rad: 0.0 });
        let diagonal = 2.0 * (1280f64.hypot(720.0) / 2.0 / i.fx).atan();
        assert!((diagonal.to_degrees() - 60.0).abs() < 0.05, "{}", diagonal.to_degrees());
    }

    #[test]
    fn wide_file_sees_90_degrees_from_the_c310_mount() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../calib/wide90.toml");
        let wide = Calibration::load(path).unwrap();
        let half = (wide.camera.width as f64 / 2.0 / wide.camera.fx).atan();
        assert!((2.0 * half - std::f64::consts::FRAC_PI_2).abs() < 1e-12, "{half}");
        assert_eq!(wide.mount, Calibration::nominal_c310().mount);
    }

    #[test]
    fn c920_file_sees_70_degrees_across_78_diagonally_from_the_c310_mount() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../calib/c920.toml");
        let c = Calibration::load(path).unwrap();
        let (w, h, f) = (c.camera.width as f64, c.camera.height as f64, c.camera.fx);
        let diagonal = 2.0 * (w.hypot(h) / 2.0 / f).atan();
        assert!((diagonal.to_degrees() - 78.0).abs() < 0.01, "{}", diagonal.to_degrees());
        let across = 2.0 * (w / 2.0 / f).atan();
        assert!((across.to_degrees() - 70.4).abs() < 0.05, "{}", across.to_degrees());
        assert_eq!(c.camera.fy, f);
        assert_eq!(c.mount, Calibration::nominal_c310().mount);
    }

    #[test]
    fn projection_round_trips_through_ray() {
        let c = Calibration::nominal_c310();
        let p = [0.3, -0.2, 2.5];
        let [u, v] = c.project(p).unwrap();
        let r = c.ray(u, v);
        assert!((r[0] * 2.5 - 0.3).abs() < 1e-12 && (r[1] * 2.5 + 0.2).abs() < 1e-12);
    }

    #[test]
    fn bad_values_are_named() {
        let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../calib/c310.toml")).unwrap();
        let err = Calibration::from_toml(&text.replace("fx = 1272.0", "fx = -3.0"), "x.toml").unwrap_err();
        assert!(err.to_string().contains("camera.fx/fy"), "{err}");
        let err = Calibration::from_toml("[camera]\nwidth = 3", "y.toml").unwrap_err();
        assert!(err.to_string().contains("y.toml"), "{err}");
        // k1 = -2 folds the image over before its corners
        let folded = text.replace("distortion = [0.0,", "distortion = [-2.0,");
        let err = Calibration::from_toml(&folded, "z.toml").unwrap_err();
        assert!(err.to_string().contains("camera.distortion") && err.to_string().contains("recalibrate"), "{err}");
        let mild = text.replace("distortion = [0.0,", "distortion = [-0.05,");
        assert_eq!(Calibration::from_toml(&mild, "c.toml").unwrap().camera.distortion[0], -0.05);
    }

    #[test]
    fn field_of_view_follows_the_lens_to_the_image_edges() {
        let mut c = Calibration::nominal_c310();
        let f = c.field_of_view().unwrap();
        let closed = |half_px: f64| 2.0 * (half_px / 1272.0).atan();
        assert!((f.horizontal_rad - closed(640.0)).abs() < 1e-12 && (f.vertical_rad - closed(360.0)).abs() < 1e-12);
        assert!((f.diagonal_rad - closed(640f64.hypot(360.0))).abs() < 1e-12);
        assert_eq!(c.corner_displacements_px().unwrap(), [[0.0; 2]; 4]);
        // Barrel distortion widens the view; the edge rays distort back onto the edges, and the
        // corners move towards the centre.
        c.camera.distortion = [-0.2, 0.05, 0.0, 0.0, 0.0];
        let wide = c.field_of_view().unwrap();
        assert!(wide.horizontal_rad > f.horizontal_rad + 0.01);
        let half = (wide.horizontal_rad / 2.0).tan();
        let [xd, _] = crate::lens::distort_normalized(&c.camera.distortion, [half, 0.0]);
        assert!((xd * 1272.0 + 639.5 - 1279.5).abs() < 1e-9, "{xd}");
        let [tl, tr, bl, br] = c.corner_displacements_px().unwrap();
        assert!(tl[0] > 0.0 && tl[1] > 0.0 && tr[0] < 0.0 && bl[1] < 0.0 && br[0] < 0.0 && br[1] < 0.0);
    }

    #[test]
    fn written_toml_reads_back_exactly() {
        let mut c = Calibration::nominal_c310();
        c.model = "a \"quoted\" name".into();
        c.camera.fx = 1268.3147259306331;
        c.camera.distortion = [-0.07124360986521346, 1e-7, -4.3e-4, 3.1e-4, -0.0538209518433001];
        c.mount.pitch_rad = 0.05;
        assert_eq!(Calibration::from_toml(&c.to_toml("# header\n"), "t").unwrap(), c);
    }

    #[test]
    fn scaling_keeps_the_field_of_view() {
        let c = Calibration::nominal_c310();
        let s = c.scaled_to(640, 360);
        assert!((c.bearing_of_column(0.0) - s.bearing_of_column(0.0 - 0.25)).abs() < 1e-3);
    }
}
