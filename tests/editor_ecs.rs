//! The editor's model side, driven like the UI drives it: stroke messages
//! become session commands, the object entity's bitmap equals the library's
//! result for the same stroke, and undo / redo return to identical states.
//! No window and no GPU needed.
#![cfg(feature = "editor")]

use bevy::prelude::*;
use isrf::app::editor::session::{EditorSession, Request};
use isrf::app::editor::state::StrokeMsg;
use isrf::app::editor::EditorCorePlugin;
use isrf::app::layers::{ObjectLayer, Selected, SessionName};
use isrf::app::MarchScene;
use isrf::command::{Edit, FieldSource, Session};
use isrf::render::{Layer, Scene};
use isrf::segment::{apply_region, region_from_stroke, Polarity, SegmentParams, Stroke};
use std::sync::Arc;

mod common;
use common::settle;

const RES: usize = 40;

fn app() -> App {
    let mut app = App::new();
    let mut es = EditorSession::new(Session::default());
    es.apply(Edit::LoadField {
        name: "tabletop".into(),
        source: FieldSource::Demo {
            scene: "tabletop".into(),
            res: RES,
            seed: 0,
        },
        transform: None,
    });
    app.add_plugins(MinimalPlugins)
        .insert_resource(es)
        .add_plugins(EditorCorePlugin);
    settle(&mut app);
    app
}

fn objects(app: &mut App) -> Vec<(String, Arc<isrf::field::Bitmap>, bool)> {
    let mut q = app.world_mut().query::<(&SessionName, &ObjectLayer, Has<Selected>)>();
    let mut v: Vec<_> = q
        .iter(app.world())
        .map(|(n, o, s)| (n.0.clone(), o.bitmap.clone(), s))
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

fn demo_stroke(object: &str) -> Stroke {
    let d = isrf::demo::build("tabletop", RES, 0).unwrap();
    let o = d.object(object).unwrap();
    let points = d
        .stroke_pixels(o)
        .into_iter()
        .map(|[x, y]| glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5))
        .collect();
    Stroke {
        camera: d.stroke_camera,
        points,
        radius: 3,
        polarity: Polarity::Positive,
        object: object.into(),
        joined: true,
    }
}

/// A positive stroke on a demo object, sent as the brush sends it, and
/// waited for.
fn paint(app: &mut App, object: &str) {
    let stroke = demo_stroke(object);
    app.world_mut().write_message(StrokeMsg {
        camera: stroke.camera,
        points: stroke.points,
        radius: stroke.radius,
        polarity: Polarity::Positive,
    });
    settle(app);
}

#[test]
fn strokes_through_the_ecs_equal_the_library_and_undo_redo_restore() {
    let mut app = app();
    assert_eq!(
        app.world().resource::<EditorSession>().state().fields.len(),
        1,
        "the demo field loads"
    );
    paint(&mut app, "mug");
    let objs = objects(&mut app);
    assert_eq!(objs.len(), 1, "the stroke made one object");
    let (name, bitmap, selected) = objs[0].clone();
    assert!(selected, "the new object is selected");

    // The library's answer for the same stroke on the same field.
    let stroke = demo_stroke("mug");
    let es = app.world().resource::<EditorSession>();
    let field = es.state().fields[0].field.clone();
    let scene = Scene::new(vec![Layer::new(field.clone())]);
    let cache = field.feature_cache().unwrap();
    let params = SegmentParams::default();
    let (region, _) = region_from_stroke(&scene, &cache, &stroke, &params).unwrap();
    let mut want = isrf::field::Bitmap::new(field.res());
    apply_region(&mut want, &region, Polarity::Positive).unwrap();
    assert!(want.count() > 20, "the mug stroke selects something");
    assert_eq!(*bitmap, want, "ECS object == library segmentation");

    // The scene for the GPU tints the selection in place: still one layer,
    // with the object's bitmap as its highlight mask.
    let march = app.world().resource::<MarchScene>();
    assert_eq!(march.scene.as_ref().unwrap().layers.len(), 1);
    let ov = &march.overlay[0];
    assert!(ov.highlight);
    assert_eq!(**ov.highlight_mask.as_ref().unwrap(), *bitmap);

    // A second (negative) stroke on the selected object, then undo / redo.
    let mut neg = stroke.clone();
    neg.points.truncate(neg.points.len().div_ceil(2));
    app.world_mut().write_message(StrokeMsg {
        camera: neg.camera,
        points: neg.points.clone(),
        radius: 1,
        polarity: Polarity::Negative,
    });
    settle(&mut app);
    let after_neg = objects(&mut app)[0].1.clone();
    assert!(after_neg.count() < bitmap.count(), "the negative stroke removed voxels");

    app.world_mut().resource_mut::<EditorSession>().push(Request::Undo);
    settle(&mut app);
    assert_eq!(*objects(&mut app)[0].1, *bitmap, "undo restores the first mask");
    app.world_mut().resource_mut::<EditorSession>().push(Request::Undo);
    settle(&mut app);
    assert!(objects(&mut app).is_empty(), "undo removes the object");
    app.world_mut().resource_mut::<EditorSession>().push(Request::Redo);
    app.world_mut().resource_mut::<EditorSession>().push(Request::Redo);
    settle(&mut app);
    let objs = objects(&mut app);
    assert_eq!(objs[0].0, name);
    assert_eq!(*objs[0].1, *after_neg, "redo returns to the same state");
}

/// The `+` key grows the selected object one step (the library's `Grower`
/// on the same mask); a placement the entity holds ahead of the session
/// (a drag) shows in the GPU scene, is committed as one `Transform`
/// command, and undo puts entity, session and scene back.
#[test]
fn keyboard_growth_and_a_committed_drag_go_through_commands() {
    use isrf::app::editor::tools::transform_command;
    use isrf::app::editor::{keyboard_shortcuts, EditorSystems};
    use isrf::segment::{Grower, Growth};

    let mut app = app();
    app.init_resource::<ButtonInput<KeyCode>>()
        .add_systems(Update, keyboard_shortcuts.before(EditorSystems::Model));
    // A tight seed and strokes without growth, so that the key's step has
    // work to do.
    app.world_mut().resource_mut::<EditorSession>().apply(Edit::SetParams {
        rule: None,
        k: None,
        theta: Some(0.02),
        sigma_f: None,
        sigma_s: None,
        tau: None,
        growth: Some(Growth::Steps(0)),
        theta_grow: None,
        solid_alpha: None,
        connected: None,
        cut_rounds: None,
        cut_lambda: None,
        coarse: None,
    });
    paint(&mut app, "mug");
    let (name, before, _) = objects(&mut app)[0].clone();

    // Grow one step with the keyboard.
    let mut keys = app.world_mut().resource_mut::<ButtonInput<KeyCode>>();
    keys.press(KeyCode::Equal);
    app.update();
    app.world_mut()
        .resource_mut::<ButtonInput<KeyCode>>()
        .release(KeyCode::Equal);
    app.world_mut().resource_mut::<ButtonInput<KeyCode>>().clear();
    settle(&mut app);
    let grown = objects(&mut app)[0].1.clone();
    let es = app.world().resource::<EditorSession>();
    let cache = es.state().fields[0].field.feature_cache().unwrap();
    let mut want = (*before).clone();
    Grower::new(&cache, es.state().params.grow).step(&mut want);
    assert_eq!(*grown, want, "keyboard growth == library growth");
    assert!(grown.count() > before.count(), "one more step adds voxels");
    assert!(matches!(
        es.session().unwrap().log().last(),
        Some(Edit::Grow {
            steps: Growth::Steps(1),
            ..
        })
    ));

    // Drag: the entity moves first (preview), the scene follows.
    let entity = {
        let mut q = app.world_mut().query::<(Entity, &SessionName)>();
        q.iter(app.world()).find(|(_, n)| n.0 == name).unwrap().0
    };
    let start = *app.world().get::<Transform>(entity).unwrap();
    let moved = start.with_translation(Vec3::new(0.3, 0.0, -0.2));
    *app.world_mut().get_mut::<Transform>(entity).unwrap() = moved;
    app.update();
    let scene = app.world().resource::<MarchScene>().scene.clone().unwrap();
    assert!(
        scene
            .layers
            .iter()
            .any(|l| (l.to_world.translation - glam::Vec3A::new(0.3, 0.0, -0.2)).length() < 1e-6),
        "the preview placement reaches the GPU scene"
    );
    // Release: one command.
    let cmd = transform_command(&name, &start, &moved);
    app.world_mut().resource_mut::<EditorSession>().apply(cmd);
    settle(&mut app);
    let es = app.world().resource::<EditorSession>();
    let placed = es.state().objects[0].placement.transform;
    assert!((placed.translation - glam::Vec3A::new(0.3, 0.0, -0.2)).length() < 1e-5);
    assert!(matches!(
        es.session().unwrap().log().last(),
        Some(Edit::Transform { .. })
    ));

    app.world_mut().resource_mut::<EditorSession>().push(Request::Undo);
    settle(&mut app);
    assert_eq!(
        *app.world().get::<Transform>(entity).unwrap(),
        start,
        "undo moves the entity back"
    );
    assert_eq!(*objects(&mut app)[0].1, want, "undo of the move keeps the grown mask");
}

/// Pointer input as winit would deliver it: the cursor moves over a window
/// whose 3D view is offset to the right (a side panel), the left button
/// presses on a gizmo ring, drags a quarter of the way round and releases.
#[test]
fn a_mouse_drag_on_a_gizmo_ring_turns_the_object_about_that_axis() {
    use bevy::camera::{ComputedCameraValues, RenderTargetInfo, Viewport};
    use bevy::window::{PrimaryWindow, WindowResolution};
    use isrf::app::editor::camera::EditorCamera;
    use isrf::app::editor::state::{GizmoView, Handle, TransformMode};
    use isrf::app::editor::tools::{gizmo, pick_handle, transform_modes};
    use isrf::app::editor::EditorSystems;

    let mut app = app();
    app.init_resource::<ButtonInput<KeyCode>>()
        .init_resource::<ButtonInput<MouseButton>>()
        .add_systems(Update, (gizmo, transform_modes).chain().before(EditorSystems::Model));
    paint(&mut app, "mug");
    let (name, _, selected) = objects(&mut app)[0].clone();
    assert!(selected, "a new object is selected");

    // An 800×600 window; the view is its right 600×600 (offset 200 px).
    let window = app
        .world_mut()
        .spawn((
            Window {
                resolution: WindowResolution::new(800, 600),
                ..default()
            },
            PrimaryWindow,
        ))
        .id();
    let mut camera = Camera {
        viewport: Some(Viewport {
            physical_position: UVec2::new(200, 0),
            physical_size: UVec2::new(600, 600),
            ..default()
        }),
        ..default()
    };
    camera.computed = ComputedCameraValues {
        clip_from_view: Mat4::perspective_infinite_reverse_rh(0.9, 1.0, 0.05),
        target_info: Some(RenderTargetInfo {
            physical_size: UVec2::new(800, 600),
            scale_factor: 1.0,
        }),
        ..default()
    };
    let eye = Transform::from_xyz(0.6, 1.2, 2.2).looking_at(Vec3::new(0.0, -0.2, 0.0), Vec3::Y);
    app.world_mut()
        .spawn((camera, GlobalTransform::from(eye), EditorCamera));
    let set_cursor = |app: &mut App, p: Vec2| {
        app.world_mut()
            .get_mut::<Window>(window)
            .unwrap()
            .set_cursor_position(Some(p));
    };
    set_cursor(&mut app, Vec2::new(10.0, 10.0));
    app.update();
    let view: GizmoView = app.world().resource::<GizmoView>().clone();
    let centre = view.center.expect("the selected object shows a gizmo");
    assert!(centre.x > 200.0, "the gizmo sits inside the view, right of the panel");
    // A point of the ring about Y that picks that ring, and the point a
    // quarter turn further round.
    let ring = &view.rings[1];
    assert_eq!(ring.len() % 4, 0);
    let rotate_y = Some(Handle {
        mode: TransformMode::Rotate,
        axis: Some(1),
    });
    let k = (0..ring.len())
        .find(|&k| {
            pick_handle(&view, ring[k]) == rotate_y
                && pick_handle(&view, ring[(k + ring.len() / 4) % ring.len()]) == rotate_y
        })
        .expect("the Y ring is visible and pickable");
    let (p0, p1) = (ring[k], ring[(k + ring.len() / 4) % ring.len()]);

    let entity = {
        let mut q = app.world_mut().query::<(Entity, &SessionName)>();
        q.iter(app.world()).find(|(_, n)| n.0 == name).unwrap().0
    };
    let start = *app.world().get::<Transform>(entity).unwrap();
    set_cursor(&mut app, p0);
    app.update();
    assert_eq!(app.world().resource::<GizmoView>().hovered, rotate_y);
    app.world_mut()
        .resource_mut::<ButtonInput<MouseButton>>()
        .press(MouseButton::Left);
    app.update();
    app.world_mut().resource_mut::<ButtonInput<MouseButton>>().clear();
    set_cursor(&mut app, p1);
    app.update();
    let dragged = *app.world().get::<Transform>(entity).unwrap();
    let (axis, angle) = (dragged.rotation * start.rotation.inverse()).to_axis_angle();
    assert!(axis.cross(Vec3::Y).length() < 1e-3, "turned about Y, not {axis}");
    assert!(
        (angle - std::f32::consts::FRAC_PI_2).abs() < 0.02,
        "a quarter turn, not {angle}"
    );
    // The turn is about the object's centre: the gizmo stays where it was.
    app.update();
    let c2 = app.world().resource::<GizmoView>().center.unwrap();
    assert!(c2.distance(centre) < 0.5, "{c2} vs {centre}");

    // Release: one Transform command, and the session agrees.
    app.world_mut()
        .resource_mut::<ButtonInput<MouseButton>>()
        .release(MouseButton::Left);
    app.update();
    settle(&mut app);
    let es = app.world().resource::<EditorSession>();
    assert!(matches!(
        es.session().unwrap().log().last(),
        Some(Edit::Transform { .. })
    ));
    let placed = isrf::app::convert::to_bevy_mat4(&es.state().objects[0].placement.transform);
    let shown = app.world().get::<Transform>(entity).unwrap().to_matrix();
    assert!(placed.abs_diff_eq(shown, 1e-4), "{placed:?} vs {shown:?}");
}

/// Names are labels: a rename (and its undo) keeps the entity, its
/// selection and its placement preview, and only relabels it.
#[test]
fn a_rename_relabels_the_same_entity() {
    let mut app = app();
    paint(&mut app, "mug");
    let (entity, id, old) = {
        let mut q = app.world_mut().query::<(Entity, &SessionName, &ObjectLayer)>();
        let (e, n, o) = q.single(app.world()).unwrap();
        (e, o.id, n.0.clone())
    };
    let rename = |app: &mut App, from: &str, to: &str| {
        let r = Edit::Rename {
            target: from.into(),
            name: to.into(),
        };
        app.world_mut().resource_mut::<EditorSession>().apply(r);
        settle(app);
    };
    let label = |app: &mut App| {
        let w = app.world();
        let layer = w.get::<ObjectLayer>(entity).expect("the same entity");
        assert_eq!(layer.id, id);
        assert!(w.get::<Selected>(entity).is_some(), "still selected");
        let (n, name) = (w.get::<SessionName>(entity).unwrap(), w.get::<Name>(entity).unwrap());
        assert_eq!(n.0, name.as_str());
        n.0.clone()
    };
    rename(&mut app, &old, "cup");
    assert_eq!(label(&mut app), "cup");
    app.world_mut().resource_mut::<EditorSession>().push(Request::Undo);
    settle(&mut app);
    assert_eq!(label(&mut app), old);
    assert_eq!(objects(&mut app).len(), 1);
}

/// File → Import splats runs as a request (off the UI thread): the `.ply`
/// becomes `<file>.safetensors` beside it, a field named after the file
/// (a fresh name when taken) joins the session and undo removes it; a bad
/// file is an error in the status, the session unchanged.
#[test]
fn splat_import_is_a_request_that_adds_a_field_and_undoes() {
    let mut app = app();
    let dir = tempfile::tempdir().unwrap();
    let ply = dir.path().join("tabletop.ply");
    let demo = isrf::demo::build("tabletop", 32, 0).unwrap();
    isrf::splat::export::export(&demo.field, &isrf::splat::export::Selection::whole(), &ply).unwrap();
    app.world_mut()
        .resource_mut::<EditorSession>()
        .push(Request::ImportSplats(ply.clone()));
    settle(&mut app);
    let names: Vec<String> = {
        let es = app.world().resource::<EditorSession>();
        es.state().fields.iter().map(|f| f.name.clone()).collect()
    };
    assert_eq!(names, ["tabletop", "tabletop 2"], "the name is taken by the demo");
    assert!(ply.with_extension("safetensors").is_file());
    let status = app
        .world()
        .resource::<isrf::app::editor::state::EditorState>()
        .status
        .clone();
    assert!(status.contains("imported") && status.contains("Gaussians"), "{status}");
    app.world_mut().resource_mut::<EditorSession>().push(Request::Undo);
    settle(&mut app);
    assert_eq!(app.world().resource::<EditorSession>().state().fields.len(), 1);
    // A file that is not a splat file: an error, nothing added.
    let bad = dir.path().join("bad.ply");
    std::fs::write(&bad, b"not a ply").unwrap();
    app.world_mut()
        .resource_mut::<EditorSession>()
        .push(Request::ImportSplats(bad));
    settle(&mut app);
    let st = app.world().resource::<isrf::app::editor::state::EditorState>();
    assert!(st.errors.iter().any(|e| e.contains("bad.ply")), "{:?}", st.errors);
    assert_eq!(app.world().resource::<EditorSession>().state().fields.len(), 1);
}

/// A start-up script's relative inputs are read from the script's folder
/// (as `isrf run` reads them), its outputs stay where the session writes:
/// `isrf edit F --script assets/scripts/fern_walk.json` then works from any
/// working folder.
#[test]
fn a_startup_scripts_inputs_are_read_from_its_own_folder() {
    use isrf::app::editor::{startup_requests, EditorOptions};
    use isrf::command::{Command, Export, Output, StrokeSource};
    let dir = tempfile::tempdir().unwrap();
    let scripts = dir.path().join("scripts");
    std::fs::create_dir(&scripts).unwrap();
    let script = scripts.join("walk.json");
    std::fs::write(
        &script,
        r#"[
 {"load_field": {"name": "b", "source": {"file": "../fields/b.safetensors"}}},
 {"stroke": {"object": "pot", "source": {"file": "../strokes/pot.json"}}},
 {"stroke": {"object": "pot", "source": {"file": "/abs/pot.json"}}},
 {"export": {"object_field": {"object": "pot", "out": "pot.safetensors"}}}
]"#,
    )
    .unwrap();
    let opts = EditorOptions {
        scene: Some("tabletop".into()),
        res: 24,
        script: Some(script.clone()),
        ..Default::default()
    };
    let reqs = startup_requests(&opts).unwrap();
    let applied: Vec<Command> = reqs
        .into_iter()
        .filter_map(|r| match r {
            Request::Apply(c) => Some(c),
            _ => None,
        })
        .collect();
    // The demo scene, then the script's four commands.
    assert_eq!(applied.len(), 5);
    let base = script.canonicalize().unwrap().parent().unwrap().to_path_buf();
    match &applied[1] {
        Command::Edit(Edit::LoadField {
            source: FieldSource::File(p),
            ..
        }) => assert_eq!(p, &base.join("../fields/b.safetensors")),
        c => panic!("unexpected {c:?}"),
    }
    let stroke_file = |c: &Command| match c {
        Command::Edit(Edit::Stroke {
            source: StrokeSource::File(p),
            ..
        }) => p.clone(),
        c => panic!("unexpected {c:?}"),
    };
    assert_eq!(stroke_file(&applied[2]), base.join("../strokes/pot.json"));
    assert_eq!(stroke_file(&applied[3]), std::path::PathBuf::from("/abs/pot.json"));
    // The output is not moved.
    match &applied[4] {
        Command::Output(Output::Export(Export::ObjectField { out, .. })) => {
            assert_eq!(out, &std::path::PathBuf::from("pot.safetensors"))
        }
        c => panic!("unexpected {c:?}"),
    }
}
