//! Edit invariants, scripts and compositions (issue: editing and `isrf run`).

use glam::Vec3;
use isrf::camera::{Camera, Intrinsics};
use isrf::command::script::{load_script, parse_script, save_script, Format};
use isrf::command::{
    composition, perform, run_script, validate_script, CameraSource, Command, Edit, Export, FieldSource, Output,
    Script, Session, StrokeSource, TransformSpec,
};
use isrf::field::{Aabb, FieldBuilder};
use isrf::render::{render, ColorEdit, RenderOptions};
use std::path::Path;

const RES: usize = 48;

fn demo(name: &str, scene: &str) -> Edit {
    Edit::LoadField {
        name: name.into(),
        source: FieldSource::Demo {
            scene: scene.into(),
            res: RES,
            seed: 0,
        },
        transform: None,
    }
}

fn stroke(object: &str, field: &str, demo_object: &str) -> Edit {
    Edit::Stroke {
        object: object.into(),
        field: Some(field.into()),
        polarity: None,
        source: StrokeSource::Demo {
            object: demo_object.into(),
        },
    }
}

fn camera() -> Camera {
    Camera::look_at(
        Intrinsics::from_fov_x(64, 48, 0.9),
        Vec3::new(0.4, 0.5, 2.2),
        Vec3::new(0.0, -0.2, 0.0),
        Vec3::Y,
    )
}

fn image(s: &Session) -> Vec<Vec3> {
    render(&s.scene(), &camera(), &RenderOptions::default())
        .unwrap()
        .out
        .color
}

fn max_diff(a: &[Vec3], b: &[Vec3]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (*x - *y).abs().max_element())
        .fold(0.0, f32::max)
}

/// Colour frames on an orbit around the tabletop, into `frames/`.
fn orbit_render(frames: usize, width: u32, height: u32) -> Output {
    Output::Render {
        cameras: CameraSource::Orbit {
            center: [0.0, -0.2, 0.0],
            radius: 2.0,
            elevation_deg: 25.0,
            frames,
            width,
            height,
            fov_deg: 50.0,
        },
        out: "frames".into(),
        downscale: 1,
        frames: None,
        depth: false,
        background: None,
    }
}

fn tabletop_with_pot() -> Session {
    let mut s = Session::default();
    s.apply(&demo("room", "tabletop")).unwrap();
    s.apply(&stroke("pot", "room", "pot")).unwrap();
    s
}

#[test]
fn remove_then_restore_is_the_original() {
    let mut s = tabletop_with_pot();
    let original = image(&s);
    s.apply(&Edit::Remove { object: "pot".into() }).unwrap();
    let removed = image(&s);
    assert!(
        max_diff(&original, &removed) > 0.2,
        "removing the pot must change the picture"
    );
    s.apply(&Edit::Restore { object: "pot".into() }).unwrap();
    assert_eq!(image(&s), original);
}

#[test]
fn translate_there_and_back_is_the_original() {
    let mut s = tabletop_with_pot();
    let original = image(&s);
    let t = Vec3::new(-0.41, -0.42, 0.55);
    s.apply(&Edit::Transform {
        object: "pot".into(),
        transform: TransformSpec::translation(t),
    })
    .unwrap();
    let moved = image(&s);
    assert!(max_diff(&original, &moved) > 0.2, "the pot must have moved");
    s.apply(&Edit::Transform {
        object: "pot".into(),
        transform: TransformSpec::translation(-t),
    })
    .unwrap();
    // The object layer back at identity plus its source with a hole is the field.
    assert!(
        max_diff(&original, &image(&s)) < 2e-3,
        "{}",
        max_diff(&original, &image(&s))
    );
}

#[test]
fn rotation_about_the_object_centre_keeps_it_in_place() {
    let mut s = tabletop_with_pot();
    let spin = TransformSpec {
        rotate: [0.0, 180.0, 0.0],
        ..Default::default()
    };
    s.apply(&Edit::Transform {
        object: "pot".into(),
        transform: spin.clone(),
    })
    .unwrap();
    s.apply(&Edit::Transform {
        object: "pot".into(),
        transform: spin,
    })
    .unwrap();
    let o = s.object("pot").unwrap();
    let m = o.placement.transform.matrix3;
    assert!((glam::Mat3::from(m) - glam::Mat3::IDENTITY).abs_diff_eq(glam::Mat3::ZERO, 1e-5));
    assert!(Vec3::from(o.placement.transform.translation).length() < 1e-4);
}

#[test]
fn composition_with_an_empty_field_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let empty =
        FieldBuilder::new(Aabb::new(Vec3::splat(-0.5), Vec3::splat(0.5)), [8; 3]).build(|_| 0.0, |_| Vec3::ONE, None);
    empty.save(&dir.path().join("empty.safetensors")).unwrap();
    let mut s = tabletop_with_pot();
    s.apply(&Edit::Transform {
        object: "pot".into(),
        transform: TransformSpec::translation(Vec3::new(0.1, 0.0, 0.2)),
    })
    .unwrap();
    let before = image(&s);
    s.base_dir = dir.path().to_path_buf();
    s.apply(&Edit::LoadField {
        name: "nothing".into(),
        source: FieldSource::File("empty.safetensors".into()),
        transform: Some(TransformSpec::translation(Vec3::new(0.1, -0.3, 0.2))),
    })
    .unwrap();
    assert_eq!(image(&s), before);
}

#[test]
fn undo_redo_return_to_identical_states() {
    let mut s = tabletop_with_pot();
    let a = image(&s);
    s.apply(&Edit::Appearance {
        object: "pot".into(),
        edit: ColorEdit {
            hue: 120.0,
            ..Default::default()
        },
    })
    .unwrap();
    let b = image(&s);
    s.apply(&Edit::Remove { object: "pot".into() }).unwrap();
    let c = image(&s);
    assert_ne!(a, b);
    assert_ne!(b, c);
    assert_eq!(s.log().len(), 4);
    s.undo().unwrap();
    assert_eq!(image(&s), b);
    s.undo().unwrap();
    assert_eq!(image(&s), a);
    s.redo().unwrap();
    assert_eq!(image(&s), b);
    s.redo().unwrap();
    assert_eq!(image(&s), c);
    assert!(s.redo().is_none());
    // A new edit after an undo drops the redo branch.
    s.undo().unwrap();
    s.apply(&Edit::SetVisible {
        target: "pot".into(),
        visible: false,
    })
    .unwrap();
    assert!(!s.can_redo());
    // Failed commands change nothing and are not logged.
    let n = s.log().len();
    assert!(s
        .apply(&Edit::Remove { object: "nope".into() })
        .unwrap_err()
        .to_string()
        .contains("no object named 'nope'"));
    assert_eq!(s.log().len(), n);
}

#[test]
fn negative_stroke_and_duplicates() {
    let mut s = tabletop_with_pot();
    let pot = s.object("pot").unwrap().mask.count();
    s.apply(&Edit::Duplicate {
        object: "pot".into(),
        name: "pot2".into(),
        transform: Some(TransformSpec::translation(Vec3::new(0.5, 0.0, 0.0))),
    })
    .unwrap();
    // The duplicate does not cut its source: the original pot still renders in place.
    let mut solo = tabletop_with_pot();
    solo.apply(&Edit::SetVisible {
        target: "room".into(),
        visible: true,
    })
    .unwrap();
    assert_eq!(s.object("pot2").unwrap().mask.count(), pot);
    // Strokes for another object on the same field, then subtract it from the pot.
    s.apply(&stroke("table", "room", "table")).unwrap();
    let table = s.object("table").unwrap().mask.clone();
    let before = s.object("pot").unwrap().mask.intersection_count(&table).unwrap();
    s.apply(&Edit::Stroke {
        object: "pot".into(),
        field: None,
        polarity: Some(isrf::segment::Polarity::Negative),
        source: StrokeSource::Demo { object: "table".into() },
    })
    .unwrap();
    let after = s.object("pot").unwrap().mask.intersection_count(&table).unwrap();
    assert!(
        after <= before && after == 0,
        "a negative stroke on the table removes table voxels from the pot"
    );
    // A negative stroke cannot create an object.
    let e = s
        .apply(&Edit::Stroke {
            object: "ghost".into(),
            field: None,
            polarity: Some(isrf::segment::Polarity::Negative),
            source: StrokeSource::Demo { object: "mug".into() },
        })
        .unwrap_err();
    assert!(e.to_string().contains("negative stroke"), "{e}");
}

fn files_under(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut v = vec![];
    for e in walk(dir) {
        v.push(e.strip_prefix(dir).unwrap().to_path_buf());
    }
    v.sort();
    v
}

fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = vec![];
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

fn small_script() -> Script {
    let edits = vec![
        demo("room", "tabletop"),
        demo("shelf", "shelf"),
        Edit::SetVisible {
            target: "shelf".into(),
            visible: false,
        },
        stroke("pot", "room", "pot"),
        Edit::Remove { object: "pot".into() },
        stroke("digger", "shelf", "excavator"),
        Edit::Transform {
            object: "digger".into(),
            transform: TransformSpec::translation(Vec3::new(0.0, -0.095, -0.1)),
        },
        Edit::Appearance {
            object: "digger".into(),
            edit: ColorEdit {
                hue: 90.0,
                ..Default::default()
            },
        },
    ];
    let outputs = vec![
        orbit_render(2, 48, 36),
        Output::Export(Export::Masks {
            object: "digger".into(),
            cameras: CameraSource::Demo {
                field: "room".into(),
                eval: true,
            },
            out: "masks".into(),
            downscale: 4,
        }),
        Output::Export(Export::Mesh {
            target: "digger".into(),
            out: "digger.ply".into(),
            iso: None,
        }),
        Output::Export(Export::Composition {
            out: "comp.json".into(),
        }),
    ];
    let commands = edits.into_iter().map(Command::Edit);
    Script {
        commands: commands.chain(outputs.into_iter().map(Command::Output)).collect(),
    }
}

#[test]
fn saved_script_reruns_to_byte_identical_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let script = small_script();
    for (fmt, name) in [(Format::Ron, "s.ron"), (Format::Json, "s.json")] {
        let path = dir.path().join(name);
        save_script(&script, &path).unwrap();
        let back = load_script(&path).unwrap();
        assert_eq!(back, script, "{fmt:?} round trip");
    }
    let out1 = dir.path().join("out1");
    let out2 = dir.path().join("out2");
    run_script(&script, dir.path(), &out1, |_, _, _| {}).unwrap();
    run_script(
        &load_script(&dir.path().join("s.ron")).unwrap(),
        dir.path(),
        &out2,
        |_, _, _| {},
    )
    .unwrap();
    let files = files_under(&out1);
    assert!(files.len() >= 2 + 8 + 3, "{files:?}");
    assert_eq!(files, files_under(&out2));
    for f in &files {
        assert!(
            std::fs::read(out1.join(f)).unwrap() == std::fs::read(out2.join(f)).unwrap(),
            "{} differs",
            f.display()
        );
    }
}

#[test]
fn invalid_scripts_fail_before_writing_anything() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let cases: Vec<(&str, &str)> = vec![
        (
            r#"[load_field(name: "a", source: demo(scene: "tabletop", res: 48)), strok(object: "pot")]"#,
            "step 2",
        ),
        (
            r#"[load_field(name: "a", source: demo(scene: "tabletop", res: 48)), remove(object: "pot")]"#,
            "step 2 (remove): no object named 'pot'",
        ),
        (
            r#"[load_field(name: "a", source: demo(scene: "tabletop", res: 48)), set_params(k: 0)]"#,
            "step 2 (set_params): K must be",
        ),
        (
            r#"[load_field(name: "a", source: file("missing.safetensors"))]"#,
            "missing.safetensors: No such file",
        ),
        (
            r#"[load_field(name: "a", source: demo(scene: "kitchen"))]"#,
            "unknown demo scene 'kitchen'",
        ),
        (
            r#"[load_field(name: "a", source: demo(scene: "tabletop", res: 48)), stroke(object: "p", source: demo(object: "pot")), transform(object: "p", transform: (scale: (0.0, 1.0, 1.0)))]"#,
            "step 3 (transform)",
        ),
        (
            r#"[load_field(name: "a", source: demo(scene: "tabletop", res: 48)), stroke(object: "p", source: demo(object: "pot")), export(mesh(target: "p", out: "p.stl"))]"#,
            ".ply or .glb",
        ),
        (
            r#"[load_field(name: "a", source: demo(scene: "tabletop", res: 48)), load_field(name: "a", source: demo(scene: "shelf", res: 48))]"#,
            "already used",
        ),
    ];
    for (text, want) in cases {
        let err = parse_script(text, Format::Ron)
            .and_then(|s| run_script(&s, dir.path(), &out, |_, _, _| {}))
            .unwrap_err()
            .to_string();
        assert!(err.contains(want), "{text}\n -> {err}\n wanted: {want}");
        assert!(files_under(&out).is_empty(), "nothing may be written for: {text}");
    }
    // A runtime failure (a stroke on empty space) after a render also leaves nothing behind.
    let text = r#"#![enable(implicit_some)]
    [load_field(name: "a", source: demo(scene: "tabletop", res: 48)),
     render(cameras: demo(field: "a"), out: "r", frames: 1, downscale: 4),
     stroke(object: "sky", source: inline((camera: (transform_matrix: ((1,0,0,0),(0,1,0,0),(0,0,1,3),(0,0,0,1)), fl_x: 50, w: 20, h: 20), points: [(1, 1)])))]"#;
    let s = parse_script(text, Format::Ron).unwrap();
    validate_script(&s, dir.path()).unwrap();
    let err = run_script(&s, dir.path(), &out, |_, _, _| {}).unwrap_err().to_string();
    assert!(err.contains("step 3 (stroke)") && err.contains("empty space"), "{err}");
    assert!(files_under(&out).is_empty());
}

#[test]
fn compositions_round_trip_and_report_changed_files() {
    let dir = tempfile::tempdir().unwrap();
    // A field file plus a demo field, one moved and recoloured object.
    let scene = isrf::demo::build("shelf", RES, 0).unwrap();
    scene.field.save(&dir.path().join("shelf.safetensors")).unwrap();
    let mut s = Session::new(dir.path(), dir.path());
    s.apply(&demo("room", "tabletop")).unwrap();
    s.apply(&Edit::LoadField {
        name: "shelf".into(),
        source: FieldSource::File("shelf.safetensors".into()),
        transform: None,
    })
    .unwrap();
    s.apply(&stroke("pot", "room", "pot")).unwrap();
    s.apply(&Edit::Transform {
        object: "pot".into(),
        transform: TransformSpec {
            translate: [0.1, 0.0, 0.3],
            rotate: [0.0, 30.0, 0.0],
            ..Default::default()
        },
    })
    .unwrap();
    s.apply(&Edit::Appearance {
        object: "pot".into(),
        edit: ColorEdit {
            saturation: 0.0,
            ..Default::default()
        },
    })
    .unwrap();
    s.apply(&Edit::SetVisible {
        target: "shelf".into(),
        visible: false,
    })
    .unwrap();
    let before = image(&s);
    let doc = dir.path().join("comp.json");
    composition::save(&s, &doc).unwrap();
    let back = composition::load(&doc, dir.path()).unwrap();
    assert_eq!(image(&back), before);
    assert_eq!(back.state().objects.len(), 1);
    // Objects keep the keys documents always had (the placement is
    // flattened into them), and RON documents read back the same.
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&doc).unwrap()).unwrap();
    let mut keys: Vec<&str> = json["objects"][0]
        .as_object()
        .unwrap()
        .keys()
        .map(|k| k.as_str())
        .collect();
    keys.sort();
    assert_eq!(
        keys,
        [
            "color_edit",
            "duplicate",
            "field",
            "name",
            "removed",
            "transform",
            "visible"
        ]
    );
    let ron_doc = dir.path().join("comp.ron");
    composition::save(&s, &ron_doc).unwrap();
    let back = composition::load(&ron_doc, dir.path()).unwrap();
    assert_eq!(image(&back), before);
    assert_eq!(back.state().objects[0].placement, s.state().objects[0].placement);
    // `isrf info` opens the document and says what it holds.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_isrf"))
        .arg("info")
        .arg(&doc)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8_lossy(&out.stdout);
    let voxels = s.state().objects[0].mask.count();
    assert!(
        text.contains(&format!("'pot' of 'room': {voxels} voxels, moved by [")),
        "{text}"
    );
    assert!(text.contains("rotated / scaled, colour edit"), "{text}");
    let shelf = text
        .lines()
        .find(|l| l.contains("field       'shelf'"))
        .unwrap_or_default();
    assert!(shelf.ends_with(", hidden"), "{text}");
    // A misspelt object key is refused, naming the object and the key.
    let mut typo = json.clone();
    typo["objects"][0]["remvoed"] = true.into();
    let typo_doc = dir.path().join("typo.json");
    std::fs::write(&typo_doc, serde_json::to_vec(&typo).unwrap()).unwrap();
    let e = composition::load(&typo_doc, dir.path()).unwrap_err().to_string();
    assert!(e.contains("object 'pot'") && e.contains("remvoed"), "{e}");
    // A changed field file is reported by name.
    let p = dir.path().join("shelf.safetensors");
    let mut bytes = std::fs::read(&p).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&p, &bytes).unwrap();
    let e = composition::load(&doc, dir.path()).unwrap_err().to_string();
    assert!(e.contains("field 'shelf'") && e.contains("changed"), "{e}");
    std::fs::remove_file(&p).unwrap();
    let e = composition::load(&doc, dir.path()).unwrap_err().to_string();
    assert!(e.contains("field 'shelf'") && e.contains("missing"), "{e}");
}

/// A bitmap whose resolution is not its field's: the error names the
/// bitmaps file and the composition.
#[test]
fn composition_bitmap_resolution_error_names_the_files() {
    let dir = tempfile::tempdir().unwrap();
    let scene = isrf::demo::build("shelf", RES, 0).unwrap();
    scene.field.save(&dir.path().join("shelf.safetensors")).unwrap();
    let mut s = Session::new(dir.path(), dir.path());
    s.apply(&Edit::LoadField {
        name: "shelf".into(),
        source: FieldSource::File("shelf.safetensors".into()),
        transform: None,
    })
    .unwrap();
    let mut st = s.state().clone();
    let mask = std::sync::Arc::new(isrf::field::Bitmap::new([4, 5, 6]));
    st.add_object("box", st.fields[0].id, mask, Default::default());
    let s = Session::with_state(dir.path(), dir.path(), st);
    let doc = dir.path().join("comp.json");
    composition::save(&s, &doc).unwrap();
    let e = composition::load(&doc, dir.path()).unwrap_err().to_string();
    assert!(
        e.contains("comp.bitmaps.") && e.contains("comp.json") && e.contains("bitmap resolution [4, 5, 6]"),
        "{e}"
    );
}

/// A frame renderer that records the session's progress at every frame.
struct ProgressProbe {
    progress: isrf::util::Progress,
    seen: Vec<(String, u64, u64)>,
}

impl isrf::command::FrameRenderer for ProgressProbe {
    fn render_rgb(&mut self, _scene: std::sync::Arc<isrf::render::Scene>, camera: &Camera) -> isrf::Result<Vec<Vec3>> {
        let p = self.progress.get().expect("progress is set while rendering");
        self.seen.push((p.stage, p.done, p.total));
        Ok(vec![
            Vec3::splat(0.5);
            camera.intrinsics.width as usize * camera.intrinsics.height as usize
        ])
    }
}

#[test]
fn commands_report_progress_and_clear_it() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = Session::new(dir.path(), dir.path());
    s.apply(&demo("room", "tabletop")).unwrap();
    assert!(s.progress.get().is_none(), "cleared once the command returns");
    let render = orbit_render(3, 8, 6);
    let mut probe = ProgressProbe {
        progress: s.progress.clone(),
        seen: vec![],
    };
    perform(&mut s, &render.into(), Some(&mut probe)).unwrap();
    let want: Vec<(String, u64, u64)> = (0..3).map(|i| ("rendering".to_string(), i, 3)).collect();
    assert_eq!(probe.seen, want);
    assert!(s.progress.get().is_none());
    // A failing command clears it too.
    assert!(s.apply(&stroke("x", "nope", "pot")).is_err());
    assert!(s.progress.get().is_none());
}

#[test]
fn script_strokes_may_name_a_view_of_the_fields_capture() {
    // A field file with `isrf train`'s `<stem>.cameras.json` beside it; a
    // stroke file names one of its views instead of spelling the camera out.
    let dir = tempfile::tempdir().unwrap();
    let scene = isrf::demo::build("tabletop", RES, 0).unwrap();
    scene.field.save(&dir.path().join("room.safetensors")).unwrap();
    let frame = isrf::camera::CameraFrame {
        name: "./views/stroke_view".into(),
        camera: scene.stroke_camera,
    };
    isrf::camera::CameraSet { frames: vec![frame] }
        .save(&dir.path().join("room.cameras.json"))
        .unwrap();
    let pot = scene.object("pot").unwrap();
    let points: Vec<[f32; 2]> = pot
        .stroke
        .iter()
        .filter_map(|&p| isrf::demo::strokes::pixel_of(&scene.stroke_camera, p))
        .map(|p| [p[0] as f32 + 0.5, p[1] as f32 + 0.5])
        .collect();
    let doc = serde_json::json!({
        "object": "pot", "radius": isrf::demo::STROKE_RADIUS,
        "points": points, "camera": {"file_path": "stroke_view"}
    });
    std::fs::write(dir.path().join("pot.json"), doc.to_string()).unwrap();
    let script = Script {
        commands: vec![
            Edit::LoadField {
                name: "room".into(),
                source: FieldSource::File("room.safetensors".into()),
                transform: None,
            }
            .into(),
            Edit::Stroke {
                object: "pot".into(),
                field: None,
                polarity: None,
                source: StrokeSource::File("pot.json".into()),
            }
            .into(),
        ],
    };
    validate_script(&script, dir.path()).unwrap();
    let mut named = Session::new(dir.path(), dir.path());
    for c in &script.commands {
        perform(&mut named, c, None).unwrap();
    }
    // The same object as the demo's built-in stroke on the same camera.
    let builtin = tabletop_with_pot();
    let mask = |s: &Session| s.object("pot").unwrap().mask.clone();
    assert!(mask(&named).count() > 0);
    assert_eq!(*mask(&named), *mask(&builtin));
    // The file does not say which way is up; the cameras beside it do.
    let up = |s: &Session| s.field("room").unwrap().field.up;
    assert_eq!(up(&named), Some(scene.stroke_camera.up()));
    // Without the cameras file the view cannot be found: a clear error.
    std::fs::remove_file(dir.path().join("room.cameras.json")).unwrap();
    let mut bare = Session::new(dir.path(), dir.path());
    perform(&mut bare, &script.commands[0], None).unwrap();
    assert_eq!(up(&bare), None);
    let e = perform(&mut bare, &script.commands[1], None).unwrap_err().to_string();
    assert!(e.contains("transform_matrix"), "{e}");
}

/// A `duplicate` with no transform shares its source's mask and placement:
/// the original's 2D mask (probe) must still come from its field's layer,
/// the copy's from its own.
#[test]
fn an_untransformed_duplicate_does_not_take_the_originals_layer() {
    let mut s = Session::default();
    s.apply(&demo("t", "tabletop")).unwrap();
    s.apply(&stroke("pot", "t", "pot")).unwrap();
    s.apply(&Edit::Duplicate {
        object: "pot".into(),
        name: "copy".into(),
        transform: None,
    })
    .unwrap();
    let composed = s.state().compose();
    assert_eq!(composed.scene.layers.len(), 2, "the field, and the copy's own layer");
    let probe = |name: &str| s.state().probe(&composed, s.object(name).unwrap().id).unwrap();
    assert_eq!(probe("pot").layer, 0, "the original sits in its field's layer");
    assert_eq!(probe("copy").layer, 1, "the copy has its own layer");
}

/// Undo reaches back a bounded number of edits; the edit log keeps them
/// all; the grids of a field deleted before the oldest kept step are freed.
#[test]
fn undo_keeps_a_bounded_history_and_frees_deleted_fields() {
    let mut s = Session::default().with_undo_limit(3);
    assert_eq!(Session::default().undo_limit(), 100);
    s.apply(&demo("room", "tabletop")).unwrap();
    let grids = std::sync::Arc::downgrade(&s.state().fields[0].field);
    s.apply(&Edit::Delete { target: "room".into() }).unwrap();
    let k = |k| Edit::SetParams {
        rule: None,
        k: Some(k),
        theta: None,
        sigma_f: None,
        sigma_s: None,
        tau: None,
        growth: None,
        theta_grow: None,
        solid_alpha: None,
        connected: None,
        cut_rounds: None,
        cut_lambda: None,
        coarse: None,
    };
    s.apply(&k(4)).unwrap();
    s.apply(&k(5)).unwrap();
    assert!(grids.upgrade().is_some(), "undo can still bring the field back");
    s.apply(&k(6)).unwrap();
    assert!(grids.upgrade().is_none(), "the deleted field's grids are freed");
    assert_eq!(s.log().len(), 5, "the log keeps every edit");
    let mut undone = 0;
    while s.undo().is_some() {
        undone += 1;
    }
    assert_eq!(undone, 3);
    assert_eq!(s.log().len(), 2);
    assert!(s.state().fields.is_empty() && s.state().params.k != 4);
    assert!(s.redo().is_some());
    assert_eq!(s.state().params.k, 4);
}

/// Checking a script is a dry run of the session's own rules: what the run
/// would refuse, the check refuses, at the same step, with an error a
/// caller can match on.
#[test]
fn a_script_check_refuses_what_its_run_would() {
    use isrf::Error;
    let dir = tempfile::tempdir().unwrap();
    let masks = Output::Export(Export::Masks {
        object: "pot".into(),
        cameras: CameraSource::Demo {
            field: "room".into(),
            eval: false,
        },
        out: "masks".into(),
        downscale: 8,
    });
    let script = Script {
        commands: vec![
            demo("room", "tabletop").into(),
            stroke("pot", "room", "pot").into(),
            Edit::Remove { object: "pot".into() }.into(),
            masks.into(),
        ],
    };
    let checked = validate_script(&script, dir.path()).unwrap_err();
    let ran = run_script(&script, dir.path(), &dir.path().join("out"), |_, _, _| {}).unwrap_err();
    assert_eq!(checked.to_string(), ran.to_string());
    assert!(
        matches!(
            checked,
            Error::Step {
                step: 4,
                kind: "export",
                ..
            }
        ),
        "{checked}"
    );
    assert!(checked.to_string().contains("removed or hidden"), "{checked}");

    let script = Script {
        commands: vec![
            demo("room", "tabletop").into(),
            Edit::Rename {
                target: "room".into(),
                name: "kitchen".into(),
            }
            .into(),
            Edit::Remove { object: "mug".into() }.into(),
        ],
    };
    let e = validate_script(&script, dir.path()).unwrap_err();
    assert!(matches!(e, Error::Step { step: 3, .. }), "{e}");
    assert!(
        matches!(e.root(), Error::UnknownName { kind: "object", name, .. } if name == "mug"),
        "{e}"
    );
    assert_eq!(
        e.to_string(),
        "step 3 (remove): no object named 'mug' (there are: none)"
    );

    let tiny = Edit::LoadField {
        name: "room".into(),
        source: FieldSource::Demo {
            scene: "tabletop".into(),
            res: 8,
            seed: 0,
        },
        transform: None,
    };
    let e = validate_script(
        &Script {
            commands: vec![tiny.into()],
        },
        dir.path(),
    )
    .unwrap_err();
    assert!(matches!(e.root(), Error::OutOfRange(_)), "{e}");
    assert_eq!(
        e.to_string(),
        "step 1 (load_field): demo resolution 8 is out of range (16..=512)"
    );
}

#[test]
fn set_params_switches_joined_seeds_and_undo_restores_them() {
    let mut s = Session::default();
    assert!(
        s.state().params.connected,
        "the default keeps the seeds joined to the stroke"
    );
    let script = parse_script("[set_params(connected: false, theta: 0.25)]", Format::Ron).unwrap();
    for c in &script.commands {
        isrf::command::output::perform(&mut s, c, None).unwrap();
    }
    assert!(!s.state().params.connected);
    assert_eq!(s.state().params.theta, 0.25);
    s.undo();
    assert!(s.state().params.connected);
}

/// The graph cut is switched and weighted through `set_params` (the
/// editor's sliders send the same edit); out-of-range values are refused
/// by name and leave the parameters as they were; undo restores them.
#[test]
fn set_params_sets_the_graph_cut_and_refuses_bad_values() {
    let mut s = Session::default();
    let defaults = s.state().params.cut;
    assert!(defaults.rounds > 0, "the cut is on by default");
    let run = |s: &mut Session, text: &str| -> isrf::Result<()> {
        for c in &parse_script(text, Format::Ron).unwrap().commands {
            isrf::command::output::perform(s, c, None)?;
        }
        Ok(())
    };
    run(&mut s, "[set_params(cut_rounds: 0, cut_lambda: 2.0)]").unwrap();
    assert_eq!(s.state().params.cut.rounds, 0);
    assert_eq!(s.state().params.cut.lambda, 2.0);
    let e = run(&mut s, "[set_params(cut_rounds: 99)]").unwrap_err().to_string();
    assert!(e.contains("cut rounds"), "{e}");
    let e = run(&mut s, "[set_params(cut_lambda: -1.0)]").unwrap_err().to_string();
    assert!(e.contains("cut lambda"), "{e}");
    assert_eq!(s.state().params.cut.rounds, 0, "a refused edit changes nothing");
    s.undo();
    assert_eq!(s.state().params.cut, defaults);
}

/// A step that does not parse is reported as a syntax error a caller can
/// match on, with its step number, in RON and JSON, from text and from a
/// file (whose name the message keeps); text that is not a list at all has
/// no step.
#[test]
fn a_step_that_does_not_parse_is_a_syntax_error_with_its_number() {
    use isrf::Error;
    let ron = r#"[load_field(name: "a", source: demo(scene: "tabletop")), strok(object: "p")]"#;
    let json = r#"[{"load_field": {"name": "a", "source": {"demo": {"scene": "tabletop"}}}},
                   {"set_params": {"theta": 0.3}},
                   {"render": {"cameras": {"demo": {"field": "a"}}, "outt": "r"}}]"#;
    for (text, format, step, word) in [(ron, Format::Ron, 2, "strok"), (json, Format::Json, 3, "outt")] {
        let e = parse_script(text, format).unwrap_err();
        let msg = e.to_string();
        assert!(
            matches!(&e, Error::ScriptSyntax { step: s, .. } if *s == step),
            "{format:?}: {e:?}"
        );
        assert_eq!(e.step(), Some(step));
        assert!(
            msg.starts_with(&format!("step {step}: ")) || msg.contains(&format!("step {step}: ")),
            "{msg}"
        );
        assert!(msg.contains(word), "{msg}");
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("typo.ron");
    std::fs::write(&path, ron).unwrap();
    let e = load_script(&path).unwrap_err();
    assert_eq!(e.step(), Some(2), "{e:?}");
    assert!(
        e.to_string().contains("typo.ron") && e.to_string().contains("step 2: "),
        "{e}"
    );
    // Not a list of commands: an error, but about no step.
    let e = parse_script("{ nonsense", Format::Json).unwrap_err();
    assert_eq!(e.step(), None, "{e:?}");
    // A later, valid parse does not inherit the failed step.
    assert!(parse_script("[]", Format::Ron).unwrap().commands.is_empty());
}

/// A script's check and its run agree where the dry run cannot read grids:
/// a missing field file fails both with the same I/O error, and a stroke on
/// a field without semantic features fails both with the same reason.
#[test]
fn checks_and_runs_agree_on_missing_files_and_fields_without_features() {
    use isrf::Error;
    let dir = tempfile::tempdir().unwrap();
    let plain = dir.path().join("plain.safetensors");
    FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [16; 3])
        .build(|p| if p.length() < 0.5 { 5.0 } else { -5.0 }, |_| Vec3::ONE, None)
        .save(&plain)
        .unwrap();
    let stroke = r#"stroke(object: "ball", source: inline((camera: (transform_matrix: ((1,0,0,0),(0,1,0,0),(0,0,1,3),(0,0,0,1)), fl_x: 20, w: 20, h: 20), points: [(10, 10)])))"#;
    for (file, want) in [
        ("plain.safetensors", "no semantic features"),
        ("missing.safetensors", "missing.safetensors"),
    ] {
        let text = format!(r#"[load_field(name: "a", source: file("{file}")), {stroke}]"#);
        let script = parse_script(&text, Format::Ron).unwrap();
        let checked = validate_script(&script, dir.path()).unwrap_err();
        let ran = run_script(&script, dir.path(), &dir.path().join("out"), |_, _, _| {}).unwrap_err();
        assert_eq!(checked.to_string(), ran.to_string(), "{file}");
        assert!(checked.to_string().contains(want), "{checked}");
        if file.starts_with("missing") {
            assert!(matches!(checked.root(), Error::Io { .. }), "{checked:?}");
        }
    }
}
