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
    /// Apply the commands of this script at start-up (RON or JSON); its
    /// relative inputs (fields, strokes, cameras) are read from the
    /// script's folder, as `isrf run` reads them, and its outputs written to
    /// the working folder
    #[arg(long, value_name = "FILE")]
    pub script: Option<PathBuf>,
    /// Hide the panels (clean screenshots)
    #[arg(long, hide = true)]
    pub no_ui: bool,
    /// Replay the recovery file of an earlier session with the same inputs
    /// (files, scene, script, working folder) instead of starting fresh.
    /// Without --restore / --no-restore the editor asks when that session
    /// left edits behind
    #[arg(long, conflicts_with = "no_restore")]
    pub restore: bool,
    /// Start fresh even if an earlier session left a recovery file (it is
    /// kept as <name>.previous.json when this session first records)
    #[arg(long)]
    pub no_restore: bool,
    /// Folder of the recovery files (default: $ISRF_RECOVERY_DIR, else
    /// $XDG_STATE_HOME/isrf/recovery, else ~/.local/state/isrf/recovery)
    #[arg(long, value_name = "DIR")]
    pub recovery_dir: Option<PathBuf>,
    /// How many edits undo reaches back (older steps are dropped, and the
    /// grids of fields deleted before them freed)
    #[arg(long, value_name = "N", default_value_t = isrf::command::session::DEFAULT_UNDO_LIMIT)]
    pub undo_steps: usize,
}

fn parse_size(s: &str) -> std::result::Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("size '{s}' is not WxH"))?;
    let w: u32 = w.trim().parse().map_err(|_| format!("bad width in '{s}'"))?;
    let h: u32 = h.trim().parse().map_err(|_| format!("bad height in '{s}'"))?;
    let max = isrf::limits::MAX_TEXTURE_SIDE;
    if !(64..=max).contains(&w) || !(64..=max).contains(&h) {
        return Err(format!("window size {w}x{h} is out of range (64..={max})"));
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
        restore: match (a.restore, a.no_restore) {
            (true, _) => Some(true),
            (_, true) => Some(false),
            _ => None,
        },
        recovery_dir: a.recovery_dir,
        undo_steps: Some(a.undo_steps),
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
    /// Time this field file (e.g. one `isrf train` wrote) instead of a demo
    /// scene, from views around its box
    #[arg(long, value_name = "FIELD")]
    pub field: Option<std::path::PathBuf>,
}

#[cfg(feature = "editor")]
pub fn bench(a: BenchArgs) -> Result<()> {
    use isrf::app::headless::{gpu_available, HeadlessRenderer};
    use isrf::camera::{Camera, Intrinsics};
    use isrf::render::{Scene, Step};
    use std::sync::Arc;
    use std::time::Instant;

    anyhow::ensure!(a.frames >= 1, "--frames must be at least 1");
    anyhow::ensure!(
        gpu_available(),
        "no GPU adapter (on a machine without a GPU install mesa-vulkan-drivers and set WGPU_BACKEND=vulkan)"
    );
    if let Some(path) = &a.field {
        return bench_field(&a, path);
    }
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
    let mask = d
        .labels
        .label_of("mug")
        .or_else(|| d.objects.first().map(|o| o.label))
        .map(|l| Arc::new(d.labels.mask(l)));
    let field = Arc::new(d.field);
    let moved_scene = mask.map(|m| Arc::new(moved_object_scene(m, &field)));
    // (name, scene, sample spacing, march resolution scale).
    let single = Arc::new(Scene::single(field.clone()));
    let step = Step::default();
    let mut rows = vec![("field".to_string(), single.clone(), step, 1.0)];
    if let Some(m) = &moved_scene {
        rows.push(("field + one moved object".to_string(), m.clone(), step, 1.0));
    }
    // The editor's "step ×" slider at 2: half the samples, a coarser image.
    rows.push((
        "field, step ×2 (slider)".to_string(),
        single.clone(),
        step.scaled(2.0),
        1.0,
    ));
    // What the editor marches while the view moves on a software GPU.
    rows.push(("field, ½ res (moving)".to_string(), single.clone(), step, 0.5));
    if let Some(m) = &moved_scene {
        rows.push(("+ moved object, ½ res".to_string(), m.clone(), step, 0.5));
    }
    let views: Vec<Camera> = d
        .cameras
        .frames
        .iter()
        .step_by((d.cameras.frames.len() / 4).max(1))
        .map(|f| Camera::new(k, f.camera.c2w))
        .collect();
    println!("every timed frame marches: the camera moves a little between frames");
    println!("{:<28} {:>10} {:>10}", "scene", "ms/frame", "fps");
    let mut full_fps = 0.0;
    let mut moving_fps = 0.0;
    for (i, (name, scene, step, scale)) in rows.into_iter().enumerate() {
        r.set_step(step);
        r.set_render_scale(scale);
        let fps = time_frames(&mut r, scene, &views, a.frames, true)?;
        if i == 0 {
            full_fps = fps;
        }
        if scale < 1.0 && moving_fps == 0.0 {
            moving_fps = fps;
        }
        println!("{name:<28} {:>10.1} {:>10.2}", 1e3 / fps, fps);
    }
    // A still view composites the last march without marching again.
    r.set_step(step);
    r.set_render_scale(1.0);
    let still = time_frames(&mut r, single, &views, a.frames, false)?;
    println!("{:<28} {:>10.1} {:>10.2}", "field, still view", 1e3 / still, still);
    if let Some(object) = &stroke_object {
        // The session's first stroke also compiles the pipeline variant that
        // tints a selection (on lavapipe about 0.1 s more); later ones reuse
        // it.
        stroke_to_visible(
            &mut r,
            &a,
            object,
            &views[0],
            1.0,
            ", first stroke, compiling its pipeline",
        )?;
        stroke_to_visible(&mut r, &a, object, &views[0], 1.0, "")?;
        // The editor's first image of a change on a software GPU.
        stroke_to_visible(&mut r, &a, object, &views[0], 0.5, "")?;
    }
    println!("fps while moving (½ resolution, the editor's default on software GPUs): {moving_fps:.2}");
    println!("fps: {full_fps:.2}");
    Ok(())
}

/// `isrf bench editor --field`: frames per second of a field file, from
/// four views around its box, with the whole field, half resolution, and an
/// object (the occupied voxels of the box's central eighth) moved.
#[cfg(feature = "editor")]
fn bench_field(a: &BenchArgs, path: &std::path::Path) -> Result<()> {
    use isrf::app::headless::HeadlessRenderer;
    use isrf::field::Bitmap;
    use isrf::render::Scene;
    use std::sync::Arc;
    use std::time::Instant;

    let t0 = Instant::now();
    let field = Arc::new(isrf::field::io::load(path)?);
    let res = field.res();
    println!(
        "editor view (GPU ray marcher), {} ({}x{}x{}) loaded in {:.1} s, {}x{} pixels",
        path.display(),
        res[0],
        res[1],
        res[2],
        t0.elapsed().as_secs_f64(),
        a.width,
        a.height
    );
    let mut r = HeadlessRenderer::new(a.width, a.height)?;
    if let Some(info) = r.adapter_info() {
        println!("adapter: {info}");
    }
    let views = match field.ndc {
        Some(n) => ndc_views(n, a.width, a.height),
        None => orbit_views(field.bounds(), a.width, a.height),
    };
    // The object: occupied voxels in the central eighth of the box.
    let mid = |i: usize, a: usize| (res[a] / 4..3 * res[a] / 4).contains(&i);
    let mask = Arc::new(Bitmap::from_fn(res, |v| {
        let (x, y, z) = (v % res[0], v / res[0] % res[1], v / (res[0] * res[1]));
        mid(x, 0) && mid(y, 1) && mid(z, 2) && field.density.sigma_at(v) > 0.01
    }));
    let single = Arc::new(Scene::single(field.clone()));
    let moved = Arc::new(moved_object_scene(mask, &field));
    let t1 = Instant::now();
    r.set_camera(&views[0])?;
    r.set_scene(single.clone());
    r.wait_drawn()?;
    let status = r.render_status();
    println!(
        "first frame (pack + upload + pipeline) {:.1} s; GPU pool {} MB, upload {:.0} ms{}",
        t1.elapsed().as_secs_f64(),
        status.pool_bytes.div_ceil(1 << 20),
        status.upload_ms,
        status.detail.map(|d| format!("; {d}")).unwrap_or_default()
    );
    println!("every timed frame marches: the camera moves a little between frames");
    println!("{:<28} {:>10} {:>10}", "scene", "ms/frame", "fps");
    let rows = [
        ("field", single.clone(), 1.0),
        ("field + one moved object", moved.clone(), 1.0),
        ("field, ½ res (moving)", single.clone(), 0.5),
    ];
    let mut full_fps = 0.0;
    for (i, (name, scene, scale)) in rows.into_iter().enumerate() {
        r.set_render_scale(scale);
        let fps = time_frames(&mut r, scene, &views, a.frames, true)?;
        if i == 0 {
            full_fps = fps;
        }
        println!("{name:<28} {:>10.1} {:>10.2}", 1e3 / fps, fps);
    }
    println!("fps: {full_fps:.2}");
    Ok(())
}

/// Four views around a field's box, from the −z side.
#[cfg(feature = "editor")]
fn orbit_views(b: isrf::field::Aabb, width: u32, height: u32) -> Vec<isrf::camera::Camera> {
    use isrf::camera::{Camera, Intrinsics};
    let (centre, size) = ((b.min + b.max) * 0.5, b.max - b.min);
    let k = Intrinsics::from_fov_x(width, height, 50f32.to_radians());
    let dist = 1.3 * size.length();
    [(-0.5f32, 0.3f32), (0.5, 0.3), (-0.2, -0.2), (0.2, 0.6)]
        .iter()
        .map(|&(yaw, pitch)| {
            let dir = glam::Vec3::new(yaw.sin() * pitch.cos(), pitch.sin(), -yaw.cos() * pitch.cos());
            Camera::look_at(k, centre + dir * dist, centre, glam::Vec3::Y)
        })
        .collect()
}

/// Four views of a forward-facing (NDC) field as its capture saw it: the
/// NDC's reference pinhole (its field of view, this size), moved and turned
/// a little, seen through the NDC.
#[cfg(feature = "editor")]
fn ndc_views(n: isrf::camera::Ndc, width: u32, height: u32) -> Vec<isrf::camera::Camera> {
    use isrf::camera::{Camera, Intrinsics};
    let fov_x = 2.0 * (0.5 * n.width as f32 / n.focal).atan();
    let k = Intrinsics::from_fov_x(width, height, fov_x);
    [(-0.05f32, 0.1f32), (0.05, -0.1), (0.0, 0.05), (0.03, 0.0)]
        .iter()
        .map(|&(yaw, x)| {
            let pose = glam::Affine3A::from_rotation_translation(
                glam::Quat::from_rotation_y(yaw),
                glam::Vec3::new(x, 0.5 * x, 0.0),
            );
            Camera::new(k, pose).with_ndc(Some(n))
        })
        .collect()
}

/// The bench's two-layer scene: an object (`mask`) cut out of the field
/// and moved.
#[cfg(feature = "editor")]
fn moved_object_scene(
    mask: std::sync::Arc<isrf::field::Bitmap>,
    field: &std::sync::Arc<isrf::field::Field>,
) -> isrf::render::Scene {
    use isrf::render::{Layer, Mask, Scene};
    let mut rest = Layer::new(field.clone());
    rest.mask = Mask::Remove(mask.clone());
    let mut moved = Layer::new(field.clone());
    moved.mask = Mask::Keep(mask);
    moved.to_world = glam::Affine3A::from_translation(glam::Vec3::new(0.3, 0.0, 0.25));
    Scene::new(vec![rest, moved])
}

/// Frames per second drawing `scene` from each of `views` in turn. With
/// `moving`, the camera shifts by a hair every frame so that each frame
/// marches (checked); otherwise the view is still and frames only
/// composite.
#[cfg(feature = "editor")]
fn time_frames(
    r: &mut isrf::app::headless::HeadlessRenderer,
    scene: std::sync::Arc<isrf::render::Scene>,
    views: &[isrf::camera::Camera],
    frames: usize,
    moving: bool,
) -> Result<f64> {
    use anyhow::Context;
    use std::time::Instant;
    let per_view = frames.div_ceil(views.len()).max(1);
    let mut total = 0.0;
    let mut n = 0;
    for cam in views {
        r.set_camera(cam)?;
        r.set_scene(scene.clone());
        r.wait_drawn().context("first frame")?;
        let (_, marches0) = r.frame_counts();
        let t = Instant::now();
        for f in 0..per_view {
            if moving {
                let mut c = *cam;
                let shift = if f % 2 == 0 { 1e-4 } else { 0.0 };
                c.c2w.translation += c.c2w.matrix3.x_axis * shift;
                r.set_camera(&c)?;
            }
            r.step();
        }
        total += t.elapsed().as_secs_f64();
        n += per_view;
        let marched = (r.frame_counts().1 - marches0) as usize;
        anyhow::ensure!(
            marched == if moving { per_view } else { 0 },
            "{marched} of {per_view} frames marched"
        );
    }
    Ok(n as f64 / total)
}

/// Times a demo stroke as the editor runs it: the session's `Stroke`
/// command (features, k-means, NNFM, growth), the scene rebuild with the new
/// object selected and tinted, the mask upload and the first GPU frame that
/// shows it, marched at `scale` of each side.
#[cfg(feature = "editor")]
fn stroke_to_visible(
    r: &mut isrf::app::headless::HeadlessRenderer,
    a: &BenchArgs,
    object: &str,
    view: &isrf::camera::Camera,
    scale: f32,
    note: &str,
) -> Result<()> {
    use isrf::app::layers::{build_scene, OverlayMode};
    use isrf::command::{Edit, FieldSource, Session, StrokeSource};
    use std::sync::Arc;
    use std::time::Instant;

    let mut s = Session::default();
    s.apply(&Edit::LoadField {
        name: a.scene.clone(),
        source: FieldSource::Demo {
            scene: a.scene.clone(),
            res: a.res,
            seed: 0,
        },
        transform: None,
    })?;
    // As in the editor after loading: features cached, the field on the GPU.
    s.state().fields[0].field.feature_cache()?;
    let mode = OverlayMode {
        tint_selected: true,
        dim_others: false,
    };
    let show = |r: &mut isrf::app::headless::HeadlessRenderer, s: &Session, selected: Option<&str>| -> Result<()> {
        let selected = selected.and_then(|n| s.object(n).ok()).map(|o| o.id);
        let (scene, overlay) = build_scene(s.state(), &[], selected, mode);
        r.set_scene(Arc::new(scene));
        r.set_overlay(overlay);
        r.wait_drawn()?;
        Ok(())
    };
    r.set_render_scale(scale);
    r.set_camera(view)?;
    show(r, &s, None)?;
    let marches = r.frame_counts().1;
    let t0 = Instant::now();
    s.apply(&Edit::Stroke {
        object: object.to_string(),
        field: None,
        polarity: None,
        source: StrokeSource::Demo {
            object: object.to_string(),
        },
    })?;
    let seg = t0.elapsed().as_secs_f64() * 1e3;
    show(r, &s, Some(object))?;
    let total = t0.elapsed().as_secs_f64() * 1e3;
    anyhow::ensure!(r.frame_counts().1 > marches, "the stroke's result was never marched");
    let res = if scale < 1.0 { " (½ res image)" } else { "" };
    println!(
        "stroke -> visible{res}{note}: {total:.0} ms (segmentation {seg:.0} ms, scene + mask upload + frame {:.0} ms)",
        total - seg
    );
    r.set_render_scale(1.0);
    Ok(())
}

#[cfg(not(feature = "editor"))]
pub fn bench(_a: BenchArgs) -> Result<()> {
    anyhow::bail!("this isrf was built without the editor: rebuild with `cargo build --features editor`")
}
