//! Flood fills over a grid's face neighbours.

use crate::field::{Bitmap, GridGeom};

/// The face neighbours of voxel `v` of `geom` (up to six; fewer on the
/// grid's border).
pub fn face_neighbours(geom: &GridGeom, v: usize) -> impl Iterator<Item = usize> {
    let res = geom.res;
    let strides = [1, res[0], res[0] * res[1]];
    let c = geom.coords(v);
    (0..3).flat_map(move |axis| {
        let below = (c[axis] > 0).then(|| v - strides[axis]);
        let above = (c[axis] + 1 < res[axis]).then(|| v + strides[axis]);
        below.into_iter().chain(above)
    })
}

/// `region` grown through the 6-neighbours (grid indices of `geom`) that
/// `admit` accepts, until none is left. Each voxel outside `region` is
/// asked at most once, so `admit` may measure something costly.
pub fn faces(geom: &GridGeom, region: &Bitmap, mut admit: impl FnMut(usize) -> bool) -> Bitmap {
    let mut out = region.clone();
    let mut asked = region.clone();
    let mut stack: Vec<usize> = region.ones().collect();
    while let Some(v) = stack.pop() {
        for n in face_neighbours(geom, v) {
            if asked.get(n) {
                continue;
            }
            asked.set(n, true);
            if admit(n) {
                out.set(n, true);
                stack.push(n);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::Aabb;
    use glam::Vec3;

    #[test]
    fn fills_the_face_connected_part_only() {
        let geom = GridGeom::new(Aabb::new(Vec3::ZERO, Vec3::ONE), [5, 5, 1]);
        let at = |x: usize, y: usize| x + 5 * y;
        // An L of admitted voxels from (0,0), and (3,3) touching it only
        // at a corner (diagonal: not a face neighbour).
        let admitted = [at(1, 0), at(2, 0), at(2, 1), at(2, 2), at(3, 3)];
        let mut seed = Bitmap::new(geom.res);
        seed.set(at(0, 0), true);
        let mut calls = vec![0; geom.len()];
        let out = faces(&geom, &seed, |n| {
            calls[n] += 1;
            admitted.contains(&n)
        });
        let got: Vec<usize> = out.ones().collect();
        assert_eq!(got, vec![at(0, 0), at(1, 0), at(2, 0), at(2, 1), at(2, 2)]);
        assert!(calls.iter().all(|&c| c <= 1), "a voxel was asked twice");
        assert_eq!(calls[at(0, 0)], 0, "the region's own voxels are not asked");
    }
}
