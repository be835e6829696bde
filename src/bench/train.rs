//! Trainer throughput: rays/s, samples/s and iterations/s per
//! coarse-to-fine stage and in the distillation phase, on a real dataset or,
//! with none given, on a capture rendered from a demo scene (colour from the
//! reference renderer, teacher maps from its rendered features), so the
//! benchmark runs anywhere.

use super::Table;
use crate::camera::Camera;
use crate::data::Image;
use crate::error::Result;
use crate::render::{render, RenderOptions, Scene};
use crate::train::{FeatureMap, FeatureMaps, RaySet, StepStats, TrainConfig, Trainer};
use glam::Vec3;
use std::sync::Arc;

/// A posed capture of a demo scene: images and teacher maps per view.
pub struct DemoCapture {
    pub cameras: Vec<Camera>,
    pub images: Vec<Image>,
    /// The scene's rendered features at each view, at the image size.
    pub teacher: FeatureMaps,
    pub truth: Scene,
}

/// Renders `scene` (built at `res`³) from `n` views of `width` pixels wide
/// spread over the front half of its orbit at elevations 8°–50°.
pub fn demo_capture(scene: &str, res: usize, n: usize, width: u32) -> Result<DemoCapture> {
    let demo = crate::demo::build(scene, res, 0)?;
    let orbit: Vec<Camera> = demo.cameras.frames.iter().map(|f| f.camera).collect();
    let cameras = views_around(&orbit, n, width);
    let truth = Scene::single(Arc::new(demo.field));
    let opts = RenderOptions {
        features: true,
        depth: false,
        ..Default::default()
    };
    let mut images = vec![];
    let mut maps = vec![];
    let mut channels = 0;
    for c in &cameras {
        let f = render(&truth, c, &opts)?;
        channels = f.out.features.len() / (f.width * f.height) as usize;
        images.push(Image {
            width: f.width,
            height: f.height,
            rgb: f.out.color.iter().flat_map(|c| c.to_array()).collect(),
            alpha: None,
        });
        maps.push(FeatureMap::from_frame(f));
    }
    Ok(DemoCapture {
        cameras,
        images,
        teacher: FeatureMaps::new(channels, maps)?,
        truth,
    })
}

/// Centre and distance of a demo scene's orbit (its cameras ring the centre
/// at [`crate::demo::ORBIT_ELEVATION_DEG`]).
pub fn orbit_centre(orbit: &[Camera]) -> (Vec3, f32) {
    let m = orbit.len().max(1) as f32;
    let ring = orbit.iter().map(|c| c.position()).sum::<Vec3>() / m;
    let r_h = orbit.iter().map(|c| (c.position() - ring).length()).sum::<f32>() / m;
    let elev = crate::demo::ORBIT_ELEVATION_DEG.to_radians();
    let radius = r_h / elev.cos();
    (ring - Vec3::Y * radius * elev.sin(), radius)
}

/// `n` cameras looking at the orbit's centre from the orbit's distance.
fn views_around(orbit: &[Camera], n: usize, width: u32) -> Vec<Camera> {
    let (center, radius) = orbit_centre(orbit);
    let factor = (orbit[0].intrinsics.width / width.max(1)).max(1);
    let k = orbit[0].intrinsics.downscaled(factor);
    (0..n)
        .map(|i| {
            let a = (-115.0 + 245.0 * (i as f32 + 0.5) / n as f32).to_radians();
            let e = (8.0 + 42.0 * (i % 4) as f32 / 3.0).to_radians();
            let eye = center + radius * Vec3::new(e.cos() * a.sin(), e.sin(), e.cos() * a.cos());
            Camera::look_at(k, eye, center, Vec3::Y)
        })
        .collect()
}

/// Throughput of one stage of a run.
#[derive(Clone, Debug)]
pub struct StageRow {
    pub phase: &'static str,
    pub res: [usize; 3],
    pub iters: usize,
    pub rays: u64,
    pub samples: u64,
    pub seconds: f64,
    /// Seconds in the optimizer (the rest marches rays).
    pub update_seconds: f64,
    pub last_psnr: f32,
}

impl StageRow {
    pub fn rays_per_s(&self) -> f64 {
        self.rays as f64 / self.seconds.max(1e-9)
    }
    pub fn iters_per_s(&self) -> f64 {
        self.iters as f64 / self.seconds.max(1e-9)
    }
}

/// Runs `trainer` to the end and groups its steps by phase and grid.
pub fn run_and_measure(trainer: &mut Trainer, mut on_step: impl FnMut(&StepStats)) -> Result<Vec<StageRow>> {
    let mut rows: Vec<StageRow> = vec![];
    while !trainer.is_done() {
        let phase = if trainer.in_feature_phase() {
            "features"
        } else {
            "radiance"
        };
        let s = trainer.step()?;
        on_step(&s);
        let res = trainer.model.geom.res;
        let row = match rows.last_mut() {
            Some(r) if r.phase == phase && r.res == res => r,
            _ => {
                rows.push(StageRow {
                    phase,
                    res,
                    iters: 0,
                    rays: 0,
                    samples: 0,
                    seconds: 0.0,
                    update_seconds: 0.0,
                    last_psnr: 0.0,
                });
                rows.last_mut().expect("just pushed")
            }
        };
        row.iters += 1;
        row.rays += s.rays as u64;
        row.samples += s.samples;
        row.seconds += s.seconds as f64;
        row.update_seconds += s.update_seconds as f64;
        row.last_psnr = s.psnr;
    }
    Ok(rows)
}

/// A trainer on a demo capture with its rendered features as the teacher.
pub fn demo_trainer(capture: &DemoCapture, config: TrainConfig) -> Result<Trainer> {
    let views: Vec<(Camera, &Image)> = capture.cameras.iter().copied().zip(&capture.images).collect();
    let rays = RaySet::build(&views)?;
    let mut t = Trainer::new(config, rays, crate::demo::bounds())?;
    t.set_teacher(capture.teacher.clone());
    Ok(t)
}

pub fn stage_table(rows: &[StageRow]) -> Table {
    let mut t = Table::new(&[
        "phase",
        "grid",
        "iters",
        "it/s",
        "rays/s",
        "samples/ray",
        "update",
        "train PSNR",
    ]);
    for r in rows {
        t.row(vec![
            r.phase.into(),
            format!("{}x{}x{}", r.res[0], r.res[1], r.res[2]),
            r.iters.to_string(),
            format!("{:.2}", r.iters_per_s()),
            format!("{:.0}", r.rays_per_s()),
            format!("{:.1}", r.samples as f64 / r.rays.max(1) as f64),
            format!("{:.0} %", 100.0 * r.update_seconds / r.seconds.max(1e-9)),
            format!("{:.2}", r.last_psnr),
        ]);
    }
    t
}

/// Iterations, rays and seconds over the rows of one phase.
pub fn totals(rows: &[StageRow], phase: &str) -> (usize, u64, f64) {
    rows.iter()
        .filter(|r| r.phase == phase)
        .fold((0, 0, 0.0), |(i, n, s), r| (i + r.iters, n + r.rays, s + r.seconds))
}
