//! 3D Gaussian splat files in and out: import (bounds, floaters, bad
//! values), byte-for-byte subsets and their complements, moved objects,
//! fields of any kind as splats, the command line, and an independent
//! reader (`splat-transform`, npm `@playcanvas/splat-transform`).

use glam::{Affine3A, Quat, Vec3};
use isrf::field::{Bitmap, Field};
use isrf::splat::export::{export, Selection};
use isrf::splat::ply::{standard_bytes, Gaussian, SplatFile};
use isrf::splat::{import_file, ImportOptions};
use std::path::{Path, PathBuf};
use std::process::Command;

fn gaussian(pos: Vec3, i: usize) -> Gaussian {
    Gaussian {
        pos,
        dc: [0.1 * (i % 7) as f32, -0.2, 0.3],
        rest: (0..45).map(|k| ((k + i) % 5) as f32 * 0.01).collect(),
        opacity: 1.0 + (i % 3) as f32,
        log_scale: [-3.5, -3.7, -5.0],
        rot: [0.9, 0.1, -0.2, 0.3],
    }
}

/// A 0.8-wide cube's surface of Gaussians (and `extra` far ones).
fn cube_file(dir: &Path, extra: &[Vec3]) -> PathBuf {
    let mut g = vec![];
    let n = 24;
    for a in 0..n {
        for b in 0..n {
            let (u, v) = (
                a as f32 / (n - 1) as f32 * 0.8 - 0.4,
                b as f32 / (n - 1) as f32 * 0.8 - 0.4,
            );
            for p in [
                Vec3::new(u, v, -0.4),
                Vec3::new(u, v, 0.4),
                Vec3::new(u, -0.4, v),
                Vec3::new(u, 0.4, v),
                Vec3::new(-0.4, u, v),
                Vec3::new(0.4, u, v),
            ] {
                g.push(gaussian(p, g.len()));
            }
        }
    }
    g.extend(extra.iter().map(|&p| gaussian(p, 1)));
    let path = dir.join("cube.ply");
    std::fs::write(&path, standard_bytes(&g, 3).unwrap()).unwrap();
    path
}

/// A bitmap over `field`'s grid: the grid points with x > 0.
fn right_half(field: &Field) -> Bitmap {
    let g = field.geom();
    Bitmap::from_fn(g.res, |i| g.point_of(i).x > 0.0)
}

#[test]
fn far_floaters_stay_out_of_the_bounds_and_in_the_complement() {
    let dir = tempfile::tempdir().unwrap();
    let floaters = [Vec3::new(40.0, 3.0, -2.0), Vec3::new(-30.0, -50.0, 9.0)];
    let path = cube_file(dir.path(), &floaters);
    let (field, r) = import_file(&path, &ImportOptions::default()).unwrap();
    assert_eq!((r.gaussians, r.outside, r.non_finite), (6 * 24 * 24 + 2, 2, 0));
    let b = field.bounds();
    assert!(
        b.min.cmpgt(Vec3::splat(-0.6)).all() && b.max.cmplt(Vec3::splat(0.6)).all(),
        "{b:?}"
    );
    assert!(
        b.min.cmplt(Vec3::splat(-0.4)).all() && b.max.cmpgt(Vec3::splat(0.4)).all(),
        "{b:?}"
    );
    assert_eq!(r.sh_degree, 3);
    let src = field.source.as_ref().unwrap();
    assert_eq!(src.count, r.gaussians);
    assert_eq!(src.crc32, crc32fast::hash(&std::fs::read(&path).unwrap()));
    // The complement of an object holds the floaters.
    let out = dir.path().join("rest.ply");
    let bits = right_half(&field);
    let sel = Selection {
        bits: Some(&bits),
        complement: true,
        ..Selection::whole()
    };
    export(&field, &sel, &out).unwrap();
    let rest = SplatFile::read(&out).unwrap();
    let has = |p: Vec3| (0..rest.len()).any(|i| rest.position(i) == p);
    assert!(floaters.iter().all(|&p| has(p)));
}

#[test]
fn object_and_complement_split_the_records_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let path = cube_file(dir.path(), &[]);
    let (field, _) = import_file(&path, &ImportOptions::default()).unwrap();
    // Saved and loaded, the field still knows its source.
    let fpath = dir.path().join("cube.safetensors");
    field.save(&fpath).unwrap();
    let field = Field::load(&fpath).unwrap();
    let bits = right_half(&field);
    let src = SplatFile::read(&path).unwrap();
    let mut parts = vec![];
    for complement in [false, true] {
        let out = dir.path().join(format!("part{complement}.ply"));
        let sel = Selection {
            bits: Some(&bits),
            complement,
            ..Selection::whole()
        };
        let r = export(&field, &sel, &out).unwrap();
        assert!(r.from_source);
        let part = SplatFile::read(&out).unwrap();
        assert_eq!(part.len(), r.written);
        // Same header but the count, same record bytes in file order.
        assert_eq!(part.header.text, src.header.with_count(part.len()));
        parts.push(part);
    }
    assert_eq!(parts[0].len() + parts[1].len(), src.len());
    let (mut a, mut b) = (0, 0);
    for i in 0..src.len() {
        let right = src.position(i).x > 0.0;
        let part = &parts[usize::from(!right)];
        let k = if right { &mut a } else { &mut b };
        assert_eq!(part.record(*k), src.record(i), "record {i}");
        *k += 1;
    }
    assert!(a > 0 && b > 0);
}

#[test]
fn a_moved_object_exports_moved_gaussians_and_keeps_other_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let path = cube_file(dir.path(), &[]);
    let (field, _) = import_file(&path, &ImportOptions::default()).unwrap();
    let bits = right_half(&field);
    let a = Affine3A::from_scale_rotation_translation(Vec3::splat(1.5), Quat::from_rotation_y(0.7), Vec3::X);
    let out = dir.path().join("moved.ply");
    let sel = Selection {
        bits: Some(&bits),
        to_world: a,
        ..Selection::whole()
    };
    export(&field, &sel, &out).unwrap();
    let moved = SplatFile::read(&out).unwrap();
    let src = SplatFile::read(&path).unwrap();
    let picked: Vec<usize> = (0..src.len()).filter(|&i| src.position(i).x > 0.0).collect();
    assert_eq!(moved.len(), picked.len());
    let l = &src.header.layout;
    for (k, &i) in picked.iter().enumerate() {
        let (g0, g1) = (src.gaussian(i), moved.gaussian(k));
        assert!((g1.pos - a.transform_point3(g0.pos)).length() < 1e-5);
        for s in 0..3 {
            assert!((g1.log_scale[s] - g0.log_scale[s] - 1.5f32.ln()).abs() < 1e-5);
        }
        let want = Quat::from_rotation_y(0.7) * g0.rotation();
        assert!(want.dot(g1.rotation()).abs() > 1.0 - 1e-5);
        assert_eq!(g1.opacity, g0.opacity);
        assert_eq!(g1.dc, g0.dc, "no appearance edit: the DC term is kept");
        // Normals are written too (zeros stay zeros here).
        let (r0, r1) = (src.record(i), moved.record(k));
        let n = l.normal.unwrap();
        assert_eq!(&r1[n[0]..n[2] + 4], &r0[n[0]..n[2] + 4]);
    }
}

#[test]
fn non_finite_gaussians_are_skipped_and_an_empty_file_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let mut g: Vec<Gaussian> = (0..50)
        .map(|i| gaussian(Vec3::new(i as f32 * 0.01, 0.0, 0.0), i))
        .collect();
    g[3].pos.y = f32::NAN;
    g[7].opacity = f32::INFINITY;
    let path = dir.path().join("nan.ply");
    std::fs::write(&path, standard_bytes(&g, 3).unwrap()).unwrap();
    let (_, r) = import_file(&path, &ImportOptions::default()).unwrap();
    assert_eq!((r.non_finite, r.used), (2, 48));
    std::fs::write(&path, standard_bytes(&[], 0).unwrap()).unwrap();
    let err = import_file(&path, &ImportOptions::default()).unwrap_err().to_string();
    assert!(err.contains("nan.ply") && err.contains("no Gaussian"), "{err}");
}

#[test]
fn a_changed_source_file_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = cube_file(dir.path(), &[]);
    let (field, _) = import_file(&path, &ImportOptions::default()).unwrap();
    let mut bytes = std::fs::read(&path).unwrap();
    let n = bytes.len();
    bytes[n - 1] ^= 1;
    std::fs::write(&path, bytes).unwrap();
    let err = export(&field, &Selection::whole(), &dir.path().join("x.ply"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("changed since the field was imported"), "{err}");
}

#[test]
fn any_field_exports_as_splats_that_import_back_to_the_same_scene() {
    let scene = isrf::demo::build("tabletop", 48, 0).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo.ply");
    let r = export(&scene.field, &Selection::whole(), &out).unwrap();
    assert!(!r.from_source && r.written > 1000);
    let (back, _) = import_file(&out, &ImportOptions::default()).unwrap();
    // Rendered from the stroke camera, the re-imported field looks like the demo.
    use isrf::render::{render, RenderOptions, Scene};
    use std::sync::Arc;
    let opts = RenderOptions::default();
    let a = render(
        &Scene::single(Arc::new(scene.field.clone())),
        &scene.stroke_camera,
        &opts,
    )
    .unwrap();
    let b = render(&Scene::single(Arc::new(back)), &scene.stroke_camera, &opts).unwrap();
    let mad: f32 = a
        .out
        .color
        .iter()
        .zip(&b.out.color)
        .map(|(x, y)| (*x - *y).abs().element_sum() / 3.0)
        .sum::<f32>()
        / a.out.color.len() as f32;
    let coverage = |o: &[f32]| o.iter().filter(|&&v| v > 0.5).count() as f32;
    let (ca, cb) = (coverage(&a.out.opacity), coverage(&b.out.opacity));
    eprintln!("demo -> splats -> field: mean colour difference {mad:.4}, covered pixels {ca} vs {cb}");
    assert!(mad < 0.08, "mean colour difference {mad}");
    assert!((ca - cb).abs() < 0.05 * ca, "coverage {ca} vs {cb}");
}

#[test]
fn command_line_import_info_and_export() {
    let isrf = env!("CARGO_BIN_EXE_isrf");
    let dir = tempfile::tempdir().unwrap();
    let path = cube_file(dir.path(), &[]);
    let field = dir.path().join("cube.safetensors");
    let run = |args: &[&str]| {
        let o = Command::new(isrf).args(args).output().unwrap();
        let text = String::from_utf8_lossy(&o.stderr).to_string() + &String::from_utf8_lossy(&o.stdout);
        (o.status.success(), text)
    };
    let (ok, text) = run(&[
        "import",
        path.to_str().unwrap(),
        "--out",
        field.to_str().unwrap(),
        "--res",
        "40",
        "--up",
        "0,-2,0",
    ]);
    assert!(ok, "{text}");
    assert!(text.contains("3456 Gaussians (SH degree 3)"), "{text}");
    let (ok, text) = run(&["info", field.to_str().unwrap()]);
    assert!(ok && text.contains("sh degree 2"), "{text}");
    assert!(text.contains("up          [0.000, -1.000, 0.000]"), "{text}");
    let (ok, text) = run(&[
        "import",
        path.to_str().unwrap(),
        "--out",
        "x.safetensors",
        "--up",
        "0,0",
    ]);
    assert!(!ok && text.contains("'0,0' is not a direction"), "{text}");
    let out = dir.path().join("all.ply");
    let (ok, text) = run(&["export-splats", field.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    assert!(
        ok && text.contains("wrote 3456 of 3456 records of the source file"),
        "{text}"
    );
    assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(&path).unwrap());
    // A broken file is a one-line error naming it.
    std::fs::write(&path, b"ply\nformat ascii 1.0\nend_header\n").unwrap();
    let (ok, text) = run(&["import", path.to_str().unwrap(), "--out", field.to_str().unwrap()]);
    assert!(!ok && text.contains("cube.ply") && text.contains("ascii"), "{text}");
}

/// `splat-transform` on PATH (or `$ISRF_SPLAT_TRANSFORM`), if installed.
fn splat_transform() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("ISRF_SPLAT_TRANSFORM") {
        return Some(PathBuf::from(p));
    }
    let ok = Command::new("splat-transform")
        .arg("--version")
        .output()
        .ok()?
        .status
        .success();
    ok.then(|| PathBuf::from("splat-transform"))
}

#[test]
fn an_independent_reader_reads_the_exported_subset_field_by_field() {
    let Some(tool) = splat_transform() else {
        eprintln!("skipped: splat-transform not found (npm install -g @playcanvas/splat-transform, as .ci/run does)");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let path = cube_file(dir.path(), &[]);
    let (field, _) = import_file(&path, &ImportOptions::default()).unwrap();
    let bits = right_half(&field);
    let sub = dir.path().join("right.ply");
    let sel = Selection {
        bits: Some(&bits),
        ..Selection::whole()
    };
    export(&field, &sel, &sub).unwrap();
    let ours = SplatFile::read(&sub).unwrap();
    let csv = dir.path().join("right.csv");
    let o = Command::new(&tool)
        .args(["-q", "-w"])
        .arg(&sub)
        .arg(&csv)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    let columns: Vec<&str> = lines.next().unwrap().split(',').collect();
    let names: Vec<&str> = ours.header.props.iter().map(|p| p.name.as_str()).collect();
    for n in &names {
        assert!(columns.contains(n), "splat-transform lacks column {n}: {columns:?}");
    }
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), ours.len(), "Gaussian count");
    for (i, row) in rows.iter().enumerate() {
        let rec = ours.record(i);
        for p in &ours.header.props {
            let col = columns.iter().position(|c| *c == p.name).unwrap();
            let want = isrf::splat::ply::f32_at(rec, p.offset) as f64;
            assert!(
                (row[col] - want).abs() <= 1e-6 * want.abs().max(1.0),
                "Gaussian {i} {}: {} vs {want}",
                p.name,
                row[col]
            );
        }
    }
}

/// The selection pipeline end to end on a small synthetic splat scene with
/// features that separate the objects (the demo's own, lifted from 12
/// rendered views): import, lift, one stroke per object, export, compared
/// with the Gaussians' true labels.
#[test]
fn one_stroke_selects_an_objects_splats() {
    use isrf::bench::splats::{bench_splats, SplatBenchConfig};
    let dir = tempfile::tempdir().unwrap();
    let cfg = SplatBenchConfig {
        scenes: vec!["tabletop".into()],
        res: 64,
        orbit: 12,
        teacher: None,
        dims: 64,
        cache_dir: None,
        work: dir.path().to_path_buf(),
        // The cut's colour models off: the stroke is on the wooden top, the
        // legs are the box's blue, and with the defaults the legs go (table
        // 0.79 by count; 0.86 without colour models, 0.91 without the cut).
        // This test checks the splat pipeline, not that trade-off (README,
        // segmentation).
        params: isrf::segment::SegmentParams {
            cut: isrf::segment::cut::CutParams {
                colour_unary: 0.0,
                ..Default::default()
            },
            ..Default::default()
        },
        diagnose: true,
    };
    let rows = bench_splats(&cfg, &|m| eprintln!("{m}")).unwrap();
    for r in &rows {
        eprintln!(
            "{} {}: IoU {:.3} by count, {:.3} by mass",
            r.scene, r.object, r.iou_count, r.iou_mass
        );
        // The diagnosis: seeds, stable region, six fixed floods (0.4 … 1.2
        // past θ 0.3), then the cut, which is the row's own selection.
        let names: Vec<&str> = r.stages.iter().map(|s| s.stage.as_str()).collect();
        assert_eq!(names.len(), 9, "{names:?}");
        assert_eq!((names[0], names[1], names[8]), ("seeds", "stable", "cut"));
        let cut = &r.stages[8];
        assert_eq!(
            (cut.selected, cut.missed, cut.iou_count),
            (r.selected, r.missed, r.iou_count)
        );
        // Each stage's counts add up: what it selected is the object's
        // Gaussians it kept plus the wrong ones by name, and its IoU is the
        // kept over selected and missed.
        for st in &r.stages {
            let kept = r.true_gaussians - st.missed;
            let wrong: usize = st.wrong.iter().map(|(_, n)| n).sum();
            assert_eq!(st.selected, kept + wrong, "{} {st:?}", r.object);
            let iou = kept as f64 / (st.selected + st.missed).max(1) as f64;
            assert!((st.iou_count - iou).abs() < 1e-12, "{} {st:?}", r.object);
        }
    }
    let iou = |name: &str| rows.iter().find(|r| r.object == name).unwrap().iou_count;
    assert!(iou("table") > 0.85 && iou("pot") > 0.7, "{rows:?}");
}

/// The script commands `export(splats(object: …, out: …[, complement: true]))`
/// on an imported field with features: the object's records and the rest
/// split the source file, byte for byte; a moved object's splats move.
#[test]
fn script_exports_an_objects_splats_its_complement_and_moved_splats() {
    use isrf::splat::synth::from_demo;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = isrf::demo::build("tabletop", 64, 0).unwrap();
    let synth = from_demo(&scene, 1, 7);
    let ply = d.join("room.ply");
    std::fs::write(&ply, standard_bytes(&synth.gaussians, 3).unwrap()).unwrap();
    let (field, _) = import_file(&ply, &ImportOptions::default()).unwrap();
    let field = isrf::bench::splats::oracle_features(&scene, &field, 12).unwrap();
    field.save(&d.join("room.safetensors")).unwrap();
    let pot: Vec<_> = scene.strokes_json().into_iter().filter(|s| s.object == "pot").collect();
    std::fs::write(d.join("pot.json"), serde_json::to_vec(&pot).unwrap()).unwrap();
    let script = r#"[
        load_field(name: "room", source: file("room.safetensors")),
        stroke(object: "pot", source: file("pot.json")),
        export(splats(object: "pot", out: "pot.ply")),
        export(splats(object: "pot", out: "rest.ply", complement: true)),
        transform(object: "pot", transform: (translate: (0.0, 0.5, 0.0))),
        export(splats(object: "pot", out: "moved.ply")),
    ]"#;
    std::fs::write(d.join("s.ron"), script).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_isrf"))
        .arg("run")
        .arg(d.join("s.ron"))
        .arg("--out")
        .arg(d.join("out"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let read = |n: &str| SplatFile::read(&d.join("out").join(n)).unwrap();
    let (src, pot, rest, moved) = (
        SplatFile::read(&ply).unwrap(),
        read("pot.ply"),
        read("rest.ply"),
        read("moved.ply"),
    );
    assert_eq!(pot.len() + rest.len(), src.len());
    let label = scene.object("pot").unwrap().label;
    let on_pot = (0..pot.len())
        .filter(|&i| scene.labels.at(pot.position(i)) == label)
        .count();
    assert!(
        on_pot as f64 > 0.8 * pot.len() as f64,
        "{on_pot} of {} on the pot",
        pot.len()
    );
    // The pot's records are the source's, in file order, byte for byte.
    let mut k = 0;
    for i in 0..src.len() {
        if k < pot.len() && src.record(i) == pot.record(k) {
            k += 1;
        }
    }
    assert_eq!(k, pot.len());
    assert_eq!(moved.len(), pot.len());
    for i in 0..pot.len() {
        assert!((moved.position(i) - pot.position(i) - Vec3::new(0.0, 0.5, 0.0)).length() < 1e-5);
    }
}
