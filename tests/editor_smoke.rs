//! Smoke test of the windowed editor under `xvfb-run` on a software Vulkan
//! driver: `isrf edit --scene tabletop --script S --screenshot OUT` strokes
//! the mug and moves it; the pixels where the mug was change against a
//! screenshot without the script; with the panels shown it still renders
//! and exits 0. Skips (with a message) without xvfb-run or
//! a Vulkan adapter.
#![cfg(feature = "editor")]

use isrf::app::headless::gpu_available;
use std::path::Path;
use std::process::Command;

const RES: usize = 48;
const W: u32 = 320;
const H: u32 = 240;

fn have(cmd: &str) -> bool {
    Command::new("sh")
        .arg("-c")
        .arg(format!("command -v {cmd}"))
        .output()
        .is_ok_and(|o| o.status.success())
}

/// Runs the editor; `ui` shows the panels (in a 960×600 window, so the view
/// keeps some room), else the bare W×H view.
fn screenshot(dir: &Path, name: &str, script: Option<&Path>, ui: bool) -> image::RgbImage {
    let size = if ui { "960x600".to_string() } else { format!("{W}x{H}") };
    let out = dir.join(format!("{name}.png"));
    let mut cmd = Command::new("xvfb-run");
    cmd.args(["-a", "-s", "-screen 0 1024x768x24"])
        .arg(env!("CARGO_BIN_EXE_isrf"))
        .args(["edit", "--scene", "tabletop", "--res", &RES.to_string()])
        .args(["--size", &size, "--screenshot"])
        .arg(&out)
        .env("WGPU_BACKEND", "vulkan")
        .current_dir(dir);
    if let Some(s) = script {
        cmd.arg("--script").arg(s);
    }
    if !ui {
        cmd.arg("--no-ui");
    }
    let o = cmd.output().expect("running xvfb-run");
    assert!(
        o.status.success(),
        "isrf edit failed ({}):\n{}\n{}",
        o.status,
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    image::open(&out).expect("reading the screenshot").to_rgb8()
}

#[test]
fn editor_strokes_and_moves_an_object_under_xvfb() {
    if !have("xvfb-run") {
        eprintln!("skipping: xvfb-run is not installed (Debian package xvfb)");
        return;
    }
    if !gpu_available() {
        eprintln!("skipping: no Vulkan adapter (Debian package mesa-vulkan-drivers, WGPU_BACKEND=vulkan)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let script = dir.path().join("move_mug.ron");
    std::fs::write(
        &script,
        r#"[
            stroke(object: "mug", source: demo(object: "mug")),
            transform(object: "mug", transform: (translate: (0.45, 0.0, 0.35))),
        ]"#,
    )
    .unwrap();
    let before = screenshot(dir.path(), "before", None, false);
    let after = screenshot(dir.path(), "after", Some(&script), false);
    assert_eq!(before.dimensions(), (W, H));
    assert_eq!(after.dimensions(), (W, H));

    // Where the mug was: its voxels' centre seen from the first capture view
    // (the demo's stroke view), scaled to the window.
    let d = isrf::demo::build("tabletop", RES, 0).unwrap();
    let mask = d.labels.mask(d.labels.label_of("mug").unwrap());
    let g = d.field.geom();
    let (lo, hi) = mask.bounding_box().unwrap();
    let c = 0.5 * (g.point(lo[0], lo[1], lo[2]) + g.point(hi[0], hi[1], hi[2]));
    let (px, _) = d.stroke_camera.project(c).unwrap();
    let s = H as f32 / d.stroke_camera.intrinsics.height as f32;
    let (cx, cy) = (px.x * s, px.y * s);
    let diff = |x: u32, y: u32| -> f32 {
        let (a, b) = (before.get_pixel(x, y), after.get_pixel(x, y));
        (0..3).map(|k| (a[k] as f32 - b[k] as f32).abs()).sum::<f32>() / (3.0 * 255.0)
    };
    let mut near = 0.0;
    let mut n = 0.0;
    for y in (cy as i32 - 3)..=(cy as i32 + 3) {
        for x in (cx as i32 - 3)..=(cx as i32 + 3) {
            if x >= 0 && y >= 0 && (x as u32) < W && (y as u32) < H {
                near += diff(x as u32, y as u32);
                n += 1.0;
            }
        }
    }
    let near = near / n;
    let overall = (0..H)
        .flat_map(|y| (0..W).map(move |x| (x, y)))
        .map(|(x, y)| diff(x, y))
        .sum::<f32>()
        / (W * H) as f32;
    eprintln!("mean change where the mug was: {near:.3}, over the image: {overall:.4}");
    assert!(near > 0.05, "the pixels where the mug was did not change ({near:.3})");
    assert!(
        overall < 0.2,
        "the whole view changed ({overall:.3}): the camera moved?"
    );

    // The same with the panels (every UI system runs, the moved object is
    // selected): it renders and exits 0.
    let ui = screenshot(dir.path(), "ui", Some(&script), true);
    let grey = ui.pixels().filter(|p| p[0] == p[1] && p[1] == p[2]).count();
    assert!(grey < ui.pixels().len(), "the screenshot with panels shows no colour");
}
