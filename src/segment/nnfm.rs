//! Nearest-neighbour feature matching (NNFM) seed over occupied voxels.
//!
//! For every cached voxel with σ above `floor`:
//! d = min_k ‖φ̂ − c_k‖² = min_k (‖φ̂‖² − 2 φ̂·c_k + ‖c_k‖²) with φ̂ = φ/‖φ‖,
//! and the voxel is a seed when d < θ. Written as dot products so the inner
//! loop is one multiply-add per channel.

use super::kmeans::{CentreBlocks, Centroids, LANES};
use crate::field::{Bitmap, FeatureCache};
use rayon::prelude::*;

/// A cheap test that rules out most voxels before the exact one.
///
/// For a unit feature φ̂, d_k < θ ⇔ φ̂·c_k > t_k with t_k = (1 + ‖c_k‖² − θ)/2,
/// and by Cauchy–Schwarz φ̂·c_k ≤ φ̂·m + ‖c_k − m‖ for any m. So a voxel with
/// φ̂·m < min_k (t_k − ‖c_k − m‖) − MARGIN matches no centre: one dot
/// product instead of K. The margin is far above f32 rounding (~1e-6 for
/// unit vectors), so every voxel it rules out would also fail the exact
/// test, and the seed is the same bitmap as without it.
struct Prune {
    /// m: the mean of the centres.
    mean: Vec<f32>,
    /// min_k (t_k − ‖c_k − m‖) − MARGIN.
    bound: f32,
}

const MARGIN: f32 = 1e-3;

impl Prune {
    fn new(centres: &Centroids, norms: &[f32], theta: f32, channels: usize) -> Self {
        let (k, dim) = (centres.len(), centres.dim);
        if dim != channels {
            // Mismatched widths: the exact test alone decides.
            return Prune {
                mean: vec![0.0; channels],
                bound: f32::NEG_INFINITY,
            };
        }
        let mut mean = vec![0.0f32; dim];
        for j in 0..k {
            for (m, &c) in mean.iter_mut().zip(centres.row(j)) {
                *m += c / k as f32;
            }
        }
        let bound = (0..k)
            .map(|j| {
                let r = super::kmeans::dist2(centres.row(j), &mean).sqrt();
                0.5 * (1.0 + norms[j] - theta) - r
            })
            .fold(f32::INFINITY, f32::min)
            - MARGIN;
        Prune { mean, bound }
    }
    /// True when cache row `r` certainly matches no centre. Zero and
    /// non-finite features are never ruled out (the exact test decides).
    #[inline]
    fn rules_out(&self, cache: &FeatureCache, r: usize) -> bool {
        let inv = cache.inv_norm[r];
        inv > 0.0 && dot8(cache.row(r), &self.mean) * inv < self.bound
    }
}

/// Dot product with eight partial sums (vectorises; the summation order
/// differs from a plain loop, which the pruning margin absorbs).
#[inline]
fn dot8(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ca.remainder().iter().zip(cb.remainder()).map(|(x, y)| x * y).sum();
    for (x, y) in ca.zip(cb) {
        for l in 0..8 {
            acc[l] += x[l] * y[l];
        }
    }
    acc.iter().sum::<f32>() + tail
}

/// Seed bitmap over the cache's grid.
pub fn nnfm_seed(cache: &FeatureCache, centres: &Centroids, theta: f32, floor: f32) -> Bitmap {
    nnfm_seed_with_distances(cache, centres, theta, floor).0
}

/// The seed bitmap, and the distances it measured: every row the exact
/// test saw (σ above `floor`, not ruled out by the cheap bound) gets its
/// exact NNFM distance, the others are left for [`StrokeDistances::get`]
/// to compute when asked. The stable flood and the graph cut ask for the
/// distances of most of the rows a large object covers; measuring them
/// here, blocked and in parallel, is what keeps them cheap.
pub fn nnfm_seed_with_distances(
    cache: &FeatureCache,
    centres: &Centroids,
    theta: f32,
    floor: f32,
) -> (Bitmap, StrokeDistances) {
    seed_measuring(cache, centres, theta, floor, true)
}

/// [`nnfm_seed_with_distances`] that measures every row with σ above
/// `floor`, for the stable flood, which reaches most of a scene (260–340k
/// of the realistic tabletop's 493k voxels, 30–130k of them ruled out by
/// the bound): measured here, blocked and on every core, instead of one by
/// one on the flood's core, they took its growth stage from 52–79 to
/// 37–50 ms.
pub fn nnfm_seed_measuring_all(
    cache: &FeatureCache,
    centres: &Centroids,
    theta: f32,
    floor: f32,
) -> (Bitmap, StrokeDistances) {
    seed_measuring(cache, centres, theta, floor, false)
}

/// The seed and distances, with or without the bound that skips rows
/// matching no centre.
fn seed_measuring(
    cache: &FeatureCache,
    centres: &Centroids,
    theta: f32,
    floor: f32,
    bound: bool,
) -> (Bitmap, StrokeDistances) {
    let mut bits = Bitmap::new(cache.geom.res);
    let mut dist = StrokeDistances::new(cache, centres.clone());
    if centres.is_empty() {
        return (bits, dist);
    }
    let norms = &dist.set.norms;
    let prune = bound.then(|| Prune::new(centres, norms, theta, cache.channels));
    let test = Exact { cache, centres, norms };
    const CHUNK: usize = 4096;
    let hits: Vec<Vec<u32>> = dist
        .d
        .par_chunks_mut(CHUNK)
        .enumerate()
        .map(|(c, d)| {
            let (start, end) = (c * CHUNK, c * CHUNK + d.len());
            let mut out = Vec::new();
            let mut block = vec![0.0f32; cache.channels * LANES];
            let mut r = start;
            while r + LANES <= end {
                let mut pending = [false; LANES];
                for (l, p) in pending.iter_mut().enumerate() {
                    *p = cache.sigma[r + l] > floor && !prune.as_ref().is_some_and(|b| b.rules_out(cache, r + l));
                }
                if pending.iter().any(|&p| p) {
                    let best = test.block(r, &mut block);
                    for l in (0..LANES).filter(|&l| pending[l]) {
                        d[r + l - start] = best[l];
                        if best[l] < theta {
                            out.push(cache.voxels[r + l]);
                        }
                    }
                }
                r += LANES;
            }
            for r in r..end {
                if cache.sigma[r] > floor {
                    let best = test.one(r);
                    d[r - start] = best;
                    if best < theta {
                        out.push(cache.voxels[r]);
                    }
                }
            }
            out
        })
        .collect();
    for v in hits.into_iter().flatten() {
        bits.set(v as usize, true);
    }
    (bits, dist)
}

/// Each cache row's NNFM distance to one stroke's centres, measured once
/// per stroke and shared by the seed, the stable flood and the graph cut
/// (NaN: not measured yet).
pub struct StrokeDistances {
    set: CentreSet,
    d: Vec<f32>,
}

impl StrokeDistances {
    fn new(cache: &FeatureCache, centres: Centroids) -> Self {
        StrokeDistances {
            set: CentreSet::new(centres),
            d: vec![f32::NAN; cache.len()],
        }
    }
    pub fn centres(&self) -> &Centroids {
        &self.set.centres
    }
    /// The distance of cache row `r`, measured now if it was not.
    pub fn get(&mut self, cache: &FeatureCache, r: usize) -> f32 {
        let d = self.d[r];
        if !d.is_nan() {
            return d;
        }
        let d = self.set.min_distance(cache, r);
        self.d[r] = d;
        d
    }
    /// Makes these the distances to this stroke's centres and `other`'s
    /// together (an object's positive strokes so far): the rows measured
    /// here keep the smaller distance, `other`'s measured now where it had
    /// not; the rest are measured against all the centres when asked. The
    /// minimum over the strokes is bit for bit the distance to all their
    /// centres at once.
    pub fn merge(&mut self, cache: &FeatureCache, mut other: StrokeDistances) {
        let known: Vec<usize> = (0..self.d.len()).filter(|&r| !self.d[r].is_nan()).collect();
        for (&r, o) in known.iter().zip(other.of_rows(cache, &known)) {
            self.d[r] = self.d[r].min(o);
        }
        let mut all = self.set.centres.clone();
        all.data.extend_from_slice(&other.set.centres.data);
        self.set = CentreSet::new(all);
    }

    /// The solid voxels (σ above `floor`) at distance `t` or less, those
    /// not measured yet measured first.
    pub fn solid_within(&mut self, cache: &FeatureCache, floor: f32, t: f32) -> Bitmap {
        let solid = |r: &usize| cache.sigma[*r] > floor;
        let missing: Vec<usize> = (0..cache.len()).filter(solid).filter(|&r| self.d[r].is_nan()).collect();
        self.of_rows(cache, &missing);
        let mut out = Bitmap::new(cache.geom.res);
        for r in (0..cache.len()).filter(solid).filter(|&r| self.d[r] <= t) {
            out.set(cache.voxels[r] as usize, true);
        }
        out
    }

    /// The distances of `rows`, those not measured yet measured in parallel
    /// (and kept).
    pub fn of_rows(&mut self, cache: &FeatureCache, rows: &[usize]) -> Vec<f32> {
        let missing: Vec<usize> = rows.par_iter().copied().filter(|&r| self.d[r].is_nan()).collect();
        for (r, d) in missing.iter().zip(self.set.min_distances(cache, &missing)) {
            self.d[*r] = d;
        }
        rows.par_iter().map(|&r| self.d[r]).collect()
    }
}

/// The dot products of `LANES` rows, stored channel-major in `block`,
/// with `centre`: each lane sums its channels in order, as a plain loop
/// over one row would (bit-identical), and the lanes vectorise.
#[inline(always)]
fn lane_dots(block: &[f32], centre: &[f32]) -> [f32; LANES] {
    let mut acc = [0.0f32; LANES];
    for (b, &ck) in block.chunks_exact(LANES).zip(centre) {
        for l in 0..LANES {
            acc[l] += b[l] * ck;
        }
    }
    acc
}

/// Calls `f(k, dots)` with [`lane_dots`] of every centre, four centres per
/// pass over `block`: each block value loaded once serves four products
/// (the kernels were bound by those loads), and each lane still sums every
/// centre's channels in order, so the products are bit for bit the same.
/// On a CPU with AVX2 the same sums run eight lanes to an instruction
/// ([`avx2::each_centre_dots`]).
#[inline(always)]
fn each_centre_dots(block: &[f32], centres: &Centroids, f: impl FnMut(usize, &[f32; LANES])) {
    #[cfg(target_arch = "x86_64")]
    if crate::util::has_avx2() && centres.dim * LANES <= block.len() {
        // SAFETY: the CPU has AVX2, and `block` holds `dim` channels of
        // `LANES` lanes.
        unsafe { avx2::each_centre_dots(block, centres, f) };
        return;
    }
    portable_each_centre_dots(block, centres, f);
}

/// [`each_centre_dots`] on any CPU.
#[inline(always)]
fn portable_each_centre_dots(block: &[f32], centres: &Centroids, mut f: impl FnMut(usize, &[f32; LANES])) {
    let k = centres.len();
    let quads = k / 4;
    for q in 0..quads {
        let c = [0, 1, 2, 3].map(|j| centres.row(4 * q + j));
        let mut acc = [[0.0f32; LANES]; 4];
        for (ch, b) in block.chunks_exact(LANES).enumerate().take(centres.dim) {
            let w = [c[0][ch], c[1][ch], c[2][ch], c[3][ch]];
            for j in 0..4 {
                for l in 0..LANES {
                    acc[j][l] += b[l] * w[j];
                }
            }
        }
        for (j, a) in acc.iter().enumerate() {
            f(4 * q + j, a);
        }
    }
    for j in 4 * quads..k {
        f(j, &lane_dots(block, centres.row(j)));
    }
}

/// The lane sums of [`each_centre_dots`] with AVX2 intrinsics: per lane
/// the same products added in the same order (a multiply, then an add:
/// no fused multiply-add), so bit for bit the portable results. LLVM did
/// not vectorise the portable loop cleanly even when built for AVX2
/// (the accumulators went through the stack).
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{Centroids, LANES};
    use std::arch::x86_64::*;

    /// # Safety
    /// The CPU must have AVX2, and `block` at least `centres.dim · LANES`
    /// values.
    #[target_feature(enable = "avx2")]
    pub unsafe fn each_centre_dots(block: &[f32], centres: &Centroids, mut f: impl FnMut(usize, &[f32; LANES])) {
        const _: () = assert!(LANES == 8);
        let (k, dim) = (centres.len(), centres.dim);
        let b = block.as_ptr();
        let mut out = [0.0f32; LANES];
        let mut j = 0;
        while j + 4 <= k {
            let c = [0, 1, 2, 3].map(|i| centres.row(j + i).as_ptr());
            let mut acc = [_mm256_setzero_ps(); 4];
            for ch in 0..dim {
                let x = _mm256_loadu_ps(b.add(ch * LANES));
                for i in 0..4 {
                    let w = _mm256_set1_ps(*c[i].add(ch));
                    acc[i] = _mm256_add_ps(acc[i], _mm256_mul_ps(x, w));
                }
            }
            for (i, a) in acc.iter().enumerate() {
                _mm256_storeu_ps(out.as_mut_ptr(), *a);
                f(j + i, &out);
            }
            j += 4;
        }
        for j in j..k {
            let c = centres.row(j).as_ptr();
            let mut acc = _mm256_setzero_ps();
            for ch in 0..dim {
                let x = _mm256_loadu_ps(b.add(ch * LANES));
                acc = _mm256_add_ps(acc, _mm256_mul_ps(x, _mm256_set1_ps(*c.add(ch))));
            }
            _mm256_storeu_ps(out.as_mut_ptr(), acc);
            f(j, &out);
        }
    }
}

/// min_k ‖φ̂ − c_k‖² of the `LANES` rows in `block` (channel-major), each
/// as ‖φ̂‖² − 2 φ·c_k/‖φ‖ + ‖c_k‖² from its 1/‖φ‖ in `inv` (0 for a zero
/// feature, whose ‖φ̂‖² is 0). The lanes' norms are read once per block,
/// not once per centre: per centre the update is then eight independent
/// lanes that vectorise (it had cost half as much as the dot products).
#[inline(always)]
fn lane_min_distances(block: &[f32], centres: &Centroids, norms: &[f32], inv: &[f32; LANES]) -> [f32; LANES] {
    let self_n: [f32; LANES] = inv.map(|i| if i > 0.0 { 1.0 } else { 0.0 });
    let mut best = [f32::INFINITY; LANES];
    each_centre_dots(block, centres, |k, acc| {
        let nk = norms[k];
        for l in 0..LANES {
            best[l] = best[l].min((self_n[l] - 2.0 * acc[l] * inv[l] + nk).max(0.0));
        }
    });
    best
}

/// The exact distances min_k ‖φ̂ − c_k‖², as ‖φ̂‖² − 2 φ̂·c_k + ‖c_k‖²,
/// bit for bit those of [`CentreSet::min_distance`].
struct Exact<'a> {
    cache: &'a FeatureCache,
    centres: &'a Centroids,
    norms: &'a [f32],
}

impl Exact<'_> {
    /// d_k given the raw dot product φ·c_k and 1/‖φ‖ (‖φ̂‖² = 1, or 0 for
    /// a zero feature).
    #[inline]
    fn distance(&self, dot: f32, inv: f32, k: usize) -> f32 {
        let self_n = if inv > 0.0 { 1.0 } else { 0.0 };
        (self_n - 2.0 * dot * inv + self.norms[k]).max(0.0)
    }

    /// One cache row.
    fn one(&self, r: usize) -> f32 {
        let phi = self.cache.row(r);
        (0..self.centres.len())
            .map(|k| {
                let dot: f32 = phi.iter().zip(self.centres.row(k)).map(|(a, b)| a * b).sum();
                self.distance(dot, self.cache.inv_norm[r], k)
            })
            .fold(f32::INFINITY, f32::min)
    }

    /// `LANES` consecutive cache rows from `r0`: transposes them into
    /// `block` (channel-major) and measures every centre against all lanes
    /// at once.
    fn block(&self, r0: usize, block: &mut [f32]) -> [f32; LANES] {
        let c = self.cache.channels;
        let rows = &self.cache.feats[r0 * c..(r0 + LANES) * c];
        for (l, row) in rows.chunks_exact(c).enumerate() {
            for (ch, &v) in row.iter().enumerate() {
                block[ch * LANES + l] = v;
            }
        }
        let inv: [f32; LANES] = std::array::from_fn(|l| self.cache.inv_norm[r0 + l]);
        lane_min_distances(block, self.centres, self.norms, &inv)
    }
}

/// Centres with their squared norms, for distances from single cache rows
/// (growth tests voxels one at a time, as it reaches them).
#[derive(Clone, Debug)]
pub struct CentreSet {
    pub centres: Centroids,
    pub(super) norms: Vec<f32>,
    /// The centres transposed for [`CentreSet::min_distance`].
    blocks: CentreBlocks,
}

impl CentreSet {
    pub fn new(centres: Centroids) -> Self {
        let norms = (0..centres.len())
            .map(|k| centres.row(k).iter().map(|x| x * x).sum())
            .collect();
        let blocks = CentreBlocks::new(&centres.data, centres.dim);
        CentreSet { centres, norms, blocks }
    }
    /// ‖φ̂ − c_k‖² of cache row `r` for every centre k, as ‖φ̂‖² − 2 φ̂·c + ‖c‖².
    fn distances<'a>(&'a self, cache: &'a FeatureCache, r: usize) -> impl Iterator<Item = f32> + 'a {
        let (phi, inv) = (cache.row(r), cache.inv_norm[r]);
        let self_n = if inv > 0.0 { 1.0 } else { 0.0 };
        (0..self.centres.len()).map(move |k| {
            let dot: f32 = phi.iter().zip(self.centres.row(k)).map(|(a, b)| a * b).sum();
            (self_n - 2.0 * dot * inv + self.norms[k]).max(0.0)
        })
    }
    /// The smallest squared distance (infinity without centres), the
    /// centres' dot products taken side by side (bit for bit those of
    /// [`CentreSet::distances`]: the stable flood calls this once per
    /// voxel it reaches).
    pub fn min_distance(&self, cache: &FeatureCache, r: usize) -> f32 {
        if self.centres.dim != cache.channels {
            return self.distances(cache, r).fold(f32::INFINITY, f32::min);
        }
        let inv = cache.inv_norm[r];
        let self_n = if inv > 0.0 { 1.0 } else { 0.0 };
        let mut best = f32::INFINITY;
        self.blocks.dots(cache.row(r), |k, dot| {
            best = best.min((self_n - 2.0 * dot * inv + self.norms[k]).max(0.0));
        });
        best
    }
    /// [`CentreSet::min_distance`] of each of `rows`, bit for bit, eight
    /// rows at a time (channel-major, so the sums vectorise across rows
    /// while each keeps the plain loop's order), in parallel.
    pub fn min_distances(&self, cache: &FeatureCache, rows: &[usize]) -> Vec<f32> {
        rows.par_chunks(4096)
            .flat_map_iter(|chunk| min_distances_of(self, cache, chunk))
            .collect()
    }
    /// Whether some centre is closer than `t` (stops at the first).
    pub fn any_within(&self, cache: &FeatureCache, r: usize, t: f32) -> bool {
        self.distances(cache, r).any(|d| d < t)
    }
}

/// [`CentreSet::min_distances`] of one chunk of rows.
fn min_distances_of(set: &CentreSet, cache: &FeatureCache, chunk: &[usize]) -> Vec<f32> {
    let c = cache.channels;
    let mut out = Vec::with_capacity(chunk.len());
    let mut block = vec![0.0f32; c * LANES];
    for group in chunk.chunks(LANES) {
        if group.len() < LANES || set.centres.dim != c {
            out.extend(group.iter().map(|&r| set.min_distance(cache, r)));
            continue;
        }
        for (l, &r) in group.iter().enumerate() {
            for (ch, &v) in cache.row(r).iter().enumerate() {
                block[ch * LANES + l] = v;
            }
        }
        let inv: [f32; LANES] = std::array::from_fn(|l| cache.inv_norm[group[l]]);
        out.extend_from_slice(&lane_min_distances(&block, &set.centres, &set.norms, &inv));
    }
    out
}

/// Minimum squared distance of every cached voxel to the centres (for soft
/// scores and tests); `f32::INFINITY` below the floor.
pub fn nnfm_distances(cache: &FeatureCache, centres: &Centroids, floor: f32) -> Vec<f32> {
    (0..cache.len())
        .into_par_iter()
        .map(|r| {
            if cache.sigma[r] <= floor || centres.is_empty() {
                return f32::INFINITY;
            }
            let inv = cache.inv_norm[r];
            let phi = cache.row(r);
            (0..centres.len())
                .map(|k| {
                    phi.iter()
                        .zip(centres.row(k))
                        .map(|(a, b)| (a * inv - b) * (a * inv - b))
                        .sum::<f32>()
                })
                .fold(f32::INFINITY, f32::min)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{Aabb, FieldBuilder};
    use crate::util::SplitMix64;
    use glam::Vec3;

    #[test]
    fn batched_distances_equal_the_single_row_ones_bit_for_bit() {
        // 12 channels: one full lane of 8 plus a remainder; some voxels with
        // a zero feature.
        let feat = |p: Vec3, out: &mut [f32]| {
            for (c, o) in out.iter_mut().enumerate() {
                *o = if p.x > 0.8 {
                    0.0
                } else {
                    (3.0 * p.x + 1.7 * p.y * c as f32 - p.z).sin()
                };
            }
        };
        let field = FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [13; 3]).build(
            |_| 1.0,
            |_| Vec3::ONE,
            Some((12, &feat)),
        );
        let cache = FeatureCache::build(&field).unwrap();
        let mut rng = SplitMix64::new(3);
        let dim = cache.channels;
        // 5 centres: one partial block; 11: a full block and a partial one.
        for k in [5, 11] {
            let centres = Centroids {
                dim,
                data: (0..k * dim).map(|_| rng.unit() as f32 - 0.5).collect(),
            };
            let set = CentreSet::new(centres);
            // Rows in any order, with repeats, and a tail shorter than a block.
            let rows: Vec<usize> = (0..1003).map(|_| rng.below(cache.len())).collect();
            let batch = set.min_distances(&cache, &rows);
            assert_eq!(batch.len(), rows.len());
            for (&r, &d) in rows.iter().zip(&batch) {
                let single = set.min_distance(&cache, r);
                assert_eq!(d.to_bits(), single.to_bits(), "row {r}");
                // The single row's side-by-side centres against one at a time.
                let plain = set.distances(&cache, r).fold(f32::INFINITY, f32::min);
                assert_eq!(single.to_bits(), plain.to_bits(), "row {r}, {k} centres");
            }
        }
    }

    #[test]
    fn merged_stroke_distances_are_the_distances_to_all_centres() {
        let feat = |p: Vec3, out: &mut [f32]| {
            for (c, o) in out.iter_mut().enumerate() {
                *o = (2.1 * p.x - 1.3 * p.y * c as f32 + 0.4 * p.z).sin();
            }
        };
        let field = FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [15; 3]).build(
            |p| if p.y < 0.5 { 1.0 } else { 0.0 },
            |_| Vec3::ONE,
            Some((10, &feat)),
        );
        let cache = FeatureCache::build(&field).unwrap();
        let mut rng = SplitMix64::new(9);
        let unit = |r: usize| -> Vec<f32> { cache.row(r).iter().map(|v| v * cache.inv_norm[r]).collect() };
        let strokes: Vec<Centroids> = [3usize, 10, 1]
            .iter()
            .map(|&k| Centroids {
                dim: 10,
                data: (0..k).flat_map(|_| unit(rng.below(cache.len()))).collect(),
            })
            .collect();
        // Each stroke measures what its seed pass measures (a tight θ
        // leaves many rows to the cheap bound, unmeasured).
        let mut merged: Option<StrokeDistances> = None;
        let mut all = Centroids { dim: 10, data: vec![] };
        for c in &strokes {
            let (_, d) = nnfm_seed_with_distances(&cache, c, 0.05, 0.5);
            all.data.extend_from_slice(&c.data);
            match &mut merged {
                Some(m) => m.merge(&cache, d),
                none => *none = Some(d),
            }
        }
        let mut merged = merged.unwrap();
        assert_eq!(merged.centres(), &all);
        let set = CentreSet::new(all);
        let rows: Vec<usize> = (0..cache.len()).collect();
        let unknown = rows.iter().filter(|&&r| merged.d[r].is_nan()).count();
        assert!(
            unknown > 0 && unknown < rows.len(),
            "{unknown} of {} rows unmeasured",
            rows.len()
        );
        for (&r, d) in rows.iter().zip(merged.of_rows(&cache, &rows)) {
            assert_eq!(d.to_bits(), set.min_distance(&cache, r).to_bits(), "row {r}");
        }
    }

    /// The plain per-voxel loop the blocked, pruned version replaces.
    fn reference(cache: &FeatureCache, centres: &Centroids, theta: f32, floor: f32) -> Bitmap {
        let norms: Vec<f32> = (0..centres.len())
            .map(|k| centres.row(k).iter().map(|x| x * x).sum())
            .collect();
        let mut bits = Bitmap::new(cache.geom.res);
        for r in 0..cache.len() {
            if cache.sigma[r] <= floor {
                continue;
            }
            let inv = cache.inv_norm[r];
            let self_n = if inv > 0.0 { 1.0 } else { 0.0 };
            let hit = (0..centres.len()).any(|k| {
                let dot: f32 = cache.row(r).iter().zip(centres.row(k)).map(|(a, b)| a * b).sum::<f32>() * inv;
                self_n - 2.0 * dot + norms[k] < theta
            });
            bits.set(cache.voxels[r] as usize, hit);
        }
        bits
    }

    fn prune_of(centres: &Centroids, theta: f32) -> Prune {
        let norms: Vec<f32> = (0..centres.len())
            .map(|j| centres.row(j).iter().map(|x| x * x).sum())
            .collect();
        Prune::new(centres, &norms, theta, centres.dim)
    }

    #[test]
    fn blocked_pruned_seed_equals_the_plain_loop() {
        let mut rng = SplitMix64::new(7);
        let dirs: Vec<[f32; 20]> = (0..5).map(|_| [(); 20].map(|_| rng.unit() as f32 - 0.5)).collect();
        // 20 channels: two full lanes of 8 plus a remainder of 4.
        let feat = |p: Vec3, out: &mut [f32]| {
            let w = [p.x, p.y, p.z, p.x * p.y, 0.3];
            for (c, o) in out.iter_mut().enumerate() {
                *o = (0..5).map(|i| w[i] * dirs[i][c]).sum::<f32>() + 0.05 * (9.0 * p.z + c as f32).sin();
            }
        };
        let f = FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [21; 3]).build(
            |p| if p.length() < 0.9 { 0.05 + p.x.abs() } else { 0.0 },
            |_| Vec3::ONE,
            Some((20, &feat)),
        );
        let cache = FeatureCache::build(&f).unwrap();
        let unit = |r: usize| -> Vec<f32> { cache.row(r).iter().map(|v| v * cache.inv_norm[r]).collect() };
        let (mut checked, mut ruled_out) = (0, 0);
        for k in [1usize, 3, 10] {
            let data: Vec<f32> = (0..k).flat_map(|_| unit(rng.below(cache.len()))).collect();
            let centres = Centroids { dim: 20, data };
            let norms: Vec<f32> = (0..k).map(|j| centres.row(j).iter().map(|x| x * x).sum()).collect();
            let prune = Prune::new(&centres, &norms, 0.4, 20);
            ruled_out += (0..cache.len()).filter(|&r| prune.rules_out(&cache, r)).count();
            let set = CentreSet::new(centres.clone());
            for theta in [0.05f32, 0.2, 0.4, 0.8, 1.5] {
                for floor in [0.0f32, 0.3] {
                    let want = reference(&cache, &centres, theta, floor);
                    let (seed, mut dist) = nnfm_seed_with_distances(&cache, &centres, theta, floor);
                    assert_eq!(seed, want, "k {k} theta {theta}");
                    checked += want.count();
                    // Every distance the seed measured, and every one
                    // measured later, is the single-row one to the bit;
                    // rows below the floor are left for later.
                    for r in 0..cache.len() {
                        let measured = !dist.d[r].is_nan();
                        assert!(measured || cache.sigma[r] <= floor || prune_of(&centres, theta).rules_out(&cache, r));
                        assert_eq!(dist.get(&cache, r).to_bits(), set.min_distance(&cache, r).to_bits());
                    }
                    // Without the bound: the same seed, and every row above
                    // the floor measured already, to the same bits.
                    let (all_seed, all) = nnfm_seed_measuring_all(&cache, &centres, theta, floor);
                    assert_eq!(all_seed, want, "k {k} theta {theta}, measuring all");
                    for r in 0..cache.len() {
                        let d = all.d[r];
                        match cache.sigma[r] > floor {
                            true => assert_eq!(d.to_bits(), set.min_distance(&cache, r).to_bits()),
                            false => assert!(d.is_nan(), "rows below the floor stay unmeasured"),
                        }
                    }
                }
            }
        }
        assert!(checked > 0, "some voxels must match");
        assert!(ruled_out > 0, "the pruning path must be exercised");
    }
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_avx2_dots_are_the_portable_dots_bit_for_bit() {
        if !crate::util::has_avx2() {
            eprintln!("skipped: this CPU has no AVX2");
            return;
        }
        let mut rng = SplitMix64::new(7);
        let mut rnd = move || rng.unit() as f32 - 0.5;
        // Centre counts around the four-centre passes, several widths.
        for (k, dim) in [(1, 64), (4, 64), (7, 64), (20, 64), (13, 3), (9, 17)] {
            let centres = Centroids {
                dim,
                data: (0..k * dim).map(|_| rnd()).collect(),
            };
            let block: Vec<f32> = (0..dim * LANES).map(|_| rnd() * 40.0).collect();
            let (mut want, mut got) = (vec![], vec![]);
            portable_each_centre_dots(&block, &centres, |j, a| want.push((j, a.map(f32::to_bits))));
            // SAFETY: checked above; the block holds dim × LANES values.
            unsafe { avx2::each_centre_dots(&block, &centres, |j, a| got.push((j, a.map(f32::to_bits)))) };
            assert_eq!(got, want, "k {k}, dim {dim}");
        }
    }
}
