//! Nearest-neighbour feature matching (NNFM) seed over occupied voxels.
//!
//! For every cached voxel with σ above `floor`:
//! d = min_k ‖φ̂ − c_k‖² = min_k (‖φ̂‖² − 2 φ̂·c_k + ‖c_k‖²) with φ̂ = φ/‖φ‖,
//! and the voxel is a seed when d < θ. Written as dot products so the inner
//! loop is one multiply-add per channel.

use super::kmeans::Centroids;
use crate::field::{Bitmap, FeatureCache};
use rayon::prelude::*;

/// Seed bitmap over the cache's grid.
pub fn nnfm_seed(cache: &FeatureCache, centres: &Centroids, theta: f32, floor: f32) -> Bitmap {
    let mut bits = Bitmap::new(cache.geom.res);
    if centres.is_empty() {
        return bits;
    }
    let norms: Vec<f32> = (0..centres.len())
        .map(|k| centres.row(k).iter().map(|x| x * x).sum())
        .collect();
    const CHUNK: usize = 4096;
    let hits: Vec<Vec<u32>> = (0..cache.len())
        .into_par_iter()
        .step_by(CHUNK)
        .map(|start| {
            let mut out = Vec::new();
            for r in start..(start + CHUNK).min(cache.len()) {
                if cache.sigma[r] <= floor {
                    continue;
                }
                let inv = cache.inv_norm[r];
                let phi = cache.row(r);
                let self_n = if inv > 0.0 { 1.0 } else { 0.0 };
                // d < θ ⇔ 2 inv φ·c_k > self_n + ‖c_k‖² − θ for some k.
                let matched = (0..centres.len()).any(|k| {
                    let dot: f32 = phi.iter().zip(centres.row(k)).map(|(a, b)| a * b).sum::<f32>() * inv;
                    self_n - 2.0 * dot + norms[k] < theta
                });
                if matched {
                    out.push(cache.voxels[r]);
                }
            }
            out
        })
        .collect();
    for v in hits.into_iter().flatten() {
        bits.set(v as usize, true);
    }
    bits
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
