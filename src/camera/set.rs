//! Camera sets: the frames of a capture or a preview path, read from and
//! written to `transforms.json` (Blender / NeRF-synthetic / nerfstudio form).
//!
//! Reading ([`CameraSet::load`]) accepts both forms, in the OpenGL camera
//! convention they share:
//! - Blender / NeRF-synthetic: `camera_angle_x` (and optionally
//!   `camera_angle_y`), frames with `file_path` (often without extension) and
//!   `transform_matrix`. The image size comes from `w`/`h` when present, else
//!   from the header of the frame's image (the path as is, then with `.png`
//!   appended, relative to the JSON's folder).
//! - nerfstudio: `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` at the top level or per
//!   frame (per frame wins). Distortion parameters (`k1`, `k2`, `p1`, `p2`,
//!   `camera_model`, …) are ignored: cameras are ideal pinholes, so images
//!   should be undistorted first.
//!
//! An optional top-level `"ndc": {"near", "focal", "width", "height"}` key
//! marks a forward-facing scene whose rays live in NDC space (see
//! [`super::Ndc`]); [`CameraSet::save`] writes it and `load` reads it back.

use super::{Camera, Intrinsics, Ndc};
use crate::error::{write_atomic, Error, Result};
use glam::{Affine3A, Mat3, Vec3};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

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
    #[serde(skip_serializing_if = "Option::is_none")]
    ndc: Option<Ndc>,
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
/// Where the cameras of the capture a field file was trained on may be:
/// `isrf train`'s `<stem>.cameras.json` beside it, else a `transforms.json`
/// in its folder (in that order).
pub fn capture_camera_files(field: &Path) -> Vec<std::path::PathBuf> {
    let name = field
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let stem = name.strip_suffix(".safetensors").unwrap_or(&name);
    let mut out = vec![field.with_file_name(format!("{stem}.cameras.json"))];
    out.extend(field.parent().map(|d| d.join("transforms.json")));
    out
}

/// The first readable camera set of [`capture_camera_files`].
pub fn capture_cameras(field: &Path) -> Option<CameraSet> {
    capture_camera_files(field)
        .into_iter()
        .filter(|t| t.exists())
        .find_map(|t| CameraSet::load(&t).ok())
}

pub use crate::util::affine_to_rows;

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
        let ndc = first.camera.ndc;
        if let Some(i) = self.frames.iter().position(|f| f.camera.ndc != ndc) {
            return Err(Error::invalid(format!(
                "cannot save camera set: frame {i} has NDC {:?} but frame 0 has {ndc:?} (one NDC space per set)",
                self.frames[i].camera.ndc
            )));
        }
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
            ndc,
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

/// The JSON we read: every field optional so that both forms parse and a
/// missing one gets a precise message instead of serde's.
#[derive(Deserialize)]
struct JsonIn {
    camera_angle_x: Option<f64>,
    camera_angle_y: Option<f64>,
    #[serde(flatten)]
    k: JsonIntrinsics,
    ndc: Option<Ndc>,
    frames: Option<Vec<JsonFrameIn>>,
}

#[derive(Deserialize, Default, Clone, Copy)]
struct JsonIntrinsics {
    fl_x: Option<f64>,
    fl_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    w: Option<f64>,
    h: Option<f64>,
}

#[derive(Deserialize)]
struct JsonFrameIn {
    file_path: Option<String>,
    transform_matrix: Option<Vec<Vec<f64>>>,
    #[serde(flatten)]
    k: JsonIntrinsics,
}

/// Largest image side accepted from a JSON file (guards against absurd sizes).
const MAX_SIDE: f64 = crate::limits::MAX_IMAGE_SIDE as f64;
/// Tolerance on |RᵀR − I| and on the bottom row for a pose to count as rigid.
pub(crate) const RIGID_TOL: f32 = 2e-3;

impl CameraSet {
    pub fn len(&self) -> usize {
        self.frames.len()
    }
    /// The cameras' shared up direction ([`super::up_of`]).
    pub fn up(&self) -> Option<glam::Vec3> {
        let cameras: Vec<_> = self.frames.iter().map(|f| f.camera).collect();
        super::up_of(&cameras)
    }
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }
    /// The frames at `indices`, in that order; an out-of-range index is an error.
    pub fn subset(&self, indices: &[usize]) -> Result<CameraSet> {
        let frames = indices
            .iter()
            .map(|&i| {
                self.frames.get(i).cloned().ok_or_else(|| {
                    Error::invalid(format!("frame index {i} out of range (set has {})", self.frames.len()))
                })
            })
            .collect::<Result<_>>()?;
        Ok(CameraSet { frames })
    }
    /// The same cameras at 1/`factor` resolution.
    pub fn downscaled(&self, factor: u32) -> CameraSet {
        let frames = self
            .frames
            .iter()
            .map(|f| CameraFrame {
                name: f.name.clone(),
                camera: f.camera.downscaled(factor),
            })
            .collect();
        CameraSet { frames }
    }
    /// Reads a `transforms*.json` (a folder means its `transforms.json`).
    /// See the module docs for the accepted forms.
    pub fn load(path: &Path) -> Result<CameraSet> {
        Self::load_inner(path, None)
    }
    /// Like [`CameraSet::load`], with `size` (width, height) used for frames
    /// whose JSON has no `w`/`h` and whose image file is absent (e.g. the
    /// NeRF-synthetic test split shipped without its images).
    pub fn load_with_size(path: &Path, size: (u32, u32)) -> Result<CameraSet> {
        Self::load_inner(path, Some(size))
    }

    fn load_inner(path: &Path, fallback_size: Option<(u32, u32)>) -> Result<CameraSet> {
        let path = if path.is_dir() {
            path.join("transforms.json")
        } else {
            path.to_path_buf()
        };
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let json: JsonIn =
            serde_json::from_str(&text).map_err(|e| Error::bad_file(&path, format!("malformed JSON: {e}")))?;
        let raw_frames = json.frames.as_deref().unwrap_or(&[]);
        if raw_frames.is_empty() {
            return Err(Error::bad_file(&path, "no frames (missing or empty `frames` list)"));
        }
        if let Some(ndc) = &json.ndc {
            ndc.validate().map_err(|e| Error::bad_file(&path, e.to_string()))?;
        }
        let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        let frames = raw_frames
            .iter()
            .enumerate()
            .map(|(i, f)| {
                let name = f
                    .file_path
                    .clone()
                    .ok_or_else(|| Error::bad_file(&path, format!("frame {i}: missing `file_path`")))?;
                let fail = |why: String| Error::bad_file(&path, format!("frame {i} ({name}): {why}"));
                let rows = f
                    .transform_matrix
                    .as_ref()
                    .ok_or_else(|| fail("missing `transform_matrix`".into()))?;
                let c2w = rigid_from_rows(rows).map_err(fail)?;
                let k = frame_intrinsics(&json, &f.k, &dir, &name, fallback_size).map_err(fail)?;
                Ok(CameraFrame {
                    camera: Camera::new(k, c2w).with_ndc(json.ndc),
                    name,
                })
            })
            .collect::<Result<_>>()?;
        Ok(CameraSet { frames })
    }
}

/// A pose from the rows of a 3×4 or 4×4 matrix; rejects non-finite numbers,
/// a bottom row other than [0 0 0 1], scale, shear and reflections.
pub(crate) fn rigid_from_rows(rows: &[Vec<f64>]) -> std::result::Result<Affine3A, String> {
    if !(rows.len() == 3 || rows.len() == 4) || rows.iter().any(|r| r.len() != 4) {
        let shape: Vec<usize> = rows.iter().map(Vec::len).collect();
        return Err(format!(
            "transform_matrix must be 4×4 (or 3×4), got {} rows of lengths {shape:?}",
            rows.len()
        ));
    }
    let m: Vec<f32> = rows.iter().flatten().map(|&x| x as f32).collect();
    if m.iter().any(|x| !x.is_finite()) {
        return Err("transform_matrix has a non-finite entry".into());
    }
    if rows.len() == 4 {
        let bottom = &m[12..16];
        let off = bottom
            .iter()
            .zip([0.0, 0.0, 0.0, 1.0])
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        if off > RIGID_TOL {
            return Err(format!(
                "transform_matrix bottom row is {bottom:?}, expected [0, 0, 0, 1]"
            ));
        }
    }
    let col = |j: usize| Vec3::new(m[j], m[4 + j], m[8 + j]);
    let r = Mat3::from_cols(col(0), col(1), col(2));
    let err = (r.transpose() * r - Mat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0.0f32, |a, x| a.max(x.abs()));
    if err > RIGID_TOL {
        return Err(format!(
            "transform_matrix is not a rigid transform: rotation part not orthonormal (max |RᵀR − I| = {err:.3})"
        ));
    }
    if r.determinant() < 0.0 {
        return Err("transform_matrix is a reflection (rotation determinant < 0)".into());
    }
    Ok(Affine3A::from_mat3_translation(r, col(3)))
}

/// Intrinsics of one frame: per-frame keys, then top-level keys, then
/// Blender's field of view and the image file's size.
fn frame_intrinsics(
    json: &JsonIn,
    own: &JsonIntrinsics,
    dir: &Path,
    name: &str,
    fallback_size: Option<(u32, u32)>,
) -> std::result::Result<Intrinsics, String> {
    let top = &json.k;
    let (width, height) = match (own.w.or(top.w), own.h.or(top.h)) {
        (Some(w), Some(h)) => (side(w, "w")?, side(h, "h")?),
        _ => image_size(dir, name).or_else(|e| fallback_size.ok_or(e))?,
    };
    let keys = IntrinsicKeys {
        fl_x: own.fl_x.or(top.fl_x),
        fl_y: own.fl_y.or(top.fl_y),
        cx: own.cx.or(top.cx),
        cy: own.cy.or(top.cy),
        camera_angle_x: json.camera_angle_x,
        camera_angle_y: json.camera_angle_y,
    };
    keys.intrinsics(width, height)
}

/// The intrinsics keys of a transforms.json camera (top level, frame or a
/// stroke document's camera), resolved in one place.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct IntrinsicKeys {
    pub fl_x: Option<f64>,
    pub fl_y: Option<f64>,
    pub cx: Option<f64>,
    pub cy: Option<f64>,
    pub camera_angle_x: Option<f64>,
    pub camera_angle_y: Option<f64>,
}

impl IntrinsicKeys {
    /// Intrinsics for a `width`×`height` image: focal lengths from `fl_x` /
    /// `fl_y` or Blender's field of view (`fl_y` defaults to `fl_x`), the
    /// principal point at the centre unless given; all checked finite and
    /// focal lengths positive.
    pub(crate) fn intrinsics(&self, width: u32, height: u32) -> std::result::Result<Intrinsics, String> {
        let from_angle = |angle: Option<f64>, side: u32| angle.map(|a| 0.5 * side as f64 / (0.5 * a).tan());
        let fx = self
            .fl_x
            .or_else(|| from_angle(self.camera_angle_x, width))
            .ok_or("missing intrinsics: no `fl_x` and no `camera_angle_x`")?;
        let fy = self
            .fl_y
            .or_else(|| from_angle(self.camera_angle_y, height))
            .unwrap_or(fx);
        let k = Intrinsics {
            width,
            height,
            fx: fx as f32,
            fy: fy as f32,
            cx: self.cx.unwrap_or(0.5 * width as f64) as f32,
            cy: self.cy.unwrap_or(0.5 * height as f64) as f32,
        };
        check_intrinsics(&k)?;
        Ok(k)
    }
}

/// Finite intrinsics with positive focal lengths and an image size within
/// [`crate::limits::image_size_ok`].
pub(crate) fn check_intrinsics(k: &Intrinsics) -> std::result::Result<(), String> {
    if !crate::limits::image_size_ok(k.width, k.height) {
        return Err(format!("bad image size {}x{}", k.width, k.height));
    }
    for (v, what) in [(k.fx, "focal length x"), (k.fy, "focal length y")] {
        if !(v.is_finite() && v > 0.0) {
            return Err(format!("bad intrinsics: {what} = {v}"));
        }
    }
    for (v, what) in [(k.cx, "cx"), (k.cy, "cy")] {
        if !v.is_finite() {
            return Err(format!("bad intrinsics: {what} = {v}"));
        }
    }
    Ok(())
}

fn side(v: f64, key: &str) -> std::result::Result<u32, String> {
    if v.fract() == 0.0 && (1.0..=MAX_SIDE).contains(&v) {
        Ok(v as u32)
    } else {
        Err(format!("bad image size: `{key}` = {v}"))
    }
}

/// Candidate files for a frame's image: the path as written, then with `.png`.
pub(crate) fn image_candidates(dir: &Path, name: &str) -> [PathBuf; 2] {
    let p = dir.join(name);
    let mut png = p.clone().into_os_string();
    png.push(".png");
    [p, PathBuf::from(png)]
}

fn image_size(dir: &Path, name: &str) -> std::result::Result<(u32, u32), String> {
    let candidates = image_candidates(dir, name);
    let Some(found) = candidates.iter().find(|p| p.is_file()) else {
        return Err(format!(
            "missing intrinsics: no `w`/`h` in the JSON and no image at {} or {} to read the size from",
            candidates[0].display(),
            candidates[1].display()
        ));
    };
    image::image_dimensions(found).map_err(|e| format!("cannot read image size from {}: {e}", found.display()))
}
