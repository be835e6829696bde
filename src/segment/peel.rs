//! Peeling the support off a region's rim.
//!
//! Where an object rests on something (a ball on the floor, a pot on the
//! table, books on a board) the voxels of the contact ring carry features
//! blurred between the two, and the cut takes a ring of the support one or
//! two voxels wide with the object. Those voxels show the support's colour,
//! not the object's: a rim voxel of the region is peeled off when no
//! stroke pixel shows its colour and a solid neighbour outside the region
//! has nearly its colour. A part of the object in a colour the stroke
//! does not show (a mug's coffee, an excavator's black tracks) stays, as
//! long as what lies outside next to it looks different.

use crate::field::{Bitmap, FeatureCache};
use glam::Vec3;

/// Rounds of peeling: the rings are at most two voxels wide.
pub const ROUNDS: usize = 2;

/// A rim voxel and an outside neighbour within this squared RGB distance
/// have the same colour (the distance at which a voxel "shows" a stroke
/// colour, `LIKE_STROKE` in the parent module).
pub const SAME_COLOUR: f32 = 0.02;

/// `region` with its rim voxels of a support's colour removed, up to
/// `rounds` voxels deep: voxels of the region whose colour `shown` rejects
/// and that have a solid (in `solid`) 6-neighbour outside the region within
/// [`SAME_COLOUR`] of their colour. Each round decides on the region as it
/// was at its start, so the order of the voxels does not matter.
pub fn peel_support(
    cache: &FeatureCache,
    solid: &Bitmap,
    mut region: Bitmap,
    rounds: usize,
    shown: impl Fn(Vec3) -> bool,
) -> Bitmap {
    let colour = |v: usize| cache.index.slot(v).map(|r| cache.colours[r]);
    for _ in 0..rounds {
        let outside = |n: usize| !region.get(n) && solid.get(n);
        let rim_of_support = |v: usize| {
            // The rim first: two bitmap reads per face rule out the
            // region's inside (most of a large region) before its colour
            // is looked up (the palette test was most of this rule's time
            // on lego's whole-model region).
            if !super::flood::face_neighbours(&cache.geom, v).any(outside) {
                return false;
            }
            let Some(c) = colour(v).filter(|&c| !shown(c)) else {
                return false;
            };
            super::flood::face_neighbours(&cache.geom, v)
                .any(|n| outside(n) && colour(n).is_some_and(|o| (o - c).length_squared() <= SAME_COLOUR))
        };
        let peeled: Vec<usize> = region.ones().filter(|&v| rim_of_support(v)).collect();
        if peeled.is_empty() {
            break;
        }
        for v in peeled {
            region.set(v, false);
        }
    }
    region
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{Aabb, GridGeom, RankIndex};

    /// A red ball resting on a grey floor, as a cache: every voxel of
    /// either solid, coloured by what it is; the ball's top cap a brown
    /// "coffee" (a colour the stroke does not show, under air).
    fn scene() -> (FeatureCache, Bitmap, Bitmap, Bitmap) {
        let n = 24;
        let geom = GridGeom::new(Aabb::new(Vec3::ZERO, Vec3::splat(n as f32)), [n; 3]);
        let centre = Vec3::new(12.0, 10.0, 12.0);
        let floor = Bitmap::from_fn(geom.res, |v| geom.coords(v)[1] < 4);
        let ball = Bitmap::from_fn(geom.res, |v| geom.point_of(v).distance(centre) <= 6.0 && !floor.get(v));
        let solid = Bitmap::from_fn(geom.res, |v| floor.get(v) || ball.get(v));
        let index = RankIndex::new(solid.clone());
        let voxels: Vec<u32> = solid.ones().map(|v| v as u32).collect();
        let colours = voxels
            .iter()
            .map(|&v| match (floor.get(v as usize), geom.point_of(v as usize).y > 14.5) {
                (true, _) => Vec3::splat(0.5),
                (false, true) => Vec3::new(0.4, 0.25, 0.1),
                (false, false) => Vec3::new(0.9, 0.1, 0.1),
            })
            .collect();
        let k = voxels.len();
        let cache = FeatureCache::from_parts(geom, 1, 1.0, voxels, index, vec![10.0; k], vec![1.0; k], colours);
        (cache, solid, floor, ball)
    }

    /// Known answers: the ball with a floor ring two voxels deep and wider
    /// than the ball's foot loses the ring and nothing of itself; the cap
    /// in a colour the stroke does not show stays, for nothing outside it
    /// has its colour; a region with nothing of the support's colour next
    /// to it is left alone; a stroke that shows grey keeps the ring.
    #[test]
    fn the_supports_ring_is_peeled_and_the_object_kept() {
        let (cache, solid, floor, ball) = scene();
        let g = &cache.geom;
        let red = |c: Vec3| (c - Vec3::new(0.9, 0.1, 0.1)).length_squared() <= SAME_COLOUR;
        let ring = Bitmap::from_fn(g.res, |v| {
            let p = g.point_of(v);
            floor.get(v) && g.coords(v)[1] >= 2 && Vec3::new(p.x - 12.0, 0.0, p.z - 12.0).length() <= 4.0
        });
        assert!(ring.count() > 50);
        let taken = Bitmap::from_fn(g.res, |v| ball.get(v) || ring.get(v));
        let peeled = peel_support(&cache, &solid, taken.clone(), ROUNDS, red);
        assert_eq!(peeled, ball, "the ring goes, the ball and its cap stay");
        // Zero rounds change nothing.
        assert_eq!(peel_support(&cache, &solid, taken.clone(), 0, red), taken);
        assert_eq!(peel_support(&cache, &solid, ball.clone(), ROUNDS, red), ball);
        let grey_too = |c: Vec3| red(c) || (c - Vec3::splat(0.5)).length_squared() <= SAME_COLOUR;
        assert_eq!(peel_support(&cache, &solid, taken.clone(), ROUNDS, grey_too), taken);
    }
}
