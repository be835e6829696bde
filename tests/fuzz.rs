//! The readers under fuzzing: every committed reproducer (tests/fuzz_corpus,
//! from ../shared/fuzz) gives a clear error, and a short fixed-seed fuzz run
//! per target finds no panic. This test binary refuses single allocations
//! over 1 GiB while an input runs (the refusal aborts the binary, so a
//! reader that allocates from an unchecked header fails the suite).

use isrf::fuzz::{self, Outcome, Target};
use std::path::Path;

#[global_allocator]
static ALLOC: fuzz::alloc::CapAlloc = fuzz::alloc::CapAlloc;

fn target(name: &str) -> &'static Target {
    fuzz::find(name).unwrap_or_else(|| panic!("no target {name}"))
}

/// Runs a committed corpus file through its target's reader.
fn outcome(target_name: &str, file: &str) -> Outcome {
    let t = target(target_name);
    let bytes = t
        .corpus
        .iter()
        .find(|(n, _)| *n == file)
        .unwrap_or_else(|| panic!("{file} is not in the {target_name} corpus"))
        .1;
    let work = tempfile::tempdir().unwrap();
    fuzz::prepare(t, work.path()).unwrap();
    fuzz::run_one(t, work.path(), bytes)
}

/// The reader's error for a reproducer; every `needles` must be in it.
fn assert_error(target_name: &str, file: &str, needles: &[&str]) {
    match outcome(target_name, file) {
        Outcome::Err(e) => {
            let msg = e.to_string();
            for n in needles {
                assert!(msg.contains(n), "{file}: error lacks {n:?}: {msg}");
            }
        }
        other => panic!("{file}: expected an error, got {other:?}"),
    }
}

macro_rules! regression {
    ($($test:ident: $target:literal, $file:literal => [$($needle:literal),*];)*) => {
        $(#[test]
        fn $test() {
            assert_error($target, $file, &[$($needle),*]);
        })*
    };
}

regression! {
    field_feat_pe_overflow_min: "field", "field_load-panic-io477-feat_pe-overflow-min.safetensors"
        => ["input.safetensors", "positional encoding frequencies out of range", "feat_pe"];
    field_feat_pe_2pow63: "field", "field_load-panic-io477-feat_pe-2pow63.safetensors"
        => ["positional encoding frequencies out of range", "9223372036854775808"];
    field_mlp_layers_overflow: "field", "field_load-panic-io495-mlp-layers-overflow.safetensors"
        => ["appearance MLP", "absurdly large"];

    llff_empty_poses: "llff", "llff-RELEASE-panic-llff203-empty-poses.npy"
        => ["poses_bounds.npy", "more elements than memory can hold"];
    llff_shape_product_overflow: "llff", "llff-panic-npyz-read369-shape-product-overflow.npy"
        => ["poses_bounds.npy", "more elements than memory can hold"];
    llff_strides_overflow: "llff", "llff-panic-npyz-read549-strides-overflow.npy"
        => ["poses_bounds.npy", "expected a dimension"];
    llff_13_braces: "llff", "llff-hang-npy-header-13-braces.npy"
        => ["poses_bounds.npy", "malformed .npy header"];
    llff_nesting_22_levels: "llff", "llff-hang-npy-header-nesting-22-levels.npy"
        => ["poses_bounds.npy", "unexpected key"];
    llff_hang_532: "llff", "llff-hang-fuzzer-found-532B.npy" => ["poses_bounds.npy", ".npy header"];
    llff_hang_658: "llff", "llff-hang-fuzzer-found-658B.npy" => ["poses_bounds.npy", ".npy header"];
    llff_alloc_3gib_header_length: "llff", "llff-alloc-3.1GiB-npyz-v2-header-length.npy"
        => ["poses_bounds.npy", "corrupt header length 3323396212", "524 bytes after it"];
    llff_alloc_512mib_header_length: "llff", "llff-alloc-512MiB-npyz-header-length.npy"
        => ["poses_bounds.npy", "corrupt header length"];
    dataset_llff_hang_503: "llff", "dataset_llff-hang-fuzzer-found-503B.npy" => ["poses_bounds.npy", ".npy header"];
    dataset_llff_read369: "llff", "dataset_llff-panic-npyz-read369.npy" => ["poses_bounds.npy"];

    image_png_bomb: "image", "image_load-alloc-3GiB-png-bomb-261KB.png"
        => ["image.png", "16384×16384", "its camera is 64×48"];
    image_jpeg_768mb: "image", "image_load-alloc-768MB-from-731B-jpeg.jpg"
        => ["image.png", "11296×5664", "its camera is 64×48"];

    strokes_error_in_list: "strokes", "strokes-misleading-error-list.json"
        => ["input.json", "stroke 2", "invalid value: integer `-3`"];
    strokes_error_in_wrapped_list: "strokes", "strokes-misleading-error-wrapped.json"
        => ["input.json", "stroke "];
}

/// The stroke reproducers that hung or overflowed in `stroke_pixels` now
/// finish (with the stroke's clipped pixels, or an error when it misses
/// the image) without a panic.
#[test]
fn stroke_pixel_reproducers_finish() {
    for (name, _) in target("strokes")
        .corpus
        .iter()
        .filter(|(n, _)| n.starts_with("stroke_pixels-"))
    {
        match outcome("strokes", name) {
            Outcome::Panic(m) => panic!("{name}: {m}"),
            Outcome::Ok | Outcome::Err(_) => {}
        }
    }
}

/// Without a camera size to check against, the pixel cap still refuses
/// the 16384² PNG before decoding it.
#[test]
fn image_pixel_cap_without_a_camera() {
    let t = target("image");
    let (_, bomb) = t.corpus.iter().find(|(n, _)| n.contains("png-bomb")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bomb.png");
    std::fs::write(&path, bomb).unwrap();
    fuzz::alloc::arm(true);
    let err = isrf::data::Image::load(&path).unwrap_err().to_string();
    fuzz::alloc::arm(false);
    assert!(
        err.contains("bomb.png") && err.contains("more than the 67108864 pixels"),
        "{err}"
    );
}

/// Every target's generated seeds are read without error: the fuzzer
/// starts from valid files.
#[test]
fn generated_seeds_are_valid() {
    for t in fuzz::TARGETS {
        let work = tempfile::tempdir().unwrap();
        let seeds = (t.seeds)(work.path()).unwrap();
        assert!(!seeds.is_empty(), "{}", t.name);
        for (i, s) in seeds.iter().enumerate() {
            match fuzz::run_one(t, work.path(), s) {
                Outcome::Ok => {}
                other => panic!("{} seed {i}: {other:?}", t.name),
            }
        }
    }
}

/// A short fixed-seed run per target: no panics, no refused allocation.
/// (Inputs over 5 s are counted, not timed here: a slow machine must not
/// fail the suite.)
#[test]
fn short_fuzz_run_per_target() {
    let mut failures = Vec::new();
    for t in fuzz::TARGETS {
        let work = tempfile::tempdir().unwrap();
        let opts = fuzz::Options {
            seed: 18,
            max_inputs: Some(300),
            ..Default::default()
        };
        let r = fuzz::run(t, &work.path().join(t.name), &opts).unwrap();
        assert_eq!(r.inputs, 300, "{}", t.name);
        // The mutants must reach the readers' error paths, not only pass.
        assert!(r.errors > 0, "{}: no input was rejected", t.name);
        if r.panics > 0 {
            failures.push(format!("{}: {:?}", t.name, r.panic_kinds));
        }
    }
    assert_eq!(fuzz::alloc::refused(), 0);
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn corpus_files_match_the_repository() {
    // The compiled-in corpus is the files in tests/fuzz_corpus: a file
    // added there but not listed in a target would never be tried.
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_corpus");
    for dir in std::fs::read_dir(&root).unwrap() {
        let dir = dir.unwrap().path();
        if !dir.is_dir() {
            continue;
        }
        let t = target(dir.file_name().unwrap().to_str().unwrap());
        for f in std::fs::read_dir(&dir).unwrap() {
            let name = f.unwrap().file_name().into_string().unwrap();
            assert!(
                t.corpus.iter().any(|(n, _)| *n == name),
                "{name} is not in {}'s corpus",
                t.name
            );
        }
    }
}

/// The command-line contract: `--list` names every target; a run ends with
/// `inputs: n, errors: n, panics: n`.
#[test]
fn fuzz_command_line() {
    let isrf = env!("CARGO_BIN_EXE_isrf");
    let out = std::process::Command::new(isrf)
        .args(["fuzz", "--list"])
        .output()
        .unwrap();
    assert!(out.status.success());
    let list = String::from_utf8(out.stdout).unwrap();
    for t in fuzz::TARGETS {
        assert!(
            list.lines().any(|l| l.starts_with(t.name)),
            "{} missing from {list}",
            t.name
        );
    }
    let out = std::process::Command::new(isrf)
        .args(["fuzz", "llff", "--secs", "30", "--max-inputs", "400", "--seed", "3"])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8(out.stdout).unwrap();
    let last = text.lines().last().unwrap();
    let (errors, panics) = last
        .strip_prefix("inputs: 400, errors: ")
        .and_then(|r| r.split_once(", panics: "))
        .unwrap_or_else(|| panic!("{text}"));
    assert!(errors.parse::<u64>().unwrap() > 0, "{last}");
    assert_eq!(panics, "0");
    let out = std::process::Command::new(isrf)
        .args(["fuzz", "nope"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no fuzz target 'nope'"));
}

/// The driver itself: a planted bug (a panic when a number in the JSON
/// grows past 10⁹, as unchecked size arithmetic would) is found from a
/// valid seed, recorded with its message and saved.
#[test]
fn driver_finds_a_planted_panic() {
    let planted = Target {
        name: "planted",
        about: "test only",
        file: "input.json",
        seeds: |_| Ok(vec![br#"{"count": 12, "size": [4, 4]}"#.to_vec()]),
        corpus: &[],
        run: |p| {
            let v: serde_json::Value = serde_json::from_slice(&std::fs::read(p).map_err(|e| isrf::Error::io(p, e))?)
                .map_err(|e| isrf::Error::invalid(e.to_string()))?;
            let n = v["count"].as_u64().ok_or_else(|| isrf::Error::invalid("no count"))?;
            assert!(n < 1_000_000_000, "planted: count {n}");
            Ok(())
        },
    };
    let dir = tempfile::tempdir().unwrap();
    let opts = fuzz::Options {
        seed: 5,
        max_inputs: Some(3000),
        save_dir: Some(dir.path().join("found")),
        ..Default::default()
    };
    let r = fuzz::run(&planted, &dir.path().join("work"), &opts).unwrap();
    assert!(r.panics > 0 && r.errors > 0, "{r:?}");
    assert!(
        r.panic_kinds.iter().all(|(m, _)| m.starts_with("planted: count")),
        "{:?}",
        r.panic_kinds
    );
    let saved = std::fs::read_dir(dir.path().join("found")).unwrap().count();
    assert!(saved >= 1 && saved == r.saved.len(), "{saved} files, {:?}", r.saved);
}
