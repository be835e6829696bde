//! A strict reader for NumPy `.npy` files and the arrays inside `.npz`
//! archives: float arrays (f2, f4, f8, either byte order) in C order.
//!
//! Our own parser rather than a general one because these files come from
//! users: the header's length is checked against the file and a cap before
//! anything is allocated, the header dict is read by a small parser that
//! never backtracks (one pass, bounded by the header's length), and the
//! shape's element and byte counts use checked arithmetic and must match the
//! bytes present. So the work and memory of a read are bounded by the file.

use std::io::Read;

/// The longest header we accept. NumPy writes 128 bytes or so and its own
/// reader refuses more than 10,000 by default.
const MAX_HEADER_LEN: usize = 65_536;
/// The most dimensions we accept (NumPy allows 64).
const MAX_DIMS: usize = 32;
/// The largest array inside an `.npz` archive (decompressed).
const MAX_NPZ_ARRAY_BYTES: u64 = 1 << 30;

const MAGIC: &[u8] = b"\x93NUMPY";

/// Element type of an array.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dtype {
    F16,
    F32,
    F64,
}

impl Dtype {
    fn size(self) -> usize {
        match self {
            Dtype::F16 => 2,
            Dtype::F32 => 4,
            Dtype::F64 => 8,
        }
    }
}

/// A parsed `.npy`: its shape and element type, and the raw data bytes.
#[derive(Clone, Debug, PartialEq)]
pub struct Array<'a> {
    pub shape: Vec<usize>,
    pub dtype: Dtype,
    big_endian: bool,
    data: &'a [u8],
}

impl Array<'_> {
    /// Number of elements (the shape's product, already checked).
    pub fn len(&self) -> usize {
        self.data.len() / self.dtype.size()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The values as f64 (exact for every supported type).
    pub fn to_f64(&self) -> Vec<f64> {
        let n = self.dtype.size();
        self.data.chunks_exact(n).map(|b| self.value(b)).collect()
    }

    /// The values as f32 (f64 values are rounded).
    pub fn to_f32(&self) -> Vec<f32> {
        let n = self.dtype.size();
        self.data.chunks_exact(n).map(|b| self.value(b) as f32).collect()
    }

    fn value(&self, b: &[u8]) -> f64 {
        let be = self.big_endian;
        match self.dtype {
            Dtype::F16 => {
                let bits = [b[0], b[1]];
                let h = if be {
                    u16::from_be_bytes(bits)
                } else {
                    u16::from_le_bytes(bits)
                };
                half::f16::from_bits(h).to_f64()
            }
            Dtype::F32 => {
                let bits = [b[0], b[1], b[2], b[3]];
                f64::from(if be {
                    f32::from_be_bytes(bits)
                } else {
                    f32::from_le_bytes(bits)
                })
            }
            Dtype::F64 => {
                let bits: [u8; 8] = b.try_into().expect("chunks of 8");
                if be {
                    f64::from_be_bytes(bits)
                } else {
                    f64::from_le_bytes(bits)
                }
            }
        }
    }
}

/// Parses a whole `.npy` file held in memory. Errors say what is wrong in
/// words (the caller adds the file name).
pub fn parse(bytes: &[u8]) -> Result<Array<'_>, String> {
    let (header, data) = split_header(bytes)?;
    let h = parse_header(header)?;
    if h.fortran_order {
        return Err("Fortran-ordered arrays are not supported; save with C order".into());
    }
    let (dtype, big_endian) = parse_descr(&h.descr)?;
    let count = h
        .shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| format!("shape {:?} has more elements than memory can hold", h.shape))?;
    let need = count.checked_mul(dtype.size()).ok_or_else(|| {
        format!(
            "shape {:?} of '{}' needs more bytes than memory can hold",
            h.shape, h.descr
        )
    })?;
    if data.len() != need {
        let what = if data.len() < need { "truncated" } else { "corrupt" };
        return Err(format!(
            "{what}: shape {:?} of '{}' needs {need} data bytes, the file has {}",
            h.shape,
            h.descr,
            data.len()
        ));
    }
    Ok(Array {
        shape: h.shape,
        dtype,
        big_endian,
        data,
    })
}

/// Checks the magic and version and splits off the header text, its length
/// checked against the file and [`MAX_HEADER_LEN`].
fn split_header(bytes: &[u8]) -> Result<(&str, &[u8]), String> {
    if bytes.len() < MAGIC.len() + 2 || &bytes[..MAGIC.len()] != MAGIC {
        return Err("not a .npy file (no \\x93NUMPY magic)".into());
    }
    let (major, minor) = (bytes[6], bytes[7]);
    let (len_bytes, rest) = match major {
        1 => (2, &bytes[8..]),
        2 | 3 => (4, &bytes[8..]),
        _ => {
            return Err(format!(
                ".npy format version {major}.{minor} is not supported (1, 2 or 3)"
            ))
        }
    };
    if rest.len() < len_bytes {
        return Err("truncated: the file ends inside the header length".into());
    }
    let mut n = [0u8; 4];
    n[..len_bytes].copy_from_slice(&rest[..len_bytes]);
    let header_len = u32::from_le_bytes(n) as usize;
    let rest = &rest[len_bytes..];
    if header_len > MAX_HEADER_LEN || header_len > rest.len() {
        return Err(format!(
            "corrupt header length {header_len}: the file has {} bytes after it (at most {MAX_HEADER_LEN} allowed)",
            rest.len()
        ));
    }
    let (header, data) = rest.split_at(header_len);
    // Versions 1 and 2 are ASCII (latin-1 in principle); 3 is UTF-8. The
    // keys and values we accept are ASCII in all three.
    let header = std::str::from_utf8(header).map_err(|_| "the header is not text".to_string())?;
    Ok((header, data))
}

/// The three entries of a `.npy` header dict.
#[derive(Debug, PartialEq)]
struct Header {
    descr: String,
    fortran_order: bool,
    shape: Vec<usize>,
}

/// Parses `{'descr': '<f8', 'fortran_order': False, 'shape': (3, 17), }`
/// (whitespace, quotes and trailing commas as Python writes them). One
/// left-to-right pass with no nesting beyond the shape tuple: the time is
/// linear in the header's length whatever it holds.
fn parse_header(text: &str) -> Result<Header, String> {
    let mut p = Lexer {
        s: text.as_bytes(),
        i: 0,
    };
    let (mut descr, mut fortran, mut shape) = (None, None, None);
    p.expect(b'{')?;
    while !p.eat(b'}') {
        let key = p.string()?;
        p.expect(b':')?;
        let fresh = match key {
            "descr" => descr.replace(p.string()?.to_string()).is_none(),
            "fortran_order" => fortran.replace(p.boolean()?).is_none(),
            "shape" => shape.replace(p.shape()?).is_none(),
            other => {
                return Err(format!(
                    "unexpected key '{}' in the .npy header",
                    other.escape_default()
                ))
            }
        };
        if !fresh {
            return Err(format!("key '{key}' appears twice in the .npy header"));
        }
        if !p.eat(b',') {
            p.expect(b'}')?;
            break;
        }
    }
    p.skip_ws();
    if p.i != p.s.len() {
        return Err(format!("unexpected text after the .npy header dict at byte {}", p.i));
    }
    let missing = |k: &str| format!("the .npy header has no '{k}'");
    Ok(Header {
        descr: descr.ok_or_else(|| missing("descr"))?,
        fortran_order: fortran.ok_or_else(|| missing("fortran_order"))?,
        shape: shape.ok_or_else(|| missing("shape"))?,
    })
}

/// `<f8`, `>f4`, `<f2` (and `=`, native, taken as little-endian).
fn parse_descr(descr: &str) -> Result<(Dtype, bool), String> {
    let (big, ty) = match descr.as_bytes().first() {
        Some(b'<') | Some(b'=') => (false, &descr[1..]),
        Some(b'>') => (true, &descr[1..]),
        _ => (false, descr),
    };
    let dtype = match ty {
        "f2" => Dtype::F16,
        "f4" => Dtype::F32,
        "f8" => Dtype::F64,
        _ => {
            return Err(format!(
                "dtype '{}' is not supported (float16, float32 or float64)",
                descr.escape_default()
            ))
        }
    };
    Ok((dtype, big))
}

/// A cursor over the header bytes.
struct Lexer<'a> {
    s: &'a [u8],
    i: usize,
}

impl<'a> Lexer<'a> {
    fn skip_ws(&mut self) {
        while self.i < self.s.len() && self.s[self.i].is_ascii_whitespace() {
            self.i += 1;
        }
    }
    fn peek(&mut self) -> Option<u8> {
        self.skip_ws();
        self.s.get(self.i).copied()
    }
    fn eat(&mut self, c: u8) -> bool {
        let hit = self.peek() == Some(c);
        self.i += usize::from(hit);
        hit
    }
    fn expect(&mut self, c: u8) -> Result<(), String> {
        if self.eat(c) {
            return Ok(());
        }
        Err(match self.peek() {
            Some(got) => format!(
                "malformed .npy header: expected '{}' at byte {}, found '{}'",
                c as char,
                self.i,
                (got as char).escape_default()
            ),
            None => format!("malformed .npy header: expected '{}' at its end", c as char),
        })
    }
    /// A quoted string without escapes ('...' or "...").
    fn string(&mut self) -> Result<&'a str, String> {
        let q = match self.peek() {
            Some(q @ (b'\'' | b'"')) => q,
            _ => {
                return Err(format!(
                    "malformed .npy header: expected a quoted string at byte {}",
                    self.i
                ))
            }
        };
        let start = self.i + 1;
        let len = self.s[start..]
            .iter()
            .position(|&c| c == q || c == b'\\')
            .filter(|&n| self.s[start + n] == q)
            .ok_or_else(|| format!("malformed .npy header: unterminated string at byte {}", self.i))?;
        self.i = start + len + 1;
        // The header is valid UTF-8 and quotes are ASCII: a valid slice.
        Ok(std::str::from_utf8(&self.s[start..start + len]).expect("UTF-8 between ASCII quotes"))
    }
    fn boolean(&mut self) -> Result<bool, String> {
        self.skip_ws();
        for (word, value) in [("True", true), ("False", false)] {
            if self.s[self.i..].starts_with(word.as_bytes()) {
                self.i += word.len();
                return Ok(value);
            }
        }
        Err(format!(
            "malformed .npy header: expected True or False at byte {}",
            self.i
        ))
    }
    /// `(a, b, ...)` with an optional trailing comma; `()` is a scalar.
    fn shape(&mut self) -> Result<Vec<usize>, String> {
        self.expect(b'(')?;
        let mut dims = Vec::new();
        while !self.eat(b')') {
            if dims.len() == MAX_DIMS {
                return Err(format!("the .npy shape has more than {MAX_DIMS} dimensions"));
            }
            dims.push(self.dim()?);
            if !self.eat(b',') {
                self.expect(b')')?;
                break;
            }
        }
        Ok(dims)
    }
    /// A non-negative integer (Python 2 files may add an `L`).
    fn dim(&mut self) -> Result<usize, String> {
        self.skip_ws();
        let start = self.i;
        let mut v: usize = 0;
        while let Some(d) = self.s.get(self.i).filter(|c| c.is_ascii_digit()) {
            v = v
                .checked_mul(10)
                .and_then(|v| v.checked_add(usize::from(d - b'0')))
                .ok_or_else(|| format!("the .npy shape has a dimension too large at byte {start}"))?;
            self.i += 1;
        }
        if self.i == start {
            return Err(format!("malformed .npy header: expected a dimension at byte {start}"));
        }
        self.i += usize::from(self.s.get(self.i) == Some(&b'L'));
        Ok(v)
    }
}

/// Reads the first array of an `.npz` archive (NumPy's `savez`, stored or
/// deflated). The array's declared size is checked against a cap before it
/// is decompressed, and no more than that is read.
pub fn read_npz_first(bytes: &[u8]) -> Result<Vec<u8>, String> {
    let mut zip =
        zip::ZipArchive::new(std::io::Cursor::new(bytes)).map_err(|e| format!("not a .npz (zip) archive: {e}"))?;
    if zip.is_empty() {
        return Err("the archive holds no array".into());
    }
    let mut names: Vec<String> = zip.file_names().map(str::to_string).collect();
    names.sort();
    let name = &names[0];
    let mut file = zip
        .by_name(name)
        .map_err(|e| format!("cannot read '{name}' in the archive: {e}"))?;
    let size = file.size();
    if size > MAX_NPZ_ARRAY_BYTES {
        return Err(format!(
            "array '{name}' is {size} bytes decompressed, more than the {MAX_NPZ_ARRAY_BYTES} allowed"
        ));
    }
    // No allocation from the declared size: the buffer grows with what
    // really inflates, and reading stops one byte past the declared size (a
    // member that inflates beyond it is corrupt and must not grow without
    // bound).
    let mut out = Vec::new();
    file.by_ref()
        .take(size + 1)
        .read_to_end(&mut out)
        .map_err(|e| format!("cannot decompress '{name}': {e}"))?;
    if out.len() as u64 != size {
        return Err(format!("array '{name}' does not have its declared size {size}"));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `.npy` v1 file as NumPy writes it.
    pub fn npy(descr: &str, shape: &str, data: &[u8]) -> Vec<u8> {
        let mut h = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
        while (10 + h.len() + 1) % 64 != 0 {
            h.push(' ');
        }
        h.push('\n');
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&[1, 0]);
        out.extend_from_slice(&(h.len() as u16).to_le_bytes());
        out.extend_from_slice(h.as_bytes());
        out.extend_from_slice(data);
        out
    }

    fn f64s(v: &[f64]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    #[test]
    fn reads_numpy_files() {
        let file = npy("<f8", "(2, 3)", &f64s(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.5]));
        let a = parse(&file).unwrap();
        assert_eq!(a.shape, vec![2, 3]);
        assert_eq!(a.dtype, Dtype::F64);
        assert_eq!(a.to_f64(), vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.5]);
        let be: Vec<u8> = [1.5f32, -2.0].iter().flat_map(|x| x.to_be_bytes()).collect();
        assert_eq!(parse(&npy(">f4", "(2,)", &be)).unwrap().to_f32(), vec![1.5, -2.0]);
        let h: Vec<u8> = half::f16::from_f32(0.25).to_le_bytes().to_vec();
        assert_eq!(parse(&npy("<f2", "(1, 1, 1)", &h)).unwrap().to_f32(), vec![0.25]);
    }

    #[test]
    fn header_variants() {
        let h = parse_header("{\"shape\":(4L,17,),\"fortran_order\":True,\"descr\":'<f4'}  \n").unwrap();
        assert_eq!(h.shape, vec![4, 17]);
        assert!(h.fortran_order);
        assert_eq!(
            parse_header("{'descr': '<f8', 'fortran_order': False, 'shape': ()}")
                .unwrap()
                .shape,
            Vec::<usize>::new()
        );
    }

    #[test]
    fn rejects_bad_headers_with_reasons() {
        let err = |t: &str| parse_header(t).unwrap_err();
        assert!(err("{'descr': '<f8', 'shape': (1,)}").contains("no 'fortran_order'"));
        assert!(err("{'descr': '<f8', 'descr': '<f8'}").contains("twice"));
        assert!(err("{'descr': [[[[<f8]]]]}").contains("quoted string"));
        assert!(err("{{{{{{{{{{{{{").contains("quoted string"));
        assert!(err("{'shape': (99999999999999999999999, 17)}").contains("too large"));
        assert!(err("{'evil': 1}").contains("unexpected key"));
        assert!(err("{'descr': '<f8', 'fortran_order': False, 'shape': (1,)} x").contains("after"));
        let deep = format!("{{'shape': ({})}}", "1,".repeat(40));
        assert!(err(&deep).contains("more than 32"));
    }

    #[test]
    fn shape_and_length_checked_against_the_data() {
        // (2^62, 17) of f8: the element count overflows.
        let e = parse(&npy("<f8", "(4611686018427387904, 17)", &[])).unwrap_err();
        assert!(e.contains("more"), "{e}");
        let e = parse(&npy("<f8", "(3, 17)", &f64s(&[0.0; 17]))).unwrap_err();
        assert!(e.contains("truncated") && e.contains("408"), "{e}");
        let e = parse(&npy("<i8", "(1,)", &[0; 8])).unwrap_err();
        assert!(e.contains("dtype '<i8'"), "{e}");
        // A header length beyond the file.
        let mut f = npy("<f8", "(1,)", &f64s(&[1.0]));
        f[8..10].copy_from_slice(&u16::MAX.to_le_bytes());
        assert!(parse(&f).unwrap_err().contains("header length 65535"));
        assert!(parse(b"\x93NUMPY\x07\x00").unwrap_err().contains("version 7"));
        assert!(parse(b"PK\x03\x04").unwrap_err().contains("magic"));
    }

    #[test]
    fn npz_first_array_and_size_checks() {
        use std::io::Write;
        let member = npy("<f4", "(2,)", &[0, 0, 128, 63, 0, 0, 0, 64]);
        let mut buf = std::io::Cursor::new(Vec::new());
        let mut z = zip::ZipWriter::new(&mut buf);
        let opts = zip::write::FileOptions::default().compression_method(zip::CompressionMethod::Deflated);
        z.start_file("arr_0.npy", opts).unwrap();
        z.write_all(&member).unwrap();
        z.finish().unwrap();
        drop(z);
        let bytes = buf.into_inner();
        let inner = read_npz_first(&bytes).unwrap();
        assert_eq!(parse(&inner).unwrap().to_f32(), vec![1.0, 2.0]);
        assert!(read_npz_first(&bytes[..bytes.len() - 30])
            .unwrap_err()
            .contains("not a .npz"));
        assert!(read_npz_first(b"").unwrap_err().contains("not a .npz"));
        // A central directory that claims 2 GiB for the member: refused
        // before anything is inflated.
        let mut huge = bytes.clone();
        let cd = huge.windows(4).position(|w| w == b"PK\x01\x02").unwrap();
        huge[cd + 24..cd + 28].copy_from_slice(&0x8000_0000u32.to_le_bytes());
        let e = read_npz_first(&huge).unwrap_err();
        assert!(e.contains("2147483648 bytes decompressed"), "{e}");
    }
}
