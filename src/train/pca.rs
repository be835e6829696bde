//! Principal components of teacher features: ViT tokens have hundreds of
//! channels; the field stores the leading components (64 by default, as the
//! paper does), fitted once over the tokens of every training image so that
//! all views share one basis.

use crate::{ensure, Result};
use nalgebra::{DMatrix, SymmetricEigen};
use rayon::prelude::*;

/// Mean and leading eigenvectors of the covariance of the rows.
#[derive(Clone, Debug, PartialEq)]
pub struct Pca {
    pub in_dim: usize,
    pub out_dim: usize,
    pub mean: Vec<f32>,
    /// `out_dim × in_dim`, row-major, rows sorted by decreasing variance.
    pub basis: Vec<f32>,
    /// Fraction of the total variance the kept components explain.
    pub explained: f32,
}

impl Pca {
    /// Fits `out_dim` components to `rows` (`n × in_dim`, row-major).
    /// Each component's sign is fixed (largest coefficient positive) so that
    /// the same data always gives the same basis.
    pub fn fit(rows: &[f32], in_dim: usize, out_dim: usize) -> Result<Pca> {
        ensure!(in_dim >= 1, "PCA needs at least one input channel");
        ensure!(
            rows.len().is_multiple_of(in_dim),
            "PCA rows are not a multiple of {in_dim} channels"
        );
        let n = rows.len() / in_dim;
        ensure!(n >= 2, "PCA needs at least two feature vectors, got {n}");
        ensure!(
            (1..=in_dim).contains(&out_dim),
            "cannot keep {out_dim} components of {in_dim}-channel features"
        );
        ensure!(
            rows.iter().all(|v| v.is_finite()),
            "teacher features contain NaN or infinity"
        );
        let mean = column_mean(rows, in_dim);
        let cov = covariance(rows, in_dim, &mean);
        let eig = SymmetricEigen::new(DMatrix::from_row_slice(in_dim, in_dim, &cov));
        let mut order: Vec<usize> = (0..in_dim).collect();
        order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
        let total: f64 = eig.eigenvalues.iter().map(|v| v.max(0.0)).sum();
        let kept: f64 = order[..out_dim].iter().map(|&k| eig.eigenvalues[k].max(0.0)).sum();
        let mut basis = Vec::with_capacity(out_dim * in_dim);
        for &k in &order[..out_dim] {
            let col = eig.eigenvectors.column(k);
            let big = col
                .iter()
                .copied()
                .fold(0.0f64, |m, v| if v.abs() > m.abs() { v } else { m });
            let sign = if big < 0.0 { -1.0 } else { 1.0 };
            basis.extend(col.iter().map(|v| (sign * v) as f32));
        }
        Ok(Pca {
            in_dim,
            out_dim,
            mean: mean.iter().map(|&v| v as f32).collect(),
            basis,
            explained: if total > 0.0 { (kept / total) as f32 } else { 1.0 },
        })
    }

    /// Projects one row (`in_dim`) onto the components (`out_dim`).
    pub fn project(&self, row: &[f32], out: &mut [f32]) {
        for (o, b) in out.iter_mut().zip(self.basis.chunks_exact(self.in_dim)) {
            *o = b.iter().zip(row).zip(&self.mean).map(|((b, x), m)| b * (x - m)).sum();
        }
    }

    /// Projects every row of `rows` (`n × in_dim`) to `n × out_dim`.
    pub fn project_all(&self, rows: &[f32]) -> Vec<f32> {
        let mut out = vec![0.0; rows.len() / self.in_dim * self.out_dim];
        out.par_chunks_mut(self.out_dim)
            .zip(rows.par_chunks(self.in_dim))
            .for_each(|(o, r)| self.project(r, o));
        out
    }
}

fn column_mean(rows: &[f32], dim: usize) -> Vec<f64> {
    let n = (rows.len() / dim) as f64;
    let sum = rows
        .par_chunks(dim * 256)
        .map(|block| {
            let mut s = vec![0.0f64; dim];
            for r in block.chunks_exact(dim) {
                s.iter_mut().zip(r).for_each(|(s, &v)| *s += v as f64);
            }
            s
        })
        .reduce(|| vec![0.0; dim], add);
    sum.into_iter().map(|s| s / n).collect()
}

/// Sample covariance (`dim × dim`, row-major), accumulated in f64 over
/// blocks of rows in parallel.
fn covariance(rows: &[f32], dim: usize, mean: &[f64]) -> Vec<f64> {
    let n = rows.len() / dim;
    let sum = rows
        .par_chunks(dim * 256)
        .map(|block| {
            let mut c = vec![0.0f64; dim * dim];
            let mut d = vec![0.0f64; dim];
            for r in block.chunks_exact(dim) {
                d.iter_mut().zip(r).zip(mean).for_each(|((d, &v), m)| *d = v as f64 - m);
                for (i, &di) in d.iter().enumerate() {
                    // Upper triangle only; mirrored below.
                    let row = &mut c[i * dim..(i + 1) * dim];
                    row[i..].iter_mut().zip(&d[i..]).for_each(|(c, dj)| *c += di * dj);
                }
            }
            c
        })
        .reduce(|| vec![0.0; dim * dim], add);
    let mut c = sum;
    let denom = (n - 1) as f64;
    for i in 0..dim {
        for j in i..dim {
            let v = c[i * dim + j] / denom;
            c[i * dim + j] = v;
            c[j * dim + i] = v;
        }
    }
    c
}

fn add(mut a: Vec<f64>, b: Vec<f64>) -> Vec<f64> {
    a.iter_mut().zip(b).for_each(|(a, b)| *a += b);
    a
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Points on a tilted plane in 3-D: two components explain everything,
    /// the discarded direction is the plane's normal, and projecting then
    /// reconstructing returns the points.
    #[test]
    fn plane_is_recovered_exactly() {
        // A full grid of (a, b): uncorrelated, so the sample covariance has
        // exactly u and v as eigenvectors; a spreads wider than b.
        let (u, v) = ([0.6f32, 0.8, 0.0], [0.0f32, 0.0, 1.0]);
        let mut rows = vec![];
        for i in 0..21 {
            for j in 0..11 {
                let (a, b) = (0.2 * (i as f32 - 10.0), 0.1 * (j as f32 - 5.0));
                rows.extend((0..3).map(|k| 1.0 + a * u[k] + b * v[k]));
            }
        }
        let p = Pca::fit(&rows, 3, 2).unwrap();
        assert!((p.explained - 1.0).abs() < 1e-5, "explained {}", p.explained);
        // The first component is the direction of largest spread (u).
        let dot: f32 = p.basis[..3].iter().zip(&u).map(|(a, b)| a * b).sum();
        assert!((dot.abs() - 1.0).abs() < 1e-4, "first component {:?}", &p.basis[..3]);
        let proj = p.project_all(&rows);
        for (r, q) in rows.chunks(3).zip(proj.chunks(2)) {
            for k in 0..3 {
                let back = p.mean[k] + q[0] * p.basis[k] + q[1] * p.basis[3 + k];
                assert!((back - r[k]).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn bad_inputs_are_rejected() {
        assert!(Pca::fit(&[1.0, 2.0, 3.0], 3, 2).is_err(), "one row");
        assert!(Pca::fit(&[1.0; 12], 3, 4).is_err(), "more components than channels");
        assert!(Pca::fit(&[1.0, f32::NAN, 0.0, 1.0, 2.0, 3.0], 3, 1).is_err(), "NaN");
        assert!(Pca::fit(&[1.0; 7], 3, 1).is_err(), "ragged");
    }
}
