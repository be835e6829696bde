//! Sparse Adam over flat parameter arrays, total-variation gradients, and
//! merging the per-thread gradient buffers.
//!
//! Every thread owns a gradient buffer over the trainable points (the slots
//! of the active voxels, [`Slots`]) and a bitmap of the slots it touched;
//! after a batch the bitmaps are OR-ed and the optimizer walks only the
//! touched slots, in parallel chunks of whole bitmap words, summing the
//! threads' gradients, zeroing them and updating parameters and moments.
//! Moments are per slot too, so memory follows the active voxels, not the
//! grid. Untouched slots cost one zero-word test per 64.

use super::model::{remap_rows, Slots};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Grid points per parallel chunk (a multiple of 64).
const CHUNK: usize = 64 * 32;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamParams {
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
}

impl Default for AdamParams {
    fn default() -> Self {
        AdamParams {
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-8,
        }
    }
}

/// First and second moments of one parameter array (`stride` values per
/// grid point).
#[derive(Clone, Debug, Default)]
pub struct Moments {
    pub m: Vec<f32>,
    pub v: Vec<f32>,
}

impl Moments {
    pub fn new(len: usize) -> Self {
        Moments {
            m: vec![0.0; len],
            v: vec![0.0; len],
        }
    }
    /// The moments of `old`'s slots renumbered for `new` (whose voxels are a
    /// subset of `old`'s, e.g. after pruning), `stride` values per slot;
    /// voxels `old` lacks start from zero.
    pub fn remap(&self, old: &Slots, new: &Slots, stride: usize) -> Moments {
        Moments {
            m: remap_rows(&self.m, old, new, stride),
            v: remap_rows(&self.v, old, new, stride),
        }
    }
}

/// OR of the threads' touched bitmaps; clears them.
pub fn merge_marks(marks: &mut [&mut Vec<u64>]) -> Vec<u64> {
    let n = marks.first().map_or(0, |m| m.len());
    let mut out = vec![0u64; n];
    for m in marks.iter_mut() {
        out.par_iter_mut().zip(m.par_iter_mut()).for_each(|(o, w)| {
            *o |= *w;
            *w = 0;
        });
    }
    out
}

/// One Adam step on the points set in `touched`. Moments, gradients and
/// `touched` are per slot; with `slots`, slot `s` updates grid point
/// `slots.voxels[s]` of `params` (the active voxels of a grid), without,
/// slot `s` is point `s`. `grads` are the threads' gradient arrays; they are
/// summed and zeroed at every touched slot. `lr_t` already includes the
/// bias correction. Values are clamped to `clamp` afterwards.
#[allow(clippy::too_many_arguments)]
pub fn adam_step(
    params: &mut [f32],
    mom: &mut Moments,
    grads: &mut [&mut Vec<f32>],
    stride: usize,
    touched: &[u64],
    slots: Option<&Slots>,
    lr_t: f32,
    hp: AdamParams,
    clamp: (f32, f32),
) {
    if mom.m.is_empty() {
        return;
    }
    let span = CHUNK * stride;
    let pieces = param_pieces(params, slots, stride);
    let nchunks = mom.m.len().div_ceil(span);
    assert_eq!(pieces.len(), nchunks, "parameters and moments do not match");
    let mut per_chunk: Vec<Vec<&mut [f32]>> = (0..nchunks).map(|_| Vec::with_capacity(grads.len())).collect();
    for g in grads.iter_mut() {
        assert_eq!(g.len(), mom.m.len(), "gradients and moments do not match");
        for (c, sl) in g.chunks_mut(span).enumerate() {
            per_chunk[c].push(sl);
        }
    }
    let AdamParams { beta1, beta2, eps } = hp;
    let (lo, hi) = clamp;
    mom.m
        .par_chunks_mut(span)
        .zip(mom.v.par_chunks_mut(span))
        .zip(per_chunk.into_par_iter())
        .zip(pieces.into_par_iter())
        .enumerate()
        .for_each(|(c, (((m, v), mut gs), (offset, p)))| {
            let w0 = c * CHUNK / 64;
            let words = &touched[w0..(w0 + CHUNK / 64).min(touched.len())];
            let Some((first, rest)) = gs.split_first_mut() else {
                return;
            };
            for (wi, &word) in words.iter().enumerate() {
                let mut bits = word;
                while bits != 0 {
                    let b = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    let local = wi * 64 + b;
                    let r = local * stride..(local + 1) * stride;
                    let point = slots.map_or(c * CHUNK + local, |sl| sl.voxels[c * CHUNK + local] as usize);
                    let p0 = point * stride - offset;
                    // The first thread's slice collects the sum; slices and
                    // zips (no indexing) so that the loops vectorise.
                    let g = &mut first[r.clone()];
                    for other in rest.iter_mut() {
                        for (s, x) in g.iter_mut().zip(&mut other[r.clone()]) {
                            *s += *x;
                            *x = 0.0;
                        }
                    }
                    let values = p[p0..p0 + stride].iter_mut().zip(&mut m[r.clone()]).zip(&mut v[r]);
                    for (((q, mk), vk), gk) in values.zip(g.iter_mut()) {
                        let gj = std::mem::take(gk);
                        *mk = beta1 * *mk + (1.0 - beta1) * gj;
                        *vk = beta2 * *vk + (1.0 - beta2) * gj * gj;
                        *q = (*q - lr_t * *mk / (vk.sqrt() + eps)).clamp(lo, hi);
                    }
                }
            }
        });
}

/// `params` cut into one piece per chunk of `CHUNK` slots, each with the
/// offset of its first value: slots are ascending voxels, so a chunk's
/// voxels lie in one contiguous, disjoint range of the grid.
fn param_pieces<'a>(params: &'a mut [f32], slots: Option<&Slots>, stride: usize) -> Vec<(usize, &'a mut [f32])> {
    let span = CHUNK * stride;
    let Some(sl) = slots else {
        return params
            .chunks_mut(span)
            .enumerate()
            .map(|(c, p)| (c * span, p))
            .collect();
    };
    let mut out = Vec::with_capacity(sl.len().div_ceil(CHUNK));
    let mut rest = params;
    let mut consumed = 0;
    for chunk in sl.voxels.chunks(CHUNK) {
        let start = chunk[0] as usize * stride;
        let end = (chunk[chunk.len() - 1] as usize + 1) * stride;
        let (_, tail) = std::mem::take(&mut rest).split_at_mut(start - consumed);
        let (piece, tail) = tail.split_at_mut(end - start);
        out.push((start, piece));
        rest = tail;
        consumed = end;
    }
    out
}

/// [`adam_step`] on every value (stride 1): small dense parameter sets such
/// as the VM planes and the MLP, which every ray touches.
pub fn dense_adam_step(
    params: &mut [f32],
    mom: &mut Moments,
    grads: &mut [&mut Vec<f32>],
    lr_t: f32,
    hp: AdamParams,
    clamp: (f32, f32),
) {
    let n = params.len();
    let mut all = vec![u64::MAX; n.div_ceil(64)];
    if n % 64 != 0 {
        if let Some(last) = all.last_mut() {
            *last = (1u64 << (n % 64)) - 1;
        }
    }
    adam_step(params, mom, grads, 1, &all, None, lr_t, hp, clamp);
}

/// Bias-corrected learning rate of Adam step `t` (1-based).
pub fn corrected_lr(lr: f32, t: u64, hp: AdamParams) -> f32 {
    let t = t.min(1_000_000) as i32;
    lr * (1.0 - hp.beta2.powi(t)).sqrt() / (1.0 - hp.beta1.powi(t))
}

/// Where the values of a regularised array live (see [`add_tv`]).
#[derive(Clone, Copy, Debug)]
pub enum Layout<'a> {
    /// Parameters and gradients per grid point (features).
    Points,
    /// Parameters per grid point, gradients per slot (density).
    SlotGrads(&'a Slots),
    /// Parameters and gradients per slot (SH colour); pruned neighbours
    /// have no value and are left out.
    Slots(&'a Slots),
}

/// Adds the gradient of `weight · Σ (xᵥ − xₙ)²` over axis neighbours (the
/// squared total variation) at the touched slots (or points) to `grad`;
/// `stride` values per point, each channel on its own.
#[allow(clippy::too_many_arguments)]
pub fn add_tv(
    params: &[f32],
    grad: &mut [f32],
    stride: usize,
    res: [usize; 3],
    touched: &[u64],
    layout: Layout,
    weight: f32,
) {
    if weight == 0.0 {
        return;
    }
    let [nx, ny, nz] = res;
    let span = CHUNK * stride;
    grad.par_chunks_mut(span).enumerate().for_each(|(c, g)| {
        let w0 = c * CHUNK / 64;
        let words = &touched[w0..(w0 + CHUNK / 64).min(touched.len())];
        for (wi, &word) in words.iter().enumerate() {
            let mut bits = word;
            while bits != 0 {
                let b = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let local = wi * 64 + b;
                let slot = c * CHUNK + local;
                // Grid point of this entry, and where its parameters live.
                let (i, own) = match layout {
                    Layout::Points => (slot, slot),
                    Layout::SlotGrads(sl) => (sl.voxels[slot] as usize, sl.voxels[slot] as usize),
                    Layout::Slots(sl) => (sl.voxels[slot] as usize, slot),
                };
                let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
                let nb = [
                    (x > 0).then(|| i - 1),
                    (x + 1 < nx).then(|| i + 1),
                    (y > 0).then(|| i - nx),
                    (y + 1 < ny).then(|| i + nx),
                    (z > 0).then(|| i - nx * ny),
                    (z + 1 < nz).then(|| i + nx * ny),
                ];
                for j in nb.into_iter().flatten() {
                    let Some(j) = (match layout {
                        Layout::Slots(sl) => sl.slot(j),
                        _ => Some(j),
                    }) else {
                        continue;
                    };
                    let mine = &params[own * stride..(own + 1) * stride];
                    let theirs = &params[j * stride..(j + 1) * stride];
                    let out = &mut g[local * stride..(local + 1) * stride];
                    for ((o, a), b) in out.iter_mut().zip(mine).zip(theirs) {
                        *o += 2.0 * weight * (a - b);
                    }
                }
            }
        }
    });
}
