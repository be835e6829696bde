//! The radiance field: a dense density grid, an appearance model and optional
//! semantic features over one world-space box, plus trilinear sampling and a
//! cache of per-voxel features for occupied voxels.

pub mod bake;
pub mod bitmap;
pub mod cache;
pub mod coarse;
pub mod geom;
pub mod grid;
pub mod io;
pub mod macro_grid;
pub mod runs;
pub mod sh;
pub mod sparse;
pub mod tensor_file;
pub mod vm;

pub use bitmap::{Bitmap, RankIndex};
pub use cache::FeatureCache;
pub use geom::{Aabb, GridGeom};
pub use grid::{Activation, ChannelGrid, DensityGrid, Layout};
pub use macro_grid::MacroGrid;
pub use vm::{Linear, Mlp, VmGrid};

use glam::Vec3;
use std::sync::{Arc, OnceLock};

/// How colour is stored.
#[derive(Clone, Debug)]
pub enum Appearance {
    /// 3 channels, colour = clamp(value, 0, 1), view independent.
    Rgb(ChannelGrid),
    /// 27 channels of degree-2 spherical harmonics, `[r0..r8, g0..g8, b0..b8]`.
    Sh2(ChannelGrid),
    /// TensoRF VM components → basis → MLP with the view direction.
    Vm { grid: VmGrid, mlp: Mlp },
}

/// Semantic (distilled) features; view independent.
#[derive(Clone, Debug)]
pub enum Features {
    Grid(ChannelGrid),
    Vm(VmGrid),
}

impl Features {
    pub fn channels(&self) -> usize {
        match self {
            Features::Grid(g) => g.channels,
            Features::Vm(v) => v.out,
        }
    }
}

/// The file a field was imported from (a 3D Gaussian splat `.ply`), so
/// that exports can go back to its records.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Source {
    pub path: std::path::PathBuf,
    pub crc32: u32,
    /// Gaussians in the file.
    pub count: usize,
}

#[derive(Debug)]
pub struct Field {
    pub density: DensityGrid,
    pub appearance: Appearance,
    pub features: Option<Features>,
    /// Rank index over the density grid points the field stores ([`sparse`]):
    /// sparse appearance grids use it, and so do sparse feature grids at the
    /// density resolution (a sparse feature grid at its own resolution has
    /// its own index). The file stores the density for these points only
    /// when every other point holds one value.
    pub occupancy: Option<Arc<RankIndex>>,
    /// Where an imported field came from (kept in the file's header).
    pub source: Option<Source>,
    /// The NDC space of the forward-facing capture (LLFF) the field was
    /// trained in: its coordinates are NDC, not the world, and views see it
    /// through this mapping (kept in the file's header).
    pub ndc: Option<crate::camera::Ndc>,
    /// The scene's up direction in the field's space (unit), where it is
    /// known: from the cameras of the capture it was trained on
    /// ([`crate::camera::up_of`]). Segmentation uses it to tell the ground
    /// an object stands on from the object (kept in the file's header).
    pub up: Option<glam::Vec3>,
    cache: OnceLock<Arc<FeatureCache>>,
    macro_grid: OnceLock<MacroGrid>,
    /// This field with VM appearance baked into SH (GPU view), on first use.
    baked: OnceLock<Arc<Field>>,
}

impl Clone for Field {
    fn clone(&self) -> Self {
        Field {
            density: self.density.clone(),
            appearance: self.appearance.clone(),
            features: self.features.clone(),
            occupancy: self.occupancy.clone(),
            source: self.source.clone(),
            ndc: self.ndc,
            up: self.up,
            cache: OnceLock::new(),
            macro_grid: OnceLock::new(),
            baked: OnceLock::new(),
        }
    }
}

impl Field {
    pub fn new(
        density: DensityGrid,
        appearance: Appearance,
        features: Option<Features>,
        occupancy: Option<Arc<RankIndex>>,
    ) -> Self {
        Field {
            density,
            appearance,
            features,
            occupancy,
            source: None,
            ndc: None,
            up: None,
            cache: OnceLock::new(),
            macro_grid: OnceLock::new(),
            baked: OnceLock::new(),
        }
    }
    /// This field in the same space as `other` (its NDC and up direction,
    /// if any): for fields derived from another (cropped, sparsified,
    /// baked, lifted).
    pub fn in_space_of(mut self, other: &Field) -> Field {
        self.ndc = other.ndc;
        self.up = other.up;
        self
    }
    /// This field, told which way is up by the cameras of its capture
    /// (`<name>.cameras.json`) when its file does not say: fields written
    /// before files kept it.
    pub fn or_up_from(mut self, cameras: Option<&crate::camera::CameraSet>) -> Field {
        if self.up.is_none() {
            self.up = cameras.and_then(|c| c.up());
        }
        self
    }
    pub fn bounds(&self) -> Aabb {
        self.density.geom.bounds
    }
    pub fn geom(&self) -> GridGeom {
        self.density.geom
    }
    pub fn res(&self) -> [usize; 3] {
        self.density.geom.res
    }
    pub fn feature_channels(&self) -> usize {
        self.features.as_ref().map_or(0, Features::channels)
    }
    /// Activated density at a world point (field-local coordinates).
    #[inline]
    pub fn sigma(&self, p: Vec3) -> f32 {
        self.density.sigma(p)
    }
    /// A sampler with scratch buffers, one per thread, so that sampling colour
    /// and features never allocates.
    pub fn sampler(&self) -> Sampler<'_> {
        let comps = match (&self.appearance, &self.features) {
            (Appearance::Vm { grid, .. }, Some(Features::Vm(f))) => grid.total_comps().max(f.total_comps()),
            (Appearance::Vm { grid, .. }, _) => grid.total_comps(),
            (_, Some(Features::Vm(f))) => f.total_comps(),
            _ => 0,
        };
        let chan = match &self.appearance {
            Appearance::Rgb(_) => 3,
            Appearance::Sh2(_) => 27,
            Appearance::Vm { grid, .. } => grid.out,
        };
        Sampler {
            field: self,
            comps: vec![0.0; comps],
            chan: vec![0.0; chan],
            mlp: Vec::with_capacity(1024),
        }
    }
    /// Per-voxel features of occupied voxels (σ > [`cache::OCCUPIED_FLOOR`]),
    /// computed on first use and then shared.
    pub fn feature_cache(&self) -> crate::error::Result<Arc<FeatureCache>> {
        if let Some(c) = self.cache.get() {
            return Ok(c.clone());
        }
        let c = Arc::new(FeatureCache::build(self)?);
        Ok(self.cache.get_or_init(|| c).clone())
    }
    /// The per-voxel feature cache if [`Field::feature_cache`] has built
    /// it (never builds it).
    pub fn cached_features(&self) -> Option<Arc<FeatureCache>> {
        self.cache.get().cloned()
    }
    /// The field as the GPU view draws it: VM + MLP appearance baked into
    /// SH ([`bake::vm_to_sh`]), computed once and shared; `None` for other
    /// appearances (drawn as they are). The editor computes it off the
    /// frame loop after loading.
    pub fn sh_baked(&self) -> crate::error::Result<Option<Arc<Field>>> {
        if !matches!(self.appearance, Appearance::Vm { .. }) {
            return Ok(None);
        }
        if let Some(b) = self.baked.get() {
            return Ok(Some(b.clone()));
        }
        let b = Arc::new(bake::vm_to_sh(self)?);
        Ok(Some(self.baked.get_or_init(|| b).clone()))
    }
    /// Coarse max-density grid for empty-space skipping, built on first use.
    pub fn macro_grid(&self) -> &MacroGrid {
        self.macro_grid.get_or_init(|| MacroGrid::build(&self.density))
    }
    /// Approximate memory held by the grids, in bytes.
    pub fn memory_bytes(&self) -> usize {
        let ch = |g: &ChannelGrid| g.data.len() * 2;
        let vm = |v: &VmGrid| {
            4 * (v.planes.iter().map(Vec::len).sum::<usize>()
                + v.lines.iter().map(Vec::len).sum::<usize>()
                + v.basis.len())
        };
        let mut n = self.density.raw.len() * 4;
        n += match &self.appearance {
            Appearance::Rgb(g) | Appearance::Sh2(g) => ch(g),
            Appearance::Vm { grid, mlp } => {
                vm(grid)
                    + mlp
                        .layers
                        .iter()
                        .map(|l| 4 * (l.weight.len() + l.bias.len()))
                        .sum::<usize>()
            }
        };
        n += match &self.features {
            Some(Features::Grid(g)) => ch(g),
            Some(Features::Vm(v)) => vm(v),
            None => 0,
        };
        n + self.occupancy.as_ref().map_or(0, |o| o.bits().words().len() * 12)
    }
}

pub struct Sampler<'a> {
    pub field: &'a Field,
    comps: Vec<f32>,
    chan: Vec<f32>,
    mlp: Vec<f32>,
}

impl Sampler<'_> {
    /// Colour in [0, 1]³ at `p` seen along unit direction `dir` (field-local).
    pub fn color(&mut self, p: Vec3, dir: Vec3) -> Vec3 {
        match &self.field.appearance {
            Appearance::Rgb(g) => {
                g.sample(p, &mut self.chan[..3]);
                Vec3::new(self.chan[0], self.chan[1], self.chan[2]).clamp(Vec3::ZERO, Vec3::ONE)
            }
            Appearance::Sh2(g) => {
                g.sample(p, &mut self.chan[..27]);
                sh::color(&self.chan, dir)
            }
            Appearance::Vm { grid, mlp } => {
                grid.sample(p, &mut self.comps, &mut self.chan);
                mlp.eval(&self.chan, dir, &mut self.mlp)
            }
        }
    }
    /// Colour at `p` averaged over the six axis directions: about the
    /// view-independent colour (for SH up to degree 2 the degree-1 and
    /// degree-2 terms cancel over ±x, ±y, ±z before the activation).
    pub fn diffuse_color(&mut self, p: Vec3) -> Vec3 {
        const DIRS: [Vec3; 6] = [Vec3::X, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_Z];
        match &self.field.appearance {
            Appearance::Sh2(g) => {
                g.sample(p, &mut self.chan[..27]);
                DIRS.iter().map(|&d| sh::color(&self.chan, d)).sum::<Vec3>() / 6.0
            }
            _ => DIRS.iter().map(|&d| self.color(p, d)).sum::<Vec3>() / 6.0,
        }
    }
    /// Semantic features at `p` into `out` (len = feature channels); zeros if
    /// the field has none or `p` is outside.
    pub fn features(&mut self, p: Vec3, out: &mut [f32]) {
        match &self.field.features {
            Some(Features::Grid(g)) => {
                g.sample(p, out);
            }
            Some(Features::Vm(v)) => {
                v.sample(p, &mut self.comps, out);
            }
            None => out.fill(0.0),
        }
    }
}

/// Builds dense fields from functions of world position: handy for tests,
/// imports and synthetic data. Raw density, colour and (optionally) features
/// are evaluated at every grid point in parallel.
pub struct FieldBuilder {
    pub geom: GridGeom,
    pub activation: Activation,
}

impl FieldBuilder {
    pub fn new(bounds: Aabb, res: [usize; 3]) -> Self {
        FieldBuilder {
            geom: GridGeom::new(bounds, res),
            activation: Activation::Relu,
        }
    }
    pub fn build(
        &self,
        raw_density: impl Fn(Vec3) -> f32 + Sync,
        color: impl Fn(Vec3) -> Vec3 + Sync,
        features: Option<(usize, &(dyn Fn(Vec3, &mut [f32]) + Sync))>,
    ) -> Field {
        use half::f16;
        use rayon::prelude::*;
        let g = self.geom;
        let raw: Vec<f32> = (0..g.len())
            .into_par_iter()
            .map(|i| raw_density(g.point_of(i)))
            .collect();
        let rgb: Vec<f16> = (0..g.len())
            .into_par_iter()
            .flat_map_iter(|i| color(g.point_of(i)).to_array().map(f16::from_f32))
            .collect();
        let feats = features.map(|(c, f)| {
            let mut data = vec![f16::ZERO; g.len() * c];
            data.par_chunks_mut(c).enumerate().for_each(|(i, row)| {
                let mut tmp = vec![0.0; c];
                f(g.point_of(i), &mut tmp);
                for (o, v) in row.iter_mut().zip(tmp) {
                    *o = f16::from_f32(v);
                }
            });
            Features::Grid(ChannelGrid::dense(g, c, data))
        });
        Field::new(
            DensityGrid {
                geom: g,
                raw,
                activation: self.activation,
            },
            Appearance::Rgb(ChannelGrid::dense(g, 3, rgb)),
            feats,
            None,
        )
    }
}
