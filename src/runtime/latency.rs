//! Frame-to-set-point latency statistics in constant memory.
//!
//! The latency of one frame is the time from its capture stamp (`Frame::t_ns`, `CLOCK_MONOTONIC`)
//! to the moment `MotorBase::set_velocity` returned with the set-point computed from it. A run of
//! hours at 30 fps must not grow memory (DESIGN.md), so samples go into a fixed histogram of
//! 20 µs bins up to 200 ms (one overflow bin above); the maximum is kept exactly. Quantiles are
//! nearest-rank and reported as the upper edge of their bin (never more than the maximum), so
//! they err high by at most 20 µs.

use serde::Serialize;

const BIN_NS: u64 = 20_000;
const BINS: usize = 10_000;

/// Median, 90th percentile and maximum of the recorded latencies, ms.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct LatencySummary {
    pub count: u64,
    pub median_ms: f64,
    pub p90_ms: f64,
    pub max_ms: f64,
}

/// The histogram at a coarser bin width, for reports: `counts[i]` samples lie in
/// [i·bin_ms, (i+1)·bin_ms), up to the bin that holds the maximum; samples above the 200 ms range
/// are counted in `over`.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct LatencyBins {
    pub bin_ms: f64,
    pub counts: Vec<u64>,
    /// Samples beyond the histogram's range (200 ms).
    pub over: u64,
}

/// The histogram; see the module docs.
#[derive(Clone, Debug)]
pub struct LatencyHistogram {
    bins: Vec<u32>,
    overflow: u64,
    count: u64,
    max_ns: u64,
}

impl Default for LatencyHistogram {
    fn default() -> Self {
        Self { bins: vec![0; BINS], overflow: 0, count: 0, max_ns: 0 }
    }
}

impl LatencyHistogram {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn record(&mut self, latency_ns: u64) {
        let bin = (latency_ns / BIN_NS) as usize;
        match self.bins.get_mut(bin) {
            Some(b) => *b = b.saturating_add(1),
            None => self.overflow += 1,
        }
        self.count += 1;
        self.max_ns = self.max_ns.max(latency_ns);
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    /// The nearest-rank `q` quantile (0 < q ≤ 1), ns; `None` without samples.
    pub fn quantile_ns(&self, q: f64) -> Option<u64> {
        if self.count == 0 {
            return None;
        }
        let rank = ((q.clamp(0.0, 1.0) * self.count as f64).ceil() as u64).max(1);
        let mut seen = 0u64;
        for (i, &n) in self.bins.iter().enumerate() {
            seen += u64::from(n);
            if seen >= rank {
                return Some(((i as u64 + 1) * BIN_NS).min(self.max_ns));
            }
        }
        Some(self.max_ns)
    }

    /// The counts regrouped into bins of `bin_ns` (a multiple of the 20 µs base bin, else rounded
    /// down to one), trailing empty bins dropped.
    pub fn bins(&self, bin_ns: u64) -> LatencyBins {
        let per = (bin_ns / BIN_NS).max(1) as usize;
        let mut counts: Vec<u64> = self.bins.chunks(per).map(|c| c.iter().map(|&n| u64::from(n)).sum()).collect();
        while counts.last() == Some(&0) {
            counts.pop();
        }
        LatencyBins { bin_ms: (per as u64 * BIN_NS) as f64 / 1e6, counts, over: self.overflow }
    }

    pub fn summary(&self) -> LatencySummary {
        // Rounded to the microsecond: finer digits would only be float noise in the report.
        let ms = |ns: Option<u64>| ns.map_or(0.0, |n| (n as f64 / 1e3).round() / 1e3);
        LatencySummary {
            count: self.count,
            median_ms: ms(self.quantile_ns(0.5)),
            p90_ms: ms(self.quantile_ns(0.9)),
            max_ms: ms((self.count > 0).then_some(self.max_ns)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_are_nearest_rank_within_one_bin() {
        let mut h = LatencyHistogram::new();
        assert_eq!(h.summary(), LatencySummary::default());
        // 1, 2, ..., 100 ms.
        for i in 1..=100u64 {
            h.record(i * 1_000_000);
        }
        let s = h.summary();
        assert_eq!(s.count, 100);
        // Rank 50 is 50 ms exactly, which sits on a bin's lower edge: reported as its upper edge.
        assert!((s.median_ms - 50.02).abs() < 1e-9, "{s:?}");
        assert!((s.p90_ms - 90.02).abs() < 1e-9, "{s:?}");
        assert_eq!(s.max_ms, 100.0);
    }

    #[test]
    fn bins_regroup_every_sample() {
        let mut h = LatencyHistogram::new();
        for us in [100u64, 499, 500, 1_250, 1_499, 7_000, 250_000] {
            h.record(us * 1_000);
        }
        let b = h.bins(500_000);
        assert_eq!(b.bin_ms, 0.5);
        // [0, 0.5): 0.1, 0.499; [0.5, 1): 0.5; [1, 1.5): 1.25, 1.499; [7, 7.5): 7.0; 250 ms over
        let mut want = vec![0u64; 15];
        (want[0], want[1], want[2], want[14]) = (2, 1, 2, 1);
        assert_eq!(b.counts, want);
        assert_eq!(b.over, 1);
        assert_eq!(b.counts.iter().sum::<u64>() + b.over, h.count());
        assert_eq!(LatencyHistogram::new().bins(500_000).counts, Vec::<u64>::new());
    }

    #[test]
    fn overflow_and_max_are_exact() {
        let mut h = LatencyHistogram::new();
        h.record(5_000);
        h.record(3_000_000_000);
        assert_eq!(h.quantile_ns(0.5), Some(BIN_NS), "the upper edge of the first bin");
        assert_eq!(h.quantile_ns(1.0), Some(3_000_000_000));
        assert_eq!(h.summary().max_ms, 3000.0);
    }
}
