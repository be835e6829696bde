// isrf GPU ray marcher: the same function as the CPU reference renderer
// (src/render/mod.rs), evaluated per pixel in a fullscreen fragment pass
// into the view's march textures (colour, depth), which composite.wgsl
// draws into the view; src/app/gpu/view.rs decides when to march.
//
// Samples sit at world distances t_i = (i + 1/2) * step along the unit ray
// from the camera, the step fixed per ray (render::Step: a fraction of a
// cell measured in cell units in the finest layer the ray meets, or a
// world distance); at each sample the layers' (masked, activated)
// densities add and colours mix by density (D²NeRF), alpha = 1 - exp(-σ δ),
// T_i = Π (1 - alpha_j), C = Σ T_i alpha_i c_i + T_N · background. Grids are
// corner-aligned (src/field/geom.rs). Only occupied bricks of the grids
// are stored, in pool textures shared by all fields (src/app/gpu/pool.rs):
// a field's indirection grid gives the pool slot of the brick a cell lies
// in, and every cell's 8 corners lie in its brick, so the texture unit's
// trilinear filter interpolates raw density (f16 texels), RGB colours
// (10-bit unorm, within 5e-4 of their f16 values) and SH coefficients
// (their f16 values) exactly as the CPU does (f32 weights on lavapipe;
// real GPUs quantise the weights, typically to 8 bits). Cells of empty
// bricks have σ ≤ 1e-4 at every corner and are read as empty. Sparse
// colours renormalise over the stored corners, as `ChannelGrid::sample`
// does. Masks weight the bitmap by density, as `render::bitmap_fraction`,
// with the corners' densities read one by one.
//
// Empty space: each field has a grid of skip cells (2 voxels wide) holding
// the Chebyshev distance to the nearest cell whose grid points have
// σ > 1e-4; a ray leaves the whole empty cube at once. Samples are skipped
// only where every layer is empty; what they would add is below the CPU's
// own skipping threshold. Each layer's empty / occupied state is cached until
// the ray leaves the cell or cube it was computed for.
//
// Data layout: see src/app/gpu/pack.rs.

#import isrf::common::{FieldInfo, COLOR_SPARSE, sh_basis, sh_dot, sh_colour, ndc_to_world}

struct View {
    c2w: mat4x4<f32>,
    clip_from_world: mat4x4<f32>,
    // fx, fy, cx, cy
    intrinsics: vec4<f32>,
    background: vec4<f32>,
    // step, min transmittance, step kind (0: cells, 1: world), 0
    march: vec4<f32>,
    // layer count
    counts: vec4<u32>,
    // 1 / the pool textures' size (xyz)
    atlas: vec4<f32>,
    // the pool's bricks per axis (xyz)
    pool: vec4<u32>,
    // NDC (forward-facing scenes): 1 when on, near, 2f/W, 2f/H
    ndc: vec4<f32>,
};

struct Layer {
    to_local: mat4x4<f32>,
    // field index, mask kind, mask word offset, flags
    info: vec4<u32>,
    tint_hue: vec4<f32>,
    sat_bright: vec4<f32>,
    box_min: vec4<f32>,
    box_max: vec4<f32>,
    // 1 + highlight mask word offset (0: none), 0, 0, 0
    highlight: vec4<u32>,
};


@group(0) @binding(0) var<uniform> view: View;
@group(0) @binding(1) var<storage, read> layers: array<Layer>;
@group(0) @binding(2) var<storage, read> fields: array<FieldInfo>;
@group(0) @binding(3) var<storage, read> aux: array<u32>;
@group(0) @binding(4) var<storage, read> bitmaps: array<u32>;
// The pool (pool.rs, pack.rs `PoolTextures`): raw density, RGB colours
// and SH coefficients (27 + a stored flag in 7 RGBA textures) of every
// field's occupied bricks, sampled with the GPU's trilinear filter: one
// texture sample instead of 8 loads per quantity, which made frames 1.8×
// faster on lavapipe (its texture unit gathers all lanes at once, where a
// storage load is a loop over the lanes).
@group(0) @binding(5) var density_tex: texture_3d<f32>;
@group(0) @binding(6) var rgb_tex: texture_3d<f32>;
@group(0) @binding(7) var sh0: texture_3d<f32>;
@group(0) @binding(8) var sh1: texture_3d<f32>;
@group(0) @binding(9) var sh2: texture_3d<f32>;
@group(0) @binding(10) var sh3: texture_3d<f32>;
@group(0) @binding(11) var sh4: texture_3d<f32>;
@group(0) @binding(12) var sh5: texture_3d<f32>;
@group(0) @binding(13) var sh6: texture_3d<f32>;
@group(0) @binding(14) var atlas_sampler: sampler;
// Every field's brick grid (pack.rs `Indirection`): per brick its position
// in the pool, 0 when empty.
@group(0) @binding(15) var indirection: texture_3d<u32>;
// Activated density per pool texel, f16 pairs (pack.rs
// `PoolTextures::sigma`): what masks weight each corner's bit by.
@group(0) @binding(16) var<storage, read> pool_sigma: array<u32>;
// The view's baked SH colours (sh_bake.wgsl), for layers with LAYER_BAKED.
@group(0) @binding(17) var baked: texture_3d<f32>;

// The pipeline is specialised on a bound of the layer count (1, 2, 4 or
// src/app/gpu/pack.rs MAX_LAYERS): the per-layer loops run a constant
// number of times, so that lavapipe unrolls them and keeps the per-layer
// state below in registers (arrays indexed by a loop counter live in memory,
// which doubles the frame time there). It is also specialised on what the
// scene uses (src/app/gpu/mod.rs `MarchKey`): shader defs RGB and / or SH
// (colour kinds), MASKS, COLOR_EDIT, OVERLAY (tint / dim) and HIGHLIGHT
// (a highlight mask); code a scene does not need is left out, as its mere
// presence slows lavapipe's whole march (SH code cost a plain RGB field
// 29 % of its frame, mask code 26 %).
const MAX_LAYERS: u32 = #{MAX_LAYERS}u;
const MAX_ITERATIONS: u32 = 1000000u;
const INF: f32 = 3.0e38;


const COLOR_SH: u32 = 2u;
const MASK_KEEP: u32 = 1u;
const MASK_REMOVE: u32 = 2u;
const LAYER_COLOR_EDIT: u32 = 1u;
const LAYER_HIGHLIGHT: u32 = 2u;
const LAYER_DIM: u32 = 4u;
const LAYER_BAKED: u32 = 8u;
// pool.rs BRICK_CELLS, BRICK, BRICK_WORDS.
const BRICK_CELLS: u32 = 7u;
const BRICK: u32 = 8u;
const BRICK_WORDS: u32 = 16u;

// Trilinear cell of a local point: the pool texel of its base corner,
// where its brick's field-local slot + 1 is in `aux` (mask words; read only
// by masks) and the corner's texel
// index in the brick (mask bits), fractions, the point's pool texture
// coordinates; `inside` false outside the grid (geom.rs `corners`) or in
// an empty brick.
struct Cell {
    texel: vec3<u32>,
    slot: u32,
    local: u32,
    frac: vec3<f32>,
    uvw: vec3<f32>,
    inside: bool,
};

// Per-ray state of each layer.
var<private> lo_origin: array<vec3<f32>, MAX_LAYERS>;
var<private> lo_dir: array<vec3<f32>, MAX_LAYERS>;
// Until which ray distance the cached empty / occupied state holds.
var<private> valid_until: array<f32, MAX_LAYERS>;
var<private> occupied: array<u32, MAX_LAYERS>;
var<private> sigma: array<f32, MAX_LAYERS>;
// The cell of each layer's last density sample (shading reuses it).
var<private> cells: array<Cell, MAX_LAYERS>;
// Each layer's field and layer records, read once per ray: a record read
// from a storage buffer inside the march is a gather per word and lane on
// lavapipe (this caching made frames 35 % faster there).
var<private> finfo: array<FieldInfo, MAX_LAYERS>;
var<private> linfo: array<vec4<u32>, MAX_LAYERS>;
var<private> lbox_min: array<vec3<f32>, MAX_LAYERS>;
var<private> lbox_max: array<vec3<f32>, MAX_LAYERS>;
// The ray's sample spacing.
var<private> ray_dt: f32;
#ifdef HIGHLIGHT
var<private> lhighlight: array<u32, MAX_LAYERS>;
#endif

fn cell_of(f: FieldInfo, p: vec3<f32>) -> Cell {
    var out: Cell;
    let n = vec3<f32>(f.res.xyz) - vec3<f32>(1.0);
    let g = (p - f.bounds_min.xyz) / (f.bounds_max.xyz - f.bounds_min.xyz) * n;
    out.inside = all(g >= vec3<f32>(0.0)) && all(g <= n);
    if !out.inside {
        return out;
    }
    // Base corner clamped so that points on the upper face use the last cell.
    let b = min(vec3<u32>(g), f.res.xyz - vec3<u32>(2u));
    out.frac = g - vec3<f32>(b);
    // The brick (pool.rs `brick_dims`, `FieldBricks::indirection`).
    let bricks = (f.res.xyz + vec3<u32>(BRICK_CELLS - 2u)) / BRICK_CELLS;
    let bc = b / BRICK_CELLS;
    let l = b - bc * BRICK_CELLS;
    // The brick's position in the pool (pack.rs `pool_entry`; 0: empty),
    // from a texture: a storage load and the divisions that decode a slot
    // number made lavapipe's march 25 % slower.
    let entry = textureLoad(indirection, vec3<i32>(bc + vec3<u32>(0u, 0u, f.offsets.z)), 0).x;
    if entry == 0u {
        out.inside = false;
        return out;
    }
    // The brick's field-local slot (mask words), in the field's slot grid.
    out.slot = f.offsets.x + bc.x + bricks.x * (bc.y + bricks.y * bc.z);
    let pb = vec3<u32>(entry & 1023u, (entry >> 10u) & 1023u, (entry >> 20u) & 1023u);
    out.texel = pb * BRICK + l;
    out.local = l.x + BRICK * (l.y + BRICK * l.z);
    // Texel centres sit at half-integer coordinates.
    out.uvw = (vec3<f32>(out.texel) + out.frac + vec3<f32>(0.5)) * view.atlas.xyz;
    return out;
}

fn activate(f: FieldInfo, raw: f32) -> f32 {
    if f.bounds_max.w > 0.5 {
        let x = raw + f.bounds_min.w;
        if x > 20.0 {
            return x;
        }
        // log(1 + e) loses e below f32 precision; softplus(x) ≈ e^x there
        // (the CPU uses ln_1p).
        if x < -12.0 {
            return exp(x);
        }
        return log(1.0 + exp(x));
    }
    return max(raw, 0.0);
}

fn raw_density(f: FieldInfo, c: Cell) -> f32 {
    return textureSampleLevel(density_tex, atlas_sampler, c.uvw, 0.0).x;
}

// RGB colour in [0, 1] at a cell (ChannelGrid::sample then clamp): the
// atlas texels are premultiplied by alpha = stored (pack.rs `rgb10a2`), so
// the filter gives Σ w·rgb and Σ w over the stored corners; sparse colours
// renormalise by the latter.
fn rgb_at(f: FieldInfo, c: Cell) -> vec3<f32> {
    let q = textureSampleLevel(rgb_tex, atlas_sampler, c.uvw, 0.0);
    if q.w <= 1e-6 {
        return vec3<f32>(0.0);
    }
    var acc = q.xyz;
    if (f.res.w & COLOR_SPARSE) != 0u {
        acc = acc / q.w;
    }
    return clamp(acc, vec3<f32>(0.0), vec3<f32>(1.0));
}


// SH colour: the coefficients interpolated by the filter (channel 27 is
// the sum of the stored corners' weights, pack.rs `sh_texel`), dotted with
// the basis, then a sigmoid (common.wgsl `sh_colour`).
fn sh_at(f: FieldInfo, c: Cell, dir: vec3<f32>) -> vec3<f32> {
    let t6 = textureSampleLevel(sh6, atlas_sampler, c.uvw, 0.0);
    let logits = sh_dot(
        sh_basis(dir),
        textureSampleLevel(sh0, atlas_sampler, c.uvw, 0.0),
        textureSampleLevel(sh1, atlas_sampler, c.uvw, 0.0),
        textureSampleLevel(sh2, atlas_sampler, c.uvw, 0.0),
        textureSampleLevel(sh3, atlas_sampler, c.uvw, 0.0),
        textureSampleLevel(sh4, atlas_sampler, c.uvw, 0.0),
        textureSampleLevel(sh5, atlas_sampler, c.uvw, 0.0),
        t6,
    );
    return sh_colour(f, logits, t6.w);
}

#ifdef BAKED
// SH colour from the view's bake (sh_bake.wgsl): per texel the SH logits
// for the direction from the camera, and the stored weight; the filter
// interpolates them as it would the coefficients (the dot product is
// linear), so one sample replaces seven. The direction is the camera's to
// each grid point rather than the ray's, a difference below the cell size
// over the viewing distance.
fn baked_at(f: FieldInfo, c: Cell) -> vec3<f32> {
    let q = textureSampleLevel(baked, atlas_sampler, c.uvw, 0.0);
    return sh_colour(f, q.xyz, q.w);
}
#endif

fn color_at(k: u32, f: FieldInfo, c: Cell) -> vec3<f32> {
#ifdef BAKED
    if (linfo[k].w & LAYER_BAKED) != 0u {
        return baked_at(f, c);
    }
#endif
#ifdef SH
#ifdef RGB
    if (f.res.w & COLOR_SH) == 0u {
        return rgb_at(f, c);
    }
#endif
    return sh_at(f, c, normalize(lo_dir[k]));
#else
#ifdef RGB
    return rgb_at(f, c);
#else
    // (Every layer is baked.)
    return vec3<f32>(0.0);
#endif
#endif
}

fn bit(offset: u32, idx: u32) -> f32 {
    let w = bitmaps[offset + (idx >> 5u)];
    return f32((w >> (idx & 31u)) & 1u);
}

// One corner of `mask_factor`: (w·σ·m, w·σ, w·m) for the corner's bit
// `m` and pool texel `texel` (its density).
fn mask_tap(f: FieldInfo, m: f32, texel: vec3<u32>, w: f32) -> vec3<f32> {
    let size = view.pool.xy * BRICK;
    let i = texel.x + size.x * (texel.y + size.y * texel.z);
    let pair = unpack2x16float(pool_sigma[i >> 1u]);
    let ws = w * select(pair.x, pair.y, (i & 1u) == 1u);
    return vec3<f32>(ws * m, ws, w * m);
}

// The share b(p) of the density that comes from the corners set in the
// mask at word offset `words` (in brick order, pool.rs `brick_bits`):
// b = Σ w σ m / Σ w σ over the 8 corners with σ activated
// (render::bitmap_fraction), so that a removal leaves no half-density
// shell around the object. Without density at any corner, b falls back to
// the plain interpolation of the bits. Where the 8 bits agree, b is that
// bit exactly and the densities are not read: only cells on the mask's
// boundary pay for 8 density loads and activations (on lavapipe that
// made a moved object's frames about 2x faster).
fn bitmap_fraction(words: u32, f: FieldInfo, c: Cell) -> f32 {
    let o = words + (aux[c.slot] - 1u) * BRICK_WORDS;
    let l = c.local;
    // +1 texel is +1, +BRICK or +BRICK² in the brick's bit order.
    let m0 = bit(o, l);
    let m1 = bit(o, l + 1u);
    let m2 = bit(o, l + 8u);
    let m3 = bit(o, l + 9u);
    let m4 = bit(o, l + 64u);
    let m5 = bit(o, l + 65u);
    let m6 = bit(o, l + 72u);
    let m7 = bit(o, l + 73u);
    let sum = m0 + m1 + m2 + m3 + m4 + m5 + m6 + m7;
    if sum == 0.0 || sum == 8.0 {
        return m0;
    }
    let a = c.frac;
    let g = vec3<f32>(1.0) - a;
    let t = c.texel;
    let x = vec3<u32>(1u, 0u, 0u);
    let y = vec3<u32>(0u, 1u, 0u);
    let z = vec3<u32>(0u, 0u, 1u);
    // Corners written out (lavapipe is much faster so).
    let s = mask_tap(f, m0, t, g.x * g.y * g.z) + mask_tap(f, m1, t + x, a.x * g.y * g.z)
        + mask_tap(f, m2, t + y, g.x * a.y * g.z)
        + mask_tap(f, m3, t + x + y, a.x * a.y * g.z)
        + mask_tap(f, m4, t + z, g.x * g.y * a.z)
        + mask_tap(f, m5, t + z + x, a.x * g.y * a.z)
        + mask_tap(f, m6, t + z + y, g.x * a.y * a.z)
        + mask_tap(f, m7, t + z + y + x, a.x * a.y * a.z);
    if s.y > 0.0 {
        return s.x / s.y;
    }
    return s.z;
}

// The mask value: b(p) (keep) or 1 - b(p) (remove).
fn mask_factor(info: vec4<u32>, f: FieldInfo, c: Cell) -> f32 {
    let kind = info.y;
    if kind != MASK_KEEP && kind != MASK_REMOVE {
        return 1.0;
    }
    // (One call: each call site is a copy of the 8 taps on lavapipe.)
    let b = bitmap_fraction(info.z, f, c);
    return select(1.0 - b, b, kind == MASK_KEEP);
}

fn safe_recip(d: vec3<f32>) -> vec3<f32> {
    let s = select(vec3<f32>(1.0), sign(d), d != vec3<f32>(0.0));
    return s / max(abs(d), vec3<f32>(1e-30));
}

// Slab test (geom.rs `Aabb::intersect`): (t0, t1) with t0 clamped to >= 0;
// empty when t1 <= t0.
fn intersect(bmin: vec3<f32>, bmax: vec3<f32>, o: vec3<f32>, d: vec3<f32>) -> vec2<f32> {
    let inv = safe_recip(d);
    let a = (bmin - o) * inv;
    let b = (bmax - o) * inv;
    let lo = min(a, b);
    let hi = max(a, b);
    let t0 = max(max(max(lo.x, lo.y), lo.z), 0.0);
    let t1 = min(min(hi.x, hi.y), hi.z);
    return vec2<f32>(t0, t1);
}

// Distance from p along d to the exit of box [lo, hi] (p inside).
fn exit_distance(lo: vec3<f32>, hi: vec3<f32>, p: vec3<f32>, d: vec3<f32>) -> f32 {
    let inv = safe_recip(d);
    let e = max((lo - p) * inv, (hi - p) * inv);
    return max(min(min(e.x, e.y), e.z), 0.0);
}

fn skip_radius(f: FieldInfo, c: vec3<u32>) -> u32 {
    let i = c.x + f.skip.x * (c.y + f.skip.y * c.z);
    let word = aux[f.skip.w + (i >> 2u)];
    return (word >> (8u * (i & 3u))) & 255u;
}

// Recomputes layer k's state at ray distance t: occupied (sample here)
// until it leaves the current skip cell, or empty until it leaves the empty
// cube around it (or enters its box).
fn update_state(k: u32, t: f32) {
    let l_box_min = lbox_min[k];
    let l_box_max = lbox_max[k];
    let f = finfo[k];
    let d = lo_dir[k];
    let p = lo_origin[k] + t * d;
    if !(all(p >= l_box_min) && all(p <= l_box_max)) {
        occupied[k] = 0u;
        let hit = intersect(l_box_min, l_box_max, p, d);
        if hit.y > hit.x && hit.x > 0.0 {
            valid_until[k] = t + hit.x;
        } else if hit.y > hit.x {
            // On the box boundary: re-check at the next sample.
            valid_until[k] = t;
        } else {
            valid_until[k] = INF;
        }
        return;
    }
    let cell = f.skip_cell.xyz;
    let rel = (p - f.bounds_min.xyz) / cell;
    let dims = f.skip.xyz;
    let c = min(vec3<u32>(max(rel, vec3<f32>(0.0))), dims - vec3<u32>(1u));
    let r = skip_radius(f, c);
    let lo = f.bounds_min.xyz + vec3<f32>(c) * cell;
    let hi = lo + cell;
    if r == 0u {
        occupied[k] = 1u;
        valid_until[k] = t + exit_distance(lo, hi, p, d);
        return;
    }
    occupied[k] = 0u;
    let grow = f32(r - 1u) * cell;
    valid_until[k] = t + exit_distance(lo - grow, hi + grow, p, d);
}

fn apply_edit(k: u32, c_in: vec3<f32>) -> vec3<f32> {
    let tint_hue = layers[k].tint_hue;
    let sat_bright = layers[k].sat_bright;
    var c = c_in;
    let hue = tint_hue.w;
    if hue != 0.0 {
        let kk = vec3<f32>(1.0 / sqrt(3.0));
        let a = radians(hue);
        let s = sin(a);
        let co = cos(a);
        c = c * co + cross(kk, c) * s + kk * dot(kk, c) * (1.0 - co);
    }
    let luma = dot(c, vec3<f32>(0.2126, 0.7152, 0.0722));
    c = vec3<f32>(luma) + (c - vec3<f32>(luma)) * sat_bright.x;
    c = c * sat_bright.y * tint_hue.xyz;
    return clamp(c, vec3<f32>(0.0), vec3<f32>(1.0));
}

fn tinted(c: vec3<f32>) -> vec3<f32> {
    return mix(c, vec3<f32>(1.0, 0.55, 0.1), 0.35);
}

fn dimmed(c: vec3<f32>) -> vec3<f32> {
    let luma = dot(c, vec3<f32>(0.2126, 0.7152, 0.0722));
    return mix(c, vec3<f32>(luma), 0.7) * 0.6;
}

// The editor's overlay of layer k at cell c. With a highlight mask the
// tint applies to the object's share h of the density and the dimming to
// the rest: the colour a split into two layers (object, rest) would mix.
// Only pipelines with shader def HIGHLIGHT (scenes with a highlight mask)
// have that code: on lavapipe its mere presence costs a third of the
// frame.
fn overlay(k: u32, f: FieldInfo, c: Cell, col: vec3<f32>) -> vec3<f32> {
    let flags = linfo[k].w;
#ifdef HIGHLIGHT
    let hl = lhighlight[k];
    if hl != 0u {
        let tint = select(col, tinted(col), (flags & LAYER_HIGHLIGHT) != 0u);
        let dim = select(col, dimmed(col), (flags & LAYER_DIM) != 0u);
        return mix(dim, tint, bitmap_fraction(hl - 1u, f, c));
    }
#endif
    if (flags & LAYER_HIGHLIGHT) != 0u {
        return tinted(col);
    }
    if (flags & LAYER_DIM) != 0u {
        return dimmed(col);
    }
    return col;
}

// Sum of the layers' masked densities at t; fills `sigma`. Layers in empty
// space contribute nothing.
fn densities(n: u32, t: f32) -> f32 {
    var sum = 0.0;
    for (var k = 0u; k < MAX_LAYERS; k++) {
        if k >= n {
            break;
        }
        var s = 0.0;
        if occupied[k] != 0u {
            let info = linfo[k];
            let f = finfo[k];
            let c = cell_of(f, lo_origin[k] + t * lo_dir[k]);
            cells[k] = c;
            if c.inside {
                s = activate(f, raw_density(f, c));
#ifdef MASKS
                if s > 0.0 {
                    s *= mask_factor(info, f, c);
                }
#endif
            }
        }
        sigma[k] = s;
        sum += s;
    }
    return sum;
}

// Density-weighted colour at t (after `densities` at the same t).
fn shade(n: u32, t: f32, sum: f32) -> vec3<f32> {
    var col = vec3<f32>(0.0);
    for (var k = 0u; k < MAX_LAYERS; k++) {
        if k >= n {
            break;
        }
        let s = sigma[k];
        if s <= 0.0 {
            continue;
        }
        let info = linfo[k];
        let f = finfo[k];
        var ck = color_at(k, f, cells[k]);
#ifdef COLOR_EDIT
        if (info.w & LAYER_COLOR_EDIT) != 0u {
            ck = apply_edit(k, ck);
        }
#endif
#ifdef OVERLAY
        ck = overlay(k, f, cells[k], ck);
#endif
        col += (s / sum) * ck;
    }
    return col;
}

// The first sample at or after sample index `i` (updated) where some layer
// may have density, past the empty space the layers' skip grids vouch for;
// -1 when the ray leaves the scene (t > t1) first. Layer states are
// refreshed as the ray goes.
fn next_sample(n: u32, i: ptr<function, f32>, t1: f32) -> f32 {
    let dt = ray_dt;
    for (var it = 0u; it < MAX_ITERATIONS; it++) {
        let t = (*i + 0.5) * dt;
        if t > t1 {
            return -1.0;
        }
        var any_occ = false;
        var next_t = INF;
        for (var k = 0u; k < MAX_LAYERS; k++) {
            if k >= n {
                break;
            }
            if t >= valid_until[k] {
                update_state(k, t);
            }
            if occupied[k] != 0u {
                any_occ = true;
            } else {
                next_t = min(next_t, valid_until[k]);
            }
        }
        if any_occ {
            return t;
        }
        if next_t >= INF {
            return -1.0;
        }
        // Jump to the first sample some layer might have density at.
        *i = max(ceil(next_t / dt - 0.5), *i + 1.0);
    }
    return -1.0;
}

fn srgb_to_linear(c: vec3<f32>) -> vec3<f32> {
    let lo = c / 12.92;
    let hi = pow((c + vec3<f32>(0.055)) / 1.055, vec3<f32>(2.4));
    return select(hi, lo, c <= vec3<f32>(0.04045));
}

// The NDC ray (origin, unit direction) of a world ray, as
// src/camera/ndc.rs `Ndc::ray`: the origin moved along the ray to the near
// plane z = -near, then both projected.
fn ndc_ray(o_world: vec3<f32>, d_world: vec3<f32>) -> array<vec3<f32>, 2> {
    let near = view.ndc.y;
    let s = view.ndc.zw;
    let dz = min(d_world.z, -1e-6);
    let d = vec3<f32>(d_world.xy, dz);
    let t = -(near + o_world.z) / dz;
    let o = o_world + t * d;
    let oz = -near;
    let origin = vec3<f32>(-s * o.xy / oz, -1.0);
    let dir = vec3<f32>(-s * (d.xy / dz - o.xy / oz), -2.0 * near / oz);
    return array<vec3<f32>, 2>(origin, normalize(dir));
}

// The march writes to two textures that the composite pass
// (shaders/composite.wgsl) draws into the view: the colour (linear) and
// the clip-space depth.
struct MarchOutput {
    @location(0) color: vec4<f32>,
    @location(1) depth: vec4<f32>,
};

@fragment
fn fragment(@builtin(position) pos: vec4<f32>) -> MarchOutput {
    // Pixel centre in the march target's pixels (v grows downwards); the
    // intrinsics are those of the target's size.
    let uv = pos.xy;
    let kk = view.intrinsics;
    let d_cam = vec3<f32>((uv.x - kk.z) / kk.x, -(uv.y - kk.w) / kk.y, -1.0);
    let c2w = view.c2w;
    let world_dir = normalize(mat3x3<f32>(c2w[0].xyz, c2w[1].xyz, c2w[2].xyz) * d_cam);
    var origin = c2w[3].xyz;
    var dir = world_dir;
    let ndc = view.ndc.x > 0.5;
    if ndc {
        let r = ndc_ray(origin, world_dir);
        origin = r[0];
        dir = r[1];
    }
    let n = min(view.counts.x, MAX_LAYERS);
    let min_t = view.march.y;

    // Rays in each layer's frame, the union of the layers' intervals and
    // the ray's cell distance (render::cell_distance) in the finest layer
    // it meets.
    var t0 = INF;
    var t1 = -INF;
    var cell = INF;
    for (var k = 0u; k < MAX_LAYERS; k++) {
        if k >= n {
            break;
        }
        let m = layers[k].to_local;
        let o = (m * vec4<f32>(origin, 1.0)).xyz;
        let d = (m * vec4<f32>(dir, 0.0)).xyz;
        lo_origin[k] = o;
        lo_dir[k] = d;
        valid_until[k] = -1.0;
        occupied[k] = 0u;
        let info = layers[k].info;
        linfo[k] = info;
        finfo[k] = fields[info.x];
        lbox_min[k] = layers[k].box_min.xyz;
        lbox_max[k] = layers[k].box_max.xyz;
#ifdef HIGHLIGHT
        lhighlight[k] = layers[k].highlight.x;
#endif
        let hit = intersect(lbox_min[k], lbox_max[k], o, d);
        if hit.y > hit.x {
            t0 = min(t0, hit.x);
            t1 = max(t1, hit.y);
            let f = finfo[k];
            let spacing = (f.bounds_max.xyz - f.bounds_min.xyz) / (vec3<f32>(f.res.xyz) - vec3<f32>(1.0));
            cell = min(cell, 1.0 / length(d / spacing));
        }
    }
    let dt = select(view.march.x * cell, view.march.x, view.march.z > 0.5);
    ray_dt = dt;

    var trans = 1.0;
    var color = vec3<f32>(0.0);
    var t_half = -1.0;
    if t1 > t0 {
        var i = max(ceil(t0 / dt - 0.5), 0.0);
        for (var it = 0u; it < MAX_ITERATIONS; it++) {
            // Advance to the next sample where some layer may have density.
            // This inner loop only reads the skip grids: on SIMD CPUs
            // (lavapipe) every lane of a group pays for each iteration of
            // the outer loop, so lanes crossing empty space wait here
            // cheaply instead of costing the others a full sample each.
            let t = next_sample(n, &i, t1);
            if t < 0.0 || trans < min_t {
                break;
            }
            i += 1.0;
            let sum = densities(n, t);
            if sum <= 0.0 {
                continue;
            }
            let alpha = 1.0 - exp(-sum * dt);
            let w = trans * alpha;
            if w > 0.0 {
                color += w * shade(n, t, sum);
            }
            trans *= 1.0 - alpha;
            if t_half < 0.0 && trans < 0.5 {
                t_half = t;
            }
        }
    }
    var out: MarchOutput;
    let c = color + trans * view.background.xyz;
    out.color = vec4<f32>(srgb_to_linear(clamp(c, vec3<f32>(0.0), vec3<f32>(1.0))), 1.0);
    // Depth of the point where transmittance falls below one half, so
    // meshes and gizmos drawn later compose with the volume; far otherwise
    // (reverse-Z: 0 is infinitely far).
    out.depth = vec4<f32>(0.0);
    if t_half > 0.0 {
        var p = origin + t_half * dir;
        var finite = true;
        if ndc {
            finite = p.z < 1.0 - 1e-6;
            p = ndc_to_world(p, view.ndc);
        }
        let clip = view.clip_from_world * vec4<f32>(p, 1.0);
        if finite {
            out.depth = vec4<f32>(clamp(clip.z / clip.w, 0.0, 1.0));
        }
    }
    return out;
}
