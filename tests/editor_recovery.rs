//! The editor survives and recovers (issue 18, parts 4 and 5).
//!
//! - Model side, no window or GPU: a failing command and a corrupt file in
//!   File → Open leave the last good state and are reported; the recovery
//!   file follows every command; an opened composition is replayed from it.
//! - Under `xvfb-run` on a software Vulkan driver: the editor, applying a
//!   script of edits, is killed with SIGKILL at a different point each run;
//!   `isrf edit --restore` then replays its recovery file and must reach the
//!   identical state (the editor checks the state digest and exits 1
//!   otherwise; the library replay is checked here too). Runs:
//!   `ISRF_KILL_RESTORE_RUNS` (default 3; the issue's figure is 10 of 10),
//!   binary `ISRF_BIN` (default this build's).
//!   Also: with a broken ray-march shader the editor keeps running and
//!   applying commands. Skips without xvfb-run or a Vulkan adapter.
#![cfg(feature = "editor")]

use bevy::prelude::*;
use isrf::app::editor::session::{EditorSession, Request};
use isrf::app::editor::state::EditorState;
use isrf::app::editor::EditorCorePlugin;
use isrf::command::recovery::{restore, state_digest, Inputs, Recorder, RecoveryDoc, StartStep};
use isrf::command::{Edit, Export, Output, Session, TransformSpec};
use isrf::util::Progress;
use std::path::{Path, PathBuf};
use std::process::Command as Process;
use std::time::{Duration, Instant};

mod common;
use common::settle;
use common::{demo_stroke as stroke, load_demo, DEMO_RES as RES};

fn app_with(es: EditorSession) -> App {
    let mut app = App::new();
    app.add_plugins(MinimalPlugins)
        .insert_resource(es)
        .add_plugins(EditorCorePlugin);
    settle(&mut app);
    app
}

fn push(app: &mut App, r: Request) {
    app.world_mut().resource_mut::<EditorSession>().push(r);
    settle(app);
}

fn errors(app: &App) -> Vec<String> {
    app.world().resource::<EditorState>().errors.clone()
}

#[test]
fn failures_keep_the_last_good_state_and_the_recovery_file_follows_every_command() {
    let dir = tempfile::tempdir().unwrap();
    let rec_path = dir.path().join("rec.json");
    let inputs = Inputs {
        cwd: dir.path().into(),
        start: vec![StartStep::Apply(load_demo().into())],
    };
    let mut es =
        EditorSession::new(Session::new(dir.path(), dir.path())).with_recorder(Recorder::new(rec_path.clone(), inputs));
    es.apply(load_demo());
    es.apply(stroke("mug"));
    let mut app = app_with(es);
    let recorded = |app: &App| {
        let doc = RecoveryDoc::load(&rec_path).unwrap();
        let es = app.world().resource::<EditorSession>();
        assert_eq!(
            doc.state,
            state_digest(es.state()),
            "the recovery file lags the session"
        );
        doc
    };
    let good = recorded(&app);
    assert_eq!(good.commands, vec![load_demo(), stroke("mug")]);

    // A failing command: reported, state and recovery file unchanged.
    push(&mut app, Request::Apply(Edit::Remove { object: "nope".into() }.into()));
    assert!(errors(&app).iter().any(|e| e.contains("nope")), "{:?}", errors(&app));
    assert_eq!(recorded(&app).state, good.state);

    // Corrupt and missing files in File → Open: the same.
    let corrupt = dir.path().join("corrupt.ron");
    std::fs::write(&corrupt, "(format: \"isrf-composition\", version: 1, bitm").unwrap();
    let missing_sidecar = dir.path().join("missing.json");
    std::fs::write(
        &missing_sidecar,
        r#"{"format":"isrf-composition","version":1,"bitmaps":"gone.safetensors","background":[1,1,1],"params":{},"fields":[],"objects":[]}"#,
    )
    .unwrap();
    for (bad, what) in [
        (corrupt.clone(), "corrupt.ron"),
        (missing_sidecar, "gone.safetensors"),
        (dir.path().join("absent.json"), "absent.json"),
    ] {
        let n = errors(&app).len();
        push(&mut app, Request::Open(bad));
        let errs = errors(&app);
        assert!(
            errs.len() > n && errs.last().unwrap().contains(what),
            "opening a bad file: {errs:?}"
        );
        let es = app.world().resource::<EditorSession>();
        assert_eq!(es.state().fields.len(), 1);
        assert_eq!(es.state().objects.len(), 1);
        assert_eq!(recorded(&app).state, good.state);
    }

    // A good composition opens; the recovery file names it, and the edits
    // after it replay from it.
    let comp = dir.path().join("scene.json");
    push(
        &mut app,
        Request::Apply(Output::Export(Export::Composition { out: comp.clone() }).into()),
    );
    push(&mut app, Request::Open(comp.clone()));
    push(
        &mut app,
        Request::Apply(
            Edit::Transform {
                object: "mug".into(),
                transform: TransformSpec::translation(glam::Vec3::new(0.2, 0.0, 0.1)),
            }
            .into(),
        ),
    );
    // The user saves over the composition the session was opened from:
    // the replay opens the copy taken when it was opened, not the new file.
    push(
        &mut app,
        Request::Apply(Output::Export(Export::Composition { out: comp.clone() }).into()),
    );
    let doc = recorded(&app);
    assert_eq!(doc.opened.as_deref(), Some(comp.as_path()));
    let copy = doc.opened_copy.clone().expect("a copy of the opened composition");
    assert_eq!(doc.commands.len(), 1);
    assert!(doc.files.iter().any(|f| f.path == copy));
    let (s, report) = restore(&doc, &Progress::default()).unwrap();
    assert!(report.identical, "{}", report.message());
    assert_eq!(s.state().objects.len(), 1);

    // And the editor's own Restore request reaches that state.
    push(&mut app, Request::Undo);
    assert_ne!(recorded(&app).state, doc.state);
    push(&mut app, Request::Restore(Box::new(doc.clone())));
    assert_eq!(recorded(&app).state, doc.state);
    assert_eq!(
        app.world().resource::<EditorState>().status,
        "restored 1 edits: the state is identical to the recorded one"
    );
}

/// The start-up's decision: replay (`--restore`), offer, or start fresh.
#[test]
fn a_recovery_file_is_offered_restored_or_set_aside_as_asked() {
    use isrf::app::editor::{recovery_plan, EditorOptions};
    let dir = tempfile::tempdir().unwrap();
    let opts = |restore: Option<bool>, screenshot: bool| EditorOptions {
        restore,
        screenshot: screenshot.then(|| dir.path().join("shot.png")),
        recovery_dir: Some(dir.path().join("rec")),
        ..Default::default()
    };
    let start = vec![Request::Apply(load_demo().into())];
    // Nothing recorded yet: a recorder, nothing to offer.
    let plan = recovery_plan(&opts(None, false), dir.path(), &start);
    assert!(plan.offer.is_none() && plan.restore.is_none() && plan.notes.is_empty());
    let mut rec = plan.recorder.expect("interactive sessions record");
    // Screenshot runs record nothing.
    assert!(recovery_plan(&opts(None, true), dir.path(), &start).recorder.is_none());
    // A killed session that only got through the start-up: not offered.
    let mut s = Session::new(dir.path(), dir.path());
    s.apply(&load_demo()).unwrap();
    rec.record(&s).unwrap();
    assert!(recovery_plan(&opts(None, false), dir.path(), &start).offer.is_none());
    // One with the user's edits: offered (interactive only), or replayed.
    s.apply(&stroke("mug")).unwrap();
    rec.record(&s).unwrap();
    let offered = recovery_plan(&opts(None, false), dir.path(), &start).offer.unwrap();
    assert_eq!(offered.commands.len(), 2);
    assert!(recovery_plan(&opts(None, true), dir.path(), &start).offer.is_none());
    assert!(recovery_plan(&opts(Some(false), false), dir.path(), &start)
        .offer
        .is_none());
    let plan = recovery_plan(&opts(Some(true), true), dir.path(), &start);
    assert_eq!(plan.restore.as_ref(), Some(&offered));
    // Other inputs have their own file.
    let other = vec![Request::Apply(stroke("pot").into())];
    assert!(recovery_plan(&opts(None, false), dir.path(), &other).offer.is_none());
    let plan = recovery_plan(&opts(Some(true), false), dir.path(), &other);
    assert!(
        plan.restore.is_none() && plan.notes[0].contains("nothing to restore"),
        "{:?}",
        plan.notes
    );

    // Accepting drops the queued start-up and replays the file.
    let mut es = EditorSession::new(Session::new(dir.path(), dir.path()))
        .with_recorder(recovery_plan(&opts(None, false), dir.path(), &start).recorder.unwrap());
    es.offer = Some(Box::new(offered.clone()));
    es.push(Request::Apply(load_demo().into()));
    es.accept_offer();
    let app = app_with(es);
    let es = app.world().resource::<EditorSession>();
    assert_eq!(state_digest(es.state()), offered.state);
    assert_eq!(es.state().objects.len(), 1);

    // Declining moves the file aside: kept, not offered again.
    let path = rec.path.clone();
    let mut es = EditorSession::new(Session::new(dir.path(), dir.path())).with_recorder(rec);
    es.offer = Some(Box::new(offered.clone()));
    es.decline_offer().unwrap();
    assert!(!path.exists());
    let kept = RecoveryDoc::load(&Recorder::previous_of(&path)).unwrap();
    assert_eq!(
        (kept.commands, kept.state),
        (offered.commands.clone(), offered.state.clone())
    );
    assert!(recovery_plan(&opts(None, false), dir.path(), &start).offer.is_none());
    // A corrupt file is reported, not offered.
    std::fs::write(&path, "{").unwrap();
    let plan = recovery_plan(&opts(None, false), dir.path(), &start);
    assert!(
        plan.offer.is_none() && plan.notes[0].contains("unreadable"),
        "{:?}",
        plan.notes
    );
}

// ------------------------------------------------------------ under Xvfb

fn have(cmd: &str) -> bool {
    Process::new("sh")
        .arg("-c")
        .arg(format!("command -v {cmd}"))
        .output()
        .is_ok_and(|o| o.status.success())
}

fn skip() -> bool {
    if !have("xvfb-run") {
        eprintln!("skipping: xvfb-run is not installed (Debian package xvfb)");
        return true;
    }
    if !isrf::app::headless::gpu_available() {
        eprintln!("skipping: no Vulkan adapter (Debian package mesa-vulkan-drivers, WGPU_BACKEND=vulkan)");
        return true;
    }
    false
}

/// The edits the killed sessions apply (after the demo's load).
const SCRIPT: &str = r#"[
    stroke(object: "mug", source: demo(object: "mug")),
    transform(object: "mug", transform: (translate: (0.3, 0.0, 0.2))),
    appearance(object: "mug", edit: (hue: 120.0)),
    stroke(object: "pot", source: demo(object: "pot")),
    duplicate(object: "pot", name: "pot 2", transform: (translate: (-0.3, 0.0, 0.0))),
    grow(object: "pot 2", steps: steps(1)),
    stroke(object: "ball", source: demo(object: "ball")),
    remove(object: "ball"),
    set_visible(target: "box", visible: false),
]"#;
const SCRIPT_EDITS: usize = 8;

/// The binary under test: `ISRF_BIN` (e.g. the release build, for the
/// long run), else this build's.
fn isrf_bin() -> PathBuf {
    std::env::var_os("ISRF_BIN").map_or_else(|| env!("CARGO_BIN_EXE_isrf").into(), PathBuf::from)
}

/// `isrf edit` under xvfb-run in `dir` with `args`; its PID is written to
/// `dir/pid` (the shell `exec`s the editor, keeping its PID).
fn editor(dir: &Path, args: &[&str]) -> Process {
    let mut cmd = Process::new("xvfb-run");
    cmd.args([
        "-a",
        "-s",
        "-screen 0 1024x768x24",
        "sh",
        "-c",
        "echo $$ > pid; exec \"$0\" \"$@\"",
    ])
    .arg(isrf_bin())
    .args([
        "edit",
        "--scene",
        "tabletop",
        "--res",
        &RES.to_string(),
        "--script",
        "edits.ron",
    ])
    .args(args)
    .env("WGPU_BACKEND", "vulkan")
    .current_dir(dir);
    cmd
}

/// The recovery file in `dir` (there is one set of inputs per test folder).
fn recovery_file(dir: &Path) -> Option<PathBuf> {
    std::fs::read_dir(dir).ok()?.find_map(|e| {
        let p = e.ok()?.path();
        let name = p.file_name()?.to_string_lossy().into_owned();
        (name.ends_with(".json") && !name.ends_with(".previous.json")).then_some(p)
    })
}

/// Waits until the running editor has recorded at least `n` commands; the
/// latest recovery document. Panics if the editor exits first.
fn wait_recorded(child: &mut std::process::Child, rec_dir: &Path, n: usize) -> RecoveryDoc {
    let t0 = Instant::now();
    loop {
        if let Some(doc) = recovery_file(rec_dir).and_then(|p| RecoveryDoc::load(&p).ok()) {
            if doc.commands.len() >= n {
                return doc;
            }
        }
        if let Some(status) = child.try_wait().unwrap() {
            panic!("the editor exited ({status}) before recording {n} commands");
        }
        assert!(t0.elapsed() < Duration::from_secs(300), "no progress after 300 s");
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn sigkill(dir: &Path) {
    let pid: i32 = std::fs::read_to_string(dir.join("pid"))
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    // SAFETY: kill(2) on the PID of the editor this test started.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGKILL) }, 0);
}

/// One kill-and-restore run: the editor is killed once it has recorded
/// `kill_after` commands (plus `delay_ms`, landing inside later commands
/// or recovery writes); returns the commands the recovery file held.
fn kill_and_restore(kill_after: usize, delay_ms: u64) -> usize {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("edits.ron"), SCRIPT).unwrap();
    let rec_dir = dir.path().join("recovery");
    let rec_arg = rec_dir.to_str().unwrap();
    let mut child = editor(dir.path(), &["--size", "640x400", "--recovery-dir", rec_arg])
        .spawn()
        .unwrap();
    wait_recorded(&mut child, &rec_dir, kill_after);
    std::thread::sleep(Duration::from_millis(delay_ms));
    sigkill(dir.path());
    child.wait().unwrap();

    // The file is whole (atomic writes) and replays to its recorded state.
    let path = recovery_file(&rec_dir).expect("a recovery file");
    let doc = RecoveryDoc::load(&path).unwrap_or_else(|e| panic!("the recovery file is torn: {e}"));
    let (_, report) = restore(&doc, &Progress::default()).unwrap();
    assert!(report.identical, "library replay: {}", report.message());

    // The editor restores it (and exits 1 unless the state is identical).
    let shot = dir.path().join("restored.png");
    let o = editor(
        dir.path(),
        &[
            "--size",
            "320x240",
            "--no-ui",
            "--recovery-dir",
            rec_arg,
            "--restore",
            "--screenshot",
        ],
    )
    .arg(&shot)
    .output()
    .unwrap();
    let log = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(o.status.success(), "isrf edit --restore failed ({}):\n{log}", o.status);
    let n = doc.commands.len();
    assert!(
        log.contains(&format!("restored {n} edits: the state is identical")),
        "no restore report in the log:\n{log}"
    );
    assert!(shot.exists());
    n
}

#[test]
fn the_editor_killed_mid_session_restores_the_identical_state_under_xvfb() {
    if skip() {
        return;
    }
    let runs: usize = std::env::var("ISRF_KILL_RESTORE_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let mut held = Vec::new();
    for run in 0..runs {
        // Kill after 2 .. all commands (the load and the script's edits).
        let kill_after = 2 + (run * 3) % SCRIPT_EDITS;
        let delay_ms = (run as u64 * 137) % 400;
        held.push(kill_and_restore(kill_after, delay_ms));
        eprintln!(
            "run {run}: killed after {kill_after} (+{delay_ms} ms), restored {} commands",
            held[run]
        );
    }
    eprintln!("kill-and-restore: identical state after restore in {runs} of {runs} runs (commands held: {held:?})");
}

/// Runs the editor with the script `edits` and the ray-march shader
/// `shader` until it has recorded `n` commands and a few seconds more;
/// asserts it is still running, kills it; returns its log.
fn survives(edits: &str, shader: &str, n: usize) -> String {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("edits.ron"), edits).unwrap();
    let shader_path = dir.path().join("shader.wgsl");
    std::fs::write(&shader_path, shader).unwrap();
    let log_path = dir.path().join("log.txt");
    let rec_dir = dir.path().join("recovery");
    let mut child = editor(
        dir.path(),
        &["--size", "640x400", "--recovery-dir", rec_dir.to_str().unwrap()],
    )
    .env("ISRF_RAYMARCH_WGSL", &shader_path)
    .stdout(std::process::Stdio::null())
    .stderr(std::fs::File::create(&log_path).unwrap())
    .spawn()
    .unwrap();
    let doc = wait_recorded(&mut child, &rec_dir, n);
    assert_eq!(doc.commands.len(), n);
    // Still running a few seconds later (many frames with the failing view).
    std::thread::sleep(Duration::from_secs(3));
    assert!(child.try_wait().unwrap().is_none(), "the editor quit");
    sigkill(dir.path());
    child.wait().unwrap();
    std::fs::read_to_string(&log_path).unwrap()
}

/// A failing step in the middle, then two good ones.
const EDITS_WITH_A_FAILING_STEP: &str = r#"[
    stroke(object: "mug", source: demo(object: "mug")),
    remove(object: "no such object"),
    transform(object: "mug", transform: (translate: (0.3, 0.0, 0.2))),
    remove(object: "mug"),
]"#;

#[test]
fn gpu_validation_errors_and_a_failing_command_do_not_stop_the_editor_under_xvfb() {
    if skip() {
        return;
    }
    // The real shader with one storage binding declared read_write: it
    // parses, but creating its pipeline against the editor's bind group
    // layout is a wgpu validation error, reported every frame it is tried.
    let real = include_str!("../shaders/raymarch.wgsl");
    let invalid = real.replacen("var<storage, read>", "var<storage, read_write>", 1);
    assert_ne!(invalid, real);
    // The load and three good edits are recorded while the view cannot draw.
    let log = survives(EDITS_WITH_A_FAILING_STEP, &invalid, 4);
    assert!(log.contains("Validation Error"), "no validation error happened:\n{log}");
    assert!(log.contains("no object named 'no such object'"), "{log}");
    // A shader that does not even parse: the same.
    let log = survives(EDITS_WITH_A_FAILING_STEP, "this is not WGSL @fragment fn", 4);
    assert!(log.contains("failed to process shader"), "{log}");
}
