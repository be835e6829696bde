//! Training checkpoints: the f32 parameters, the active mask, Adam's moments,
//! the iteration and the loss history in one `.safetensors` file, written
//! atomically, so that `--resume` continues exactly where a run stopped.
//!
//! `__metadata__`: `format = "isrf-train-checkpoint"`, `version`, `state`
//! (JSON [`State`]). Tensors (F32 unless noted): `density [n]`, `sh [n, 3K]`,
//! `active` (U8, packed bits), `features [nf, C]`, `vm.grid` / `vm.net` (VM
//! appearance), `m.*` / `v.*` moments of each, `history [iters, 7]`.

use super::model::{DenseGrid, Model};
use super::optim::Moments;
use super::trainer::{OptState, StepStats, TrainConfig};
use super::vm::{VmAppearance, VmShape};
use crate::error::{write_atomic, Error, Result};
use crate::field::geom::check_res;
use crate::field::io::{check_format, parse, read_all, read_metadata, serialize, Tensors};
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

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    bytemuck::cast_slice(v).to_vec()
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
    let mut names = vec![];
    let mut tensors = vec![];
    let mut push = |name: &str, v: &[f32]| {
        names.push(name.to_string());
        tensors.push((Dtype::F32, vec![v.len()], f32_bytes(v)));
    };
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
        push(name, values);
        push(&format!("m.{name}"), &mom.m);
        push(&format!("v.{name}"), &mom.v);
    }
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
    push("history", &hist);
    let active: Vec<u8> = model.active.iter().flat_map(|w| w.to_le_bytes()).collect();
    names.push("active".into());
    tensors.push((Dtype::U8, vec![active.len()], active));
    let mut meta = HashMap::new();
    meta.insert("format".to_string(), FORMAT.to_string());
    meta.insert("version".to_string(), VERSION.to_string());
    meta.insert(
        "state".to_string(),
        serde_json::to_string(&state).map_err(|e| Error::invalid(e.to_string()))?,
    );
    write_atomic(path, &serialize(&names, &tensors, meta)?)
}

/// Reads a checkpoint, validating every shape against its state.
pub fn load(path: &Path) -> Result<Restored> {
    let (meta, _) = read_metadata(path)?;
    check_format(&meta, FORMAT, VERSION, path)?;
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
    let bytes = read_all(path)?;
    let t = Tensors {
        st: parse(&bytes, path)?,
        path,
    };
    let geom = GridGeom::new(bounds, state.res);
    let n = geom.len();
    let k = 3 * super::model::sh_coeffs(state.degree);
    let density = t.f32("density", &[n])?;
    let sh = t.f32("sh", &[n * k])?;
    let words = n.div_ceil(64);
    let active_bytes = t.u8("active", &[words * 8])?;
    let active: Vec<u64> = active_bytes
        .chunks_exact(8)
        .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")))
        .collect();
    // The Adam moments saved beside array `name` of `len` values.
    let moments = |name: &str, len: usize| -> Result<Moments> {
        Ok(Moments {
            m: t.f32(&format!("m.{name}"), &[len])?,
            v: t.f32(&format!("v.{name}"), &[len])?,
        })
    };
    let mut opt = OptState {
        density: moments("density", n)?,
        sh: moments("sh", n * k)?,
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
    let hist_len =
        t.st.tensor("history")
            .map_err(|_| bad("missing tensor 'history'".into()))?
            .shape()
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
        })
        .collect();
    let mut model = Model::from_parts(geom, state.shift, state.degree, density, sh, active, features)?;
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
