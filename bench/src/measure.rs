//! Timing a render: the same frame rendered until the measurement is long enough, the
//! fastest run kept (the least disturbed by whatever else the machine does).

use std::time::{Duration, Instant};

use render::{render_frame, Frame, RenderSettings, Scene, Tracer, DEFAULT_TILE_SIZE};

/// One setting's measurement.
pub struct Timed {
    /// The fastest run, in seconds.
    pub seconds: f64,
    pub frame: Frame,
}

/// Renders `scene` at `settings` on `pool` at least once and until `min_total` has
/// passed (at most `max_runs` times); keeps the fastest time.
pub fn time_frame(
    scene: &Scene,
    settings: RenderSettings,
    pool: &rayon::ThreadPool,
    min_total: Duration,
    max_runs: u32,
) -> Timed {
    let tracer = Tracer::new(scene, settings);
    let started = Instant::now();
    let mut best = f64::INFINITY;
    let mut runs = 0;
    let mut frame = None;
    while runs == 0 || (started.elapsed() < min_total && runs < max_runs) {
        let t = Instant::now();
        let f = pool.install(|| render_frame(&tracer, DEFAULT_TILE_SIZE, &|_| {}));
        best = best.min(t.elapsed().as_secs_f64());
        runs += 1;
        frame = Some(f);
    }
    Timed {
        seconds: best,
        frame: frame.expect("rendered at least once"),
    }
}

/// A rayon pool of `threads` threads.
pub fn pool(threads: usize) -> anyhow::Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| anyhow::anyhow!("cannot start {threads} rendering threads: {e}"))
}
