//! The brick pool: what the GPU view stores of each field's grids, for
//! occupied space only.
//!
//! A field's grid is cut into bricks of [`BRICK_CELLS`]³ cells. A brick is
//! *occupied* when any of its grid points has σ > [`EMPTY_SIGMA`]; only
//! occupied bricks are stored, each as [`BRICK`]³ texels (its 7 cells and
//! the grid points on its far faces, which neighbouring bricks store again).
//! A cell's 8 corners are then always in one brick, so the GPU's trilinear
//! filter never reads across bricks and one texture sample interpolates
//! density (and RGB, and SH coefficients) exactly like the CPU's
//! `geom.corners`. Per field a *slot grid* (one u32 per brick: its
//! field-local slot + 1, 0 when empty) numbers the occupied bricks; the
//! pool textures hold every field's bricks side by side, pool slot `s` at
//! brick position `(s mod px, s / px mod py, s / (px·py))`, and the shader
//! finds a brick's position in an indirection texture
//! (`pack::Indirection`).
//!
//! Empty bricks hold no density above [`EMPTY_SIGMA`] at any corner, so the
//! density interpolated anywhere in their cells is at most that too (the
//! activations are monotonic): the shader reads them as σ = 0, which is the
//! same skip the empty-space grid already makes.
//!
//! When the occupied bricks do not fit the device (3D texture size) or the
//! memory budget, the pool is built on every 2nd (4th, …) grid point: a
//! coarser level of detail over the same box (the *stride*). Each coarse
//! point takes the values of the densest grid point around it (within
//! stride / 2 on each axis), so thin parts get thicker instead of
//! vanishing between coarse points.
//!
//! Mask bitmaps follow the same layout: per occupied brick 16 u32 words,
//! bit `lx + 8·ly + 64·lz` for its texel (x, y, z).
//!
//! Plain data and functions: no bevy types, unit-tested without a GPU.

use crate::field::macro_grid::EMPTY_SIGMA;
use crate::field::{Bitmap, DensityGrid};
use crate::Result;
use rayon::prelude::*;

/// Cells per brick edge.
pub const BRICK_CELLS: usize = 7;
/// Texels (grid points) per brick edge.
pub const BRICK: usize = BRICK_CELLS + 1;
/// Texels per brick.
pub const BRICK_TEXELS: usize = BRICK * BRICK * BRICK;
/// Mask words (u32) per brick.
pub const BRICK_WORDS: usize = BRICK_TEXELS / 32;
/// Coarsest level of detail tried before giving up.
pub const MAX_STRIDE: usize = 16;

/// Grid points per axis at `stride` (every `stride`-th point of `res`).
pub fn lod_res(res: [usize; 3], stride: usize) -> [usize; 3] {
    res.map(|n| (n - 1) / stride + 1)
}

/// Bricks per axis for a grid of `res` points.
pub fn brick_dims(res: [usize; 3]) -> [usize; 3] {
    res.map(|n| (n.saturating_sub(1)).div_ceil(BRICK_CELLS).max(1))
}

/// One field's occupied bricks at one level of detail.
#[derive(Clone, Debug, PartialEq)]
pub struct FieldBricks {
    /// Grid points of the field per point of this level.
    pub stride: usize,
    /// The field's own resolution.
    pub full_res: [usize; 3],
    /// Points per axis at this level ([`lod_res`]).
    pub res: [usize; 3],
    /// Bricks per axis.
    pub dims: [usize; 3],
    /// The slot grid: per brick (x fastest) its field-local slot + 1, 0
    /// when empty.
    pub indirection: Vec<u32>,
    /// Per field-local slot: the brick's linear index.
    pub bricks: Vec<u32>,
    /// At strides above 1, per field-local slot and texel: the grid point
    /// it shows ([`representative`]; `u32::MAX` beyond the grid).
    reps: Vec<u32>,
}

/// The grid point a coarse point `p` (at `stride`) shows: the one with the
/// largest σ within stride / 2 of it on each axis, `p` itself on ties.
fn representative(density: &DensityGrid, stride: usize, p: [usize; 3]) -> usize {
    let res = density.geom.res;
    let c = p.map(|v| v * stride);
    let lin = |q: [usize; 3]| q[0] + res[0] * (q[1] + res[1] * q[2]);
    let r = stride / 2;
    let range = |a: usize| c[a].saturating_sub(r)..=(c[a] + r).min(res[a] - 1);
    let mut best = lin(c);
    let mut best_sigma = density.sigma_at(best);
    for z in range(2) {
        for y in range(1) {
            for x in range(0) {
                let v = lin([x, y, z]);
                let s = density.sigma_at(v);
                if s > best_sigma {
                    (best, best_sigma) = (v, s);
                }
            }
        }
    }
    best
}

impl FieldBricks {
    /// The occupied bricks of `density` at `stride` (every stride-th grid
    /// point; 1 is the full grid).
    pub fn build(density: &DensityGrid, stride: usize) -> Self {
        let full_res = density.geom.res;
        let res = lod_res(full_res, stride);
        let dims = brick_dims(res);
        let mut bricks = FieldBricks {
            stride,
            full_res,
            res,
            dims,
            indirection: Vec::new(),
            bricks: Vec::new(),
            reps: Vec::new(),
        };
        // Per brick, the grid point of each texel (u32::MAX beyond the
        // grid), kept for occupied bricks only.
        let texel_points = |b: usize| -> Option<Vec<u32>> {
            let pts: Vec<u32> = (0..BRICK_TEXELS)
                .map(|t| {
                    bricks.lod_point(b, texel_coords(t)).map_or(u32::MAX, |p| {
                        if stride == 1 {
                            (p[0] + full_res[0] * (p[1] + full_res[1] * p[2])) as u32
                        } else {
                            representative(density, stride, p) as u32
                        }
                    })
                })
                .collect();
            let occupied = pts
                .iter()
                .any(|&v| v != u32::MAX && density.sigma_at(v as usize) > EMPTY_SIGMA);
            occupied.then_some(pts)
        };
        let per_brick: Vec<Option<Vec<u32>>> = (0..dims.iter().product::<usize>())
            .into_par_iter()
            .map(texel_points)
            .collect();
        bricks.indirection = vec![0; per_brick.len()];
        let mut reps = Vec::new();
        for (b, pts) in per_brick.into_iter().enumerate() {
            let Some(pts) = pts else { continue };
            bricks.bricks.push(b as u32);
            bricks.indirection[b] = bricks.bricks.len() as u32;
            if stride > 1 {
                reps.extend(pts);
            }
        }
        bricks.reps = reps;
        bricks
    }

    /// Number of occupied bricks.
    pub fn count(&self) -> usize {
        self.bricks.len()
    }

    /// Coordinates at this level of texel `l` of brick `brick`; `None`
    /// beyond the grid.
    #[inline]
    fn lod_point(&self, brick: usize, l: [usize; 3]) -> Option<[usize; 3]> {
        let d = self.dims;
        let b = [brick % d[0], brick / d[0] % d[1], brick / (d[0] * d[1])];
        let p = [0, 1, 2].map(|a| b[a] * BRICK_CELLS + l[a]);
        (0..3).all(|a| p[a] < self.res[a]).then_some(p)
    }

    /// The full-resolution grid point (linear, x fastest) that texel
    /// `(lx, ly, lz)` of brick `brick` shows; `None` beyond the grid (or,
    /// at strides above 1, in an empty brick).
    #[inline]
    pub fn point(&self, brick: usize, l: [usize; 3]) -> Option<usize> {
        let p = self.lod_point(brick, l)?;
        if self.stride == 1 {
            return Some(p[0] + self.full_res[0] * (p[1] + self.full_res[1] * p[2]));
        }
        let slot = (self.indirection[brick] as usize).checked_sub(1)?;
        let t = l[0] + BRICK * (l[1] + BRICK * l[2]);
        let v = self.reps[slot * BRICK_TEXELS + t];
        (v != u32::MAX).then_some(v as usize)
    }

    /// Every texel of a brick in texel order (x fastest) with its grid point.
    fn brick_points(&self, brick: usize) -> impl Iterator<Item = (usize, Option<usize>)> + '_ {
        (0..BRICK_TEXELS).map(move |t| (t, self.point(brick, texel_coords(t))))
    }
}

/// Texel `t` of a brick as (x, y, z), x fastest.
#[inline]
pub fn texel_coords(t: usize) -> [usize; 3] {
    [t % BRICK, t / BRICK % BRICK, t / (BRICK * BRICK)]
}

/// The bitmap's bits in brick order for `bricks`' occupied bricks:
/// [`BRICK_WORDS`] words per brick, bit `t` for texel `t`.
pub fn brick_bits(bricks: &FieldBricks, bitmap: &Bitmap) -> Vec<u32> {
    let mut words = vec![0u32; bricks.count() * BRICK_WORDS];
    words
        .par_chunks_mut(BRICK_WORDS)
        .zip(bricks.bricks.par_iter())
        .for_each(|(out, &b)| {
            for (t, v) in bricks.brick_points(b as usize) {
                if v.is_some_and(|v| bitmap.get(v)) {
                    out[t >> 5] |= 1 << (t & 31);
                }
            }
        });
    words
}

/// Where every field's bricks sit in the pool textures.
#[derive(Clone, Debug, PartialEq)]
pub struct PoolLayout {
    /// Bricks per axis.
    pub bricks: [usize; 3],
    /// Texels per axis (`bricks × BRICK`).
    pub size: [usize; 3],
    /// Per field, its first slot; field `f`'s local slot `s` is pool slot
    /// `first[f] + s`.
    pub first: Vec<usize>,
    /// Per pool slot: (field, brick linear index); empty slots at the end.
    pub slots: Vec<(u32, u32)>,
}

impl PoolLayout {
    /// Lays out `fields`' bricks in a pool whose textures hold at most
    /// `max_side` texels per axis; `None` when they do not fit.
    pub fn new(fields: &[&FieldBricks], max_side: usize) -> Option<Self> {
        let n: usize = fields.iter().map(|f| f.count()).sum::<usize>().max(1);
        let cap = max_side / BRICK;
        if cap == 0 {
            return None;
        }
        // Roughly a cube, so that no side hits the limit first.
        let px = (n as f64).cbrt().ceil().min(cap as f64) as usize;
        let py = ((n as f64 / px as f64).sqrt().ceil() as usize).clamp(1, cap);
        let pz = n.div_ceil(px * py);
        if pz > cap {
            return None;
        }
        let mut first = Vec::with_capacity(fields.len());
        let mut slots = Vec::with_capacity(n);
        for (i, f) in fields.iter().enumerate() {
            first.push(slots.len());
            slots.extend(f.bricks.iter().map(|&b| (i as u32, b)));
        }
        let bricks = [px, py, pz];
        Some(PoolLayout {
            bricks,
            size: bricks.map(|b| b * BRICK),
            first,
            slots,
        })
    }

    /// Texels in each pool texture.
    pub fn texels(&self) -> usize {
        self.size.iter().product()
    }

    /// A pool texture's contents (x fastest): `value(field, brick, texel
    /// coords)` for texels of occupied bricks, `T::default()` elsewhere.
    /// Filled one texel row at a time, in parallel, straight from the
    /// fields' grids (no per-brick staging copy).
    pub fn fill<T: Copy + Default + Send>(&self, value: impl Fn(usize, usize, [usize; 3]) -> T + Sync) -> Vec<T> {
        let [sx, sy, _] = self.size;
        let [px, py, _] = self.bricks;
        let mut out = vec![T::default(); self.texels()];
        out.par_chunks_mut(sx).enumerate().for_each(|(row, texels)| {
            let (ty, tz) = (row % sy, row / sy);
            let (by, bz) = (ty / BRICK, tz / BRICK);
            for bx in 0..px {
                let Some(&(f, b)) = self.slots.get(bx + px * (by + py * bz)) else {
                    break;
                };
                for lx in 0..BRICK {
                    texels[bx * BRICK + lx] = value(f as usize, b as usize, [lx, ty % BRICK, tz % BRICK]);
                }
            }
        });
        out
    }
}

/// The level of detail the GPU view shows and the pool that holds it.
#[derive(Clone, Debug)]
pub struct PoolPlan {
    /// Grid points per texel (1: full detail).
    pub stride: usize,
    pub fields: Vec<FieldBricks>,
    pub layout: PoolLayout,
    /// Bytes the pool textures take.
    pub bytes: usize,
}

/// Chooses the finest level of detail at which `fields`' occupied bricks
/// fit the device's 3D texture size (`max_side`), `budget` bytes of pool
/// textures at `bytes_per_texel`, and `max_texels` texels (what a
/// per-texel storage buffer may index).
pub fn plan(
    fields: &[&DensityGrid],
    bytes_per_texel: usize,
    max_side: usize,
    budget: usize,
    max_texels: usize,
) -> Result<PoolPlan> {
    let mut stride = 1;
    let mut needed = 0;
    while stride <= MAX_STRIDE {
        let bricks: Vec<FieldBricks> = fields.iter().map(|d| FieldBricks::build(d, stride)).collect();
        let refs: Vec<&FieldBricks> = bricks.iter().collect();
        let count: usize = bricks.iter().map(FieldBricks::count).sum();
        let bytes = count * BRICK_TEXELS * bytes_per_texel;
        if stride == 1 {
            needed = bytes;
        }
        if bytes <= budget {
            let layout = PoolLayout::new(&refs, max_side).filter(|l| l.texels() <= max_texels);
            if let Some(layout) = layout {
                let bytes = layout.texels() * bytes_per_texel;
                return Ok(PoolPlan {
                    stride,
                    fields: bricks,
                    layout,
                    bytes,
                });
            }
        }
        // Coarser, as long as every axis keeps two points.
        if fields
            .iter()
            .any(|d| d.geom.res.iter().any(|&n| (n - 1) / (2 * stride) < 1))
        {
            break;
        }
        stride *= 2;
    }
    Err(crate::Error::device_limit(format!(
        "the scene does not fit the GPU even at a coarse level of detail: it needs {} of textures \
         at full detail, the budget is {} and 3D textures hold {max_side} texels per side",
        crate::util::human_bytes(needed),
        crate::util::human_bytes(budget)
    )))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{Aabb, FieldBuilder};
    use glam::Vec3;

    /// A ball of density in one corner of a 30 × 20 × 16 grid.
    fn corner_ball() -> DensityGrid {
        FieldBuilder::new(Aabb::new(Vec3::ZERO, Vec3::new(29.0, 19.0, 15.0)), [30, 20, 16])
            .build(
                |p| {
                    if (p - Vec3::splat(3.0)).length() < 2.5 {
                        5.0
                    } else {
                        -1.0
                    }
                },
                |_| Vec3::ONE,
                None,
            )
            .density
    }

    #[test]
    fn only_bricks_with_density_are_stored_and_texels_map_to_their_points() {
        let d = corner_ball();
        let b = FieldBricks::build(&d, 1);
        // 29 × 19 × 15 cells = 5 × 3 × 3 bricks of 7.
        assert_eq!(b.dims, [5, 3, 3]);
        // The ball (points 1..=5 on each axis) lies in brick 0 only.
        assert_eq!(b.bricks, vec![0]);
        assert_eq!(b.indirection.iter().filter(|&&s| s != 0).count(), 1);
        assert_eq!(b.indirection[0], 1);
        // Texel (lx, ly, lz) of brick (1, 2, 0) is point (7 + lx, 14 + ly, lz);
        // its last texels share the next brick's first points.
        let brick = 1 + 5 * 2;
        assert_eq!(b.point(brick, [0, 0, 0]), Some(7 + 30 * 14));
        assert_eq!(b.point(brick, [7, 5, 3]), Some(14 + 30 * (19 + 20 * 3)));
        // Beyond the grid (y = 14 + 6 = 20).
        assert_eq!(b.point(brick, [0, 6, 0]), None);
        // A brick is occupied iff one of its points is: brute force.
        for brick in 0..45 {
            let any = (0..BRICK_TEXELS).any(|t| {
                b.point(brick, texel_coords(t))
                    .is_some_and(|v| d.sigma_at(v) > EMPTY_SIGMA)
            });
            assert_eq!(b.indirection[brick] != 0, any, "brick {brick}");
        }
    }

    #[test]
    fn coarser_levels_show_the_densest_point_around_every_stride_th_point() {
        let mut d = corner_ball();
        d.raw.fill(1.0);
        let b = FieldBricks::build(&d, 2);
        assert_eq!(b.res, [15, 10, 8]);
        assert_eq!(b.dims, [2, 2, 1]);
        // Uniform density: texel (1, 2, 3) of brick (1, 0, 0) is LOD point
        // (8, 2, 3), grid point (16, 4, 6) itself.
        let at = |x: usize, y: usize, z: usize| x + 30 * (y + 20 * z);
        assert_eq!(b.point(1, [1, 2, 3]), Some(at(16, 4, 6)));
        // A denser neighbour within one point wins; one two points away does not.
        d.raw[at(17, 3, 6)] = 9.0;
        d.raw[at(16, 4, 8)] = 20.0;
        let b = FieldBricks::build(&d, 2);
        assert_eq!(b.point(1, [1, 2, 3]), Some(at(17, 3, 6)));
        // A ball of radius 2.5 between every 8th point still shows at stride 8.
        let ball = corner_ball();
        let coarse = FieldBricks::build(&ball, 8);
        assert_eq!(coarse.count(), 1);
        assert!((0..BRICK_TEXELS).any(|t| coarse.point(0, texel_coords(t)).is_some_and(|v| ball.sigma_at(v) > 1.0)));
    }

    #[test]
    fn mask_bits_follow_the_bricks() {
        let d = corner_ball();
        let b = FieldBricks::build(&d, 1);
        let res = d.geom.res;
        let bits = Bitmap::from_fn(res, |v| v % 3 == 0);
        let words = brick_bits(&b, &bits);
        assert_eq!(words.len(), BRICK_WORDS);
        for t in 0..BRICK_TEXELS {
            let want = b.point(0, texel_coords(t)).is_some_and(|v| v % 3 == 0);
            assert_eq!(words[t >> 5] >> (t & 31) & 1 == 1, want, "texel {t}");
        }
    }

    #[test]
    fn pool_places_slots_and_fills_texels_from_their_bricks() {
        let d = corner_ball();
        let full = FieldBricks::build(&d, 1);
        let mut many = full.clone();
        // Pretend 10 bricks are occupied to get several pool rows.
        many.bricks = (0..10).collect();
        let layout = PoolLayout::new(&[&full, &many], 1024).unwrap();
        assert_eq!(layout.slots.len(), 11);
        assert_eq!(layout.first, vec![0, 1]);
        let [px, py, pz] = layout.bricks;
        assert!(px * py * pz >= 11);
        let tex = layout.fill(|f, b, l| (f * 1000 + b * 10 + l[0] + l[1] + l[2]) as u32 + 1);
        for (slot, &(f, b)) in layout.slots.iter().enumerate() {
            let base = [slot % px, slot / px % py, slot / (px * py)].map(|c| c * BRICK);
            let at = |l: [usize; 3]| {
                let [x, y, z] = [0, 1, 2].map(|a| base[a] + l[a]);
                tex[x + layout.size[0] * (y + layout.size[1] * z)]
            };
            for l in [[0, 0, 0], [7, 0, 0], [3, 5, 7], [7, 7, 7]] {
                assert_eq!(
                    at(l),
                    (f * 1000 + b * 10) + (l[0] + l[1] + l[2]) as u32 + 1,
                    "slot {slot}"
                );
            }
        }
        // Unused slots stay at the default.
        assert_eq!(
            tex.iter().filter(|&&v| v == 0).count(),
            (px * py * pz - 11) * BRICK_TEXELS
        );
        // Too small a texture: no layout.
        assert!(PoolLayout::new(&[&many], 8).is_none());
    }

    #[test]
    fn plan_falls_back_to_coarser_detail_within_the_budget() {
        let d = corner_ball();
        let fine = plan(&[&d], 2, 2048, 1 << 30, usize::MAX).unwrap();
        assert_eq!(fine.stride, 1);
        // Less than one brick of budget at full detail: nothing fits at
        // stride 1 (one brick = 1 KiB at 2 bytes a texel).
        let e = plan(&[&d], 2, 2048, 512, usize::MAX).unwrap_err();
        assert!(e.to_string().contains("does not fit"), "{e}");
        // A texture limit of 8 texels fits one brick: stride 1 has one
        // occupied brick, so it fits; with a 7-texel limit nothing does.
        assert_eq!(plan(&[&d], 2, 8, 1 << 30, usize::MAX).unwrap().stride, 1);
        assert!(plan(&[&d], 2, 7, 1 << 30, usize::MAX).is_err());
        // Nor when one brick is more texels than a storage buffer indexes.
        assert!(plan(&[&d], 2, 2048, 1 << 30, BRICK_TEXELS - 1).is_err());
        // Density everywhere: 45 bricks at full detail, 4 at stride 2.
        let mut solid = d.clone();
        solid.raw.fill(5.0);
        let brick_bytes = BRICK_TEXELS * 2;
        assert_eq!(
            plan(&[&solid], 2, 2048, 45 * brick_bytes, usize::MAX).unwrap().stride,
            1
        );
        let p = plan(&[&solid], 2, 2048, 10 * brick_bytes, usize::MAX).unwrap();
        assert_eq!(p.stride, 2);
        assert_eq!(p.fields[0].count(), 4);
        assert!(p.bytes >= 4 * brick_bytes);
    }
}
