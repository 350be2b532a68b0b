//! `flownav replay`: re-runs the per-frame pipeline on a run log's frames and odometry, and
//! checks the result against what the run logged.
//!
//! A log written through [`crate::logging::record`] holds everything a step consumed: the frames
//! (`/camera/image`, raw mono8 or the camera's JPEG bytes), the odometry passed to each step and
//! which frame it was paired with (`/step/input`), every `fail_safe` call, and the configuration,
//! calibration, mission and map (the `flownav.config` metadata record). [`replay`] rebuilds a
//! fresh [`Pipeline`] from the metadata, feeds it the same inputs in the same order, and compares
//! each step's flow, perception (with the OFFIS attributes), goal and set-point with the logged
//! messages byte for byte (the logger's own JSON encoding; floats are written shortest-round-trip,
//! so equal bytes means equal bits). On the CPU flow backend the pipeline is deterministic, so a
//! faithful log replays with zero mismatches.
//!
//! Steps that cannot be reproduced are reported, not counted as mismatches: when the logger
//! dropped the image of a step's frame or of its previous frame (images are dropped first under
//! load), that step is *unchecked*; the pipeline state after it (limiter, PAFSIS progress, the
//! TPO that OFFIS decides over its last steps) may then differ from the run's, so later steps
//! are still compared but counted apart (`after_gap`), until a logged `fail_safe` resets the
//! state (runs without a mission only; PAFSIS progress cannot be resynchronised).

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use hal::mjpeg::MjpegDecoder;
use hal::{BodyVelocity, Calibration, Frame, LumaImage};
use serde::Serialize;
use serde_json::Value;

use crate::config::Config;
use crate::flow::Backend;
use crate::logging::record::{self, CONFIG_METADATA, KEY_CALIBRATION, KEY_CONFIG, KEY_MAP, KEY_MISSION};
use crate::logging::{LogEntry, LogError, LogEvent, LogReader, LoggedImage, StepInputLog, encode};
use crate::pafsis::{Mission, TopoMap};
use crate::step::{Pipeline, PipelineError, StepOutput};

/// Errors that stop a replay (mismatches are not errors: see [`ReplaySummary`]).
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Log(#[from] LogError),
    #[error(
        "{} has no flownav.config metadata record, so the configuration, calibration and mission of the run are unknown: replay needs a log written by `flownav run` or `flownav sim` (through flownav::logging::record)",
        path.display()
    )]
    NoSetup { path: PathBuf },
    #[error("{}: the logged {what} cannot be used: {message}", path.display())]
    BadSetup { path: PathBuf, what: &'static str, message: String },
    #[error("cannot build the pipeline from the logged configuration: {0}")]
    Pipeline(#[from] PipelineError),
}

/// What the log says the run was made with.
#[derive(Clone, Debug)]
pub struct LoggedSetup {
    pub config: Config,
    pub calibration: Calibration,
    /// Mission `FROM:TO` and its map, when the run had one.
    pub mission: Option<(TopoMap, Mission)>,
    /// The `flownav.config` record as written (kind, flownav version, ...).
    pub record: std::collections::BTreeMap<String, String>,
}

impl LoggedSetup {
    /// Reads the setup from a log's metadata records.
    pub fn from_metadata(
        path: &Path,
        metadata: &[(String, std::collections::BTreeMap<String, String>)],
    ) -> Result<Self, ReplayError> {
        let Some((_, m)) = metadata.iter().find(|(name, _)| name == CONFIG_METADATA) else {
            return Err(ReplayError::NoSetup { path: path.to_path_buf() });
        };
        let bad = |what, message: String| ReplayError::BadSetup { path: path.to_path_buf(), what, message };
        let text = |key: &str, what| {
            m.get(key).ok_or_else(|| {
                let why = m.get(&format!("{}_error", what)).cloned().unwrap_or_else(|| format!("no {key} entry"));
                bad(what, why)
            })
        };
        let config: Config =
            toml::from_str(text(KEY_CONFIG, "config")?).map_err(|e| bad("configuration", e.to_string()))?;
        config.validate().map_err(|e| bad("configuration", e.to_string()))?;
        let calibration = Calibration::from_toml(text(KEY_CALIBRATION, "calibration")?, "the log's calibration")
            .map_err(|e| bad("calibration", e.to_string()))?;
        let mission = match m.get(KEY_MISSION) {
            None => None,
            Some(mission) => {
                let mission = Mission::from_str(mission).map_err(|e| bad("mission", e.to_string()))?;
                let map_text = m.get(KEY_MAP).ok_or_else(|| {
                    bad("mission", format!("{mission} has no map in the log (the run did not call record::add_map)"))
                })?;
                let map = TopoMap::parse(map_text, "<map in the log>").map_err(|e| bad("map", e.to_string()))?;
                Some((map, mission))
            }
        };
        Ok(Self { config, calibration, mission, record: m.clone() })
    }
}

/// How to replay.
#[derive(Clone, Debug, Default)]
pub struct ReplayOptions {
    /// Flow backend; `None` = the CPU engine (the reference for bit-exact checks).
    pub backend: Option<Backend>,
    /// Use this configuration instead of the logged one (what-if runs; steps will differ).
    pub config: Option<Config>,
}

/// One field that differs between the log and the replay.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FieldDiff {
    /// The topic, e.g. `/control/setpoint`.
    pub topic: String,
    /// JSON path inside the message, e.g. `tpo.confidence`, `vectors[17].u`.
    pub field: String,
    pub logged: Value,
    pub replayed: Value,
}

impl std::fmt::Display for FieldDiff {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} {}: logged {}, replayed {}", self.topic, self.field, self.logged, self.replayed)
    }
}

/// How one logged step compared.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "check", rename_all = "snake_case")]
pub enum Check {
    /// Every logged output of the step equals the replayed one, bit for bit.
    Match,
    /// Some differ (the first few differences).
    Mismatch { diffs: Vec<FieldDiff> },
    /// The step could not be reproduced (why).
    Unchecked { reason: String },
}

/// One replayed step, for per-frame output.
#[derive(Debug)]
pub struct StepRecord<'a> {
    pub seq: u64,
    pub t_ns: u64,
    /// The replayed output (absent for unchecked steps).
    pub output: Option<&'a StepOutput>,
    pub check: &'a Check,
    /// The pipeline state may differ from the run's (after an unchecked step).
    pub after_gap: bool,
}

/// The outcome of a replay.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ReplaySummary {
    /// The flow engine used.
    pub backend: String,
    /// Images read from the log.
    pub frames: u64,
    /// Steps the run logged (`/step/input` kind `step`).
    pub steps: u64,
    /// Steps replayed and compared with an identical pipeline state.
    pub checked: u64,
    pub matched: u64,
    /// Checked steps with a difference: a failure of the determinism contract (or a tampered log).
    pub mismatched: u64,
    /// Steps that could not be reproduced (their frame or previous frame was not logged).
    pub unchecked: u64,
    /// Steps compared after an unchecked step (the state may differ), and how many differed.
    pub after_gap: u64,
    pub after_gap_mismatched: u64,
    /// `fail_safe` calls replayed.
    pub fail_safes: u64,
    /// Steps whose frame `seq` did not follow the previous step's (frames the run skipped,
    /// e.g. latest-frame-wins): harmless, the pairing comes from `prev_t_ns`.
    pub seq_gaps: u64,
    /// Images the logger reported dropping (last `/logger/stats`).
    pub dropped_images: u64,
    pub first_mismatch: Option<MismatchReport>,
    pub first_unchecked: Option<String>,
    /// Why the file ended early, when it was cut off (a crash).
    pub truncated: Option<String>,
    /// Mean replay time per step, ms (flow + OFFIS + PAFSIS + MOFIS + comparison; decode excluded).
    pub ms_per_step: f64,
}

/// Where the first mismatch was.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MismatchReport {
    pub seq: u64,
    pub t_ns: u64,
    pub diffs: Vec<FieldDiff>,
}

impl ReplaySummary {
    /// Whether `--check` passes: no checked step differed.
    pub fn passed(&self) -> bool {
        self.mismatched == 0
    }
}

/// Most field differences kept per step.
const MAX_DIFFS: usize = 8;
/// Images kept to prime the pipeline with a step's previous frame.
const RECENT_IMAGES: usize = 4;

/// The messages of one capture time, in file order.
#[derive(Default)]
struct Group {
    t_ns: u64,
    image: Option<LoggedImage>,
    inputs: Vec<StepInputLog>,
    setpoints: Vec<Vec<u8>>,
    perception: Option<Vec<u8>>,
    goal: Option<Vec<u8>>,
    flow: Option<Vec<u8>>,
}

struct Replayer {
    pipeline: Pipeline,
    has_mission: bool,
    decoder: MjpegDecoder,
    /// Capture time of the frame the pipeline holds as its previous frame.
    last_fed: Option<u64>,
    last_seq: Option<u64>,
    recent: VecDeque<(u64, LoggedImage)>,
    diverged: bool,
    summary: ReplaySummary,
    step_time: std::time::Duration,
}

/// Replays the log `paths` (one file, or the parts of a split log in order), calling `on_step`
/// for every logged step.
pub fn replay(
    paths: &[PathBuf],
    options: &ReplayOptions,
    mut on_step: impl FnMut(&StepRecord),
) -> Result<ReplaySummary, ReplayError> {
    let first = paths.first().cloned().unwrap_or_default();
    let mut reader = LogReader::open_parts(paths.iter().cloned())?;
    // Metadata records precede the messages: after the first message they are all known.
    let first_entry = reader.next().transpose()?;
    let setup = LoggedSetup::from_metadata(&first, reader.metadata())?;
    let mut config = options.config.clone().unwrap_or(setup.config);
    config.flow.backend = options.backend.unwrap_or(Backend::Cpu);
    let has_mission = setup.mission.is_some();
    let pipeline = Pipeline::new(&config, setup.calibration, setup.mission)?;
    let backend = pipeline.backend().engine.to_string();
    let mut r = Replayer {
        pipeline,
        has_mission,
        decoder: MjpegDecoder::new(),
        last_fed: None,
        last_seq: None,
        recent: VecDeque::new(),
        diverged: false,
        summary: ReplaySummary { backend, ..ReplaySummary::default() },
        step_time: std::time::Duration::ZERO,
    };
    let mut group: Option<Group> = None;
    for entry in first_entry.into_iter().map(Ok).chain(&mut reader) {
        let entry = entry?;
        if group.as_ref().is_some_and(|g| g.t_ns != entry.t_ns) {
            r.process(group.take().expect("checked"), &mut on_step);
        }
        let g = group.get_or_insert_with(|| Group { t_ns: entry.t_ns, ..Group::default() });
        r.collect(g, entry);
    }
    if let Some(g) = group {
        r.process(g, &mut on_step);
    }
    r.summary.truncated = reader.truncated().first().map(|(p, why)| format!("{}: {why}", p.display()));
    let replayed = r.summary.checked + r.summary.after_gap;
    if replayed > 0 {
        r.summary.ms_per_step = r.step_time.as_secs_f64() * 1e3 / replayed as f64;
    }
    Ok(r.summary)
}

impl Replayer {
    fn collect(&mut self, g: &mut Group, entry: LogEntry) {
        match entry.event {
            LogEvent::Image(image) => {
                self.summary.frames += 1;
                g.image = Some(image);
            }
            LogEvent::StepInput(input) => g.inputs.push(input),
            LogEvent::Setpoint(_) => g.setpoints.push(entry.data),
            LogEvent::Perception(_) => g.perception = Some(entry.data),
            LogEvent::Goal(_) => g.goal = Some(entry.data),
            LogEvent::Flow(_) => g.flow = Some(entry.data),
            LogEvent::Stats(s) => self.summary.dropped_images = self.summary.dropped_images.max(s.dropped_images),
            _ => {}
        }
    }

    fn process(&mut self, mut g: Group, on_step: &mut impl FnMut(&StepRecord)) {
        if let Some(image) = g.image.take() {
            if self.recent.len() == RECENT_IMAGES {
                self.recent.pop_front();
            }
            self.recent.push_back((g.t_ns, image));
        }
        // /step/input and /control/setpoint are both critical (never dropped short of the cap)
        // and written in pairs by record_step / record_failsafe: the k-th of each belong together.
        let mut setpoints = std::mem::take(&mut g.setpoints).into_iter();
        for input in std::mem::take(&mut g.inputs) {
            let setpoint = setpoints.next();
            match input {
                StepInputLog::FailSafe { .. } => {
                    self.pipeline.fail_safe();
                    self.last_fed = None;
                    self.last_seq = None;
                    self.summary.fail_safes += 1;
                    // Without PAFSIS, the limiter and the previous frame are all the state there is.
                    if !self.has_mission {
                        self.diverged = false;
                    }
                }
                StepInputLog::Step { seq, t_ns, prev_t_ns, v, omega, odometry_scale, odometry_bend_rad_m } => {
                    // the learned odometry errors depend on pairs a gap may have hidden: the
                    // step gets the ones the robot used
                    self.pipeline.set_odometry_calibration(odometry_scale, odometry_bend_rad_m);
                    self.step(&g, setpoint, seq, t_ns, prev_t_ns, BodyVelocity { v, omega }, on_step)
                }
            }
        }
    }

    fn image(&mut self, t_ns: u64) -> Result<Option<LumaImage>, String> {
        let Some((_, image)) = self.recent.iter().rev().find(|(t, _)| *t == t_ns) else {
            return Ok(None);
        };
        match image {
            LoggedImage::Mono8(img) => Ok(Some(img.clone())),
            LoggedImage::Jpeg(bytes) => {
                self.decoder.decode(bytes).map(Some).map_err(|e| format!("its JPEG image cannot be decoded: {e}"))
            }
        }
    }

    /// Drops the pipeline's pairing after a step that cannot be reproduced.
    fn unchecked(&mut self, seq: u64, t_ns: u64, reason: String, on_step: &mut impl FnMut(&StepRecord)) {
        self.summary.unchecked += 1;
        if self.summary.first_unchecked.is_none() {
            self.summary.first_unchecked = Some(format!("seq {seq} (t {t_ns} ns): {reason}"));
        }
        self.diverged = true;
        let check = Check::Unchecked { reason };
        on_step(&StepRecord { seq, t_ns, output: None, check: &check, after_gap: true });
    }

    #[allow(clippy::too_many_arguments)]
    fn step(
        &mut self,
        g: &Group,
        setpoint: Option<Vec<u8>>,
        seq: u64,
        t_ns: u64,
        prev_t_ns: u64,
        odometry: BodyVelocity,
        on_step: &mut impl FnMut(&StepRecord),
    ) {
        self.summary.steps += 1;
        if self.last_seq.is_some_and(|s| seq != s + 1) {
            self.summary.seq_gaps += 1;
        }
        self.last_seq = Some(seq);
        let image = match self.image(t_ns) {
            Ok(Some(image)) => image,
            Ok(None) => {
                // Forget the previous frame so the next step is not paired across the gap.
                self.pipeline.fail_safe();
                self.last_fed = None;
                let reason = "cannot check: the image of its frame was not logged (dropped by the logger)".to_string();
                return self.unchecked(seq, t_ns, reason, on_step);
            }
            Err(reason) => {
                self.pipeline.fail_safe();
                self.last_fed = None;
                return self.unchecked(seq, t_ns, reason, on_step);
            }
        };
        if self.last_fed != Some(prev_t_ns) {
            let prev = if self.last_fed.is_none() { self.image(prev_t_ns) } else { Ok(None) };
            match prev {
                Ok(Some(prev)) => {
                    // The run's pipeline was empty too (start, or after a fail-safe): prime it.
                    let frame = Frame { seq: seq.saturating_sub(1), t_ns: prev_t_ns, image: prev };
                    let _ = self.pipeline.step(frame, BodyVelocity::ZERO);
                    self.last_fed = Some(prev_t_ns);
                }
                other => {
                    let reason = match other {
                        Err(reason) => format!("cannot check: its previous frame (t {prev_t_ns} ns): {reason}"),
                        _ => format!(
                            "cannot check steps whose previous frame was not logged: the previous frame (t {prev_t_ns} ns) is missing from the log (its image was dropped, or it was stepped without a logged step)"
                        ),
                    };
                    // Prime with this frame so the next step pairs correctly.
                    self.pipeline.fail_safe();
                    let _ = self.pipeline.step(Frame { seq, t_ns, image }, BodyVelocity::ZERO);
                    self.last_fed = Some(t_ns);
                    return self.unchecked(seq, t_ns, reason, on_step);
                }
            }
        }
        let started = std::time::Instant::now();
        let result = self.pipeline.step(Frame { seq, t_ns, image }, odometry);
        self.last_fed = Some(t_ns);
        let (check, output) = match result {
            Ok(Some(out)) => (self.compare(g, setpoint.as_deref(), &out), Some(out)),
            Ok(None) => (
                Check::Mismatch {
                    diffs: vec![diff("/step/input", "step", "an output".into(), "none (priming frame)".into())],
                },
                None,
            ),
            Err(e) => (
                Check::Mismatch {
                    diffs: vec![diff("/step/input", "step", "an output".into(), format!("error: {e}").into())],
                },
                None,
            ),
        };
        self.step_time += started.elapsed();
        let after_gap = self.diverged;
        let mismatch = matches!(check, Check::Mismatch { .. });
        if after_gap {
            self.summary.after_gap += 1;
            self.summary.after_gap_mismatched += u64::from(mismatch);
        } else {
            self.summary.checked += 1;
            if let Check::Mismatch { diffs } = &check {
                self.summary.mismatched += 1;
                if self.summary.first_mismatch.is_none() {
                    self.summary.first_mismatch = Some(MismatchReport { seq, t_ns, diffs: diffs.clone() });
                }
            } else {
                self.summary.matched += 1;
            }
        }
        on_step(&StepRecord { seq, t_ns, output: output.as_ref(), check: &check, after_gap });
    }

    /// Compares what the replayed step would have logged with what was logged, byte for byte,
    /// and explains differences field by field.
    fn compare(&self, g: &Group, setpoint: Option<&[u8]>, out: &StepOutput) -> Check {
        let mut diffs = Vec::new();
        let mut check = |topic: &str, logged: Option<&[u8]>, replayed: Vec<u8>| {
            if let Some(logged) = logged
                && logged != replayed.as_slice()
            {
                json_diff(topic, logged, &replayed, &mut diffs);
            }
        };
        check("/control/setpoint", setpoint, encode::setpoint(&record::setpoint_log(out)));
        check(
            "/offis/perception",
            g.perception.as_deref(),
            encode::perception(&out.perception, &record::attributes_json(&self.pipeline)),
        );
        check("/pafsis/goal", g.goal.as_deref(), encode::goal(&record::goal_log(out, &self.pipeline)));
        check("/flow/field", g.flow.as_deref(), encode::flow_field(&out.flow));
        if diffs.is_empty() { Check::Match } else { Check::Mismatch { diffs } }
    }
}

fn diff(topic: &str, field: &str, logged: Value, replayed: Value) -> FieldDiff {
    FieldDiff { topic: topic.into(), field: field.into(), logged, replayed }
}

/// Appends the differing leaves of two JSON messages (at most [`MAX_DIFFS`] in all).
fn json_diff(topic: &str, logged: &[u8], replayed: &[u8], out: &mut Vec<FieldDiff>) {
    let parse = |b: &[u8]| serde_json::from_slice::<Value>(b).unwrap_or_else(|e| Value::String(format!("({e})")));
    let (a, b) = (parse(logged), parse(replayed));
    let before = out.len();
    walk(topic, "", &a, &b, out);
    if out.len() == before {
        // Same values, different bytes (e.g. key order): still a difference in what was logged.
        out.push(diff(
            topic,
            "(encoding)",
            String::from_utf8_lossy(logged).into(),
            String::from_utf8_lossy(replayed).into(),
        ));
    }
}

fn walk(topic: &str, path: &str, a: &Value, b: &Value, out: &mut Vec<FieldDiff>) {
    if out.len() >= MAX_DIFFS || a == b {
        return;
    }
    let join = |k: &str| if path.is_empty() { k.to_string() } else { format!("{path}.{k}") };
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let keys: Vec<&String> = x.keys().chain(y.keys().filter(|k| !x.contains_key(*k))).collect();
            for k in keys {
                let null = Value::Null;
                walk(topic, &join(k), x.get(k).unwrap_or(&null), y.get(k).unwrap_or(&null), out);
            }
        }
        (Value::Array(x), Value::Array(y)) if x.len() == y.len() => {
            for (i, (p, q)) in x.iter().zip(y).enumerate() {
                walk(topic, &format!("{path}[{i}]"), p, q, out);
            }
        }
        _ => out.push(diff(topic, if path.is_empty() { "(message)" } else { path }, a.clone(), b.clone())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn json_diff_names_the_leaves_that_differ() {
        let a =
            serde_json::to_vec(&json!({"tpo": {"shape": "wall", "confidence": 0.5}, "m": [[1, 0], [0, 1]]})).unwrap();
        let b =
            serde_json::to_vec(&json!({"tpo": {"shape": "wall", "confidence": 0.25}, "m": [[1, 0], [1, 1]]})).unwrap();
        let mut out = Vec::new();
        json_diff("/offis/perception", &a, &b, &mut out);
        let fields: Vec<_> = out.iter().map(|d| d.field.as_str()).collect();
        // Keys in serde_json's (sorted) order.
        assert_eq!(fields, ["m[1][0]", "tpo.confidence"]);
        assert_eq!(out[1].to_string(), "/offis/perception tpo.confidence: logged 0.5, replayed 0.25");
    }

    #[test]
    fn a_log_without_the_setup_record_is_refused_by_name() {
        let e = LoggedSetup::from_metadata(Path::new("x.mcap"), &[]).unwrap_err();
        assert!(e.to_string().contains("no flownav.config metadata record"), "{e}");
    }

    #[test]
    fn a_mission_without_its_map_is_refused() {
        let options = record::run_options("run", &Config::default(), &Calibration::nominal_c310(), Some("R1:R2"), None);
        let e = LoggedSetup::from_metadata(Path::new("x.mcap"), &options.metadata).unwrap_err();
        assert!(e.to_string().contains("add_map"), "{e}");
    }
}
