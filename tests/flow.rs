//! Flow on real images with ground truth (`shared/data`, see its README) and the `flownav flow`
//! command end to end.
//!
//! The data folder is `data/` in the repository (`flownav::frames::reference_data_dir`;
//! `FLOWNAV_DATA` overrides it).

use flownav::flow::cpu::CpuFlow;
use flownav::flow::{FlowEngine, FlowField, FlowParams, Placement, Validity};
use flownav::frames::load_luma;
use hal::LumaImage;
use std::path::PathBuf;
use std::process::Command;

fn data_dir() -> PathBuf {
    let dir = flownav::frames::reference_data_dir();
    assert!(
        dir.join("graf_shift_512/0000.png").is_file(),
        "reference data not found in {}: set FLOWNAV_DATA to the folder holding graf_shift_512/ and motorcycle_stereo/",
        dir.display()
    );
    dir
}

/// One row of `gt/blocks32_tile.csv`.
#[derive(Debug, Clone)]
struct GtBlock {
    row: usize,
    col: usize,
    centre_valid: bool,
    u: f64,
    v: f64,
    in_range16: bool,
    target_inside: bool,
}

fn read_blocks(pair: &str) -> Vec<GtBlock> {
    let path = data_dir().join(pair).join("gt/blocks32_tile.csv");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let (ir, ic, icv, iu, iv, iin, iti) = (
        col("row"),
        col("col"),
        col("centre_valid"),
        col("u_centre"),
        col("v_centre"),
        col("in_range16"),
        col("target_inside"),
    );
    lines
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            GtBlock {
                row: f[ir].parse().unwrap(),
                col: f[ic].parse().unwrap(),
                centre_valid: f[icv] == "1",
                u: f[iu].parse().unwrap_or(f64::NAN),
                v: f[iv].parse().unwrap_or(f64::NAN),
                in_range16: f[iin] == "1",
                target_inside: f[iti] == "1",
            }
        })
        .collect()
}

fn pair(name: &str) -> (LumaImage, LumaImage) {
    let d = data_dir().join(name);
    (load_luma(d.join("0000.png")).unwrap(), load_luma(d.join("0001.png")).unwrap())
}

/// Flow on the 32×32 tiles of `blocks32_tile.csv` (rows = H div 32, cols = W div 32).
fn tile_flow(a: &LumaImage, b: &LumaImage, extra: impl FnOnce(&mut FlowParams)) -> FlowField {
    let mut p = FlowParams {
        rows: a.height() / 32,
        cols: a.width() / 32,
        block: 32,
        radius: 16,
        placement: Placement::Tile,
        ..FlowParams::default()
    };
    extra(&mut p);
    CpuFlow::new(p).unwrap().compute(a, b).unwrap().clone()
}

/// Mean endpoint error over the GT blocks selected by `keep` (all of them, whatever our
/// validity flag says), and how many of those we flagged valid.
fn epe(field: &FlowField, gt: &[GtBlock], keep: impl Fn(&GtBlock) -> bool) -> (f64, usize, usize) {
    let (mut sum, mut n, mut valid) = (0.0, 0, 0);
    for g in gt.iter().filter(|g| g.centre_valid && keep(g)) {
        let v = field.at(g.row, g.col);
        sum += (f64::from(v.u) - g.u).hypot(f64::from(v.v) - g.v);
        n += 1;
        valid += usize::from(v.valid());
    }
    (sum / n as f64, n, valid)
}

/// The documented figure (docs/results.md): an exhaustive 32×32 matcher with radius 16 returns exactly (5, −3)
/// for every tile whose target lies inside image 1 (225 of 256). The default spread placement
/// tiles 512×512 exactly, so the default parameters are used unchanged.
#[test]
fn graf_shift_every_inside_block_is_exact() {
    let (a, b) = pair("graf_shift_512");
    let gt = read_blocks("graf_shift_512");
    let mut eng = CpuFlow::new(FlowParams::default()).unwrap();
    let f = eng.compute(&a, &b).unwrap();
    let inside: Vec<_> = gt.iter().filter(|g| g.target_inside).collect();
    assert_eq!(inside.len(), 225);
    let (mut exact, mut valid) = (0, 0);
    for g in &inside {
        let v = f.at(g.row, g.col);
        assert_eq!((v.x, v.y), (32.0 * g.col as f32 + 16.0, 32.0 * g.row as f32 + 16.0));
        assert_eq!((v.u.round(), v.v.round()), (5.0, -3.0), "block {g:?}: {v:?}");
        // Exact to the last bit unless the block of A lies within the prefilter radius (4 px)
        // of A's border (column 0, row 15): there edge replication makes A and B differ, the
        // cost is > 0 and the parabola leaves a small sub-pixel residue.
        if g.col > 0 && g.row < 15 {
            assert_eq!((v.u, v.v), (5.0, -3.0), "block {g:?}");
        }
        assert!((v.u - 5.0).abs() < 0.3 && (v.v + 3.0).abs() < 0.3, "block {g:?}: {v:?}");
        exact += usize::from((v.u, v.v) == (5.0, -3.0));
        valid += usize::from(v.valid());
    }
    eprintln!("graf: {exact}/225 exactly (5, -3) including sub-pixel, {valid}/225 flagged valid");
    assert!(exact >= 196, "{exact}");
    assert!(valid >= 215, "{valid}");
    // Blocks whose true match leaves image 1 must not claim to have found it.
    for g in gt.iter().filter(|g| !g.target_inside) {
        let v = f.at(g.row, g.col);
        assert!(!v.valid() || (v.u.round(), v.v.round()) != (5.0, -3.0), "{g:?} {v:?}");
    }
}

/// Exposure changes between the frames (offset, gain, both, with clipping) leave the result
/// on the real texture essentially unchanged: that is what the high-pass prefilter is for.
#[test]
fn graf_shift_tolerates_exposure_change() {
    let (a, b) = pair("graf_shift_512");
    let gt = read_blocks("graf_shift_512");
    for (gain, offset) in [(1.0, 40.0), (1.3, 0.0), (0.7, 30.0), (1.2, -25.0)] {
        let b2 = photometric(&b, gain, offset);
        let f = tile_flow(&a, &b2, |_| {});
        let ok = gt
            .iter()
            .filter(|g| g.target_inside)
            .filter(|g| {
                let v = f.at(g.row, g.col);
                (v.u.round(), v.v.round()) == (5.0, -3.0)
            })
            .count();
        eprintln!("gain {gain} offset {offset}: {ok}/225 exact");
        assert!(ok >= 222, "gain {gain} offset {offset}: only {ok}/225 blocks exact");
    }
}

fn photometric(img: &LumaImage, gain: f64, offset: f64) -> LumaImage {
    LumaImage::from_fn(img.width(), img.height(), |x, y| {
        (gain * f64::from(img.get(x, y)) + offset).round().clamp(0.0, 255.0) as u8
    })
}

/// Middlebury "Motorcycle" (real scene, occlusions, motion −7…−60 px). Single level, radius
/// 16: the 49 tiles whose motion is in range and whose target is inside (mostly on depth edges
/// of the background shelves, where a 32×32 block mixes two motions). Coarse-to-fine (3 levels,
/// up to ±64 px): every tile with known ground truth. Measured (docs/flow.md): 3.87 px and
/// 4.29 px (2.10 px over the tiles flagged valid); OpenCV DIS (medium) at the same pixels
/// 3.00 px and 2.30 px. The bounds allow ~15 % above our measurement, so a regression fails.
#[test]
fn motorcycle_endpoint_error() {
    let (a, b) = pair("motorcycle_stereo");
    let gt = read_blocks("motorcycle_stereo");
    let single = tile_flow(&a, &b, |_| {});
    let (e_in, n_in, valid_in) = epe(&single, &gt, |g| g.in_range16 && g.target_inside);
    let valid_in_epe = {
        let sel: Vec<_> =
            gt.iter().filter(|g| g.in_range16 && g.target_inside && single.at(g.row, g.col).valid()).cloned().collect();
        epe(&single, &sel, |_| true).0
    };
    let pyr = tile_flow(&a, &b, |p| p.pyramid_levels = 3);
    let (e_all, n_all, valid_all) = epe(&pyr, &gt, |_| true);
    let valid_only = {
        let sel: Vec<_> = gt.iter().filter(|g| g.centre_valid && pyr.at(g.row, g.col).valid()).cloned().collect();
        epe(&pyr, &sel, |_| true).0
    };
    eprintln!(
        "motorcycle: {n_in} in-range tiles, single level: EPE {e_in:.3} px ({valid_in} valid, EPE over those {valid_in_epe:.3}); \
         all {n_all} GT tiles, 3-level pyramid: EPE {e_all:.3} px ({valid_all} valid, EPE over those {valid_only:.3} px)"
    );
    assert_eq!((n_in, n_all), (49, 320));
    assert!(e_in < 4.5, "in-range EPE {e_in}");
    assert!(valid_in_epe < 1.5, "in-range EPE over valid tiles {valid_in_epe}");
    assert!(e_all < 5.0, "all-tile EPE with pyramid {e_all}");
    assert!(valid_only < 2.5, "EPE over valid-flagged tiles {valid_only}");
    assert!(valid_all >= 160, "only {valid_all} of 320 tiles valid with the pyramid");
}

fn flownav(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_flownav")).args(args).output().unwrap()
}

/// `flownav flow A B --json` prints exactly the DESIGN.md contract (plus extra fields).
#[test]
fn cli_json_contract() {
    let d = data_dir().join("graf_shift_512");
    let (a, b) = (d.join("0000.png"), d.join("0001.png"));
    let out = flownav(&["flow", a.to_str().unwrap(), b.to_str().unwrap(), "--json", "--rows", "8", "--cols", "4"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8(out.stdout).unwrap();
    assert_eq!(text.lines().count(), 1, "one JSON line");
    let j: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(j["grid"], serde_json::json!([8, 4]));
    assert_eq!((j["width"].as_u64(), j["height"].as_u64()), (Some(512), Some(512)));
    let vs = j["vectors"].as_array().unwrap();
    assert_eq!(vs.len(), 32);
    for v in vs {
        for k in ["x", "y", "u", "v"] {
            assert!(v[k].is_number(), "{v}");
        }
        assert!(v["valid"].is_boolean());
        if v["valid"].as_bool().unwrap() {
            assert_eq!((v["u"].as_f64(), v["v"].as_f64()), (Some(5.0), Some(-3.0)), "{v}");
        }
    }
    // Row-major: second vector is to the right of the first.
    assert!(vs[1]["x"].as_f64() > vs[0]["x"].as_f64() && vs[1]["y"] == vs[0]["y"]);

    let png = tempfile::tempdir().unwrap();
    let out_png = png.path().join("flow.png");
    let out = flownav(&["flow", a.to_str().unwrap(), b.to_str().unwrap(), "--png", out_png.to_str().unwrap()]);
    assert!(out.status.success());
    let summary = String::from_utf8(out.stdout).unwrap();
    assert!(summary.contains("valid 226/256") && summary.contains("(5.00, -3.00)"), "{summary}");
    let img = image::open(&out_png).unwrap();
    assert_eq!((img.width(), img.height()), (512, 512));
}

/// `--repeat N` keeps every field of the contract and appends a `timing` object: N counted
/// calls, min ≤ median ≤ p90 (wall and thread CPU time), the engine and what it ran on.
#[test]
fn cli_repeat_timing() {
    let d = data_dir().join("graf_shift_512");
    let (a, b) = (d.join("0000.png"), d.join("0001.png"));
    let args = ["flow", a.to_str().unwrap(), b.to_str().unwrap(), "--json", "--rows", "4", "--cols", "4"];
    let plain = flownav(&[&args[..], &["--flow-backend", "cpu"]].concat());
    let timed = flownav(&[&args[..], &["--flow-backend", "cpu", "--repeat", "7"]].concat());
    assert!(timed.status.success(), "{}", String::from_utf8_lossy(&timed.stderr));
    let plain: serde_json::Value = serde_json::from_slice(&plain.stdout).unwrap();
    let mut timed: serde_json::Value = serde_json::from_slice(&timed.stdout).unwrap();
    let t = timed.as_object_mut().unwrap().remove("timing").expect("a timing object");
    assert_eq!(timed, plain, "the contract's fields are unchanged");
    assert_eq!((t["n"].as_u64(), t["warmup"].as_u64()), (Some(7), Some(1)), "{t}");
    assert_eq!(t["engine"], "cpu");
    assert!(t["adapter"].as_str().is_some_and(|s| s.contains("SAD")), "{t}");
    for prefix in ["", "cpu_"] {
        let f = |k: &str| t[format!("{prefix}{k}_ms")].as_f64().unwrap_or_else(|| panic!("{prefix}{k}_ms in {t}"));
        assert!(0.0 < f("min") && f("min") <= f("median") && f("median") <= f("p90"), "{t}");
    }
    assert!(t["min_ms"].as_f64() <= t["mean_ms"].as_f64(), "{t}");

    let bad = flownav(&[&args[..], &["--repeat", "0"]].concat());
    assert!(!bad.status.success() && String::from_utf8_lossy(&bad.stderr).contains("--repeat"));
}

/// Bad input gives one clear error and a non-zero exit, never a panic.
#[test]
fn cli_bad_inputs() {
    let d = data_dir();
    let graf = d.join("graf_shift_512/0000.png");
    let moto = d.join("motorcycle_stereo/0000.png");
    let tmp = tempfile::tempdir().unwrap();
    let empty = tmp.path().join("empty.png");
    std::fs::write(&empty, b"").unwrap();
    let text = tmp.path().join("notes.png");
    std::fs::write(&text, b"not an image at all").unwrap();
    let cases: [(Vec<&str>, &[&str]); 5] = [
        (vec![graf.to_str().unwrap(), moto.to_str().unwrap()], &["512x512", "741x500", "same size"]),
        (vec![graf.to_str().unwrap(), empty.to_str().unwrap()], &["empty.png", "empty"]),
        (vec![text.to_str().unwrap(), graf.to_str().unwrap()], &["notes.png", "not a readable"]),
        (vec![graf.to_str().unwrap(), "/nonexistent/b.png"], &["/nonexistent/b.png"]),
        (vec![graf.to_str().unwrap(), graf.to_str().unwrap(), "--block", "7"], &["flow.block"]),
    ];
    for (args, needles) in cases {
        let mut full = vec!["flow"];
        full.extend(args.iter().copied());
        let out = flownav(&full);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{full:?} should fail");
        assert!(!err.contains("panicked"), "{err}");
        for n in needles {
            assert!(err.contains(n), "{full:?}: error {err:?} should mention {n:?}");
        }
    }
}

/// Matching-cost study behind the prefilter choice (docs/flow.md): on graf_shift_512 with a
/// photometric change applied to image 1, the share of the 225 inside tiles found exactly by
/// plain SAD, zero-mean SAD, NCC, and SAD after the high-pass prefilter; on motorcycle the
/// in-range EPE. Run with
/// `cargo test --release --test flow -- --ignored cost_study --nocapture`.
#[test]
#[ignore = "measurement for docs/flow.md, prints a table"]
fn cost_study() {
    let (a, b) = pair("graf_shift_512");
    let gt = read_blocks("graf_shift_512");
    let (ma, mb) = pair("motorcycle_stereo");
    let mgt = read_blocks("motorcycle_stereo");
    let conditions = [(1.0, 0.0), (1.0, 40.0), (1.3, 0.0), (0.7, 30.0), (1.2, -25.0)];
    println!("| cost | {} | motorcycle EPE (49 tiles) |", conditions.map(|(g, o)| format!("g={g} o={o}")).join(" | "));
    println!("|---|{}---|", "---|".repeat(conditions.len()));
    for cost in [Cost::Sad, Cost::Zsad, Cost::Ncc, Cost::HighPass] {
        let mut cells = vec![];
        for (g, o) in conditions {
            let b2 = photometric(&b, g, o);
            let d = cost.flow(&a, &b2);
            let ok = gt.iter().filter(|t| t.target_inside).filter(|t| d[t.row * 16 + t.col] == (5, -3)).count();
            cells.push(format!("{ok}/225"));
        }
        let d = cost.flow(&ma, &mb);
        let cols = ma.width() / 32;
        let sel: Vec<_> = mgt.iter().filter(|t| t.centre_valid && t.in_range16 && t.target_inside).collect();
        let e: f64 = sel
            .iter()
            .map(|t| {
                let (u, v) = d[t.row * cols + t.col];
                (f64::from(u) - t.u).hypot(f64::from(v) - t.v)
            })
            .sum::<f64>()
            / sel.len() as f64;
        println!("| {cost:?} | {} | {e:.3} |", cells.join(" | "));
    }
}

#[derive(Debug, Clone, Copy)]
enum Cost {
    /// SAD of raw intensities.
    Sad,
    /// SAD after subtracting each block's own mean.
    Zsad,
    /// 1 − normalised cross-correlation.
    Ncc,
    /// SAD after the (2·4+1)² local-mean high-pass (the engine's default).
    HighPass,
}

impl Cost {
    /// Integer displacement of every 32×32 tile, exhaustive search radius 16, ties to the
    /// smallest |d|.
    fn flow(self, a: &LumaImage, b: &LumaImage) -> Vec<(i32, i32)> {
        if let Cost::Sad | Cost::HighPass = self {
            let k = if let Cost::Sad = self { 0 } else { 4 };
            let f = tile_flow(a, b, |p| p.prefilter_radius = k);
            return f.vectors.iter().map(|v| (v.u.round() as i32, v.v.round() as i32)).collect();
        }
        let (w, h) = (a.width() as i32, a.height() as i32);
        let mut out = vec![];
        for r in 0..h / 32 {
            for c in 0..w / 32 {
                let (x0, y0) = (c * 32, r * 32);
                let block = |img: &LumaImage, x: i32, y: i32| -> Vec<f64> {
                    (0..32 * 32).map(|i| f64::from(img.get((x + i % 32) as usize, (y + i / 32) as usize))).collect()
                };
                let pa = block(a, x0, y0);
                let mean = |p: &[f64]| p.iter().sum::<f64>() / p.len() as f64;
                let ma = mean(&pa);
                let mut best = (f64::INFINITY, i32::MAX, (0, 0));
                for dy in -16..=16 {
                    for dx in -16..=16 {
                        let (x, y) = (x0 + dx, y0 + dy);
                        if x < 0 || y < 0 || x + 32 > w || y + 32 > h {
                            continue;
                        }
                        let pb = block(b, x, y);
                        let mb = mean(&pb);
                        let cost = match self {
                            Cost::Zsad => pa.iter().zip(&pb).map(|(p, q)| ((p - ma) - (q - mb)).abs()).sum::<f64>(),
                            _ => {
                                let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
                                for (p, q) in pa.iter().zip(&pb) {
                                    sab += (p - ma) * (q - mb);
                                    saa += (p - ma).powi(2);
                                    sbb += (q - mb).powi(2);
                                }
                                1.0 - sab / (saa * sbb).sqrt().max(1e-9)
                            }
                        };
                        let key = dx * dx + dy * dy;
                        if (cost, key) < (best.0, best.1) {
                            best = (cost, key, (dx, dy));
                        }
                    }
                }
                out.push(best.2);
            }
        }
        out
    }
}

/// Validity reasons are reported per vector and are one of the four names.
#[test]
fn validity_names_are_stable() {
    let names: Vec<_> =
        [Validity::Valid, Validity::Textureless, Validity::Ambiguous, Validity::OutOfFrame].map(|v| v.name()).into();
    assert_eq!(names, ["valid", "textureless", "ambiguous", "out_of_frame"]);
}
