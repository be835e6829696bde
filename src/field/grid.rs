//! Channel grids: C values per grid point, stored densely over the whole grid
//! or sparsely for the occupied voxels of a [`RankIndex`] only.

use super::bitmap::RankIndex;
use super::geom::GridGeom;
use glam::Vec3;
use half::f16;
use std::sync::Arc;

#[derive(Clone, Debug)]
pub enum Layout {
    /// Every grid point stores its channels.
    Dense,
    /// Only voxels set in the index store channels; sampling renormalises the
    /// trilinear weights over the corners that are present, so values at a
    /// surface are not blended with empty space.
    Sparse(Arc<RankIndex>),
}

#[derive(Clone, Debug)]
pub struct ChannelGrid {
    pub geom: GridGeom,
    pub channels: usize,
    pub layout: Layout,
    /// `slots × channels` values, channels contiguous.
    pub data: Vec<f16>,
}

impl ChannelGrid {
    pub fn dense(geom: GridGeom, channels: usize, data: Vec<f16>) -> Self {
        debug_assert_eq!(data.len(), geom.len() * channels);
        ChannelGrid {
            geom,
            channels,
            layout: Layout::Dense,
            data,
        }
    }
    pub fn sparse(geom: GridGeom, channels: usize, index: Arc<RankIndex>, data: Vec<f16>) -> Self {
        debug_assert_eq!(data.len(), index.count() * channels);
        ChannelGrid {
            geom,
            channels,
            layout: Layout::Sparse(index),
            data,
        }
    }
    /// Number of stored grid points.
    pub fn slots(&self) -> usize {
        self.data.len() / self.channels.max(1)
    }
    #[inline]
    fn slot(&self, voxel: usize) -> Option<usize> {
        match &self.layout {
            Layout::Dense => Some(voxel),
            Layout::Sparse(ix) => ix.slot(voxel),
        }
    }
    /// Channels of grid point `voxel`; zeros if it is not stored.
    pub fn at_voxel(&self, voxel: usize, out: &mut [f32]) {
        match self.slot(voxel) {
            Some(s) => {
                let src = &self.data[s * self.channels..(s + 1) * self.channels];
                for (o, v) in out.iter_mut().zip(src) {
                    *o = v.to_f32();
                }
            }
            None => out.fill(0.0),
        }
    }
    /// `out += w × channels of slot s`, with an inlined exact conversion so
    /// the loop vectorises (no call per value).
    #[inline]
    fn add_weighted(&self, s: usize, w: f32, out: &mut [f32]) {
        let src = &self.data[s * self.channels..(s + 1) * self.channels];
        for (o, h) in out.iter_mut().zip(src) {
            *o += w * f16_to_f32_exact(h.to_bits());
        }
    }
    /// Trilinear sample at world point `p` into `out` (len = channels).
    /// Returns false (and zeros) outside the grid or where no corner is stored.
    pub fn sample(&self, p: Vec3, out: &mut [f32]) -> bool {
        out.fill(0.0);
        let Some(c) = self.geom.corners(p) else { return false };
        let mut wsum = 0.0;
        for k in 0..8 {
            let w = c.weight[k];
            if w == 0.0 {
                continue;
            }
            let Some(s) = self.slot(c.index[k]) else { continue };
            wsum += w;
            self.add_weighted(s, w, out);
        }
        if wsum <= 1e-6 {
            out.fill(0.0);
            return false;
        }
        if matches!(self.layout, Layout::Sparse(_)) {
            let inv = 1.0 / wsum;
            out.iter_mut().for_each(|o| *o *= inv);
        }
        true
    }
}

/// f16 bits → f32, the same value and bits as `f16::to_f32` for every input
/// (NaNs quieted the same way), in branch-free integer and float operations
/// that the compiler vectorises.
#[inline(always)]
pub fn f16_to_f32_exact(h: u16) -> f32 {
    let h = h as u32;
    let sign = (h & 0x8000) << 16;
    let abs = h & 0x7fff;
    // Finite values: exponent and mantissa shifted into place, rescaled by
    // 2^(127 − 15). Exact, subnormals included: multiplying by a power of two
    // whose result is a normal f32 rounds nothing.
    let finite = (f32::from_bits(abs << 13) * f32::from_bits(0x7780_0000)).to_bits();
    let special = if abs > 0x7c00 {
        0x7fc0_0000 | (abs & 0x3ff) << 13 // NaN, quiet bit set
    } else {
        0x7f80_0000 // infinity
    };
    f32::from_bits(sign | if abs >= 0x7c00 { special } else { finite })
}

/// Density activation applied *after* trilinear interpolation of the raw grid
/// (as DVGO/TensoRF do). Edits act on the activated value.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Activation {
    /// σ = ln(1 + exp(raw + shift))
    Softplus { shift: f32 },
    /// σ = max(raw, 0)
    Relu,
}

impl Activation {
    #[inline]
    pub fn apply(&self, raw: f32) -> f32 {
        match *self {
            Activation::Softplus { shift } => {
                let x = raw + shift;
                // Numerically stable softplus.
                if x > 20.0 {
                    x
                } else {
                    x.exp().ln_1p()
                }
            }
            Activation::Relu => raw.max(0.0),
        }
    }
    /// d σ / d raw at `raw` (used by training).
    #[inline]
    pub fn derivative(&self, raw: f32) -> f32 {
        match *self {
            Activation::Softplus { shift } => 1.0 / (1.0 + (-(raw + shift)).exp()),
            Activation::Relu => (raw > 0.0) as u8 as f32,
        }
    }
}

/// The raw density grid (f32, dense, the field's own resolution).
#[derive(Clone, Debug)]
pub struct DensityGrid {
    pub geom: GridGeom,
    pub raw: Vec<f32>,
    pub activation: Activation,
}

impl DensityGrid {
    /// Activated density at a world point; 0 outside the grid.
    #[inline]
    pub fn sigma(&self, p: Vec3) -> f32 {
        match self.geom.corners(p) {
            Some(c) => {
                let mut r = 0.0;
                for k in 0..8 {
                    r += c.weight[k] * self.raw[c.index[k]];
                }
                self.activation.apply(r)
            }
            None => 0.0,
        }
    }
    /// Activated density at grid point `i`.
    #[inline]
    pub fn sigma_at(&self, i: usize) -> f32 {
        self.activation.apply(self.raw[i])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_f16_conversion_matches_half_for_every_value() {
        for h in 0..=u16::MAX {
            let want = f16::from_bits(h).to_f32().to_bits();
            assert_eq!(f16_to_f32_exact(h).to_bits(), want, "f16 bits {h:#06x}");
        }
    }
}
