//! The custom render pass: a WGSL ray marcher (`shaders/raymarch.wgsl`) that
//! draws every layer of a [`Scene`] into each camera marked with
//! [`RayMarchCamera`], before bevy's opaque pass, writing colour and depth so
//! that meshes and gizmos drawn afterwards compose with the volume.
//!
//! The march renders into per-view textures, and only when what it shows
//! changed (camera, scene, masks, size); a cheap composite pass
//! (`shaders/composite.wgsl`) draws them into the view every frame. A still
//! view thus costs nothing, and [`RayMarchCamera::render_scale`] lets the
//! editor march fewer pixels while the view moves (see [`view`]).
//!
//! Flow (as bevy's own render features): the main world holds a
//! [`MarchScene`] resource (the library's `render::Scene`, shared with `Arc`s,
//! so extraction copies pointers); `prepare_scene` packs and uploads the
//! occupied bricks of the fields' grids when the set of fields changes
//! (keyed by the fields' `Arc` identity; see [`pool`] and [`pack`] for the
//! layout, within the device's limits and [`MarchScene::memory_budget`],
//! at a coarser level of detail when the scene does not fit) and
//! re-uploads only the mask bitmaps whose contents changed;
//! `view::prepare_views` decides per view whether to march and builds the
//! bind groups; `view::raymarch_pass` runs in the `Core3d` schedule.

mod bake;
pub mod pack;
pub mod pool;
mod view;

use crate::field::Field;
use crate::render::{Scene, Step};
use bevy::asset::{Assets, Handle};
use bevy::core_pipeline::core_3d::main_opaque_pass_3d;
use bevy::core_pipeline::{Core3d, Core3dSystems, FullscreenShader};
use bevy::prelude::*;
use bevy::render::error_handler::{ErrorType, RenderError, RenderErrorHandler, RenderErrorPolicy};
use bevy::render::extract_component::{ExtractComponent, ExtractComponentPlugin};
use bevy::render::extract_resource::{ExtractResource, ExtractResourcePlugin};
use bevy::render::render_resource::binding_types::{
    sampler, storage_buffer_read_only_sized, texture_3d, uniform_buffer_sized,
};
use bevy::render::render_resource::{
    AddressMode, BindGroupLayoutDescriptor, BindGroupLayoutEntries, Buffer, BufferInitDescriptor, BufferUsages,
    CachedPipelineState, ColorTargetState, ColorWrites, Extent3d, FilterMode, FragmentState, RenderPipelineDescriptor,
    Sampler, SamplerBindingType, SamplerDescriptor, ShaderStages, SpecializedRenderPipeline,
    SpecializedRenderPipelines, TextureDescriptor, TextureDimension, TextureFormat, TextureSampleType, TextureUsages,
    TextureView,
};
use bevy::render::renderer::{RenderDevice, RenderQueue};
use bevy::render::{Render, RenderApp, RenderStartup, RenderSystems};
use bevy::shader::{Shader, ShaderCacheError, ShaderDefVal};
use pack::{GpuLayer, GpuView, MaskRef, Overlay, PackedField};
use std::num::NonZero;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// What the ray marcher draws (main world; extracted every frame).
#[derive(Resource, Clone, Debug)]
pub struct MarchScene {
    pub scene: Option<Arc<Scene>>,
    /// Editor overlay per layer (tint the selected object, dim others).
    pub overlay: Vec<Overlay>,
    /// Sample spacing along each ray (the CPU renderer's default: half a cell).
    pub step: Step,
    pub min_transmittance: f32,
    /// The NDC space of a forward-facing capture (LLFF): when set, every
    /// pixel's world ray is mapped into it (as [`crate::camera::Camera::ray`]
    /// does for a camera with NDC) and the scene is marched there, since
    /// such fields live in NDC space.
    pub ndc: Option<crate::camera::Ndc>,
    /// Bytes of GPU memory the pool textures may take; beyond it the view
    /// shows a coarser level of detail ([`pool::plan`]).
    pub memory_budget: usize,
}

/// Default [`MarchScene::memory_budget`]: 2 GiB, or `ISRF_GPU_BUDGET_MB`.
pub fn default_memory_budget() -> usize {
    std::env::var("ISRF_GPU_BUDGET_MB")
        .ok()
        .and_then(|v| v.trim().parse::<usize>().ok())
        .map_or(2 << 30, |mb| mb << 20)
}

impl Default for MarchScene {
    fn default() -> Self {
        MarchScene {
            scene: None,
            overlay: Vec::new(),
            step: Step::default(),
            min_transmittance: 1e-4,
            ndc: None,
            memory_budget: default_memory_budget(),
        }
    }
}

impl ExtractResource for MarchScene {
    type Source = MarchScene;
    fn extract_resource(source: &Self::Source) -> Self {
        source.clone()
    }
}

/// Marks a camera that draws the ray-marched scene.
#[derive(Component, Clone, Copy, Debug, ExtractComponent)]
pub struct RayMarchCamera {
    /// fx, fy, cx, cy in pixels: overrides the ones derived from the
    /// camera's perspective projection, e.g. to match an `isrf` camera
    /// exactly.
    pub intrinsics: Option<[f32; 4]>,
    /// Fraction of the viewport's width and height that the march renders
    /// (clamped to [1/8, 1]); the composite pass upsamples it. 1 draws
    /// the same image as the CPU renderer.
    pub render_scale: f32,
}

impl Default for RayMarchCamera {
    fn default() -> Self {
        RayMarchCamera {
            intrinsics: None,
            render_scale: 1.0,
        }
    }
}

/// Shared between the worlds: what the render world did last.
#[derive(Clone, Debug, Default)]
pub struct RenderStatus {
    /// Frames in which the pass drew (pipeline compiled, scene uploaded).
    pub frames_drawn: u64,
    /// Frames among them that ran the ray march (the others showed the
    /// previous march unchanged).
    pub marches: u64,
    /// Pointer identity of the scene the last drawn frame showed.
    pub scene_drawn: usize,
    /// Whether the last drawn frame showed a full-resolution march (not
    /// the upsampled one of a moving view).
    pub full_resolution: bool,
    /// Last upload or packing error (shown in the UI).
    pub error: Option<String>,
    /// Why the view shows a coarser level of detail than the fields have
    /// (shown in the UI); `None` at full detail.
    pub detail: Option<String>,
    /// Grid points per pool texel of the fields shown (1: full detail).
    pub stride: usize,
    /// Bytes of the uploaded pool textures.
    pub pool_bytes: usize,
    /// A GPU error (wgpu validation, out of memory) reported while drawing
    /// the fields of upload generation `.0`: that scene is not drawn again
    /// until the fields change. The editor keeps running.
    pub gpu_error: Option<(u64, String)>,
    /// Milliseconds spent uploading grids, last time any were uploaded.
    pub upload_ms: f64,
    pub uploads: u64,
    /// Bitmaps re-uploaded in total (counting only changed ones).
    pub bitmap_uploads: u64,
}

#[derive(Resource, Clone, Default)]
pub struct SharedStatus(pub Arc<Mutex<RenderStatus>>);

impl SharedStatus {
    pub fn get(&self) -> RenderStatus {
        self.0.lock().map(|s| s.clone()).unwrap_or_default()
    }
    fn update(&self, f: impl FnOnce(&mut RenderStatus)) {
        if let Ok(mut s) = self.0.lock() {
            f(&mut s);
        }
    }
}

pub struct RayMarchPlugin;

impl Plugin for RayMarchPlugin {
    fn build(&self, app: &mut App) {
        // ISRF_RAYMARCH_WGSL=path loads the shader from a file instead of the
        // built-in copy (for shader development without rebuilding).
        let source = std::env::var("ISRF_RAYMARCH_WGSL")
            .ok()
            .and_then(|p| std::fs::read_to_string(p).ok())
            .unwrap_or_else(|| include_str!("../../../shaders/raymarch.wgsl").to_string());
        let mut shaders = app.world_mut().resource_mut::<Assets<Shader>>();
        let shader = shaders.add(Shader::from_wgsl(source, "shaders/raymarch.wgsl"));
        let composite = shaders.add(Shader::from_wgsl(
            include_str!("../../../shaders/composite.wgsl"),
            "shaders/composite.wgsl",
        ));
        let common = shaders.add(Shader::from_wgsl(
            include_str!("../../../shaders/common.wgsl"),
            "shaders/common.wgsl",
        ));
        let bake = shaders.add(Shader::from_wgsl(
            include_str!("../../../shaders/sh_bake.wgsl"),
            "shaders/sh_bake.wgsl",
        ));
        let status = SharedStatus::default();
        app.init_resource::<MarchScene>()
            .insert_resource(status.clone())
            .insert_resource(RenderErrorHandler(keep_running_on_gpu_errors))
            .add_plugins((
                ExtractResourcePlugin::<MarchScene>::default(),
                ExtractComponentPlugin::<RayMarchCamera>::default(),
            ));
        let Some(render_app) = app.get_sub_app_mut(RenderApp) else {
            return;
        };
        render_app
            .insert_resource(RayMarchShaders {
                march: shader,
                composite,
                bake,
                _common: common,
            })
            .insert_resource(status)
            .init_resource::<GpuSceneCache>()
            .init_resource::<SpecializedRenderPipelines<RayMarchPipeline>>()
            .init_resource::<SpecializedRenderPipelines<view::CompositePipeline>>()
            .add_systems(
                RenderStartup,
                (init_pipeline, view::init_composite_pipeline, bake::init_bake_pipeline),
            )
            .add_systems(
                Render,
                (
                    prepare_scene.in_set(RenderSystems::PrepareResources),
                    view::prepare_views.in_set(RenderSystems::PrepareBindGroups),
                ),
            )
            .add_systems(
                Core3d,
                view::raymarch_pass
                    .in_set(Core3dSystems::MainPass)
                    .before(main_opaque_pass_3d),
            );
    }
}

/// bevy quits the app on any wgpu error by default. An editor must not
/// lose the user's session to a drawing problem: the error goes to the
/// status line, and the scene that caused it is not drawn again until its
/// fields change (drawing it again would repeat the error every frame).
/// Only a lost device stops rendering (the app keeps running, so the edit
/// log can still be saved).
fn keep_running_on_gpu_errors(error: &RenderError, main: &mut World, render: &mut World) -> RenderErrorPolicy {
    let generation = render.get_resource::<GpuSceneCache>().map_or(0, |c| c.generation);
    let first_line = error.description.lines().find(|l| !l.trim().is_empty()).unwrap_or("");
    let msg = format!("GPU error ({:?}): {}", error.ty, first_line.trim());
    if let Some(status) = main.get_resource::<SharedStatus>() {
        status.update(|s| {
            s.gpu_error = Some((generation, msg.clone()));
            s.error = Some(msg);
        });
    }
    match error.ty {
        ErrorType::DeviceLost => RenderErrorPolicy::StopRendering,
        _ => RenderErrorPolicy::Ignore,
    }
}

#[derive(Resource)]
struct RayMarchShaders {
    march: Handle<Shader>,
    composite: Handle<Shader>,
    bake: Handle<Shader>,
    /// shaders/common.wgsl, which the others import (held so that it stays
    /// loaded).
    _common: Handle<Shader>,
}

#[derive(Resource)]
struct RayMarchPipeline {
    layout: BindGroupLayoutDescriptor,
    shader: Handle<Shader>,
    fullscreen: FullscreenShader,
}

fn init_pipeline(mut commands: Commands, shaders: Res<RayMarchShaders>, fullscreen: Res<FullscreenShader>) {
    let storage = || storage_buffer_read_only_sized(false, None);
    let layout = BindGroupLayoutDescriptor::new(
        "isrf_raymarch_layout",
        &BindGroupLayoutEntries::sequential(
            ShaderStages::FRAGMENT,
            (
                uniform_buffer_sized(false, NonZero::new(size_of::<GpuView>() as u64)),
                storage(),
                storage(),
                storage(),
                storage(),
                // The pool textures: density, RGB, then the SH textures.
                texture_3d(TextureSampleType::Float { filterable: true }),
                texture_3d(TextureSampleType::Float { filterable: true }),
                texture_3d(TextureSampleType::Float { filterable: true }),
                texture_3d(TextureSampleType::Float { filterable: true }),
                texture_3d(TextureSampleType::Float { filterable: true }),
                texture_3d(TextureSampleType::Float { filterable: true }),
                texture_3d(TextureSampleType::Float { filterable: true }),
                texture_3d(TextureSampleType::Float { filterable: true }),
                texture_3d(TextureSampleType::Float { filterable: true }),
                sampler(SamplerBindingType::Filtering),
                texture_3d(TextureSampleType::Uint),
                storage(),
                // The view's baked SH colours.
                texture_3d(TextureSampleType::Float { filterable: true }),
            ),
        ),
    );
    commands.insert_resource(RayMarchPipeline {
        layout,
        shader: shaders.march.clone(),
        fullscreen: fullscreen.clone(),
    });
}

/// The march's colour target (linear, filterable for the upsampling).
const MARCH_COLOR_FORMAT: TextureFormat = TextureFormat::Rgba16Float;
/// The march's depth target (the clip-space depth as a colour).
const MARCH_DEPTH_FORMAT: TextureFormat = TextureFormat::R32Float;

/// A pipeline's compile failure, to report; `None` while it is queued,
/// compiling or waiting for a shader asset to load. bevy keeps a pipeline
/// queued before its shader has loaded in `Err(ShaderNotLoaded)` and
/// queues it again the next frame; on a busy machine that lasts a frame or
/// more, and reporting it failed a headless render that would have drawn.
fn compile_failure(state: &CachedPipelineState) -> Option<&ShaderCacheError> {
    match state {
        CachedPipelineState::Err(
            ShaderCacheError::ShaderNotLoaded(_) | ShaderCacheError::ShaderImportNotYetAvailable,
        ) => None,
        CachedPipelineState::Err(e) => Some(e),
        _ => None,
    }
}

/// The bound on the layer count a march pipeline is specialised for: 1, 2,
/// 4 or [`pack::MAX_LAYERS`] (see the shader's `MAX_LAYERS`).
fn layer_bound(layers: usize) -> u32 {
    match layers {
        0 | 1 => 1,
        2 => 2,
        3 | 4 => 4,
        _ => pack::MAX_LAYERS as u32,
    }
}

/// What a march pipeline is specialised for: the bound on the layer count
/// and the shader code the scene needs (shader defs). Code a scene does not
/// use is left out because on lavapipe its mere presence slows the whole
/// march (register pressure): on the plain tabletop field, leaving out the
/// SH path, the masks and the colour edits / overlay made frames 2× faster.
/// Variants are compiled when first needed (the view keeps its last image
/// meanwhile): compiling pipelines ahead, concurrently with drawing, made
/// lavapipe's marches come out empty at times.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
struct MarchKey {
    /// [`layer_bound`] of the layer count.
    bound: u32,
    /// Some layer's field has RGB colours (`RGB`).
    rgb: bool,
    /// Some layer's field has SH colours that it evaluates per sample (`SH`).
    sh: bool,
    /// Some layer's SH colours come from the view's bake (`BAKED`).
    baked: bool,
    /// Some layer has a keep or remove mask (`MASKS`).
    masks: bool,
    /// Some layer has an appearance edit (`COLOR_EDIT`).
    edits: bool,
    /// Some layer is tinted or dimmed by the editor (`OVERLAY`).
    overlay: bool,
    /// Some layer has a highlight mask (`HIGHLIGHT`).
    highlight: bool,
}

impl MarchKey {
    /// The key for the packed layers of a scene whose fields are `fields`.
    fn of(layers: &[GpuLayer], fields: &[pack::GpuField]) -> Self {
        let colour_kind = |l: &GpuLayer| fields.get(l.info[0] as usize).map_or(0, |f| f.res[3]);
        let flags = |bits: u32| layers.iter().any(|l| l.info[3] & bits != 0);
        let highlight = layers.iter().any(|l| l.highlight[0] != 0);
        let any_sh = layers.iter().any(|l| colour_kind(l) & pack::COLOR_SH != 0);
        let baked = |l: &GpuLayer| l.info[3] & pack::LAYER_BAKED != 0;
        MarchKey {
            bound: layer_bound(layers.len()),
            // (A scene without layers draws the background with the RGB variant.)
            rgb: !any_sh || layers.iter().any(|l| colour_kind(l) & pack::COLOR_SH == 0),
            sh: layers.iter().any(|l| colour_kind(l) & pack::COLOR_SH != 0 && !baked(l)),
            baked: layers.iter().any(baked),
            masks: layers.iter().any(|l| l.info[1] != pack::MASK_ALL),
            edits: flags(pack::LAYER_COLOR_EDIT),
            overlay: highlight || flags(pack::LAYER_HIGHLIGHT | pack::LAYER_DIM),
            highlight,
        }
    }

    fn shader_defs(self) -> Vec<ShaderDefVal> {
        let flags = [
            (self.rgb, "RGB"),
            (self.sh, "SH"),
            (self.baked, "BAKED"),
            (self.masks, "MASKS"),
            (self.edits, "COLOR_EDIT"),
            (self.overlay, "OVERLAY"),
            (self.highlight, "HIGHLIGHT"),
        ];
        std::iter::once(ShaderDefVal::UInt("MAX_LAYERS".into(), self.bound))
            .chain(flags.into_iter().filter(|f| f.0).map(|f| f.1.into()))
            .collect()
    }
}

/// An opaque colour target of `format` (the passes overwrite every pixel).
fn opaque_target(format: TextureFormat) -> Option<ColorTargetState> {
    Some(ColorTargetState {
        format,
        blend: None,
        write_mask: ColorWrites::ALL,
    })
}

impl SpecializedRenderPipeline for RayMarchPipeline {
    type Key = MarchKey;
    fn specialize(&self, key: Self::Key) -> RenderPipelineDescriptor {
        RenderPipelineDescriptor {
            label: Some("isrf_raymarch_pipeline".into()),
            layout: vec![self.layout.clone()],
            vertex: self.fullscreen.to_vertex_state(),
            fragment: Some(FragmentState {
                shader: self.shader.clone(),
                shader_defs: key.shader_defs(),
                entry_point: Some("fragment".into()),
                targets: vec![opaque_target(MARCH_COLOR_FORMAT), opaque_target(MARCH_DEPTH_FORMAT)],
            }),
            ..default()
        }
    }
}

struct FieldSlot {
    /// The scene's field (its identity).
    field: Arc<Field>,
    /// What is drawn of it ([`pack::drawn_field`]).
    drawn: Arc<Field>,
    packed: PackedField,
}

/// Render-world GPU copies of the scene's grids, reused across frames.
#[derive(Resource, Default)]
struct GpuSceneCache {
    fields: Vec<FieldSlot>,
    /// The fields' records as uploaded (absolute offsets).
    field_infos: Vec<pack::GpuField>,
    /// The level of detail and brick layout uploaded.
    plan: Option<pool::PoolPlan>,
    /// The budget `plan` was made for.
    budget: usize,
    /// Fields (pointers) and budget that could not be uploaded, and why.
    failed: Option<(Vec<usize>, usize, String)>,
    bitmaps: Vec<MaskRef>,
    bitmap_words: usize,
    bitmap_buffer: Option<Buffer>,
    field_buffer: Option<Buffer>,
    aux_buffer: Option<Buffer>,
    /// Activated densities per pool texel ([`pack::PoolTextures::sigma`]).
    sigma_buffer: Option<Buffer>,
    /// The pool textures and their trilinear sampler.
    atlas: Option<AtlasTextures>,
    layer_buffer: Option<Buffer>,
    layers: Vec<GpuLayer>,
    step: Step,
    background: [f32; 4],
    min_transmittance: f32,
    /// [`pack::ndc_params`] of the scene's NDC space.
    ndc: [f32; 4],
    scene_ptr: usize,
    /// Bumped whenever grids or bitmaps are uploaded (views re-march).
    generation: u64,
    ready: bool,
}

/// A storage buffer holding `data`, padded to a multiple of 16 bytes and to
/// at least 256: empty bindings are not allowed, and a runtime-sized array
/// binding must hold one element (`Layer` is 160 bytes) even when the scene
/// is empty. Refuses (with a message naming `label`) data beyond the
/// device's binding limit, which would otherwise be a validation error.
fn storage_buffer(device: &RenderDevice, label: &'static str, data: &[u8]) -> crate::Result<Buffer> {
    let max = binding_limit(device);
    crate::ensure_within!(
        DeviceLimit,
        data.len() <= max,
        "{label}: {} MB exceed the GPU's {} MB storage binding limit",
        data.len() >> 20,
        max >> 20
    );
    let mut bytes = data.to_vec();
    bytes.resize(bytes.len().max(256).next_multiple_of(16), 0);
    Ok(device.create_buffer_with_data(&BufferInitDescriptor {
        label: Some(label),
        contents: &bytes,
        usage: BufferUsages::STORAGE | BufferUsages::COPY_DST,
    }))
}

/// Bytes one storage buffer binding may hold on this device.
fn binding_limit(device: &RenderDevice) -> usize {
    let limits = device.limits();
    limits.max_storage_buffer_binding_size.min(limits.max_buffer_size) as usize
}

/// The pool on the GPU; textures a scene does not use hold one texel.
struct AtlasTextures {
    density: TextureView,
    rgb: TextureView,
    sh: Vec<TextureView>,
    sampler: Sampler,
    /// The brick indirection texture ([`pack::Indirection`]).
    indirection: TextureView,
    size: [usize; 3],
    /// Pool bricks per axis.
    bricks: [usize; 3],
    /// Per pool slot its field and brick ([`pack::pool_owners`]), for the
    /// SH bake, and the number of slots in use.
    owners: Buffer,
    slots: usize,
    /// Bound where a view has no baked colours (no SH field shown).
    no_bake: TextureView,
}

/// A single-level 3D texture of `size` texels.
fn texture_3d_desc(
    label: &'static str,
    format: TextureFormat,
    size: [usize; 3],
    usage: TextureUsages,
) -> TextureDescriptor<'static> {
    TextureDescriptor {
        label: Some(label),
        size: Extent3d {
            width: size[0] as u32,
            height: size[1] as u32,
            depth_or_array_layers: size[2] as u32,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: TextureDimension::D3,
        format,
        usage,
        view_formats: &[],
    }
}

/// A 3D texture of `size` holding `data` (texels x fastest).
fn texture_3d_with(
    device: &RenderDevice,
    queue: &RenderQueue,
    label: &'static str,
    format: TextureFormat,
    size: [usize; 3],
    data: &[u8],
) -> TextureView {
    let desc = texture_3d_desc(
        label,
        format,
        size,
        TextureUsages::TEXTURE_BINDING | TextureUsages::COPY_DST,
    );
    let texture = device.create_texture(&desc);
    let row = size[0] as u32 * format.block_copy_size(None).unwrap_or(1);
    queue.write_texture(
        texture.as_image_copy(),
        data,
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(row),
            rows_per_image: Some(size[1] as u32),
        },
        desc.size,
    );
    texture.create_view(&default())
}

/// A pool texture: `data` at the pool's size, or one zero texel when the
/// scene has no data of this kind (the binding still needs a texture).
fn pool_texture<T: bytemuck::Pod>(
    device: &RenderDevice,
    queue: &RenderQueue,
    label: &'static str,
    format: TextureFormat,
    size: [usize; 3],
    data: &[T],
) -> TextureView {
    if data.is_empty() {
        let zero = vec![0u8; format.block_copy_size(None).unwrap_or(4) as usize];
        return texture_3d_with(device, queue, label, format, [1, 1, 1], &zero);
    }
    texture_3d_with(device, queue, label, format, size, bytemuck::cast_slice(data))
}

/// Uploads the pool. Density goes up as f16: filterable on every GPU
/// without an optional feature, at full filtering rate, in half the memory;
/// raw densities keep 3 significant digits, far below what the tests'
/// GPU-vs-CPU comparison can see. SH coefficients are f16 in the fields
/// already.
fn upload_pool(
    device: &RenderDevice,
    queue: &RenderQueue,
    t: &pack::PoolTextures,
    ind: &pack::Indirection,
    plan: &pool::PoolPlan,
) -> crate::Result<AtlasTextures> {
    let bricks = plan.layout.bricks;
    let size = t.size;
    let indirection = pool_texture(
        device,
        queue,
        "isrf_pool_indirection",
        TextureFormat::R32Uint,
        ind.size,
        &ind.data,
    );
    let density = pool_texture(
        device,
        queue,
        "isrf_pool_density",
        TextureFormat::R16Float,
        size,
        &t.density,
    );
    let rgb = pool_texture(
        device,
        queue,
        "isrf_pool_rgb",
        TextureFormat::Rgb10a2Unorm,
        size,
        &t.rgb,
    );
    let no_sh: Vec<[u16; 4]> = Vec::new();
    let sh = (0..pack::SH_TEXTURES)
        .map(|k| {
            let data = t.sh.get(k).unwrap_or(&no_sh);
            pool_texture(device, queue, "isrf_pool_sh", TextureFormat::Rgba16Float, size, data)
        })
        .collect();
    let sampler = device.create_sampler(&SamplerDescriptor {
        label: Some("isrf_pool_sampler"),
        address_mode_u: AddressMode::ClampToEdge,
        address_mode_v: AddressMode::ClampToEdge,
        address_mode_w: AddressMode::ClampToEdge,
        mag_filter: FilterMode::Linear,
        min_filter: FilterMode::Linear,
        ..default()
    });
    let owners = pack::pool_owners(plan);
    let no_bake = bake::bake_texture(device, [1, 1, 1]);
    Ok(AtlasTextures {
        density,
        rgb,
        sh,
        sampler,
        indirection,
        size,
        bricks,
        owners: storage_buffer(device, "isrf_pool_owners", bytemuck::cast_slice(&owners))?,
        slots: plan.layout.slots.len(),
        no_bake,
    })
}

fn prepare_scene(
    march: Option<Res<MarchScene>>,
    mut cache: ResMut<GpuSceneCache>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
    status: Res<SharedStatus>,
) {
    cache.ready = false;
    let Some(march) = march else { return };
    let Some(scene) = march.scene.clone() else {
        return;
    };
    if let Err(e) = update_cache(&mut cache, &march, &scene, &device, &queue, &status) {
        status.update(|s| s.error = Some(e.to_string()));
        return;
    }
    // A scene that made the GPU report an error is not drawn again until
    // its fields or masks change (see `keep_running_on_gpu_errors`).
    let generation = cache.generation;
    let failed = status.get().gpu_error.is_some_and(|(g, _)| g == generation);
    cache.ready = !failed;
}

/// Packs and uploads the fields when the set of fields (or the memory
/// budget) changes: the finest level of detail whose occupied bricks fit
/// the device and the budget ([`pool::plan`]).
fn update_fields(
    cache: &mut GpuSceneCache,
    wanted: &[Arc<Field>],
    budget: usize,
    device: &RenderDevice,
    queue: &RenderQueue,
    status: &SharedStatus,
) -> crate::Result<()> {
    let same =
        wanted.len() == cache.fields.len() && wanted.iter().zip(&cache.fields).all(|(a, b)| Arc::ptr_eq(a, &b.field));
    // (An empty scene still needs its empty buffers, to draw the background.)
    if same && cache.budget == budget && cache.field_buffer.is_some() {
        return Ok(());
    }
    // A set of fields that did not fit is not packed again every frame.
    let key: Vec<usize> = wanted.iter().map(|f| Arc::as_ptr(f) as usize).collect();
    if let Some((k, b, e)) = &cache.failed {
        if *k == key && *b == budget {
            return Err(crate::Error::invalid(e.clone()));
        }
    }
    let result = upload_fields(cache, wanted, budget, device, queue, status);
    cache.failed = result.as_ref().err().map(|e| (key, budget, e.to_string()));
    result
}

fn upload_fields(
    cache: &mut GpuSceneCache,
    wanted: &[Arc<Field>],
    budget: usize,
    device: &RenderDevice,
    queue: &RenderQueue,
    status: &SharedStatus,
) -> crate::Result<()> {
    let t0 = Instant::now();
    let mut old = std::mem::take(&mut cache.fields);
    let mut packed = 0;
    for f in wanted {
        match old.iter().position(|s| Arc::ptr_eq(&s.field, f)) {
            Some(i) => cache.fields.push(old.swap_remove(i)),
            None => {
                let drawn = pack::drawn_field(f)?;
                let p = pack::pack_field(&drawn)?;
                cache.fields.push(FieldSlot {
                    field: f.clone(),
                    drawn,
                    packed: p,
                });
                packed += 1;
            }
        }
    }
    // Whatever fails from here leaves no half-updated scene behind.
    cache.plan = None;
    cache.field_buffer = None;
    let drawn: Vec<&Field> = cache.fields.iter().map(|s| &*s.drawn).collect();
    let densities: Vec<&crate::field::DensityGrid> = drawn.iter().map(|f| &f.density).collect();
    let max_side = device.limits().max_texture_dimension_3d as usize;
    // The activated densities (two bytes a texel) are one storage binding.
    let max_texels = binding_limit(device) / 2;
    let plan = pool::plan(&densities, pack::pool_texel_bytes(&drawn), max_side, budget, max_texels)?;
    let parts: Vec<&PackedField> = cache.fields.iter().map(|s| &s.packed).collect();
    let (mut infos, aux) = pack::concat_fields(&parts, &plan)?;
    let ind = pack::indirection(&plan, max_side)?;
    for (info, z0) in infos.iter_mut().zip(&ind.z0) {
        info.offsets[2] = *z0 as u32;
    }
    let textures = pack::pool_textures(&drawn, &plan);
    cache.atlas = Some(upload_pool(device, queue, &textures, &ind, &plan)?);
    cache.aux_buffer = Some(storage_buffer(device, "isrf_aux", bytemuck::cast_slice(&aux))?);
    cache.sigma_buffer = Some(storage_buffer(
        device,
        "isrf_pool_sigma",
        bytemuck::cast_slice(&textures.sigma),
    )?);
    cache.field_buffer = Some(storage_buffer(device, "isrf_fields", bytemuck::cast_slice(&infos))?);
    cache.field_infos = infos;
    cache.budget = budget;
    // Masks are laid out by the new bricks: upload them all again.
    cache.bitmaps.clear();
    cache.bitmap_buffer = None;
    cache.generation += 1;
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    let detail = (plan.stride > 1).then(|| {
        format!(
            "showing 1/{} of the grid resolution: at full detail the fields need more than the {} GPU \
             memory budget (ISRF_GPU_BUDGET_MB) or the GPU's {max_side}-texel 3D textures",
            plan.stride,
            crate::util::human_bytes(budget)
        )
    });
    status.update(|s| {
        s.upload_ms = ms;
        s.uploads += packed;
        s.stride = plan.stride;
        s.pool_bytes = plan.bytes;
        s.detail = detail;
    });
    cache.plan = Some(plan);
    Ok(())
}

/// The uploaded bricks of a mask's field (none before any plan).
fn mask_bricks<'a>(cache: &'a GpuSceneCache, m: &MaskRef) -> Option<&'a pool::FieldBricks> {
    let i = cache.fields.iter().position(|s| Arc::ptr_eq(&s.field, &m.field))?;
    cache.plan.as_ref().map(|plan| &plan.fields[i])
}

/// A mask's words in its field's brick order.
fn mask_words(cache: &GpuSceneCache, m: &MaskRef) -> Vec<u32> {
    mask_bricks(cache, m).map_or_else(Vec::new, |b| pool::brick_bits(b, &m.bits))
}

/// Uploads mask bitmaps: only those whose contents changed when the layout
/// (masks and fields in order) is unchanged; the whole buffer otherwise.
fn update_bitmaps(
    cache: &mut GpuSceneCache,
    bitmaps: Vec<MaskRef>,
    offs: &[u32],
    total: usize,
    device: &RenderDevice,
    queue: &RenderQueue,
    status: &SharedStatus,
) -> crate::Result<()> {
    let same_layout = cache.bitmap_buffer.is_some()
        && total == cache.bitmap_words
        && bitmaps.len() == cache.bitmaps.len()
        && bitmaps
            .iter()
            .zip(&cache.bitmaps)
            .all(|(a, b)| Arc::ptr_eq(&a.field, &b.field) && a.bits.len() == b.bits.len());
    if same_layout {
        let mut n = 0;
        for (k, m) in bitmaps.iter().enumerate() {
            let old = &cache.bitmaps[k].bits;
            // A new Arc with the same bits (a scene rebuilt during a drag)
            // needs no upload.
            if !Arc::ptr_eq(&m.bits, old) && *m.bits != **old {
                let words = mask_words(cache, m);
                queue.write_buffer(
                    cache.bitmap_buffer.as_ref().unwrap(),
                    offs[k] as u64 * 4,
                    bytemuck::cast_slice(&words),
                );
                n += 1;
            }
        }
        if n > 0 {
            cache.generation += 1;
            status.update(|s| s.bitmap_uploads += n);
        }
    } else {
        let mut words = Vec::with_capacity(total);
        for m in &bitmaps {
            words.extend(mask_words(cache, m));
        }
        cache.bitmap_buffer = Some(storage_buffer(device, "isrf_bitmaps", bytemuck::cast_slice(&words))?);
        cache.bitmap_words = total;
        cache.generation += 1;
        let n = bitmaps.len() as u64;
        status.update(|s| s.bitmap_uploads += n);
    }
    cache.bitmaps = bitmaps;
    Ok(())
}

/// Mask words per occupied brick of each mask's field.
fn mask_word_counts(cache: &GpuSceneCache, bitmaps: &[MaskRef]) -> Vec<usize> {
    bitmaps
        .iter()
        .map(|m| mask_bricks(cache, m).map_or(0, |b| b.count() * pool::BRICK_WORDS))
        .collect()
}

fn update_cache(
    cache: &mut GpuSceneCache,
    march: &MarchScene,
    scene: &Arc<Scene>,
    device: &RenderDevice,
    queue: &RenderQueue,
    status: &SharedStatus,
) -> crate::Result<()> {
    let wanted = pack::distinct_fields(scene);
    update_fields(cache, &wanted, march.memory_budget, device, queue, status)?;
    let bitmaps = pack::distinct_bitmaps(scene, &march.overlay);
    let (offs, total) = pack::bitmap_offsets(&mask_word_counts(cache, &bitmaps));
    update_bitmaps(cache, bitmaps, &offs, total, device, queue, status)?;
    // Layers: small, repacked every frame.
    let mut layers = pack::pack_layers(scene, &wanted, &cache.bitmaps, &offs, &march.overlay)?;
    pack::mark_baked(&mut layers, &cache.field_infos, march.ndc.is_some());
    let bytes: &[u8] = bytemuck::cast_slice(&layers);
    let fits = cache
        .layer_buffer
        .as_ref()
        .is_some_and(|b| b.size() as usize >= bytes.len().max(16));
    if fits && !bytes.is_empty() {
        queue.write_buffer(cache.layer_buffer.as_ref().unwrap(), 0, bytes);
    } else if !fits {
        cache.layer_buffer = Some(storage_buffer(device, "isrf_layers", bytes)?);
    }
    cache.layers = layers;
    march.step.check()?;
    cache.step = march.step;
    let bg = scene.background;
    cache.background = [bg.x, bg.y, bg.z, 1.0];
    cache.min_transmittance = march.min_transmittance;
    cache.ndc = pack::ndc_params(march.ndc.as_ref());
    cache.scene_ptr = Arc::as_ptr(scene) as usize;
    let generation = cache.generation;
    status.update(|s| {
        // Keep a GPU error on show while its scene is the one shown.
        s.error = s
            .gpu_error
            .as_ref()
            .filter(|(g, _)| *g == generation)
            .map(|(_, m)| m.clone());
    });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_shader_still_loading_is_not_a_compile_failure() {
        let waiting = [
            CachedPipelineState::Queued,
            CachedPipelineState::Err(ShaderCacheError::ShaderNotLoaded(AssetId::default())),
            CachedPipelineState::Err(ShaderCacheError::ShaderImportNotYetAvailable),
        ];
        for state in &waiting {
            assert!(compile_failure(state).is_none(), "{state:?} is reported as a failure");
        }
        let broken = CachedPipelineState::Err(ShaderCacheError::CreateShaderModule("bad WGSL".into()));
        let e = compile_failure(&broken).expect("a shader module error is a failure");
        assert!(e.to_string().contains("bad WGSL"), "{e}");
    }

    fn layer(field: u32, mask: u32, flags: u32, highlight: u32) -> GpuLayer {
        GpuLayer {
            info: [field, mask, 0, flags],
            highlight: [highlight, 0, 0, 0],
            ..Default::default()
        }
    }

    fn field(kind: u32) -> pack::GpuField {
        pack::GpuField {
            res: [2, 2, 2, kind],
            ..Default::default()
        }
    }

    fn defs(key: MarchKey) -> Vec<String> {
        key.shader_defs()
            .into_iter()
            .map(|d| match d {
                ShaderDefVal::UInt(name, v) => format!("{name}={v}"),
                ShaderDefVal::Bool(name, _) => name,
                ShaderDefVal::Int(name, v) => format!("{name}={v}"),
            })
            .collect()
    }

    #[test]
    fn march_variants_hold_exactly_the_code_their_scene_uses() {
        let rgb = field(pack::COLOR_SPARSE);
        let sh = field(pack::COLOR_SH);
        // A plain RGB field: the leanest variant.
        let key = MarchKey::of(&[layer(0, pack::MASK_ALL, 0, 0)], &[rgb]);
        assert_eq!(defs(key), ["MAX_LAYERS=1", "RGB"]);
        // No layers (nothing loaded yet): drawn by the RGB variant.
        assert_eq!(defs(MarchKey::of(&[], &[])), ["MAX_LAYERS=1", "RGB"]);
        // A moved, selected object of an SH field: two masked layers, tinted.
        let key = MarchKey::of(
            &[
                layer(0, pack::MASK_REMOVE, 0, 0),
                layer(0, pack::MASK_KEEP, pack::LAYER_HIGHLIGHT, 0),
            ],
            &[sh],
        );
        assert_eq!(defs(key), ["MAX_LAYERS=2", "SH", "MASKS", "OVERLAY"]);
        // An in-place selection (highlight mask) next to an edited RGB field.
        let key = MarchKey::of(
            &[
                layer(0, pack::MASK_ALL, pack::LAYER_DIM, 1),
                layer(1, pack::MASK_ALL, pack::LAYER_COLOR_EDIT, 0),
                layer(1, pack::MASK_ALL, 0, 0),
            ],
            &[sh, rgb],
        );
        assert_eq!(
            defs(key),
            ["MAX_LAYERS=4", "RGB", "SH", "COLOR_EDIT", "OVERLAY", "HIGHLIGHT"]
        );
    }
}
