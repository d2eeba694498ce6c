//! Numerically hard cases for the tracer, each with a concrete expected outcome.
//!
//! Every case also runs the textbook method, the quadratic's discriminant as b² − 4ac
//! and a fixed ε on t to skip self-intersections (here ε = 1e-3, as in many tutorials, ε = 1e-6 and
//! ε = 1e-9), and states whether it gets the case right. The textbook's failures are
//! asserted too, so the table in docs/numerics.md cannot silently go stale.

use render::{CameraSpec, Light, Material, Object, RenderSettings, Scene, Shape, Tracer, Vec3};

use crate::support::{v, Mix};

/// The textbook sphere and plane tests with a fixed epsilon, as most tutorials write
/// them (the seed program included).
mod textbook {
    use render::Vec3;

    pub const EPSILONS: [f64; 3] = [1e-3, 1e-6, 1e-9];

    pub fn sphere(o: Vec3, d: Vec3, center: Vec3, radius: f64, eps: f64) -> Option<f64> {
        let oc = o - center;
        let a = d.dot(d);
        let b = 2.0 * oc.dot(d);
        let c = oc.dot(oc) - radius * radius;
        let disc = b * b - 4.0 * a * c;
        if disc < 0.0 {
            return None;
        }
        let sq = disc.sqrt();
        let t0 = (-b - sq) / (2.0 * a);
        let t1 = (-b + sq) / (2.0 * a);
        if t0 > eps {
            Some(t0)
        } else if t1 > eps {
            Some(t1)
        } else {
            None
        }
    }

    pub fn plane(o: Vec3, d: Vec3, normal: Vec3, distance: f64, eps: f64) -> Option<f64> {
        let n = normal.normalize();
        let denom = n.dot(d);
        if denom == 0.0 {
            return None;
        }
        let t = (distance - n.dot(o)) / denom;
        (t > eps).then_some(t)
    }

    /// Textbook shadow test: any object hit with ε < t < distance to the light,
    /// including the object the ray leaves.
    pub fn shadowed(scene: &render::Scene, p: Vec3, light: Vec3, eps: f64) -> bool {
        let to_light = light - p;
        let dist = to_light.length();
        let d = to_light / dist;
        scene.objects.iter().any(|o| {
            let t = match o.shape {
                render::Shape::Sphere { center, radius } => sphere(p, d, center, radius, eps),
                render::Shape::Plane { normal, distance } => plane(p, d, normal, distance, eps),
                _ => unreachable!("spheres and planes only"),
            };
            t.is_some_and(|t| t < dist)
        })
    }
}

fn sphere(center: Vec3, radius: f64, color: Vec3, material: Material) -> Object {
    Object {
        shape: Shape::Sphere { center, radius },
        color,
        material,
    }
}

fn plane(normal: Vec3, distance: f64, color: Vec3, material: Material) -> Object {
    Object {
        shape: Shape::Plane { normal, distance },
        color,
        material,
    }
}

fn white_light(position: Vec3) -> Light {
    Light {
        position,
        color: Vec3::new(1.0, 1.0, 1.0),
    }
}

fn scene(objects: Vec<Object>, lights: Vec<Light>, camera: CameraSpec) -> Scene {
    Scene {
        lights,
        objects,
        camera,
        settings: RenderSettings::default(),
        ambient: 0.2,
    }
}

const GREY: Vec3 = Vec3::new(0.5, 0.5, 0.5);

/// How one hard case went: whether Tessera's answers were all right (the case's own
/// test asserts them in detail) and, for each textbook ε, how many of the case's rays
/// or decisions the textbook method got wrong.
struct Outcome {
    name: &'static str,
    textbook_wrong: [usize; 3],
    probes: usize,
}

/// Camera rays through a grid over the image, with what Tessera hits.
fn camera_sweep(s: &Scene, w: u32, h: u32) -> Vec<(Vec3, Vec3)> {
    let settings = RenderSettings {
        width: w,
        height: h,
        ..RenderSettings::default()
    };
    let cam = s.camera;
    let forward = (cam.look_at - cam.position).normalize();
    let right = v(0.0, 1.0, 0.0).cross(forward).normalize();
    let up = forward.cross(right);
    let m = f64::from(w.min(h));
    let mut rays = Vec::new();
    for j in 0..settings.height {
        for i in 0..settings.width {
            let x = (f64::from(i) + 0.5 - f64::from(w) / 2.0) / m;
            let y = (f64::from(h) / 2.0 - (f64::from(j) + 0.5)) / m;
            rays.push((cam.position, (forward + right * x + up * y).normalize()));
        }
    }
    rays
}

/// Whether the segment from `p` to `light` passes through the interior of a sphere,
/// with the margin (relative to the radius) inside which the answer is ambiguous.
fn segment_enters_sphere(p: Vec3, light: Vec3, center: Vec3, radius: f64) -> (bool, f64) {
    let seg = light - p;
    let len = seg.length();
    let d = seg / len;
    let along = (center - p).dot(d).clamp(0.0, len);
    let closest = p + d * along;
    let dist = (center - closest).length();
    (dist < radius, (dist - radius).abs() / radius)
}

/// Lit/shadowed decisions at every point where camera rays meet `ground` (object 0),
/// for a scene whose only possible occluders are the spheres other than the ground.
/// Returns (ours wrong, textbook wrong per ε, decisions checked).
fn ground_shadow_sweep(s: &Scene, w: u32, h: u32) -> (usize, [usize; 3], usize) {
    let tracer = Tracer::new(s, RenderSettings::default());
    let light = s.lights[0].position;
    let (mut ours_wrong, mut tb_wrong, mut checked) = (0, [0; 3], 0);
    for (o, d) in camera_sweep(s, w, h) {
        let Some(hit) = tracer.nearest_hit(o, d, None) else {
            continue;
        };
        if hit.object != 0 {
            continue;
        }
        let p = o + d * hit.t;
        let mut expected_shadow = false;
        let mut ambiguous = false;
        for obj in &s.objects[1..] {
            if let Shape::Sphere { center, radius } = obj.shape {
                let (enters, margin) = segment_enters_sphere(p, light, center, radius);
                expected_shadow |= enters;
                ambiguous |= margin < 1e-6;
            }
        }
        if ambiguous {
            continue;
        }
        checked += 1;
        if tracer.light_visible(p, 0, 0) == expected_shadow {
            ours_wrong += 1;
        }
        for (k, eps) in textbook::EPSILONS.iter().enumerate() {
            if textbook::shadowed(s, p, light, *eps) != expected_shadow {
                tb_wrong[k] += 1;
            }
        }
    }
    (ours_wrong, tb_wrong, checked)
}

fn tiny_sphere_far() -> Outcome {
    // Radius 1e-3 seen from 1e3: rays parallel to the axis at offsets h within 1e-5
    // of the radius must hit exactly when h < r.
    let r = 1e-3;
    let s = scene(
        vec![sphere(Vec3::ZERO, r, GREY, Material::Matte)],
        vec![],
        CameraSpec::default(),
    );
    let tracer = Tracer::new(&s, RenderSettings::default());
    let d = v(0.0, 0.0, 1.0);
    let centre_hit = tracer.nearest_hit(v(0.0, 0.0, -1e3), d, None).unwrap();
    assert_eq!(centre_hit.t, 1e3 - 1e-3, "distance to the near pole");
    let mut tb_wrong = [0; 3];
    let mut probes = 0;
    for k in (-100..=100).filter(|k| *k != 0) {
        let h = r * (1.0 + f64::from(k) * 1e-7);
        let o = v(h, 0.0, -1e3);
        let expected = h < r;
        probes += 1;
        assert_eq!(
            tracer.nearest_hit(o, d, None).is_some(),
            expected,
            "offset {h}"
        );
        for (i, eps) in textbook::EPSILONS.iter().enumerate() {
            if textbook::sphere(o, d, Vec3::ZERO, r, *eps).is_some() != expected {
                tb_wrong[i] += 1;
            }
        }
    }
    Outcome {
        name: "sphere of radius 1e-3 seen from 1e3 (hits near the rim)",
        textbook_wrong: tb_wrong,
        probes,
    }
}

#[test]
fn tiny_sphere_seen_from_far_away() {
    tiny_sphere_far();
}

/// A ground (a sphere of `ground_radius` whose top is at `offset`, or a plane through
/// `offset` when the radius is infinite) with a sphere of radius `small` resting on it,
/// a distant light and a camera framing the small sphere.
fn ground_scene(offset: Vec3, ground_radius: f64, small: f64) -> Scene {
    let ground = if ground_radius.is_finite() {
        sphere(
            offset + v(0.0, -ground_radius, 0.0),
            ground_radius,
            GREY,
            Material::Matte,
        )
    } else {
        plane(v(0.0, 1.0, 0.0), offset.y, GREY, Material::Matte)
    };
    scene(
        vec![
            ground,
            sphere(
                offset + v(0.0, small, 0.0),
                small,
                v(0.8, 0.2, 0.2),
                Material::Matte,
            ),
        ],
        vec![white_light(offset + v(-30.0, 40.0, -20.0))],
        CameraSpec {
            position: offset + v(0.0, 4.0, -15.0) * small,
            look_at: offset + v(0.0, 0.5, 0.0) * small,
            ..CameraSpec::default()
        },
    )
}

fn huge_ground_sphere() -> Outcome {
    // Resting spheres of radius 1 and 1e-3 (a ratio of 1e7 to the ground).
    let mut tb_wrong = [0; 3];
    let mut checked = 0;
    for small in [1.0, 1e-3] {
        let s = ground_scene(Vec3::ZERO, 1e4, small);
        let (ours_wrong, wrong, n) = ground_shadow_sweep(&s, 160, 120);
        assert!(n > 5000, "the sweep sees the ground ({n} points)");
        assert_eq!(ours_wrong, 0, "lit/shadowed decisions on the ground");
        checked += n;
        for k in 0..3 {
            tb_wrong[k] += wrong[k];
        }
    }
    let s = ground_scene(Vec3::ZERO, 1e4, 1.0);

    // Uniformly lit: every unshadowed ground sample has exactly the colour of the
    // formula ambient·C + C·cos, with no speckle of false shadow.
    let tracer = Tracer::new(&s, RenderSettings::default());
    let light = s.lights[0].position;
    let ground_center = v(0.0, -1e4, 0.0);
    let mut lit_points = 0;
    for (o, d) in camera_sweep(&s, 160, 120) {
        let Some(hit) = tracer.nearest_hit(o, d, None) else {
            continue;
        };
        let p = o + d * hit.t;
        if hit.object != 0 || !tracer.light_visible(p, 0, 0) {
            continue;
        }
        lit_points += 1;
        let n = (p - ground_center) / 1e4;
        let cos = n.dot((light - p).normalize());
        let expected = 0.2 * 0.5 + 0.5 * cos;
        let got = tracer.trace(o, d);
        assert!(
            (got.x - expected).abs() < 1e-12,
            "ground colour {got:?} at {p:?}"
        );
    }
    assert!(lit_points > 5000);
    Outcome {
        name: "sphere of radius 1e4 as ground, small sphere resting on it",
        textbook_wrong: tb_wrong,
        probes: checked,
    }
}

#[test]
fn huge_sphere_as_ground_has_no_acne() {
    huge_ground_sphere();
}

fn far_from_origin() -> Outcome {
    // The same ground scene (a plane this time) moved to coordinates around 1e5.
    let offset = v(1e5, 1e5, 1e5);
    let s = ground_scene(offset, f64::INFINITY, 1.0);
    let (ours_wrong, mut tb_wrong, mut checked) = ground_shadow_sweep(&s, 160, 120);
    assert!(checked > 5000);
    assert_eq!(ours_wrong, 0, "lit/shadowed decisions on the plane");

    // Points on the lit side of the sphere see the light; on the far side they do not.
    let tracer = Tracer::new(&s, RenderSettings::default());
    let light = s.lights[0].position;
    let center = offset + v(0.0, 1.0, 0.0);
    for (o, d) in camera_sweep(&s, 160, 120) {
        let Some(hit) = tracer.nearest_hit(o, d, None) else {
            continue;
        };
        if hit.object != 1 {
            continue;
        }
        let p = o + d * hit.t;
        assert!(
            ((p - center).length() - 1.0).abs() < 1e-9,
            "hit point on the sphere"
        );
        let cos = ((p - center) / 1.0).dot((light - p).normalize());
        if cos.abs() < 1e-6 {
            continue;
        }
        checked += 1;
        assert_eq!(tracer.light_visible(p, 1, 0), cos > 0.0, "at {p:?}");
        for (k, eps) in textbook::EPSILONS.iter().enumerate() {
            if textbook::shadowed(&s, p, light, *eps) == (cos > 0.0) {
                tb_wrong[k] += 1;
            }
        }
    }
    Outcome {
        name: "objects around coordinates 1e5",
        textbook_wrong: tb_wrong,
        probes: checked,
    }
}

#[test]
fn objects_far_from_the_origin() {
    far_from_origin();
}

fn camera_inside_sphere() -> Outcome {
    let inner = white_light(v(0.0, 2.0, 0.0));
    let outer = white_light(v(0.0, 10.0, 0.0));
    let s = scene(
        vec![sphere(Vec3::ZERO, 5.0, GREY, Material::Matte)],
        vec![inner, outer],
        CameraSpec {
            position: Vec3::ZERO,
            look_at: v(0.0, 0.0, 1.0),
            ..CameraSpec::default()
        },
    );
    let tracer = Tracer::new(&s, RenderSettings::default());
    let mut tb_wrong = [0; 3];
    let mut probes = 0;
    for (o, d) in camera_sweep(&s, 40, 30) {
        let hit = tracer
            .nearest_hit(o, d, None)
            .expect("every ray meets the wall");
        assert!((hit.t - 5.0).abs() <= 5.0 * 1e-15, "t = {}", hit.t);
        let p = o + d * hit.t;
        // The normal faces the camera (inwards); the inner light is seen wherever it
        // is in front of the wall, the outer one never.
        let inward = -p / 5.0;
        let cos_inner = inward.dot((inner.position - p).normalize());
        if cos_inner > 1e-9 {
            probes += 1;
            assert!(tracer.light_visible(p, 0, 0), "inner light at {p:?}");
            for (k, eps) in textbook::EPSILONS.iter().enumerate() {
                if textbook::shadowed(&s, p, inner.position, *eps) {
                    tb_wrong[k] += 1;
                }
            }
        }
        if inward.dot((outer.position - p).normalize()) > 1e-9 {
            probes += 1;
            assert!(!tracer.light_visible(p, 0, 1), "outer light at {p:?}");
            for (k, eps) in textbook::EPSILONS.iter().enumerate() {
                if !textbook::shadowed(&s, p, outer.position, *eps) {
                    tb_wrong[k] += 1;
                }
            }
        }
    }
    // The centre pixel by hand: p = (0, 0, 5), N = (0, 0, -1), the inner light at
    // cos = 5/√29; the outer light is behind the wall.
    let got = tracer.trace(Vec3::ZERO, v(0.0, 0.0, 1.0));
    let expected = 0.2 * 0.5 + 0.5 * (5.0 / 29f64.sqrt());
    assert!((got.x - expected).abs() < 1e-12, "{got:?} vs {expected}");
    Outcome {
        name: "camera inside a sphere (lights inside and outside)",
        textbook_wrong: tb_wrong,
        probes,
    }
}

#[test]
fn camera_inside_a_sphere() {
    camera_inside_sphere();
}

fn grazing_plane() -> Outcome {
    // Rays meeting the plane y = 0 at 0.5e-4 to 1.7e-4 rad (0.003° to 0.0097°), from
    // a height of 1, with a light also at a grazing elevation.
    let s = scene(
        vec![plane(
            v(0.0, 1.0, 0.0),
            0.0,
            GREY,
            Material::Reflective(1.0),
        )],
        vec![white_light(v(0.0, 1.0, 3e4))],
        CameraSpec::default(),
    );
    let tracer = Tracer::new(&s, RenderSettings::default());
    let light = s.lights[0].position;
    let mut rng = Mix(7);
    let mut tb_wrong = [0; 3];
    let mut probes = 0;
    for _ in 0..2000 {
        let angle = 0.5e-4 + 1.2e-4 * rng.unit();
        let x = 1e3 * (rng.unit() - 0.5);
        let (sin, cos) = angle.sin_cos();
        let o = v(x, 1.0, -1e4);
        let d = v(0.0, -sin, cos);
        let hit = tracer.nearest_hit(o, d, None).expect("the plane is hit");
        let expected_t = 1.0 / sin;
        assert!(
            (hit.t - expected_t).abs() <= expected_t * 1e-12,
            "t {}",
            hit.t
        );
        let p = o + d * hit.t;
        // The mirror's reflection leaves the plane and meets nothing.
        let reflected = v(0.0, sin, cos);
        assert_eq!(tracer.nearest_hit(p, reflected, Some(0)), None);
        // The light is above the plane: lit.
        assert!(tracer.light_visible(p, 0, 0));
        probes += 2;
        for (k, eps) in textbook::EPSILONS.iter().enumerate() {
            if textbook::plane(p, reflected, v(0.0, 1.0, 0.0), 0.0, *eps).is_some() {
                tb_wrong[k] += 1;
            }
            if textbook::shadowed(&s, p, light, *eps) {
                tb_wrong[k] += 1;
            }
        }
    }
    Outcome {
        name: "rays grazing a plane at under 0.01 degrees",
        textbook_wrong: tb_wrong,
        probes,
    }
}

#[test]
fn rays_grazing_a_plane() {
    grazing_plane();
}

fn tangent_ray() -> Outcome {
    // Rays along x, exactly tangent to spheres of several radii resting on the x axis.
    let mut tb_wrong = [0; 3];
    let mut probes = 0;
    for x0 in [10.0, 1e3, 1e5] {
        for r in [0.1, 0.3, 0.7, 1.1, 0.01, 3.0] {
            let center = v(0.0, r, 0.0);
            let s = scene(
                vec![sphere(center, r, GREY, Material::Matte)],
                vec![],
                CameraSpec::default(),
            );
            let tracer = Tracer::new(&s, RenderSettings::default());
            let (o, d) = (v(-x0, 0.0, 0.0), v(1.0, 0.0, 0.0));
            let hit = tracer
                .nearest_hit(o, d, None)
                .expect("a tangent ray touches");
            assert!((hit.t - x0).abs() <= x0 * 1e-12, "t = {} for {x0}", hit.t);
            probes += 1;
            for (k, eps) in textbook::EPSILONS.iter().enumerate() {
                if textbook::sphere(o, d, center, r, *eps)
                    .is_none_or(|t| (t - x0).abs() > x0 * 1e-12)
                {
                    tb_wrong[k] += 1;
                }
            }
        }
    }
    Outcome {
        name: "a ray exactly tangent to a sphere",
        textbook_wrong: tb_wrong,
        probes,
    }
}

#[test]
fn ray_exactly_tangent_to_a_sphere() {
    tangent_ray();
}

fn light_on_surface() -> Outcome {
    // A light lying on the plane y = 0, under a sphere: the sphere's underside is lit
    // (the plane is met exactly at the light, not before it), the plane itself is not
    // (cos = 0).
    let light = white_light(Vec3::ZERO);
    let s = scene(
        vec![
            plane(v(0.0, 1.0, 0.0), 0.0, GREY, Material::Matte),
            sphere(v(0.0, 2.0, 0.0), 1.0, GREY, Material::Matte),
        ],
        vec![light],
        CameraSpec {
            position: v(0.3, 0.4, -6.0),
            look_at: v(0.0, 1.5, 0.0),
            ..CameraSpec::default()
        },
    );
    let tracer = Tracer::new(&s, RenderSettings::default());
    let mut tb_wrong = [0; 3];
    let mut probes = 0;
    for (o, d) in camera_sweep(&s, 120, 90) {
        let Some(hit) = tracer.nearest_hit(o, d, None) else {
            continue;
        };
        let p = o + d * hit.t;
        if hit.object == 0 {
            // On the plane the light is at grazing incidence: ambient only.
            let got = tracer.trace(o, d);
            assert!((got.x - 0.1).abs() < 1e-12, "plane colour {got:?}");
            continue;
        }
        let n = p - v(0.0, 2.0, 0.0);
        if n.dot(light.position - p) <= 1e-9 {
            continue;
        }
        probes += 1;
        assert!(tracer.light_visible(p, 1, 0), "underside at {p:?}");
        for (k, eps) in textbook::EPSILONS.iter().enumerate() {
            if textbook::shadowed(&s, p, light.position, *eps) {
                tb_wrong[k] += 1;
            }
        }
    }
    assert!(probes > 100);
    Outcome {
        name: "a light exactly on a surface",
        textbook_wrong: tb_wrong,
        probes,
    }
}

#[test]
fn light_exactly_on_a_surface() {
    light_on_surface();
}

fn non_unit_normal() -> Outcome {
    // normal (0, 2, 0), distance 1: the plane n̂·p = 1, i.e. y = 1 (not y = 0.5).
    let s = scene(
        vec![plane(v(0.0, 2.0, 0.0), 1.0, GREY, Material::Matte)],
        vec![white_light(v(0.0, 5.0, 0.0))],
        CameraSpec::default(),
    );
    let tracer = Tracer::new(&s, RenderSettings::default());
    let hit = tracer
        .nearest_hit(v(0.0, 5.0, 0.0), v(0.0, -1.0, 0.0), None)
        .unwrap();
    assert_eq!(hit.t, 4.0);
    // Lit head-on: ambient 0.2·0.5 plus 0.5·cos 0 = 0.6 (the unit normal, not 2).
    let got = tracer.trace(v(0.0, 5.0, 0.0), v(0.0, -1.0, 0.0));
    assert!((got.x - 0.6).abs() < 1e-15, "{got:?}");
    let mut tb_wrong = [0; 3];
    for (k, eps) in textbook::EPSILONS.iter().enumerate() {
        let t = textbook::plane(
            v(0.0, 5.0, 0.0),
            v(0.0, -1.0, 0.0),
            v(0.0, 2.0, 0.0),
            1.0,
            *eps,
        );
        if t != Some(4.0) {
            tb_wrong[k] += 1;
        }
    }
    Outcome {
        name: "a plane with a non-unit normal",
        textbook_wrong: tb_wrong,
        probes: 1,
    }
}

#[test]
fn plane_with_a_non_unit_normal() {
    non_unit_normal();
}

fn touching_spheres() -> Outcome {
    // Spheres of radius 1 at x = -1 and x = 1 touch at the origin. A shadow ray from
    // the contact point that leaves sphere 0 enters sphere 1: shadowed. Points on
    // sphere 0 near the contact are shadowed for the same reason.
    let light = white_light(v(3.0, 5.0, 0.0));
    let s = scene(
        vec![
            sphere(v(-1.0, 0.0, 0.0), 1.0, GREY, Material::Matte),
            sphere(v(1.0, 0.0, 0.0), 1.0, GREY, Material::Matte),
        ],
        vec![light],
        CameraSpec::default(),
    );
    let tracer = Tracer::new(&s, RenderSettings::default());
    let mut tb_wrong = [0; 3];
    let mut probes = 0;
    for k in 0..200 {
        // From the contact point itself outwards along sphere 0, up to 0.2 rad away.
        let a = f64::from(k) * 1e-3;
        let p = v(-1.0 + a.cos(), a.sin(), 0.0);
        probes += 1;
        assert!(!tracer.light_visible(p, 0, 0), "contact region at {p:?}");
        for (i, eps) in textbook::EPSILONS.iter().enumerate() {
            if !textbook::shadowed(&s, p, light.position, *eps) {
                tb_wrong[i] += 1;
            }
        }
    }
    Outcome {
        name: "shadow ray from the contact point of two touching spheres",
        textbook_wrong: tb_wrong,
        probes,
    }
}

#[test]
fn shadow_ray_from_the_contact_of_touching_spheres() {
    touching_spheres();
}

#[test]
fn two_facing_mirrors_respect_the_depth_limit() {
    // Perfect mirrors (s = 1) at x = ±1, the camera between them looking at one head-on:
    // the ray bounces until the depth limit. Without lights each bounce adds the
    // ambient 0.2·0.1, so the colour is 0.02·(max_depth + 1) and exactly max_depth + 1
    // rays are traced.
    for max_depth in [0, 1, 10, 64] {
        let mirror = Vec3::new(0.1, 0.1, 0.1);
        let mut s = scene(
            vec![
                plane(v(1.0, 0.0, 0.0), 1.0, mirror, Material::Reflective(1.0)),
                plane(v(1.0, 0.0, 0.0), -1.0, mirror, Material::Reflective(1.0)),
            ],
            vec![],
            CameraSpec {
                position: Vec3::ZERO,
                look_at: v(1.0, 0.0, 0.0),
                ..CameraSpec::default()
            },
        );
        s.settings = RenderSettings {
            width: 1,
            height: 1,
            aa: 1,
            max_depth,
            ..RenderSettings::default()
        };
        let tracer = Tracer::new(&s, s.settings);
        let mut rays = 0;
        let px = tracer.pixel(0, 0, &mut rays);
        assert_eq!(rays, u64::from(max_depth) + 1);
        let expected = (0.02 * f64::from(max_depth + 1)).min(1.0);
        assert_eq!(
            px,
            [(expected * 255.0).round() as u8; 3],
            "depth {max_depth}"
        );

        // With a light and coloured mirrors every bounce adds light: still finite,
        // clipped to [0, 1].
        s.lights.push(white_light(v(0.0, 0.5, 0.0)));
        let got = Tracer::new(&s, s.settings).trace(Vec3::ZERO, v(1.0, 0.0, 0.0));
        assert!(
            got.is_finite()
                && [got.x, got.y, got.z]
                    .iter()
                    .all(|c| (0.0..=1.0).contains(c))
        );
    }
}

/// The comparison of docs/numerics.md: Tessera gets every case right (each case's own
/// assertions), and the textbook method fails these, for the εs listed.
#[test]
fn textbook_comparison_table() {
    let outcomes = [
        tiny_sphere_far(),
        huge_ground_sphere(),
        far_from_origin(),
        camera_inside_sphere(),
        grazing_plane(),
        tangent_ray(),
        light_on_surface(),
        non_unit_normal(),
        touching_spheres(),
    ];
    println!("| case | probes | textbook wrong, ε = 1e-3 | ε = 1e-6 | ε = 1e-9 |");
    for o in &outcomes {
        println!(
            "| {} | {} | {} | {} | {} |",
            o.name, o.probes, o.textbook_wrong[0], o.textbook_wrong[1], o.textbook_wrong[2]
        );
    }
    // b² − 4ac cancels near the rim of a small, distant sphere whatever ε is.
    assert!(outcomes[0].textbook_wrong.iter().all(|&n| n > 0));
    // ε = 1e-3 is larger than the 1e-3 sphere's chords: contact shadows are lost.
    assert!(outcomes[1].textbook_wrong[0] > 0);
}
