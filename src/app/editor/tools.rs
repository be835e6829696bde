//! Pointer tools: the brush (a drag becomes a [`StrokeMsg`]) and the
//! keyboard transform modes G / R / S on the selected object (drag, then
//! click or Enter to confirm, Esc or right click to cancel).

use super::camera::EditorCamera;
use super::session::EditorSession;
use super::state::{CurrentStroke, EditorState, StrokeMsg, Tool, TransformDrag, TransformMode};
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
    mut out: MessageWriter<StrokeMsg>,
) {
    if state.tool != Tool::Brush || state.fly || state.transform.is_some() {
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

#[allow(clippy::too_many_arguments)]
pub fn transform_modes(
    mut state: ResMut<EditorState>,
    mut es: ResMut<EditorSession>,
    keys: Res<ButtonInput<KeyCode>>,
    buttons: Res<ButtonInput<MouseButton>>,
    wants: Option<Res<EguiWantsInput>>,
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
        if typing || state.fly || keys.any_pressed([KeyCode::ControlLeft, KeyCode::ControlRight]) {
            return;
        }
        let mode = if keys.just_pressed(KeyCode::KeyG) {
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
        });
        state.status = format!("{mode:?}: move the mouse, click or Enter confirms, Esc cancels");
        return;
    }
    let drag = state.transform.unwrap();
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
    if keys.just_pressed(KeyCode::Enter) || buttons.just_pressed(MouseButton::Left) {
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
            // Cursor delta at the object's depth, in the view plane.
            let (Ok(a), Ok(b)) = (
                cam.viewport_to_world(cam_t, drag.cursor0),
                cam.viewport_to_world(cam_t, cursor),
            ) else {
                return;
            };
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
}
