//! Which side of an object's boundary the Gaussians that straddle it go to.
//!
//! An object's bitmap lives on the imported field's grid, which is coarser
//! than the Gaussians near an edge: a voxel where a pot stands on a table
//! holds Gaussians of both, and its grid point is either the pot's or not.
//! By mass alone ([`super::import::inside`] spreads each Gaussian over the
//! grid as the import does) the table's Gaussians in that ring go with the
//! pot when the bitmap took the ring's points, and the pot's lowest ones
//! stay behind when it did not. On the splat benchmark (`isrf bench
//! splats`) most Gaussians selected wrongly were such straddlers: the pot's
//! ring of table (94 of its 124), the ball's floor, the books' board.
//!
//! A Gaussian's own colour is exact where the grid's is a blend, so a
//! straddler (part of its mass on the bitmap, part off it) goes to the side
//! whose nearby Gaussians look like it: the mean colours of the Gaussians
//! (nearly) wholly on each side within [`REACH`] grid points of it. Where
//! the two sides look alike there (their means not clearly apart for
//! their spreads, [`SEPARATION`]), the straddler is not clearly nearer one
//! ([`CLEARER`]) or one side has too few Gaussians there, the mass decides
//! as before. Measured with `isrf bench splats` (2026-11-30): mean IoU by
//! count 0.819 → 0.826 with the ViT teacher (jar 0.823 → 0.858, box 0.974
//! → 0.991, mug 0.916 → 0.926), 0.844 → 0.851 with the oracle features
//! (mug 0.915 → 0.948, box 0.974 → 0.996, excavator 0.893 → 0.907).
//! A vote by the three nearest colours on each side, with no separation
//! guard, scored 0.831 (the side means alone 0.830), but on a surface of
//! many colours cut by the bitmap (the splat tests' cube) straddlers
//! flipped at random to whichever side had their colour in reach.
//! Gaussians wholly inside the bitmap stay in whatever their colour: where
//! the bitmap took a ring of the table two points wide, the ring's inner
//! Gaussians are the object's references too (the pot keeps 113 of the
//! table's Gaussians); that is the segmentation's to fix.

use super::ply::{f32_at, SplatFile};
use crate::field::GridGeom;
use glam::Vec3;
use rayon::prelude::*;

/// Fewest references on each side for colour to decide.
pub const MIN_REFERENCES: usize = 3;

/// The two sides' mean colours must be this many times their summed
/// spreads apart (squared distances) for colour to tell them apart: on a
/// textured or many-coloured surface cut by the bitmap both sides look
/// alike and the mass decides.
pub const SEPARATION: f32 = 1.0;

/// The nearer side's colour distance must be below 1/this of the other's
/// for colour to decide; otherwise the mass does.
pub const CLEARER: f32 = 2.0;

/// A Gaussian with at least this share of its mass on the bitmap (or at
/// most 1 − this) is wholly on one side.
const WHOLE: f32 = 0.999;

/// Gaussians with at least this share of their mass on one side are the
/// references a straddler is compared with.
const REFERENCE: f32 = 0.95;

/// How far (grid points along each axis) a straddler's references may be.
/// The import widens every footprint by half a grid point, so a Gaussian
/// within about 1.5 points of the edge straddles it: the nearest
/// references on the far side are two or more points away.
const REACH: usize = 3;

/// One Gaussian as the boundary vote sees it.
#[derive(Clone, Copy, Debug)]
pub struct Placed {
    /// Record index in the file.
    pub index: u32,
    /// Nearest grid point of its centre (flat index).
    pub cell: u32,
    /// Share of its mass on the bitmap's grid points.
    pub on: f32,
}

/// `keep[i]` for every record of `file`: Gaussians wholly on the bitmap
/// (`on` ≥ 0.999) are in, wholly off it out, straddlers as the module
/// docs say. Records not in `placed` (outside the field, non-finite) are
/// out.
pub fn assign(file: &SplatFile, geom: &GridGeom, placed: &[Placed]) -> Vec<bool> {
    let mut keep = vec![false; file.len()];
    // The references with their colours, sorted by cell so that a row of
    // cells is a contiguous run found by binary search.
    let mut refs: Vec<Reference> = placed
        .iter()
        .filter(|p| p.on >= REFERENCE || p.on <= 1.0 - REFERENCE)
        .map(|p| Reference {
            cell: p.cell,
            index: p.index,
            on: p.on >= 0.5,
            colour: dc(file, p.index as usize),
        })
        .collect();
    refs.par_sort_unstable_by_key(|r| r.cell);
    let decided: Vec<(u32, bool)> = placed
        .par_iter()
        .map(|p| {
            let by_mass = p.on >= 0.5;
            if !straddles(p.on) {
                return (p.index, by_mass);
            }
            let side = colour_side(&refs, geom, p, dc(file, p.index as usize));
            (p.index, side.unwrap_or(by_mass))
        })
        .collect();
    for (i, k) in decided {
        keep[i as usize] = k;
    }
    keep
}

fn straddles(on: f32) -> bool {
    on > 1.0 - WHOLE && on < WHOLE
}

/// The DC colour coefficients of record `i` (the view-independent colour,
/// up to the SH constant and offset, so distances compare colours).
fn dc(file: &SplatFile, i: usize) -> Vec3 {
    let r = file.record(i);
    let o = file.header.layout.dc;
    Vec3::new(f32_at(r, o[0]), f32_at(r, o[1]), f32_at(r, o[2]))
}

/// A Gaussian (nearly) wholly on one side, which straddlers near it are
/// compared with.
struct Reference {
    cell: u32,
    index: u32,
    /// On the bitmap.
    on: bool,
    colour: Vec3,
}

/// The colours of the references on one side of a straddler: count, sum
/// and sum of squared norms, for their mean and spread.
#[derive(Clone, Copy, Default)]
struct Side {
    n: usize,
    sum: Vec3,
    sq: f32,
}

impl Side {
    fn add(&mut self, c: Vec3) {
        self.n += 1;
        self.sum += c;
        self.sq += c.length_squared();
    }
    fn mean(&self) -> Vec3 {
        self.sum / self.n as f32
    }
    /// Mean squared distance of the colours from their mean.
    fn spread(&self) -> f32 {
        (self.sq / self.n as f32 - self.mean().length_squared()).max(0.0)
    }
}

/// The side (true: the bitmap's) whose references around `p` colour `c`
/// is clearly nearer, if the two sides' colours are told apart there: at
/// least [`MIN_REFERENCES`] references on each side within [`REACH`] grid
/// points of `p` (`refs` sorted by cell; `p` itself left out),
/// their means [`SEPARATION`] times their spreads apart, and `c` [`CLEARER`]
/// times nearer one mean than the other.
fn colour_side(refs: &[Reference], geom: &GridGeom, p: &Placed, c: Vec3) -> Option<bool> {
    let mut sides = [Side::default(); 2];
    for (first, last) in neighbour_rows(geom, p.cell as usize) {
        let start = refs.partition_point(|r| r.cell < first);
        let run = refs[start..].iter().take_while(|r| r.cell <= last);
        for r in run.filter(|r| r.index != p.index) {
            sides[r.on as usize].add(r.colour);
        }
    }
    let [out, inn] = sides;
    if inn.n < MIN_REFERENCES || out.n < MIN_REFERENCES {
        return None;
    }
    let apart = inn.mean().distance_squared(out.mean());
    if apart <= SEPARATION * (inn.spread() + out.spread()) {
        return None;
    }
    let (d_in, d_out) = (c.distance_squared(inn.mean()), c.distance_squared(out.mean()));
    if d_in * CLEARER < d_out {
        Some(true)
    } else if d_out * CLEARER < d_in {
        Some(false)
    } else {
        None
    }
}

/// The runs of flat indices within [`REACH`] grid points of `cell` along
/// every axis (clipped to the grid), one contiguous `first..=last` range
/// per row.
fn neighbour_rows(geom: &GridGeom, cell: usize) -> impl Iterator<Item = (u32, u32)> + '_ {
    let [x, y, z] = geom.coords(cell);
    let span = |v: usize, n: usize| v.saturating_sub(REACH)..=(v + REACH).min(n - 1);
    let xs = span(x, geom.res[0]);
    span(z, geom.res[2]).flat_map(move |zz| {
        let xs = xs.clone();
        span(y, geom.res[1]).map(move |yy| {
            (
                geom.index(*xs.start(), yy, zz) as u32,
                geom.index(*xs.end(), yy, zz) as u32,
            )
        })
    })
}

#[cfg(test)]
mod tests {
    use super::super::ply::{standard_bytes, Gaussian};
    use super::*;

    fn grid(res: [usize; 3]) -> GridGeom {
        GridGeom::new(crate::field::Aabb::new(Vec3::ZERO, Vec3::ONE), res)
    }

    fn cell(x: usize, y: usize, z: usize) -> u32 {
        grid([10; 3]).index(x, y, z) as u32
    }

    /// A file of Gaussians with these DC colours (positions do not matter
    /// to [`assign`]: it takes cells and shares as given).
    fn file_of(colours: &[[f32; 3]]) -> SplatFile {
        let gs: Vec<Gaussian> = colours
            .iter()
            .enumerate()
            .map(|(i, &dc)| Gaussian {
                pos: Vec3::new(i as f32, 0.0, 0.0),
                dc,
                rest: vec![],
                opacity: 0.0,
                log_scale: [-2.0; 3],
                rot: [1.0, 0.0, 0.0, 0.0],
            })
            .collect();
        SplatFile::parse(standard_bytes(&gs, 0).unwrap()).unwrap()
    }

    #[test]
    fn straddlers_go_to_the_side_they_look_like_or_where_their_mass_is() {
        const RED: [f32; 3] = [1.2, -0.8, -0.9];
        const GREY: [f32; 3] = [0.1, 0.1, 0.1];
        const HALFWAY: [f32; 3] = [0.65, -0.35, -0.4];
        let mut colours = vec![];
        let mut placed = vec![];
        let mut add = |dc: [f32; 3], cell: u32, on: f32| {
            placed.push(Placed {
                index: colours.len() as u32,
                cell,
                on,
            });
            colours.push(dc);
        };
        // The object (red) on x 2..=4, the rest (grey) on x 6..=8, with a
        // little colour noise.
        for (k, x) in (2..=4).enumerate() {
            let n = 0.02 * k as f32;
            add([RED[0] + n, RED[1] - n, RED[2]], cell(x, 5, 5), 1.0);
            add([GREY[0] - n, GREY[1], GREY[2] + n], cell(x + 4, 5, 5), 0.0);
        }
        // Straddlers at x 5, between the two, and one at x 0 with no grey
        // within reach; then a grey one wholly on the bitmap, elsewhere.
        add(GREY, cell(5, 5, 5), 0.7);
        add(RED, cell(5, 5, 5), 0.3);
        add(HALFWAY, cell(5, 5, 5), 0.6);
        add(HALFWAY, cell(5, 5, 5), 0.4);
        add(GREY, cell(0, 5, 5), 0.7);
        add(GREY, cell(9, 1, 9), 1.0);
        let geom = grid([10; 3]);
        let keep = assign(&file_of(&colours), &geom, &placed);
        assert_eq!(
            &keep[..6],
            &[true, false, true, false, true, false],
            "references keep their side"
        );
        // Grey goes out against its mass, red in; halfway colours and the
        // straddler with one side out of reach follow the mass; wholly on
        // stays on whatever its colour.
        assert_eq!(&keep[6..], &[false, true, true, false, true, true]);
        // Without colours to tell (everything grey) the mass decides alone.
        let grey = file_of(&vec![GREY; placed.len()]);
        let by_mass: Vec<bool> = placed.iter().map(|p| p.on >= 0.5).collect();
        assert_eq!(assign(&grey, &geom, &placed), by_mass);
    }

    #[test]
    fn neighbour_rows_stay_on_the_grid() {
        let geom = grid([9, 8, 2]);
        let corner: Vec<(u32, u32)> = neighbour_rows(&geom, 0).collect();
        // y 0..=3 on both planes, x 0..=3.
        assert_eq!(corner.len(), 8);
        assert_eq!(corner[0], (0, 3));
        assert_eq!(corner[5], (72 + 9, 72 + 12));
        let far = 8 + 9 * 7 + 72; // (8, 7, 1)
        let rows: Vec<(u32, u32)> = neighbour_rows(&geom, far).collect();
        assert_eq!(rows.len(), 8);
        assert!(rows
            .iter()
            .all(|&(a, b)| b - a == 3 && (b as usize) < 144 && b % 9 == 8));
    }
}
