//! The WGSL ray marcher computes the CPU reference renderer's image: the demo
//! tabletop and a composition with a moved, masked, recoloured object, at
//! 160×120, PSNR ≥ 35 dB. Skips (with a message) where no GPU adapter exists.
#![cfg(feature = "editor")]

use glam::{Affine3A, Quat, Vec3};
use isrf::app::headless::{gpu_available, HeadlessRenderer};
use isrf::camera::{Camera, Intrinsics};
use isrf::render::{render, ColorEdit, Layer, Mask, RenderOptions, Scene};
use std::sync::Arc;

const W: u32 = 160;
const H: u32 = 120;

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
    assert!(p >= 35.0, "tabletop PSNR {p:.2} dB < 35");
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
    assert!(p2 >= 35.0, "composition PSNR {p2:.2} dB < 35");
    // The composition differs from the plain field (the edit is visible).
    assert!(psnr(&want, &want2) < 40.0, "moving the mug changed nothing");
}
