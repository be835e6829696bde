//! Hand-written forward and backward passes of volume rendering for one ray,
//! the same function the CPU reference renderer computes
//! ([`crate::render`]): samples at tᵢ = (i + ½)δ along a unit ray inside the
//! field's box, σᵢ = softplus(trilinear(raw) + shift), αᵢ = 1 − exp(−σᵢδ),
//! Tᵢ = Πⱼ<ᵢ(1 − αⱼ), wᵢ = Tᵢαᵢ, C = Σ wᵢcᵢ + T·background,
//! cᵢ = sigmoid(Σₖ SHₖ(dir)·trilinear(coeffs)), features Φ = Σ wᵢφᵢ.
//!
//! Backward (dL/dC = g, dL/dΦ = h), with "after" sums Aᵢ = Σⱼ>ᵢ wⱼcⱼ + T·bg:
//!   dL/dcᵢ = wᵢ g,   dL/dσᵢ = δ·[g·(Tᵢ₊₁cᵢ − Aᵢ) + h·(Tᵢ₊₁φᵢ − Bᵢ)]
//! (B the same sum for features without background), then through the
//! sigmoid / softplus and the trilinear weights into per-voxel gradients.
//!
//! Two shortcuts, both off when exactness matters (tests): samples whose
//! weight is below `weight_floor` are not shaded (their colour counts as
//! black, so their density still gets the exact gradient of what was
//! computed), and rays stop once T < `min_transmittance` (as the renderer).

use super::grads::GradLog;
use super::model::{bit, Model, BLOCK};
use crate::camera::Ray;
use crate::field::sh;
use glam::Vec3;

#[derive(Clone, Copy, Debug)]
pub struct MarchOpts {
    /// Sample spacing δ in field units.
    pub step: f32,
    pub background: Vec3,
    /// Samples with weight at or below this are not shaded.
    pub weight_floor: f32,
    pub min_transmittance: f32,
    /// Render (and train) semantic features.
    pub features: bool,
    /// Shade colour. Off while distilling features into a frozen field:
    /// nothing uses the colour then, and gathering a sample's SH
    /// coefficients was the forward pass's largest cost (memory stalls).
    /// The ray's colour is then the background alone.
    pub colour: bool,
    /// Density and colour train: the backward pass records their
    /// gradients (off while distilling features into a frozen field).
    pub geometry: bool,
    /// Weight of this ray's distortion loss (mip-NeRF 360's L_dist, see
    /// [`distortion`]); 0: not computed.
    pub distortion: f32,
}

#[derive(Clone, Copy, Debug, Default)]
struct Sample {
    base: u32,
    frac: [f32; 3],
    t: f32,
    alpha: f32,
    trans: f32,
    /// dσ/draw at the interpolated raw value.
    dsig: f32,
    color: [f32; 3],
    shaded: bool,
    /// Start of this sample's VM row in `Scratch::vm_rows` (VM models).
    row: u32,
}

/// Per-thread scratch: the samples of the last forward pass.
#[derive(Default)]
pub struct Scratch {
    samples: Vec<Sample>,
    /// Features of shaded samples, `samples × channels` (unshaded rows zero).
    feats: Vec<f32>,
    tmp: Vec<f32>,
    /// VM models: the encoded ray direction, per shaded sample the values
    /// the backward pass needs, and backward scratch.
    dir_enc: Vec<f32>,
    vm_rows: Vec<f32>,
    vm_tmp: Vec<f32>,
    /// λ·dL_dist/dwᵢ per sample (backward pass).
    dist: Vec<f32>,
    final_trans: f32,
    color: Vec3,
    /// Length of the ray's chord through the box: distances along the ray
    /// are measured in it for the distortion loss.
    chord: f32,
    pub features: Vec<f32>,
}

/// What one ray renders to.
#[derive(Clone, Copy, Debug)]
pub struct RayOut {
    pub color: Vec3,
    pub opacity: f32,
    /// Σ wᵢ tᵢ.
    pub depth: f32,
    /// Samples evaluated (for throughput figures).
    pub samples: u32,
}

/// Precomputed per-grid constants for fast trilinear lookups.
#[derive(Clone, Copy)]
struct Lattice {
    min: Vec3,
    scale: Vec3,
    hi: Vec3,
    res: [usize; 3],
    off: [usize; 8],
}

impl Lattice {
    fn new(g: &crate::field::GridGeom) -> Self {
        let [nx, ny, nz] = g.res;
        let n = Vec3::new((nx - 1) as f32, (ny - 1) as f32, (nz - 1) as f32);
        Lattice {
            min: g.bounds.min,
            scale: n / g.bounds.size(),
            hi: n,
            res: g.res,
            off: corner_offsets(g.res),
        }
    }
    /// Continuous grid coordinates of `p`.
    #[inline]
    fn grid(&self, p: Vec3) -> Vec3 {
        (p - self.min) * self.scale
    }
    /// (base index, fractions) of the cell holding grid point `g`, or `None`
    /// outside the grid.
    #[inline]
    fn cell(&self, g: Vec3) -> Option<(usize, [f32; 3])> {
        if !(g.x >= 0.0 && g.y >= 0.0 && g.z >= 0.0 && g.x <= self.hi.x && g.y <= self.hi.y && g.z <= self.hi.z) {
            return None;
        }
        let [nx, ny, nz] = self.res;
        let x0 = (g.x as usize).min(nx - 2);
        let y0 = (g.y as usize).min(ny - 2);
        let z0 = (g.z as usize).min(nz - 2);
        Some((
            x0 + nx * (y0 + ny * z0),
            [g.x - x0 as f32, g.y - y0 as f32, g.z - z0 as f32],
        ))
    }
}

/// Grid-index offsets of a cell's 8 corners from its lower corner (corner
/// k = x bit 0, y bit 1, z bit 2), on a grid of `res` points.
pub(super) fn corner_offsets(res: [usize; 3]) -> [usize; 8] {
    let [nx, ny, _] = res;
    std::array::from_fn(|k| (k & 1) + nx * (((k >> 1) & 1) + ny * ((k >> 2) & 1)))
}

/// Trilinear weights of a cell's corners (order of [`corner_offsets`]).
#[inline]
pub(super) fn weights(f: [f32; 3]) -> [f32; 8] {
    let [fx, fy, fz] = f;
    let (gx, gy, gz) = (1.0 - fx, 1.0 - fy, 1.0 - fz);
    [
        gx * gy * gz,
        fx * gy * gz,
        gx * fy * gz,
        fx * fy * gz,
        gx * gy * fz,
        fx * gy * fz,
        gx * fy * fz,
        fx * fy * fz,
    ]
}

#[inline]
fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// σ and dσ/draw for softplus(raw + shift).
#[inline]
fn softplus_d(x: f32) -> (f32, f32) {
    if x > 20.0 {
        (x, 1.0)
    } else {
        let e = x.exp();
        (e.ln_1p(), e / (1.0 + e))
    }
}

/// The parameter interval and first sample index of a ray in the model's
/// box, or `None` when it misses; also the chord's length.
fn span(model: &Model, ray: &Ray, step: f32) -> Option<(i64, f32, f32)> {
    let (t0, t1) = model.geom.bounds.intersect(ray.origin, ray.dir)?;
    Some(((t0 / step - 0.5).ceil().max(0.0) as i64, t1, t1 - t0.max(0.0)))
}

/// Distortion loss of one ray (Barron et al., mip-NeRF 360, eq. 15) over
/// its samples' weights wᵢ at positions sᵢ = tᵢ / chord, each an interval
/// of length δ = step / chord:
///
/// L = Σᵢ Σⱼ wᵢ wⱼ |sᵢ − sⱼ| + ⅓ Σᵢ wᵢ² δ.
///
/// It is small when a ray's weight sits in one short stretch, and large
/// when it is spread out or split between depths: semi-transparent fog
/// and doubled surfaces that the training views cannot tell apart but a
/// new view sees as ghosts. With the weights in depth order the double sum
/// takes one pass with running sums.
fn distortion(samples: &[Sample], step: f32, chord: f32) -> f32 {
    let inv = 1.0 / chord.max(1e-12);
    let (mut w_sum, mut ws_sum, mut loss) = (0.0f32, 0.0f32, 0.0f32);
    for smp in samples {
        let (w, s) = (smp.trans * smp.alpha, smp.t * inv);
        loss += 2.0 * w * (s * w_sum - ws_sum) + w * w * step * inv / 3.0;
        w_sum += w;
        ws_sum += w * s;
    }
    loss
}

/// The unweighted distortion loss of the ray of the last [`forward`] with
/// sample spacing `step`. Training needs only its gradient (in
/// [`backward`]); this is for checking that gradient.
pub fn ray_distortion(s: &Scratch, step: f32) -> f32 {
    distortion(&s.samples, step, s.chord)
}

/// dL/dwᵢ of [`distortion`] for every sample, in order, into `out`:
/// 2 Σⱼ wⱼ |sᵢ − sⱼ| + ⅔ wᵢ δ, from the running sums before and after i.
fn distortion_grads(samples: &[Sample], step: f32, chord: f32, out: &mut Vec<f32>) {
    let inv = 1.0 / chord.max(1e-12);
    let (w_tot, ws_tot) = samples.iter().fold((0.0f32, 0.0f32), |(a, b), smp| {
        let w = smp.trans * smp.alpha;
        (a + w, b + w * smp.t * inv)
    });
    out.clear();
    let (mut w_before, mut ws_before) = (0.0f32, 0.0f32);
    for smp in samples {
        let (w, s) = (smp.trans * smp.alpha, smp.t * inv);
        let (w_after, ws_after) = (w_tot - w_before - w, ws_tot - ws_before - w * s);
        out.push(2.0 * (s * w_before - ws_before + ws_after - s * w_after) + 2.0 / 3.0 * w * step * inv);
        w_before += w;
        ws_before += w * s;
    }
}

/// Colour of a sample from the SH coefficients at its cell's corners
/// (stored per active voxel; a pruned corner counts as 0).
#[inline]
fn sh_color<const K: usize>(model: &Model, base: usize, off: &[usize; 8], w8: &[f32; 8], basis: &[f32]) -> [f32; 3] {
    let stride = 3 * K;
    let mut acc = [[0.0f32; K]; 3];
    for k in 0..8 {
        let Some(v) = model.slots.slot(base + off[k]) else {
            continue;
        };
        let src = &model.sh[v * stride..(v + 1) * stride];
        for c in 0..3 {
            for j in 0..K {
                acc[c][j] += w8[k] * src[c * K + j];
            }
        }
    }
    [0, 1, 2].map(|c| sigmoid((0..K).map(|j| acc[c][j] * basis[j]).sum()))
}

/// Asks the caches for what the march reads a few samples ahead: the cell
/// flag, density corners and rank words two samples on, the colour rows of
/// the next sample's corners (whose rank words the previous call asked
/// for). A ray enters new cells every other sample, and their rows lie
/// far apart in a grid of 100–300 MB: the loads missed the caches and the
/// march waited on them.
#[inline(always)]
fn prefetch_ahead<const K: usize>(model: &Model, lat: &Lattice, ray: &Ray, t: f32, dt: f32) {
    use crate::util::prefetch;
    if let Some((base, _)) = lat.cell(lat.grid(ray.at(t + 2.0 * dt))) {
        prefetch(model.cells.as_ptr().wrapping_add(base));
        for k in [0, 2, 4, 6] {
            prefetch(model.density.as_ptr().wrapping_add(base + lat.off[k]));
            model.slots.index.prefetch(base + lat.off[k]);
        }
    }
    if model.vm.is_some() {
        return;
    }
    if let Some((base, _)) = lat.cell(lat.grid(ray.at(t + dt))) {
        let stride = 3 * K;
        for k in 0..8 {
            if let Some(v) = model.slots.slot(base + lat.off[k]) {
                let row = model.sh.as_ptr().wrapping_add(v * stride);
                // A row (27 values for degree 2) spans up to three lines.
                for line in (0..stride).step_by(16).chain([stride - 1]) {
                    prefetch(row.wrapping_add(line));
                }
            }
        }
    }
}

/// Forward pass of one ray; fills `scratch` for [`backward`].
pub fn forward(model: &Model, ray: &Ray, opts: &MarchOpts, scratch: &mut Scratch) -> RayOut {
    match model.degree {
        0 => forward_k::<1>(model, ray, opts, scratch),
        1 => forward_k::<4>(model, ray, opts, scratch),
        _ => forward_k::<9>(model, ray, opts, scratch),
    }
}

fn forward_k<const K: usize>(model: &Model, ray: &Ray, opts: &MarchOpts, s: &mut Scratch) -> RayOut {
    s.samples.clear();
    s.feats.clear();
    let fc = if opts.features {
        model.features.as_ref().map_or(0, |f| f.channels)
    } else {
        0
    };
    s.features.clear();
    s.features.resize(fc, 0.0);
    s.tmp.resize(fc, 0.0);
    let mut trans = 1.0f32;
    let mut color = Vec3::ZERO;
    let mut depth = 0.0;
    let lat = Lattice::new(&model.geom);
    let flat = model.features.as_ref().map(|f| Lattice::new(&f.geom));
    let basis = sh::basis(ray.dir);
    s.vm_rows.clear();
    if let Some(vm) = &model.vm {
        vm.encode_dir(ray.dir, &mut s.dir_enc);
    }
    let dt = opts.step;
    let bd = model.block_dims;
    let dir_g = ray.dir * lat.scale;
    s.chord = 0.0;
    if let Some((mut i, t1, chord)) = span(model, ray, dt) {
        s.chord = chord;
        loop {
            let t = (i as f32 + 0.5) * dt;
            if t > t1 || trans < opts.min_transmittance {
                break;
            }
            let g = lat.grid(ray.at(t));
            let Some((base, frac)) = lat.cell(g) else {
                i += 1;
                continue;
            };
            // Empty block: jump to the first sample past it.
            let b = [0, 1, 2].map(|a| ((g[a] as usize) / BLOCK).min(bd[a] - 1));
            if !model.blocks[b[0] + bd[0] * (b[1] + bd[1] * b[2])] {
                let mut exit = f32::INFINITY;
                for a in 0..3 {
                    let (lo, hi) = ((b[a] * BLOCK) as f32, ((b[a] + 1) * BLOCK) as f32);
                    let d = dir_g[a];
                    if d > 0.0 {
                        exit = exit.min((hi - g[a]) / d);
                    } else if d < 0.0 {
                        exit = exit.min((lo - g[a]) / d);
                    }
                }
                let next = ((t + exit.max(0.0)) / dt - 0.5).ceil() as i64;
                i = next.max(i + 1);
                continue;
            }
            i += 1;
            prefetch_ahead::<K>(model, &lat, ray, t, dt);
            if model.cells[base] == 0 {
                continue;
            }
            let w8 = weights(frac);
            let mut raw = 0.0;
            for k in 0..8 {
                raw += w8[k] * model.density[base + lat.off[k]];
            }
            let (sigma, dsig) = softplus_d(raw + model.shift);
            let alpha = 1.0 - (-sigma * dt).exp();
            let w = trans * alpha;
            let mut smp = Sample {
                base: base as u32,
                frac,
                t,
                alpha,
                trans,
                dsig,
                color: [0.0; 3],
                shaded: false,
                row: 0,
            };
            if w > opts.weight_floor {
                smp.color = match &model.vm {
                    _ if !opts.colour => [0.0; 3],
                    Some(vm) => {
                        let start = s.vm_rows.len();
                        s.vm_rows.resize(start + vm.shape.row_len(), 0.0);
                        smp.row = start as u32;
                        vm.shade(g, &s.dir_enc, &mut s.vm_rows[start..])
                    }
                    None => sh_color::<K>(model, base, &lat.off, &w8, &basis),
                };
                smp.shaded = true;
                color += w * Vec3::from(smp.color);
                depth += w * t;
                if fc > 0 {
                    let start = s.feats.len();
                    s.feats.resize(start + fc, 0.0);
                    if let (Some(fl), Some(fg)) = (&flat, &model.features) {
                        if let Some((fb, ff)) = fl.cell(fl.grid(ray.at(t))) {
                            let fw = weights(ff);
                            let row = &mut s.feats[start..start + fc];
                            for k in 0..8 {
                                let v = (fb + fl.off[k]) * fc;
                                for (o, x) in row.iter_mut().zip(&fg.data[v..v + fc]) {
                                    *o += fw[k] * x;
                                }
                            }
                            for (o, x) in s.features.iter_mut().zip(row.iter()) {
                                *o += w * x;
                            }
                        }
                    }
                }
            } else if fc > 0 {
                let start = s.feats.len();
                s.feats.resize(start + fc, 0.0);
            }
            s.samples.push(smp);
            trans *= 1.0 - alpha;
        }
    }
    s.final_trans = trans;
    s.color = color + trans * opts.background;
    RayOut {
        color: s.color,
        opacity: 1.0 - trans,
        depth,
        samples: s.samples.len() as u32,
    }
}

/// Backward pass for the ray of the last [`forward`], given dL/dC (`g`) and
/// dL/dΦ (`h`, empty when features are not trained): one record per sample
/// into `log`, spread over the grids later by [`super::grads::gather`]
/// (VM appearance gradients go straight into the log's dense arrays).
pub fn backward(model: &Model, ray: &Ray, opts: &MarchOpts, s: &mut Scratch, g: Vec3, h: &[f32], log: &mut GradLog) {
    let lat = Lattice::new(&model.geom);
    let fc = if opts.features && !h.is_empty() {
        model.features.as_ref().map_or(0, |f| f.channels)
    } else {
        0
    };
    let flat = model.features.as_ref().map(|f| Lattice::new(&f.geom));
    // SH colour gradients need the ray's basis (not VM's, not frozen ones).
    let sh_colour = model.vm.is_none() && opts.geometry;
    let (basis, h_row) = log.begin_ray(sh_colour.then(|| sh::basis(ray.dir)), &h[..fc]);
    let dt = opts.step;
    let g3 = g.to_array();
    // "After" sums: colour includes the background seen through the end.
    let mut after = s.final_trans * opts.background;
    let after_f = &mut s.tmp;
    after_f.clear();
    after_f.resize(fc, 0.0);
    if !opts.geometry {
        feature_records(ray, s, fc, flat.as_ref(), h_row, log);
        return;
    }
    // Distortion: λ·dL/dwᵢ per sample; a weight's gradient reaches σᵢ as
    // T₍ᵢ₊₁₎·gᵢ − Σ_{j>i} wⱼ gⱼ, like colour (where gⱼ = g·cⱼ).
    let mut dist_g = std::mem::take(&mut s.dist);
    dist_g.clear();
    if opts.distortion > 0.0 {
        distortion_grads(&s.samples, dt, s.chord, &mut dist_g);
        dist_g.iter_mut().for_each(|d| *d *= opts.distortion);
    }
    let mut after_dist = 0.0f32;
    for (idx, smp) in s.samples.iter().enumerate().rev() {
        let w = smp.trans * smp.alpha;
        let t_next = smp.trans * (1.0 - smp.alpha);
        let c = Vec3::from(smp.color);
        let mut dsigma = if smp.shaded {
            g.dot(t_next * c - after)
        } else {
            -g.dot(after)
        };
        if let Some(&gd) = dist_g.get(idx) {
            dsigma += t_next * gd - after_dist;
            after_dist += w * gd;
        }
        // Colour: through the sigmoid, then (SH) the basis and the weights.
        let dz = [0, 1, 2].map(|ch| w * g3[ch] * smp.color[ch] * (1.0 - smp.color[ch]));
        if let (true, Some(vm)) = (smp.shaded, &model.vm) {
            let start = smp.row as usize;
            let row = &s.vm_rows[start..start + vm.shape.row_len()];
            let gp = lat.grid(ray.at(smp.t));
            vm.backward(gp, row, dz, &mut log.vm_grid, &mut log.vm_net, &mut s.vm_tmp);
        }
        if smp.shaded {
            after += w * c;
            if fc > 0 {
                let phi = &s.feats[idx * fc..(idx + 1) * fc];
                let mut df = 0.0;
                for ((&hh, &p), a) in h.iter().zip(phi).zip(after_f.iter_mut()) {
                    df += hh * (t_next * p - *a);
                    *a += w * p;
                }
                dsigma += df;
                if let Some(fl) = &flat {
                    if let Some((fb, ff)) = fl.cell(fl.grid(ray.at(smp.t))) {
                        log.push_feature(fb as u32, ff, w, h_row);
                    }
                }
            }
        } else if fc > 0 {
            let dfe: f32 = h.iter().zip(after_f.iter()).map(|(a, b)| a * b).sum();
            dsigma -= dfe;
        }
        let colour = (smp.shaded && sh_colour).then_some((basis, dz));
        log.push_cell(smp.base, smp.frac, dsigma * dt * smp.dsig, colour);
    }
    s.dist = dist_g;
}

/// The feature records of the last forward pass alone (frozen density and
/// colour): each shaded sample's weight in its feature cell.
fn feature_records(ray: &Ray, s: &Scratch, fc: usize, flat: Option<&Lattice>, h_row: u32, log: &mut GradLog) {
    let Some(fl) = flat.filter(|_| fc > 0) else {
        return;
    };
    // Back to front, as the full pass records them (same sums, bit for bit).
    for smp in s.samples.iter().rev().filter(|smp| smp.shaded) {
        if let Some((fb, ff)) = fl.cell(fl.grid(ray.at(smp.t))) {
            log.push_feature(fb as u32, ff, smp.trans * smp.alpha, h_row);
        }
    }
}

/// True when grid point `i` trains (used by tests and the optimizer).
pub fn is_active(model: &Model, i: usize) -> bool {
    bit(&model.active, i)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(t: f32, trans: f32, alpha: f32) -> Sample {
        Sample {
            t,
            trans,
            alpha,
            ..Default::default()
        }
    }

    #[test]
    fn distortion_has_the_closed_form_of_its_definition() {
        // One opaque sample: only the interval's own term, w²δ/3.
        let one = [sample(0.5, 1.0, 1.0)];
        assert!((distortion(&one, 0.1, 2.0) - 0.05 / 3.0).abs() < 1e-7);
        // Half the weight at s = 0.1, half at s = 0.4 (chord 1):
        // 2·½·½·0.3 + ⅓(¼ + ¼)δ.
        let two = [sample(0.1, 1.0, 0.5), sample(0.4, 0.5, 1.0)];
        let want = 2.0 * 0.25 * 0.3 + (0.5 / 3.0) * 0.01;
        assert!((distortion(&two, 0.01, 1.0) - want).abs() < 1e-6);
        // Spreading the same weight further apart costs more.
        let far = [sample(0.1, 1.0, 0.5), sample(0.9, 0.5, 1.0)];
        assert!(distortion(&far, 0.01, 1.0) > distortion(&two, 0.01, 1.0));
    }

    #[test]
    fn distortion_grads_are_the_partial_derivatives_in_the_weights() {
        // L as a function of free weights wᵢ (trans = 1, alpha = wᵢ).
        let ts = [0.05f32, 0.2, 0.3, 0.55, 0.8];
        let ws = [0.1f32, 0.3, 0.05, 0.4, 0.15];
        let make = |w: &[f32]| -> Vec<Sample> { ts.iter().zip(w).map(|(&t, &w)| sample(t, 1.0, w)).collect() };
        let (step, chord) = (0.05, 1.3);
        let mut g = vec![];
        distortion_grads(&make(&ws), step, chord, &mut g);
        for i in 0..ws.len() {
            let eps = 1e-3;
            let (mut p, mut m) = (ws, ws);
            p[i] += eps;
            m[i] -= eps;
            let fd = (distortion(&make(&p), step, chord) - distortion(&make(&m), step, chord)) / (2.0 * eps);
            assert!(
                (fd - g[i]).abs() < 1e-3,
                "w{i}: analytic {} vs finite difference {fd}",
                g[i]
            );
        }
    }
}
