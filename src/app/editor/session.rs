//! The editor's bridge to the library's [`Session`]: every user action is a
//! [`Command`] (or undo / redo) queued here and applied one at a time on
//! bevy's async compute pool, so strokes, growth, loading and exports never
//! block the frame loop. The session moves into the task and back; the
//! panels show the last finished state meanwhile. After each change the
//! entities are re-synced from the session's state ([`sync_entities`]).
//!
//! Survival: a command that fails or panics leaves the last good state
//! (reported in the status line and the error list); with a [`Recorder`],
//! the edit log goes to a recovery file after every request, inside the
//! task (checksumming a newly named field file stays off the frame loop).

use super::state::EditorState;
use crate::app::convert::bevy_transform;
use crate::app::layers::{FieldLayer, ObjectLayer, SessionName};
use crate::command::composition;
use crate::command::recovery::{self, Recorder, RecoveryDoc};
use crate::command::state::State;
use crate::command::{output, Command, Session, StepOutput};
use crate::util::{Progress, ProgressState};
use crate::Result;
use bevy::prelude::*;
use bevy::tasks::{futures::check_ready, AsyncComputeTaskPool, Task};
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// One queued request.
// A handful are queued at a time: boxing the large `Command` buys nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
pub enum Request {
    Apply(Command),
    Undo,
    Redo,
    /// Replace the session by a composition file.
    Open(PathBuf),
    /// Replace the session by replaying a recovery file.
    Restore(Box<RecoveryDoc>),
    /// Import a 3D Gaussian splat `.ply` (off the UI thread: millions of
    /// Gaussians take seconds) and load the field it makes.
    ImportSplats(PathBuf),
}

impl Request {
    fn label(&self) -> String {
        match self {
            Request::Apply(c) => c.kind().replace('_', " "),
            Request::Undo => "undo".into(),
            Request::Redo => "redo".into(),
            Request::Open(p) => format!("opening {}", p.display()),
            Request::Restore(d) => format!("restoring {} edits", d.commands.len()),
            Request::ImportSplats(p) => format!("importing {}", p.display()),
        }
    }
}

/// What a finished request hands back: the session (the last good one if
/// the request failed), the recorder, the result, and problems that did
/// not stop the request (a recovery file that could not be written, a
/// restore that differs from the recorded state).
struct Outcome {
    session: Session,
    recorder: Option<Recorder>,
    result: Result<StepOutput>,
    warnings: Vec<String>,
}

struct Running {
    label: String,
    started: Instant,
    request: Request,
    task: Task<Outcome>,
}

#[derive(Resource)]
pub struct EditorSession {
    /// `None` while a request runs (the task owns it).
    session: Option<Session>,
    /// The latest finished state (what the entities mirror); changed only
    /// by requests the session ran ([`EditorSession::state`] reads it).
    state: State,
    /// Bumped whenever `state` changes.
    pub version: u64,
    queue: VecDeque<Request>,
    running: Option<Running>,
    pub can_undo: bool,
    pub can_redo: bool,
    /// Requests finished so far.
    pub finished: u64,
    /// Command log of the session (for "save script").
    pub log_len: usize,
    /// The session's progress handle (kept across `Open`).
    progress: Progress,
    /// Writes the recovery file after each request (`None` while a request
    /// runs, or when the editor records nothing).
    recorder: Option<Recorder>,
    /// The recorder's file (also while a task holds the recorder).
    recovery_path: Option<PathBuf>,
    /// A recovery file of an earlier session with the same inputs, offered
    /// for restoring until the user decides. Nothing is recorded meanwhile,
    /// so that the offered file stays where it is should this session die
    /// too.
    pub offer: Option<Box<RecoveryDoc>>,
}

impl EditorSession {
    pub fn new(session: Session) -> Self {
        EditorSession {
            progress: session.progress.clone(),
            state: session.state().clone(),
            session: Some(session),
            version: 1,
            queue: VecDeque::new(),
            running: None,
            can_undo: false,
            can_redo: false,
            finished: 0,
            log_len: 0,
            recorder: None,
            recovery_path: None,
            offer: None,
        }
    }
    /// Records the edit log with `recorder` after every request.
    pub fn with_recorder(mut self, recorder: Recorder) -> Self {
        self.recovery_path = Some(recorder.path.clone());
        self.recorder = Some(recorder);
        self
    }
    /// The recovery file being written, if any.
    pub fn recovery_path(&self) -> Option<&Path> {
        self.recovery_path.as_deref()
    }
    /// Declines the offered recovery: its file is moved aside to
    /// `<name>.previous.json` (not offered again, not lost), and recording
    /// starts with the next request.
    pub fn decline_offer(&mut self) -> Result<()> {
        if self.offer.take().is_none() {
            return Ok(());
        }
        let Some(path) = &self.recovery_path else {
            return Ok(());
        };
        let prev = Recorder::previous_of(path);
        match std::fs::rename(path, &prev) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(crate::Error::io(&prev, e)),
            _ => Ok(()),
        }
    }
    /// Accepts the offered recovery: requests not yet started (the
    /// start-up's) are dropped, and the session is replaced by the replay.
    pub fn accept_offer(&mut self) {
        if let Some(doc) = self.offer.take() {
            self.queue.clear();
            self.push(Request::Restore(doc));
        }
    }
    pub fn push(&mut self, r: Request) {
        self.queue.push_back(r);
    }
    pub fn apply(&mut self, c: impl Into<Command>) {
        self.push(Request::Apply(c.into()));
    }
    pub fn busy(&self) -> bool {
        self.running.is_some() || !self.queue.is_empty()
    }
    /// The running request: its label, seconds so far, and what the
    /// command reported of its progress.
    pub fn progress(&self) -> Option<(String, f32, Option<ProgressState>)> {
        self.running
            .as_ref()
            .map(|r| (r.label.clone(), r.started.elapsed().as_secs_f32(), self.progress.get()))
    }
    /// The latest finished state (what the entities mirror).
    pub fn state(&self) -> &State {
        &self.state
    }
    /// The session, when no request holds it.
    pub fn session(&self) -> Option<&Session> {
        self.session.as_ref()
    }
    /// A name not used by any field or object, from `base`.
    pub fn fresh_name(&self, base: &str) -> String {
        fresh_name(&self.state, base)
    }
}

/// `base`, or `base 2`, `base 3`, … : the first name `st` does not use.
pub(super) fn fresh_name(st: &State, base: &str) -> String {
    let used = |n: &str| st.name_used(n);
    if !used(base) {
        return base.to_string();
    }
    (2..).map(|i| format!("{base} {i}")).find(|n| !used(n)).unwrap()
}

/// Applies one request, then records the edit log.
fn run(session: Session, mut recorder: Option<Recorder>, r: Request) -> Outcome {
    let mut warnings = Vec::new();
    let (session, result) = apply_request(session, recorder.as_mut(), &r, &mut warnings);
    if let Some(rec) = recorder.as_mut() {
        if let Err(e) = rec.record(&session) {
            warnings.push(format!("the recovery file could not be written: {e}"));
        }
    }
    Outcome {
        session,
        recorder,
        result,
        warnings,
    }
}

/// Applies one request. A panic inside it (a bug, never the user's fault)
/// becomes an error: `Session::apply` builds the next state aside and
/// swaps it in only on success, so the session is the last good one.
fn apply_request(
    mut session: Session,
    recorder: Option<&mut Recorder>,
    r: &Request,
    warnings: &mut Vec<String>,
) -> (Session, Result<StepOutput>) {
    let progress = session.progress.clone();
    let result = crate::error::catch_panic(r.label().as_str(), || match r {
        Request::Apply(c) => output::perform(&mut session, c, None),
        Request::Undo => Ok(StepOutput {
            message: session
                .undo()
                .map_or("nothing to undo".into(), |c| format!("undid {}", c.kind())),
            ..Default::default()
        }),
        Request::Redo => Ok(StepOutput {
            message: session
                .redo()
                .map_or("nothing to redo".into(), |c| format!("redid {}", c.kind())),
            ..Default::default()
        }),
        Request::Open(p) => {
            let mut s = composition::load(p, &session.out_dir)?.with_undo_limit(session.undo_limit());
            s.progress = progress.clone();
            session = s;
            Ok(StepOutput {
                message: format!("opened {}", p.display()),
                ..Default::default()
            })
        }
        Request::ImportSplats(ply) => super::splats::import(&mut session, ply),
        Request::Restore(doc) => {
            let (s, report) = recovery::restore(doc, &progress)?;
            session = s.with_undo_limit(session.undo_limit());
            if !report.identical {
                warnings.push(report.message());
            }
            Ok(StepOutput {
                message: report.message(),
                ..Default::default()
            })
        }
    });
    if result.is_ok() {
        if let Some(rec) = recorder {
            match r {
                Request::Open(p) => {
                    if let Err(e) = rec.opened(p, &session) {
                        warnings.push(format!("the recovery copy of {} could not be saved: {e}", p.display()));
                    }
                }
                Request::Restore(doc) => rec.restored(doc),
                _ => {}
            }
        }
    }
    // The GPU view draws VM fields through an SH bake: make it here, off the
    // frame loop, rather than in the render world's upload.
    for f in &session.state().fields {
        if let Err(e) = f.field.sh_baked() {
            return (session, Err(e));
        }
    }
    (session, result)
}

/// Collects the finished request and starts the next one.
pub fn run_requests(mut es: ResMut<EditorSession>, mut state: ResMut<EditorState>) {
    if let Some(running) = es.running.as_mut() {
        let Some(Outcome {
            session,
            recorder,
            result,
            warnings,
        }) = check_ready(&mut running.task)
        else {
            return;
        };
        let running = es.running.take().unwrap();
        es.finished += 1;
        match result {
            Ok(out) => {
                if let Request::Restore(_) = &running.request {
                    // Scripted restores (`--restore --screenshot`) read it in the log.
                    info!("{}", out.message);
                }
                if let Some(t) = out.timings {
                    state.last_timings = Some(t);
                }
                state.status = if out.message.is_empty() {
                    format!("{} done", running.label)
                } else {
                    out.message
                };
                if !out.files.is_empty() {
                    state.status += &format!(" ({} file(s) written)", out.files.len());
                }
            }
            Err(e) => {
                state.status = format!("{} failed", running.label);
                state.error(e);
            }
        }
        for w in warnings {
            state.error(w);
        }
        es.recorder = recorder;
        es.can_undo = session.can_undo();
        es.can_redo = session.can_redo();
        es.log_len = session.log().len();
        es.state = session.state().clone();
        es.version += 1;
        es.session = Some(session);
    }
    let Some(request) = es.queue.pop_front() else {
        return;
    };
    let session = es.session.take().expect("no request runs, so the session is here");
    // While a recovery is offered nothing is recorded (see `offer`).
    let recorder = if es.offer.is_some() { None } else { es.recorder.take() };
    let label = request.label();
    let r = request.clone();
    let task = AsyncComputeTaskPool::get().spawn(async move { run(session, recorder, r) });
    state.bypass_change_detection().status = format!("{label}…");
    es.running = Some(Running {
        label,
        started: Instant::now(),
        request,
        task,
    });
}

/// Mirrors the session's fields and objects as entities (matched by id),
/// spawning, updating and despawning as needed; collects capture views.
pub fn sync_entities(
    mut commands: Commands,
    es: Res<EditorSession>,
    mut seen: Local<u64>,
    mut state: ResMut<EditorState>,
    mut fields: FieldEntities,
    mut objects: ObjectEntities,
) {
    if *seen == es.version {
        return;
    }
    *seen = es.version;
    let st = es.state();
    let mut keep = Vec::new();
    for f in &st.fields {
        let layer = FieldLayer {
            id: f.id,
            field: f.field.clone(),
            placement: f.placement,
        };
        let t = bevy_transform(&f.placement.transform);
        let e = match fields.iter_mut().find(|(_, _, l, _)| l.id == f.id) {
            Some((e, mut n, mut fl, mut ft)) => {
                relabel(&mut commands, e, &mut n, &f.name);
                if !std::sync::Arc::ptr_eq(&fl.field, &layer.field) || fl.placement != layer.placement {
                    *fl = layer;
                }
                if *ft != t {
                    *ft = t;
                }
                e
            }
            None => {
                let views = capture_views(f);
                if st.fields.first().is_some_and(|first| first.id == f.id) {
                    state.ndc = f.field.ndc.or_else(|| views.first().and_then(|(_, c)| c.ndc));
                }
                state.capture_cameras.extend(views);
                spawn_named(&mut commands, &f.name, (layer, t))
            }
        };
        keep.push(e);
    }
    for o in &st.objects {
        let Some(fe) = st.fields.iter().position(|f| f.id == o.field).map(|i| keep[i]) else {
            continue;
        };
        let layer = ObjectLayer {
            id: o.id,
            field: fe,
            bitmap: o.mask.clone(),
            placement: o.placement,
        };
        let t = bevy_transform(&o.placement.transform);
        let e = match objects.iter_mut().find(|(_, _, l, _)| l.id == o.id) {
            Some((e, mut n, mut ol, mut ot)) => {
                relabel(&mut commands, e, &mut n, &o.name);
                *ol = layer;
                if *ot != t {
                    *ot = t;
                }
                e
            }
            None => spawn_named(&mut commands, &o.name, (layer, t)),
        };
        keep.push(e);
    }
    let stale = fields.iter().map(|f| f.0).chain(objects.iter().map(|o| o.0));
    for e in stale.filter(|e| !keep.contains(e)).collect::<Vec<_>>() {
        commands.entity(e).despawn();
    }
    // Parameters follow the session (undo of SetParams included).
    if state.params != st.params {
        state.params = st.params;
    }
    if state.background != st.background {
        state.background = st.background;
    }
}

type FieldEntities<'w, 's> = Query<
    'w,
    's,
    (
        Entity,
        &'static mut SessionName,
        &'static mut FieldLayer,
        &'static mut Transform,
    ),
    Without<ObjectLayer>,
>;
type ObjectEntities<'w, 's> = Query<
    'w,
    's,
    (
        Entity,
        &'static mut SessionName,
        &'static mut ObjectLayer,
        &'static mut Transform,
    ),
    Without<FieldLayer>,
>;

fn spawn_named(commands: &mut Commands, name: &str, bundle: impl Bundle) -> Entity {
    commands
        .spawn((Name::new(name.to_string()), SessionName(name.to_string()), bundle))
        .id()
}

/// A rename changes the labels only: the entity (and the selection) stays.
fn relabel(commands: &mut Commands, e: Entity, n: &mut Mut<SessionName>, name: &str) {
    if n.0 != name {
        n.0 = name.to_string();
        commands.entity(e).insert(Name::new(name.to_string()));
    }
}

/// The views of the capture a field comes from, placed with the field: a
/// demo's stroke view and orbit; for a file, `isrf train`'s
/// `<stem>.cameras.json`, else a transforms.json beside the file.
/// Forward-facing captures' cameras keep their NDC (the view then maps its
/// rays into it, [`super::state::EditorState::ndc`]); their poses are in
/// the world, not in the NDC space the field's placement moves, so they
/// stay where the capture put them.
fn capture_views(f: &crate::command::state::FieldEntry) -> Vec<(String, crate::camera::Camera)> {
    let views: Vec<(String, crate::camera::Camera)> = if let Some(d) = &f.demo {
        std::iter::once(("stroke view".to_string(), d.stroke_camera))
            .chain(d.cameras.frames.iter().map(|c| (c.name.clone(), c.camera)))
            .collect()
    } else if let crate::command::FieldSource::File(p) = &f.source {
        crate::camera::set::capture_cameras(p)
            .map(|set| set.frames)
            .into_iter()
            .flatten()
            .map(|c| (c.name, c.camera))
            .collect()
    } else {
        vec![]
    };
    // An NDC field without its capture's cameras (an exported object) is
    // seen from the NDC's reference view.
    let views = match (views.is_empty(), f.field.ndc) {
        (true, Some(n)) => vec![("reference view".to_string(), n.reference_camera())],
        _ => views,
    };
    views
        .into_iter()
        .map(|(n, mut c)| {
            if c.ndc.is_none() {
                c.c2w = f.placement.transform * c.c2w;
            }
            (format!("{}: {n}", f.name), c)
        })
        .collect()
}
