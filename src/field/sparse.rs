//! Sparse storage of a field: appearance and features only where they can
//! matter, so that field files of captured scenes (a few per cent of the
//! grid occupied) stay small.
//!
//! Which grid points are stored:
//! - density grid resolution: every point with σ above
//!   [`OCCUPIED_FLOOR`](super::cache::OCCUPIED_FLOOR) (the voxels
//!   segmentation works on), dilated by one voxel. Every cell that has a
//!   corner above the floor then has all eight corners stored, so samples
//!   there interpolate exactly as in the dense field. In the other cells
//!   every corner is at or below the floor, so each sample's opacity is at
//!   most `floor × step` (about 1e-5 in lego) whatever is stored there.
//! - the feature grid (its own, usually coarser resolution): every point
//!   that is a corner of a feature cell reaching within one density voxel of
//!   a stored density point, so features sampled anywhere a stored density
//!   cell can give weight are exact too, and so are the features that
//!   segmentation reads at occupied voxels.
//!
//! Density itself stays dense in memory; the file stores it for the
//! occupied points only when every other point holds one fill value, which
//! [`sparsify`] arranges (raw [`EMPTY_RAW_LOGIT`] − shift, σ ≈ 1e-13).

use super::bitmap::{Bitmap, RankIndex};
use super::cache::OCCUPIED_FLOOR;
use super::geom::GridGeom;
use super::grid::{Activation, ChannelGrid, DensityGrid, Layout};
use super::{Appearance, Features, Field};
use crate::error::Result;
use half::f16;
use rayon::prelude::*;
use std::sync::Arc;

/// Pre-activation value (raw + shift) of unstored softplus density points:
/// softplus(−30) ≈ 1e-13, the value pruned voxels hold while training.
pub const EMPTY_RAW_LOGIT: f32 = -30.0;

/// Raw density of unstored points for an activation (σ numerically 0).
pub fn empty_raw(activation: Activation) -> f32 {
    match activation {
        Activation::Relu => 0.0,
        Activation::Softplus { shift } => EMPTY_RAW_LOGIT - shift,
    }
}

/// Density grid points to store: σ > [`OCCUPIED_FLOOR`], dilated by one.
pub fn density_occupancy(density: &DensityGrid) -> Bitmap {
    Bitmap::from_fn(density.geom.res, |i| density.sigma_at(i) > OCCUPIED_FLOOR).dilated()
}

/// Points of grid `fgeom` (the feature grid) to store for the stored density
/// points `occ` of grid `dgeom`: every point within one feature spacing plus
/// one density spacing (per axis) of a stored density point. A sample in a
/// stored density cell lies within one density spacing of a stored corner,
/// and the corners of its feature cell within one feature spacing of it.
pub fn feature_occupancy(occ: &Bitmap, dgeom: &GridGeom, fgeom: &GridGeom) -> Bitmap {
    let reach = fgeom.spacing() + dgeom.spacing();
    let mut out = Bitmap::new(fgeom.res);
    let [fx, fy, _] = fgeom.res;
    for i in occ.ones() {
        let p = dgeom.point_of(i);
        let lo = fgeom.to_grid(p - reach);
        let hi = fgeom.to_grid(p + reach);
        // Grid coordinates of the box, clipped to the feature grid.
        let range = |a: usize| {
            let n = fgeom.res[a] as f32 - 1.0;
            let l = lo[a].ceil().clamp(0.0, n) as usize;
            let h = hi[a].floor().clamp(0.0, n) as usize;
            l..=h
        };
        for z in range(2) {
            for y in range(1) {
                for x in range(0) {
                    out.set(x + fx * (y + fy * z), true);
                }
            }
        }
    }
    out
}

/// Values of the points of `index`, `channels` per point, each written by
/// `fill(voxel, row)`; rows in ascending voxel order (the rank index's slots).
pub fn gather(index: &RankIndex, channels: usize, fill: impl Fn(usize, &mut [f16]) + Sync) -> Vec<f16> {
    let voxels: Vec<usize> = index.bits().ones().collect();
    let mut data = vec![f16::ZERO; voxels.len() * channels];
    data.par_chunks_mut(channels.max(1))
        .zip(voxels.par_iter())
        .for_each(|(row, &v)| fill(v, row));
    data
}

/// `density` with every point outside `occ` set to [`empty_raw`]: what the
/// file stores sparsely.
pub fn emptied_density(density: &DensityGrid, occ: &Bitmap) -> DensityGrid {
    let empty = empty_raw(density.activation);
    let raw = density
        .raw
        .par_iter()
        .enumerate()
        .map(|(i, &r)| if occ.get(i) { r } else { empty })
        .collect();
    DensityGrid {
        geom: density.geom,
        raw,
        activation: density.activation,
    }
}

/// A dense channel grid restricted to the points of `index` (same geometry).
fn restrict(g: &ChannelGrid, index: &Arc<RankIndex>) -> ChannelGrid {
    let ch = g.channels;
    let data = gather(index, ch, |v, row| row.copy_from_slice(&g.data[v * ch..(v + 1) * ch]));
    ChannelGrid::sparse(g.geom, ch, index.clone(), data)
}

/// The field with appearance and features stored for the occupied points
/// only (module docs) and density emptied elsewhere. Fields that already
/// have an occupancy index come back unchanged; VM grids stay as they are.
pub fn sparsify(field: &Field) -> Result<Field> {
    if field.occupancy.is_some() {
        return Ok(field.clone());
    }
    let geom = field.geom();
    let bits = density_occupancy(&field.density);
    let density = emptied_density(&field.density, &bits);
    let index = Arc::new(RankIndex::new(bits));
    let dense_here = |g: &ChannelGrid| matches!(g.layout, Layout::Dense) && g.geom.res == geom.res;
    let appearance = match &field.appearance {
        Appearance::Rgb(g) if dense_here(g) => Appearance::Rgb(restrict(g, &index)),
        Appearance::Sh2(g) if dense_here(g) => Appearance::Sh2(restrict(g, &index)),
        other => other.clone(),
    };
    let features = match &field.features {
        Some(Features::Grid(g)) if matches!(g.layout, Layout::Dense) => {
            let fi = Arc::new(RankIndex::new(feature_occupancy(index.bits(), &geom, &g.geom)));
            Some(Features::Grid(restrict(g, &fi)))
        }
        other => other.clone(),
    };
    Ok(Field::new(density, appearance, features, Some(index)).in_space_of(field))
}
