//! `isrf export-splats FIELD --out FILE.ply [--object BITMAP [--complement]]`:
//! a field, an object or the scene without it as a 3D Gaussian splat file.
//! For a field imported from a `.ply` the records are the file's own, byte
//! for byte; other fields give one Gaussian per occupied grid point.

use anyhow::Result;
use isrf::field::Field;
use isrf::segment::bitmap_file::load_bitmap;
use isrf::splat::export::{export, Selection};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Field file (.safetensors).
    pub field: PathBuf,
    /// Output splat file (.ply).
    #[arg(long)]
    pub out: PathBuf,
    /// An object's bitmap over the field (.safetensors, as `isrf segment` writes).
    #[arg(long)]
    pub object: Option<PathBuf>,
    /// Everything but the object.
    #[arg(long, requires = "object")]
    pub complement: bool,
}

pub fn run(a: Args) -> Result<()> {
    let field = Field::load(&a.field)?;
    let bits = a.object.as_deref().map(load_bitmap).transpose()?.map(|(b, _)| b);
    let sel = Selection {
        bits: bits.as_ref(),
        complement: a.complement,
        ..Selection::whole()
    };
    let r = export(&field, &sel, &a.out)?;
    let what = if r.from_source {
        "records of the source file"
    } else {
        "occupied grid points"
    };
    eprintln!("wrote {} of {} {what} to {}", r.written, r.total, a.out.display());
    Ok(())
}
