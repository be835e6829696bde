//! isrf: interactive segmentation and editing of radiance fields.
//!
//! Module map (see DESIGN.md): `field` (grids, sampling, files), `camera`
//! (pinhole cameras, rays, camera sets), `render` (CPU reference renderer),
//! `segment` (strokes → mask), `edit`, `command`, `data`, `train`, `eval`,
//! `demo` (procedural scenes), `app` (the bevy editor).

pub mod camera;
pub mod error;
pub mod field;

pub use error::{Error, Result};
