//! A bounding volume hierarchy over a scene's spheres: 4-wide nodes whose child boxes
//! are stored as structure-of-arrays, so one node test is a handful of SIMD operations,
//! and leaves of up to four spheres.
//!
//! It is built once per scene (binned surface area heuristic, then binary nodes pulled
//! up into 4-wide ones) and answers the same questions as the brute-force loop over all
//! spheres, with exactly the same answers:
//!
//! - every sphere it reaches is tested by the same code as in the brute-force loop, so
//!   a hit has the same bits;
//! - a subtree is skipped only if the ray's entry into its box is strictly beyond the
//!   best hit so far (a hit at an equal distance could still win on its lower object
//!   index), or, for shadow rays, at or beyond the light;
//! - boxes are tested with a margin, below, that covers the rounding of both the box
//!   test and the sphere test, so a sphere that the brute-force loop would report as hit
//!   is never in a box the ray is judged to miss;
//! - the sphere a ray leaves is not tested here: its caller tests it (its far-wall root
//!   need not lie near the sphere when the origin is not exactly on it).
//!
//! # Margin
//!
//! A computed sphere hit t lies, in exact arithmetic, within some multiple of ε·(|o| +
//! |centre| + r) of the sphere's box (ε = 2⁻⁵³, o the ray origin): the cancellation-free
//! quadratic of [`crate::geometry`] moves a root only by rounding its inputs, and a
//! grazing root, where the square root magnifies that error, moves along the ray to a
//! point that still lies on the (perturbed) sphere. The box test itself rounds within
//! the same order. Boxes are therefore widened by δ = 2⁻³⁶·(|o|₁ + S), with S the
//! largest |centre|₁ + r of the scene, thousands of times that bound, plus a floor for
//! values near the underflow range. Rays too far out for this argument (|o|₁ > 10¹⁰⁰,
//! non-unit directions) and scenes with S > 10¹⁰⁰ are not traced through the hierarchy
//! at all: callers fall back to the brute-force loop, which gives the same answers.

use std::cmp::Ordering;

use crate::geometry::SphereGeom;
use crate::vec3::{Vec3, F4, LANES, M4};

/// Most spheres in a leaf.
const LEAF_SIZE: usize = 4;
/// Split-plane candidates per axis in the surface area heuristic.
const BINS: usize = 16;
/// Below this binary depth the heuristic chooses splits; deeper, splits are at the
/// median, which halves the sphere count and so bounds the depth for any input.
const SAH_MAX_DEPTH: usize = 40;
/// Entries of the traversal stack. A deeper tree than it can hold makes the traversal
/// report an overflow, and its caller then uses the brute-force loop.
const STACK_SIZE: usize = 64;

/// Largest scene scale S and ray origin |o|₁ for which the margin argument holds.
const MAX_SCALE: f64 = 1e100;
/// The margin δ per unit of |o|₁ + S.
const MARGIN: f64 = 1.0 / (1u64 << 36) as f64;
/// The margin's floor, far above the rounding of values near the underflow range.
const MARGIN_FLOOR: f64 = 1e-150;

/// Marks a child reference as a leaf (index into the leaves) rather than a node.
const LEAF_BIT: u32 = 1 << 31;
/// An unused child slot; its box is empty, so it is never entered.
const EMPTY: u32 = u32::MAX;

/// Four child boxes, per axis their low and high sides across the four children, and
/// the children.
#[derive(Clone, Copy, Debug)]
struct Node {
    lo: [F4; 3],
    hi: [F4; 3],
    children: [u32; LANES],
}

/// A leaf: `count` spheres from `first` in [`Bvh::spheres`].
#[derive(Clone, Copy, Debug)]
struct Leaf {
    first: u32,
    count: u32,
}

/// The hierarchy: nodes (the root first), leaves, and the spheres in leaf order.
#[derive(Clone, Debug)]
pub(crate) struct Bvh {
    nodes: Vec<Node>,
    leaves: Vec<Leaf>,
    /// (object index, geometry), each leaf's spheres contiguous.
    spheres: Vec<(u32, SphereGeom)>,
    /// S: the largest |centre|₁ + r over the spheres.
    scale: f64,
    /// Whether the processor has AVX2: the node tests then run on all four children in
    /// one instruction each (with the same IEEE results).
    avx2: bool,
}

/// The traversal stack, allocated once by the caller (per pixel) and reused for every
/// ray: node references and the entry distance at which each was pushed.
#[derive(Clone, Debug)]
pub(crate) struct Stack {
    node: [u32; STACK_SIZE],
    entry: [f64; STACK_SIZE],
}

impl Stack {
    pub fn new() -> Self {
        Stack {
            node: [0; STACK_SIZE],
            entry: [0.0; STACK_SIZE],
        }
    }
}

/// The hierarchy cannot answer for this ray (it is outside the range of the margin
/// argument, or the traversal stack overflowed): the caller answers by brute force.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Fallback;

/// A ray prepared for box tests: reciprocal direction, which side of each slab it meets
/// first, and its origin moved by the margin so that every box looks δ larger.
struct BoxRay {
    inv: [f64; 3],
    /// Whether the ray meets the `hi` side of a slab first (negative direction).
    negative: [bool; 3],
    origin_near: [f64; 3],
    origin_far: [f64; 3],
}

impl BoxRay {
    #[inline(always)]
    fn new(origin: Vec3, dir: Vec3, scale: f64) -> Option<Self> {
        let o = [origin.x, origin.y, origin.z];
        let d = [dir.x, dir.y, dir.z];
        let reach = o[0].abs() + o[1].abs() + o[2].abs();
        let d2 = dir.dot(dir);
        if !(reach <= MAX_SCALE && d2 > 0.5 && d2 < 2.0) {
            return None;
        }
        let delta = (reach + scale) * MARGIN + MARGIN_FLOOR;
        let negative = d.map(f64::is_sign_negative);
        let step = |a: usize| if negative[a] { -delta } else { delta };
        Some(BoxRay {
            inv: d.map(|d| 1.0 / d),
            negative,
            origin_near: std::array::from_fn(|a| o[a] + step(a)),
            origin_far: std::array::from_fn(|a| o[a] - step(a)),
        })
    }

    /// Which of the node's (widened) child boxes the ray meets within [0, `t_max`], and
    /// where it enters each. A NaN slab distance (a zero direction component exactly on
    /// a box side) is ignored, which can only widen the box.
    #[inline(always)]
    fn enter(&self, node: &Node, t_max: f64) -> (M4, F4) {
        let mut t0 = F4::splat(0.0);
        let mut t1 = F4::splat(t_max);
        for axis in 0..3 {
            let (near_side, far_side) = if self.negative[axis] {
                (node.hi[axis], node.lo[axis])
            } else {
                (node.lo[axis], node.hi[axis])
            };
            let near = (near_side - self.origin_near[axis]) * self.inv[axis];
            let far = (far_side - self.origin_far[axis]) * self.inv[axis];
            t0 = near.zip(t0, |a, b| if a > b { a } else { b });
            t1 = far.zip(t1, |a, b| if a < b { a } else { b });
        }
        (t0.test(t1, |a, b| a <= b), t0)
    }
}

/// Keeps the better of `best` and the hit (`t`, `index`): the nearer one, or on a tie
/// the lower object index; a NaN (a miss) never wins. The result does not depend on the
/// order in which hits are considered, which lets the hierarchy visit spheres in any
/// order and still find what the loop over all spheres in scene order finds.
#[inline(always)]
pub(crate) fn consider(best: &mut (f64, u32), t: f64, index: u32) {
    if t < best.0 || (t == best.0 && index < best.1) {
        *best = (t, index);
    }
}

impl Bvh {
    /// Builds the hierarchy over `spheres` (object index, geometry), or `None` if the
    /// scene is too large in scale for the margin argument (then only brute force).
    pub fn build(spheres: &[(u32, SphereGeom)]) -> Option<Bvh> {
        let scale = spheres
            .iter()
            .map(|(_, s)| s.center.x.abs() + s.center.y.abs() + s.center.z.abs() + s.radius)
            .fold(0.0, f64::max);
        if spheres.is_empty() || scale.is_nan() || scale > MAX_SCALE {
            return None;
        }
        let mut prims: Vec<Prim> = spheres
            .iter()
            .map(|&(index, s)| {
                let c = [s.center.x, s.center.y, s.center.z];
                Prim {
                    bounds: Aabb {
                        lo: c.map(|c| c - s.radius),
                        hi: c.map(|c| c + s.radius),
                    },
                    centroid: c,
                    sphere: (index, s),
                }
            })
            .collect();
        let mut binary = Vec::new();
        let root = build_range(&mut prims, 0, 0, &mut binary);
        let mut bvh = Bvh {
            nodes: Vec::new(),
            leaves: Vec::new(),
            spheres: prims.iter().map(|p| p.sphere).collect(),
            scale,
            avx2: has_avx2(),
        };
        bvh.collapse(&binary, root);
        Some(bvh)
    }

    /// Number of 4-wide nodes (for tests and the documentation).
    #[cfg(test)]
    fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Makes a 4-wide node from binary node `root` by pulling up the grandchildren
    /// with the largest boxes, and returns its index.
    fn collapse(&mut self, binary: &[BinaryNode], root: usize) -> u32 {
        let mut slots: Vec<usize> = match binary[root].kind {
            Kind::Leaf { .. } => vec![root],
            Kind::Inner { left, right } => vec![left, right],
        };
        while slots.len() < LANES {
            let widest = slots
                .iter()
                .enumerate()
                .filter(|(_, &n)| matches!(binary[n].kind, Kind::Inner { .. }))
                .max_by(|a, b| {
                    binary[*a.1]
                        .bounds
                        .area()
                        .total_cmp(&binary[*b.1].bounds.area())
                });
            let Some((slot, &n)) = widest else { break };
            let Kind::Inner { left, right } = binary[n].kind else {
                unreachable!("filtered to inner nodes")
            };
            slots[slot] = left;
            slots.push(right);
        }
        let index = self.nodes.len();
        self.nodes.push(Node {
            lo: [F4::splat(f64::INFINITY); 3],
            hi: [F4::splat(f64::NEG_INFINITY); 3],
            children: [EMPTY; LANES],
        });
        for (k, &n) in slots.iter().enumerate() {
            let b = binary[n].bounds;
            for axis in 0..3 {
                self.nodes[index].lo[axis].0[k] = b.lo[axis];
                self.nodes[index].hi[axis].0[k] = b.hi[axis];
            }
            let child = match binary[n].kind {
                Kind::Leaf { first, count } => {
                    self.leaves.push(Leaf {
                        first: u32::try_from(first).expect("sphere count fits in u32"),
                        count: count as u32,
                    });
                    LEAF_BIT | u32::try_from(self.leaves.len() - 1).expect("leaf count fits")
                }
                Kind::Inner { .. } => self.collapse(binary, n),
            };
            self.nodes[index].children[k] = child;
        }
        index as u32
    }

    /// Updates `best` with the nearest hit among the spheres, leaving out object `from`
    /// (which the caller tests itself). `Err` if the ray is outside the hierarchy's
    /// range or the stack overflowed: then `best` holds valid but possibly partial
    /// results, and the caller completes them by brute force.
    pub fn nearest(
        &self,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        best: &mut (f64, u32),
        stack: &mut Stack,
    ) -> Result<(), Fallback> {
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` is set only where the processor supports AVX2.
            return unsafe { self.nearest_avx2(origin, dir, from, best, stack) };
        }
        self.nearest_in(origin, dir, from, best, stack)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn nearest_avx2(
        &self,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        best: &mut (f64, u32),
        stack: &mut Stack,
    ) -> Result<(), Fallback> {
        self.nearest_in(origin, dir, from, best, stack)
    }

    #[inline(always)]
    fn nearest_in(
        &self,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        best: &mut (f64, u32),
        stack: &mut Stack,
    ) -> Result<(), Fallback> {
        let ray = BoxRay::new(origin, dir, self.scale).ok_or(Fallback)?;
        let mut top = 1;
        stack.node[0] = 0;
        stack.entry[0] = 0.0;
        while top > 0 {
            top -= 1;
            if stack.entry[top] > best.0 {
                continue;
            }
            let node = &self.nodes[stack.node[top] as usize];
            let (hit, entry) = ray.enter(node, best.0);
            // Push the children far to near, so the nearest is visited first.
            let mut order: [(f64, u32); LANES] = [(0.0, 0); LANES];
            let mut n = 0;
            for k in 0..LANES {
                if hit.get(k) {
                    let child = node.children[k];
                    if child & LEAF_BIT != 0 && child != EMPTY {
                        self.leaf_nearest(child, origin, dir, from, best);
                        continue;
                    }
                    let mut j = n;
                    while j > 0 && order[j - 1].0 < entry.0[k] {
                        order[j] = order[j - 1];
                        j -= 1;
                    }
                    order[j] = (entry.0[k], child);
                    n += 1;
                }
            }
            if top + n > STACK_SIZE {
                return Err(Fallback);
            }
            for &(t, child) in &order[..n] {
                stack.node[top] = child;
                stack.entry[top] = t;
                top += 1;
            }
        }
        Ok(())
    }

    /// The spheres of the leaf `child` refers to.
    #[inline(always)]
    fn leaf(&self, child: u32) -> &[(u32, SphereGeom)] {
        let leaf = self.leaves[(child & !LEAF_BIT) as usize];
        &self.spheres[leaf.first as usize..(leaf.first + leaf.count) as usize]
    }

    #[inline(always)]
    fn leaf_nearest(&self, child: u32, origin: Vec3, dir: Vec3, from: u32, best: &mut (f64, u32)) {
        for &(index, ref sphere) in self.leaf(child) {
            if index != from {
                if let Some(t) = sphere.hit(origin, dir, false) {
                    consider(best, t, index);
                }
            }
        }
    }

    /// The object index of some sphere other than `from` hit at a distance in
    /// (0, `limit`), if any: shadow rays stop at the first occluder found.
    pub fn occluder(
        &self,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        limit: f64,
        stack: &mut Stack,
    ) -> Result<Option<u32>, Fallback> {
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` is set only where the processor supports AVX2.
            return unsafe { self.occluder_avx2(origin, dir, from, limit, stack) };
        }
        self.occluder_in(origin, dir, from, limit, stack)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn occluder_avx2(
        &self,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        limit: f64,
        stack: &mut Stack,
    ) -> Result<Option<u32>, Fallback> {
        self.occluder_in(origin, dir, from, limit, stack)
    }

    #[inline(always)]
    fn occluder_in(
        &self,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        limit: f64,
        stack: &mut Stack,
    ) -> Result<Option<u32>, Fallback> {
        let ray = BoxRay::new(origin, dir, self.scale).ok_or(Fallback)?;
        let mut top = 1;
        stack.node[0] = 0;
        while top > 0 {
            top -= 1;
            let node = &self.nodes[stack.node[top] as usize];
            let (hit, _) = ray.enter(node, limit);
            for k in 0..LANES {
                if !hit.get(k) {
                    continue;
                }
                let child = node.children[k];
                if child & LEAF_BIT != 0 && child != EMPTY {
                    for &(index, ref sphere) in self.leaf(child) {
                        if index != from
                            && sphere.hit(origin, dir, false).is_some_and(|t| t < limit)
                        {
                            return Ok(Some(index));
                        }
                    }
                } else {
                    if top == STACK_SIZE {
                        return Err(Fallback);
                    }
                    stack.node[top] = child;
                    top += 1;
                }
            }
        }
        Ok(None)
    }
}

/// An axis-aligned box.
#[derive(Clone, Copy, Debug)]
struct Aabb {
    lo: [f64; 3],
    hi: [f64; 3],
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        lo: [f64::INFINITY; 3],
        hi: [f64::NEG_INFINITY; 3],
    };

    fn union(self, o: Aabb) -> Aabb {
        Aabb {
            lo: std::array::from_fn(|a| self.lo[a].min(o.lo[a])),
            hi: std::array::from_fn(|a| self.hi[a].max(o.hi[a])),
        }
    }

    fn grow(self, p: [f64; 3]) -> Aabb {
        self.union(Aabb { lo: p, hi: p })
    }

    /// Half the surface area (the heuristic only compares areas); 0 for an empty box.
    fn area(&self) -> f64 {
        let e: [f64; 3] = std::array::from_fn(|a| (self.hi[a] - self.lo[a]).max(0.0));
        e[0] * e[1] + e[1] * e[2] + e[2] * e[0]
    }
}

/// A sphere during the build: its box, its centre and what it is.
#[derive(Clone, Copy, Debug)]
struct Prim {
    bounds: Aabb,
    centroid: [f64; 3],
    sphere: (u32, SphereGeom),
}

#[derive(Clone, Copy, Debug)]
enum Kind {
    Leaf { first: usize, count: usize },
    Inner { left: usize, right: usize },
}

#[derive(Clone, Copy, Debug)]
struct BinaryNode {
    bounds: Aabb,
    kind: Kind,
}

/// Builds the binary hierarchy over `prims`, reordering them so that each leaf's are
/// contiguous, and returns the root's index in `out`. `offset` is the position of
/// `prims` in the whole array, `depth` that of the node to build.
fn build_range(
    prims: &mut [Prim],
    offset: usize,
    depth: usize,
    out: &mut Vec<BinaryNode>,
) -> usize {
    let bounds = prims.iter().fold(Aabb::EMPTY, |b, p| b.union(p.bounds));
    let n = prims.len();
    let leaf = |out: &mut Vec<BinaryNode>| {
        out.push(BinaryNode {
            bounds,
            kind: Kind::Leaf {
                first: offset,
                count: n,
            },
        });
        out.len() - 1
    };
    // One leaf is tested as fast as one node: small sets are always leaves.
    if n <= LEAF_SIZE {
        return leaf(out);
    }
    let split = match best_split(prims) {
        Some((axis, plane)) if depth < SAH_MAX_DEPTH => partition(prims, axis, plane),
        _ => median_split(prims),
    };
    let index = out.len();
    out.push(BinaryNode {
        bounds,
        kind: Kind::Leaf {
            first: offset,
            count: n,
        },
    });
    let (left, right) = prims.split_at_mut(split);
    let l = build_range(left, offset, depth + 1, out);
    let r = build_range(right, offset + split, depth + 1, out);
    out[index].kind = Kind::Inner { left: l, right: r };
    index
}

/// The cheapest binned split (axis, bin boundary) by the surface area heuristic, or
/// `None` if the centres do not spread along any axis.
fn best_split(prims: &[Prim]) -> Option<(usize, f64)> {
    let centers = prims.iter().fold(Aabb::EMPTY, |b, p| b.grow(p.centroid));
    let mut best: Option<(f64, usize, f64)> = None;
    for axis in 0..3 {
        let (lo, hi) = (centers.lo[axis], centers.hi[axis]);
        if hi.partial_cmp(&lo) != Some(Ordering::Greater) {
            continue;
        }
        let width = (hi - lo) / BINS as f64;
        let bin_of = |c: f64| (((c - lo) / width) as usize).min(BINS - 1);
        let mut count = [0usize; BINS];
        let mut boxes = [Aabb::EMPTY; BINS];
        for p in prims {
            let b = bin_of(p.centroid[axis]);
            count[b] += 1;
            boxes[b] = boxes[b].union(p.bounds);
        }
        // Areas and counts left of each boundary, then right of it.
        let mut left = [(0.0, 0usize); BINS];
        let (mut acc, mut m) = (Aabb::EMPTY, 0);
        for b in 0..BINS - 1 {
            acc = acc.union(boxes[b]);
            m += count[b];
            left[b] = (acc.area(), m);
        }
        let (mut acc, mut m) = (Aabb::EMPTY, 0);
        for b in (1..BINS).rev() {
            acc = acc.union(boxes[b]);
            m += count[b];
            let (la, ln) = left[b - 1];
            if ln == 0 || m == 0 {
                continue;
            }
            // Expected sphere tests below the split, times the parent's area.
            let cost = la * ln as f64 + acc.area() * m as f64;
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, lo + width * b as f64));
            }
        }
    }
    best.map(|(_, axis, plane)| (axis, plane))
}

/// Moves the prims with centre below `plane` on `axis` first; returns how many.
/// Falls back to the median if the plane separates nothing (rounding of bin bounds).
fn partition(prims: &mut [Prim], axis: usize, plane: f64) -> usize {
    let mut i = 0;
    for j in 0..prims.len() {
        if prims[j].centroid[axis] < plane {
            prims.swap(i, j);
            i += 1;
        }
    }
    if i == 0 || i == prims.len() {
        median_split(prims)
    } else {
        i
    }
}

/// Splits at the median centre along the widest axis of the centres.
fn median_split(prims: &mut [Prim]) -> usize {
    let centers = prims.iter().fold(Aabb::EMPTY, |b, p| b.grow(p.centroid));
    let axis = (0..3)
        .max_by(|&a, &b| {
            (centers.hi[a] - centers.lo[a]).total_cmp(&(centers.hi[b] - centers.lo[b]))
        })
        .unwrap_or(0);
    let mid = prims.len() / 2;
    prims.select_nth_unstable_by(mid, |a, b| a.centroid[axis].total_cmp(&b.centroid[axis]));
    mid
}

/// Whether the processor running this has AVX2.
pub(crate) fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(n: usize) -> Vec<(u32, SphereGeom)> {
        (0..n)
            .map(|i| {
                let c = Vec3::new((i % 37) as f64, ((i / 37) % 11) as f64, (i / 407) as f64);
                (i as u32, SphereGeom::new(c, 0.3))
            })
            .collect()
    }

    #[test]
    fn every_sphere_is_in_exactly_one_leaf() {
        for n in [1, 2, 3, 4, 5, 9, 17, 100, 1000] {
            let bvh = Bvh::build(&grid(n)).unwrap();
            let mut seen: Vec<u32> = (0..bvh.leaves.len() as u32)
                .flat_map(|l| bvh.leaf(LEAF_BIT | l).iter().map(|&(i, _)| i))
                .collect();
            assert!(bvh
                .leaves
                .iter()
                .all(|l| (1..=LEAF_SIZE as u32).contains(&l.count)));
            seen.sort_unstable();
            assert_eq!(seen, (0..n as u32).collect::<Vec<_>>(), "{n} spheres");
            assert!(bvh.node_count() >= 1);
        }
    }

    #[test]
    fn coincident_spheres_build_a_shallow_tree() {
        let same: Vec<(u32, SphereGeom)> = (0..10_000)
            .map(|i| (i, SphereGeom::new(Vec3::ZERO, 1.0)))
            .collect();
        let bvh = Bvh::build(&same).unwrap();
        let mut stack = Stack::new();
        let mut best = (f64::INFINITY, u32::MAX);
        let dir = Vec3::new(0.0, 0.0, 1.0);
        bvh.nearest(
            Vec3::new(0.0, 0.0, -5.0),
            dir,
            u32::MAX,
            &mut best,
            &mut stack,
        )
        .expect("the median splits keep the tree shallow");
        assert_eq!(best, (4.0, 0));
    }

    #[test]
    fn scenes_beyond_the_margin_argument_get_no_hierarchy() {
        assert!(Bvh::build(&[(0, SphereGeom::new(Vec3::new(1e200, 0.0, 0.0), 1.0))]).is_none());
        assert!(Bvh::build(&[]).is_none());
    }
}
