//! Training rays (one per pixel of the training views, in the field's space:
//! the world, or NDC for forward-facing captures) and the default box a
//! dataset's field lives in.

use crate::camera::{Camera, Ray};
use crate::data::{Dataset, DatasetKind, Image, Split};
use crate::field::Aabb;
use crate::Result;
use glam::Vec3;
use rayon::prelude::*;

/// Every pixel of some views: its target colour, 6 bytes each; its view and
/// pixel follow from its index (views are stored one after another, rows
/// top to bottom), and its ray is computed from the view's camera when a
/// batch needs it (a few flops beside a march of hundreds of samples). So a
/// full-resolution capture (lego at 800×800: 64 M pixels) holds 384 MB of
/// colour, not 44 bytes of ray and f32 colour per pixel.
#[derive(Clone, Debug, Default)]
pub struct RaySet {
    cameras: Vec<Camera>,
    /// RGB in units of 1/65535: exact for 8- and 16-bit images.
    colors: Vec<[u16; 3]>,
    /// Each pixel's opacity in the same units when the views have an alpha
    /// channel (Blender scenes: `colors` are composited on the dataset's
    /// background), else empty: 2 more bytes a pixel, so that a batch can
    /// be trained on another background ([`RaySet::color_over`]).
    alpha: Vec<u16>,
    /// Index of each view's first pixel, ascending.
    starts: Vec<u32>,
}

/// The most views a ray set holds (a bound on absurd inputs).
const MAX_VIEWS: usize = u16::MAX as usize + 1;

fn to_u16(v: f32) -> u16 {
    (v.clamp(0.0, 1.0) * 65535.0).round() as u16
}

impl RaySet {
    /// Rays of `views` (camera and image of each; sizes must agree).
    pub fn build(views: &[(Camera, &Image)]) -> Result<RaySet> {
        crate::ensure_within!(
            OutOfRange,
            views.len() <= MAX_VIEWS,
            "{} training views: at most {MAX_VIEWS}",
            views.len()
        );
        for (i, (c, img)) in views.iter().enumerate() {
            crate::ensure!(
                (c.intrinsics.width, c.intrinsics.height) == (img.width, img.height),
                "view {i}: camera is {}x{} but its image is {}x{}",
                c.intrinsics.width,
                c.intrinsics.height,
                img.width,
                img.height
            );
            crate::ensure_within!(
                OutOfRange,
                crate::limits::image_size_ok(img.width, img.height),
                "view {i}: image {}x{} is too large",
                img.width,
                img.height
            );
        }
        let n: usize = views.iter().map(|(_, img)| img.len()).sum();
        // Ray indices are 32-bit (batches, the runs of `hitting`).
        crate::ensure_within!(
            OutOfRange,
            n <= u32::MAX as usize,
            "{n} training pixels: at most {} in one set",
            u32::MAX
        );
        let with_alpha = views.iter().any(|(_, img)| img.alpha.is_some());
        let mut out = RaySet {
            cameras: views.iter().map(|(c, _)| *c).collect(),
            colors: Vec::with_capacity(n),
            alpha: Vec::with_capacity(if with_alpha { n } else { 0 }),
            starts: Vec::with_capacity(views.len()),
        };
        for (_, img) in views {
            out.starts.push(out.colors.len() as u32);
            for y in 0..img.height {
                for x in 0..img.width {
                    out.colors.push(img.pixel(x, y).map(to_u16));
                }
            }
            if with_alpha {
                match &img.alpha {
                    Some(a) => out.alpha.extend(a.iter().map(|&v| to_u16(v))),
                    None => out.alpha.resize(out.colors.len(), u16::MAX),
                }
            }
        }
        Ok(out)
    }
    pub fn len(&self) -> usize {
        self.colors.len()
    }
    pub fn is_empty(&self) -> bool {
        self.colors.is_empty()
    }
    /// View and pixel coordinates of pixel `i`.
    #[inline]
    fn locate(&self, i: usize) -> (usize, u32, u32) {
        let v = self.starts.partition_point(|&s| s as usize <= i) - 1;
        let r = i - self.starts[v] as usize;
        let w = self.cameras[v].intrinsics.width as usize;
        (v, (r % w) as u32, (r / w) as u32)
    }
    /// The ray of pixel `i`, as its camera makes it (`Camera::pixel_ray`).
    #[inline]
    pub fn ray(&self, i: usize) -> Ray {
        let (v, x, y) = self.locate(i);
        self.cameras[v].pixel_ray(x, y)
    }
    /// The target colour of pixel `i`, in [0, 1].
    #[inline]
    pub fn color(&self, i: usize) -> Vec3 {
        Vec3::from(self.colors[i].map(|c| f32::from(c) / 65535.0))
    }
    /// Whether the views' opacity is known ([`RaySet::color_over`]).
    pub fn has_alpha(&self) -> bool {
        !self.alpha.is_empty()
    }
    /// The target colour of pixel `i` over `background` instead of
    /// `composited_on`, the background its colour was composited on when
    /// loaded: c + (1 − α)(background − composited_on). Without alpha, the
    /// colour as stored.
    #[inline]
    pub fn color_over(&self, i: usize, background: Vec3, composited_on: Vec3) -> Vec3 {
        match self.alpha.get(i) {
            Some(&a) => self.color(i) + (1.0 - f32::from(a) / 65535.0) * (background - composited_on),
            None => self.color(i),
        }
    }
    /// The view (index into the list the set was built from) of pixel `i`.
    #[inline]
    pub fn view(&self, i: usize) -> usize {
        self.locate(i).0
    }
    /// Pixel coordinates of pixel `i` in its view.
    #[inline]
    pub fn pixel(&self, i: usize) -> [u16; 2] {
        let (_, x, y) = self.locate(i);
        [x as u16, y as u16]
    }
    /// Bytes the set holds.
    pub fn memory_bytes(&self) -> usize {
        self.len() * size_of::<[u16; 3]>()
            + self.alpha.len() * size_of::<u16>()
            + self.starts.len() * size_of::<u32>()
            + self.cameras.len() * size_of::<Camera>()
    }
    /// The rays that meet `bounds`. A box projects to a convex region of an
    /// image, so they come in runs along rows: stored as runs, the subset
    /// takes a few bytes per image row instead of 4 per ray.
    pub fn hitting(&self, bounds: &Aabb) -> RaySubset {
        self.hitting_views(bounds, |_| true)
    }

    /// [`RaySet::hitting`] over the views `keep` accepts only.
    pub fn hitting_views(&self, bounds: &Aabb, keep: impl Fn(usize) -> bool + Sync) -> RaySubset {
        let views: Vec<usize> = (0..self.cameras.len()).filter(|&v| keep(v)).collect();
        let per_view: Vec<Vec<[u32; 2]>> = views
            .into_par_iter()
            .map(|v| {
                // The view's pixels in index order, rays straight from its camera.
                let cam = &self.cameras[v];
                let (w, h) = (cam.intrinsics.width, cam.intrinsics.height);
                let mut runs = RunBuilder::default();
                let mut i = self.starts[v];
                for (y, x) in (0..h).flat_map(|y| (0..w).map(move |x| (y, x))) {
                    let r = cam.pixel_ray(x, y);
                    if bounds.intersect(r.origin, r.dir).is_some() {
                        runs.push(i);
                    }
                    i += 1;
                }
                runs.runs
            })
            .collect();
        RaySubset::from_runs(per_view.into_iter().flatten())
    }
}

/// Appends ascending indices as `[start, length]` runs.
#[derive(Default)]
struct RunBuilder {
    runs: Vec<[u32; 2]>,
}

impl RunBuilder {
    fn push(&mut self, i: u32) {
        match self.runs.last_mut() {
            Some([s, n]) if *s + *n == i => *n += 1,
            _ => self.runs.push([i, 1]),
        }
    }
}

/// An ascending subset of a ray set's indices, held as runs of
/// consecutive indices: `get(k)` is its k-th index.
#[derive(Clone, Debug, PartialEq)]
pub struct RaySubset {
    /// First index of each run.
    starts: Vec<u32>,
    /// Subset position of each run's first index (ascending), and the
    /// subset's length at the end.
    offsets: Vec<u64>,
}

impl Default for RaySubset {
    fn default() -> Self {
        Self::from_runs([])
    }
}

impl RaySubset {
    /// The subset made of `[start, length]` runs, ascending and disjoint.
    fn from_runs(runs: impl IntoIterator<Item = [u32; 2]>) -> Self {
        let mut out = RaySubset {
            starts: vec![],
            offsets: vec![0],
        };
        for [s, n] in runs {
            let total = *out.offsets.last().expect("starts with 0");
            out.starts.push(s);
            out.offsets.push(total + u64::from(n));
        }
        out
    }
    pub fn len(&self) -> usize {
        *self.offsets.last().expect("starts with 0") as usize
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// The subset's `k`-th index (k < len).
    #[inline]
    pub fn get(&self, k: usize) -> u32 {
        let k = k as u64;
        let run = self.offsets.partition_point(|&o| o <= k) - 1;
        self.starts[run] + (k - self.offsets[run]) as u32
    }
}

/// The box a dataset's field should cover before training narrows it:
/// NeRF-synthetic scenes fit in [−1.5, 1.5]³; forward-facing (NDC) scenes
/// span the NDC frustum of the training views; otherwise the frustums
/// between the views' near/far bounds, or the box around the cameras.
pub fn default_bounds(ds: &Dataset) -> Aabb {
    let idx = ds.indices(Split::Train);
    let train: Vec<&Camera> = idx.iter().map(|&i| &ds.cameras.frames[i].camera).collect();
    if ds.kind == DatasetKind::Blender {
        return Aabb::new(Vec3::splat(-1.5), Vec3::splat(1.5));
    }
    if train.iter().any(|c| c.ndc.is_some()) {
        let depths = ds
            .near_far
            .as_ref()
            .and_then(|nf| depth_range(idx.iter().map(|&i| nf.get(i).copied())));
        return ndc_bounds(&train, depths);
    }
    if let Some(nf) = &ds.near_far {
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

/// NDC depth the box keeps beyond the capture's depth bounds on each side
/// (COLMAP's bounds are percentiles of the sparse points' depths).
pub const NDC_DEPTH_PAD: f32 = 0.1;

/// The nearest near bound and the farthest far bound of some views (finite
/// and positive), or `None`.
fn depth_range(bounds: impl Iterator<Item = Option<[f32; 2]>>) -> Option<[f32; 2]> {
    let (lo, hi) = bounds
        .flatten()
        .filter(|[n, f]| n.is_finite() && f.is_finite() && *n > 0.0 && n <= f)
        .fold((f32::INFINITY, 0.0f32), |(lo, hi), [n, f]| (lo.min(n), hi.max(f)));
    (lo <= hi).then_some([lo, hi])
}

/// NDC box: x and y spanning every view's frustum over the box's depth
/// range; z from the near plane (−1) to infinity (1), or, when the
/// capture's depth bounds are known, over the NDC depths of those bounds
/// padded by [`NDC_DEPTH_PAD`]. Fern's content lies in z −0.5 … 0.68
/// (depths 1.33 … 6.3 after scaling): the whole range left 40 % of the
/// depth cells in front of and behind everything, and the same 45 depth
/// points over the content alone sharpen the held-out views (3000
/// iterations: 23.05 → 23.78 dB; views offset along the camera rows had
/// fronds smeared across one depth cell's parallax, see
/// [`crate::eval::metrics::blur_fit`]).
fn ndc_bounds(cams: &[&Camera], depths: Option<[f32; 2]>) -> Aabb {
    let near_plane = cams.iter().find_map(|c| c.ndc).map_or(1.0, |n| n.near);
    let ndc_z = |d: f32| 1.0 - 2.0 * near_plane / d;
    let [z_lo, z_hi] = depths.map_or([-1.0, 1.0], |[n, f]| {
        [
            (ndc_z(n) - NDC_DEPTH_PAD).max(-1.0),
            (ndc_z(f) + NDC_DEPTH_PAD).min(1.0),
        ]
    });
    let mut lo = Vec3::new(f32::INFINITY, f32::INFINITY, z_lo);
    let mut hi = Vec3::new(f32::NEG_INFINITY, f32::NEG_INFINITY, z_hi);
    for c in cams {
        for r in border_rays(c, false) {
            // Where the ray is at the box's near and far depth (rays start
            // on the near plane, z = −1, and run towards +z).
            let at = |z: f32| {
                if r.dir.z > 1e-6 {
                    r.at(((z - r.origin.z) / r.dir.z).max(0.0))
                } else {
                    r.origin
                }
            };
            for p in [at(z_lo), at(z_hi)] {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Intrinsics, Ndc};
    use glam::Affine3A;

    /// The compact set gives back each pixel's ray exactly as its camera
    /// makes it (pinhole and NDC views), 8-bit colours exactly, its view
    /// and pixel (views one after another, rows top to bottom), in 6 bytes
    /// per pixel.
    #[test]
    fn rays_are_the_cameras_and_colours_survive_16_bits() {
        let k = Intrinsics::from_fov_x(7, 5, 1.0);
        let a = Camera::new(k, Affine3A::from_translation(Vec3::new(0.1, 0.2, 0.3)));
        let b = Camera::new(k, Affine3A::from_rotation_y(0.2)).with_ndc(Some(Ndc::new(6.0, 7, 5)));
        let img = |seed: u32| Image {
            width: 7,
            height: 5,
            rgb: (0..105).map(|i| ((i * 37 + seed) % 256) as f32 / 255.0).collect(),
            alpha: None,
        };
        let (ia, ib) = (img(1), img(2));
        let set = RaySet::build(&[(a, &ia), (b, &ib)]).unwrap();
        assert_eq!(set.len(), 70);
        assert_eq!(set.memory_bytes(), 70 * 6 + 2 * 4 + 2 * size_of::<Camera>());
        for i in 0..set.len() {
            let (v, [x, y]) = (set.view(i), set.pixel(i));
            assert_eq!((v, x as usize, y as usize), (i / 35, i % 35 % 7, i % 35 / 7));
            let (cam, im) = if v == 0 { (&a, &ia) } else { (&b, &ib) };
            let want = cam.pixel_ray(u32::from(x), u32::from(y));
            let got = set.ray(i);
            assert_eq!((got.origin, got.dir), (want.origin, want.dir));
            let c = set.color(i).to_array();
            let t = im.pixel(u32::from(x), u32::from(y));
            for ch in 0..3 {
                assert!((c[ch] - t[ch]).abs() < 1e-7, "{c:?} vs {t:?}");
            }
        }
        // A camera whose size is not its image's is refused.
        let small = Image {
            width: 3,
            height: 5,
            rgb: vec![0.0; 45],
            alpha: None,
        };
        assert!(RaySet::build(&[(a, &small)]).is_err());
    }

    /// Photos with alpha, composited on a background when loaded: the
    /// colour over another background is what compositing the straight
    /// colour on it gives (to 16-bit rounding); a view without alpha counts
    /// as opaque, and a set without alpha keeps its 6 bytes a pixel.
    #[test]
    fn colours_over_another_background_follow_the_alpha() {
        let k = Intrinsics::from_fov_x(4, 3, 1.0);
        let cam = Camera::new(k, Affine3A::IDENTITY);
        let on = Vec3::new(1.0, 1.0, 1.0);
        let straight = |i: usize| Vec3::new(0.9, (i as f32 * 0.07) % 1.0, 0.2);
        let alpha = |i: usize| (i as f32 / 11.0).min(1.0);
        let with = Image {
            width: 4,
            height: 3,
            rgb: (0..12)
                .flat_map(|i| (straight(i) * alpha(i) + on * (1.0 - alpha(i))).to_array())
                .collect(),
            alpha: Some((0..12).map(alpha).collect()),
        };
        let without = Image {
            alpha: None,
            ..with.clone()
        };
        let set = RaySet::build(&[(cam, &with), (cam, &without)]).unwrap();
        assert!(set.has_alpha());
        assert_eq!(set.memory_bytes(), 24 * 8 + 2 * 4 + 2 * size_of::<Camera>());
        let over = Vec3::new(0.1, 0.6, 0.3);
        for i in 0..12 {
            let want = straight(i) * alpha(i) + over * (1.0 - alpha(i));
            assert!(set.color_over(i, over, on).abs_diff_eq(want, 1e-4), "pixel {i}");
            // The view without alpha is taken as opaque: its colour as stored.
            assert_eq!(set.color_over(12 + i, over, on), set.color(12 + i));
        }
        let plain = RaySet::build(&[(cam, &without)]).unwrap();
        assert!(!plain.has_alpha());
        assert_eq!(plain.color_over(5, over, on), plain.color(5));
        assert_eq!(plain.memory_bytes(), 12 * 6 + 4 + size_of::<Camera>());
    }

    /// Views of different sizes: every pixel is found in its own view, and
    /// the rays meeting a box, kept as runs, are exactly those a ray-by-ray
    /// test finds, in the same order.
    #[test]
    fn mixed_sizes_and_the_rays_that_meet_a_box() {
        let views: Vec<(Camera, Image)> = [(9u32, 4u32, 0.0f32), (5, 6, 0.4), (1, 1, -0.2), (8, 3, 1.2)]
            .into_iter()
            .map(|(w, h, turn)| {
                let k = Intrinsics::from_fov_x(w, h, 1.2);
                let pose = Affine3A::from_rotation_y(turn) * Affine3A::from_translation(Vec3::new(0.0, 0.0, 2.0));
                let img = Image {
                    width: w,
                    height: h,
                    rgb: vec![0.5; (3 * w * h) as usize],
                    alpha: None,
                };
                (Camera::new(k, pose), img)
            })
            .collect();
        let refs: Vec<(Camera, &Image)> = views.iter().map(|(c, i)| (*c, i)).collect();
        let set = RaySet::build(&refs).unwrap();
        let mut i = 0;
        for (v, (cam, img)) in views.iter().enumerate() {
            for y in 0..img.height {
                for x in 0..img.width {
                    assert_eq!((set.view(i), set.pixel(i)), (v, [x as u16, y as u16]));
                    let (got, want) = (set.ray(i), cam.pixel_ray(x, y));
                    assert_eq!((got.origin, got.dir), (want.origin, want.dir));
                    i += 1;
                }
            }
        }
        assert_eq!(i, set.len());
        let bounds = Aabb::new(Vec3::splat(-0.3), Vec3::new(0.2, 0.25, 0.3));
        let want: Vec<u32> = (0..set.len() as u32)
            .filter(|&i| {
                let r = set.ray(i as usize);
                bounds.intersect(r.origin, r.dir).is_some()
            })
            .collect();
        assert!(
            !want.is_empty() && want.len() < set.len(),
            "some rays meet the box, not all"
        );
        let sub = set.hitting(&bounds);
        assert_eq!(sub.len(), want.len());
        let got: Vec<u32> = (0..sub.len()).map(|k| sub.get(k)).collect();
        assert_eq!(got, want);
        assert!(set.hitting(&Aabb::new(Vec3::splat(50.0), Vec3::splat(51.0))).is_empty());
    }

    /// Three forward-facing NDC views along a row (one turned a little).
    fn row_of_views() -> Vec<Camera> {
        let k = Intrinsics::from_fov_x(40, 30, 1.0);
        let ndc = Some(Ndc::new(k.fx, 40, 30));
        [(-0.3, 0.0), (0.0, 0.0), (0.3, 0.08)]
            .map(|(x, turn)| {
                Camera::new(
                    k,
                    Affine3A::from_translation(Vec3::new(x, 0.05, 0.0)) * Affine3A::from_rotation_y(turn),
                )
                .with_ndc(ndc)
            })
            .to_vec()
    }

    /// With the capture's depth bounds the NDC box spans their NDC depths
    /// (z = 1 − 2·near/d) padded by `NDC_DEPTH_PAD`, clamped to [−1, 1],
    /// and x/y span every pixel's ray over that depth range only: no
    /// training ray leaves through a side, and the box is no wider than
    /// the whole-range one.
    #[test]
    fn the_ndc_box_spans_the_depth_bounds_and_every_ray_between_them() {
        let cams = row_of_views();
        let refs: Vec<&Camera> = cams.iter().collect();
        let whole = ndc_bounds(&refs, None);
        assert_eq!((whole.min.z, whole.max.z), (-1.0, 1.0));
        let b = ndc_bounds(&refs, Some([2.0, 10.0]));
        assert!((b.min.z - (0.0 - NDC_DEPTH_PAD)).abs() < 1e-6, "{b:?}");
        assert!((b.max.z - (0.8 + NDC_DEPTH_PAD)).abs() < 1e-6, "{b:?}");
        for c in &cams {
            for (x, y) in (0..40).flat_map(|x| (0..30).map(move |y| (x, y))) {
                let r = c.pixel_ray(x, y);
                for z in [b.min.z, b.max.z] {
                    let p = r.at((z - r.origin.z) / r.dir.z);
                    assert!(
                        p.x >= b.min.x && p.x <= b.max.x && p.y >= b.min.y && p.y <= b.max.y,
                        "{p} outside {b:?}"
                    );
                }
            }
        }
        assert!(b.min.x >= whole.min.x && b.max.x <= whole.max.x && b.size().y <= whole.size().y);
        assert!(b.size().x < whole.size().x, "the turned view spreads at infinity");
        // Bounds nearer than the near plane or out to infinity clamp to the
        // whole range.
        let c = ndc_bounds(&refs, Some([0.5, 1e9]));
        assert_eq!((c.min.z, c.max.z), (-1.0, 1.0));
    }

    #[test]
    fn depth_range_is_the_nearest_near_and_farthest_far_of_sane_bounds() {
        let views = [
            Some([2.0, 5.0]),
            None,
            Some([1.5, 8.0]),
            Some([f32::NAN, 3.0]),
            Some([-1.0, 2.0]),
            Some([5.0, 3.0]),
            Some([2.5, f32::INFINITY]),
        ];
        assert_eq!(depth_range(views.into_iter()), Some([1.5, 8.0]));
        assert_eq!(depth_range([None, Some([f32::NAN, 1.0])].into_iter()), None);
        assert_eq!(depth_range(std::iter::empty()), None);
    }
}
