//! Bilateral growth of a 3D mask (DESIGN.md, Segmentation step 4).
//!
//! One step: the frontier is every occupied voxel c (σ > the cache floor) not
//! in the mask with a masked voxel among its 26 neighbours. For each, over the
//! occupied voxels n of its 3×3×3 neighbourhood (c included),
//! v = Σ mₙ wₙ / Σ wₙ with wₙ = exp(−‖φₙ − φ_c‖²/σ_φ) · exp(−‖n − c‖₁/σ_s);
//! c joins the mask when v > τ. All frontier voxels are decided against the
//! mask as it was at the start of the step (a synchronous update).
//!
//! Empty neighbours (σ ≤ floor) are left out of the sums: they carry no
//! meaningful features in a trained field, and are never in the mask.
//!
//! The frontier version only evaluates voxels whose neighbourhood changed:
//! after the first step, the candidates are the unmasked occupied neighbours
//! of the voxels added by the previous step (any other frontier voxel sees the
//! same neighbourhood as before and would be rejected again). It gives the
//! same masks as [`grow_step_dense`], which scans the whole grid.

use crate::field::{Bitmap, FeatureCache};
use rayon::prelude::*;

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GrowParams {
    pub sigma_f: f32,
    pub sigma_s: f32,
    pub tau: f32,
}

impl Default for GrowParams {
    fn default() -> Self {
        GrowParams {
            sigma_f: 10.0,
            sigma_s: 1.0,
            tau: 0.1,
        }
    }
}

/// The 26 neighbour offsets plus the centre, with their spatial weights and
/// their flat-index deltas on this grid (x fastest), in a fixed order (the
/// order of the sums, so results do not depend on how a voxel is reached).
#[derive(Clone, Debug)]
struct Offsets {
    res: [usize; 3],
    step: Vec<([i64; 3], f32)>,
    delta: Vec<isize>,
}

impl Offsets {
    fn new(res: [usize; 3], p: &GrowParams) -> Self {
        let mut step = Vec::with_capacity(27);
        let mut delta = Vec::with_capacity(27);
        let (sx, sy) = (res[0] as isize, (res[0] * res[1]) as isize);
        for dz in -1..=1i64 {
            for dy in -1..=1i64 {
                for dx in -1..=1i64 {
                    let l1 = (dx.abs() + dy.abs() + dz.abs()) as f32;
                    step.push(([dx, dy, dz], (-l1 / p.sigma_s).exp()));
                    delta.push(dx as isize + sx * dy as isize + sy * dz as isize);
                }
            }
        }
        Offsets { res, step, delta }
    }
    /// Calls `f(k, n)` for every in-grid neighbour n (centre included) of
    /// voxel `v`, k being the offset's position. Interior voxels take the
    /// fast path of flat deltas; border voxels check bounds.
    #[inline]
    fn for_each(&self, v: usize, mut f: impl FnMut(usize, usize)) {
        let [nx, ny, nz] = self.res;
        let x = v % nx;
        let yz = v / nx;
        let (y, z) = (yz % ny, yz / ny);
        if x >= 1 && y >= 1 && z >= 1 && x + 1 < nx && y + 1 < ny && z + 1 < nz {
            for (k, &d) in self.delta.iter().enumerate() {
                f(k, v.wrapping_add_signed(d));
            }
        } else {
            for (k, &(d, _)) in self.step.iter().enumerate() {
                if let Some(n) = neighbour(self.res, [x, y, z], d) {
                    f(k, n);
                }
            }
        }
    }
}

#[inline]
fn neighbour(res: [usize; 3], c: [usize; 3], d: [i64; 3]) -> Option<usize> {
    let x = c[0] as i64 + d[0];
    let y = c[1] as i64 + d[1];
    let z = c[2] as i64 + d[2];
    if x < 0 || y < 0 || z < 0 || x >= res[0] as i64 || y >= res[1] as i64 || z >= res[2] as i64 {
        return None;
    }
    Some(x as usize + res[0] * (y as usize + res[1] * z as usize))
}

/// Decides one frontier candidate: Some(true) to add, Some(false) to reject,
/// None if it is not on the frontier (masked, empty, or no masked neighbour).
fn decide(cache: &FeatureCache, mask: &Bitmap, offs: &Offsets, p: &GrowParams, v: usize) -> Option<bool> {
    if mask.get(v) {
        return None;
    }
    let rc = cache.index.slot(v)?;
    let fc = cache.row(rc);
    let (mut num, mut den) = (0.0f32, 0.0f32);
    let mut touches = false;
    offs.for_each(v, |k, n| {
        let masked = mask.get(n);
        touches |= masked;
        let Some(rn) = cache.index.slot(n) else { return };
        let df: f32 = cache.row(rn).iter().zip(fc).map(|(a, b)| (a - b) * (a - b)).sum();
        let w = offs.step[k].1 * (-df / p.sigma_f).exp();
        den += w;
        if masked {
            num += w;
        }
    });
    touches.then(|| den > 0.0 && num / den > p.tau)
}

/// Unmasked occupied neighbours of `voxels` (deduplicated, ascending).
fn candidates(cache: &FeatureCache, mask: &Bitmap, offs: &Offsets, voxels: &[u32]) -> Vec<u32> {
    let occupied = cache.index.bits();
    let mut out: Vec<u32> = voxels
        .par_chunks(2048)
        .flat_map_iter(|chunk| {
            let mut local = Vec::new();
            for &v in chunk {
                offs.for_each(v as usize, |_, n| {
                    if !mask.get(n) && occupied.get(n) {
                        local.push(n as u32);
                    }
                });
            }
            local
        })
        .collect();
    out.par_sort_unstable();
    out.dedup();
    out
}

/// Incremental grower: remembers which voxels were added last so each step
/// only revisits their neighbourhoods.
pub struct Grower<'a> {
    cache: &'a FeatureCache,
    params: GrowParams,
    offs: Offsets,
    /// Voxels added by the previous step; `None` before the first step (then
    /// the whole mask's neighbourhood is the candidate set).
    last_added: Option<Vec<u32>>,
}

impl<'a> Grower<'a> {
    pub fn new(cache: &'a FeatureCache, params: GrowParams) -> Self {
        Grower {
            cache,
            params,
            offs: Offsets::new(cache.geom.res, &params),
            last_added: None,
        }
    }
    /// One synchronous step; returns the number of voxels added.
    pub fn step(&mut self, mask: &mut Bitmap) -> usize {
        let sources: Vec<u32> = match self.last_added.take() {
            Some(v) => v,
            None => mask.ones().map(|i| i as u32).collect(),
        };
        let cand = candidates(self.cache, mask, &self.offs, &sources);
        let added: Vec<u32> = cand
            .par_iter()
            .copied()
            .filter(|&v| decide(self.cache, mask, &self.offs, &self.params, v as usize) == Some(true))
            .collect();
        for &v in &added {
            mask.set(v as usize, true);
        }
        let n = added.len();
        self.last_added = Some(added);
        n
    }
    /// Steps until nothing changes or `max_steps`; returns the steps taken.
    pub fn converge(&mut self, mask: &mut Bitmap, max_steps: usize) -> usize {
        for s in 0..max_steps {
            if self.step(mask) == 0 {
                return s + 1;
            }
        }
        max_steps
    }
}

/// The straightforward implementation: every voxel of the grid is tested
/// each step. Used as the reference in tests and the benchmark.
pub fn grow_step_dense(cache: &FeatureCache, mask: &mut Bitmap, params: &GrowParams) -> usize {
    let offs = Offsets::new(cache.geom.res, params);
    let added: Vec<usize> = (0..cache.geom.len())
        .into_par_iter()
        .filter(|&v| decide(cache, mask, &offs, params, v) == Some(true))
        .collect();
    for &v in &added {
        mask.set(v, true);
    }
    added.len()
}
