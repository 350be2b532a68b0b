//! Situation determination (paper §5, Fig. 11–13): a rough classifier decides the object group
//! (flat: wall or door; bent: corner or corridor; empty), three fine classifiers decide the
//! shape inside each group, and the TPO decision takes the maximum over the classes of
//! `min(group degree, shape degree)`; that value is the reported confidence.
//!
//! All four are Mamdani rule bases (`rules/offis/*.toml`, evaluated with [`crate::fuzzy`]),
//! built into the binary and overridable with `offis.rules_dir`. They are loaded once; an
//! evaluation allocates nothing.

use super::features::Features;
use crate::fuzzy::{Evaluation, FuzzyError, FuzzySystem, InputId, OutputTermId};
use crate::perception::TpoShape;
use std::path::{Path, PathBuf};

/// The shipped rule bases, compiled in.
const BUILTIN: [(&str, &str); 4] = [
    ("rough.toml", include_str!("../../rules/offis/rough.toml")),
    ("fine_flat.toml", include_str!("../../rules/offis/fine_flat.toml")),
    ("fine_bent.toml", include_str!("../../rules/offis/fine_bent.toml")),
    ("fine_empty.toml", include_str!("../../rules/offis/fine_empty.toml")),
];

/// Why the classifiers could not be loaded or evaluated.
#[derive(Debug, thiserror::Error)]
pub enum ClassifyError {
    #[error("OFFIS rule base {}: {source}", path.display())]
    Rules {
        path: PathBuf,
        #[source]
        source: FuzzyError,
    },
    #[error(
        "OFFIS rule base {origin}: input '{name}' is not a feature OFFIS computes (known: {known}); see docs/offis.md"
    )]
    UnknownInput { origin: String, name: String, known: String },
    #[error("OFFIS rule base {origin} lacks {what} '{name}', which OFFIS reads; see docs/offis.md")]
    Missing { origin: String, what: &'static str, name: String },
    #[error("OFFIS classifier evaluation failed: {0}")]
    Evaluate(#[from] FuzzyError),
}

/// The feature names the rule bases may use as inputs.
pub const FEATURES: [&str; 10] = [
    "near_frac",
    "planes",
    "pair_angle_deg",
    "side_angle_deg",
    "opposite",
    "front_m",
    "open_ahead_m",
    "gap_m",
    "meet_m",
    "hidden_partner",
];

fn feature(f: &Features, k: usize) -> f64 {
    match k {
        0 => f.near_frac,
        1 => f.planes,
        2 => f.pair_angle_deg,
        3 => f.side_angle_deg,
        4 => f.opposite,
        5 => f.front_m,
        6 => f.open_ahead_m,
        7 => f.gap_m,
        8 => f.meet_m,
        _ => f.hidden_partner,
    }
}

/// One loaded rule base: which feature feeds each input, and its buffers.
#[derive(Clone, Debug)]
struct Base {
    sys: FuzzySystem,
    /// `(input slot, feature index)`.
    feed: Vec<(InputId, usize)>,
    buf: Vec<f64>,
    ev: Evaluation,
}

impl Base {
    fn new(sys: FuzzySystem) -> Result<Self, ClassifyError> {
        let mut feed = Vec::new();
        for v in sys.inputs() {
            let k = FEATURES.iter().position(|f| *f == v.name).ok_or_else(|| ClassifyError::UnknownInput {
                origin: sys.origin().into(),
                name: v.name.clone(),
                known: FEATURES.join(", "),
            })?;
            feed.push((sys.input(&v.name)?, k));
        }
        Ok(Self { buf: vec![0.0; sys.inputs().len()], ev: sys.evaluation(), sys, feed })
    }

    fn term(&self, output: &str, term: &str) -> Result<OutputTermId, ClassifyError> {
        self.sys.output_term(output, term).map_err(|_| ClassifyError::Missing {
            origin: self.sys.origin().into(),
            what: "output term",
            name: format!("{output} is {term}"),
        })
    }

    fn eval(&mut self, f: &Features) -> Result<&Evaluation, ClassifyError> {
        for &(id, k) in &self.feed {
            self.buf[id.0] = feature(f, k);
        }
        self.sys.evaluate_into(&self.buf, &mut self.ev)?;
        Ok(&self.ev)
    }
}

/// Degrees of one classification, for logs and the benchmark.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Decision {
    pub shape: TpoShape,
    pub confidence: f64,
    /// Group degrees: flat, bent, empty.
    pub groups: [f64; 3],
    /// Class degrees `min(group, shape)` in [`TpoShape::ALL`] order.
    pub classes: [f64; 5],
}

/// The four rule bases (Fig. 11) and the TPO decision.
#[derive(Clone, Debug)]
pub struct Classifier {
    rough: Base,
    flat: Base,
    bent: Base,
    empty: Base,
    /// Output terms: rough flat/bent/empty; flat wall/door/none; bent corner/corridor/none; empty none.
    groups: [OutputTermId; 3],
    flat_terms: [OutputTermId; 3],
    bent_terms: [OutputTermId; 3],
    empty_term: OutputTermId,
}

impl Classifier {
    /// The built-in rule bases (`rules/offis/` at build time).
    pub fn builtin() -> Result<Self, ClassifyError> {
        Self::load(None)
    }

    /// The rule bases from `dir` (`rough.toml`, `fine_flat.toml`, `fine_bent.toml`,
    /// `fine_empty.toml`), or the built-in ones when `dir` is `None`.
    pub fn load(dir: Option<&Path>) -> Result<Self, ClassifyError> {
        let read = |(name, text): (&str, &str)| match dir {
            Some(dir) => {
                let path = dir.join(name);
                FuzzySystem::from_file(&path).map_err(|source| ClassifyError::Rules { path, source })
            }
            None => {
                let origin = format!("(built-in) rules/offis/{name}");
                FuzzySystem::from_toml_str(text, &origin)
                    .map_err(|source| ClassifyError::Rules { path: PathBuf::from(origin), source })
            }
        };
        let [r, f, b, e] = BUILTIN.map(read);
        let (rough, flat, bent, empty) = (Base::new(r?)?, Base::new(f?)?, Base::new(b?)?, Base::new(e?)?);
        Ok(Self {
            groups: [rough.term("group", "flat")?, rough.term("group", "bent")?, rough.term("group", "empty")?],
            flat_terms: [flat.term("shape", "wall")?, flat.term("shape", "door")?, flat.term("shape", "none")?],
            bent_terms: [bent.term("shape", "corner")?, bent.term("shape", "corridor")?, bent.term("shape", "none")?],
            empty_term: empty.term("shape", "none")?,
            rough,
            flat,
            bent,
            empty,
        })
    }

    /// The TPO decision for `f`: the class with the largest `min(group, shape)` degree (ties
    /// go to the first in wall, corner, door, corridor, none order); no rule firing means
    /// `none` with confidence 0.
    pub fn classify(&mut self, f: &Features) -> Result<Decision, ClassifyError> {
        let ev = self.rough.eval(f)?;
        let groups = self.groups.map(|t| ev.degree(t));
        let ev = self.flat.eval(f)?;
        let [wall, door, none_flat] = self.flat_terms.map(|t| ev.degree(t));
        let ev = self.bent.eval(f)?;
        let [corner, corridor, none_bent] = self.bent_terms.map(|t| ev.degree(t));
        let none_empty = self.empty.eval(f)?.degree(self.empty_term);
        let [g_flat, g_bent, g_empty] = groups;
        let classes = [
            g_flat.min(wall),
            g_bent.min(corner),
            g_flat.min(door),
            g_bent.min(corridor),
            g_empty.min(none_empty).max(g_flat.min(none_flat)).max(g_bent.min(none_bent)),
        ];
        let best = decide(&classes);
        Ok(Decision { shape: TpoShape::ALL[best], confidence: classes[best], groups, classes })
    }
}

/// The TPO decision by maximum over class memberships in [`TpoShape::ALL`] order (wall, corner,
/// door, corridor, none): the index of the largest, ties to the first; `none` (4) when no class
/// has any membership.
pub(crate) fn decide(classes: &[f64; 5]) -> usize {
    let mut best = 4;
    for k in 0..4 {
        if classes[k] > classes[best] || (classes[k] == classes[best] && k < best && classes[k] > 0.0) {
            best = k;
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    fn f() -> Features {
        Features {
            near_frac: 1.0,
            planes: 1.0,
            side_angle_deg: 90.0,
            front_m: 3.0,
            open_ahead_m: 3.0,
            ..Default::default()
        }
    }

    #[test]
    fn the_shipped_rules_decide_each_class() {
        let mut c = Classifier::builtin().unwrap();
        assert_eq!(c.classify(&f()).unwrap().shape, TpoShape::Wall);
        let door = Features { gap_m: 1.0, open_ahead_m: 6.0, ..f() };
        assert_eq!(c.classify(&door).unwrap().shape, TpoShape::Door);
        let corner = Features { planes: 2.0, pair_angle_deg: 90.0, side_angle_deg: 45.0, ..f() };
        assert_eq!(c.classify(&corner).unwrap().shape, TpoShape::Corner);
        let corridor = Features {
            planes: 2.0,
            side_angle_deg: 3.0,
            opposite: 1.0,
            front_m: 8.0,
            open_ahead_m: 8.0,
            ..Default::default()
        };
        let d = c.classify(&Features { near_frac: 0.8, ..corridor }).unwrap();
        assert_eq!((d.shape, d.confidence), (TpoShape::Corridor, 1.0));
        let d = c.classify(&Features { side_angle_deg: 90.0, ..Default::default() }).unwrap();
        assert_eq!((d.shape, d.confidence), (TpoShape::None, 1.0));
        let far = Features { front_m: 7.0, ..f() };
        assert_eq!(c.classify(&far).unwrap().shape, TpoShape::None);
    }

    #[test]
    fn a_rules_dir_is_loaded_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        for (name, text) in BUILTIN {
            std::fs::write(dir.path().join(name), text).unwrap();
        }
        Classifier::load(Some(dir.path())).unwrap();
        let bad = BUILTIN[1].1.replace("gap_m", "gap_width");
        std::fs::write(dir.path().join("fine_flat.toml"), bad).unwrap();
        let e = Classifier::load(Some(dir.path())).unwrap_err().to_string();
        assert!(e.contains("gap_width") && e.contains("fine_flat.toml"), "{e}");
        std::fs::remove_file(dir.path().join("rough.toml")).unwrap();
        let e = Classifier::load(Some(dir.path())).unwrap_err().to_string();
        assert!(e.contains("rough.toml"), "{e}");
    }
}
