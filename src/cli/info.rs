use anyhow::Result;
use isrf::field::{io, Appearance, Features, Field, Layout};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Field file (.safetensors), or a composition (.json / .ron)
    pub field: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    if isrf::command::script::Format::of(&a.field).is_ok() {
        return composition(&a.field);
    }
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
    match field.up {
        Some(u) => println!("  up          [{:.3}, {:.3}, {:.3}]", u.x, u.y, u.z),
        None => println!("  up          unknown (segmentation keeps the ground an object stands on)"),
    }
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

/// A composition's fields and objects, opened (and so checked: field
/// files against their recorded CRC, bitmaps against their fields) as
/// `isrf edit` opens it.
fn composition(path: &std::path::Path) -> Result<()> {
    let session = isrf::command::composition::load(path, &std::env::temp_dir())?;
    let st = session.state();
    println!("{}", path.display());
    println!(
        "  format      {} v{}",
        isrf::command::composition::FORMAT,
        isrf::command::composition::VERSION
    );
    println!("  background  {:?}", st.background);
    for f in &st.fields {
        let source = match &f.source {
            isrf::command::FieldSource::File(p) => p.display().to_string(),
            other => serde_json::to_string(other)?,
        };
        let res = f.field.res();
        let shown = if f.placement.visible { "" } else { ", hidden" };
        println!(
            "  field       '{}': {source}, {} x {} x {}{}{shown}",
            f.name,
            res[0],
            res[1],
            res[2],
            placement(&f.placement.transform)
        );
    }
    for o in &st.objects {
        let field = st
            .fields
            .iter()
            .find(|f| f.id == o.field)
            .map_or("?", |f| f.name.as_str());
        let p = &o.placement;
        let flags: Vec<&str> = [
            (p.removed, "removed"),
            (!p.visible, "hidden"),
            (p.duplicate, "duplicate"),
            (p.color_edit.is_some(), "colour edit"),
        ]
        .into_iter()
        .filter_map(|(on, name)| on.then_some(name))
        .collect();
        let flags = if flags.is_empty() {
            String::new()
        } else {
            format!(", {}", flags.join(", "))
        };
        println!(
            "  object      '{}' of '{field}': {} voxels{}{flags}",
            o.name,
            o.mask.count(),
            placement(&p.transform)
        );
    }
    Ok(())
}

/// A placement in words: nothing for the identity, else the translation
/// and whether it also rotates or scales.
fn placement(t: &glam::Affine3A) -> String {
    if *t == glam::Affine3A::IDENTITY {
        return String::new();
    }
    let d = t.translation;
    let linear = if t.matrix3 == glam::Mat3A::IDENTITY {
        ""
    } else {
        ", rotated / scaled"
    };
    format!(", moved by [{:.3}, {:.3}, {:.3}]{linear}", d.x, d.y, d.z)
}
