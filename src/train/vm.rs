//! Trainable VM + MLP appearance (TensoRF, the paper's appearance model):
//! per mode m a plane × line product of `rank` components, a basis matrix
//! to `out` channels, and an MLP on [channels, view dir, PE(view dir)] with
//! one ReLU hidden layer and a sigmoid on RGB.
//!
//! The parameters live in two flat arrays so that Adam sees plain data:
//! `grid` = planes then lines in [`crate::field::VmGrid`]'s layout (plane m
//! `[R, n_b, n_a]`, line m `[R, n_c]`), `net` = basis `[3R, out]`, W1
//! `[H, in]`, b1, W2 `[3, H]`, b2. [`VmAppearance::to_field`] hands them to
//! the renderer's [`crate::field::Appearance::Vm`], which evaluates the same
//! function (a test checks it), so a VM-trained field renders as it trained.
//!
//! The grid is always on the density grid's geometry (it is resampled with
//! it at every stage). No positional encoding of the channels (TensoRF uses
//! 6 frequencies): on two CPU cores the MLP dominates the cost, and without
//! it the basis matrix and first layer stay small.

use crate::field::vm::{positional_encoding, Linear, Mlp, VmGrid, MODE_AXES};
use crate::field::{Appearance, GridGeom};
use crate::util::SplitMix64;
use crate::Result;
use glam::Vec3;
use serde::{Deserialize, Serialize};

/// Sizes of a VM appearance (saved in checkpoints).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct VmShape {
    /// Components per mode.
    pub rank: usize,
    /// Channels the basis matrix maps the 3·rank components to.
    pub out: usize,
    pub hidden: usize,
    /// Frequencies of the view-direction encoding.
    pub view_pe: usize,
}

impl VmShape {
    pub fn validate(&self) -> Result<()> {
        crate::ensure!(
            (1..=128).contains(&self.rank)
                && (1..=256).contains(&self.out)
                && (1..=512).contains(&self.hidden)
                && self.view_pe <= 8,
            "VM appearance sizes out of range: {self:?} (rank 1..128, out 1..256, hidden 1..512, view_pe 0..8)"
        );
        Ok(())
    }
    pub fn comps(&self) -> usize {
        3 * self.rank
    }
    /// MLP input length: channels, direction, PE(direction).
    pub fn inputs(&self) -> usize {
        self.out + 3 + 6 * self.view_pe
    }
    fn net_offsets(&self) -> NetOffsets {
        let basis = 0;
        let w1 = basis + self.comps() * self.out;
        let b1 = w1 + self.hidden * self.inputs();
        let w2 = b1 + self.hidden;
        let b2 = w2 + 3 * self.hidden;
        NetOffsets {
            w1,
            b1,
            w2,
            b2,
            len: b2 + 3,
        }
    }
    /// Floats one shaded sample keeps for the backward pass: components,
    /// MLP input (its first `out` values are the channels), hidden
    /// activations.
    pub fn row_len(&self) -> usize {
        self.comps() + self.inputs() + self.hidden
    }
    /// Length of the plane + line array on a grid of `res`.
    pub fn grid_len(&self, res: [usize; 3]) -> usize {
        grid_offsets(self, res).2
    }
    /// Length of the basis + MLP array.
    pub fn net_len(&self) -> usize {
        self.net_offsets().len
    }
}

/// Where one mode's interpolation reads (see [`VmAppearance::mode_taps`]).
struct ModeTaps {
    plane: [usize; 4],
    plane_w: [f32; 4],
    plane_stride: usize,
    line: usize,
    line_w: [f32; 2],
    line_stride: usize,
}

#[derive(Clone, Copy)]
struct NetOffsets {
    w1: usize,
    b1: usize,
    w2: usize,
    b2: usize,
    len: usize,
}

/// Where plane and line m start in `grid`.
fn grid_offsets(shape: &VmShape, res: [usize; 3]) -> ([usize; 3], [usize; 3], usize) {
    let mut o = 0;
    let mut planes = [0; 3];
    for (m, &(a, b, _)) in MODE_AXES.iter().enumerate() {
        planes[m] = o;
        o += shape.rank * res[a] * res[b];
    }
    let mut lines = [0; 3];
    for (m, &(_, _, c)) in MODE_AXES.iter().enumerate() {
        lines[m] = o;
        o += shape.rank * res[c];
    }
    (planes, lines, o)
}

#[derive(Clone, Debug)]
pub struct VmAppearance {
    pub shape: VmShape,
    pub res: [usize; 3],
    pub grid: Vec<f32>,
    pub net: Vec<f32>,
}

/// Linear-interpolation taps along one axis of continuous grid coordinate
/// `g` (clamped into the grid).
#[inline]
fn taps(g: f32, n: usize) -> (usize, f32) {
    let g = g.clamp(0.0, (n - 1) as f32);
    let i0 = (g as usize).min(n - 2);
    (i0, g - i0 as f32)
}

/// Σ a·b with independent lanes, so that it vectorises.
#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    let tail: f32 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
    acc.iter().sum::<f32>() + tail
}

#[inline]
fn axpy(y: &mut [f32], a: f32, x: &[f32]) {
    for (o, v) in y.iter_mut().zip(x) {
        *o += a * v;
    }
}

impl VmAppearance {
    /// Random initial parameters (TensoRF's: components 0.1·N(0,1)-like,
    /// layers uniform ±1/√fan-in, last bias 0) on a grid of `res`.
    pub fn new(shape: VmShape, res: [usize; 3], seed: u64) -> Result<VmAppearance> {
        shape.validate()?;
        crate::field::geom::check_res(res, "VM appearance grid")?;
        let mut rng = SplitMix64::new(seed ^ 0x005E_ED0F_7E45);
        let mut u = move || 2.0 * rng.unit() as f32 - 1.0;
        let glen = shape.grid_len(res);
        // Uniform with the variance of 0.1·N(0, 1).
        let grid = (0..glen).map(|_| 0.1 * 3f32.sqrt() * u()).collect();
        let o = shape.net_offsets();
        let mut net = vec![0.0; o.len];
        let fill = |v: &mut [f32], fan_in: usize, u: &mut dyn FnMut() -> f32| {
            let s = 1.0 / (fan_in as f32).sqrt();
            v.iter_mut().for_each(|x| *x = s * u());
        };
        fill(&mut net[..o.w1], shape.comps(), &mut u);
        fill(&mut net[o.w1..o.w2], shape.inputs(), &mut u);
        fill(&mut net[o.w2..o.b2], shape.hidden, &mut u);
        Ok(VmAppearance { shape, res, grid, net })
    }

    pub fn from_parts(shape: VmShape, res: [usize; 3], grid: Vec<f32>, net: Vec<f32>) -> Result<VmAppearance> {
        shape.validate()?;
        crate::field::geom::check_res(res, "VM appearance grid")?;
        crate::ensure!(
            grid.len() == shape.grid_len(res) && net.len() == shape.net_len(),
            "VM appearance arrays do not match {shape:?} at {res:?}"
        );
        Ok(VmAppearance { shape, res, grid, net })
    }

    /// The per-ray direction part of the MLP input: [dir, PE(dir)].
    pub fn encode_dir(&self, dir: Vec3, out: &mut Vec<f32>) {
        out.clear();
        out.extend_from_slice(&dir.to_array());
        positional_encoding(&dir.to_array(), self.shape.view_pe, out);
    }

    /// Colour at continuous grid coordinates `g` (of the density grid)
    /// seen with encoded direction `dir_enc`; fills `row` (len
    /// [`VmShape::row_len`]) for [`Self::backward`].
    pub fn shade(&self, g: Vec3, dir_enc: &[f32], row: &mut [f32]) -> [f32; 3] {
        let sh = &self.shape;
        let (nc, no, ni, nh) = (sh.comps(), sh.out, sh.inputs(), sh.hidden);
        let (comps, rest) = row.split_at_mut(nc);
        let (x, hid) = rest.split_at_mut(ni);
        self.components(g, comps);
        let o = sh.net_offsets();
        // x = [channels = basisᵀ·components, encoded direction].
        let (chan, dir) = x.split_at_mut(no);
        chan.fill(0.0);
        for (r, &c) in comps.iter().enumerate() {
            axpy(chan, c, &self.net[r * no..(r + 1) * no]);
        }
        dir.copy_from_slice(dir_enc);
        for (j, h) in hid.iter_mut().enumerate().take(nh) {
            let w = &self.net[o.w1 + j * ni..o.w1 + (j + 1) * ni];
            *h = (self.net[o.b1 + j] + dot(w, x)).max(0.0);
        }
        let mut rgb = [0.0; 3];
        for (c, v) in rgb.iter_mut().enumerate() {
            let w = &self.net[o.w2 + c * nh..o.w2 + (c + 1) * nh];
            *v = crate::field::vm::sigmoid(self.net[o.b2 + c] + dot(w, hid));
        }
        rgb
    }

    /// Interpolation taps of mode `m` at grid coordinates `g`, for
    /// component 0 (component k adds k·`plane_stride` / k·`line_stride`).
    fn mode_taps(&self, g: Vec3, m: usize) -> ModeTaps {
        let (po, lo, _) = grid_offsets(&self.shape, self.res);
        let (a, b, c) = MODE_AXES[m];
        let (na, nb, nc) = (self.res[a], self.res[b], self.res[c]);
        let (ia, fa) = taps(g[a], na);
        let (ib, fb) = taps(g[b], nb);
        let (ic, fc) = taps(g[c], nc);
        let p0 = po[m] + ib * na + ia;
        ModeTaps {
            plane: [p0, p0 + 1, p0 + na, p0 + na + 1],
            plane_w: [(1.0 - fa) * (1.0 - fb), fa * (1.0 - fb), (1.0 - fa) * fb, fa * fb],
            plane_stride: na * nb,
            line: lo[m] + ic,
            line_w: [1.0 - fc, fc],
            line_stride: nc,
        }
    }

    /// Plane and line values of component `k` at `t`.
    #[inline]
    fn plane_line(&self, t: &ModeTaps, k: usize) -> (f32, f32) {
        let (p, po, lo) = (&self.grid, k * t.plane_stride, t.line + k * t.line_stride);
        let pv = (0..4).map(|i| p[t.plane[i] + po] * t.plane_w[i]).sum();
        (pv, p[lo] * t.line_w[0] + p[lo + 1] * t.line_w[1])
    }

    /// Plane·line products at grid coordinates `g`.
    fn components(&self, g: Vec3, out: &mut [f32]) {
        let r = self.shape.rank;
        for m in 0..3 {
            let t = self.mode_taps(g, m);
            for (k, o) in out[m * r..(m + 1) * r].iter_mut().enumerate() {
                let (pv, lv) = self.plane_line(&t, k);
                *o = pv * lv;
            }
        }
    }

    /// Accumulates the gradients of a shaded sample, given dL/dz (the
    /// pre-sigmoid RGB), into `dgrid` / `dnet`. `tmp` is scratch.
    pub fn backward(
        &self,
        g: Vec3,
        row: &[f32],
        dz: [f32; 3],
        dgrid: &mut [f32],
        dnet: &mut [f32],
        tmp: &mut Vec<f32>,
    ) {
        let sh = &self.shape;
        let (nc, no, ni, nh) = (sh.comps(), sh.out, sh.inputs(), sh.hidden);
        let o = sh.net_offsets();
        let comps = &row[..nc];
        let x = &row[nc..nc + ni];
        let hid = &row[nc + ni..nc + ni + nh];
        tmp.clear();
        tmp.resize(nh + no + nc, 0.0);
        let (dh, rest) = tmp.split_at_mut(nh);
        let (dchan, dcomp) = rest.split_at_mut(no);
        for c in 0..3 {
            dnet[o.b2 + c] += dz[c];
            axpy(&mut dnet[o.w2 + c * nh..o.w2 + (c + 1) * nh], dz[c], hid);
            axpy(dh, dz[c], &self.net[o.w2 + c * nh..o.w2 + (c + 1) * nh]);
        }
        for (j, d) in dh.iter_mut().enumerate() {
            if hid[j] <= 0.0 || *d == 0.0 {
                *d = 0.0;
                continue;
            }
            dnet[o.b1 + j] += *d;
            axpy(&mut dnet[o.w1 + j * ni..o.w1 + (j + 1) * ni], *d, x);
            axpy(dchan, *d, &self.net[o.w1 + j * ni..o.w1 + j * ni + no]);
        }
        for (r, &c) in comps.iter().enumerate() {
            axpy(&mut dnet[r * no..(r + 1) * no], c, dchan);
            dcomp[r] = dot(&self.net[r * no..(r + 1) * no], dchan);
        }
        self.components_backward(g, dcomp, dgrid);
    }

    /// Scatters dL/d(component) into plane and line gradients.
    fn components_backward(&self, g: Vec3, dcomp: &[f32], dgrid: &mut [f32]) {
        let r = self.shape.rank;
        for m in 0..3 {
            let t = self.mode_taps(g, m);
            for k in 0..r {
                let d = dcomp[m * r + k];
                if d == 0.0 {
                    continue;
                }
                let (pv, lv) = self.plane_line(&t, k);
                for i in 0..4 {
                    dgrid[t.plane[i] + k * t.plane_stride] += d * lv * t.plane_w[i];
                }
                let l0 = t.line + k * t.line_stride;
                dgrid[l0] += d * pv * t.line_w[0];
                dgrid[l0 + 1] += d * pv * t.line_w[1];
            }
        }
    }

    /// The same appearance moved from the density grid `old` to `new` (the
    /// trainer's upsampling and box shrinking): planes bilinear and lines
    /// linear, positions mapped through world space and clamped.
    pub fn resampled(&self, old: &GridGeom, new: &GridGeom) -> VmAppearance {
        let res = new.res;
        let sh = self.shape;
        let (po, lo, _) = grid_offsets(&sh, self.res);
        let (npo, nlo, len) = grid_offsets(&sh, res);
        let mut grid = vec![0.0; len];
        // Old continuous coordinate along axis a of new index i.
        let map = |a: usize, i: usize| {
            let w = new.bounds.min[a] + new.spacing()[a] * i as f32;
            (w - old.bounds.min[a]) / old.spacing()[a]
        };
        let src = &self.grid;
        for (m, &(a, b, c)) in MODE_AXES.iter().enumerate() {
            let (na, nb, nc) = (self.res[a], self.res[b], self.res[c]);
            let (ma, mb, mc) = (res[a], res[b], res[c]);
            for k in 0..sh.rank {
                for jb in 0..mb {
                    let (ib, fb) = taps(map(b, jb), nb);
                    for ja in 0..ma {
                        let (ia, fa) = taps(map(a, ja), na);
                        let p0 = po[m] + k * na * nb + ib * na + ia;
                        grid[npo[m] + k * ma * mb + jb * ma + ja] = src[p0] * (1.0 - fa) * (1.0 - fb)
                            + src[p0 + 1] * fa * (1.0 - fb)
                            + src[p0 + na] * (1.0 - fa) * fb
                            + src[p0 + na + 1] * fa * fb;
                    }
                }
                for jc in 0..mc {
                    let (ic, fc) = taps(map(c, jc), nc);
                    let l0 = lo[m] + k * nc + ic;
                    grid[nlo[m] + k * mc + jc] = src[l0] * (1.0 - fc) + src[l0 + 1] * fc;
                }
            }
        }
        VmAppearance {
            shape: sh,
            res,
            grid,
            net: self.net.clone(),
        }
    }

    /// The renderer's appearance for a density grid of `geom`.
    pub fn to_field(&self, geom: GridGeom) -> Appearance {
        let sh = &self.shape;
        let (po, lo, glen) = grid_offsets(sh, self.res);
        let planes = [0, 1, 2].map(|m| self.grid[po[m]..if m < 2 { po[m + 1] } else { lo[0] }].to_vec());
        let lines = [0, 1, 2].map(|m| self.grid[lo[m]..if m < 2 { lo[m + 1] } else { glen }].to_vec());
        let o = sh.net_offsets();
        let layer = |w: usize, b: usize, inputs: usize, outputs: usize| Linear {
            inputs,
            outputs,
            weight: self.net[w..w + inputs * outputs].to_vec(),
            bias: self.net[b..b + outputs].to_vec(),
        };
        Appearance::Vm {
            grid: VmGrid {
                geom: GridGeom::new(geom.bounds, self.res),
                comps: [sh.rank; 3],
                planes,
                lines,
                basis: self.net[..o.w1].to_vec(),
                out: sh.out,
            },
            mlp: Mlp {
                feat_pe: 0,
                view_pe: sh.view_pe,
                layers: vec![
                    layer(o.w1, o.b1, sh.inputs(), sh.hidden),
                    layer(o.w2, o.b2, sh.hidden, 3),
                ],
            },
        }
    }
}
