//! A bitmap as runs of set voxels along x, and the 26-connected components
//! that contain given voxels.
//!
//! Following a component voxel by voxel looks at 26 neighbours of each of
//! its voxels: on lego's coarse grid the stroke's 117k seeds took 10–16 ms
//! a pass, twice per stroke. A run of consecutive set voxels in one row
//! meets another run 26-connectedly exactly when their rows are adjacent
//! (y and z each within one, not the same row: runs in one row are apart)
//! and their x spans overlap once widened by one voxel, so the same
//! components follow from a search over runs, about a tenth as many items,
//! each looking at the runs of 8 neighbouring rows.

use super::Bitmap;

/// The runs of a bitmap, row by row (row = y + ny·z), each row's runs
/// ascending in x.
pub struct Runs {
    res: [usize; 3],
    /// Runs of row r: `row_start[r]..row_start[r + 1]`.
    row_start: Vec<u32>,
    /// Each run's x span, `x0..x1`.
    span: Vec<(u32, u32)>,
    /// Each run's row.
    row: Vec<u32>,
}

impl Runs {
    pub fn of(bits: &Bitmap) -> Runs {
        let res = bits.res();
        let nx = res[0];
        let rows = res[1] * res[2];
        let (mut span, mut row) = (Vec::<(u32, u32)>::new(), Vec::<u32>::new());
        let mut row_start = vec![0u32; rows + 1];
        for v in bits.ones() {
            let (r, x) = ((v / nx) as u32, (v % nx) as u32);
            match (span.last_mut(), row.last()) {
                (Some(last), Some(&lr)) if lr == r && last.1 == x => last.1 = x + 1,
                _ => {
                    span.push((x, x + 1));
                    row.push(r);
                }
            }
        }
        // Counts per row, then prefix sums (runs are in row order).
        for &r in &row {
            row_start[r as usize + 1] += 1;
        }
        for r in 0..rows {
            row_start[r + 1] += row_start[r];
        }
        Runs {
            res,
            row_start,
            span,
            row,
        }
    }

    pub fn len(&self) -> usize {
        self.span.len()
    }

    pub fn is_empty(&self) -> bool {
        self.span.is_empty()
    }

    /// Every run as (row, x0, x1), in row order.
    pub fn iter(&self) -> impl Iterator<Item = (usize, usize, usize)> + '_ {
        self.row
            .iter()
            .zip(&self.span)
            .map(|(&r, &(x0, x1))| (r as usize, x0 as usize, x1 as usize))
    }

    /// The run holding voxel `v`, if `v` is set.
    pub fn run_of(&self, v: usize) -> Option<usize> {
        let nx = self.res[0];
        let (r, x) = (v / nx, (v % nx) as u32);
        let (lo, hi) = (self.row_start[r] as usize, self.row_start[r + 1] as usize);
        let runs = &self.span[lo..hi];
        // The first run ending after x, if it starts at or before x.
        let i = runs.partition_point(|s| s.1 <= x);
        (i < runs.len() && runs[i].0 <= x).then_some(lo + i)
    }

    /// Calls `f` with every run 26-connected to run `i`.
    fn each_neighbour(&self, i: usize, mut f: impl FnMut(usize)) {
        let [_, ny, nz] = self.res;
        let r = self.row[i] as usize;
        let (y, z) = (r % ny, r / ny);
        let (x0, x1) = self.span[i];
        for zz in z.saturating_sub(1)..=(z + 1).min(nz - 1) {
            for yy in y.saturating_sub(1)..=(y + 1).min(ny - 1) {
                let rr = yy + ny * zz;
                if rr == r {
                    continue;
                }
                let (lo, hi) = (self.row_start[rr] as usize, self.row_start[rr + 1] as usize);
                let runs = &self.span[lo..hi];
                // Runs overlapping x0 - 1 .. x1 + 1: ending after x0 - 1
                // and starting before x1 + 1.
                let first = runs.partition_point(|s| s.1 < x0);
                for (j, s) in runs.iter().enumerate().skip(first) {
                    if s.0 > x1 {
                        break;
                    }
                    f(lo + j);
                }
            }
        }
    }

    /// The voxels of every component (26-connected) that holds one of
    /// `starts` (set voxels; others are ignored).
    pub fn components_of(&self, starts: impl IntoIterator<Item = usize>) -> Bitmap {
        let mut joined = vec![false; self.len()];
        let mut stack: Vec<usize> = starts
            .into_iter()
            .filter_map(|v| self.run_of(v))
            .filter(|&i| !std::mem::replace(&mut joined[i], true))
            .collect();
        while let Some(i) = stack.pop() {
            self.each_neighbour(i, |j| {
                if !joined[j] {
                    joined[j] = true;
                    stack.push(j);
                }
            });
        }
        let mut out = Bitmap::new(self.res);
        let nx = self.res[0];
        for ((r, x0, x1), _) in self.iter().zip(&joined).filter(|(_, &j)| j) {
            out.set_range(r * nx + x0, r * nx + x1);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::SplitMix64;

    /// Components voxel by voxel, 26 neighbours each.
    fn reference(bits: &Bitmap, starts: &[usize]) -> Bitmap {
        let [nx, ny, nz] = bits.res().map(|n| n as isize);
        let mut out = Bitmap::new(bits.res());
        let mut stack: Vec<usize> = starts.iter().copied().filter(|&v| bits.get(v)).collect();
        for &v in &stack {
            out.set(v, true);
        }
        while let Some(v) = stack.pop() {
            let (x, y, z) = (v as isize % nx, v as isize / nx % ny, v as isize / (nx * ny));
            for (dx, dy, dz) in (-1..=1).flat_map(|a| (-1..=1).flat_map(move |b| (-1..=1).map(move |c| (a, b, c)))) {
                let (a, b, c) = (x + dx, y + dy, z + dz);
                if a < 0 || b < 0 || c < 0 || a >= nx || b >= ny || c >= nz {
                    continue;
                }
                let n = (a + nx * (b + ny * c)) as usize;
                if bits.get(n) && !out.get(n) {
                    out.set(n, true);
                    stack.push(n);
                }
            }
        }
        out
    }

    #[test]
    fn components_over_runs_equal_those_voxel_by_voxel() {
        // Random bitmaps of several densities on grids whose rows are not
        // whole words (runs cross word boundaries and rows touch the grid's
        // faces), from several starts.
        let mut rng = SplitMix64::new(9);
        for (res, density) in [([13, 7, 5], 30), ([70, 9, 6], 45), ([3, 3, 3], 50), ([97, 4, 11], 60)] {
            let n = res[0] * res[1] * res[2];
            let mut bits = Bitmap::new(res);
            for v in 0..n {
                if rng.below(100) < density {
                    bits.set(v, true);
                }
            }
            let runs = Runs::of(&bits);
            assert_eq!(
                runs.span.iter().map(|s| (s.1 - s.0) as usize).sum::<usize>(),
                bits.count()
            );
            for _ in 0..5 {
                let starts: Vec<usize> = (0..3).map(|_| rng.below(n)).collect();
                let got = runs.components_of(starts.iter().copied());
                assert_eq!(got, reference(&bits, &starts), "{res:?} {density}% from {starts:?}");
            }
            // No start on a set voxel: nothing.
            assert!(!runs.components_of(std::iter::empty()).any());
        }
    }

    #[test]
    fn diagonal_neighbours_join_and_rows_apart_do_not() {
        let res = [8, 4, 4];
        let idx = |x: usize, y: usize, z: usize| x + 8 * (y + 4 * z);
        let mut bits = Bitmap::new(res);
        for x in 0..3 {
            bits.set(idx(x, 0, 0), true);
        }
        // Touches (2, 0, 0) only at a corner.
        bits.set(idx(3, 1, 1), true);
        // Two rows up: apart.
        bits.set(idx(4, 3, 1), true);
        let runs = Runs::of(&bits);
        assert_eq!(runs.len(), 3);
        let c = runs.components_of([idx(0, 0, 0)]);
        assert_eq!(c.count(), 4);
        assert!(c.get(idx(3, 1, 1)) && !c.get(idx(4, 3, 1)));
        assert_eq!(runs.run_of(idx(1, 0, 0)), Some(0));
        assert_eq!(runs.run_of(idx(5, 0, 0)), None);
    }
}
