//! Scene compilation: what a [`Tracer`] computes once from a scene and its settings so
//! that tracing allocates nothing and repeats no work: normals normalised, spheres and
//! planes apart in scene order, the constants of every camera ray, the sample groups
//! and image-plane tables, and the hierarchy when there are enough spheres to pay.

use super::Tracer;
use crate::bvh::Bvh;
use crate::camera::Camera;
use crate::geometry::{PlaneGeom, SphereGeom};
use crate::scene::{Material, RenderSettings, Scene, Shape};
use crate::simd::Isa;
use crate::vec3::{Divisor, Vec3, F4, LANES};

#[derive(Clone, Copy, Debug)]
pub(super) enum Geometry {
    Sphere(SphereGeom),
    Plane(PlaneGeom),
}

#[derive(Clone, Copy, Debug)]
pub(super) struct Surface {
    pub geometry: Geometry,
    pub color: Vec3,
    pub material: Material,
    /// For a sphere whose radius is a power of two, 1 / radius (see
    /// [`Divisor`]): the normals of a packet then cost a multiplication
    /// instead of a division, with the same bits.
    pub inverse_radius: Option<f64>,
}

#[derive(Clone, Copy, Debug)]
pub(super) struct LightSource {
    pub position: Vec3,
    pub color: Vec3,
}

/// Constants of every camera ray for one sphere: camera rays all start at the eye, so
/// f = eye − centre and c = f·f − r² are computed once, by the same operations that
/// [`SphereGeom::hit`] performs per ray, hence with the same bits.
#[derive(Clone, Copy, Debug)]
pub(super) struct EyeSphere {
    pub f: Vec3,
    pub c: f64,
    pub radius2: f64,
    pub index: u32,
}

/// A plane as camera rays see it: the numerator distance − n̂·eye of
/// [`PlaneGeom::hit`] is the same for all of them.
#[derive(Clone, Copy, Debug)]
pub(super) struct EyePlane {
    pub normal: Vec3,
    pub num: f64,
    pub index: u32,
}

/// Spheres from which the hierarchy is built at one sample per pixel (aa = 1). Camera
/// rays are traced four at a time at every aa, and testing every sphere then runs in
/// SIMD lanes across the four rays, from per-object camera constants, while the
/// hierarchy is traversed ray by ray: it pays only from a few dozen spheres.
/// `cargo bench -p render --bench bvh_threshold` (thread CPU time, best of 7, shared
/// 2-core Xeon) gave hierarchy / every sphere = 2.06 (cluster) and 1.75 (spread) at 12
/// spheres, 1.20 and 0.87 at 32, 0.90 and 0.64 at 48, 0.77 and 0.50 at 64: 48 is the
/// first count measured at which the hierarchy is as fast in both layouts.
const BVH_MIN_SPHERES: usize = 48;

/// The same for several samples per pixel (aa ≥ 2), measured likewise at aa 2:
/// hierarchy / every sphere = 2.28 (cluster) and 1.89 (spread) at 12 spheres, 1.33 and
/// 0.95 at 32, 0.98 and 0.70 at 48, 0.84 at 64 (cluster). Kept apart from
/// [`BVH_MIN_SPHERES`] because the two differ once the hierarchy traces packets too.
const BVH_MIN_SPHERES_PACKETS: usize = 48;

/// Scenes from this many objects have their objects prepared in parallel.
const PARALLEL_PREPARE_MIN: usize = 4096;

/// The most entries of the tables of image-plane coordinates ((width + height) × groups
/// of four samples): 2 MiB.
pub(super) const PLANE_TABLE_MAX: usize = 1 << 16;

/// Up to [`LANES`] samples of the grid, traced together: their offsets inside the pixel
/// in lanes (unused lanes repeat the first sample, and their results are dropped).
#[derive(Clone, Copy, Debug)]
pub(super) struct SampleGroup {
    pub sx: F4,
    pub sy: F4,
    pub count: usize,
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

impl Tracer {
    pub(super) fn prepare(
        scene: &Scene,
        settings: RenderSettings,
        force_bvh: Option<bool>,
    ) -> Self {
        // Per object, in order: mapped in parallel on the current pool when the scene
        // is large.
        use rayon::prelude::*;
        let surface = |o: &crate::scene::Object| Surface {
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
        };
        let surfaces: Vec<Surface> =
            if scene.objects.len() >= PARALLEL_PREPARE_MIN && rayon::current_num_threads() > 1 {
                scene.objects.par_iter().map(surface).collect()
            } else {
                scene.objects.iter().map(surface).collect()
            };
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
        let isa = Isa::detect();
        let bvh = if force_bvh.unwrap_or(spheres.len() >= threshold) {
            Bvh::build(&spheres, isa)
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
            isa,
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
}
