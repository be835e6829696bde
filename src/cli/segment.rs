//! `isrf segment`: strokes → an object's 3D bitmap, with per-stage timings.

use anyhow::{bail, Result};
use isrf::field::Bitmap;
use isrf::field::Field;
use isrf::render::Scene;
use isrf::segment::bitmap_file::save_bitmap;
use isrf::segment::{load_strokes_on, Growth, GrowthRule, MaskBuilder, SegmentParams};
use std::path::PathBuf;
use std::sync::Arc;

/// Segmentation parameters; every flag left out takes the value of the
/// `--growth` rule's defaults (`isrf segment --help` shows them).
#[derive(clap::Args, Clone, Debug)]
pub struct ParamArgs {
    /// Growth rule: `stable` (the default: seeds grown through solid voxels
    /// that still match the stroke, up to the threshold where the region is
    /// most stable), `bounded` (bilateral steps on unit features with a fixed
    /// threshold --theta-grow) or `paper` (the paper's rule and defaults,
    /// for ablations).
    #[arg(long, default_value = "stable")]
    pub growth: GrowthRule,
    /// K-means clusters over the stroke features (1 = average matching)
    /// [default: 10].
    #[arg(long)]
    pub k: Option<usize>,
    /// NNFM seed threshold (squared L2 distance between unit features)
    /// [default: 0.3; paper 0.4].
    #[arg(long)]
    pub theta: Option<f32>,
    /// Growth steps: a number (0 = seed only) or "converge" [default: converge].
    #[arg(long, value_parser = parse_growth)]
    pub grow: Option<Growth>,
    /// Bilateral feature bandwidth σ_φ [default: bounded 0.2 on unit
    /// features, paper 10 on raw ones].
    #[arg(long)]
    pub sigma_f: Option<f32>,
    /// Bilateral spatial bandwidth σ_s (voxels, L1) [default: 1].
    #[arg(long)]
    pub sigma_s: Option<f32>,
    /// Growth threshold τ [default: 0.1].
    #[arg(long)]
    pub tau: Option<f32>,
    /// Fraction of the stroke's features, the closest to their mean, that
    /// K-means clusters [default: 0.8; paper 1].
    #[arg(long)]
    pub stroke_keep: Option<f32>,
    /// Bounded rule: grown voxels need an NNFM distance below this
    /// [default: 0.8].
    #[arg(long)]
    pub theta_grow: Option<f32>,
    /// Bounded rule: seeds and grown voxels must stop this fraction of the
    /// light over one voxel [default: 0.02].
    #[arg(long)]
    pub solid_alpha: Option<f32>,
    /// Select every look-alike in the field, not only the seeds joined to
    /// the stroked surface (the paper's global matching; its rule's default).
    #[arg(long)]
    pub anywhere: bool,
    /// Stable rule: weight λ of the graph cut's boundary term against the
    /// feature distances [default: 0.5].
    #[arg(long)]
    pub cut_lambda: Option<f32>,
    /// Stable rule: graph-cut rounds refining the region, each re-fitting
    /// the background model (0: no cut) [default: 1].
    #[arg(long)]
    pub cut_rounds: Option<usize>,
    /// Stable rule: colour's share of the cut's boundary term (0: features
    /// only) [default: 1].
    #[arg(long)]
    pub cut_colour: Option<f32>,
    /// Stable rule: weight of colour in the cut's region term (0: features
    /// only) [default: 3].
    #[arg(long)]
    pub cut_colour_unary: Option<f32>,
    /// Stable rule: only voxels at least this far from the stroke's
    /// centres (and past the stable threshold) feed the cut's background
    /// model (0: every voxel outside the region) [default: 0.6].
    #[arg(long)]
    pub cut_background_min: Option<f32>,
    /// Seed of the K-means clusterings (for spread measurements) [default: 0].
    #[arg(long)]
    pub kmeans_seed: Option<u64>,
    /// Stable rule: the most the cut's colour models may move a voxel's
    /// balance between object and background [default: 1].
    #[arg(long)]
    pub cut_colour_margin: Option<f32>,
    /// Segment on the field's grid coarsened 2× (an eighth of the voxels;
    /// 3× past 1.5 M occupied voxels) and map the mask back to the fine
    /// grid, on fields with at least 800k occupied voxels, and for objects
    /// whose first stroke's graph cut would label 100k voxels or more on
    /// smaller fields: `true` or `false` [default: true].
    #[arg(long)]
    pub coarse: Option<bool>,
}

pub fn parse_growth(s: &str) -> Result<Growth, String> {
    match s {
        "converge" => Ok(Growth::Converge),
        _ => s
            .parse::<usize>()
            .map(Growth::Steps)
            .map_err(|_| format!("'{s}' is neither a number of steps nor 'converge'")),
    }
}

impl ParamArgs {
    pub fn params(&self) -> Result<SegmentParams> {
        let mut p = SegmentParams::for_rule(self.growth);
        p.k = self.k.unwrap_or(p.k);
        p.theta = self.theta.unwrap_or(p.theta);
        p.growth = self.grow.unwrap_or(p.growth);
        p.solid_alpha = self.solid_alpha.unwrap_or(p.solid_alpha);
        p.stroke_keep = self.stroke_keep.unwrap_or(p.stroke_keep);
        p.connected &= !self.anywhere;
        p.cut.lambda = self.cut_lambda.unwrap_or(p.cut.lambda);
        p.cut.rounds = self.cut_rounds.unwrap_or(p.cut.rounds);
        p.cut.colour = self.cut_colour.unwrap_or(p.cut.colour);
        p.cut.colour_unary = self.cut_colour_unary.unwrap_or(p.cut.colour_unary);
        p.cut.background_min = self.cut_background_min.unwrap_or(p.cut.background_min);
        p.kmeans_seed = self.kmeans_seed.unwrap_or(p.kmeans_seed);
        p.cut.colour_margin = self.cut_colour_margin.unwrap_or(p.cut.colour_margin);
        p.coarse = self.coarse.unwrap_or(p.coarse);
        let g = &mut p.grow;
        g.sigma_f = self.sigma_f.unwrap_or(g.sigma_f);
        g.sigma_s = self.sigma_s.unwrap_or(g.sigma_s);
        g.tau = self.tau.unwrap_or(g.tau);
        g.theta_grow = self.theta_grow.unwrap_or(g.theta_grow);
        p.validate()?;
        Ok(p)
    }
}

#[derive(clap::Args)]
pub struct Args {
    /// Field file (.safetensors) with semantic features.
    pub field: PathBuf,
    /// Stroke documents (JSON); positive strokes add, negative ones subtract, in order.
    #[arg(long, required = true, num_args = 1..)]
    pub strokes: Vec<PathBuf>,
    /// Only use strokes for this object name (default: every stroke).
    #[arg(long)]
    pub object: Option<String>,
    /// Output bitmap file (.safetensors).
    #[arg(long)]
    pub out: PathBuf,
    /// Camera set for strokes whose camera is given only by name
    /// (`"camera": {"file_path": "image012"}`), e.g. the
    /// `<field>.cameras.json` that `isrf train` writes.
    #[arg(long)]
    pub cameras: Option<PathBuf>,
    #[command(flatten)]
    pub params: ParamArgs,
}

pub fn run(a: Args) -> Result<()> {
    let params = a.params.params()?;
    let mut strokes = vec![];
    let cameras = a.cameras.as_deref().map(isrf::camera::CameraSet::load).transpose()?;
    for p in &a.strokes {
        strokes.extend(load_strokes_on(p, cameras.as_ref())?);
    }
    if let Some(name) = &a.object {
        let known: Vec<String> = strokes.iter().map(|s| s.object.clone()).collect();
        strokes.retain(|s| &s.object == name);
        if strokes.is_empty() {
            bail!(
                "no stroke is for object '{name}' (strokes are for: {})",
                known.join(", ")
            );
        }
    }
    let t0 = std::time::Instant::now();
    let field = Arc::new(Field::load(&a.field)?.or_up_from(cameras.as_ref()));
    let load_ms = isrf::util::ms_since(t0);
    let t0 = std::time::Instant::now();
    let cache = field.feature_cache()?;
    let cache_ms = isrf::util::ms_since(t0);
    println!(
        "field loaded in {load_ms:.0} ms; feature cache of {} occupied voxels built in {cache_ms:.0} ms",
        cache.len()
    );
    let scene = Scene::single(field.clone());
    let mut builder = MaskBuilder::new(Bitmap::new(field.res()));
    for (i, s) in strokes.iter().enumerate() {
        let t = builder
            .stroke(&scene, &cache, s, s.polarity, &params)
            .map_err(|e| anyhow::anyhow!("stroke {i} ('{}'): {e}", s.object))?;
        let growth = if t.threshold > 0.0 {
            format!("stable region at threshold {:.2}", t.threshold)
        } else {
            format!("{} steps", t.grow_steps)
        };
        let grid = t.grid_note();
        println!(
            "stroke {i} ({:?}, '{}', {} px){grid}: features {:.1} ms, k-means {:.1} ms, nnfm {:.1} ms ({} seeds), growth {:.1} ms ({growth}), cut {:.1} ms -> {} voxels; total {:.1} ms",
            s.polarity, s.object, t.stroke_pixels, t.stroke_features_ms, t.kmeans_ms, t.nnfm_ms, t.seed_voxels, t.grow_ms, t.cut_ms, t.region_voxels, t.total_ms()
        );
    }
    let name = a.object.clone().unwrap_or_else(|| strokes[0].object.clone());
    let mask = builder.mask;
    save_bitmap(&a.out, &mask, &name)?;
    let bb = mask.bounding_box();
    println!(
        "object '{name}': {} voxels, bounding box {:?} -> {}",
        mask.count(),
        bb,
        a.out.display()
    );
    Ok(())
}
