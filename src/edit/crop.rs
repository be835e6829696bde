//! A segmented object as a standalone field: the sub-grid over the object's
//! bounding box (plus a margin), with the density outside the object removed.
//!
//! The cropped field keeps the original's world coordinates: its bounds are
//! the world box of the kept sub-grid, so it renders where the object was.
//! Inside that box it samples exactly like the original with its density
//! multiplied by the bitmap at the grid points (σ·b):
//! - density: the raw value is kept inside the object and replaced outside
//!   by [`empty_raw`]. Edits act on the *activated* density: for ReLU fields
//!   raw 0 gives σ = 0; for softplus fields raw = [`EMPTY_LOGIT`] − shift
//!   gives σ = softplus(−20) ≈ 2·10⁻⁹, i.e. empty (raw 0 would leave haze,
//!   since softplus(shift) is not 0);
//! - appearance and features are cropped, not masked (the density already
//!   hides them), so colours at the object's surface blend with the same
//!   neighbours as in the original;
//! - sparse grids keep the occupied voxels of the sub-box, under a rebuilt
//!   occupancy / rank index, so their renormalised samples are unchanged;
//! - grids of another resolution (dense channel grids, VM planes and lines)
//!   are mapped through world space: where the box falls on their grid
//!   points they are cut exactly, otherwise they are resampled (linearly)
//!   at no coarser spacing.

use crate::error::{Error, Result};
use crate::field::vm::MODE_AXES;
use crate::field::{
    Aabb, Activation, Appearance, Bitmap, ChannelGrid, DensityGrid, Features, Field, GridGeom, Layout, RankIndex,
    VmGrid,
};
use half::f16;
use rayon::prelude::*;
use std::sync::Arc;

/// Pre-activation value (raw + shift) that softplus fields get outside the
/// object: softplus(−20) ≈ 2·10⁻⁹.
pub const EMPTY_LOGIT: f32 = -20.0;

/// Raw density value whose activation is (numerically) zero.
pub fn empty_raw(activation: Activation) -> f32 {
    match activation {
        Activation::Relu => 0.0,
        Activation::Softplus { shift } => EMPTY_LOGIT - shift,
    }
}

/// The kept sub-grid: inclusive voxel range `[lo, hi]` of the density grid
/// and its world box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CropBox {
    pub lo: [usize; 3],
    pub hi: [usize; 3],
    pub geom: GridGeom,
}

/// The sub-grid over the bitmap's bounding box grown by `margin_voxels`,
/// clamped to the grid and at least two points along every axis.
pub fn crop_box(geom: &GridGeom, bitmap: &Bitmap, margin_voxels: usize) -> Result<CropBox> {
    crate::ensure!(
        bitmap.res() == geom.res,
        "object bitmap has resolution {:?} but the field's density grid is {:?}",
        bitmap.res(),
        geom.res
    );
    crate::ensure!(
        geom.res.iter().all(|&n| n >= 2),
        "field resolution {:?} is too small to crop",
        geom.res
    );
    let (bmin, bmax) = bitmap
        .bounding_box()
        .ok_or_else(|| Error::invalid("the object's bitmap is empty: there is nothing to crop"))?;
    let mut lo = [0; 3];
    let mut hi = [0; 3];
    for a in 0..3 {
        lo[a] = bmin[a].saturating_sub(margin_voxels);
        hi[a] = bmax[a].saturating_add(margin_voxels).min(geom.res[a] - 1);
        if hi[a] == lo[a] {
            // A one-voxel-thin object still needs a cell to interpolate in.
            if hi[a] + 1 < geom.res[a] {
                hi[a] += 1;
            } else {
                lo[a] -= 1;
            }
        }
    }
    let bounds = Aabb::new(geom.point(lo[0], lo[1], lo[2]), geom.point(hi[0], hi[1], hi[2]));
    let res = [0, 1, 2].map(|a| hi[a] - lo[a] + 1);
    Ok(CropBox {
        lo,
        hi,
        geom: GridGeom::new(bounds, res),
    })
}

/// A standalone field holding only the object `bitmap` (over `field`'s
/// density grid): see the module docs for what is kept and how.
pub fn object_field(field: &Field, bitmap: &Bitmap, margin_voxels: usize) -> Result<Field> {
    let geom = field.geom();
    let cb = crop_box(&geom, bitmap, margin_voxels)?;
    let density = crop_density(&field.density, bitmap, &cb);
    let occupancy = field
        .occupancy
        .as_ref()
        .map(|o| Arc::new(RankIndex::new(crop_bits(o.bits(), &geom, &cb))));
    let shared = Shared {
        old: field.occupancy.as_ref(),
        new: occupancy.as_ref(),
        res: geom.res,
    };
    let appearance = match &field.appearance {
        Appearance::Rgb(g) => Appearance::Rgb(crop_channels(g, &shared, &cb)?),
        Appearance::Sh2(g) => Appearance::Sh2(crop_channels(g, &shared, &cb)?),
        Appearance::Vm { grid, mlp } => Appearance::Vm {
            grid: crop_vm(grid, &cb),
            mlp: mlp.clone(),
        },
    };
    let features = match &field.features {
        Some(Features::Grid(g)) => Some(Features::Grid(crop_channels(g, &shared, &cb)?)),
        Some(Features::Vm(v)) => Some(Features::Vm(crop_vm(v, &cb))),
        None => None,
    };
    Ok(Field::new(density, appearance, features, occupancy).in_space_of(field))
}

/// Flat index in the full grid of sub-grid point `i`.
#[inline]
fn full_index(geom: &GridGeom, cb: &CropBox, i: usize) -> usize {
    let [x, y, z] = cb.geom.coords(i);
    geom.index(x + cb.lo[0], y + cb.lo[1], z + cb.lo[2])
}

fn crop_density(d: &DensityGrid, bitmap: &Bitmap, cb: &CropBox) -> DensityGrid {
    let empty = empty_raw(d.activation);
    let raw = (0..cb.geom.len())
        .into_par_iter()
        .map(|i| {
            let j = full_index(&d.geom, cb, i);
            if bitmap.get(j) {
                d.raw[j]
            } else {
                empty
            }
        })
        .collect();
    DensityGrid {
        geom: cb.geom,
        raw,
        activation: d.activation,
    }
}

fn crop_bits(bits: &Bitmap, geom: &GridGeom, cb: &CropBox) -> Bitmap {
    Bitmap::from_fn(cb.geom.res, |i| bits.get(full_index(geom, cb, i)))
}

/// The field's occupancy before and after cropping; sparse grids must use it.
struct Shared<'a> {
    old: Option<&'a Arc<RankIndex>>,
    new: Option<&'a Arc<RankIndex>>,
    res: [usize; 3],
}

fn crop_channels(g: &ChannelGrid, shared: &Shared, cb: &CropBox) -> Result<ChannelGrid> {
    match &g.layout {
        Layout::Dense => Ok(crop_dense(g, cb)),
        Layout::Sparse(_) if g.geom.res != shared.res => Ok(crop_sampled(g, cb)),
        Layout::Sparse(ix) => {
            let (Some(old), Some(new)) = (shared.old, shared.new) else {
                return Err(Error::invalid("a grid is sparse but the field has no occupancy index"));
            };
            crate::ensure!(
                g.geom.res == shared.res && (Arc::ptr_eq(ix, old) || ix.bits() == old.bits()),
                "a sparse grid does not use the field's occupancy index"
            );
            let ch = g.channels;
            let voxels: Vec<usize> = new.bits().ones().collect();
            let mut data = vec![f16::ZERO; voxels.len() * ch];
            data.par_chunks_mut(ch.max(1)).zip(&voxels).for_each(|(dst, &i)| {
                let s = old
                    .slot(full_index(&g.geom, cb, i))
                    .expect("cropped occupancy is a subset of the original");
                dst.copy_from_slice(&g.data[s * ch..(s + 1) * ch]);
            });
            Ok(ChannelGrid::sparse(cb.geom, ch, new.clone(), data))
        }
    }
}

/// Source taps along one axis for each point of the cropped grid:
/// `(i0, f)` means `(1 − f)·v[i0] + f·v[i0 + 1]`.
type AxisMap = Vec<(usize, f32)>;

/// Where the crop box's extent along `axis` falls on grid `src`: exact
/// grid points when it is aligned with them, otherwise a resampling with
/// spacing no coarser than the source's.
fn axis_map(src: &GridGeom, cb: &CropBox, axis: usize) -> AxisMap {
    let n = src.res[axis];
    let (min, max) = (src.bounds.min[axis] as f64, src.bounds.max[axis] as f64);
    let to_grid = |w: f32| ((w as f64 - min) / (max - min) * (n - 1) as f64).clamp(0.0, (n - 1) as f64);
    let g_lo = to_grid(cb.geom.bounds.min[axis]);
    let g_hi = to_grid(cb.geom.bounds.max[axis]);
    let (r_lo, r_hi) = (g_lo.round(), g_hi.round());
    const SNAP: f64 = 1e-3;
    if (g_lo - r_lo).abs() < SNAP && (g_hi - r_hi).abs() < SNAP && r_hi > r_lo {
        return (r_lo as usize..=r_hi as usize).map(|i| (i, 0.0)).collect();
    }
    let m = ((g_hi - g_lo - SNAP).ceil().max(1.0) as usize) + 1;
    (0..m)
        .map(|j| {
            let g = g_lo + (g_hi - g_lo) * j as f64 / (m - 1) as f64;
            let i0 = (g.floor() as usize).min(n.saturating_sub(2));
            (i0, (g - i0 as f64) as f32)
        })
        .collect()
}

/// The two taps of an axis-map entry (the second has weight 0 when exact).
#[inline]
fn taps((i0, f): (usize, f32), n: usize) -> [(usize, f32); 2] {
    [(i0, 1.0 - f), ((i0 + 1).min(n - 1), f)]
}

fn crop_dense(g: &ChannelGrid, cb: &CropBox) -> ChannelGrid {
    let maps = [0, 1, 2].map(|a| axis_map(&g.geom, cb, a));
    let res = [0, 1, 2].map(|a| maps[a].len());
    let geom = GridGeom::new(cb.geom.bounds, res);
    let ch = g.channels;
    let mut data = vec![f16::ZERO; geom.len() * ch];
    data.par_chunks_mut(res[0] * res[1] * ch)
        .enumerate()
        .for_each(|(z, plane)| {
            let mut acc = vec![0.0f32; ch];
            for y in 0..res[1] {
                for x in 0..res[0] {
                    acc.fill(0.0);
                    for (iz, wz) in taps(maps[2][z], g.geom.res[2]) {
                        for (iy, wy) in taps(maps[1][y], g.geom.res[1]) {
                            for (ix, wx) in taps(maps[0][x], g.geom.res[0]) {
                                let w = wx * wy * wz;
                                if w == 0.0 {
                                    continue;
                                }
                                let s = g.geom.index(ix, iy, iz) * ch;
                                for (a, v) in acc.iter_mut().zip(&g.data[s..s + ch]) {
                                    *a += w * v.to_f32();
                                }
                            }
                        }
                    }
                    let d = (x + res[0] * y) * ch;
                    for (o, &a) in plane[d..d + ch].iter_mut().zip(&acc) {
                        *o = f16::from_f32(a);
                    }
                }
            }
        });
    ChannelGrid::dense(geom, ch, data)
}

/// A sparse grid with its own index (features at their own resolution):
/// the points [`crop_dense`] would make, each sampled from the grid as the
/// renderer does (renormalised over stored corners); the result is dense.
fn crop_sampled(g: &ChannelGrid, cb: &CropBox) -> ChannelGrid {
    let res = [0, 1, 2].map(|a| axis_map(&g.geom, cb, a).len());
    let geom = GridGeom::new(cb.geom.bounds, res);
    let ch = g.channels;
    let mut data = vec![f16::ZERO; geom.len() * ch];
    data.par_chunks_mut(ch.max(1)).enumerate().for_each_init(
        || vec![0.0f32; ch],
        |tmp, (i, row)| {
            g.sample(geom.point_of(i), tmp);
            for (o, &v) in row.iter_mut().zip(tmp.iter()) {
                *o = f16::from_f32(v);
            }
        },
    );
    ChannelGrid::dense(geom, ch, data)
}

fn crop_vm(v: &VmGrid, cb: &CropBox) -> VmGrid {
    let maps = [0, 1, 2].map(|a| axis_map(&v.geom, cb, a));
    let res = [0, 1, 2].map(|a| maps[a].len());
    let src = v.geom.res;
    let mut planes: [Vec<f32>; 3] = Default::default();
    let mut lines: [Vec<f32>; 3] = Default::default();
    for (m, &(a, b, c)) in MODE_AXES.iter().enumerate() {
        let mut plane = Vec::with_capacity(v.comps[m] * res[a] * res[b]);
        let mut line = Vec::with_capacity(v.comps[m] * res[c]);
        for r in 0..v.comps[m] {
            let sp = &v.planes[m][r * src[a] * src[b]..(r + 1) * src[a] * src[b]];
            for &mb in &maps[b] {
                for &ma in &maps[a] {
                    let mut acc = 0.0;
                    for (ib, wb) in taps(mb, src[b]) {
                        for (ia, wa) in taps(ma, src[a]) {
                            acc += wa * wb * sp[ib * src[a] + ia];
                        }
                    }
                    plane.push(acc);
                }
            }
            let sl = &v.lines[m][r * src[c]..(r + 1) * src[c]];
            for &mc in &maps[c] {
                line.push(taps(mc, src[c]).iter().map(|&(i, w)| w * sl[i]).sum());
            }
        }
        planes[m] = plane;
        lines[m] = line;
    }
    VmGrid {
        geom: GridGeom::new(cb.geom.bounds, res),
        comps: v.comps,
        planes,
        lines,
        basis: v.basis.clone(),
        out: v.out,
    }
}
