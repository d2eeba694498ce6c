//! The seed frame (600 × 400, aa 2) on one thread, two ways in one run: through
//! `render_frame` (the sampler, which also keeps per-pixel statistics for its error
//! estimate, as `seed_frame` measures it) and through the tracer alone, row by row with
//! `Tracer::pixel_span` (the same spans of grid samples, each pixel's mean converted to
//! bytes, no statistics and no tiles). The difference is what the sampler and the
//! tiling add; the tracer's own time is the second figure.

use std::hint::black_box;
use std::time::{Duration, Instant};

use rayon::ThreadPoolBuilder;
use render::{parse_scene, render_frame, RenderSettings, Tracer, DEFAULT_TILE_SIZE};

const SEED_SCENE: &str = include_str!("../../scenes/seed.json");

fn main() {
    let flag = |f: &str| std::env::args().any(|a| a == f);
    if flag("--list") {
        return;
    }
    // `cargo test --benches` only checks that it runs.
    let runs = if flag("--bench") && !flag("--test") {
        9
    } else {
        1
    };
    let scene = parse_scene(SEED_SCENE).expect("scenes/seed.json is a valid scene");
    let settings = RenderSettings {
        width: 600,
        height: 400,
        aa: 2,
        ..scene.settings
    };
    let tracer = Tracer::new(&scene, settings);
    let pool = ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("building a rayon pool");
    let frame = || pool.install(|| render_frame(&tracer, DEFAULT_TILE_SIZE, &|_| {}));
    let pixels = || {
        let mut rays = 0;
        let mut rgb = Vec::with_capacity(600 * 400 * 3);
        for j in 0..settings.height {
            tracer.pixel_span(j, 0..settings.width, &mut rays, &mut rgb);
        }
        rgb
    };
    assert!(
        frame().image.rgb == pixels(),
        "both ways give the same image"
    );
    let time = |f: &dyn Fn()| {
        let start = Instant::now();
        f();
        start.elapsed()
    };
    let (mut sampler, mut alone) = (Duration::MAX, Duration::MAX);
    for _ in 0..runs {
        sampler = sampler.min(time(&|| {
            black_box(frame());
        }));
        alone = alone.min(time(&|| {
            black_box(pixels());
        }));
    }
    println!(
        "seed 600x400 aa 2, 1 thread, best of {runs}: render_frame {sampler:.3?}, \
         Tracer::pixel_span for every row {alone:.3?}"
    );
}
