//! Camera controls: orbit / pan / zoom (bevy_panorbit_camera, switched off
//! while egui has the pointer, while painting or transforming, and in fly
//! mode), a WASD fly mode, snapping to the capture's views, and the march
//! resolution while the view moves.

use super::state::{EditorState, MovingResolution, Tool};
use crate::app::convert::{bevy_transform, projection_for, to_bevy_vec3};
use crate::app::gpu::{MarchScene, RayMarchCamera};
use crate::camera::Camera as IsrfCamera;
use bevy::camera::Projection;
use bevy::input::mouse::AccumulatedMouseMotion;
use bevy::prelude::*;
use bevy_egui::input::EguiWantsInput;
use bevy_panorbit_camera::PanOrbitCamera;

/// Marks the editor's view camera.
#[derive(Component)]
pub struct EditorCamera;

/// Yaw / pitch / radius of a pose looking at `focus` in panorbit's
/// convention (translation = focus + Ry(yaw)·Rx(−pitch)·(0, 0, r)).
pub fn orbit_of(eye: Vec3, focus: Vec3) -> (f32, f32, f32) {
    let off = eye - focus;
    let r = off.length().max(1e-4);
    (off.x.atan2(off.z), (off.y / r).clamp(-1.0, 1.0).asin(), r)
}

/// Points the panorbit controller at a pose: focus on the view axis at the
/// distance of `target_depth`.
pub fn aim_orbit(pan: &mut PanOrbitCamera, t: &Transform, target_depth: f32) {
    let eye = t.translation;
    let focus = eye + t.forward() * target_depth.max(0.05);
    let (yaw, pitch, r) = orbit_of(eye, focus);
    pan.focus = focus;
    pan.target_focus = focus;
    pan.yaw = Some(yaw);
    pan.pitch = Some(pitch);
    pan.radius = Some(r);
    pan.target_yaw = yaw;
    pan.target_pitch = pitch;
    pan.target_radius = r;
    pan.force_update = true;
}

/// Snaps the view camera to a capture view (pose and vertical FOV).
pub fn snap_to(
    cam: &IsrfCamera,
    focus_depth: f32,
    transform: &mut Transform,
    projection: &mut Projection,
    pan: &mut PanOrbitCamera,
) {
    *transform = bevy_transform(&cam.c2w);
    if let (Projection::Perspective(p), Projection::Perspective(q)) = (projection, projection_for(&cam.intrinsics)) {
        p.fov = q.fov;
    }
    aim_orbit(pan, transform, focus_depth);
}

/// Snaps the view to a capture view, orbiting about the first field's
/// centre (in the world: an NDC field's centre is mapped back from `ndc`).
pub fn snap_to_capture(
    cam: &IsrfCamera,
    st: &crate::command::state::State,
    ndc: Option<crate::camera::Ndc>,
    transform: &mut Transform,
    projection: &mut Projection,
    pan: &mut PanOrbitCamera,
) {
    let center = st.fields.first().map_or(Vec3::ZERO, |f| {
        let c = f.field.bounds().center();
        to_bevy_vec3(ndc.and_then(|n| n.to_world(c)).unwrap_or(c))
    });
    let depth = (center - to_bevy_vec3(cam.position())).dot(to_bevy_vec3(cam.forward()));
    snap_to(cam, depth, transform, projection, pan);
}

/// Seconds without a change after which the view counts as still.
const REST_SECONDS: f64 = 0.3;

/// Tracks whether the view is in motion: from a change until
/// [`REST_SECONDS`] after the last one. A single change (a stroke's result,
/// a typed value) counts too: on a slow GPU its first image then comes from
/// the quick half-resolution march, and the full one follows at rest
/// (progressive refinement, for a quarter more work).
#[derive(Default, Debug, Clone, Copy)]
pub struct MotionClock {
    last_change: Option<f64>,
}

impl MotionClock {
    /// Updates the clock at time `now` (seconds) and says whether the view
    /// is moving.
    pub fn tick(&mut self, now: f64, changed: bool) -> bool {
        if changed {
            self.last_change = Some(now);
        }
        self.last_change.is_some_and(|t| now - t < REST_SECONDS)
    }
}

/// The march resolution scale for a mode, on a software GPU or not.
pub fn moving_scale(mode: MovingResolution, software_gpu: bool, moving: bool) -> f32 {
    let half = match mode {
        MovingResolution::Auto => software_gpu,
        MovingResolution::Full => false,
        MovingResolution::Half => true,
    };
    if moving && half {
        0.5
    } else {
        1.0
    }
}

/// Marches at a lower resolution while the view moves (camera, drags,
/// anything that rebuilds the scene every frame), in full once it rests.
/// A viewport resize alone is no motion: the panels around the view may
/// change size with what they show, and counting that would let the
/// resolution feed back into itself.
pub fn adaptive_resolution(
    time: Res<Time<Real>>,
    state: Res<EditorState>,
    march: Res<MarchScene>,
    adapter: Option<Res<bevy::render::renderer::RenderAdapterInfo>>,
    mut clock: Local<MotionClock>,
    mut last_pose: Local<Option<Mat4>>,
    mut cams: Query<(&GlobalTransform, &mut RayMarchCamera), With<EditorCamera>>,
) {
    let Ok((t, mut rm)) = cams.single_mut() else {
        return;
    };
    let pose = t.to_matrix();
    let changed = march.is_changed() || *last_pose != Some(pose);
    *last_pose = Some(pose);
    let software = adapter.is_some_and(|a| a.device_type == wgpu::DeviceType::Cpu);
    let moving = clock.tick(time.elapsed_secs_f64(), changed);
    let scale = moving_scale(state.moving_resolution, software, moving);
    if rm.render_scale != scale {
        rm.render_scale = scale;
    }
}

/// Enables the orbit controller only when the mouse is free for it, and
/// maps its buttons to the tool (brush: left paints, middle orbits).
pub fn gate_orbit(
    state: Res<EditorState>,
    gizmo: Res<super::state::GizmoView>,
    wants: Option<Res<EguiWantsInput>>,
    mut cams: Query<&mut PanOrbitCamera, With<EditorCamera>>,
) {
    let egui_busy = wants.is_some_and(|w| w.wants_any_pointer_input());
    for mut pan in &mut cams {
        // Over a gizmo arrow a press drags the object, not the view.
        let enabled = !egui_busy && !state.fly && state.transform.is_none() && gizmo.hovered.is_none();
        if pan.enabled != enabled {
            pan.enabled = enabled;
        }
        let orbit = match state.tool {
            Tool::Navigate => MouseButton::Left,
            Tool::Brush => MouseButton::Middle,
        };
        if pan.button_orbit != orbit {
            pan.button_orbit = orbit;
        }
    }
}

/// Fly mode: WASD / QE move, right drag looks around, Shift is faster.
pub fn fly(
    mut state: ResMut<EditorState>,
    keys: Res<ButtonInput<KeyCode>>,
    buttons: Res<ButtonInput<MouseButton>>,
    motion: Res<AccumulatedMouseMotion>,
    wants: Option<Res<EguiWantsInput>>,
    time: Res<Time>,
    mut cams: Query<(&mut Transform, &mut PanOrbitCamera), With<EditorCamera>>,
) {
    let typing = wants.as_ref().is_some_and(|w| w.wants_keyboard_input());
    if !typing && keys.just_pressed(KeyCode::KeyF) && state.transform.is_none() {
        state.fly = !state.fly;
        state.status = if state.fly {
            "fly mode: WASD/QE move, right drag looks, F leaves".into()
        } else {
            "orbit mode".into()
        };
        if !state.fly {
            for (t, mut pan) in &mut cams {
                aim_orbit(&mut pan, &t, 2.0);
            }
        }
    }
    if !state.fly || typing {
        return;
    }
    let speed = if keys.pressed(KeyCode::ShiftLeft) { 2.0 } else { 0.6 } * time.delta_secs();
    for (mut t, _) in &mut cams {
        let mut v = Vec3::ZERO;
        let pairs = [
            (KeyCode::KeyW, t.forward().as_vec3()),
            (KeyCode::KeyS, -t.forward().as_vec3()),
            (KeyCode::KeyD, t.right().as_vec3()),
            (KeyCode::KeyA, -t.right().as_vec3()),
            (KeyCode::KeyE, Vec3::Y),
            (KeyCode::KeyQ, -Vec3::Y),
        ];
        for (k, dir) in pairs {
            if keys.pressed(k) {
                v += dir;
            }
        }
        t.translation += v * speed;
        if buttons.pressed(MouseButton::Right) {
            let d = motion.delta * 0.003;
            let (mut yaw, mut pitch, _) = t.rotation.to_euler(EulerRot::YXZ);
            yaw -= d.x;
            pitch = (pitch - d.y).clamp(-1.5, 1.5);
            t.rotation = Quat::from_euler(EulerRot::YXZ, yaw, pitch, 0.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn motion_lasts_from_a_change_until_a_rest() {
        let mut c = MotionClock::default();
        assert!(!c.tick(0.0, false), "no change yet: at rest");
        assert!(c.tick(0.1, true), "a single change starts a motion");
        assert!(c.tick(0.3, false));
        assert!(!c.tick(0.41, false), "REST_SECONDS later: at rest");
        // Changes that keep coming keep it going.
        assert!(c.tick(1.0, true));
        assert!(c.tick(1.2, true));
        assert!(c.tick(1.4, true));
        assert!(c.tick(1.6, false));
        assert!(!c.tick(1.71, false));
    }

    #[test]
    fn the_view_marches_at_half_resolution_while_the_camera_keeps_moving() {
        use bevy::platform::time::Instant;
        use std::time::Duration;
        let start = Instant::now();
        let mut app = App::new();
        let state = EditorState {
            moving_resolution: MovingResolution::Half,
            ..Default::default()
        };
        app.insert_resource(state)
            .init_resource::<MarchScene>()
            .insert_resource(Time::<Real>::new(start))
            .add_systems(Update, adaptive_resolution);
        let cam = app
            .world_mut()
            .spawn((
                GlobalTransform::IDENTITY,
                Camera::default(),
                RayMarchCamera::default(),
                EditorCamera,
            ))
            .id();
        let frame = |app: &mut App, ms: u64, x: Option<f32>| -> f32 {
            app.world_mut()
                .resource_mut::<Time<Real>>()
                .update_with_instant(start + Duration::from_millis(ms));
            if let Some(x) = x {
                *app.world_mut().get_mut::<GlobalTransform>(cam).unwrap() =
                    GlobalTransform::from_translation(Vec3::X * x);
            }
            app.update();
            app.world().get::<RayMarchCamera>(cam).unwrap().render_scale
        };
        assert_eq!(frame(&mut app, 0, None), 0.5, "the first image: half");
        assert_eq!(frame(&mut app, 400, None), 1.0, "then at rest: full");
        assert_eq!(frame(&mut app, 500, Some(0.1)), 0.5, "moving: half");
        assert_eq!(frame(&mut app, 600, Some(0.2)), 0.5);
        assert_eq!(frame(&mut app, 700, None), 0.5, "just stopped");
        assert_eq!(frame(&mut app, 850, None), 0.5);
        assert_eq!(frame(&mut app, 950, None), 1.0, "at rest: full again");
    }

    #[test]
    fn half_resolution_only_while_moving_and_where_the_mode_wants_it() {
        use MovingResolution::*;
        assert_eq!(moving_scale(Auto, true, true), 0.5);
        assert_eq!(moving_scale(Auto, false, true), 1.0);
        assert_eq!(moving_scale(Auto, true, false), 1.0);
        assert_eq!(moving_scale(Half, false, true), 0.5);
        assert_eq!(moving_scale(Full, true, true), 1.0);
    }

    #[test]
    fn orbit_angles_reproduce_the_eye() {
        let focus = Vec3::new(0.1, -0.3, 0.2);
        let eye = Vec3::new(1.0, 0.8, -2.0);
        let (yaw, pitch, r) = orbit_of(eye, focus);
        let rot = Quat::from_rotation_y(yaw) * Quat::from_rotation_x(-pitch);
        let back = focus + rot * Vec3::new(0.0, 0.0, r);
        assert!((back - eye).length() < 1e-4, "{back} vs {eye}");
    }
}
