//! Planar and tilt attributes (paper §3.2–3.3, eq. 2–10) on the quadrant matrices.
//!
//! Layout of the plane matrices (spatial, as in [`super::quadrants`]): a vertical plane joins
//! two vertically adjacent quadrants *inside the same parent*, so `vplaneL2` (eq. 4) is 2×4 with
//! `vplane_l2[R][c] = vplane(Q^II[2R][c], Q^II[2R+1][c])`; a horizontal plane joins two
//! horizontally adjacent quadrants inside the same parent, so `hplaneL2` (eq. 5) is 4×2 with
//! `hplane_l2[r][C] = hplane(Q^II[r][2C], Q^II[r][2C+1])`. Layer 3 is the same at 8×8
//! (`vplaneL3` 4×8, `hplaneL3` 8×4, eq. 6–7).
//!
//! Eq. (4) as printed has `vplane(Q31, Q34)` in its second row; `Q31` and `Q34` are diagonal, not
//! vertical neighbours. Every other entry pairs `Q_ij` with `Q_i(j+2)`, so we read it as
//! `vplane(Q32, Q34)`.

use super::quadrants::CellStats;
use serde::{Deserialize, Serialize};

/// What "≈" means in eq. (2)–(3): `a ≈ b` when `|a − b| ≤ max(abs_px, rel · max(|a|, |b|))`.
/// The relative part scales with the flow (speed, distance); the absolute part keeps
/// sub-pixel noise on slow flow from breaking planes apart.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlaneTolerance {
    pub rel: f64,
    pub abs_px: f64,
}

impl Default for PlaneTolerance {
    fn default() -> Self {
        Self { rel: 0.25, abs_px: 0.15 }
    }
}

impl PlaneTolerance {
    pub fn approx_eq(&self, a: f64, b: f64) -> bool {
        (a - b).abs() <= self.abs_px.max(self.rel * a.abs().max(b.abs()))
    }
}

/// Eq. (2): 1 when the U-projected averages of two vertically adjacent quadrants agree (they
/// lie on one vertical plane: on a plane parallel to the image's vertical axis, or on a
/// frontal plane, `u` depends on the column only). 0 otherwise, and 0 when either quadrant is
/// empty (no evidence of a plane).
pub fn vplane(qi: &CellStats, qj: &CellStats, tol: &PlaneTolerance) -> u8 {
    u8::from(!qi.is_empty() && !qj.is_empty() && tol.approx_eq(qi.u, qj.u))
}

/// Eq. (3): 1 when the V-projected averages of two horizontally adjacent quadrants agree (on a
/// horizontal or frontal plane `v` depends on the row only); 0 otherwise or when either is empty.
pub fn hplane(qi: &CellStats, qj: &CellStats, tol: &PlaneTolerance) -> u8 {
    u8::from(!qi.is_empty() && !qj.is_empty() && tol.approx_eq(qi.v, qj.v))
}

/// Parameters of eq. (8).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TiltParams {
    /// `k_Tilt`, the user's multiplier that maps the ratio to the fuzzy range.
    pub k_tilt: f64,
    /// The ratio `μV_i / μV_j` is clamped to `[0, max_ratio]`; a ratio with a (near-)zero
    /// denominator takes `max_ratio` (or 1 when the numerator is also near zero).
    pub max_ratio: f64,
    /// Below this many pixels a mean V-projection counts as zero.
    pub eps_px: f64,
}

impl Default for TiltParams {
    fn default() -> Self {
        Self { k_tilt: 0.25, max_ratio: 4.0, eps_px: 1e-3 }
    }
}

/// Eq. (8): `tilt = k_tilt · μV_i / μV_j`. On a frontal plane `v` depends on the row only, so the
/// ratio is 1; a plane turned about the vertical axis has depth varying with the column, which
/// shows as a ratio away from 1. Division by zero: both near zero → ratio 1 (no evidence of tilt);
/// only the denominator → `max_ratio`. Either quadrant empty → ratio 1 as well.
pub fn tilt(qi: &CellStats, qj: &CellStats, p: &TiltParams) -> f64 {
    let ratio = if qi.is_empty() || qj.is_empty() {
        1.0
    } else if qj.v < p.eps_px {
        if qi.v < p.eps_px { 1.0 } else { p.max_ratio }
    } else {
        (qi.v / qj.v).clamp(0.0, p.max_ratio)
    };
    p.k_tilt * ratio
}

fn vplanes<const N: usize, const H: usize>(q: &[[CellStats; N]; N], tol: &PlaneTolerance) -> [[u8; N]; H] {
    debug_assert_eq!(2 * H, N);
    let mut m = [[0; N]; H];
    for (rr, row) in m.iter_mut().enumerate() {
        for (c, x) in row.iter_mut().enumerate() {
            *x = vplane(&q[2 * rr][c], &q[2 * rr + 1][c], tol);
        }
    }
    m
}

fn hplanes<const N: usize, const H: usize>(q: &[[CellStats; N]; N], tol: &PlaneTolerance) -> [[u8; H]; N] {
    debug_assert_eq!(2 * H, N);
    let mut m = [[0; H]; N];
    for (r, row) in m.iter_mut().enumerate() {
        for (cc, x) in row.iter_mut().enumerate() {
            *x = hplane(&q[r][2 * cc], &q[r][2 * cc + 1], tol);
        }
    }
    m
}

fn tilts<const N: usize>(q: &[[CellStats; N]; N], p: &TiltParams) -> [[f64; 2]; N] {
    let mut m = [[0.0; 2]; N];
    for (r, row) in m.iter_mut().enumerate() {
        row[0] = tilt(&q[r][0], &q[r][1], p);
        row[1] = tilt(&q[r][N - 1], &q[r][N - 2], p);
    }
    m
}

/// Eq. (4): `vplaneL2` (2×4), with the typo of its second row read as `vplane(Q32, Q34)`.
pub fn vplane_l2(q2: &[[CellStats; 4]; 4], tol: &PlaneTolerance) -> [[u8; 4]; 2] {
    vplanes(q2, tol)
}

/// Eq. (5): `hplaneL2` (4×2).
pub fn hplane_l2(q2: &[[CellStats; 4]; 4], tol: &PlaneTolerance) -> [[u8; 2]; 4] {
    hplanes(q2, tol)
}

/// Eq. (6): `vplaneL3` (4×8).
pub fn vplane_l3(q3: &[[CellStats; 8]; 8], tol: &PlaneTolerance) -> [[u8; 8]; 4] {
    vplanes(q3, tol)
}

/// Eq. (7): `hplaneL3` (8×4).
pub fn hplane_l3(q3: &[[CellStats; 8]; 8], tol: &PlaneTolerance) -> [[u8; 4]; 8] {
    hplanes(q3, tol)
}

/// Eq. (9): `tiltL2` (4×2) on the two first and two last columns of `Q^II`: row `r` is
/// `[tilt(Q^II[r][0], Q^II[r][1]), tilt(Q^II[r][3], Q^II[r][2])]`, outer over inner on both sides.
pub fn tilt_l2(q2: &[[CellStats; 4]; 4], p: &TiltParams) -> [[f64; 2]; 4] {
    tilts(q2, p)
}

/// Eq. (10): `tiltL3` (8×2), row `r` = `[tilt(Q^III[r][0], Q^III[r][1]), tilt(Q^III[r][7], Q^III[r][6])]`.
pub fn tilt_l3(q3: &[[CellStats; 8]; 8], p: &TiltParams) -> [[f64; 2]; 8] {
    tilts(q3, p)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cell(u: f64, v: f64) -> CellStats {
        CellStats { amp: u.hypot(v), u, v, n: 4 }
    }

    #[test]
    fn tolerance_is_relative_and_absolute() {
        let t = PlaneTolerance { rel: 0.2, abs_px: 0.15 };
        assert!(t.approx_eq(10.0, 8.0));
        assert!(!t.approx_eq(10.0, 7.9));
        assert!(t.approx_eq(0.1, 0.2), "sub-pixel noise on slow flow is within abs_px");
        assert!(!t.approx_eq(0.1, 0.3));
    }

    #[test]
    fn planes_and_empty_quadrants() {
        let t = PlaneTolerance::default();
        assert_eq!(vplane(&cell(5.0, 1.0), &cell(5.5, 9.0), &t), 1);
        assert_eq!(vplane(&cell(5.0, 1.0), &cell(2.0, 1.0), &t), 0);
        assert_eq!(hplane(&cell(1.0, 3.0), &cell(9.0, 3.1), &t), 1);
        assert_eq!(hplane(&cell(1.0, 3.0), &CellStats::default(), &t), 0);
    }

    #[test]
    fn matrices_by_hand() {
        // Q^II with U = 1 + column and V = 1 + row, except Q32 ([2][1]) whose U is 9 and Q42
        // ([2][3]) whose V is 9.
        let mut q = [[CellStats::default(); 4]; 4];
        for (r, row) in q.iter_mut().enumerate() {
            for (c, x) in row.iter_mut().enumerate() {
                *x = cell(1.0 + c as f64, 1.0 + r as f64);
            }
        }
        q[2][1].u = 9.0;
        q[2][3].v = 9.0;
        let t = PlaneTolerance { rel: 0.01, abs_px: 0.0 };
        // vplane(Q32, Q34) is 0 (the typo'd entry, read as the vertical pair)
        assert_eq!(vplane_l2(&q, &t), [[1, 1, 1, 1], [1, 0, 1, 1]]);
        // hplane(Q41, Q42) is 0: row 2, right pair
        assert_eq!(hplane_l2(&q, &t), [[1, 1], [1, 1], [1, 0], [1, 1]]);
        let p = TiltParams { k_tilt: 0.5, max_ratio: 4.0, eps_px: 1e-3 };
        let tl = tilt_l2(&q, &p);
        assert_eq!(tl[0], [0.5, 0.5]);
        // row 2: right side tilt(Q42, Q41) = 0.5 · 9/3
        assert_eq!(tl[2], [0.5, 0.5 * 3.0]);
    }

    #[test]
    fn layer_3_shapes_by_hand() {
        let mut q = [[CellStats::default(); 8]; 8];
        for (r, row) in q.iter_mut().enumerate() {
            for (c, x) in row.iter_mut().enumerate() {
                *x = cell(1.0, 1.0 + (c as f64 - 3.5).abs() * (r as f64 + 1.0));
            }
        }
        let t = PlaneTolerance { rel: 0.01, abs_px: 0.0 };
        assert_eq!(vplane_l3(&q, &t), [[1; 8]; 4], "U is constant");
        // V differs between the two columns of every pair (|c − 3.5| differs inside each pair)…
        let mut want = [[0; 4]; 8];
        assert_eq!(hplane_l3(&q, &t), want);
        // …until two are made equal: hplane(Q^III[5][4], Q^III[5][5]) is hplaneL3[5][2].
        q[5][5].v = q[5][4].v;
        want[5][2] = 1;
        assert_eq!(hplane_l3(&q, &t), want);
        q[5][5].v = q[5][2].v;
        let p = TiltParams { k_tilt: 1.0, max_ratio: 10.0, eps_px: 1e-3 };
        let tl = tilt_l3(&q, &p);
        for (r, row) in tl.iter().enumerate() {
            let k = r as f64 + 1.0;
            let want = (1.0 + 3.5 * k) / (1.0 + 2.5 * k);
            assert!((row[0] - want).abs() < 1e-12 && (row[1] - want).abs() < 1e-12, "row {r}");
        }
    }

    #[test]
    fn tilt_division_by_zero() {
        let p = TiltParams { k_tilt: 0.5, max_ratio: 4.0, eps_px: 1e-3 };
        assert_eq!(tilt(&cell(1.0, 2.0), &cell(1.0, 0.0), &p), 2.0);
        assert_eq!(tilt(&cell(1.0, 0.0), &cell(1.0, 0.0), &p), 0.5);
        assert_eq!(tilt(&cell(1.0, 2.0), &CellStats::default(), &p), 0.5);
        assert_eq!(tilt(&cell(1.0, 100.0), &cell(1.0, 1.0), &p), 2.0, "clamped");
        assert!(tilt(&cell(1.0, 1.0), &cell(1.0, 2.0), &p) == 0.25);
    }
}
