//! Teacher feature maps: one low-resolution map of C-channel features per
//! training view (a ViT's patch tokens after PCA), sampled bilinearly at a
//! pixel to give the target of the distillation loss.

use crate::data::Image;
use crate::error::Error;
use crate::{ensure, Result};
use std::path::{Path, PathBuf};

/// One view's map: `height × width × channels`, row-major, channels last,
/// covering the whole image (map cell centres at (j + ½)/width of its width).
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureMap {
    pub width: usize,
    pub height: usize,
    /// Size of the image the map covers.
    pub image_width: u32,
    pub image_height: u32,
    pub data: Vec<f32>,
}

impl FeatureMap {
    /// Adds `weight` times the bilinear sample at cell coordinates (u, v)
    /// (cell centres at whole numbers, clamped to the map) of this
    /// `channels`-channel map to `acc`.
    pub fn add_bilinear(&self, channels: usize, u: f32, v: f32, weight: f32, acc: &mut [f32]) {
        let c = channels;
        let u = u.clamp(0.0, (self.width - 1) as f32);
        let v = v.clamp(0.0, (self.height - 1) as f32);
        let (x0, y0) = (u as usize, v as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (fx, fy) = (u - x0 as f32, v - y0 as f32);
        let at = |x: usize, y: usize| &self.data[(y * self.width + x) * c..(y * self.width + x + 1) * c];
        let (a, b, d, e) = (at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1));
        for k in 0..c {
            acc[k] += weight * ((1.0 - fy) * ((1.0 - fx) * a[k] + fx * b[k]) + fy * ((1.0 - fx) * d[k] + fx * e[k]));
        }
    }

    /// The features of a rendered frame as a map at the frame's own
    /// resolution (what a perfect teacher would give).
    pub fn from_frame(f: crate::render::Frame) -> FeatureMap {
        FeatureMap {
            width: f.width as usize,
            height: f.height as usize,
            image_width: f.width,
            image_height: f.height,
            data: f.out.features,
        }
    }
}

/// Maps of the training views (every view, or the subset in `views`), all
/// with the same channel count.
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureMaps {
    pub channels: usize,
    pub maps: Vec<FeatureMap>,
    /// Per map, the mean image colour under each cell (row-major): the
    /// guide of [`FeatureMaps::sample_guided`]; empty when not attached.
    pub guides: Vec<Vec<[f32; 3]>>,
    /// The training views the maps are of, ascending (`maps[k]` is of
    /// view `views[k]`); empty: one map per view, in order.
    pub views: Vec<usize>,
}

/// Joint bilateral upsampling window: cells within this many of the
/// sample's cell, weighted by a Gaussian of σ = [`GUIDE_SIGMA_CELLS`] cells.
const GUIDE_RADIUS: isize = 2;
const GUIDE_SIGMA_CELLS: f32 = 1.0;

impl FeatureMaps {
    pub fn new(channels: usize, maps: Vec<FeatureMap>) -> Result<Self> {
        ensure!(channels >= 1, "feature maps need at least one channel");
        for (i, m) in maps.iter().enumerate() {
            ensure!(
                m.width >= 1 && m.height >= 1 && m.data.len() == m.width * m.height * channels,
                "feature map {i}: {}×{}×{channels} does not match its {} values",
                m.height,
                m.width,
                m.data.len()
            );
            ensure!(
                m.data.iter().all(|v| v.is_finite()),
                "feature map {i} has a non-finite value"
            );
        }
        Ok(FeatureMaps {
            channels,
            maps,
            guides: vec![],
            views: vec![],
        })
    }

    /// The same maps, said to be of the training views `views` (ascending,
    /// one per map) rather than of every view in order.
    pub fn of_views(self, views: Vec<usize>) -> Result<Self> {
        ensure!(
            views.len() == self.maps.len() && views.windows(2).all(|w| w[0] < w[1]),
            "{} feature maps for the views {views:?} (one map per view, views ascending)",
            self.maps.len()
        );
        Ok(FeatureMaps { views, ..self })
    }

    /// The training view map `k` is of.
    #[inline]
    pub fn view_of(&self, k: usize) -> usize {
        self.views.get(k).copied().unwrap_or(k)
    }

    /// The index of training view `view`'s map, if the teacher saw it.
    #[inline]
    pub fn map_of(&self, view: usize) -> Option<usize> {
        if self.views.is_empty() {
            (view < self.maps.len()).then_some(view)
        } else {
            self.views.binary_search(&view).ok()
        }
    }

    /// Bilinear sample of map `map` at the centre of `pixel` (clamped at
    /// the borders) into `out` (len = channels).
    pub fn sample(&self, map: usize, pixel: [u16; 2], out: &mut [f32]) {
        let m = &self.maps[map];
        let u = (pixel[0] as f32 + 0.5) / m.image_width as f32 * m.width as f32 - 0.5;
        let v = (pixel[1] as f32 + 0.5) / m.image_height as f32 * m.height as f32 - 0.5;
        out[..self.channels].fill(0.0);
        m.add_bilinear(self.channels, u, v, 1.0, out);
    }

    /// Attaches the guides of [`FeatureMaps::sample_guided`]: for each map,
    /// the mean colour of its image under each cell (`images` in map order,
    /// each of the size its map covers).
    pub fn attach_guides(&mut self, images: &[&Image]) -> Result<()> {
        ensure!(
            images.len() == self.maps.len(),
            "{} guide images for {} feature maps",
            images.len(),
            self.maps.len()
        );
        self.guides = self
            .maps
            .iter()
            .zip(images)
            .map(|(m, img)| cell_colours(m, img))
            .collect::<Result<_>>()?;
        Ok(())
    }

    /// Map `map` at `pixel`, upsampled with the image as guide
    /// (joint bilateral upsampling, Kopf et al. 2007): the cells around the
    /// pixel are weighted by their distance (σ one cell) and by how close
    /// their mean colour is to the pixel's `colour` (σ `sigma_colour`).
    /// A ViT's patch token blends everything under its 14×14 patch, so the
    /// bilinear map blurs an object into its support for a patch or two;
    /// the colour term takes a pixel's feature from the cells that look
    /// like it. Falls back to [`FeatureMaps::sample`] without guides, and
    /// where no cell nearby has a colour like the pixel's.
    pub fn sample_guided(&self, map: usize, pixel: [u16; 2], colour: [f32; 3], sigma_colour: f32, out: &mut [f32]) {
        let (Some(guide), true) = (self.guides.get(map), sigma_colour > 0.0) else {
            return self.sample(map, pixel, out);
        };
        let m = &self.maps[map];
        let c = self.channels;
        let u = (pixel[0] as f32 + 0.5) / m.image_width as f32 * m.width as f32 - 0.5;
        let v = (pixel[1] as f32 + 0.5) / m.image_height as f32 * m.height as f32 - 0.5;
        let (cu, cv) = (u.round() as isize, v.round() as isize);
        let (inv_s, inv_c) = (
            0.5 / (GUIDE_SIGMA_CELLS * GUIDE_SIGMA_CELLS),
            0.5 / (sigma_colour * sigma_colour),
        );
        out[..c].fill(0.0);
        let (mut total, mut spatial) = (0.0f32, 0.0f32);
        for y in (cv - GUIDE_RADIUS).max(0)..=(cv + GUIDE_RADIUS).min(m.height as isize - 1) {
            for x in (cu - GUIDE_RADIUS).max(0)..=(cu + GUIDE_RADIUS).min(m.width as isize - 1) {
                let cell = y as usize * m.width + x as usize;
                let (dx, dy) = (x as f32 - u, y as f32 - v);
                let ws = (-(dx * dx + dy * dy) * inv_s).exp();
                let g = guide[cell];
                let dc = (0..3).map(|k| (g[k] - colour[k]).powi(2)).sum::<f32>();
                let w = ws * (-dc * inv_c).exp();
                spatial += ws;
                total += w;
                for (o, f) in out[..c].iter_mut().zip(&m.data[cell * c..(cell + 1) * c]) {
                    *o += w * f;
                }
            }
        }
        if total <= 1e-4 * spatial {
            return self.sample(map, pixel, out);
        }
        out[..c].iter_mut().for_each(|o| *o /= total);
    }
}

/// The mean colour of `img` under each cell of `map` (pixels assigned to
/// the cell their centre falls in).
fn cell_colours(map: &FeatureMap, img: &Image) -> Result<Vec<[f32; 3]>> {
    ensure!(
        img.width == map.image_width && img.height == map.image_height,
        "guide image {}x{} does not match its feature map's {}x{}",
        img.width,
        img.height,
        map.image_width,
        map.image_height
    );
    let mut sum = vec![[0.0f32; 4]; map.width * map.height];
    for y in 0..img.height {
        let cy = ((y as f32 + 0.5) / img.height as f32 * map.height as f32) as usize;
        for x in 0..img.width {
            let cx = ((x as f32 + 0.5) / img.width as f32 * map.width as f32) as usize;
            let s = &mut sum[cy.min(map.height - 1) * map.width + cx.min(map.width - 1)];
            let p = img.pixel(x, y);
            s[0] += p[0];
            s[1] += p[1];
            s[2] += p[2];
            s[3] += 1.0;
        }
    }
    Ok(sum
        .into_iter()
        .map(|s| {
            let n = s[3].max(1.0);
            [s[0] / n, s[1] / n, s[2] / n]
        })
        .collect())
}

/// Planar `[C, n]` values (channel-major) to `[n, C]` (channels last).
pub fn channels_last(planar: &[f32], channels: usize) -> Vec<f32> {
    let n = planar.len() / channels;
    let mut out = vec![0.0; planar.len()];
    for (k, plane) in planar.chunks_exact(n).enumerate() {
        for (i, &v) in plane.iter().enumerate() {
            out[i * channels + k] = v;
        }
    }
    out
}

/// Where teacher features come from.
#[derive(Clone, Debug, PartialEq)]
pub enum TeacherSource {
    /// An ONNX ViT run on every training image ([`super::vit`]); `size` is
    /// the long side of its input (0 = automatic, [`super::vit::input_dims`]);
    /// `shifts` > 1 runs it on `shifts²` inputs moved by fractions of a
    /// patch for a map that many times as dense ([`super::vit::Vit::run_dense`]);
    /// `tiles` > 1 on `tiles²` overlapping enlarged crops.
    Onnx {
        path: PathBuf,
        output: String,
        size: u32,
        shifts: u32,
        tiles: u32,
    },
    /// A folder of precomputed maps, one `.npy` / `.npz` per image named
    /// after it (`r_0.npy` or `r_0.png.npy`), `[h, w, C]` or `[C, h, w]`
    /// (the larger of the first and last sizes is the channel axis), f32 or
    /// f16, an optional leading 1.
    Precomputed(PathBuf),
}

impl TeacherSource {
    /// A folder means precomputed maps, a file an ONNX model (run with
    /// `shifts` and `tiles` per axis).
    pub fn from_path(path: &Path, output: &str, size: u32, shifts: u32, tiles: u32) -> Result<TeacherSource> {
        crate::ensure_within!(
            OutOfRange,
            (1..=super::vit::MAX_SHIFTS).contains(&shifts),
            "teacher shifts {shifts} is out of range 1..={}",
            super::vit::MAX_SHIFTS
        );
        crate::ensure_within!(
            OutOfRange,
            (1..=super::vit::MAX_TILES).contains(&tiles),
            "teacher tiles {tiles} is out of range 1..={}",
            super::vit::MAX_TILES
        );
        if path.is_dir() {
            Ok(TeacherSource::Precomputed(path.to_path_buf()))
        } else if path.is_file() {
            Ok(TeacherSource::Onnx {
                path: path.to_path_buf(),
                output: output.to_string(),
                size,
                shifts,
                tiles,
            })
        } else {
            Err(Error::bad_file(
                path,
                "teacher not found (expected an .onnx file or a folder of .npy/.npz maps)",
            ))
        }
    }

    /// Input pixels the teacher runs on for one `width × height` image (all
    /// its shifted runs and crops; a crop is an input of the same size),
    /// which is what its time goes with; 0 for precomputed maps.
    pub fn input_pixels(&self, width: u32, height: u32) -> u64 {
        match self {
            TeacherSource::Onnx {
                size, shifts, tiles, ..
            } => {
                let [w, h] = super::vit::input_dims(*size, width, height, *shifts);
                let runs = (*shifts as u64).pow(2) * (*tiles as u64).pow(2);
                w as u64 * h as u64 * runs
            }
            TeacherSource::Precomputed(_) => 0,
        }
    }

    fn describe(&self) -> String {
        match self {
            TeacherSource::Onnx {
                path,
                output,
                size,
                shifts,
                tiles,
            } => {
                let (len, modified) = file_stamp(path);
                let size = match size {
                    0 => {
                        let (lo, hi) = super::vit::auto_side(*shifts);
                        format!("auto {lo}..{hi}")
                    }
                    s => s.to_string(),
                };
                // One run per image keeps the key it always had (caches stay valid).
                let shifts = match shifts {
                    1 => String::new(),
                    s => format!(" shifts {s}"),
                };
                // Whole-image runs keep the key they always had.
                let tiles = match tiles {
                    1 => String::new(),
                    t => format!(" tiles {t}"),
                };
                format!(
                    "onnx {} ({len} bytes, modified {modified}) output {output} size {size}{shifts}{tiles}",
                    path.display()
                )
            }
            TeacherSource::Precomputed(dir) => format!("precomputed {}", dir.display()),
        }
    }
}

fn file_stamp(path: &Path) -> (u64, u64) {
    let m = std::fs::metadata(path).ok();
    let len = m.as_ref().map_or(0, |m| m.len());
    let modified = m
        .and_then(|m| m.modified().ok())
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_secs());
    (len, modified)
}

/// What [`teacher_features`] did, for the user.
#[derive(Clone, Debug)]
pub struct TeacherReport {
    pub source: String,
    pub raw_channels: usize,
    pub channels: usize,
    /// Variance explained by the kept PCA components.
    pub explained: f32,
    pub map_size: [usize; 2],
    /// Images the teacher ran on (or whose maps came from the cache).
    pub images: usize,
    pub cached: Option<PathBuf>,
    pub from_cache: bool,
    pub seconds: f64,
}

/// Teacher features of `images` (the training views, in order; `paths` name
/// them for precomputed maps), reduced by PCA to `dims` channels fitted over
/// all of them. With a cache folder the result is stored under a key of the
/// teacher, the settings and the image contents, and reused when they match.
pub fn teacher_features(
    source: &TeacherSource,
    images: &[&Image],
    paths: &[PathBuf],
    dims: usize,
    cache_dir: Option<&Path>,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<(FeatureMaps, TeacherReport)> {
    ensure!(!images.is_empty() && images.len() == paths.len(), "teacher: no images");
    let t0 = std::time::Instant::now();
    let key = cache_key(source, images, dims);
    let cache_file = cache_dir.map(|d| d.join(format!("{:016x}.safetensors", fnv(key.as_bytes()))));
    let mut report = TeacherReport {
        source: source.describe(),
        raw_channels: 0,
        channels: dims,
        explained: 1.0,
        map_size: [0, 0],
        images: images.len(),
        cached: cache_file.clone(),
        from_cache: false,
        seconds: 0.0,
    };
    if let Some(maps) = cache_file.as_deref().and_then(|f| cache::load(f, &key).ok()) {
        report.from_cache = true;
        report.map_size = [maps.maps[0].width, maps.maps[0].height];
        report.seconds = t0.elapsed().as_secs_f64();
        return Ok((maps, report));
    }
    let raw = match source {
        TeacherSource::Onnx {
            path,
            output,
            size,
            shifts,
            tiles,
        } => {
            // The network allocates and frees activations of megabytes
            // per layer: kept in the heaps while it runs (`Heap::Scratch`).
            let _heap = crate::heap::scoped(crate::heap::Heap::Scratch);
            // One prepared model per input size (captures rarely mix sizes).
            let mut vits: Vec<super::vit::Vit> = Vec::new();
            let mut maps = Vec::with_capacity(images.len());
            for (i, img) in images.iter().enumerate() {
                let dims = super::vit::input_dims(*size, img.width, img.height, *shifts);
                let k = match vits.iter().position(|v| v.dims == dims) {
                    Some(k) => k,
                    None => {
                        vits.push(super::vit::Vit::load(path, output, dims)?);
                        vits.len() - 1
                    }
                };
                maps.push(vits[k].run_tiled(img, *shifts, *tiles)?);
                progress(i + 1, images.len());
            }
            maps
        }
        TeacherSource::Precomputed(dir) => precomputed(dir, images, paths)?,
    };
    let raw_c = raw[0].data.len() / (raw[0].width * raw[0].height);
    ensure!(
        dims <= raw_c,
        "the teacher gives {raw_c} channels, fewer than the {dims} asked for"
    );
    let pca = super::pca::Pca::fit(&pca_sample(&raw, raw_c), raw_c, dims)?;
    let maps: Vec<FeatureMap> = raw
        .into_iter()
        .map(|m| FeatureMap {
            data: pca.project_all(&m.data),
            ..m
        })
        .collect();
    let maps = FeatureMaps::new(dims, maps)?;
    report.raw_channels = raw_c;
    report.explained = pca.explained;
    report.map_size = [maps.maps[0].width, maps.maps[0].height];
    if let Some(f) = &cache_file {
        // A cache that cannot be written is not an error: the features are
        // simply recomputed next time.
        if let Err(e) = cache::save(f, &key, &maps) {
            eprintln!("note: teacher feature cache not written: {e}");
            report.cached = None;
        }
    }
    report.seconds = t0.elapsed().as_secs_f64();
    Ok((maps, report))
}

/// Most tokens the PCA is fitted on (400 MB of 384-channel f32 rows).
const PCA_MAX_TOKENS: usize = 1 << 18;

/// The tokens the PCA is fitted on: every one while they number at most
/// [`PCA_MAX_TOKENS`], else an even stride through all maps, so that dense
/// maps of a large capture (`shifts`) are not all copied once more.
fn pca_sample(maps: &[FeatureMap], channels: usize) -> Vec<f32> {
    let total: usize = maps.iter().map(|m| m.data.len() / channels).sum();
    let stride = total.div_ceil(PCA_MAX_TOKENS).max(1);
    let rows = maps.iter().flat_map(|m| m.data.chunks_exact(channels));
    rows.step_by(stride).flatten().copied().collect()
}

/// The per-user cache folder for teacher features: `$ISRF_CACHE`, else
/// `$XDG_CACHE_HOME/isrf`, else `~/.cache/isrf`.
pub fn default_cache_dir() -> Option<PathBuf> {
    let base = if let Some(d) = std::env::var_os("ISRF_CACHE") {
        PathBuf::from(d)
    } else if let Some(d) = std::env::var_os("XDG_CACHE_HOME") {
        PathBuf::from(d).join("isrf")
    } else {
        PathBuf::from(std::env::var_os("HOME")?).join(".cache/isrf")
    };
    Some(base.join("teacher"))
}

/// The teacher, the PCA size and every image's size and pixels (CRC32).
fn cache_key(source: &TeacherSource, images: &[&Image], dims: usize) -> String {
    let mut k = format!("{} dims {dims} images {}", source.describe(), images.len());
    for img in images {
        let crc = crc32fast::hash(bytemuck::cast_slice(&img.rgb));
        k.push_str(&format!(" {}x{}:{crc:08x}", img.width, img.height));
    }
    k
}

/// 64-bit FNV-1a: a short stable file name for a long key.
fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
    })
}

/// Reads the precomputed map of every image from `dir`.
fn precomputed(dir: &Path, images: &[&Image], paths: &[PathBuf]) -> Result<Vec<FeatureMap>> {
    let mut maps: Vec<FeatureMap> = Vec::with_capacity(images.len());
    for (img, p) in images.iter().zip(paths) {
        let name = p
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let stem = p
            .file_stem()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let file = [&stem, &name]
            .iter()
            .flat_map(|b| [dir.join(format!("{b}.npy")), dir.join(format!("{b}.npz"))])
            .find(|f| f.is_file())
            .ok_or_else(|| Error::bad_file(dir, format!("no {stem}.npy or {stem}.npz for image {}", p.display())))?;
        let (shape, data) = npy::read(&file)?;
        let (w, h, c, data) = npy::to_hwc(&shape, data).map_err(|r| Error::bad_file(&file, r))?;
        if let Some(first) = maps.first() {
            let c0 = first.data.len() / (first.width * first.height);
            if c != c0 {
                return Err(Error::bad_file(
                    &file,
                    format!("{c} channels, but the first map has {c0}"),
                ));
            }
        }
        maps.push(FeatureMap {
            width: w,
            height: h,
            image_width: img.width,
            image_height: img.height,
            data,
        });
    }
    Ok(maps)
}

mod npy {
    use crate::error::{Error, Result};
    use std::path::Path;

    /// Shape and values (as f32) of a `.npy`, or of the first array of a
    /// `.npz`, read by the strict parser in [`crate::npy`].
    pub fn read(path: &Path) -> Result<(Vec<usize>, Vec<f32>)> {
        let bad = |why: String| Error::bad_file(path, why);
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let bytes = match crate::util::extension(path) == "npz" {
            true => crate::npy::read_npz_first(&bytes).map_err(bad)?,
            false => bytes,
        };
        let npy = crate::npy::parse(&bytes).map_err(bad)?;
        let data = npy.to_f32();
        if let Some(i) = data.iter().position(|v| !v.is_finite()) {
            return Err(bad(format!("value {i} is not finite (as f32)")));
        }
        Ok((npy.shape, data))
    }

    /// `[h, w, C]` / `[C, h, w]` (optionally with a leading 1) to
    /// channels-last `(w, h, C, data)`.
    pub fn to_hwc(shape: &[usize], data: Vec<f32>) -> std::result::Result<(usize, usize, usize, Vec<f32>), String> {
        let s: &[usize] = if shape.len() == 4 && shape[0] == 1 {
            &shape[1..]
        } else {
            shape
        };
        let &[a, b, c] = s else {
            return Err(format!("shape {shape:?} is not [h, w, C] or [C, h, w]"));
        };
        if a == 0 || b == 0 || c == 0 {
            return Err(format!("empty map {shape:?}"));
        }
        if c >= a {
            return Ok((b, a, c, data));
        }
        Ok((c, b, a, super::channels_last(&data, a)))
    }
}

mod cache {
    use super::{FeatureMap, FeatureMaps};
    use crate::error::{write_atomic, Error, Result};
    use crate::field::io::{check_format, parse, read_all, read_metadata, serialize, Tensors};
    use safetensors::Dtype;
    use std::collections::HashMap;
    use std::path::Path;

    const FORMAT: &str = "isrf-teacher";
    const VERSION: u32 = 1;

    pub fn save(path: &Path, key: &str, maps: &FeatureMaps) -> Result<()> {
        if let Some(d) = path.parent() {
            std::fs::create_dir_all(d).map_err(|e| Error::io(d, e))?;
        }
        let c = maps.channels;
        let mut names = vec![];
        let mut tensors = vec![];
        let mut sizes = vec![];
        for (i, m) in maps.maps.iter().enumerate() {
            names.push(format!("map.{i:05}"));
            tensors.push((
                Dtype::F32,
                vec![m.height, m.width, c],
                bytemuck::cast_slice(&m.data).to_vec(),
            ));
            sizes.push([m.image_width, m.image_height]);
        }
        let mut meta = HashMap::new();
        meta.insert("format".into(), FORMAT.into());
        meta.insert("version".into(), VERSION.to_string());
        meta.insert("key".into(), key.into());
        meta.insert("channels".into(), c.to_string());
        meta.insert(
            "image_sizes".into(),
            serde_json::to_string(&sizes).expect("sizes serialise"),
        );
        write_atomic(path, &serialize(&names, &tensors, meta)?)
    }

    pub fn load(path: &Path, key: &str) -> Result<FeatureMaps> {
        let (meta, _) = read_metadata(path)?;
        check_format(&meta, FORMAT, VERSION, path)?;
        let bad = |r: &str| Error::bad_file(path, r.to_string());
        if meta.get("key").map(String::as_str) != Some(key) {
            return Err(bad("cached for other images or another teacher"));
        }
        let c: usize = meta
            .get("channels")
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| bad("no channel count"))?;
        let sizes: Vec<[u32; 2]> = meta
            .get("image_sizes")
            .and_then(|s| serde_json::from_str(s).ok())
            .ok_or_else(|| bad("no image sizes"))?;
        let bytes = read_all(path)?;
        let t = Tensors {
            st: parse(&bytes, path)?,
            path,
        };
        let mut maps = Vec::with_capacity(sizes.len());
        for (i, [iw, ih]) in sizes.into_iter().enumerate() {
            let name = format!("map.{i:05}");
            let shape = t.st.tensor(&name).map_err(|_| bad("missing map"))?.shape().to_vec();
            let &[h, w, _] = shape.as_slice() else {
                return Err(bad("map is not 3-D"));
            };
            maps.push(FeatureMap {
                width: w,
                height: h,
                image_width: iw,
                image_height: ih,
                data: t.f32(&name, &[h, w, c])?,
            });
        }
        FeatureMaps::new(c, maps)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pca_sample_strides_evenly_through_large_captures() {
        // One channel holding each token's index across the maps.
        let map = |first: usize, n: usize| FeatureMap {
            width: n,
            height: 1,
            image_width: 8,
            image_height: 8,
            data: (first..first + n).map(|t| t as f32).collect(),
        };
        let small = [map(0, 5), map(5, 3)];
        assert_eq!(pca_sample(&small, 1), (0..8).map(|t| t as f32).collect::<Vec<_>>());
        let n = PCA_MAX_TOKENS + PCA_MAX_TOKENS / 2;
        let big = [map(0, n / 2), map(n / 2, n - n / 2)];
        let s = pca_sample(&big, 1);
        assert!(
            s.len() <= PCA_MAX_TOKENS && s.len() >= PCA_MAX_TOKENS / 2,
            "{} tokens",
            s.len()
        );
        assert!(
            s.iter().enumerate().all(|(k, &t)| t == (2 * k) as f32),
            "every other token, across maps"
        );
    }

    /// A 4×1 map whose left two cells hold feature 0 and right two feature
    /// 1, over a 16×4 image that is black left of x = 7 and white from it:
    /// the colour edge sits inside cell 1, one pixel left of the features'.
    fn split_map() -> (FeatureMaps, Image) {
        let map = FeatureMap {
            width: 4,
            height: 1,
            image_width: 16,
            image_height: 4,
            data: vec![1.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1.0],
        };
        let rgb = (0..4)
            .flat_map(|_| (0..16).flat_map(|x| [if x < 7 { 0.0 } else { 1.0 }; 3]))
            .collect();
        let img = Image {
            width: 16,
            height: 4,
            rgb,
            alpha: None,
        };
        (FeatureMaps::new(2, vec![map]).unwrap(), img)
    }

    #[test]
    fn guided_samples_take_the_feature_of_cells_coloured_like_the_pixel() {
        let (mut maps, img) = split_map();
        maps.attach_guides(&[&img]).unwrap();
        // Cell colours: black, 3/4 black (pixels 4..8: three black), white, white.
        assert_eq!(maps.guides[0][1], [0.25; 3]);
        let mut out = [0.0f32; 2];
        // Pixel 2 (black) and 13 (white): the far cells' features are
        // excluded by colour, so each side keeps its own feature.
        maps.sample_guided(0, [2, 1], img.pixel(2, 1), 0.1, &mut out);
        assert!(out[0] > 0.99 && out[1] < 0.01, "{out:?}");
        maps.sample_guided(0, [13, 1], img.pixel(13, 1), 0.1, &mut out);
        assert!(out[1] > 0.99 && out[0] < 0.01, "{out:?}");
        // Pixel 7 is white but sits in cell 1 (feature 0): bilinear sampling
        // blends the features, the guided sample follows the colour.
        let mut bilinear = [0.0f32; 2];
        maps.sample(0, [7, 1], &mut bilinear);
        assert!(bilinear[0] > 0.5, "{bilinear:?}");
        maps.sample_guided(0, [7, 1], img.pixel(7, 1), 0.1, &mut out);
        assert!(out[1] > 0.99, "{out:?}");
        // The weights are normalised: features sum to one here.
        assert!((out[0] + out[1] - 1.0).abs() < 1e-5);
        // σ = 0 or no guides: the bilinear sample.
        maps.sample_guided(0, [7, 1], img.pixel(7, 1), 0.0, &mut out);
        assert_eq!(out, bilinear);
    }

    #[test]
    fn the_guide_sigma_must_be_finite_and_not_negative() {
        use crate::train::TrainConfig;
        for ok in [0.0, 0.1, 2.0] {
            assert!(TrainConfig {
                feature_guide: ok,
                ..Default::default()
            }
            .validate()
            .is_ok());
        }
        for bad in [-0.1, f32::NAN, f32::INFINITY] {
            let e = TrainConfig {
                feature_guide: bad,
                ..Default::default()
            }
            .validate()
            .unwrap_err();
            assert!(e.to_string().contains("feature guide"), "{e}");
        }
    }

    #[test]
    fn guides_must_match_their_maps() {
        let (mut maps, img) = split_map();
        assert!(maps.attach_guides(&[]).is_err());
        let small = Image {
            width: 8,
            height: 4,
            rgb: vec![0.0; 96],
            alpha: None,
        };
        let e = maps.attach_guides(&[&small]).unwrap_err().to_string();
        assert!(e.contains("8x4") && e.contains("16x4"), "{e}");
        let mut out = [0.0f32; 2];
        let mut bilinear = [0.0f32; 2];
        maps.sample_guided(0, [7, 1], img.pixel(7, 1), 0.1, &mut out);
        maps.sample(0, [7, 1], &mut bilinear);
        assert_eq!(out, bilinear, "no guides attached: bilinear");
    }
}
