//! The OFFIS accuracy benchmark (`flownav bench-offis`): a labelled scene set rendered with
//! `mocks::scene` (walls, corners, doors, corridors and empty floor at varied distances, widths
//! and angles, half of them with a box or a person in front, with sensor noise), each seen as a
//! short sequence of frames while the camera drives forward (straight, or along an arc with
//! `omega_max` > 0: each scene's turn rate drawn from ±`omega_max`), run through the real per-frame
//! pipeline ([`crate::step::Pipeline`]: flow, OFFIS with its temporal filter) and compared with
//! the ground truth (`mocks::truth`) at the last frame.
//!
//! Deterministic for a seed: scene `i` of seed `s` draws its parameters from
//! `SplitMix64(s · 1_000_003 + i)`.

use crate::config::Config;
use crate::offis::ClassifierKind;
use crate::perception::{Perception, TpoShape};
use crate::step::{Pipeline, PipelineError, StepError};
use hal::{BodyVelocity, Calibration, Frame, LumaImage};
use mocks::scene::{self, Scene};
use mocks::world::SplitMix64;
use mocks::{Effects, GroundTruth, Pose, Renderer, TpoClass};
use serde::Serialize;
use std::f64::consts::PI;

/// Why the benchmark could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error("bench-offis: {0}")]
    Pipeline(#[from] PipelineError),
    #[error("bench-offis: scene {index} ({scene}): {source}")]
    Step {
        index: usize,
        scene: String,
        #[source]
        source: Box<StepError>,
    },
    #[error("bench-offis: {0}")]
    Options(String),
}

/// What to run.
#[derive(Clone, Debug, PartialEq)]
pub struct BenchOptions {
    /// Number of scenes (cycling wall, corner, door, corridor, none).
    pub scenes: usize,
    pub seed: u64,
    /// Forward speed, m/s.
    pub velocity: f64,
    /// Frame rates are drawn uniformly from this range, frames/s.
    pub fps: [f64; 2],
    /// Sensor noise, grey levels (standard deviation).
    pub noise: f64,
    /// Fraction of the scenes with an obstacle.
    pub obstacle_frac: f64,
    /// Frames per scene: the camera drives through them, the last one at the scene's start
    /// pose (where the truth is taken); at least 2 (one frame pair).
    pub frames: usize,
    /// Turning scenes: each scene's turn rate is drawn uniformly from ±this, rad/s, and the
    /// camera drives along that arc (the odometry says so); 0 drives straight ahead, and the
    /// scene set is then the same as without the option.
    pub omega_max: f64,
}

impl Default for BenchOptions {
    fn default() -> Self {
        Self {
            scenes: 200,
            seed: 2,
            velocity: 0.3,
            fps: [10.0, 30.0],
            noise: 2.0,
            obstacle_frac: 0.5,
            frames: FRAMES,
            omega_max: 0.0,
        }
    }
}

/// Frames per scene by default: 8 frame pairs, so the TPO filter's window
/// ([`crate::offis::temporal::TemporalParams::window`], 8 steps) is full at the last frame; 0.27–0.8 s
/// of driving at 10–30 fps, 8–24 cm at 0.3 m/s.
pub const FRAMES: usize = 9;

/// One labelled scene.
#[derive(Clone, Debug)]
pub struct Case {
    pub label: String,
    pub scene: Scene,
    pub fps: f64,
    /// Turn rate while driving through the scene's frames, rad/s (positive = left).
    pub omega: f64,
}

fn uniform(rng: &mut SplitMix64, [lo, hi]: [f64; 2]) -> f64 {
    rng.range(lo, hi)
}

/// Scene `index` of the set for `seed`.
pub fn case(seed: u64, index: usize, opts: &BenchOptions) -> Case {
    let mut rng = SplitMix64::new(seed.wrapping_mul(1_000_003).wrapping_add(index as u64));
    let deg = PI / 180.0;
    let (mut scene, mut label, tpo_m, half_width) = match index % 5 {
        0 => {
            let (d, a) = (uniform(&mut rng, [1.2, 4.5]), uniform(&mut rng, [-40.0, 40.0]));
            (scene::wall(d, a * deg), format!("wall d={d:.2} angle={a:.0}°"), d, f64::INFINITY)
        }
        1 => {
            let d = uniform(&mut rng, [1.5, 4.5]);
            let a = if rng.range(0.0, 1.0) < 0.7 {
                uniform(&mut rng, [70.0, 150.0])
            } else {
                uniform(&mut rng, [210.0, 290.0])
            };
            // a concave corner's walls come nearer towards the sides of the view
            let near = if a < 180.0 { d * (a * deg / 2.0).sin().max(0.5) } else { d };
            (scene::corner(d, a * deg), format!("corner d={d:.2} angle={a:.0}°"), near, f64::INFINITY)
        }
        2 => {
            let (w, d) = (uniform(&mut rng, [0.8, 1.4]), uniform(&mut rng, [1.5, 4.5]));
            (scene::door(w, d), format!("door w={w:.2} d={d:.2}"), d, f64::INFINITY)
        }
        3 => {
            let (w, l) = (uniform(&mut rng, [1.4, 3.0]), uniform(&mut rng, [8.0, 20.0]));
            (scene::corridor(w, l), format!("corridor w={w:.2} len={l:.1}"), l, w / 2.0)
        }
        _ => (scene::empty(), "empty".to_string(), f64::INFINITY, f64::INFINITY),
    };
    let yaw_max: f64 = [0.0, 10.0, 12.0, 8.0, 0.0][index % 5];
    let yaw = uniform(&mut rng, [-yaw_max, yaw_max.max(1e-9)]);
    scene.camera = Pose::new(0.0, 0.0, yaw * deg);
    if yaw_max > 0.0 {
        label.push_str(&format!(" yaw={yaw:.0}°"));
    }
    if rng.range(0.0, 1.0) < opts.obstacle_frac {
        let far = (tpo_m - 0.8).min(3.0);
        for _ in 0..20 {
            if far < 0.8 {
                break;
            }
            let d = uniform(&mut rng, [0.8, far]);
            let b = uniform(&mut rng, [-0.3, 0.3]) + yaw * deg;
            let person = rng.range(0.0, 1.0) < 0.5;
            let reach = if person { 0.25 } else { 0.35 };
            if ((d + reach) * (b - yaw * deg).sin()).abs() + reach > half_width - 0.05 {
                continue;
            }
            let with = if person { scene.clone().with_person(d, b) } else { scene.clone().with_obstacle(d, b) };
            if with.world.validate(&with.world.name).is_ok() {
                let what = if person { "person" } else { "box" };
                label.push_str(&format!(" + {what} d={d:.2} b={:.0}°", b / deg));
                scene = with;
                break;
            }
        }
    }
    let fps = uniform(&mut rng, opts.fps);
    label.push_str(&format!(" @{fps:.0}fps"));
    // drawn last, so that the straight scene set stays what it was
    let omega = if opts.omega_max > 0.0 { uniform(&mut rng, [-opts.omega_max, opts.omega_max]) } else { 0.0 };
    if omega != 0.0 {
        label.push_str(&format!(" ω={omega:+.3}"));
    }
    Case { label, scene, fps, omega }
}

fn shape_of(c: TpoClass) -> TpoShape {
    match c {
        TpoClass::Wall => TpoShape::Wall,
        TpoClass::Corner => TpoShape::Corner,
        TpoClass::Door => TpoShape::Door,
        TpoClass::Corridor => TpoShape::Corridor,
        TpoClass::None => TpoShape::None,
    }
}

fn index(s: TpoShape) -> usize {
    TpoShape::ALL.iter().position(|&x| x == s).expect("ALL lists every shape")
}

/// One scene's truth and prediction.
#[derive(Clone, Debug, Serialize)]
pub struct Sample {
    pub index: usize,
    pub label: String,
    pub truth: TpoShape,
    pub predicted: TpoShape,
    pub confidence: f64,
    pub truth_tpo_m: Option<f64>,
    pub tpo_m: Option<f64>,
    /// Ground-truth nearest obstacle (distance m, bearing rad), if one is visible.
    pub truth_obstacle: Option<(f64, f64)>,
    /// Reported obstacle (distance m, bearing rad), if present.
    pub obstacle: Option<(Option<f64>, Option<f64>)>,
    pub features: crate::offis::features::Features,
    /// The envelope profile (forward, left per bin, m), for diagnosis.
    pub profile: Vec<Option<[f64; 2]>>,
    /// Blocks found nearer than the TPO, and in the reported obstacle's cluster.
    pub obstacle_blocks: [usize; 2],
    /// The planes fitted to the profile for the TPO's shape, for diagnosis.
    pub model: crate::offis::features::TpoModel,
    /// The paper classifier's inputs (paper mode; the defaults otherwise).
    pub paper: crate::offis::paper::PaperFeatures,
}

/// The benchmark's result.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    /// `offis.classifier` of the run: "flownav" or "paper".
    pub classifier: &'static str,
    pub scenes: usize,
    pub seed: u64,
    /// The turn rates were drawn from ±this, rad/s (0: straight drives).
    pub omega_max: f64,
    pub width: u32,
    pub height: u32,
    /// Rows = truth, columns = predicted, in wall, corner, door, corridor, none order.
    pub confusion: [[usize; 5]; 5],
    pub tpo_accuracy: f64,
    /// Scenes with a visible obstacle, and the fraction of them where one was reported.
    pub obstacle_scenes: usize,
    pub detection_rate: f64,
    /// Scenes without a visible obstacle, and the fraction where one was reported anyway.
    pub clear_scenes: usize,
    pub false_alarm_rate: f64,
    /// Over the detected obstacles: |d̂ − d| / d, median and 90th percentile.
    pub distance_rel_err: [f64; 2],
    /// Over the detected obstacles: |b̂ − b|, degrees, median and 90th percentile.
    pub bearing_err_deg: [f64; 2],
    /// Over correctly classified TPOs with a truth distance: |d̂ − d| / d, median and p90.
    pub tpo_distance_rel_err: [f64; 2],
    pub samples: Vec<Sample>,
}

/// Median and 90th percentile (nearest rank); NaN for an empty set.
fn quantiles(mut v: Vec<f64>) -> [f64; 2] {
    if v.is_empty() {
        return [f64::NAN; 2];
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1];
    [at(0.5), at(0.9)]
}

/// Renders scene `index` (case `c`) as `opts.frames` frames into `out`: the camera drives at
/// `opts.velocity` and turns at `c.omega` (along the exact arc), one frame every `1 / c.fps` s,
/// and the last frame is taken at the scene's start pose. Sensor noise is drawn anew for every
/// frame.
pub fn render_sequence(c: &Case, calib: &Calibration, opts: &BenchOptions, index: usize, out: &mut Vec<Frame>) {
    out.clear();
    let dt = 1.0 / c.fps;
    let end = c.scene.start(calib);
    let renderer = Renderer::new(&c.scene.world, calib);
    let effects = Effects {
        noise_sigma: opts.noise,
        seed: opts.seed.wrapping_mul(7919).wrapping_add(index as u64),
        ..Effects::default()
    };
    let pose = |j: usize| {
        let frames_back = (opts.frames - 1 - j) as f64;
        if c.omega == 0.0 {
            let back = opts.velocity * dt * frames_back;
            Pose::new(end.x - back * end.yaw.cos(), end.y - back * end.yaw.sin(), end.yaw)
        } else {
            end.advance(opts.velocity, c.omega, -dt * frames_back)
        }
    };
    for j in 0..opts.frames {
        let mut image = LumaImage::default();
        renderer.render_frame(pose(j.saturating_sub(1)), pose(j), &effects, j as u64, &mut image);
        let t_ns = 1_000_000_000 + (j as f64 * dt * 1e9).round() as u64;
        out.push(Frame { seq: j as u64, t_ns, image });
    }
}

/// Renders the scene set at the size of `calib` and runs it through the pipeline of `cfg`.
/// `progress` is called after each scene.
pub fn run(
    cfg: &Config,
    calib: &Calibration,
    opts: &BenchOptions,
    mut progress: impl FnMut(usize, &Sample),
) -> Result<Report, BenchError> {
    let mut reports = run_each(std::slice::from_ref(cfg), calib, opts, |i, _, s| progress(i, s))?;
    Ok(reports.remove(0))
}

/// As [`run`], for several configurations (e.g. the two `offis.classifier`s) on the same
/// rendered frames: one report per configuration, in order. `progress(scene, config, sample)`
/// is called after each scene and configuration.
pub fn run_each(
    cfgs: &[Config],
    calib: &Calibration,
    opts: &BenchOptions,
    mut progress: impl FnMut(usize, usize, &Sample),
) -> Result<Vec<Report>, BenchError> {
    if opts.scenes == 0 {
        return Err(BenchError::Options("--scenes must be at least 1".into()));
    }
    if !(opts.velocity.is_finite() && opts.velocity > 0.0 && opts.fps[0] > 0.0 && opts.fps[1] >= opts.fps[0]) {
        return Err(BenchError::Options("velocity and frame rates must be positive".into()));
    }
    if !(opts.omega_max.is_finite() && opts.omega_max >= 0.0) {
        return Err(BenchError::Options("--omega-max must be zero or a positive turn rate, rad/s".into()));
    }
    if opts.frames < 2 {
        return Err(BenchError::Options("a scene needs at least 2 frames (one frame pair)".into()));
    }
    if cfgs.is_empty() {
        return Err(BenchError::Options("no configuration to run".into()));
    }
    let mut pipelines = Vec::with_capacity(cfgs.len());
    for cfg in cfgs {
        pipelines.push(Pipeline::new(cfg, calib.clone(), None)?);
    }
    let mut samples: Vec<Vec<Sample>> = cfgs.iter().map(|_| Vec::with_capacity(opts.scenes)).collect();
    let mut frames = Vec::new();
    for i in 0..opts.scenes {
        let c = case(opts.seed, i, opts);
        render_sequence(&c, calib, opts, i, &mut frames);
        let truth = GroundTruth::new(&c.scene.world, calib).frame(c.scene.start(calib));
        let odo = BodyVelocity::new(opts.velocity, c.omega);
        for (k, pipeline) in pipelines.iter_mut().enumerate() {
            // a new scene: nothing of the last one is remembered (a pair gap, as after a stop)
            pipeline.fail_safe();
            let step_err = |source| BenchError::Step { index: i, scene: c.label.clone(), source: Box::new(source) };
            let mut last = None;
            for frame in &frames {
                last = pipeline.step(frame.clone(), odo).map_err(step_err)?;
            }
            let out = last.expect("a sequence of at least two frames gives a step");
            let p: &Perception = &out.perception;
            let sample = Sample {
                index: i,
                label: c.label.clone(),
                truth: shape_of(truth.tpo.shape),
                predicted: p.tpo.shape,
                confidence: p.tpo.confidence,
                truth_tpo_m: truth.tpo.distance_m,
                tpo_m: p.tpo.distance_m,
                truth_obstacle: truth
                    .obstacle
                    .distance_m
                    .zip(truth.obstacle.bearing_rad)
                    .filter(|_| truth.obstacle.present),
                obstacle: p.obstacle.present.then_some((p.obstacle.distance_m, p.obstacle.bearing_rad)),
                features: pipeline.offis().attributes().features,
                profile: pipeline.offis().attributes().bins.iter().map(|b| b.point).collect(),
                obstacle_blocks: [
                    pipeline.offis().attributes().obstacle_blocks,
                    pipeline.offis().attributes().obstacle_cluster,
                ],
                model: pipeline.offis().attributes().shape_model,
                paper: pipeline.offis().attributes().paper,
            };
            progress(i, k, &sample);
            samples[k].push(sample);
        }
    }
    Ok(samples.into_iter().zip(cfgs).map(|(s, cfg)| report(opts, calib, cfg.offis.classifier, s)).collect())
}

fn report(opts: &BenchOptions, calib: &Calibration, classifier: ClassifierKind, samples: Vec<Sample>) -> Report {
    let mut confusion = [[0usize; 5]; 5];
    let (mut dist, mut bearing, mut tpo_err) = (Vec::new(), Vec::new(), Vec::new());
    let (mut obstacle_scenes, mut detected, mut clear, mut false_alarms) = (0, 0, 0, 0);
    for s in &samples {
        confusion[index(s.truth)][index(s.predicted)] += 1;
        if s.truth == s.predicted
            && let (Some(t), Some(d)) = (s.truth_tpo_m, s.tpo_m)
        {
            tpo_err.push((d - t).abs() / t);
        }
        match (s.truth_obstacle, s.obstacle) {
            (Some((td, tb)), Some((d, b))) => {
                obstacle_scenes += 1;
                detected += 1;
                if let Some(d) = d {
                    dist.push((d - td).abs() / td);
                }
                if let Some(b) = b {
                    bearing.push((b - tb).abs().to_degrees());
                }
            }
            (Some(_), None) => obstacle_scenes += 1,
            (None, o) => {
                clear += 1;
                false_alarms += usize::from(o.is_some());
            }
        }
    }
    let correct: usize = (0..5).map(|k| confusion[k][k]).sum();
    let frac = |a: usize, b: usize| if b == 0 { f64::NAN } else { a as f64 / b as f64 };
    Report {
        classifier: classifier.name(),
        scenes: samples.len(),
        seed: opts.seed,
        omega_max: opts.omega_max,
        width: calib.camera.width,
        height: calib.camera.height,
        confusion,
        tpo_accuracy: frac(correct, samples.len()),
        obstacle_scenes,
        detection_rate: frac(detected, obstacle_scenes),
        clear_scenes: clear,
        false_alarm_rate: frac(false_alarms, clear),
        distance_rel_err: quantiles(dist),
        bearing_err_deg: quantiles(bearing),
        tpo_distance_rel_err: quantiles(tpo_err),
        samples,
    }
}

impl Report {
    /// The human-readable summary (confusion matrix and error figures).
    pub fn table(&self) -> String {
        let mut s = format!(
            "OFFIS accuracy ({} classifier): {} scenes, seed {}, {}x{}, {}\n\nconfusion (rows = truth, columns = predicted):\n{:>10}",
            self.classifier,
            self.scenes,
            self.seed,
            self.width,
            self.height,
            match self.omega_max {
                0.0 => "driving straight".to_string(),
                w => format!("turning at up to ±{w} rad/s"),
            },
            ""
        );
        for shape in TpoShape::ALL {
            s.push_str(&format!("{:>9}", shape.name()));
        }
        s.push('\n');
        for (k, row) in self.confusion.iter().enumerate() {
            s.push_str(&format!("{:>10}", TpoShape::ALL[k].name()));
            for n in row {
                s.push_str(&format!("{n:>9}"));
            }
            s.push('\n');
        }
        let pct = |x: f64| format!("{:.1}%", 100.0 * x);
        s.push_str(&format!(
            "\nTPO accuracy: {} ({} of {})\n",
            pct(self.tpo_accuracy),
            (0..5).map(|k| self.confusion[k][k]).sum::<usize>(),
            self.scenes
        ));
        s.push_str(&format!(
            "TPO distance rel. error (correct class): median {}, p90 {}\n",
            pct(self.tpo_distance_rel_err[0]),
            pct(self.tpo_distance_rel_err[1])
        ));
        s.push_str(&format!(
            "obstacle detection: {} of {} scenes with a visible obstacle; false alarms: {} of {} scenes without\n",
            pct(self.detection_rate),
            self.obstacle_scenes,
            pct(self.false_alarm_rate),
            self.clear_scenes
        ));
        s.push_str(&format!(
            "obstacle distance rel. error: median {}, p90 {}\n",
            pct(self.distance_rel_err[0]),
            pct(self.distance_rel_err[1])
        ));
        s.push_str(&format!(
            "obstacle bearing error: median {:.2}°, p90 {:.2}°\n",
            self.bearing_err_deg[0], self.bearing_err_deg[1]
        ));
        s
    }
}

/// Two reports' tables side by side (same scenes, e.g. the two classifiers), left first.
pub fn side_by_side(left: &Report, right: &Report) -> String {
    let (a, b) = (left.table(), right.table());
    let width = a.lines().map(|l| l.chars().count()).max().unwrap_or(0) + 4;
    let (a, b): (Vec<&str>, Vec<&str>) = (a.lines().collect(), b.lines().collect());
    let mut s = String::new();
    for k in 0..a.len().max(b.len()) {
        let l = a.get(k).copied().unwrap_or("");
        let r = b.get(k).copied().unwrap_or("");
        let line = format!("{l}{:pad$}{r}", "", pad = width - l.chars().count());
        s.push_str(line.trim_end());
        s.push('\n');
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scene_set_is_deterministic_and_covers_every_class() {
        let opts = BenchOptions::default();
        let a: Vec<String> = (0..10).map(|i| case(3, i, &opts).label).collect();
        let b: Vec<String> = (0..10).map(|i| case(3, i, &opts).label).collect();
        assert_eq!(a, b);
        for (k, name) in ["wall", "corner", "door", "corridor", "empty"].iter().enumerate() {
            assert!(a[k].starts_with(name), "{a:?}");
        }
        assert!(a.iter().any(|l| l.contains('+')) && a.iter().any(|l| !l.contains('+')), "{a:?}");
        for i in 0..50 {
            let c = case(1, i, &opts);
            c.scene.world.validate(&c.label).unwrap();
        }
    }

    #[test]
    fn two_reports_print_side_by_side() {
        let opts = BenchOptions::default();
        let calib = Calibration::nominal_c310();
        let a = report(&opts, &calib, ClassifierKind::Flownav, Vec::new());
        let b = report(&opts, &calib, ClassifierKind::Paper, Vec::new());
        let both = side_by_side(&a, &b);
        let first = both.lines().next().unwrap();
        assert!(first.starts_with("OFFIS accuracy (flownav classifier)"), "{both}");
        assert!(first.contains("OFFIS accuracy (paper classifier)"), "{both}");
        assert_eq!(both.lines().count(), a.table().lines().count());
        assert_eq!(both.lines().filter(|l| l.matches("wall").count() == 2).count(), 2, "{both}");
    }

    #[test]
    fn quantiles_are_nearest_rank() {
        assert_eq!(quantiles((1..=10).map(f64::from).collect()), [5.0, 9.0]);
        assert!(quantiles(Vec::new())[0].is_nan());
    }
}
