//! The packet integrator: section 5 for four rays at once, lane by lane the operations
//! of the single-ray integrator ([`super::single`]) in the same order, so each lane's
//! colour has the bits that ray has when traced alone. Lanes that meet the same object
//! are shaded together; at a silhouette, where they part, each lane is shaded alone.

use super::prepare::Geometry;
use super::ray::{Packet, Path, Ray, FROM_CAMERA};
use super::shading::{checker_white_lanes, clip, clip_lanes, pow10};
use super::single::{Shading, Towards};
use super::{Ctx, Tracer, SHADOW_REACH};
use crate::bvh::consider;
use crate::geometry::{plane_hits, sphere_hits, SphereGeom};
use crate::scene::Material;
use crate::simd::isa_dispatch;
use crate::vec3::{Vec3, F4, LANES, M4, V4};

impl Tracer {
    isa_dispatch! {
        /// The clipped colours of the rays of `packet` on `path`, black in inactive
        /// lanes, compiled for the tracer's instruction set.
        pub(super) fn packet / packet_avx2(&self, packet: &Packet, path: Path, ctx: &mut Ctx) -> V4 {
            self.packet_lanes(packet, path, ctx)
        }
    }

    #[inline(always)]
    fn packet_lanes(&self, packet: &Packet, path: Path, ctx: &mut Ctx) -> V4 {
        ctx.count(packet.active);
        let (t, index) = self.nearest_lanes(packet, ctx);
        let hit = packet
            .active
            .and(index.lt(F4::splat(f64::from(FROM_CAMERA))));
        let mut colors = V4::splat(Vec3::ZERO);
        let Some(first) = (0..LANES).find(|&k| hit.get(k)) else {
            return colors;
        };
        let object = index.0[first];
        if !hit
            .and_not(index.test(F4::splat(object), |a, b| a == b))
            .any()
        {
            return self.shade_lanes(&packet.with_active(hit), t, object as u32, path, ctx);
        }
        if self.bvh.is_some() {
            return self.shade_apart(&packet.with_active(hit), t, index, path, ctx);
        }
        for k in 0..LANES {
            if hit.get(k) {
                let color = self.shade(&packet.lane(k), t.0[k], index.0[k] as u32, path, ctx);
                colors.set_lane(k, color);
            }
        }
        colors
    }

    /// The nearest hits of the packet's active lanes: the distances and the object
    /// indices, the latter as f64 (exact for every u32) so that the tie rule runs in
    /// the same SIMD lanes as the distances; [`FROM_CAMERA`] where nothing is hit.
    #[inline(always)]
    fn nearest_lanes(&self, packet: &Packet, ctx: &mut Ctx) -> (F4, F4) {
        let mut t = F4::splat(f64::INFINITY);
        let mut index = F4::splat(f64::from(FROM_CAMERA));
        let (origin, dir, from) = (packet.origin, packet.dir, packet.from);
        if let (Some(bvh), Some(stack)) = (&self.bvh, ctx.stack.as_deref_mut()) {
            // Lane by lane what `Tracer::nearest` tests besides the hierarchy, then the
            // hierarchy for all four rays together, and the brute-force loop for any
            // lane it cannot answer.
            let rays: [Ray; LANES] = std::array::from_fn(|k| packet.lane(k));
            let mut best = [(f64::INFINITY, FROM_CAMERA); LANES];
            let mut lanes = 0u32;
            for k in 0..LANES {
                if packet.active.get(k) {
                    lanes |= 1 << k;
                    for &(i, ref plane) in &self.planes {
                        if i == from {
                            continue;
                        }
                        if let Some(tk) = plane.hit(rays[k].origin, rays[k].dir) {
                            consider(&mut best[k], tk, i);
                        }
                    }
                    self.nearest_leaving(&rays[k], &mut best[k]);
                }
            }
            if lanes != 0 {
                let origins = rays.map(|r| r.origin);
                let dirs = rays.map(|r| r.dir);
                let rest = bvh.nearests(&origins, &dirs, from, &mut best, lanes, stack);
                for k in 0..LANES {
                    if rest & (1 << k) != 0 {
                        self.nearest_brute(&rays[k], &mut best[k]);
                    }
                    if lanes & (1 << k) != 0 && best[k].1 != FROM_CAMERA {
                        t.0[k] = best[k].0;
                        index.0[k] = f64::from(best[k].1);
                    }
                }
            }
        } else if from == FROM_CAMERA {
            // Camera rays: the per-object constants of the eye.
            for s in &self.eye_spheres {
                if s.cone.misses(dir).all() {
                    continue;
                }
                let (f, c, radius2) = (V4::splat(s.f), F4::splat(s.c), F4::splat(s.radius2));
                let hits = sphere_hits(f, c, radius2, dir, M4::NONE);
                consider_lanes(&mut t, &mut index, hits, s.index);
            }
            for plane in &self.eye_planes {
                let hits = plane_hits(F4::splat(plane.num), V4::splat(plane.normal).dot(dir));
                consider_lanes(&mut t, &mut index, hits, plane.index);
            }
        } else {
            for &(i, ref s) in &self.spheres {
                let hits = sphere_lane_hits(s, origin, dir, i == from);
                consider_lanes(&mut t, &mut index, hits, i);
            }
            for &(i, ref plane) in &self.planes {
                if i == from {
                    continue;
                }
                let n = V4::splat(plane.normal);
                let num = F4::splat(plane.distance) - n.dot(origin);
                consider_lanes(&mut t, &mut index, plane_hits(num, n.dot(dir)), i);
            }
        }
        (t, index)
    }

    /// [`Tracer::shade`] for the packet's active lanes, which all meet object `index`
    /// at distances `t` (other lanes are black).
    #[inline(always)]
    fn shade_lanes(&self, packet: &Packet, t: F4, index: u32, path: Path, ctx: &mut Ctx) -> V4 {
        let zero = F4::splat(0.0);
        let hit = packet.active;
        let dir = packet.dir;
        let surface = &self.surfaces[index as usize];
        let p = packet.origin + dir.scale(t);

        // 1. Checkerboard colour.
        let base = match surface.material {
            Material::Checker => checker_white_lanes(p)
                .select3(V4::splat(Vec3::new(1.0, 1.0, 1.0)), V4::splat(Vec3::ZERO)),
            _ => V4::splat(surface.color),
        };
        // 2. Two-sided normal, facing the incoming ray.
        let normal = match surface.geometry {
            Geometry::Sphere(ref s) => {
                let offset = p - V4::splat(s.center);
                match surface.inverse_radius {
                    Some(inverse) => offset.scale(F4::splat(inverse)),
                    None => offset.div(F4::splat(s.radius)),
                }
            }
            Geometry::Plane(ref pl) => V4::splat(pl.normal),
            Geometry::Beyond => unreachable!("section 8's shapes are traced one ray at a time"),
        };
        let normal = normal.dot(dir).gt(zero).select3(-normal, normal);
        // 3. Ambient.
        let mut acc = base.scale(F4::splat(self.ambient));
        // 4. Mirror reflection.
        let special = match surface.material {
            Material::Reflective(s) => s,
            _ => 0.0,
        };
        let reflected = if special > 0.0 {
            dir - normal.scale(dir.dot(normal).map(|x| 2.0 * x))
        } else {
            V4::splat(Vec3::ZERO)
        };
        if let Some(mirror) = path.reflected(special, self.settings.max_depth) {
            let rays = Packet {
                origin: p,
                dir: reflected,
                from: index,
                active: hit,
            };
            let c = self.packet(&rays, mirror, ctx);
            acc = hit.select3(acc + c.scale(F4::splat(special)), acc);
        }
        // 5. Direct light, diffuse and highlight, where the light is not shadowed.
        for (light_index, light) in self.lights.iter().enumerate() {
            let to_light = V4::splat(light.position) - p;
            let distance = to_light.dot(to_light).sqrt();
            let l = to_light.div(distance);
            let cos = normal.dot(l);
            // Not `cos > 0`: a NaN cosine is traced on, as in the single-ray code.
            let lit = hit.and_not(cos.le(zero));
            if !lit.any() {
                continue;
            }
            ctx.count(lit);
            let shadow = Packet {
                origin: p,
                dir: l,
                from: index,
                active: lit,
            };
            let unshadowed = lit.and_not(self.occluded_lanes(&shadow, distance, light_index, ctx));
            let light_color = V4::splat(light.color);
            acc = unshadowed.select3(acc + base.hadamard(light_color).scale(cos), acc);
            if special > 0.0 {
                let r_dot_l = reflected.dot(l);
                let highlight = unshadowed.and(r_dot_l.gt(zero));
                let strength = F4::splat(special) * r_dot_l.map(pow10);
                acc = highlight.select3(acc + light_color.scale(strength), acc);
            }
        }
        // 6. Clip.
        hit.select3(clip_lanes(acc), V4::splat(Vec3::ZERO))
    }

    /// [`Tracer::shade`] for the packet's active lanes, which meet the objects
    /// `index` (as f64) at distances `t`, not all the same one (other lanes are
    /// black), in a scene with a hierarchy. Each lane is shaded alone up to its
    /// direct light; then the shadow rays of all lanes towards each light, each
    /// leaving its own object, traverse the hierarchy together.
    #[inline(always)]
    fn shade_apart(&self, packet: &Packet, t: F4, index: F4, path: Path, ctx: &mut Ctx) -> V4 {
        let hit = packet.active;
        let objects: [u32; LANES] = std::array::from_fn(|k| index.0[k] as u32);
        let mut shadings: [Option<Shading>; LANES] = [None; LANES];
        for k in 0..LANES {
            if hit.get(k) {
                let ray = packet.lane(k);
                shadings[k] = Some(self.shading(&ray, t.0[k], objects[k], path, ctx));
            }
        }
        for light in &self.lights {
            let mut shadows = [Ray::camera(Vec3::ZERO, Vec3::ZERO); LANES];
            let mut distance = [0.0; LANES];
            let mut towards: [Option<Towards>; LANES] = [None; LANES];
            let mut lit = M4::NONE;
            for k in 0..LANES {
                let Some(shading) = &shadings[k] else {
                    continue;
                };
                if let Some(way) = shading.towards(light) {
                    shadows[k] = Ray {
                        origin: shading.p,
                        dir: way.dir,
                        from: objects[k],
                    };
                    distance[k] = way.distance;
                    towards[k] = Some(way);
                    lit.0[k] = u64::MAX;
                }
            }
            if !lit.any() {
                continue;
            }
            ctx.count(lit);
            let blocked = self.occluded_rays(&shadows, &distance, lit, ctx);
            for k in 0..LANES {
                if let (Some(shading), Some(way), false) =
                    (&mut shadings[k], &towards[k], blocked.get(k))
                {
                    shading.add(light, way);
                }
            }
        }
        let mut colors = V4::splat(Vec3::ZERO);
        for (k, shading) in shadings.iter().enumerate() {
            if let Some(shading) = shading {
                colors.set_lane(k, clip(shading.color));
            }
        }
        colors
    }

    /// [`Tracer::occluded`] for the shadow rays of the packet's active lanes, towards
    /// light `light` at `distance`: the lanes that are blocked. Without a hierarchy, a
    /// sphere that every open lane passes by ([`super::prepare::SphereCone`]) is not
    /// tested.
    #[inline(always)]
    fn occluded_lanes(&self, shadow: &Packet, distance: F4, light: usize, ctx: &mut Ctx) -> M4 {
        let (p, l, from, lit) = (shadow.origin, shadow.dir, shadow.from, shadow.active);
        if self.bvh.is_some() {
            let rays: [Ray; LANES] = std::array::from_fn(|k| shadow.lane(k));
            return self.occluded_rays(&rays, &distance.0, lit, ctx);
        }
        let mut blocked = M4::NONE;
        let zero = F4::splat(0.0);
        let limit = distance * SHADOW_REACH;
        for &(index, ref plane) in &self.planes {
            if index == from {
                continue;
            }
            let n = V4::splat(plane.normal);
            let num = F4::splat(plane.distance) - n.dot(p);
            let denom = n.dot(l);
            let ahead = num.gt(zero).and(denom.gt(zero));
            let ahead = lit.and(ahead.or(num.lt(zero).and(denom.lt(zero))));
            if ahead.any() {
                blocked = blocked.or(ahead.and(plane_hits(num, denom).lt(limit)));
            }
        }
        let cones = self.shadow_cones(light);
        for (k, &(index, ref s)) in self.spheres.iter().enumerate() {
            let open = lit.and_not(blocked);
            if !open.any() {
                break;
            }
            if let Some(cone) = cones.get(k) {
                if index != from && !open.and_not(cone.passes_by(l, distance)).any() {
                    continue;
                }
            }
            let t = sphere_lane_hits(s, p, l, index == from);
            blocked = blocked.or(t.lt(limit));
        }
        blocked
    }
}

impl Tracer {
    /// [`Tracer::occluded`] for the shadow rays `rays` of the lanes `lit`, each
    /// leaving its own object, towards lights at `distance`: the lanes that are
    /// blocked. With a hierarchy: lane by lane the tests before the hierarchy in
    /// [`Tracer::occluded`], then the hierarchy for the lanes still open, all four rays
    /// together, and the brute-force loop for any lane it cannot answer; without one,
    /// lane by lane [`Tracer::occluded`].
    #[inline(always)]
    fn occluded_rays(
        &self,
        rays: &[Ray; LANES],
        distance: &[f64; LANES],
        lit: M4,
        ctx: &mut Ctx,
    ) -> M4 {
        let mut blocked = M4::NONE;
        if let (Some(bvh), Some(stack)) = (&self.bvh, ctx.stack.as_deref_mut()) {
            let limit = distance.map(|d| d * SHADOW_REACH);
            let mut open = 0u32;
            for k in 0..LANES {
                if lit.get(k) {
                    if self.occluded_before_bvh(&rays[k], limit[k]) {
                        blocked.0[k] = u64::MAX;
                    } else {
                        open |= 1 << k;
                    }
                }
            }
            if open != 0 {
                let origins = rays.map(|r| r.origin);
                let dirs = rays.map(|r| r.dir);
                let from = rays.map(|r| r.from);
                let (hit, rest) = bvh.occluders(&origins, &dirs, &from, &limit, open, stack);
                for k in 0..LANES {
                    if hit & (1 << k) != 0
                        || (rest & (1 << k) != 0 && self.occluded_brute(&rays[k], limit[k]))
                    {
                        blocked.0[k] = u64::MAX;
                    }
                }
            }
            return blocked;
        }
        for k in 0..LANES {
            if lit.get(k) && self.occluded(&rays[k], distance[k], ctx) {
                blocked.0[k] = u64::MAX;
            }
        }
        blocked
    }
}

/// [`crate::bvh::consider`] lane by lane, for one object's hits in four rays; object
/// indices are held as f64 (exact for every u32) so that the whole rule runs in SIMD
/// lanes.
#[inline(always)]
fn consider_lanes(best_t: &mut F4, best: &mut F4, t: F4, index: u32) {
    let index = F4::splat(f64::from(index));
    let tie = t.test(*best_t, |a, b| a == b).and(index.lt(*best));
    let better = t.lt(*best_t).or(tie);
    *best_t = better.select(t, *best_t);
    *best = better.select(index, *best);
}

/// Lane by lane, [`SphereGeom::hit`] of the rays `origin + t·dir` with sphere `s`, which
/// they leave when `leaving`.
#[inline(always)]
fn sphere_lane_hits(s: &SphereGeom, origin: V4, dir: V4, leaving: bool) -> F4 {
    let f = origin - V4::splat(s.center);
    if leaving {
        leaving_hits(f, dir)
    } else {
        let radius2 = F4::splat(s.radius2);
        sphere_hits(f, f.dot(f) - radius2, radius2, dir, M4::NONE)
    }
}

/// Lane by lane, [`SphereGeom::hit`] for rays leaving the sphere (`f`
/// = origin − centre): the far wall at t = −2 f·d when ahead, NaN otherwise.
#[inline(always)]
fn leaving_hits(f: V4, dir: V4) -> F4 {
    let t = f.dot(dir).map(|b| -2.0 * b);
    t.gt(F4::splat(0.0)).select(t, F4::splat(f64::NAN))
}
