//! Confidence intervals for the mission counts of a `--seeds` run: how many seeds a rate needs
//! before it says anything (with 0 runs with contact in 20, the per-run rate may still be 17 %).

/// The exact (Clopper–Pearson) two-sided interval of a binomial proportion: `k` successes in `n`
/// trials at the given `confidence` (0.95 for 95 %). `(0, 1)` when `n` is 0.
pub fn clopper_pearson(k: u64, n: u64, confidence: f64) -> (f64, f64) {
    if n == 0 {
        return (0.0, 1.0);
    }
    let k = k.min(n);
    let tail = 0.5 * (1.0 - confidence);
    // the lower bound: P(X ≥ k | p) = tail; the upper: P(X ≤ k | p) = tail (both monotone in p)
    let lower = match k {
        0 => 0.0,
        _ => bisect(|p| 1.0 - binomial_cdf(k - 1, n, p) - tail),
    };
    let upper = match k == n {
        true => 1.0,
        false => bisect(|p| tail - binomial_cdf(k, n, p)),
    };
    (lower, upper)
}

/// The root in (0, 1) of `f`, increasing in `p`.
fn bisect(f: impl Fn(f64) -> f64) -> f64 {
    let (mut lo, mut hi) = (0.0, 1.0);
    for _ in 0..64 {
        let mid = 0.5 * (lo + hi);
        if f(mid) < 0.0 { lo = mid } else { hi = mid }
    }
    0.5 * (lo + hi)
}

/// P(X ≤ k) for X ~ Binomial(n, p), summed in log space (no underflow for hundreds of trials).
fn binomial_cdf(k: u64, n: u64, p: f64) -> f64 {
    if p <= 0.0 {
        return 1.0;
    }
    if p >= 1.0 {
        return if k >= n { 1.0 } else { 0.0 };
    }
    let (lp, lq) = (p.ln(), (-p).ln_1p());
    // ln of the term for i, from ln C(n, 0) = 0 by C(n, i+1) = C(n, i) (n − i) / (i + 1)
    let mut ln_c = 0.0;
    let mut terms = Vec::with_capacity(k as usize + 1);
    for i in 0..=k.min(n) {
        terms.push(ln_c + i as f64 * lp + (n - i) as f64 * lq);
        ln_c += ((n - i) as f64).ln() - ((i + 1) as f64).ln();
    }
    let max = terms.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    (max + terms.iter().map(|t| (t - max).exp()).sum::<f64>().ln()).exp().min(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: (f64, f64), b: (f64, f64)) -> bool {
        (a.0 - b.0).abs() < 2e-6 && (a.1 - b.1).abs() < 2e-6
    }

    #[test]
    fn matches_published_clopper_pearson_intervals() {
        // reference values: SciPy's beta.ppf(0.025, k, n − k + 1) and beta.ppf(0.975, k + 1, n − k)
        let cases = [
            ((0, 20), (0.0, 0.168433)),
            ((1, 20), (0.001265, 0.248733)),
            ((6, 60), (0.037591, 0.205058)),
            ((20, 20), (0.831567, 1.0)),
            ((56, 60), (0.838013, 0.981538)),
        ];
        for ((k, n), want) in cases {
            let got = clopper_pearson(k, n, 0.95);
            assert!(close(got, want), "{k} of {n}: {got:?}, want {want:?}");
        }
    }

    #[test]
    fn the_binomial_sums_to_one_and_survives_many_trials() {
        assert!((binomial_cdf(500, 500, 0.3) - 1.0).abs() < 1e-12);
        // mean 150, sd ≈ 10.2: about half the mass at or below the mean
        let half = binomial_cdf(150, 500, 0.3);
        assert!(half > 0.5 && half < 0.55, "{half}");
        assert_eq!(clopper_pearson(3, 0, 0.95), (0.0, 1.0));
    }
}
