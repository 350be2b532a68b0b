//! Situation determination (paper §5, Fig. 11–13): a rough classifier decides the object group,
//! three fine classifiers decide the shape inside each group, and the TPO decision takes the
//! maximum over the classes of `min(group degree, shape degree)`; that value is the reported
//! confidence.
//!
//! Two sets of rule bases share this machinery ([`ClassifierKind`], `offis.classifier`):
//! - `flownav` (default): inputs are the [`Features`] of the plane fit to the per-block depths;
//!   groups flat (wall, door), bent (corner, corridor), empty (none).
//! - `paper`: inputs are the [`PaperFeatures`] read off the paper's rough and fine structures,
//!   plane matrices and tilts (§4, eq. 4–12); groups plane (one surface across the view: wall,
//!   door, corner), sides (eq. 11's pattern: door, corner, corridor), empty (none).
//!
//! All rule bases are Mamdani (`rules/offis/*.toml`, evaluated with [`crate::fuzzy`]), built into
//! the binary and overridable with `offis.rules_dir`. They are loaded once; an evaluation
//! allocates nothing. A fine classifier's output `shape` has terms named after TPO shapes
//! (`wall`, `corner`, `door`, `corridor`, `none`); each names the class it supports.

use super::features::Features;
use super::paper::PaperFeatures;
use crate::fuzzy::{Evaluation, FuzzyError, FuzzySystem, InputId, OutputTermId};
use crate::perception::TpoShape;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Which recognition path decides the TPO (`offis.classifier`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ClassifierKind {
    /// Features of wall lines fitted to the per-block depths (docs/offis.md, *Features*).
    #[default]
    Flownav,
    /// The paper's rough and fine structures, plane matrices and tilts (§4–5).
    Paper,
}

impl ClassifierKind {
    pub fn name(self) -> &'static str {
        match self {
            ClassifierKind::Flownav => "flownav",
            ClassifierKind::Paper => "paper",
        }
    }

    /// The rule base files: rough first, then the fine one of each group in `groups()` order.
    fn files(self) -> [(&'static str, &'static str); 4] {
        match self {
            ClassifierKind::Flownav => BUILTIN,
            ClassifierKind::Paper => BUILTIN_PAPER,
        }
    }

    /// The rough classifier's output terms (`group is ...`), in the order of the fine files.
    fn groups(self) -> [&'static str; 3] {
        match self {
            ClassifierKind::Flownav => ["flat", "bent", "empty"],
            ClassifierKind::Paper => ["plane", "sides", "empty"],
        }
    }

    /// The inputs its rule bases may read.
    pub fn features(self) -> &'static [&'static str] {
        match self {
            ClassifierKind::Flownav => &FEATURES,
            ClassifierKind::Paper => &super::paper::FEATURES,
        }
    }
}

impl std::str::FromStr for ClassifierKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "flownav" => Ok(ClassifierKind::Flownav),
            "paper" => Ok(ClassifierKind::Paper),
            _ => Err(format!("unknown classifier '{s}' (known: flownav, paper)")),
        }
    }
}

/// The shipped rule bases, compiled in.
const BUILTIN: [(&str, &str); 4] = [
    ("rough.toml", include_str!("../../rules/offis/rough.toml")),
    ("fine_flat.toml", include_str!("../../rules/offis/fine_flat.toml")),
    ("fine_bent.toml", include_str!("../../rules/offis/fine_bent.toml")),
    ("fine_empty.toml", include_str!("../../rules/offis/fine_empty.toml")),
];

/// The paper's rule bases (§5, Fig. 11), reconstructed from the structures of §4.
const BUILTIN_PAPER: [(&str, &str); 4] = [
    ("paper_rough.toml", include_str!("../../rules/offis/paper_rough.toml")),
    ("paper_fine_plane.toml", include_str!("../../rules/offis/paper_fine_plane.toml")),
    ("paper_fine_sides.toml", include_str!("../../rules/offis/paper_fine_sides.toml")),
    ("paper_fine_empty.toml", include_str!("../../rules/offis/paper_fine_empty.toml")),
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
    #[error(
        "OFFIS rule base {origin}: output term 'shape is {name}' is not a TPO shape (known: wall, corner, door, corridor, none)"
    )]
    UnknownShape { origin: String, name: String },
    #[error("OFFIS classifier evaluation failed: {0}")]
    Evaluate(#[from] FuzzyError),
}

/// The feature names the flownav rule bases may use as inputs.
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

impl Features {
    /// The values in [`FEATURES`] order.
    pub fn values(&self) -> [f64; 10] {
        [
            self.near_frac,
            self.planes,
            self.pair_angle_deg,
            self.side_angle_deg,
            self.opposite,
            self.front_m,
            self.open_ahead_m,
            self.gap_m,
            self.meet_m,
            self.hidden_partner,
        ]
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
    fn new(sys: FuzzySystem, known: &[&str]) -> Result<Self, ClassifyError> {
        let mut feed = Vec::new();
        for v in sys.inputs() {
            let k = known.iter().position(|f| *f == v.name).ok_or_else(|| ClassifyError::UnknownInput {
                origin: sys.origin().into(),
                name: v.name.clone(),
                known: known.join(", "),
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

    /// Every term of output `shape` with the class it names.
    fn shapes(&self) -> Result<Vec<(OutputTermId, usize)>, ClassifyError> {
        let missing =
            || ClassifyError::Missing { origin: self.sys.origin().into(), what: "output", name: "shape".into() };
        let out = self.sys.outputs().iter().find(|o| o.variable.name == "shape").ok_or_else(missing)?;
        out.variable
            .terms
            .iter()
            .map(|t| {
                let k = TpoShape::ALL.iter().position(|s| s.name() == t.name).ok_or_else(|| {
                    ClassifyError::UnknownShape { origin: self.sys.origin().into(), name: t.name.clone() }
                })?;
                Ok((self.term("shape", &t.name)?, k))
            })
            .collect()
    }

    fn eval(&mut self, values: &[f64]) -> Result<&Evaluation, ClassifyError> {
        for &(id, k) in &self.feed {
            self.buf[id.0] = values[k];
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
    /// Group degrees, in the rough classifier's order (flownav: flat, bent, empty; paper:
    /// plane, sides, empty).
    pub groups: [f64; 3],
    /// Class degrees `min(group, shape)` in [`TpoShape::ALL`] order.
    pub classes: [f64; 5],
}

/// The four rule bases (Fig. 11) and the TPO decision.
#[derive(Clone, Debug)]
pub struct Classifier {
    kind: ClassifierKind,
    rough: Base,
    /// The fine classifier of each group, with its output terms and the class each names.
    fine: [(Base, Vec<(OutputTermId, usize)>); 3],
    /// Output terms of the rough classifier, one per group.
    groups: [OutputTermId; 3],
}

impl Classifier {
    /// The built-in flownav rule bases (`rules/offis/` at build time).
    pub fn builtin() -> Result<Self, ClassifyError> {
        Self::load(None)
    }

    /// The flownav rule bases from `dir` (`rough.toml`, `fine_flat.toml`, `fine_bent.toml`,
    /// `fine_empty.toml`), or the built-in ones when `dir` is `None`.
    pub fn load(dir: Option<&Path>) -> Result<Self, ClassifyError> {
        Self::load_kind(ClassifierKind::Flownav, dir)
    }

    /// The rule bases of `kind` from `dir`, or the built-in ones when `dir` is `None`
    /// (paper: `paper_rough.toml`, `paper_fine_plane.toml`, `paper_fine_sides.toml`,
    /// `paper_fine_empty.toml`).
    pub fn load_kind(kind: ClassifierKind, dir: Option<&Path>) -> Result<Self, ClassifyError> {
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
        let known = kind.features();
        let [r, a, b, c] = kind.files().map(read);
        let rough = Base::new(r?, known)?;
        let fine = |sys: Result<FuzzySystem, ClassifyError>| -> Result<_, ClassifyError> {
            let base = Base::new(sys?, known)?;
            let shapes = base.shapes()?;
            Ok((base, shapes))
        };
        let fine = [fine(a)?, fine(b)?, fine(c)?];
        let g = kind.groups();
        Ok(Self {
            kind,
            groups: [rough.term("group", g[0])?, rough.term("group", g[1])?, rough.term("group", g[2])?],
            rough,
            fine,
        })
    }

    pub fn kind(&self) -> ClassifierKind {
        self.kind
    }

    /// The flownav TPO decision for `f` (see [`Classifier::classify_values`]).
    pub fn classify(&mut self, f: &Features) -> Result<Decision, ClassifyError> {
        self.classify_values(&f.values())
    }

    /// The paper's TPO decision for `f` (see [`Classifier::classify_values`]).
    pub fn classify_paper(&mut self, f: &PaperFeatures) -> Result<Decision, ClassifyError> {
        self.classify_values(&f.values())
    }

    /// The TPO decision for the inputs `values` (in [`ClassifierKind::features`] order): each
    /// class's degree is the maximum over the groups of `min(group degree, the degree the
    /// group's fine classifier gives the class)`, and the class with the largest degree wins
    /// (ties go to the first in wall, corner, door, corridor, none order); no rule firing means
    /// `none` with confidence 0.
    pub fn classify_values(&mut self, values: &[f64]) -> Result<Decision, ClassifyError> {
        let ev = self.rough.eval(values)?;
        let groups = self.groups.map(|t| ev.degree(t));
        let mut classes = [0.0f64; 5];
        for ((base, shapes), g) in self.fine.iter_mut().zip(groups) {
            let ev = base.eval(values)?;
            for &(t, k) in shapes.iter() {
                classes[k] = classes[k].max(g.min(ev.degree(t)));
            }
        }
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
