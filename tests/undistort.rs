//! Lens distortion end to end: a view rendered through a distorted 90° lens, undistorted with
//! `hal::Undistorter` as the pipeline does, against the ideal pinhole's view of the same pose;
//! block-matching flow on the undistorted frames against the flow on the pinhole frames; and the
//! pipeline's step, which undistorts the frames itself.

use flownav::config::Config;
use flownav::flow::cpu::CpuFlow;
use flownav::flow::{Backend, FlowEngine, FlowField, FlowParams};
use flownav::step::Pipeline;
use hal::{BodyVelocity, Calibration, Frame, LumaImage, Undistorter};
use mocks::{Pose, Renderer, World};

/// `calib/wide90.toml` (fx = fy = 640 at 1280×720) with a wide lens's barrel distortion, at
/// 320×180; and the same camera as an ideal pinhole.
fn cameras() -> (Calibration, Calibration) {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/calib/wide90.toml");
    let pinhole = Calibration::load(path).unwrap().scaled_to(320, 180);
    let mut lens = pinhole.clone();
    lens.camera.distortion = [-0.25, 0.06, 0.0, 0.0, 0.0];
    (lens, pinhole)
}

fn mean_abs_diff(a: &LumaImage, b: &LumaImage) -> f64 {
    a.data().iter().zip(b.data()).map(|(x, y)| x.abs_diff(*y) as f64).sum::<f64>() / a.data().len() as f64
}

/// Two views of the office: the start, and 8 cm ahead turned 0.03 rad left (4 to 12 px of flow).
fn poses(world: &World) -> [Pose; 2] {
    [world.start, world.start.advance(0.08, 0.03, 1.0)]
}

#[test]
fn an_undistorted_wide_lens_view_is_the_pinhole_view() {
    let (lens, pinhole) = cameras();
    let world = World::office();
    let undistorter = Undistorter::new(&lens).unwrap().expect("the lens has distortion");
    let (distorted, ideal) = (Renderer::new(&world, &lens), Renderer::new(&world, &pinhole));
    for pose in poses(&world) {
        let raw = distorted.render(pose);
        let expect = ideal.render(pose);
        let undistorted = undistorter.undistort(&raw).unwrap();
        // measured: 2.4 grey levels after undistortion at both poses, 13.3 without; what is left
        // is the blur of two bilinear resamplings (renderer and undistorter) of a texture whose
        // one-pixel shift differs by 5 grey levels, the same over the centre and the edges
        let (after, before) = (mean_abs_diff(&undistorted, &expect), mean_abs_diff(&raw, &expect));
        assert!(after < 4.0, "undistorted view differs by {after:.2} grey levels on average");
        assert!(before > 8.0, "the distorted view should differ clearly, differs by {before:.2}");
    }
}

fn flow(a: &LumaImage, b: &LumaImage) -> FlowField {
    let params = FlowParams { rows: 8, cols: 12, ..FlowParams::default() };
    CpuFlow::new(params).unwrap().compute(a, b).unwrap().clone()
}

#[test]
fn flow_on_undistorted_frames_is_the_pinhole_flow() {
    let (lens, pinhole) = cameras();
    let world = World::office();
    let undistorter = Undistorter::new(&lens).unwrap().unwrap();
    let (distorted, ideal) = (Renderer::new(&world, &lens), Renderer::new(&world, &pinhole));
    let [a, b] = poses(&world);
    let expect = flow(&ideal.render(a), &ideal.render(b));
    let undistort = |p| undistorter.undistort(&distorted.render(p)).unwrap();
    let got = flow(&undistort(a), &undistort(b));
    let raw = flow(&distorted.render(a), &distorted.render(b));
    // per block valid in both fields: how far the vector is from the pinhole's
    let errors = |field: &FlowField| -> Vec<f32> {
        let mut e: Vec<f32> = field
            .vectors
            .iter()
            .zip(&expect.vectors)
            .filter(|(g, e)| g.valid() && e.valid())
            .map(|(g, e)| (g.u - e.u).hypot(g.v - e.v))
            .collect();
        e.sort_by(f32::total_cmp);
        e
    };
    let (undistorted, distorted) = (errors(&got), errors(&raw));
    assert!(undistorted.len() >= 48, "{} of 96 blocks valid in both", undistorted.len());
    let pct = |e: &[f32], q: f64| e[((e.len() - 1) as f64 * q) as usize];
    // measured on 60 blocks: median 0.09 px, 90th percentile 0.45 px, worst 0.96 px (the
    // distorted frames: 0.89, 2.87 and 4.33 px)
    assert!(pct(&undistorted, 0.5) < 0.2 && pct(&undistorted, 0.9) < 0.7, "{undistorted:?}");
    assert!(pct(&distorted, 0.9) > 2.0 * pct(&undistorted, 0.9), "{distorted:?}");
}

/// The flow of one step of a pipeline with `calib` over the frames of `renderer` at `a` and `b`.
fn step_flow(calib: &Calibration, renderer: &Renderer, [a, b]: [Pose; 2]) -> FlowField {
    let mut cfg = Config::default();
    cfg.flow.backend = Backend::Cpu;
    cfg.pairing.min_baseline_m = 0.0;
    let mut pipeline = Pipeline::new(&cfg, calib.clone(), None).unwrap();
    let drive = BodyVelocity::new(0.08, 0.03);
    let frame = |seq: u64, pose| Frame { seq, t_ns: seq * 1_000_000_000, image: renderer.render(pose) };
    assert!(pipeline.step(frame(0, a), drive).unwrap().is_none());
    pipeline.step(frame(1, b), drive).unwrap().unwrap().flow
}

#[test]
fn the_pipeline_undistorts_its_frames() {
    let (lens, pinhole) = cameras();
    let world = World::office();
    let distorted = Renderer::new(&world, &lens);
    let expect = step_flow(&pinhole, &Renderer::new(&world, &pinhole), poses(&world));
    // the share of the blocks valid in both fields whose vectors agree within 0.5 px
    let agree = |field: &FlowField| {
        let near: Vec<bool> = field
            .vectors
            .iter()
            .zip(&expect.vectors)
            .filter(|(g, e)| g.valid() && e.valid())
            .map(|(g, e)| (g.u - e.u).hypot(g.v - e.v) < 0.5)
            .collect();
        (near.iter().filter(|n| **n).count() as f64 / near.len() as f64, near.len())
    };
    let (share, blocks) = agree(&step_flow(&lens, &distorted, poses(&world)));
    // a pipeline told of no distortion does not undistort the same frames
    let (unaware, _) = agree(&step_flow(&pinhole, &distorted, poses(&world)));
    // measured: 92 % of 170 blocks, against 27 % without undistortion
    assert!(blocks >= 100 && share > 0.85, "{share:.2} of {blocks} blocks agree");
    assert!(unaware < 0.6, "{unaware:.2} of the blocks agree without undistortion");
}
