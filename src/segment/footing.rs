//! The layer of its support that a standing object's region takes.
//!
//! A mug on a table: at the field's resolution the table's top is blurred
//! a voxel up into the mug's foot, and under the foot the teacher's
//! features are the mug's (its patch tokens cover both), so the stroke's
//! region takes a patch of the table top the shape of the foot (the
//! realistic benchmark's mug and box: 39 and 41 voxels, a tenth of each
//! object). Nothing in the features or the colours tells that patch from
//! the foot; the level it lies at does: there, the ground around the
//! region's outline is solid too. Around the foot's own lowest level there
//! is air (or, at most, a neighbour's side).
//!
//! So, walking up from the region's lowest level, a level at which the
//! annulus around the region's outline (cells two to four voxels from it,
//! past the blurred contact) is solid outside the region for at least
//! [`GROUND`] of its cells is the ground's, and leaves the region; the
//! walk stops at the first level that is not, at one the stroke touches,
//! and after [`MAX_LEVELS`]. Measured on the realistic benchmark's fields
//! (share of the annulus solid): at the levels the table's and the board's
//! tops took 0.86–1.00; at the first level of the objects above them
//! 0.03–0.70 (the mug's and the box's 0.46–0.59, where each stands next to
//! the other).
//!
//! It needs to know which way is up (a field's [`crate::field::Field::up`],
//! from the cameras it was trained from): without it, the top of a shelf
//! board under the toys on it is as much "a level beside solid" as the
//! table under a mug (an earlier try that guessed the side from the plane
//! the region touches cut the shelf as if it stood on the toys).

use crate::field::{Bitmap, GridGeom};
use glam::Vec3;

/// A level whose annulus is at least this share solid is the ground's.
pub(super) const GROUND: f32 = 0.8;
/// The most levels of ground a region can have taken: the blur of a
/// trained surface is a voxel or two.
const MAX_LEVELS: usize = 3;
/// The annulus: cells more than `INNER` and at most `OUTER` cells (along
/// either in-plane axis) from the region's outline.
const INNER: usize = 1;
const OUTER: usize = 4;

/// `region` without the levels of ground it took (module docs); `solid`
/// marks the voxels that can be ground, `up` is the scene's up direction
/// (the grid axis nearest it is used), `anchors` the voxels under the
/// stroke (ascending).
pub fn off_the_ground(geom: &GridGeom, solid: &Bitmap, region: Bitmap, up: Vec3, anchors: &[u32]) -> Bitmap {
    let frame = Frame::new(geom, up);
    let Some(lowest) = region.ones().map(|v| frame.height(v)).min() else {
        return region;
    };
    // Only the lowest levels are looked at (a whole model's region holds
    // hundreds of thousands of voxels: no sort of them all).
    let mut by_level: Vec<(usize, u32)> = region
        .ones()
        .map(|v| (frame.height(v), v as u32))
        .filter(|&(h, _)| h < lowest + MAX_LEVELS)
        .collect();
    by_level.sort_unstable();
    let low: Vec<u32> = by_level.iter().map(|&(_, v)| v).collect();
    let annulus = Annulus::around(&frame, &low);
    let mut out = region;
    for level in by_level.chunk_by(|a, b| a.0 == b.0) {
        let touched = level.iter().any(|(_, v)| anchors.binary_search(v).is_ok());
        if touched || annulus.solid_share(&frame, level[0].0, |v| solid.get(v) && !out.get(v)) < GROUND {
            break;
        }
        for &(_, v) in level {
            out.set(v as usize, false);
        }
    }
    out
}

/// The grid seen along the axis nearest `up`: a voxel's height (levels
/// counted upwards) and its cell in the plane across it.
pub(super) struct Frame<'a> {
    geom: &'a GridGeom,
    axis: usize,
    /// The two other axes.
    across: [usize; 2],
    rising: bool,
}

impl<'a> Frame<'a> {
    pub(super) fn new(geom: &'a GridGeom, up: Vec3) -> Self {
        let axis = up.abs().max_position();
        Frame {
            geom,
            axis,
            across: [(axis + 1) % 3, (axis + 2) % 3],
            rising: up[axis] >= 0.0,
        }
    }
    pub(super) fn height(&self, v: usize) -> usize {
        self.flip(self.geom.coords(v)[self.axis])
    }
    /// A grid coordinate along the up axis as a height, and back.
    fn flip(&self, c: usize) -> usize {
        if self.rising {
            c
        } else {
            self.geom.res[self.axis] - 1 - c
        }
    }
    pub(super) fn cell(&self, v: usize) -> [usize; 2] {
        let c = self.geom.coords(v);
        self.across.map(|a| c[a])
    }
    /// The voxel of `cell` at `height`.
    fn voxel(&self, cell: [usize; 2], height: usize) -> usize {
        let mut c = [0; 3];
        c[self.axis] = self.flip(height);
        c[self.across[0]] = cell[0];
        c[self.across[1]] = cell[1];
        self.geom.index(c[0], c[1], c[2])
    }
}

/// The cells some voxels cover, seen along up, on a raster over their box
/// widened by [`OUTER`]: those cells widened by [`INNER`] (`near`) and by
/// [`OUTER`] (`far`).
pub(super) struct Outline {
    lo: [usize; 2],
    size: [usize; 2],
    near: Vec<bool>,
    far: Vec<bool>,
}

impl Outline {
    /// The outline of `voxels` (dilated twice: square windows, one pass
    /// per axis).
    pub(super) fn of(frame: &Frame, voxels: impl Iterator<Item = usize>) -> Self {
        let cells: Vec<[usize; 2]> = voxels.map(|v| frame.cell(v)).collect();
        let lo = [0, 1].map(|k| cells.iter().map(|c| c[k]).min().unwrap_or(0).saturating_sub(OUTER));
        let hi = [0, 1].map(|k| {
            let top = frame.geom.res[frame.across[k]] - 1;
            (cells.iter().map(|c| c[k]).max().unwrap_or(0) + OUTER).min(top)
        });
        let size = [hi[0] - lo[0] + 1, hi[1] - lo[1] + 1];
        let mut covered = vec![false; size[0] * size[1]];
        for c in &cells {
            covered[(c[1] - lo[1]) * size[0] + c[0] - lo[0]] = true;
        }
        Outline {
            lo,
            size,
            near: dilate(&covered, size, INNER),
            far: dilate(&covered, size, OUTER),
        }
    }

    fn index(&self, [x, y]: [usize; 2]) -> Option<usize> {
        let inside = (self.lo[0]..self.lo[0] + self.size[0]).contains(&x)
            && (self.lo[1]..self.lo[1] + self.size[1]).contains(&y);
        inside.then(|| (y - self.lo[1]) * self.size[0] + x - self.lo[0])
    }

    /// Whether `cell` is within [`INNER`] cells of the outline.
    pub(super) fn near(&self, cell: [usize; 2]) -> bool {
        self.index(cell).is_some_and(|i| self.near[i])
    }

    /// The annulus: cells more than [`INNER`] and at most [`OUTER`] cells
    /// from the outline.
    pub(super) fn ring(&self) -> Annulus {
        let ring = (0..self.near.len())
            .filter(|&i| self.far[i] && !self.near[i])
            .map(|i| [self.lo[0] + i % self.size[0], self.lo[1] + i / self.size[0]])
            .collect();
        Annulus(ring)
    }
}

/// The cells around an outline (module docs), in the grid.
pub(super) struct Annulus(Vec<[usize; 2]>);

impl Annulus {
    /// Around the cells of `voxels`.
    fn around(frame: &Frame, voxels: &[u32]) -> Self {
        Outline::of(frame, voxels.iter().map(|&v| v as usize)).ring()
    }

    /// The share of the annulus's cells at `height` whose voxel `full` accepts.
    pub(super) fn solid_share(&self, frame: &Frame, height: usize, full: impl Fn(usize) -> bool) -> f32 {
        let n = self.0.iter().filter(|&&c| full(frame.voxel(c, height))).count();
        n as f32 / self.0.len().max(1) as f32
    }
}

/// `mask` (row-major, `size`) dilated by a square of half-side `r`.
fn dilate(mask: &[bool], size: [usize; 2], r: usize) -> Vec<bool> {
    let pass = |src: &[bool], along_x: bool| -> Vec<bool> {
        let mut out = vec![false; src.len()];
        for y in 0..size[1] {
            for x in 0..size[0] {
                let (at, len) = if along_x { (x, size[0]) } else { (y, size[1]) };
                let span = at.saturating_sub(r)..=(at + r).min(len - 1);
                out[y * size[0] + x] = span.into_iter().any(|t| match along_x {
                    true => src[y * size[0] + t],
                    false => src[t * size[0] + x],
                });
            }
        }
        out
    };
    pass(&pass(mask, true), false)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::Aabb;

    /// A table top (y 10–13) blurred one voxel up around a mug (a 6×6
    /// cylinder-ish block, y 14–25) whose region took the table's top two
    /// levels under its foot; the same scene upside down (up = −y); and a
    /// board under toys, seen from the side the toys stand on: the mug
    /// loses exactly the two levels, the toys' board nothing.
    #[test]
    fn the_ground_under_a_foot_leaves_the_region_and_nothing_else() {
        let n = 40;
        let geom = GridGeom::new(Aabb::new(Vec3::ZERO, Vec3::splat((n - 1) as f32)), [n; 3]);
        let at = |v: usize| geom.coords(v).map(|c| c as i32);
        for up in [1i32, -1] {
            // y measured upwards from the grid's bottom (or top, upside down).
            let y_of = |v: usize| if up > 0 { at(v)[1] } else { n as i32 - 1 - at(v)[1] };
            let foot = |v: usize| (16..22).contains(&at(v)[0]) && (16..22).contains(&at(v)[2]);
            let table = Bitmap::from_fn(geom.res, |v| (10..14).contains(&y_of(v)));
            let mug = Bitmap::from_fn(geom.res, |v| foot(v) && (14..26).contains(&y_of(v)));
            let taken = Bitmap::from_fn(geom.res, |v| foot(v) && (12..14).contains(&y_of(v)));
            let region = Bitmap::from_fn(geom.res, |v| mug.get(v) || taken.get(v));
            let solid = Bitmap::from_fn(geom.res, |v| table.get(v) || region.get(v));
            let anchors: Vec<u32> = mug.ones().filter(|&v| y_of(v) == 25).map(|v| v as u32).collect();
            let got = off_the_ground(&geom, &solid, region.clone(), Vec3::new(0.0, up as f32, 0.0), &anchors);
            assert!(got == mug, "up {up}: the mug without the table's levels");
            // Looking the wrong way, the mug's top has air around it: kept.
            let wrong = off_the_ground(&geom, &solid, region.clone(), Vec3::new(0.0, -up as f32, 0.0), &anchors);
            assert!(wrong == region, "up {up}: nothing below the table's underside");
            // A stroke on the taken levels keeps them.
            let low: Vec<u32> = taken.ones().map(|v| v as u32).collect();
            let kept = off_the_ground(&geom, &solid, region.clone(), Vec3::new(0.0, up as f32, 0.0), &low);
            assert!(kept == region, "up {up}: stroked levels stay");
        }
        // Something floating: its lowest level has air around it.
        let ball = Bitmap::from_fn(geom.res, |v| at(v).iter().all(|&c| (18..24).contains(&c)));
        let got = off_the_ground(&geom, &ball, ball.clone(), Vec3::Y, &[]);
        assert!(got == ball);
        assert!(off_the_ground(&geom, &ball, Bitmap::new(geom.res), Vec3::Y, &[]).count() == 0);
    }

    /// The dilation reaches r cells along both axes and no further.
    #[test]
    fn dilation_is_a_square_window() {
        let size = [9, 7];
        let mut mask = vec![false; 63];
        mask[3 * 9 + 4] = true;
        let d = dilate(&mask, size, 2);
        for y in 0..7usize {
            for x in 0..9usize {
                let inside = x.abs_diff(4) <= 2 && y.abs_diff(3) <= 2;
                assert_eq!(d[y * 9 + x], inside, "({x}, {y})");
            }
        }
    }
}
