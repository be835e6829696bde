//! Turning render outputs into pictures: colour, colour-mapped depth and
//! features projected to RGB by PCA. PNGs are written atomically.

use crate::error::{write_atomic, Error, Result};
use glam::Vec3;
use std::path::Path;

/// Quantises linear [0, 1] colours (stored as the NeRF datasets store them,
/// display-referred) to 8-bit RGB.
pub fn to_rgb8(colors: &[Vec3]) -> Vec<u8> {
    colors
        .iter()
        .flat_map(|c| c.to_array().map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8))
        .collect()
}

pub fn save_png(path: &Path, width: u32, height: u32, rgb8: &[u8]) -> Result<()> {
    let img = image::RgbImage::from_raw(width, height, rgb8.to_vec())
        .ok_or_else(|| Error::invalid(format!("image buffer does not match {width}x{height}")))?;
    let mut bytes = std::io::Cursor::new(Vec::new());
    img.write_to(&mut bytes, image::ImageFormat::Png)
        .map_err(|e| Error::invalid(format!("png encoding: {e}")))?;
    write_atomic(path, &bytes.into_inner())
}

/// A perceptually ordered colour map (approximation of "turbo").
fn turbo(x: f32) -> Vec3 {
    let x = x.clamp(0.0, 1.0);
    let r = 0.1357 + x * (4.5974 - x * (42.3277 - x * (130.5887 - x * (150.5666 - x * 58.1375))));
    let g = 0.0914 + x * (2.1856 + x * (4.8052 - x * (14.0195 - x * (4.2109 + x * 2.7747))));
    let b = 0.1067 + x * (12.5925 - x * (60.1097 - x * (109.0745 - x * (88.5066 - x * 26.8183))));
    Vec3::new(r, g, b).clamp(Vec3::ZERO, Vec3::ONE)
}

/// Depth to colour: near = warm, far = cool, background (opacity < 0.5) black.
/// The range is taken over the hit pixels.
pub fn colorize_depth(depth: &[f32], opacity: &[f32]) -> Vec<Vec3> {
    let hits = depth
        .iter()
        .zip(opacity)
        .filter(|(_, &o)| o >= 0.5)
        .map(|(&d, &o)| d / o);
    let (lo, hi) = hits.fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), d| (a.min(d), b.max(d)));
    let span = (hi - lo).max(1e-6);
    depth
        .iter()
        .zip(opacity)
        .map(|(&d, &o)| {
            if o < 0.5 {
                Vec3::ZERO
            } else {
                turbo(1.0 - (d / o - lo) / span)
            }
        })
        .collect()
}

/// Projects `n × c` features on their first three principal components and
/// maps each to [0, 1] (1st–99th percentile), pixels with opacity < 0.05 white.
pub fn features_to_rgb(feats: &[f32], c: usize, opacity: &[f32]) -> Vec<Vec3> {
    let n = opacity.len();
    if c == 0 || feats.len() != n * c {
        return vec![Vec3::ONE; n];
    }
    let rows: Vec<usize> = (0..n).filter(|&i| opacity[i] >= 0.05).collect();
    if rows.is_empty() {
        return vec![Vec3::ONE; n];
    }
    let mean: Vec<f64> = (0..c)
        .map(|j| rows.iter().map(|&i| feats[i * c + j] as f64).sum::<f64>() / rows.len() as f64)
        .collect();
    let mut cov = vec![0.0f64; c * c];
    for &i in &rows {
        let r = &feats[i * c..(i + 1) * c];
        for a in 0..c {
            let da = r[a] as f64 - mean[a];
            for b in a..c {
                cov[a * c + b] += da * (r[b] as f64 - mean[b]);
            }
        }
    }
    for a in 0..c {
        for b in 0..a {
            cov[a * c + b] = cov[b * c + a];
        }
    }
    let comps = top_eigenvectors(&cov, c, 3);
    let proj: Vec<[f32; 3]> = (0..n)
        .map(|i| {
            let r = &feats[i * c..(i + 1) * c];
            let mut p = [0.0f32; 3];
            for (k, v) in comps.iter().enumerate() {
                p[k] = (0..c).map(|j| (r[j] as f64 - mean[j]) * v[j]).sum::<f64>() as f32;
            }
            p
        })
        .collect();
    let range = |k: usize| {
        let mut v: Vec<f32> = rows.iter().map(|&i| proj[i][k]).collect();
        v.sort_by(f32::total_cmp);
        (v[v.len() / 100], v[v.len() - 1 - v.len() / 100])
    };
    let ranges = [range(0), range(1), range(2)];
    (0..n)
        .map(|i| {
            if opacity[i] < 0.05 {
                return Vec3::ONE;
            }
            let ch = |k: usize| {
                let (lo, hi) = ranges[k];
                ((proj[i][k] - lo) / (hi - lo).max(1e-6)).clamp(0.0, 1.0)
            };
            Vec3::new(ch(0), ch(1), ch(2))
        })
        .collect()
}

/// Leading eigenvectors of a symmetric matrix by power iteration with deflation.
pub fn top_eigenvectors(m: &[f64], n: usize, k: usize) -> Vec<Vec<f64>> {
    let mut a = m.to_vec();
    let mut out = Vec::with_capacity(k);
    for comp in 0..k.min(n) {
        // Deterministic start that is unlikely to be orthogonal to the answer.
        let mut v: Vec<f64> = (0..n).map(|i| 1.0 + ((i * 7 + comp * 13) % 11) as f64 * 0.1).collect();
        let mut lambda = 0.0;
        for _ in 0..200 {
            let w: Vec<f64> = (0..n).map(|i| (0..n).map(|j| a[i * n + j] * v[j]).sum()).collect();
            let norm = w.iter().map(|x| x * x).sum::<f64>().sqrt();
            if norm < 1e-30 {
                break;
            }
            lambda = norm;
            v = w.into_iter().map(|x| x / norm).collect();
        }
        for i in 0..n {
            for j in 0..n {
                a[i * n + j] -= lambda * v[i] * v[j];
            }
        }
        out.push(v);
    }
    while out.len() < k {
        out.push(vec![0.0; n]);
    }
    out
}
