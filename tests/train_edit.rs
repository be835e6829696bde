//! Train → edit, as a user does it: `isrf train` on a real capture (the
//! NeRF-synthetic lego, a few hundred iterations, at the default grid size so
//! that the GPU view gets buffers as large as a user's field), then the
//! written field opened in the editor's GPU view, headless on lavapipe, and
//! compared with the CPU reference renderer from one of the capture's own
//! cameras. Skips (with a message) without the capture or a GPU adapter.
#![cfg(feature = "editor")]

use glam::Vec3;
use isrf::app::headless::{gpu_available, HeadlessRenderer};
use isrf::camera::{Camera, CameraSet, Intrinsics};
use isrf::render::{render, RenderOptions, Scene};
use std::path::Path;
use std::process::Command;
use std::sync::Arc;

fn psnr(a: &[Vec3], b: &[Vec3]) -> f64 {
    let mse: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (*x - *y).length_squared() as f64 / 3.0)
        .sum::<f64>()
        / a.len() as f64;
    10.0 * (1.0 / mse.max(1e-12)).log10()
}

#[test]
fn a_field_isrf_train_writes_opens_in_the_gpu_view() {
    let lego = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/nerf_synthetic/lego");
    if !lego.join("transforms_train.json").exists() || !gpu_available() {
        eprintln!("skipping: needs ../shared/data/nerf_synthetic/lego and a GPU adapter (mesa-vulkan-drivers)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("lego.safetensors");
    // Colour and density only (no teacher): the GPU view draws those.
    let run = Command::new(env!("CARGO_BIN_EXE_isrf"))
        .args(["train", lego.to_str().unwrap(), "--downscale", "8", "--iters", "300"])
        .args([
            "--feature-iters",
            "0",
            "--eval-every",
            "100000",
            "--out",
            out.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "isrf train failed:\n{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let field = Arc::new(isrf::field::io::load(&out).unwrap());
    let res = field.res();
    eprintln!("trained field {res:?}, {} MB in memory", field.memory_bytes() >> 20);
    assert!(res.iter().max().unwrap() >= &128, "default-sized grid, got {res:?}");

    // A training camera (Blender: plain pinhole) at a small size.
    let cams = CameraSet::load(&dir.path().join("lego.cameras.json")).unwrap();
    let c = cams.frames[0].camera;
    let (w, h) = (160u32, 160u32);
    let fov = 2.0 * (0.5 * c.intrinsics.width as f32 / c.intrinsics.fx).atan();
    let cam = Camera::new(Intrinsics::from_fov_x(w, h, fov), c.c2w);

    let scene = Scene::single(field.clone());
    let mut r = HeadlessRenderer::new(w, h).unwrap();
    let gpu = r.render(Arc::new(scene.clone()), &cam).unwrap();
    let want: Vec<Vec3> = render(&scene, &cam, &RenderOptions::default())
        .unwrap()
        .out
        .color
        .iter()
        .map(|c| (c.clamp(Vec3::ZERO, Vec3::ONE) * 255.0).round() / 255.0)
        .collect();
    let p = psnr(&gpu, &want);
    let status = r.render_status();
    eprintln!(
        "GPU view vs CPU renderer: PSNR {p:.2} dB; pool {} MB, stride {}",
        status.pool_bytes >> 20,
        status.stride
    );
    assert!(p >= 35.0, "PSNR {p:.2} dB < 35");
    assert_eq!(status.stride, 1);
    // The lego is in view (not only the white background).
    let fg = want.iter().filter(|c| (**c - Vec3::ONE).length() > 0.1).count();
    assert!(fg > want.len() / 20, "only {fg} foreground pixels");
}
