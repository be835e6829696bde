//! A splat file to a field: density from the Gaussians' opacity mass, SH2
//! colour from their SH, over robust bounds on a grid as fine as the splats.
//!
//! **Opacity to density.** A Gaussian with opacity α (after its sigmoid)
//! and scales s₁ ≤ s₂ ≤ s₃ becomes the density σ(x) = k·G(x), G its
//! unnormalised Gaussian, with k = τ / (s₁·√(2π)) and τ = −ln(1 − α): a
//! ray through its centre along its thinnest axis (the surface normal of
//! the flat splats captures are made of) then sees optical depth τ, i.e.
//! opacity 1 − e^(−τ) = α, what the splat renderer draws at its centre.
//! (α is capped at 0.995.) Its mass ∫σ = τ·2π·s₂·s₃ (optical depth × disk
//! area) is spread over the grid points near it with weights of the same
//! Gaussian widened by half a voxel per axis (so splats thinner than a voxel
//! still land on grid points), normalised to keep the mass; each grid point
//! gets mass / voxel volume. Density uses [`Activation::Relu`].
//!
//! **Colour.** Each grid point's SH2 is the mass-weighted mean of its
//! Gaussians' SH converted by [`super::sh::to_field_sh2`] (degree 3 dropped).
//!
//! **Bounds.** Per axis, from the 1 % and 99 % quantiles of the centres
//! outwards until the first gap between consecutive centres larger than 5 %
//! of that span (or ten typical splat sizes), padded by three typical
//! splat sizes: far floaters fall outside and are left out of the field
//! (they stay in the file and in every complement export).
//!
//! **Resolution.** Grid spacing = the median largest splat scale, then
//! coarsened until the longest axis has at most [`MAX_LONGEST`] points and
//! the grid at most [`ImportOptions::max_points`]; `res` overrides the
//! longest axis. Grids are deposited slab by slab in parallel (see
//! [`slab_phases`]).

use super::boundary::{assign, Placed};
use super::ply::SplatFile;
use crate::error::{Error, Result};
use crate::field::bitmap::{Bitmap, RankIndex};
use crate::field::grid::{Activation, ChannelGrid, DensityGrid};
use crate::field::{sparse, Aabb, Appearance, Field, GridGeom, Source};
use glam::{Mat3, Vec3};
use half::f16;
use rayon::prelude::*;
use std::path::Path;

/// Longest grid axis chosen automatically.
pub const MAX_LONGEST: usize = 512;
/// Default cap on grid points (2^25: a 128 MB density grid).
pub const DEFAULT_MAX_POINTS: usize = 1 << 25;
/// Footprints that reach at most this many grid points from the centre
/// per axis are deposited slab by slab in parallel; larger ones after
/// them, batch by batch.
const REACH: usize = 6;
/// No footprint reaches further (larger splats are truncated to it, their
/// mass kept: far background splats, seldom).
const MAX_REACH: usize = 32;
/// Planes per slab of the parallel deposit (≥ [`REACH`]).
const SLAB: usize = REACH + 2;
const MAX_ALPHA: f32 = 0.995;
/// Largest Mahalanobis² of a footprint point (weight e^(−q/2) ≥ 1e-3).
const MAX_Q: f32 = 13.815_51;
/// Channels of the colour accumulator: 27 SH2 values and the weight.
const ACC: usize = 28;

#[derive(Clone, Debug)]
pub struct ImportOptions {
    /// Grid points along the longest axis; `None`: from the splat sizes.
    pub res: Option<usize>,
    pub max_points: usize,
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            res: None,
            max_points: DEFAULT_MAX_POINTS,
        }
    }
}

/// What an import did.
#[derive(Clone, Debug)]
pub struct ImportReport {
    pub gaussians: usize,
    /// Gaussians deposited into the field.
    pub used: usize,
    pub non_finite: usize,
    /// Centres outside the robust bounds (floaters).
    pub outside: usize,
    pub bounds: Aabb,
    pub res: [usize; 3],
    pub occupied: usize,
    pub sh_degree: usize,
}

/// One Gaussian ready to deposit.
struct Prep {
    index: u32,
    /// Continuous grid coordinates of the centre.
    centre: Vec3,
    /// Inverse of the widened covariance, in grid units.
    inv: Mat3,
    /// Half extent of the footprint box, grid units.
    half: Vec3,
    mass: f32,
}

/// Reads `path` and imports it; the field remembers the file (path, CRC-32).
pub fn import_file(path: &Path, opts: &ImportOptions) -> Result<(Field, ImportReport)> {
    import_read(path, &SplatFile::read(path)?, opts)
}

/// [`import_file`] of `file`, already read from `path`.
pub fn import_read(path: &Path, file: &SplatFile, opts: &ImportOptions) -> Result<(Field, ImportReport)> {
    let (mut field, report) = build_field(file, opts).map_err(|e| Error::bad_file(path, e.to_string()))?;
    let abs = std::fs::canonicalize(path).map_err(|e| Error::io(path, e))?;
    field.source = Some(Source {
        path: abs,
        crc32: file.crc32(),
        count: file.len(),
    });
    Ok((field, report))
}

/// Builds the field of a splat file (module docs).
pub fn build_field(file: &SplatFile, opts: &ImportOptions) -> Result<(Field, ImportReport)> {
    let n = file.len();
    let finite: Vec<u32> = (0..n as u32)
        .into_par_iter()
        .filter(|&i| file.is_finite(i as usize))
        .collect();
    crate::ensure!(!finite.is_empty(), "the file holds no Gaussian with finite values");
    let sizes: Vec<f32> = finite
        .par_iter()
        .map(|&i| {
            file.gaussian(i as usize)
                .log_scale
                .iter()
                .fold(f32::MIN, |a, &b| a.max(b))
                .exp()
        })
        .collect();
    let typical = median(sizes);
    let bounds = robust_bounds(file, &finite, typical);
    crate::ensure!(
        bounds.is_valid() && bounds.size().max_element() < 1e30,
        "the Gaussians' centres span no usable box ({:?} .. {:?})",
        bounds.min,
        bounds.max
    );
    let geom = GridGeom::new(bounds, resolution(bounds, typical, opts)?);
    let preps = prepare(file, &finite, &geom);
    let density = deposit_density(&preps, &geom);
    let occ = sparse::density_occupancy(&density);
    let density = sparse::emptied_density(&density, &occ);
    let index = std::sync::Arc::new(RankIndex::new(occ));
    let sh = deposit_colour(file, &preps, &geom, &index);
    let report = ImportReport {
        gaussians: n,
        used: preps.len(),
        non_finite: n - finite.len(),
        outside: finite.len() - preps.len(),
        bounds,
        res: geom.res,
        occupied: index.count(),
        sh_degree: file.header.layout.degree(),
    };
    let app = Appearance::Sh2(ChannelGrid::sparse(geom, 27, index.clone(), sh));
    Ok((Field::new(density, app, None, Some(index)), report))
}

fn median(mut v: Vec<f32>) -> f32 {
    let mid = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(mid, f32::total_cmp);
    *m
}

/// The range of one coordinate without its far floaters: from the 1 % and
/// 99 % quantiles outwards as long as consecutive values are closer than
/// 5 % of the span between them (or ten typical splat sizes); the first
/// larger gap ends the scene.
fn axis_range(mut v: Vec<f32>, typical: f32) -> (f32, f32) {
    v.par_sort_unstable_by(f32::total_cmp);
    let n = v.len();
    let at = |q: f64| ((n - 1) as f64 * q).round() as usize;
    let (mut lo, mut hi) = (at(0.01), at(0.99));
    let gap = (0.05 * (v[hi] - v[lo])).max(10.0 * typical);
    while lo > 0 && v[lo] - v[lo - 1] <= gap {
        lo -= 1;
    }
    while hi + 1 < n && v[hi + 1] - v[hi] <= gap {
        hi += 1;
    }
    (v[lo], v[hi])
}

/// Bounds of the centres robust to far floaters (module docs).
fn robust_bounds(file: &SplatFile, finite: &[u32], typical: f32) -> Aabb {
    let mut lo = Vec3::ZERO;
    let mut hi = Vec3::ZERO;
    for a in 0..3 {
        let v: Vec<f32> = finite.par_iter().map(|&i| file.position(i as usize)[a]).collect();
        (lo[a], hi[a]) = axis_range(v, typical);
    }
    let pad = (3.0 * typical).max(1e-3 * (hi - lo).max_element()).max(1e-6);
    Aabb::new(lo - pad, hi + pad)
}

/// Grid points per axis (module docs).
fn resolution(b: Aabb, typical: f32, opts: &ImportOptions) -> Result<[usize; 3]> {
    let size = b.size();
    let longest = match opts.res {
        Some(r) => {
            crate::ensure_within!(
                OutOfRange,
                (8..=2048).contains(&r),
                "--res {r} is out of range (8..=2048)"
            );
            r
        }
        None => ((size.max_element() / typical.max(1e-9)).ceil() as usize + 1).clamp(16, MAX_LONGEST),
    };
    let mut longest = longest as f32;
    loop {
        let h = size.max_element() / (longest - 1.0);
        let res = size.to_array().map(|s| ((s / h).round() as usize + 1).max(8));
        let points = res.iter().product::<usize>();
        if points <= opts.max_points || longest <= 16.0 || opts.res.is_some() {
            crate::field::geom::check_res(res, "imported grid")?;
            return Ok(res);
        }
        longest *= 0.95;
    }
}

/// The deposit parameters of every finite Gaussian whose centre is inside.
fn prepare(file: &SplatFile, finite: &[u32], geom: &GridGeom) -> Vec<Prep> {
    let spacing = geom.spacing();
    let to_grid = Mat3::from_diagonal(spacing.recip());
    finite
        .par_iter()
        .filter_map(|&i| {
            let g = file.gaussian(i as usize);
            if !geom.bounds.contains(g.pos) {
                return None;
            }
            let s = g.scales().max(Vec3::splat(1e-9));
            let mut sorted = s.to_array();
            sorted.sort_by(f32::total_cmp);
            let tau = -(1.0 - g.alpha().min(MAX_ALPHA)).ln();
            let mass = tau * std::f32::consts::TAU * sorted[1] * sorted[2];
            let r = Mat3::from_quat(g.rotation());
            // Covariance in grid units, widened by half a voxel per axis.
            let m = to_grid * r * Mat3::from_diagonal(s);
            let cov = m * m.transpose() + Mat3::from_diagonal(Vec3::splat(0.25));
            // Huge scales (exp of a large log) leave nothing usable.
            if !(mass.is_finite() && cov.is_finite()) {
                return None;
            }
            let diag = Vec3::new(cov.x_axis.x, cov.y_axis.y, cov.z_axis.z);
            let half = (3.0 * diag.max(Vec3::ZERO).powf(0.5)).min(Vec3::splat(MAX_REACH as f32));
            Some(Prep {
                index: i,
                centre: geom.to_grid(g.pos),
                inv: cov.inverse(),
                half,
                mass,
            })
        })
        .collect()
}

/// The grid points of a Gaussian's footprint and their normalised weights.
fn footprint(p: &Prep, res: [usize; 3], out: &mut Vec<(usize, f32)>) {
    out.clear();
    let lo = (p.centre - p.half).ceil().max(Vec3::ZERO);
    let hi = (p.centre + p.half).floor();
    let hi = [
        hi.x.min(res[0] as f32 - 1.0),
        hi.y.min(res[1] as f32 - 1.0),
        hi.z.min(res[2] as f32 - 1.0),
    ];
    let mut sum = 0.0;
    for z in lo.z as usize..=hi[2].max(-1.0) as usize {
        for y in lo.y as usize..=hi[1].max(-1.0) as usize {
            for x in lo.x as usize..=hi[0].max(-1.0) as usize {
                let d = Vec3::new(x as f32, y as f32, z as f32) - p.centre;
                let q = d.dot(p.inv * d);
                // Weights below 1e-3 (q > 2 ln 1000) are dropped before the exp.
                if q < MAX_Q {
                    let w = (-0.5 * q).exp();
                    sum += w;
                    out.push((x + res[0] * (y + res[1] * z), w));
                }
            }
        }
    }
    if hi.iter().any(|&h| h < 0.0) || sum <= 0.0 {
        out.clear();
        return;
    }
    out.iter_mut().for_each(|(_, w)| *w /= sum);
}

impl Prep {
    fn is_big(&self) -> bool {
        self.half.max_element() > REACH as f32
    }
}

/// Deposits every Gaussian's footprint: `write(what, voxel, weight,
/// window, window start)` adds to `data`, where plane z starts at
/// `plane_off[z]` and `what = per_gaussian(prep)`.
/// Small footprints go slab by slab in parallel ([`slab_phases`]); big ones
/// are computed in parallel batches and written one after the other.
fn deposit<T: Send, C: Send>(
    preps: &[Prep],
    geom: &GridGeom,
    data: &mut [T],
    plane_off: &[usize],
    per_gaussian: impl Fn(&Prep) -> C + Sync,
    write: impl Fn(&C, usize, f32, &mut [T], usize) + Sync,
) {
    let slabs = by_slab(preps, geom.res[2]);
    slab_phases(data, plane_off, |b, lo, w| {
        let mut fp = Vec::with_capacity(512);
        for &k in &slabs[b] {
            footprint(&preps[k], geom.res, &mut fp);
            let what = per_gaussian(&preps[k]);
            for &(v, wt) in &fp {
                write(&what, v, wt, w, plane_off[lo]);
            }
        }
    });
    let big: Vec<&Prep> = preps.iter().filter(|p| p.is_big()).collect();
    for batch in big.chunks(1024) {
        let fps: Vec<(C, Vec<(usize, f32)>)> = batch
            .par_iter()
            .map(|p| {
                let mut fp = vec![];
                footprint(p, geom.res, &mut fp);
                (per_gaussian(p), fp)
            })
            .collect();
        for (what, fp) in fps {
            for (v, wt) in fp {
                write(&what, v, wt, data, 0);
            }
        }
    }
}

/// Gaussians grouped by slab (of [`SLAB`] z planes) of their centre.
fn by_slab(preps: &[Prep], nz: usize) -> Vec<Vec<usize>> {
    let mut slabs = vec![vec![]; nz.div_ceil(SLAB)];
    for (k, p) in preps.iter().enumerate().filter(|(_, p)| !p.is_big()) {
        let z = (p.centre.z.round().max(0.0) as usize).min(nz - 1);
        slabs[z / SLAB].push(k);
    }
    slabs
}

/// Runs `f(slab, first plane, window)` for every slab, in parallel, where
/// the window is `data` from plane `(slab − 1)·SLAB` to `(slab + 2)·SLAB`
/// (`plane_off[z]`: where plane z starts in `data`). A footprint reaches
/// at most [`REACH`] ≤ SLAB planes from its slab, so it stays inside the
/// window; slabs three apart have disjoint windows, so three phases cover
/// every slab with no two threads writing the same element.
fn slab_phases<T: Send>(data: &mut [T], plane_off: &[usize], f: impl Fn(usize, usize, &mut [T]) + Sync) {
    let nz = plane_off.len() - 1;
    let slabs = nz.div_ceil(SLAB);
    for phase in 0..3 {
        let mut windows = vec![];
        let mut rest: &mut [T] = &mut *data;
        let mut cut = 0;
        for b in (phase..slabs).step_by(3) {
            let lo = (b * SLAB).saturating_sub(SLAB);
            let hi = ((b + 2) * SLAB).min(nz);
            let (a, z) = (plane_off[lo], plane_off[hi]);
            let (_, tail) = std::mem::take(&mut rest).split_at_mut(a - cut);
            let (w, tail) = tail.split_at_mut(z - a);
            rest = tail;
            cut = z;
            windows.push((b, lo, w));
        }
        windows.into_par_iter().for_each(|(b, lo, w)| f(b, lo, w));
    }
}

fn deposit_density(preps: &[Prep], geom: &GridGeom) -> DensityGrid {
    let [nx, ny, nz] = geom.res;
    let inv_volume = 1.0 / geom.spacing().to_array().iter().product::<f32>();
    let mut raw = vec![0f32; geom.len()];
    let plane_off: Vec<usize> = (0..=nz).map(|z| z * nx * ny).collect();
    deposit(
        preps,
        geom,
        &mut raw,
        &plane_off,
        |p| p.mass * inv_volume,
        |m, v, wt, w, base| {
            w[v - base] += m * wt;
        },
    );
    DensityGrid {
        geom: *geom,
        raw,
        activation: Activation::Relu,
    }
}

/// Mass-weighted SH2 of every stored grid point (f16, slot order).
fn deposit_colour(file: &SplatFile, preps: &[Prep], geom: &GridGeom, index: &RankIndex) -> Vec<f16> {
    let [nx, ny, nz] = geom.res;
    let plane_off: Vec<usize> = plane_ranks(index, nx * ny, nz).iter().map(|r| r * ACC).collect();
    let mut acc = vec![0f32; index.count() * ACC];
    let colour = |p: &Prep| {
        let g = file.gaussian(p.index as usize);
        let mut sh = [0f32; ACC];
        super::sh::to_field_sh2(g.dc, &g.rest[..g.rest.len().min(24)], &mut sh[..27]);
        sh.iter_mut().for_each(|v| *v *= p.mass);
        sh[27] = p.mass;
        sh
    };
    deposit(preps, geom, &mut acc, &plane_off, colour, |sh, v, wt, w, base| {
        let Some(s) = index.slot(v) else { return };
        let row = &mut w[s * ACC - base..(s + 1) * ACC - base];
        for (r, c) in row.iter_mut().zip(sh) {
            *r += wt * c;
        }
    });
    finish_colour(&acc, index, geom)
}

/// Number of set bits before each plane start (plane `z` starts at voxel
/// `z · plane`), and before the end.
fn plane_ranks(index: &RankIndex, plane: usize, nz: usize) -> Vec<usize> {
    let words = index.bits().words();
    let mut prefix = Vec::with_capacity(words.len() + 1);
    let mut acc = 0usize;
    prefix.push(0);
    for w in words {
        acc += w.count_ones() as usize;
        prefix.push(acc);
    }
    (0..=nz)
        .map(|z| {
            let v = z * plane;
            let (w, b) = (v >> 6, v & 63);
            let partial = if b == 0 {
                0
            } else {
                (words[w] & ((1u64 << b) - 1)).count_ones() as usize
            };
            prefix[w] + partial
        })
        .collect()
}

/// Normalised colours; stored points no Gaussian coloured (the one-voxel
/// ring of the occupancy) take the mean of their coloured neighbours.
fn finish_colour(acc: &[f32], index: &RankIndex, geom: &GridGeom) -> Vec<f16> {
    let voxels: Vec<usize> = index.bits().ones().collect();
    let mut out = vec![f16::ZERO; voxels.len() * 27];
    out.par_chunks_mut(27)
        .zip(voxels.par_iter())
        .enumerate()
        .for_each(|(s, (row, &v))| {
            let add = |sum: &mut [f32; ACC], slot: usize| {
                let a = &acc[slot * ACC..(slot + 1) * ACC];
                sum.iter_mut().zip(a).for_each(|(s, a)| *s += a);
            };
            let mut sum = [0f32; ACC];
            add(&mut sum, s);
            if sum[27] <= 0.0 {
                geom.neighbours26(v, |n| {
                    if let Some(t) = index.slot(n) {
                        add(&mut sum, t);
                    }
                });
            }
            let inv = if sum[27] > 0.0 { 1.0 / sum[27] } else { 0.0 };
            for (o, a) in row.iter_mut().zip(&sum[..27]) {
                *o = f16::from_f32(a * inv);
            }
        });
    out
}

/// Which of the file's Gaussians a bitmap over the field's grid holds: a
/// Gaussian wholly on the bitmap's grid points (its mass spread over the
/// grid as the import spreads it) belongs to the object, one wholly off it
/// does not, and one straddling the bitmap's edge goes to the side whose
/// nearby Gaussians it looks like, or where most of its mass is when
/// colour does not tell ([`super::boundary`]). Each Gaussian goes wholly to
/// one side, so an object and its complement split the file exactly.
/// Gaussians the field left out (floaters outside the bounds, non-finite
/// values) belong to no object.
pub fn inside(file: &SplatFile, geom: &GridGeom, bits: &Bitmap) -> Vec<bool> {
    let all: Vec<u32> = (0..file.len() as u32).collect();
    let preps = prepare(file, &all, geom);
    let res = geom.res;
    let placed: Vec<Placed> = preps
        .par_iter()
        .map_init(Vec::new, |fp, p| {
            footprint(p, res, fp);
            let on: f32 = fp.iter().filter(|(v, _)| bits.get(*v)).map(|(_, w)| w).sum();
            let g = p.centre.round().clamp(
                Vec3::ZERO,
                Vec3::new(res[0] as f32 - 1.0, res[1] as f32 - 1.0, res[2] as f32 - 1.0),
            );
            Placed {
                index: p.index,
                cell: geom.index(g.x as usize, g.y as usize, g.z as usize) as u32,
                on,
            }
        })
        .collect();
    assign(file, geom, &placed)
}

#[cfg(test)]
mod tests {
    use super::super::ply::{standard_bytes, Gaussian};
    use super::*;
    use crate::render::{render, RenderOptions, Scene};
    use glam::Quat;
    use std::sync::Arc;

    fn disk(pos: Vec3, alpha: f32, rot: Quat) -> Gaussian {
        Gaussian {
            pos,
            dc: [0.8, -0.5, 0.0],
            rest: vec![0.0; 9],
            opacity: (alpha / (1.0 - alpha)).ln(),
            log_scale: [0.15f32.ln(), 0.15f32.ln(), 0.01f32.ln()],
            rot: [rot.w, rot.x, rot.y, rot.z],
        }
    }

    /// Opacity along the ray through the field's centre looking down −z'
    /// where z' is `axis`.
    fn centre_opacity(field: Field, axis: Vec3) -> f32 {
        use crate::camera::{Camera, Intrinsics};
        let c = field.bounds().center();
        let cam = Camera::look_at(
            Intrinsics::from_fov_x(1, 1, 0.01),
            c + 3.0 * axis,
            c,
            axis.any_orthonormal_vector(),
        );
        let scene = Scene::single(Arc::new(field));
        let f = render(&scene, &cam, &RenderOptions::default()).unwrap();
        f.out.opacity[0]
    }

    #[test]
    fn a_ray_through_one_gaussian_sees_the_splat_opacity() {
        for (alpha, rot) in [
            (0.3, Quat::IDENTITY),
            (0.9, Quat::IDENTITY),
            (0.6, Quat::from_rotation_x(0.7) * Quat::from_rotation_y(-0.4)),
        ] {
            // A few tiny transparent companions so the robust bounds have a spread.
            let mut g = vec![disk(Vec3::ZERO, alpha, rot)];
            for p in [Vec3::splat(-0.6), Vec3::splat(0.6)] {
                g.push(Gaussian {
                    opacity: -12.0,
                    ..disk(p, 0.5, Quat::IDENTITY)
                });
            }
            let file = SplatFile::parse(standard_bytes(&g, 1).unwrap()).unwrap();
            let opts = ImportOptions {
                res: Some(64),
                ..Default::default()
            };
            let (field, report) = build_field(&file, &opts).unwrap();
            assert_eq!(report.used, 3);
            let normal = rot * Vec3::Z;
            let seen = centre_opacity(field, normal);
            eprintln!("splat opacity {alpha}: a ray through the imported field sees {seen:.4}");
            assert!((seen - alpha).abs() < 0.03, "alpha {alpha}: the field gives {seen}");
        }
    }
}
