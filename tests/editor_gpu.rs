//! The WGSL ray marcher computes the CPU reference renderer's image (PSNR
//! ≥ 45 dB at 160×120; the issue asks 35): the demo tabletop; a composition
//! with a moved, masked, recoloured object; a removed object and the object
//! alone (density-weighted masks); SH appearance (sparse and dense),
//! softplus density and a second field with its own scaled transform. Skips
//! (with a message) where no GPU adapter exists.
#![cfg(feature = "editor")]

use glam::{Affine3A, Quat, Vec3};
use isrf::app::headless::{gpu_available, HeadlessRenderer};
use isrf::camera::{Camera, Intrinsics};
use isrf::field::{Aabb, Activation, Appearance, ChannelGrid, Field, FieldBuilder, GridGeom, Layout};
use isrf::render::{render, ColorEdit, Layer, Mask, RenderOptions, Scene};
use std::sync::Arc;

const W: u32 = 160;
const H: u32 = 120;
/// The issue asks for 35 dB; the images agree to 8-bit rounding (about
/// 60 dB on lavapipe), while a plain-trilinear mask or an SH colour off by
/// 10 % already drops to 36–38 dB: 45 dB tells those apart and leaves room
/// for GPUs with less exact exp / log.
const MIN_PSNR: f64 = 45.0;

fn psnr(a: &[Vec3], b: &[Vec3]) -> f64 {
    assert_eq!(a.len(), b.len());
    let mse: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| {
            let d = *x - *y;
            (d.x * d.x + d.y * d.y + d.z * d.z) as f64 / 3.0
        })
        .sum::<f64>()
        / a.len() as f64;
    10.0 * (1.0 / mse.max(1e-12)).log10()
}

fn cpu(scene: &Scene, cam: &Camera) -> Vec<Vec3> {
    let f = render(scene, cam, &RenderOptions::default()).unwrap();
    // Quantise like the GPU's 8-bit target so both sides round alike.
    f.out
        .color
        .iter()
        .map(|c| (c.clamp(Vec3::ZERO, Vec3::ONE) * 255.0).round() / 255.0)
        .collect()
}

fn skip() -> bool {
    if !gpu_available() {
        eprintln!("skipping: no GPU adapter (install mesa-vulkan-drivers and set WGPU_BACKEND=vulkan)");
        return true;
    }
    false
}

fn demo() -> (isrf::demo::DemoScene, Camera) {
    let d = isrf::demo::build("tabletop", 64, 7).unwrap();
    let c2w = d.cameras.frames[2].camera.c2w;
    let cam = Camera::new(Intrinsics::from_fov_x(W, H, 42f32.to_radians()), c2w);
    (d, cam)
}

/// The demo field, the mug's bitmap and the camera.
fn demo_mug() -> (Arc<Field>, Arc<isrf::field::Bitmap>, Camera) {
    let (d, cam) = demo();
    let mug = Arc::new(d.labels.mask(d.labels.label_of("mug").unwrap()));
    (Arc::new(d.field), mug, cam)
}

#[test]
fn gpu_matches_cpu_on_the_tabletop_and_a_composition() {
    if skip() {
        return;
    }
    let (d, cam) = demo();
    let field = Arc::new(d.field);
    let mut r = HeadlessRenderer::new(W, H).unwrap();

    // 1. The plain field.
    let scene = Scene::single(field.clone());
    let gpu = r.render(Arc::new(scene.clone()), &cam).unwrap();
    let want = cpu(&scene, &cam);
    let p = psnr(&gpu, &want);
    eprintln!("tabletop 64³ at {W}x{H}: PSNR {p:.2} dB");
    assert!(p >= MIN_PSNR, "tabletop PSNR {p:.2} dB < {MIN_PSNR}");
    // The image is not trivially the background.
    let bg = want.iter().filter(|c| (**c - Vec3::ONE).length() < 1e-3).count();
    assert!(bg < want.len() / 2, "the view shows mostly background");

    // 2. The mug cut out, moved, rotated and recoloured; its old place removed.
    let mug = Arc::new(d.labels.mask(d.labels.label_of("mug").unwrap()));
    assert!(mug.count() > 50);
    let mut rest = Layer::new(field.clone());
    rest.mask = Mask::Remove(mug.clone());
    let mut moved = Layer::new(field.clone());
    moved.mask = Mask::Keep(mug.clone());
    moved.to_world = Affine3A::from_rotation_translation(Quat::from_rotation_y(0.6), Vec3::new(0.25, 0.05, 0.2));
    moved.color_edit = Some(ColorEdit {
        tint: [1.0, 0.8, 0.6],
        hue: 40.0,
        saturation: 1.5,
        brightness: 0.9,
    });
    let comp = Scene::new(vec![rest, moved]);
    let gpu2 = r.render(Arc::new(comp.clone()), &cam).unwrap();
    let want2 = cpu(&comp, &cam);
    let p2 = psnr(&gpu2, &want2);
    eprintln!("composition at {W}x{H}: PSNR {p2:.2} dB");
    assert!(p2 >= MIN_PSNR, "composition PSNR {p2:.2} dB < {MIN_PSNR}");
    // The composition differs from the plain field (the edit is visible).
    assert!(psnr(&want, &want2) < 40.0, "moving the mug changed nothing");
}

/// Forward-facing captures (LLFF) live in NDC space: a camera with NDC
/// marches the scene along NDC rays, on the GPU as on the CPU, from the
/// reference pose and from one moved off it, with SH appearance (whose
/// direction is the NDC ray's) and a mask.
#[test]
fn gpu_matches_cpu_for_ndc_cameras() {
    if skip() {
        return;
    }
    let (d, _) = demo();
    let mug = Arc::new(d.labels.mask(d.labels.label_of("mug").unwrap()));
    let field = Arc::new(sparse_sh(&d.field));
    let b = field.bounds();
    eprintln!("NDC test field bounds {:?} .. {:?}", b.min, b.max);
    let ndc = isrf::camera::Ndc::new(0.9 * W as f32, W, H);
    let k = Intrinsics::from_fov_x(W, H, 2.0 * (0.5 / 0.9f32).atan());
    let reference = Camera::new(k, Affine3A::IDENTITY).with_ndc(Some(ndc));
    let moved = Camera::new(
        k,
        Affine3A::from_rotation_translation(Quat::from_rotation_y(0.08), Vec3::new(0.15, -0.05, 0.1)),
    )
    .with_ndc(Some(ndc));
    let mut r = HeadlessRenderer::new(W, H).unwrap();
    let mut rest = Layer::new(field.clone());
    rest.mask = Mask::Remove(mug.clone());
    let mut lifted = Layer::new(field.clone());
    lifted.mask = Mask::Keep(mug);
    lifted.to_world = Affine3A::from_translation(Vec3::new(0.0, 0.2, 0.0));
    for (what, scene) in [
        ("plain", Scene::single(field.clone())),
        ("mug lifted", Scene::new(vec![rest, lifted])),
    ] {
        for (name, cam) in [("reference", &reference), ("moved", &moved)] {
            let gpu = r.render(Arc::new(scene.clone()), cam).unwrap();
            let want = cpu(&scene, cam);
            let p = psnr(&gpu, &want);
            eprintln!("NDC {what}, {name} camera: PSNR {p:.2} dB");
            assert!(p >= MIN_PSNR, "NDC {what} {name}: PSNR {p:.2} dB < {MIN_PSNR}");
            let bg = want.iter().filter(|c| (**c - Vec3::ONE).length() < 1e-3).count();
            eprintln!(
                "  background {:.1} % of the pixels",
                100.0 * bg as f64 / want.len() as f64
            );
            assert!(bg < want.len() * 9 / 10, "the NDC view shows mostly background");
        }
    }
    // The same camera without NDC sees the field differently (NDC mattered).
    let plain = Scene::single(field);
    let pinhole = r.render(Arc::new(plain.clone()), &Camera::new(k, moved.c2w)).unwrap();
    assert!(psnr(&pinhole, &cpu(&plain, &moved)) < 30.0, "NDC changed nothing");
}

/// 27 SH channels per slot whose DC term gives `rgb` and whose higher
/// terms add a view-dependent ripple, so that direction handling matters.
fn sh_from_rgb(rgb: [f32; 3], seed: f32) -> Vec<half::f16> {
    const C0: f32 = 0.282_094_8;
    let mut out = Vec::with_capacity(27);
    for (c, v) in rgb.iter().enumerate() {
        let v = v.clamp(0.03, 0.97);
        out.push(half::f16::from_f32((v / (1.0 - v)).ln() / C0));
        for j in 1..9 {
            out.push(half::f16::from_f32(0.6 * (seed * 0.37 + (j * 3 + c) as f32).sin()));
        }
    }
    out
}

/// The demo tabletop with its sparse RGB turned into sparse SH (same rank
/// index), as an imported Plenoxels-style grid would be.
fn sparse_sh(field: &Field) -> Field {
    let Appearance::Rgb(g) = &field.appearance else {
        panic!("demo appearance is RGB")
    };
    let Layout::Sparse(ix) = &g.layout else {
        panic!("demo appearance is sparse")
    };
    let data: Vec<half::f16> = g
        .data
        .chunks(3)
        .enumerate()
        .flat_map(|(s, c)| sh_from_rgb([c[0].to_f32(), c[1].to_f32(), c[2].to_f32()], s as f32))
        .collect();
    let mut f = field.clone();
    f.appearance = Appearance::Sh2(ChannelGrid::sparse(g.geom, 27, ix.clone(), data));
    f
}

/// A trained-looking field: softplus density with a shift, dense SH.
fn softplus_sh_ball() -> Field {
    let b = FieldBuilder {
        geom: GridGeom::new(Aabb::new(Vec3::splat(-0.3), Vec3::splat(0.3)), [40, 40, 40]),
        activation: Activation::Softplus { shift: -6.0 },
    };
    let mut f = b.build(|p| (300.0 * (0.22 - p.length())).max(-10.0), |_| Vec3::ONE, None);
    let g = f.geom();
    let data: Vec<half::f16> = (0..g.len())
        .flat_map(|i| {
            let p = g.point_of(i);
            sh_from_rgb([0.5 + p.x, 0.5 + p.y, 0.5 - p.z], p.x * 20.0 + p.z * 7.0)
        })
        .collect();
    f.appearance = Appearance::Sh2(ChannelGrid::dense(g, 27, data));
    f
}

#[test]
fn gpu_matches_cpu_with_sh_appearance_softplus_density_and_two_fields() {
    if skip() {
        return;
    }
    let (d, cam) = demo();
    let mug = Arc::new(d.labels.mask(d.labels.label_of("mug").unwrap()));
    let table = Arc::new(sparse_sh(&d.field));
    let ball = Arc::new(softplus_sh_ball());
    let mut r = HeadlessRenderer::new(W, H).unwrap();

    // The mug removed from the SH tabletop, and a second field (softplus,
    // dense SH) placed, rotated and scaled on the table.
    let mut rest = Layer::new(table.clone());
    rest.mask = Mask::Remove(mug.clone());
    let mut other = Layer::new(ball);
    let g = table.geom();
    let (lo, hi) = mug.bounding_box().unwrap();
    let mug_centre = 0.5 * (g.point(lo[0], lo[1], lo[2]) + g.point(hi[0], hi[1], hi[2]));
    other.to_world =
        Affine3A::from_scale_rotation_translation(Vec3::splat(0.5), Quat::from_rotation_x(0.4), mug_centre);
    let comp = Scene::new(vec![rest.clone(), other]);
    // The ball is in view where the mug was.
    let seen = psnr(&cpu(&comp, &cam), &cpu(&Scene::new(vec![rest]), &cam));
    assert!(
        seen < 40.0,
        "the ball is not in view (PSNR {seen:.1} dB against the scene without it)"
    );
    for (name, scene) in [
        ("sparse SH tabletop", Scene::single(table.clone())),
        ("SH tabletop, mug removed, + softplus SH ball", comp),
    ] {
        let gpu = r.render(Arc::new(scene.clone()), &cam).unwrap();
        let want = cpu(&scene, &cam);
        let p = psnr(&gpu, &want);
        eprintln!("{name} at {W}x{H}: PSNR {p:.2} dB");
        assert!(p >= MIN_PSNR, "{name}: PSNR {p:.2} dB < {MIN_PSNR}");
    }
}

#[test]
fn a_removed_object_leaves_no_shell_on_the_gpu() {
    if skip() {
        return;
    }
    let (field, mug, cam) = demo_mug();
    let mut removed = Layer::new(field.clone());
    removed.mask = Mask::Remove(mug.clone());
    let scene = Scene::new(vec![removed]);
    let mut r = HeadlessRenderer::new(W, H).unwrap();
    let gpu = r.render(Arc::new(scene.clone()), &cam).unwrap();
    let want = cpu(&scene, &cam);
    let p = psnr(&gpu, &want);
    eprintln!("mug removed at {W}x{H}: PSNR {p:.2} dB");
    assert!(p >= MIN_PSNR, "removal PSNR {p:.2} dB < {MIN_PSNR}");
    // Only the object's layer: what remains is exactly the mug.
    let mut keep = Layer::new(field);
    keep.mask = Mask::Keep(mug);
    let only = Scene::new(vec![keep]);
    let gpu = r.render(Arc::new(only.clone()), &cam).unwrap();
    let p = psnr(&gpu, &cpu(&only, &cam));
    eprintln!("mug alone at {W}x{H}: PSNR {p:.2} dB");
    assert!(p >= MIN_PSNR, "keep PSNR {p:.2} dB < {MIN_PSNR}");
}

/// `isrf run --gpu`: the same script's render frames drawn by the GPU ray
/// marcher (through `run_script_with`) match the CPU run's frames; the
/// mask export in the same script still comes from the CPU.
#[test]
fn scripts_render_on_the_gpu_like_on_the_cpu() {
    use isrf::app::headless::GpuFrames;
    use isrf::command::{
        run_script_with, CameraSource, Edit, FieldSource, Output, Script, StrokeSource, TransformSpec,
    };
    if skip() {
        return;
    }
    let load = Edit::LoadField {
        name: "room".into(),
        source: FieldSource::Demo {
            scene: "tabletop".into(),
            res: 48,
            seed: 3,
        },
        transform: None,
    };
    let render_cmd = |width, height| Output::Render {
        cameras: CameraSource::Orbit {
            center: [0.0, -0.2, 0.0],
            radius: 2.0,
            elevation_deg: 25.0,
            frames: 2,
            width,
            height,
            fov_deg: 50.0,
        },
        out: format!("frames_{width}").into(),
        downscale: 1,
        frames: None,
        depth: false,
        background: None,
    };
    let script = Script {
        commands: vec![
            load.into(),
            Edit::Stroke {
                object: "mug".into(),
                field: None,
                polarity: None,
                source: StrokeSource::Demo { object: "mug".into() },
            }
            .into(),
            Edit::Transform {
                object: "mug".into(),
                transform: TransformSpec::translation(Vec3::new(0.25, 0.0, 0.1)),
            }
            .into(),
            // Two frame sizes: the GPU renderer is rebuilt for the second.
            render_cmd(96, 72).into(),
            render_cmd(64, 48).into(),
        ],
    };
    let dir = tempfile::tempdir().unwrap();
    let (cpu_out, gpu_out) = (dir.path().join("cpu"), dir.path().join("gpu"));
    run_script_with(&script, dir.path(), &cpu_out, None, |_, _, _| {}).unwrap();
    let mut gpu = GpuFrames::default();
    run_script_with(&script, dir.path(), &gpu_out, Some(&mut gpu), |_, _, _| {}).unwrap();
    let mut compared = 0;
    for sub in ["frames_96", "frames_64"] {
        for e in std::fs::read_dir(cpu_out.join(sub)).unwrap() {
            let p = e.unwrap().path();
            let a = isrf::data::Image::load(&p).unwrap();
            let b = isrf::data::Image::load(&gpu_out.join(sub).join(p.file_name().unwrap())).unwrap();
            assert_eq!((a.width, a.height), (b.width, b.height));
            let px = |im: &isrf::data::Image| -> Vec<Vec3> {
                (0..im.height)
                    .flat_map(|y| (0..im.width).map(move |x| (x, y)))
                    .map(|(x, y)| Vec3::from(im.pixel(x, y)))
                    .collect()
            };
            let q = psnr(&px(&a), &px(&b));
            assert!(
                q >= MIN_PSNR,
                "{}: GPU frame is {q:.1} dB from the CPU one",
                p.display()
            );
            compared += 1;
        }
    }
    assert_eq!(compared, 4);
}

/// Selecting an object that sits in place tints it through a highlight
/// mask on its field's layer: one layer to march, and the same image as
/// splitting the object out into a tinted layer of its own (the rest
/// dimmed), which is exact by construction (densities σ·b and σ·(1 − b)).
#[test]
fn an_in_place_selection_tints_like_a_split_into_two_layers() {
    use isrf::app::gpu::pack::Overlay;
    if skip() {
        return;
    }
    let (field, mug, cam) = demo_mug();
    let mut r = HeadlessRenderer::new(W, H).unwrap();
    let plain = r.render(Arc::new(Scene::single(field.clone())), &cam).unwrap();

    r.set_overlay(vec![Overlay {
        highlight: true,
        dim: true,
        highlight_mask: Some(mug.clone()),
    }]);
    let one = r.render(Arc::new(Scene::single(field.clone())), &cam).unwrap();

    let mut rest = Layer::new(field.clone());
    rest.mask = Mask::Remove(mug.clone());
    let mut part = Layer::new(field.clone());
    part.mask = Mask::Keep(mug);
    r.set_overlay(vec![
        Overlay {
            dim: true,
            ..Default::default()
        },
        Overlay {
            highlight: true,
            ..Default::default()
        },
    ]);
    let two = r.render(Arc::new(Scene::new(vec![rest, part])), &cam).unwrap();
    let p = psnr(&one, &two);
    eprintln!("highlight mask vs split layers: PSNR {p:.2} dB");
    assert!(p >= MIN_PSNR, "highlight mask vs split: {p:.2} dB < {MIN_PSNR}");
    let tinted = psnr(&one, &plain);
    assert!(
        tinted < 30.0,
        "the overlay changed little: {tinted:.2} dB from the plain field"
    );
}

/// The march runs only when what it shows changes; a still view composites
/// the last march again, pixel for pixel. A half-resolution march (the
/// editor's while moving) is upsampled to a close image, and going back
/// to full resolution restores the exact one.
#[test]
fn still_views_reuse_the_march_and_half_resolution_is_close() {
    if skip() {
        return;
    }
    let (d, cam) = demo();
    let scene = Arc::new(Scene::single(Arc::new(d.field)));
    let mut r = HeadlessRenderer::new(W, H).unwrap();
    r.set_camera(&cam).unwrap();
    r.set_scene(scene.clone());
    r.wait_drawn().unwrap();
    let full = r.capture().unwrap();
    let (frames, marches) = r.frame_counts();
    for _ in 0..3 {
        r.step();
    }
    let (frames2, marches2) = r.frame_counts();
    assert!(frames2 >= frames + 3, "a still view is still drawn every frame");
    assert_eq!(marches2, marches, "a still view does not march again");
    assert_eq!(r.capture().unwrap(), full, "the composite shows the last march exactly");

    r.set_render_scale(0.5);
    r.set_camera(&cam).unwrap();
    r.wait_drawn().unwrap();
    let half = r.capture().unwrap();
    assert_eq!(r.frame_counts().1, marches + 1, "the new resolution marched once");
    let to_rgb = |b: &[u8]| -> Vec<Vec3> {
        b.chunks_exact(4)
            .map(|p| Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32) / 255.0)
            .collect()
    };
    let p = psnr(&to_rgb(&half), &to_rgb(&full));
    eprintln!("half-resolution march upsampled vs full: PSNR {p:.2} dB");
    assert!(half != full, "the half-resolution image is a different image");
    assert!(p >= 20.0, "half resolution is too far from full: {p:.2} dB");

    r.set_render_scale(1.0);
    r.set_camera(&cam).unwrap();
    r.wait_drawn().unwrap();
    assert_eq!(r.capture().unwrap(), full, "full resolution again: the same image");
}

/// A trained-sized field: 160³ grid points with dense SH colours (27 f16 per
/// point), as `isrf train` writes for lego. Uploaded as one buffer its
/// colours took 229 MB, over the 128 MiB storage binding most GPUs (and
/// lavapipe) allow: the editor quit with a validation error. Only occupied
/// bricks are uploaded now. The density is a hollow shell with a few
/// thin rods, so that most of the box is empty, as in a real capture.
fn big_sh_field() -> Field {
    let n = 160;
    let b = FieldBuilder {
        geom: GridGeom::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [n, n, n]),
        activation: Activation::Softplus { shift: -4.0 },
    };
    let mut f = b.build(
        |p| {
            let shell = 0.04 - (p.length() - 0.6).abs();
            let rod = 0.03 - Vec3::new(p.x - 0.2, 0.0, p.z + 0.1).length();
            150.0 * shell.max(rod).max(-0.08)
        },
        |_| Vec3::ONE,
        None,
    );
    let g = f.geom();
    let data: Vec<half::f16> = (0..g.len())
        .flat_map(|i| {
            let p = g.point_of(i);
            sh_from_rgb(
                [0.5 + 0.4 * p.x, 0.5 + 0.4 * p.y, 0.5 - 0.4 * p.z],
                p.x * 9.0 + p.y * 4.0,
            )
        })
        .collect();
    f.appearance = Appearance::Sh2(ChannelGrid::dense(g, 27, data));
    f
}

#[test]
fn a_field_larger_than_one_storage_binding_draws_like_the_cpu() {
    if skip() {
        return;
    }
    let field = Arc::new(big_sh_field());
    let dense_colour_bytes = 160usize.pow(3) * 27 * 2;
    assert!(dense_colour_bytes > 128 << 20);
    let cam = Camera::look_at(
        Intrinsics::from_fov_x(W, H, 50f32.to_radians()),
        Vec3::new(0.6, 0.9, 2.6),
        Vec3::ZERO,
        Vec3::Y,
    );
    let scene = Scene::single(field.clone());
    let mut r = HeadlessRenderer::new(W, H).unwrap();
    let gpu = r.render(Arc::new(scene.clone()), &cam).unwrap();
    let want = cpu(&scene, &cam);
    let p = psnr(&gpu, &want);
    let status = r.render_status();
    eprintln!(
        "160³ dense-SH field at {W}x{H}: PSNR {p:.2} dB; pool {} MB (dense colours {} MB)",
        status.pool_bytes >> 20,
        dense_colour_bytes >> 20
    );
    assert!(p >= MIN_PSNR, "PSNR {p:.2} dB < {MIN_PSNR}");
    assert_eq!(status.stride, 1, "shown at full detail");
    assert!(status.detail.is_none());
    // What is uploaded scales with the occupied shell, not with the box.
    assert!(
        status.pool_bytes < dense_colour_bytes / 3,
        "pool {} MB",
        status.pool_bytes >> 20
    );
    let bg = want.iter().filter(|c| (**c - Vec3::ONE).length() < 1e-3).count();
    assert!(bg < want.len() * 9 / 10, "the view shows mostly background");
}

#[test]
fn a_scene_over_the_memory_budget_shows_a_coarser_level_of_detail() {
    if skip() {
        return;
    }
    let (field, mug, cam) = demo_mug();
    let mut rest = Layer::new(field.clone());
    rest.mask = Mask::Remove(mug.clone());
    let mut moved = Layer::new(field.clone());
    moved.mask = Mask::Keep(mug);
    moved.to_world = Affine3A::from_translation(Vec3::new(0.2, 0.0, 0.15));
    let scene = Arc::new(Scene::new(vec![rest, moved]));
    let mut r = HeadlessRenderer::new(W, H).unwrap();
    let full = r.render(scene.clone(), &cam).unwrap();
    let full_bytes = r.render_status().pool_bytes;
    assert_eq!(r.render_status().stride, 1);
    // Half of what full detail needs: the view falls back to every 2nd
    // grid point, says so, and still draws the scene (with its masks).
    r.set_memory_budget(full_bytes / 2);
    let coarse = r.render(scene.clone(), &cam).unwrap();
    let status = r.render_status();
    eprintln!(
        "budget {} KB: stride {}, pool {} KB, {:?}",
        full_bytes / 2048,
        status.stride,
        status.pool_bytes >> 10,
        status.detail
    );
    assert_eq!(status.stride, 2);
    assert!(status.pool_bytes <= full_bytes / 2);
    assert!(
        status.detail.as_deref().is_some_and(|d| d.contains("1/2")),
        "{:?}",
        status.detail
    );
    let p = psnr(&coarse, &full);
    eprintln!("coarse vs full detail: PSNR {p:.2} dB");
    // (Seen: 18.7 dB on lavapipe, the same scene with thicker parts.)
    assert!(
        (15.0..45.0).contains(&p),
        "the coarse image is close to, not equal to, the full one: {p:.2} dB"
    );
    // A budget too small for any level of detail: a clear error, no panic,
    // and the renderer keeps working once the budget is back.
    r.set_memory_budget(1024);
    let e = r.render(scene.clone(), &cam).unwrap_err();
    assert!(e.to_string().contains("does not fit"), "{e}");
    r.set_memory_budget(full_bytes);
    let again = r.render(scene, &cam).unwrap();
    assert!(psnr(&again, &full) > 60.0);
}

/// Large grids in the editor's path: the 320³ tabletop (the paper's grid
/// size, loaded by the session as a demo) and a flat 512 × 512 × 128
/// tabletop (loaded from its file, stroked inline); each gets a stroke, a
/// move and two undos, every state drawn by the GPU view and checked
/// against the CPU renderer; undoing brings back the first image.
#[test]
fn large_grids_stroke_move_and_undo_on_the_gpu() {
    if skip() {
        return;
    }
    use isrf::command::{Edit, FieldSource, StrokeSource};
    use isrf::segment::stroke::{CameraDoc, StrokeDoc};
    let demo = |res: usize| Edit::LoadField {
        name: "tabletop".into(),
        source: FieldSource::Demo {
            scene: "tabletop".into(),
            res,
            seed: 0,
        },
        transform: None,
    };
    let mug = |source| Edit::Stroke {
        object: "mug".into(),
        field: None,
        polarity: None,
        source,
    };
    stroke_move_undo("320³", demo(320), mug(StrokeSource::Demo { object: "mug".into() }));

    let d = isrf::demo::build_grid("tabletop", [512, 512, 128], 0).unwrap();
    let dir = tempfile::tempdir().unwrap();
    d.write(dir.path()).unwrap();
    let doc = StrokeDoc {
        camera: CameraDoc::from_camera(&d.stroke_camera),
        points: d
            .stroke_pixels(d.object("mug").unwrap())
            .iter()
            .map(|p| [p[0] as f32, p[1] as f32])
            .collect(),
        radius: 3,
        polarity: Default::default(),
        object: "mug".into(),
    };
    drop(d);
    let load = Edit::LoadField {
        name: "tabletop".into(),
        source: FieldSource::File(dir.path().join("field.safetensors")),
        transform: None,
    };
    stroke_move_undo("512×512×128", load, mug(StrokeSource::Inline(doc)));
}

fn stroke_move_undo(what: &str, load: isrf::command::Edit, stroke: isrf::command::Edit) {
    use isrf::app::layers::{build_scene, OverlayMode};
    use isrf::command::{Edit, Session, TransformSpec};
    let mut s = Session::default();
    s.apply(&load).unwrap();
    let field = s.state().fields[0].field.clone();
    eprintln!("{what}: grid {:?}", field.res());
    let (d, _) = demo();
    let c2w = d.cameras.frames[2].camera.c2w;
    let cam = Camera::new(Intrinsics::from_fov_x(W, H, 42f32.to_radians()), c2w);
    let mode = OverlayMode {
        tint_selected: false,
        dim_others: false,
    };
    let mut r = HeadlessRenderer::new(W, H).unwrap();
    let mut draw = |s: &Session, state: &str| {
        let (scene, _) = build_scene(s.state(), &[], None, mode);
        let gpu = r.render(Arc::new(scene.clone()), &cam).unwrap();
        let p = psnr(&gpu, &cpu(&scene, &cam));
        let status = r.render_status();
        eprintln!(
            "{what} {state}: GPU vs CPU {p:.2} dB, pool {} MB, stride {}",
            status.pool_bytes >> 20,
            status.stride
        );
        assert!(p >= MIN_PSNR, "{what} {state}: PSNR {p:.2} dB < {MIN_PSNR}");
        assert_eq!(status.stride, 1, "{what}: shown at full detail");
        gpu
    };
    let first = draw(&s, "field");
    s.apply(&stroke).unwrap();
    let mv = Edit::Transform {
        object: "mug".into(),
        transform: TransformSpec::translation(Vec3::new(0.3, 0.0, 0.2)),
    };
    s.apply(&mv).unwrap();
    let moved = draw(&s, "mug moved");
    assert!(psnr(&first, &moved) < 40.0, "{what}: the move changed nothing");
    assert!(s.undo().is_some() && s.undo().is_some());
    let back = draw(&s, "after two undos");
    assert!(psnr(&first, &back) > 60.0, "{what}: undo did not restore the view");
}
