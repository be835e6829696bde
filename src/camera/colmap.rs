//! COLMAP sparse models: `cameras.{bin,txt}` and `images.{bin,txt}`.
//!
//! COLMAP stores world-to-camera poses (quaternion `qvec` = w, x, y, z and
//! translation `tvec`) in the OpenCV camera convention; we invert them and
//! convert with [`Camera::from_opencv`]. Pixel centres are at +0.5 in COLMAP
//! too. Lens distortion parameters are read but ignored (cameras are ideal
//! pinholes: undistort images with `colmap image_undistorter` for accuracy);
//! fisheye models are rejected because a pinhole is no approximation of them.

use super::{Camera, CameraFrame, CameraSet, Intrinsics};
use crate::error::{Error, Result};
use glam::{DAffine3, DMat3, DQuat, DVec3};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// COLMAP camera models, with their ids in the binary format.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraModel {
    SimplePinhole,
    Pinhole,
    SimpleRadial,
    Radial,
    OpenCv,
    OpenCvFisheye,
    FullOpenCv,
    Fov,
    SimpleRadialFisheye,
    RadialFisheye,
    ThinPrismFisheye,
}

const MODELS: [(CameraModel, &str, usize); 11] = [
    (CameraModel::SimplePinhole, "SIMPLE_PINHOLE", 3),
    (CameraModel::Pinhole, "PINHOLE", 4),
    (CameraModel::SimpleRadial, "SIMPLE_RADIAL", 4),
    (CameraModel::Radial, "RADIAL", 5),
    (CameraModel::OpenCv, "OPENCV", 8),
    (CameraModel::OpenCvFisheye, "OPENCV_FISHEYE", 8),
    (CameraModel::FullOpenCv, "FULL_OPENCV", 12),
    (CameraModel::Fov, "FOV", 5),
    (CameraModel::SimpleRadialFisheye, "SIMPLE_RADIAL_FISHEYE", 4),
    (CameraModel::RadialFisheye, "RADIAL_FISHEYE", 5),
    (CameraModel::ThinPrismFisheye, "THIN_PRISM_FISHEYE", 12),
];

impl CameraModel {
    pub fn from_id(id: i32) -> Option<Self> {
        usize::try_from(id).ok().and_then(|i| MODELS.get(i)).map(|m| m.0)
    }
    pub fn from_name(name: &str) -> Option<Self> {
        MODELS.iter().find(|m| m.1 == name).map(|m| m.0)
    }
    pub fn name(self) -> &'static str {
        MODELS[self as usize].1
    }
    pub fn num_params(self) -> usize {
        MODELS[self as usize].2
    }
    /// Models whose parameters start with one focal length (f, cx, cy, …);
    /// the others start with fx, fy, cx, cy.
    fn single_focal(self) -> bool {
        use CameraModel::*;
        matches!(
            self,
            SimplePinhole | SimpleRadial | Radial | SimpleRadialFisheye | RadialFisheye
        )
    }
    fn pinhole_like(self) -> bool {
        use CameraModel::*;
        matches!(
            self,
            SimplePinhole | Pinhole | SimpleRadial | Radial | OpenCv | FullOpenCv
        )
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    pub id: u32,
    pub model: CameraModel,
    pub width: u32,
    pub height: u32,
    pub params: Vec<f64>,
}

impl ColmapCamera {
    /// Pinhole intrinsics (distortion ignored); fisheye and FOV models are an
    /// error.
    pub fn intrinsics(&self) -> Result<Intrinsics> {
        if !self.model.pinhole_like() {
            return Err(Error::invalid(format!(
                "COLMAP camera {} uses the {} model, which a pinhole cannot represent; undistort the images first",
                self.id,
                self.model.name()
            )));
        }
        let p = &self.params;
        let (fx, fy, cx, cy) = match self.model.single_focal() {
            true => (p[0], p[0], p[1], p[2]),
            false => (p[0], p[1], p[2], p[3]),
        };
        Ok(Intrinsics {
            width: self.width,
            height: self.height,
            fx: fx as f32,
            fy: fy as f32,
            cx: cx as f32,
            cy: cy as f32,
        })
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    pub id: u32,
    /// World-to-camera rotation quaternion (w, x, y, z).
    pub qvec: [f64; 4],
    /// World-to-camera translation.
    pub tvec: [f64; 3],
    pub camera_id: u32,
    pub name: String,
}

impl ColmapImage {
    /// Camera-to-world pose in the OpenCV convention.
    pub fn c2w_opencv(&self) -> DAffine3 {
        let [w, x, y, z] = self.qvec;
        let r = DMat3::from_quat(DQuat::from_xyzw(x, y, z, w).normalize());
        let w2c = DAffine3::from_mat3_translation(r, DVec3::from_array(self.tvec));
        w2c.inverse()
    }
}

/// Largest image side and parameter/record counts we accept before allocating.
const MAX_SIDE: u64 = crate::limits::MAX_IMAGE_SIDE as u64;

/// Reads `cameras.bin` or `cameras.txt` (by extension), keyed by camera id.
pub fn read_cameras(path: &Path) -> Result<BTreeMap<u32, ColmapCamera>> {
    let bad = |why: String| Error::bad_file(path, why);
    let cams = if is_text(path) {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        parse_cameras_txt(&text).map_err(bad)?
    } else {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        parse_cameras_bin(&bytes).map_err(bad)?
    };
    let mut map = BTreeMap::new();
    for cam in cams {
        let id = cam.id;
        if !crate::limits::image_size_ok(cam.width, cam.height) {
            return Err(bad(format!("camera {id}: bad size {}×{}", cam.width, cam.height)));
        }
        if cam.params.iter().any(|p| !p.is_finite()) {
            return Err(bad(format!("camera {id}: non-finite parameter")));
        }
        if map.insert(id, cam).is_some() {
            return Err(bad(format!("camera id {id} appears twice")));
        }
    }
    Ok(map)
}

/// Reads `images.bin` or `images.txt` (by extension), in file order.
pub fn read_images(path: &Path) -> Result<Vec<ColmapImage>> {
    let images = if is_text(path) {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        parse_images_txt(&text)
    } else {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        parse_images_bin(&bytes)
    }
    .map_err(|why| Error::bad_file(path, why))?;
    for im in &images {
        if im.qvec.iter().chain(&im.tvec).any(|x| !x.is_finite()) || im.qvec.iter().all(|&q| q == 0.0) {
            return Err(Error::bad_file(
                path,
                format!("image {} ({}): bad pose", im.id, im.name),
            ));
        }
    }
    Ok(images)
}

fn is_text(path: &Path) -> bool {
    crate::util::extension(path) == "txt"
}

/// `cameras` and `images` files of the model in `dir`: `dir` itself, or
/// `dir/sparse/0`, or `dir/sparse`; binary preferred over text.
pub fn find_model(dir: &Path) -> Result<(PathBuf, PathBuf)> {
    let model_dir = [dir.to_path_buf(), dir.join("sparse/0"), dir.join("sparse")]
        .into_iter()
        .find(|d| find_file(d, "cameras").is_some() || find_file(d, "images").is_some())
        .ok_or_else(|| {
            Error::bad_file(
                dir,
                "no COLMAP model: cameras.bin/cameras.txt not found here, in sparse/0 or in sparse",
            )
        })?;
    let missing = |stem: &str| {
        Error::bad_file(
            model_dir.join(format!("{stem}.bin")),
            format!("missing (neither {stem}.bin nor {stem}.txt exists); a COLMAP model needs cameras and images"),
        )
    };
    let cameras = find_file(&model_dir, "cameras").ok_or_else(|| missing("cameras"))?;
    let images = find_file(&model_dir, "images").ok_or_else(|| missing("images"))?;
    Ok((cameras, images))
}

fn find_file(dir: &Path, stem: &str) -> Option<PathBuf> {
    ["bin", "txt"]
        .iter()
        .map(|ext| dir.join(format!("{stem}.{ext}")))
        .find(|p| p.is_file())
}

/// Cameras of a COLMAP model (see [`find_model`] for where it is looked
/// for), sorted by image name; frames are named by the image names.
pub fn load(dir: &Path) -> Result<CameraSet> {
    let (cameras_path, images_path) = find_model(dir)?;
    let cameras = read_cameras(&cameras_path)?;
    let mut images = read_images(&images_path)?;
    if images.is_empty() {
        return Err(Error::bad_file(&images_path, "no registered images"));
    }
    images.sort_by(|a, b| a.name.cmp(&b.name));
    let frames = images
        .iter()
        .map(|im| {
            let cam = cameras.get(&im.camera_id).ok_or_else(|| {
                Error::bad_file(
                    &images_path,
                    format!(
                        "image {} ({}) uses camera {}, absent from {}",
                        im.id,
                        im.name,
                        im.camera_id,
                        cameras_path.display()
                    ),
                )
            })?;
            let k = cam
                .intrinsics()
                .map_err(|e| Error::bad_file(&cameras_path, e.to_string()))?;
            let c2w = im.c2w_opencv();
            let c2w = glam::Affine3A::from_mat3_translation(c2w.matrix3.as_mat3(), c2w.translation.as_vec3());
            Ok(CameraFrame {
                name: im.name.clone(),
                camera: Camera::from_opencv(k, c2w),
            })
        })
        .collect::<Result<_>>()?;
    Ok(CameraSet { frames })
}

/// Little-endian reader over a byte slice that checks every length.
struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> std::result::Result<&'a [u8], String> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len());
        let end = end.ok_or_else(|| format!("truncated at byte {} (needed {n} more bytes)", self.pos))?;
        let s = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn u32(&mut self) -> std::result::Result<u32, String> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap_or_default()))
    }
    fn i32(&mut self) -> std::result::Result<i32, String> {
        Ok(i32::from_le_bytes(self.take(4)?.try_into().unwrap_or_default()))
    }
    fn u64(&mut self) -> std::result::Result<u64, String> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().unwrap_or_default()))
    }
    fn f64(&mut self) -> std::result::Result<f64, String> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().unwrap_or_default()))
    }
    fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }
    /// A record count, checked against the bytes left (each record needs at
    /// least `min_size` bytes) before anything is allocated.
    fn count(&mut self, min_size: usize, what: &str) -> std::result::Result<usize, String> {
        let n = self.u64()?;
        if n > (self.remaining() / min_size) as u64 {
            return Err(format!(
                "truncated or corrupt: {what} count {n} does not fit in the {} bytes left",
                self.remaining()
            ));
        }
        Ok(n as usize)
    }
}

fn parse_cameras_bin(bytes: &[u8]) -> std::result::Result<Vec<ColmapCamera>, String> {
    let mut r = Reader { bytes, pos: 0 };
    let n = r.count(24, "camera")?;
    let mut cams = Vec::with_capacity(n);
    for _ in 0..n {
        let id = r.u32()?;
        let model_id = r.i32()?;
        let model =
            CameraModel::from_id(model_id).ok_or_else(|| format!("camera {id}: unknown model id {model_id}"))?;
        let (width, height) = (r.u64()?, r.u64()?);
        if width > MAX_SIDE || height > MAX_SIDE {
            return Err(format!("camera {id}: absurd size {width}×{height}"));
        }
        let params = (0..model.num_params())
            .map(|_| r.f64())
            .collect::<std::result::Result<_, _>>()?;
        cams.push(ColmapCamera {
            id,
            model,
            width: width as u32,
            height: height as u32,
            params,
        });
    }
    if r.remaining() != 0 {
        return Err(format!("{} unexpected bytes after the last camera", r.remaining()));
    }
    Ok(cams)
}

fn parse_images_bin(bytes: &[u8]) -> std::result::Result<Vec<ColmapImage>, String> {
    let mut r = Reader { bytes, pos: 0 };
    let n = r.count(73, "image")?;
    let mut images = Vec::with_capacity(n);
    for _ in 0..n {
        let id = r.u32()?;
        let mut qvec = [0.0; 4];
        for q in &mut qvec {
            *q = r.f64()?;
        }
        let mut tvec = [0.0; 3];
        for t in &mut tvec {
            *t = r.f64()?;
        }
        let camera_id = r.u32()?;
        let rest = &r.bytes[r.pos..];
        let len = rest
            .iter()
            .position(|&b| b == 0)
            .ok_or_else(|| format!("image {id}: unterminated name"))?;
        let name = String::from_utf8_lossy(r.take(len + 1)?.split_last().map_or(&[][..], |s| s.1)).into_owned();
        // 2D points: x, y (f64) and a point3D id (i64) each; skipped.
        let points = r.count(24, "2D point")?;
        r.take(points * 24)?;
        images.push(ColmapImage {
            id,
            qvec,
            tvec,
            camera_id,
            name,
        });
    }
    Ok(images)
}

/// Lines that carry data: trimmed, neither empty nor comments.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

fn num<T: std::str::FromStr>(s: Option<&str>, line: usize, what: &str) -> std::result::Result<T, String> {
    let s = s.ok_or_else(|| format!("line {line}: missing {what}"))?;
    s.parse().map_err(|_| format!("line {line}: bad {what} {s:?}"))
}

fn parse_cameras_txt(text: &str) -> std::result::Result<Vec<ColmapCamera>, String> {
    data_lines(text)
        .map(|(line, l)| {
            let mut it = l.split_whitespace();
            let id = num(it.next(), line, "camera id")?;
            let model_name = it.next().ok_or_else(|| format!("line {line}: missing model"))?;
            let model = CameraModel::from_name(model_name)
                .ok_or_else(|| format!("line {line}: unknown model {model_name:?}"))?;
            let width: u64 = num(it.next(), line, "width")?;
            let height: u64 = num(it.next(), line, "height")?;
            if width > MAX_SIDE || height > MAX_SIDE {
                return Err(format!("line {line}: absurd size {width}×{height}"));
            }
            let params: Vec<f64> = it
                .map(|s| num(Some(s), line, "parameter"))
                .collect::<std::result::Result<_, _>>()?;
            if params.len() != model.num_params() {
                return Err(format!(
                    "line {line}: {} takes {} parameters, got {}",
                    model.name(),
                    model.num_params(),
                    params.len()
                ));
            }
            Ok(ColmapCamera {
                id,
                model,
                width: width as u32,
                height: height as u32,
                params,
            })
        })
        .collect()
}

/// Two lines per image, as COLMAP writes them: the pose line, then the 2D
/// points line, which may be empty (so it is read unconditionally).
fn parse_images_txt(text: &str) -> std::result::Result<Vec<ColmapImage>, String> {
    let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l.trim()));
    let mut images = Vec::new();
    while let Some((line, l)) = lines.next() {
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let mut it = l.split_whitespace();
        let id = num(it.next(), line, "image id")?;
        let mut v = [0.0; 7];
        for (k, x) in v.iter_mut().enumerate() {
            *x = num(it.next(), line, ["QW", "QX", "QY", "QZ", "TX", "TY", "TZ"][k])?;
        }
        let camera_id = num(it.next(), line, "camera id")?;
        // Names may contain spaces: the rest of the line.
        let name = it.collect::<Vec<_>>().join(" ");
        if name.is_empty() {
            return Err(format!("line {line}: missing image name"));
        }
        lines.next();
        images.push(ColmapImage {
            id,
            qvec: [v[0], v[1], v[2], v[3]],
            tvec: [v[4], v[5], v[6]],
            camera_id,
            name,
        });
    }
    Ok(images)
}
