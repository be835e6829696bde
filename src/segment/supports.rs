//! What holds a flat top up: a table's legs.
//!
//! A stroke on a table top selects the top: its legs look like something
//! else to the teacher (the realistic benchmark's blue legs are farther
//! from the top in features than the floor is) and meet the top at a thin
//! joint, so neither the features nor the cut join them. Their geometry
//! does: below a flat region, inside its outline, they run from the region
//! to a wider surface (the floor) that reaches out past the outline.
//! Things standing on the region (a pot on the table) end in open space
//! instead, and a wall or a board the region meets at its edge is never a
//! surface wider than the region's outline that the region stands on.
//!
//! The walk goes away from the region's slab one layer (one voxel along its
//! normal) at a time, through solid voxels inside the outline that are
//! joined to the region:
//! - while the layers stay about as large as those before them, they are
//!   the legs;
//! - when a layer grows to [`WIDER`] times the median layer so far, the
//!   legs have reached their feet and the surface under them: from then on
//!   only voxels in the legs' columns are taken;
//! - the walk ends at the first layer covering [`SUPPORT_SHARE`] of the
//!   outline, the support, and takes what it found only if that layer goes
//!   on past the outline (at least [`BEYOND`] times its area in all),
//!   leaving out the layers just before it that are the support's blurred
//!   surface ([`BLUR_SHARE`]); if the walk runs out of voxels first,
//!   nothing stood under the region.

use super::plane::{PlaneCells, Slab};
use crate::field::{Bitmap, GridGeom};
use glam::Vec3;

/// A layer this many times the median layer before it is where the legs
/// widen into their feet and the surface they stand on.
const WIDER: f32 = 2.0;
/// Layers needed before a widening counts (the first layers, inside the
/// slab and just out of it, carry its blur).
const MIN_LAYERS: usize = 3;
/// A layer covering this share of the region's outline is the support.
const SUPPORT_SHARE: f32 = 0.5;
/// Layers just before the support that cover this share of the outline
/// are the support's blurred surface (a trained field spreads a floor's
/// surface over a few voxels).
const BLUR_SHARE: f32 = 0.125;
/// The support's layer must reach this many times its area inside the
/// outline when followed past it: a floor goes on past a table; the
/// ceiling over a room's floor does not go past the floor.
const BEYOND: f32 = 1.5;

/// `region` with the legs that hold it up (module docs), if it is flat
/// (`slab`, its plane); `solid` marks the voxels that can be legs.
pub fn with_supports(geom: &GridGeom, solid: &Bitmap, region: Bitmap, slab: &Slab) -> Bitmap {
    let outline = Outline::of(geom, &region, slab);
    let ground = Ground {
        geom,
        solid,
        region: &region,
        slab,
        outline: &outline,
    };
    let legs = [1.0f32, -1.0]
        .into_iter()
        .find_map(|side| Walk::new(ground, side).legs());
    let mut out = region;
    for v in legs.into_iter().flatten() {
        out.set(v as usize, true);
    }
    out
}

/// The cells (voxel-sized squares in the slab's plane) that the region
/// covers, one cell wider all round.
struct Outline {
    plane: PlaneCells,
    h: f32,
    min: [i32; 2],
    size: [usize; 2],
    cells: Vec<bool>,
    count: usize,
}

impl Outline {
    fn of(geom: &GridGeom, region: &Bitmap, slab: &Slab) -> Self {
        let plane = PlaneCells::new(geom, slab);
        let covered: Vec<[i32; 2]> = region.ones().map(|v| plane.of(geom.point_of(v))).collect();
        let lo = |k: usize| covered.iter().map(|c| c[k]).min().unwrap_or(0) - 1;
        let hi = |k: usize| covered.iter().map(|c| c[k]).max().unwrap_or(0) + 1;
        let min = [lo(0), lo(1)];
        let size = [(hi(0) - min[0] + 1) as usize, (hi(1) - min[1] + 1) as usize];
        let mut outline = Outline {
            plane,
            h: geom.spacing().min_element(),
            min,
            size,
            cells: vec![false; size[0] * size[1]],
            count: 0,
        };
        outline.cells = outline.widened(covered.into_iter());
        outline.count = outline.cells.iter().filter(|&&c| c).count();
        outline
    }

    /// The cell under point `p`, if inside the outline's box.
    fn cell(&self, p: Vec3) -> Option<usize> {
        let [x, y] = self.plane.of(p);
        let (x, y) = (x - self.min[0], y - self.min[1]);
        let inside = x >= 0 && y >= 0 && (x as usize) < self.size[0] && (y as usize) < self.size[1];
        inside.then(|| y as usize * self.size[0] + x as usize)
    }

    /// The box's cells `squares` cover, one cell wider all round (clipped
    /// to the box).
    fn widened(&self, squares: impl Iterator<Item = [i32; 2]>) -> Vec<bool> {
        let mut cells = vec![false; self.size[0] * self.size[1]];
        for [x, y] in squares {
            for (dx, dy) in (-1..=1).flat_map(|dy| (-1..=1).map(move |dx| (dx, dy))) {
                let (nx, ny) = (x + dx - self.min[0], y + dy - self.min[1]);
                if nx >= 0 && ny >= 0 && (nx as usize) < self.size[0] && (ny as usize) < self.size[1] {
                    cells[ny as usize * self.size[0] + nx as usize] = true;
                }
            }
        }
        cells
    }

    fn holds(&self, p: Vec3) -> bool {
        self.cell(p).is_some_and(|c| self.cells[c])
    }
}

/// What a walk looks at: the grid, the voxels that can be legs, the region
/// and its slab and outline.
#[derive(Clone, Copy)]
struct Ground<'a> {
    geom: &'a GridGeom,
    solid: &'a Bitmap,
    region: &'a Bitmap,
    slab: &'a Slab,
    outline: &'a Outline,
}

/// The walk away from one side of the slab (module docs).
struct Walk<'a> {
    ground: Ground<'a>,
    side: f32,
    /// Voxels waiting per layer (index: the layer).
    pending: Vec<Vec<u32>>,
    reached: Bitmap,
    /// Neighbours found around one voxel (reused: no allocation per voxel).
    found: Vec<(usize, usize)>,
}

impl<'a> Walk<'a> {
    fn new(ground: Ground<'a>, side: f32) -> Self {
        let region = ground.region;
        let mut w = Walk {
            ground,
            side,
            pending: vec![],
            reached: Bitmap::new(ground.geom.res),
            found: vec![],
        };
        for v in region.ones() {
            w.push_neighbours(v, 0);
        }
        w
    }

    /// How many voxels from the slab's mid-plane `v` lies, if on this side.
    fn layer(&self, v: usize) -> Option<usize> {
        self.layer_at(self.ground.geom.point_of(v))
    }

    /// [`Self::layer`] of the voxel at point `p`.
    fn layer_at(&self, p: Vec3) -> Option<usize> {
        let s = (p - self.ground.slab.centre).dot(self.ground.slab.normal) * self.side;
        (s > 0.0).then(|| (s / self.ground.outline.h).round() as usize)
    }

    /// Queues the solid neighbours of `v` outside the region, inside the
    /// outline, at layer `from` or farther.
    fn push_neighbours(&mut self, v: usize, from: usize) {
        let mut found = std::mem::take(&mut self.found);
        self.candidates(v, |l| l >= from, &mut found);
        for &(n, l) in &found {
            self.reached.set(n, true);
            if self.pending.len() <= l {
                self.pending.resize(l + 1, vec![]);
            }
            self.pending[l].push(n as u32);
        }
        self.found = found;
    }

    /// The solid neighbours of `v` not reached yet, outside the region and
    /// inside the outline, whose layer passes `layer_ok`, with their layers
    /// (into `out`, cleared first).
    fn candidates(&self, v: usize, layer_ok: impl Fn(usize) -> bool, out: &mut Vec<(usize, usize)>) {
        out.clear();
        let g = self.ground;
        g.geom.neighbours26(v, |n| {
            if self.reached.get(n) || g.region.get(n) || !g.solid.get(n) {
                return;
            }
            let p = g.geom.point_of(n);
            if let Some(l) = self.layer_at(p).filter(|&l| layer_ok(l)) {
                if g.outline.holds(p) {
                    out.push((n, l));
                }
            }
        });
    }

    /// Every voxel of layer `l` joined to the queued ones within the layer.
    fn flood_layer(&mut self, l: usize) -> Vec<u32> {
        let mut layer = vec![];
        let mut same = std::mem::take(&mut self.found);
        while let Some(v) = self.pending.get_mut(l).and_then(|p| p.pop()) {
            layer.push(v);
            self.candidates(v as usize, |k| k == l, &mut same);
            for &(n, _) in &same {
                self.reached.set(n, true);
                self.pending[l].push(n as u32);
            }
        }
        self.found = same;
        layer
    }

    /// The legs found on this side, or `None` if nothing stands there.
    fn legs(mut self) -> Option<Vec<u32>> {
        // Per layer kept: how many voxels the whole layer had inside the
        // outline, and those kept.
        let mut layers: Vec<(usize, Vec<u32>)> = vec![];
        // Cells of the legs once their feet are reached.
        let mut columns: Option<Vec<bool>> = None;
        let mut l = 0;
        while l < self.pending.len() {
            let layer = self.flood_layer(l);
            if layer.is_empty() {
                l += 1;
                continue;
            }
            let full = layer.len();
            if full as f32 >= SUPPORT_SHARE * self.ground.outline.count as f32 {
                return self.standing_on(&layer, layers);
            }
            if columns.is_none() && layers.len() >= MIN_LAYERS {
                let sizes: Vec<usize> = layers.iter().map(|(_, k)| k.len()).collect();
                if full as f32 > WIDER * median(&sizes) {
                    let legs: Vec<u32> = layers.iter().flat_map(|(_, k)| k.iter().copied()).collect();
                    columns = Some(self.columns(&legs));
                }
            }
            let kept: Vec<u32> = match &columns {
                Some(cells) => layer
                    .into_iter()
                    .filter(|&v| {
                        self.ground
                            .outline
                            .cell(self.ground.geom.point_of(v as usize))
                            .is_some_and(|c| cells[c])
                    })
                    .collect(),
                None => layer,
            };
            for &v in &kept {
                self.push_neighbours(v as usize, l + 1);
            }
            layers.push((full, kept));
            l += 1;
        }
        None
    }

    /// The legs in `layers` when `support` (a layer covering the outline)
    /// goes on past the outline: the layers just before it that already
    /// cover [`BLUR_SHARE`] of the outline are the support's own blurred
    /// surface, not legs, and are left out.
    fn standing_on(&self, support: &[u32], mut layers: Vec<(usize, Vec<u32>)>) -> Option<Vec<u32>> {
        while layers
            .last()
            .is_some_and(|&(full, _)| full as f32 >= BLUR_SHARE * self.ground.outline.count as f32)
        {
            layers.pop();
        }
        let legs: Vec<u32> = layers.into_iter().flat_map(|(_, k)| k).collect();
        (!legs.is_empty() && self.goes_past(support)).then_some(legs)
    }

    /// The outline cells under `voxels`, one cell wider all round.
    fn columns(&self, voxels: &[u32]) -> Vec<bool> {
        let o = self.ground.outline;
        o.widened(
            voxels
                .iter()
                .map(|&v| o.plane.of(self.ground.geom.point_of(v as usize))),
        )
    }

    /// Whether the support's `layer`, followed through solid voxels of the
    /// same layer past the outline, reaches [`BEYOND`] times its size.
    fn goes_past(&self, layer: &[u32]) -> bool {
        let Some(l) = layer.first().and_then(|&v| self.layer(v as usize)) else {
            return false;
        };
        let goal = (BEYOND * layer.len() as f32).ceil() as usize;
        let mut seen = Bitmap::from_ones(self.ground.geom.res, layer);
        let mut stack: Vec<usize> = layer.iter().map(|&v| v as usize).collect();
        let mut count = layer.len();
        let mut next = vec![];
        while let Some(v) = stack.pop() {
            next.clear();
            self.ground.geom.neighbours26(v, |n| {
                if !seen.get(n) && self.ground.solid.get(n) && !self.ground.region.get(n) && self.layer(n) == Some(l) {
                    next.push(n);
                }
            });
            for &n in &next {
                seen.set(n, true);
                count += 1;
                if count >= goal {
                    return true;
                }
                stack.push(n);
            }
        }
        false
    }
}

fn median(xs: &[usize]) -> f32 {
    let mut s = xs.to_vec();
    s.sort_unstable();
    s.get(s.len() / 2).copied().unwrap_or(0) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::Aabb;
    use crate::segment::plane::flat_slab;

    /// A 64³ room: a floor (y < 6), a table top (y 30–33, x and z within
    /// ±14 voxels of the centre) on four 3×3 legs, a pot on the top, and a
    /// ball on the floor beside the table.
    struct Room {
        geom: GridGeom,
        floor: Bitmap,
        top: Bitmap,
        legs: Bitmap,
        pot: Bitmap,
        solid: Bitmap,
    }

    fn room(with_floor: bool) -> Room {
        let n = 64;
        let geom = GridGeom::new(Aabb::new(Vec3::ZERO, Vec3::splat((n - 1) as f32)), [n; 3]);
        let at = |v: usize| geom.coords(v).map(|c| c as i32);
        let floor = Bitmap::from_fn(geom.res, |v| with_floor && at(v)[1] < 6);
        let top = Bitmap::from_fn(geom.res, |v| {
            let [x, y, z] = at(v);
            (30..=33).contains(&y) && (x - 32).abs() <= 14 && (z - 32).abs() <= 14
        });
        let legs = Bitmap::from_fn(geom.res, |v| {
            let [x, y, z] = at(v);
            let corner = |c: i32| (c - 32).abs() >= 10 && (c - 32).abs() <= 12;
            (6..30).contains(&y) && corner(x) && corner(z)
        });
        let pot = Bitmap::from_fn(geom.res, |v| {
            let [x, y, z] = at(v);
            (34..44).contains(&y) && (x - 30).abs() <= 3 && (z - 30).abs() <= 3
        });
        let ball = Bitmap::from_fn(geom.res, |v| {
            geom.point_of(v).distance(Vec3::new(55.0, 10.0, 55.0)) <= 4.0
        });
        let solid = Bitmap::from_fn(geom.res, |v| {
            floor.get(v) || top.get(v) || legs.get(v) || pot.get(v) || ball.get(v)
        });
        Room {
            geom,
            floor,
            top,
            legs,
            pot,
            solid,
        }
    }

    fn slab_of(g: &GridGeom, b: &Bitmap) -> Slab {
        let voxels: Vec<u32> = b.ones().map(|v| v as u32).collect();
        flat_slab(g, &voxels).expect("flat")
    }

    fn union(a: &Bitmap, b: &Bitmap) -> Bitmap {
        Bitmap::from_fn(a.res(), |v| a.get(v) || b.get(v))
    }

    /// Known answers: the top gains its legs to the floor and neither the
    /// floor nor the pot on it; the floor gains nothing (what stands on it
    /// ends in open space or on a top no wider than itself); a top with
    /// legs that stand on nothing (no floor) gains nothing.
    #[test]
    fn a_table_top_gains_its_legs_and_nothing_else() {
        let r = room(true);
        let got = with_supports(&r.geom, &r.solid, r.top.clone(), &slab_of(&r.geom, &r.top));
        assert_eq!(got, union(&r.top, &r.legs));
        let floor = with_supports(&r.geom, &r.solid, r.floor.clone(), &slab_of(&r.geom, &r.floor));
        assert_eq!(floor, r.floor);
        assert!(!got.ones().any(|v| r.pot.get(v)));
        let bare = room(false);
        let got = with_supports(
            &bare.geom,
            &bare.solid,
            bare.top.clone(),
            &slab_of(&bare.geom, &bare.top),
        );
        assert_eq!(got, bare.top);
    }

    /// Legs that widen into feet one layer above the floor: the feet come
    /// with the legs, the floor under them does not.
    #[test]
    fn feet_come_with_the_legs() {
        let r = room(true);
        let at = |v: usize| r.geom.coords(v).map(|c| c as i32);
        let feet = Bitmap::from_fn(r.geom.res, |v| {
            let [x, y, z] = at(v);
            let near = |c: i32| (c - 32).abs() >= 9 && (c - 32).abs() <= 13;
            (6..8).contains(&y) && near(x) && near(z)
        });
        let solid = union(&r.solid, &feet);
        let got = with_supports(&r.geom, &solid, r.top.clone(), &slab_of(&r.geom, &r.top));
        let want = union(&union(&r.top, &r.legs), &feet);
        let missing = want.ones().filter(|&v| !got.get(v)).count();
        let extra = got.ones().filter(|&v| !want.get(v)).count();
        assert_eq!(extra, 0, "took {extra} voxels beyond the table");
        assert!(
            missing * 20 <= feet.count(),
            "missed {missing} of the feet's {}",
            feet.count()
        );
    }
}
