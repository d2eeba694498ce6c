//! Watertightness and self-intersection on closed meshes, through the whole path
//! (hierarchies, transforms, triangle test), at scales from 1e-3 to 1e4 and offsets to
//! 1e5.

use std::collections::HashMap;
use std::sync::Arc;

use super::*;
use crate::mesh::{MeshData, MeshFile};
use crate::scene::{CameraSpec, Material, MeshObject, Object};
use crate::settings::RenderSettings;
use crate::test_rng::Mix;
use crate::transform::TransformSpec;

/// A subdivided icosahedron on the unit sphere: closed and convex, every edge shared by
/// two triangles at a small angle.
fn icosphere(levels: u32) -> MeshData {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut positions: Vec<[f64; 3]> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .map(|p| {
        let l = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        [p[0] / l, p[1] / l, p[2] / l]
    })
    .to_vec();
    let mut triangles: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..levels {
        let mut middle: HashMap<(u32, u32), u32> = HashMap::new();
        let mut mid = |a: u32, b: u32, positions: &mut Vec<[f64; 3]>| {
            *middle.entry((a.min(b), a.max(b))).or_insert_with(|| {
                let (p, q) = (positions[a as usize], positions[b as usize]);
                let m = [p[0] + q[0], p[1] + q[1], p[2] + q[2]];
                let l = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
                positions.push([m[0] / l, m[1] / l, m[2] / l]);
                positions.len() as u32 - 1
            })
        };
        triangles = triangles
            .iter()
            .flat_map(|&[a, b, c]| {
                let ab = mid(a, b, &mut positions);
                let bc = mid(b, c, &mut positions);
                let ca = mid(c, a, &mut positions);
                [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
            })
            .collect();
    }
    let corner_normals = vec![[NO_NORMAL; 3]; triangles.len()];
    MeshData {
        positions,
        normals: Vec::new(),
        triangles,
        corner_normals,
    }
}

/// A cube of side 2 whose faces are n × n grids of coplanar triangle pairs: rays
/// through the edges inside a face meet two triangles in one plane.
fn grid_cube(n: u32) -> MeshData {
    let mut positions = Vec::new();
    let mut triangles = Vec::new();
    let mut index: HashMap<[i64; 3], u32> = HashMap::new();
    let mut vertex = |p: [i64; 3], positions: &mut Vec<[f64; 3]>| {
        *index.entry(p).or_insert_with(|| {
            positions.push(p.map(|x| x as f64 * 2.0 / f64::from(n) - 1.0));
            positions.len() as u32 - 1
        })
    };
    let n = i64::from(n);
    for axis in 0..3 {
        for side in [0, n] {
            for i in 0..n {
                for j in 0..n {
                    let at = |a: i64, b: i64| {
                        let mut p = [0; 3];
                        p[axis] = side;
                        p[(axis + 1) % 3] = a;
                        p[(axis + 2) % 3] = b;
                        p
                    };
                    let q = [at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)]
                        .map(|p| vertex(p, &mut positions));
                    triangles.push([q[0], q[1], q[2]]);
                    triangles.push([q[0], q[2], q[3]]);
                }
            }
        }
    }
    let corner_normals = vec![[NO_NORMAL; 3]; triangles.len()];
    MeshData {
        positions,
        normals: Vec::new(),
        triangles,
        corner_normals,
    }
}

fn mesh_scene(data: MeshData, spec: TransformSpec) -> Scene {
    let file = Arc::new(MeshFile {
        name: "test".into(),
        path: "test".into(),
        sha256: [0; 32],
        geometry: Arc::new(MeshGeometry::new(data)),
    });
    Scene {
        lights: Vec::new(),
        objects: vec![Object {
            shape: Shape::Mesh(MeshObject {
                file,
                spec,
                transform: spec.affine().unwrap(),
                smooth: false,
            }),
            color: Vec3::new(1.0, 1.0, 1.0),
            material: Material::Matte,
        }],
        camera: CameraSpec::default(),
        settings: RenderSettings::default(),
        ambient: 0.2,
    }
}

/// Distances within `tolerance` of each other are one crossing.
fn crossings(mut ts: Vec<f64>, tolerance: f64) -> usize {
    ts.sort_by(f64::total_cmp);
    let mut count = 0;
    let mut last = f64::NEG_INFINITY;
    for t in ts {
        if t - last > tolerance {
            count += 1;
        }
        last = t;
    }
    count
}

const PLACES: [(f64, f64); 6] = [
    (1.0, 0.0),
    (1e-3, 0.0),
    (1e4, 0.0),
    (1e-3, 1e5),
    (1.0, 1e5),
    (1e4, 1e5),
];

/// Rays aimed at shared edges and vertices of closed meshes meet each mesh at an even,
/// non-zero number of distinct distances: none passes through a seam.
#[test]
fn rays_at_edges_and_vertices_never_pass_through() {
    let mut rng = Mix(17);
    let mut rays = 0u64;
    for (name, data) in [("icosphere", icosphere(3)), ("grid cube", grid_cube(4))] {
        let edges: Vec<(u32, u32)> = data
            .triangles
            .iter()
            .flat_map(|&[a, b, c]| [(a, b), (b, c), (c, a)])
            .filter(|&(a, b)| a < b)
            .collect();
        for (scale, offset) in PLACES {
            let spec = TransformSpec::Parts {
                scale: Vec3::new(scale, scale, scale),
                rotate: Vec3::new(rng.unit() * 360.0, rng.unit() * 360.0, 0.0),
                translate: Vec3::new(offset, -offset * 0.5, offset * 0.25),
            };
            let scene = mesh_scene(data.clone(), spec);
            let shapes = Shapes::new(&scene).unwrap();
            let affine = spec.affine().unwrap();
            let world = |i: u32| affine.point(data.positions[i as usize]);
            let centre = affine.point([0.0; 3]);
            for _ in 0..100_000 {
                let &(a, b) = &edges[(rng.next() % edges.len() as u64) as usize];
                // On the edge, or exactly at one of its vertices.
                let target = match rng.next() % 4 {
                    0 => world(a),
                    _ => {
                        let s = rng.unit();
                        world(a) * (1.0 - s) + world(b) * s
                    }
                };
                // Through a point well inside, so that the line crosses the surface
                // at the target rather than touching it there.
                let inside = centre
                    + Vec3::new(rng.unit() - 0.5, rng.unit() - 0.5, rng.unit() - 0.5)
                        * (0.6 * scale);
                let dir = (inside - target).normalize();
                let origin = target - dir * (3.0 * scale);
                let ts: Vec<f64> = shapes.all_hits(origin, dir).iter().map(|h| h.0).collect();
                let count = crossings(ts, 1e-9 * scale);
                rays += 1;
                assert!(
                    count > 0 && count.is_multiple_of(2),
                    "{name} at scale {scale}, offset {offset}: {count} crossings from \
                     {origin:?} along {dir:?}"
                );
                // The nearest hit is found too, whatever the culling.
                assert!(shapes
                    .nearest(origin, dir, u32::MAX, NO_PRIM, (f64::INFINITY, u32::MAX, 0))
                    .is_some());
            }
        }
    }
    assert!(rays >= 1_200_000);
}

/// Shadow rays leaving a convex mesh towards its outside are never blocked by it: no
/// acne, whatever the angle between neighbours, at every scale and offset.
#[test]
fn rays_leaving_a_convex_mesh_do_not_meet_it_again() {
    let mut rng = Mix(23);
    for (name, data) in [("icosphere", icosphere(4)), ("grid cube", grid_cube(3))] {
        for (scale, offset) in PLACES {
            let spec = TransformSpec::Parts {
                scale: Vec3::new(scale, scale * 0.5, scale),
                rotate: Vec3::new(rng.unit() * 360.0, rng.unit() * 360.0, rng.unit() * 360.0),
                translate: Vec3::new(-offset, offset, offset * 0.5),
            };
            let scene = mesh_scene(data.clone(), spec);
            let shapes = Shapes::new(&scene).unwrap();
            let centre = spec.affine().unwrap().point([0.0; 3]);
            let mut hits = 0;
            for _ in 0..20_000 {
                let dir =
                    Vec3::new(rng.unit() - 0.5, rng.unit() - 0.5, rng.unit() - 0.5).normalize();
                let aim = centre
                    + Vec3::new(rng.unit() - 0.5, rng.unit() - 0.5, rng.unit() - 0.5) * scale;
                let origin = aim - dir * (4.0 * scale);
                let best = (f64::INFINITY, u32::MAX, 0);
                let Some(hit) = shapes.nearest(origin, dir, u32::MAX, NO_PRIM, best) else {
                    continue;
                };
                hits += 1;
                let s = shapes.surface(&hit, origin, dir);
                let ng = if s.ng.dot(dir) > 0.0 { -s.ng } else { s.ng };
                // Any direction on the outside of the hit triangle's plane.
                let mut l =
                    Vec3::new(rng.unit() - 0.5, rng.unit() - 0.5, rng.unit() - 0.5).normalize();
                if l.dot(ng) < 0.0 {
                    l = -l;
                }
                if rng.next().is_multiple_of(4) {
                    // Grazing: almost in the plane.
                    l = (l - ng * l.dot(ng) + ng * 1e-6).normalize();
                }
                let from = s.origin(l);
                assert!(
                    !shapes.occluded(from, l, hit.object, hit.prim, f64::INFINITY),
                    "{name} at scale {scale}, offset {offset}: a ray leaving triangle {} \
                     along {l:?} meets the mesh again",
                    hit.prim
                );
                // And a ray leaving without the triangle's exclusion does not either.
                assert!(!shapes.occluded(from, l, u32::MAX, NO_PRIM, f64::INFINITY));
            }
            assert!(hits > 5_000, "{name}: {hits} hits");
        }
    }
}

/// Two triangles sharing an edge at any angle (a valley from almost flat to almost
/// closed): a ray leaving one of them near the edge, heading away from both planes, is
/// never blocked by the other, at every scale and offset, from as near the edge as the
/// coordinates' precision can tell a point from it.
#[test]
fn neighbours_at_any_angle_do_not_shadow_each_other() {
    let mut rng = Mix(29);
    for degrees in [1.0, 10.0, 45.0, 90.0, 135.0, 170.0, 179.0] {
        // A in the plane z = 0 for x ≥ 0; B rises from the shared edge (the y axis) at
        // `degrees` from A, on A's upper side: the valley opens upwards.
        let (s, c) = crate::trig::sin_cos_deg(degrees);
        let data = MeshData {
            positions: vec![
                [0.0, -1.0, 0.0],
                [0.0, 1.0, 0.0],
                [1.0, 0.0, 0.0],
                [-c, 0.0, s],
            ],
            normals: Vec::new(),
            triangles: vec![[0, 1, 2], [1, 0, 3]],
            corner_normals: vec![[NO_NORMAL; 3]; 2],
        };
        for (scale, offset) in PLACES {
            let spec = TransformSpec::Parts {
                scale: Vec3::new(scale, scale, scale),
                rotate: Vec3::new(rng.unit() * 360.0, rng.unit() * 360.0, rng.unit() * 360.0),
                translate: Vec3::new(offset, offset, -offset),
            };
            let affine = spec.affine().unwrap();
            let scene = mesh_scene(data.clone(), spec);
            let shapes = Shapes::new(&scene).unwrap();
            let n_a = affine.vector(Vec3::new(0.0, 0.0, 1.0)).normalize();
            // B's normal towards the valley.
            let n_b = affine.vector(Vec3::new(s, 0.0, c)).normalize();
            for _ in 0..5_000 {
                // A point of A near the edge, hit from above: as near as the world's
                // precision tells from the edge itself (closer, the point is on the
                // edge to within rounding, where either answer is right).
                let nearest = 1e-11 * (offset / scale + 1.0);
                let x = nearest.powf(rng.unit());
                let local = [x * 0.5, rng.unit() - 0.5, 0.0];
                let target = affine.point(local);
                let dir = -(n_a
                    + affine.vector(Vec3::new(rng.unit() - 0.5, rng.unit() - 0.5, 0.0)))
                .normalize();
                let origin = target - dir * (2.0 * scale);
                let best = (f64::INFINITY, u32::MAX, 0);
                let Some(hit) = shapes.nearest(origin, dir, u32::MAX, NO_PRIM, best) else {
                    continue;
                };
                if hit.prim != 0 {
                    continue;
                }
                let surface = shapes.surface(&hit, origin, dir);
                let mut l =
                    Vec3::new(rng.unit() - 0.5, rng.unit() - 0.5, rng.unit() - 0.5).normalize();
                if l.dot(n_a) < 0.0 {
                    l = -l;
                }
                if l.dot(n_b) <= 1e-9 {
                    continue;
                }
                let from = surface.origin(l);
                assert!(
                    !shapes.occluded(from, l, hit.object, hit.prim, f64::INFINITY),
                    "{degrees}° at scale {scale}, offset {offset}: a ray leaving A at {x} \
                     from the edge along {l:?} meets B"
                );
            }
        }
    }
}

/// A scene of every kind of object: meshes flat and smooth, shared and transformed,
/// boxes, loose triangles, spheres and planes, mirrors and checkers.
fn mixed_scene(rng: &mut Mix) -> Scene {
    let ball = Arc::new(MeshGeometry::new(icosphere(2)));
    let file = |name: &str| {
        Arc::new(MeshFile {
            name: name.into(),
            path: name.into(),
            sha256: [0; 32],
            geometry: ball.clone(),
        })
    };
    let material = |rng: &mut Mix| match rng.next() % 4 {
        0 => Material::Checker,
        1 => Material::Reflective(0.05 + 0.9 * rng.unit()),
        _ => Material::Matte,
    };
    let mut objects = Vec::new();
    for n in 0..3 {
        let spec = TransformSpec::Parts {
            scale: Vec3::new(0.5 + rng.unit(), 0.5 + rng.unit(), 0.5 + rng.unit()),
            rotate: Vec3::new(rng.unit() * 360.0, 90.0 * (n as f64), 0.0),
            translate: Vec3::new(2.0 * rng.unit() - 1.0, rng.unit(), 2.0 * rng.unit() - 1.0) * 2.0,
        };
        objects.push(Object {
            shape: Shape::Mesh(MeshObject {
                file: file(if n == 0 { "a" } else { "b" }),
                spec,
                transform: spec.affine().unwrap(),
                smooth: n != 1,
            }),
            color: Vec3::new(rng.unit(), rng.unit(), rng.unit()),
            material: material(rng),
        });
    }
    objects.push(Object {
        shape: Shape::Box {
            min: Vec3::new(-2.5, -1.0, 1.0),
            max: Vec3::new(-1.5, 0.5, 2.0),
        },
        color: Vec3::new(0.8, 0.3, 0.2),
        material: material(rng),
    });
    objects.push(Object {
        shape: Shape::Triangle {
            vertices: [
                Vec3::new(1.0, -1.0, 2.0),
                Vec3::new(3.0, -1.0, 2.5),
                Vec3::new(2.0, 1.5, 2.2),
            ],
        },
        color: Vec3::new(0.2, 0.8, 0.3),
        material: material(rng),
    });
    objects.push(Object {
        shape: Shape::Sphere {
            center: Vec3::new(0.0, 1.8, 1.5),
            radius: 0.6,
        },
        color: Vec3::new(0.9, 0.9, 0.9),
        material: Material::Reflective(0.6),
    });
    objects.push(Object {
        shape: Shape::Plane {
            normal: Vec3::new(0.0, 1.0, 0.0),
            distance: -1.0,
        },
        color: Vec3::new(0.5, 0.5, 0.5),
        material: Material::Checker,
    });
    Scene {
        lights: vec![
            crate::scene::Light {
                position: Vec3::new(-5.0, 8.0, -6.0),
                color: Vec3::new(0.9, 0.9, 0.9),
            },
            crate::scene::Light {
                position: Vec3::new(4.0, 6.0, -3.0),
                color: Vec3::new(0.5, 0.4, 0.3),
            },
        ],
        objects,
        camera: CameraSpec {
            position: Vec3::new(1.0, 2.0, -6.0),
            look_at: Vec3::new(0.0, 0.3, 0.0),
            up: Vec3::new(0.1, 1.0, 0.0),
            fov: Some(50.0),
        },
        settings: RenderSettings {
            width: 40,
            height: 30,
            aa: 2,
            max_depth: 4,
            ..RenderSettings::default()
        },
        ambient: 0.2,
    }
}

/// Samples traced four at a time (the shapes' packet kernels) have exactly the colours
/// and the ray counts of the same samples traced alone, with the AVX2 and the portable
/// lane code alike.
#[test]
fn packets_equal_single_samples_with_every_shape() {
    use crate::simd::Isa;
    use crate::tracer::Tracer;
    let mut rng = Mix(31);
    for case in 0..20 {
        let scene = mixed_scene(&mut rng);
        let reference = Tracer::new(&scene, scene.settings).with_isa(Isa::Portable);
        for isa in [Isa::Portable, Isa::best()] {
            let tracer = Tracer::new(&scene, scene.settings).with_isa(isa);
            for j in 0..scene.settings.height {
                for i in 0..scene.settings.width {
                    let points: Vec<(f64, f64)> = (0..1 + rng.next() % 6)
                        .map(|_| (f64::from(i) + rng.unit(), f64::from(j) + rng.unit()))
                        .collect();
                    let mut colors = vec![Vec3::ZERO; points.len()];
                    let (mut packed, mut single) = (0, 0);
                    tracer.samples(&points, &mut colors, &mut packed);
                    for (&(px, py), color) in points.iter().zip(&colors) {
                        let alone = reference.sample(px, py, &mut single);
                        let bits = |c: Vec3| [c.x, c.y, c.z].map(f64::to_bits);
                        assert_eq!(
                            bits(*color),
                            bits(alone),
                            "case {case}, {isa:?}, ({px}, {py})"
                        );
                    }
                    assert_eq!(packed, single, "case {case}: rays");
                    let (mut a, mut b) = (0, 0);
                    assert_eq!(tracer.pixel(i, j, &mut a), reference.pixel(i, j, &mut b));
                }
            }
        }
    }
}
