//! The single-ray integrator: section 5 for one ray, the definition every packet lane
//! reproduces. Nearest hits and shadow tests go through the hierarchy when the scene
//! has one, else over every object.

use super::prepare::{Geometry, LightSource};
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
            Geometry::Plane(_) | Geometry::Beyond => None,
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
        if self.shapes.is_some() {
            let ray = super::general::GRay::leaving(self.camera.position(), dir, FROM_CAMERA);
            return self.general_radiance(&ray, Path::CAMERA, ctx);
        }
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
        let mut shading = self.shading(ray, t, index, path, ctx);
        // 5. Direct light, diffuse and highlight, where the light is not shadowed.
        for light in &self.lights {
            let Some(towards) = shading.towards(light) else {
                continue;
            };
            ctx.rays += 1;
            let shadow = Ray {
                origin: shading.p,
                dir: towards.dir,
                from: index,
            };
            if self.occluded(&shadow, towards.distance, ctx) {
                continue;
            }
            shading.add(light, &towards);
        }
        // 6. Clip.
        clip(shading.color)
    }

    /// Section 5, steps 1 to 4, where `ray` meets object `index` at distance `t`: the
    /// hit's shading up to its direct light, which is added light by light.
    #[inline(always)]
    pub(super) fn shading(
        &self,
        ray: &Ray,
        t: f64,
        index: u32,
        path: Path,
        ctx: &mut Ctx,
    ) -> Shading {
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
            Geometry::Beyond => {
                unreachable!("section 8's shapes are shaded by the general integrator")
            }
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
        Shading {
            p,
            base,
            normal,
            special,
            reflected,
            color,
        }
    }
}

/// A hit being shaded (section 5): steps 1 to 4 done, the colour so far, and what
/// step 5 needs to add each light. Split from the shadow tests so that the packet
/// integrator can test the shadow rays of hits on different objects together.
#[derive(Clone, Copy, Debug)]
pub(super) struct Shading {
    /// The hit point, where shadow rays start.
    pub p: Vec3,
    base: Vec3,
    normal: Vec3,
    special: f64,
    reflected: Vec3,
    pub color: Vec3,
}

/// The way from a hit point to a light that faces it: the unit direction, the distance
/// and the cosine with the normal.
#[derive(Clone, Copy, Debug)]
pub(super) struct Towards {
    pub dir: Vec3,
    pub distance: f64,
    cos: f64,
}

impl Shading {
    /// The way to `light`, unless the surface faces away from it (a NaN cosine is
    /// traced on).
    #[inline(always)]
    pub fn towards(&self, light: &LightSource) -> Option<Towards> {
        let to_light = light.position - self.p;
        let distance = to_light.length();
        let dir = to_light / distance;
        let cos = self.normal.dot(dir);
        if cos <= 0.0 {
            return None;
        }
        Some(Towards { dir, distance, cos })
    }

    /// Adds the diffuse light and the highlight of `light`, which is not shadowed.
    #[inline(always)]
    pub fn add(&mut self, light: &LightSource, towards: &Towards) {
        self.color += self.base.hadamard(light.color) * towards.cos;
        if self.special > 0.0 {
            let r_dot_l = self.reflected.dot(towards.dir);
            if r_dot_l > 0.0 {
                self.color += light.color * (self.special * pow10(r_dot_l));
            }
        }
    }
}
