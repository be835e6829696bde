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
        let k = centres.len() / dim.max(1);
        let blocks = k.div_ceil(LANES);
        let mut data = vec![0.0; blocks * dim * LANES];
        for (c, row) in centres.chunks_exact(dim.max(1)).enumerate() {
            let (b, lane) = (c / LANES, c % LANES);
            for (j, &v) in row.iter().enumerate() {
                data[(b * dim + j) * LANES + lane] = v;
            }
        }
        CentreBlocks { k, dim, data }
    }

    /// The nearest centre to `p` and its squared distance (the first one
    /// on ties, as a scan in centre order).
    fn nearest(&self, p: &[f32]) -> (usize, f32) {
        let mut best = (0, f32::INFINITY);
        self.sums(
            p,
            |c, x| (c - x) * (c - x),
            |k, d| {
                if d < best.1 {
                    best = (k, d);
                }
            },
        );
        best
    }

    /// Calls `f(k, p·c_k)` for every centre in order, each dot product
    /// summed over the channels in order (as a plain zip-sum would be).
    pub(crate) fn dots(&self, p: &[f32], f: impl FnMut(usize, f32)) {
        self.sums(p, |c, x| x * c, f);
    }

    /// Calls `f(k, Σ_j term(c_kj, p_j))` for every centre k in order, the
    /// sum taken over the channels in order, a block of centres at a time.
    #[inline(always)]
    fn sums(&self, p: &[f32], term: impl Fn(f32, f32) -> f32, mut f: impl FnMut(usize, f32)) {
        for (b, block) in self.data.chunks_exact((self.dim * LANES).max(1)).enumerate() {
            let mut acc = [0.0f32; LANES];
            for (lanes, &x) in block.chunks_exact(LANES).zip(p) {
                for l in 0..LANES {
                    acc[l] += term(lanes[l], x);
                }
            }
            for (l, &d) in acc.iter().enumerate().take(self.k - b * LANES) {
                f(b * LANES + l, d);
            }
        }
    }
}

/// k-means++ initialisation then Lloyd iterations until assignments stop
/// changing or `max_iters` is reached. `points` is `n × dim`.
pub fn kmeans(points: &[f32], dim: usize, k: usize, seed: u64, max_iters: usize) -> Centroids {
    let n = if dim == 0 { 0 } else { points.len() / dim };
    if n == 0 || k == 0 {
        return Centroids { dim, data: vec![] };
    }
    let row = |i: usize| &points[i * dim..(i + 1) * dim];
    let mut rng = SplitMix64::new(seed);
    // k-means++: first centre uniformly, then proportional to squared distance.
    let mut centres: Vec<f32> = row(rng.below(n)).to_vec();
    let mut d2: Vec<f32> = (0..n).map(|i| dist2(row(i), &centres[..dim])).collect();
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
        let new = &centres[start..];
        d2.par_iter_mut()
            .with_min_len(MIN_TASK)
            .enumerate()
            .for_each(|(i, d)| *d = d.min(dist2(row(i), new)));
    }
    let kk = centres.len() / dim;
    let mut assign = vec![usize::MAX; n];
    for _ in 0..max_iters {
        let blocks = CentreBlocks::new(&centres, dim);
        // Each point's nearest centre on its own (the same sums as one
        // thread, so the result does not depend on the thread count).
        let changed = assign
            .par_iter_mut()
            .with_min_len(MIN_TASK)
            .enumerate()
            .map(|(i, a)| {
                let (best, _) = blocks.nearest(row(i));
                let moved = *a != best;
                *a = best;
                moved
            })
            .reduce(|| false, |x, y| x || y);
        if !changed {
            break;
        }
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
    }
    Centroids { dim, data: centres }
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

    #[test]
    fn blocked_nearest_centre_is_the_plain_scan_to_the_bit() {
        let mut rng = SplitMix64::new(7);
        for (k, dim) in [(1, 3), (7, 5), (8, 64), (9, 64), (20, 64), (17, 3)] {
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
}
