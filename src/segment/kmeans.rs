//! K-means with k-means++ seeding over unit-length stroke features.
//! Deterministic for a seed; K is clamped to the number of distinct points.

use crate::util::SplitMix64;
use rayon::prelude::*;

/// Points per rayon task in the distance passes: stroke-sized inputs (a few
/// hundred points) stay on one thread, background samples (20k) split.
const MIN_TASK: usize = 2048;

/// Result: `k × dim` centres, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Centroids {
    pub dim: usize,
    pub data: Vec<f32>,
}

impl Centroids {
    pub fn len(&self) -> usize {
        self.data.len() / self.dim.max(1)
    }
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
    pub fn row(&self, k: usize) -> &[f32] {
        &self.data[k * self.dim..(k + 1) * self.dim]
    }
}

#[inline]
pub fn dist2(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// Width of the side-by-side distance kernels of segmentation (centres per
/// block here, voxels per block in NNFM, neighbours per group in growth):
/// eight f32 lanes, two SSE registers on the plain x86-64 target. Each lane
/// sums its channels in the order of a plain loop, so results are
/// bit-identical to it, while the compiler vectorises across the lanes.
pub(crate) const LANES: usize = 8;

/// `rows` (`dim` wide) transposed into blocks of [`LANES`] rows,
/// channel-major within a block, the last block padded with zeros.
fn transposed(rows: &[f32], dim: usize) -> Vec<f32> {
    let n = rows.len() / dim.max(1);
    let mut data = vec![0.0; n.div_ceil(LANES) * dim * LANES];
    for (i, row) in rows.chunks_exact(dim.max(1)).enumerate() {
        let (b, lane) = (i / LANES, i % LANES);
        for (j, &v) in row.iter().enumerate() {
            data[(b * dim + j) * LANES + lane] = v;
        }
    }
    data
}

/// The centres transposed into blocks of [`LANES`] (channel-major within a
/// block, the last block padded), so that one point's distances to a
/// block's centres are computed lane by lane: each lane still sums its
/// channels in order, as `dist2` does (bit-identical), and the lanes
/// vectorise. The plain row-by-row loop is a serial float reduction the
/// compiler cannot vectorise; on the fern's strokes the background
/// model's K-means spent a quarter of the segmentation time in it.
#[derive(Clone, Debug)]
pub(crate) struct CentreBlocks {
    k: usize,
    dim: usize,
    data: Vec<f32>,
}

impl CentreBlocks {
    pub(crate) fn new(centres: &[f32], dim: usize) -> Self {
        CentreBlocks {
            k: centres.len() / dim.max(1),
            dim,
            data: transposed(centres, dim),
        }
    }

    /// The nearest centre to `p` and its squared distance (the first one
    /// on ties, as a scan in centre order).
    #[cfg(test)]
    fn nearest(&self, p: &[f32]) -> (usize, f32) {
        let (k, d, _) = self.nearest2(p);
        (k, d)
    }

    /// [`Self::nearest`], and the squared distance to the second nearest
    /// centre (infinite with one centre).
    fn nearest2(&self, p: &[f32]) -> (usize, f32, f32) {
        let mut best = (0, f32::INFINITY, f32::INFINITY);
        self.each_distance(p, |k, d| {
            if d < best.1 {
                best = (k, d, best.1);
            } else if d < best.2 {
                best.2 = d;
            }
        });
        best
    }

    /// Calls `f(k, |p − c_k|²)` for every centre in order (each summed
    /// over the channels in order, as [`dist2`]), up to [`GROUP`] blocks of
    /// centres at a time ([`with_lane_distances`]).
    #[inline(always)]
    fn each_distance(&self, p: &[f32], mut f: impl FnMut(usize, f32)) {
        let stride = self.dim * LANES;
        let blocks = self.data.len() / stride.max(1);
        let mut b = 0;
        while b < blocks {
            let count = (blocks - b).min(GROUP);
            let first = b * LANES;
            with_lane_distances(&self.data[b * stride..], self.dim, p, count, |d| {
                // The padding lanes of the last block left out.
                for (i, &d) in d.iter().flatten().enumerate().take(self.k - first) {
                    f(first + i, d);
                }
            });
            b += count;
        }
    }

    /// Calls `f(k, p·c_k)` for every centre in order, each dot product
    /// summed over the channels in order (as a plain zip-sum would be).
    pub(crate) fn dots(&self, p: &[f32], mut f: impl FnMut(usize, f32)) {
        for (b, block) in self.data.chunks_exact((self.dim * LANES).max(1)).enumerate() {
            let mut acc = [0.0f32; LANES];
            for (lanes, &x) in block.chunks_exact(LANES).zip(p) {
                for l in 0..LANES {
                    acc[l] += x * lanes[l];
                }
            }
            for (l, &d) in acc.iter().enumerate().take(self.k - b * LANES) {
                f(b * LANES + l, d);
            }
        }
    }
}

/// Per lane l of each of the `G` blocks at the start of `blocks` (each
/// `dim` rows of [`LANES`] values), Σ_j (block_jl − x_j)², summed over j in
/// order as [`dist2`] sums it: a lane is a centre against a point
/// ([`CentreBlocks`]) or a point against a centre ([`PointLanes`]). With
/// AVX2 the `G` blocks are summed side by side, eight lanes to an
/// instruction ([`avx2::lane_distances`]): one block's sum is a chain of
/// dependent adds, bound by the add's latency, and a background model's
/// twenty centres are three chains that overlap. (Written portably, LLVM
/// shuffled the side-by-side accumulators through the stack and ran
/// slower than one block at a time.)
#[inline(always)]
fn lane_distances<const G: usize>(blocks: &[f32], dim: usize, x: &[f32]) -> [[f32; LANES]; G] {
    assert!(blocks.len() >= G * dim * LANES && x.len() >= dim);
    #[cfg(target_arch = "x86_64")]
    if crate::util::has_avx2() {
        // SAFETY: the CPU has AVX2, and the lengths are checked above.
        return unsafe { avx2::lane_distances::<G>(blocks, dim, x) };
    }
    portable_lane_distances(blocks, dim, x)
}

/// Hands `f` the [`lane_distances`] of the first `count` (1 to [`GROUP`])
/// blocks of `blocks`.
#[inline(always)]
fn with_lane_distances(blocks: &[f32], dim: usize, x: &[f32], count: usize, f: impl FnOnce(&[[f32; LANES]])) {
    match count {
        1 => f(&lane_distances::<1>(blocks, dim, x)),
        2 => f(&lane_distances::<2>(blocks, dim, x)),
        3 => f(&lane_distances::<3>(blocks, dim, x)),
        _ => f(&lane_distances::<GROUP>(blocks, dim, x)),
    }
}

/// [`lane_distances`] on any CPU, one block at a time.
#[inline(always)]
fn portable_lane_distances<const G: usize>(blocks: &[f32], dim: usize, x: &[f32]) -> [[f32; LANES]; G] {
    std::array::from_fn(|g| {
        let mut acc = [0.0f32; LANES];
        for (lanes, &xj) in blocks[g * dim * LANES..(g + 1) * dim * LANES]
            .chunks_exact(LANES)
            .zip(x)
        {
            for l in 0..LANES {
                let e = lanes[l] - xj;
                acc[l] += e * e;
            }
        }
        acc
    })
}

/// [`lane_distances`] with AVX2 intrinsics: per lane the same subtraction,
/// product and sum in the same order (no fused multiply-add), so bit for
/// bit the portable results.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::LANES;
    use std::arch::x86_64::*;

    /// # Safety
    /// The CPU must have AVX2; `blocks` holds at least `G · dim · LANES`
    /// values and `x` at least `dim`.
    #[target_feature(enable = "avx2")]
    pub unsafe fn lane_distances<const G: usize>(blocks: &[f32], dim: usize, x: &[f32]) -> [[f32; LANES]; G] {
        const _: () = assert!(LANES == 8);
        let b = blocks.as_ptr();
        let mut acc = [_mm256_setzero_ps(); G];
        for j in 0..dim {
            let xj = _mm256_set1_ps(*x.get_unchecked(j));
            for (g, a) in acc.iter_mut().enumerate() {
                let e = _mm256_sub_ps(_mm256_loadu_ps(b.add((g * dim + j) * LANES)), xj);
                *a = _mm256_add_ps(*a, _mm256_mul_ps(e, e));
            }
        }
        let mut out = [[0.0f32; LANES]; G];
        for (o, a) in out.iter_mut().zip(acc) {
            _mm256_storeu_ps(o.as_mut_ptr(), a);
        }
        out
    }
}

/// Blocks of centres (or groups of points) summed side by side.
const GROUP: usize = 4;

/// When Lloyd iterations stop: when no assignment changes, after
/// `max_iters`, or (with `tol` > 0) once no centre moved farther than `tol`
/// times the points' RMS distance to their mean.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stop {
    pub max_iters: usize,
    pub tol: f32,
}

impl Stop {
    /// Until assignments settle (or `max_iters`).
    pub fn exact(max_iters: usize) -> Self {
        Stop { max_iters, tol: 0.0 }
    }
}

/// k-means++ initialisation then Lloyd iterations until assignments stop
/// changing or `max_iters` is reached. `points` is `n × dim`.
pub fn kmeans(points: &[f32], dim: usize, k: usize, seed: u64, max_iters: usize) -> Centroids {
    kmeans_until(points, dim, k, seed, Stop::exact(max_iters))
}

/// [`kmeans`] with a stopping rule.
pub fn kmeans_until(points: &[f32], dim: usize, k: usize, seed: u64, stop: Stop) -> Centroids {
    let n = points.len().checked_div(dim).unwrap_or(0);
    if n == 0 || k == 0 {
        return Centroids { dim, data: vec![] };
    }
    let row = |i: usize| &points[i * dim..(i + 1) * dim];
    let mut rng = SplitMix64::new(seed);
    // k-means++: first centre uniformly, then proportional to squared distance.
    let mut centres: Vec<f32> = row(rng.below(n)).to_vec();
    let mut d2 = vec![f32::INFINITY; n];
    let lanes = PointLanes::new(points, dim);
    nearer_of(&lanes, &centres[..dim], &mut d2);
    while centres.len() / dim < k {
        let total: f64 = d2.iter().map(|&d| d as f64).sum();
        if total <= 1e-12 {
            break; // every point coincides with a centre: fewer distinct points than K
        }
        let mut target = rng.unit() * total;
        let mut pick = n - 1;
        for (i, &d) in d2.iter().enumerate() {
            target -= d as f64;
            if target <= 0.0 && d > 0.0 {
                pick = i;
                break;
            }
        }
        let start = centres.len();
        centres.extend_from_slice(row(pick));
        nearer_of(&lanes, &centres[start..], &mut d2);
    }
    lloyd(points, dim, centres, stop)
}

/// [`kmeans_until`] from `draws` k-means++ draws (seeds `seed`, `seed + 1`,
/// …), keeping the centres of least [`inertia`]: one draw can settle in a
/// poor local minimum (a centre spent on a few outliers), and what is
/// built on the centres then depends on the seed. Lego's stroke colours
/// (five centres): one draw in eight left the yellow body without a centre
/// (inertia 103 against 80) and flagged 57 % of the model unlike the
/// stroke instead of 42 %, which sent its cut down the path for floods
/// into other things (alpha IoU 0.605 instead of 0.996).
pub fn kmeans_best_of(points: &[f32], dim: usize, k: usize, seed: u64, stop: Stop, draws: usize) -> Centroids {
    let n = points.len().checked_div(dim).unwrap_or(0);
    if draws <= 1 || n == 0 {
        return kmeans_until(points, dim, k, seed, stop);
    }
    // The draws compete on a strided sample; the winner is then fitted to
    // every point from where it stands.
    let stride = n.div_ceil(DRAW_ROWS).max(1);
    let sample: std::borrow::Cow<[f32]> = match stride {
        1 => points.into(),
        _ => (points.chunks_exact(dim).step_by(stride).flatten().copied())
            .collect::<Vec<f32>>()
            .into(),
    };
    let mut best = kmeans_until(&sample, dim, k, seed, stop);
    let mut least = inertia(&sample, &best);
    for d in 1..draws as u64 {
        let c = kmeans_until(&sample, dim, k, seed.wrapping_add(d), stop);
        let e = inertia(&sample, &c);
        // Strictly less: ties keep the earliest draw.
        if e < least {
            (best, least) = (c, e);
        }
    }
    match stride {
        1 => best,
        _ => kmeans_from(points, &best, stop),
    }
}

/// Most rows the draws of [`kmeans_best_of`] compete on: enough that a
/// centre spent on outliers shows in the inertia (lego: 25 % more), few
/// enough that eight draws cost what one fit of the whole set does.
const DRAW_ROWS: usize = 1_000;

/// K-means' objective: the sum over `points` of the squared distance to
/// the nearest centre (0 for no points; infinite for no centres).
pub fn inertia(points: &[f32], centres: &Centroids) -> f64 {
    let dim = centres.dim;
    if dim == 0 || points.is_empty() {
        return 0.0;
    }
    let lanes = PointLanes::new(points, dim);
    let mut d2 = vec![f32::INFINITY; points.len() / dim];
    for k in 0..centres.len() {
        nearer_of(&lanes, centres.row(k), &mut d2);
    }
    d2.iter().map(|&d| d as f64).sum()
}

/// Points transposed into groups of [`LANES`] (channel-major within a
/// group, the last group padded with zeros), so that a k-means++ pass
/// loads one channel of eight points as one vector: gathered from eight
/// rows, the loads bound the K passes (10 ms of a fern background fit).
struct PointLanes {
    dim: usize,
    data: Vec<f32>,
}

impl PointLanes {
    fn new(points: &[f32], dim: usize) -> Self {
        PointLanes {
            dim,
            data: transposed(points, dim),
        }
    }
}

/// Lowers each `d2[i]` to point i's squared distance to `c` (as [`dist2`]
/// sums it: each lane adds its channels in order), in parallel, up to
/// [`GROUP`] groups of points side by side (one group's sum is a chain of
/// dependent adds).
fn nearer_of(points: &PointLanes, c: &[f32], d2: &mut [f32]) {
    const _: () = assert!(MIN_TASK.is_multiple_of(LANES * GROUP));
    d2.par_chunks_mut(MIN_TASK).enumerate().for_each(|(t, d)| {
        let first = t * MIN_TASK / LANES;
        for (q, out) in d.chunks_mut(LANES * GROUP).enumerate() {
            let groups = &points.data[(first + q * GROUP) * points.dim * LANES..];
            with_lane_distances(groups, points.dim, c, out.len().div_ceil(LANES), |d| {
                // The last group perhaps in part.
                for (o, a) in out.iter_mut().zip(d.iter().flatten()) {
                    *o = o.min(*a);
                }
            });
        }
    });
}

/// Lloyd iterations over `points` started from `start` (the centres of a
/// similar set, e.g. the last round's background): they converge in a
/// few iterations where fresh k-means++ centres take tens; `start` itself
/// for no points.
pub fn kmeans_from(points: &[f32], start: &Centroids, stop: Stop) -> Centroids {
    if points.is_empty() || start.is_empty() || start.dim == 0 {
        return start.clone();
    }
    lloyd(points, start.dim, start.data.clone(), stop)
}

/// Lloyd iterations from `centres` until `stop` says so.
fn lloyd(points: &[f32], dim: usize, mut centres: Vec<f32>, stop: Stop) -> Centroids {
    let n = points.len() / dim;
    let row = |i: usize| &points[i * dim..(i + 1) * dim];
    let kk = centres.len() / dim;
    let mut assign = vec![usize::MAX; n];
    let mut bounds = vec![Bounds::UNKNOWN; n];
    let mut shift = CentreShift::none(kk);
    let settled = if stop.tol > 0.0 {
        stop.tol * rms_spread(points, dim)
    } else {
        0.0
    };
    for _ in 0..stop.max_iters {
        let blocks = CentreBlocks::new(&centres, dim);
        let half_gap = half_gaps(&centres, dim);
        // Each point's nearest centre on its own (the same sums as one
        // thread, so the result does not depend on the thread count).
        let changed = assign
            .par_iter_mut()
            .zip(bounds.par_iter_mut())
            .with_min_len(MIN_TASK)
            .enumerate()
            .map(|(i, (a, b))| {
                let best = b.nearest(*a, row(i), &blocks, &centres, &half_gap, &shift);
                let moved = *a != best;
                *a = best;
                moved
            })
            .reduce(|| false, |x, y| x || y);
        if !changed {
            break;
        }
        let old = centres.clone();
        let mut sum = vec![0.0f64; kk * dim];
        let mut count = vec![0usize; kk];
        for i in 0..n {
            count[assign[i]] += 1;
            for (s, &v) in sum[assign[i] * dim..(assign[i] + 1) * dim].iter_mut().zip(row(i)) {
                *s += v as f64;
            }
        }
        for c in 0..kk {
            // An empty cluster keeps its centre (it cannot happen for k-means++
            // centres that are data points, but stay safe).
            if count[c] > 0 {
                for j in 0..dim {
                    centres[c * dim + j] = (sum[c * dim + j] / count[c] as f64) as f32;
                }
            }
        }
        shift = CentreShift::between(&old, &centres, dim);
        if shift.top.0 < settled {
            break;
        }
    }
    Centroids { dim, data: centres }
}

/// The RMS distance of `points` to their mean.
fn rms_spread(points: &[f32], dim: usize) -> f32 {
    let n = (points.len() / dim).max(1) as f64;
    let mut mean = vec![0.0f64; dim];
    for p in points.chunks_exact(dim) {
        for (m, &v) in mean.iter_mut().zip(p) {
            *m += v as f64;
        }
    }
    mean.iter_mut().for_each(|m| *m /= n);
    let sq: f64 = points
        .chunks_exact(dim)
        .map(|p| p.iter().zip(&mean).map(|(&v, m)| (v as f64 - m).powi(2)).sum::<f64>())
        .sum();
    (sq / n).sqrt() as f32
}

/// Hamerly's bounds on a point's distances (not squared): an upper bound
/// on the distance to its assigned centre and a lower bound on the
/// distance to every other centre. While the first stays below the second
/// (and below half the gap from its centre to the nearest other one) the
/// assignment cannot change and the point's K distances need not be
/// summed; later Lloyd iterations skip most points that way. The test
/// keeps a margin far above f32 rounding, so a point is skipped only when
/// its centre is strictly the nearest, and the assignments and centres are
/// those of plain Lloyd iterations to the bit (tested).
#[derive(Clone, Copy)]
struct Bounds {
    upper: f32,
    lower: f32,
}

/// Slack on the bounds' test (distances between unit-scale points).
const BOUND_MARGIN: f32 = 1e-4;

impl Bounds {
    const UNKNOWN: Bounds = Bounds {
        upper: f32::INFINITY,
        lower: f32::NEG_INFINITY,
    };

    /// The nearest centre of `p` (assigned to `a` before the centres moved
    /// by `shift`), updating the bounds.
    fn nearest(
        &mut self,
        a: usize,
        p: &[f32],
        blocks: &CentreBlocks,
        centres: &[f32],
        half_gap: &[f32],
        shift: &CentreShift,
    ) -> usize {
        if a != usize::MAX {
            self.upper += shift.of[a];
            self.lower -= shift.largest_but(a);
            let bound = self.lower.max(half_gap[a]);
            if self.upper + BOUND_MARGIN < bound {
                return a;
            }
            // Tighten the upper bound to the exact distance and try again.
            let dim = p.len();
            self.upper = dist2(p, &centres[a * dim..(a + 1) * dim]).sqrt();
            if self.upper + BOUND_MARGIN < bound {
                return a;
            }
        }
        let (best, d1, d2) = blocks.nearest2(p);
        *self = Bounds {
            upper: d1.sqrt(),
            lower: d2.sqrt(),
        };
        best
    }
}

/// How far each centre moved in the last update, and the two largest moves.
struct CentreShift {
    of: Vec<f32>,
    /// The largest move and its centre, and the second largest.
    top: (f32, usize, f32),
}

impl CentreShift {
    fn none(k: usize) -> Self {
        CentreShift {
            of: vec![0.0; k],
            top: (0.0, usize::MAX, 0.0),
        }
    }

    fn between(old: &[f32], new: &[f32], dim: usize) -> Self {
        let of: Vec<f32> = old
            .chunks_exact(dim)
            .zip(new.chunks_exact(dim))
            .map(|(a, b)| dist2(a, b).sqrt())
            .collect();
        let mut top = (0.0, usize::MAX, 0.0);
        for (c, &d) in of.iter().enumerate() {
            if d > top.0 {
                top = (d, c, top.0);
            } else if d > top.2 {
                top.2 = d;
            }
        }
        CentreShift { of, top }
    }

    /// The largest move of a centre other than `a`.
    fn largest_but(&self, a: usize) -> f32 {
        if self.top.1 == a {
            self.top.2
        } else {
            self.top.0
        }
    }
}

/// Half the distance from each centre to its nearest other centre: a point
/// closer than that to its centre is nearest to it.
fn half_gaps(centres: &[f32], dim: usize) -> Vec<f32> {
    let k = centres.len() / dim.max(1);
    (0..k)
        .map(|a| {
            let ca = &centres[a * dim..(a + 1) * dim];
            let nearest = (0..k)
                .filter(|&b| b != a)
                .map(|b| dist2(ca, &centres[b * dim..(b + 1) * dim]))
                .fold(f32::INFINITY, f32::min);
            0.5 * nearest.sqrt()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The scan the blocks replace: every centre's `dist2`, first minimum.
    fn scan(centres: &[f32], dim: usize, p: &[f32]) -> (usize, f32) {
        centres
            .chunks_exact(dim)
            .enumerate()
            .map(|(k, r)| (k, dist2(r, p)))
            .fold((0, f32::INFINITY), |a, b| if b.1 < a.1 { b } else { a })
    }

    /// Plain Lloyd iterations from the same k-means++ seeding: every
    /// point's distance to every centre in every iteration.
    fn lloyd(points: &[f32], dim: usize, k: usize, seed: u64, max_iters: usize) -> Centroids {
        let seeded = kmeans(points, dim, k, seed, 0);
        let mut centres = seeded.data;
        let n = points.len() / dim;
        let kk = centres.len() / dim;
        let mut assign = vec![usize::MAX; n];
        for _ in 0..max_iters {
            let mut changed = false;
            for (i, a) in assign.iter_mut().enumerate() {
                let best = scan(&centres, dim, &points[i * dim..(i + 1) * dim]).0;
                changed |= *a != best;
                *a = best;
            }
            if !changed {
                break;
            }
            let mut sum = vec![0.0f64; kk * dim];
            let mut count = vec![0usize; kk];
            for i in 0..n {
                count[assign[i]] += 1;
                for (s, &v) in sum[assign[i] * dim..(assign[i] + 1) * dim]
                    .iter_mut()
                    .zip(&points[i * dim..])
                {
                    *s += v as f64;
                }
            }
            for c in (0..kk).filter(|&c| count[c] > 0) {
                for j in 0..dim {
                    centres[c * dim + j] = (sum[c * dim + j] / count[c] as f64) as f32;
                }
            }
        }
        Centroids { dim, data: centres }
    }

    #[test]
    fn side_by_side_distances_are_the_plain_sums_bit_for_bit() {
        let mut rng = SplitMix64::new(5);
        // Several rayon tasks, and a tail that is not a whole group of lanes.
        for (n, dim) in [(2 * MIN_TASK + 13, 64), (21, 3), (5, 7)] {
            let points: Vec<f32> = (0..n * dim).map(|_| rng.unit() as f32 - 0.5).collect();
            let c: Vec<f32> = (0..dim).map(|_| rng.unit() as f32 - 0.5).collect();
            let before: Vec<f32> = (0..n).map(|i| if i % 3 == 0 { 0.25 } else { f32::INFINITY }).collect();
            let mut got = before.clone();
            nearer_of(&PointLanes::new(&points, dim), &c, &mut got);
            for i in 0..n {
                let want = before[i].min(dist2(&points[i * dim..(i + 1) * dim], &c));
                assert_eq!(got[i].to_bits(), want.to_bits(), "n {n}, dim {dim}, point {i}");
            }
        }
    }

    #[test]
    fn bounded_iterations_give_the_plain_lloyd_centres_to_the_bit() {
        let mut rng = SplitMix64::new(11);
        // Unit features in blobs that overlap (many points near the
        // boundaries, where a wrong skip would show), and exact
        // duplicates (ties).
        for (n, dim, k, blobs) in [(3000, 64, 20, 12), (2000, 8, 10, 30), (500, 3, 7, 3), (300, 16, 1, 2)] {
            let mut centre_of_blob = vec![];
            for _ in 0..blobs {
                centre_of_blob.push((0..dim).map(|_| rng.unit() as f32 - 0.5).collect::<Vec<f32>>());
            }
            let mut points = Vec::with_capacity(n * dim);
            for i in 0..n {
                if i % 10 == 9 {
                    let copy = points[(i - 5) * dim..(i - 4) * dim].to_vec();
                    points.extend(copy);
                    continue;
                }
                let c = &centre_of_blob[i % blobs];
                let mut p: Vec<f32> = c.iter().map(|&x| x + 0.6 * (rng.unit() as f32 - 0.5)).collect();
                let norm = p.iter().map(|x| x * x).sum::<f32>().sqrt();
                p.iter_mut().for_each(|x| *x /= norm);
                points.extend(p);
            }
            for seed in 0..3 {
                let got = kmeans(&points, dim, k, seed, 50);
                let want = lloyd(&points, dim, k, seed, 50);
                assert_eq!(got.data.len(), want.data.len());
                let same = got.data.iter().zip(&want.data).all(|(a, b)| a.to_bits() == b.to_bits());
                assert!(same, "n {n}, dim {dim}, k {k}, seed {seed}");
            }
        }
    }

    #[test]
    fn warm_started_iterations_find_separated_clusters_and_keep_a_fixed_point() {
        // Three tight blobs far apart in 2-D.
        let blobs = [[0.0f32, 0.0], [10.0, 0.0], [0.0, 10.0]];
        let mut rng = SplitMix64::new(3);
        let mut points = vec![];
        for i in 0..300 {
            let c = blobs[i % 3];
            points.push(c[0] + 0.2 * (rng.unit() as f32 - 0.5));
            points.push(c[1] + 0.2 * (rng.unit() as f32 - 0.5));
        }
        let mean = |b: usize| -> [f32; 2] {
            let rows: Vec<&[f32]> = points.chunks_exact(2).skip(b).step_by(3).collect();
            let n = rows.len() as f64;
            let m = |j: usize| (rows.iter().map(|r| r[j] as f64).sum::<f64>() / n) as f32;
            [m(0), m(1)]
        };
        // Started off-centre (each start nearest its own blob), the
        // iterations land on the blobs' means.
        let start = Centroids {
            dim: 2,
            data: vec![2.0, 1.0, 8.0, 2.0, 1.0, 7.0],
        };
        let got = kmeans_from(&points, &start, Stop::exact(30));
        for b in 0..3 {
            let want = mean(b);
            let row = got.row(b);
            assert!(
                (row[0] - want[0]).abs() < 1e-5 && (row[1] - want[1]).abs() < 1e-5,
                "{b}: {row:?} vs {want:?}"
            );
        }
        // Converged centres are a fixed point, bit for bit.
        assert_eq!(kmeans_from(&points, &got, Stop::exact(30)), got);
        // No points: the start comes back.
        assert_eq!(kmeans_from(&[], &start, Stop::exact(30)), start);
    }

    #[test]
    fn a_tolerance_stops_once_centres_barely_move() {
        // Points spread evenly along a line: Lloyd's centres creep along
        // it for many iterations, each move smaller than the last.
        let points: Vec<f32> = (0..2000).map(|i| i as f32 / 2000.0).collect();
        let start = Centroids {
            dim: 1,
            data: vec![0.0, 0.01, 0.02, 0.03],
        };
        let exact = kmeans_from(&points, &start, Stop::exact(500));
        // A tolerance larger than any move: one update, then stop.
        let huge = Stop {
            max_iters: 500,
            tol: 1e3,
        };
        assert_eq!(
            kmeans_from(&points, &start, huge),
            kmeans_from(&points, &start, Stop::exact(1))
        );
        // A small one stops early, near where the exact iterations end:
        // the creep left is a geometric tail of the moves it stopped at.
        let tol = Stop {
            max_iters: 500,
            tol: 1e-3,
        };
        let early = kmeans_from(&points, &start, tol);
        assert_ne!(early, exact);
        let far = early
            .data
            .iter()
            .zip(&exact.data)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(far < 0.05, "{:?} vs {:?}", early.data, exact.data);
        // The exact centres split [0, 1] into four equal cells.
        for (c, want) in exact.data.iter().zip([0.125, 0.375, 0.625, 0.875]) {
            assert!((c - want).abs() < 2e-3, "{:?}", exact.data);
        }
        // Tolerance 0 is the exact rule.
        assert_eq!(
            kmeans_from(
                &points,
                &start,
                Stop {
                    max_iters: 500,
                    tol: 0.0
                }
            ),
            exact
        );
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_avx2_lane_distances_are_the_portable_ones_bit_for_bit() {
        if !crate::util::has_avx2() {
            eprintln!("skipped: this CPU has no AVX2");
            return;
        }
        let mut rng = SplitMix64::new(13);
        for dim in [1, 3, 64] {
            let blocks: Vec<f32> = (0..4 * dim * LANES).map(|_| rng.unit() as f32 - 0.5).collect();
            let x: Vec<f32> = (0..dim).map(|_| rng.unit() as f32 - 0.5).collect();
            fn bits<const G: usize>(d: [[f32; LANES]; G]) -> Vec<u32> {
                d.iter().flatten().map(|v| v.to_bits()).collect()
            }
            // SAFETY: AVX2 is checked above; the lengths hold four blocks.
            unsafe {
                let one = avx2::lane_distances::<1>(&blocks, dim, &x);
                assert_eq!(
                    bits(one),
                    bits(portable_lane_distances::<1>(&blocks, dim, &x)),
                    "dim {dim}"
                );
                let four = avx2::lane_distances::<4>(&blocks, dim, &x);
                assert_eq!(
                    bits(four),
                    bits(portable_lane_distances::<4>(&blocks, dim, &x)),
                    "dim {dim}"
                );
            }
        }
    }

    #[test]
    fn blocked_nearest_centre_is_the_plain_scan_to_the_bit() {
        let mut rng = SplitMix64::new(7);
        for (k, dim) in [(1, 3), (7, 5), (8, 64), (9, 64), (20, 64), (17, 3), (41, 64)] {
            let centres: Vec<f32> = (0..k * dim).map(|_| rng.unit() as f32 - 0.5).collect();
            let blocks = CentreBlocks::new(&centres, dim);
            for i in 0..200 {
                // Every fourth point is a centre itself (distance 0), and
                // a duplicated centre makes a tie the first one must win.
                let p: Vec<f32> = if i % 4 == 0 {
                    centres[(i / 4 % k) * dim..][..dim].to_vec()
                } else {
                    (0..dim).map(|_| rng.unit() as f32 - 0.5).collect()
                };
                let got = blocks.nearest(&p);
                let want = scan(&centres, dim, &p);
                assert_eq!(got.0, want.0, "k {k}, dim {dim}, point {i}");
                assert_eq!(got.1.to_bits(), want.1.to_bits(), "k {k}, dim {dim}, point {i}");
            }
            let mut twice = centres.clone();
            twice.extend_from_slice(&centres);
            let p = &centres[(k - 1) * dim..];
            assert_eq!(CentreBlocks::new(&twice, dim).nearest(p), (k - 1, 0.0));
        }
        // No channels: no centres to find, and no panic.
        let empty = CentreBlocks::new(&[], 0);
        assert_eq!(empty.nearest(&[]), (0, f32::INFINITY));
        empty.dots(&[], |_, _| panic!("no centre to visit"));
    }

    /// Known answer: two points either side of one centre, and a centre on
    /// each.
    #[test]
    fn inertia_sums_squared_distances_to_the_nearest_centre() {
        let points = [0.0, 0.0, 2.0, 0.0];
        let one = Centroids {
            dim: 2,
            data: vec![1.0, 0.0],
        };
        assert_eq!(inertia(&points, &one), 2.0);
        let two = Centroids {
            dim: 2,
            data: vec![0.0, 0.0, 2.0, 1.0],
        };
        assert_eq!(inertia(&points, &two), 1.0);
        assert_eq!(inertia(&[], &two), 0.0);
    }

    /// Three tight clusters and a few far outliers, K = 3: k-means++ now
    /// and then spends a centre on the outliers and merges two clusters.
    /// Best of eight draws finds the three clusters from every seed, never
    /// worse than that seed's own draw (also with more points than the
    /// draws compete on).
    #[test]
    fn the_best_of_several_draws_escapes_a_poor_local_minimum() {
        let mut rng = SplitMix64::new(3);
        let blobs = [[0.0f32, 0.0], [1.0, 0.0], [0.0, 1.0]];
        for per_blob in [300, 1500] {
            let mut points = vec![];
            for i in 0..3 * per_blob {
                let b = blobs[i % 3];
                points.extend([
                    b[0] + 0.1 * (rng.unit() as f32 - 0.5),
                    b[1] + 0.1 * (rng.unit() as f32 - 0.5),
                ]);
            }
            for _ in 0..5 {
                points.extend([3.0 + 0.1 * rng.unit() as f32, 3.0]);
            }
            let stop = Stop::exact(100);
            let mut poor_draws = 0;
            for seed in 0..40 {
                let one = inertia(&points, &kmeans_until(&points, 2, 3, seed, stop));
                let best = kmeans_best_of(&points, 2, 3, seed, stop, 8);
                let e = inertia(&points, &best);
                assert!(e <= one * 1.0001, "seed {seed}: best of eight {e}, one draw {one}");
                for b in blobs {
                    let near = (0..3).any(|k| dist2(best.row(k), &b) < 0.01);
                    assert!(near, "seed {seed}: no centre at {b:?}: {:?}", best.data);
                }
                if one > 1.5 * e {
                    poor_draws += 1;
                }
            }
            assert!(poor_draws > 0, "some single draw should settle in the poor minimum");
        }
    }
}
