//! Splat benchmarks: import speed on a large synthetic file, and one-stroke
//! selection of splats against exact ground truth.
//!
//! The selection benchmark builds a demo scene, samples Gaussians on its
//! surfaces with their object labels ([`crate::splat::synth`]), writes them
//! as a `.ply`, imports it, lifts teacher features from views rendered
//! around it (`isrf features --orbit`), segments every object from the
//! demo's built-in positive stroke with the default parameters and compares
//! the Gaussians the object exports with the ones on it, by count and by
//! opacity mass (τ·2π·s₂·s₃, the import's mass).
//!
//! Two teachers: the ONNX ViT (what `isrf features` uses), and an oracle,
//! the demo's own synthetic features rendered from the same orbit cameras
//! and lifted by the same code: it separates the objects by construction,
//! so its rows measure import, lifting, stroke selection and export alone.

use crate::demo;
use crate::error::{Error, Result};
use crate::field::Field;
use crate::lift::{lift, lift_maps, orbit_cameras, orbit_views};
use crate::render::Scene;
use crate::render::{render, RenderOptions};
use crate::segment::{object_from_stroke, SegmentParams};
use crate::splat::import::{import_file, import_read, inside, ImportOptions, ImportReport};
use crate::splat::ply::{standard_bytes, SplatFile};
use crate::splat::synth::{from_demo, SynthScene};
use crate::train::teacher::{FeatureMap, FeatureMaps};
use crate::train::TeacherSource;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// Writes a synthetic splat file of exactly `n` Gaussians (the tabletop
/// demo at `res`, several Gaussians per surface voxel) to `path`.
pub fn write_synthetic(path: &Path, n: usize, res: usize) -> Result<()> {
    let scene = demo::build("tabletop", res, 0)?;
    let one = from_demo(&scene, 1, 0).gaussians.len();
    crate::ensure!(one > 0, "the demo scene has no surface");
    let mut s = from_demo(&scene, n.div_ceil(one), 0);
    s.gaussians.truncate(n);
    write_scene(path, &s)
}

fn write_scene(path: &Path, s: &SynthScene) -> Result<()> {
    let bytes = standard_bytes(&s.gaussians, 3).map_err(Error::invalid)?;
    crate::error::write_atomic(path, &bytes)
}

/// What `isrf bench import` measures.
pub struct ImportTimes {
    pub report: ImportReport,
    /// Import, reading included, saving not.
    pub import_secs: f64,
    /// Which Gaussians an object holds ([`inside`], as an export decides),
    /// for the half of the grid with x above its centre: a plane through
    /// the whole scene, so many Gaussians straddle its edge.
    pub select_secs: f64,
    /// Gaussians that half holds.
    pub selected: usize,
}

/// Import time of a splat file, and the time to select the Gaussians of
/// half its grid as an export does.
pub fn bench_import(path: &Path, opts: &ImportOptions) -> Result<ImportTimes> {
    let t0 = Instant::now();
    let file = SplatFile::read(path)?;
    let (field, report) = import_read(path, &file, opts)?;
    let import_secs = t0.elapsed().as_secs_f64();
    let geom = field.geom();
    let mid = geom.bounds.center().x;
    let half = crate::field::Bitmap::from_fn(geom.res, |i| geom.point_of(i).x > mid);
    let t1 = Instant::now();
    let selected = inside(&file, &geom, &half).iter().filter(|&&k| k).count();
    Ok(ImportTimes {
        report,
        import_secs,
        select_secs: t1.elapsed().as_secs_f64(),
        selected,
    })
}

#[derive(Clone, Debug)]
pub struct SplatBenchConfig {
    pub scenes: Vec<String>,
    pub res: usize,
    pub orbit: usize,
    /// The ViT teacher; `None`: the oracle only.
    pub teacher: Option<TeacherSource>,
    pub dims: usize,
    pub cache_dir: Option<PathBuf>,
    /// Where the .ply and field files go.
    pub work: PathBuf,
    /// Segmentation parameters of the strokes.
    pub params: SegmentParams,
    /// Also score each stroke's selection after every stage
    /// ([`crate::bench::quality::stage_params`]).
    pub diagnose: bool,
}

/// One object's row.
#[derive(Clone, Debug, serde::Serialize)]
pub struct SplatRow {
    pub scene: String,
    /// "oracle" or "vit".
    pub features: String,
    pub object: String,
    pub true_gaussians: usize,
    pub selected: usize,
    pub iou_count: f64,
    pub iou_mass: f64,
    /// True Gaussians of the object left out.
    pub missed: usize,
    /// Gaussians selected that are not the object's, by the name of what
    /// they are (most first; "unlabelled" for label 0).
    pub wrong: Vec<(String, usize)>,
    /// With `diagnose`: the selection after each stage of the stroke, the
    /// defaults' last.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub stages: Vec<SplatStage>,
}

/// What one stage of a stroke's segmentation selects, in Gaussians.
#[derive(Clone, Debug, serde::Serialize)]
pub struct SplatStage {
    pub stage: String,
    pub selected: usize,
    pub iou_count: f64,
    pub missed: usize,
    pub wrong: Vec<(String, usize)>,
}

/// Runs the selection benchmark (module docs); `log` hears each stage.
pub fn bench_splats(cfg: &SplatBenchConfig, log: &(dyn Fn(&str) + Sync)) -> Result<Vec<SplatRow>> {
    let mut rows = vec![];
    for name in &cfg.scenes {
        let scene = demo::build(name, cfg.res, 0)?;
        let synth = from_demo(&scene, 1, 7);
        let ply = cfg.work.join(format!("{name}.ply"));
        write_scene(&ply, &synth)?;
        let (mut field, r) = import_file(&ply, &ImportOptions::default())?;
        // As `isrf import --up 0,1,0` would say: the demo scenes stand on y.
        field.up = Some(glam::Vec3::Y);
        log(&format!(
            "{name}: {} Gaussians imported to a {:?} grid ({} occupied points)",
            synth.gaussians.len(),
            r.res,
            r.occupied
        ));
        let field = Arc::new(field);
        let oracle = oracle_features(&scene, &field, cfg.orbit)?;
        rows.extend(score_objects(&scene, &synth, &oracle, "oracle", cfg)?);
        if let Some(teacher) = &cfg.teacher {
            let views = orbit_views(&field, cfg.orbit, &|_, _| ())?;
            let (with, lr) = lift(
                &field,
                &views,
                teacher,
                cfg.dims,
                cfg.cache_dir.as_deref(),
                &|_, _, _| (),
            )?;
            log(&format!(
                "{name}: ViT features from {} orbit views ({:.0} % of points seen)",
                cfg.orbit,
                100.0 * lr.seen as f64 / lr.points.max(1) as f64
            ));
            with.save(&cfg.work.join(format!("{name}.features.safetensors")))?;
            rows.extend(score_objects(&scene, &synth, &with, "vit", cfg)?);
        }
    }
    Ok(rows)
}

/// The imported field with the demo's own features, rendered from the
/// orbit cameras and lifted.
pub fn oracle_features(scene: &demo::DemoScene, field: &Field, orbit: usize) -> Result<Field> {
    let cams = orbit_cameras(field, orbit)?;
    let truth = Scene::single(Arc::new(scene.field.clone()));
    let opts = RenderOptions {
        features: true,
        depth: false,
        ..Default::default()
    };
    let mut maps = vec![];
    for c in &cams {
        maps.push(FeatureMap::from_frame(render(&truth, c, &opts)?));
    }
    let maps = FeatureMaps::new(scene.field.feature_channels(), maps)?;
    Ok(lift_maps(field, &cams, &maps, &|_, _| ())?.0)
}

fn score_objects(
    scene: &demo::DemoScene,
    synth: &SynthScene,
    field: &Field,
    features: &str,
    cfg: &SplatBenchConfig,
) -> Result<Vec<SplatRow>> {
    let field = Arc::new(field.clone());
    let file = crate::splat::export::source_file(&field)?;
    let cache = field.feature_cache()?;
    let render_scene = Scene::single(field.clone());
    let mass: Vec<f64> = (0..file.len()).map(|i| opacity_mass(&file, i)).collect();
    let mut rows = vec![];
    for o in &scene.objects {
        let Some(stroke) = crate::eval::protocol::demo_stroke(scene, &o.name) else {
            continue;
        };
        let truth: Vec<bool> = synth.labels.iter().map(|&l| l == o.label).collect();
        let select = |p: &SegmentParams| -> Result<Vec<bool>> {
            let (region, _) = object_from_stroke(&render_scene, &cache, &stroke, p)?;
            Ok(inside(&file, &field.geom(), &region))
        };
        let stage = |name: String, picked: &[bool]| SplatStage {
            stage: name,
            selected: picked.iter().filter(|&&t| t).count(),
            iou_count: iou(picked, &truth, |_| 1.0),
            missed: (0..truth.len()).filter(|&i| truth[i] && !picked[i]).count(),
            wrong: wrong_by_label(scene, synth, picked, o.label),
        };
        let picked = select(&cfg.params)?;
        let last = stage("cut".into(), &picked);
        let mut stages = vec![];
        if cfg.diagnose {
            for (name, p) in crate::bench::quality::stage_params(&cfg.params) {
                stages.push(stage(name, &select(&p)?));
            }
            stages.push(last.clone());
        }
        rows.push(SplatRow {
            missed: last.missed,
            wrong: last.wrong,
            scene: scene.name.clone(),
            features: features.to_string(),
            object: o.name.clone(),
            true_gaussians: truth.iter().filter(|&&t| t).count(),
            selected: last.selected,
            iou_count: last.iou_count,
            iou_mass: iou(&picked, &truth, |i| mass[i]),
            stages,
        });
    }
    Ok(rows)
}

/// The Gaussians `picked` that are not `label`'s, counted by the name of
/// what they are, most first.
fn wrong_by_label(scene: &demo::DemoScene, synth: &SynthScene, picked: &[bool], label: u8) -> Vec<(String, usize)> {
    let mut per = [0usize; 256];
    for (&l, _) in synth.labels.iter().zip(picked).filter(|(_, &p)| p) {
        per[l as usize] += 1;
    }
    super::wrong_by_name(&per, &scene.labels, label)
}

/// τ·2π·s₂·s₃ of Gaussian `i`.
fn opacity_mass(file: &SplatFile, i: usize) -> f64 {
    let g = file.gaussian(i);
    let mut s = g.scales().to_array();
    s.sort_by(f32::total_cmp);
    let tau = -(1.0 - g.alpha().min(0.995) as f64).ln();
    tau * std::f64::consts::TAU * s[1] as f64 * s[2] as f64
}

fn iou(a: &[bool], b: &[bool], w: impl Fn(usize) -> f64) -> f64 {
    let (mut inter, mut union) = (0.0, 0.0);
    for i in 0..a.len() {
        if a[i] || b[i] {
            union += w(i);
            if a[i] && b[i] {
                inter += w(i);
            }
        }
    }
    if union > 0.0 {
        inter / union
    } else {
        1.0
    }
}
