//! The fuzzy engine against an independent implementation: scikit-fuzzy 0.5.0 and an exact
//! continuous centroid on a 21×21 grid (`data/fuzzy/fuzzy_grid_21x21.csv` in the shared data).

use flownav::fuzzy::FuzzySystem;
use proptest::prelude::*;
use std::path::PathBuf;

const REFERENCE: &str = include_str!("../rules/examples/reference.toml");

struct Row {
    x: f64,
    y: f64,
    mu: [f64; 3],
    exact: f64,
    discrete_u101: f64,
    discrete_u1001: f64,
    skfuzzy_u101: f64,
    skfuzzy_u1001: f64,
}

fn csv_path() -> PathBuf {
    flownav::frames::reference_data_dir().join("fuzzy/fuzzy_grid_21x21.csv")
}

fn rows() -> Vec<Row> {
    let path = csv_path();
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap_or_else(|| panic!("column {name}"));
    let (x, y, lo, med, hi) = (col("x"), col("y"), col("mu_lo"), col("mu_med"), col("mu_hi"));
    let (exact, d101, d1001) = (col("exact"), col("discrete_u101"), col("discrete_u1001"));
    let (sk101, sk1001) = (col("skfuzzy_u101"), col("skfuzzy_u1001"));
    lines
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|s| s.parse().expect("number")).collect();
            Row {
                x: v[x],
                y: v[y],
                mu: [v[lo], v[med], v[hi]],
                exact: v[exact],
                discrete_u101: v[d101],
                discrete_u1001: v[d1001],
                skfuzzy_u101: v[sk101],
                skfuzzy_u1001: v[sk1001],
            }
        })
        .collect()
}

fn sampled(resolution: usize) -> FuzzySystem {
    let text = REFERENCE.replace("centroid = \"exact\"", &format!("centroid = \"sampled\"\nresolution = {resolution}"));
    FuzzySystem::from_toml_str(&text, "reference-sampled.toml").expect("valid")
}

#[test]
fn reference_grid_matches_scikit_fuzzy_exact_and_sampled() {
    let rows = rows();
    assert_eq!(rows.len(), 441);
    let exact = FuzzySystem::from_file(concat!(env!("CARGO_MANIFEST_DIR"), "/rules/examples/reference.toml")).unwrap();
    let (s101, s1001) = (sampled(101), sampled(1001));
    let z = exact.output("z").unwrap();
    let terms = ["lo", "med", "hi"].map(|t| exact.output_term("z", t).unwrap());
    let mut ev = exact.evaluation();
    let (mut worst_exact, mut worst_101, mut worst_1001) = (0.0f64, 0.0f64, 0.0f64);
    let (mut vs_sk101, mut vs_sk1001) = (0.0f64, 0.0f64);
    for r in &rows {
        exact.evaluate_into(&[r.x, r.y], &mut ev).unwrap();
        assert!(ev.fired(z));
        for (k, t) in terms.iter().enumerate() {
            // The CSV prints 8 decimals; cut levels are min/max of triangle degrees.
            assert!(
                (ev.degree(*t) - r.mu[k]).abs() < 1e-8,
                "mu {k} at ({}, {}): {} vs {}",
                r.x,
                r.y,
                ev.degree(*t),
                r.mu[k]
            );
        }
        worst_exact = worst_exact.max((ev.value(z) - r.exact).abs());
        vs_sk101 = vs_sk101.max((ev.value(z) - r.skfuzzy_u101).abs());
        vs_sk1001 = vs_sk1001.max((ev.value(z) - r.skfuzzy_u1001).abs());
        let e101 = s101.evaluate(&[r.x, r.y]).unwrap();
        worst_101 = worst_101.max((e101.value(z) - r.discrete_u101).abs());
        let e1001 = s1001.evaluate_named(&[("y", r.y), ("x", r.x)]).unwrap();
        worst_1001 = worst_1001.max((e1001.value(z) - r.discrete_u1001).abs());
    }
    eprintln!("max |error|: exact {worst_exact:.2e}, u101 {worst_101:.2e}, u1001 {worst_1001:.2e}");
    eprintln!("exact centroid vs scikit-fuzzy itself: u101 {vs_sk101:.2e}, u1001 {vs_sk1001:.2e}");
    assert!(worst_exact < 1e-6, "exact centroid off by {worst_exact}");
    // The CSV holds 8 decimal places, so 5e-9 is its own rounding.
    assert!(worst_101 < 1e-8, "101-sample centroid off by {worst_101}");
    assert!(worst_1001 < 1e-8, "1001-sample centroid off by {worst_1001}");
    // scikit-fuzzy's own discretisation error, as its README states it (1.9e-3 and 2.5e-5).
    assert!(vs_sk101 < 2e-3 && vs_sk1001 < 3e-5, "vs scikit-fuzzy: {vs_sk101}, {vs_sk1001}");
}

proptest! {
    #[test]
    fn outputs_stay_in_the_universe_and_are_never_nan(
        x in -20.0f64..30.0, y in -3.0f64..3.0, gauss in any::<bool>(), w in 0.0f64..=1.0
    ) {
        let mut text = REFERENCE.replace("if = \"x is M and y is Z\"", &format!("if = \"x is M and y is Z\"\nweight = {w}"));
        if gauss {
            text = text.replace("centroid = \"exact\"", "")
                .replace("med = { tri = [20, 50, 80] }", "med = { gauss = [50, 12] }");
        }
        let sys = FuzzySystem::from_toml_str(&text, "prop.toml").unwrap();
        let ev = sys.evaluate(&[x, y]).unwrap();
        let z = ev.values()[0];
        prop_assert!(z.is_finite());
        prop_assert!((0.0..=100.0).contains(&z), "z = {}", z);
    }
}
