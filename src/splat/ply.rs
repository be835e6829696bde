//! A strict reader and writer of 3D Gaussian splat `.ply` files in the
//! INRIA layout (binary little-endian, one `vertex` element of scalar
//! properties): `x y z`, optional `nx ny nz`, `f_dc_0..2`, `f_rest_*`
//! (0, 9, 24 or 45 of them: SH degree 0..3, channel-major as INRIA writes
//! them: all of red's coefficients, then green's, then blue's), `opacity`
//! (a logit), `scale_0..2` (logs) and `rot_0..3` (a quaternion w x y z).
//! Other scalar properties are allowed and carried through untouched.
//!
//! Everything the header claims is checked against limits and the file's
//! length before anything is allocated from it; every failure names the file
//! and the problem. The records stay in the file's own bytes, so subsets are
//! written byte for byte.

use crate::error::{Error, Result};
use glam::{Quat, Vec3};
use std::path::Path;

/// Longest header read (real files have well under 2 KiB).
pub const MAX_HEADER: usize = 64 * 1024;
/// Most Gaussians in one file (2^28: a 62 GB file at the usual 248 bytes).
pub const MAX_COUNT: usize = 1 << 28;
/// Most properties per record.
pub const MAX_PROPERTIES: usize = 1024;

/// A property's scalar type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }
    pub fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Property {
    pub name: String,
    pub ty: Scalar,
    /// Byte offset inside a record.
    pub offset: usize,
}

/// Byte offsets of the Gaussian's attributes inside a record (all f32).
#[derive(Clone, Debug, PartialEq)]
pub struct Layout {
    pub pos: [usize; 3],
    pub normal: Option<[usize; 3]>,
    pub dc: [usize; 3],
    /// `f_rest_0..`, in index order (channel-major).
    pub rest: Vec<usize>,
    pub opacity: usize,
    pub scale: [usize; 3],
    pub rot: [usize; 4],
}

impl Layout {
    /// SH coefficients per channel beyond the DC term (0, 3, 8 or 15).
    pub fn rest_per_channel(&self) -> usize {
        self.rest.len() / 3
    }
    /// SH degree of the file (0..=3).
    pub fn degree(&self) -> usize {
        match self.rest_per_channel() {
            0 => 0,
            3 => 1,
            8 => 2,
            _ => 3,
        }
    }
}

/// The header of a splat file.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    pub count: usize,
    pub props: Vec<Property>,
    /// Bytes per record.
    pub stride: usize,
    /// The header's bytes, `ply` to `end_header\n` included.
    pub text: Vec<u8>,
    /// Where the vertex count's digits are in `text` (rewritten for subsets).
    count_span: (usize, usize),
    pub layout: Layout,
}

impl Header {
    /// The header with another vertex count, otherwise byte for byte.
    pub fn with_count(&self, n: usize) -> Vec<u8> {
        let (a, b) = self.count_span;
        let mut out = Vec::with_capacity(self.text.len() + 8);
        out.extend_from_slice(&self.text[..a]);
        out.extend_from_slice(n.to_string().as_bytes());
        out.extend_from_slice(&self.text[b..]);
        out
    }
    pub fn find(&self, name: &str) -> Option<&Property> {
        self.props.iter().find(|p| p.name == name)
    }
}

/// One Gaussian's attributes as stored (activations not applied).
#[derive(Clone, Debug, PartialEq)]
pub struct Gaussian {
    pub pos: Vec3,
    pub dc: [f32; 3],
    /// Channel-major `[r.., g.., b..]`, `3 × rest_per_channel` values.
    pub rest: Vec<f32>,
    /// Logit.
    pub opacity: f32,
    /// Natural logs.
    pub log_scale: [f32; 3],
    /// w x y z, as stored (not necessarily unit length).
    pub rot: [f32; 4],
}

impl Gaussian {
    pub fn alpha(&self) -> f32 {
        1.0 / (1.0 + (-self.opacity).exp())
    }
    pub fn scales(&self) -> Vec3 {
        Vec3::from(self.log_scale.map(f32::exp))
    }
    /// Unit rotation (identity for a zero quaternion).
    pub fn rotation(&self) -> Quat {
        let [w, x, y, z] = self.rot;
        let q = Quat::from_xyzw(x, y, z, w);
        if q.length_squared() > 1e-20 && q.is_finite() {
            q.normalize()
        } else {
            Quat::IDENTITY
        }
    }
    /// True when every attribute is finite.
    pub fn is_finite(&self) -> bool {
        self.pos.is_finite()
            && self.dc.iter().chain(&self.rest).all(|v| v.is_finite())
            && self.opacity.is_finite()
            && self.log_scale.iter().chain(&self.rot).all(|v| v.is_finite())
    }
}

/// A splat file in memory: its header and the bytes of its records.
#[derive(Clone, Debug)]
pub struct SplatFile {
    pub header: Header,
    /// `count × stride` bytes.
    pub records: Vec<u8>,
}

#[inline]
pub fn f32_at(rec: &[u8], off: usize) -> f32 {
    f32::from_le_bytes([rec[off], rec[off + 1], rec[off + 2], rec[off + 3]])
}

#[inline]
pub fn put_f32(rec: &mut [u8], off: usize, v: f32) {
    rec[off..off + 4].copy_from_slice(&v.to_le_bytes());
}

impl SplatFile {
    pub fn len(&self) -> usize {
        self.header.count
    }
    pub fn is_empty(&self) -> bool {
        self.header.count == 0
    }
    pub fn record(&self, i: usize) -> &[u8] {
        let s = self.header.stride;
        &self.records[i * s..(i + 1) * s]
    }
    /// Centre of Gaussian `i` (cheaper than [`SplatFile::gaussian`]).
    pub fn position(&self, i: usize) -> Vec3 {
        let r = self.record(i);
        let p = self.header.layout.pos;
        Vec3::new(f32_at(r, p[0]), f32_at(r, p[1]), f32_at(r, p[2]))
    }
    /// True when every splat attribute of record `i` is finite (no decoding).
    pub fn is_finite(&self, i: usize) -> bool {
        let r = self.record(i);
        let l = &self.header.layout;
        let mut offs = l.pos.iter().chain(&l.dc).chain(&l.rest).chain(&l.scale).chain(&l.rot);
        offs.all(|&o| f32_at(r, o).is_finite()) && f32_at(r, l.opacity).is_finite()
    }
    pub fn gaussian(&self, i: usize) -> Gaussian {
        decode(self.record(i), &self.header.layout)
    }
    /// Reads and checks a splat file.
    pub fn read(path: &Path) -> Result<SplatFile> {
        let bytes = read_capped(path)?;
        Self::parse(bytes).map_err(|r| Error::bad_file(path, r))
    }
    /// Parses a whole file's bytes (header, then exactly `count` records).
    pub fn parse(mut bytes: Vec<u8>) -> std::result::Result<SplatFile, String> {
        let header = parse_header(&bytes)?;
        let body = bytes.len() - header.text.len();
        let need = header
            .count
            .checked_mul(header.stride)
            .ok_or("vertex count × record size overflows")?;
        if body < need {
            return Err(format!(
                "truncated: {} Gaussians of {} bytes need {need} bytes after the header, the file has {body}",
                header.count, header.stride
            ));
        }
        if body > need {
            return Err(format!(
                "{} bytes after the last of the {} Gaussians (a second element or a damaged file)",
                body - need,
                header.count
            ));
        }
        bytes.drain(..header.text.len());
        Ok(SplatFile { header, records: bytes })
    }
}

/// Reads a file whose length is first checked against what a splat file of
/// [`MAX_COUNT`] Gaussians could hold.
fn read_capped(path: &Path) -> Result<Vec<u8>> {
    let len = std::fs::metadata(path).map_err(|e| Error::io(path, e))?.len();
    let cap = (MAX_HEADER + MAX_COUNT * 4 * MAX_PROPERTIES) as u64;
    if len > cap {
        return Err(Error::bad_file(
            path,
            format!("{len} bytes is too large for a splat file"),
        ));
    }
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

pub fn decode(rec: &[u8], l: &Layout) -> Gaussian {
    let f = |o: usize| f32_at(rec, o);
    Gaussian {
        pos: Vec3::new(f(l.pos[0]), f(l.pos[1]), f(l.pos[2])),
        dc: l.dc.map(f),
        rest: l.rest.iter().map(|&o| f(o)).collect(),
        opacity: f(l.opacity),
        log_scale: l.scale.map(f),
        rot: l.rot.map(f),
    }
}

/// Writes `g`'s attributes into a record laid out as `l` (other bytes kept).
pub fn encode(g: &Gaussian, l: &Layout, rec: &mut [u8]) {
    for a in 0..3 {
        put_f32(rec, l.pos[a], g.pos[a]);
        put_f32(rec, l.dc[a], g.dc[a]);
        put_f32(rec, l.scale[a], g.log_scale[a]);
    }
    for (&o, &v) in l.rest.iter().zip(&g.rest) {
        put_f32(rec, o, v);
    }
    put_f32(rec, l.opacity, g.opacity);
    for a in 0..4 {
        put_f32(rec, l.rot[a], g.rot[a]);
    }
}

/// Header lines, each with its start offset.
type Lines<'a> = Vec<(usize, &'a str)>;

/// The header lines up to `end_header`, and the header's length.
fn header_lines(bytes: &[u8]) -> std::result::Result<(Lines<'_>, usize), String> {
    if !bytes.starts_with(b"ply\n") && !bytes.starts_with(b"ply\r\n") {
        return Err("not a .ply file (it does not start with 'ply')".into());
    }
    let window = &bytes[..bytes.len().min(MAX_HEADER)];
    let end = find(window, b"end_header\n")
        .map(|i| i + 11)
        .or_else(|| find(window, b"end_header\r\n").map(|i| i + 12))
        .ok_or_else(|| format!("no 'end_header' line in the first {MAX_HEADER} bytes"))?;
    let text = std::str::from_utf8(&bytes[..end]).map_err(|_| "the header is not text (UTF-8)".to_string())?;
    let mut lines = vec![];
    let mut at = 0;
    for line in text.split_inclusive('\n') {
        lines.push((at, line.trim_end_matches(['\n', '\r'])));
        at += line.len();
    }
    Ok((lines, end))
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// Parses and checks the header (format, the one vertex element, its
/// properties and the splat attributes' presence and types).
pub fn parse_header(bytes: &[u8]) -> std::result::Result<Header, String> {
    let (lines, end) = header_lines(bytes)?;
    let mut format_ok = false;
    let mut vertex: Option<(usize, (usize, usize))> = None;
    let mut in_vertex = false;
    let mut props: Vec<Property> = vec![];
    let mut stride = 0usize;
    for (no, &(at, line)) in lines.iter().enumerate().skip(1) {
        let words: Vec<&str> = line.split_ascii_whitespace().collect();
        let lineno = no + 1;
        match words.as_slice() {
            [] | ["comment", ..] | ["obj_info", ..] | ["end_header"] => {}
            ["format", f, v] => {
                if *f != "binary_little_endian" {
                    return Err(format!(
                        "format '{f}' is not supported (only binary_little_endian, as splat tools write)"
                    ));
                }
                if *v != "1.0" {
                    return Err(format!("ply version '{v}' is not 1.0"));
                }
                format_ok = true;
            }
            ["element", name, n] => {
                let n: usize = n
                    .parse()
                    .map_err(|_| format!("line {lineno}: element count '{n}' is not a number"))?;
                if *name == "vertex" && vertex.is_none() && props.is_empty() {
                    if n > MAX_COUNT {
                        return Err(format!("{n} Gaussians is more than this reader accepts ({MAX_COUNT})"));
                    }
                    let start = at + line.rfind(words[2]).unwrap_or(0);
                    vertex = Some((n, (start, start + words[2].len())));
                    in_vertex = true;
                } else if n == 0 {
                    in_vertex = false;
                } else if *name == "chunk" {
                    return Err("a compressed .ply (element 'chunk') is not supported: decompress it first (e.g. splat-transform in.compressed.ply out.ply)".into());
                } else {
                    return Err(format!(
                        "line {lineno}: element '{name}' ({n} items): a splat file holds one 'vertex' element only"
                    ));
                }
            }
            ["property", "list", ..] => return Err(format!("line {lineno}: list properties are not supported")),
            ["property", ty, name] => {
                if !in_vertex {
                    continue;
                }
                let ty = Scalar::parse(ty).ok_or_else(|| format!("line {lineno}: unknown property type '{ty}'"))?;
                if props.len() >= MAX_PROPERTIES {
                    return Err(format!("more than {MAX_PROPERTIES} properties"));
                }
                if props.iter().any(|p| p.name == *name) {
                    return Err(format!("property '{name}' appears twice"));
                }
                props.push(Property {
                    name: name.to_string(),
                    ty,
                    offset: stride,
                });
                stride += ty.size();
            }
            _ => return Err(format!("line {lineno}: cannot read '{}'", clip(line))),
        }
    }
    if !format_ok {
        return Err("no 'format' line".into());
    }
    let (count, count_span) = vertex.ok_or("no 'element vertex' line")?;
    let layout = layout(&props)?;
    Ok(Header {
        count,
        props,
        stride,
        text: bytes[..end].to_vec(),
        count_span,
        layout,
    })
}

fn clip(s: &str) -> String {
    s.chars().take(60).collect()
}

/// Finds the splat attributes among the properties (each must be a float).
fn layout(props: &[Property]) -> std::result::Result<Layout, String> {
    let get = |name: &str| -> std::result::Result<usize, String> {
        let p = props
            .iter()
            .find(|p| p.name == name)
            .ok_or_else(|| format!("missing property '{name}' (not a 3D Gaussian splat file?)"))?;
        if p.ty != Scalar::F32 {
            return Err(format!("property '{name}' is {:?}, expected float", p.ty));
        }
        Ok(p.offset)
    };
    let three =
        |a: &str, b: &str, c: &str| -> std::result::Result<[usize; 3], String> { Ok([get(a)?, get(b)?, get(c)?]) };
    let n_rest = props.iter().filter(|p| p.name.starts_with("f_rest_")).count();
    if ![0, 9, 24, 45].contains(&n_rest) {
        return Err(format!(
            "{n_rest} f_rest_* properties: expected 0, 9, 24 or 45 (SH degree 0 to 3)"
        ));
    }
    let rest = (0..n_rest)
        .map(|i| get(&format!("f_rest_{i}")))
        .collect::<std::result::Result<Vec<_>, _>>()?;
    let normal = match props.iter().any(|p| p.name == "nx") {
        true => Some(three("nx", "ny", "nz")?),
        false => None,
    };
    Ok(Layout {
        pos: three("x", "y", "z")?,
        normal,
        dc: three("f_dc_0", "f_dc_1", "f_dc_2")?,
        rest,
        opacity: get("opacity")?,
        scale: three("scale_0", "scale_1", "scale_2")?,
        rot: [get("rot_0")?, get("rot_1")?, get("rot_2")?, get("rot_3")?],
    })
}

/// The header INRIA's trainer writes, for `count` Gaussians of SH `degree`.
pub fn standard_header(count: usize, degree: usize) -> std::result::Result<Header, String> {
    let n_rest = 3 * ((degree + 1) * (degree + 1) - 1);
    let mut text = format!("ply\nformat binary_little_endian 1.0\nelement vertex {count}\n");
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        .map(String::from)
        .to_vec();
    names.extend((0..n_rest).map(|i| format!("f_rest_{i}")));
    names.extend(
        [
            "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
        ]
        .map(String::from),
    );
    for n in &names {
        text.push_str(&format!("property float {n}\n"));
    }
    text.push_str("end_header\n");
    parse_header(text.as_bytes())
}

/// Writes a header and records atomically.
pub fn write(path: &Path, header: &[u8], records: &[u8]) -> Result<()> {
    let mut bytes = Vec::with_capacity(header.len() + records.len());
    bytes.extend_from_slice(header);
    bytes.extend_from_slice(records);
    crate::error::write_atomic(path, &bytes)
}

/// New records in the standard layout, one per Gaussian (`g.rest` must hold
/// the degree's coefficients; normals are written as zeros).
pub fn standard_bytes(gaussians: &[Gaussian], degree: usize) -> std::result::Result<Vec<u8>, String> {
    let h = standard_header(gaussians.len(), degree)?;
    let mut out = h.text.clone();
    let start = out.len();
    out.resize(start + gaussians.len() * h.stride, 0);
    for (g, rec) in gaussians.iter().zip(out[start..].chunks_exact_mut(h.stride)) {
        if g.rest.len() != h.layout.rest.len() {
            return Err(format!(
                "a Gaussian has {} SH rest values, degree {degree} needs {}",
                g.rest.len(),
                h.layout.rest.len()
            ));
        }
        encode(g, &h.layout, rec);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(degree: usize) -> Gaussian {
        let n = 3 * ((degree + 1) * (degree + 1) - 1);
        Gaussian {
            pos: Vec3::new(1.0, -2.0, 3.5),
            dc: [0.1, 0.2, 0.3],
            rest: (0..n).map(|i| i as f32 * 0.01).collect(),
            opacity: 1.5,
            log_scale: [-3.0, -2.0, -4.0],
            rot: [1.0, 0.0, 0.0, 0.0],
        }
    }

    #[test]
    fn standard_files_round_trip_at_every_degree() {
        for degree in 0..=3 {
            let g = [one(degree), one(degree)];
            let bytes = standard_bytes(&g, degree).unwrap();
            let f = SplatFile::parse(bytes).unwrap();
            assert_eq!(f.len(), 2);
            assert_eq!(f.header.layout.degree(), degree);
            assert_eq!(f.header.stride, 4 * (17 + 3 * ((degree + 1) * (degree + 1) - 1)));
            assert_eq!(f.gaussian(1), g[1]);
        }
    }

    #[test]
    fn header_count_is_rewritten_in_place() {
        let f = SplatFile::parse(standard_bytes(&[one(1)], 1).unwrap()).unwrap();
        let h = String::from_utf8(f.header.with_count(12345)).unwrap();
        assert!(h.contains("element vertex 12345\n"));
        assert_eq!(h.len(), f.header.text.len() + 4);
    }

    #[test]
    fn bad_headers_are_named() {
        let good = String::from_utf8(standard_header(1, 0).unwrap().text).unwrap();
        let cases = [
            (good.replace("binary_little_endian", "ascii"), "ascii"),
            (
                good.replace("binary_little_endian", "binary_big_endian"),
                "binary_big_endian",
            ),
            (
                good.replace("property float opacity\n", ""),
                "missing property 'opacity'",
            ),
            (
                good.replace("property float x\n", "property double x\n"),
                "expected float",
            ),
            (good.replace("vertex 1", "vertex 99999999999"), "more than"),
            (good.replace("vertex 1", "vertex -1"), "not a number"),
            (good.replace("end_header", "end_heade"), "end_header"),
            ("PLY\n".to_string(), "does not start"),
        ];
        for (text, want) in cases {
            let err = SplatFile::parse(text.into_bytes()).unwrap_err();
            assert!(err.contains(want), "{err} lacks {want}");
        }
    }

    #[test]
    fn truncated_and_padded_bodies_are_refused_before_allocating() {
        let bytes = standard_bytes(&[one(0), one(0)], 0).unwrap();
        let short = bytes[..bytes.len() - 3].to_vec();
        assert!(SplatFile::parse(short).unwrap_err().contains("truncated"));
        let mut long = bytes.clone();
        long.push(0);
        assert!(SplatFile::parse(long).unwrap_err().contains("after the last"));
        let mut rest = bytes;
        rest.extend_from_slice(b"x");
        // A count far beyond the bytes present is refused from the header.
        let huge = String::from_utf8(standard_header(1 << 27, 0).unwrap().text).unwrap();
        assert!(SplatFile::parse(huge.into_bytes()).unwrap_err().contains("truncated"));
    }

    #[test]
    fn wrong_rest_counts_and_duplicates_are_refused() {
        let good = String::from_utf8(standard_header(0, 1).unwrap().text).unwrap();
        let eight = good.replace("property float f_rest_8\n", "");
        assert!(SplatFile::parse(eight.into_bytes()).unwrap_err().contains("8 f_rest"));
        let dup = good.replace("property float f_rest_8\n", "property float f_rest_7\n");
        assert!(SplatFile::parse(dup.into_bytes()).unwrap_err().contains("twice"));
    }
}
