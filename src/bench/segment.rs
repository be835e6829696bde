//! Per-stage times of stroke → mask on a demo scene: the library's pipeline
//! (feature cache of occupied voxels, NNFM over the cache, frontier growth)
//! next to the straightforward dense implementation of
//! [`crate::segment::dense`] (features at every grid point, NNFM over every
//! voxel, growth steps that scan the whole grid), run in the same process on
//! the same stroke features and centres, with a check that both give the
//! same bitmaps.
//!
//! One-off work per field is timed separately and left out of the stage
//! times: the feature cache (or the dense feature array) and the macro grid
//! the renderer uses for the stroke's features. Stroke features and K-means
//! are the same code in both columns.

use super::{load_average, mb, mb_or_na, peak_rss_bytes, repeat, repeat_with, reset_peak_rss, time_ms, Table, Timed};
use crate::error::{Error, Result};
use crate::field::{Bitmap, FeatureCache};
use crate::render::Scene;
use crate::segment::dense::{dense_features, grow_step_full_scan, nnfm_dense};
use crate::segment::{
    nnfm_seed, region_from_stroke, stroke_centres, stroke_features, stroke_pixels, Grower, SegmentParams,
    MAX_GROW_STEPS,
};
use std::sync::Arc;

#[derive(Clone, Debug)]
pub struct SegmentBenchConfig {
    pub scene: String,
    /// Object whose built-in stroke is used.
    pub object: String,
    pub res: usize,
    /// Runs per stage (the median is reported).
    pub repeats: usize,
    /// A stage stops repeating once its runs took this long in total.
    pub budget_ms: f64,
    /// Also run the dense reference (needs `res³ × channels × 4` bytes).
    pub dense: bool,
}

impl SegmentBenchConfig {
    pub fn new(res: usize) -> Self {
        SegmentBenchConfig {
            scene: "tabletop".into(),
            object: "pot".into(),
            res,
            repeats: 5,
            budget_ms: 10_000.0,
            dense: true,
        }
    }
}

/// Median times of one stage; `dense_ms` is `None` when the dense reference
/// was not run. `shared` stages run the same code in both columns.
#[derive(Clone, Debug)]
pub struct Stage {
    pub name: &'static str,
    pub ms: f64,
    /// Median CPU time of all threads (None where not measurable).
    pub cpu_ms: Option<f64>,
    pub runs: usize,
    pub dense_ms: Option<f64>,
    pub dense_cpu_ms: Option<f64>,
    pub dense_runs: usize,
    pub shared: bool,
}

/// Median wall ms, median CPU ms, runs.
type StageTime = (f64, Option<f64>, usize);

fn stage_time<T>(t: &Timed<T>) -> StageTime {
    (t.median_ms(), t.median_cpu_ms(), t.runs())
}

#[derive(Clone, Debug)]
pub struct SegmentBenchReport {
    pub config: SegmentBenchConfig,
    pub threads: usize,
    /// 1-minute load average when the run started (other work on the machine
    /// makes wall times longer than CPU times).
    pub load_average: Option<f64>,
    pub channels: usize,
    /// Voxels in the feature cache (σ above the occupancy floor).
    pub cached_voxels: usize,
    pub stroke_pixels: usize,
    /// Stroke pixels that hit the field (rows of the stroke features).
    pub stroke_features: usize,
    pub centres: usize,
    pub seed_voxels: usize,
    pub one_step_voxels: usize,
    pub region_voxels: usize,
    pub grow_steps: usize,
    pub scene_build_ms: f64,
    pub macro_build_ms: f64,
    pub cache_build_ms: f64,
    pub cache_bytes: usize,
    pub stages: Vec<Stage>,
    /// The library's own `region_from_stroke`, end to end (median).
    pub pipeline_ms: f64,
    pub pipeline_matches: bool,
    /// `region_from_stroke` with the default rule, end to end
    /// (median), and the voxels it selects.
    pub default_ms: f64,
    pub default_voxels: usize,
    /// Peak resident memory while building the scene and running the cache
    /// path (before the dense arrays).
    pub peak_before_dense: Option<u64>,
    pub dense: Option<DenseSide>,
}

#[derive(Clone, Debug)]
pub struct DenseSide {
    pub build_ms: f64,
    pub bytes: usize,
    pub grow_steps: usize,
    /// Peak resident memory while the dense arrays were alive.
    pub peak_after: Option<u64>,
    /// Names of the outputs that differ from the cache path (empty = identical).
    pub mismatches: Vec<String>,
}

pub const STAGE_NAMES: [&str; 5] = [
    "stroke features",
    "k-means",
    "nnfm seed",
    "growth, one step",
    "growth to convergence",
];

/// The stages that make up stroke-to-mask.
pub const MASK_STAGES: [&str; 4] = ["stroke features", "k-means", "nnfm seed", "growth to convergence"];

impl SegmentBenchReport {
    fn stage(&self, name: &str) -> &Stage {
        self.stages
            .iter()
            .find(|s| s.name == name)
            .expect("every stage is measured")
    }
    /// Stroke features + K-means + NNFM + growth to convergence, cache built.
    pub fn stroke_to_mask_ms(&self) -> f64 {
        MASK_STAGES.iter().map(|n| self.stage(n).ms).sum()
    }
    /// CPU time of the same stages (all threads).
    pub fn stroke_to_mask_cpu_ms(&self) -> Option<f64> {
        MASK_STAGES.iter().map(|n| self.stage(n).cpu_ms).sum()
    }
    /// The same with the dense reference's NNFM and growth.
    pub fn dense_stroke_to_mask_ms(&self) -> Option<f64> {
        MASK_STAGES.iter().map(|n| self.stage(n).dense_ms).sum()
    }
    pub fn dense_stroke_to_mask_cpu_ms(&self) -> Option<f64> {
        MASK_STAGES.iter().map(|n| self.stage(n).dense_cpu_ms).sum()
    }
    pub fn speedup(&self) -> Option<f64> {
        self.dense_stroke_to_mask_ms().map(|d| d / self.stroke_to_mask_ms())
    }
    pub fn identical(&self) -> Option<bool> {
        self.dense.as_ref().map(|d| d.mismatches.is_empty())
    }
}

fn stage(name: &'static str, fast: StageTime, dense: Option<StageTime>, shared: bool) -> Stage {
    Stage {
        name,
        ms: fast.0,
        cpu_ms: fast.1,
        runs: fast.2,
        dense_ms: dense.map(|d| d.0),
        dense_cpu_ms: dense.and_then(|d| d.1),
        dense_runs: dense.map_or(0, |d| d.2),
        shared,
    }
}

/// Grows `mask` with full-grid scans until a step adds nothing; returns the
/// steps taken, counted like [`Grower::converge`] (the final empty step too).
fn converge_dense(
    d: &crate::segment::dense::DenseFeatures,
    mask: &mut Bitmap,
    p: &crate::segment::GrowParams,
) -> usize {
    for s in 0..MAX_GROW_STEPS {
        if grow_step_full_scan(d, mask, p) == 0 {
            return s + 1;
        }
    }
    MAX_GROW_STEPS
}

/// Builds the demo scene and measures every stage on the object's stroke.
pub fn bench_segment(cfg: &SegmentBenchConfig) -> Result<SegmentBenchReport> {
    crate::ensure!(
        (1..=1000).contains(&cfg.repeats),
        "repeats must be 1..=1000, got {}",
        cfg.repeats
    );
    // The stage-by-stage comparison runs the paper's rule, which is what the
    // dense reference implements; the default rule is timed end to end.
    let p = SegmentParams::paper();
    reset_peak_rss();
    let load_average = load_average();
    let (demo, scene_build_ms) = time_ms(|| crate::demo::build(&cfg.scene, cfg.res, 0));
    let demo = demo?;
    let stroke = crate::eval::protocol::demo_stroke(&demo, &cfg.object).ok_or_else(|| {
        Error::invalid(format!(
            "demo scene '{}' at {}^3 has no built-in stroke for '{}' (objects: {})",
            cfg.scene,
            cfg.res,
            cfg.object,
            demo.objects
                .iter()
                .map(|o| o.name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        ))
    })?;
    let field = Arc::new(demo.field);
    let (_, macro_build_ms) = time_ms(|| field.macro_grid().occupied_fraction());
    let (cache, cache_build_ms) = time_ms(|| FeatureCache::build(&field));
    let cache = cache?;
    let scene = Scene::single(field.clone());
    let (r, b) = (cfg.repeats, cfg.budget_ms);

    stroke_features(&scene, &stroke, p.min_stroke_opacity)?; // warm-up
    let feats = repeat(r, b, || stroke_features(&scene, &stroke, p.min_stroke_opacity));
    let (f, dim) = match &feats.value {
        Ok((f, dim)) => (f.clone(), *dim),
        Err(e) => return Err(Error::invalid(e.to_string())),
    };
    let centres = repeat(r, b, || stroke_centres(&f, dim, &p));
    let seed = repeat(r, b, || nnfm_seed(&cache, &centres.value, p.theta, p.seed_floor));
    let grower = |m: Bitmap| {
        let mut m = m;
        Grower::new(&cache, p.grow).step(&mut m);
        m
    };
    let one = repeat_with(r, b, || seed.value.clone(), grower);
    let conv = repeat_with(
        r,
        b,
        || seed.value.clone(),
        |mut m| {
            let steps = Grower::new(&cache, p.grow).converge(&mut m, MAX_GROW_STEPS);
            (m, steps)
        },
    );
    let pipeline = repeat(r, b, || region_from_stroke(&scene, &cache, &stroke, &p));
    let pipeline_matches = match &pipeline.value {
        Ok((region, _)) => *region == conv.value.0,
        Err(_) => false,
    };
    let pipeline_ms = pipeline.median_ms();
    pipeline.value?;
    let default = repeat(r, b, || {
        region_from_stroke(&scene, &cache, &stroke, &SegmentParams::default())
    });
    let default_ms = default.median_ms();
    let default_voxels = default.value?.0.count();
    let peak_before_dense = peak_rss_bytes();

    let fast = Outputs {
        centres: &centres.value,
        seed: &seed.value,
        one: &one.value,
        conv: &conv.value,
    };
    let dense = cfg.dense.then(|| bench_dense(&field, &p, &fast, r, b));
    let ft = stage_time(&feats);
    let kt = stage_time(&centres);
    // Stroke features and K-means are the same code on both sides.
    let same = |t: StageTime| cfg.dense.then_some((t.0, t.1, 0));
    let dt = |i: usize| dense.as_ref().map(|d| d.1[i]);
    let stages = vec![
        stage(STAGE_NAMES[0], ft, same(ft), true),
        stage(STAGE_NAMES[1], kt, same(kt), true),
        stage(STAGE_NAMES[2], stage_time(&seed), dt(0), false),
        stage(STAGE_NAMES[3], stage_time(&one), dt(1), false),
        stage(STAGE_NAMES[4], stage_time(&conv), dt(2), false),
    ];
    Ok(SegmentBenchReport {
        config: cfg.clone(),
        threads: rayon::current_num_threads(),
        load_average,
        channels: dim,
        cached_voxels: cache.len(),
        stroke_pixels: stroke_pixels(&stroke)?.len(),
        stroke_features: f.len() / dim.max(1),
        centres: centres.value.len(),
        seed_voxels: seed.value.count(),
        one_step_voxels: one.value.count(),
        region_voxels: conv.value.0.count(),
        grow_steps: conv.value.1,
        scene_build_ms,
        macro_build_ms,
        cache_build_ms,
        cache_bytes: cache.memory_bytes(),
        stages,
        pipeline_ms,
        pipeline_matches,
        default_ms,
        default_voxels,
        peak_before_dense,
        dense: dense.map(|d| d.0),
    })
}

/// What the cache path computed, for the dense reference to reproduce.
struct Outputs<'a> {
    centres: &'a crate::segment::Centroids,
    seed: &'a Bitmap,
    one: &'a Bitmap,
    conv: &'a (Bitmap, usize),
}

/// The dense reference on the same centres; compares its outputs with the
/// cache path's. Returns the side's summary and the times of
/// NNFM, one growth step and growth to convergence.
fn bench_dense(
    field: &crate::field::Field,
    p: &SegmentParams,
    fast: &Outputs,
    r: usize,
    b: f64,
) -> (DenseSide, [StageTime; 3]) {
    let (centres, seed, one, conv) = (fast.centres, fast.seed, fast.one, fast.conv);
    reset_peak_rss();
    let (d, build_ms) = time_ms(|| dense_features(field));
    let bytes = (d.feats.len() + d.sigma.len()) * 4;
    let dseed = repeat(r, b, || nnfm_dense(&d, centres, p.theta, p.seed_floor));
    let done = repeat_with(
        r,
        b,
        || seed.clone(),
        |mut m| {
            grow_step_full_scan(&d, &mut m, &p.grow);
            m
        },
    );
    let dconv = repeat_with(
        r,
        b,
        || seed.clone(),
        |mut m| {
            let steps = converge_dense(&d, &mut m, &p.grow);
            (m, steps)
        },
    );
    let peak_after = peak_rss_bytes();
    let mut mismatches = vec![];
    if dseed.value != *seed {
        mismatches.push(format!(
            "nnfm seed ({} vs {} voxels)",
            seed.count(),
            dseed.value.count()
        ));
    }
    if done.value != *one {
        mismatches.push(format!(
            "one growth step ({} vs {} voxels)",
            one.count(),
            done.value.count()
        ));
    }
    if dconv.value.0 != conv.0 {
        mismatches.push(format!(
            "converged region ({} vs {} voxels)",
            conv.0.count(),
            dconv.value.0.count()
        ));
    }
    if dconv.value.1 != conv.1 {
        mismatches.push(format!("growth steps ({} vs {})", conv.1, dconv.value.1));
    }
    let side = DenseSide {
        build_ms,
        bytes,
        grow_steps: dconv.value.1,
        peak_after,
        mismatches,
    };
    let times = [stage_time(&dseed), stage_time(&done), stage_time(&dconv)];
    (side, times)
}

fn ratio(dense: Option<f64>, fast: f64) -> String {
    dense.map_or_else(|| "-".into(), |d| format!("{:.1}x", d / fast.max(1e-9)))
}

/// The per-stage table of one report.
pub fn stage_table(r: &SegmentBenchReport) -> Table {
    let mut t = Table::new(&[
        "stage", "cache ms", "cpu ms", "runs", "dense ms", "cpu ms", "runs", "speed-up",
    ]);
    let ms = |v: Option<f64>| v.map_or_else(|| "-".into(), |x| format!("{x:.2}"));
    for s in &r.stages {
        let (dense, dense_cpu, dense_runs) = if s.shared && s.dense_ms.is_some() {
            ("(same code)".into(), "".into(), "".into())
        } else {
            (ms(s.dense_ms), ms(s.dense_cpu_ms), s.dense_runs.to_string())
        };
        t.row(vec![
            s.name.to_string(),
            format!("{:.2}", s.ms),
            ms(s.cpu_ms),
            s.runs.to_string(),
            dense,
            dense_cpu,
            dense_runs,
            ratio(s.dense_ms, s.ms),
        ]);
    }
    t.row(vec![
        "stroke-to-mask".into(),
        format!("{:.2}", r.stroke_to_mask_ms()),
        ms(r.stroke_to_mask_cpu_ms()),
        "".into(),
        ms(r.dense_stroke_to_mask_ms()),
        ms(r.dense_stroke_to_mask_cpu_ms()),
        "".into(),
        ratio(r.dense_stroke_to_mask_ms(), r.stroke_to_mask_ms()),
    ]);
    t
}

/// Human summary lines of one report (sizes, one-off costs, memory, identity).
pub fn summary(r: &SegmentBenchReport) -> Vec<String> {
    let c = &r.config;
    let mut v = vec![
        format!(
            "{} {}^3, object '{}': {} cached voxels x {} channels; stroke {} px ({} on the field), {} centres",
            c.scene, c.res, c.object, r.cached_voxels, r.channels, r.stroke_pixels, r.stroke_features, r.centres
        ),
        format!(
            "{} rayon threads, load average {} at the start (wall ms include waiting for other processes; cpu ms = all threads' CPU time)",
            r.threads,
            r.load_average.map_or_else(|| "n/a".into(), |l| format!("{l:.2}"))
        ),
        format!(
            "seed {} voxels, after one step {}, converged {} voxels in {} steps",
            r.seed_voxels, r.one_step_voxels, r.region_voxels, r.grow_steps
        ),
        format!(
            "one-off per field (not in the stage times): demo scene {:.0} ms, macro grid {:.1} ms, feature cache {:.1} ms{}",
            r.scene_build_ms,
            r.macro_build_ms,
            r.cache_build_ms,
            r.dense
                .as_ref()
                .map_or(String::new(), |d| format!(", dense features {:.1} ms", d.build_ms))
        ),
        format!(
            "memory: feature cache {:.1} MB{}; peak RSS (VmHWM) {} for scene + cache path{}",
            mb(r.cache_bytes as u64),
            r.dense
                .as_ref()
                .map_or(String::new(), |d| format!(", dense features + sigma {:.1} MB", mb(d.bytes as u64))),
            mb_or_na(r.peak_before_dense),
            r.dense
                .as_ref()
                .map_or(String::new(), |d| format!(", {} while the dense arrays lived", mb_or_na(d.peak_after)))
        ),
        format!(
            "library pipeline (region_from_stroke, end to end, paper rule): {:.2} ms, same region: {}",
            r.pipeline_ms,
            if r.pipeline_matches { "yes" } else { "no" }
        ),
        format!(
            "stroke to mask with the default rule (stable growth): {:.2} ms, {} voxels",
            r.default_ms, r.default_voxels
        ),
    ];
    match &r.dense {
        Some(d) if d.mismatches.is_empty() => v.push("identical: yes".into()),
        Some(d) => v.push(format!("identical: no ({})", d.mismatches.join("; "))),
        None => v.push("identical: not checked (dense reference skipped)".into()),
    }
    v
}
