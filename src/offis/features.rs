//! Features for the situation classifiers (paper §5, Fig. 11–13): what the fuzzy rule bases
//! read. The paper's rule tables are figures only; these features are our design (see
//! `docs/offis.md`). The geometric ones come from the *horizon profile*: per layer-3 column,
//! the median located point of the blocks in a band of rows around the camera's horizon, where
//! the planes are probed without the floor or a door's lintel — an 8-ray scan of the TPO.

use serde::{Deserialize, Serialize};

/// Surfaces beyond this are out of range for the TPO definitions (DESIGN.md: "none within 5 m").
pub const RANGE_M: f64 = 5.0;
/// `open_ahead_m` when nothing straight ahead is measurable.
pub const OPEN_AHEAD_MAX_M: f64 = 8.0;

/// One profile point: the median (forward, left) in robot axes from the camera, m.
pub type ProfilePoint = Option<[f64; 2]>;

/// The classifier inputs for one frame pair.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Features {
    /// Forward distance of the surface straight ahead (profile columns 3 and 4), m, capped at
    /// [`OPEN_AHEAD_MAX_M`] (also its value when nothing there is measurable).
    pub open_ahead_m: f64,
    /// Fraction of the 8 profile columns with a surface within [`RANGE_M`].
    pub near_frac: f64,
    /// RMS distance of the near profile points from one fitted line, relative to their mean
    /// range: ~0 for a wall or a door's coplanar halves, large for a corner.
    pub line_resid: f64,
    /// Angle between the lines fitted left and right of the best split of the near points,
    /// degrees in [0, 90]: ≥ 20 for a corner.
    pub corner_angle_deg: f64,
    /// The larger angle to the heading of the lines fitted to the near points on the left and on
    /// the right, degrees in [0, 90] (90 when a side has fewer than 2 points): ≤ 15 in a corridor.
    pub side_angle_deg: f64,
    /// Fraction of the columns between the outermost near points that lie beyond the line
    /// through those two points by more than 0.3 m, or have no point: a door's opening when the
    /// flanks are one plane (small `line_resid` and `corner_angle_deg`); a corridor or a concave
    /// corner is also open behind that chord, so the rules never read it alone.
    pub gap_frac: f64,
}

/// Total-least-squares line through `pts`: (centroid, unit direction, RMS residual).
fn fit_line(pts: &[[f64; 2]]) -> Option<([f64; 2], [f64; 2], f64)> {
    if pts.len() < 2 {
        return None;
    }
    let n = pts.len() as f64;
    let mx = pts.iter().map(|p| p[0]).sum::<f64>() / n;
    let my = pts.iter().map(|p| p[1]).sum::<f64>() / n;
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for p in pts {
        let (dx, dy) = (p[0] - mx, p[1] - my);
        sxx += dx * dx;
        syy += dy * dy;
        sxy += dx * dy;
    }
    let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let d = [theta.cos(), theta.sin()];
    let resid = (pts.iter().map(|p| ((p[0] - mx) * d[1] - (p[1] - my) * d[0]).powi(2)).sum::<f64>() / n).sqrt();
    Some(([mx, my], d, resid))
}

/// Angle between two undirected directions, degrees in [0, 90].
fn angle_between(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] * b[0] + a[1] * b[1]).abs().min(1.0).acos().to_degrees()
}

impl Features {
    /// Computes the features from the horizon profile (8 columns, left image column first,
    /// i.e. from the robot's left to its right).
    pub fn from_profile(profile: &[ProfilePoint; 8]) -> Self {
        let near: Vec<(usize, [f64; 2])> = profile
            .iter()
            .enumerate()
            .filter_map(|(c, p)| p.filter(|p| p[0].hypot(p[1]) <= RANGE_M).map(|p| (c, p)))
            .collect();
        let pts: Vec<[f64; 2]> = near.iter().map(|(_, p)| *p).collect();
        let open_ahead_m = [3, 4]
            .iter()
            .filter_map(|&c| profile[c].map(|p| p[0]))
            .fold(OPEN_AHEAD_MAX_M, f64::min)
            .clamp(0.0, OPEN_AHEAD_MAX_M);
        let mean_range = pts.iter().map(|p| p[0].hypot(p[1])).sum::<f64>() / pts.len().max(1) as f64;
        let line_resid = match fit_line(&pts) {
            Some((_, _, r)) if pts.len() >= 3 => r / mean_range.max(1e-6),
            _ => 0.0,
        };
        let mut corner_angle_deg = 0.0;
        let mut best = f64::INFINITY;
        for k in 2..=pts.len().saturating_sub(2) {
            if let (Some((_, da, ra)), Some((_, db, rb))) = (fit_line(&pts[..k]), fit_line(&pts[k..])) {
                let cost = ra * ra * k as f64 + rb * rb * (pts.len() - k) as f64;
                if cost < best {
                    best = cost;
                    corner_angle_deg = angle_between(da, db);
                }
            }
        }
        let side = |left: bool| {
            let s: Vec<[f64; 2]> = pts.iter().copied().filter(|p| (p[1] > 0.0) == left).collect();
            fit_line(&s).map_or(90.0, |(_, d, _)| angle_between(d, [1.0, 0.0]))
        };
        let side_angle_deg = side(true).max(side(false));
        let gap_frac = match (near.first(), near.last()) {
            (Some(&(c0, a)), Some(&(c1, b))) if c1 >= c0 + 2 => {
                let inner = c1 - c0 - 1;
                let beyond = (c0 + 1..c1)
                    .filter(|&c| match profile[c] {
                        None => true,
                        // the point lies beyond the chord a–b (on the far side from the camera)
                        Some(p) => {
                            let (ex, ey) = (b[0] - a[0], b[1] - a[1]);
                            let len = ex.hypot(ey).max(1e-9);
                            let side = |q: [f64; 2]| (ex * (q[1] - a[1]) - ey * (q[0] - a[0])) / len;
                            let (cam, pt) = (side([0.0, 0.0]), side(p));
                            cam * pt < 0.0 && pt.abs() > 0.3
                        }
                    })
                    .count();
                beyond as f64 / inner as f64
            }
            _ => 0.0,
        };
        Self { open_ahead_m, near_frac: pts.len() as f64 / 8.0, line_resid, corner_angle_deg, side_angle_deg, gap_frac }
    }
}
