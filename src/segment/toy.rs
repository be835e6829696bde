//! A toy standing on a board, for the tests of the rules that read a
//! region's shape ([`super::beside`], [`super::under`]).

use crate::field::{Aabb, Bitmap, GridGeom};
use glam::Vec3;

/// On a 64³ grid of unit spacing: a board (y < 8) carrying a toy, a body
/// (x 10–39, y 16–23, z 20–43) on two tracks (x 8–41, y 8–15, z 20–26 and
/// 37–43), and a jar (x 40–47, y 8–19, z 28–35) standing on the board
/// against the body's end; the stroke runs across the body's top, over
/// both tracks.
pub struct Toy {
    pub geom: GridGeom,
    pub board: Bitmap,
    pub body: Bitmap,
    pub tracks: Bitmap,
    pub jar: Bitmap,
    /// The voxels under the stroke, ascending.
    pub anchors: Vec<u32>,
}

impl Toy {
    pub fn new() -> Self {
        let n = 64;
        let geom = GridGeom::new(Aabb::new(Vec3::ZERO, Vec3::splat((n - 1) as f32)), [n; 3]);
        let block = |lo: [i32; 3], hi: [i32; 3]| block(&geom, lo, hi);
        let body = block([10, 16, 20], [40, 24, 44]);
        let anchors = body
            .ones()
            .filter(|&v| {
                let [x, y, z] = at(&geom, v);
                y == 23 && (12..36).contains(&x) && z == 22 + (x - 12) * 19 / 24
            })
            .map(|v| v as u32)
            .collect();
        let (a, b) = (block([8, 8, 20], [42, 16, 27]), block([8, 8, 37], [42, 16, 44]));
        Toy {
            board: Bitmap::from_fn(geom.res, |v| at(&geom, v)[1] < 8),
            tracks: union(&[&a, &b]),
            jar: block([40, 8, 28], [48, 20, 36]),
            body,
            anchors,
            geom,
        }
    }

    /// Grid coordinates of voxel `v`.
    pub fn at(&self, v: usize) -> [i32; 3] {
        at(&self.geom, v)
    }

    /// The voxels from `lo` up to (not including) `hi`.
    pub fn block(&self, lo: [i32; 3], hi: [i32; 3]) -> Bitmap {
        block(&self.geom, lo, hi)
    }
}

fn at(geom: &GridGeom, v: usize) -> [i32; 3] {
    geom.coords(v).map(|c| c as i32)
}

fn block(geom: &GridGeom, lo: [i32; 3], hi: [i32; 3]) -> Bitmap {
    Bitmap::from_fn(geom.res, |v| {
        let c = at(geom, v);
        (0..3).all(|k| (lo[k]..hi[k]).contains(&c[k]))
    })
}

/// Every voxel of any of `parts`.
pub fn union(parts: &[&Bitmap]) -> Bitmap {
    let res = parts[0].res();
    Bitmap::from_fn(res, |v| parts.iter().any(|p| p.get(v)))
}
