//! Minimum s–t cut of a sparse graph: the Boykov–Kolmogorov max-flow
//! algorithm ("An Experimental Comparison of Min-Cut/Max-Flow Algorithms
//! for Energy Minimization in Vision", PAMI 2004), the standard solver for
//! the grid-shaped graphs of interactive segmentation.
//!
//! Two search trees grow from the source and the sink through unsaturated
//! arcs; where they touch, flow is pushed along the path found, the arcs it
//! saturates orphan their subtrees, and orphans are adopted by another node
//! of their tree or freed. The trees are reused from path to path, which is
//! what makes the method fast on images and voxel grids. Nodes keep their
//! distance to their terminal and a timestamp of when it was last checked,
//! so that adoption prefers short paths (the paper's heuristic).
//!
//! Capacities are `f32`; a terminal capacity of [`HARD`] ties a node to its
//! terminal for good.
//!
//! After a max-flow, terminal capacities may change ([`Graph::set_terminal`])
//! and [`Graph::maxflow`] then resumes from the flow and the search trees
//! it left (Kohli & Torr's dynamic graph cuts, "Dynamic Graph Cuts for
//! Efficient Inference in Markov Random Fields", PAMI 2007; the tree reuse
//! of Kolmogorov's maxflow v3): GrabCut-style rounds change only the
//! region terms, and most of the flow found by the last round still
//! stands.

use std::collections::VecDeque;

/// A terminal capacity larger than any cut the caller can build: a hard
/// constraint.
pub const HARD: f32 = 1e20;

const NONE: u32 = u32::MAX;
/// `parent` of a node whose parent is its terminal.
const TERMINAL: u32 = u32::MAX - 1;
/// `parent` of an orphan (while orphans are being adopted).
const ORPHAN: u32 = u32::MAX - 2;

#[derive(Clone, Copy)]
struct Node {
    /// Its outgoing arcs are `first..last` (from the first max-flow on).
    first: u32,
    last: u32,
    /// Arc to the parent (from this node), `TERMINAL`, `ORPHAN` or `NONE`
    /// (a free node, in neither tree).
    parent: u32,
    /// Residual capacity from the source (> 0) or to the sink (< 0).
    tr_cap: f32,
    /// In the sink's tree (meaningful only when `parent != NONE`).
    sink: bool,
    /// When `dist` was last known to be right, and the distance to the
    /// terminal then.
    ts: u32,
    dist: u32,
    /// Net terminal capacity (source − sink) as set, for
    /// [`Graph::set_terminal`].
    cap: f32,
    /// Its terminal capacity changed since the last max-flow.
    changed: bool,
}

#[derive(Clone, Copy)]
struct Arc {
    head: u32,
    /// The reverse arc.
    sister: u32,
    r_cap: f32,
}

/// A graph with terminal links and symmetric pairs of arcs.
pub struct Graph {
    nodes: Vec<Node>,
    /// Arcs, each with its reverse: in pairs (a, a ^ 1) as added, then
    /// every node's outgoing arcs side by side ([`Graph::freeze`]).
    arcs: Vec<Arc>,
    frozen: bool,
    flow: f64,
    time: u32,
    active: VecDeque<u32>,
    orphans: Vec<u32>,
    /// A max-flow ran: the next one resumes from its trees.
    solved: bool,
    /// Nodes whose terminal capacity changed since then.
    changed: Vec<u32>,
}

impl Graph {
    pub fn new(nodes: usize, edges_hint: usize) -> Self {
        assert!(nodes < ORPHAN as usize, "too many nodes for a cut graph");
        Graph {
            nodes: vec![
                Node {
                    first: 0,
                    last: 0,
                    parent: NONE,
                    tr_cap: 0.0,
                    sink: false,
                    ts: 0,
                    dist: 0,
                    cap: 0.0,
                    changed: false,
                };
                nodes
            ],
            arcs: Vec::with_capacity(2 * edges_hint),
            frozen: false,
            flow: 0.0,
            time: 0,
            active: VecDeque::new(),
            orphans: vec![],
            solved: false,
            changed: vec![],
        }
    }

    /// A graph of `nodes` nodes and the undirected `edges` (i, j,
    /// capacity both ways), its arcs laid out as [`Graph::freeze`] lays
    /// them, directly: building arc pairs and then laying them out copies
    /// a large graph's arcs, which cost as much as the max-flow on lego
    /// (10 ms, most of it the kernel zeroing fresh pages).
    pub fn from_edges(nodes: usize, edges: &[(u32, u32, f32)]) -> Self {
        let mut g = Graph::new(nodes, 0);
        g.arcs = g.lay_out(|| edges.iter().map(|&(i, j, w)| (i, j, w, w)));
        g.frozen = true;
        g
    }

    /// Adds capacities `source` (cut when `i` ends on the sink side) and
    /// `sink` (cut when it ends on the source side); both ≥ 0.
    pub fn add_terminal(&mut self, i: usize, source: f32, sink: f32) {
        debug_assert!(source >= 0.0 && sink >= 0.0);
        let n = &mut self.nodes[i];
        // Only the difference matters to the cut; the common part is flow
        // already pushed.
        let delta = n.tr_cap;
        let (mut s, mut t) = (source, sink);
        if delta > 0.0 {
            s += delta;
        } else {
            t -= delta;
        }
        self.flow += s.min(t) as f64;
        n.tr_cap = s - t;
        n.cap += source - sink;
        if self.solved && !n.changed {
            n.changed = true;
            self.changed.push(i as u32);
        }
    }

    /// Sets node `i`'s terminal capacities to `source` and `sink` (both ≥ 0),
    /// replacing what [`Graph::add_terminal`] gave it. The next max-flow
    /// leaves a minimum cut of the new graph; the flow it reports is that
    /// of an equivalent graph (terminal capacities that differ by a
    /// constant per node), not of this one.
    pub fn set_terminal(&mut self, i: usize, source: f32, sink: f32) {
        debug_assert!(source >= 0.0 && sink >= 0.0);
        let old = self.nodes[i].cap;
        let delta = (source - sink) - old;
        if delta == 0.0 {
            return;
        }
        // Only the net capacity matters to the cut: add the change on the
        // side it grows.
        if delta > 0.0 {
            self.add_terminal(i, delta, 0.0);
        } else {
            self.add_terminal(i, 0.0, -delta);
        }
        self.nodes[i].cap = source - sink;
    }

    /// Adds an edge with capacity `cap` from `i` to `j` and `rev_cap` back.
    pub fn add_edge(&mut self, i: usize, j: usize, cap: f32, rev_cap: f32) {
        debug_assert!(i != j && cap >= 0.0 && rev_cap >= 0.0);
        assert!(
            !self.frozen,
            "edges are added before the first max-flow, and not to a graph made from edges"
        );
        let a = self.arcs.len() as u32;
        self.arcs.push(Arc {
            head: j as u32,
            sister: a + 1,
            r_cap: cap,
        });
        self.arcs.push(Arc {
            head: i as u32,
            sister: a,
            r_cap: rev_cap,
        });
    }

    /// Lays every node's outgoing arcs side by side (see
    /// [`Graph::lay_out`]) before the first max-flow.
    fn freeze(&mut self) {
        if self.frozen {
            return;
        }
        self.frozen = true;
        // Until now arcs come in pairs (a, a ^ 1): the edge a's tail → head.
        let pairs = std::mem::take(&mut self.arcs);
        self.arcs = self.lay_out(|| {
            pairs
                .chunks_exact(2)
                .map(|p| (p[1].head, p[0].head, p[0].r_cap, p[1].r_cap))
        });
    }

    /// The arcs of `edges` (i, j, capacity i → j, capacity j → i; the
    /// closure lists them, twice), every node's outgoing arcs side by side
    /// in `first..last`, each node's in the reverse of the order of its
    /// edges: the order the per-node arc lists gave before, so the searches
    /// visit them as they did and the flow and the cut are the same to the
    /// bit. The trees scan a node's arcs over and over, and in the order
    /// of addition a grid voxel's six arcs lay in three or four distant
    /// places: on the fern's trunk stroke the two rounds' max-flow fell
    /// from 118 + 89 ms to 95 + 63 ms.
    fn lay_out<I: Iterator<Item = (u32, u32, f32, f32)>>(&mut self, edges: impl Fn() -> I) -> Vec<Arc> {
        let mut end = vec![0u32; self.nodes.len()];
        for (i, j, _, _) in edges() {
            end[i as usize] += 1;
            end[j as usize] += 1;
        }
        let mut at = 0u32;
        for (n, e) in self.nodes.iter_mut().zip(&mut end) {
            n.first = at;
            at += *e;
            n.last = at;
            *e = at;
        }
        let empty = Arc {
            head: 0,
            sister: 0,
            r_cap: 0.0,
        };
        let mut arcs = vec![empty; at as usize];
        for (i, j, cap, rev_cap) in edges() {
            debug_assert!(i != j && cap >= 0.0 && rev_cap >= 0.0);
            end[i as usize] -= 1;
            end[j as usize] -= 1;
            let (a, b) = (end[i as usize], end[j as usize]);
            arcs[a as usize] = Arc {
                head: j,
                sister: b,
                r_cap: cap,
            };
            arcs[b as usize] = Arc {
                head: i,
                sister: a,
                r_cap: rev_cap,
            };
        }
        arcs
    }

    /// Runs max-flow; returns the flow, which equals the minimum cut's
    /// capacity (until [`Graph::set_terminal`] changes a capacity). A
    /// second run resumes from the first's flow and trees.
    pub fn maxflow(&mut self) -> f64 {
        self.freeze();
        if self.solved {
            self.reuse_trees();
        } else {
            self.init_trees();
        }
        self.solved = true;
        while let Some(i) = self.next_active() {
            let Some(mid) = self.grow(i) else { continue };
            self.time += 1;
            self.augment(mid);
            self.adopt_orphans();
            // `i` may still have neighbours to grow into.
            if self.nodes[i as usize].parent != NONE {
                self.active.push_front(i);
            }
        }
        self.flow
    }

    /// After [`Graph::maxflow`]: whether node `i` is on the source side of
    /// a minimum cut (free nodes go to the sink side).
    pub fn is_source(&self, i: usize) -> bool {
        let n = &self.nodes[i];
        n.parent != NONE && !n.sink
    }

    fn init_trees(&mut self) {
        self.active.clear();
        for (i, n) in self.nodes.iter_mut().enumerate() {
            if n.tr_cap != 0.0 {
                n.parent = TERMINAL;
                n.sink = n.tr_cap < 0.0;
                n.ts = 0;
                n.dist = 1;
                self.active.push_back(i as u32);
            } else {
                n.parent = NONE;
            }
        }
    }

    /// Repairs the trees of the last max-flow where terminal capacities
    /// changed: such a node hangs on its terminal again (in the tree its
    /// new residual capacity points to, orphaning its children when it
    /// changes tree), or becomes an orphan when none is left; it and the
    /// neighbours that may now reach across become active.
    fn reuse_trees(&mut self) {
        self.active.clear();
        self.time += 1;
        let changed = std::mem::take(&mut self.changed);
        for &i in &changed {
            let n = &mut self.nodes[i as usize];
            n.changed = false;
            let (tr, parent, sink) = (n.tr_cap, n.parent, n.sink);
            self.active.push_back(i);
            if tr == 0.0 {
                if parent != NONE {
                    self.make_orphan(i);
                }
                continue;
            }
            let to_sink = tr < 0.0;
            if parent == NONE || sink != to_sink {
                self.nodes[i as usize].sink = to_sink;
                self.join_tree(i, parent != NONE);
            }
            let n = &mut self.nodes[i as usize];
            n.parent = TERMINAL;
            n.ts = self.time;
            n.dist = 1;
        }
        self.adopt_orphans();
    }

    /// Node `i` joined the tree `self.nodes[i].sink`, from the other one
    /// (`was_in`) or from no tree: its children in the old tree become
    /// orphans, and the neighbours in the other tree it can now reach
    /// across become active.
    fn join_tree(&mut self, i: u32, was_in: bool) {
        let now_sink = self.nodes[i as usize].sink;
        let (first, last) = (self.nodes[i as usize].first, self.nodes[i as usize].last);
        for a in first..last {
            let arc = self.arcs[a as usize];
            let j = arc.head;
            let nj = self.nodes[j as usize];
            if !nj.changed && nj.parent != NONE && nj.sink != now_sink {
                // j's parent arc (from j) is the reverse of a: i was its
                // parent, in the tree i left.
                if was_in && nj.parent == arc.sister {
                    self.make_orphan(j);
                }
                // Adopted again or not, j may reach i across the trees'
                // boundary (residual capacity from the source side).
                let cap = if now_sink {
                    self.arcs[arc.sister as usize].r_cap
                } else {
                    arc.r_cap
                };
                if cap > 0.0 {
                    self.active.push_back(j);
                }
            }
        }
    }

    /// The next active node still in a tree (free nodes left in the queue
    /// are skipped).
    fn next_active(&mut self) -> Option<u32> {
        while let Some(i) = self.active.pop_front() {
            if self.nodes[i as usize].parent != NONE {
                return Some(i);
            }
        }
        None
    }

    /// Grows the tree of `i` through its unsaturated arcs; returns the arc
    /// from the source tree to the sink tree where the trees meet.
    fn grow(&mut self, i: u32) -> Option<u32> {
        let ni = self.nodes[i as usize];
        let (first, last) = (ni.first, ni.last);
        for a in first..last {
            let arc = self.arcs[a as usize];
            // Residual capacity in the direction of the tree's flow.
            let cap = if ni.sink {
                self.arcs[arc.sister as usize].r_cap
            } else {
                arc.r_cap
            };
            if cap > 0.0 {
                let j = arc.head as usize;
                let nj = self.nodes[j];
                if nj.parent == NONE {
                    let n = &mut self.nodes[j];
                    n.sink = ni.sink;
                    n.parent = arc.sister;
                    n.ts = ni.ts;
                    n.dist = ni.dist + 1;
                    self.active.push_back(j as u32);
                } else if nj.sink != ni.sink {
                    return Some(if ni.sink { arc.sister } else { a });
                } else if nj.ts <= ni.ts && nj.dist > ni.dist {
                    // A shorter path to the terminal for j.
                    let n = &mut self.nodes[j];
                    n.parent = arc.sister;
                    n.ts = ni.ts;
                    n.dist = ni.dist + 1;
                }
            }
        }
        None
    }

    /// Pushes the bottleneck flow along the path through `mid` (an arc
    /// from a source-tree node to a sink-tree node).
    fn augment(&mut self, mid: u32) {
        let head = self.arcs[mid as usize].head;
        let tail = self.arcs[self.rev(mid)].head;
        let mut f = self.arcs[mid as usize].r_cap;
        // Source side: flow runs parent → child, along the parent arc's sister.
        let mut i = tail;
        loop {
            let p = self.nodes[i as usize].parent;
            if p == TERMINAL {
                f = f.min(self.nodes[i as usize].tr_cap);
                break;
            }
            f = f.min(self.arcs[self.rev(p)].r_cap);
            i = self.arcs[p as usize].head;
        }
        // Sink side: flow runs child → parent, along parent.
        let mut j = head;
        loop {
            let p = self.nodes[j as usize].parent;
            if p == TERMINAL {
                f = f.min(-self.nodes[j as usize].tr_cap);
                break;
            }
            f = f.min(self.arcs[p as usize].r_cap);
            j = self.arcs[p as usize].head;
        }
        self.arcs[mid as usize].r_cap -= f;
        let back = self.rev(mid);
        self.arcs[back].r_cap += f;
        let mut i = tail;
        loop {
            let p = self.nodes[i as usize].parent;
            if p == TERMINAL {
                let n = &mut self.nodes[i as usize];
                n.tr_cap -= f;
                if n.tr_cap <= 0.0 {
                    n.tr_cap = 0.0;
                    self.make_orphan(i);
                }
                break;
            }
            self.arcs[p as usize].r_cap += f;
            let next = self.arcs[p as usize].head;
            let back = self.rev(p);
            let r = &mut self.arcs[back].r_cap;
            *r -= f;
            if *r <= 0.0 {
                *r = 0.0;
                self.make_orphan(i);
            }
            i = next;
        }
        let mut j = head;
        loop {
            let p = self.nodes[j as usize].parent;
            if p == TERMINAL {
                let n = &mut self.nodes[j as usize];
                n.tr_cap += f;
                if n.tr_cap >= 0.0 {
                    n.tr_cap = 0.0;
                    self.make_orphan(j);
                }
                break;
            }
            let back = self.rev(p);
            self.arcs[back].r_cap += f;
            let next = self.arcs[p as usize].head;
            let r = &mut self.arcs[p as usize].r_cap;
            *r -= f;
            if *r <= 0.0 {
                *r = 0.0;
                self.make_orphan(j);
            }
            j = next;
        }
        self.flow += f as f64;
    }

    /// The index of arc `a`'s reverse.
    #[inline]
    fn rev(&self, a: u32) -> usize {
        self.arcs[a as usize].sister as usize
    }

    fn make_orphan(&mut self, i: u32) {
        self.nodes[i as usize].parent = ORPHAN;
        self.orphans.push(i);
    }

    fn adopt_orphans(&mut self) {
        while let Some(i) = self.orphans.pop() {
            self.adopt(i);
        }
    }

    /// Finds `i` a new parent in its tree (the one closest to the terminal
    /// among neighbours whose path to the terminal is intact), or frees it.
    fn adopt(&mut self, i: u32) {
        let sink = self.nodes[i as usize].sink;
        let mut best: Option<(u32, u32)> = None; // (arc, dist)
        let (first, last) = (self.nodes[i as usize].first, self.nodes[i as usize].last);
        for a in first..last {
            let arc = self.arcs[a as usize];
            // Residual capacity from the candidate parent's side.
            let cap = if sink {
                arc.r_cap
            } else {
                self.arcs[arc.sister as usize].r_cap
            };
            let j = arc.head;
            let nj = self.nodes[j as usize];
            if cap > 0.0 && nj.parent != NONE && nj.sink == sink {
                if let Some(d) = self.origin_distance(j) {
                    if best.is_none_or(|(_, bd)| d < bd) {
                        best = Some((a, d));
                    }
                }
            }
        }
        if let Some((a, d)) = best {
            let n = &mut self.nodes[i as usize];
            n.parent = a;
            n.ts = self.time;
            n.dist = d + 1;
            return;
        }
        // No parent: free i; neighbours that could regrow into it become
        // active, and its children become orphans.
        self.nodes[i as usize].parent = NONE;
        let (first, last) = (self.nodes[i as usize].first, self.nodes[i as usize].last);
        for a in first..last {
            let arc = self.arcs[a as usize];
            let j = arc.head;
            let nj = self.nodes[j as usize];
            if nj.parent != NONE && nj.sink == sink {
                let cap = if sink {
                    arc.r_cap
                } else {
                    self.arcs[arc.sister as usize].r_cap
                };
                if cap > 0.0 {
                    self.active.push_back(j);
                }
                // j's parent is i (through this arc or a parallel one).
                if nj.parent != TERMINAL && nj.parent != ORPHAN && self.arcs[nj.parent as usize].head == i {
                    self.make_orphan(j);
                }
            }
        }
    }

    /// The distance of `j` to its terminal if its chain of parents reaches
    /// it (not an orphan); marks the chain with the current time.
    fn origin_distance(&mut self, j: u32) -> Option<u32> {
        let mut k = j;
        let mut d = 0u32;
        loop {
            let n = self.nodes[k as usize];
            if n.ts == self.time {
                d += n.dist;
                break;
            }
            let p = n.parent;
            d += 1;
            if p == TERMINAL {
                let n = &mut self.nodes[k as usize];
                n.ts = self.time;
                n.dist = 1;
                break;
            }
            if p == ORPHAN || p == NONE {
                return None;
            }
            k = self.arcs[p as usize].head;
        }
        // Stamp the chain with its distances.
        let total = d;
        let mut k = j;
        let mut d = total;
        while self.nodes[k as usize].ts != self.time {
            let n = &mut self.nodes[k as usize];
            n.ts = self.time;
            n.dist = d;
            d -= 1;
            k = self.arcs[n.parent as usize].head;
        }
        Some(total)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::SplitMix64;

    /// A graph with these terminal capacities (source, sink) and edges
    /// (i, j, capacity i → j, capacity j → i).
    fn graph(term: &[(f32, f32)], edges: &[(usize, usize, f32, f32)]) -> Graph {
        let mut g = Graph::new(term.len(), edges.len());
        for (i, &(s, t)) in term.iter().enumerate() {
            g.add_terminal(i, s, t);
        }
        for &(i, j, c, r) in edges {
            g.add_edge(i, j, c, r);
        }
        g
    }

    /// The minimum cut by enumeration of every labelling.
    fn brute_force(n: usize, term: &[(f32, f32)], edges: &[(usize, usize, f32, f32)]) -> f64 {
        (0u32..1 << n)
            .map(|s| {
                let src = |i: usize| s >> i & 1 == 1;
                let t: f64 = (0..n).map(|i| if src(i) { term[i].1 } else { term[i].0 } as f64).sum();
                let e: f64 = edges
                    .iter()
                    .map(|&(i, j, c, r)| match (src(i), src(j)) {
                        (true, false) => c as f64,
                        (false, true) => r as f64,
                        _ => 0.0,
                    })
                    .sum();
                t + e
            })
            .fold(f64::INFINITY, f64::min)
    }

    #[test]
    fn max_flow_equals_the_minimum_cut_on_random_graphs() {
        let mut rng = SplitMix64::new(7);
        for case in 0..300 {
            let n = 1 + rng.below(11);
            // Terminal capacities, 40 % of them zero.
            let cap = |r: &mut SplitMix64, top: f64| if r.unit() < 0.4 { 0.0 } else { (r.unit() * top) as f32 };
            let term: Vec<(f32, f32)> = (0..n).map(|_| (cap(&mut rng, 4.0), cap(&mut rng, 4.0))).collect();
            let mut edges = vec![];
            if n > 1 {
                for _ in 0..rng.below(3 * n) {
                    let i = rng.below(n);
                    let j = (i + 1 + rng.below(n - 1)) % n;
                    edges.push((i, j, (rng.unit() * 3.0) as f32, (rng.unit() * 3.0) as f32));
                }
            }
            let mut g = graph(&term, &edges);
            let flow = g.maxflow();
            let best = brute_force(n, &term, &edges);
            assert!(
                (flow - best).abs() < 1e-3 * (1.0 + best),
                "case {case}: flow {flow} cut {best}"
            );
            // The labelling the solver reports is a cut of that capacity.
            let cut: f64 = (0..n)
                .map(|i| if g.is_source(i) { term[i].1 } else { term[i].0 } as f64)
                .sum::<f64>()
                + edges
                    .iter()
                    .map(|&(i, j, c, r)| match (g.is_source(i), g.is_source(j)) {
                        (true, false) => c as f64,
                        (false, true) => r as f64,
                        _ => 0.0,
                    })
                    .sum::<f64>();
            assert!(
                (cut - best).abs() < 1e-3 * (1.0 + best),
                "case {case}: labelling {cut} cut {best}"
            );
        }
    }

    /// Max-flow by shortest augmenting paths (Edmonds–Karp) on a dense
    /// capacity matrix with the source at n and the sink at n + 1.
    fn edmonds_karp(n: usize, term: &[(f32, f32)], edges: &[(usize, usize, f32, f32)]) -> f64 {
        let m = n + 2;
        let mut cap = vec![0.0f64; m * m];
        for (i, &(s, t)) in term.iter().enumerate() {
            cap[n * m + i] += s as f64;
            cap[i * m + n + 1] += t as f64;
        }
        for &(i, j, c, r) in edges {
            cap[i * m + j] += c as f64;
            cap[j * m + i] += r as f64;
        }
        let mut flow = 0.0;
        loop {
            let mut prev = vec![usize::MAX; m];
            prev[n] = n;
            let mut queue = std::collections::VecDeque::from([n]);
            while let Some(u) = queue.pop_front() {
                for v in 0..m {
                    if prev[v] == usize::MAX && cap[u * m + v] > 1e-9 {
                        prev[v] = u;
                        queue.push_back(v);
                    }
                }
            }
            if prev[n + 1] == usize::MAX {
                return flow;
            }
            let (mut f, mut v) = (f64::INFINITY, n + 1);
            while v != n {
                f = f.min(cap[prev[v] * m + v]);
                v = prev[v];
            }
            let mut v = n + 1;
            while v != n {
                cap[prev[v] * m + v] -= f;
                cap[v * m + prev[v]] += f;
                v = prev[v];
            }
            flow += f;
        }
    }

    #[test]
    fn a_graph_made_from_edges_cuts_as_one_built_arc_by_arc() {
        // The same arcs in the same order per node: the same flow to the
        // bit and the same labels, also after terminal changes resume it.
        let mut rng = SplitMix64::new(23);
        for case in 0..30 {
            let (w, h) = (4 + rng.below(20), 4 + rng.below(20));
            let n = w * h;
            let sym: Vec<(u32, u32, f32)> = grid_edges(w, h, &mut rng)
                .into_iter()
                .map(|(i, j, c, _)| (i as u32, j as u32, c))
                .collect();
            let mut built = Graph::new(n, sym.len());
            for &(i, j, c) in &sym {
                built.add_edge(i as usize, j as usize, c, c);
            }
            let mut made = Graph::from_edges(n, &sym);
            for round in 0..3 {
                for i in 0..n {
                    if round == 0 || rng.below(3) == 0 {
                        let (s, t) = ((rng.unit() * 4.0) as f32, (rng.unit() * 4.0) as f32);
                        built.set_terminal(i, s, t);
                        made.set_terminal(i, s, t);
                    }
                }
                let (a, b) = (built.maxflow(), made.maxflow());
                assert_eq!(a.to_bits(), b.to_bits(), "case {case}, round {round}");
                assert!(
                    (0..n).all(|i| built.is_source(i) == made.is_source(i)),
                    "case {case}, round {round}"
                );
            }
        }
    }

    /// The 4-neighbour edges of a `w × h` grid, random capacities each way.
    fn grid_edges(w: usize, h: usize, rng: &mut SplitMix64) -> Vec<(usize, usize, f32, f32)> {
        let mut edges = vec![];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if x + 1 < w {
                    edges.push((i, i + 1, (rng.unit() * 3.0) as f32, (rng.unit() * 3.0) as f32));
                }
                if y + 1 < h {
                    edges.push((i, i + w, (rng.unit() * 3.0) as f32, (rng.unit() * 3.0) as f32));
                }
            }
        }
        edges
    }

    #[test]
    fn max_flow_matches_edmonds_karp_on_larger_grids() {
        // 2D grids with random terminal links and weights: many paths share
        // arcs, so trees are orphaned and re-adopted many times.
        let mut rng = SplitMix64::new(11);
        for case in 0..40 {
            let (w, h) = (4 + rng.below(9), 4 + rng.below(9));
            let n = w * h;
            let term: Vec<(f32, f32)> = (0..n)
                .map(|_| match rng.below(4) {
                    0 => ((rng.unit() * 5.0) as f32, 0.0),
                    1 => (0.0, (rng.unit() * 5.0) as f32),
                    2 => ((rng.unit() * 2.0) as f32, (rng.unit() * 2.0) as f32),
                    _ => (0.0, 0.0),
                })
                .collect();
            let edges = grid_edges(w, h, &mut rng);
            let mut g = graph(&term, &edges);
            let flow = g.maxflow();
            let reference = edmonds_karp(n, &term, &edges);
            assert!(
                (flow - reference).abs() < 1e-3 * (1.0 + reference),
                "case {case} ({w}x{h}): {flow} vs {reference}"
            );
        }
    }

    /// Capacity of the cut `g` reports, under these capacities.
    fn labelling_cost(g: &Graph, term: &[(f32, f32)], edges: &[(usize, usize, f32, f32)]) -> f64 {
        let t: f64 = (0..term.len())
            .map(|i| if g.is_source(i) { term[i].1 } else { term[i].0 } as f64)
            .sum();
        t + edges
            .iter()
            .map(|&(i, j, c, r)| match (g.is_source(i), g.is_source(j)) {
                (true, false) => c as f64,
                (false, true) => r as f64,
                _ => 0.0,
            })
            .sum::<f64>()
    }

    #[test]
    fn a_resumed_max_flow_cuts_the_changed_graph_minimally() {
        // Grids solved, then most terminal capacities changed (some to
        // zero, some across to the other terminal, some made hard), and
        // solved again from the first run's trees: the cut must be a
        // minimum cut of the changed graph, as a fresh solve finds.
        let mut rng = SplitMix64::new(5);
        let term_of = |r: &mut SplitMix64| -> (f32, f32) {
            match r.below(6) {
                0 => ((r.unit() * 5.0) as f32, 0.0),
                1 => (0.0, (r.unit() * 5.0) as f32),
                2 | 3 => ((r.unit() * 2.0) as f32, (r.unit() * 2.0) as f32),
                4 => (HARD, 0.0),
                _ => (0.0, 0.0),
            }
        };
        let (mut changed_sides, mut cases) = (0, 0);
        for case in 0..60 {
            let (w, h) = (3 + rng.below(8), 3 + rng.below(8));
            let n = w * h;
            let term: Vec<(f32, f32)> = (0..n).map(|_| term_of(&mut rng)).collect();
            let edges = grid_edges(w, h, &mut rng);
            let mut g = graph(&term, &edges);
            g.maxflow();
            let before: Vec<bool> = (0..n).map(|i| g.is_source(i)).collect();
            // Up to three rounds of changes, each solved from the last.
            let mut now = term.clone();
            for _round in 0..1 + rng.below(3) {
                for (i, t) in now.iter_mut().enumerate() {
                    if t.0 < HARD && rng.unit() < 0.6 {
                        *t = term_of(&mut rng);
                        g.set_terminal(i, t.0, t.1);
                    }
                }
                g.maxflow();
                let mut fresh = graph(&now, &edges);
                let best = fresh.maxflow();
                let got = labelling_cost(&g, &now, &edges);
                let tol = 1e-3 * (1.0 + best.min(1e6));
                assert!(best < 1e15, "case {case}: a finite cut exists");
                assert!(
                    (got - best).abs() < tol,
                    "case {case}: resumed cut {got}, minimum {best}"
                );
                cases += 1;
            }
            changed_sides += (0..n).filter(|&i| g.is_source(i) != before[i]).count();
        }
        assert!(cases > 60 && changed_sides > 100, "the changes must move the cut");
    }

    #[test]
    fn resumed_cuts_of_small_chains_match_fresh_ones() {
        // Thousands of short chains with small integer capacities (many
        // ties, nodes switching trees, nodes left with no terminal link),
        // changed once after a first solve.
        let mut rng = SplitMix64::new(1);
        let term_of = |r: &mut SplitMix64| -> (f32, f32) {
            match r.below(4) {
                0 => (r.below(5) as f32, 0.0),
                1 => (0.0, r.below(5) as f32),
                2 => (r.below(3) as f32, r.below(3) as f32),
                _ => (0.0, 0.0),
            }
        };
        for case in 0..20_000 {
            let n = 2 + rng.below(5);
            let term: Vec<(f32, f32)> = (0..n).map(|_| term_of(&mut rng)).collect();
            let edges: Vec<(usize, usize, f32, f32)> = (0..n - 1)
                .map(|i| (i, i + 1, rng.below(4) as f32, rng.below(4) as f32))
                .collect();
            let mut g = graph(&term, &edges);
            g.maxflow();
            let mut now = term.clone();
            for (i, t) in now.iter_mut().enumerate() {
                if rng.below(2) == 0 {
                    *t = term_of(&mut rng);
                    g.set_terminal(i, t.0, t.1);
                }
            }
            g.maxflow();
            let best = graph(&now, &edges).maxflow();
            let got = labelling_cost(&g, &now, &edges);
            assert!(
                (got - best).abs() < 1e-6,
                "case {case}: resumed cut {got}, minimum {best}"
            );
        }
    }

    #[test]
    fn a_chain_is_cut_at_its_weakest_link() {
        // source → 0 — 1 — 2 — 3 → sink, link 1–2 the weakest.
        let mut g = Graph::new(4, 3);
        g.add_terminal(0, HARD, 0.0);
        g.add_terminal(3, 0.0, HARD);
        for (i, c) in [(0, 5.0), (1, 1.5), (2, 4.0)] {
            g.add_edge(i, i + 1, c, c);
        }
        assert!((g.maxflow() - 1.5).abs() < 1e-9);
        let sides: Vec<bool> = (0..4).map(|i| g.is_source(i)).collect();
        assert_eq!(sides, [true, true, false, false]);
    }
}
