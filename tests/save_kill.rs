//! Saves never corrupt (issue 18, part 6): a child process saves, over and
//! over, two versions of a composition (document + bitmaps sidecar) and of
//! a field file (tens of MB, streamed); it is killed with SIGKILL at
//! random moments. After each kill the composition opens as exactly the
//! old or the new version (compared by state digest) and the field file
//! holds exactly one version's bytes: never a mix, never a torn file.
//!
//! The child is this test binary itself, re-run with `ISRF_SAVE_LOOP_DIR`
//! set (`save_loop_child` does nothing otherwise). Unix only (SIGKILL).
#![cfg(unix)]

use isrf::command::composition;
use isrf::command::recovery::state_digest;
use isrf::command::{Edit, FieldSource, Session, StrokeSource};
use std::io::BufRead;
use std::path::Path;
use std::process::{Command as Process, Stdio};

const RES: usize = 40;
/// Field files of this demo resolution are tens of MB: a write takes long
/// enough that many kills land inside one.
const FIELD_RES: usize = 128;

/// Version `v` (0 or 1) of the composition: the tabletop with the mug, and
/// for version 1 the pot (moved) and the mug.
fn session(dir: &Path, v: usize) -> Session {
    let mut s = Session::new(dir, dir);
    s.apply(&Edit::LoadField {
        name: "t".into(),
        source: FieldSource::Demo {
            scene: "tabletop".into(),
            res: RES,
            seed: 0,
        },
        transform: None,
    })
    .unwrap();
    // Version 1's first bitmap is another object's: an old document
    // reading new bitmaps would give its mug the pot's voxels.
    let objects: &[&str] = if v == 0 { &["mug"] } else { &["pot", "mug"] };
    for o in objects {
        s.apply(&Edit::Stroke {
            object: o.to_string(),
            field: None,
            polarity: None,
            source: StrokeSource::Demo { object: o.to_string() },
        })
        .unwrap();
    }
    if v == 1 {
        s.apply(&Edit::Transform {
            object: "pot".into(),
            transform: isrf::command::TransformSpec::translation(glam::Vec3::new(0.2, 0.0, 0.1)),
        })
        .unwrap();
    }
    s
}

fn field(v: usize) -> isrf::field::Field {
    isrf::demo::build("tabletop", FIELD_RES, v as u64).unwrap().field
}

/// The child: saves versions 0 and 1 in turn until killed; prints "ready"
/// once both versions of both files are on disk.
#[test]
fn save_loop_child() {
    let Some(dir) = std::env::var_os("ISRF_SAVE_LOOP_DIR") else {
        return;
    };
    let dir = Path::new(&dir);
    let sessions = [session(dir, 0), session(dir, 1)];
    let fields = [field(0), field(1)];
    for round in 0.. {
        for v in 0..2 {
            composition::save(&sessions[v], &dir.join("scene.json")).unwrap();
            fields[v].save(&dir.join("field.safetensors")).unwrap();
        }
        if round == 0 {
            println!("ready");
        }
    }
}

/// Temporary files a killed write left in `dir`.
fn leftovers(dir: &Path) -> usize {
    std::fs::read_dir(dir)
        .unwrap()
        .filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().starts_with(".tmp"))
        .count()
}

#[test]
fn a_save_killed_half_way_leaves_the_old_or_the_new_file() {
    let runs: usize = std::env::var("ISRF_SAVE_KILL_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(6);
    let reference = tempfile::tempdir().unwrap();
    let digests: Vec<String> = (0..2)
        .map(|v| state_digest(session(reference.path(), v).state()))
        .collect();
    assert_ne!(digests[0], digests[1]);
    let field_crcs: Vec<u32> = (0..2)
        .map(|v| {
            let p = reference.path().join(format!("f{v}.safetensors"));
            field(v).save(&p).unwrap();
            crc32fast::hash(&std::fs::read(&p).unwrap())
        })
        .collect();
    assert_ne!(field_crcs[0], field_crcs[1]);

    let mut rng = isrf::util::SplitMix64::new(18);
    let (mut found, mut field_found, mut torn) = ([0usize; 2], [0usize; 2], 0);
    for run in 0..runs {
        let dir = tempfile::tempdir().unwrap();
        let mut child = Process::new(std::env::current_exe().unwrap())
            .args(["--exact", "save_loop_child", "--nocapture", "--test-threads", "1"])
            .env("ISRF_SAVE_LOOP_DIR", dir.path())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let mut out = std::io::BufReader::new(child.stdout.take().unwrap());
        let mut line = String::new();
        while !line.contains("ready") {
            line.clear();
            assert!(out.read_line(&mut line).unwrap() > 0, "the saving child ended early");
        }
        // A random moment within about two save rounds.
        std::thread::sleep(std::time::Duration::from_millis(rng.below(1500) as u64));
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        torn += leftovers(dir.path());

        let s = composition::load(&dir.path().join("scene.json"), dir.path())
            .unwrap_or_else(|e| panic!("run {run}: the composition does not open after the kill: {e}"));
        let d = state_digest(s.state());
        let v = digests
            .iter()
            .position(|x| *x == d)
            .unwrap_or_else(|| panic!("run {run}: the composition is neither version (a mix)"));
        let crc = crc32fast::hash(&std::fs::read(dir.path().join("field.safetensors")).unwrap());
        let fv = field_crcs
            .iter()
            .position(|x| *x == crc)
            .unwrap_or_else(|| panic!("run {run}: the field file is neither version (torn)"));
        isrf::field::Field::load(&dir.path().join("field.safetensors")).unwrap();
        found[v] += 1;
        field_found[fv] += 1;
        // At most the old sidecar of the last save besides the current one.
        let sidecars = std::fs::read_dir(dir.path())
            .unwrap()
            .filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().contains(".bitmaps."))
            .count();
        assert!(sidecars <= 2, "run {run}: {sidecars} bitmaps sidecars pile up");
    }
    eprintln!(
        "{runs} kills: composition found as version 0/1 {}/{} times, field file {}/{} times; {torn} temporary files left by writes cut short",
        found[0], found[1], field_found[0], field_found[1]
    );
}

/// The child of the failpoint tests: saves version 1 over version 0 once,
/// dying at the failpoint named in `ISRF_FAILPOINT`.
#[test]
fn save_once_child() {
    let Some(dir) = std::env::var_os("ISRF_SAVE_ONCE_DIR") else {
        return;
    };
    let dir = Path::new(&dir);
    composition::save(&session(dir, 1), &dir.join("scene.json")).unwrap();
    println!("the save finished: the failpoint was not reached");
}

/// Saves version 0, then has a child save version 1 and die at
/// `failpoint`; returns the version the composition opens as, and the
/// folder's file names.
fn cut_save_at(failpoint: &str) -> (usize, Vec<String>) {
    let dir = tempfile::tempdir().unwrap();
    composition::save(&session(dir.path(), 0), &dir.path().join("scene.json")).unwrap();
    let o = Process::new(std::env::current_exe().unwrap())
        .args(["--exact", "save_once_child", "--nocapture", "--test-threads", "1"])
        .env("ISRF_SAVE_ONCE_DIR", dir.path())
        .env("ISRF_FAILPOINT", failpoint)
        .output()
        .unwrap();
    assert!(!o.status.success(), "the child was not cut at {failpoint}");
    let s = composition::load(&dir.path().join("scene.json"), dir.path())
        .unwrap_or_else(|e| panic!("cut at {failpoint}, the composition does not open: {e}"));
    let d = state_digest(s.state());
    let v = (0..2)
        .position(|v| state_digest(session(dir.path(), v).state()) == d)
        .unwrap_or_else(|| panic!("cut at {failpoint}: the composition is neither version (a mix)"));
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    (v, names)
}

#[test]
fn a_save_cut_between_the_bitmaps_and_the_document_opens_as_the_old_composition() {
    // The new sidecar is complete and on disk, the document is the old
    // one: the old document must still find its own bitmaps (before the
    // sidecar's name carried its checksum, it found the new ones: a mix).
    let (v, names) = cut_save_at("composition.between_writes");
    assert_eq!(v, 0);
    let sidecars = names.iter().filter(|n| n.contains(".bitmaps.")).count();
    assert_eq!(sidecars, 2, "{names:?}");
}

#[test]
fn a_save_cut_inside_a_write_leaves_the_old_file_and_a_stray_temporary() {
    let (v, names) = cut_save_at("write_atomic.before_rename");
    assert_eq!(v, 0);
    assert!(names.iter().any(|n| n.starts_with(".tmp")), "{names:?}");
}
