//! The one place the renderer computes in single precision, the hierarchy's node boxes
//! (render/src/bvh.rs: 8-wide `f32` boxes rounded outward, rays widened by a margin),
//! must not change a single answer on the numerically hard cases: with the hierarchy
//! forced on, frames have the bytes and ray counts of the brute-force loop (forced
//! off), and so have nearest hits and shadow decisions one ray at a time.
//!
//! The cases are where `f32` is coarsest relative to the geometry: at coordinates of
//! 1e5 the spacing of `f32` (2⁻⁷ ≈ 0.008) already exceeds a sphere of radius 1e-3, at
//! 1e12 it is 2¹⁷. So: tiny spheres far from the origin, spheres at coordinates 1e6 to
//! 1e12, rays grazing silhouettes and box faces, contact shadows at large coordinates,
//! many coincident and touching spheres. `bvh.rs` checks random soups up to a scale of
//! 1e5 and `numerics.rs` checks the hard cases against analytic answers with the
//! default tracer (brute force for so few spheres); this file puts the hard cases,
//! pushed further out, through the hierarchy.
//!
//! It also checks that no absolute tolerance hides anywhere in the renderer, hierarchy
//! included: a scene multiplied by a power of two renders the same bytes
//! (docs/numerics.md, "no ε anywhere").
//!
//! Each test prints what it checked, the figures docs/numerics.md quotes:
//! `cargo test --release -p render --test renderer -- --nocapture --test-threads 1
//! hierarchy_precision::`.

use render::{
    render_tile, CameraSpec, Light, Material, Object, Rect, RenderSettings, Scene, Shape,
    TileImage, Tracer, Vec3,
};

use crate::support::{both, sphere, v, Mix};

/// What these tests draw beyond the shared generator's values.
impl Mix {
    /// `v` moved by up to three units in the last place either way.
    fn nudge(&mut self, v: f64) -> f64 {
        let mut v = v;
        for _ in 0..self.below(4) {
            v = if self.next() & 1 == 0 {
                v.next_up()
            } else {
                v.next_down()
            };
        }
        v
    }

    fn nudge3(&mut self, v: Vec3) -> Vec3 {
        Vec3::new(self.nudge(v.x), self.nudge(v.y), self.nudge(v.z))
    }

    fn material(&mut self) -> Material {
        match self.below(4) {
            0 => Material::Reflective(0.5),
            1 => Material::Reflective(1.0),
            _ => Material::Matte,
        }
    }
}

/// The plane y = `height`, a checkerboard unless `matte`.
fn ground(height: f64, matte: bool) -> Object {
    Object {
        shape: Shape::Plane {
            normal: v(0.0, 1.0, 0.0),
            distance: height,
        },
        color: v(0.5, 0.5, 0.5),
        material: if matte {
            Material::Matte
        } else {
            Material::Checker
        },
    }
}

fn light(position: Vec3, color: Vec3) -> Light {
    Light { position, color }
}

/// A scene of `objects` lit by `lights`, seen from `position` towards `look_at`, at
/// 96 × 64 with 2 × 2 samples and mirrors four deep.
fn scene(objects: Vec<Object>, lights: Vec<Light>, position: Vec3, look_at: Vec3) -> Scene {
    Scene {
        lights,
        objects,
        camera: CameraSpec {
            position,
            look_at,
            ..CameraSpec::default()
        },
        settings: RenderSettings {
            width: 96,
            height: 64,
            aa: 2,
            max_depth: 4,
            ..RenderSettings::default()
        },
        ambient: 0.2,
    }
}

/// The spheres of a scene: centre and radius.
fn spheres(scene: &Scene) -> Vec<(Vec3, f64)> {
    scene
        .objects
        .iter()
        .filter_map(|o| match o.shape {
            Shape::Sphere { center, radius } => Some((center, radius)),
            _ => None,
        })
        .collect()
}

fn frame(tracer: &Tracer) -> TileImage {
    let s = tracer.settings();
    let rect = Rect {
        x: 0,
        y: 0,
        width: s.width,
        height: s.height,
    };
    render_tile(tracer, rect).expect("the whole frame is a valid tile")
}

/// Where two frames of the same size differ: the number of pixels and the first one.
fn difference(a: &[u8], b: &[u8], width: u32) -> Option<(usize, (u32, u32))> {
    let differing: Vec<usize> = a
        .chunks(3)
        .zip(b.chunks(3))
        .enumerate()
        .filter(|(_, (p, q))| p != q)
        .map(|(i, _)| i)
        .collect();
    let first = *differing.first()?;
    Some((
        differing.len(),
        (first as u32 % width, first as u32 / width),
    ))
}

/// What a case checked, for its line of the table.
#[derive(Default)]
struct Tally {
    frames: usize,
    pixels: usize,
    /// Pixels that are not black: the camera sees the case.
    lit_pixels: usize,
    rays: usize,
    hits: usize,
    /// Shadow decisions and secondary rays from hit points.
    secondary: usize,
}

impl Tally {
    fn print(&self, name: &str) {
        println!(
            "| {name} | {} | {} ({} not black) | {} ({} hit) | {} |",
            self.frames, self.pixels, self.lit_pixels, self.rays, self.hits, self.secondary
        );
    }
}

/// Renders `scene` through the hierarchy and by brute force and asserts the same bytes
/// and the same ray count.
fn same_frame(name: &str, scene: &Scene, tally: &mut Tally) {
    let (bvh, brute) = both(scene);
    let (a, b) = (frame(&bvh), frame(&brute));
    if let Some((count, (x, y))) = difference(&a.rgb, &b.rgb, scene.settings.width) {
        let i = 3 * (y * scene.settings.width + x) as usize;
        panic!(
            "{name}: {count} pixels differ with the hierarchy; the first at ({x}, {y}): \
             {:?} with, {:?} without",
            &a.rgb[i..i + 3],
            &b.rgb[i..i + 3]
        );
    }
    assert_eq!(a.rays, b.rays, "{name}: ray counts differ");
    tally.frames += 1;
    tally.pixels += a.rgb.len() / 3;
    tally.lit_pixels += a.rgb.chunks(3).filter(|p| p.iter().any(|&c| c > 0)).count();
}

/// Traces each ray through the hierarchy and by brute force and asserts the same
/// nearest hit (distance bits and object); from each hit, the same shadow decision for
/// every light and the same nearest hit along the mirror direction, back along the ray
/// and on through the surface (into a sphere: its far wall).
fn same_answers(
    name: &str,
    scene: &Scene,
    rays: impl IntoIterator<Item = (Vec3, Vec3)>,
    tally: &mut Tally,
) {
    let (bvh, brute) = both(scene);
    for (q, (o, d)) in rays.into_iter().enumerate() {
        let hit = bvh.nearest_hit(o, d, None);
        assert_eq!(
            hit,
            brute.nearest_hit(o, d, None),
            "{name}, ray {q}: nearest hit from {o:?} along {d:?}"
        );
        tally.rays += 1;
        let Some(hit) = hit else { continue };
        tally.hits += 1;
        let p = o + d * hit.t;
        let normal = match scene.objects[hit.object].shape {
            Shape::Sphere { center, radius } => (p - center) / radius,
            Shape::Plane { normal, .. } => normal.normalize(),
            _ => unreachable!("spheres and planes only"),
        };
        let mirror = (d - normal * (2.0 * d.dot(normal))).normalize();
        for d2 in [mirror, -d, d] {
            assert_eq!(
                bvh.nearest_hit(p, d2, Some(hit.object)),
                brute.nearest_hit(p, d2, Some(hit.object)),
                "{name}, ray {q}: from {p:?} on object {} along {d2:?}",
                hit.object
            );
            tally.secondary += 1;
        }
        for l in 0..scene.lights.len() {
            assert_eq!(
                bvh.light_visible(p, hit.object, l),
                brute.light_visible(p, hit.object, l),
                "{name}, ray {q}: light {l} from {p:?} on object {}",
                hit.object
            );
            tally.secondary += 1;
        }
    }
}

/// Rays that mean trouble for `(center, radius)` seen from about `distance` away:
/// grazing the silhouette to within 1e-9 of the radius, along an axis through (or a
/// few ulps off) a corner, edge or face of its box, tangent to the sphere in the plane
/// of a box face, and through the centre.
fn hard_rays(rng: &mut Mix, center: Vec3, radius: f64, distance: f64) -> Vec<(Vec3, Vec3)> {
    let mut rays = Vec::new();
    for _ in 0..4 {
        let o = center + rng.direction() * distance;
        let to_c = center - o;
        let side = to_c.cross(rng.direction()).normalize();
        let aim = center + side * (radius * (1.0 + rng.signed() * 1e-9));
        rays.push((o, (aim - o).normalize()));
    }
    for _ in 0..2 {
        let d = rng.axis();
        let pick = |rng: &mut Mix| [-1.0, 0.0, 1.0][rng.below(3)];
        let corner = center + v(pick(rng), pick(rng), pick(rng)) * radius;
        rays.push((rng.nudge3(corner) - d * distance, d));
    }
    for _ in 0..2 {
        let axis = rng.axis();
        let top = rng.nudge3(center + axis * radius);
        let d = rng.direction();
        let d = (d - axis * d.dot(axis)).normalize();
        rays.push((top - d * distance, d));
    }
    let o = center + rng.direction() * distance;
    rays.push((o, (center - o).normalize()));
    rays
}

/// Offsets from the origin, up to where `f64` itself has only a few digits left for a
/// sphere of radius 1e-3 (its spacing at 1e12 is 1.2e-4).
const FAR: [f64; 7] = [1e3, 1e5, 1e6, 1e8, 1e9, 1e10, 1e12];

/// A point `far` from the origin, mostly along x: the hierarchy's margin grows with the
/// sum of the coordinates' magnitudes, the rounding of a ray's origin to `f32` with the
/// largest of them, so a point near an axis leaves the margin the least room. The other
/// coordinates, one negative, make every rounding direction occur.
fn offset(far: f64) -> Vec3 {
    v(far, -0.02 * far, 0.01 * far)
}

/// 256 spheres of radius 0.5e-3 to 2e-3 in a cube of side 0.01 around a point from 1e3
/// to 1e12 away from the origin, seen from 0.016 away, with rays grazing each sphere
/// from 1e3 away.
#[test]
fn tiny_spheres_far_from_the_origin() {
    let name = "256 spheres of radius 1e-3 at 1e3 … 1e12, seen from 0.016 and from 1e3";
    let mut tally = Tally::default();
    for far in FAR {
        let at = offset(far);
        let mut rng = Mix(far.to_bits());
        let objects: Vec<Object> = (0..256)
            .map(|_| {
                let r = 1e-3 * (0.5 + 1.5 * rng.unit());
                sphere(at + rng.vec() * 0.005, r, rng.material())
            })
            .collect();
        let s = scene(
            objects,
            vec![
                light(at + v(-1.0, 2.0, -1.0), v(1.0, 1.0, 1.0)),
                light(at + v(0.5, 0.2, -0.3), v(0.3, 0.4, 0.5)),
            ],
            at + v(0.002, 0.006, -0.015),
            at,
        );
        same_frame(name, &s, &mut tally);
        let rays: Vec<_> = spheres(&s)
            .into_iter()
            .flat_map(|(c, r)| hard_rays(&mut rng, c, r, 1e3))
            .collect();
        same_answers(name, &s, rays, &mut tally);
    }
    assert!(tally.lit_pixels > tally.pixels / 4, "the clusters are seen");
    assert!(tally.hits > tally.rays / 4 && tally.hits < tally.rays);
    tally.print(name);
}

/// A field of `n` spheres of radius 1e-3·size to 0.3·size within 4·size of `at`, some
/// resting on a checkered ground, some coincident with or touching another, with two
/// lights and a camera at about 6·size.
fn field(rng: &mut Mix, at: Vec3, size: f64, n: usize) -> Scene {
    let floor = at.y - size;
    let mut objects = vec![ground(floor, false)];
    let mut placed: Vec<(Vec3, f64)> = Vec::new();
    while placed.len() < n {
        let m = rng.material();
        let (c, r) = match (rng.below(6), placed.last().copied()) {
            (0, Some((c, r))) => (c, r),
            (1, Some((c, r))) => {
                let r2 = r * (0.25 + rng.unit());
                (c + rng.axis() * (r + r2), r2)
            }
            (2, _) => {
                let r = size * (1e-3 + 0.3 * rng.unit());
                let c = at + rng.vec() * (4.0 * size);
                (v(c.x, floor + r, c.z), r)
            }
            _ => (
                at + rng.vec() * (4.0 * size),
                size * (1e-3 + 0.3 * rng.unit() * rng.unit()),
            ),
        };
        placed.push((c, r));
        objects.push(sphere(c, r, m));
    }
    scene(
        objects,
        vec![
            light(at + v(-3.0, 5.0, -4.0) * size, v(1.0, 1.0, 1.0)),
            light(at + v(2.0, 3.0, 1.0) * size, v(0.3, 0.4, 0.5)),
        ],
        at + v(0.5, 1.5, -6.0) * size,
        at,
    )
}

/// Fields of spheres scaled up to 1e6 … 1e12 around the origin, and fields of size 1
/// moved out to 1e6 … 1e12: the hierarchy's margin grows with the coordinates, the
/// spheres of the moved fields do not.
#[test]
fn spheres_at_large_coordinates() {
    let name = "fields of 200 spheres scaled to 1e6 … 1e12, or of size 1 moved there";
    let mut tally = Tally::default();
    for far in [1e6, 1e8, 1e10, 1e12] {
        for (at, size) in [(Vec3::ZERO, far), (offset(far), 1.0)] {
            let mut rng = Mix(far.to_bits() ^ size.to_bits());
            let s = field(&mut rng, at, size, 200);
            same_frame(name, &s, &mut tally);
            let camera = s.camera.position;
            let mut rays = Vec::new();
            for _ in 0..600 {
                let target = at + rng.vec() * (4.0 * size);
                rays.push((camera, (target - camera).normalize()));
                rays.push((target + rng.vec() * (6.0 * size), rng.direction()));
            }
            for (c, r) in spheres(&s).into_iter().take(60) {
                rays.extend(hard_rays(&mut rng, c, r, 8.0 * size));
            }
            same_answers(name, &s, rays, &mut tally);
        }
    }
    assert!(tally.lit_pixels > tally.pixels / 4, "the fields are seen");
    assert!(tally.hits > tally.rays / 4);
    tally.print(name);
}

/// Rays grazing silhouettes and box faces of spheres of radius 1e-3 to 1e4 around
/// coordinates up to 1e12, from 10 radii to 1e6 radii away, with the grazing rays
/// half just inside, half just outside the silhouette (by 1e-7 of the radius and less).
#[test]
fn rays_grazing_silhouettes() {
    let name = "rays grazing silhouettes and box faces, radius 1e-3 … 1e4 at up to 1e12";
    let mut tally = Tally::default();
    for far in [0.0, 1e5, 1e6, 1e9, 1e12] {
        for radius in [1e-3, 1.0, 1e4_f64] {
            let at = offset(far);
            let mut rng = Mix(far.to_bits() ^ radius.to_bits());
            // A sphere and its neighbours, so the hierarchy has boxes to test: a ring of
            // 40 of the same radius, 3 radii apart.
            let objects: Vec<Object> = (0..40)
                .map(|k| {
                    let a = f64::from(k) * std::f64::consts::TAU / 40.0;
                    let ring = 40.0 * 3.0 * radius / std::f64::consts::TAU;
                    sphere(
                        at + v(a.cos(), 0.25 * a.sin(), a.sin()) * ring,
                        radius,
                        rng.material(),
                    )
                })
                .collect();
            let s = scene(
                objects,
                vec![light(at + v(1.0, 30.0, -2.0) * radius, v(1.0, 1.0, 1.0))],
                at + v(0.0, 4.0, -25.0) * radius,
                at,
            );
            let mut rays = Vec::new();
            for (c, r) in spheres(&s) {
                for distance in [10.0 * r, 1e3 * r, 1e6 * r] {
                    rays.extend(hard_rays(&mut rng, c, r, distance));
                    // Parallel to an axis, at offsets from the rim of 1e-7 · r and
                    // less, inside and outside.
                    for k in 1..=4 {
                        for sign in [-1.0, 1.0] {
                            let h = r * (1.0 + sign * f64::from(k) * 0.25e-7);
                            let o = c + v(h, 0.0, -distance);
                            rays.push((o, v(0.0, 0.0, 1.0)));
                        }
                    }
                }
            }
            same_answers(name, &s, rays, &mut tally);
        }
    }
    assert!(tally.hits > tally.rays / 4 && tally.hits < tally.rays);
    tally.print(name);
}

/// Spheres of radius 1e-3, 1 and 1e3 resting on a plane and on a ground sphere 1e4
/// times their radius, with a second sphere resting on each, around coordinates 1e5 to
/// 1e12, lit from the side so the contact shadows are in view; shadow rays from the
/// ground and from each sphere at and around every contact point.
#[test]
fn contact_shadows_at_large_coordinates() {
    let name = "contact shadows of resting spheres, radius 1e-3 … 1e3 at 1e5 … 1e12";
    let mut tally = Tally::default();
    for far in [1e5, 1e6, 1e8, 1e10, 1e12] {
        for r in [1e-3, 1.0, 1e3_f64] {
            for on_sphere in [false, true] {
                let at = offset(far);
                let mut rng = Mix(far.to_bits() ^ r.to_bits() ^ u64::from(on_sphere));
                let big = 1e4 * r;
                let mut objects = vec![if on_sphere {
                    sphere(at - v(0.0, big, 0.0), big, Material::Matte)
                } else {
                    ground(at.y, true)
                }];
                // A row of 24 resting spheres, 3 radii apart, each with a half-size
                // sphere resting on its top.
                let mut contacts = Vec::new();
                for k in 0..24 {
                    let x = (f64::from(k) - 11.5) * 3.0 * r;
                    let foot = if on_sphere {
                        // On the ground sphere, along its surface.
                        let n = v(x, big, 0.0).normalize();
                        at - v(0.0, big, 0.0) + n * big
                    } else {
                        at + v(x, 0.0, 0.0)
                    };
                    let up = if on_sphere {
                        (foot - (at - v(0.0, big, 0.0))).normalize()
                    } else {
                        v(0.0, 1.0, 0.0)
                    };
                    let c = foot + up * r;
                    objects.push(sphere(c, r, rng.material()));
                    objects.push(sphere(c + up * (1.5 * r), 0.5 * r, rng.material()));
                    contacts.push((foot, up, c));
                    contacts.push((c + up * r, up, c + up * (1.5 * r)));
                }
                let s = scene(
                    objects,
                    vec![light(at + v(-30.0, 40.0, -20.0) * r, v(1.0, 1.0, 1.0))],
                    at + v(0.0, 4.0, -15.0) * r,
                    at + v(0.0, 0.5, 0.0) * r,
                );
                same_frame(name, &s, &mut tally);
                // Rays straight down onto the ground or the lower sphere near each
                // contact, from 0 to 2 radii out, so that their shadow rays start at
                // and around the contact point.
                let mut rays = Vec::new();
                for &(point, up, _) in &contacts {
                    for _ in 0..12 {
                        let side = up.cross(rng.direction()).normalize();
                        let out = side * (r * 2.0 * rng.unit() * rng.unit());
                        let o = point + out + up * (3.0 * r);
                        rays.push((o, -up));
                    }
                    // And a ray at the contact point exactly.
                    let o = point + up * (0.2 * r) + v(0.0, 0.0, -10.0 * r);
                    rays.push((o, (point - o).normalize()));
                }
                same_answers(name, &s, rays, &mut tally);
            }
        }
    }
    assert!(tally.lit_pixels > tally.pixels / 4, "the rows are seen");
    assert!(tally.hits > tally.rays / 2);
    tally.print(name);
}

/// A 6 × 6 × 6 lattice of touching spheres (centres one diameter apart), 100 copies of
/// one sphere and 50 spheres nested around one centre, at coordinates up to 1e12:
/// every tie of distance goes to the lower object index, through the hierarchy too,
/// and shadow rays start at the contact points.
#[test]
fn many_coincident_and_touching_spheres() {
    let name = "216 touching, 100 coincident and 50 nested spheres at up to 1e12";
    let mut tally = Tally::default();
    for far in [0.0, 1e5, 1e6, 1e9, 1e12] {
        for r in [1e-3, 0.5_f64] {
            let at = offset(far);
            let mut rng = Mix(far.to_bits() ^ r.to_bits());
            let mut objects = Vec::new();
            let mut contacts = Vec::new();
            for i in 0..6 {
                for j in 0..6 {
                    for k in 0..6 {
                        let c = at + v(f64::from(i), f64::from(j), f64::from(k)) * (2.0 * r);
                        objects.push(sphere(c, r, rng.material()));
                        contacts.push(c + v(r, 0.0, 0.0));
                        contacts.push(c + v(0.0, r, 0.0));
                    }
                }
            }
            let twin = at + v(-4.0, 2.0, 1.0) * r;
            objects.extend((0..100).map(|_| sphere(twin, 1.5 * r, Material::Matte)));
            let nest = at + v(5.0, -4.0, 2.0) * r;
            objects.extend((1..=50).map(|k| sphere(nest, 0.05 * r * f64::from(k), rng.material())));
            let s = scene(
                objects,
                vec![
                    light(at + v(-10.0, 30.0, -20.0) * r, v(1.0, 1.0, 1.0)),
                    light(at + v(5.0, 5.0, 5.0) * r, v(0.4, 0.3, 0.2)),
                ],
                at + v(-6.0, 9.0, -14.0) * r,
                at + v(5.0, 5.0, 5.0) * r,
            );
            same_frame(name, &s, &mut tally);
            let mut rays = Vec::new();
            // From just outside each contact point towards it, and from the contact
            // point itself (it lies on both spheres) in any direction.
            for &p in &contacts {
                let o = p + rng.direction() * (3.0 * r);
                rays.push((o, (p - o).normalize()));
                rays.push((p, rng.direction()));
            }
            for _ in 0..400 {
                let o = at + rng.vec() * (20.0 * r);
                for target in [twin, nest] {
                    let aim = target + rng.vec() * (1.5 * r);
                    rays.push((o, (aim - o).normalize()));
                }
            }
            same_answers(name, &s, rays, &mut tally);
        }
    }
    assert!(tally.lit_pixels > tally.pixels / 4, "the lattices are seen");
    assert!(tally.hits > tally.rays / 2);
    tally.print(name);
}

/// Multiplies every length of `scene` by `factor`.
fn scaled(scene: &Scene, factor: f64) -> Scene {
    let mut s = scene.clone();
    for o in &mut s.objects {
        o.shape = match o.shape {
            Shape::Sphere { center, radius } => Shape::Sphere {
                center: center * factor,
                radius: radius * factor,
            },
            Shape::Plane { normal, distance } => Shape::Plane {
                normal,
                distance: distance * factor,
            },
            ref other => other.clone(),
        };
    }
    for l in &mut s.lights {
        l.position = l.position * factor;
    }
    s.camera.position = s.camera.position * factor;
    s.camera.look_at = s.camera.look_at * factor;
    s
}

/// Multiplying by a power of two is exact, and every test of the renderer is relative
/// (the shadow reach, the hierarchy's margin above its floor) or exact (the surface a
/// ray leaves), so a scene scaled by 2⁻⁴⁰ … 2⁴⁰ renders the bytes of the original,
/// with and without the hierarchy. The scene has no checkerboard: its squares are of
/// unit size whatever the scale, so its image does change.
#[test]
fn scaling_by_a_power_of_two_changes_no_byte() {
    let name = "a field of 200 spheres scaled by 2^-40 … 2^40";
    let mut tally = Tally::default();
    let mut original = field(&mut Mix(99), Vec3::ZERO, 1.0, 200);
    original.objects[0] = ground(-1.0, true);
    let (bvh, brute) = both(&original);
    let reference = frame(&brute);
    assert!(frame(&bvh).rgb == reference.rgb);
    for e in [-40, -20, -7, 7, 20, 40] {
        let factor = 2f64.powi(e);
        let s = scaled(&original, factor);
        let (bvh, brute) = both(&s);
        for (tracer, how) in [(&bvh, "with"), (&brute, "without")] {
            let image = frame(tracer);
            if let Some((count, (x, y))) = difference(&image.rgb, &reference.rgb, s.settings.width)
            {
                panic!(
                    "scaled by 2^{e}, {how} the hierarchy: {count} pixels differ from the \
                     original, the first at ({x}, {y})"
                );
            }
            assert_eq!(image.rays, reference.rays, "scaled by 2^{e}: ray count");
            tally.frames += 1;
            tally.pixels += image.rgb.len() / 3;
            tally.lit_pixels += image
                .rgb
                .chunks(3)
                .filter(|p| p.iter().any(|&c| c > 0))
                .count();
        }
    }
    assert!(tally.lit_pixels > tally.pixels / 2);
    tally.print(name);
}

/// The cones that let packets skip spheres without a hierarchy (docs/numerics.md,
/// "Cones") are widened so that they skip no hit; the frames without the hierarchy,
/// which use them, must have the bytes of those with it, which does not. The hard cases
/// for a cone are a light on, just inside or just outside a sphere (the tangent cone
/// opens to 180°), spheres seen from the light or the eye under a tiny angle, and rays
/// grazing their silhouettes: 40 spheres and 1 to 4 lights at scales 1e-6 to 1e6 and up
/// to 1e12 from the origin, at 1 and 2 × 2 samples.
#[test]
fn lights_on_and_beside_spheres_and_tiny_cones() {
    let name = "lights on, in and beside spheres, tiny cones, scale 1e-6 … 1e6 at up to 1e12";
    let mut tally = Tally::default();
    let mut rng = Mix(2026);
    for case in 0..24 {
        let scale = 10f64.powi(case % 13 - 6);
        let at = if case % 3 == 0 {
            Vec3::ZERO
        } else {
            offset(FAR[case as usize % FAR.len()])
        };
        let point = |rng: &mut Mix, spread: f64| at + rng.vec() * (spread * scale);
        let lights: Vec<Light> = (0..1 + rng.below(4))
            .map(|_| {
                let p = point(&mut rng, 3.0) + v(0.0, 2.0 * scale, 0.0);
                light(p, v(0.6, 0.6, 0.6))
            })
            .collect();
        let mut objects = vec![ground(at.y - scale, case % 2 == 0)];
        for k in 0..40 {
            let r = scale * 10f64.powf(-3.0 * rng.unit());
            let centre = match k % 4 {
                // Around a light: the light on the surface (to the last bits), just
                // inside or just outside.
                0 => {
                    let l = lights[rng.below(lights.len())].position;
                    let d = r * (1.0 + 1e-9 * rng.signed() * f64::from(u8::from(k % 8 == 0)));
                    let on = l + rng.direction() * d;
                    rng.nudge3(on)
                }
                // Far and small as seen from a light: a cone of a tiny angle.
                1 => point(&mut rng, 3.0),
                _ => point(&mut rng, 2.0),
            };
            let r = if k % 4 == 1 { r * 1e-3 } else { r };
            objects.push(sphere(centre, r, rng.material()));
        }
        let mut s = scene(
            objects,
            lights,
            at + v(0.5 * scale, 3.0 * scale, -7.0 * scale),
            at,
        );
        for aa in [1, 2] {
            s.settings.aa = aa;
            same_frame(name, &s, &mut tally);
        }
    }
    assert!(tally.lit_pixels > tally.pixels / 4, "the scenes are seen");
    tally.print(name);
}
