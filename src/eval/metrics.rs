//! Metrics (paper supplement, NVOS protocol): IoU = TP/(TP+FP+FN), pixel
//! accuracy = (TP+TN)/pixels, average precision of a soft mask, 3D IoU of
//! bitmaps, PSNR of images. Plain functions over slices.

use crate::field::Bitmap;
use glam::Vec3;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct Confusion {
    pub tp: u64,
    pub fp: u64,
    #[serde(rename = "fn")]
    pub fn_: u64,
    pub tn: u64,
}

impl Confusion {
    pub fn of(pred: &[bool], gt: &[bool]) -> Self {
        Self::count(pred.iter().copied().zip(gt.iter().copied()))
    }
    /// [`Confusion::of`] over the pixels `ignore` leaves out.
    pub fn outside(pred: &[bool], gt: &[bool], ignore: &[bool]) -> Self {
        let pairs = pred.iter().zip(gt).zip(ignore).filter(|(_, &skip)| !skip);
        Self::count(pairs.map(|((&p, &g), _)| (p, g)))
    }
    fn count(pairs: impl Iterator<Item = (bool, bool)>) -> Self {
        let mut c = Confusion::default();
        for pair in pairs {
            match pair {
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

/// Pixels within `r` pixels of the edge of mask `gt` (`w` × `h`,
/// row-major): their (2r+1)² square, clipped to the image, holds both
/// labels. Scores that leave them out ([`Confusion::outside`]) tell a wrong
/// outline from wrong parts; the outline is also where a hand-drawn or
/// thresholded mask is least certain.
pub fn edge_band(gt: &[bool], w: usize, h: usize, r: usize) -> Vec<bool> {
    assert_eq!(gt.len(), w * h, "mask of {w}×{h}");
    // Trues per clipped window: along rows, then along columns.
    let window = |i: usize, n: usize| i.saturating_sub(r)..(i + r + 1).min(n);
    let mut rows = vec![0u32; w * h];
    let mut prefix = vec![0u32; w.max(h) + 1];
    for y in 0..h {
        let line = &gt[y * w..(y + 1) * w];
        for x in 0..w {
            prefix[x + 1] = prefix[x] + line[x] as u32;
        }
        for x in 0..w {
            let span = window(x, w);
            rows[y * w + x] = prefix[span.end] - prefix[span.start];
        }
    }
    let mut band = vec![false; w * h];
    for x in 0..w {
        for y in 0..h {
            prefix[y + 1] = prefix[y] + rows[y * w + x];
        }
        let across = window(x, w).len() as u32;
        for y in 0..h {
            let span = window(y, h);
            let trues = prefix[span.end] - prefix[span.start];
            band[y * w + x] = trues > 0 && trues < across * span.len() as u32;
        }
    }
    band
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

/// How a render differs from its photo, split into blur and the rest: the
/// photo blurred by the Gaussian (σx, σy pixels, each from [`BLUR_SIGMAS`])
/// that the render is closest to, and the PSNR against that blurred photo.
/// A render that is the photo seen through a soft lens scores high against
/// the blurred photo; misplaced edges, floaters and colour errors do not go
/// away by blurring. Blur along one image axis only is what a field shows
/// when its depth is too coarse for the views offset along that axis (a
/// thin surface is smeared across the parallax of one depth cell).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct BlurFit {
    pub sigma_x: f32,
    pub sigma_y: f32,
    /// PSNR of the render against the photo blurred by (σx, σy).
    pub psnr: f64,
}

/// The Gaussian widths (pixels) [`blur_fit`] tries along each axis.
pub const BLUR_SIGMAS: [f32; 6] = [0.0, 0.4, 0.8, 1.2, 1.6, 2.0];

/// The [`BlurFit`] of `render` against `photo`, both `width × height`
/// row-major; `None` when the sizes disagree or the image is empty.
pub fn blur_fit(render: &[Vec3], photo: &[Vec3], width: usize, height: usize) -> Option<BlurFit> {
    let n = width.checked_mul(height)?;
    if n == 0 || render.len() != n || photo.len() != n {
        return None;
    }
    use rayon::prelude::*;
    let along_x: Vec<Vec<Vec3>> = BLUR_SIGMAS
        .par_iter()
        .map(|&sx| blur_axis(photo, width, height, sx, true))
        .collect();
    let pairs: Vec<(usize, usize)> = (0..BLUR_SIGMAS.len())
        .flat_map(|i| (0..BLUR_SIGMAS.len()).map(move |j| (i, j)))
        .collect();
    // In a fixed order, so that ties go to the least blur whatever the pool did.
    let scores: Vec<f64> = pairs
        .par_iter()
        .map(|&(i, j)| psnr(render, &blur_axis(&along_x[i], width, height, BLUR_SIGMAS[j], false)))
        .collect();
    let k = (1..scores.len()).fold(0, |best, k| if scores[k] > scores[best] { k } else { best });
    let (i, j) = pairs[k];
    Some(BlurFit {
        sigma_x: BLUR_SIGMAS[i],
        sigma_y: BLUR_SIGMAS[j],
        psnr: scores[k],
    })
}

/// `img` convolved with a normalised Gaussian of σ pixels along x (rows)
/// or y (columns), edges clamped; a copy for σ = 0.
fn blur_axis(img: &[Vec3], width: usize, height: usize, sigma: f32, along_x: bool) -> Vec<Vec3> {
    if sigma <= 0.0 {
        return img.to_vec();
    }
    let r = (3.0 * sigma).ceil() as isize;
    let norm: f32 = (-r..=r).map(|i| gauss(i, sigma)).sum();
    let kernel: Vec<f32> = (-r..=r).map(|i| gauss(i, sigma) / norm).collect();
    let clamp = |i: isize, len: usize| i.clamp(0, len as isize - 1) as usize;
    let mut out = vec![Vec3::ZERO; img.len()];
    for (y, row) in out.chunks_exact_mut(width).enumerate() {
        for (k, &w) in kernel.iter().enumerate() {
            let d = k as isize - r;
            if along_x {
                let src = &img[y * width..(y + 1) * width];
                for (x, o) in row.iter_mut().enumerate() {
                    *o += w * src[clamp(x as isize + d, width)];
                }
            } else {
                // Whole rows at a time: contiguous in memory.
                let sy = clamp(y as isize + d, height);
                for (o, s) in row.iter_mut().zip(&img[sy * width..(sy + 1) * width]) {
                    *o += w * *s;
                }
            }
        }
    }
    out
}

fn gauss(i: isize, sigma: f32) -> f32 {
    (-((i * i) as f32) / (2.0 * sigma * sigma)).exp()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_edge_band_holds_the_pixels_whose_square_sees_both_labels() {
        // A 4×4 square at x, y in 3..7 of a 10×10 mask.
        let (w, h) = (10, 10);
        let gt: Vec<bool> = (0..w * h)
            .map(|i| (3..7).contains(&(i % w)) && (3..7).contains(&(i / w)))
            .collect();
        assert!(edge_band(&gt, w, h, 0).iter().all(|&b| !b), "no band at radius 0");
        let band = edge_band(&gt, w, h, 1);
        // Squares that see a true pixel: 2..=7 each way (36); of those,
        // squares of trues only: 4..=5 each way (4).
        assert_eq!(band.iter().filter(|&&b| b).count(), 32);
        assert!(band[2 * w + 2] && band[3 * w + 3] && !band[4 * w + 4] && !band[w + 1]);
        let wide = edge_band(&gt, w, h, 2);
        assert_eq!(
            wide.iter().filter(|&&b| b).count(),
            64,
            "1..=8 each way, no square of trues only"
        );
        // At the image's border the window is clipped, not padded.
        let all = vec![true; w * h];
        assert!(edge_band(&all, w, h, 3).iter().all(|&b| !b));

        // The mask moved one pixel right: every error lies on the outline.
        let moved: Vec<bool> = (0..w * h).map(|i| i % w > 0 && gt[i - 1]).collect();
        assert!((Confusion::of(&moved, &gt).iou() - 12.0 / 20.0).abs() < 1e-12);
        assert_eq!(Confusion::outside(&moved, &gt, &band).iou(), 1.0);
        // A wrong part far from the outline still counts.
        let mut blob = moved.clone();
        blob[9 * w + 9] = true;
        let c = Confusion::outside(&blob, &gt, &band);
        assert_eq!((c.tp, c.fp, c.fn_), (4, 1, 0));
    }

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

    /// A test card: a hard-edged checkerboard (edges along both axes).
    fn card(w: usize, h: usize) -> Vec<Vec3> {
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if (x / 5 + y / 5) % 2 == 0 {
                    Vec3::new(0.9, 0.8, 0.7)
                } else {
                    Vec3::new(0.1, 0.2, 0.3)
                }
            })
            .collect()
    }

    #[test]
    fn blur_fit_finds_the_axis_and_width_a_render_is_blurred_by() {
        let (w, h) = (40, 30);
        let photo = card(w, h);
        // The photo itself: no blur, exact.
        let f = blur_fit(&photo, &photo, w, h).unwrap();
        assert_eq!((f.sigma_x, f.sigma_y, f.psnr), (0.0, 0.0, f64::INFINITY));
        // Blurred along x only (a smear across horizontal parallax).
        let smeared = blur_axis(&photo, w, h, 1.2, true);
        let f = blur_fit(&smeared, &photo, w, h).unwrap();
        assert_eq!((f.sigma_x, f.sigma_y), (1.2, 0.0));
        assert!(psnr(&smeared, &photo) < 25.0 && f.psnr == f64::INFINITY, "{f:?}");
        // Along y, then both, at other widths.
        let f = blur_fit(&blur_axis(&photo, w, h, 0.8, false), &photo, w, h).unwrap();
        assert_eq!((f.sigma_x, f.sigma_y), (0.0, 0.8));
        let both = blur_axis(&blur_axis(&photo, w, h, 1.6, true), w, h, 0.4, false);
        let f = blur_fit(&both, &photo, w, h).unwrap();
        assert_eq!((f.sigma_x, f.sigma_y), (1.6, 0.4));
        // Blur keeps the mean: a flat image blurs to itself.
        let flat = vec![Vec3::splat(0.5); w * h];
        for along_x in [true, false] {
            let b = blur_axis(&flat, w, h, 2.0, along_x);
            assert!(b.iter().all(|c| (*c - Vec3::splat(0.5)).abs().max_element() < 1e-6));
        }
        // An error blur cannot explain stays: a shifted card.
        let shifted: Vec<Vec3> = (0..w * h).map(|i| photo[(i / w) * w + (i % w + 2) % w]).collect();
        assert!(blur_fit(&shifted, &photo, w, h).unwrap().psnr < 15.0);
        // Sizes that disagree or an empty image: no fit.
        assert!(blur_fit(&photo[1..], &photo, w, h).is_none());
        assert!(blur_fit(&[], &[], 0, 5).is_none());
    }
}
