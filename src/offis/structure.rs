//! Rough (4×4) and fine (8×8) structure masks (paper §4.1–4.2, eq. 11–12).
//!
//! Both masks mark "the closest area" of each parent quadrant: the child with the biggest average
//! amplitude and every child joined to it by planes inside the same parent: vertical neighbours
//! whose `vplane` is 1, horizontal neighbours whose `hplane` is 1 (the paper's `Q_i(j+2)` and
//! `Q_i(j+1)` for the top-left child, mirrored for the others), repeated until the area stops
//! growing. The repetition only matters when a plane link reaches the diagonal child, as on the
//! obstacle of eq. (12), whose 2×2 cells are all marked.
//!
//! The rough mask runs this in every layer-1 quadrant (over `Q^II`). The fine mask runs it in the
//! layer-2 quadrants *that the rough mask selected* (over `Q^III`): the segmentation zooms into
//! the closest areas, layer by layer. That reading is what reproduces eq. (12), whose middle
//! columns are all zero although every layer-2 quadrant has a biggest child.

use super::quadrants::CellStats;

/// Marks the closest area of the parent `[pr, pc]` in `mask` (children at `2pr..2pr+2`,
/// `2pc..2pc+2`). `vp` / `hp` are the plane matrices of that layer (eq. 4–7 layout).
fn closest_area<const N: usize, const H: usize>(
    q: &[[CellStats; N]; N],
    vp: &[[u8; N]; H],
    hp: &[[u8; H]; N],
    [pr, pc]: [usize; 2],
    mask: &mut [[u8; N]; N],
) {
    let mut best: Option<(usize, usize, f64)> = None;
    for (a, b) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
        let s = q[2 * pr + a][2 * pc + b];
        if !s.is_empty() && best.is_none_or(|(_, _, m)| s.amp > m) {
            best = Some((a, b, s.amp));
        }
    }
    let Some((a, b, _)) = best else { return };
    let mut area = [[false; 2]; 2];
    area[a][b] = true;
    loop {
        let mut grew = false;
        for (a, b) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
            if !area[a][b] {
                continue;
            }
            let (r, c) = (2 * pr + a, 2 * pc + b);
            if vp[pr][c] == 1 && !area[1 - a][b] {
                area[1 - a][b] = true;
                grew = true;
            }
            if hp[r][pc] == 1 && !area[a][1 - b] {
                area[a][1 - b] = true;
                grew = true;
            }
        }
        if !grew {
            break;
        }
    }
    for (a, row) in area.iter().enumerate() {
        for (b, &m) in row.iter().enumerate() {
            if m {
                mask[2 * pr + a][2 * pc + b] = 1;
            }
        }
    }
}

/// §4.1, eq. (11): the rough structure on `Q^II`, `vplaneL2`, `hplaneL2`. In each layer-1
/// quadrant: the layer-2 child with the biggest average, extended along the planes it forms.
pub fn rough_mask(q2: &[[CellStats; 4]; 4], vp: &[[u8; 4]; 2], hp: &[[u8; 2]; 4]) -> [[u8; 4]; 4] {
    let mut mask = [[0; 4]; 4];
    for pr in 0..2 {
        for pc in 0..2 {
            closest_area(q2, vp, hp, [pr, pc], &mut mask);
        }
    }
    mask
}

/// §4.2, eq. (12): the fine structure on `Q^III`, `vplaneL3`, `hplaneL3`, inside each layer-2
/// quadrant that `rough` marks (see the module doc).
pub fn fine_mask(q3: &[[CellStats; 8]; 8], vp: &[[u8; 8]; 4], hp: &[[u8; 4]; 8], rough: &[[u8; 4]; 4]) -> [[u8; 8]; 8] {
    let mut mask = [[0; 8]; 8];
    for (pr, row) in rough.iter().enumerate() {
        for (pc, &m) in row.iter().enumerate() {
            if m == 1 {
                closest_area(q3, vp, hp, [pr, pc], &mut mask);
            }
        }
    }
    mask
}

#[cfg(test)]
mod tests {
    use super::super::planes::{PlaneTolerance, hplane_l2, vplane_l2};
    use super::*;

    #[test]
    fn rough_by_hand() {
        // Q1: Q11 biggest, same U as Q13, V unlike Q12 → {Q11, Q13}.
        // Q2: Q24 biggest, planes with both neighbours → {Q24, Q22, Q23}.
        // Q3: Q32 biggest, no planes → {Q32}.
        // Q4: Q41 biggest, hplane to Q42, whose vplane reaches Q44 → {Q41, Q42, Q44}.
        let c = |amp: f64, u: f64, v: f64| CellStats { amp, u, v, n: 4 };
        let q = [
            [c(9.0, 5.0, 1.0), c(2.0, 1.0, 5.0), c(1.0, 1.0, 1.0), c(3.0, 2.0, 7.0)],
            [c(3.0, 5.0, 9.0), c(1.0, 1.0, 1.0), c(3.0, 3.0, 2.0), c(8.0, 2.0, 2.0)],
            [c(1.0, 1.0, 3.0), c(4.0, 1.0, 1.0), c(5.0, 1.0, 1.0), c(1.0, 4.0, 1.0)],
            [c(1.0, 9.0, 9.0), c(2.0, 9.0, 9.0), c(1.0, 7.0, 3.0), c(1.0, 4.0, 8.0)],
        ];
        let t = PlaneTolerance { rel: 0.05, abs_px: 0.0 };
        let (vp, hp) = (vplane_l2(&q, &t), hplane_l2(&q, &t));
        assert_eq!(rough_mask(&q, &vp, &hp), [[1, 0, 0, 1], [1, 0, 1, 1], [0, 1, 1, 1], [0, 0, 0, 1]]);
    }
}
