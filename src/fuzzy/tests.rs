//! System-level unit tests: operators, weights, defaults, clamping and every validation error.

use super::*;

/// One input `x` in [0, 10] with terms lo/hi, one output `z` in [0, 1] with off/on.
const HEAD: &str = r#"
[system]
name = "t"
[[input]]
name = "x"
range = [0, 10]
terms = { lo = { tri = [0, 0, 10] }, hi = { tri = [0, 10, 10] } }
[[input]]
name = "y"
range = [0, 10]
terms = { lo = { trap = [0, 0, 2, 10] }, hi = { tri = [0, 10, 10] } }
[[output]]
name = "z"
range = [0, 1]
terms = { off = { tri = [0, 0, 1] }, on = { tri = [0, 1, 1] } }
"#;

fn system(rules: &str) -> FuzzySystem {
    FuzzySystem::from_toml_str(&format!("{HEAD}{rules}"), "t.toml").unwrap_or_else(|e| panic!("{e}"))
}

fn problem(text: &str) -> (Problem, String) {
    let e = FuzzySystem::from_toml_str(text, "bad.toml").expect_err("must be rejected");
    let msg = e.to_string();
    assert!(msg.starts_with("bad.toml:"), "error must name the file: {msg}");
    (e.problem().unwrap_or_else(|| panic!("not a validation error: {msg}")).clone(), msg)
}

fn on_degree(sys: &FuzzySystem, x: f64, y: f64) -> f64 {
    sys.evaluate(&[x, y]).unwrap().degree(sys.output_term("z", "on").unwrap())
}

#[test]
fn not_or_and_compute_complement_max_and_min() {
    // At x = 2.5: x lo 0.75, x hi 0.25; y = 6: y lo 0.5, y hi 0.6.
    let sys = system("[[rule]]\nif = \"x is not lo\"\nthen = \"z is on\"");
    assert!((on_degree(&sys, 2.5, 6.0) - 0.25).abs() < 1e-12);
    let sys = system("[[rule]]\nif = \"x is hi or y is lo\"\nthen = \"z is on\"");
    assert!((on_degree(&sys, 2.5, 6.0) - 0.5).abs() < 1e-12);
    let sys = system("[[rule]]\nif = \"x is lo and y is hi\"\nthen = \"z is on\"");
    assert!((on_degree(&sys, 2.5, 6.0) - 0.6).abs() < 1e-12);
    let sys = system("[[rule]]\nif = \"not (x is lo and y is hi) or (x is hi and y is hi)\"\nthen = \"z is on\"");
    assert!((on_degree(&sys, 2.5, 6.0) - 0.4).abs() < 1e-12);
}

#[test]
fn several_rules_for_one_term_take_the_max_and_weights_scale_strength() {
    let sys = system(
        "[[rule]]\nif = \"x is lo\"\nthen = \"z is on\"\nweight = 0.5\n\
         [[rule]]\nif = \"y is hi\"\nthen = \"z is on\"\nweight = 0.25",
    );
    let ev = sys.evaluate(&[2.5, 6.0]).unwrap();
    assert_eq!(ev.rule_strengths(), &[0.375, 0.15]);
    assert_eq!(ev.degrees(sys.output("z").unwrap()), &[0.0, 0.375]);
}

#[test]
fn a_rule_may_conclude_several_outputs() {
    let text = format!(
        "{HEAD}[[output]]\nname = \"w\"\nrange = [-1, 1]\nterms = {{ neg = {{ tri = [-1, -1, 1] }}, pos = {{ tri = [-1, 1, 1] }} }}\n\
         [[rule]]\nif = \"x is hi\"\nthen = \"z is on and w is neg\""
    );
    let sys = FuzzySystem::from_toml_str(&text, "two.toml").unwrap();
    let ev = sys.evaluate(&[10.0, 0.0]).unwrap();
    let (z, w) = (sys.output("z").unwrap(), sys.output("w").unwrap());
    // A full right shoulder on [0,1] has its centroid at 2/3; a full left one on [-1,1] at -1/3.
    assert!((ev.value(z) - 2.0 / 3.0).abs() < 1e-12);
    assert!((ev.value(w) + 1.0 / 3.0).abs() < 1e-12);
    assert_eq!(ev.strongest(w), (0, 1.0));
}

#[test]
fn no_rule_firing_gives_the_default_or_the_middle_of_the_range() {
    let sys = system("[[rule]]\nif = \"x is hi and y is hi\"\nthen = \"z is on\"");
    let z = sys.output("z").unwrap();
    let ev = sys.evaluate(&[0.0, 0.0]).unwrap();
    assert!(!ev.fired(z));
    assert_eq!(ev.value(z), 0.5);
    let text = format!("{HEAD}[[rule]]\nif = \"x is hi\"\nthen = \"z is on\"")
        .replace("range = [0, 1]", "range = [0, 1]\ndefault = 0.1");
    let sys = FuzzySystem::from_toml_str(&text, "d.toml").unwrap();
    let ev = sys.evaluate(&[0.0, 0.0]).unwrap();
    assert_eq!((ev.value(z), ev.fired(z)), (0.1, false));
}

#[test]
fn inputs_outside_the_range_are_clamped_and_nan_is_rejected() {
    let sys = system("[[rule]]\nif = \"x is hi\"\nthen = \"z is on\"");
    let a = sys.evaluate(&[10.0, 5.0]).unwrap();
    let b = sys.evaluate(&[1e9, f64::INFINITY]).unwrap();
    assert_eq!(a.values(), b.values());
    assert_eq!(sys.evaluate(&[-3.0, 5.0]).unwrap().input_degrees(sys.input("x").unwrap()), &[1.0, 0.0]);
    let e = sys.evaluate(&[f64::NAN, 0.0]).unwrap_err();
    assert!(matches!(e, FuzzyError::NotANumber { ref input, .. } if input == "x"), "{e}");
    let e = sys.evaluate(&[1.0]).unwrap_err();
    assert!(e.to_string().contains("expected 2 input values (in the order x, y), got 1"), "{e}");
}

#[test]
fn named_evaluation_checks_names() {
    let sys = system("[[rule]]\nif = \"x is hi\"\nthen = \"z is on\"");
    let ev = sys.evaluate_named(&[("y", 0.0), ("x", 7.0)]).unwrap();
    assert_eq!(ev.values(), sys.evaluate(&[7.0, 0.0]).unwrap().values());
    assert!(matches!(sys.evaluate_named(&[("x", 1.0)]), Err(FuzzyError::NamedInput { problem: "missing", .. })));
    assert!(matches!(
        sys.evaluate_named(&[("x", 1.0), ("x", 1.0), ("y", 0.0)]),
        Err(FuzzyError::NamedInput { problem: "given twice", .. })
    ));
    assert!(matches!(sys.evaluate_named(&[("q", 1.0)]), Err(FuzzyError::UnknownName { kind: "input", .. })));
    assert!(matches!(sys.output_term("z", "maybe"), Err(FuzzyError::UnknownName { kind: "term", .. })));
}

#[test]
fn terms_keep_the_file_order() {
    let text = HEAD.replace(
        "terms = { off = { tri = [0, 0, 1] }, on = { tri = [0, 1, 1] } }",
        "terms = { zz = { tri = [0, 0, 1] }, aa = { tri = [0, 1, 1] } }",
    );
    let sys =
        FuzzySystem::from_toml_str(&format!("{text}[[rule]]\nif = \"x is hi\"\nthen = \"z is aa\""), "o.toml").unwrap();
    let names: Vec<&str> = sys.outputs()[0].variable.terms.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(names, ["zz", "aa"]);
    assert_eq!(sys.output_term("z", "aa").unwrap().term, 1);
}

#[test]
fn gaussian_outputs_use_the_sampled_centroid() {
    let text = HEAD.replace("on = { tri = [0, 1, 1] }", "on = { gauss = [0.5, 0.1] }");
    let sys =
        FuzzySystem::from_toml_str(&format!("{text}[[rule]]\nif = \"x is hi\"\nthen = \"z is on\""), "g.toml").unwrap();
    assert_eq!(sys.outputs()[0].centroid, Centroid::Sampled { resolution: 1001 });
    // A symmetric Gaussian clipped anywhere keeps its centroid at the mean.
    let z = sys.evaluate(&[3.0, 0.0]).unwrap().values()[0];
    assert!((z - 0.5).abs() < 1e-9, "{z}");
}

#[test]
fn evaluate_into_reuses_its_buffers() {
    let sys = system("[[rule]]\nif = \"x is hi\"\nthen = \"z is on\"");
    let mut ev = sys.evaluation();
    sys.evaluate_into(&[5.0, 0.0], &mut ev).unwrap();
    let first = ev.values()[0];
    sys.evaluate_into(&[10.0, 0.0], &mut ev).unwrap();
    sys.evaluate_into(&[5.0, 0.0], &mut ev).unwrap();
    assert_eq!(ev.values()[0], first);
}

fn rule(text: &str) -> String {
    format!("{HEAD}[[rule]]\nif = \"{text}\"\nthen = \"z is on\"")
}

#[test]
fn unknown_variables_and_terms_are_named_with_their_position() {
    let (p, msg) = problem(&rule("x is lo and q is hi"));
    assert!(matches!(p, Problem::UnknownInput { ref name, .. } if name == "q"), "{msg}");
    // Line 17 of the file holds `if = "x is lo and q is hi"`; `q` is at column 19.
    assert!(msg.starts_with("bad.toml:17:19: rule 1: unknown input variable 'q' (inputs: x, y)"), "{msg}");
    let (p, msg) = problem(&rule("x is lo and z is on"));
    assert!(matches!(p, Problem::UnknownInput { .. }) && msg.contains("'z' is an output"), "{msg}");
    let (p, msg) = problem(&rule("x is middle"));
    assert!(matches!(p, Problem::UnknownTerm { ref term, .. } if term == "middle"), "{msg}");
    assert!(msg.contains("unknown term 'middle' of input 'x' (terms: lo, hi)"), "{msg}");
    let (p, _) = problem(&format!("{HEAD}[[rule]]\nif = \"x is lo\"\nthen = \"w is on\""));
    assert!(matches!(p, Problem::UnknownOutput { ref name, .. } if name == "w"));
    let (p, _) = problem(&format!("{HEAD}[[rule]]\nif = \"x is lo\"\nthen = \"z is maybe\""));
    assert!(matches!(p, Problem::UnknownTerm { kind: "output", .. }));
}

#[test]
fn parse_errors_show_the_rule_text_and_position() {
    let (p, msg) = problem(&rule("x is lo and (y is hi"));
    assert!(matches!(p, Problem::Parse { field: "if", position: 20, .. }), "{msg}");
    assert!(msg.contains("x is lo and (y is hi\n") && msg.contains("^"), "{msg}");
    let (p, _) = problem(&format!("{HEAD}[[rule]]\nif = \"x is lo\"\nthen = \"z on\""));
    assert!(matches!(p, Problem::Parse { field: "then", position: 2, .. }));
}

#[test]
fn bad_membership_functions_are_rejected() {
    let bad = |from: &str, to: &str| problem(&rule("x is lo").replacen(from, to, 1)).0;
    assert!(matches!(bad("tri = [0, 0, 10]", "tri = [0, 5, 3]"), Problem::NotOrdered { .. }));
    assert!(matches!(bad("tri = [0, 0, 10]", "tri = [4, 4, 4]"), Problem::ZeroWidth { .. }));
    assert!(matches!(bad("tri = [0, 0, 10]", "tri = [0, 0, 12]"), Problem::OutsideRange { value: 12.0, .. }));
    assert!(matches!(bad("trap = [0, 0, 2, 10]", "trap = [0, 3, 2, 10]"), Problem::NotOrdered { .. }));
    assert!(matches!(bad("tri = [0, 0, 10]", "gauss = [5, 0]"), Problem::BadParameter { .. }));
    assert!(matches!(bad("tri = [0, 0, 10]", "gauss = [-5, 1]"), Problem::OutsideRange { .. }));
    assert!(matches!(bad("tri = [0, 0, 10]", "sigmoid = [5, 0]"), Problem::BadParameter { .. }));
    assert!(matches!(bad("range = [0, 10]", "range = [10, 0]"), Problem::BadRange { .. }));
    assert!(matches!(bad("name = \"x\"", "name = \"and\""), Problem::BadName { .. }));
    assert!(matches!(
        bad("terms = { lo = { tri = [0, 0, 10] }, hi = { tri = [0, 10, 10] } }", "terms = {}"),
        Problem::NoTerms { .. }
    ));
    let e = FuzzySystem::from_toml_str(
        &rule("x is lo").replacen("tri = [0, 0, 10]", "triangle = [0, 0, 10]", 1),
        "bad.toml",
    )
    .unwrap_err();
    assert!(matches!(e, FuzzyError::Toml { .. }) && e.to_string().contains("triangle"), "{e}");
}

#[test]
fn system_level_mistakes_are_rejected() {
    assert!(matches!(problem(HEAD).0, Problem::NoRules));
    assert!(matches!(problem(&rule("x is lo").replace("name = \"y\"", "name = \"x\"")).0, Problem::Duplicate { .. }));
    assert!(matches!(problem(&format!("{}\nweight = 1.5", rule("x is lo"))).0, Problem::BadWeight { weight: 1.5 }));
    let out = |extra: &str| problem(&rule("x is lo").replace("range = [0, 1]", &format!("range = [0, 1]\n{extra}"))).0;
    assert!(matches!(out("default = 2"), Problem::DefaultOutsideRange { .. }));
    assert!(matches!(out("resolution = 1"), Problem::BadResolution { value: 1 }));
    let gauss = rule("x is lo").replace("on = { tri = [0, 1, 1] }", "on = { gauss = [1, 0.2] }");
    let (p, _) = problem(&gauss.replace("range = [0, 1]", "range = [0, 1]\ncentroid = \"exact\""));
    assert!(matches!(p, Problem::ExactNeedsPiecewiseLinear { ref term } if term == "on"));
    let two = format!(
        "{HEAD}[[output]]\nname = \"w\"\nrange = [0, 1]\nterms = {{ a = {{ tri = [0, 0, 1] }} }}\n[[rule]]\nif = \"x is lo\"\nthen = \"z is on\""
    );
    assert!(matches!(problem(&two).0, Problem::UnusedOutput { ref output } if output == "w"));
    let no_inputs = "[[output]]\nname = \"z\"\nrange = [0, 1]\nterms = { a = { tri = [0, 0, 1] } }";
    assert!(matches!(problem(no_inputs).0, Problem::NoInputs));
}

#[test]
fn the_shipped_examples_load() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/rules/examples");
    let mut n = 0;
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            FuzzySystem::from_file(&path).unwrap_or_else(|e| panic!("{e}"));
            n += 1;
        }
    }
    assert!(n >= 1);
    let e = FuzzySystem::from_file(format!("{dir}/missing.toml")).unwrap_err();
    assert!(matches!(e, FuzzyError::Read { .. }) && e.to_string().contains("missing.toml"));
}

#[test]
fn toml_schema_errors_name_the_file_and_line() {
    let text = rule("x is lo").replacen("tri = [0, 0, 10]", "triangle = [0, 0, 10]", 1);
    let e = FuzzySystem::from_toml_str(&text, "bad.toml").unwrap_err();
    let msg = e.to_string();
    assert!(msg.starts_with("bad.toml: ") && msg.contains("line 7") && msg.contains("triangle"), "{msg}");
}

#[test]
fn the_avoidance_example_turns_towards_the_free_side() {
    let sys = FuzzySystem::from_file(concat!(env!("CARGO_MANIFEST_DIR"), "/rules/examples/avoid.toml")).unwrap();
    let (omega, speed) = (sys.output("omega").unwrap(), sys.output("speed").unwrap());
    let open = sys.evaluate_named(&[("front_m", 4.0), ("left_m", 4.0), ("right_m", 4.0)]).unwrap();
    assert!(open.value(omega).abs() < 1e-9 && open.value(speed) > 0.35);
    let blocked = sys.evaluate_named(&[("front_m", 0.3), ("left_m", 3.0), ("right_m", 0.8)]).unwrap();
    assert!(blocked.value(omega) > 0.3 && blocked.value(speed) < 0.05);
    let wall_left = sys.evaluate_named(&[("front_m", 4.0), ("left_m", 0.2), ("right_m", 3.0)]).unwrap();
    assert!(wall_left.value(omega) < -0.1);
}

#[test]
fn terms_may_be_written_as_a_sub_table() {
    let text = r#"
[[input]]
name = "x"
range = [0, 1]
[input.terms]
far = { tri = [0, 1, 1] }
near = { tri = [0, 0, 1] }

[[output]]
name = "z"
range = [0, 1]
[output.terms]
b = { trap = [0, 0.5, 1, 1] }
a = { tri = [0, 0, 0.5] }

[[rule]]
if = "x is near"
then = "z is a"
"#;
    let sys = FuzzySystem::from_toml_str(text, "sub.toml").unwrap();
    assert_eq!(sys.name(), "sub.toml");
    assert_eq!(sys.inputs()[0].terms[0].name, "far");
    assert_eq!(sys.output_term("z", "a").unwrap().term, 1);
}
