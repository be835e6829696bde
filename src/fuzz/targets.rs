//! The fuzz targets: one per reader of user files, each with its seeds.
//!
//! Seeds come from two places: valid files written by the library's own
//! writers (so they follow the formats as they evolve) and the committed
//! corpus in `tests/fuzz_corpus/<target>/` (hand-written files and the
//! inputs that once broke a reader), compiled in so that the binary fuzzes
//! from anywhere.

use crate::camera::{Camera, CameraSet, Intrinsics};
use crate::command::state::Placement;
use crate::command::{composition, script, FieldSource, Session};
use crate::error::{Error, Result};
use crate::field::Bitmap;
use crate::segment::{load_strokes, scribble_stroke, stroke_pixels, Polarity};
use glam::{Affine3A, Vec3};
use std::path::Path;
use std::sync::{Arc, OnceLock};

/// One reader under test.
pub struct Target {
    pub name: &'static str,
    pub about: &'static str,
    /// The file each input is written to, in the target's work folder (its
    /// extension picks the format where readers go by extension).
    pub file: &'static str,
    /// Writes the other files the reader needs into the work folder and
    /// returns generated seed inputs.
    pub seeds: fn(&Path) -> Result<Vec<Vec<u8>>>,
    /// Committed seeds and regression inputs: (name, bytes).
    pub corpus: &'static [(&'static str, &'static [u8])],
    /// Reads the input file; `Err` is a fine outcome, a panic is a bug.
    pub run: fn(&Path) -> Result<()>,
}

/// `corpus!("llff", "a.npy", ...)`: files of `tests/fuzz_corpus/llff/`.
macro_rules! corpus {
    ($dir:literal $(, $file:literal)* $(,)?) => {
        &[$(($file, include_bytes!(concat!("../../tests/fuzz_corpus/", $dir, "/", $file)) as &[u8])),*]
    };
}

/// Every target, in the order `isrf fuzz --list` prints them.
pub static TARGETS: &[Target] = &[
    Target {
        name: "field",
        about: "field files (.safetensors): header, tensors, sparse grids",
        file: "input.safetensors",
        seeds: |_| Ok(vec![crate::field::io::to_bytes(&demo()?.field)?]),
        corpus: corpus!(
            "field",
            "field_load-panic-io477-feat_pe-2pow63.safetensors",
            "field_load-panic-io477-feat_pe-overflow-min.safetensors",
            "field_load-panic-io495-mlp-layers-overflow.safetensors",
        ),
        run: |p| crate::field::io::load(p).map(drop),
    },
    Target {
        name: "bitmap",
        about: "object bitmap files (.safetensors)",
        file: "input.safetensors",
        seeds: |_| {
            let bits = Bitmap::from_fn([9, 8, 7], |i| i % 3 == 0 || i % 7 == 1);
            Ok(vec![crate::segment::bitmap_file::bitmap_bytes(&bits, "mug")?])
        },
        corpus: &[],
        run: |p| crate::segment::bitmap_file::load_bitmap(p).map(drop),
    },
    Target {
        name: "checkpoint",
        about: "training checkpoints (.safetensors), read tensor by tensor",
        file: "input.safetensors",
        seeds: |dir| Ok(vec![checkpoint_seed(dir)?]),
        corpus: &[],
        run: |p| crate::train::checkpoint::load(p).map(drop),
    },
    Target {
        name: "labels",
        about: "demo ground-truth label grids (.safetensors)",
        file: "input.safetensors",
        seeds: |_| Ok(vec![demo()?.labels.to_bytes()?]),
        corpus: &[],
        run: |p| crate::demo::labels::Labels::load(p).map(drop),
    },
    Target {
        name: "composition-json",
        about: "composition documents (JSON) with their field and bitmaps",
        file: "input.json",
        seeds: |w| composition_seed(w, "json"),
        corpus: &[],
        run: |p| composition::load(p, &p.with_file_name("out")).map(drop),
    },
    Target {
        name: "composition-ron",
        about: "composition documents (RON) with their field and bitmaps",
        file: "input.ron",
        seeds: |w| composition_seed(w, "ron"),
        corpus: &[],
        run: |p| composition::load(p, &p.with_file_name("out")).map(drop),
    },
    Target {
        name: "script-json",
        about: "edit scripts (JSON), parsed and checked (the dry run)",
        file: "input.json",
        seeds: |w| script_seeds(w, "json"),
        corpus: &[],
        run: run_script_check,
    },
    Target {
        name: "script-ron",
        about: "edit scripts (RON), parsed and checked (the dry run)",
        file: "input.ron",
        seeds: |w| script_seeds(w, "ron"),
        corpus: &[],
        run: run_script_check,
    },
    Target {
        name: "strokes",
        about: "stroke documents (JSON), then the pixels each stroke covers",
        file: "input.json",
        seeds: |_| {
            Ok(vec![
                serde_json::to_vec_pretty(&demo()?.strokes_json()).map_err(invalid)?
            ])
        },
        corpus: corpus!(
            "strokes",
            "lego_r_0.json",
            "strokes-misleading-error-list.json",
            "strokes-misleading-error-wrapped.json",
            "stroke_pixels-RELEASE-hang-isrf-segment-demo.json",
            "stroke_pixels-fuzzer-found-panic-stroke_pixels-0bcfe923.json",
            "stroke_pixels-fuzzer-found-panic-stroke_pixels-64da856d.json",
            "stroke_pixels-fuzzer-found-panic-stroke_pixels-6affdf42.json",
            "stroke_pixels-fuzzer-found-panic-stroke_pixels-bf964d70.json",
            "stroke_pixels-hang-fuzzer-found-1370B.json",
            "stroke_pixels-hang-fuzzer-found-582B.json",
            "stroke_pixels-hang-min.json",
            "stroke_pixels-overflow-add-x-min.json",
            "stroke_pixels-overflow-add-y-min.json",
            "stroke_pixels-overflow-sub-x-min.json",
            "stroke_pixels-overflow-sub-y-min.json",
        ),
        run: |p| {
            for s in load_strokes(p)? {
                stroke_pixels(&s)?;
            }
            Ok(())
        },
    },
    Target {
        name: "splat-ply",
        about: "3D Gaussian splat .ply files, read and imported on a 16-point grid",
        file: "input.ply",
        seeds: |_| crate::splat::fuzz_seeds(),
        corpus: corpus!(
            "splat-ply",
            "normals-and-extra.ply",
            "huge-count.ply",
            "compressed-chunk.ply",
            "ascii.ply",
        ),
        run: crate::splat::fuzz_run,
    },
    Target {
        name: "transforms",
        about: "camera sets: transforms.json (Blender / nerfstudio)",
        file: "transforms.json",
        seeds: |_| {
            let d = demo()?;
            Ok(vec![camera_json(&d.cameras)?, camera_json(&d.eval_cameras)?])
        },
        corpus: &[],
        run: |p| CameraSet::load(p).map(drop),
    },
    Target {
        name: "llff",
        about: "LLFF poses_bounds.npy, loaded as a scene (no image folder)",
        file: "poses_bounds.npy",
        seeds: |_| Ok(llff_seeds()),
        corpus: corpus!(
            "llff",
            "dataset_llff-hang-fuzzer-found-503B.npy",
            "dataset_llff-panic-npyz-read369.npy",
            "llff-RELEASE-panic-llff203-empty-poses.npy",
            "llff-alloc-3.1GiB-npyz-v2-header-length.npy",
            "llff-alloc-512MiB-npyz-header-length.npy",
            "llff-hang-fuzzer-found-532B.npy",
            "llff-hang-fuzzer-found-658B.npy",
            "llff-hang-npy-header-13-braces.npy",
            "llff-hang-npy-header-nesting-22-levels.npy",
            "llff-panic-npyz-read369-shape-product-overflow.npy",
            "llff-panic-npyz-read549-strides-overflow.npy",
        ),
        run: |p| {
            let dir = p.parent().unwrap_or(Path::new("."));
            crate::camera::llff::load_scene(dir, &Default::default()).map(drop)
        },
    },
    Target {
        name: "colmap-cameras-txt",
        about: "COLMAP cameras.txt (with a fixed images.txt)",
        file: "cameras.txt",
        seeds: |w| {
            write(&w.join("images.txt"), IMAGES_TXT.as_bytes())?;
            Ok(vec![CAMERAS_TXT.as_bytes().to_vec()])
        },
        corpus: &[],
        run: run_colmap,
    },
    Target {
        name: "colmap-images-txt",
        about: "COLMAP images.txt (with a fixed cameras.txt)",
        file: "images.txt",
        seeds: |w| {
            write(&w.join("cameras.txt"), CAMERAS_TXT.as_bytes())?;
            Ok(vec![IMAGES_TXT.as_bytes().to_vec()])
        },
        corpus: &[],
        run: run_colmap,
    },
    Target {
        name: "colmap-cameras-bin",
        about: "COLMAP cameras.bin (with a fixed images.bin)",
        file: "cameras.bin",
        seeds: |w| {
            write(&w.join("images.bin"), &images_bin())?;
            Ok(vec![cameras_bin()])
        },
        corpus: &[],
        run: run_colmap,
    },
    Target {
        name: "colmap-images-bin",
        about: "COLMAP images.bin (with a fixed cameras.bin)",
        file: "images.bin",
        seeds: |w| {
            write(&w.join("cameras.bin"), &cameras_bin())?;
            Ok(vec![images_bin()])
        },
        corpus: &[],
        run: run_colmap,
    },
    Target {
        name: "scribble",
        about: "NVOS scribble PNGs on a 64x48 camera, then the stroke's pixels",
        file: "scribble.png",
        seeds: |_| Ok(png_seeds()),
        corpus: &[],
        run: |p| {
            let cam = Camera::new(Intrinsics::from_fov_x(64, 48, 1.0), Affine3A::IDENTITY);
            stroke_pixels(&scribble_stroke(p, cam, Polarity::Positive, "object")?).map(drop)
        },
    },
    Target {
        name: "image",
        about: "dataset images (PNG/JPEG) for a 64x48 camera",
        file: "image.png",
        seeds: |_| {
            let mut seeds = png_seeds();
            let rgb = image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([x as u8 * 4, y as u8 * 5, 7]));
            let mut jpeg = std::io::Cursor::new(Vec::new());
            image::DynamicImage::ImageRgb8(rgb)
                .write_to(&mut jpeg, image::ImageFormat::Jpeg)
                .map_err(invalid)?;
            seeds.push(jpeg.into_inner());
            Ok(seeds)
        },
        corpus: corpus!(
            "image",
            "image_load-alloc-3GiB-png-bomb-261KB.png",
            "image_load-alloc-768MB-from-731B-jpeg.jpg",
        ),
        run: |p| crate::data::Image::load_sized(p, 64, 48).map(drop),
    },
    Target {
        name: "npy",
        about: "teacher feature maps (.npy)",
        file: "map.npy",
        seeds: |_| Ok(vec![npy_bytes("<f4", "(4, 3, 2)", &[0u8; 96]), llff_seeds().remove(0)]),
        corpus: &[],
        run: |p| read_array(p, false),
    },
    Target {
        name: "npz",
        about: "teacher feature maps (.npz archives)",
        file: "map.npz",
        seeds: |_| {
            let npy = npy_bytes("<f4", "(4, 3, 2)", &[0u8; 96]);
            Ok(vec![npz_bytes(&npy, true)?, npz_bytes(&npy, false)?])
        },
        corpus: &[],
        run: |p| read_array(p, true),
    },
];

/// The target called `name`.
pub fn find(name: &str) -> Option<&'static Target> {
    TARGETS.iter().find(|t| t.name == name)
}

fn invalid(e: impl std::fmt::Display) -> Error {
    Error::invalid(e.to_string())
}

fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).map_err(|e| Error::io(path, e))
}

/// The small demo scene the seeds are made from, built once.
fn demo() -> Result<&'static crate::demo::DemoScene> {
    static SCENE: OnceLock<std::result::Result<crate::demo::DemoScene, String>> = OnceLock::new();
    SCENE
        .get_or_init(|| crate::demo::build("tabletop", crate::demo::MIN_RES, 1).map_err(|e| e.to_string()))
        .as_ref()
        .map_err(|e| Error::invalid(e.clone()))
}

fn camera_json(set: &CameraSet) -> Result<Vec<u8>> {
    let dir = tempfile::tempdir().map_err(|e| Error::io(Path::new("tmp"), e))?;
    let path = dir.path().join("transforms.json");
    set.save(&path)?;
    std::fs::read(&path).map_err(|e| Error::io(&path, e))
}

/// A composition of the demo field with one object, saved as `ext` into
/// the work folder (its field and bitmaps file stay there for the reader).
fn composition_seed(work: &Path, ext: &str) -> Result<Vec<Vec<u8>>> {
    let d = demo()?;
    d.field.save(&work.join("field.safetensors"))?;
    let mut loaded = Session::new(work, work.join("out"));
    loaded.apply(&crate::command::Edit::LoadField {
        name: "table".into(),
        source: FieldSource::File("field.safetensors".into()),
        transform: None,
    })?;
    let mut st = loaded.state().clone();
    let placement = Placement {
        transform: Affine3A::from_translation(Vec3::new(0.1, 0.0, 0.0)),
        ..Default::default()
    };
    st.add_object("mug", st.fields[0].id, Arc::new(d.labels.mask(1)), placement);
    let session = Session::with_state(work, work.join("out"), st);
    let doc = work.join(format!("seed.{ext}"));
    composition::save(&session, &doc)?;
    Ok(vec![std::fs::read(&doc).map_err(|e| Error::io(&doc, e))?])
}

/// The example scripts in `assets/scripts` that stand alone (`move_mug`
/// needs `isrf run --field`), as RON or converted to JSON.
fn script_seeds(work: &Path, ext: &str) -> Result<Vec<Vec<u8>>> {
    const RON: &[&str] = &[
        include_str!("../../assets/scripts/excavator_on_table.ron"),
        include_str!("../../assets/scripts/move_pot.ron"),
        include_str!("../../assets/scripts/remove_pot.ron"),
    ];
    if ext == "ron" {
        return Ok(RON.iter().map(|s| s.as_bytes().to_vec()).collect());
    }
    let path = work.join("seed.json");
    RON.iter()
        .map(|text| {
            script::save_script(&script::parse_script(text, script::Format::Ron)?, &path)?;
            std::fs::read(&path).map_err(|e| Error::io(&path, e))
        })
        .collect()
}

fn run_script_check(p: &Path) -> Result<()> {
    let s = script::load_script(p)?;
    crate::command::validate_script(&s, p.parent().unwrap_or(Path::new(".")))
}

fn run_colmap(p: &Path) -> Result<()> {
    crate::camera::colmap::load(p.parent().unwrap_or(Path::new("."))).map(drop)
}

/// Teacher maps go through the strict `.npy` parser (inside a `.npz` too).
fn read_array(p: &Path, npz: bool) -> Result<()> {
    let bad = |why: String| Error::bad_file(p, why);
    let bytes = std::fs::read(p).map_err(|e| Error::io(p, e))?;
    let bytes = if npz {
        crate::npy::read_npz_first(&bytes).map_err(bad)?
    } else {
        bytes
    };
    crate::npy::parse(&bytes).map_err(bad)?.to_f32();
    Ok(())
}

const CAMERAS_TXT: &str = "# Camera list\n1 PINHOLE 64 48 60 60 32 24\n2 SIMPLE_RADIAL 64 48 55 32 24 0.01\n";
const IMAGES_TXT: &str =
    "# Image list\n1 1 0 0 0 0 0 4 1 a.png\n10 20 -1\n2 0.9238795 0 0.3826834 0 0.5 0 4 2 b.png\n\n";

fn cameras_bin() -> Vec<u8> {
    let mut b = 2u64.to_le_bytes().to_vec();
    for (id, model, params) in [
        (1u32, 1i32, vec![60.0, 60.0, 32.0, 24.0]),
        (2, 2, vec![55.0, 32.0, 24.0, 0.01]),
    ] {
        b.extend(id.to_le_bytes());
        b.extend(model.to_le_bytes());
        b.extend(64u64.to_le_bytes());
        b.extend(48u64.to_le_bytes());
        b.extend(params.iter().flat_map(|p: &f64| p.to_le_bytes()));
    }
    b
}

fn images_bin() -> Vec<u8> {
    let mut b = 2u64.to_le_bytes().to_vec();
    for (id, q, cam, name, points) in [
        (1u32, [1.0, 0.0, 0.0, 0.0], 1u32, "a.png", 1u64),
        (2, [0.92388, 0.0, 0.38268, 0.0], 2, "b.png", 0),
    ] {
        b.extend(id.to_le_bytes());
        b.extend(q.iter().chain(&[0.5, 0.0, 4.0]).flat_map(|v: &f64| v.to_le_bytes()));
        b.extend(cam.to_le_bytes());
        b.extend(name.as_bytes());
        b.push(0);
        b.extend(points.to_le_bytes());
        for _ in 0..points {
            b.extend(10.0f64.to_le_bytes());
            b.extend(20.0f64.to_le_bytes());
            b.extend((-1i64).to_le_bytes());
        }
    }
    b
}

/// A `.npy` v1 file as NumPy writes it (header padded to 64 bytes).
pub fn npy_bytes(descr: &str, shape: &str, data: &[u8]) -> Vec<u8> {
    let mut h = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + h.len() + 1) % 64 != 0 {
        h.push(' ');
    }
    h.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((h.len() as u16).to_le_bytes());
    out.extend(h.as_bytes());
    out.extend(data);
    out
}

fn npz_bytes(npy: &[u8], deflate: bool) -> Result<Vec<u8>> {
    use std::io::Write;
    let mut buf = std::io::Cursor::new(Vec::new());
    let mut z = zip::ZipWriter::new(&mut buf);
    let method = if deflate {
        zip::CompressionMethod::Deflated
    } else {
        zip::CompressionMethod::Stored
    };
    z.start_file(
        "arr_0.npy",
        zip::write::FileOptions::default().compression_method(method),
    )
    .map_err(invalid)?;
    z.write_all(npy).map_err(invalid)?;
    z.finish().map_err(invalid)?;
    drop(z);
    Ok(buf.into_inner())
}

/// Three forward-facing poses (f64 and f32 files), as LLFF writes them.
fn llff_seeds() -> Vec<Vec<u8>> {
    let rows: Vec<[f64; 17]> = (0..3)
        .map(|i| {
            let x = 0.1 * i as f64;
            // [down, right, back | t | hwf] rows, then near and far.
            [
                0.0, 1.0, 0.0, x, 480.0, -1.0, 0.0, 0.0, 0.0, 640.0, 0.0, 0.0, 1.0, 0.0, 500.0, 2.0, 9.0,
            ]
        })
        .collect();
    let f64s: Vec<u8> = rows.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
    let f32s: Vec<u8> = rows.iter().flatten().flat_map(|&v| (v as f32).to_le_bytes()).collect();
    vec![npy_bytes("<f8", "(3, 17)", &f64s), npy_bytes("<f4", "(3, 17)", &f32s)]
}

/// Scribble-like PNGs of 64x48: grey, grey+alpha, RGB, 16-bit.
fn png_seeds() -> Vec<Vec<u8>> {
    let encode = |img: image::DynamicImage| {
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png)
            .map(|_| out.into_inner())
    };
    let grey = image::GrayImage::from_fn(64, 48, |x, y| image::Luma([u8::from((x + y) % 9 == 0) * 255]));
    let rgb = image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([x as u8 * 4, y as u8 * 5, 7]));
    [
        image::DynamicImage::ImageLuma8(grey.clone()),
        image::DynamicImage::ImageLumaA8(image::DynamicImage::ImageLuma8(grey).to_luma_alpha8()),
        image::DynamicImage::ImageRgb8(rgb.clone()),
        image::DynamicImage::ImageRgba16(image::DynamicImage::ImageRgb8(rgb).to_rgba16()),
    ]
    .into_iter()
    .filter_map(|img| encode(img).ok())
    .collect()
}

/// A checkpoint of a tiny field after two training steps (SH, Adam moments,
/// history: every tensor a checkpoint holds but features).
fn checkpoint_seed(dir: &Path) -> Result<Vec<u8>> {
    use crate::train::{RaySet, TrainConfig, Trainer};
    let (cam, image) = crate::train::trainer::tiny_view((0..144).map(|i| (i % 5) as f32 / 5.0).collect(), None);
    let config = TrainConfig {
        iters: 4,
        batch: 16,
        res: 6,
        coarse_res: 6,
        stages: 1,
        ..Default::default()
    };
    let bounds = crate::field::Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0));
    let mut t = Trainer::new(config, RaySet::build(&[(cam, &image)])?, bounds)?;
    t.step()?;
    t.step()?;
    let path = dir.join("seed.ckpt.safetensors");
    crate::train::checkpoint::save(&path, &t.config, &t.model, &t.opt, t.iter, &t.history, "fuzz seed")?;
    std::fs::read(&path).map_err(|e| Error::io(&path, e))
}
