//! One loader per capture layout. Each gathers views (camera, image file,
//! split) and hands them to [`finish`], which reads the images in parallel.

use super::{Dataset, DatasetKind, Image, LoadOptions, Split};
use crate::camera::{self, llff, CameraFrame, CameraSet};
use crate::error::{Error, Result};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

struct View {
    frame: CameraFrame,
    path: PathBuf,
    split: Split,
}

/// Everything a loader found besides its views.
#[derive(Default)]
struct Extras {
    notes: Vec<String>,
    /// Downscale already owed by the source (LLFF folder fallback).
    factor: u32,
    normalization: Option<glam::Affine3A>,
    near_far: Option<Vec<[f32; 2]>>,
}

fn wanted(opts: &LoadOptions, split: Split) -> bool {
    opts.splits.as_ref().is_none_or(|s| s.contains(&split))
}

/// The image file of frame `i` named `name` in the JSON/model `src`: the
/// path as written, then with `.png` appended.
fn image_path(dir: &Path, name: &str, i: usize, src: &Path) -> Result<PathBuf> {
    let [plain, png] = camera::set::image_candidates(dir, name);
    if plain.is_file() {
        return Ok(plain);
    }
    if png.is_file() {
        return Ok(png);
    }
    Err(Error::bad_file(
        &plain,
        format!(
            "missing image of frame {i} in {} (also tried {})",
            src.display(),
            png.display()
        ),
    ))
}

pub(super) fn blender(root: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let mut views = Vec::new();
    let mut extras = Extras::default();
    for split in Split::ALL.into_iter().filter(|&s| wanted(opts, s)) {
        let json = root.join(format!("transforms_{}.json", split.name()));
        if !json.is_file() && opts.splits.is_none() {
            continue;
        }
        // The placeholder size only reaches frames without `w`/`h` whose
        // image is absent, and those fail below for the missing image.
        let cams = CameraSet::load_with_size(&json, (1, 1))?;
        let paths: Vec<_> = cams
            .frames
            .iter()
            .enumerate()
            .map(|(i, f)| image_path(root, &f.name, i, &json))
            .collect();
        if opts.splits.is_none() && paths.iter().all(|p| p.is_err()) {
            extras.notes.push(format!(
                "{}: none of its {} images exist; {} split skipped",
                json.display(),
                paths.len(),
                split.name()
            ));
            continue;
        }
        for (frame, path) in cams.frames.into_iter().zip(paths) {
            views.push(View {
                frame,
                path: path?,
                split,
            });
        }
    }
    if views.is_empty() {
        return Err(Error::bad_file(
            root,
            "no views to load (no transforms_*.json with images)",
        ));
    }
    finish(DatasetKind::Blender, root, views, opts, extras)
}

/// The image folder to read for LLFF factor `n`: `images_n`, else the
/// largest existing `images_m` with m dividing n; returns (m, n / m).
fn llff_folder(root: &Path, n: u32) -> Result<(u32, u32)> {
    (1..=n)
        .rev()
        .find(|&m| n.is_multiple_of(m) && llff::image_dir(root, m).is_dir())
        .map(|m| (m, n / m))
        .ok_or_else(|| {
            Error::bad_file(
                llff::image_dir(root, n),
                format!("missing image folder (nor any images_M with M dividing {n})"),
            )
        })
}

pub(super) fn llff(root: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let (m, owed) = llff_folder(root, opts.llff_factor)?;
    let scene = llff::load_scene(
        root,
        &llff::LlffOptions {
            factor: m,
            ndc: opts.llff_ndc,
            ..Default::default()
        },
    )?;
    let folder = llff::image_dir(root, m);
    let files = llff::list_images(&folder)?;
    if files.len() != scene.cameras.len() {
        return Err(Error::bad_file(
            &folder,
            format!(
                "{} images but poses_bounds.npy has {} poses",
                files.len(),
                scene.cameras.len()
            ),
        ));
    }
    let mut extras = Extras {
        factor: owed,
        normalization: Some(scene.transform),
        near_far: Some(scene.bounds),
        ..Default::default()
    };
    if owed > 1 {
        extras.notes.push(format!(
            "{} is missing; downscaling {} by {owed}",
            llff::image_dir(root, opts.llff_factor).display(),
            folder.display()
        ));
    }
    let views = with_holdout(scene.cameras.frames.into_iter().zip(files), opts.holdout_every);
    finish(DatasetKind::Llff, root, views, opts, extras)
}

fn with_holdout(pairs: impl Iterator<Item = (CameraFrame, PathBuf)>, every: usize) -> Vec<View> {
    pairs
        .enumerate()
        .map(|(i, (frame, path))| View {
            frame,
            path,
            split: if every > 0 && i % every == 0 {
                Split::Test
            } else {
                Split::Train
            },
        })
        .collect()
}

pub(super) fn nerfstudio(root: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let json = root.join("transforms.json");
    let cams = CameraSet::load(&json)?;
    let pairs = cams
        .frames
        .into_iter()
        .enumerate()
        .map(|(i, f)| Ok((image_path(root, &f.name, i, &json)?, f)))
        .collect::<Result<Vec<_>>>()?;
    let views = with_holdout(pairs.into_iter().map(|(p, f)| (f, p)), opts.holdout_every);
    finish(DatasetKind::Nerfstudio, root, views, opts, Extras::default())
}

pub(super) fn colmap(root: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let cams = camera::colmap::load(root)?;
    let (_, images_file) = camera::colmap::find_model(root)?;
    let folder = root.join("images");
    let pairs = cams
        .frames
        .into_iter()
        .enumerate()
        .map(|(i, f)| Ok((image_path(&folder, &f.name, i, &images_file)?, f)))
        .collect::<Result<Vec<_>>>()?;
    let views = with_holdout(pairs.into_iter().map(|(p, f)| (f, p)), opts.holdout_every);
    finish(DatasetKind::Colmap, root, views, opts, Extras::default())
}

/// Keeps the wanted splits, reads the images in parallel (checking each
/// against its camera), composites, downscales images and cameras alike.
fn finish(kind: DatasetKind, root: &Path, views: Vec<View>, opts: &LoadOptions, extras: Extras) -> Result<Dataset> {
    let keep: Vec<usize> = (0..views.len()).filter(|&i| wanted(opts, views[i].split)).collect();
    let views: Vec<View> = {
        let mut all: Vec<Option<View>> = views.into_iter().map(Some).collect();
        keep.iter().filter_map(|&i| all[i].take()).collect()
    };
    if views.is_empty() {
        return Err(Error::bad_file(
            root,
            format!("no views in the requested splits {:?}", opts.splits),
        ));
    }
    let factor = extras.factor.max(1) * opts.downscale;
    let images = views
        .par_iter()
        .map(|v| {
            // The size is checked against the camera from the file's header,
            // before anything is decoded.
            let k = &v.frame.camera.intrinsics;
            if opts.deferred.contains(&v.split) {
                super::images::check_image(&v.path, Some((k.width, k.height)))?;
                return Ok(Image::deferred(k.width / factor, k.height / factor));
            }
            Image::load_view(&v.path, Some((k.width, k.height)), opts.background, factor)
        })
        .collect::<Result<Vec<_>>>()?;
    let near_far = extras
        .near_far
        .map(|nf| keep.iter().filter_map(|&i| nf.get(i).copied()).collect());
    Ok(Dataset {
        kind,
        root: root.to_path_buf(),
        cameras: CameraSet {
            frames: views
                .iter()
                .map(|v| CameraFrame {
                    name: v.frame.name.clone(),
                    camera: v.frame.camera.downscaled(factor),
                })
                .collect(),
        },
        image_paths: views.iter().map(|v| v.path.clone()).collect(),
        splits: views.iter().map(|v| v.split).collect(),
        images,
        background: opts.background,
        normalization: extras.normalization,
        near_far,
        notes: extras.notes,
        factor,
    })
}
