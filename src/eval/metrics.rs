//! Metrics (paper supplement, NVOS protocol): IoU = TP/(TP+FP+FN), pixel
//! accuracy = (TP+TN)/pixels, average precision of a soft mask, 3D IoU of
//! bitmaps, PSNR of images. Plain functions over slices.

use crate::field::Bitmap;
use glam::Vec3;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Confusion {
    pub tp: u64,
    pub fp: u64,
    pub fn_: u64,
    pub tn: u64,
}

impl Confusion {
    pub fn of(pred: &[bool], gt: &[bool]) -> Self {
        let mut c = Confusion::default();
        for (&p, &g) in pred.iter().zip(gt) {
            match (p, g) {
                (true, true) => c.tp += 1,
                (true, false) => c.fp += 1,
                (false, true) => c.fn_ += 1,
                (false, false) => c.tn += 1,
            }
        }
        c
    }
    /// TP/(TP+FP+FN); 1 when both masks are empty.
    pub fn iou(&self) -> f64 {
        let d = self.tp + self.fp + self.fn_;
        if d == 0 {
            1.0
        } else {
            self.tp as f64 / d as f64
        }
    }
    pub fn accuracy(&self) -> f64 {
        let n = self.tp + self.fp + self.fn_ + self.tn;
        if n == 0 {
            1.0
        } else {
            (self.tp + self.tn) as f64 / n as f64
        }
    }
}

pub fn iou(pred: &[bool], gt: &[bool]) -> f64 {
    Confusion::of(pred, gt).iou()
}

pub fn accuracy(pred: &[bool], gt: &[bool]) -> f64 {
    Confusion::of(pred, gt).accuracy()
}

/// Average precision of soft scores against a binary mask: pixels ranked by
/// score, AP = Σₙ (Rₙ − Rₙ₋₁) Pₙ over the ranks where recall grows (ties
/// are taken together). 0 if there are no positives.
pub fn average_precision(score: &[f32], gt: &[bool]) -> f64 {
    let positives = gt.iter().filter(|&&g| g).count();
    if positives == 0 {
        return 0.0;
    }
    let mut order: Vec<usize> = (0..score.len()).collect();
    order.sort_by(|&a, &b| score[b].total_cmp(&score[a]));
    let (mut tp, mut seen, mut ap, mut last_recall) = (0usize, 0usize, 0.0f64, 0.0f64);
    let mut i = 0;
    while i < order.len() {
        // Process a block of tied scores at once.
        let s = score[order[i]];
        while i < order.len() && score[order[i]] == s {
            tp += gt[order[i]] as usize;
            seen += 1;
            i += 1;
        }
        let recall = tp as f64 / positives as f64;
        ap += (recall - last_recall) * (tp as f64 / seen as f64);
        last_recall = recall;
    }
    ap
}

/// 3D IoU of two bitmaps of the same resolution.
pub fn iou3d(pred: &Bitmap, gt: &Bitmap) -> crate::Result<f64> {
    let inter = pred.intersection_count(gt)?;
    let union = pred.count() + gt.count() - inter;
    Ok(if union == 0 { 1.0 } else { inter as f64 / union as f64 })
}

/// Peak signal-to-noise ratio of two images in [0, 1] (infinite if equal).
pub fn psnr(a: &[Vec3], b: &[Vec3]) -> f64 {
    let n = a.len().min(b.len()).max(1) as f64 * 3.0;
    let mse: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (*x - *y).length_squared() as f64)
        .sum::<f64>()
        / n;
    if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_answers() {
        let p = [true, true, false, false, true];
        let g = [true, false, true, false, true];
        let c = Confusion::of(&p, &g);
        assert_eq!((c.tp, c.fp, c.fn_, c.tn), (2, 1, 1, 1));
        assert!((iou(&p, &g) - 0.5).abs() < 1e-12);
        assert!((accuracy(&p, &g) - 0.6).abs() < 1e-12);
        // Perfect ranking gives AP 1; a reversed one gives the hand-computed value.
        assert!((average_precision(&[0.9, 0.8, 0.1], &[true, true, false]) - 1.0).abs() < 1e-12);
        // Ranking f, t, t: P@2 = 1/2 at R = 1/2, P@3 = 2/3 at R = 1 → 0.25 + 1/3.
        let ap = average_precision(&[0.9, 0.8, 0.7], &[false, true, true]);
        assert!((ap - (0.25 + 1.0 / 3.0)).abs() < 1e-12, "{ap}");
        assert_eq!(psnr(&[Vec3::ONE], &[Vec3::ONE]), f64::INFINITY);
        let d = psnr(&[Vec3::splat(0.1)], &[Vec3::ZERO]);
        assert!((d - 20.0).abs() < 1e-4, "{d}");
        let a = Bitmap::from_fn([4, 4, 4], |i| i < 32);
        let b = Bitmap::from_fn([4, 4, 4], |i| i >= 16);
        assert!((iou3d(&a, &b).unwrap() - 16.0 / 64.0).abs() < 1e-12);
    }
}
