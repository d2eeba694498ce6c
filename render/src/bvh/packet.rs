//! The packet traversals: the nearest hits ([`Bvh::nearests`]) and occluders
//! ([`Bvh::occluders`]) of up to four rays that traverse the tree together, sharing
//! the stack and the node loads, each lane with the answer [`super::single`] gives
//! its ray alone. The tracer's packet integrator traces its four rays through them.

use std::mem::MaybeUninit;

use super::box_ray::BoxRay;
use super::{consider, Bvh, Stack, LEAF_BIT, STACK_SIZE, WIDTH};
use crate::geometry::{sphere_hits, SphereGeom};
use crate::simd::isa_dispatch;
use crate::vec3::{Vec3, F4, M4, V4};

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
