//! `tessera render`: load a scene, render it on a local thread pool, write the PNG
//! atomically and print a one-line summary: size, samples spent, estimated error, time.
//!
//! An animated scene renders its frame 1, or the frame `--frame K` names, or with
//! `--frames A-B` a sequence of frames into a directory, one file per frame, each
//! written atomically. Every choice is checked against the scene before anything is
//! rendered or written.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crate::output::{default_output, FileOutput, FramesDir, ImageOutput};
use crate::render_state;
use anyhow::{anyhow, bail, Context, Result};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use render::progressive::{meets, render_to_target, sample_cap, BlockState, Region, LAST_RUNG};
use render::{
    parse_animated, parse_scene, render_frame, validate_settings, AnimatedScene, RenderSettings,
    Sampling, Tracer, DEFAULT_TILE_SIZE,
};

/// What the user asked for; `None` keeps the scene's own value.
pub struct Options {
    /// Stop adaptive sampling after about this long, at the best image reached.
    pub time_limit: Option<Duration>,
    /// Save every sample taken (adaptive sampling) to this file, for `tessera refine`.
    pub state: Option<PathBuf>,
    pub scene: PathBuf,
    pub output: Option<PathBuf>,
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub aa: Option<u32>,
    pub max_depth: Option<u32>,
    /// `None`: the regular grid (a scene file never chooses a sampler).
    pub sampling: Option<Sampling>,
    pub threads: Option<u32>,
    /// `--frame K`: one frame of an animated scene (frame 1 when neither is given).
    pub frame: Option<u64>,
    /// `--frames RANGE`: a sequence of frames, into the directory `output`.
    pub frames: Option<FrameRange>,
}

/// Which frames `--frames` asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameRange {
    /// Every frame of the scene (`--frames` alone, or `--frames all`).
    All,
    /// Frames `first` to `last`, both included (`A-B`, or `K` for one).
    Span { first: u64, last: u64 },
}

/// Reads `--frames`: `A-B`, `K` or `all`, frame numbers from 1.
pub fn parse_frame_range(text: &str) -> std::result::Result<FrameRange, String> {
    if text == "all" {
        return Ok(FrameRange::All);
    }
    let number = |t: &str| -> std::result::Result<u64, String> {
        if t.is_empty() || !t.bytes().all(|b| b.is_ascii_digit()) {
            return Err(format!(
                "expected A-B, K or all (frame numbers from 1), got {text:?}"
            ));
        }
        let n = t
            .parse::<u64>()
            .map_err(|_| format!("frame {t} is too large"))?;
        if n == 0 {
            return Err("frames are numbered from 1".to_owned());
        }
        Ok(n)
    };
    let (first, last) = match text.split_once('-') {
        Some((a, b)) => (number(a)?, number(b)?),
        None => {
            let k = number(text)?;
            (k, k)
        }
    };
    if last < first {
        return Err(format!(
            "the range ends (frame {last}) before it starts (frame {first})"
        ));
    }
    Ok(FrameRange::Span { first, last })
}

/// Files from this size are read in parallel parts, one per thread of the pool.
const PARALLEL_READ_MIN: u64 = 16 << 20;

/// The scene file's text. A large file is read in as many parts as the current rayon
/// pool has threads, each copied from the page cache by its own thread: one thread
/// copying a 186 MB scene of a million spheres took as long as rendering it.
fn read_scene_file(path: &Path) -> std::io::Result<String> {
    use std::os::unix::fs::FileExt;
    let file = std::fs::File::open(path)?;
    let len = file.metadata()?.len();
    let threads = rayon::current_num_threads();
    if len < PARALLEL_READ_MIN || threads < 2 {
        return std::fs::read_to_string(path);
    }
    let len = usize::try_from(len).map_err(|_| std::io::ErrorKind::OutOfMemory)?;
    let mut bytes = vec![0u8; len];
    let part = len.div_ceil(threads);
    let mut parts: Vec<(usize, &mut [u8])> = bytes
        .chunks_mut(part)
        .enumerate()
        .map(|(i, chunk)| (i * part, chunk))
        .collect();
    use rayon::prelude::*;
    parts
        .par_iter_mut()
        .try_for_each(|(offset, chunk)| file.read_exact_at(chunk, *offset as u64))?;
    // Worded as `read_to_string` words it for a smaller file.
    String::from_utf8(bytes).map_err(|_| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "stream did not contain valid UTF-8",
        )
    })
}

/// The progress bar appears only after this long, so quick renders stay quiet.
const PROGRESS_DELAY: Duration = Duration::from_secs(1);

pub fn run(opts: Options) -> Result<()> {
    let scene_path = &opts.scene;
    if opts.state.is_some() && (opts.frame.is_some() || opts.frames.is_some()) {
        bail!("--state saves one render of a scene's frame 1: it cannot be used with --frame or --frames");
    }
    // The pool renders, and reads a large scene's file and objects first.
    let pool = thread_pool(opts.threads)?;
    let text = pool
        .install(|| read_scene_file(scene_path))
        .with_context(|| format!("cannot read scene file {}", scene_path.display()))?;
    let animated = pool
        .install(|| parse_animated(&text))
        .map_err(|e| anyhow!("{}: {e}", scene_path.display()))?;
    // Only a render that saves its samples needs the text again; otherwise it goes now,
    // before the tracer is built (a large scene's text is larger than the scene).
    let text = opts.state.is_some().then_some(text);

    // Image settings are not animated: the same for every frame.
    let mut settings = animated.base.settings;
    settings.width = opts.width.unwrap_or(settings.width);
    settings.height = opts.height.unwrap_or(settings.height);
    settings.aa = opts.aa.unwrap_or(settings.aa);
    settings.max_depth = opts.max_depth.unwrap_or(settings.max_depth);
    settings.sampling = opts.sampling.unwrap_or(settings.sampling);
    validate_settings(&settings, "").map_err(|e| anyhow!("command line: {e}"))?;
    if opts.state.is_some() && settings.sampling.target_error().is_none() {
        bail!("--state saves the samples of adaptive sampling: add --sampler adaptive");
    }
    if let Some(range) = opts.frames {
        return run_sequence(&opts, &animated, range, settings, pool);
    }
    let frame = opts.frame.unwrap_or(1);
    let scene = animated
        .into_frame(frame)
        .map_err(|e| anyhow!("{}: {e}", scene_path.display()))?;
    let output = ImageOutput::create(
        &opts
            .output
            .clone()
            .unwrap_or_else(|| default_output(scene_path)),
    )?;
    let job = Job {
        scene: &scene,
        text: text.as_deref(),
        settings,
        output,
        pool: &pool,
        time_limit: opts.time_limit,
        state: opts.state.as_deref().map(FileOutput::create).transpose()?,
        resume: None,
    };
    job.run()
}

/// `--frames`: checks the range against the scene and every output file, then renders
/// the frames in order, each written atomically into the directory as soon as it is
/// done. An interrupted sequence leaves whole frames only.
fn run_sequence(
    opts: &Options,
    animated: &AnimatedScene,
    range: FrameRange,
    settings: RenderSettings,
    pool: rayon::ThreadPool,
) -> Result<()> {
    let scene_path = &opts.scene;
    let count = animated.frame_count();
    let (first, last) = match range {
        FrameRange::All => (1, u64::from(count)),
        FrameRange::Span { first, last } => (first, last),
    };
    // The last frame is the largest: if it exists, they all do.
    if let Err(e) = animated.frame(last) {
        bail!("{}: --frames {first}-{last}: {e}", scene_path.display());
    }
    let dir = FramesDir::create(
        &opts
            .output
            .clone()
            .unwrap_or_else(|| default_output(scene_path).with_extension("")),
    )?;
    let outputs = (first..=last)
        .map(|k| Ok((k, dir.frame(k, count)?)))
        .collect::<Result<Vec<_>>>()?;
    for (k, output) in outputs {
        let scene = animated
            .frame(k)
            .map_err(|e| anyhow!("{}: frame {k}: {e}", scene_path.display()))?;
        let job = Job {
            scene: &scene,
            text: None,
            settings,
            output,
            pool: &pool,
            time_limit: opts.time_limit,
            state: None,
            resume: None,
        };
        job.run()?;
    }
    Ok(())
}

/// What `tessera refine` asked for.
pub struct RefineOptions {
    pub state: PathBuf,
    pub output: Option<PathBuf>,
    pub aa: Option<u32>,
    pub target_error: Option<f64>,
    pub time_limit: Option<Duration>,
    pub threads: Option<u32>,
}

/// `tessera refine FILE`: goes on from a saved adaptive render to a lower target or a
/// larger cap, taking only the samples it lacks; the image is the one a direct render
/// with the final settings gives, byte for byte. The state file is updated in place.
pub fn refine(opts: RefineOptions) -> Result<()> {
    let saved = render_state::load(&opts.state)?;
    let pool = thread_pool(opts.threads)?;
    let scene = pool
        .install(|| parse_scene(&saved.scene))
        .map_err(|e| anyhow!("{}: the saved scene: {e}", opts.state.display()))?;
    let target = match opts.target_error {
        Some(levels) => Sampling::adaptive(levels).map_err(|e| anyhow!("--target-error: {e}"))?,
        None => Sampling::Adaptive {
            target_milli: saved.target_milli,
        },
    };
    let settings = RenderSettings {
        width: saved.width,
        height: saved.height,
        aa: opts.aa.unwrap_or(saved.aa),
        max_depth: saved.max_depth,
        sampling: target,
    };
    validate_settings(&settings, "").map_err(|e| anyhow!("command line: {e}"))?;
    let output = ImageOutput::create(&opts.output.clone().unwrap_or_else(|| {
        let mut p = opts.state.clone();
        p.set_extension("png");
        p
    }))?;
    let job = Job {
        scene: &scene,
        text: Some(&saved.scene),
        settings,
        output,
        pool: &pool,
        time_limit: opts.time_limit,
        state: Some(FileOutput::create(&opts.state)?),
        resume: Some((opts.state.clone(), saved.blocks)),
    };
    job.run()
}

/// The local thread pool: `threads` threads, or one per core.
fn thread_pool(threads: Option<u32>) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads.map_or(0, |n| n as usize))
        .build()
        .context("cannot start the rendering threads")
}

/// One local render, from the command line or a saved state.
struct Job<'a> {
    scene: &'a render::Scene,
    /// The scene's text, kept when the samples are saved (with it).
    text: Option<&'a str>,
    settings: RenderSettings,
    /// Checked writable before the render starts.
    output: ImageOutput,
    /// Renders: `--threads` threads, one per core by default.
    pool: &'a rayon::ThreadPool,
    time_limit: Option<Duration>,
    /// Where the samples are saved: checked writable before the render starts, too.
    state: Option<FileOutput>,
    /// The saved blocks to go on from, and the file they came from.
    resume: Option<(PathBuf, Vec<BlockState>)>,
}

impl Job<'_> {
    fn run(self) -> Result<()> {
        let settings = self.settings;
        let pool = self.pool;
        // In the pool: a large scene's hierarchy is built in parallel, on `--threads` threads.
        let tracer = pool.install(|| Tracer::new(self.scene, settings));
        let started = Instant::now();
        // Until the image is made: saving the samples is not rendering.
        let elapsed;
        let (image, rays, samples, error, note) = match settings.sampling.target_error() {
            Some(target) => {
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
                    format!(
                        "; every pixel at its cap of {} samples",
                        sample_cap(settings.aa)
                    )
                } else if !met && target_given(&settings) {
                    "; stopped by the time limit before the target".to_owned()
                } else if !met {
                    format!("; as far as the time limit allowed (rung {})", frame.rung)
                } else {
                    String::new()
                };
                if let Some(out) = self.state {
                    let saved = render_state::Saved {
                        scene: self
                            .text
                            .expect("a render that saves its samples keeps the scene text")
                            .to_owned(),
                        width: settings.width,
                        height: settings.height,
                        aa: settings.aa,
                        max_depth: settings.max_depth,
                        target_milli: match settings.sampling {
                            Sampling::Adaptive { target_milli } => target_milli,
                            _ => unreachable!("adaptive sampling has a target"),
                        },
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
            None => {
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
            "{}: {}x{}, {}{note}, {:.3} s, {:.1} M rays/s ({} threads)",
            output.display(),
            settings.width,
            settings.height,
            sampling_summary(&settings, samples, error.is_finite().then_some(error)),
            secs,
            rays as f64 / secs.max(1e-9) / 1e6,
            pool.current_num_threads(),
        );
        Ok(())
    }
}

/// Whether adaptive sampling was given a target: `--time-limit` alone asks for the
/// smallest target there is, and the time decides.
fn target_given(settings: &RenderSettings) -> bool {
    settings.sampling
        != (Sampling::Adaptive {
            target_milli: render::MIN_TARGET_MILLI,
        })
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

/// What a render spent and how wrong it may be, for the summary lines of `render`,
/// `up` and `submit --wait`: `4 samples/pixel (grid 2x2, 96000 in all), estimated
/// error 0.842 levels`. The mean is exact for the grid and jittered samplers, a
/// fraction of the budget for adaptive sampling.
pub fn sampling_summary(settings: &RenderSettings, samples: u64, error: Option<f64>) -> String {
    let n = settings.aa;
    let pixels = settings.pixel_count().max(1);
    let mean = if samples.is_multiple_of(pixels) {
        (samples / pixels).to_string()
    } else {
        format!("{:.2}", samples as f64 / pixels as f64)
    };
    let pattern = match settings.sampling {
        Sampling::Adaptive { .. } if !target_given(settings) => {
            format!("adaptive up to {n}x{n}, no target")
        }
        Sampling::Adaptive { .. } => format!(
            "adaptive up to {n}x{n}, target {} levels",
            settings.sampling.target_error().unwrap_or_default()
        ),
        other => format!("{} {n}x{n}", other.name()),
    };
    let error = match error {
        Some(e) => format!("estimated error {e:.3} levels"),
        None if n == 1 => "no error estimate from 1 sample/pixel".to_string(),
        None => "no error estimate".to_string(),
    };
    format!("{mean} samples/pixel ({pattern}, {samples} in all), {error}")
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
    fn a_large_scene_file_read_in_parts_is_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("large.json");
        // Not a multiple of the part size, with multi-byte characters across the parts.
        let line = "{\"type\": \"sphere\", \"name\": \"é€\"}\n";
        let text = line.repeat((PARALLEL_READ_MIN as usize) / line.len() + 1234);
        std::fs::write(&path, &text).unwrap();
        for threads in [1, 2, 3] {
            let pool = thread_pool(Some(threads)).unwrap();
            let read = pool.install(|| read_scene_file(&path)).unwrap();
            assert!(read == text, "{threads} threads");
        }
        // A byte that is not UTF-8 is the same one-line error as for a small file.
        let mut bytes = text.into_bytes();
        bytes.push(0xff);
        std::fs::write(&path, &bytes).unwrap();
        let pool = thread_pool(Some(2)).unwrap();
        let error = pool.install(|| read_scene_file(&path)).unwrap_err();
        std::fs::write(&path, b"{}\xff").unwrap();
        let small = std::fs::read_to_string(&path).unwrap_err();
        assert_eq!(error.to_string(), small.to_string());
    }

    #[test]
    fn frame_ranges_are_a_dash_b_k_or_all() {
        assert_eq!(parse_frame_range("all"), Ok(FrameRange::All));
        assert_eq!(
            parse_frame_range("3-5"),
            Ok(FrameRange::Span { first: 3, last: 5 })
        );
        assert_eq!(
            parse_frame_range("7"),
            Ok(FrameRange::Span { first: 7, last: 7 })
        );
        assert_eq!(
            parse_frame_range("5-3").unwrap_err(),
            "the range ends (frame 3) before it starts (frame 5)"
        );
        assert_eq!(
            parse_frame_range("0").unwrap_err(),
            "frames are numbered from 1"
        );
        for bad in ["", "-", "1-", "-3", "+1", "1-2-3", " 1", "1.5", "a-b"] {
            assert_eq!(
                parse_frame_range(bad).unwrap_err(),
                format!("expected A-B, K or all (frame numbers from 1), got {bad:?}"),
                "{bad:?}"
            );
        }
        assert_eq!(
            parse_frame_range("99999999999999999999").unwrap_err(),
            "frame 99999999999999999999 is too large"
        );
    }

    #[test]
    fn frame_files_have_at_least_four_digits() {
        assert_eq!(render::frame_file_name(7, 1), "frame_0007.png");
        assert_eq!(render::frame_file_name(120, 121), "frame_0120.png");
        assert_eq!(render::frame_file_name(9999, 9999), "frame_9999.png");
        assert_eq!(render::frame_file_name(7, 10_000), "frame_00007.png");
        assert_eq!(
            render::frame_file_name(100_000, 100_000),
            "frame_100000.png"
        );
    }
}
