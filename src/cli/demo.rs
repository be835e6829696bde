use anyhow::{Context, Result};
use isrf::demo;
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args)]
pub struct Args {
    /// Output folder; each scene is written to DIR/<scene>/
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Scene to build: tabletop, shelf or all
    #[arg(long, default_value = "tabletop")]
    pub scene: String,
    /// Grid points per axis (16..=512): N for N³, or NXxNYxNZ
    #[arg(long, default_value_t = demo::DEFAULT_RES.to_string(), value_parser = parse_res)]
    pub res: String,
    /// Seed for textures, plant leaves and feature noise
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// `N` or `NXxNYxNZ` (checked against the demo's range when built).
fn parse_res(s: &str) -> std::result::Result<String, String> {
    res_of(s).map(|_| s.to_string())
}

fn res_of(s: &str) -> std::result::Result<[usize; 3], String> {
    let parts: Vec<&str> = s.split(['x', 'X']).collect();
    let nums: Vec<usize> = parts
        .iter()
        .map(|p| p.trim().parse::<usize>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| format!("resolution '{s}' is not N or NXxNYxNZ"))?;
    match nums[..] {
        [n] => Ok([n; 3]),
        [x, y, z] => Ok([x, y, z]),
        _ => Err(format!("resolution '{s}' is not N or NXxNYxNZ")),
    }
}

pub fn run(a: Args) -> Result<()> {
    let res = res_of(&a.res).map_err(anyhow::Error::msg)?;
    let scenes: Vec<&str> = match a.scene.as_str() {
        "all" => demo::names().to_vec(),
        s => vec![s],
    };
    for name in scenes {
        let start = Instant::now();
        let scene = demo::build_grid(name, res, a.seed)?;
        let built = start.elapsed().as_secs_f64();
        let dir = a.out.join(name);
        let paths = scene
            .write(&dir)
            .with_context(|| format!("writing demo scene '{name}' to {}", dir.display()))?;
        let total = scene.labels.data.len();
        let occupied = scene.occupied();
        println!(
            "{name}: {}x{}x{}, {occupied} occupied voxels ({:.2} %), {} objects, built in {built:.2} s, written in {:.2} s",
            res[0],
            res[1],
            res[2],
            100.0 * occupied as f64 / total as f64,
            scene.objects.len(),
            start.elapsed().as_secs_f64() - built,
        );
        let counts = scene.labels.counts();
        let objects: Vec<String> = scene
            .objects
            .iter()
            .map(|o| format!("{} {}", o.name, counts[o.label as usize]))
            .collect();
        println!("  voxels per object: {}", objects.join(", "));
        let strokeless: Vec<&str> = scene
            .objects
            .iter()
            .filter(|o| o.stroke.is_empty())
            .map(|o| o.name.as_str())
            .collect();
        if !strokeless.is_empty() {
            println!(
                "  no visible stroke at this resolution for: {} (left out of strokes.json)",
                strokeless.join(", ")
            );
        }
        for p in paths {
            let len = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(0);
            println!("  {:<48} {:>8.2} MB", p.display(), len as f64 / 1e6);
        }
    }
    Ok(())
}
