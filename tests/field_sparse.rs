//! Sparse field files: a trained model written sparse renders and segments
//! like its dense export, `isrf info` reports the stored and dense sizes,
//! dense (version 1) files still load, and broken sparse files are refused
//! with a message.

use glam::Vec3;
use isrf::camera::Ray;
use isrf::field::io::Storage::F16;
use isrf::field::{io, Aabb, Appearance, Features, Field, GridGeom, Layout};
use isrf::render::{render_rays, RenderOptions, Scene};
use isrf::train::model::Model;
use isrf::train::step_of;
use isrf::util::SplitMix64;
use std::path::Path;
use std::process::Command;
use std::sync::Arc;

/// A model like a trained one: two dense blobs in a mostly empty box (empty
/// voxels pruned, a low-density haze elsewhere), random colours and features.
fn blob_model(seed: u64) -> Model {
    let geom = GridGeom::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [40, 41, 39]);
    let mut m = Model::new(geom, 2, 0.0, 0.01).unwrap();
    let mut rng = SplitMix64::new(seed);
    let centres = [Vec3::new(0.3, 0.1, 0.0), Vec3::new(-0.4, -0.2, 0.2)];
    for i in 0..m.len() {
        let p = geom.point_of(i);
        let d = centres.iter().map(|c| (p - *c).length()).fold(f32::MAX, f32::min);
        // Solid inside 0.25, a soft shell to 0.35, then empty.
        m.density[i] = if d < 0.35 {
            40.0 * (0.35 - d) / 0.1 + rng.unit() as f32
        } else {
            -8.0 - rng.unit() as f32
        };
    }
    for v in m.sh.iter_mut() {
        *v = 2.0 * rng.unit() as f32 - 1.0;
    }
    m.add_features([16, 17, 15], 6).unwrap();
    for v in m.features.as_mut().unwrap().data.iter_mut() {
        *v = 2.0 * rng.unit() as f32 - 1.0;
    }
    // Prune the empty space the way training does.
    m.prune(step_of(&geom), 1e-3, 2);
    m
}

fn rays(n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = SplitMix64::new(seed);
    (0..n)
        .map(|_| {
            let mut u = || 2.0 * rng.unit() as f32 - 1.0;
            let origin = Vec3::new(u() * 0.5, u() * 0.5, 2.5);
            let target = Vec3::new(u() * 0.6, u() * 0.6, u() * 0.6);
            Ray {
                origin,
                dir: (target - origin).normalize(),
            }
        })
        .collect()
}

fn render(field: Field, rays: &[Ray], step: f32) -> isrf::render::RenderOutput {
    let scene = Scene::single(Arc::new(field));
    let opts = RenderOptions {
        step: isrf::render::Step::World(step),
        features: true,
        ..Default::default()
    };
    render_rays(&scene, rays, &opts).unwrap()
}

fn max_diff(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

#[test]
fn sparse_file_renders_and_segments_like_the_dense_export() {
    let m = blob_model(1);
    let dir = tempfile::tempdir().unwrap();
    let (dense_path, sparse_path) = (
        dir.path().join("dense.safetensors"),
        dir.path().join("sparse.safetensors"),
    );
    // f16 features here, so that only the layout differs (8-bit features
    // have their own test below).
    io::save_with(&m.to_field(), &dense_path, F16).unwrap();
    io::save_with(&m.to_sparse_field(), &sparse_path, F16).unwrap();
    let dense = Field::load(&dense_path).unwrap();
    let sparse = Field::load(&sparse_path).unwrap();
    // Stored sparse: SH and features over their own indices.
    assert!(matches!(&sparse.appearance, Appearance::Sh2(g) if matches!(g.layout, Layout::Sparse(_))));
    let Some(Features::Grid(fg)) = &sparse.features else {
        panic!("features")
    };
    assert!(matches!(fg.layout, Layout::Sparse(_)));
    assert!(
        fg.slots() < fg.geom.len(),
        "the feature grid should not be stored whole"
    );
    let (ld, ls) = (file_len(&dense_path), file_len(&sparse_path));
    assert!(ls * 2 < ld, "sparse file {ls} bytes vs dense {ld}");

    // Rendering: colour, opacity and features agree.
    let rs = rays(200, 2);
    let step = step_of(&m.geom);
    let (a, b) = (render(dense.clone(), &rs, step), render(sparse.clone(), &rs, step));
    let hit = a.opacity.iter().filter(|&&o| o > 0.5).count();
    assert!(hit > 40, "the rays should see the blobs ({hit} of 200)");
    let colour = |o: &isrf::render::RenderOutput| o.color.iter().flat_map(|c| c.to_array()).collect::<Vec<_>>();
    assert!(max_diff(&colour(&a), &colour(&b)) < 1e-3);
    assert!(max_diff(&a.opacity, &b.opacity) < 1e-3);
    assert!(max_diff(&a.features, &b.features) < 1e-3);

    // Segmentation: the same occupied voxels with the same features.
    let (ca, cb) = (dense.feature_cache().unwrap(), sparse.feature_cache().unwrap());
    assert_eq!(ca.voxels, cb.voxels);
    assert!(!ca.voxels.is_empty());
    assert_eq!(ca.sigma, cb.sigma);
    assert!(max_diff(&ca.feats, &cb.feats) < 1e-5);

    // Saving the loaded sparse field again gives the same bytes.
    let again = dir.path().join("again.safetensors");
    io::save_with(&sparse, &again, F16).unwrap();
    assert_eq!(std::fs::read(&again).unwrap(), std::fs::read(&sparse_path).unwrap());
}

#[test]
fn feature_grids_are_stored_in_8_bits_within_half_a_step() {
    let m = blob_model(11);
    let dir = tempfile::tempdir().unwrap();
    let (q8_path, f16_path) = (dir.path().join("q8.safetensors"), dir.path().join("f16.safetensors"));
    let field = m.to_sparse_field();
    field.save(&q8_path).unwrap();
    io::save_with(&field, &f16_path, F16).unwrap();
    let (meta, _) = io::read_metadata(&q8_path).unwrap();
    assert_eq!(meta["version"], "3", "8-bit grids need a version-3 reader");
    assert!(meta["header"].contains("\"storage\":\"q8\""), "{}", meta["header"]);
    // One byte per value instead of two: the file shrinks by about half the
    // feature bytes.
    let Some(Features::Grid(orig)) = &field.features else {
        panic!("features")
    };
    let saved = file_len(&f16_path) - file_len(&q8_path);
    // (less the scales and their header entries)
    let n = orig.data.len() as u64;
    assert!(saved <= n && saved + 256 >= n, "saved {saved} of {n} bytes");

    // Every value within half a quantisation step of its channel (plus f16
    // rounding); the step is max |channel| / 127.
    let loaded = Field::load(&q8_path).unwrap();
    let Some(Features::Grid(back)) = &loaded.features else {
        panic!("features")
    };
    assert_eq!(back.data.len(), orig.data.len());
    let c = orig.channels;
    for ch in 0..c {
        let column = |g: &[half::f16]| g.iter().skip(ch).step_by(c).map(|v| v.to_f32()).collect::<Vec<_>>();
        let (a, b) = (column(&orig.data), column(&back.data));
        let step = a.iter().fold(0f32, |m, v| m.max(v.abs())) / 127.0;
        let err = max_diff(&a, &b);
        assert!(err <= 0.5 * step + 1e-3, "channel {ch}: error {err}, step {step}");
        assert!(err > 0.0, "channel {ch}: 8 bits should not be exact for random values");
    }
    // Everything else is stored as before, and re-saving is stable.
    assert_eq!(loaded.density.raw, field.density.raw);
    let again = dir.path().join("again.safetensors");
    loaded.save(&again).unwrap();
    assert_eq!(std::fs::read(&again).unwrap(), std::fs::read(&q8_path).unwrap());
    assert_eq!(io::to_bytes(&loaded).unwrap(), std::fs::read(&q8_path).unwrap());
}

#[test]
fn sparsify_keeps_any_dense_field_rendering() {
    // The generic conversion (dense SH and features from any source).
    let m = blob_model(3);
    let dense = m.to_field();
    let sparse = isrf::field::sparse::sparsify(&dense).unwrap();
    assert!(sparse.occupancy.is_some());
    let rs = rays(100, 4);
    let step = step_of(&m.geom);
    let (a, b) = (render(dense, &rs, step), render(sparse, &rs, step));
    assert!(max_diff(&a.opacity, &b.opacity) < 1e-3);
    assert!(max_diff(&a.features, &b.features) < 1e-3);
}

fn file_len(p: &Path) -> u64 {
    std::fs::metadata(p).unwrap().len()
}

fn info(path: &Path) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_isrf"))
        .arg("info")
        .arg(path)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

/// The number after `label` at the start of a (trimmed) line.
fn number_after(text: &str, label: &str) -> u64 {
    let line = text
        .lines()
        .map(str::trim)
        .find(|l| l.starts_with(label))
        .unwrap_or_else(|| panic!("no '{label}' line in:\n{text}"));
    line[label.len()..].split_whitespace().next().unwrap().parse().unwrap()
}

#[test]
fn info_reports_stored_and_dense_equivalent_bytes() {
    let m = blob_model(5);
    let dir = tempfile::tempdir().unwrap();
    let (dense_path, sparse_path) = (dir.path().join("d.safetensors"), dir.path().join("s.safetensors"));
    io::save_with(&m.to_field(), &dense_path, F16).unwrap();
    io::save_with(&m.to_sparse_field(), &sparse_path, F16).unwrap();
    let d = info(&dense_path);
    let s = info(&sparse_path);
    let header = |p: &Path| {
        let bytes = std::fs::read(p).unwrap();
        8 + u64::from_le_bytes(bytes[..8].try_into().unwrap())
    };
    // Stored bytes are the file's data section.
    assert_eq!(number_after(&d, "stored:"), file_len(&dense_path) - header(&dense_path));
    assert_eq!(
        number_after(&s, "stored:"),
        file_len(&sparse_path) - header(&sparse_path)
    );
    // A dense file's dense equivalent is what it stores; the sparse file's
    // is the same as the dense file's.
    assert_eq!(number_after(&d, "dense equivalent:"), number_after(&d, "stored:"));
    assert_eq!(number_after(&s, "dense equivalent:"), number_after(&d, "stored:"));
    assert!(s.contains("sparse"), "{s}");
    assert!(s.contains("isrf-field v2"), "{s}");
    assert!(d.contains("isrf-field v1"), "{d}");
}

#[test]
fn dense_files_are_still_version_1_and_load() {
    // A dense field (what every earlier isrf wrote) keeps its version-1
    // header: no new keys, so the bytes are what older builds wrote and read.
    let m = blob_model(7);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.safetensors");
    io::save_with(&m.to_field(), &path, F16).unwrap();
    let (meta, _) = io::read_metadata(&path).unwrap();
    assert_eq!(meta["version"], "1");
    assert!(!meta["header"].contains("feature_occupied"));
    assert!(!meta["header"].contains("\"density\""));
    let f = Field::load(&path).unwrap();
    assert_eq!(f.density.raw, m.density);
    assert!(f.occupancy.is_none());
    assert!(matches!(&f.appearance, Appearance::Sh2(g) if matches!(g.layout, Layout::Dense)));
}

/// Rewrites one tensor or the header of a field file (safetensors layout).
fn tamper(src: &Path, dst: &Path, edit: impl Fn(&mut serde_json::Value)) {
    let bytes = std::fs::read(src).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut v: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    edit(&mut v);
    let mut h = serde_json::to_vec(&v).unwrap();
    while h.len() % 8 != 0 {
        h.push(b' ');
    }
    let mut out = (h.len() as u64).to_le_bytes().to_vec();
    out.extend(h);
    out.extend(&bytes[8 + n..]);
    std::fs::write(dst, out).unwrap();
}

/// Edits the field header inside the metadata.
fn edit_header(v: &mut serde_json::Value, f: impl Fn(&mut serde_json::Value)) {
    let meta = v.get_mut("__metadata__").unwrap();
    let mut h: serde_json::Value = serde_json::from_str(meta["header"].as_str().unwrap()).unwrap();
    f(&mut h);
    meta["header"] = serde_json::Value::String(h.to_string());
}

#[test]
fn broken_sparse_files_are_refused_with_a_message() {
    let m = blob_model(9);
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("s.safetensors");
    m.to_sparse_field().save(&good).unwrap();
    let bad = dir.path().join("bad.safetensors");
    let cases: Vec<(&str, Box<dyn Fn(&mut serde_json::Value)>)> = vec![
        (
            "feature occupied",
            Box::new(|v| {
                edit_header(v, |h| {
                    h["feature_occupied"] = (h["feature_occupied"].as_u64().unwrap() + 1).into()
                })
            }),
        ),
        (
            "density",
            Box::new(|v| edit_header(v, |h| h["density"]["layout"] = "dense".into())),
        ),
        (
            "occupied count",
            Box::new(|v| edit_header(v, |h| h["occupied"] = serde_json::Value::Null)),
        ),
        (
            "fill",
            Box::new(|v| edit_header(v, |h| h["density"]["fill"] = "NaN".into())),
        ),
        (
            "feat.occupancy",
            Box::new(|v| {
                v.as_object_mut().unwrap().remove("feat.occupancy");
            }),
        ),
        (
            "feat.grid.scale",
            Box::new(|v| {
                v.as_object_mut().unwrap().remove("feat.grid.scale");
            }),
        ),
        (
            "storage",
            Box::new(|v| edit_header(v, |h| h["features"]["storage"] = "f16".into())),
        ),
    ];
    for (what, edit) in cases {
        tamper(&good, &bad, edit);
        let e = Field::load(&bad).expect_err(what).to_string();
        assert!(e.contains("bad.safetensors"), "{what}: {e}");
    }
    // A file names its version to older readers: here, a newer one.
    tamper(&good, &bad, |v| v["__metadata__"]["version"] = "4".into());
    let e = Field::load(&bad).unwrap_err().to_string();
    assert!(e.contains("newer"), "{e}");
}

#[cfg(unix)]
#[test]
fn info_ends_quietly_when_its_reader_goes_away() {
    use std::os::unix::process::ExitStatusExt;
    use std::process::Stdio;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.safetensors");
    blob_model(13).to_sparse_field().save(&path).unwrap();
    // The reader closes the pipe before isrf writes (as `| head -0` would).
    let mut child = Command::new(env!("CARGO_BIN_EXE_isrf"))
        .arg("info")
        .arg(&path)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(out.status.signal(), Some(libc::SIGPIPE), "{:?}: {stderr}", out.status);
}

/// A field trained on a forward-facing capture says which NDC space it
/// lives in, and a trained field which way is up: the header keeps both,
/// fields cut from it (an exported object) and its sparse form keep them,
/// fields without them load as before, and a broken one is refused with
/// the file's name.
#[test]
fn the_ndc_space_survives_files_crops_and_sparsifying() {
    let m = blob_model(5);
    let mut field = m.to_sparse_field();
    assert!(field.ndc.is_none() && field.up.is_none());
    let ndc = isrf::camera::Ndc::new(407.6, 504, 378);
    let up = glam::Vec3::new(0.0, 0.6, 0.8);
    field.ndc = Some(ndc);
    field.up = Some(up);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ndc.safetensors");
    field.save(&path).unwrap();
    let back = Field::load(&path).unwrap();
    assert_eq!(back.ndc, Some(ndc));
    assert_eq!(back.up, Some(up));
    // An object cut from it: the bitmap of its occupied voxels.
    let bits = isrf::field::Bitmap::from_fn(back.res(), |i| back.density.sigma_at(i) > 1.0);
    assert!(bits.count() > 0);
    let obj = isrf::edit::crop::object_field(&back, &bits, 1).unwrap();
    assert_eq!((obj.ndc, obj.up), (Some(ndc), Some(up)));
    assert_eq!(
        isrf::field::sparse::sparsify(&m.to_field().in_space_of(&back))
            .unwrap()
            .ndc,
        Some(ndc)
    );
    // Without NDC the header has no such key, as before.
    let plain = dir.path().join("plain.safetensors");
    m.to_sparse_field().save(&plain).unwrap();
    let plain = Field::load(&plain).unwrap();
    assert!(plain.ndc.is_none() && plain.up.is_none());
    let bad = dir.path().join("bad.safetensors");
    tamper(&path, &bad, |v| edit_header(v, |h| h["ndc"]["focal"] = (-1.0).into()));
    let e = Field::load(&bad).unwrap_err().to_string();
    assert!(e.contains("bad.safetensors") && e.contains("NDC"), "{e}");
    let flat = dir.path().join("flat.safetensors");
    tamper(&path, &flat, |v| {
        edit_header(v, |h| h["up"] = serde_json::json!([0.0, 0.0, 0.0]))
    });
    let e = Field::load(&flat).unwrap_err().to_string();
    assert!(e.contains("flat.safetensors") && e.contains("up direction"), "{e}");
}
