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
    /// Fine voxels per voxel of this cache along each axis: 1 for a cache
    /// of the field's own grid, f for its [coarse copy](Self::coarse).
    pub factor: usize,
    /// The scene's up direction in the grid's space, where known
    /// ([`Field::up`]).
    pub up: Option<glam::Vec3>,
    /// The coarser copy, made when first asked for.
    coarse: std::sync::OnceLock<Option<Box<FeatureCache>>>,
    /// See [`Self::neighbours`].
    neighbours: std::sync::OnceLock<Vec<Neighbours>>,
    /// See [`Self::solid`]: the last floor asked for and its bitmap.
    solid: std::sync::Mutex<Option<(u32, std::sync::Arc<Bitmap>)>>,
}

/// A cache row's neighbours one voxel along +x, +y and +z: their rows
/// (`u32::MAX` where that voxel is not cached) and the squared distances
/// between the unit features.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Neighbours {
    pub row: [u32; 3],
    pub distance: [f32; 3],
}

impl Neighbours {
    const NONE: Neighbours = Neighbours {
        row: [u32::MAX; 3],
        distance: [f32::NAN; 3],
    };
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
        )
        .with_up(field.up))
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
            factor: 1,
            up: None,
            coarse: std::sync::OnceLock::new(),
            neighbours: std::sync::OnceLock::new(),
            solid: std::sync::Mutex::new(None),
        }
    }

    /// This cache marked as a coarse copy of `f` fine voxels to one along
    /// each axis.
    pub fn coarsened(mut self, f: usize) -> Self {
        self.factor = f;
        self
    }

    /// This cache with the scene's up direction ([`Self::up`]).
    pub fn with_up(mut self, up: Option<glam::Vec3>) -> Self {
        self.up = up;
        self
    }

    /// The cached voxels with σ above `floor`, kept for the last floor
    /// asked for: every stroke on a coarse copy maps its mask back through
    /// it, and building it walks every row (8 ms on the fern).
    pub fn solid(&self, floor: f32) -> std::sync::Arc<Bitmap> {
        let mut memo = self.solid.lock().unwrap_or_else(|e| e.into_inner());
        match &*memo {
            Some((bits, b)) if *bits == floor.to_bits() => b.clone(),
            _ => {
                let mut out = Bitmap::new(self.geom.res);
                for (&v, _) in self.voxels.iter().zip(&self.sigma).filter(|(_, &s)| s > floor) {
                    out.set(v as usize, true);
                }
                let out = std::sync::Arc::new(out);
                *memo = Some((floor.to_bits(), out.clone()));
                out
            }
        }
    }

    /// Each row's +x, +y and +z neighbours among the rows and the squared
    /// distances between their unit features, made on first use and kept
    /// (24 bytes a row). The graph cut weighs every neighbour pair of its
    /// domain by them, stroke after stroke: found per stroke (rank lookups
    /// and 64-channel distances) they took 20–40 ms of it.
    pub fn neighbours(&self) -> &[Neighbours] {
        self.neighbours.get_or_init(|| {
            let res = self.geom.res;
            let strides = [1, res[0], res[0] * res[1]];
            self.voxels
                .par_iter()
                .enumerate()
                .map(|(r, &v)| {
                    let at = self.geom.coords(v as usize);
                    let mut n = Neighbours::NONE;
                    for axis in 0..3 {
                        let next = (at[axis] + 1 < res[axis])
                            .then(|| self.index.slot(v as usize + strides[axis]))
                            .flatten();
                        if let Some(next) = next {
                            n.row[axis] = next as u32;
                            n.distance[axis] = self.unit_distance(r, next);
                        }
                    }
                    n
                })
                .collect()
        })
    }

    /// ‖φ̂_a − φ̂_b‖² between two rows' unit features, in eight partial
    /// sums: a plain sum is a serial chain of float adds the compiler may
    /// not reorder.
    fn unit_distance(&self, a: usize, b: usize) -> f32 {
        let (ia, ib) = (self.inv_norm[a], self.inv_norm[b]);
        let (ra, rb) = (self.row(a), self.row(b));
        let (ca, cb) = (ra.chunks_exact(8), rb.chunks_exact(8));
        let tail: f32 = ca
            .remainder()
            .iter()
            .zip(cb.remainder())
            .map(|(x, y)| (x * ia - y * ib) * (x * ia - y * ib))
            .sum();
        let mut acc = [0.0f32; 8];
        for (x, y) in ca.zip(cb) {
            for l in 0..8 {
                let d = x[l] * ia - y[l] * ib;
                acc[l] += d * d;
            }
        }
        acc.iter().sum::<f32>() + tail
    }

    /// The copy of this cache on a grid two or three times as coarse
    /// ([`super::coarse`]; its [`factor`](Self::factor) says which), made
    /// on first use and kept; `None` when the grid is too small to coarsen.
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
        self.feats.len() * 4
            + self.voxels.len() * 24
            + self.index.bits().words().len() * 12
            + self
                .neighbours
                .get()
                .map_or(0, |n| n.len() * std::mem::size_of::<Neighbours>())
            + self
                .solid
                .lock()
                .map_or(0, |m| m.as_ref().map_or(0, |(_, b)| b.words().len() * 8))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{Aabb, FieldBuilder};
    use glam::Vec3;

    #[test]
    fn neighbours_are_the_next_cached_rows_with_their_feature_distances() {
        // Empty at x = 2 and at the top layer's corner; features that turn
        // with position (and a zero feature at one voxel).
        let field = FieldBuilder::new(Aabb::new(Vec3::ZERO, Vec3::new(5.0, 3.0, 2.0)), [6, 4, 3]).build(
            |p| {
                if p.x == 2.0 || (p.z == 2.0 && p.y == 3.0) {
                    0.0
                } else {
                    40.0
                }
            },
            |_| Vec3::ONE,
            Some((3, &|p: Vec3, out: &mut [f32]| {
                if p == Vec3::new(4.0, 1.0, 1.0) {
                    out.fill(0.0);
                } else {
                    out.copy_from_slice(&[1.0 + p.x, p.y * p.z, 2.0 - p.y]);
                }
            })),
        );
        let cache = FeatureCache::build(&field).unwrap();
        let unit = |r: usize| -> Vec<f32> { cache.row(r).iter().map(|x| x * cache.inv_norm[r]).collect() };
        let n = cache.neighbours();
        assert_eq!(n.len(), cache.len());
        let res = cache.geom.res;
        let mut pairs = 0;
        for (r, &v) in cache.voxels.iter().enumerate() {
            let at = cache.geom.coords(v as usize);
            for axis in 0..3 {
                let mut next = at;
                next[axis] += 1;
                let slot = (next[axis] < res[axis])
                    .then(|| cache.index.slot(cache.geom.index(next[0], next[1], next[2])))
                    .flatten();
                match slot {
                    Some(s) => {
                        pairs += 1;
                        assert_eq!(n[r].row[axis], s as u32);
                        let want: f32 = unit(r).iter().zip(unit(s)).map(|(a, b)| (a - b) * (a - b)).sum();
                        assert!((n[r].distance[axis] - want).abs() < 1e-6, "{r} {axis}");
                        assert_eq!(n[r].distance[axis].to_bits(), cache.unit_distance(r, s).to_bits());
                    }
                    None => assert!(n[r].row[axis] == u32::MAX && n[r].distance[axis].is_nan()),
                }
            }
        }
        // Some pairs exist and some are missing (the empty plane).
        assert!(pairs > 0 && pairs < 3 * cache.len());
        assert!(cache.memory_bytes() >= cache.len() * std::mem::size_of::<Neighbours>());
    }

    #[test]
    fn the_solid_bitmap_follows_the_floor_asked_for() {
        // σ rises along x: each floor leaves a different share solid.
        let field = FieldBuilder::new(Aabb::new(Vec3::ZERO, Vec3::new(7.0, 2.0, 2.0)), [8, 3, 3]).build(
            |p| p.x,
            |_| Vec3::ONE,
            Some((2, &|_: Vec3, out: &mut [f32]| out.fill(1.0))),
        );
        let cache = FeatureCache::build(&field).unwrap();
        let want = |floor: f32| {
            Bitmap::from_fn(cache.geom.res, |v| {
                cache.index.slot(v).is_some_and(|r| cache.sigma[r] > floor)
            })
        };
        let mut sigmas = cache.sigma.clone();
        sigmas.sort_by(f32::total_cmp);
        let at = |q: usize| sigmas[q * (sigmas.len() - 1) / 4];
        for floor in [at(2), at(1), at(2), at(3), at(3)] {
            let got = cache.solid(floor);
            assert_eq!(*got, want(floor), "floor {floor}");
            assert!(got.any() && got.count() < cache.len());
        }
    }
}
