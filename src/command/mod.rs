//! Every user action, of the editor and of scripts, is a serialisable
//! [`Command`]: an [`Edit`] (changes the session; undoable, logged) or an
//! [`Output`] (writes files from it).
//!
//! Modules, each importing only those above it:
//! - [`state`]: the model: fields and objects with stable ids, their one
//!   [`Placement`](state::Placement), the composition of a state;
//! - [`session`]: the state machine: `apply` an edit, undo / redo over a
//!   bounded history, the edit log; a dry session checks without working;
//! - [`script`]: scripts on disk (parse, save);
//! - [`composition`]: compositions on disk (save, open);
//! - [`output`]: renders and exports from a session, and [`perform`],
//!   which runs either kind of command;
//! - [`run`]: `isrf run` (check as a dry run, then execute);
//! - [`recovery`]: the editor's crash-recovery files.
//!
//! `Session::apply` validates and performs an edit and pushes the previous
//! state on the undo history (states share their grids and bitmaps through
//! `Arc`, so a step costs only what it changed); "save as script" writes
//! the log.

pub mod composition;
pub mod output;
pub mod recovery;
pub mod run;
pub mod script;
pub mod session;
pub mod state;
mod wire;

pub use output::{perform, FrameRenderer};
pub use run::{run_script, run_script_with, validate_script};
pub use script::{parse_script, Script};
pub use session::{Session, StepOutput};

use crate::camera::CameraSet;
use crate::render::ColorEdit;
use crate::segment::stroke::{CameraDoc, StrokeDoc};
use crate::segment::{Growth, Polarity};
use crate::util::{affine_from_rows, invertible};
use crate::Result;
use glam::{Affine3A, EulerRot, Quat, Vec3};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Where a field comes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FieldSource {
    /// A field file (.safetensors).
    File(PathBuf),
    /// A built-in demo scene, by name.
    Demo {
        scene: String,
        #[serde(default = "default_demo_res")]
        res: usize,
        #[serde(default)]
        seed: u64,
    },
}

pub fn default_demo_res() -> usize {
    128
}

/// An affine edit. Applied as
/// `A = T(translate) · T(pivot) · R(rotate) · S(scale) · T(−pivot)`, or the
/// given `matrix` (4×4, row-major) when present. Rotations are XYZ Euler
/// angles in degrees. The pivot defaults to the object's centre.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TransformSpec {
    pub translate: [f32; 3],
    pub rotate: [f32; 3],
    pub scale: [f32; 3],
    pub pivot: Option<[f32; 3]>,
    pub matrix: Option<[[f32; 4]; 4]>,
}

impl Default for TransformSpec {
    fn default() -> Self {
        TransformSpec {
            translate: [0.0; 3],
            rotate: [0.0; 3],
            scale: [1.0; 3],
            pivot: None,
            matrix: None,
        }
    }
}

impl TransformSpec {
    pub fn translation(t: Vec3) -> Self {
        TransformSpec {
            translate: t.to_array(),
            ..Default::default()
        }
    }
    pub fn validate(&self) -> Result<()> {
        let mut all: Vec<f32> = [self.translate, self.rotate, self.scale].concat();
        all.extend(self.pivot.unwrap_or_default());
        all.extend(self.matrix.iter().flatten().flatten());
        crate::ensure_within!(
            OutOfRange,
            all.iter().all(|v| v.is_finite()),
            "transform has a non-finite value"
        );
        crate::ensure_within!(
            OutOfRange,
            self.scale.iter().all(|&s| s.abs() > 1e-6 && s.abs() < 1e6),
            "transform scale {:?} is zero or absurd",
            self.scale
        );
        if let Some(m) = self.matrix {
            crate::ensure_within!(
                OutOfRange,
                invertible(&affine_from_rows(&m)),
                "transform matrix is not invertible"
            );
        }
        Ok(())
    }
    /// The affine map, with `default_pivot` used when none is given.
    pub fn affine(&self, default_pivot: Vec3) -> Affine3A {
        if let Some(m) = self.matrix {
            return affine_from_rows(&m);
        }
        let p = self.pivot.map(Vec3::from).unwrap_or(default_pivot);
        let [rx, ry, rz] = self.rotate.map(f32::to_radians);
        let rs = Affine3A::from_scale_rotation_translation(
            Vec3::from(self.scale),
            Quat::from_euler(EulerRot::XYZ, rx, ry, rz),
            Vec3::ZERO,
        );
        Affine3A::from_translation(Vec3::from(self.translate) + p) * rs * Affine3A::from_translation(-p)
    }
}

/// Which stroke.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StrokeSource {
    /// A stroke document inline.
    Inline(StrokeDoc),
    /// A stroke JSON file (see `isrf segment`); all its strokes, in order.
    File(PathBuf),
    /// An NVOS-style scribble PNG on a camera.
    Scribble { path: PathBuf, camera: CameraDoc },
    /// The built-in stroke of a demo scene's object (the field must be a demo).
    Demo { object: String },
}

/// Cameras for rendering and mask export.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraSource {
    /// A transforms.json file.
    File(PathBuf),
    /// The orbit of a loaded demo field (by field name); `eval` for its held-out views.
    Demo {
        field: String,
        #[serde(default)]
        eval: bool,
    },
    /// An orbit around a point.
    Orbit {
        center: [f32; 3],
        radius: f32,
        #[serde(default = "default_elevation")]
        elevation_deg: f32,
        #[serde(default = "default_frames")]
        frames: usize,
        #[serde(default = "default_width")]
        width: u32,
        #[serde(default = "default_height")]
        height: u32,
        #[serde(default = "default_fov")]
        fov_deg: f32,
    },
}

fn default_elevation() -> f32 {
    25.0
}
fn default_frames() -> usize {
    24
}
fn default_width() -> u32 {
    400
}
fn default_height() -> u32 {
    300
}
fn default_fov() -> f32 {
    50.0
}

/// What to export.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Export {
    /// 2D masks (object opacity > 0.1, with occlusion) for a camera set:
    /// `<out>/<frame>_mask.png`.
    Masks {
        object: String,
        cameras: CameraSource,
        out: PathBuf,
        #[serde(default = "one")]
        downscale: u32,
    },
    /// The object as a standalone field cropped to its bounding box.
    ObjectField {
        object: String,
        out: PathBuf,
        #[serde(default = "two")]
        margin: usize,
    },
    /// A mesh (marching cubes on density) of an object or a whole field, as
    /// placed in the composition; `.ply` or `.glb`.
    Mesh {
        target: String,
        out: PathBuf,
        #[serde(default)]
        iso: Option<f32>,
    },
    /// The 3D bitmap of an object.
    Bitmap { object: String, out: PathBuf },
    /// The composition document (fields by path, objects, transforms, edits).
    Composition { out: PathBuf },
    /// The edit log as a script.
    Script { out: PathBuf },
    /// 3D Gaussian splats (`.ply`) of an object as placed, or with
    /// `complement` its field without it; for a field imported from a
    /// `.ply`, the file's own records ([`crate::splat::export`]).
    Splats {
        object: String,
        out: PathBuf,
        #[serde(default)]
        complement: bool,
    },
}

fn one() -> u32 {
    1
}
fn two() -> usize {
    2
}

/// A change of the session: undoable, and written to the edit log.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Edit {
    /// Add a field to the composition under `name`, placed by `transform`.
    LoadField {
        name: String,
        source: FieldSource,
        #[serde(default)]
        transform: Option<TransformSpec>,
    },
    /// Move / rotate / scale a whole field (composition alignment).
    TransformField {
        field: String,
        transform: TransformSpec,
    },
    /// Segmentation parameters (unset ones keep their value). `rule` first
    /// resets every parameter to that growth rule's defaults.
    SetParams {
        #[serde(default)]
        rule: Option<crate::segment::GrowthRule>,
        #[serde(default)]
        k: Option<usize>,
        #[serde(default)]
        theta: Option<f32>,
        #[serde(default)]
        sigma_f: Option<f32>,
        #[serde(default)]
        sigma_s: Option<f32>,
        #[serde(default)]
        tau: Option<f32>,
        #[serde(default)]
        growth: Option<Growth>,
        #[serde(default)]
        theta_grow: Option<f32>,
        #[serde(default)]
        solid_alpha: Option<f32>,
        /// Only the seeds joined to the stroked surface (false: every
        /// look-alike in the field, as `isrf segment --anywhere`).
        #[serde(default)]
        connected: Option<bool>,
        /// Graph-cut rounds after the growth (0: no cut; faster strokes on
        /// large fields, coarser boundaries).
        #[serde(default)]
        cut_rounds: Option<usize>,
        /// Weight λ of the cut's boundary term (higher: smoother, fewer
        /// small islands).
        #[serde(default)]
        cut_lambda: Option<f32>,
        /// Segment on the field's grid coarsened 2× or 3× (an eighth of the
        /// voxels or less: several times faster strokes on large fields).
        #[serde(default)]
        coarse: Option<bool>,
    },
    /// A brush stroke for `object` (created on first positive stroke) on
    /// `field` (default: the object's field, else the first field).
    Stroke {
        object: String,
        #[serde(default)]
        field: Option<String>,
        #[serde(default)]
        polarity: Option<Polarity>,
        source: StrokeSource,
    },
    /// Grow an object's mask by bilateral filtering.
    Grow {
        object: String,
        steps: Growth,
    },
    Remove {
        object: String,
    },
    Restore {
        object: String,
    },
    /// Show or hide a field or an object (a hidden field still shows its
    /// visible detached objects: that is how an object is placed alone).
    SetVisible {
        target: String,
        visible: bool,
    },
    /// Move / rotate / scale an object relative to its current placement.
    Transform {
        object: String,
        transform: TransformSpec,
    },
    /// Copy an object (the copy does not cut its source).
    Duplicate {
        object: String,
        name: String,
        #[serde(default)]
        transform: Option<TransformSpec>,
    },
    /// Appearance edit of an object (replaces the previous edit).
    Appearance {
        object: String,
        edit: ColorEdit,
    },
    Rename {
        target: String,
        name: String,
    },
    Delete {
        target: String,
    },
}

/// Files written from the session (renders, exports, saves); changes
/// nothing, so it is neither undone nor logged. New outputs are new
/// variants here or in [`Export`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Output {
    /// Render the composition to `<out>/<frame>.png`.
    Render {
        cameras: CameraSource,
        out: PathBuf,
        #[serde(default = "one")]
        downscale: u32,
        #[serde(default)]
        frames: Option<usize>,
        #[serde(default)]
        depth: bool,
        #[serde(default)]
        background: Option<[f32; 3]>,
    },
    Export(Export),
}

/// One step of a script or one user action of the editor: an edit or an
/// output. On disk it is the variant of either (`stroke(...)`,
/// `render(...)`, `{"export": ...}`), see [`wire`].
// A handful are queued at a time: boxing the large variants buys nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(untagged)]
pub enum Command {
    Edit(Edit),
    Output(Output),
}

impl From<Edit> for Command {
    fn from(e: Edit) -> Self {
        Command::Edit(e)
    }
}

impl From<Output> for Command {
    fn from(o: Output) -> Self {
        Command::Output(o)
    }
}

impl Command {
    /// Short name for messages ("stroke", "load_field", ...).
    pub fn kind(&self) -> &'static str {
        match self {
            Command::Edit(e) => e.kind(),
            Command::Output(o) => o.kind(),
        }
    }
    pub fn as_edit(&self) -> Option<&Edit> {
        match self {
            Command::Edit(e) => Some(e),
            Command::Output(_) => None,
        }
    }
    /// The command with its relative input paths (fields, strokes,
    /// scribbles, cameras) taken from `dir`, as `isrf run` reads a script's
    /// inputs from the script's folder. Outputs are left alone: they go
    /// where the session writes.
    pub fn with_inputs_under(mut self, dir: &Path) -> Command {
        let rebase = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = dir.join(&*p);
            }
        };
        let cameras = |c: &mut CameraSource| {
            if let CameraSource::File(p) = c {
                rebase(p)
            }
        };
        match &mut self {
            Command::Edit(e) => {
                if let Some(p) = e.input_mut() {
                    rebase(p)
                }
            }
            Command::Output(Output::Render { cameras: c, .. })
            | Command::Output(Output::Export(Export::Masks { cameras: c, .. })) => cameras(c),
            Command::Output(_) => {}
        }
        self
    }
}

impl Output {
    pub fn kind(&self) -> &'static str {
        match self {
            Output::Render { .. } => "render",
            Output::Export(_) => "export",
        }
    }
}

impl Edit {
    /// The file this edit reads (a field, a stroke document, a scribble),
    /// if any: what a script's folder resolves and what crash recovery
    /// stamps.
    pub fn input_mut(&mut self) -> Option<&mut PathBuf> {
        match self {
            Edit::LoadField {
                source: FieldSource::File(p),
                ..
            } => Some(p),
            Edit::Stroke { source, .. } => match source {
                StrokeSource::File(p) | StrokeSource::Scribble { path: p, .. } => Some(p),
                StrokeSource::Inline(_) | StrokeSource::Demo { .. } => None,
            },
            _ => None,
        }
    }
    /// Short name for messages ("stroke", "load_field", ...).
    pub fn kind(&self) -> &'static str {
        match self {
            Edit::LoadField { .. } => "load_field",
            Edit::TransformField { .. } => "transform_field",
            Edit::SetParams { .. } => "set_params",
            Edit::Stroke { .. } => "stroke",
            Edit::Grow { .. } => "grow",
            Edit::Remove { .. } => "remove",
            Edit::Restore { .. } => "restore",
            Edit::SetVisible { .. } => "set_visible",
            Edit::Transform { .. } => "transform",
            Edit::Duplicate { .. } => "duplicate",
            Edit::Appearance { .. } => "appearance",
            Edit::Rename { .. } => "rename",
            Edit::Delete { .. } => "delete",
        }
    }
    /// For `SetParams`: `current` with the parameters it sets, validated.
    pub fn merged_params(&self, current: &crate::segment::SegmentParams) -> Result<crate::segment::SegmentParams> {
        let mut p = *current;
        if let Edit::SetParams {
            rule,
            k,
            theta,
            sigma_f,
            sigma_s,
            tau,
            growth,
            theta_grow,
            solid_alpha,
            connected,
            cut_rounds,
            cut_lambda,
            coarse,
        } = self
        {
            if let Some(r) = rule {
                p = crate::segment::SegmentParams::for_rule(*r);
            }
            p.grow.theta_grow = theta_grow.unwrap_or(p.grow.theta_grow);
            p.solid_alpha = solid_alpha.unwrap_or(p.solid_alpha);
            p.connected = connected.unwrap_or(p.connected);
            p.k = k.unwrap_or(p.k);
            p.theta = theta.unwrap_or(p.theta);
            p.grow.sigma_f = sigma_f.unwrap_or(p.grow.sigma_f);
            p.grow.sigma_s = sigma_s.unwrap_or(p.grow.sigma_s);
            p.grow.tau = tau.unwrap_or(p.grow.tau);
            p.growth = growth.unwrap_or(p.growth);
            p.cut.rounds = cut_rounds.unwrap_or(p.cut.rounds);
            p.cut.lambda = cut_lambda.unwrap_or(p.cut.lambda);
            p.coarse = coarse.unwrap_or(p.coarse);
        }
        p.validate()?;
        Ok(p)
    }
}

impl CameraSource {
    pub fn validate(&self) -> Result<()> {
        if let CameraSource::Orbit {
            center,
            radius,
            frames,
            width,
            height,
            fov_deg,
            elevation_deg,
        } = self
        {
            crate::ensure_within!(
                OutOfRange,
                center.iter().all(|v| v.is_finite()) && radius.is_finite() && *radius > 0.0,
                "orbit centre/radius must be finite, radius > 0"
            );
            crate::ensure_within!(
                OutOfRange,
                *frames >= 1 && *frames <= 10_000,
                "orbit frames must be 1..=10000, got {frames}"
            );
            crate::ensure_within!(
                OutOfRange,
                crate::limits::image_size_ok(*width, *height),
                "orbit image size {width}x{height} is out of range"
            );
            crate::ensure_within!(
                OutOfRange,
                fov_deg.is_finite() && *fov_deg > 1.0 && *fov_deg < 179.0,
                "orbit fov {fov_deg} must be in (1, 179) degrees"
            );
            crate::ensure_within!(
                OutOfRange,
                elevation_deg.is_finite() && elevation_deg.abs() < 90.0,
                "orbit elevation must be in (-90, 90) degrees"
            );
        }
        Ok(())
    }
    pub fn orbit_set(&self) -> Option<CameraSet> {
        if let CameraSource::Orbit {
            center,
            radius,
            elevation_deg,
            frames,
            width,
            height,
            fov_deg,
        } = self
        {
            let k = crate::camera::Intrinsics::from_fov_x(*width, *height, fov_deg.to_radians());
            return Some(CameraSet::orbit(
                k,
                Vec3::from(*center),
                *radius,
                elevation_deg.to_radians(),
                *frames,
            ));
        }
        None
    }
}
