//! Deterministic randomness and surface colours for the procedural scenes.
//!
//! Everything random comes from [`Rng`] (SplitMix64) or [`hash`], seeded by
//! the scene seed, so a scene is a pure function of (name, resolution, seed).

use glam::Vec3;
use std::f32::consts::TAU;

/// SplitMix64: tiny, fast, good enough for procedural content.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed ^ 0x5EED_15A5_D3E0_0001)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix64(self.0)
    }
    /// Uniform in [0, 1).
    pub fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f32()
    }
    /// Standard normal (Box–Muller).
    pub fn gauss(&mut self) -> f32 {
        let u = self.f32().max(1e-7);
        let v = self.f32();
        (-2.0 * u.ln()).sqrt() * (TAU * v).cos()
    }
    pub fn unit3(&mut self) -> Vec3 {
        loop {
            let v = Vec3::new(self.gauss(), self.gauss(), self.gauss());
            if v.length_squared() > 1e-6 {
                return v.normalize();
            }
        }
    }
}

fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A uniform value in [0, 1) from three integers (per-board colours etc.).
pub fn hash(seed: u64, a: i64, b: i64) -> f32 {
    let h = mix64(seed ^ mix64((a as u64).wrapping_mul(0x9E37_79B9) ^ mix64(b as u64 ^ 0xABCD)));
    (h >> 40) as f32 / (1u64 << 24) as f32
}

/// Smooth noise: a sum of a few random plane waves, unit variance, with
/// wavelengths between 2π/`fmax` and 2π/`fmin` world units.
#[derive(Clone, Debug)]
pub struct Waves {
    /// (angular frequency vector, phase)
    waves: Vec<(Vec3, f32)>,
    amp: f32,
}

impl Waves {
    pub fn new(rng: &mut Rng, n: usize, fmin: f32, fmax: f32) -> Self {
        let waves = (0..n)
            .map(|_| (rng.unit3() * rng.range(fmin, fmax), rng.range(0.0, TAU)))
            .collect();
        Waves {
            waves,
            amp: (2.0 / n.max(1) as f32).sqrt(),
        }
    }
    #[inline]
    pub fn eval(&self, p: Vec3) -> f32 {
        self.amp * self.waves.iter().map(|(w, ph)| (w.dot(p) + ph).sin()).sum::<f32>()
    }
}

/// Noise shared by every material of a scene.
#[derive(Clone, Debug)]
pub struct Texture {
    pub seed: u64,
    /// Low-frequency brightness variation.
    pub low: Waves,
    /// Medium frequency, used to warp wood grain.
    pub mid: Waves,
}

impl Texture {
    pub fn new(seed: u64) -> Self {
        let mut rng = Rng::new(seed ^ 0x7E47);
        Texture {
            seed,
            low: Waves::new(&mut rng, 5, 2.0, 7.0),
            mid: Waves::new(&mut rng, 5, 10.0, 25.0),
        }
    }
}

/// How a surface is coloured; evaluated at grid points (world coordinates).
#[derive(Clone, Debug)]
pub enum Material {
    /// A colour with smooth brightness variation of relative size `var`.
    Flat { rgb: Vec3, var: f32 },
    /// Floor boards running along x, `width` wide (z) and `length` long, with
    /// per-board tone, grain and darker joints.
    Planks { rgb: Vec3, width: f32, length: f32 },
    /// Wood with fine grain running along x.
    Wood { rgb: Vec3 },
    /// Flower pot: clay, with soil on the recessed top disc.
    Pot {
        clay: Vec3,
        soil: Vec3,
        centre: Vec3,
        soil_y: f32,
        soil_radius: f32,
    },
    /// Rubber tracks: dark, with lighter treads every `period` along x.
    Treads { rgb: Vec3, period: f32 },
    /// A cab: body colour with a dark window band between heights y0 and y1.
    Cab { rgb: Vec3, window: Vec3, y0: f32, y1: f32 },
}

fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

impl Material {
    pub fn color(&self, p: Vec3, tex: &Texture) -> Vec3 {
        let c = match self {
            Material::Flat { rgb, var } => *rgb * (1.0 + var * tex.low.eval(p)),
            Material::Planks { rgb, width, length } => planks(p, *rgb, *width, *length, tex),
            Material::Wood { rgb } => {
                let grain = (p.z * 90.0 + 2.5 * tex.mid.eval(p * Vec3::new(0.3, 1.0, 1.0))).sin();
                *rgb * (1.0 + 0.06 * grain + 0.05 * tex.low.eval(p))
            }
            Material::Pot {
                clay,
                soil,
                centre,
                soil_y,
                soil_radius,
            } => {
                let r = (p - *centre).truncate_y();
                if (p.y - soil_y).abs() < 0.015 && r < *soil_radius {
                    *soil * (1.0 + 0.25 * tex.mid.eval(p * 3.0))
                } else {
                    *clay * (1.0 + 0.05 * tex.low.eval(p * 3.0))
                }
            }
            Material::Treads { rgb, period } => {
                let s = (p.x / period).rem_euclid(1.0);
                *rgb * (1.0 + 1.2 * smoothstep(0.55, 0.7, s) * (1.0 - smoothstep(0.85, 1.0, s)))
            }
            Material::Cab { rgb, window, y0, y1 } => {
                if p.y > *y0 && p.y < *y1 {
                    *window
                } else {
                    *rgb
                }
            }
        };
        c.clamp(Vec3::ZERO, Vec3::ONE)
    }
}

/// Distance in the xz plane from the y axis through the origin.
trait TruncateY {
    fn truncate_y(self) -> f32;
}
impl TruncateY for Vec3 {
    fn truncate_y(self) -> f32 {
        (self.x * self.x + self.z * self.z).sqrt()
    }
}

fn planks(p: Vec3, rgb: Vec3, width: f32, length: f32, tex: &Texture) -> Vec3 {
    let row = (p.z / width).floor();
    // Stagger the board ends from row to row.
    let shift = hash(tex.seed, row as i64, 17) * length;
    let along = p.x + shift;
    let board = (along / length).floor();
    let tone = 0.78 + 0.4 * hash(tex.seed, row as i64, board as i64);
    let grain = (p.z * 140.0 + 3.0 * tex.mid.eval(p * Vec3::new(0.25, 1.0, 1.0))).sin();
    // Distance to the nearest joint, in world units.
    let fz = (p.z / width).rem_euclid(1.0) * width;
    let fx = (along / length).rem_euclid(1.0) * length;
    let edge = fz.min(width - fz).min(fx).min(length - fx);
    let joint = 1.0 - 0.5 * (1.0 - smoothstep(0.0, 0.012, edge));
    rgb * tone * (1.0 + 0.07 * grain + 0.04 * tex.low.eval(p)) * joint
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rng_is_deterministic_and_uniformish() {
        let a: Vec<u64> = {
            let mut r = Rng::new(3);
            (0..4).map(|_| r.next_u64()).collect()
        };
        let mut r = Rng::new(3);
        assert_eq!(a, (0..4).map(|_| r.next_u64()).collect::<Vec<_>>());
        let mut r = Rng::new(4);
        let mean = (0..10_000).map(|_| r.f32()).sum::<f32>() / 10_000.0;
        assert!((mean - 0.5).abs() < 0.02, "{mean}");
        let var = (0..10_000).map(|_| r.gauss().powi(2)).sum::<f32>() / 10_000.0;
        assert!((var - 1.0).abs() < 0.1, "{var}");
    }

    #[test]
    fn waves_have_unit_variance() {
        let w = Waves::new(&mut Rng::new(9), 4, 3.0, 8.0);
        let mut r = Rng::new(10);
        let n = 20_000;
        let var = (0..n)
            .map(|_| {
                w.eval(Vec3::new(
                    r.range(-20.0, 20.0),
                    r.range(-20.0, 20.0),
                    r.range(-20.0, 20.0),
                ))
                .powi(2)
            })
            .sum::<f32>()
            / n as f32;
        assert!((var - 1.0).abs() < 0.1, "{var}");
    }
}
