//! Where the bounding volume hierarchy starts to pay: frames of n spheres rendered by
//! testing every sphere and through a (forced) hierarchy, for n from 1 to 64, with one
//! sample per pixel and with four (camera rays traced as packets of four either way;
//! the hierarchy is traversed ray by ray), in two layouts:
//!
//! - `cluster`: spheres of radius 0.4 to 1 packed around the origin and filling the
//!   view, over a plane, like the example scenes;
//! - `spread`: small spheres (radius 0.05 to 0.09) scattered over a 20 × 20 plane.
//!
//! It prints one line per n with both times and their ratio; the tracer's thresholds
//! (`BVH_MIN_SPHERES` for aa 1, `BVH_MIN_SPHERES_PACKETS` for aa ≥ 2, in
//! `src/tracer/prepare.rs`) are the smallest n from which the hierarchy is at least as
//! fast in both layouts. Frames are 600 × 400, rendered on the bench's thread and timed
//! by that thread's CPU time (best of several alternating runs), which a busy machine
//! disturbs far less than wall-clock time.

use std::hint::black_box;
use std::time::{Duration, Instant};

use render::{
    render_tile, CameraSpec, Light, Material, Object, Rect, RenderSettings, Scene, Shape, Tracer,
    Vec3,
};

const COUNTS: [usize; 13] = [1, 2, 4, 6, 8, 10, 12, 16, 20, 24, 32, 48, 64];
/// Frames rendered per timing: the scheduler's statistics advance in ticks.
const FRAMES_PER_TIMING: u32 = 3;

/// SplitMix64.
fn hash(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A number in [-1, 1) from a hash.
fn signed(h: u64) -> f64 {
    2.0 * ((h >> 11) as f64 / (1u64 << 53) as f64) - 1.0
}

fn scene(n: usize, spread: bool, aa: u32) -> Scene {
    let mut objects = vec![Object {
        shape: Shape::Plane {
            normal: Vec3::new(0.0, 1.0, 0.0),
            distance: -1.0,
        },
        color: Vec3::new(0.5, 0.5, 0.5),
        material: Material::Checker,
    }];
    for k in 0..n {
        let h = |salt: u64| hash((k as u64) << 8 | salt);
        let (center, radius) = if spread {
            let r = 0.07 + 0.02 * signed(h(0));
            (
                Vec3::new(10.0 * signed(h(1)), r - 1.0, 10.0 * signed(h(2))),
                r,
            )
        } else {
            let r = 0.7 + 0.3 * signed(h(0));
            (
                Vec3::new(2.5 * signed(h(1)), 1.5 * signed(h(2)), 2.5 * signed(h(3))),
                r,
            )
        };
        objects.push(Object {
            shape: Shape::Sphere { center, radius },
            color: Vec3::new(0.6, 0.5 + 0.4 * signed(h(4)), 0.4),
            material: if k % 3 == 0 {
                Material::Reflective(0.4)
            } else {
                Material::Matte
            },
        });
    }
    Scene {
        lights: vec![
            Light {
                position: Vec3::new(-7.0, 10.0, -10.0),
                color: Vec3::new(1.0, 1.0, 1.0),
            },
            Light {
                position: Vec3::new(7.0, 10.0, 10.0),
                color: Vec3::new(0.5, 0.5, 0.5),
            },
        ],
        objects,
        camera: if spread {
            CameraSpec {
                position: Vec3::new(0.0, 11.0, -22.0),
                look_at: Vec3::new(0.0, -1.0, 0.5),
                ..CameraSpec::default()
            }
        } else {
            CameraSpec {
                position: Vec3::new(3.0, 2.5, -8.0),
                look_at: Vec3::ZERO,
                ..CameraSpec::default()
            }
        },
        settings: RenderSettings {
            width: 600,
            height: 400,
            aa,
            ..RenderSettings::default()
        },
        ambient: 0.2,
    }
}

/// The CPU time this thread has run, from Linux's scheduler statistics, so that other
/// processes on a shared machine do not count; elsewhere the wall-clock time.
fn thread_time(since: Instant) -> Duration {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse().ok())
        .map_or_else(|| since.elapsed(), Duration::from_nanos)
}

/// Best-of-`runs` frame times without and with the hierarchy, measured alternately on
/// this thread.
fn times(scene: &Scene, runs: usize) -> (Duration, Duration) {
    let brute = Tracer::with_bvh(scene, scene.settings, false);
    let bvh = Tracer::with_bvh(scene, scene.settings, true);
    let frame = Rect {
        x: 0,
        y: 0,
        width: scene.settings.width,
        height: scene.settings.height,
    };
    let epoch = Instant::now();
    // Several frames per timing: the scheduler's statistics advance in ticks.
    let time = |t: &Tracer| {
        let start = thread_time(epoch);
        for _ in 0..FRAMES_PER_TIMING {
            black_box(render_tile(t, frame).expect("the frame is inside itself"));
        }
        (thread_time(epoch) - start) / FRAMES_PER_TIMING
    };
    let (mut a, mut b) = (Duration::MAX, Duration::MAX);
    for _ in 0..runs {
        a = a.min(time(&brute));
        b = b.min(time(&bvh));
    }
    (a, b)
}

fn main() {
    let flag = |f: &str| std::env::args().any(|a| a == f);
    if flag("--list") {
        return;
    }
    // `cargo test --benches` only checks that it runs, on a few counts.
    let bench = flag("--bench") && !flag("--test");
    let (runs, counts) = if bench {
        (7, &COUNTS[..])
    } else {
        (1, &COUNTS[..2])
    };
    for aa in [1, 2] {
        for spread in [false, true] {
            let layout = if spread { "spread" } else { "cluster" };
            for &n in counts {
                let (brute, bvh) = times(&scene(n, spread, aa), runs);
                println!(
                    "aa {aa} {layout:7} {n:3} spheres: every sphere {brute:9.3?}, hierarchy \
                     {bvh:9.3?}, hierarchy / every sphere = {:.2}",
                    bvh.as_secs_f64() / brute.as_secs_f64()
                );
            }
        }
    }
}
