//! A safetensors file read one tensor at a time, from its offsets.
//!
//! [`super::io::Tensors`] parses a file held whole in memory. For a
//! full-size training checkpoint (lego at 800×800: 906 MB) that doubles
//! what the load holds: the file and the arrays parsed from it, beside the
//! training photos (a resumed run peaked at 2.82 GB). Here only the header
//! is held; each tensor is read straight into the array that keeps it.

use super::io::{check_finite, check_kind, metadata_of, read_header_json};
use crate::error::{Error, Result};
use safetensors::tensor::{Dtype, TensorInfo};
use std::collections::HashMap;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

/// An open safetensors file and its validated header.
pub struct TensorFile<'a> {
    file: File,
    pub path: &'a Path,
    /// Where the data section starts in the file.
    data_start: u64,
    infos: HashMap<String, TensorInfo>,
    metadata: HashMap<String, String>,
}

impl<'a> TensorFile<'a> {
    /// Opens `path` and checks its header: every tensor's byte range matches
    /// its dtype and shape and lies inside the file.
    pub fn open(path: &'a Path) -> Result<TensorFile<'a>> {
        let bad = |r: String| Error::bad_file(path, r);
        let mut file = File::open(path).map_err(|e| Error::io(path, e))?;
        let (header, len) = read_header_json(&mut file, path)?;
        let metadata = metadata_of(&header);
        let data_start = file.stream_position().map_err(|e| Error::io(path, e))?;
        let mut infos = HashMap::new();
        for (name, v) in header {
            if name == "__metadata__" {
                continue;
            }
            let info: TensorInfo =
                serde_json::from_value(v).map_err(|e| bad(format!("corrupt header entry '{name}': {e}")))?;
            let (begin, end) = info.data_offsets;
            let want = info
                .shape
                .iter()
                .try_fold(info.dtype.bitsize() / 8, |a, &d| a.checked_mul(d));
            if end < begin || want != Some(end - begin) || end as u64 > len - data_start {
                return Err(bad(format!(
                    "corrupt or truncated: tensor '{name}' ({:?} {:?}) claims bytes {begin}..{end} of a {}-byte data section",
                    info.dtype,
                    info.shape,
                    len - data_start
                )));
            }
            infos.insert(name, info);
        }
        Ok(TensorFile {
            file,
            path,
            data_start,
            infos,
            metadata,
        })
    }

    /// The header's `__metadata__` map.
    pub fn metadata(&self) -> &HashMap<String, String> {
        &self.metadata
    }

    /// The shape of tensor `name`, if the file has it.
    pub fn shape(&self, name: &str) -> Option<&[usize]> {
        self.infos.get(name).map(|i| &i.shape[..])
    }

    /// The dtype of tensor `name`, if the file has it.
    pub fn dtype(&self, name: &str) -> Option<Dtype> {
        self.infos.get(name).map(|i| i.dtype)
    }

    /// Reads tensor `name`, which must be `dtype` of `shape`, as raw
    /// little-endian words.
    fn read_into<T: bytemuck::Pod>(&self, name: &str, dtype: Dtype, shape: &[usize]) -> Result<Vec<T>> {
        let info = self
            .infos
            .get(name)
            .ok_or_else(|| Error::bad_file(self.path, format!("missing tensor '{name}'")))?;
        check_kind(self.path, name, (info.dtype, &info.shape), (dtype, shape))?;
        let (begin, end) = info.data_offsets;
        let mut out = vec![T::zeroed(); (end - begin) / std::mem::size_of::<T>()];
        let mut f = &self.file;
        f.seek(SeekFrom::Start(self.data_start + begin as u64))
            .and_then(|_| f.read_exact(bytemuck::cast_slice_mut(&mut out)))
            .map_err(|e| Error::io(self.path, e))?;
        Ok(out)
    }

    /// An F32 tensor, every value finite.
    pub fn f32(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>> {
        // The words become floats in place (same size and alignment).
        let v: Vec<f32> = self
            .read_into::<u32>(name, Dtype::F32, shape)?
            .into_iter()
            .map(|w| f32::from_bits(u32::from_le(w)))
            .collect();
        check_finite(self.path, name, v.iter().copied())?;
        Ok(v)
    }

    /// A BF16 tensor, or an F32 one rounded to bf16, every value finite.
    pub fn bf16_or_f32(&self, name: &str, shape: &[usize]) -> Result<Vec<half::bf16>> {
        if self.dtype(name) == Some(Dtype::F32) {
            return Ok(self.f32(name, shape)?.into_iter().map(half::bf16::from_f32).collect());
        }
        let v: Vec<half::bf16> = self
            .read_into::<u16>(name, Dtype::BF16, shape)?
            .into_iter()
            .map(|w| half::bf16::from_bits(u16::from_le(w)))
            .collect();
        check_finite(self.path, name, v.iter().map(|x| x.to_f32()))?;
        Ok(v)
    }

    /// A U8 tensor.
    pub fn u8(&self, name: &str, shape: &[usize]) -> Result<Vec<u8>> {
        self.read_into::<u8>(name, Dtype::U8, shape)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(path: &Path, tensors: &[(&str, Dtype, Vec<usize>, Vec<u8>)]) {
        let views: Vec<(String, safetensors::tensor::TensorView)> = tensors
            .iter()
            .map(|(n, d, s, b)| {
                (
                    n.to_string(),
                    safetensors::tensor::TensorView::new(*d, s.clone(), b).unwrap(),
                )
            })
            .collect();
        safetensors::serialize_to_file(views, None, path).unwrap();
    }

    /// Every tensor comes back as written, the same as the whole-file
    /// reader gives; wrong names, dtypes and shapes, non-finite values and
    /// truncation are errors naming the problem.
    #[test]
    fn tensors_read_from_their_offsets_match_what_was_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.safetensors");
        let floats = [1.5f32, -2.0, 3.25, 0.0, 7.0, -0.5];
        let f32_bytes: Vec<u8> = floats.iter().flat_map(|x| x.to_le_bytes()).collect();
        let halves: Vec<half::bf16> = floats.iter().map(|&x| half::bf16::from_f32(x)).collect();
        let bf16_bytes: Vec<u8> = halves.iter().flat_map(|x| x.to_le_bytes()).collect();
        let nan: Vec<u8> = [1.0f32, f32::NAN].iter().flat_map(|x| x.to_le_bytes()).collect();
        write(
            &path,
            &[
                ("a", Dtype::F32, vec![2, 3], f32_bytes),
                ("m", Dtype::BF16, vec![6], bf16_bytes),
                ("bits", Dtype::U8, vec![3], vec![9, 8, 7]),
                ("nan", Dtype::F32, vec![2], nan),
            ],
        );
        let t = TensorFile::open(&path).unwrap();
        assert_eq!(t.f32("a", &[2, 3]).unwrap(), floats);
        assert_eq!(t.shape("a"), Some(&[2usize, 3][..]));
        assert_eq!(t.bf16_or_f32("m", &[6]).unwrap(), halves);
        assert_eq!(t.bf16_or_f32("a", &[2, 3]).unwrap(), halves, "f32 rounded to bf16");
        assert_eq!(t.u8("bits", &[3]).unwrap(), vec![9, 8, 7]);
        // The whole-file reader agrees.
        let bytes = std::fs::read(&path).unwrap();
        let whole = super::super::io::Tensors {
            st: super::super::io::parse(&bytes, &path).unwrap(),
            path: &path,
        };
        assert_eq!(whole.f32("a", &[2, 3]).unwrap(), t.f32("a", &[2, 3]).unwrap());
        let err = |r: Result<Vec<f32>>| r.unwrap_err().to_string();
        assert!(err(t.f32("b", &[6])).contains("missing tensor 'b'"));
        assert!(err(t.f32("a", &[6])).contains("shape [2, 3]"));
        assert!(err(t.f32("m", &[6])).contains("dtype BF16"));
        assert!(err(t.f32("nan", &[2])).contains("non-finite"));
        // Cut short: the header's last tensor no longer fits.
        let cut = dir.path().join("cut.safetensors");
        std::fs::write(&cut, &bytes[..bytes.len() - 4]).unwrap();
        let e = TensorFile::open(&cut).err().unwrap().to_string();
        assert!(e.contains("truncated"), "{e}");
        std::fs::write(&cut, &bytes[..5]).unwrap();
        assert!(TensorFile::open(&cut).err().unwrap().to_string().contains("too short"));
    }
}
