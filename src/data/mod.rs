//! Datasets: posed images for training and evaluation.
//!
//! Four capture layouts are read (see [`DatasetKind`]); [`Dataset::detect`]
//! tells them apart from a folder's contents and [`Dataset::load`] reads
//! cameras and images (in parallel) into one [`Dataset`] whose cameras match
//! its images' resolution.

mod images;
mod loaders;

pub use images::{open_image, Image, MAX_IMAGE_PIXELS};

use crate::camera::CameraSet;
use crate::error::{Error, Result};
use glam::Affine3A;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Which part of a dataset a view belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    pub const ALL: [Split; 3] = [Split::Train, Split::Val, Split::Test];
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        }
    }
}

/// Capture layouts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum DatasetKind {
    /// NeRF-synthetic: `transforms_{train,val,test}.json`, RGBA renders.
    Blender,
    /// `poses_bounds.npy` + `images_N/` (forward-facing; NDC by default).
    Llff,
    /// nerfstudio: one `transforms.json` naming its images.
    Nerfstudio,
    /// COLMAP model (`sparse/0/{cameras,images}.{bin,txt}`) + `images/`.
    Colmap,
}

/// How to load a dataset. The default suits every kind.
#[derive(Clone, Debug, PartialEq)]
pub struct LoadOptions {
    /// Extra box-filter downscale applied on load (1 = as stored).
    pub downscale: u32,
    /// Colour put behind transparent pixels (NeRF-synthetic uses white).
    pub background: [f32; 3],
    /// Splits to load. `None`: every split the dataset has; a Blender split
    /// whose images are all absent (the NeRF-synthetic test set is often
    /// shipped without them) is then skipped with a note. Naming a split
    /// makes its missing images an error.
    pub splits: Option<Vec<Split>>,
    /// LLFF: read `images_N` for this N (NeRF's `--factor`). When that folder
    /// is missing, a folder `images_M` with M dividing N is box-downscaled.
    pub llff_factor: u32,
    /// LLFF, nerfstudio and COLMAP: views with index % n == 0 are test views
    /// (NeRF's `llffhold`); 0 = all train.
    pub holdout_every: usize,
    /// LLFF: NDC rays (the default for forward-facing scenes).
    pub llff_ndc: bool,
    /// Splits whose pixels are not decoded at load (their sizes are checked
    /// from the files' headers): [`Dataset::pixels`] reads them when they
    /// are needed. Training defers its held-out views, which are only
    /// scored now and then: lego's 100 val views at 800×800 are 1 GB of f32.
    pub deferred: Vec<Split>,
}

impl Default for LoadOptions {
    fn default() -> Self {
        LoadOptions {
            downscale: 1,
            background: [1.0; 3],
            splits: None,
            llff_factor: 8,
            holdout_every: 8,
            llff_ndc: true,
            deferred: vec![],
        }
    }
}

/// Posed images. `cameras.frames[i]`, `images[i]`, `image_paths[i]` and
/// `splits[i]` describe view i; each camera's size equals its image's.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub kind: DatasetKind,
    /// The dataset folder.
    pub root: PathBuf,
    pub cameras: CameraSet,
    /// Colours composited over `background` where the file had alpha.
    pub images: Vec<Image>,
    pub image_paths: Vec<PathBuf>,
    pub splits: Vec<Split>,
    pub background: [f32; 3],
    /// LLFF: capture world → normalised world (scale, then recentring).
    pub normalization: Option<Affine3A>,
    /// LLFF: near/far bounds per view in the normalised world.
    pub near_far: Option<Vec<[f32; 2]>>,
    /// Things worth telling a user (skipped splits, fallbacks taken).
    pub notes: Vec<String>,
    /// Downscale from the files to `images` (for deferred views).
    pub factor: u32,
}

impl Dataset {
    /// View `i`'s image, read from its file now if its split was deferred
    /// ([`LoadOptions::deferred`]); composited and downscaled as at load.
    pub fn pixels(&self, i: usize) -> Result<std::borrow::Cow<'_, Image>> {
        let img = &self.images[i];
        if !img.is_deferred() {
            return Ok(std::borrow::Cow::Borrowed(img));
        }
        // The file's size was checked against the camera at load.
        let out = Image::load_view(&self.image_paths[i], None, self.background, self.factor)?;
        crate::ensure!(
            (out.width, out.height) == (img.width, img.height),
            "{}: image is {}×{} after downscaling, {}×{} at load",
            self.image_paths[i].display(),
            out.width,
            out.height,
            img.width,
            img.height
        );
        Ok(std::borrow::Cow::Owned(out))
    }
    /// The kind of dataset at `path`: a folder, or one of its marker files
    /// (`transforms_*.json`, `transforms.json`, `poses_bounds.npy`).
    pub fn detect(path: &Path) -> Result<DatasetKind> {
        Ok(resolve(path)?.0)
    }

    /// Detects the kind and loads.
    pub fn load(path: &Path, opts: &LoadOptions) -> Result<Dataset> {
        let (kind, root) = resolve(path)?;
        Self::load_kind(kind, &root, opts)
    }

    /// Loads the dataset folder `root` as `kind`.
    pub fn load_kind(kind: DatasetKind, root: &Path, opts: &LoadOptions) -> Result<Dataset> {
        crate::ensure!(opts.downscale >= 1, "downscale must be ≥ 1");
        crate::ensure!(opts.llff_factor >= 1, "LLFF factor must be ≥ 1");
        crate::ensure!(
            opts.background.iter().all(|c| c.is_finite()),
            "background colour must be finite"
        );
        match kind {
            DatasetKind::Blender => loaders::blender(root, opts),
            DatasetKind::Llff => loaders::llff(root, opts),
            DatasetKind::Nerfstudio => loaders::nerfstudio(root, opts),
            DatasetKind::Colmap => loaders::colmap(root, opts),
        }
    }

    pub fn len(&self) -> usize {
        self.images.len()
    }
    pub fn is_empty(&self) -> bool {
        self.images.is_empty()
    }

    /// Indices of the views in `split`.
    pub fn indices(&self, split: Split) -> Vec<usize> {
        (0..self.splits.len()).filter(|&i| self.splits[i] == split).collect()
    }
}

/// (kind, dataset folder) for a folder or marker file.
fn resolve(path: &Path) -> Result<(DatasetKind, PathBuf)> {
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    if meta.is_file() {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let root = path.parent().map(Path::to_path_buf).unwrap_or_default();
        let kind = match name.as_str() {
            "transforms.json" => DatasetKind::Nerfstudio,
            "poses_bounds.npy" => DatasetKind::Llff,
            n if n.starts_with("transforms_") && n.ends_with(".json") => DatasetKind::Blender,
            _ => return Err(Error::bad_file(
                path,
                "not a dataset marker file (expected a folder, transforms.json, transforms_*.json or poses_bounds.npy)",
            )),
        };
        return Ok((kind, root));
    }
    let has = |p: &str| path.join(p).is_file();
    let kind = if Split::ALL.iter().any(|s| has(&format!("transforms_{}.json", s.name()))) {
        DatasetKind::Blender
    } else if has("transforms.json") {
        DatasetKind::Nerfstudio
    } else if has("poses_bounds.npy") {
        DatasetKind::Llff
    } else if ["sparse/0/", "sparse/", ""]
        .iter()
        .any(|d| has(&format!("{d}cameras.bin")) || has(&format!("{d}cameras.txt")))
    {
        DatasetKind::Colmap
    } else {
        return Err(Error::bad_file(
            path,
            "unrecognised dataset folder: found none of transforms_{train,val,test}.json (Blender), \
             transforms.json (nerfstudio), poses_bounds.npy (LLFF), sparse/0/cameras.{bin,txt} (COLMAP)",
        ));
    };
    Ok((kind, path.to_path_buf()))
}
