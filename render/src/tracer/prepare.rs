//! Scene compilation: what a [`Tracer`] computes once from a scene and its settings so
//! that tracing allocates nothing and repeats no work: normals normalised, spheres and
//! planes apart in scene order, the constants of every camera ray, the sample groups
//! and image-plane tables, and the hierarchy when there are enough spheres to pay.

use super::Tracer;
use crate::bvh::Bvh;
use crate::camera::Camera;
use crate::geometry::{PlaneGeom, SphereGeom};
use crate::scene::{Material, Scene, Shape};
use crate::settings::RenderSettings;
use crate::simd::Isa;
use crate::vec3::{Divisor, Vec3, F4, LANES, M4, V4};

#[derive(Clone, Copy, Debug)]
pub(super) enum Geometry {
    Sphere(SphereGeom),
    Plane(PlaneGeom),
    /// One of section 8's shapes, traced through [`crate::shapes::Shapes`].
    Beyond,
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

/// The cone, with its apex at the eye or at a light, that holds one sphere: a camera
/// ray, or a shadow ray towards that light, can only meet the sphere if its direction
/// lies inside. Tested first (one dot product instead of the sphere test's dozen
/// products), it lets a packet pass by a sphere that all its lanes miss.
///
/// The test must never pass by a sphere that [`SphereGeom::hit`] would report (closer than
/// the light, for a shadow ray), or an image would change. So the cone is widened: a
/// direction counts as outside only if the cosine of its angle to the axis is below the
/// cone's by [`CONE_MARGIN`]. Only spheres whose tangent cone has a half-angle under 30°,
/// at a distance within 10^±100, have one (the others are always tested, as are rays
/// leaving the sphere). Then either the ray's line passes the sphere by at least
/// `CONE_MARGIN / 2 · |C − A|` (A the apex), or the sphere lies behind the eye, or beyond
/// the light, where a hit is farther than the light by at least `|C − A| / 2`. The rounding
/// of the ray's direction and of the sphere test moves the line, or the hit, by some 10 ε
/// (|p − A| + |C − A|) (p the ray's origin): about 4 · 10⁻⁹ |C − A| for shadow rays from up
/// to [`CONE_REACH`] times the sphere's distance from the light, a hundred times less than
/// the margin. Shadow rays from farther away test the sphere.
#[derive(Clone, Copy, Debug)]
pub(super) struct SphereCone {
    /// The unit direction from the apex to the sphere's centre.
    axis: Vec3,
    /// The cosine below which a direction from the apex misses the sphere: that of the
    /// tangent cone less [`CONE_MARGIN`]; −∞ where the sphere is always tested.
    min_cos: f64,
    /// Shadow rays from at least this far from the light always test the sphere.
    reach: f64,
}

/// The most [`SphereCone`]s from the lights a tracer holds (lights × spheres): 2.5 MiB.
pub(super) const SHADOW_CONES_MAX: usize = 1 << 16;

/// How much the tangent cone's cosine is widened ([`SphereCone`]).
const CONE_MARGIN: f64 = 1e-6;

/// How far a shadow ray's origin may be from the light, in multiples of the sphere's
/// distance from it, for the cone to be tested instead of the sphere ([`SphereCone`]).
const CONE_REACH: f64 = 1e6;

impl SphereCone {
    /// The cone from `apex` that holds sphere `s`.
    fn new(apex: Vec3, s: &SphereGeom) -> Self {
        let to_center = s.center - apex;
        let d2 = to_center.dot(to_center);
        let distance = d2.sqrt();
        // sin θ = r / |C − A| < ½: the apex is well outside, and cos θ = √(1 − sin²θ)
        // is computed without cancellation. And the distance within 10^±100, so that
        // neither the cone nor the sphere test's products come near underflow or
        // overflow, where rounding is no longer relative.
        let narrow = s.radius2 < 0.25 * d2 && (1e-100..=1e100).contains(&distance);
        if !narrow {
            return SphereCone {
                axis: Vec3::ZERO,
                min_cos: f64::NEG_INFINITY,
                reach: 0.0,
            };
        }
        SphereCone {
            axis: to_center / distance,
            min_cos: ((d2 - s.radius2) / d2).sqrt() - CONE_MARGIN,
            reach: distance * CONE_REACH,
        }
    }

    /// Lane by lane, whether camera rays in direction `dir` (from the apex, the eye)
    /// certainly miss the sphere. NaN answers no.
    #[inline(always)]
    pub fn misses(&self, dir: V4) -> M4 {
        dir.dot(V4::splat(self.axis)).lt(F4::splat(self.min_cos))
    }

    /// Lane by lane, whether shadow rays in direction `dir` (towards the apex, the
    /// light) from points at `distance` from it certainly pass by the sphere. NaN
    /// answers no.
    #[inline(always)]
    pub fn passes_by(&self, dir: V4, distance: F4) -> M4 {
        // The direction from the light to the point is −dir: −dir·axis < min_cos.
        dir.dot(V4::splat(self.axis))
            .gt(F4::splat(-self.min_cos))
            .and(distance.lt(F4::splat(self.reach)))
    }
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
    /// The sphere's cone from the eye: packets whose rays all miss it skip the test.
    pub cone: SphereCone,
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
                Shape::Triangle { .. } | Shape::Box { .. } | Shape::Mesh(_) => Geometry::Beyond,
            },
            color: o.color,
            material: o.material,
            inverse_radius: match o.shape {
                Shape::Sphere { radius, .. } => Divisor::new(radius).reciprocal(),
                _ => None,
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
                Geometry::Beyond => {}
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
                        cone: SphereCone::new(eye, &s),
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
        // Per light, a cone for each sphere, in the order of `spheres`: only where the
        // spheres are tested one by one, and within bounded memory (the hierarchy can
        // be forced off for any number of spheres).
        let shadow_cones = if bvh.is_some()
            || spheres.len().saturating_mul(scene.lights.len()) > SHADOW_CONES_MAX
        {
            Vec::new()
        } else {
            scene
                .lights
                .iter()
                .flat_map(|l| spheres.iter().map(|(_, s)| SphereCone::new(l.position, s)))
                .collect()
        };
        let shapes = crate::shapes::Shapes::new(scene).map(std::sync::Arc::new);
        Tracer {
            shapes,
            shadow_cones,
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::tests::Mix;
    use crate::tracer::SHADOW_REACH;

    /// A unit vector at angle `angle` from unit vector `axis`, turned about it by `turn`.
    fn at_angle(axis: Vec3, angle: f64, turn: f64) -> Vec3 {
        let helper = if axis.x.abs() < 0.9 {
            Vec3::new(1.0, 0.0, 0.0)
        } else {
            Vec3::new(0.0, 1.0, 0.0)
        };
        let u = axis.cross(helper).normalize();
        let v = axis.cross(u);
        axis * angle.cos() + (u * turn.cos() + v * turn.sin()) * angle.sin()
    }

    /// Whenever a cone says a shadow ray passes by its sphere, the sphere test (the
    /// tracer's own, from the same point, direction and limit) finds no hit closer than
    /// the light, and whenever it says a camera ray from its apex misses the sphere, the
    /// sphere test finds no hit at all: on rays grazing the tangent cone from either
    /// side, before, inside and beyond the sphere, at scales from 10⁻⁶ to 10⁶ and
    /// offsets up to 10⁹. And the cone does pass by most rays that are clearly outside
    /// it.
    #[test]
    fn a_cone_never_passes_by_a_sphere_its_ray_hits() {
        let mut rng = Mix::seeded(11);
        let (mut passed, mut clear) = (0u64, 0u64);
        for case in 0..40_000 {
            let scale = 10f64.powi((case % 13) - 6);
            let offset = rng.vec() * 10f64.powi(case % 10) * ((case % 3) as f64);
            let light = offset + rng.vec() * scale;
            let center = offset + rng.vec() * scale;
            let d = (center - light).length();
            let radius = d * (0.6 * rng.unit().abs()).max(1e-9);
            let sphere = SphereGeom::new(center, radius);
            let cone = SphereCone::new(light, &sphere);
            let axis = (center - light).normalize();
            let tangent = (radius / d).min(1.0).asin();
            let points: [Vec3; LANES] = std::array::from_fn(|k| {
                // Near the tangent cone (within 10⁻¹² to 10⁻³ of its angle, either
                // side) or anywhere, at a distance from before the sphere to far
                // beyond it, sometimes on the light's other side.
                let near = 10f64.powf(-3.0 - 9.0 * rng.unit().abs()) * rng.unit();
                let angle = if k < 3 {
                    tangent * (1.0 + near) + near * 1e-3
                } else {
                    std::f64::consts::PI * rng.unit().abs()
                };
                let reach = d * 10f64.powf(4.0 * rng.unit());
                light + at_angle(axis, angle, 7.0 * rng.unit()) * reach
            });
            let p = V4::from_lanes(points);
            let to_light = V4::splat(light) - p;
            let distance = to_light.dot(to_light).sqrt();
            let dir = to_light.div(distance);
            let passes = cone.passes_by(dir, distance);
            // The same cone as seen from an eye at the light: camera rays away from it.
            let misses = cone.misses(-dir);
            for k in 0..LANES {
                if misses.get(k) {
                    let hit = sphere.hit(light, -dir.lane(k), false);
                    assert!(
                        hit.is_none(),
                        "case {case}: the cone misses a sphere the camera ray hits at {hit:?} \
                         (eye {light:?}, sphere {center:?} r {radius})"
                    );
                }
                let (origin, l, dist) = (p.lane(k), dir.lane(k), distance.0[k]);
                let hit = sphere.hit(origin, l, false);
                let blocked = hit.is_some_and(|t| t < dist * SHADOW_REACH);
                if passes.get(k) {
                    passed += 1;
                    assert!(misses.get(k) || !cone.min_cos.is_finite() || dist >= cone.reach);
                    assert!(
                        !blocked,
                        "case {case}: the cone passes by a sphere the ray hits at {hit:?} \
                         (light {light:?}, sphere {center:?} r {radius}, point {origin:?})"
                    );
                }
                let outside = -l.dot(axis) < (tangent * 1.5 + 1e-3).min(3.0).cos();
                if outside && cone.min_cos.is_finite() && dist < cone.reach {
                    clear += 1;
                    assert!(passes.get(k), "case {case}: a ray well outside is tested");
                }
            }
        }
        assert!(
            passed > 40_000 && clear > 10_000,
            "{passed} passed, {clear} clear"
        );
    }

    /// A sphere that holds the light, whose cone is wider than 60°, or that lies where
    /// products underflow or overflow, has no cone: its shadow rays always test it.
    #[test]
    fn wide_spheres_are_always_tested() {
        let light = Vec3::new(0.0, 0.0, 0.0);
        for (center, radius) in [
            (Vec3::new(0.0, 0.0, 0.5), 1.0),
            (Vec3::new(2.0, 0.0, 0.0), 1.0),
            (Vec3::new(1e-160, 0.0, 0.0), 1e-162),
            (Vec3::new(1e160, 0.0, 0.0), 1e158),
            (Vec3::new(0.0, 0.0, 0.0), 1.0),
        ] {
            let cone = SphereCone::new(light, &SphereGeom::new(center, radius));
            let away = V4::splat(Vec3::new(0.0, 1.0, 0.0));
            assert!(!cone.passes_by(away, F4::splat(1.0)).any());
        }
        let cone = SphereCone::new(light, &SphereGeom::new(Vec3::new(3.0, 0.0, 0.0), 1.0));
        let away = V4::splat(Vec3::new(0.0, 1.0, 0.0));
        assert!(cone.passes_by(away, F4::splat(1.0)).all());
    }
}
