//! 3D Gaussian splat files in and out: the INRIA `.ply` reader and writer
//! ([`ply`]), import into a field ([`import`]), and export of objects and
//! fields as splats ([`export`]), with the spherical-harmonic conversions
//! they need ([`sh`]).
//!
//! An imported field remembers its file (absolute path, CRC-32, count in
//! the field header's `source`). Exporting an object of such a field writes
//! the file's own records whose centres are inside the object's bitmap (see
//! [`import::inside`] for the boundary rule), byte for byte, or their
//! complement; other fields export one Gaussian per occupied voxel.

pub mod boundary;
pub mod export;
pub mod import;
pub mod ply;
pub mod sh;
pub mod synth;

pub use import::{import_file, ImportOptions, ImportReport};
pub use ply::{Gaussian, SplatFile};

impl SplatFile {
    /// CRC-32 of the whole file (header and records), as stored in an
    /// imported field's `source`.
    pub fn crc32(&self) -> u32 {
        let mut h = crc32fast::Hasher::new();
        h.update(&self.header.text);
        h.update(&self.records);
        h.finalize()
    }
}

/// Seeds of the `splat-ply` fuzz target: small valid files of SH degree 0
/// and 3 (the committed corpus adds hand-written ones).
pub fn fuzz_seeds() -> crate::Result<Vec<Vec<u8>>> {
    let g = |x: f32, rest: usize| Gaussian {
        pos: glam::Vec3::new(x, 0.5 * x, -x),
        dc: [0.1, 0.2, 0.3],
        rest: vec![0.05; rest],
        opacity: 1.0,
        log_scale: [-2.0, -2.5, -4.0],
        rot: [1.0, 0.1, 0.0, 0.0],
    };
    [(0, 0), (3, 45)]
        .iter()
        .map(|&(degree, rest)| {
            let gs: Vec<Gaussian> = (0..4).map(|i| g(i as f32 * 0.3, rest)).collect();
            ply::standard_bytes(&gs, degree).map_err(crate::Error::invalid)
        })
        .collect()
}

/// The `splat-ply` fuzz target: read, then import on a 16-point grid.
pub fn fuzz_run(path: &std::path::Path) -> crate::Result<()> {
    let file = SplatFile::read(path)?;
    let opts = ImportOptions {
        res: Some(16),
        ..Default::default()
    };
    import::build_field(&file, &opts).map(drop)
}
