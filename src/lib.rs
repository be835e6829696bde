//! isrf: interactive segmentation and editing of radiance fields.
//!
//! Module map (see DESIGN.md): `field` (grids, sampling, files), `camera`
//! (pinhole cameras, rays, camera sets), `render` (CPU reference renderer),
//! `segment` (strokes → mask), `edit`, `command`, `data`, `train`, `eval`,
//! `demo` (procedural scenes), `app` (the bevy editor).

#[cfg(feature = "editor")]
pub mod app;
pub mod bench;
pub mod camera;
pub mod command;
pub mod data;
pub mod demo;
pub mod edit;
pub mod error;
pub mod eval;
pub mod field;
pub mod fuzz;
pub mod heap;
pub mod lift;
pub mod limits;
pub mod npy;
pub mod render;
pub mod segment;
pub mod splat;
pub mod train;
pub mod util;

pub use error::{Error, Result};
