//! Fault → stop gaps, measured inside a simulated base, which knows when each link fault was
//! injected and what its motors were told.
//!
//! After a link fault the base may be running on a command the host no longer means: a lost or
//! damaged SETPOINT or STOP never arrived, a damaged ODOM or STATUS left the host without a
//! measurement, or the link is down. The fault is settled at the first moment the base is
//! commanded to zero (its watchdog trips, a STOP or a zero SETPOINT arrives) or receives an
//! intact command from the host, which is in control again. The gap is the simulated time from
//! the fault to that moment; a fault that finds the base already commanded to zero has a gap of
//! 0. Times are the base's simulated clock, so the figures do not depend on how loaded the
//! machine running the simulation is.

use serde::Serialize;

/// A kind of link fault, as the simulated link injects them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LinkFault {
    /// Bytes dropped from a chunk.
    Drop,
    /// A bit flipped in a chunk's bytes.
    Corrupt,
    /// The link went down.
    Disconnect,
}

/// Gaps of one fault kind: count, maximum and a 1 ms histogram (for the 99th percentile), in
/// constant memory however long the run.
#[derive(Clone, Debug, PartialEq)]
pub struct GapHistogram {
    count: u64,
    max_s: f64,
    /// `bins[i]` counts gaps in [i, i + 1) ms; the last bin counts all longer ones.
    bins: Vec<u64>,
}

/// Gaps of 2 s and more share the histogram's last bin (their maximum is still exact).
const BINS: usize = 2000;

impl Default for GapHistogram {
    fn default() -> Self {
        Self { count: 0, max_s: 0.0, bins: vec![0; BINS] }
    }
}

impl GapHistogram {
    pub fn record(&mut self, gap_s: f64) {
        let gap_s = gap_s.max(0.0);
        self.count += 1;
        self.max_s = self.max_s.max(gap_s);
        self.bins[((gap_s * 1000.0) as usize).min(BINS - 1)] += 1;
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    pub fn max_ms(&self) -> f64 {
        self.max_s * 1000.0
    }

    /// The upper edge of the bin holding quantile `q` (0 < q ≤ 1), ms: at least the true
    /// quantile, at most 1 ms above it (never above the maximum).
    pub fn quantile_ms(&self, q: f64) -> f64 {
        if self.count == 0 {
            return 0.0;
        }
        let rank = ((q * self.count as f64).ceil() as u64).clamp(1, self.count);
        let mut seen = 0;
        for (i, n) in self.bins.iter().enumerate() {
            seen += n;
            if seen >= rank {
                return if i == BINS - 1 { self.max_ms() } else { ((i + 1) as f64).min(self.max_ms()) };
            }
        }
        self.max_ms()
    }

    pub fn summary(&self) -> GapSummary {
        GapSummary { count: self.count, max_ms: self.max_ms(), p99_ms: self.quantile_ms(0.99) }
    }
}

/// One kind's figures, for JSON.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct GapSummary {
    pub count: u64,
    pub max_ms: f64,
    pub p99_ms: f64,
}

/// All kinds' figures, for JSON.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct StopGapSummary {
    pub drop: GapSummary,
    pub corrupt: GapSummary,
    pub disconnect: GapSummary,
    /// Faults not settled yet (the last ones of a run that ended right after them).
    pub pending: u64,
}

/// Faults waiting for a stop, and the gaps of the settled ones. See the module docs.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StopGaps {
    drop: GapHistogram,
    corrupt: GapHistogram,
    disconnect: GapHistogram,
    /// Fault kind and time, s. Never longer than the faults of one watchdog period: the
    /// watchdog settles them all.
    pending: Vec<(LinkFault, f64)>,
}

impl StopGaps {
    fn histogram(&mut self, kind: LinkFault) -> &mut GapHistogram {
        match kind {
            LinkFault::Drop => &mut self.drop,
            LinkFault::Corrupt => &mut self.corrupt,
            LinkFault::Disconnect => &mut self.disconnect,
        }
    }

    /// A fault at `t_s`; `stopped`: the base is commanded to zero already.
    pub fn fault(&mut self, kind: LinkFault, t_s: f64, stopped: bool) {
        if stopped {
            self.histogram(kind).record(0.0);
        } else {
            self.pending.push((kind, t_s));
        }
    }

    /// The base was stopped, or got an intact command, at `t_s`: every pending fault is settled.
    pub fn settle(&mut self, t_s: f64) {
        for (kind, t0) in std::mem::take(&mut self.pending) {
            self.histogram(kind).record(t_s - t0);
        }
    }

    pub fn get(&self, kind: LinkFault) -> &GapHistogram {
        match kind {
            LinkFault::Drop => &self.drop,
            LinkFault::Corrupt => &self.corrupt,
            LinkFault::Disconnect => &self.disconnect,
        }
    }

    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    pub fn summary(&self) -> StopGapSummary {
        StopGapSummary {
            drop: self.drop.summary(),
            corrupt: self.corrupt.summary(),
            disconnect: self.disconnect.summary(),
            pending: self.pending.len() as u64,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaps_are_settled_together_and_summarised() {
        let mut g = StopGaps::default();
        g.fault(LinkFault::Drop, 1.0, false);
        g.fault(LinkFault::Corrupt, 1.010, false);
        g.fault(LinkFault::Disconnect, 1.020, true);
        assert_eq!(g.pending(), 2);
        g.settle(1.040);
        assert_eq!(g.pending(), 0);
        let s = g.summary();
        assert_eq!((s.drop.count, s.corrupt.count, s.disconnect.count), (1, 1, 1));
        assert!((s.drop.max_ms - 40.0).abs() < 1e-9 && (s.corrupt.max_ms - 30.0).abs() < 1e-9, "{s:?}");
        assert_eq!(s.disconnect.max_ms, 0.0);
        // A settle with nothing pending records nothing.
        g.settle(2.0);
        assert_eq!(g.get(LinkFault::Drop).count(), 1);
    }

    #[test]
    fn p99_is_the_bin_edge_above_the_true_quantile() {
        let mut h = GapHistogram::default();
        for i in 0..100 {
            h.record(0.0105 + f64::from(i) * 1e-4); // 10.5 .. 20.4 ms
        }
        h.record(3.5); // beyond the last bin: the maximum is still exact
        assert_eq!(h.count(), 101);
        assert_eq!(h.max_ms(), 3500.0);
        assert_eq!(h.quantile_ms(0.99), 21.0);
        assert_eq!(h.quantile_ms(1.0), 3500.0);
        assert_eq!(GapHistogram::default().quantile_ms(0.99), 0.0);
    }
}
