//! Rendering on this machine: a scene, whole or from a saved state, on a local thread
//! pool, with a progress display on a terminal, the PNG written atomically and a
//! one-line summary: size, samples spent, estimated error, time. What `tessera render`
//! and `tessera refine FILE` share.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context, Result};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use render::adaptive::{meets, render_to_target, sample_cap, BlockState, Region, LAST_RUNG};
use render::{render_frame, RenderSettings, Sampling, Tracer, DEFAULT_TILE_SIZE};

use crate::output::{FileOutput, ImageOutput};
use crate::render_state;
use crate::report::{counted, sampling_summary};

/// The progress bar appears only after this long, so quick renders stay quiet.
const PROGRESS_DELAY: Duration = Duration::from_secs(1);

/// The local thread pool: `threads` threads, or one per core.
pub fn thread_pool(threads: Option<u32>) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads.map_or(0, |n| n as usize))
        .build()
        .context("cannot start the rendering threads")
}

/// One local render, from the command line or a saved state.
pub struct Job<'a> {
    pub scene: &'a render::Scene,
    /// What a render that saves its samples saves of the scene with them.
    pub source: Option<SceneSource<'a>>,
    pub settings: RenderSettings,
    /// Checked writable before the render starts.
    pub output: ImageOutput,
    /// Renders: `--threads` threads, one per core by default.
    pub pool: &'a rayon::ThreadPool,
    /// Stop adaptive sampling after about this long, at the best image reached.
    pub time_limit: Option<Duration>,
    /// Where the samples are saved: checked writable before the render starts, too.
    pub state: Option<FileOutput>,
    /// The saved blocks to go on from, and the file they came from.
    pub resume: Option<(PathBuf, Vec<BlockState>)>,
}

/// A scene as a saved render keeps it: its text, and where its mesh files are.
#[derive(Clone, Copy)]
pub struct SceneSource<'a> {
    pub text: &'a str,
    /// The directory the scene's mesh files were read from: absolute and canonical.
    pub mesh_dir: &'a Path,
}

impl Job<'_> {
    /// Renders, writes the image (and the samples, if saved) and prints the summary.
    pub fn run(self) -> Result<()> {
        let settings = self.settings;
        let pool = self.pool;
        // In the pool: a large scene's hierarchy is built in parallel, on `--threads` threads.
        let tracer = pool.install(|| Tracer::new(self.scene, settings));
        let started = Instant::now();
        // Until the image is made: saving the samples is not rendering.
        let elapsed;
        let sampling = settings.sampling;
        let (image, rays, samples, error, note) = match (sampling, sampling.target_error()) {
            (Sampling::Adaptive { target_milli }, Some(target)) => {
                let full = render::Rect {
                    x: 0,
                    y: 0,
                    width: settings.width,
                    height: settings.height,
                };
                let deadline = self.time_limit.map(|t| started + t);
                let progress = RungProgress::new();
                let (region, frame) = pool.install(|| -> Result<_> {
                    let region = match self.resume {
                        Some((path, blocks)) => Some(
                            Region::new(&tracer, Region::footprints(&tracer), full, Some(blocks))
                                .map_err(|e| anyhow!("{}: {e}", path.display()))?,
                        ),
                        None => None,
                    };
                    Ok(render_to_target(
                        &tracer,
                        region,
                        target,
                        &mut |k, totals| {
                            progress.show(k, totals.estimated_error());
                            deadline.is_none_or(|d| Instant::now() < d)
                        },
                    ))
                })?;
                progress.finish();
                elapsed = started.elapsed();
                let e = frame.estimated_error();
                let met = meets(&frame.totals, frame.rung, target);
                let capped = frame.rung >= LAST_RUNG && (e > target || e.is_nan());
                let note = if capped {
                    let cap = sample_cap(settings.aa);
                    let (at_cap, pixels) =
                        region
                            .blocks()
                            .iter()
                            .fold((0, 0), |(at_cap, pixels), block| {
                                let n = block.rect.pixel_count();
                                let full = block.levels.last().is_some_and(|l| l.count >= cap);
                                (at_cap + if full { n } else { 0 }, pixels + n)
                            });
                    cap_note(cap, at_cap, pixels)
                } else if !met && !settings.sampling.time_decides() {
                    "; stopped by the time limit before the target".to_owned()
                } else if !met {
                    format!("; as far as the time limit allowed (rung {})", frame.rung)
                } else {
                    String::new()
                };
                if let Some(out) = self.state {
                    let source = self
                        .source
                        .expect("a render that saves its samples keeps the scene's source");
                    let saved = render_state::Saved {
                        scene: source.text.to_owned(),
                        mesh_dir: source.mesh_dir.to_path_buf(),
                        meshes: render_state::meshes_of(self.scene),
                        width: settings.width,
                        height: settings.height,
                        aa: settings.aa,
                        max_depth: settings.max_depth,
                        target_milli,
                        rung: frame.rung,
                        blocks: region.into_blocks(),
                    };
                    render_state::save(out, &saved)?;
                }
                (
                    frame.image,
                    frame.totals.rays,
                    frame.totals.samples,
                    e,
                    note,
                )
            }
            _ => {
                let progress = DelayedProgress::new(settings.pixel_count());
                let frame = pool
                    .install(|| render_frame(&tracer, DEFAULT_TILE_SIZE, &|px| progress.add(px)));
                progress.finish();
                elapsed = started.elapsed();
                let e = frame.estimated_error();
                (frame.image, frame.rays, frame.samples, e, String::new())
            }
        };
        let output = self.output.path().to_path_buf();
        self.output.write(&image.to_png())?;
        let secs = elapsed.as_secs_f64();
        eprintln!(
            "{}: {}x{}, {}{note}, {:.3} s, {:.1} M rays/s ({})",
            output.display(),
            settings.width,
            settings.height,
            sampling_summary(&settings, samples, error.is_finite().then_some(error)),
            secs,
            rays as f64 / secs.max(1e-9) / 1e6,
            counted(pool.current_num_threads(), "thread"),
        );
        Ok(())
    }
}

/// What an adaptive render that reached its last rung above its target says of its
/// pixels: how many are at the cap of `cap` samples (`at_cap` of `pixels`). The others
/// met their last threshold with fewer, which is why the mean samples per pixel can be
/// well below the cap: "every pixel at its cap" only when every one is.
pub fn cap_note(cap: u32, at_cap: u64, pixels: u64) -> String {
    if at_cap >= pixels {
        return format!("; every pixel at its cap of {}", counted(cap, "sample"));
    }
    let share = 100.0 * at_cap as f64 / pixels.max(1) as f64;
    format!(
        "; the last rung reached with {share:.1} % of the pixels at the cap of {} (the others \
         below their threshold with fewer)",
        counted(cap, "sample")
    )
}

/// A spinner on stderr for adaptive renders, shown only on a terminal after
/// [`PROGRESS_DELAY`]: the rung reached and the estimated error falling.
struct RungProgress {
    bar: ProgressBar,
    started: Instant,
    interactive: bool,
    shown: AtomicBool,
}

impl RungProgress {
    fn new() -> Self {
        let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::hidden());
        bar.set_style(
            ProgressStyle::with_template("{spinner} [{elapsed_precise}] {msg}")
                .expect("the template is valid"),
        );
        RungProgress {
            bar,
            started: Instant::now(),
            interactive: std::io::stderr().is_terminal(),
            shown: AtomicBool::new(false),
        }
    }

    fn show(&self, rung: u32, error: f64) {
        self.bar
            .set_message(format!("rung {rung}, estimated error {error:.3} levels"));
        if self.interactive
            && self.started.elapsed() >= PROGRESS_DELAY
            && !self.shown.swap(true, Ordering::Relaxed)
        {
            self.bar.set_draw_target(ProgressDrawTarget::stderr());
        }
    }

    fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

/// A progress bar on stderr that shows itself only when stderr is a terminal and the
/// render has taken longer than [`PROGRESS_DELAY`].
struct DelayedProgress {
    bar: ProgressBar,
    started: Instant,
    interactive: bool,
    shown: AtomicBool,
}

impl DelayedProgress {
    fn new(total_pixels: u64) -> Self {
        let bar = ProgressBar::with_draw_target(Some(total_pixels), ProgressDrawTarget::hidden());
        bar.set_style(
            ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {wide_bar} {percent:>3}% {human_pos}/{human_len} px, {eta} left",
            )
            .expect("the template is valid"),
        );
        DelayedProgress {
            bar,
            started: Instant::now(),
            interactive: std::io::stderr().is_terminal(),
            shown: AtomicBool::new(false),
        }
    }

    fn add(&self, pixels: u64) {
        self.bar.inc(pixels);
        if self.interactive
            && self.started.elapsed() >= PROGRESS_DELAY
            && !self.shown.swap(true, Ordering::Relaxed)
        {
            self.bar.set_draw_target(ProgressDrawTarget::stderr());
        }
    }

    fn finish(&self) {
        self.bar.finish_and_clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cap_note_says_how_many_pixels_are_at_the_cap() {
        assert_eq!(
            cap_note(64, 100, 100),
            "; every pixel at its cap of 64 samples"
        );
        // 46.02 samples per pixel on average: not every pixel at 64.
        let note = cap_note(64, 6_902, 10_000);
        assert_eq!(
            note,
            "; the last rung reached with 69.0 % of the pixels at the cap of 64 samples \
             (the others below their threshold with fewer)"
        );
    }
}
