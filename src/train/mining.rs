//! Error-guided ray sampling ("soft mining", Kheradmand et al., CVPR 2024).
//!
//! At 800×800 a NeRF-synthetic capture holds 64 M pixels, and a 30-minute
//! run on two cores marches fewer rays than that: uniform batches visit
//! most pixels less than once, spending half of them on white background
//! and flat colour that the field already renders right. The miner keeps a
//! running squared colour error per cell of consecutive training rays (a
//! stretch of an image row) and draws part of each batch in proportion to
//! it, so edges and fine texture are visited more often.
//!
//! A ray's probability is p = (1 − m)/n + m·e_c / Σ_c (s_c·e_c), where m is
//! the mined share, e_c its cell's error, s_c the cell's size. Its gradient
//! is weighted by (p_uniform / p)^α, normalised to a batch mean of 1: α = 1
//! would be the unbiased importance-sampling estimate of the uniform loss,
//! α = 0 plain hard mining (the soft-mining paper finds values between
//! them best). The loss shown is the self-normalised importance estimate of
//! the uniform loss, so the printed PSNR means what it meant before.
//!
//! Cells never visited count as the running mean error, so they are drawn
//! as often as an average cell until they are seen. The state is not kept
//! in checkpoints: a resumed run starts mining afresh.

use crate::util::SplitMix64;

/// Consecutive training rays per cell (a stretch of an image row).
pub const CELL: usize = 128;
/// Weight of a new measurement in a cell's running error.
const EMA: f32 = 0.5;

/// Running per-cell errors over `n` rays (positions in the subset of rays
/// that meet the box).
#[derive(Clone, Debug)]
pub struct RayMiner {
    n: usize,
    /// Mean squared error per cell; negative: never measured.
    err: Vec<f32>,
    /// Running mean of the measured errors (stands in for unmeasured cells).
    mean: f32,
    /// Share m of the sampling weight that follows the error.
    share: f32,
    /// Exponent α of the importance weights.
    alpha: f32,
    /// Cumulative error mass (error × size) over the cells, rebuilt in place
    /// after each batch is recorded; all 0 until then (uniform batches).
    cdf: Vec<f64>,
}

/// One mined batch: subset positions (ascending), gradient weights (mean 1)
/// and importance ratios p_uniform / p (for the loss estimate).
#[derive(Clone, Debug, Default)]
pub struct MinedBatch {
    pub positions: Vec<usize>,
    pub weights: Vec<f32>,
    pub ratios: Vec<f32>,
}

impl RayMiner {
    pub fn new(n: usize, share: f32, alpha: f32) -> RayMiner {
        let cells = n.div_ceil(CELL);
        RayMiner {
            n,
            err: vec![-1.0; cells],
            mean: 0.0,
            share: share.clamp(0.0, 1.0),
            alpha: alpha.clamp(0.0, 1.0),
            cdf: vec![0.0; cells],
        }
    }

    fn cell_size(&self, c: usize) -> usize {
        CELL.min(self.n - c * CELL)
    }

    /// A cell's error, unmeasured cells counting as the mean (a cell with no
    /// error left is still drawn through the uniform share).
    fn cell_error(&self, c: usize) -> f32 {
        let e = self.err[c];
        if e < 0.0 {
            self.mean
        } else {
            e
        }
    }

    /// `count` positions drawn with `rng` (see the module docs).
    pub fn sample(&self, rng: &mut SplitMix64, count: usize) -> MinedBatch {
        if self.n == 0 || count == 0 {
            return MinedBatch::default();
        }
        let (cdf, total) = (&self.cdf, self.cdf.last().copied().unwrap_or(0.0));
        let mined = if total > 0.0 { self.share as f64 } else { 0.0 };
        let uniform_p = 1.0 / self.n as f64;
        let mut drawn: Vec<(usize, f64)> = (0..count)
            .map(|_| {
                let k = if rng.unit() < mined {
                    let u = rng.unit() * total;
                    let c = cdf.partition_point(|&x| x <= u).min(self.err.len() - 1);
                    c * CELL + rng.below(self.cell_size(c))
                } else {
                    rng.below(self.n)
                };
                let c = k / CELL;
                let p_mined = if total > 0.0 {
                    self.cell_error(c) as f64 / total
                } else {
                    0.0
                };
                (k, uniform_p / ((1.0 - mined) * uniform_p + mined * p_mined))
            })
            .collect();
        drawn.sort_unstable_by_key(|d| d.0);
        let raw: Vec<f64> = drawn.iter().map(|d| d.1.powf(self.alpha as f64)).collect();
        let norm = count as f64 / raw.iter().sum::<f64>();
        MinedBatch {
            positions: drawn.iter().map(|d| d.0).collect(),
            weights: raw.iter().map(|w| (w * norm) as f32).collect(),
            ratios: drawn.iter().map(|d| d.1 as f32).collect(),
        }
    }

    /// Records the squared colour errors (mean over channels) measured at
    /// `positions`.
    pub fn record(&mut self, positions: &[usize], errors: &[f32]) {
        let mut sum = 0.0f64;
        for (&k, &e) in positions.iter().zip(errors) {
            let cell = &mut self.err[k / CELL];
            *cell = if *cell < 0.0 { e } else { (1.0 - EMA) * *cell + EMA * e };
            sum += e as f64;
        }
        if !errors.is_empty() {
            let batch = (sum / errors.len() as f64) as f32;
            self.mean = if self.mean == 0.0 {
                batch
            } else {
                0.9 * self.mean + 0.1 * batch
            };
        }
        self.rebuild_cdf();
    }

    /// Refills `cdf` from the errors (no allocation: at 800×800 lego it has
    /// 300k cells, rebuilt once per iteration).
    fn rebuild_cdf(&mut self) {
        let mut total = 0.0f64;
        for c in 0..self.err.len() {
            total += (self.cell_error(c) as f64) * self.cell_size(c) as f64;
            self.cdf[c] = total;
        }
    }
}

/// The self-normalised importance estimate of the uniform mean of
/// `errors`, from rays drawn with importance ratios `ratios`.
pub fn uniform_estimate(errors: &[f32], ratios: &[f32]) -> f64 {
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for (&e, &r) in errors.iter().zip(ratios) {
        num += e as f64 * r as f64;
        den += r as f64;
    }
    if den > 0.0 {
        num / den
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn without_errors_the_batch_is_uniform_with_unit_weights() {
        let m = RayMiner::new(1000, 0.5, 0.5);
        let b = m.sample(&mut SplitMix64::new(1), 64);
        assert_eq!(b.positions.len(), 64);
        assert!(b.positions.windows(2).all(|w| w[0] <= w[1]), "ascending");
        assert!(b.positions.iter().all(|&k| k < 1000));
        assert!(b.weights.iter().all(|&w| (w - 1.0).abs() < 1e-6));
        assert!(b.ratios.iter().all(|&r| (r - 1.0).abs() < 1e-6));
    }

    #[test]
    fn hard_cells_are_drawn_more_and_weighted_less() {
        // Two cells: the first 100 times as hard as the second.
        let mut m = RayMiner::new(2 * CELL, 0.5, 1.0);
        m.record(&[0, CELL], &[1.0, 0.01]);
        let b = m.sample(&mut SplitMix64::new(7), 20_000);
        let hard = b.positions.iter().filter(|&&k| k < CELL).count() as f64 / 20_000.0;
        // p(hard cell) = 0.5·0.5 + 0.5·100/101 ≈ 0.745.
        assert!((hard - 0.745).abs() < 0.02, "hard share {hard}");
        let w_hard = b.weights[0];
        let w_easy = *b.weights.last().unwrap();
        assert!(w_hard < 1.0 && w_easy > 1.0, "{w_hard} {w_easy}");
        // α = 1: weights are the (normalised) ratios p_uniform / p.
        let ratio = w_easy / w_hard;
        let expect = (0.5 / (0.25 + 0.5 / 101.0)) / (0.5 / (0.25 + 0.5 * 100.0 / 101.0));
        assert!((ratio / expect as f32 - 1.0).abs() < 1e-4, "{ratio} {expect}");
        // The importance estimate recovers the uniform mean (0.505).
        let errors: Vec<f32> = b.positions.iter().map(|&k| if k < CELL { 1.0 } else { 0.01 }).collect();
        let est = uniform_estimate(&errors, &b.ratios);
        assert!((est - 0.505).abs() < 0.02, "estimate {est}");
    }

    #[test]
    fn unmeasured_cells_count_as_the_mean_and_a_partial_last_cell_is_in_range() {
        let n = 3 * CELL + 5;
        let mut m = RayMiner::new(n, 1.0, 0.0);
        m.record(&[0], &[0.2]);
        assert_eq!(m.cell_error(3), m.mean);
        let b = m.sample(&mut SplitMix64::new(3), 10_000);
        assert!(b.positions.iter().all(|&k| k < n));
        // The 5-ray cell holds 5 / n of the (equal per ray) error mass.
        let last = b.positions.iter().filter(|&&k| k >= 3 * CELL).count() as f64 / 10_000.0;
        assert!((last - 5.0 / n as f64).abs() < 0.01, "{last}");
    }
}
