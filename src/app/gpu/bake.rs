//! The SH bake: before a view marches, a compute pass evaluates the SH
//! colour of every pool texel of the fields it shows for the direction from
//! the camera (shaders/sh_bake.wgsl), into a per-view texture the march
//! samples once per shaded sample instead of sampling seven SH textures.
//! On lavapipe those seven samples were three quarters of a trained
//! field's frame; a desktop GPU saves the same texture traffic.
//!
//! Which layers use the bake is decided with the layers
//! ([`pack::mark_baked`]); the camera per field with the view
//! ([`pack::bake_params`]).

use super::pack::{self, GpuBake, GpuLayer};
use super::{AtlasTextures, RayMarchShaders};
use bevy::prelude::*;
use bevy::render::render_resource::binding_types::{
    storage_buffer_read_only_sized, texture_3d, texture_storage_3d, uniform_buffer_sized,
};
use bevy::render::render_resource::{
    BindGroup, BindGroupEntries, BindGroupLayoutDescriptor, BindGroupLayoutEntries, BufferInitDescriptor, BufferUsages,
    CachedComputePipelineId, ComputePipelineDescriptor, PipelineCache, ShaderStages, StorageTextureAccess,
    TextureFormat, TextureSampleType, TextureUsages, TextureView,
};
use bevy::render::renderer::RenderDevice;
use std::num::NonZero;

/// The baked colours' format: f16 logits (as the SH coefficients) and the
/// stored weight.
const FORMAT: TextureFormat = TextureFormat::Rgba16Float;

#[derive(Resource)]
pub(super) struct BakePipeline {
    layout: BindGroupLayoutDescriptor,
    pub id: CachedComputePipelineId,
}

pub(super) fn init_bake_pipeline(mut commands: Commands, shaders: Res<RayMarchShaders>, cache: Res<PipelineCache>) {
    let sh = || texture_3d(TextureSampleType::Float { filterable: true });
    let layout = BindGroupLayoutDescriptor::new(
        "isrf_sh_bake_layout",
        &BindGroupLayoutEntries::sequential(
            ShaderStages::COMPUTE,
            (
                uniform_buffer_sized(false, NonZero::new(size_of::<GpuBake>() as u64)),
                storage_buffer_read_only_sized(false, None),
                storage_buffer_read_only_sized(false, None),
                sh(),
                sh(),
                sh(),
                sh(),
                sh(),
                sh(),
                sh(),
                texture_storage_3d(FORMAT, StorageTextureAccess::WriteOnly),
            ),
        ),
    );
    let id = cache.queue_compute_pipeline(ComputePipelineDescriptor {
        label: Some("isrf_sh_bake_pipeline".into()),
        layout: vec![layout.clone()],
        immediate_size: 0,
        shader: shaders.bake.clone(),
        shader_defs: vec![],
        entry_point: Some("bake_colours".into()),
        zero_initialize_workgroup_memory: false,
    });
    commands.insert_resource(BakePipeline { layout, id });
}

/// A baked-colour texture of `size` texels (the pool's).
pub(super) fn bake_texture(device: &RenderDevice, size: [usize; 3]) -> TextureView {
    let usage = TextureUsages::STORAGE_BINDING | TextureUsages::TEXTURE_BINDING;
    device
        .create_texture(&super::texture_3d_desc("isrf_baked_colours", FORMAT, size, usage))
        .create_view(&default())
}

/// A view's baked colours, at the pool's size.
#[derive(Component, Clone)]
pub(super) struct BakedColours {
    pub size: [usize; 3],
    pub view: TextureView,
    /// What the last bake was for besides the camera (layers, uploads,
    /// NDC; see [`scene_key`]); empty before the first.
    pub scene: Vec<u8>,
}

/// The inputs of a bake other than the camera position: a moving view may
/// reuse a bake of the same `scene_key` ([`reuse_while_moving`]).
pub(super) fn scene_key(layers: &[GpuLayer], generation: u64, ndc: [f32; 4]) -> Vec<u8> {
    let mut key = bytemuck::cast_slice::<GpuLayer, u8>(layers).to_vec();
    key.extend_from_slice(&generation.to_le_bytes());
    key.extend_from_slice(bytemuck::cast_slice(&ndc));
    key
}

/// Whether a march may use the view's last bake instead of baking again:
/// only while the view moves (a reduced-resolution march) and the scene is
/// the one baked. The bake costs as much as a half-resolution march of a
/// trained field on lavapipe (it touches every pool texel), and SH colour
/// changes little over one drag; the full-resolution march at rest bakes
/// for its exact camera.
pub(super) fn reuse_while_moving(last: Option<&BakedColours>, scene: &[u8], full_resolution: bool) -> bool {
    !full_resolution && last.is_some_and(|b| !b.scene.is_empty() && b.scene == scene)
}

/// This march's bake: its bind group and workgroup counts.
pub(super) struct BakeJob {
    pub bind_group: BindGroup,
    pub groups: [u32; 3],
}

/// Whether the bake pipeline has compiled (a compile error goes to the
/// status line as the march's do).
pub(super) fn ready(cache: &PipelineCache, pipeline: &BakePipeline, status: &super::SharedStatus) -> bool {
    if cache.get_compute_pipeline(pipeline.id).is_some() {
        return true;
    }
    if let Some(e) = super::compile_failure(cache.get_compute_pipeline_state(pipeline.id)) {
        let msg = format!("the SH bake shader failed to compile: {e}");
        status.update(|s| s.error = Some(msg));
    }
    false
}

/// The bake for a camera at `origin` (world) into `target` (for scenes with
/// baked layers, `MarchKey::baked`).
pub(super) fn job(
    device: &RenderDevice,
    cache: &PipelineCache,
    pipeline: &BakePipeline,
    layers: &[GpuLayer],
    fields: &bevy::render::render_resource::Buffer,
    atlas: &AtlasTextures,
    target: &TextureView,
    origin: Vec3,
    ndc: [f32; 4],
) -> BakeJob {
    let origin = glam::Vec3::from_array(origin.to_array());
    let params = GpuBake {
        ndc,
        ..pack::bake_params(layers, atlas.bricks, atlas.slots, origin)
    };
    let uniform = device.create_buffer_with_data(&BufferInitDescriptor {
        label: Some("isrf_sh_bake"),
        contents: bytemuck::bytes_of(&params),
        usage: BufferUsages::UNIFORM,
    });
    let sh = &atlas.sh;
    let bind_group = device.create_bind_group(
        "isrf_sh_bake_bind_group",
        &cache.get_bind_group_layout(&pipeline.layout),
        &BindGroupEntries::sequential((
            uniform.as_entire_binding(),
            fields.as_entire_binding(),
            atlas.owners.as_entire_binding(),
            &sh[0],
            &sh[1],
            &sh[2],
            &sh[3],
            &sh[4],
            &sh[5],
            &sh[6],
            target,
        )),
    );
    BakeJob {
        bind_group,
        groups: pack::bake_dispatch(atlas.slots),
    }
}
