//! Window-less rendering with the GPU ray marcher: a bevy app with no winit,
//! synchronous pipeline compilation and a camera that renders into an image,
//! read back with bevy's screenshot machinery. Used by tests, `isrf bench
//! editor` and anything that wants GPU frames without a window.

use super::convert::{bevy_transform, projection_for};
use super::gpu::{MarchScene, RayMarchCamera, RayMarchPlugin, SharedStatus};
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::render::Scene;
use bevy::app::PluginsState;
use bevy::asset::RenderAssetUsages;
use bevy::camera::RenderTarget;
use bevy::core_pipeline::tonemapping::{DebandDither, Tonemapping};
use bevy::prelude::*;
use bevy::render::render_resource::{TextureFormat, TextureUsages};
use bevy::render::renderer::RenderDevice;
use bevy::render::view::screenshot::{Screenshot, ScreenshotCaptured};
use bevy::render::view::Msaa;
use bevy::render::RenderPlugin;
use bevy::window::ExitCondition;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Frames to wait for pipelines, uploads and read-back before giving up.
const MAX_FRAMES: usize = 600;

/// A reusable window-less renderer of a fixed image size.
pub struct HeadlessRenderer {
    app: App,
    width: u32,
    height: u32,
    camera: Entity,
    target: Handle<Image>,
}

/// The plugins of a window-less app (no winit, no log capture, rendering
/// driven by `update()`).
pub fn headless_plugins() -> bevy::app::PluginGroupBuilder {
    DefaultPlugins
        .build()
        .disable::<bevy::winit::WinitPlugin>()
        .disable::<bevy::log::LogPlugin>()
        .disable::<bevy::render::pipelined_rendering::PipelinedRenderingPlugin>()
        .set(WindowPlugin {
            primary_window: None,
            exit_condition: ExitCondition::DontExit,
            close_when_requested: false,
            ..default()
        })
        .set(RenderPlugin {
            synchronous_pipeline_compilation: true,
            ..default()
        })
}

impl HeadlessRenderer {
    pub fn new(width: u32, height: u32) -> Result<Self> {
        crate::ensure_within!(
            DeviceLimit,
            crate::limits::texture_size_ok(width, height),
            "image size {width}x{height} is out of range"
        );
        let mut app = App::new();
        app.add_plugins(headless_plugins()).add_plugins(RayMarchPlugin);
        // Finish plugin setup (the render device is created asynchronously).
        let t0 = Instant::now();
        while app.plugins_state() == PluginsState::Adding {
            if t0.elapsed().as_secs() > 60 {
                return Err(Error::invalid("timed out creating the GPU device"));
            }
            std::thread::yield_now();
            bevy::tasks::tick_global_task_pools_on_main_thread();
        }
        app.finish();
        app.cleanup();
        if app.world().get_resource::<RenderDevice>().is_none() {
            return Err(Error::invalid("no GPU adapter (bevy created no render device)"));
        }
        let mut image = Image::new_target_texture(width, height, TextureFormat::Rgba8UnormSrgb, None);
        image.texture_descriptor.usage |= TextureUsages::COPY_SRC;
        image.asset_usage = RenderAssetUsages::RENDER_WORLD;
        let target = app.world_mut().resource_mut::<Assets<Image>>().add(image);
        let camera = app
            .world_mut()
            .spawn((
                Camera3d::default(),
                RenderTarget::Image(target.clone().into()),
                Tonemapping::None,
                DebandDither::Disabled,
                Msaa::Off,
                RayMarchCamera::default(),
            ))
            .id();
        Ok(HeadlessRenderer {
            app,
            width,
            height,
            camera,
            target,
        })
    }

    /// The adapter bevy picked, in words.
    pub fn adapter_info(&self) -> Option<String> {
        let i = self
            .app
            .world()
            .get_resource::<bevy::render::renderer::RenderAdapterInfo>()?;
        Some(format!("{} ({:?}, {:?})", i.name, i.backend, i.device_type))
    }

    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Points the bevy camera like `camera` (its intrinsics must match this
    /// renderer's image size); an NDC camera (forward-facing capture) makes
    /// the scene's space its NDC space.
    pub fn set_camera(&mut self, camera: &Camera) -> Result<()> {
        let k = camera.intrinsics;
        crate::ensure!(
            k.width == self.width && k.height == self.height,
            "camera is {}x{}, the renderer {}x{}",
            k.width,
            k.height,
            self.width,
            self.height
        );
        // A camera with NDC marches the scene in its NDC space, as the CPU
        // renderer does.
        self.app.world_mut().resource_mut::<MarchScene>().ndc = camera.ndc;
        let mut e = self.app.world_mut().entity_mut(self.camera);
        let render_scale = e.get::<RayMarchCamera>().map_or(1.0, |c| c.render_scale);
        e.insert((
            bevy_transform(&camera.c2w),
            projection_for(&k),
            RayMarchCamera {
                intrinsics: Some([k.fx, k.fy, k.cx, k.cy]),
                render_scale,
            },
        ));
        Ok(())
    }

    /// Fraction of each side the march renders (see
    /// [`RayMarchCamera::render_scale`]).
    pub fn set_render_scale(&mut self, scale: f32) {
        if let Some(mut c) = self.app.world_mut().get_mut::<RayMarchCamera>(self.camera) {
            c.render_scale = scale;
        }
    }

    /// Frames drawn and marches run so far (a still view draws without
    /// marching).
    pub fn frame_counts(&self) -> (u64, u64) {
        let s = self.status().get();
        (s.frames_drawn, s.marches)
    }

    pub fn set_scene(&mut self, scene: Arc<Scene>) {
        self.app.world_mut().resource_mut::<MarchScene>().scene = Some(scene);
    }

    /// The editor's per-layer overlay (tint / dim); empty for none.
    pub fn set_overlay(&mut self, overlay: Vec<super::gpu::pack::Overlay>) {
        self.app.world_mut().resource_mut::<MarchScene>().overlay = overlay;
    }

    /// Sample spacing along the rays (the CPU renderer's default:
    /// `Step::default()`).
    pub fn set_step(&mut self, step: crate::render::Step) {
        self.app.world_mut().resource_mut::<MarchScene>().step = step;
    }

    fn status(&self) -> SharedStatus {
        self.app.world().resource::<SharedStatus>().clone()
    }

    /// What the render world did last (level of detail, pool size, errors).
    pub fn render_status(&self) -> super::gpu::RenderStatus {
        self.status().get()
    }

    /// Bytes of GPU memory the view's pool textures may take (beyond it the
    /// view shows a coarser level of detail).
    pub fn set_memory_budget(&mut self, bytes: usize) {
        self.app.world_mut().resource_mut::<MarchScene>().memory_budget = bytes;
    }

    /// One frame, waiting for the GPU to finish it.
    pub fn step(&mut self) {
        self.app.update();
        if let Some(device) = self.app.world().get_resource::<RenderDevice>() {
            let _ = device
                .wgpu_device()
                .poll(bevy::render::render_resource::PollType::wait_indefinitely());
        }
    }

    /// Updates until the pass has drawn the current scene (pipelines
    /// compiled, grids uploaded).
    pub fn wait_drawn(&mut self) -> Result<()> {
        let status = self.status();
        let ptr = self
            .app
            .world()
            .resource::<MarchScene>()
            .scene
            .as_ref()
            .map(|s| Arc::as_ptr(s) as usize)
            .ok_or_else(|| Error::invalid("no scene to render"))?;
        let before = status.get().frames_drawn;
        for _ in 0..MAX_FRAMES {
            self.step();
            let s = status.get();
            if let Some(e) = s.error {
                return Err(Error::invalid(format!("GPU render: {e}")));
            }
            if s.frames_drawn > before && s.scene_drawn == ptr {
                return Ok(());
            }
        }
        Err(Error::invalid(
            "the GPU ray marcher drew nothing (pipeline never compiled?)",
        ))
    }

    /// Reads the target image back (sRGB bytes, RGBA, row-major).
    pub fn capture(&mut self) -> Result<Vec<u8>> {
        let slot: Arc<Mutex<Option<Image>>> = Arc::default();
        let out = slot.clone();
        self.app
            .world_mut()
            .spawn(Screenshot::image(self.target.clone()))
            .observe(move |shot: On<ScreenshotCaptured>| {
                if let Ok(mut s) = out.lock() {
                    *s = Some(shot.image.clone());
                }
            });
        for _ in 0..MAX_FRAMES {
            self.step();
            if let Some(img) = slot.lock().ok().and_then(|mut s| s.take()) {
                let data = img.data.ok_or_else(|| Error::invalid("screenshot has no pixel data"))?;
                let want = (self.width * self.height * 4) as usize;
                crate::ensure!(
                    data.len() == want,
                    "screenshot has {} bytes, expected {want}",
                    data.len()
                );
                return Ok(data);
            }
        }
        Err(Error::invalid("the screenshot never arrived"))
    }

    /// Renders `scene` seen by `camera`: colours in [0, 1], row-major.
    pub fn render(&mut self, scene: Arc<Scene>, camera: &Camera) -> Result<Vec<glam::Vec3>> {
        self.set_camera(camera)?;
        self.set_scene(scene);
        self.wait_drawn()?;
        let rgba = self.capture()?;
        Ok(rgba
            .chunks_exact(4)
            .map(|p| glam::Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32) / 255.0)
            .collect())
    }
}

/// Renders one frame of `scene` on the GPU, with no window (see
/// [`HeadlessRenderer`] to render several).
pub fn render_headless(scene: &Scene, camera: &Camera) -> Result<Vec<glam::Vec3>> {
    let k = camera.intrinsics;
    let mut r = HeadlessRenderer::new(k.width, k.height)?;
    r.render(Arc::new(scene.clone()), camera)
}

/// Whether wgpu finds an adapter on the backends bevy would use
/// (`WGPU_BACKEND` or the primary ones). Bevy panics without one, so callers
/// that may run on machines without a GPU check this first.
pub fn gpu_available() -> bool {
    let backends = wgpu::Backends::from_env().unwrap_or(wgpu::Backends::PRIMARY);
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
        backends,
        ..wgpu::InstanceDescriptor::new_without_display_handle()
    });
    !bevy::tasks::block_on(instance.enumerate_adapters(backends)).is_empty()
}

/// `Render` frames of edit scripts drawn by the GPU ray marcher (`isrf run
/// --gpu`); one window-less renderer, recreated when the frame size changes.
#[derive(Default)]
pub struct GpuFrames {
    renderer: Option<HeadlessRenderer>,
}

impl crate::command::FrameRenderer for GpuFrames {
    fn render_rgb(&mut self, scene: Arc<Scene>, camera: &Camera) -> Result<Vec<glam::Vec3>> {
        let k = camera.intrinsics;
        if self.renderer.as_ref().map(|r| r.size()) != Some((k.width, k.height)) {
            // Drop the old app (and its GPU buffers) before making the next.
            self.renderer = None;
            self.renderer = Some(HeadlessRenderer::new(k.width, k.height)?);
        }
        let r = self.renderer.as_mut().expect("created above");
        r.render(scene, camera)
    }
}
