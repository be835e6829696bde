//! A feature cache on a coarser grid: each coarse voxel stands for an
//! f×f×f block of fine voxels, f = 2, or 3 on grids of more than
//! [`THREE_FOLD_MIN`] occupied voxels ([`factor_for`]).
//!
//! Why: a stroke's segmentation (NNFM, the stable flood, the graph cut)
//! visits every solid voxel the object and its neighbourhood hold, about a
//! million on a real capture's 320³ or 448×408×46 grid, and took 1.3–3 s
//! there. The features it decides by are coarse anyway: the teacher's
//! patch tokens are distilled into a feature grid of 128 points across at
//! most, so two fine voxels side by side carry nearly the same feature.
//! On the coarse copy the same pipeline runs over an eighth of the voxels.
//!
//! A coarse voxel holds
//! - σ: the largest σ of its block, so it is solid exactly when one of its
//!   fine voxels is (the same floor applies: `voxel_size` stays the fine
//!   grid's);
//! - its feature: the sum of its fine voxels' unit features, each weighted
//!   by the share of light it stops across one fine voxel (1 − e^{−σh}), so
//!   haze next to a surface barely counts; segmentation reads it as a unit
//!   vector;
//! - its colour: the same weighted mean of the fine colours.
//!
//! The coarse grid's bounds start at the fine grid's and its points are
//! every f-th fine point (fine voxel x lies in coarse voxel x / f).

use super::bitmap::{Bitmap, RankIndex};
use super::cache::FeatureCache;
use super::runs::Runs;
use super::{Aabb, GridGeom};
use rayon::prelude::*;

/// Fine grids need at least this many points along every axis to get a
/// coarse copy (a coarse axis of one point has no spacing).
pub const MIN_FINE_RES: usize = 4;

/// Fine caches with more occupied voxels than this get a coarse copy three
/// times as coarse instead of two: a stroke visits every solid voxel of the
/// object and its neighbourhood, so its time grows with the grid. Lego at
/// 800×800 has 1.0 M occupied voxels on its 320 grid (twofold: 135–155 ms
/// a stroke) and 2.0 M on a 400 grid (twofold: 234–277 ms); the fern's
/// 448×408×46 grid has 2.5 M. Both finer grids are still finer than their
/// feature grids (128 points across) at three.
pub const THREE_FOLD_MIN: usize = 1_500_000;

/// How many fine voxels a coarse copy of a cache of `fine_len` occupied
/// voxels merges along each axis.
pub fn factor_for(fine_len: usize) -> usize {
    if fine_len > THREE_FOLD_MIN {
        3
    } else {
        2
    }
}

/// The coarse voxel (index into the coarse grid) holding fine voxel `v` of
/// a grid of resolution `fine_res`, `f` fine voxels to a coarse one.
#[inline]
fn parent(fine_res: [usize; 3], f: usize, v: usize) -> usize {
    let res = coarse_res(fine_res, f);
    let [x, y, z] = [
        v % fine_res[0],
        (v / fine_res[0]) % fine_res[1],
        v / (fine_res[0] * fine_res[1]),
    ];
    x / f + res[0] * (y / f + res[1] * (z / f))
}

/// The coarse resolution of a fine one, `f` fine voxels to a coarse one.
pub fn coarse_res(res: [usize; 3], f: usize) -> [usize; 3] {
    res.map(|n| n.div_ceil(f))
}

/// The coarse copy of `fine` ([`factor_for`] fine voxels to a coarse one
/// along each axis), or `None` when the grid is too small to coarsen.
pub fn build(fine: &FeatureCache) -> Option<FeatureCache> {
    build_with(fine, factor_for(fine.len()))
}

/// [`build`] with `f` fine voxels to a coarse one along each axis.
pub fn build_with(fine: &FeatureCache, f: usize) -> Option<FeatureCache> {
    let fres = fine.geom.res;
    if f < 2 || fres.iter().any(|&n| n < MIN_FINE_RES.max(2 * f)) {
        return None;
    }
    let res = coarse_res(fres, f);
    let h = fine.geom.spacing();
    let bounds = Aabb::new(
        fine.geom.bounds.min,
        fine.geom.bounds.min
            + f as f32 * h * glam::Vec3::new((res[0] - 1) as f32, (res[1] - 1) as f32, (res[2] - 1) as f32),
    );
    let geom = GridGeom::new(bounds, res);
    let mut bits = Bitmap::new(res);
    for &v in &fine.voxels {
        bits.set(parent(fres, f, v as usize), true);
    }
    let index = RankIndex::new(bits);
    let voxels: Vec<u32> = index.bits().ones().map(|v| v as u32).collect();
    let n = voxels.len();
    let ch = fine.channels;
    let mut feats = vec![0.0f32; n * ch];
    let mut sigma = vec![0.0f32; n];
    let mut colours = vec![glam::Vec3::ZERO; n];
    // Coarse slab z owns its rows and reads the fine rows of slabs f·z to
    // f·z + f − 1 (rows ascend with z, the slowest axis), so slabs fill in
    // parallel without sharing a row.
    let slab_rows = |z: usize, len: usize, of: &[u32]| of.partition_point(|&v| (v as usize) < z * len);
    let (fslab, cslab) = (fres[0] * fres[1], res[0] * res[1]);
    let bounds_of = |z: usize| (slab_rows(z, cslab, &voxels), slab_rows(z + 1, cslab, &voxels));
    let mut chunks: Vec<(usize, &mut [f32], &mut [f32], &mut [glam::Vec3])> = Vec::with_capacity(res[2]);
    {
        let (mut fe, mut s, mut c) = (&mut feats[..], &mut sigma[..], &mut colours[..]);
        for z in 0..res[2] {
            let (a, b) = bounds_of(z);
            let (f0, f1) = std::mem::take(&mut fe).split_at_mut((b - a) * ch);
            let (s0, s1) = std::mem::take(&mut s).split_at_mut(b - a);
            let (c0, c1) = std::mem::take(&mut c).split_at_mut(b - a);
            chunks.push((z, f0, s0, c0));
            (fe, s, c) = (f1, s1, c1);
        }
    }
    let hmin = h.min_element();
    chunks.into_par_iter().for_each(|(z, fe, s, c)| {
        let first = bounds_of(z).0;
        let mut wsum = vec![0.0f32; s.len()];
        let (lo, hi) = (
            slab_rows(f * z, fslab, &fine.voxels),
            slab_rows((f * z + f).min(fres[2]), fslab, &fine.voxels),
        );
        for r in lo..hi {
            let p = parent(fres, f, fine.voxels[r] as usize);
            let i = index.slot(p).expect("parent of a cached voxel") - first;
            let sig = fine.sigma[r];
            s[i] = s[i].max(sig);
            let w = 1.0 - (-sig * hmin).exp();
            wsum[i] += w;
            c[i] += w * fine.colours[r];
            let inv = fine.inv_norm[r];
            if inv > 0.0 {
                for (o, &x) in fe[i * ch..(i + 1) * ch].iter_mut().zip(fine.row(r)) {
                    *o += w * inv * x;
                }
            }
        }
        for (c, &w) in c.iter_mut().zip(&wsum) {
            if w > 0.0 {
                *c /= w;
            }
        }
    });
    Some(
        FeatureCache::from_parts(geom, ch, fine.voxel_size, voxels, index, sigma, feats, colours)
            .coarsened(f)
            .with_up(fine.up),
    )
}

/// The coarse voxels (`f` fine ones to a coarse one along each axis)
/// holding the fine voxels set in `fine_mask`.
pub fn downsample(fine_mask: &Bitmap, f: usize) -> Bitmap {
    let fres = fine_mask.res();
    let res = coarse_res(fres, f);
    let mut out = Bitmap::new(res);
    for v in fine_mask.ones() {
        out.set(parent(fres, f, v), true);
    }
    out
}

/// The fine voxels of `fine` with σ above `floor` whose coarse voxel (`f`
/// fine ones to a coarse one along each axis) is set in `coarse_mask`.
pub fn upsample(fine: &FeatureCache, coarse_mask: &Bitmap, f: usize, floor: f32) -> Bitmap {
    let [fx, fy, fz] = fine.geom.res;
    let mut out = Bitmap::new(fine.geom.res);
    // Each coarse run covers f times its span in the (up to) f² fine rows
    // under it; a set-range per run, not f³ rank lookups per voxel.
    let cy = coarse_mask.res()[1];
    for (row, x0, x1) in Runs::of(coarse_mask).iter() {
        let (y, z) = (row % cy, row / cy);
        for zz in (f * z..f * z + f).filter(|&zz| zz < fz) {
            for yy in (f * y..f * y + f).filter(|&yy| yy < fy) {
                let base = fx * (yy + fy * zz);
                out.set_range(base + f * x0, base + (f * x1).min(fx));
            }
        }
    }
    out.intersect_with(&fine.solid(floor)).expect("same grid");
    out
}

/// The coarse voxels (`f` fine ones to a coarse one along each axis) of
/// fine voxel indices, ascending and distinct.
pub fn parents(fine_res: [usize; 3], f: usize, voxels: &[u32]) -> Vec<u32> {
    let mut out: Vec<u32> = voxels.iter().map(|&v| parent(fine_res, f, v as usize) as u32).collect();
    out.sort_unstable();
    out.dedup();
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{Aabb, Field, FieldBuilder};
    use glam::Vec3;

    /// A field of odd resolution (the last coarse voxel has one fine
    /// layer) with a density that varies voxel to voxel, empty space
    /// included, and features that turn with x.
    fn field() -> Field {
        FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [11, 9, 7]).build(
            |p| {
                let s = (7.0 * p.x).sin() * (5.0 * p.y).cos() + 0.3 * p.z;
                if s > -0.2 {
                    40.0 * (s + 0.2)
                } else {
                    0.0
                }
            },
            |p| Vec3::new(p.x.abs(), 0.5, p.z.abs()),
            Some((4, &|p: Vec3, out: &mut [f32]| {
                out.copy_from_slice(&[(2.0 * p.x).cos(), (2.0 * p.x).sin(), 0.3 * p.y, 1.0 + p.z])
            })),
        )
    }

    #[test]
    fn a_coarse_voxel_sums_its_blocks_weighted_unit_features() {
        let f = field();
        let fine = FeatureCache::build(&f).unwrap();
        assert_eq!(
            fine.coarse().expect("big enough to coarsen").factor,
            2,
            "a small cache is coarsened twofold"
        );
        for k in [2, 3] {
            let coarse = build_with(&fine, k).expect("big enough");
            assert_eq!(coarse.factor, k);
            assert_eq!(coarse.geom.res, [11, 9, 7].map(|n: usize| n.div_ceil(k)));
            assert_eq!(coarse.geom.spacing(), k as f32 * fine.geom.spacing());
            assert_eq!(coarse.voxel_size, fine.voxel_size);
            // Reference: every coarse voxel's block, summed voxel by voxel.
            let h = fine.voxel_size;
            let mut seen = 0;
            for (cr, &cv) in coarse.voxels.iter().enumerate() {
                let [cx, cy, cz] = coarse.geom.coords(cv as usize);
                let (mut sig, mut feat, mut col, mut wsum) = (0.0f32, [0.0f32; 4], Vec3::ZERO, 0.0f32);
                for j in 0..k * k * k {
                    let (x, y, z) = (k * cx + j % k, k * cy + j / k % k, k * cz + j / (k * k));
                    let Some(r) = (x < 11 && y < 9 && z < 7)
                        .then(|| fine.index.slot(fine.geom.index(x, y, z)))
                        .flatten()
                    else {
                        continue;
                    };
                    seen += 1;
                    sig = sig.max(fine.sigma[r]);
                    let w = 1.0 - (-fine.sigma[r] * h).exp();
                    wsum += w;
                    col += w * fine.colours[r];
                    for (o, x) in feat.iter_mut().zip(fine.row(r)) {
                        *o += w * fine.inv_norm[r] * x;
                    }
                }
                assert!(sig > 0.0, "a coarse voxel is cached only over cached fine ones");
                assert_eq!(coarse.sigma[cr], sig);
                for (a, b) in coarse.row(cr).iter().zip(feat) {
                    assert!((a - b).abs() < 1e-5, "{a} {b}");
                }
                assert!((coarse.colours[cr] - col / wsum).length() < 1e-5);
            }
            assert_eq!(seen, fine.len(), "every fine voxel counted once ({k}-fold)");
        }
    }

    #[test]
    fn masks_go_down_and_up_through_blocks() {
        let f = field();
        let fine = FeatureCache::build(&f).unwrap();
        let res = fine.geom.res;
        let floor = 5.0;
        let mask = Bitmap::from_fn(res, |v| v % 3 == 0 && v % 5 != 0);
        for k in [2, 3] {
            let coarse = build_with(&fine, k).unwrap();
            let down = downsample(&mask, k);
            assert_eq!(down.res(), coarse.geom.res);
            let listed: Vec<u32> = mask.ones().map(|v| v as u32).collect();
            let want: Vec<u32> = down.ones().map(|v| v as u32).collect();
            assert_eq!(parents(res, k, &listed), want);
            let up = upsample(&fine, &down, k, floor);
            // Up: exactly the solid fine voxels of the selected blocks.
            for v in 0..fine.geom.len() {
                let solid = fine.index.slot(v).is_some_and(|r| fine.sigma[r] > floor);
                let [x, y, z] = fine.geom.coords(v);
                let block = down.get(coarse.geom.index(x / k, y / k, z / k));
                assert_eq!(up.get(v), solid && block, "voxel {v} ({k}-fold)");
            }
            assert!(up.count() > 0);
        }
    }

    #[test]
    fn large_caches_are_coarsened_threefold() {
        assert_eq!(factor_for(THREE_FOLD_MIN), 2);
        assert_eq!(factor_for(THREE_FOLD_MIN + 1), 3);
    }

    #[test]
    fn grids_too_thin_to_halve_have_no_coarse_copy() {
        let f = FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [8, 8, 3]).build(
            |_| 10.0,
            |_| Vec3::ONE,
            Some((2, &|_p: Vec3, out: &mut [f32]| out.fill(1.0))),
        );
        assert!(FeatureCache::build(&f).unwrap().coarse().is_none());
    }
}
