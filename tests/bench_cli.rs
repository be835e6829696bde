//! `isrf bench render` and `isrf bench segment` on tiny grids: they run, and
//! their last lines have the documented machine-readable format.

use std::process::Command;

fn isrf(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_isrf"))
        .args(args)
        .output()
        .expect("run the isrf binary");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn last_line(s: &str) -> &str {
    s.lines().last().unwrap_or("")
}

/// The positive number the last line of `out` gives after `prefix`.
fn last_number(out: &str, prefix: &str) -> f64 {
    let line = last_line(out);
    let n: f64 = line
        .strip_prefix(prefix)
        .unwrap_or_else(|| panic!("last line is not '{prefix}<number>': {line:?}"))
        .parse()
        .unwrap_or_else(|e| panic!("not a number in {line:?}: {e}"));
    assert!(n.is_finite() && n > 0.0, "{line}");
    n
}

#[test]
fn bench_render_ends_with_rays_per_second() {
    let (ok, out, err) = isrf(&[
        "bench", "render", "--res", "24", "--width", "40", "--height", "30", "--frames", "1",
    ]);
    assert!(ok, "bench render failed: {err}\n{out}");
    last_number(&out, "rays/s: ");
    assert!(out.contains("rayon threads"), "thread count missing:\n{out}");
    assert!(out.contains("24^3"), "resolution row missing:\n{out}");
}

#[test]
fn bench_segment_ends_with_stroke_to_mask_and_speedup() {
    let (ok, out, err) = isrf(&["bench", "segment", "--res", "48", "--repeats", "2"]);
    assert!(ok, "bench segment failed: {err}\n{out}");
    let line = last_line(&out);
    let rest = line
        .strip_prefix("stroke-to-mask ms at 48^3: ")
        .unwrap_or_else(|| panic!("unexpected last line {line:?}"));
    let (ms, speedup) = rest
        .split_once(", speed-up over dense: ")
        .unwrap_or_else(|| panic!("no speed-up in {line:?}"));
    let ms: f64 = ms.parse().unwrap_or_else(|e| panic!("bad ms in {line:?}: {e}"));
    let x: f64 = speedup
        .strip_suffix('x')
        .unwrap_or_else(|| panic!("speed-up lacks its 'x' in {line:?}"))
        .parse()
        .unwrap_or_else(|e| panic!("bad speed-up in {line:?}: {e}"));
    assert!(ms > 0.0 && x > 0.0, "{line}");
    // The cache path and the dense reference agree on this grid.
    assert!(out.contains("identical: yes"), "outputs differ:\n{out}");
}

#[test]
fn bench_rejects_bad_arguments_with_a_message() {
    let (ok, _, err) = isrf(&["bench", "render", "--res", "5", "--frames", "1"]);
    assert!(!ok);
    assert!(err.contains("out of range"), "{err}");
    let (ok, _, err) = isrf(&["bench", "segment", "--res", "48", "--object", "unicorn"]);
    assert!(!ok);
    assert!(err.contains("unicorn"), "{err}");
}

/// `isrf bench editor` on a tiny grid: every row prints, each timed frame
/// marched (the command checks that itself and fails otherwise), and the
/// last line is `fps: <number>`. Skips where no GPU adapter exists.
#[cfg(feature = "editor")]
#[test]
fn bench_editor_ends_with_fps() {
    if !isrf::app::headless::gpu_available() {
        eprintln!("skipping: no GPU adapter (install mesa-vulkan-drivers and set WGPU_BACKEND=vulkan)");
        return;
    }
    let (ok, out, err) = isrf(&[
        "bench", "editor", "--res", "32", "--width", "80", "--height", "48", "--frames", "2",
    ]);
    assert!(ok, "bench editor failed: {err}\n{out}");
    for row in [
        "field ",
        "field + one moved object",
        "½ res (moving)",
        "field, still view",
        "stroke -> visible",
        "fps while moving",
    ] {
        assert!(out.contains(row), "row {row:?} missing:\n{out}");
    }
    last_number(&out, "fps: ");
}
