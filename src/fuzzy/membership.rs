//! Membership functions of linguistic terms: triangular, trapezoidal, Gaussian and sigmoid.
//!
//! The triangular and trapezoidal shapes follow scikit-fuzzy's `trimf`/`trapmf` exactly,
//! including shoulders: `tri(a, a, c)` is 1 at `a` and falls to 0 at `c`, `tri(a, c, c)` rises
//! from `a` to 1 at `c`. Outside `[a, c]` (`[a, d]`) the degree is 0. Both are piecewise linear,
//! which lets the centroid of a clipped aggregate be integrated exactly (see `centroid`).

/// The shape of one linguistic term's membership function `mu(x)` in `[0, 1]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Membership {
    /// `tri = [a, b, c]`: 0 at `a`, 1 at `b`, 0 at `c` (`a ≤ b ≤ c`, `a < c`); `a == b` or
    /// `b == c` gives a shoulder (1 at that edge).
    Triangle { a: f64, b: f64, c: f64 },
    /// `trap = [a, b, c, d]`: 0 at `a`, 1 on `[b, c]`, 0 at `d` (`a ≤ b ≤ c ≤ d`, `a < d`).
    Trapezoid { a: f64, b: f64, c: f64, d: f64 },
    /// `gauss = [mean, sigma]`: `exp(-(x - mean)² / (2 sigma²))`, `sigma > 0`.
    Gaussian { mean: f64, sigma: f64 },
    /// `sigmoid = [center, slope]`: `1 / (1 + exp(-slope (x - center)))`; a positive slope
    /// opens to the right, a negative one to the left. `slope != 0`.
    Sigmoid { center: f64, slope: f64 },
}

impl Membership {
    /// Degree of membership of `x`, in `[0, 1]`.
    #[inline]
    pub fn degree(&self, x: f64) -> f64 {
        match *self {
            Membership::Triangle { a, b, c } => {
                if x < a || x > c {
                    0.0
                } else if x <= b {
                    if b == a { 1.0 } else { (x - a) / (b - a) }
                } else if c == b {
                    1.0
                } else {
                    (c - x) / (c - b)
                }
            }
            Membership::Trapezoid { a, b, c, d } => {
                if x < a || x > d {
                    0.0
                } else if x < b {
                    (x - a) / (b - a)
                } else if x <= c {
                    1.0
                } else {
                    (d - x) / (d - c)
                }
            }
            Membership::Gaussian { mean, sigma } => {
                let t = x - mean;
                (-(t * t) / (2.0 * sigma * sigma)).exp()
            }
            Membership::Sigmoid { center, slope } => 1.0 / (1.0 + (-slope * (x - center)).exp()),
        }
    }

    /// True for the piecewise-linear shapes (triangle, trapezoid), whose clipped aggregate
    /// has an exact centroid.
    pub fn is_piecewise_linear(&self) -> bool {
        matches!(self, Membership::Triangle { .. } | Membership::Trapezoid { .. })
    }

    /// The kinks of a piecewise-linear shape and the points where it meets the cut level
    /// `cut` (on its rising and falling edges); passed to `push`. Nothing for smooth shapes.
    pub(crate) fn knots(&self, cut: f64, mut push: impl FnMut(f64)) {
        match *self {
            Membership::Triangle { a, b, c } => {
                push(a);
                push(b);
                push(c);
                push(a + cut * (b - a));
                push(c - cut * (c - b));
            }
            Membership::Trapezoid { a, b, c, d } => {
                push(a);
                push(b);
                push(c);
                push(d);
                push(a + cut * (b - a));
                push(d - cut * (d - c));
            }
            Membership::Gaussian { .. } | Membership::Sigmoid { .. } => {}
        }
    }

    /// Values at `t0` and `t1` of the linear piece that holds on the open interval `(t0, t1)`,
    /// which contains no kink. Using the piece (not the function at the end points) keeps the
    /// integral right at a shoulder's jump, e.g. `tri(2, 2, 5)` just left of 2.
    pub(crate) fn piece(&self, t0: f64, t1: f64) -> (f64, f64) {
        let m = 0.5 * (t0 + t1);
        match *self {
            Membership::Triangle { a, b, c } => {
                if m <= a || m >= c {
                    (0.0, 0.0)
                } else if m <= b {
                    ((t0 - a) / (b - a), (t1 - a) / (b - a))
                } else {
                    ((c - t0) / (c - b), (c - t1) / (c - b))
                }
            }
            Membership::Trapezoid { a, b, c, d } => {
                if m <= a || m >= d {
                    (0.0, 0.0)
                } else if m < b {
                    ((t0 - a) / (b - a), (t1 - a) / (b - a))
                } else if m <= c {
                    (1.0, 1.0)
                } else {
                    ((d - t0) / (d - c), (d - t1) / (d - c))
                }
            }
            Membership::Gaussian { .. } | Membership::Sigmoid { .. } => (self.degree(t0), self.degree(t1)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn triangle_rises_peaks_and_falls() {
        let m = Membership::Triangle { a: 20.0, b: 50.0, c: 80.0 };
        for (x, want) in [(0.0, 0.0), (20.0, 0.0), (35.0, 0.5), (50.0, 1.0), (65.0, 0.5), (80.0, 0.0), (90.0, 0.0)] {
            assert!(close(m.degree(x), want), "tri at {x}: {} != {want}", m.degree(x));
        }
    }

    #[test]
    fn triangle_shoulders_are_one_at_the_edge() {
        let left = Membership::Triangle { a: 0.0, b: 0.0, c: 5.0 };
        assert_eq!(left.degree(0.0), 1.0);
        assert!(close(left.degree(2.5), 0.5));
        assert_eq!(left.degree(5.0), 0.0);
        let right = Membership::Triangle { a: 5.0, b: 10.0, c: 10.0 };
        assert_eq!(right.degree(10.0), 1.0);
        assert!(close(right.degree(7.5), 0.5));
        assert_eq!(right.degree(4.9), 0.0);
        // A shoulder inside the universe is 1 only from its edge on, as in scikit-fuzzy.
        let inner = Membership::Triangle { a: 2.0, b: 2.0, c: 4.0 };
        assert_eq!(inner.degree(1.99), 0.0);
        assert_eq!(inner.degree(2.0), 1.0);
    }

    #[test]
    fn trapezoid_has_a_flat_top() {
        let m = Membership::Trapezoid { a: 0.0, b: 2.0, c: 4.0, d: 8.0 };
        for (x, want) in [(-1.0, 0.0), (1.0, 0.5), (2.0, 1.0), (3.0, 1.0), (4.0, 1.0), (6.0, 0.5), (8.0, 0.0)] {
            assert!(close(m.degree(x), want), "trap at {x}");
        }
        let shoulder = Membership::Trapezoid { a: 0.0, b: 0.0, c: 4.0, d: 8.0 };
        assert_eq!(shoulder.degree(0.0), 1.0);
    }

    #[test]
    fn gaussian_is_one_at_the_mean_and_exp_minus_half_at_one_sigma() {
        let m = Membership::Gaussian { mean: 3.0, sigma: 2.0 };
        assert_eq!(m.degree(3.0), 1.0);
        assert!(close(m.degree(5.0), (-0.5f64).exp()));
        assert!(close(m.degree(1.0), (-0.5f64).exp()));
    }

    #[test]
    fn sigmoid_is_half_at_the_center() {
        let m = Membership::Sigmoid { center: 1.0, slope: 4.0 };
        assert!(close(m.degree(1.0), 0.5));
        assert!(m.degree(3.0) > 0.999);
        assert!(m.degree(-1.0) < 0.001);
        let left = Membership::Sigmoid { center: 1.0, slope: -4.0 };
        assert!(left.degree(-1.0) > 0.999);
    }

    #[test]
    fn piece_ignores_the_jump_of_an_inner_shoulder() {
        let m = Membership::Triangle { a: 2.0, b: 2.0, c: 4.0 };
        assert_eq!(m.piece(1.0, 2.0), (0.0, 0.0));
        assert_eq!(m.piece(2.0, 4.0), (1.0, 0.0));
    }
}
