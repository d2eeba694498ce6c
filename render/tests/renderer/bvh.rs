//! The bounding volume hierarchy changes speed, never answers: for random sphere soups,
//! nearest hits, shadow tests and whole frames traced through the hierarchy equal, bit
//! for bit, those of the brute-force loop over every sphere.
//!
//! The soups are made to be hard: coincident, touching and nested spheres (ties at
//! equal distances, decided by object index), radii from 10⁻³ to 10⁴ at coordinates up
//! to 10⁵, spheres resting on planes, rays along the axes through box corners and
//! faces, rays grazing silhouettes, rays leaving a sphere's surface.

use proptest::prelude::*;
use render::{
    parse_scene, render_tile, CameraSpec, Light, Material, Object, Rect, RenderSettings, Scene,
    Shape, Tracer, Vec3,
};

use crate::support::{both, sphere, Mix, SEED};

/// A soup of `n` spheres at `scale`, with the hard cases mixed in, sometimes on a plane.
fn soup(rng: &mut Mix, n: usize, scale: f64, with_plane: bool) -> Scene {
    let mut objects: Vec<Object> = Vec::new();
    if with_plane {
        objects.push(Object {
            shape: Shape::Plane {
                normal: Vec3::new(0.0, 1.0, 0.0),
                distance: -scale,
            },
            color: Vec3::new(0.5, 0.5, 0.5),
            material: Material::Checker,
        });
    }
    let material = |rng: &mut Mix| match rng.below(4) {
        0 => Material::Reflective(0.5),
        1 => Material::Checker,
        _ => Material::Matte,
    };
    while objects.len() < n {
        let kind = rng.below(8);
        let previous = objects
            .iter()
            .filter_map(|o| match o.shape {
                Shape::Sphere { center, radius } => Some((center, radius)),
                _ => None,
            })
            .nth(rng.below(objects.len().max(1)));
        let m = material(rng);
        let s = match (kind, previous) {
            // The same sphere again: every hit ties, the lower index must win.
            (0, Some((c, r))) => sphere(c, r, m),
            // Touching: centres exactly r1 + r2 apart along an axis.
            (1, Some((c, r))) => {
                let r2 = r * (0.25 + rng.unit());
                sphere(c + rng.axis() * (r + r2), r2, m)
            }
            // Nested: same centre, smaller or larger.
            (2, Some((c, r))) => sphere(c, r * (0.1 + 1.8 * rng.unit()), m),
            // Resting on the plane.
            (3, _) if with_plane => {
                let r = scale * (0.01 + 0.2 * rng.unit());
                let c = rng.vec() * (2.0 * scale);
                sphere(Vec3::new(c.x, -scale + r, c.z), r, m)
            }
            // Huge or tiny.
            (4, _) => {
                let r = if rng.next() & 1 == 0 { 1e4 } else { 1e-3 };
                sphere(rng.vec() * (3.0 * scale), r, m)
            }
            _ => sphere(
                rng.vec() * (2.0 * scale),
                scale * (0.002 + 0.1 * rng.unit()),
                m,
            ),
        };
        objects.push(s);
    }
    Scene {
        lights: vec![
            Light {
                position: Vec3::new(-3.0, 5.0, -4.0) * scale,
                color: Vec3::new(1.0, 1.0, 1.0),
            },
            Light {
                position: Vec3::new(2.0, 3.0, 1.0) * scale,
                color: Vec3::new(0.3, 0.4, 0.5),
            },
        ],
        objects,
        camera: CameraSpec {
            position: Vec3::new(0.5, 1.5, -6.0) * scale,
            look_at: Vec3::ZERO,
            ..CameraSpec::default()
        },
        settings: RenderSettings {
            width: 40,
            height: 30,
            aa: 1,
            max_depth: 4,
            ..RenderSettings::default()
        },
        ambient: 0.2,
    }
}

/// A ray that means trouble for the soup: at a box corner or face along an axis, at a
/// silhouette, through a centre, or anywhere.
fn ray(rng: &mut Mix, scene: &Scene, scale: f64) -> (Vec3, Vec3) {
    let spheres: Vec<(Vec3, f64)> = scene
        .objects
        .iter()
        .filter_map(|o| match o.shape {
            Shape::Sphere { center, radius } => Some((center, radius)),
            _ => None,
        })
        .collect();
    let (c, r) = spheres[rng.below(spheres.len())];
    // A coordinate moved by up to three units in the last place either way.
    let nudge = |rng: &mut Mix, v: f64| {
        let mut v = v;
        for _ in 0..rng.below(4) {
            v = if rng.next() & 1 == 0 {
                v.next_up()
            } else {
                v.next_down()
            };
        }
        v
    };
    match rng.below(6) {
        0 => {
            // Along an axis, through (or a few ulps off) a corner, an edge or a face of
            // the sphere's box: where rounding decides both the box and the sphere test.
            let d = rng.axis();
            let pick = |rng: &mut Mix| [-1.0, 0.0, 1.0][rng.below(3)];
            let corner = c + Vec3::new(pick(rng), pick(rng), pick(rng)) * r;
            let corner = Vec3::new(
                nudge(rng, corner.x),
                nudge(rng, corner.y),
                nudge(rng, corner.z),
            );
            (corner - d * (5.0 * scale), d)
        }
        1 => {
            // In the plane of a box face, tangent (to a few ulps) to the sphere's extreme
            // point on that face, from any direction within the plane.
            let axis = rng.axis();
            let top = c + axis * r;
            let top = Vec3::new(nudge(rng, top.x), nudge(rng, top.y), nudge(rng, top.z));
            let mut d = rng.direction();
            d = (d - axis * d.dot(axis)).normalize();
            (top - d * (3.0 * scale), d)
        }
        2 => {
            // Grazing the silhouette from far away.
            let o = rng.direction() * (4.0 * scale) + c;
            let to_c = c - o;
            let side = to_c.cross(rng.direction()).normalize();
            let aim = c + side * (r * (1.0 + rng.signed() * 1e-9));
            (o, (aim - o).normalize())
        }
        3 => {
            let o = rng.vec() * (3.0 * scale);
            (o, (c - o).normalize())
        }
        _ => (rng.vec() * (3.0 * scale), rng.direction()),
    }
}

fn check_queries(seed: u64, n: usize, scale: f64, with_plane: bool, rays: usize) {
    let mut rng = Mix(seed);
    let scene = soup(&mut rng, n, scale, with_plane);
    let (bvh, brute) = both(&scene);
    for q in 0..rays {
        let (o, d) = ray(&mut rng, &scene, scale);
        let hit = bvh.nearest_hit(o, d, None);
        assert_eq!(
            hit,
            brute.nearest_hit(o, d, None),
            "seed {seed}, ray {q}: {o:?} {d:?}"
        );
        let Some(hit) = hit else { continue };
        // From the hit point: a random ray, the shadow rays, a ray along an axis.
        let p = o + d * hit.t;
        for d2 in [rng.direction(), rng.axis(), -d] {
            assert_eq!(
                bvh.nearest_hit(p, d2, Some(hit.object)),
                brute.nearest_hit(p, d2, Some(hit.object)),
                "seed {seed}, ray {q}: from {p:?} on {} along {d2:?}",
                hit.object
            );
        }
        for light in 0..scene.lights.len() {
            assert_eq!(
                bvh.light_visible(p, hit.object, light),
                brute.light_visible(p, hit.object, light),
                "seed {seed}, ray {q}: light {light} from {p:?} on {}",
                hit.object
            );
        }
    }
}

fn render_both(scene: &Scene, aa: u32) {
    let settings = RenderSettings {
        aa,
        ..scene.settings
    };
    let bvh = Tracer::with_bvh(scene, settings, true);
    let brute = Tracer::with_bvh(scene, settings, false);
    let rect = Rect {
        x: 0,
        y: 0,
        width: settings.width,
        height: settings.height,
    };
    let a = render_tile(&bvh, rect).unwrap();
    let b = render_tile(&brute, rect).unwrap();
    assert!(a.rgb == b.rgb, "frames differ");
    assert_eq!(a.rays, b.rays, "ray counts differ");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Nearest hits and shadow tests, at every scale.
    #[test]
    fn queries_equal_brute_force(
        seed in any::<u64>(),
        n in 2usize..300,
        scale_exp in prop::sample::select(vec![-3i32, 0, 2, 5]),
        with_plane in any::<bool>(),
    ) {
        check_queries(seed, n, 10f64.powi(scale_exp), with_plane, 300);
    }

    /// Whole frames, with mirrors, checkerboards and two lights.
    #[test]
    fn frames_equal_brute_force(
        seed in any::<u64>(),
        n in 2usize..120,
        aa in 1u32..3,
        with_plane in any::<bool>(),
    ) {
        let mut rng = Mix(seed);
        let scene = soup(&mut rng, n, 1.0, with_plane);
        render_both(&scene, aa);
    }
}

/// Hundreds of copies of one sphere, and spheres nested around one centre: every ray
/// ties, and the lowest index must win through the hierarchy too.
#[test]
fn coincident_and_nested_spheres() {
    let mut objects: Vec<Object> = (0..300)
        .map(|_| sphere(Vec3::new(0.5, 0.25, 0.0), 1.0, Material::Matte))
        .collect();
    objects.extend((1..200).map(|k| sphere(Vec3::ZERO, 0.01 * f64::from(k), Material::Matte)));
    let scene = Scene {
        objects,
        ..soup(&mut Mix(1), 0, 1.0, false)
    };
    let (bvh, brute) = both(&scene);
    let mut rng = Mix(2);
    for _ in 0..2000 {
        let o = rng.vec() * 4.0;
        let d = rng.direction();
        let hit = bvh.nearest_hit(o, d, None);
        assert_eq!(hit, brute.nearest_hit(o, d, None));
        if let Some(hit) = hit {
            let p = o + d * hit.t;
            assert_eq!(
                bvh.nearest_hit(p, d, Some(hit.object)),
                brute.nearest_hit(p, d, Some(hit.object))
            );
            assert_eq!(
                bvh.light_visible(p, hit.object, 0),
                brute.light_visible(p, hit.object, 0)
            );
        }
    }
    render_both(&scene, 2);
}

/// The seed scene through a (forced) hierarchy renders its own bytes.
#[test]
fn the_seed_scene_through_a_hierarchy() {
    let scene = parse_scene(SEED).unwrap();
    let settings = RenderSettings {
        width: 120,
        height: 80,
        aa: 2,
        ..scene.settings
    };
    let scene = Scene { settings, ..scene };
    render_both(&scene, 2);
}

/// Few spheres are traced without a hierarchy, many with one.
#[test]
fn the_hierarchy_is_built_only_when_it_pays() {
    let seed = parse_scene(SEED).unwrap();
    assert!(!Tracer::new(&seed, seed.settings).uses_bvh());
    let many = soup(&mut Mix(3), 1000, 1.0, true);
    assert!(Tracer::new(&many, many.settings).uses_bvh());
}
