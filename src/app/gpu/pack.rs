//! CPU-side packing of a [`Scene`] into the flat arrays and `#[repr(C)]`
//! structs that `shaders/raymarch.wgsl` reads. Plain functions over plain
//! data (no bevy types), so they are unit-tested without a GPU.
//!
//! Layout contract with the shader (every struct is made of 16-byte vectors
//! so that WGSL's uniform/storage layout rules equal `#[repr(C)]`); all
//! fields' arrays are concatenated, and [`GpuField::offsets`] say where each
//! field's part starts:
//! - the density and RGB colour textures (3D, sampled with the GPU's
//!   trilinear filter): every field's grid stacked along z in one
//!   [`Atlas`], raw density (uploaded as f16) and [`rgb10a2`] colours
//!   (alpha = stored, so sparse colours renormalise over stored corners
//!   like `ChannelGrid::sample`); [`GpuField::offsets`]`[3]` is the field's
//!   first slice;
//! - `density` (`array<f32>`): raw density per grid point again, in the
//!   bricked order of [`bricked_index`], for masks (which weight each
//!   corner's bit by its own density);
//! - `colors` (`array<u32>`): SH appearance: see [`sh_colors`] (kind in
//!   `GpuField::res[3]`); nothing for RGB fields;
//! - `aux` (`array<u32>`): per field the empty-space grid (one byte per
//!   skip cell, see [`skip_grid`]);
//! - `bitmaps` (`array<u32>`): the packed words of every mask (bit `i` is bit
//!   `i & 31` of word `offset + i >> 5`).

use crate::field::macro_grid::EMPTY_SIGMA;
use crate::field::{Activation, Appearance, Bitmap, ChannelGrid, DensityGrid, Field, Layout};
use crate::render::{Mask, Scene};
use crate::{ensure, Result};
use bytemuck::{Pod, Zeroable};
use glam::{Affine3A, Mat4, Vec3};
use rayon::prelude::*;
use std::sync::Arc;

/// Layers one frame can draw (the shader's per-ray scratch size).
pub const MAX_LAYERS: usize = 16;
/// Grid cells per skip cell along each axis (a skip cell covers grid
/// points `[c·SKIP_BLOCK, c·SKIP_BLOCK + SKIP_BLOCK]`).
pub const SKIP_BLOCK: usize = 2;
/// Largest empty radius stored (in skip cells).
pub const SKIP_MAX: u8 = 31;

/// Layer flags (`GpuLayer::info[3]`).
pub const LAYER_COLOR_EDIT: u32 = 1;
/// Editor overlay: tint this layer (the selected object).
pub const LAYER_HIGHLIGHT: u32 = 2;
/// Editor overlay: dim this layer.
pub const LAYER_DIM: u32 = 4;

pub const MASK_ALL: u32 = 0;
pub const MASK_KEEP: u32 = 1;
pub const MASK_REMOVE: u32 = 2;

/// Grid points per brick edge: per-point arrays are stored in 4³ bricks.
pub const BRICK: usize = 4;

/// Bricks per axis for a grid of `res` points.
pub fn brick_dims(res: [usize; 3]) -> [usize; 3] {
    res.map(|n| n.div_ceil(BRICK))
}

/// Where grid point (x, y, z) sits in a bricked per-point array: bricks of
/// 4³ = 64 points one after the other (x fastest, then y, then z), points
/// in a brick in the same order. A cell's 8 corners and its neighbours'
/// then share cache lines and pages; with x-fastest rows a step in z is a
/// whole slice away. (On lavapipe, with x-fastest rows, confining the
/// colour loads to an L2-sized window made frames 20 % faster, and with
/// bricks it no longer changed them; whole-frame A/B runs were within this
/// machine's noise. The density and RGB colours now come from the atlas
/// textures; masks and SH colours still read these arrays.)
pub fn bricked_index(res: [usize; 3], x: usize, y: usize, z: usize) -> usize {
    let b = brick_dims(res);
    let brick = (z / BRICK * b[1] + y / BRICK) * b[0] + x / BRICK;
    brick * BRICK.pow(3) + ((z % BRICK) * BRICK + y % BRICK) * BRICK + x % BRICK
}

/// A per-point array in bricked order: `value(v)` for grid point v (linear
/// index, x fastest), `fill` for the padding of partial bricks.
fn bricked<T: Copy + Send + Sync>(res: [usize; 3], fill: T, value: impl Fn(usize) -> T + Sync) -> Vec<T> {
    let b = brick_dims(res);
    let per = BRICK.pow(3);
    (0..b[0] * b[1] * b[2] * per)
        .into_par_iter()
        .map(|i| {
            let (brick, w) = (i / per, i % per);
            let x = brick % b[0] * BRICK + w % BRICK;
            let y = brick / b[0] % b[1] * BRICK + w / BRICK % BRICK;
            let z = brick / (b[0] * b[1]) * BRICK + w / (BRICK * BRICK);
            if x < res[0] && y < res[1] && z < res[2] {
                value(x + res[0] * (y + res[1] * z))
            } else {
                fill
            }
        })
        .collect()
}

/// Per-view parameters (uniform).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct GpuView {
    /// Camera-to-world (OpenGL convention), column-major.
    pub c2w: [[f32; 4]; 4],
    /// World to clip space of the bevy camera (for the depth we write).
    pub clip_from_world: [[f32; 4]; 4],
    /// fx, fy, cx, cy in pixels of the march target.
    pub intrinsics: [f32; 4],
    /// Background colour (rgb).
    pub background: [f32; 4],
    /// step, min transmittance, 0, 0.
    pub march: [f32; 4],
    /// layer count, 0, 0, 0.
    pub counts: [u32; 4],
    /// 1 / the atlas textures' size in texels (xyz), 0.
    pub atlas: [f32; 4],
}

/// One layer (storage buffer, array).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct GpuLayer {
    /// World to field-local, column-major.
    pub to_local: [[f32; 4]; 4],
    /// field index, mask kind, mask word offset, flags.
    pub info: [u32; 4],
    /// tint rgb, hue (degrees).
    pub tint_hue: [f32; 4],
    /// saturation, brightness, 0, 0.
    pub sat_bright: [f32; 4],
    /// Local box outside which the layer has no density (the field's box,
    /// or a keep-mask's bounding box grown by a voxel).
    pub box_min: [f32; 4],
    pub box_max: [f32; 4],
    /// 1 + word offset of the highlight mask ([`Overlay::highlight_mask`]),
    /// 0 for none; 0, 0, 0.
    pub highlight: [u32; 4],
}

/// One field (storage buffer, array).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct GpuField {
    /// xyz; w = activation shift.
    pub bounds_min: [f32; 4],
    /// xyz; w = activation kind (0 relu, 1 softplus).
    pub bounds_max: [f32; 4],
    /// nx, ny, nz, colour kind ([`COLOR_SPARSE`] | [`COLOR_SH`]).
    pub res: [u32; 4],
    /// Offsets: density (f32), colours (u32), SH coefficients (u32), first
    /// atlas slice.
    pub offsets: [u32; 4],
    /// Skip grid dims xyz, offset (aux u32).
    pub skip: [u32; 4],
    /// World size of a skip cell, xyz.
    pub skip_cell: [f32; 4],
}

/// A field's grids in upload form (offsets relative to its own arrays).
#[derive(Clone, Debug)]
pub struct PackedField {
    /// Raw density, bricked ([`bricked_index`]).
    pub density: Vec<f32>,
    /// [`sh_colors`] (empty for RGB fields).
    pub colors: Vec<u32>,
    /// [`rgb10a2`] texels per grid point, x fastest (empty for SH fields).
    pub rgb: Vec<u32>,
    /// Skip grid bytes packed four per u32.
    pub aux: Vec<u32>,
    pub info: GpuField,
}

fn v4(v: Vec3, w: f32) -> [f32; 4] {
    [v.x, v.y, v.z, w]
}

pub fn affine_cols(a: &Affine3A) -> [[f32; 4]; 4] {
    Mat4::from(*a).to_cols_array_2d()
}

/// Empty-space grid: per skip cell, 0 if any of its grid points has
/// σ > [`EMPTY_SIGMA`] (so interpolated σ inside may exceed it), else the
/// Chebyshev distance in cells to the nearest such cell (capped at
/// [`SKIP_MAX`]): every cell within distance − 1 is empty too, so a ray can
/// jump out of that whole cube.
pub fn skip_grid(d: &DensityGrid) -> ([usize; 3], Vec<u8>) {
    let g = d.geom;
    let dims = g.res.map(|n| (n - 1).div_ceil(SKIP_BLOCK).max(1));
    let occupied: Vec<bool> = (0..dims[0] * dims[1] * dims[2])
        .into_par_iter()
        .map(|c| {
            let (cx, cy, cz) = (c % dims[0], (c / dims[0]) % dims[1], c / (dims[0] * dims[1]));
            let range = |cc: usize, a: usize| cc * SKIP_BLOCK..=((cc + 1) * SKIP_BLOCK).min(g.res[a] - 1);
            range(cz, 2).any(|z| range(cy, 1).any(|y| range(cx, 0).any(|x| d.sigma_at(g.index(x, y, z)) > EMPTY_SIGMA)))
        })
        .collect();
    (dims, chebyshev(&occupied, dims))
}

/// Chebyshev distance (capped at [`SKIP_MAX`]) from every cell to the
/// nearest occupied cell, by repeated 26-neighbour dilation done as three
/// separable 1D min passes per step.
fn chebyshev(occ: &[bool], dims: [usize; 3]) -> Vec<u8> {
    let mut dist: Vec<u8> = occ.iter().map(|&o| if o { 0 } else { SKIP_MAX }).collect();
    let mut front: Vec<bool> = occ.to_vec();
    for k in 1..SKIP_MAX {
        // front ← cells within L∞ distance 1 of the front (cube dilation).
        for axis in 0..3 {
            let stride = [1, dims[0], dims[0] * dims[1]][axis];
            let prev = front.clone();
            front.par_iter_mut().enumerate().for_each(|(c, f)| {
                if *f {
                    return;
                }
                let coord = [c % dims[0], (c / dims[0]) % dims[1], c / (dims[0] * dims[1])][axis];
                *f = (coord > 0 && prev[c - stride]) || (coord + 1 < dims[axis] && prev[c + stride]);
            });
        }
        let mut any_new = false;
        for (d, &f) in dist.iter_mut().zip(&front) {
            if f && *d == SKIP_MAX {
                *d = k;
                any_new = true;
            }
        }
        if !any_new {
            break;
        }
    }
    dist
}

/// A stored RGB colour as an `Rgb10a2Unorm` texel: 10-bit unorm r, g, b
/// (bits 0..10, 10..20, 20..30) and alpha 1 (bits 30..32 = 3); points
/// the appearance does not store are 0 (alpha 0). The trilinear filter
/// then yields Σ w·rgb and Σ w over the stored corners, whose ratio is the
/// sparse renormalisation of `ChannelGrid::sample`. 10 bits per channel
/// keep colours within 5e-4 of their f16 values. Values outside [0, 1] are
/// clamped before interpolation where the CPU clamps after: the same for
/// RGB grids in range (demo scenes, imports); trained fields use SH.
pub fn rgb10a2(c: [f32; 3]) -> u32 {
    let q = |v: f32| (v.clamp(0.0, 1.0) * 1023.0).round() as u32;
    q(c[0]) | q(c[1]) << 10 | q(c[2]) << 20 | 3 << 30
}

fn sparse_bit(g: &ChannelGrid) -> u32 {
    match g.layout {
        Layout::Dense => 0,
        Layout::Sparse(_) => COLOR_SPARSE,
    }
}

fn rgb_texels(g: &ChannelGrid) -> Vec<u32> {
    let ch = g.channels;
    (0..g.geom.len())
        .into_par_iter()
        .map(|v| {
            slot_of(g, v).map_or(0, |s| {
                let c = &g.data[s * ch..s * ch + 3];
                rgb10a2([c[0].to_f32(), c[1].to_f32(), c[2].to_f32()])
            })
        })
        .collect()
}

/// Colour kind bits (`GpuField::res[3]`): the appearance is sparse.
pub const COLOR_SPARSE: u32 = 1;
/// Colour kind bits: degree-2 spherical harmonics (else RGB).
pub const COLOR_SH: u32 = 2;
/// u32 words per SH grid point: 27 f16 coefficients and one pad.
pub const SH_WORDS: usize = 14;

fn slot_of(g: &ChannelGrid, v: usize) -> Option<usize> {
    match &g.layout {
        Layout::Dense => Some(v),
        Layout::Sparse(ix) => ix.slot(v),
    }
}

/// The [`SH_WORDS`] words of f16 pairs of one stored point's 27
/// coefficients (`[r0..r8, g0..g8, b0..b8]`, as `ChannelGrid`).
fn sh_words(c: &[half::f16]) -> [u32; SH_WORDS] {
    std::array::from_fn(|w| {
        let lo = c[2 * w].to_bits() as u32;
        let hi = c.get(2 * w + 1).map_or(0, |h| h.to_bits() as u32);
        lo | hi << 16
    })
}

/// SH appearance for the shader: for sparse grids a bricked table with
/// slot + 1 per grid point (0 = not stored), then the [`sh_words`] of each
/// stored point; for dense grids the [`sh_words`] of every grid point in
/// bricked order. Returns the words and where the coefficients start.
fn sh_colors(g: &ChannelGrid) -> Result<(Vec<u32>, u32)> {
    ensure!(
        g.channels == 27,
        "SH appearance with {} channels (expected 27)",
        g.channels
    );
    let res = g.geom.res;
    let points = brick_dims(res).iter().product::<usize>() * BRICK.pow(3);
    let (table, records) = match &g.layout {
        Layout::Dense => (0, points),
        Layout::Sparse(_) => (points, g.slots()),
    };
    ensure!(
        table + records * SH_WORDS < u32::MAX as usize,
        "the SH appearance is too large for the GPU view"
    );
    let out: Vec<u32> = match &g.layout {
        Layout::Dense => bricked(res, [0; SH_WORDS], |v| sh_words(&g.data[v * 27..v * 27 + 27]))
            .into_iter()
            .flatten()
            .collect(),
        Layout::Sparse(_) => {
            let mut out = bricked(res, 0, |v| slot_of(g, v).map_or(0, |s| s as u32 + 1));
            out.extend(g.data.chunks(27).flat_map(sh_words));
            out
        }
    };
    Ok((out, table as u32))
}

/// Packs a field for upload: RGB or SH appearance (dense or sparse); VM +
/// MLP appearance is baked into sparse SH first ([`crate::field::bake`]).
pub fn pack_field(field: &Field) -> Result<PackedField> {
    let geom = field.geom();
    let (colors, rgb, color_kind, sh_start) = match &field.appearance {
        Appearance::Rgb(g) => {
            ensure!(g.channels >= 3, "RGB appearance with {} channels", g.channels);
            (Vec::new(), rgb_texels(g), sparse_bit(g), 0)
        }
        Appearance::Sh2(g) => {
            let (c, start) = sh_colors(g)?;
            (c, Vec::new(), sparse_bit(g) | COLOR_SH, start)
        }
        // The ray marcher has no MLP: the network is baked into SH once,
        // when the field is first uploaded.
        Appearance::Vm { .. } => {
            let baked = field
                .sh_baked()?
                .ok_or_else(|| crate::Error::invalid("VM appearance without an SH bake"))?;
            return pack_field(&baked);
        }
    };
    let (dims, skip) = skip_grid(&field.density);
    let aux: Vec<u32> = skip
        .chunks(4)
        .map(|c| c.iter().enumerate().fold(0u32, |a, (i, &b)| a | (b as u32) << (8 * i)))
        .collect();
    let (activation, shift) = match field.density.activation {
        Activation::Relu => (0.0, 0.0),
        Activation::Softplus { shift } => (1.0, shift),
    };
    let b = geom.bounds;
    let cell = geom.spacing() * SKIP_BLOCK as f32;
    Ok(PackedField {
        density: bricked(geom.res, 0.0, |v| field.density.raw[v]),
        colors,
        rgb,
        aux,
        info: GpuField {
            bounds_min: v4(b.min, shift),
            bounds_max: v4(b.max, activation),
            res: [geom.res[0] as u32, geom.res[1] as u32, geom.res[2] as u32, color_kind],
            offsets: [0, 0, sh_start, 0],
            skip: [dims[0] as u32, dims[1] as u32, dims[2] as u32, 0],
            skip_cell: v4(cell, 0.0),
        },
    })
}

/// The fields' grids stacked along z in two 3D textures (x fastest, then
/// y, then z), each field from its [`GpuField::offsets`]`[3]`th slice;
/// textures as wide and high as the largest field.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Atlas {
    pub size: [usize; 3],
    /// Raw density per texel.
    pub density: Vec<f32>,
    /// [`rgb10a2`] per texel (0 for SH fields and padding).
    pub rgb: Vec<u32>,
    /// Each field's first slice.
    pub z0: Vec<usize>,
}

/// Stacks the fields' `(raw density, RGB texels (may be empty), res)`
/// into an [`Atlas`] of at most `max_side` texels per side (the device's
/// 3D texture limit).
pub fn atlas(fields: &[(&[f32], &[u32], [usize; 3])], max_side: usize) -> Result<Atlas> {
    let w = fields.iter().map(|f| f.2[0]).max().unwrap_or(1);
    let h = fields.iter().map(|f| f.2[1]).max().unwrap_or(1);
    let z0: Vec<usize> = fields
        .iter()
        .scan(0, |z, f| {
            let at = *z;
            *z += f.2[2];
            Some(at)
        })
        .collect();
    let d = fields.iter().map(|f| f.2[2]).sum::<usize>().max(1);
    ensure!(
        w <= max_side && h <= max_side && d <= max_side,
        "the fields need a {w}x{h}x{d} texture, more than this GPU's 3D textures hold ({max_side} per side)"
    );
    let mut density = vec![0.0; w * h * d];
    let mut texels = vec![0; w * h * d];
    for ((dens, rgb, r), &first) in fields.iter().zip(&z0) {
        // One row of the field (x fastest) at a time.
        for z in 0..r[2] {
            for y in 0..r[1] {
                let src = r[0] * (y + r[1] * z);
                let dst = w * (y + h * (first + z));
                density[dst..dst + r[0]].copy_from_slice(&dens[src..src + r[0]]);
                if !rgb.is_empty() {
                    texels[dst..dst + r[0]].copy_from_slice(&rgb[src..src + r[0]]);
                }
            }
        }
    }
    Ok(Atlas {
        size: [w, h, d],
        density,
        rgb: texels,
        z0,
    })
}

/// Concatenates packed fields; returns the field infos with absolute
/// offsets (the atlas slice is set by the caller, from [`atlas`]).
pub fn concat_fields(fields: &[&PackedField]) -> (Vec<GpuField>, Vec<f32>, Vec<u32>, Vec<u32>) {
    let mut infos = Vec::new();
    let (mut density, mut colors, mut aux) = (Vec::new(), Vec::new(), Vec::new());
    for p in fields {
        let mut info = p.info;
        let a = aux.len() as u32;
        let c = colors.len() as u32;
        info.offsets = [density.len() as u32, c, c + p.info.offsets[2], 0];
        info.skip[3] = a;
        density.extend_from_slice(&p.density);
        colors.extend_from_slice(&p.colors);
        aux.extend_from_slice(&p.aux);
        infos.push(info);
    }
    (infos, density, colors, aux)
}

/// The local box outside which a keep-masked layer is empty: the mask's
/// voxel bounding box grown by one voxel (trilinear weights reach that far),
/// or `None` for an empty mask.
pub fn keep_box(field: &Field, bits: &Bitmap) -> Option<(Vec3, Vec3)> {
    let (lo, hi) = bits.bounding_box()?;
    let g = field.geom();
    let lo = lo.map(|v| v.saturating_sub(1));
    let hi = [0, 1, 2].map(|a| (hi[a] + 1).min(g.res[a] - 1));
    Some((g.point(lo[0], lo[1], lo[2]), g.point(hi[0], hi[1], hi[2])))
}

/// Distinct fields of a scene, in order of first use.
pub fn distinct_fields(scene: &Scene) -> Vec<Arc<Field>> {
    let mut out: Vec<Arc<Field>> = Vec::new();
    for l in &scene.layers {
        if !out.iter().any(|f| Arc::ptr_eq(f, &l.field)) {
            out.push(l.field.clone());
        }
    }
    out
}

/// Distinct mask bitmaps of a scene, in order of first use.
pub fn distinct_bitmaps(scene: &Scene, overlay: &[Overlay]) -> Vec<Arc<Bitmap>> {
    let masks = scene.layers.iter().filter_map(|l| match &l.mask {
        Mask::Keep(b) | Mask::Remove(b) => Some(b),
        Mask::All => None,
    });
    let highlights = overlay.iter().filter_map(|o| o.highlight_mask.as_ref());
    let mut out: Vec<Arc<Bitmap>> = Vec::new();
    for b in masks.chain(highlights) {
        if !out.iter().any(|x| Arc::ptr_eq(x, b)) {
            out.push(b.clone());
        }
    }
    out
}

/// Word offsets (u32 units) of each bitmap in the concatenated buffer, and
/// the total word count.
pub fn bitmap_offsets(bitmaps: &[Arc<Bitmap>]) -> (Vec<u32>, usize) {
    let mut offs = Vec::with_capacity(bitmaps.len());
    let mut total = 0usize;
    for b in bitmaps {
        offs.push(total as u32);
        total += b.words().len() * 2;
    }
    (offs, total)
}

/// The bitmap's words as little-endian u32 pairs.
pub fn bitmap_u32(b: &Bitmap) -> Vec<u32> {
    b.words().iter().flat_map(|&w| [w as u32, (w >> 32) as u32]).collect()
}

/// Editor overlay per layer.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Overlay {
    /// Tint the layer (the selected object); only its part inside
    /// `highlight_mask` when there is one.
    pub highlight: bool,
    /// Dim the layer; only its part outside `highlight_mask` when there is
    /// one.
    pub dim: bool,
    /// The selected object when it sits in place inside this layer: the
    /// shader splits the colour by the object's share of the density, which
    /// draws the same image as splitting the object out into a layer of its
    /// own, for the price of one layer.
    pub highlight_mask: Option<Arc<Bitmap>>,
}

/// Packs the layers: `fields` and `bitmaps` are the lists from
/// [`distinct_fields`] / [`distinct_bitmaps`], `bitmap_offs` their word
/// offsets. Layers whose keep mask is empty are left out (they draw
/// nothing).
pub fn pack_layers(
    scene: &Scene,
    fields: &[Arc<Field>],
    bitmaps: &[Arc<Bitmap>],
    bitmap_offs: &[u32],
    overlay: &[Overlay],
) -> Result<Vec<GpuLayer>> {
    // Word offset of a layer's bitmap (`what`: "mask", "highlight mask").
    let offset_of = |i: usize, what: &str, bits: &Arc<Bitmap>, field: &Field| -> Result<u32> {
        ensure!(
            bits.res() == field.res(),
            "layer {i}: {what} resolution {:?} differs from the field's {:?}",
            bits.res(),
            field.res()
        );
        let k = bitmaps
            .iter()
            .position(|x| Arc::ptr_eq(x, bits))
            .ok_or_else(|| crate::Error::invalid(format!("layer {i}: its {what} was not uploaded")))?;
        Ok(bitmap_offs[k])
    };
    let no_overlay = Overlay::default();
    let mut out = Vec::with_capacity(scene.layers.len());
    for (i, l) in scene.layers.iter().enumerate() {
        let det = l.to_world.matrix3.determinant();
        ensure!(
            det.is_finite() && det.abs() > 1e-12,
            "layer {i}: its transform is not invertible"
        );
        let slot = fields
            .iter()
            .position(|f| Arc::ptr_eq(f, &l.field))
            .ok_or_else(|| crate::Error::invalid(format!("layer {i}: its field was not uploaded")))?;
        let b = l.field.bounds();
        let (mut lo, mut hi) = (b.min, b.max);
        let (kind, offset) = match &l.mask {
            Mask::All => (MASK_ALL, 0),
            Mask::Keep(bits) | Mask::Remove(bits) => {
                let offset = offset_of(i, "mask", bits, &l.field)?;
                if matches!(l.mask, Mask::Keep(_)) {
                    let Some((a, z)) = keep_box(&l.field, bits) else {
                        continue;
                    };
                    (lo, hi) = (a, z);
                    (MASK_KEEP, offset)
                } else {
                    (MASK_REMOVE, offset)
                }
            }
        };
        let edit = l.color_edit.filter(|e| !e.is_identity());
        if let Some(e) = &edit {
            e.validate()?;
        }
        let e = edit.unwrap_or_default();
        let ov = overlay.get(i).unwrap_or(&no_overlay);
        let highlight = match &ov.highlight_mask {
            None => 0,
            Some(h) => offset_of(i, "highlight mask", h, &l.field)? + 1,
        };
        let flag = |on: bool, bit: u32| if on { bit } else { 0 };
        let flags =
            flag(edit.is_some(), LAYER_COLOR_EDIT) | flag(ov.highlight, LAYER_HIGHLIGHT) | flag(ov.dim, LAYER_DIM);
        out.push(GpuLayer {
            to_local: affine_cols(&l.to_world.inverse()),
            info: [slot as u32, kind, offset, flags],
            tint_hue: [e.tint[0], e.tint[1], e.tint[2], e.hue],
            sat_bright: [e.saturation, e.brightness, 0.0, 0.0],
            box_min: v4(lo, 0.0),
            box_max: v4(hi, 0.0),
            highlight: [highlight, 0, 0, 0],
        });
    }
    ensure!(
        out.len() <= MAX_LAYERS,
        "the GPU view draws at most {MAX_LAYERS} layers at once, this scene has {}",
        out.len()
    );
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{Aabb, FieldBuilder, GridGeom, RankIndex};
    use crate::render::Layer;
    use half::f16;

    fn ball() -> Field {
        FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::ONE), [17, 17, 17]).build(
            |p| if p.length() < 0.3 { 5.0 } else { -1.0 },
            |p| p * 0.5 + 0.5,
            None,
        )
    }

    #[test]
    fn sh_coefficients_pack_as_f16_pairs_behind_a_slot_table() {
        let f = ball();
        let g = f.geom();
        let bits = Bitmap::from_fn(g.res, |i| i % 5 == 0);
        let ix = Arc::new(RankIndex::new(bits.clone()));
        let data: Vec<f16> = (0..ix.count() * 27).map(|k| f16::from_f32(k as f32 * 0.25)).collect();
        let mut f2 = f.clone();
        f2.appearance = Appearance::Sh2(ChannelGrid::sparse(g, 27, ix.clone(), data.clone()));
        let p = pack_field(&f2).unwrap();
        assert_eq!(p.info.res[3], COLOR_SH | COLOR_SPARSE);
        let start = p.info.offsets[2] as usize;
        // 17 points = 5 bricks per axis.
        assert_eq!(start, 125 * 64);
        // The shader's lookup: table entry = slot + 1, then half k of the slot.
        for v in [0, 5, 7, 100, g.len() - 1] {
            let slot = (p.colors[at(g, v)] as usize).checked_sub(1);
            assert_eq!(slot, ix.slot(v), "voxel {v}");
            let Some(s) = slot else { continue };
            for k in [0, 8, 9, 26] {
                let w = p.colors[start + s * SH_WORDS + k / 2];
                let h = if k % 2 == 0 { w & 0xffff } else { w >> 16 };
                assert_eq!(h as u16, data[s * 27 + k].to_bits());
            }
        }
        // Offsets stay right after concatenation behind another field.
        let rgb = pack_field(&f).unwrap();
        let (infos, _, colors, _) = concat_fields(&[&rgb, &p]);
        assert_eq!(infos[1].offsets[1] as usize, rgb.colors.len());
        assert_eq!(infos[1].offsets[2] as usize, rgb.colors.len() + start);
        assert_eq!(colors.len(), rgb.colors.len() + p.colors.len());
    }

    /// Bricked index of linear grid point v.
    fn at(g: GridGeom, v: usize) -> usize {
        let r = g.res;
        bricked_index(r, v % r[0], v / r[0] % r[1], v / (r[0] * r[1]))
    }

    #[test]
    fn bricked_order_is_a_bijection_with_the_shaders_neighbour_steps() {
        let res = [9, 6, 5];
        let n = res.iter().product::<usize>();
        let g = GridGeom::new(Aabb::new(Vec3::ZERO, Vec3::ONE), res);
        let b = brick_dims(res);
        assert_eq!(b, [3, 2, 2]);
        let mut seen = vec![false; b.iter().product::<usize>() * 64];
        for v in 0..n {
            let i = at(g, v);
            assert!(!seen[i], "two points at {i}");
            seen[i] = true;
        }
        // `bricked` puts value(v) at v's bricked index, `fill` elsewhere.
        let arr = bricked(res, usize::MAX, |v| v);
        assert_eq!(arr.len(), seen.len());
        for (i, &v) in arr.iter().enumerate() {
            assert_eq!(v != usize::MAX, seen[i]);
            if v != usize::MAX {
                assert_eq!(at(g, v), i);
            }
        }
        // raymarch.wgsl `cell_of`: the +x/+y/+z neighbour is 1/4/16 on,
        // or 61, 64·bx − 12, 64·bx·by − 48 on across a brick face.
        for z in 0..res[2] - 1 {
            for y in 0..res[1] - 1 {
                for x in 0..res[0] - 1 {
                    let i = bricked_index(res, x, y, z);
                    let step = |w: usize, inside: usize, across: usize| if w % 4 == 3 { across } else { inside };
                    assert_eq!(bricked_index(res, x + 1, y, z) - i, step(x, 1, 61));
                    assert_eq!(bricked_index(res, x, y + 1, z) - i, step(y, 4, 64 * b[0] - 12));
                    assert_eq!(bricked_index(res, x, y, z + 1) - i, step(z, 16, 64 * b[0] * b[1] - 48));
                }
            }
        }
    }

    #[test]
    fn skip_grid_holds_chebyshev_distances_to_density() {
        let f = ball();
        let (dims, d) = skip_grid(&f.density);
        assert_eq!(dims, [8, 8, 8]);
        let at = |x: usize, y: usize, z: usize| d[x + 8 * (y + 8 * z)];
        // The ball (radius 0.3 = 2.4 voxels) sits around grid point 8 =
        // the corner shared by cells 3 and 4.
        assert_eq!(at(3, 3, 3), 0);
        assert_eq!(at(4, 4, 4), 0);
        // Brute force check of every cell.
        let occ: Vec<(i32, i32, i32)> = (0..512)
            .filter(|&c| d[c] == 0)
            .map(|c| ((c % 8) as i32, ((c / 8) % 8) as i32, (c / 64) as i32))
            .collect();
        assert!(!occ.is_empty());
        for (c, &got) in d.iter().enumerate() {
            let p = ((c % 8) as i32, ((c / 8) % 8) as i32, (c / 64) as i32);
            let want = occ
                .iter()
                .map(|q| (p.0 - q.0).abs().max((p.1 - q.1).abs()).max((p.2 - q.2).abs()))
                .min()
                .unwrap();
            assert_eq!(got as i32, want.min(SKIP_MAX as i32), "cell {p:?}");
        }
        // Cells marked empty really have no density at their grid points.
        let g = f.geom();
        for c in (0..512).filter(|&c| d[c] > 0) {
            let (cx, cy, cz) = (c % 8, (c / 8) % 8, c / 64);
            for z in 2 * cz..=2 * cz + 2 {
                for y in 2 * cy..=2 * cy + 2 {
                    for x in 2 * cx..=2 * cx + 2 {
                        assert!(f.density.sigma_at(g.index(x, y, z)) <= EMPTY_SIGMA);
                    }
                }
            }
        }
    }

    #[test]
    fn colours_cover_every_grid_point_with_a_stored_flag() {
        let f = ball();
        let p = pack_field(&f).unwrap();
        assert_eq!(p.rgb.len(), 17 * 17 * 17);
        assert!(p.colors.is_empty());
        // 17 points = 5 bricks of 4 per axis.
        assert_eq!(p.density.len(), 125 * 64);
        let g = GridGeom::new(f.bounds(), [17; 3]);
        let i = g.index(16, 0, 8);
        let want = g.point_of(i) * 0.5 + 0.5;
        let r = (p.rgb[i] & 1023) as f32 / 1023.0;
        assert!((r - want.x).abs() < 1e-3);
        assert_eq!(p.rgb[i] >> 30, 3);
        assert_eq!(p.density[at(g, i)], f.density.raw[i]);
        assert_eq!(p.info.res, [17, 17, 17, 0]);
        // Sparse appearance: unstored points carry flag 0.
        let bits = Bitmap::from_fn(g.res, |i| i % 7 == 0);
        let ix = Arc::new(RankIndex::new(bits.clone()));
        let data: Vec<f16> = bits.ones().flat_map(|_| [f16::ONE, f16::ZERO, f16::ONE]).collect();
        let mut f2 = f.clone();
        f2.appearance = Appearance::Rgb(ChannelGrid::sparse(g, 3, ix, data));
        let p = pack_field(&f2).unwrap();
        assert_eq!(p.info.res[3], 1);
        for v in 0..g.len() {
            // Stored points have alpha 1, the others are 0 entirely.
            assert_eq!(p.rgb[v] >> 30 == 3, v % 7 == 0, "voxel {v}");
            assert_eq!(p.rgb[v] == 0, v % 7 != 0, "voxel {v}");
        }
        assert_eq!(p.rgb[0], rgb10a2([1.0, 0.0, 1.0]));
    }

    #[test]
    fn atlas_stacks_fields_along_z_and_refuses_oversized_ones() {
        let small: Vec<f32> = (0..2 * 3 * 2).map(|v| v as f32).collect();
        let big: Vec<f32> = (0..4 * 2 * 3).map(|v| 100.0 + v as f32).collect();
        let rgb: Vec<u32> = (0..4 * 2 * 3).map(|v| v as u32 + 1).collect();
        let a = atlas(&[(&small, &[], [2, 3, 2]), (&big, &rgb, [4, 2, 3])], 16).unwrap();
        assert_eq!(a.size, [4, 3, 5]);
        assert_eq!(a.z0, vec![0, 2]);
        let texel = |x: usize, y: usize, z: usize| x + 4 * (y + 3 * z);
        // Field 0's point (1, 2, 1) and field 1's point (3, 1, 2).
        assert_eq!(a.density[texel(1, 2, 1)], (1 + 2 * (2 + 3)) as f32);
        assert_eq!(a.rgb[texel(1, 2, 1)], 0);
        let v = 3 + 4 * (1 + 2 * 2);
        assert_eq!(a.density[texel(3, 1, 2 + 2)], big[v]);
        assert_eq!(a.rgb[texel(3, 1, 2 + 2)], rgb[v]);
        // Padding beside the narrower field stays empty.
        assert_eq!(a.density[texel(3, 0, 0)], 0.0);
        let e = atlas(&[(&big, &rgb, [4, 2, 3]), (&big, &rgb, [4, 2, 3])], 5).unwrap_err();
        assert!(e.to_string().contains("4x2x6"), "{e}");
        // No fields: one texel, to bind something.
        assert_eq!(atlas(&[], 16).unwrap().size, [1, 1, 1]);
    }

    #[test]
    fn concatenation_offsets_fields() {
        let f = ball();
        let p = pack_field(&f).unwrap();
        let (infos, density, colors, aux) = concat_fields(&[&p, &p]);
        assert_eq!(density.len(), 2 * p.density.len());
        assert_eq!(infos[1].offsets[0] as usize, p.density.len());
        assert_eq!(infos[1].offsets[1] as usize, p.colors.len());
        assert_eq!(infos[1].skip[3] as usize, p.aux.len());
        assert_eq!(colors.len(), 2 * p.colors.len());
        assert_eq!(aux.len(), 2 * p.aux.len());
    }

    #[test]
    fn bitmap_words_split_little_endian() {
        let mut b = Bitmap::new([8, 8, 2]);
        for i in [0usize, 31, 32, 63, 64, 127] {
            b.set(i, true);
        }
        let w = bitmap_u32(&b);
        assert_eq!(w.len(), 4);
        for i in 0..128usize {
            let bit = w[i >> 5] >> (i & 31) & 1 == 1;
            assert_eq!(bit, b.get(i), "bit {i}");
        }
    }

    #[test]
    fn layers_share_fields_and_empty_keep_masks_drop() {
        let f = Arc::new(ball());
        let mut bits = Bitmap::new(f.res());
        let g = f.geom();
        bits.set(g.index(8, 8, 8), true);
        let bits = Arc::new(bits);
        let empty = Arc::new(Bitmap::new(f.res()));
        let mut moved = Layer::new(f.clone());
        moved.mask = Mask::Keep(bits.clone());
        moved.to_world = Affine3A::from_translation(Vec3::X);
        let mut removed = Layer::new(f.clone());
        removed.mask = Mask::Remove(bits.clone());
        let mut nothing = Layer::new(f.clone());
        nothing.mask = Mask::Keep(empty);
        let scene = Scene::new(vec![removed, moved, nothing]);
        let fields = distinct_fields(&scene);
        assert_eq!(fields.len(), 1);
        let bms = distinct_bitmaps(&scene, &[]);
        assert_eq!(bms.len(), 2);
        let (offs, total) = bitmap_offsets(&bms);
        assert_eq!(offs, vec![0, (bits.words().len() * 2) as u32]);
        assert_eq!(total, offs[1] as usize * 2);
        let layers = pack_layers(&scene, &fields, &bms, &offs, &[]).unwrap();
        assert_eq!(layers.len(), 2);
        assert_eq!(layers[0].info[..3], [0, MASK_REMOVE, 0]);
        assert_eq!(layers[1].info[1], MASK_KEEP);
        // Keep box: voxel 8 ± 1 → [-0.125, 0.125]³ at spacing 0.125.
        assert!((layers[1].box_min[0] + 0.125).abs() < 1e-6);
        assert!((layers[1].box_max[2] - 0.125).abs() < 1e-6);
        let m = Mat4::from_cols_array_2d(&layers[1].to_local);
        assert!((m.transform_point3(Vec3::X) - Vec3::ZERO).length() < 1e-6);
    }
}
