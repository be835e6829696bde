//! Known answers and invariants of the CPU reference renderer.

use glam::{Affine3A, Vec3};
use isrf::camera::{Camera, Intrinsics, Ray};
use isrf::field::{Aabb, Activation, Bitmap, Field, FieldBuilder};
use isrf::render::{render, render_rays, ColorEdit, Layer, Mask, Probe, RenderOptions, Scene};
use std::sync::Arc;

fn unit_box() -> Aabb {
    Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0))
}

/// A slab of constant density σ for |x| < 0.5 (exactly representable on a
/// grid whose points fall on ±0.5), colour depends on position.
fn slab(sigma: f32, res: usize) -> Field {
    FieldBuilder::new(unit_box(), [res; 3]).build(
        |p| if p.x.abs() <= 0.5 + 1e-4 { sigma } else { 0.0 },
        |p| Vec3::new(0.5 + 0.4 * p.y, 0.3, 0.5 + 0.4 * p.z),
        None,
    )
}

fn blob(center: Vec3, radius: f32, color: Vec3) -> Field {
    FieldBuilder::new(unit_box(), [33; 3]).build(
        |p| (40.0 * (1.0 - (p - center).length() / radius)).max(0.0),
        |_| color,
        Some((4, &|p: Vec3, out: &mut [f32]| {
            out.copy_from_slice(&[p.x, p.y, 1.0, 2.0])
        })),
    )
}

fn ray_x() -> Ray {
    Ray {
        origin: Vec3::new(-3.0, 0.1, 0.2),
        dir: Vec3::X,
    }
}

#[test]
fn slab_opacity_matches_closed_form() {
    // Grid points at multiples of 2/40 = 0.05, so ±0.5 are grid points and the
    // slab is exactly [-0.5, 0.5] wide along the ray (σ interpolates linearly
    // to zero over one cell outside it, adding half a cell of density).
    for sigma in [0.5f32, 2.0, 6.0] {
        let field = Arc::new(slab(sigma, 41));
        let scene = Scene::new(vec![Layer::new(field)]);
        let opts = RenderOptions {
            step: isrf::render::Step::World(0.001),
            ..Default::default()
        };
        let out = render_rays(&scene, &[ray_x()], &opts).unwrap();
        let length = 1.0 + 0.05; // slab + two half cells of the linear ramp
        let expected = 1.0 - (-sigma * length).exp();
        assert!(
            (out.opacity[0] - expected).abs() < 2e-3,
            "σ={sigma}: {} vs {expected}",
            out.opacity[0]
        );
        // Background white mixes in by the transmittance.
        let c = out.color[0];
        let want = Vec3::new(0.5 + 0.04, 0.3, 0.5 + 0.08) * expected + Vec3::ONE * (1.0 - expected);
        assert!((c - want).abs().max_element() < 3e-3, "{c} vs {want}");
    }
}

#[test]
fn composition_with_empty_field_changes_nothing() {
    let a = Arc::new(blob(Vec3::new(0.2, 0.0, 0.0), 0.5, Vec3::new(0.9, 0.2, 0.1)));
    let empty = Arc::new(FieldBuilder::new(unit_box(), [33; 3]).build(|_| 0.0, |_| Vec3::ONE, None));
    let cam = Camera::look_at(
        Intrinsics::from_fov_x(24, 18, 0.8),
        Vec3::new(0.3, 0.8, 3.0),
        Vec3::ZERO,
        Vec3::Y,
    );
    let opts = RenderOptions {
        features: true,
        ..Default::default()
    };
    let alone = render(&Scene::new(vec![Layer::new(a.clone())]), &cam, &opts).unwrap();
    let mut shifted = Layer::new(empty);
    shifted.to_world = Affine3A::from_translation(Vec3::new(0.7, 0.1, -0.4));
    let both = render(&Scene::new(vec![Layer::new(a), shifted]), &cam, &opts).unwrap();
    assert_eq!(alone.out.color, both.out.color);
    assert_eq!(alone.out.features, both.out.features);
    assert!(alone.out.opacity.iter().any(|&o| o > 0.5), "the blob must be visible");
}

#[test]
fn composition_is_order_independent_and_sums_densities() {
    let a = Arc::new(blob(Vec3::new(-0.2, 0.0, 0.0), 0.5, Vec3::new(0.9, 0.2, 0.1)));
    let b = Arc::new(blob(Vec3::new(0.25, 0.1, 0.0), 0.45, Vec3::new(0.1, 0.3, 0.9)));
    let cam = Camera::look_at(
        Intrinsics::from_fov_x(24, 18, 0.8),
        Vec3::new(0.0, 0.5, 3.0),
        Vec3::ZERO,
        Vec3::Y,
    );
    let opts = RenderOptions {
        layer_opacity: true,
        ..Default::default()
    };
    let ab = render(
        &Scene::new(vec![Layer::new(a.clone()), Layer::new(b.clone())]),
        &cam,
        &opts,
    )
    .unwrap();
    let ba = render(&Scene::new(vec![Layer::new(b), Layer::new(a)]), &cam, &opts).unwrap();
    for (x, y) in ab.out.color.iter().zip(&ba.out.color) {
        assert!((*x - *y).abs().max_element() < 1e-5);
    }
    // Per-layer opacities sum to the total opacity and swap with the order.
    let n = ab.out.opacity.len();
    for r in 0..n {
        let s = ab.out.layer_opacity[r] + ab.out.layer_opacity[n + r];
        assert!((s - ab.out.opacity[r]).abs() < 1e-4);
        assert!((ab.out.layer_opacity[r] - ba.out.layer_opacity[n + r]).abs() < 1e-5);
    }
    // Both blobs contribute somewhere.
    assert!(ab.out.layer_opacity[..n].iter().any(|&o| o > 0.5));
    assert!(ab.out.layer_opacity[n..].iter().any(|&o| o > 0.5));
}

#[test]
fn keep_plus_remove_equals_the_field() {
    let f = Arc::new(blob(Vec3::ZERO, 0.6, Vec3::new(0.2, 0.8, 0.3)));
    let bits = Arc::new(Bitmap::from_fn(f.res(), |i| f.geom().point_of(i).x > 0.1));
    let cam = Camera::look_at(
        Intrinsics::from_fov_x(20, 20, 0.8),
        Vec3::new(1.0, 0.4, 2.5),
        Vec3::ZERO,
        Vec3::Y,
    );
    let opts = RenderOptions::default();
    let whole = render(&Scene::single(f.clone()), &cam, &opts).unwrap();
    let mut keep = Layer::new(f.clone());
    keep.mask = Mask::Keep(bits.clone());
    let mut remove = Layer::new(f.clone());
    remove.mask = Mask::Remove(bits.clone());
    let split = render(&Scene::new(vec![keep.clone(), remove.clone()]), &cam, &opts).unwrap();
    for (x, y) in whole.out.color.iter().zip(&split.out.color) {
        assert!((*x - *y).abs().max_element() < 1e-4, "{x} vs {y}");
    }
    // A probe of the bitmap on the whole field measures the same object
    // opacity as the Keep layer of the split scene.
    let split_lo = render(
        &Scene::new(vec![keep.clone(), remove.clone()]),
        &cam,
        &RenderOptions {
            layer_opacity: true,
            ..Default::default()
        },
    )
    .unwrap();
    let probe = Probe {
        layer: 0,
        mask: bits.clone(),
    };
    let probed = render(
        &Scene::single(f.clone()),
        &cam,
        &RenderOptions {
            probes: vec![probe],
            ..Default::default()
        },
    )
    .unwrap();
    let n = probed.out.opacity.len();
    for r in 0..n {
        assert!((probed.out.probe_opacity[r] - split_lo.out.layer_opacity[r]).abs() < 1e-4);
    }
    assert!(probed.out.probe_opacity.iter().any(|&o| o > 0.5));
    // Removing alone leaves a hole: strictly less opacity somewhere.
    let holed = render(&Scene::new(vec![remove]), &cam, &opts).unwrap();
    let lost: f32 = whole
        .out
        .opacity
        .iter()
        .zip(&holed.out.opacity)
        .map(|(a, b)| a - b)
        .sum();
    assert!(lost > 1.0, "removal must remove something (lost {lost})");
}

#[test]
fn translated_layer_renders_like_translated_camera() {
    let f = Arc::new(blob(Vec3::ZERO, 0.5, Vec3::new(0.9, 0.6, 0.1)));
    let t = Vec3::new(0.3, -0.2, 0.1);
    let k = Intrinsics::from_fov_x(20, 16, 0.9);
    let cam = Camera::look_at(k, Vec3::new(0.5, 0.5, 3.0), Vec3::ZERO, Vec3::Y);
    let mut moved = Layer::new(f.clone());
    moved.to_world = Affine3A::from_translation(t);
    let opts = RenderOptions {
        step: isrf::render::Step::World(0.01),
        ..Default::default()
    };
    let a = render(&Scene::new(vec![moved]), &cam, &opts).unwrap();
    let mut cam2 = cam;
    cam2.c2w = Affine3A::from_translation(-t) * cam.c2w;
    let b = render(&Scene::single(f), &cam2, &opts).unwrap();
    for (x, y) in a.out.opacity.iter().zip(&b.out.opacity) {
        assert!((x - y).abs() < 0.02, "{x} vs {y}");
    }
}

#[test]
fn empty_space_skipping_is_exact() {
    // Softplus with a very negative raw value: σ ≈ 0 but not exactly zero.
    let mut fb = FieldBuilder::new(unit_box(), [65; 3]);
    fb.activation = Activation::Softplus { shift: 0.0 };
    let f = fb.build(
        |p| {
            if (p - Vec3::new(0.3, 0.1, 0.0)).length() < 0.3 {
                3.0
            } else {
                -30.0
            }
        },
        |p| p.abs(),
        None,
    );
    let f = Arc::new(f);
    assert!(f.macro_grid().occupied_fraction() < 0.5);
    let cam = Camera::look_at(
        Intrinsics::from_fov_x(16, 16, 0.9),
        Vec3::new(0.0, 0.3, 3.0),
        Vec3::ZERO,
        Vec3::Y,
    );
    let opts = RenderOptions {
        step: isrf::render::Step::World(0.01),
        min_transmittance: 0.0,
        ..Default::default()
    };
    let fast = render(&Scene::single(f.clone()), &cam, &opts).unwrap();
    // Reference: plain quadrature over every sample, written out here.
    let rays: Vec<Ray> = (0..16)
        .flat_map(|y| (0..16).map(move |x| cam.pixel_ray(x, y)))
        .collect();
    for (r, ray) in rays.iter().enumerate() {
        let (t0, t1) = f.bounds().intersect(ray.origin, ray.dir).unwrap_or((0.0, 0.0));
        let mut trans = 1.0f32;
        let mut i = (t0 / 0.01 - 0.5).ceil().max(0.0) as i64;
        while (i as f32 + 0.5) * 0.01 <= t1 {
            let s = f.sigma(ray.at((i as f32 + 0.5) * 0.01));
            trans *= (-s * 0.01).exp();
            i += 1;
        }
        assert!((fast.out.opacity[r] - (1.0 - trans)).abs() < 1e-4, "ray {r}");
    }
}

#[test]
fn colour_edit_identity_and_grey() {
    let c = Vec3::new(0.8, 0.3, 0.1);
    assert!((ColorEdit::default().apply(c) - c).abs().max_element() < 1e-6);
    let grey = ColorEdit {
        saturation: 0.0,
        ..Default::default()
    }
    .apply(c);
    assert!((grey.x - grey.y).abs() < 1e-6 && (grey.y - grey.z).abs() < 1e-6);
    // A full hue turn is the identity; a third of a turn permutes channels.
    let full = ColorEdit {
        hue: 360.0,
        ..Default::default()
    }
    .apply(c);
    assert!((full - c).abs().max_element() < 1e-5);
    let third = ColorEdit {
        hue: 120.0,
        ..Default::default()
    }
    .apply(c);
    assert!((third - Vec3::new(c.z, c.x, c.y)).abs().max_element() < 1e-5, "{third}");
    assert!(ColorEdit {
        brightness: f32::NAN,
        ..Default::default()
    }
    .validate()
    .is_err());
}

#[test]
fn bad_inputs_are_rejected() {
    let f = Arc::new(blob(Vec3::ZERO, 0.5, Vec3::ONE));
    let mut l = Layer::new(f.clone());
    l.to_world = Affine3A::from_scale(Vec3::new(1.0, 0.0, 1.0));
    let e = render_rays(&Scene::new(vec![l]), &[ray_x()], &RenderOptions::default()).unwrap_err();
    assert!(e.to_string().contains("not invertible"), "{e}");
    let mut l = Layer::new(f);
    l.mask = Mask::Keep(Arc::new(Bitmap::new([4, 4, 4])));
    let e = render_rays(&Scene::new(vec![l]), &[ray_x()], &RenderOptions::default()).unwrap_err();
    assert!(e.to_string().contains("mask resolution"), "{e}");
}

#[test]
fn the_default_step_is_half_a_cell_along_each_ray() {
    use isrf::render::{RenderOutput, Step};
    // Dense sheets one grid point thick on every axis, on a grid whose z
    // cells are 4x longer than its x and y cells (as an NDC field's depth
    // cells are): the quadrature of such hat-shaped densities depends on
    // where the samples fall, so renders tell sample spacings apart.
    let sheet = |v: f32, s: f32| ((v + 1.0) / s - 0.5).rem_euclid(4.0) < 1.0;
    let (sx, sz) = (2.0 / 64.0, 2.0 / 16.0);
    let field = Arc::new(FieldBuilder::new(unit_box(), [65, 65, 17]).build(
        |p| if sheet(p.x, sx) || sheet(p.z, sz) { 4.0 } else { 0.0 },
        |p| Vec3::new(0.5 + 0.4 * p.x, 0.3, 0.5 + 0.4 * p.z),
        None,
    ));
    let scene = Scene::single(field);
    let opts = |step| RenderOptions {
        step,
        min_transmittance: 0.0,
        ..Default::default()
    };
    let render = |d: Vec3, step| {
        let ray = Ray {
            origin: Vec3::new(0.013, -0.03, 0.021) - 3.0 * d,
            dir: d,
        };
        render_rays(&scene, &[ray], &opts(step)).unwrap()
    };
    let same = |a: &RenderOutput, b: &RenderOutput| {
        (a.color[0] - b.color[0]).abs().max_element() < 1e-6 && (a.opacity[0] - b.opacity[0]).abs() < 1e-6
    };
    // Along z: half a (long) z cell; along x: half an x cell; an oblique
    // ray moves half a cell in cell units per sample.
    let oblique = Vec3::new(1.0, 0.0, 1.0).normalize();
    let cases = [
        (Vec3::Z, 0.5 * sz),
        (Vec3::X, 0.5 * sx),
        (oblique, 0.5 / (oblique / Vec3::new(sx, sx, sz)).length()),
    ];
    for (d, want) in cases {
        let cells = render(d, Step::default());
        assert!(same(&cells, &render(d, Step::World(want))), "along {d}");
        // ... and not the finest side's step (the test can tell them apart).
        if want > 0.5 * sx * 1.01 {
            assert!(!same(&cells, &render(d, Step::World(0.5 * sx))), "along {d}");
        }
        assert!(!same(&cells, &render(d, Step::World(0.9 * want))), "along {d}");
    }
    assert!(Step::World(0.0).check().is_err() && Step::Cells(f32::NAN).check().is_err());
}

#[test]
fn rendering_without_colour_keeps_features_depth_and_opacity_to_the_bit() {
    // Two overlapping blobs of different colours, one moved and recoloured:
    // features, depth and opacity do not depend on shading, so turning it
    // off (as a stroke's pixels do) changes none of them; the colour is
    // then the background's share alone.
    let a = Arc::new(blob(Vec3::new(-0.2, 0.0, 0.0), 0.5, Vec3::new(0.9, 0.2, 0.1)));
    let b = Arc::new(blob(Vec3::new(0.2, 0.1, 0.0), 0.4, Vec3::new(0.1, 0.3, 0.8)));
    let mut moved = Layer::new(b);
    moved.to_world = Affine3A::from_translation(Vec3::new(0.0, 0.05, 0.1));
    moved.color_edit = Some(ColorEdit {
        hue: 40.0,
        ..Default::default()
    });
    let scene = Scene::new(vec![Layer::new(a), moved]);
    let rays: Vec<Ray> = (0..40)
        .map(|i| Ray {
            origin: Vec3::new(-3.0, -0.5 + i as f32 * 0.025, 0.05),
            dir: Vec3::X,
        })
        .collect();
    let on = RenderOptions {
        features: true,
        ..Default::default()
    };
    let off = RenderOptions {
        colour: false,
        ..on.clone()
    };
    let (with, without) = (
        render_rays(&scene, &rays, &on).unwrap(),
        render_rays(&scene, &rays, &off).unwrap(),
    );
    assert!(with.opacity.iter().any(|&o| o > 0.5), "the rays hit the blobs");
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&with.features), bits(&without.features));
    assert_eq!(bits(&with.depth), bits(&without.depth));
    assert_eq!(bits(&with.opacity), bits(&without.opacity));
    for (i, (c, o)) in without.color.iter().zip(&without.opacity).enumerate() {
        let background = scene.background * (1.0 - o);
        assert!(
            (*c - background).abs().max_element() < 1e-6,
            "ray {i}: {c} vs {background}"
        );
        assert!(
            (with.color[i] - *c).length() > 1e-3 || *o < 1e-3,
            "ray {i} is shaded when colour is on"
        );
    }
}

#[test]
fn samples_at_or_below_the_weight_floor_add_no_colour() {
    // σ = 0.5 sampled every 0.001: no sample weighs more than σ·δ = 5e-4.
    let scene = Scene::new(vec![Layer::new(Arc::new(slab(0.5, 41)))]);
    let at = |min_weight: f32| {
        let opts = RenderOptions {
            step: isrf::render::Step::World(0.001),
            min_weight,
            ..Default::default()
        };
        render_rays(&scene, &[ray_x()], &opts).unwrap()
    };
    let (exact, light, above) = (at(0.0), at(1e-5), at(1e-3));
    // The floor only decides what is shaded, never how light passes.
    assert_eq!(exact.opacity, light.opacity);
    assert_eq!(exact.opacity, above.opacity);
    assert!(exact.opacity[0] > 0.3);
    // Below every sample's weight but the ramp's faintest: about the same.
    assert!((exact.color[0] - light.color[0]).abs().max_element() < 1e-4);
    // Above every weight: nothing is shaded, only the background shows.
    let t = 1.0 - exact.opacity[0];
    assert!(
        (above.color[0] - Vec3::splat(t)).abs().max_element() < 1e-6,
        "{}",
        above.color[0]
    );
    assert_eq!(above.depth[0], 0.0);
    assert!((exact.color[0] - above.color[0]).abs().max_element() > 0.05);
}
