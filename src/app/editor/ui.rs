//! egui panels: menu bar (file, export, edit, view), outliner (fields and
//! objects: select, rename, hide, remove, delete, duplicate), tools (brush,
//! segmentation sliders, growth), the selection's transform and appearance,
//! a status line with the last stroke's per-stage timings, progress and
//! errors, and the stroke being painted drawn over the view.
//!
//! Widgets only read entities and write previews; every change the user
//! commits becomes a [`Command`] queued on the session.

use super::browse;
use super::camera::{snap_to_capture, EditorCamera};
use super::session::{EditorSession, Request};
use super::state::{CurrentStroke, EditorState, GizmoView, Handle, MovingResolution, Tool, TransformMode};
use super::tools::{self, transform_command};
use crate::app::convert::bevy_transform;
use crate::app::gpu::SharedStatus;
use crate::app::layers::{FieldLayer, ObjectLayer, Selected, SessionName};
use crate::command::{CameraSource, Edit, Export, FieldSource, Output};
use crate::segment::{Growth, GrowthRule, SegmentParams};
use crate::util::ProgressState;
use bevy::camera::visibility::RenderLayers;
use bevy::camera::{CameraOutputMode, ClearColorConfig, Projection, Viewport};
use bevy::diagnostic::{DiagnosticsStore, FrameTimeDiagnosticsPlugin};
use bevy::prelude::*;
use bevy::render::render_resource::BlendState;
use bevy::window::PrimaryWindow;
use bevy_egui::{egui, EguiContexts, EguiGlobalSettings, EguiInput, PrimaryEguiContext};
use bevy_panorbit_camera::PanOrbitCamera;
use std::path::PathBuf;

/// A separate full-window camera carries egui, so that the 3D view can be
/// limited to the area the panels leave free.
pub fn spawn_ui_camera(mut commands: Commands, mut settings: ResMut<EguiGlobalSettings>) {
    settings.auto_create_primary_context = false;
    commands.spawn((
        PrimaryEguiContext,
        Camera2d,
        RenderLayers::none(),
        Camera {
            order: 1,
            output_mode: CameraOutputMode::Write {
                blend_state: Some(BlendState::ALPHA_BLENDING),
                clear_color: ClearColorConfig::None,
            },
            clear_color: ClearColorConfig::Custom(Color::NONE),
            ..default()
        },
    ));
}

/// Whether an edit widget's change is final (drag released, focus left, or
/// a click / keyboard change).
fn committed(r: &egui::Response) -> bool {
    r.drag_stopped() || r.lost_focus() || (r.changed() && !r.dragged() && !r.has_focus())
}

/// A logarithmic slider for a positive parameter; whether a change was
/// committed (see [`committed`]).
fn log_slider(ui: &mut egui::Ui, value: &mut f32, range: std::ops::RangeInclusive<f32>, text: &str) -> bool {
    committed(&ui.add(egui::Slider::new(value, range).logarithmic(true).text(text)))
}

type ObjectQuery<'w, 's> = Query<
    'w,
    's,
    (
        Entity,
        &'static SessionName,
        &'static mut ObjectLayer,
        &'static mut Transform,
    ),
    (Without<EditorCamera>, Without<FieldLayer>),
>;

#[allow(clippy::too_many_arguments)]
pub fn panels(
    mut contexts: EguiContexts,
    mut commands: Commands,
    mut state: ResMut<EditorState>,
    mut es: ResMut<EditorSession>,
    stroke: Res<CurrentStroke>,
    gizmo: Res<GizmoView>,
    status: Res<SharedStatus>,
    diagnostics: Option<Res<DiagnosticsStore>>,
    fields: Query<(Entity, &SessionName, &FieldLayer), Without<ObjectLayer>>,
    mut objects: ObjectQuery,
    selected: Query<Entity, With<Selected>>,
    windows: Query<&Window, With<PrimaryWindow>>,
    mut cams: Query<(&mut Camera, &mut Transform, &mut Projection, &mut PanOrbitCamera), With<EditorCamera>>,
) -> Result {
    let ctx = contexts.ctx_mut()?.clone();
    let sel = selected.iter().next();
    let mut select: Option<Option<Entity>> = None;
    let mut snap = None;
    let mut root = egui::Ui::new(
        ctx.clone(),
        "isrf_root".into(),
        egui::UiBuilder::new()
            .layer_id(egui::LayerId::background())
            .max_rect(ctx.viewport_rect()),
    );

    egui::Panel::top("menu").show(&mut root, |ui| {
        egui::MenuBar::new().ui(ui, |ui| {
            menu_bar(ui, &mut state, &mut es, sel, &fields, &objects, &mut snap);
        });
    });
    egui::Panel::bottom("status").show(&mut root, |ui| {
        status_line(ui, &mut state, &es, &status, diagnostics.as_deref());
    });
    egui::Panel::left("outliner").default_size(230.0).show(&mut root, |ui| {
        outliner(ui, &mut es, sel, &fields, &objects, &mut select);
    });
    egui::Panel::right("tools").default_size(290.0).show(&mut root, |ui| {
        egui::ScrollArea::vertical().show(ui, |ui| {
            tools_panel(ui, &mut state, &mut es, sel, &objects);
            if let Some(e) = sel {
                if objects.contains(e) {
                    selection_panel(ui, &mut state, &mut es, e, &mut objects);
                } else if let Ok((_, name, f)) = fields.get(e) {
                    ui.separator();
                    ui.heading("Field");
                    name_editor(ui, &mut state, &mut es, e, &name.0);
                    ui.label(format!(
                        "{:?} grid, {:.1} MB",
                        f.field.res(),
                        f.field.memory_bytes() as f64 / 1e6
                    ));
                }
            }
            view_panel(ui, &mut state, &mut snap);
        });
    });
    // The 3D view gets what the panels leave.
    let free = root.available_rect_before_wrap();
    draw_stroke(&ctx, &stroke, &state);
    draw_gizmo(&ctx, &gizmo);
    recovery_dialog(&ctx, &mut es, &mut state);

    if let Some(s) = select {
        for old in &selected {
            commands.entity(old).remove::<Selected>();
        }
        if let Some(e) = s {
            commands.entity(e).insert(Selected);
        }
    }
    let Ok((mut cam, mut t, mut p, mut pan)) = cams.single_mut() else {
        return Ok(());
    };
    if let Some(i) = snap {
        if let Some((_, c)) = state.capture_cameras.get(i).cloned() {
            snap_to_capture(&c, es.state(), state.ndc, &mut t, &mut p, &mut pan);
        }
    }
    if let Ok(window) = windows.single() {
        let scale = window.scale_factor();
        let min = (free.min.to_vec2() * scale).max(egui::Vec2::ZERO);
        let size = (free.size() * scale).max(egui::vec2(16.0, 16.0));
        let win = egui::vec2(window.physical_width() as f32, window.physical_height() as f32);
        let size = size.min(win - min).max(egui::vec2(1.0, 1.0));
        let vp = Viewport {
            physical_position: UVec2::new(min.x as u32, min.y as u32),
            physical_size: UVec2::new(size.x as u32, size.y as u32),
            ..default()
        };
        let same = cam
            .viewport
            .as_ref()
            .is_some_and(|v| v.physical_position == vp.physical_position && v.physical_size == vp.physical_size);
        if !same && vp.physical_size.x > 0 && vp.physical_size.y > 0 {
            cam.viewport = Some(vp);
        }
    }
    Ok(())
}

/// "3 stroke, 1 transform": the kinds of `commands`, counted, in order of
/// first appearance.
fn command_summary(commands: &[Edit]) -> String {
    let mut counts: Vec<(&str, usize)> = Vec::new();
    for c in commands {
        match counts.iter_mut().find(|(k, _)| *k == c.kind()) {
            Some((_, n)) => *n += 1,
            None => counts.push((c.kind(), 1)),
        }
    }
    let parts: Vec<String> = counts
        .iter()
        .map(|(k, n)| format!("{n} {}", k.replace('_', " ")))
        .collect();
    parts.join(", ")
}

/// "12 s", "5 min", "3 h", "2 days": how long ago `written` (Unix seconds) was.
fn age(written: u64) -> String {
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(written, |d| d.as_secs());
    let s = now.saturating_sub(written);
    match s {
        0..=119 => format!("{s} s"),
        120..=7199 => format!("{} min", s / 60),
        7200..=172_799 => format!("{} h", s / 3600),
        _ => format!("{} days", s / 86_400),
    }
}

/// The restore offer: an earlier session with the same inputs ended
/// without its edits being redone by a fresh start (a crash, a kill).
/// Modal: the choice comes before new edits.
fn recovery_dialog(ctx: &egui::Context, es: &mut EditorSession, state: &mut EditorState) {
    let Some(doc) = es.offer.as_deref() else {
        return;
    };
    let kept = es
        .recovery_path()
        .map(|p| crate::command::recovery::Recorder::previous_of(p).display().to_string())
        .unwrap_or_default();
    let mut choice = None;
    egui::Modal::new(egui::Id::new("isrf_restore")).show(ctx, |ui| {
        ui.set_max_width(460.0);
        ui.heading("Restore the last session?");
        ui.label(format!(
            "An earlier session with these inputs stopped {} ago. Its edit log holds {} commands, more than a fresh start redoes ({}).",
            age(doc.written),
            doc.commands.len(),
            command_summary(&doc.commands)
        ));
        if let Some(p) = &doc.opened {
            ui.label(format!("It was opened from {}.", p.display()));
        }
        ui.label("Restore replays them and checks that the state is identical to the recorded one.");
        ui.label(egui::RichText::new(format!("Start fresh keeps the recovery file as {kept}.")).small());
        ui.horizontal(|ui| {
            if ui.button("Restore").clicked() {
                choice = Some(true);
            }
            if ui.button("Start fresh").clicked() {
                choice = Some(false);
            }
        });
    });
    match choice {
        Some(true) => es.accept_offer(),
        Some(false) => {
            if let Err(e) = es.decline_offer() {
                state.error(format!("the recovery file could not be moved aside: {e}"));
            }
        }
        None => {}
    }
}

fn path_of(s: &str) -> Option<PathBuf> {
    let t = s.trim();
    (!t.is_empty()).then(|| PathBuf::from(t))
}

#[allow(clippy::too_many_arguments)]
fn menu_bar(
    ui: &mut egui::Ui,
    state: &mut EditorState,
    es: &mut EditorSession,
    sel: Option<Entity>,
    fields: &Query<(Entity, &SessionName, &FieldLayer), Without<ObjectLayer>>,
    objects: &ObjectQuery,
    snap: &mut Option<usize>,
) {
    ui.menu_button("File", |ui| {
        ui.label("Path:");
        ui.text_edit_singleline(&mut state.path_input);
        browse::browser(ui, &mut state.path_input);
        let path = path_of(&state.path_input);
        let has = path.is_some();
        if ui
            .add_enabled(has, egui::Button::new("Open composition (.ron / .json)"))
            .clicked()
        {
            es.push(Request::Open(path.clone().unwrap()));
        }
        if ui
            .add_enabled(has, egui::Button::new("Import 3D Gaussian splats (.ply)"))
            .clicked()
        {
            es.push(Request::ImportSplats(path.clone().unwrap()));
        }
        if ui
            .add_enabled(has, egui::Button::new("Add field file to the composition"))
            .clicked()
        {
            let p = path.clone().unwrap();
            let stem = p
                .file_stem()
                .map_or("field".into(), |s| s.to_string_lossy().into_owned());
            let name = es.fresh_name(&stem);
            es.apply(Edit::LoadField {
                name,
                source: FieldSource::File(p),
                transform: None,
            });
        }
        ui.separator();
        if ui.add_enabled(has, egui::Button::new("Save composition")).clicked() {
            es.apply(Output::Export(Export::Composition {
                out: path.clone().unwrap(),
            }));
        }
        if ui
            .add_enabled(has, egui::Button::new("Save edit log as script"))
            .clicked()
        {
            es.apply(Output::Export(Export::Script {
                out: path.clone().unwrap(),
            }));
        }
    });
    ui.menu_button("Edit", |ui| {
        if ui
            .add_enabled(es.can_undo, egui::Button::new("Undo (Ctrl+Z)"))
            .clicked()
        {
            es.push(Request::Undo);
        }
        if ui
            .add_enabled(es.can_redo, egui::Button::new("Redo (Ctrl+Shift+Z)"))
            .clicked()
        {
            es.push(Request::Redo);
        }
        ui.label(format!("{} edits in the log", es.log_len));
    });
    ui.menu_button("Export", |ui| {
        ui.label("Path (file, or folder for masks):");
        ui.text_edit_singleline(&mut state.path_input);
        browse::browser(ui, &mut state.path_input);
        let path = path_of(&state.path_input);
        let target = sel.and_then(|e| {
            objects
                .get(e)
                .ok()
                .map(|o| (o.1 .0.clone(), Some(o.2.field)))
                .or_else(|| fields.get(e).ok().map(|f| (f.1 .0.clone(), None)))
        });
        let (Some(out), Some((name, field))) = (path, target) else {
            ui.label("select an object (or a field) and type a path");
            return;
        };
        if ui.button("Mesh (.glb / .ply)").clicked() {
            es.apply(Output::Export(Export::Mesh {
                target: name.clone(),
                out: out.clone(),
                iso: None,
            }));
        }
        let Some(fe) = field else { return };
        if ui.button("Object field (.safetensors)").clicked() {
            es.apply(Output::Export(Export::ObjectField {
                object: name.clone(),
                out: out.clone(),
                margin: 2,
            }));
        }
        if ui.button("3D mask bitmap (.safetensors)").clicked() {
            es.apply(Output::Export(Export::Bitmap {
                object: name.clone(),
                out: out.clone(),
            }));
        }
        super::splats::export_buttons(ui, es, &name, &out);
        let Ok((_, field_name, field_layer)) = fields.get(fe) else {
            return;
        };
        let field_name = field_name.0.clone();
        let is_demo = es.state().field(field_layer.id).is_some_and(|f| f.demo.is_some());
        if ui
            .add_enabled(is_demo, egui::Button::new("2D masks of the capture views"))
            .on_disabled_hover_text("needs a field with capture cameras (demo scenes)")
            .clicked()
        {
            es.apply(Output::Export(Export::Masks {
                object: name,
                cameras: CameraSource::Demo {
                    field: field_name,
                    eval: false,
                },
                out,
                downscale: 1,
            }));
        }
    });
    ui.menu_button("View", |ui| {
        ui.checkbox(&mut state.fly, "Fly mode (F)");
        ui.separator();
        ui.label("Snap to a capture view:");
        egui::ScrollArea::vertical().max_height(260.0).show(ui, |ui| {
            for (i, (name, _)) in state.capture_cameras.iter().enumerate() {
                if ui.button(name).clicked() {
                    *snap = Some(i);
                }
            }
        });
    });
}

fn outliner(
    ui: &mut egui::Ui,
    es: &mut EditorSession,
    sel: Option<Entity>,
    fields: &Query<(Entity, &SessionName, &FieldLayer), Without<ObjectLayer>>,
    objects: &ObjectQuery,
    select: &mut Option<Option<Entity>>,
) {
    ui.heading("Outliner");
    egui::ScrollArea::vertical().show(ui, |ui| {
        for (fe, fname, f) in fields.iter() {
            ui.horizontal(|ui| {
                if ui.selectable_label(sel == Some(fe), format!("▣ {}", fname.0)).clicked() {
                    *select = Some(Some(fe));
                }
                if ui
                    .small_button(if f.placement.visible { "hide" } else { "show" })
                    .clicked()
                {
                    es.apply(Edit::SetVisible {
                        target: fname.0.clone(),
                        visible: !f.placement.visible,
                    });
                }
                if ui.small_button("delete").clicked() {
                    es.apply(Edit::Delete {
                        target: fname.0.clone(),
                    });
                }
            });
            ui.indent(fe, |ui| {
                for (oe, oname, o, _) in objects.iter() {
                    if o.field != fe {
                        continue;
                    }
                    let name = oname.0.clone();
                    ui.horizontal(|ui| {
                        let label = if o.placement.removed {
                            format!("✂ {name} (removed)")
                        } else {
                            format!("● {name} ({} vx)", o.bitmap.count())
                        };
                        if ui.selectable_label(sel == Some(oe), label).clicked() {
                            *select = Some(Some(oe));
                        }
                    });
                    ui.horizontal(|ui| {
                        if ui
                            .small_button(if o.placement.visible { "hide" } else { "show" })
                            .clicked()
                        {
                            es.apply(Edit::SetVisible {
                                target: name.clone(),
                                visible: !o.placement.visible,
                            });
                        }
                        if o.placement.removed {
                            if ui.small_button("restore").clicked() {
                                es.apply(Edit::Restore { object: name.clone() });
                            }
                        } else if ui
                            .small_button("remove")
                            .on_hover_text("take it out of the scene (leaves a hole)")
                            .clicked()
                        {
                            es.apply(Edit::Remove { object: name.clone() });
                        }
                        if ui.small_button("duplicate").clicked() {
                            let copy = es.fresh_name(&format!("{name} copy"));
                            es.apply(Edit::Duplicate {
                                object: name.clone(),
                                name: copy,
                                transform: Some(crate::command::session::translate(glam::Vec3::new(0.15, 0.0, 0.0))),
                            });
                        }
                        if ui
                            .small_button("delete")
                            .on_hover_text("forget the segmentation (the field is whole again)")
                            .clicked()
                        {
                            es.apply(Edit::Delete { target: name.clone() });
                            *select = Some(None);
                        }
                    });
                }
            });
        }
        if fields.is_empty() {
            ui.label(if es.busy() {
                "loading…"
            } else {
                "no field: File ▸ add one"
            });
        }
    });
}

fn tools_panel(
    ui: &mut egui::Ui,
    state: &mut EditorState,
    es: &mut EditorSession,
    sel: Option<Entity>,
    objects: &ObjectQuery,
) {
    ui.heading("Tools");
    ui.horizontal(|ui| {
        ui.selectable_value(&mut state.tool, Tool::Navigate, "Navigate");
        ui.selectable_value(&mut state.tool, Tool::Brush, "Brush (B)");
    });
    ui.add(egui::Slider::new(&mut state.brush_radius, 0..=40).text("brush radius px"));
    ui.checkbox(&mut state.negative, "negative strokes (or hold Ctrl)");
    ui.separator();
    ui.heading("Segmentation");
    let p = &mut state.params;
    let mut commit = false;
    let mut rule = None;
    ui.horizontal(|ui| {
        ui.label("growth rule");
        for (r, name) in [
            (GrowthRule::Stable, "stable"),
            (GrowthRule::Bounded, "bounded"),
            (GrowthRule::Paper, "paper"),
        ] {
            if ui.selectable_label(p.grow.rule == r, name).clicked() && p.grow.rule != r {
                rule = Some(r);
            }
        }
    });
    commit |= committed(&ui.add(egui::Slider::new(&mut p.k, 1..=64).text("K (clusters)")));
    commit |= committed(&ui.add(egui::Slider::new(&mut p.theta, 0.01..=2.0).text("θ (NNFM)")));
    commit |= log_slider(ui, &mut p.grow.sigma_f, 0.01..=50.0, "σ_φ");
    if p.grow.rule != GrowthRule::Paper {
        commit |= committed(&ui.add(egui::Slider::new(&mut p.grow.theta_grow, 0.01..=4.0).text("θ grow")));
        commit |= log_slider(ui, &mut p.solid_alpha, 0.0..=0.5, "solid α");
    }
    commit |= log_slider(ui, &mut p.grow.sigma_s, 0.1..=10.0, "σ_s");
    commit |= committed(&ui.add(egui::Slider::new(&mut p.grow.tau, 0.0..=0.99).text("τ")));
    if p.grow.rule == GrowthRule::Stable {
        commit |= committed(
            &ui.add(egui::Slider::new(&mut p.cut.rounds, 0..=4).text("graph-cut rounds"))
                .on_hover_text("Refine each stroke's region with a graph cut on features and colour; 0: off (faster strokes on large fields)"),
        );
        commit |= log_slider(ui, &mut p.cut.lambda, 0.01..=10.0, "cut λ (boundary)");
    }
    commit |= ui
        .checkbox(&mut p.connected, "only what the stroke touches")
        .on_hover_text("Keep the matches joined to the stroked surface; off: every look-alike in the field")
        .changed();
    commit |= ui
        .checkbox(&mut p.coarse, "fast: segment on a 2–3× coarser grid")
        .on_hover_text("The same pipeline over an eighth of the voxels (a 27th past 1.5 M occupied voxels), the mask mapped back to the field's grid: several times faster strokes on large fields, and on large objects (a floor, a whole model) of smaller ones")
        .changed();
    ui.checkbox(&mut state.live, "live: redo the last stroke with new values");
    if let Some(r) = rule {
        // A rule change resets the sliders to that rule's defaults.
        state.params = SegmentParams::for_rule(r);
        commit = true;
    }
    if commit && state.params != es.state().params {
        let p = state.params;
        let set = Edit::SetParams {
            rule,
            k: Some(p.k),
            theta: Some(p.theta),
            sigma_f: Some(p.grow.sigma_f),
            sigma_s: Some(p.grow.sigma_s),
            tau: Some(p.grow.tau),
            growth: None,
            theta_grow: Some(p.grow.theta_grow),
            solid_alpha: Some(p.solid_alpha),
            connected: Some(p.connected),
            cut_rounds: Some(p.cut.rounds),
            cut_lambda: Some(p.cut.lambda),
            coarse: Some(p.coarse),
        };
        // Live re-segmentation: take back the last stroke, change the
        // parameters, stroke again (all through the session, so undo works).
        let last = es.session().and_then(|s| s.log().last().cloned());
        match last.filter(|c| state.live && matches!(c, Edit::Stroke { .. })) {
            Some(stroke) => {
                es.push(Request::Undo);
                es.apply(set);
                es.apply(stroke);
            }
            None => es.apply(set),
        }
    }
    let object = sel.and_then(|e| objects.get(e).ok()).map(|o| o.1 .0.clone());
    ui.horizontal(|ui| {
        if ui
            .add_enabled(object.is_some(), egui::Button::new("Grow one step (+)"))
            .clicked()
        {
            es.apply(Edit::Grow {
                object: object.clone().unwrap(),
                steps: Growth::Steps(1),
            });
        }
        if ui
            .add_enabled(object.is_some(), egui::Button::new("Grow to convergence"))
            .clicked()
        {
            es.apply(Edit::Grow {
                object: object.clone().unwrap(),
                steps: Growth::Converge,
            });
        }
    });
}

/// The selected field's or object's name; Enter or leaving the box renames
/// it through the session (undoable; a taken name shows as an error).
/// Outside editing the box shows the current label, so a rename by a
/// script or an undo shows too.
fn name_editor(ui: &mut egui::Ui, state: &mut EditorState, es: &mut EditorSession, e: Entity, name: &str) {
    let id = egui::Id::new(("isrf_name", e));
    let editing = ui.memory(|m| m.has_focus(id));
    if state.rename.as_ref().map(|r| r.0) != Some(e) || !editing {
        state.rename = Some((e, name.to_string()));
    }
    let Some((_, buf)) = state.rename.as_mut() else {
        return;
    };
    let r = ui.add(egui::TextEdit::singleline(buf).id(id).hint_text("name"));
    let new = buf.trim();
    if r.lost_focus() && new != name && !new.is_empty() {
        es.apply(Edit::Rename {
            target: name.to_string(),
            name: new.to_string(),
        });
    }
}

fn selection_panel(
    ui: &mut egui::Ui,
    state: &mut EditorState,
    es: &mut EditorSession,
    e: Entity,
    objects: &mut ObjectQuery,
) {
    let Ok((_, name, mut obj, mut t)) = objects.get_mut(e) else {
        return;
    };
    let name = name.0.clone();
    let Some(entry) = es.state().object(obj.id).cloned() else {
        return;
    };
    ui.separator();
    ui.heading("Object");
    name_editor(ui, state, es, e, &name);
    ui.label(format!("{} voxels", obj.bitmap.count()));
    ui.label("Move (G), rotate (R), scale (S), or type:");
    let mut tr = t.translation;
    let (ry, rx, rz) = t.rotation.to_euler(EulerRot::YXZ);
    let mut rot = Vec3::new(rx.to_degrees(), ry.to_degrees(), rz.to_degrees());
    let mut s = t.scale.x;
    let mut edited = false;
    let mut commit = false;
    ui.horizontal(|ui| {
        ui.label("pos");
        for v in [&mut tr.x, &mut tr.y, &mut tr.z] {
            let r = ui.add(egui::DragValue::new(v).speed(0.01));
            edited |= r.changed();
            commit |= committed(&r);
        }
    });
    ui.horizontal(|ui| {
        ui.label("rot°");
        for v in [&mut rot.x, &mut rot.y, &mut rot.z] {
            let r = ui.add(egui::DragValue::new(v).speed(1.0));
            edited |= r.changed();
            commit |= committed(&r);
        }
    });
    ui.horizontal(|ui| {
        ui.label("scale");
        let r = ui.add(egui::DragValue::new(&mut s).speed(0.01).range(0.05..=20.0));
        edited |= r.changed();
        commit |= committed(&r);
    });
    if edited {
        *t = Transform {
            translation: tr,
            rotation: Quat::from_euler(
                EulerRot::YXZ,
                rot.y.to_radians(),
                rot.x.to_radians(),
                rot.z.to_radians(),
            ),
            scale: Vec3::splat(s),
        };
    }
    if ui.button("Reset placement").clicked() {
        *t = Transform::IDENTITY;
        commit = true;
    }
    let placed = bevy_transform(&entry.placement.transform);
    if commit && *t != placed {
        es.apply(transform_command(&name, &placed, &t));
    }
    ui.label("Appearance");
    let mut c = obj.color_edit();
    let mut commit = false;
    ui.horizontal(|ui| {
        ui.label("tint");
        commit |= ui.color_edit_button_rgb(&mut c.tint).changed();
    });
    commit |= committed(&ui.add(egui::Slider::new(&mut c.hue, -180.0..=180.0).text("hue°")));
    commit |= committed(&ui.add(egui::Slider::new(&mut c.saturation, 0.0..=3.0).text("saturation")));
    commit |= committed(&ui.add(egui::Slider::new(&mut c.brightness, 0.0..=3.0).text("brightness")));
    if ui.button("Reset appearance").clicked() {
        c = Default::default();
        commit = true;
    }
    if c != obj.color_edit() {
        obj.placement.color_edit = Some(c);
    }
    if commit && Some(c).filter(|e| !e.is_identity()) != entry.placement.color_edit {
        es.apply(Edit::Appearance { object: name, edit: c });
    }
}

fn view_panel(ui: &mut egui::Ui, state: &mut EditorState, snap: &mut Option<usize>) {
    ui.separator();
    ui.heading("View");
    ui.checkbox(&mut state.overlay.tint_selected, "tint the selected object");
    ui.checkbox(&mut state.overlay.dim_others, "dim the others");
    ui.horizontal(|ui| {
        ui.label("background");
        ui.color_edit_button_rgb(&mut state.background);
    });
    ui.add(egui::Slider::new(&mut state.step_scale, 1.0..=4.0).text("step × (faster, coarser)"));
    let labels = [
        (MovingResolution::Auto, "auto (½ on software GPUs)"),
        (MovingResolution::Full, "full"),
        (MovingResolution::Half, "½"),
    ];
    egui::ComboBox::from_label("resolution while moving")
        .selected_text(
            labels
                .iter()
                .find(|l| l.0 == state.moving_resolution)
                .map_or("", |l| l.1),
        )
        .show_ui(ui, |ui| {
            for (mode, label) in labels {
                ui.selectable_value(&mut state.moving_resolution, mode, label);
            }
        });
    if !state.capture_cameras.is_empty() {
        egui::ComboBox::from_label("capture view")
            .selected_text("snap to…")
            .show_ui(ui, |ui| {
                for (i, (name, _)) in state.capture_cameras.iter().enumerate() {
                    if ui.selectable_label(false, name).clicked() {
                        *snap = Some(i);
                    }
                }
            });
    }
}

fn status_line(
    ui: &mut egui::Ui,
    state: &mut EditorState,
    es: &EditorSession,
    status: &SharedStatus,
    diagnostics: Option<&DiagnosticsStore>,
) {
    let gpu = status.get();
    ui.horizontal_wrapped(|ui| {
        if let Some((label, secs, p)) = es.progress() {
            progress_widget(ui, p.as_ref());
            ui.label(format!("{label} ({secs:.1} s)"));
        }
        ui.label(&state.status);
        if let Some(t) = &state.last_timings {
            ui.separator();
            let grid = t.grid_note();
            ui.label(format!(
                "last stroke{grid}: features {:.0} ms · k-means {:.0} ms · NNFM {:.0} ms · growth {:.0} ms ({} steps) · cut {:.0} ms · total {:.0} ms",
                t.stroke_features_ms,
                t.kmeans_ms,
                t.nnfm_ms,
                t.grow_ms,
                t.grow_steps,
                t.cut_ms,
                t.total_ms()
            ));
        }
        if let Some(fps) = diagnostics
            .and_then(|d| d.get(&FrameTimeDiagnosticsPlugin::FPS))
            .and_then(|d| d.smoothed())
        {
            ui.separator();
            ui.label(format!("{fps:.1} fps"));
        }
        if gpu.uploads > 0 {
            ui.separator();
            ui.label(format!(
                "GPU upload {:.0} ms, {} MB",
                gpu.upload_ms,
                gpu.pool_bytes.div_ceil(1 << 20)
            ));
        }
    });
    if let Some(e) = &gpu.error {
        ui.colored_label(egui::Color32::RED, format!("GPU view: {e}"));
    }
    if let Some(d) = &gpu.detail {
        ui.colored_label(egui::Color32::YELLOW, format!("GPU view: {d}"));
    }
    let mut dismiss = None;
    for (i, e) in state.errors.iter().enumerate() {
        ui.horizontal(|ui| {
            ui.colored_label(egui::Color32::RED, e);
            if ui.small_button("dismiss").clicked() {
                dismiss = Some(i);
            }
        });
    }
    if let Some(i) = dismiss {
        state.errors.remove(i);
    }
}

/// bevy_egui 0.42 hands egui the modifier keys' state every frame as a
/// `ModifiersChanged` event, and any event makes egui ask for the next
/// frame at once: the editor never idled (20 frames a second, 1.7 of two
/// cores on lavapipe while nothing happened, and strokes slower for it).
/// The event is kept only when the modifiers changed; egui carries their
/// state from frame to frame.
pub fn drop_unchanged_modifiers(mut inputs: Query<&mut EguiInput>, mut last: Local<Option<egui::Modifiers>>) {
    for mut input in &mut inputs {
        input.events.retain(|e| match e {
            egui::Event::ModifiersChanged(m) => {
                let changed = *last != Some(*m);
                *last = Some(*m);
                changed
            }
            _ => true,
        });
    }
}

/// A bar with the percentage where the running command knows its total,
/// else a spinner with its stage (and step count, if any).
fn progress_widget(ui: &mut egui::Ui, p: Option<&ProgressState>) {
    match p.and_then(|p| Some((p, p.fraction()?))) {
        Some((p, f)) => {
            let text = format!("{}: {} / {} ({:.0} %)", p.stage, p.done, p.total, 100.0 * f);
            ui.add(egui::ProgressBar::new(f).text(text).desired_width(260.0));
        }
        None => {
            ui.spinner();
            if let Some(p) = p {
                let steps = if p.done > 0 {
                    format!(", {}", p.done)
                } else {
                    String::new()
                };
                ui.label(format!("{}{steps}", p.stage));
            }
        }
    }
}

/// The transform gizmo of the selected object: X / Y / Z move arrows and
/// rotation rings (red, green, blue) and the grey scale circle, each
/// brighter under the cursor or while dragged; clipped to the 3D view.
fn draw_gizmo(ctx: &egui::Context, g: &GizmoView) {
    let Some(c) = g.center else { return };
    let mut painter = ctx.layer_painter(egui::LayerId::new(egui::Order::Foreground, "isrf_gizmo".into()));
    if let Some(r) = g.clip {
        painter = painter.with_clip_rect(egui::Rect::from_min_max(
            egui::pos2(r.min.x, r.min.y),
            egui::pos2(r.max.x, r.max.y),
        ));
    }
    let colors = [
        egui::Color32::from_rgb(230, 70, 70),
        egui::Color32::from_rgb(90, 200, 90),
        egui::Color32::from_rgb(80, 130, 240),
    ];
    let hot = |mode, axis| {
        let h = Some(Handle { mode, axis });
        g.hovered == h || g.active == h
    };
    let style = |hot: bool, color: egui::Color32| {
        if hot {
            (4.0, color.linear_multiply(1.3))
        } else {
            (2.0, color.gamma_multiply(0.8))
        }
    };
    let c = egui::pos2(c.x, c.y);
    let pos = |p: &Vec2| egui::pos2(p.x, p.y);
    let (w, col) = style(hot(TransformMode::Scale, None), egui::Color32::from_gray(220));
    painter.circle_stroke(c, tools::GIZMO_SCALE, egui::Stroke::new(w - 0.5, col));
    for (i, ring) in g.rings.iter().enumerate() {
        if ring.is_empty() {
            continue;
        }
        let (w, col) = style(hot(TransformMode::Rotate, Some(i)), colors[i]);
        painter.add(egui::Shape::closed_line(
            ring.iter().map(pos).collect(),
            egui::Stroke::new(w - 0.5, col),
        ));
    }
    for (i, tip) in g.tips.iter().enumerate() {
        let Some(tip) = tip else { continue };
        let h = hot(TransformMode::Move, Some(i));
        let (w, col) = style(h, colors[i]);
        painter.line_segment([c, pos(tip)], egui::Stroke::new(w + 0.5, col));
        painter.circle_filled(pos(tip), if h { 6.5 } else { 5.0 }, col);
    }
    painter.circle_filled(c, 3.5, egui::Color32::WHITE);
}

/// The stroke being painted, and the brush outline at the cursor.
fn draw_stroke(ctx: &egui::Context, stroke: &CurrentStroke, state: &EditorState) {
    if state.tool != Tool::Brush {
        return;
    }
    let painter = ctx.layer_painter(egui::LayerId::new(egui::Order::Foreground, "isrf_stroke".into()));
    let ppp = ctx.pixels_per_point();
    let r = (state.brush_radius as f32 + 0.5) / ppp;
    let color = if stroke.negative {
        egui::Color32::from_rgb(230, 60, 60)
    } else {
        egui::Color32::from_rgb(60, 200, 90)
    };
    let pts: Vec<egui::Pos2> = stroke.screen.iter().map(|p| egui::pos2(p.x, p.y)).collect();
    if pts.len() >= 2 {
        painter.add(egui::Shape::line(
            pts,
            egui::Stroke::new(2.0 * r, color.gamma_multiply(0.6)),
        ));
    } else if let Some(p) = pts.first() {
        painter.circle_filled(*p, r, color.gamma_multiply(0.6));
    }
    if let Some(p) = ctx.pointer_hover_pos() {
        painter.circle_stroke(p, r, egui::Stroke::new(1.0, color));
    }
}
