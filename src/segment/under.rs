//! What holds a standing object up: an excavator's tracks under its body.
//!
//! A stroke along a toy excavator's yellow body and arm selects them, but
//! its black tracks look like something else to the teacher (on the splat
//! benchmark the ViT's region took 83 of the tracks' 334 Gaussians), and
//! nothing in the features joins them. Their place does: they stand on the
//! ground under the body, inside its outline and under the stroke, and
//! hold it up. A table's legs are the same thing under a flat region
//! ([`super::supports`]); this is the rule for any other shape, and it
//! needs to know which way is up ([`crate::field::Field::up`]).
//!
//! The ground is the highest level, at most [`ABOVE_LOWEST`] above the
//! region's lowest voxel, whose annulus around the region's outline is
//! solid outside the region for [`GROUND`] of its cells (as in
//! [`super::footing`]). Above it, the solid voxels outside the region
//! and below its top are grouped (26-neighbours); a group touching the
//! region joins it when it holds it up:
//! - it stands on the ground (its lowest voxel within [`ON_GROUND`] levels
//!   of it) and rises at least [`MIN_SPAN`] levels (a blurred ground's
//!   upper levels around the region's foot are flat);
//! - at least [`UNDER_SHARE`] of it lies within one cell of the region's
//!   outline (a neighbour standing beside the region, a box a mug leans
//!   on, lies mostly outside it);
//! - it lies lower than the region (its mean height below the region's);
//! - it is under the stroke (within one cell of a voxel under it): where
//!   the region already took a neighbour's top by mistake, that
//!   neighbour's sides are not added to the mistake.
//!
//! Something the region stands on that is not part of the object (a
//! plinth no wider than the statue on it) would join it too; a negative
//! stroke takes it off.

use super::footing::{Frame, Outline, GROUND};
use crate::field::{Bitmap, GridGeom};
use glam::Vec3;

/// The ground may lie this many levels above the region's lowest voxel (a
/// region that took a voxel or two of the ground's blur).
const ABOVE_LOWEST: usize = 2;
/// A group stands on the ground when its lowest voxel is at most this many
/// levels above it.
const ON_GROUND: usize = 2;
/// Levels a group must span to hold anything up.
const MIN_SPAN: usize = 3;
/// Share of a group that must lie within one cell of the region's outline.
const UNDER_SHARE: f32 = 0.5;
/// A group larger than this many times the region is the rest of the
/// scene (a shelf's boards and sides), not its undercarriage.
const MOST: usize = 2;

/// `region` with what holds it up (module docs); `solid` marks the voxels
/// that can hold it, `up` is the scene's up direction, `anchors` the voxels
/// under the stroke.
pub fn with_undercarriage(geom: &GridGeom, solid: &Bitmap, region: Bitmap, up: Vec3, anchors: &[u32]) -> Bitmap {
    let frame = Frame::new(geom, up);
    let voxels: Vec<usize> = region.ones().collect();
    if voxels.is_empty() || anchors.is_empty() {
        return region;
    }
    let heights = || voxels.iter().map(|&v| frame.height(v));
    let (lowest, top) = (heights().min().unwrap_or(0), heights().max().unwrap_or(0));
    let outline = Outline::of(&frame, voxels.iter().copied());
    let outside = |v: usize| solid.get(v) && !region.get(v);
    let annulus = outline.ring();
    let Some(ground) = (0..=(lowest + ABOVE_LOWEST).min(top))
        .rev()
        .find(|&h| annulus.solid_share(&frame, h, outside) >= GROUND)
    else {
        return region;
    };
    let under = Under {
        frame: &frame,
        outline,
        stroke: Outline::of(&frame, anchors.iter().map(|&v| v as usize)),
        ground,
        mean_height: heights().map(|h| h as f64).sum::<f64>() / voxels.len() as f64,
    };
    let candidate = |v: usize| outside(v) && (ground + 1..top).contains(&frame.height(v));
    let groups = Groups {
        geom,
        candidate: &candidate,
        most: MOST * voxels.len(),
    };
    let mut seen = Bitmap::new(geom.res);
    let mut out = region.clone();
    for &v in &voxels {
        geom.neighbours26(v, |n| {
            if seen.get(n) || !candidate(n) {
                return;
            }
            let group = groups.collect(n, &mut seen);
            if group.as_ref().is_some_and(|g| under.holds_up(g)) {
                for g in group.into_iter().flatten() {
                    out.set(g as usize, true);
                }
            }
        });
    }
    out
}

/// What a group of voxels must be to hold the region up (module docs).
struct Under<'a> {
    frame: &'a Frame<'a>,
    /// The region's outline and the stroke's, seen along up.
    outline: Outline,
    stroke: Outline,
    ground: usize,
    mean_height: f64,
}

impl Under<'_> {
    fn holds_up(&self, group: &[u32]) -> bool {
        let heights = || group.iter().map(|&g| self.frame.height(g as usize));
        let (low, high) = (heights().min().unwrap_or(0), heights().max().unwrap_or(0));
        let mean = heights().map(|h| h as f64).sum::<f64>() / group.len().max(1) as f64;
        let cell = |g: &u32| self.frame.cell(*g as usize);
        let under = group.iter().filter(|g| self.outline.near(cell(g))).count();
        low <= self.ground + ON_GROUND
            && high + 1 - low >= MIN_SPAN
            && under as f32 >= UNDER_SHARE * group.len() as f32
            && mean < self.mean_height
            && group.iter().any(|g| self.stroke.near(cell(g)))
    }
}

/// The flood that groups candidate voxels (26-neighbours). A group too
/// large to hold the region up is still flooded whole, once (its voxels
/// are marked seen), so a stroke visits each candidate at most once: no
/// more than the solid voxels below the region's top (on the fern's
/// default field the walk's strokes took the same time with the rule as
/// without it).
struct Groups<'a> {
    geom: &'a GridGeom,
    candidate: &'a dyn Fn(usize) -> bool,
    /// A group past this size is given up (`None`).
    most: usize,
}

impl Groups<'_> {
    /// The group of candidate `start`, marking what it floods in `seen`;
    /// `None` past [`Groups::most`] voxels (the rest of that group is
    /// marked too, so no later start floods it again).
    fn collect(&self, start: usize, seen: &mut Bitmap) -> Option<Vec<u32>> {
        let mut group = vec![start as u32];
        seen.set(start, true);
        let mut next = 0;
        while next < group.len() {
            let v = group[next] as usize;
            next += 1;
            self.geom.neighbours26(v, |n| {
                if !seen.get(n) && (self.candidate)(n) {
                    seen.set(n, true);
                    group.push(n as u32);
                }
            });
        }
        (group.len() <= self.most).then_some(group)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::segment::toy::{union, Toy};

    /// The region is the toy's body, the stroke across its top; the
    /// tracks hold it up, the jar stands beside it.
    #[test]
    fn the_tracks_under_the_stroke_join_the_jar_beside_does_not() {
        let t = Toy::new();
        let solid = union(&[&t.board, &t.body, &t.tracks, &t.jar]);
        let got = with_undercarriage(&t.geom, &solid, t.body.clone(), Vec3::Y, &t.anchors);
        let kept = |b: &Bitmap| b.ones().filter(|&v| got.get(v)).count();
        assert_eq!(kept(&t.tracks), t.tracks.count(), "the tracks join");
        assert_eq!(kept(&t.jar), 0, "the jar beside stays out");
        assert_eq!(kept(&t.board), 0, "the ground stays out");
        assert_eq!(got.count(), t.body.count() + t.tracks.count());
        // Upside down (up = −y), the body has nothing under it.
        let flipped = with_undercarriage(&t.geom, &solid, t.body.clone(), Vec3::NEG_Y, &t.anchors);
        assert!(flipped == t.body);
        // A stroke on one end of the body over one track only: that track
        // joins, the other does not.
        let end: Vec<u32> = t
            .body
            .ones()
            .filter(|&v| matches!(t.at(v), [14, 23, z] if (21..26).contains(&z)))
            .map(|v| v as u32)
            .collect();
        let one = with_undercarriage(&t.geom, &solid, t.body.clone(), Vec3::Y, &end);
        let near_track = |v: usize| t.at(v)[2] < 30;
        assert!(t.tracks.ones().filter(|&v| near_track(v)).all(|v| one.get(v)));
        assert!(t.tracks.ones().filter(|&v| !near_track(v)).all(|v| !one.get(v)));
        // A body resting on the board itself: nothing under it to add.
        let low_body = t.block([10, 8, 20], [40, 16, 44]);
        let low_solid = union(&[&t.board, &low_body]);
        let low_anchors: Vec<u32> = low_body
            .ones()
            .filter(|&v| t.at(v)[1] == 15)
            .map(|v| v as u32)
            .collect();
        assert!(with_undercarriage(&t.geom, &low_solid, low_body.clone(), Vec3::Y, &low_anchors) == low_body);
    }
}
