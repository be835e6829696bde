//! The procedural demo scenes: determinism, ground truth consistent with the
//! field, feature statistics the segmentation relies on, strokes on visible
//! surfaces, file round trips and the `isrf demo` command.

use glam::Vec3;
use isrf::camera::Ray;
use isrf::demo::{self, DemoScene, Labels};
use isrf::field::{io, Appearance, Features, Field};
use std::path::Path;
use std::process::Command;

const RES: usize = 64;

fn scene(name: &str) -> DemoScene {
    demo::build(name, RES, 1).unwrap()
}

/// Every stored value of a field, as bytes (the file header's metadata map
/// has no fixed key order, so whole files are compared through this).
fn field_bytes(f: &Field) -> Vec<u8> {
    let mut out: Vec<u8> = bytemuck::cast_slice(&f.density.raw).to_vec();
    out.extend(f.occupancy.as_ref().unwrap().bits().to_bytes());
    let (Appearance::Rgb(a), Some(Features::Grid(g))) = (&f.appearance, &f.features) else {
        panic!("demo fields store rgb and a feature grid")
    };
    out.extend_from_slice(bytemuck::cast_slice(&a.data));
    out.extend_from_slice(bytemuck::cast_slice(&g.data));
    out
}

#[test]
fn build_is_deterministic_for_a_seed() {
    let a = demo::build("tabletop", 48, 7).unwrap();
    let b = demo::build("tabletop", 48, 7).unwrap();
    let c = demo::build("tabletop", 48, 8).unwrap();
    assert!(field_bytes(&a.field) == field_bytes(&b.field));
    assert!(a.labels == b.labels);
    assert!(a.voxel_parts == b.voxel_parts);
    for (x, y) in a.objects.iter().zip(&b.objects) {
        assert_eq!(x.stroke, y.stroke);
    }
    assert!(field_bytes(&a.field) != field_bytes(&c.field));
    // Geometry apart from the plant does not depend on the seed.
    assert_eq!(a.labels.counts()[1..3], c.labels.counts()[1..3]);
}

#[test]
fn bad_names_and_resolutions_are_rejected() {
    let e = demo::build("kitchen", 32, 0).unwrap_err().to_string();
    assert!(
        e.contains("kitchen") && e.contains("tabletop") && e.contains("shelf"),
        "{e}"
    );
    assert!(demo::build("tabletop", 15, 0).is_err());
    assert!(demo::build("tabletop", 513, 0).is_err());
    assert!(demo::build("shelf", 16, 0).is_ok());
}

/// Every occupied voxel (σ > 0, the occupancy index, the feature cache's
/// σ > 0.001) carries its object's label and nothing else does.
#[test]
fn labels_agree_with_occupancy() {
    for name in demo::names() {
        let s = scene(name);
        let occ = s.field.occupancy.as_ref().unwrap();
        let n = s.labels.data.len();
        assert_eq!(s.labels.res, s.field.res());
        assert_eq!(s.labels.names.len(), s.objects.len());
        for i in 0..n {
            let occupied = s.field.density.sigma_at(i) > 0.0;
            assert_eq!(occupied, occ.bits().get(i), "{name}: voxel {i}");
            assert_eq!(occupied, s.labels.data[i] != 0, "{name}: voxel {i}");
            assert!(s.labels.data[i] as usize <= s.objects.len());
        }
        assert_eq!(s.field.feature_cache().unwrap().len(), occ.count());
        assert_eq!(s.voxel_parts.len(), occ.count());
        let counts = s.labels.counts();
        for o in &s.objects {
            assert_eq!(s.labels.name_of(o.label), Some(o.name.as_str()));
            assert!(
                counts[o.label as usize] > 20,
                "{name}: {} has {} voxels",
                o.name,
                counts[o.label as usize]
            );
        }
        for (slot, v) in occ.bits().ones().enumerate() {
            let obj = &s.objects[s.labels.data[v] as usize - 1];
            assert!((s.voxel_parts[slot] as usize) < obj.parts.len());
        }
        // Thin slabs and solid objects keep the occupied set small.
        assert!(occ.count() * 8 < n, "{name}: {} of {n} voxels occupied", occ.count());
    }
}

#[test]
fn surfaces_are_opaque_and_colours_are_sharp() {
    let s = scene("tabletop");
    let h = s.field.geom().spacing().x;
    // Straight down onto the table top, away from objects: opaque within
    // about two voxels of the surface, and table-coloured (not blended with
    // empty space).
    let ray = Ray {
        origin: Vec3::new(0.1, 0.9, 0.3),
        dir: Vec3::NEG_Y,
    };
    let t = demo::strokes::first_hit(&s.field.density, &ray).unwrap();
    let top = -0.18;
    assert!((ray.at(t).y - top).abs() < 1.5 * h, "hit at {}", ray.at(t).y);
    let mut depth = 0.0;
    let mut y = top + 2.0 * h;
    while y > top - 2.0 * h {
        depth += s.field.sigma(Vec3::new(0.1, y, 0.3)) * 0.05 * h;
        y -= 0.05 * h;
    }
    assert!(depth > 3.0, "optical depth across the surface {depth}");
    let c = s.field.sampler().color(ray.at(t), Vec3::NEG_Y);
    assert!(c.x > 0.4 && c.x > c.z + 0.15, "table top colour {c}");
}

fn unit(v: &[f32]) -> Vec<f32> {
    let n = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
    v.iter().map(|x| x / n).collect()
}

fn sq(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// NNFM matches unit features with squared distance < 0.4; bilateral growth
/// weighs raw features by exp(−‖Δφ‖²/10).
#[test]
fn features_separate_objects_and_join_parts() {
    for name in demo::names() {
        let s = scene(name);
        let Some(Features::Grid(g)) = &s.field.features else {
            panic!("no feature grid")
        };
        let c = g.channels;
        assert_eq!(c, 32);
        let occ = s.field.occupancy.as_ref().unwrap();
        let labels: Vec<u8> = occ.bits().ones().map(|v| s.labels.data[v]).collect();
        let raw: Vec<f32> = g.data.iter().map(|x| x.to_f32()).collect();
        let units: Vec<Vec<f32>> = raw.chunks(c).map(unit).collect();
        let norms: Vec<f32> = raw
            .chunks(c)
            .map(|r| r.iter().map(|x| x * x).sum::<f32>().sqrt())
            .collect();
        let mut raw_means = vec![];
        for o in &s.objects {
            let base: Vec<usize> = (0..labels.len())
                .filter(|&i| labels[i] == o.label && s.voxel_parts[i] == 0)
                .collect();
            let mut mean = vec![0.0f32; c];
            let mut raw_mean = vec![0.0f32; c];
            for &i in &base {
                mean.iter_mut()
                    .zip(&units[i])
                    .for_each(|(m, u)| *m += u / base.len() as f32);
                raw_mean
                    .iter_mut()
                    .zip(&raw[i * c..(i + 1) * c])
                    .for_each(|(m, u)| *m += u / base.len() as f32);
            }
            let (mut own, mut own_hit, mut other, mut other_hit) = (0, 0, 0, 0);
            for i in 0..labels.len() {
                let hit = sq(&units[i], &mean) < 0.4;
                if labels[i] == o.label {
                    own += 1;
                    own_hit += hit as usize;
                } else {
                    other += 1;
                    other_hit += hit as usize;
                }
            }
            let own_frac = own_hit as f32 / own as f32;
            let other_frac = other_hit as f32 / other as f32;
            assert!(
                own_frac >= 0.97,
                "{name}/{}: {own_frac} of its voxels match its base part",
                o.name
            );
            assert!(
                other_frac <= 0.01,
                "{name}/{}: {other_frac} of other voxels match it",
                o.name
            );
            // Within the base part, raw features (noise included) stay close:
            // the mean squared distance between two of its voxels is 2·variance.
            let var = base
                .iter()
                .map(|&i| sq(&raw[i * c..(i + 1) * c], &raw_mean))
                .sum::<f32>()
                / base.len() as f32;
            assert!(
                2.0 * var < 2.0,
                "{name}/{}: within-part squared distance {}",
                o.name,
                2.0 * var
            );
            let mean_norm = base.iter().map(|&i| norms[i]).sum::<f32>() / base.len() as f32;
            assert!((6.0..=8.0).contains(&mean_norm), "{name}/{}: norm {mean_norm}", o.name);
            raw_means.push(raw_mean);
        }
        for a in 0..raw_means.len() {
            for b in 0..a {
                let d = sq(&raw_means[a], &raw_means[b]);
                assert!(d > 40.0, "{name}: objects {a} and {b} are only {d} apart");
            }
        }
    }
}

/// Parts of one object are distinct but close (cosine ≈ 0.85–0.9).
#[test]
fn parts_are_close_but_distinct() {
    let s = scene("shelf");
    let Some(Features::Grid(g)) = &s.field.features else {
        panic!("no feature grid")
    };
    let occ = s.field.occupancy.as_ref().unwrap();
    let ex = s.object("excavator").unwrap();
    let labels: Vec<u8> = occ.bits().ones().map(|v| s.labels.data[v]).collect();
    let part_mean = |p: u8| {
        let mut m = vec![0.0f32; 32];
        for i in (0..labels.len()).filter(|&i| labels[i] == ex.label && s.voxel_parts[i] == p) {
            let u = unit(
                &g.data[i * 32..(i + 1) * 32]
                    .iter()
                    .map(|x| x.to_f32())
                    .collect::<Vec<_>>(),
            );
            m.iter_mut().zip(u).for_each(|(a, b)| *a += b);
        }
        unit(&m)
    };
    let means: Vec<Vec<f32>> = (0..ex.parts.len() as u8).map(part_mean).collect();
    for a in 0..means.len() {
        for b in 0..a {
            let cos: f32 = means[a].iter().zip(&means[b]).map(|(x, y)| x * y).sum();
            assert!((0.8..0.97).contains(&cos), "parts {a} and {b}: cosine {cos}");
        }
    }
}

/// Distance along the unit direction `dir` from `origin` where transmittance
/// first drops below 1/2 (independent of the library's march).
fn first_surface(field: &Field, origin: Vec3, dir: Vec3) -> Option<f32> {
    let step = 0.2 * field.geom().spacing().x;
    let (t0, t1) = field.bounds().intersect(origin, dir)?;
    let (mut t, mut depth) = (t0, 0.0);
    while t < t1 {
        depth += field.sigma(origin + t * dir) * step;
        if depth > std::f32::consts::LN_2 {
            return Some(t);
        }
        t += step;
    }
    None
}

/// Object label seen first through a pixel of the stroke camera (0 = none).
fn pixel_label(s: &DemoScene, x: u32, y: u32) -> u8 {
    let ray = s.stroke_camera.pixel_ray(x, y);
    let h = s.field.geom().spacing().x;
    let Some(t) = first_surface(&s.field, ray.origin, ray.dir) else {
        return 0;
    };
    (0..8)
        .map(|i| s.labels.at(ray.at(t + 0.25 * h * i as f32)))
        .find(|&l| l != 0)
        .unwrap_or(0)
}

#[test]
fn strokes_lie_on_visible_surfaces() {
    for name in demo::names() {
        let s = scene(name);
        let h = s.field.geom().spacing().x;
        let eye = s.stroke_camera.position();
        let mut seen = std::collections::HashMap::new();
        for o in &s.objects {
            assert!(
                (5..=15).contains(&o.stroke.len()),
                "{name}/{}: {} stroke points",
                o.name,
                o.stroke.len()
            );
            for &p in &o.stroke {
                assert_eq!(s.labels.at(p), o.label, "{name}/{}: {p} is not on the object", o.name);
                let t = first_surface(&s.field, eye, (p - eye).normalize()).expect("the ray hits something");
                let dist = (p - eye).length();
                assert!(
                    (t - dist).abs() < 2.5 * h,
                    "{name}/{}: {p} is hidden (first surface at {t}, point at {dist})",
                    o.name
                );
            }
            let px = s.stroke_pixels(o);
            assert!(px.len() >= 5);
            // A 7×7 brush dragged along the stroke (points joined by
            // segments, as segmentation stamps it) sees only this object, so
            // rendered stroke features come from it alone.
            let r = demo::STROKE_RADIUS as i64;
            let mut centres = vec![];
            for w in px.windows(2) {
                let (a, b) = (
                    glam::Vec2::new(w[0][0] as f32, w[0][1] as f32),
                    glam::Vec2::new(w[1][0] as f32, w[1][1] as f32),
                );
                let n = (a.distance(b) * 2.0).ceil().max(1.0) as usize;
                centres.extend((0..=n).map(|i| a.lerp(b, i as f32 / n as f32).floor()));
            }
            centres.dedup();
            for c in centres {
                for (dx, dy) in (-r..=r).flat_map(|dy| (-r..=r).map(move |dx| (dx, dy))) {
                    let (bx, by) = (c.x as i64 + dx, c.y as i64 + dy);
                    assert!(bx >= 0 && by >= 0 && bx < demo::WIDTH as i64 && by < demo::HEIGHT as i64);
                    let l = *seen
                        .entry((bx, by))
                        .or_insert_with(|| pixel_label(&s, bx as u32, by as u32));
                    assert_eq!(l, o.label, "{name}/{}: brush pixel {bx},{by}", o.name);
                }
            }
        }
        assert_eq!(s.cameras.frames.len(), demo::ORBIT_FRAMES);
        assert_eq!(s.eval_cameras.frames.len(), demo::EVAL_FRAMES);
        for e in &s.eval_cameras.frames {
            for f in &s.cameras.frames {
                assert!(e.camera.position().distance(f.camera.position()) > 0.1);
            }
        }
    }
}

#[test]
fn pot_stroke_reaches_into_the_plant() {
    let s = scene("tabletop");
    let pot = s.object("pot").unwrap();
    let occ = s.field.occupancy.as_ref().unwrap();
    let g = s.field.geom();
    let parts: Vec<u8> = pot
        .stroke
        .iter()
        .map(|&p| {
            let [x, y, z] = g.nearest(p).unwrap();
            s.voxel_parts[occ.slot(g.index(x, y, z)).unwrap()]
        })
        .collect();
    assert!(parts.contains(&0) && parts.contains(&1), "pot stroke parts {parts:?}");
}

#[test]
fn field_and_labels_round_trip() {
    let s = demo::build("shelf", 48, 3).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let fp = dir.path().join("field.safetensors");
    s.field.save(&fp).unwrap();
    let back = Field::load(&fp).unwrap();
    // Features are stored in 8 bits, so compare at the file's precision:
    // what was read encodes to the same bytes as what was written.
    assert!(isrf::field::io::to_bytes(&back).unwrap() == isrf::field::io::to_bytes(&s.field).unwrap());
    assert_eq!(back.density.raw, s.field.density.raw);
    assert_eq!(back.geom(), s.field.geom());
    let p = s.objects[1].stroke[0];
    assert_eq!(back.sampler().color(p, Vec3::Z), s.field.sampler().color(p, Vec3::Z));
    let lp = dir.path().join("labels.safetensors");
    s.labels.save(&lp).unwrap();
    assert!(Labels::load(&lp).unwrap() == s.labels);
    // A field file is not a labels file.
    let e = Labels::load(&fp).unwrap_err().to_string();
    assert!(e.contains("isrf-field"), "{e}");
}

fn write_labels_file(path: &Path, names: &str, res: &str, shape: Vec<usize>, data: Vec<u8>) {
    use std::collections::HashMap;
    let meta = HashMap::from([
        ("format".to_string(), "isrf-labels".to_string()),
        ("version".to_string(), "1".to_string()),
        ("names".to_string(), names.to_string()),
        ("resolution".to_string(), res.to_string()),
        ("bounds".to_string(), "[[-1,-1,-1],[1,1,1]]".to_string()),
    ]);
    let bytes = io::serialize(&["labels".to_string()], &[(safetensors::Dtype::U8, shape, data)], meta).unwrap();
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn bad_labels_files_are_rejected() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("l.safetensors");
    write_labels_file(
        &p,
        r#"["a","b"]"#,
        "[2,2,2]",
        vec![2, 2, 2],
        vec![0, 1, 2, 0, 0, 0, 0, 0],
    );
    let ok = Labels::load(&p).unwrap();
    assert_eq!(ok.counts(), vec![6, 1, 1]);
    assert_eq!(ok.mask(2).count(), 1);
    write_labels_file(&p, r#"["a"]"#, "[2,2,2]", vec![2, 2, 2], vec![0, 1, 2, 0, 0, 0, 0, 0]);
    let e = Labels::load(&p).unwrap_err().to_string();
    assert!(e.contains("label 2") && e.contains("1 names"), "{e}");
    write_labels_file(&p, r#"["a"]"#, "[2,2,3]", vec![2, 2, 2], vec![0; 8]);
    let e = Labels::load(&p).unwrap_err().to_string();
    assert!(e.contains("12 bytes") || e.contains("shape"), "{e}");
    write_labels_file(&p, r#"["a"]"#, "[4000,4000,4000]", vec![2, 2, 2], vec![0; 8]);
    let e = Labels::load(&p).unwrap_err().to_string();
    assert!(e.contains("absurdly large"), "{e}");
    write_labels_file(&p, r#"{"a":1}"#, "[2,2,2]", vec![2, 2, 2], vec![0; 8]);
    let e = Labels::load(&p).unwrap_err().to_string();
    assert!(e.contains("names"), "{e}");
    std::fs::write(&p, b"short").unwrap();
    assert!(Labels::load(&p).is_err());
}

#[test]
fn cli_writes_scene_files() {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_isrf"))
        .args(["demo", "--scene", "all", "--res", "48", "--seed", "2", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("occupied voxels"), "{stdout}");
    for name in demo::names() {
        let d = dir.path().join(name);
        let field = Field::load(&d.join("field.safetensors")).unwrap();
        assert_eq!(field.res(), [48; 3]);
        let labels = Labels::load(&d.join("labels.safetensors")).unwrap();
        let transforms: serde_json::Value =
            serde_json::from_slice(&std::fs::read(d.join("transforms.json")).unwrap()).unwrap();
        assert_eq!(transforms["frames"].as_array().unwrap().len(), demo::ORBIT_FRAMES);
        assert_eq!(transforms["frames"][0]["file_path"], "./frame_000");
        assert!(d.join("transforms_eval.json").exists());
        let strokes: serde_json::Value =
            serde_json::from_slice(&std::fs::read(d.join("strokes.json")).unwrap()).unwrap();
        let strokes = strokes.as_array().unwrap();
        assert_eq!(strokes.len(), labels.names.len());
        for st in strokes {
            assert!(labels.label_of(st["object"].as_str().unwrap()).is_some());
            assert_eq!(st["polarity"], "positive");
            assert_eq!(st["radius"], 3);
            assert!(st["points"].as_array().unwrap().len() >= 5);
            assert_eq!(st["camera"]["w"], demo::WIDTH);
            assert_eq!(st["camera"]["transform_matrix"].as_array().unwrap().len(), 4);
        }
    }
    let bad = Command::new(env!("CARGO_BIN_EXE_isrf"))
        .args(["demo", "--scene", "kitchen", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("tabletop, shelf"), "{err}");
    let bad = Command::new(env!("CARGO_BIN_EXE_isrf"))
        .args(["demo", "--res", "8", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("out of range"));
}
