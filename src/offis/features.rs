//! The TPO model and the features of the situation classifiers (paper §5, Fig. 11–13), and the
//! reference the obstacle decision compares against. The paper's rule tables are figures only;
//! this design is ours (see `docs/offis.md`).
//!
//! **Envelope profile.** The image is cut into at most [`MAX_BINS`] vertical bins (one per
//! block column on the paper's 16×16 grid). In each bin, the located blocks between the floor
//! and [`TOP_M`] give horizontal ranges; the bin's *envelope point* is the block at the 75th
//! percentile of range. TPO planes (walls) are vertical and reach from the floor to the
//! ceiling, obstacles (boxes, people) stand in front of them: where the wall shows above or
//! beside an obstacle, the envelope is the wall.
//!
//! **TPO model.** At most two straight lines fitted to the envelope points on the floor plan by
//! exhaustive two-point consensus (every pair of points proposes a line; the one with the most
//! points within `0.06 m + 6 %` of their range wins, then a total-least-squares refit). A line
//! is a TPO plane only if its inliers span at least [`MIN_PLANE_M`] (a box face or a person is
//! narrower). The second line is fitted to the points the first leaves (or, beside a wall along
//! the heading, its parallel partner); a corner split replaces the two when the points bend.
//! Occluders (narrow runs of bins in front of the surfaces on both sides, [`occluders`], or at
//! the image edge in front of everything else, [`edge_candidates`]) take no part in the fit.
//!
//! **Features** (inputs of `rules/offis/*.toml`): how much of the view the planes cover, how
//! many planes, their angle to each other and to the heading, whether two planes lie on
//! opposite sides of the heading, the distance to the plane ahead and to the first surface
//! actually on the heading, and the widest gap in a plane that shows a surface beyond it.

use serde::{Deserialize, Serialize};

/// Surfaces beyond this are out of range for the TPO definitions (DESIGN.md: "none within 5 m").
pub const RANGE_M: f64 = 5.0;
/// Envelope points up to this range take part in the line fits (slack for depth noise).
pub const FIT_RANGE_M: f64 = 8.0;
/// `open_ahead_m` / `front_m` when nothing is on the heading.
pub const OPEN_AHEAD_MAX_M: f64 = 8.0;
/// Most profile bins: finer grids are merged into this many bins (keeps the fit cheap).
pub const MAX_BINS: usize = 16;
/// Blocks located higher than this above the floor are ignored by the profile and the obstacle
/// decision (ceiling, a door's lintel).
pub const TOP_M: f64 = 1.95;
/// The profile uses blocks at least this fraction of the camera height above the floor.
pub const PROFILE_MIN_REL: f64 = 0.75;
/// A TPO plane's inliers span at least this along the line, m.
pub const MIN_PLANE_M: f64 = 0.9;
/// Fewest inliers of a TPO plane.
pub const MIN_PLANE_POINTS: usize = 3;

/// One profile bin: its envelope point (forward, left) from the camera, m, and the bearing of
/// its centre, rad (+ left).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Bin {
    pub point: Option<[f64; 2]>,
    pub bearing: f64,
}

/// Inlier tolerance of a line fit at range `r`, m.
fn tolerance(r: f64) -> f64 {
    0.06 + 0.06 * r
}

fn range(p: [f64; 2]) -> f64 {
    p[0].hypot(p[1])
}

/// A fitted plane seen from above: a line on the floor plan.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Line {
    /// A point on the line (centroid of the inliers) and its unit direction, robot axes, m.
    pub centre: [f64; 2],
    pub dir: [f64; 2],
    /// Inlier bins (bit `b` = bin `b`).
    pub inliers: u64,
    /// Extent of the inliers along `dir` from `centre`, m.
    pub extent: [f64; 2],
}

impl Line {
    /// Perpendicular distance of `p`, m.
    pub fn distance(&self, p: [f64; 2]) -> f64 {
        ((p[0] - self.centre[0]) * self.dir[1] - (p[1] - self.centre[1]) * self.dir[0]).abs()
    }

    /// Range along the ray at `bearing` to where it meets the line, if ahead of the camera and
    /// within the inliers' extent widened by `slack_m`.
    pub fn hit(&self, bearing: f64, slack_m: f64) -> Option<f64> {
        let r = [bearing.cos(), bearing.sin()];
        // centre + s·dir = t·r
        let det = r[0] * (-self.dir[1]) - r[1] * (-self.dir[0]);
        if det.abs() < 1e-9 {
            return None;
        }
        let (cx, cy) = (self.centre[0], self.centre[1]);
        let t = (cx * (-self.dir[1]) - cy * (-self.dir[0])) / det;
        let s = (r[0] * cy - r[1] * cx) / det;
        (t > 0.0 && s >= self.extent[0] - slack_m && s <= self.extent[1] + slack_m).then_some(t)
    }

    /// Angle between the line and the heading, degrees in [0, 90]: 0 for a corridor's side
    /// wall, 90 for a frontal wall.
    pub fn heading_angle_deg(&self) -> f64 {
        self.dir[0].abs().min(1.0).acos().to_degrees()
    }

    /// Lateral offset of the line's centre, m (+ left).
    pub fn side(&self) -> f64 {
        self.centre[1]
    }

    fn count(&self) -> usize {
        self.inliers.count_ones() as usize
    }
}

/// Angle between two undirected directions, degrees in [0, 90].
fn angle_between(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] * b[0] + a[1] * b[1]).abs().min(1.0).acos().to_degrees()
}

/// Total-least-squares line through the points of `bins` selected by `mask`.
fn fit_mask(bins: &[Bin], mask: u64) -> Option<Line> {
    let pts = || bins.iter().enumerate().filter(move |(b, _)| mask >> b & 1 == 1).filter_map(|(_, x)| x.point);
    let n = pts().count();
    if n < 2 {
        return None;
    }
    let nf = n as f64;
    let mx = pts().map(|p| p[0]).sum::<f64>() / nf;
    let my = pts().map(|p| p[1]).sum::<f64>() / nf;
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for p in pts() {
        let (dx, dy) = (p[0] - mx, p[1] - my);
        sxx += dx * dx;
        syy += dy * dy;
        sxy += dx * dy;
    }
    let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let dir = [theta.cos(), theta.sin()];
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for p in pts() {
        let s = (p[0] - mx) * dir[0] + (p[1] - my) * dir[1];
        lo = lo.min(s);
        hi = hi.max(s);
    }
    Some(Line { centre: [mx, my], dir, inliers: mask, extent: [lo, hi] })
}

/// Bins of `free` whose point lies within tolerance of `line`.
fn inliers_of(bins: &[Bin], free: u64, line: &Line) -> u64 {
    let mut m = 0;
    for (b, bin) in bins.iter().enumerate() {
        if free >> b & 1 == 1
            && let Some(p) = bin.point
            && line.distance(p) <= tolerance(range(p))
        {
            m |= 1 << b;
        }
    }
    m
}

/// Largest spacing along a plane between neighbouring inliers, m: a wider hole splits the
/// inliers into separate surfaces (a door opening is at most ~1.4 m, plus a bin either side).
pub const MAX_HOLE_M: f64 = 1.8;

/// Keeps the largest run of `line`'s inliers whose neighbours along the line are at most
/// [`MAX_HOLE_M`] apart (two collinear but separate objects are not one plane). Neighbours with
/// no other surface seen between them (adjacent bins, or only empty bins between) are never
/// split: far along a grazing wall, one bin spans more than [`MAX_HOLE_M`].
fn contiguous(bins: &[Bin], line: &Line, occluded: u64) -> u64 {
    let mut pts: Vec<(f64, usize)> = (0..bins.len())
        .filter(|&b| line.inliers >> b & 1 == 1)
        .filter_map(|b| {
            bins[b].point.map(|p| ((p[0] - line.centre[0]) * line.dir[0] + (p[1] - line.centre[1]) * line.dir[1], b))
        })
        .collect();
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut best, mut run, mut best_n, mut n) = (0u64, 0u64, 0, 0);
    for (k, &(s, b)) in pts.iter().enumerate() {
        let seen_between = |a: usize, b: usize| (a.min(b) + 1..a.max(b)).any(|x| bins[x].point.is_some());
        // an occluder in the hole hides part of it: only the rest counts towards its width
        let visible = |a: usize, b: usize| {
            let between = a.max(b) - a.min(b);
            let hidden = (a.min(b) + 1..a.max(b)).filter(|&x| occluded >> x & 1 == 1).count();
            (between - hidden) as f64 / between as f64
        };
        if k > 0 && (s - pts[k - 1].0) * visible(pts[k - 1].1, b) > MAX_HOLE_M && seen_between(pts[k - 1].1, b) {
            run = 0;
            n = 0;
        }
        run |= 1 << b;
        n += 1;
        if n > best_n {
            best_n = n;
            best = run;
        }
    }
    best
}

/// The best line among the points of `free` (see the module doc), if it is a plane. Lines are
/// scored MSAC-style, `Σ min(d², T²)` over the free points with `T` the inlier tolerance, so a
/// line through the middle of a corner (many points, each far off) loses to one of its walls.
fn best_line(bins: &[Bin], free: u64, occluded: u64, min_extent_m: f64) -> Option<Line> {
    let idx: Vec<usize> = (0..bins.len()).filter(|&b| free >> b & 1 == 1).collect();
    let mut best: Option<(f64, u64)> = None;
    for (k, &i) in idx.iter().enumerate() {
        for &j in &idx[k + 1..] {
            let (Some(a), Some(b)) = (bins[i].point, bins[j].point) else { continue };
            let len = (b[0] - a[0]).hypot(b[1] - a[1]);
            if len < 1e-6 {
                continue;
            }
            let line = Line { centre: a, dir: [(b[0] - a[0]) / len, (b[1] - a[1]) / len], ..Line::default() };
            let mut cost = 0.0;
            let mut m = 0u64;
            for &q in &idx {
                let p = bins[q].point.expect("free bins have points");
                let (d, t) = (line.distance(p), tolerance(range(p)));
                if d <= t {
                    m |= 1 << q;
                }
                cost += d.min(t).powi(2) / (t * t);
            }
            if best.is_none_or(|(bc, _)| cost < bc) {
                best = Some((cost, m));
            }
        }
    }
    let (_, mask) = best?;
    let first = fit_mask(bins, mask)?;
    // one refinement: the refit line's own inliers, then the largest contiguous run of them
    let mut line = fit_mask(bins, inliers_of(bins, free, &first)).unwrap_or(first);
    line = fit_mask(bins, contiguous(bins, &line, occluded)).unwrap_or(line);
    is_plane(&line, min_extent_m).then_some(line)
}

fn is_plane(line: &Line, min_extent_m: f64) -> bool {
    line.count() >= MIN_PLANE_POINTS && line.extent[1] - line.extent[0] >= min_extent_m
}

/// MSAC cost of explaining the points of `free` by `lines`: per point, the smallest squared
/// distance to a line over the squared tolerance, at most 1 (an unexplained point costs 1).
fn cost(bins: &[Bin], free: u64, lines: &[Option<Line>; 2]) -> f64 {
    (0..bins.len())
        .filter(|&b| free >> b & 1 == 1)
        .filter_map(|b| bins[b].point)
        .map(|p| {
            let t = tolerance(range(p));
            lines.iter().flatten().map(|l| (l.distance(p) / t).powi(2)).fold(1.0, f64::min)
        })
        .sum()
}

/// A corner: the best split of the points in bin order into a left and a right plane that meet
/// at [`SPLIT_MIN_DEG`] or more (each side fitted like the first plane), if it explains the
/// points better than `current` by at least [`SPLIT_MARGIN`]. The sequential fit can miss a
/// shallow corner, whose two walls stay within the tolerance of one line through its middle.
fn split(bins: &[Bin], free: u64, occluded: u64, current: &[Option<Line>; 2]) -> Option<[Line; 2]> {
    let is_bent = bent(bins, free);
    if !is_bent && occluded == 0 {
        return None;
    }
    let idx: Vec<usize> = (0..bins.len()).filter(|&b| free >> b & 1 == 1).collect();
    let base = cost(bins, free, current);
    let mut best = (base - SPLIT_MARGIN, None);
    for k in MIN_PLANE_POINTS..=idx.len().saturating_sub(MIN_PLANE_POINTS) {
        let left: u64 = idx[..k].iter().fold(0, |m, &b| m | 1 << b);
        // an occluder between the two sides hides the corner's edge and part of each wall
        let hidden = (idx[k - 1] + 1..idx[k]).any(|x| occluded >> x & 1 == 1);
        if !is_bent && !hidden {
            continue;
        }
        let side = if hidden { CORNER_SIDE_HIDDEN_M } else { CORNER_SIDE_M };
        let (Some(a), Some(b)) = (best_line(bins, left, occluded, side), best_line(bins, free & !left, occluded, side))
        else {
            continue;
        };
        if a.count() + b.count() < 2 * MIN_PLANE_POINTS + 2 {
            continue;
        }
        if angle_between(a.dir, b.dir) < SPLIT_MIN_DEG {
            continue;
        }
        // points that do not bend may still be a corner whose edge an occluder hides: then the
        // two walls must cross behind it
        let behind = hidden && behind_occluder(bins, occluded, idx[k - 1], idx[k], &a, &b);
        if !is_bent && !behind {
            continue;
        }
        let c = cost(bins, free, &[Some(a), Some(b)]);
        // a crossing behind the occluder is evidence of its own: a smaller margin will do
        let limit = match best.1 {
            None if behind => base - SPLIT_MARGIN_BEHIND,
            _ => best.0,
        };
        if c < limit {
            best = (c, Some([a, b]));
        }
    }
    best.1
}

/// Whether the lines `a` and `b` cross behind the occluder between bins `i` and `j` (the
/// occluded bins between them): ahead of the camera, within the occluder's bearings (widened by
/// half a bin either side) and farther than its nearest point. A corner whose edge a person or
/// a box hides.
fn behind_occluder(bins: &[Bin], occluded: u64, i: usize, j: usize, a: &Line, b: &Line) -> bool {
    let Some(v) = intersect(a, b) else { return false };
    if v[0] <= 0.0 {
        return false;
    }
    let half = if bins.len() > 1 {
        0.5 * (bins[0].bearing - bins[bins.len() - 1].bearing).abs() / (bins.len() - 1) as f64
    } else {
        0.0
    };
    let (mut lo, mut hi, mut near) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY);
    for x in (i + 1..j).filter(|&x| x < 64 && occluded >> x & 1 == 1) {
        lo = lo.min(bins[x].bearing);
        hi = hi.max(bins[x].bearing);
        if let Some(p) = bins[x].point {
            near = near.min(range(p));
        }
    }
    let bv = v[1].atan2(v[0]);
    lo - half <= bv && bv <= hi + half && range(v) > near
}

/// Whether the points of `free` bend: at least half of them lie significantly off one line
/// through all of them (total least squares; beyond [`BEND_SIGNIFICANT`] of their tolerance),
/// and the signs of those residuals, in bin order, form fewer runs than random signs would
/// (Wald–Wolfowitz runs test, z ≤ [`BEND_MAX_Z`]). A corner's points lie beyond the line at
/// both ends and before it in the middle (3 runs); depth noise on a wall flips the sign from
/// bin to bin or stays within the tolerance.
fn bent(bins: &[Bin], free: u64) -> bool {
    let Some(line) = fit_mask(bins, free) else { return false };
    let (mut n, mut plus, mut minus, mut runs, mut last) = (0usize, 0usize, 0usize, 0usize, 0.0f64);
    for b in (0..bins.len()).filter(|&b| free >> b & 1 == 1) {
        let Some(p) = bins[b].point else { continue };
        n += 1;
        let r = (p[0] - line.centre[0]) * line.dir[1] - (p[1] - line.centre[1]) * line.dir[0];
        if r.abs() > BEND_SIGNIFICANT * tolerance(range(p)) {
            if r > 0.0 {
                plus += 1
            } else {
                minus += 1
            }
            if r.signum() != last {
                runs += 1;
                last = r.signum();
            }
        }
    }
    let m = (plus + minus) as f64;
    if 2 * (plus + minus) < n || plus == 0 || minus == 0 {
        return false;
    }
    let (np, nm) = (plus as f64, minus as f64);
    let mean = 1.0 + 2.0 * np * nm / m;
    let var = 2.0 * np * nm * (2.0 * np * nm - m) / (m * m * (m - 1.0));
    // three runs is a corner's shape; too few points for the test to say more
    runs <= 3 || (var > 0.0 && (runs as f64 - mean) / var.sqrt() <= BEND_MAX_Z)
}

/// The corner test (`bent`): points bend when at least half of them lie more than this
/// fraction of their tolerance off one line through them all and the signs of those residuals,
/// in bin order, form few runs (Wald–Wolfowitz z ≤ [`BEND_MAX_Z`]).
pub const BEND_SIGNIFICANT: f64 = 0.3;
pub const BEND_MAX_Z: f64 = -1.2;

/// A corner (`split`: two planes that meet at [`SPLIT_MIN_DEG`] or more) replaces the
/// sequential fit only when it lowers the MSAC cost (an unexplained point costs 1) by at least
/// this much. Each wall of a corner must span at least [`CORNER_SIDE_M`] (a near corner shows
/// little of each wall) and the two hold at least 8 points together.
pub const SPLIT_MARGIN: f64 = 1.0;
/// ... or this much when the two walls cross behind an occluder between them.
pub const SPLIT_MARGIN_BEHIND: f64 = 0.5;
pub const CORNER_SIDE_M: f64 = 0.5;
/// ... or this much when an occluder stands between the two walls.
pub const CORNER_SIDE_HIDDEN_M: f64 = 0.15;
pub const SPLIT_MIN_DEG: f64 = 12.0;

/// The TPO's planes: up to two lines on the floor plan.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct TpoModel {
    /// The plane with the most support first.
    pub lines: [Option<Line>; 2],
    /// Bins whose envelope point lies on an occluder ([`occluders`]), left out of the fit.
    pub occluded: u64,
}

/// Two neighbouring envelope points are on different surfaces (a depth step) when the nearer
/// is nearer than the farther by more than this fraction of the farther's range, and by more
/// than [`STEP_MIN_M`]. Looser than [`clearly_nearer`]: depth noise on one bin must not cut a
/// wall into pieces.
pub const STEP_REL: f64 = 0.25;
pub const STEP_MIN_M: f64 = 0.4;

fn depth_step(a: f64, b: f64) -> bool {
    let (near, far) = (a.min(b), a.max(b));
    far - near > (STEP_REL * far).max(STEP_MIN_M)
}

/// The envelope points of a profile as `(bin, point)` pairs, left bin first.
type Points = Vec<(usize, [f64; 2])>;

/// The envelope points of `bins` (at most 64) cut into runs at depth steps: the points and the
/// `[start, end)` ranges of the runs in that list.
fn runs(bins: &[Bin]) -> (Points, Vec<[usize; 2]>) {
    let pts: Vec<(usize, [f64; 2])> =
        bins.iter().enumerate().take(64).filter_map(|(b, x)| x.point.map(|p| (b, p))).collect();
    let mut out = Vec::new();
    let mut start = 0;
    while start < pts.len() {
        let mut end = start + 1;
        while end < pts.len() && !depth_step(range(pts[end - 1].1), range(pts[end].1)) {
            end += 1;
        }
        out.push([start, end]);
        start = end;
    }
    (pts, out)
}

/// The bins of the points `run` as a mask.
fn run_mask(pts: &[(usize, [f64; 2])], [start, end]: [usize; 2]) -> u64 {
    pts[start..end].iter().fold(0, |m, &(b, _)| m | 1 << b)
}

/// Width of the points `run` from its first to its last point, m.
fn run_width(pts: &[(usize, [f64; 2])], [start, end]: [usize; 2]) -> f64 {
    let (first, last) = (pts[start].1, pts[end - 1].1);
    (last[0] - first[0]).hypot(last[1] - first[1])
}

/// What a plane fit is for, which decides how a narrow run nearer than its neighbours is read.
///
/// - `Surfaces`: the reference the obstacle test measures against, the walls PAFSIS steers by
///   and the TPO's distance (a corner's aside). Every such run is an occluder, left out of the planes: a box
///   beside a wall must stay clearly nearer than the surface behind it, or it is no obstacle.
/// - `Shape`: the TPO's class, the corner's vertex (its distance) and whether the pair places
///   a TPO at all. A run that lies on one line with farther points at a grazing angle
///   (`grazing_wall`) is a stretch of wall between door openings and stays in the fit:
///   without it a corridor near its doors loses both walls and reads `none`. Taking it for a
///   wall costs at most a wrong class, never an obstacle unseen.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reading {
    Surfaces,
    Shape,
}

/// Bins whose envelope points form an *occluder*: a run of bins (neighbours within a depth
/// step of each other, empty bins skipped) that is nearer than the surfaces on both sides of
/// it, across a depth step, and narrower than a plane ([`MIN_PLANE_M`]). A box or a person in
/// front of a wall; TPO planes reach the floor and the ceiling and are wide, and a door's
/// opening is farther than its wall, not nearer. A run at the image edge has a neighbour on
/// one side only: see [`edge_candidates`] and [`TpoModel::fit`]. An occluder in front of
/// another leaves it out of the runs, and the one behind is looked for again. In the
/// [`Reading::Shape`], a run that is a stretch of wall seen at a grazing angle
/// (`grazing_wall`) is no occluder.
pub fn occluders(bins: &[Bin], reading: Reading) -> u64 {
    // an occluder may stand in front of another (a noisy bin in front of a person): the runs
    // are cut again without the occluders found so far, until no new one appears
    let mut mask = 0u64;
    let mut view = bins.to_vec();
    for _ in 0..3 {
        let found = occluders_once(&view, reading);
        if found & !mask == 0 {
            break;
        }
        mask |= found;
        for (b, bin) in view.iter_mut().enumerate().take(64) {
            if mask >> b & 1 == 1 {
                bin.point = None;
            }
        }
    }
    mask
}

/// A run of points is a stretch of wall seen at a grazing angle, not an occluder, when its
/// line makes an angle of at least this with the view ray through it, degrees ...
pub const GRAZING_MIN_DEG: f64 = 8.0;
/// ... and at most this (a box face or a person is seen nearly face on) ...
pub const GRAZING_MAX_DEG: f64 = 45.0;
/// ... and the line through it and a farther point of the profile spans at most this beyond
/// the run's own width, m.
pub const GRAZING_REACH_M: f64 = 3.0;

/// Whether the points `run` are a stretch of a wall seen at a grazing angle that continues past
/// a depth step: a point farther than all of them lies, with them, on one line (every point
/// within its tolerance) spanning a plane's width, and both that line and the stretch's own
/// (of two points or more) run away from the camera ([`GRAZING_MIN_DEG`]–[`GRAZING_MAX_DEG`]
/// off the view ray); a stretch of one point needs a nearer point on that line as well, on its
/// other side, so a single bin at the image edge is never one. Along a corridor's wall the
/// range grows by more than a depth step from bin to bin, and door openings cut the wall into
/// runs narrower than a plane that are nearer than their neighbours: an occluder's shape, on a
/// surface the TPO planes need. A box or a person seen face on, or a line along a view ray
/// (which no visible surface is), does not pass.
fn grazing_wall(bins: &[Bin], pts: &[(usize, [f64; 2])], run: [usize; 2]) -> bool {
    let own = run_mask(pts, run);
    let (near, far) = pts[run[0]..run[1]]
        .iter()
        .map(|&(_, p)| range(p))
        .fold((f64::INFINITY, 0.0_f64), |(lo, hi), r| (lo.min(r), hi.max(r)));
    let n = (run[1] - run[0]) as f64;
    let centre = pts[run[0]..run[1]].iter().fold([0.0, 0.0], |c, &(_, p)| [c[0] + p[0] / n, c[1] + p[1] / n]);
    let ray = {
        let r = range(centre).max(1e-9);
        [centre[0] / r, centre[1] / r]
    };
    let grazing = |line: &Line| (GRAZING_MIN_DEG..=GRAZING_MAX_DEG).contains(&angle_between(line.dir, ray));
    // a stretch of two points or more must itself run away from the camera (a face-on box or
    // person does not); a single point must lie between a nearer and a farther one on the line
    let single = run[1] - run[0] < 2;
    if !single && !fit_mask(bins, own).is_some_and(|l| grazing(&l)) {
        return false;
    }
    // the wall goes on where the stretch's range grows: beyond its farther end in bin order (a
    // single point: the nearer part on one side of it, the farther on the other)
    let (first, last) = (pts[run[0]], pts[run[1] - 1]);
    let onward = |b: usize| if range(last.1) >= range(first.1) { b > last.0 } else { b < first.0 };
    let farther: Vec<u64> = pts
        .iter()
        .filter(|&&(b, q)| range(q) > far && range(q) <= FIT_RANGE_M && (onward(b) || single && b < first.0))
        .map(|&(b, _)| 1u64 << b)
        .collect();
    let nearer = |q: u64| -> Vec<u64> {
        if !single {
            return vec![0];
        }
        let before = q < 1 << first.0;
        pts.iter()
            .filter(|&&(b, p)| range(p) < near && (b < first.0) != before && b != first.0)
            .map(|&(b, _)| 1u64 << b)
            .collect()
    };
    let on_one_line = |mask: u64| {
        let Some(line) = fit_mask(bins, mask) else { return false };
        let fits = (0..bins.len().min(64))
            .filter(|&x| mask >> x & 1 == 1)
            .filter_map(|x| bins[x].point)
            .all(|p| line.distance(p) <= tolerance(range(p)));
        let span = line.extent[1] - line.extent[0];
        fits && span >= MIN_PLANE_M && span <= run_width(pts, run) + GRAZING_REACH_M && grazing(&line)
    };
    farther.iter().any(|&q| nearer(q).iter().any(|&m| on_one_line(own | q | m)))
}

/// One pass of [`occluders`].
fn occluders_once(bins: &[Bin], reading: Reading) -> u64 {
    let (pts, runs) = runs(bins);
    let mut mask = 0u64;
    for w in runs.windows(3) {
        let [before, run, after] = [w[0], w[1], w[2]];
        let nearer_than = |q: [f64; 2], p: [f64; 2]| range(p) < range(q);
        if nearer_than(pts[before[1] - 1].1, pts[run[0]].1)
            && nearer_than(pts[after[0]].1, pts[run[1] - 1].1)
            && run_width(&pts, run) < MIN_PLANE_M
            && !(reading == Reading::Shape && grazing_wall(bins, &pts, run))
        {
            mask |= run_mask(&pts, run);
        }
    }
    mask
}

/// The runs at the two image edges that may be occluders: narrower than a plane and nearer
/// than their one neighbour across a depth step (`[left, right]` bin masks, 0 where not). Such
/// a run is either an obstacle at the edge of the view or a stretch of wall beside an opening
/// (a door's jamb); [`TpoModel::fit`] tells them apart. Nearer runs at both edges are the two
/// sides of an opening (a door's wall, a corridor's walls), not occluders: none is returned.
/// In the [`Reading::Shape`], a run that is a stretch of wall seen at a grazing angle
/// (`grazing_wall`) is no candidate.
pub fn edge_candidates(bins: &[Bin], reading: Reading) -> [u64; 2] {
    let (pts, runs) = runs(bins);
    if runs.len() < 2 {
        return [0, 0];
    }
    let candidate = |run: [usize; 2], neighbour: [f64; 2]| {
        let nearest = pts[run[0]..run[1]].iter().map(|&(_, p)| range(p)).fold(f64::INFINITY, f64::min);
        let edge_to_neighbour = if run[0] == 0 { pts[run[1] - 1].1 } else { pts[run[0]].1 };
        if range(edge_to_neighbour) < range(neighbour)
            && nearest < range(neighbour)
            && run_width(&pts, run) < MIN_PLANE_M
            && !(reading == Reading::Shape && grazing_wall(bins, &pts, run))
        {
            run_mask(&pts, run)
        } else {
            0
        }
    };
    let (first, last) = (runs[0], runs[runs.len() - 1]);
    let left = candidate(first, pts[first[1]].1);
    let right = candidate(last, pts[last[0] - 1].1);
    if left != 0 && right != 0 {
        return [0, 0];
    }
    [left, right]
}

/// A wall along the heading beyond which the camera sees a parallel one: the partner of a
/// corridor's wall, of which an obstacle or the camera's turn may leave only a few bins in view.
/// Fitted with the direction of `first` (only its offset is free), so [`PARTNER_POINTS`] points
/// spanning [`PARTNER_M`] suffice; it must lie on the other side of the camera.
fn partner(bins: &[Bin], free: u64, first: &Line) -> Option<Line> {
    if first.heading_angle_deg() > PARTNER_MAX_DEG {
        return None;
    }
    let side = |p: [f64; 2]| (p[0] - first.centre[0]) * first.dir[1] - (p[1] - first.centre[1]) * first.dir[0];
    let camera = side([0.0, 0.0]);
    let mut best: Option<(usize, f64, u64)> = None;
    for (b, bin) in bins.iter().enumerate().take(64) {
        let Some(p) = bin.point.filter(|_| free >> b & 1 == 1) else { continue };
        // beyond the camera, seen from the first wall
        if side(p) * camera <= 0.0 || side(p).abs() < camera.abs() + PARTNER_MIN_OFFSET_M {
            continue;
        }
        let line = Line { centre: p, dir: first.dir, ..Line::default() };
        let m = inliers_of(bins, free, &line);
        let cost: f64 = (0..bins.len())
            .filter(|&q| m >> q & 1 == 1)
            .filter_map(|q| bins[q].point)
            .map(|q| (line.distance(q) / tolerance(range(q))).powi(2))
            .sum();
        let n = m.count_ones() as usize;
        if best.is_none_or(|(bn, bc, _)| n > bn || (n == bn && cost < bc)) {
            best = Some((n, cost, m));
        }
    }
    let (n, _, mask) = best?;
    if n < PARTNER_POINTS {
        return None;
    }
    // the offset is the inliers' mean distance across the direction; the extent along it
    let pts: Vec<[f64; 2]> = (0..bins.len()).filter(|&q| mask >> q & 1 == 1).filter_map(|q| bins[q].point).collect();
    let nf = pts.len() as f64;
    let centre = [pts.iter().map(|p| p[0]).sum::<f64>() / nf, pts.iter().map(|p| p[1]).sum::<f64>() / nf];
    let along = |p: &[f64; 2]| (p[0] - centre[0]) * first.dir[0] + (p[1] - centre[1]) * first.dir[1];
    let lo = pts.iter().map(along).fold(f64::INFINITY, f64::min);
    let hi = pts.iter().map(along).fold(f64::NEG_INFINITY, f64::max);
    (hi - lo >= PARTNER_M).then_some(Line { centre, dir: first.dir, inliers: mask, extent: [lo, hi] })
}

/// The partner of a corridor's wall (`partner`: a parallel wall on the other side of the
/// camera, of which only a few bins may be in view) is looked for only when the first plane
/// runs within this angle of the heading, degrees; the partner holds at least this many points
/// spanning at least this length, m.
pub const PARTNER_MAX_DEG: f64 = 25.0;
pub const PARTNER_POINTS: usize = 2;
pub const PARTNER_M: f64 = 0.5;
/// The partner's points lie at least this far beyond the camera, m (a corridor's half width is
/// more than that; points near the heading, where depth from flow is least reliable, are not a
/// wall).
pub const PARTNER_MIN_OFFSET_M: f64 = 0.5;

impl TpoModel {
    /// Fits the model to the envelope points within [`FIT_RANGE_M`] (at most 64 bins) that are
    /// not on an occluder. An edge run that may be an occluder ([`edge_candidates`]) is left out
    /// first; it is an occluder when it stands clearly in front of every other point in view
    /// (its median range [`clearly_nearer`] than their nearest) and a plane fitted to the rest
    /// passes behind it (its points mostly clearly nearer than the plane's line along their
    /// bearings) or it stands on the far side of the heading from a lone wall along it (where a
    /// corridor's other wall would be); otherwise it is put back and the model refitted with it.
    pub fn fit(bins: &[Bin]) -> Self {
        Self::fit_masked(bins, Self::masks(bins, Reading::Surfaces))
    }

    /// The fit [`TpoModel::fit`] makes, for the TPO's shape: a stretch of wall seen at a
    /// grazing angle (`grazing_wall`: between two door openings, or beside one at the image
    /// edge) is a wall, not an occluder.
    pub fn fit_shape(bins: &[Bin]) -> Self {
        Self::fit_masked(bins, Self::masks(bins, Reading::Shape))
    }

    /// Both fits, `[surfaces, shape]`, as [`TpoModel::fit`] and [`TpoModel::fit_shape`] make
    /// them; fitted once when the two readings leave out the same runs (most steps).
    pub fn fit_both(bins: &[Bin]) -> [Self; 2] {
        let (surfaces, shape) = (Self::masks(bins, Reading::Surfaces), Self::masks(bins, Reading::Shape));
        let fitted = Self::fit_masked(bins, surfaces);
        [fitted, if shape == surfaces { fitted } else { Self::fit_masked(bins, shape) }]
    }

    /// The occluders and the edge candidates of `bins` in `reading`.
    fn masks(bins: &[Bin], reading: Reading) -> (u64, [u64; 2]) {
        (occluders(bins, reading), edge_candidates(bins, reading))
    }

    fn fit_masked(bins: &[Bin], (occluded, edges): (u64, [u64; 2])) -> Self {
        if edges == [0, 0] {
            return Self::fit_without(bins, occluded);
        }
        let model = Self::fit_without(bins, occluded | edges[0] | edges[1]);
        // the nearest of the other points: an obstacle at the edge stands clearly in front of
        // everything else in view, a stretch of wall beside an opening does not
        let others = (0..bins.len().min(64))
            .filter(|&b| (occluded | edges[0] | edges[1]) >> b & 1 == 0)
            .filter_map(|b| bins[b].point.map(range))
            .fold(f64::INFINITY, f64::min);
        // the candidate's median range
        let median = |mask: u64| {
            let mut r: Vec<f64> = (0..bins.len().min(64))
                .filter(|&b| mask >> b & 1 == 1)
                .filter_map(|b| bins[b].point.map(range))
                .collect();
            r.sort_by(f64::total_cmp);
            r.get(r.len() / 2).copied().unwrap_or(f64::INFINITY)
        };
        let in_front = |mask: u64| others.is_finite() && clearly_nearer(median(mask), others);
        let behind = |mask: u64| {
            let (mut n, mut nearer) = (0, 0);
            for (b, bin) in bins.iter().enumerate().take(64) {
                let Some(p) = bin.point.filter(|_| mask >> b & 1 == 1) else { continue };
                n += 1;
                let plane = model.planes().filter_map(|l| l.hit(bin.bearing, f64::INFINITY)).min_by(f64::total_cmp);
                nearer += usize::from(plane.is_some_and(|h| clearly_nearer(range(p), h)));
            }
            n > 0 && 2 * nearer > n
        };
        // or it stands on the far side of the heading from a lone wall along it, where that
        // wall's partner (a corridor's other wall) would be seen
        let hides_partner = |mask: u64| {
            let side = match model.lines {
                [Some(l), None] if l.heading_angle_deg() <= PARTNER_MAX_DEG => l.side(),
                _ => return false,
            };
            (0..bins.len().min(64))
                .filter(|&b| mask >> b & 1 == 1)
                .filter_map(|b| bins[b].point)
                .all(|p| p[1] * side < 0.0)
        };
        let confirmed =
            edges.iter().filter(|&&m| m != 0 && in_front(m) && (behind(m) || hides_partner(m))).fold(0, |a, &m| a | m);
        if confirmed == edges[0] | edges[1] {
            return model;
        }
        Self::fit_without(bins, occluded | confirmed)
    }

    /// The fit with the bins of `occluded` left out.
    fn fit_without(bins: &[Bin], occluded: u64) -> Self {
        let mut free = 0u64;
        for (b, bin) in bins.iter().enumerate().take(64) {
            if bin.point.is_some_and(|p| range(p) <= FIT_RANGE_M) && occluded >> b & 1 == 0 {
                free |= 1 << b;
            }
        }
        let first = best_line(bins, free, occluded, MIN_PLANE_M);
        let second = first.and_then(|l| {
            best_line(bins, free & !l.inliers, occluded, MIN_PLANE_M).or_else(|| partner(bins, free & !l.inliers, &l))
        });
        match split(bins, free, occluded, &[first, second]) {
            Some([a, b]) => Self { lines: [Some(a), Some(b)], occluded },
            None => Self { lines: [first, second], occluded },
        }
    }

    pub fn planes(&self) -> impl Iterator<Item = &Line> {
        self.lines.iter().flatten()
    }

    /// Whether the profile `bins` this model was fitted to says anything about the TPO: a plane
    /// was fitted, or fewer points than a plane needs lie within [`RANGE_M`] (nothing there).
    /// Surfaces within range that fit no plane say only that their place is unknown (depth
    /// noise at a low resolution scatters a wall's points), not that no TPO is there.
    pub fn places(&self, bins: &[Bin]) -> bool {
        let near = bins.iter().filter_map(|b| b.point).filter(|&p| range(p) <= RANGE_M).count();
        self.planes().next().is_some() || near < MIN_PLANE_POINTS
    }

    /// Whether bin `b` is an inlier of a plane.
    pub fn is_inlier(&self, b: usize) -> bool {
        self.planes().any(|l| l.inliers >> b & 1 == 1)
    }

    /// Nearest range along `bearing` to a plane (within its extent widened by `slack_m`).
    pub fn hit(&self, bearing: f64, slack_m: f64) -> Option<f64> {
        self.planes().filter_map(|l| l.hit(bearing, slack_m)).min_by(f64::total_cmp)
    }

    /// The range the TPO's surface has in bin `b`: what an obstacle must be clearly nearer
    /// than. The bin's own envelope point when it is a plane's inlier, or beyond the planes, or
    /// no plane passes there; the plane's range when the envelope point is clearly nearer than
    /// a plane (an obstacle hides the plane in the whole bin) or missing; infinite when nothing
    /// but unexplained surfaces is there (no TPO: anything within range is an obstacle).
    pub fn expected_range(&self, bins: &[Bin], b: usize) -> f64 {
        let bin = bins[b];
        let plane = self.hit(bin.bearing, 1.5);
        match (bin.point, plane) {
            (Some(p), _) if self.is_inlier(b) => range(p),
            (Some(p), Some(h)) if !clearly_nearer(range(p), h) => range(p),
            (_, Some(h)) => h,
            (Some(_), None) => f64::INFINITY,
            (None, None) => f64::INFINITY,
        }
    }
}

/// The obstacle test: range `r` is clearly nearer than the reference range `reference`
/// (always, for a finite `r`, when the reference is infinite: no TPO surface there).
pub fn clearly_nearer(r: f64, reference: f64) -> bool {
    if reference == f64::INFINITY {
        return r.is_finite();
    }
    reference - r > (0.2 * reference).max(0.3)
}

/// The classifier inputs for one frame pair.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Features {
    /// Fraction of the bins whose envelope point is an inlier of a plane that comes within
    /// [`RANGE_M`] (its second-nearest inlier does; all its inliers count).
    pub near_frac: f64,
    /// Number of planes (0, 1, 2).
    pub planes: f64,
    /// Angle between the two planes, degrees in [0, 90] (0 with fewer than two).
    pub pair_angle_deg: f64,
    /// The larger angle of the planes to the heading, degrees in [0, 90]: ~0 in a corridor,
    /// ~90 facing a wall (90 without planes).
    pub side_angle_deg: f64,
    /// 1 when two planes lie on opposite sides of the heading (a corridor), else 0.
    pub opposite: f64,
    /// Range along the heading to the plane most across it, ignoring gaps, m (capped at
    /// [`OPEN_AHEAD_MAX_M`], also the value when no plane crosses the heading).
    pub front_m: f64,
    /// Range along the heading to the first surface actually there (planes, with their gaps,
    /// and the envelope of the centre bins), m, capped at [`OPEN_AHEAD_MAX_M`].
    pub open_ahead_m: f64,
    /// Width of the widest gap in a plane that shows a surface clearly beyond the plane (or
    /// nothing), flanked by the plane's inliers on both sides, m: a door's opening.
    pub gap_m: f64,
    /// How far the point where the two planes' lines cross lies outside the planes' seen
    /// extents, m (the larger of the two; 0 when both reach it): ~0 at a corner, large for a
    /// door's wall and the room's back wall seen through it. [`OPEN_AHEAD_MAX_M`] with fewer
    /// than two planes or parallel ones.
    pub meet_m: f64,
    /// Forward distance to where the two planes meet, m (`None` when they do not).
    pub vertex_m: Option<f64>,
    /// 1 when the only plane runs along the heading (within [`PARTNER_MAX_DEG`]) and an
    /// occluder stands on the other side of the heading, where its partner would be seen (a
    /// corridor's other wall hidden by a person or a box), else 0.
    #[serde(default)]
    pub hidden_partner: f64,
}

/// Where two lines meet (on the floor plan).
fn intersect(a: &Line, b: &Line) -> Option<[f64; 2]> {
    let det = a.dir[0] * (-b.dir[1]) - a.dir[1] * (-b.dir[0]);
    if det.abs() < 1e-6 {
        return None;
    }
    let (dx, dy) = (b.centre[0] - a.centre[0], b.centre[1] - a.centre[1]);
    let s = (dx * (-b.dir[1]) - dy * (-b.dir[0])) / det;
    Some([a.centre[0] + s * a.dir[0], a.centre[1] + s * a.dir[1]])
}

impl Features {
    /// Computes the features from the profile bins (left image column first) and their model.
    pub fn compute(bins: &[Bin], model: &TpoModel) -> Self {
        let nb = bins.len().max(1) as f64;
        // a plane is near when it comes within RANGE_M (its second-nearest inlier, so that one
        // noisy point does not decide); all its inliers count, also those beyond (a corridor's
        // wall seen at a grazing angle is mostly far)
        let near_plane = |l: &Line| {
            let mut r: Vec<f64> =
                (0..bins.len()).filter(|&b| l.inliers >> b & 1 == 1).filter_map(|b| bins[b].point.map(range)).collect();
            r.sort_by(f64::total_cmp);
            r.get(1).is_some_and(|&x| x <= RANGE_M)
        };
        let near_inliers = model.planes().filter(|l| near_plane(l)).fold(0u64, |m, l| m | l.inliers);
        let near = (0..bins.len()).filter(|&b| near_inliers >> b & 1 == 1).count();
        let planes: Vec<&Line> = model.planes().collect();
        let pair_angle_deg = match planes[..] {
            [a, b] => angle_between(a.dir, b.dir),
            _ => 0.0,
        };
        let side_angle_deg = planes
            .iter()
            .map(|l| l.heading_angle_deg())
            .fold(None, |m: Option<f64>, a| Some(m.map_or(a, |m| m.max(a))));
        let opposite = match planes[..] {
            [a, b] if a.side() * b.side() < 0.0 => 1.0,
            _ => 0.0,
        };
        // the plane most across the heading, hit on the heading ignoring gaps
        let front = planes
            .iter()
            .filter(|l| l.heading_angle_deg() >= 30.0)
            .filter_map(|l| l.hit(0.0, 1.0))
            .min_by(f64::total_cmp);
        let (gap_m, gap_bearings) = Self::widest_gap(bins, &planes, model.occluded);
        let heading_in_gap = gap_bearings.is_some_and(|[lo, hi]| lo <= 0.0 && 0.0 <= hi);
        // through a gap, the next plane behind it (if any)
        let open_ahead = if heading_in_gap {
            planes
                .iter()
                .filter_map(|l| l.hit(0.0, 0.5))
                .filter(|&t| front.is_none_or(|f| t > f + 0.3))
                .min_by(f64::total_cmp)
        } else {
            model.hit(0.0, 0.5)
        };
        let vertex = match planes[..] {
            [a, b] if pair_angle_deg >= 5.0 => intersect(a, b),
            _ => None,
        };
        // how far `p` lies beyond the plane's seen extent, unless an occluder hides the stretch
        let outside = |l: &Line, p: [f64; 2]| {
            let s = (p[0] - l.centre[0]) * l.dir[0] + (p[1] - l.centre[1]) * l.dir[1];
            let d = (l.extent[0] - s).max(s - l.extent[1]).max(0.0);
            let e = if s < l.extent[0] { l.extent[0] } else { l.extent[1] };
            let end = [l.centre[0] + e * l.dir[0], l.centre[1] + e * l.dir[1]];
            if d > 0.0 && Self::stretch_hidden(bins, model.occluded, end, p, l.inliers) { 0.0 } else { d }
        };
        let meet_m = match (vertex, &planes[..]) {
            (Some(v), [a, b]) => outside(a, v).max(outside(b, v)).min(OPEN_AHEAD_MAX_M),
            _ => OPEN_AHEAD_MAX_M,
        };
        let vertex_m = vertex.map(|p| p[0]).filter(|&x| x > 0.0);
        let hidden_partner = match planes[..] {
            [l] if l.heading_angle_deg() <= PARTNER_MAX_DEG => {
                let across = (0..bins.len().min(64))
                    .filter(|&b| model.occluded >> b & 1 == 1)
                    .filter(|&b| bins[b].point.is_some_and(|p| p[1] * l.side() < 0.0))
                    .count();
                if across >= PARTNER_POINTS { 1.0 } else { 0.0 }
            }
            _ => 0.0,
        };
        let cap = |x: Option<f64>| x.unwrap_or(OPEN_AHEAD_MAX_M).clamp(0.0, OPEN_AHEAD_MAX_M);
        Self {
            near_frac: near as f64 / nb,
            planes: planes.len() as f64,
            pair_angle_deg,
            side_angle_deg: side_angle_deg.unwrap_or(90.0),
            opposite,
            front_m: cap(front),
            open_ahead_m: cap(open_ahead),
            gap_m,
            meet_m,
            vertex_m,
            hidden_partner,
        }
    }

    /// Whether the stretch of a plane from the end of its seen extent `end` to the point `v`
    /// (where it meets another) is hidden by an occluder: the bins whose bearings lie between
    /// (leaving out half a bin at `v`, and the plane's own inliers `own`: the bin of its end
    /// point may reach past `end`) include occluded ones and show nothing else. Behind a
    /// person the planes may well reach their crossing: a corner's edge hidden.
    fn stretch_hidden(bins: &[Bin], occluded: u64, end: [f64; 2], v: [f64; 2], own: u64) -> bool {
        let half = if bins.len() > 1 {
            0.5 * (bins[0].bearing - bins[bins.len() - 1].bearing).abs() / (bins.len() - 1) as f64
        } else {
            0.0
        };
        let (a, bv) = (end[1].atan2(end[0]), v[1].atan2(v[0]));
        let (lo, hi) = if a < bv { (a, bv - half) } else { (bv + half, a) };
        let mut any = false;
        for (b, bin) in bins.iter().enumerate().take(64) {
            if bin.bearing <= lo || bin.bearing >= hi || bin.point.is_none() || own >> b & 1 == 1 {
                continue;
            }
            if occluded >> b & 1 == 0 {
                return false;
            }
            any = true;
        }
        any
    }

    /// The widest gap (m) among the planes' [`openings`], and the bearings `[right, left]` of
    /// its edges.
    fn widest_gap(bins: &[Bin], planes: &[&Line], occluded: u64) -> (f64, Option<[f64; 2]>) {
        let mut best = (0.0, None);
        for l in planes {
            for o in openings(bins, l, occluded) {
                if o.width_m() > best.0 {
                    best = (o.width_m(), Some(o.bearings));
                }
            }
        }
        best
    }
}

/// An opening in a plane: a stretch between two of its inlier bins where some bin shows a
/// surface clearly beyond the plane and none is nearer than it (a door's opening, seen head-on
/// or in a side wall).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Opening {
    /// Where the jambs are on the plane, (forward, left) from the camera, m: the rays halfway
    /// between the flanking inliers and their neighbours in the gap meet it there.
    pub jambs_m: [[f64; 2]; 2],
    /// Bearings `[right, left]` of the jambs, rad.
    pub bearings: [f64; 2],
}

impl Opening {
    /// Jamb to jamb, m.
    pub fn width_m(&self) -> f64 {
        let [a, b] = self.jambs_m;
        (a[0] - b[0]).hypot(a[1] - b[1])
    }
}

/// The openings of plane `line` among `bins` (left image column first), bins of `occluded`
/// hiding, not closing, what lies behind them.
pub fn openings<'a>(bins: &'a [Bin], line: &'a Line, occluded: u64) -> impl Iterator<Item = Opening> + 'a {
    let near_occluder = move |x: usize| x < 64 && occluded >> x & 1 == 1;
    let inliers = line.inliers;
    // each inlier bin with the next one
    (0..bins.len().min(64)).filter(move |&i| inliers >> i & 1 == 1).filter_map(move |i| {
        let above = inliers >> i >> 1;
        let j = i + 1 + above.trailing_zeros() as usize;
        if above == 0 || j < i + 2 || j >= bins.len() {
            return None;
        }
        let mut beyond = false;
        let mut blocked = false;
        for (k, bin) in bins.iter().enumerate().take(j).skip(i + 1) {
            let (Some(p), Some(h)) = (bin.point, line.hit(bin.bearing, 2.0)) else { continue };
            if near_occluder(k) {
                // an obstacle in front of the opening hides it, does not close it
                continue;
            }
            let r = range(p);
            beyond |= r - h > (0.15 * h).max(0.4);
            if near_occluder(k + 1) || (k > 0 && near_occluder(k - 1)) {
                // the occluder's outline: its flow mixes with what lies behind
                continue;
            }
            blocked |= clearly_nearer(r, h);
        }
        if !beyond || blocked {
            return None;
        }
        // the jambs lie between the flanking inliers and their neighbours in the gap
        let edge = |a: usize, b: usize| 0.5 * (bins[a].bearing + bins[b].bearing);
        let (ba, bb) = (edge(i, i + 1), edge(j - 1, j));
        let (ra, rb) = (line.hit(ba, 2.0)?, line.hit(bb, 2.0)?);
        let (pa, pb) = ([ra * ba.cos(), ra * ba.sin()], [rb * bb.cos(), rb * bb.sin()]);
        let (right, left) = if ba <= bb { (pa, pb) } else { (pb, pa) };
        Some(Opening { jambs_m: [right, left], bearings: [ba.min(bb), ba.max(bb)] })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bins_on(points: &[[f64; 2]]) -> Vec<Bin> {
        points.iter().map(|&p| Bin { point: Some(p), bearing: p[1].atan2(p[0]) }).collect()
    }

    #[test]
    fn an_occluder_is_left_out_of_the_fit_and_does_not_close_a_door() {
        // wall at 3 m, a person (0.4 m wide) 1.5 m ahead in front of it
        let mut pts: Vec<[f64; 2]> = (0..16).map(|k| [3.0, 1.4 - k as f64 * 0.19]).collect();
        for (k, p) in pts.iter_mut().enumerate().take(9).skip(6) {
            *p = [1.5, 0.5 * (1.4 - k as f64 * 0.19)];
        }
        let bins = bins_on(&pts);
        let m = TpoModel::fit(&bins);
        assert_eq!(m.occluded, 0b1_1100_0000, "{m:?}");
        assert!(m.lines[0].is_some_and(|l| l.count() == 13) && m.lines[1].is_none(), "{m:?}");
        assert!((m.expected_range(&bins, 7) - 3.0).abs() < 0.05);
        let f = Features::compute(&bins, &m);
        assert_eq!((f.planes, f.gap_m), (1.0, 0.0), "{f:?}");
        // the same wall with a 1.3 m opening (back wall at 6 m), the person in front of it
        let pts: Vec<[f64; 2]> = (0..16)
            .map(|k| {
                let y = 1.4 - k as f64 * 0.19;
                match k {
                    6..=8 => [1.5, y * 0.5],
                    5 | 9 | 10 => [6.0, y * 2.0],
                    _ => [3.0, y],
                }
            })
            .collect();
        let bins = bins_on(&pts);
        let m = TpoModel::fit(&bins);
        let f = Features::compute(&bins, &m);
        assert!((0.9..1.8).contains(&f.gap_m) && (f.front_m - 3.0).abs() < 0.05, "{f:?} {m:?}");
    }

    #[test]
    fn an_occluder_at_the_image_edge_is_left_out_when_it_stands_in_front_of_everything() {
        // a wall at 2 m turned 28°, a person 0.85 m ahead covering the six rightmost bins
        let mut pts: Vec<[f64; 2]> = (0..16)
            .map(|k| {
                let b = (25.0 - 3.3 * k as f64).to_radians();
                // wall: x = 2 + 0.53 y (turned), intersected with the ray at bearing b
                let r = 2.0 / (b.cos() - 0.53 * b.sin());
                [r * b.cos(), r * b.sin()]
            })
            .collect();
        for (k, p) in pts.iter_mut().enumerate().skip(10) {
            let b = (25.0 - 3.3 * k as f64).to_radians();
            *p = [0.85 * b.cos(), 0.85 * b.sin()];
        }
        let bins = bins_on(&pts);
        assert_eq!(edge_candidates(&bins, Reading::Surfaces), [0, 0b1111_1100_0000_0000]);
        let m = TpoModel::fit(&bins);
        assert_eq!(m.occluded, 0b1111_1100_0000_0000, "{m:?}");
        let f = Features::compute(&bins, &m);
        assert_eq!(f.planes, 1.0, "{f:?}");
        assert!((f.front_m - 2.0).abs() < 0.05, "{f:?}");
        // a door's wall at both edges with the room behind the opening: no edge occluder
        let pts: Vec<[f64; 2]> = (0..16)
            .map(|k| {
                let y = 1.4 - k as f64 * 0.19;
                if y.abs() < 1.0 { [5.0, y * 2.5] } else { [2.0, y] }
            })
            .collect();
        assert_eq!(edge_candidates(&bins_on(&pts), Reading::Surfaces), [0, 0]);
    }

    /// The view down a 2 m corridor from 0.3 m left of its centre, over 16 bins of ±25°: the
    /// walls 0.7 m to the left and 1.3 m to the right, each with a door opening from 2.45 m to
    /// 3.35 m ahead onto a room 4 m deep.
    fn corridor_with_doors() -> Vec<Bin> {
        (0..16)
            .map(|k| {
                let b = (25.0 - 50.0 * (k as f64 + 0.5) / 16.0).to_radians();
                let wall = if b > 0.0 { 0.7 } else { 1.3 };
                let mut forward = wall / b.tan().abs();
                if (2.45..=3.35).contains(&forward) {
                    forward = (wall + 4.0) / b.tan().abs();
                }
                Bin { point: Some([forward, forward * b.tan()]), bearing: b }
            })
            .collect()
    }

    #[test]
    fn stretches_of_a_corridor_wall_between_openings_are_walls_for_the_shape_only() {
        // each wall shows a stretch before its door and one after it: narrower than a plane,
        // nearer than the room seen through the door and than the far wall past a depth step,
        // but on one line with the farther wall, seen at a grazing angle
        let bins = corridor_with_doors();
        assert_eq!(occluders(&bins, Reading::Shape), 0);
        assert_eq!(edge_candidates(&bins, Reading::Shape), [0, 0]);
        let m = TpoModel::fit_shape(&bins);
        let f = Features::compute(&bins, &m);
        assert_eq!(f.planes, 2.0, "{m:?}");
        assert!(f.pair_angle_deg < 3.0 && f.side_angle_deg < 3.0 && f.opposite == 1.0, "{f:?} {m:?}");
        let mut sides: Vec<f64> = m.planes().map(|l| l.side()).collect();
        sides.sort_by(f64::total_cmp);
        assert!((sides[0] + 1.3).abs() < 0.05 && (sides[1] - 0.7).abs() < 0.05, "{m:?}");
        // for the surfaces the same stretches stay occluders: the obstacle test never loses a
        // narrow thing nearer than its neighbours to a wall
        assert_eq!(occluders(&bins, Reading::Surfaces), 0b111_0000);
        assert_eq!(edge_candidates(&bins, Reading::Surfaces), [0b111, 0]);
        let surfaces = TpoModel::fit(&bins);
        assert_ne!(surfaces.occluded & 0b111_0000, 0, "{surfaces:?}");
        assert_eq!(TpoModel::fit_both(&bins), [surfaces, m]);
        // where the readings agree, both fits are one
        let wall: Vec<Bin> = (0..16)
            .map(|k| {
                let b = (25.0 - 50.0 * (k as f64 + 0.5) / 16.0_f64).to_radians();
                Bin { point: Some([2.0, 2.0 * b.tan()]), bearing: b }
            })
            .collect();
        let [a, b] = TpoModel::fit_both(&wall);
        assert_eq!((a, b), (TpoModel::fit(&wall), TpoModel::fit_shape(&wall)));
        assert_eq!(a, b);
        // a box seen face on in front of the far corridor is an occluder for the shape too,
        // although its face lines up with the walls' points at its range
        let mut bins = bins;
        for bin in bins.iter_mut().take(9).skip(7) {
            bin.point = Some([3.0, 3.0 * bin.bearing.tan()]);
        }
        assert_eq!(occluders(&bins, Reading::Shape), 0b1_1000_0000);
    }

    #[test]
    fn an_occluder_in_front_of_another_does_not_hide_it() {
        // a wall at 3.5 m, a person at 2 m over bins 5–7, a noisy bin at 1.1 m right of it
        let mut pts: Vec<[f64; 2]> = (0..16).map(|k| [3.5, 1.4 - k as f64 * 0.19]).collect();
        for (k, p) in pts.iter_mut().enumerate().take(8).skip(5) {
            *p = [2.0, (1.4 - k as f64 * 0.19) * 2.0 / 3.5];
        }
        pts[8] = [1.1, -0.05];
        let m = TpoModel::fit(&bins_on(&pts));
        assert_eq!(m.occluded, 0b1_1110_0000, "{m:?}");
    }

    #[test]
    fn a_lone_corridor_wall_with_an_occluder_across_the_heading_has_a_hidden_partner() {
        // the left wall of a corridor 1 m to the left, a person 1.2 m ahead on the right edge
        let mut pts: Vec<Option<[f64; 2]>> = (0..10).map(|k| Some([1.5 + k as f64 * 0.5, 1.0])).collect();
        pts.extend([None, None]);
        pts.extend((0..4).map(|k| Some([1.2, -0.2 - 0.12 * k as f64])));
        let bins: Vec<Bin> =
            pts.iter().map(|p| Bin { point: *p, bearing: p.map_or(0.0, |p: [f64; 2]| p[1].atan2(p[0])) }).collect();
        let m = TpoModel::fit(&bins);
        assert_eq!(m.occluded, 0b1111 << 12, "{m:?}");
        let f = Features::compute(&bins, &m);
        assert_eq!((f.planes, f.hidden_partner), (1.0, 1.0), "{f:?}");
        let mut c = super::super::classify::Classifier::builtin().unwrap();
        assert_eq!(c.classify(&f).unwrap().shape, crate::perception::TpoShape::Corridor);
    }

    #[test]
    fn a_corridor_wall_hidden_but_for_two_bins_is_found_as_the_partner() {
        let mut pts = Vec::new();
        for k in 0..10 {
            pts.push(Some([1.5 + k as f64 * 0.5, 1.0]));
        }
        pts.extend([None, None, None, None]);
        pts.extend([Some([2.5, -1.0]), Some([2.0, -1.0])]);
        let bins: Vec<Bin> =
            pts.iter().map(|p| Bin { point: *p, bearing: p.map_or(0.0, |p: [f64; 2]| p[1].atan2(p[0])) }).collect();
        let m = TpoModel::fit(&bins);
        let f = Features::compute(&bins, &m);
        assert_eq!((f.planes, f.opposite), (2.0, 1.0), "{f:?}");
        assert!(f.pair_angle_deg < 1.0 && f.side_angle_deg < 1.0, "{f:?}");
        // one wall alone has no partner
        let bins: Vec<Bin> = bins.into_iter().take(10).collect();
        assert_eq!(Features::compute(&bins, &TpoModel::fit(&bins)).planes, 1.0);
    }

    #[test]
    fn a_corner_whose_edge_a_person_hides_is_split_where_its_walls_cross_behind_the_person() {
        // a 140° corner 3 m ahead (each wall 20° off frontal), a person 1.4 m ahead over bins 6–9
        let bearing = |k: usize| (25.0 - 50.0 * k as f64 / 15.0f64).to_radians();
        let t = 20f64.to_radians().tan();
        let pts: Vec<[f64; 2]> = (0..16)
            .map(|k| {
                let b = bearing(k);
                // wall x = 3 - t·|y| along the ray at bearing b
                let r = if (6..=9).contains(&k) { 1.4 } else { 3.0 / (b.cos() + t * b.sin().abs()) };
                [r * b.cos(), r * b.sin()]
            })
            .collect();
        let bins = bins_on(&pts);
        let m = TpoModel::fit(&bins);
        assert_eq!(m.occluded, 0b11_1100_0000, "{m:?}");
        let [Some(a), Some(b)] = m.lines else { panic!("{m:?}") };
        assert!(behind_occluder(&bins, m.occluded, 5, 10, &a, &b), "{m:?}");
        let v = intersect(&a, &b).unwrap();
        assert!((v[0] - 3.0).abs() < 0.05 && v[1].abs() < 0.05, "{v:?}");
        // the wall's two sides of a person are one line: they do not cross behind it
        let wall = bins_on(
            &(0..16)
                .map(|k| if (6..=9).contains(&k) { [1.4, 0.0] } else { [3.0, 0.2 * (7.5 - k as f64)] })
                .collect::<Vec<_>>(),
        );
        let m = TpoModel::fit(&wall);
        assert!(m.lines[0].is_some() && m.lines[1].is_none(), "{m:?}");
    }

    #[test]
    fn a_corner_bends_depth_noise_on_a_wall_does_not() {
        let all = (1u64 << 16) - 1;
        // a 90° corner 3 m ahead: both walls at 45° to the heading
        let corner: Vec<[f64; 2]> = (0..16).map(|k| 1.6 - k as f64 * 0.2).map(|y: f64| [3.0 - y.abs(), y]).collect();
        assert!(bent(&bins_on(&corner), all));
        // a frontal wall at 1.4 m with ±0.12 m of alternating depth noise
        let noisy: Vec<[f64; 2]> =
            (0..16).map(|k| [1.4 + if k % 2 == 0 { 0.12 } else { -0.12 }, 0.7 - k as f64 * 0.09]).collect();
        assert!(!bent(&bins_on(&noisy), all));
        // and no corner is split out of it
        let m = TpoModel::fit(&bins_on(&noisy));
        assert!(m.planes().all(|l| l.heading_angle_deg() > 80.0), "{m:?}");
    }

    #[test]
    fn a_frontal_wall_is_one_plane_across_the_heading() {
        let pts: Vec<[f64; 2]> = (0..16).map(|k| [3.0, 1.4 - k as f64 * 0.19]).collect();
        let bins = bins_on(&pts);
        let m = TpoModel::fit(&bins);
        assert!(m.lines[0].is_some() && m.lines[1].is_none(), "{m:?}");
        let f = Features::compute(&bins, &m);
        assert_eq!(f.planes, 1.0);
        assert!((f.side_angle_deg - 90.0).abs() < 1e-6 && (f.front_m - 3.0).abs() < 1e-9, "{f:?}");
        assert_eq!(f.gap_m, 0.0);
        assert_eq!(f.near_frac, 1.0);
    }

    #[test]
    fn a_door_is_a_gap_with_a_surface_behind() {
        // wall at 3 m with a 1 m opening in the middle showing a back wall at 6 m
        let pts: Vec<[f64; 2]> = (0..16)
            .map(|k| {
                let y = 1.4 - k as f64 * 0.19;
                if y.abs() < 0.5 { [6.0, y * 2.0] } else { [3.0, y] }
            })
            .collect();
        let bins = bins_on(&pts);
        let m = TpoModel::fit(&bins);
        let f = Features::compute(&bins, &m);
        assert!((0.8..1.3).contains(&f.gap_m), "{f:?}");
        assert!(f.open_ahead_m > 5.0 && (f.front_m - 3.0).abs() < 1e-6, "{f:?}");
    }

    #[test]
    fn a_door_in_a_side_wall_is_an_opening_of_that_wall() {
        // a corridor 2 m wide seen from its centre line: bins every 3.4° over ±26°; the left
        // wall (y = 1) has a door from x = 2.6 m to 3.5 m with a room 3 m deep behind it
        let (door, room_y) = (2.6..=3.5, 4.0);
        let bins: Vec<Bin> = (0..16)
            .map(|k| {
                let b = (26.0 - k as f64 * 3.4_f64).to_radians();
                let (s, c) = b.sin_cos();
                let on_wall = |y: f64| [y / s * c, y];
                let point = match b {
                    b if b > 0.0 => {
                        let p = on_wall(1.0);
                        if door.contains(&p[0]) { on_wall(room_y) } else { p }
                    }
                    b if b < 0.0 => on_wall(-1.0),
                    _ => [8.0, 0.0],
                };
                Bin { point: Some(point), bearing: b }
            })
            .collect();
        let m = TpoModel::fit(&bins);
        let left = m.planes().find(|l| l.side() > 0.5).expect("the left wall is fitted");
        let found: Vec<Opening> = openings(&bins, left, m.occluded).collect();
        assert_eq!(found.len(), 1, "{found:?}");
        let [right, far] = found[0].jambs_m;
        // the jambs lie halfway between the bins on either side of each edge: within one bin
        assert!((right[1] - 1.0).abs() < 0.05 && (far[1] - 1.0).abs() < 0.05, "{found:?}");
        assert!((right[0] - 3.5).abs() < 0.35 && (far[0] - 2.6).abs() < 0.35, "{found:?}");
        assert!((0.5..1.3).contains(&found[0].width_m()), "{found:?}");
        // the right wall has none
        let other = m.planes().find(|l| l.side() < -0.5).expect("the right wall is fitted");
        assert_eq!(openings(&bins, other, m.occluded).count(), 0);
    }

    #[test]
    fn a_corridor_is_two_planes_along_the_heading_on_both_sides() {
        let mut pts = Vec::new();
        for k in 0..8 {
            pts.push([1.5 + k as f64 * 0.5, 1.0]);
        }
        for k in 0..8 {
            pts.push([5.0 - k as f64 * 0.5, -1.0]);
        }
        let bins = bins_on(&pts);
        let f = Features::compute(&bins, &TpoModel::fit(&bins));
        assert_eq!((f.planes, f.opposite), (2.0, 1.0), "{f:?}");
        assert!(f.side_angle_deg < 1.0 && f.pair_angle_deg < 1.0 && f.open_ahead_m == OPEN_AHEAD_MAX_M, "{f:?}");
    }

    #[test]
    fn surfaces_within_range_that_fit_no_plane_place_nothing_a_wall_or_an_empty_view_does() {
        // points scattered in depth (no three on a line within the fit's tolerance), and a lone
        // 0.4 m box face: surfaces within range, no plane
        for pts in [
            vec![[1.6, 0.6], [3.4, 0.2], [2.0, -0.2], [3.8, -0.6], [1.2, 0.1]],
            vec![[1.5, 0.2], [1.5, 0.07], [1.5, -0.07], [1.5, -0.2]],
        ] {
            let bins = bins_on(&pts);
            let m = TpoModel::fit(&bins);
            assert!(m.planes().next().is_none() && !m.places(&bins), "{pts:?}: {m:?}");
        }
        // a wall places; so do two points (too few for a plane) and points beyond RANGE_M only
        let wall = bins_on(&(0..16).map(|k| [3.0, 1.4 - k as f64 * 0.19]).collect::<Vec<_>>());
        let two = bins_on(&[[1.5, 0.2], [2.5, -0.3]]);
        let far = bins_on(&[[6.0, 1.5], [7.5, 0.2], [6.2, -1.0], [9.0, -2.5]]);
        for bins in [wall, two, far] {
            assert!(TpoModel::fit(&bins).places(&bins), "{bins:?}");
        }
    }

    #[test]
    fn a_narrow_object_is_not_a_plane_and_is_an_obstacle_reference() {
        // a 0.4 m box face 1.5 m ahead and nothing else: no plane, obstacle reference infinite
        let bins = bins_on(&[[1.5, 0.2], [1.5, 0.07], [1.5, -0.07], [1.5, -0.2]]);
        let m = TpoModel::fit(&bins);
        assert!(m.lines[0].is_none());
        assert_eq!(m.expected_range(&bins, 1), f64::INFINITY);
        // in front of a wall at 3 m the reference is the wall
        let mut pts: Vec<[f64; 2]> = (0..16).map(|k| [3.0, 1.4 - k as f64 * 0.19]).collect();
        pts[7] = [1.5, 0.02];
        pts[8] = [1.5, -0.03];
        let bins = bins_on(&pts);
        let m = TpoModel::fit(&bins);
        assert!(!m.is_inlier(7) && m.is_inlier(6));
        assert!((m.expected_range(&bins, 7) - 3.0).abs() < 0.01);
        assert!(clearly_nearer(1.5, m.expected_range(&bins, 7)));
        assert!(!clearly_nearer(2.8, 3.0));
    }
}
