//! A bounding volume hierarchy over primitives given by their bounds: binned
//! surface-area heuristic, binary nodes in depth-first order, leaves of a few
//! primitives. One builder serves the triangles of a mesh and the top level (boxes,
//! triangles, mesh instances); traversal belongs to the callers, which know their
//! primitives.
//!
//! It knows nothing of meshes or scenes, and sits below both: a mesh's geometry keeps
//! its hierarchy with it ([`crate::mesh::accel`]), built once for every object and frame
//! that shows the file.

use crate::bounds::{Bounds, SlabRay};

/// Most primitives in a leaf.
const LEAF_MAX: usize = 4;
/// Bins of the surface-area heuristic.
const BINS: usize = 12;
/// Deepest node; traversal stacks hold this many entries. Splits by count past a depth
/// of [`DEPTH_MAX`] − 2, so it is never exceeded.
pub(crate) const DEPTH_MAX: usize = 64;

#[derive(Clone, Copy, Debug)]
pub(crate) struct Node {
    pub bounds: Bounds,
    /// A leaf's first primitive (in [`Hierarchy::order`]), or an inner node's first
    /// child (the second follows it).
    pub start: u32,
    /// A leaf's primitive count; 0 for an inner node.
    pub count: u32,
}

#[derive(Clone, Debug, Default)]
pub(crate) struct Hierarchy {
    pub nodes: Vec<Node>,
    /// Primitive indices in leaf order.
    pub order: Vec<u32>,
}

impl Hierarchy {
    /// The hierarchy over primitives with bounds `boxes` (none if there are none).
    pub fn build(boxes: &[Bounds]) -> Hierarchy {
        let mut order: Vec<u32> = (0..boxes.len() as u32).collect();
        let centroids: Vec<[f64; 3]> = boxes
            .iter()
            .map(|b| std::array::from_fn(|k| b.centroid(k)))
            .collect();
        let nodes = if boxes.is_empty() {
            Vec::new()
        } else {
            subtree(0, 0, boxes, &centroids, &mut order)
        };
        Hierarchy { nodes, order }
    }

    pub fn root_bounds(&self) -> Option<Bounds> {
        self.nodes.first().map(|n| n.bounds)
    }

    /// Visits the leaves the ray may reach before `t_max()` (re-read after each leaf,
    /// so a closer hit prunes the rest), nearer children first, with every box widened
    /// by `margin`; `leaf(primitives, exit)` returns `true` to stop. Boxes entered
    /// exactly at `t_max()` are still visited, so equal distances can be compared.
    #[inline(always)]
    pub fn walk(
        &self,
        ray: &SlabRay,
        margin: f64,
        mut t_max: impl FnMut() -> f64,
        mut leaf: impl FnMut(&[u32], f64) -> bool,
    ) {
        let Some(root) = self.nodes.first() else {
            return;
        };
        if root.bounds.lo[0] > root.bounds.hi[0] {
            return;
        }
        // Each node is tested once, by its parent (the root here); a node waiting on
        // the stack keeps where the ray enters it, and is skipped when a hit found
        // meanwhile comes before that.
        let Some((_, root_exit)) = ray.enter(&root.bounds, margin, t_max()) else {
            return;
        };
        let mut stack = [(0u32, 0.0f64, 0.0f64); DEPTH_MAX];
        let mut top = 0usize;
        let (mut node, mut exit) = (0u32, root_exit);
        loop {
            let n = &self.nodes[node as usize];
            if n.count > 0 {
                let first = n.start as usize;
                if leaf(&self.order[first..first + n.count as usize], exit) {
                    return;
                }
            } else {
                let limit = t_max();
                let (a, b) = (n.start, n.start + 1);
                let da = ray.enter(&self.nodes[a as usize].bounds, margin, limit);
                let db = ray.enter(&self.nodes[b as usize].bounds, margin, limit);
                match (da, db) {
                    (Some((ta, xa)), Some((tb, xb))) => {
                        let ((near, near_exit), far) = if tb < ta {
                            ((b, xb), (a, ta, xa))
                        } else {
                            ((a, xa), (b, tb, xb))
                        };
                        stack[top] = far;
                        top += 1;
                        (node, exit) = (near, near_exit);
                        continue;
                    }
                    (Some((_, xa)), None) => {
                        (node, exit) = (a, xa);
                        continue;
                    }
                    (None, Some((_, xb))) => {
                        (node, exit) = (b, xb);
                        continue;
                    }
                    (None, None) => {}
                }
            }
            loop {
                if top == 0 {
                    return;
                }
                top -= 1;
                let (next, enter, next_exit) = stack[top];
                // Entered exactly at the best distance: still visited, for ties.
                if enter <= t_max() {
                    (node, exit) = (next, next_exit);
                    break;
                }
            }
        }
    }
}

/// Subtrees of at least this many primitives are built in parallel, when the pool has
/// more than one thread; below it, one thread builds faster than two can share.
const PARALLEL_MIN: usize = 8_192;

/// Where primitives `order` go: their bounds, and either a leaf (`None`) or the position in `order`
/// where they were split in two, after reordering them.
fn choose(
    depth: usize,
    boxes: &[Bounds],
    centroids: &[[f64; 3]],
    order: &mut [u32],
) -> (Bounds, Option<usize>) {
    let mut bounds = Bounds::EMPTY;
    let mut cb = Bounds::EMPTY;
    for &p in order.iter() {
        bounds = bounds.union(&boxes[p as usize]);
        let c = centroids[p as usize];
        cb.lo = std::array::from_fn(|k| cb.lo[k].min(c[k]));
        cb.hi = std::array::from_fn(|k| cb.hi[k].max(c[k]));
    }
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
        count / 2
    };
    let by_count = !(extent > 0.0 && extent.is_finite()) || depth + 2 >= DEPTH_MAX;
    if by_count {
        // All centroids in one place (or too deep): halves by count, in order.
        if count <= LEAF_MAX {
            return (bounds, None);
        }
        return (bounds, Some(halve(order)));
    }
    let bin_of = |p: u32| {
        let x = (centroids[p as usize][axis] - cb.lo[axis]) / extent * BINS as f64;
        (x as usize).min(BINS - 1)
    };
    let mut bin_bounds = [Bounds::EMPTY; BINS];
    let mut bin_count = [0usize; BINS];
    for &p in order.iter() {
        let b = bin_of(p);
        bin_bounds[b] = bin_bounds[b].union(&boxes[p as usize]);
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
    (bounds, Some(i))
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
) -> Vec<Node> {
    if order.len() >= PARALLEL_MIN && rayon::current_num_threads() > 1 {
        let count = order.len();
        let (bounds, cut) = choose(depth, boxes, centroids, order);
        let Some(mid) = cut else {
            return vec![Node {
                bounds,
                start: base as u32,
                count: count as u32,
            }];
        };
        let (low, high) = order.split_at_mut(mid);
        let (left, right) = rayon::join(
            || subtree(base, depth + 1, boxes, centroids, low),
            || subtree(base + mid, depth + 1, boxes, centroids, high),
        );
        return joined(bounds, left, right);
    }
    let mut nodes = vec![Node {
        bounds: Bounds::EMPTY,
        start: 0,
        count: 0,
    }];
    split(0, base, depth, boxes, centroids, order, &mut nodes);
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
fn split(
    index: usize,
    base: usize,
    depth: usize,
    boxes: &[Bounds],
    centroids: &[[f64; 3]],
    order: &mut [u32],
    nodes: &mut Vec<Node>,
) {
    let count = order.len();
    let (bounds, cut) = choose(depth, boxes, centroids, order);
    let Some(mid) = cut else {
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
    split(first, base, depth + 1, boxes, centroids, low, nodes);
    split(
        first + 1,
        base + mid,
        depth + 1,
        boxes,
        centroids,
        high,
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
                    |prims, _| {
                        for &p in prims {
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

    /// The tree read from its root: each node's bounds and, for a leaf, its primitives.
    fn canonical(h: &Hierarchy) -> Vec<(Bounds, Vec<u32>)> {
        let mut out = Vec::new();
        let mut stack = vec![0usize];
        while let Some(i) = stack.pop() {
            let n = h.nodes[i];
            if n.count > 0 {
                let first = n.start as usize;
                out.push((n.bounds, h.order[first..first + n.count as usize].to_vec()));
            } else {
                out.push((n.bounds, Vec::new()));
                stack.push(n.start as usize + 1);
                stack.push(n.start as usize);
            }
        }
        out
    }

    /// Built on two threads, the hierarchy is the very tree one thread builds: only
    /// where its nodes sit in memory differs.
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
        let one = pool(1).install(|| Hierarchy::build(&boxes));
        let two = pool(2).install(|| Hierarchy::build(&boxes));
        assert_eq!(one.order, two.order);
        assert_eq!(one.nodes.len(), two.nodes.len());
        assert!(canonical(&one) == canonical(&two));
    }
}
