//! The Whitted-style tracer of the scene format (sections 4 and 5): nearest hit,
//! two-sided normals, ambient, mirror reflection, shadows, highlight and clip.

use crate::camera::Camera;
use crate::geometry::{PlaneGeom, SphereGeom};
use crate::scene::{Material, RenderSettings, Scene, Shape};
use crate::vec3::Vec3;

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
}

#[derive(Clone, Copy, Debug)]
struct LightSource {
    position: Vec3,
    color: Vec3,
}

/// A scene prepared for tracing at given settings: normals normalised, camera basis
/// and per-object constants computed once, so tracing allocates nothing.
#[derive(Clone, Debug)]
pub struct Tracer {
    surfaces: Vec<Surface>,
    /// Object indices of the spheres and of the planes, each in scene order, so the
    /// hot loops run over one shape at a time.
    spheres: Vec<(u32, SphereGeom)>,
    planes: Vec<(u32, PlaneGeom)>,
    lights: Vec<LightSource>,
    ambient: f64,
    camera: Camera,
    settings: RenderSettings,
    /// (a + ½)/n for a in 0..n: the sample offsets inside a pixel, on both axes.
    offsets: Vec<f64>,
}

/// Marks a ray that leaves no surface (a camera ray).
const FROM_CAMERA: u32 = u32::MAX;

impl Tracer {
    /// Prepares `scene` for rendering with `settings` (the scene's own or overridden
    /// ones, already validated).
    pub fn new(scene: &Scene, settings: RenderSettings) -> Self {
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
        Tracer {
            surfaces,
            spheres,
            planes,
            lights: scene
                .lights
                .iter()
                .map(|l| LightSource {
                    position: l.position,
                    color: l.color,
                })
                .collect(),
            ambient: scene.ambient,
            camera: Camera::new(&scene.camera, &settings),
            offsets: (0..settings.aa)
                .map(|a| (f64::from(a) + 0.5) / f64::from(settings.aa))
                .collect(),
            settings,
        }
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    /// The nearest hit with t > 0 of the ray `origin + t·dir` (|dir| = 1), ignoring the
    /// surface the ray leaves (`from`). Equal distances go to the lower object index.
    pub fn nearest_hit(&self, origin: Vec3, dir: Vec3, from: Option<usize>) -> Option<Hit> {
        let from = from.map_or(FROM_CAMERA, |i| i as u32);
        self.nearest(origin, dir, from).map(|(t, object)| Hit {
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
        !self.occluded(point, dir, from as u32, distance)
    }

    /// The clipped colour seen along a camera ray.
    pub fn trace(&self, origin: Vec3, dir: Vec3) -> Vec3 {
        let mut rays = 0;
        self.radiance(origin, dir, FROM_CAMERA, 0, 1.0, &mut rays)
    }

    /// The 8-bit colour of pixel (`i`, `j`) (column, row from the top left): the mean of
    /// its n × n clipped samples, summed in sample order. Adds the rays traced to `rays`.
    pub fn pixel(&self, i: u32, j: u32, rays: &mut u64) -> [u8; 3] {
        let nf = f64::from(self.settings.aa);
        let origin = self.camera.position();
        let mut sum = Vec3::ZERO;
        for &sy in &self.offsets {
            let py = f64::from(j) + sy;
            for &sx in &self.offsets {
                let px = f64::from(i) + sx;
                let dir = self.camera.direction(px, py);
                sum += self.radiance(origin, dir, FROM_CAMERA, 0, 1.0, rays);
            }
        }
        let mean = sum / (nf * nf);
        [to_byte(mean.x), to_byte(mean.y), to_byte(mean.z)]
    }

    fn nearest(&self, origin: Vec3, dir: Vec3, from: u32) -> Option<(f64, u32)> {
        let mut best_t = f64::INFINITY;
        let mut best = FROM_CAMERA;
        for &(index, ref sphere) in &self.spheres {
            if let Some(t) = sphere.hit(origin, dir, index == from) {
                if t < best_t || (t == best_t && index < best) {
                    best_t = t;
                    best = index;
                }
            }
        }
        for &(index, ref plane) in &self.planes {
            if index == from {
                continue;
            }
            if let Some(t) = plane.hit(origin, dir) {
                if t < best_t || (t == best_t && index < best) {
                    best_t = t;
                    best = index;
                }
            }
        }
        (best != FROM_CAMERA).then_some((best_t, best))
    }

    /// Whether any object is hit at a distance in (0, reach·`max_t`): shadow rays stop
    /// at the first occluder found.
    fn occluded(&self, origin: Vec3, dir: Vec3, from: u32, max_t: f64) -> bool {
        let limit = max_t * SHADOW_REACH;
        self.spheres.iter().any(|&(index, ref sphere)| {
            sphere
                .hit(origin, dir, index == from)
                .is_some_and(|t| t < limit)
        }) || self.planes.iter().any(|&(index, ref plane)| {
            index != from && plane.hit(origin, dir).is_some_and(|t| t < limit)
        })
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
        *rays += 1;
        let Some((t, index)) = self.nearest(origin, dir, from) else {
            return Vec3::ZERO;
        };
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
            let c = self.radiance(p, reflected, index, depth + 1, weight * special, rays);
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
            *rays += 1;
            if self.occluded(p, l, index, distance) {
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

/// Black and white unit squares in x and z: white where floor(x) + floor(z) is odd.
fn checker(p: Vec3) -> Vec3 {
    let sum = floor_to_int(p.x).wrapping_add(floor_to_int(p.z));
    if sum & 1 == 1 {
        Vec3::new(1.0, 1.0, 1.0)
    } else {
        Vec3::ZERO
    }
}

/// ⌊x⌋ as an integer (saturating beyond ±2⁶³), without a call into the C library.
fn floor_to_int(x: f64) -> i64 {
    let t = x as i64;
    if (t as f64) > x {
        t - 1
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

/// Section 6: round(clamp(v, 0, 1) · 255).
fn to_byte(v: f64) -> u8 {
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
