//! A bounding volume hierarchy over a scene's spheres: 8-wide nodes whose child boxes
//! are stored in single precision as structure-of-arrays, so one node test is a handful
//! of 8-lane SIMD operations, and leaves of up to four spheres.
//!
//! It is built once per scene (binned surface area heuristic over the sphere centres,
//! splitting the child with the largest box until a node has eight children; subtrees
//! are built in parallel on the current rayon pool) and answers the same questions as
//! the brute-force loop over all spheres, with exactly the same answers:
//!
//! - every sphere it reaches is tested by the same double-precision code as in the
//!   brute-force loop, so a hit has the same bits;
//! - a subtree is skipped only if the ray's entry into its box is beyond the best hit
//!   so far by more than the rounding bound below (a hit at an equal distance could
//!   still win on its lower object index), or, for shadow rays, beyond the light;
//! - boxes are tested with a margin, below, that covers the rounding of the sphere test
//!   and of the single-precision box test, so a sphere that the brute-force loop would
//!   report as hit is never in a box the ray is judged to miss;
//! - the sphere a ray leaves is not tested here: its caller tests it (its far-wall root
//!   need not lie near the sphere when the origin is not exactly on it).
//!
//! # Margin
//!
//! A computed sphere hit t lies, in exact arithmetic, within some multiple of ε·(|o| +
//! |centre| + r) of the sphere's box (ε = 2⁻⁵³, o the ray origin): the cancellation-free
//! quadratic of [`crate::geometry`] moves a root only by rounding its inputs, and a
//! grazing root, where the square root magnifies that error, moves along the ray to a
//! point that still lies on the (perturbed) sphere. Call that bound β; 2⁻³⁷·(|o|₁ + S)
//! is thousands of times β, with S the largest |centre|₁ + r of the scene.
//!
//! The box test runs in single precision (u = 2⁻²⁴) with boxes widened by
//! δ = 2⁻²²·(|o|₁ + S) + 2⁻¹²⁰, and is conservative for these reasons:
//!
//! 1. Box sides are rounded outward (low sides down, high sides up) from the double
//!    values c ± r to `f32`, so the stored box contains the double one; a node's box
//!    contains its children's.
//! 2. The widening is applied to the ray, not the boxes: per axis the origin is
//!    shifted in double precision by δ towards the far side of the slab for the near
//!    side's distance (o + δ for a positive direction) and by δ the other way for the
//!    far side's, then rounded to nearest `f32`. Those roundings (≤ 2⁻²⁴·(|oₐ| + δ)
//!    plus 2⁻¹⁵⁰ for a subnormal) and the double ones (≤ 2⁻⁵³ of the values, also for
//!    c ± r) take away at most δ/4 + 2⁻²³·δ, so each exact slab distance of the
//!    rounded inputs, (side − o′)·(1/dₐ), is that of a box widened by at least
//!    0.74·δ ≥ β + δ/2.
//!    The inverse direction is 1/dₐ in double, rounded to nearest `f32` (±∞ if it
//!    overflows).
//! 3. Let p = o + t_p·d be the exact point of a hit the brute-force loop reports: it
//!    lies within β of its sphere's box, so every exact near-side distance of the
//!    rounded inputs is ≤ t_p − δ/(2|dₐ|), every far-side one ≥ t_p + δ/(2|dₐ|). The
//!    computed distance fl(fl(side − o′)·inv) carries three `f32` roundings and one
//!    double one: a relative error γ ≤ 3u + 2⁻⁵³ + O(u²), plus at most 2⁻¹⁵⁰ absolute
//!    where the product underflows (a difference that underflows is exact). Since
//!    δ/(2|dₐ|) ≥ 2⁻¹²¹/1.5 dwarfs 2⁻¹⁵⁰, a computed near distance is ≤ t_p(1 + γ) when
//!    positive, and ≤ 0 when its exact value is negative (rounding keeps signs); a far
//!    one is ≥ t_p(1 − γ) ≥ 0.
//! 4. The entry t₀ = max(0, near distances) is thus ≤ t_p(1 + γ), and the exit
//!    t₁ = min(T, far distances) ≥ t_p(1 − γ), with T the distance limit (the best hit
//!    or the light, ≥ t_p) rounded *up* to `f32`. A box is entered when
//!    t₀ ≤ fl(t₁·K) with K = 1 + 2⁻²⁰ ≥ (1 + γ)/((1 − γ)(1 − u)): so always for such a
//!    sphere's boxes. A subtree or leaf waiting on the stack is dropped only when its
//!    entry exceeds fl(T·K), which t₀ ≤ t_p(1 + γ) never does.
//! 5. Overflow: with |o|₁, S ≤ 10³⁰ every hit distance is below 10³¹, far inside the
//!    `f32` range, so a distance that rounds to ±∞ (a tiny direction component, whose
//!    inverse overflows) is beyond every hit with the right sign, and rejects only
//!    boxes that no hit lies in. A NaN distance (0·∞: the origin exactly on a side and
//!    a tiny direction component) is ignored, which can only widen the box. An empty
//!    child slot (box +∞ to −∞) gives +∞ entries and −∞ exits, never NaN, and is never
//!    entered.
//!
//! The packet traversals (four rays sharing the stack and the node loads) keep every
//! step of this argument per lane: each lane's box tests use its own shifted origins,
//! inverse direction and limit, and a lane drops a subtree or leaf only when its own
//! entry (or the least entry over the lanes that entered it, which is no larger)
//! exceeds its own fl(T·K). Visiting a node, or testing a sphere, for a lane that
//! did not need it costs time but changes no answer.
//!
//! Rays too far out for this argument (|o|₁ > 10³⁰, non-unit directions) and scenes
//! with S > 10³⁰ or more than 2²⁸ spheres are not traced through the hierarchy at all:
//! callers fall back to the brute-force loop, which gives the same answers.
//!
//! The parts: [`build`] makes the tree; [`box_ray`] holds the single-precision box test
//! that the margin argument above is about; [`single`] traces one ray at a time and
//! [`packet`] four at a time. This file keeps what they share: the tree's layout, the
//! traversal stack, the rounding of distances to `f32` and the order of hits
//! ([`consider`]).

mod box_ray;
mod build;
mod packet;
mod single;

use std::mem::MaybeUninit;

use crate::geometry::SphereGeom;
use crate::simd::Isa;

/// Children per node.
const WIDTH: usize = 8;
/// Most spheres in a leaf (at most 8: the count is kept in three bits).
const LEAF_SIZE: usize = 4;
/// Entries of the traversal stack. A deeper tree than it can hold makes the traversal
/// report an overflow, and its caller then uses the brute-force loop.
const STACK_SIZE: usize = 128;

/// Largest scene scale S and ray origin |o|₁ for which the margin argument holds.
const MAX_SCALE: f64 = 1e30;

/// Marks a child reference as a leaf: bits 28–30 hold its sphere count − 1, bits 0–27
/// the position of its first sphere in [`Bvh::spheres`].
const LEAF_BIT: u32 = 1 << 31;
const FIRST_MASK: u32 = (1 << 28) - 1;
/// An unused child slot; its box is empty, so it is never entered.
const EMPTY: u32 = u32::MAX;

/// Eight child boxes in single precision, per axis their low side (`bounds[2·axis]`)
/// and high side (`bounds[2·axis + 1]`) across the eight children, and the children.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
struct Node {
    bounds: [[f32; WIDTH]; 6],
    children: [u32; WIDTH],
}

/// The hierarchy: nodes (the root first) and the spheres in leaf order.
#[derive(Clone, Debug)]
pub(crate) struct Bvh {
    nodes: Vec<Node>,
    /// (object index, geometry), each leaf's spheres contiguous.
    spheres: Vec<(u32, SphereGeom)>,
    /// S: the largest |centre|₁ + r over the spheres.
    scale: f64,
    /// The instruction set the traversals run with, the tracer's: with AVX2 a node
    /// test is one 256-bit instruction per step for all eight children (with the same
    /// IEEE results as the portable code).
    isa: Isa,
}

/// The traversal stack, allocated once by the caller (per pixel) and reused for every
/// ray: child references and the entry distance at which each was pushed. It is not
/// initialised (a traversal reads only the entries it wrote), so making one costs
/// nothing.
#[derive(Clone, Debug)]
pub(crate) struct Stack {
    node: [MaybeUninit<u32>; STACK_SIZE],
    entry: [MaybeUninit<f32>; STACK_SIZE],
    /// For the packet traversal, the lanes an entry is still wanted by.
    lanes: [MaybeUninit<u32>; STACK_SIZE],
}

impl Stack {
    pub fn new() -> Self {
        Stack {
            node: [MaybeUninit::uninit(); STACK_SIZE],
            entry: [MaybeUninit::uninit(); STACK_SIZE],
            lanes: [MaybeUninit::uninit(); STACK_SIZE],
        }
    }

    /// Writes an entry of the packet traversal: a child, its entry distance (the
    /// least over its lanes) and the lanes that want it.
    #[inline(always)]
    fn set_lanes(&mut self, top: usize, child: u32, entry: f32, lanes: u32) {
        self.set(top, child, entry);
        self.lanes[top] = MaybeUninit::new(lanes);
    }

    /// The lanes at `top`, which the packet traversal has written.
    #[inline(always)]
    fn lanes(&self, top: usize) -> u32 {
        // SAFETY: as in `node`; the packet traversal writes all three with `set_lanes`.
        unsafe { self.lanes[top].assume_init() }
    }

    #[inline(always)]
    fn set(&mut self, top: usize, child: u32, entry: f32) {
        self.node[top] = MaybeUninit::new(child);
        self.entry[top] = MaybeUninit::new(entry);
    }

    /// Writes a child reference alone, for the shadow-ray traversal, which keeps no
    /// entry distances.
    #[inline(always)]
    fn set_node(&mut self, top: usize, child: u32) {
        self.node[top] = MaybeUninit::new(child);
    }

    /// The child reference at `top`, which the traversal has written.
    #[inline(always)]
    fn node(&self, top: usize) -> u32 {
        // SAFETY: traversals read only below their stack top, all written by `set`.
        unsafe { self.node[top].assume_init() }
    }

    /// The entry distance at `top`, which the traversal has written.
    #[inline(always)]
    fn entry(&self, top: usize) -> f32 {
        // SAFETY: as in `node`.
        unsafe { self.entry[top].assume_init() }
    }
}

/// The hierarchy cannot answer for this ray (it is outside the range of the margin
/// argument, or the traversal stack overflowed): the caller answers by brute force.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Fallback;

/// `x` rounded up to `f32` (to +∞ beyond its range; `x` not NaN). Written in integer
/// arithmetic without branches: whether the nearest `f32` lies below `x` is a coin toss
/// for a ray's distance limit, and a mispredicted branch on it cost every shadow ray
/// about as much as a node test (the compiler turned the selects of an earlier version
/// into branches).
#[inline(always)]
pub(crate) fn up32(x: f64) -> f32 {
    let f = x as f32;
    let bits = f.to_bits();
    // One step towards +∞ when the nearest value lies below x: away from zero for a
    // positive value (from +0 to the least positive subnormal), towards it for a
    // negative one. (−0 never lies below x: an x above it is positive and rounds to
    // +0 or above.)
    let below = u32::from(f64::from(f) < x);
    let negative = bits >> 31;
    f32::from_bits(
        bits.wrapping_add(below)
            .wrapping_sub((below & negative) << 1),
    )
}

/// `x` rounded down to `f32` (to −∞ beyond its range; `x` not NaN).
#[inline(always)]
pub(crate) fn down32(x: f64) -> f32 {
    -up32(-x)
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
    /// Makes the traversals run with `isa` (the tracer's, when it changes), which must
    /// be available on this processor.
    pub fn set_isa(&mut self, isa: Isa) {
        self.isa = isa;
    }

    /// The instruction set the traversals run with.
    #[cfg(test)]
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// Number of nodes (for tests and the documentation).
    #[cfg(test)]
    fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// The spheres of the leaf `child` refers to.
    #[inline(always)]
    fn leaf(&self, child: u32) -> &[(u32, SphereGeom)] {
        let first = (child & FIRST_MASK) as usize;
        let count = ((child >> 28) & 7) as usize + 1;
        &self.spheres[first..first + count]
    }
}

#[cfg(test)]
mod tests;
