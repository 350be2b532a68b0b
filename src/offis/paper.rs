//! The paper's recognition path (`offis.classifier = "paper"`): the inputs of its rough and
//! fine classifiers, read off the structures of §4 (eq. 11–12), the plane matrices (eq. 4–7)
//! and the tilts (eq. 8–10), and the obstacle located by the zoom of Fig. 6.
//!
//! The paper shows its rule tables only as figures (Fig. 12–13, not in the text), so the
//! inputs are reconstructed from what §4 says the structures show: the rough structure marks
//! the closest area of each layer-1 quadrant, and the area reaches the inner columns only when a
//! plane joins them to the outer ones (one surface across the view: a wall); eq. (11) (Fig. 7,
//! a door) and eq. (12) (Fig. 8, a corridor) mark the outer columns only. What tells a door,
//! a corner and a corridor apart there is how the depth changes across the view, which the
//! tilts measure: `μV` is `|y − y_e| · t_z / Z` for a block at height `y` in the image, so the
//! ratio of two cells of one row is the inverse ratio of their depths, whatever the column
//! (docs/offis.md, *The paper's classifier*).
//!
//! All of it is pure arithmetic on the attribute matrices; nothing allocates.

use super::quadrants::{CellStats, Quadrants};
use serde::{Deserialize, Serialize};

/// The inputs the paper's rule bases may read.
pub const FEATURES: [&str; 6] = ["rough_inner", "near_m", "fine_inner", "tilt_left", "tilt_right", "tilt_centre"];

/// `near_m` when nothing marked is located (and its cap), m.
pub const FAR_M: f64 = 8.0;

/// Rows whose outer cell's `μV` is below this (pixels) are too close to the horizon for a
/// depth ratio: their `v` is mostly matching noise.
pub const MIN_V_PX: f64 = 0.3;

/// The paper classifier's inputs for one frame pair.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PaperFeatures {
    /// Share of the rough structure's inner cells (columns 1–2 of the 4×4 mask, those with
    /// vectors) that are marked: 1 when one plane joins the inner columns to the outer ones (a
    /// wall), 0 for eq. (11)'s pattern.
    pub rough_inner: f64,
    /// Median horizontal range of the blocks in the rough structure's marked cells, from flow and
    /// odometry (§2.2), m; [`FAR_M`] when none is located.
    pub near_m: f64,
    /// Share of the fine structure's cells in the centre columns (2–5 of the 8×8 mask) that are
    /// marked, of those with vectors under a marked rough cell; 1 when there are none. A door's
    /// opening inside a marked rough cell leaves its cells unmarked.
    pub fine_inner: f64,
    /// Eq. (10), left and right: the tilt of the outermost pair of layer-3 columns,
    /// `μV(outer) / μV(inner)` (the tilt over `k_tilt`), median over the rows whose outer cell
    /// the fine structure marks; 1 without such a row. 1 on a plane facing the camera, > 1 on a
    /// plane that recedes towards the centre (a corridor wall, a concave corner), < 1 on one that
    /// comes nearer towards the centre (a convex corner; an oblique wall gives > 1 on one side
    /// and < 1 on the other).
    pub tilt_left: f64,
    pub tilt_right: f64,
    /// Eq. (8) between the centre and the outer layer-3 columns of each row,
    /// `μV(columns 3–4) / μV(columns 0 and 7)`, median over the rows whose outer `μV` is at least
    /// [`MIN_V_PX`]; 1 without such a row. The outer depth over the centre depth: ≪ 1 in a
    /// corridor (the far end), < 1 through a door's opening, near 1 at a concave corner or a
    /// wall, > 1 at a convex corner.
    pub tilt_centre: f64,
}

impl Default for PaperFeatures {
    fn default() -> Self {
        Self { rough_inner: 0.0, near_m: FAR_M, fine_inner: 1.0, tilt_left: 1.0, tilt_right: 1.0, tilt_centre: 1.0 }
    }
}

impl PaperFeatures {
    /// The values in [`FEATURES`] order.
    pub fn values(&self) -> [f64; 6] {
        [self.rough_inner, self.near_m, self.fine_inner, self.tilt_left, self.tilt_right, self.tilt_centre]
    }

    /// Computes the inputs from the quadrants, the structures, the tilts (`tilt_l3` with its
    /// `k_tilt`) and `range_l2` (the median range of each layer-2 cell's located blocks).
    pub fn compute(
        q: &Quadrants,
        rough: &[[u8; 4]; 4],
        fine: &[[u8; 8]; 8],
        tilt_l3: &[[f64; 2]; 8],
        k_tilt: f64,
        range_l2: &[[Option<f64>; 4]; 4],
    ) -> Self {
        let share = |hits: usize, n: usize, empty: f64| if n == 0 { empty } else { hits as f64 / n as f64 };
        let (mut hits, mut n) = (0, 0);
        for (cells, marks) in q.l2.iter().zip(rough) {
            for (cell, &mark) in cells[1..3].iter().zip(&marks[1..3]) {
                if !cell.is_empty() {
                    n += 1;
                    hits += usize::from(mark == 1);
                }
            }
        }
        let rough_inner = share(hits, n, 0.0);
        let mut ranges = [0.0; 16];
        let mut k = 0;
        for r in 0..4 {
            for c in 0..4 {
                if let (1, Some(d)) = (rough[r][c], range_l2[r][c]) {
                    ranges[k] = d;
                    k += 1;
                }
            }
        }
        let near_m = median(&mut ranges[..k]).map_or(FAR_M, |d| d.min(FAR_M));
        let (mut hits, mut n) = (0, 0);
        for r in 0..8 {
            for c in 2..6 {
                if rough[r / 2][c / 2] == 1 && !q.l3[r][c].is_empty() {
                    n += 1;
                    hits += usize::from(fine[r][c] == 1);
                }
            }
        }
        let fine_inner = share(hits, n, 1.0);
        let side = |s: usize| {
            let (outer, inner) = if s == 0 { (0, 1) } else { (7, 6) };
            let mut v = [0.0; 8];
            let mut k = 0;
            for r in 0..8 {
                if fine[r][outer] == 1 && !q.l3[r][outer].is_empty() && !q.l3[r][inner].is_empty() {
                    v[k] = tilt_l3[r][s] / k_tilt;
                    k += 1;
                }
            }
            median(&mut v[..k]).unwrap_or(1.0)
        };
        let mut v = [0.0; 8];
        let mut k = 0;
        for row in &q.l3 {
            let outer = mean_v(&[row[0], row[7]]);
            let centre = mean_v(&[row[3], row[4]]);
            if let (Some(o), Some(c)) = (outer, centre)
                && o >= MIN_V_PX
            {
                v[k] = c / o;
                k += 1;
            }
        }
        let tilt_centre = median(&mut v[..k]).unwrap_or(1.0);
        Self { rough_inner, near_m, fine_inner, tilt_left: side(0), tilt_right: side(1), tilt_centre }
    }
}

/// The vector-weighted mean `μV` of the cells with vectors; `None` when all are empty.
fn mean_v(cells: &[CellStats]) -> Option<f64> {
    let n: u32 = cells.iter().map(|c| c.n).sum();
    (n > 0).then(|| cells.iter().map(|c| c.v * c.n as f64).sum::<f64>() / n as f64)
}

/// Median of `v` (upper middle for an even count), reordering it; `None` when empty.
fn median(v: &mut [f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    Some(v[v.len() / 2])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cell(v: f64) -> CellStats {
        CellStats { amp: v, u: v, v, n: 4 }
    }

    #[test]
    fn features_by_hand() {
        // every row: outer V 2, next 1.6 (tilt 1.25), centre 0.5 (a far centre)
        let mut q = Quadrants::default();
        for row in q.l3.iter_mut() {
            *row = [2.0, 1.6, 1.0, 0.5, 0.5, 1.0, 1.6, 2.0].map(cell);
        }
        q.l2 = [[cell(1.0); 4]; 4];
        let rough = [[1, 0, 0, 1]; 4];
        let fine = [[1, 0, 0, 0, 0, 0, 0, 1]; 8];
        let tilt = [[0.25 * 1.25; 2]; 8];
        let mut range = [[Some(6.0); 4]; 4];
        for row in range.iter_mut() {
            row[0] = Some(2.0);
            row[3] = Some(2.5);
        }
        let f = PaperFeatures::compute(&q, &rough, &fine, &tilt, 0.25, &range);
        assert_eq!(f.rough_inner, 0.0);
        assert_eq!(f.near_m, 2.5, "the marked cells' median range");
        assert_eq!(f.fine_inner, 1.0, "no marked rough cell in the centre");
        assert!((f.tilt_left - 1.25).abs() < 1e-12 && (f.tilt_right - 1.25).abs() < 1e-12);
        assert_eq!(f.tilt_centre, 0.25);
        // a wall: everything marked, a hole in the fine structure's centre
        let mut fine = [[1; 8]; 8];
        fine[0][3] = 0;
        fine[0][4] = 0;
        let f = PaperFeatures::compute(&q, &[[1; 4]; 4], &fine, &tilt, 0.25, &range);
        assert_eq!((f.rough_inner, f.fine_inner), (1.0, 30.0 / 32.0));
        // nothing located, no vectors: the defaults
        let f = PaperFeatures::compute(&Quadrants::default(), &rough, &fine, &tilt, 0.25, &[[None; 4]; 4]);
        assert_eq!(f, PaperFeatures::default());
    }
}
