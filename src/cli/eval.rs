//! `isrf eval`: segmentation quality as JSON (demo scenes or NVOS layout).

use anyhow::{bail, Result};
use isrf::camera::CameraSet;
use isrf::eval::protocol::{ablation, evaluate_demo, evaluate_nvos};
use isrf::field::Field;
use std::path::PathBuf;
use std::sync::Arc;

#[derive(clap::Args)]
pub struct Args {
    /// Demo scene to evaluate (tabletop, shelf), from its built-in strokes.
    #[arg(long, default_value = "tabletop")]
    pub scene: String,
    #[arg(long, default_value_t = 128)]
    pub res: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Held-out views are rendered at 1/N resolution for the 2D scores.
    #[arg(long, default_value_t = 2)]
    pub downscale: u32,
    /// Print the feature-matching ablation table instead.
    #[arg(long)]
    pub ablation: bool,
    /// NVOS-layout folder (reference_image/, scribbles/, masks/): evaluate
    /// `--field` on scene `--scene` instead of a demo scene.
    #[arg(long, requires_all = ["field", "cameras"])]
    pub nvos: Option<PathBuf>,
    /// Field of the NVOS scene.
    #[arg(long)]
    pub field: Option<PathBuf>,
    /// Camera set of the NVOS scene (frames named like the NVOS images, or
    /// use --reference-view / --target-view).
    #[arg(long)]
    pub cameras: Option<PathBuf>,
    #[arg(long)]
    pub reference_view: Option<String>,
    #[arg(long)]
    pub target_view: Option<String>,
    /// Dataset with true alpha (NeRF-synthetic): score `--object`, a bitmap
    /// of `--field`, against the alpha of its val views.
    #[arg(long, requires_all = ["field", "object"])]
    pub alpha: Option<PathBuf>,
    /// With --nvos: write the predicted mask on the target view (white =
    /// selected) to this PNG.
    #[arg(long, requires = "nvos")]
    pub mask_out: Option<PathBuf>,
    /// With --nvos: write where the mask goes wrong to this PNG: the field's
    /// render of the target view, dimmed, false pixels red, missed ones blue.
    #[arg(long, requires = "nvos")]
    pub errors_out: Option<PathBuf>,
    /// With --nvos: write the selection (a 3D bitmap of `--field`, as
    /// `isrf segment` writes) to this file, to render or edit it.
    #[arg(long, requires = "nvos")]
    pub object_out: Option<PathBuf>,
    /// Object bitmap (from `isrf segment`) for --alpha.
    #[arg(long)]
    pub object: Option<PathBuf>,
    #[command(flatten)]
    pub params: super::segment::ParamArgs,
}

pub fn run(a: Args) -> Result<()> {
    let params = a.params.params()?;
    if a.downscale == 0 {
        bail!("--downscale must be at least 1");
    }
    if let Some(ds) = &a.alpha {
        return run_alpha(&a, ds);
    }
    if let Some(root) = &a.nvos {
        let cams = CameraSet::load(a.cameras.as_ref().unwrap())?;
        let field = Arc::new(Field::load(a.field.as_ref().unwrap())?.or_up_from(Some(&cams)));
        let r = evaluate_nvos(
            field,
            &cams,
            root,
            &a.scene,
            a.reference_view.as_deref(),
            a.target_view.as_deref(),
            &params,
        )?;
        if let Some(out) = &a.mask_out {
            let v = |&b: &bool| if b { 255u8 } else { 0 };
            let rgb: Vec<u8> = r.predicted.iter().flat_map(|b| [v(b); 3]).collect();
            isrf::render::save_png(out, r.size[0], r.size[1], &rgb)?;
        }
        if let Some(out) = &a.errors_out {
            let rgb = isrf::eval::protocol::error_overlay(&r.render, &r.predicted, &r.truth);
            isrf::render::save_png(out, r.size[0], r.size[1], &rgb)?;
        }
        if let Some(out) = &a.object_out {
            isrf::segment::bitmap_file::save_bitmap(out, &r.mask, &a.scene)?;
        }
        println!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    let scene = isrf::demo::build(&a.scene, a.res, a.seed)?;
    if a.ablation {
        let rows = ablation(&scene, &params, a.downscale)?;
        eprintln!(
            "{:<24} {:>7} {:>11} {:>10} {:>12}",
            "matching", "growth", "mean IoU3D", "min IoU3D", "mean mIoU2D"
        );
        for r in &rows {
            eprintln!(
                "{:<24} {:>7} {:>11.3} {:>10.3} {:>12.3}",
                r.matching,
                if r.growth { "yes" } else { "no" },
                r.mean_iou3d,
                r.min_iou3d,
                r.mean_miou2d
            );
        }
        println!("{}", serde_json::to_string_pretty(&rows)?);
        return Ok(());
    }
    let r = evaluate_demo(&scene, &params, a.downscale)?;
    println!("{}", serde_json::to_string_pretty(&r)?);
    Ok(())
}

/// `--alpha DATASET`: object masks against the val views' alpha, rendered at
/// the dataset's resolution divided by `--downscale`.
fn run_alpha(a: &Args, dataset: &std::path::Path) -> Result<()> {
    use isrf::data::{Dataset, LoadOptions, Split};
    let field = Arc::new(Field::load(a.field.as_ref().expect("clap requires --field"))?);
    let object = a.object.as_ref().expect("clap requires --object");
    let (bits, name) = isrf::segment::bitmap_file::load_bitmap(object)?;
    let opts = LoadOptions {
        downscale: a.downscale,
        splits: Some(vec![Split::Val]),
        ..Default::default()
    };
    let ds = Dataset::load(dataset, &opts)?;
    let mut views = vec![];
    for i in ds.indices(Split::Val) {
        let Some(alpha) = ds.images[i].alpha.as_deref() else {
            bail!(
                "{}: view {} has no alpha channel",
                dataset.display(),
                ds.cameras.frames[i].name
            );
        };
        views.push((ds.cameras.frames[i].camera, alpha, ds.cameras.frames[i].name.clone()));
    }
    let r = isrf::eval::protocol::evaluate_alpha(field, Arc::new(bits), &views)?;
    eprintln!(
        "object '{name}' vs alpha of {} val views: mean IoU {:.3}, min {:.3}, accuracy {:.3}",
        r.views.len(),
        r.mean_iou,
        r.min_iou,
        r.accuracy
    );
    println!("{}", serde_json::to_string_pretty(&r)?);
    Ok(())
}
