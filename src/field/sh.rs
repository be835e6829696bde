//! Real spherical harmonics up to degree 2 (9 coefficients), the basis used by
//! Plenoxels / 3D Gaussian splatting. Colour = sigmoid(Σ_k c_k Y_k(dir)).

use glam::Vec3;

pub const SH_COEFFS: usize = 9;
const C0: f32 = 0.282_094_8;
const C1: f32 = 0.488_602_5;
const C2: [f32; 5] = [1.092_548_4, -1.092_548_4, 0.315_391_57, -1.092_548_4, 0.546_274_2];

/// The 9 basis values for unit direction `d`.
#[inline]
pub fn basis(d: Vec3) -> [f32; SH_COEFFS] {
    let (x, y, z) = (d.x, d.y, d.z);
    [
        C0,
        -C1 * y,
        C1 * z,
        -C1 * x,
        C2[0] * x * y,
        C2[1] * y * z,
        C2[2] * (2.0 * z * z - x * x - y * y),
        C2[3] * x * z,
        C2[4] * (x * x - y * y),
    ]
}

/// Colour from 27 channels laid out `[r0..r8, g0..g8, b0..b8]`.
#[inline]
pub fn color(coeffs: &[f32], d: Vec3) -> Vec3 {
    let b = basis(d);
    let ch = |c: usize| {
        let s: f32 = coeffs[c * SH_COEFFS..(c + 1) * SH_COEFFS]
            .iter()
            .zip(&b)
            .map(|(a, b)| a * b)
            .sum();
        super::vm::sigmoid(s)
    };
    Vec3::new(ch(0), ch(1), ch(2))
}
