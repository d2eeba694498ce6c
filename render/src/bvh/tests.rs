use super::*;
use crate::vec3::Vec3;

fn grid(n: usize) -> Vec<(u32, SphereGeom)> {
    (0..n)
        .map(|i| {
            let c = Vec3::new((i % 37) as f64, ((i / 37) % 11) as f64, (i / 407) as f64);
            (i as u32, SphereGeom::new(c, 0.3))
        })
        .collect()
}

/// The leaves' child references, by walking the tree from the root.
fn leaves(bvh: &Bvh) -> Vec<u32> {
    let mut out = Vec::new();
    let mut todo = vec![0u32];
    while let Some(n) = todo.pop() {
        for &c in &bvh.nodes[n as usize].children {
            if c == EMPTY {
                continue;
            }
            if c & LEAF_BIT != 0 {
                out.push(c);
            } else {
                todo.push(c);
            }
        }
    }
    out
}

#[test]
fn every_sphere_is_in_exactly_one_leaf() {
    for n in [1, 2, 3, 4, 5, 9, 17, 100, 1000, 20_000] {
        let bvh = Bvh::build(&grid(n), Isa::best()).unwrap();
        let leaves = leaves(&bvh);
        assert!(leaves.iter().all(|&l| bvh.leaf(l).len() <= LEAF_SIZE));
        let mut seen: Vec<u32> = leaves
            .iter()
            .flat_map(|&l| bvh.leaf(l).iter().map(|&(i, _)| i))
            .collect();
        seen.sort_unstable();
        assert_eq!(seen, (0..n as u32).collect::<Vec<_>>(), "{n} spheres");
        assert!(bvh.node_count() >= 1);
    }
}

#[test]
fn a_parallel_build_equals_the_sequential_one() {
    let spheres = grid(50_000);
    let one = Bvh::build(&spheres, Isa::best()).unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let two = pool.install(|| Bvh::build(&spheres, Isa::best()).unwrap());
    let order = |b: &Bvh| b.spheres.iter().map(|s| s.0).collect::<Vec<_>>();
    assert_eq!(order(&one), order(&two));
    assert_eq!(one.node_count(), two.node_count());
}

#[test]
fn coincident_spheres_build_a_shallow_tree() {
    let same: Vec<(u32, SphereGeom)> = (0..10_000)
        .map(|i| (i, SphereGeom::new(Vec3::ZERO, 1.0)))
        .collect();
    let bvh = Bvh::build(&same, Isa::best()).unwrap();
    let mut stack = Stack::new();
    let mut best = (f64::INFINITY, u32::MAX);
    let dir = Vec3::new(0.0, 0.0, 1.0);
    bvh.nearest(
        Vec3::new(0.0, 0.0, -5.0),
        dir,
        u32::MAX,
        &mut best,
        &mut stack,
    )
    .expect("the median splits keep the tree shallow");
    assert_eq!(best, (4.0, 0));
}

#[test]
fn scenes_beyond_the_margin_argument_get_no_hierarchy() {
    assert!(Bvh::build(
        &[(0, SphereGeom::new(Vec3::new(1e200, 0.0, 0.0), 1.0))],
        Isa::best()
    )
    .is_none());
    assert!(Bvh::build(
        &[(0, SphereGeom::new(Vec3::new(2e30, 0.0, 0.0), 1.0))],
        Isa::best()
    )
    .is_none());
    assert!(Bvh::build(&[], Isa::best()).is_none());
}

#[test]
fn rounding_to_f32_is_outward() {
    for x in [
        0.1,
        -0.1,
        1e-40,
        -1e-40,
        1e30,
        -1e30,
        0.0,
        16_777_217.0,
        1e5 + 1e-3,
    ] {
        assert!(f64::from(down32(x)) <= x && f64::from(up32(x)) >= x, "{x}");
        assert!(f64::from(down32(x).next_up()) > x || f64::from(down32(x)) == x);
    }
    assert_eq!(up32(f64::INFINITY), f32::INFINITY);
}

/// The branch-free rounding equals the least `f32` not below `x`.
#[test]
fn rounding_up_is_the_least_f32_not_below() {
    let reference = |x: f64| {
        let f = x as f32;
        if f64::from(f) < x {
            f.next_up()
        } else {
            f
        }
    };
    let mut rng = Mix::seeded(4);
    let mut cases = vec![
        0.0,
        -0.0,
        1e-46,
        -1e-46,
        f64::from(f32::MAX) * (1.0 + 1e-9),
        -f64::from(f32::MAX) * (1.0 + 1e-9),
        1e39,
        -1e39,
        f64::INFINITY,
        f64::NEG_INFINITY,
    ];
    for _ in 0..200_000 {
        let exponent = (rng.next() % 320) as i32 - 160;
        cases.push(rng.unit() * 2f64.powi(exponent));
        let f = f32::from_bits(rng.next() as u32);
        if !f.is_nan() {
            cases.extend([f64::from(f), f64::from(f) * (1.0 + 1e-12)]);
        }
    }
    for x in cases {
        assert_eq!(up32(x).to_bits(), reference(x).to_bits(), "{x:e}");
        assert_eq!(down32(x).to_bits(), (-reference(-x)).to_bits(), "{x:e}");
    }
}

use crate::geometry::tests::Mix;

/// The nearest hit and some occluder within `limit` by the brute-force loop, and by
/// the hierarchy (portable and, where there is AVX2, vector box tests): equal.
///
/// The brute-force loop runs once for each ray (the ray, and the packet's lanes
/// below): the spheres it meets and where, in the spheres' order, from which every
/// expected answer is read.
fn check(bvh: &mut Bvh, spheres: &[(u32, SphereGeom)], origin: Vec3, dir: Vec3, limit: f64) {
    let meets = |origin: Vec3, dir: Vec3| -> Vec<(f64, u32)> {
        spheres
            .iter()
            .filter_map(|&(i, ref s)| s.hit(origin, dir, false).map(|t| (t, i)))
            .collect()
    };
    let met = meets(origin, dir);
    let mut brute = (f64::INFINITY, u32::MAX);
    for &(t, i) in &met {
        consider(&mut brute, t, i);
    }
    let blocked = met.iter().any(|&(t, _)| t < limit);
    let mut stack = Stack::new();
    let built_for = bvh.isa;
    for isa in [Isa::Portable, Isa::best()] {
        bvh.isa = isa;
        let mut best = (f64::INFINITY, u32::MAX);
        bvh.nearest(origin, dir, u32::MAX, &mut best, &mut stack)
            .unwrap_or_else(|_| panic!("{origin:?} {dir:?}: out of range"));
        assert!(
            best.0.to_bits() == brute.0.to_bits() && best.1 == brute.1,
            "{isa:?} {origin:?} {dir:?}: {best:?} vs {brute:?}"
        );
        let occluder = bvh
            .occluder(origin, dir, u32::MAX, limit, &mut stack)
            .expect("within range");
        assert_eq!(
            occluder.is_some(),
            blocked,
            "{isa:?} {origin:?} {dir:?} {limit}"
        );
        // The packet traversal, lane by lane the same answers: the ray, the ray
        // reversed, an inactive lane holding a ray out of range, and the ray with
        // half its limit (ties with the single-ray answers; lanes parting ways).
        let origins = [origin, origin, Vec3::new(1e31, 0.0, 0.0), origin];
        let dirs = [dir, -dir, Vec3::ZERO, dir];
        let limits = [limit, limit, f64::NAN, limit * 0.5];
        let masks = [0b1011, 0b0001, 0b1000];
        // What each lane's ray meets, for the lanes some mask turns on.
        let lane_met: [Vec<(f64, u32)>; 4] = std::array::from_fn(|k| {
            if masks.iter().any(|m| m & (1 << k) != 0) {
                meets(origins[k], dirs[k])
            } else {
                Vec::new()
            }
        });
        for lanes in masks {
            // Nearest hits: lane 3 starts from a best hit found elsewhere, at the
            // brute-force distance with a higher or lower index (a tie either way).
            let seed = [
                (f64::INFINITY, u32::MAX),
                (f64::INFINITY, u32::MAX),
                (1.0, 7),
                (brute.0, if brute.1 % 2 == 0 { 0 } else { u32::MAX - 1 }),
            ];
            let mut best4 = seed;
            let rest = bvh.nearests(&origins, &dirs, u32::MAX, &mut best4, lanes, &mut stack);
            assert_eq!(rest, 0, "{isa:?} {origin:?} {dir:?}: out of range");
            for k in 0..4 {
                let mut expected = seed[k];
                if lanes & (1 << k) != 0 {
                    for &(t, i) in &lane_met[k] {
                        consider(&mut expected, t, i);
                    }
                }
                assert!(
                    best4[k].0.to_bits() == expected.0.to_bits() && best4[k].1 == expected.1,
                    "{isa:?} lane {k} of {lanes:b}: {origin:?} {dir:?}: {:?} vs {expected:?}",
                    best4[k]
                );
            }
            let (hit, rest) =
                bvh.occluders(&origins, &dirs, &[u32::MAX; 4], &limits, lanes, &mut stack);
            assert_eq!(rest, 0, "{isa:?} {origin:?} {dir:?}: out of range");
            for k in 0..4 {
                let expected =
                    lanes & (1 << k) != 0 && lane_met[k].iter().any(|&(t, _)| t < limits[k]);
                assert_eq!(
                    hit & (1 << k) != 0,
                    expected,
                    "{isa:?} lane {k} of {lanes:b}: {origin:?} {dir:?} {limit}"
                );
            }
            // Each lane leaving its own sphere, as the shadow rays of hits on
            // different spheres do: lane 0 the sphere the ray meets first (not
            // tested for that lane alone), lane 3 none, with its limit exactly at
            // the nearest hit (a tie, which does not block). The same answers as
            // the brute-force loop and as one ray at a time.
            let froms = [brute.1, u32::MAX, 0, u32::MAX];
            let limits = [limit, limit, f64::NAN, brute.0];
            let (hit, rest) = bvh.occluders(&origins, &dirs, &froms, &limits, lanes, &mut stack);
            assert_eq!(rest, 0, "{isa:?} {origin:?} {dir:?}: out of range");
            for k in 0..4 {
                let expected = lanes & (1 << k) != 0
                    && lane_met[k]
                        .iter()
                        .any(|&(t, i)| i != froms[k] && t < limits[k]);
                assert_eq!(
                    hit & (1 << k) != 0,
                    expected,
                    "{isa:?} lane {k} of {lanes:b} from {}: {origin:?} {dir:?} {limit}",
                    froms[k]
                );
                if lanes & (1 << k) != 0 {
                    let alone = bvh
                        .occluder(origins[k], dirs[k], froms[k], limits[k], &mut stack)
                        .expect("within range");
                    assert_eq!(alone.is_some(), expected, "{isa:?} lane {k} alone");
                }
            }
        }
    }
    bvh.isa = built_for;
}

/// Rays aimed at a sphere's silhouette (a relative 10⁻⁹ inside or outside), at its
/// box's corners and along the axes through them, from `origin`s near `scale`.
fn grazing(rng: &mut Mix, spheres: &[(u32, SphereGeom)], far: f64, rays: usize) {
    let mut bvh = Bvh::build(spheres, Isa::best()).unwrap();
    for case in 0..rays {
        let (_, s) = spheres[(rng.next() % spheres.len() as u64) as usize];
        let origin = s.center + rng.vec() * far;
        let aim = match case % 3 {
            0 => s.center + rng.vec().normalize() * (s.radius * (1.0 + rng.unit() * 1e-9)),
            1 => {
                let corner = |r: &mut Mix| if r.unit() < 0.0 { -s.radius } else { s.radius };
                s.center + Vec3::new(corner(rng), corner(rng), corner(rng))
            }
            _ => s.center + rng.vec() * (2.0 * s.radius),
        };
        let mut dir = (aim - origin).normalize();
        if case % 7 == 0 {
            // Along an axis, exactly, through the sphere's silhouette.
            let axis = (rng.next() % 3) as usize;
            let mut o = [s.center.x, s.center.y, s.center.z];
            let mut d = [0.0; 3];
            d[axis] = if rng.unit() < 0.0 { -1.0 } else { 1.0 };
            o[axis] -= d[axis] * far;
            let side = (axis + 1) % 3;
            o[side] += s.radius * (1.0 + rng.unit() * 1e-12);
            let origin = Vec3::new(o[0], o[1], o[2]);
            dir = Vec3::new(d[0], d[1], d[2]);
            check(&mut bvh, spheres, origin, dir, f64::INFINITY);
            continue;
        }
        let limit = [f64::INFINITY, far, far * 0.5][case % 3];
        check(&mut bvh, spheres, origin, dir, limit);
    }
}

fn soup(rng: &mut Mix, n: usize, at: f64, spread: f64, radius: f64) -> Vec<(u32, SphereGeom)> {
    (0..n)
        .map(|i| {
            let c = Vec3::new(at, -at, at * 0.5) + rng.vec() * spread;
            (
                i as u32,
                SphereGeom::new(c, radius * (1.0 + rng.unit().abs())),
            )
        })
        .collect()
}

#[test]
fn grazing_rays_at_unit_scale() {
    let mut rng = Mix::seeded(1);
    let spheres = soup(&mut rng, 2000, 0.0, 10.0, 0.1);
    grazing(&mut rng, &spheres, 20.0, 20_000);
}

/// Spheres at 10⁵ with radius 10⁻³: f32 spacing there is ~0.008, larger than the
/// spheres, so rounding the origin and the boxes to f32 matters. Seen from about
/// their own spread, and (below) from within a hundredth of it, as two tests that
/// run side by side: each takes seconds, as the margin at 10⁵ makes a ray enter
/// most boxes.
#[test]
fn tiny_spheres_far_from_the_origin() {
    let mut rng = Mix::seeded(2);
    let spheres = soup(&mut rng, 3000, 1e5, 0.5, 1e-3);
    grazing(&mut rng, &spheres, 1.0, 20_000);
}

#[test]
fn tiny_spheres_far_from_the_origin_seen_from_close_by() {
    let spheres = soup(&mut Mix::seeded(2), 3000, 1e5, 0.5, 1e-3);
    grazing(&mut Mix::seeded(7), &spheres, 1e-2, 20_000);
}

#[test]
fn huge_and_tiny_coordinates() {
    for (at, spread, radius, far) in [
        (1e28f64, 1e26, 1e24, 1e27),
        (1e-20, 1e-22, 1e-25, 1e-21),
        (0.0, 1e-30, 1e-33, 1e-30),
        (3.0, 1e-6, 1e-9, 1e-7),
    ] {
        let mut rng = Mix::seeded(at.to_bits());
        let spheres = soup(&mut rng, 500, at, spread, radius);
        grazing(&mut rng, &spheres, far, 5000);
    }
}

#[test]
fn origins_on_box_sides_and_zero_direction_components() {
    // Spheres on a lattice of f32-exact coordinates, rays from their box planes.
    let spheres: Vec<(u32, SphereGeom)> = (0..512)
        .map(|i| {
            let c = Vec3::new((i % 8) as f64, ((i / 8) % 8) as f64, (i / 64) as f64);
            (i as u32, SphereGeom::new(c, 0.5))
        })
        .collect();
    let mut bvh = Bvh::build(&spheres, Isa::best()).unwrap();
    let mut rng = Mix::seeded(3);
    for _ in 0..20_000 {
        let pick = |r: &mut Mix| ((r.next() % 17) as f64 - 4.0) * 0.5;
        let origin = Vec3::new(pick(&mut rng), pick(&mut rng), pick(&mut rng));
        let mut d = [rng.unit(), rng.unit(), rng.unit()];
        for c in &mut d {
            match rng.next() % 4 {
                0 => *c = 0.0,
                1 => *c = -0.0,
                2 => {
                    *c *= if rng.next().is_multiple_of(2) {
                        1e-30
                    } else {
                        1e-300
                    }
                }
                _ => {}
            }
        }
        let dir = Vec3::new(d[0], d[1], d[2]);
        if dir.dot(dir) < 1e-6 {
            continue;
        }
        check(&mut bvh, &spheres, origin, dir.normalize(), f64::INFINITY);
    }
}
