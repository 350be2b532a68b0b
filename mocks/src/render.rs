//! CPU ray caster (rayon) for the simulated camera: walls, door openings, boxes, cylinders,
//! floor and ceiling with world-anchored textures, plus the depth map and per-pixel surface ids
//! the ground truth is computed from.
//!
//! Every solid in a world is vertical (walls, boxes, cylinders), so a ray's horizontal part
//! decides *which* solids it can meet and its vertical part only *whether* it meets each. With
//! a level camera (pitch 0) the horizontal direction is the same for a whole pixel column: the
//! renderer intersects each column's direction with every solid once (sorted "spans"), then
//! shades each pixel by walking that short list with its own vertical slope. A pitched camera
//! falls back to per-pixel intersection against the solids that the column's wedge of
//! directions can reach.
//!
//! Depth is the distance along the optical axis (the `z` of the point in the optical frame),
//! exact up to `f32` rounding: rays are `(x_n, y_n, 1)` in the optical frame, so the ray
//! parameter of a hit *is* its depth.
//!
//! **Lens distortion.** A calibration with non-zero `distortion` (plumb_bob, [`hal::undistort`])
//! is rendered in two passes: the view is traced as a pinhole image with the same focal length
//! over the whole field the distorted image sees (wider than the image for barrel distortion),
//! then each pixel of the distorted image takes the pinhole image at its ray (the undistorted
//! normalized coordinates of the pixel, computed once): grey values bilinearly, before exposure,
//! noise and rounding; depth and surface ids from the nearest pinhole pixel, so they describe
//! what the pixel shows. A pinhole calibration (all coefficients zero) is traced directly, as
//! before.

use crate::camera::CameraPose;
use crate::texture::{self, Texture};
use crate::world::{BoxObstacle, Pose, World, box_corners, cross, mix64};
use hal::calib::Intrinsics;
use hal::undistort::{self, undistort_normalized};
use hal::{Calibration, LumaImage};
use rayon::prelude::*;

/// At most this many solids are kept per column (nearest first); far ones behind them are hidden.
const MAX_SPANS: usize = 24;
/// Plan direction of the light used for the mild per-surface shading.
const LIGHT: [f64; 2] = [0.6, 0.8];
/// Grey value where a ray meets nothing (open sky in scenes without a ceiling).
const SKY: f32 = 200.0;
/// The pinhole image of a distorted lens extends this far beyond the field its pixels see, px.
const LENS_MARGIN_PX: f64 = 2.0;
/// A distortion whose pinhole image would be this many times the image's width or height is
/// not rendered (it is not a lens; [`hal::calib::Intrinsics::check_lens`] refuses such models).
const LENS_MAX_GROWTH: f64 = 4.0;

/// What a pixel shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SurfaceKind {
    /// Nothing (no ceiling, no solid): depth is infinite.
    Sky,
    Floor,
    Ceiling,
    /// A wall segment: indices into `World::walls` and its segment.
    Wall {
        wall: usize,
        segment: usize,
    },
    /// Side or top of `World::boxes[i]`.
    Box(usize),
    /// `World::cylinders[i]`.
    Cylinder(usize),
}

impl SurfaceKind {
    /// Boxes and cylinders: what DESIGN.md calls obstacles.
    pub fn is_obstacle(self) -> bool {
        matches!(self, SurfaceKind::Box(_) | SurfaceKind::Cylinder(_))
    }
}

/// Image effects for one rendered frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Effects {
    /// Exposure: output = gain · rendered + offset (grey levels), before noise.
    pub gain: f64,
    pub offset: f64,
    /// Standard deviation of additive sensor noise, grey levels (0 = none).
    pub noise_sigma: f64,
    /// Seed of the noise; with the frame sequence number it fixes every noise value.
    pub seed: u64,
    /// Sub-frame renders averaged for motion blur between the previous and the current pose
    /// (1 = no blur).
    pub blur_samples: usize,
}

impl Default for Effects {
    fn default() -> Self {
        Self { gain: 1.0, offset: 0.0, noise_sigma: 0.0, seed: 0, blur_samples: 1 }
    }
}

/// A per-pixel depth map, metres along the optical axis; `f32::INFINITY` where nothing is hit.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthMap {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl DepthMap {
    pub fn at(&self, u: usize, v: usize) -> f32 {
        self.data[v * self.width + u]
    }
}

#[derive(Clone, Copy, Debug)]
struct Surface {
    kind: SurfaceKind,
    /// Grey level of the texture's mean, `255 · albedo`.
    bright: f32,
    /// Twice the texture's contrast: grey = bright · shade · (1 + contrast2 · (texture − 0.5)).
    contrast2: f32,
    /// Texture offset, m (different per surface so their textures differ).
    offset: [f32; 2],
    /// Obstacles carry print (boxes) and folds (clothes) finer than the walls' texture.
    detailed: bool,
}

impl Surface {
    fn new(kind: SurfaceKind, albedo: f32, contrast: f32, offset: [f32; 2]) -> Self {
        // the products are formed as in `255 · albedo · shade · (1 + contrast · 2 · (t − 0.5))`,
        // left to right, so precomputing them leaves every grey level as it was
        Self { kind, bright: 255.0 * albedo, contrast2: contrast * 2.0, offset, detailed: kind.is_obstacle() }
    }
}

#[derive(Clone, Copy, Debug)]
enum Prim {
    /// A wall face from `a` to `b`: its edge `e = b − a`, length, the unit normal
    /// `(−e_y, e_x) / len` and the lighting of that normal and of its opposite (which of the two
    /// faces the camera depends on the ray).
    Face {
        a: [f64; 2],
        b: [f64; 2],
        e: [f64; 2],
        len: f64,
        normal: [f64; 2],
        shade: [f32; 2],
        z0: f64,
        z1: f64,
        along0: f64,
        surface: u32,
    },
    Box {
        center: [f64; 2],
        cos: f64,
        sin: f64,
        hx: f64,
        hy: f64,
        h: f64,
        surface: u32,
    },
    Cyl {
        center: [f64; 2],
        r: f64,
        h: f64,
        surface: u32,
    },
}

impl Prim {
    /// Plan points bounding the primitive (for the wedge test of pitched cameras).
    fn bounds(&self) -> [[f64; 2]; 4] {
        match *self {
            Prim::Face { a, b, .. } => [a, b, a, b],
            Prim::Box { center, cos, sin, hx, hy, .. } => box_corners(&BoxObstacle {
                name: String::new(),
                center,
                size: [2.0 * hx, 2.0 * hy, 1.0],
                yaw: sin.atan2(cos),
            }),
            Prim::Cyl { center: c, r, .. } => {
                [[c[0] - r, c[1] - r], [c[0] + r, c[1] - r], [c[0] + r, c[1] + r], [c[0] - r, c[1] + r]]
            }
        }
    }
}

/// Lighting factor of a surface with horizontal unit normal `n`.
fn light(n: [f64; 2]) -> f32 {
    let l = (LIGHT[0] * n[0] + LIGHT[1] * n[1]) / (LIGHT[0].hypot(LIGHT[1]));
    (0.8 + 0.2 * l) as f32
}

/// Where a horizontal ray direction meets one solid, with what shading the entry face needs
/// from that direction.
#[derive(Clone, Copy, Debug, Default)]
struct Span {
    s_in: f64,
    s_out: f64,
    z0: f64,
    z1: f64,
    /// `fx · max(|cos|, 1e-3)` of the angle between the ray's plan direction and the entry
    /// face's normal: the pixel footprint's denominator.
    fx_cos: f64,
    /// A solid (box, cylinder) has a top at `z1`; a face is thin.
    solid: bool,
    surface: u32,
    /// Texture coordinate along the surface at the entry point plus the surface's offset, m.
    tu: f32,
    /// `bright · shade` of the entry face.
    gain: f32,
}

/// Renders views of one world through one calibrated camera.
pub struct Renderer {
    calib: Calibration,
    width: usize,
    height: usize,
    xn: Vec<f64>,
    yn: Vec<f64>,
    prims: Vec<Prim>,
    surfaces: Vec<Surface>,
    ceiling: Option<f64>,
    tex: &'static Texture,
    /// Shade and expose eight pixels at once (x86-64 with AVX2, detected at run time).
    simd: bool,
    /// Lens distortion to simulate; `None` for a pinhole.
    lens: Option<Lens>,
}

/// A lens with distortion: the pinhole view over the field the distorted image sees, and where
/// each distorted pixel's ray falls in it.
struct Lens {
    pinhole: Box<Renderer>,
    /// Per pixel of the distorted image (row-major): the top-left pinhole pixel of its bilinear
    /// sample and the weights of the right and lower neighbours.
    taps: Vec<(u32, f32, f32)>,
    /// Per pixel of the distorted image: the nearest pinhole pixel.
    nearest: Vec<u32>,
}

/// How a traced image is stored: grey levels rounded to `u8`, or the `f32` values themselves.
trait Grey: Copy + Send + Sync {
    fn from_value(value: f32) -> Self;
}

impl Grey for u8 {
    #[inline]
    fn from_value(value: f32) -> Self {
        (value + 0.5).clamp(0.0, 255.0) as u8
    }
}

impl Grey for f32 {
    #[inline]
    fn from_value(value: f32) -> Self {
        value
    }
}

/// Pixels of a row traced together: the ray pass writes a run's hits, the shading pass
/// textures them eight at a time.
const RUN: usize = 64;

/// The hits of up to [`RUN`] consecutive pixels of a row: what the ray met and what shading it
/// needs (structure of arrays, so that the shading pass loads eight pixels at once), then the
/// grey values.
struct Run {
    /// Metres along the optical axis, infinite for sky.
    depth: [f64; RUN],
    /// Index into `Renderer::surfaces`, `u32::MAX` for sky.
    surface: [u32; RUN],
    /// The ray's squared length and the footprint's denominator (see `Span::fx_cos`).
    dir2: [f64; RUN],
    fx_cos: [f64; RUN],
    /// Texture coordinates with the surface's offset, m.
    tu: [f32; RUN],
    tv: [f32; RUN],
    /// `bright · shade` where the surface is hit, and the surface's `contrast2`.
    gain: [f32; RUN],
    contrast2: [f32; RUN],
    /// All bits set where the surface takes [`Texture::sample_detailed`] (a lane mask).
    detailed: [u32; RUN],
    /// Grey levels (0 without texture, [`SKY`] for sky).
    value: [f32; RUN],
}

impl Run {
    fn new() -> Self {
        Self {
            depth: [0.0; RUN],
            surface: [0; RUN],
            dir2: [0.0; RUN],
            fx_cos: [0.0; RUN],
            tu: [0.0; RUN],
            tv: [0.0; RUN],
            gain: [0.0; RUN],
            contrast2: [0.0; RUN],
            detailed: [0; RUN],
            value: [0.0; RUN],
        }
    }

    /// Pixel `i` sees sky; its shading inputs are ones the texture pass handles without a
    /// special case (an infinite footprint takes the coarsest level).
    #[inline(always)]
    fn sky(&mut self, i: usize) {
        self.depth[i] = f64::INFINITY;
        self.surface[i] = u32::MAX;
        self.dir2[i] = 1.0;
        self.fx_cos[i] = 1.0;
        self.tu[i] = 0.0;
        self.tv[i] = 0.0;
        self.gain[i] = 0.0;
        self.contrast2[i] = 0.0;
        self.detailed[i] = 0;
    }
}

/// Whether the eight-lane shading and exposure can run here.
fn simd_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

impl Renderer {
    /// Prepares `world` for rendering with `calib`: image size, intrinsics and lens distortion
    /// from it. A distortion that is not a lens model over the image
    /// ([`hal::calib::Intrinsics::check_lens`], which `Calibration::load` enforces) is not simulated:
    /// the view is an ideal pinhole's, with a warning.
    pub fn new(world: &World, calib: &Calibration) -> Self {
        let mut renderer = Self::pinhole(world, calib);
        renderer.lens = Lens::new(world, calib);
        renderer
    }

    /// The renderer of an ideal pinhole with `calib`'s intrinsics (its distortion ignored).
    fn pinhole(world: &World, calib: &Calibration) -> Self {
        let c = calib.camera;
        let (width, height) = (c.width as usize, c.height as usize);
        let xn = (0..width).map(|u| (u as f64 - c.cx) / c.fx).collect();
        let yn = (0..height).map(|v| (v as f64 - c.cy) / c.fy).collect();
        let mut surfaces = vec![
            Surface::new(SurfaceKind::Floor, 0.42, 0.55, [0.0, 0.0]),
            Surface::new(SurfaceKind::Ceiling, 0.85, 0.35, [1.3, 2.9]),
        ];
        let mut add = |kind: SurfaceKind, albedo: f32, contrast: f32, key: u64| {
            let h = mix64(key);
            let offset = [(h & 0xffff) as f32 / 65536.0 * 8.0, ((h >> 16) & 0xffff) as f32 / 65536.0 * 8.0];
            let jitter = ((h >> 32) & 0xff) as f32 / 255.0 - 0.5;
            surfaces.push(Surface::new(kind, albedo + 0.12 * jitter, contrast, offset));
            (surfaces.len() - 1) as u32
        };
        let mut prims = Vec::new();
        let mut seg_surface = std::collections::HashMap::new();
        for f in world.faces() {
            let surface = *seg_surface.entry((f.wall, f.segment)).or_insert_with(|| {
                add(
                    SurfaceKind::Wall { wall: f.wall, segment: f.segment },
                    0.62,
                    0.5,
                    ((f.wall as u64) << 20) ^ f.segment as u64 ^ 0xA11,
                )
            });
            let e = [f.b[0] - f.a[0], f.b[1] - f.a[1]];
            let len = e[0].hypot(e[1]);
            let normal = [-e[1] / len, e[0] / len];
            let shade = [light(normal), light([-normal[0], -normal[1]])];
            prims.push(Prim::Face {
                a: f.a,
                b: f.b,
                e,
                len,
                normal,
                shade,
                z0: f.z0,
                z1: f.z1,
                along0: f.along0,
                surface,
            });
        }
        for (i, b) in world.boxes.iter().enumerate() {
            let surface = add(SurfaceKind::Box(i), 0.5, 0.55, 0xB0C5 ^ ((i as u64) << 24));
            let (sin, cos) = b.yaw.sin_cos();
            prims.push(Prim::Box {
                center: b.center,
                cos,
                sin,
                hx: b.size[0] / 2.0,
                hy: b.size[1] / 2.0,
                h: b.size[2],
                surface,
            });
        }
        for (i, c) in world.cylinders.iter().enumerate() {
            let surface = add(SurfaceKind::Cylinder(i), 0.3, 0.6, 0xC11 ^ ((i as u64) << 28));
            prims.push(Prim::Cyl { center: c.center, r: c.radius, h: c.height, surface });
        }
        Self {
            calib: calib.clone(),
            width,
            height,
            xn,
            yn,
            prims,
            surfaces,
            ceiling: world.ceiling_height,
            tex: texture::shared(),
            simd: simd_available(),
            lens: None,
        }
    }

    pub fn calibration(&self) -> &Calibration {
        &self.calib
    }

    /// What surface id `id` (from [`Renderer::render_surfaces`]) is.
    pub fn surface_kind(&self, id: u32) -> SurfaceKind {
        self.surfaces.get(id as usize).map_or(SurfaceKind::Sky, |s| s.kind)
    }

    /// The clean view from robot pose `pose`.
    pub fn render(&self, pose: Pose) -> LumaImage {
        let mut img = LumaImage::new(self.width, self.height);
        self.render_frame(pose, pose, &Effects::default(), 0, &mut img);
        img
    }

    /// The clean view and its depth map.
    pub fn render_with_depth(&self, pose: Pose) -> (LumaImage, DepthMap) {
        let mut img = LumaImage::new(self.width, self.height);
        let mut depth = vec![0f32; self.width * self.height];
        self.trace(pose, Some(img.data_mut()), Some(&mut depth), None);
        (img, DepthMap { width: self.width, height: self.height, data: depth })
    }

    /// The depth map alone.
    pub fn depth(&self, pose: Pose) -> DepthMap {
        let mut depth = vec![0f32; self.width * self.height];
        self.trace(pose, None::<&mut [u8]>, Some(&mut depth), None);
        DepthMap { width: self.width, height: self.height, data: depth }
    }

    /// Per-pixel surface ids (see [`Renderer::surface_kind`]) and depth.
    pub fn render_surfaces(&self, pose: Pose) -> (Vec<u32>, DepthMap) {
        let mut ids = vec![0u32; self.width * self.height];
        let mut depth = vec![0f32; self.width * self.height];
        self.trace(pose, None::<&mut [u8]>, Some(&mut depth), Some(&mut ids));
        (ids, DepthMap { width: self.width, height: self.height, data: depth })
    }

    /// Renders frame number `seq` seen at `pose` into `out` (resized to the calibration's size),
    /// with `effects`: motion blur averages `blur_samples` views from `from` to `pose`; then
    /// exposure, then noise seeded by `(effects.seed, seq)`.
    pub fn render_frame(&self, from: Pose, pose: Pose, effects: &Effects, seq: u64, out: &mut LumaImage) {
        out.resize(self.width, self.height);
        let n = effects.blur_samples.max(1);
        let plain = n == 1 && effects.gain == 1.0 && effects.offset == 0.0 && effects.noise_sigma == 0.0;
        if plain {
            self.trace(pose, Some(out.data_mut()), None, None);
            return;
        }
        let (gain, offset, sigma) = (effects.gain as f32 / n as f32, effects.offset as f32, effects.noise_sigma as f32);
        let seed = mix64(effects.seed ^ mix64(seq.wrapping_add(0x5EED)));
        let w = self.width;
        if n == 1 && self.lens.is_none() {
            // one view through a pinhole (the simulator's frames): exposure and noise are
            // applied as each row is traced, without a buffer of values in between
            let view = self.view(from.lerp(&pose, 1.0));
            out.data_mut().par_chunks_mut(w).enumerate().with_min_len(4).for_each_init(Run::new, |run, (v, dst)| {
                self.trace_row(&view, v, true, run, |u, run, n| {
                    let noise = Noise { gain, offset, sigma, seed, first: v * w + u };
                    self.expose_run(&run.value[..n], &mut dst[u..u + n], &noise);
                });
            });
            return;
        }
        // a distorted lens: the pinhole view is accumulated, then warped
        let traced = self.lens.as_ref().map_or(self, |lens| &*lens.pinhole);
        let mut acc = vec![0f32; traced.width * traced.height];
        for k in 0..n {
            let f = if n == 1 { 1.0 } else { k as f64 / (n - 1) as f64 };
            let p = from.lerp(&pose, f);
            traced.trace_values(p, &mut acc, k > 0);
        }
        if let Some(lens) = &self.lens {
            let mut warped = vec![0f32; self.width * self.height];
            lens.bilinear(&acc, &mut warped, self.width);
            acc = warped;
        }
        out.data_mut().par_chunks_mut(w).zip(acc.par_chunks(w)).enumerate().for_each(|(v, (dst, src))| {
            for (u, (d, &s)) in dst.iter_mut().zip(src).enumerate() {
                *d = expose(s, gain, offset, sigma, seed, v * w + u);
            }
        });
    }

    /// Grey values as `f32` (added to `acc` when `add`).
    fn trace_values(&self, pose: Pose, acc: &mut [f32], add: bool) {
        let view = self.view(pose);
        acc.par_chunks_mut(self.width).enumerate().with_min_len(4).for_each_init(Run::new, |run, (v, row)| {
            if add {
                self.trace_row(&view, v, true, run, |u, run, n| {
                    row[u..u + n].iter_mut().zip(&run.value).for_each(|(a, &x)| *a += x)
                });
            } else {
                self.trace_row(&view, v, true, run, |u, run, n| row[u..u + n].copy_from_slice(&run.value[..n]));
            }
        });
    }

    /// The core: fills whichever outputs are given.
    fn trace<G: Grey>(&self, pose: Pose, img: Option<&mut [G]>, depth: Option<&mut [f32]>, ids: Option<&mut [u32]>) {
        if let Some(lens) = &self.lens {
            lens.trace(pose, self.width, img, depth, ids);
            return;
        }
        let view = self.view(pose);
        let w = self.width;
        let rows = self.height;
        let img_rows: Vec<Option<&mut [G]>> = match img {
            Some(i) => i.chunks_mut(w).map(Some).collect(),
            None => (0..rows).map(|_| None).collect(),
        };
        let depth_rows: Vec<Option<&mut [f32]>> = match depth {
            Some(d) => d.chunks_mut(w).map(Some).collect(),
            None => (0..rows).map(|_| None).collect(),
        };
        let id_rows: Vec<Option<&mut [u32]>> = match ids {
            Some(d) => d.chunks_mut(w).map(Some).collect(),
            None => (0..rows).map(|_| None).collect(),
        };
        // depth and surface ids alone need no texture
        let grey = img_rows.first().is_some_and(Option::is_some);
        img_rows.into_par_iter().zip(depth_rows).zip(id_rows).enumerate().with_min_len(4).for_each_init(
            Run::new,
            |run, (v, ((mut img, mut depth), mut ids))| {
                self.trace_row(&view, v, grey, run, |u, run, n| {
                    if let Some(r) = img.as_deref_mut() {
                        r[u..u + n].iter_mut().zip(&run.value).for_each(|(o, &x)| *o = G::from_value(x));
                    }
                    if let Some(r) = depth.as_deref_mut() {
                        r[u..u + n].iter_mut().zip(&run.depth).for_each(|(o, &x)| *o = x as f32);
                    }
                    if let Some(r) = ids.as_deref_mut() {
                        r[u..u + n].copy_from_slice(&run.surface[..n]);
                    }
                })
            },
        );
    }

    /// What every pixel of a view from `pose` shares: the camera and, per column, the sorted
    /// spans of its direction (level camera) or the solids within its wedge of directions
    /// (pitched camera).
    fn view(&self, pose: Pose) -> View {
        let cam = CameraPose::of_robot(pose, &self.calib);
        if cam.is_level() {
            // With pitch 0 every pixel of column u has the plan direction of (x_n(u), 0) and
            // every pixel of row v the vertical part of (0, y_n(v)) (`CameraPose::direction`:
            // the row's cos − y_n·sin is exactly 1 and the column's x_n does not enter the
            // vertical part), so both are computed once.
            // each column keeps its own sorted list (no room for [`MAX_SPANS`] reserved per column)
            let columns: Vec<Column> = self
                .xn
                .par_iter()
                .map(|&xn| {
                    let (dh, _) = cam.direction(xn, 0.0);
                    let mut spans: Vec<Span> = self.prims.iter().filter_map(|p| self.span(p, &cam, dh)).collect();
                    spans.sort_by(|a, b| a.s_in.total_cmp(&b.s_in));
                    let blocks_all = |s: &Span| !s.solid && s.z0 <= 0.0 && self.ceiling.is_some_and(|c| s.z1 >= c);
                    let n = spans.iter().take(MAX_SPANS).position(blocks_all).map_or(MAX_SPANS, |i| i + 1);
                    spans.truncate(n);
                    Column { dh, dh2: dh[0] * dh[0] + dh[1] * dh[1], spans }
                })
                .collect();
            View::Level { cam, columns }
        } else {
            let top = self.yn[0];
            let bottom = self.yn[self.height - 1];
            let candidates: Vec<Vec<u32>> = (0..self.width)
                .into_par_iter()
                .map(|u| {
                    let (da, _) = cam.direction(self.xn[u], top);
                    let (db, _) = cam.direction(self.xn[u], bottom);
                    let sa = if cross(da, db) >= 0.0 { 1.0 } else { -1.0 };
                    let mid = [da[0] + db[0], da[1] + db[1]];
                    let c = [cam.position[0], cam.position[1]];
                    self.prims
                        .iter()
                        .enumerate()
                        .filter(|(_, p)| {
                            let pts = p.bounds().map(|q| [q[0] - c[0], q[1] - c[1]]);
                            let out_a = pts.iter().all(|q| sa * cross(da, *q) < 0.0);
                            let out_b = pts.iter().all(|q| sa * cross(*q, db) < 0.0);
                            let behind = pts.iter().all(|q| mid[0] * q[0] + mid[1] * q[1] < 0.0);
                            !(out_a || out_b || behind)
                        })
                        .map(|(i, _)| i as u32)
                        .collect()
                })
                .collect();
            View::Pitched { cam, candidates }
        }
    }

    /// Traces row `v` of `view` in runs of up to [`RUN`] pixels, handing each run to `put` with
    /// its first column and length; without `grey` the values are left 0 (no texture is
    /// sampled), sky's [`SKY`]. `run` is scratch space kept across rows (every lane that is
    /// shaded or handed out is written first, so what an earlier row left is never read).
    #[inline(always)]
    fn trace_row(&self, view: &View, v: usize, grey: bool, run: &mut Run, mut put: impl FnMut(usize, &Run, usize)) {
        match view {
            View::Level { cam, columns } => {
                let (_, dz) = cam.direction(0.0, self.yn[v]);
                let zc = cam.position[2];
                let (mut best0, mut base) = (f64::INFINITY, Target::Sky);
                if dz < 0.0 {
                    best0 = -zc / dz;
                    base = Target::Floor;
                } else if let Some(c) = self.ceiling.filter(|_| dz > 0.0) {
                    best0 = (c - zc) / dz;
                    base = Target::Ceiling;
                }
                let flat = Flat::of(self, dz);
                self.runs(run, grey, &mut put, columns.iter(), |run, i, col| {
                    let (mut best, mut what) = (best0, base);
                    for s in &col.spans {
                        if s.s_in >= best {
                            break;
                        }
                        consider(s, zc, dz, &mut best, &mut what);
                    }
                    let ray = Ray { dh: col.dh, dz, dir2: col.dh2 + flat.dz2, flat_fx_cos: flat.fx_cos };
                    self.prepare(cam, &ray, best, what, run, i);
                });
            }
            View::Pitched { cam, candidates } => {
                self.runs(run, grey, &mut put, candidates.iter().enumerate(), |run, i, (u, candidates)| {
                    self.pitched_pixel(cam, candidates, u, v, run, i)
                });
            }
        }
    }

    /// Feeds the pixels of a row (`pixels`, one item per column) to `trace`, which writes each
    /// one's hit into the run at its index; shades each full run (or the row's last) and hands
    /// it to `put`.
    #[inline(always)]
    fn runs<P>(
        &self,
        run: &mut Run,
        grey: bool,
        put: &mut impl FnMut(usize, &Run, usize),
        pixels: impl Iterator<Item = P>,
        mut trace: impl FnMut(&mut Run, usize, P),
    ) {
        let mut start = 0;
        let mut n = 0;
        for p in pixels {
            trace(run, n, p);
            n += 1;
            if n == RUN {
                self.finish_run(run, grey, n);
                put(start, run, n);
                start += n;
                n = 0;
            }
        }
        if n > 0 {
            self.finish_run(run, grey, n);
            put(start, run, n);
        }
    }

    /// The grey values of the first `n` hits of `run` (0 without `grey`, sky's [`SKY`]).
    #[inline(always)]
    fn finish_run(&self, run: &mut Run, grey: bool, n: usize) {
        if !grey {
            for i in 0..n {
                run.value[i] = if run.surface[i] == u32::MAX { SKY } else { 0.0 };
            }
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if self.simd {
            // SAFETY: `simd` is set only where AVX2 was detected.
            unsafe { self.shade_avx2(run, n) };
            return;
        }
        for i in 0..n {
            run.value[i] = self.shade(run, i);
        }
    }

    /// The nearest hit of pixel (u, v) of a pitched camera, from the solids in its column's
    /// wedge, written into `run` at `i`.
    fn pitched_pixel(&self, cam: &CameraPose, candidates: &[u32], u: usize, v: usize, run: &mut Run, i: usize) {
        let (dh, dz) = cam.direction(self.xn[u], self.yn[v]);
        let zc = cam.position[2];
        let (mut best, mut what) = (f64::INFINITY, Target::Sky);
        if dz < 0.0 {
            best = -zc / dz;
            what = Target::Floor;
        } else if let Some(c) = self.ceiling.filter(|_| dz > 0.0) {
            best = (c - zc) / dz;
            what = Target::Ceiling;
        }
        // the span whose side is the nearest hit so far (spans are computed per pixel here)
        let mut side: Option<Span> = None;
        for &c in candidates {
            if let Some(s) = self.span(&self.prims[c as usize], cam, dh)
                && s.s_in < best
            {
                let mut got = Target::Sky;
                consider(&s, zc, dz, &mut best, &mut got);
                match got {
                    Target::Side(_) => side = Some(s),
                    Target::Top(surface) => {
                        what = Target::Top(surface);
                        side = None;
                    }
                    _ => {}
                }
            }
        }
        let what = side.as_ref().map_or(what, Target::Side);
        let ray = Ray { dh, dz, dir2: dh[0] * dh[0] + dh[1] * dh[1] + dz * dz, flat_fx_cos: Flat::of(self, dz).fx_cos };
        self.prepare(cam, &ray, best, what, run, i);
    }

    /// Writes into `run` at `i` a hit at `ray`'s parameter `s` (its depth) on `what`: the
    /// surface, and what its texture sample and grey level need.
    #[inline(always)]
    fn prepare(&self, cam: &CameraPose, ray: &Ray, s: f64, what: Target, run: &mut Run, i: usize) {
        let Ray { dh, dz, dir2, flat_fx_cos } = *ray;
        let at = |s: f64| [cam.position[0] + s * dh[0], cam.position[1] + s * dh[1]];
        let (surface, tu, tv, gain, fx_cos) = match what {
            Target::Sky => {
                run.sky(i);
                return;
            }
            Target::Floor | Target::Ceiling => {
                let surface = if matches!(what, Target::Floor) { 0 } else { 1 };
                let (sf, p) = (&self.surfaces[surface as usize], at(s));
                (surface, p[0] as f32 + sf.offset[0], p[1] as f32 + sf.offset[1], sf.bright, flat_fx_cos)
            }
            Target::Top(surface) => {
                let (sf, p) = (&self.surfaces[surface as usize], at(s));
                let (tu, tv) = ((p[0] + 3.7) as f32 + sf.offset[0], (p[1] + 1.9) as f32 + sf.offset[1]);
                // the tops of boxes are lit 1.12 times
                (surface, tu, tv, sf.bright * 1.12, flat_fx_cos)
            }
            Target::Side(sp) => {
                let sf = &self.surfaces[sp.surface as usize];
                (sp.surface, sp.tu, (cam.position[2] + s * dz) as f32 + sf.offset[1], sp.gain, sp.fx_cos)
            }
        };
        let sf = &self.surfaces[surface as usize];
        run.depth[i] = s;
        run.surface[i] = surface;
        run.dir2[i] = dir2;
        run.fx_cos[i] = fx_cos;
        run.tu[i] = tu;
        run.tv[i] = tv;
        run.gain[i] = gain;
        run.contrast2[i] = sf.contrast2;
        run.detailed[i] = if sf.detailed { u32::MAX } else { 0 };
    }

    /// The grey level of hit `i` of `run`: the texture sampled with the pixel's footprint on
    /// the surface, scaled by the surface's gain and contrast.
    #[inline(always)]
    fn shade(&self, run: &Run, i: usize) -> f32 {
        if run.surface[i] == u32::MAX {
            return SKY;
        }
        let (s, dir2, fx_cos) = (run.depth[i], run.dir2[i], run.fx_cos[i]);
        let footprint = (s * dir2 / (fx_cos * dir2.sqrt())) as f32;
        let (tu, tv) = (run.tu[i], run.tv[i]);
        let t = if run.detailed[i] != 0 {
            self.tex.sample_detailed(tu, tv, footprint)
        } else {
            self.tex.sample(tu, tv, footprint)
        };
        run.gain[i] * (1.0 + run.contrast2[i] * (t - 0.5))
    }

    /// [`Renderer::shade`] of the first `n` hits of `run`, eight at a time: the same IEEE
    /// operations in the same order per lane, so every value is bit for bit the scalar one.
    ///
    /// # Safety
    /// AVX2 must be available.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn shade_avx2(&self, run: &mut Run, n: usize) {
        use std::arch::x86_64::*;
        let end = n.next_multiple_of(8);
        // the lanes past the row's end are shaded as sky and not handed out
        for i in n..end {
            run.sky(i);
        }
        for g in (0..end).step_by(8) {
            // SAFETY: AVX2 is available (the caller's contract); every load and store is of
            // eight elements from `g`, and `g + 8 ≤ end ≤ RUN` (RUN is a multiple of 8).
            unsafe {
                let footprint = |k: usize| {
                    let s = _mm256_loadu_pd(run.depth.as_ptr().add(g + k));
                    let dir2 = _mm256_loadu_pd(run.dir2.as_ptr().add(g + k));
                    let fx_cos = _mm256_loadu_pd(run.fx_cos.as_ptr().add(g + k));
                    _mm256_cvtpd_ps(_mm256_div_pd(_mm256_mul_pd(s, dir2), _mm256_mul_pd(fx_cos, _mm256_sqrt_pd(dir2))))
                };
                let footprint = _mm256_set_m128(footprint(4), footprint(0));
                let tu = _mm256_loadu_ps(run.tu.as_ptr().add(g));
                let tv = _mm256_loadu_ps(run.tv.as_ptr().add(g));
                let detailed = _mm256_loadu_ps(run.detailed.as_ptr().add(g) as *const f32);
                let mut bad = _mm256_setzero_ps();
                let t = texture::avx2::sample(self.tex, tu, tv, footprint, detailed, &mut bad);
                let gain = _mm256_loadu_ps(run.gain.as_ptr().add(g));
                let contrast2 = _mm256_loadu_ps(run.contrast2.as_ptr().add(g));
                let one = _mm256_set1_ps(1.0);
                let value = _mm256_mul_ps(
                    gain,
                    _mm256_add_ps(one, _mm256_mul_ps(contrast2, _mm256_sub_ps(t, _mm256_set1_ps(0.5)))),
                );
                let surface = _mm256_loadu_si256(run.surface.as_ptr().add(g) as *const __m256i);
                let sky = _mm256_castsi256_ps(_mm256_cmpeq_epi32(surface, _mm256_set1_epi32(-1)));
                _mm256_storeu_ps(run.value.as_mut_ptr().add(g), _mm256_blendv_ps(value, _mm256_set1_ps(SKY), sky));
                if _mm256_movemask_ps(bad) != 0 {
                    for i in g..g + 8 {
                        run.value[i] = self.shade(run, i);
                    }
                }
            }
        }
    }

    /// Exposure, sensor noise and rounding ([`expose`]) of a run of values into `out`.
    #[inline(always)]
    fn expose_run(&self, values: &[f32], out: &mut [u8], noise: &Noise) {
        let mut done = 0;
        #[cfg(target_arch = "x86_64")]
        if self.simd && noise.first + values.len() <= u32::MAX as usize {
            // SAFETY: `simd` is set only where AVX2 was detected; the pixel indices fit 32 bits.
            done = unsafe { expose_avx2(values, out, noise) };
        }
        let Noise { gain, offset, sigma, seed, first } = *noise;
        for (k, (o, &x)) in out.iter_mut().zip(values).enumerate().skip(done) {
            *o = expose(x, gain, offset, sigma, seed, first + k);
        }
    }

    /// Where the horizontal ray from the camera along `dh` meets `prim`, if it does ahead.
    fn span(&self, prim: &Prim, cam: &CameraPose, dh: [f64; 2]) -> Option<Span> {
        let c = [cam.position[0], cam.position[1]];
        // the entry face's shading seen along `dh`
        let finish =
            |s_in: f64, s_out: f64, z0: f64, z1: f64, solid: bool, surface: u32, tu: f64, n: [f64; 2], shade: f32| {
                let sf = &self.surfaces[surface as usize];
                let cos = (n[0] * dh[0] + n[1] * dh[1]).abs();
                Some(Span {
                    s_in,
                    s_out,
                    z0,
                    z1,
                    fx_cos: self.calib.camera.fx * cos.max(1e-3),
                    solid,
                    surface,
                    tu: tu as f32 + sf.offset[0],
                    gain: sf.bright * shade,
                })
            };
        match *prim {
            Prim::Face { a, e, len, normal, shade, z0, z1, along0, surface, .. } => {
                let den = cross(dh, e);
                if den.abs() < 1e-12 {
                    return None;
                }
                let ac = [a[0] - c[0], a[1] - c[1]];
                let s = cross(ac, e) / den;
                let t = cross(ac, dh) / den;
                if s <= 1e-9 || !(0.0..=1.0).contains(&t) {
                    return None;
                }
                let (n, shade) = if normal[0] * dh[0] + normal[1] * dh[1] > 0.0 {
                    ([-normal[0], -normal[1]], shade[1])
                } else {
                    (normal, shade[0])
                };
                finish(s, s, z0, z1, false, surface, along0 + t * len, n, shade)
            }
            Prim::Box { center, cos, sin, hx, hy, h, surface } => {
                let o = [c[0] - center[0], c[1] - center[1]];
                let ol = [cos * o[0] + sin * o[1], -sin * o[0] + cos * o[1]];
                let dl = [cos * dh[0] + sin * dh[1], -sin * dh[0] + cos * dh[1]];
                let half = [hx, hy];
                let (mut t_in, mut t_out, mut axis, mut sign) = (f64::NEG_INFINITY, f64::INFINITY, 0usize, 0.0);
                for k in 0..2 {
                    if dl[k].abs() < 1e-12 {
                        if ol[k].abs() > half[k] {
                            return None;
                        }
                        continue;
                    }
                    let t1 = (-half[k] - ol[k]) / dl[k];
                    let t2 = (half[k] - ol[k]) / dl[k];
                    let (lo, hi) = if t1 < t2 { (t1, t2) } else { (t2, t1) };
                    if lo > t_in {
                        t_in = lo;
                        axis = k;
                        sign = if dl[k] > 0.0 { -1.0 } else { 1.0 };
                    }
                    t_out = t_out.min(hi);
                }
                if t_in > t_out || t_in <= 1e-9 {
                    return None;
                }
                let hit = [ol[0] + t_in * dl[0], ol[1] + t_in * dl[1]];
                let nl = if axis == 0 { [sign, 0.0] } else { [0.0, sign] };
                let n = [cos * nl[0] - sin * nl[1], sin * nl[0] + cos * nl[1]];
                let tu = if axis == 0 { hit[1] + 5.0 * (sign + 2.0) } else { hit[0] + 5.0 * (sign + 4.0) };
                finish(t_in, t_out, 0.0, h, true, surface, tu, n, light(n))
            }
            Prim::Cyl { center, r, h, surface } => {
                let o = [c[0] - center[0], c[1] - center[1]];
                let a = dh[0] * dh[0] + dh[1] * dh[1];
                let b = 2.0 * (o[0] * dh[0] + o[1] * dh[1]);
                let cc = o[0] * o[0] + o[1] * o[1] - r * r;
                let disc = b * b - 4.0 * a * cc;
                if disc < 0.0 {
                    return None;
                }
                let sq = disc.sqrt();
                let (t_in, t_out) = ((-b - sq) / (2.0 * a), (-b + sq) / (2.0 * a));
                if t_in <= 1e-9 {
                    return None;
                }
                let p = [o[0] + t_in * dh[0], o[1] + t_in * dh[1]];
                let n = [p[0] / r, p[1] / r];
                finish(t_in, t_out, 0.0, h, true, surface, p[1].atan2(p[0]) * r, n, light(n))
            }
        }
    }
}

/// The span `s` if the ray of slope `dz` from height `zc` meets its side or its top before
/// `best` (which it then becomes).
#[inline(always)]
fn consider<'a>(s: &'a Span, zc: f64, dz: f64, best: &mut f64, what: &mut Target<'a>) {
    let z = zc + s.s_in * dz;
    if z >= s.z0 && z <= s.z1 {
        *best = s.s_in;
        *what = Target::Side(s);
    } else if s.solid && z > s.z1 && dz < 0.0 {
        let st = (s.z1 - zc) / dz;
        if st <= s.s_out && st < *best {
            *best = st;
            *what = Target::Top(s.surface);
        }
    }
}

/// Exposure, sensor noise and rounding of the value `s` of pixel `i` (row-major) of a frame.
#[inline(always)]
fn expose(s: f32, gain: f32, offset: f32, sigma: f32, seed: u64, i: usize) -> u8 {
    let mut v = s * gain + offset;
    if sigma > 0.0 {
        v += sigma * gaussian(seed ^ (i as u64).wrapping_mul(0x9E37_79B9));
    }
    (v + 0.5).clamp(0.0, 255.0) as u8
}

/// What [`expose`] takes besides a value: exposure, noise, and the row-major index of a run's
/// first pixel.
#[derive(Clone, Copy)]
struct Noise {
    gain: f32,
    offset: f32,
    sigma: f32,
    seed: u64,
    first: usize,
}

/// [`expose`] of the values of `values` eight at a time into `out`, bit for bit (the hash in
/// 64-bit lanes, the same float operations per lane); returns how many it wrote (a multiple of
/// eight, the rest is the caller's).
///
/// # Safety
/// AVX2 must be available; `noise.first + values.len()` fits 32 bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn expose_avx2(values: &[f32], out: &mut [u8], noise: &Noise) -> usize {
    use std::arch::x86_64::*;
    let n = values.len().min(out.len()) / 8 * 8;
    let (gain, offset, sigma) = (_mm256_set1_ps(noise.gain), _mm256_set1_ps(noise.offset), _mm256_set1_ps(noise.sigma));
    let seed = _mm256_set1_epi64x(noise.seed as i64);
    let golden = _mm256_set1_epi64x(0x9E37_79B9);
    let sqrt3 = _mm256_set1_ps(3.0f32.sqrt());
    for g in (0..n).step_by(8) {
        // SAFETY: AVX2 is available (the caller's contract); eight values are read from `g`
        // and eight bytes written there, `g + 8 ≤ n` within both slices.
        unsafe {
            let mut v = _mm256_add_ps(_mm256_mul_ps(_mm256_loadu_ps(values.as_ptr().add(g)), gain), offset);
            if noise.sigma > 0.0 {
                let i = (noise.first + g) as i64;
                // `(i as u64).wrapping_mul(0x9E37_79B9)`: exact as a 32 × 32 → 64-bit product
                // while the index fits 32 bits
                let key = |i: i64| {
                    let index = _mm256_set_epi64x(i + 3, i + 2, i + 1, i);
                    gaussian_sums(_mm256_xor_si256(seed, _mm256_mul_epu32(index, golden)))
                };
                let sums = _mm256_set_m128i(key(i + 4), key(i));
                let g = _mm256_mul_ps(
                    _mm256_sub_ps(
                        _mm256_div_ps(_mm256_cvtepi32_ps(sums), _mm256_set1_ps(65535.0)),
                        _mm256_set1_ps(2.0),
                    ),
                    sqrt3,
                );
                v = _mm256_add_ps(v, _mm256_mul_ps(sigma, g));
            }
            // `maxps` returns its second operand for a NaN first one: NaN becomes 0, as the
            // saturating `as u8` makes it
            let v = _mm256_min_ps(
                _mm256_max_ps(_mm256_add_ps(v, _mm256_set1_ps(0.5)), _mm256_setzero_ps()),
                _mm256_set1_ps(255.0),
            );
            let v = _mm256_cvttps_epi32(v);
            let words = _mm_packus_epi32(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
            _mm_storel_epi64(out.as_mut_ptr().add(g) as *mut __m128i, _mm_packus_epi16(words, words));
        }
    }
    n
}

/// The four 16-bit fields of `mix64(key)` summed ([`gaussian`] before scaling), for four keys:
/// the sums (below 2¹⁸) as four 32-bit integers.
///
/// # Safety
/// AVX2 must be available.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn gaussian_sums(key: std::arch::x86_64::__m256i) -> std::arch::x86_64::__m128i {
    use std::arch::x86_64::*;
    // SAFETY (whole body): the caller guarantees AVX2.
    unsafe {
        let z = mul64(_mm256_xor_si256(key, _mm256_srli_epi64::<30>(key)), 0xBF58_476D_1CE4_E5B9);
        let z = mul64(_mm256_xor_si256(z, _mm256_srli_epi64::<27>(z)), 0x94D0_49BB_1331_11EB);
        let h = _mm256_xor_si256(z, _mm256_srli_epi64::<31>(z));
        let fields = _mm256_set1_epi64x(0x0000_ffff_0000_ffff);
        let pairs = _mm256_add_epi64(_mm256_and_si256(h, fields), _mm256_and_si256(_mm256_srli_epi64::<16>(h), fields));
        let sums = _mm256_add_epi64(pairs, _mm256_srli_epi64::<32>(pairs));
        // the low 32 bits of each 64-bit lane
        let low = _mm256_permutevar8x32_epi32(sums, _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6));
        _mm256_castsi256_si128(low)
    }
}

/// Wrapping 64-bit products `z · c` of four lanes, from three 32 × 32 → 64-bit ones.
///
/// # Safety
/// AVX2 must be available.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn mul64(z: std::arch::x86_64::__m256i, c: u64) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    // SAFETY (whole body): the caller guarantees AVX2.
    unsafe {
        let lo = _mm256_set1_epi64x(c as u32 as i64);
        let hi = _mm256_set1_epi64x((c >> 32) as i64);
        let cross = _mm256_add_epi64(_mm256_mul_epu32(_mm256_srli_epi64::<32>(z), lo), _mm256_mul_epu32(z, hi));
        _mm256_add_epi64(_mm256_mul_epu32(z, lo), _mm256_slli_epi64::<32>(cross))
    }
}

impl Lens {
    /// The lens of `calib`, `None` for a pinhole or a distortion that is not a lens model.
    fn new(world: &World, calib: &Calibration) -> Option<Self> {
        let c = calib.camera;
        if undistort::is_identity(&c.distortion) {
            return None;
        }
        let refuse = |problem: String| {
            tracing::warn!("camera.distortion {:?} {problem}: rendering an ideal pinhole", c.distortion);
            None
        };
        if let Err(problem) = c.check_lens() {
            return refuse(problem);
        }
        let (width, height) = (c.width as usize, c.height as usize);
        if width < 2 || height < 2 {
            return refuse(format!("on a {width}x{height} image"));
        }
        // each pixel's ray: the ideal (pinhole) normalized point the lens put there
        let rays: Option<Vec<[f64; 2]>> = (0..width * height)
            .into_par_iter()
            .map(|i| {
                let (u, v) = ((i % width) as f64, (i / width) as f64);
                undistort_normalized(&c.distortion, [(u - c.cx) / c.fx, (v - c.cy) / c.fy])
            })
            .collect();
        let Some(rays) = rays else {
            return refuse("cannot be inverted at every pixel".into());
        };
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for r in &rays {
            for k in 0..2 {
                lo[k] = lo[k].min(r[k]);
                hi[k] = hi[k].max(r[k]);
            }
        }
        // the pinhole image: same focal lengths, spanning the rays with a margin
        let cx = -lo[0] * c.fx + LENS_MARGIN_PX;
        let cy = -lo[1] * c.fy + LENS_MARGIN_PX;
        let inner_w = ((hi[0] - lo[0]) * c.fx + 2.0 * LENS_MARGIN_PX).ceil() + 1.0;
        let inner_h = ((hi[1] - lo[1]) * c.fy + 2.0 * LENS_MARGIN_PX).ceil() + 1.0;
        if inner_w > LENS_MAX_GROWTH * width as f64 || inner_h > LENS_MAX_GROWTH * height as f64 {
            return refuse(format!("needs a {inner_w}x{inner_h} pinhole view"));
        }
        let (inner_w, inner_h) = (inner_w as usize, inner_h as usize);
        let mut inner = calib.clone();
        inner.camera = Intrinsics {
            width: inner_w as u32,
            height: inner_h as u32,
            fx: c.fx,
            fy: c.fy,
            cx,
            cy,
            distortion: [0.0; 5],
        };
        let at = |r: &[f64; 2]| {
            [(c.fx * r[0] + cx).clamp(0.0, (inner_w - 1) as f64), (c.fy * r[1] + cy).clamp(0.0, (inner_h - 1) as f64)]
        };
        let taps = rays
            .iter()
            .map(|r| {
                let [x, y] = at(r);
                let (x0, y0) = ((x.floor() as usize).min(inner_w - 2), (y.floor() as usize).min(inner_h - 2));
                ((y0 * inner_w + x0) as u32, (x - x0 as f64) as f32, (y - y0 as f64) as f32)
            })
            .collect();
        let nearest = rays
            .iter()
            .map(|r| {
                let [x, y] = at(r);
                (y.round() as usize * inner_w + x.round() as usize) as u32
            })
            .collect();
        Some(Self { pinhole: Box::new(Renderer::pinhole(world, &inner)), taps, nearest })
    }

    /// Traces the pinhole view and warps whichever outputs are given (rows of `width` pixels).
    fn trace<G: Grey>(
        &self,
        pose: Pose,
        width: usize,
        img: Option<&mut [G]>,
        depth: Option<&mut [f32]>,
        ids: Option<&mut [u32]>,
    ) {
        let n = self.pinhole.width * self.pinhole.height;
        let mut values = img.as_ref().map(|_| vec![0f32; n]);
        let mut inner_depth = depth.as_ref().map(|_| vec![0f32; n]);
        let mut inner_ids = ids.as_ref().map(|_| vec![0u32; n]);
        self.pinhole.trace(pose, values.as_deref_mut(), inner_depth.as_deref_mut(), inner_ids.as_deref_mut());
        if let (Some(out), Some(values)) = (img, &values) {
            self.bilinear(values, out, width);
        }
        if let (Some(out), Some(inner)) = (depth, &inner_depth) {
            out.par_iter_mut().zip(&self.nearest).for_each(|(d, &i)| *d = inner[i as usize]);
        }
        if let (Some(out), Some(inner)) = (ids, &inner_ids) {
            out.par_iter_mut().zip(&self.nearest).for_each(|(d, &i)| *d = inner[i as usize]);
        }
    }

    /// Bilinear samples of the pinhole image's `values` at each distorted pixel's ray.
    fn bilinear<G: Grey>(&self, values: &[f32], out: &mut [G], width: usize) {
        let w = self.pinhole.width;
        out.par_chunks_mut(width).zip(self.taps.par_chunks(width)).for_each(|(row, taps)| {
            for (o, &(i, fx, fy)) in row.iter_mut().zip(taps) {
                let i = i as usize;
                let top = values[i] + fx * (values[i + 1] - values[i]);
                let bottom = values[i + w] + fx * (values[i + w + 1] - values[i + w]);
                *o = G::from_value(top + fy * (bottom - top));
            }
        });
    }
}

/// Per-view data of [`Renderer::view`].
enum View {
    Level { cam: CameraPose, columns: Vec<Column> },
    Pitched { cam: CameraPose, candidates: Vec<Vec<u32>> },
}

/// A pixel column of a level camera: its plan direction, that direction's squared length and
/// the spans it meets, nearest first (at most [`MAX_SPANS`], none behind one that blocks all).
struct Column {
    dh: [f64; 2],
    dh2: f64,
    spans: Vec<Span>,
}

/// A pixel's ray `(dh, dz)`: plan direction and slope, its squared length `dir2`, and the
/// footprint's denominator on a horizontal surface.
#[derive(Clone, Copy)]
struct Ray {
    dh: [f64; 2],
    dz: f64,
    dir2: f64,
    flat_fx_cos: f64,
}

/// What the floor, the ceiling and the tops of boxes need of a ray's slope `dz`.
struct Flat {
    dz2: f64,
    /// `fx · max(|dz|, 1e-3)`: the footprint's denominator on a horizontal surface.
    fx_cos: f64,
}

impl Flat {
    #[inline(always)]
    fn of(r: &Renderer, dz: f64) -> Self {
        Self { dz2: dz * dz, fx_cos: r.calib.camera.fx * dz.abs().max(1e-3) }
    }
}

/// What a ray meets first.
#[derive(Clone, Copy)]
enum Target<'a> {
    Sky,
    Floor,
    Ceiling,
    Side(&'a Span),
    Top(u32),
}

/// An approximately standard-normal value from a hash (sum of four uniforms, Irwin–Hall).
#[inline]
fn gaussian(key: u64) -> f32 {
    let h = mix64(key);
    let s = (h & 0xffff) + ((h >> 16) & 0xffff) + ((h >> 32) & 0xffff) + (h >> 48);
    (s as f32 / 65535.0 - 2.0) * 3.0f32.sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene;

    fn small() -> Calibration {
        Calibration::nominal_c310().scaled_to(320, 180)
    }

    #[test]
    fn frontal_wall_depth_is_exact() {
        let calib = small();
        let sc = scene::wall(3.0, 0.0);
        let r = Renderer::new(&sc.world, &calib);
        let d = r.depth(sc.start(&calib));
        // Rows above the floor-wall junction all see the wall at depth 3.
        for v in [0usize, 50, 90, 100] {
            for u in [0usize, 160, 319] {
                assert!((d.at(u, v) - 3.0).abs() < 1e-5, "({u},{v}) {}", d.at(u, v));
            }
        }
    }

    #[test]
    fn floor_pixel_depth_matches_closed_form() {
        let calib = small();
        let sc = scene::empty();
        let r = Renderer::new(&sc.world, &calib);
        let d = r.depth(sc.start(&calib));
        let c = calib.camera;
        let v = 150usize;
        let expect = calib.mount.z_m * c.fy / (v as f64 - c.cy);
        assert!((d.at(10, v) as f64 - expect).abs() < 1e-5 * expect, "{} vs {expect}", d.at(10, v));
        assert!(d.at(10, 10).is_infinite());
    }

    #[test]
    fn pitched_and_level_paths_agree_at_zero_pitch_limit() {
        // A tiny pitch takes the per-pixel path; depths must match the level path closely.
        let mut calib = small();
        let sc = scene::corner(2.5, std::f64::consts::FRAC_PI_2).with_obstacle(1.5, 0.1);
        let level = Renderer::new(&sc.world, &calib).depth(sc.start(&calib));
        calib.mount.pitch_rad = 1e-7;
        let pitched = Renderer::new(&sc.world, &calib).depth(sc.start(&calib));
        let bad = level
            .data
            .iter()
            .zip(&pitched.data)
            .filter(|(a, b)| !(a.is_infinite() && b.is_infinite()) && (*a - *b).abs() > 1e-3 * a.abs().max(1.0))
            .count();
        assert!(bad < 10, "{bad} pixels differ");
    }

    #[test]
    fn rendering_is_deterministic_and_noise_is_seeded() {
        let calib = small();
        let w = World::office();
        let r = Renderer::new(&w, &calib);
        let fx = Effects { noise_sigma: 3.0, seed: 7, blur_samples: 2, ..Effects::default() };
        let to = w.start.advance(0.3, 0.1, 0.1);
        let mut a = LumaImage::default();
        let mut b = LumaImage::default();
        r.render_frame(w.start, to, &fx, 4, &mut a);
        r.render_frame(w.start, to, &fx, 4, &mut b);
        assert_eq!(a, b);
        r.render_frame(w.start, to, &Effects { seed: 8, ..fx.clone() }, 4, &mut b);
        assert_ne!(a, b);
        // The noise has about the requested spread.
        let clean = {
            let mut c = LumaImage::default();
            r.render_frame(w.start, to, &Effects { noise_sigma: 0.0, ..fx.clone() }, 4, &mut c);
            c
        };
        let n = a.data().len() as f64;
        let var = a.data().iter().zip(clean.data()).map(|(x, y)| (*x as f64 - *y as f64).powi(2)).sum::<f64>() / n;
        assert!((var.sqrt() - 3.0).abs() < 0.3, "{}", var.sqrt());
    }

    /// The 90° lens of `calib/wide90.toml` with barrel distortion, at 320×180.
    fn distorted_wide() -> Calibration {
        let mut calib = Calibration::nominal_c310();
        calib.camera.fx = 640.0;
        calib.camera.fy = 640.0;
        calib.camera.distortion = [-0.25, 0.06, 0.0005, -0.0003, 0.0];
        calib.scaled_to(320, 180)
    }

    #[test]
    fn only_a_distorted_lens_takes_the_two_pass_path() {
        let w = World::office();
        assert!(Renderer::new(&w, &small()).lens.is_none());
        let r = Renderer::new(&w, &distorted_wide());
        let inner = &r.lens.as_ref().unwrap().pinhole;
        // barrel distortion: the pinhole view of the same field is larger than the image
        assert!(inner.width > 320 && inner.height > 180, "{}x{}", inner.width, inner.height);
        let folded = Calibration {
            camera: Intrinsics { distortion: [-2.0, 0.0, 0.0, 0.0, 0.0], ..distorted_wide().camera },
            ..small()
        };
        assert!(Renderer::new(&w, &folded).lens.is_none(), "not a lens: rendered as a pinhole");
    }

    #[test]
    fn distorted_floor_depth_follows_the_lens_model() {
        // pixel (u, v) sees the floor along its ideal ray (x, y, 1): depth = height / y
        let calib = distorted_wide();
        let sc = scene::empty();
        let (ids, d) = Renderer::new(&sc.world, &calib).render_surfaces(sc.start(&calib));
        let c = calib.camera;
        for (u, v) in [(0usize, 179usize), (10, 150), (160, 170), (300, 120), (319, 100)] {
            let [_, y] =
                undistort_normalized(&c.distortion, [(u as f64 - c.cx) / c.fx, (v as f64 - c.cy) / c.fy]).unwrap();
            let expect = calib.mount.z_m / y;
            // the nearest pinhole pixel's ray is within half a pixel of this one's
            let tolerance = 0.5 / (c.fy * y) * expect;
            assert!((d.at(u, v) as f64 - expect).abs() <= tolerance, "({u},{v}) {} vs {expect}", d.at(u, v));
            assert_eq!(ids[v * 320 + u], 0, "({u},{v}) is floor");
        }
        assert!(d.at(160, 10).is_infinite());
    }

    #[test]
    fn distorted_frames_warp_before_the_effects() {
        // two identical blur samples at half gain each: the effects path equals the clean render
        let calib = distorted_wide();
        let w = World::office();
        let r = Renderer::new(&w, &calib);
        let mut blurred = LumaImage::default();
        r.render_frame(w.start, w.start, &Effects { blur_samples: 2, ..Effects::default() }, 0, &mut blurred);
        let clean = r.render(w.start);
        let worst = clean.data().iter().zip(blurred.data()).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
        assert!(worst <= 1, "{worst}");
        assert_eq!(r.render_with_depth(w.start).0, clean);
    }

    /// FNV-1a over bytes: a stable fingerprint of rendered output.
    fn fingerprint(bytes: impl IntoIterator<Item = u8>) -> u64 {
        bytes.into_iter().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3))
    }

    /// The views `flownav sim` renders (office with random obstacles, 320×180, sensor noise, the
    /// level camera) along a path through the room, the doorway and the corridor, pinned bit for
    /// bit: a simulated mission is deterministic for a seed only while its frames are. A change
    /// that alters a single grey level, depth or surface id fails here; a deliberate change of
    /// the picture must update these fingerprints (and re-measure the missions).
    #[test]
    fn sim_views_are_pinned_bit_for_bit() {
        let calib = small();
        let world = World::office().with_random_obstacles(1).unwrap();
        let r = Renderer::new(&world, &calib);
        let fx = Effects { noise_sigma: 2.0, seed: 1, ..Effects::default() };
        let poses = [
            world.start,
            world.start.advance(0.4, 0.3, 1.0),
            Pose::new(20.0, 0.0, std::f64::consts::PI),
            Pose::new(14.0, 0.3, 3.0),
            Pose::new(9.0, 0.4, 1.5),
            Pose::new(5.0, -0.5, 0.2),
        ];
        let mut img = LumaImage::default();
        let mut frames = Vec::new();
        for (seq, p) in poses.iter().enumerate() {
            r.render_frame(*p, *p, &fx, seq as u64, &mut img);
            frames.extend_from_slice(img.data());
        }
        assert_eq!(fingerprint(frames), 742_913_129_166_118_754, "noisy frames");
        let clean = r.render(poses[2]);
        assert_eq!(fingerprint(clean.data().iter().copied()), 16_461_047_994_621_080_923, "clean frame");
        let (ids, depth) = r.render_surfaces(poses[3]);
        let bytes = ids.iter().flat_map(|i| i.to_le_bytes()).chain(depth.data.iter().flat_map(|d| d.to_le_bytes()));
        assert_eq!(fingerprint(bytes), 14_638_333_303_054_208_351, "surface ids and depth");
    }

    /// The paths the simulator's views do not take, pinned like them: a pitched camera (per-pixel
    /// intersection), a distorted lens (two passes) and motion blur with exposure (accumulated
    /// values), so that a speed-up of one path cannot change another's output unnoticed.
    #[test]
    fn pitched_lens_and_blurred_views_are_pinned_bit_for_bit() {
        let world = World::office().with_random_obstacles(1).unwrap();
        let fx = Effects { noise_sigma: 2.0, seed: 1, ..Effects::default() };
        let (a, b) = (Pose::new(14.0, 0.3, 3.0), Pose::new(9.0, 0.4, 1.5));
        let surfaces = |ids: Vec<u32>, depth: DepthMap| -> Vec<u8> {
            ids.iter().flat_map(|i| i.to_le_bytes()).chain(depth.data.iter().flat_map(|d| d.to_le_bytes())).collect()
        };
        let mut img = LumaImage::default();
        let mut pitched = small();
        pitched.mount.pitch_rad = 0.1;
        let r = Renderer::new(&world, &pitched);
        r.render_frame(a, a, &fx, 3, &mut img);
        let (ids, depth) = r.render_surfaces(b);
        let pitched: Vec<u8> = img.data().iter().copied().chain(surfaces(ids, depth)).collect();
        let r = Renderer::new(&world, &distorted_wide());
        r.render_frame(a, a, &fx, 3, &mut img);
        let mut lens: Vec<u8> = img.data().iter().copied().chain(r.render(b).data().iter().copied()).collect();
        let (ids, depth) = r.render_surfaces(a);
        lens.extend(surfaces(ids, depth));
        let r = Renderer::new(&world, &small());
        let blur = Effects { noise_sigma: 3.0, seed: 2, blur_samples: 3, gain: 1.1, offset: -4.0 };
        r.render_frame(a.advance(-0.3, 0.2, 0.1), a, &blur, 5, &mut img);
        let blurred = img.data().to_vec();
        assert_eq!(fingerprint(pitched), 13_441_642_304_231_375_879, "pitched camera");
        assert_eq!(fingerprint(lens), 11_269_747_614_991_474_503, "distorted lens");
        assert_eq!(fingerprint(blurred), 13_472_808_451_934_076_673, "motion blur and exposure");
    }

    /// Where AVX2 is available the views are shaded and exposed eight pixels at a time; the
    /// scalar code (other CPUs) must give the same bytes, level and pitched, with and without
    /// noise.
    #[test]
    fn lane_and_scalar_shading_agree_bit_for_bit() {
        let world = World::office().with_random_obstacles(1).unwrap();
        let mut pitched = small();
        pitched.mount.pitch_rad = 0.1;
        let poses = [world.start.advance(0.4, 0.3, 1.0), Pose::new(20.0, 0.0, 3.0), Pose::new(9.0, 0.4, 1.5)];
        for calib in [small(), pitched] {
            let mut r = Renderer::new(&world, &calib);
            for (seq, &p) in poses.iter().enumerate() {
                let fx = Effects { noise_sigma: 2.0, seed: 1, ..Effects::default() };
                let mut views = Vec::new();
                for simd in [simd_available(), false] {
                    r.simd = simd;
                    let mut img = LumaImage::default();
                    r.render_frame(p, p, &fx, seq as u64, &mut img);
                    views.push((img, r.render_with_depth(p)));
                }
                assert_eq!(views[0], views[1], "pose {p:?}");
            }
        }
    }

    #[test]
    fn views_have_texture_everywhere() {
        // Every 32×32 block of the office start view has grey-level spread for block matching.
        let calib = Calibration::nominal_c310().scaled_to(640, 360);
        let w = World::office();
        let img = Renderer::new(&w, &calib).render(w.start);
        for by in 0..360 / 32 {
            for bx in 0..640 / 32 {
                let (mut lo, mut hi) = (255u8, 0u8);
                for y in by * 32..by * 32 + 32 {
                    for x in bx * 32..bx * 32 + 32 {
                        lo = lo.min(img.get(x, y));
                        hi = hi.max(img.get(x, y));
                    }
                }
                assert!(hi - lo > 20, "block ({bx},{by}) spans only {lo}..{hi}");
            }
        }
    }
}
