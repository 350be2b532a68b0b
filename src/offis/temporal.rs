//! Temporal filtering of the TPO decision over the last frame pairs while the robot drives.
//!
//! One frame pair's depth is noisy (1–3 cm of travel between the frames), and the class
//! memberships of §5 flicker from pair to pair: on the benchmark's tuning scenes the single-pair
//! decision of consecutive steps of the same scene is right 90–98 % of the time, but not always
//! on the same steps. The robot sees the same TPO for seconds, so the decision reported is
//! taken over the last few steps: the class memberships `min(group, shape)` of each step
//! (before the maximum, paper Fig. 11) are averaged with weights that fall geometrically with
//! the step's age, and the TPO decision by maximum (the paper's) is taken on the average. This
//! is an exponentially weighted moving average over a bounded window (the fuzzy analogue of
//! accumulating evidence per class, as in a discrete Bayes filter with a static state and
//! forgetting); it needs no geometry, so it costs nothing next to the plane fit.
//!
//! Evidence is only valid for the view it was taken in. A step's memberships are forgotten when
//! the robot has turned by more than [`TemporalParams::max_turn_rad`] since (the TPO in view
//! changes with the heading, and turns are where odometry is least trusted), when they are
//! older than [`TemporalParams::max_age_s`], or after a gap between frames longer than that
//! (a stall, a restart: [`ClassFilter::advance`]); [`ClassFilter::reset`] forgets everything
//! (the pipeline's fail-safe). Steps without translation measure nothing and add nothing.
//!
//! Pure and deterministic: the ages come from the frame intervals and the turns from the
//! odometry passed in, never from a clock; the window is a fixed-capacity ring (no allocation
//! per step).

use super::classify::Decision;
use crate::perception::TpoShape;
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

/// The `[offis.temporal]` config table.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TemporalParams {
    /// Steps averaged, the current one included (1 = this frame pair only, no filtering).
    pub window: usize,
    /// Weight of a step relative to the next newer one, in (0, 1].
    pub decay: f64,
    /// A step is forgotten once the robot has turned more than this since it, rad.
    pub max_turn_rad: f64,
    /// ... or once it is older than this, s (also the longest gap between frames bridged).
    pub max_age_s: f64,
    /// A pair adds to the window only when its travel times the focal length reaches this,
    /// pixels (the shift of a point 1 m away across the view: the baseline in the units of the
    /// matching noise, so the same at every resolution); a shorter pair reports the window's
    /// decision, as a step without translation does. 0: every translating pair counts.
    pub min_baseline_px: f64,
    /// A profile bin that a pair leaves empty takes the newest envelope point of an earlier
    /// pair that the robot's motion has moved into it ([`super::carry`]), for at most this
    /// travel, m (0: off) ...
    pub carry_m: f64,
    /// ... this turn, rad ...
    pub carry_turn_rad: f64,
    /// ... and this time, s.
    pub carry_age_s: f64,
    /// The weight of the window's `none` against the TPO classes when it decides, in (0, 1]
    /// (1: the largest mean membership wins).
    pub none_weight: f64,
}

impl Default for TemporalParams {
    fn default() -> Self {
        Self {
            window: 8,
            decay: 0.8,
            max_turn_rad: 0.25,
            max_age_s: 1.0,
            min_baseline_px: 8.0,
            carry_m: 0.6,
            carry_turn_rad: 0.8,
            carry_age_s: 3.0,
            none_weight: 0.4,
        }
    }
}

/// The largest window accepted (the ring is allocated once at this size or less).
pub const MAX_WINDOW: usize = 64;

/// The robot's motion since the previous step, from the odometry: turn, rad, the frame
/// interval, s, and the forward travel, m.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Motion {
    pub yaw_rad: f64,
    pub dt: f64,
    pub forward_m: f64,
}

/// The TPO decision over the window.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Filtered {
    pub shape: TpoShape,
    /// The winning class's averaged membership.
    pub confidence: f64,
    /// Averaged class memberships in [`TpoShape::ALL`] order.
    pub classes: [f64; 5],
    /// Steps averaged (0 when the last step measured nothing).
    pub steps: usize,
}

#[derive(Clone, Copy, Debug)]
struct Entry {
    classes: [f64; 5],
    /// Turned since this step (absolute sum), rad, and its age, s.
    turned_rad: f64,
    age_s: f64,
}

/// The filter's state: the class memberships of the last steps still valid, newest last.
#[derive(Clone, Debug)]
pub struct ClassFilter {
    params: TemporalParams,
    entries: VecDeque<Entry>,
}

impl ClassFilter {
    pub fn new(params: TemporalParams) -> Self {
        let window = params.window.clamp(1, MAX_WINDOW);
        Self { params: TemporalParams { window, ..params }, entries: VecDeque::with_capacity(window) }
    }

    /// Forgets every step.
    pub fn reset(&mut self) {
        self.entries.clear();
    }

    /// Steps held.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The robot moved by `m` since the last step: ages the steps held and forgets those turned
    /// or aged past the limits; a gap (or a motion that is not finite) forgets all.
    pub fn advance(&mut self, m: Motion) {
        let p = self.params;
        if !(m.dt.is_finite() && m.yaw_rad.is_finite() && m.dt >= 0.0) || m.dt > p.max_age_s {
            self.entries.clear();
            return;
        }
        for e in &mut self.entries {
            e.turned_rad += m.yaw_rad.abs();
            e.age_s += m.dt;
        }
        // the oldest are the most turned and the oldest: drop from the front
        while self.entries.front().is_some_and(|e| e.turned_rad > p.max_turn_rad || e.age_s > p.max_age_s) {
            self.entries.pop_front();
        }
    }

    /// Adds this step's decision and returns the decision over the window: the class with the
    /// largest weighted mean membership (weights `decay^age in steps`), ties to the first in
    /// wall, corner, door, corridor, none order as in [`super::classify::Classifier::classify`];
    /// `none` with confidence 0 when no class has any membership.
    pub fn push(&mut self, d: &Decision) -> Filtered {
        if self.entries.len() == self.params.window {
            self.entries.pop_front();
        }
        self.entries.push_back(Entry { classes: d.classes, turned_rad: 0.0, age_s: 0.0 });
        self.held()
    }

    /// The decision over the steps still in the window, without adding one: for a step that
    /// measures nothing (no translation), the evidence of the view the robot has not turned
    /// away from yet still holds; `none` with 0 steps once it has all been forgotten.
    pub fn held(&self) -> Filtered {
        if self.entries.is_empty() {
            return Filtered::default();
        }
        let (mut sum, mut weight, mut w) = ([0.0; 5], 0.0, 1.0);
        for e in self.entries.iter().rev() {
            for (s, c) in sum.iter_mut().zip(e.classes) {
                *s += w * c;
            }
            weight += w;
            w *= self.params.decay;
        }
        let classes = sum.map(|s| s / weight);
        let mut weighed = classes;
        weighed[4] *= self.params.none_weight;
        let best = super::classify::decide(&weighed);
        Filtered { shape: TpoShape::ALL[best], confidence: classes[best], classes, steps: self.entries.len() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Where `shape`'s membership is in a decision's `classes`.
    fn class_index(shape: TpoShape) -> usize {
        TpoShape::ALL.iter().position(|&s| s == shape).unwrap()
    }

    /// A decision whose memberships are `m` for `shape` and `rest` for every other class.
    fn evidence(shape: TpoShape, m: f64, rest: f64) -> Decision {
        let mut classes = [rest; 5];
        classes[class_index(shape)] = m;
        Decision { shape, confidence: m, groups: [0.0; 3], classes }
    }

    const FRAME: Motion = Motion { yaw_rad: 0.0, dt: 1.0 / 30.0, forward_m: 0.0 };

    fn filter() -> ClassFilter {
        ClassFilter::new(TemporalParams::default())
    }

    /// `n` frames of driving straight on, each pair with the same evidence.
    fn drive(f: &mut ClassFilter, n: usize, shape: TpoShape, m: f64) {
        for _ in 0..n {
            f.advance(FRAME);
            f.push(&evidence(shape, m, 0.0));
        }
    }

    #[test]
    fn a_step_without_translation_holds_the_views_evidence_until_the_robot_turns_away() {
        let mut f = filter();
        drive(&mut f, 5, TpoShape::Corridor, 0.9);
        // a pause, then a turn on the spot: nothing measured, the corridor still in view
        f.advance(FRAME);
        let held = f.held();
        assert_eq!((held.shape, held.steps), (TpoShape::Corridor, 5));
        assert!((held.confidence - 0.9).abs() < 1e-12);
        f.advance(Motion { yaw_rad: 0.2, dt: 1.0 / 30.0, forward_m: 0.0 });
        assert_eq!(f.held().shape, TpoShape::Corridor, "0.2 rad is inside max_turn_rad");
        f.advance(Motion { yaw_rad: -0.1, dt: 1.0 / 30.0, forward_m: 0.0 });
        assert_eq!(f.held(), Filtered::default(), "0.3 rad turned in all: the corridor is forgotten");
        // standing still: forgotten with age
        drive(&mut f, 3, TpoShape::Wall, 0.8);
        for _ in 0..29 {
            f.advance(FRAME);
        }
        assert_eq!(f.held().shape, TpoShape::Wall);
        for _ in 0..2 {
            f.advance(FRAME);
        }
        assert_eq!(f.held().steps, 0, "older than max_age_s");
    }

    #[test]
    fn one_step_is_the_single_pair_decision() {
        let mut f = filter();
        let d = Decision {
            shape: TpoShape::Door,
            confidence: 0.7,
            groups: [0.9, 0.1, 0.0],
            classes: [0.3, 0.1, 0.7, 0.0, 0.2],
        };
        let out = f.push(&d);
        assert_eq!((out.shape, out.confidence, out.classes, out.steps), (TpoShape::Door, 0.7, d.classes, 1));
    }

    #[test]
    fn none_weighs_less_against_a_tpo_by_none_weight() {
        // pairs alternating between a corridor named and one fitted to no class
        let steps = [evidence(TpoShape::Corridor, 0.7, 0.0), evidence(TpoShape::None, 1.0, 0.0)];
        for (none_weight, expect) in [(1.0, TpoShape::None), (0.5, TpoShape::Corridor)] {
            let mut f = ClassFilter::new(TemporalParams { none_weight, ..TemporalParams::default() });
            let mut out = Filtered::default();
            for d in steps.iter().cycle().take(8) {
                f.advance(FRAME);
                out = f.push(d);
            }
            // the last step is a `none`: means over decay 0.8, none 0.56, corridor 0.31
            assert_eq!(out.shape, expect, "none_weight {none_weight}: {out:?}");
            let weights: Vec<f64> = (0..8).map(|age| 0.8f64.powi(age)).collect();
            let corridor = 0.7 * weights.iter().skip(1).step_by(2).sum::<f64>() / weights.iter().sum::<f64>();
            assert!((out.classes[class_index(TpoShape::Corridor)] - corridor).abs() < 1e-12, "{out:?}");
            assert_eq!(out.confidence, out.classes[class_index(expect)]);
        }
    }

    #[test]
    fn a_flicker_in_single_pair_evidence_does_not_flip_the_class() {
        let mut f = filter();
        for _ in 0..5 {
            f.advance(FRAME);
            assert_eq!(f.push(&evidence(TpoShape::Door, 0.8, 0.1)).shape, TpoShape::Door);
        }
        // a person hides the opening in one frame pair: that pair alone says wall, firmly
        f.advance(FRAME);
        let out = f.push(&evidence(TpoShape::Wall, 1.0, 0.0));
        assert_eq!(out.shape, TpoShape::Door, "{out:?}");
        assert!(out.confidence < 0.8, "the flicker lowers the confidence: {out:?}");
        f.advance(FRAME);
        assert_eq!(f.push(&evidence(TpoShape::Door, 0.8, 0.1)).shape, TpoShape::Door);
    }

    #[test]
    fn lasting_evidence_takes_over_within_the_window() {
        let mut f = filter();
        drive(&mut f, 8, TpoShape::Corridor, 0.9);
        // the robot reaches the corridor's end wall: consistent new evidence wins in a few steps
        let steps = (1..=8)
            .find(|_| {
                f.advance(FRAME);
                f.push(&evidence(TpoShape::Wall, 0.9, 0.0)).shape == TpoShape::Wall
            })
            .expect("the wall wins within the window");
        assert!(steps <= 3, "took {steps} steps");
    }

    #[test]
    fn a_new_scene_after_a_turn_is_not_held_back_by_stale_evidence() {
        let mut f = filter();
        drive(&mut f, 8, TpoShape::Corridor, 1.0);
        // turning on the spot at 1 rad/s for 0.3 s: the corridor's memberships are forgotten
        for _ in 0..9 {
            f.advance(Motion { yaw_rad: 1.0 / 30.0, dt: 1.0 / 30.0, forward_m: 0.0 });
        }
        assert!(f.is_empty());
        let out = f.push(&evidence(TpoShape::Wall, 0.4, 0.0));
        assert_eq!((out.shape, out.confidence, out.steps), (TpoShape::Wall, 0.4, 1));
    }

    #[test]
    fn slow_turns_keep_the_evidence_until_the_limit_and_gaps_forget_it() {
        let mut f = filter();
        f.push(&evidence(TpoShape::Corner, 1.0, 0.0));
        // 0.2 rad in total (under the 0.25 rad limit), 0.5 s (under the 1 s limit)
        for _ in 0..5 {
            f.advance(Motion { yaw_rad: -0.04, dt: 0.1, forward_m: 0.0 });
        }
        assert_eq!(f.len(), 1);
        f.advance(Motion { yaw_rad: -0.1, dt: 0.1, forward_m: 0.0 });
        assert!(f.is_empty(), "turned 0.3 rad since");
        f.push(&evidence(TpoShape::Corner, 1.0, 0.0));
        f.advance(Motion { yaw_rad: 0.0, dt: 1.5, forward_m: 0.0 });
        assert!(f.is_empty(), "a 1.5 s gap");
        f.push(&evidence(TpoShape::Corner, 1.0, 0.0));
        f.advance(Motion { yaw_rad: f64::NAN, dt: 0.03, forward_m: 0.0 });
        assert!(f.is_empty(), "unknown motion");
    }

    #[test]
    fn the_window_is_bounded_and_recent_steps_weigh_more() {
        let mut f = ClassFilter::new(TemporalParams { window: 3, ..TemporalParams::default() });
        drive(&mut f, 10, TpoShape::Wall, 1.0);
        assert_eq!(f.len(), 3);
        // two old wall steps (weights 0.8², 0.8) against one new corner step (weight 1) ...
        f.advance(FRAME);
        f.push(&evidence(TpoShape::Corner, 1.0, 0.0));
        f.advance(FRAME);
        // ... then two corner steps against one wall step (weight 0.64): corner
        let out = f.push(&evidence(TpoShape::Corner, 1.0, 0.0));
        assert_eq!(out.shape, TpoShape::Corner);
        let expect = 1.8 / (1.0 + 0.8 + 0.64);
        assert!((out.confidence - expect).abs() < 1e-12, "{out:?}");
        // no membership at all: none with confidence 0
        let mut f = filter();
        let out = f.push(&Decision::default());
        assert_eq!((out.shape, out.confidence), (TpoShape::None, 0.0));
    }
}
