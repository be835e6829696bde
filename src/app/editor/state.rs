//! Editor resources and messages: tool settings, segmentation parameters,
//! status and errors shown in the UI, and the strokes the brush produces.

use crate::app::layers::OverlayMode;
use crate::camera::Camera;
use crate::segment::{Polarity, SegmentParams, Timings};
use bevy::prelude::*;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Tool {
    /// Orbit / pan / zoom with the mouse.
    #[default]
    Navigate,
    /// Left drag paints a stroke (Ctrl or the toggle: negative).
    Brush,
}

/// How the view marches while it moves (camera, drags): fewer pixels keep
/// a slow (software) GPU interactive; a still view is always drawn in full.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum MovingResolution {
    /// Half resolution on software GPUs (lavapipe), full on real ones.
    #[default]
    Auto,
    Full,
    Half,
}

/// Keyboard transform modes (Blender-like G / R / S).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TransformMode {
    Move,
    Rotate,
    Scale,
}

/// A transform drag in progress on the selected object.
#[derive(Clone, Copy, Debug)]
pub struct TransformDrag {
    pub mode: TransformMode,
    pub entity: Entity,
    /// The object's transform when the drag began (Esc restores it).
    pub start: Transform,
    /// Cursor position (logical) when the drag began.
    pub cursor0: Vec2,
    /// Moves only along this world axis, an index into `Vec3::AXES` (a
    /// gizmo arrow, or X / Y / Z typed during G).
    pub axis: Option<usize>,
    /// Started by pressing a gizmo arrow: releasing the button confirms.
    pub gizmo: bool,
}

/// One handle of the gizmo: a move arrow or a rotation ring of a world
/// axis (index into `Vec3::AXES`), or the uniform scale circle (no axis).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Handle {
    pub mode: TransformMode,
    pub axis: Option<usize>,
}

/// The transform gizmo of the selected object in window coordinates
/// (logical pixels), recomputed every frame; drawn by the UI, picked by
/// [`super::tools::transform_modes`].
#[derive(Resource, Default, Clone, Debug)]
pub struct GizmoView {
    pub center: Option<Vec2>,
    /// Arrow tips of the world X, Y, Z axes (`None`: the axis points at the
    /// camera and cannot be dragged).
    pub tips: [Option<Vec2>; 3],
    /// Rotation rings about X, Y, Z as closed screen polylines (empty where
    /// the ring is edge-on and cannot be dragged).
    pub rings: [Vec<Vec2>; 3],
    /// The handle under the cursor.
    pub hovered: Option<Handle>,
    /// The handle being dragged.
    pub active: Option<Handle>,
    /// The 3D view's rectangle: the gizmo is clipped to it.
    pub clip: Option<Rect>,
}

#[derive(Resource)]
pub struct EditorState {
    pub tool: Tool,
    /// Brush half-size in pixels (the authors' 7×7 brush is 3).
    pub brush_radius: u32,
    /// Paint negative strokes (also while Ctrl is held).
    pub negative: bool,
    pub params: SegmentParams,
    /// Re-segment the selected object when a slider changes.
    pub live: bool,
    pub overlay: OverlayMode,
    pub fly: bool,
    /// Sample step multiplier (1 = the reference step; larger is faster).
    pub step_scale: f32,
    pub moving_resolution: MovingResolution,
    pub background: [f32; 3],
    pub transform: Option<TransformDrag>,
    /// One-line status (bottom bar).
    pub status: String,
    /// Errors not yet dismissed, newest last.
    pub errors: Vec<String>,
    pub last_timings: Option<Timings>,
    /// Views of the capture (snap targets).
    pub capture_cameras: Vec<(String, Camera)>,
    /// The NDC space the scene lives in when the session's first field
    /// comes from a forward-facing capture (LLFF): the view maps its rays
    /// there, as the capture's cameras did in training.
    pub ndc: Option<crate::camera::Ndc>,
    /// Path typed in the file menu.
    pub path_input: String,
    /// Select this object once the session has it (after a stroke made it).
    pub pending_select: Option<String>,
    /// Name being edited in the selection panel.
    pub rename: Option<(Entity, String)>,
}

impl Default for EditorState {
    fn default() -> Self {
        EditorState {
            tool: Tool::Navigate,
            brush_radius: 3,
            negative: false,
            params: SegmentParams::default(),
            live: false,
            overlay: OverlayMode {
                tint_selected: true,
                dim_others: false,
            },
            fly: false,
            step_scale: 1.0,
            moving_resolution: MovingResolution::Auto,
            background: [1.0; 3],
            transform: None,
            status: "ready".into(),
            errors: Vec::new(),
            last_timings: None,
            capture_cameras: Vec::new(),
            ndc: None,
            path_input: String::new(),
            pending_select: None,
            rename: None,
        }
    }
}

impl EditorState {
    pub fn error(&mut self, e: impl std::fmt::Display) {
        let msg = e.to_string();
        bevy::log::error!("{msg}");
        self.errors.push(msg);
        if self.errors.len() > 8 {
            self.errors.remove(0);
        }
    }
}

/// A finished brush stroke on the current view.
#[derive(Message, Clone, Debug)]
pub struct StrokeMsg {
    pub camera: Camera,
    /// Continuous pixel coordinates of the view.
    pub points: Vec<glam::Vec2>,
    pub radius: u32,
    pub polarity: Polarity,
}

/// The stroke being painted (drawn over the view by the UI).
#[derive(Resource, Default)]
pub struct CurrentStroke {
    /// Logical window coordinates, for drawing.
    pub screen: Vec<Vec2>,
    /// Physical pixel coordinates relative to the view, for segmenting.
    pub pixels: Vec<glam::Vec2>,
    pub negative: bool,
}
