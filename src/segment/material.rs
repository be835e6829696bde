//! Growth through the stroke's material: an object that is not flat and
//! whose features drift across it.
//!
//! A teacher sees a large object's near and far parts differently (a
//! shelf's top board and its bottom board, its sides from inside and
//! outside), so a stroke's feature flood stops part way, and the stable
//! search finds no boundary: on the ViT splat benchmark the shelf's flood
//! reached two thirds of it by squared distance 1.2 and the region stayed
//! the seeds (IoU 0.168). A flat region goes on along its slab
//! ([`super::plane`]); one that is not goes on through voxels of the
//! stroke's own material, where colour tells things apart (see
//! `surface_colours` in the parent module):
//!
//! - the colour is within [`SAME_MATERIAL`] of one the stroke's pixels
//!   show, half the reach at which a colour merely looks like the stroke's
//!   (a clay pot's shaded foot looks like the wooden table it stands on at
//!   that reach, and the table's flood climbed into the pot);
//! - the voxel is opaque ([`OPAQUE_ALPHA`] across one voxel): a trained
//!   field's haze in front of a wall has the wall's colour;
//! - its features are not the opposite of the stroke's
//!   ([`FARTHEST`]): colour alone never decides against features that
//!   disagree outright.
//!
//! A flat region keeps to its slab because a flat support's material is
//! often another support's too: a floor of planks and a wooden table top
//! are the same colour, and a floor's region that holds a few voxels of the
//! table (where a trained field blurs the legs) would climb onto it.

use super::flood;
use crate::field::{Bitmap, FeatureCache};
use glam::Vec3;

/// A colour within this squared RGB distance of one a stroke's pixels show
/// is the stroke's material.
pub const SAME_MATERIAL: f32 = 0.01;

/// The least opacity across one voxel of a voxel the growth takes.
pub const OPAQUE_ALPHA: f32 = 0.5;

/// The largest squared distance between unit features (in [0, 4]; 2 is
/// orthogonal) of a voxel the growth takes from the stroke's centres.
pub const FARTHEST: f32 = 3.0;

/// The σ of [`OPAQUE_ALPHA`] across a voxel of size `h`.
pub fn opaque_sigma(h: f32) -> f32 {
    -(1.0 - OPAQUE_ALPHA).ln() / h.max(1e-12)
}

/// `region` grown through the 6-neighbours of its voxels whose σ is above
/// `sigma_floor`, whose colour (the cache's per-voxel diffuse colour)
/// `material` accepts and whose cache row `near` accepts (the feature
/// test, asked last: it may measure a distance).
pub fn grow_in_material(
    cache: &FeatureCache,
    region: &Bitmap,
    sigma_floor: f32,
    material: impl Fn(Vec3) -> bool,
    mut near: impl FnMut(usize) -> bool,
) -> Bitmap {
    flood::faces(&cache.geom, region, |n| match cache.index.slot(n) {
        Some(r) => cache.sigma[r] > sigma_floor && material(cache.colours[r]) && near(r),
        None => false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{Aabb, GridGeom, RankIndex};

    const WOOD: Vec3 = Vec3::new(0.7, 0.5, 0.3);

    /// Known answers on a wooden L (a top board and a side) whose features
    /// turn by 40° along it, with a red toy on the board, a block of
    /// wood joined to the board's far end only through haze of its colour,
    /// and a wooden block under the board whose features are the opposite
    /// of the stroke's. From a piece of the board, the growth takes the
    /// whole L and nothing else.
    #[test]
    fn grows_through_the_material_and_nothing_else() {
        let n = 32;
        let geom = GridGeom::new(Aabb::new(Vec3::ZERO, Vec3::splat(n as f32)), [n; 3]);
        let inside = |v: usize, lo: [usize; 3], hi: [usize; 3]| {
            let c = geom.coords(v);
            (0..3).all(|a| c[a] >= lo[a] && c[a] < hi[a])
        };
        let board = |v| inside(v, [4, 10, 8], [28, 12, 24]);
        let side = |v| inside(v, [4, 0, 8], [6, 10, 24]);
        let toy = |v| inside(v, [12, 12, 12], [16, 16, 16]);
        let haze = |v| inside(v, [28, 10, 8], [30, 12, 24]);
        let beyond = |v| inside(v, [30, 10, 8], [32, 12, 24]);
        let opposite = |v| inside(v, [20, 6, 12], [24, 10, 16]);
        let solid = Bitmap::from_fn(geom.res, |v| {
            board(v) || side(v) || toy(v) || haze(v) || beyond(v) || opposite(v)
        });
        let voxels: Vec<u32> = solid.ones().map(|v| v as u32).collect();
        let (mut sigma, mut feats, mut colours) = (vec![], vec![], vec![]);
        for &v in &voxels {
            let v = v as usize;
            let c = geom.coords(v);
            // The L's features turn with the path along it: 41° at the
            // side's foot, 79° at the board's far end (beyond: 91°).
            let turn = (c[0] as f32 + (10.0 - c[1].min(10) as f32)) / 34.0 * 100f32.to_radians();
            let (angle, colour, s) = match () {
                _ if toy(v) => (0.0, Vec3::new(0.9, 0.1, 0.1), 10.0),
                _ if haze(v) => (turn, WOOD, 0.1),
                _ if opposite(v) => (std::f32::consts::PI, WOOD, 10.0),
                _ => (turn, WOOD + Vec3::splat(0.02 * (c[2] % 3) as f32), 10.0),
            };
            sigma.push(s);
            feats.extend([angle.cos(), angle.sin()]);
            colours.push(colour);
        }
        let index = RankIndex::new(solid.clone());
        let cache = FeatureCache::from_parts(geom, 2, 1.0, voxels, index, sigma, feats, colours);
        let g = &cache.geom;
        let shown = [WOOD, WOOD + Vec3::splat(0.02), WOOD + Vec3::splat(0.04)];
        let material = |c: Vec3| shown.iter().any(|s| (c - *s).length_squared() <= SAME_MATERIAL);
        // Squared distance of a row's unit feature from the stroke's (1, 0).
        let near = |r: usize| {
            let f = &cache.feats[2 * r..2 * r + 2];
            (f[0] - 1.0).powi(2) + f[1].powi(2) <= FARTHEST
        };
        let seed = Bitmap::from_fn(g.res, |v| board(v) && g.coords(v)[0] < 10);
        let grown = grow_in_material(&cache, &seed, opaque_sigma(1.0), material, near);
        let shelf = Bitmap::from_fn(g.res, |v| board(v) || side(v));
        assert_eq!(grown.count(), shelf.count());
        assert_eq!(
            grown, shelf,
            "the whole L, without the toy, the haze, the block beyond it or the opposite block"
        );
        // Without the feature test the opposite block is taken too; with a
        // floor under the haze's σ, the block beyond it as well.
        let all = grow_in_material(&cache, &seed, opaque_sigma(1.0), material, |_| true);
        assert_eq!(all.count(), shelf.count() + 4 * 4 * 4);
        let hazy = grow_in_material(&cache, &seed, 0.05, material, near);
        assert_eq!(hazy.count(), shelf.count() + 2 * 2 * 16 * 2);
    }
}
