//! Images for training and evaluation: flat f32 RGB arrays in [0, 1] with an
//! optional alpha channel.
//!
//! Values are the file's values scaled to [0, 1] (8-bit / 255, 16-bit /
//! 65535), not converted from sRGB: radiance fields are fitted to the stored
//! (display-referred) colours, as NeRF does, so rendered colours can be
//! written back to image files as they are.

use crate::error::{write_atomic, Error, Result};
use rayon::prelude::*;
use std::path::Path;

#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    /// Row-major RGB triples, `3 * width * height` values in [0, 1].
    pub rgb: Vec<f32>,
    /// Row-major opacity, `width * height` values in [0, 1], when the file
    /// has an alpha channel (for Blender scenes: the exact foreground mask).
    pub alpha: Option<Vec<f32>>,
}

pub use crate::limits::MAX_IMAGE_PIXELS;

/// Decodes a PNG or JPEG after reading its size from the header: the size
/// must be `expected` (width, height) when given and at most
/// [`MAX_IMAGE_PIXELS`], so a small file that claims a huge image costs
/// nothing. The decoder's own allocations are capped as well.
pub fn open_image(path: &Path, expected: Option<(u32, u32)>) -> Result<image::DynamicImage> {
    let decoder = open_decoder(path, expected)?;
    image::DynamicImage::from_decoder(decoder).map_err(|e| decode_error(path, e))
}

/// Checks a PNG or JPEG's size against `expected` and the limits from its
/// header, without decoding the pixels.
pub fn check_image(path: &Path, expected: Option<(u32, u32)>) -> Result<()> {
    open_decoder(path, expected).map(|_| ())
}

fn decode_error(path: &Path, e: image::ImageError) -> Error {
    match e {
        image::ImageError::IoError(io) => Error::io(path, io),
        other => Error::bad_file(path, format!("cannot decode image: {other}")),
    }
}

/// The decoder of a PNG or JPEG whose header passed the size checks.
fn open_decoder(path: &Path, expected: Option<(u32, u32)>) -> Result<impl image::ImageDecoder> {
    let mut reader = image::ImageReader::open(path)
        .and_then(|r| r.with_guessed_format())
        .map_err(|e| Error::io(path, e))?;
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(1 << 30);
    reader.limits(limits);
    let decoder = reader.into_decoder().map_err(|e| decode_error(path, e))?;
    let (w, h) = image::ImageDecoder::dimensions(&decoder);
    if let Some((ew, eh)) = expected.filter(|&e| e != (w, h)) {
        return Err(Error::bad_file(
            path,
            format!("image is {w}×{h} but its camera is {ew}×{eh}"),
        ));
    }
    if u64::from(w) * u64::from(h) > MAX_IMAGE_PIXELS {
        return Err(Error::bad_file(
            path,
            format!("image is {w}×{h}, more than the {MAX_IMAGE_PIXELS} pixels allowed"),
        ));
    }
    Ok(decoder)
}

impl Image {
    /// A `width`×`height` image whose pixels are not read yet
    /// ([`crate::data::Dataset::pixels`] reads them).
    pub fn deferred(width: u32, height: u32) -> Image {
        Image {
            width: width.max(1),
            height: height.max(1),
            rgb: vec![],
            alpha: None,
        }
    }
    /// True for an image made by [`Image::deferred`] (or whose pixels were
    /// released).
    pub fn is_deferred(&self) -> bool {
        self.rgb.is_empty()
    }
    /// Reads a PNG or JPEG file. RGB is left as stored (not composited).
    pub fn load(path: &Path) -> Result<Image> {
        Self::from_dynamic(open_image(path, None)?)
    }

    /// A dataset's view of the file at `path`: read (its size checked
    /// against `expected` from the header first, when given), composited
    /// over `background`, box-downscaled by `factor`.
    pub fn load_view(path: &Path, expected: Option<(u32, u32)>, background: [f32; 3], factor: u32) -> Result<Image> {
        let mut img = Self::from_dynamic(open_image(path, expected)?)?;
        img.composite(background);
        Ok(img.downscaled(factor))
    }

    /// Like [`Image::load`] for an image that must be `width`×`height` (its
    /// camera's size): checked from the header before decoding.
    pub fn load_sized(path: &Path, width: u32, height: u32) -> Result<Image> {
        Self::from_dynamic(open_image(path, Some((width, height)))?)
    }

    fn from_dynamic(img: image::DynamicImage) -> Result<Image> {
        let (width, height) = (img.width(), img.height());
        if !img.color().has_alpha() {
            return Ok(Image {
                width,
                height,
                rgb: img.into_rgb32f().into_raw(),
                alpha: None,
            });
        }
        let rgba = img.into_rgba32f().into_raw();
        let rgb = rgba.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
        let alpha = rgba.chunks_exact(4).map(|p| p[3]).collect();
        Ok(Image {
            width,
            height,
            rgb,
            alpha: Some(alpha),
        })
    }

    /// Number of pixels.
    pub fn len(&self) -> usize {
        self.width as usize * self.height as usize
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// RGB of pixel (x, y); panics when out of range (a programming error).
    pub fn pixel(&self, x: u32, y: u32) -> [f32; 3] {
        let i = 3 * (y as usize * self.width as usize + x as usize);
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }

    /// Puts the (straight-alpha) colours over `background`:
    /// rgb ← rgb·α + bg·(1 − α). Alpha is kept as the mask; no-op without it.
    pub fn composite(&mut self, background: [f32; 3]) {
        let Some(alpha) = &self.alpha else { return };
        self.rgb
            .par_chunks_exact_mut(3)
            .zip(alpha.par_iter())
            .for_each(|(c, &a)| {
                for (v, b) in c.iter_mut().zip(background) {
                    *v = *v * a + b * (1.0 - a);
                }
            });
    }

    /// Box-filtered copy at 1/`factor` size (floor of each side; leftover
    /// rows and columns are dropped, matching `Intrinsics::downscaled`).
    /// Each output pixel is the mean of a `factor`×`factor` block, which for
    /// composited colours equals compositing the box-filtered premultiplied
    /// colours.
    pub fn downscaled(&self, factor: u32) -> Image {
        let f = factor.max(1);
        if f == 1 {
            return self.clone();
        }
        let (w, h) = ((self.width / f).max(1), (self.height / f).max(1));
        Image {
            width: w,
            height: h,
            rgb: box_filter(&self.rgb, self.width, self.height, 3, f),
            alpha: self
                .alpha
                .as_ref()
                .map(|a| box_filter(a, self.width, self.height, 1, f)),
        }
    }

    /// Writes an 8-bit PNG (RGBA when there is alpha), atomically.
    pub fn save_png(&self, path: &Path) -> Result<()> {
        let to8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
        let (data, color) = match &self.alpha {
            None => (
                self.rgb.iter().map(|&v| to8(v)).collect::<Vec<u8>>(),
                image::ExtendedColorType::Rgb8,
            ),
            Some(a) => (
                self.rgb
                    .chunks_exact(3)
                    .zip(a)
                    .flat_map(|(c, &a)| [to8(c[0]), to8(c[1]), to8(c[2]), to8(a)])
                    .collect(),
                image::ExtendedColorType::Rgba8,
            ),
        };
        let mut bytes = Vec::new();
        image::ImageEncoder::write_image(
            image::codecs::png::PngEncoder::new(&mut bytes),
            &data,
            self.width,
            self.height,
            color,
        )
        .map_err(|e| Error::bad_file(path, format!("cannot encode PNG: {e}")))?;
        write_atomic(path, &bytes)
    }
}

/// Mean over `f`×`f` blocks of a row-major image with `c` channels; output
/// rows are computed in parallel.
fn box_filter(src: &[f32], width: u32, height: u32, c: usize, f: u32) -> Vec<f32> {
    let (w, f) = (width as usize, f as usize);
    let (ow, oh) = ((w / f).max(1), (height as usize / f).max(1));
    // A side shorter than the factor averages what there is.
    let (fx, fy) = (f.min(w), f.min(height as usize));
    let norm = 1.0 / (fx * fy) as f32;
    let mut out = vec![0.0f32; ow * oh * c];
    out.par_chunks_exact_mut(ow * c).enumerate().for_each(|(oy, row)| {
        for y in oy * fy..oy * fy + fy {
            let line = &src[y * w * c..(y + 1) * w * c];
            for (ox, px) in row.chunks_exact_mut(c).enumerate() {
                for x in ox * fx..ox * fx + fx {
                    for (k, v) in px.iter_mut().enumerate() {
                        *v += line[x * c + k];
                    }
                }
            }
        }
        row.iter_mut().for_each(|v| *v *= norm);
    });
    out
}
