//! Procedural demo scenes with per-voxel ground truth, so that every part of
//! isrf runs with no download and segmentation quality has known answers.
//!
//! A scene is a recipe of objects made of parts made of signed-distance
//! primitives ([`tabletop`], [`shelf`]), voxelised directly into a field:
//! density with [`Activation::Relu`](crate::field::Activation) (σ ≈ 3/voxel
//! inside, smooth 1.5-voxel falloff, 0 in empty space), an occupancy index of
//! the voxels with σ > 0, and sparse RGB colours and 32-channel semantic
//! features over it (see [`features`] for how the features imitate distilled
//! DINO features). Everything is a pure function of (name, resolution, seed).
//!
//! Coordinates: bounds [-1, 1]³, y up, floor top at y = [`recipe::FLOOR_Y`].

pub mod features;
pub mod labels;
pub mod recipe;
pub mod sdf;
pub mod shelf;
pub mod strokes;
pub mod tabletop;
pub mod texture;
mod voxelize;

pub use labels::Labels;

use crate::camera::set::affine_to_rows;
use crate::camera::{Camera, CameraFrame, CameraSet, Intrinsics};
use crate::error::{write_atomic, Error, Result};
use crate::field::{Aabb, Field, GridGeom};
use glam::Vec3;
use serde::Serialize;
use std::path::{Path, PathBuf};

pub const MIN_RES: usize = 16;
pub const MAX_RES: usize = 512;
pub const DEFAULT_RES: usize = 128;
/// Image size of every demo camera.
pub const WIDTH: u32 = 400;
pub const HEIGHT: u32 = 300;
pub const ORBIT_FRAMES: usize = 24;
pub const ORBIT_ELEVATION_DEG: f32 = 25.0;
pub const EVAL_FRAMES: usize = 8;
/// Brush radius written with the built-in strokes (the authors' 7×7 brush).
pub const STROKE_RADIUS: u32 = 3;

/// The scenes [`build`] knows.
pub fn names() -> &'static [&'static str] {
    &["tabletop", "shelf"]
}

/// World box of every demo scene.
pub fn bounds() -> Aabb {
    Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0))
}

#[derive(Clone, Debug)]
pub struct DemoObject {
    pub name: String,
    /// Its value in [`DemoScene::labels`] (1-based).
    pub label: u8,
    /// Part names; part 0 is the base part.
    pub parts: Vec<String>,
    /// World points on the object's surface, visible from the stroke camera;
    /// a brush of [`STROKE_RADIUS`] along the polyline through them touches
    /// only this object (5–15 points from about 48³ up; fewer, even none,
    /// for small objects on very coarse grids).
    pub stroke: Vec<Vec3>,
}

#[derive(Debug)]
pub struct DemoScene {
    pub name: String,
    pub field: Field,
    pub labels: Labels,
    /// Orbit of [`ORBIT_FRAMES`] views (`./frame_000`, …).
    pub cameras: CameraSet,
    /// Held-out views for 2D evaluation, none of them in the orbit.
    pub eval_cameras: CameraSet,
    /// A view from which every object's stroke is visible.
    pub stroke_camera: Camera,
    pub objects: Vec<DemoObject>,
    /// Part index (within its object) of every occupied voxel, in occupancy
    /// order (the slot order of the field's sparse grids).
    pub voxel_parts: Vec<u8>,
}

/// A demo grid's points per axis must lie in `MIN_RES..=MAX_RES`.
pub fn check_res(r: usize) -> Result<()> {
    crate::ensure_within!(
        OutOfRange,
        (MIN_RES..=MAX_RES).contains(&r),
        "demo resolution {r} is out of range ({MIN_RES}..={MAX_RES})"
    );
    Ok(())
}

/// Builds scene `name` at `res`³ grid points, deterministic for `seed`.
pub fn build(name: &str, res: usize, seed: u64) -> Result<DemoScene> {
    build_grid(name, [res; 3], seed)
}

/// Builds scene `name` on a grid of `res` points per axis (over the same
/// box: other than cubic grids have voxels longer along some axes, which
/// makes large flat grids such as 512 × 512 × 128 for memory tests).
pub fn build_grid(name: &str, res: [usize; 3], seed: u64) -> Result<DemoScene> {
    for r in res {
        check_res(r)?;
    }
    let geom = GridGeom::new(bounds(), res);
    // Primitives are made at the finest voxel size.
    let voxel = geom.spacing().min_element();
    let recipe = match name {
        "tabletop" => tabletop::recipe(seed, voxel),
        "shelf" => shelf::recipe(seed, voxel),
        _ => {
            return Err(Error::invalid(format!(
                "unknown demo scene '{name}' (known: {})",
                names().join(", ")
            )))
        }
    };
    let vocab = features::Vocabulary::new()?;
    let v = voxelize::voxelize(&recipe, geom, seed, &vocab)?;
    let view = recipe.view;
    let intr = Intrinsics::from_fov_x(WIDTH, HEIGHT, view.fov_x.to_radians());
    let look = |name: String, azimuth: f32, elevation: f32, radius: f32| {
        let (a, e) = (azimuth.to_radians(), elevation.to_radians());
        let eye = view.center + radius * Vec3::new(e.cos() * a.sin(), e.sin(), e.cos() * a.cos());
        CameraFrame {
            name,
            camera: Camera::look_at(intr, eye, view.center, Vec3::Y),
        }
    };
    let mut cameras = CameraSet::orbit(
        intr,
        view.center,
        view.radius,
        ORBIT_ELEVATION_DEG.to_radians(),
        ORBIT_FRAMES,
    );
    for (i, f) in cameras.frames.iter_mut().enumerate() {
        f.name = format!("./frame_{i:03}");
    }
    // Held out: between orbit azimuths, above and below its elevation, in
    // the front half where the wall does not hide the scene.
    let eval_cameras = CameraSet {
        frames: (0..EVAL_FRAMES)
            .map(|i| {
                let az = -97.5 + 30.0 * i as f32;
                let (el, r) = if i % 2 == 0 { (12.0, 1.0) } else { (42.0, 1.08) };
                look(format!("./eval_{i:03}"), az, el, view.radius * r)
            })
            .collect(),
    };
    let stroke_camera = look(
        "./stroke".into(),
        view.stroke_azimuth,
        view.stroke_elevation,
        view.radius,
    )
    .camera;
    let mut image = strokes::LabelImage::new(&stroke_camera, &v.field.density, &v.labels);
    let objects = recipe
        .objects
        .iter()
        .enumerate()
        .map(|(i, o)| {
            let label = i as u8 + 1;
            DemoObject {
                name: o.name.to_string(),
                label,
                parts: o.parts.iter().map(|p| p.to_string()).collect(),
                stroke: strokes::stroke(&mut image, label, &o.anchors, STROKE_RADIUS),
            }
        })
        .collect();
    Ok(DemoScene {
        name: name.to_string(),
        field: v.field,
        labels: v.labels,
        cameras,
        eval_cameras,
        stroke_camera,
        objects,
        voxel_parts: v.voxel_parts,
    })
}

/// A camera as one transforms.json-style frame (strokes.json embeds it).
#[derive(Serialize)]
pub struct FrameJson {
    pub file_path: String,
    pub transform_matrix: [[f32; 4]; 4],
    pub fl_x: f32,
    pub fl_y: f32,
    pub cx: f32,
    pub cy: f32,
    pub w: u32,
    pub h: u32,
}

impl FrameJson {
    pub fn new(name: &str, c: &Camera) -> Self {
        let k = c.intrinsics;
        FrameJson {
            file_path: name.to_string(),
            transform_matrix: affine_to_rows(&c.c2w),
            fl_x: k.fx,
            fl_y: k.fy,
            cx: k.cx,
            cy: k.cy,
            w: k.width,
            h: k.height,
        }
    }
}

/// One entry of strokes.json.
#[derive(Serialize)]
pub struct StrokeJson {
    pub object: String,
    pub polarity: &'static str,
    pub radius: u32,
    pub points: Vec<[u32; 2]>,
    pub camera: FrameJson,
}

impl DemoScene {
    pub fn object(&self, name: &str) -> Option<&DemoObject> {
        self.objects.iter().find(|o| o.name == name)
    }
    /// Number of occupied voxels (σ > 0).
    pub fn occupied(&self) -> usize {
        self.field.occupancy.as_ref().map_or(0, |o| o.count())
    }
    /// The object's stroke as pixels of the stroke camera (consecutive
    /// repeats removed).
    pub fn stroke_pixels(&self, object: &DemoObject) -> Vec<[u32; 2]> {
        let mut px: Vec<[u32; 2]> = object
            .stroke
            .iter()
            .filter_map(|&p| strokes::pixel_of(&self.stroke_camera, p))
            .collect();
        px.dedup();
        px
    }
    /// The built-in strokes as written to strokes.json (objects whose stroke
    /// is empty at this resolution are left out).
    pub fn strokes_json(&self) -> Vec<StrokeJson> {
        self.objects
            .iter()
            .filter(|o| !o.stroke.is_empty())
            .map(|o| StrokeJson {
                object: o.name.clone(),
                polarity: "positive",
                radius: STROKE_RADIUS,
                points: self.stroke_pixels(o),
                camera: FrameJson::new("./stroke", &self.stroke_camera),
            })
            .collect()
    }
    /// Writes `field.safetensors`, `labels.safetensors`, `transforms.json`
    /// (the orbit), `transforms_eval.json` (held-out views) and
    /// `strokes.json` into `dir`; returns the paths written.
    pub fn write(&self, dir: &Path) -> Result<Vec<PathBuf>> {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let paths: Vec<PathBuf> = [
            "field.safetensors",
            "labels.safetensors",
            "transforms.json",
            "transforms_eval.json",
            "strokes.json",
        ]
        .iter()
        .map(|f| dir.join(f))
        .collect();
        self.field.save(&paths[0])?;
        self.labels.save(&paths[1])?;
        self.cameras.save(&paths[2])?;
        self.eval_cameras.save(&paths[3])?;
        let json = serde_json::to_string_pretty(&self.strokes_json()).map_err(|e| Error::invalid(e.to_string()))?;
        write_atomic(&paths[4], json.as_bytes())?;
        Ok(paths)
    }
}
