//! The training loop: batches of random rays, forward + backward on every
//! thread into its own gradient buffer, sparse Adam on the touched voxels,
//! coarse-to-fine resolution stages, pruning, and an optional feature
//! distillation phase after the radiance iterations.

use super::grads::{gather, GradBuf, GradLog};
use super::march::{backward, forward, MarchOpts, RayOut, Scratch};
use super::mining::{uniform_estimate, MinedBatch, RayMiner};
use super::model::{res_for, Model, PRUNED_RAW};
use super::optim::{adam_step, add_tv, corrected_lr, dense_adam_step, merge_marks, AdamParams, Layout, Moments, Tv};
use super::rays::RaySet;
use super::teacher::FeatureMaps;
use super::vm::{VmAppearance, VmShape};
use crate::camera::Ray;
use crate::field::{Aabb, GridGeom};
use crate::util::SplitMix64;
use crate::{ensure, Result};
use glam::Vec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Everything that shapes a training run. Defaults suit a NeRF-synthetic
/// scene at 200×200 on two cores; `isrf train` adjusts a few per dataset.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct TrainConfig {
    /// Radiance iterations (colour loss only).
    pub iters: usize,
    /// Rays per iteration.
    pub batch: usize,
    /// Grid points along the longest side of the box at the last stage.
    pub res: usize,
    /// Grid points along the longest side at the first stage.
    pub coarse_res: usize,
    /// Per-axis multipliers of the resolution (cubic voxels when all 1;
    /// forward-facing scenes need less along NDC depth).
    pub axis_scale: [f32; 3],
    /// Resolution stages from `coarse_res` to `res` (geometric), the last
    /// one starting at `last_stage_at` of the iterations.
    pub stages: usize,
    pub last_stage_at: f32,
    /// Spherical-harmonic degree (0–2) after the first stage (which uses 0).
    pub sh_degree: usize,
    /// Adam learning rate of the density, in raw units times the voxel size
    /// (so it means the same at every resolution).
    ///
    /// Sparse Adam moves a voxel by about the learning rate each step a ray
    /// touches it; fine grids, whose voxels a step touches rarely, take
    /// twice these ([`super::session::FINE_GRID_LR`]), and full-size
    /// NeRF-synthetic grids twice again on their last stage
    /// ([`Self::lr_last_stage`]).
    pub lr_density: f32,
    pub lr_sh: f32,
    pub lr_features: f32,
    /// Factor on the density and colour learning rates on the last
    /// (full-resolution) stage: the finest grid's voxels are touched least
    /// often per step, so they can take larger steps than the coarse
    /// stages, whose cells many rays share.
    pub lr_last_stage: f32,
    /// Learning rates decay exponentially to this fraction at the end.
    pub lr_final: f32,
    /// Initial per-sample opacity (empty but trainable).
    pub init_alpha: f32,
    /// After the first stage, samples with weight below this are not shaded.
    pub weight_floor: f32,
    /// Rays stop once their transmittance drops below this.
    pub min_transmittance: f32,
    /// Voxels whose per-sample opacity stays below this are pruned (with a
    /// margin of `prune_dilate` voxels) at every stage change and every
    /// `prune_every` iterations.
    pub prune_alpha: f32,
    pub prune_dilate: usize,
    pub prune_every: usize,
    /// Also prune once halfway through the first stage. Until its first
    /// prune every ray marches the whole coarse box and shades every
    /// sample: on lego that stage took half of a 7-minute run.
    pub prune_first_stage: bool,
    /// Shrink the box to the occupied region when the second stage starts.
    pub shrink_bounds: bool,
    /// Squared total-variation weights (per touched voxel and iteration) on
    /// voxel-scaled density, SH coefficients and features.
    pub tv_density: f32,
    pub tv_sh: f32,
    pub tv_features: f32,
    /// Fraction of the touched voxels whose density and colour TV is taken
    /// at each iteration (weight divided by it: the same TV in expectation).
    pub tv_keep: f32,
    /// Factor on the density and colour TV weights during the last (full
    /// resolution) stage: 0 lets the coarse stages settle the geometry
    /// smoothly and the full grid then fit thin parts freely.
    pub tv_last_stage: f32,
    /// Weight λ of the distortion loss (mip-NeRF 360) added to the mean
    /// colour error: it pulls each ray's weight into one short stretch, so
    /// that fog and doubled surfaces, invisible in the training views,
    /// do not ghost in new ones. 0: off.
    pub distortion: f32,
    /// Factor on `distortion` before the last stage: 0 leaves the coarse
    /// stages free to spread weight (their cells are too large for thin
    /// surfaces) and compacts the surfaces of the full grid only.
    pub distortion_coarse: f32,
    /// Share of each radiance batch drawn in proportion to the running
    /// colour error of its stretch of image row ([`super::mining`]); 0:
    /// uniform batches.
    pub mining: f32,
    /// Exponent α of the mined rays' importance weights (0: plain hard
    /// mining, 1: unbiased).
    pub mining_alpha: f32,
    pub background: [f32; 3],
    /// Train each radiance step over a random background colour where the
    /// photos' opacity is known (Blender scenes), as Instant-NGP does:
    /// over the one background a field can hide a faint halo in it (a
    /// white fringe on white); over changing ones its opacity must match
    /// the photos'. Held-out views are still scored over `background`.
    pub random_background: bool,
    /// Initial box; `None`: [`super::rays::default_bounds`] of the dataset.
    pub bounds: Option<[[f32; 3]; 2]>,
    pub seed: u64,
    /// Feature distillation iterations after the radiance ones (0 = none).
    pub feature_iters: usize,
    /// Longest side of the feature grid.
    pub feature_res: usize,
    /// λ of L = L_rgb + λ·L_feat.
    pub feature_lambda: f32,
    /// σ of the colour term when the teacher's maps are upsampled to the
    /// sampled pixel with the image as guide (`FeatureMaps::sample_guided`);
    /// 0: plain bilinear sampling.
    pub feature_guide: f32,
    /// Keep density and colour fixed while distilling features (the
    /// default): distillation then trains only the feature grid, at about
    /// half the cost per iteration. Training them on at the decayed rate
    /// bought fern 0.06 dB (22.47 against 22.41 held-out) for 5 more
    /// minutes (19:14 against 14:15).
    pub freeze_geometry: bool,
    /// Colour model after the first stage: dense SH (the default) or the
    /// paper's VM + MLP.
    pub appearance: AppearanceKind,
    /// Sizes of the VM + MLP appearance.
    pub vm: VmShape,
    /// Adam learning rates of the VM planes/lines and of the basis + MLP.
    pub lr_vm_grid: f32,
    pub lr_vm_net: f32,
}

/// Which colour model trains (see `isrf train --appearance`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum AppearanceKind {
    /// Dense spherical harmonics per voxel (degree `sh_degree`).
    #[default]
    Sh,
    /// TensoRF vector–matrix components with a small MLP.
    Vm,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            iters: 4000,
            batch: 4096,
            res: 160,
            coarse_res: 64,
            axis_scale: [1.0; 3],
            stages: 4,
            last_stage_at: 0.5,
            sh_degree: 2,
            lr_density: 0.1,
            lr_sh: 0.05,
            lr_features: 0.1,
            lr_last_stage: 1.0,
            lr_final: 0.1,
            init_alpha: 1e-4,
            weight_floor: 1e-4,
            min_transmittance: 1e-4,
            prune_alpha: 1e-3,
            prune_dilate: 2,
            prune_every: 1000,
            prune_first_stage: false,
            shrink_bounds: true,
            tv_density: 0.0,
            tv_sh: 0.0,
            tv_features: 0.0,
            tv_keep: 1.0,
            tv_last_stage: 1.0,
            distortion: 0.0,
            distortion_coarse: 1.0,
            mining: 0.0,
            mining_alpha: 0.5,
            background: [1.0; 3],
            random_background: true,
            bounds: None,
            seed: 0,
            feature_iters: 0,
            feature_res: 128,
            feature_lambda: 1e-3,
            feature_guide: 0.1,
            freeze_geometry: true,
            appearance: AppearanceKind::Sh,
            vm: VmShape {
                rank: 16,
                out: 27,
                hidden: 64,
                view_pe: 2,
            },
            lr_vm_grid: 0.02,
            lr_vm_net: 1e-3,
        }
    }
}

impl TrainConfig {
    pub fn validate(&self) -> Result<()> {
        crate::ensure_within!(
            OutOfRange,
            self.batch >= 1 && self.batch <= 1 << 22,
            "batch must be 1..4M rays"
        );
        crate::ensure_within!(
            OutOfRange,
            self.res >= 4 && self.res <= 1024,
            "res must be 4..1024, got {}",
            self.res
        );
        crate::ensure_within!(
            OutOfRange,
            self.coarse_res >= 4 && self.coarse_res <= self.res,
            "coarse res must be 4..=res, got {}",
            self.coarse_res
        );
        crate::ensure_within!(
            OutOfRange,
            self.stages >= 1 && self.stages <= 16,
            "stages must be 1..16"
        );
        crate::ensure_within!(
            OutOfRange,
            self.axis_scale
                .iter()
                .all(|s| s.is_finite() && (0.05..=4.0).contains(s)),
            "axis scales must be in [0.05, 4]"
        );
        crate::ensure_within!(
            OutOfRange,
            (0.0..1.0).contains(&self.last_stage_at),
            "last_stage_at must be in [0, 1)"
        );
        crate::ensure_within!(OutOfRange, self.sh_degree <= 2, "SH degree must be 0, 1 or 2");
        self.vm.validate()?;
        crate::ensure_within!(
            OutOfRange,
            (1e-6..0.5).contains(&self.init_alpha),
            "init_alpha must be in (0, 0.5)"
        );
        crate::ensure_within!(
            OutOfRange,
            self.feature_res >= 4 && self.feature_res <= 512,
            "feature res must be 4..512"
        );
        crate::ensure_within!(
            OutOfRange,
            (0.0..0.5).contains(&self.min_transmittance),
            "min_transmittance must be in [0, 0.5)"
        );
        let finite = [
            self.lr_density,
            self.lr_sh,
            self.lr_features,
            self.lr_last_stage,
            self.lr_final,
            self.weight_floor,
            self.prune_alpha,
            self.tv_density,
            self.tv_sh,
            self.tv_features,
            self.tv_last_stage,
            self.distortion,
            self.distortion_coarse,
            self.feature_lambda,
            self.lr_vm_grid,
            self.lr_vm_net,
        ];
        crate::ensure_within!(
            OutOfRange,
            finite.iter().all(|x| x.is_finite() && *x >= 0.0),
            "learning rates, floors and weights must be finite and ≥ 0"
        );
        crate::ensure_within!(
            OutOfRange,
            (0.0..=1.0).contains(&self.mining) && (0.0..=1.0).contains(&self.mining_alpha),
            "mining share and mining_alpha must be in [0, 1], got {} and {}",
            self.mining,
            self.mining_alpha
        );
        crate::ensure_within!(
            OutOfRange,
            self.feature_guide.is_finite() && self.feature_guide >= 0.0,
            "feature guide σ must be finite and ≥ 0 (0: bilinear teacher maps), got {}",
            self.feature_guide
        );
        crate::ensure_within!(
            OutOfRange,
            self.tv_keep > 0.0 && self.tv_keep <= 1.0,
            "tv_keep must be in (0, 1], got {}",
            self.tv_keep
        );
        crate::ensure_within!(
            OutOfRange,
            self.background.iter().all(|c| c.is_finite()),
            "background must be finite"
        );
        Ok(())
    }
    /// The factor on the density and colour TV at iteration `iter`:
    /// `tv_last_stage` from the last stage's first iteration on, else 1.
    pub fn tv_scale(&self, iter: usize) -> f32 {
        self.by_stage(iter, 1.0, self.tv_last_stage)
    }
    /// The factor on the density and colour learning rates at iteration
    /// `iter`: `lr_last_stage` from the last stage's first iteration on.
    pub fn lr_scale(&self, iter: usize) -> f32 {
        self.by_stage(iter, 1.0, self.lr_last_stage)
    }
    /// The distortion weight at iteration `iter`.
    pub fn distortion_at(&self, iter: usize) -> f32 {
        self.distortion * self.by_stage(iter, self.distortion_coarse, 1.0)
    }
    /// `coarse` before the last stage's first iteration, `last` from it on.
    fn by_stage(&self, iter: usize, coarse: f32, last: f32) -> f32 {
        let last_stage = self.schedule().last().map_or(0, |s| s.0);
        if iter >= last_stage {
            last
        } else {
            coarse
        }
    }
    pub fn total_iters(&self) -> usize {
        self.iters + self.feature_iters
    }
    /// (first iteration, longest-side resolution) of every stage.
    pub fn schedule(&self) -> Vec<(usize, usize)> {
        let s = self.stages;
        (0..s)
            .map(|k| {
                if s == 1 {
                    return (0, self.res);
                }
                let f = k as f32 / (s - 1) as f32;
                let res = (self.coarse_res as f32 * (self.res as f32 / self.coarse_res as f32).powf(f)).round();
                let start = (self.iters as f32 * self.last_stage_at * f).round() as usize;
                (start, res as usize)
            })
            .collect()
    }
}

/// Figures of one iteration.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
pub struct StepStats {
    pub iter: usize,
    /// Mean squared colour error of the batch.
    pub loss: f32,
    pub psnr: f32,
    /// Mean squared feature error (distillation phase), else 0.
    pub feature_loss: f32,
    pub rays: usize,
    pub samples: u64,
    pub seconds: f32,
    /// Of `seconds`, the optimizer's share (TV and Adam over the touched
    /// voxels); the rest is marching rays forward and backward. Not kept in
    /// checkpoints (0 after a resume).
    #[serde(default)]
    pub update_seconds: f32,
}

/// Optimizer state.
#[derive(Clone, Debug, Default)]
pub struct OptState {
    pub density: Moments,
    pub sh: Moments,
    pub features: Moments,
    pub vm_grid: Moments,
    pub vm_net: Moments,
    /// Adam steps since the moments were last reset (bias correction).
    pub t: u64,
}

pub struct Trainer {
    pub config: TrainConfig,
    pub model: Model,
    pub opt: OptState,
    /// Completed iterations.
    pub iter: usize,
    pub history: Vec<StepStats>,
    pub rays: RaySet,
    /// Teacher features of the training views (distillation); set with
    /// [`Trainer::set_teacher`], which also decides which rays batches
    /// draw.
    teacher: Option<FeatureMaps>,
    /// What the schedule did (stage changes, pruning), for people to read.
    pub notes: Vec<String>,
    /// The step's gradients, and each rayon task's records of them.
    grads: GradBuf,
    logs: Vec<GradLog>,
    useful: super::rays::RaySubset,
    /// Running errors for mined batches (`config.mining` > 0), over `useful`.
    miner: Option<RayMiner>,
}

impl Trainer {
    /// A trainer over `rays` starting from an empty model on `bounds`.
    pub fn new(config: TrainConfig, rays: RaySet, bounds: Aabb) -> Result<Trainer> {
        config.validate()?;
        ensure!(!rays.is_empty(), "no training rays");
        ensure!(bounds.is_valid(), "training box {bounds:?} is not a valid box");
        let res0 = config.schedule()[0].1;
        let geom = GridGeom::new(bounds, res_for(bounds, res0, config.axis_scale));
        let step = step_of(&geom);
        let init_sigma = -(1.0 - config.init_alpha).ln() / step;
        let model = Model::new(geom, 0, 0.0, init_sigma)?;
        Ok(Self::from_parts(config, model, OptState::default(), 0, vec![], rays))
    }

    /// Reassembles a trainer (checkpoint resume).
    pub fn from_parts(
        config: TrainConfig,
        model: Model,
        opt: OptState,
        iter: usize,
        history: Vec<StepStats>,
        rays: RaySet,
    ) -> Trainer {
        let mut t = Trainer {
            config,
            model,
            opt,
            iter,
            history,
            rays,
            teacher: None,
            notes: vec![],
            grads: GradBuf::default(),
            logs: vec![],
            useful: Default::default(),
            miner: None,
        };
        // Keeps the checkpoint's moments where they fit the model.
        t.reset_buffers(true);
        t
    }

    /// Reallocates gradient buffers (and moments unless `keep_moments`) for
    /// the current model; recomputes which rays meet the box.
    fn reset_buffers(&mut self, keep_moments: bool) {
        let nt = rayon::current_num_threads().max(1);
        // Free the old buffers before allocating new ones (peak memory).
        self.free_grads();
        // A frozen field needs neither gradients nor moments for density
        // and SH colour (on lego's 320 grid, 730 MB each).
        let radiance = !self.radiance_frozen();
        self.grads = GradBuf::new(&self.model, radiance);
        self.logs = (0..nt).map(|_| GradLog::new(&self.model)).collect();
        let (vg, vn) = self.model.vm.as_ref().map_or((0, 0), |v| (v.grid.len(), v.net.len()));
        let slots = if radiance { self.model.slots.len() } else { 0 };
        let fits = self.opt.density.m.len() == slots
            && self.opt.sh.m.len() == slots * self.model.sh_stride()
            && self.opt.features.m.len() == self.model.features.as_ref().map_or(0, |f| f.data.len())
            && (self.opt.vm_grid.m.len(), self.opt.vm_net.m.len()) == (vg, vn);
        if !keep_moments || !fits {
            self.opt = OptState::default();
            self.opt = OptState {
                density: Moments::new(slots),
                sh: Moments::new(slots * self.model.sh_stride()),
                features: Moments::new(self.model.features.as_ref().map_or(0, |f| f.data.len())),
                vm_grid: Moments::new(vg),
                vm_net: Moments::new(vn),
                t: 0,
            };
        }
        self.refresh_useful();
    }

    /// Recomputes the rays batches are drawn from ([`Trainer::useful_rays`]).
    fn refresh_useful(&mut self) {
        let useful = self.useful_rays();
        // The miner's cells are positions in `useful`: they keep their
        // errors while the rays stay the same (most stage changes).
        if useful != self.useful || self.miner.is_none() {
            self.miner = (self.config.mining > 0.0)
                .then(|| RayMiner::new(useful.len(), self.config.mining, self.config.mining_alpha));
        }
        self.useful = useful;
    }

    /// Distils from `maps` from now on.
    pub fn set_teacher(&mut self, maps: FeatureMaps) {
        self.teacher = Some(maps);
        self.refresh_useful();
    }

    /// The teacher's maps distilled from, if any.
    pub fn teacher(&self) -> Option<&FeatureMaps> {
        self.teacher.as_ref()
    }

    /// Takes the teacher's maps out (batches then draw from every view).
    pub fn take_teacher(&mut self) -> Option<FeatureMaps> {
        let maps = self.teacher.take();
        self.refresh_useful();
        maps
    }

    /// The rays batches are drawn from: those that meet the box; when only
    /// features are trained (a frozen field), only those of views the
    /// teacher saw.
    fn useful_rays(&self) -> super::rays::RaySubset {
        let bounds = &self.model.geom.bounds;
        match self
            .teacher
            .as_ref()
            .filter(|t| !t.views.is_empty() && self.radiance_frozen())
        {
            Some(t) => self.rays.hitting_views(bounds, |v| t.map_of(v).is_some()),
            None => self.rays.hitting(bounds),
        }
    }

    /// Drops the distilled features and rewinds to the start of the feature
    /// phase, with density and colour frozen: distils again (another
    /// teacher, feature grid size or iteration count) without retraining the
    /// radiance field.
    pub fn restart_features(&mut self, feature_res: Option<usize>) -> Result<()> {
        if let Some(r) = feature_res {
            self.config.feature_res = r;
        }
        self.config.freeze_geometry = true;
        self.config.validate()?;
        ensure!(
            self.iter >= self.config.iters,
            "the checkpoint is at iteration {} of {}: finish the radiance phase before distilling again",
            self.iter,
            self.config.iters
        );
        self.model.features = None;
        self.iter = self.config.iters;
        self.history.retain(|s| s.iter <= self.config.iters);
        self.reset_buffers(true);
        Ok(())
    }

    pub fn is_done(&self) -> bool {
        self.iter >= self.config.total_iters()
    }
    pub fn in_feature_phase(&self) -> bool {
        self.iter >= self.config.iters
    }
    /// Density and colour no longer change (distilling into a frozen field).
    pub fn radiance_frozen(&self) -> bool {
        self.in_feature_phase() && self.config.freeze_geometry
    }
    /// Sample spacing at the current resolution (the renderer's default:
    /// half the smallest voxel side).
    pub fn step_size(&self) -> f32 {
        step_of(&self.model.geom)
    }

    fn march_opts(&self, features: bool) -> MarchOpts {
        let sched = self.config.schedule();
        let first_stage = sched.len() > 1 && self.iter < sched[1].0;
        MarchOpts {
            step: self.step_size(),
            background: Vec3::from(self.config.background),
            weight_floor: if first_stage { 0.0 } else { self.config.weight_floor },
            min_transmittance: self.config.min_transmittance,
            features,
            colour: true,
            geometry: !self.radiance_frozen(),
            // Per ray: the loss is a mean over the batch.
            distortion: if self.radiance_frozen() {
                0.0
            } else {
                self.config.distortion_at(self.iter) / self.config.batch as f32
            },
        }
    }

    /// Stage changes due at the current iteration: pruning, box shrinking,
    /// resampling, SH degree, the feature grid.
    fn apply_schedule(&mut self) -> Result<()> {
        let sched = self.config.schedule();
        for (k, &(start, res)) in sched.iter().enumerate().skip(1) {
            if self.iter != start || start == 0 {
                continue;
            }
            // Gradients and moments start anew at the new resolution
            // (`reset_buffers(false)` below): not held while it is built.
            self.free_grads();
            self.opt = OptState::default();
            let step = self.step_size();
            let kept = self
                .model
                .prune(step, self.config.prune_alpha, self.config.prune_dilate);
            let mut bounds = self.model.geom.bounds;
            if k == 1 && self.config.shrink_bounds {
                if let Some(b) = self.model.occupied_bounds(step, self.config.prune_alpha, 2) {
                    bounds = b;
                }
            }
            let geom = GridGeom::new(bounds, res_for(bounds, res, self.config.axis_scale));
            let mut resampled = self.model.resampled(geom)?;
            // The margin kept above is `prune_dilate` voxels of the coarse
            // grid, twice or more as many fine ones: prune again at the new
            // resolution so that memory and the optimizer's work follow
            // the occupied space (fern at 512: 43 % of the grid active).
            resampled.prune(step_of(&geom), self.config.prune_alpha, self.config.prune_dilate);
            self.model = match self.config.appearance {
                AppearanceKind::Sh => resampled.with_degree(self.config.sh_degree),
                AppearanceKind::Vm => resampled,
            };
            // With VM, the first stage learns geometry with cheap SH-0
            // colour; the VM takes over from the second (and is resampled
            // along with the grid after that).
            if self.config.appearance == AppearanceKind::Vm && self.model.vm.is_none() {
                self.model.vm = Some(VmAppearance::new(self.config.vm, geom.res, self.config.seed)?);
            }
            self.reset_buffers(false);
            self.notes.push(format!(
                "iteration {}: stage {k}: pruned to {kept} voxels, box {:.3?}..{:.3?}, grid {:?}, {} active, {} of {} rays meet the box",
                self.iter,
                bounds.min.to_array(),
                bounds.max.to_array(),
                geom.res,
                self.model.active_count(),
                self.useful.len(),
                self.rays.len()
            ));
        }
        let pe = self.config.prune_every;
        let first = sched.get(1).map_or(usize::MAX, |s| s.0);
        // Halfway through the first stage (`prune_first_stage`); then every
        // `prune_every` iterations after it.
        let halfway = self.config.prune_first_stage && first < usize::MAX && self.iter == first / 2;
        let periodic = pe > 0 && self.iter.is_multiple_of(pe) && self.iter > first;
        if self.iter > 0 && self.iter < self.config.iters && (halfway || periodic) {
            let kept = self.prune_within_stage();
            let what = if halfway { "first stage pruned" } else { "pruned" };
            self.notes.push(format!(
                "iteration {}: {what} to {kept} of {} voxels",
                self.iter,
                self.model.len()
            ));
        }
        if self.iter == self.config.iters && self.config.feature_iters > 0 && self.model.features.is_none() {
            let ch = self
                .teacher
                .as_ref()
                .map(|t| t.channels)
                .ok_or_else(|| crate::Error::invalid("feature distillation needs teacher features"))?;
            let res = res_for(self.model.geom.bounds, self.config.feature_res, self.config.axis_scale);
            self.model.add_features(res, ch)?;
            self.reset_buffers(true);
            self.opt.features = Moments::new(self.model.features.as_ref().map_or(0, |f| f.data.len()));
        }
        Ok(())
    }

    /// Prunes between stage changes: Adam keeps the moments of the voxels
    /// that stay (renumbered to the new slots); gradient buffers shrink.
    fn prune_within_stage(&mut self) -> usize {
        // The gradient buffers are rebuilt for the new slots below: free
        // them first, so that they are not held while the rows move.
        self.free_grads();
        let old = self.model.slots.clone();
        let kept = self
            .model
            .prune(self.step_size(), self.config.prune_alpha, self.config.prune_dilate);
        let new = &self.model.slots;
        let stride = self.model.sh_stride();
        // The model renumbered its own colour rows; the moments follow.
        self.opt.density.remap_in_place(&old, new, 1);
        self.opt.sh.remap_in_place(&old, new, stride);
        self.reset_buffers(true);
        kept
    }

    /// Drops the gradient buffers and per-thread logs ([`Self::reset_buffers`]
    /// makes new ones).
    fn free_grads(&mut self) {
        self.grads = GradBuf::default();
        self.logs.clear();
    }

    /// Learning-rate multiplier at the current iteration (exponential decay
    /// over the radiance phase; the feature phase restarts it for features).
    fn decay(&self, phase_start: usize, phase_len: usize) -> f32 {
        let f = (self.iter.saturating_sub(phase_start)) as f32 / phase_len.max(1) as f32;
        self.config.lr_final.powf(f.min(1.0))
    }

    /// The background of this step's rays: one random colour per step
    /// with [`TrainConfig::random_background`] while density and colour
    /// train on photos with alpha, else the dataset's. (A colour per ray
    /// instead gave lego `--downscale 4` 33.30 dB against 33.59 for one per
    /// step, alpha IoU min 0.979 against 0.976.)
    fn batch_background(&self, geometry: bool) -> Vec3 {
        if !(self.config.random_background && geometry && self.rays.has_alpha()) {
            return Vec3::from(self.config.background);
        }
        let mut rng =
            crate::util::SplitMix64::new(self.config.seed ^ (self.iter as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        Vec3::new(rng.unit() as f32, rng.unit() as f32, rng.unit() as f32)
    }

    /// One iteration.
    pub fn step(&mut self) -> Result<StepStats> {
        ensure!(!self.is_done(), "training is already complete");
        let t0 = Instant::now();
        self.apply_schedule()?;
        let features = self.in_feature_phase() && self.model.features.is_some();
        let opts = self.march_opts(features);
        // Distilling into a frozen field, colour is not shaded (see
        // `MarchOpts::colour`) and the loss shown is the last radiance
        // step's; only a field with no radiance step behind it shades it.
        let carried = if opts.geometry {
            None
        } else {
            self.history.last().map(|s| s.loss)
        };
        let composited_on = opts.background;
        let opts = MarchOpts {
            colour: carried.is_none(),
            background: self.batch_background(opts.geometry),
            ..opts
        };
        let (batch, mined) = self.sample_batch();
        let nb = batch.len().max(1) as f32;
        let nt = self.logs.len();
        let chunk = batch.len().div_ceil(nt).max(1);
        let (model, rays, teacher) = (&self.model, &self.rays, self.teacher.as_ref());
        let (lambda, guide) = (self.config.feature_lambda, self.config.feature_guide);
        let weights = mined.as_ref().map(|m| &m.weights[..]);
        let results: Vec<(f64, f64, u64, Vec<f32>)> = self
            .logs
            .par_iter_mut()
            .zip(batch.par_chunks(chunk).enumerate())
            .map(|(log, (ci, idx))| {
                let mut s = Scratch::default();
                let fc = if features { teacher.map_or(0, |t| t.channels) } else { 0 };
                let mut target = vec![0.0f32; fc];
                let mut h = vec![0.0f32; fc];
                let (mut se, mut fe, mut ns) = (0.0f64, 0.0f64, 0u64);
                // Per-ray errors, for the miner.
                let mut errors = Vec::with_capacity(if weights.is_some() { idx.len() } else { 0 });
                for (j, &ri) in idx.iter().enumerate() {
                    let ri = ri as usize;
                    let ray = rays.ray(ri);
                    let opts = MarchOpts {
                        step: ray_step(&model.geom, ray.dir),
                        ..opts
                    };
                    let out = forward(model, &ray, &opts, &mut s);
                    ns += out.samples as u64;
                    // The photo's colour guides the teacher's upsampling;
                    // the target is that colour over this step's background.
                    let photo = rays.color(ri);
                    let d = out.color - rays.color_over(ri, opts.background, composited_on);
                    se += d.length_squared() as f64;
                    let mut g = d * (2.0 / (3.0 * nb));
                    if let Some(w) = weights {
                        g *= w[ci * chunk + j];
                        errors.push(d.length_squared() / 3.0);
                    }
                    // Views the teacher did not see distil nothing (their
                    // rays are left out of frozen-field batches).
                    let map = teacher
                        .filter(|_| fc > 0)
                        .and_then(|t| Some((t, t.map_of(rays.view(ri))?)));
                    h.fill(0.0);
                    if let Some((t, m)) = map {
                        t.sample_guided(m, rays.pixel(ri), photo.to_array(), guide, &mut target);
                        for c in 0..fc {
                            let e = s.features[c] - target[c];
                            fe += (e * e) as f64;
                            h[c] = lambda * 2.0 * e / (fc as f32 * nb);
                        }
                    }
                    backward(model, &ray, &opts, &mut s, g, &h, log);
                }
                (se, fe, ns, errors)
            })
            .collect();
        gather(&self.model, &mut self.logs, &mut self.grads);
        let t_update = Instant::now();
        self.optimize(features)?;
        let update_seconds = t_update.elapsed().as_secs_f32();
        self.iter += 1;
        let se: f64 = results.iter().map(|r| r.0).sum();
        let fe: f64 = results.iter().map(|r| r.1).sum();
        let mut loss = carried.unwrap_or((se / (3.0 * nb as f64)) as f32);
        if let (Some(m), Some(miner)) = (&mined, self.miner.as_mut()) {
            let errors: Vec<f32> = results.iter().flat_map(|r| r.3.iter().copied()).collect();
            miner.record(&m.positions, &errors);
            // The batch over-samples hard rays: show the uniform loss.
            loss = uniform_estimate(&errors, &m.ratios) as f32;
        }
        let fc = self.model.features.as_ref().map_or(1, |f| f.channels) as f64;
        let stats = StepStats {
            iter: self.iter,
            loss,
            psnr: psnr_of(loss),
            feature_loss: (fe / (fc * nb as f64)) as f32,
            rays: batch.len(),
            samples: results.iter().map(|r| r.2).sum(),
            seconds: t0.elapsed().as_secs_f32(),
            update_seconds,
        };
        self.history.push(stats);
        Ok(stats)
    }

    /// Random ray indices (deterministic per seed and iteration), sorted so
    /// that neighbouring rays of a view run one after another (cache); with
    /// mining (radiance phase only), the mined batch they come from.
    fn sample_batch(&self) -> (Vec<u32>, Option<MinedBatch>) {
        let n = self.useful.len();
        if n == 0 {
            return (vec![], None);
        }
        // One generator per iteration (resumable), seeded through a mixing
        // step: consecutive raw seeds would give overlapping sequences.
        let mixed = SplitMix64::new(self.config.seed.wrapping_mul(0x1000_0000_01B3) ^ self.iter as u64).next_u64();
        let mut rng = SplitMix64::new(mixed);
        // `reset_buffers` remakes the miner whenever `useful` changes.
        if let Some(miner) = self.miner.as_ref().filter(|_| !self.in_feature_phase()) {
            let m = miner.sample(&mut rng, self.config.batch);
            // Ascending positions give ascending ray indices.
            let b = m.positions.iter().map(|&k| self.useful.get(k)).collect();
            return (b, Some(m));
        }
        let mut b: Vec<u32> = (0..self.config.batch).map(|_| self.useful.get(rng.below(n))).collect();
        b.sort_unstable();
        (b, None)
    }

    /// TV regularisers and the sparse Adam step on everything touched.
    fn optimize(&mut self, features: bool) -> Result<()> {
        self.opt.t += 1;
        let hp = AdamParams::default();
        let in_feat = self.iter >= self.config.iters;
        let decay = if in_feat {
            self.config.lr_final
        } else {
            self.decay(0, self.config.iters)
        } * self.config.lr_scale(self.iter);
        // Frozen geometry (distilling into a finished field): the backward
        // pass recorded no density or colour gradients, nothing to step.
        if !self.radiance_frozen() {
            self.step_geometry(decay, hp);
        }
        if features {
            self.step_features(hp);
        }
        Ok(())
    }

    /// TV and the Adam step of the feature grid.
    fn step_features(&mut self, hp: AdamParams) {
        let cfg = &self.config;
        let ftouched = merge_marks(&mut [&mut self.grads.feat_marks]);
        let fdecay = self.decay(cfg.iters, cfg.feature_iters);
        let f = self.model.features.as_mut().expect("feature phase has a feature grid");
        add_tv(
            &f.data,
            &mut self.grads.feat,
            f.channels,
            f.geom.res,
            &ftouched,
            Layout::Points,
            Tv::full(cfg.tv_features),
        );
        let lr_f = corrected_lr(cfg.lr_features * fdecay, self.opt.t, hp);
        adam_step(
            &mut f.data,
            &mut self.opt.features,
            &mut [&mut self.grads.feat],
            f.channels,
            &ftouched,
            None,
            lr_f,
            hp,
            (-1e4, 1e4),
        );
    }

    /// TV and the Adam step of density and colour (SH or VM).
    fn step_geometry(&mut self, decay: f32, hp: AdamParams) {
        let cfg = &self.config;
        let voxel = self.model.geom.spacing().min_element();
        let touched = merge_marks(&mut [&mut self.grads.marks]);
        let sh_touched = merge_marks(&mut [&mut self.grads.sh_marks]);
        let res = self.model.geom.res;
        let tv_scale = cfg.tv_scale(self.iter);
        let tv_sample = Tv {
            weight: 0.0,
            keep: cfg.tv_keep,
            seed: SplitMix64::new(cfg.seed ^ (self.iter as u64).wrapping_mul(0x9E37_79B9)).next_u64(),
        };
        {
            // TV on voxel-scaled density: the weight means the same at every
            // resolution; the gradient w.r.t. raw carries voxel².
            add_tv(
                &self.model.density,
                &mut self.grads.density,
                1,
                res,
                &touched,
                Layout::SlotGrads(&self.model.slots),
                Tv {
                    weight: cfg.tv_density * voxel * voxel * tv_scale,
                    ..tv_sample
                },
            );
            add_tv(
                &self.model.sh,
                &mut self.grads.sh,
                self.model.sh_stride(),
                res,
                &sh_touched,
                Layout::Slots(&self.model.slots),
                Tv {
                    weight: cfg.tv_sh * tv_scale,
                    ..tv_sample
                },
            );
        }
        let t = self.opt.t;
        let lr_d = corrected_lr(cfg.lr_density / voxel * decay, t, hp);
        let lr_s = corrected_lr(cfg.lr_sh * decay, t, hp);
        {
            adam_step(
                &mut self.model.density,
                &mut self.opt.density,
                &mut [&mut self.grads.density],
                1,
                &touched,
                Some(&self.model.slots),
                lr_d,
                hp,
                (PRUNED_RAW, 1e6),
            );
        }
        {
            let stride = self.model.sh_stride();
            adam_step(
                &mut self.model.sh,
                &mut self.opt.sh,
                &mut [&mut self.grads.sh],
                stride,
                &sh_touched,
                None,
                lr_s,
                hp,
                (-1e3, 1e3),
            );
        }
        if let Some(vm) = self.model.vm.as_mut() {
            let lr_g = corrected_lr(cfg.lr_vm_grid * decay, t, hp);
            let lr_n = corrected_lr(cfg.lr_vm_net * decay, t, hp);
            let g = &mut self.grads;
            dense_adam_step(
                &mut vm.grid,
                &mut self.opt.vm_grid,
                &mut [&mut g.vm_grid],
                lr_g,
                hp,
                (-1e3, 1e3),
            );
            dense_adam_step(
                &mut vm.net,
                &mut self.opt.vm_net,
                &mut [&mut g.vm_net],
                lr_n,
                hp,
                (-1e3, 1e3),
            );
        }
    }

    /// Renders rays with the training forward pass (every sample shaded:
    /// the renderer's function), in parallel; features when the model has
    /// them and `features` is set (`n × channels`).
    pub fn render_rays(&self, rays: &[Ray], features: bool) -> (Vec<RayOut>, Vec<f32>) {
        let mut opts = self.march_opts(features && self.model.features.is_some());
        opts.weight_floor = 0.0;
        let fc = if opts.features {
            self.model.features.as_ref().map_or(0, |f| f.channels)
        } else {
            0
        };
        let parts: Vec<(Vec<RayOut>, Vec<f32>)> = rays
            .par_chunks(256)
            .map(|chunk| {
                let mut s = Scratch::default();
                let mut outs = Vec::with_capacity(chunk.len());
                let mut feats = Vec::with_capacity(chunk.len() * fc);
                for r in chunk {
                    outs.push(forward(&self.model, r, &opts, &mut s));
                    feats.extend_from_slice(&s.features[..fc]);
                }
                (outs, feats)
            })
            .collect();
        let mut outs = Vec::with_capacity(rays.len());
        let mut feats = Vec::with_capacity(rays.len() * fc);
        for (o, f) in parts {
            outs.extend(o);
            feats.extend(f);
        }
        (outs, feats)
    }
}

/// The renderer's default sample spacing for a grid: half the smallest
/// voxel side.
pub fn step_of(geom: &GridGeom) -> f32 {
    0.5 * geom.spacing().min_element()
}

/// Training sample spacing along a unit direction: half a voxel measured in
/// grid units along the ray. On cubic voxels this is [`step_of`]; on the
/// anisotropic NDC grids of forward-facing scenes (depth voxels 2–3× longer)
/// rays run mostly along depth, and the smallest side would sample them 2–3×
/// finer than the grid can resolve, at 2–3× the cost.
pub fn ray_step(geom: &GridGeom, dir: Vec3) -> f32 {
    let cell = crate::render::cell_distance(geom.spacing(), dir);
    if cell.is_finite() && cell > 0.0 {
        0.5 * cell
    } else {
        step_of(geom)
    }
}

pub fn psnr_of(mse: f32) -> f32 {
    if mse <= 0.0 {
        f32::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

/// An 8×6 view of the box ±1 from 3 units away, and its photo (tests and
/// the checkpoint fuzz target's seed).
pub(crate) fn tiny_view(rgb: Vec<f32>, alpha: Option<Vec<f32>>) -> (crate::camera::Camera, crate::data::Image) {
    use crate::camera::{Camera, Intrinsics};
    let cam = Camera::look_at(
        Intrinsics::from_fov_x(8, 6, 0.8),
        Vec3::new(0.0, 0.0, 3.0),
        Vec3::ZERO,
        Vec3::Y,
    );
    let image = crate::data::Image {
        width: 8,
        height: 6,
        rgb,
        alpha,
    };
    (cam, image)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tv_is_scaled_from_the_last_stage_on() {
        let c = TrainConfig {
            iters: 1000,
            stages: 4,
            last_stage_at: 0.5,
            tv_last_stage: 0.0,
            ..Default::default()
        };
        // Stages start at 0, 167, 333 and 500.
        assert_eq!(c.schedule().last().unwrap().0, 500);
        assert_eq!((c.tv_scale(0), c.tv_scale(499)), (1.0, 1.0));
        assert_eq!((c.tv_scale(500), c.tv_scale(999)), (0.0, 0.0));
        // The default keeps one weight throughout; one stage is all last.
        assert_eq!(TrainConfig::default().tv_scale(10_000), 1.0);
        let one = TrainConfig { stages: 1, ..c.clone() };
        assert_eq!(one.tv_scale(0), 0.0);
        // The distortion's factor acts the other way round: before the last stage.
        let d = TrainConfig {
            distortion: 0.01,
            distortion_coarse: 0.0,
            ..c.clone()
        };
        assert_eq!((d.distortion_at(499), d.distortion_at(500)), (0.0, 0.01));
        assert_eq!(
            TrainConfig {
                distortion: 0.01,
                ..Default::default()
            }
            .distortion_at(0),
            0.01
        );
        // Negative or NaN factors are refused.
        for bad in [-1.0, f32::NAN] {
            let c = TrainConfig {
                tv_last_stage: bad,
                ..Default::default()
            };
            assert!(c.validate().is_err(), "{bad}");
            let c = TrainConfig {
                distortion_coarse: bad,
                ..Default::default()
            };
            assert!(c.validate().is_err(), "{bad}");
        }
    }

    /// Photos with alpha train each step over its own random background
    /// (and a step trains on them); without alpha, with the setting off,
    /// or while geometry is frozen, over the dataset's.
    #[test]
    fn steps_draw_their_own_background_only_where_alpha_is_known() {
        let view = |alpha: bool| tiny_view(vec![0.8; 144], alpha.then(|| vec![0.5; 48]));
        let config = TrainConfig {
            iters: 4,
            batch: 16,
            res: 8,
            coarse_res: 4,
            stages: 1,
            ..Default::default()
        };
        let bounds = Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0));
        let trainer = |alpha: bool, config: &TrainConfig| {
            let (cam, image) = view(alpha);
            let rays = RaySet::build(&[(cam, &image)]).unwrap();
            Trainer::new(config.clone(), rays, bounds).unwrap()
        };
        let white = Vec3::ONE;
        let mut t = trainer(true, &config);
        let drawn: Vec<Vec3> = (0..4)
            .map(|i| {
                t.iter = i;
                t.batch_background(true)
            })
            .collect();
        assert!(drawn
            .iter()
            .all(|c| c.min_element() >= 0.0 && c.max_element() <= 1.0 && *c != white));
        assert!(drawn.windows(2).all(|w| w[0] != w[1]), "{drawn:?}");
        assert_eq!(t.batch_background(false), white, "frozen geometry");
        t.iter = 0;
        assert!(t.step().unwrap().loss.is_finite());
        assert_eq!(trainer(false, &config).batch_background(true), white, "no alpha");
        let off = TrainConfig {
            random_background: false,
            ..config
        };
        assert_eq!(trainer(true, &off).batch_background(true), white, "turned off");
    }

    /// `lr_last_stage` scales the density step on the last stage, and only
    /// there: Adam's first step moves each touched value by about its
    /// learning rate, so a factor 2 moves every value exactly twice as far.
    #[test]
    fn a_frozen_field_distils_only_from_the_views_the_teacher_saw() {
        use crate::train::teacher::{FeatureMap, FeatureMaps};
        let views: Vec<_> = (0..3)
            .map(|k| tiny_view((0..144).map(|i| ((i + k) % 5) as f32 / 5.0).collect(), None))
            .collect();
        let pairs: Vec<_> = views.iter().map(|(c, img)| (*c, img)).collect();
        let rays = RaySet::build(&pairs).unwrap();
        let config = TrainConfig {
            iters: 4,
            feature_iters: 4,
            feature_res: 8,
            batch: 64,
            res: 8,
            coarse_res: 8,
            stages: 1,
            freeze_geometry: true,
            random_background: false,
            ..Default::default()
        };
        let bounds = Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0));
        let mut t = Trainer::new(config, rays.clone(), bounds).unwrap();
        // Maps of views 0 and 2 only: a constant feature each.
        let map = |v: f32| FeatureMap {
            width: 2,
            height: 2,
            image_width: 8,
            image_height: 6,
            data: vec![v, -v, v, -v, v, -v, v, -v],
        };
        let maps = FeatureMaps::new(2, vec![map(0.5), map(-0.5)]).unwrap();
        assert!(maps.clone().of_views(vec![2, 0]).is_err(), "views must ascend");
        assert!(maps.clone().of_views(vec![0]).is_err(), "one view per map");
        let maps = maps.of_views(vec![0, 2]).unwrap();
        assert_eq!(
            (maps.map_of(0), maps.map_of(1), maps.map_of(2)),
            (Some(0), None, Some(1))
        );
        t.set_teacher(maps);
        let all = rays.hitting(&t.model.geom.bounds).len();
        assert_eq!(t.useful.len(), all, "radiance trains on every view");
        while !t.in_feature_phase() {
            t.step().unwrap();
        }
        t.step().unwrap();
        let seen: Vec<usize> = (0..t.useful.len())
            .map(|k| rays.view(t.useful.get(k) as usize))
            .collect();
        assert!(seen.iter().all(|&v| v != 1), "view 1 has no map");
        assert!(seen.contains(&0) && seen.contains(&2));
        assert_eq!(seen.len(), all * 2 / 3, "every ray of the two views that meets the box");
        assert!(t.history.last().unwrap().feature_loss > 0.0);
    }

    #[test]
    fn the_last_stage_takes_its_own_learning_rate() {
        let (cam, image) = tiny_view((0..144).map(|i| (i % 7) as f32 / 7.0).collect(), None);
        let bounds = Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0));
        // The change of every density value after the first step.
        let first_step = |stages: usize, lr_last_stage: f32| {
            let config = TrainConfig {
                iters: 8,
                batch: 32,
                res: 8,
                coarse_res: 8,
                stages,
                lr_last_stage,
                random_background: false,
                ..Default::default()
            };
            let rays = RaySet::build(&[(cam, &image)]).unwrap();
            let mut t = Trainer::new(config, rays, bounds).unwrap();
            let before = t.model.density.clone();
            t.step().unwrap();
            before
                .iter()
                .zip(&t.model.density)
                .map(|(a, b)| b - a)
                .collect::<Vec<f32>>()
        };
        let close = |a: &[f32], b: &[f32], k: f32| {
            a.iter()
                .zip(b)
                .all(|(x, y)| (k * x - y).abs() <= 1e-4 * x.abs().max(1e-3))
        };
        // One stage: it is the last, from the first step on.
        let (one, two) = (first_step(1, 1.0), first_step(1, 2.0));
        assert!(one.iter().any(|d| d.abs() > 1e-4), "the step moved nothing");
        assert!(close(&one, &two, 2.0));
        // Two stages (the last from iteration 4): the first keeps the base rate.
        assert!(close(&first_step(2, 1.0), &first_step(2, 2.0), 1.0));
        let c = TrainConfig {
            lr_last_stage: 3.0,
            iters: 8,
            stages: 2,
            ..Default::default()
        };
        assert_eq!((c.lr_scale(3), c.lr_scale(4)), (1.0, 3.0));
        for bad in [-1.0, f32::NAN] {
            assert!(TrainConfig {
                lr_last_stage: bad,
                ..Default::default()
            }
            .validate()
            .is_err());
        }
    }

    #[test]
    fn ray_step_is_half_a_voxel_in_grid_units() {
        let cube = GridGeom::new(Aabb::new(Vec3::ZERO, Vec3::ONE), [65, 65, 65]);
        for d in [Vec3::X, Vec3::new(1.0, 2.0, -3.0).normalize(), Vec3::NEG_Z] {
            assert!((ray_step(&cube, d) - step_of(&cube)).abs() < 1e-7);
        }
        // Depth voxels 4× longer: a ray along depth takes 4× longer steps,
        // one along x keeps the fine step.
        let flat = GridGeom::new(Aabb::new(Vec3::ZERO, Vec3::ONE), [65, 65, 17]);
        let s = flat.spacing();
        assert!((ray_step(&flat, Vec3::Z) - 0.5 * s.z).abs() < 1e-7);
        assert!((ray_step(&flat, Vec3::X) - 0.5 * s.x).abs() < 1e-7);
        let diag = Vec3::new(0.0, 1.0, 1.0).normalize();
        let expect = 0.5 / ((diag.y / s.y).powi(2) + (diag.z / s.z).powi(2)).sqrt();
        assert!((ray_step(&flat, diag) - expect).abs() < 1e-7);
    }
}
