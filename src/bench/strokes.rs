//! Stroke-to-mask latency on a user's own field: the strokes of a stroke
//! document replayed with the default pipeline ([`MaskBuilder`], as the
//! editor and `isrf segment` run it), each stage's median over repeats.
//!
//! The demo benchmark ([`super::segment`]) selects a 37k-voxel pot; a real
//! capture's object is often a million voxels (lego at 320³), and that is
//! where the stages that scale with the object (growth, the graph cut) show.
//! One-off work per field (load, feature cache, the renderer's macro grid)
//! is timed apart: the editor pays it once when it opens the field.

use super::{load_average, median, peak_rss_bytes, process_cpu_ns, time_ms, Table};
use crate::error::Result;
use crate::field::{Bitmap, Field};
use crate::render::Scene;
use crate::segment::{MaskBuilder, SegmentParams, Stroke, Timings};
use std::sync::Arc;

/// Median figures of one stroke over the repeats.
#[derive(Clone, Debug)]
pub struct StrokeFigures {
    pub object: String,
    pub polarity: String,
    pub pixels: usize,
    /// Median per-stage times (each stage's own median).
    pub stages: Timings,
    /// Median wall time of the whole stroke (stages plus what the mask
    /// builder does after them: enclosed voxels, a negative's cut).
    pub wall_ms: f64,
    /// The fastest run's wall time: on a shared machine, whose speed
    /// drifts by ±15 % from run to run, the steadier figure to compare two
    /// builds by (the median is what a user meets).
    pub fastest_ms: f64,
    /// Median CPU time of all threads over the stroke.
    pub cpu_ms: Option<f64>,
    /// Voxels in the object's mask after the stroke (last run).
    pub mask_voxels: usize,
    pub runs: usize,
}

#[derive(Clone, Debug)]
pub struct FieldStrokeReport {
    pub threads: usize,
    pub load_average: Option<f64>,
    pub res: [usize; 3],
    pub cached_voxels: usize,
    pub channels: usize,
    pub cache_ms: f64,
    /// Making the coarse copy and the cut's neighbour table
    /// ([`crate::segment::prepare`]).
    pub coarse_ms: f64,
    pub macro_ms: f64,
    pub strokes: Vec<StrokeFigures>,
    pub peak_rss: Option<u64>,
}

impl FieldStrokeReport {
    /// The slowest stroke's median wall time.
    pub fn worst_ms(&self) -> f64 {
        self.strokes.iter().map(|s| s.wall_ms).fold(0.0, f64::max)
    }
}

/// Replays `strokes` (in order, each object's mask built from scratch per
/// run) `repeats` times on `field`.
pub fn bench_field_strokes(
    field: Arc<Field>,
    strokes: &[Stroke],
    p: &SegmentParams,
    repeats: usize,
) -> Result<FieldStrokeReport> {
    crate::ensure!(!strokes.is_empty(), "no strokes to replay");
    crate::ensure!((1..=1000).contains(&repeats), "repeats must be 1..=1000, got {repeats}");
    let load_average = load_average();
    let (cache, cache_ms) = time_ms(|| field.feature_cache());
    let cache = cache?;
    // The coarse copy and the cut's neighbour table are made once per
    // field too (a session's first stroke makes them with the cache).
    let (_, coarse_ms) = time_ms(|| crate::segment::prepare(&cache, p));
    let (_, macro_ms) = time_ms(|| field.macro_grid().occupied_fraction());
    let scene = Scene::single(field.clone());
    // runs[stroke]: one per repeat.
    let mut runs: Vec<Vec<Run>> = vec![vec![]; strokes.len()];
    for _ in 0..repeats {
        let mut builders: Vec<(String, MaskBuilder)> = vec![];
        for (i, s) in strokes.iter().enumerate() {
            let at = match builders.iter().position(|(o, _)| *o == s.object) {
                Some(at) => at,
                None => {
                    builders.push((s.object.clone(), MaskBuilder::new(Bitmap::new(field.res()))));
                    builders.len() - 1
                }
            };
            let b = &mut builders[at].1;
            let cpu0 = process_cpu_ns();
            let (t, ms) = time_ms(|| b.stroke(&scene, &cache, s, s.polarity, p));
            let t = t.map_err(|e| crate::Error::invalid(format!("stroke {i} ('{}'): {e}", s.object)))?;
            let cpu = cpu0
                .zip(process_cpu_ns())
                .map(|(a, b)| b.saturating_sub(a) as f64 / 1e6);
            runs[i].push(Run {
                t,
                wall_ms: ms,
                cpu_ms: cpu,
                voxels: b.mask.count(),
            });
        }
    }
    let strokes = strokes
        .iter()
        .zip(&runs)
        .map(|(s, r)| figures(s, r))
        .collect::<Result<Vec<_>>>()?;
    Ok(FieldStrokeReport {
        threads: rayon::current_num_threads(),
        load_average,
        res: field.res(),
        cached_voxels: cache.len(),
        channels: cache.channels,
        cache_ms,
        coarse_ms,
        macro_ms,
        strokes,
        peak_rss: peak_rss_bytes(),
    })
}

/// One replay of one stroke.
#[derive(Clone)]
struct Run {
    t: Timings,
    wall_ms: f64,
    cpu_ms: Option<f64>,
    /// The object's mask after the stroke.
    voxels: usize,
}

fn figures(s: &Stroke, runs: &[Run]) -> Result<StrokeFigures> {
    let med = |f: fn(&Timings) -> f64| median(&runs.iter().map(|r| f(&r.t)).collect::<Vec<_>>());
    let last = runs.last().expect("at least one run");
    let mut stages = last.t;
    stages.stroke_features_ms = med(|t| t.stroke_features_ms);
    stages.kmeans_ms = med(|t| t.kmeans_ms);
    stages.nnfm_ms = med(|t| t.nnfm_ms);
    stages.grow_ms = med(|t| t.grow_ms);
    stages.cut_ms = med(|t| t.cut_ms);
    stages.cut.edges_ms = med(|t| t.cut.edges_ms);
    stages.cut.fit_ms = med(|t| t.cut.fit_ms);
    stages.cut.distance_ms = med(|t| t.cut.distance_ms);
    stages.cut.flow_ms = med(|t| t.cut.flow_ms);
    let cpus: Option<Vec<f64>> = runs.iter().map(|r| r.cpu_ms).collect();
    Ok(StrokeFigures {
        object: s.object.clone(),
        polarity: format!("{:?}", s.polarity).to_lowercase(),
        pixels: crate::segment::stroke_pixels(s)?.len(),
        stages,
        wall_ms: median(&runs.iter().map(|r| r.wall_ms).collect::<Vec<_>>()),
        fastest_ms: runs.iter().map(|r| r.wall_ms).fold(f64::INFINITY, f64::min),
        cpu_ms: cpus.map(|c| median(&c)),
        mask_voxels: last.voxels,
        runs: runs.len(),
    })
}

/// One row per stroke: its stages' median ms, the whole stroke's wall and
/// CPU ms, and the mask after it.
pub fn field_stroke_table(r: &FieldStrokeReport) -> Table {
    let mut t = Table::new(&[
        "stroke",
        "object",
        "px",
        "features",
        "k-means",
        "nnfm",
        "growth",
        "cut",
        "stroke ms",
        "fastest",
        "cpu ms",
        "grid",
        "seeds",
        "region",
        "mask",
    ]);
    for (i, s) in r.strokes.iter().enumerate() {
        let g = &s.stages;
        t.row(vec![
            format!("{i} {}", s.polarity),
            s.object.clone(),
            s.pixels.to_string(),
            format!("{:.1}", g.stroke_features_ms),
            format!("{:.1}", g.kmeans_ms),
            format!("{:.1}", g.nnfm_ms),
            format!("{:.1}", g.grow_ms),
            format!("{:.1}", g.cut_ms),
            format!("{:.1}", s.wall_ms),
            format!("{:.1}", s.fastest_ms),
            s.cpu_ms.map_or_else(|| "-".into(), |c| format!("{c:.1}")),
            format!("{}×", g.grid),
            g.seed_voxels.to_string(),
            g.region_voxels.to_string(),
            s.mask_voxels.to_string(),
        ]);
    }
    t
}

/// One row per stroke: the graph cut's stages (median ms over the runs;
/// with a coarse grid, `cut` in the stroke table also maps the mask back).
pub fn cut_stage_table(r: &FieldStrokeReport) -> Table {
    let mut t = Table::new(&[
        "stroke",
        "rounds",
        "nodes",
        "pairs",
        "edges",
        "bg fit",
        "bg distances",
        "max-flow",
        "cut ms",
    ]);
    for (i, s) in r.strokes.iter().enumerate() {
        let c = &s.stages.cut;
        t.row(vec![
            format!("{i} {}", s.polarity),
            c.rounds.to_string(),
            c.nodes.to_string(),
            c.pairs.to_string(),
            format!("{:.1}", c.edges_ms),
            format!("{:.1}", c.fit_ms),
            format!("{:.1}", c.distance_ms),
            format!("{:.1}", c.flow_ms),
            format!("{:.1}", s.stages.cut_ms),
        ]);
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replayed_strokes_report_the_masks_the_builder_makes() {
        let demo = crate::demo::build("tabletop", 48, 0).unwrap();
        let strokes: Vec<Stroke> = ["pot", "mug"]
            .iter()
            .map(|o| crate::eval::protocol::demo_stroke(&demo, o).unwrap())
            .collect();
        let field = Arc::new(demo.field);
        let p = SegmentParams::default();
        let r = bench_field_strokes(field.clone(), &strokes, &p, 2).unwrap();
        assert_eq!(r.strokes.len(), 2);
        assert_eq!(r.cached_voxels, field.feature_cache().unwrap().len());
        // Each object's mask as the builder makes it on its own.
        let scene = Scene::single(field.clone());
        let cache = field.feature_cache().unwrap();
        for (s, f) in strokes.iter().zip(&r.strokes) {
            let mut b = MaskBuilder::new(Bitmap::new(field.res()));
            b.stroke(&scene, &cache, s, s.polarity, &p).unwrap();
            assert!(b.mask.count() > 0);
            assert_eq!(f.mask_voxels, b.mask.count(), "{}", s.object);
            assert_eq!((f.runs, f.object.as_str()), (2, s.object.as_str()));
            assert!(f.wall_ms >= f.stages.stroke_features_ms && f.stages.region_voxels > 0);
            // The cut ran, and says how many rounds.
            assert!(f.stages.cut.rounds >= 1, "{}", s.object);
        }
        assert!(r.worst_ms() >= r.strokes[0].wall_ms);
        // Nothing to replay, or no runs: an error, not a panic.
        assert!(bench_field_strokes(field.clone(), &[], &p, 2).is_err());
        assert!(bench_field_strokes(field, &strokes, &p, 0).is_err());
    }
}
