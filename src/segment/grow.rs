//! Bilateral growth of a 3D mask (DESIGN.md, Segmentation step 4).
//!
//! One step: the frontier is every occupied voxel c (σ > the cache floor) not
//! in the mask with a masked voxel among its 26 neighbours. For each, over the
//! occupied voxels n of its 3×3×3 neighbourhood (c included),
//! v = Σ mₙ wₙ / Σ wₙ with wₙ = exp(−‖φₙ − φ_c‖²/σ_φ) · exp(−‖n − c‖₁/σ_s);
//! c joins the mask when v > τ. All frontier voxels are decided against the
//! mask as it was at the start of the step (a synchronous update).
//!
//! Two rules ([`GrowthRule`]):
//! - `Paper`: exactly the above on the raw features, as in the authors' code.
//!   With our unit-scale distilled features it floods: ‖Δφ‖² is small next
//!   to σ_φ = 10, so every weight is close to 1 and growth is a flood fill
//!   through everything with density (IoU 0.000 on the real fern).
//! - `Bounded` (the default): φ are unit features, so ‖Δφ‖² ∈ [0, 4] and
//!   σ_φ is on that scale; and growth has hysteresis, as Canny's edges do:
//!   seeds need the NNFM distance below θ, grown voxels only below the looser
//!   θ_grow, and must be solid (σ above the segmentation floor). Growth then
//!   fills thin parts the seed missed, along voxels that still look like the
//!   stroke, and stops where the features change.
//!
//! Empty neighbours (σ ≤ floor) are left out of the sums: they carry no
//! meaningful features in a trained field, and are never in the mask.
//!
//! The frontier version only evaluates voxels whose neighbourhood changed:
//! after the first step, the candidates are the unmasked occupied neighbours
//! of the voxels added by the previous step (any other frontier voxel sees the
//! same neighbourhood as before and would be rejected again). It gives the
//! same masks as [`grow_step_dense`], which scans the whole grid.

use super::kmeans::{Centroids, LANES};
use super::nnfm::CentreSet;
use super::Growth;
use crate::field::{Bitmap, FeatureCache};
use rayon::prelude::*;

/// Which growth rule (module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GrowthRule {
    /// The paper's rule on raw features (for the ablation).
    Paper,
    /// Unit features, NNFM hysteresis and a solidity floor.
    Bounded,
    /// Seeds grown to the region most stable under the hysteresis
    /// threshold ([`super::stable`]); grow steps on their own (the editor's
    /// grow button) use the bounded rule.
    #[default]
    Stable,
}

impl std::str::FromStr for GrowthRule {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "paper" => Ok(GrowthRule::Paper),
            "bounded" => Ok(GrowthRule::Bounded),
            "stable" => Ok(GrowthRule::Stable),
            _ => Err(format!("unknown growth rule '{s}' (stable, bounded or paper)")),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct GrowParams {
    pub sigma_f: f32,
    pub sigma_s: f32,
    pub tau: f32,
    pub rule: GrowthRule,
    /// Bounded rule: grown voxels need an NNFM distance (squared, unit
    /// features) to the stroke's centres below this.
    pub theta_grow: f32,
}

impl Default for GrowParams {
    fn default() -> Self {
        GrowParams {
            sigma_f: 0.2,
            sigma_s: 1.0,
            tau: 0.1,
            rule: GrowthRule::Stable,
            theta_grow: 0.8,
        }
    }
}

impl GrowParams {
    /// The paper's rule and defaults (σ_φ = 10 on raw features, τ = 0.1).
    pub fn paper() -> Self {
        GrowParams {
            sigma_f: 10.0,
            sigma_s: 1.0,
            tau: 0.1,
            rule: GrowthRule::Paper,
            theta_grow: f32::INFINITY,
        }
    }
}

/// What bounds the `Bounded` rule: the stroke's centres and the floor on σ.
#[derive(Clone, Debug)]
pub struct Bound {
    pub centres: CentreSet,
    pub theta_grow: f32,
    pub floor: f32,
}

impl Bound {
    pub fn new(centres: Centroids, theta_grow: f32, floor: f32) -> Self {
        Bound {
            centres: CentreSet::new(centres),
            theta_grow,
            floor,
        }
    }
    /// Whether cache row `r` is solid and matches a centre within θ_grow.
    fn admits(&self, cache: &FeatureCache, r: usize) -> bool {
        cache.sigma[r] > self.floor && self.centres.any_within(cache, r, self.theta_grow)
    }
}

/// The 26 neighbour offsets plus the centre, with their spatial weights and
/// their flat-index deltas on this grid (x fastest), in a fixed order (the
/// order of the sums, so results do not depend on how a voxel is reached).
#[derive(Clone, Debug)]
pub(super) struct Offsets {
    res: [usize; 3],
    step: Vec<([i64; 3], f32)>,
    delta: Vec<isize>,
}

impl Offsets {
    pub(super) fn new(res: [usize; 3], p: &GrowParams) -> Self {
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
    pub(super) fn for_each(&self, v: usize, mut f: impl FnMut(usize, usize)) {
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
    /// The in-grid neighbours of `v` (centre included) into `out`, how many
    /// there are: for loops whose body is too large to inline into
    /// [`Self::for_each`]'s two paths (the stable flood's was called once
    /// per neighbour).
    #[inline]
    pub(super) fn fill(&self, v: usize, out: &mut [usize; 27]) -> usize {
        let mut n = 0;
        self.for_each(v, |_, u| {
            out[n] = u;
            n += 1;
        });
        n
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

/// Per-thread scratch of [`decide`]: the occupied neighbours of a voxel and
/// their squared feature distances.
struct Scratch {
    /// (offset position, cache row, masked) of each occupied neighbour.
    hood: Vec<(usize, usize, bool)>,
    df: Vec<f32>,
}

impl Scratch {
    fn new() -> Self {
        Scratch {
            hood: Vec::with_capacity(27),
            df: Vec::with_capacity(32),
        }
    }
}

/// Squared distances between unit features (‖a/‖a‖ − b/‖b‖‖² = 2 − 2 cos,
/// 2 for a zero feature) from row `rc` to the rows of `s.hood`, into `s.df`,
/// [`LANES`] neighbours at a time (their independent sums interleaved so
/// that they do not wait on each other's additions).
fn hood_unit_distances(cache: &FeatureCache, rc: usize, s: &mut Scratch) {
    let fc = cache.row(rc);
    let inv_c = cache.inv_norm[rc];
    s.df.clear();
    for group in s.hood.chunks(LANES) {
        let rows: [&[f32]; LANES] = std::array::from_fn(|l| group.get(l).map_or(fc, |h| cache.row(h.1)));
        let mut acc = [0.0f32; LANES];
        for (ch, &f) in fc.iter().enumerate() {
            for l in 0..LANES {
                acc[l] += rows[l][ch] * f;
            }
        }
        for (h, dot) in group.iter().zip(acc) {
            let cos = dot * inv_c * cache.inv_norm[h.1];
            s.df.push((2.0 - 2.0 * cos).max(0.0));
        }
    }
}

/// Squared feature distances from `fc` to the rows of `s.hood`, into `s.df`.
fn hood_distances(cache: &FeatureCache, fc: &[f32], s: &mut Scratch) {
    let c = fc.len();
    s.df.clear();
    for group in s.hood.chunks(LANES) {
        // Unused lanes read the centre's own row (distance 0, discarded).
        let rows: [&[f32]; LANES] = std::array::from_fn(|l| group.get(l).map_or(fc, |h| &cache.row(h.1)[..c]));
        let mut acc = [0.0f32; LANES];
        for (ch, &f) in fc.iter().enumerate() {
            for l in 0..LANES {
                let d = rows[l][ch] - f;
                acc[l] += d * d;
            }
        }
        s.df.extend_from_slice(&acc[..group.len()]);
    }
}

/// Decides one frontier candidate: Some(true) to add, Some(false) to reject,
/// None if it is not on the frontier (masked, empty, or no masked neighbour).
fn decide(
    cache: &FeatureCache,
    mask: &Bitmap,
    offs: &Offsets,
    p: &GrowParams,
    bound: Option<&Bound>,
    v: usize,
    s: &mut Scratch,
) -> Option<bool> {
    if mask.get(v) {
        return None;
    }
    let rc = cache.index.slot(v)?;
    let unit = p.rule != GrowthRule::Paper;
    if unit && bound.is_some_and(|b| cache.sigma[rc] <= b.floor) {
        return None;
    }
    let mut touches = false;
    s.hood.clear();
    offs.for_each(v, |k, n| {
        let masked = mask.get(n);
        touches |= masked;
        if let Some(rn) = cache.index.slot(n) {
            s.hood.push((k, rn, masked));
        }
    });
    if !touches {
        return None;
    }
    if let Some(b) = bound.filter(|_| unit) {
        if !b.admits(cache, rc) {
            return Some(false);
        }
    }
    if unit {
        hood_unit_distances(cache, rc, s);
    } else {
        hood_distances(cache, cache.row(rc), s);
    }
    // Sums in offset order, as the definition reads.
    let (mut num, mut den) = (0.0f32, 0.0f32);
    for (&(k, _, masked), &df) in s.hood.iter().zip(&s.df) {
        let w = offs.step[k].1 * (-df / p.sigma_f).exp();
        den += w;
        if masked {
            num += w;
        }
    }
    Some(den > 0.0 && num / den > p.tau)
}

/// Below these sizes a step's parts run on the calling thread: late growth
/// steps touch a few hundred voxels, for which waking the thread pool (on a
/// busy machine, waiting for a time slice) costs more than the work.
const PAR_MIN_SOURCES: usize = 4096;
const PAR_MIN_SORT: usize = 1 << 16;
const PAR_MIN_DECIDE: usize = 512;

/// Unmasked occupied neighbours of `voxels` (deduplicated, ascending).
fn candidates(cache: &FeatureCache, mask: &Bitmap, offs: &Offsets, voxels: &[u32]) -> Vec<u32> {
    let occupied = cache.index.bits();
    let collect = |chunk: &[u32]| {
        let mut local = Vec::new();
        for &v in chunk {
            offs.for_each(v as usize, |_, n| {
                if !mask.get(n) && occupied.get(n) {
                    local.push(n as u32);
                }
            });
        }
        local
    };
    let mut out: Vec<u32> = if voxels.len() < PAR_MIN_SOURCES {
        collect(voxels)
    } else {
        voxels.par_chunks(2048).flat_map_iter(collect).collect()
    };
    if out.len() < PAR_MIN_SORT {
        out.sort_unstable();
    } else {
        out.par_sort_unstable();
    }
    out.dedup();
    out
}

/// Incremental grower: remembers which voxels were added last so each step
/// only revisits their neighbourhoods.
pub struct Grower<'a> {
    cache: &'a FeatureCache,
    params: GrowParams,
    bound: Option<Bound>,
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
            bound: None,
            offs: Offsets::new(cache.geom.res, &params),
            last_added: None,
        }
    }
    /// Bounds growth by a stroke (used by the `Bounded` rule only).
    pub fn with_bound(mut self, bound: Bound) -> Self {
        self.bound = Some(bound);
        self
    }
    /// One synchronous step; returns the number of voxels added.
    pub fn step(&mut self, mask: &mut Bitmap) -> usize {
        let sources: Vec<u32> = match self.last_added.take() {
            Some(v) => v,
            None => mask.ones().map(|i| i as u32).collect(),
        };
        let cand = candidates(self.cache, mask, &self.offs, &sources);
        let (cache, offs, params, bound) = (self.cache, &self.offs, &self.params, self.bound.as_ref());
        let joins = |s: &mut Scratch, v: u32| decide(cache, mask, offs, params, bound, v as usize, s) == Some(true);
        let added: Vec<u32> = if cand.len() < PAR_MIN_DECIDE {
            let mut s = Scratch::new();
            cand.iter().copied().filter(|&v| joins(&mut s, v)).collect()
        } else {
            cand.par_iter()
                .copied()
                .map_init(Scratch::new, |s, v| joins(s, v).then_some(v))
                .flatten()
                .collect()
        };
        for &v in &added {
            mask.set(v as usize, true);
        }
        let n = added.len();
        self.last_added = Some(added);
        n
    }
    /// Steps until nothing changes or `max_steps`; returns the steps taken.
    pub fn converge(&mut self, mask: &mut Bitmap, max_steps: usize) -> usize {
        self.grow(mask, Growth::Converge, max_steps, |_| ())
    }

    /// Grows as `growth` asks, calling `on_step(i)` before step i (progress
    /// reports). Returns the steps counted as [`super::Timings::grow_steps`] does:
    /// `Steps(n)` counts the steps that added voxels (it stops at the first
    /// that adds none), convergence counts that last, empty step too; at
    /// most `max_steps` for convergence.
    pub fn grow(
        &mut self,
        mask: &mut Bitmap,
        growth: Growth,
        max_steps: usize,
        mut on_step: impl FnMut(usize),
    ) -> usize {
        let (limit, counts_last) = match growth {
            Growth::Steps(n) => (n, false),
            Growth::Converge => (max_steps, true),
        };
        for s in 0..limit {
            on_step(s);
            if self.step(mask) == 0 {
                return s + counts_last as usize;
            }
        }
        limit
    }
}

/// The straightforward implementation: every voxel of the grid is tested
/// each step. Used as the reference in tests and the benchmark.
pub fn grow_step_dense(cache: &FeatureCache, mask: &mut Bitmap, params: &GrowParams, bound: Option<&Bound>) -> usize {
    let offs = Offsets::new(cache.geom.res, params);
    let added: Vec<usize> = (0..cache.geom.len())
        .into_par_iter()
        .map_init(Scratch::new, |s, v| {
            (decide(cache, mask, &offs, params, bound, v, s) == Some(true)).then_some(v)
        })
        .flatten()
        .collect();
    for &v in &added {
        mask.set(v, true);
    }
    added.len()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{Aabb, FieldBuilder};
    use glam::Vec3;

    #[test]
    fn lane_distances_equal_the_plain_sums_bit_for_bit() {
        // 13 channels: one full group of 8 lanes, then a partial one.
        let feat = |p: Vec3, out: &mut [f32]| {
            for (c, o) in out.iter_mut().enumerate() {
                *o = (3.1 * p.x + 1.7 * c as f32).sin() * (2.3 * p.y - 0.4 * c as f32).cos() + p.z * 0.1;
            }
        };
        let f = FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [9; 3]).build(
            |p| if p.length() < 1.2 { 1.0 } else { 0.0 },
            |_| Vec3::ONE,
            Some((13, &feat)),
        );
        let cache = FeatureCache::build(&f).unwrap();
        let offs = Offsets::new(cache.geom.res, &GrowParams::default());
        let mut s = Scratch::new();
        let mut checked = 0;
        for &v in &cache.voxels {
            s.hood.clear();
            offs.for_each(v as usize, |k, n| {
                if let Some(rn) = cache.index.slot(n) {
                    s.hood.push((k, rn, false));
                }
            });
            let fc = cache.row(cache.index.slot(v as usize).unwrap());
            hood_distances(&cache, fc, &mut s);
            assert_eq!(s.df.len(), s.hood.len());
            for (&(_, rn, _), &df) in s.hood.iter().zip(&s.df) {
                let plain: f32 = cache.row(rn).iter().zip(fc).map(|(a, b)| (a - b) * (a - b)).sum();
                assert_eq!(df.to_bits(), plain.to_bits());
                checked += 1;
            }
        }
        // Interior voxels have 27 occupied neighbours, border ones fewer.
        assert!(checked > 27 * 100, "{checked}");
    }
}
