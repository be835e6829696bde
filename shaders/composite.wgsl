// isrf composite pass: draws the ray marcher's last image (colour and
// depth textures, see raymarch.wgsl) into the view, every frame. The march
// itself runs only when what it shows changed, possibly at a lower
// resolution while the view moves; this pass upsamples the colour
// bilinearly and takes the depth of the nearest march pixel, so that meshes
// and gizmos drawn later compose with the volume.

#import bevy_core_pipeline::fullscreen_vertex_shader::FullscreenVertexOutput

@group(0) @binding(0) var march_color: texture_2d<f32>;
@group(0) @binding(1) var march_depth: texture_2d<f32>;
@group(0) @binding(2) var linear_sampler: sampler;

struct FragmentOutput {
    @location(0) color: vec4<f32>,
    @builtin(frag_depth) depth: f32,
};

@fragment
fn fragment(in: FullscreenVertexOutput) -> FragmentOutput {
    var out: FragmentOutput;
    // The march target covers the viewport exactly, so the viewport's uv
    // addresses it; at full resolution this reads each pixel's own texel.
    out.color = textureSampleLevel(march_color, linear_sampler, in.uv, 0.0);
    let dims = textureDimensions(march_depth);
    let texel = min(vec2<u32>(in.uv * vec2<f32>(dims)), dims - vec2<u32>(1u));
    out.depth = textureLoad(march_depth, texel, 0).x;
    return out;
}
