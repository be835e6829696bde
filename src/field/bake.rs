//! Baking a VM + MLP appearance into per-voxel degree-2 SH, for the GPU
//! view (whose ray marcher reads RGB or SH grids, not networks).
//!
//! At every grid point with density the MLP's pre-sigmoid output (the logit
//! of its colour) is evaluated along a fixed set of directions and fitted by
//! least squares with the 9 SH basis functions; the renderer's SH colour is
//! sigmoid(Σ cₖ Yₖ(d)), so the fit is exact wherever the network's logit is
//! a degree-2 polynomial in the direction and smooth otherwise. Empty grid
//! points store nothing (sparse layout).

use super::sh::{basis, SH_COEFFS};
use super::{Appearance, ChannelGrid, Field, RankIndex};
use crate::field::Bitmap;
use crate::Result;
use glam::Vec3;
use half::f16;
use rayon::prelude::*;
use std::sync::Arc;

/// Directions the network is sampled along (a Fibonacci sphere).
const DIRECTIONS: usize = 48;
/// Grid points whose σ is at or below this store no colour.
const FLOOR: f32 = 1e-4;

fn fibonacci_sphere(n: usize) -> Vec<Vec3> {
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let a = golden * i as f32;
            Vec3::new(r * a.cos(), r * a.sin(), z)
        })
        .collect()
}

/// The 9 × n least-squares projector P = (YᵀY)⁻¹Yᵀ of the SH basis sampled
/// at `dirs` (Y is n × 9), row-major; Gauss–Jordan in f64 on the 9 × 9
/// normal matrix, which is well conditioned for a spread of directions.
fn projector(dirs: &[Vec3]) -> Vec<f32> {
    let n = dirs.len();
    let y: Vec<[f64; SH_COEFFS]> = dirs.iter().map(|&d| basis(d).map(|v| v as f64)).collect();
    // [YᵀY | Yᵀ], reduced to [I | P].
    let w = SH_COEFFS + n;
    let mut m = vec![0.0f64; SH_COEFFS * w];
    for r in 0..SH_COEFFS {
        for c in 0..SH_COEFFS {
            m[r * w + c] = y.iter().map(|row| row[r] * row[c]).sum();
        }
        for (j, row) in y.iter().enumerate() {
            m[r * w + SH_COEFFS + j] = row[r];
        }
    }
    for col in 0..SH_COEFFS {
        let piv = (col..SH_COEFFS)
            .max_by(|&a, &b| m[a * w + col].abs().total_cmp(&m[b * w + col].abs()))
            .expect("rows left");
        for k in 0..w {
            m.swap(col * w + k, piv * w + k);
        }
        let p = m[col * w + col];
        for k in 0..w {
            m[col * w + k] /= p;
        }
        for r in (0..SH_COEFFS).filter(|&r| r != col) {
            let f = m[r * w + col];
            for k in 0..w {
                m[r * w + k] -= f * m[col * w + k];
            }
        }
    }
    (0..SH_COEFFS)
        .flat_map(|r| (0..n).map(move |j| (r, j)))
        .map(|(r, j)| m[r * w + SH_COEFFS + j] as f32)
        .collect()
}

fn logit(c: f32) -> f32 {
    let c = c.clamp(1e-4, 1.0 - 1e-4);
    (c / (1.0 - c)).ln()
}

/// `field` with a VM + MLP appearance replaced by sparse degree-2 SH (the
/// same field, cloned, for any other appearance).
pub fn vm_to_sh(field: &Field) -> Result<Field> {
    let Appearance::Vm { grid, mlp } = &field.appearance else {
        return Ok(field.clone());
    };
    let geom = field.geom();
    let dirs = fibonacci_sphere(DIRECTIONS);
    let proj = projector(&dirs);
    // Sparse grids of one field share one index: reuse the field's if it
    // has one (sparse features), else store where there is density.
    let index = match &field.occupancy {
        Some(ix) => ix.clone(),
        None => Arc::new(RankIndex::new(Bitmap::from_fn(geom.res, |i| {
            field.density.sigma_at(i) > FLOOR
        }))),
    };
    let points: Vec<usize> = index.bits().ones().collect();
    let mut data = vec![f16::ZERO; points.len() * 3 * SH_COEFFS];
    data.par_chunks_mut(3 * SH_COEFFS).zip(points.par_iter()).for_each_init(
        || {
            (
                vec![0.0f32; grid.total_comps()],
                vec![0.0f32; grid.out],
                Vec::new(),
                vec![0.0f32; 3 * DIRECTIONS],
            )
        },
        |(comps, chan, buf, logits), (out, &i)| {
            grid.sample(geom.point_of(i), comps, chan);
            for (j, &d) in dirs.iter().enumerate() {
                let c = mlp.eval(chan, d, buf);
                for ch in 0..3 {
                    logits[ch * DIRECTIONS + j] = logit(c[ch]);
                }
            }
            for ch in 0..3 {
                let l = &logits[ch * DIRECTIONS..(ch + 1) * DIRECTIONS];
                for k in 0..SH_COEFFS {
                    let row = &proj[k * DIRECTIONS..(k + 1) * DIRECTIONS];
                    let v: f32 = row.iter().zip(l).map(|(a, b)| a * b).sum();
                    out[ch * SH_COEFFS + k] = f16::from_f32(v);
                }
            }
        },
    );
    Ok(Field::new(
        field.density.clone(),
        Appearance::Sh2(ChannelGrid::sparse(geom, 3 * SH_COEFFS, index.clone(), data)),
        field.features.clone(),
        Some(index),
    )
    .in_space_of(field))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_projector_recovers_sh_coefficients_exactly() {
        // Any degree-2 SH function sampled at the directions projects back
        // onto its own coefficients.
        let dirs = fibonacci_sphere(DIRECTIONS);
        let p = projector(&dirs);
        let coeffs = [0.7f32, -0.3, 0.2, 0.5, -0.8, 0.1, 0.4, -0.6, 0.25];
        let samples: Vec<f32> = dirs
            .iter()
            .map(|&d| basis(d).iter().zip(&coeffs).map(|(a, b)| a * b).sum())
            .collect();
        for k in 0..SH_COEFFS {
            let got: f32 = p[k * DIRECTIONS..(k + 1) * DIRECTIONS]
                .iter()
                .zip(&samples)
                .map(|(a, b)| a * b)
                .sum();
            assert!(
                (got - coeffs[k]).abs() < 1e-4,
                "coefficient {k}: {got} vs {}",
                coeffs[k]
            );
        }
    }
}
