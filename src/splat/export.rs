//! Objects and fields out as splat `.ply` files.
//!
//! - A field imported from a splat file ([`Field::source`]): the file's own
//!   records whose centres are inside the object's bitmap
//!   ([`super::import::inside`]), or all the others (`complement`), byte for
//!   byte when the object is where it was cut from and has no appearance
//!   edit. A moved object's records are transformed (centre, rotation and
//!   scales through the covariance, SH rotated by the rotation part, normals
//!   rotated), an appearance edit is applied to the SH
//!   ([`super::sh::apply_color_matrix`]); every other property is kept.
//! - Any other field (trained, demo, edited): one Gaussian per occupied grid
//!   point ([`voxel_gaussians`]), SH degree 2.

use super::import::inside;
use super::ply::{self, encode, Gaussian, SplatFile};
use super::sh::{apply_color_matrix, from_field_sh2, ShRotation, C0};
use crate::error::{Error, Result};
use crate::field::cache::OCCUPIED_FLOOR;
use crate::field::{Appearance, Bitmap, ChannelGrid, Field};
use crate::render::ColorEdit;
use glam::{Affine3A, Mat3, Quat, Vec3};
use nalgebra::Matrix3;
use rayon::prelude::*;
use std::path::Path;

/// Which part of a field to export and where it now is.
#[derive(Clone, Debug)]
pub struct Selection<'a> {
    /// The object's bitmap over the field's grid; `None`: the whole field.
    pub bits: Option<&'a Bitmap>,
    /// Everything but the bitmap instead.
    pub complement: bool,
    /// Field-local to world (identity: where it was cut from).
    pub to_world: Affine3A,
    pub color: Option<ColorEdit>,
}

impl Selection<'_> {
    pub fn whole() -> Selection<'static> {
        Selection {
            bits: None,
            complement: false,
            to_world: Affine3A::IDENTITY,
            color: None,
        }
    }
    fn moves(&self) -> bool {
        self.to_world != Affine3A::IDENTITY || self.color.is_some_and(|c| !c.is_identity())
    }
}

/// What an export wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct ExportReport {
    pub written: usize,
    /// Gaussians (source records, or occupied grid points) considered.
    pub total: usize,
    /// True when the records are the source file's own.
    pub from_source: bool,
}

/// Exports `sel` of `field` to `out` (module docs).
pub fn export(field: &Field, sel: &Selection, out: &Path) -> Result<ExportReport> {
    if field.source.is_some() {
        let file = source_file(field)?;
        let keep = select_records(field, &file, sel);
        let written = write_records(&file, &keep, sel, out)?;
        return Ok(ExportReport {
            written,
            total: file.len(),
            from_source: true,
        });
    }
    let (gaussians, total) = voxel_gaussians(field, sel)?;
    let bytes = ply::standard_bytes(&gaussians, 2).map_err(Error::invalid)?;
    crate::error::write_atomic(out, &bytes)?;
    Ok(ExportReport {
        written: gaussians.len(),
        total,
        from_source: false,
    })
}

/// An object of a composition as splats, where it is now (`object_to_world`,
/// its colour edit applied), or with `complement` its field without it,
/// where the field is (`field_to_world`): the script command
/// `export(splats(object: NAME, out: FILE[, complement: true]))`.
pub fn export_object(
    field: &Field,
    mask: &Bitmap,
    complement: bool,
    field_to_world: Affine3A,
    object: (Affine3A, Option<ColorEdit>),
    out: &Path,
) -> Result<ExportReport> {
    let (to_world, color) = match complement {
        true => (field_to_world, None),
        false => object,
    };
    let sel = Selection {
        bits: Some(mask),
        complement,
        to_world,
        color,
    };
    export(field, &sel, out)
}

/// The splat file an imported field came from, checked against the CRC-32
/// and count it had at import.
pub fn source_file(field: &Field) -> Result<SplatFile> {
    let src = field
        .source
        .as_ref()
        .ok_or_else(|| Error::invalid("the field was not imported from a splat file"))?;
    let file = SplatFile::read(&src.path)?;
    if file.crc32() != src.crc32 || file.len() != src.count {
        return Err(Error::bad_file(
            &src.path,
            format!(
                "changed since the field was imported (CRC-32 {:08x}, {} Gaussians; now {:08x}, {})",
                src.crc32,
                src.count,
                file.crc32(),
                file.len()
            ),
        ));
    }
    Ok(file)
}

/// Which records `sel` exports.
pub fn select_records(field: &Field, file: &SplatFile, sel: &Selection) -> Vec<bool> {
    let Some(bits) = sel.bits else {
        return vec![true; file.len()];
    };
    let mut keep = inside(file, &field.geom(), bits);
    if sel.complement {
        keep.iter_mut().for_each(|k| *k = !*k);
    }
    keep
}

/// Writes the kept records, moved and recoloured as `sel` says; returns how
/// many.
pub fn write_records(file: &SplatFile, keep: &[bool], sel: &Selection, out: &Path) -> Result<usize> {
    let h = &file.header;
    let n = keep.iter().filter(|&&k| k).count();
    let mut records = Vec::with_capacity(n * h.stride);
    for (i, _) in keep.iter().enumerate().filter(|(_, &k)| k) {
        records.extend_from_slice(file.record(i));
    }
    if sel.moves() {
        let mover = Mover::new(sel.to_world, sel.color);
        records
            .par_chunks_mut(h.stride)
            .for_each(|rec| mover.record(rec, &h.layout));
    }
    ply::write(out, &h.with_count(n), &records)?;
    Ok(n)
}

/// Transforms and recolours Gaussians (module docs).
pub struct Mover {
    affine: Affine3A,
    /// Rotation part of the linear map (polar decomposition).
    rotation: Mat3,
    /// Uniform scale when the map is a rotation times a positive scale.
    similarity: Option<f32>,
    sh: ShRotation,
    color: Option<Mat3>,
}

impl Mover {
    pub fn new(affine: Affine3A, color: Option<ColorEdit>) -> Mover {
        let m = Mat3::from(affine.matrix3);
        let rotation = polar_rotation(m);
        let s = m.determinant().abs().cbrt();
        let similarity = ((m - rotation * s)
            .abs()
            .to_cols_array()
            .iter()
            .all(|v| *v < 1e-5 * s.max(1.0))
            && m.determinant() > 0.0)
            .then_some(s);
        let color = color
            .filter(|c| !c.is_identity())
            .map(|c| Mat3::from_cols(c.linear(Vec3::X), c.linear(Vec3::Y), c.linear(Vec3::Z)));
        Mover {
            affine,
            rotation,
            similarity,
            sh: ShRotation::new(rotation),
            color,
        }
    }

    /// Moves one Gaussian.
    pub fn gaussian(&self, g: &mut Gaussian) {
        g.pos = self.affine.transform_point3(g.pos);
        let q = g.rotation();
        match self.similarity {
            Some(s) => {
                let r = (Quat::from_mat3(&self.rotation) * q).normalize();
                g.rot = [r.w, r.x, r.y, r.z];
                g.log_scale = g.log_scale.map(|l| l + s.ln());
            }
            None => {
                let m = Mat3::from(self.affine.matrix3) * Mat3::from_quat(q) * Mat3::from_diagonal(g.scales());
                let (r, s) = decompose_covariance(m * m.transpose());
                g.rot = [r.w, r.x, r.y, r.z];
                g.log_scale = s.to_array().map(|v| v.max(1e-30).ln());
            }
        }
        self.sh.apply(&mut g.rest);
        if let Some(c) = self.color {
            apply_color_matrix(c, &mut g.dc, &mut g.rest);
        }
    }

    /// Moves one record in place (every other property kept).
    pub fn record(&self, rec: &mut [u8], layout: &ply::Layout) {
        let mut g = ply::decode(rec, layout);
        self.gaussian(&mut g);
        encode(&g, layout, rec);
        if let Some(n) = layout.normal {
            let v = Vec3::from(n.map(|o| ply::f32_at(rec, o)));
            let v = self.rotation * v;
            for (a, &o) in n.iter().enumerate() {
                ply::put_f32(rec, o, v[a]);
            }
        }
    }
}

fn to_na(m: Mat3) -> Matrix3<f32> {
    Matrix3::from_column_slice(&m.to_cols_array())
}

fn from_na(m: &Matrix3<f32>) -> Mat3 {
    Mat3::from_cols_slice(m.as_slice())
}

/// The orthogonal factor Q of M = Q·P.
fn polar_rotation(m: Mat3) -> Mat3 {
    let svd = to_na(m).svd(true, true);
    match (svd.u, svd.v_t) {
        (Some(u), Some(vt)) => from_na(&(u * vt)),
        _ => Mat3::IDENTITY,
    }
}

/// Rotation and standard deviations of a covariance matrix.
fn decompose_covariance(cov: Mat3) -> (Quat, Vec3) {
    let e = to_na(cov).symmetric_eigen();
    let mut r = from_na(&e.eigenvectors);
    if r.determinant() < 0.0 {
        r.z_axis = -r.z_axis;
    }
    let s = Vec3::new(e.eigenvalues[0], e.eigenvalues[1], e.eigenvalues[2])
        .max(Vec3::ZERO)
        .powf(0.5);
    (Quat::from_mat3(&r).normalize(), s)
}

/// One Gaussian per occupied grid point of `sel` (σ > the occupancy floor
/// and opacity ≥ 1/255): at the grid point, isotropic with σ = half the
/// mean spacing, opacity from the point's density by the import's mapping
/// read backwards (mass σ·voxel volume = τ·2π·s²), colour from the field's
/// SH2 or RGB at the point (VM appearance baked to SH2 first). Also returns
/// the number of occupied grid points considered.
pub fn voxel_gaussians(field: &Field, sel: &Selection) -> Result<(Vec<Gaussian>, usize)> {
    if let Some(b) = sel.bits {
        crate::ensure!(
            b.res() == field.res(),
            "the bitmap's resolution {:?} is not the field's {:?}",
            b.res(),
            field.res()
        );
    }
    let baked = field.sh_baked()?;
    let src = baked.as_deref().unwrap_or(field);
    let geom = field.geom();
    let h = geom.spacing();
    let s = 0.5 * (h.x + h.y + h.z) / 3.0;
    let volume = h.x * h.y * h.z;
    let candidates: Vec<usize> = match &field.occupancy {
        Some(o) => o.bits().ones().collect(),
        None => (0..geom.len()).collect(),
    };
    let wanted = |v: usize| match sel.bits {
        None => true,
        Some(b) => b.get(v) != sel.complement,
    };
    let occupied: Vec<usize> = candidates
        .into_par_iter()
        .filter(|&v| field.density.sigma_at(v) > OCCUPIED_FLOOR && wanted(v))
        .collect();
    let mover = sel.moves().then(|| Mover::new(sel.to_world, sel.color));
    let gaussians: Vec<Gaussian> = occupied
        .par_iter()
        .filter_map(|&v| {
            let tau = field.density.sigma_at(v) * volume / (std::f32::consts::TAU * s * s);
            let alpha = (1.0 - (-tau).exp()).min(0.999);
            if alpha < 1.0 / 255.0 {
                return None;
            }
            let (dc, rest) = voxel_colour(&src.appearance, v);
            let mut g = Gaussian {
                pos: geom.point_of(v),
                dc,
                rest,
                opacity: (alpha / (1.0 - alpha)).ln(),
                log_scale: [s.ln(); 3],
                rot: [1.0, 0.0, 0.0, 0.0],
            };
            if let Some(m) = &mover {
                m.gaussian(&mut g);
            }
            Some(g)
        })
        .collect();
    Ok((gaussians, occupied.len()))
}

/// A grid point's colour as splat SH (degree 2).
fn voxel_colour(app: &Appearance, v: usize) -> ([f32; 3], Vec<f32>) {
    let at = |g: &ChannelGrid, out: &mut [f32]| g.at_voxel(v, out);
    match app {
        Appearance::Sh2(g) => {
            let mut sh = [0f32; 27];
            at(g, &mut sh);
            from_field_sh2(&sh)
        }
        Appearance::Rgb(g) => {
            let mut c = [0f32; 3];
            at(g, &mut c);
            (c.map(|c| (c.clamp(0.0, 1.0) - 0.5) / C0), vec![0.0; 24])
        }
        // Baked to SH2 by the caller; grey if that ever changes.
        Appearance::Vm { .. } => ([0.0; 3], vec![0.0; 24]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn g() -> Gaussian {
        Gaussian {
            pos: Vec3::new(0.1, 0.2, 0.3),
            dc: [0.1, 0.2, 0.3],
            rest: (0..24).map(|i| i as f32 * 0.01).collect(),
            opacity: 0.5,
            log_scale: [-2.0, -3.0, -4.0],
            rot: [0.9, 0.1, -0.3, 0.2],
        }
    }

    fn covariance(g: &Gaussian) -> Mat3 {
        let m = Mat3::from_quat(g.rotation()) * Mat3::from_diagonal(g.scales());
        m * m.transpose()
    }

    #[test]
    fn moved_gaussians_carry_their_covariance() {
        let rot = Quat::from_euler(glam::EulerRot::XYZ, 0.4, 1.0, -0.2);
        for a in [
            Affine3A::from_scale_rotation_translation(Vec3::splat(2.0), rot, Vec3::new(1.0, 0.0, -1.0)),
            Affine3A::from_scale_rotation_translation(Vec3::new(1.0, 2.0, 0.5), rot, Vec3::ZERO),
        ] {
            let mut moved = g();
            Mover::new(a, None).gaussian(&mut moved);
            assert!((moved.pos - a.transform_point3(g().pos)).length() < 1e-5);
            let m = Mat3::from(a.matrix3);
            let want = m * covariance(&g()) * m.transpose();
            let got = covariance(&moved);
            let err = (want - got).abs().to_cols_array().iter().fold(0f32, |a, b| a.max(*b));
            assert!(err < 1e-5, "{want} vs {got}");
        }
    }

    #[test]
    fn the_identity_changes_nothing() {
        let mut moved = g();
        Mover::new(Affine3A::IDENTITY, None).gaussian(&mut moved);
        for (a, b) in moved.rest.iter().zip(&g().rest) {
            assert!((a - b).abs() < 1e-5);
        }
        assert!((moved.rotation().dot(g().rotation()).abs() - 1.0).abs() < 1e-5);
    }
}
