//! The single-ray integrator: section 5 for one ray, the definition every packet lane
//! reproduces. Nearest hits and shadow tests go through the hierarchy when the scene
//! has one, else over every object.

use super::prepare::Geometry;
use super::ray::{Path, Ray, FROM_CAMERA};
use super::shading::{checker, clip, pow10};
use super::{Ctx, Tracer, SHADOW_REACH};
use crate::bvh::consider;
use crate::geometry::{plane_ahead, SphereGeom};
use crate::scene::Material;
use crate::vec3::Vec3;

impl Tracer {
    /// The nearest hit, as (distance, object index). Equal distances go to the lower
    /// object index.
    #[inline(always)]
    pub(super) fn nearest(&self, ray: &Ray, ctx: &mut Ctx) -> Option<(f64, u32)> {
        let mut best = (f64::INFINITY, FROM_CAMERA);
        for &(index, ref plane) in &self.planes {
            if index == ray.from {
                continue;
            }
            if let Some(t) = plane.hit(ray.origin, ray.dir) {
                consider(&mut best, t, index);
            }
        }
        self.nearest_sphere(ray, &mut best, ctx);
        (best.1 != FROM_CAMERA).then_some(best)
    }

    /// Updates `best` with the spheres' hits: through the hierarchy if there is one
    /// (and the ray is within its range), else by testing every sphere.
    #[inline(always)]
    fn nearest_sphere(&self, ray: &Ray, best: &mut (f64, u32), ctx: &mut Ctx) {
        let Ray { origin, dir, from } = *ray;
        if let (Some(bvh), Some(stack)) = (&self.bvh, ctx.stack.as_deref_mut()) {
            self.nearest_leaving(ray, best);
            if bvh.nearest(origin, dir, from, best, stack).is_ok() {
                return;
            }
        }
        self.nearest_brute(ray, best);
    }

    /// Updates `best` with the far wall of the sphere the ray leaves, if it leaves
    /// one: the hierarchy leaves that sphere to its caller.
    #[inline(always)]
    pub(super) fn nearest_leaving(&self, ray: &Ray, best: &mut (f64, u32)) {
        if let Some(s) = self.sphere(ray.from) {
            if let Some(t) = s.hit(ray.origin, ray.dir, true) {
                consider(best, t, ray.from);
            }
        }
    }

    /// Updates `best` with the hits of every sphere.
    #[inline(always)]
    pub(super) fn nearest_brute(&self, ray: &Ray, best: &mut (f64, u32)) {
        let Ray { origin, dir, from } = *ray;
        for &(index, ref sphere) in &self.spheres {
            if let Some(t) = sphere.hit(origin, dir, index == from) {
                consider(best, t, index);
            }
        }
    }

    /// The geometry of object `index` if it is a sphere.
    #[inline(always)]
    fn sphere(&self, index: u32) -> Option<&SphereGeom> {
        match self.surfaces.get(index as usize)?.geometry {
            Geometry::Sphere(ref s) => Some(s),
            Geometry::Plane(_) => None,
        }
    }

    /// The nearest hit of a camera ray, from the per-object camera constants.
    #[inline(always)]
    fn nearest_from_eye(&self, dir: Vec3) -> Option<(f64, u32)> {
        let mut best = (f64::INFINITY, FROM_CAMERA);
        for s in &self.eye_spheres {
            if let Some(t) = SphereGeom::hit_offset(s.f, s.c, s.radius2, dir) {
                consider(&mut best, t, s.index);
            }
        }
        for plane in &self.eye_planes {
            // PlaneGeom::hit with its numerator precomputed.
            let denom = plane.normal.dot(dir);
            if denom == 0.0 {
                continue;
            }
            let t = plane.num / denom;
            if t > 0.0 && t.is_finite() {
                consider(&mut best, t, plane.index);
            }
        }
        (best.1 != FROM_CAMERA).then_some(best)
    }

    /// Whether any object is hit at a distance in (0, reach·`max_t`): shadow rays stop
    /// at the first occluder found.
    #[inline(always)]
    pub(super) fn occluded(&self, ray: &Ray, max_t: f64, ctx: &mut Ctx) -> bool {
        let limit = max_t * SHADOW_REACH;
        if let (Some(bvh), Some(stack)) = (&self.bvh, ctx.stack.as_deref_mut()) {
            if self.occluded_before_bvh(ray, limit) {
                return true;
            }
            let Ray { origin, dir, from } = *ray;
            if let Ok(occluder) = bvh.occluder(origin, dir, from, limit, stack) {
                return occluder.is_some();
            }
            return self.occluded_brute(ray, limit);
        }
        self.occluded_planes(ray, limit) || self.occluded_brute(ray, limit)
    }

    /// Whether a plane, or the sphere the ray leaves, is hit at a distance in (0,
    /// `limit`): the tests made before the hierarchy's, which leaves that sphere out.
    #[inline(always)]
    pub(super) fn occluded_before_bvh(&self, ray: &Ray, limit: f64) -> bool {
        self.occluded_planes(ray, limit)
            || self
                .sphere(ray.from)
                .is_some_and(|s| s.hit(ray.origin, ray.dir, true).is_some_and(|t| t < limit))
    }

    /// Whether a plane is hit at a distance in (0, `limit`).
    #[inline(always)]
    fn occluded_planes(&self, ray: &Ray, limit: f64) -> bool {
        let Ray { origin, dir, from } = *ray;
        for &(index, ref plane) in &self.planes {
            if index == from {
                continue;
            }
            let num = plane.distance - plane.normal.dot(origin);
            let denom = plane.normal.dot(dir);
            if plane_ahead(num, denom) {
                let t = num / denom;
                if t > 0.0 && t.is_finite() && t < limit {
                    return true;
                }
            }
        }
        false
    }

    /// Whether a sphere is hit at a distance in (0, `limit`), by testing every one.
    #[inline(always)]
    pub(super) fn occluded_brute(&self, ray: &Ray, limit: f64) -> bool {
        let Ray { origin, dir, from } = *ray;
        for &(index, ref sphere) in &self.spheres {
            if let Some(t) = sphere.hit(origin, dir, index == from) {
                if t < limit {
                    return true;
                }
            }
        }
        false
    }

    /// Section 5: the clipped colour seen along `ray` on `path`.
    pub(super) fn radiance(&self, ray: &Ray, path: Path, ctx: &mut Ctx) -> Vec3 {
        ctx.rays += 1;
        let Some((t, index)) = self.nearest(ray, ctx) else {
            return Vec3::ZERO;
        };
        self.shade(ray, t, index, path, ctx)
    }

    /// One camera ray's clipped colour.
    #[inline(always)]
    pub(super) fn camera_sample(&self, dir: Vec3, ctx: &mut Ctx) -> Vec3 {
        ctx.rays += 1;
        let ray = Ray::camera(self.camera.position(), dir);
        let hit = if self.bvh.is_some() {
            self.nearest(&ray, ctx)
        } else {
            self.nearest_from_eye(dir)
        };
        match hit {
            Some((t, index)) => self.shade(&ray, t, index, Path::CAMERA, ctx),
            None => Vec3::ZERO,
        }
    }

    /// Section 5, steps 1 to 6, where `ray` meets object `index` at distance `t`.
    #[inline(always)]
    pub(super) fn shade(&self, ray: &Ray, t: f64, index: u32, path: Path, ctx: &mut Ctx) -> Vec3 {
        let surface = &self.surfaces[index as usize];
        let dir = ray.dir;
        let p = ray.at(t);

        // 1. Checkerboard colour.
        let base = match surface.material {
            Material::Checker => checker(p),
            _ => surface.color,
        };
        // 2. Two-sided normal, facing the incoming ray.
        let mut normal = match surface.geometry {
            Geometry::Sphere(ref s) => s.normal_at(p),
            Geometry::Plane(ref pl) => pl.normal,
        };
        if normal.dot(dir) > 0.0 {
            normal = -normal;
        }
        // 3. Ambient.
        let mut color = base * self.ambient;
        // 4. Mirror reflection.
        let special = match surface.material {
            Material::Reflective(s) => s,
            _ => 0.0,
        };
        let reflected = if special > 0.0 {
            dir - normal * (2.0 * dir.dot(normal))
        } else {
            Vec3::ZERO
        };
        if let Some(mirror) = path.reflected(special, self.settings.max_depth) {
            let bounce = Ray {
                origin: p,
                dir: reflected,
                from: index,
            };
            color += self.radiance(&bounce, mirror, ctx) * special;
        }
        // 5. Direct light, diffuse and highlight, where the light is not shadowed.
        for light in &self.lights {
            let to_light = light.position - p;
            let distance = to_light.length();
            let l = to_light / distance;
            let cos = normal.dot(l);
            if cos <= 0.0 {
                continue;
            }
            ctx.rays += 1;
            let shadow = Ray {
                origin: p,
                dir: l,
                from: index,
            };
            if self.occluded(&shadow, distance, ctx) {
                continue;
            }
            color += base.hadamard(light.color) * cos;
            if special > 0.0 {
                let r_dot_l = reflected.dot(l);
                if r_dot_l > 0.0 {
                    color += light.color * (special * pow10(r_dot_l));
                }
            }
        }
        // 6. Clip.
        clip(color)
    }
}
