//! Stroke-based 3D segmentation (the method of the paper, DESIGN.md
//! "Segmentation"): stroke → unit rendered features → K-means centres → NNFM
//! seed over occupied voxels → bilateral growth → union (positive) or
//! difference (negative) with the object's 3D bitmap.

pub mod anchor;
pub mod beside;
pub mod bitmap_file;
pub mod cut;
pub mod dense;
pub mod enclosed;
mod flood;
mod footing;
pub mod grow;
pub mod kmeans;
pub mod material;
pub mod maxflow;
pub mod nnfm;
pub mod palette;
pub mod peel;
pub mod plane;
pub mod stable;
pub mod stroke;
pub mod supports;
#[cfg(test)]
mod toy;
mod under;

pub use grow::{grow_step_dense, Bound, GrowParams, Grower, GrowthRule};
use kmeans::Stop;
pub use kmeans::{kmeans, Centroids};
pub use nnfm::nnfm_seed;
pub use stroke::{
    load_strokes, load_strokes_in, load_strokes_on, parse_strokes, parse_strokes_on, scribble_stroke, stroke_features,
    stroke_pixels, stroke_samples, Polarity, Stroke, StrokeDoc, StrokeSamples,
};

use crate::field::{Bitmap, FeatureCache, Field};
use crate::render::Scene;
use crate::util::ms_since;
use crate::{ensure, Result};
use palette::{Palette, PaletteTable};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// How far to grow after seeding.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Growth {
    /// A fixed number of steps (0 = seed only).
    Steps(usize),
    /// Until nothing changes (capped at [`MAX_GROW_STEPS`]).
    Converge,
}

pub const MAX_GROW_STEPS: usize = 10_000;

/// Segmentation parameters. The defaults are the bounded growth rule
/// (see [`grow`]), measured on real captures; [`SegmentParams::paper`] is the
/// paper's rule with the defaults of its supplement and the authors' code.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct SegmentParams {
    /// K-means clusters (1 = average matching; ≥ stroke pixels = plain NNFM).
    pub k: usize,
    /// NNFM threshold on squared L2 distance between unit features.
    pub theta: f32,
    pub grow: GrowParams,
    pub growth: Growth,
    /// Voxels need σ above this to be seeds.
    pub seed_floor: f32,
    /// Fraction of the stroke's features (the closest to their mean
    /// direction) that K-means clusters (1 = all).
    pub stroke_keep: f32,
    /// Stable rule: where to look for the most stable region.
    pub stable: stable::StableParams,
    /// Stable rule: the graph cut that refines its region ([`cut`]).
    pub cut: cut::CutParams,
    /// Bounded and stable rules: seeds and grown voxels must be solid, i.e. stop at
    /// least this fraction of the light over one voxel (1 − exp(−σ·h), h
    /// the voxel size): the haze of a real capture has features that match
    /// anything and must not carry the selection.
    pub solid_alpha: f32,
    /// Stroke pixels with rendered opacity below this are on empty space.
    pub min_stroke_opacity: f32,
    /// Keep only the seeds joined to the stroked surface ([`anchor`]);
    /// false: every look-alike in the field (the paper's global NNFM).
    pub connected: bool,
    pub kmeans_seed: u64,
    pub kmeans_iters: usize,
    /// Segment on the field's grid coarsened 2× or 3× ([`crate::field::coarse`]),
    /// an eighth of the voxels or less, and map the mask back to the fine grid,
    /// when the field has at least `coarse_min_voxels` occupied voxels
    /// (see [`coarse_cache`]).
    pub coarse: bool,
    /// Fields with fewer occupied voxels are segmented on their own grid
    /// even with `coarse`: their strokes take under a second there (the
    /// realistic benchmark's tabletop, 618k voxels: 0.5–1 s), and a coarse
    /// voxel is a larger share of their objects: forced onto the coarse
    /// grid, the tabletop pot's NVOS-style strokes fell from 0.837 to
    /// 0.486 (the benchmark's NVOS mean 0.859 → 0.826).
    pub coarse_min_voxels: usize,
    /// On fields below `coarse_min_voxels`, an object whose first stroke's
    /// graph cut would label at least this many voxels (probed on the
    /// coarse copy, counted in fine voxels) is segmented on the coarse copy
    /// all the same. Such cuts are a surface whose features drift (a floor)
    /// or a whole model (lego): on the realistic tabletop the floor's cut
    /// labels 349k voxels (max-flow alone 119 ms, the stroke 420 ms), every
    /// other object's 3k–40k (README, "Large cuts on the coarse copy").
    pub coarse_min_cut: usize,
}

impl Default for SegmentParams {
    fn default() -> Self {
        SegmentParams {
            k: 10,
            // 0.3 rather than the authors' 0.4 (their features are not unit
            // length either): on the realistic benchmark 0.4 lets one toy's
            // stroke seed the others (mean 3D IoU 0.228 -> 0.284 at 0.3),
            // at a small cost on the blurred fern (0.761 -> 0.739).
            theta: 0.3,
            grow: GrowParams::default(),
            growth: Growth::Converge,
            seed_floor: 0.1,
            solid_alpha: 0.02,
            stable: stable::StableParams::default(),
            cut: cut::CutParams::default(),
            stroke_keep: 0.8,
            min_stroke_opacity: 0.5,
            connected: true,
            kmeans_seed: 0,
            kmeans_iters: 50,
            // Strokes on real captures 4-7x faster (fern 1.3-3.0 s ->
            // 0.2-0.6 s, lego at 320³ 1.4 -> 0.3 s); fern NVOS IoU 0.781 ->
            // 0.774, lego's alpha IoU 0.9919 either way (README, "Strokes
            // on a coarse grid").
            coarse: true,
            coarse_min_voxels: 800_000,
            coarse_min_cut: 100_000,
        }
    }
}

impl SegmentParams {
    /// The paper's method: its growth rule, σ_φ = 10, τ = 0.1, no solidity
    /// floor (for the ablation).
    pub fn paper() -> Self {
        SegmentParams {
            theta: 0.4,
            grow: GrowParams::paper(),
            solid_alpha: 0.0,
            stroke_keep: 1.0,
            connected: false,
            coarse: false,
            ..Default::default()
        }
    }

    /// The defaults of a growth rule.
    pub fn for_rule(rule: GrowthRule) -> Self {
        match rule {
            GrowthRule::Paper => Self::paper(),
            r => {
                let mut p = Self::default();
                p.grow.rule = r;
                p
            }
        }
    }

    /// Whether strokes are refined by the graph cut: the stable rule with
    /// growth and at least one cut round.
    pub fn cuts(&self) -> bool {
        self.grow.rule == GrowthRule::Stable && self.growth != Growth::Steps(0) && self.cut.rounds > 0
    }

    /// The σ below which voxels are neither seeds nor (bounded rule) grown
    /// into, on a grid of voxel size `h`.
    pub fn sigma_floor(&self, h: f32) -> f32 {
        let solid = if self.solid_alpha > 0.0 {
            -(1.0 - self.solid_alpha).ln() / h.max(1e-12)
        } else {
            0.0
        };
        self.seed_floor.max(solid)
    }
}

impl SegmentParams {
    pub fn validate(&self) -> Result<()> {
        crate::ensure_within!(
            OutOfRange,
            self.k >= 1 && self.k <= 100_000,
            "K must be between 1 and 100000, got {}",
            self.k
        );
        crate::ensure_within!(
            OutOfRange,
            self.theta.is_finite() && self.theta > 0.0,
            "theta must be positive, got {}",
            self.theta
        );
        let g = &self.grow;
        crate::ensure_within!(
            OutOfRange,
            g.sigma_f.is_finite() && g.sigma_f > 0.0,
            "sigma_f must be positive, got {}",
            g.sigma_f
        );
        crate::ensure_within!(
            OutOfRange,
            g.sigma_s.is_finite() && g.sigma_s > 0.0,
            "sigma_s must be positive, got {}",
            g.sigma_s
        );
        crate::ensure_within!(
            OutOfRange,
            g.tau.is_finite() && (0.0..1.0).contains(&g.tau),
            "tau must be in [0, 1), got {}",
            g.tau
        );
        crate::ensure_within!(
            OutOfRange,
            self.seed_floor.is_finite() && self.seed_floor >= 0.0,
            "seed floor must be >= 0"
        );
        crate::ensure_within!(
            OutOfRange,
            self.stroke_keep > 0.0 && self.stroke_keep <= 1.0,
            "stroke keep must be in (0, 1], got {}",
            self.stroke_keep
        );
        crate::ensure_within!(
            OutOfRange,
            self.solid_alpha.is_finite() && (0.0..1.0).contains(&self.solid_alpha),
            "solid alpha must be in [0, 1), got {}",
            self.solid_alpha
        );
        crate::ensure_within!(
            OutOfRange,
            g.theta_grow > 0.0 && !g.theta_grow.is_nan(),
            "theta_grow must be positive, got {}",
            g.theta_grow
        );
        let c = &self.cut;
        crate::ensure_within!(
            OutOfRange,
            c.lambda.is_finite() && c.lambda >= 0.0 && c.lambda <= 1e6,
            "cut lambda must be in [0, 1e6], got {}",
            c.lambda
        );
        crate::ensure_within!(
            OutOfRange,
            c.colour.is_finite() && c.colour >= 0.0 && c.colour <= 1e3,
            "cut colour weight must be in [0, 1000], got {}",
            c.colour
        );
        crate::ensure_within!(
            OutOfRange,
            c.colour_unary.is_finite() && c.colour_unary >= 0.0 && c.colour_unary <= 1e3,
            "cut colour unary weight must be in [0, 1000], got {}",
            c.colour_unary
        );
        crate::ensure_within!(
            OutOfRange,
            c.colour_margin.is_finite() && c.colour_margin >= 0.0 && c.colour_margin <= 1e3,
            "cut colour margin must be in [0, 1000], got {}",
            c.colour_margin
        );
        crate::ensure_within!(
            OutOfRange,
            c.rounds <= 20,
            "cut rounds must be at most 20, got {}",
            c.rounds
        );
        crate::ensure_within!(
            OutOfRange,
            (1..=256).contains(&c.background_k),
            "cut background centres must be 1..=256, got {}",
            c.background_k
        );
        Ok(())
    }
}

/// Makes what every stroke on `cache`'s field reuses: the coarse copy when
/// strokes go there, and the neighbour table of the graph cut's grid. The
/// session's first stroke on a field makes them with the feature cache,
/// under a progress message; the stroke benchmark counts them as one-off.
pub fn prepare(cache: &FeatureCache, p: &SegmentParams) {
    if p.grow.rule != GrowthRule::Stable || p.cut.rounds == 0 {
        return;
    }
    match coarse_cache(cache, p) {
        Some(coarse) => {
            coarse.neighbours();
        }
        None => {
            cache.neighbours();
            // Large objects go to the coarse copy ([`SegmentParams::coarse_min_cut`]).
            if let Some(coarse) = p.coarse.then(|| cache.coarse()).flatten() {
                coarse.neighbours();
            }
        }
    }
}

/// The cache a stroke is segmented on, when it is `cache`'s coarse copy
/// (made on first use).
pub fn coarse_cache<'a>(cache: &'a FeatureCache, p: &SegmentParams) -> Option<&'a FeatureCache> {
    if p.coarse && p.grow.rule != GrowthRule::Paper && cache.len() >= p.coarse_min_voxels {
        cache.coarse()
    } else {
        None
    }
}

/// Per-stage timings of one stroke, in milliseconds.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct Timings {
    pub stroke_features_ms: f64,
    pub kmeans_ms: f64,
    pub nnfm_ms: f64,
    pub grow_ms: f64,
    /// Stable rule: the graph cut's refinement (with a coarse grid, also
    /// mapping the mask back to the fine one).
    pub cut_ms: f64,
    /// The graph cut's stages (within `cut_ms`).
    pub cut: cut::CutTimings,
    pub grow_steps: usize,
    pub stroke_pixels: usize,
    /// Fine voxels per coarse voxel along each axis of the grid the
    /// stroke was segmented on (1: the field's own; `seed_voxels` and
    /// `region_voxels` count that grid's voxels).
    pub grid: usize,
    pub seed_voxels: usize,
    pub region_voxels: usize,
    /// Stable rule: the hysteresis threshold it chose (0 otherwise).
    pub threshold: f32,
    /// Positive strokes: unseen voxels enclosed by the object that joined
    /// it ([`enclosed`]).
    pub enclosed_voxels: usize,
}

impl Timings {
    pub fn total_ms(&self) -> f64 {
        self.stroke_features_ms + self.kmeans_ms + self.nnfm_ms + self.grow_ms + self.cut_ms
    }
    /// " on the f× coarser grid" when the stroke was segmented on a coarse
    /// copy, else nothing (for the lines that report a stroke).
    pub fn grid_note(&self) -> String {
        match self.grid {
            0 | 1 => String::new(),
            f => format!(" on the {f}× coarser grid"),
        }
    }
}

/// Centres of a set of unit stroke features: K-means over the fraction
/// `p.stroke_keep` of them closest to their mean direction. A brush on a
/// small object also covers its rim, where the field's features blend with
/// the neighbours'; those outliers would become centres that seed the
/// neighbours.
pub fn stroke_centres(feats: &[f32], dim: usize, p: &SegmentParams) -> Centroids {
    if dim == 0 || p.stroke_keep >= 1.0 {
        return drawn_kmeans(feats, dim, p, Stop::exact(p.kmeans_iters));
    }
    let n = feats.len() / dim;
    let mut mean = vec![0.0f32; dim];
    for f in feats.chunks_exact(dim) {
        for (m, &x) in mean.iter_mut().zip(f) {
            *m += x;
        }
    }
    let dots: Vec<f32> = feats
        .chunks_exact(dim)
        .map(|f| f.iter().zip(&mean).map(|(a, b)| a * b).sum())
        .collect();
    let keep = ((n as f32 * p.stroke_keep).ceil() as usize).clamp(1, n);
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| dots[b].total_cmp(&dots[a]));
    order.truncate(keep);
    order.sort_unstable();
    let kept: Vec<f32> = order
        .iter()
        .flat_map(|&i| feats[i * dim..(i + 1) * dim].iter().copied())
        .collect();
    drawn_kmeans(&kept, dim, p, Stop::exact(p.kmeans_iters))
}

/// The K-means of a stroke's (or a mask's) features, best of
/// [`STROKE_DRAWS`] k-means++ draws: the centres seed everything after
/// them, and one draw's poor minimum (a centre spent on a few rim
/// features) moved fern NVOS by ±0.01 with the seed.
fn drawn_kmeans(feats: &[f32], dim: usize, p: &SegmentParams, stop: Stop) -> Centroids {
    kmeans::kmeans_best_of(feats, dim, p.k, p.kmeans_seed, stop, STROKE_DRAWS)
}

/// A stroke has a few thousand features, a mask's sample up to
/// [`MAX_CLUSTERED_ROWS`]; the draws compete on 1,000 of them, 1–4 ms in
/// all.
pub(crate) const STROKE_DRAWS: usize = 8;

/// The 3D region selected by stroke features: NNFM seed, then growth.
pub fn region_from_features(
    cache: &FeatureCache,
    feats: &[f32],
    dim: usize,
    p: &SegmentParams,
    t: &mut Timings,
) -> Result<Bitmap> {
    let stroke = StrokeLook::default();
    segment_anchored(cache, None, feats, dim, &stroke, &Negatives::default(), p, t).map(|(region, _)| region)
}

/// What the negative strokes of an object said so far: the graph cut of a
/// later stroke keeps the voxels they touched background and counts their
/// centres in its background model (Boykov & Jolly's seeds of both kinds).
#[derive(Clone, Debug, Default)]
struct Negatives {
    centres: Option<Centroids>,
    /// Voxels of their regions near their stroked surfaces, ascending.
    touched: Vec<u32>,
}

impl Negatives {
    fn add(&mut self, centres: &Centroids, touched: &[u32]) {
        match &mut self.centres {
            Some(c) if c.dim == centres.dim => c.data.extend_from_slice(&centres.data),
            slot => *slot = Some(centres.clone()),
        }
        self.touched.extend_from_slice(touched);
        self.touched.sort_unstable();
        self.touched.dedup();
    }
}

/// Where a stroke lies in the field: the voxels under it and the colours
/// its pixels show (both empty for features given without a stroke).
#[derive(Default)]
struct StrokeLook<'a> {
    anchors: &'a [u32],
    palette: Palette,
}

/// [`region_from_features`], also returning the stroke's NNFM distances
/// (and K-means centres);
/// with `stroke.anchors` (voxels under the stroke), only the seeds joined to them
/// are kept, and the stable rule's region is refined by a graph cut (with
/// the colours of `field`, the field that owns `cache`, when given) that
/// respects the object's earlier `negatives`; a region on a drifting
/// surface then goes on in its colours, along its slab when flat, else
/// through the stroke's material ([`along_surface`]).
#[allow(clippy::too_many_arguments)]
fn segment_anchored(
    cache: &FeatureCache,
    field: Option<&Field>,
    feats: &[f32],
    dim: usize,
    stroke: &StrokeLook,
    negatives: &Negatives,
    p: &SegmentParams,
    t: &mut Timings,
) -> Result<(Bitmap, nnfm::StrokeDistances)> {
    ensure!(
        dim == cache.channels,
        "stroke features have {dim} channels, the field's cache {}",
        cache.channels
    );
    let t0 = Instant::now();
    let centres = stroke_centres(feats, dim, p);
    t.kmeans_ms = ms_since(t0);
    let t0 = Instant::now();
    let floor = match p.grow.rule {
        GrowthRule::Paper => p.seed_floor,
        _ => p.sigma_floor(cache.voxel_size),
    };
    let stable = p.grow.rule == GrowthRule::Stable && p.growth != Growth::Steps(0);
    let anchors = stroke.anchors;
    let (mut region, mut dist) = joined_seeds(cache, &centres, anchors, floor, stable, p);
    t.nnfm_ms = ms_since(t0);
    t.seed_voxels = region.count();
    let t0 = Instant::now();
    if stable {
        let s = stable::stable_region(cache, &mut dist, &region, p.theta, floor, &p.stable);
        t.grow_ms = ms_since(t0);
        t.grow_steps = 1;
        t.threshold = s.threshold;
        let t0 = Instant::now();
        let mut hard = anchor::near_anchors(&region, anchors, anchor::radius(cache));
        if field.is_some() {
            hard = anchor::seen_by_stroke(cache, hard, &stroke.palette);
        }
        // No stable threshold: a surface whose features drift (see
        // `cut_region`); its colours, where they tell things apart. Both
        // uses refine the stable region, as the cut does, so `--cut-rounds
        // 0` leaves the stable region alone.
        let like_stroke = stroke.palette.table(LIKE_STROKE);
        let surface = match field {
            Some(_) if s.threshold <= p.theta && p.cut.rounds > 0 => {
                surface_colours(&stroke.palette, &like_stroke, &cache.colours)
            }
            _ => None,
        };
        let seeds = Seeds {
            region: &region,
            hard: &hard,
            anchors,
            surface,
        };
        let cut = cut_region(cache, field, &mut dist, &s, &seeds, negatives, p, &mut t.cut);
        // A cut against the stroke-unlike colours alone kept the seeds'
        // material and nothing else: the rest of that material is the
        // object's too, as on a drifting surface.
        let by_colour = cut.as_ref().is_some_and(|c| c.against_colours);
        let region = cut.map_or(s.region, |c| c.region);
        let region = if surface.is_some() || by_colour {
            along_surface(cache, floor, region, &like_stroke, &stroke.palette, &mut dist)
        } else {
            region
        };
        // The support's ring the cut took with the object ([`peel`]).
        let region = match field {
            Some(_) if !stroke.palette.is_empty() => {
                let shows = |c| like_stroke.shows(c);
                let peeled = peel::peel_support(cache, &cache.solid(floor), region, peel::ROUNDS, shows);
                anchor::joined_seeds(&peeled, anchors, anchor::radius(cache)).unwrap_or(peeled)
            }
            _ => region,
        };
        let region = by_structure(cache, floor, region, anchors);
        t.cut_ms = ms_since(t0);
        t.region_voxels = region.count();
        return Ok((region, dist));
    }
    let mut g = Grower::new(cache, p.grow);
    if p.grow.rule != GrowthRule::Paper {
        g = g.with_bound(Bound::new(centres.clone(), p.grow.theta_grow.max(p.theta), floor));
    }
    t.grow_steps = g.grow(&mut region, p.growth, MAX_GROW_STEPS, |_| ());
    t.grow_ms = ms_since(t0);
    t.region_voxels = region.count();
    Ok((region, dist))
}

/// What a stroke's cut starts from: the NNFM seeds joined to the stroke,
/// the seeds under it (tied to the object), the voxels under it and, on a
/// drifting surface, the colours that look like the stroke's pixels
/// ([`surface_colours`]).
struct Seeds<'a> {
    region: &'a Bitmap,
    hard: &'a [u32],
    anchors: &'a [u32],
    surface: Option<&'a PaletteTable<'a>>,
}

/// The stable region refined by the graph cut over the voxels its flood
/// reached, kept where joined to the stroke; `None` when the cut is off,
/// has nothing to tie to the stroke (`seeds.hard`) or leaves nothing there.
///
/// When the flood took in nearly everything it reached, the features saw
/// no boundary and the cut would have no background to fit; if most of
/// what it took does not look like the stroke either (colours unlike the
/// voxels under it), the features are not trusted past θ: the cut starts
/// from the NNFM seeds, everything past θ outside them its background.
/// On the realistic benchmark's fields trained as `isrf train` trains
/// them, the books' stroke flooded the whole shelf (3D IoU 0.095 → 0.949)
/// and the jar's the excavator (0.281 → 0.945); the shelf's own flood,
/// right to take everything, has colours like its stroke (42 % unlike
/// against the books' 65 %), as has the fern's (2 %). But when some of it
/// (more than [`SOME_UNLIKE`]) is in colours unlike the stroke's and the
/// features too put those voxels farther from the stroke
/// ([`farther_in_features`]), they are other things the flood ran into
/// (the toys on the shelf): the cut starts from the seeds, and only voxels
/// in unlike colours feed its background; what it keeps then goes on
/// through the stroke's material (`against_colours`, [`along_surface`]).
/// Realistic benchmark, shelf: 3D IoU 0.799 → 0.963 on full fields,
/// 0.814 → 0.856 on default ones; lego's flood is 38 % unlike but its
/// grey parts are nearer the stroke than its yellow ones, and stays whole.
///
/// When no threshold was stable (the region is the seeds: the region crept
/// on steadily as the threshold rose), the stroke is on something whose
/// features drift across it, a wall, a floor, a table top, and the parts
/// of it past the background threshold would feed the background model
/// and hold the cut at the seeds (the realistic benchmark's wall: 3,960 of
/// its 8,952 voxels). So voxels showing a colour the stroke's pixels show
/// ([`LIKE_STROKE`]) do not feed the background model then, unless most of
/// the scene does ([`surface_colours`]); if that leaves the cut no
/// background at all, the whole flood looks like the stroke and is the
/// region (joined to the stroke), not the seeds.
#[allow(clippy::too_many_arguments)]
fn cut_region(
    cache: &FeatureCache,
    field: Option<&Field>,
    dist: &mut nnfm::StrokeDistances,
    s: &stable::StableRegion,
    seeds: &Seeds,
    negatives: &Negatives,
    p: &SegmentParams,
    t: &mut cut::CutTimings,
) -> Option<CutRegion> {
    if p.cut.rounds == 0 || seeds.hard.is_empty() {
        return None;
    }
    // Per domain voxel (300k of the tabletop's 493k for a mug), in
    // parallel and in domain order.
    let rows = cut::rows_of(cache, &s.reached);
    let colours = voxel_colours(field, cache, &rows);
    let object_distance = dist.of_rows(cache, &rows);
    let not_background: Vec<bool> = match seeds.surface {
        Some(table) => colours.par_iter().map(|&c| table.shows(c)).collect(),
        None => vec![],
    };
    let unlike = if p.cut.background_min > 0.0 {
        p.cut.background_min.max(s.threshold)
    } else {
        0.0
    };
    let mut input = cut::CutInput {
        cache,
        domain: &s.reached,
        rows: &rows,
        graph: s.before_flood.as_ref(),
        colours: &colours,
        object_distance: &object_distance,
        region: &s.region,
        hard: seeds.hard,
        background_hard: &negatives.touched,
        known_background: negatives.centres.as_ref(),
        unlike,
        not_background: &not_background,
    };
    let background = (s.reached.par_iter().zip(&object_distance))
        .filter(|&(&v, &d)| d > unlike && !s.region.get(v as usize))
        .count();
    let like_stroke: Vec<bool>;
    let mut against_colours = false;
    if background * NO_BACKGROUND < s.reached.len() {
        let unlike = cut::unlike_colours(&input, p.kmeans_seed);
        let share = unlike.iter().filter(|&&u| u).count() as f32 / unlike.len().max(1) as f32;
        if share > MOSTLY_UNLIKE {
            input.region = seeds.region;
            input.unlike = p.theta;
        } else if share > SOME_UNLIKE && farther_in_features(&object_distance, &unlike) {
            like_stroke = unlike.iter().map(|&u| !u).collect();
            input.region = seeds.region;
            input.unlike = p.theta;
            input.not_background = &like_stroke;
            against_colours = true;
        }
    }
    let cut = match cut::refine(&input, &p.cut, p.kmeans_seed, t) {
        Some(cut) => cut,
        // A drifting surface whose whole flood looks like the stroke, in a
        // scene where colour tells things apart: the flood is the surface.
        None if !not_background.is_empty() => Bitmap::from_ones(cache.geom.res, &s.reached),
        None => return None,
    };
    let region = anchor::joined_seeds(&cut, seeds.anchors, anchor::radius(cache))?;
    Some(CutRegion {
        region,
        against_colours,
    })
}

/// What [`cut_region`] gives: the region, and whether only voxels in
/// colours unlike the stroke's fed its background model.
struct CutRegion {
    region: Bitmap,
    against_colours: bool,
}

/// Whether the voxels flagged `unlike` (in colours unlike the stroke's)
/// are, on average, more than [`FARTHER`] times as far from the stroke's
/// centres in features as the others (`distance`: each voxel's): the
/// features, too, say they are something else ([`cut_region`]).
fn farther_in_features(distance: &[f32], unlike: &[bool]) -> bool {
    let mean = |want: bool| {
        let picked = || distance.iter().zip(unlike).filter(move |&(_, &u)| u == want);
        picked().map(|(&d, _)| d as f64).sum::<f64>() / picked().count().max(1) as f64
    };
    mean(true) > FARTHER as f64 * mean(false)
}

/// A colour within this squared RGB distance of one the stroke's pixels
/// show looks like the stroke ([`cut_region`]).
const LIKE_STROKE: f32 = 0.02;

/// The colours that look like the stroke's (within [`LIKE_STROKE`] of one
/// its pixels show); none when they are the colours of most of the scene
/// (`scene`, every solid voxel's colour): colour then tells nothing apart. On the
/// fern the stroke's pixels show the blur of fronds and of the wall, the
/// floor and the dark behind them, and their colours are those of 88–99 %
/// of the scene's voxels (kept out of the background model, the walk's
/// strokes took the wall behind the plant: 0.782 → 0.695 on `image001`);
/// on the demo scenes at most 73 % (the floor, most of the tabletop),
/// mostly 2–50 %, and 82 % for the splat benchmark's shelf, which is most
/// of its scene (there colour tells it from the toys on it, and its
/// drifting features need it: [`material`]). (The share of the stroke's own flood does not tell the
/// two apart: the fern's floods and the splat benchmark's floor and wall
/// both look wholly like their strokes.)
/// `table` is `palette`'s at [`LIKE_STROKE`].
fn surface_colours<'t, 'p>(
    palette: &Palette,
    table: &'t PaletteTable<'p>,
    scene: &[glam::Vec3],
) -> Option<&'t PaletteTable<'p>> {
    (!palette.is_empty() && scene_share(table, scene) <= MOSTLY_LIKE).then_some(table)
}

/// `region`, on a drifting surface, continued through its colours: along
/// its slab through solid voxels (σ above `floor`) of `colours` (those
/// that look like the stroke's) when it is flat ([`plane`]), else through opaque voxels of
/// the stroke's own material (`palette`, the stroke's pixels' colours)
/// whose features are not the opposite of the stroke's ([`material`]).
fn along_surface(
    cache: &FeatureCache,
    floor: f32,
    region: Bitmap,
    colours: &PaletteTable,
    palette: &Palette,
    dist: &mut nnfm::StrokeDistances,
) -> Bitmap {
    let voxels: Vec<u32> = region.ones().map(|v| v as u32).collect();
    match plane::flat_slab(&cache.geom, &voxels) {
        Some(slab) => plane::grow_in_slab(cache, &cache.solid(floor), &region, &slab, |c| colours.shows(c)),
        None => {
            let same = palette.table(material::SAME_MATERIAL);
            let opaque = floor.max(material::opaque_sigma(cache.voxel_size));
            let near = |r: usize| dist.get(cache, r) <= material::FARTHEST;
            material::grow_in_material(cache, &region, opaque, |c| same.shows(c), near)
        }
    }
}

/// `region` with the legs that hold it up when it is flat (a table top:
/// [`supports`]), through solid voxels (σ above `floor`).
fn with_legs(cache: &FeatureCache, floor: f32, region: Bitmap) -> Bitmap {
    by_structure(cache, floor, region, &[])
}

/// What the region's shape says about its object: a flat region gains the
/// legs that hold it up ([`supports`]); any other region, drawn on by a
/// stroke (`anchors`, the voxels under it, ascending), gains what holds it
/// up where the field knows which way is up ([`under`]: an excavator's
/// tracks), loses what stands beside it on its support ([`beside`]) and,
/// again where up is known, the levels of the ground under it that it took
/// ([`footing`]). (A flat region stands beside nothing: a floor's patches
/// would otherwise count as things standing on the field's solid under
/// it.)
fn by_structure(cache: &FeatureCache, floor: f32, region: Bitmap, anchors: &[u32]) -> Bitmap {
    debug_assert!(anchors.is_sorted(), "anchors ascend (anchor_voxels, coarse::parents)");
    let voxels: Vec<u32> = region.ones().map(|v| v as u32).collect();
    let solid = || cache.solid(floor);
    match plane::flat_slab(&cache.geom, &voxels) {
        Some(slab) => supports::with_supports(&cache.geom, &solid(), region, &slab),
        None if !anchors.is_empty() => {
            let region = match cache.up {
                Some(up) => under::with_undercarriage(&cache.geom, &solid(), region, up, anchors),
                None => region,
            };
            let stroked = anchor::near_anchors(&region, anchors, anchor::radius(cache));
            let colour = |v: usize| cache.index.slot(v).and_then(|r| cache.colours.get(r).copied());
            let region = beside::without_neighbours(&cache.geom, &solid(), region, &stroked, colour);
            match cache.up {
                Some(up) => footing::off_the_ground(&cache.geom, &solid(), region, up, anchors),
                None => region,
            }
        }
        None => region,
    }
}

/// The share of `scene` that `table` shows, judged on at most
/// [`SCENE_SAMPLE`] colours drawn at random (a fixed seed: the same
/// answer every time; a stride could fall in step with the grid's rows).
fn scene_share(table: &PaletteTable, scene: &[glam::Vec3]) -> f32 {
    if scene.len() <= SCENE_SAMPLE {
        return scene.iter().filter(|&&c| table.shows(c)).count() as f32 / scene.len().max(1) as f32;
    }
    let mut rng = crate::util::SplitMix64::new(SCENE_SEED);
    let shown = (0..SCENE_SAMPLE)
        .filter(|_| table.shows(scene[rng.below(scene.len())]))
        .count();
    shown as f32 / SCENE_SAMPLE as f32
}

const SCENE_SEED: u64 = 0x5CE7E;

/// Colours of the scene sampled to judge how common the stroke's are.
const SCENE_SAMPLE: usize = 16_384;

/// Past this share of the scene looking like the stroke, colour tells
/// nothing apart ([`surface_colours`]).
const MOSTLY_LIKE: f32 = 0.85;

/// A flood that leaves fewer than 1/this of the voxels it reached for the
/// cut's background has found no boundary.
const NO_BACKGROUND: usize = 20;
/// Past this share of the flood unlike the stroke's colours, the features'
/// flood is not trusted ([`cut_region`]).
const MOSTLY_UNLIKE: f32 = 0.5;
/// Past this share unlike the stroke's colours, a flood that found no
/// boundary holds enough of something else to cut against, if the
/// features agree ([`farther_in_features`]).
const SOME_UNLIKE: f32 = 0.1;
/// How much farther from the stroke, in features, the voxels in unlike
/// colours must lie on average for them to be something else: on the
/// realistic benchmark's shelf 2.4–2.5 times (the toys on it), on lego 0.84
/// (its grey tracks and yellow body are one object).
const FARTHER: f32 = 1.5;

/// The diffuse colour (cached per field) of each of `voxels`, solid
/// voxels of `cache`'s grid; none when the cut has no field to colour by.
fn voxel_colours(field: Option<&Field>, cache: &FeatureCache, rows: &[usize]) -> Vec<glam::Vec3> {
    if field.is_none() {
        return vec![];
    }
    rows.par_iter().map(|&r| cache.colours[r]).collect()
}

/// An object's mask built stroke by stroke. Positive strokes add their
/// regions and remember their centres and stroked surfaces. A negative
/// stroke re-labels the mask and its own region together with the graph cut
/// ([`cut`]), object seeds under the positive strokes and background seeds
/// where it touched the mask, its centres joining the background model and
/// the look of what the mask already holds joining the object's
/// (`held_centres`): it removes what it touched and whatever
/// looks and joins more like that than like the object, never the object
/// (with plain subtraction NVOS-style
/// negatives emptied the mask). What stays is joined to the positive
/// strokes. Later positive strokes keep the negatives' voxels out. Without
/// the cut (`cut.rounds` 0), a negative removes the voxels of its region
/// closer to its centres than to the object's; the paper's rule keeps plain
/// subtraction.
pub struct MaskBuilder {
    pub mask: Bitmap,
    /// Voxels under the positive strokes so far, ascending.
    positive_anchors: Vec<u32>,
    /// The colours the positive strokes' pixels showed.
    positive_palette: Palette,
    /// The positive strokes' centres so far, concatenated, with the
    /// distances to them as far as measured: a negative stroke's cut needs
    /// them over the whole mask.
    positive: Option<nnfm::StrokeDistances>,
    negatives: Negatives,
    /// With [`SegmentParams::coarse`]: the builder that works on the
    /// cache's coarse copy, and the fine mask it last gave (a mask changed
    /// since, by other edits, is coarsened again before the next stroke).
    coarse: Option<Box<(MaskBuilder, Bitmap)>>,
    /// Whether the object is large enough to be segmented on the coarse
    /// copy of a mid-size field ([`SegmentParams::coarse_min_cut`]),
    /// decided at its first stroke and kept for the rest.
    large: Option<bool>,
}

impl MaskBuilder {
    pub fn new(mask: Bitmap) -> Self {
        MaskBuilder {
            mask,
            positive_anchors: vec![],
            positive_palette: Palette::default(),
            positive: None,
            negatives: Negatives::default(),
            coarse: None,
            large: None,
        }
    }

    /// Segments `stroke` on `scene` and applies it with `polarity`
    /// (`cache`: the features of the field the stroke is drawn on).
    pub fn stroke(
        &mut self,
        scene: &Scene,
        cache: &FeatureCache,
        stroke: &Stroke,
        polarity: Polarity,
        p: &SegmentParams,
    ) -> Result<Timings> {
        let look = look_at(scene, cache, stroke, p)?;
        let t0 = Instant::now();
        let on = match coarse_cache(cache, p) {
            Some(coarse) => Some(coarse),
            None => self.large_object_copy(cache, &look, polarity, p),
        };
        let decided_ms = ms_since(t0);
        let mut t = match on {
            Some(coarse) => self.stroke_coarse(cache, coarse, &look, polarity, p)?,
            None => self.stroke_on(cache, cache, &look, polarity, p)?,
        };
        t.nnfm_ms += decided_ms;
        Ok(t)
    }

    /// The coarse copy of a mid-size field's `cache` when this object's
    /// cuts are large, decided at its first stroke: a positive one whose
    /// graph cut, probed on the coarse copy, would label at least
    /// [`SegmentParams::coarse_min_cut`] fine voxels, or a negative one on
    /// a mask that large.
    fn large_object_copy<'c>(
        &mut self,
        cache: &'c FeatureCache,
        look: &Look,
        polarity: Polarity,
        p: &SegmentParams,
    ) -> Option<&'c FeatureCache> {
        if !p.coarse || !p.cuts() {
            return None;
        }
        let coarse = cache.coarse()?;
        let large = *self.large.get_or_insert_with(|| match polarity {
            Polarity::Positive => cut_size(coarse, cache, look, p) * coarse.factor.pow(3) >= p.coarse_min_cut,
            // A negative stroke's cut labels the mask (the editor starts a
            // builder from the object's mask for every stroke).
            Polarity::Negative => self.mask.count() >= p.coarse_min_cut,
        });
        large.then_some(coarse)
    }

    /// The stroke segmented on the coarse copy of `fine`, its mask mapped
    /// back: every solid fine voxel of a selected coarse voxel.
    fn stroke_coarse(
        &mut self,
        fine: &FeatureCache,
        coarse: &FeatureCache,
        look: &Look,
        polarity: Polarity,
        p: &SegmentParams,
    ) -> Result<Timings> {
        ensure!(
            self.mask.res() == fine.geom.res,
            "the mask's grid {:?} is not the field's {:?}",
            self.mask.res(),
            fine.geom.res
        );
        let level = self.coarse.get_or_insert_with(|| {
            Box::new((
                MaskBuilder::new(crate::field::coarse::downsample(&self.mask, coarse.factor)),
                self.mask.clone(),
            ))
        });
        if level.1 != self.mask {
            level.0.mask = crate::field::coarse::downsample(&self.mask, coarse.factor);
        }
        let mut t = level.0.stroke_on(coarse, fine, look, polarity, p)?;
        let t0 = Instant::now();
        let floor = p.sigma_floor(fine.voxel_size);
        self.mask = crate::field::coarse::upsample(fine, &level.0.mask, coarse.factor, floor);
        level.1 = self.mask.clone();
        t.cut_ms += ms_since(t0);
        Ok(t)
    }

    /// The stroke segmented on `cache`, the features of `owner` (the
    /// field in `scene`) or their coarse copy.
    fn stroke_on(
        &mut self,
        cache: &FeatureCache,
        owner: &FeatureCache,
        look: &Look,
        polarity: Polarity,
        p: &SegmentParams,
    ) -> Result<Timings> {
        // A negative stroke's own region is found as any stroke's; a
        // positive one's keeps clear of the negatives so far.
        let none = Negatives::default();
        let known = if polarity == Polarity::Positive {
            &self.negatives
        } else {
            &none
        };
        // A negative stroke's own region only seeds the cut over the mask
        // (below), which labels those voxels again: its NNFM seeds joined
        // to the stroke are enough. Cutting that region first cost each of
        // the fern walk's negative strokes 100–220 ms and changed one voxel
        // of its mask (fern NVOS the same to the digit, the realistic
        // benchmark's NVOS mean 0.859 → 0.858); the stable flood (40–85
        // ms) changed nothing there or on the benchmark (its negatives'
        // stable regions are their seeds).
        let cuts = p.cuts();
        let own = match polarity {
            Polarity::Negative if cuts => SegmentParams {
                growth: Growth::Steps(0),
                ..*p
            },
            _ => *p,
        };
        let (s, mut t) = segment_stroke(cache, owner, look, known, &own)?;
        match polarity {
            Polarity::Positive => {
                self.positive_anchors.extend_from_slice(&s.anchors);
                self.positive_anchors.sort_unstable();
                self.positive_anchors.dedup();
                self.positive_palette.extend(&s.palette);
                match &mut self.positive {
                    Some(d) => d.merge(cache, s.dist),
                    none => *none = Some(s.dist),
                }
                self.mask.union_with(&s.region)?;
                if p.grow.rule != GrowthRule::Paper {
                    // What no view saw inside the object moves with it.
                    let floor = p.sigma_floor(cache.voxel_size);
                    t.enclosed_voxels = enclosed::fill_enclosed_unseen(cache, &mut self.mask, floor);
                }
            }
            Polarity::Negative if p.grow.rule == GrowthRule::Paper => self.mask.subtract(&s.region)?,
            Polarity::Negative => {
                let t0 = Instant::now();
                // Its own region's voxels at the stroked surface: with the
                // anchors' two-voxel margin the floor's negatives took the
                // wall's edge along (NVOS-style 0.874 → 0.841).
                let touched: Vec<u32> = s
                    .anchors
                    .iter()
                    .copied()
                    .filter(|&a| s.region.get(a as usize))
                    .collect();
                self.negatives.add(s.dist.centres(), &touched);
                if !cuts || !self.cut_out(cache, look.field, &s, p, &mut t.cut)? {
                    self.subtract_competing(cache, &s.region, s.dist.centres().clone(), p)?;
                }
                if p.grow.rule == GrowthRule::Stable {
                    self.keep_legs(cache, &s.region, p)?;
                }
                t.cut_ms += ms_since(t0);
            }
        }
        Ok(t)
    }

    /// The legs of a flat mask ([`with_legs`]) that a negative stroke's cut
    /// took off: the cut labels by features, and a table's legs look
    /// nothing like its top. What that stroke's own region or an earlier
    /// negative stroke touched stays out.
    fn keep_legs(&mut self, cache: &FeatureCache, negative: &Bitmap, p: &SegmentParams) -> Result<()> {
        if !self.mask.any() {
            return Ok(());
        }
        let mut legs = with_legs(cache, p.sigma_floor(cache.voxel_size), self.mask.clone());
        legs.subtract(negative)?;
        for &v in &self.negatives.touched {
            legs.set(v as usize, false);
        }
        self.mask.union_with(&legs)
    }

    /// The object's model: the positive strokes' centres, or (for a mask
    /// made elsewhere) centres of the mask outside `region`.
    fn object_centres(&self, cache: &FeatureCache, region: &Bitmap, p: &SegmentParams) -> Result<Centroids> {
        if let Some(d) = self.positive.as_ref().filter(|d| !d.centres().is_empty()) {
            return Ok(d.centres().clone());
        }
        let mut rest = self.mask.clone();
        rest.subtract(region)?;
        Ok(mask_centres(cache, &rest, p))
    }

    /// A negative stroke's graph cut over the solid voxels of the mask and
    /// of its region `s`; false when there was nothing to cut (the caller
    /// falls back to [`Self::subtract_competing`]).
    fn cut_out(
        &mut self,
        cache: &FeatureCache,
        field: Option<&Field>,
        s: &StrokeRegion,
        p: &SegmentParams,
        t: &mut cut::CutTimings,
    ) -> Result<bool> {
        let object = self.object_centres(cache, &s.region, p)?;
        if object.is_empty() || !self.mask.any() {
            return Ok(false);
        }
        let mut reach = self.mask.clone();
        reach.union_with(&s.region)?;
        // The reached voxels with features, and their cache rows.
        let (domain, rows): (Vec<u32>, Vec<usize>) = reach
            .ones()
            .filter_map(|v| Some((v as u32, cache.index.slot(v)?)))
            .unzip();
        let colours = voxel_colours(field, cache, &rows);
        let mut hard = anchor::near_anchors(&self.mask, &self.positive_anchors, anchor::radius(cache));
        if field.is_some() {
            hard = anchor::seen_by_stroke(cache, hard, &self.positive_palette);
        }
        let object_distance = match &mut self.positive {
            Some(d) if !d.centres().is_empty() => {
                let mut stroked = d.of_rows(cache, &rows);
                let held = held_centres(&self.mask, d, cache, s, p);
                if !held.is_empty() {
                    let held = nnfm::CentreSet::new(held).min_distances(cache, &rows);
                    stroked.iter_mut().zip(held).for_each(|(a, b)| *a = a.min(b));
                }
                stroked
            }
            _ => nnfm::CentreSet::new(object).min_distances(cache, &rows),
        };
        let input = cut::CutInput {
            cache,
            domain: &domain,
            rows: &rows,
            graph: None,
            colours: &colours,
            object_distance: &object_distance,
            region: &self.mask,
            hard: &hard,
            background_hard: &self.negatives.touched,
            known_background: self.negatives.centres.as_ref(),
            unlike: p.cut.background_min,
            not_background: &[],
        };
        let Some(kept) = cut::refine(&input, &p.cut, p.kmeans_seed, t) else {
            return Ok(false);
        };
        // A negative stroke only removes: the reached voxels the cut left
        // out, and what then no longer joins a positive stroke. With no
        // positive stroke known (a mask made by earlier commands) nothing
        // holds the object in place, so only the stroke's own region may go.
        reach.subtract(&kept)?;
        if self.positive_anchors.is_empty() {
            reach.intersect_with(&s.region)?;
        }
        self.mask.subtract(&reach)?;
        if let Some(joined) = anchor::joined_seeds(&self.mask, &self.positive_anchors, anchor::radius(cache)) {
            self.mask = joined;
        }
        Ok(true)
    }

    fn subtract_competing(
        &mut self,
        cache: &FeatureCache,
        region: &Bitmap,
        negative: Centroids,
        p: &SegmentParams,
    ) -> Result<()> {
        let keep = self.object_centres(cache, region, p)?;
        if keep.is_empty() {
            return self.mask.subtract(region);
        }
        let (neg, keep) = (nnfm::CentreSet::new(negative), nnfm::CentreSet::new(keep));
        let doomed: Vec<usize> = region
            .ones()
            .filter(|&v| self.mask.get(v))
            .filter(|&v| {
                cache
                    .index
                    .slot(v)
                    .is_none_or(|r| neg.min_distance(cache, r) < keep.min_distance(cache, r))
            })
            .collect();
        for v in doomed {
            self.mask.set(v, false);
        }
        Ok(())
    }
}

/// K-means centres of the unit features of a mask's voxels (a strided
/// sample of at most [`MAX_CLUSTERED_ROWS`], so that large masks stay
/// cheap; zero features left out).
fn mask_centres(cache: &FeatureCache, mask: &Bitmap, p: &SegmentParams) -> Centroids {
    let rows: Vec<usize> = mask.ones().filter_map(|v| cache.index.slot(v)).collect();
    let sample = unit_feature_sample(cache, &rows, false, MAX_CLUSTERED_ROWS);
    drawn_kmeans(&sample, cache.channels, p, Stop::exact(p.kmeans_iters))
}

/// The look of what the mask holds and the negative stroke `s` does
/// not speak against: K-means centres of the mask's voxels outside the
/// stroke's region that are closer to the positive strokes' centres
/// (`positive`) than to the negative's. A negative's cut measures the
/// object by them as well as by the positive strokes: a stroke on one board of
/// the shelf reaches its sides and lower boards through the first cut,
/// but their features are far from the stroked board's, and with the
/// strokes' centres alone a negative on the books beside them took
/// 19,507 of the shelf's 34,894 voxels along (NVOS-style 0.651).
fn held_centres(
    mask: &Bitmap,
    positive: &mut nnfm::StrokeDistances,
    cache: &FeatureCache,
    s: &StrokeRegion,
    p: &SegmentParams,
) -> Centroids {
    let outside: Vec<usize> = mask
        .ones()
        .filter(|&v| !s.region.get(v))
        .filter_map(|v| cache.index.slot(v))
        .collect();
    // A strided sample: the centres only summarise the mask's looks,
    // and with every voxel this took 70–90 ms of a fern negative.
    let stride = outside.len().div_ceil(HELD_SAMPLE).max(1);
    let rows: Vec<usize> = outside.into_iter().step_by(stride).collect();
    let to_object = positive.of_rows(cache, &rows);
    let to_negative = nnfm::CentreSet::new(s.dist.centres().clone()).min_distances(cache, &rows);
    let held: Vec<usize> = rows
        .iter()
        .zip(to_object.iter().zip(&to_negative))
        .filter(|(_, (a, b))| a < b)
        .map(|(&r, _)| r)
        .collect();
    let sample = unit_feature_sample(cache, &held, false, MAX_CLUSTERED_ROWS);
    drawn_kmeans(&sample, cache.channels, p, HELD_STOP)
}

/// Most voxels of the mask a negative stroke's [`held_centres`]
/// look at, and when their K-means stops (no centre moving by 1 % of
/// the spread).
const HELD_SAMPLE: usize = 5_000;
const HELD_STOP: Stop = Stop {
    max_iters: 30,
    tol: 0.01,
};

/// Most cache rows a background or mask model clusters (a strided sample).
const MAX_CLUSTERED_ROWS: usize = 20_000;

/// The unit features of a strided sample of at most `most` of cache
/// `rows`, row after row; zero features kept as zero vectors with
/// `keep_zero`, else left out.
fn unit_feature_sample(cache: &FeatureCache, rows: &[usize], keep_zero: bool, most: usize) -> Vec<f32> {
    let stride = rows.len().div_ceil(most.max(1)).max(1);
    let c = cache.channels;
    let mut feats = Vec::with_capacity(rows.len().div_ceil(stride) * c);
    for &r in rows.iter().step_by(stride) {
        let inv = cache.inv_norm[r];
        if inv > 0.0 || keep_zero {
            feats.extend(cache.row(r).iter().map(|x| x * inv));
        }
    }
    feats
}

/// The bound of a `Bounded` growth step asked for on its own (the editor's
/// "grow" button, the `grow` command): grown voxels must look like what the
/// mask already holds, i.e. match K-means centres of its unit features.
/// `None` for the paper's rule, which is unbounded. (The stable rule's steps
/// on their own are bounded steps too.)
pub fn mask_bound(cache: &FeatureCache, mask: &Bitmap, p: &SegmentParams) -> Option<Bound> {
    if p.grow.rule == GrowthRule::Paper {
        return None;
    }
    let floor = p.sigma_floor(cache.voxel_size);
    Some(Bound::new(
        mask_centres(cache, mask, p),
        p.grow.theta_grow.max(p.theta),
        floor,
    ))
}

/// One stroke on `scene` (which must contain the field whose cache is given,
/// at the place the stroke's camera sees it) to its grown 3D region, on
/// the field's own grid (ablations and the benchmark's one-stroke scores;
/// [`MaskBuilder`] segments large fields on a coarse copy).
pub fn region_from_stroke(
    scene: &Scene,
    cache: &FeatureCache,
    stroke: &Stroke,
    p: &SegmentParams,
) -> Result<(Bitmap, Timings)> {
    let look = look_at(scene, cache, stroke, p)?;
    segment_stroke(cache, cache, &look, &Negatives::default(), p).map(|(s, t)| (s.region, t))
}

/// What one positive stroke selects as a user's stroke does (the editor,
/// scripts, `isrf segment`): through a fresh object's [`MaskBuilder`],
/// which sends a large object to the field's coarse copy. The benchmarks
/// score this; [`region_from_stroke`] always stays on the field's grid.
pub fn object_from_stroke(
    scene: &Scene,
    cache: &FeatureCache,
    stroke: &Stroke,
    p: &SegmentParams,
) -> Result<(Bitmap, Timings)> {
    let mut builder = MaskBuilder::new(Bitmap::new(cache.geom.res));
    let t = builder.stroke(scene, cache, stroke, Polarity::Positive, p)?;
    Ok((builder.mask, t))
}

/// What one stroke selected.
struct StrokeRegion {
    region: Bitmap,
    /// The stroke's K-means centres and its NNFM distances, as far as
    /// measured.
    dist: nnfm::StrokeDistances,
    /// The voxels under the stroke (its surface), ascending.
    anchors: Vec<u32>,
    /// The colours its pixels show.
    palette: Palette,
}

/// The NNFM seeds of `centres` (σ above `floor`) joined to the voxels
/// under the stroke (`anchors`, when any join), with their distances;
/// with `measure_all` (the stable flood will want nearly every solid
/// row's distance) every solid row is measured in the same pass.
fn joined_seeds(
    cache: &FeatureCache,
    centres: &Centroids,
    anchors: &[u32],
    floor: f32,
    measure_all: bool,
    p: &SegmentParams,
) -> (Bitmap, nnfm::StrokeDistances) {
    let (seeds, dist) = match measure_all {
        true => nnfm::nnfm_seed_measuring_all(cache, centres, p.theta, floor),
        false => nnfm::nnfm_seed_with_distances(cache, centres, p.theta, floor),
    };
    let seeds = anchor::joined_seeds(&seeds, anchors, anchor::radius(cache)).unwrap_or(seeds);
    (seeds, dist)
}

/// What a stroke shows, read from the scene once whichever grid it is
/// segmented on: its pixels' features and colours, the voxels under it on
/// the field's own grid (ascending), and the field it is drawn on.
struct Look<'a> {
    samples: StrokeSamples,
    anchors: Vec<u32>,
    field: Option<&'a Field>,
    pixels: usize,
    ms: f64,
}

/// The [`Look`] of `stroke` on `scene`, whose field has the features
/// `owner`.
fn look_at<'a>(scene: &'a Scene, owner: &FeatureCache, stroke: &Stroke, p: &SegmentParams) -> Result<Look<'a>> {
    p.validate()?;
    let t0 = Instant::now();
    let pixels = stroke_pixels(stroke)?.len();
    let samples = stroke_samples(scene, stroke, p.min_stroke_opacity)?;
    let anchors = if p.connected {
        anchor::anchor_voxels(scene, owner, &samples.hits)
    } else {
        vec![]
    };
    Ok(Look {
        samples,
        anchors,
        field: anchor::layer_of(scene, owner).map(|l| &*l.field),
        pixels,
        ms: ms_since(t0),
    })
}

/// How many voxels the graph cut of `look`'s stroke labels on `coarse`,
/// the coarse copy of `fine`: its NNFM seeds joined to the stroke and
/// their stable flood, as [`segment_anchored`] finds them (a few ms: an
/// eighth of the voxels).
fn cut_size(coarse: &FeatureCache, fine: &FeatureCache, look: &Look, p: &SegmentParams) -> usize {
    let centres = stroke_centres(&look.samples.features, look.samples.channels, p);
    let floor = p.sigma_floor(coarse.voxel_size);
    let anchors = crate::field::coarse::parents(fine.geom.res, coarse.factor, &look.anchors);
    let (seeds, mut dist) = joined_seeds(coarse, &centres, &anchors, floor, true, p);
    let s = stable::stable_region(coarse, &mut dist, &seeds, p.theta, floor, &p.stable);
    s.before_flood.map_or(s.reached.len(), |graph| graph.count())
}

/// [`region_from_stroke`] for an object with earlier `negatives`, also
/// returning the stroke's centres and anchors.
/// `owner` is the cache of the field the stroke was looked at on, `cache`
/// that cache or its coarse copy.
fn segment_stroke(
    cache: &FeatureCache,
    owner: &FeatureCache,
    look: &Look,
    negatives: &Negatives,
    p: &SegmentParams,
) -> Result<(StrokeRegion, Timings)> {
    let on_own_grid = std::ptr::eq(cache, owner);
    let mut t = Timings {
        stroke_features_ms: look.ms,
        stroke_pixels: look.pixels,
        grid: if on_own_grid { 1 } else { cache.factor },
        ..Timings::default()
    };
    let anchors = match on_own_grid {
        true => look.anchors.clone(),
        false => crate::field::coarse::parents(owner.geom.res, cache.factor, &look.anchors),
    };
    let stroke_look = StrokeLook {
        anchors: &anchors,
        palette: Palette::new(&look.samples.colours),
    };
    let samples = &look.samples;
    let (region, dist) = segment_anchored(
        cache,
        look.field,
        &samples.features,
        samples.channels,
        &stroke_look,
        negatives,
        p,
        &mut t,
    )?;
    let palette = stroke_look.palette;
    Ok((
        StrokeRegion {
            region,
            dist,
            anchors,
            palette,
        },
        t,
    ))
}

/// Applies a stroke's region to an object mask: union for positive strokes,
/// difference for negative ones.
pub fn apply_region(mask: &mut Bitmap, region: &Bitmap, polarity: Polarity) -> Result<()> {
    match polarity {
        Polarity::Positive => mask.union_with(region),
        Polarity::Negative => mask.subtract(region),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// Known answers: a stroke showing red marks the red voxels of its
    /// flood while red is a third of the scene, and none once red is most
    /// of it (colour then tells nothing apart); on a large scene the share
    /// is judged on a random sample, which a periodic layout (every 4th
    /// voxel red) does not fool as a stride of 16 would.
    #[test]
    fn stroke_colours_count_only_where_the_scene_has_others() {
        let red = Vec3::new(0.9, 0.1, 0.1);
        let grey = Vec3::splat(0.5);
        let palette = Palette::new(&[red, Vec3::new(0.85, 0.15, 0.1)]);
        let flood = [red, grey, Vec3::new(0.95, 0.05, 0.1), Vec3::new(0.1, 0.1, 0.9)];
        let scene: Vec<Vec3> = (0..300).map(|i| if i % 3 == 0 { red } else { grey }).collect();
        let shown = |t: &PaletteTable| flood.iter().map(|&c| t.shows(c)).collect::<Vec<_>>();
        let table = palette.table(LIKE_STROKE);
        assert_eq!(
            surface_colours(&palette, &table, &scene).map(shown),
            Some(vec![true, false, true, false])
        );
        let reddish: Vec<Vec3> = (0..300).map(|i| if i % 10 == 0 { grey } else { red }).collect();
        assert!(surface_colours(&palette, &table, &reddish).is_none());
        let none = Palette::default();
        assert!(surface_colours(&none, &none.table(LIKE_STROKE), &scene).is_none());
        let many: Vec<Vec3> = (0..1_000_000).map(|i| if i % 4 == 1 { red } else { grey }).collect();
        let share = scene_share(&palette.table(LIKE_STROKE), &many);
        assert!((share - 0.25).abs() < 0.02, "sampled share {share}");
    }

    /// Known answers: unlike-coloured voxels at twice the others' mean
    /// distance are something else, at 1.2 times (or nearer) they are not;
    /// with no voxel of either kind the answer is no.
    #[test]
    fn unlike_colours_count_as_something_else_only_when_the_features_agree() {
        let unlike = [false, false, true, true];
        assert!(farther_in_features(&[0.1, 0.3, 0.4, 0.4], &unlike));
        assert!(!farther_in_features(&[0.1, 0.3, 0.24, 0.24], &unlike));
        assert!(!farther_in_features(&[0.3, 0.3, 0.1, 0.1], &unlike));
        assert!(!farther_in_features(&[0.1, 0.2], &[false, false]));
        assert!(!farther_in_features(&[], &[]));
    }
}
