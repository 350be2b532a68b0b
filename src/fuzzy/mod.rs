//! Mamdani fuzzy inference (paper §5: the OFFIS situation classifiers; MOFIS collision
//! avoidance and fusion build on it too).
//!
//! A [`FuzzySystem`] is loaded from a TOML rule file (format in `docs/fuzzy.md`), validated
//! with errors that name the file, line, rule, variable and term, and compiled: names become
//! indices and rules become small postfix programs, so [`FuzzySystem::evaluate_into`] does no
//! string work and no allocation.
//!
//! Semantics: inputs are clamped to their universe (NaN is an error); AND = min, OR = max,
//! NOT = 1 − x; a rule's strength is `weight × antecedent`; min implication (each output term
//! is clipped at its *cut level*, the max strength over the rules that conclude it); max
//! aggregation; centroid defuzzification, exact for triangle/trapezoid outputs and sampled
//! otherwise. When no rule fires for an output (all its cut levels are 0), its value is its
//! declared `default` (the middle of its range if not declared) and [`Evaluation::fired`] is
//! false; the output is never NaN.
//!
//! ```
//! use flownav::fuzzy::FuzzySystem;
//! let sys = FuzzySystem::from_toml_str(r#"
//!     [system]
//!     name = "demo"
//!     [[input]]
//!     name = "x"
//!     range = [0, 10]
//!     terms = { low = { tri = [0, 0, 10] }, high = { tri = [0, 10, 10] } }
//!     [[output]]
//!     name = "z"
//!     range = [0, 1]
//!     terms = { off = { tri = [0, 0, 1] }, on = { tri = [0, 1, 1] } }
//!     [[rule]]
//!     if = "x is low"
//!     then = "z is off"
//!     [[rule]]
//!     if = "x is high"
//!     then = "z is on"
//! "#, "demo.toml")?;
//! let z = sys.output("z")?;
//! let on = sys.output_term("z", "on")?;
//! let mut ev = sys.evaluation();
//! sys.evaluate_into(&[7.5], &mut ev)?;
//! assert!(ev.value(z) > 0.5);
//! assert_eq!(ev.degree(on), 0.75);
//! # Ok::<(), flownav::fuzzy::FuzzyError>(())
//! ```

mod centroid;
mod error;
mod load;
mod membership;
mod rule;

pub use error::{FuzzyError, Problem};
pub use membership::Membership;
pub use rule::{Assignment, Expr, ParseError, parse_antecedent, parse_consequent};

use centroid::Scratch;
use rule::Op;
use std::path::Path;

/// One linguistic term: a name and its membership function.
#[derive(Clone, Debug, PartialEq)]
pub struct Term {
    pub name: String,
    pub membership: Membership,
}

/// A linguistic variable: a name, its universe `[min, max]` and its terms (in file order).
#[derive(Clone, Debug, PartialEq)]
pub struct Variable {
    pub name: String,
    pub min: f64,
    pub max: f64,
    pub terms: Vec<Term>,
}

impl Variable {
    /// Index of the term called `name`.
    pub fn term_index(&self, name: &str) -> Option<usize> {
        self.terms.iter().position(|t| t.name == name)
    }

    fn term_names(&self) -> String {
        names(self.terms.iter().map(|t| t.name.as_str()))
    }
}

/// How an output's centroid is computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Centroid {
    /// Exact integration of the piecewise-linear aggregate (triangle/trapezoid terms only).
    Exact,
    /// `sum(z mu) / sum(mu)` over `resolution` evenly spaced samples of the universe.
    Sampled { resolution: usize },
}

/// An output variable with its defuzzification settings.
#[derive(Clone, Debug, PartialEq)]
pub struct Output {
    pub variable: Variable,
    /// The value when no rule fires.
    pub default: f64,
    pub centroid: Centroid,
    /// Samples `z_i` and tabulated degrees `table[k * n + i]` for the sampled centroid.
    samples: Vec<f64>,
    table: Vec<f64>,
    /// The terms' shapes, contiguous for the exact centroid.
    shapes: Vec<Membership>,
}

/// A rule after loading: its text (for messages) and weight; the compiled program lives in
/// the system.
#[derive(Clone, Debug, PartialEq)]
pub struct Rule {
    pub antecedent: String,
    pub consequent: String,
    pub weight: f64,
    ops: std::ops::Range<usize>,
    then: std::ops::Range<usize>,
}

/// Index of an input variable; its position in the slice given to [`FuzzySystem::evaluate`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct InputId(pub usize);

/// Index of an output variable.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct OutputId(pub usize);

/// One term of one output: read its cut level with [`Evaluation::degree`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct OutputTermId {
    pub output: OutputId,
    /// Position of the term in its output's `terms`.
    pub term: usize,
    flat: usize,
}

/// A compiled Mamdani fuzzy system. Immutable and `Sync`: share one between threads and give
/// each caller its own [`Evaluation`].
#[derive(Clone, Debug)]
pub struct FuzzySystem {
    name: String,
    origin: String,
    inputs: Vec<Variable>,
    outputs: Vec<Output>,
    rules: Vec<Rule>,
    /// Flat offset of each input's terms in [`Evaluation`]'s input degrees (plus the total).
    input_offsets: Vec<usize>,
    /// Flat offset of each output's terms in the cut levels (plus the total).
    output_offsets: Vec<usize>,
    ops: Vec<Op>,
    /// Flat output-term index of each consequent assignment.
    consequents: Vec<usize>,
    stack_depth: usize,
    max_output_terms: usize,
}

/// The result of one evaluation and the buffers it reuses: crisp outputs, each output term's
/// cut level, each rule's strength. Create it once with [`FuzzySystem::evaluation`] and pass
/// it to [`FuzzySystem::evaluate_into`] on every step.
#[derive(Clone, Debug, Default)]
pub struct Evaluation {
    input_degrees: Vec<f64>,
    cuts: Vec<f64>,
    values: Vec<f64>,
    fired: Vec<bool>,
    strengths: Vec<f64>,
    input_offsets: Vec<usize>,
    output_offsets: Vec<usize>,
    stack: Vec<f64>,
    scratch: Scratch,
}

impl Evaluation {
    /// Crisp value of `output` (its default when no rule fired).
    pub fn value(&self, output: OutputId) -> f64 {
        self.values[output.0]
    }

    /// Crisp values of all outputs, in file order.
    pub fn values(&self) -> &[f64] {
        &self.values
    }

    /// Whether any rule fired for `output` (false: the value is the default).
    pub fn fired(&self, output: OutputId) -> bool {
        self.fired[output.0]
    }

    /// Cut level of one output term: the max over the rules concluding it of their strength.
    pub fn degree(&self, term: OutputTermId) -> f64 {
        self.cuts[term.flat]
    }

    /// Cut levels of all terms of `output`, in file order.
    pub fn degrees(&self, output: OutputId) -> &[f64] {
        &self.cuts[self.output_offsets[output.0]..self.output_offsets[output.0 + 1]]
    }

    /// The term of `output` with the highest cut level and that level (first on ties).
    pub fn strongest(&self, output: OutputId) -> (usize, f64) {
        self.degrees(output).iter().enumerate().fold(
            (0, f64::NEG_INFINITY),
            |best, (k, &d)| {
                if d > best.1 { (k, d) } else { best }
            },
        )
    }

    /// Degrees of all terms of `input` at the (clamped) input value.
    pub fn input_degrees(&self, input: InputId) -> &[f64] {
        &self.input_degrees[self.input_offsets[input.0]..self.input_offsets[input.0 + 1]]
    }

    /// Strength of each rule (`weight × antecedent`), in file order.
    pub fn rule_strengths(&self) -> &[f64] {
        &self.strengths
    }
}

fn names<'a>(it: impl Iterator<Item = &'a str>) -> String {
    it.collect::<Vec<_>>().join(", ")
}

impl FuzzySystem {
    /// Parses and validates a system from TOML text; `origin` (usually the file name) prefixes
    /// every error message.
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Self, FuzzyError> {
        load::load(text, origin)
    }

    /// Reads, parses and validates a system file.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self, FuzzyError> {
        let path = path.as_ref();
        let text =
            std::fs::read_to_string(path).map_err(|source| FuzzyError::Read { path: path.to_path_buf(), source })?;
        load::load(&text, &path.display().to_string())
    }

    /// The `[system] name` (the origin when the file does not name it).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Where the system was loaded from.
    pub fn origin(&self) -> &str {
        &self.origin
    }

    pub fn inputs(&self) -> &[Variable] {
        &self.inputs
    }

    pub fn outputs(&self) -> &[Output] {
        &self.outputs
    }

    pub fn rules(&self) -> &[Rule] {
        &self.rules
    }

    fn unknown(&self, kind: &'static str, name: &str, known: String) -> FuzzyError {
        FuzzyError::UnknownName { system: self.name.clone(), kind, name: name.to_string(), known }
    }

    /// The input called `name`.
    pub fn input(&self, name: &str) -> Result<InputId, FuzzyError> {
        self.inputs
            .iter()
            .position(|v| v.name == name)
            .map(InputId)
            .ok_or_else(|| self.unknown("input", name, names(self.inputs.iter().map(|v| v.name.as_str()))))
    }

    /// The output called `name`.
    pub fn output(&self, name: &str) -> Result<OutputId, FuzzyError> {
        self.outputs
            .iter()
            .position(|o| o.variable.name == name)
            .map(OutputId)
            .ok_or_else(|| self.unknown("output", name, names(self.outputs.iter().map(|o| o.variable.name.as_str()))))
    }

    /// The term `term` of output `output`, whose cut level [`Evaluation::degree`] reads.
    pub fn output_term(&self, output: &str, term: &str) -> Result<OutputTermId, FuzzyError> {
        let o = self.output(output)?;
        let var = &self.outputs[o.0].variable;
        let k = var.term_index(term).ok_or_else(|| self.unknown("term", term, var.term_names()))?;
        Ok(OutputTermId { output: o, term: k, flat: self.output_offsets[o.0] + k })
    }

    /// Empty result buffers sized for this system (the only allocation of the evaluation path).
    pub fn evaluation(&self) -> Evaluation {
        let n_out_terms = *self.output_offsets.last().expect("offsets");
        Evaluation {
            input_degrees: vec![0.0; *self.input_offsets.last().expect("offsets")],
            cuts: vec![0.0; n_out_terms],
            values: self.outputs.iter().map(|o| o.default).collect(),
            fired: vec![false; self.outputs.len()],
            strengths: vec![0.0; self.rules.len()],
            input_offsets: self.input_offsets.clone(),
            output_offsets: self.output_offsets.clone(),
            stack: Vec::with_capacity(self.stack_depth),
            scratch: Scratch::new(
                self.max_output_terms,
                self.outputs.iter().map(|o| o.samples.len()).max().unwrap_or(0),
            ),
        }
    }

    /// Evaluates the system for `inputs` (one value per input, in file order) into `ev`,
    /// without allocating. Values outside an input's range are clamped to it; NaN is an error.
    pub fn evaluate_into(&self, inputs: &[f64], ev: &mut Evaluation) -> Result<(), FuzzyError> {
        if inputs.len() != self.inputs.len() {
            return Err(FuzzyError::InputCount {
                system: self.name.clone(),
                expected: self.inputs.len(),
                got: inputs.len(),
                order: names(self.inputs.iter().map(|v| v.name.as_str())),
            });
        }
        if ev.output_offsets != self.output_offsets || ev.input_offsets != self.input_offsets {
            *ev = self.evaluation();
        }
        // Fuzzify.
        for (i, (var, &x)) in self.inputs.iter().zip(inputs).enumerate() {
            if x.is_nan() {
                return Err(FuzzyError::NotANumber { system: self.name.clone(), input: var.name.clone() });
            }
            let x = x.clamp(var.min, var.max);
            let off = self.input_offsets[i];
            for (k, t) in var.terms.iter().enumerate() {
                ev.input_degrees[off + k] = t.membership.degree(x);
            }
        }
        // Rules: strength, then min implication = raising each concluded term's cut level.
        ev.cuts.fill(0.0);
        for (r, rule) in self.rules.iter().enumerate() {
            let s = rule.weight * rule::run(&self.ops[rule.ops.clone()], &ev.input_degrees, &mut ev.stack);
            ev.strengths[r] = s;
            for &flat in &self.consequents[rule.then.clone()] {
                ev.cuts[flat] = ev.cuts[flat].max(s);
            }
        }
        // Aggregate (max) and defuzzify (centroid).
        for (o, out) in self.outputs.iter().enumerate() {
            let cuts = &ev.cuts[self.output_offsets[o]..self.output_offsets[o + 1]];
            let var = &out.variable;
            let (area, moment) = match out.centroid {
                Centroid::Exact => centroid::exact_moments(&out.shapes, cuts, var.min, var.max, &mut ev.scratch),
                Centroid::Sampled { .. } => centroid::sampled_moments(&out.samples, &out.table, cuts, &mut ev.scratch),
            };
            let fired = area > 0.0 && moment.is_finite();
            ev.fired[o] = fired;
            // The clamp only guards the last ulp of rounding; the centroid lies in the range.
            ev.values[o] = if fired { (moment / area).clamp(var.min, var.max) } else { out.default };
        }
        Ok(())
    }

    /// Evaluates into a fresh [`Evaluation`] (allocates; use `evaluate_into` in loops).
    pub fn evaluate(&self, inputs: &[f64]) -> Result<Evaluation, FuzzyError> {
        let mut ev = self.evaluation();
        self.evaluate_into(inputs, &mut ev)?;
        Ok(ev)
    }

    /// Evaluates with inputs given by name, e.g. `&[("x", 1.0), ("y", 0.5)]`; every input must
    /// be given exactly once. Convenient for tests and tools.
    pub fn evaluate_named(&self, inputs: &[(&str, f64)]) -> Result<Evaluation, FuzzyError> {
        let mut values = vec![f64::NAN; self.inputs.len()];
        let mut given = vec![false; self.inputs.len()];
        for &(name, x) in inputs {
            let i = self.input(name)?.0;
            if given[i] {
                return Err(FuzzyError::NamedInput {
                    system: self.name.clone(),
                    input: name.to_string(),
                    problem: "given twice",
                });
            }
            given[i] = true;
            values[i] = x;
        }
        if let Some(i) = given.iter().position(|g| !g) {
            return Err(FuzzyError::NamedInput {
                system: self.name.clone(),
                input: self.inputs[i].name.clone(),
                problem: "missing",
            });
        }
        self.evaluate(&values)
    }
}

#[cfg(test)]
mod tests;
