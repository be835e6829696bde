//! Grid geometry shared by every grid of a field.
//!
//! Convention (tested): a grid of resolution `[nx, ny, nz]` has its sample
//! points at the *corners*, `p(i,j,k) = min + (i/(nx-1), j/(ny-1), k/(nz-1)) * (max - min)`
//! (TensoRF/DVGO `align_corners = true`). Flat arrays are **x fastest**:
//! `index = x + nx * (y + ny * z)`; a voxel's channels are contiguous.

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Largest number of grid points we accept in one grid (1024³). Files that ask
/// for more are rejected before anything is allocated.
pub const MAX_VOXELS: usize = 1 << 30;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    pub fn new(min: Vec3, max: Vec3) -> Self {
        Aabb { min, max }
    }
    pub fn size(&self) -> Vec3 {
        self.max - self.min
    }
    pub fn center(&self) -> Vec3 {
        0.5 * (self.min + self.max)
    }
    pub fn contains(&self, p: Vec3) -> bool {
        p.cmpge(self.min).all() && p.cmple(self.max).all()
    }
    pub fn is_valid(&self) -> bool {
        self.min.is_finite() && self.max.is_finite() && self.max.cmpgt(self.min).all()
    }
    /// Slab test: the parametric interval `[t0, t1]` (clamped to `t >= 0`) where
    /// the ray `o + t d` is inside the box, if any.
    pub fn intersect(&self, o: Vec3, d: Vec3) -> Option<(f32, f32)> {
        let inv = d.recip();
        let a = (self.min - o) * inv;
        let b = (self.max - o) * inv;
        // NaN arises for d = 0 with o on a slab plane; treat as inside.
        let lo = a.min(b);
        let hi = a.max(b);
        let t0 = lo.x.max(lo.y).max(lo.z).max(0.0);
        let t1 = hi.x.min(hi.y).min(hi.z);
        (t1 > t0).then_some((t0, t1))
    }
    /// Smallest box holding the eight corners of this box mapped by `m`.
    pub fn transformed(&self, m: &glam::Affine3A) -> Aabb {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for i in 0..8 {
            let c = Vec3::new(
                if i & 1 == 0 { self.min.x } else { self.max.x },
                if i & 2 == 0 { self.min.y } else { self.max.y },
                if i & 4 == 0 { self.min.z } else { self.max.z },
            );
            let p = m.transform_point3(c);
            lo = lo.min(p);
            hi = hi.max(p);
        }
        Aabb::new(lo, hi)
    }
}

/// Resolution plus bounds: maps world points to continuous grid coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridGeom {
    pub bounds: Aabb,
    pub res: [usize; 3],
}

/// The eight corners of the cell holding a point and their trilinear weights.
#[derive(Clone, Copy, Debug)]
pub struct Corners {
    pub index: [usize; 8],
    pub weight: [f32; 8],
}

impl GridGeom {
    pub fn new(bounds: Aabb, res: [usize; 3]) -> Self {
        GridGeom { bounds, res }
    }
    pub fn len(&self) -> usize {
        self.res[0] * self.res[1] * self.res[2]
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    #[inline]
    pub fn index(&self, x: usize, y: usize, z: usize) -> usize {
        x + self.res[0] * (y + self.res[1] * z)
    }
    #[inline]
    /// Calls `f` for every grid point in the 3×3×3 neighbourhood of `v`
    /// (26-connected; `v` excluded, clipped to the grid).
    pub fn neighbours26(&self, v: usize, mut f: impl FnMut(usize)) {
        let [x, y, z] = self.coords(v);
        let near = |c: usize, n: usize| c.saturating_sub(1)..=(c + 1).min(n - 1);
        for zz in near(z, self.res[2]) {
            for yy in near(y, self.res[1]) {
                for xx in near(x, self.res[0]) {
                    let n = self.index(xx, yy, zz);
                    if n != v {
                        f(n);
                    }
                }
            }
        }
    }
    pub fn coords(&self, i: usize) -> [usize; 3] {
        let x = i % self.res[0];
        let yz = i / self.res[0];
        [x, yz % self.res[1], yz / self.res[1]]
    }
    /// World-space distance between neighbouring grid points along each axis.
    pub fn spacing(&self) -> Vec3 {
        let n = Vec3::new(
            (self.res[0] - 1) as f32,
            (self.res[1] - 1) as f32,
            (self.res[2] - 1) as f32,
        );
        self.bounds.size() / n
    }
    /// World position of grid point `(x, y, z)`.
    pub fn point(&self, x: usize, y: usize, z: usize) -> Vec3 {
        self.bounds.min + Vec3::new(x as f32, y as f32, z as f32) * self.spacing()
    }
    pub fn point_of(&self, i: usize) -> Vec3 {
        let [x, y, z] = self.coords(i);
        self.point(x, y, z)
    }
    /// Continuous grid coordinates of a world point (grid point i at i).
    #[inline]
    pub fn to_grid(&self, p: Vec3) -> Vec3 {
        let n = Vec3::new(
            (self.res[0] - 1) as f32,
            (self.res[1] - 1) as f32,
            (self.res[2] - 1) as f32,
        );
        (p - self.bounds.min) / self.bounds.size() * n
    }
    /// Nearest grid point of a world point, if inside the grid.
    pub fn nearest(&self, p: Vec3) -> Option<[usize; 3]> {
        let g = self.to_grid(p).round();
        if g.cmplt(Vec3::ZERO).any() || !g.is_finite() {
            return None;
        }
        let (x, y, z) = (g.x as usize, g.y as usize, g.z as usize);
        (x < self.res[0] && y < self.res[1] && z < self.res[2]).then_some([x, y, z])
    }
    /// Trilinear corners of a world point; `None` outside the grid.
    #[inline]
    pub fn corners(&self, p: Vec3) -> Option<Corners> {
        let g = self.to_grid(p);
        let [nx, ny, nz] = self.res;
        if !(g.x >= 0.0
            && g.y >= 0.0
            && g.z >= 0.0
            && g.x <= (nx - 1) as f32
            && g.y <= (ny - 1) as f32
            && g.z <= (nz - 1) as f32)
        {
            return None;
        }
        // Base corner clamped so that points on the upper face use the last cell.
        let x0 = (g.x as usize).min(nx.saturating_sub(2));
        let y0 = (g.y as usize).min(ny.saturating_sub(2));
        let z0 = (g.z as usize).min(nz.saturating_sub(2));
        let (fx, fy, fz) = (g.x - x0 as f32, g.y - y0 as f32, g.z - z0 as f32);
        let base = self.index(x0, y0, z0);
        let (sx, sy, sz) = (1, nx, nx * ny);
        let mut c = Corners {
            index: [0; 8],
            weight: [0.0; 8],
        };
        for k in 0..8 {
            let (dx, dy, dz) = (k & 1, (k >> 1) & 1, (k >> 2) & 1);
            c.index[k] = base + dx * sx + dy * sy + dz * sz;
            let wx = if dx == 1 { fx } else { 1.0 - fx };
            let wy = if dy == 1 { fy } else { 1.0 - fy };
            let wz = if dz == 1 { fz } else { 1.0 - fz };
            c.weight[k] = wx * wy * wz;
        }
        Some(c)
    }
}

/// Checks a resolution read from a file or the command line.
pub fn check_res(res: [usize; 3], what: &str) -> crate::error::Result<()> {
    crate::ensure_within!(
        OutOfRange,
        res.iter().all(|&n| n >= 2),
        "{what}: resolution {res:?} must be at least 2 along every axis"
    );
    let total = res.iter().try_fold(1usize, |acc, &n| acc.checked_mul(n));
    crate::ensure_within!(
        OutOfRange,
        matches!(total, Some(t) if t <= MAX_VOXELS),
        "{what}: resolution {res:?} is absurdly large (more than {MAX_VOXELS} grid points)"
    );
    Ok(())
}
