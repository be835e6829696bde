//! CPU-side packing of a [`Scene`] into the flat arrays and `#[repr(C)]`
//! structs that `shaders/raymarch.wgsl` reads. Plain functions over plain
//! data (no bevy types), so they are unit-tested without a GPU.
//!
//! Layout contract with the shader (every struct is made of 16-byte vectors
//! so that WGSL's uniform/storage layout rules equal `#[repr(C)]`):
//! - the pool textures (3D, sampled with the GPU's trilinear filter): the
//!   occupied bricks of every field ([`super::pool`]): raw density (f16),
//!   [`rgb10a2`] colours (alpha = stored, so sparse colours renormalise over
//!   stored corners like `ChannelGrid::sample`) and SH coefficients in
//!   [`SH_TEXTURES`] RGBA f16 textures ([`sh_texel`]); nothing is stored for
//!   empty space;
//! - `aux` (`array<u32>`): per field its empty-space grid (one byte per
//!   skip cell, see [`skip_grid`]) and its brick indirection grid;
//!   [`GpuField::skip`]`[3]` and [`GpuField::offsets`]`[0]` say where;
//! - `bitmaps` (`array<u32>`): the words of every mask, in its field's
//!   brick order ([`super::pool::brick_bits`]).
use super::pool::PoolPlan;
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
/// The layer's SH colours come from the view's bake ([`mark_baked`]).
pub const LAYER_BAKED: u32 = 8;

pub const MASK_ALL: u32 = 0;
pub const MASK_KEEP: u32 = 1;
pub const MASK_REMOVE: u32 = 2;

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
    /// step, min transmittance, step kind (0: cells, 1: world), 0.
    pub march: [f32; 4],
    /// layer count, 0, 0, 0.
    pub counts: [u32; 4],
    /// 1 / the pool textures' size in texels (xyz), 0.
    pub atlas: [f32; 4],
    /// The pool's bricks per axis (xyz), 0.
    pub pool: [u32; 4],
    /// [`ndc_params`]: 1 (NDC on), near, x and y scales; zeros when off.
    pub ndc: [f32; 4],
}

/// The view uniform's NDC parameters: 1 (on), near, 2f/W, 2f/H.
pub fn ndc_params(ndc: Option<&crate::camera::Ndc>) -> [f32; 4] {
    ndc.map_or([0.0; 4], |n| {
        let (sx, sy) = n.scale();
        [1.0, n.near, sx, sy]
    })
}

/// The SH bake's parameters for one view (uniform, shaders/sh_bake.wgsl).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct GpuBake {
    /// The pool's bricks per axis (xyz), pool slots to bake.
    pub pool: [u32; 4],
    /// [`ndc_params`] of an NDC scene: directions are then those of the
    /// NDC rays through each texel.
    pub ndc: [f32; 4],
    /// Per field: the camera in the field's frame; w = 1 where baked.
    pub cams: [[f32; 4]; MAX_LAYERS],
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
    /// Grid points per axis at the level of detail shown (the field's
    /// resolution, or every stride-th point: [`super::pool`]), colour kind
    /// ([`COLOR_SPARSE`] | [`COLOR_SH`]). `bounds_max` is then the last
    /// point shown.
    pub res: [u32; 4],
    /// Word offset of the brick slot grid in `aux` (field-local slot + 1
    /// per brick, 0 when empty: masks), first pool slot, first z slice of
    /// the field's bricks in the [`Indirection`] texture, 0.
    pub offsets: [u32; 4],
    /// Skip grid dims xyz, offset (aux u32).
    pub skip: [u32; 4],
    /// World size of a skip cell, xyz.
    pub skip_cell: [f32; 4],
}

/// What the GPU view keeps of a field besides its bricks: its empty-space
/// grid and its record (offsets and level of detail are set when the
/// scene's fields are concatenated, [`concat_fields`]).
#[derive(Clone, Debug)]
pub struct PackedField {
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

/// Colour kind bits (`GpuField::res[3]`): the appearance is sparse.
pub const COLOR_SPARSE: u32 = 1;
/// Colour kind bits: degree-2 spherical harmonics (else RGB).
pub const COLOR_SH: u32 = 2;
/// RGBA f16 textures holding a grid point's 27 SH coefficients and its
/// stored flag.
pub const SH_TEXTURES: usize = 7;
/// f16 1.0: the stored flag of an SH texel.
const F16_ONE: u16 = 0x3c00;

fn slot_of(g: &ChannelGrid, v: usize) -> Option<usize> {
    match &g.layout {
        Layout::Dense => Some(v),
        Layout::Sparse(ix) => ix.slot(v),
    }
}

/// Texel of SH texture `t` for grid point `v`: f16 channels `4t..4t + 4`
/// of the point's `[r0..r8, g0..g8, b0..b8, stored]` (coefficients in
/// `ChannelGrid` order, stored = 1.0); all zero where the appearance
/// stores nothing. The filter then yields Σ w·coefficient and, in channel
/// 27, Σ w over the stored corners, the sparse renormalisation.
pub fn sh_texel(g: &ChannelGrid, v: usize, t: usize) -> [u16; 4] {
    let Some(s) = slot_of(g, v) else { return [0; 4] };
    let c = &g.data[s * 27..s * 27 + 27];
    std::array::from_fn(|k| match 4 * t + k {
        27 => F16_ONE,
        i => c[i].to_bits(),
    })
}

/// The [`rgb10a2`] texel of grid point `v` (0 where nothing is stored).
pub fn rgb_texel(g: &ChannelGrid, v: usize) -> u32 {
    slot_of(g, v).map_or(0, |s| {
        let c = &g.data[s * g.channels..s * g.channels + 3];
        rgb10a2([c[0].to_f32(), c[1].to_f32(), c[2].to_f32()])
    })
}

/// Raw density as an f16 texel, clamped to f16's finite range (a raw
/// value far below any activation's threshold stays far below it).
pub fn density_texel(raw: f32) -> u16 {
    half::f16::from_f32(raw.clamp(-65504.0, 65504.0)).to_bits()
}

/// The field the GPU view draws: VM + MLP appearance baked into SH once
/// ([`crate::field::bake`]; the ray marcher has no MLP), others as they are.
pub fn drawn_field(field: &Arc<Field>) -> Result<Arc<Field>> {
    Ok(field.sh_baked()?.unwrap_or_else(|| field.clone()))
}

/// Packs what the GPU view keeps of a field besides its bricks (see
/// [`PackedField`]); `field` is a [`drawn_field`] (RGB or SH appearance).
pub fn pack_field(field: &Field) -> Result<PackedField> {
    let color_kind = match &field.appearance {
        Appearance::Rgb(g) => {
            ensure!(g.channels >= 3, "RGB appearance with {} channels", g.channels);
            sparse_bit(g)
        }
        Appearance::Sh2(g) => {
            ensure!(
                g.channels == 27,
                "SH appearance with {} channels (expected 27)",
                g.channels
            );
            sparse_bit(g) | COLOR_SH
        }
        Appearance::Vm { .. } => {
            return Err(crate::Error::invalid(
                "VM appearance must be baked into SH before it is drawn",
            ))
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
    let geom = field.geom();
    let b = geom.bounds;
    let cell = geom.spacing() * SKIP_BLOCK as f32;
    Ok(PackedField {
        aux,
        info: GpuField {
            bounds_min: v4(b.min, shift),
            bounds_max: v4(b.max, activation),
            res: [geom.res[0] as u32, geom.res[1] as u32, geom.res[2] as u32, color_kind],
            offsets: [0; 4],
            skip: [dims[0] as u32, dims[1] as u32, dims[2] as u32, 0],
            skip_cell: v4(cell, 0.0),
        },
    })
}

/// GPU memory per pool texel: f16 density, plus RGB and SH textures when
/// some field has that kind of colour.
pub fn pool_texel_bytes(fields: &[&Field]) -> usize {
    let sh = fields.iter().any(|f| matches!(f.appearance, Appearance::Sh2(_)));
    let rgb = fields.iter().any(|f| matches!(f.appearance, Appearance::Rgb(_)));
    // Density texture and activated density (`PoolTextures::sigma`); SH
    // textures and a view's baked colours.
    4 + if rgb { 4 } else { 0 } + if sh { 8 * SH_TEXTURES + 8 } else { 0 }
}

/// Per pool slot, for the SH bake: its field and brick position in the
/// field's brick grid (`x | y << 10 | z << 20`); `u32::MAX` for unused
/// slots.
pub fn pool_owners(plan: &PoolPlan) -> Vec<[u32; 2]> {
    let mut out = vec![[u32::MAX, 0]; plan.layout.slots.len().max(1)];
    for (o, &(f, b)) in out.iter_mut().zip(&plan.layout.slots) {
        let Some(bricks) = plan.fields.get(f as usize) else {
            continue;
        };
        let [nx, ny, _] = bricks.dims;
        let b = b as usize;
        let (x, y, z) = (b % nx, b / nx % ny, b / (nx * ny));
        *o = [f, (x | y << POOL_BITS | z << (2 * POOL_BITS)) as u32];
    }
    out
}

/// Flags the layers whose SH colours the view's bake serves: per SH field
/// the bake uses the camera in the frame of the field's first layer, so
/// the layers of that field in the same frame share it; a layer moved
/// away from it (a moved object) keeps evaluating its SH per sample. In an
/// NDC scene (`ndc`) only layers in the scene's own frame are baked: the
/// bake maps texels between NDC and the world in that frame.
pub fn mark_baked(layers: &mut [GpuLayer], fields: &[GpuField], ndc: bool) {
    for k in 0..layers.len() {
        let f = layers[k].info[0] as usize;
        let sh = fields.get(f).is_some_and(|g| g.res[3] & COLOR_SH != 0);
        let first = layers.iter().position(|l| l.info[0] as usize == f).unwrap_or(k);
        let frame_ok = !ndc || layers[k].to_local == Mat4::IDENTITY.to_cols_array_2d();
        if sh && f < MAX_LAYERS && layers[first].to_local == layers[k].to_local && frame_ok {
            layers[k].info[3] |= LAYER_BAKED;
        }
    }
}

/// The bake's parameters for a camera at `origin` (world): per baked field
/// the camera in the frame of its first layer ([`mark_baked`]).
pub fn bake_params(layers: &[GpuLayer], pool_bricks: [usize; 3], slots: usize, origin: Vec3) -> GpuBake {
    let mut b = GpuBake {
        pool: [
            pool_bricks[0] as u32,
            pool_bricks[1] as u32,
            pool_bricks[2] as u32,
            slots as u32,
        ],
        ..Default::default()
    };
    for l in layers.iter().filter(|l| l.info[3] & LAYER_BAKED != 0) {
        let f = l.info[0] as usize;
        if f < MAX_LAYERS && b.cams[f][3] == 0.0 {
            let c = Mat4::from_cols_array_2d(&l.to_local).transform_point3(origin);
            b.cams[f] = [c.x, c.y, c.z, 1.0];
        }
    }
    b
}

/// Workgroups of the bake (shaders/sh_bake.wgsl): 8 per brick along x,
/// the slots along y then z (at most 65535 per dimension).
pub fn bake_dispatch(slots: usize) -> [u32; 3] {
    const MAX: usize = 65535;
    let slots = slots.max(1);
    let y = slots.min(MAX);
    [8, y as u32, slots.div_ceil(y) as u32]
}

/// The pool textures' contents (x fastest, [`PoolLayout::fill`]); the RGB
/// and SH textures are empty when no field has that kind of colour.
#[derive(Clone, Debug, Default)]
pub struct PoolTextures {
    pub size: [usize; 3],
    /// Raw density, f16 bits ([`density_texel`]).
    pub density: Vec<u16>,
    pub rgb: Vec<u32>,
    /// [`SH_TEXTURES`] textures of [`sh_texel`]s.
    pub sh: Vec<Vec<[u16; 4]>>,
    /// Activated density per texel as f16, two to a word (texel `i` in
    /// the low half of word `i / 2` when even): what masks weight each
    /// corner's bit by. A storage buffer, as 8 loads from it cost lavapipe
    /// less than 8 texture loads, and activating once here saves the
    /// shader 8 softplus per masked sample.
    pub sigma: Vec<u32>,
}

/// Fills the pool textures of `plan` from `fields` (the [`drawn_field`]s,
/// in the plan's order).
pub fn pool_textures(fields: &[&Field], plan: &PoolPlan) -> PoolTextures {
    let layout = &plan.layout;
    let bricks = &plan.fields;
    // Grid point of a texel, by (field, brick, texel coordinates).
    let point = |f: usize, b: usize, l: [usize; 3]| bricks[f].point(b, l);
    let density = layout.fill(|f, b, l| point(f, b, l).map_or(0, |v| density_texel(fields[f].density.raw[v])));
    let has = |sh: bool| {
        fields.iter().any(|f| {
            matches!(
                (&f.appearance, sh),
                (Appearance::Sh2(_), true) | (Appearance::Rgb(_), false)
            )
        })
    };
    let rgb = if has(false) {
        layout.fill(|f, b, l| match (&fields[f].appearance, point(f, b, l)) {
            (Appearance::Rgb(g), Some(v)) => rgb_texel(g, v),
            _ => 0,
        })
    } else {
        Vec::new()
    };
    let sh = if has(true) {
        (0..SH_TEXTURES)
            .map(|t| {
                layout.fill(|f, b, l| match (&fields[f].appearance, point(f, b, l)) {
                    (Appearance::Sh2(g), Some(v)) => sh_texel(g, v, t),
                    _ => [0; 4],
                })
            })
            .collect()
    } else {
        Vec::new()
    };
    let sigma_texels = layout.fill(|f, b, l| {
        point(f, b, l).map_or(0, |v| {
            let s = fields[f].density.sigma_at(v).min(65504.0);
            half::f16::from_f32(s).to_bits()
        })
    });
    let sigma = sigma_texels
        .chunks(2)
        .map(|p| p[0] as u32 | (p.get(1).copied().unwrap_or(0) as u32) << 16)
        .collect();
    PoolTextures {
        size: layout.size,
        density,
        rgb,
        sh,
        sigma,
    }
}

/// Bits per axis of a brick's pool position in an [`Indirection`] texel.
pub const POOL_BITS: u32 = 10;
/// Set in every [`Indirection`] texel of an occupied brick.
pub const POOL_OCCUPIED: u32 = 1 << 31;

/// The [`Indirection`] texel of pool slot `slot`: its brick position in
/// the pool, `x | y << 10 | z << 20`, and [`POOL_OCCUPIED`]. The shader
/// finds a brick with one texture load and shifts: a storage load and the
/// divisions that decode a slot number made lavapipe's march 25 % slower.
pub fn pool_entry(pool: [usize; 3], slot: usize) -> u32 {
    let (x, y, z) = (slot % pool[0], slot / pool[0] % pool[1], slot / (pool[0] * pool[1]));
    POOL_OCCUPIED | x as u32 | (y as u32) << POOL_BITS | (z as u32) << (2 * POOL_BITS)
}

/// Every field's brick grid in one 3D `R32Uint` texture (fields stacked
/// along z, x fastest): per brick its [`pool_entry`], 0 when empty.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Indirection {
    pub size: [usize; 3],
    pub data: Vec<u32>,
    /// Each field's first z slice.
    pub z0: Vec<usize>,
}

/// The plan's [`Indirection`] texture, at most `max_side` texels a side.
pub fn indirection(plan: &PoolPlan, max_side: usize) -> Result<Indirection> {
    let w = plan.fields.iter().map(|f| f.dims[0]).max().unwrap_or(1);
    let h = plan.fields.iter().map(|f| f.dims[1]).max().unwrap_or(1);
    let d = plan.fields.iter().map(|f| f.dims[2]).sum::<usize>().max(1);
    crate::ensure_within!(
        DeviceLimit,
        w.max(h).max(d) <= max_side && plan.layout.bricks.iter().all(|&n| n <= 1 << POOL_BITS),
        "the fields have more bricks ({w}x{h}x{d}) than the GPU view can index"
    );
    let mut data = vec![0; w * h * d];
    let mut z0 = Vec::with_capacity(plan.fields.len());
    let mut z = 0;
    for (f, &first) in plan.fields.iter().zip(&plan.layout.first) {
        z0.push(z);
        let [nx, ny, nz] = f.dims;
        for (b, &slot) in f.indirection.iter().enumerate() {
            if slot != 0 {
                let (x, y, bz) = (b % nx, b / nx % ny, b / (nx * ny));
                data[x + w * (y + h * (z + bz))] = pool_entry(plan.layout.bricks, first + slot as usize - 1);
            }
        }
        z += nz;
    }
    Ok(Indirection {
        size: [w, h, d],
        data,
        z0,
    })
}

/// Concatenates the fields' skip grids and the plan's brick slot grids
/// into `aux`; returns the field records with absolute offsets (but the
/// [`Indirection`] slice, set by the caller) and the plan's level of
/// detail.
pub fn concat_fields(fields: &[&PackedField], plan: &PoolPlan) -> Result<(Vec<GpuField>, Vec<u32>)> {
    let mut infos = Vec::with_capacity(fields.len());
    let mut aux = Vec::new();
    for ((p, bricks), &first) in fields.iter().zip(&plan.fields).zip(&plan.layout.first) {
        let mut info = p.info;
        info.skip[3] = aux.len() as u32;
        aux.extend_from_slice(&p.aux);
        info.offsets = [aux.len() as u32, first as u32, 0, 0];
        aux.extend_from_slice(&bricks.indirection);
        // The last point shown and the points per axis at this level.
        let lo = Vec3::from_slice(&info.bounds_min[..3]);
        let hi = Vec3::from_slice(&info.bounds_max[..3]);
        let full = bricks.full_res.map(|n| (n - 1) as f32);
        let shown = bricks.res.map(|n| ((n - 1) * bricks.stride) as f32);
        let last = lo + (hi - lo) * Vec3::from(shown) / Vec3::from(full);
        info.bounds_max = v4(last, info.bounds_max[3]);
        info.res = [
            bricks.res[0] as u32,
            bricks.res[1] as u32,
            bricks.res[2] as u32,
            info.res[3],
        ];
        infos.push(info);
    }
    crate::ensure_within!(
        DeviceLimit,
        aux.len() < u32::MAX as usize,
        "the fields are too large for the GPU view"
    );
    Ok((infos, aux))
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

/// A mask bitmap over a field's grid, as uploaded: the same bitmap over
/// two fields is two uploads (its words follow each field's bricks).
#[derive(Clone, Debug)]
pub struct MaskRef {
    pub bits: Arc<Bitmap>,
    pub field: Arc<Field>,
}

impl MaskRef {
    fn is(&self, bits: &Arc<Bitmap>, field: &Arc<Field>) -> bool {
        Arc::ptr_eq(&self.bits, bits) && Arc::ptr_eq(&self.field, field)
    }
}

/// Distinct (mask, field) pairs of a scene (layer masks, then highlight
/// masks), in order of first use.
pub fn distinct_bitmaps(scene: &Scene, overlay: &[Overlay]) -> Vec<MaskRef> {
    let masks = scene.layers.iter().filter_map(|l| match &l.mask {
        Mask::Keep(b) | Mask::Remove(b) => Some((b, &l.field)),
        Mask::All => None,
    });
    let highlights = overlay
        .iter()
        .zip(&scene.layers)
        .filter_map(|(o, l)| o.highlight_mask.as_ref().map(|b| (b, &l.field)));
    let mut out: Vec<MaskRef> = Vec::new();
    for (b, f) in masks.chain(highlights) {
        if !out.iter().any(|m| m.is(b, f)) {
            out.push(MaskRef {
                bits: b.clone(),
                field: f.clone(),
            });
        }
    }
    out
}

/// Word offsets (u32 units) of masks of `words` words each in the
/// concatenated buffer, and the total word count.
pub fn bitmap_offsets(words: &[usize]) -> (Vec<u32>, usize) {
    let mut total = 0usize;
    let offs = words
        .iter()
        .map(|&n| {
            total += n;
            (total - n) as u32
        })
        .collect();
    (offs, total)
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
    bitmaps: &[MaskRef],
    bitmap_offs: &[u32],
    overlay: &[Overlay],
) -> Result<Vec<GpuLayer>> {
    // Word offset of a layer's bitmap (`what`: "mask", "highlight mask").
    let offset_of = |i: usize, what: &str, bits: &Arc<Bitmap>, field: &Arc<Field>| -> Result<u32> {
        ensure!(
            bits.res() == field.res(),
            "layer {i}: {what} resolution {:?} differs from the field's {:?}",
            bits.res(),
            field.res()
        );
        let k = bitmaps
            .iter()
            .position(|m| m.is(bits, field))
            .ok_or_else(|| crate::Error::invalid(format!("layer {i}: its {what} was not uploaded")))?;
        Ok(bitmap_offs[k])
    };
    let no_overlay = Overlay::default();
    let mut out = Vec::with_capacity(scene.layers.len());
    for (i, l) in scene.layers.iter().enumerate() {
        ensure!(
            crate::util::invertible(&l.to_world),
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
    crate::ensure_within!(
        DeviceLimit,
        out.len() <= MAX_LAYERS,
        "the GPU view draws at most {MAX_LAYERS} layers at once, this scene has {}",
        out.len()
    );
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::app::gpu::pool;
    use crate::field::{Aabb, FieldBuilder, RankIndex};
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
    fn sh_texels_hold_the_coefficients_and_a_stored_flag() {
        let f = ball();
        let g = f.geom();
        let bits = Bitmap::from_fn(g.res, |i| i % 5 == 0);
        let ix = Arc::new(RankIndex::new(bits.clone()));
        let data: Vec<f16> = (0..ix.count() * 27).map(|k| f16::from_f32(k as f32 * 0.25)).collect();
        let sh = ChannelGrid::sparse(g, 27, ix.clone(), data.clone());
        for v in [0, 5, 7, 100, g.len() - 1] {
            let texels: Vec<u16> = (0..SH_TEXTURES).flat_map(|t| sh_texel(&sh, v, t)).collect();
            match ix.slot(v) {
                None => assert!(texels.iter().all(|&h| h == 0), "voxel {v}"),
                Some(s) => {
                    for k in 0..27 {
                        assert_eq!(texels[k], data[s * 27 + k].to_bits(), "voxel {v} coefficient {k}");
                    }
                    assert_eq!(f16::from_bits(texels[27]), f16::ONE);
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
    fn pool_texels_hold_their_grid_points_values() {
        let f = ball();
        let g = f.geom();
        // Sparse RGB: stored points have alpha 1, the others are 0 entirely.
        let bits = Bitmap::from_fn(g.res, |i| i % 7 == 0);
        let ix = Arc::new(RankIndex::new(bits.clone()));
        let data: Vec<f16> = bits.ones().flat_map(|_| [f16::ONE, f16::ZERO, f16::ONE]).collect();
        let mut sparse = f.clone();
        sparse.appearance = Appearance::Rgb(ChannelGrid::sparse(g, 3, ix, data));
        let fields = [&f, &sparse];
        let plan = pool::plan(
            &[&f.density, &sparse.density],
            pool_texel_bytes(&fields),
            2048,
            1 << 30,
            usize::MAX,
        )
        .unwrap();
        assert_eq!(plan.stride, 1);
        let tex = pool_textures(&fields, &plan);
        assert!(tex.sh.is_empty());
        let layout = &plan.layout;
        let [px, py, _] = layout.bricks;
        let mut checked = 0;
        for (slot, &(fi, b)) in layout.slots.iter().enumerate() {
            let base = [slot % px, slot / px % py, slot / (px * py)].map(|c| c * pool::BRICK);
            for t in 0..pool::BRICK_TEXELS {
                let l = pool::texel_coords(t);
                let Some(v) = plan.fields[fi as usize].point(b as usize, l) else {
                    continue;
                };
                let [x, y, z] = [0, 1, 2].map(|a| base[a] + l[a]);
                let at = x + layout.size[0] * (y + layout.size[1] * z);
                let field = fields[fi as usize];
                assert_eq!(tex.density[at], density_texel(field.density.raw[v]));
                let half = tex.sigma[at / 2] >> (16 * (at % 2)) & 0xffff;
                let sigma = f16::from_f32(field.density.sigma_at(v)).to_bits() as u32;
                assert_eq!(half, sigma, "activated density of texel {at}");
                let Appearance::Rgb(rgb) = &field.appearance else {
                    unreachable!()
                };
                assert_eq!(tex.rgb[at], rgb_texel(rgb, v));
                if fi == 1 {
                    assert_eq!(tex.rgb[at] != 0, v % 7 == 0, "voxel {v}");
                }
                checked += 1;
            }
        }
        assert!(checked > 0);
        let want = g.point_of(g.index(8, 8, 8)) * 0.5 + 0.5;
        let got = rgb_texel(
            match &f.appearance {
                Appearance::Rgb(g) => g,
                _ => unreachable!(),
            },
            g.index(8, 8, 8),
        );
        assert!(((got & 1023) as f32 / 1023.0 - want.x).abs() < 1e-3);
        assert_eq!(got >> 30, 3);
        // Raw densities beyond f16 stay finite.
        assert_eq!(f16::from_bits(density_texel(-1e9)), f16::MIN);
    }

    #[test]
    fn concatenation_offsets_fields_and_sets_the_level_of_detail() {
        let f = ball();
        let p = pack_field(&f).unwrap();
        let plan = pool::plan(&[&f.density, &f.density], 2, 2048, 1 << 30, usize::MAX).unwrap();
        let (infos, aux) = concat_fields(&[&p, &p], &plan).unwrap();
        let ind = plan.fields[0].indirection.len();
        assert_eq!(aux.len(), 2 * (p.aux.len() + ind));
        assert_eq!(infos[0].skip[3], 0);
        assert_eq!(infos[0].offsets[0] as usize, p.aux.len());
        assert_eq!(infos[1].skip[3] as usize, p.aux.len() + ind);
        assert_eq!(infos[1].offsets[1] as usize, plan.fields[0].count());
        assert_eq!(&aux[infos[1].offsets[0] as usize..], &plan.fields[1].indirection[..]);
        // The indirection texture: field 1's bricks after field 0's, each
        // at its pool position.
        let ind = indirection(&plan, 2048).unwrap();
        let d = plan.fields[0].dims;
        assert_eq!(ind.size, [d[0], d[1], 2 * d[2]]);
        assert_eq!(ind.z0, vec![0, d[2]]);
        let [px, py, _] = plan.layout.bricks;
        for (b, &slot) in plan.fields[1].indirection.iter().enumerate() {
            let (x, y, z) = (b % d[0], b / d[0] % d[1], b / (d[0] * d[1]) + d[2]);
            let e = ind.data[x + d[0] * (y + d[1] * z)];
            if slot == 0 {
                assert_eq!(e, 0);
                continue;
            }
            let s = plan.fields[0].count() + slot as usize - 1;
            let at = |k: u32| (e >> (k * POOL_BITS) & 1023) as usize;
            assert_eq!(e & POOL_OCCUPIED, POOL_OCCUPIED);
            assert_eq!([at(0), at(1), at(2)], [s % px, s / px % py, s / (px * py)]);
        }
        assert_eq!(infos[0].res, [17, 17, 17, 0]);
        assert_eq!(infos[0].bounds_max[..3], [1.0, 1.0, 1.0]);
        // Every 2nd point of 17 is 9 points, up to the last one; every
        // 4th of 17 is 5 (0, 4, .., 16); of 16 points (15 cells), every
        // 2nd is 8 points, ending one spacing before the box's end.
        let mut coarse = plan.clone();
        coarse.fields = vec![pool::FieldBricks::build(&f.density, 2); 2];
        let (infos, _) = concat_fields(&[&p, &p], &coarse).unwrap();
        assert_eq!(infos[0].res, [9, 9, 9, 0]);
        assert_eq!(infos[0].bounds_max[..3], [1.0, 1.0, 1.0]);
        let odd =
            FieldBuilder::new(Aabb::new(Vec3::ZERO, Vec3::splat(15.0)), [16; 3]).build(|_| 1.0, |_| Vec3::ONE, None);
        let po = pack_field(&odd).unwrap();
        coarse.fields = vec![pool::FieldBricks::build(&odd.density, 2)];
        let (infos, _) = concat_fields(&[&po], &coarse).unwrap();
        assert_eq!(infos[0].res, [8, 8, 8, 0]);
        assert_eq!(infos[0].bounds_max[..3], [14.0, 14.0, 14.0]);
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
        let (offs, total) = bitmap_offsets(&[16, 32]);
        assert_eq!(offs, vec![0, 16]);
        assert_eq!(total, 48);
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

    #[test]
    fn the_bake_serves_sh_layers_in_their_fields_first_frame() {
        let sh = GpuField {
            res: [17, 17, 17, COLOR_SH],
            ..Default::default()
        };
        let rgb = GpuField::default();
        let at = |field: u32, x: f32| GpuLayer {
            to_local: affine_cols(&Affine3A::from_translation(Vec3::new(x, 0.0, 0.0))),
            info: [field, MASK_ALL, 0, 0],
            ..Default::default()
        };
        // Field 0 (SH): the rest in place, an object moved, a second copy
        // in place; field 1 (RGB); field 2 (SH) moved as a whole.
        let mut layers = vec![at(0, 0.0), at(0, 1.0), at(1, 0.0), at(0, 0.0), at(2, 2.0)];
        mark_baked(&mut layers, &[sh, rgb, sh], false);
        let baked: Vec<bool> = layers.iter().map(|l| l.info[3] & LAYER_BAKED != 0).collect();
        assert_eq!(baked, [true, false, false, true, true]);
        // Cameras in each baked field's frame (the layers translate by x).
        let b = bake_params(&layers, [3, 4, 5], 42, Vec3::new(0.5, 1.0, 2.0));
        assert_eq!(b.pool, [3, 4, 5, 42]);
        assert_eq!(b.cams[0], [0.5, 1.0, 2.0, 1.0]);
        assert_eq!(b.cams[1], [0.0; 4]);
        assert_eq!(b.cams[2], [2.5, 1.0, 2.0, 1.0]);
    }

    #[test]
    fn bake_workgroups_cover_every_slot_within_dispatch_limits() {
        for slots in [0usize, 1, 7, 65535, 65536, 200_001] {
            let [x, y, z] = bake_dispatch(slots);
            assert_eq!(x as usize * 64, pool::BRICK_TEXELS);
            assert!(y <= 65535 && z <= 65535);
            assert!(y as usize * z as usize >= slots.max(1), "{slots}");
            assert!(
                (y as usize) * (z as usize - 1) < slots.max(1),
                "{slots}: a whole z layer is spare"
            );
        }
    }

    #[test]
    fn pool_owners_name_each_slots_field_and_brick() {
        let f = ball();
        let plan = pool::plan(&[&f.density, &f.density], 2, 2048, 1 << 30, usize::MAX).unwrap();
        let owners = pool_owners(&plan);
        assert_eq!(owners.len(), plan.layout.slots.len());
        for (o, &(field, brick)) in owners.iter().zip(&plan.layout.slots) {
            assert_eq!(o[0], field);
            let [nx, ny, _] = plan.fields[field as usize].dims;
            let m = (1 << POOL_BITS) - 1;
            let (x, y, z) = (o[1] & m, o[1] >> POOL_BITS & m, o[1] >> (2 * POOL_BITS));
            assert_eq!(x as usize + nx * (y as usize + ny * z as usize), brick as usize);
        }
    }
}
