//! Spherical harmonics as splat renderers use them (degree ≤ 3, colour =
//! 0.5 + Σ Y·c, clamped), their conversion to and from isrf's SH2
//! appearance (colour = sigmoid(Σ Y·c), degree ≤ 2), and their rotation.

use crate::field::sh::SH_COEFFS;
use glam::{Mat3, Vec3};
use nalgebra::DMatrix;

pub const C0: f32 = 0.282_094_8;
const C3: [f32; 7] = [
    -0.590_043_6,
    2.890_611_4,
    -0.457_045_8,
    0.373_176_33,
    -0.457_045_8,
    1.445_305_7,
    -0.590_043_6,
];

/// The 16 basis values of degrees 0..=3 for unit direction `d`, in the
/// order and signs of the INRIA renderer (its first 9 are
/// [`crate::field::sh::basis`]).
pub fn basis16(d: Vec3) -> [f32; 16] {
    let b9 = crate::field::sh::basis(d);
    let (x, y, z) = (d.x, d.y, d.z);
    let (xx, yy, zz) = (x * x, y * y, z * z);
    let mut out = [0.0; 16];
    out[..9].copy_from_slice(&b9);
    out[9] = C3[0] * y * (3.0 * xx - yy);
    out[10] = C3[1] * x * y * z;
    out[11] = C3[2] * y * (4.0 * zz - xx - yy);
    out[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
    out[13] = C3[4] * x * (4.0 * zz - xx - yy);
    out[14] = C3[5] * z * (xx - yy);
    out[15] = C3[6] * x * (xx - 3.0 * yy);
    out
}

/// A splat's colour seen along `d`: `dc` and channel-major `rest`
/// (`3 × k` values, k = 0, 3, 8 or 15), before clamping.
pub fn splat_color(dc: [f32; 3], rest: &[f32], d: Vec3) -> Vec3 {
    let b = basis16(d);
    let k = rest.len() / 3;
    let ch = |c: usize| C0 * dc[c] + (0..k).map(|j| rest[c * k + j] * b[j + 1]).sum::<f32>() + 0.5;
    Vec3::new(ch(0), ch(1), ch(2))
}

fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

/// Smallest slope of the sigmoid used to convert view-dependent terms:
/// near-black or near-white colours would otherwise blow them up.
const MIN_SLOPE: f32 = 0.1;

/// A splat's SH (degree ≤ 2 kept) as isrf's 27 SH2 channels
/// `[r0..r8, g0..g8, b0..b8]`: the DC term gives the same base colour
/// through the sigmoid (within 1/50 of 0 and 1), the others are scaled by
/// the sigmoid's slope there, so small view-dependent changes match.
pub fn to_field_sh2(dc: [f32; 3], rest: &[f32], out: &mut [f32]) {
    let k = rest.len() / 3;
    for c in 0..3 {
        let base = (0.5 + C0 * dc[c]).clamp(0.02, 0.98);
        let row = &mut out[c * SH_COEFFS..(c + 1) * SH_COEFFS];
        row[0] = logit(base) / C0;
        let slope = (base * (1.0 - base)).max(MIN_SLOPE);
        for (j, r) in row[1..].iter_mut().enumerate() {
            *r = if j < k { rest[c * k + j] / slope } else { 0.0 };
        }
    }
}

/// Inverse of [`to_field_sh2`]: 27 SH2 channels to a splat's `dc` and
/// channel-major degree-2 `rest` (24 values).
pub fn from_field_sh2(sh: &[f32]) -> ([f32; 3], Vec<f32>) {
    let mut dc = [0.0; 3];
    let mut rest = vec![0.0; 24];
    for c in 0..3 {
        let row = &sh[c * SH_COEFFS..(c + 1) * SH_COEFFS];
        let base = 1.0 / (1.0 + (-C0 * row[0]).exp());
        dc[c] = (base - 0.5) / C0;
        let slope = (base * (1.0 - base)).max(MIN_SLOPE);
        for j in 0..8 {
            rest[c * 8 + j] = row[j + 1] * slope;
        }
    }
    (dc, rest)
}

/// A linear colour map `m` (e.g. an appearance edit) applied to a splat's
/// SH: colour(d) = 0.5 + Σ Y c becomes m·colour(d) exactly (before clamping).
pub fn apply_color_matrix(m: Mat3, dc: &mut [f32; 3], rest: &mut [f32]) {
    let base = Vec3::splat(0.5) + C0 * Vec3::from(*dc);
    *dc = ((m * base - Vec3::splat(0.5)) / C0).to_array();
    let k = rest.len() / 3;
    for j in 0..k {
        let v = m * Vec3::new(rest[j], rest[k + j], rest[2 * k + j]);
        rest[j] = v.x;
        rest[k + j] = v.y;
        rest[2 * k + j] = v.z;
    }
}

/// Per-band matrices that rotate SH coefficients: with `r` applied to the
/// scene, the rotated coefficients give at `r·d` the colour the old ones gave
/// at `d`. Fitted by least squares on 64 spread directions (exact for a
/// rotation: each band spans a rotation-invariant space).
pub struct ShRotation {
    /// Band l (1..=3): (2l+1)² values, row-major.
    bands: Vec<Vec<f32>>,
}

impl ShRotation {
    pub fn new(r: Mat3) -> ShRotation {
        let dirs = fibonacci(64);
        let inv = r.transpose();
        let bands = (1..=3)
            .map(|l: usize| {
                let (lo, n) = (l * l, 2 * l + 1);
                let b = DMatrix::from_fn(dirs.len(), n, |i, j| basis16(dirs[i])[lo + j] as f64);
                let br = DMatrix::from_fn(dirs.len(), n, |i, j| basis16(inv * dirs[i])[lo + j] as f64);
                // c' = (BᵀB)⁻¹ Bᵀ B_R c
                let bt = b.transpose();
                let m = (&bt * &b).try_inverse().map(|i| i * bt * br);
                let m = m.unwrap_or_else(|| DMatrix::identity(n, n));
                m.iter().map(|&v| v as f32).collect::<Vec<f32>>()
            })
            .collect::<Vec<_>>();
        // nalgebra is column-major: transpose into row-major per band.
        let bands = bands
            .into_iter()
            .enumerate()
            .map(|(i, cm)| {
                let n = 2 * (i + 1) + 1;
                (0..n * n).map(|k| cm[(k % n) * n + k / n]).collect()
            })
            .collect();
        ShRotation { bands }
    }

    /// Rotates channel-major `rest` (`3 × k` values) in place.
    pub fn apply(&self, rest: &mut [f32]) {
        let k = rest.len() / 3;
        let mut tmp = [0.0f32; 7];
        for c in 0..3 {
            let row = &mut rest[c * k..(c + 1) * k];
            for l in 1..=3usize {
                let (lo, n) = (l * l - 1, 2 * l + 1);
                if lo + n > k {
                    break;
                }
                let m = &self.bands[l - 1];
                for i in 0..n {
                    tmp[i] = (0..n).map(|j| m[i * n + j] * row[lo + j]).sum();
                }
                row[lo..lo + n].copy_from_slice(&tmp[..n]);
            }
        }
    }
}

/// `n` directions spread evenly over the sphere.
fn fibonacci(n: usize) -> Vec<Vec3> {
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..n)
        .map(|i| {
            let y = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let r = (1.0 - y * y).sqrt();
            let a = golden * i as f32;
            Vec3::new(r * a.cos(), y, r * a.sin())
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Quat;

    fn rest(k: usize) -> Vec<f32> {
        (0..3 * k).map(|i| ((i * 37 % 11) as f32 - 5.0) * 0.03).collect()
    }

    #[test]
    fn rotated_sh_gives_the_old_colour_at_the_rotated_direction() {
        let r = Mat3::from_quat(Quat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.0));
        let rot = ShRotation::new(r);
        let dc = [0.2, -0.1, 0.4];
        for k in [3, 8, 15] {
            let old = rest(k);
            let mut new = old.clone();
            rot.apply(&mut new);
            for d in fibonacci(20) {
                let a = splat_color(dc, &old, d);
                let b = splat_color(dc, &new, r * d);
                assert!((a - b).abs().max_element() < 1e-4, "k {k}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn field_sh2_conversion_keeps_colours() {
        let dc = [0.5, -0.8, 1.2];
        let old = rest(8).iter().map(|v| v * 0.2).collect::<Vec<_>>();
        let mut sh = [0.0; 27];
        to_field_sh2(dc, &old, &mut sh);
        for d in fibonacci(10) {
            let want = splat_color(dc, &old, d);
            let got = crate::field::sh::color(&sh, d);
            assert!((want - got).abs().max_element() < 0.02, "{want} vs {got}");
        }
        let (dc2, rest2) = from_field_sh2(&sh);
        for (a, b) in dc.iter().zip(dc2) {
            assert!((a - b).abs() < 1e-4);
        }
        for (a, b) in old.iter().zip(rest2) {
            assert!((a - b).abs() < 1e-5);
        }
    }

    #[test]
    fn colour_matrices_act_on_the_colour_exactly() {
        let m = Mat3::from_cols(
            Vec3::new(0.9, 0.1, 0.0),
            Vec3::new(0.0, 0.5, 0.2),
            Vec3::new(0.1, 0.0, 1.1),
        );
        let (mut dc, old) = ([0.3, -0.2, 0.1], rest(8));
        let mut new = old.clone();
        let dc0 = dc;
        apply_color_matrix(m, &mut dc, &mut new);
        for d in fibonacci(10) {
            let want = m * splat_color(dc0, &old, d);
            assert!((want - splat_color(dc, &new, d)).abs().max_element() < 1e-5);
        }
    }
}
