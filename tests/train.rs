//! Trainer core: the forward pass agrees with the reference renderer, every
//! gradient agrees with finite differences, resampling / pruning / export
//! keep what they promise, and sparse Adam touches only what it should.

use glam::Vec3;
use half::f16;
use isrf::camera::Ray;
use isrf::field::{Aabb, GridGeom};
use isrf::render::{render_rays, RenderOptions, Scene};
use isrf::train::grads::{GradBuf, GradLog};
use isrf::train::march::{backward, forward, ray_distortion, MarchOpts, Scratch};
use isrf::train::model::{bit, res_for, Model, Slots, PRUNED_RAW};
use isrf::train::optim::{adam_step, corrected_lr, merge_marks, AdamParams, Moments};
use isrf::train::step_of;
use isrf::train::vm::{VmAppearance, VmShape};
use isrf::util::SplitMix64;
use std::sync::Arc;

fn unit_box() -> Aabb {
    Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0))
}

/// A model with random but moderate density, colour and features; a blob
/// of density in the middle so rays see a range of opacities.
fn random_model(res: usize, degree: usize, feat: Option<(usize, usize)>, seed: u64) -> Model {
    let geom = GridGeom::new(unit_box(), [res, res + 1, res - 1]);
    let mut m = Model::new(geom, degree, 0.0, 0.01).unwrap();
    let mut rng = SplitMix64::new(seed);
    for i in 0..m.len() {
        let p = geom.point_of(i);
        let blob = 6.0 * (1.0 - p.length() / 0.8).max(0.0);
        m.density[i] = blob + 2.0 * rng.unit() as f32 - 1.0;
    }
    for v in m.sh.iter_mut() {
        *v = 2.0 * rng.unit() as f32 - 1.0;
    }
    if let Some((fres, c)) = feat {
        m.add_features([fres; 3], c).unwrap();
        for v in m.features.as_mut().unwrap().data.iter_mut() {
            *v = 2.0 * rng.unit() as f32 - 1.0;
        }
    }
    m
}

/// Small VM sizes for the gradient and exactness tests.
const SMALL_VM: VmShape = VmShape {
    rank: 3,
    out: 5,
    hidden: 8,
    view_pe: 1,
};

/// `m` with a random VM + MLP appearance on its grid.
fn with_vm(mut m: Model, seed: u64) -> Model {
    let mut vm = VmAppearance::new(SMALL_VM, m.geom.res, seed).unwrap();
    // Larger components than the training init, so colours vary visibly.
    vm.grid.iter_mut().for_each(|v| *v *= 6.0);
    m.vm = Some(vm);
    m
}

fn rays(n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = SplitMix64::new(seed);
    (0..n)
        .map(|_| {
            let mut u = || 2.0 * rng.unit() as f32 - 1.0;
            let origin = Vec3::new(u() * 0.3, u() * 0.3, 0.0) + Vec3::new(0.0, 0.0, 2.5);
            let target = Vec3::new(u() * 0.4, u() * 0.4, u() * 0.4);
            Ray {
                origin,
                dir: (target - origin).normalize(),
            }
        })
        .collect()
}

fn exact_opts(step: f32, features: bool) -> MarchOpts {
    MarchOpts {
        step,
        background: Vec3::new(0.9, 0.6, 0.3),
        weight_floor: 0.0,
        min_transmittance: 0.0,
        features,
        colour: true,
        geometry: true,
        distortion: 0.0,
    }
}

#[test]
fn forward_matches_reference_renderer() {
    let mut m = random_model(14, 2, Some((9, 5)), 1);
    // Prune a slab so that skipped cells are exercised, and store colours
    // and features at f16 precision as the field file does.
    for i in 0..m.len() {
        if m.geom.point_of(i).x > 0.55 {
            m.active[i >> 6] &= !(1 << (i & 63));
        }
    }
    m.refresh_masks();
    for v in m.sh.iter_mut() {
        *v = f16::from_f32(*v).to_f32();
    }
    for v in m.features.as_mut().unwrap().data.iter_mut() {
        *v = f16::from_f32(*v).to_f32();
    }
    let field = Arc::new(m.to_field());
    let step = step_of(&m.geom);
    let mut scene = Scene::single(field);
    let opts = exact_opts(step, true);
    scene.background = opts.background;
    let rs = rays(64, 2);
    let reference = render_rays(
        &scene,
        &rs,
        &RenderOptions {
            step: isrf::render::Step::World(step),
            features: true,
            min_transmittance: 0.0,
            ..Default::default()
        },
    )
    .unwrap();
    let mut s = Scratch::default();
    let mut max_c = 0.0f32;
    let mut max_f = 0.0f32;
    for (i, r) in rs.iter().enumerate() {
        let out = forward(&m, r, &opts, &mut s);
        max_c = max_c.max((out.color - reference.color[i]).abs().max_element());
        max_c = max_c.max((out.opacity - reference.opacity[i]).abs());
        for c in 0..5 {
            max_f = max_f.max((s.features[c] - reference.features[i * 5 + c]).abs());
        }
    }
    let opaque = reference.opacity.iter().filter(|&&o| o > 0.5).count();
    assert!(opaque > 8, "test rays should hit the blob ({opaque} opaque)");
    assert!(max_c < 2e-4, "colour/opacity differ from the renderer by {max_c}");
    assert!(max_f < 2e-4, "features differ from the renderer by {max_f}");
}

/// L = Σ_r a_r·C_r + b_r·Φ_r for fixed random a, b.
struct Probe {
    rays: Vec<Ray>,
    a: Vec<Vec3>,
    b: Vec<Vec<f32>>,
}

impl Probe {
    fn new(n: usize, fc: usize, seed: u64) -> Self {
        let mut rng = SplitMix64::new(seed);
        let mut u = || 2.0 * rng.unit() as f32 - 1.0;
        Probe {
            rays: rays(n, seed + 1),
            a: (0..n).map(|_| Vec3::new(u(), u(), u())).collect(),
            b: (0..n).map(|_| (0..fc).map(|_| u()).collect()).collect(),
        }
    }
    fn loss(&self, m: &Model, opts: &MarchOpts) -> f64 {
        let mut s = Scratch::default();
        let mut l = 0.0f64;
        for (i, r) in self.rays.iter().enumerate() {
            let out = forward(m, r, opts, &mut s);
            l += self.a[i].dot(out.color) as f64 + opts.distortion as f64 * ray_distortion(&s, opts.step) as f64;
            if opts.features {
                l += self.b[i]
                    .iter()
                    .zip(&s.features)
                    .map(|(x, y)| (x * y) as f64)
                    .sum::<f64>();
            }
        }
        l
    }
    fn grads(&self, m: &Model, opts: &MarchOpts) -> GradBuf {
        // Two logs, rays dealt alternately: what the trainer's tasks do.
        let mut logs = [GradLog::new(m), GradLog::new(m)];
        let mut s = Scratch::default();
        for (i, r) in self.rays.iter().enumerate() {
            forward(m, r, opts, &mut s);
            let h: &[f32] = if opts.features { &self.b[i] } else { &[] };
            backward(m, r, opts, &mut s, self.a[i], h, &mut logs[i % 2]);
        }
        GradBuf::from_logs(m, &mut logs)
    }
}

enum Kind {
    Density,
    /// Density with the feature term of the loss on.
    DensityFeatures,
    /// Density with the distortion loss on.
    DensityDistortion,
    Sh,
    Features,
    /// Density, planes/lines and basis+MLP of a VM-appearance model.
    DensityVm,
    VmGrid,
    VmNet,
    /// Density and colour of a pruned model: gradients per slot of the
    /// active voxels, some corners of sampled cells without one.
    PrunedDensity,
    PrunedSh,
}

/// Compares analytic and central-difference gradients on the parameters
/// with the largest analytic gradients plus a few random ones.
fn check_gradients(degree: usize, kind: Kind) {
    let feat = matches!(kind, Kind::Features | Kind::DensityFeatures);
    let m0 = random_model(10, degree, feat.then_some((7, 4)), 10 + degree as u64);
    let mut m0 = match kind {
        Kind::DensityVm | Kind::VmGrid | Kind::VmNet => with_vm(m0, 3),
        _ => m0,
    };
    if matches!(kind, Kind::PrunedDensity | Kind::PrunedSh) {
        let all = m0.len();
        let kept = m0.prune(step_of(&m0.geom), 0.1, 0);
        assert!(kept > all / 10 && kept < all * 9 / 10, "{kept} of {all} voxels kept");
    }
    let opts = MarchOpts {
        distortion: if matches!(kind, Kind::DensityDistortion) {
            2.0
        } else {
            0.0
        },
        ..exact_opts(step_of(&m0.geom), feat)
    };
    let probe = Probe::new(24, 4, 20 + degree as u64);
    let g = probe.grads(&m0, &opts);
    let (analytic, eps): (&[f32], f32) = match kind {
        Kind::Density | Kind::DensityFeatures | Kind::DensityDistortion | Kind::DensityVm | Kind::PrunedDensity => {
            (&g.density, 1e-2)
        }
        Kind::Sh | Kind::PrunedSh => (&g.sh, 1e-2),
        Kind::Features => (&g.feat, 1e-2),
        Kind::VmGrid => (&g.vm_grid, 1e-2),
        Kind::VmNet => (&g.vm_net, 1e-2),
    };
    let mut order: Vec<usize> = (0..analytic.len()).collect();
    order.sort_by(|&i, &j| analytic[j].abs().total_cmp(&analytic[i].abs()));
    let mut pick: Vec<usize> = order[..12].to_vec();
    let mut rng = SplitMix64::new(99);
    pick.extend((0..8).map(|_| order[rng.below(order.len() / 4)]));
    let scale = analytic[order[0]].abs();
    assert!(scale > 1e-4, "gradients should not all vanish");
    for &i in &pick {
        let eval = |delta: f32| {
            let mut m = m0.clone();
            match kind {
                Kind::Density | Kind::DensityFeatures | Kind::DensityDistortion | Kind::DensityVm => {
                    m.density[i] += delta
                }
                Kind::PrunedDensity => m.density[m0.slots.voxels[i] as usize] += delta,
                Kind::Sh | Kind::PrunedSh => m.sh[i] += delta,
                Kind::Features => m.features.as_mut().unwrap().data[i] += delta,
                Kind::VmGrid => m.vm.as_mut().unwrap().grid[i] += delta,
                Kind::VmNet => m.vm.as_mut().unwrap().net[i] += delta,
            }
            probe.loss(&m, &opts)
        };
        let fd = ((eval(eps) - eval(-eps)) / (2.0 * eps as f64)) as f32;
        let an = analytic[i];
        let tol = 5e-3 * scale + 2e-2 * an.abs().max(fd.abs());
        assert!(
            (fd - an).abs() < tol,
            "parameter {i}: analytic {an} vs finite difference {fd} (degree {degree})"
        );
    }
}

#[test]
fn distortion_gradient_matches_finite_differences() {
    check_gradients(2, Kind::DensityDistortion);
    check_gradients(0, Kind::DensityDistortion);
}

#[test]
fn density_gradient_matches_finite_differences() {
    check_gradients(2, Kind::Density);
    check_gradients(0, Kind::Density);
    check_gradients(1, Kind::DensityFeatures);
}

#[test]
fn gradients_of_a_pruned_model_match_finite_differences() {
    check_gradients(2, Kind::PrunedDensity);
    check_gradients(2, Kind::PrunedSh);
}

#[test]
fn sh_gradient_matches_finite_differences() {
    for degree in 0..=2 {
        check_gradients(degree, Kind::Sh);
    }
}

#[test]
fn feature_gradient_matches_finite_differences() {
    check_gradients(1, Kind::Features);
}

#[test]
fn vm_appearance_gradients_match_finite_differences() {
    check_gradients(0, Kind::VmGrid);
    check_gradients(0, Kind::VmNet);
    check_gradients(0, Kind::DensityVm);
}

#[test]
fn vm_forward_matches_reference_renderer_and_file_round_trip() {
    // The trained VM + MLP exports as the renderer's VM appearance: the
    // training forward pass and `isrf render` compute the same colours,
    // also after a save / load through a field file.
    let mut m = with_vm(random_model(12, 0, None, 4), 5);
    // A stronger network so that colours differ clearly between rays.
    m.vm.as_mut().unwrap().net.iter_mut().for_each(|v| *v *= 2.5);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("vm.safetensors");
    m.to_field().save(&path).unwrap();
    let field = Arc::new(isrf::field::Field::load(&path).unwrap());
    assert!(matches!(field.appearance, isrf::field::Appearance::Vm { .. }));
    let step = step_of(&m.geom);
    let opts = exact_opts(step, false);
    let mut scene = Scene::single(field);
    scene.background = opts.background;
    let rs = rays(48, 6);
    let reference = render_rays(
        &scene,
        &rs,
        &RenderOptions {
            step: isrf::render::Step::World(step),
            min_transmittance: 0.0,
            ..Default::default()
        },
    )
    .unwrap();
    let mut s = Scratch::default();
    let mut max_c = 0.0f32;
    let mut spread = 0.0f32;
    for (i, r) in rs.iter().enumerate() {
        let out = forward(&m, r, &opts, &mut s);
        max_c = max_c.max((out.color - reference.color[i]).abs().max_element());
        spread = spread.max((reference.color[i] - reference.color[0]).abs().max_element());
    }
    assert!(spread > 0.05, "colours should vary between rays ({spread})");
    assert!(max_c < 2e-4, "VM colour differs from the renderer by {max_c}");
}

#[test]
fn vm_resampling_is_exact_on_nested_grids() {
    // Upsampling 7 → 13 points per axis nests the old cells: plane·line
    // products are bilinear × linear inside each old cell, which the finer
    // interpolation reproduces exactly.
    let coarse = GridGeom::new(unit_box(), [7, 7, 7]);
    let fine = GridGeom::new(unit_box(), [13, 13, 13]);
    let m = with_vm(Model::new(coarse, 0, 0.0, 1.0).unwrap(), 8);
    let r = m.resampled(fine).unwrap();
    let (a, b) = (m.vm.as_ref().unwrap(), r.vm.as_ref().unwrap());
    assert_eq!(b.res, [13; 3]);
    assert_eq!(a.net, b.net);
    let mut rng = SplitMix64::new(9);
    let (mut ra, mut rb) = (vec![0.0; SMALL_VM.row_len()], vec![0.0; SMALL_VM.row_len()]);
    let mut enc = vec![];
    a.encode_dir(Vec3::Z, &mut enc);
    for _ in 0..50 {
        let p = Vec3::new(rng.unit() as f32, rng.unit() as f32, rng.unit() as f32) * 2.0 - 1.0;
        let ca = a.shade(coarse.to_grid(p), &enc, &mut ra);
        let cb = b.shade(fine.to_grid(p), &enc, &mut rb);
        for k in 0..SMALL_VM.comps() {
            assert!((ra[k] - rb[k]).abs() < 1e-5, "component {k}: {} vs {}", ra[k], rb[k]);
        }
        assert!((Vec3::from(ca) - Vec3::from(cb)).abs().max_element() < 1e-5);
    }
}

#[test]
fn density_gradient_includes_feature_term() {
    // With features on, density gradients must change by the feature term.
    let m = random_model(10, 1, Some((7, 4)), 5);
    let probe = Probe::new(16, 4, 6);
    let step = step_of(&m.geom);
    let with = probe.grads(&m, &exact_opts(step, true));
    let without = probe.grads(&m, &exact_opts(step, false));
    let diff: f32 = with
        .density
        .iter()
        .zip(&without.density)
        .map(|(a, b)| (a - b).abs())
        .sum();
    assert!(diff > 1e-3, "feature loss does not reach the density ({diff})");
    // Colour gradients are identical.
    assert_eq!(with.sh, without.sh);
}

#[test]
fn frozen_geometry_gets_no_gradient_and_the_same_feature_gradient() {
    let m = random_model(10, 1, Some((7, 4)), 5);
    let probe = Probe::new(16, 4, 6);
    let opts = exact_opts(step_of(&m.geom), true);
    let free = probe.grads(&m, &opts);
    let frozen = probe.grads(
        &m,
        &MarchOpts {
            geometry: false,
            ..opts
        },
    );
    assert!(free.feat.iter().any(|&g| g != 0.0));
    assert!(frozen.feat == free.feat, "feature gradients differ");
    assert!(frozen.feat_marks == free.feat_marks, "touched feature points differ");
    assert!(frozen.density.iter().chain(&frozen.sh).all(|&g| g == 0.0));
    assert!(frozen.marks.iter().chain(&frozen.sh_marks).all(|&w| w == 0));
    // The trainer distils without shading colour: the same features and
    // feature gradients, the ray's colour only the background left over.
    let dark = MarchOpts {
        geometry: false,
        colour: false,
        ..opts
    };
    let unshaded = probe.grads(&m, &dark);
    assert!(unshaded.feat == free.feat, "feature gradients differ without colour");
    assert!(unshaded.feat_marks == free.feat_marks);
    let (mut a, mut b) = (Scratch::default(), Scratch::default());
    for r in &probe.rays {
        let (lit, unlit) = (forward(&m, r, &opts, &mut a), forward(&m, r, &dark, &mut b));
        assert_eq!(lit.opacity, unlit.opacity);
        assert_eq!(a.features, b.features);
        let left = opts.background * (1.0 - unlit.opacity);
        assert!((unlit.color - left).length() < 1e-5, "{:?} vs {left:?}", unlit.color);
    }
}

#[test]
fn skipping_light_samples_changes_little() {
    // The training shortcut (no shading below a weight floor, early stop)
    // stays close to the exact function.
    let m = random_model(16, 2, None, 3);
    let step = step_of(&m.geom);
    let exact = exact_opts(step, false);
    let fast = MarchOpts {
        weight_floor: 1e-4,
        min_transmittance: 1e-4,
        ..exact
    };
    let mut s = Scratch::default();
    for r in rays(32, 4) {
        let a = forward(&m, &r, &exact, &mut s).color;
        let b = forward(&m, &r, &fast, &mut s).color;
        assert!((a - b).abs().max_element() < 5e-3, "{a} vs {b}");
    }
}

#[test]
fn resampling_is_exact_for_linear_fields() {
    let geom = GridGeom::new(unit_box(), [9, 9, 9]);
    let mut m = Model::new(geom, 1, 0.0, 0.1).unwrap();
    let f = |p: Vec3| 2.0 * p.x - p.y + 0.5 * p.z + 1.0;
    for i in 0..m.len() {
        let p = geom.point_of(i);
        m.density[i] = f(p);
        m.sh[i * 12 + 5] = -f(p);
    }
    let fine = GridGeom::new(Aabb::new(Vec3::splat(-0.7), Vec3::splat(0.9)), [13, 17, 11]);
    let r = m.resampled(fine).unwrap();
    for i in 0..r.len() {
        let p = fine.point_of(i);
        assert!((r.density[i] - f(p)).abs() < 1e-4, "{} vs {}", r.density[i], f(p));
        assert!((r.sh[i * 12 + 5] + f(p)).abs() < 1e-4);
    }
    assert_eq!(r.active_count(), r.len());
    // Raising the degree keeps degree-1 coefficients in place.
    let r2 = r.clone().with_degree(2);
    for i in 0..r.len() {
        for c in 0..3 {
            assert_eq!(
                &r2.sh[i * 27 + c * 9..i * 27 + c * 9 + 4],
                &r.sh[i * 12 + c * 4..i * 12 + c * 4 + 4]
            );
            assert!(r2.sh[i * 27 + c * 9 + 4..i * 27 + c * 9 + 9].iter().all(|&v| v == 0.0));
        }
    }
}

#[test]
fn pruning_keeps_dense_voxels_and_a_margin() {
    let geom = GridGeom::new(unit_box(), [21; 3]);
    let mut m = Model::new(geom, 0, 0.0, 1e-3).unwrap();
    let centre = geom.index(10, 10, 10);
    m.density[centre] = 50.0;
    let step = step_of(&geom);
    let kept = m.prune(step, 1e-2, 1);
    assert_eq!(kept, 27, "the dense voxel and its 26 neighbours stay");
    assert!(bit(&m.active, centre));
    assert!(!bit(&m.active, geom.index(12, 10, 10)));
    assert_eq!(m.density[geom.index(12, 10, 10)], PRUNED_RAW);
    // Cells touching an active voxel are live, the rest are skipped.
    assert_eq!(m.cells[geom.index(8, 8, 8)], 1);
    assert_eq!(m.cells[geom.index(7, 7, 7)], 0);
    assert_eq!(m.cells[geom.index(11, 11, 11)], 1);
    assert_eq!(m.cells[geom.index(12, 10, 10)], 0);
    let b = m.occupied_bounds(step, 1e-2, 1).unwrap();
    assert!((b.min - geom.point(9, 9, 9)).length() < 1e-5);
    assert!((b.max - geom.point(11, 11, 11)).length() < 1e-5);
}

/// A faint haze of lone voxels (what a first stage leaves over the whole
/// box) does not hold the box open when it shrinks; a small solid part
/// away from the main one does.
#[test]
fn the_box_shrinks_past_haze_but_keeps_small_solid_parts() {
    let geom = GridGeom::new(unit_box(), [32; 3]);
    let mut m = Model::new(geom, 0, 0.0, 1e-3).unwrap();
    let step = step_of(&geom);
    // Raw density giving a per-sample opacity of `a`.
    let raw = |a: f32| isrf::train::model::inverse_softplus(-(1.0 - a).ln() / step);
    for z in 10..20 {
        for y in 12..18 {
            for x in 8..22 {
                m.density[geom.index(x, y, z)] = raw(0.9);
            }
        }
    }
    // Haze: lone voxels of opacity 0.05 near every face and corner.
    for &c in &[
        [0, 0, 0],
        [31, 31, 31],
        [0, 16, 15],
        [30, 2, 29],
        [15, 31, 0],
        [16, 0, 31],
    ] {
        m.density[geom.index(c[0], c[1], c[2])] = raw(0.05);
    }
    let b = m.occupied_bounds(step, 1e-2, 1).unwrap();
    assert!((b.min - geom.point(7, 11, 9)).length() < 1e-5, "{b:?}");
    assert!((b.max - geom.point(22, 18, 20)).length() < 1e-5, "{b:?}");
    // A separate 2×2×2 block of opaque voxels (mass 7.2) is content.
    for z in 26..28 {
        for y in 3..5 {
            for x in 26..28 {
                m.density[geom.index(x, y, z)] = raw(0.9);
            }
        }
    }
    let b = m.occupied_bounds(step, 1e-2, 1).unwrap();
    assert!((b.min - geom.point(7, 2, 9)).length() < 1e-5, "{b:?}");
    assert!((b.max - geom.point(28, 18, 28)).length() < 1e-5, "{b:?}");
}

#[test]
fn colour_is_stored_for_active_voxels_only_and_survives_pruning() {
    let geom = GridGeom::new(unit_box(), [21; 3]);
    let mut m = Model::new(geom, 1, 0.0, 1e-3).unwrap();
    assert_eq!(m.sh.len(), geom.len() * m.sh_stride());
    let (centre, edge) = (geom.index(10, 10, 10), geom.index(11, 10, 10));
    m.density[centre] = 50.0;
    // Tag every voxel's colour with its own index to follow the rows.
    let k = m.sh_stride();
    for (v, row) in m.sh.chunks_mut(k).enumerate() {
        row.fill(v as f32);
    }
    m.prune(step_of(&geom), 1e-2, 1);
    assert_eq!(m.sh.len(), 27 * k, "27 active voxels, one colour row each");
    assert_eq!(m.sh_of(centre).unwrap(), &[centre as f32; 12][..]);
    assert_eq!(m.sh_of(edge).unwrap(), &[edge as f32; 12][..]);
    assert!(
        m.sh_of(geom.index(13, 10, 10)).is_none(),
        "pruned voxels have no colour"
    );
    // A checkpoint written before (one row per grid point) still loads.
    let dense: Vec<f32> = (0..geom.len()).flat_map(|v| [v as f32; 12]).collect();
    let r = Model::from_parts(geom, 0.0, 1, m.density.clone(), dense, m.active.clone(), None).unwrap();
    assert_eq!(r.sh, m.sh);
    assert!(Model::from_parts(geom, 0.0, 1, m.density.clone(), vec![0.0; 5], m.active.clone(), None).is_err());
}

#[test]
fn export_round_trips_through_a_field_file() {
    let m = random_model(8, 1, Some((5, 3)), 7);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("f.safetensors");
    m.to_field().save(&path).unwrap();
    let f = isrf::field::Field::load(&path).unwrap();
    assert_eq!(f.density.raw, m.density);
    assert_eq!(f.res(), m.geom.res);
    assert_eq!(f.feature_channels(), 3);
    let mut s = f.sampler();
    let p = Vec3::new(0.1, -0.2, 0.3);
    let dir3 = Vec3::new(0.0, 0.6, 0.8);
    let c = s.color(p, dir3);
    // The model's own colour at p through the exact forward of a tiny ray
    // segment is awkward; compare against the SH formula directly instead.
    let corners = m.geom.corners(p).unwrap();
    let basis = isrf::field::sh::basis(dir3);
    for ch in 0..3 {
        let mut z = 0.0;
        for k in 0..8 {
            for j in 0..4 {
                z += corners.weight[k] * m.sh[corners.index[k] * 12 + ch * 4 + j] * basis[j];
            }
        }
        let want = 1.0 / (1.0 + (-z).exp());
        assert!((c[ch] - want).abs() < 2e-3, "channel {ch}: {} vs {want}", c[ch]);
    }
}

#[test]
fn sparse_adam_updates_only_touched_active_points() {
    // 300 grid points, point 250 pruned: 299 slots; slot s is point s
    // below 250 and point s + 1 above.
    let n: usize = 300;
    let res = [n, 1, 1];
    let mut active = vec![u64::MAX; n.div_ceil(64)];
    active[250 >> 6] &= !(1 << (250 & 63));
    let slots = Slots::new(res, &active);
    assert_eq!(slots.len(), n - 1);
    assert_eq!(slots.slot(250), None);
    assert_eq!(slots.slot(251), Some(250));
    let a = slots.len();
    let mut p = vec![1.0f32; n];
    let mut mom = Moments::new(a);
    let mut g0 = vec![0.0f32; a];
    let mut g1 = vec![0.0f32; a];
    let mut m0 = vec![0u64; a.div_ceil(64)];
    let mut m1 = vec![0u64; a.div_ceil(64)];
    g0[3] = 1.0;
    m0[0] |= 1 << 3;
    g1[3] = 1.0;
    m1[0] |= 1 << 3;
    g1[200] = -2.0;
    m1[200 >> 6] |= 1 << (200 & 63);
    g1[260] = 5.0; // slot 260 is point 261
    m1[260 >> 6] |= 1 << (260 & 63);
    let touched = merge_marks(&mut [&mut m0, &mut m1]);
    assert!(m0.iter().chain(&m1).all(|&w| w == 0), "marks are cleared");
    let hp = AdamParams::default();
    let lr = corrected_lr(0.1, 1, hp);
    adam_step(
        &mut p,
        &mut mom,
        &mut [&mut g0, &mut g1],
        1,
        &touched,
        Some(&slots),
        lr,
        hp,
        (-10.0, 10.0),
    );
    // First Adam step moves by lr against the gradient's sign.
    assert!((p[3] - 0.9).abs() < 1e-5, "{}", p[3]);
    assert!((p[200] - 1.1).abs() < 1e-5, "{}", p[200]);
    assert!((p[261] - 0.9).abs() < 1e-5, "{}", p[261]);
    assert_eq!(p[250], 1.0, "the pruned point keeps its value");
    let moved = p.iter().filter(|&&v| v != 1.0).count();
    assert_eq!(moved, 3);
    assert!(g0.iter().chain(&g1).all(|&v| v == 0.0), "gradients are zeroed");
    // Pruning point 3 renumbers the moments; the others keep theirs.
    let mut fewer = active.clone();
    fewer[0] &= !(1 << 3);
    let slots2 = Slots::new(res, &fewer);
    let mom2 = mom.remap(&slots, &slots2, 1);
    assert_eq!(mom2.m.len(), n - 2);
    assert_eq!(mom2.m[slots2.slot(200).unwrap()], mom.m[200]);
    assert_eq!(mom2.v[slots2.slot(261).unwrap()], mom.v[260]);
}

#[test]
fn resolution_follows_the_box_shape() {
    let b = Aabb::new(Vec3::ZERO, Vec3::new(2.0, 1.0, 0.5));
    assert_eq!(res_for(b, 161, [1.0; 3]), [161, 81, 41]);
    assert_eq!(res_for(b, 161, [1.0, 1.0, 0.5]), [161, 81, 21]);
}

#[test]
fn vm_appearance_bakes_into_sh_for_the_gpu_view() {
    // The GPU view draws VM fields through an SH bake: renders of the baked
    // field stay close to the network's own.
    let m = with_vm(random_model(16, 0, None, 11), 12);
    let field = m.to_field();
    let baked = isrf::field::bake::vm_to_sh(&field).unwrap();
    assert!(matches!(baked.appearance, isrf::field::Appearance::Sh2(_)));
    let rs = rays(200, 13);
    let opts = RenderOptions::default();
    let a = render_rays(&Scene::single(Arc::new(field)), &rs, &opts).unwrap();
    let b = render_rays(&Scene::single(Arc::new(baked)), &rs, &opts).unwrap();
    let mse: f64 = a
        .color
        .iter()
        .zip(&b.color)
        .map(|(x, y)| (*x - *y).length_squared() as f64 / 3.0)
        .sum::<f64>()
        / rs.len() as f64;
    let psnr = -10.0 * mse.log10();
    eprintln!("VM vs baked SH: {psnr:.1} dB");
    assert!(psnr > 30.0, "baked SH renders {psnr:.1} dB from the VM field");
    // And differ from a bake of nothing: colours vary across rays.
    let spread = a
        .color
        .iter()
        .map(|c| (*c - a.color[0]).abs().max_element())
        .fold(0.0, f32::max);
    assert!(spread > 0.05, "{spread}");
}

/// A training setting out of its range is an out-of-range error a caller
/// can match on (the CLI and the editor show its message), as is an
/// absurd grid resolution; other bad settings stay plain invalid input.
#[test]
fn training_settings_out_of_range_are_reported_as_such() {
    use isrf::train::trainer::TrainConfig;
    use isrf::Error;
    let bad = [
        TrainConfig {
            res: 5000,
            ..Default::default()
        },
        TrainConfig {
            tv_keep: 0.0,
            ..Default::default()
        },
        TrainConfig {
            lr_density: f32::NAN,
            ..Default::default()
        },
    ];
    for c in bad {
        let e = c.validate().unwrap_err();
        assert!(matches!(e, Error::OutOfRange(_)), "{e:?}");
    }
    TrainConfig::default().validate().unwrap();
    let e = isrf::field::geom::check_res([100_000, 100_000, 100_000], "density").unwrap_err();
    assert!(
        matches!(e, Error::OutOfRange(_)) && e.to_string().contains("absurdly large"),
        "{e:?}"
    );
}

/// Adam with bf16 moments follows the f32 reference on a quadratic bowl
/// with targets of very different scales (the rounding of the stored
/// moments must not stall or bias the descent).
#[test]
fn adam_with_bf16_moments_tracks_the_f32_reference() {
    let n = 64;
    let res = [n, 1, 1];
    let slots = Slots::new(res, &vec![u64::MAX; 1]);
    let target: Vec<f32> = (0..n)
        .map(|i| (i as f32 * 0.7).sin() * 10f32.powi(-(i as i32 % 4)))
        .collect();
    let hp = AdamParams::default();
    let (mut p, mut mom) = (vec![0.0f32; n], Moments::new(n));
    let (mut q, mut m, mut v) = (vec![0.0f32; n], vec![0.0f32; n], vec![0.0f32; n]);
    for t in 1..=2000u64 {
        let lr = corrected_lr(0.05 * 0.995f32.powi(t as i32), t, hp);
        let mut g: Vec<f32> = p.iter().zip(&target).map(|(a, b)| 2.0 * (a - b)).collect();
        let mut marks = vec![u64::MAX; 1];
        let touched = merge_marks(&mut [&mut marks]);
        adam_step(
            &mut p,
            &mut mom,
            &mut [&mut g],
            1,
            &touched,
            Some(&slots),
            lr,
            hp,
            (-1e3, 1e3),
        );
        for i in 0..n {
            let gi = 2.0 * (q[i] - target[i]);
            m[i] = hp.beta1 * m[i] + (1.0 - hp.beta1) * gi;
            v[i] = hp.beta2 * v[i] + (1.0 - hp.beta2) * gi * gi;
            q[i] -= lr * m[i] / (v[i].sqrt() + hp.eps);
        }
        if t == 100 {
            // Mid-descent, the paths agree (not only the end points) to
            // within a fraction of a step.
            for i in 0..n {
                let tol = 0.02 * q[i].abs() + 0.2 * lr;
                assert!((p[i] - q[i]).abs() <= tol, "step 100, point {i}: {} vs {}", p[i], q[i]);
            }
        }
    }
    for i in 0..n {
        let tol = 1e-3 + 1e-2 * target[i].abs();
        assert!(
            (q[i] - target[i]).abs() < tol,
            "point {i}: f32 Adam {} vs target {}",
            q[i],
            target[i]
        );
        assert!(
            (p[i] - target[i]).abs() < tol,
            "point {i}: {} vs target {}",
            p[i],
            target[i]
        );
        assert!((p[i] - q[i]).abs() < tol, "point {i}: {} vs f32 Adam {}", p[i], q[i]);
    }
    // Checkpoints store the moments as BF16 and still read the F32 ones
    // older checkpoints hold, rounded to the same bf16 values.
    let m32: Vec<f32> = mom.m.iter().map(|x| x.to_f32() * 1.001).collect();
    let b16: Vec<u8> = bytemuck::cast_slice(&mom.m).to_vec();
    let b32: Vec<u8> = bytemuck::cast_slice(&m32).to_vec();
    let views = [
        ("new", safetensors::Dtype::BF16, &b16),
        ("old", safetensors::Dtype::F32, &b32),
        ("odd", safetensors::Dtype::U8, &b16),
    ];
    let views: Vec<(&str, safetensors::tensor::TensorView)> = views
        .iter()
        .map(|(name, dt, b)| {
            let len = b.len() * 8 / dt.bitsize();
            (*name, safetensors::tensor::TensorView::new(*dt, vec![len], b).unwrap())
        })
        .collect();
    let file = safetensors::serialize(views, None).unwrap();
    let path = std::path::Path::new("ckpt.safetensors");
    let t = isrf::field::io::Tensors {
        st: isrf::field::io::parse(&file, path).unwrap(),
        path,
    };
    assert_eq!(t.bf16_or_f32("new", &[n]).unwrap(), mom.m);
    let old: Vec<half::bf16> = m32.iter().map(|&x| half::bf16::from_f32(x)).collect();
    assert_eq!(t.bf16_or_f32("old", &[n]).unwrap(), old);
    let e = t.bf16_or_f32("odd", &[2 * n]).unwrap_err().to_string();
    assert!(e.contains("odd") && e.contains("BF16"), "{e}");
}

/// Slots of a random `keep` share of `of`'s voxels (and, with `extra`,
/// every voxel `of` lacks in the first quarter of the grid).
fn random_slots(res: [usize; 3], of: &[u64], keep: f32, extra: bool, seed: u64) -> Slots {
    let n = res[0] * res[1] * res[2];
    let mut rng = SplitMix64::new(seed);
    let mut bits = vec![0u64; n.div_ceil(64)];
    for i in 0..n {
        let was = bit(of, i);
        if (was && (rng.unit() as f32) < keep) || (extra && !was && i < n / 4) {
            bits[i / 64] |= 1 << (i % 64);
        }
    }
    Slots::new(res, &bits)
}

#[test]
fn rows_remapped_in_place_match_the_copying_remap() {
    use isrf::train::model::{remap_rows, remap_rows_in_place};
    let res: [usize; 3] = [13, 11, 7];
    let n = res[0] * res[1] * res[2];
    let mut rng = SplitMix64::new(5);
    let mut active = vec![0u64; n.div_ceil(64)];
    for i in 0..n {
        if rng.unit() < 0.6 {
            active[i / 64] |= 1 << (i % 64);
        }
    }
    let old = Slots::new(res, &active);
    for stride in [1, 3, 27] {
        let values: Vec<f32> = (0..old.len() * stride).map(|i| i as f32 + 0.5).collect();
        // A prune (a subset, moved forward in place) and a growth (copied).
        for (keep, extra) in [(0.5, false), (1.0, false), (0.0, false), (0.7, true)] {
            let new = random_slots(res, &active, keep, extra, 9 + stride as u64);
            let want = remap_rows(&values, &old, &new, stride);
            let mut got = values.clone();
            remap_rows_in_place(&mut got, &old, &new, stride);
            assert_eq!(got, want, "stride {stride}, keep {keep}, extra {extra}");
            assert_eq!(got.len(), new.len() * stride);
        }
    }
    // Moments follow the same rule, both of them.
    let new = random_slots(res, &active, 0.5, false, 3);
    let mut mom = Moments::new(old.len() * 2);
    for (i, (m, v)) in mom.m.iter_mut().zip(mom.v.iter_mut()).enumerate() {
        *m = half::bf16::from_f32(i as f32);
        *v = half::bf16::from_f32(-(i as f32));
    }
    let want = mom.remap(&old, &new, 2);
    mom.remap_in_place(&old, &new, 2);
    assert_eq!((mom.m, mom.v), (want.m, want.v));
}
