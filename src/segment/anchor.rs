//! Seeds joined to the stroke.
//!
//! NNFM seeds every voxel in the field whose feature is near the stroke's,
//! wherever it is: on a real capture, and on any scene where objects share
//! a look (two toys on a shelf, the fronds of the fern and the plants behind
//! it), the look-alikes far from the stroke are seeded too, and growth
//! then floods out from all of them. The user stroked one object, at one
//! place: the surface under the stroke (each pixel's expected hit point)
//! anchors the selection, and only the seeds joined to an anchor through
//! other seeds (26-connected) are kept. `SegmentParams::connected = false`
//! keeps the paper's global matching (select every look-alike at once).

use crate::field::runs::Runs;
use crate::field::{Bitmap, FeatureCache};
use crate::render::{Layer, Scene};
use glam::Vec3;

/// Voxels (of the field's own grid) within this many voxels of a stroke's
/// hit point start the search: the expected hit depth of a blurred surface
/// lies a voxel or so in front of or behind its solid voxels.
const ANCHOR_RADIUS: isize = 2;

/// [`ANCHOR_RADIUS`] in voxels of `cache`'s grid: one on a coarse copy,
/// whose voxels are twice as large (two would reach four fine voxels,
/// into a touching neighbour).
pub fn radius(cache: &FeatureCache) -> isize {
    let ratio = cache.geom.spacing().min_element() / cache.voxel_size;
    ((ANCHOR_RADIUS as f32 / ratio).round() as isize).max(1)
}

/// The voxels of `cache`'s grid at the world points `hits` (the stroke's
/// surface), through the transform of the scene layer whose field owns
/// `cache`; empty when no layer does or no point falls in the grid.
pub fn anchor_voxels(scene: &Scene, cache: &FeatureCache, hits: &[Vec3]) -> Vec<u32> {
    let Some(layer) = layer_of(scene, cache) else {
        return vec![];
    };
    let to_local = layer.to_world.inverse();
    let g = &cache.geom;
    let mut out: Vec<u32> = hits
        .iter()
        .filter_map(|&p| g.nearest(to_local.transform_point3(p)))
        .map(|[x, y, z]| g.index(x, y, z) as u32)
        .collect();
    out.sort_unstable();
    out.dedup();
    out
}

/// The layer of `scene` whose field owns `cache`.
pub fn layer_of<'a>(scene: &'a Scene, cache: &FeatureCache) -> Option<&'a Layer> {
    scene
        .layers
        .iter()
        .find(|l| l.field.cached_features().is_some_and(|c| std::ptr::eq(&*c, cache)))
}

/// The seeds joined to an anchor: every seed within `radius` (see
/// [`radius`]) of an anchor, and every seed 26-connected to those through
/// seeds. `None` when no seed is near an anchor (the caller keeps all
/// seeds).
pub fn joined_seeds(seed: &Bitmap, anchors: &[u32], radius: isize) -> Option<Bitmap> {
    let res = seed.res();
    let mut starts: Vec<usize> = anchors
        .iter()
        .flat_map(|&a| block(res, a as usize, radius))
        .filter(|&n| seed.get(n))
        .collect();
    if starts.is_empty() {
        return None;
    }
    starts.sort_unstable();
    starts.dedup();
    Some(Runs::of(seed).components_of(starts))
}

/// The voxels of `bits` within `radius` of an anchor, ascending.
pub fn near_anchors(bits: &Bitmap, anchors: &[u32], radius: isize) -> Vec<u32> {
    let res = bits.res();
    let mut out: Vec<u32> = anchors
        .iter()
        .flat_map(|&a| block(res, a as usize, radius))
        .filter(|&n| bits.get(n))
        .map(|n| n as u32)
        .collect();
    out.sort_unstable();
    out.dedup();
    out
}

/// In-grid voxels of the cube of half-side `r` around voxel `v`.
fn block(res: [usize; 3], v: usize, r: isize) -> impl Iterator<Item = usize> {
    let [nx, ny, nz] = res.map(|n| n as isize);
    let (x, y, z) = (
        (v % res[0]) as isize,
        ((v / res[0]) % res[1]) as isize,
        (v / (res[0] * res[1])) as isize,
    );
    (-r..=r)
        .flat_map(move |dz| (-r..=r).flat_map(move |dy| (-r..=r).map(move |dx| (x + dx, y + dy, z + dz))))
        .filter(move |&(a, b, c)| a >= 0 && b >= 0 && c >= 0 && a < nx && b < ny && c < nz)
        .map(move |(a, b, c)| (a + nx * (b + ny * c)) as usize)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_seed_components_near_an_anchor_are_kept() {
        let res = [12, 4, 4];
        let idx = |x: usize, y: usize, z: usize| x + 12 * (y + 4 * z);
        let mut seed = Bitmap::new(res);
        // Two bars along x, at x 0..4 and 7..12, joined by nothing.
        for x in (0..4).chain(7..12) {
            seed.set(idx(x, 1, 1), true);
        }
        // A diagonal step still joins (26-connectivity).
        seed.set(idx(4, 2, 2), true);
        let joined = joined_seeds(&seed, &[idx(0, 1, 1) as u32], ANCHOR_RADIUS).unwrap();
        assert_eq!(joined.count(), 5);
        assert!(joined.get(idx(4, 2, 2)) && !joined.get(idx(7, 1, 1)));
        // An anchor two voxels off the bar (a blurred hit depth) still finds it.
        let joined = joined_seeds(&seed, &[idx(11, 3, 3) as u32], ANCHOR_RADIUS).unwrap();
        assert_eq!(joined.count(), 5);
        assert!(joined.get(idx(7, 1, 1)) && !joined.get(idx(0, 1, 1)));
        // Far from every seed: nothing to anchor to.
        let mut lone = Bitmap::new(res);
        lone.set(idx(11, 0, 0), true);
        assert!(joined_seeds(&lone, &[idx(0, 3, 3) as u32], ANCHOR_RADIUS).is_none());
    }
}
