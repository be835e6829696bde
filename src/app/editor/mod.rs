//! The interactive editor: a bevy app whose entities mirror the editing
//! [`Session`](crate::command::Session) (fields and segmented objects, see
//! [`crate::app::layers`]), drawn by the GPU ray marcher, with egui panels,
//! orbit / fly cameras, a brush, transform modes and a screenshot mode.
//!
//! Every user action becomes a [`Command`] (or undo / redo) queued on
//! [`session::EditorSession`], which applies them off the frame loop; the
//! edit log, undo/redo and "save as script" therefore come from the session.
//! Systems stay thin: they read components, queue commands or call library
//! functions, and write components.

pub mod browse;
pub mod camera;
pub mod capture;
pub mod session;
pub mod splats;
pub mod state;
pub mod tools;
pub mod ui;

use crate::app::convert::{bevy_transform, from_bevy_transform, projection_for};
use crate::app::gpu::{MarchScene, RayMarchCamera, RayMarchPlugin};
use crate::app::layers::{build_scene, FieldLayer, ObjectLayer, OverlayMode, Preview, Selected, SessionName};
use crate::camera::Camera as IsrfCamera;
use crate::command::recovery::{self, Inputs, Recorder, RecoveryDoc, StartStep};
use crate::command::state::ObjectId;
use crate::command::{Edit, FieldSource, Session, StrokeSource};
use crate::segment::stroke::StrokeDoc;
use crate::segment::{Polarity, Stroke};
use crate::{Error, Result};
use bevy::core_pipeline::tonemapping::{DebandDither, Tonemapping};
use bevy::prelude::*;
use bevy::render::view::Msaa;
use bevy_egui::{EguiPlugin, EguiPrimaryContextPass};
use bevy_panorbit_camera::{PanOrbitCamera, PanOrbitCameraPlugin};
use camera::{aim_orbit, EditorCamera};
use session::{EditorSession, Request};
use state::{CurrentStroke, EditorState, StrokeMsg};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// What to open and how.
#[derive(Clone, Debug, Default)]
pub struct EditorOptions {
    /// A demo scene name (`tabletop`, `shelf`); used when no files are given.
    pub scene: Option<String>,
    /// Field files (.safetensors) or a composition (.ron / .json) to open.
    pub files: Vec<PathBuf>,
    /// Demo scene resolution (0 = 96).
    pub res: usize,
    /// Commands to apply at start-up (a script file).
    pub script: Option<PathBuf>,
    /// Save a screenshot once everything is rendered, then exit.
    pub screenshot: Option<PathBuf>,
    /// Window size in logical pixels (0 = 1280×720).
    pub size: (u32, u32),
    /// Hide the panels (clean screenshots).
    pub no_ui: bool,
    /// A recovery file of an earlier session with the same inputs:
    /// `Some(true)` replays it instead of the start-up requests,
    /// `Some(false)` starts fresh, `None` offers it in a dialog
    /// (screenshot runs start fresh).
    pub restore: Option<bool>,
    /// Where recovery files go (default [`recovery::default_dir`]).
    pub recovery_dir: Option<PathBuf>,
    /// How many edits undo reaches back (default
    /// [`DEFAULT_UNDO_LIMIT`](crate::command::session::DEFAULT_UNDO_LIMIT)).
    pub undo_steps: Option<usize>,
}

fn is_composition(p: &std::path::Path) -> bool {
    crate::command::script::Format::of(p).is_ok()
}

/// The requests that open what the options name.
pub fn startup_requests(opts: &EditorOptions) -> Result<Vec<Request>> {
    let mut out = Vec::new();
    if opts.files.is_empty() {
        let scene = opts.scene.clone().unwrap_or_else(|| "tabletop".into());
        out.push(Request::Apply(
            Edit::LoadField {
                name: scene.clone(),
                source: FieldSource::Demo {
                    scene,
                    res: if opts.res == 0 { 96 } else { opts.res },
                    seed: 0,
                },
                transform: None,
            }
            .into(),
        ));
    }
    let mut used: Vec<String> = Vec::new();
    for p in &opts.files {
        let abs = std::fs::canonicalize(p).map_err(|e| Error::io(p, e))?;
        if is_composition(&abs) {
            out.push(Request::Open(abs));
            continue;
        }
        let stem = abs
            .file_stem()
            .map_or("field".into(), |s| s.to_string_lossy().into_owned());
        let mut name = stem.clone();
        let mut i = 2;
        while used.contains(&name) {
            name = format!("{stem} {i}");
            i += 1;
        }
        used.push(name.clone());
        out.push(Request::Apply(
            Edit::LoadField {
                name,
                source: FieldSource::File(abs),
                transform: None,
            }
            .into(),
        ));
    }
    if let Some(s) = &opts.script {
        // Its relative inputs are read from its own folder, as `isrf run`
        // reads them, so a script works from any working folder.
        let script = crate::command::script::load_script(s)?;
        let dir = script_dir(s)?;
        out.extend(
            script
                .commands
                .into_iter()
                .map(|c| Request::Apply(c.with_inputs_under(&dir))),
        );
    }
    Ok(out)
}

/// The absolute folder of a script file.
fn script_dir(script: &Path) -> Result<PathBuf> {
    let abs = std::fs::canonicalize(script).map_err(|e| Error::io(script, e))?;
    Ok(abs.parent().map(Path::to_path_buf).unwrap_or(abs))
}

/// What crash recovery does at start-up.
#[derive(Debug, Default)]
pub struct RecoveryPlan {
    /// Writes this session's recovery file (none in screenshot runs: they
    /// are scripted, nothing of them can be lost).
    pub recorder: Option<Recorder>,
    /// Replay this instead of the start-up requests (`--restore`).
    pub restore: Option<RecoveryDoc>,
    /// Offer this in a dialog.
    pub offer: Option<RecoveryDoc>,
    /// Problems to show: an unreadable recovery file, `--restore` with
    /// nothing to restore.
    pub notes: Vec<String>,
}

/// The start-up requests as a recovery file names them.
fn start_steps(requests: &[Request]) -> Vec<StartStep> {
    requests
        .iter()
        .filter_map(|r| match r {
            Request::Apply(c) => Some(StartStep::Apply(c.clone())),
            Request::Open(p) => Some(StartStep::Open(p.clone())),
            Request::Undo | Request::Redo | Request::Restore(_) | Request::ImportSplats(_) => None,
        })
        .collect()
}

/// Finds the recovery file of these start-up requests (started in `cwd`)
/// and decides, from `opts.restore`, whether to replay it, offer it or
/// start fresh.
pub fn recovery_plan(opts: &EditorOptions, cwd: &Path, requests: &[Request]) -> RecoveryPlan {
    let inputs = Inputs {
        cwd: cwd.to_path_buf(),
        start: start_steps(requests),
    };
    let dir = opts.recovery_dir.clone().unwrap_or_else(recovery::default_dir);
    let recorder = Recorder::new(inputs.file_in(&dir), inputs.clone());
    let interactive = opts.screenshot.is_none();
    let mut plan = RecoveryPlan::default();
    let found = if recorder.path.exists() {
        match RecoveryDoc::load(&recorder.path) {
            Ok(d) if d.inputs == inputs => Some(d),
            Ok(_) => {
                plan.notes.push(format!(
                    "{} belongs to other inputs: not restored",
                    recorder.path.display()
                ));
                None
            }
            Err(e) => {
                plan.notes.push(format!(
                    "the recovery file is unreadable, not restored: {e} (kept as {})",
                    recorder.previous_path().display()
                ));
                None
            }
        }
    } else {
        None
    };
    match (opts.restore, found) {
        (Some(true), Some(d)) => plan.restore = Some(d),
        (Some(true), None) => plan.notes.push(format!(
            "--restore: nothing to restore (no recovery file {})",
            recorder.path.display()
        )),
        (None, Some(d)) if interactive && d.has_edits_beyond_start() => plan.offer = Some(d),
        _ => {}
    }
    plan.recorder = interactive.then_some(recorder);
    plan
}

/// The editor's model side with no window, input or GPU: the session
/// bridge, the entity mirror, strokes to commands and the scene for the ray
/// marcher. Tests drive it with [`StrokeMsg`]s.
pub struct EditorCorePlugin;

impl Plugin for EditorCorePlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<EditorState>()
            .init_resource::<state::GizmoView>()
            .init_resource::<CurrentStroke>()
            .init_resource::<SceneSync>()
            .init_resource::<MarchScene>()
            .add_message::<StrokeMsg>()
            .add_systems(
                Update,
                (
                    session::run_requests,
                    session::sync_entities,
                    strokes_to_commands,
                    select_pending,
                )
                    .chain()
                    .in_set(EditorSystems::Model),
            )
            .add_systems(PostUpdate, sync_scene);
        if !app.world().contains_resource::<EditorSession>() {
            app.insert_resource(EditorSession::new(Session::default()));
        }
    }
}

/// Ordering of the editor's systems.
#[derive(SystemSet, Debug, Clone, PartialEq, Eq, Hash)]
pub enum EditorSystems {
    /// Input: camera, brush, transform modes, shortcuts.
    Input,
    /// Session requests and the entity mirror.
    Model,
}

/// The whole editor: the core plus the GPU view, cameras, tools and (with
/// `ui`) the egui panels.
pub struct EditorPlugin {
    pub ui: bool,
}

impl Plugin for EditorPlugin {
    fn build(&self, app: &mut App) {
        // Frames on input, on change, or at least every `IDLE_FRAME`: an
        // editor left alone draws a few frames a second, not 20.
        app.insert_resource(bevy::winit::WinitSettings {
            focused_mode: bevy::winit::UpdateMode::reactive(IDLE_FRAME),
            unfocused_mode: bevy::winit::UpdateMode::reactive_low_power(IDLE_FRAME),
        })
        .add_systems(Last, redraw_while_the_camera_moves);
        app.add_plugins((EditorCorePlugin, RayMarchPlugin, PanOrbitCameraPlugin))
            .configure_sets(Update, EditorSystems::Input.before(EditorSystems::Model))
            .add_systems(Startup, spawn_camera)
            .add_systems(
                PostUpdate,
                camera::adaptive_resolution
                    .after(sync_scene)
                    .after(bevy::transform::TransformSystems::Propagate),
            )
            .add_systems(
                Update,
                (
                    tools::gizmo,
                    camera::gate_orbit,
                    camera::fly,
                    tools::brush,
                    tools::transform_modes,
                    keyboard_shortcuts,
                )
                    .chain()
                    .in_set(EditorSystems::Input),
            );
        if self.ui {
            app.add_plugins(EguiPlugin::default())
                .add_systems(Startup, ui::spawn_ui_camera)
                .add_systems(
                    PreUpdate,
                    ui::drop_unchanged_modifiers
                        .after(bevy_egui::EguiPreUpdateSet::ProcessInput)
                        .before(bevy_egui::EguiPreUpdateSet::BeginPass),
                )
                .add_systems(EguiPrimaryContextPass, ui::panels);
        }
    }
}

/// The longest the editor waits for the next frame when nothing asks for
/// one: timers (the view's refinement after a move, a request's progress)
/// advance at least this often.
const IDLE_FRAME: std::time::Duration = std::time::Duration::from_millis(250);

/// Asks for the next frame while the view camera moves (the orbit camera
/// eases out after the mouse lets go, with no input to wake the loop).
fn redraw_while_the_camera_moves(
    moved: Query<(), (With<EditorCamera>, Changed<Transform>)>,
    mut redraw: MessageWriter<bevy::window::RequestRedraw>,
) {
    if !moved.is_empty() {
        redraw.write(bevy::window::RequestRedraw);
    }
}

/// The view camera, aimed by the first capture view once one is known.
pub fn spawn_camera(mut commands: Commands) {
    let k = crate::camera::Intrinsics::from_fov_x(640, 360, 45f32.to_radians());
    let view = IsrfCamera::look_at(k, glam::Vec3::new(0.0, 1.0, 3.0), glam::Vec3::ZERO, glam::Vec3::Y);
    let transform = bevy_transform(&view.c2w);
    let mut pan = PanOrbitCamera::default();
    aim_orbit(&mut pan, &transform, 3.0);
    commands.spawn((
        Camera3d::default(),
        transform,
        projection_for(&view.intrinsics),
        Tonemapping::None,
        DebandDither::Disabled,
        Msaa::Off,
        RayMarchCamera::default(),
        pan,
        EditorCamera,
    ));
}

/// Rebuilds the ray marcher's scene when the session, the entities (previews)
/// or the overlay settings change.
#[derive(Resource, Default)]
pub struct SceneSync {
    /// What the current scene was built from (rebuild only when it differs:
    /// egui's `&mut` bindings mark resources and components changed every
    /// frame, and a scene per frame would never finish drawing).
    built_from: Option<SceneInputs>,
    /// Whether the view was aimed at the first capture view already.
    aimed: bool,
    /// Scenes built so far.
    pub builds: u64,
}

/// Everything `build_scene` reads besides the session state.
#[derive(Clone, PartialEq)]
struct SceneInputs {
    version: u64,
    previews: Vec<Preview>,
    selected: Option<ObjectId>,
    mode: OverlayMode,
    background: [f32; 3],
    step_scale: f32,
    ndc: Option<crate::camera::Ndc>,
}

type EditorCamQuery<'w, 's> = Query<
    'w,
    's,
    (
        &'static mut Transform,
        &'static mut Projection,
        &'static mut PanOrbitCamera,
    ),
    (With<EditorCamera>, Without<ObjectLayer>),
>;

/// Aims the view at the first capture view, once there is one.
fn aim_once(sync: &mut SceneSync, state: &EditorState, es: &EditorSession, cams: &mut EditorCamQuery) {
    if sync.aimed {
        return;
    }
    let (Some((_, cam)), Ok((mut t, mut p, mut pan))) = (state.capture_cameras.first(), cams.single_mut()) else {
        return;
    };
    camera::snap_to_capture(cam, es.state(), state.ndc, &mut t, &mut p, &mut pan);
    sync.aimed = true;
}

/// The scene inputs: objects whose entity placement or appearance differs
/// from the session's become previews.
fn scene_inputs(
    state: &EditorState,
    es: &EditorSession,
    objects: &Query<(&ObjectLayer, &Transform, Has<Selected>)>,
    field_selected: bool,
) -> SceneInputs {
    let mut previews = Vec::new();
    let mut selected = None;
    for (o, t, sel) in objects {
        if sel {
            selected = Some(o.id);
        }
        let Some(entry) = es.state().object(o.id) else {
            continue;
        };
        let edit = entry.placement.color_edit.unwrap_or_default();
        if *t != bevy_transform(&entry.placement.transform) || o.color_edit() != edit {
            previews.push(Preview {
                object: o.id,
                transform: from_bevy_transform(t),
                color_edit: o.color_edit(),
            });
        }
    }
    previews.sort_by_key(|p| p.object);
    SceneInputs {
        version: es.version,
        previews,
        selected,
        mode: if field_selected {
            OverlayMode::default()
        } else {
            state.overlay
        },
        background: state.background,
        step_scale: state.step_scale,
        ndc: state.ndc,
    }
}

pub fn sync_scene(
    mut sync: ResMut<SceneSync>,
    mut march: ResMut<MarchScene>,
    state: Res<EditorState>,
    es: Res<EditorSession>,
    objects: Query<(&ObjectLayer, &Transform, Has<Selected>)>,
    fields: Query<(&FieldLayer, Has<Selected>)>,
    mut cams: EditorCamQuery,
) {
    aim_once(&mut sync, &state, &es, &mut cams);
    let inputs = scene_inputs(&state, &es, &objects, fields.iter().any(|f| f.1));
    if sync.built_from.as_ref() == Some(&inputs) {
        return;
    }
    let mut st = es.state().clone();
    st.background = inputs.background;
    let (scene, overlay) = build_scene(&st, &inputs.previews, inputs.selected, inputs.mode);
    let step = crate::render::Step::default().scaled(inputs.step_scale);
    march.scene = Some(Arc::new(scene));
    march.overlay = overlay;
    march.step = step;
    march.ndc = inputs.ndc;
    sync.builds += 1;
    sync.built_from = Some(inputs);
}

/// Turns finished strokes into `Stroke` commands on the selected object (a
/// new object of the selected or first field when none is selected).
pub fn strokes_to_commands(
    mut strokes: MessageReader<StrokeMsg>,
    mut state: ResMut<EditorState>,
    mut es: ResMut<EditorSession>,
    selected: Query<(&SessionName, Has<ObjectLayer>), With<Selected>>,
) {
    for s in strokes.read() {
        let sel = selected.iter().next();
        let (object, field) = match sel {
            Some((n, true)) => (n.0.clone(), None),
            other => {
                if s.polarity == Polarity::Negative {
                    state.error("select an object to subtract a negative stroke from");
                    continue;
                }
                let field = other.map(|(n, _)| n.0.clone());
                (es.fresh_name("object"), field)
            }
        };
        let stroke = Stroke {
            camera: s.camera,
            points: s.points.clone(),
            radius: s.radius,
            polarity: s.polarity,
            object: object.clone(),
            joined: true,
        };
        state.pending_select = Some(object.clone());
        es.apply(Edit::Stroke {
            object,
            field,
            polarity: Some(s.polarity),
            source: StrokeSource::Inline(StrokeDoc::from_stroke(&stroke)),
        });
    }
}

/// Selects what a stroke just created, once the session has it.
pub fn select_pending(
    mut commands: Commands,
    mut state: ResMut<EditorState>,
    es: Res<EditorSession>,
    selected: Query<Entity, With<Selected>>,
    named: Query<(Entity, &SessionName)>,
) {
    let Some(name) = state.pending_select.clone() else {
        return;
    };
    if let Some((e, _)) = named.iter().find(|(_, n)| n.0 == name) {
        for old in &selected {
            if old != e {
                commands.entity(old).remove::<Selected>();
            }
        }
        commands.entity(e).insert(Selected);
        state.pending_select = None;
    } else if !es.busy() {
        state.pending_select = None;
    }
}

/// Undo / redo, tool toggle, delete and grow shortcuts.
pub fn keyboard_shortcuts(
    keys: Res<ButtonInput<KeyCode>>,
    wants: Option<Res<bevy_egui::input::EguiWantsInput>>,
    mut state: ResMut<EditorState>,
    mut es: ResMut<EditorSession>,
    selected: Query<(&SessionName, Has<ObjectLayer>), With<Selected>>,
) {
    if wants.is_some_and(|w| w.wants_keyboard_input()) || state.transform.is_some() {
        return;
    }
    let ctrl = keys.any_pressed([KeyCode::ControlLeft, KeyCode::ControlRight, KeyCode::SuperLeft]);
    let shift = keys.any_pressed([KeyCode::ShiftLeft, KeyCode::ShiftRight]);
    if ctrl && keys.just_pressed(KeyCode::KeyZ) {
        es.push(if shift { Request::Redo } else { Request::Undo });
        return;
    }
    if ctrl && keys.just_pressed(KeyCode::KeyY) {
        es.push(Request::Redo);
        return;
    }
    if ctrl {
        return;
    }
    if keys.just_pressed(KeyCode::KeyB) {
        state.tool = match state.tool {
            state::Tool::Brush => state::Tool::Navigate,
            state::Tool::Navigate => state::Tool::Brush,
        };
    }
    let Some((name, is_object)) = selected.iter().next() else {
        return;
    };
    if !is_object {
        return;
    }
    let object = name.0.clone();
    if keys.just_pressed(KeyCode::Delete) || keys.just_pressed(KeyCode::KeyX) {
        es.apply(Edit::Remove { object });
    } else if keys.just_pressed(KeyCode::Equal) || keys.just_pressed(KeyCode::NumpadAdd) {
        es.apply(Edit::Grow {
            object,
            steps: crate::segment::Growth::Steps(1),
        });
    }
}

/// The object of the last `Stroke` among `requests`.
fn last_stroked(requests: &[Request]) -> Option<String> {
    let stroked = |c: &Edit| match c {
        Edit::Stroke { object, .. } => Some(object.clone()),
        _ => None,
    };
    requests.iter().rev().find_map(|r| match r {
        Request::Apply(c) => c.as_edit().and_then(stroked),
        Request::Restore(d) => d.commands.iter().rev().find_map(stroked),
        _ => None,
    })
}

/// Opens the editor window and runs until it is closed (or, with
/// `screenshot`, until the screenshot is saved).
pub fn run(opts: EditorOptions) -> Result<()> {
    let mut requests = startup_requests(&opts)?;
    let cwd = std::env::current_dir().map_err(|e| Error::io(".", e))?;
    let plan = recovery_plan(&opts, &cwd, &requests);
    if let Some(doc) = plan.restore {
        requests = vec![Request::Restore(Box::new(doc))];
    }
    let (w, h) = if opts.size.0 == 0 { (1280, 720) } else { opts.size };
    let mut app = App::new();
    app.add_plugins(DefaultPlugins.set(WindowPlugin {
        primary_window: Some(Window {
            title: "isrf editor".into(),
            resolution: (w, h).into(),
            ..default()
        }),
        ..default()
    }))
    .add_plugins(bevy::diagnostic::FrameTimeDiagnosticsPlugin::default());
    let mut session = Session::new(cwd.clone(), cwd);
    if let Some(n) = opts.undo_steps {
        session = session.with_undo_limit(n);
    }
    let mut es = EditorSession::new(session);
    if let Some(r) = plan.recorder {
        es = es.with_recorder(r);
    }
    es.offer = plan.offer.map(Box::new);
    // The last object a start-up script strokes starts selected.
    let mut state = EditorState {
        pending_select: last_stroked(&requests),
        ..default()
    };
    for n in plan.notes {
        state.error(n);
    }
    for r in requests {
        es.push(r);
    }
    app.insert_resource(es)
        .insert_resource(state)
        .add_plugins(EditorPlugin { ui: !opts.no_ui });
    if let Some(path) = &opts.screenshot {
        app.add_plugins(capture::ScreenshotPlugin { path: path.clone() });
    }
    match app.run() {
        AppExit::Success => Ok(()),
        AppExit::Error(code) => Err(Error::invalid(format!("the editor exited with code {code}"))),
    }
}
