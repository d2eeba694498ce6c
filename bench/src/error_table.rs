//! `tessera-bench`'s speed-against-error table: every benchmark scene rendered with each
//! sampling setting, timed, and compared with a converged reference render.
//!
//! The grid and jittered rows are rendered by [`render::render_frame`]; the adaptive
//! rows by [`render::adaptive::render_to_target`], the path `--target-error` takes,
//! which walks the threshold ladder until the renderer's estimate of the image's RMSE
//! is at most the target. Each row has its time, its samples per pixel, its RMSE
//! measured against the reference, the renderer's own estimate and their ratio.
//!
//! The adaptive rows answer three questions:
//!
//! - **the ladder**: targets 8 to 0.5 levels with a cap (aa 16, 256 samples per pixel)
//!   meant not to bind, so that each row shows where the estimate alone stops; the share
//!   of pixels whose block wanted to go on but stood at the cap says whether it did;
//! - **the headline**: the target set to the RMSE the grid 8 × 8 row measured, with the
//!   grid's own budget (cap aa 8): does adaptive sampling reach the grid's quality, and
//!   in what share of its time;
//! - **the estimate**: measured / target and estimate / measured for every target.
//!
//! With `--reference-check` the reference itself is checked against a grid of twice its
//! `aa`: where sub-pixel detail aliases, the grid 32 × 32 is not converged either, and
//! no measured error can meaningfully go below that difference.

use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use render::adaptive::{self, Region, RungFrame};
use render::{metrics, Image, RenderSettings, Sampling, Scene, Tracer};

use super::measure::{self, Timed};
use super::scenes::{self, BenchScene};
use super::Options;

mod report;

use report::{csv, markdown, panels};

/// What a row is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    /// A grid or jittered render at a fixed aa.
    Fixed,
    /// Adaptive at one of the ladder's targets, with a cap meant not to bind.
    Ladder,
    /// Adaptive with the target set to the grid 8 × 8's measured RMSE, capped at aa 8.
    Headline,
    /// The same target with the ladder's cap (aa 16): whether the cap is what stops it.
    HeadlineWide,
}

/// The sizes of the table: full, or `--quick`.
struct Plan {
    grid: &'static [u32],
    jittered: &'static [u32],
    targets: &'static [f64],
    /// The cap of the ladder's rows (aa; the cap is `sample_cap(aa)` samples).
    ladder_aa: u32,
    /// The grid row the headline is measured against, and the headline's cap.
    headline_aa: u32,
}

impl Plan {
    fn new(quick: bool) -> Plan {
        if quick {
            Plan {
                grid: &[1, 2, 4],
                jittered: &[2],
                targets: &[4.0, 1.0],
                ladder_aa: 8,
                headline_aa: 4,
            }
        } else {
            Plan {
                grid: &[1, 2, 3, 4, 6, 8],
                jittered: &[2, 4, 8],
                targets: &[8.0, 4.0, 2.0, 1.0, 0.5],
                ladder_aa: 16,
                headline_aa: 8,
            }
        }
    }
}

/// One line of the table.
pub struct Row {
    pub scene: &'static str,
    pub family: &'static str,
    pub role: Role,
    pub setting: String,
    /// aa: the fixed samplers' n × n, adaptive's cap.
    pub aa: u32,
    pub target: Option<f64>,
    pub ms: f64,
    pub rays: u64,
    pub samples_per_pixel: f64,
    /// The renderer's estimate of the image's RMSE (levels); NaN when it has none.
    pub estimated_error: f64,
    pub error: metrics::ImageError,
    /// Adaptive only: the share of pixels in blocks that stood at the cap while their
    /// priority was still above the rung's threshold (the cap bound them).
    pub capped_share: Option<f64>,
    /// The RMSE against the reference check (grid of twice the reference's aa), when
    /// it was rendered.
    pub rmse_against_check: Option<f64>,
}

impl Row {
    /// Estimate / measured; NaN without an estimate.
    pub fn estimate_ratio(&self) -> f64 {
        self.estimated_error / self.error.rmse
    }

    /// Measured / target for adaptive rows.
    pub fn target_ratio(&self) -> Option<f64> {
        self.target.map(|t| self.error.rmse / t)
    }
}

/// One scene's reference, and its check when asked for.
pub struct Reference {
    pub scene: &'static str,
    pub aa: u32,
    pub ms: f64,
    /// aa of the check, and RMSE(reference, check).
    pub check: Option<(u32, f64)>,
}

/// Goals for the adaptive rows (see docs/performance.md).
const GOAL_TIME_RATIO: f64 = 0.75;
const GOAL_TARGET_RATIO: f64 = 1.1;
const GOAL_ESTIMATE_FACTOR: f64 = 1.25;

/// Runs the table; writes `bench.md`, `bench.csv` and `bench.png` into `out`.
pub fn run(opts: &Options, out: &Path) -> Result<Vec<Row>> {
    let pool = measure::pool(opts.threads)?;
    let plan = Plan::new(opts.quick);
    let mut rows = Vec::new();
    let mut references = Vec::new();
    let reference_aa = opts.reference_aa;
    for bench in scenes::error_suite() {
        let scene = parse(&bench)?;
        let base = RenderSettings {
            width: opts.width,
            height: opts.height,
            ..scene.settings
        };
        let grid = |aa: u32| RenderSettings {
            aa,
            sampling: Sampling::Grid,
            ..base
        };
        eprintln!(
            "{}: reference, grid {reference_aa}×{reference_aa}",
            bench.name
        );
        let reference = measure::time_frame(&scene, grid(reference_aa), &pool, Duration::ZERO, 1);
        std::fs::write(
            out.join(format!("{}-reference.png", bench.name)),
            reference.frame.image.to_png(),
        )?;
        let check = if opts.reference_check {
            let aa = 2 * reference_aa;
            eprintln!("{}: reference check, grid {aa}×{aa}", bench.name);
            let finer = measure::time_frame(&scene, grid(aa), &pool, Duration::ZERO, 1);
            let rmse = metrics::rmse(&finer.frame.image, &reference.frame.image);
            eprintln!(
                "{}: RMSE(grid {reference_aa}, grid {aa}) = {rmse:.3}",
                bench.name
            );
            Some((aa, finer.frame.image))
        } else {
            None
        };
        references.push(Reference {
            scene: bench.name,
            aa: reference_aa,
            ms: reference.seconds * 1e3,
            check: check
                .as_ref()
                .map(|(aa, image)| (*aa, metrics::rmse(image, &reference.frame.image))),
        });
        let images = Images {
            reference: &reference.frame.image,
            check: check.as_ref().map(|(_, image)| image),
        };
        let of_scene = scene_rows(&bench, &scene, base, &plan, &pool, opts, &images);
        rows.extend(of_scene);
    }
    std::fs::write(
        out.join("bench.md"),
        markdown(&rows, &references, &plan, opts),
    )?;
    std::fs::write(out.join("bench.csv"), csv(&rows, &references))?;
    crate::plot::write_png(&out.join("bench.png"), &panels(&rows), 2, (640, 480))?;
    Ok(rows)
}

/// The images a row is compared with.
struct Images<'a> {
    reference: &'a Image,
    check: Option<&'a Image>,
}

/// Every row of one scene: the fixed samplers, the ladder, then the headline (whose
/// target is the grid row's measured RMSE).
fn scene_rows(
    bench: &BenchScene,
    scene: &Scene,
    base: RenderSettings,
    plan: &Plan,
    pool: &rayon::ThreadPool,
    opts: &Options,
    images: &Images,
) -> Vec<Row> {
    let mut rows: Vec<Row> = Vec::new();
    let log = |row: Row, rows: &mut Vec<Row>| {
        eprintln!(
            "{}: {:<40} {:>9.1} ms  {:>7.2} spp  RMSE {:>6.3}  est. {:>6.3}",
            bench.name,
            row.setting,
            row.ms,
            row.samples_per_pixel,
            row.error.rmse,
            row.estimated_error
        );
        rows.push(row);
    };
    let fixed = plan
        .grid
        .iter()
        .map(|&aa| ("grid", Sampling::Grid, aa))
        .chain(
            plan.jittered
                .iter()
                .map(|&aa| ("jittered", Sampling::Jittered, aa)),
        );
    for (family, sampling, aa) in fixed {
        let settings = RenderSettings {
            aa,
            sampling,
            ..base
        };
        let timed = measure::time_frame(scene, settings, pool, opts.min_time, opts.max_runs);
        log(fixed_row(bench, family, aa, &timed, images), &mut rows);
    }
    for &target in plan.targets {
        let timed = time_adaptive(scene, base, plan.ladder_aa, target, pool, opts);
        let setting = format!("adaptive ≤{}², target {target}", plan.ladder_aa);
        log(
            adaptive_row(bench, Role::Ladder, setting, &timed, images),
            &mut rows,
        );
    }
    let grid = rows
        .iter()
        .find(|r| r.family == "grid" && r.aa == plan.headline_aa)
        .map(|r| r.error.rmse);
    if let Some(grid_rmse) = grid {
        // The target as `--target-error` would take it: thousandths of a level.
        let target = Sampling::adaptive(grid_rmse)
            .ok()
            .and_then(Sampling::target_error)
            .unwrap_or(grid_rmse);
        let timed = time_adaptive(scene, base, plan.headline_aa, target, pool, opts);
        let n = plan.headline_aa;
        let setting = format!("adaptive ≤{n}², target = grid {n}²'s RMSE ({target})");
        log(
            adaptive_row(bench, Role::Headline, setting, &timed, images),
            &mut rows,
        );
        let wide = plan.ladder_aa;
        let timed = time_adaptive(scene, base, wide, target, pool, opts);
        let setting = format!("adaptive ≤{wide}², target = grid {n}²'s RMSE ({target})");
        log(
            adaptive_row(bench, Role::HeadlineWide, setting, &timed, images),
            &mut rows,
        );
    }
    rows
}

fn parse(bench: &BenchScene) -> Result<Scene> {
    render::parse_scene(&bench.json).with_context(|| format!("benchmark scene {}", bench.name))
}

fn fixed_row(
    bench: &BenchScene,
    family: &'static str,
    aa: u32,
    timed: &Timed,
    images: &Images,
) -> Row {
    let frame = &timed.frame;
    Row {
        scene: bench.name,
        family,
        role: Role::Fixed,
        setting: format!("{family} {aa}²"),
        aa,
        target: None,
        ms: timed.seconds * 1e3,
        rays: frame.rays,
        samples_per_pixel: frame.samples_per_pixel(),
        estimated_error: frame.estimated_error(),
        error: metrics::compare(images.reference, &frame.image),
        capped_share: None,
        rmse_against_check: images.check.map(|c| metrics::rmse(c, &frame.image)),
    }
}

/// One adaptive measurement: the fastest run's time, and the frame.
struct TimedAdaptive {
    seconds: f64,
    aa: u32,
    target: f64,
    frame: RungFrame,
    capped_share: f64,
}

/// Renders `scene` adaptively to `target` with the cap of `aa`, on `pool`, at least
/// once and until `opts.min_time` has passed (at most `opts.max_runs` times), keeping
/// the fastest time: the rule of [`measure::time_frame`], for the path `--target-error`
/// takes. The time includes everything that path does (the footprints, the blocks, the
/// ladder and painting the image).
fn time_adaptive(
    scene: &Scene,
    base: RenderSettings,
    aa: u32,
    target: f64,
    pool: &rayon::ThreadPool,
    opts: &Options,
) -> TimedAdaptive {
    let settings = RenderSettings {
        aa,
        sampling: Sampling::adaptive(target).expect("a valid target"),
        ..base
    };
    let tracer = Tracer::new(scene, settings);
    let started = Instant::now();
    let mut best = f64::INFINITY;
    let mut runs = 0;
    let mut last = None;
    while runs == 0 || (started.elapsed() < opts.min_time && runs < opts.max_runs) {
        let t = Instant::now();
        let (region, frame) =
            pool.install(|| adaptive::render_to_target(&tracer, None, target, &mut |_, _| true));
        best = best.min(t.elapsed().as_secs_f64());
        runs += 1;
        let capped = capped_share(&region, frame.rung, adaptive::sample_cap(aa));
        last = Some((frame, capped));
    }
    let (frame, capped_share) = last.expect("rendered at least once");
    TimedAdaptive {
        seconds: best,
        aa,
        target,
        frame,
        capped_share,
    }
}

/// The share of pixels whose block stands at `cap` samples at rung `k` while its
/// priority is still above the rung's threshold: the blocks the cap stopped.
fn capped_share(region: &Region, k: u32, cap: u32) -> f64 {
    let lambda = adaptive::threshold(k);
    let (mut capped, mut pixels) = (0u64, 0u64);
    for block in region.blocks() {
        let n = block.rect.pixel_count();
        pixels += n;
        // `render_to_target` advances every block to rung k and no further, so its last
        // level is the one in the image.
        let l = block.levels.len() - 1;
        if block.levels[l].count >= cap && block.estimate(l).priority > lambda {
            capped += n;
        }
    }
    if pixels == 0 {
        0.0
    } else {
        capped as f64 / pixels as f64
    }
}

fn adaptive_row(
    bench: &BenchScene,
    role: Role,
    setting: String,
    timed: &TimedAdaptive,
    images: &Images,
) -> Row {
    let frame = &timed.frame;
    let pixels = frame.image.pixel_count().max(1) as f64;
    Row {
        scene: bench.name,
        family: "adaptive",
        role,
        setting,
        aa: timed.aa,
        target: Some(timed.target),
        ms: timed.seconds * 1e3,
        rays: frame.totals.rays,
        samples_per_pixel: frame.totals.samples as f64 / pixels,
        estimated_error: frame.estimated_error(),
        error: metrics::compare(images.reference, &frame.image),
        capped_share: Some(timed.capped_share),
        rmse_against_check: images.check.map(|c| metrics::rmse(c, &frame.image)),
    }
}
