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
//! | envelope profile, plane fit, classifier features (flownav) | ours | [`features`] |
//! | the paper classifier's inputs from the structures and tilts (paper) | §4–5 | [`paper`] |
//! | obstacle: blocks clearly nearer than the TPO planes; flownav: their nearest cluster; paper: Fig. 6 on them | §3.1 | [`Offis::step`] |
//! | rough + three fine classifiers, TPO decision by maximum | §5, Fig. 11–13 | [`classify`] |
//! | TPO decision over the last steps (class memberships averaged while driving) | ours | [`temporal`] |
//!
//! `offis.classifier` ([`ClassifierKind`]) picks what decides the TPO: `flownav` (default), the
//! plane fit's features, with the paper's attributes computed for the logs only; or `paper`,
//! the paper's structures (built from the blocks that are not floor) and tilts, with the
//! obstacle placed by the Fig. 6 zoom.
//!
//! [`Offis::step`] sees one frame pair alone; [`Offis::step_filtered`], which the per-frame
//! pipeline calls, also takes the robot's motion since the previous step and reports the TPO
//! decided over the last few steps ([`temporal`]).
//!
//! The step is pure and deterministic: no clock, no I/O; its buffers are reused between frames.

pub mod carry;
pub mod classify;
pub mod features;
pub mod geometry;
pub mod paper;
pub mod planes;
pub mod points;
pub mod quadrants;
pub mod structure;
pub mod synth;
pub mod temporal;

use crate::config_error::ConfigError;
use crate::flow::FlowField;
use crate::perception::{Obstacle, Perception, Tpo, TpoShape};
use carry::{CarryLimits, ProfileCarry};
use classify::Classifier;
pub use classify::{ClassifierKind, ClassifyError, Decision};
use features::{Bin, Features, TpoModel};
use geometry::{DepthParams, FrameMotion, Located, PinholeCamera};
use hal::{BodyVelocity, Calibration};
use paper::PaperFeatures;
use planes::{PlaneTolerance, TiltParams};
use quadrants::{Grid, OutlierParams, Quadrants, Zoom};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use temporal::{ClassFilter, Filtered, Motion, TemporalParams};

/// Why a step could not run; each names the input and what to do.
#[derive(Debug, thiserror::Error)]
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
    #[error("{0}")]
    Classify(ClassifyError),
}

/// OFFIS parameters: the `[offis]` table of the config file (sub-tables `[offis.outlier]`,
/// `[offis.plane]`, `[offis.tilt]`, `[offis.depth]`, `[offis.temporal]`, and `classifier`,
/// `rules_dir`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OffisParams {
    /// Which recognition path decides the TPO and the obstacle: `"flownav"` (plane fit to the
    /// per-block depths, the default) or `"paper"` (the paper's structures and tilts, §4–5).
    pub classifier: ClassifierKind,
    /// Folder with the situation classifiers' rule bases (`rough.toml`, `fine_flat.toml`,
    /// `fine_bent.toml`, `fine_empty.toml`; for the paper classifier `paper_rough.toml`,
    /// `paper_fine_plane.toml`, `paper_fine_sides.toml`, `paper_fine_empty.toml`); unset = the
    /// copies of `rules/offis/` built into the binary.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rules_dir: Option<PathBuf>,
    pub outlier: OutlierParams,
    pub plane: PlaneTolerance,
    pub tilt: TiltParams,
    pub depth: DepthParams,
    pub temporal: TemporalParams,
}

impl OffisParams {
    /// Range checks; the error names the offending field under `offis.`.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let pos = |v: f64| v.is_finite() && v > 0.0;
        let nonneg = |v: f64| v.is_finite() && v >= 0.0;
        let t = &self.temporal;
        let checks: [(&str, bool, &str); 21] = [
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
            ("depth.reliable_radial_px", nonneg(self.depth.reliable_radial_px), "must be ≥ 0 pixels"),
            ("depth.floor_rel", nonneg(self.depth.floor_rel) && self.depth.floor_rel < 1.0, "must be in [0, 1)"),
            ("depth.yaw_fix_max_rad", nonneg(self.depth.yaw_fix_max_rad), "must be ≥ 0 rad (0: off)"),
            (
                "temporal.window",
                (1..=temporal::MAX_WINDOW).contains(&t.window),
                "must be in 1..=64 steps (1 = no filtering)",
            ),
            ("temporal.decay", pos(t.decay) && t.decay <= 1.0, "must be in (0, 1]"),
            (
                "temporal.max_turn_rad",
                pos(t.max_turn_rad) && pos(t.max_age_s),
                "and temporal.max_age_s must be positive",
            ),
            ("temporal.min_baseline_px", nonneg(t.min_baseline_px), "must be ≥ 0 pixels (0: off)"),
            (
                "temporal.carry_m",
                nonneg(t.carry_m) && nonneg(t.carry_turn_rad) && nonneg(t.carry_age_s),
                "and temporal.carry_turn_rad, temporal.carry_age_s must be ≥ 0 (carry_m 0: off)",
            ),
            ("temporal.none_weight", pos(t.none_weight) && t.none_weight <= 1.0, "must be in (0, 1]"),
        ];
        match checks.iter().find(|(_, ok, _)| !ok) {
            Some((field, _, problem)) => Err(ConfigError::invalid(format!("offis.{field}"), *problem)),
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
    /// §3.1, Fig. 6, paper-literal on the inliers that are not floor (when translating).
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
    /// The envelope profile, left image column first ([`features`]) ...
    pub bins: Vec<Bin>,
    /// ... of which this many bins hold a point carried from earlier steps ([`carry`]).
    pub carried_bins: usize,
    /// The planes fitted to it as surfaces: the obstacle test's reference, the walls PAFSIS
    /// steers by, the TPO's distance (a corner's aside) ([`features::Reading::Surfaces`]) ...
    pub model: TpoModel,
    /// ... and as the TPO's shape, which the features (the class, a corner's vertex) are
    /// computed from ([`features::Reading::Shape`]).
    pub shape_model: TpoModel,
    /// The classifier inputs (flownav's, computed in both modes).
    pub features: Features,
    /// The paper classifier's inputs (computed in both modes; they decide in paper mode).
    pub paper: PaperFeatures,
    /// The classifiers' degrees and the TPO decision of this frame pair alone (default when not
    /// translating).
    pub decision: Decision,
    /// The TPO decision reported: over the last steps ([`temporal`]; `steps` 0 when not
    /// translating).
    pub filtered: Filtered,
    /// Blocks found clearly nearer than the TPO planes, and those of the reported obstacle.
    pub obstacle_blocks: usize,
    pub obstacle_cluster: usize,
}

/// The OFFIS stage: its parameters, the classifiers and the buffers it reuses from frame to frame.
#[derive(Clone, Debug)]
pub struct Offis {
    params: OffisParams,
    classifier: Classifier,
    filter: ClassFilter,
    carry: ProfileCarry,
    /// A profile of carried points alone ([`Offis::carried_decision`]).
    carried: Vec<Bin>,
    u: Vec<f64>,
    v: Vec<f64>,
    valid: Vec<bool>,
    inlier: Vec<bool>,
    /// Inliers that are not floor: the blocks the paper's zoom-in looks at.
    candidate: Vec<bool>,
    located: Vec<Option<Located>>,
    /// Blocks clearly nearer than the TPO (obstacle blocks), and the cluster label of each.
    near: Vec<bool>,
    label: Vec<u32>,
    stack: Vec<usize>,
    picks: Vec<(f64, [f64; 2])>,
    scratch: Vec<f64>,
    scratch2: Vec<f64>,
    attributes: Attributes,
}

impl Offis {
    /// OFFIS with the situation classifiers from `params.rules_dir`, or the built-in ones.
    pub fn new(params: OffisParams) -> Result<Self, ClassifyError> {
        let classifier = Classifier::load_kind(params.classifier, params.rules_dir.as_deref())?;
        Ok(Self {
            filter: ClassFilter::new(params.temporal),
            carry: ProfileCarry::new(CarryLimits::from_temporal(&params.temporal)),
            carried: Vec::new(),
            params,
            classifier,
            u: Vec::new(),
            v: Vec::new(),
            valid: Vec::new(),
            inlier: Vec::new(),
            candidate: Vec::new(),
            located: Vec::new(),
            near: Vec::new(),
            label: Vec::new(),
            stack: Vec::new(),
            picks: Vec::new(),
            scratch: Vec::new(),
            scratch2: Vec::new(),
            attributes: Attributes::default(),
        })
    }

    pub fn params(&self) -> &OffisParams {
        &self.params
    }

    /// What the last [`Offis::step`] computed (attribute matrices, masks, per-cell distances).
    pub fn attributes(&self) -> &Attributes {
        &self.attributes
    }

    /// One frame pair alone: `flow` from frame A to frame B, the odometry `odo` over the
    /// interval, the interval `dt` (s) and the camera calibration (scaled to the flow's image
    /// size if it differs). The perception describes the scene at frame B. Nothing of earlier
    /// steps is used (the temporal filter is reset).
    pub fn step(
        &mut self,
        flow: &FlowField,
        odo: BodyVelocity,
        dt: f64,
        calib: &Calibration,
    ) -> Result<Perception, OffisError> {
        self.reset_filter();
        self.step_filtered(flow, odo, dt, calib, Motion::default())
    }

    /// The yaw the flow of a pair says the odometry `odo` missed over its interval `dt`, rad
    /// (positive = the camera turned further left): [`geometry::yaw_correction`] on the valid
    /// vectors. `None` when too few blocks show it, and while the robot drives slower than
    /// `depth.min_speed_m_s`: on the spot the camera, mounted ahead of the axle, swings
    /// sideways, and that parallax, which depends on the unknown depth, reads as up to
    /// `mount_x / depth` more turn (10 % facing a wall 1 m away).
    pub fn measure_yaw(&mut self, flow: &FlowField, odo: BodyVelocity, dt: f64, calib: &Calibration) -> Option<f64> {
        if !(dt.is_finite() && dt > 0.0 && odo.v.abs() >= self.params.depth.min_speed_m_s && odo.omega.is_finite()) {
            return None;
        }
        let cam = PinholeCamera::new(calib, flow.width, flow.height);
        let blocks = flow.vectors.iter().filter(|f| f.valid()).map(|f| [f.x, f.y, f.u, f.v].map(f64::from));
        geometry::yaw_correction(&cam, odo, dt, blocks, &mut self.scratch)
    }

    /// Forgets the earlier steps of the temporal filter (a gap in the sequence: a stop, a stall,
    /// a failure).
    pub fn reset_filter(&mut self) {
        self.filter.reset();
        self.carry.reset();
    }

    /// One frame pair of a sequence, as [`Offis::step`], with `since` the robot's motion since
    /// the previous call (its turn from the per-frame odometry, the frame interval): the TPO
    /// reported is decided over the last steps ([`temporal`]); obstacle, masks and the TPO
    /// distance are this pair's (the distance for the filtered shape, from this pair's planes).
    pub fn step_filtered(
        &mut self,
        flow: &FlowField,
        odo: BodyVelocity,
        dt: f64,
        calib: &Calibration,
        since: Motion,
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
        let (outlier_p, plane_p, tilt_p, depth_p) =
            (self.params.outlier, self.params.plane, self.params.tilt, self.params.depth);
        let cam = PinholeCamera::new(calib, flow.width, flow.height);
        let mut motion = FrameMotion::from_odometry(&cam, odo, dt);
        if depth_p.yaw_fix_max_rad > 0.0 {
            let blocks = flow.vectors.iter().filter(|f| f.valid()).map(|f| [f.x, f.y, f.u, f.v].map(f64::from));
            if let Some(fix) = geometry::yaw_correction(&cam, odo, dt, blocks, &mut self.scratch)
                .filter(|d| d.abs() <= depth_p.yaw_fix_max_rad)
            {
                motion = FrameMotion::from_odometry(&cam, BodyVelocity::new(odo.v, odo.omega + fix / dt), dt);
            }
        }
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
            &outlier_p,
            &mut self.inlier,
            &mut self.scratch,
        );
        // Distances (§2.2): only while translating.
        let translating = odo.v.abs() >= depth_p.min_speed_m_s;
        let foe = motion.foe(&cam).filter(|_| translating);
        for (i, f) in flow.vectors.iter().enumerate() {
            self.located[i] = match foe {
                Some(e) if self.inlier[i] => {
                    geometry::locate(&cam, &motion, e, &depth_p, [f.x as f64, f.y as f64], [self.u[i], self.v[i]])
                }
                _ => None,
            };
        }
        // The inliers that are not floor: what the paper's zoom-in (Fig. 6) looks at, and in
        // paper mode what its structures are built from (the paper's figures show no floor; its
        // flow, the biggest in view below the horizon, would mark the bottom rows everywhere).
        let floor_m = depth_p.floor_height_m;
        let z_m = cam.mount_m[2];
        self.candidate.resize(n, false);
        for (i, keep) in self.candidate.iter_mut().enumerate() {
            *keep = self.inlier[i] && !self.located[i].is_some_and(|l| l.up + z_m < floor_m);
        }
        let paper_mode = self.params.classifier == ClassifierKind::Paper;
        let q = Quadrants::compute(grid, &self.u, &self.v, if paper_mode { &self.candidate } else { &self.inlier });
        // Eq. (2)–(10), §4.1–4.2, Fig. 6.
        let vplane_l2 = planes::vplane_l2(&q.l2, &plane_p);
        let hplane_l2 = planes::hplane_l2(&q.l2, &plane_p);
        let vplane_l3 = planes::vplane_l3(&q.l3, &plane_p);
        let hplane_l3 = planes::hplane_l3(&q.l3, &plane_p);
        let rough = structure::rough_mask(&q.l2, &vplane_l2, &hplane_l2);
        let fine = structure::fine_mask(&q.l3, &vplane_l3, &hplane_l3, &rough);
        let tilt_l3 = planes::tilt_l3(&q.l3, &tilt_p);
        let zoom = if paper_mode {
            quadrants::zoom_in(&q)
        } else {
            quadrants::zoom_in(&Quadrants::compute(grid, &self.u, &self.v, &self.candidate))
        };
        let paper = if paper_mode && foe.is_some() {
            let mut range_l2 = [[None; 4]; 4];
            for (r, row) in range_l2.iter_mut().enumerate() {
                for (c, x) in row.iter_mut().enumerate() {
                    *x = self.cell_median(grid, 4, [r, c], Located::range);
                }
            }
            PaperFeatures::compute(&q, &rough, &fine, &tilt_l3, tilt_p.k_tilt, &range_l2)
        } else {
            PaperFeatures::default()
        };
        let mut forward_l3 = [[None; 8]; 8];
        let mut range_l3 = [[None; 8]; 8];
        if foe.is_some() {
            for r in 0..8 {
                for c in 0..8 {
                    forward_l3[r][c] = self.cell_median(grid, 8, [r, c], |l| l.forward);
                    range_l3[r][c] = self.cell_median(grid, 8, [r, c], Located::range);
                }
            }
        }

        // §5: envelope profile, plane fit, features, classifiers.
        let mut bins = std::mem::take(&mut self.attributes.bins);
        bins.clear();
        let nb = grid.cols.min(features::MAX_BINS);
        let reliable = depth_p.reliable_radial_px;
        // the floor test, relative: a floor block whose depth is off by a fraction e appears
        // e·z_m above the floor, so anything below floor_rel·z_m may still be floor
        let floor_rel_m = floor_m.max(depth_p.floor_rel * z_m);
        // the profile takes blocks whose flow is clearly radial; the obstacle decision tolerates more tangential flow,
        // as blocks on an obstacle's outline mix its flow with the background's
        let usable = |l: &Located, across: f64| {
            l.up + z_m >= floor_rel_m
                && l.up + z_m <= features::TOP_M
                && l.radial_px >= reliable
                && l.tangential_px <= across * l.radial_px
        };
        let eligible = |l: &Located| usable(l, 0.5);
        // the profile looks at the planes from about the camera's height up (walls reach the
        // ceiling, the floor never gets there, even with a grossly wrong depth)
        let profile_min_m = features::PROFILE_MIN_REL * z_m;
        // the bins' bearings always (a step without translation may take carried points), their
        // points only while translating
        for b in 0..nb {
            let (c0, c1) = (b * grid.cols / nb, (b + 1) * grid.cols / nb);
            let x = 0.5 * (flow.at(0, c0).x as f64 + flow.at(0, c1 - 1).x as f64);
            self.picks.clear();
            if foe.is_some() {
                for r in 0..grid.rows {
                    for c in c0..c1 {
                        if let Some(l) =
                            self.located[r * grid.cols + c].filter(|l| eligible(l) && l.up + z_m >= profile_min_m)
                        {
                            self.picks.push((l.range(), [l.forward, l.left]));
                        }
                    }
                }
            }
            self.picks.sort_by(|a, b| a.0.total_cmp(&b.0));
            let point = (!self.picks.is_empty()).then(|| self.picks[(self.picks.len() * 3) / 4].1);
            let horizon = cam.cy - cam.fy * cam.pitch_rad.tan();
            bins.push(Bin { point, bearing: cam.bearing(x, horizon) - motion.yaw });
        }
        // a step without translation, or with too short a baseline for its depth to be more than
        // matching noise, measures nothing; a step that measures fills its empty bins from the
        // points of the steps before ([`carry`]) and passes its own on
        self.carry.advance(since, [cam.mount_m[0], cam.mount_m[1]]);
        let evidence = foe.is_some() && odo.v.abs() * dt * cam.fx >= self.params.temporal.min_baseline_px;
        // without translation the profile is all carried points (the robot standing or turning
        // on the spot, its odometry turn moving them); a short pair's own points are too noisy
        // to pass on, and its gaps are left open
        let flownav = self.params.classifier == ClassifierKind::Flownav;
        let carried_bins = match (evidence, foe) {
            (true, _) => self.carry.fill_and_keep(&mut bins),
            // the paper classifier decides from the flow's structures, which need translation
            (false, None) if flownav => self.carry.fill(&mut bins),
            (false, _) => 0,
        };
        let [model, shape_model] = TpoModel::fit_both(&bins);
        let features = Features::compute(&bins, &shape_model);
        let decision = if foe.is_some() || carried_bins > 0 {
            match self.params.classifier {
                ClassifierKind::Flownav => self.classifier.classify(&features),
                ClassifierKind::Paper => self.classifier.classify_paper(&paper),
            }
            .map_err(OffisError::Classify)?
        } else {
            Decision::default()
        };
        // the decision over the last steps. A pair that located surfaces within range but fits
        // no plane to them has not seen that no TPO is there, only not where (depth noise at a
        // low resolution scatters a wall's points): it adds nothing, as a short pair does,
        // instead of voting `none` against the pairs around it that name the TPO
        let evidence = evidence && shape_model.places(&bins);
        self.filter.advance(since);
        let report = |d: &Decision| Filtered { shape: d.shape, confidence: d.confidence, classes: d.classes, steps: 0 };
        let filtered = match (evidence, self.filter.held()) {
            (true, _) => self.filter.push(&decision),
            (false, held) if held.steps > 0 => held,
            // a step that measures nothing when the window has forgotten everything (turned or
            // aged past its limits): what the carried points show; without translation they are
            // this step's profile, a short pair's own points are left out
            (false, _) if foe.is_none() && carried_bins > 0 => report(&decision),
            (false, held) if foe.is_some() && flownav => self.carried_decision(&bins)?.map_or(held, |d| report(&d)),
            (false, held) => held,
        };

        // The obstacle: blocks clearly nearer than the TPO's surface in their bin, grouped into
        // 8-connected clusters; the nearest sizeable cluster, its cell by Fig. 6 on its blocks.
        self.near.clear();
        self.near.resize(n, false);
        let mut obstacle_blocks = 0;
        if foe.is_some() {
            for b in 0..nb {
                let reference = model.expected_range(&bins, b);
                let (c0, c1) = (b * grid.cols / nb, (b + 1) * grid.cols / nb);
                for r in 0..grid.rows {
                    for c in c0..c1 {
                        let i = r * grid.cols + c;
                        if let Some(l) = self.located[i].filter(|l| usable(l, 1.0)) {
                            let d = l.range();
                            if d <= features::RANGE_M && features::clearly_nearer(d, reference) {
                                self.near[i] = true;
                                obstacle_blocks += 1;
                            }
                        }
                    }
                }
            }
        }
        let min_blocks = (3 * n).div_ceil(256).max(3);
        let cluster = if paper_mode { None } else { self.nearest_cluster(grid, min_blocks) };
        let (obstacle, obstacle_cluster) = match cluster {
            _ if paper_mode => self.zoomed_obstacle(grid, min_blocks),
            Some((label, size, distance, bearing)) => {
                for (k, m) in self.candidate.iter_mut().enumerate() {
                    *m = self.label[k] == label;
                }
                let cell =
                    quadrants::zoom_in(&Quadrants::compute(grid, &self.u, &self.v, &self.candidate)).map(|z| z.l3);
                let o = Obstacle { present: true, distance_m: Some(distance), bearing_rad: Some(bearing), cell };
                (o, size)
            }
            None => (Obstacle::default(), 0),
        };

        let tpo_distance = match filtered.shape {
            TpoShape::Wall | TpoShape::Door => model
                .planes()
                .filter(|l| l.heading_angle_deg() >= 30.0)
                .filter_map(|l| l.hit(0.0, 1.0))
                .min_by(f64::total_cmp),
            TpoShape::Corner => features.vertex_m.or_else(|| model.hit(0.0, 1.0)),
            TpoShape::Corridor => {
                // the nearest visible point of the side walls: where the image edge on each
                // wall's side meets it
                let edges = [cam.bearing(0.0, cam.cy), cam.bearing(flow.width as f64 - 1.0, cam.cy)];
                model
                    .planes()
                    .filter_map(|l| {
                        let e = if l.side() > 0.0 { edges[0] } else { edges[1] } - motion.yaw;
                        l.hit(e, 50.0).map(|t| t * e.cos())
                    })
                    .min_by(f64::total_cmp)
            }
            TpoShape::None => None,
        };

        self.attributes = Attributes {
            quadrants: q,
            vplane_l2,
            hplane_l2,
            vplane_l3,
            hplane_l3,
            tilt_l2: planes::tilt_l2(&q.l2, &tilt_p),
            tilt_l3,
            rough,
            fine,
            zoom,
            valid,
            outliers,
            foe,
            forward_l3,
            range_l3,
            bins,
            carried_bins,
            model,
            shape_model,
            features,
            paper,
            decision,
            filtered,
            obstacle_blocks,
            obstacle_cluster,
        };
        let tpo = Tpo { shape: filtered.shape, confidence: filtered.confidence, distance_m: tpo_distance };
        Ok(Perception { tpo, obstacle, rough, fine })
    }

    /// The flownav classifier's decision on a profile of carried points alone, with the
    /// bearings of `bins` ([`carry`]); `None` when no carried point lies in view.
    fn carried_decision(&mut self, bins: &[Bin]) -> Result<Option<Decision>, OffisError> {
        self.carried.clear();
        self.carried.extend(bins.iter().map(|b| Bin { point: None, bearing: b.bearing }));
        if self.carry.fill(&mut self.carried) == 0 {
            return Ok(None);
        }
        let model = TpoModel::fit_shape(&self.carried);
        let features = Features::compute(&self.carried, &model);
        self.classifier.classify(&features).map(Some).map_err(OffisError::Classify)
    }

    /// Paper mode: the obstacle located by the zoom of Fig. 6 over the obstacle blocks
    /// (`self.near`): the layer-1 quadrant with the biggest average flow, its biggest layer-2
    /// child, its biggest layer-3 child ("the person is defined as the nearest obstacle due to
    /// its biggest average optical flow vector", §5). Present when that layer-1 quadrant holds
    /// at least `min_blocks` of them (fewer is matching noise); the distance and bearing are the
    /// medians of the located obstacle blocks in the zoomed layer-3 cell. Returns the obstacle
    /// and the number of obstacle blocks in its cell.
    fn zoomed_obstacle(&mut self, grid: Grid, min_blocks: usize) -> (Obstacle, usize) {
        let q = Quadrants::compute(grid, &self.u, &self.v, &self.near);
        let Some(z) = quadrants::zoom_in(&q) else { return (Obstacle::default(), 0) };
        if (q.l1[z.l1[0]][z.l1[1]].n as usize) < min_blocks {
            return (Obstacle::default(), 0);
        }
        let [r, c] = z.l3;
        let (h, w) = (grid.rows / 8, grid.cols / 8);
        self.scratch.clear();
        self.scratch2.clear();
        for br in r * h..(r + 1) * h {
            for bc in c * w..(c + 1) * w {
                let i = br * grid.cols + bc;
                if let Some(l) = self.located[i].filter(|_| self.near[i]) {
                    self.scratch.push(l.range());
                    self.scratch2.push(l.bearing());
                }
            }
        }
        let size = self.scratch.len();
        let o = Obstacle {
            present: true,
            distance_m: quadrants::median(&mut self.scratch),
            bearing_rad: quadrants::median(&mut self.scratch2),
            cell: Some(z.l3),
        };
        (o, size)
    }

    /// Labels the 8-connected clusters of obstacle blocks (`self.near`) and returns the nearest
    /// one with at least `min_blocks` blocks: `(label, size, distance, bearing)`, where the
    /// distance is the median of its blocks' horizontal ranges and the bearing the median of
    /// their bearings. The median, not a lower quantile: blocks on the obstacle's foot mix its
    /// flow with the nearer floor's and come out too near, blocks on its outline mix it with the
    /// farther background; a lower quantile picked the former (−15 % bias on boxes).
    fn nearest_cluster(&mut self, grid: Grid, min_blocks: usize) -> Option<(u32, usize, f64, f64)> {
        let n = grid.len();
        self.label.clear();
        self.label.resize(n, 0);
        let mut next = 0u32;
        let mut best: Option<(u32, usize, f64, f64)> = None;
        for start in 0..n {
            if !self.near[start] || self.label[start] != 0 {
                continue;
            }
            next += 1;
            self.label[start] = next;
            self.stack.clear();
            self.stack.push(start);
            self.scratch.clear();
            self.scratch2.clear();
            while let Some(i) = self.stack.pop() {
                if let Some(l) = self.located[i] {
                    self.scratch.push(l.range());
                    self.scratch2.push(l.bearing());
                }
                let (r, c) = ((i / grid.cols) as isize, (i % grid.cols) as isize);
                for dr in -1..=1 {
                    for dc in -1..=1 {
                        let (rr, cc) = (r + dr, c + dc);
                        if rr < 0 || cc < 0 || rr >= grid.rows as isize || cc >= grid.cols as isize {
                            continue;
                        }
                        let j = rr as usize * grid.cols + cc as usize;
                        if self.near[j] && self.label[j] == 0 {
                            self.label[j] = next;
                            self.stack.push(j);
                        }
                    }
                }
            }
            let size = self.scratch.len();
            if size < min_blocks {
                continue;
            }
            self.scratch.sort_by(f64::total_cmp);
            let distance = self.scratch[(size - 1) / 2];
            let bearing = quadrants::median(&mut self.scratch2).unwrap_or(0.0);
            if best.is_none_or(|(_, _, d, _)| distance < d) {
                best = Some((next, size, distance, bearing));
            }
        }
        best
    }

    /// Median of `f` over the located blocks of cell `[r, c]` of the `side × side` layer: on
    /// layer 3 (`side` 8) all of them, on layer 2 (`side` 4, the paper's structures) those
    /// that are not floor.
    fn cell_median(&mut self, grid: Grid, side: usize, [r, c]: [usize; 2], f: impl Fn(&Located) -> f64) -> Option<f64> {
        let (h, w) = (grid.rows / side, grid.cols / side);
        self.scratch.clear();
        for br in r * h..(r + 1) * h {
            for bc in c * w..(c + 1) * w {
                let i = br * grid.cols + bc;
                if let Some(l) = self.located[i].as_ref().filter(|_| side == 8 || self.candidate[i]) {
                    self.scratch.push(f(l));
                }
            }
        }
        quadrants::median(&mut self.scratch)
    }
}

#[cfg(test)]
mod tests;
