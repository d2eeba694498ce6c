//! The seed's own measurement (report section 4): the seed scene at 600 × 400 with
//! antialiasing depth 2, rendered by a transcription of the seed program's structure
//! (the baseline, single-threaded like each of the seed's MPI processes) and by
//! Tessera on one thread and on every available thread.
//!
//! Throughput is counted in Tessera's rays per frame for all three, so that criterion's
//! rays/s figures compare frame times directly.

mod seed_structured;

use std::hint::black_box;
use std::num::NonZeroUsize;
use std::thread;
use std::time::{Duration, Instant};

use criterion::{Criterion, SamplingMode, Throughput};
use rayon::{ThreadPool, ThreadPoolBuilder};
use render::{parse_scene, render_frame, Frame, RenderSettings, Tracer, DEFAULT_TILE_SIZE};

use seed_structured::SeedScene;

const SEED_SCENE: &str = include_str!("../../scenes/seed.json");

/// The baseline may differ from Tessera only at silhouette and shadow-edge samples,
/// where its epsilon and quadratic round differently: at most this fraction of the
/// channels may differ by more than [`LEVEL_TOLERANCE`].
const MAX_DIFFERING_FRACTION: f64 = 0.02;
const LEVEL_TOLERANCE: u8 = 2;

/// Everything the benchmarks share, built once.
struct Setup {
    tracer: Tracer,
    baseline: SeedScene,
    one_thread: ThreadPool,
    all_threads: ThreadPool,
    threads: usize,
    /// Rays Tessera traces for one frame.
    rays: u64,
}

impl Setup {
    fn new() -> Self {
        let scene = parse_scene(SEED_SCENE).expect("scenes/seed.json is a valid scene");
        let settings = RenderSettings {
            width: 600,
            height: 400,
            aa: 2,
            ..scene.settings
        };
        let threads = thread::available_parallelism().map_or(1, NonZeroUsize::get);
        let pool = |n| {
            ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .expect("building a rayon pool")
        };
        let mut setup = Setup {
            tracer: Tracer::new(&scene, settings),
            baseline: SeedScene::new(&scene, settings),
            one_thread: pool(1),
            all_threads: pool(threads),
            threads,
            rays: 0,
        };
        let frame = setup.tessera(&setup.one_thread);
        setup.check_baseline(&frame.image.rgb);
        setup.rays = frame.rays;
        println!("tessera traces {} rays per frame", setup.rays);
        setup
    }

    fn tessera(&self, pool: &ThreadPool) -> Frame {
        // Borrow only the tracer: the single-threaded baseline's trait objects are not
        // `Sync`, so `self` cannot cross into the pool.
        let tracer = &self.tracer;
        pool.install(|| render_frame(tracer, DEFAULT_TILE_SIZE, &|_| {}))
    }

    /// Asserts that the baseline renders the image Tessera renders, so that the
    /// comparison is between two programs doing the same work.
    fn check_baseline(&self, tessera: &[u8]) {
        let baseline = self.baseline.render();
        assert_eq!(baseline.len(), tessera.len(), "image sizes differ");
        let diffs = || baseline.iter().zip(tessera).map(|(&a, &b)| a.abs_diff(b));
        let differing = diffs().filter(|&d| d > LEVEL_TOLERANCE).count();
        let max = diffs().max().unwrap_or(0);
        let fraction = differing as f64 / tessera.len() as f64;
        println!(
            "seed_structured vs tessera: {differing} of {} channels ({:.3}%) differ by more \
             than {LEVEL_TOLERANCE} levels, {} differ at all, max difference {max}",
            tessera.len(),
            fraction * 100.0,
            diffs().filter(|&d| d > 0).count(),
        );
        assert!(
            fraction < MAX_DIFFERING_FRACTION,
            "the baseline's image is not Tessera's: {:.3}% of channels differ by more than \
             {LEVEL_TOLERANCE} levels",
            fraction * 100.0
        );
    }
}

fn bench_seed_frame(c: &mut Criterion, setup: &Setup) {
    let mut group = c.benchmark_group("seed_600x400_aa2");
    // Frames take tenths of a second: flat sampling keeps ten samples affordable.
    group
        .sample_size(10)
        .sampling_mode(SamplingMode::Flat)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(3))
        .throughput(Throughput::Elements(setup.rays));
    group.bench_function("seed_structured_1_thread", |b| {
        b.iter(|| setup.baseline.render())
    });
    group.bench_function("tessera_1_thread", |b| {
        b.iter(|| setup.tessera(&setup.one_thread))
    });
    group.bench_function("tessera_all_threads", |b| {
        b.iter(|| setup.tessera(&setup.all_threads))
    });
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

/// One line with the speed-up ratios, from simple best-of-5 timings.
fn print_ratios(setup: &Setup) {
    const RUNS: usize = 5;
    let baseline = best_of(RUNS, || setup.baseline.render());
    let one = best_of(RUNS, || setup.tessera(&setup.one_thread));
    let all = best_of(RUNS, || setup.tessera(&setup.all_threads));
    println!(
        "best of {RUNS}: seed_structured {baseline:.3?}, tessera_1_thread {one:.3?}, \
         tessera_all_threads ({} threads) {all:.3?}; seed_structured / tessera_1_thread = \
         {:.2}, tessera_1_thread / tessera_all_threads = {:.2}",
        setup.threads,
        baseline.as_secs_f64() / one.as_secs_f64(),
        one.as_secs_f64() / all.as_secs_f64(),
    );
}

fn main() {
    let mut criterion = Criterion::default().configure_from_args();
    let setup = Setup::new();
    bench_seed_frame(&mut criterion, &setup);
    criterion.final_summary();
    // Only a real benchmark run (`cargo bench`) is worth the extra timings, not
    // `cargo test --benches` nor `--list`.
    let flag = |f: &str| std::env::args().any(|a| a == f);
    if flag("--bench") && !flag("--test") && !flag("--list") {
        print_ratios(&setup);
    }
}
