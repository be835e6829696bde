//! `isrf import SCENE.ply --out FIELD.safetensors [--res N]`: a 3D Gaussian
//! splat file to a field (see `isrf::splat::import` for the mapping).

use anyhow::Result;
use isrf::splat::{import_file, ImportOptions};
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args)]
pub struct Args {
    /// 3D Gaussian splat file (.ply, INRIA layout, binary little-endian).
    pub ply: PathBuf,
    /// Output field file (.safetensors).
    #[arg(long)]
    pub out: PathBuf,
    /// Grid points along the longest axis (default: from the splat sizes, at most 512).
    #[arg(long)]
    pub res: Option<usize>,
    /// Most grid points in all (memory: 4 bytes each for density).
    #[arg(long, default_value_t = isrf::splat::import::DEFAULT_MAX_POINTS)]
    pub max_points: usize,
    /// The scene's up direction in the splats' frame, `X,Y,Z` (e.g.
    /// `0,-1,0` for captures left in COLMAP's frame): a splat file does not
    /// say, and segmentation uses it to keep the ground off what stands on
    /// it (`isrf info` shows it).
    #[arg(long, value_parser = parse_up, allow_hyphen_values = true)]
    pub up: Option<glam::Vec3>,
}

/// `X,Y,Z`: three finite numbers, not all zero.
fn parse_up(s: &str) -> Result<glam::Vec3, String> {
    let parts: Vec<f32> = s
        .split(',')
        .map(|p| p.trim().parse::<f32>().map_err(|e| format!("'{p}': {e}")))
        .collect::<Result<_, _>>()?;
    match parts[..] {
        [x, y, z] if [x, y, z].iter().all(|v| v.is_finite()) && (x, y, z) != (0.0, 0.0, 0.0) => {
            Ok(glam::Vec3::new(x, y, z).normalize())
        }
        _ => Err(format!(
            "'{s}' is not a direction X,Y,Z (three finite numbers, not all zero)"
        )),
    }
}

pub fn run(a: Args) -> Result<()> {
    let t0 = Instant::now();
    let opts = ImportOptions {
        res: a.res,
        max_points: a.max_points,
    };
    let (mut field, r) = import_file(&a.ply, &opts)?;
    field.up = a.up;
    let secs = t0.elapsed().as_secs_f64();
    field.save(&a.out)?;
    let b = r.bounds;
    eprintln!(
        "{} Gaussians (SH degree {}): {} in the field, {} floaters outside the bounds, {} with non-finite values",
        r.gaussians, r.sh_degree, r.used, r.outside, r.non_finite
    );
    eprintln!(
        "bounds [{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}], grid {} x {} x {}, {} occupied points",
        b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z, r.res[0], r.res[1], r.res[2], r.occupied
    );
    eprintln!("imported in {secs:.2} s; wrote {}", a.out.display());
    Ok(())
}
