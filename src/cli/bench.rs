//! `isrf bench <what>`: measured figures printed as tables (never timed
//! asserts). Each kind of benchmark is one variant of [`What`]; add new ones
//! there with their own argument struct and `run_*` function.

use anyhow::{bail, Result};
use isrf::bench::render::{bench_render, build_table, render_table};
use isrf::bench::segment::{bench_segment, stage_table, summary, SegmentBenchConfig};

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    pub what: What,
}

#[derive(clap::Subcommand)]
pub enum What {
    /// Rays per second of the CPU reference renderer on a demo scene.
    Render(RenderArgs),
    /// Per-stage times of stroke -> mask, against the dense reference implementation.
    Segment(SegmentArgs),
    /// Frames per second of the editor's GPU view (needs the `editor` feature).
    Editor(super::edit::BenchArgs),
}

pub fn run(a: Args) -> Result<()> {
    match a.what {
        What::Render(a) => run_render(a),
        What::Segment(a) => run_segment(a),
        What::Editor(a) => super::edit::bench(a),
    }
}

#[derive(clap::Args)]
pub struct RenderArgs {
    /// Grid resolutions to measure, comma separated; the last line reports the largest.
    #[arg(long, value_delimiter = ',', default_values_t = [128, 320])]
    pub res: Vec<usize>,
    /// Demo scene.
    #[arg(long, default_value = "tabletop")]
    pub scene: String,
    /// Image width in pixels.
    #[arg(long, default_value_t = 400)]
    pub width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 300)]
    pub height: u32,
    /// Orbit cameras rendered per measurement (spread over the orbit).
    #[arg(long, default_value_t = 4)]
    pub frames: usize,
}

#[derive(clap::Args)]
pub struct SegmentArgs {
    /// Grid resolutions to measure, comma separated; the last line reports the largest.
    #[arg(long, value_delimiter = ',', default_values_t = [128, 320])]
    pub res: Vec<usize>,
    /// Demo scene.
    #[arg(long, default_value = "tabletop")]
    pub scene: String,
    /// Object whose built-in stroke is segmented.
    #[arg(long, default_value = "pot")]
    pub object: String,
    /// Runs per stage; the median is reported (slow stages stop after ~10 s of runs).
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// Skip the dense reference (it needs res^3 x channels x 4 bytes of memory).
    #[arg(long)]
    pub no_dense: bool,
}

fn check_res(res: &[usize]) -> Result<usize> {
    match res.iter().max() {
        Some(&m) => Ok(m),
        None => bail!("--res needs at least one resolution"),
    }
}

fn run_render(a: RenderArgs) -> Result<()> {
    let largest = check_res(&a.res)?;
    println!(
        "CPU reference renderer, {} demo scene, {}x{} pixels, {} orbit cameras, {} rayon threads",
        a.scene,
        a.width,
        a.height,
        a.frames,
        rayon::current_num_threads()
    );
    let mut rows = vec![];
    for &res in &a.res {
        eprintln!("building {} at {res}^3 and rendering ...", a.scene);
        rows.push(bench_render(&a.scene, res, a.width, a.height, a.frames)?);
    }
    println!("\none-off per field (the renderer needs the macro grid; segmentation the cache):");
    print!("{}", build_table(&rows));
    println!("\nrendering (colour + depth; +feat: also the semantic features), after one warm-up frame:");
    print!("{}", render_table(&rows));
    let last = rows
        .iter()
        .rev()
        .find(|r| r.res == largest)
        .expect("measured every resolution");
    if let Some(l) = last.load_average {
        println!("load average {l:.2} at the start: wall times include waiting for other processes, cpu times do not");
    }
    println!("rays/s: {:.0}", last.plain.rays_per_s);
    Ok(())
}

fn run_segment(a: SegmentArgs) -> Result<()> {
    let largest = check_res(&a.res)?;
    println!(
        "stroke -> mask, {} demo scene, object '{}', {} rayon threads, median of up to {} runs per stage",
        a.scene,
        a.object,
        rayon::current_num_threads(),
        a.repeats
    );
    println!(
        "stroke-to-mask = stroke features + k-means + nnfm + growth to convergence, per-field caches already built"
    );
    let mut last = None;
    for &res in &a.res {
        eprintln!("building {} at {res}^3 and segmenting ...", a.scene);
        let cfg = SegmentBenchConfig {
            scene: a.scene.clone(),
            object: a.object.clone(),
            repeats: a.repeats,
            dense: !a.no_dense,
            ..SegmentBenchConfig::new(res)
        };
        let r = bench_segment(&cfg)?;
        println!();
        for line in summary(&r) {
            println!("{line}");
        }
        print!("{}", stage_table(&r));
        if res == largest {
            last = Some(r);
        }
    }
    let r = last.expect("measured every resolution");
    let speedup = r.speedup().map_or_else(|| "n/a".into(), |s| format!("{s:.1}x"));
    println!(
        "stroke-to-mask ms at {}^3: {:.1}, speed-up over dense: {speedup}",
        r.config.res,
        r.stroke_to_mask_ms()
    );
    Ok(())
}
