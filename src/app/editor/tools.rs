//! Pointer tools: the brush (a drag becomes a [`StrokeMsg`]), the move
//! gizmo (drag an axis arrow of the selected object, release to confirm) and
//! the keyboard transform modes G / R / S (X / Y / Z lock G to an axis; move
//! the mouse, click or Enter confirms, Esc or right click cancels).

use super::camera::EditorCamera;
use super::session::EditorSession;
use super::state::{CurrentStroke, EditorState, GizmoView, Handle, StrokeMsg, Tool, TransformDrag, TransformMode};
use crate::app::convert::{camera_from_bevy, from_bevy_vec3, to_bevy_vec3};
use crate::app::layers::{FieldLayer, ObjectLayer, Selected, SessionName};
use crate::command::{Edit, TransformSpec};
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

/// The scene's space seen from the view's world (where the bevy camera
/// lives): the same for pinhole scenes; for forward-facing captures the
/// NDC space the fields live in ([`EditorState::ndc`]).
#[derive(Clone, Copy, Debug)]
pub struct SceneSpace(pub Option<crate::camera::Ndc>);

impl SceneSpace {
    /// Window position of a scene point (`None` behind the camera).
    pub fn to_screen(&self, cam: &Camera, cam_t: &GlobalTransform, p: Vec3) -> Option<Vec2> {
        let world = match &self.0 {
            Some(n) => to_bevy_vec3(n.to_world(from_bevy_vec3(p))?),
            None => p,
        };
        cam.world_to_viewport(cam_t, world).ok()
    }
    /// The scene-space ray (origin, unit direction) under a window position.
    pub fn ray(&self, cam: &Camera, cam_t: &GlobalTransform, p: Vec2) -> Option<(Vec3, Vec3)> {
        let r = cam.viewport_to_world(cam_t, p).ok()?;
        let (o, d) = (r.origin, r.direction.as_vec3());
        Some(match &self.0 {
            Some(n) => {
                let q = n.ray(&crate::camera::Ray {
                    origin: from_bevy_vec3(o),
                    dir: from_bevy_vec3(d),
                });
                (to_bevy_vec3(q.origin), to_bevy_vec3(q.dir))
            }
            None => (o, d),
        })
    }
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
                let camera = camera.with_ndc(state.ndc);
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
pub fn transform_command(object: &str, from: &Transform, to: &Transform) -> Edit {
    let w = to.to_matrix() * from.to_matrix().inverse();
    Edit::Transform {
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
            let (t, d) = segment_distance(center, tip, cursor);
            // Skip the first fifth: the centre belongs to no single arrow.
            (d <= GIZMO_PICK && t > 0.2).then_some((i, d))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// Screen radius of the rotation rings and of the uniform scale circle
/// (logical pixels).
pub const GIZMO_RING: f32 = 0.7 * GIZMO_ARROW;
pub const GIZMO_SCALE: f32 = GIZMO_ARROW + 24.0;
/// Points per ring polyline.
const RING_POINTS: usize = 48;

/// Screen polylines of the rings about the world axes through `center`,
/// `radius` world units wide; empty for a ring seen (nearly) edge-on, whose
/// plane the cursor ray cannot meet reliably, or one crossing behind the
/// camera.
pub fn gizmo_rings(to_screen: impl Fn(Vec3) -> Option<Vec2>, center: Vec3, radius: f32) -> [Vec<Vec2>; 3] {
    Vec3::AXES.map(|axis| {
        let (u, v) = axis.any_orthonormal_pair();
        let pts: Option<Vec<Vec2>> = (0..RING_POINTS)
            .map(|k| {
                let a = std::f32::consts::TAU * k as f32 / RING_POINTS as f32;
                to_screen(center + radius * (u * a.cos() + v * a.sin()))
            })
            .collect();
        let Some(pts) = pts else { return vec![] };
        // Shoelace area against the circle through the farthest point.
        let area = 0.5
            * pts
                .iter()
                .zip(pts.iter().cycle().skip(1))
                .map(|(p, q)| p.perp_dot(*q))
                .sum::<f32>()
                .abs();
        let c = pts.iter().copied().sum::<Vec2>() / pts.len() as f32;
        let r = pts.iter().map(|p| p.distance(c)).fold(0.0, f32::max);
        if area < 0.15 * std::f32::consts::PI * r * r {
            return vec![];
        }
        pts
    })
}

/// (t, distance) of the point `a + t·(b − a)`, t in [0, 1], nearest `p`.
fn segment_distance(a: Vec2, b: Vec2, p: Vec2) -> (f32, f32) {
    let seg = b - a;
    let t = ((p - a).dot(seg) / seg.length_squared().max(1e-9)).clamp(0.0, 1.0);
    (t, (a + t * seg).distance(p))
}

/// Distance from `p` to the closed polyline `pts`.
fn polyline_distance(pts: &[Vec2], p: Vec2) -> f32 {
    pts.iter()
        .zip(pts.iter().cycle().skip(1))
        .map(|(&a, &b)| segment_distance(a, b, p).1)
        .fold(f32::INFINITY, f32::min)
}

/// The handle under `cursor`: an arrow first, then the nearest ring, then
/// the scale circle.
pub fn pick_handle(view: &GizmoView, cursor: Vec2) -> Option<Handle> {
    let center = view.center?;
    if let Some(i) = pick_arrow(center, &view.tips, cursor) {
        return Some(Handle {
            mode: TransformMode::Move,
            axis: Some(i),
        });
    }
    let ring = (0..3)
        .filter(|&i| !view.rings[i].is_empty())
        .map(|i| (i, polyline_distance(&view.rings[i], cursor)))
        .filter(|&(_, d)| d <= GIZMO_PICK)
        .min_by(|a, b| a.1.total_cmp(&b.1));
    if let Some((i, _)) = ring {
        return Some(Handle {
            mode: TransformMode::Rotate,
            axis: Some(i),
        });
    }
    ((cursor.distance(center) - GIZMO_SCALE).abs() <= GIZMO_PICK).then_some(Handle {
        mode: TransformMode::Scale,
        axis: None,
    })
}

/// Rotation angle (radians, right-handed about `axis`) that carries the
/// point where ray 0 meets the plane through `center` perpendicular to
/// `axis` onto the point where ray 1 meets it: the ring follows the cursor.
/// `None` when a ray misses the plane or meets it at the centre.
pub fn ring_angle(center: Vec3, axis: Vec3, r0: (Vec3, Vec3), r1: (Vec3, Vec3)) -> Option<f32> {
    let hit = |(o, d): (Vec3, Vec3)| {
        let den = d.dot(axis);
        let t = (center - o).dot(axis) / den;
        (den.abs() > 1e-4 && t > 0.0).then(|| o + d * t - center)
    };
    let (a, b) = (hit(r0)?, hit(r1)?);
    (a.length() > 1e-6 && b.length() > 1e-6).then(|| axis.dot(a.cross(b)).atan2(a.dot(b)))
}

/// Uniform scale of a drag on the scale circle: the ratio of the cursor's
/// distances from the centre, kept within [0.01, 100].
pub fn scale_factor(center: Vec2, cursor0: Vec2, cursor: Vec2) -> f32 {
    (cursor.distance(center) / cursor0.distance(center).max(1.0)).clamp(0.01, 100.0)
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
    let active = state.transform.filter(|d| d.gizmo).map(|d| Handle {
        mode: d.mode,
        axis: d.axis,
    });
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
    if obj.placement.removed || !obj.placement.visible {
        return;
    }
    let center = object_center(obj, t, field, field_t);
    let space = SceneSpace(state.ndc);
    let to_screen = |p| space.to_screen(cam, cam_t, p);
    // Length of the arrows: their screen size at the object's depth.
    let Some((eye, _)) = to_screen(center).and_then(|c| space.ray(cam, cam_t, c)) else {
        return;
    };
    let scale = 0.25 * (center - eye).length().max(1e-3);
    let Some((c, tips)) = gizmo_arrows(to_screen, center, scale) else {
        return;
    };
    // Ring radius in world units that shows as `GIZMO_RING` pixels: the
    // screen length of the most face-on axis gives pixels per world unit.
    let px_per_unit = Vec3::AXES
        .iter()
        .filter_map(|a| Some((to_screen(center + *a * scale)? - c).length() / scale))
        .fold(0.0, f32::max);
    let rings = if px_per_unit > 0.0 {
        gizmo_rings(to_screen, center, GIZMO_RING / px_per_unit)
    } else {
        Default::default()
    };
    // bevy's viewport conversions work in window coordinates (the
    // viewport's offset included), like the cursor.
    view.center = Some(c);
    view.clip = cam.logical_viewport_rect();
    view.tips = tips;
    view.rings = rings;
    if let Some(cursor) = windows.single().ok().and_then(|w| w.cursor_position()) {
        view.hovered = pick_handle(&view, cursor);
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
        // A press on a gizmo handle starts its drag; else G / R / S.
        let egui_pointer = wants.as_ref().is_some_and(|w| w.wants_pointer_input());
        let handle = gizmo
            .hovered
            .filter(|_| buttons.just_pressed(MouseButton::Left) && !egui_pointer);
        let mode = if let Some(h) = handle {
            h.mode
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
            axis: handle.and_then(|h| h.axis),
            gizmo: handle.is_some(),
        });
        state.status = match handle {
            Some(Handle { mode, axis: Some(i) }) => {
                let verb = if mode == TransformMode::Move {
                    "moving along"
                } else {
                    "rotating about"
                };
                format!("{verb} {}: release to place, Esc cancels", AXIS_NAMES[i])
            }
            Some(_) => "scaling: release to place, Esc cancels".into(),
            None => format!("{mode:?}: move the mouse (X / Y / Z: world axis), click or Enter confirms, Esc cancels"),
        };
        return;
    }
    let Some(mut drag) = state.transform else { return };
    // X / Y / Z lock a keyboard move, rotation or scale to a world axis
    // (again: unlock).
    if !drag.gizmo {
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
    // Window coordinates, like the cursor (bevy includes the viewport
    // offset); rays in the scene's space.
    let space = SceneSpace(state.ndc);
    let ray = |p: Vec2| space.ray(cam, cam_t, p);
    let (Some(r0), Some(r1)) = (ray(drag.cursor0), ray(cursor)) else {
        return;
    };
    // The line of sight through the object's centre.
    let center_px = space.to_screen(cam, cam_t, center);
    let Some((_, fwd)) = center_px.and_then(ray) else {
        return;
    };
    let axis = drag.axis.map(|i| Vec3::AXES[i]);
    let about_center = |m: Mat4| Mat4::from_translation(center) * m * Mat4::from_translation(-center);
    let w = match drag.mode {
        TransformMode::Move => {
            if let Some(axis) = axis {
                // Along the axis: between the points of the axis line
                // nearest to the two cursor rays.
                let s = |r: (Vec3, Vec3)| closest_on_axis(center, axis, r.0, r.1);
                let (Some(sa), Some(sb)) = (s(r0), s(r1)) else { return };
                Mat4::from_translation(axis * (sb - sa))
            } else {
                // Free: the cursor delta on the plane through the object's
                // centre facing the line of sight.
                let on_plane = |r: (Vec3, Vec3)| r.0 + r.1 * ((center - r.0).dot(fwd) / r.1.dot(fwd));
                Mat4::from_translation(on_plane(r1) - on_plane(r0))
            }
        }
        TransformMode::Rotate => {
            let angle = match axis {
                // The ring follows the cursor.
                Some(a) => ring_angle(center, a, r0, r1).unwrap_or(0.0),
                None => -(cursor - drag.cursor0).x * 0.01,
            };
            about_center(Mat4::from_axis_angle(axis.unwrap_or(fwd), angle))
        }
        TransformMode::Scale => {
            let s = if drag.gizmo {
                let c = center_px.unwrap_or(drag.cursor0);
                scale_factor(c, drag.cursor0, cursor)
            } else {
                ((cursor - drag.cursor0).x * 0.005).exp()
            };
            let v = axis.map_or(Vec3::splat(s), |a| Vec3::ONE + (s - 1.0) * a);
            about_center(Mat4::from_scale(v))
        }
    };
    *t = Transform::from_matrix(w * drag.start.to_matrix());
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::command::state::{Placement, State};
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
        let mut st = State::default();
        let fid = st.add_field("f", FieldSource::File("x".into()), f, Placement::default(), None);
        let placement = Placement {
            transform: start,
            ..Default::default()
        };
        st.add_object("o", fid, Arc::new(mask), placement);
        let mut s = Session::with_state(".", ".", st);
        let from = crate::app::convert::bevy_transform(&start);
        let to = Transform::from_translation(Vec3::new(-0.4, 0.0, 0.5))
            .with_rotation(Quat::from_rotation_y(0.7))
            .with_scale(Vec3::splat(1.3));
        s.apply(&transform_command("o", &from, &to)).unwrap();
        let got = crate::app::convert::to_bevy_mat4(&s.object("o").unwrap().placement.transform);
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

    /// A pinhole at the origin looking down -z, 500 px focal, 800×600.
    fn pinhole(p: Vec3) -> Option<Vec2> {
        (p.z < 0.0).then(|| Vec2::new(400.0 + 500.0 * p.x / -p.z, 300.0 - 500.0 * p.y / -p.z))
    }

    #[test]
    fn rings_are_picked_and_edge_on_rings_dropped() {
        let center = Vec3::new(0.0, 0.0, -4.0);
        let rings = gizmo_rings(pinhole, center, 0.5);
        // Looking down -z: the ring about z faces the camera (a circle of
        // 500·0.5/4 = 62.5 px); those about x and y are edge-on.
        assert!(rings[0].is_empty() && rings[1].is_empty());
        let r = rings[2].iter().map(|p| p.distance(Vec2::new(400.0, 300.0)));
        assert!(r.clone().all(|d| (d - 62.5).abs() < 0.5));
        let (c, tips) = gizmo_arrows(pinhole, center, 1.0).unwrap();
        let view = GizmoView {
            center: Some(c),
            tips,
            rings,
            ..Default::default()
        };
        let rotate_z = Handle {
            mode: TransformMode::Rotate,
            axis: Some(2),
        };
        // On the ring, off the arrows (45° between x and y).
        let on_ring = c + Vec2::new(1.0, -1.0).normalize() * 62.0;
        assert_eq!(pick_handle(&view, on_ring), Some(rotate_z));
        // Where the ring crosses the x arrow, the arrow wins.
        assert_eq!(
            pick_handle(&view, c + Vec2::new(62.5, 0.0)).map(|h| h.mode),
            Some(TransformMode::Move)
        );
        // The scale circle, and empty space between ring and circle.
        let scale = pick_handle(&view, c + Vec2::new(0.0, GIZMO_SCALE + 3.0)).unwrap();
        assert_eq!((scale.mode, scale.axis), (TransformMode::Scale, None));
        assert_eq!(pick_handle(&view, c + Vec2::new(-75.0, 0.0)), None);
    }

    #[test]
    fn dragging_a_ring_rotates_by_the_angle_the_cursor_sweeps() {
        // Rays from a camera at (0, 0, 5) towards points of the plane z = 0:
        // from +x to +y is a quarter turn counter-clockwise about +z.
        let eye = Vec3::new(0.0, 0.0, 5.0);
        let ray = |p: Vec3| (eye, (p - eye).normalize());
        let a = ring_angle(Vec3::ZERO, Vec3::Z, ray(Vec3::X), ray(Vec3::Y)).unwrap();
        assert!((a - std::f32::consts::FRAC_PI_2).abs() < 1e-5, "{a}");
        let b = ring_angle(Vec3::ZERO, Vec3::Z, ray(Vec3::Y), ray(Vec3::X)).unwrap();
        assert!((b + std::f32::consts::FRAC_PI_2).abs() < 1e-5, "{b}");
        // Rotating the start point by the angle lands on the end point.
        let (p0, p1) = (Vec3::new(0.3, 0.1, 0.0), Vec3::new(-0.2, 0.25, 0.0));
        let c = ring_angle(Vec3::ZERO, Vec3::Z, ray(p0), ray(p1)).unwrap();
        let q = Quat::from_axis_angle(Vec3::Z, c) * p0;
        assert!(q.normalize().abs_diff_eq(p1.normalize(), 1e-5), "{q} vs {p1}");
        // A ray parallel to the plane has no angle.
        assert!(ring_angle(Vec3::ZERO, Vec3::Z, (eye, Vec3::X), ray(Vec3::Y)).is_none());
    }

    #[test]
    fn the_scale_circle_scales_by_the_distance_ratio() {
        let c = Vec2::new(100.0, 100.0);
        assert!((scale_factor(c, c + Vec2::new(50.0, 0.0), c + Vec2::new(0.0, 75.0)) - 1.5).abs() < 1e-6);
        assert_eq!(scale_factor(c, c + Vec2::X * 50.0, c), 0.01);
    }
}
