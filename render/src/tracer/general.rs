//! The general integrator: section 5 for one ray in a scene with section 8's shapes.
//!
//! It asks the spheres and planes as the single-ray integrator does, and the shapes of
//! [`Shapes`]; equal distances go to the object listed first, then to the triangle
//! listed first. A hit on a sphere or a plane is shaded exactly as there. A hit on a
//! triangle or a box face is shaded with its geometric normal Ng and its shading
//! normal Ns (section 8): Ns gives the cosine and the mirror direction, Ng decides the
//! side, and a light below the geometric surface does not light the point. Rays leave a
//! triangle or a face from an origin moved off the surface by more than the hit point's
//! rounding error ([`crate::shapes::SurfacePoint::origin`]), and never test the very
//! triangle they leave.

use super::prepare::Geometry;
use super::ray::{Path, Ray, FROM_CAMERA};
use super::shading::{checker, clip, pow10};
use super::{Ctx, Tracer, SHADOW_REACH};
use crate::scene::Material;
use crate::shapes::packet::Rays4;
use crate::shapes::{ShapeHit, Shapes, NO_PRIM};
use crate::simd::isa_dispatch;
use crate::vec3::{Vec3, LANES, M4, V4};

/// A ray leaving object `from` (and, on a mesh, its triangle `prim`).
#[derive(Clone, Copy, Debug)]
pub(crate) struct GRay {
    pub origin: Vec3,
    pub dir: Vec3,
    pub from: u32,
    pub prim: u32,
}

impl GRay {
    /// A ray leaving object `from` ([`FROM_CAMERA`] for none) at no particular triangle.
    pub fn leaving(origin: Vec3, dir: Vec3, from: u32) -> GRay {
        GRay {
            origin,
            dir,
            from,
            prim: NO_PRIM,
        }
    }

    fn basic(&self) -> Ray {
        Ray {
            origin: self.origin,
            dir: self.dir,
            from: self.from,
        }
    }
}

/// The nearest hit: a sphere or a plane, or one of section 8's shapes.
#[derive(Clone, Copy, Debug)]
pub(crate) enum GHit {
    Basic(f64, u32),
    Shape(ShapeHit),
}

impl GHit {
    pub fn t(&self) -> f64 {
        match self {
            GHit::Basic(t, _) => *t,
            GHit::Shape(h) => h.t,
        }
    }

    pub fn object(&self) -> u32 {
        match self {
            GHit::Basic(_, o) => *o,
            GHit::Shape(h) => h.object,
        }
    }
}

impl Tracer {
    fn shapes(&self) -> &Shapes {
        self.shapes
            .as_deref()
            .expect("the general integrator runs only with section 8's shapes")
    }

    pub(super) fn general_nearest(&self, ray: &GRay, ctx: &mut Ctx) -> Option<GHit> {
        let basic = self.nearest(&ray.basic(), ctx);
        let (t, object) = basic.unwrap_or((f64::INFINITY, FROM_CAMERA));
        match self
            .shapes()
            .nearest(ray.origin, ray.dir, ray.from, ray.prim, (t, object, 0))
        {
            Some(hit) => Some(GHit::Shape(hit)),
            None => basic.map(|(t, object)| GHit::Basic(t, object)),
        }
    }

    pub(super) fn general_occluded(&self, ray: &GRay, max_t: f64, ctx: &mut Ctx) -> bool {
        self.occluded(&ray.basic(), max_t, ctx)
            || self.shapes().occluded(
                ray.origin,
                ray.dir,
                ray.from,
                ray.prim,
                max_t * SHADOW_REACH,
            )
    }

    /// Section 5: the clipped colour seen along `ray` on `path`.
    pub(super) fn general_radiance(&self, ray: &GRay, path: Path, ctx: &mut Ctx) -> Vec3 {
        ctx.rays += 1;
        match self.general_nearest(ray, ctx) {
            Some(hit) => self.general_shade(ray, hit, path, ctx),
            None => Vec3::ZERO,
        }
    }

    isa_dispatch! {
        /// The clipped colours of the camera rays along the first `count` lanes of
        /// `dir`: those [`Tracer::general_radiance`] gives each, with the shapes' nearest
        /// hits searched four rays at a time, compiled for the tracer's instruction set.
        pub(super) fn general_packet / general_packet_avx2(&self, dir: V4, count: usize, ctx: &mut Ctx) -> V4 {
            self.general_packet_lanes(dir, count, ctx)
        }
    }

    #[inline(always)]
    fn general_packet_lanes(&self, dir: V4, count: usize, ctx: &mut Ctx) -> V4 {
        let eye = self.camera.position();
        let mut best = [(f64::INFINITY, FROM_CAMERA, 0); LANES];
        let mut basic = [None; LANES];
        for k in 0..count {
            basic[k] = self.nearest(&Ray::camera(eye, dir.lane(k)), ctx);
            if let Some((t, object)) = basic[k] {
                best[k] = (t, object, 0);
            }
        }
        let rays = Rays4 {
            origin: V4::splat(eye),
            dir,
            active: M4::first(count),
            from: [FROM_CAMERA; LANES],
            prim: [NO_PRIM; LANES],
        };
        let shapes = self.shapes().nearest4(&rays, &mut best);
        let mut colors = V4::splat(Vec3::ZERO);
        for k in 0..count {
            ctx.rays += 1;
            let hit = match shapes[k] {
                Some(hit) => Some(GHit::Shape(hit)),
                None => basic[k].map(|(t, object)| GHit::Basic(t, object)),
            };
            if let Some(hit) = hit {
                let ray = GRay::leaving(eye, dir.lane(k), FROM_CAMERA);
                colors.set_lane(k, self.general_shade(&ray, hit, Path::CAMERA, ctx));
            }
        }
        for k in count..LANES {
            colors.set_lane(k, colors.lane(0));
        }
        colors
    }

    /// Section 5, steps 1 to 6, where `ray` meets `hit`.
    fn general_shade(&self, ray: &GRay, hit: GHit, path: Path, ctx: &mut Ctx) -> Vec3 {
        let dir = ray.dir;
        let object = hit.object();
        let surface = &self.surfaces[object as usize];
        // Where the hit is, its normals, and where rays leaving it start.
        let (p, mut ng, mut ns, point) = match hit {
            GHit::Basic(t, _) => {
                let p = ray.basic().at(t);
                let n = match surface.geometry {
                    Geometry::Sphere(ref s) => s.normal_at(p),
                    Geometry::Plane(ref pl) => pl.normal,
                    Geometry::Beyond => unreachable!("spheres and planes only"),
                };
                (p, n, n, None)
            }
            GHit::Shape(ref h) => {
                let s = self.shapes().surface(h, ray.origin, dir);
                (s.p, s.ng, s.ns, Some((s, h.prim)))
            }
        };
        let leave = |towards: Vec3| -> GRay {
            match point {
                None => GRay::leaving(p, towards, object),
                Some((s, prim)) => GRay {
                    origin: s.origin(towards),
                    dir: towards,
                    from: object,
                    prim,
                },
            }
        };
        // 1. Checkerboard colour, at the hit's world position.
        let base = match surface.material {
            Material::Checker => checker(p),
            _ => surface.color,
        };
        // 2. Two-sided: the geometric normal decides the side, the shading normal
        // follows it.
        if ng.dot(dir) > 0.0 {
            ng = -ng;
            ns = -ns;
        }
        // 3. Ambient.
        let mut color = base * self.ambient;
        // 4. Mirror reflection, about the shading normal, traced as it is.
        let special = match surface.material {
            Material::Reflective(s) => s,
            _ => 0.0,
        };
        let reflected = if special > 0.0 {
            dir - ns * (2.0 * dir.dot(ns))
        } else {
            Vec3::ZERO
        };
        if let Some(mirror) = path.reflected(special, self.settings.max_depth) {
            let bounce = leave(reflected);
            color += self.general_radiance(&bounce, mirror, ctx) * special;
        }
        // 5. Direct light, from the side the geometric normal faces.
        for light in &self.lights {
            let start = leave(ng);
            let to_light = light.position - start.origin;
            let distance = to_light.length();
            let l = to_light / distance;
            let cos = ns.dot(l);
            if cos <= 0.0 || ng.dot(l) <= 0.0 {
                continue;
            }
            ctx.rays += 1;
            let shadow = GRay { dir: l, ..start };
            if self.general_occluded(&shadow, distance, ctx) {
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
