//! 3D bitmaps over a grid: packed bits (x fastest, like every grid), set
//! algebra, counting, bounding boxes, and a rank index that maps an occupied
//! voxel to its slot in a compact per-voxel array.
//!
//! Bitmaps live in `field` rather than `segment` because the renderer (masks),
//! the editor (objects) and segmentation all consume them; keeping them here
//! keeps the module graph acyclic.

use crate::error::Result;

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Bitmap {
    res: [usize; 3],
    words: Vec<u64>,
}

impl Bitmap {
    pub fn new(res: [usize; 3]) -> Self {
        let n = res[0] * res[1] * res[2];
        Bitmap {
            res,
            words: vec![0; n.div_ceil(64)],
        }
    }
    /// Builds a bitmap from packed words; checks the word count.
    pub fn from_words(res: [usize; 3], words: Vec<u64>) -> Result<Self> {
        let n = res[0] * res[1] * res[2];
        crate::ensure!(
            words.len() == n.div_ceil(64),
            "bitmap of resolution {res:?} needs {} words, got {}",
            n.div_ceil(64),
            words.len()
        );
        let mut b = Bitmap { res, words };
        b.clear_tail();
        Ok(b)
    }
    /// The bitmap whose set voxels are `ones` (indices below the voxel count).
    pub fn from_ones(res: [usize; 3], ones: &[u32]) -> Self {
        let mut b = Bitmap::new(res);
        for &v in ones {
            b.set(v as usize, true);
        }
        b
    }
    pub fn from_fn(res: [usize; 3], f: impl Fn(usize) -> bool + Sync) -> Self {
        use rayon::prelude::*;
        let n = res[0] * res[1] * res[2];
        let words = (0..n.div_ceil(64))
            .into_par_iter()
            .map(|w| {
                let mut bits = 0u64;
                for b in 0..64 {
                    let i = w * 64 + b;
                    if i < n && f(i) {
                        bits |= 1 << b;
                    }
                }
                bits
            })
            .collect();
        Bitmap { res, words }
    }
    pub fn res(&self) -> [usize; 3] {
        self.res
    }
    pub fn len(&self) -> usize {
        self.res[0] * self.res[1] * self.res[2]
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    pub fn words(&self) -> &[u64] {
        &self.words
    }
    #[inline]
    pub fn get(&self, i: usize) -> bool {
        self.words[i >> 6] >> (i & 63) & 1 == 1
    }
    #[inline]
    pub fn set(&mut self, i: usize, v: bool) {
        let m = 1u64 << (i & 63);
        if v {
            self.words[i >> 6] |= m;
        } else {
            self.words[i >> 6] &= !m;
        }
    }
    /// Sets the bits `start..end`, a word at a time.
    pub fn set_range(&mut self, start: usize, end: usize) {
        debug_assert!(start <= end && end <= self.len());
        let mut i = start;
        while i < end {
            let (w, b) = (i >> 6, i & 63);
            let n = (64 - b).min(end - i);
            let mask = if n == 64 { u64::MAX } else { ((1u64 << n) - 1) << b };
            self.words[w] |= mask;
            i += n;
        }
    }
    pub fn count(&self) -> usize {
        self.words.iter().map(|w| w.count_ones() as usize).sum()
    }
    pub fn any(&self) -> bool {
        self.words.iter().any(|&w| w != 0)
    }
    /// Indices of set voxels, ascending.
    pub fn ones(&self) -> impl Iterator<Item = usize> + '_ {
        self.words.iter().enumerate().flat_map(|(wi, &w)| {
            let mut bits = w;
            std::iter::from_fn(move || {
                if bits == 0 {
                    return None;
                }
                let b = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                Some(wi * 64 + b)
            })
        })
    }
    fn same_shape(&self, other: &Bitmap) -> Result<()> {
        crate::ensure!(
            self.res == other.res,
            "bitmaps have different resolutions: {:?} and {:?}",
            self.res,
            other.res
        );
        Ok(())
    }
    fn zip(&mut self, other: &Bitmap, f: impl Fn(u64, u64) -> u64) -> Result<()> {
        self.same_shape(other)?;
        for (a, &b) in self.words.iter_mut().zip(&other.words) {
            *a = f(*a, b);
        }
        Ok(())
    }
    pub fn union_with(&mut self, other: &Bitmap) -> Result<()> {
        self.zip(other, |a, b| a | b)
    }
    pub fn subtract(&mut self, other: &Bitmap) -> Result<()> {
        self.zip(other, |a, b| a & !b)
    }
    pub fn intersect_with(&mut self, other: &Bitmap) -> Result<()> {
        self.zip(other, |a, b| a & b)
    }
    /// Number of voxels set in both.
    pub fn intersection_count(&self, other: &Bitmap) -> Result<usize> {
        self.same_shape(other)?;
        Ok(self
            .words
            .iter()
            .zip(&other.words)
            .map(|(a, b)| (a & b).count_ones() as usize)
            .sum())
    }
    /// Inclusive voxel bounding box `(min, max)` of the set voxels.
    pub fn bounding_box(&self) -> Option<([usize; 3], [usize; 3])> {
        let mut lo = [usize::MAX; 3];
        let mut hi = [0usize; 3];
        let mut any = false;
        for i in self.ones() {
            any = true;
            let x = i % self.res[0];
            let y = (i / self.res[0]) % self.res[1];
            let z = i / (self.res[0] * self.res[1]);
            for (a, v) in [x, y, z].into_iter().enumerate() {
                lo[a] = lo[a].min(v);
                hi[a] = hi[a].max(v);
            }
        }
        any.then_some((lo, hi))
    }
    /// Voxels within Chebyshev distance 1 of a set voxel (the 3×3×3
    /// neighbourhood), e.g. the corners of every cell that touches a set
    /// voxel.
    pub fn dilated(&self) -> Bitmap {
        let [nx, ny, nz] = self.res;
        let near = |c: usize, m: usize| c.saturating_sub(1)..=(c + 1).min(m - 1);
        Bitmap::from_fn(self.res, |i| {
            if self.get(i) {
                return true;
            }
            let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
            near(z, nz).any(|zz| near(y, ny).any(|yy| near(x, nx).any(|xx| self.get(xx + nx * (yy + ny * zz)))))
        })
    }
    fn clear_tail(&mut self) {
        let n = self.len();
        if !n.is_multiple_of(64) {
            if let Some(last) = self.words.last_mut() {
                *last &= (1u64 << (n % 64)) - 1;
            }
        }
    }
    /// Packed little-endian bytes (for files).
    pub fn to_bytes(&self) -> Vec<u8> {
        bytemuck::cast_slice(&self.words).to_vec()
    }
    pub fn from_bytes(res: [usize; 3], bytes: &[u8]) -> Result<Self> {
        crate::ensure!(
            bytes.len().is_multiple_of(8),
            "bitmap byte length {} is not a multiple of 8",
            bytes.len()
        );
        let words = bytes
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().unwrap()))
            .collect();
        Self::from_words(res, words)
    }
}

/// Rank index over a bitmap: slot of a set voxel in the ascending list of set
/// voxels, in O(1) (a prefix count per 64-bit word plus one popcount).
#[derive(Clone, Debug)]
pub struct RankIndex {
    bits: Bitmap,
    prefix: Vec<u32>,
}

impl RankIndex {
    pub fn new(bits: Bitmap) -> Self {
        let mut prefix = Vec::with_capacity(bits.words.len());
        let mut acc = 0u32;
        for &w in &bits.words {
            prefix.push(acc);
            acc += w.count_ones();
        }
        RankIndex { bits, prefix }
    }
    pub fn bits(&self) -> &Bitmap {
        &self.bits
    }
    pub fn count(&self) -> usize {
        self.prefix.last().map_or(0, |&p| {
            p as usize + self.bits.words.last().unwrap().count_ones() as usize
        })
    }
    /// Asks the caches for the words [`Self::slot`] reads for voxel `i`
    /// (a hint; nothing for `i` off the grid).
    #[inline(always)]
    pub fn prefetch(&self, i: usize) {
        if let (Some(w), Some(p)) = (self.bits.words.get(i >> 6), self.prefix.get(i >> 6)) {
            crate::util::prefetch(w);
            crate::util::prefetch(p);
        }
    }
    /// Slot of voxel `i`, or `None` when it is not set.
    #[inline]
    pub fn slot(&self, i: usize) -> Option<usize> {
        let w = self.bits.words[i >> 6];
        let b = i & 63;
        if w >> b & 1 == 0 {
            return None;
        }
        let below = w & ((1u64 << b) - 1);
        Some(self.prefix[i >> 6] as usize + below.count_ones() as usize)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn set_range_sets_exactly_the_range_across_words() {
        let res = [50, 3, 2];
        for (start, end) in [
            (0, 0),
            (0, 300),
            (3, 5),
            (60, 64),
            (63, 65),
            (10, 200),
            (128, 192),
            (299, 300),
        ] {
            let mut b = Bitmap::new(res);
            b.set_range(start, end);
            let want = Bitmap::from_fn(res, |i| (start..end).contains(&i));
            assert_eq!(b, want, "{start}..{end}");
        }
    }
}
