//! Built-in strokes: short polylines of visible surface points per object,
//! found by casting rays from the stroke camera through pixels along the
//! projected anchor polyline and keeping the longest stretch where a brush
//! sees only the object, so that rendered stroke features (which the
//! segmentation samples over the whole brush and along the segments joining
//! the points) come from that object alone.

use super::labels::Labels;
use crate::camera::{Camera, Ray};
use crate::field::DensityGrid;
use glam::{Vec2, Vec3};

/// Most points in one stroke.
pub const SAMPLES: usize = 15;

/// Distance along `ray` where the transmittance through the field's density
/// first drops below 1/2 (the visible surface), marching in quarter voxels.
pub fn first_hit(density: &DensityGrid, ray: &Ray) -> Option<f32> {
    let (t0, t1) = density.geom.bounds.intersect(ray.origin, ray.dir)?;
    let step = 0.25 * density.geom.spacing().min_element();
    let mut depth = 0.0;
    let mut t = t0;
    while t <= t1 {
        depth += density.sigma(ray.at(t)) * step;
        if depth > std::f32::consts::LN_2 {
            return Some(t);
        }
        t += step;
    }
    None
}

/// Pixel (integer column, row) holding the projection of `p`, if on screen.
pub fn pixel_of(camera: &Camera, p: Vec3) -> Option<[u32; 2]> {
    let (uv, _) = camera.project(p)?;
    let k = camera.intrinsics;
    (uv.x >= 0.0 && uv.y >= 0.0 && uv.x < k.width as f32 && uv.y < k.height as f32)
        .then(|| [uv.x.floor() as u32, uv.y.floor() as u32])
}

/// The first visible surface through pixel (x, y): its world point and the
/// label there. The half-transmittance point can sit just outside the last
/// occupied grid point, so this steps in up to 1.5 voxels until a label shows.
pub fn surface_at(camera: &Camera, density: &DensityGrid, labels: &Labels, x: u32, y: u32) -> Option<(Vec3, u8)> {
    let ray = camera.pixel_ray(x, y);
    let t = first_hit(density, &ray)?;
    let h = density.geom.spacing().min_element();
    (0..=6).map(|i| ray.at(t + 0.25 * h * i as f32)).find_map(|p| {
        let l = labels.at(p);
        (l != 0).then_some((p, l))
    })
}

/// First-hit labels of the stroke camera's pixels, computed on demand (a
/// stroke only looks at pixels near its polyline).
pub struct LabelImage<'a> {
    camera: &'a Camera,
    density: &'a DensityGrid,
    labels: &'a Labels,
    /// Per pixel: label + 1 once known, 0 while unknown.
    known: Vec<u16>,
}

impl<'a> LabelImage<'a> {
    pub fn new(camera: &'a Camera, density: &'a DensityGrid, labels: &'a Labels) -> Self {
        let k = camera.intrinsics;
        LabelImage {
            camera,
            density,
            labels,
            known: vec![0; k.width as usize * k.height as usize],
        }
    }
    /// Label seen first through pixel (x, y); `None` off the image.
    pub fn get(&mut self, x: i64, y: i64) -> Option<u8> {
        let k = self.camera.intrinsics;
        if x < 0 || y < 0 || x >= k.width as i64 || y >= k.height as i64 {
            return None;
        }
        let i = y as usize * k.width as usize + x as usize;
        if self.known[i] == 0 {
            let l = surface_at(self.camera, self.density, self.labels, x as u32, y as u32).map_or(0, |(_, l)| l);
            self.known[i] = l as u16 + 1;
        }
        Some((self.known[i] - 1) as u8)
    }
    /// Whether every pixel of the square of radius `r` around (x, y) is on
    /// the image and sees `label` first.
    fn square_is(&mut self, x: i64, y: i64, r: i64, label: u8) -> bool {
        (-r..=r).all(|dy| (-r..=r).all(|dx| self.get(x + dx, y + dy) == Some(label)))
    }
}

/// Spacing in pixels of the candidate positions along a stroke polyline.
const STEP_PX: f32 = 1.0;

/// The stroke of object `label` through `anchors` (projected on the stroke
/// camera): the longest stretch of the anchor polyline along which a brush of
/// radius `brush` (plus one pixel of slack for rounding) touches only this
/// object, as up to [`SAMPLES`] surface points. The polyline's bends inside
/// the stretch are kept, so the segments joining consecutive points stay on
/// the checked stretch. At coarse resolutions a small object may keep fewer
/// points, or none.
pub fn stroke(img: &mut LabelImage, label: u8, anchors: &[Vec3], brush: u32) -> Vec<Vec3> {
    let pts: Vec<Vec2> = anchors
        .iter()
        .filter_map(|&a| img.camera.project(a).map(|(uv, _)| uv))
        .collect();
    let (cands, bends) = dense_polyline(&pts, STEP_PX);
    let r = brush as i64 + 1;
    let ok: Vec<bool> = cands
        .iter()
        .map(|c| img.square_is(c.x.floor() as i64, c.y.floor() as i64, r, label))
        .collect();
    let Some((a, b)) = longest_run(&ok) else { return vec![] };
    let inner_bends: Vec<usize> = bends.into_iter().filter(|&i| i > a && i < b).collect();
    let even = SAMPLES.saturating_sub(inner_bends.len()).min(b - a + 1).max(1);
    let mut pick: Vec<usize> = (0..even)
        .map(|i| a + ((b - a) as f32 * i as f32 / (even - 1).max(1) as f32).round() as usize)
        .chain(inner_bends)
        .collect();
    pick.sort_unstable();
    pick.dedup();
    pick.into_iter()
        .filter_map(|i| {
            let c = cands[i];
            surface_at(
                img.camera,
                img.density,
                img.labels,
                c.x.floor() as u32,
                c.y.floor() as u32,
            )
            .map(|(p, _)| p)
        })
        .collect()
}

/// Points every `step` pixels along a polyline (ends included), and the
/// indices of the points at its inner vertices.
fn dense_polyline(pts: &[Vec2], step: f32) -> (Vec<Vec2>, Vec<usize>) {
    let mut out = vec![];
    let mut bends = vec![];
    for (j, w) in pts.windows(2).enumerate() {
        if j > 0 {
            bends.push(out.len());
        }
        let n = (w[0].distance(w[1]) / step).ceil().max(1.0) as usize;
        out.extend((0..n).map(|i| w[0].lerp(w[1], i as f32 / n as f32)));
    }
    out.extend(pts.last());
    (out, bends)
}

/// Inclusive bounds of the longest run of `true`.
fn longest_run(ok: &[bool]) -> Option<(usize, usize)> {
    let mut best: Option<(usize, usize)> = None;
    let mut start = None;
    for (i, &v) in ok.iter().chain([false].iter()).enumerate() {
        match (v, start) {
            (true, None) => start = Some(i),
            (false, Some(s)) => {
                if best.is_none_or(|(a, b)| i - s > b - a + 1) {
                    best = Some((s, i - 1));
                }
                start = None;
            }
            _ => {}
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dense_polyline_keeps_ends_and_bends() {
        let (pts, bends) = dense_polyline(&[Vec2::ZERO, Vec2::new(4.0, 0.0), Vec2::new(4.0, 2.0)], 1.0);
        assert_eq!(pts.len(), 7);
        assert_eq!(bends, vec![4]);
        assert_eq!(pts[4], Vec2::new(4.0, 0.0));
        assert_eq!(pts[6], Vec2::new(4.0, 2.0));
        assert!(pts.windows(2).all(|w| w[0].distance(w[1]) <= 1.0 + 1e-6));
    }

    #[test]
    fn longest_run_finds_the_longest_stretch() {
        assert_eq!(longest_run(&[false, true, true, false, true, true, true]), Some((4, 6)));
        assert_eq!(longest_run(&[true, true, false, true]), Some((0, 1)));
        assert_eq!(longest_run(&[false, false]), None);
    }
}
