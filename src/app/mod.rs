//! The bevy editor (`isrf edit`, feature `editor`) and the GPU ray marcher.
//!
//! - [`gpu`]: the custom render pass (`shaders/raymarch.wgsl`) that draws a
//!   `render::Scene` into bevy cameras, computing the CPU reference
//!   renderer's function; [`gpu::pack`] packs scenes into GPU arrays.
//! - [`headless`]: window-less GPU rendering (`render_headless`).
//! - [`convert`]: library ↔ bevy maths and cameras.

pub mod convert;
pub mod editor;
pub mod gpu;
pub mod headless;
pub mod layers;

pub use gpu::{MarchScene, RayMarchCamera, RayMarchPlugin};
pub use headless::{render_headless, HeadlessRenderer};
