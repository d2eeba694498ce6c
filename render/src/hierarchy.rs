//! A bounding volume hierarchy over primitives given by their bounds: built as a binary
//! tree by the binned surface-area heuristic, then collapsed into nodes of four children
//! whose boxes are tested together, four doubles side by side, with leaves of up to four
//! primitives. One builder serves the triangles of a mesh and the top level (boxes,
//! triangles, mesh instances); what a leaf holds is the callers' business.
//!
//! The boxes stay in double precision and each child's slab test is the one of
//! [`SlabRay::enter`], lane by lane: culling is conservative, so the primitives a
//! traversal tests include every one the ray meets, whatever the tree's shape, and the
//! nearest hit (the smallest distance, ties to the primitive listed first) does not
//! depend on it.
//!
//! It knows nothing of meshes or scenes, and sits below both: a mesh's geometry keeps
//! its hierarchy with it ([`crate::mesh::accel`]), built once for every object and frame
//! that shows the file.

use std::mem::MaybeUninit;

use crate::bounds::{Bounds, SlabRay, EXIT_SCALE};
use crate::vec3::{F4, LANES};

/// Most primitives in a leaf.
const LEAF_MAX: usize = 4;
/// Bins of the surface-area heuristic.
const BINS: usize = 12;
/// Deepest binary node. Splits by count past a depth of [`DEPTH_MAX`] − 2, so it is
/// never exceeded; a wide node holds at least two binary levels, so traversal stacks of
/// [`STACK`] entries (three waiting siblings a level) never overflow.
pub(crate) const DEPTH_MAX: usize = 64;

/// Entries of a traversal stack.
pub(crate) const STACK: usize = 3 * DEPTH_MAX;

/// A child slot that holds nothing.
pub(crate) const EMPTY: u32 = u32::MAX;
/// The bit of a child slot that says it holds a leaf (the rest is the leaf's index).
pub(crate) const LEAF: u32 = 1 << 31;

/// A node of the binary tree, as built.
#[derive(Clone, Copy, Debug)]
struct Node {
    pub bounds: Bounds,
    /// A leaf's first primitive (in [`Hierarchy::order`]), or an inner node's first
    /// child (the second follows it).
    pub start: u32,
    /// A leaf's primitive count; 0 for an inner node.
    pub count: u32,
}

/// A traversal stack that costs nothing to make (a walk makes one per ray): entries are
/// written before they are read.
pub(crate) struct Stack<T: Copy> {
    items: [MaybeUninit<T>; STACK],
    top: usize,
}

impl<T: Copy> Stack<T> {
    #[inline(always)]
    pub fn new() -> Self {
        Stack {
            items: [const { MaybeUninit::uninit() }; STACK],
            top: 0,
        }
    }

    #[inline(always)]
    pub fn push(&mut self, item: T) {
        self.items[self.top] = MaybeUninit::new(item);
        self.top += 1;
    }

    #[inline(always)]
    pub fn pop(&mut self) -> Option<T> {
        if self.top == 0 {
            return None;
        }
        self.top -= 1;
        // SAFETY: every entry below `top` was written by `push`.
        Some(unsafe { self.items[self.top].assume_init() })
    }
}

/// A node of four children: per axis, their lower and upper bounds side by side (an
/// empty slot's are +∞ and −∞, which no ray enters), and what each holds.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(align(32))]
pub(crate) struct WideNode {
    /// `bounds[axis][0]` the children's lower bounds, `bounds[axis][1]` their upper.
    pub bounds: [[F4; 2]; 3],
    /// An inner node's index, `LEAF | leaf index`, or [`EMPTY`].
    pub child: [u32; LANES],
}

impl WideNode {
    /// Child `c`'s bounds.
    pub fn child_bounds(&self, c: usize) -> Bounds {
        Bounds {
            lo: std::array::from_fn(|k| self.bounds[k][0].0[c]),
            hi: std::array::from_fn(|k| self.bounds[k][1].0[c]),
        }
    }
}

/// A leaf: `count` primitives from position `start` of [`Hierarchy::order`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Leaf {
    pub start: u32,
    pub count: u32,
}

#[derive(Clone, Debug, Default)]
pub(crate) struct Hierarchy {
    /// The root first; empty when there are no primitives.
    pub nodes: Vec<WideNode>,
    pub leaves: Vec<Leaf>,
    /// Primitive indices in leaf order.
    pub order: Vec<u32>,
    root: Option<Bounds>,
}

impl Hierarchy {
    /// The hierarchy over primitives with bounds `boxes` (none if there are none).
    pub fn build(boxes: &[Bounds]) -> Hierarchy {
        let (binary, order) = binary(boxes);
        if binary.is_empty() {
            return Hierarchy::default();
        }
        let mut nodes = Vec::with_capacity(binary.len() / 3 + 1);
        let mut leaves = Vec::with_capacity(binary.len() / 2 + 1);
        collapse(&binary, 0, &mut nodes, &mut leaves);
        Hierarchy {
            nodes,
            leaves,
            order,
            root: Some(binary[0].bounds),
        }
    }

    pub fn root_bounds(&self) -> Option<Bounds> {
        self.root
    }

    /// The primitives of leaf `leaf`.
    #[inline(always)]
    pub fn primitives(&self, leaf: u32) -> &[u32] {
        let l = self.leaves[leaf as usize];
        &self.order[l.start as usize..(l.start + l.count) as usize]
    }

    /// Visits the leaves the ray may reach before `t_max()` (re-read after each leaf,
    /// so a closer hit prunes the rest), nearer children first, with every box widened
    /// by `margin`; `leaf(index, exit)` (the leaf's index and the distance where the ray
    /// leaves its box) returns `true` to stop. Boxes entered exactly at `t_max()` are
    /// still visited, so equal distances can be compared.
    #[inline(always)]
    pub fn walk(
        &self,
        ray: &SlabRay,
        margin: f64,
        mut t_max: impl FnMut() -> f64,
        mut leaf: impl FnMut(u32, f64) -> bool,
    ) {
        if self.nodes.is_empty() {
            return;
        }
        let wide = WideRay::new(ray, margin);
        // Each node's children are tested together, by the node; a child waiting on the
        // stack keeps where the ray enters and leaves it, and is skipped when a hit found
        // meanwhile comes before its entry.
        let mut stack = Stack::<(u32, f64, f64)>::new();
        let mut node = 0u32;
        loop {
            let n = &self.nodes[node as usize];
            let (enter, exit, mut bits) = wide.enter(n, t_max());
            // The children entered, nearest first (equal entries in slot order).
            let mut hits = [(0.0f64, 0u32, 0.0f64); LANES];
            let mut count = 0;
            while bits != 0 {
                let c = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let entry = (enter.0[c], n.child[c], exit.0[c]);
                let mut at = count;
                while at > 0 && hits[at - 1].0 > entry.0 {
                    hits[at] = hits[at - 1];
                    at -= 1;
                }
                hits[at] = entry;
                count += 1;
            }
            for &h in hits[..count].iter().rev() {
                stack.push((h.1, h.0, h.2));
            }
            loop {
                let Some((child, entry, exit)) = stack.pop() else {
                    return;
                };
                // Entered exactly at the best distance: still visited, for ties.
                if entry > t_max() {
                    continue;
                }
                if child & LEAF != 0 {
                    if leaf(child & !LEAF, exit) {
                        return;
                    }
                    continue;
                }
                node = child;
                break;
            }
        }
    }
}

/// A ray and its margin set up for the four slab tests of a wide node: each lane
/// computes what [`SlabRay::enter`] computes for that child, with the entry and exit
/// faces chosen by the direction's sign instead of by comparing the two.
#[derive(Clone, Copy, Debug)]
pub(crate) struct WideRay {
    origin: [F4; 3],
    inv: [F4; 3],
    /// Per axis, the margin subtracted at the entry face and added at the exit face
    /// (−margin where the direction is negative: the entry face is then the upper one).
    margin: [F4; 3],
    /// Per axis, 1 where the direction is negative (the entry face is the upper one).
    near: [usize; 3],
}

impl WideRay {
    #[inline(always)]
    pub fn new(ray: &SlabRay, margin: f64) -> WideRay {
        let near: [usize; 3] = std::array::from_fn(|k| usize::from(ray.inv[k].is_sign_negative()));
        WideRay {
            origin: ray.origin.map(F4::splat),
            inv: ray.inv.map(F4::splat),
            margin: std::array::from_fn(|k| F4::splat(if near[k] == 1 { -margin } else { margin })),
            near,
        }
    }

    /// Where the ray enters and leaves each child of `node` before `t_max`, and the
    /// children it enters (bit c for child c). Lane c is [`SlabRay::enter`] of child c:
    /// with a positive direction the entry is (lo − m − o)·inv and the exit (hi + m −
    /// o)·inv, with a negative one (hi − (−m) − o)·inv and (lo + (−m) − o)·inv, the same
    /// values; where one is NaN (the ray in a face's plane) that face is left out, which
    /// only widens the interval.
    #[inline(always)]
    pub fn enter(&self, node: &WideNode, t_max: f64) -> (F4, F4, u32) {
        let mut t0 = F4::splat(0.0);
        let mut t1 = F4::splat(t_max);
        for k in 0..3 {
            let near =
                ((node.bounds[k][self.near[k]] - self.margin[k]) - self.origin[k]) * self.inv[k];
            let far = ((node.bounds[k][1 - self.near[k]] + self.margin[k]) - self.origin[k])
                * self.inv[k]
                * EXIT_SCALE;
            t0 = near.gt(t0).select(near, t0);
            t1 = far.lt(t1).select(far, t1);
        }
        (t0, t1, t0.le(t1).bitmask())
    }
}

/// The binary tree over primitives with bounds `boxes`, its root first, and the
/// primitives in leaf order.
fn binary(boxes: &[Bounds]) -> (Vec<Node>, Vec<u32>) {
    let mut order: Vec<u32> = (0..boxes.len() as u32).collect();
    let centroids: Vec<[f64; 3]> = boxes
        .iter()
        .map(|b| std::array::from_fn(|k| b.centroid(k)))
        .collect();
    let nodes = if boxes.is_empty() {
        Vec::new()
    } else {
        subtree(0, 0, boxes, &centroids, &mut order, None)
    };
    (nodes, order)
}

/// Appends the wide node for binary node `index` and those below it (depth first, a
/// node before its children, children in the binary tree's order), and returns its
/// index. A binary leaf at the root becomes a wide node holding it alone.
fn collapse(
    binary: &[Node],
    index: usize,
    nodes: &mut Vec<WideNode>,
    leaves: &mut Vec<Leaf>,
) -> u32 {
    let n = binary[index];
    let mut kids = [0usize; LANES];
    let mut count;
    if n.count > 0 {
        kids[0] = index;
        count = 1;
    } else {
        kids[0] = n.start as usize;
        kids[1] = n.start as usize + 1;
        count = 2;
        // Open the inner child of largest area until there are four (or only leaves).
        while count < LANES {
            let open = (0..count)
                .filter(|&c| binary[kids[c]].count == 0)
                .max_by(|&a, &b| {
                    binary[kids[a]]
                        .bounds
                        .area()
                        .total_cmp(&binary[kids[b]].bounds.area())
                        .then(b.cmp(&a))
                });
            let Some(c) = open else { break };
            let first = binary[kids[c]].start as usize;
            kids.copy_within(c + 1..count, c + 2);
            kids[c] = first;
            kids[c + 1] = first + 1;
            count += 1;
        }
    }
    let at = nodes.len();
    nodes.push(WideNode {
        bounds: [[F4::splat(f64::INFINITY), F4::splat(f64::NEG_INFINITY)]; 3],
        child: [EMPTY; LANES],
    });
    for (c, &kid) in kids[..count].iter().enumerate() {
        let k = binary[kid];
        let code = if k.count > 0 {
            leaves.push(Leaf {
                start: k.start,
                count: k.count,
            });
            LEAF | (leaves.len() as u32 - 1)
        } else {
            collapse(binary, kid, nodes, leaves)
        };
        let node = &mut nodes[at];
        node.child[c] = code;
        for axis in 0..3 {
            node.bounds[axis][0].0[c] = k.bounds.lo[axis];
            node.bounds[axis][1].0[c] = k.bounds.hi[axis];
        }
    }
    at as u32
}

/// Subtrees of at least this many primitives are built in parallel, when the pool has
/// more than one thread; below it, one thread builds faster than two can share.
const PARALLEL_MIN: usize = 8_192;

/// The bounds of a set of primitives and of their centroids.
type Extent = (Bounds, Bounds);

/// The bounds of primitives `order` and of their centroids.
fn extent(boxes: &[Bounds], centroids: &[[f64; 3]], order: &[u32]) -> Extent {
    let mut bounds = Bounds::EMPTY;
    let mut cb = Bounds::EMPTY;
    for &p in order {
        bounds = bounds.union(&boxes[p as usize]);
        cb.grow_by(centroids[p as usize]);
    }
    (bounds, cb)
}

/// How primitives are split: at a position of the reordered `order`, with each half's
/// extent when the bins gave it (a split by count leaves the halves to find theirs).
type Cut = (usize, Option<[Extent; 2]>);

/// Where primitives `order` go: their bounds, and either a leaf (`None`) or the cut
/// where they were split in two, after reordering them. `known` is their extent, if
/// the parent's bins gave it.
fn choose(
    depth: usize,
    boxes: &[Bounds],
    centroids: &[[f64; 3]],
    order: &mut [u32],
    known: Option<Extent>,
) -> (Bounds, Option<Cut>) {
    let (bounds, cb) = known.unwrap_or_else(|| extent(boxes, centroids, order));
    let count = order.len();
    if count <= LEAF_MAX && depth > 0 || count == 1 {
        return (bounds, None);
    }
    let axis = (0..3)
        .max_by(|&a, &b| (cb.hi[a] - cb.lo[a]).total_cmp(&(cb.hi[b] - cb.lo[b])))
        .unwrap_or(0);
    let extent = cb.hi[axis] - cb.lo[axis];
    let halve = |order: &mut [u32]| {
        order.select_nth_unstable_by(count / 2, |&a, &b| {
            centroids[a as usize][axis]
                .total_cmp(&centroids[b as usize][axis])
                .then(a.cmp(&b))
        });
        (count / 2, None)
    };
    let by_count = !(extent > 0.0 && extent.is_finite()) || depth + 2 >= DEPTH_MAX;
    if by_count {
        // All centroids in one place (or too deep): halves by count, in order.
        if count <= LEAF_MAX {
            return (bounds, None);
        }
        return (bounds, Some(halve(order)));
    }
    let lo = cb.lo[axis];
    let scale = BINS as f64 / extent;
    let bin_of = |p: u32| {
        let x = (centroids[p as usize][axis] - lo) * scale;
        (x as usize).min(BINS - 1)
    };
    let mut bin_bounds = [Bounds::EMPTY; BINS];
    let mut bin_centroids = [Bounds::EMPTY; BINS];
    let mut bin_count = [0usize; BINS];
    for &p in order.iter() {
        let b = bin_of(p);
        bin_bounds[b] = bin_bounds[b].union(&boxes[p as usize]);
        bin_centroids[b].grow_by(centroids[p as usize]);
        bin_count[b] += 1;
    }
    // Cost of each cut after bin i: area × count on both sides.
    let mut best = (f64::INFINITY, 0usize);
    let mut right_area = [0.0; BINS];
    let mut acc = Bounds::EMPTY;
    let mut acc_n = 0;
    for i in (1..BINS).rev() {
        acc = acc.union(&bin_bounds[i]);
        acc_n += bin_count[i];
        right_area[i] = acc.area() * acc_n as f64;
    }
    let mut left = Bounds::EMPTY;
    let mut left_n = 0;
    for i in 0..BINS - 1 {
        left = left.union(&bin_bounds[i]);
        left_n += bin_count[i];
        if left_n == 0 || left_n == count {
            continue;
        }
        let cost = left.area() * left_n as f64 + right_area[i + 1];
        if cost < best.0 {
            best = (cost, i);
        }
    }
    let leaf_cost = bounds.area() * count as f64;
    if count <= LEAF_MAX && best.0 >= leaf_cost {
        return (bounds, None);
    }
    if !best.0.is_finite() {
        return (bounds, Some(halve(order)));
    }
    let mut i = 0;
    let mut j = count;
    while i < j {
        if bin_of(order[i]) <= best.1 {
            i += 1;
        } else {
            j -= 1;
            order.swap(i, j);
        }
    }
    // Each half's extent, from its bins.
    let union = |bins: std::ops::Range<usize>| {
        bins.fold((Bounds::EMPTY, Bounds::EMPTY), |(b, c), k| {
            (b.union(&bin_bounds[k]), c.union(&bin_centroids[k]))
        })
    };
    let halves = [union(0..best.1 + 1), union(best.1 + 1..BINS)];
    (bounds, Some((i, Some(halves))))
}

/// The subtree over `order` (which starts at position `base` of the whole order), its
/// root first: halves of at least [`PARALLEL_MIN`] primitives built side by side on
/// the current pool. The tree is the same whatever the threads; only where its nodes
/// sit in memory differs, which no traversal sees.
fn subtree(
    base: usize,
    depth: usize,
    boxes: &[Bounds],
    centroids: &[[f64; 3]],
    order: &mut [u32],
    known: Option<Extent>,
) -> Vec<Node> {
    if order.len() >= PARALLEL_MIN && rayon::current_num_threads() > 1 {
        let count = order.len();
        let (bounds, cut) = choose(depth, boxes, centroids, order, known);
        let Some((mid, halves)) = cut else {
            return vec![Node {
                bounds,
                start: base as u32,
                count: count as u32,
            }];
        };
        let (low, high) = order.split_at_mut(mid);
        let (left, right) = rayon::join(
            || subtree(base, depth + 1, boxes, centroids, low, halves.map(|h| h[0])),
            || {
                subtree(
                    base + mid,
                    depth + 1,
                    boxes,
                    centroids,
                    high,
                    halves.map(|h| h[1]),
                )
            },
        );
        return joined(bounds, left, right);
    }
    let mut nodes = vec![Node {
        bounds: Bounds::EMPTY,
        start: 0,
        count: 0,
    }];
    split(0, base, depth, boxes, centroids, order, known, &mut nodes);
    nodes
}

/// An inner node over two subtrees built apart, laid out as the sequential build lays
/// out children: the node, both roots side by side, then the rest of each subtree.
fn joined(bounds: Bounds, left: Vec<Node>, right: Vec<Node>) -> Vec<Node> {
    let n = left.len();
    let in_left = |k: u32| if k == 0 { 1 } else { k + 2 };
    let in_right = |k: u32| if k == 0 { 2 } else { k + n as u32 + 1 };
    let moved = |node: &Node, to: &dyn Fn(u32) -> u32| Node {
        start: if node.count == 0 {
            to(node.start)
        } else {
            node.start
        },
        ..*node
    };
    let mut nodes = Vec::with_capacity(1 + left.len() + right.len());
    nodes.push(Node {
        bounds,
        start: 1,
        count: 0,
    });
    nodes.push(moved(&left[0], &in_left));
    nodes.push(moved(&right[0], &in_right));
    nodes.extend(left[1..].iter().map(|node| moved(node, &in_left)));
    nodes.extend(right[1..].iter().map(|node| moved(node, &in_right)));
    nodes
}

/// Builds, into `nodes[index]` and on, the subtree over `order` (which starts at
/// position `base` of the whole order), one thread.
#[expect(
    clippy::too_many_arguments,
    reason = "the recursion's state: where the node goes, its primitives and what the parent knows of them"
)]
fn split(
    index: usize,
    base: usize,
    depth: usize,
    boxes: &[Bounds],
    centroids: &[[f64; 3]],
    order: &mut [u32],
    known: Option<Extent>,
    nodes: &mut Vec<Node>,
) {
    let count = order.len();
    let (bounds, cut) = choose(depth, boxes, centroids, order, known);
    let Some((mid, halves)) = cut else {
        nodes[index] = Node {
            bounds,
            start: base as u32,
            count: count as u32,
        };
        return;
    };
    let first = nodes.len();
    let placeholder = Node {
        bounds: Bounds::EMPTY,
        start: 0,
        count: 0,
    };
    nodes.push(placeholder);
    nodes.push(placeholder);
    nodes[index] = Node {
        bounds,
        start: first as u32,
        count: 0,
    };
    let (low, high) = order.split_at_mut(mid);
    split(
        first,
        base,
        depth + 1,
        boxes,
        centroids,
        low,
        halves.map(|h| h[0]),
        nodes,
    );
    split(
        first + 1,
        base + mid,
        depth + 1,
        boxes,
        centroids,
        high,
        halves.map(|h| h[1]),
        nodes,
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vec3::Vec3;

    /// Every primitive a ray's segment meets is in a leaf the walk visits, whatever
    /// the shape of the hierarchy.
    #[test]
    fn the_walk_visits_every_box_the_ray_meets() {
        let mut rng = crate::test_rng::Mix(3);
        for case in 0..50 {
            let n = 1 + (rng.next() % 300) as usize;
            let boxes: Vec<Bounds> = (0..n)
                .map(|_| {
                    let c = Vec3::new(rng.unit(), rng.unit(), rng.unit()) * 10.0;
                    let mut b = Bounds::of_point(c);
                    b.grow(c + Vec3::new(rng.unit(), rng.unit(), rng.unit()));
                    b
                })
                .collect();
            let h = Hierarchy::build(&boxes);
            assert!(h.nodes.len() < 2 * n + 1, "case {case}");
            for _ in 0..50 {
                let o =
                    Vec3::new(rng.unit(), rng.unit(), rng.unit()) * 12.0 - Vec3::new(1.0, 1.0, 1.0);
                let d = (Vec3::new(rng.unit(), rng.unit(), rng.unit()) - Vec3::new(0.5, 0.5, 0.5))
                    .normalize();
                let ray = SlabRay::new(o, d);
                let mut seen = vec![false; n];
                h.walk(
                    &ray,
                    0.0,
                    || f64::INFINITY,
                    |leaf, _| {
                        for &p in h.primitives(leaf) {
                            seen[p as usize] = true;
                        }
                        false
                    },
                );
                for (p, b) in boxes.iter().enumerate() {
                    if ray.enter(b, 0.0, f64::INFINITY).is_some() {
                        assert!(seen[p], "case {case}: box {p} missed");
                    }
                }
            }
        }
    }

    /// The binary tree read from its root: each node's bounds and, for a leaf, its
    /// primitives.
    fn canonical((nodes, order): &(Vec<Node>, Vec<u32>)) -> Vec<(Bounds, Vec<u32>)> {
        let mut out = Vec::new();
        let mut stack = vec![0usize];
        while let Some(i) = stack.pop() {
            let n = nodes[i];
            if n.count > 0 {
                let first = n.start as usize;
                out.push((n.bounds, order[first..first + n.count as usize].to_vec()));
            } else {
                out.push((n.bounds, Vec::new()));
                stack.push(n.start as usize + 1);
                stack.push(n.start as usize);
            }
        }
        out
    }

    /// Built on two threads, the binary tree is the very tree one thread builds (only
    /// where its nodes sit in memory differs), and the wide hierarchy the same bytes.
    #[test]
    fn parallel_and_sequential_builds_give_the_same_tree() {
        let mut rng = crate::test_rng::Mix(5);
        let boxes: Vec<Bounds> = (0..40_000)
            .map(|_| {
                let c = Vec3::new(rng.unit(), rng.unit(), rng.unit()) * 100.0;
                let mut b = Bounds::of_point(c);
                b.grow(c + Vec3::new(rng.unit(), rng.unit(), rng.unit()));
                b
            })
            .collect();
        let pool = |threads| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
        };
        let one = pool(1).install(|| binary(&boxes));
        let two = pool(2).install(|| binary(&boxes));
        assert_eq!(one.1, two.1);
        assert_eq!(one.0.len(), two.0.len());
        assert!(canonical(&one) == canonical(&two));
        // The wide tree is read from the binary one in its order: the same nodes.
        let (one, two) = (
            pool(1).install(|| Hierarchy::build(&boxes)),
            pool(2).install(|| Hierarchy::build(&boxes)),
        );
        assert!(one.nodes == two.nodes && one.leaves == two.leaves && one.order == two.order);
    }
}
