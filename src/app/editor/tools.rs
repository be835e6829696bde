//! Pointer tools: the brush (a drag becomes a [`StrokeMsg`]), the move
//! gizmo (drag an axis arrow of the selected object, release to confirm) and
//! the keyboard transform modes G / R / S (X / Y / Z lock G to an axis; move
//! the mouse, click or Enter confirms, Esc or right click cancels).

use super::camera::EditorCamera;
use super::session::EditorSession;
use super::state::{CurrentStroke, EditorState, GizmoView, StrokeMsg, Tool, TransformDrag, TransformMode};
use crate::app::convert::camera_from_bevy;
use crate::app::layers::{FieldLayer, ObjectLayer, Selected, SessionName};
use crate::command::{Command, TransformSpec};
use crate::segment::Polarity;
use bevy::camera::Projection;
use bevy::prelude::*;
use bevy::window::PrimaryWindow;
use bevy_egui::input::EguiWantsInput;

/// The library camera of the editor view (physical pixels of its viewport).
pub fn view_camera(cam: &Camera, t: &GlobalTransform, proj: &Projection) -> Option<crate::camera::Camera> {
    let Projection::Perspective(p) = proj else {
        return None;
    };
    let size = cam.physical_viewport_size()?;
    Some(camera_from_bevy(&t.compute_transform(), p.fov, size.x, size.y))
}

/// Cursor in physical pixels relative to the camera's viewport.
fn cursor_pixels(window: &Window, cam: &Camera) -> Option<Vec2> {
    let c = window.physical_cursor_position()?;
    let origin = cam.physical_viewport_rect().map_or(Vec2::ZERO, |r| r.min.as_vec2());
    Some(c - origin)
}

#[allow(clippy::too_many_arguments)]
pub fn brush(
    mut state: ResMut<EditorState>,
    mut stroke: ResMut<CurrentStroke>,
    buttons: Res<ButtonInput<MouseButton>>,
    keys: Res<ButtonInput<KeyCode>>,
    wants: Option<Res<EguiWantsInput>>,
    windows: Query<&Window, With<PrimaryWindow>>,
    cams: Query<(&Camera, &GlobalTransform, &Projection), With<EditorCamera>>,
    gizmo: Res<GizmoView>,
    mut out: MessageWriter<StrokeMsg>,
) {
    // A press on a gizmo arrow moves the object instead of painting.
    let on_gizmo = stroke.pixels.is_empty() && gizmo.hovered.is_some();
    if state.tool != Tool::Brush || state.fly || state.transform.is_some() || on_gizmo {
        stroke.screen.clear();
        stroke.pixels.clear();
        return;
    }
    let (Ok(window), Ok((cam, gt, proj))) = (windows.single(), cams.single()) else {
        return;
    };
    let egui_busy = wants.is_some_and(|w| w.wants_any_pointer_input());
    if buttons.just_pressed(MouseButton::Left) && !egui_busy {
        stroke.screen.clear();
        stroke.pixels.clear();
        stroke.negative = state.negative || keys.pressed(KeyCode::ControlLeft) || keys.pressed(KeyCode::ControlRight);
    }
    let painting = buttons.pressed(MouseButton::Left) && !(stroke.pixels.is_empty() && egui_busy);
    if painting {
        if let (Some(screen), Some(px)) = (window.cursor_position(), cursor_pixels(window, cam)) {
            if stroke.screen.last() != Some(&screen) {
                stroke.screen.push(screen);
                stroke.pixels.push(glam::Vec2::new(px.x, px.y));
            }
        }
    }
    if buttons.just_released(MouseButton::Left) && !stroke.pixels.is_empty() {
        let points = std::mem::take(&mut stroke.pixels);
        stroke.screen.clear();
        match view_camera(cam, gt, proj) {
            Some(camera) => {
                out.write(StrokeMsg {
                    camera,
                    points,
                    radius: state.brush_radius,
                    polarity: if stroke.negative {
                        Polarity::Negative
                    } else {
                        Polarity::Positive
                    },
                });
            }
            None => state.error("strokes need a perspective view"),
        }
    }
}

/// World-space centre of an object's voxels: its field's placement, then
/// the object's (world = object · field).
pub fn object_center(obj: &ObjectLayer, obj_t: &Transform, field: &FieldLayer, field_t: &Transform) -> Vec3 {
    let g = field.field.geom();
    let c = match obj.bitmap.bounding_box() {
        Some((lo, hi)) => 0.5 * (g.point(lo[0], lo[1], lo[2]) + g.point(hi[0], hi[1], hi[2])),
        None => g.bounds.center(),
    };
    obj_t.transform_point(field_t.transform_point(Vec3::from_array(c.to_array())))
}

/// The `Transform` command that turns placement `from` into `to`
/// (world-space change `to · from⁻¹`, given as a row-major matrix).
pub fn transform_command(object: &str, from: &Transform, to: &Transform) -> Command {
    let w = to.to_matrix() * from.to_matrix().inverse();
    Command::Transform {
        object: object.to_string(),
        transform: TransformSpec {
            matrix: Some(w.transpose().to_cols_array_2d()),
            ..Default::default()
        },
    }
}

/// Length of the gizmo arrows on screen (logical pixels).
pub const GIZMO_ARROW: f32 = 80.0;
/// How close (logical pixels) the cursor must be to pick an arrow.
const GIZMO_PICK: f32 = 8.0;

/// Screen arrows of the world axes at `center`: each `GIZMO_ARROW` long,
/// `None` where the axis is nearly along the view ray (its screen direction
/// would be meaningless) or the centre is behind the camera.
pub fn gizmo_arrows(
    to_screen: impl Fn(Vec3) -> Option<Vec2>,
    center: Vec3,
    scale: f32,
) -> Option<(Vec2, [Option<Vec2>; 3])> {
    let c = to_screen(center)?;
    let tips = Vec3::AXES.map(|a| {
        let d = to_screen(center + a * scale)? - c;
        // Shorter than a fifth of the arrow per `scale`: pointing at us.
        (d.length() > 0.2 * GIZMO_ARROW).then(|| c + d.normalize() * GIZMO_ARROW)
    });
    Some((c, tips))
}

/// The arrow whose segment passes within `GIZMO_PICK` of `cursor` (the
/// nearest one).
pub fn pick_arrow(center: Vec2, tips: &[Option<Vec2>; 3], cursor: Vec2) -> Option<usize> {
    tips.iter()
        .enumerate()
        .filter_map(|(i, tip)| {
            let tip = (*tip)?;
            let seg = tip - center;
            let t = ((cursor - center).dot(seg) / seg.length_squared()).clamp(0.0, 1.0);
            let d = (center + t * seg).distance(cursor);
            // Skip the first fifth: the centre belongs to no single arrow.
            (d <= GIZMO_PICK && t > 0.2).then_some((i, d))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// Parameter s of the point on the line `center + s·axis` closest to the
/// ray `(origin, dir)`; `None` when they are (nearly) parallel.
pub fn closest_on_axis(center: Vec3, axis: Vec3, origin: Vec3, dir: Vec3) -> Option<f32> {
    let w = center - origin;
    let (a, b, c) = (axis.dot(axis), axis.dot(dir), dir.dot(dir));
    let (d, e) = (axis.dot(w), dir.dot(w));
    let den = a * c - b * b;
    (den.abs() > 1e-6 * a * c).then(|| (b * e - c * d) / den)
}

/// Places the move gizmo on the selected object (or clears it).
#[allow(clippy::too_many_arguments)]
pub fn gizmo(
    state: Res<EditorState>,
    mut view: ResMut<GizmoView>,
    windows: Query<&Window, With<PrimaryWindow>>,
    cams: Query<(&Camera, &GlobalTransform), With<EditorCamera>>,
    selected: Query<Entity, (With<Selected>, With<ObjectLayer>)>,
    objects: Query<(&ObjectLayer, &Transform), Without<FieldLayer>>,
    fields: Query<(&FieldLayer, &Transform), Without<ObjectLayer>>,
) {
    let active = state.transform.filter(|d| d.gizmo).and_then(|d| d.axis);
    *view = GizmoView {
        active,
        ..Default::default()
    };
    let busy = state.fly || state.transform.is_some_and(|d| !d.gizmo);
    let (Ok(entity), Ok((cam, cam_t)), false) = (selected.single(), cams.single(), busy) else {
        return;
    };
    let Ok((obj, t)) = objects.get(entity) else { return };
    let Ok((field, field_t)) = fields.get(obj.field) else {
        return;
    };
    if obj.removed || obj.hidden {
        return;
    }
    let center = object_center(obj, t, field, field_t);
    // World length of the arrows: their screen size at the object's depth.
    let scale = 0.25 * (center - cam_t.translation()).length().max(1e-3);
    let Some((c, tips)) = gizmo_arrows(|p| cam.world_to_viewport(cam_t, p).ok(), center, scale) else {
        return;
    };
    let origin = cam.logical_viewport_rect().map_or(Vec2::ZERO, |r| r.min);
    view.center = Some(c + origin);
    view.tips = tips.map(|t| t.map(|t| t + origin));
    if let Some(cursor) = windows.single().ok().and_then(|w| w.cursor_position()) {
        view.hovered = pick_arrow(c + origin, &view.tips, cursor);
    }
}

const AXIS_NAMES: [&str; 3] = ["X", "Y", "Z"];

#[allow(clippy::too_many_arguments)]
pub fn transform_modes(
    mut state: ResMut<EditorState>,
    mut es: ResMut<EditorSession>,
    keys: Res<ButtonInput<KeyCode>>,
    buttons: Res<ButtonInput<MouseButton>>,
    wants: Option<Res<EguiWantsInput>>,
    gizmo: Res<GizmoView>,
    windows: Query<&Window, With<PrimaryWindow>>,
    cams: Query<(&Camera, &GlobalTransform), With<EditorCamera>>,
    selected: Query<Entity, (With<Selected>, With<ObjectLayer>)>,
    mut objects: Query<(&SessionName, &ObjectLayer, &mut Transform), Without<FieldLayer>>,
    fields: Query<(&FieldLayer, &Transform), Without<ObjectLayer>>,
) {
    let typing = wants.as_ref().is_some_and(|w| w.wants_keyboard_input());
    let Ok(window) = windows.single() else { return };
    let Some(cursor) = window.cursor_position() else { return };
    if state.transform.is_none() {
        // A press on a gizmo arrow starts an axis move; else G / R / S.
        let egui_pointer = wants.as_ref().is_some_and(|w| w.wants_pointer_input());
        let arrow = gizmo
            .hovered
            .filter(|_| buttons.just_pressed(MouseButton::Left) && !egui_pointer);
        let mode = if arrow.is_some() {
            TransformMode::Move
        } else if typing || state.fly || keys.any_pressed([KeyCode::ControlLeft, KeyCode::ControlRight]) {
            return;
        } else if keys.just_pressed(KeyCode::KeyG) {
            TransformMode::Move
        } else if keys.just_pressed(KeyCode::KeyR) {
            TransformMode::Rotate
        } else if keys.just_pressed(KeyCode::KeyS) {
            TransformMode::Scale
        } else {
            return;
        };
        let Ok(entity) = selected.single() else {
            state.status = "select an object to move, rotate or scale it".into();
            return;
        };
        let Ok((_, _, t)) = objects.get(entity) else { return };
        state.transform = Some(TransformDrag {
            mode,
            entity,
            start: *t,
            cursor0: cursor,
            axis: arrow,
            gizmo: arrow.is_some(),
        });
        state.status = match arrow {
            Some(i) => format!("moving along {}: release to place, Esc cancels", AXIS_NAMES[i]),
            None => format!("{mode:?}: move the mouse, click or Enter confirms, Esc cancels"),
        };
        return;
    }
    let Some(mut drag) = state.transform else { return };
    // X / Y / Z lock a keyboard move to a world axis (again: unlock).
    if drag.mode == TransformMode::Move && !drag.gizmo {
        for (a, k) in [KeyCode::KeyX, KeyCode::KeyY, KeyCode::KeyZ].into_iter().enumerate() {
            if keys.just_pressed(k) {
                drag.axis = if drag.axis == Some(a) { None } else { Some(a) };
                state.transform = Some(drag);
            }
        }
    }
    let Ok((name, obj, mut t)) = objects.get_mut(drag.entity) else {
        state.transform = None;
        return;
    };
    let Ok((field, field_t)) = fields.get(obj.field) else {
        state.transform = None;
        return;
    };
    if keys.just_pressed(KeyCode::Escape) || buttons.just_pressed(MouseButton::Right) {
        *t = drag.start;
        state.transform = None;
        state.status = "transform cancelled".into();
        return;
    }
    let confirm = if drag.gizmo {
        !buttons.pressed(MouseButton::Left)
    } else {
        keys.just_pressed(KeyCode::Enter) || buttons.just_pressed(MouseButton::Left)
    };
    if confirm {
        state.transform = None;
        if *t != drag.start {
            es.apply(transform_command(&name.0, &drag.start, &t));
        }
        return;
    }
    let Ok((cam, cam_t)) = cams.single() else { return };
    let center = object_center(obj, &drag.start, field, field_t);
    let d = cursor - drag.cursor0;
    let fwd = cam_t.forward().as_vec3();
    let w = match drag.mode {
        TransformMode::Move => {
            let origin = cam.logical_viewport_rect().map_or(Vec2::ZERO, |r| r.min);
            let (Ok(a), Ok(b)) = (
                cam.viewport_to_world(cam_t, drag.cursor0 - origin),
                cam.viewport_to_world(cam_t, cursor - origin),
            ) else {
                return;
            };
            if let Some(axis) = drag.axis.map(|i| Vec3::AXES[i]) {
                // Along the axis: between the points of the axis line
                // nearest to the two cursor rays.
                let s = |r: Ray3d| closest_on_axis(center, axis, r.origin, r.direction.as_vec3());
                let (Some(sa), Some(sb)) = (s(a), s(b)) else { return };
                *t = Transform::from_matrix(Mat4::from_translation(axis * (sb - sa)) * drag.start.to_matrix());
                return;
            }
            // Free: the cursor delta at the object's depth, in the view plane.
            let depth = (center - cam_t.translation()).dot(fwd);
            let pa = a.origin + a.direction * (depth / a.direction.dot(fwd));
            let pb = b.origin + b.direction * (depth / b.direction.dot(fwd));
            Mat4::from_translation(pb - pa)
        }
        TransformMode::Rotate => {
            let r = Mat4::from_axis_angle(fwd, -d.x * 0.01);
            Mat4::from_translation(center) * r * Mat4::from_translation(-center)
        }
        TransformMode::Scale => {
            let s = (d.x * 0.005).exp();
            Mat4::from_translation(center) * Mat4::from_scale(Vec3::splat(s)) * Mat4::from_translation(-center)
        }
    };
    *t = Transform::from_matrix(w * drag.start.to_matrix());
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::command::session::{FieldEntry, ObjectEntry, State};
    use crate::command::{FieldSource, Session};
    use crate::field::{Aabb, Bitmap, FieldBuilder};
    use std::sync::Arc;

    #[test]
    fn transform_commands_reach_the_dragged_placement() {
        let f = Arc::new(
            FieldBuilder::new(Aabb::new(glam::Vec3::splat(-1.0), glam::Vec3::ONE), [5, 5, 5]).build(
                |_| 1.0,
                |_| glam::Vec3::ONE,
                None,
            ),
        );
        let mut mask = Bitmap::new(f.res());
        mask.set(62, true);
        let start = glam::Affine3A::from_translation(glam::Vec3::new(0.1, 0.2, 0.3));
        let mut s = Session::default();
        s.set_state(State {
            fields: vec![FieldEntry {
                name: "f".into(),
                source: FieldSource::File("x".into()),
                field: f,
                transform: glam::Affine3A::IDENTITY,
                visible: true,
                demo: None,
            }],
            objects: vec![ObjectEntry {
                name: "o".into(),
                field: "f".into(),
                mask: Arc::new(mask),
                transform: start,
                removed: false,
                visible: true,
                duplicate: false,
                color_edit: None,
            }],
            params: Default::default(),
            background: [1.0; 3],
        });
        let from = crate::app::convert::bevy_transform(&start);
        let to = Transform::from_translation(Vec3::new(-0.4, 0.0, 0.5))
            .with_rotation(Quat::from_rotation_y(0.7))
            .with_scale(Vec3::splat(1.3));
        s.apply(&transform_command("o", &from, &to)).unwrap();
        let got = crate::app::convert::to_bevy_mat4(&s.object("o").unwrap().transform);
        assert!(got.abs_diff_eq(to.to_matrix(), 1e-5), "{got:?} vs {:?}", to.to_matrix());
    }

    #[test]
    fn closest_point_on_the_axis_to_a_ray() {
        // Axis x through (0, 0, -5); a ray from the origin towards (2, 1, -5)
        // passes over x = 2 on that line.
        let c = Vec3::new(0.0, 0.0, -5.0);
        let s = closest_on_axis(c, Vec3::X, Vec3::ZERO, Vec3::new(2.0, 0.0, -5.0).normalize()).unwrap();
        assert!((s - 2.0).abs() < 1e-5, "{s}");
        // Skew lines: the ray (2t, t, −5t) is nearest the axis where
        // t² + 25(1 − t)² is least, t = 25/26, so x = 2t = 50/26.
        let s = closest_on_axis(c, Vec3::X, Vec3::ZERO, Vec3::new(2.0, 1.0, -5.0).normalize()).unwrap();
        assert!((s - 50.0 / 26.0).abs() < 1e-5, "{s}");
        // A ray along the axis has no single nearest point.
        assert!(closest_on_axis(c, Vec3::Z, Vec3::ZERO, Vec3::NEG_Z).is_none());
    }

    #[test]
    fn arrows_are_picked_along_their_shaft_only() {
        // A pinhole looking down -z: the z arrow points at the camera.
        let project = |p: Vec3| (p.z < 0.0).then(|| Vec2::new(400.0 + 500.0 * p.x / -p.z, 300.0 - 500.0 * p.y / -p.z));
        let (c, tips) = gizmo_arrows(project, Vec3::new(0.0, 0.0, -4.0), 1.0).unwrap();
        assert_eq!(c, Vec2::new(400.0, 300.0));
        let x = tips[0].unwrap();
        let y = tips[1].unwrap();
        assert!((x - Vec2::new(400.0 + GIZMO_ARROW, 300.0)).length() < 1e-3);
        assert!((y - Vec2::new(400.0, 300.0 - GIZMO_ARROW)).length() < 1e-3);
        assert!(tips[2].is_none(), "the z arrow points at the camera");
        assert_eq!(pick_arrow(c, &tips, Vec2::new(450.0, 305.0)), Some(0));
        assert_eq!(pick_arrow(c, &tips, Vec2::new(398.0, 250.0)), Some(1));
        // Off the shafts, past the tips, and at the shared centre: nothing.
        assert_eq!(pick_arrow(c, &tips, Vec2::new(450.0, 330.0)), None);
        assert_eq!(pick_arrow(c, &tips, Vec2::new(400.0 + GIZMO_ARROW + 20.0, 300.0)), None);
        assert_eq!(pick_arrow(c, &tips, Vec2::new(402.0, 298.0)), None);
        // Behind the camera: no gizmo.
        assert!(gizmo_arrows(project, Vec3::new(0.0, 0.0, 4.0), 1.0).is_none());
    }
}
