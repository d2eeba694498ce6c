//! The Whitted-style tracer of the scene format (sections 4 and 5): nearest hit,
//! two-sided normals, ambient, mirror reflection, shadows, highlight and clip.
//!
//! A [`Tracer`] is a scene compiled for tracing ([`prepare`]). Rays ([`ray`]) are traced
//! one at a time by the single-ray integrator ([`single`]), the definition of a
//! pixel's colour, or four at a time by the packet integrator ([`packet`]), which
//! reproduces it lane by lane, bit for bit; camera rays come from [`camera_rays`], and
//! the arithmetic of shading that is not geometry from [`shading`]. The lane code runs
//! compiled for the best instruction set the processor has ([`crate::simd`]).

mod camera_rays;
mod general;
mod packet;
mod prepare;
mod ray;
mod shading;
mod single;

use self::prepare::{EyePlane, EyeSphere, LightSource, SampleGroup, SphereCone, Surface};
use self::ray::{Path, Ray, FROM_CAMERA};
use crate::bvh::{Bvh, Stack};
use crate::camera::Camera;
use crate::geometry::{PlaneGeom, SphereGeom};
use crate::scene::{Material, Scene};
use crate::settings::RenderSettings;
use crate::simd::Isa;
use crate::vec3::{Divisor, Vec3, F4, LANES, M4, V4};

pub(crate) use self::camera_rays::GridSink;
pub(crate) use self::shading::to_byte;

/// A shadow ray is blocked only by a hit closer than this fraction of the distance to
/// the light. The margin is relative, hence scale-free, and keeps a light that lies
/// exactly on a surface from being shadowed by that surface through rounding.
const SHADOW_REACH: f64 = 1.0 - 1e-9;

/// The nearest intersection along a ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray direction.
    pub t: f64,
    /// Index of the object in the scene's `objects` list.
    pub object: usize,
}

/// A scene prepared for tracing at given settings: normals normalised, camera basis,
/// per-object constants and, for many spheres, a bounding volume hierarchy computed
/// once, so tracing allocates nothing.
#[derive(Clone, Debug)]
pub struct Tracer {
    surfaces: Vec<Surface>,
    /// Object indices of the spheres and of the planes, each in scene order, so the
    /// hot loops run over one shape at a time.
    spheres: Vec<(u32, SphereGeom)>,
    planes: Vec<(u32, PlaneGeom)>,
    /// The hierarchy over the spheres, when there are enough of them to pay.
    bvh: Option<Bvh>,
    /// Section 8's shapes (triangles, boxes, meshes), if the scene has any: then every
    /// ray goes through the general integrator ([`general`]), which also asks them.
    shapes: Option<std::sync::Arc<crate::shapes::Shapes>>,
    /// Camera-ray constants (only without a hierarchy, which has its own).
    eye_spheres: Vec<EyeSphere>,
    eye_planes: Vec<EyePlane>,
    /// Without a hierarchy, for each light the cone of each sphere (`[light][sphere]`,
    /// flattened, spheres in the order of `spheres`): shadow rays skip a sphere all of
    /// them pass by. Empty when there would be more than [`prepare::SHADOW_CONES_MAX`].
    shadow_cones: Vec<SphereCone>,
    /// The instruction set the lane code runs with.
    isa: Isa,
    lights: Vec<LightSource>,
    ambient: f64,
    camera: Camera,
    settings: RenderSettings,
    /// The grid's sample offsets inside a pixel, in sample order, in groups of four.
    groups: Vec<SampleGroup>,
    /// n², by which a pixel's sum of samples is divided.
    samples_per_pixel: Divisor,
    /// The image-plane coordinates of the groups' samples, x for each column and y for
    /// each row (`[column or row][group]`, flattened), computed once so that a packet's
    /// directions start without two divisions; empty for frames too large for it to be
    /// worth the memory ([`prepare::PLANE_TABLE_MAX`]).
    plane_xs: Vec<F4>,
    plane_ys: Vec<F4>,
}

/// Per-pixel working state: the ray count and, with a hierarchy, its traversal stack.
struct Ctx<'a> {
    rays: u64,
    /// Rays of packets, counted in lanes ([`Ctx::count`]) and added to `rays` at the
    /// end: one vector subtraction per packet instead of a count of its mask's bits.
    lane_rays: M4,
    stack: Option<&'a mut Stack>,
}

impl Tracer {
    /// The cones of the spheres (in the order of `spheres`) from light `light`, or none
    /// when the tracer has none.
    #[inline(always)]
    fn shadow_cones(&self, light: usize) -> &[SphereCone] {
        let n = self.spheres.len();
        self.shadow_cones
            .get(light * n..(light + 1) * n)
            .unwrap_or(&[])
    }
}

impl Ctx<'_> {
    /// Counts one ray for each lane of `lanes`: a set lane is all ones, that is −1, so
    /// subtracting it adds one.
    #[inline(always)]
    fn count(&mut self, lanes: M4) {
        self.lane_rays = M4(std::array::from_fn(|k| {
            self.lane_rays.0[k].wrapping_sub(lanes.0[k])
        }));
    }

    /// All the rays counted.
    fn total(&self) -> u64 {
        self.lane_rays.0.iter().fold(self.rays, |sum, &r| sum + r)
    }
}

impl Tracer {
    /// Prepares `scene` for rendering with `settings` (the scene's own or overridden
    /// ones, already validated).
    pub fn new(scene: &Scene, settings: RenderSettings) -> Self {
        Self::prepare(scene, settings, None)
    }

    /// [`Tracer::new`] with the hierarchy forced on (`true`) or off, whatever the object
    /// count: the images are the same either way, only the speed differs. For tests and
    /// benchmarks.
    #[doc(hidden)]
    pub fn with_bvh(scene: &Scene, settings: RenderSettings, bvh: bool) -> Self {
        Self::prepare(scene, settings, Some(bvh))
    }

    /// Whether rays are traced through a hierarchy (for tests and benchmarks).
    #[doc(hidden)]
    pub fn uses_bvh(&self) -> bool {
        self.bvh.is_some()
    }

    /// The tracer with its lane code, the hierarchy's node tests included, run for
    /// `isa`, which must be [`Isa::Portable`] or [`Isa::best`]: the images are the same
    /// either way, only the speed differs. For tests that both give the same bytes.
    ///
    /// # Panics
    ///
    /// If `isa` is not available on this processor.
    #[doc(hidden)]
    pub fn with_isa(mut self, isa: Isa) -> Self {
        assert!(
            isa == Isa::Portable || isa == Isa::best(),
            "{isa:?} is not available on this processor"
        );
        self.isa = isa;
        if let Some(bvh) = &mut self.bvh {
            bvh.set_isa(isa);
        }
        if let Some(shapes) = &mut self.shapes {
            std::sync::Arc::get_mut(shapes)
                .expect("a tracer's shapes are its own until it is shared")
                .isa = isa;
        }
        self
    }

    /// The instruction set the lane code runs with.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    /// The camera the tracer's camera rays start from.
    pub(crate) fn camera(&self) -> &Camera {
        &self.camera
    }

    /// The spheres with their object indices, in scene order.
    pub(crate) fn spheres(&self) -> &[(u32, SphereGeom)] {
        &self.spheres
    }

    /// The planes (unit normals) with their object indices, in scene order.
    pub(crate) fn planes(&self) -> &[(u32, PlaneGeom)] {
        &self.planes
    }

    /// The material of object `object`.
    pub(crate) fn material(&self, object: usize) -> Material {
        self.surfaces[object].material
    }

    /// Runs `f` with a fresh per-pixel state (and a traversal stack if there is a
    /// hierarchy), then adds the rays it traced to `rays`.
    #[inline(always)]
    fn with_ctx<T>(&self, rays: &mut u64, f: impl FnOnce(&mut Ctx) -> T) -> T {
        let run = |stack: Option<&mut Stack>| {
            let mut ctx = Ctx {
                rays: 0,
                lane_rays: M4::NONE,
                stack,
            };
            let out = f(&mut ctx);
            *rays += ctx.total();
            out
        };
        if self.bvh.is_some() {
            run(Some(&mut Stack::new()))
        } else {
            run(None)
        }
    }

    /// The nearest hit with t > 0 of the ray `origin + t·dir` (|dir| = 1), ignoring the
    /// surface the ray leaves (`from`). Equal distances go to the lower object index.
    pub fn nearest_hit(&self, origin: Vec3, dir: Vec3, from: Option<usize>) -> Option<Hit> {
        let from = from.map_or(FROM_CAMERA, |i| i as u32);
        let ray = Ray { origin, dir, from };
        if self.shapes.is_some() {
            let ray = general::GRay::leaving(origin, dir, from);
            return self
                .with_ctx(&mut 0, |ctx| self.general_nearest(&ray, ctx))
                .map(|hit| Hit {
                    t: hit.t(),
                    object: hit.object() as usize,
                });
        }
        self.with_ctx(&mut 0, |ctx| self.nearest(&ray, ctx))
            .map(|(t, object)| Hit {
                t,
                object: object as usize,
            })
    }

    /// Whether the light `light` (index into the scene's lights) is seen from `point`
    /// on object `from`: no object is hit on the segment between them.
    pub fn light_visible(&self, point: Vec3, from: usize, light: usize) -> bool {
        let to_light = self.lights[light].position - point;
        let distance = to_light.length();
        let dir = to_light / distance;
        let ray = Ray {
            origin: point,
            dir,
            from: from as u32,
        };
        if self.shapes.is_some() {
            let ray = general::GRay::leaving(point, dir, from as u32);
            return !self.with_ctx(&mut 0, |ctx| self.general_occluded(&ray, distance, ctx));
        }
        !self.with_ctx(&mut 0, |ctx| self.occluded(&ray, distance, ctx))
    }

    /// The clipped colour seen along a camera ray.
    pub fn trace(&self, origin: Vec3, dir: Vec3) -> Vec3 {
        if self.shapes.is_some() {
            let ray = general::GRay::leaving(origin, dir, FROM_CAMERA);
            return self.with_ctx(&mut 0, |ctx| self.general_radiance(&ray, Path::CAMERA, ctx));
        }
        let ray = Ray::camera(origin, dir);
        self.with_ctx(&mut 0, |ctx| self.radiance(&ray, Path::CAMERA, ctx))
    }

    /// The clipped colour of the camera sample through the image point (`px`, `py`),
    /// measured in pixels from the top-left corner (pixel column i with offset sx is
    /// `i + sx`). Adds the rays traced to `rays`.
    pub fn sample(&self, px: f64, py: f64, rays: &mut u64) -> Vec3 {
        let dir = self.camera.direction(px, py);
        self.with_ctx(rays, |ctx| self.camera_sample(dir, ctx))
    }

    /// The clipped colours of the camera samples through the image points `points`
    /// (as in [`Tracer::sample`]), written to `colors`: bit for bit what one call of
    /// [`Tracer::sample`] per point gives, but traced four at a time, which is faster
    /// where neighbouring samples meet the same object. Adds the rays traced to `rays`.
    ///
    /// # Panics
    ///
    /// If `colors` is not as long as `points`.
    pub fn samples(&self, points: &[(f64, f64)], colors: &mut [Vec3], rays: &mut u64) {
        assert_eq!(points.len(), colors.len(), "one colour per point");
        self.with_ctx(rays, |ctx| {
            for (points, colors) in points.chunks(LANES).zip(colors.chunks_mut(LANES)) {
                let px = F4(std::array::from_fn(|k| points[k.min(points.len() - 1)].0));
                let py = F4(std::array::from_fn(|k| points[k.min(points.len() - 1)].1));
                let out = self.trace_group(px, py, points.len(), ctx);
                for (k, color) in colors.iter_mut().enumerate() {
                    *color = out.lane(k);
                }
            }
        });
    }

    /// The 8-bit colour of pixel (`i`, `j`) (column, row from the top left): the mean of
    /// its n × n clipped samples, summed in sample order. Adds the rays traced to `rays`.
    pub fn pixel(&self, i: u32, j: u32, rays: &mut u64) -> [u8; 3] {
        /// Keeps the pixel's sum, ignores its samples.
        struct Sum(Vec3);
        impl GridSink for Sum {
            fn samples(&mut self, _: &V4, _: usize) {}
            fn pixel(&mut self, sum: Vec3) {
                self.0 = sum;
            }
        }
        let mut sum = Sum(Vec3::ZERO);
        self.grid_span(j, i..i + 1, rays, &mut sum);
        let mean = self.grid_mean(sum.0);
        [to_byte(mean.x), to_byte(mean.y), to_byte(mean.z)]
    }

    /// The 8-bit colours of the pixels `columns` of row `j`, appended to `rgb`: those of
    /// [`Tracer::pixel`], traced a span at a time like a frame's tiles but without the
    /// sampler's statistics. For benchmarks: the tracer's share of a frame.
    #[doc(hidden)]
    pub fn pixel_span(
        &self,
        j: u32,
        columns: std::ops::Range<u32>,
        rays: &mut u64,
        rgb: &mut Vec<u8>,
    ) {
        /// Converts each pixel's mean to bytes, ignores its samples.
        struct Bytes<'a> {
            tracer: &'a Tracer,
            rgb: &'a mut Vec<u8>,
        }
        impl GridSink for Bytes<'_> {
            #[inline(always)]
            fn samples(&mut self, _: &V4, _: usize) {}
            #[inline(always)]
            fn pixel(&mut self, sum: Vec3) {
                let mean = self.tracer.grid_mean(sum);
                let bytes = [to_byte(mean.x), to_byte(mean.y), to_byte(mean.z)];
                self.rgb.extend_from_slice(&bytes);
            }
        }
        self.grid_span(j, columns, rays, &mut Bytes { tracer: self, rgb });
    }

    /// A grid pixel's mean from the sum of its samples: sum / n², by a multiplication
    /// when n² is a power of two (same bits, see [`Divisor`]).
    #[inline(always)]
    pub(crate) fn grid_mean(&self, sum: Vec3) -> Vec3 {
        self.samples_per_pixel.divide3(sum)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{CameraSpec, Light, Object, Shape};
    use crate::test_rng::Mix;

    fn random_scene(rng: &mut Mix) -> Scene {
        let material = |rng: &mut Mix| match rng.next() % 4 {
            0 => Material::Checker,
            1 => Material::Reflective(0.05 + 0.95 * rng.unit()),
            _ => Material::Matte,
        };
        let mut objects = Vec::new();
        for _ in 0..rng.next() % 20 {
            let shape = Shape::Sphere {
                center: rng.vec(2.0),
                radius: 0.1 + rng.unit(),
            };
            objects.push(Object {
                shape,
                color: rng.vec(1.0),
                material: material(rng),
            });
        }
        for _ in 0..rng.next() % 3 {
            let shape = Shape::Plane {
                normal: rng.vec(1.0),
                distance: 2.0 * rng.unit() - 1.0,
            };
            objects.push(Object {
                shape,
                color: rng.vec(1.0),
                material: material(rng),
            });
        }
        let lights = (0..rng.next() % 4)
            .map(|_| Light {
                position: rng.vec(6.0),
                color: Vec3::new(rng.unit(), rng.unit(), rng.unit()),
            })
            .collect();
        Scene {
            lights,
            objects,
            camera: CameraSpec {
                position: rng.vec(2.0) + Vec3::new(0.0, 0.0, -6.0),
                look_at: rng.vec(0.5),
                ..CameraSpec::default()
            },
            settings: RenderSettings {
                width: 24,
                height: 16,
                aa: 2,
                max_depth: (rng.next() % 5) as u32,
                ..RenderSettings::default()
            },
            ambient: 0.2,
        }
    }

    /// Grid pixels traced with the tables of image-plane coordinates have the bytes (and
    /// the rays) of the same pixels traced without them, as in frames too large for the
    /// tables.
    #[test]
    fn plane_tables_change_nothing() {
        let mut rng = Mix(9);
        for case in 0..40 {
            let mut scene = random_scene(&mut rng);
            scene.settings.aa = 1 + (case % 5);
            let with = Tracer::new(&scene, scene.settings);
            assert!(!with.plane_xs.is_empty());
            let mut without = with.clone();
            without.plane_xs.clear();
            without.plane_ys.clear();
            for j in 0..scene.settings.height {
                for i in 0..scene.settings.width {
                    let (mut a, mut b) = (0, 0);
                    assert_eq!(
                        with.pixel(i, j, &mut a),
                        without.pixel(i, j, &mut b),
                        "{case}"
                    );
                    assert_eq!(a, b, "case {case}: rays");
                }
            }
        }
    }

    /// The hierarchy's node tests run with the tracer's instruction set, also when it is
    /// changed after the hierarchy is built, so that the portable tests reach them.
    #[test]
    fn the_hierarchy_follows_the_tracers_instruction_set() {
        let mut rng = Mix(11);
        let scene = loop {
            let scene = random_scene(&mut rng);
            if Tracer::with_bvh(&scene, scene.settings, true).uses_bvh() {
                break scene;
            }
        };
        let tracer = Tracer::with_bvh(&scene, scene.settings, true);
        let isa = |t: &Tracer| t.bvh.as_ref().map(Bvh::isa);
        assert_eq!(isa(&tracer), Some(tracer.isa()));
        for choice in [Isa::Portable, Isa::best(), Isa::Portable] {
            let tracer = tracer.clone().with_isa(choice);
            assert_eq!(isa(&tracer), Some(choice));
        }
    }

    /// Four samples traced as a packet have exactly the colours (and count exactly the
    /// rays) of the same samples traced one by one, whatever the scene.
    #[test]
    fn packets_equal_single_samples() {
        let mut rng = Mix(5);
        for case in 0..300 {
            let scene = random_scene(&mut rng);
            for bvh in [false, true] {
                let tracer = Tracer::with_bvh(&scene, scene.settings, bvh);
                for j in 0..scene.settings.height {
                    for i in 0..scene.settings.width {
                        let points: Vec<(f64, f64)> = (0..1 + rng.next() % 6)
                            .map(|_| (f64::from(i) + rng.unit(), f64::from(j) + rng.unit()))
                            .collect();
                        let mut colors = vec![Vec3::ZERO; points.len()];
                        let (mut packed, mut single) = (0, 0);
                        tracer.samples(&points, &mut colors, &mut packed);
                        for (&(px, py), color) in points.iter().zip(&colors) {
                            let alone = tracer.sample(px, py, &mut single);
                            let bits = |c: Vec3| [c.x, c.y, c.z].map(f64::to_bits);
                            assert_eq!(bits(*color), bits(alone), "case {case} at ({px}, {py})");
                        }
                        assert_eq!(packed, single, "case {case}: rays");
                    }
                }
            }
        }
    }
}
