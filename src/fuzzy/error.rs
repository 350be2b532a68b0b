//! Errors of the fuzzy engine: loading (I/O, TOML syntax, validation with a file position) and
//! evaluation (bad inputs, unknown names).

use std::path::PathBuf;

/// Everything that can go wrong loading or evaluating a fuzzy system.
#[derive(Debug, thiserror::Error)]
pub enum FuzzyError {
    #[error("{}: cannot read the fuzzy system: {source}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// TOML syntax or schema error (unknown key, wrong type, unknown shape); `message` holds
    /// the TOML parser's text, which includes the line and column.
    #[error("{origin}: {message}")]
    Toml { origin: String, message: String },
    /// A well-formed file whose content is wrong, at `line:column` (1-based) of `origin`.
    #[error("{origin}:{line}:{column}: {context}: {problem}")]
    Invalid { origin: String, line: usize, column: usize, context: String, problem: Box<Problem> },
    #[error("fuzzy system '{system}': expected {expected} input values (in the order {order}), got {got}")]
    InputCount { system: String, expected: usize, got: usize, order: String },
    #[error("fuzzy system '{system}': input '{input}' is NaN; pass a number (values outside the range are clamped)")]
    NotANumber { system: String, input: String },
    #[error("fuzzy system '{system}': no {kind} named '{name}' (known: {known})")]
    UnknownName { system: String, kind: &'static str, name: String, known: String },
    #[error("fuzzy system '{system}': input '{input}' is {problem}")]
    NamedInput { system: String, input: String, problem: &'static str },
}

impl FuzzyError {
    /// The validation problem, for an `Invalid` error.
    pub fn problem(&self) -> Option<&Problem> {
        match self {
            FuzzyError::Invalid { problem, .. } => Some(problem),
            _ => None,
        }
    }
}

/// What is wrong with a fuzzy system file; the `Invalid` error says where.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum Problem {
    #[error("the system has no [[input]]; declare at least one input variable")]
    NoInputs,
    #[error("the system has no [[output]]; declare at least one output variable")]
    NoOutputs,
    #[error("the system has no [[rule]]; add at least one rule")]
    NoRules,
    #[error("'{name}' is not a valid name: use letters, digits, '_' or '-', not a keyword (is/not/and/or)")]
    BadName { name: String },
    #[error("duplicate {what} name '{name}'; names must be unique")]
    Duplicate { what: &'static str, name: String },
    #[error("range [{min}, {max}] is empty or not finite; write range = [min, max] with min < max")]
    BadRange { min: f64, max: f64 },
    #[error("'{variable}' has no terms; add e.g. terms = {{ low = {{ tri = [..] }} }}")]
    NoTerms { variable: String },
    #[error("points {points:?} are not in order; {shape} needs {order}")]
    NotOrdered { shape: &'static str, points: Vec<f64>, order: &'static str },
    #[error("points {points:?} have zero width; the first and last point must differ")]
    ZeroWidth { points: Vec<f64> },
    #[error("{what} {value} lies outside the range [{min}, {max}] of '{variable}'")]
    OutsideRange { what: &'static str, value: f64, min: f64, max: f64, variable: String },
    #[error("{message}")]
    BadParameter { message: String },
    #[error("weight {weight} is not in [0, 1]")]
    BadWeight { weight: f64 },
    #[error("default {value} lies outside the range [{min}, {max}]; the default must be a possible output")]
    DefaultOutsideRange { value: f64, min: f64, max: f64 },
    #[error("resolution {value} must be at least 2 samples (and at most 1000000)")]
    BadResolution { value: i64 },
    #[error(
        "centroid = \"exact\" needs triangular/trapezoidal terms, but term '{term}' is not; use centroid = \"sampled\""
    )]
    ExactNeedsPiecewiseLinear { term: String },
    #[error("no rule concludes '{output}'; it would always be its default")]
    UnusedOutput { output: String },
    #[error("parse error at character {position} of the `{field}` text: {message}\n    {text}\n    {caret}^")]
    Parse { field: &'static str, position: usize, message: String, text: String, caret: String },
    #[error("unknown input variable '{name}' (inputs: {known}){hint}")]
    UnknownInput { name: String, known: String, hint: String },
    #[error("unknown output variable '{name}' (outputs: {known}){hint}")]
    UnknownOutput { name: String, known: String, hint: String },
    #[error("unknown term '{term}' of {kind} '{variable}' (terms: {known})")]
    UnknownTerm { kind: &'static str, variable: String, term: String, known: String },
}
