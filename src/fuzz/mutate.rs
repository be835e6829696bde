//! Deterministic input mutation: byte-level mutations
//! (bit flips, byte sets, boundary integers, truncation, splices, inserts,
//! deletes, repeated chunks and number tweaks for text formats).

/// The library's SplitMix64: fully determined by its seed, so a run with
/// the same seed tries the same inputs.
pub use crate::util::SplitMix64 as Rng;

/// Integers at the edges of the usual widths: where size and offset
/// arithmetic overflows or wraps.
const BOUNDARY: &[u64] = &[
    0,
    1,
    2,
    3,
    16,
    17,
    64,
    127,
    128,
    255,
    256,
    1024,
    4096,
    32767,
    32768,
    65535,
    65536,
    0x7fff_ffff,
    0x8000_0000,
    0xffff_ffff,
    1 << 32,
    1 << 40,
    1 << 62,
    0x7fff_ffff_ffff_ffff,
    0x8000_0000_0000_0000,
    u64::MAX,
    u64::MAX - 1,
];

/// Replacements for numbers in text formats (JSON, RON, `.npy` headers,
/// COLMAP text): huge, negative, fractional, non-finite, overflowing.
const NUMBERS: &[&str] = &[
    "0",
    "-0",
    "1",
    "-1",
    "2",
    "-3",
    "17",
    "255",
    "256",
    "65535",
    "65536",
    "4294967295",
    "4294967296",
    "9223372036854775807",
    "9223372036854775808",
    "18446744073709551615",
    "18446744073709551616",
    "1085102592571150096",
    "1e12",
    "-1e12",
    "1e38",
    "3.5e38",
    "1e308",
    "-1e308",
    "1e309",
    "1e-320",
    "0.5",
    "-0.5",
    "NaN",
    "nan",
    "inf",
    "-inf",
    "1e",
    "",
];

/// Bytes worth planting: structure characters of the text formats and the
/// edges of a byte.
const BYTES: &[u8] = b"\x00\x01\x7f\x80\xff{}[]()\"',:;-.0123456789eE \n\\";

/// Mutates `data` in place with one to four stacked mutations; `others`
/// feeds splices. The result is at most `max_len` bytes.
pub fn mutate(rng: &mut Rng, data: &mut Vec<u8>, others: &[Vec<u8>], max_len: usize) {
    for _ in 0..1 + rng.below(4) {
        match rng.below(11) {
            0 => flip_bit(rng, data),
            1 => set_byte(rng, data),
            2 | 3 => boundary_int(rng, data),
            4 => truncate(rng, data),
            5 => {
                let other = pick_other(rng, others);
                splice(rng, data, other)
            }
            6 => insert_bytes(rng, data),
            7 => delete_range(rng, data),
            8 => repeat_chunk(rng, data, max_len),
            _ => tweak_number(rng, data),
        }
    }
    data.truncate(max_len);
}

fn pick_other<'a>(rng: &mut Rng, others: &'a [Vec<u8>]) -> &'a [u8] {
    if others.is_empty() {
        &[]
    } else {
        rng.pick(others).as_slice()
    }
}

fn flip_bit(rng: &mut Rng, d: &mut [u8]) {
    if !d.is_empty() {
        let i = rng.below(d.len());
        d[i] ^= 1 << rng.below(8);
    }
}

fn set_byte(rng: &mut Rng, d: &mut [u8]) {
    if !d.is_empty() {
        let i = rng.below(d.len());
        d[i] = if rng.below(2) == 0 {
            *rng.pick(BYTES)
        } else {
            rng.next_u64() as u8
        };
    }
}

/// Writes a boundary integer (±1) of width 1, 2, 4 or 8, either byte order.
fn boundary_int(rng: &mut Rng, d: &mut [u8]) {
    let width = 1 << rng.below(4);
    if d.len() < width {
        return;
    }
    let v = rng.pick(BOUNDARY).wrapping_add([0, 1, u64::MAX][rng.below(3)]);
    // Big-endian: the low `width` bytes of v, most significant first.
    let bytes = if rng.below(2) == 0 {
        v.to_le_bytes()
    } else {
        (v << (64 - 8 * width as u32)).to_be_bytes()
    };
    let at = rng.below(d.len() - width + 1);
    d[at..at + width].copy_from_slice(&bytes[..width]);
}

fn truncate(rng: &mut Rng, d: &mut Vec<u8>) {
    let keep = rng.below(d.len() + 1);
    d.truncate(keep);
}

/// The head of `d` followed by the tail of another input.
fn splice(rng: &mut Rng, d: &mut Vec<u8>, other: &[u8]) {
    let at = rng.below(d.len() + 1);
    let from = rng.below(other.len() + 1);
    d.truncate(at);
    d.extend_from_slice(&other[from..]);
}

fn insert_bytes(rng: &mut Rng, d: &mut Vec<u8>) {
    let at = rng.below(d.len() + 1);
    let n = 1 + rng.below(16);
    let b = *rng.pick(BYTES);
    let fill: Vec<u8> = (0..n)
        .map(|_| if rng.below(2) == 0 { b } else { rng.next_u64() as u8 })
        .collect();
    d.splice(at..at, fill);
}

fn delete_range(rng: &mut Rng, d: &mut Vec<u8>) {
    if d.is_empty() {
        return;
    }
    let at = rng.below(d.len());
    let n = 1 + rng.below((d.len() - at).min(64));
    d.drain(at..at + n);
}

/// Repeats a short chunk many times in place: deep nesting (`[[[[`) and
/// long runs, the shapes that make parsers recurse or backtrack.
fn repeat_chunk(rng: &mut Rng, d: &mut Vec<u8>, max_len: usize) {
    if d.is_empty() {
        return;
    }
    let at = rng.below(d.len());
    let len = 1 + rng.below((d.len() - at).min(8));
    let times = 1 + rng.below(64);
    let chunk = d[at..at + len].to_vec();
    let room = max_len.saturating_sub(d.len()) / len;
    let rep: Vec<u8> = chunk.iter().copied().cycle().take(len * times.min(room)).collect();
    d.splice(at..at, rep);
}

/// Replaces one number written in text (digits, sign, point, exponent)
/// with another from [`NUMBERS`].
fn tweak_number(rng: &mut Rng, d: &mut Vec<u8>) {
    let starts: Vec<usize> = (0..d.len())
        .filter(|&i| d[i].is_ascii_digit() && (i == 0 || !is_number_byte(d[i - 1])))
        .collect();
    if starts.is_empty() {
        return insert_bytes(rng, d);
    }
    let mut a = *rng.pick(&starts);
    if a > 0 && d[a - 1] == b'-' {
        a -= 1;
    }
    let b = a + 1 + d[a + 1..].iter().take_while(|&&c| is_number_byte(c)).count();
    d.splice(a..b, rng.pick(NUMBERS).bytes());
}

fn is_number_byte(c: u8) -> bool {
    c.is_ascii_digit() || matches!(c, b'.' | b'e' | b'E' | b'+' | b'-')
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_mutants() {
        let seed = b"{\"a\": [1, 2.5, -3e4], \"b\": \"xyz\"}".to_vec();
        let run = |s: u64| {
            let mut rng = Rng::new(s);
            (0..200)
                .map(|_| {
                    let mut d = seed.clone();
                    mutate(&mut rng, &mut d, std::slice::from_ref(&seed), 256);
                    d
                })
                .collect::<Vec<_>>()
        };
        let a = run(7);
        assert_eq!(a, run(7));
        assert_ne!(a, run(8));
        assert!(a.iter().all(|d| d.len() <= 256));
        // The mutants differ from the seed and from each other.
        let distinct: std::collections::HashSet<_> = a.iter().collect();
        assert!(distinct.len() > 150, "{}", distinct.len());
    }

    #[test]
    fn number_tweak_replaces_whole_numbers() {
        let mut rng = Rng::new(1);
        for _ in 0..50 {
            let mut d = b"[-12.5e3, 7]".to_vec();
            tweak_number(&mut rng, &mut d);
            let s = String::from_utf8(d).unwrap();
            assert!(s.starts_with('[') && s.ends_with(']') && s.contains(", "), "{s}");
        }
    }
}
