//! Recipe → field: density from signed distances, labels, sparse colours and
//! features over the occupied voxels.
//!
//! Two passes, both parallel: (1) per z-slice, the nearest primitive of every
//! grid point (only primitives whose box reaches the slice and row are
//! tested) gives density and label; (2) per occupied voxel, the same nearest
//! primitive gives colour and, blended over the parts of its object, the
//! semantic feature.

use super::features::{FeatureNoise, Vocabulary, CHANNELS};
use super::labels::Labels;
use super::recipe::{Prim, Recipe, MAX_PARTS};
use super::texture::Texture;
use crate::error::Result;
use crate::field::{
    Aabb, Activation, Appearance, Bitmap, ChannelGrid, DensityGrid, Features, Field, GridGeom, RankIndex,
};
use glam::Vec3;
use half::f16;
use rayon::prelude::*;
use std::sync::Arc;

/// Optical depth per voxel inside a surface: σ = 3 / voxel, so a surface is
/// opaque (transmittance e⁻³ ≈ 5 %) within about one voxel.
const SIGMA_VOXELS: f32 = 3.0;
/// Half-width of the density falloff across a boundary, in voxels: σ goes
/// from full to zero over 1.5 voxels of signed distance.
const FALLOFF: f32 = 0.75;
/// Relative densities below this are cut to exactly zero, so that occupancy
/// (σ > 0) has a clean edge well above the segmentation floor (σ > 0.001).
const CUT: f32 = 0.02;
/// Width (world units) of the feature blend across part boundaries.
const BLUR: f32 = 0.015;

pub struct Voxelized {
    pub field: Field,
    pub labels: Labels,
    /// Part index (within its object) of every occupied voxel, in occupancy
    /// order (the slot order of the sparse grids).
    pub voxel_parts: Vec<u8>,
}

/// Relative density for signed distance `t` in voxels: 1 inside, 0 outside,
/// smooth in between.
fn profile(t: f32) -> f32 {
    let x = ((FALLOFF - t) / (2.0 * FALLOFF)).clamp(0.0, 1.0);
    let s = x * x * (3.0 - 2.0 * x);
    if s < CUT {
        0.0
    } else {
        s
    }
}

fn grow(b: Aabb, by: f32) -> Aabb {
    Aabb::new(b.min - Vec3::splat(by), b.max + Vec3::splat(by))
}

/// Nearest of the candidate primitives whose reach box holds `p`: (signed
/// distance, primitive). Ties go to the lower index, whatever the candidate
/// list, so both passes agree.
#[inline]
fn nearest(p: Vec3, candidates: &[usize], prims: &[Prim], reach: &[Aabb]) -> Option<(f32, usize)> {
    let mut best: Option<(f32, usize)> = None;
    for &i in candidates {
        if !reach[i].contains(p) {
            continue;
        }
        let d = prims[i].sdf.dist(p);
        if best.is_none_or(|(b, _)| d < b) {
            best = Some((d, i));
        }
    }
    best
}

pub fn voxelize(recipe: &Recipe, geom: GridGeom, seed: u64, vocab: &Vocabulary) -> Result<Voxelized> {
    crate::ensure!(recipe.objects.len() < 255, "a demo scene has at most 254 objects");
    crate::ensure!(
        recipe
            .objects
            .iter()
            .all(|o| !o.parts.is_empty() && o.parts.len() <= MAX_PARTS),
        "every demo object needs 1..={MAX_PARTS} parts"
    );
    crate::ensure!(
        recipe
            .prims
            .iter()
            .all(|p| p.object < recipe.objects.len() && p.part < recipe.objects[p.object].parts.len()),
        "a demo primitive names an object or part that does not exist"
    );
    let h = geom.spacing().max_element();
    let reach: Vec<Aabb> = recipe.prims.iter().map(|p| grow(p.sdf.bound(), h)).collect();
    let (raw, labels) = density_and_labels(recipe, geom, &reach);
    let bits = Bitmap::from_fn(geom.res, |i| raw[i] > 0.0);
    let voxels: Vec<u32> = bits.ones().map(|i| i as u32).collect();
    let occupancy = Arc::new(RankIndex::new(bits));
    let (rgb, feat, voxel_parts) = surface(recipe, geom, seed, vocab, &reach, &voxels);
    let field = Field::new(
        DensityGrid {
            geom,
            raw,
            activation: Activation::Relu,
        },
        Appearance::Rgb(ChannelGrid::sparse(geom, 3, occupancy.clone(), rgb)),
        Some(Features::Grid(ChannelGrid::sparse(
            geom,
            CHANNELS,
            occupancy.clone(),
            feat,
        ))),
        Some(occupancy),
    );
    let labels = Labels {
        bounds: geom.bounds,
        res: geom.res,
        names: recipe.objects.iter().map(|o| o.name.to_string()).collect(),
        data: labels,
    };
    Ok(Voxelized {
        field,
        labels,
        voxel_parts,
    })
}

/// Pass 1: σ and label of every grid point, one z-slice per task.
fn density_and_labels(recipe: &Recipe, geom: GridGeom, reach: &[Aabb]) -> (Vec<f32>, Vec<u8>) {
    let [nx, ny, _] = geom.res;
    let h = geom.spacing().max_element();
    let sigma_max = SIGMA_VOXELS / h;
    let mut raw = vec![0.0f32; geom.len()];
    let mut labels = vec![0u8; geom.len()];
    raw.par_chunks_mut(nx * ny)
        .zip(labels.par_chunks_mut(nx * ny))
        .enumerate()
        .for_each(|(z, (rs, ls))| {
            let pz = geom.point(0, 0, z).z;
            let slice: Vec<usize> = (0..reach.len())
                .filter(|&i| reach[i].min.z <= pz && pz <= reach[i].max.z)
                .collect();
            let mut row = Vec::with_capacity(slice.len());
            for y in 0..ny {
                let py = geom.point(0, y, z).y;
                row.clear();
                row.extend(
                    slice
                        .iter()
                        .copied()
                        .filter(|&i| reach[i].min.y <= py && py <= reach[i].max.y),
                );
                if row.is_empty() {
                    continue;
                }
                for x in 0..nx {
                    let Some((d, prim)) = nearest(geom.point(x, y, z), &row, &recipe.prims, reach) else {
                        continue;
                    };
                    let s = profile(d / h);
                    if s > 0.0 {
                        rs[x + nx * y] = sigma_max * s;
                        ls[x + nx * y] = recipe.prims[prim].object as u8 + 1;
                    }
                }
            }
        });
    (raw, labels)
}

/// Pass 2: colour, feature and part of every occupied voxel.
fn surface(
    recipe: &Recipe,
    geom: GridGeom,
    seed: u64,
    vocab: &Vocabulary,
    reach: &[Aabb],
    voxels: &[u32],
) -> (Vec<f16>, Vec<f16>, Vec<u8>) {
    const CHUNK: usize = 1024;
    let tex = Texture::new(seed);
    let noise = FeatureNoise::new(seed);
    let prims = &recipe.prims;
    let all: Vec<usize> = (0..prims.len()).collect();
    let blur_reach: Vec<Aabb> = prims.iter().map(|p| grow(p.sdf.bound(), 6.0 * BLUR)).collect();
    let by_object: Vec<Vec<usize>> = (0..recipe.objects.len())
        .map(|o| (0..prims.len()).filter(|&i| prims[i].object == o).collect())
        .collect();
    let n = voxels.len();
    let mut rgb = vec![f16::ZERO; n * 3];
    let mut feat = vec![f16::ZERO; n * CHANNELS];
    let mut parts = vec![0u8; n];
    rgb.par_chunks_mut(3 * CHUNK)
        .zip(feat.par_chunks_mut(CHANNELS * CHUNK))
        .zip(parts.par_chunks_mut(CHUNK))
        .enumerate()
        .for_each(|(c, ((rgb, feat), parts))| {
            for (j, part_out) in parts.iter_mut().enumerate() {
                let p = geom.point_of(voxels[c * CHUNK + j] as usize);
                // Every occupied voxel has a nearest primitive (pass 1 found it).
                let Some((d, prim)) = nearest(p, &all, prims, reach) else {
                    continue;
                };
                let col = prims[prim].material.color(p, &tex);
                rgb[3 * j..3 * j + 3].copy_from_slice(&[
                    f16::from_f32(col.x),
                    f16::from_f32(col.y),
                    f16::from_f32(col.z),
                ]);
                let mut f = [0.0f32; CHANNELS];
                feature(recipe, vocab, &by_object, &blur_reach, p, d, prim, &mut f);
                noise.add(p, &mut f);
                for (o, v) in feat[CHANNELS * j..CHANNELS * (j + 1)].iter_mut().zip(f) {
                    *o = f16::from_f32(v);
                }
                *part_out = prims[prim].part as u8;
            }
        });
    (rgb, feat, parts)
}

/// The object's feature at `p`: part directions blended by how close each
/// part's surface is (a soft minimum over signed distances), scaled to the
/// kind's norm.
#[allow(clippy::too_many_arguments)]
fn feature(
    recipe: &Recipe,
    vocab: &Vocabulary,
    by_object: &[Vec<usize>],
    blur_reach: &[Aabb],
    p: Vec3,
    d: f32,
    prim: usize,
    out: &mut [f32; CHANNELS],
) {
    let prims = &recipe.prims;
    let object = prims[prim].object;
    let spec = &recipe.objects[object];
    let mut part_d = [f32::INFINITY; MAX_PARTS];
    part_d[prims[prim].part] = d;
    for &q in &by_object[object] {
        if q != prim && blur_reach[q].contains(p) {
            let k = prims[q].part;
            part_d[k] = part_d[k].min(prims[q].sdf.dist(p));
        }
    }
    out.fill(0.0);
    for (k, &dk) in part_d.iter().enumerate().take(spec.parts.len()) {
        if dk.is_finite() {
            let w = (-(dk - d).max(0.0) / BLUR).exp();
            for (o, v) in out.iter_mut().zip(vocab.part(spec.kind, k)) {
                *o += w * v;
            }
        }
    }
    let norm = out.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
    let scale = spec.kind.norm() / norm;
    out.iter_mut().for_each(|v| *v *= scale);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn density_profile_is_monotone_and_cut() {
        assert_eq!(profile(-2.0), 1.0);
        assert_eq!(profile(2.0), 0.0);
        assert!((profile(0.0) - 0.5).abs() < 1e-6);
        let mut last = 1.0;
        for i in 0..100 {
            let s = profile(-1.0 + i as f32 * 0.02);
            assert!(s <= last);
            assert!(s == 0.0 || s >= CUT);
            last = s;
        }
    }
}
