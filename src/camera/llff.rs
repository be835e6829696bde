//! LLFF captures: `poses_bounds.npy` plus `images_N` folders.
//!
//! `poses_bounds.npy` is an N×17 float array: per image a row-major 3×5
//! matrix `[R | t | hwf]` (camera-to-world with camera axes [down, right,
//! back], then image height, width and focal length at full resolution),
//! followed by the near and far scene depth bounds.
//!
//! [`load_scene`] does what the standard NeRF `load_llff_data` does: axes to
//! OpenGL [right, up, back], scale the world so that the nearest bound becomes
//! 1/`bd_factor` (≈ 1.33 for 0.75), then recentre so that the average pose is
//! the identity. The resulting world→normalised transform is kept in
//! [`LlffScene::transform`]. By default cameras carry NeRF's NDC space (near
//! plane 1.0), which suits forward-facing scenes.

use super::{Camera, CameraFrame, CameraSet, Intrinsics, Ndc};
use crate::error::{Error, Result};
use glam::{Affine3A, DAffine3, DMat3, DVec3};
use std::path::{Path, PathBuf};

/// Options of [`load_scene`]; the defaults are NeRF's for LLFF scenes.
#[derive(Clone, Debug, PartialEq)]
pub struct LlffOptions {
    /// Downscale factor N: images in `images_N` (1 means `images`).
    pub factor: u32,
    /// Scale so that the smallest near bound becomes 1/bd_factor; `None`
    /// keeps the capture's scale.
    pub bd_factor: Option<f64>,
    /// Move and rotate the world so that the average pose is the identity.
    pub recenter: bool,
    /// Give cameras NeRF's NDC space (near plane 1.0).
    pub ndc: bool,
}

impl Default for LlffOptions {
    fn default() -> Self {
        LlffOptions {
            factor: 8,
            bd_factor: Some(0.75),
            recenter: true,
            ndc: true,
        }
    }
}

/// One row of `poses_bounds.npy`, as stored.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LlffPose {
    /// Rows of the 3×5 matrix `[R | t | hwf]`, camera axes [down, right, back].
    pub matrix: [[f64; 5]; 3],
    /// Near and far depth bounds.
    pub bounds: [f64; 2],
}

impl LlffPose {
    /// Full-resolution (height, width, focal).
    pub fn hwf(&self) -> [f64; 3] {
        [self.matrix[0][4], self.matrix[1][4], self.matrix[2][4]]
    }
    /// Camera-to-world in the OpenGL convention [right, up, back] (world
    /// axes unchanged): columns (right, up, back) = (c1, −c0, c2).
    pub fn c2w_opengl(&self) -> DAffine3 {
        let c = |j: usize| DVec3::new(self.matrix[0][j], self.matrix[1][j], self.matrix[2][j]);
        DAffine3::from_mat3_translation(DMat3::from_cols(c(1), -c(0), c(2)), c(3))
    }
}

/// A loaded LLFF scene.
#[derive(Clone, Debug, PartialEq)]
pub struct LlffScene {
    /// One camera per pose, named after its image (`images_8/image000.png`)
    /// when the image folder matches the poses, else `image000`.
    pub cameras: CameraSet,
    /// Near/far bounds per camera in the normalised world.
    pub bounds: Vec<[f32; 2]>,
    /// Capture world → normalised world: scale by `scale`, then the inverse
    /// of the average pose.
    pub transform: Affine3A,
    pub scale: f32,
    /// Full-resolution (height, width, focal) from the first pose.
    pub hwf: [f32; 3],
    /// The image folder for the chosen factor, if it exists.
    pub image_dir: Option<PathBuf>,
}

/// Reads and checks `poses_bounds.npy` (N×17, float64 or float32, C order).
pub fn read_poses_bounds(path: &Path) -> Result<Vec<LlffPose>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let bad = |why: String| Error::bad_file(path, why);
    let npy = crate::npy::parse(&bytes).map_err(bad)?;
    if npy.shape.len() != 2 || npy.shape[1] != 17 || npy.shape[0] == 0 {
        return Err(bad(format!(
            "expected an N×17 array (N ≥ 1), got shape {:?}",
            npy.shape
        )));
    }
    // The parser checked the shape against the bytes present: 17·N values.
    let values = npy.to_f64();
    values
        .chunks_exact(17)
        .enumerate()
        .map(|(i, r)| {
            if r.iter().any(|x| !x.is_finite()) {
                return Err(bad(format!("pose {i} has a non-finite value")));
            }
            let mut matrix = [[0.0; 5]; 3];
            for (row, m) in matrix.iter_mut().enumerate() {
                m.copy_from_slice(&r[row * 5..row * 5 + 5]);
            }
            let pose = LlffPose {
                matrix,
                bounds: [r[15], r[16]],
            };
            check_pose(&pose).map_err(|why| bad(format!("pose {i}: {why}")))?;
            Ok(pose)
        })
        .collect()
}

fn check_pose(p: &LlffPose) -> std::result::Result<(), String> {
    let r = p.c2w_opengl().matrix3;
    let err = (r.transpose() * r - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0.0f64, |a, x| a.max(x.abs()));
    if err > f64::from(super::set::RIGID_TOL) || r.determinant() <= 0.0 {
        return Err(format!("rotation is not a proper rotation (max |RᵀR − I| = {err:.3})"));
    }
    let [h, w, f] = p.hwf();
    let side = f64::from(crate::limits::MAX_IMAGE_SIDE);
    if !(h >= 1.0 && w >= 1.0 && f > 0.0 && h <= side && w <= side) {
        return Err(format!("bad height/width/focal {:?}", p.hwf()));
    }
    let [near, far] = p.bounds;
    if !(near > 0.0 && far >= near) {
        return Err(format!("bad depth bounds [{near}, {far}] (need 0 < near ≤ far)"));
    }
    Ok(())
}

/// The image folder for a factor: `images` for 1, `images_N` otherwise.
pub fn image_dir(dir: &Path, factor: u32) -> PathBuf {
    if factor <= 1 {
        dir.join("images")
    } else {
        dir.join(format!("images_{factor}"))
    }
}

/// Image files of a folder (png/jpg/jpeg, any case), sorted by name as the
/// LLFF and NeRF loaders do.
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut files = Vec::new();
    for entry in entries {
        let path = entry.map_err(|e| Error::io(dir, e))?.path();
        if matches!(crate::util::extension(&path).as_str(), "png" | "jpg" | "jpeg") && path.is_file() {
            files.push(path);
        }
    }
    files.sort();
    Ok(files)
}

/// Cameras of an LLFF scene with the default options (NeRF's scaling,
/// recentring and NDC) at downscale `factor`.
pub fn load(dir: &Path, factor: u32) -> Result<CameraSet> {
    Ok(load_scene(
        dir,
        &LlffOptions {
            factor,
            ..Default::default()
        },
    )?
    .cameras)
}

/// Loads `dir/poses_bounds.npy` into cameras for the `images_N` resolution.
/// The image size is hwf / N, or the actual size of the first image in
/// `images_N` when that folder exists (it must agree within a pixel).
pub fn load_scene(dir: &Path, opts: &LlffOptions) -> Result<LlffScene> {
    crate::ensure!(opts.factor >= 1, "LLFF downscale factor must be ≥ 1");
    let poses_path = dir.join("poses_bounds.npy");
    let poses = read_poses_bounds(&poses_path)?;
    let factor = opts.factor as f64;
    let [h_full, w_full, f_full] = poses
        .first()
        .ok_or_else(|| Error::bad_file(&poses_path, "holds no poses"))?
        .hwf();
    let folder = image_dir(dir, opts.factor);
    let images = if folder.is_dir() {
        list_images(&folder)?
    } else {
        Vec::new()
    };
    let (width, height) = match images.first() {
        Some(first) => checked_size(first, w_full / factor, h_full / factor)?,
        None => ((w_full / factor).round() as u32, (h_full / factor).round() as u32),
    };
    if width < 1 || height < 1 {
        return Err(Error::bad_file(
            &poses_path,
            format!(
                "downscale factor {} leaves no pixels of the {w_full}×{h_full} images",
                opts.factor
            ),
        ));
    }
    let focal = (f_full / factor) as f32;
    let intrinsics = Intrinsics {
        width,
        height,
        fx: focal,
        fy: focal,
        cx: 0.5 * width as f32,
        cy: 0.5 * height as f32,
    };

    let min_near = poses.iter().map(|p| p.bounds[0]).fold(f64::INFINITY, f64::min);
    let scale = opts.bd_factor.map_or(1.0, |bd| 1.0 / (min_near * bd));
    let scaled: Vec<DAffine3> = poses
        .iter()
        .map(|p| {
            let c = p.c2w_opengl();
            DAffine3::from_mat3_translation(c.matrix3, c.translation * scale)
        })
        .collect();
    let recenter = if opts.recenter {
        average_pose(&scaled).inverse()
    } else {
        DAffine3::IDENTITY
    };
    let ndc = opts.ndc.then(|| Ndc::new(focal, width, height));
    let names_match = images.len() == poses.len();
    let frames = scaled
        .iter()
        .enumerate()
        .map(|(i, c2w)| CameraFrame {
            name: match names_match {
                true => relative_name(dir, &images[i]),
                false => format!("image{i:03}"),
            },
            camera: Camera::new(intrinsics, to_f32(&(recenter * *c2w))).with_ndc(ndc),
        })
        .collect();
    Ok(LlffScene {
        cameras: CameraSet { frames },
        bounds: poses
            .iter()
            .map(|p| [(p.bounds[0] * scale) as f32, (p.bounds[1] * scale) as f32])
            .collect(),
        transform: to_f32(&(recenter * DAffine3::from_scale(DVec3::splat(scale)))),
        scale: scale as f32,
        hwf: [h_full as f32, w_full as f32, f_full as f32],
        image_dir: folder.is_dir().then_some(folder),
    })
}

/// Size of `image`, which must match the expected size within a pixel
/// (downscaled folders round differently).
fn checked_size(image: &Path, w: f64, h: f64) -> Result<(u32, u32)> {
    let (iw, ih) =
        image::image_dimensions(image).map_err(|e| Error::bad_file(image, format!("cannot read image size: {e}")))?;
    if (iw as f64 - w).abs() > 1.0 || (ih as f64 - h).abs() > 1.0 {
        return Err(Error::bad_file(
            image,
            format!("image is {iw}×{ih} but poses_bounds.npy implies {w:.1}×{h:.1} at this factor"),
        ));
    }
    Ok((iw, ih))
}

fn relative_name(dir: &Path, file: &Path) -> String {
    file.strip_prefix(dir).unwrap_or(file).to_string_lossy().into_owned()
}

/// NeRF's `poses_avg`: mean centre, summed viewing axis, summed up vector,
/// orthonormalised.
fn average_pose(poses: &[DAffine3]) -> DAffine3 {
    let n = poses.len() as f64;
    let center = poses.iter().map(|p| p.translation).sum::<DVec3>() / n;
    let back = poses.iter().map(|p| p.matrix3.z_axis).sum::<DVec3>().normalize();
    let up = poses.iter().map(|p| p.matrix3.y_axis).sum::<DVec3>();
    let right = up.cross(back).normalize();
    let up = back.cross(right).normalize();
    DAffine3::from_mat3_translation(DMat3::from_cols(right, up, back), center)
}

fn to_f32(a: &DAffine3) -> Affine3A {
    Affine3A::from_mat3_translation(a.matrix3.as_mat3(), a.translation.as_vec3())
}

/// NeRF's LLFF hold-out: views with `i % every == 0` are test views, the
/// rest train. Returns (train, test); `every` = 0 means no test views.
pub fn holdout(n: usize, every: usize) -> (Vec<usize>, Vec<usize>) {
    (0..n).partition(|&i| every == 0 || i % every != 0)
}
