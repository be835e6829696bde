//! The trainable field: flat f32 parameter arrays over one grid geometry
//! (the same conventions as [`crate::field`]: corner-aligned grid points,
//! x fastest), plus the occupancy masks that decide which voxels train.
//!
//! - `density`: raw values; σ = softplus(raw + shift) in the field's own
//!   length units (the renderer's [`Activation::Softplus`]).
//! - `sh`: per active voxel (in slot order, [`Slots`]) `3·K` spherical-
//!   harmonic coefficients, K = (degree+1)², laid out `[r0..rK, g0..gK,
//!   b0..bK]`; colour = sigmoid(Σ cₖ Yₖ(dir)) exactly as
//!   [`crate::field::sh::color`] evaluates degree 2. Pruned voxels have no
//!   colour (their coefficients count as 0), so colour memory follows the
//!   occupied space: at 512×455×89 on fern a dense SH grid would take 2.2 GB.
//! - `features`: optional dense semantic feature grid with its own (usually
//!   coarser) resolution over the same bounds.
//!
//! Pruned voxels hold [`PRUNED_RAW`] and never train; a sample whose eight
//! corners are all pruned is skipped, which is exact up to σ ≈ 1e-13.

use super::vm::VmAppearance;
use crate::error::Result;
use crate::field::geom::check_res;
use crate::field::sh::SH_COEFFS;
use crate::field::{
    sparse, Aabb, Activation, Appearance, Bitmap, ChannelGrid, DensityGrid, Features, Field, GridGeom, RankIndex,
};
use glam::Vec3;
use half::f16;
use rayon::prelude::*;
use std::sync::Arc;

/// Raw density of pruned voxels: softplus(−30) ≈ 1e-13, empty for any
/// renderer threshold.
pub const PRUNED_RAW: f32 = -30.0;
/// Cells per side of a skip block (empty-space skipping while marching).
pub const BLOCK: usize = 8;

/// Number of SH coefficients per colour channel for a degree.
pub fn sh_coeffs(degree: usize) -> usize {
    (degree + 1) * (degree + 1)
}

/// A dense f32 channel grid (features during training).
#[derive(Clone, Debug)]
pub struct DenseGrid {
    pub geom: GridGeom,
    pub channels: usize,
    pub data: Vec<f32>,
}

#[derive(Clone, Debug)]
pub struct Model {
    pub geom: GridGeom,
    /// Softplus shift of the density activation.
    pub shift: f32,
    pub degree: usize,
    pub density: Vec<f32>,
    pub sh: Vec<f32>,
    pub features: Option<DenseGrid>,
    /// VM + MLP appearance; when present it replaces the SH colour.
    pub vm: Option<VmAppearance>,
    /// Trainable voxels (not pruned), one bit per grid point.
    pub active: Vec<u64>,
    /// Compact numbering of the active voxels: gradients and Adam moments
    /// of density and SH are stored per slot, not per grid point (after
    /// pruning a few per cent of the grid trains).
    pub slots: Slots,
    /// Per cell, indexed by its lowest corner: 1 when any corner is active.
    pub cells: Vec<u8>,
    /// Per block of `BLOCK³` cells: true when any cell in it is active.
    pub blocks: Vec<bool>,
    pub block_dims: [usize; 3],
}

/// Slot `s` of the active voxels ↔ voxel `voxels[s]`, ascending; the rank
/// index gives a voxel's slot in O(1).
#[derive(Clone, Debug)]
pub struct Slots {
    pub index: RankIndex,
    pub voxels: Vec<u32>,
}

impl Slots {
    /// Slots of the set bits of `active` over grid `res` (grids are checked
    /// by [`check_res`], far below 2³² points).
    pub fn new(res: [usize; 3], active: &[u64]) -> Slots {
        let bits = Bitmap::from_fn(res, |i| bit(active, i));
        let voxels = bits.ones().map(|v| v as u32).collect();
        Slots {
            index: RankIndex::new(bits),
            voxels,
        }
    }
    /// Number of slots (active voxels).
    pub fn len(&self) -> usize {
        self.voxels.len()
    }
    pub fn is_empty(&self) -> bool {
        self.voxels.is_empty()
    }
    #[inline]
    pub fn slot(&self, voxel: usize) -> Option<usize> {
        self.index.slot(voxel)
    }
}

/// Bit helpers over `u64` words.
#[inline]
pub fn bit(words: &[u64], i: usize) -> bool {
    words[i >> 6] >> (i & 63) & 1 == 1
}
#[inline]
pub fn set_bit(words: &mut [u64], i: usize) {
    words[i >> 6] |= 1 << (i & 63);
}

impl Model {
    /// A fresh model: every voxel active, density at `init_sigma`, grey colour.
    pub fn new(geom: GridGeom, degree: usize, shift: f32, init_sigma: f32) -> Result<Model> {
        check_res(geom.res, "training grid")?;
        crate::ensure_within!(OutOfRange, degree <= 2, "SH degree must be 0, 1 or 2, got {degree}");
        crate::ensure!(
            init_sigma > 0.0 && init_sigma.is_finite(),
            "initial density must be positive"
        );
        let n = geom.len();
        let raw0 = inverse_softplus(init_sigma) - shift;
        let mut m = Model {
            geom,
            shift,
            degree,
            density: vec![raw0; n],
            sh: vec![],
            features: None,
            vm: None,
            active: vec![u64::MAX; n.div_ceil(64)],
            slots: Slots::new([0; 3], &[]),
            cells: vec![],
            blocks: vec![],
            block_dims: [1; 3],
        };
        m.clear_tail();
        m.rebuild_masks();
        m.sh = vec![0.0; m.slots.len() * m.sh_stride()];
        Ok(m)
    }

    /// Reassembles a model from its arrays (checkpoints); checks sizes. `sh`
    /// holds a row per active voxel, or (older checkpoints) per grid point.
    pub fn from_parts(
        geom: GridGeom,
        shift: f32,
        degree: usize,
        density: Vec<f32>,
        sh: Vec<f32>,
        active: Vec<u64>,
        features: Option<DenseGrid>,
    ) -> Result<Model> {
        check_res(geom.res, "training grid")?;
        let n = geom.len();
        crate::ensure_within!(OutOfRange, degree <= 2, "SH degree must be 0, 1 or 2, got {degree}");
        crate::ensure!(
            density.len() == n && active.len() == n.div_ceil(64),
            "model arrays do not match the grid {:?}",
            geom.res
        );
        if let Some(f) = &features {
            crate::ensure!(
                f.data.len() == f.geom.len() * f.channels,
                "feature grid size does not match its resolution"
            );
        }
        let mut m = Model {
            geom,
            shift,
            degree,
            density,
            sh: vec![],
            features,
            vm: None,
            active,
            slots: Slots::new([0; 3], &[]),
            cells: vec![],
            blocks: vec![],
            block_dims: [1; 3],
        };
        m.clear_tail();
        m.rebuild_masks();
        let stride = m.sh_stride();
        m.sh = if sh.len() == m.slots.len() * stride {
            sh
        } else if sh.len() == n * stride {
            let all = Slots::new(geom.res, &vec![u64::MAX; n.div_ceil(64)]);
            remap_rows(&sh, &all, &m.slots, stride)
        } else {
            return Err(crate::Error::invalid(format!(
                "SH array of {} values matches neither the {} active voxels nor the grid {:?}",
                sh.len(),
                m.slots.len(),
                geom.res
            )));
        };
        Ok(m)
    }

    pub fn len(&self) -> usize {
        self.geom.len()
    }
    pub fn is_empty(&self) -> bool {
        self.geom.is_empty()
    }
    /// SH values per voxel (3·K).
    pub fn sh_stride(&self) -> usize {
        3 * sh_coeffs(self.degree)
    }
    pub fn activation(&self) -> Activation {
        Activation::Softplus { shift: self.shift }
    }
    pub fn sigma_at(&self, i: usize) -> f32 {
        self.activation().apply(self.density[i])
    }
    /// SH coefficients of grid point `voxel`, `None` when it is pruned.
    #[inline]
    pub fn sh_of(&self, voxel: usize) -> Option<&[f32]> {
        let k = self.sh_stride();
        self.slots.slot(voxel).map(|s| &self.sh[s * k..(s + 1) * k])
    }
    pub fn active_count(&self) -> usize {
        self.active.iter().map(|w| w.count_ones() as usize).sum()
    }

    fn clear_tail(&mut self) {
        let n = self.len();
        if !n.is_multiple_of(64) {
            let last = self.active.len() - 1;
            self.active[last] &= (1u64 << (n % 64)) - 1;
        }
    }

    /// Applies a change of `active`: masks and slots recomputed, the colour
    /// rows renumbered (rows of newly active voxels are 0).
    pub fn refresh_masks(&mut self) {
        let old = std::mem::replace(&mut self.slots, Slots::new([0; 3], &[]));
        self.rebuild_masks();
        let stride = self.sh_stride();
        remap_rows_in_place(&mut self.sh, &old, &self.slots, stride);
    }

    /// Recomputes the cell and block masks and the slots from `active`;
    /// pruned voxels get [`PRUNED_RAW`] so that what is skipped is really
    /// empty. Per-slot arrays are the caller's.
    fn rebuild_masks(&mut self) {
        let g = self.geom;
        let [nx, ny, nz] = g.res;
        let active = &self.active;
        self.density.par_iter_mut().enumerate().for_each(|(i, d)| {
            if !bit(active, i) {
                *d = PRUNED_RAW;
            }
        });
        let mut cells = vec![0u8; g.len()];
        cells.par_chunks_mut(nx).enumerate().for_each(|(row, out)| {
            let (y, z) = (row % ny, row / ny);
            if y + 1 >= ny || z + 1 >= nz {
                return;
            }
            for (x, c) in out.iter_mut().enumerate().take(nx - 1) {
                let base = g.index(x, y, z);
                let any = (0..8).any(|k| {
                    let (dx, dy, dz) = (k & 1, (k >> 1) & 1, (k >> 2) & 1);
                    bit(active, base + dx + nx * (dy + ny * dz))
                });
                *c = any as u8;
            }
        });
        let bd = [0, 1, 2].map(|a| (g.res[a] - 1).div_ceil(BLOCK).max(1));
        let blocks = (0..bd[0] * bd[1] * bd[2])
            .into_par_iter()
            .map(|b| {
                let (bx, by, bz) = (b % bd[0], (b / bd[0]) % bd[1], b / (bd[0] * bd[1]));
                let r = |c: usize, a: usize| c * BLOCK..((c + 1) * BLOCK).min(g.res[a] - 1);
                r(bz, 2).any(|z| r(by, 1).any(|y| r(bx, 0).any(|x| cells[g.index(x, y, z)] != 0)))
            })
            .collect();
        self.cells = cells;
        self.blocks = blocks;
        self.block_dims = bd;
        self.slots = Slots::new(g.res, &self.active);
    }

    /// Prunes voxels: keeps those with σ·`step` ≥ `alpha_floor`·… (per-sample
    /// opacity above the floor) and their neighbours within `dilate` voxels.
    /// Already pruned voxels stay pruned. Returns the active count.
    pub fn prune(&mut self, step: f32, alpha_floor: f32, dilate: usize) -> usize {
        let g = self.geom;
        let act = self.activation();
        let keep: Vec<u64> = {
            let d = &self.density;
            let active = &self.active;
            let n = g.len();
            (0..n.div_ceil(64))
                .into_par_iter()
                .map(|w| {
                    let mut bits = 0u64;
                    for b in 0..64 {
                        let i = w * 64 + b;
                        if i < n && bit(active, i) && 1.0 - (-act.apply(d[i]) * step).exp() >= alpha_floor {
                            bits |= 1 << b;
                        }
                    }
                    bits
                })
                .collect()
        };
        let grown = dilate_bits(&keep, g.res, dilate);
        for (a, k) in self.active.iter_mut().zip(&grown) {
            *a &= *k;
        }
        self.refresh_masks();
        self.active_count()
    }

    /// The model resampled on `geom` (trilinear in raw values, like the
    /// renderer). Points outside the old box get an empty, grey voxel.
    /// Activity: a new voxel is active when the old grid is active there.
    pub fn resampled(&self, geom: GridGeom) -> Result<Model> {
        check_res(geom.res, "training grid")?;
        let n = geom.len();
        let mut density = vec![PRUNED_RAW; n];
        let mut active = vec![0u64; n.div_ceil(64)];
        density.par_iter_mut().enumerate().for_each(|(i, d)| {
            if let Some(c) = self.geom.corners(geom.point_of(i)) {
                *d = (0..8).map(|j| c.weight[j] * self.density[c.index[j]]).sum();
            }
        });
        // Active where any corner of the old cell holding the point is active.
        active.par_iter_mut().enumerate().for_each(|(w, bits)| {
            for b in 0..64 {
                let i = w * 64 + b;
                if i >= n {
                    break;
                }
                if let Some(c) = self.geom.corners(geom.point_of(i)) {
                    if (0..8).any(|j| c.weight[j] > 0.0 && bit(&self.active, c.index[j])) {
                        *bits |= 1 << b;
                    }
                }
            }
        });
        // Colour of the new active points: the old active corners' SH,
        // weights renormalised over them (pruned corners have no colour).
        let k = self.sh_stride();
        let slots = Slots::new(geom.res, &active);
        let mut sh = vec![0.0f32; slots.len() * k];
        sh.par_chunks_mut(k).zip(&slots.voxels).for_each(|(s, &v)| {
            let Some(c) = self.geom.corners(geom.point_of(v as usize)) else {
                return;
            };
            let mut total = 0.0;
            for j in 0..8 {
                if let (true, Some(src)) = (c.weight[j] > 0.0, self.sh_of(c.index[j])) {
                    total += c.weight[j];
                    for (o, x) in s.iter_mut().zip(src) {
                        *o += c.weight[j] * x;
                    }
                }
            }
            if total > 0.0 {
                s.iter_mut().for_each(|o| *o /= total);
            }
        });
        let features = self.features.clone();
        let mut m = Model::from_parts(geom, self.shift, self.degree, density, sh, active, features)?;
        m.vm = self.vm.as_ref().map(|v| v.resampled(&self.geom, &geom));
        Ok(m)
    }

    /// The same model with SH degree raised to `degree` (new coefficients 0).
    pub fn with_degree(mut self, degree: usize) -> Model {
        if degree <= self.degree {
            return self;
        }
        let (ko, kn) = (sh_coeffs(self.degree), sh_coeffs(degree));
        let mut sh = vec![0.0f32; self.slots.len() * 3 * kn];
        sh.par_chunks_mut(3 * kn)
            .zip(self.sh.par_chunks(3 * ko))
            .for_each(|(d, s)| {
                for c in 0..3 {
                    d[c * kn..c * kn + ko].copy_from_slice(&s[c * ko..(c + 1) * ko]);
                }
            });
        self.sh = sh;
        self.degree = degree;
        self
    }

    /// A feature grid of `channels` zeros at `res` over the model's bounds.
    pub fn add_features(&mut self, res: [usize; 3], channels: usize) -> Result<()> {
        check_res(res, "feature grid")?;
        crate::ensure!((1..=4096).contains(&channels), "bad feature channel count {channels}");
        let geom = GridGeom::new(self.geom.bounds, res);
        self.features = Some(DenseGrid {
            geom,
            channels,
            data: vec![0.0; geom.len() * channels],
        });
        Ok(())
    }

    /// The field the renderer reads: raw density, SH padded to degree 2 (or
    /// plain RGB never: colour always goes through the sigmoid) in f16, or
    /// the VM + MLP appearance as trained.
    pub fn to_field(&self) -> Field {
        let appearance = match &self.vm {
            Some(vm) => vm.to_field(self.geom),
            None => self.sh_appearance(),
        };
        let features = self.features.as_ref().map(|f| {
            Features::Grid(ChannelGrid::dense(
                f.geom,
                f.channels,
                f.data.par_iter().map(|&v| f16::from_f32(v)).collect(),
            ))
        });
        Field::new(
            DensityGrid {
                geom: self.geom,
                raw: self.density.clone(),
                activation: self.activation(),
            },
            appearance,
            features,
            None,
        )
    }

    /// The field `isrf train` writes: [`Model::to_field`] with appearance
    /// and features stored for the occupied points only and the density
    /// emptied elsewhere ([`crate::field::sparse`]: renders and segments
    /// the same), built without a dense f16 copy of the grids.
    pub fn to_sparse_field(&self) -> Field {
        let dense = DensityGrid {
            geom: self.geom,
            raw: self.density.clone(),
            activation: self.activation(),
        };
        let bits = sparse::density_occupancy(&dense);
        let density = sparse::emptied_density(&dense, &bits);
        drop(dense);
        let index = Arc::new(RankIndex::new(bits));
        let appearance = match &self.vm {
            Some(vm) => vm.to_field(self.geom),
            None => {
                let data = sparse::gather(&index, 3 * SH_COEFFS, |v, row| self.sh_row(v, row));
                Appearance::Sh2(ChannelGrid::sparse(self.geom, 3 * SH_COEFFS, index.clone(), data))
            }
        };
        let features = self.features.as_ref().map(|f| {
            let fi = Arc::new(RankIndex::new(sparse::feature_occupancy(
                index.bits(),
                &self.geom,
                &f.geom,
            )));
            let c = f.channels;
            let data = sparse::gather(&fi, c, |v, row| {
                for (o, &x) in row.iter_mut().zip(&f.data[v * c..(v + 1) * c]) {
                    *o = f16::from_f32(x);
                }
            });
            Features::Grid(ChannelGrid::sparse(f.geom, c, fi, data))
        });
        Field::new(density, appearance, features, Some(index))
    }

    /// SH coefficients of voxel `v` padded to degree 2, in f16.
    fn sh_row(&self, v: usize, row: &mut [f16]) {
        let k = sh_coeffs(self.degree);
        row.fill(f16::ZERO);
        let Some(src) = self.sh_of(v) else {
            return;
        };
        for c in 0..3 {
            for j in 0..k {
                row[c * SH_COEFFS + j] = f16::from_f32(src[c * k + j]);
            }
        }
    }

    /// The SH coefficients padded to degree 2, in f16.
    fn sh_appearance(&self) -> Appearance {
        let mut sh = vec![f16::ZERO; self.len() * 3 * SH_COEFFS];
        sh.par_chunks_mut(3 * SH_COEFFS)
            .enumerate()
            .for_each(|(v, row)| self.sh_row(v, row));
        Appearance::Sh2(ChannelGrid::dense(self.geom, 3 * SH_COEFFS, sh))
    }

    /// Smallest box holding the solid voxels (per-sample opacity at `step`
    /// at least `alpha_floor`) of every 26-connected component that carries
    /// real opacity ([`SOLID_COMPONENT_MASS`]; the heaviest one if none
    /// does), padded by `pad` voxels and clipped to the grid; `None` when
    /// no voxel is solid.
    ///
    /// Components, not single voxels: a first stage leaves a faint haze of
    /// lone voxels all over the box (lego at 64³: 20–40 per slice, each
    /// with an opacity of a few hundredths, and more on the box's faces),
    /// and one of them anywhere kept the whole box, so lego's grid spent
    /// its points on a 3-unit cube around a 2.4 × 1.3 × 1.4 model.
    pub fn occupied_bounds(&self, step: f32, alpha_floor: f32, pad: usize) -> Option<Aabb> {
        let g = self.geom;
        let act = self.activation();
        let alpha: Vec<f32> = self
            .density
            .par_iter()
            .map(|&d| 1.0 - (-act.apply(d) * step).exp())
            .collect();
        let solid = |i: usize| alpha[i] >= alpha_floor;
        let (mut lo, mut hi) = ([usize::MAX; 3], [0usize; 3]);
        // The heaviest component's box, in case none is heavy enough.
        let mut heaviest = (0.0f64, [0usize; 3], [0usize; 3]);
        let mut seen = vec![false; g.len()];
        let mut queue = vec![];
        for start in 0..g.len() {
            if seen[start] || !solid(start) {
                continue;
            }
            // One component: its opacity mass and its bounds.
            seen[start] = true;
            queue.clear();
            queue.push(start);
            let (mut k, mut mass) = (0, 0.0f64);
            let (mut clo, mut chi) = ([usize::MAX; 3], [0usize; 3]);
            while k < queue.len() {
                let v = queue[k];
                k += 1;
                mass += alpha[v] as f64;
                let c = g.coords(v);
                for a in 0..3 {
                    clo[a] = clo[a].min(c[a]);
                    chi[a] = chi[a].max(c[a]);
                }
                g.neighbours26(v, |j| {
                    if !seen[j] && solid(j) {
                        seen[j] = true;
                        queue.push(j);
                    }
                });
            }
            if mass > heaviest.0 {
                heaviest = (mass, clo, chi);
            }
            if mass >= SOLID_COMPONENT_MASS {
                lo = [0, 1, 2].map(|a| lo[a].min(clo[a]));
                hi = [0, 1, 2].map(|a| hi[a].max(chi[a]));
            }
        }
        if lo[0] == usize::MAX {
            if heaviest.0 == 0.0 {
                return None;
            }
            (lo, hi) = (heaviest.1, heaviest.2);
        }
        let lo = [0, 1, 2].map(|k| lo[k].saturating_sub(pad));
        let hi = [0, 1, 2].map(|k| (hi[k] + pad).min(g.res[k] - 1));
        let p0 = g.point(lo[0], lo[1], lo[2]);
        let p1 = g.point(hi[0], hi[1], hi[2]);
        // Keep at least one voxel of extent per axis.
        let sp = g.spacing();
        let p1 = Vec3::select(p1.cmpgt(p0), p1, p0 + sp);
        Some(Aabb::new(p0, p1))
    }
}

/// Opacity mass (summed per-sample opacity) a connected group of solid
/// voxels needs to count as content when the box shrinks: four opaque
/// voxels' worth. The haze a first stage leaves comes in groups of well
/// under one; a real part the coarse grid resolves holds several.
pub const SOLID_COMPONENT_MASS: f64 = 4.0;

/// [`remap_rows`] into `values` itself. When every voxel of `new` is one
/// of `old`'s (a prune), row s of `new` comes from a row o ≥ s of `old`
/// (both ascending by voxel), so the rows move forward one by one and no
/// second array is held: on the fern's `--preset best` grid the colour rows
/// are 580 MB, and their copy during a prune, beside the gradient buffers,
/// was the training run's peak. Otherwise (voxels added) it copies.
pub fn remap_rows_in_place<T: Copy + Default + Send + Sync>(
    values: &mut Vec<T>,
    old: &Slots,
    new: &Slots,
    stride: usize,
) {
    if !new.voxels.iter().all(|&v| old.slot(v as usize).is_some()) {
        *values = remap_rows(values, old, new, stride);
        return;
    }
    // Every voxel has an old slot (checked above), so s counts new slots.
    for (s, o) in new.voxels.iter().filter_map(|&v| old.slot(v as usize)).enumerate() {
        if o != s {
            values.copy_within(o * stride..(o + 1) * stride, s * stride);
        }
    }
    values.truncate(new.len() * stride);
    // Large buffers are mapped on their own (`crate::heap`, set in main), so this
    // gives the tail back without copying.
    values.shrink_to_fit();
}

/// Per-slot rows (`stride` values each) of `old`'s slots renumbered for
/// `new`; voxels `old` lacks get zeros.
pub fn remap_rows<T: Copy + Default + Send + Sync>(values: &[T], old: &Slots, new: &Slots, stride: usize) -> Vec<T> {
    let mut out = vec![T::default(); new.len() * stride];
    out.par_chunks_mut(stride.max(1))
        .zip(new.voxels.par_iter())
        .for_each(|(row, &voxel)| {
            if let Some(o) = old.slot(voxel as usize) {
                row.copy_from_slice(&values[o * stride..(o + 1) * stride]);
            }
        });
    out
}

/// Grid resolution with about `longest` points along the longest side of
/// `bounds` and the same spacing along every axis, then scaled per axis by
/// `scale` (e.g. fewer points along NDC depth); at least 2 per axis.
pub fn res_for(bounds: Aabb, longest: usize, scale: [f32; 3]) -> [usize; 3] {
    let s = bounds.size();
    let m = s.max_element();
    [0, 1, 2].map(|a| (((longest - 1) as f32 * s[a] / m * scale[a]).round() as usize + 1).max(2))
}

/// softplus⁻¹(y) = ln(eʸ − 1), stable for small and large y.
pub fn inverse_softplus(y: f32) -> f32 {
    if y > 20.0 {
        y
    } else {
        y.exp_m1().ln()
    }
}

/// Bits set within Chebyshev distance `r` (voxels) of a set bit.
pub fn dilate_bits(words: &[u64], res: [usize; 3], r: usize) -> Vec<u64> {
    let mut cur = words.to_vec();
    let [nx, ny, nz] = res;
    let n = nx * ny * nz;
    for _ in 0..r {
        let src = cur.clone();
        cur.par_iter_mut().enumerate().for_each(|(w, bits)| {
            for b in 0..64 {
                let i = w * 64 + b;
                if i >= n || *bits >> b & 1 == 1 {
                    continue;
                }
                let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
                let near = |c: usize, m: usize| c.saturating_sub(1)..=(c + 1).min(m - 1);
                let hit = near(z, nz)
                    .any(|zz| near(y, ny).any(|yy| near(x, nx).any(|xx| bit(&src, xx + nx * (yy + ny * zz)))));
                if hit {
                    *bits |= 1 << b;
                }
            }
        });
    }
    cur
}
