//! `isrf train` from the command line on a tiny Blender-layout capture: the
//! held-out preview it writes while training.

use glam::Vec3;
use isrf::camera::{CameraSet, Intrinsics};
use std::path::Path;
use std::process::Command;

/// A patterned RGB image (no alpha, so the photo is the training target as is).
fn pattern(w: u32, h: u32, seed: u32) -> image::RgbImage {
    image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([(x * 20 + seed * 7) as u8, (y * 30) as u8, ((x ^ y) * 9 + seed) as u8])
    })
}

/// Train (6 views) and val (1 view) splits around the origin, 12×10 pixels.
fn blender_capture(root: &Path) -> image::RgbImage {
    let orbit = |n| CameraSet::orbit(Intrinsics::from_fov_x(12, 10, 0.8), Vec3::ZERO, 3.0, 0.3, n);
    let mut val_image = None;
    for (split, n) in [("train", 6), ("val", 1)] {
        let mut cams = orbit(n);
        for (i, f) in cams.frames.iter_mut().enumerate() {
            f.name = format!("./{split}/r_{i}");
            let img = pattern(12, 10, i as u32 + if split == "val" { 50 } else { 0 });
            std::fs::create_dir_all(root.join(split)).unwrap();
            img.save(root.join(format!("{split}/r_{i}.png"))).unwrap();
            val_image = Some(img);
        }
        cams.save(&root.join(format!("transforms_{split}.json"))).unwrap();
    }
    val_image.unwrap()
}

#[test]
fn training_writes_a_preview_of_a_held_out_view() {
    let dir = tempfile::tempdir().unwrap();
    let photo = blender_capture(dir.path());
    let out = dir.path().join("f.safetensors");
    let run = Command::new(env!("CARGO_BIN_EXE_isrf"))
        .arg("train")
        .arg(dir.path())
        .args(["--iters", "30", "--res", "16", "--batch", "256", "--feature-iters", "0"])
        .args(["--eval-every", "10"])
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "isrf train failed:\n{stderr}");
    let preview_path = dir.path().join("f.preview.png");
    assert!(
        stderr.contains("f.preview.png"),
        "the preview path is announced:\n{stderr}"
    );
    let preview = image::open(&preview_path).unwrap().to_rgb8();
    // The render on the left, the held-out photo on the right, pixel for pixel.
    assert_eq!(preview.dimensions(), (24, 10));
    for y in 0..10 {
        for x in 0..12 {
            assert_eq!(
                preview.get_pixel(12 + x, y),
                photo.get_pixel(x, y),
                "photo pixel ({x}, {y})"
            );
        }
    }
    // The left half is the field's render, not a copy of the photo.
    let differs = (0..10).any(|y| (0..12).any(|x| preview.get_pixel(x, y) != photo.get_pixel(x, y)));
    assert!(
        differs,
        "after 30 iterations the render should not equal the photo exactly"
    );
}
