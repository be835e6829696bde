//! Evaluation. `metrics` holds the plain metric functions (no dependencies);
//! `protocol` runs the segmentation pipeline on demo scenes (ground-truth
//! label grids) and on data in the NVOS layout and scores it.

pub mod metrics;
pub mod protocol;

pub use metrics::{accuracy, average_precision, iou, iou3d, psnr, Confusion};
