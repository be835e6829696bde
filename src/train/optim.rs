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
//!
//! Moments are stored in bf16 (f32's range, 8 bits of mantissa): on the
//! fern's 448 grid the SH moments alone were 820 MB in f32. Each step
//! computes in f32 from them and rounds once when storing; the rounding
//! (≤ 0.4 %) is far below what the β's average over.

use super::model::{remap_rows, remap_rows_in_place, Slots};
use crate::util::SplitMix64;
use half::bf16;
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
    pub m: Vec<bf16>,
    pub v: Vec<bf16>,
}

impl Moments {
    pub fn new(len: usize) -> Self {
        Moments {
            m: vec![bf16::ZERO; len],
            v: vec![bf16::ZERO; len],
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
    /// [`Moments::remap`] in place ([`remap_rows_in_place`]: no copy when
    /// `new` only drops slots).
    pub fn remap_in_place(&mut self, old: &Slots, new: &Slots, stride: usize) {
        remap_rows_in_place(&mut self.m, old, new, stride);
        remap_rows_in_place(&mut self.v, old, new, stride);
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
    let (k, avx2) = (StepConsts::new(hp, lr_t, clamp), crate::util::has_avx2());
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
    mom.m
        .par_chunks_mut(span)
        .zip(mom.v.par_chunks_mut(span))
        .zip(per_chunk.into_par_iter())
        .zip(pieces.into_par_iter())
        .enumerate()
        .for_each(|(c, (((m, v), mut gs), (offset, p)))| {
            let w0 = c * CHUNK / 64;
            let words = &touched[w0..(w0 + CHUNK / 64).min(touched.len())];
            let chunk = Chunk {
                first_slot: c * CHUNK,
                offset,
                stride,
                slots,
            };
            #[cfg(target_arch = "x86_64")]
            if avx2 {
                // SAFETY: `has_avx2` found AVX2 on this CPU.
                unsafe { avx2_update_chunk(&chunk, words, p, m, v, &mut gs, k) };
                return;
            }
            let _ = avx2;
            update_chunk(&chunk, words, p, m, v, &mut gs, k);
        });
}

/// The constants of one Adam step (`lr_t` bias-corrected).
#[derive(Clone, Copy)]
struct StepConsts {
    beta1: f32,
    beta2: f32,
    eps: f32,
    lr_t: f32,
    lo: f32,
    hi: f32,
}

impl StepConsts {
    fn new(hp: AdamParams, lr_t: f32, (lo, hi): (f32, f32)) -> Self {
        StepConsts {
            beta1: hp.beta1,
            beta2: hp.beta2,
            eps: hp.eps,
            lr_t,
            lo,
            hi,
        }
    }
}

/// Where one parallel chunk of [`adam_step`] lies: its first slot, the
/// grid value its parameter piece starts at, values per slot, and the
/// slot-to-point map (none: slot `s` is point `s`).
struct Chunk<'a> {
    first_slot: usize,
    offset: usize,
    stride: usize,
    slots: Option<&'a Slots>,
}

/// [`update_chunk`] compiled for AVX2: the same operations on each value
/// (no fused multiply-add), eight lanes wide, so bit for bit the same.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn avx2_update_chunk(
    chunk: &Chunk,
    words: &[u64],
    p: &mut [f32],
    m: &mut [bf16],
    v: &mut [bf16],
    gs: &mut [&mut [f32]],
    k: StepConsts,
) {
    update_chunk(chunk, words, p, m, v, gs, k)
}

/// Adam on the touched slots of one chunk. Runs of consecutive touched
/// slots whose points are consecutive too (always so for per-point arrays
/// such as the SH colour) are updated as one stretch of values: a loop
/// long enough to vectorise, where a slot's 27 SH values alone left the
/// loop scalar (the colour update was 30 % of a full-size lego step).
#[inline(always)]
fn update_chunk(
    chunk: &Chunk,
    words: &[u64],
    p: &mut [f32],
    m: &mut [bf16],
    v: &mut [bf16],
    gs: &mut [&mut [f32]],
    k: StepConsts,
) {
    let Some((first, rest)) = gs.split_first_mut() else {
        return;
    };
    let stride = chunk.stride;
    let point = |local: usize| {
        let s = chunk.first_slot + local;
        chunk.slots.map_or(s, |sl| sl.voxels[s] as usize)
    };
    for (wi, &word) in words.iter().enumerate() {
        let mut bits = word;
        while bits != 0 {
            let b = bits.trailing_zeros() as usize;
            // The run of set bits from b, cut where the points stop being
            // consecutive.
            let ones = (!(bits >> b)).trailing_zeros().min(64 - b as u32) as usize;
            let start = wi * 64 + b;
            let mut len = 1;
            while len < ones && point(start + len) == point(start) + len {
                len += 1;
            }
            bits &= !(((1u128 << (b + len)) - 1) as u64 & !((1u64 << b) - 1));
            let r = start * stride..(start + len) * stride;
            let p0 = point(start) * stride - chunk.offset;
            // The first thread's slice collects the sum.
            let g = &mut first[r.clone()];
            for other in rest.iter_mut() {
                for (s, x) in g.iter_mut().zip(&mut other[r.clone()]) {
                    *s += *x;
                    *x = 0.0;
                }
            }
            update_values(&mut p[p0..p0 + r.len()], &mut m[r.clone()], &mut v[r], g, k);
        }
    }
}

/// Adam on one stretch of values; `g` holds their summed gradients and is
/// zeroed. Indexed over slices cut to one length, so that the loop
/// vectorises without bounds checks.
#[inline(always)]
fn update_values(q: &mut [f32], m: &mut [bf16], v: &mut [bf16], g: &mut [f32], k: StepConsts) {
    let n = q.len();
    let (m, v, g) = (&mut m[..n], &mut v[..n], &mut g[..n]);
    for i in 0..n {
        let gj = g[i];
        g[i] = 0.0;
        let mf = k.beta1 * widen(m[i]) + (1.0 - k.beta1) * gj;
        let vf = k.beta2 * widen(v[i]) + (1.0 - k.beta2) * gj * gj;
        q[i] = (q[i] - k.lr_t * mf / (vf.sqrt() + k.eps)).clamp(k.lo, k.hi);
        m[i] = narrow(mf);
        v[i] = narrow(vf);
    }
}

/// bf16 → f32, exact. `half`'s conversions branch on NaN, which keeps the
/// Adam loop from vectorising; moments are finite.
#[inline(always)]
fn widen(b: bf16) -> f32 {
    f32::from_bits((b.to_bits() as u32) << 16)
}

/// f32 → bf16, rounding to nearest even (as `bf16::from_f32` for every
/// finite value and infinity), without branches.
#[inline(always)]
fn narrow(x: f32) -> bf16 {
    let u = x.to_bits();
    bf16::from_bits((u.wrapping_add(0x7FFF + ((u >> 16) & 1)) >> 16) as u16)
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
    if !n.is_multiple_of(64) {
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

/// Weight and sampling of a total-variation term (see [`add_tv`]).
#[derive(Clone, Copy, Debug)]
pub struct Tv {
    pub weight: f32,
    /// Fraction of the touched points regularised at this step, drawn
    /// afresh each step from `seed`; their weight is divided by it, so the
    /// expected gradient is the full one at a fraction of the cost (as
    /// Plenoxels samples its TV).
    pub keep: f32,
    pub seed: u64,
}

impl Tv {
    /// Every touched point, every step.
    pub fn full(weight: f32) -> Tv {
        Tv {
            weight,
            keep: 1.0,
            seed: 0,
        }
    }
    /// Whether entry `i` is regularised at this step.
    #[inline]
    fn keeps(&self, i: usize) -> bool {
        self.keep >= 1.0 || (SplitMix64::new(self.seed ^ i as u64).unit() as f32) < self.keep
    }
}

/// Adds the gradient of `weight · Σ (xᵥ − xₙ)²` over axis neighbours (the
/// squared total variation) at the touched slots (or points) to `grad`;
/// `stride` values per point, each channel on its own.
pub fn add_tv(
    params: &[f32],
    grad: &mut [f32],
    stride: usize,
    res: [usize; 3],
    touched: &[u64],
    layout: Layout,
    tv: Tv,
) {
    if tv.weight == 0.0 || tv.keep <= 0.0 {
        return;
    }
    let weight = tv.weight / tv.keep.min(1.0);
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
                if !tv.keeps(slot) {
                    continue;
                }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn branch_free_bf16_conversions_agree_with_half() {
        let mut rng = crate::util::SplitMix64::new(7);
        let special = [
            0.0f32,
            -0.0,
            1.0,
            -1.0,
            f32::MAX,
            f32::MIN_POSITIVE,
            1e-40,
            f32::INFINITY,
            65504.0,
        ];
        let random = (0..100_000)
            .map(|_| f32::from_bits(rng.next_u64() as u32))
            .filter(|x| x.is_finite());
        for x in special.into_iter().chain(random) {
            assert_eq!(narrow(x).to_bits(), bf16::from_f32(x).to_bits(), "{x:e}");
            let b = bf16::from_f32(x);
            assert_eq!(widen(b).to_bits(), b.to_f32().to_bits(), "{x:e}");
        }
    }

    /// The sparse step, whatever its chunking, runs and vector width, is
    /// per value exactly the textbook update on the touched slots (bit for
    /// bit) and leaves every other value alone: with and without a slot
    /// map, one value and 27 values (SH degree 2) per slot, two gradient
    /// buffers summed.
    #[test]
    fn sparse_adam_is_the_scalar_update_bit_for_bit() {
        let mut rng = SplitMix64::new(11);
        let mut unit = move || (rng.next_u64() >> 40) as f32 / (1u64 << 24) as f32;
        let points = 3 * CHUNK + 517;
        // Every third point pruned in runs, so runs of slots meet gaps in
        // the points.
        let active: Vec<u64> = (0..points.div_ceil(64))
            .map(|w| if w % 3 == 1 { 0xF0F0_FFFF_0000_FFFF } else { u64::MAX })
            .collect();
        let slots = Slots::new([points, 1, 1], &active);
        let cases = [(1, true), (27, false), (3, true)];
        // `adam_step` (chunked, in parallel, on AVX2 where the CPU has it)
        // and the portable kernel over the whole array as one chunk.
        for ((stride, with_slots), portable) in cases.into_iter().flat_map(|c| [false, true].map(|a| (c, a))) {
            let n = if with_slots { slots.len() } else { points };
            let len_p = if with_slots { points * stride } else { n * stride };
            let mut p: Vec<f32> = (0..len_p).map(|_| unit() - 0.5).collect();
            let mut mom = Moments::new(n * stride);
            for (m, v) in mom.m.iter_mut().zip(mom.v.iter_mut()) {
                *m = bf16::from_f32(unit() - 0.5);
                *v = bf16::from_f32(unit() * 0.01);
            }
            let touched: Vec<u64> = (0..n.div_ceil(64))
                .map(|w| {
                    let word = if w % 5 == 0 { u64::MAX } else { rng_word(w) };
                    if (w + 1) * 64 > n {
                        word & ((1u64 << (n % 64)) - 1)
                    } else {
                        word
                    }
                })
                .collect();
            let mut g0: Vec<f32> = (0..n * stride).map(|_| unit() - 0.5).collect();
            let mut g1: Vec<f32> = (0..n * stride).map(|_| unit() - 0.5).collect();
            let (p_ref, m_ref, v_ref) = (p.clone(), mom.m.clone(), mom.v.clone());
            let (g0_ref, g1_ref) = (g0.clone(), g1.clone());
            let hp = AdamParams::default();
            let (lr, clamp) = (0.05, (-0.4, 0.45));
            let map = with_slots.then_some(&slots);
            if portable {
                let chunk = Chunk {
                    first_slot: 0,
                    offset: 0,
                    stride,
                    slots: map,
                };
                let (m, v, k) = (&mut mom.m, &mut mom.v, StepConsts::new(hp, lr, clamp));
                update_chunk(&chunk, &touched, &mut p, m, v, &mut [&mut g0, &mut g1], k);
            } else {
                adam_step(
                    &mut p,
                    &mut mom,
                    &mut [&mut g0, &mut g1],
                    stride,
                    &touched,
                    map,
                    lr,
                    hp,
                    clamp,
                );
            }
            for s in 0..n {
                let point = map.map_or(s, |sl| sl.voxels[s] as usize);
                for j in 0..stride {
                    let (i, q) = (s * stride + j, point * stride + j);
                    if !bit(&touched, s) {
                        assert_eq!(p[q].to_bits(), p_ref[q].to_bits());
                        assert_eq!(mom.m[i], m_ref[i]);
                        assert_eq!(g0[i], g0_ref[i]);
                        continue;
                    }
                    let g = g0_ref[i] + g1_ref[i];
                    let mf = hp.beta1 * widen(m_ref[i]) + (1.0 - hp.beta1) * g;
                    let vf = hp.beta2 * widen(v_ref[i]) + (1.0 - hp.beta2) * g * g;
                    let want = (p_ref[q] - lr * mf / (vf.sqrt() + hp.eps)).clamp(clamp.0, clamp.1);
                    assert_eq!(
                        p[q].to_bits(),
                        want.to_bits(),
                        "stride {stride}, portable {portable}, slot {s}, value {j}"
                    );
                    assert_eq!((mom.m[i], mom.v[i]), (narrow(mf), narrow(vf)));
                    assert_eq!((g0[i], g1[i]), (0.0, 0.0));
                }
            }
        }
    }

    /// A scrambled bitmap word.
    fn rng_word(w: usize) -> u64 {
        SplitMix64::new(w as u64 ^ 0xA5A5).next_u64()
    }

    fn bit(words: &[u64], i: usize) -> bool {
        words[i / 64] >> (i % 64) & 1 == 1
    }

    const RES: [usize; 3] = [5, 4, 3];

    /// A bitmap with the first `n` bits set.
    fn ones(n: usize) -> Vec<u64> {
        (0..n.div_ceil(64))
            .map(|w| {
                if (w + 1) * 64 <= n {
                    u64::MAX
                } else {
                    (1u64 << (n % 64)) - 1
                }
            })
            .collect()
    }

    /// w · Σ over pairs of active axis neighbours of |xₐ − x_b|², by brute force.
    fn tv_energy(x: &[f32], active: &dyn Fn(usize) -> bool, stride: usize, w: f32) -> f64 {
        let [nx, ny, nz] = RES;
        let mut e = 0.0f64;
        for i in 0..nx * ny * nz {
            let (a, b, c) = (i % nx, (i / nx) % ny, i / (nx * ny));
            let fwd = [(a + 1 < nx, i + 1), (b + 1 < ny, i + nx), (c + 1 < nz, i + nx * ny)];
            for (ok, j) in fwd {
                if ok && active(i) && active(j) {
                    for s in 0..stride {
                        let d = (x[i * stride + s] - x[j * stride + s]) as f64;
                        e += w as f64 * d * d;
                    }
                }
            }
        }
        e
    }

    #[test]
    fn tv_gradient_matches_finite_differences_on_points_and_slots() {
        let n = RES.iter().product::<usize>();
        let stride = 2;
        let mut rng = SplitMix64::new(3);
        let x: Vec<f32> = (0..n * stride).map(|_| rng.unit() as f32).collect();
        let w = 0.7;
        // Every point touched, grid layout.
        let all = ones(n);
        let mut g = vec![0.0; n * stride];
        add_tv(&x, &mut g, stride, RES, &all, Layout::Points, Tv::full(w));
        let yes = |_: usize| true;
        for k in [0, 7, 23, 41, 59] {
            let (mut p, mut m) = (x.clone(), x.clone());
            p[k] += 1e-2;
            m[k] -= 1e-2;
            let fd = (tv_energy(&p, &yes, stride, w) - tv_energy(&m, &yes, stride, w)) / 2e-2;
            assert!((g[k] as f64 - fd).abs() < 1e-3, "point value {k}: {} vs {fd}", g[k]);
        }
        // Per-slot storage with every third point pruned: pruned neighbours
        // take no part in the energy.
        let active = |i: usize| i % 3 != 1;
        let mut bits = vec![0u64; n.div_ceil(64)];
        for i in (0..n).filter(|&i| active(i)) {
            bits[i >> 6] |= 1 << (i & 63);
        }
        let slots = Slots::new(RES, &bits);
        let xs: Vec<f32> = slots
            .voxels
            .iter()
            .flat_map(|&v| x[v as usize * stride..(v as usize + 1) * stride].to_vec())
            .collect();
        let touched = ones(slots.len());
        let mut gs = vec![0.0; xs.len()];
        add_tv(&xs, &mut gs, stride, RES, &touched, Layout::Slots(&slots), Tv::full(w));
        for (s, &v) in slots.voxels.iter().enumerate().step_by(5) {
            let k = v as usize * stride + 1;
            let (mut p, mut m) = (x.clone(), x.clone());
            p[k] += 1e-2;
            m[k] -= 1e-2;
            let fd = (tv_energy(&p, &active, stride, w) - tv_energy(&m, &active, stride, w)) / 2e-2;
            assert!(
                (gs[s * stride + 1] as f64 - fd).abs() < 1e-3,
                "slot {s}: {} vs {fd}",
                gs[s * stride + 1]
            );
        }
    }

    #[test]
    fn sampled_tv_is_the_full_tv_in_expectation() {
        let n = RES.iter().product::<usize>();
        let mut rng = SplitMix64::new(5);
        let x: Vec<f32> = (0..n).map(|_| rng.unit() as f32).collect();
        let all = ones(n);
        let mut full = vec![0.0; n];
        add_tv(&x, &mut full, 1, RES, &all, Layout::Points, Tv::full(1.0));
        let mut mean = vec![0.0f64; n];
        let trials = 4000;
        let mut kept = 0usize;
        for seed in 0..trials {
            let mut g = vec![0.0; n];
            let tv = Tv {
                weight: 1.0,
                keep: 0.25,
                seed: SplitMix64::new(seed).next_u64(),
            };
            add_tv(&x, &mut g, 1, RES, &all, Layout::Points, tv);
            kept += g.iter().filter(|v| **v != 0.0).count();
            for (m, v) in mean.iter_mut().zip(&g) {
                *m += *v as f64 / trials as f64;
            }
        }
        let frac = kept as f64 / (trials as usize * n) as f64;
        assert!(
            (frac - 0.25).abs() < 0.01,
            "a quarter of the points each step, got {frac}"
        );
        for (m, f) in mean.iter().zip(&full) {
            assert!(
                (m - *f as f64).abs() < 0.1 * f.abs().max(0.5) as f64,
                "mean {m} vs full {f}"
            );
        }
    }
}
