//! Gradient accumulation for one training step.
//!
//! Rays are marched in parallel, one rayon task per chunk of the batch.
//! Each task writes what its samples owe the grids as compact records in its
//! [`GradLog`] (per sample: its cell, the trilinear fractions, dL/draw and
//! dL/d the colour logits), not into a buffer over every active voxel.
//! [`gather`] then orders all records by bucket of cells (4096 grid points)
//! and spreads them over the cells'
//! corners into the one shared [`GradBuf`]: the slots are cut into pieces
//! that one task owns outright, so there are no atomics and no per-thread
//! copies of the grid-sized buffers.
//!
//! Why: a full gradient buffer per thread is 470 MB on fern's 448 grid, so
//! memory grew with the core count (7.5 GB on 16 cores), and the optimizer
//! had to sum and clear every copy. Bucketed records also spread with good
//! locality: consecutive records touch nearby voxels. A sample's
//! record is 36 bytes, a batch of 4096 rays about 300 k samples (11 MB).

use super::march::{corner_offsets, weights};
use super::model::{set_bit, Model};
use crate::field::sh::SH_COEFFS;
use rayon::prelude::*;
use std::ops::Range;

/// `CellGrad::basis` of a sample whose colour gets no gradient (not shaded,
/// or VM appearance).
const NO_COLOUR: u32 = u32::MAX;

/// What one density/colour sample owes the corners of its cell.
#[derive(Clone, Copy, Debug)]
struct CellGrad {
    /// Grid index of the cell's lower corner.
    base: u32,
    frac: [f32; 3],
    /// dL/draw at the sample.
    draw: f32,
    /// dL/dz of the colour logits (r, g, b).
    dz: [f32; 3],
    /// Index of the ray's SH basis in `basis`, or [`NO_COLOUR`].
    basis: u32,
}

/// What one shaded sample owes the corners of its feature-grid cell:
/// `w · h`, with h the ray's dL/dΦ.
#[derive(Clone, Copy, Debug)]
struct FeatGrad {
    base: u32,
    frac: [f32; 3],
    w: f32,
    /// Index of the ray's h in `hs` (rows of `channels`).
    ray: u32,
}

/// A record spread over the corners of a grid cell.
trait Record: Copy + Send + Sync {
    /// Grid index of the cell's lower corner.
    fn base(&self) -> u32;
}

impl Record for CellGrad {
    fn base(&self) -> u32 {
        self.base
    }
}

impl Record for FeatGrad {
    fn base(&self) -> u32 {
        self.base
    }
}

/// Grid points per bucket of the record sort (log2): a bucket's records
/// touch a few grid rows (and the plane above), close in memory.
const BUCKET_BITS: u32 = 12;

fn bucket(grid_point: usize) -> usize {
    grid_point >> BUCKET_BITS
}

/// Moves the records of `parts` into `out` ordered by the bucket of their
/// cell: a counting sort, linear (sorting by cell cost more than it saved on
/// coarse grids). Stable: part after part, each in its own order, so sums
/// do not depend on the sort. `renumber(r, part)` fixes indices that were
/// relative to the part.
fn merge_in_buckets<R: Record>(parts: &mut [&mut Vec<R>], out: &mut Vec<R>, renumber: impl Fn(R, usize) -> R) {
    out.clear();
    let Some(&first) = parts.iter().find_map(|p| p.first()) else {
        return;
    };
    let all = || parts.iter().flat_map(|p| p.iter());
    let nb = all().map(|r| bucket(r.base() as usize)).max().unwrap_or(0) + 1;
    let mut start = vec![0usize; nb + 1];
    for r in all() {
        start[bucket(r.base() as usize) + 1] += 1;
    }
    for i in 1..=nb {
        start[i] += start[i - 1];
    }
    out.resize(start[nb], first);
    for (k, part) in parts.iter_mut().enumerate() {
        for r in part.drain(..) {
            let b = bucket(r.base() as usize);
            out[start[b]] = renumber(r, k);
            start[b] += 1;
        }
    }
}

/// One task's gradient records for a step (see the module docs). The VM
/// appearance (small dense arrays, optional) still accumulates densely per
/// task.
#[derive(Clone, Debug, Default)]
pub struct GradLog {
    cells: Vec<CellGrad>,
    basis: Vec<[f32; SH_COEFFS]>,
    feats: Vec<FeatGrad>,
    /// dL/dΦ of the rays, `h_rows` rows.
    hs: Vec<f32>,
    h_rows: u32,
    pub vm_grid: Vec<f32>,
    pub vm_net: Vec<f32>,
}

impl GradLog {
    pub fn new(model: &Model) -> Self {
        GradLog {
            vm_grid: vec![0.0; model.vm.as_ref().map_or(0, |v| v.grid.len())],
            vm_net: vec![0.0; model.vm.as_ref().map_or(0, |v| v.net.len())],
            ..Default::default()
        }
    }
    /// Starts a ray: records its SH basis (when its colour trains) and its
    /// dL/dΦ (when features train); returns their indices for the samples.
    pub(super) fn begin_ray(&mut self, basis: Option<[f32; SH_COEFFS]>, h: &[f32]) -> (u32, u32) {
        let b = match basis {
            Some(b) => {
                self.basis.push(b);
                (self.basis.len() - 1) as u32
            }
            None => NO_COLOUR,
        };
        let ray = self.h_rows;
        if !h.is_empty() {
            self.hs.extend_from_slice(h);
            self.h_rows += 1;
        }
        (b, ray)
    }
    /// A sample's density gradient, and its colour-logit gradient `dz`
    /// when `basis` (from [`GradLog::begin_ray`]) is given.
    pub(super) fn push_cell(&mut self, base: u32, frac: [f32; 3], draw: f32, colour: Option<(u32, [f32; 3])>) {
        let (basis, dz) = colour.unwrap_or((NO_COLOUR, [0.0; 3]));
        self.cells.push(CellGrad {
            base,
            frac,
            draw,
            dz,
            basis,
        });
    }
    /// A shaded sample's weight `w` in feature-grid cell `base`.
    pub(super) fn push_feature(&mut self, base: u32, frac: [f32; 3], w: f32, ray: u32) {
        self.feats.push(FeatGrad { base, frac, w, ray });
    }
}

/// The step's gradients over the model's parameters. Density and SH
/// gradients are per slot of the model's active voxels ([`Model::slots`];
/// pruned voxels never train), `marks` flag every slot whose density received
/// a gradient since the last optimizer step, `sh_marks` those whose colour
/// did (only shaded samples: far fewer, and the optimizer's cost follows
/// them). Features (a small dense grid) are per grid point.
#[derive(Clone, Debug, Default)]
pub struct GradBuf {
    pub density: Vec<f32>,
    pub sh: Vec<f32>,
    pub marks: Vec<u64>,
    pub sh_marks: Vec<u64>,
    pub feat: Vec<f32>,
    pub feat_marks: Vec<u64>,
    /// VM appearance: dense gradients of the grid and network arrays.
    pub vm_grid: Vec<f32>,
    pub vm_net: Vec<f32>,
    /// The logs' records merged in bucket order (kept to reuse the
    /// allocations), with the rays' SH bases and dL/dΦ rows they index.
    cells: Vec<CellGrad>,
    basis: Vec<[f32; SH_COEFFS]>,
    feats: Vec<FeatGrad>,
    hs: Vec<f32>,
    h_rows: u32,
}

impl GradBuf {
    /// Buffers for the arrays of `model` that train: without `radiance`
    /// (distilling into a frozen field) none for density and SH colour,
    /// which on lego's 320 grid would be 730 MB of zeros (VM appearance's
    /// small arrays are kept either way).
    pub fn new(model: &Model, radiance: bool) -> Self {
        let n = if radiance { model.slots.len() } else { 0 };
        let (nf, fc) = model.features.as_ref().map_or((0, 0), |f| (f.geom.len(), f.channels));
        GradBuf {
            density: vec![0.0; n],
            sh: vec![0.0; n * model.sh_stride()],
            marks: vec![0; n.div_ceil(64)],
            sh_marks: vec![0; n.div_ceil(64)],
            feat: vec![0.0; nf * fc],
            feat_marks: vec![0; nf.div_ceil(64)],
            vm_grid: vec![0.0; model.vm.as_ref().map_or(0, |v| v.grid.len())],
            vm_net: vec![0.0; model.vm.as_ref().map_or(0, |v| v.net.len())],
            ..Default::default()
        }
    }

    /// A buffer with every log of `logs` gathered into it (tests, one-off
    /// uses; training reuses one buffer).
    pub fn from_logs(model: &Model, logs: &mut [GradLog]) -> Self {
        let mut g = GradBuf::new(model, true);
        gather(model, logs, &mut g);
        g
    }
}

/// Spreads the records of `logs` into `out` (adding to what it holds) and
/// empties the logs.
pub fn gather(model: &Model, logs: &mut [GradLog], out: &mut GradBuf) {
    merge_records(logs, out);
    spread_cells(model, out);
    spread_features(model, out);
    for log in logs.iter_mut() {
        add_and_clear(&mut out.vm_grid, &mut log.vm_grid);
        add_and_clear(&mut out.vm_net, &mut log.vm_net);
    }
}

/// Moves every log's records into `out` in bucket order, renumbering their
/// basis and ray indices into `out`'s lists.
fn merge_records(logs: &mut [GradLog], out: &mut GradBuf) {
    let prefix = |lens: Vec<u32>| -> Vec<u32> {
        lens.iter()
            .scan(0u32, |acc, &n| {
                let at = *acc;
                *acc += n;
                Some(at)
            })
            .collect()
    };
    let b0 = prefix(logs.iter().map(|l| l.basis.len() as u32).collect());
    let r0 = prefix(logs.iter().map(|l| l.h_rows).collect());
    let mut cells: Vec<&mut Vec<CellGrad>> = logs.iter_mut().map(|l| &mut l.cells).collect();
    merge_in_buckets(&mut cells, &mut out.cells, |mut c, k| {
        if c.basis != NO_COLOUR {
            c.basis += b0[k];
        }
        c
    });
    let mut feats: Vec<&mut Vec<FeatGrad>> = logs.iter_mut().map(|l| &mut l.feats).collect();
    merge_in_buckets(&mut feats, &mut out.feats, |mut f, k| {
        f.ray += r0[k];
        f
    });
    out.basis.clear();
    out.hs.clear();
    out.h_rows = 0;
    for log in logs.iter_mut() {
        out.basis.append(&mut log.basis);
        out.hs.append(&mut log.hs);
        out.h_rows += std::mem::take(&mut log.h_rows);
    }
}

fn add_and_clear(sum: &mut [f32], part: &mut [f32]) {
    sum.par_iter_mut().zip(part.par_iter_mut()).for_each(|(s, p)| {
        *s += std::mem::take(p);
    });
}

/// A piece of the spread: the slots it owns (starting on a multiple of 64,
/// so that it owns whole words of the mark bitmaps), the grid points those
/// slots are, and the sorted records whose cells can reach them.
#[derive(Clone, Debug, PartialEq)]
struct Piece {
    slots: Range<usize>,
    grid: Range<usize>,
    records: Range<usize>,
}

/// Cuts `n_slots` slots into about `pieces` pieces of similar record counts.
/// `records` are in bucket order ([`merge_in_buckets`]); `first_slot(g)` is the
/// first slot whose grid point is ≥ g, `grid_of(s)` slot s's grid point; a
/// cell reaches grid points up to `reach` above its base. A piece scans the
/// whole buckets that hold cells able to reach it (a few records more than
/// needed; the spread checks each corner).
fn plan<R: Record>(
    records: &[R],
    n_slots: usize,
    first_slot: impl Fn(usize) -> usize,
    grid_of: impl Fn(usize) -> usize,
    reach: usize,
    pieces: usize,
) -> Vec<Piece> {
    let n = records.len();
    if n == 0 || n_slots == 0 {
        return vec![];
    }
    let mut cuts = vec![0usize];
    for p in 1..pieces {
        let s = first_slot(records[n * p / pieces].base() as usize) / 64 * 64;
        if s > *cuts.last().unwrap() && s < n_slots {
            cuts.push(s);
        }
    }
    cuts.push(n_slots);
    let bucket_of = |r: &R| bucket(r.base() as usize);
    cuts.windows(2)
        .map(|w| {
            let lo = grid_of(w[0]);
            let hi = if w[1] == n_slots { usize::MAX } else { grid_of(w[1]) };
            let from = bucket(lo.saturating_sub(reach));
            let first = records.partition_point(|r| bucket_of(r) < from);
            let last = if hi == usize::MAX {
                n
            } else {
                records.partition_point(|r| bucket_of(r) <= bucket(hi - 1))
            };
            Piece {
                slots: w[0]..w[1],
                grid: lo..hi,
                records: first..last,
            }
        })
        .collect()
}

/// Cuts `data` (`stride` values per slot) into the pieces' slot ranges;
/// `stride` 0 cuts bitmaps (64 slots per word).
fn cut<'a, T>(mut data: &'a mut [T], pieces: &[Piece], stride: usize) -> Vec<&'a mut [T]> {
    // Index of a slot boundary in `data`.
    let at = |slot: usize| if stride == 0 { slot.div_ceil(64) } else { slot * stride };
    let mut out = Vec::with_capacity(pieces.len());
    for p in pieces {
        let (mine, rest) = std::mem::take(&mut data).split_at_mut(at(p.slots.end) - at(p.slots.start));
        out.push(mine);
        data = rest;
    }
    out
}

/// Pieces per thread: enough that uneven pieces still balance.
fn piece_count() -> usize {
    4 * rayon::current_num_threads().max(1)
}

fn spread_cells(model: &Model, out: &mut GradBuf) {
    match model.degree {
        0 => spread_cells_k::<1>(model, out),
        1 => spread_cells_k::<4>(model, out),
        _ => spread_cells_k::<9>(model, out),
    }
}

fn spread_cells_k<const K: usize>(model: &Model, out: &mut GradBuf) {
    let slots = &model.slots;
    let off = corner_offsets(model.geom.res);
    let pieces = plan(
        &out.cells,
        slots.len(),
        |g| slots.voxels.partition_point(|&v| (v as usize) < g),
        |s| slots.voxels[s] as usize,
        off[7],
        piece_count(),
    );
    let stride = 3 * K;
    let density = cut(&mut out.density, &pieces, 1);
    let sh = cut(&mut out.sh, &pieces, stride);
    let marks = cut(&mut out.marks, &pieces, 0);
    let sh_marks = cut(&mut out.sh_marks, &pieces, 0);
    let (cells, basis) = (&out.cells, &out.basis);
    pieces
        .par_iter()
        .zip(density)
        .zip(sh)
        .zip(marks)
        .zip(sh_marks)
        .for_each(|((((p, density), sh), marks), sh_marks)| {
            for c in &cells[p.records.clone()] {
                let w8 = weights(c.frac);
                let colour = (c.basis != NO_COLOUR).then(|| {
                    let b = &basis[c.basis as usize];
                    [0, 1, 2].map(|ch| std::array::from_fn::<f32, K, _>(|j| c.dz[ch] * b[j]))
                });
                for k in 0..8 {
                    let j = c.base as usize + off[k];
                    if !p.grid.contains(&j) {
                        continue;
                    }
                    // Pruned corners never train: they have no slot.
                    let Some(v) = slots.slot(j) else {
                        continue;
                    };
                    let l = v - p.slots.start;
                    density[l] += w8[k] * c.draw;
                    set_bit(marks, l);
                    if let Some(d) = &colour {
                        let dst = &mut sh[l * stride..(l + 1) * stride];
                        for ch in 0..3 {
                            for (o, &x) in dst[ch * K..(ch + 1) * K].iter_mut().zip(&d[ch]) {
                                *o += w8[k] * x;
                            }
                        }
                        set_bit(sh_marks, l);
                    }
                }
            }
        });
}

fn spread_features(model: &Model, out: &mut GradBuf) {
    let Some(f) = &model.features else {
        return;
    };
    if out.feats.is_empty() {
        return;
    }
    let fc = f.channels;
    let off = corner_offsets(f.geom.res);
    let pieces = plan(&out.feats, f.geom.len(), |g| g, |s| s, off[7], piece_count());
    let feat = cut(&mut out.feat, &pieces, fc);
    let marks = cut(&mut out.feat_marks, &pieces, 0);
    let (feats, hs) = (&out.feats, &out.hs);
    pieces.par_iter().zip(feat).zip(marks).for_each(|((p, feat), marks)| {
        for c in &feats[p.records.clone()] {
            let fw = weights(c.frac);
            let h = &hs[c.ray as usize * fc..(c.ray as usize + 1) * fc];
            for k in 0..8 {
                let j = c.base as usize + off[k];
                if !p.grid.contains(&j) {
                    continue;
                }
                let l = j - p.slots.start;
                let scale = c.w * fw[k];
                for (o, &hh) in feat[l * fc..(l + 1) * fc].iter_mut().zip(h) {
                    *o += scale * hh;
                }
                set_bit(marks, l);
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    impl Record for u32 {
        fn base(&self) -> u32 {
            *self
        }
    }

    /// Random cells over `grid` points, in bucket order.
    fn random_records(n: u32, grid: u32) -> Vec<u32> {
        let mut records: Vec<u32> = (0..n).map(|i| (i.wrapping_mul(2_654_435_761) >> 7) % grid).collect();
        let mut sorted = vec![];
        merge_in_buckets(&mut [&mut records], &mut sorted, |r, _| r);
        sorted
    }

    #[test]
    fn merging_orders_by_bucket_and_keeps_order_within_one() {
        let records: Vec<(u32, u32)> = (0..20_000u32).map(|i| ((i * 7919) % 100_000, i)).collect();
        #[derive(Clone, Copy)]
        struct R(u32, u32);
        impl Record for R {
            fn base(&self) -> u32 {
                self.0
            }
        }
        // Two parts, as two tasks' logs: the second part's records come
        // after the first's within a bucket.
        let (a, b) = records.split_at(records.len() / 2);
        let mut a: Vec<R> = a.iter().map(|&(b, i)| R(b, i)).collect();
        let mut b: Vec<R> = b.iter().map(|&(b, i)| R(b, i)).collect();
        let mut rs = vec![];
        merge_in_buckets(&mut [&mut a, &mut b], &mut rs, |r, _| r);
        assert_eq!(rs.len(), records.len());
        assert!(a.is_empty() && b.is_empty());
        for w in rs.windows(2) {
            let (a, b) = (bucket(w[0].0 as usize), bucket(w[1].0 as usize));
            assert!(a < b || (a == b && w[0].1 < w[1].1), "out of order");
        }
    }

    #[test]
    fn pieces_own_whole_mark_words_and_see_every_record_that_reaches_them() {
        // 50 000 slots, every other grid point active; records on many cells
        // over about 25 buckets.
        let voxels: Vec<usize> = (0..50_000).map(|s| 2 * s).collect();
        let records = random_records(20_000, 100_000);
        let reach = 4097;
        let pieces = plan(
            &records,
            voxels.len(),
            |g| voxels.partition_point(|&v| v < g),
            |s| voxels[s],
            reach,
            7,
        );
        assert!(pieces.len() > 3);
        assert_eq!(pieces[0].slots.start, 0);
        assert_eq!(pieces.last().unwrap().slots.end, voxels.len());
        for w in pieces.windows(2) {
            assert_eq!(w[0].slots.end, w[1].slots.start);
            assert_eq!(w[1].slots.start % 64, 0);
            assert_eq!(w[0].grid.end, w[1].grid.start);
        }
        // Every (record, corner) pair lands in exactly one piece that
        // scans the record.
        for (i, &b) in records.iter().enumerate() {
            for o in [0, 1, reach] {
                let g = b as usize + o;
                let owners: Vec<&Piece> = pieces.iter().filter(|p| p.grid.contains(&g)).collect();
                assert_eq!(owners.len(), 1, "grid point {g}");
                assert!(
                    owners[0].records.contains(&i),
                    "record {i} (cell {b}) not scanned for {g}"
                );
            }
        }
    }

    #[test]
    fn cutting_gives_disjoint_slices_in_order() {
        let records = random_records(5_000, 40_000);
        let pieces = plan(&records, 40_000, |g| g, |s| s, 0, 4);
        assert!(pieces.len() > 1);
        let mut data: Vec<usize> = (0..80_000).collect();
        let parts = cut(&mut data, &pieces, 2);
        assert_eq!(parts.iter().map(|p| p.len()).sum::<usize>(), 80_000);
        for (p, part) in pieces.iter().zip(&parts) {
            assert_eq!(part[0], 2 * p.slots.start);
        }
        let mut words = vec![0u64; 40_000usize.div_ceil(64)];
        let n_words = words.len();
        let parts = cut(&mut words, &pieces, 0);
        assert_eq!(parts.iter().map(|p| p.len()).sum::<usize>(), n_words);
    }
}
