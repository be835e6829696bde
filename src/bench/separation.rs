//! Does the teacher itself tell an object from its neighbours?
//!
//! `isrf bench quality --diagnose` asks this of the teacher's own maps (the
//! PCA'd tokens the field is distilled from), before any field, growth or
//! cut: every map cell of every training view takes the true label of the
//! first surface its centre pixel sees, and each object's cells are
//! compared with every label's mean feature. The same question asked of
//! the distilled field ([`field_separation`]: every seen voxel with its
//! true label) often has a better answer, since a voxel's feature averages
//! many views: on the realistic shelf the maps put 31 % of the excavator's
//! cells nearer the jar's mean, the field 7 % of its voxels. When the
//! field parts two objects and a stroke's selection does not, the failure
//! is the segmentation's, not the teacher's.

use crate::camera::Camera;
use crate::demo::{self, Labels};
use crate::field::{DensityGrid, FeatureCache};
use crate::train::FeatureMaps;
use rayon::prelude::*;
use serde::Serialize;

/// One label's cells against every label's mean (squared L2 distances
/// between unit-length features, so within 0..=4).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Separation {
    pub label: u8,
    pub cells: usize,
    /// Mean squared distance of the label's cells to their own mean.
    pub spread: f64,
    /// The other label whose mean is nearest the label's cells on average.
    pub nearest: u8,
    /// Mean squared distance of the label's cells to that label's mean.
    pub to_nearest: f64,
    /// Share of the label's cells nearer another label's mean than their own.
    pub confused: f64,
}

/// [`Separation`] of every label present in `labels` (one per cell). The
/// cells' features are `blocks` read one after the other, `channels` values
/// per cell (the maps' own buffers, not copied), normalised here. Label 0
/// (nothing, or the background) takes part as a neighbour, not as a row.
pub fn separation(labels: &[u8], blocks: &[&[f32]], channels: usize) -> Vec<Separation> {
    let total: usize = blocks.iter().map(|b| b.len()).sum();
    assert_eq!(total, labels.len() * channels, "one feature vector per label");
    let cells = || {
        blocks.iter().flat_map(|b| b.chunks_exact(channels)).map(|f| {
            let n = f.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            f.iter().map(move |v| (v / n) as f64)
        })
    };
    let mut sums = vec![vec![0.0f64; channels]; 256];
    let mut counts = [0usize; 256];
    for (&l, f) in labels.iter().zip(cells()) {
        counts[l as usize] += 1;
        for (s, v) in sums[l as usize].iter_mut().zip(f) {
            *s += v;
        }
    }
    let present: Vec<u8> = (0..=255u8).filter(|&l| counts[l as usize] > 0).collect();
    let means: Vec<Vec<f64>> = present
        .iter()
        .map(|&l| sums[l as usize].iter().map(|s| s / counts[l as usize] as f64).collect())
        .collect();
    // to[a][b]: summed squared distance of label a's cells to label b's mean.
    let k = present.len();
    let mut to = vec![vec![0.0f64; k]; k];
    let mut confused = vec![0usize; k];
    let mut d = vec![0.0f64; k];
    for (&l, f) in labels.iter().zip(cells()) {
        let a = present.binary_search(&l).expect("label was counted");
        d.fill(0.0);
        for (c, v) in f.enumerate() {
            for (db, m) in d.iter_mut().zip(&means) {
                *db += (v - m[c]).powi(2);
            }
        }
        if d.iter().enumerate().any(|(b, &db)| b != a && db < d[a]) {
            confused[a] += 1;
        }
        for (t, db) in to[a].iter_mut().zip(&d) {
            *t += db;
        }
    }
    (0..k)
        .filter(|&a| present[a] != 0)
        .filter_map(|a| {
            let n = counts[present[a] as usize] as f64;
            let (b, dist) = (0..k)
                .filter(|&b| b != a)
                .map(|b| (b, to[a][b] / n))
                .min_by(|x, y| x.1.total_cmp(&y.1))?;
            Some(Separation {
                label: present[a],
                cells: n as usize,
                spread: to[a][a] / n,
                nearest: present[b],
                to_nearest: dist,
                confused: confused[a] as f64 / n,
            })
        })
        .collect()
}

/// The true label of every map cell of `maps` (of the training views
/// `cameras`, [`FeatureMaps::view_of`]): that of the first surface `truth`
/// shows at the cell's centre pixel ([`demo::strokes::surface_at`]), 0
/// where none.
pub fn cell_labels(maps: &FeatureMaps, cameras: &[Camera], truth: &DensityGrid, labels: &Labels) -> Vec<u8> {
    maps.maps
        .par_iter()
        .enumerate()
        .flat_map_iter(|(k, m)| {
            let camera = &cameras[maps.view_of(k)];
            let (sx, sy) = (
                m.image_width as f32 / m.width as f32,
                m.image_height as f32 / m.height as f32,
            );
            (0..m.height).flat_map(move |y| {
                (0..m.width).map(move |x| {
                    let px = (((x as f32 + 0.5) * sx) as u32).min(camera.intrinsics.width - 1);
                    let py = (((y as f32 + 0.5) * sy) as u32).min(camera.intrinsics.height - 1);
                    demo::strokes::surface_at(camera, truth, labels, px, py).map_or(0, |(_, l)| l)
                })
            })
        })
        .collect()
}

/// [`separation`] of the teacher's maps of the training views `cameras`.
pub fn teacher_separation(
    maps: &FeatureMaps,
    cameras: &[Camera],
    truth: &DensityGrid,
    labels: &Labels,
) -> Vec<Separation> {
    let cell_label = cell_labels(maps, cameras, truth, labels);
    let blocks: Vec<&[f32]> = maps.maps.iter().map(|m| m.data.as_slice()).collect();
    separation(&cell_label, &blocks, maps.channels)
}

/// [`separation`] of a distilled field's features: `voxels` (grid
/// indices) with their true `labels`, those without features left out.
/// The cache's rows are read in place, one block per voxel.
pub fn field_separation(cache: &FeatureCache, voxels: &[u32], labels: &[u8]) -> Vec<Separation> {
    let (kept, rows): (Vec<u8>, Vec<&[f32]>) = voxels
        .iter()
        .zip(labels)
        .filter_map(|(&v, &l)| cache.index.slot(v as usize).map(|r| (l, r)))
        .filter(|&(_, r)| cache.inv_norm[r] > 0.0)
        .map(|(l, r)| (l, cache.row(r)))
        .unzip();
    separation(&kept, &rows, cache.channels)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_answer_for_two_labels_one_half_confused() {
        // Label 1: two cells at x. Label 2: one cell at y, one at x (its
        // mean is (0.5, 0.5)). Label 0 is not a row but a neighbour.
        let labels = [1, 1, 2, 2, 0];
        // Two blocks, as two views' maps.
        let (view_a, view_b) = ([2.0, 0.0, 1.0, 0.0, 0.0, 3.0], [5.0, 0.0, -1.0, 0.0]);
        let s = separation(&labels, &[&view_a, &view_b], 2);
        assert_eq!(s.len(), 2);
        assert_eq!((s[0].label, s[0].cells, s[0].nearest), (1, 2, 2));
        assert!((s[0].spread - 0.0).abs() < 1e-9);
        // ‖(1,0) − (0.5,0.5)‖² = 0.5; the cells are on label 1's mean.
        assert!((s[0].to_nearest - 0.5).abs() < 1e-9);
        assert_eq!(s[0].confused, 0.0);
        // Label 2: each cell 0.5 from its mean; the x cell sits on label 1's.
        assert_eq!((s[1].label, s[1].nearest), (2, 1));
        assert!((s[1].spread - 0.5).abs() < 1e-9);
        // To (1,0): the y cell at 2, the x cell at 0.
        assert!((s[1].to_nearest - 1.0).abs() < 1e-9);
        assert!((s[1].confused - 0.5).abs() < 1e-9);
    }

    /// Known answer on a field: voxels 0–1 of label 1 along x, voxels
    /// 2–3 of label 2 along y, voxel 4 of label 2 along x (so label 2's
    /// mean is off both axes and that voxel is nearer label 1's), voxel 5
    /// with no features (left out), and voxel 6 unoccupied (left out);
    /// the features' lengths do not matter.
    #[test]
    fn a_fields_voxels_are_compared_by_their_unit_features() {
        use crate::field::{Aabb, Bitmap, GridGeom, RankIndex};
        use glam::Vec3;
        let geom = GridGeom::new(Aabb::new(Vec3::ZERO, Vec3::new(8.0, 1.0, 1.0)), [8, 1, 1]);
        let occupied = Bitmap::from_fn(geom.res, |v| v < 6);
        let feats = vec![2.0, 0.0, 0.5, 0.0, 0.0, 3.0, 0.0, 1.0, 4.0, 0.0, 0.0, 0.0];
        let colours = vec![Vec3::ZERO; 6];
        let cache = FeatureCache::from_parts(
            geom,
            2,
            1.0,
            (0..6).collect(),
            RankIndex::new(occupied),
            vec![1.0; 6],
            feats,
            colours,
        );
        let s = field_separation(&cache, &[0, 1, 2, 3, 4, 5, 6], &[1, 1, 2, 2, 2, 1, 2]);
        assert_eq!(s.len(), 2);
        assert_eq!((s[0].label, s[0].cells, s[0].nearest), (1, 2, 2));
        assert_eq!(s[0].confused, 0.0);
        // Label 2's mean is (1/3, 2/3): its y voxels are 1/9 + 1/9 from
        // it, its x voxel 4/9 + 4/9, and that one sits on label 1's mean.
        assert_eq!((s[1].label, s[1].cells, s[1].nearest), (2, 3, 1));
        assert!((s[1].spread - (2.0 / 9.0 + 2.0 / 9.0 + 8.0 / 9.0) / 3.0).abs() < 1e-9);
        assert!((s[1].confused - 1.0 / 3.0).abs() < 1e-9);
    }

    #[test]
    fn the_demo_shelf_labels_its_objects_in_map_cells() {
        let scene = demo::build("shelf", 64, 0).unwrap();
        let cameras: Vec<Camera> = scene.cameras.frames.iter().take(2).map(|f| f.camera).collect();
        let (w, h) = (cameras[0].intrinsics.width, cameras[0].intrinsics.height);
        let map = |_| crate::train::teacher::FeatureMap {
            width: 40,
            height: 30,
            image_width: w,
            image_height: h,
            data: vec![1.0; 40 * 30],
        };
        let maps = FeatureMaps::new(1, (0..2).map(map).collect()).unwrap();
        let l = cell_labels(&maps, &cameras, &scene.field.density, &scene.labels);
        assert_eq!(l.len(), 2 * 40 * 30);
        // The orbit sees the shelf and the background around it.
        let shelf = scene.objects.iter().find(|o| o.name == "shelf").unwrap().label;
        assert!(l.contains(&0) && l.contains(&shelf));
    }
}
