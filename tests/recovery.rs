//! Crash recovery (issue 18, part 5) at the library level: the recovery
//! file a session records after every command replays to the identical
//! state; changed input files refuse to restore; an older file is kept
//! aside, never overwritten. The editor's own kill-and-restore test under
//! Xvfb is in `tests/editor_recovery.rs`.

use isrf::command::recovery::{restore, state_digest, Inputs, Recorder, RecoveryDoc, StartStep};
use isrf::command::{Edit, FieldSource, Session, TransformSpec};
use isrf::render::ColorEdit;
use isrf::util::Progress;
use std::path::Path;

mod common;
use common::{demo_stroke as stroke, load_demo};

fn inputs(dir: &Path, start: Vec<Edit>) -> Inputs {
    Inputs {
        cwd: dir.to_path_buf(),
        start: start.into_iter().map(|e| StartStep::Apply(e.into())).collect(),
    }
}

/// A session with a few kinds of edits, recorded after each one as the
/// editor does.
fn recorded_session(dir: &Path) -> (Session, Recorder) {
    let mut s = Session::new(dir, dir);
    let mut rec = Recorder::new(dir.join("r.json"), inputs(dir, vec![load_demo()]));
    let edits = [
        load_demo(),
        stroke("mug"),
        Edit::Transform {
            object: "mug".into(),
            transform: TransformSpec::translation(glam::Vec3::new(0.3, 0.0, 0.2)),
        },
        Edit::Appearance {
            object: "mug".into(),
            edit: ColorEdit {
                hue: 120.0,
                ..Default::default()
            },
        },
        Edit::Duplicate {
            object: "mug".into(),
            name: "mug 2".into(),
            transform: Some(TransformSpec::translation(glam::Vec3::new(-0.3, 0.0, 0.0))),
        },
        Edit::Grow {
            object: "mug 2".into(),
            steps: isrf::segment::Growth::Steps(1),
        },
    ];
    for c in &edits {
        s.apply(c).unwrap();
        rec.record(&s).unwrap();
    }
    // An undone edit is not part of the state, nor of the log.
    s.apply(&Edit::Remove { object: "mug".into() }).unwrap();
    rec.record(&s).unwrap();
    s.undo().unwrap();
    rec.record(&s).unwrap();
    (s, rec)
}

#[test]
fn a_recorded_session_replays_to_the_identical_state() {
    let dir = tempfile::tempdir().unwrap();
    let (s, rec) = recorded_session(dir.path());
    let doc = RecoveryDoc::load(&rec.path).unwrap();
    assert_eq!(doc.commands, s.log());
    assert_eq!(doc.commands.len(), 6);
    assert_eq!(doc.state, state_digest(s.state()));
    assert!(doc.has_edits_beyond_start());

    let (r, report) = restore(&doc, &Progress::default()).unwrap();
    assert_eq!(report.applied, 6);
    assert!(report.failed.is_none());
    assert!(report.identical, "{}", report.message());
    // Identical object by object, not only by digest.
    assert_eq!(r.state().objects.len(), 2);
    for (a, b) in r.state().objects.iter().zip(&s.state().objects) {
        assert_eq!(a.name, b.name);
        assert_eq!(*a.mask, *b.mask);
        assert_eq!(a.placement, b.placement);
    }
    // The replayed session's log is the recorded one: recording it again
    // gives the same file contents (bar the time).
    assert_eq!(r.log(), doc.commands);
}

#[test]
fn the_digest_tells_apart_states_that_differ_in_one_voxel_or_one_float() {
    let dir = tempfile::tempdir().unwrap();
    let (s, _) = recorded_session(dir.path());
    let d0 = state_digest(s.state());
    let mut st = s.state().clone();
    let mut mask = (*st.objects[0].mask).clone();
    let v = (0..mask.len()).find(|&v| !mask.get(v)).unwrap();
    mask.set(v, true);
    st.objects[0].mask = std::sync::Arc::new(mask);
    assert_ne!(state_digest(&st), d0);
    let mut st = s.state().clone();
    let x = &mut st.objects[1].placement.transform.translation.x;
    *x = f32::from_bits(x.to_bits() + 1);
    assert_ne!(state_digest(&st), d0);
}

#[test]
fn only_work_a_fresh_start_would_not_redo_is_offered() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = Session::new(dir.path(), dir.path());
    let start = vec![load_demo(), stroke("mug")];
    let mut rec = Recorder::new(dir.path().join("r.json"), inputs(dir.path(), start.clone()));
    // Killed during the start-up: a prefix of it.
    s.apply(&start[0]).unwrap();
    assert!(!rec.doc(&s).unwrap().has_edits_beyond_start());
    s.apply(&start[1]).unwrap();
    assert!(!rec.doc(&s).unwrap().has_edits_beyond_start());
    // One more edit, or an undone start-up edit, is the user's work.
    s.apply(&Edit::Remove { object: "mug".into() }).unwrap();
    assert!(rec.doc(&s).unwrap().has_edits_beyond_start());
    s.undo();
    s.undo();
    s.apply(&stroke("pot")).unwrap();
    assert!(rec.doc(&s).unwrap().has_edits_beyond_start());
}

#[test]
fn an_older_recovery_file_is_moved_aside_not_overwritten() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("r.json");
    std::fs::write(&path, b"the earlier session").unwrap();
    let mut s = Session::new(dir.path(), dir.path());
    let mut rec = Recorder::new(path.clone(), inputs(dir.path(), vec![]));
    s.apply(&load_demo()).unwrap();
    rec.record(&s).unwrap();
    assert_eq!(std::fs::read(rec.previous_path()).unwrap(), b"the earlier session");
    assert_eq!(RecoveryDoc::load(&path).unwrap().commands.len(), 1);
    // Later writes replace its own file only.
    s.apply(&stroke("mug")).unwrap();
    rec.record(&s).unwrap();
    assert_eq!(RecoveryDoc::load(&path).unwrap().commands.len(), 2);
    assert_eq!(std::fs::read(rec.previous_path()).unwrap(), b"the earlier session");
}

#[test]
fn a_changed_input_file_refuses_to_restore_and_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let field = dir.path().join("f.safetensors");
    let d = isrf::demo::build("tabletop", 24, 0).unwrap();
    d.field.save(&field).unwrap();
    let mut s = Session::new(dir.path(), dir.path());
    let mut rec = Recorder::new(dir.path().join("r.json"), inputs(dir.path(), vec![]));
    s.apply(&Edit::LoadField {
        name: "f".into(),
        source: FieldSource::File("f.safetensors".into()),
        transform: None,
    })
    .unwrap();
    rec.record(&s).unwrap();
    let doc = RecoveryDoc::load(&rec.path).unwrap();
    assert_eq!(doc.files.len(), 1);
    assert_eq!(doc.files[0].path, dir.path().join("f.safetensors"));
    assert!(restore(&doc, &Progress::default()).unwrap().1.identical);

    isrf::demo::build("tabletop", 24, 1)
        .unwrap()
        .field
        .save(&field)
        .unwrap();
    let e = restore(&doc, &Progress::default()).unwrap_err().to_string();
    assert!(e.contains("has changed") && e.contains("f.safetensors"), "{e}");
    std::fs::remove_file(&field).unwrap();
    let e = restore(&doc, &Progress::default()).unwrap_err().to_string();
    assert!(e.contains("gone") && e.contains("f.safetensors"), "{e}");
}

#[test]
fn a_corrupt_recovery_file_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let (_, rec) = recorded_session(dir.path());
    let text = std::fs::read_to_string(&rec.path).unwrap();
    for bad in [&text[..text.len() / 2], "", "{\"format\": \"isrf-recovery\"}", "[1, 2]"] {
        std::fs::write(&rec.path, bad).unwrap();
        let e = RecoveryDoc::load(&rec.path).unwrap_err().to_string();
        assert!(e.contains("r.json") && e.contains("not a recovery file"), "{e}");
    }
}

#[test]
fn a_panic_inside_a_guarded_call_becomes_an_error() {
    let r: isrf::Result<u32> = isrf::error::catch_panic("stroke", || panic!("index out of bounds"));
    let e = r.unwrap_err().to_string();
    assert!(e.contains("stroke") && e.contains("index out of bounds"), "{e}");
    assert_eq!(isrf::error::catch_panic("x", || Ok(7)).unwrap(), 7);
}
