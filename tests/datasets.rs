//! Datasets with images: kind detection, the four loaders, compositing,
//! downscaling, splits and errors.

use glam::Vec3;
use isrf::camera::{CameraSet, Intrinsics};
use isrf::data::{Dataset, DatasetKind, Image, LoadOptions, Split};
use std::path::{Path, PathBuf};

fn data_dir(sub: &str) -> Option<PathBuf> {
    let d = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data").join(sub);
    if d.is_dir() {
        Some(d)
    } else {
        eprintln!("SKIPPED: {} is absent (real captures not available)", d.display());
        None
    }
}

fn opts() -> LoadOptions {
    LoadOptions::default()
}

// ---------------------------------------------------------------- real data

#[test]
fn detect_real_layouts() {
    let Some(d) = data_dir("") else { return };
    assert_eq!(
        Dataset::detect(&d.join("nerf_synthetic/lego")).unwrap(),
        DatasetKind::Blender
    );
    assert_eq!(
        Dataset::detect(&d.join("nerf_synthetic/lego/transforms_val.json")).unwrap(),
        DatasetKind::Blender
    );
    // fern has both poses_bounds.npy and a COLMAP folder: LLFF wins.
    assert_eq!(Dataset::detect(&d.join("llff/fern")).unwrap(), DatasetKind::Llff);
    assert_eq!(
        Dataset::detect(&d.join("llff/fern/sparse/0")).unwrap(),
        DatasetKind::Colmap
    );
}

#[test]
fn lego_val_downscaled() {
    let Some(d) = data_dir("nerf_synthetic/lego") else {
        return;
    };
    let o = LoadOptions {
        splits: Some(vec![Split::Val]),
        downscale: 8,
        ..opts()
    };
    let ds = Dataset::load(&d, &o).unwrap();
    assert_eq!(ds.kind, DatasetKind::Blender);
    assert_eq!(ds.len(), 100);
    assert_eq!(ds.indices(Split::Val).len(), 100);
    assert!(ds.indices(Split::Train).is_empty());
    let focal = 0.5 * 800.0 / (0.5f32 * 0.6911112).tan() / 8.0;
    for (cam, img) in ds.cameras.frames.iter().zip(&ds.images) {
        let k = cam.camera.intrinsics;
        assert_eq!((k.width, k.height), (100, 100));
        assert_eq!((img.width, img.height), (100, 100));
        assert!((k.fx - focal).abs() < 1e-3, "{} vs {focal}", k.fx);
        assert_eq!(img.rgb.len(), 3 * 100 * 100);
        let alpha = img.alpha.as_ref().expect("lego keeps its alpha mask");
        // Fully transparent pixels show the (white) background.
        let mut bg = 0;
        for (i, &a) in alpha.iter().enumerate() {
            assert!((0.0..=1.0).contains(&a));
            if a == 0.0 {
                bg += 1;
                assert_eq!(&img.rgb[3 * i..3 * i + 3], &[1.0, 1.0, 1.0]);
            }
        }
        // The object covers part of the view, never all of it.
        assert!(bg > 1000 && bg < 9900, "{bg} background pixels");
    }
    assert_eq!(ds.image_paths[0], d.join("./val/r_0.png"));
    assert!(ds.notes.is_empty());
}

#[test]
fn fern_llff_dataset() {
    let Some(d) = data_dir("llff/fern") else { return };
    let ds = Dataset::load(&d, &opts()).unwrap();
    assert_eq!(ds.kind, DatasetKind::Llff);
    assert_eq!(ds.len(), 20);
    assert_eq!(ds.indices(Split::Test), vec![0, 8, 16]);
    assert_eq!(ds.indices(Split::Train).len(), 17);
    for (cam, img) in ds.cameras.frames.iter().zip(&ds.images) {
        let k = cam.camera.intrinsics;
        assert_eq!((img.width, img.height, k.width, k.height), (504, 378, 504, 378));
        assert!(cam.camera.ndc.is_some(), "NDC by default for LLFF");
        assert!(img.alpha.is_none());
        assert!(img.rgb.iter().all(|v| (0.0..=1.0).contains(v)));
    }
    assert!(ds.image_paths.windows(2).all(|w| w[0] < w[1]), "sorted file names");
    assert!(ds.image_paths[12].ends_with("images_8/image012.png"));
    assert!(ds.normalization.is_some());
    assert_eq!(ds.near_far.as_ref().map(Vec::len), Some(20));
    // A green-ish fern: mean green above mean blue.
    let img = &ds.images[0];
    let mean = |c: usize| img.rgb.iter().skip(c).step_by(3).sum::<f32>() / img.len() as f32;
    assert!(mean(1) > mean(2), "green {} blue {}", mean(1), mean(2));

    // Only the test views, world rays.
    let o = LoadOptions {
        splits: Some(vec![Split::Test]),
        llff_ndc: false,
        ..opts()
    };
    let test = Dataset::load(&d, &o).unwrap();
    assert_eq!(test.len(), 3);
    assert_eq!(test.images[1], ds.images[8]);
    assert_eq!(test.near_far.as_ref().unwrap()[2], ds.near_far.as_ref().unwrap()[16]);
    assert!(test.cameras.frames[0].camera.ndc.is_none());
}

#[test]
fn fern_factors_and_folder_fallback() {
    let Some(d) = data_dir("llff/fern") else { return };
    let o16 = LoadOptions {
        llff_factor: 16,
        splits: Some(vec![Split::Test]),
        ..opts()
    };
    let ds16 = Dataset::load(&d, &o16).unwrap();
    assert_eq!((ds16.images[0].width, ds16.images[0].height), (252, 189));
    assert!(ds16.image_paths[0].ends_with("images_16/IMG_4026.png"));
    // No images_32: images_16 box-downscaled by 2, as its cameras.
    let o32 = LoadOptions { llff_factor: 32, ..o16 };
    let ds32 = Dataset::load(&d, &o32).unwrap();
    let k = ds32.cameras.frames[0].camera.intrinsics;
    assert_eq!((ds32.images[0].width, ds32.images[0].height), (126, 94));
    assert_eq!((k.width, k.height), (126, 94));
    assert!((k.fx - 3260.526 / 32.0).abs() < 1e-3);
    assert_eq!(ds32.images[0], ds16.images[0].downscaled(2));
    assert!(ds32.notes.iter().any(|n| n.contains("images_32")), "{:?}", ds32.notes);
}

#[test]
fn fern_as_colmap_names_the_missing_file() {
    let Some(d) = data_dir("llff/fern") else { return };
    let err = Dataset::load_kind(DatasetKind::Colmap, &d, &opts())
        .unwrap_err()
        .to_string();
    assert!(err.contains("images.bin") && err.contains("missing"), "{err}");
}

// ------------------------------------------------------------ images

#[test]
fn composite_and_box_downscale() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("a.png");
    let mut png = image::RgbaImage::new(4, 2);
    for (x, y, p) in png.enumerate_pixels_mut() {
        *p = image::Rgba([255, (x * 60) as u8, 0, if y == 0 { 255 } else { 51 }]);
    }
    png.save(&path).unwrap();
    let mut img = Image::load(&path).unwrap();
    assert_eq!((img.width, img.height, img.len()), (4, 2, 8));
    let close = |a: [f32; 3], b: [f32; 3]| a.iter().zip(b).all(|(a, b)| (a - b).abs() < 1e-6);
    assert!(close(img.pixel(2, 0), [1.0, 120.0 / 255.0, 0.0]));
    img.composite([0.0, 0.0, 1.0]);
    // rgb·α + bg·(1 − α) with α = 0.2 on the second row.
    let p = img.pixel(1, 1);
    let want = [0.2, 60.0 / 255.0 * 0.2, 0.8];
    assert!(close(p, want), "{p:?}");
    assert!(close(img.pixel(3, 0), [1.0, 180.0 / 255.0, 0.0]));

    let half = img.downscaled(2);
    assert_eq!((half.width, half.height), (2, 1));
    // Block (0..2, 0..2): mean of the four composited pixels.
    let g = (0.0 + 60.0 + 0.2 * 0.0 + 0.2 * 60.0) / 4.0 / 255.0;
    let want = [(1.0 + 1.0 + 0.2 + 0.2) / 4.0, g, (0.0 + 0.0 + 0.8 + 0.8) / 4.0];
    assert!(close(half.pixel(0, 0), want), "{:?}", half.pixel(0, 0));
    let alpha = half.alpha.as_ref().unwrap();
    assert!(
        alpha.len() == 2 && alpha.iter().all(|a| (a - 0.6).abs() < 1e-6),
        "{alpha:?}"
    );
    // Leftover rows and columns are dropped, as Intrinsics::downscaled does.
    assert_eq!((img.downscaled(3).width, img.downscaled(3).height), (1, 1));
    assert_eq!(img.downscaled(1), img);

    // PNG round trip at 8 bits.
    let out = tmp.path().join("out.png");
    half.save_png(&out).unwrap();
    let back = Image::load(&out).unwrap();
    assert!(back
        .rgb
        .iter()
        .zip(&half.rgb)
        .all(|(a, b)| (a - b).abs() <= 0.5 / 255.0 + 1e-6));

    let bad = tmp.path().join("bad.png");
    std::fs::write(&bad, b"not a png").unwrap();
    let err = Image::load(&bad).unwrap_err().to_string();
    assert!(err.contains("bad.png") && err.contains("decode"), "{err}");
}

// ---------------------------------------------------- synthetic layouts

/// A tiny RGB(A) PNG with a per-image colour.
fn write_png(path: &Path, w: u32, h: u32, v: u8, alpha: bool) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    if alpha {
        image::RgbaImage::from_pixel(w, h, image::Rgba([v, 0, 0, 255]))
            .save(path)
            .unwrap();
    } else {
        image::RgbImage::from_pixel(w, h, image::Rgb([v, 10, 20]))
            .save(path)
            .unwrap();
    }
}

fn orbit(n: usize, w: u32, h: u32) -> CameraSet {
    CameraSet::orbit(Intrinsics::from_fov_x(w, h, 0.8), Vec3::ZERO, 3.0, 0.3, n)
}

/// A Blender folder: train (4 frames) and test (2 frames, images absent).
fn blender_folder(root: &Path) {
    let mut train = orbit(4, 8, 6);
    for (i, f) in train.frames.iter_mut().enumerate() {
        f.name = format!("./train/r_{i}");
        write_png(&root.join(format!("train/r_{i}.png")), 8, 6, 50 * i as u8, true);
    }
    train.save(&root.join("transforms_train.json")).unwrap();
    let mut test = orbit(2, 8, 6);
    test.frames
        .iter_mut()
        .enumerate()
        .for_each(|(i, f)| f.name = format!("./test/r_{i}"));
    test.save(&root.join("transforms_test.json")).unwrap();
}

#[test]
fn blender_splits_and_skips() {
    let tmp = tempfile::tempdir().unwrap();
    blender_folder(tmp.path());
    assert_eq!(Dataset::detect(tmp.path()).unwrap(), DatasetKind::Blender);
    let ds = Dataset::load(tmp.path(), &opts()).unwrap();
    assert_eq!(ds.len(), 4);
    assert_eq!(ds.splits, vec![Split::Train; 4]);
    assert!(ds
        .notes
        .iter()
        .any(|n| n.contains("transforms_test.json") && n.contains("skipped")));
    assert!((ds.images[2].pixel(0, 0)[0] - 100.0 / 255.0).abs() < 1e-6);
    // Asking for the test split explicitly: its missing images are an error.
    let o = LoadOptions {
        splits: Some(vec![Split::Test]),
        ..opts()
    };
    let err = Dataset::load(tmp.path(), &o).unwrap_err().to_string();
    assert!(err.contains("r_0") && err.contains("missing image"), "{err}");
    // Asking for a split with no JSON names the file.
    let o = LoadOptions {
        splits: Some(vec![Split::Val]),
        ..opts()
    };
    let err = Dataset::load(tmp.path(), &o).unwrap_err().to_string();
    assert!(err.contains("transforms_val.json"), "{err}");
    // One image missing among present ones: an error naming it.
    std::fs::remove_file(tmp.path().join("train/r_2.png")).unwrap();
    let err = Dataset::load(tmp.path(), &opts()).unwrap_err().to_string();
    assert!(err.contains("r_2") && err.contains("transforms_train.json"), "{err}");
}

#[test]
fn image_size_must_match_camera() {
    let tmp = tempfile::tempdir().unwrap();
    blender_folder(tmp.path());
    write_png(&tmp.path().join("train/r_1.png"), 4, 3, 0, true);
    let err = Dataset::load(tmp.path(), &opts()).unwrap_err().to_string();
    assert!(
        err.contains("r_1.png") && err.contains("4×3") && err.contains("8×6"),
        "{err}"
    );
}

#[test]
fn nerfstudio_dataset() {
    let tmp = tempfile::tempdir().unwrap();
    let mut set = orbit(10, 16, 12);
    for (i, f) in set.frames.iter_mut().enumerate() {
        f.name = format!("images/frame_{i:05}.png");
        write_png(&tmp.path().join(&f.name), 16, 12, i as u8, false);
    }
    set.save(&tmp.path().join("transforms.json")).unwrap();
    assert_eq!(Dataset::detect(tmp.path()).unwrap(), DatasetKind::Nerfstudio);
    let o = LoadOptions { downscale: 2, ..opts() };
    let ds = Dataset::load(&tmp.path().join("transforms.json"), &o).unwrap();
    assert_eq!(ds.kind, DatasetKind::Nerfstudio);
    assert_eq!(ds.indices(Split::Test), vec![0, 8]);
    assert_eq!(ds.cameras.frames[3].camera, set.frames[3].camera.downscaled(2));
    assert_eq!((ds.images[3].width, ds.images[3].height), (8, 6));
    let p = ds.images[3].pixel(1, 1);
    assert!(
        (p[0] - 3.0 / 255.0).abs() < 1e-6 && (p[2] - 20.0 / 255.0).abs() < 1e-6,
        "{p:?}"
    );

    std::fs::remove_file(tmp.path().join("images/frame_00004.png")).unwrap();
    let err = Dataset::load(tmp.path(), &o).unwrap_err().to_string();
    assert!(err.contains("frame_00004.png") && err.contains("frame 4"), "{err}");
}

#[test]
fn colmap_dataset() {
    let tmp = tempfile::tempdir().unwrap();
    let sparse = tmp.path().join("sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    std::fs::write(sparse.join("cameras.txt"), "1 PINHOLE 8 6 7 7 4 3\n").unwrap();
    // Identity world-to-camera poses shifted along x; names out of order.
    let mut lines = String::new();
    for (id, name) in [(1, "b.png"), (2, "a.png"), (3, "c.png")] {
        lines += &format!("{id} 1 0 0 0 {id} 0 0 1 {name}\n\n");
        write_png(&tmp.path().join("images").join(name), 8, 6, id as u8, false);
    }
    std::fs::write(sparse.join("images.txt"), lines).unwrap();
    assert_eq!(Dataset::detect(tmp.path()).unwrap(), DatasetKind::Colmap);
    let o = LoadOptions {
        holdout_every: 2,
        ..opts()
    };
    let ds = Dataset::load(tmp.path(), &o).unwrap();
    let names: Vec<_> = ds.cameras.frames.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, ["a.png", "b.png", "c.png"]);
    assert_eq!(ds.splits, vec![Split::Test, Split::Train, Split::Test]);
    // a.png is image 2: camera centre −Rᵀt = (−2, 0, 0); OpenCV +z is OpenGL −z.
    assert_eq!(ds.cameras.frames[0].camera.position(), Vec3::new(-2.0, 0.0, 0.0));
    assert_eq!(ds.cameras.frames[0].camera.forward(), Vec3::Z);
    assert!((ds.images[0].pixel(0, 0)[0] - 2.0 / 255.0).abs() < 1e-6);

    std::fs::remove_file(tmp.path().join("images/c.png")).unwrap();
    let err = Dataset::load(tmp.path(), &o).unwrap_err().to_string();
    assert!(err.contains("c.png") && err.contains("images.txt"), "{err}");
}

#[test]
fn llff_count_mismatch_and_detection_errors() {
    let Some(d) = data_dir("llff/fern") else { return };
    let tmp = tempfile::tempdir().unwrap();
    std::fs::copy(d.join("poses_bounds.npy"), tmp.path().join("poses_bounds.npy")).unwrap();
    for i in 0..3 {
        write_png(
            &tmp.path().join(format!("images_8/image{i:03}.png")),
            504,
            378,
            0,
            false,
        );
    }
    let err = Dataset::load(tmp.path(), &opts()).unwrap_err().to_string();
    assert!(
        err.contains("images_8") && err.contains("3 images") && err.contains("20 poses"),
        "{err}"
    );
    let o = LoadOptions {
        llff_factor: 3,
        ..opts()
    };
    let err = Dataset::load(tmp.path(), &o).unwrap_err().to_string();
    assert!(err.contains("images_3") && err.contains("missing"), "{err}");
}

#[test]
fn detection_errors_and_bad_options() {
    let tmp = tempfile::tempdir().unwrap();
    let err = Dataset::detect(tmp.path()).unwrap_err().to_string();
    assert!(err.contains("unrecognised dataset folder"), "{err}");
    let err = Dataset::detect(&tmp.path().join("absent")).unwrap_err();
    assert!(matches!(err, isrf::Error::Io { .. }));
    std::fs::write(tmp.path().join("notes.txt"), "x").unwrap();
    assert!(Dataset::detect(&tmp.path().join("notes.txt")).is_err());
    blender_folder(tmp.path());
    let o = LoadOptions { downscale: 0, ..opts() };
    assert!(Dataset::load(tmp.path(), &o)
        .unwrap_err()
        .to_string()
        .contains("downscale"));
    // Bad poses name the JSON file.
    let json = tmp.path().join("transforms_train.json");
    let text = std::fs::read_to_string(&json).unwrap().replacen(
        "\"transform_matrix\": [",
        "\"transform_matrix\": [[9,9,9,9],",
        1,
    );
    std::fs::write(&json, text).unwrap();
    let err = Dataset::load(tmp.path(), &opts()).unwrap_err().to_string();
    assert!(
        err.contains("transforms_train.json") && err.contains("frame 0"),
        "{err}"
    );
}

/// A PNG with a gradient and partial alpha, so that compositing and the box
/// filter both change its values.
fn write_gradient_png(path: &Path, w: u32, h: u32, seed: u8) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    image::RgbaImage::from_fn(w, h, |x, y| {
        image::Rgba([
            (x * 30) as u8 ^ seed,
            (y * 40) as u8,
            seed.wrapping_mul(7),
            (100 + 20 * x + y) as u8,
        ])
    })
    .save(path)
    .unwrap();
}

#[test]
fn deferred_views_read_later_equal_views_read_at_load() {
    let tmp = tempfile::tempdir().unwrap();
    blender_folder(tmp.path());
    let mut val = orbit(3, 8, 6);
    for (i, f) in val.frames.iter_mut().enumerate() {
        f.name = format!("./val/r_{i}");
        write_gradient_png(&tmp.path().join(format!("val/r_{i}.png")), 8, 6, 11 * i as u8);
    }
    val.save(&tmp.path().join("transforms_val.json")).unwrap();
    let eager = LoadOptions {
        downscale: 2,
        background: [0.2, 0.5, 0.9],
        splits: Some(vec![Split::Train, Split::Val]),
        ..opts()
    };
    let lazy = LoadOptions {
        deferred: vec![Split::Val],
        ..eager.clone()
    };
    let a = Dataset::load(tmp.path(), &eager).unwrap();
    let b = Dataset::load(tmp.path(), &lazy).unwrap();
    assert_eq!(a.len(), 7);
    for i in 0..a.len() {
        let deferred = b.splits[i] == Split::Val;
        assert_eq!(b.images[i].is_deferred(), deferred, "view {i}");
        assert_eq!(
            (b.images[i].width, b.images[i].height),
            (a.images[i].width, a.images[i].height)
        );
        let (pa, pb) = (a.pixels(i).unwrap(), b.pixels(i).unwrap());
        assert!(!pa.rgb.is_empty());
        assert_eq!(pa.rgb, pb.rgb, "view {i}: the same composited, downscaled colours");
        assert_eq!(pa.alpha, pb.alpha, "view {i}");
    }
    // A deferred photo of the wrong size is refused at load (header only).
    write_gradient_png(&tmp.path().join("val/r_1.png"), 4, 3, 0);
    let err = Dataset::load(tmp.path(), &lazy).unwrap_err().to_string();
    assert!(err.contains("r_1.png") && err.contains("4×3"), "{err}");
    // One that breaks after the load is an error naming it when read.
    write_gradient_png(&tmp.path().join("val/r_1.png"), 8, 6, 0);
    let b = Dataset::load(tmp.path(), &lazy).unwrap();
    std::fs::write(tmp.path().join("val/r_1.png"), b"not a png").unwrap();
    let i = (0..b.len())
        .find(|&i| b.image_paths[i].ends_with("val/r_1.png"))
        .unwrap();
    let err = b.pixels(i).unwrap_err().to_string();
    assert!(err.contains("r_1.png"), "{err}");
}
