// Shared by raymarch.wgsl and sh_bake.wgsl.
#define_import_path isrf::common

struct FieldInfo {
    // xyz bounds; w: activation shift
    bounds_min: vec4<f32>,
    // xyz bounds; w: activation kind (0 relu, 1 softplus)
    bounds_max: vec4<f32>,
    // points per axis at the level of detail shown, colour kind
    // (COLOR_SPARSE | COLOR_SH bits)
    res: vec4<u32>,
    // brick slot grid (word in aux), first pool slot, first z slice in
    // `indirection`, 0
    offsets: vec4<u32>,
    // skip dims xyz, skip offset
    skip: vec4<u32>,
    skip_cell: vec4<f32>,
};

const COLOR_SPARSE: u32 = 1u;

// The world point of an NDC point in front of z_ndc = 1
// (src/camera/ndc.rs `Ndc::to_world`); `ndc` is pack.rs `ndc_params`
// (on, near, 2f/W, 2f/H).
fn ndc_to_world(q: vec3<f32>, ndc: vec4<f32>) -> vec3<f32> {
    let z = 2.0 * ndc.y / (q.z - 1.0);
    return vec3<f32>(-q.xy * z / ndc.zw, z);
}

// Degree-2 real SH basis for a unit direction (src/field/sh.rs).
fn sh_basis(d: vec3<f32>) -> array<f32, 9> {
    let x = d.x;
    let y = d.y;
    let z = d.z;
    return array<f32, 9>(
        0.2820948,
        -0.4886025 * y,
        0.4886025 * z,
        -0.4886025 * x,
        1.0925484 * x * y,
        -1.0925484 * y * z,
        0.31539157 * (2.0 * z * z - x * x - y * y),
        -1.0925484 * x * z,
        0.5462742 * (x * x - y * y),
    );
}

// The SH logits (r, g, b) of the 27 coefficients in the seven pool texels
// t0..t6 (pack.rs `sh_texel`: channels 0..8 red, 9..17 green, 18..26 blue).
fn sh_dot(
    b: array<f32, 9>,
    t0: vec4<f32>,
    t1: vec4<f32>,
    t2: vec4<f32>,
    t3: vec4<f32>,
    t4: vec4<f32>,
    t5: vec4<f32>,
    t6: vec4<f32>,
) -> vec3<f32> {
    let r = b[0] * t0.x + b[1] * t0.y + b[2] * t0.z + b[3] * t0.w + b[4] * t1.x + b[5] * t1.y + b[6] * t1.z
        + b[7] * t1.w + b[8] * t2.x;
    let g = b[0] * t2.y + b[1] * t2.z + b[2] * t2.w + b[3] * t3.x + b[4] * t3.y + b[5] * t3.z + b[6] * t3.w
        + b[7] * t4.x + b[8] * t4.y;
    let bl = b[0] * t4.z + b[1] * t4.w + b[2] * t5.x + b[3] * t5.y + b[4] * t5.z + b[5] * t5.w + b[6] * t6.x
        + b[7] * t6.y + b[8] * t6.z;
    return vec3<f32>(r, g, bl);
}

// The colour of interpolated SH logits whose stored corners' weights sum
// to `wsum`: none stored gives black; sparse appearances renormalise by it
// (as `ChannelGrid::sample`); then a sigmoid.
fn sh_colour(f: FieldInfo, logits: vec3<f32>, wsum: f32) -> vec3<f32> {
    var acc = logits;
    if wsum <= 1e-6 {
        acc = vec3<f32>(0.0);
    } else if (f.res.w & COLOR_SPARSE) != 0u {
        acc = acc / wsum;
    }
    return vec3<f32>(1.0) / (vec3<f32>(1.0) + exp(-acc));
}
