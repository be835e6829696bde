//! Unseen pockets enclosed by an object.
//!
//! A trained field keeps density inside solids and behind surfaces that no
//! training ray reaches; distillation gives those voxels no features (their
//! feature cells never get a gradient), so no stroke matches them and they
//! stay behind when the object is moved: lego at 800×800 on a 320 grid has
//! 15 % of its solid voxels in feature cells that are exactly zero, and a
//! moved lego left a grey ghost of its insides in its old place.
//!
//! A connected pocket of such unseen solid voxels joins the object when
//! everything solid around it is either the object or unseen too: it is
//! enclosed by the object. A pocket that also touches a seen voxel outside
//! the object (the inside of a table under a pot) belongs to nobody it can
//! be told from, and is left alone.

use super::grow::{GrowParams, Offsets};
use crate::field::{Bitmap, FeatureCache};
use rayon::prelude::*;

/// A voxel is unseen when its feature is shorter than this share of the
/// median feature length over solid voxels.
pub const UNSEEN_SHARE: f32 = 0.05;

/// Adds to `mask` every pocket of unseen solid voxels (σ above `floor`)
/// that touches it and is enclosed by it; returns how many voxels joined.
pub fn fill_enclosed_unseen(cache: &FeatureCache, mask: &mut Bitmap, floor: f32) -> usize {
    let Some(limit) = unseen_limit(cache, floor) else {
        return 0;
    };
    let unseen_row = |r: usize| cache.sigma[r] > floor && (cache.inv_norm[r] == 0.0 || 1.0 / cache.inv_norm[r] < limit);
    let unseen = |v: usize| cache.index.slot(v).is_some_and(unseen_row);
    let offs = Offsets::new(cache.geom.res, &GrowParams::default());
    let solid = |v: usize| cache.index.slot(v).is_some_and(|r| cache.sigma[r] > floor);
    // Pockets found open (touching a seen solid voxel outside the object),
    // as far as they were flooded: a flood that reaches one of their
    // voxels is in the same pocket, so open too. That lets a flood stop at
    // the first seen voxel it meets instead of walking the whole pocket (a
    // floor's or a table's unseen inside, 30 ms a stroke on the tabletop's
    // floor). An enclosed pocket joins the mask at once: it is a whole
    // connected pocket, so no later flood reaches it anyway.
    let mut visited = Bitmap::new(cache.geom.res);
    let mut open_pockets = Bitmap::new(cache.geom.res);
    let (mut added, mut pocket, mut stack) = (0, Vec::new(), Vec::new());
    for s in pocket_starts(cache, mask, &offs, &unseen_row) {
        if visited.get(s) {
            continue;
        }
        let mut open = false;
        visited.set(s, true);
        stack.push(s);
        while let Some(v) = stack.pop() {
            pocket.push(v);
            offs.for_each(v, |_, n| {
                if open || mask.get(n) {
                    return;
                }
                if visited.get(n) {
                    open |= open_pockets.get(n);
                } else if unseen(n) {
                    visited.set(n, true);
                    stack.push(n);
                } else if solid(n) {
                    open = true;
                }
            });
            if open {
                break;
            }
        }
        if open {
            for v in pocket.drain(..).chain(stack.drain(..)) {
                open_pockets.set(v, true);
            }
        } else {
            added += pocket.len();
            for v in pocket.drain(..) {
                mask.set(v, true);
            }
        }
    }
    added
}

/// The unseen voxels outside `mask` next to it, where its pockets start:
/// the unseen rows (a few per cent of the cache) that touch the mask,
/// found in parallel (scanning the neighbours of every mask voxel instead
/// took 5–10 ms a stroke). A pocket is a connected set of unseen voxels
/// whichever of its voxels its flood starts from, and the mask does not
/// change while they flood, so the order of the starts does not change
/// what joins.
fn pocket_starts(
    cache: &FeatureCache,
    mask: &Bitmap,
    offs: &Offsets,
    unseen_row: &(impl Fn(usize) -> bool + Sync),
) -> Vec<usize> {
    (0..cache.len())
        .into_par_iter()
        .filter(|&r| unseen_row(r))
        .map(|r| cache.voxels[r] as usize)
        .filter(|&v| !mask.get(v) && touches(mask, offs, v))
        .collect()
}

/// Whether voxel `v` has a neighbour in `mask`.
fn touches(mask: &Bitmap, offs: &Offsets, v: usize) -> bool {
    let mut any = false;
    offs.for_each(v, |_, n| any |= mask.get(n));
    any
}

/// The feature length below which a solid voxel is unseen (see
/// [`UNSEEN_SHARE`]); `None` when no solid voxel has a feature.
fn unseen_limit(cache: &FeatureCache, floor: f32) -> Option<f32> {
    let mut norms: Vec<f32> = (0..cache.voxels.len())
        .filter(|&r| cache.sigma[r] > floor && cache.inv_norm[r] > 0.0)
        .map(|r| 1.0 / cache.inv_norm[r])
        .collect();
    if norms.is_empty() {
        return None;
    }
    let mid = norms.len() / 2;
    let median = *norms.select_nth_unstable_by(mid, f32::total_cmp).1;
    Some(UNSEEN_SHARE * median)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{Aabb, FieldBuilder};
    use glam::Vec3;

    /// A solid 16×8×8 bar of two objects side by side: the left one
    /// (x < 8, feature [1, 0]) has an unseen core (zero features) at
    /// x 2–5, y and z 2–5; an unseen slab at x 7–8 straddles the two
    /// objects (the right one, x ≥ 8, has feature [0, 1]).
    fn two_blocks() -> crate::field::Field {
        FieldBuilder::new(Aabb::new(Vec3::ZERO, Vec3::new(15.0, 7.0, 7.0)), [16, 8, 8]).build(
            |_| 50.0,
            |_| Vec3::ONE,
            Some((2, &|p: Vec3, out: &mut [f32]| {
                let core = (1.5..5.5).contains(&p.x) && (1.5..5.5).contains(&p.y) && (1.5..5.5).contains(&p.z);
                let slab = (6.5..8.5).contains(&p.x) && (2.5..4.5).contains(&p.y) && (2.5..4.5).contains(&p.z);
                let f = if core || slab {
                    [0.0, 0.0]
                } else if p.x < 7.5 {
                    [1.0, 0.0]
                } else {
                    [0.0, 1.0]
                };
                out.copy_from_slice(&f);
            })),
        )
    }

    #[test]
    fn an_unseen_core_joins_the_object_around_it_and_a_shared_pocket_does_not() {
        let cache = FeatureCache::build(&two_blocks()).unwrap();
        let res = cache.geom.res;
        let xyz = |v: usize| (v % res[0], v / res[0] % res[1], v / (res[0] * res[1]));
        let core = |v: usize| {
            let (x, y, z) = xyz(v);
            (2..=5).contains(&x) && (2..=5).contains(&y) && (2..=5).contains(&z)
        };
        // The left object's seen voxels: everything left of the slab that
        // is not its core or the slab.
        let unseen = |v: usize| {
            let (x, y, z) = xyz(v);
            core(v) || ((7..=8).contains(&x) && (3..=4).contains(&y) && (3..=4).contains(&z))
        };
        let mut mask = Bitmap::from_fn(res, |v| xyz(v).0 < 8 && !unseen(v));
        let before = mask.clone();
        let added = fill_enclosed_unseen(&cache, &mut mask, 1e-3);
        assert_eq!(added, 4 * 4 * 4, "the core, and nothing else");
        for v in 0..mask.len() {
            assert_eq!(mask.get(v), before.get(v) || core(v), "voxel {:?}", xyz(v));
        }
        // With nothing seen at all there is nothing to measure against.
        let mut empty = Bitmap::new(res);
        assert_eq!(fill_enclosed_unseen(&cache, &mut empty, 1e-3), 0);
    }

    /// The plain rule: flood each pocket whole, then add the enclosed ones.
    fn reference(cache: &FeatureCache, mask: &Bitmap, floor: f32) -> Bitmap {
        let limit = unseen_limit(cache, floor).unwrap();
        let row_unseen =
            |r: usize| cache.sigma[r] > floor && (cache.inv_norm[r] == 0.0 || 1.0 / cache.inv_norm[r] < limit);
        let unseen = |v: usize| cache.index.slot(v).is_some_and(row_unseen);
        let solid = |v: usize| cache.index.slot(v).is_some_and(|r| cache.sigma[r] > floor);
        let offs = Offsets::new(cache.geom.res, &GrowParams::default());
        let (mut visited, mut out) = (Bitmap::new(cache.geom.res), mask.clone());
        for s in (0..mask.len()).filter(|&v| unseen(v) && !mask.get(v) && touches(mask, &offs, v)) {
            if visited.get(s) {
                continue;
            }
            let (mut pocket, mut stack, mut open) = (vec![], vec![s], false);
            visited.set(s, true);
            while let Some(v) = stack.pop() {
                pocket.push(v);
                offs.for_each(v, |_, n| {
                    if mask.get(n) || visited.get(n) {
                    } else if unseen(n) {
                        visited.set(n, true);
                        stack.push(n);
                    } else if solid(n) {
                        open = true;
                    }
                });
            }
            if !open {
                pocket.into_iter().for_each(|v| out.set(v, true));
            }
        }
        out
    }

    /// Scattered unseen blobs and empty cells, and masks of random boxes:
    /// many pockets, some reached from several starts, open and enclosed
    /// ones side by side. The early-stopping flood adds exactly what the
    /// plain one does.
    #[test]
    fn stopping_at_the_first_seen_voxel_adds_what_the_whole_flood_does() {
        let hash = |p: Vec3, k: u64| {
            let q = (p.x as i64 * 73_856_093) ^ (p.y as i64 * 19_349_663) ^ (p.z as i64 * 83_492_791);
            crate::util::SplitMix64::new(q as u64 ^ k).unit()
        };
        let res = [20, 18, 16];
        let field = FieldBuilder::new(Aabb::new(Vec3::ZERO, Vec3::new(19.0, 17.0, 15.0)), res).build(
            |p| if hash(p, 1) < 0.08 { 0.0 } else { 50.0 },
            |_| Vec3::ONE,
            Some((2, &|p: Vec3, out: &mut [f32]| {
                let blob = hash((p / 3.0).floor(), 2) < 0.35;
                out.copy_from_slice(&if blob { [0.0, 0.0] } else { [1.0, 0.5] });
            })),
        );
        let cache = FeatureCache::build(&field).unwrap();
        let mut total = 0;
        for seed in 0..12u64 {
            let mut rng = crate::util::SplitMix64::new(seed);
            let lo: Vec<usize> = (0..3).map(|k| rng.below(res[k] / 2)).collect();
            let hi: Vec<usize> = (0..3).map(|k| lo[k] + 3 + rng.below(res[k] / 2)).collect();
            let mask = Bitmap::from_fn(res, |v| {
                let c = [v % res[0], v / res[0] % res[1], v / (res[0] * res[1])];
                (0..3).all(|k| (lo[k]..hi[k]).contains(&c[k]))
                    && hash(Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32), 3) < 0.9
            });
            let want = reference(&cache, &mask, 1e-3);
            let mut got = mask.clone();
            let added = fill_enclosed_unseen(&cache, &mut got, 1e-3);
            assert!(got == want, "seed {seed}");
            assert_eq!(added, want.count() - mask.count());
            total += added;
        }
        assert!(total > 0, "some pocket was enclosed");
    }
}
