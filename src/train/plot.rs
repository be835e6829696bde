//! The loss / PSNR curves of a run as a PNG: two panels (log₁₀ colour loss,
//! PSNR in dB) over iterations, the raw per-iteration values in light grey
//! and a moving average in colour, held-out PSNR as dots. Drawn with the
//! `image` crate and a built-in 3×5 pixel font for the axis labels, so no
//! plotting or font crates are needed.

use super::trainer::StepStats;
use crate::error::{write_atomic, Error, Result};
use image::{Rgb, RgbImage};
use std::path::Path;

const W: u32 = 900;
const PANEL_H: u32 = 300;
const LEFT: u32 = 70;
const RIGHT: u32 = 20;
const TOP: u32 = 30;
const BOTTOM: u32 = 30;

/// A held-out measurement: (iteration, PSNR).
pub type EvalPoint = (usize, f32);

/// Draws the curves of `history` (and held-out `evals`) into a PNG.
pub fn save_plot(path: &Path, history: &[StepStats], evals: &[EvalPoint]) -> Result<()> {
    let img = draw(history, evals);
    let mut bytes = std::io::Cursor::new(Vec::new());
    img.write_to(&mut bytes, image::ImageFormat::Png)
        .map_err(|e| Error::invalid(format!("png encoding: {e}")))?;
    write_atomic(path, &bytes.into_inner())
}

pub fn draw(history: &[StepStats], evals: &[EvalPoint]) -> RgbImage {
    let h = 2 * (PANEL_H + TOP + BOTTOM);
    let mut img = RgbImage::from_pixel(W, h, Rgb([255, 255, 255]));
    let xmax = history
        .last()
        .map_or(1, |s| s.iter)
        .max(evals.iter().map(|e| e.0).max().unwrap_or(1))
        .max(1) as f32;
    let loss: Vec<(f32, f32)> = history
        .iter()
        .filter(|s| s.loss > 0.0 && s.loss.is_finite())
        .map(|s| (s.iter as f32, s.loss.log10()))
        .collect();
    let psnr: Vec<(f32, f32)> = history
        .iter()
        .filter(|s| s.psnr.is_finite())
        .map(|s| (s.iter as f32, s.psnr))
        .collect();
    let ev: Vec<(f32, f32)> = evals.iter().map(|&(i, p)| (i as f32, p)).collect();
    panel(&mut img, 0, "LOSS LOG10", &loss, &[], xmax, [200, 60, 40]);
    panel(
        &mut img,
        PANEL_H + TOP + BOTTOM,
        "PSNR DB",
        &psnr,
        &ev,
        xmax,
        [40, 90, 200],
    );
    img
}

fn panel(img: &mut RgbImage, y0: u32, title: &str, pts: &[(f32, f32)], dots: &[(f32, f32)], xmax: f32, color: [u8; 3]) {
    let (x_lo, x_hi) = (LEFT, W - RIGHT);
    let (y_lo, y_hi) = (y0 + TOP, y0 + TOP + PANEL_H);
    text(img, LEFT, y0 + 8, title, 2, [0, 0, 0]);
    let all = pts.iter().chain(dots).map(|p| p.1);
    let (mut lo, mut hi) = all.fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if !lo.is_finite() {
        (lo, hi) = (0.0, 1.0);
    }
    if hi - lo < 1e-3 {
        hi = lo + 1.0;
    }
    let pad = 0.05 * (hi - lo);
    let (lo, hi) = (lo - pad, hi + pad);
    let map = |x: f32, y: f32| -> (i64, i64) {
        let px = x_lo as f32 + x / xmax * (x_hi - x_lo) as f32;
        let py = y_hi as f32 - (y - lo) / (hi - lo) * (y_hi - y_lo) as f32;
        (px.round() as i64, py.round() as i64)
    };
    // Frame, grid lines and tick labels.
    for k in 0..=4 {
        let v = lo + (hi - lo) * k as f32 / 4.0;
        let (_, py) = map(0.0, v);
        hline(img, x_lo, x_hi, py, [225, 225, 225]);
        text(img, 4, (py - 5).max(0) as u32, &format!("{v:.2}"), 2, [60, 60, 60]);
        let it = xmax * k as f32 / 4.0;
        let (px, _) = map(it, lo);
        text(
            img,
            (px - 10).max(0) as u32,
            y_hi + 8,
            &format!("{}", it.round() as i64),
            2,
            [60, 60, 60],
        );
    }
    hline(img, x_lo, x_hi, y_hi as i64, [0, 0, 0]);
    for y in y_lo..=y_hi {
        put(img, x_lo as i64, y as i64, [0, 0, 0]);
    }
    for &(x, y) in pts {
        let (px, py) = map(x, y);
        put(img, px, py, [200, 200, 200]);
    }
    // Moving average over ~1 % of the run (at least 1 point).
    let win = (pts.len() / 100).max(1);
    let mut prev: Option<(i64, i64)> = None;
    let mut acc = 0.0;
    for (i, &(x, y)) in pts.iter().enumerate() {
        acc += y;
        if i >= win {
            acc -= pts[i - win].1;
        }
        let n = (i + 1).min(win) as f32;
        let p = map(x, acc / n);
        if let Some(q) = prev {
            line(img, q, p, color);
        }
        prev = Some(p);
    }
    for &(x, y) in dots {
        let (px, py) = map(x, y);
        for dy in -3..=3 {
            for dx in -3..=3 {
                if dx * dx + dy * dy <= 9 {
                    put(img, px + dx, py + dy, [20, 150, 60]);
                }
            }
        }
    }
}

fn put(img: &mut RgbImage, x: i64, y: i64, c: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, Rgb(c));
    }
}

fn hline(img: &mut RgbImage, x0: u32, x1: u32, y: i64, c: [u8; 3]) {
    for x in x0..=x1 {
        put(img, x as i64, y, c);
    }
}

/// Bresenham line.
fn line(img: &mut RgbImage, a: (i64, i64), b: (i64, i64), c: [u8; 3]) {
    let (mut x, mut y) = a;
    let (dx, dy) = ((b.0 - x).abs(), -(b.1 - y).abs());
    let (sx, sy) = (if x < b.0 { 1 } else { -1 }, if y < b.1 { 1 } else { -1 });
    let mut err = dx + dy;
    loop {
        put(img, x, y, c);
        if (x, y) == b {
            break;
        }
        let e2 = 2 * err;
        if e2 >= dy {
            err += dy;
            x += sx;
        }
        if e2 <= dx {
            err += dx;
            y += sy;
        }
    }
}

/// 3×5 glyphs, one row per entry (bit 2 = left column).
fn glyph(ch: char) -> [u8; 5] {
    match ch {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 1, 2, 2],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        '-' => [0, 0, 7, 0, 0],
        'B' => [6, 5, 6, 5, 6],
        'D' => [6, 5, 5, 5, 6],
        'G' => [7, 4, 5, 5, 7],
        'L' => [4, 4, 4, 4, 7],
        'N' => [5, 7, 7, 7, 5],
        'O' => [7, 5, 5, 5, 7],
        'P' => [7, 5, 7, 4, 4],
        'R' => [6, 5, 6, 5, 5],
        'S' => [7, 4, 7, 1, 7],
        _ => [0; 5],
    }
}

fn text(img: &mut RgbImage, x: u32, y: u32, s: &str, scale: u32, c: [u8; 3]) {
    for (i, ch) in s.chars().enumerate() {
        let g = glyph(ch);
        let ox = x + i as u32 * 4 * scale;
        for (row, bits) in g.iter().enumerate() {
            for col in 0..3 {
                if bits >> (2 - col) & 1 == 1 {
                    for dy in 0..scale {
                        for dx in 0..scale {
                            put(
                                img,
                                (ox + col * scale + dx) as i64,
                                (y + row as u32 * scale + dy) as i64,
                                c,
                            );
                        }
                    }
                }
            }
        }
    }
}
