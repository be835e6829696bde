//! `isrf edit`: the interactive editor (needs the `editor` cargo feature),
//! and `isrf bench editor`'s measurement of its GPU view.

use anyhow::Result;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Field files (.safetensors) to compose, or one composition (.ron / .json)
    pub files: Vec<PathBuf>,
    /// Demo scene to open when no file is given (tabletop, shelf)
    #[arg(long)]
    pub scene: Option<String>,
    /// Grid resolution of the demo scene
    #[arg(long, default_value_t = 96)]
    pub res: usize,
    /// Save a screenshot once everything is rendered, then exit
    #[arg(long, value_name = "OUT.png")]
    pub screenshot: Option<PathBuf>,
    /// Window size in logical pixels, WxH
    #[arg(long, default_value = "1280x720", value_parser = parse_size)]
    pub size: (u32, u32),
    /// Apply the commands of this script at start-up (RON or JSON)
    #[arg(long, value_name = "FILE")]
    pub script: Option<PathBuf>,
    /// Hide the panels (clean screenshots)
    #[arg(long, hide = true)]
    pub no_ui: bool,
}

fn parse_size(s: &str) -> std::result::Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("size '{s}' is not WxH"))?;
    let w: u32 = w.trim().parse().map_err(|_| format!("bad width in '{s}'"))?;
    let h: u32 = h.trim().parse().map_err(|_| format!("bad height in '{s}'"))?;
    if !(64..=8192).contains(&w) || !(64..=8192).contains(&h) {
        return Err(format!("window size {w}x{h} is out of range (64..=8192)"));
    }
    Ok((w, h))
}

#[cfg(feature = "editor")]
pub fn run(a: Args) -> Result<()> {
    use isrf::app::editor::{run, EditorOptions};
    run(EditorOptions {
        scene: a.scene,
        files: a.files,
        res: a.res,
        script: a.script,
        screenshot: a.screenshot,
        size: a.size,
        no_ui: a.no_ui,
    })?;
    Ok(())
}

#[cfg(not(feature = "editor"))]
pub fn run(_a: Args) -> Result<()> {
    anyhow::bail!("this isrf was built without the editor: rebuild with `cargo build --features editor`")
}

#[derive(clap::Args)]
pub struct BenchArgs {
    /// Demo scene
    #[arg(long, default_value = "tabletop")]
    pub scene: String,
    /// Grid resolution
    #[arg(long, default_value_t = 128)]
    pub res: usize,
    /// Image width
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height
    #[arg(long, default_value_t = 360)]
    pub height: u32,
    /// Frames timed per measurement
    #[arg(long, default_value_t = 10)]
    pub frames: usize,
}

#[cfg(feature = "editor")]
pub fn bench(a: BenchArgs) -> Result<()> {
    use anyhow::Context;
    use isrf::app::headless::{gpu_available, HeadlessRenderer};
    use isrf::camera::{Camera, Intrinsics};
    use isrf::render::{Layer, Mask, Scene};
    use std::sync::Arc;
    use std::time::Instant;

    anyhow::ensure!(a.frames >= 1, "--frames must be at least 1");
    anyhow::ensure!(
        gpu_available(),
        "no GPU adapter (on a machine without a GPU install mesa-vulkan-drivers and set WGPU_BACKEND=vulkan)"
    );
    let t0 = Instant::now();
    let d = isrf::demo::build(&a.scene, a.res, 0)?;
    println!(
        "editor view (GPU ray marcher), {} demo scene {r}x{r}x{r} built in {:.1} s, {}x{} pixels",
        a.scene,
        t0.elapsed().as_secs_f64(),
        a.width,
        a.height,
        r = a.res
    );
    let mut r = HeadlessRenderer::new(a.width, a.height)?;
    if let Some(info) = r.adapter_info() {
        println!("adapter: {info}");
    }
    let k = Intrinsics::from_fov_x(a.width, a.height, 50f32.to_radians());
    // The object the stroke timing segments: the mug, else the first one.
    let stroke_object = d.object("mug").or(d.objects.first()).map(|o| o.name.clone());
    let field = Arc::new(d.field);
    // (name, scene, sample spacing; None = the renderer's default).
    let mut scenes = vec![("field".to_string(), Scene::single(field.clone()), None)];
    if let Some(label) = d.labels.label_of("mug").or_else(|| d.objects.first().map(|o| o.label)) {
        let mask = Arc::new(d.labels.mask(label));
        let mut rest = Layer::new(field.clone());
        rest.mask = Mask::Remove(mask.clone());
        let mut moved = Layer::new(field.clone());
        moved.mask = Mask::Keep(mask);
        moved.to_world = glam::Affine3A::from_translation(glam::Vec3::new(0.3, 0.0, 0.25));
        scenes.push((
            "field + one moved object".to_string(),
            Scene::new(vec![rest, moved]),
            None,
        ));
    }
    // The editor's "step ×" slider at 2: half the samples, a coarser image.
    let coarse = Scene::single(field.clone());
    let step = coarse.default_step() * 2.0;
    scenes.push(("field, step ×2 (slider)".to_string(), coarse, Some(step)));
    let views: Vec<Camera> = d
        .cameras
        .frames
        .iter()
        .step_by((d.cameras.frames.len() / 4).max(1))
        .map(|f| Camera::new(k, f.camera.c2w))
        .collect();
    println!("{:<28} {:>10} {:>10}", "scene", "ms/frame", "fps");
    let mut first_fps = 0.0;
    for (i, (name, scene, step)) in scenes.into_iter().enumerate() {
        let scene = Arc::new(scene);
        let mut total = 0.0;
        let mut n = 0;
        r.set_step(step);
        for cam in &views {
            r.set_camera(cam)?;
            r.set_scene(scene.clone());
            r.wait_drawn().context("first frame")?;
            let t = Instant::now();
            let frames = a.frames.div_ceil(views.len()).max(1);
            for _ in 0..frames {
                r.step();
            }
            total += t.elapsed().as_secs_f64();
            n += frames;
        }
        let fps = n as f64 / total;
        if i == 0 {
            first_fps = fps;
        }
        println!("{name:<28} {:>10.1} {:>10.2}", 1e3 / fps, fps);
    }
    r.set_step(None);
    if let Some(object) = &stroke_object {
        stroke_to_visible(&mut r, &a, object, &views[0])?;
    }
    println!("fps: {first_fps:.2}");
    Ok(())
}

/// Times a demo stroke as the editor runs it: the session's `Stroke`
/// command (features, k-means, NNFM, growth), the scene rebuild, the mask
/// upload and the first GPU frame that shows it.
#[cfg(feature = "editor")]
fn stroke_to_visible(
    r: &mut isrf::app::headless::HeadlessRenderer,
    a: &BenchArgs,
    object: &str,
    view: &isrf::camera::Camera,
) -> Result<()> {
    use isrf::command::session::scene_of;
    use isrf::command::{Command, FieldSource, Session, StrokeSource};
    use std::sync::Arc;
    use std::time::Instant;

    let mut s = Session::default();
    s.apply(&Command::LoadField {
        name: a.scene.clone(),
        source: FieldSource::Demo {
            scene: a.scene.clone(),
            res: a.res,
            seed: 0,
        },
        transform: None,
    })?;
    // As in the editor after loading: features cached, the field on the GPU.
    s.state.fields[0].field.feature_cache()?;
    r.set_camera(view)?;
    r.set_scene(Arc::new(scene_of(&s.state).0));
    r.wait_drawn()?;
    let t0 = Instant::now();
    s.apply(&Command::Stroke {
        object: object.to_string(),
        field: None,
        polarity: None,
        source: StrokeSource::Demo {
            object: object.to_string(),
        },
    })?;
    let seg = t0.elapsed().as_secs_f64() * 1e3;
    r.set_scene(Arc::new(scene_of(&s.state).0));
    r.wait_drawn()?;
    let total = t0.elapsed().as_secs_f64() * 1e3;
    println!(
        "stroke -> visible: {total:.0} ms (segmentation {seg:.0} ms, mask upload + frame {:.0} ms)",
        total - seg
    );
    Ok(())
}

#[cfg(not(feature = "editor"))]
pub fn bench(_a: BenchArgs) -> Result<()> {
    anyhow::bail!("this isrf was built without the editor: rebuild with `cargo build --features editor`")
}
