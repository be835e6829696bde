//! Growth along a flat surface: a floor, a wall, a table top.
//!
//! A teacher sees the near and the far end of a large surface differently,
//! so its features drift across it, and a stroke's flood stops part way
//! (the splat benchmark's floor: a third of it past the flood's limit).
//! Such surfaces are flat, and where colour tells things apart (see
//! `surface_colours` in the parent module) their colour does not drift:
//! when the region a stroke found lies in a thin slab, it continues along
//! that slab through solid voxels showing a colour the stroke's pixels
//! show. What stands on the surface leaves the slab within a few voxels
//! and what meets it at an angle (a wall on a floor) crosses it in a
//! strip, so neither is taken, and a region that is not flat (a pot, a
//! jar) is left as it is.

use crate::field::{Bitmap, FeatureCache, GridGeom};
use glam::{DVec3, Vec3};
use nalgebra::{Matrix3, SymmetricEigen};

/// A slab around a plane: the points within `half_width` of it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Slab {
    pub centre: Vec3,
    /// Unit normal.
    pub normal: Vec3,
    pub half_width: f32,
}

impl Slab {
    pub fn holds(&self, p: Vec3) -> bool {
        (p - self.centre).dot(self.normal).abs() <= self.half_width
    }
}

/// The least half-width of a slab, in voxels (the smallest grid spacing).
const MIN_HALF_WIDTH: f32 = 2.0;
/// A slab's half-width in standard deviations of its points across it: a
/// trained or imported surface is a few voxels thick, a splat floor
/// sampled on a thick slab ten.
const HALF_WIDTH_SIGMAS: f32 = 2.5;
/// The least share of a region inside its slab for it to be flat.
const FLAT_SHARE: f32 = 0.85;
/// The most a flat region's thickness (standard deviation across its
/// plane) may be against its spread along it (standard deviation along
/// its narrower in-plane axis): on the splat benchmark the regions of
/// floors, walls, table tops and boards 0.05–0.19, of pots, mugs, boxes,
/// balls, jars, books and the excavator 0.74–0.95.
const FLAT_RATIO: f32 = 0.25;
/// The least spread along the plane, in voxels: a smaller patch is no
/// surface to follow, and its plane would be guessed from a few voxels.
const MIN_SPREAD: f32 = 6.0;

/// The slab that holds most of `voxels` (grid indices of `geom`), if they
/// are flat: at least `FLAT_SHARE` of them in it, thin against their
/// spread along it (`FLAT_RATIO`, `MIN_SPREAD`). The plane is the
/// least-variance plane of the voxels, fitted again to those within the
/// first fit's slab, so that a strip of a neighbouring surface the region
/// took (the foot of a wall) does not tilt or thicken it.
pub fn flat_slab(geom: &GridGeom, voxels: &[u32]) -> Option<Slab> {
    let h = geom.spacing().min_element();
    let points: Vec<Vec3> = voxels.iter().map(|&v| geom.point_of(v as usize)).collect();
    let first = fit(points.iter().copied())?.slab(h);
    let second = fit(points.iter().copied().filter(|&p| first.holds(p)))?;
    let inside = points.iter().filter(|&&p| second.slab(h).holds(p)).count();
    let flat = inside as f32 >= FLAT_SHARE * points.len() as f32
        && second.thickness <= FLAT_RATIO * second.spread
        && second.spread >= MIN_SPREAD * h;
    flat.then(|| second.slab(h))
}

/// The least-squares slab of `voxels` and whether it is thin against its
/// spread along the plane ([`FLAT_RATIO`]), with no least size: the
/// ground under a small object ([`super::beside`]) is a few voxels wide.
pub fn thin_slab(geom: &GridGeom, voxels: &[u32]) -> Option<Slab> {
    let h = geom.spacing().min_element();
    let f = fit(voxels.iter().map(|&v| geom.point_of(v as usize)))?;
    (f.thickness <= FLAT_RATIO * f.spread).then(|| f.slab(h))
}

/// Voxel-sized squares in a slab's plane, on two axes as near the grid's
/// as the plane allows (a plane across a grid axis gets the other two),
/// so that the squares fall on the voxels' own columns ([`super::supports`],
/// [`super::beside`]).
pub struct PlaneCells {
    origin: Vec3,
    axes: [Vec3; 2],
    h: f32,
}

impl PlaneCells {
    pub fn new(geom: &GridGeom, slab: &Slab) -> Self {
        let n = slab.normal;
        let a = Vec3::AXES[(n.abs().max_position() + 1) % 3];
        let a = (a - a.dot(n) * n).normalize_or(n.any_orthonormal_vector());
        PlaneCells {
            origin: slab.centre,
            axes: [a, n.cross(a)],
            h: geom.spacing().min_element(),
        }
    }

    /// The square under point `p`.
    pub fn of(&self, p: Vec3) -> [i32; 2] {
        let d = p - self.origin;
        self.axes.map(|a| (d.dot(a) / self.h).floor() as i32)
    }
}

/// A least-squares plane: its centre, unit normal, and the standard
/// deviations of the points across it and along its narrower in-plane axis.
struct Fit {
    centre: Vec3,
    normal: Vec3,
    thickness: f32,
    spread: f32,
}

impl Fit {
    /// Its slab on a grid of spacing `h`.
    fn slab(&self, h: f32) -> Slab {
        Slab {
            centre: self.centre,
            normal: self.normal,
            half_width: (HALF_WIDTH_SIGMAS * self.thickness).max(MIN_HALF_WIDTH * h),
        }
    }
}

/// One pass of sums in f64 (world coordinates of a few units against
/// voxels of a hundredth: no loss in the covariance's subtraction).
fn fit(points: impl Iterator<Item = Vec3>) -> Option<Fit> {
    let column = |p: DVec3| nalgebra::Vector3::new(p.x, p.y, p.z);
    let (mut n, mut sum, mut outer) = (0usize, DVec3::ZERO, Matrix3::<f64>::zeros());
    for p in points.map(|p| p.as_dvec3()) {
        n += 1;
        sum += p;
        outer += column(p) * column(p).transpose();
    }
    if n < 3 {
        return None;
    }
    let mean = sum / n as f64;
    let cov = outer / n as f64 - column(mean) * column(mean).transpose();
    let eig = SymmetricEigen::new(cov);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let normal = eig.eigenvectors.column(order[0]);
    let normal = DVec3::new(normal[0], normal[1], normal[2]).normalize_or_zero();
    (normal != DVec3::ZERO).then(|| Fit {
        centre: mean.as_vec3(),
        normal: normal.as_vec3(),
        thickness: eig.eigenvalues[order[0]].max(0.0).sqrt() as f32,
        spread: eig.eigenvalues[order[1]].max(0.0).sqrt() as f32,
    })
}

/// `region` grown through the 6-neighbours of its voxels that are solid
/// (`solid`), inside `slab` and of a colour `shows` accepts (colours are
/// the cache's per-voxel diffuse colours), until none is left.
pub fn grow_in_slab(
    cache: &FeatureCache,
    solid: &Bitmap,
    region: &Bitmap,
    slab: &Slab,
    shows: impl Fn(Vec3) -> bool,
) -> Bitmap {
    let geom = &cache.geom;
    super::flood::faces(geom, region, |n| {
        solid.get(n) && slab.holds(geom.point_of(n)) && cache.index.slot(n).is_some_and(|r| shows(cache.colours[r]))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::Aabb;

    fn grid(n: usize) -> GridGeom {
        GridGeom::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [n; 3])
    }

    fn voxels(g: &GridGeom, keep: impl Fn(Vec3) -> bool) -> Vec<u32> {
        (0..g.len())
            .filter(|&v| keep(g.point_of(v)))
            .map(|v| v as u32)
            .collect()
    }

    /// Known answers: a tilted slab three voxels thick is flat, its normal
    /// found to within a degree; with the foot of a wall standing on it (a
    /// tenth of the voxels) the plane is the same; a ball, a cube and a
    /// small patch are not flat.
    #[test]
    fn flat_regions_give_their_slab_and_others_none() {
        let g = grid(64);
        let h = g.spacing().x;
        let n = Vec3::new(0.2, 1.0, 0.1).normalize();
        let slab = |p: Vec3| (p.dot(n) + 0.3).abs() <= 1.5 * h && p.x.abs() < 0.8 && p.z.abs() < 0.8;
        let floor = voxels(&g, slab);
        let s = flat_slab(&g, &floor).expect("a slab is flat");
        assert!(s.normal.dot(n).abs() > 1f32.to_radians().cos(), "normal {:?}", s.normal);
        assert!(floor.iter().all(|&v| s.holds(g.point_of(v as usize))));
        assert!(
            s.half_width >= MIN_HALF_WIDTH * h && s.half_width <= 3.0 * h,
            "half-width {}",
            s.half_width / h
        );
        // The foot of a wall: a strip standing up from the slab.
        let foot = |p: Vec3| {
            slab(p) || (p.z.abs() < 2.0 * h && p.x.abs() < 0.8 && p.dot(n) + 0.3 > 0.0 && p.dot(n) + 0.3 < 0.15)
        };
        let with_foot = voxels(&g, foot);
        assert!(with_foot.len() > floor.len() + floor.len() / 20);
        let t = flat_slab(&g, &with_foot).expect("still flat");
        assert!(t.normal.dot(n).abs() > 2f32.to_radians().cos(), "normal {:?}", t.normal);
        let ball = voxels(&g, |p| p.length() < 0.5);
        assert_eq!(flat_slab(&g, &ball), None);
        let cube = voxels(&g, |p| p.abs().max_element() < 0.3);
        assert_eq!(flat_slab(&g, &cube), None);
        let patch = voxels(&g, |p| p.y.abs() < h && p.x.abs() < 3.0 * h && p.z.abs() < 3.0 * h);
        assert_eq!(flat_slab(&g, &patch), None);
        assert_eq!(flat_slab(&g, &[]), None);
    }
}
