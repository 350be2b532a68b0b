//! Centroid defuzzification of a Mamdani output: the aggregate
//! `mu(z) = max_k min(cut_k, mu_k(z))` over the output universe, reduced to
//! `∫ z mu(z) dz / ∫ mu(z) dz`.
//!
//! Two methods:
//! - **exact** (triangles and trapezoids only): the aggregate is piecewise linear. Its kinks are
//!   the terms' corners, the points where each term meets its cut level, and the points where
//!   two clipped terms cross; with all of them included every segment is linear and both
//!   integrals are closed-form. Matches a continuous reference to rounding (~1e-12).
//! - **sampled** (any shape): `sum(z_i mu(z_i)) / sum(mu(z_i))` over `n` evenly spaced samples
//!   `z_i` of the universe (numpy's `linspace`), what scikit-fuzzy-style engines compute; the
//!   term degrees at the samples are tabulated at load.

use super::membership::Membership;

/// Reusable buffers for the exact centroid, sized at load so evaluation does not allocate.
#[derive(Clone, Debug, Default)]
pub(crate) struct Scratch {
    knots: Vec<f64>,
    active: Vec<usize>,
    v0: Vec<f64>,
    v1: Vec<f64>,
    sub: Vec<f64>,
    /// The sampled aggregate, one value per sample.
    mu: Vec<f64>,
}

impl Scratch {
    pub(crate) fn new(terms: usize, samples: usize) -> Self {
        Scratch {
            knots: Vec::with_capacity(6 * terms + 2),
            active: Vec::with_capacity(terms),
            v0: Vec::with_capacity(terms),
            v1: Vec::with_capacity(terms),
            sub: Vec::with_capacity(terms * terms / 2 + 2),
            mu: Vec::with_capacity(samples),
        }
    }
}

/// `(∫ mu, ∫ z mu)` of the exact piecewise-linear aggregate of `terms` clipped at `cuts` over
/// `[lo, hi]`. All terms must be piecewise linear.
pub(crate) fn exact_moments(terms: &[Membership], cuts: &[f64], lo: f64, hi: f64, s: &mut Scratch) -> (f64, f64) {
    s.active.clear();
    s.knots.clear();
    s.knots.push(lo);
    s.knots.push(hi);
    for (k, (m, &cut)) in terms.iter().zip(cuts).enumerate() {
        if cut > 0.0 {
            s.active.push(k);
            m.knots(cut, |t| {
                if t > lo && t < hi {
                    s.knots.push(t);
                }
            });
        }
    }
    if s.active.is_empty() {
        return (0.0, 0.0);
    }
    s.knots.sort_unstable_by(f64::total_cmp);
    s.knots.dedup();

    let (mut area, mut moment) = (0.0, 0.0);
    for w in 0..s.knots.len() - 1 {
        let (t0, t1) = (s.knots[w], s.knots[w + 1]);
        // On (t0, t1) every clipped term is linear: min(cut, piece) needs no split because the
        // cut crossings are knots.
        s.v0.clear();
        s.v1.clear();
        for &k in &s.active {
            let (a, b) = terms[k].piece(t0, t1);
            s.v0.push(a.min(cuts[k]));
            s.v1.push(b.min(cuts[k]));
        }
        // Where two lines cross inside the interval, the upper envelope may change line.
        s.sub.clear();
        s.sub.push(t0);
        let n = s.active.len();
        for i in 0..n {
            for j in i + 1..n {
                let d0 = s.v0[i] - s.v0[j];
                let d1 = s.v1[i] - s.v1[j];
                if (d0 < 0.0 && d1 > 0.0) || (d0 > 0.0 && d1 < 0.0) {
                    s.sub.push(t0 + (t1 - t0) * d0 / (d0 - d1));
                }
            }
        }
        s.sub.push(t1);
        if s.sub.len() > 3 {
            s.sub[1..].sort_unstable_by(f64::total_cmp);
        }
        let envelope = |t: f64, v0: &[f64], v1: &[f64]| {
            let f = if t1 > t0 { (t - t0) / (t1 - t0) } else { 0.0 };
            v0.iter().zip(v1).fold(0.0f64, |m, (&a, &b)| m.max(a + (b - a) * f))
        };
        let mut za = s.sub[0];
        let mut ma = envelope(za, &s.v0, &s.v1);
        for q in 1..s.sub.len() {
            let zb = s.sub[q];
            let mb = envelope(zb, &s.v0, &s.v1);
            let h = zb - za;
            area += 0.5 * h * (ma + mb);
            moment += h * (za * (2.0 * ma + mb) + zb * (ma + 2.0 * mb)) / 6.0;
            za = zb;
            ma = mb;
        }
    }
    (area, moment)
}

/// The sample points of a universe, exactly as numpy's `linspace(lo, hi, n)`.
pub(crate) fn linspace(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    let step = (hi - lo) / (n - 1) as f64;
    let mut z: Vec<f64> = (0..n).map(|i| lo + i as f64 * step).collect();
    z[n - 1] = hi;
    z
}

/// `(sum mu_i, sum z_i mu_i)` over the samples `z`, with `table[k * n + i]` the degree of term
/// `k` at `z[i]`. Term by term over contiguous rows, so the inner loops vectorise.
pub(crate) fn sampled_moments(z: &[f64], table: &[f64], cuts: &[f64], s: &mut Scratch) -> (f64, f64) {
    let n = z.len();
    s.mu.clear();
    s.mu.resize(n, 0.0);
    for (k, &cut) in cuts.iter().enumerate() {
        if cut > 0.0 {
            for (m, &t) in s.mu.iter_mut().zip(&table[k * n..(k + 1) * n]) {
                let v = if t < cut { t } else { cut };
                *m = if v > *m { v } else { *m };
            }
        }
    }
    let (mut area, mut moment) = (0.0, 0.0);
    for (&zi, &mu) in z.iter().zip(&s.mu) {
        area += mu;
        moment += zi * mu;
    }
    (area, moment)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tri(a: f64, b: f64, c: f64) -> Membership {
        Membership::Triangle { a, b, c }
    }

    fn exact(terms: &[Membership], cuts: &[f64], lo: f64, hi: f64) -> (f64, f64) {
        let mut s = Scratch::new(terms.len(), 0);
        exact_moments(terms, cuts, lo, hi, &mut s)
    }

    #[test]
    fn a_full_symmetric_triangle_has_its_centroid_at_the_peak() {
        let (a, m) = exact(&[tri(20.0, 50.0, 80.0)], &[1.0], 0.0, 100.0);
        assert!((a - 30.0).abs() < 1e-12);
        assert!((m / a - 50.0).abs() < 1e-12);
    }

    #[test]
    fn a_clipped_left_shoulder_is_a_trapezoid() {
        // tri(0,0,50) clipped at 0.5: 1/2 on [0,25], then falls to 0 at 50.
        let (a, m) = exact(&[tri(0.0, 0.0, 50.0)], &[0.5], 0.0, 100.0);
        assert!((a - (12.5 + 6.25)).abs() < 1e-12);
        // moments: rectangle 0.5*25*12.5 + triangle 6.25 * (25 + 25/3)
        let want = 12.5 * 12.5 + 6.25 * (25.0 + 25.0 / 3.0);
        assert!((m - want).abs() < 1e-9);
    }

    #[test]
    fn crossing_terms_are_integrated_at_their_crossing() {
        // Two full triangles overlapping: the envelope is max, so the crossing at 50 matters.
        let terms = [tri(0.0, 25.0, 75.0), tri(25.0, 75.0, 100.0)];
        let (a, m) = exact(&terms, &[1.0, 1.0], 0.0, 100.0);
        // Dense sampling converges to the exact value.
        let z = linspace(0.0, 100.0, 200_001);
        let table: Vec<f64> = terms.iter().flat_map(|t| z.iter().map(|&x| t.degree(x))).collect();
        let (sa, sm) = sampled_moments(&z, &table, &[1.0, 1.0], &mut Scratch::new(2, z.len()));
        assert!((m / a - sm / sa).abs() < 1e-6, "{} vs {}", m / a, sm / sa);
        let step = z[1] - z[0];
        assert!((a - sa * step).abs() < 1e-3);
    }

    #[test]
    fn nothing_fired_gives_zero_area() {
        assert_eq!(exact(&[tri(0.0, 1.0, 2.0)], &[0.0], 0.0, 2.0), (0.0, 0.0));
    }

    #[test]
    fn linspace_matches_numpy_end_points() {
        let z = linspace(0.0, 100.0, 101);
        assert_eq!((z[0], z[37], z[100]), (0.0, 37.0, 100.0));
    }
}
