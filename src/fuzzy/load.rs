//! Loading a fuzzy system from TOML: the file schema, validation with positions, and
//! compilation of names to indices.

use super::centroid::linspace;
use super::error::{FuzzyError, Problem};
use super::membership::Membership;
use super::rule::{self, Expr};
use super::{Centroid, FuzzySystem, Output, Rule, Term, Variable, names};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::ops::Range;
use toml::Spanned;

/// Samples of a sampled centroid when the file does not say.
pub const DEFAULT_RESOLUTION: usize = 1001;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFile {
    system: Option<RawSystem>,
    #[serde(default)]
    input: Vec<Spanned<RawInput>>,
    #[serde(default)]
    output: Vec<Spanned<RawOutput>>,
    #[serde(default)]
    rule: Vec<Spanned<RawRule>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSystem {
    name: Option<String>,
    #[allow(dead_code)]
    description: Option<String>,
}

type RawTerms = BTreeMap<Spanned<String>, Spanned<RawShape>>;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawInput {
    name: Spanned<String>,
    range: Spanned<[f64; 2]>,
    terms: Spanned<RawTerms>,
    #[allow(dead_code)]
    description: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawOutput {
    name: Spanned<String>,
    range: Spanned<[f64; 2]>,
    terms: Spanned<RawTerms>,
    default: Option<Spanned<f64>>,
    centroid: Option<Spanned<RawCentroid>>,
    resolution: Option<Spanned<i64>>,
    #[allow(dead_code)]
    description: Option<String>,
}

#[derive(Deserialize, Clone, Copy, PartialEq)]
#[serde(rename_all = "lowercase")]
enum RawCentroid {
    Exact,
    Sampled,
}

#[derive(Deserialize, Clone, Copy)]
#[serde(rename_all = "lowercase", deny_unknown_fields)]
enum RawShape {
    Tri([f64; 3]),
    Trap([f64; 4]),
    Gauss([f64; 2]),
    Sigmoid([f64; 2]),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRule {
    #[serde(rename = "if")]
    antecedent: Spanned<String>,
    #[serde(rename = "then")]
    consequent: Spanned<String>,
    weight: Option<Spanned<f64>>,
}

/// Turns byte offsets into `line:column` errors of one source.
struct Ctx<'a> {
    origin: &'a str,
    src: &'a str,
}

impl Ctx<'_> {
    fn err(&self, offset: usize, context: impl Into<String>, problem: Problem) -> FuzzyError {
        let offset = offset.min(self.src.len());
        let before = &self.src[..offset];
        let line = before.matches('\n').count() + 1;
        let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
        FuzzyError::Invalid {
            origin: self.origin.to_string(),
            line,
            column,
            context: context.into(),
            problem: Box::new(problem),
        }
    }

    /// Byte offset in the source of character `pos` of a string value spanning `span`
    /// (exact for strings without escapes).
    fn in_string(&self, span: &Range<usize>, text: &str, pos: usize) -> usize {
        let raw = &self.src[span.start..span.end.min(self.src.len())];
        let quote = if raw.starts_with("\"\"\"") || raw.starts_with("'''") { 3 } else { 1 };
        let byte = text.char_indices().nth(pos).map_or(text.len(), |(b, _)| b);
        span.start + quote + byte
    }
}

fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.chars().all(|c| c.is_alphanumeric() || c == '_' || c == '-')
        && !name.starts_with('-')
        && !["is", "not", "and", "or"].iter().any(|k| name.eq_ignore_ascii_case(k))
}

fn check_name(ctx: &Ctx, name: &Spanned<String>, context: &str) -> Result<(), FuzzyError> {
    if valid_name(name.get_ref()) {
        Ok(())
    } else {
        Err(ctx.err(name.span().start, context, Problem::BadName { name: name.get_ref().clone() }))
    }
}

fn variable(
    ctx: &Ctx,
    kind: &'static str,
    name: &Spanned<String>,
    range: &Spanned<[f64; 2]>,
    terms: &Spanned<RawTerms>,
) -> Result<Variable, FuzzyError> {
    let vname = name.get_ref().clone();
    let here = format!("{kind} '{vname}'");
    check_name(ctx, name, &here)?;
    let [min, max] = *range.get_ref();
    if !(min.is_finite() && max.is_finite() && min < max) {
        return Err(ctx.err(range.span().start, &here, Problem::BadRange { min, max }));
    }
    if terms.get_ref().is_empty() {
        return Err(ctx.err(terms.span().start, &here, Problem::NoTerms { variable: vname }));
    }
    // Keep the file order (the map is sorted by name).
    let mut entries: Vec<_> = terms.get_ref().iter().collect();
    entries.sort_by_key(|(k, _)| k.span().start);
    let mut out = Vec::with_capacity(entries.len());
    for (tname, shape) in entries {
        let tctx = format!("{kind} '{vname}', term '{}'", tname.get_ref());
        check_name(ctx, tname, &tctx)?;
        let at = shape.span().start;
        let fail = |problem| Err(ctx.err(at, &tctx, problem));
        let inside = |what: &'static str, v: f64| -> Result<(), FuzzyError> {
            if (min..=max).contains(&v) {
                Ok(())
            } else {
                Err(ctx.err(at, &tctx, Problem::OutsideRange { what, value: v, min, max, variable: vname.clone() }))
            }
        };
        let membership = match *shape.get_ref() {
            RawShape::Tri([a, b, c]) => {
                linear_points(&[a, b, c], "tri = [a, b, c]", "a <= b <= c").map_err(|p| ctx.err(at, &tctx, p))?;
                for v in [a, b, c] {
                    inside("point", v)?;
                }
                Membership::Triangle { a, b, c }
            }
            RawShape::Trap([a, b, c, d]) => {
                linear_points(&[a, b, c, d], "trap = [a, b, c, d]", "a <= b <= c <= d")
                    .map_err(|p| ctx.err(at, &tctx, p))?;
                for v in [a, b, c, d] {
                    inside("point", v)?;
                }
                Membership::Trapezoid { a, b, c, d }
            }
            RawShape::Gauss([mean, sigma]) => {
                if !(sigma.is_finite() && sigma > 0.0) {
                    return fail(Problem::BadParameter {
                        message: format!("gauss = [mean, sigma] needs sigma > 0, got {sigma}"),
                    });
                }
                inside("mean", mean)?;
                Membership::Gaussian { mean, sigma }
            }
            RawShape::Sigmoid([center, slope]) => {
                if !(slope.is_finite() && slope != 0.0) {
                    return fail(Problem::BadParameter {
                        message: format!("sigmoid = [center, slope] needs a finite, non-zero slope, got {slope}"),
                    });
                }
                inside("center", center)?;
                Membership::Sigmoid { center, slope }
            }
        };
        out.push(Term { name: tname.get_ref().clone(), membership });
    }
    Ok(Variable { name: vname, min, max, terms: out })
}

fn linear_points(p: &[f64], shape: &'static str, order: &'static str) -> Result<(), Problem> {
    if p.iter().any(|v| !v.is_finite()) {
        return Err(Problem::BadParameter { message: format!("points {p:?} must be finite numbers") });
    }
    if p.windows(2).any(|w| w[0] > w[1]) {
        return Err(Problem::NotOrdered { shape, points: p.to_vec(), order });
    }
    if p[0] == p[p.len() - 1] {
        return Err(Problem::ZeroWidth { points: p.to_vec() });
    }
    Ok(())
}

fn hint_other(name: &str, other: &[Variable], other_kind: &str) -> String {
    if other.iter().any(|v| v.name == name) { format!("; '{name}' is an {other_kind}") } else { String::new() }
}

pub(super) fn load(src: &str, origin: &str) -> Result<FuzzySystem, FuzzyError> {
    let ctx = Ctx { origin, src };
    let raw: RawFile = toml::from_str(src)
        .map_err(|e| FuzzyError::Toml { origin: origin.to_string(), message: e.to_string().trim_end().to_string() })?;
    let name = raw.system.and_then(|s| s.name).unwrap_or_else(|| origin.to_string());

    if raw.input.is_empty() {
        return Err(ctx.err(0, "system", Problem::NoInputs));
    }
    if raw.output.is_empty() {
        return Err(ctx.err(0, "system", Problem::NoOutputs));
    }
    if raw.rule.is_empty() {
        return Err(ctx.err(src.len(), "system", Problem::NoRules));
    }

    let mut seen: Vec<String> = Vec::new();
    let mut check_unique = |n: &Spanned<String>, what: &'static str| {
        if seen.contains(n.get_ref()) {
            return Err(ctx.err(
                n.span().start,
                format!("{what} '{}'", n.get_ref()),
                Problem::Duplicate { what: "variable", name: n.get_ref().clone() },
            ));
        }
        seen.push(n.get_ref().clone());
        Ok(())
    };
    let mut inputs = Vec::new();
    for r in &raw.input {
        let r = r.get_ref();
        check_unique(&r.name, "input")?;
        inputs.push(variable(&ctx, "input", &r.name, &r.range, &r.terms)?);
    }
    let mut outputs = Vec::new();
    for r in &raw.output {
        let r = r.get_ref();
        check_unique(&r.name, "output")?;
        let variable = variable(&ctx, "output", &r.name, &r.range, &r.terms)?;
        let here = format!("output '{}'", variable.name);
        let default = match &r.default {
            Some(d) => {
                let v = *d.get_ref();
                if !(variable.min..=variable.max).contains(&v) {
                    return Err(ctx.err(
                        d.span().start,
                        &here,
                        Problem::DefaultOutsideRange { value: v, min: variable.min, max: variable.max },
                    ));
                }
                v
            }
            None => 0.5 * (variable.min + variable.max),
        };
        let linear = variable.terms.iter().find(|t| !t.membership.is_piecewise_linear());
        let wanted = r.centroid.as_ref().map(|c| (*c.get_ref(), c.span().start));
        let resolution = match &r.resolution {
            Some(n) if !(2..=1_000_000).contains(n.get_ref()) => {
                return Err(ctx.err(n.span().start, &here, Problem::BadResolution { value: *n.get_ref() }));
            }
            Some(n) => *n.get_ref() as usize,
            None => DEFAULT_RESOLUTION,
        };
        let centroid = match (wanted, linear) {
            (Some((RawCentroid::Exact, at)), Some(t)) => {
                return Err(ctx.err(at, &here, Problem::ExactNeedsPiecewiseLinear { term: t.name.clone() }));
            }
            (Some((RawCentroid::Sampled, _)), _) | (None, Some(_)) => Centroid::Sampled { resolution },
            (Some((RawCentroid::Exact, _)), None) | (None, None) => Centroid::Exact,
        };
        let (samples, table) = match centroid {
            Centroid::Sampled { resolution } => {
                let z = linspace(variable.min, variable.max, resolution);
                let table = variable.terms.iter().flat_map(|t| z.iter().map(|&x| t.membership.degree(x))).collect();
                (z, table)
            }
            Centroid::Exact => (Vec::new(), Vec::new()),
        };
        let shapes = variable.terms.iter().map(|t| t.membership).collect();
        outputs.push(Output { variable, default, centroid, samples, table, shapes });
    }

    let offsets = |counts: &mut dyn Iterator<Item = usize>| {
        let mut v = vec![0];
        for c in counts {
            v.push(v.last().copied().unwrap_or(0) + c);
        }
        v
    };
    let input_offsets = offsets(&mut inputs.iter().map(|v| v.terms.len()));
    let output_offsets = offsets(&mut outputs.iter().map(|o| o.variable.terms.len()));

    let mut ops = Vec::new();
    let mut consequents = Vec::new();
    let mut rules = Vec::new();
    let mut stack_depth = 1;
    let mut used = vec![false; outputs.len()];
    for (n, r) in raw.rule.iter().enumerate() {
        let r = r.get_ref();
        let here = format!("rule {}", n + 1);
        let (atext, aspan) = (r.antecedent.get_ref(), r.antecedent.span());
        let (ctext, cspan) = (r.consequent.get_ref(), r.consequent.span());
        let parse_err = |field: &'static str, text: &str, span: &Range<usize>, e: rule::ParseError| {
            ctx.err(
                ctx.in_string(span, text, e.position),
                &here,
                Problem::Parse {
                    field,
                    position: e.position,
                    message: e.message,
                    text: text.to_string(),
                    caret: " ".repeat(e.position),
                },
            )
        };
        let expr = rule::parse_antecedent(atext).map_err(|e| parse_err("if", atext, &aspan, e))?;
        let start = ops.len();
        let depth = rule::compile(&expr, &mut ops, &mut |c: &Expr| {
            let Expr::Is { variable, variable_at, term, term_at } = c else {
                unreachable!("compile resolves clauses only")
            };
            let Some(i) = inputs.iter().position(|v| &v.name == variable) else {
                return Err(ctx.err(
                    ctx.in_string(&aspan, atext, *variable_at),
                    &here,
                    Problem::UnknownInput {
                        name: variable.clone(),
                        known: names(inputs.iter().map(|v| v.name.as_str())),
                        hint: hint_other(
                            variable,
                            &outputs.iter().map(|o| o.variable.clone()).collect::<Vec<_>>(),
                            "output",
                        ),
                    },
                ));
            };
            let Some(k) = inputs[i].term_index(term) else {
                return Err(ctx.err(
                    ctx.in_string(&aspan, atext, *term_at),
                    &here,
                    Problem::UnknownTerm {
                        kind: "input",
                        variable: variable.clone(),
                        term: term.clone(),
                        known: inputs[i].term_names(),
                    },
                ));
            };
            Ok((input_offsets[i] + k) as u32)
        })?;
        stack_depth = stack_depth.max(depth);
        let assignments = rule::parse_consequent(ctext).map_err(|e| parse_err("then", ctext, &cspan, e))?;
        let then_start = consequents.len();
        for a in &assignments {
            let Some(o) = outputs.iter().position(|o| o.variable.name == a.variable) else {
                return Err(ctx.err(
                    ctx.in_string(&cspan, ctext, a.variable_at),
                    &here,
                    Problem::UnknownOutput {
                        name: a.variable.clone(),
                        known: names(outputs.iter().map(|o| o.variable.name.as_str())),
                        hint: hint_other(&a.variable, &inputs, "input"),
                    },
                ));
            };
            let var = &outputs[o].variable;
            let Some(k) = var.term_index(&a.term) else {
                return Err(ctx.err(
                    ctx.in_string(&cspan, ctext, a.term_at),
                    &here,
                    Problem::UnknownTerm {
                        kind: "output",
                        variable: a.variable.clone(),
                        term: a.term.clone(),
                        known: var.term_names(),
                    },
                ));
            };
            used[o] = true;
            consequents.push(output_offsets[o] + k);
        }
        let weight = match &r.weight {
            Some(w) if !(0.0..=1.0).contains(w.get_ref()) => {
                return Err(ctx.err(w.span().start, &here, Problem::BadWeight { weight: *w.get_ref() }));
            }
            Some(w) => *w.get_ref(),
            None => 1.0,
        };
        rules.push(Rule {
            antecedent: atext.clone(),
            consequent: ctext.clone(),
            weight,
            ops: start..ops.len(),
            then: then_start..consequents.len(),
        });
    }
    if let Some(o) = used.iter().position(|u| !u) {
        let at = raw.output[o].get_ref().name.span().start;
        let name = outputs[o].variable.name.clone();
        return Err(ctx.err(at, format!("output '{name}'"), Problem::UnusedOutput { output: name }));
    }

    let max_output_terms = outputs.iter().map(|o| o.variable.terms.len()).max().unwrap_or(0);
    Ok(FuzzySystem {
        name,
        origin: origin.to_string(),
        inputs,
        outputs,
        rules,
        input_offsets,
        output_offsets,
        ops,
        consequents,
        stack_depth,
        max_output_terms,
    })
}
