//! Hierarchical segmentation (paper §3.1, eq. 1), the outlier filter (§2.3) and the obstacle
//! zoom-in (§3.1, Fig. 6).
//!
//! # Index mapping
//! The paper names quadrants by their path: layer-1 `Q_i`, layer-2 `Q_ij`, layer-3 `Q_ijk`, each
//! index running 1 = top-left, 2 = top-right, 3 = bottom-left, 4 = bottom-right inside its
//! parent. Eq. (1) arranges them so that `Q^II` (4×4) and `Q^III` (8×8) are the *spatial*
//! layout of the image, which is how this module stores them: `l2[r][c]` is the layer-2 cell in
//! image row-band `r` and column-band `c`. [`paper_l2`] and [`paper_l3`] convert a position to the
//! paper's name (e.g. `l2[2][1]` is `Q_32`, `l3[7][0]` is `Q_333`).
//!
//! A flow grid of `rows × cols` blocks (both divisible by 8) splits into 8×8 layer-3 cells of
//! `rows/8 × cols/8` vectors each; the paper's 16×16 grid gives 2×2 vectors per layer-3 cell,
//! 4×4 per layer-2 and 8×8 per layer-1 quadrant.

use serde::{Deserialize, Serialize};

/// The shape of a flow grid that OFFIS can segment.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Grid {
    pub rows: usize,
    pub cols: usize,
}

impl Grid {
    /// `None` unless both sides are positive multiples of 8 (three halvings, eq. 1).
    pub fn new(rows: usize, cols: usize) -> Option<Self> {
        (rows >= 8 && cols >= 8 && rows.is_multiple_of(8) && cols.is_multiple_of(8)).then_some(Self { rows, cols })
    }

    pub fn len(&self) -> usize {
        self.rows * self.cols
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The layer-3 cell `[row, col]` (0..8) holding block `(r, c)`.
    pub fn l3_of(&self, r: usize, c: usize) -> [usize; 2] {
        [r / (self.rows / 8), c / (self.cols / 8)]
    }

    /// The layer-2 cell `[row, col]` (0..4) holding block `(r, c)`.
    pub fn l2_of(&self, r: usize, c: usize) -> [usize; 2] {
        [r / (self.rows / 4), c / (self.cols / 4)]
    }
}

/// The paper's name `(i, j)` of the layer-2 cell at `[row, col]` of `Q^II` (eq. 1).
pub fn paper_l2(row: usize, col: usize) -> (u8, u8) {
    let i = 1 + 2 * (row / 2) + col / 2;
    let j = 1 + 2 * (row % 2) + col % 2;
    (i as u8, j as u8)
}

/// The paper's name `(i, j, k)` of the layer-3 cell at `[row, col]` of `Q^III` (eq. 1).
pub fn paper_l3(row: usize, col: usize) -> (u8, u8, u8) {
    let (i, j) = paper_l2(row / 2, col / 2);
    let k = 1 + 2 * (row % 2) + col % 2;
    (i, j, k as u8)
}

/// Averages of one quadrant's inlier vectors (eq. 1): the mean amplitude `|(u, v)|` and the
/// means of the U- and V-projected amplitudes `|u|`, `|v|` (eq. 2, 3, 8), in pixels per frame
/// interval, over `n` vectors. Projections are taken as magnitudes because signed means cancel
/// in a quadrant that straddles the focus of expansion. An empty quadrant (`n == 0`: no valid
/// vector) has zero means; every attribute treats it as "unknown".
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CellStats {
    pub amp: f64,
    pub u: f64,
    pub v: f64,
    pub n: u32,
}

impl CellStats {
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    fn merge(parts: &[CellStats]) -> CellStats {
        let n: u32 = parts.iter().map(|p| p.n).sum();
        if n == 0 {
            return CellStats::default();
        }
        let w = |f: fn(&CellStats) -> f64| parts.iter().map(|p| f(p) * p.n as f64).sum::<f64>() / n as f64;
        CellStats { amp: w(|p| p.amp), u: w(|p| p.u), v: w(|p| p.v), n }
    }
}

/// The quadrant matrices `Q^I` (2×2), `Q^II` (4×4) and `Q^III` (8×8) of eq. (1), in spatial layout.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Quadrants {
    pub l1: [[CellStats; 2]; 2],
    pub l2: [[CellStats; 4]; 4],
    pub l3: [[CellStats; 8]; 8],
}

impl Quadrants {
    /// Eq. (1): averages the vectors with `inlier[i]` set (row-major over `grid`) into the three
    /// layers. `u`, `v` are the (de-rotated) flow components.
    pub fn compute(grid: Grid, u: &[f64], v: &[f64], inlier: &[bool]) -> Self {
        let mut sums = [[(0.0f64, 0.0f64, 0.0f64, 0u32); 8]; 8];
        for r in 0..grid.rows {
            for c in 0..grid.cols {
                let i = r * grid.cols + c;
                if !inlier[i] {
                    continue;
                }
                let [lr, lc] = grid.l3_of(r, c);
                let s = &mut sums[lr][lc];
                s.0 += u[i].hypot(v[i]);
                s.1 += u[i].abs();
                s.2 += v[i].abs();
                s.3 += 1;
            }
        }
        let mut q = Quadrants::default();
        for (r, row) in sums.iter().enumerate() {
            for (c, &(a, su, sv, n)) in row.iter().enumerate() {
                if n > 0 {
                    let k = n as f64;
                    q.l3[r][c] = CellStats { amp: a / k, u: su / k, v: sv / k, n };
                }
            }
        }
        for r in 0..4 {
            for c in 0..4 {
                let l3 = &q.l3;
                q.l2[r][c] = CellStats::merge(&[
                    l3[2 * r][2 * c],
                    l3[2 * r][2 * c + 1],
                    l3[2 * r + 1][2 * c],
                    l3[2 * r + 1][2 * c + 1],
                ]);
            }
        }
        for r in 0..2 {
            for c in 0..2 {
                let l2 = &q.l2;
                q.l1[r][c] = CellStats::merge(&[
                    l2[2 * r][2 * c],
                    l2[2 * r][2 * c + 1],
                    l2[2 * r + 1][2 * c],
                    l2[2 * r + 1][2 * c + 1],
                ]);
            }
        }
        q
    }

    /// The amplitude matrix of a layer (what the paper's `Q^II` holds).
    pub fn amp_l2(&self) -> [[f64; 4]; 4] {
        self.l2.map(|row| row.map(|s| s.amp))
    }

    pub fn amp_l3(&self) -> [[f64; 8]; 8] {
        self.l3.map(|row| row.map(|s| s.amp))
    }
}

/// Parameters of the outlier filter (§2.3).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OutlierParams {
    /// A vector is suspect when its amplitude exceeds `k_median` × the median amplitude of its
    /// layer-2 quadrant plus `floor_px`.
    pub k_median: f64,
    /// Absolute slack, pixels, so that near-zero flow does not make every vector suspect.
    pub floor_px: f64,
    /// A suspect vector is kept when at least this many of its 8 neighbours (valid ones) agree
    /// with its amplitude within `coherence` (relative): a real near object covers several
    /// adjacent blocks, a mismatch is isolated.
    pub min_support: usize,
    pub coherence: f64,
}

impl Default for OutlierParams {
    fn default() -> Self {
        Self { k_median: 3.0, floor_px: 1.0, min_support: 2, coherence: 0.5 }
    }
}

/// §2.3, outlier removal with dynamic per-quadrant thresholds. The paper defers the filter to
/// another paper; this design keeps its stated idea, thresholds generated from the average
/// amplitude of each examined quadrant, and makes it robust:
///
/// 1. the threshold of each layer-2 quadrant is `k_median · median(|f|) + floor_px` over its
///    valid vectors (the median, not the mean, so the outliers cannot raise their own bar);
/// 2. a vector above its quadrant's threshold is an outlier unless it has spatial support:
///    `min_support` or more valid 8-neighbours whose amplitude is within `coherence · |f|` of
///    its own. Isolated mismatches go; a near obstacle covering a few blocks stays.
///
/// Writes `inlier[i] = valid[i] && !outlier` and returns the number of outliers removed.
/// `scratch` is a reusable buffer.
pub fn reject_outliers(
    grid: Grid,
    u: &[f64],
    v: &[f64],
    valid: &[bool],
    params: &OutlierParams,
    inlier: &mut [bool],
    scratch: &mut Vec<f64>,
) -> usize {
    let amp = |i: usize| u[i].hypot(v[i]);
    let (qh, qw) = (grid.rows / 4, grid.cols / 4);
    let mut thresholds = [[f64::INFINITY; 4]; 4];
    for (qr, row) in thresholds.iter_mut().enumerate() {
        for (qc, t) in row.iter_mut().enumerate() {
            scratch.clear();
            for r in qr * qh..(qr + 1) * qh {
                for c in qc * qw..(qc + 1) * qw {
                    let i = r * grid.cols + c;
                    if valid[i] {
                        scratch.push(amp(i));
                    }
                }
            }
            if let Some(m) = median(scratch) {
                *t = params.k_median * m + params.floor_px;
            }
        }
    }
    let mut removed = 0;
    for r in 0..grid.rows {
        for c in 0..grid.cols {
            let i = r * grid.cols + c;
            inlier[i] = valid[i];
            if !valid[i] {
                continue;
            }
            let a = amp(i);
            let [qr, qc] = grid.l2_of(r, c);
            if a <= thresholds[qr][qc] {
                continue;
            }
            let mut support = 0;
            for dr in -1i64..=1 {
                for dc in -1i64..=1 {
                    let (nr, nc) = (r as i64 + dr, c as i64 + dc);
                    if (dr, dc) == (0, 0) || nr < 0 || nc < 0 || nr >= grid.rows as i64 || nc >= grid.cols as i64 {
                        continue;
                    }
                    let j = nr as usize * grid.cols + nc as usize;
                    if valid[j] && (amp(j) - a).abs() <= params.coherence * a {
                        support += 1;
                    }
                }
            }
            if support < params.min_support {
                inlier[i] = false;
                removed += 1;
            }
        }
    }
    removed
}

/// Median of a non-empty slice (reorders it); `None` when empty.
pub(crate) fn median(xs: &mut [f64]) -> Option<f64> {
    if xs.is_empty() {
        return None;
    }
    let n = xs.len();
    let (_, hi, _) = xs.select_nth_unstable_by(n / 2, f64::total_cmp);
    let hi = *hi;
    if n % 2 == 1 {
        return Some(hi);
    }
    let lo = xs[..n / 2].iter().copied().fold(f64::NEG_INFINITY, f64::max);
    Some(0.5 * (lo + hi))
}

/// Where the zoom-in of §3.1 / Fig. 6 ended: the position at each layer, in spatial layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Zoom {
    /// Layer-1 quadrant `[row, col]` in `Q^I`.
    pub l1: [usize; 2],
    /// Layer-2 cell in `Q^II`.
    pub l2: [usize; 2],
    /// Layer-3 cell in `Q^III` (the paper's position of the obstacle in the 8×8 matrix).
    pub l3: [usize; 2],
}

/// §3.1, Fig. 6: the obstacle zoom-in. Picks the layer-1 quadrant with the biggest average
/// amplitude, then the biggest of its four layer-2 quadrants, then the biggest of that one's four
/// layer-3 quadrants. Empty quadrants never win; ties go to the first in the paper's order
/// (1 = top-left … 4 = bottom-right). `None` when no quadrant holds a vector.
pub fn zoom_in(q: &Quadrants) -> Option<Zoom> {
    let best = |cells: [(usize, usize, CellStats); 4]| {
        cells
            .into_iter()
            .filter(|(_, _, s)| !s.is_empty())
            .fold(None, |acc: Option<(usize, usize, f64)>, (r, c, s)| match acc {
                Some((_, _, a)) if a >= s.amp => acc,
                _ => Some((r, c, s.amp)),
            })
            .map(|(r, c, _)| [r, c])
    };
    let children = |m: &dyn Fn(usize, usize) -> CellStats, [pr, pc]: [usize; 2]| {
        [
            (2 * pr, 2 * pc, m(2 * pr, 2 * pc)),
            (2 * pr, 2 * pc + 1, m(2 * pr, 2 * pc + 1)),
            (2 * pr + 1, 2 * pc, m(2 * pr + 1, 2 * pc)),
            (2 * pr + 1, 2 * pc + 1, m(2 * pr + 1, 2 * pc + 1)),
        ]
    };
    let l1 = best([(0, 0, q.l1[0][0]), (0, 1, q.l1[0][1]), (1, 0, q.l1[1][0]), (1, 1, q.l1[1][1])])?;
    let l2 = best(children(&|r, c| q.l2[r][c], l1))?;
    let l3 = best(children(&|r, c| q.l3[r][c], l2))?;
    Some(Zoom { l1, l2, l3 })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(grid: Grid, f: impl Fn(usize, usize) -> (f64, f64)) -> (Vec<f64>, Vec<f64>) {
        let mut u = vec![0.0; grid.len()];
        let mut v = vec![0.0; grid.len()];
        for r in 0..grid.rows {
            for c in 0..grid.cols {
                (u[r * grid.cols + c], v[r * grid.cols + c]) = f(r, c);
            }
        }
        (u, v)
    }

    #[test]
    fn grid_sides_must_be_multiples_of_eight() {
        assert!(Grid::new(16, 16).is_some());
        assert!(Grid::new(8, 24).is_some());
        assert!(Grid::new(12, 16).is_none());
        assert!(Grid::new(0, 16).is_none());
    }

    #[test]
    fn paper_names_follow_eq_1() {
        assert_eq!(paper_l2(0, 0), (1, 1));
        assert_eq!(paper_l2(0, 2), (2, 1));
        assert_eq!(paper_l2(1, 1), (1, 4));
        assert_eq!(paper_l2(2, 1), (3, 2));
        assert_eq!(paper_l2(3, 3), (4, 4));
        assert_eq!(paper_l3(0, 7), (2, 2, 2));
        assert_eq!(paper_l3(1, 6), (2, 2, 3));
        assert_eq!(paper_l3(6, 0), (3, 3, 1));
        assert_eq!(paper_l3(7, 7), (4, 4, 4));
        assert_eq!(paper_l3(6, 4), (4, 3, 1));
    }

    #[test]
    fn averages_by_hand_on_16x16() {
        // u = column index, v = -row index: a layer-3 cell (2×2 vectors) at [R, C] averages
        // |u| = 2C + 0.5 and |v| = 2R + 0.5.
        let g = Grid::new(16, 16).unwrap();
        let (u, v) = field(g, |r, c| (c as f64, -(r as f64)));
        let all = vec![true; g.len()];
        let q = Quadrants::compute(g, &u, &v, &all);
        assert_eq!(q.l3[3][5].u, 10.5);
        assert_eq!(q.l3[3][5].v, 6.5);
        assert_eq!(q.l3[3][5].n, 4);
        // amplitude: mean of hypot over (10,6),(11,6),(10,7),(11,7)
        let a =
            [(10.0f64, 6.0f64), (11.0, 6.0), (10.0, 7.0), (11.0, 7.0)].iter().map(|(x, y)| x.hypot(*y)).sum::<f64>()
                / 4.0;
        assert!((q.l3[3][5].amp - a).abs() < 1e-12);
        // layer-2 [1][2] = columns 8..12, rows 4..8: |u| = 9.5, |v| = 5.5, 16 vectors.
        assert_eq!((q.l2[1][2].u, q.l2[1][2].v, q.l2[1][2].n), (9.5, 5.5, 16));
        // layer-1 [1][0] = rows 8..16, columns 0..8.
        assert_eq!((q.l1[1][0].u, q.l1[1][0].v, q.l1[1][0].n), (3.5, 11.5, 64));
    }

    #[test]
    fn invalid_vectors_are_excluded_and_other_grids_work() {
        for (rows, cols) in [(8, 8), (24, 24), (8, 16)] {
            let g = Grid::new(rows, cols).unwrap();
            let (u, v) = field(g, |_, c| if c % 2 == 0 { (2.0, 1.0) } else { (100.0, 100.0) });
            let mask: Vec<bool> = (0..g.len()).map(|i| (i % cols) % 2 == 0).collect();
            let q = Quadrants::compute(g, &u, &v, &mask);
            for r in 0..8 {
                for c in 0..8 {
                    let s = q.l3[r][c];
                    if cols / 8 == 1 && c % 2 == 1 {
                        assert!(s.is_empty(), "{rows}x{cols} [{r}][{c}]");
                    } else {
                        assert_eq!((s.u, s.v), (2.0, 1.0), "{rows}x{cols} [{r}][{c}]");
                    }
                }
            }
            assert_eq!(q.l1[0][0].n as usize, rows * cols / 8);
        }
    }

    #[test]
    fn an_isolated_spike_is_removed_a_coherent_patch_is_kept() {
        let g = Grid::new(16, 16).unwrap();
        // background 1 px; an isolated mismatch of 15 px at (2, 2); a 2×2 near object of 8 px at (10..12, 10..12).
        let (u, v) = field(g, |r, c| match (r, c) {
            (2, 2) => (15.0, 0.0),
            (10..=11, 10..=11) => (8.0, 0.0),
            _ => (1.0, 0.0),
        });
        let valid = vec![true; g.len()];
        let mut inlier = vec![false; g.len()];
        let removed = reject_outliers(g, &u, &v, &valid, &OutlierParams::default(), &mut inlier, &mut Vec::new());
        assert_eq!(removed, 1);
        assert!(!inlier[2 * 16 + 2]);
        assert!(inlier[10 * 16 + 10] && inlier[11 * 16 + 11]);
        // a vector that was invalid stays out, and is not counted as removed
        let mut valid = valid;
        valid[0] = false;
        let removed = reject_outliers(g, &u, &v, &valid, &OutlierParams::default(), &mut inlier, &mut Vec::new());
        assert_eq!(removed, 1);
        assert!(!inlier[0]);
    }

    #[test]
    fn thresholds_are_per_quadrant() {
        // Quadrant [0][0] moves at 10 px, the rest at 1 px: 10 px is normal there, so a lone
        // 20 px vector inside it survives (20 < 3·10 + 1) while a lone 20 px vector elsewhere goes.
        let g = Grid::new(16, 16).unwrap();
        let (u, v) = field(g, |r, c| match (r, c) {
            (1, 1) | (9, 9) => (20.0, 0.0),
            (0..4, 0..4) => (10.0, 0.0),
            _ => (1.0, 0.0),
        });
        let valid = vec![true; g.len()];
        let mut inlier = vec![false; g.len()];
        reject_outliers(g, &u, &v, &valid, &OutlierParams::default(), &mut inlier, &mut Vec::new());
        assert!(inlier[16 + 1]);
        assert!(!inlier[9 * 16 + 9]);
    }

    #[test]
    fn median_of_even_and_odd() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(&mut []), None);
    }

    #[test]
    fn zoom_in_follows_fig_6() {
        // The biggest layer-1 quadrant is Q3 even though the single biggest layer-3 cell lies in
        // Q2: the zoom-in descends layer by layer, as in Fig. 6 (Q3 → Q34 → Q34k).
        let mut q = Quadrants::default();
        let cell = |amp| CellStats { amp, u: amp, v: 0.0, n: 4 };
        for r in 0..8 {
            for c in 0..8 {
                q.l3[r][c] = cell(1.0);
            }
        }
        q.l3[0][7] = cell(9.0); // in Q2
        for r in 4..8 {
            for c in 0..4 {
                q.l3[r][c] = cell(3.0); // Q3 is big everywhere
            }
        }
        q.l3[7][3] = cell(5.0); // Q344 is the peak of Q34
        // recompute the upper layers from l3 with the merge rule
        let g = Grid::new(8, 8).unwrap();
        let mut u = vec![0.0; 64];
        for r in 0..8 {
            for c in 0..8 {
                u[r * 8 + c] = q.l3[r][c].amp;
            }
        }
        let q = Quadrants::compute(g, &u, &vec![0.0; 64], &[true; 64]);
        let z = zoom_in(&q).unwrap();
        assert_eq!(z, Zoom { l1: [1, 0], l2: [3, 1], l3: [7, 3] });
        assert_eq!(paper_l3(7, 3), (3, 4, 4));
        assert_eq!(zoom_in(&Quadrants::default()), None);
    }
}
