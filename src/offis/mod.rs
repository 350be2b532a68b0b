//! OFFIS, the paper's optical-flow fuzzy inference system (§2.3–§5): from one flow field and the
//! odometry, the two-plane object (TPO) in view, the nearest obstacle, and their distances.
//!
//! One [`Offis::step`] runs the sub-modules of the paper's Fig. 4 in order, after removing the
//! robot's rotation from the flow (OFFIS works on "the translational components of optical
//! flow", §2.2):
//!
//! | stage | paper | module |
//! |---|---|---|
//! | de-rotation, focus of expansion | §2.2 | [`geometry`] |
//! | hierarchical segmentation, quadrant averaging `Q^I`, `Q^II`, `Q^III` | §3.1, eq. 1 | [`quadrants`] |
//! | outlier removal, dynamic per-quadrant thresholds | §2.3 | [`quadrants::reject_outliers`] |
//! | vplane / hplane / tilt matrices | §3.2–3.3, eq. 2–10 | [`planes`] |
//! | rough and fine structure masks | §4.1–4.2, eq. 11–12 | [`structure`] |
//! | obstacle zoom-in, layer 1 → 3 | §3.1, Fig. 6 | [`quadrants::zoom_in`] |
//! | distance from flow and velocity (τ = r/ṙ, Z = t_z·τ) | §2.2 | [`geometry::locate`] |
//! | classifier features (horizon profile, fits) | §5 | [`features`] |
//!
//! The step is pure and deterministic: no clock, no I/O; its buffers are reused between frames.

pub mod features;
pub mod geometry;
pub mod planes;
pub mod quadrants;
pub mod structure;
pub mod synth;

use crate::flow::FlowField;
use crate::perception::{Obstacle, Perception, Tpo};
use features::{Features, ProfilePoint};
use geometry::{DepthParams, FrameMotion, Located, PinholeCamera};
use hal::{BodyVelocity, Calibration};
use planes::{PlaneTolerance, TiltParams};
use quadrants::{Grid, OutlierParams, Quadrants, Zoom};
use serde::{Deserialize, Serialize};

/// Why a step could not run; each names the input and what to do.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum OffisError {
    #[error(
        "flow grid {rows}×{cols} cannot be segmented: OFFIS needs rows and cols that are positive multiples of 8 (set flow.rows/flow.cols, e.g. 16)"
    )]
    Grid { rows: usize, cols: usize },
    #[error("flow field holds {got} vectors for a {rows}×{cols} grid (expected {})", rows * cols)]
    Size { rows: usize, cols: usize, got: usize },
    #[error("flow field image size {width}×{height} is empty")]
    Image { width: usize, height: usize },
    #[error("frame interval dt = {0} s must be positive and finite (check the frame timestamps or --fps)")]
    Dt(f64),
    #[error("odometry v = {v} m/s, omega = {omega} rad/s must be finite")]
    Odometry { v: f64, omega: f64 },
}

/// OFFIS parameters: the `[offis]` table of the config file (sub-tables `[offis.outlier]`,
/// `[offis.plane]`, `[offis.tilt]`, `[offis.depth]`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OffisParams {
    pub outlier: OutlierParams,
    pub plane: PlaneTolerance,
    pub tilt: TiltParams,
    pub depth: DepthParams,
}

impl OffisParams {
    /// Range checks; `Err((field, problem))` names the offending field under `offis.`.
    pub fn check(&self) -> Result<(), (String, String)> {
        let pos = |v: f64| v.is_finite() && v > 0.0;
        let nonneg = |v: f64| v.is_finite() && v >= 0.0;
        let checks: [(&str, bool, &str); 12] = [
            ("outlier.k_median", pos(self.outlier.k_median), "must be a positive number (typ. 2..5)"),
            ("outlier.floor_px", nonneg(self.outlier.floor_px), "must be ≥ 0 pixels"),
            ("outlier.min_support", self.outlier.min_support <= 8, "must be in 0..=8 neighbours"),
            ("outlier.coherence", pos(self.outlier.coherence), "must be a positive fraction (typ. 0.5)"),
            ("plane.rel", nonneg(self.plane.rel) && self.plane.rel < 1.0, "must be in [0, 1)"),
            ("plane.abs_px", nonneg(self.plane.abs_px), "must be ≥ 0 pixels"),
            ("tilt.k_tilt", pos(self.tilt.k_tilt), "must be a positive number"),
            ("tilt.max_ratio", self.tilt.max_ratio.is_finite() && self.tilt.max_ratio >= 1.0, "must be ≥ 1"),
            ("tilt.eps_px", pos(self.tilt.eps_px), "must be a positive number of pixels"),
            ("depth.min_speed_m_s", pos(self.depth.min_speed_m_s), "must be a positive speed"),
            (
                "depth.min_radius_frac",
                nonneg(self.depth.min_radius_frac) && nonneg(self.depth.min_radial_px),
                "and depth.min_radial_px must be ≥ 0",
            ),
            (
                "depth.max_depth_m",
                pos(self.depth.max_depth_m) && nonneg(self.depth.floor_height_m),
                "must be a positive distance (and depth.floor_height_m ≥ 0)",
            ),
        ];
        match checks.iter().find(|(_, ok, _)| !ok) {
            Some((field, _, problem)) => Err((format!("offis.{field}"), problem.to_string())),
            None => Ok(()),
        }
    }
}

/// Everything OFFIS computed for one frame pair, for logging and for the classifiers.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Attributes {
    /// Eq. (1) on the de-rotated, outlier-filtered flow.
    pub quadrants: Quadrants,
    /// Eq. (4)–(7).
    pub vplane_l2: [[u8; 4]; 2],
    pub hplane_l2: [[u8; 2]; 4],
    pub vplane_l3: [[u8; 8]; 4],
    pub hplane_l3: [[u8; 4]; 8],
    /// Eq. (9)–(10).
    pub tilt_l2: [[f64; 2]; 4],
    pub tilt_l3: [[f64; 2]; 8],
    /// §4.1–4.2.
    pub rough: [[u8; 4]; 4],
    pub fine: [[u8; 8]; 8],
    /// §3.1, Fig. 6, on the inliers that are not floor (when translating).
    pub zoom: Option<Zoom>,
    /// Valid vectors in, outliers removed (§2.3).
    pub valid: usize,
    pub outliers: usize,
    /// Focus of expansion, pixels; `None` when the robot is not translating.
    pub foe: Option<[f64; 2]>,
    /// Per layer-3 cell: median forward distance and median horizontal range of its located
    /// blocks, m (`None`: not translating, or no block measurable).
    pub forward_l3: [[Option<f64>; 8]; 8],
    pub range_l3: [[Option<f64>; 8]; 8],
    /// Per layer-3 column, the median located point (forward, left) near the horizon ([`features`]).
    pub profile: [ProfilePoint; 8],
    /// The classifier inputs.
    pub features: Features,
}

/// The OFFIS stage: its parameters and the buffers it reuses from frame to frame.
#[derive(Clone, Debug, Default)]
pub struct Offis {
    params: OffisParams,
    u: Vec<f64>,
    v: Vec<f64>,
    valid: Vec<bool>,
    inlier: Vec<bool>,
    /// Inliers that are not floor: the blocks the obstacle zoom-in looks at.
    candidate: Vec<bool>,
    located: Vec<Option<Located>>,
    scratch: Vec<f64>,
    scratch2: Vec<f64>,
    attributes: Attributes,
}

impl Offis {
    pub fn new(params: OffisParams) -> Self {
        Self { params, ..Self::default() }
    }

    pub fn params(&self) -> &OffisParams {
        &self.params
    }

    /// What the last [`Offis::step`] computed (attribute matrices, masks, per-cell distances).
    pub fn attributes(&self) -> &Attributes {
        &self.attributes
    }

    /// One frame pair: `flow` from frame A to frame B, the odometry `odo` over the interval, the
    /// interval `dt` (s) and the camera calibration (scaled to the flow's image size if it
    /// differs). The perception describes the scene at frame B.
    pub fn step(
        &mut self,
        flow: &FlowField,
        odo: BodyVelocity,
        dt: f64,
        calib: &Calibration,
    ) -> Result<Perception, OffisError> {
        let grid = Grid::new(flow.rows, flow.cols).ok_or(OffisError::Grid { rows: flow.rows, cols: flow.cols })?;
        if flow.vectors.len() != grid.len() {
            return Err(OffisError::Size { rows: flow.rows, cols: flow.cols, got: flow.vectors.len() });
        }
        if flow.width == 0 || flow.height == 0 {
            return Err(OffisError::Image { width: flow.width, height: flow.height });
        }
        if !(dt.is_finite() && dt > 0.0) {
            return Err(OffisError::Dt(dt));
        }
        if !(odo.v.is_finite() && odo.omega.is_finite()) {
            return Err(OffisError::Odometry { v: odo.v, omega: odo.omega });
        }
        let p = self.params;
        let cam = PinholeCamera::new(calib, flow.width, flow.height);
        let motion = FrameMotion::from_odometry(&cam, odo, dt);
        let n = grid.len();
        self.u.resize(n, 0.0);
        self.v.resize(n, 0.0);
        self.valid.resize(n, false);
        self.inlier.resize(n, false);
        self.located.resize(n, None);

        // De-rotation: the translational flow (§2.2).
        for (i, f) in flow.vectors.iter().enumerate() {
            let t = f.valid().then(|| motion.derotate(&cam, f.x as f64, f.y as f64, f.u as f64, f.v as f64)).flatten();
            self.valid[i] = t.is_some_and(|[a, b]| a.is_finite() && b.is_finite());
            [self.u[i], self.v[i]] = t.filter(|_| self.valid[i]).unwrap_or([0.0, 0.0]);
        }
        let valid = self.valid.iter().filter(|&&b| b).count();
        // §2.3, eq. (1).
        let outliers = quadrants::reject_outliers(
            grid,
            &self.u,
            &self.v,
            &self.valid,
            &p.outlier,
            &mut self.inlier,
            &mut self.scratch,
        );
        let q = Quadrants::compute(grid, &self.u, &self.v, &self.inlier);
        // Eq. (2)–(10), §4.1–4.2, Fig. 6.
        let vplane_l2 = planes::vplane_l2(&q.l2, &p.plane);
        let hplane_l2 = planes::hplane_l2(&q.l2, &p.plane);
        let vplane_l3 = planes::vplane_l3(&q.l3, &p.plane);
        let hplane_l3 = planes::hplane_l3(&q.l3, &p.plane);
        let rough = structure::rough_mask(&q.l2, &vplane_l2, &hplane_l2);
        let fine = structure::fine_mask(&q.l3, &vplane_l3, &hplane_l3, &rough);

        // Distances (§2.2): only while translating.
        let translating = odo.v.abs() >= p.depth.min_speed_m_s;
        let foe = motion.foe(&cam).filter(|_| translating);
        for (i, f) in flow.vectors.iter().enumerate() {
            self.located[i] = match foe {
                Some(e) if self.inlier[i] => {
                    geometry::locate(&cam, &motion, e, &p.depth, [f.x as f64, f.y as f64], [self.u[i], self.v[i]])
                }
                _ => None,
            };
        }
        // Fig. 6 zoom-in, on the blocks that are not floor: the floor's flow near the bottom
        // corners is always the biggest in view, and the floor is not an obstacle. Without
        // translation the floor cannot be told apart and every inlier takes part (paper-literal).
        let floor_m = p.depth.floor_height_m;
        let z_m = cam.mount_m[2];
        self.candidate.resize(n, false);
        for (i, keep) in self.candidate.iter_mut().enumerate() {
            *keep = self.inlier[i] && !self.located[i].is_some_and(|l| l.up + z_m < floor_m);
        }
        let zoom = quadrants::zoom_in(&Quadrants::compute(grid, &self.u, &self.v, &self.candidate));
        let mut forward_l3 = [[None; 8]; 8];
        let mut range_l3 = [[None; 8]; 8];
        if foe.is_some() {
            for r in 0..8 {
                for c in 0..8 {
                    forward_l3[r][c] = self.cell_median(grid, [r, c], |l| l.forward);
                    range_l3[r][c] = self.cell_median(grid, [r, c], Located::range);
                }
            }
        }

        let mut profile = [None; 8];
        if foe.is_some() {
            // the band of rows around the horizon, where the TPO definitions probe the planes
            let horizon = cam.cy - cam.fy * cam.pitch_rad.tan();
            let band = (horizon - 0.2 * cam.fy)..=(horizon + 0.05 * cam.fy);
            for (c, point) in profile.iter_mut().enumerate() {
                *point = self.column_point(flow, grid, c, &band);
            }
        }
        let features = Features::from_profile(&profile);

        let obstacle = match zoom {
            Some(z) => {
                let [r, c] = z.l3;
                let (x, y) = cell_centre(flow, grid, [r, c]);
                Obstacle {
                    present: range_l3[r][c].is_none_or(|d| d <= features::RANGE_M),
                    distance_m: range_l3[r][c],
                    bearing_rad: Some(cam.bearing(x, y) - motion.yaw),
                    cell: Some(z.l3),
                }
            }
            None => Obstacle::default(),
        };
        let tpo_distance = (0..64)
            .map(|k| (k / 8, k % 8))
            .filter(|&(r, c)| fine[r][c] == 1 && zoom.is_none_or(|z| z.l3 != [r, c]))
            .filter_map(|(r, c)| forward_l3[r][c])
            .min_by(f64::total_cmp);

        self.attributes = Attributes {
            quadrants: q,
            vplane_l2,
            hplane_l2,
            vplane_l3,
            hplane_l3,
            tilt_l2: planes::tilt_l2(&q.l2, &p.tilt),
            tilt_l3: planes::tilt_l3(&q.l3, &p.tilt),
            rough,
            fine,
            zoom,
            valid,
            outliers,
            foe,
            forward_l3,
            range_l3,
            profile,
            features,
        };
        Ok(Perception { tpo: Tpo { distance_m: tpo_distance, ..Tpo::default() }, obstacle, rough, fine })
    }

    /// Median of `f` over the located blocks of layer-3 cell `[r, c]`.
    fn cell_median(&mut self, grid: Grid, [r, c]: [usize; 2], f: impl Fn(&Located) -> f64) -> Option<f64> {
        let (h, w) = (grid.rows / 8, grid.cols / 8);
        self.scratch.clear();
        for br in r * h..(r + 1) * h {
            for bc in c * w..(c + 1) * w {
                if let Some(l) = &self.located[br * grid.cols + bc] {
                    self.scratch.push(f(l));
                }
            }
        }
        quadrants::median(&mut self.scratch)
    }
}

impl Offis {
    /// The median (forward, left) of the located blocks of layer-3 column `c` whose centre row
    /// lies in `band` (pixels).
    fn column_point(
        &mut self,
        flow: &FlowField,
        grid: Grid,
        c: usize,
        band: &std::ops::RangeInclusive<f64>,
    ) -> ProfilePoint {
        let w = grid.cols / 8;
        self.scratch.clear();
        self.scratch2.clear();
        for br in 0..grid.rows {
            for bc in c * w..(c + 1) * w {
                let i = br * grid.cols + bc;
                if let Some(l) = self.located[i].filter(|_| band.contains(&(flow.vectors[i].y as f64))) {
                    self.scratch.push(l.forward);
                    self.scratch2.push(l.left);
                }
            }
        }
        Some([quadrants::median(&mut self.scratch)?, quadrants::median(&mut self.scratch2)?])
    }
}

/// The pixel centre of layer-3 cell `[r, c]`: the mean of its block centres.
fn cell_centre(flow: &FlowField, grid: Grid, [r, c]: [usize; 2]) -> (f64, f64) {
    let (h, w) = (grid.rows / 8, grid.cols / 8);
    let (mut x, mut y) = (0.0, 0.0);
    for br in r * h..(r + 1) * h {
        for bc in c * w..(c + 1) * w {
            let f = flow.at(br, bc);
            x += f.x as f64;
            y += f.y as f64;
        }
    }
    let k = (h * w) as f64;
    (x / k, y / k)
}

#[cfg(test)]
mod tests;
