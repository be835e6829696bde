//! Camera sets: the frames of a capture or a preview path, read from and
//! written to `transforms.json` (Blender / NeRF-synthetic / nerfstudio form).

use super::{Camera, Intrinsics};
use crate::error::{write_atomic, Error, Result};
use glam::{Affine3A, Mat4, Vec3};
use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Clone, Debug, PartialEq)]
pub struct CameraFrame {
    /// `file_path` as written in the JSON (e.g. `./train/r_0`); output images
    /// are named after its base name.
    pub name: String,
    pub camera: Camera,
}

impl CameraFrame {
    /// Base name of `file_path` without extension (`./train/r_0.png` → `r_0`).
    pub fn base_name(&self) -> String {
        let p = Path::new(&self.name);
        p.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| self.name.clone())
    }
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct CameraSet {
    pub frames: Vec<CameraFrame>,
}

/// The JSON we write: nerfstudio-style shared intrinsics plus Blender's
/// `camera_angle_x`, so that both kinds of readers accept it.
#[derive(Serialize, Deserialize)]
struct JsonOut {
    camera_angle_x: f32,
    fl_x: f32,
    fl_y: f32,
    cx: f32,
    cy: f32,
    w: u32,
    h: u32,
    frames: Vec<JsonFrameOut>,
}

#[derive(Serialize, Deserialize)]
struct JsonFrameOut {
    file_path: String,
    transform_matrix: [[f32; 4]; 4],
    #[serde(skip_serializing_if = "Option::is_none")]
    fl_x: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    fl_y: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    cx: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    cy: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    w: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    h: Option<u32>,
}

/// Rows of a 4×4 matrix (JSON `transform_matrix` is row-major).
pub fn affine_to_rows(a: &Affine3A) -> [[f32; 4]; 4] {
    let m = Mat4::from(*a).transpose();
    [
        m.x_axis.to_array(),
        m.y_axis.to_array(),
        m.z_axis.to_array(),
        m.w_axis.to_array(),
    ]
}

impl CameraSet {
    /// Orbit of `n` cameras around `center` at `radius`, `elevation` radians
    /// above the horizontal plane (+y up), all looking at the centre.
    pub fn orbit(intrinsics: Intrinsics, center: Vec3, radius: f32, elevation: f32, n: usize) -> Self {
        let frames = (0..n)
            .map(|i| {
                let a = std::f32::consts::TAU * i as f32 / n as f32;
                let eye =
                    center + radius * Vec3::new(elevation.cos() * a.sin(), elevation.sin(), elevation.cos() * a.cos());
                CameraFrame {
                    name: format!("./orbit/frame_{i:03}"),
                    camera: Camera::look_at(intrinsics, eye, center, Vec3::Y),
                }
            })
            .collect();
        CameraSet { frames }
    }
    /// Writes `transforms.json` atomically. Intrinsics of the first frame are
    /// shared; frames whose intrinsics differ carry their own.
    pub fn save(&self, path: &Path) -> Result<()> {
        let first = self
            .frames
            .first()
            .ok_or_else(|| Error::invalid("cannot save an empty camera set"))?;
        let k0 = first.camera.intrinsics;
        let frames = self
            .frames
            .iter()
            .map(|f| {
                let k = f.camera.intrinsics;
                let own = k != k0;
                JsonFrameOut {
                    file_path: f.name.clone(),
                    transform_matrix: affine_to_rows(&f.camera.c2w),
                    fl_x: own.then_some(k.fx),
                    fl_y: own.then_some(k.fy),
                    cx: own.then_some(k.cx),
                    cy: own.then_some(k.cy),
                    w: own.then_some(k.width),
                    h: own.then_some(k.height),
                }
            })
            .collect();
        let out = JsonOut {
            camera_angle_x: 2.0 * (0.5 * k0.width as f32 / k0.fx).atan(),
            fl_x: k0.fx,
            fl_y: k0.fy,
            cx: k0.cx,
            cy: k0.cy,
            w: k0.width,
            h: k0.height,
            frames,
        };
        let text = serde_json::to_string_pretty(&out).map_err(|e| Error::invalid(e.to_string()))?;
        write_atomic(path, text.as_bytes())
    }
}
