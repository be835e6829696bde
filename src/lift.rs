//! Features for any field (`isrf features`): teacher features lifted into
//! an existing field whose density and colour stay as they are.
//!
//! Views come from a capture (its photos and cameras, in the field's
//! frame, as `isrf train` reads them) or are rendered from the field itself
//! on two rings around the centre of its occupied voxels ([`orbit_views`]).
//! The teacher's maps of those views (PCA-reduced, cached like training's,
//! [`crate::train::teacher::teacher_features`]) are lifted by weighted
//! back-projection: every ray deposits its pixel's teacher feature into the
//! grid points around its samples with weight wᵢ·(trilinear weight), wᵢ the
//! volume-rendering weight of the frozen density, and each grid point keeps
//! the weighted mean. With the geometry frozen this is the closed-form
//! stand-in for distillation: a surface point's feature is the mean of the
//! teacher features of the pixels that see it. Stored points no ray reached
//! (hidden interiors) take the mean of their reached neighbours, a few
//! rounds. The features are then centred on the mean of the reached points
//! (see `Accumulator::mean_of_seen`). The result is a sparse 8-bit feature
//! grid at the density resolution over the field's occupancy.

use crate::camera::{Camera, Intrinsics};
use crate::data::Image;
use crate::error::Result;
use crate::field::{sparse, ChannelGrid, Features, Field};
use crate::render::{render, RenderOptions, Scene};
use crate::train::teacher::{teacher_features, FeatureMaps, TeacherReport, TeacherSource};
use glam::Vec3;
use half::f16;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// One posed image in the field's frame.
pub struct View {
    pub name: PathBuf,
    pub camera: Camera,
    pub image: Image,
}

/// Image size of rendered orbit views.
pub const ORBIT_WIDTH: u32 = 320;
pub const ORBIT_HEIGHT: u32 = 240;
const ORBIT_FOV_DEG: f32 = 50.0;
/// Rounds of filling unseen points from their neighbours.
const FILL_ROUNDS: usize = 4;
/// Samples with a smaller rendering weight deposit nothing.
const MIN_WEIGHT: f32 = 1e-3;

/// Cameras on two rings (elevations 20° and 50°, alternating, +y up)
/// around the centre of the occupied voxels, far enough to see them all.
pub fn orbit_cameras(field: &Field, n: usize) -> Result<Vec<Camera>> {
    crate::ensure_within!(
        OutOfRange,
        (1..=720).contains(&n),
        "--orbit {n}: between 1 and 720 views"
    );
    let geom = field.geom();
    let bits = sparse::density_occupancy(&field.density);
    let (lo, hi) = bits
        .bounding_box()
        .ok_or_else(|| crate::error::Error::invalid("the field has no occupied voxel to look at"))?;
    let p = |c: [usize; 3]| geom.point(c[0], c[1], c[2]);
    let (lo, hi) = (p(lo), p(hi));
    let centre = 0.5 * (lo + hi);
    let radius = 0.5 * (hi - lo).length() / (0.5 * ORBIT_FOV_DEG.to_radians()).tan() * 1.1;
    let k = Intrinsics::from_fov_x(ORBIT_WIDTH, ORBIT_HEIGHT, ORBIT_FOV_DEG.to_radians());
    Ok((0..n)
        .map(|i| {
            let a = std::f32::consts::TAU * i as f32 / n as f32;
            let e = if i % 2 == 0 { 20f32 } else { 50f32 }.to_radians();
            let eye = centre + radius * Vec3::new(e.cos() * a.sin(), e.sin(), e.cos() * a.cos());
            Camera::look_at(k, eye, centre, Vec3::Y)
        })
        .collect())
}

/// `n` views of the field rendered from [`orbit_cameras`] (white background).
pub fn orbit_views(field: &Arc<Field>, n: usize, progress: &(dyn Fn(usize, usize) + Sync)) -> Result<Vec<View>> {
    let scene = Scene::single(field.clone());
    let opts = RenderOptions {
        depth: false,
        ..Default::default()
    };
    let cams = orbit_cameras(field, n)?;
    let mut views = Vec::with_capacity(n);
    for (i, camera) in cams.into_iter().enumerate() {
        let frame = render(&scene, &camera, &opts)?;
        let rgb = frame.out.color.iter().flat_map(|c| c.to_array()).collect();
        views.push(View {
            name: PathBuf::from(format!("orbit_{i:03}.png")),
            camera,
            image: Image {
                width: frame.width,
                height: frame.height,
                rgb,
                alpha: None,
            },
        });
        progress(i + 1, n);
    }
    Ok(views)
}

/// The training views of a capture.
pub fn dataset_views(ds: crate::data::Dataset) -> Vec<View> {
    let train = ds.indices(crate::data::Split::Train);
    let mut images: Vec<Option<Image>> = ds.images.into_iter().map(Some).collect();
    train
        .into_iter()
        .filter_map(|i| {
            Some(View {
                name: ds.image_paths[i].clone(),
                camera: ds.cameras.frames[i].camera,
                image: images[i].take()?,
            })
        })
        .collect()
}

/// What [`lift`] did.
#[derive(Clone, Debug)]
pub struct LiftReport {
    pub teacher: TeacherReport,
    pub points: usize,
    /// Stored points some ray reached.
    pub seen: usize,
}

/// The field with features lifted from `views` (module docs); `dims` PCA
/// channels.
pub fn lift(
    field: &Field,
    views: &[View],
    source: &TeacherSource,
    dims: usize,
    cache_dir: Option<&Path>,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<(Field, LiftReport)> {
    crate::ensure!(!views.is_empty(), "no views to take features from");
    let images: Vec<&Image> = views.iter().map(|v| &v.image).collect();
    let names: Vec<PathBuf> = views.iter().map(|v| v.name.clone()).collect();
    let (maps, teacher) = teacher_features(source, &images, &names, dims, cache_dir, &|i, n| {
        progress("teacher", i, n)
    })?;
    let cameras: Vec<Camera> = views.iter().map(|v| v.camera).collect();
    let (out, seen) = lift_maps(field, &cameras, &maps, &|i, n| progress("lift", i, n))?;
    let report = LiftReport {
        teacher,
        points: out.occupancy.as_ref().map_or(0, |o| o.count()),
        seen,
    };
    Ok((out, report))
}

/// The field with features lifted from one feature map per camera (the
/// teacher's, or any other); also returns how many stored points a ray
/// reached.
pub fn lift_maps(
    field: &Field,
    cameras: &[Camera],
    maps: &FeatureMaps,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<(Field, usize)> {
    crate::ensure!(
        cameras.len() == maps.maps.len(),
        "{} cameras but {} feature maps",
        cameras.len(),
        maps.maps.len()
    );
    let mut out = sparse::sparsify(field)?;
    out.source = field.source.clone();
    let index = out.occupancy.clone().expect("sparsify gives an occupancy");
    let mut acc = Accumulator::new(index.count(), maps.channels);
    for (i, cam) in cameras.iter().enumerate() {
        acc.add_view(&out, &index, cam, maps, i);
        progress(i + 1, cameras.len());
    }
    let seen = acc.weight.iter().filter(|&&w| w > 0.0).count();
    let data = acc.finish(&out.geom(), &index);
    let grid = ChannelGrid::sparse(out.geom(), maps.channels, index.clone(), data);
    out.features = Some(Features::Grid(grid));
    Ok((out, seen))
}

/// Weighted feature sums per stored grid point.
struct Accumulator {
    channels: usize,
    sum: Vec<f32>,
    weight: Vec<f32>,
}

impl Accumulator {
    fn new(slots: usize, channels: usize) -> Self {
        Accumulator {
            channels,
            sum: vec![0.0; slots * channels],
            weight: vec![0.0; slots],
        }
    }

    /// Deposits one view: (slot, pixel, weight) triples from every ray,
    /// gathered per slot (counting sort) so slots are written in parallel
    /// without sharing.
    fn add_view(
        &mut self,
        field: &Field,
        index: &crate::field::RankIndex,
        cam: &Camera,
        maps: &FeatureMaps,
        view: usize,
    ) {
        let k = cam.intrinsics;
        let (w, h) = (k.width as usize, k.height as usize);
        let c = self.channels;
        let triples: Vec<(u32, u32, f32)> = (0..h)
            .into_par_iter()
            .flat_map_iter(|y| {
                let mut out = vec![];
                for x in 0..w {
                    march(field, index, cam, x as u32, y as u32, |s, wt| {
                        out.push((s as u32, (y * w + x) as u32, wt))
                    });
                }
                out
            })
            .collect();
        let mut teacher = vec![0f32; w * h * c];
        teacher.par_chunks_mut(c).enumerate().for_each(|(p, row)| {
            maps.sample(view, [(p % w) as u16, (p / w) as u16], row);
        });
        let (starts, order) = group_by_slot(&triples, self.weight.len());
        self.sum
            .par_chunks_mut(c)
            .zip(self.weight.par_iter_mut())
            .enumerate()
            .for_each(|(s, (row, wsum))| {
                for &t in &order[starts[s]..starts[s + 1]] {
                    let (_, p, wt) = triples[t as usize];
                    let f = &teacher[p as usize * c..(p as usize + 1) * c];
                    row.iter_mut().zip(f).for_each(|(r, f)| *r += wt * f);
                    *wsum += wt;
                }
            });
    }

    /// Weighted means as f16, unseen points filled from seen neighbours.
    fn finish(mut self, geom: &crate::field::GridGeom, index: &crate::field::RankIndex) -> Vec<f16> {
        let c = self.channels;
        self.sum.par_chunks_mut(c).zip(&self.weight).for_each(|(row, &w)| {
            if w > 0.0 {
                row.iter_mut().for_each(|v| *v /= w);
            }
        });
        let voxels: Vec<usize> = index.bits().ones().collect();
        let mut known: Vec<bool> = self.weight.iter().map(|&w| w > 0.0).collect();
        for _ in 0..FILL_ROUNDS {
            let filled: Vec<(usize, Vec<f32>)> = (0..voxels.len())
                .into_par_iter()
                .filter(|&s| !known[s])
                .filter_map(|s| {
                    let mut mean = vec![0f32; c];
                    let mut n = 0;
                    geom.neighbours26(voxels[s], |v| {
                        if let Some(t) = index.slot(v).filter(|&t| known[t]) {
                            mean.iter_mut()
                                .zip(&self.sum[t * c..(t + 1) * c])
                                .for_each(|(m, v)| *m += v);
                            n += 1;
                        }
                    });
                    (n > 0).then(|| (s, mean.into_iter().map(|m| m / n as f32).collect()))
                })
                .collect();
            if filled.is_empty() {
                break;
            }
            for (s, row) in filled {
                self.sum[s * c..(s + 1) * c].copy_from_slice(&row);
                known[s] = true;
            }
        }
        let mean = self.mean_of_seen();
        self.sum
            .par_chunks(c)
            .flat_map_iter(|row| row.iter().zip(&mean).map(|(v, m)| f16::from_f32(v - m)))
            .collect()
    }

    /// Mean feature of the points some ray reached. The teacher's PCA is
    /// centred over every pixel of the views, background included, so the
    /// scene's points share an offset that dominates their unit-length
    /// comparisons (on a demo scene every pair of objects within 0.4 in
    /// squared distance, below the seed threshold); subtracting it leaves
    /// their differences.
    fn mean_of_seen(&self) -> Vec<f32> {
        let c = self.channels;
        let mut mean = vec![0f64; c];
        let mut n = 0usize;
        for (row, &w) in self.sum.chunks(c).zip(&self.weight) {
            if w > 0.0 {
                mean.iter_mut().zip(row).for_each(|(m, v)| *m += *v as f64);
                n += 1;
            }
        }
        mean.iter().map(|m| (m / n.max(1) as f64) as f32).collect()
    }
}

/// Marches pixel (x, y)'s ray through the field's density like the
/// renderer (half-voxel steps) and calls `deposit(slot, weight)` for the
/// stored corners of every sample whose rendering weight counts.
fn march(
    field: &Field,
    index: &crate::field::RankIndex,
    cam: &Camera,
    x: u32,
    y: u32,
    mut deposit: impl FnMut(usize, f32),
) {
    let ray = cam.pixel_ray(x, y);
    let geom = field.geom();
    let Some((t0, t1)) = geom.bounds.intersect(ray.origin, ray.dir) else {
        return;
    };
    let step = 0.5 * geom.spacing().min_element();
    let mut t = t0.max(0.0) + 0.5 * step;
    let mut trans = 1.0f32;
    while t < t1 && trans > 1e-3 {
        let p = ray.at(t);
        t += step;
        let sigma = field.sigma(p);
        if sigma <= 0.0 {
            continue;
        }
        let alpha = 1.0 - (-sigma * step).exp();
        let w = trans * alpha;
        trans *= 1.0 - alpha;
        if w < MIN_WEIGHT {
            continue;
        }
        let Some(c) = geom.corners(p) else { continue };
        for k in 0..8 {
            if c.weight[k] > 0.0 {
                if let Some(s) = index.slot(c.index[k]) {
                    deposit(s, w * c.weight[k]);
                }
            }
        }
    }
}

/// Counting sort of triples by slot: `order[starts[s]..starts[s + 1]]`
/// are the triples of slot `s`.
fn group_by_slot(triples: &[(u32, u32, f32)], slots: usize) -> (Vec<usize>, Vec<u32>) {
    let mut starts = vec![0usize; slots + 1];
    for t in triples {
        starts[t.0 as usize + 1] += 1;
    }
    for s in 0..slots {
        starts[s + 1] += starts[s];
    }
    let mut next = starts.clone();
    let mut order = vec![0u32; triples.len()];
    for (i, t) in triples.iter().enumerate() {
        order[next[t.0 as usize]] = i as u32;
        next[t.0 as usize] += 1;
    }
    (starts, order)
}
