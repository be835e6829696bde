//! Per-voxel ground-truth object labels and their file format.
//!
//! `labels.safetensors`: one tensor `labels` (U8, `[nz, ny, nx]`, x fastest
//! like every grid) and `__metadata__` with `format = "isrf-labels"`,
//! `version = "1"`, `names` (JSON list; label k ≥ 1 is `names[k-1]`, 0 is
//! empty space), `resolution` (JSON `[nx, ny, nz]`) and `bounds` (JSON
//! `[[min], [max]]`). Reading checks all of it before allocating.

use crate::error::{write_atomic, Error, Result};
use crate::field::geom::check_res;
use crate::field::io::{check_format, parse, read_all, read_metadata, serialize, Tensors};
use crate::field::{Aabb, Bitmap, GridGeom};
use glam::Vec3;
use safetensors::tensor::Dtype;
use std::collections::HashMap;
use std::path::Path;

pub const FORMAT: &str = "isrf-labels";
pub const VERSION: u32 = 1;

#[derive(Clone, Debug, PartialEq)]
pub struct Labels {
    pub bounds: Aabb,
    /// `[nx, ny, nz]`, the field's grid.
    pub res: [usize; 3],
    /// Object names; label `k` (1-based) is `names[k - 1]`.
    pub names: Vec<String>,
    /// One label per grid point, x fastest; 0 = empty / none.
    pub data: Vec<u8>,
}

impl Labels {
    pub fn geom(&self) -> GridGeom {
        GridGeom::new(self.bounds, self.res)
    }
    /// Label of the grid point nearest to `p`; 0 outside the grid.
    pub fn at(&self, p: Vec3) -> u8 {
        let g = self.geom();
        g.nearest(p).map_or(0, |[x, y, z]| self.data[g.index(x, y, z)])
    }
    /// Label of an object name.
    pub fn label_of(&self, name: &str) -> Option<u8> {
        self.names.iter().position(|n| n == name).map(|i| i as u8 + 1)
    }
    /// Name of a label (None for 0 and unknown labels).
    pub fn name_of(&self, label: u8) -> Option<&str> {
        (label as usize)
            .checked_sub(1)
            .and_then(|i| self.names.get(i))
            .map(String::as_str)
    }
    /// Voxel count per label, index 0 = empty.
    pub fn counts(&self) -> Vec<usize> {
        let mut c = vec![0; self.names.len() + 1];
        for &l in &self.data {
            if let Some(n) = c.get_mut(l as usize) {
                *n += 1;
            }
        }
        c
    }
    /// The ground-truth mask of one label, for scoring 3D segmentations.
    pub fn mask(&self, label: u8) -> Bitmap {
        Bitmap::from_fn(self.res, |i| self.data[i] == label)
    }
    /// Checks shapes, the name list and that every label names an object.
    pub fn validate(&self) -> Result<()> {
        crate::ensure!(
            self.bounds.is_valid(),
            "labels: bounds {:?} are not a valid box",
            self.bounds
        );
        check_res(self.res, "labels")?;
        let n: usize = self.res.iter().product();
        crate::ensure!(
            self.data.len() == n,
            "labels: {} values for a {:?} grid ({n} points)",
            self.data.len(),
            self.res
        );
        crate::ensure!(
            self.names.len() <= 255,
            "labels: {} names, at most 255 fit in u8 labels",
            self.names.len()
        );
        if let Some(i) = self.data.iter().position(|&l| l as usize > self.names.len()) {
            return Err(Error::invalid(format!(
                "labels: voxel {i} has label {} but there are only {} names",
                self.data[i],
                self.names.len()
            )));
        }
        Ok(())
    }
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        self.validate()?;
        let [nx, ny, nz] = self.res;
        let b = self.bounds;
        let json = |v: serde_json::Value| v.to_string();
        let meta = HashMap::from([
            ("format".to_string(), FORMAT.to_string()),
            ("version".to_string(), VERSION.to_string()),
            ("names".to_string(), json(serde_json::json!(self.names))),
            ("resolution".to_string(), json(serde_json::json!(self.res))),
            (
                "bounds".to_string(),
                json(serde_json::json!([b.min.to_array(), b.max.to_array()])),
            ),
        ]);
        serialize(
            &["labels".to_string()],
            &[(Dtype::U8, vec![nz, ny, nx], self.data.clone())],
            meta,
        )
    }
    /// Writes the labels atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        write_atomic(path, &self.to_bytes()?)
    }
    /// Reads and validates a labels file.
    pub fn load(path: &Path) -> Result<Labels> {
        let (meta, len) = read_metadata(path)?;
        check_format(&meta, FORMAT, VERSION, path)?;
        let field = |key: &str| -> Result<serde_json::Value> {
            let s = meta
                .get(key)
                .ok_or_else(|| Error::bad_file(path, format!("missing '{key}' in metadata")))?;
            serde_json::from_str(s).map_err(|e| Error::bad_file(path, format!("malformed '{key}' in metadata: {e}")))
        };
        let bad =
            |key: &str, e: serde_json::Error| Error::bad_file(path, format!("malformed '{key}' in metadata: {e}"));
        let names: Vec<String> = serde_json::from_value(field("names")?).map_err(|e| bad("names", e))?;
        let res: [usize; 3] = serde_json::from_value(field("resolution")?).map_err(|e| bad("resolution", e))?;
        let bounds: [[f32; 3]; 2] = serde_json::from_value(field("bounds")?).map_err(|e| bad("bounds", e))?;
        let bounds = Aabb::new(Vec3::from(bounds[0]), Vec3::from(bounds[1]));
        let check = |r: Result<()>| r.map_err(|e| Error::bad_file(path, e.to_string()));
        check(check_res(res, "labels"))?;
        check(if bounds.is_valid() {
            Ok(())
        } else {
            Err(Error::invalid(format!("bounds {bounds:?} are not a valid box")))
        })?;
        let n: usize = res.iter().product();
        if n as u64 > len {
            return Err(Error::bad_file(
                path,
                format!("truncated: a {res:?} label grid needs {n} bytes but the file has {len}"),
            ));
        }
        let bytes = read_all(path)?;
        let t = Tensors {
            st: parse(&bytes, path)?,
            path,
        };
        let data = t.u8("labels", &[res[2], res[1], res[0]])?;
        let labels = Labels {
            bounds,
            res,
            names,
            data,
        };
        check(labels.validate())?;
        Ok(labels)
    }
}
