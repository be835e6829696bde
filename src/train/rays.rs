//! Training rays (one per pixel of the training views, in the field's space:
//! the world, or NDC for forward-facing captures) and the default box a
//! dataset's field lives in.

use crate::camera::{Camera, Ray};
use crate::data::{Dataset, DatasetKind, Image, Split};
use crate::field::Aabb;
use crate::Result;
use glam::Vec3;
use rayon::prelude::*;

/// Every pixel of some views: its ray, target colour, view and pixel.
#[derive(Clone, Debug, Default)]
pub struct RaySet {
    pub rays: Vec<Ray>,
    pub colors: Vec<Vec3>,
    /// Index of the view (into the list the set was built from).
    pub view: Vec<u32>,
    pub pixel: Vec<[u16; 2]>,
}

impl RaySet {
    /// Rays of `views` (camera and image of each; sizes must agree).
    pub fn build(views: &[(Camera, &Image)]) -> Result<RaySet> {
        for (i, (c, img)) in views.iter().enumerate() {
            crate::ensure!(
                (c.intrinsics.width, c.intrinsics.height) == (img.width, img.height),
                "view {i}: camera is {}x{} but its image is {}x{}",
                c.intrinsics.width,
                c.intrinsics.height,
                img.width,
                img.height
            );
            crate::ensure!(
                img.width <= u16::MAX as u32 && img.height <= u16::MAX as u32,
                "view {i}: image is too large"
            );
        }
        let parts: Vec<RaySet> = views
            .par_iter()
            .enumerate()
            .map(|(v, (cam, img))| {
                let n = img.len();
                let mut s = RaySet {
                    rays: Vec::with_capacity(n),
                    colors: Vec::with_capacity(n),
                    view: vec![v as u32; n],
                    pixel: Vec::with_capacity(n),
                };
                for y in 0..img.height {
                    for x in 0..img.width {
                        s.rays.push(cam.pixel_ray(x, y));
                        s.colors.push(Vec3::from(img.pixel(x, y)));
                        s.pixel.push([x as u16, y as u16]);
                    }
                }
                s
            })
            .collect();
        let mut out = RaySet::default();
        for p in parts {
            out.rays.extend(p.rays);
            out.colors.extend(p.colors);
            out.view.extend(p.view);
            out.pixel.extend(p.pixel);
        }
        Ok(out)
    }
    pub fn len(&self) -> usize {
        self.rays.len()
    }
    pub fn is_empty(&self) -> bool {
        self.rays.is_empty()
    }
    /// Indices of the rays that meet `bounds`.
    pub fn hitting(&self, bounds: &Aabb) -> Vec<u32> {
        (0..self.len() as u32)
            .into_par_iter()
            .filter(|&i| {
                let r = &self.rays[i as usize];
                bounds.intersect(r.origin, r.dir).is_some()
            })
            .collect()
    }
}

/// The box a dataset's field should cover before training narrows it:
/// NeRF-synthetic scenes fit in [−1.5, 1.5]³; forward-facing (NDC) scenes
/// span the NDC frustum of the training views; otherwise the frustums
/// between the views' near/far bounds, or the box around the cameras.
pub fn default_bounds(ds: &Dataset) -> Aabb {
    let train: Vec<&Camera> = ds
        .indices(Split::Train)
        .into_iter()
        .map(|i| &ds.cameras.frames[i].camera)
        .collect();
    if ds.kind == DatasetKind::Blender {
        return Aabb::new(Vec3::splat(-1.5), Vec3::splat(1.5));
    }
    if train.iter().any(|c| c.ndc.is_some()) {
        return ndc_bounds(&train);
    }
    if let Some(nf) = &ds.near_far {
        let idx = ds.indices(Split::Train);
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for (&i, cam) in idx.iter().zip(&train) {
            let [near, far] = nf.get(i).copied().unwrap_or([1.0, 10.0]);
            for r in border_rays(cam, true) {
                for t in [near, far] {
                    let p = r.at(t);
                    lo = lo.min(p);
                    hi = hi.max(p);
                }
            }
        }
        return Aabb::new(lo, hi);
    }
    // Inward-facing captures: the cube around the cameras' centres.
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for c in &train {
        lo = lo.min(c.position());
        hi = hi.max(c.position());
    }
    let c = 0.5 * (lo + hi);
    let h = (0.5 * (hi - lo).max_element()).max(1e-3);
    Aabb::new(c - Vec3::splat(h), c + Vec3::splat(h))
}

/// Rays through the border pixels of a camera (corners and edge midpoints).
fn border_rays(cam: &Camera, world: bool) -> Vec<Ray> {
    let k = cam.intrinsics;
    let (w, h) = (k.width as f32, k.height as f32);
    let mut out = vec![];
    for u in [0.0, 0.5 * w, w] {
        for v in [0.0, 0.5 * h, h] {
            out.push(if world { cam.world_ray(u, v) } else { cam.ray(u, v) });
        }
    }
    out
}

/// NDC box: z from −1 (near plane) to 1 (infinity); x and y spanning every
/// view's frustum between them.
fn ndc_bounds(cams: &[&Camera]) -> Aabb {
    let mut lo = Vec3::new(f32::INFINITY, f32::INFINITY, -1.0);
    let mut hi = Vec3::new(f32::NEG_INFINITY, f32::NEG_INFINITY, 1.0);
    for c in cams {
        for r in border_rays(c, false) {
            let far = if r.dir.z > 1e-6 {
                r.at((1.0 - r.origin.z) / r.dir.z)
            } else {
                r.origin
            };
            for p in [r.origin, far] {
                lo.x = lo.x.min(p.x);
                lo.y = lo.y.min(p.y);
                hi.x = hi.x.max(p.x);
                hi.y = hi.y.max(p.y);
            }
        }
    }
    // A hair of margin so border rays stay inside.
    let m = Vec3::new(0.01, 0.01, 0.0);
    Aabb::new(lo - m, hi + m)
}
