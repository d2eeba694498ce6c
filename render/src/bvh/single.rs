//! The single-ray traversals: the nearest hit of one ray ([`Bvh::nearest`]), visiting
//! children near to far, and some occluder of one shadow ray ([`Bvh::occluder`]),
//! which stops at the first found. They define what the hierarchy answers for a ray;
//! the packet traversals of [`super::packet`] give each lane the same answer.

use super::box_ray::BoxRay;
use super::{consider, Bvh, Fallback, Stack, LEAF_BIT, STACK_SIZE, WIDTH};
use crate::simd::isa_dispatch;
use crate::vec3::Vec3;

impl Bvh {
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
