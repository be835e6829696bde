//! Per-view drawing: each view marches into its own colour and depth
//! textures, only when what they would show changed, and a composite pass
//! draws them into the view every frame.
//!
//! Why: on a software rasteriser (lavapipe) one march of a 640×360 view
//! takes a few hundred milliseconds. Marching only on change keeps a still
//! view (and the egui panels around it) at full frame rate, and a
//! [`RayMarchCamera::render_scale`] below 1 marches a quarter of the pixels
//! while the camera moves; the composite pass upsamples it.

use super::bake::{self, BakeJob, BakePipeline, BakedColours};
use super::pack::GpuView;
use super::{
    opaque_target, GpuSceneCache, MarchKey, RayMarchCamera, RayMarchPipeline, RayMarchShaders, SharedStatus,
    MARCH_COLOR_FORMAT, MARCH_DEPTH_FORMAT,
};
use crate::render::Step;
use bevy::core_pipeline::FullscreenShader;
use bevy::prelude::*;
use bevy::render::camera::ExtractedCamera;
use bevy::render::render_resource::binding_types::{sampler, texture_2d};
use bevy::render::render_resource::{
    BindGroup, BindGroupEntries, BindGroupLayoutDescriptor, BindGroupLayoutEntries, BufferInitDescriptor, BufferUsages,
    CachedRenderPipelineId, CompareFunction, DepthStencilState, Extent3d, FilterMode, FragmentState, LoadOp,
    MultisampleState, Operations, PipelineCache, RenderPassColorAttachment, RenderPassDescriptor,
    RenderPipelineDescriptor, Sampler, SamplerBindingType, SamplerDescriptor, ShaderStages, SpecializedRenderPipeline,
    SpecializedRenderPipelines, StoreOp, TextureDescriptor, TextureDimension, TextureFormat, TextureSampleType,
    TextureUsages, TextureView,
};
use bevy::render::renderer::{RenderContext, RenderDevice, ViewQuery};
use bevy::render::view::{ExtractedView, Msaa, ViewDepthTexture, ViewTarget};
use bevy::shader::Shader;
use std::sync::{Arc, Mutex};

/// The composite pipeline: march textures -> view colour and depth.
#[derive(Resource)]
pub(super) struct CompositePipeline {
    layout: BindGroupLayoutDescriptor,
    shader: Handle<Shader>,
    fullscreen: FullscreenShader,
    sampler: Sampler,
}

pub(super) fn init_composite_pipeline(
    mut commands: Commands,
    shaders: Res<RayMarchShaders>,
    fullscreen: Res<FullscreenShader>,
    device: Res<RenderDevice>,
) {
    let layout = BindGroupLayoutDescriptor::new(
        "isrf_composite_layout",
        &BindGroupLayoutEntries::sequential(
            ShaderStages::FRAGMENT,
            (
                texture_2d(TextureSampleType::Float { filterable: true }),
                texture_2d(TextureSampleType::Float { filterable: false }),
                sampler(SamplerBindingType::Filtering),
            ),
        ),
    );
    let sampler = device.create_sampler(&SamplerDescriptor {
        label: Some("isrf_composite_sampler"),
        mag_filter: FilterMode::Linear,
        min_filter: FilterMode::Linear,
        ..default()
    });
    commands.insert_resource(CompositePipeline {
        layout,
        shader: shaders.composite.clone(),
        fullscreen: fullscreen.clone(),
        sampler,
    });
}

impl SpecializedRenderPipeline for CompositePipeline {
    /// The view's target format and MSAA samples.
    type Key = (TextureFormat, u32);
    fn specialize(&self, (format, samples): Self::Key) -> RenderPipelineDescriptor {
        RenderPipelineDescriptor {
            label: Some("isrf_composite_pipeline".into()),
            layout: vec![self.layout.clone()],
            vertex: self.fullscreen.to_vertex_state(),
            fragment: Some(FragmentState {
                shader: self.shader.clone(),
                shader_defs: vec![],
                entry_point: Some("fragment".into()),
                targets: vec![opaque_target(format)],
            }),
            depth_stencil: Some(DepthStencilState {
                format: bevy::core_pipeline::core_3d::CORE_3D_DEPTH_FORMAT,
                depth_write_enabled: Some(true),
                depth_compare: Some(CompareFunction::Always),
                stencil: default(),
                bias: default(),
            }),
            multisample: MultisampleState {
                count: samples,
                ..default()
            },
            ..default()
        }
    }
}

/// A view's march textures and what they hold.
#[derive(Component, Clone)]
pub(super) struct MarchTargets {
    size: UVec2,
    color: TextureView,
    depth: TextureView,
    composite: BindGroup,
    /// The march inputs (view uniform, layers, data generation) of the
    /// image the textures hold; `None` before the first march. Set by the
    /// pass that marched, not when the march is planned, so that a march
    /// planned for a view that is then not drawn is not taken as done.
    shown: Arc<Mutex<Option<Vec<u8>>>>,
}

/// This frame's work for a view.
#[derive(Component)]
pub(super) struct ViewDraw {
    /// Bind group, pipeline and inputs (`MarchTargets::shown`) of the
    /// march, when it has to run.
    march: Option<(BindGroup, CachedRenderPipelineId, Vec<u8>)>,
    /// The SH bake that runs before the march, when it marches SH layers.
    bake: Option<(BakeJob, bevy::render::render_resource::CachedComputePipelineId)>,
    composite: CachedRenderPipelineId,
    scene_ptr: usize,
    /// The textures hold a march at the viewport's full size.
    full: bool,
}

fn march_texture(device: &RenderDevice, label: &'static str, size: UVec2, format: TextureFormat) -> TextureView {
    device
        .create_texture(&TextureDescriptor {
            label: Some(label),
            size: Extent3d {
                width: size.x,
                height: size.y,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: TextureDimension::D2,
            format,
            usage: TextureUsages::RENDER_ATTACHMENT | TextureUsages::TEXTURE_BINDING,
            view_formats: &[],
        })
        .create_view(&default())
}

fn new_targets(
    device: &RenderDevice,
    cache: &PipelineCache,
    composite: &CompositePipeline,
    size: UVec2,
) -> MarchTargets {
    let color = march_texture(device, "isrf_march_color", size, MARCH_COLOR_FORMAT);
    let depth = march_texture(device, "isrf_march_depth", size, MARCH_DEPTH_FORMAT);
    let bind_group = device.create_bind_group(
        "isrf_composite_bind_group",
        &cache.get_bind_group_layout(&composite.layout),
        &BindGroupEntries::sequential((&color, &depth, &composite.sampler)),
    );
    MarchTargets {
        size,
        color,
        depth,
        composite: bind_group,
        shown: Arc::default(),
    }
}

/// The march's pixel size for a viewport: `scale` of each side, at least 1.
pub(super) fn march_size(viewport: UVec2, scale: f32) -> UVec2 {
    let s = if scale.is_finite() {
        scale.clamp(0.125, 1.0)
    } else {
        1.0
    };
    (viewport.as_vec2() * s).round().as_uvec2().max(UVec2::ONE)
}

/// Intrinsics (fx, fy, cx, cy) of a perspective view from its projection:
/// bevy's infinite reverse-z perspective has `[0][0] = f/aspect`,
/// `[1][1] = f` with f = 1/tan(fov_y/2); the principal point is the centre.
fn view_intrinsics(view: &ExtractedView) -> [f32; 4] {
    let p = view.clip_from_view.to_cols_array_2d();
    let (w, h) = (view.viewport.z as f32, view.viewport.w as f32);
    [p[0][0] * 0.5 * w, p[1][1] * 0.5 * h, 0.5 * w, 0.5 * h]
}

/// The view uniform for a march of `size` pixels: the intrinsics scaled so
/// that the march's pixels tile the viewport exactly.
fn gpu_view(view: &ExtractedView, cam: &RayMarchCamera, cache: &GpuSceneCache, size: UVec2) -> GpuView {
    let world_from_view = view.world_from_view.to_matrix();
    let clip_from_world = view
        .clip_from_world
        .unwrap_or(view.clip_from_view * world_from_view.inverse());
    let [fx, fy, cx, cy] = cam.intrinsics.unwrap_or_else(|| view_intrinsics(view));
    let sx = size.x as f32 / view.viewport.z.max(1) as f32;
    let sy = size.y as f32 / view.viewport.w.max(1) as f32;
    GpuView {
        c2w: world_from_view.to_cols_array_2d(),
        clip_from_world: clip_from_world.to_cols_array_2d(),
        intrinsics: [fx * sx, fy * sy, cx * sx, cy * sy],
        background: cache.background,
        march: match cache.step {
            Step::Cells(v) => [v, cache.min_transmittance, 0.0, 0.0],
            Step::World(v) => [v, cache.min_transmittance, 1.0, 0.0],
        },
        counts: [cache.layers.len() as u32, 0, 0, 0],
        atlas: cache.atlas.as_ref().map_or([1.0; 4], |a| {
            let s = a.size.map(|n| 1.0 / n as f32);
            [s[0], s[1], s[2], 0.0]
        }),
        pool: cache.atlas.as_ref().map_or([1, 1, 1, 0], |a| {
            let b = a.bricks.map(|n| n as u32);
            [b[0], b[1], b[2], 0]
        }),
        ndc: cache.ndc,
    }
}

/// The march's bind group for one view uniform.
fn march_bind_group(
    device: &RenderDevice,
    pipeline_cache: &PipelineCache,
    pipeline: &RayMarchPipeline,
    cache: &GpuSceneCache,
    gv: &GpuView,
    baked: &TextureView,
) -> Option<BindGroup> {
    let uniform = device.create_buffer_with_data(&BufferInitDescriptor {
        label: Some("isrf_view"),
        contents: bytemuck::bytes_of(gv),
        usage: BufferUsages::UNIFORM,
    });
    let (Some(layers), Some(fields), Some(aux), Some(bitmaps), Some(sigma)) = (
        &cache.layer_buffer,
        &cache.field_buffer,
        &cache.aux_buffer,
        &cache.bitmap_buffer,
        &cache.sigma_buffer,
    ) else {
        return None;
    };
    let atlas = cache.atlas.as_ref()?;
    let sh = &atlas.sh;
    Some(device.create_bind_group(
        "isrf_raymarch_bind_group",
        &pipeline_cache.get_bind_group_layout(&pipeline.layout),
        &BindGroupEntries::sequential((
            uniform.as_entire_binding(),
            layers.as_entire_binding(),
            fields.as_entire_binding(),
            aux.as_entire_binding(),
            bitmaps.as_entire_binding(),
            &atlas.density,
            &atlas.rgb,
            &sh[0],
            &sh[1],
            &sh[2],
            &sh[3],
            &sh[4],
            &sh[5],
            &sh[6],
            &atlas.sampler,
            &atlas.indirection,
            sigma.as_entire_binding(),
            baked,
        )),
    ))
}

/// Whether a pipeline is ready; reports a compile error to the UI.
fn pipeline_ready(cache: &PipelineCache, id: CachedRenderPipelineId, status: &SharedStatus) -> bool {
    if cache.get_render_pipeline(id).is_some() {
        return true;
    }
    if let Some(e) = super::compile_failure(cache.get_render_pipeline_state(id)) {
        let msg = format!("the ray-marching shaders failed to compile: {e}");
        status.update(|s| s.error = Some(msg));
    }
    false
}

/// The views to draw, with their march textures once they have some.
type Views<'w, 's> = Query<
    'w,
    's,
    (
        Entity,
        &'static ExtractedView,
        &'static RayMarchCamera,
        Option<&'static Msaa>,
        Option<&'static MarchTargets>,
        Option<&'static BakedColours>,
    ),
>;

#[allow(clippy::too_many_arguments)]
pub(super) fn prepare_views(
    mut commands: Commands,
    views: Views,
    cache: Res<GpuSceneCache>,
    pipelines: (
        Option<Res<RayMarchPipeline>>,
        Option<Res<CompositePipeline>>,
        Option<Res<BakePipeline>>,
    ),
    mut specialized: (
        ResMut<SpecializedRenderPipelines<RayMarchPipeline>>,
        ResMut<SpecializedRenderPipelines<CompositePipeline>>,
    ),
    pipeline_cache: Res<PipelineCache>,
    device: Res<RenderDevice>,
    status: Res<SharedStatus>,
) {
    let (Some(march_pipeline), Some(composite_pipeline), Some(bake_pipeline)) = pipelines else {
        return;
    };
    for (entity, view, cam, msaa, targets, baked) in &views {
        if !cache.ready {
            commands.entity(entity).remove::<ViewDraw>();
            continue;
        }
        let variant = MarchKey::of(&cache.layers, &cache.field_infos);
        let march_id = specialized.0.specialize(&pipeline_cache, &march_pipeline, variant);
        let samples = msaa.map_or(1, |m| m.samples());
        let composite_id =
            specialized
                .1
                .specialize(&pipeline_cache, &composite_pipeline, (view.target_format, samples));
        // (Both checked: each reports its compile error.)
        let bakes = variant.baked;
        let march_ready = pipeline_ready(&pipeline_cache, march_id, &status)
            && (!bakes || bake::ready(&pipeline_cache, &bake_pipeline, &status));
        if !pipeline_ready(&pipeline_cache, composite_id, &status) {
            commands.entity(entity).remove::<ViewDraw>();
            continue;
        }
        let viewport = UVec2::new(view.viewport.z, view.viewport.w);
        let size = march_size(viewport, cam.render_scale);
        let targets = match targets {
            Some(t) if t.size == size => t.clone(),
            _ => new_targets(&device, &pipeline_cache, &composite_pipeline, size),
        };
        // Until a variant the scene now needs has compiled, the view keeps
        // showing its last image (not counted as showing this scene).
        let (mut march, mut bake_job, mut scene_ptr, full) = (None, None, 0, march_ready && size == viewport);
        // The view's baked colours, at the pool's size.
        let mut baked = match (cache.atlas.as_ref(), baked) {
            (Some(a), Some(b)) if !bakes || b.size == a.size => Some(b.clone()),
            (Some(a), _) if bakes => Some(BakedColours {
                size: a.size,
                view: bake::bake_texture(&device, a.size),
                scene: Vec::new(),
            }),
            _ => None,
        };
        if march_ready {
            scene_ptr = cache.scene_ptr;
            let gv = gpu_view(view, cam, &cache, size);
            let mut key = bytemuck::bytes_of(&gv).to_vec();
            key.extend_from_slice(bytemuck::cast_slice(&cache.layers));
            key.extend_from_slice(&cache.generation.to_le_bytes());
            if !targets.shown.lock().is_ok_and(|s| s.as_ref() == Some(&key)) {
                let (Some(atlas), Some(fields)) = (cache.atlas.as_ref(), cache.field_buffer.as_ref()) else {
                    continue;
                };
                let scene = bake::scene_key(&cache.layers, cache.generation, gv.ndc);
                let reuse = bake::reuse_while_moving(baked.as_ref(), &scene, size == viewport);
                if let Some(b) = baked.as_mut().filter(|_| bakes && !reuse) {
                    b.scene = scene;
                }
                let target = match (&baked, bakes) {
                    (Some(b), true) => &b.view,
                    _ => &atlas.no_bake,
                };
                let Some(bg) = march_bind_group(&device, &pipeline_cache, &march_pipeline, &cache, &gv, target) else {
                    continue;
                };
                let origin = Vec3::from_slice(&gv.c2w[3][..3]);
                bake_job = (bakes && !reuse).then(|| {
                    let job = bake::job(
                        &device,
                        &pipeline_cache,
                        &bake_pipeline,
                        &cache.layers,
                        fields,
                        atlas,
                        target,
                        origin,
                        gv.ndc,
                    );
                    (job, bake_pipeline.id)
                });
                march = Some((bg, march_id, key));
            }
        }
        let has_image = targets.shown.lock().is_ok_and(|s| s.is_some());
        let mut view_entity = commands.entity(entity);
        if let Some(b) = baked {
            view_entity.insert(b);
        }
        if march.is_none() && !has_image {
            view_entity.insert(targets).remove::<ViewDraw>();
            continue;
        }
        view_entity.insert((
            targets,
            ViewDraw {
                march,
                bake: bake_job,
                composite: composite_id,
                scene_ptr,
                full,
            },
        ));
    }
}

fn target_attachment(view: &TextureView) -> Option<RenderPassColorAttachment<'_>> {
    Some(RenderPassColorAttachment {
        view,
        depth_slice: None,
        resolve_target: None,
        ops: Operations {
            load: LoadOp::Clear(default()),
            store: StoreOp::Store,
        },
    })
}

pub(super) fn raymarch_pass(
    view: ViewQuery<(
        &ExtractedCamera,
        &ViewTarget,
        &ViewDepthTexture,
        &MarchTargets,
        &ViewDraw,
    )>,
    pipeline_cache: Res<PipelineCache>,
    status: Res<SharedStatus>,
    mut ctx: RenderContext,
) {
    let (camera, target, depth, targets, draw) = view.into_inner();
    // (prepare_views checked that both pipelines exist.)
    let Some(composite) = pipeline_cache.get_render_pipeline(draw.composite) else {
        return;
    };
    if let Some((bind_group, id, key)) = &draw.march {
        let Some(pipeline) = pipeline_cache.get_render_pipeline(*id) else {
            return;
        };
        if let Some((job, bake_id)) = &draw.bake {
            let Some(bake) = pipeline_cache.get_compute_pipeline(*bake_id) else {
                return;
            };
            let mut pass =
                ctx.command_encoder()
                    .begin_compute_pass(&bevy::render::render_resource::ComputePassDescriptor {
                        label: Some("isrf_sh_bake_pass"),
                        timestamp_writes: None,
                    });
            pass.set_pipeline(bake);
            pass.set_bind_group(0, &job.bind_group, &[]);
            let [x, y, z] = job.groups;
            pass.dispatch_workgroups(x, y, z);
        }
        let attachments = [target_attachment(&targets.color), target_attachment(&targets.depth)];
        let mut pass = ctx.begin_tracked_render_pass(RenderPassDescriptor {
            label: Some("isrf_raymarch_pass"),
            color_attachments: &attachments,
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_render_pipeline(pipeline);
        pass.set_bind_group(0, bind_group, &[]);
        pass.draw(0..3, 0..1);
        if let Ok(mut shown) = targets.shown.lock() {
            *shown = Some(key.clone());
        }
    }
    let color_attachments = [Some(target.get_color_attachment())];
    let mut pass = ctx.begin_tracked_render_pass(RenderPassDescriptor {
        label: Some("isrf_composite_pass"),
        color_attachments: &color_attachments,
        depth_stencil_attachment: Some(depth.get_attachment(StoreOp::Store)),
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    });
    if let Some(viewport) = camera.viewport.as_ref() {
        pass.set_camera_viewport(viewport);
    }
    pass.set_render_pipeline(composite);
    pass.set_bind_group(0, &targets.composite, &[]);
    pass.draw(0..3, 0..1);
    let (ptr, marched, full) = (draw.scene_ptr, draw.march.is_some() as u64, draw.full);
    status.update(|s| {
        s.frames_drawn += 1;
        s.marches += marched;
        s.scene_drawn = ptr;
        s.full_resolution = full;
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn march_size_scales_each_side_and_stays_positive() {
        assert_eq!(march_size(UVec2::new(640, 360), 1.0), UVec2::new(640, 360));
        assert_eq!(march_size(UVec2::new(640, 360), 0.5), UVec2::new(320, 180));
        assert_eq!(march_size(UVec2::new(641, 361), 0.5), UVec2::new(321, 181));
        // Clamped to [1/8, 1]; NaN means full resolution.
        assert_eq!(march_size(UVec2::new(640, 360), 0.01), UVec2::new(80, 45));
        assert_eq!(march_size(UVec2::new(640, 360), 3.0), UVec2::new(640, 360));
        assert_eq!(march_size(UVec2::new(640, 360), f32::NAN), UVec2::new(640, 360));
        assert_eq!(march_size(UVec2::new(3, 1), 0.125), UVec2::new(1, 1));
    }
}
