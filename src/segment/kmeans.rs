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

fn nearest(c: &[f32], dim: usize, p: &[f32]) -> (usize, f32) {
    c.chunks_exact(dim)
        .enumerate()
        .map(|(k, r)| (k, dist2(r, p)))
        .fold((0, f32::INFINITY), |a, b| if b.1 < a.1 { b } else { a })
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
        // Each point's nearest centre on its own (the same sums as one
        // thread, so the result does not depend on the thread count).
        let changed = assign
            .par_iter_mut()
            .with_min_len(MIN_TASK)
            .enumerate()
            .map(|(i, a)| {
                let (best, _) = nearest(&centres, dim, row(i));
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
