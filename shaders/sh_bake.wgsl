// Bakes the view-dependent colour of SH fields for one view: per pool
// texel of a baked field (src/app/gpu/pack.rs `bake_cameras`), the SH
// logits for the direction from the camera to its grid point, and its
// stored weight (channel 27). The march (raymarch.wgsl `baked_at`) then
// samples one texture per shaded sample instead of seven: on lavapipe the
// seven SH samples were three quarters of a trained field's frame.
//
// One workgroup of 64 invocations bakes an eighth of a brick; workgroups
// (y, z) number the pool slots (y fastest), as pack.rs `bake_dispatch`.

#import isrf::common::{FieldInfo, sh_basis, sh_dot, ndc_to_world}

struct Bake {
    // pool bricks per axis (xyz), pool slots to bake
    pool: vec4<u32>,
    // NDC scenes (pack.rs `ndc_params`): 1 when on, near, 2f/W, 2f/H
    ndc: vec4<f32>,
    // per field (pack.rs MAX_LAYERS of them): the camera position in the
    // field's frame, w = 1 where the field is baked
    cams: array<vec4<f32>, 16>,
};

@group(0) @binding(0) var<uniform> bake: Bake;
@group(0) @binding(1) var<storage, read> fields: array<FieldInfo>;
// Per pool slot: its field (0xffffffff: none) and brick position in the
// field's brick grid, x | y << 10 | z << 20 (pack.rs `pool_owners`).
@group(0) @binding(2) var<storage, read> owners: array<vec2<u32>>;
@group(0) @binding(3) var sh0: texture_3d<f32>;
@group(0) @binding(4) var sh1: texture_3d<f32>;
@group(0) @binding(5) var sh2: texture_3d<f32>;
@group(0) @binding(6) var sh3: texture_3d<f32>;
@group(0) @binding(7) var sh4: texture_3d<f32>;
@group(0) @binding(8) var sh5: texture_3d<f32>;
@group(0) @binding(9) var sh6: texture_3d<f32>;
@group(0) @binding(10) var baked: texture_storage_3d<rgba16float, write>;

// pool.rs BRICK_CELLS, BRICK.
const BRICK_CELLS: u32 = 7u;
const BRICK: u32 = 8u;

fn direction(v: vec3<f32>) -> vec3<f32> {
    let len = length(v);
    return select(vec3<f32>(0.0, 0.0, -1.0), v / len, len > 0.0);
}

// In an NDC scene (src/camera/ndc.rs) the march's rays are the NDC images
// of the world rays from the camera (`cam`, world): at NDC point `q`, the
// direction of the one through the world point P = to_world(q) is the
// NDC map's Jacobian at P applied to P - cam.
fn ndc_direction(q: vec3<f32>, cam: vec3<f32>) -> vec3<f32> {
    if q.z >= 1.0 - 1e-6 {
        return vec3<f32>(0.0, 0.0, 1.0);
    }
    let n = bake.ndc.y;
    let s = bake.ndc.zw;
    let p = ndc_to_world(q, bake.ndc);
    let z = p.z;
    let d = p - cam;
    let j = vec3<f32>(-s * (d.xy / z - p.xy * d.z / (z * z)), -2.0 * n * d.z / (z * z));
    return direction(j);
}

@compute @workgroup_size(64)
fn bake_colours(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let slot = wg.y + wg.z * groups.y;
    if slot >= bake.pool.w {
        return;
    }
    let owner = owners[slot];
    if owner.x >= 16u || bake.cams[owner.x].w == 0.0 {
        return;
    }
    let f = fields[owner.x];
    let cam = bake.cams[owner.x].xyz;
    // The texel in its brick, the brick in the field, the grid point.
    let t = wg.x * 64u + lane;
    let l = vec3<u32>(t % BRICK, t / BRICK % BRICK, t / (BRICK * BRICK));
    let b = vec3<u32>(owner.y & 1023u, (owner.y >> 10u) & 1023u, (owner.y >> 20u) & 1023u);
    let g = min(b * BRICK_CELLS + l, f.res.xyz - vec3<u32>(1u));
    let n = max(vec3<f32>(f.res.xyz) - vec3<f32>(1.0), vec3<f32>(1.0));
    let p = f.bounds_min.xyz + vec3<f32>(g) / n * (f.bounds_max.xyz - f.bounds_min.xyz);
    var dir = direction(p - cam);
    if bake.ndc.x > 0.5 {
        dir = ndc_direction(p, cam);
    }
    let pb = vec3<u32>(slot % bake.pool.x, slot / bake.pool.x % bake.pool.y, slot / (bake.pool.x * bake.pool.y));
    let texel = vec3<i32>(pb * BRICK + l);
    let t6 = textureLoad(sh6, texel, 0);
    let logits = sh_dot(
        sh_basis(dir),
        textureLoad(sh0, texel, 0),
        textureLoad(sh1, texel, 0),
        textureLoad(sh2, texel, 0),
        textureLoad(sh3, texel, 0),
        textureLoad(sh4, texel, 0),
        textureLoad(sh5, texel, 0),
        t6,
    );
    textureStore(baked, texel, vec4<f32>(logits, t6.w));
}
