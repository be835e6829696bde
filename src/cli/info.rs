use anyhow::Result;
use isrf::field::{io, Appearance, Features, Field, Layout};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Field file (.safetensors)
    pub field: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    let field = Field::load(&a.field)?;
    let len = std::fs::metadata(&a.field)?.len();
    let (header, _) = io::read_header(&a.field)?;
    let g = field.geom();
    let b = g.bounds;
    println!("{}", a.field.display());
    let (meta, _) = io::read_metadata(&a.field)?;
    println!(
        "  format      isrf-field v{}  ({:.1} MB on disk)",
        meta.get("version").map_or("?", String::as_str),
        len as f64 / 1e6
    );
    println!(
        "  bounds      [{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}]",
        b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z
    );
    println!(
        "  resolution  {} x {} x {}  ({} grid points, spacing {:.4})",
        g.res[0],
        g.res[1],
        g.res[2],
        g.len(),
        g.spacing().x
    );
    println!("  activation  {}", serde_json::to_string(&header.activation)?);
    let density = match (header.sparse_density(), header.occupied) {
        (true, Some(n)) => format!(
            "f32, sparse ({n} points stored, {:.2} %)",
            100.0 * n as f64 / g.len() as f64
        ),
        _ => "f32, dense".to_string(),
    };
    println!("  density     {density}");
    let layout = |l: &Layout| if matches!(l, Layout::Dense) { "dense" } else { "sparse" };
    let app = match &field.appearance {
        Appearance::Rgb(c) => format!("rgb, {} {:?}", layout(&c.layout), c.geom.res),
        Appearance::Sh2(c) => format!("sh degree 2, {} {:?}", layout(&c.layout), c.geom.res),
        Appearance::Vm { grid, mlp } => format!(
            "vm {:?} components at {:?} -> {} channels, mlp {} layers",
            grid.comps,
            grid.geom.res,
            grid.out,
            mlp.layers.len()
        ),
    };
    println!("  appearance  {app}");
    let feat = match &field.features {
        Some(Features::Grid(c)) => format!("{} channels, {} {:?}", c.channels, layout(&c.layout), c.geom.res),
        Some(Features::Vm(v)) => format!("vm {:?} components at {:?} -> {} channels", v.comps, v.geom.res, v.out),
        None => "none".into(),
    };
    println!("  features    {feat}");
    let occupied = (0..g.len())
        .filter(|&i| field.density.sigma_at(i) > isrf::field::cache::OCCUPIED_FLOOR)
        .count();
    println!(
        "  occupancy   {} voxels with sigma > {} ({:.2} %)",
        occupied,
        isrf::field::cache::OCCUPIED_FLOOR,
        100.0 * occupied as f64 / g.len() as f64
    );
    println!("  memory      {:.1} MB", field.memory_bytes() as f64 / 1e6);
    // What the file stores against the same field with every grid dense.
    let stored = io::data_section_bytes(&a.field)?;
    let dense = io::tensor_bytes(&header, true);
    println!(
        "  stored: {stored} bytes of tensors ({:.1} MB; file {len} bytes)",
        stored as f64 / 1e6
    );
    println!(
        "  dense equivalent: {dense} bytes ({:.1} MB; {:.1}x the stored size)",
        dense as f64 / 1e6,
        dense as f64 / stored.max(1) as f64
    );
    Ok(())
}
