//! Field files: one `.safetensors` per field.
//!
//! `__metadata__` holds `format = "isrf-field"`, `version = "1"` and `header`,
//! a JSON [`Header`] (bounds, resolution, activation, kinds). Tensors:
//!
//! | name | dtype | shape |
//! |---|---|---|
//! | `density` | F32 | `[nz, ny, nx]` raw (pre-activation), or `[occupied]` when sparse |
//! | `occupancy` | U8 | packed bits (x fastest, little-endian u64 words); only with sparse grids |
//! | `app.rgb` / `app.sh` | F16 | dense `[nz, ny, nx, C]` or sparse `[occupied, C]` |
//! | `app.vm.plane{m}`, `app.vm.line{m}`, `app.vm.basis` | F32 | `[R, nb, na]`, `[R, nc]`, `[ΣR, D]` |
//! | `app.mlp.{i}.weight`, `app.mlp.{i}.bias` | F32 | `[out, in]`, `[out]` |
//! | `feat.grid` | F16, or I8 with `storage: q8` | like `app.rgb` |
//! | `feat.grid.scale` | F32 | `[C]`: value = stored integer × scale (q8 only) |
//! | `feat.occupancy` | U8 | packed bits at the feature resolution; only for a sparse feature grid with its own index |
//! | `feat.vm.*` | F32 | like `app.vm.*` |
//!
//! Version 2 added sparse density (header `density: {layout: sparse, fill}`:
//! the occupied points are stored, every other point holds `fill`) and
//! sparse feature grids at their own resolution (header `feature_occupied`
//! and the `feat.occupancy` tensor; without them a sparse feature grid uses
//! `occupancy`, at the density resolution). A file that uses neither is
//! written as version 1, so older readers keep reading it; version 1 files
//! (all dense) read as before. Version 3 added 8-bit channel grids (channel
//! header `storage: q8`: signed bytes with one f32 scale per channel), used
//! for feature grids: 64 distilled channels are half of a trained field's
//! file in f16, and segmentation compares them by distance, where the
//! quantisation error (≤ max|channel| / 254 per channel) is far below the
//! differences it decides on.
//!
//! The header's optional `ndc` (`{near, focal, width, height}`) says the
//! field lives in the NDC space of a forward-facing capture
//! (`crate::camera::Ndc`), as `isrf train` writes for LLFF scenes.
//!
//! The header's optional `source` names the 3D Gaussian splat file an
//! imported field came from (path, CRC-32, count; `crate::splat`); readers
//! that predate it ignore it.
//!
//! Reading validates the header, every resolution and the exact byte size the
//! header implies *before* reading the tensor data, then checks every tensor's
//! dtype and shape and that all values are finite.

use super::bitmap::{Bitmap, RankIndex};
use super::geom::{check_res, Aabb, GridGeom};
use super::grid::{Activation, ChannelGrid, DensityGrid, Layout};
use super::vm::{Linear, Mlp, VmGrid, MODE_AXES};
use super::{Appearance, Features, Field};
use crate::error::{Error, Result};
use glam::Vec3;
use half::f16;
use rayon::prelude::*;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use std::borrow::Cow;
use std::collections::HashMap;
use std::io::Read;
use std::path::Path;
use std::sync::Arc;

pub const FORMAT: &str = "isrf-field";
/// Newest version this build reads and writes (see the module docs).
pub const VERSION: u32 = 3;

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "lowercase")]
pub enum LayoutKind {
    Dense,
    Sparse,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct ChannelHeader {
    pub layout: LayoutKind,
    pub resolution: [usize; 3],
    pub channels: usize,
    /// How values are encoded; absent: f16 (versions 1 and 2).
    #[serde(default, skip_serializing_if = "Storage::is_f16")]
    pub storage: Storage,
}

/// Value encoding of a channel grid in the file.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Storage {
    #[default]
    F16,
    /// Signed bytes, value = q × scale[channel], scale = max |value| / 127.
    Q8,
}

impl Storage {
    fn is_f16(&self) -> bool {
        *self == Storage::F16
    }
    /// File bytes per stored value.
    fn value_bytes(self) -> usize {
        match self {
            Storage::F16 => 2,
            Storage::Q8 => 1,
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct VmHeader {
    pub resolution: [usize; 3],
    pub comps: [usize; 3],
    pub out: usize,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct MlpHeader {
    pub feat_pe: usize,
    pub view_pe: usize,
    /// `[inputs, outputs]` per layer.
    pub layers: Vec<[usize; 2]>,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum AppearanceHeader {
    Rgb(ChannelHeader),
    Sh2(ChannelHeader),
    Vm { grid: VmHeader, mlp: MlpHeader },
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum FeaturesHeader {
    Grid(ChannelHeader),
    Vm(VmHeader),
}

/// How the density grid is stored (absent: dense, version 1).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct DensityHeader {
    pub layout: LayoutKind,
    /// Raw value of every point the file does not store (sparse only).
    pub fill: f32,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Header {
    pub bounds: [[f32; 3]; 2],
    pub resolution: [usize; 3],
    pub activation: Activation,
    pub appearance: AppearanceHeader,
    pub features: Option<FeaturesHeader>,
    /// Number of set bits in `occupancy` (sparse grids only).
    #[serde(default)]
    pub occupied: Option<usize>,
    /// Density storage; `None`: dense.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub density: Option<DensityHeader>,
    /// Number of set bits in `feat.occupancy` (a sparse feature grid with
    /// its own index).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feature_occupied: Option<usize>,
    /// The splat file an imported field came from (readers before it ignore it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<super::Source>,
    /// The NDC space of a field trained on a forward-facing capture
    /// ([`super::Field::ndc`]; readers before it ignore it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ndc: Option<crate::camera::Ndc>,
    /// The scene's up direction ([`super::Field::up`]; readers before it
    /// ignore it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub up: Option<[f32; 3]>,
}

impl Header {
    /// Semantic feature channels the file holds (0: none).
    pub fn feature_channels(&self) -> usize {
        match &self.features {
            Some(FeaturesHeader::Grid(c)) => c.channels,
            Some(FeaturesHeader::Vm(v)) => v.out,
            None => 0,
        }
    }
    /// The header of every channel grid (appearance and features).
    fn channel_headers(&self) -> impl Iterator<Item = &ChannelHeader> {
        let app = match &self.appearance {
            AppearanceHeader::Rgb(c) | AppearanceHeader::Sh2(c) => Some(c),
            AppearanceHeader::Vm { .. } => None,
        };
        let feat = match &self.features {
            Some(FeaturesHeader::Grid(c)) => Some(c),
            _ => None,
        };
        app.into_iter().chain(feat)
    }
    /// True when the density grid is stored for the occupied points only.
    pub fn sparse_density(&self) -> bool {
        self.density.as_ref().is_some_and(|d| d.layout == LayoutKind::Sparse)
    }
    /// Oldest format version that can read a file with this header.
    pub fn min_version(&self) -> u32 {
        if self.channel_headers().any(|c| c.storage != Storage::F16) {
            3
        } else if self.sparse_density() || self.feature_occupied.is_some() {
            2
        } else {
            1
        }
    }
}

// ---------------------------------------------------------------- writing

/// Named tensors to write, borrowing the field's arrays where they are
/// stored as they are (no copy of a large grid while saving).
struct Out<'a> {
    names: Vec<String>,
    tensors: Vec<(Dtype, Vec<usize>, Cow<'a, [u8]>)>,
}

impl<'a> Out<'a> {
    fn push(&mut self, name: impl Into<String>, dtype: Dtype, shape: Vec<usize>, bytes: Cow<'a, [u8]>) {
        self.names.push(name.into());
        self.tensors.push((dtype, shape, bytes));
    }
    fn bits(&mut self, name: &str, bits: &Bitmap) {
        let bytes = bits.to_bytes();
        self.push(name, Dtype::U8, vec![bytes.len()], Cow::Owned(bytes));
    }
    fn channel_grid(&mut self, name: &str, g: &'a ChannelGrid, storage: Storage) -> ChannelHeader {
        let [nx, ny, nz] = g.geom.res;
        let (layout, shape) = match g.layout {
            Layout::Dense => (LayoutKind::Dense, vec![nz, ny, nx, g.channels]),
            Layout::Sparse(_) => (LayoutKind::Sparse, vec![g.slots(), g.channels]),
        };
        match storage {
            Storage::F16 => self.push(name, Dtype::F16, shape, Cow::Borrowed(bytemuck::cast_slice(&g.data))),
            Storage::Q8 => {
                let (q, scale) = quantise_q8(&g.data, g.channels);
                self.push(name, Dtype::I8, shape, Cow::Owned(bytemuck::cast_vec(q)));
                self.push(
                    format!("{name}.scale"),
                    Dtype::F32,
                    vec![g.channels],
                    Cow::Owned(bytemuck::cast_slice(&scale).to_vec()),
                );
            }
        }
        ChannelHeader {
            layout,
            resolution: g.geom.res,
            channels: g.channels,
            storage,
        }
    }
    fn vm(&mut self, prefix: &str, v: &'a VmGrid) -> VmHeader {
        for (m, &(a, b, c)) in MODE_AXES.iter().enumerate() {
            let r = v.comps[m];
            let res = v.geom.res;
            self.push(
                format!("{prefix}.plane{m}"),
                Dtype::F32,
                vec![r, res[b], res[a]],
                f32_bytes(&v.planes[m]),
            );
            self.push(
                format!("{prefix}.line{m}"),
                Dtype::F32,
                vec![r, res[c]],
                f32_bytes(&v.lines[m]),
            );
        }
        self.push(
            format!("{prefix}.basis"),
            Dtype::F32,
            vec![v.total_comps(), v.out],
            f32_bytes(&v.basis),
        );
        VmHeader {
            resolution: v.geom.res,
            comps: v.comps,
            out: v.out,
        }
    }
}

fn f32_bytes(v: &[f32]) -> Cow<'_, [u8]> {
    Cow::Borrowed(bytemuck::cast_slice(v))
}

/// 8-bit encoding of `channels`-wide rows: per channel, scale = max |v| / 127
/// and q = round(v / scale) (a channel that is zero everywhere gets scale 0).
fn quantise_q8(data: &[f16], channels: usize) -> (Vec<i8>, Vec<f32>) {
    let max_abs = data
        .par_chunks(channels * 4096)
        .map(|block| {
            let mut m = vec![0f32; channels];
            for row in block.chunks_exact(channels) {
                for (m, v) in m.iter_mut().zip(row) {
                    *m = m.max(v.to_f32().abs());
                }
            }
            m
        })
        .reduce(
            || vec![0f32; channels],
            |a, b| a.iter().zip(&b).map(|(a, b)| a.max(*b)).collect(),
        );
    let scale: Vec<f32> = max_abs.iter().map(|m| m / 127.0).collect();
    let inv: Vec<f32> = scale.iter().map(|&s| if s > 0.0 { 1.0 / s } else { 0.0 }).collect();
    let mut q = vec![0i8; data.len()];
    q.par_chunks_mut(channels * 4096)
        .zip(data.par_chunks(channels * 4096))
        .for_each(|(q, d)| {
            for (q, d) in q.chunks_exact_mut(channels).zip(d.chunks_exact(channels)) {
                for ((q, v), inv) in q.iter_mut().zip(d).zip(&inv) {
                    *q = (v.to_f32() * inv).round().clamp(-127.0, 127.0) as i8;
                }
            }
        });
    (q, scale)
}

/// Inverse of [`quantise_q8`], to the f16 values the grid holds in memory.
fn dequantise_q8(q: &[u8], scale: &[f32]) -> Vec<f16> {
    let c = scale.len();
    let mut out = vec![f16::ZERO; q.len()];
    out.par_chunks_mut(c * 4096)
        .zip(q.par_chunks(c * 4096))
        .for_each(|(o, q)| {
            for (o, q) in o.chunks_exact_mut(c).zip(q.chunks_exact(c)) {
                for ((o, &q), s) in o.iter_mut().zip(q).zip(scale) {
                    *o = f16::from_f32(q as i8 as f32 * s);
                }
            }
        });
    out
}

/// True when `ix` is the field's occupancy index (the same object, or the
/// same bits at the same resolution).
fn is_shared(ix: &Arc<RankIndex>, occ: Option<&Arc<RankIndex>>) -> bool {
    occ.is_some_and(|o| Arc::ptr_eq(ix, o) || ix.bits() == o.bits())
}

/// The single raw value every point outside `occ` holds, if there is one
/// (then the file stores the density for the occupied points only).
fn uniform_fill(raw: &[f32], occ: &RankIndex) -> Option<f32> {
    let bits = occ.bits();
    let first = (0..raw.len()).find(|&i| !bits.get(i))?;
    let fill = raw[first];
    let uniform = raw
        .par_iter()
        .enumerate()
        .all(|(i, &r)| bits.get(i) || r.to_bits() == fill.to_bits());
    (uniform && fill.is_finite()).then_some(fill)
}

/// The density tensor: sparse over the occupancy when the rest is uniform.
fn density_tensor<'a>(out: &mut Out<'a>, field: &'a Field) -> Option<DensityHeader> {
    let [nx, ny, nz] = field.res();
    let raw = &field.density.raw;
    if let Some(occ) = &field.occupancy {
        if let Some(fill) = uniform_fill(raw, occ) {
            let kept: Vec<f32> = occ.bits().ones().map(|i| raw[i]).collect();
            out.push(
                "density",
                Dtype::F32,
                vec![kept.len()],
                Cow::Owned(bytemuck::cast_slice(&kept).to_vec()),
            );
            return Some(DensityHeader {
                layout: LayoutKind::Sparse,
                fill,
            });
        }
    }
    out.push("density", Dtype::F32, vec![nz, ny, nx], f32_bytes(raw));
    None
}

/// The field's tensors and header.
fn plan(field: &Field, feature_storage: Storage) -> Result<(Out<'_>, Header)> {
    let mut out = Out {
        names: vec![],
        tensors: vec![],
    };
    let density = density_tensor(&mut out, field);
    let occ = field.occupancy.as_ref();
    if let Some(o) = occ {
        crate::ensure!(
            o.bits().res() == field.res(),
            "the field's occupancy has resolution {:?}, its density grid {:?}",
            o.bits().res(),
            field.res()
        );
        out.bits("occupancy", o.bits());
    }
    // Sparse appearance always uses the field's index; a sparse feature grid
    // may have its own (at its own resolution).
    let check_shared = |g: &ChannelGrid, what: &str| -> Result<()> {
        if let Layout::Sparse(ix) = &g.layout {
            crate::ensure!(
                is_shared(ix, occ),
                "the sparse {what} grid does not use the field's occupancy index"
            );
        }
        Ok(())
    };
    let appearance = match &field.appearance {
        Appearance::Rgb(g) => {
            check_shared(g, "appearance")?;
            AppearanceHeader::Rgb(out.channel_grid("app.rgb", g, Storage::F16))
        }
        Appearance::Sh2(g) => {
            check_shared(g, "appearance")?;
            AppearanceHeader::Sh2(out.channel_grid("app.sh", g, Storage::F16))
        }
        Appearance::Vm { grid, mlp } => {
            let grid = out.vm("app.vm", grid);
            let mut layers = vec![];
            for (i, l) in mlp.layers.iter().enumerate() {
                out.push(
                    format!("app.mlp.{i}.weight"),
                    Dtype::F32,
                    vec![l.outputs, l.inputs],
                    f32_bytes(&l.weight),
                );
                out.push(
                    format!("app.mlp.{i}.bias"),
                    Dtype::F32,
                    vec![l.outputs],
                    f32_bytes(&l.bias),
                );
                layers.push([l.inputs, l.outputs]);
            }
            AppearanceHeader::Vm {
                grid,
                mlp: MlpHeader {
                    feat_pe: mlp.feat_pe,
                    view_pe: mlp.view_pe,
                    layers,
                },
            }
        }
    };
    let mut feature_occupied = None;
    let features = match &field.features {
        Some(Features::Grid(g)) => {
            if let Layout::Sparse(ix) = &g.layout {
                if !is_shared(ix, occ) {
                    out.bits("feat.occupancy", ix.bits());
                    feature_occupied = Some(ix.count());
                }
            }
            Some(FeaturesHeader::Grid(out.channel_grid("feat.grid", g, feature_storage)))
        }
        Some(Features::Vm(v)) => Some(FeaturesHeader::Vm(out.vm("feat.vm", v))),
        None => None,
    };
    let b = field.bounds();
    let header = Header {
        bounds: [b.min.to_array(), b.max.to_array()],
        resolution: field.res(),
        activation: field.density.activation,
        appearance,
        features,
        occupied: occ.map(|o| o.count()),
        density,
        feature_occupied,
        source: field.source.clone(),
        ndc: field.ndc,
        up: field.up.map(|u| u.to_array()),
    };
    Ok((out, header))
}

fn field_metadata(header: &Header) -> HashMap<String, String> {
    let mut meta = HashMap::new();
    meta.insert("format".to_string(), FORMAT.to_string());
    meta.insert("version".to_string(), header.min_version().to_string());
    meta.insert(
        "header".to_string(),
        serde_json::to_string(header).expect("header serialises"),
    );
    meta
}

/// Serialises a field to safetensors bytes (in memory; [`save`] streams).
pub fn to_bytes(field: &Field) -> Result<Vec<u8>> {
    let (out, header) = plan(field, Storage::Q8)?;
    let v = views(&out.names, out.tensors.iter().map(|(d, s, b)| (*d, s, &b[..])))?;
    let bytes = safetensors::serialize(v, Some(field_metadata(&header)))
        .map_err(|e| Error::invalid(format!("cannot serialise: {e}")))?;
    Ok(canonical_header(bytes))
}

fn views<'a>(
    names: &[String],
    tensors: impl Iterator<Item = (Dtype, &'a Vec<usize>, &'a [u8])>,
) -> Result<Vec<(String, TensorView<'a>)>> {
    names
        .iter()
        .zip(tensors)
        .map(|(n, (d, s, b))| TensorView::new(d, s.clone(), b).map(|v| (n.clone(), v)))
        .collect::<std::result::Result<_, _>>()
        .map_err(|e| Error::invalid(format!("cannot build tensor: {e}")))
}

/// Serialises named tensors with metadata (shared by every isrf file kind).
pub fn serialize(
    names: &[String],
    tensors: &[(Dtype, Vec<usize>, Vec<u8>)],
    meta: HashMap<String, String>,
) -> Result<Vec<u8>> {
    let v = views(names, tensors.iter().map(|(d, s, b)| (*d, s, &b[..])))?;
    let bytes = safetensors::serialize(v, Some(meta)).map_err(|e| Error::invalid(format!("cannot serialise: {e}")))?;
    Ok(canonical_header(bytes))
}

/// Writes named tensors with metadata to `path` atomically, streaming the
/// tensor data from the borrowed slices: the same bytes as [`serialize`]
/// without holding a copy of the whole file in memory (training
/// checkpoints and fields are hundreds of MB).
pub fn write_tensors(
    path: &Path,
    names: &[String],
    tensors: &[(Dtype, Vec<usize>, &[u8])],
    meta: HashMap<String, String>,
) -> Result<()> {
    let v = views(names, tensors.iter().map(|(d, s, b)| (*d, s, *b)))?;
    let tmp = crate::error::temp_beside(path)?;
    let mode = tmp.as_file().metadata().map_err(|e| Error::io(path, e))?.permissions();
    let tmp = tmp.into_temp_path();
    safetensors::serialize_to_file(v, Some(meta), &tmp)
        .map_err(|e| Error::invalid(format!("cannot write {}: {e}", path.display())))?;
    canonicalise_file(&tmp).map_err(|e| Error::io(path, e))?;
    // safetensors writes through a temporary file of its own (owner-only)
    // and renames it over ours: give it back the mode ours was made with,
    // last, since it may be the read-only mode of the file it replaces.
    std::fs::set_permissions(&tmp, mode).map_err(|e| Error::io(path, e))?;
    tmp.persist(path).map_err(|e| Error::io(path, e.error))?;
    Ok(())
}

/// [`canonical_header`] applied to a file in place, then synced. The sorted
/// header has the same length (same keys and values, same padding), so only
/// the header bytes are rewritten; should it ever differ, the whole file is.
fn canonicalise_file(path: &Path) -> std::io::Result<()> {
    use std::io::{Seek, SeekFrom, Write};
    let mut f = std::fs::OpenOptions::new().read(true).write(true).open(path)?;
    let mut n = [0u8; 8];
    f.read_exact(&mut n)?;
    let n = u64::from_le_bytes(n) as usize;
    let mut header = vec![0u8; n];
    f.read_exact(&mut header)?;
    let mut prefix = (n as u64).to_le_bytes().to_vec();
    prefix.extend_from_slice(&header);
    let fixed = canonical_header(prefix);
    if fixed.len() == 8 + n {
        f.seek(SeekFrom::Start(0))?;
        f.write_all(&fixed)?;
    } else {
        drop(f);
        let all = canonical_header(std::fs::read(path)?);
        std::fs::write(path, all)?;
        f = std::fs::File::open(path)?;
    }
    f.sync_all()
}

/// Rewrites the JSON header with sorted keys. `safetensors` writes the
/// metadata map in hash order, so the same field would otherwise give
/// different bytes from run to run; scripts promise byte-identical outputs.
/// Tensor offsets are relative to the data section, so only the header and
/// its length prefix change. The header stays padded to 8 bytes with spaces.
fn canonical_header(bytes: Vec<u8>) -> Vec<u8> {
    let n = u64::from_le_bytes(bytes[..8].try_into().expect("8-byte prefix")) as usize;
    let Ok(v) = serde_json::from_slice::<serde_json::Value>(&bytes[8..8 + n]) else {
        return bytes;
    };
    // serde_json's default map is a BTreeMap: serialising sorts every key.
    let mut header = serde_json::to_vec(&v).expect("JSON value serialises");
    while header.len() % 8 != 0 {
        header.push(b' ');
    }
    let mut out = Vec::with_capacity(8 + header.len() + bytes.len() - 8 - n);
    out.extend_from_slice(&(header.len() as u64).to_le_bytes());
    out.extend_from_slice(&header);
    out.extend_from_slice(&bytes[8 + n..]);
    out
}

/// Writes a field atomically (streamed: no in-memory copy of the file).
pub fn save(field: &Field, path: &Path) -> Result<()> {
    save_with(field, path, Storage::Q8)
}

/// [`save`] with a chosen encoding for the feature grid (`Storage::F16`
/// writes what versions 1 and 2 read).
pub fn save_with(field: &Field, path: &Path, features: Storage) -> Result<()> {
    let (out, header) = plan(field, features)?;
    let tensors: Vec<(Dtype, Vec<usize>, &[u8])> =
        out.tensors.iter().map(|(d, s, b)| (*d, s.clone(), &b[..])).collect();
    write_tensors(path, &out.names, &tensors, field_metadata(&header))
}

// ---------------------------------------------------------------- reading

/// Reads only the safetensors header of `path`: its `__metadata__` map and the
/// file's total length. Rejects files too short to hold the header they claim.
pub fn read_metadata(path: &Path) -> Result<(HashMap<String, String>, u64)> {
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let (header, len) = read_header_json(&mut f, path)?;
    Ok((metadata_of(&header), len))
}

/// The JSON header of the safetensors file `f` (open at its start, named
/// `path` in errors), leaving `f` at the data section; and the file's length.
pub(crate) fn read_header_json(
    f: &mut std::fs::File,
    path: &Path,
) -> Result<(serde_json::Map<String, serde_json::Value>, u64)> {
    let bad = |r: String| Error::bad_file(path, r);
    let len = f.metadata().map_err(|e| Error::io(path, e))?.len();
    if len < 8 {
        return Err(bad(format!(
            "truncated: {len} bytes is too short for a safetensors file"
        )));
    }
    let mut n = [0u8; 8];
    f.read_exact(&mut n).map_err(|e| Error::io(path, e))?;
    let n = u64::from_le_bytes(n);
    if n > 100_000_000 || 8 + n > len {
        return Err(bad(format!(
            "corrupt or truncated: header length {n} does not fit in a {len}-byte file"
        )));
    }
    let mut h = vec![0u8; n as usize];
    f.read_exact(&mut h).map_err(|e| Error::io(path, e))?;
    let header = serde_json::from_slice(&h).map_err(|e| bad(format!("corrupt safetensors header: {e}")))?;
    Ok((header, len))
}

/// The `__metadata__` map of a safetensors header (empty if it has none).
pub(crate) fn metadata_of(header: &serde_json::Map<String, serde_json::Value>) -> HashMap<String, String> {
    header
        .get("__metadata__")
        .and_then(|m| serde_json::from_value::<HashMap<String, String>>(m.clone()).ok())
        .unwrap_or_default()
}

/// Bytes of a safetensors file's data section: the stored tensors, without
/// the 8-byte length prefix and the JSON header.
pub fn data_section_bytes(path: &Path) -> Result<u64> {
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = f.metadata().map_err(|e| Error::io(path, e))?.len();
    let mut n = [0u8; 8];
    f.read_exact(&mut n)
        .map_err(|_| Error::bad_file(path, "truncated: too short for a safetensors file"))?;
    let n = u64::from_le_bytes(n);
    len.checked_sub(8).and_then(|l| l.checked_sub(n)).ok_or_else(|| {
        Error::bad_file(
            path,
            format!("corrupt or truncated: header length {n} does not fit in a {len}-byte file"),
        )
    })
}

/// Checks `format` and `version` in a metadata map.
pub fn check_format(meta: &HashMap<String, String>, format: &str, version: u32, path: &Path) -> Result<()> {
    match meta.get("format") {
        Some(f) if f == format => {}
        Some(f) => {
            return Err(Error::bad_file(
                path,
                format!("this is a '{f}' file, not an '{format}' file"),
            ))
        }
        None => {
            return Err(Error::bad_file(
                path,
                format!("not an {format} file (no 'format' in the safetensors metadata)"),
            ))
        }
    }
    match meta.get("version").and_then(|v| v.parse::<u32>().ok()) {
        Some(v) if v <= version => Ok(()),
        Some(v) => Err(Error::bad_file(
            path,
            format!("{format} version {v} is newer than this isrf reads ({version})"),
        )),
        None => Err(Error::bad_file(path, "missing or malformed 'version' in metadata")),
    }
}

/// Reads a whole safetensors file after its header has been validated.
pub fn read_all(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

pub fn parse<'a>(bytes: &'a [u8], path: &Path) -> Result<SafeTensors<'a>> {
    SafeTensors::deserialize(bytes)
        .map_err(|e| Error::bad_file(path, format!("corrupt or truncated safetensors data: {e}")))
}

/// Typed tensor access with dtype, shape and finiteness checks; every error
/// names the file and the tensor.
pub struct Tensors<'a> {
    pub st: SafeTensors<'a>,
    pub path: &'a Path,
}

impl<'a> Tensors<'a> {
    fn view(&self, name: &str, dtype: Dtype, shape: &[usize]) -> Result<TensorView<'a>> {
        let t = self
            .st
            .tensor(name)
            .map_err(|_| Error::bad_file(self.path, format!("missing tensor '{name}'")))?;
        check_kind(self.path, name, (t.dtype(), t.shape()), (dtype, shape))?;
        Ok(t)
    }
    pub fn has(&self, name: &str) -> bool {
        self.st.tensor(name).is_ok()
    }
    pub fn f32(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>> {
        let t = self.view(name, Dtype::F32, shape)?;
        let v: Vec<f32> = t
            .data()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        self.finite(name, v.iter().copied())?;
        Ok(v)
    }
    pub fn f16(&self, name: &str, shape: &[usize]) -> Result<Vec<f16>> {
        let t = self.view(name, Dtype::F16, shape)?;
        let v: Vec<f16> = t
            .data()
            .chunks_exact(2)
            .map(|c| f16::from_le_bytes([c[0], c[1]]))
            .collect();
        self.finite(name, v.iter().map(|x| x.to_f32()))?;
        Ok(v)
    }
    /// A BF16 tensor, or an F32 one rounded to bf16 (checkpoints wrote Adam
    /// moments in f32 before they were kept in bf16).
    pub fn bf16_or_f32(&self, name: &str, shape: &[usize]) -> Result<Vec<half::bf16>> {
        if self.st.tensor(name).is_ok_and(|t| t.dtype() == Dtype::F32) {
            return Ok(self.f32(name, shape)?.into_iter().map(half::bf16::from_f32).collect());
        }
        let t = self.view(name, Dtype::BF16, shape)?;
        let v: Vec<half::bf16> = t
            .data()
            .chunks_exact(2)
            .map(|c| half::bf16::from_le_bytes([c[0], c[1]]))
            .collect();
        self.finite(name, v.iter().map(|x| x.to_f32()))?;
        Ok(v)
    }
    pub fn u8(&self, name: &str, shape: &[usize]) -> Result<Vec<u8>> {
        Ok(self.view(name, Dtype::U8, shape)?.data().to_vec())
    }
    /// A channel grid's values as f16, whatever their storage in the file.
    fn channels(&self, name: &str, shape: &[usize], storage: Storage) -> Result<Vec<f16>> {
        match storage {
            Storage::F16 => self.f16(name, shape),
            Storage::Q8 => {
                let channels = shape[shape.len() - 1];
                let scale = self.f32(&format!("{name}.scale"), &[channels])?;
                if let Some(c) = scale.iter().position(|&s| s < 0.0) {
                    return Err(Error::bad_file(
                        self.path,
                        format!("tensor '{name}.scale' is negative for channel {c}"),
                    ));
                }
                Ok(dequantise_q8(self.view(name, Dtype::I8, shape)?.data(), &scale))
            }
        }
    }
    fn finite(&self, name: &str, v: impl Iterator<Item = f32>) -> Result<()> {
        check_finite(self.path, name, v)
    }
}

/// An error unless tensor `name` in `path`, `got` (dtype, shape), is `want`.
pub(crate) fn check_kind(path: &Path, name: &str, got: (Dtype, &[usize]), want: (Dtype, &[usize])) -> Result<()> {
    if got.0 != want.0 {
        return Err(Error::bad_file(
            path,
            format!("tensor '{name}' has dtype {:?}, expected {:?}", got.0, want.0),
        ));
    }
    if got.1 != want.1 {
        return Err(Error::bad_file(
            path,
            format!("tensor '{name}' has shape {:?}, expected {:?}", got.1, want.1),
        ));
    }
    Ok(())
}

/// An error naming the first non-finite value of tensor `name` in `path`.
pub(crate) fn check_finite(path: &Path, name: &str, mut v: impl Iterator<Item = f32>) -> Result<()> {
    if let Some(pos) = v.position(|x| !x.is_finite()) {
        return Err(Error::bad_file(
            path,
            format!("tensor '{name}' holds a non-finite value (NaN or infinity) at element {pos}"),
        ));
    }
    Ok(())
}

/// Parses and validates the header in a field file's metadata.
pub fn read_header(path: &Path) -> Result<(Header, u64)> {
    let (meta, len) = read_metadata(path)?;
    check_format(&meta, FORMAT, VERSION, path)?;
    let h = meta
        .get("header")
        .ok_or_else(|| Error::bad_file(path, "missing 'header' in metadata"))?;
    let header: Header =
        serde_json::from_str(h).map_err(|e| Error::bad_file(path, format!("malformed field header: {e}")))?;
    validate_header(&header).map_err(|e| Error::bad_file(path, e.to_string()))?;
    let expected = expected_data_bytes(&header);
    // The data section must at least hold what the header implies.
    if expected > len {
        return Err(Error::bad_file(
            path,
            format!("truncated: the header implies {expected} bytes of tensors but the file has {len} bytes"),
        ));
    }
    Ok((header, len))
}

fn validate_header(h: &Header) -> Result<()> {
    let b = Aabb::new(Vec3::from(h.bounds[0]), Vec3::from(h.bounds[1]));
    crate::ensure!(
        b.is_valid(),
        "bounds {:?} are not a finite box with max > min",
        h.bounds
    );
    check_res(h.resolution, "density grid")?;
    if let Some(n) = &h.ndc {
        n.validate()?;
    }
    if let Some(u) = h.up {
        crate::ensure!(
            u.iter().all(|x| x.is_finite()) && Vec3::from(u).length() > 0.5,
            "up direction {u:?} is not a finite direction of length about 1"
        );
    }
    let chan = |c: &ChannelHeader, what: &str| -> Result<()> {
        check_res(c.resolution, what)?;
        crate::ensure!(
            c.channels >= 1 && c.channels <= 4096,
            "{what}: {} channels is out of range",
            c.channels
        );
        if c.layout == LayoutKind::Sparse && !(what == "features" && h.feature_occupied.is_some()) {
            crate::ensure!(
                c.resolution == h.resolution,
                "{what}: sparse grids must have the density resolution (or, for features, their own occupancy)"
            );
            crate::ensure!(
                h.occupied.is_some(),
                "{what} is sparse but the header has no occupied count"
            );
        }
        Ok(())
    };
    let vm = |v: &VmHeader, what: &str| -> Result<()> {
        check_res(v.resolution, what)?;
        crate::ensure!(
            v.comps.iter().all(|&c| c <= 1024) && v.out >= 1 && v.out <= 4096,
            "{what}: component or channel count out of range"
        );
        Ok(())
    };
    match &h.appearance {
        AppearanceHeader::Rgb(c) => {
            chan(c, "appearance")?;
            crate::ensure!(
                c.channels == 3,
                "rgb appearance must have 3 channels, not {}",
                c.channels
            );
        }
        AppearanceHeader::Sh2(c) => {
            chan(c, "appearance")?;
            crate::ensure!(
                c.channels == 27,
                "sh2 appearance must have 27 channels, not {}",
                c.channels
            );
        }
        AppearanceHeader::Vm { grid, mlp } => {
            vm(grid, "appearance")?;
            crate::ensure!(
                !mlp.layers.is_empty() && mlp.layers.len() <= 16,
                "appearance MLP must have 1..16 layers"
            );
            // Ranges first: the input count below multiplies header values.
            crate::ensure!(
                mlp.feat_pe <= 16 && mlp.view_pe <= 16,
                "positional encoding frequencies out of range (feat_pe {}, view_pe {}; at most 16)",
                mlp.feat_pe,
                mlp.view_pe
            );
            let inputs = grid.out + 3 + 2 * grid.out * mlp.feat_pe + 6 * mlp.view_pe;
            crate::ensure!(
                mlp.layers[0][0] == inputs,
                "appearance MLP takes {} inputs, the encoding gives {inputs}",
                mlp.layers[0][0]
            );
            for w in mlp.layers.windows(2) {
                crate::ensure!(
                    w[0][1] == w[1][0],
                    "appearance MLP layer sizes do not chain: {:?}",
                    mlp.layers
                );
            }
            crate::ensure!(
                mlp.layers.last().unwrap()[1] == 3,
                "appearance MLP must output 3 values"
            );
            for (i, l) in mlp.layers.iter().enumerate() {
                crate::ensure!(
                    l[0].checked_mul(l[1]).is_some_and(|n| (1..=1 << 24).contains(&n)),
                    "appearance MLP layer {i} ({}×{}) is empty or absurdly large",
                    l[0],
                    l[1]
                );
            }
        }
    }
    match &h.features {
        Some(FeaturesHeader::Grid(c)) => chan(c, "features")?,
        Some(FeaturesHeader::Vm(v)) => vm(v, "features")?,
        None => {}
    }
    if let Some(o) = h.occupied {
        let n: usize = h.resolution.iter().product();
        crate::ensure!(o <= n, "occupied count {o} exceeds the grid size {n}");
    }
    if let Some(d) = &h.density {
        crate::ensure!(d.fill.is_finite(), "density fill value {} is not finite", d.fill);
        crate::ensure!(
            d.layout == LayoutKind::Dense || h.occupied.is_some(),
            "the density is sparse but the header has no occupied count"
        );
    }
    if let Some(o) = h.feature_occupied {
        let Some(FeaturesHeader::Grid(c)) = &h.features else {
            return Err(Error::invalid(
                "feature_occupied is set but the features are not a grid",
            ));
        };
        crate::ensure!(
            c.layout == LayoutKind::Sparse,
            "feature_occupied is set but the feature grid is dense"
        );
        let n: usize = c.resolution.iter().product();
        crate::ensure!(o <= n, "feature occupied count {o} exceeds the feature grid size {n}");
    }
    Ok(())
}

fn channel_bytes(c: &ChannelHeader, occupied: usize) -> u64 {
    let slots = match c.layout {
        LayoutKind::Dense => c.resolution.iter().product::<usize>(),
        LayoutKind::Sparse => occupied,
    };
    (slots * c.channels * c.storage.value_bytes()) as u64
}

fn vm_bytes(v: &VmHeader) -> u64 {
    let r = v.resolution;
    let mut n = 0;
    for (m, &(a, b, c)) in MODE_AXES.iter().enumerate() {
        n += v.comps[m] * (r[a] * r[b] + r[c]);
    }
    ((n + v.comps.iter().sum::<usize>() * v.out) * 4) as u64
}

/// Lower bound on the tensor bytes a header implies.
fn expected_data_bytes(h: &Header) -> u64 {
    tensor_bytes(h, false)
}

/// Bytes of the tensors a header describes (occupancy bits left out), or
/// with `dense` what they would take with every grid stored dense (density
/// in f32, channel grids in their own encoding): the dense-equivalent size.
pub fn tensor_bytes(h: &Header, dense: bool) -> u64 {
    let points = h.resolution.iter().product::<usize>();
    let occ = if dense { points } else { h.occupied.unwrap_or(0) };
    let dense_layout = |c: &ChannelHeader| ChannelHeader {
        layout: LayoutKind::Dense,
        ..c.clone()
    };
    let density_points = if h.sparse_density() && !dense { occ } else { points };
    let mut n = (density_points * 4) as u64;
    n += match &h.appearance {
        AppearanceHeader::Rgb(c) | AppearanceHeader::Sh2(c) if dense => channel_bytes(&dense_layout(c), 0),
        AppearanceHeader::Rgb(c) | AppearanceHeader::Sh2(c) => channel_bytes(c, occ),
        AppearanceHeader::Vm { grid, mlp } => {
            vm_bytes(grid) + mlp.layers.iter().map(|l| ((l[0] + 1) * l[1] * 4) as u64).sum::<u64>()
        }
    };
    n += match &h.features {
        Some(FeaturesHeader::Grid(c)) if dense => channel_bytes(&dense_layout(c), 0),
        Some(FeaturesHeader::Grid(c)) => channel_bytes(c, h.feature_occupied.unwrap_or(occ)),
        Some(FeaturesHeader::Vm(v)) => vm_bytes(v),
        None => 0,
    };
    n
}

fn read_channel_grid(
    t: &Tensors,
    name: &str,
    c: &ChannelHeader,
    bounds: Aabb,
    occ: &Option<Arc<RankIndex>>,
) -> Result<ChannelGrid> {
    let geom = GridGeom::new(bounds, c.resolution);
    let [nx, ny, nz] = c.resolution;
    Ok(match c.layout {
        LayoutKind::Dense => ChannelGrid::dense(
            geom,
            c.channels,
            t.channels(name, &[nz, ny, nx, c.channels], c.storage)?,
        ),
        LayoutKind::Sparse => {
            let ix = occ
                .clone()
                .ok_or_else(|| Error::bad_file(t.path, format!("'{name}' is sparse but there is no occupancy")))?;
            let data = t.channels(name, &[ix.count(), c.channels], c.storage)?;
            ChannelGrid::sparse(geom, c.channels, ix.clone(), data)
        }
    })
}

fn read_vm(t: &Tensors, prefix: &str, v: &VmHeader, bounds: Aabb) -> Result<VmGrid> {
    let r = v.resolution;
    let mut planes: [Vec<f32>; 3] = Default::default();
    let mut lines: [Vec<f32>; 3] = Default::default();
    for (m, &(a, b, c)) in MODE_AXES.iter().enumerate() {
        planes[m] = t.f32(&format!("{prefix}.plane{m}"), &[v.comps[m], r[b], r[a]])?;
        lines[m] = t.f32(&format!("{prefix}.line{m}"), &[v.comps[m], r[c]])?;
    }
    let total = v.comps.iter().sum();
    let basis = t.f32(&format!("{prefix}.basis"), &[total, v.out])?;
    Ok(VmGrid {
        geom: GridGeom::new(bounds, r),
        comps: v.comps,
        planes,
        lines,
        basis,
        out: v.out,
    })
}

/// Reads a packed occupancy tensor at `res` and checks its count.
fn read_occupancy(t: &Tensors, name: &str, res: [usize; 3], count: usize) -> Result<Arc<RankIndex>> {
    let n: usize = res.iter().product();
    let bytes = t.u8(name, &[n.div_ceil(64) * 8])?;
    let ix = RankIndex::new(Bitmap::from_bytes(res, &bytes)?);
    if ix.count() != count {
        return Err(Error::bad_file(
            t.path,
            format!("'{name}' has {} voxels set, the header says {count}", ix.count()),
        ));
    }
    Ok(Arc::new(ix))
}

/// Loads a field file, validating everything (see the module docs).
pub fn load(path: &Path) -> Result<Field> {
    let (h, _) = read_header(path)?;
    let bytes = read_all(path)?;
    let t = Tensors {
        st: parse(&bytes, path)?,
        path,
    };
    let bounds = Aabb::new(Vec3::from(h.bounds[0]), Vec3::from(h.bounds[1]));
    let [nx, ny, nz] = h.resolution;
    let geom = GridGeom::new(bounds, h.resolution);
    let occupancy = match h.occupied {
        Some(count) => Some(read_occupancy(&t, "occupancy", h.resolution, count)?),
        None => None,
    };
    let raw = match (&h.density, &occupancy) {
        (Some(d), Some(ix)) if d.layout == LayoutKind::Sparse => {
            let kept = t.f32("density", &[ix.count()])?;
            let mut raw = vec![d.fill; nx * ny * nz];
            for (i, v) in ix.bits().ones().zip(kept) {
                raw[i] = v;
            }
            raw
        }
        _ => t.f32("density", &[nz, ny, nx])?,
    };
    let feature_index = match (&h.feature_occupied, &h.features) {
        (Some(count), Some(FeaturesHeader::Grid(c))) => {
            Some(read_occupancy(&t, "feat.occupancy", c.resolution, *count)?)
        }
        _ => occupancy.clone(),
    };
    let appearance = match &h.appearance {
        AppearanceHeader::Rgb(c) => Appearance::Rgb(read_channel_grid(&t, "app.rgb", c, bounds, &occupancy)?),
        AppearanceHeader::Sh2(c) => Appearance::Sh2(read_channel_grid(&t, "app.sh", c, bounds, &occupancy)?),
        AppearanceHeader::Vm { grid, mlp } => {
            let grid = read_vm(&t, "app.vm", grid, bounds)?;
            let mut layers = vec![];
            for (i, &[inputs, outputs]) in mlp.layers.iter().enumerate() {
                let weight = t.f32(&format!("app.mlp.{i}.weight"), &[outputs, inputs])?;
                let bias = t.f32(&format!("app.mlp.{i}.bias"), &[outputs])?;
                layers.push(Linear {
                    inputs,
                    outputs,
                    weight,
                    bias,
                });
            }
            Appearance::Vm {
                grid,
                mlp: Mlp {
                    feat_pe: mlp.feat_pe,
                    view_pe: mlp.view_pe,
                    layers,
                },
            }
        }
    };
    let features = match &h.features {
        Some(FeaturesHeader::Grid(c)) => Some(Features::Grid(read_channel_grid(
            &t,
            "feat.grid",
            c,
            bounds,
            &feature_index,
        )?)),
        Some(FeaturesHeader::Vm(v)) => Some(Features::Vm(read_vm(&t, "feat.vm", v, bounds)?)),
        None => None,
    };
    let mut field = Field::new(
        DensityGrid {
            geom,
            raw,
            activation: h.activation,
        },
        appearance,
        features,
        occupancy,
    );
    field.source = h.source;
    field.ndc = h.ndc;
    field.up = h.up.map(|u| Vec3::from(u).normalize());
    Ok(field)
}

impl Field {
    pub fn load(path: &Path) -> Result<Field> {
        load(path)
    }
    pub fn save(&self, path: &Path) -> Result<()> {
        save(self, path)
    }
}
