//! `tessera-bench`'s speed-against-error table: every benchmark scene rendered with each
//! sampling setting, timed, and compared with a converged reference render.
//!
//! The grid and jittered rows are rendered by [`render::render_frame`]; the adaptive
//! rows by [`render::progressive::render_to_target`], the path `--target-error` takes,
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

use std::fmt::Write as _;
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use render::progressive::{self, Region, RungFrame};
use render::{metrics, Image, RenderSettings, Sampling, Scene, Tracer};

use super::measure::{self, Timed};
use super::scenes::{self, BenchScene};
use super::Options;
use crate::plot::{Panel, Series};

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
            pool.install(|| progressive::render_to_target(&tracer, None, target, &mut |_, _| true));
        best = best.min(t.elapsed().as_secs_f64());
        runs += 1;
        let capped = capped_share(&region, frame.rung, progressive::sample_cap(aa));
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
    let lambda = progressive::threshold(k);
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

/// Indices of the rows no other row of the same scene beats on both time and error.
fn pareto(rows: &[Row], scene: &str) -> Vec<usize> {
    let mut front: Vec<usize> = (0..rows.len())
        .filter(|&i| rows[i].scene == scene)
        .filter(|&i| {
            !rows.iter().any(|o| {
                o.scene == scene
                    && o.ms <= rows[i].ms
                    && o.error.rmse <= rows[i].error.rmse
                    && (o.ms < rows[i].ms || o.error.rmse < rows[i].error.rmse)
            })
        })
        .collect();
    front.sort_by(|&a, &b| rows[a].ms.total_cmp(&rows[b].ms));
    front
}

fn scene_names(rows: &[Row]) -> Vec<&'static str> {
    let mut names: Vec<&'static str> = Vec::new();
    for r in rows {
        if !names.contains(&r.scene) {
            names.push(r.scene);
        }
    }
    names
}

fn of_scene<'r>(rows: &'r [Row], scene: &'r str) -> impl Iterator<Item = &'r Row> + 'r {
    rows.iter().filter(move |r| r.scene == scene)
}

/// The grid row the headline is measured against.
fn grid_row<'r>(rows: &'r [Row], scene: &'r str, aa: u32) -> Option<&'r Row> {
    of_scene(rows, scene).find(|r| r.family == "grid" && r.aa == aa)
}

fn headline<'r>(rows: &'r [Row], scene: &'r str) -> Option<&'r Row> {
    of_scene(rows, scene).find(|r| r.role == Role::Headline)
}

fn headline_wide<'r>(rows: &'r [Row], scene: &'r str) -> Option<&'r Row> {
    of_scene(rows, scene).find(|r| r.role == Role::HeadlineWide)
}

fn ladder<'r>(rows: &'r [Row], scene: &'r str) -> impl Iterator<Item = &'r Row> + 'r {
    of_scene(rows, scene).filter(|r| r.role == Role::Ladder)
}

/// The fastest row of `family` at least as accurate as `than`.
fn fastest_as_accurate<'r>(rows: &'r [Row], family: &str, than: &Row) -> Option<&'r Row> {
    of_scene(rows, than.scene)
        .filter(|r| r.family == family && r.error.rmse <= than.error.rmse)
        .min_by(|a, b| a.ms.total_cmp(&b.ms))
}

fn number(v: f64, digits: usize) -> String {
    if v.is_finite() {
        format!("{v:.digits$}")
    } else {
        "—".to_owned()
    }
}

fn mark(ok: bool) -> &'static str {
    if ok {
        "✓"
    } else {
        "✗"
    }
}

fn within_factor(ratio: f64, factor: f64) -> bool {
    ratio.is_finite() && ratio <= factor && ratio >= 1.0 / factor
}

fn markdown(rows: &[Row], references: &[Reference], plan: &Plan, opts: &Options) -> String {
    let mut md = String::new();
    let h = plan.headline_aa;
    let _ = writeln!(
        md,
        "Speed against error at {}×{}, {} thread(s); error against a grid {}×{} reference. \
         Time is the fastest of up to {} runs (each setting repeated until {} ms have \
         passed). RMSE is measured over the 8-bit channels; `est.` is the renderer's own \
         estimate of it. Adaptive rows are rendered to a target by the ladder of \
         `render::progressive` (the path of `--target-error`); the ladder's rows have a \
         cap of aa {} ({} samples per pixel), `capped` is the share of pixels whose block \
         stood at the cap while it would have gone on.\n",
        opts.width,
        opts.height,
        opts.threads,
        opts.reference_aa,
        opts.reference_aa,
        opts.max_runs,
        opts.min_time.as_millis(),
        plan.ladder_aa,
        progressive::sample_cap(plan.ladder_aa),
    );
    let scenes = scene_names(rows);

    // 1. The headline.
    let _ = writeln!(
        md,
        "## Adaptive at grid {h}×{h}'s RMSE\n\n\
         Adaptive sampling with grid {h}×{h}'s budget (at most {} samples per pixel) and \
         the target set to the RMSE grid {h}×{h} measured. Goal: at most {GOAL_TIME_RATIO}× \
         the grid's time, and its RMSE reached. `capped`: the share of pixels whose block \
         the cap stopped. The last three columns: the same target with the ladder's cap \
         (aa {w}, {} samples per pixel), which says whether the cap is what stands in the \
         way.\n",
        progressive::sample_cap(h),
        progressive::sample_cap(plan.ladder_aa),
        w = plan.ladder_aa,
    );
    let _ = writeln!(
        md,
        "| scene | grid {h}² RMSE | grid {h}² ms | adaptive RMSE | est. | adaptive ms | samples/px | capped | time ratio | reached | goal | ≤{w}²: RMSE | ≤{w}²: time ratio | ≤{w}²: reached |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---:|---:|---|",
        w = plan.ladder_aa
    );
    for &scene in &scenes {
        let (Some(g), Some(a)) = (grid_row(rows, scene, h), headline(rows, scene)) else {
            continue;
        };
        let ratio = a.ms / g.ms;
        let reached = a.error.rmse <= g.error.rmse;
        let yes = |b: bool| if b { "yes" } else { "no" };
        let wide = headline_wide(rows, scene).map_or(" | | |".to_owned(), |w| {
            format!(
                " {:.3} | {:.2}× | {} |",
                w.error.rmse,
                w.ms / g.ms,
                yes(w.error.rmse <= g.error.rmse)
            )
        });
        let _ = writeln!(
            md,
            "| {scene} | {:.3} | {:.1} | {:.3} | {} | {:.1} | {:.2} | {:.1}% | {:.2}× | {} | {} |{wide}",
            g.error.rmse,
            g.ms,
            a.error.rmse,
            number(a.estimated_error, 3),
            a.ms,
            a.samples_per_pixel,
            a.capped_share.unwrap_or(0.0) * 100.0,
            ratio,
            yes(reached),
            mark(reached && ratio <= GOAL_TIME_RATIO)
        );
    }
    md.push('\n');

    // 2. The ladder against its targets.
    let _ = writeln!(
        md,
        "## Adaptive against its target\n\n\
         Each target with a cap of aa {} (`capped` above 0 would mean the cap, not the \
         estimate, ended some blocks). measured/target: goal ≤ {GOAL_TARGET_RATIO}; \
         est./measured: goal within ×/÷ {GOAL_ESTIMATE_FACTOR}.\n",
        plan.ladder_aa
    );
    type Ratio = fn(&Row) -> (f64, bool);
    let tables: [(&str, Ratio); 2] = [
        ("measured / target", |r| {
            let q = r.target_ratio().unwrap_or(f64::NAN);
            (q, q <= GOAL_TARGET_RATIO)
        }),
        ("estimate / measured", |r| {
            let q = r.estimate_ratio();
            (q, within_factor(q, GOAL_ESTIMATE_FACTOR))
        }),
    ];
    for (title, ratio) in tables {
        let _ = write!(md, "| {title} |");
        for t in plan.targets {
            let _ = write!(md, " target {t} |");
        }
        md.push_str("\n|---|");
        for _ in plan.targets {
            md.push_str("---:|");
        }
        md.push('\n');
        for &scene in &scenes {
            let _ = write!(md, "| {scene} |");
            for r in ladder(rows, scene) {
                let (q, ok) = ratio(r);
                let _ = write!(md, " {} {} |", number(q, 2), mark(ok));
            }
            md.push('\n');
        }
        md.push('\n');
    }
    let met = |f: &dyn Fn(&Row) -> bool| {
        let all: Vec<&Row> = rows.iter().filter(|r| r.role == Role::Ladder).collect();
        (all.iter().filter(|r| f(r)).count(), all.len())
    };
    let (t_ok, t_all) = met(&|r| r.target_ratio().is_some_and(|q| q <= GOAL_TARGET_RATIO));
    let (e_ok, e_all) = met(&|r| within_factor(r.estimate_ratio(), GOAL_ESTIMATE_FACTOR));
    let (c_ok, c_all) = met(&|r| r.capped_share.is_some_and(|c| c == 0.0));
    let _ = writeln!(
        md,
        "Measured/target met in {t_ok} of {t_all} rows, est./measured in {e_ok} of {e_all}; \
         the cap bound no block in {c_ok} of {c_all}.\n"
    );

    // 3. Time to reach each target.
    let _ = writeln!(
        md,
        "## Time to reach each target\n\n\
         The ladder's times (ms), with the factor over the previous (larger) target in \
         brackets: each halving of the target should cost a steady factor, not a jump.\n"
    );
    let _ = write!(md, "| scene |");
    for t in plan.targets {
        let _ = write!(md, " {t} |");
    }
    md.push('\n');
    let _ = write!(md, "|---|");
    for _ in plan.targets {
        md.push_str("---:|");
    }
    md.push('\n');
    for &scene in &scenes {
        let ladder: Vec<&Row> = ladder(rows, scene).collect();
        let _ = write!(md, "| {scene} |");
        let mut previous: Option<f64> = None;
        for r in &ladder {
            match previous {
                Some(p) => {
                    let _ = write!(md, " {:.1} (×{:.2}) |", r.ms, r.ms / p);
                }
                None => {
                    let _ = write!(md, " {:.1} |", r.ms);
                }
            }
            previous = Some(r.ms);
        }
        md.push('\n');
    }
    md.push('\n');

    // 4. Each sampler against grid 8×8.
    let _ = writeln!(
        md,
        "## Each sampler against grid {h}×{h}\n\n\
         For each family, the fastest setting at least as accurate as grid {h}×{h}, and its \
         time as a multiple of the grid's.\n"
    );
    let _ = writeln!(
        md,
        "| scene | grid {h}² | grid | jittered | adaptive |\n|---|---|---|---|---|"
    );
    for &scene in &scenes {
        let Some(g) = grid_row(rows, scene, h) else {
            continue;
        };
        let _ = write!(md, "| {scene} | RMSE {:.3}, {:.1} ms |", g.error.rmse, g.ms);
        for family in ["grid", "jittered", "adaptive"] {
            match fastest_as_accurate(rows, family, g) {
                Some(r) => {
                    let _ = write!(
                        md,
                        " {} (RMSE {:.3}): {:.2}× |",
                        r.setting,
                        r.error.rmse,
                        r.ms / g.ms
                    );
                }
                None => {
                    let best = of_scene(rows, scene)
                        .filter(|r| r.family == family)
                        .map(|r| r.error.rmse)
                        .fold(f64::INFINITY, f64::min);
                    let _ = write!(md, " none (best RMSE {}) |", number(best, 3));
                }
            }
        }
        md.push('\n');
    }
    md.push('\n');

    // 5. The reference.
    let _ = writeln!(md, "## The reference\n");
    if references.iter().any(|r| r.check.is_some()) {
        let _ = writeln!(
            md,
            "The reference (grid {0}×{0}) against a grid of twice its aa: where sub-pixel \
             detail aliases, the reference is not converged either, and a measured RMSE \
             near this difference says as much about the reference as about the row. \
             `lowest RMSE` is the lowest any row of the table measured.\n",
            opts.reference_aa
        );
        let _ = writeln!(
            md,
            "| scene | reference ms | RMSE(reference, check) | lowest RMSE |\n|---|---:|---:|---:|"
        );
        for r in references {
            if let Some((aa, rmse)) = r.check {
                let lowest = of_scene(rows, r.scene)
                    .map(|x| x.error.rmse)
                    .fold(f64::INFINITY, f64::min);
                let _ = writeln!(
                    md,
                    "| {} | {:.0} | {:.3} (grid {}², grid {aa}²) | {:.3} |",
                    r.scene, r.ms, rmse, r.aa, lowest
                );
            }
        }
        md.push('\n');
    } else {
        let _ = writeln!(
            md,
            "Not checked (`--reference-check` renders a grid of twice the reference's aa and \
             measures how far the reference itself is from converged).\n"
        );
    }

    // 6. Every row.
    let _ = writeln!(
        md,
        "## Every row\n\n\
         Rows marked ◆ are on the Pareto front (no other setting of the scene is both \
         faster and more accurate). `off>2` is the share of pixels with a channel more \
         than 2 levels off. For grid and jittered rows `est.` is the root mean square of \
         each pixel's standard error computed as if its samples were independent (the \
         largest of its channels); for adaptive rows, the four-group estimate of \
         `render::progressive`.{}\n",
        if references.iter().any(|r| r.check.is_some()) {
            " `vs check` is the RMSE against the reference check instead of the reference."
        } else {
            ""
        }
    );
    let with_check = rows.iter().any(|r| r.rmse_against_check.is_some());
    for scene in scenes {
        let front = pareto(rows, scene);
        let what = scenes::error_suite()
            .into_iter()
            .find(|b| b.name == scene)
            .map_or(String::new(), |b| b.what);
        let _ = writeln!(md, "### {scene}\n\n{what}\n");
        let _ = writeln!(
            md,
            "| setting | time (ms) | samples/px | rays | RMSE | PSNR (dB) | off>2 | est. | est./measured | measured/target | capped |{} |\n\
             |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|{}---|",
            if with_check { " vs check |" } else { "" },
            if with_check { "---:|" } else { "" }
        );
        for (i, r) in rows.iter().enumerate().filter(|(_, r)| r.scene == scene) {
            let _ = writeln!(
                md,
                "| {} | {:.1} | {:.2} | {} | {:.3} | {} | {:.2}% | {} | {} | {} | {} |{} {} |",
                r.setting,
                r.ms,
                r.samples_per_pixel,
                r.rays,
                r.error.rmse,
                psnr_text(r.error.psnr),
                r.error.share_off_by_more_than_2 * 100.0,
                number(r.estimated_error, 3),
                number(r.estimate_ratio(), 2),
                r.target_ratio()
                    .map_or("".to_owned(), |q| format!("{q:.2}")),
                r.capped_share
                    .map_or("".to_owned(), |c| format!("{:.1}%", c * 100.0)),
                match r.rmse_against_check {
                    Some(c) if with_check => format!(" {c:.3} |"),
                    _ if with_check => " |".to_owned(),
                    _ => String::new(),
                },
                if front.contains(&i) { "◆" } else { "" }
            );
        }
        md.push('\n');
    }
    md
}

fn psnr_text(psnr: f64) -> String {
    if psnr.is_finite() {
        format!("{psnr:.1}")
    } else {
        "∞".into()
    }
}

fn csv(rows: &[Row], references: &[Reference]) -> String {
    let mut out = String::from(
        "scene,family,role,aa,cap_samples,target_error,time_ms,rays,samples_per_pixel,rmse,psnr_db,\
         share_off_by_more_than_2,estimated_error,estimate_over_measured,measured_over_target,\
         capped_share,rmse_against_check,reference_check_rmse\n",
    );
    let opt = |v: Option<f64>, digits: usize| {
        v.filter(|v| v.is_finite())
            .map_or(String::new(), |v| format!("{v:.digits$}"))
    };
    for r in rows {
        let check = references
            .iter()
            .find(|x| x.scene == r.scene)
            .and_then(|x| x.check)
            .map(|(_, rmse)| rmse);
        let _ = writeln!(
            out,
            "{},{},{},{},{},{},{:.3},{},{:.4},{:.5},{:.3},{:.6},{},{},{},{},{},{}",
            r.scene,
            r.family,
            match r.role {
                Role::Fixed => "fixed",
                Role::Ladder => "ladder",
                Role::Headline => "headline",
                Role::HeadlineWide => "headline_wide",
            },
            r.aa,
            if r.family == "adaptive" {
                progressive::sample_cap(r.aa)
            } else {
                r.aa * r.aa
            },
            r.target.map_or(String::new(), |t| t.to_string()),
            r.ms,
            r.rays,
            r.samples_per_pixel,
            r.error.rmse,
            r.error.psnr,
            r.error.share_off_by_more_than_2,
            opt(Some(r.estimated_error), 4),
            opt(Some(r.estimate_ratio()), 4),
            opt(r.target_ratio(), 4),
            opt(r.capped_share, 6),
            opt(r.rmse_against_check, 5),
            opt(check, 5),
        );
    }
    out
}

/// Per scene, time against measured RMSE for each sampler family and the Pareto front;
/// then the renderer's estimate against the measured RMSE over every row, and the time
/// to reach each target.
fn panels(rows: &[Row]) -> Vec<Panel> {
    let floor = |v: f64| v.max(1e-3);
    let mut panels: Vec<Panel> = scene_names(rows)
        .into_iter()
        .map(|scene| {
            let series = |label: &str, keep: &dyn Fn(&Row) -> bool, joined: bool| {
                let mut points: Vec<(f64, f64)> = of_scene(rows, scene)
                    .filter(|r| keep(r))
                    .map(|r| (r.ms, floor(r.error.rmse)))
                    .collect();
                points.sort_by(|a, b| a.0.total_cmp(&b.0));
                Series {
                    label: label.to_owned(),
                    points,
                    joined,
                    markers: true,
                }
            };
            let headline_label =
                headline(rows, scene).map_or("adaptive at the grid's RMSE".to_owned(), |r| {
                    let wide = headline_wide(rows, scene).map_or(r.aa, |w| w.aa);
                    format!("adaptive at grid {}²'s RMSE (≤{}², ≤{wide}²)", r.aa, r.aa)
                });
            let ladder_label = ladder(rows, scene)
                .next()
                .map_or("adaptive".to_owned(), |r| format!("adaptive ≤{}²", r.aa));
            let front = Series {
                label: "Pareto front".into(),
                points: pareto(rows, scene)
                    .into_iter()
                    .map(|i| (rows[i].ms, floor(rows[i].error.rmse)))
                    .collect(),
                joined: true,
                markers: false,
            };
            Panel {
                title: scene.to_owned(),
                x_label: "time (ms, log)".into(),
                y_label: "measured RMSE (8-bit levels, log)".into(),
                log_x: true,
                log_y: true,
                series: vec![
                    series("grid", &|r| r.family == "grid", true),
                    series("jittered", &|r| r.family == "jittered", true),
                    series(&ladder_label, &|r| r.role == Role::Ladder, true),
                    series(
                        &headline_label,
                        &|r| matches!(r.role, Role::Headline | Role::HeadlineWide),
                        false,
                    ),
                    front,
                ],
            }
        })
        .collect();

    // The estimate against the measured error, every scene and row with an estimate.
    let estimated = |keep: &dyn Fn(&Row) -> bool| -> Vec<(f64, f64)> {
        rows.iter()
            .filter(|r| keep(r) && r.estimated_error.is_finite() && r.estimated_error > 0.0)
            .map(|r| (floor(r.error.rmse), r.estimated_error))
            .collect()
    };
    let all: Vec<(f64, f64)> = estimated(&|_| true);
    let (lo, hi) = all
        .iter()
        .flat_map(|&(x, y)| [x, y])
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    let (lo, hi) = if lo.is_finite() && hi > 0.0 {
        (lo / 1.3, hi * 1.3)
    } else {
        (0.1, 10.0)
    };
    let line = |label: &str, factor: f64| Series {
        label: label.to_owned(),
        points: vec![(lo, lo * factor), (hi, hi * factor)],
        joined: true,
        markers: false,
    };
    let markers = |label: &str, points: Vec<(f64, f64)>| Series {
        label: label.to_owned(),
        points,
        joined: false,
        markers: true,
    };
    panels.push(Panel {
        title: "estimate against measured, every scene".into(),
        x_label: "measured RMSE (levels, log)".into(),
        y_label: "estimated RMSE (levels, log)".into(),
        log_x: true,
        log_y: true,
        series: vec![
            markers("grid", estimated(&|r| r.family == "grid")),
            markers("jittered", estimated(&|r| r.family == "jittered")),
            markers("adaptive", estimated(&|r| r.family == "adaptive")),
            line("y = x", 1.0),
            line(&format!("×/÷ {GOAL_ESTIMATE_FACTOR}"), GOAL_ESTIMATE_FACTOR),
            // Unlabelled: drawn in the colour of the line before it.
            line("", 1.0 / GOAL_ESTIMATE_FACTOR),
        ],
    });

    // The time to reach each target, one line per scene.
    panels.push(Panel {
        title: "time to reach each target (adaptive ladder)".into(),
        x_label: "target RMSE (levels, log)".into(),
        y_label: "time (ms, log)".into(),
        log_x: true,
        log_y: true,
        series: scene_names(rows)
            .into_iter()
            .map(|scene| Series {
                label: scene.to_owned(),
                points: ladder(rows, scene)
                    .filter_map(|r| Some((r.target?, r.ms)))
                    .collect(),
                joined: true,
                markers: true,
            })
            .collect(),
    });
    panels
}
