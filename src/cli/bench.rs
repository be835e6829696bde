//! `isrf bench <what>`: measured figures printed as tables (never timed
//! asserts). Each kind of benchmark is one variant of [`What`]; add new ones
//! there with their own argument struct and `run_*` function.

use anyhow::{bail, Result};
use isrf::bench::render::{bench_render, build_table, render_table};
use isrf::bench::segment::{bench_segment, stage_table, summary, SegmentBenchConfig};

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    pub what: What,
}

#[derive(clap::Subcommand)]
pub enum What {
    /// Rays per second of the CPU reference renderer on a demo scene.
    Render(RenderArgs),
    /// Per-stage times of stroke -> mask, against the dense reference implementation.
    Segment(SegmentArgs),
    /// Frames per second of the editor's GPU view (needs the `editor` feature).
    Editor(super::edit::BenchArgs),
    /// Rays/s and iterations/s of the trainer (a dataset, or a rendered demo capture).
    Train(TrainArgs),
    /// Segmentation quality with exact ground truth: fields trained (as
    /// `isrf train` does, real teacher) on renders of the demo scenes, every
    /// object segmented from one stroke with the default parameters.
    Quality(QualityArgs),
    /// Import time of a splat .ply (a synthetic 1M-Gaussian file by default).
    Import(super::bench_splats::ImportArgs),
    /// One-stroke selection of splats: exported Gaussians against exact ground truth.
    Splats(super::bench_splats::SplatArgs),
}

#[derive(clap::Args)]
pub struct QualityArgs {
    /// Demo scenes, comma separated (default: all).
    #[arg(long, value_delimiter = ',')]
    pub scenes: Vec<String>,
    /// Resolution of the ground-truth scenes (rendered and scored against).
    #[arg(long, default_value_t = 192)]
    pub res: usize,
    /// Training views per scene (a spiral over the upper hemisphere).
    #[arg(long, default_value_t = 80)]
    pub views: usize,
    /// Image width (400 divided by a whole number; 4:3 images).
    #[arg(long, default_value_t = 200)]
    pub width: u32,
    /// Radiance iterations (default: `isrf train`'s, 9500 for these
    /// Blender-layout captures: about 1 hour for both scenes on two cores
    /// the first time, cached after). `--iters 2000 --feature-iters 500`
    /// trains a scene in about 15 minutes (the table's header then says
    /// REDUCED).
    #[arg(long)]
    pub iters: Option<usize>,
    /// Distillation iterations (default: `isrf train`'s, 1500).
    #[arg(long)]
    pub feature_iters: Option<usize>,
    /// Negative strokes (on the nearest objects) per object in the NVOS-style test.
    #[arg(long, default_value_t = 2)]
    pub negatives: usize,
    /// Train again instead of using the cached fields.
    #[arg(long)]
    pub retrain: bool,
    /// Teacher input size, long side in pixels (default: `isrf train`'s).
    #[arg(long, default_value_t = 0)]
    pub teacher_size: u32,
    /// Shifted teacher runs per axis (`isrf train --teacher-shifts`; the
    /// renders get NeRF-synthetic's default, 1).
    #[arg(long, default_value_t = 1)]
    pub teacher_shifts: u32,
    /// Teacher crops per axis (`isrf train --teacher-tiles`).
    #[arg(long, default_value_t = 1)]
    pub teacher_tiles: u32,
    /// The teacher's tensor to distil (`isrf train --teacher-output`; e.g.
    /// the last block's attention keys,
    /// `/backbone/encoder/layer.11/attention/attention/key/Add_output_0`).
    #[arg(long)]
    pub teacher_output: Option<String>,
    /// σ of the image-guided upsampling of teacher maps (0: bilinear;
    /// default: `isrf train`'s).
    #[arg(long)]
    pub feature_guide: Option<f32>,
    /// Longest side of the feature grid (default: `isrf train`'s).
    #[arg(long)]
    pub feature_res: Option<usize>,
    /// Print the report as JSON instead of tables.
    #[arg(long)]
    pub json: bool,
    /// Also score each stroke's seeds and stable region before the graph
    /// cut, name the objects every stage selects wrongly, and say how far
    /// apart the teacher's own maps, and the field distilled from them,
    /// hold each object from its neighbours.
    #[arg(long)]
    pub diagnose: bool,
    /// JSON file with training settings put over the Blender preset (as
    /// `isrf train --config`), to score fields trained otherwise; such
    /// fields are cached under their own keys.
    #[arg(long)]
    pub config: Option<std::path::PathBuf>,
    /// Segmentation parameters (defaults unless given: for ablations).
    #[command(flatten)]
    pub params: super::segment::ParamArgs,
}

#[derive(clap::Args)]
pub struct TrainArgs {
    /// Dataset to train on (default: a capture rendered from the tabletop demo,
    /// with its rendered features as the teacher).
    #[arg(long)]
    pub dataset: Option<std::path::PathBuf>,
    /// Downscale the dataset's images by N.
    #[arg(long, default_value_t = 4)]
    pub downscale: u32,
    /// Radiance iterations (the preset's coarse-to-fine schedule, compressed).
    #[arg(long, default_value_t = 300)]
    pub iters: usize,
    /// Distillation iterations (demo capture only).
    #[arg(long, default_value_t = 100)]
    pub feature_iters: usize,
    /// Final grid resolution (default: the preset's).
    #[arg(long)]
    pub res: Option<usize>,
    /// JSON file with training settings put over the preset (as `isrf
    /// train --config`), for comparing settings.
    #[arg(long)]
    pub config: Option<std::path::PathBuf>,
}

pub fn run(a: Args) -> Result<()> {
    match a.what {
        What::Render(a) => run_render(a),
        What::Segment(a) => run_segment(a),
        What::Editor(a) => super::edit::bench(a),
        What::Train(a) => run_train(a),
        What::Quality(a) => run_quality(a),
        What::Import(a) => super::bench_splats::run_import(a),
        What::Splats(a) => super::bench_splats::run_splats(a),
    }
}

#[derive(clap::Args)]
pub struct RenderArgs {
    /// Grid resolutions to measure, comma separated; the last line reports the largest.
    #[arg(long, value_delimiter = ',', default_values_t = [128, 320])]
    pub res: Vec<usize>,
    /// Demo scene.
    #[arg(long, default_value = "tabletop")]
    pub scene: String,
    /// Image width in pixels.
    #[arg(long, default_value_t = 400)]
    pub width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 300)]
    pub height: u32,
    /// Orbit cameras rendered per measurement (spread over the orbit).
    #[arg(long, default_value_t = 4)]
    pub frames: usize,
}

#[derive(clap::Args)]
pub struct SegmentArgs {
    /// Grid resolutions to measure, comma separated; the last line reports the largest.
    #[arg(long, value_delimiter = ',', default_values_t = [128, 320])]
    pub res: Vec<usize>,
    /// Demo scene.
    #[arg(long, default_value = "tabletop")]
    pub scene: String,
    /// Object whose built-in stroke is segmented.
    #[arg(long, default_value = "pot")]
    pub object: String,
    /// Runs per stage; the median is reported (slow stages stop after ~10 s of runs).
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// Skip the dense reference (it needs res^3 x channels x 4 bytes of memory).
    #[arg(long)]
    pub no_dense: bool,
    /// Measure on this field (with features) instead of a demo scene: the
    /// strokes of --strokes replayed with the default pipeline, per stroke.
    #[arg(long, requires = "strokes")]
    pub field: Option<std::path::PathBuf>,
    /// Stroke documents for --field, replayed in order.
    #[arg(long, num_args = 1.., requires = "field")]
    pub strokes: Vec<std::path::PathBuf>,
    /// Camera set for strokes whose camera is given only by name (the
    /// `<field>.cameras.json` that `isrf train` writes).
    #[arg(long, requires = "field")]
    pub cameras: Option<std::path::PathBuf>,
    #[command(flatten)]
    pub params: super::segment::ParamArgs,
}

fn check_res(res: &[usize]) -> Result<usize> {
    match res.iter().max() {
        Some(&m) => Ok(m),
        None => bail!("--res needs at least one resolution"),
    }
}

fn run_render(a: RenderArgs) -> Result<()> {
    let largest = check_res(&a.res)?;
    println!(
        "CPU reference renderer, {} demo scene, {}x{} pixels, {} orbit cameras, {} rayon threads",
        a.scene,
        a.width,
        a.height,
        a.frames,
        rayon::current_num_threads()
    );
    let mut rows = vec![];
    for &res in &a.res {
        eprintln!("building {} at {res}^3 and rendering ...", a.scene);
        rows.push(bench_render(&a.scene, res, a.width, a.height, a.frames)?);
    }
    println!("\none-off per field (the renderer needs the macro grid; segmentation the cache):");
    print!("{}", build_table(&rows));
    println!("\nrendering (colour + depth; +feat: also the semantic features), after one warm-up frame:");
    print!("{}", render_table(&rows));
    let last = rows
        .iter()
        .rev()
        .find(|r| r.res == largest)
        .expect("measured every resolution");
    if let Some(l) = last.load_average {
        println!("load average {l:.2} at the start: wall times include waiting for other processes, cpu times do not");
    }
    println!("rays/s: {:.0}", last.plain.rays_per_s);
    Ok(())
}

fn run_segment(a: SegmentArgs) -> Result<()> {
    if let Some(field) = &a.field {
        return run_field_strokes(field, &a);
    }
    let largest = check_res(&a.res)?;
    println!(
        "stroke -> mask, {} demo scene, object '{}', {} rayon threads, median of up to {} runs per stage",
        a.scene,
        a.object,
        rayon::current_num_threads(),
        a.repeats
    );
    println!(
        "stroke-to-mask = stroke features + k-means + nnfm + growth to convergence, per-field caches already built"
    );
    let mut last = None;
    for &res in &a.res {
        eprintln!("building {} at {res}^3 and segmenting ...", a.scene);
        let cfg = SegmentBenchConfig {
            scene: a.scene.clone(),
            object: a.object.clone(),
            repeats: a.repeats,
            dense: !a.no_dense,
            ..SegmentBenchConfig::new(res)
        };
        let r = bench_segment(&cfg)?;
        println!();
        for line in summary(&r) {
            println!("{line}");
        }
        print!("{}", stage_table(&r));
        if res == largest {
            last = Some(r);
        }
    }
    let r = last.expect("measured every resolution");
    let speedup = r.speedup().map_or_else(|| "n/a".into(), |s| format!("{s:.1}x"));
    println!(
        "stroke-to-mask ms at {}^3: {:.1}, speed-up over dense: {speedup}",
        r.config.res,
        r.stroke_to_mask_ms()
    );
    Ok(())
}

/// `isrf bench segment --field F --strokes S`: stroke latency on a real field.
fn run_field_strokes(path: &std::path::Path, a: &SegmentArgs) -> Result<()> {
    use isrf::bench::strokes::{bench_field_strokes, cut_stage_table, field_stroke_table};
    let p = a.params.params()?;
    let cameras = a.cameras.as_deref().map(isrf::camera::CameraSet::load).transpose()?;
    let mut strokes = vec![];
    for s in &a.strokes {
        strokes.extend(isrf::segment::load_strokes_on(s, cameras.as_ref())?);
    }
    let (field, load_ms) = isrf::bench::time_ms(|| isrf::field::Field::load(path));
    let field = std::sync::Arc::new(field?.or_up_from(cameras.as_ref()));
    let r = bench_field_strokes(field, &strokes, &p, a.repeats)?;
    println!(
        "stroke -> mask on {}: grid {:?}, {} cached voxels x {} channels, {} rayon threads, median of {} runs, load average {}",
        path.display(),
        r.res,
        r.cached_voxels,
        r.channels,
        r.threads,
        a.repeats,
        r.load_average.map_or_else(|| "n/a".into(), |l| format!("{l:.2}"))
    );
    println!(
        "one-off per field (not in the stroke times): load {load_ms:.0} ms, feature cache {:.0} ms, coarse copy and cut neighbours {:.0} ms, macro grid {:.0} ms; peak RSS {}",
        r.cache_ms,
        r.coarse_ms,
        r.macro_ms,
        isrf::bench::mb_or_na(r.peak_rss)
    );
    print!("{}", field_stroke_table(&r));
    println!("graph cut stages (ms):");
    print!("{}", cut_stage_table(&r));
    println!("slowest stroke-to-mask ms: {:.1}", r.worst_ms());
    Ok(())
}

fn run_train(a: TrainArgs) -> Result<()> {
    use isrf::bench::train::{demo_capture, demo_trainer, run_and_measure, stage_table, totals};
    use isrf::data::{Dataset, LoadOptions};
    use isrf::train::{preset, Session};
    if a.iters == 0 {
        bail!("--iters must be at least 1");
    }
    let threads = rayon::current_num_threads();
    let (what, mut trainer) = match &a.dataset {
        Some(path) => {
            let kind = Dataset::detect(path)?;
            let mut config = preset(kind);
            if let Some(p) = &a.config {
                config = super::train::overlay_config(config, p)?;
            }
            config.iters = a.iters;
            if let Some(r) = a.res {
                config.res = r;
                config.coarse_res = config.coarse_res.min(r);
            }
            config.validate()?;
            let opts = LoadOptions {
                downscale: a.downscale,
                ..Default::default()
            };
            let ds = Dataset::load(path, &opts)?;
            let what = format!("{} ({:?}, downscale {})", path.display(), kind, a.downscale);
            (what, Session::new(ds, config)?.trainer)
        }
        None => {
            eprintln!("rendering a 40-view 200x150 capture of the tabletop demo ...");
            let capture = demo_capture("tabletop", 96, 40, 200)?;
            let config = isrf::train::TrainConfig {
                iters: a.iters,
                feature_iters: a.feature_iters,
                res: a.res.unwrap_or(96),
                coarse_res: 48.min(a.res.unwrap_or(96)),
                feature_res: 48,
                ..Default::default()
            };
            config.validate()?;
            (
                "tabletop demo capture, 40 views at 200x150".to_string(),
                demo_trainer(&capture, config)?,
            )
        }
    };
    println!(
        "trainer throughput on {what}, {threads} rayon threads, batch {}",
        trainer.config.batch
    );
    let rows = run_and_measure(&mut trainer, |_| ())?;
    print!("{}", stage_table(&rows));
    if let Some(l) = isrf::bench::load_average() {
        println!("load average {l:.2}: wall times include waiting for other processes");
    }
    let (fi, fr, fs) = totals(&rows, "features");
    if fi > 0 {
        println!("distillation: {:.0} rays/s, {:.2} it/s", fr as f64 / fs, fi as f64 / fs);
    }
    let (i, r, s) = totals(&rows, "radiance");
    println!("it/s: {:.2}", i as f64 / s.max(1e-9));
    println!("rays/s: {:.0}", r as f64 / s.max(1e-9));
    Ok(())
}

fn run_quality(a: QualityArgs) -> Result<()> {
    use isrf::bench::quality::{bench_quality, object_table, run_lines, separation_lines, stage_lines, QualityConfig};
    let mut cfg = QualityConfig {
        demo_res: a.res,
        views: a.views,
        width: a.width,
        iters: a.iters,
        feature_iters: a.feature_iters,
        retrain: a.retrain,
        negatives: a.negatives,
        params: a.params.params()?,
        teacher_size: a.teacher_size,
        teacher_shifts: a.teacher_shifts,
        teacher_tiles: a.teacher_tiles,
        teacher_output: a.teacher_output,
        feature_guide: a.feature_guide,
        feature_res: a.feature_res,
        diagnose: a.diagnose,
        base_train: a
            .config
            .as_deref()
            .map(|p| super::train::overlay_config(isrf::train::preset(isrf::data::DatasetKind::Blender), p))
            .transpose()?,
        ..Default::default()
    };
    if !a.scenes.is_empty() {
        cfg.scenes = a.scenes;
    }
    let r = bench_quality(&cfg)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    println!(
        "segmentation quality on renders of the demo scenes, fields trained as `isrf train` (Blender preset, \
         default teacher), one positive stroke per object, {} segmentation parameters, {} rayon threads",
        if cfg.params == isrf::segment::SegmentParams::default() {
            "default"
        } else {
            "NON-DEFAULT"
        },
        rayon::current_num_threads()
    );
    for l in run_lines(&r) {
        println!("{l}");
    }
    println!(
        "3D IoU: voxels of the trained field that a training view sees (a sample there takes ≥ 10 % of a pixel's light), \
         labelled by the label grid at their centres or, in the blur of a surface, one voxel away, \
         else by the true label of the pixels whose light they take most of (a surface blurred deeper, haze beside it) \
         (all: every voxel with 1 % opacity across it, seen or not, centre labels); 2D: held-out views, opacity > 0.1 (ceiling: the field's own labelled voxels, a perfect selection); \
         NVOS: stroke + {} negative strokes on the nearest objects, IoU on the held-out view where the object is largest",
        cfg.negatives
    );
    print!("{}", object_table(&r));
    for l in stage_lines(&r).into_iter().chain(separation_lines(&r)) {
        println!("{l}");
    }
    println!("realistic NVOS mean 2D mIoU: {:.3}", r.nvos_mean_miou);
    println!(
        "realistic mean 2D mIoU: {:.3}, accuracy: {:.3}",
        r.mean_miou2d, r.mean_accuracy2d
    );
    println!("realistic min 3D IoU: {:.3}, mean: {:.3}", r.min_iou3d, r.mean_iou3d);
    Ok(())
}
