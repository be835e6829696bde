//! Fitting a field to posed images (DESIGN.md "train"): a DVGO-style dense
//! density grid with dense spherical-harmonic colour (or, on request, the
//! paper's VM + MLP appearance, [`vm`]), trained on the CPU with
//! hand-written forward/backward passes ([`march`]) and sparse Adam
//! ([`optim`]), coarse to fine with pruning ([`trainer`]); then, optionally,
//! a dense feature grid distilled from teacher features ([`teacher`]).
//!
//! The forward pass is the function the reference renderer computes (same
//! samples, activation, interpolation and SH), so a trained model exported
//! with [`Model::to_field`] renders as it trained.

pub mod checkpoint;
pub mod grads;
pub mod march;
pub mod mining;
pub mod model;
pub mod optim;
pub mod pca;
pub mod plot;
pub mod rays;
pub mod session;
pub mod teacher;
pub mod trainer;
pub mod vit;
pub mod vm;

pub use grads::{GradBuf, GradLog};
pub use march::{MarchOpts, RayOut, Scratch};
pub use model::{DenseGrid, Model};
pub use rays::{default_bounds, RaySet};
pub use session::{
    default_teacher, default_teacher_shifts, preset, preset_for, preset_with, EvalReport, Quality, Session,
    DEFAULT_FEATURE_DIMS, DEFAULT_FEATURE_ITERS, ORBIT_TEACHER_SHIFTS,
};
pub use teacher::{default_cache_dir, teacher_features, FeatureMap, FeatureMaps, TeacherReport, TeacherSource};
pub use trainer::{psnr_of, step_of, StepStats, TrainConfig, Trainer};
