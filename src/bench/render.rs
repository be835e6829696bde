//! Rays per second of the CPU reference renderer ([`crate::render::render`])
//! on a demo scene, seen from a few of its orbit cameras.
//!
//! The one-off per-field work is built and timed first (the macro grid for
//! empty-space skipping, which the renderer needs, and the feature cache,
//! which segmentation needs), then one untimed warm-up frame is rendered, then
//! each camera is rendered once with colour + depth and once with features
//! too.

use super::{load_average, repeat, time_ms, Table};
use crate::camera::{Camera, Intrinsics};
use crate::error::Result;
use crate::render::{render, RenderOptions, Scene};
use std::sync::Arc;

#[derive(Clone, Debug)]
pub struct RenderBenchRow {
    pub scene: String,
    pub res: usize,
    /// Voxels with σ > 0.
    pub occupied: usize,
    pub field_bytes: usize,
    pub scene_build_ms: f64,
    pub macro_build_ms: f64,
    pub cache_build_ms: f64,
    pub width: u32,
    pub height: u32,
    pub frames: usize,
    pub load_average: Option<f64>,
    /// Colour + depth.
    pub plain: FrameTimes,
    /// Colour + depth + semantic features.
    pub features: FrameTimes,
}

/// `camera` with the same field of view at `width × height` pixels.
pub fn resized(camera: &Camera, width: u32, height: u32) -> Camera {
    let k = camera.intrinsics;
    let (sx, sy) = (width as f32 / k.width as f32, height as f32 / k.height as f32);
    let intr = Intrinsics {
        width,
        height,
        fx: k.fx * sx,
        fy: k.fy * sy,
        cx: k.cx * sx,
        cy: k.cy * sy,
    };
    Camera {
        intrinsics: intr,
        ..*camera
    }
}

/// `n` cameras spread evenly over `all` (wrapping round when `n` exceeds it).
fn spread(all: &[Camera], n: usize) -> Vec<Camera> {
    (0..n).map(|i| all[(i * all.len() / n.max(1)) % all.len()]).collect()
}

/// Frame times of one render setting.
#[derive(Clone, Copy, Debug)]
pub struct FrameTimes {
    /// Median wall time per frame.
    pub ms_per_frame: f64,
    /// Median CPU time (all threads) per frame, where measurable.
    pub cpu_ms_per_frame: Option<f64>,
    /// All rays of all frames over their total wall time.
    pub rays_per_s: f64,
}

/// Renders every camera once.
fn time_frames(scene: &Scene, cams: &[Camera], opts: &RenderOptions) -> Result<FrameTimes> {
    let mut rays = 0u64;
    for c in cams {
        rays += c.intrinsics.width as u64 * c.intrinsics.height as u64;
    }
    let (mut i, mut err) = (0, None);
    let t = repeat(cams.len(), f64::INFINITY, || {
        if let Err(e) = render(scene, &cams[i], opts) {
            err.get_or_insert(e);
        }
        i += 1;
    });
    if let Some(e) = err {
        return Err(e);
    }
    let total_s = t.runs_ms.iter().sum::<f64>() / 1e3;
    Ok(FrameTimes {
        ms_per_frame: t.median_ms(),
        cpu_ms_per_frame: t.median_cpu_ms(),
        rays_per_s: rays as f64 / total_s.max(1e-9),
    })
}

/// Builds demo scene `scene_name` at `res`³ and measures the renderer on it.
pub fn bench_render(scene_name: &str, res: usize, width: u32, height: u32, frames: usize) -> Result<RenderBenchRow> {
    crate::ensure_within!(
        OutOfRange,
        crate::limits::image_size_ok(width, height),
        "image size {width}x{height} is out of range"
    );
    crate::ensure_within!(
        OutOfRange,
        (1..=1000).contains(&frames),
        "frames must be 1..=1000, got {frames}"
    );
    let (demo, scene_build_ms) = time_ms(|| crate::demo::build(scene_name, res, 0));
    let demo = demo?;
    let occupied = demo.occupied();
    let all: Vec<Camera> = demo.cameras.frames.iter().map(|f| f.camera).collect();
    crate::ensure!(!all.is_empty(), "demo scene '{scene_name}' has no cameras");
    let cams: Vec<Camera> = spread(&all, frames).iter().map(|c| resized(c, width, height)).collect();
    let field = Arc::new(demo.field);
    let field_bytes = field.memory_bytes();
    let (_, macro_build_ms) = time_ms(|| field.macro_grid().occupied_fraction());
    let (cache, cache_build_ms) = time_ms(|| field.feature_cache());
    cache?;
    let scene = Scene::single(field);
    let plain = RenderOptions::default();
    let with_features = RenderOptions {
        features: true,
        ..Default::default()
    };
    render(&scene, &cams[0], &plain)?; // warm-up: threads, page faults, caches
    let load_average = load_average();
    let plain = time_frames(&scene, &cams, &plain)?;
    let features = time_frames(&scene, &cams, &with_features)?;
    Ok(RenderBenchRow {
        scene: scene_name.to_string(),
        res,
        occupied,
        field_bytes,
        scene_build_ms,
        macro_build_ms,
        cache_build_ms,
        width,
        height,
        frames,
        load_average,
        plain,
        features,
    })
}

/// The table of `isrf bench render`.
pub fn render_table(rows: &[RenderBenchRow]) -> Table {
    let mut t = Table::new(&[
        "res",
        "occupied voxels",
        "field MB",
        "image",
        "frames",
        "ms/frame",
        "cpu ms/frame",
        "rays/s",
        "ms/frame +feat",
        "cpu ms +feat",
        "rays/s +feat",
    ]);
    let cpu = |v: Option<f64>| v.map_or_else(|| "-".into(), |x| format!("{x:.1}"));
    for r in rows {
        t.row(vec![
            format!("{}^3", r.res),
            r.occupied.to_string(),
            format!("{:.1}", r.field_bytes as f64 / 1e6),
            format!("{}x{}", r.width, r.height),
            r.frames.to_string(),
            format!("{:.1}", r.plain.ms_per_frame),
            cpu(r.plain.cpu_ms_per_frame),
            format!("{:.0}", r.plain.rays_per_s),
            format!("{:.1}", r.features.ms_per_frame),
            cpu(r.features.cpu_ms_per_frame),
            format!("{:.0}", r.features.rays_per_s),
        ]);
    }
    t
}

/// The one-off build times, one table row per resolution.
pub fn build_table(rows: &[RenderBenchRow]) -> Table {
    let mut t = Table::new(&[
        "res",
        "demo scene build ms",
        "macro grid build ms",
        "feature cache build ms",
    ]);
    for r in rows {
        t.row(vec![
            format!("{}^3", r.res),
            format!("{:.0}", r.scene_build_ms),
            format!("{:.1}", r.macro_build_ms),
            format!("{:.1}", r.cache_build_ms),
        ]);
    }
    t
}
