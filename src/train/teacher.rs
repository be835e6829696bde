//! Teacher feature maps: one low-resolution map of C-channel features per
//! training view (a ViT's patch tokens after PCA), sampled bilinearly at a
//! pixel to give the target of the distillation loss.

use crate::{ensure, Result};

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

/// Maps of every training view, all with the same channel count.
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureMaps {
    pub channels: usize,
    pub maps: Vec<FeatureMap>,
}

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
        Ok(FeatureMaps { channels, maps })
    }

    /// Bilinear sample of view `view`'s map at the centre of `pixel`
    /// (clamped at the borders) into `out` (len = channels).
    pub fn sample(&self, view: usize, pixel: [u16; 2], out: &mut [f32]) {
        let m = &self.maps[view];
        let c = self.channels;
        let u = (pixel[0] as f32 + 0.5) / m.image_width as f32 * m.width as f32 - 0.5;
        let v = (pixel[1] as f32 + 0.5) / m.image_height as f32 * m.height as f32 - 0.5;
        let u = u.clamp(0.0, (m.width - 1) as f32);
        let v = v.clamp(0.0, (m.height - 1) as f32);
        let (x0, y0) = (u as usize, v as usize);
        let (x1, y1) = ((x0 + 1).min(m.width - 1), (y0 + 1).min(m.height - 1));
        let (fx, fy) = (u - x0 as f32, v - y0 as f32);
        let at = |x: usize, y: usize| &m.data[(y * m.width + x) * c..(y * m.width + x + 1) * c];
        let (a, b, d, e) = (at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1));
        for k in 0..c {
            out[k] = (1.0 - fy) * ((1.0 - fx) * a[k] + fx * b[k]) + fy * ((1.0 - fx) * d[k] + fx * e[k]);
        }
    }
}
