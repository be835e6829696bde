//! The default growth: a region chosen where it is most stable.
//!
//! Growth with a fixed hysteresis threshold θ_grow (grow from the seeds
//! through solid voxels whose NNFM distance d is below θ_grow) cannot suit
//! every scene: an isolated object made of unlike parts (lego's yellow body,
//! grey tracks) needs a loose θ_grow, a plant among plants (the fern in its
//! planter) a tight one. Like MSER regions in images, the object is the
//! region that changes least when the threshold moves:
//!
//! - b(v), the bottleneck distance of a solid voxel v: the smallest t such
//!   that v is joined to a seed through 26-connected solid voxels that all
//!   have d ≤ t (seeds: b = d). One priority flood from the seeds computes
//!   it for every voxel with b ≤ t_max, in increasing order of b, so the
//!   region R(t) = {b ≤ t} is known for every t at once.
//! - The chosen threshold t* ∈ [θ + δ, t_max − δ] minimises the relative
//!   growth (|R(t + δ)| − |R(t − δ)|) / |R(t)|, the smallest such t on ties:
//!   past the object's boundary the region either stops growing (nothing
//!   else is there) or floods into the next object.
//! - If even the most stable threshold lets the region grow by more than
//!   `max_growth` over the window, there is no boundary to grow to: the
//!   region creeps steadily through the blur of a real capture's field (the
//!   fern: 3–4 % per 0.1 from θ up to the flood into the planter at 1.4),
//!   and the seeds are kept as they are.
//!
//! d comes from the stroke's NNFM pass ([`StrokeDistances`]), which measures
//! every solid voxel for this rule; the others are measured when the flood
//! first touches them.

use super::grow::{GrowParams, Offsets};
use super::nnfm::StrokeDistances;
use crate::field::runs::Runs;
use crate::field::{Bitmap, FeatureCache};
use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// Settings of the stable-region search (squared distances between unit
/// features, in [0, 4]).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct StableParams {
    /// The flood stops at this bottleneck distance.
    pub t_max: f32,
    /// Half-width of the window over which growth is measured.
    pub delta: f32,
    /// Spacing of the thresholds tried.
    pub step: f32,
    /// Largest relative growth over ±δ that still counts as stable.
    pub max_growth: f32,
    /// A relative growth over ±δ above this (the region grows by half) is a
    /// flood into another object.
    pub flood_growth: f32,
}

impl Default for StableParams {
    fn default() -> Self {
        StableParams {
            t_max: 1.5,
            delta: 0.1,
            step: 0.02,
            max_growth: 0.02,
            flood_growth: 0.5,
        }
    }
}

/// The stable region grown from `seed` and the threshold chosen.
#[derive(Clone, Debug)]
pub struct StableRegion {
    pub region: Bitmap,
    pub threshold: f32,
    /// Every voxel the flood reached (bottleneck distance ≤ `t_max`),
    /// ascending.
    pub reached: Vec<u32>,
    /// Where the flood ran into something else ([`flood_level`]): the
    /// voxels reached before that and the band of [`BAND`] voxels past
    /// them.
    pub before_flood: Option<Bitmap>,
    /// The voxels the priority flood put in order before the region and
    /// its threshold were settled (the rest of `reached` needs no order).
    pub flooded: usize,
}

/// Voxels past where the flood ran into something else that stay within
/// the graph cut's reach ([`StableRegion::reached`]), in 26-neighbour steps
/// through voxels the flood reached.
///
/// Why the cut need not see the rest: the flood goes on to `t_max`, and
/// once it runs into the table or the floor under a mug it takes most of
/// the scene (the realistic benchmark's tabletop: 260–340k of its 493k
/// voxels for every stroke, against regions of 350–16,000 voxels, and a
/// cut over all of them cost each stroke 280–460 ms). What the cut does
/// past that level is move the boundary by a few voxels: a band of the
/// other object is enough to cut against, and what lies beyond it could
/// only join through the band.
pub const BAND: usize = 4;

/// Bottleneck distances, in flood order: `(b, voxel)` pairs with
/// non-decreasing b, from the seeds through the voxels of `open`
/// ([`passable`]), until `settled` says the keys so far decide everything
/// asked of them (it is shown each key before it is ordered, and the keys
/// ordered so far) or the flood has nowhere left to go.
fn flood(
    cache: &FeatureCache,
    dist: &mut StrokeDistances,
    seed: &Bitmap,
    mut open: Bitmap,
    t_max: f32,
    mut settled: impl FnMut(f32, &[(f32, u32)]) -> bool,
) -> Vec<(f32, u32)> {
    // The grower's 3×3×3 neighbourhood (its spatial weights are unused).
    let offs = Offsets::new(cache.geom.res, &GrowParams::default());
    let mut queue = BucketQueue::new(t_max);
    for v in seed.ones() {
        if let Some(r) = cache.index.slot(v) {
            open.set(v, false);
            queue.push(dist.get(cache, r), v as u32);
        }
    }
    let mut order = Vec::new();
    // Voxels whose key equals the level being flooded: a neighbour no
    // farther than the current bottleneck gets exactly that key, so it is
    // flooded now, without a trip through the queue (inside an object most
    // voxels are; the order among equal keys changes nothing).
    let mut level: Vec<u32> = vec![];
    let mut hood = [0usize; 27];
    while let Some((b, v)) = queue.pop() {
        if settled(b, &order) {
            break;
        }
        level.push(v);
        while let Some(v) = level.pop() {
            order.push((b, v));
            let count = offs.fill(v as usize, &mut hood);
            for &n in &hood[..count] {
                if !open.get(n) {
                    continue;
                }
                open.set(n, false);
                let r = cache.index.slot(n).expect("solid voxels are cached");
                // Keys never decrease along the flood, so the first touch
                // gives n its bottleneck distance.
                let d = dist.get(cache, r);
                if d <= b {
                    level.push(n as u32);
                } else {
                    queue.push(d, n as u32);
                }
            }
        }
    }
    order
}

/// The voxels a flood from `seed` may pass through: the solid ones with
/// d ≤ `t_max`, and the seeds within it; with the seeds in it, to start
/// from.
fn passable(
    cache: &FeatureCache,
    dist: &mut StrokeDistances,
    seed: &Bitmap,
    floor: f32,
    t_max: f32,
) -> (Bitmap, Vec<usize>) {
    let mut within = dist.solid_within(cache, floor, t_max);
    let mut starts = vec![];
    for v in seed.ones() {
        if let Some(r) = cache.index.slot(v) {
            if dist.get(cache, r) <= t_max {
                within.set(v, true);
                starts.push(v);
            }
        }
    }
    (within, starts)
}

/// Every voxel the flood from the seeds `starts` reaches by the end
/// (b ≤ `t_max`) when it stopped before: the 26-connected components of
/// the [`passable`] voxels that hold a seed (a voxel's bottleneck distance
/// is at most `t_max` exactly when such a path joins it to a seed). Found
/// over runs of voxels, not by flooding them in order: the region and
/// threshold need the order only up to where the region runs into
/// something else, the graph cut's domain needs all of them (the
/// realistic tabletop's strokes: 260–340k of its 493k voxels).
fn reach(passable: &Bitmap, starts: Vec<usize>) -> Bitmap {
    Runs::of(passable).components_of(starts)
}

/// Says when the flood's keys so far settle [`stable_threshold`] and
/// [`flood_level`]: both look at the thresholds from θ + δ up, each
/// through the counts of keys up to t + δ, and stop at the first that
/// grows past `flood_growth` (the threshold's search) or jumps (the
/// flood level). Once the flood's next key is past t + δ for such a t
/// (for both), the keys so far give both the answers all keys would.
struct Settles<'a> {
    /// The thresholds not looked at yet.
    thresholds: std::iter::Peekable<Box<dyn Iterator<Item = f32> + 'a>>,
    theta_searched: bool,
    level_found: bool,
    p: &'a StableParams,
}

impl<'a> Settles<'a> {
    fn new(theta: f32, p: &'a StableParams) -> Self {
        let thresholds: Box<dyn Iterator<Item = f32> + 'a> = Box::new(thresholds(theta, p));
        Settles {
            thresholds: thresholds.peekable(),
            theta_searched: false,
            level_found: false,
            p,
        }
    }
    /// Whether both are settled (the flood stops there, before its end).
    fn both(&self) -> bool {
        self.theta_searched && self.level_found
    }
    /// Whether the keys of `order` (every key below `key`) settle both.
    fn settled(&mut self, key: f32, order: &[(f32, u32)]) -> bool {
        let count = |t: f32| order.partition_point(|o| o.0 <= t) as f32;
        let delta = self.p.delta;
        while let Some(t) = self.thresholds.next_if(|&t| t + delta < key) {
            let w = window(count, t, self.p);
            self.theta_searched |= w.growth > self.p.flood_growth;
            self.level_found |= w.jumps;
            if self.both() {
                return true;
            }
        }
        false
    }
}

/// The region's growth around one threshold t ([`window`]).
struct Window {
    /// (|R(t + δ)| − |R(t − δ)|) / |R(t)|.
    growth: f32,
    /// |R(t + δ)| > [`FLOOD_JUMP`] · |R(t − δ)|: a flood into something else.
    jumps: bool,
}

/// [`Window`] at `t`, `count(t)` being |R(t)|.
fn window(count: impl Fn(f32) -> f32, t: f32, p: &StableParams) -> Window {
    let (below, above) = (count(t - p.delta), count(t + p.delta));
    Window {
        growth: (above - below) / count(t).max(1.0),
        jumps: above > FLOOD_JUMP * below.max(1.0),
    }
}

/// A monotone priority queue of voxels keyed by distances in [0, `t_max`]
/// (keys above it are dropped: the flood stops there): the key range cut
/// into [`BUCKETS`] buckets, the bucket being flooded kept as a binary heap,
/// later ones as plain lists. A key pushed is never below the last popped
/// (the flood's keys never decrease), so it lands in the current bucket or
/// a later one. Pops come out in the exact order of one binary heap over
/// everything, but each costs a sift through the current bucket's few
/// thousand voxels rather than through the whole flood's (on lego's
/// strokes 160k seeds: the heap's pops were a third of the flood's time).
struct BucketQueue {
    scale: f32,
    t_max: f32,
    current: usize,
    heap: BinaryHeap<Reverse<(u32, u32)>>,
    later: Vec<Vec<(u32, u32)>>,
}

/// Buckets across the flood's key range (0.0015 wide at `t_max` 1.5).
const BUCKETS: usize = 1024;

impl BucketQueue {
    fn new(t_max: f32) -> Self {
        BucketQueue {
            scale: BUCKETS as f32 / t_max.max(f32::MIN_POSITIVE),
            t_max,
            current: 0,
            heap: BinaryHeap::new(),
            later: vec![vec![]; BUCKETS],
        }
    }
    /// Non-decreasing in `key`, so the buckets keep the keys' order.
    fn bucket(&self, key: f32) -> usize {
        ((key * self.scale) as usize).min(BUCKETS - 1)
    }
    /// Queues voxel `v` at distance `key` (≥ 0; f32 keys ≥ 0 order like
    /// their bits), unless it is past `t_max`.
    fn push(&mut self, key: f32, v: u32) {
        if key.is_nan() || key > self.t_max {
            return;
        }
        // -0.0 would order after every positive key.
        let key = key.max(0.0) + 0.0;
        let b = self.bucket(key);
        debug_assert!(b >= self.current, "keys pushed never go below the last popped");
        if b <= self.current {
            self.heap.push(Reverse((key.to_bits(), v)));
        } else {
            self.later[b].push((key.to_bits(), v));
        }
    }
    /// The voxel with the smallest key, and that key.
    fn pop(&mut self) -> Option<(f32, u32)> {
        loop {
            if let Some(Reverse((key, v))) = self.heap.pop() {
                return Some((f32::from_bits(key), v));
            }
            let next = (self.current + 1..BUCKETS).find(|&b| !self.later[b].is_empty())?;
            self.current = next;
            // Heapify (linear), reusing the empty heap's buffer.
            let mut buf = std::mem::take(&mut self.heap).into_vec();
            buf.extend(std::mem::take(&mut self.later[next]).into_iter().map(Reverse));
            self.heap = BinaryHeap::from(buf);
        }
    }
}

/// The threshold at which the region's relative growth over ±δ is smallest,
/// or θ when no threshold is stable (module docs); `keys` are the flood's
/// bottleneck distances, sorted.
pub fn stable_threshold(keys: &[f32], theta: f32, p: &StableParams) -> f32 {
    let count = |t: f32| count_within(keys, t);
    let (lo, hi) = (theta + p.delta, p.t_max - p.delta);
    let mut best = (f32::INFINITY, lo.min(hi).max(theta));
    for t in thresholds(theta, p) {
        let growth = window(count, t, p).growth;
        if growth > p.flood_growth {
            break;
        }
        // Strictly smaller only: ties keep the smallest threshold.
        if growth < best.0 - 1e-4 {
            best = (growth, t);
        }
    }
    if best.0 > p.max_growth {
        return theta;
    }
    best.1
}

/// The last bottleneck distance before the flood runs into something
/// else: the first threshold t past θ whose region, over the next ±δ,
/// grows more than [`FLOOD_JUMP`] times; `None` when it never does.
pub fn flood_level(keys: &[f32], theta: f32, p: &StableParams) -> Option<f32> {
    let count = |t: f32| count_within(keys, t);
    thresholds(theta, p)
        .find(|&t| window(count, t, p).jumps)
        // The jump lies within the last step before t + δ.
        .map(|t| t + p.delta - p.step)
}

/// The thresholds the region is looked at: from θ + δ to `t_max` − δ,
/// `step` apart.
fn thresholds(theta: f32, p: &StableParams) -> impl Iterator<Item = f32> + '_ {
    let hi = p.t_max - p.delta + 1e-6;
    std::iter::successors(Some(theta + p.delta), move |&t| Some(t + p.step)).take_while(move |&t| t <= hi)
}

/// How many of the sorted `keys` are at most `t`.
fn count_within(keys: &[f32], t: f32) -> f32 {
    keys.partition_point(|&b| b <= t) as f32
}

/// A flood into something else, for [`flood_level`]: the region grows this
/// many times over. Lower, the realistic benchmark's wall (whose features
/// drift, so its region creeps on: 5.3k, 8.4k, 13.4k, 17.1k voxels at
/// 0.6, 0.8, 1.0, 1.2) was cut off at its first growth by half
/// (`flood_growth`): 3D IoU 0.867 → 0.620. Floods into the table and the
/// floor grow 18 to 230 times.
pub const FLOOD_JUMP: f32 = 3.0;

/// `reached` (the flood's voxels) within `steps` 26-neighbour steps of
/// `core`'s voxels, through voxels of `reached`.
fn band_around(cache: &FeatureCache, core: &[(f32, u32)], reached: &Bitmap, steps: usize) -> Bitmap {
    let offs = Offsets::new(cache.geom.res, &GrowParams::default());
    let mut out = Bitmap::new(cache.geom.res);
    let mut layer: Vec<u32> = core.iter().map(|&(_, v)| v).collect();
    for &v in &layer {
        out.set(v as usize, true);
    }
    for _ in 0..steps {
        let mut next = vec![];
        for &v in &layer {
            offs.for_each(v as usize, |_, n| {
                if reached.get(n) && !out.get(n) {
                    out.set(n, true);
                    next.push(n as u32);
                }
            });
        }
        layer = next;
    }
    out
}

/// Grows `seed` (NNFM seeds at θ of the stroke whose distances `dist`
/// holds, on solid voxels) to the stable region. The reach reads the
/// distance of every solid voxel: `dist` from
/// [`super::nnfm::nnfm_seed_measuring_all`] has them already, others are
/// measured first, in parallel.
pub fn stable_region(
    cache: &FeatureCache,
    dist: &mut StrokeDistances,
    seed: &Bitmap,
    theta: f32,
    floor: f32,
    p: &StableParams,
) -> StableRegion {
    let (within, starts) = passable(cache, dist, seed, floor, p.t_max);
    let mut settles = Settles::new(theta, p);
    let order = flood(cache, dist, seed, within.clone(), p.t_max, |key, order| {
        settles.settled(key, order)
    });
    // A flood that ran to the end ordered its whole reach.
    let bits = if settles.both() {
        reach(&within, starts)
    } else {
        ordered_voxels(cache, &order)
    };
    settle(cache, seed, &order, bits, theta, p)
}

/// The voxels of a flood's `order`, as a bitmap.
fn ordered_voxels(cache: &FeatureCache, order: &[(f32, u32)]) -> Bitmap {
    Bitmap::from_ones(cache.geom.res, &order.iter().map(|o| o.1).collect::<Vec<_>>())
}

/// The stable region of the flood from `seed` whose keys in order (at
/// least as far as they settle the threshold and the flood level) are
/// `order`, and whose whole reach is `bits`.
fn settle(
    cache: &FeatureCache,
    seed: &Bitmap,
    order: &[(f32, u32)],
    bits: Bitmap,
    theta: f32,
    p: &StableParams,
) -> StableRegion {
    let keys: Vec<f32> = order.iter().map(|o| o.0).collect();
    let threshold = stable_threshold(&keys, theta, p);
    let mut region = seed.clone();
    for &(b, v) in order.iter().take_while(|o| o.0 <= threshold) {
        debug_assert!(b <= threshold);
        region.set(v as usize, true);
    }
    let before_flood = flood_level(&keys, theta, p).map(|level| {
        let before = keys.partition_point(|&b| b <= level);
        band_around(cache, &order[..before], &bits, BAND)
    });
    let reached: Vec<u32> = bits.ones().map(|v| v as u32).collect();
    StableRegion {
        region,
        threshold,
        reached,
        before_flood,
        flooded: order.len(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::{Aabb, FieldBuilder};
    use crate::segment::kmeans::Centroids;
    use crate::segment::nnfm::{nnfm_seed_with_distances, CentreSet};
    use glam::Vec3;

    /// The flood as plain Dijkstra on bottleneck keys: every touched voxel
    /// through the heap.
    fn reference_keys(cache: &FeatureCache, set: &CentreSet, seed: &Bitmap, floor: f32, t_max: f32) -> Vec<(u32, u32)> {
        let offs = Offsets::new(cache.geom.res, &GrowParams::default());
        let mut touched = Bitmap::new(cache.geom.res);
        let mut heap = BinaryHeap::new();
        for v in seed.ones() {
            let r = cache.index.slot(v).unwrap();
            touched.set(v, true);
            heap.push(Reverse((set.min_distance(cache, r).to_bits(), v as u32)));
        }
        let mut out = vec![];
        while let Some(Reverse((key, v))) = heap.pop() {
            let b = f32::from_bits(key);
            if b > t_max {
                break;
            }
            out.push((v, key));
            offs.for_each(v as usize, |_, n| {
                let Some(r) = cache.index.slot(n) else { return };
                if touched.get(n) || cache.sigma[r] <= floor {
                    return;
                }
                touched.set(n, true);
                heap.push(Reverse((b.max(set.min_distance(cache, r)).to_bits(), n as u32)));
            });
        }
        out.sort_unstable();
        out
    }

    #[test]
    fn the_flood_gives_every_voxel_its_bottleneck_distance() {
        // Features that wander across a blob with holes (σ 0 where the
        // sine is low): many levels, plateaus and dead ends.
        let feat = |p: Vec3, out: &mut [f32]| {
            for (c, o) in out.iter_mut().enumerate() {
                *o = (2.0 * p.x + 1.3 * p.y * (c as f32 + 1.0) - 0.7 * p.z * c as f32).cos();
            }
        };
        let field = FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [20; 3]).build(
            |p| {
                if (5.0 * p.x).sin() * (4.0 * p.z).cos() > -0.6 {
                    1.0
                } else {
                    0.0
                }
            },
            |_| Vec3::ONE,
            Some((6, &feat)),
        );
        let cache = FeatureCache::build(&field).unwrap();
        let unit: Vec<f32> = cache.row(40).iter().map(|x| x * cache.inv_norm[40]).collect();
        let centres = Centroids { dim: 6, data: unit };
        let set = CentreSet::new(centres.clone());
        for (theta, t_max) in [(0.1f32, 1.5f32), (0.3, 0.8), (0.05, 4.0)] {
            let (seed, mut dist) = nnfm_seed_with_distances(&cache, &centres, theta, 0.5);
            assert!(seed.any());
            let (within, starts) = passable(&cache, &mut dist, &seed, 0.5, t_max);
            let open = reach(&within, starts);
            let order = flood(&cache, &mut dist, &seed, within, t_max, |_, _| false);
            let ordered: Vec<u32> = order.iter().map(|o| o.1).collect();
            assert_eq!(ordered.len(), open.count());
            assert_eq!(
                Bitmap::from_ones(cache.geom.res, &ordered),
                open,
                "the reach is what the whole flood orders"
            );
            let keys: Vec<f32> = order.iter().map(|o| o.0).collect();
            assert!(keys.windows(2).all(|w| w[0] <= w[1]), "keys in flood order");
            let mut got: Vec<(u32, u32)> = order.iter().map(|&(b, v)| (v, b.to_bits())).collect();
            got.sort_unstable();
            let want = reference_keys(&cache, &set, &seed, 0.5, t_max);
            assert!(want.len() > seed.count(), "the flood must grow past the seeds");
            assert_eq!(got, want, "theta {theta}, t_max {t_max}");
        }
    }

    #[test]
    fn the_flood_stops_once_the_region_is_settled_with_the_same_answer() {
        // A small block pushed against a large one (the pot on the
        // table): features of each drift across it, and the large one's
        // lie about 1.0 from the small one's, so the flood runs into it.
        let feat = |p: Vec3, out: &mut [f32]| {
            let (a, b) = if p.x < -0.3 { (1.0, 0.0) } else { (0.5, 0.866) };
            out.fill(0.0);
            out[0] = a;
            out[1] = b;
            out[2] = 0.25 * (3.0 * p.y).sin() + 0.1 * p.z;
            out[3] = 0.2 * (2.0 * p.x + p.z).cos();
        };
        let solid = |p: Vec3| {
            let small = p.x > -0.8 && p.x < -0.3 && p.y.abs() < 0.3 && p.z.abs() < 0.3;
            let large = p.x >= -0.3 && p.x < 0.9 && p.y.abs() < 0.8 && p.z.abs() < 0.8;
            if small || large {
                1.0
            } else {
                0.0
            }
        };
        let field = FieldBuilder::new(Aabb::new(Vec3::splat(-1.0), Vec3::splat(1.0)), [32; 3]).build(
            solid,
            |_| Vec3::ONE,
            Some((4, &feat)),
        );
        let cache = FeatureCache::build(&field).unwrap();
        let [x, y, z] = cache.geom.nearest(Vec3::new(-0.55, 0.0, 0.0)).unwrap();
        let r = cache
            .index
            .slot(cache.geom.index(x, y, z))
            .expect("inside the small block");
        let unit: Vec<f32> = cache.row(r).iter().map(|x| x * cache.inv_norm[r]).collect();
        let centres = Centroids { dim: 4, data: unit };
        let p = StableParams::default();
        let (seed, mut dist) = nnfm_seed_with_distances(&cache, &centres, 0.05, 0.5);
        // What `stable_region` gives when the flood orders every voxel of
        // its reach (as it did before it stopped once the region settled).
        let whole_flood_region = |dist: &mut StrokeDistances, p: &StableParams| {
            let (within, _) = passable(&cache, dist, &seed, 0.5, p.t_max);
            let order = flood(&cache, dist, &seed, within, p.t_max, |_, _| false);
            settle(&cache, &seed, &order, ordered_voxels(&cache, &order), 0.05, p)
        };
        let got = stable_region(&cache, &mut dist, &seed, 0.05, 0.5, &p);
        let want = whole_flood_region(&mut dist, &p);
        assert!(want.before_flood.is_some(), "the flood runs into the large block");
        assert!(
            3 * got.flooded < 2 * want.flooded,
            "stopped early: {} of {}",
            got.flooded,
            want.flooded
        );
        assert_eq!(got.threshold, want.threshold);
        assert_eq!(got.region, want.region);
        assert_eq!(got.reached, want.reached);
        assert_eq!(got.before_flood, want.before_flood);
        // With no flood to stop at (the large block's features too far for
        // t_max), the whole reach is ordered.
        let p = StableParams { t_max: 0.9, ..p };
        let got = stable_region(&cache, &mut dist, &seed, 0.05, 0.5, &p);
        let want = whole_flood_region(&mut dist, &p);
        assert_eq!(
            (got.threshold, &got.region, &got.reached),
            (want.threshold, &want.region, &want.reached)
        );
        assert!(got.before_flood.is_none());
    }

    #[test]
    fn the_bucket_queue_pops_in_the_order_of_one_heap() {
        // Seeds anywhere in [0, 2] (those past t_max dropped), then each
        // pop pushes up to three keys no smaller than the one popped, some
        // in the same bucket, some equal, some past t_max.
        let t_max = 1.5f32;
        let mut rng = crate::util::SplitMix64::new(7);
        let mut queue = BucketQueue::new(t_max);
        let mut heap = BinaryHeap::new();
        let push = |q: &mut BucketQueue, h: &mut BinaryHeap<Reverse<(u32, u32)>>, key: f32, v: u32| {
            q.push(key, v);
            if key <= t_max {
                h.push(Reverse((key.to_bits(), v)));
            }
        };
        for v in 0..2000u32 {
            let key = 2.0 * rng.below(1_000_000) as f32 / 1e6;
            push(&mut queue, &mut heap, key, v);
        }
        let mut next = 2000u32;
        let mut popped = 0;
        while let Some(Reverse((bits, want))) = heap.pop() {
            let (key, got) = queue.pop().expect("the queue empties with the heap");
            assert_eq!((key.to_bits(), got), (bits, want), "pop {popped}");
            popped += 1;
            if next < 20_000 {
                for step in [0.0, 1e-4, 0.01 * rng.below(100) as f32] {
                    push(&mut queue, &mut heap, key + step, next);
                    next += 1;
                }
            }
        }
        assert_eq!(queue.pop(), None);
        assert!(popped > 10_000, "{popped}");
    }

    #[test]
    fn the_flood_level_is_where_the_region_jumps() {
        let p = StableParams::default();
        // An object up to 0.6, nothing to 1.0, then the table (50 times
        // the object): the level lies before the jump and after the object.
        let mut keys: Vec<f32> = (0..1000).map(|i| 0.6 * i as f32 / 1000.0).collect();
        keys.extend((0..50_000).map(|i| 1.0 + 0.4 * i as f32 / 50_000.0));
        let level = flood_level(&keys, 0.3, &p).expect("a flood");
        assert!(level >= 0.6 && level < 1.0, "{level}");
        // The realistic benchmark's wall: its region creeps on (×1.3 to
        // ×1.6 per 0.2) and is no flood; the floor it runs into at 1.3 is.
        let creep = [(0.4, 3409), (0.6, 5338), (0.8, 8392), (1.0, 13408), (1.2, 17098)];
        let mut keys = vec![];
        let mut below = 0;
        for (t, n) in creep {
            keys.extend((below..n).map(|i| t - 0.2 * (n - i) as f32 / (n - below) as f32));
            below = n;
        }
        assert_eq!(flood_level(&keys, 0.3, &p), None);
        keys.extend((0..300_000).map(|i| 1.3 + 0.2 * i as f32 / 300_000.0));
        let level = flood_level(&keys, 0.3, &p).expect("the floor");
        assert!(level > 1.15 && level < 1.3, "{level}");
        // Nothing but the object: no flood.
        assert_eq!(flood_level(&keys[..1000], 0.3, &p), None);
    }

    #[test]
    fn the_threshold_sits_on_the_plateau_before_a_flood() {
        // 1000 voxels up to d = 0.6 (the object, two thirds of it seeds),
        // none until 1.0, then a flood of 50000 (the next object).
        let mut keys: Vec<f32> = (0..1000).map(|i| 0.6 * i as f32 / 1000.0).collect();
        keys.extend((0..50_000).map(|i| 1.0 + 0.4 * i as f32 / 50_000.0));
        let t = stable_threshold(&keys, 0.4, &StableParams::default());
        assert!(t > 0.6 && t < 1.0, "{t}");
        // Nothing after the object: the plateau runs to t_max; the
        // smallest threshold past the object is chosen.
        let keys: Vec<f32> = (0..1000).map(|i| 1.1 * i as f32 / 1000.0).collect();
        let t = stable_threshold(&keys, 0.4, &StableParams::default());
        assert!(t > 1.1 && t < 1.25, "{t}");
        // An object (to 0.6), a flood into the rest (at 1.0, 10× its size),
        // then nothing more: the plateau after the flood is not chosen.
        let mut keys: Vec<f32> = (0..1000).map(|i| 0.6 * i as f32 / 1000.0).collect();
        keys.extend((0..10_000).map(|i| 1.0 + 0.05 * i as f32 / 10_000.0));
        let t = stable_threshold(&keys, 0.4, &StableParams::default());
        assert!(t > 0.6 && t < 1.0, "{t}");
        // A steady creep (3 % per 0.1) has no stable boundary: seeds only.
        let mut keys = vec![0.0f32; 10_000];
        let mut n = 10_000.0f32;
        for i in 0..110 {
            let step = (0.003 * n) as usize;
            keys.extend(std::iter::repeat_n(0.4 + 0.01 * i as f32, step));
            n += step as f32;
        }
        assert_eq!(stable_threshold(&keys, 0.4, &StableParams::default()), 0.4);
    }
}
