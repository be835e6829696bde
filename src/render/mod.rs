//! CPU reference volume renderer.
//!
//! A [`Scene`] is a list of [`Layer`]s: a field, its field-to-world transform,
//! an optional bitmap mask (keep only the object / remove the object) and an
//! optional colour edit. Layers composite D²NeRF-style: at a sample x the
//! densities add, σ = Σ σₖ, and the colour is the density-weighted mean
//! c = Σ σₖ cₖ / σ. Along a ray, αᵢ = 1 − exp(−σᵢ δ), Tᵢ = Πⱼ<ᵢ (1 − αⱼ),
//! wᵢ = Tᵢ αᵢ, C = Σ wᵢ cᵢ + T_N · background; features, depth and
//! per-layer opacity accumulate with the same weights.
//!
//! Samples sit at fixed world distances tᵢ = (i + ½) δ from the ray origin,
//! independent of which layers exist, so adding an empty layer or reordering
//! layers changes nothing. Empty space is skipped with a coarse max-density
//! grid per field ([`MacroGrid`]) and rays stop once T < `min_transmittance`.
//! This is the reference the GPU ray marcher is checked against: keep it
//! simple and exact.

mod image_out;

pub use image_out::{colorize_depth, features_to_rgb, save_png, to_rgb8};

use crate::camera::{Camera, Ray};
use crate::field::{Bitmap, Field, MacroGrid};
use crate::{ensure, Result};
use glam::{Affine3A, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Per-object appearance edit, applied to the layer's colour at shading time
/// in this order: hue rotation, saturation, brightness, tint.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ColorEdit {
    /// Multiplies each channel.
    pub tint: [f32; 3],
    /// Hue rotation in degrees.
    pub hue: f32,
    /// Saturation multiplier (0 = grey).
    pub saturation: f32,
    /// Brightness multiplier.
    pub brightness: f32,
}

impl Default for ColorEdit {
    fn default() -> Self {
        ColorEdit {
            tint: [1.0; 3],
            hue: 0.0,
            saturation: 1.0,
            brightness: 1.0,
        }
    }
}

impl ColorEdit {
    pub fn is_identity(&self) -> bool {
        *self == ColorEdit::default()
    }
    pub fn validate(&self) -> Result<()> {
        let v = [
            self.tint[0],
            self.tint[1],
            self.tint[2],
            self.hue,
            self.saturation,
            self.brightness,
        ];
        crate::ensure_within!(
            OutOfRange,
            v.iter().all(|x| x.is_finite()),
            "colour edit has a non-finite value: {self:?}"
        );
        crate::ensure_within!(
            OutOfRange,
            self.tint.iter().all(|&t| t >= 0.0) && self.saturation >= 0.0 && self.brightness >= 0.0,
            "colour edit: tint, saturation and brightness must not be negative: {self:?}"
        );
        Ok(())
    }
    pub fn apply(&self, c: Vec3) -> Vec3 {
        self.linear(c).clamp(Vec3::ZERO, Vec3::ONE)
    }
    /// The edit before clamping: a linear map of the colour (splat export
    /// applies it to every spherical-harmonic coefficient).
    pub fn linear(&self, c: Vec3) -> Vec3 {
        // Hue rotation about the grey axis (Rodrigues), then saturation about
        // the luma, so that hue and saturation edits keep brightness.
        let mut c = c;
        if self.hue != 0.0 {
            let k = Vec3::splat(1.0 / 3f32.sqrt());
            let (s, co) = self.hue.to_radians().sin_cos();
            c = c * co + k.cross(c) * s + k * k.dot(c) * (1.0 - co);
        }
        let luma = c.dot(Vec3::new(0.2126, 0.7152, 0.0722));
        c = Vec3::splat(luma) + (c - Vec3::splat(luma)) * self.saturation;
        c * self.brightness * Vec3::from(self.tint)
    }
}

/// Which part of a field a layer shows.
#[derive(Clone, Debug, Default)]
pub enum Mask {
    #[default]
    All,
    /// σ'(x) = σ(x)·b(x): only the object (b: see [`bitmap_fraction`]).
    Keep(Arc<Bitmap>),
    /// σ'(x) = σ(x)·(1 − b(x)): the field with the object removed.
    Remove(Arc<Bitmap>),
}

#[derive(Clone, Debug)]
pub struct Layer {
    pub field: Arc<Field>,
    /// Field-local to world.
    pub to_world: Affine3A,
    pub mask: Mask,
    pub color_edit: Option<ColorEdit>,
}

impl Layer {
    pub fn new(field: Arc<Field>) -> Self {
        Layer {
            field,
            to_world: Affine3A::IDENTITY,
            mask: Mask::All,
            color_edit: None,
        }
    }
}

#[derive(Clone, Debug)]
pub struct Scene {
    pub layers: Vec<Layer>,
    pub background: Vec3,
}

impl Scene {
    pub fn new(layers: Vec<Layer>) -> Self {
        Scene {
            layers,
            background: Vec3::ONE,
        }
    }
    pub fn single(field: Arc<Field>) -> Self {
        Scene::new(vec![Layer::new(field)])
    }
    /// Feature channel count shared by the layers that have features.
    pub fn feature_channels(&self) -> Result<usize> {
        let mut c = 0;
        for l in &self.layers {
            let n = l.field.feature_channels();
            if n == 0 {
                continue;
            }
            ensure!(
                c == 0 || c == n,
                "layers have different feature channel counts ({c} and {n})"
            );
            c = n;
        }
        Ok(c)
    }
}

/// Measures how much of each ray's opacity comes from a bitmap region of one
/// layer: Σ wᵢ (σₖ/σ) b(xᵢ). With the layer's field, this is the rendered
/// opacity of an object *with occlusion by everything else*, i.e. its 2D mask
/// (the paper's "object opacity > 0.1").
#[derive(Clone, Debug)]
pub struct Probe {
    pub layer: usize,
    pub mask: Arc<Bitmap>,
}

/// How far apart a ray's samples lie.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Step {
    /// This fraction of a grid cell along the ray, per ray: the distance
    /// over which the ray moves by that fraction of a cell, measured in
    /// cell units ([`cell_distance`]), in the finest layer whose box it
    /// meets. The trainer samples so ([`crate::train::trainer::ray_step`]):
    /// on cubic cells it is a fixed world step, on the anisotropic NDC grids
    /// of forward-facing scenes (depth cells 2–3× longer) rays along depth
    /// take 2–3× fewer samples than the finest side would ask for.
    Cells(f32),
    /// A fixed world distance.
    World(f32),
}

impl Default for Step {
    /// Half a cell: two samples per cell crossed, as DVGO and Plenoxels.
    fn default() -> Self {
        Step::Cells(0.5)
    }
}

impl Step {
    pub fn check(self) -> Result<()> {
        let (Step::Cells(v) | Step::World(v)) = self;
        ensure!(v.is_finite() && v > 0.0, "render step must be positive, got {self:?}");
        Ok(())
    }
    /// The same rule with samples `k` times as far apart.
    pub fn scaled(self, k: f32) -> Step {
        match self {
            Step::Cells(v) => Step::Cells(v * k),
            Step::World(v) => Step::World(v * k),
        }
    }
}

/// World distance along a ray whose direction in a grid's local frame is
/// `d_local` (per unit world distance) over which it moves by one cell of
/// `spacing`, measured in cell units (the Euclidean length of its path in
/// grid coordinates).
pub fn cell_distance(spacing: Vec3, d_local: Vec3) -> f32 {
    let rate = (d_local / spacing).length();
    if rate > 0.0 {
        1.0 / rate
    } else {
        f32::INFINITY
    }
}

#[derive(Clone, Debug)]
pub struct RenderOptions {
    /// Sample spacing along each ray ([`Step::default`]: half a cell).
    pub step: Step,
    pub features: bool,
    pub depth: bool,
    pub layer_opacity: bool,
    /// Shade colour (off: `color` holds only the background's share, for
    /// callers that want features, depth or opacity alone).
    pub colour: bool,
    /// Rays stop when the transmittance drops below this.
    pub min_transmittance: f32,
    /// Samples whose weight (transmittance × opacity) is at or below this
    /// are not shaded: their colour and features count as zero.
    pub min_weight: f32,
    pub probes: Vec<Probe>,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            step: Step::default(),
            features: false,
            depth: true,
            layer_opacity: false,
            colour: true,
            min_transmittance: 1e-4,
            min_weight: 0.0,
            probes: vec![],
        }
    }
}

/// Results for a batch of rays (or the pixels of a frame, row-major).
#[derive(Clone, Debug, Default)]
pub struct RenderOutput {
    pub color: Vec<Vec3>,
    pub opacity: Vec<f32>,
    /// Expected ray distance Σ wᵢ tᵢ (0 where nothing was hit).
    pub depth: Vec<f32>,
    pub feature_channels: usize,
    /// `rays × feature_channels`, Σ wᵢ φᵢ.
    pub features: Vec<f32>,
    /// `layers × rays`: Σ wᵢ σₖ/σ per layer.
    pub layer_opacity: Vec<f32>,
    /// `probes × rays`, see [`Probe`].
    pub probe_opacity: Vec<f32>,
}

#[derive(Clone, Debug)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub out: RenderOutput,
}

/// Everything a ray needs about one layer, precomputed once per render.
struct Prepared<'a> {
    field: &'a Field,
    to_local: Affine3A,
    mask: Option<(&'a Bitmap, bool)>,
    color_edit: Option<ColorEdit>,
    macro_grid: &'a MacroGrid,
}

impl Prepared<'_> {
    #[inline]
    fn mask_factor(&self, p: Vec3) -> f32 {
        let Some((bits, keep)) = self.mask else { return 1.0 };
        let b = bitmap_fraction(self.field, bits, p);
        if keep {
            b
        } else {
            1.0 - b
        }
    }
}

fn prepare(scene: &Scene) -> Result<Vec<Prepared<'_>>> {
    scene
        .layers
        .iter()
        .enumerate()
        .map(|(i, l)| {
            ensure!(
                crate::util::invertible(&l.to_world),
                "layer {i}: its transform is not invertible"
            );
            let mask = match &l.mask {
                Mask::All => None,
                Mask::Keep(b) => Some((b.as_ref(), true)),
                Mask::Remove(b) => Some((b.as_ref(), false)),
            };
            if let Some((b, _)) = mask {
                ensure!(
                    b.res() == l.field.res(),
                    "layer {i}: mask resolution {:?} differs from the field's {:?}",
                    b.res(),
                    l.field.res()
                );
            }
            if let Some(e) = &l.color_edit {
                e.validate()?;
            }
            Ok(Prepared {
                field: &l.field,
                to_local: l.to_world.inverse(),
                mask,
                color_edit: l.color_edit.filter(|e| !e.is_identity()),
                macro_grid: l.field.macro_grid(),
            })
        })
        .collect()
}

/// Per-thread scratch state.
struct Tracer<'a> {
    layers: &'a [Prepared<'a>],
    samplers: Vec<crate::field::Sampler<'a>>,
    sigma: Vec<f32>,
    feat: Vec<f32>,
    opts: &'a RenderOptions,
    /// Per-ray accumulators: layer opacities then probe opacities.
    nl: usize,
    background: Vec3,
}

/// One ray's results, written into slices of the output buffers.
struct RaySlot<'o> {
    color: &'o mut Vec3,
    opacity: &'o mut f32,
    depth: &'o mut f32,
    features: &'o mut [f32],
}

impl<'a> Tracer<'a> {
    fn new(layers: &'a [Prepared<'a>], opts: &'a RenderOptions, background: Vec3, channels: usize) -> Self {
        Tracer {
            layers,
            samplers: layers.iter().map(|l| l.field.sampler()).collect(),
            sigma: vec![0.0; layers.len()],
            feat: vec![0.0; channels],
            opts,
            nl: if opts.layer_opacity { layers.len() } else { 0 },
            background,
        }
    }

    /// The world-distance interval where the ray meets any layer's box, and
    /// the ray's sample spacing.
    fn interval(&self, ray: &Ray) -> Option<(f32, f32, f32)> {
        let mut lo = f32::INFINITY;
        let mut hi = f32::NEG_INFINITY;
        let mut cell = f32::INFINITY;
        for l in self.layers {
            let o = l.to_local.transform_point3(ray.origin);
            let d = l.to_local.transform_vector3(ray.dir);
            if let Some((a, b)) = l.field.bounds().intersect(o, d) {
                lo = lo.min(a);
                hi = hi.max(b);
                cell = cell.min(cell_distance(l.field.geom().spacing(), d));
            }
        }
        let dt = match self.opts.step {
            Step::Cells(f) => f * cell,
            Step::World(w) => w,
        };
        (hi > lo && dt.is_finite() && dt > 0.0).then_some((lo, hi, dt))
    }

    /// If every layer is empty around world point `x`, the world distance to
    /// travel along the ray before one of them might not be.
    fn empty_skip(&self, ray: &Ray, t: f32) -> Option<f32> {
        let mut skip = f32::INFINITY;
        for l in self.layers {
            let o = l.to_local.transform_point3(ray.origin);
            let d = l.to_local.transform_vector3(ray.dir);
            let s = l.macro_grid.skip_distance(o + t * d, d)?;
            skip = skip.min(s);
        }
        Some(skip)
    }

    fn trace(&mut self, ray: &Ray, layer_opacity: &mut [f32], slot: RaySlot) {
        let mut t_acc = 1.0f32;
        let mut color = Vec3::ZERO;
        let mut depth = 0.0;
        slot.features.fill(0.0);
        layer_opacity.fill(0.0);
        if let Some((t0, t1, dt)) = self.interval(ray) {
            let mut i = (t0 / dt - 0.5).ceil().max(0.0) as i64;
            loop {
                let t = (i as f32 + 0.5) * dt;
                if t > t1 || t_acc < self.opts.min_transmittance {
                    break;
                }
                if let Some(skip) = self.empty_skip(ray, t) {
                    // Jump to the first sample past the empty region.
                    let next = ((t + skip) / dt - 0.5).ceil() as i64;
                    i = next.max(i + 1);
                    continue;
                }
                i += 1;
                let sum = self.densities(ray, t);
                if sum <= 0.0 {
                    continue;
                }
                let alpha = 1.0 - (-sum * dt).exp();
                let w = t_acc * alpha;
                if w > self.opts.min_weight {
                    color += w * self.shade(ray, t, sum, layer_opacity, w, slot.features);
                    depth += w * t;
                }
                t_acc *= 1.0 - alpha;
            }
        }
        *slot.color = color + t_acc * self.background;
        *slot.opacity = 1.0 - t_acc;
        *slot.depth = depth;
    }

    /// Fills `self.sigma` with each layer's (masked) density at distance `t`.
    fn densities(&mut self, ray: &Ray, t: f32) -> f32 {
        let mut sum = 0.0;
        for (k, l) in self.layers.iter().enumerate() {
            let p = l.to_local.transform_point3(ray.at(t));
            let mut s = l.field.sigma(p);
            if s > 0.0 {
                s *= l.mask_factor(p);
            }
            self.sigma[k] = s;
            sum += s;
        }
        sum
    }

    /// Density-weighted colour at distance `t`; accumulates features and
    /// per-layer opacity with weight `w`.
    fn shade(&mut self, ray: &Ray, t: f32, sum: f32, layer_opacity: &mut [f32], w: f32, feats: &mut [f32]) -> Vec3 {
        let mut c = Vec3::ZERO;
        let want_feat = !feats.is_empty();
        for (k, l) in self.layers.iter().enumerate() {
            let s = self.sigma[k];
            if s <= 0.0 {
                continue;
            }
            let share = s / sum;
            let p = l.to_local.transform_point3(ray.at(t));
            if self.opts.colour {
                let dir = l.to_local.transform_vector3(ray.dir).normalize();
                let mut ck = self.samplers[k].color(p, dir);
                if let Some(e) = &l.color_edit {
                    ck = e.apply(ck);
                }
                c += share * ck;
            }
            if self.nl > 0 {
                layer_opacity[k] += w * share;
            }
            if want_feat && l.field.feature_channels() == feats.len() {
                self.samplers[k].features(p, &mut self.feat);
                for (f, v) in feats.iter_mut().zip(&self.feat) {
                    *f += w * share * v;
                }
            }
        }
        for (m, probe) in self.opts.probes.iter().enumerate() {
            let k = probe.layer;
            if self.sigma[k] > 0.0 {
                let l = &self.layers[k];
                let p = l.to_local.transform_point3(ray.at(t));
                let b = bitmap_fraction(l.field, &probe.mask, p);
                layer_opacity[self.nl + m] += w * self.sigma[k] / sum * b;
            }
        }
        c
    }
}

/// The share b(x) of the density at `p` that comes from voxels in `bits`:
/// b = Σ wᵢ σᵢ mᵢ / Σ wᵢ σᵢ over the 8 corners (σᵢ activated).
///
/// Weighting the bitmap by density, rather than interpolating the 0/1 bitmap
/// alone, is what makes a removal clean: halfway between a dense voxel of the
/// object and an empty voxel outside it, all the density is the object's, so
/// σ·(1 − b) is 0 there, where σ·(1 − trilinear b) would leave half of it as
/// a visible shell. For ReLU fields σ·b is exactly the trilinear interpolation
/// of the masked grid σᵢ·mᵢ; Keep and Remove still add up to σ everywhere.
#[inline]
pub fn bitmap_fraction(field: &Field, bits: &Bitmap, p: Vec3) -> f32 {
    let Some(c) = field.geom().corners(p) else { return 0.0 };
    let (mut inside, mut total) = (0.0f32, 0.0f32);
    for k in 0..8 {
        let w = c.weight[k] * field.density.sigma_at(c.index[k]);
        total += w;
        if bits.get(c.index[k]) {
            inside += w;
        }
    }
    if total > 0.0 {
        inside / total
    } else {
        // No density at any corner: fall back to the plain interpolation.
        (0..8).filter(|&k| bits.get(c.index[k])).map(|k| c.weight[k]).sum()
    }
}

/// Renders a batch of rays.
pub fn render_rays(scene: &Scene, rays: &[Ray], opts: &RenderOptions) -> Result<RenderOutput> {
    let layers = prepare(scene)?;
    let channels = if opts.features { scene.feature_channels()? } else { 0 };
    opts.step.check()?;
    let n = rays.len();
    let nl = if opts.layer_opacity { layers.len() } else { 0 };
    let np = opts.probes.len();
    for (m, p) in opts.probes.iter().enumerate() {
        ensure!(
            p.layer < layers.len(),
            "probe {m} names layer {} of {}",
            p.layer,
            layers.len()
        );
        let res = scene.layers[p.layer].field.res();
        ensure!(
            p.mask.res() == res,
            "probe {m}: mask resolution {:?} differs from the field's {res:?}",
            p.mask.res()
        );
    }
    let ne = nl + np;
    const CHUNK: usize = 64;
    // Each chunk of rays renders into its own small output, then the chunks
    // are concatenated in order; layer opacities are transposed at the end.
    let chunks: Vec<(RenderOutput, Vec<f32>)> = rays
        .par_chunks(CHUNK)
        .map(|chunk| {
            let m = chunk.len();
            let mut o = RenderOutput {
                color: vec![Vec3::ZERO; m],
                opacity: vec![0.0; m],
                depth: vec![0.0; m],
                feature_channels: channels,
                features: vec![0.0; m * channels],
                layer_opacity: vec![],
                probe_opacity: vec![],
            };
            let mut lo = vec![0.0f32; m * ne];
            let mut tracer = Tracer::new(&layers, opts, scene.background, channels);
            for (j, ray) in chunk.iter().enumerate() {
                let slot = RaySlot {
                    color: &mut o.color[j],
                    opacity: &mut o.opacity[j],
                    depth: &mut o.depth[j],
                    features: &mut o.features[j * channels..(j + 1) * channels],
                };
                tracer.trace(ray, &mut lo[j * ne..(j + 1) * ne], slot);
            }
            (o, lo)
        })
        .collect();
    let mut out = RenderOutput {
        feature_channels: channels,
        layer_opacity: vec![0.0; n * nl],
        probe_opacity: vec![0.0; n * np],
        ..Default::default()
    };
    let mut r0 = 0;
    for (o, lo) in chunks {
        if ne > 0 {
            for (j, per_ray) in lo.chunks(ne).enumerate() {
                for (k, &v) in per_ray[..nl].iter().enumerate() {
                    out.layer_opacity[k * n + r0 + j] = v;
                }
                for (m, &v) in per_ray[nl..].iter().enumerate() {
                    out.probe_opacity[m * n + r0 + j] = v;
                }
            }
        }
        r0 += o.color.len();
        out.color.extend(o.color);
        out.opacity.extend(o.opacity);
        out.depth.extend(o.depth);
        out.features.extend(o.features);
    }
    Ok(out)
}

/// Renders every pixel of a camera (row-major, pixel centres).
pub fn render(scene: &Scene, camera: &Camera, opts: &RenderOptions) -> Result<Frame> {
    let k = camera.intrinsics;
    crate::ensure_within!(
        OutOfRange,
        crate::limits::image_size_ok(k.width, k.height),
        "image size {}x{} is out of range",
        k.width,
        k.height
    );
    let rays: Vec<Ray> = (0..k.height)
        .flat_map(|y| (0..k.width).map(move |x| camera.pixel_ray(x, y)))
        .collect();
    Ok(Frame {
        width: k.width,
        height: k.height,
        out: render_rays(scene, &rays, opts)?,
    })
}
