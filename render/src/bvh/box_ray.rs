//! The box test of a traversal: a ray prepared once for single-precision slab tests,
//! and the test of a node's eight child boxes against it, portable and in AVX2. It is
//! what the margin argument of [`super`] proves conservative; both traversals,
//! [`super::single`] and [`super::packet`], test their boxes with it.

use super::{up32, Node, MAX_SCALE, WIDTH};
use crate::simd::Isa;
use crate::vec3::Vec3;

/// The margin δ per unit of |o|₁ + S: it also covers rounding the origin to `f32`.
const MARGIN: f64 = 1.0 / (1u64 << 22) as f64;
/// The margin's floor, far above the rounding of values near the underflow range.
const MARGIN_FLOOR: f64 = 1.0 / (1u128 << 120) as f64;
/// The slack factor K of the entry test t₀ ≤ t₁·K.
const SLACK: f32 = 1.0 + 1.0 / (1u32 << 20) as f32;

/// A ray prepared for box tests in single precision (see the margin argument of
/// [`super`]): the origin shifted by ±δ and rounded outward, once for the slab side
/// met first and once for the other, and the reciprocal direction.
pub(super) struct BoxRay {
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
    pub(super) fn new(origin: Vec3, dir: Vec3, scale: f64) -> Option<Self> {
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
    pub(super) fn limit(t: f64) -> (f32, f32) {
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
    pub(super) fn enter(&self, node: &Node, t_max: f32, isa: Isa) -> (u32, u32, [f32; WIDTH]) {
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
