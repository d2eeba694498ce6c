//! Frame time against object count: a 600 × 400, aa 1 frame of 10 small spheres over a
//! plane and the same frame with 10,000 of them, on one thread. With the bounding volume
//! hierarchy the second may take at most four times the first (the requirement), where
//! testing every sphere for every ray would take about a thousand times as long.
//!
//! The scenes are deterministic: spheres of radius 0.05 to 0.09 on a 100 × 100 grid
//! (spacing 0.2) over the checkerboard plane y = 0, jittered by a fixed-seed hash; the
//! 10-sphere scene takes the grid's first 10 spheres in a hashed order, spread over the
//! same area. Two lights; the camera sees the whole grid.

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, SamplingMode, Throughput};
use rayon::{ThreadPool, ThreadPoolBuilder};
use render::{
    render_frame, CameraSpec, Frame, Light, Material, Object, RenderSettings, Scene, Shape, Tracer,
    Vec3, DEFAULT_TILE_SIZE,
};

/// Spheres per side of the grid: 100 × 100 = 10,000.
const GRID: usize = 100;
const SPACING: f64 = 0.2;

/// SplitMix64: a fixed-seed hash of a sphere's grid index.
fn hash(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A number in [0, 1) from a hash.
fn unit(h: u64) -> f64 {
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// Sphere `k` of the grid: jittered centre, radius 0.05 to 0.09, resting on the plane.
fn grid_sphere(k: usize) -> Object {
    let h = hash(k as u64);
    let (i, j) = ((k % GRID) as f64, (k / GRID) as f64);
    let half = (GRID as f64 - 1.0) * SPACING / 2.0;
    let jitter = |bits: u64| (unit(hash(bits)) - 0.5) * 0.05;
    let radius = 0.05 + 0.04 * unit(h);
    let center = Vec3::new(
        i * SPACING - half + jitter(h),
        radius,
        j * SPACING - half + jitter(h ^ 0x5555),
    );
    let color = Vec3::new(
        0.3 + 0.7 * unit(hash(h ^ 1)),
        0.3 + 0.7 * unit(hash(h ^ 2)),
        0.3 + 0.7 * unit(hash(h ^ 3)),
    );
    Object {
        shape: Shape::Sphere { center, radius },
        color,
        material: Material::Matte,
    }
}

/// The scene with `count` spheres of the grid (all of it for 10,000).
fn scene(count: usize) -> Scene {
    let mut order: Vec<usize> = (0..GRID * GRID).collect();
    if count < order.len() {
        // Spread the few spheres over the whole grid: take them in a hashed order.
        order.sort_by_key(|&k| hash(k as u64 ^ 0xABCD));
        order.truncate(count);
    }
    let mut objects = vec![Object {
        shape: Shape::Plane {
            normal: Vec3::new(0.0, 1.0, 0.0),
            distance: 0.0,
        },
        color: Vec3::new(0.5, 0.5, 0.5),
        material: Material::Checker,
    }];
    objects.extend(order.into_iter().map(grid_sphere));
    Scene {
        lights: vec![
            Light {
                position: Vec3::new(-8.0, 12.0, -10.0),
                color: Vec3::new(0.9, 0.9, 0.9),
            },
            Light {
                position: Vec3::new(9.0, 7.0, -4.0),
                color: Vec3::new(0.4, 0.4, 0.5),
            },
        ],
        objects,
        camera: CameraSpec {
            position: Vec3::new(0.0, 12.0, -22.0),
            look_at: Vec3::new(0.0, 0.0, 0.5),
            ..CameraSpec::default()
        },
        settings: RenderSettings {
            width: 600,
            height: 400,
            aa: 1,
            ..RenderSettings::default()
        },
        ambient: 0.2,
    }
}

struct Setup {
    few: Tracer,
    many: Tracer,
    pool: ThreadPool,
}

impl Setup {
    fn new() -> Self {
        let tracer = |count| {
            let s = scene(count);
            Tracer::new(&s, s.settings)
        };
        Setup {
            few: tracer(10),
            many: tracer(GRID * GRID),
            pool: ThreadPoolBuilder::new()
                .num_threads(1)
                .build()
                .expect("building a rayon pool"),
        }
    }

    fn frame(&self, tracer: &Tracer) -> Frame {
        self.pool
            .install(|| render_frame(tracer, DEFAULT_TILE_SIZE, &|_| {}))
    }
}

fn bench(c: &mut Criterion, setup: &Setup) {
    let mut group = c.benchmark_group("spheres_600x400_aa1_1_thread");
    group
        .sample_size(10)
        .sampling_mode(SamplingMode::Flat)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(3))
        .throughput(Throughput::Elements(600 * 400));
    group.bench_function("10_spheres", |b| b.iter(|| setup.frame(&setup.few)));
    group.bench_function("10000_spheres", |b| b.iter(|| setup.frame(&setup.many)));
    group.finish();
}

/// The shortest of `runs` timings of `f`.
fn best_of<T>(runs: usize, mut f: impl FnMut() -> T) -> Duration {
    (0..runs)
        .map(|_| {
            let start = Instant::now();
            black_box(f());
            start.elapsed()
        })
        .min()
        .expect("at least one run")
}

/// What the 10,000-sphere frame would cost testing every sphere for every ray,
/// extrapolated from every 20th row (the whole frame takes tens of seconds).
fn brute_force_estimate() -> Duration {
    let s = scene(GRID * GRID);
    let tracer = Tracer::with_bvh(&s, s.settings, false);
    let start = Instant::now();
    let mut rays = 0;
    for j in (0..s.settings.height).step_by(20) {
        for i in 0..s.settings.width {
            black_box(tracer.pixel(i, j, &mut rays));
        }
    }
    start.elapsed() * 20
}

/// One line with the ratio, from best-of-7 timings taken alternately.
fn print_ratio(setup: &Setup) {
    const RUNS: usize = 7;
    let (mut few, mut many) = (Duration::MAX, Duration::MAX);
    for _ in 0..RUNS {
        few = few.min(best_of(1, || setup.frame(&setup.few)));
        many = many.min(best_of(1, || setup.frame(&setup.many)));
    }
    println!(
        "best of {RUNS}, 1 thread: 10 spheres {few:.3?} (hierarchy: {}), 10,000 spheres \
         {many:.3?} (hierarchy: {}); 10,000 / 10 = {:.2}",
        setup.few.uses_bvh(),
        setup.many.uses_bvh(),
        many.as_secs_f64() / few.as_secs_f64(),
    );
    println!(
        "10,000 spheres testing every sphere instead (estimated from every 20th row): {:.1?}",
        brute_force_estimate()
    );
}

fn main() {
    let mut criterion = Criterion::default().configure_from_args();
    let setup = Setup::new();
    let rays = |t: &Tracer| setup.frame(t).rays;
    println!(
        "rays per frame: 10 spheres {}, 10,000 spheres {}",
        rays(&setup.few),
        rays(&setup.many)
    );
    bench(&mut criterion, &setup);
    criterion.final_summary();
    let flag = |f: &str| std::env::args().any(|a| a == f);
    if flag("--bench") && !flag("--test") && !flag("--list") {
        print_ratio(&setup);
    }
}
