//! The reference baseline: a Rust transcription of the *structure* of the seed program
//! (the C++ ray tracer of `seed/ray-tracing-report.fr.txt`), so that Tessera's speed can
//! be compared with the design it replaces rather than with a strawman.
//!
//! Kept from the seed, because that is what the comparison is about: the `Vect`, `Ray`,
//! `Camera` and four-channel `Color` types, objects and light sources behind virtual
//! calls (`Vec<Box<dyn Object>>`, `Vec<Box<dyn Source>>`), a freshly allocated
//! `Vec<f64>` of intersections with every object for every ray (camera, reflection and
//! shadow rays), `winning_object_index` over that vector, the recursive `get_color_at`,
//! the textbook b² − 4ac sphere quadratic, a fixed epsilon against self-intersection,
//! `f64` everywhere and a single thread.
//!
//! Not kept: the seed's bugs that SCENE-FORMAT.md fixes (shadow test stopping after the
//! first object, distance to the light taken from a normalised vector, samples only on
//! the pixel diagonal, unbounded recursion, white tiles keeping the object's blue). The
//! shading follows SCENE-FORMAT.md sections 2 to 6, so this renders essentially the same
//! image as Tessera; only silhouette and shadow-edge samples may differ, because the
//! epsilon and the quadratic round differently from Tessera's exact methods.

use std::ops::{Add, Div, Mul, Neg, Sub};

use render::{Material, RenderSettings, Scene, Shape, Vec3};

/// Hits at t ≤ ACCURACY are taken to be the surface the ray leaves, as in the seed:
/// fine at the seed scene's unit scale, which is all this baseline has to render.
const ACCURACY: f64 = 1e-6;

/// The seed's `special` value that selects the checkerboard.
const CHECKER: f64 = 2.0;

/// A point or direction (the seed's `Vect`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Vect {
    x: f64,
    y: f64,
    z: f64,
}

impl Vect {
    const fn new(x: f64, y: f64, z: f64) -> Self {
        Vect { x, y, z }
    }

    fn magnitude(self) -> f64 {
        self.dot(self).sqrt()
    }

    fn normalize(self) -> Vect {
        self / self.magnitude()
    }

    fn dot(self, o: Vect) -> f64 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }

    fn cross(self, o: Vect) -> Vect {
        Vect::new(
            self.y * o.z - self.z * o.y,
            self.z * o.x - self.x * o.z,
            self.x * o.y - self.y * o.x,
        )
    }
}

impl From<Vec3> for Vect {
    fn from(v: Vec3) -> Self {
        Vect::new(v.x, v.y, v.z)
    }
}

impl Add for Vect {
    type Output = Vect;
    fn add(self, o: Vect) -> Vect {
        Vect::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}

impl Sub for Vect {
    type Output = Vect;
    fn sub(self, o: Vect) -> Vect {
        Vect::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}

impl Mul<f64> for Vect {
    type Output = Vect;
    fn mul(self, s: f64) -> Vect {
        Vect::new(self.x * s, self.y * s, self.z * s)
    }
}

impl Div<f64> for Vect {
    type Output = Vect;
    fn div(self, s: f64) -> Vect {
        Vect::new(self.x / s, self.y / s, self.z / s)
    }
}

impl Neg for Vect {
    type Output = Vect;
    fn neg(self) -> Vect {
        Vect::new(-self.x, -self.y, -self.z)
    }
}

/// A half-line `origin + t·direction`, |direction| = 1.
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    origin: Vect,
    direction: Vect,
}

/// The seed's colour: r g b plus the `special` channel that selects the material
/// (0 matte, (0, 1] reflective, 2 checkerboard).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Color {
    red: f64,
    green: f64,
    blue: f64,
    special: f64,
}

impl Color {
    const fn new(red: f64, green: f64, blue: f64, special: f64) -> Self {
        Color {
            red,
            green,
            blue,
            special,
        }
    }

    fn from_rgb(rgb: Vec3, special: f64) -> Self {
        Color::new(rgb.x, rgb.y, rgb.z, special)
    }

    /// Component-wise product (the seed's `colorMultiply`), keeping `self`'s special.
    fn multiply(self, o: Color) -> Color {
        Color::new(
            self.red * o.red,
            self.green * o.green,
            self.blue * o.blue,
            self.special,
        )
    }

    /// Section 5, step 6: light above white spills into every channel in proportion,
    /// then each channel is clamped to [0, 1].
    fn clip(self) -> Color {
        let all_light = self.red + self.green + self.blue;
        let excess_light = all_light - 3.0;
        let mut c = self;
        if excess_light > 0.0 {
            c.red += excess_light * (c.red / all_light);
            c.green += excess_light * (c.green / all_light);
            c.blue += excess_light * (c.blue / all_light);
        }
        Color::new(
            c.red.clamp(0.0, 1.0),
            c.green.clamp(0.0, 1.0),
            c.blue.clamp(0.0, 1.0),
            c.special,
        )
    }
}

/// Channel-wise sum, keeping `self`'s special (the seed's `colorAdd`).
impl Add for Color {
    type Output = Color;
    fn add(self, o: Color) -> Color {
        Color::new(
            self.red + o.red,
            self.green + o.green,
            self.blue + o.blue,
            self.special,
        )
    }
}

/// Scales r g b, keeping the special (the seed's `colorScalar`).
impl Mul<f64> for Color {
    type Output = Color;
    fn mul(self, s: f64) -> Color {
        Color::new(self.red * s, self.green * s, self.blue * s, self.special)
    }
}

/// The pinhole camera of section 2.
#[derive(Clone, Copy, Debug)]
pub struct Camera {
    position: Vect,
    forward: Vect,
    right: Vect,
    up: Vect,
}

impl Camera {
    fn new(position: Vect, look_at: Vect) -> Self {
        let forward = (look_at - position).normalize();
        let right = Vect::new(0.0, 1.0, 0.0).cross(forward).normalize();
        let up = forward.cross(right);
        Camera {
            position,
            forward,
            right,
            up,
        }
    }

    /// The camera ray through the image-plane point (`x`, `y`), in units of the
    /// shorter image side from the image centre.
    fn ray(&self, x: f64, y: f64) -> Ray {
        Ray {
            origin: self.position,
            direction: (self.forward + self.right * x + self.up * y).normalize(),
        }
    }
}

/// The seed's abstract `Object`: every scene object is reached through these virtual
/// calls.
pub trait Object {
    fn color(&self) -> Color;
    /// The outward unit normal at a point of the surface.
    fn normal_at(&self, p: Vect) -> Vect;
    /// The nearest t > ACCURACY where `ray` meets the object, or -1 if there is none.
    fn find_intersection(&self, ray: &Ray) -> f64;
}

/// The seed's abstract light `Source`.
pub trait Source {
    fn light_position(&self) -> Vect;
    fn light_color(&self) -> Color;
}

pub struct Sphere {
    center: Vect,
    radius: f64,
    color: Color,
}

impl Object for Sphere {
    fn color(&self) -> Color {
        self.color
    }

    fn normal_at(&self, p: Vect) -> Vect {
        (p - self.center).normalize()
    }

    /// The textbook quadratic a·t² + b·t + c = 0 (report section 2), with a = 1 because
    /// ray directions are unit vectors, as in the seed.
    fn find_intersection(&self, ray: &Ray) -> f64 {
        let oc = ray.origin - self.center;
        let b = 2.0 * ray.direction.dot(oc);
        let c = oc.dot(oc) - self.radius * self.radius;
        let discriminant = b * b - 4.0 * c;
        if discriminant <= 0.0 {
            return -1.0;
        }
        let root = discriminant.sqrt();
        let root_1 = (-b - root) / 2.0;
        if root_1 > ACCURACY {
            return root_1;
        }
        let root_2 = (-b + root) / 2.0;
        if root_2 > ACCURACY {
            root_2
        } else {
            -1.0
        }
    }
}

pub struct Plane {
    /// Unit normal.
    normal: Vect,
    distance: f64,
    color: Color,
}

impl Object for Plane {
    fn color(&self) -> Color {
        self.color
    }

    fn normal_at(&self, _p: Vect) -> Vect {
        self.normal
    }

    fn find_intersection(&self, ray: &Ray) -> f64 {
        let a = ray.direction.dot(self.normal);
        if a == 0.0 {
            // Parallel to the plane.
            return -1.0;
        }
        let b = self.normal.dot(ray.origin - self.normal * self.distance);
        let t = -b / a;
        if t > ACCURACY {
            t
        } else {
            -1.0
        }
    }
}

pub struct Light {
    position: Vect,
    color: Color,
}

impl Source for Light {
    fn light_position(&self) -> Vect {
        self.position
    }

    fn light_color(&self) -> Color {
        self.color
    }
}

/// The distance to every object along `ray`, in object order (-1 where it misses), in
/// a vector allocated for this ray: the seed's per-ray `std::vector<double>`.
fn intersections(objects: &[Box<dyn Object>], ray: &Ray) -> Vec<f64> {
    objects.iter().map(|o| o.find_intersection(ray)).collect()
}

/// The index of the nearest hit (the smallest positive distance, the lowest index on a
/// tie), or `None` if the ray hits nothing.
fn winning_object_index(intersections: &[f64]) -> Option<usize> {
    let mut winner: Option<usize> = None;
    for (index, &t) in intersections.iter().enumerate() {
        if t > 0.0 && winner.is_none_or(|w| t < intersections[w]) {
            winner = Some(index);
        }
    }
    winner
}

/// The seed scene in the seed program's data structures, with its render settings.
pub struct SeedScene {
    objects: Vec<Box<dyn Object>>,
    lights: Vec<Box<dyn Source>>,
    camera: Camera,
    ambient: f64,
    width: u32,
    height: u32,
    aadepth: u32,
    max_depth: u32,
}

impl SeedScene {
    /// Builds the seed program's objects from a loaded scene, to be rendered with
    /// `settings`.
    pub fn new(scene: &Scene, settings: RenderSettings) -> Self {
        let objects = scene
            .objects
            .iter()
            .map(|o| -> Box<dyn Object> {
                let special = match o.material {
                    Material::Matte => 0.0,
                    Material::Reflective(s) => s,
                    Material::Checker => CHECKER,
                };
                let color = Color::from_rgb(o.color, special);
                match o.shape {
                    Shape::Sphere { center, radius } => Box::new(Sphere {
                        center: center.into(),
                        radius,
                        color,
                    }),
                    Shape::Plane { normal, distance } => Box::new(Plane {
                        normal: Vect::from(normal).normalize(),
                        distance,
                        color,
                    }),
                    // The seed had spheres and planes only, and so do the scenes this
                    // baseline is measured on.
                    Shape::Triangle { .. } | Shape::Box { .. } | Shape::Mesh(_) => {
                        panic!("the seed's structure renders spheres and planes only")
                    }
                }
            })
            .collect();
        let lights = scene
            .lights
            .iter()
            .map(|l| -> Box<dyn Source> {
                Box::new(Light {
                    position: l.position.into(),
                    color: Color::from_rgb(l.color, 0.0),
                })
            })
            .collect();
        SeedScene {
            objects,
            lights,
            camera: Camera::new(scene.camera.position.into(), scene.camera.look_at.into()),
            ambient: scene.ambient,
            width: settings.width,
            height: settings.height,
            aadepth: settings.aa,
            max_depth: settings.max_depth,
        }
    }

    /// Renders the frame: RGB8, rows top to bottom, `width × height × 3` bytes.
    pub fn render(&self) -> Vec<u8> {
        let (w, h) = (f64::from(self.width), f64::from(self.height));
        let short_side = w.min(h);
        let n = f64::from(self.aadepth);
        let mut rgb = Vec::with_capacity(self.width as usize * self.height as usize * 3);
        for j in 0..self.height {
            for i in 0..self.width {
                let mut sum = Color::default();
                for b in 0..self.aadepth {
                    let y = (h / 2.0 - (f64::from(j) + (f64::from(b) + 0.5) / n)) / short_side;
                    for a in 0..self.aadepth {
                        let x = (f64::from(i) + (f64::from(a) + 0.5) / n - w / 2.0) / short_side;
                        sum = sum + self.trace(&self.camera.ray(x, y));
                    }
                }
                let mean = sum * (1.0 / (n * n));
                rgb.extend([mean.red, mean.green, mean.blue].map(to_byte));
            }
        }
        rgb
    }

    /// The clipped colour seen along a camera ray (the body of the seed's pixel loop).
    fn trace(&self, ray: &Ray) -> Color {
        let intersections = intersections(&self.objects, ray);
        match winning_object_index(&intersections) {
            Some(index) => {
                let position = ray.origin + ray.direction * intersections[index];
                self.get_color_at(position, ray.direction, index, 0)
            }
            None => Color::default(),
        }
    }

    /// Section 5: the clipped colour at `position` on object `index`, reached along
    /// `direction` at reflection depth `depth`.
    fn get_color_at(&self, position: Vect, direction: Vect, index: usize, depth: u32) -> Color {
        let object = &self.objects[index];
        let mut object_color = object.color();
        let special = object_color.special;
        if special == CHECKER {
            let square = position.x.floor() as i64 + position.z.floor() as i64;
            let v = if square.rem_euclid(2) == 1 { 1.0 } else { 0.0 };
            object_color = Color::new(v, v, v, special);
        }
        let mut normal = object.normal_at(position);
        if normal.dot(direction) > 0.0 {
            normal = -normal;
        }
        let mut final_color = object_color * self.ambient;

        let reflective = special > 0.0 && special <= 1.0;
        let reflection_direction = if reflective {
            (direction - normal * (2.0 * direction.dot(normal))).normalize()
        } else {
            Vect::default()
        };
        if reflective && depth < self.max_depth {
            let reflection_ray = Ray {
                origin: position,
                direction: reflection_direction,
            };
            let reflection_intersections = intersections(&self.objects, &reflection_ray);
            if let Some(hit) = winning_object_index(&reflection_intersections) {
                let hit_position = position + reflection_direction * reflection_intersections[hit];
                let reflection_color =
                    self.get_color_at(hit_position, reflection_direction, hit, depth + 1);
                final_color = final_color + reflection_color * special;
            }
        }

        for light in &self.lights {
            let to_light = light.light_position() - position;
            let distance_to_light = to_light.magnitude();
            let light_direction = to_light / distance_to_light;
            let cosine_angle = normal.dot(light_direction);
            if cosine_angle <= 0.0 {
                continue;
            }
            let shadow_ray = Ray {
                origin: position,
                direction: light_direction,
            };
            let shadowed = intersections(&self.objects, &shadow_ray)
                .iter()
                .any(|&t| t > 0.0 && t <= distance_to_light);
            if shadowed {
                continue;
            }
            let light_color = light.light_color();
            final_color = final_color + object_color.multiply(light_color) * cosine_angle;
            if reflective {
                let specular = reflection_direction.dot(light_direction);
                if specular > 0.0 {
                    final_color = final_color + light_color * (specular.powi(10) * special);
                }
            }
        }
        final_color.clip()
    }
}

/// Section 6: round(clamp(v, 0, 1) · 255).
fn to_byte(v: f64) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}
