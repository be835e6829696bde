//! Coarse max-density grid for empty-space skipping.
//!
//! Cell c covers `BLOCK` density cells per axis (grid points
//! `[c·BLOCK, c·BLOCK + BLOCK]`, inclusive, because trilinear interpolation in
//! a cell reads both ends). A cell is empty when the largest activated σ at
//! those points is ≤ [`EMPTY_SIGMA`]; since the activation is monotone, the
//! interpolated σ anywhere inside is then ≤ EMPTY_SIGMA too, so skipping it
//! changes transmittance by at most exp(−EMPTY_SIGMA·distance).

use super::{Aabb, DensityGrid};
use glam::Vec3;
use rayon::prelude::*;

pub const BLOCK: usize = 8;
pub const EMPTY_SIGMA: f32 = 1e-4;

#[derive(Debug, Clone)]
pub struct MacroGrid {
    bounds: Aabb,
    /// World size of one macro cell per axis.
    cell: Vec3,
    dims: [usize; 3],
    occupied: Vec<bool>,
}

impl MacroGrid {
    pub fn build(d: &DensityGrid) -> Self {
        let g = d.geom;
        let dims = g.res.map(|n| (n - 1).div_ceil(BLOCK).max(1));
        let occupied = (0..dims[0] * dims[1] * dims[2])
            .into_par_iter()
            .map(|c| {
                let (cx, cy, cz) = (c % dims[0], (c / dims[0]) % dims[1], c / (dims[0] * dims[1]));
                let range = |cc: usize, a: usize| cc * BLOCK..=((cc + 1) * BLOCK).min(g.res[a] - 1);
                range(cz, 2)
                    .any(|z| range(cy, 1).any(|y| range(cx, 0).any(|x| d.sigma_at(g.index(x, y, z)) > EMPTY_SIGMA)))
            })
            .collect();
        MacroGrid {
            bounds: g.bounds,
            cell: g.spacing() * BLOCK as f32,
            dims,
            occupied,
        }
    }

    /// `None` when the field may have density near `p` (local coordinates);
    /// otherwise the distance along `d` (not necessarily unit: distances are
    /// in the caller's ray parameter) over which it certainly has none.
    pub fn skip_distance(&self, p: Vec3, d: Vec3) -> Option<f32> {
        if !self.bounds.contains(p) {
            // Outside the box: empty until the ray (maybe) enters it.
            return Some(match self.bounds.intersect(p, d) {
                Some((t0, _)) => t0,
                None => f32::INFINITY,
            });
        }
        let rel = (p - self.bounds.min) / self.cell;
        let c = [0, 1, 2].map(|a| (rel[a].max(0.0) as usize).min(self.dims[a] - 1));
        if self.occupied[c[0] + self.dims[0] * (c[1] + self.dims[1] * c[2])] {
            return None;
        }
        let lo = self.bounds.min + Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32) * self.cell;
        let hi = lo + self.cell;
        // Exit distance of the cell along d.
        let inv = d.recip();
        let t = ((lo - p) * inv).max((hi - p) * inv);
        let exit = t.x.min(t.y).min(t.z);
        Some(if exit.is_finite() { exit.max(0.0) } else { 0.0 })
    }

    pub fn occupied_fraction(&self) -> f32 {
        self.occupied.iter().filter(|&&o| o).count() as f32 / self.occupied.len() as f32
    }
}
