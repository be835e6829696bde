//! Object bitmap files: `.safetensors` with one U8 tensor `bits` (packed
//! little-endian u64 words, x fastest) and metadata `format = "isrf-bitmap"`,
//! `version`, `resolution` (JSON) and `name`.

use crate::error::{write_atomic, Error, Result};
use crate::field::geom::check_res;
use crate::field::io::{check_format, parse, read_all, read_metadata, serialize, Tensors};
use crate::field::Bitmap;
use safetensors::tensor::Dtype;
use std::collections::HashMap;
use std::path::Path;

pub const FORMAT: &str = "isrf-bitmap";
pub const VERSION: u32 = 1;

pub fn bitmap_bytes(bits: &Bitmap, name: &str) -> Result<Vec<u8>> {
    let bytes = bits.to_bytes();
    let mut meta = HashMap::new();
    meta.insert("format".into(), FORMAT.into());
    meta.insert("version".into(), VERSION.to_string());
    meta.insert(
        "resolution".into(),
        serde_json::to_string(&bits.res()).expect("array serialises"),
    );
    meta.insert("name".into(), name.into());
    meta.insert("count".into(), bits.count().to_string());
    serialize(&["bits".to_string()], &[(Dtype::U8, vec![bytes.len()], bytes)], meta)
}

pub fn save_bitmap(path: &Path, bits: &Bitmap, name: &str) -> Result<()> {
    write_atomic(path, &bitmap_bytes(bits, name)?)
}

/// Loads a bitmap and its object name, checking sizes before reading data.
pub fn load_bitmap(path: &Path) -> Result<(Bitmap, String)> {
    let (meta, len) = read_metadata(path)?;
    check_format(&meta, FORMAT, VERSION, path)?;
    let res: [usize; 3] = meta
        .get("resolution")
        .and_then(|r| serde_json::from_str(r).ok())
        .ok_or_else(|| Error::bad_file(path, "missing or malformed 'resolution' in metadata"))?;
    check_res(res, "bitmap").map_err(|e| Error::bad_file(path, e.to_string()))?;
    let n = res.iter().product::<usize>().div_ceil(64) * 8;
    if (n as u64) > len {
        return Err(Error::bad_file(
            path,
            format!("truncated: a {res:?} bitmap needs {n} bytes, the file has {len}"),
        ));
    }
    let bytes = read_all(path)?;
    let t = Tensors {
        st: parse(&bytes, path)?,
        path,
    };
    let data = t.u8("bits", &[n])?;
    let bits = Bitmap::from_bytes(res, &data).map_err(|e| Error::bad_file(path, e.to_string()))?;
    Ok((bits, meta.get("name").cloned().unwrap_or_default()))
}
