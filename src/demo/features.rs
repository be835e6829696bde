//! Synthetic semantic features that behave like distilled DINO features, as
//! the segmentation algorithm expects them (DESIGN.md, "Segmentation").
//!
//! - NNFM compares *unit* features with squared distance θ = 0.4, i.e. a match
//!   is cosine > 0.8. So every object kind has a base direction, its parts are
//!   at cosine [`PART_COS`] from it (and ≈ PART_COS² from each other), and
//!   different kinds are at cosine ≤ 0.5 (related kinds somewhat similar).
//! - Bilateral growth uses *raw* features with weight exp(−‖Δφ‖²/10), so the
//!   raw norm matters: norms are 6.5–7.5, which puts other objects at squared
//!   distances ≳ 45 (weight ≈ 0.01) and points of one part, including the
//!   spatial noise, within ≈ 1.5 of each other.
//!
//! The vocabulary (kind and part directions) is fixed, independent of the
//! scene seed, so that objects keep their meaning when scenes are composed;
//! the seed only drives the smooth spatial noise.

use super::texture::{Rng, Waves};
use crate::error::Result;
use glam::Vec3;

pub const CHANNELS: usize = 32;

/// Cosine between a part direction and its kind's base direction.
pub const PART_COS: f32 = 0.92;

/// Number of smooth noise fields mixed into the 32 channels.
const NOISE_FIELDS: usize = 8;
/// Expected norm of the noise vector added to every feature.
const NOISE_NORM: f32 = 0.8;

/// The kinds of objects in the demo scenes, with one feature direction each.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Floor,
    Wall,
    Table,
    Pot,
    Mug,
    Ball,
    Box,
    Shelf,
    Excavator,
    Books,
    Jar,
}

pub const KINDS: [Kind; 11] = [
    Kind::Floor,
    Kind::Wall,
    Kind::Table,
    Kind::Pot,
    Kind::Mug,
    Kind::Ball,
    Kind::Box,
    Kind::Shelf,
    Kind::Excavator,
    Kind::Books,
    Kind::Jar,
];

impl Kind {
    fn index(self) -> usize {
        KINDS.iter().position(|&k| k == self).unwrap_or(0)
    }
    /// Parts beyond the base part that have their own direction.
    pub fn extra_parts(self) -> usize {
        match self {
            Kind::Table | Kind::Pot | Kind::Mug | Kind::Shelf | Kind::Jar => 1,
            Kind::Excavator | Kind::Books => 3,
            _ => 0,
        }
    }
    /// Raw feature norm (objects differ a little, as real features do).
    pub fn norm(self) -> f32 {
        6.5 + 0.1 * ((self.index() * 7) % 11) as f32
    }
}

/// Target cosine between the base directions of two different kinds.
pub fn kind_cos(a: Kind, b: Kind) -> f32 {
    use Kind::*;
    let pair = |x: Kind, y: Kind| (a == x && b == y) || (a == y && b == x);
    if a == b {
        1.0
    } else if pair(Floor, Wall) || pair(Pot, Mug) {
        0.5
    } else if pair(Table, Shelf) || pair(Mug, Jar) {
        0.45
    } else if pair(Floor, Table) {
        0.4
    } else if pair(Pot, Jar) {
        0.35
    } else if pair(Ball, Box) || pair(Excavator, Box) || pair(Excavator, Ball) || pair(Books, Shelf) {
        0.3
    } else if pair(Floor, Shelf) || pair(Wall, Table) || pair(Wall, Shelf) {
        0.25
    } else {
        0.15
    }
}

/// Unit feature directions of every kind and part.
#[derive(Clone, Debug)]
pub struct Vocabulary {
    base: Vec<[f32; CHANNELS]>,
    /// Extra part directions of each kind, in kind order.
    parts: Vec<Vec<[f32; CHANNELS]>>,
}

impl Vocabulary {
    /// Kind directions with exactly the cosines of [`kind_cos`] (Cholesky
    /// factor of the target Gram matrix in a random orthonormal basis), and
    /// part directions mixing the base with basis vectors no kind uses.
    pub fn new() -> Result<Self> {
        let basis = orthonormal_basis(&mut Rng::new(0x15F_D1E0));
        let n = KINDS.len();
        let gram: Vec<f64> = (0..n * n)
            .map(|i| kind_cos(KINDS[i / n], KINDS[i % n]) as f64)
            .collect();
        let l = cholesky(&gram, n).ok_or_else(|| {
            crate::error::Error::invalid("demo feature vocabulary: Gram matrix is not positive definite")
        })?;
        let combine = |coef: &[(usize, f32)]| {
            let mut v = [0.0f32; CHANNELS];
            for &(j, c) in coef {
                for (o, b) in v.iter_mut().zip(&basis[j]) {
                    *o += c * b;
                }
            }
            v
        };
        let base: Vec<_> = (0..n)
            .map(|k| combine(&(0..=k).map(|j| (j, l[k * n + j] as f32)).collect::<Vec<_>>()))
            .collect();
        let side = (1.0 - PART_COS * PART_COS).sqrt();
        let mut slot = n;
        let mut parts = vec![];
        for (k, kind) in KINDS.iter().enumerate() {
            let mut ps = vec![];
            for _ in 0..kind.extra_parts() {
                crate::ensure!(
                    slot < CHANNELS,
                    "demo feature vocabulary needs more than {CHANNELS} channels"
                );
                let mut v = [0.0f32; CHANNELS];
                for c in 0..CHANNELS {
                    v[c] = PART_COS * base[k][c] + side * basis[slot][c];
                }
                ps.push(v);
                slot += 1;
            }
            parts.push(ps);
        }
        Ok(Vocabulary { base, parts })
    }
    /// Unit direction of part `part` of `kind` (part 0 is the base); parts
    /// past the kind's own directions reuse the last one.
    pub fn part(&self, kind: Kind, part: usize) -> &[f32; CHANNELS] {
        let k = kind.index();
        match part {
            0 => &self.base[k],
            p => self.parts[k]
                .get(p - 1)
                .or(self.parts[k].last())
                .unwrap_or(&self.base[k]),
        }
    }
}

fn orthonormal_basis(rng: &mut Rng) -> Vec<[f32; CHANNELS]> {
    let mut out: Vec<[f64; CHANNELS]> = vec![];
    while out.len() < CHANNELS {
        let mut v = [0.0f64; CHANNELS];
        v.iter_mut().for_each(|x| *x = rng.gauss() as f64);
        for u in &out {
            let d: f64 = v.iter().zip(u).map(|(a, b)| a * b).sum();
            v.iter_mut().zip(u).for_each(|(a, b)| *a -= d * b);
        }
        let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if n > 1e-3 {
            v.iter_mut().for_each(|x| *x /= n);
            out.push(v);
        }
    }
    out.iter().map(|v| v.map(|x| x as f32)).collect()
}

/// Lower-triangular L with L Lᵀ = A (row-major n×n), or None if A is not
/// positive definite.
fn cholesky(a: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let s: f64 = (0..j).map(|k| l[i * n + k] * l[j * n + k]).sum();
            if i == j {
                let d = a[i * n + i] - s;
                if d <= 1e-9 {
                    return None;
                }
                l[i * n + i] = d.sqrt();
            } else {
                l[i * n + j] = (a[i * n + j] - s) / l[j * n + j];
            }
        }
    }
    Some(l)
}

/// Smooth, low-rank spatial noise added to every feature (seeded): a few
/// smooth scalar fields mixed into the channels by a random matrix, so
/// features drift slowly across a surface instead of being piecewise constant.
#[derive(Clone, Debug)]
pub struct FeatureNoise {
    fields: Vec<Waves>,
    /// `CHANNELS × NOISE_FIELDS`, row-major.
    mix: Vec<f32>,
}

impl FeatureNoise {
    pub fn new(seed: u64) -> Self {
        let mut rng = Rng::new(seed ^ 0xFEA7);
        let fields = (0..NOISE_FIELDS).map(|_| Waves::new(&mut rng, 3, 2.0, 6.0)).collect();
        // Each field has unit variance, so E‖noise‖² = CHANNELS·NOISE_FIELDS·s².
        let s = NOISE_NORM / ((CHANNELS * NOISE_FIELDS) as f32).sqrt();
        let mix = (0..CHANNELS * NOISE_FIELDS).map(|_| s * rng.gauss()).collect();
        FeatureNoise { fields, mix }
    }
    /// Adds the noise at `p` to `out`.
    pub fn add(&self, p: Vec3, out: &mut [f32]) {
        let mut n = [0.0f32; NOISE_FIELDS];
        for (v, f) in n.iter_mut().zip(&self.fields) {
            *v = f.eval(p);
        }
        for (o, row) in out.iter_mut().zip(self.mix.chunks_exact(NOISE_FIELDS)) {
            *o += row.iter().zip(&n).map(|(a, b)| a * b).sum::<f32>();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dot(a: &[f32], b: &[f32]) -> f32 {
        a.iter().zip(b).map(|(x, y)| x * y).sum()
    }

    #[test]
    fn vocabulary_has_the_designed_cosines() {
        let v = Vocabulary::new().unwrap();
        for &a in &KINDS {
            assert!((dot(v.part(a, 0), v.part(a, 0)) - 1.0).abs() < 1e-4);
            for &b in &KINDS {
                let c = dot(v.part(a, 0), v.part(b, 0));
                assert!((c - kind_cos(a, b)).abs() < 1e-4, "{a:?} {b:?}: {c}");
                assert!(a == b || c <= 0.5 + 1e-4);
            }
            for p in 1..=a.extra_parts() {
                let d = v.part(a, p);
                assert!((dot(d, d) - 1.0).abs() < 1e-4);
                assert!((dot(d, v.part(a, 0)) - PART_COS).abs() < 1e-4);
                for q in 1..p {
                    assert!((dot(d, v.part(a, q)) - PART_COS * PART_COS).abs() < 1e-4);
                }
            }
        }
        // A part of one kind is no closer to another kind than its base is.
        let c = dot(v.part(Kind::Pot, 1), v.part(Kind::Mug, 0));
        assert!((c - PART_COS * 0.5).abs() < 1e-4, "{c}");
    }

    #[test]
    fn noise_is_smooth_and_small() {
        let n = FeatureNoise::new(5);
        let mut rng = Rng::new(1);
        let (mut sq, mut step) = (0.0, 0.0f32);
        let count = 2000;
        for _ in 0..count {
            let p = Vec3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0));
            let (mut a, mut b) = ([0.0; CHANNELS], [0.0; CHANNELS]);
            n.add(p, &mut a);
            n.add(p + Vec3::splat(0.01), &mut b);
            sq += dot(&a, &a);
            step = step.max(a.iter().zip(&b).map(|(x, y)| (x - y).powi(2)).sum::<f32>());
        }
        let rms = (sq / count as f32).sqrt();
        assert!(rms > 0.4 && rms < 1.2, "noise norm {rms}");
        assert!(step < 0.01, "noise changes too fast between neighbours: {step}");
    }
}
