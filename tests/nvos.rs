//! `isrf eval --nvos` end to end on a demo scene laid out as an NVOS folder:
//! a scribble on one view selects an object, its mask on another view is
//! scored, and the selection it writes (`--object-out`) is the one scored.

use isrf::camera::{Camera, CameraSet};
use isrf::eval::metrics::iou;
use isrf::eval::protocol::silhouette_voxels;
use isrf::field::{Bitmap, Field};
use isrf::render::{render, Probe, RenderOptions, Scene};
use isrf::segment::bitmap_file::load_bitmap;
use isrf::segment::SegmentParams;
use std::path::Path;
use std::process::Command;
use std::sync::Arc;

/// The opacity of `mask` seen from `cam`, one value per pixel.
fn probe(field: &Arc<Field>, cam: &Camera, mask: Bitmap) -> Vec<f32> {
    let opts = RenderOptions {
        probes: vec![Probe {
            layer: 0,
            mask: Arc::new(mask),
        }],
        depth: false,
        ..Default::default()
    };
    render(&Scene::single(field.clone()), cam, &opts)
        .unwrap()
        .out
        .probe_opacity
}

fn save_mask(path: &Path, cam: &Camera, on: impl Fn(usize) -> bool) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let k = cam.intrinsics;
    let rgb: Vec<u8> = (0..(k.width * k.height) as usize)
        .flat_map(|i| [if on(i) { 255 } else { 0 }; 3])
        .collect();
    isrf::render::save_png(path, k.width, k.height, &rgb).unwrap();
}

#[test]
fn nvos_scores_a_scribbled_object_and_writes_the_selection_it_scored() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let scene = isrf::demo::build("tabletop", 64, 0).unwrap();
    scene.write(&dir.join("demo")).unwrap();
    let cams = CameraSet::load(&dir.join("demo/transforms.json")).unwrap();
    let (reference, target) = (&cams.frames[0], &cams.frames[3]);
    let field = Arc::new(scene.field.clone());
    let ball = scene.labels.mask(scene.labels.label_of("ball").unwrap());
    // The scribble: where the ball is solid on the reference view, every
    // fourth pixel; the true mask: the ball on the target view.
    let on_ref = probe(&field, &reference.camera, ball.clone());
    save_mask(&dir.join("nvos/scribbles/tabletop/pos_1.png"), &reference.camera, |i| {
        on_ref[i] > 0.9 && i % 4 == 0
    });
    let on_target = probe(&field, &target.camera, ball);
    let target_name = target.base_name();
    save_mask(
        &dir.join(format!("nvos/masks/tabletop/{target_name}_mask.png")),
        &target.camera,
        |i| on_target[i] > 0.1,
    );
    let sel = dir.join("ball.safetensors");
    let out = Command::new(env!("CARGO_BIN_EXE_isrf"))
        .args(["eval", "--nvos"])
        .arg(dir.join("nvos"))
        .args(["--scene", "tabletop", "--field"])
        .arg(dir.join("demo/field.safetensors"))
        .arg("--cameras")
        .arg(dir.join("demo/transforms.json"))
        .args(["--reference-view", &reference.base_name(), "--object-out"])
        .arg(&sel)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}\n{stdout}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    let scored = report["iou"].as_f64().unwrap();
    assert!(scored > 0.8, "ball IoU {scored}");
    // The written selection, rendered on the target view, is the scored
    // prediction: the same IoU against the true mask.
    let (mask, _) = load_bitmap(&sel).unwrap();
    assert_eq!(mask.count() as u64, report["voxels"].as_u64().unwrap());
    let over = |o: &[f32]| o.iter().map(|&v| v > 0.1).collect::<Vec<bool>>();
    let truth = over(&on_target);
    let scored_here = |m: Bitmap| iou(&over(&probe(&field, &target.camera, m)), &truth);
    let shown = over(&probe(&field, &target.camera, mask.clone()));
    let rendered = iou(&shown, &truth);
    assert!((rendered - scored).abs() < 1e-9, "{rendered} vs {scored}");
    // Its pixel counts are that render's against the truth.
    let count = |want: (bool, bool)| shown.iter().zip(&truth).filter(|&(&p, &t)| (p, t) == want).count() as u64;
    let pixels = &report["pixels"];
    for (key, want) in [
        ("tp", (true, true)),
        ("fp", (true, false)),
        ("fn", (false, true)),
        ("tn", (false, false)),
    ] {
        assert_eq!(pixels[key].as_u64(), Some(count(want)), "{key}: {pixels}");
    }

    // The oracles are those selections, rendered and scored the same way.
    // The truth is the ball's own render, so the selection less what
    // projects outside it keeps the ball and scores at least as well; every
    // voxel projecting inside it (the floor's under the ball too, each a few
    // pixels wide on this coarse grid) nearly reproduces it.
    let oracle = |k: &str| report["oracles"][k].as_f64().unwrap();
    let cache = field.feature_cache().unwrap();
    let floor = SegmentParams::default().sigma_floor(cache.voxel_size);
    let k = target.camera.intrinsics;
    let silhouette = silhouette_voxels(&cache, floor, &target.camera, &truth, [k.width, k.height]);
    let mut inside = mask;
    inside.intersect_with(&silhouette).unwrap();
    let (inside, silhouette) = (scored_here(inside), scored_here(silhouette));
    assert!(
        (oracle("selection_inside_truth") - inside).abs() < 1e-9,
        "{inside}: {}",
        report["oracles"]
    );
    assert!(
        (oracle("silhouette") - silhouette).abs() < 1e-9,
        "{silhouette}: {}",
        report["oracles"]
    );
    assert!(inside >= scored && inside > silhouette, "{}", report["oracles"]);
    assert!(silhouette > 0.8, "{}", report["oracles"]);
}
