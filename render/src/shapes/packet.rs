//! Four rays at once through section 8's shapes: the slab test and the watertight
//! triangle test lane by lane, with the operations of the single-ray code
//! ([`crate::bounds`], [`super::triangle`]) in the same order, so each lane's hit has
//! the bits that ray's hit has when traced alone. The tracer runs this code compiled
//! for its instruction set (AVX2 or portable), like its other lane code.
//!
//! The walk visits a node when any live lane enters it; a lane that does not enter it
//! only costs a wasted test, since every hit is checked lane by lane against that
//! lane's best so far, with the same tie rule.

use super::{before, cuboid, Detail, Item, ShapeHit, Shapes};
use crate::bounds::{gamma, Bounds, EXIT_SCALE};
use crate::hierarchy::{insert_sorted, Hierarchy, Stack, EMPTY, LEAF};
use crate::vec3::{Vec3, F4, LANES, M4, V4};

/// Up to four rays, each leaving object `from[k]` (triangle `prim[k]`); lanes outside
/// `active` are ignored.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Rays4 {
    pub origin: V4,
    pub dir: V4,
    pub active: M4,
    pub from: [u32; LANES],
    pub prim: [u32; LANES],
}

/// The slab test's constants for four rays.
#[derive(Clone, Copy, Debug)]
struct Slab4 {
    origin: V4,
    inv: V4,
}

impl Slab4 {
    #[inline(always)]
    fn new(origin: V4, dir: V4) -> Self {
        let one = F4::splat(1.0);
        Slab4 {
            origin,
            inv: V4 {
                x: one / dir.x,
                y: one / dir.y,
                z: one / dir.z,
            },
        }
    }

    /// The lanes whose ray enters `b` widened by `margin` before their `t_max`, and
    /// where each enters.
    #[inline(always)]
    fn enter(&self, b: &Bounds, margin: F4, t_max: F4) -> (M4, F4) {
        let mut t0 = F4::splat(0.0);
        let mut t1 = t_max;
        let axes = [
            (self.origin.x, self.inv.x),
            (self.origin.y, self.inv.y),
            (self.origin.z, self.inv.z),
        ];
        for (k, (o, inv)) in axes.into_iter().enumerate() {
            let near = (F4::splat(b.lo[k]) - margin - o) * inv;
            let far = (F4::splat(b.hi[k]) + margin - o) * inv;
            let swap = near.gt(far);
            let (near, far) = (swap.select(far, near), swap.select(near, far));
            let far = far * EXIT_SCALE;
            t0 = near.gt(t0).select(near, t0);
            t1 = far.lt(t1).select(far, t1);
        }
        // t0 ≤ t1, as the scalar test's "not t0 > t1" (the bounds are never NaN).
        (t0.le(t1), t0)
    }
}

/// The sheared frames of four rays ([`super::triangle::ShearedRay`], lane by lane).
#[derive(Clone, Copy, Debug)]
struct Sheared4 {
    origin: V4,
    kx: [usize; LANES],
    ky: [usize; LANES],
    kz: [usize; LANES],
    sx: F4,
    sy: F4,
    sz: F4,
}

impl Sheared4 {
    #[inline(always)]
    fn new(origin: V4, dir: V4) -> Self {
        let lanes: [super::triangle::ShearedRay; LANES] =
            std::array::from_fn(|k| super::triangle::ShearedRay::new(origin.lane(k), dir.lane(k)));
        let part = |f: &dyn Fn(&super::triangle::ShearedRay) -> f64| {
            F4(std::array::from_fn(|k| f(&lanes[k])))
        };
        Sheared4 {
            origin,
            kx: std::array::from_fn(|k| lanes[k].axes().0),
            ky: std::array::from_fn(|k| lanes[k].axes().1),
            kz: std::array::from_fn(|k| lanes[k].axes().2),
            sx: part(&|r| r.shear().0),
            sy: part(&|r| r.shear().1),
            sz: part(&|r| r.shear().2),
        }
    }

    #[inline(always)]
    fn frame(&self, p: Vec3) -> [F4; 3] {
        let q = [
            F4::splat(p.x) - self.origin.x,
            F4::splat(p.y) - self.origin.y,
            F4::splat(p.z) - self.origin.z,
        ];
        let pick = |axes: &[usize; LANES]| F4(std::array::from_fn(|k| q[axes[k]].0[k]));
        let (x, y, z) = (pick(&self.kx), pick(&self.ky), pick(&self.kz));
        [x + self.sx * z, y + self.sy * z, z]
    }

    /// Lane by lane, [`super::triangle::ShearedRay::hit`]: the lanes that hit, their
    /// distances and barycentric coordinates.
    #[inline(always)]
    fn hit(&self, p0: Vec3, p1: Vec3, p2: Vec3, t_max: F4) -> (M4, F4, [F4; 3]) {
        woop4(
            self.frame(p0),
            self.frame(p1),
            self.frame(p2),
            self.sz,
            t_max,
        )
    }
}

impl Sheared4 {
    /// The lanes of `lanes` that hit triangle `v` before their `t_max` (bit k for lane
    /// k), and their distances and barycentric coordinates.
    #[inline(always)]
    fn hits(&self, v: [Vec3; 3], lanes: M4, t_max: F4) -> (u32, F4, [F4; 3]) {
        let (hit, t, b) = self.hit(v[0], v[1], v[2], t_max);
        (hit.and(lanes).bitmask(), t, b)
    }
}

/// The watertight test after the frame, lane by lane ([`super::triangle::ShearedRay::hit`]
/// from its edge functions on): vertices `a`, `b`, `c` in the ray's frame, its `sz`; the
/// lanes that hit, their distances and barycentric coordinates. The lanes are four rays
/// and one triangle, or one ray and four triangles.
#[inline(always)]
pub(super) fn woop4(a: [F4; 3], b: [F4; 3], c: [F4; 3], sz: F4, t_max: F4) -> (M4, F4, [F4; 3]) {
    let zero = F4::splat(0.0);
    let e0 = b[0] * c[1] - b[1] * c[0];
    let e1 = c[0] * a[1] - c[1] * a[0];
    let e2 = a[0] * b[1] - a[1] * b[0];
    let negative = e0.lt(zero).or(e1.lt(zero)).or(e2.lt(zero));
    let positive = e0.gt(zero).or(e1.gt(zero)).or(e2.gt(zero));
    let mut hit = negative.and(positive).xor(M4::ALL);
    let det = e0 + e1 + e2;
    hit = hit.and(M4::from_fn(|k| det.0[k] != 0.0 && det.0[k].is_finite()));
    let (az, bz, cz) = (a[2] * sz, b[2] * sz, c[2] * sz);
    let t_scaled = e0 * az + e1 * bz + e2 * cz;
    let bound = t_max * det;
    let below = det.lt(zero).and(t_scaled.ge(zero).or(t_scaled.lt(bound)));
    let above = det.gt(zero).and(t_scaled.le(zero).or(t_scaled.gt(bound)));
    hit = hit.and_not(below.or(above));
    let inv_det = F4::splat(1.0) / det;
    let t = t_scaled * inv_det;
    hit = hit.and(t.le(t_max));
    let abs = |v: F4| v.map(f64::abs);
    let max = |u: F4, v: F4| u.zip(v, f64::max);
    let max_z = max(max(abs(az), abs(bz)), abs(cz));
    let delta_z = max_z * gamma(3);
    let max_x = max(max(abs(a[0]), abs(b[0])), abs(c[0]));
    let max_y = max(max(abs(a[1]), abs(b[1])), abs(c[1]));
    let delta_x = (max_x + max_z) * gamma(5);
    let delta_y = (max_y + max_z) * gamma(5);
    let delta_e = (F4::splat(gamma(2)) * max_x * max_y + delta_y * max_x + delta_x * max_y) * 2.0;
    let max_e = max(max(abs(e0), abs(e1)), abs(e2));
    let delta_t = (F4::splat(gamma(3)) * max_e * max_z + delta_e * max_z + delta_z * max_e)
        * 3.0
        * abs(inv_det);
    hit = hit.and(t.gt(delta_t));
    (hit, t, [e0 * inv_det, e1 * inv_det, e2 * inv_det])
}

impl Hierarchy {
    /// [`Hierarchy::walk`] for four rays: leaves reached by any lane of `live`, with
    /// the lanes that reach them, nearer children first (by the entry of the first
    /// lane that enters them).
    #[inline(always)]
    fn walk4(
        &self,
        ray: &Slab4,
        margin: F4,
        live: M4,
        t_max: impl Fn() -> F4,
        mut leaf: impl FnMut(u32, M4),
    ) {
        if self.nodes.is_empty() || !live.any() {
            return;
        }
        // The boxes are relative to the hierarchy's origin: so are the rays here (each
        // origin's rounding, at most 2⁻⁵³ of it, is covered by widening the margin).
        let shift = |k: usize| F4::splat(self.origin[k]);
        let origin = V4 {
            x: ray.origin.x - shift(0),
            y: ray.origin.y - shift(1),
            z: ray.origin.z - shift(2),
        };
        let reach = |k: usize| {
            let o = origin.lane(k);
            o.x.abs().max(o.y.abs()).max(o.z.abs())
        };
        let margin = F4(std::array::from_fn(|k| {
            margin.0[k] + (reach(k) + self.scale) * (1.0 / (1u64 << 50) as f64)
        }));
        let ray = &Slab4 {
            origin,
            inv: ray.inv,
        };
        // A child waiting on the stack keeps where each lane enters it, and loses the
        // lanes whose hit found meanwhile comes before that.
        let mut stack = Stack::<(u32, M4, F4)>::new();
        let mut node = 0u32;
        loop {
            let n = &self.nodes[node as usize];
            let limit = t_max();
            let mut hits = [(0.0f64, (0u32, M4::NONE, F4::splat(0.0))); LANES];
            let mut count = 0;
            for c in 0..LANES {
                if n.child[c] == EMPTY {
                    break;
                }
                let (lanes, enter) = ray.enter(&n.child_bounds(c), margin, limit);
                let lanes = lanes.and(live);
                if !lanes.any() {
                    continue;
                }
                let first = lanes.bitmask().trailing_zeros() as usize;
                insert_sorted(
                    &mut hits,
                    count,
                    (enter.0[first], (n.child[c], lanes, enter)),
                );
                count += 1;
            }
            for &(_, (child, lanes, enter)) in hits[..count].iter().rev() {
                stack.push((child, lanes, enter));
            }
            loop {
                let Some((child, lanes, enter)) = stack.pop() else {
                    return;
                };
                // Entered exactly at the best distance: still visited, for ties.
                let lanes = lanes.and(enter.le(t_max()));
                if !lanes.any() {
                    continue;
                }
                if child & LEAF != 0 {
                    leaf(child & !LEAF, lanes);
                    continue;
                }
                node = child;
                break;
            }
        }
    }
}

impl Shapes {
    /// [`Shapes::nearest`] for four rays: each lane's nearest hit before its `best`,
    /// with the bits the single-ray search gives it. Call it compiled for the tracer's
    /// instruction set.
    #[inline(always)]
    pub fn nearest4(
        &self,
        rays: &Rays4,
        best: &mut [(f64, u32, u32); LANES],
    ) -> [Option<ShapeHit>; LANES] {
        let sheared = Sheared4::new(rays.origin, rays.dir);
        let slab = Slab4::new(rays.origin, rays.dir);
        let margin = F4(std::array::from_fn(|k| {
            self.world_margin(rays.origin.lane(k))
        }));
        let best_cell = std::cell::Cell::new(*best);
        let t_max = || F4(best_cell.get().map(|b| b.0));
        let mut found: [Option<ShapeHit>; LANES] = [None; LANES];
        let mut consider = |k: usize, hit: (f64, u32, u32, Detail), item: u32| {
            let mut b = best_cell.get();
            let (t, object, prim, detail) = hit;
            if before(t, object, prim, &b[k]) {
                b[k] = (t, object, prim);
                best_cell.set(b);
                found[k] = Some(ShapeHit {
                    t,
                    object,
                    prim,
                    item,
                    detail,
                });
            }
        };
        self.top.walk4(
            &slab,
            margin,
            rays.active,
            t_max,
            #[inline(always)]
            |leaf, lanes| {
                for &i in self.top.primitives(leaf) {
                    match &self.items[i as usize] {
                        &Item::Box { object, min, max } => {
                            for k in 0..LANES {
                                if lanes.get(k) {
                                    let limit = best_cell.get()[k].0;
                                    let (o, d) = (rays.origin.lane(k), rays.dir.lane(k));
                                    if let Some(h) = cuboid::hit(min, max, o, d, limit) {
                                        consider(k, (h.t, object, 0, Detail::Box(h)), i);
                                    }
                                }
                            }
                        }
                        Item::Triangle { object, v } => {
                            let lanes = lanes.and(M4::from_fn(|k| rays.from[k] != *object));
                            let (mut bits, t, b) = sheared.hits(*v, lanes, t_max());
                            while bits != 0 {
                                let k = bits.trailing_zeros() as usize;
                                bits &= bits - 1;
                                let bary = [b[0].0[k], b[1].0[k], b[2].0[k]];
                                consider(k, (t.0[k], *object, 0, Detail::Triangle(bary)), i);
                            }
                        }
                        Item::Instance(instance) => {
                            let accel = crate::mesh::accel::MeshAccel::of(&instance.geometry);
                            let (local, margin) = if instance.identity {
                                (slab, margin)
                            } else {
                                let map = |k: usize| {
                                    let o = rays.origin.lane(k);
                                    (
                                        instance.inverse.point([o.x, o.y, o.z]),
                                        instance.inverse.vector(rays.dir.lane(k)),
                                    )
                                };
                                let mapped: [(Vec3, Vec3); LANES] = std::array::from_fn(map);
                                let origin = V4 {
                                    x: F4(mapped.map(|m| m.0.x)),
                                    y: F4(mapped.map(|m| m.0.y)),
                                    z: F4(mapped.map(|m| m.0.z)),
                                };
                                let dir = V4 {
                                    x: F4(mapped.map(|m| m.1.x)),
                                    y: F4(mapped.map(|m| m.1.y)),
                                    z: F4(mapped.map(|m| m.1.z)),
                                };
                                let margin = F4(std::array::from_fn(|k| {
                                    self.instance_margin(
                                        instance,
                                        rays.origin.lane(k),
                                        f64::INFINITY,
                                    )
                                }));
                                (Slab4::new(origin, dir), margin)
                            };
                            accel.hierarchy.walk4(
                                &local,
                                margin,
                                lanes,
                                t_max,
                                #[inline(always)]
                                |leaf, lanes| {
                                    let block = instance.block(&accel.hierarchy, leaf);
                                    let v = block.v;
                                    for k in 0..LANES {
                                        if !block.live().get(k) {
                                            break;
                                        }
                                        let tri = block.tri[k];
                                        let lanes = lanes.and(M4::from_fn(|r| {
                                            rays.from[r] != instance.object || rays.prim[r] != tri
                                        }));
                                        if !lanes.any() {
                                            continue;
                                        }
                                        let (mut bits, t, b) = sheared.hits(
                                            [v[0].lane(k), v[1].lane(k), v[2].lane(k)],
                                            lanes,
                                            t_max(),
                                        );
                                        while bits != 0 {
                                            let r = bits.trailing_zeros() as usize;
                                            bits &= bits - 1;
                                            let bary = [b[0].0[r], b[1].0[r], b[2].0[r]];
                                            let detail = Detail::Triangle(bary);
                                            consider(r, (t.0[r], instance.object, tri, detail), i);
                                        }
                                    }
                                },
                            );
                        }
                    }
                }
            },
        );
        *best = best_cell.get();
        found
    }
}
