//! Scoring segmentations against ground truth.
//!
//! Demo scenes: each object is segmented from its built-in stroke (one
//! positive stroke on the stroke camera) and compared with its label grid in
//! 3D (IoU over occupied voxels: σ above the occupancy floor, the voxels a
//! segmentation can select) and in 2D on the held-out views (predicted mask =
//! the object's rendered opacity > 0.1, as the paper; ground-truth mask = the
//! same for the label bitmap, so both see the same occlusions).
//!
//! NVOS layout: `reference_image/<scene>/<img>`, `scribbles/<scene>/{pos,neg}_*.png`
//! (any non-zero pixel is a stroke), `masks/<scene>/<target>_mask.png`.

use super::metrics::{average_precision, edge_band, iou3d, Confusion};
use crate::camera::{Camera, CameraSet};
use crate::demo::{DemoScene, STROKE_RADIUS};
use crate::error::{Error, Result};
use crate::field::{Bitmap, FeatureCache, Field};
use crate::render::{render, Probe, RenderOptions, Scene};
use crate::segment::{object_from_stroke, scribble_stroke, MaskBuilder, Polarity, SegmentParams, Stroke, Timings};
use glam::Vec2;
use rayon::prelude::*;
use serde::Serialize;
use std::path::Path;
use std::sync::Arc;

#[derive(Clone, Debug, Serialize)]
pub struct ObjectScore {
    pub name: String,
    pub iou3d: f64,
    pub miou2d: f64,
    pub accuracy2d: f64,
    pub ap2d: f64,
    pub voxels_predicted: usize,
    pub voxels_true: usize,
    pub timings: Timings,
}

#[derive(Clone, Debug, Serialize)]
pub struct DemoReport {
    pub scene: String,
    pub resolution: usize,
    pub objects: Vec<ObjectScore>,
    pub mean_iou3d: f64,
    pub min_iou3d: f64,
    pub mean_miou2d: f64,
}

/// The built-in stroke of a demo object, if it has one at this resolution.
pub fn demo_stroke(scene: &DemoScene, object: &str) -> Option<Stroke> {
    let o = scene.object(object)?;
    let px = scene.stroke_pixels(o);
    (!px.is_empty()).then(|| Stroke {
        camera: scene.stroke_camera,
        points: px
            .iter()
            .map(|p| Vec2::new(p[0] as f32 + 0.5, p[1] as f32 + 0.5))
            .collect(),
        radius: STROKE_RADIUS,
        polarity: Polarity::Positive,
        object: o.name.clone(),
        joined: true,
    })
}

/// 2D scores of predicted vs true bitmaps on a set of views, all objects in
/// one render per view (probes). Returns per object (mIoU, accuracy, AP),
/// averaged over the views where the object is visible in either mask.
pub fn masks_2d(
    field: &Arc<Field>,
    views: &[Camera],
    pairs: &[(Arc<Bitmap>, Arc<Bitmap>)],
) -> Result<Vec<(f64, f64, f64)>> {
    let scene = Scene::single(field.clone());
    let mut probes = vec![];
    for (pred, gt) in pairs {
        probes.push(Probe {
            layer: 0,
            mask: pred.clone(),
        });
        probes.push(Probe {
            layer: 0,
            mask: gt.clone(),
        });
    }
    let opts = RenderOptions {
        probes,
        depth: false,
        ..Default::default()
    };
    let mut acc = vec![(0.0, 0.0, 0.0, 0usize); pairs.len()];
    for cam in views {
        let f = render(&scene, cam, &opts)?;
        let n = (f.width * f.height) as usize;
        for (k, a) in acc.iter_mut().enumerate() {
            let soft = &f.out.probe_opacity[2 * k * n..(2 * k + 1) * n];
            let gt: Vec<bool> = f.out.probe_opacity[(2 * k + 1) * n..(2 * k + 2) * n]
                .iter()
                .map(|&v| v > 0.1)
                .collect();
            let pred: Vec<bool> = soft.iter().map(|&v| v > 0.1).collect();
            let c = Confusion::of(&pred, &gt);
            if c.tp + c.fp + c.fn_ == 0 {
                continue; // not visible in this view
            }
            a.0 += c.iou();
            a.1 += c.accuracy();
            a.2 += average_precision(soft, &gt);
            a.3 += 1;
        }
    }
    Ok(acc
        .into_iter()
        .map(|(i, c, p, n)| {
            if n == 0 {
                (1.0, 1.0, 1.0)
            } else {
                (i / n as f64, c / n as f64, p / n as f64)
            }
        })
        .collect())
}

/// Ground truth of a label restricted to the voxels a segmentation can select.
fn true_bitmap(scene: &DemoScene, cache: &FeatureCache, label: u8) -> Result<Bitmap> {
    let mut gt = scene.labels.mask(label);
    gt.intersect_with(cache.index.bits())?;
    Ok(gt)
}

/// Segments every demo object from its built-in stroke and scores it.
/// `downscale` reduces the held-out views' resolution for the 2D scores.
pub fn evaluate_demo(scene: &DemoScene, params: &SegmentParams, downscale: u32) -> Result<DemoReport> {
    let field = Arc::new(scene.field.clone());
    let cache = field.feature_cache()?;
    let render_scene = Scene::single(field.clone());
    let mut scored = vec![];
    let mut pairs = vec![];
    for o in &scene.objects {
        let Some(stroke) = demo_stroke(scene, &o.name) else {
            continue;
        };
        let (region, timings) = object_from_stroke(&render_scene, &cache, &stroke, params)?;
        let gt = true_bitmap(scene, &cache, o.label)?;
        let score = ObjectScore {
            name: o.name.clone(),
            iou3d: iou3d(&region, &gt)?,
            miou2d: 0.0,
            accuracy2d: 0.0,
            ap2d: 0.0,
            voxels_predicted: region.count(),
            voxels_true: gt.count(),
            timings,
        };
        scored.push(score);
        pairs.push((Arc::new(region), Arc::new(gt)));
    }
    if scored.is_empty() {
        return Err(Error::invalid(format!(
            "no object of '{}' has a stroke at this resolution",
            scene.name
        )));
    }
    let views: Vec<Camera> = scene
        .eval_cameras
        .frames
        .iter()
        .map(|f| f.camera.downscaled(downscale))
        .collect();
    for (s, (i, a, p)) in scored.iter_mut().zip(masks_2d(&field, &views, &pairs)?) {
        s.miou2d = i;
        s.accuracy2d = a;
        s.ap2d = p;
    }
    let n = scored.len() as f64;
    Ok(DemoReport {
        scene: scene.name.clone(),
        resolution: field.res()[0],
        mean_iou3d: scored.iter().map(|s| s.iou3d).sum::<f64>() / n,
        min_iou3d: scored.iter().map(|s| s.iou3d).fold(f64::INFINITY, f64::min),
        mean_miou2d: scored.iter().map(|s| s.miou2d).sum::<f64>() / n,
        objects: scored,
    })
}

/// One row of the feature-matching ablation.
#[derive(Clone, Debug, Serialize)]
pub struct AblationRow {
    pub matching: String,
    pub growth: bool,
    pub mean_iou3d: f64,
    pub min_iou3d: f64,
    pub mean_miou2d: f64,
}

/// Average matching (K = 1) vs plain NNFM (K = every stroke pixel) vs
/// K-means + NNFM (K = 10), each without and with growth to convergence.
pub fn ablation(scene: &DemoScene, base: &SegmentParams, downscale: u32) -> Result<Vec<AblationRow>> {
    use crate::segment::Growth;
    let mut rows = vec![];
    for (name, k) in [
        ("average (K=1)", 1),
        ("plain NNFM (K=all)", 100_000),
        ("K-means + NNFM (K=10)", 10),
    ] {
        for grow in [false, true] {
            let p = SegmentParams {
                k,
                growth: if grow { Growth::Converge } else { Growth::Steps(0) },
                ..*base
            };
            let r = evaluate_demo(scene, &p, downscale)?;
            rows.push(AblationRow {
                matching: name.into(),
                growth: grow,
                mean_iou3d: r.mean_iou3d,
                min_iou3d: r.min_iou3d,
                mean_miou2d: r.mean_miou2d,
            });
        }
    }
    Ok(rows)
}

#[derive(Clone, Debug, Serialize)]
pub struct NvosReport {
    pub scene: String,
    pub reference: String,
    pub target: String,
    pub positive_scribbles: usize,
    pub negative_scribbles: usize,
    pub iou: f64,
    pub accuracy: f64,
    pub ap: f64,
    /// IoU when a pixel counts as the object from a larger share of what
    /// it shows (0.1 is `iou`; 0.5: the object is most of the pixel): how
    /// much of the error is a faint halo rather than wrong voxels.
    pub iou_by_share: Vec<(f32, f64)>,
    /// IoU over the pixels farther than r pixels from the ground truth's
    /// edge ([`edge_band`]), for r = 1 and 2: how much of the error is the
    /// outline (a blurred field's and a hand-drawn or thresholded mask's
    /// least certain pixels) rather than whole parts.
    pub iou_beyond_edge: Vec<(usize, f64)>,
    pub oracles: NvosOracles,
    /// The pixel counts behind `iou` and `accuracy`: right (`tp`), false
    /// (`fp`), missed (`fn`) and rightly left out (`tn`).
    pub pixels: Confusion,
    pub voxels: usize,
    /// The predicted mask on the target view (row-major, mask size), for
    /// `isrf eval --mask-out`.
    #[serde(skip)]
    pub predicted: Vec<bool>,
    /// The ground truth and the field's colour on the target view (the
    /// same pixels), for `isrf eval --errors-out` ([`error_overlay`]).
    #[serde(skip)]
    pub truth: Vec<bool>,
    #[serde(skip)]
    pub render: Vec<glam::Vec3>,
    #[serde(skip)]
    pub size: [u32; 2],
    /// The selection itself, for `isrf eval --object-out`.
    #[serde(skip)]
    pub mask: Bitmap,
}

/// Yardsticks that split a score into the selection's share and the
/// field's: the IoU of two selections that know the ground truth (so they
/// are oracles, not segmentations), rendered and scored as the selection is.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct NvosOracles {
    /// The selection less its voxels whose centres project outside the
    /// truth: what it would score with nothing wrongly taken.
    pub selection_inside_truth: f64,
    /// Every solid voxel whose centre projects inside the truth
    /// ([`silhouette_voxels`]): about what a selection that is right
    /// voxel by voxel scores on this field. What it misses is the field's
    /// geometry (a blurred or misplaced outline; voxels larger than pixels
    /// spill past it) or the truth's own errors. It is not a strict bound:
    /// leaving out an outline voxel whose centre is inside may score higher.
    pub silhouette: f64,
}

/// An RGB8 picture of where a predicted mask goes wrong: the field's colour
/// `render` at a third of its brightness, false pixels (`pred` but not
/// `truth`) red and missed ones blue; right pixels keep the dimmed colour,
/// selected ones a little brighter, so the outline of the selection shows.
pub fn error_overlay(render: &[glam::Vec3], pred: &[bool], truth: &[bool]) -> Vec<u8> {
    let byte = |c: glam::Vec3| (c * 255.0).round().to_array().map(|v| v as u8);
    render
        .iter()
        .map(|c| c.clamp(glam::Vec3::ZERO, glam::Vec3::ONE))
        .zip(pred.iter().zip(truth))
        .flat_map(|(c, (&p, &t))| match (p, t) {
            (true, false) => [255, 0, 0],
            (false, true) => [0, 96, 255],
            (true, true) => byte(c * 0.6),
            (false, false) => byte(c * 0.3),
        })
        .collect()
}

fn frame_camera(cams: &CameraSet, name: &str) -> Result<Camera> {
    cams.frames
        .iter()
        .find(|f| f.base_name() == name)
        .map(|f| f.camera)
        .ok_or_else(|| Error::invalid(format!("no camera frame named '{name}' in the camera set")))
}

/// The camera resized to an image's size (NVOS scribbles and masks are at a
/// downsampled resolution).
fn camera_at(cam: Camera, w: u32, h: u32) -> Camera {
    let mut c = cam;
    let k = &mut c.intrinsics;
    let (sx, sy) = (w as f32 / k.width as f32, h as f32 / k.height as f32);
    *k = crate::camera::Intrinsics {
        width: w,
        height: h,
        fx: k.fx * sx,
        fy: k.fy * sy,
        cx: k.cx * sx,
        cy: k.cy * sy,
    };
    c
}

/// Files in `dir` whose names start with `prefix` and end with `suffix`, sorted.
fn list_files(dir: &Path, prefix: &str, suffix: &str) -> Result<Vec<std::path::PathBuf>> {
    let rd = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut v: Vec<_> = rd
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with(prefix) && n.ends_with(suffix))
        })
        .collect();
    v.sort();
    Ok(v)
}

/// NVOS protocol for one scene: scribbles on the reference view segment the
/// field; the target view's predicted mask is scored against the given mask.
/// `reference`/`target` are frame base names in `cams` (default: the NVOS
/// file stems).
pub fn evaluate_nvos(
    field: Arc<Field>,
    cams: &CameraSet,
    root: &Path,
    scene_name: &str,
    reference: Option<&str>,
    target: Option<&str>,
    params: &SegmentParams,
) -> Result<NvosReport> {
    // The reference view is named by --reference-view or by the one file in
    // reference_image/<scene>/ (the image itself is not needed).
    let ref_stem = match reference {
        Some(r) => r.to_string(),
        None => {
            let ref_dir = root.join("reference_image").join(scene_name);
            let ref_img = list_files(&ref_dir, "", "")?.into_iter().next();
            let ref_img =
                ref_img.ok_or_else(|| Error::invalid(format!("{}: no reference image", ref_dir.display())))?;
            ref_img.file_stem().unwrap_or_default().to_string_lossy().into_owned()
        }
    };
    let mask_path = list_files(&root.join("masks").join(scene_name), "", "_mask.png")?
        .into_iter()
        .next()
        .ok_or_else(|| Error::invalid(format!("no masks/{scene_name}/*_mask.png")))?;
    let target_stem = mask_path
        .file_name()
        .unwrap()
        .to_string_lossy()
        .trim_end_matches("_mask.png")
        .to_string();
    let ref_cam = frame_camera(cams, &ref_stem)?;
    let target_cam = frame_camera(cams, target.unwrap_or(&target_stem))?;
    let scrib = root.join("scribbles").join(scene_name);
    let pos = list_files(&scrib, "pos", ".png")?;
    let neg = list_files(&scrib, "neg", ".png")?;
    if pos.is_empty() {
        return Err(Error::invalid(format!("{}: no pos_*.png scribbles", scrib.display())));
    }
    let cache = field.feature_cache()?;
    let scene = Scene::single(field.clone());
    let mut builder = MaskBuilder::new(Bitmap::new(field.res()));
    for (paths, pol) in [(&pos, Polarity::Positive), (&neg, Polarity::Negative)] {
        for p in paths {
            let (w, h) = image::image_dimensions(p).map_err(|e| Error::bad_file(p, e.to_string()))?;
            let stroke = scribble_stroke(p, camera_at(ref_cam, w, h), pol, scene_name)?;
            builder.stroke(&scene, &cache, &stroke, pol, params)?;
        }
    }
    let mask = builder.mask;
    let gt_img = crate::data::open_image(&mask_path, None)?.to_luma8();
    let gt: Vec<bool> = gt_img.pixels().map(|p| p.0[0] > 127).collect();
    let size = [gt_img.width(), gt_img.height()];
    let cam = camera_at(target_cam, size[0], size[1]);
    // The selection and the two oracles of `NvosReport::oracles`, in one render.
    let silhouette = silhouette_voxels(&cache, params.sigma_floor(cache.voxel_size), &cam, &gt, size);
    let mut inside = mask.clone();
    inside.intersect_with(&silhouette)?;
    let probe = |m: Bitmap| Probe {
        layer: 0,
        mask: Arc::new(m),
    };
    let opts = RenderOptions {
        probes: vec![probe(mask.clone()), probe(inside), probe(silhouette)],
        depth: false,
        ..Default::default()
    };
    let f = render(&scene, &cam, &opts)?;
    let n = gt.len();
    let above = |opacity: &[f32], s: f32| -> Vec<bool> { opacity.iter().map(|&v| v > s).collect() };
    let shown = |k: usize| above(&f.out.probe_opacity[k * n..(k + 1) * n], 0.1);
    let opacity = &f.out.probe_opacity[..n];
    let pred = shown(0);
    let c = Confusion::of(&pred, &gt);
    let oracles = NvosOracles {
        selection_inside_truth: Confusion::of(&shown(1), &gt).iou(),
        silhouette: Confusion::of(&shown(2), &gt).iou(),
    };
    Ok(NvosReport {
        scene: scene_name.into(),
        reference: ref_stem,
        target: target_stem,
        positive_scribbles: pos.len(),
        negative_scribbles: neg.len(),
        iou: c.iou(),
        accuracy: c.accuracy(),
        ap: average_precision(opacity, &gt),
        iou_by_share: [0.1f32, 0.3, 0.5, 0.7]
            .iter()
            .map(|&s| (s, Confusion::of(&above(opacity, s), &gt).iou()))
            .collect(),
        iou_beyond_edge: [1, 2]
            .iter()
            .map(|&r| {
                let band = edge_band(&gt, size[0] as usize, size[1] as usize, r);
                (r, Confusion::outside(&pred, &gt, &band).iou())
            })
            .collect(),
        oracles,
        pixels: c,
        voxels: mask.count(),
        mask,
        predicted: pred,
        truth: gt,
        render: f.out.color,
        size,
    })
}

/// The solid voxels (σ above `floor`) of `cache` whose centres project
/// inside `truth` (row-major, `size` pixels) on `cam`, whatever lies behind
/// them: a selection that knows the truth of this one view
/// ([`NvosOracles::silhouette`]).
pub fn silhouette_voxels(cache: &FeatureCache, floor: f32, cam: &Camera, truth: &[bool], size: [u32; 2]) -> Bitmap {
    let [w, h] = size.map(|s| s as f32);
    let inside = |v: u32| {
        cam.project(cache.geom.point_of(v as usize)).is_some_and(|(px, _)| {
            px.x >= 0.0
                && px.y >= 0.0
                && px.x < w
                && px.y < h
                && truth[px.y as usize * size[0] as usize + px.x as usize]
        })
    };
    let kept: Vec<u32> = (cache.voxels.par_iter().zip(&cache.sigma))
        .filter(|&(&v, &s)| s > floor && inside(v))
        .map(|(&v, _)| v)
        .collect();
    Bitmap::from_ones(cache.geom.res, &kept)
}

/// IoU of a segmented object's rendered mask with the true foreground
/// alpha of held-out views (NeRF-synthetic scenes have exact alpha).
#[derive(Clone, Debug, Serialize)]
pub struct AlphaReport {
    pub views: Vec<String>,
    pub iou: Vec<f64>,
    pub mean_iou: f64,
    pub min_iou: f64,
    pub accuracy: f64,
}

/// Renders the object opacity of `object` (a bitmap of `field`) from every
/// view in `views` (camera, alpha, name) and scores `opacity > 0.5` against
/// `alpha > 0.5`.
pub fn evaluate_alpha(
    field: Arc<Field>,
    object: Arc<Bitmap>,
    views: &[(Camera, &[f32], String)],
) -> Result<AlphaReport> {
    crate::ensure!(!views.is_empty(), "no views with alpha to evaluate on");
    crate::ensure!(
        object.res() == field.res(),
        "object bitmap {:?} does not match the field's grid {:?}",
        object.res(),
        field.res()
    );
    let scene = Scene::single(field);
    let opts = RenderOptions {
        probes: vec![Probe { layer: 0, mask: object }],
        depth: false,
        ..Default::default()
    };
    let (mut iou, mut acc) = (vec![], 0.0);
    for (cam, alpha, _) in views {
        let f = render(&scene, cam, &opts)?;
        crate::ensure!(
            alpha.len() == f.out.probe_opacity.len(),
            "alpha has {} pixels, the camera {}",
            alpha.len(),
            f.out.probe_opacity.len()
        );
        let pred: Vec<bool> = f.out.probe_opacity.iter().map(|&v| v > 0.5).collect();
        let gt: Vec<bool> = alpha.iter().map(|&v| v > 0.5).collect();
        let c = Confusion::of(&pred, &gt);
        iou.push(c.iou());
        acc += c.accuracy();
    }
    let n = iou.len() as f64;
    Ok(AlphaReport {
        views: views.iter().map(|v| v.2.clone()).collect(),
        mean_iou: iou.iter().sum::<f64>() / n,
        min_iou: iou.iter().copied().fold(f64::INFINITY, f64::min),
        accuracy: acc / n,
        iou,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn the_error_overlay_paints_false_pixels_red_and_missed_ones_blue() {
        let grey = Vec3::splat(0.5);
        let render = [grey, grey, grey, Vec3::ONE];
        let pred = [true, false, true, false];
        let truth = [false, true, true, false];
        let rgb = error_overlay(&render, &pred, &truth);
        assert_eq!(
            rgb,
            [[255, 0, 0], [0, 96, 255], [77, 77, 77], [77, 77, 77]].concat(),
            "false, missed, right and selected (0.5 × 0.6), right and not (1 × 0.3)"
        );
        // Colours past [0, 1] (a render's background) are clamped, not wrapped.
        assert_eq!(error_overlay(&[Vec3::splat(9.0)], &[true], &[true]), [153, 153, 153]);
    }

    #[test]
    fn the_silhouette_oracle_takes_what_projects_inside_the_truth_and_nothing_else() {
        let scene = crate::demo::build("tabletop", 48, 0).unwrap();
        let cache = scene.field.feature_cache().unwrap();
        let cam = scene.cameras.frames[3].camera;
        let k = cam.intrinsics;
        let size = [k.width, k.height];
        let floor = SegmentParams::default().sigma_floor(cache.voxel_size);
        let solid = cache.solid(floor);
        let of = |name: &str| {
            let mut m = scene.labels.mask(scene.labels.label_of(name).unwrap());
            m.intersect_with(&solid).unwrap();
            m
        };
        // Where the ball shows on this view (any of its light), as a mask.
        let opts = RenderOptions {
            probes: vec![Probe {
                layer: 0,
                mask: Arc::new(of("ball")),
            }],
            depth: false,
            ..Default::default()
        };
        let shown = render(&Scene::single(Arc::new(scene.field.clone())), &cam, &opts).unwrap();
        let truth: Vec<bool> = shown.out.probe_opacity.iter().map(|&v| v > 0.0).collect();
        assert!(truth.iter().any(|&t| t), "the ball is in view");

        let none = silhouette_voxels(&cache, floor, &cam, &vec![false; truth.len()], size);
        assert_eq!(none.count(), 0, "an empty truth takes nothing");

        let inside = silhouette_voxels(&cache, floor, &cam, &truth, size);
        let ball = of("ball");
        // (Not all of them: a few are hidden on this view, so not in the truth.)
        let taken = inside.intersection_count(&ball).unwrap();
        assert!(taken * 10 >= ball.count() * 9, "{taken} of the ball's {}", ball.count());
        // The floor under the ball is taken only where the ball covers it.
        let floor_voxels = of("floor");
        let taken = inside.intersection_count(&floor_voxels).unwrap();
        assert!(
            taken > 0 && taken * 20 < floor_voxels.count(),
            "{taken} of the floor's {}",
            floor_voxels.count()
        );
        // Each taken voxel projects inside the truth, each other solid one outside it.
        for v in solid.ones() {
            let px = cam.project(cache.geom.point_of(v)).map(|(p, _)| p);
            let on_truth = px.is_some_and(|p| {
                (0.0..size[0] as f32).contains(&p.x)
                    && (0.0..size[1] as f32).contains(&p.y)
                    && truth[p.y as usize * size[0] as usize + p.x as usize]
            });
            assert_eq!(inside.get(v), on_truth, "voxel {v} at {px:?}");
        }
    }
}
