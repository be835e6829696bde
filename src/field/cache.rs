//! Per-voxel features of occupied voxels, computed once per field.
//!
//! Segmentation queries features at grid points many times (NNFM over every
//! occupied voxel, bilateral weights between neighbours); decoding a VM grid or
//! interpolating a dense one each time would dominate. The cache is a flat
//! `occupied × channels` f32 array plus a rank index that maps a voxel to its
//! row in O(1), so there is no hash map and no per-voxel allocation.

use super::bitmap::{Bitmap, RankIndex};
use super::{Field, GridGeom};
use crate::error::Result;
use rayon::prelude::*;

/// Voxels with activated density above this are "occupied": the floor below
/// which the authors' code stops growing (σ > 0.001).
pub const OCCUPIED_FLOOR: f32 = 1e-3;

#[derive(Debug)]
pub struct FeatureCache {
    pub geom: GridGeom,
    pub channels: usize,
    /// Occupied voxel indices, ascending (row r of `feats` is voxel `voxels[r]`).
    pub voxels: Vec<u32>,
    pub index: RankIndex,
    /// Activated density of each occupied voxel.
    pub sigma: Vec<f32>,
    /// Raw features, `voxels.len() × channels`.
    pub feats: Vec<f32>,
    /// 1 / ‖feature‖ per occupied voxel (0 for a zero feature).
    pub inv_norm: Vec<f32>,
    /// Colour of each occupied voxel averaged over directions
    /// ([`super::Sampler::diffuse_color`]): the graph cut's colour terms
    /// read it for every voxel it labels, on every stroke.
    pub colours: Vec<glam::Vec3>,
    /// Edge length of the voxels whose σ is stored (the smallest grid
    /// spacing): the solidity floor of segmentation depends on it. A
    /// [coarse copy](Self::coarse) keeps its fine grid's, as its σ is the
    /// largest fine σ of its block.
    pub voxel_size: f32,
    /// The copy on a grid twice as coarse, made when first asked for.
    coarse: std::sync::OnceLock<Option<Box<FeatureCache>>>,
}

/// Segmenting needs semantic features: the check shared by the cache and
/// a script's dry run (which builds no cache).
pub fn require_features(field: &Field) -> crate::Result<()> {
    crate::ensure!(
        field.feature_channels() > 0,
        "this field has no semantic features to segment with"
    );
    Ok(())
}

impl FeatureCache {
    pub fn build(field: &Field) -> Result<Self> {
        let geom = field.geom();
        crate::ensure_within!(
            OutOfRange,
            geom.len() <= u32::MAX as usize,
            "grid {:?} is too large to index",
            geom.res
        );
        let channels = field.feature_channels();
        require_features(field)?;
        let d = &field.density;
        let bits = Bitmap::from_fn(geom.res, |i| d.sigma_at(i) > OCCUPIED_FLOOR);
        let voxels: Vec<u32> = bits.ones().map(|i| i as u32).collect();
        let index = RankIndex::new(bits);
        let sigma: Vec<f32> = voxels.par_iter().map(|&v| d.sigma_at(v as usize)).collect();
        let mut feats = vec![0.0f32; voxels.len() * channels];
        let mut colours = vec![glam::Vec3::ZERO; voxels.len()];
        feats
            .par_chunks_mut(channels * 256)
            .zip(colours.par_chunks_mut(256))
            .enumerate()
            .for_each(|(chunk, (out, colour))| {
                let mut s = field.sampler();
                for (j, (row, c)) in out.chunks_mut(channels).zip(colour).enumerate() {
                    let p = geom.point_of(voxels[chunk * 256 + j] as usize);
                    s.features(p, row);
                    *c = s.diffuse_color(p);
                }
            });
        Ok(Self::from_parts(
            geom,
            channels,
            geom.spacing().min_element(),
            voxels,
            index,
            sigma,
            feats,
            colours,
        ))
    }

    /// A cache of the given rows (`voxels` ascending and set in `index`);
    /// the feature norms are computed here.
    #[allow(clippy::too_many_arguments)]
    pub fn from_parts(
        geom: GridGeom,
        channels: usize,
        voxel_size: f32,
        voxels: Vec<u32>,
        index: RankIndex,
        sigma: Vec<f32>,
        feats: Vec<f32>,
        colours: Vec<glam::Vec3>,
    ) -> Self {
        let inv_norm = feats
            .par_chunks(channels.max(1))
            .map(|r| {
                let n = r.iter().map(|x| x * x).sum::<f32>().sqrt();
                if n > 1e-12 {
                    1.0 / n
                } else {
                    0.0
                }
            })
            .collect();
        FeatureCache {
            geom,
            channels,
            voxels,
            index,
            sigma,
            feats,
            inv_norm,
            colours,
            voxel_size,
            coarse: std::sync::OnceLock::new(),
        }
    }

    /// The copy of this cache on a grid twice as coarse
    /// ([`super::coarse`]), made on first use and kept; `None` when the
    /// grid is too small to halve.
    pub fn coarse(&self) -> Option<&FeatureCache> {
        self.coarse
            .get_or_init(|| super::coarse::build(self).map(Box::new))
            .as_deref()
    }
    pub fn len(&self) -> usize {
        self.voxels.len()
    }
    pub fn is_empty(&self) -> bool {
        self.voxels.is_empty()
    }
    #[inline]
    pub fn row(&self, r: usize) -> &[f32] {
        &self.feats[r * self.channels..(r + 1) * self.channels]
    }
    pub fn memory_bytes(&self) -> usize {
        self.feats.len() * 4 + self.voxels.len() * 24 + self.index.bits().words().len() * 12
    }
}
