//! The Whitted-style tracer of the scene format (sections 4 and 5): nearest hit,
//! two-sided normals, ambient, mirror reflection, shadows, highlight and clip.

use crate::bvh::{consider, has_avx2, Bvh, Stack};
use crate::camera::Camera;
use crate::geometry::{plane_ahead, plane_hits, sphere_hits, PlaneGeom, SphereGeom};
use crate::scene::{Material, RenderSettings, Scene, Shape};
use crate::vec3::{Divisor, Vec3, F4, LANES, M4, V4};

/// A reflection path whose weight (the product of its `special` factors) is below this
/// contributes less than a quarter of an 8-bit level, so it is not traced (section 5,
/// step 4 allows it).
const MIN_PATH_WEIGHT: f64 = 1.0 / 1024.0;

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

#[derive(Clone, Copy, Debug)]
enum Geometry {
    Sphere(SphereGeom),
    Plane(PlaneGeom),
}

#[derive(Clone, Copy, Debug)]
struct Surface {
    geometry: Geometry,
    color: Vec3,
    material: Material,
    /// For a sphere whose radius is a power of two, 1 / radius (see
    /// [`Divisor`]): the normals of a packet then cost a multiplication
    /// instead of a division, with the same bits.
    inverse_radius: Option<f64>,
}

#[derive(Clone, Copy, Debug)]
struct LightSource {
    position: Vec3,
    color: Vec3,
}

/// Constants of every camera ray for one sphere: camera rays all start at the eye, so
/// f = eye − centre and c = f·f − r² are computed once, by the same operations that
/// [`SphereGeom::hit`] performs per ray, hence with the same bits.
#[derive(Clone, Copy, Debug)]
struct EyeSphere {
    f: Vec3,
    c: f64,
    radius2: f64,
    index: u32,
}

/// A plane as camera rays see it: the numerator distance − n̂·eye of
/// [`PlaneGeom::hit`] is the same for all of them.
#[derive(Clone, Copy, Debug)]
struct EyePlane {
    normal: Vec3,
    num: f64,
    index: u32,
}

/// Spheres from which the hierarchy is built when camera rays are traced one by one
/// (aa = 1): below this, testing every sphere is as fast. Measured with
/// `cargo bench -p render --bench bvh_threshold` (see docs/performance.md).
const BVH_MIN_SPHERES: usize = 12;

/// The same when camera rays are traced four at a time (aa ≥ 2): testing every sphere
/// then runs in SIMD lanes across the four rays while the hierarchy is traversed ray by
/// ray, so it pays only from more spheres. Measured likewise.
const BVH_MIN_SPHERES_PACKETS: usize = 40;

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
    /// Camera-ray constants (only without a hierarchy, which has its own).
    eye_spheres: Vec<EyeSphere>,
    eye_planes: Vec<EyePlane>,
    /// Whether the processor has AVX2, for the packet code.
    avx2: bool,
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
    /// worth the memory ([`PLANE_TABLE_MAX`]).
    plane_xs: Vec<F4>,
    plane_ys: Vec<F4>,
}

/// The most entries of the tables of image-plane coordinates ((width + height) × groups
/// of four samples): 2 MiB.
const PLANE_TABLE_MAX: usize = 1 << 16;

/// What a grid render does with the colours it traces ([`Tracer::grid_span`]).
pub(crate) trait GridSink {
    /// One sample's clipped colour; a pixel's samples come in sample order.
    fn sample(&mut self, color: Vec3);
    /// The end of a pixel, with the sum of its samples' colours in sample order.
    fn pixel(&mut self, sum: Vec3);
}

/// Up to [`LANES`] samples of the grid, traced together: their offsets inside the pixel
/// in lanes (unused lanes repeat the first sample, and their results are dropped).
#[derive(Clone, Copy, Debug)]
struct SampleGroup {
    sx: F4,
    sy: F4,
    count: usize,
}

impl SampleGroup {
    /// The n × n grid of section 3, ((a + ½)/n, (b + ½)/n) row by row, in groups of
    /// four.
    fn grid(n: u32) -> Vec<SampleGroup> {
        let offset = |a: u32| (f64::from(a) + 0.5) / f64::from(n);
        let points: Vec<(f64, f64)> = (0..n)
            .flat_map(|b| (0..n).map(move |a| (offset(a), offset(b))))
            .collect();
        points
            .chunks(LANES)
            .map(|chunk| {
                let lane = |k: usize| chunk[if k < chunk.len() { k } else { 0 }];
                SampleGroup {
                    sx: F4(std::array::from_fn(|k| lane(k).0)),
                    sy: F4(std::array::from_fn(|k| lane(k).1)),
                    count: chunk.len(),
                }
            })
            .collect()
    }
}

/// Marks a ray that leaves no surface (a camera ray); no object has this index.
const FROM_CAMERA: u32 = u32::MAX;

/// Per-pixel working state: the ray count and, with a hierarchy, its traversal stack.
struct Ctx<'a> {
    rays: u64,
    /// Rays of packets, counted in lanes ([`Ctx::count`]) and added to `rays` at the
    /// end: one vector subtraction per packet instead of a count of its mask's bits.
    lane_rays: M4,
    stack: Option<&'a mut Stack>,
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

    fn prepare(scene: &Scene, settings: RenderSettings, force_bvh: Option<bool>) -> Self {
        let surfaces: Vec<Surface> = scene
            .objects
            .iter()
            .map(|o| Surface {
                geometry: match o.shape {
                    Shape::Sphere { center, radius } => {
                        Geometry::Sphere(SphereGeom::new(center, radius))
                    }
                    Shape::Plane { normal, distance } => {
                        Geometry::Plane(PlaneGeom::new(normal, distance))
                    }
                },
                color: o.color,
                material: o.material,
                inverse_radius: match o.shape {
                    Shape::Sphere { radius, .. } => Divisor::new(radius).reciprocal(),
                    Shape::Plane { .. } => None,
                },
            })
            .collect();
        let mut spheres = Vec::new();
        let mut planes = Vec::new();
        for (i, s) in surfaces.iter().enumerate() {
            let index = u32::try_from(i).expect("object count fits in u32");
            match s.geometry {
                Geometry::Sphere(g) => spheres.push((index, g)),
                Geometry::Plane(g) => planes.push((index, g)),
            }
        }
        let camera = Camera::new(&scene.camera, &settings);
        let eye = camera.position();
        let threshold = if settings.aa == 1 {
            BVH_MIN_SPHERES
        } else {
            BVH_MIN_SPHERES_PACKETS
        };
        let bvh = if force_bvh.unwrap_or(spheres.len() >= threshold) {
            Bvh::build(&spheres)
        } else {
            None
        };
        let eye_spheres: Vec<EyeSphere> = if bvh.is_some() {
            Vec::new()
        } else {
            spheres
                .iter()
                .map(|&(index, s)| {
                    let f = eye - s.center;
                    EyeSphere {
                        f,
                        c: f.dot(f) - s.radius2,
                        radius2: s.radius2,
                        index,
                    }
                })
                .collect()
        };
        let groups = SampleGroup::grid(settings.aa);
        let table = |side: u32, coordinate: &dyn Fn(F4) -> F4, offset: fn(&SampleGroup) -> F4| {
            if (settings.width as usize + settings.height as usize) * groups.len() > PLANE_TABLE_MAX
            {
                return Vec::new();
            }
            (0..side)
                .flat_map(|a| groups.iter().map(move |g| (a, g)))
                .map(|(a, g)| coordinate(F4::splat(f64::from(a)) + offset(g)))
                .collect()
        };
        let plane_xs = table(settings.width, &|px| camera.plane_x(px), |g| g.sx);
        let plane_ys = table(settings.height, &|py| camera.plane_y(py), |g| g.sy);
        Tracer {
            eye_planes: planes
                .iter()
                .map(|&(index, p)| EyePlane {
                    normal: p.normal,
                    num: p.distance - p.normal.dot(eye),
                    index,
                })
                .collect(),
            avx2: has_avx2(),
            surfaces,
            spheres,
            planes,
            bvh,
            eye_spheres,
            lights: scene
                .lights
                .iter()
                .map(|l| LightSource {
                    position: l.position,
                    color: l.color,
                })
                .collect(),
            ambient: scene.ambient,
            camera,
            plane_xs,
            plane_ys,
            groups,
            samples_per_pixel: Divisor::new(f64::from(settings.aa) * f64::from(settings.aa)),
            settings,
        }
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
        self.with_ctx(&mut 0, |ctx| self.nearest(origin, dir, from, ctx))
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
        !self.with_ctx(&mut 0, |ctx| {
            self.occluded(point, dir, from as u32, distance, ctx)
        })
    }

    /// The clipped colour seen along a camera ray.
    pub fn trace(&self, origin: Vec3, dir: Vec3) -> Vec3 {
        let mut rays = 0;
        self.radiance(origin, dir, FROM_CAMERA, 0, 1.0, &mut rays)
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
            fn sample(&mut self, _: Vec3) {}
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
            fn sample(&mut self, _: Vec3) {}
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

    /// Traces the n × n grid samples (section 3) of the pixels `columns` of row `j`, left
    /// to right, and hands `sink` each sample's clipped colour in sample order, then each
    /// pixel's sum of them, summed in sample order. A whole span at a time, so that the
    /// constants of the loop are set up once and the sink's own work on each pixel is
    /// compiled with the tracer's SIMD code. Adds the rays traced to `rays`.
    #[inline]
    pub(crate) fn grid_span(
        &self,
        j: u32,
        columns: std::ops::Range<u32>,
        rays: &mut u64,
        sink: &mut impl GridSink,
    ) {
        self.with_ctx(rays, |ctx| {
            #[cfg(target_arch = "x86_64")]
            if self.avx2 {
                // SAFETY: `avx2` is set only where the processor was found to support
                // AVX2.
                return unsafe { self.grid_span_avx2(j, columns, ctx, sink) };
            }
            self.grid_span_in(j, columns, ctx, sink)
        })
    }

    /// [`Tracer::grid_span`] compiled for AVX2, like [`Tracer::packet_avx2`]: the
    /// camera directions of a group of four and the sink's work are SIMD code too.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn grid_span_avx2(
        &self,
        j: u32,
        columns: std::ops::Range<u32>,
        ctx: &mut Ctx,
        sink: &mut impl GridSink,
    ) {
        self.grid_span_in(j, columns, ctx, sink)
    }

    /// [`Tracer::grid_span`] within a span's state: each pixel's samples row by row,
    /// traced four at a time (the last group may be smaller), summed in sample order.
    #[inline(always)]
    fn grid_span_in(
        &self,
        j: u32,
        columns: std::ops::Range<u32>,
        ctx: &mut Ctx,
        sink: &mut impl GridSink,
    ) {
        if columns.is_empty() {
            return;
        }
        // The directions of the next group are computed before the current group is
        // traced: their square root and divisions are a long chain, which then
        // overlaps with the tracing instead of delaying the start of each packet.
        let (mut i, mut g) = (columns.start, 0);
        let mut dir = self.directions_of(i, j, g);
        let mut sum = Vec3::ZERO;
        loop {
            let count = self.groups[g].count;
            let (next_i, next_g) = if g + 1 < self.groups.len() {
                (i, g + 1)
            } else {
                (i + 1, 0)
            };
            let more = next_i < columns.end;
            // No closure here: it could be compiled apart, without the AVX2 features.
            let next = if more {
                self.directions_of(next_i, j, next_g)
            } else {
                dir
            };
            let colors = self.trace_directions(dir, count, ctx);
            for k in 0..count {
                let color = colors.lane(k);
                sum += color;
                sink.sample(color);
            }
            if next_g == 0 {
                sink.pixel(sum);
                sum = Vec3::ZERO;
            }
            if !more {
                return;
            }
            (i, g, dir) = (next_i, next_g, next);
        }
    }

    /// The camera directions of group `g` of pixel (`i`, `j`).
    #[inline(always)]
    fn directions_of(&self, i: u32, j: u32, g: usize) -> V4 {
        if self.plane_xs.is_empty() {
            self.group_directions(i, F4::splat(f64::from(j)), &self.groups[g])
        } else {
            self.table_directions(i, j, g)
        }
    }

    /// The camera directions of a group of samples of the pixel in column `i` (row
    /// `y0`, in every lane): whole vectors, since filling the lanes one by one through
    /// memory would stall the vector loads that follow.
    #[inline(always)]
    fn group_directions(&self, i: u32, y0: F4, group: &SampleGroup) -> V4 {
        let x0 = F4::splat(f64::from(i));
        self.camera.directions(x0 + group.sx, y0 + group.sy)
    }

    /// [`Tracer::group_directions`] of group `g` of pixel (`i`, `j`) from the tables of
    /// image-plane coordinates: the same operations, done ahead.
    #[inline(always)]
    fn table_directions(&self, i: u32, j: u32, g: usize) -> V4 {
        let n = self.groups.len();
        let x = self.plane_xs[i as usize * n + g];
        let y = self.plane_ys[j as usize * n + g];
        self.camera.directions_at(x, y)
    }

    /// Traces the camera samples of the first `count` lanes (1 to [`LANES`]) of `dir`,
    /// whose other lanes repeat the first: alone, or as one packet.
    #[inline(always)]
    fn trace_directions(&self, dir: V4, count: usize, ctx: &mut Ctx) -> V4 {
        if count == 1 {
            return V4::splat(self.camera_sample(dir.lane(0), ctx));
        }
        let origin = V4::splat(self.camera.position());
        self.packet(origin, dir, FROM_CAMERA, 0, 1.0, M4::first(count), ctx)
    }

    /// Traces the camera samples through the image points of the first `count` lanes
    /// (1 to [`LANES`]) of (`px`, `py`), whose other lanes repeat the first: alone, or
    /// as one packet.
    #[inline(always)]
    fn trace_group(&self, px: F4, py: F4, count: usize, ctx: &mut Ctx) -> V4 {
        self.trace_directions(self.camera.directions(px, py), count, ctx)
    }

    /// The nearest hit, as (distance, object index).
    #[inline(always)]
    fn nearest(&self, origin: Vec3, dir: Vec3, from: u32, ctx: &mut Ctx) -> Option<(f64, u32)> {
        let mut best = (f64::INFINITY, FROM_CAMERA);
        for &(index, ref plane) in &self.planes {
            if index == from {
                continue;
            }
            if let Some(t) = plane.hit(origin, dir) {
                consider(&mut best, t, index);
            }
        }
        self.nearest_sphere(origin, dir, from, &mut best, ctx);
        (best.1 != FROM_CAMERA).then_some(best)
    }

    /// Updates `best` with the spheres' hits: through the hierarchy if there is one
    /// (and the ray is within its range), else by testing every sphere.
    #[inline(always)]
    fn nearest_sphere(
        &self,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        best: &mut (f64, u32),
        ctx: &mut Ctx,
    ) {
        if let (Some(bvh), Some(stack)) = (&self.bvh, ctx.stack.as_deref_mut()) {
            if let Some(s) = self.sphere(from) {
                if let Some(t) = s.hit(origin, dir, true) {
                    consider(best, t, from);
                }
            }
            if bvh.nearest(origin, dir, from, best, stack).is_ok() {
                return;
            }
        }
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

    /// The nearest hit of a camera ray, from the per-sphere camera constants.
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
    fn occluded(&self, origin: Vec3, dir: Vec3, from: u32, max_t: f64, ctx: &mut Ctx) -> bool {
        let limit = max_t * SHADOW_REACH;
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
        if let (Some(bvh), Some(stack)) = (&self.bvh, ctx.stack.as_deref_mut()) {
            if let Some(s) = self.sphere(from) {
                if s.hit(origin, dir, true).is_some_and(|t| t < limit) {
                    return true;
                }
            }
            if let Ok(occluder) = bvh.occluder(origin, dir, from, limit, stack) {
                return occluder.is_some();
            }
        }
        for &(index, ref sphere) in &self.spheres {
            if let Some(t) = sphere.hit(origin, dir, index == from) {
                if t < limit {
                    return true;
                }
            }
        }
        false
    }

    /// Section 5: the clipped colour of the ray `origin + t·dir` at reflection depth
    /// `depth`, whose contribution to the pixel is scaled by `weight`.
    fn radiance(
        &self,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        depth: u32,
        weight: f64,
        rays: &mut u64,
    ) -> Vec3 {
        self.with_ctx(rays, |ctx| {
            self.radiance_in(origin, dir, from, depth, weight, ctx)
        })
    }

    /// [`Tracer::radiance`] within a pixel's state.
    fn radiance_in(
        &self,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        depth: u32,
        weight: f64,
        ctx: &mut Ctx,
    ) -> Vec3 {
        ctx.rays += 1;
        let Some((t, index)) = self.nearest(origin, dir, from, ctx) else {
            return Vec3::ZERO;
        };
        self.shade(origin, dir, t, index, depth, weight, ctx)
    }

    /// One camera ray's clipped colour.
    #[inline(always)]
    fn camera_sample(&self, dir: Vec3, ctx: &mut Ctx) -> Vec3 {
        ctx.rays += 1;
        let origin = self.camera.position();
        let hit = if self.bvh.is_some() {
            self.nearest(origin, dir, FROM_CAMERA, ctx)
        } else {
            self.nearest_from_eye(dir)
        };
        match hit {
            Some((t, index)) => self.shade(origin, dir, t, index, 0, 1.0, ctx),
            None => Vec3::ZERO,
        }
    }

    /// Section 5, steps 1 to 6, at the hit `origin + t·dir` on object `index`.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn shade(
        &self,
        origin: Vec3,
        dir: Vec3,
        t: f64,
        index: u32,
        depth: u32,
        weight: f64,
        ctx: &mut Ctx,
    ) -> Vec3 {
        let surface = &self.surfaces[index as usize];
        let p = origin + dir * t;

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
        if special > 0.0 && depth < self.settings.max_depth && weight * special >= MIN_PATH_WEIGHT {
            let c = self.radiance_in(p, reflected, index, depth + 1, weight * special, ctx);
            color += c * special;
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
            if self.occluded(p, l, index, distance, ctx) {
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

    /// [`Tracer::radiance_in`] for the rays of the lanes in `active`, all leaving object
    /// `from` (or the camera) at reflection depth `depth` with path weight `weight`:
    /// their clipped colours, black in other lanes. Lanes that meet the same object are
    /// shaded together; lanes that meet different objects (at a silhouette) one by one.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn packet(
        &self,
        origin: V4,
        dir: V4,
        from: u32,
        depth: u32,
        weight: f64,
        active: M4,
        ctx: &mut Ctx,
    ) -> V4 {
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: `avx2` is set only where the processor was found to support AVX2.
            return unsafe { self.packet_avx2(origin, dir, from, depth, weight, active, ctx) };
        }
        self.packet_lanes(origin, dir, from, depth, weight, active, ctx)
    }

    /// [`Tracer::packet`] compiled for AVX2, whose 256-bit registers hold the four
    /// lanes at once. The same IEEE operations as the baseline code, so the same bits
    /// (no fused multiply-add: Rust never contracts `a * b + c`).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    fn packet_avx2(
        &self,
        origin: V4,
        dir: V4,
        from: u32,
        depth: u32,
        weight: f64,
        active: M4,
        ctx: &mut Ctx,
    ) -> V4 {
        self.packet_lanes(origin, dir, from, depth, weight, active, ctx)
    }

    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn packet_lanes(
        &self,
        origin: V4,
        dir: V4,
        from: u32,
        depth: u32,
        weight: f64,
        active: M4,
        ctx: &mut Ctx,
    ) -> V4 {
        ctx.count(active);
        let (t, index) = self.nearest_lanes(origin, dir, from, active, ctx);
        let hit = active.and(index.lt(F4::splat(f64::from(FROM_CAMERA))));
        let mut colors = V4::splat(Vec3::ZERO);
        let Some(first) = (0..LANES).find(|&k| hit.get(k)) else {
            return colors;
        };
        let object = index.0[first];
        if !hit
            .and_not(index.test(F4::splat(object), |a, b| a == b))
            .any()
        {
            return self.shade_lanes(origin, dir, t, object as u32, hit, depth, weight, ctx);
        }
        for k in 0..LANES {
            if hit.get(k) {
                let (o, d) = (origin.lane(k), dir.lane(k));
                let color = self.shade(o, d, t.0[k], index.0[k] as u32, depth, weight, ctx);
                colors.set_lane(k, color);
            }
        }
        colors
    }

    /// [`Tracer::nearest`] in the lanes of `active`: the distances and the object
    /// indices, the latter as f64 (exact for every u32) so that the tie rule runs in
    /// the same SIMD lanes as the distances; [`FROM_CAMERA`] where nothing is hit.
    #[inline(always)]
    fn nearest_lanes(&self, origin: V4, dir: V4, from: u32, active: M4, ctx: &mut Ctx) -> (F4, F4) {
        let mut t = F4::splat(f64::INFINITY);
        let mut index = F4::splat(f64::from(FROM_CAMERA));
        if self.bvh.is_some() {
            for k in 0..LANES {
                if active.get(k) {
                    if let Some((tk, ik)) = self.nearest(origin.lane(k), dir.lane(k), from, ctx) {
                        t.0[k] = tk;
                        index.0[k] = f64::from(ik);
                    }
                }
            }
        } else if from == FROM_CAMERA {
            // Camera rays: the per-object constants of the eye.
            for s in &self.eye_spheres {
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
                let f = origin - V4::splat(s.center);
                let hits = if i == from {
                    leaving_hits(f, dir)
                } else {
                    let radius2 = F4::splat(s.radius2);
                    sphere_hits(f, f.dot(f) - radius2, radius2, dir, M4::NONE)
                };
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

    /// [`Tracer::shade`] for rays that all meet object `index`, in the lanes of `hit`
    /// (other lanes are black). Each lane performs the operations of the scalar code in
    /// the same order.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn shade_lanes(
        &self,
        origin: V4,
        dir: V4,
        t: F4,
        index: u32,
        hit: M4,
        depth: u32,
        weight: f64,
        ctx: &mut Ctx,
    ) -> V4 {
        let zero = F4::splat(0.0);
        let surface = &self.surfaces[index as usize];
        let p = origin + dir.scale(t);

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
        if special > 0.0 && depth < self.settings.max_depth && weight * special >= MIN_PATH_WEIGHT {
            let weight = weight * special;
            let c = self.packet(p, reflected, index, depth + 1, weight, hit, ctx);
            acc = hit.select3(acc + c.scale(F4::splat(special)), acc);
        }
        // 5. Direct light, diffuse and highlight, where the light is not shadowed.
        for light in &self.lights {
            let to_light = V4::splat(light.position) - p;
            let distance = to_light.dot(to_light).sqrt();
            let l = to_light.div(distance);
            let cos = normal.dot(l);
            // Not `cos > 0`: a NaN cosine is traced on, as in the scalar code.
            let lit = hit.and_not(cos.le(zero));
            if !lit.any() {
                continue;
            }
            ctx.count(lit);
            let unshadowed = lit.and_not(self.occluded_lanes(p, l, index, distance, lit, ctx));
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

    /// [`Tracer::occluded`] for the shadow rays of the lanes in `lit`: from `p` along
    /// `l`, leaving object `from`, towards a light at `distance`.
    #[inline(always)]
    fn occluded_lanes(&self, p: V4, l: V4, from: u32, distance: F4, lit: M4, ctx: &mut Ctx) -> M4 {
        let mut blocked = M4::NONE;
        if self.bvh.is_some() {
            for k in 0..LANES {
                if lit.get(k) && self.occluded(p.lane(k), l.lane(k), from, distance.0[k], ctx) {
                    blocked.0[k] = u64::MAX;
                }
            }
            return blocked;
        }
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
        for &(index, ref s) in &self.spheres {
            if !lit.and_not(blocked).any() {
                break;
            }
            let f = p - V4::splat(s.center);
            let t = if index == from {
                leaving_hits(f, l)
            } else {
                let radius2 = F4::splat(s.radius2);
                sphere_hits(f, f.dot(f) - radius2, radius2, l, M4::NONE)
            };
            blocked = blocked.or(t.lt(limit));
        }
        blocked
    }
}

/// [`consider`] lane by lane, for one object's hits in four rays; object indices are
/// held as f64 (exact for every u32) so that the whole rule runs in SIMD lanes.
#[inline(always)]
fn consider_lanes(best_t: &mut F4, best: &mut F4, t: F4, index: u32) {
    let index = F4::splat(f64::from(index));
    let tie = t.test(*best_t, |a, b| a == b).and(index.lt(*best));
    let better = t.lt(*best_t).or(tie);
    *best_t = better.select(t, *best_t);
    *best = better.select(index, *best);
}

/// Lane by lane, [`SphereGeom::hit`] for rays leaving the sphere (`f` = origin −
/// centre): the far wall at t = −2 f·d when ahead, NaN otherwise.
#[inline(always)]
fn leaving_hits(f: V4, dir: V4) -> F4 {
    let t = f.dot(dir).map(|b| -2.0 * b);
    t.gt(F4::splat(0.0)).select(t, F4::splat(f64::NAN))
}

/// Black and white unit squares in x and z: white where floor(x) + floor(z) is odd.
fn checker(p: Vec3) -> Vec3 {
    if checker_white(p) {
        Vec3::new(1.0, 1.0, 1.0)
    } else {
        Vec3::ZERO
    }
}

/// Whether the checkerboard is white at `p`.
#[inline(always)]
fn checker_white(p: Vec3) -> bool {
    floor_to_int(p.x).wrapping_add(floor_to_int(p.z)) & 1 == 1
}

/// [`checker_white`] for four points at once. Where |x| and |z| are below 2⁵¹ (always,
/// but for absurd coordinates), the parities of ⌊x⌋ and ⌊z⌋ come from SIMD additions and
/// comparisons ([`floor_odd`]); otherwise each lane takes the scalar path, which gives
/// the same answer.
#[inline(always)]
fn checker_white_lanes(p: V4) -> M4 {
    let limit = F4::splat(FLOOR_PARITY_LIMIT);
    let small = p.x.map(f64::abs).lt(limit).and(p.z.map(f64::abs).lt(limit));
    if !small.all() {
        return M4::from_fn(|k| checker_white(p.lane(k)));
    }
    floor_odd(p.x).xor(floor_odd(p.z))
}

/// Lane by lane, whether ⌊x⌋ is odd, for |x| < 2⁵¹, with operations that vectorise
/// (AVX2 has no 64-bit arithmetic shift, hence the subtraction). y = x + 1.5·2⁵² lies
/// in [2⁵², 2⁵³), where the spacing of doubles is 1, so it is x rounded to the nearest
/// integer r plus an even constant, exactly: its lowest bit is r's parity, and
/// y − 1.5·2⁵² is r exactly. ⌊x⌋ is r, or r − 1 when r > x, which flips the parity.
#[inline(always)]
fn floor_odd(x: F4) -> M4 {
    let shift = F4::splat(FLOOR_PARITY_SHIFT);
    let y = x + shift;
    let r = y - shift;
    let odd = M4(y.0.map(|y| 0u64.wrapping_sub(y.to_bits() & 1)));
    odd.xor(r.gt(x))
}

/// 1.5 · 2⁵², the shift of [`floor_odd`].
const FLOOR_PARITY_SHIFT: f64 = 6_755_399_441_055_744.0;

/// The bound on |x| below which [`floor_odd`] is exact: 2⁵¹.
const FLOOR_PARITY_LIMIT: f64 = 2_251_799_813_685_248.0;

/// ⌊x⌋ as an integer, without a call into the C library. Beyond ±2⁶³ the conversion
/// saturates, and below −2⁶³ the correction wraps around to `i64::MAX`: only the
/// parity is used, and it is the same in every build (a plain `t - 1` would panic
/// there in a debug build and wrap in a release build).
fn floor_to_int(x: f64) -> i64 {
    let t = x as i64;
    if (t as f64) > x {
        t.wrapping_sub(1)
    } else {
        t
    }
}

/// x¹⁰ by repeated multiplication, bit-exact on every platform (unlike `powf`).
fn pow10(x: f64) -> f64 {
    let x2 = x * x;
    let x4 = x2 * x2;
    let x8 = x4 * x4;
    x8 * x2
}

/// Section 5, step 6: light above white (r + g + b > 3) spills into every channel in
/// proportion, then each channel is clamped to [0, 1].
pub(crate) fn clip(c: Vec3) -> Vec3 {
    let sum = c.x + c.y + c.z;
    let c = if sum > 3.0 {
        let excess = sum - 3.0;
        Vec3::new(
            c.x + excess * c.x / sum,
            c.y + excess * c.y / sum,
            c.z + excess * c.z / sum,
        )
    } else {
        c
    };
    Vec3::new(
        c.x.clamp(0.0, 1.0),
        c.y.clamp(0.0, 1.0),
        c.z.clamp(0.0, 1.0),
    )
}

/// [`clip`] lane by lane, with the same operations in the same order. The spill into
/// other channels (and its divisions) is computed only when some lane is above white.
#[inline(always)]
fn clip_lanes(c: V4) -> V4 {
    let sum = c.x + c.y + c.z;
    let three = F4::splat(3.0);
    let over = sum.gt(three);
    let c = if over.any() {
        let excess = sum - three;
        let spill = V4 {
            x: c.x + excess * c.x / sum,
            y: c.y + excess * c.y / sum,
            z: c.z + excess * c.z / sum,
        };
        over.select3(spill, c)
    } else {
        c
    };
    V4 {
        x: clamp_unit(c.x),
        y: clamp_unit(c.y),
        z: clamp_unit(c.z),
    }
}

/// Lane by lane `f64::clamp(x, 0, 1)`: NaN and −0 pass through unchanged.
#[inline(always)]
fn clamp_unit(x: F4) -> F4 {
    let (zero, one) = (F4::splat(0.0), F4::splat(1.0));
    let x = x.lt(zero).select(zero, x);
    x.gt(one).select(one, x)
}

/// Section 6: round(clamp(v, 0, 1) · 255).
#[inline(always)]
pub(crate) fn to_byte(v: f64) -> u8 {
    // round() halves away from zero; for x in [0, 255] that is trunc, plus one when the
    // (exact) fractional part is at least one half.
    let x = v.clamp(0.0, 1.0) * 255.0;
    let t = x as u8;
    if x - f64::from(t) >= 0.5 {
        t + 1
    } else {
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{CameraSpec, Light, Object};

    /// SplitMix64, for reproducible random scenes.
    struct Mix(u64);

    impl Mix {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }

        fn unit(&mut self) -> f64 {
            (self.next() >> 11) as f64 / (1u64 << 53) as f64
        }

        fn vec(&mut self, scale: f64) -> Vec3 {
            let mut c = || (2.0 * self.unit() - 1.0) * scale;
            Vec3::new(c(), c(), c())
        }
    }

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

    /// The SIMD checker and clip agree with the scalar ones, at integers, halves (where
    /// rounding to nearest ties), signed zeros, near and beyond 2⁵¹ and on random points.
    #[test]
    fn lane_checker_and_clip_equal_the_scalar_ones() {
        let mut rng = Mix(3);
        let edges = [
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            1.5,
            -1.5,
            2.5,
            -2.5,
            1e-300,
            -1e-300,
            0.999_999_999_999_999_9,
            -0.999_999_999_999_999_9,
            FLOOR_PARITY_LIMIT - 0.5,
            -FLOOR_PARITY_LIMIT + 0.5,
            FLOOR_PARITY_LIMIT,
            -FLOOR_PARITY_LIMIT,
            4.0 * FLOOR_PARITY_LIMIT + 2.0,
            1e300,
            f64::INFINITY,
            f64::NAN,
        ];
        for case in 0..100_000 {
            let value = |rng: &mut Mix| match rng.next() % 3 {
                0 => edges[(rng.next() % edges.len() as u64) as usize],
                1 => (2.0 * rng.unit() - 1.0) * 100.0,
                _ => (rng.next() % 2001) as f64 / 2.0 - 500.0,
            };
            let points: [Vec3; LANES] =
                std::array::from_fn(|_| Vec3::new(value(&mut rng), 0.0, value(&mut rng)));
            let p = V4::from_lanes(points);
            let white = checker_white_lanes(p);
            for (k, point) in points.iter().enumerate() {
                assert_eq!(
                    white.get(k),
                    checker_white(*point),
                    "case {case}: {point:?}"
                );
            }
            let colors: [Vec3; LANES] = std::array::from_fn(|_| {
                let mut c = || match rng.next() % 4 {
                    0 => edges[(rng.next() % edges.len() as u64) as usize],
                    _ => 3.0 * rng.unit() - 0.5,
                };
                Vec3::new(c(), c(), c())
            });
            let c = V4::from_lanes(colors);
            let clipped = clip_lanes(c);
            for (k, color) in colors.iter().enumerate() {
                let bits = |c: Vec3| [c.x, c.y, c.z].map(f64::to_bits);
                assert_eq!(bits(clipped.lane(k)), bits(clip(*color)), "case {case}");
            }
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
