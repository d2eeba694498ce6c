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

use std::mem::MaybeUninit;

use crate::geometry::{sphere_hits, SphereGeom};
use crate::simd::{isa_dispatch, Isa};
use crate::vec3::{Vec3, F4, M4, V4};

/// Children per node.
const WIDTH: usize = 8;
/// Most spheres in a leaf (at most 8: the count is kept in three bits).
const LEAF_SIZE: usize = 4;
/// Split-plane candidates per axis in the surface area heuristic.
const BINS: usize = 16;
/// Below this binary depth the heuristic chooses splits; deeper, splits are at the
/// median, which halves the sphere count and so bounds the depth for any input.
const SAH_MAX_DEPTH: u32 = 40;
/// Subtrees with at least this many spheres are built in parallel with their siblings.
const PARALLEL_MIN: usize = 4096;
/// Entries of the traversal stack. A deeper tree than it can hold makes the traversal
/// report an overflow, and its caller then uses the brute-force loop.
const STACK_SIZE: usize = 128;

/// Largest scene scale S and ray origin |o|₁ for which the margin argument holds.
const MAX_SCALE: f64 = 1e30;
/// The margin δ per unit of |o|₁ + S: it also covers rounding the origin to `f32`.
const MARGIN: f64 = 1.0 / (1u64 << 22) as f64;
/// The margin's floor, far above the rounding of values near the underflow range.
const MARGIN_FLOOR: f64 = 1.0 / (1u128 << 120) as f64;
/// The slack factor K of the entry test t₀ ≤ t₁·K.
const SLACK: f32 = 1.0 + 1.0 / (1u32 << 20) as f32;
/// Most spheres: a leaf's first sphere is kept in 28 bits.
const MAX_SPHERES: usize = 1 << 28;

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

impl Node {
    const EMPTY: Node = Node {
        bounds: [
            [f32::INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
            [f32::INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
            [f32::INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
        ],
        children: [EMPTY; WIDTH],
    };

    fn set(&mut self, k: usize, b: &Box4, child: u32) {
        for axis in 0..3 {
            self.bounds[2 * axis][k] = b.lo[axis];
            self.bounds[2 * axis + 1][k] = b.hi[axis];
        }
        self.children[k] = child;
    }
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

/// A ray prepared for box tests in single precision (see the module documentation):
/// the origin shifted by ±δ and rounded outward, once for the slab side met first and
/// once for the other, and the reciprocal direction.
struct BoxRay {
    origin_near: [f32; 3],
    origin_far: [f32; 3],
    inv: [f32; 3],
    /// Per axis, the row of [`Node::bounds`] met first (the high side for a negative
    /// direction) and the other.
    near: [usize; 3],
    far: [usize; 3],
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
        let plus = o.map(|o| (o + delta) as f32);
        let minus = o.map(|o| (o - delta) as f32);
        Some(BoxRay {
            origin_near: std::array::from_fn(|a| if negative[a] { minus[a] } else { plus[a] }),
            origin_far: std::array::from_fn(|a| if negative[a] { plus[a] } else { minus[a] }),
            inv: d.map(|d| (1.0 / d) as f32),
            near: std::array::from_fn(|a| 2 * a + usize::from(negative[a])),
            far: std::array::from_fn(|a| 2 * a + 1 - usize::from(negative[a])),
        })
    }

    /// The distance limit T (rounded up) and fl(T·K) for the best distance `t`.
    #[inline(always)]
    fn limit(t: f64) -> (f32, f32) {
        let t = up32(t);
        (t, t * SLACK)
    }

    /// Which of the node's child boxes the ray enters within [0, `t_max`] (a bit per
    /// child), which children are leaves (a bit per child; empty slots too, but their
    /// boxes are never entered), and where the ray enters each (+∞ for the boxes it
    /// does not enter, so that the packet traversal takes least entries over its
    /// lanes with element-wise minima). A NaN slab distance
    /// is ignored. With `isa` AVX2 the test runs in 256-bit instructions
    /// ([`BoxRay::enter_avx2`]): the compiler does not vectorise the portable loops
    /// well (it splits them into 128-bit pieces and shuffles to build the masks). The
    /// traversals pass the hierarchy's own `isa` (a branch taken the same way for
    /// every node), so `TESSERA_SIMD=portable` reaches this test too.
    #[inline(always)]
    fn enter(&self, node: &Node, t_max: f32, isa: Isa) -> (u32, u32, [f32; WIDTH]) {
        #[cfg(target_arch = "x86_64")]
        if isa == Isa::Avx2 {
            // SAFETY: an `Isa::Avx2` is only ever made where the processor supports
            // AVX2 (`Isa::best`).
            return unsafe { self.enter_avx2(node, t_max) };
        }
        let mut t0 = [0.0f32; WIDTH];
        let mut t1 = [t_max; WIDTH];
        for axis in 0..3 {
            let near_side = &node.bounds[self.near[axis]];
            let far_side = &node.bounds[self.far[axis]];
            for k in 0..WIDTH {
                let near = (near_side[k] - self.origin_near[axis]) * self.inv[axis];
                let far = (far_side[k] - self.origin_far[axis]) * self.inv[axis];
                t0[k] = if near > t0[k] { near } else { t0[k] };
                t1[k] = if far < t1[k] { far } else { t1[k] };
            }
        }
        let mut mask = 0;
        let mut leaves = 0;
        for k in 0..WIDTH {
            if t0[k] <= t1[k] * SLACK {
                mask |= 1 << k;
            } else {
                t0[k] = f32::INFINITY;
            }
            leaves |= (node.children[k] >> 31) << k;
        }
        (mask, leaves, t0)
    }

    /// [`BoxRay::enter`] in AVX instructions: `max_ps(a, b)` is `a > b ? a : b` and
    /// `min_ps(a, b)` is `a < b ? a : b`, exactly the portable expressions.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn enter_avx2(&self, node: &Node, t_max: f32) -> (u32, u32, [f32; WIDTH]) {
        use std::arch::x86_64::*;
        let mut t0 = _mm256_setzero_ps();
        let mut t1 = _mm256_set1_ps(t_max);
        for axis in 0..3 {
            // SAFETY: each row is eight f32s, 32-byte aligned within the node.
            let (near_side, far_side) = unsafe {
                (
                    _mm256_load_ps(node.bounds[self.near[axis]].as_ptr()),
                    _mm256_load_ps(node.bounds[self.far[axis]].as_ptr()),
                )
            };
            let inv = _mm256_set1_ps(self.inv[axis]);
            let near = _mm256_mul_ps(
                _mm256_sub_ps(near_side, _mm256_set1_ps(self.origin_near[axis])),
                inv,
            );
            let far = _mm256_mul_ps(
                _mm256_sub_ps(far_side, _mm256_set1_ps(self.origin_far[axis])),
                inv,
            );
            t0 = _mm256_max_ps(near, t0);
            t1 = _mm256_min_ps(far, t1);
        }
        let hit = _mm256_cmp_ps::<_CMP_LE_OQ>(t0, _mm256_mul_ps(t1, _mm256_set1_ps(SLACK)));
        let mut entry = [0.0f32; WIDTH];
        let entry_or_never = _mm256_blendv_ps(_mm256_set1_ps(f32::INFINITY), t0, hit);
        // SAFETY: `entry` holds eight f32s.
        unsafe { _mm256_storeu_ps(entry.as_mut_ptr(), entry_or_never) };
        // SAFETY: the children are eight u32s, 32-byte aligned within the node.
        let children = unsafe { _mm256_load_si256(node.children.as_ptr().cast()) };
        (
            _mm256_movemask_ps(hit) as u32,
            _mm256_movemask_ps(_mm256_castsi256_ps(children)) as u32,
            entry,
        )
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
    /// scene is too large in scale or count for the margin argument (then only brute
    /// force). Subtrees are built in parallel on the current rayon pool. The
    /// traversals run with `isa`, which must be available on this processor.
    pub fn build(spheres: &[(u32, SphereGeom)], isa: Isa) -> Option<Bvh> {
        let scale = spheres
            .iter()
            .map(|(_, s)| s.center.x.abs() + s.center.y.abs() + s.center.z.abs() + s.radius)
            .fold(0.0, f64::max);
        if spheres.is_empty() || spheres.len() > MAX_SPHERES || scale.is_nan() || scale > MAX_SCALE
        {
            return None;
        }
        use rayon::prelude::*;
        let parallel = rayon::current_num_threads() > 1;
        // Per sphere, in order: mapped in parallel when large (the order, so the
        // hierarchy, is the same).
        let mut prims: Vec<Prim> = if parallel && spheres.len() >= PARALLEL_MIN {
            spheres
                .par_iter()
                .enumerate()
                .map(|(i, (_, s))| Box4::prim(i as u32, s))
                .collect()
        } else {
            spheres
                .iter()
                .enumerate()
                .map(|(i, (_, s))| Box4::prim(i as u32, s))
                .collect()
        };
        let (bounds, centres) = prims.iter().fold((Box4::EMPTY, Box4::EMPTY), |(b, c), p| {
            (b.union(&p.bounds()), c.grow(p.centre2()))
        });
        let whole = Part {
            start: 0,
            len: prims.len(),
            bounds,
            centres,
            depth: 0,
        };
        let mut nodes = Vec::with_capacity(spheres.len() / 4 + 1);
        build_node(&mut prims, 0, whole, parallel, &mut nodes);
        let spheres = if parallel && prims.len() >= PARALLEL_MIN {
            prims
                .par_iter()
                .map(|p| spheres[p.index() as usize])
                .collect()
        } else {
            prims.iter().map(|p| spheres[p.index() as usize]).collect()
        };
        Some(Bvh {
            nodes,
            spheres,
            scale,
            isa,
        })
    }

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

    isa_dispatch! {
        /// Updates `best` with the nearest hit among the spheres, leaving out object
        /// `from` (which the caller tests itself). `Err` if the ray is outside the
        /// hierarchy's range or the stack overflowed: then `best` holds valid but
        /// possibly partial results, and the caller completes them by brute force.
        pub fn nearest / nearest_avx2(
            &self,
            origin: Vec3,
            dir: Vec3,
            from: u32,
            best: &mut (f64, u32),
            stack: &mut Stack,
        ) -> Result<(), Fallback> {
            self.nearest_in(origin, dir, from, best, stack)
        }
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
        let (mut t_max, mut t_skip) = BoxRay::limit(best.0);
        let mut top = 0;
        let mut current = 0u32;
        loop {
            let node = &self.nodes[current as usize];
            let (mut hit, _, entry) = ray.enter(node, t_max, self.isa);
            // The children entered, sorted far to near; then, from the nearest, leaves
            // are tested until an inner child comes, which is visited next while the
            // others wait on the stack. A leaf or node entered beyond the best hit is
            // dropped.
            let mut order: [(f32, u32); WIDTH] = [(0.0, 0); WIDTH];
            let mut n = 0;
            while hit != 0 {
                let k = hit.trailing_zeros() as usize;
                hit &= hit - 1;
                let t = entry[k];
                let mut j = n;
                while j > 0 && order[j - 1].0 < t {
                    order[j] = order[j - 1];
                    j -= 1;
                }
                order[j] = (t, node.children[k]);
                n += 1;
            }
            let mut next = None;
            while n > 0 && order[n - 1].0 <= t_skip {
                n -= 1;
                let child = order[n].1;
                if child & LEAF_BIT == 0 {
                    next = Some(child);
                    break;
                }
                if self.leaf_nearest(child, origin, dir, from, best) {
                    (t_max, t_skip) = BoxRay::limit(best.0);
                }
            }
            if let Some(child) = next {
                let mut keep = 0;
                while keep < n && order[keep].0 > t_skip {
                    keep += 1;
                }
                if top + n - keep > STACK_SIZE {
                    return Err(Fallback);
                }
                for &(t, child) in &order[keep..n] {
                    stack.set(top, child, t);
                    top += 1;
                }
                current = child;
                continue;
            }
            loop {
                if top == 0 {
                    return Ok(());
                }
                top -= 1;
                if stack.entry(top) > t_skip {
                    continue;
                }
                let child = stack.node(top);
                if child & LEAF_BIT == 0 {
                    current = child;
                    break;
                }
                if self.leaf_nearest(child, origin, dir, from, best) {
                    (t_max, t_skip) = BoxRay::limit(best.0);
                }
            }
        }
    }

    /// The spheres of the leaf `child` refers to.
    #[inline(always)]
    fn leaf(&self, child: u32) -> &[(u32, SphereGeom)] {
        let first = (child & FIRST_MASK) as usize;
        let count = ((child >> 28) & 7) as usize + 1;
        &self.spheres[first..first + count]
    }

    /// Tests the leaf's spheres; whether `best` changed.
    #[inline(always)]
    fn leaf_nearest(
        &self,
        child: u32,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        best: &mut (f64, u32),
    ) -> bool {
        let before = *best;
        for &(index, ref sphere) in self.leaf(child) {
            if index != from {
                if let Some(t) = sphere.hit(origin, dir, false) {
                    consider(best, t, index);
                }
            }
        }
        *best != before
    }

    isa_dispatch! {
        /// The object index of some sphere other than `from` hit at a distance in
        /// (0, `limit`), if any: shadow rays stop at the first occluder found.
        pub fn occluder / occluder_avx2(
            &self,
            origin: Vec3,
            dir: Vec3,
            from: u32,
            limit: f64,
            stack: &mut Stack,
        ) -> Result<Option<u32>, Fallback> {
            self.occluder_in(origin, dir, from, limit, stack)
        }
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
        let (t_max, _) = BoxRay::limit(limit);
        let mut top = 1;
        stack.set_node(0, 0);
        while top > 0 {
            top -= 1;
            let node = &self.nodes[stack.node(top) as usize];
            let (hit, leaf, _) = ray.enter(node, t_max, self.isa);
            let mut leaves = hit & leaf;
            while leaves != 0 {
                let k = leaves.trailing_zeros() as usize;
                leaves &= leaves - 1;
                for &(index, ref sphere) in self.leaf(node.children[k]) {
                    if index != from && sphere.hit(origin, dir, false).is_some_and(|t| t < limit) {
                        return Ok(Some(index));
                    }
                }
            }
            let mut inner = hit & !leaf;
            // A whole node's worth of room, not the count of `inner`: the test is then
            // one comparison (and the stack still 120 deep before a fallback).
            if top + WIDTH > STACK_SIZE {
                return Err(Fallback);
            }
            while inner != 0 {
                let k = inner.trailing_zeros() as usize;
                inner &= inner - 1;
                stack.set_node(top, node.children[k]);
                top += 1;
            }
        }
        Ok(None)
    }
}

impl Bvh {
    isa_dispatch! {
        /// [`Bvh::nearest`] for up to four rays at once (lane k: `origin[k]`, `dir[k]`,
        /// `best[k]`; the lanes of the bit mask `lanes`), all leaving object `from`:
        /// the rays traverse the tree together, sharing the stack and the node loads.
        /// Returns the lanes the hierarchy could not answer (outside its range; all
        /// live lanes if the stack overflowed), whose `best` holds valid but possibly
        /// partial results that the caller completes by brute force.
        pub fn nearests / nearests_avx2(
            &self,
            origin: &[Vec3; 4],
            dir: &[Vec3; 4],
            from: u32,
            best: &mut [(f64, u32); 4],
            lanes: u32,
            stack: &mut Stack,
        ) -> u32 {
            self.nearests_in(origin, dir, from, best, lanes, stack)
        }
    }

    /// The packet traversal of [`Bvh::nearests`]. Each node is visited with the lanes
    /// that entered its box no later than their own skip distance fl(T·K); a child's
    /// box is tested against each of them, and the child is kept for the lanes that
    /// enter it, with the least of their entry distances. A lane tests a leaf's
    /// spheres, or descends into a child node, unless its own entry distance, or that
    /// least one (which is no larger), exceeds its skip distance: a lane drops only
    /// what [`Bvh::nearest`] would drop for it. Since the best hit does not depend on
    /// the order in which spheres are considered ([`consider`]), every lane ends with
    /// the brute-force loop's answer.
    #[inline(always)]
    fn nearests_in(
        &self,
        origin: &[Vec3; 4],
        dir: &[Vec3; 4],
        from: u32,
        best: &mut [(f64, u32); 4],
        lanes: u32,
        stack: &mut Stack,
    ) -> u32 {
        let mut rays: [MaybeUninit<BoxRay>; 4] = [const { MaybeUninit::uninit() }; 4];
        let mut t_max = [0.0f32; 4];
        let mut t_skip = [0.0f32; 4];
        let mut live = 0u32;
        let mut fallback = 0u32;
        for k in 0..4 {
            if lanes & (1 << k) == 0 {
                continue;
            }
            match BoxRay::new(origin[k], dir[k], self.scale) {
                Some(ray) => {
                    rays[k] = MaybeUninit::new(ray);
                    (t_max[k], t_skip[k]) = BoxRay::limit(best[k].0);
                    live |= 1 << k;
                }
                None => fallback |= 1 << k,
            }
        }
        if live == 0 {
            return fallback;
        }
        let (o4, d4) = (lanes4(origin), lanes4(dir));
        let mut top = 0;
        let mut current = 0u32;
        let mut active = live;
        loop {
            let node = &self.nodes[current as usize];
            let mut entry = [[0.0f32; WIDTH]; 4];
            let mut entered = [0u32; 4];
            let mut any = 0u32;
            // Per child, the least entry distance over the lanes entering it (+∞ where
            // none does): a lane's entries are +∞ for the children it does not enter,
            // so this is an element-wise minimum.
            let mut least = [f32::INFINITY; WIDTH];
            let mut ks = active;
            while ks != 0 {
                let k = ks.trailing_zeros() as usize;
                ks &= ks - 1;
                // SAFETY: the lanes of `live` (which hold `active`) were written above.
                let ray = unsafe { rays[k].assume_init_ref() };
                let (hit, _, e) = ray.enter(node, t_max[k], self.isa);
                entered[k] = hit;
                entry[k] = e;
                any |= hit;
                for c in 0..WIDTH {
                    least[c] = if e[c] < least[c] { e[c] } else { least[c] };
                }
            }
            // The children entered by some lane, sorted far to near by their least
            // entry distance over the lanes entering them.
            let mut order: [(f32, u32); WIDTH] = [(0.0, 0); WIDTH];
            let mut n = 0;
            while any != 0 {
                let c = any.trailing_zeros() as usize;
                any &= any - 1;
                let t = least[c];
                let mut j = n;
                while j > 0 && order[j - 1].0 < t {
                    order[j] = order[j - 1];
                    j -= 1;
                }
                order[j] = (t, c as u32);
                n += 1;
            }
            // The lanes that still want child `c`: those entering it no later than
            // their skip distance.
            let want = |c: usize, t_skip: &[f32; 4]| {
                let mut want = 0u32;
                let mut ks = active;
                while ks != 0 {
                    let k = ks.trailing_zeros() as usize;
                    ks &= ks - 1;
                    if entered[k] & (1 << c) != 0 && entry[k][c] <= t_skip[k] {
                        want |= 1 << k;
                    }
                }
                want
            };
            let mut next = None;
            while n > 0 {
                n -= 1;
                let c = order[n].1 as usize;
                let lanes = want(c, &t_skip);
                if lanes == 0 {
                    continue;
                }
                let child = node.children[c];
                if child & LEAF_BIT == 0 {
                    next = Some((child, lanes));
                    break;
                }
                self.leaf_lanes(child, &o4, &d4, from, best, lanes, &mut t_max, &mut t_skip);
            }
            if let Some((child, lanes)) = next {
                if top + n > STACK_SIZE {
                    return fallback | live;
                }
                for &(t, c) in &order[..n] {
                    let lanes = want(c as usize, &t_skip);
                    if lanes != 0 {
                        stack.set_lanes(top, node.children[c as usize], t, lanes);
                        top += 1;
                    }
                }
                current = child;
                active = lanes;
                continue;
            }
            loop {
                if top == 0 {
                    return fallback;
                }
                top -= 1;
                let t = stack.entry(top);
                let mut lanes = 0u32;
                let mut ks = stack.lanes(top);
                while ks != 0 {
                    let k = ks.trailing_zeros() as usize;
                    ks &= ks - 1;
                    if t <= t_skip[k] {
                        lanes |= 1 << k;
                    }
                }
                if lanes == 0 {
                    continue;
                }
                let child = stack.node(top);
                if child & LEAF_BIT == 0 {
                    current = child;
                    active = lanes;
                    break;
                }
                self.leaf_lanes(child, &o4, &d4, from, best, lanes, &mut t_max, &mut t_skip);
            }
        }
    }

    /// Tests the leaf's spheres for the rays of `lanes` (`origin` and `dir` in SIMD
    /// lanes: each sphere is tested against all four rays at once, with the same bits
    /// as [`SphereGeom::hit`]), updating their best hits and distance limits.
    #[expect(
        clippy::too_many_arguments,
        reason = "four rays' lanes passed as registers, not packed in a struct"
    )]
    #[inline(always)]
    fn leaf_lanes(
        &self,
        child: u32,
        origin: &V4,
        dir: &V4,
        from: u32,
        best: &mut [(f64, u32); 4],
        lanes: u32,
        t_max: &mut [f32; 4],
        t_skip: &mut [f32; 4],
    ) {
        let before = *best;
        for &(index, ref sphere) in self.leaf(child) {
            if index == from {
                continue;
            }
            let t = sphere_lanes(sphere, origin, dir);
            let mut ks = lanes;
            while ks != 0 {
                let k = ks.trailing_zeros() as usize;
                ks &= ks - 1;
                consider(&mut best[k], t.0[k], index);
            }
        }
        let mut ks = lanes;
        while ks != 0 {
            let k = ks.trailing_zeros() as usize;
            ks &= ks - 1;
            if best[k] != before[k] {
                (t_max[k], t_skip[k]) = BoxRay::limit(best[k].0);
            }
        }
    }

    isa_dispatch! {
        /// [`Bvh::occluder`] for up to four shadow rays at once (lane k: `origin[k]`,
        /// `dir[k]`, `limit[k]`, leaving object `from[k]`; the lanes of the bit mask
        /// `lanes`): the rays traverse the tree together, sharing the stack and the
        /// node loads. Each lane leaves its own object, so that the shadow rays of
        /// neighbouring pixels that meet different spheres still travel together.
        /// Returns the lanes blocked by some sphere and the lanes the hierarchy cannot
        /// answer (outside its range; all of `lanes` that are not blocked if the stack
        /// overflowed), which the caller answers by brute force.
        pub fn occluders / occluders_avx2(
            &self,
            origin: &[Vec3; 4],
            dir: &[Vec3; 4],
            from: &[u32; 4],
            limit: &[f64; 4],
            lanes: u32,
            stack: &mut Stack,
        ) -> (u32, u32) {
            self.occluders_in(origin, dir, from, limit, lanes, stack)
        }
    }

    /// The packet traversal of [`Bvh::occluders`]. A lane tests a leaf's spheres only
    /// when it enters the leaf's box itself, and a child node is visited when any
    /// live lane enters its box; a lane that did not enter a node's box is tested
    /// against its children's boxes anyway, which only costs time: every box holding
    /// a sphere the lane hits within its limit is entered by that lane (the margin
    /// argument above, per lane with its own origin, direction and limit). So a
    /// lane is reported blocked exactly when [`Bvh::occluder`] finds an occluder for
    /// it, and an occluder is whatever the brute-force loop would find.
    #[inline(always)]
    fn occluders_in(
        &self,
        origin: &[Vec3; 4],
        dir: &[Vec3; 4],
        from: &[u32; 4],
        limit: &[f64; 4],
        lanes: u32,
        stack: &mut Stack,
    ) -> (u32, u32) {
        let mut rays: [MaybeUninit<BoxRay>; 4] = [const { MaybeUninit::uninit() }; 4];
        let mut t_max = [0.0f32; 4];
        let mut live = 0u32;
        let mut fallback = 0u32;
        for k in 0..4 {
            if lanes & (1 << k) == 0 {
                continue;
            }
            match BoxRay::new(origin[k], dir[k], self.scale) {
                Some(ray) => {
                    rays[k] = MaybeUninit::new(ray);
                    t_max[k] = BoxRay::limit(limit[k]).0;
                    live |= 1 << k;
                }
                None => fallback |= 1 << k,
            }
        }
        let (o4, d4) = (lanes4(origin), lanes4(dir));
        let mut blocked = 0u32;
        let mut top = 1;
        stack.set_node(0, 0);
        while top > 0 && live != 0 {
            top -= 1;
            let node = &self.nodes[stack.node(top) as usize];
            let mut entered = [0u32; 4];
            let mut any = 0u32;
            let mut leaf = 0u32;
            let mut ks = live;
            while ks != 0 {
                let k = ks.trailing_zeros() as usize;
                ks &= ks - 1;
                // SAFETY: the lanes of `live` were all written above.
                let ray = unsafe { rays[k].assume_init_ref() };
                let (hit, leaves, _) = ray.enter(node, t_max[k], self.isa);
                entered[k] = hit;
                any |= hit;
                leaf = leaves;
            }
            let mut leaves = any & leaf;
            while leaves != 0 {
                let c = leaves.trailing_zeros();
                leaves &= leaves - 1;
                let mut want = 0u32;
                let mut ks = live;
                while ks != 0 {
                    let k = ks.trailing_zeros() as usize;
                    ks &= ks - 1;
                    want |= ((entered[k] >> c) & 1) << k;
                }
                for &(index, ref sphere) in self.leaf(node.children[c as usize]) {
                    if want == 0 {
                        break;
                    }
                    // The lanes that leave this sphere do not test it.
                    let testing = want & !leaving(from, index);
                    if testing == 0 {
                        continue;
                    }
                    let t = sphere_lanes(sphere, &o4, &d4);
                    let mut ks = testing;
                    while ks != 0 {
                        let k = ks.trailing_zeros() as usize;
                        ks &= ks - 1;
                        if t.0[k] < limit[k] {
                            want &= !(1 << k);
                            blocked |= 1 << k;
                            live &= !(1 << k);
                        }
                    }
                }
            }
            let mut inner = any & !leaf;
            if top + WIDTH > STACK_SIZE {
                return (blocked, fallback | live);
            }
            while inner != 0 {
                let k = inner.trailing_zeros() as usize;
                inner &= inner - 1;
                stack.set_node(top, node.children[k]);
                top += 1;
            }
        }
        (blocked, fallback)
    }
}

/// The lanes (a bit each) whose ray leaves object `index`.
#[inline(always)]
fn leaving(from: &[u32; 4], index: u32) -> u32 {
    (0..4).fold(0, |lanes, k| lanes | (u32::from(from[k] == index) << k))
}

/// Four vectors in SIMD lanes.
#[inline(always)]
fn lanes4(v: &[Vec3; 4]) -> V4 {
    V4 {
        x: F4(v.map(|v| v.x)),
        y: F4(v.map(|v| v.y)),
        z: F4(v.map(|v| v.z)),
    }
}

/// [`SphereGeom::hit`] of four rays (not leaving the sphere) in SIMD lanes, the same
/// operations in the same order; NaN for a miss.
#[inline(always)]
fn sphere_lanes(sphere: &SphereGeom, origin: &V4, dir: &V4) -> F4 {
    let f = *origin - V4::splat(sphere.center);
    let r2 = F4::splat(sphere.radius2);
    sphere_hits(f, f.dot(f) - r2, r2, *dir, M4::NONE)
}

/// An axis-aligned box in single precision, in four lanes so that a union is two SIMD
/// operations: lane 3 is unused (a [`Prim`] keeps its sphere's position there).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
struct Box4 {
    lo: [f32; 4],
    hi: [f32; 4],
}

#[inline(always)]
fn min4(a: [f32; 4], b: [f32; 4]) -> [f32; 4] {
    std::array::from_fn(|i| if a[i] < b[i] { a[i] } else { b[i] })
}

#[inline(always)]
fn max4(a: [f32; 4], b: [f32; 4]) -> [f32; 4] {
    std::array::from_fn(|i| if a[i] > b[i] { a[i] } else { b[i] })
}

impl Box4 {
    const EMPTY: Box4 = Box4 {
        lo: [f32::INFINITY; 4],
        hi: [f32::NEG_INFINITY; 4],
    };

    #[inline(always)]
    fn union(&self, o: &Box4) -> Box4 {
        Box4 {
            lo: min4(self.lo, o.lo),
            hi: max4(self.hi, o.hi),
        }
    }

    #[inline(always)]
    fn grow(&self, p: [f32; 4]) -> Box4 {
        Box4 {
            lo: min4(self.lo, p),
            hi: max4(self.hi, p),
        }
    }

    /// Half the surface area (the heuristic only compares areas); 0 for an empty box.
    #[inline(always)]
    fn area(&self) -> f32 {
        let e: [f32; 3] = std::array::from_fn(|a| (self.hi[a] - self.lo[a]).max(0.0));
        e[0] * e[1] + e[1] * e[2] + e[2] * e[0]
    }
}

/// A sphere during the build: its box, rounded outward to `f32`, with the sphere's
/// position in the input in lane 3 of `lo` (as bits).
type Prim = Box4;

impl Box4 {
    fn prim(index: u32, s: &SphereGeom) -> Prim {
        let c = [s.center.x, s.center.y, s.center.z];
        Box4 {
            lo: [
                down32(c[0] - s.radius),
                down32(c[1] - s.radius),
                down32(c[2] - s.radius),
                f32::from_bits(index),
            ],
            hi: [
                up32(c[0] + s.radius),
                up32(c[1] + s.radius),
                up32(c[2] + s.radius),
                0.0,
            ],
        }
    }

    /// The prim's sphere's position in the input.
    fn index(&self) -> u32 {
        self.lo[3].to_bits()
    }

    /// The prim's box without the index.
    #[inline(always)]
    fn bounds(&self) -> Box4 {
        Box4 {
            lo: [self.lo[0], self.lo[1], self.lo[2], 0.0],
            hi: self.hi,
        }
    }

    /// Twice the prim's centre (only compared), lane 3 zero.
    #[inline(always)]
    fn centre2(&self) -> [f32; 4] {
        [
            self.lo[0] + self.hi[0],
            self.lo[1] + self.hi[1],
            self.lo[2] + self.hi[2],
            0.0,
        ]
    }
}

/// A range of prims that becomes one child of a node: its box, the box of its doubled
/// centres, and its binary depth.
#[derive(Clone, Copy, Debug)]
struct Part {
    start: usize,
    len: usize,
    bounds: Box4,
    centres: Box4,
    depth: u32,
}

/// Builds the node over the prims of `whole` and its subtree into `out`, reordering
/// the prims so that each leaf's are contiguous; `offset` is the position of `prims`
/// in the whole array. Returns the node's index.
fn build_node(
    prims: &mut [Prim],
    offset: usize,
    whole: Part,
    parallel: bool,
    out: &mut Vec<Node>,
) -> u32 {
    // Split the child with the largest box until there are eight.
    let mut parts = [whole; WIDTH];
    let mut count = 1;
    while count < WIDTH {
        let widest = (0..count)
            .filter(|&i| parts[i].len > LEAF_SIZE)
            .max_by(|&a, &b| parts[a].bounds.area().total_cmp(&parts[b].bounds.area()));
        let Some(i) = widest else { break };
        let p = parts[i];
        let (left, right) = split(&mut prims[p.start..p.start + p.len], &p);
        parts.copy_within(i + 1..count, i + 2);
        parts[i] = left;
        parts[i + 1] = right;
        count += 1;
    }
    let index = out.len();
    out.push(Node::EMPTY);
    let parts = &parts[..count];
    for (k, p) in parts.iter().enumerate() {
        if p.len <= LEAF_SIZE {
            let first = u32::try_from(offset + p.start).expect("at most 2²⁸ spheres");
            out[index].set(k, &p.bounds, LEAF_BIT | ((p.len as u32 - 1) << 28) | first);
        }
    }
    if parallel && prims.len() >= PARALLEL_MIN {
        // The inner children's subtrees, each into its own array, then appended.
        use rayon::prelude::*;
        let mut jobs = Vec::new();
        let mut rest = prims;
        for (k, p) in parts.iter().enumerate() {
            let (mine, tail) = std::mem::take(&mut rest).split_at_mut(p.len);
            rest = tail;
            if p.len > LEAF_SIZE {
                jobs.push((k, mine, *p));
            }
        }
        let built: Vec<(usize, Vec<Node>)> = jobs
            .into_par_iter()
            .map(|(k, mine, p)| {
                let mut sub = Vec::with_capacity(p.len / 4);
                let whole = Part { start: 0, ..p };
                build_node(
                    mine,
                    offset + p.start,
                    whole,
                    p.len >= PARALLEL_MIN,
                    &mut sub,
                );
                (k, sub)
            })
            .collect();
        for (k, sub) in built {
            let base = u32::try_from(out.len()).expect("node count fits in u32");
            out.extend(sub.into_iter().map(|mut node| {
                for c in &mut node.children {
                    if *c & LEAF_BIT == 0 {
                        *c += base;
                    }
                }
                node
            }));
            out[index].set(k, &parts[k].bounds, base);
        }
    } else {
        for (k, p) in parts.iter().enumerate() {
            if p.len > LEAF_SIZE {
                let whole = Part { start: 0, ..*p };
                let child = build_node(
                    &mut prims[p.start..p.start + p.len],
                    offset + p.start,
                    whole,
                    false,
                    out,
                );
                out[index].set(k, &p.bounds, child);
            }
        }
    }
    u32::try_from(index).expect("node count fits in u32")
}

/// Per axis, the bin of doubled centres `c` for bins from `lo` with `scale` per unit.
#[inline(always)]
fn bins_of(c: [f32; 4], lo: [f32; 4], scale: [f32; 4], last: i32) -> [usize; 3] {
    let b: [i32; 4] = std::array::from_fn(|a| ((c[a] - lo[a]) * scale[a]) as i32);
    std::array::from_fn(|a| (b[a].clamp(0, last)) as usize)
}

/// Splits the prims of `whole` (`prims`, more than one) in two by the binned surface
/// area heuristic over their centres, or at the median below [`SAH_MAX_DEPTH`];
/// returns the two parts.
fn split(prims: &mut [Prim], whole: &Part) -> (Part, Part) {
    let cb = whole.centres;
    let extent: [f32; 4] = std::array::from_fn(|a| cb.hi[a] - cb.lo[a]);
    let part = |start, len, bounds, centres| Part {
        start: whole.start + start,
        len,
        bounds,
        centres,
        depth: whole.depth + 1,
    };
    if whole.depth < SAH_MAX_DEPTH {
        // Fewer bins for few prims, where sweeping the bins would cost more than
        // binning. `scale` maps a centre to its bin (to bin 0 on an axis without
        // spread).
        let bins = (prims.len() / 2).clamp(4, BINS);
        let last = bins as i32 - 1;
        let scale: [f32; 4] = std::array::from_fn(|a| {
            if a < 3 && extent[a] > 0.0 {
                bins as f32 * 0.999_99 / extent[a]
            } else {
                0.0
            }
        });
        let mut boxes = [[Box4::EMPTY; BINS]; 3];
        let mut counts = [[0u32; BINS]; 3];
        for p in prims.iter() {
            let b = bins_of(p.centre2(), cb.lo, scale, last);
            for a in 0..3 {
                counts[a][b[a]] += 1;
                boxes[a][b[a]] = boxes[a][b[a]].union(p);
            }
        }
        // (cost, axis, first bin of the right part, left box, right box)
        let mut best: Option<(f32, usize, usize, Box4, Box4)> = None;
        for a in 0..3 {
            if extent[a] <= 0.0 {
                continue;
            }
            let mut left = [(Box4::EMPTY, 0u32); BINS];
            let (mut acc, mut m) = (Box4::EMPTY, 0);
            for b in 0..bins - 1 {
                acc = acc.union(&boxes[a][b]);
                m += counts[a][b];
                left[b] = (acc, m);
            }
            let (mut acc, mut m) = (Box4::EMPTY, 0);
            for b in (1..bins).rev() {
                acc = acc.union(&boxes[a][b]);
                m += counts[a][b];
                let (lb, ln) = left[b - 1];
                if ln == 0 || m == 0 {
                    continue;
                }
                let cost = lb.area() * ln as f32 + acc.area() * m as f32;
                if best.as_ref().is_none_or(|x| cost < x.0) {
                    best = Some((cost, a, b, lb, acc));
                }
            }
        }
        if let Some((_, a, b, lb, rb)) = best {
            // Hoare partition, gathering each side's centre bounds on the way.
            let (lo, per) = (cb.lo[a], scale[a]);
            let goes_left =
                |p: &Prim| ((((p.lo[a] + p.hi[a]) - lo) * per) as i32).clamp(0, last) < b as i32;
            let (mut lc, mut rc) = (Box4::EMPTY, Box4::EMPTY);
            let (mut i, mut j) = (0, prims.len());
            loop {
                while i < j && goes_left(&prims[i]) {
                    lc = lc.grow(prims[i].centre2());
                    i += 1;
                }
                while i < j && !goes_left(&prims[j - 1]) {
                    rc = rc.grow(prims[j - 1].centre2());
                    j -= 1;
                }
                if i >= j {
                    break;
                }
                prims.swap(i, j - 1);
            }
            let n = prims.len();
            return (part(0, i, lb.bounds(), lc), part(i, n - i, rb.bounds(), rc));
        }
    }
    // The median centre along the widest axis (any halving if the centres coincide).
    let axis = (0..3)
        .max_by(|&a, &b| extent[a].total_cmp(&extent[b]))
        .unwrap_or(0);
    let mid = prims.len() / 2;
    if extent[axis] > 0.0 {
        prims.select_nth_unstable_by(mid, |a, b| a.centre2()[axis].total_cmp(&b.centre2()[axis]));
    }
    let side = |ps: &[Prim]| {
        ps.iter().fold((Box4::EMPTY, Box4::EMPTY), |(b, c), p| {
            (b.union(&p.bounds()), c.grow(p.centre2()))
        })
    };
    let (lb, lc) = side(&prims[..mid]);
    let (rb, rc) = side(&prims[mid..]);
    (part(0, mid, lb, lc), part(mid, prims.len() - mid, rb, rc))
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

    /// The leaves' child references, by walking the tree from the root.
    fn leaves(bvh: &Bvh) -> Vec<u32> {
        let mut out = Vec::new();
        let mut todo = vec![0u32];
        while let Some(n) = todo.pop() {
            for &c in &bvh.nodes[n as usize].children {
                if c == EMPTY {
                    continue;
                }
                if c & LEAF_BIT != 0 {
                    out.push(c);
                } else {
                    todo.push(c);
                }
            }
        }
        out
    }

    #[test]
    fn every_sphere_is_in_exactly_one_leaf() {
        for n in [1, 2, 3, 4, 5, 9, 17, 100, 1000, 20_000] {
            let bvh = Bvh::build(&grid(n), Isa::best()).unwrap();
            let leaves = leaves(&bvh);
            assert!(leaves.iter().all(|&l| bvh.leaf(l).len() <= LEAF_SIZE));
            let mut seen: Vec<u32> = leaves
                .iter()
                .flat_map(|&l| bvh.leaf(l).iter().map(|&(i, _)| i))
                .collect();
            seen.sort_unstable();
            assert_eq!(seen, (0..n as u32).collect::<Vec<_>>(), "{n} spheres");
            assert!(bvh.node_count() >= 1);
        }
    }

    #[test]
    fn a_parallel_build_equals_the_sequential_one() {
        let spheres = grid(50_000);
        let one = Bvh::build(&spheres, Isa::best()).unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let two = pool.install(|| Bvh::build(&spheres, Isa::best()).unwrap());
        let order = |b: &Bvh| b.spheres.iter().map(|s| s.0).collect::<Vec<_>>();
        assert_eq!(order(&one), order(&two));
        assert_eq!(one.node_count(), two.node_count());
    }

    #[test]
    fn coincident_spheres_build_a_shallow_tree() {
        let same: Vec<(u32, SphereGeom)> = (0..10_000)
            .map(|i| (i, SphereGeom::new(Vec3::ZERO, 1.0)))
            .collect();
        let bvh = Bvh::build(&same, Isa::best()).unwrap();
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
        assert!(Bvh::build(
            &[(0, SphereGeom::new(Vec3::new(1e200, 0.0, 0.0), 1.0))],
            Isa::best()
        )
        .is_none());
        assert!(Bvh::build(
            &[(0, SphereGeom::new(Vec3::new(2e30, 0.0, 0.0), 1.0))],
            Isa::best()
        )
        .is_none());
        assert!(Bvh::build(&[], Isa::best()).is_none());
    }

    #[test]
    fn rounding_to_f32_is_outward() {
        for x in [
            0.1,
            -0.1,
            1e-40,
            -1e-40,
            1e30,
            -1e30,
            0.0,
            16_777_217.0,
            1e5 + 1e-3,
        ] {
            assert!(f64::from(down32(x)) <= x && f64::from(up32(x)) >= x, "{x}");
            assert!(f64::from(down32(x).next_up()) > x || f64::from(down32(x)) == x);
        }
        assert_eq!(up32(f64::INFINITY), f32::INFINITY);
    }

    /// The branch-free rounding equals the least `f32` not below `x`.
    #[test]
    fn rounding_up_is_the_least_f32_not_below() {
        let reference = |x: f64| {
            let f = x as f32;
            if f64::from(f) < x {
                f.next_up()
            } else {
                f
            }
        };
        let mut rng = Mix::seeded(4);
        let mut cases = vec![
            0.0,
            -0.0,
            1e-46,
            -1e-46,
            f64::from(f32::MAX) * (1.0 + 1e-9),
            -f64::from(f32::MAX) * (1.0 + 1e-9),
            1e39,
            -1e39,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        for _ in 0..200_000 {
            let exponent = (rng.next() % 320) as i32 - 160;
            cases.push(rng.unit() * 2f64.powi(exponent));
            let f = f32::from_bits(rng.next() as u32);
            if !f.is_nan() {
                cases.extend([f64::from(f), f64::from(f) * (1.0 + 1e-12)]);
            }
        }
        for x in cases {
            assert_eq!(up32(x).to_bits(), reference(x).to_bits(), "{x:e}");
            assert_eq!(down32(x).to_bits(), (-reference(-x)).to_bits(), "{x:e}");
        }
    }

    use crate::geometry::tests::Mix;

    /// The nearest hit and some occluder within `limit` by the brute-force loop, and by
    /// the hierarchy (portable and, where there is AVX2, vector box tests): equal.
    ///
    /// The brute-force loop runs once for each ray (the ray, and the packet's lanes
    /// below): the spheres it meets and where, in the spheres' order, from which every
    /// expected answer is read.
    fn check(bvh: &mut Bvh, spheres: &[(u32, SphereGeom)], origin: Vec3, dir: Vec3, limit: f64) {
        let meets = |origin: Vec3, dir: Vec3| -> Vec<(f64, u32)> {
            spheres
                .iter()
                .filter_map(|&(i, ref s)| s.hit(origin, dir, false).map(|t| (t, i)))
                .collect()
        };
        let met = meets(origin, dir);
        let mut brute = (f64::INFINITY, u32::MAX);
        for &(t, i) in &met {
            consider(&mut brute, t, i);
        }
        let blocked = met.iter().any(|&(t, _)| t < limit);
        let mut stack = Stack::new();
        let built_for = bvh.isa;
        for isa in [Isa::Portable, Isa::best()] {
            bvh.isa = isa;
            let mut best = (f64::INFINITY, u32::MAX);
            bvh.nearest(origin, dir, u32::MAX, &mut best, &mut stack)
                .unwrap_or_else(|_| panic!("{origin:?} {dir:?}: out of range"));
            assert!(
                best.0.to_bits() == brute.0.to_bits() && best.1 == brute.1,
                "{isa:?} {origin:?} {dir:?}: {best:?} vs {brute:?}"
            );
            let occluder = bvh
                .occluder(origin, dir, u32::MAX, limit, &mut stack)
                .expect("within range");
            assert_eq!(
                occluder.is_some(),
                blocked,
                "{isa:?} {origin:?} {dir:?} {limit}"
            );
            // The packet traversal, lane by lane the same answers: the ray, the ray
            // reversed, an inactive lane holding a ray out of range, and the ray with
            // half its limit (ties with the single-ray answers; lanes parting ways).
            let origins = [origin, origin, Vec3::new(1e31, 0.0, 0.0), origin];
            let dirs = [dir, -dir, Vec3::ZERO, dir];
            let limits = [limit, limit, f64::NAN, limit * 0.5];
            let masks = [0b1011, 0b0001, 0b1000];
            // What each lane's ray meets, for the lanes some mask turns on.
            let lane_met: [Vec<(f64, u32)>; 4] = std::array::from_fn(|k| {
                if masks.iter().any(|m| m & (1 << k) != 0) {
                    meets(origins[k], dirs[k])
                } else {
                    Vec::new()
                }
            });
            for lanes in masks {
                // Nearest hits: lane 3 starts from a best hit found elsewhere, at the
                // brute-force distance with a higher or lower index (a tie either way).
                let seed = [
                    (f64::INFINITY, u32::MAX),
                    (f64::INFINITY, u32::MAX),
                    (1.0, 7),
                    (brute.0, if brute.1 % 2 == 0 { 0 } else { u32::MAX - 1 }),
                ];
                let mut best4 = seed;
                let rest = bvh.nearests(&origins, &dirs, u32::MAX, &mut best4, lanes, &mut stack);
                assert_eq!(rest, 0, "{isa:?} {origin:?} {dir:?}: out of range");
                for k in 0..4 {
                    let mut expected = seed[k];
                    if lanes & (1 << k) != 0 {
                        for &(t, i) in &lane_met[k] {
                            consider(&mut expected, t, i);
                        }
                    }
                    assert!(
                        best4[k].0.to_bits() == expected.0.to_bits() && best4[k].1 == expected.1,
                        "{isa:?} lane {k} of {lanes:b}: {origin:?} {dir:?}: {:?} vs {expected:?}",
                        best4[k]
                    );
                }
                let (hit, rest) =
                    bvh.occluders(&origins, &dirs, &[u32::MAX; 4], &limits, lanes, &mut stack);
                assert_eq!(rest, 0, "{isa:?} {origin:?} {dir:?}: out of range");
                for k in 0..4 {
                    let expected =
                        lanes & (1 << k) != 0 && lane_met[k].iter().any(|&(t, _)| t < limits[k]);
                    assert_eq!(
                        hit & (1 << k) != 0,
                        expected,
                        "{isa:?} lane {k} of {lanes:b}: {origin:?} {dir:?} {limit}"
                    );
                }
                // Each lane leaving its own sphere, as the shadow rays of hits on
                // different spheres do: lane 0 the sphere the ray meets first (not
                // tested for that lane alone), lane 3 none, with its limit exactly at
                // the nearest hit (a tie, which does not block). The same answers as
                // the brute-force loop and as one ray at a time.
                let froms = [brute.1, u32::MAX, 0, u32::MAX];
                let limits = [limit, limit, f64::NAN, brute.0];
                let (hit, rest) =
                    bvh.occluders(&origins, &dirs, &froms, &limits, lanes, &mut stack);
                assert_eq!(rest, 0, "{isa:?} {origin:?} {dir:?}: out of range");
                for k in 0..4 {
                    let expected = lanes & (1 << k) != 0
                        && lane_met[k]
                            .iter()
                            .any(|&(t, i)| i != froms[k] && t < limits[k]);
                    assert_eq!(
                        hit & (1 << k) != 0,
                        expected,
                        "{isa:?} lane {k} of {lanes:b} from {}: {origin:?} {dir:?} {limit}",
                        froms[k]
                    );
                    if lanes & (1 << k) != 0 {
                        let alone = bvh
                            .occluder(origins[k], dirs[k], froms[k], limits[k], &mut stack)
                            .expect("within range");
                        assert_eq!(alone.is_some(), expected, "{isa:?} lane {k} alone");
                    }
                }
            }
        }
        bvh.isa = built_for;
    }

    /// Rays aimed at a sphere's silhouette (a relative 10⁻⁹ inside or outside), at its
    /// box's corners and along the axes through them, from `origin`s near `scale`.
    fn grazing(rng: &mut Mix, spheres: &[(u32, SphereGeom)], far: f64, rays: usize) {
        let mut bvh = Bvh::build(spheres, Isa::best()).unwrap();
        for case in 0..rays {
            let (_, s) = spheres[(rng.next() % spheres.len() as u64) as usize];
            let origin = s.center + rng.vec() * far;
            let aim = match case % 3 {
                0 => s.center + rng.vec().normalize() * (s.radius * (1.0 + rng.unit() * 1e-9)),
                1 => {
                    let corner = |r: &mut Mix| if r.unit() < 0.0 { -s.radius } else { s.radius };
                    s.center + Vec3::new(corner(rng), corner(rng), corner(rng))
                }
                _ => s.center + rng.vec() * (2.0 * s.radius),
            };
            let mut dir = (aim - origin).normalize();
            if case % 7 == 0 {
                // Along an axis, exactly, through the sphere's silhouette.
                let axis = (rng.next() % 3) as usize;
                let mut o = [s.center.x, s.center.y, s.center.z];
                let mut d = [0.0; 3];
                d[axis] = if rng.unit() < 0.0 { -1.0 } else { 1.0 };
                o[axis] -= d[axis] * far;
                let side = (axis + 1) % 3;
                o[side] += s.radius * (1.0 + rng.unit() * 1e-12);
                let origin = Vec3::new(o[0], o[1], o[2]);
                dir = Vec3::new(d[0], d[1], d[2]);
                check(&mut bvh, spheres, origin, dir, f64::INFINITY);
                continue;
            }
            let limit = [f64::INFINITY, far, far * 0.5][case % 3];
            check(&mut bvh, spheres, origin, dir, limit);
        }
    }

    fn soup(rng: &mut Mix, n: usize, at: f64, spread: f64, radius: f64) -> Vec<(u32, SphereGeom)> {
        (0..n)
            .map(|i| {
                let c = Vec3::new(at, -at, at * 0.5) + rng.vec() * spread;
                (
                    i as u32,
                    SphereGeom::new(c, radius * (1.0 + rng.unit().abs())),
                )
            })
            .collect()
    }

    #[test]
    fn grazing_rays_at_unit_scale() {
        let mut rng = Mix::seeded(1);
        let spheres = soup(&mut rng, 2000, 0.0, 10.0, 0.1);
        grazing(&mut rng, &spheres, 20.0, 20_000);
    }

    /// Spheres at 10⁵ with radius 10⁻³: f32 spacing there is ~0.008, larger than the
    /// spheres, so rounding the origin and the boxes to f32 matters. Seen from about
    /// their own spread, and (below) from within a hundredth of it, as two tests that
    /// run side by side: each takes seconds, as the margin at 10⁵ makes a ray enter
    /// most boxes.
    #[test]
    fn tiny_spheres_far_from_the_origin() {
        let mut rng = Mix::seeded(2);
        let spheres = soup(&mut rng, 3000, 1e5, 0.5, 1e-3);
        grazing(&mut rng, &spheres, 1.0, 20_000);
    }

    #[test]
    fn tiny_spheres_far_from_the_origin_seen_from_close_by() {
        let spheres = soup(&mut Mix::seeded(2), 3000, 1e5, 0.5, 1e-3);
        grazing(&mut Mix::seeded(7), &spheres, 1e-2, 20_000);
    }

    #[test]
    fn huge_and_tiny_coordinates() {
        for (at, spread, radius, far) in [
            (1e28f64, 1e26, 1e24, 1e27),
            (1e-20, 1e-22, 1e-25, 1e-21),
            (0.0, 1e-30, 1e-33, 1e-30),
            (3.0, 1e-6, 1e-9, 1e-7),
        ] {
            let mut rng = Mix::seeded(at.to_bits());
            let spheres = soup(&mut rng, 500, at, spread, radius);
            grazing(&mut rng, &spheres, far, 5000);
        }
    }

    #[test]
    fn origins_on_box_sides_and_zero_direction_components() {
        // Spheres on a lattice of f32-exact coordinates, rays from their box planes.
        let spheres: Vec<(u32, SphereGeom)> = (0..512)
            .map(|i| {
                let c = Vec3::new((i % 8) as f64, ((i / 8) % 8) as f64, (i / 64) as f64);
                (i as u32, SphereGeom::new(c, 0.5))
            })
            .collect();
        let mut bvh = Bvh::build(&spheres, Isa::best()).unwrap();
        let mut rng = Mix::seeded(3);
        for _ in 0..20_000 {
            let pick = |r: &mut Mix| ((r.next() % 17) as f64 - 4.0) * 0.5;
            let origin = Vec3::new(pick(&mut rng), pick(&mut rng), pick(&mut rng));
            let mut d = [rng.unit(), rng.unit(), rng.unit()];
            for c in &mut d {
                match rng.next() % 4 {
                    0 => *c = 0.0,
                    1 => *c = -0.0,
                    2 => {
                        *c *= if rng.next().is_multiple_of(2) {
                            1e-30
                        } else {
                            1e-300
                        }
                    }
                    _ => {}
                }
            }
            let dir = Vec3::new(d[0], d[1], d[2]);
            if dir.dot(dir) < 1e-6 {
                continue;
            }
            check(&mut bvh, &spheres, origin, dir.normalize(), f64::INFINITY);
        }
    }
}
