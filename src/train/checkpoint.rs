//! Training checkpoints: the f32 parameters, the active mask, Adam's moments,
//! the iteration and the loss history in one `.safetensors` file, written
//! atomically, so that `--resume` continues exactly where a run stopped.
//!
//! `__metadata__`: `format = "isrf-train-checkpoint"`, `version`, `state`
//! (JSON [`State`]). Tensors (F32 unless noted): `density [n]`, `sh [n, 3K]`,
//! `active` (U8, packed bits), `features [nf, C]`, `vm.grid` / `vm.net` (VM
//! appearance), `m.*` / `v.*` moments of each (those of density and SH per
//! active voxel, ascending; older checkpoints hold them per grid point and
//! still load), `history [iters, 7]`.

use super::model::{DenseGrid, Model, Slots};
use super::optim::Moments;
use super::trainer::{OptState, StepStats, TrainConfig};
use super::vm::{VmAppearance, VmShape};
use crate::error::{Error, Result};
use crate::field::geom::check_res;
use crate::field::io::{check_format, write_tensors};
use crate::field::tensor_file::TensorFile;
use crate::field::{Aabb, GridGeom};
use glam::Vec3;
use safetensors::tensor::Dtype;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;

pub const FORMAT: &str = "isrf-train-checkpoint";
pub const VERSION: u32 = 1;

/// Everything besides the big arrays.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct State {
    pub config: TrainConfig,
    pub iter: usize,
    pub adam_t: u64,
    pub bounds: [[f32; 3]; 2],
    pub res: [usize; 3],
    pub degree: usize,
    pub shift: f32,
    /// (resolution, channels) of the feature grid, if any.
    pub features: Option<([usize; 3], usize)>,
    /// Sizes and grid resolution of the VM appearance, if any.
    #[serde(default)]
    pub vm: Option<(VmShape, [usize; 3])>,
    /// Free-form description of the data trained on (dataset path, options),
    /// checked on resume.
    pub data: String,
}

/// What a checkpoint restores.
pub struct Restored {
    pub state: State,
    pub model: Model,
    pub opt: OptState,
    pub history: Vec<StepStats>,
}

const HIST: usize = 7;

/// Writes a checkpoint atomically.
pub fn save(
    path: &Path,
    config: &TrainConfig,
    model: &Model,
    opt: &OptState,
    iter: usize,
    history: &[StepStats],
    data: &str,
) -> Result<()> {
    let state = State {
        config: config.clone(),
        iter,
        adam_t: opt.t,
        bounds: [model.geom.bounds.min.to_array(), model.geom.bounds.max.to_array()],
        res: model.geom.res,
        degree: model.degree,
        shift: model.shift,
        features: model.features.as_ref().map(|f| (f.geom.res, f.channels)),
        vm: model.vm.as_ref().map(|v| (v.shape, v.res)),
        data: data.to_string(),
    };
    let hist: Vec<f32> = history
        .iter()
        .flat_map(|s| {
            [
                s.iter as f32,
                s.loss,
                s.psnr,
                s.feature_loss,
                s.rays as f32,
                s.samples as f32,
                s.seconds,
            ]
        })
        .collect();
    // Tensors borrow the trainer's arrays and stream to the file: a copy of
    // a checkpoint (model and both moments, over 1 GB on a 160³ grid) would
    // double the peak memory of a training run.
    let mut out = Outgoing::default();
    // Each trained array with its Adam moments `m.<name>` / `v.<name>`.
    let mut trained = vec![
        ("density", &model.density[..], &opt.density),
        ("sh", &model.sh[..], &opt.sh),
    ];
    if let Some(f) = &model.features {
        trained.push(("features", &f.data[..], &opt.features));
    }
    if let Some(vm) = &model.vm {
        trained.push(("vm.grid", &vm.grid[..], &opt.vm_grid));
        trained.push(("vm.net", &vm.net[..], &opt.vm_net));
    }
    for (name, values, mom) in trained {
        out.f32(name, values);
        out.bytes(&format!("m.{name}"), Dtype::BF16, bytemuck::cast_slice(&mom.m));
        out.bytes(&format!("v.{name}"), Dtype::BF16, bytemuck::cast_slice(&mom.v));
    }
    out.f32("history", &hist);
    // Packed little-endian words, like every bitmap in isrf files.
    out.bytes("active", Dtype::U8, bytemuck::cast_slice(&model.active));
    let mut meta = HashMap::new();
    meta.insert("format".to_string(), FORMAT.to_string());
    meta.insert("version".to_string(), VERSION.to_string());
    meta.insert(
        "state".to_string(),
        serde_json::to_string(&state).map_err(|e| Error::invalid(e.to_string()))?,
    );
    write_tensors(path, &out.names, &out.tensors, meta)
}

/// Tensors to write, borrowing the arrays (flat shapes).
#[derive(Default)]
struct Outgoing<'a> {
    names: Vec<String>,
    tensors: Vec<(Dtype, Vec<usize>, &'a [u8])>,
}

impl<'a> Outgoing<'a> {
    fn bytes(&mut self, name: &str, dtype: Dtype, bytes: &'a [u8]) {
        let len = bytes.len() * 8 / dtype.bitsize();
        self.names.push(name.to_string());
        self.tensors.push((dtype, vec![len], bytes));
    }
    fn f32(&mut self, name: &str, v: &'a [f32]) {
        self.bytes(name, Dtype::F32, bytemuck::cast_slice(v));
    }
}

/// Reads a checkpoint, validating every shape against its state.
pub fn load(path: &Path) -> Result<Restored> {
    // Tensor by tensor: a full-size checkpoint is not held whole beside
    // what is parsed from it.
    let t = TensorFile::open(path)?;
    let meta = t.metadata();
    check_format(meta, FORMAT, VERSION, path)?;
    let bad = |r: String| Error::bad_file(path, r);
    let state: State = serde_json::from_str(
        meta.get("state")
            .ok_or_else(|| bad("missing 'state' in metadata".into()))?,
    )
    .map_err(|e| bad(format!("malformed checkpoint state: {e}")))?;
    check_res(state.res, "checkpoint grid").map_err(|e| bad(e.to_string()))?;
    if state.degree > 2 {
        return Err(bad(format!("SH degree {} is out of range", state.degree)));
    }
    let bounds = Aabb::new(Vec3::from(state.bounds[0]), Vec3::from(state.bounds[1]));
    if !bounds.is_valid() {
        return Err(bad(format!("bounds {:?} are not a valid box", state.bounds)));
    }
    let geom = GridGeom::new(bounds, state.res);
    let n = geom.len();
    let k = 3 * super::model::sh_coeffs(state.degree);
    let density = t.f32("density", &[n])?;
    let words = n.div_ceil(64);
    let active_bytes = t.u8("active", &[words * 8])?;
    let active: Vec<u64> = active_bytes
        .chunks_exact(8)
        .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")))
        .collect();
    // SH rows per active voxel; checkpoints written before hold a row per
    // grid point (the model accepts either).
    let active_count: usize = active.iter().map(|w| w.count_ones() as usize).sum();
    let sh_len = t.shape("sh").map_or(0, |s| s.iter().product::<usize>());
    let sh = t.f32("sh", &[if sh_len == n * k { n * k } else { active_count * k }])?;
    // The Adam moments saved beside array `name` of `len` values.
    let moments = |name: &str, len: usize| -> Result<Moments> {
        Ok(Moments {
            m: t.bf16_or_f32(&format!("m.{name}"), &[len])?,
            v: t.bf16_or_f32(&format!("v.{name}"), &[len])?,
        })
    };
    let mut opt = OptState {
        density: Moments::default(),
        sh: Moments::default(),
        features: Moments::default(),
        vm_grid: Moments::default(),
        vm_net: Moments::default(),
        t: state.adam_t,
    };
    let features = match state.features {
        Some((res, c)) => {
            check_res(res, "checkpoint feature grid").map_err(|e| bad(e.to_string()))?;
            if c == 0 || c > 4096 {
                return Err(bad(format!("feature channel count {c} is out of range")));
            }
            let fg = GridGeom::new(bounds, res);
            let len = fg.len() * c;
            opt.features = moments("features", len)?;
            Some(DenseGrid {
                geom: fg,
                channels: c,
                data: t.f32("features", &[len])?,
            })
        }
        None => None,
    };
    let hist_len = t
        .shape("history")
        .ok_or_else(|| bad("missing tensor 'history'".into()))?
        .first()
        .copied()
        .unwrap_or(0);
    if hist_len % HIST != 0 {
        return Err(bad(format!("history has {hist_len} values, not a multiple of {HIST}")));
    }
    let history = t
        .f32("history", &[hist_len])?
        .chunks_exact(HIST)
        .map(|h| StepStats {
            iter: h[0] as usize,
            loss: h[1],
            psnr: h[2],
            feature_loss: h[3],
            rays: h[4] as usize,
            samples: h[5] as u64,
            seconds: h[6],
            update_seconds: 0.0,
        })
        .collect();
    let mut model = Model::from_parts(geom, state.shift, state.degree, density, sh, active, features)?;
    // Density and SH moments are per active voxel; checkpoints written
    // before they were hold them for every grid point.
    let slot_moments = |name: &str, stride: usize| -> Result<Moments> {
        let full_len = n * stride;
        let len = t.shape(&format!("m.{name}")).map_or(0, |s| s.iter().product::<usize>());
        if len == 0 {
            // Written while distilling into the frozen field, which keeps
            // no moments for it.
            Ok(Moments::default())
        } else if len == full_len && full_len != model.slots.len() * stride {
            let all = Slots::new(geom.res, &vec![u64::MAX; n.div_ceil(64)]);
            Ok(moments(name, full_len)?.remap(&all, &model.slots, stride))
        } else {
            moments(name, model.slots.len() * stride)
        }
    };
    opt.density = slot_moments("density", 1)?;
    opt.sh = slot_moments("sh", k)?;
    if let Some((shape, res)) = state.vm {
        shape.validate().map_err(|e| bad(e.to_string()))?;
        check_res(res, "checkpoint VM grid").map_err(|e| bad(e.to_string()))?;
        let (gl, nl) = (shape.grid_len(res), shape.net_len());
        model.vm = Some(VmAppearance::from_parts(
            shape,
            res,
            t.f32("vm.grid", &[gl])?,
            t.f32("vm.net", &[nl])?,
        )?);
        opt.vm_grid = moments("vm.grid", gl)?;
        opt.vm_net = moments("vm.net", nl)?;
    }
    Ok(Restored {
        state,
        model,
        opt,
        history,
    })
}
