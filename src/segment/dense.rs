//! The straightforward dense implementation of the same method, used as the
//! reference in tests and as the baseline in `isrf bench segment`: features
//! computed for *every* grid point, NNFM over every voxel, and each growth
//! step scanning the whole grid. Deliberately independent of the
//! [`FeatureCache`](crate::field::FeatureCache) code path.

use super::grow::GrowParams;
use super::kmeans::Centroids;
use crate::field::cache::OCCUPIED_FLOOR;
use crate::field::{Bitmap, Field};
use rayon::prelude::*;

pub struct DenseFeatures {
    pub res: [usize; 3],
    pub channels: usize,
    pub sigma: Vec<f32>,
    pub feats: Vec<f32>,
}

/// Features and σ at every grid point.
pub fn dense_features(field: &Field) -> DenseFeatures {
    let g = field.geom();
    let c = field.feature_channels();
    let mut feats = vec![0.0f32; g.len() * c];
    feats
        .par_chunks_mut((c * 1024).max(1))
        .enumerate()
        .for_each(|(chunk, out)| {
            let mut s = field.sampler();
            for (j, row) in out.chunks_mut(c).enumerate() {
                s.features(g.point_of(chunk * 1024 + j), row);
            }
        });
    let sigma = (0..g.len())
        .into_par_iter()
        .map(|i| field.density.sigma_at(i))
        .collect();
    DenseFeatures {
        res: g.res,
        channels: c,
        sigma,
        feats,
    }
}

pub fn nnfm_dense(d: &DenseFeatures, centres: &Centroids, theta: f32, floor: f32) -> Bitmap {
    let c = d.channels;
    let hits: Vec<bool> = (0..d.sigma.len())
        .into_par_iter()
        .map(|v| {
            if d.sigma[v] <= floor || d.sigma[v] <= OCCUPIED_FLOOR {
                return false;
            }
            let f = &d.feats[v * c..(v + 1) * c];
            let n = f.iter().map(|x| x * x).sum::<f32>().sqrt();
            let inv = if n > 1e-12 { 1.0 / n } else { 0.0 };
            (0..centres.len()).any(|k| {
                let dist: f32 = f
                    .iter()
                    .zip(centres.row(k))
                    .map(|(a, b)| (a * inv - b) * (a * inv - b))
                    .sum();
                dist < theta
            })
        })
        .collect();
    Bitmap::from_fn(d.res, |v| hits[v])
}

/// One growth step over the whole grid.
pub fn grow_step_full_scan(d: &DenseFeatures, mask: &mut Bitmap, p: &GrowParams) -> usize {
    let [nx, ny, nz] = d.res;
    let c = d.channels;
    let occ = |v: usize| d.sigma[v] > OCCUPIED_FLOOR;
    let row = |v: usize| &d.feats[v * c..(v + 1) * c];
    let add: Vec<usize> = (0..d.sigma.len())
        .into_par_iter()
        .filter(|&v| {
            if mask.get(v) || !occ(v) {
                return false;
            }
            let (x, y, z) = ((v % nx) as i64, ((v / nx) % ny) as i64, (v / (nx * ny)) as i64);
            let (mut num, mut den, mut touches) = (0.0f32, 0.0f32, false);
            for dz in -1..=1i64 {
                for dy in -1..=1i64 {
                    for dx in -1..=1i64 {
                        let (a, b, cc) = (x + dx, y + dy, z + dz);
                        if a < 0 || b < 0 || cc < 0 || a >= nx as i64 || b >= ny as i64 || cc >= nz as i64 {
                            continue;
                        }
                        let n = a as usize + nx * (b as usize + ny * cc as usize);
                        touches |= mask.get(n);
                        if !occ(n) {
                            continue;
                        }
                        let df: f32 = row(n).iter().zip(row(v)).map(|(s, t)| (s - t) * (s - t)).sum();
                        let l1 = (dx.abs() + dy.abs() + dz.abs()) as f32;
                        let w = (-df / p.sigma_f).exp() * (-l1 / p.sigma_s).exp();
                        den += w;
                        if mask.get(n) {
                            num += w;
                        }
                    }
                }
            }
            touches && den > 0.0 && num / den > p.tau
        })
        .collect();
    for &v in &add {
        mask.set(v, true);
    }
    add.len()
}
