//! `--screenshot OUT.png`: wait until pipelines are compiled, the grids are
//! uploaded, queued segmentation is done and the current scene has been
//! drawn, then save the window and exit (0 on success).

use super::session::EditorSession;
use super::state::EditorState;
use crate::app::gpu::{MarchScene, SharedStatus};
use bevy::prelude::*;
use bevy::render::view::screenshot::{Screenshot, ScreenshotCaptured};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Frames to wait after the scene is drawn, so the UI has settled.
const SETTLE_FRAMES: u32 = 5;
/// Give up (exit 1) after this long.
const TIMEOUT_S: f32 = 300.0;

pub struct ScreenshotPlugin {
    pub path: PathBuf,
}

/// Anything else that must finish before the screenshot (e.g. a start-up
/// script); systems set `pending` while they work.
#[derive(Resource, Default)]
pub struct ScreenshotGate {
    pub pending: bool,
}

#[derive(Resource)]
struct ShotState {
    path: PathBuf,
    settled: u32,
    requested: bool,
    started: Instant,
    result: Arc<Mutex<Option<Result<(), String>>>>,
}

impl Plugin for ScreenshotPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<ScreenshotGate>()
            .insert_resource(ShotState {
                path: self.path.clone(),
                settled: 0,
                requested: false,
                started: Instant::now(),
                result: Arc::default(),
            })
            .add_systems(Last, screenshot_when_ready);
    }
}

/// Whether the current scene has been drawn by the GPU pass, at full
/// resolution (a moving view marches at less; it rests before a screenshot).
pub fn scene_drawn(march: &MarchScene, status: &SharedStatus) -> bool {
    let s = status.get();
    march
        .scene
        .as_ref()
        .is_some_and(|sc| s.frames_drawn > 0 && s.full_resolution && s.scene_drawn == Arc::as_ptr(sc) as usize)
}

#[allow(clippy::too_many_arguments)]
fn screenshot_when_ready(
    mut commands: Commands,
    mut shot: ResMut<ShotState>,
    gate: Res<ScreenshotGate>,
    es: Res<EditorSession>,
    state: Res<EditorState>,
    march: Res<MarchScene>,
    status: Res<SharedStatus>,
    mut exit: MessageWriter<AppExit>,
) {
    if let Some(r) = shot.result.lock().ok().and_then(|mut r| r.take()) {
        match r {
            Ok(()) => {
                info!("screenshot saved to {}", shot.path.display());
                exit.write(AppExit::Success);
            }
            Err(e) => {
                error!("{e}");
                exit.write(AppExit::error());
            }
        }
        return;
    }
    if shot.started.elapsed().as_secs_f32() > TIMEOUT_S {
        let err = status.get().error.unwrap_or_else(|| "nothing was drawn".into());
        error!("screenshot: timed out after {TIMEOUT_S} s ({err})");
        exit.write(AppExit::error());
        return;
    }
    if shot.requested {
        return;
    }
    if let Some(e) = status.get().error {
        error!("screenshot: the GPU view failed: {e}");
        exit.write(AppExit::error());
        return;
    }
    // A start-up request failed (a missing file, a bad script step): the
    // screenshot would not show what was asked for.
    if !es.busy() && !state.errors.is_empty() {
        error!(
            "screenshot: not taken, the editor reported: {}",
            state.errors.join("; ")
        );
        exit.write(AppExit::error());
        return;
    }
    let ready = !gate.pending && !es.busy() && scene_drawn(&march, &status);
    shot.settled = if ready { shot.settled + 1 } else { 0 };
    if shot.settled < SETTLE_FRAMES {
        return;
    }
    shot.requested = true;
    let path = shot.path.clone();
    let result = shot.result.clone();
    commands
        .spawn(Screenshot::primary_window())
        .observe(move |captured: On<ScreenshotCaptured>| {
            let r = save(&captured.image, &path);
            if let Ok(mut slot) = result.lock() {
                *slot = Some(r);
            }
        });
}

fn save(image: &Image, path: &std::path::Path) -> Result<(), String> {
    let img = image
        .clone()
        .try_into_dynamic()
        .map_err(|e| format!("screenshot has an unexpected format: {e}"))?
        .to_rgb8();
    let mut bytes = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .map_err(|e| format!("encoding the screenshot: {e}"))?;
    crate::error::write_atomic(path, &bytes).map_err(|e| e.to_string())
}
