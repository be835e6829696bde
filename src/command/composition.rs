//! Compositions on disk: a small human-readable document (JSON, or RON by
//! extension) naming the field files (with a CRC-32 and size so that a
//! changed file is noticed), the objects with their transforms and edits,
//! the segmentation parameters; plus one `.safetensors` sidecar holding the
//! objects' bitmaps (tensor `object.<i>`, packed bits). Both written
//! atomically, the bitmaps first so the document never names missing data.
//! The sidecar's name carries the CRC-32 of its bytes
//! (`<stem>.bitmaps.<crc>.safetensors`), so a save killed between the two
//! writes leaves the old document with its old bitmaps, never the old
//! document with new bitmaps; the old sidecar goes once the new document
//! is in place.

use super::script::Format;
use super::session::Session;
use super::state::{Placement, State};
use super::{Edit, FieldSource};
use crate::error::{write_atomic, Error, Result};
use crate::field::io::{check_format, parse, read_all, read_metadata, serialize, Tensors};
use crate::field::Bitmap;
use crate::segment::SegmentParams;
use crate::util::{affine_from_rows, affine_to_rows};
use glam::Affine3A;
use safetensors::tensor::Dtype;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

pub const FORMAT: &str = "isrf-composition";
pub const VERSION: u32 = 1;
const BITMAPS_FORMAT: &str = "isrf-bitmaps";

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Doc {
    format: String,
    version: u32,
    bitmaps: PathBuf,
    background: [f32; 3],
    params: SegmentParams,
    fields: Vec<FieldDoc>,
    objects: Vec<ObjectDoc>,
}

/// A field: its name, its source and the parts of a [`Placement`] that a
/// whole field has (`transform`, `visible`; removal, duplication and colour
/// edits are object edits), so its keys stay as documents always had them.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct FieldDoc {
    name: String,
    source: FieldSource,
    transform: [[f32; 4]; 4],
    visible: bool,
    #[serde(default)]
    crc32: Option<u32>,
    #[serde(default)]
    bytes: Option<u64>,
}

/// An object: its name, its field's name and its placement (flattened:
/// `transform`, `visible`, `removed`, `duplicate`, `color_edit`, as
/// documents always had them). serde cannot refuse unknown keys through a
/// flattened struct, so they are collected in `unknown` (what the
/// placement leaves) and refused on load.
#[derive(Serialize, Deserialize)]
struct ObjectDoc {
    name: String,
    field: String,
    #[serde(flatten)]
    placement: Placement,
    #[serde(flatten, skip_serializing)]
    unknown: std::collections::BTreeMap<String, serde::de::IgnoredAny>,
}

fn checked(a: Affine3A, what: &str) -> Result<Affine3A> {
    crate::ensure!(
        a.to_cols_array().iter().all(|v| v.is_finite()),
        "{what}: transform has a non-finite value"
    );
    crate::ensure!(crate::util::invertible(&a), "{what}: transform is not invertible");
    Ok(a)
}

fn checksum(path: &Path) -> Result<(u32, u64)> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    Ok((crc32fast::hash(&bytes), bytes.len() as u64))
}

/// Path of `p` relative to `dir` when it lies inside it, else absolute.
fn relative_to(p: &Path, dir: &Path) -> PathBuf {
    let abs = std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    let d = std::fs::canonicalize(dir).unwrap_or_else(|_| dir.to_path_buf());
    abs.strip_prefix(&d).map(Path::to_path_buf).unwrap_or(abs)
}

/// Saves the session's composition to `path` (+
/// `<stem>.bitmaps.<crc>.safetensors`). Returns the files written.
pub fn save(session: &Session, path: &Path) -> Result<Vec<PathBuf>> {
    let st = session.state();
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
        .to_path_buf();
    std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "composition".into());
    let mut fields = vec![];
    for f in &st.fields {
        let (source, crc, bytes) = match &f.source {
            FieldSource::File(p) => {
                let full = if p.is_absolute() {
                    p.clone()
                } else {
                    session.base_dir.join(p)
                };
                let (c, n) = checksum(&full)?;
                (FieldSource::File(relative_to(&full, &dir)), Some(c), Some(n))
            }
            s => (s.clone(), None, None),
        };
        fields.push(FieldDoc {
            name: f.name.clone(),
            source,
            transform: affine_to_rows(&f.placement.transform),
            visible: f.placement.visible,
            crc32: crc,
            bytes,
        });
    }
    let mut names = vec![];
    let mut tensors = vec![];
    let mut res_meta = std::collections::BTreeMap::new();
    for (i, o) in st.objects.iter().enumerate() {
        let b = o.mask.to_bytes();
        names.push(format!("object.{i}"));
        tensors.push((Dtype::U8, vec![b.len()], b));
        res_meta.insert(format!("object.{i}"), o.mask.res());
    }
    let mut meta = HashMap::new();
    meta.insert("format".to_string(), BITMAPS_FORMAT.to_string());
    meta.insert("version".to_string(), VERSION.to_string());
    meta.insert(
        "resolutions".to_string(),
        serde_json::to_string(&res_meta).expect("map serialises"),
    );
    let bitmaps = serialize(&names, &tensors, meta)?;
    let bitmaps_name = PathBuf::from(format!("{stem}.bitmaps.{:08x}.safetensors", crc32fast::hash(&bitmaps)));
    let bitmaps_path = dir.join(&bitmaps_name);
    write_atomic(&bitmaps_path, &bitmaps)?;
    crate::error::failpoint("composition.between_writes");
    let old_bitmaps = sidecar_of(path);
    let objects = st
        .objects
        .iter()
        .map(|o| {
            Ok(ObjectDoc {
                name: o.name.clone(),
                field: st.field_of(o)?.name.clone(),
                placement: o.placement,
                unknown: Default::default(),
            })
        })
        .collect::<Result<_>>()?;
    let doc = Doc {
        format: FORMAT.into(),
        version: VERSION,
        bitmaps: bitmaps_name.clone(),
        background: st.background,
        params: st.params,
        fields,
        objects,
    };
    let text = match format_of(path) {
        Format::Ron => ron::ser::to_string_pretty(&doc, ron::ser::PrettyConfig::default())
            .map_err(|e| Error::invalid(e.to_string()))?,
        Format::Json => serde_json::to_string_pretty(&doc).map_err(|e| Error::invalid(e.to_string()))?,
    };
    write_atomic(path, text.as_bytes())?;
    if let Some(old) = old_bitmaps.filter(|o| *o != bitmaps_name) {
        remove_unused_sidecar(&dir, &stem, &old, path);
    }
    Ok(vec![bitmaps_path, path.to_path_buf()])
}

/// The bitmaps file an existing composition document names, if it is one.
fn sidecar_of(path: &Path) -> Option<PathBuf> {
    let text = std::fs::read_to_string(path).ok()?;
    parse_doc(&text, path).ok().map(|d| d.bitmaps)
}

/// A composition is RON when its name says so, JSON otherwise (the rule
/// of scripts, with JSON for any other extension).
fn format_of(path: &Path) -> Format {
    Format::of(path).unwrap_or(Format::Json)
}

fn parse_doc(text: &str, path: &Path) -> Result<Doc> {
    match format_of(path) {
        Format::Ron => ron::from_str(text).map_err(|e| Error::bad_file(path, format!("not a composition: {e}"))),
        Format::Json => {
            serde_json::from_str(text).map_err(|e| Error::bad_file(path, format!("not a composition: {e}")))
        }
    }
}

/// Removes the sidecar `old` that the document at `path` named before it
/// was overwritten, if it is a sidecar of this stem in this folder and no
/// other composition of the same stem (`.ron` beside `.json`) names it.
/// Best effort: a sidecar left behind only takes space.
fn remove_unused_sidecar(dir: &Path, stem: &str, old: &Path, path: &Path) {
    let name = old.to_string_lossy();
    let ours = old.components().count() == 1
        && name.starts_with(&format!("{stem}.bitmaps."))
        && name.ends_with(".safetensors");
    let named_elsewhere = ["ron", "json"]
        .iter()
        .map(|e| dir.join(format!("{stem}.{e}")))
        .filter(|p| p.file_name() != path.file_name())
        .any(|p| sidecar_of(&p).is_some_and(|b| b == old));
    if ours && !named_elsewhere {
        let _ = std::fs::remove_file(dir.join(old));
    }
}

/// Opens a composition into a fresh session (paths resolve against the
/// document's folder; outputs go to `out_dir`).
pub fn load(path: &Path, out_dir: &Path) -> Result<Session> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let doc = parse_doc(&text, path)?;
    if doc.format != FORMAT {
        return Err(Error::bad_file(
            path,
            format!("this is a '{}' document, not a composition", doc.format),
        ));
    }
    if doc.version > VERSION {
        return Err(Error::bad_file(
            path,
            format!(
                "composition version {} is newer than this isrf reads ({VERSION})",
                doc.version
            ),
        ));
    }
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
        .to_path_buf();
    let mut st = State {
        params: doc.params,
        background: doc.background,
        ..Default::default()
    };
    doc.params
        .validate()
        .map_err(|e| Error::bad_file(path, e.to_string()))?;
    for f in &doc.fields {
        let ctx = |e: Error| Error::bad_file(path, format!("field '{}': {e}", f.name));
        if let (FieldSource::File(p), Some(crc), Some(n)) = (&f.source, f.crc32, f.bytes) {
            let full = if p.is_absolute() { p.clone() } else { dir.join(p) };
            if !full.exists() {
                return Err(ctx(Error::invalid(format!("file '{}' is missing", full.display()))));
            }
            let (c, len) = checksum(&full).map_err(ctx)?;
            if (c, len) != (crc, n) {
                return Err(ctx(Error::invalid(format!(
                    "file '{}' has changed since the composition was saved",
                    full.display()
                ))));
            }
        }
        // Load through the same code path as the LoadField command.
        let mut tmp = Session::new(&dir, out_dir);
        tmp.apply(&Edit::LoadField {
            name: f.name.clone(),
            source: f.source.clone(),
            transform: None,
        })
        .map_err(ctx)?;
        let loaded = &tmp.state().fields[0];
        let placement = Placement {
            transform: checked(affine_from_rows(&f.transform), &f.name).map_err(ctx)?,
            visible: f.visible,
            ..Default::default()
        };
        st.add_field(
            &f.name,
            f.source.clone(),
            loaded.field.clone(),
            placement,
            loaded.demo.clone(),
        );
    }
    let bitmaps_path = dir.join(&doc.bitmaps);
    let (meta, _) = read_metadata(&bitmaps_path)?;
    check_format(&meta, BITMAPS_FORMAT, VERSION, &bitmaps_path)?;
    let res: HashMap<String, [usize; 3]> = meta
        .get("resolutions")
        .and_then(|r| serde_json::from_str(r).ok())
        .ok_or_else(|| Error::bad_file(&bitmaps_path, "missing 'resolutions' in metadata"))?;
    let bytes = read_all(&bitmaps_path)?;
    let t = Tensors {
        st: parse(&bytes, &bitmaps_path)?,
        path: &bitmaps_path,
    };
    for (i, o) in doc.objects.iter().enumerate() {
        let ctx = |e: Error| Error::bad_file(path, format!("object '{}': {e}", o.name));
        if !o.unknown.is_empty() {
            let keys: Vec<&str> = o.unknown.keys().map(String::as_str).collect();
            return Err(ctx(Error::invalid(format!(
                "unknown key(s) {} (an object has name, field, transform, visible, removed, duplicate, color_edit)",
                keys.join(", ")
            ))));
        }
        let field = st.fields.iter().find(|f| f.name == o.field).cloned().ok_or_else(|| {
            ctx(Error::invalid(format!(
                "its field '{}' is not in the composition",
                o.field
            )))
        })?;
        let key = format!("object.{i}");
        let r = *res
            .get(&key)
            .ok_or_else(|| ctx(Error::invalid("its bitmap is missing")))?;
        if r != field.field.res() {
            return Err(Error::bad_file(
                &bitmaps_path,
                format!(
                    "object '{}' (of {}): bitmap resolution {r:?} differs from field '{}' {:?}",
                    o.name,
                    path.display(),
                    o.field,
                    field.field.res()
                ),
            ));
        }
        let n = r.iter().product::<usize>().div_ceil(64) * 8;
        let mask = Bitmap::from_bytes(r, &t.u8(&key, &[n])?).map_err(ctx)?;
        if let Some(e) = &o.placement.color_edit {
            e.validate().map_err(ctx)?;
        }
        let placement = Placement {
            transform: checked(o.placement.transform, &o.name).map_err(ctx)?,
            ..o.placement
        };
        st.add_object(&o.name, field.id, Arc::new(mask), placement);
    }
    Ok(Session::with_state(&dir, out_dir, st))
}
