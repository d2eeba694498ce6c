//! A bounding volume hierarchy over primitives given by their bounds: built as a binary
//! tree by the binned surface-area heuristic, then collapsed into nodes of four children
//! whose boxes are tested together, four doubles side by side, with leaves of up to four
//! primitives. One builder serves the triangles of a mesh and the top level (boxes,
//! triangles, mesh instances); what a leaf holds is the callers' business.
//!
//! The children's boxes are kept in single precision, relative to a point of the
//! root's box (so that a mesh far from the origin keeps tight boxes), rounded outward,
//! and tested as the spheres' hierarchy tests its own ([`crate::bvh`], "Margin"): the
//! ray's origin shifted by a margin δ = 2⁻²²·(|o|₁ + S) + 8m + 2⁻¹²⁰ that covers the
//! single-precision test's rounding and m, the caller's own margin for its primitives'
//! tests, and exit distances given the slack K. Culling is thus conservative: the
//! primitives a traversal tests include every one the ray meets, whatever the tree's
//! shape, and the nearest hit (the smallest distance, ties to the primitive listed
//! first) does not depend on it. Rays beyond that argument's range (|o|₁ or S above
//! 10³⁰, a direction's length outside [2⁻²⁰, 2²⁰]) enter every box instead.
//!
//! It knows nothing of meshes or scenes, and sits below both: a mesh's geometry keeps
//! its hierarchy with it ([`crate::mesh::accel`]), built once for every object and frame
//! that shows the file.

use std::mem::MaybeUninit;

use crate::bounds::{Bounds, SlabRay};
use crate::bvh::{down32, up32};
use crate::vec3::{Vec3, LANES};

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

/// A node of four children: their boxes in single precision relative to
/// [`Hierarchy::origin`], per axis the lower sides (`bounds[2·axis]`) and the upper
/// ones (`bounds[2·axis + 1]`), rounded outward (an empty slot's are +∞ and −∞, which
/// no ray enters), and what each holds.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(16))]
pub(crate) struct WideNode {
    pub bounds: [[f32; LANES]; 6],
    /// An inner node's index, `LEAF | leaf index`, or [`EMPTY`].
    pub child: [u32; LANES],
}

impl WideNode {
    /// Child `c`'s box relative to the hierarchy's origin, in double precision (exactly
    /// the stored box).
    pub fn child_bounds(&self, c: usize) -> Bounds {
        Bounds {
            lo: std::array::from_fn(|k| f64::from(self.bounds[2 * k][c])),
            hi: std::array::from_fn(|k| f64::from(self.bounds[2 * k + 1][c])),
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
    /// The point the nodes' boxes are relative to: the root box's centre.
    pub origin: [f64; 3],
    /// S: the largest |corner − origin|₁ of the root's box (rounded up).
    pub scale: f64,
}

impl Hierarchy {
    /// The hierarchy over primitives with bounds `boxes` (none if there are none).
    pub fn build(boxes: &[Bounds]) -> Hierarchy {
        let (binary, order) = binary(boxes);
        if binary.is_empty() {
            return Hierarchy::default();
        }
        let root = binary[0].bounds;
        let origin = std::array::from_fn(|k| root.centroid(k));
        let scale = root
            .corners()
            .iter()
            .map(|c| (0..3).map(|k| (c[k] - origin[k]).abs()).sum::<f64>())
            .fold(0.0f64, f64::max)
            * (1.0 + 1e-12);
        let mut nodes = Vec::with_capacity(binary.len() / 3 + 1);
        let mut leaves = Vec::with_capacity(binary.len() / 2 + 1);
        collapse(&binary, 0, origin, &mut nodes, &mut leaves);
        Hierarchy {
            nodes,
            leaves,
            order,
            root: Some(root),
            origin,
            scale,
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
    /// by `margin` (besides the single-precision test's own margin); `leaf(index)`
    /// returns `true` to stop. Boxes entered at `t_max()` (within the slack) are still
    /// visited, so equal distances can be compared.
    #[inline(always)]
    pub fn walk(
        &self,
        ray: &SlabRay,
        margin: f64,
        mut t_max: impl FnMut() -> f64,
        mut leaf: impl FnMut(u32) -> bool,
    ) {
        if self.nodes.is_empty() {
            return;
        }
        let wide = WideRay::new(ray, margin, self);
        // Each node's children are tested together, by the node; a child waiting on the
        // stack keeps where the ray enters it, and is skipped when a hit found meanwhile
        // comes before that.
        let mut stack = Stack::<(u32, f32)>::new();
        let mut node = 0u32;
        loop {
            let n = &self.nodes[node as usize];
            let (enter, mut bits) = wide.enter(n, up32(t_max()));
            // The children entered, nearest first (equal entries in slot order).
            let mut hits = [(0.0f32, 0u32); LANES];
            let mut count = 0;
            while bits != 0 {
                let c = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                insert_sorted(&mut hits, count, (enter[c], n.child[c]));
                count += 1;
            }
            for &h in hits[..count].iter().rev() {
                stack.push((h.1, h.0));
            }
            loop {
                let Some((child, entry)) = stack.pop() else {
                    return;
                };
                if entry > up32(t_max()) * SLACK {
                    continue;
                }
                if child & LEAF != 0 {
                    if leaf(child & !LEAF) {
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

/// Inserts `entry` among the first `count` entries of `hits`, which are in ascending
/// order of their first element, keeping that order (an equal key goes after those
/// already there): the children a traversal entered, nearest first.
#[inline(always)]
pub(crate) fn insert_sorted<K: PartialOrd + Copy, V: Copy>(
    hits: &mut [(K, V); LANES],
    count: usize,
    entry: (K, V),
) {
    let mut at = count;
    while at > 0 && hits[at - 1].0 > entry.0 {
        hits[at] = hits[at - 1];
        at -= 1;
    }
    hits[at] = entry;
}

/// Largest |o|₁ and S for which the margin argument holds.
const MAX_SCALE: f64 = 1e30;
/// The margin δ per unit of |o|₁ + S.
const MARGIN: f64 = 1.0 / (1u64 << 22) as f64;
/// The margin's floor, far above the rounding of values near the underflow range.
const MARGIN_FLOOR: f64 = 1.0 / (1u128 << 120) as f64;
/// The slack factor K of the entry test t₀ ≤ t₁·K.
const SLACK: f32 = 1.0 + 1.0 / (1u32 << 20) as f32;

/// A ray prepared for a hierarchy's single-precision box tests: per axis its origin
/// relative to the hierarchy's, shifted by ±δ and rounded, once for the side met first
/// and once for the other, and its reciprocal direction.
#[derive(Clone, Copy, Debug)]
pub(crate) struct WideRay {
    origin_near: [f32; 3],
    origin_far: [f32; 3],
    inv: [f32; 3],
    /// Per axis, the row of [`WideNode::bounds`] met first (the upper side for a
    /// negative direction) and the other.
    near: [usize; 3],
    far: [usize; 3],
}

impl WideRay {
    #[inline(always)]
    pub fn new(ray: &SlabRay, margin: f64, h: &Hierarchy) -> WideRay {
        let o: [f64; 3] = std::array::from_fn(|k| ray.origin[k] - h.origin[k]);
        let reach = o[0].abs() + o[1].abs() + o[2].abs();
        let d = ray.inv.map(|inv| 1.0 / inv);
        let d2 = Vec3::new(d[0], d[1], d[2]).dot(Vec3::new(d[0], d[1], d[2]));
        let within = reach <= MAX_SCALE
            && h.scale <= MAX_SCALE
            && d2 >= 1.0 / (1u64 << 40) as f64
            && d2 <= (1u64 << 40) as f64
            && margin.is_finite();
        // Beyond the argument's range: every box is entered.
        let delta = if within {
            (reach + h.scale) * MARGIN + 8.0 * margin + MARGIN_FLOOR
        } else {
            f64::INFINITY
        };
        let negative = ray.inv.map(f64::is_sign_negative);
        let plus = o.map(|o| (o + delta) as f32);
        let minus = o.map(|o| (o - delta) as f32);
        WideRay {
            origin_near: std::array::from_fn(|k| if negative[k] { minus[k] } else { plus[k] }),
            origin_far: std::array::from_fn(|k| if negative[k] { plus[k] } else { minus[k] }),
            inv: ray.inv.map(|inv| inv as f32),
            near: std::array::from_fn(|k| 2 * k + usize::from(negative[k])),
            far: std::array::from_fn(|k| 2 * k + 1 - usize::from(negative[k])),
        }
    }

    /// Where the ray enters each child of `node` and the children it enters before
    /// `t_max` (rounded up; bit c for child c): entry ≤ exit·K, as in [`crate::bvh`].
    #[inline(always)]
    pub fn enter(&self, node: &WideNode, t_max: f32) -> ([f32; LANES], u32) {
        let mut t0 = [0.0f32; LANES];
        let mut t1 = [t_max; LANES];
        for axis in 0..3 {
            let near_side = &node.bounds[self.near[axis]];
            let far_side = &node.bounds[self.far[axis]];
            for c in 0..LANES {
                let near = (near_side[c] - self.origin_near[axis]) * self.inv[axis];
                let far = (far_side[c] - self.origin_far[axis]) * self.inv[axis];
                t0[c] = if near > t0[c] { near } else { t0[c] };
                t1[c] = if far < t1[c] { far } else { t1[c] };
            }
        }
        let mut mask = 0;
        for c in 0..LANES {
            mask |= u32::from(t0[c] <= t1[c] * SLACK) << c;
        }
        (t0, mask)
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
    origin: [f64; 3],
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
        bounds: std::array::from_fn(|row| {
            [if row % 2 == 0 {
                f32::INFINITY
            } else {
                f32::NEG_INFINITY
            }; LANES]
        }),
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
            collapse(binary, kid, origin, nodes, leaves)
        };
        let node = &mut nodes[at];
        node.child[c] = code;
        for (axis, &o) in origin.iter().enumerate() {
            node.bounds[2 * axis][c] = down32(k.bounds.lo[axis] - o);
            node.bounds[2 * axis + 1][c] = up32(k.bounds.hi[axis] - o);
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
                    |leaf| {
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
