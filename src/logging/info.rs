//! `flownav log info`: a one-pass summary of a log, also for files cut off by a crash.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::LogError;
use super::payload::LoggerStats;
use super::reader::{Scan, Scanned};

/// One channel's numbers.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TopicInfo {
    pub topic: String,
    pub schema: String,
    pub encoding: String,
    pub count: u64,
    /// First and last log time, ns.
    pub first_ns: u64,
    pub last_ns: u64,
    /// Messages whose log time is earlier than the previous one on the channel.
    pub out_of_order: u64,
    /// Messages whose sequence number did not increase.
    pub sequence_regressions: u64,
}

/// What a log holds.
#[derive(Clone, Debug, PartialEq)]
pub struct LogInfo {
    pub path: PathBuf,
    pub bytes: u64,
    /// Channels in id order.
    pub topics: Vec<TopicInfo>,
    pub messages: u64,
    pub first_ns: Option<u64>,
    pub last_ns: Option<u64>,
    /// The file ends with its summary and footer (closed cleanly).
    pub complete: bool,
    /// Why reading stopped before the footer, for a truncated file.
    pub truncation: Option<String>,
    /// The drop counters: final (`flownav.stats` metadata) when `stats_final`, else the last
    /// periodic `/logger/stats` message before the cut.
    pub stats: Option<LoggerStats>,
    pub stats_final: bool,
    /// The `flownav.header` metadata (kind, part, time offset).
    pub header: BTreeMap<String, String>,
}

impl LogInfo {
    /// Reads the whole file once.
    pub fn read(path: &Path) -> Result<Self, LogError> {
        let bytes = std::fs::metadata(path).map_err(|error| LogError::Read { path: path.to_path_buf(), error })?.len();
        let mut scan = Scan::open(path)?;
        let mut per_channel: BTreeMap<u16, TopicInfo> = BTreeMap::new();
        let mut last_seq: BTreeMap<u16, u32> = BTreeMap::new();
        let (mut stats, mut stats_final, mut header) = (None, false, BTreeMap::new());
        let (mut first, mut last, mut messages) = (None::<u64>, None::<u64>, 0u64);
        while let Some(item) = scan.next_item()? {
            match item {
                Scanned::Message { channel, sequence, log_time, data } => {
                    messages += 1;
                    first = Some(first.map_or(log_time, |f| f.min(log_time)));
                    last = Some(last.map_or(log_time, |l| l.max(log_time)));
                    let t = per_channel.entry(channel.id).or_insert_with(|| TopicInfo {
                        topic: channel.topic.clone(),
                        schema: channel.schema.clone(),
                        encoding: channel.message_encoding.clone(),
                        count: 0,
                        first_ns: log_time,
                        last_ns: log_time,
                        out_of_order: 0,
                        sequence_regressions: 0,
                    });
                    if t.count > 0 && log_time < t.last_ns {
                        t.out_of_order += 1;
                    }
                    if let Some(prev) = last_seq.insert(channel.id, sequence)
                        && sequence <= prev
                    {
                        t.sequence_regressions += 1;
                    }
                    t.count += 1;
                    t.first_ns = t.first_ns.min(log_time);
                    t.last_ns = t.last_ns.max(log_time);
                    if channel.schema == "flownav.LoggerStats"
                        && !stats_final
                        && let Ok(s) = serde_json::from_slice::<LoggerStats>(&data)
                    {
                        stats = Some(s);
                    }
                }
                Scanned::Metadata { name, metadata } => match name.as_str() {
                    "flownav.header" => header = metadata,
                    "flownav.stats" => {
                        let n = |k: &str| metadata.get(k).and_then(|v| v.parse().ok()).unwrap_or(0);
                        stats = Some(LoggerStats {
                            written: n("written"),
                            dropped_images: n("dropped_images"),
                            dropped_data: n("dropped_data"),
                            dropped_critical: n("dropped_critical"),
                            lost: n("lost"),
                        });
                        stats_final = true;
                    }
                    _ => {}
                },
            }
        }
        let truncation = (!scan.complete).then(|| scan.stopped.clone().unwrap_or_else(|| "no footer".into()));
        Ok(Self {
            path: path.to_path_buf(),
            bytes,
            topics: per_channel.into_values().collect(),
            messages,
            first_ns: first,
            last_ns: last,
            complete: scan.complete,
            truncation,
            stats,
            stats_final,
            header,
        })
    }

    /// Duration from the first to the last message, s.
    pub fn duration_s(&self) -> f64 {
        match (self.first_ns, self.last_ns) {
            (Some(a), Some(b)) => (b - a) as f64 * 1e-9,
            _ => 0.0,
        }
    }

    /// The human-readable report `flownav log info` prints.
    pub fn render(&self) -> String {
        let mut s = String::new();
        let secs = |ns: u64| format!("{}.{:09}", ns / 1_000_000_000, ns % 1_000_000_000);
        let _ = writeln!(s, "file:      {} ({:.1} MB)", self.path.display(), self.bytes as f64 / 1e6);
        if !self.header.is_empty() {
            let h = |k: &str| self.header.get(k).map(String::as_str).unwrap_or("?");
            let _ = writeln!(
                s,
                "log:       kind {}, part {}, time offset {} ns",
                h("kind"),
                h("part"),
                h("time_offset_ns")
            );
        }
        match &self.truncation {
            None => {
                let _ = writeln!(s, "status:    complete (summary and footer present)");
            }
            Some(why) => {
                let _ = writeln!(
                    s,
                    "status:    truncated: no summary, {} messages recovered (stopped: {why})",
                    self.messages
                );
            }
        }
        match (self.first_ns, self.last_ns) {
            (Some(a), Some(b)) => {
                let _ = writeln!(s, "time:      {} .. {} s (duration {:.3} s)", secs(a), secs(b), self.duration_s());
            }
            _ => {
                let _ = writeln!(s, "time:      no messages");
            }
        }
        let _ = writeln!(s, "messages:  {}", self.messages);
        match &self.stats {
            Some(st) => {
                let which = if self.stats_final { "final" } else { "last periodic report before the cut" };
                let _ = writeln!(
                    s,
                    "drops:     {} images, {} data, {} critical (set-points/odometry), {} lost ({which})",
                    st.dropped_images, st.dropped_data, st.dropped_critical, st.lost
                );
            }
            None => {
                let _ = writeln!(s, "drops:     unknown (no flownav.stats record and no /logger/stats message)");
            }
        }
        let width = self.topics.iter().map(|t| t.topic.len()).max().unwrap_or(5).max(5);
        let swidth = self.topics.iter().map(|t| t.schema.len()).max().unwrap_or(6).max(6);
        let _ = writeln!(s, "topics:");
        let _ = writeln!(
            s,
            "  {:width$}  {:swidth$}  {:>8}  {:>20}  {:>20}  {:>8}",
            "topic", "schema", "count", "first (s)", "last (s)", "rate Hz"
        );
        for t in &self.topics {
            let span = (t.last_ns - t.first_ns) as f64 * 1e-9;
            let rate =
                if t.count > 1 && span > 0.0 { format!("{:.1}", (t.count - 1) as f64 / span) } else { "-".into() };
            let mut line = format!(
                "  {:width$}  {:swidth$}  {:>8}  {:>20}  {:>20}  {:>8}",
                t.topic,
                t.schema,
                t.count,
                secs(t.first_ns),
                secs(t.last_ns),
                rate
            );
            if t.out_of_order > 0 {
                let _ = write!(line, "  ({} out of time order)", t.out_of_order);
            }
            let _ = writeln!(s, "{line}");
        }
        s
    }
}
