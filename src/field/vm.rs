//! TensoRF vector-matrix (VM) decomposition and the small MLP that decodes
//! appearance, as in the paper (appearance: VM + MLP with view direction;
//! features: VM-64 with a basis matrix, no MLP).
//!
//! Mode m pairs a plane with a line: m = 0 plane (x, y) × line z,
//! m = 1 plane (x, z) × line y, m = 2 plane (y, z) × line x. Plane m is stored
//! `[R_m, n_b, n_a]` (a fastest), line m `[R_m, n_c]`. The component vector is
//! the concatenation over modes of plane·line products (length Σ R_m); the
//! basis matrix `[Σ R_m, out]` maps it to the output channels.

use super::geom::GridGeom;
use glam::Vec3;

/// Axes (a, b) of the plane and c of the line for each mode.
pub const MODE_AXES: [(usize, usize, usize); 3] = [(0, 1, 2), (0, 2, 1), (1, 2, 0)];

#[derive(Clone, Debug)]
pub struct VmGrid {
    pub geom: GridGeom,
    pub comps: [usize; 3],
    pub planes: [Vec<f32>; 3],
    pub lines: [Vec<f32>; 3],
    /// Row-major `[Σ comps, out]`.
    pub basis: Vec<f32>,
    pub out: usize,
}

impl VmGrid {
    pub fn total_comps(&self) -> usize {
        self.comps.iter().sum()
    }
    pub fn plane_len(&self, m: usize) -> usize {
        let (a, b, _) = MODE_AXES[m];
        self.comps[m] * self.geom.res[a] * self.geom.res[b]
    }
    pub fn line_len(&self, m: usize) -> usize {
        let (_, _, c) = MODE_AXES[m];
        self.comps[m] * self.geom.res[c]
    }
    /// Component vector (len Σ comps) at world point `p`; false outside.
    pub fn components(&self, p: Vec3, out: &mut [f32]) -> bool {
        let g = self.geom.to_grid(p);
        let res = self.geom.res;
        let gc = [g.x, g.y, g.z];
        if (0..3).any(|a| !(gc[a] >= 0.0 && gc[a] <= (res[a] - 1) as f32)) {
            out.fill(0.0);
            return false;
        }
        // Per axis: base index and fraction.
        let lerp = |a: usize| {
            let i0 = (gc[a] as usize).min(res[a] - 2);
            (i0, gc[a] - i0 as f32)
        };
        let mut o = 0;
        for (m, &(a, b, c)) in MODE_AXES.iter().enumerate() {
            let (ia, fa) = lerp(a);
            let (ib, fb) = lerp(b);
            let (ic, fc) = lerp(c);
            let (na, nb, nc) = (res[a], res[b], res[c]);
            let plane = &self.planes[m];
            let line = &self.lines[m];
            for r in 0..self.comps[m] {
                let p0 = r * na * nb + ib * na + ia;
                let pv = plane[p0] * (1.0 - fa) * (1.0 - fb)
                    + plane[p0 + 1] * fa * (1.0 - fb)
                    + plane[p0 + na] * (1.0 - fa) * fb
                    + plane[p0 + na + 1] * fa * fb;
                let l0 = r * nc + ic;
                let lv = line[l0] * (1.0 - fc) + line[l0 + 1] * fc;
                out[o] = pv * lv;
                o += 1;
            }
        }
        true
    }
    /// Output channels at `p` (components times basis). `scratch` holds
    /// Σ comps floats so that callers can reuse it without allocating.
    pub fn sample(&self, p: Vec3, scratch: &mut [f32], out: &mut [f32]) -> bool {
        out.fill(0.0);
        let n = self.total_comps();
        if !self.components(p, &mut scratch[..n]) {
            return false;
        }
        for (r, &v) in scratch[..n].iter().enumerate() {
            if v == 0.0 {
                continue;
            }
            let row = &self.basis[r * self.out..(r + 1) * self.out];
            for (o, &b) in out.iter_mut().zip(row) {
                *o += v * b;
            }
        }
        true
    }
}

/// One fully connected layer, weights row-major `[out, in]`.
#[derive(Clone, Debug)]
pub struct Linear {
    pub inputs: usize,
    pub outputs: usize,
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
}

/// TensoRF's `MLPRender_Fea`: input = [feat, viewdir, PE(feat), PE(viewdir)],
/// ReLU between layers, sigmoid on the 3 outputs.
#[derive(Clone, Debug)]
pub struct Mlp {
    pub feat_pe: usize,
    pub view_pe: usize,
    pub layers: Vec<Linear>,
}

/// Positional encoding in TensoRF's order: all sines then all cosines, each
/// block `x_d * 2^f` with frequency fastest.
pub fn positional_encoding(x: &[f32], freqs: usize, out: &mut Vec<f32>) {
    for &v in x {
        for f in 0..freqs {
            out.push((v * (1u32 << f) as f32).sin());
        }
    }
    for &v in x {
        for f in 0..freqs {
            out.push((v * (1u32 << f) as f32).cos());
        }
    }
}

impl Mlp {
    pub fn input_len(&self, feat: usize) -> usize {
        feat + 3 + 2 * feat * self.feat_pe + 2 * 3 * self.view_pe
    }
    /// RGB in [0, 1]. `buf` is scratch space reused across calls.
    pub fn eval(&self, feat: &[f32], dir: Vec3, buf: &mut Vec<f32>) -> Vec3 {
        buf.clear();
        buf.extend_from_slice(feat);
        buf.extend_from_slice(&dir.to_array());
        positional_encoding(feat, self.feat_pe, buf);
        positional_encoding(&dir.to_array(), self.view_pe, buf);
        let mut cur_start = 0;
        let mut cur_len = buf.len();
        for (li, l) in self.layers.iter().enumerate() {
            let next_start = cur_start + cur_len;
            for o in 0..l.outputs {
                let w = &l.weight[o * l.inputs..(o + 1) * l.inputs];
                let mut acc = l.bias[o];
                for (a, b) in w.iter().zip(&buf[cur_start..cur_start + cur_len]) {
                    acc += a * b;
                }
                if li + 1 < self.layers.len() {
                    acc = acc.max(0.0);
                }
                buf.push(acc);
            }
            cur_start = next_start;
            cur_len = l.outputs;
        }
        let o = &buf[cur_start..cur_start + 3];
        Vec3::new(sigmoid(o[0]), sigmoid(o[1]), sigmoid(o[2]))
    }
}

#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}
