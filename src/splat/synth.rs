//! Synthetic splat scenes with ground truth: Gaussians sampled on the
//! surfaces of a demo scene, each with the label of the object it lies on,
//! for the splat benchmarks and tests.

use super::ply::Gaussian;
use super::sh::C0;
use crate::demo::DemoScene;
use crate::field::Appearance;
use crate::util::SplitMix64;
use glam::{Quat, Vec3};
use rayon::prelude::*;

/// Opacities are drawn uniformly from this range.
pub const ALPHA: [f32; 2] = [0.5, 0.98];

pub struct SynthScene {
    pub gaussians: Vec<Gaussian>,
    /// Demo label (0: background, floor, walls) of every Gaussian.
    pub labels: Vec<u8>,
}

/// `per_voxel` flat Gaussians on every surface voxel of `scene` (occupied,
/// with an empty 6-neighbour): centred at the voxel's grid point jittered
/// by up to half a voxel in the surface plane, their thin axis along the
/// density gradient, scales k / k / 0.1 voxel (k in 0.6..0.9), opacity
/// in [`ALPHA`], the
/// field's colour as SH DC with degree-3 view-dependent terms set to zero
/// (the common 248-byte record).
pub fn from_demo(scene: &DemoScene, per_voxel: usize, seed: u64) -> SynthScene {
    let field = &scene.field;
    let geom = field.geom();
    let h = geom.spacing().min_element();
    let occ = |v: Option<usize>| v.is_some_and(|v| field.density.sigma_at(v) > 0.0);
    let surface: Vec<usize> = field
        .occupancy
        .as_ref()
        .map(|o| o.bits().ones().collect::<Vec<_>>())
        .unwrap_or_default()
        .into_par_iter()
        .filter(|&v| occ(Some(v)) && six(geom.res, v).iter().any(|&n| !occ(n)))
        .collect();
    let per: Vec<(Vec<Gaussian>, Vec<u8>)> = surface
        .par_iter()
        .map(|&v| {
            let mut rng = SplitMix64::new(seed ^ (v as u64).wrapping_mul(0x9E37_79B9));
            let p = geom.point_of(v);
            let n = gradient(scene, v).normalize_or(Vec3::Y);
            let rot = Quat::from_rotation_arc(Vec3::Z, n);
            let dc = colour(&field.appearance, v).map(|c| (c - 0.5) / C0);
            let (t, b) = n.any_orthonormal_pair();
            let mut gs = vec![];
            let mut ls = vec![];
            for _ in 0..per_voxel {
                let (u, w) = (rng.unit() as f32 - 0.5, rng.unit() as f32 - 0.5);
                let alpha = ALPHA[0] + (ALPHA[1] - ALPHA[0]) * rng.unit() as f32;
                let k = (0.6 + 0.3 * rng.unit() as f32) * h;
                let pos = p + h * (u * t + w * b);
                ls.push(scene.labels.at(pos));
                gs.push(Gaussian {
                    pos,
                    dc,
                    rest: vec![0.0; 45],
                    opacity: (alpha / (1.0 - alpha)).ln(),
                    log_scale: [k.ln(), k.ln(), (0.1 * h).ln()],
                    rot: [rot.w, rot.x, rot.y, rot.z],
                });
            }
            (gs, ls)
        })
        .collect();
    let (mut gaussians, mut labels) = (vec![], vec![]);
    for (g, l) in per {
        gaussians.extend(g);
        labels.extend(l);
    }
    SynthScene { gaussians, labels }
}

/// The six face neighbours of a voxel (`None` outside the grid).
fn six(res: [usize; 3], v: usize) -> [Option<usize>; 6] {
    let [nx, ny, nz] = res;
    let (x, y, z) = (v % nx, (v / nx) % ny, v / (nx * ny));
    let at = |x: usize, y: usize, z: usize| x + nx * (y + ny * z);
    [
        (x > 0).then(|| at(x - 1, y, z)),
        (x + 1 < nx).then(|| at(x + 1, y, z)),
        (y > 0).then(|| at(x, y - 1, z)),
        (y + 1 < ny).then(|| at(x, y + 1, z)),
        (z > 0).then(|| at(x, y, z - 1)),
        (z + 1 < nz).then(|| at(x, y, z + 1)),
    ]
}

/// Outward normal direction: minus the density gradient (central differences).
fn gradient(scene: &DemoScene, v: usize) -> Vec3 {
    let d = &scene.field.density;
    let [a, b, c, e, f, g] = six(d.geom.res, v).map(|n| n.map_or(0.0, |n| d.sigma_at(n)));
    -Vec3::new(b - a, e - c, g - f)
}

fn colour(app: &Appearance, v: usize) -> [f32; 3] {
    let mut c = [0.5f32; 3];
    if let Appearance::Rgb(g) = app {
        g.at_voxel(v, &mut c);
    }
    c.map(|x| x.clamp(0.0, 1.0))
}
