//! The scaling report: time against pixels and against objects on one machine, the
//! farm's speed-up with 1 to N workers, and the pull scheduler against a static split.

use std::fmt::Write as _;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use render::{RenderSettings, Scene, Tracer};

use super::measure;
use super::scenes::{self, BenchScene};
use super::Options;
use crate::plot::{Panel, Series};

/// One measured point of a curve.
pub struct Point {
    pub x: f64,
    pub seconds: f64,
    pub rays: u64,
    /// Loading the scene and building the tracer, where measured (the object sweep).
    pub setup_seconds: Option<f64>,
}

fn parse(bench: &BenchScene) -> Result<Scene> {
    render::parse_scene(&bench.json).with_context(|| format!("benchmark scene {}", bench.name))
}

/// The seed scene at aa 1 from 150 × 100 to 2400 × 1600 on one thread.
pub fn time_against_pixels(opts: &Options) -> Result<Vec<Point>> {
    let pool = measure::pool(1)?;
    let scene = parse(&scenes::seed())?;
    let sizes: &[(u32, u32)] = if opts.quick {
        &[(75, 50), (150, 100), (300, 200)]
    } else {
        &[
            (150, 100),
            (300, 200),
            (600, 400),
            (1200, 800),
            (2400, 1600),
        ]
    };
    let mut out = Vec::new();
    for &(width, height) in sizes {
        let timed = measure::time_frame(
            &scene,
            RenderSettings {
                width,
                height,
                aa: 1,
                ..scene.settings
            },
            &pool,
            opts.min_time,
            opts.max_runs,
        );
        eprintln!("pixels: {width}×{height}: {:.1} ms", timed.seconds * 1e3);
        out.push(Point {
            x: f64::from(width) * f64::from(height),
            seconds: timed.seconds,
            rays: timed.frame.rays,
            setup_seconds: None,
        });
    }
    Ok(out)
}

/// The fastest of `f`'s runs, run at least once and until `min_total` has passed (at
/// most `max_runs` times), in seconds.
fn best_seconds(
    min_total: Duration,
    max_runs: u32,
    mut f: impl FnMut() -> Result<()>,
) -> Result<f64> {
    let started = Instant::now();
    let mut best = f64::INFINITY;
    let mut runs = 0;
    while runs == 0 || (started.elapsed() < min_total && runs < max_runs) {
        let t = Instant::now();
        f()?;
        best = best.min(t.elapsed().as_secs_f64());
        runs += 1;
    }
    Ok(best)
}

/// The many-spheres scene with `counts` spheres at 600 × 400 (150 × 100 when quick),
/// aa 1, on one thread; loading the scene and building the tracer are timed apart.
pub fn time_against_objects(opts: &Options, counts: &[usize]) -> Result<Vec<Point>> {
    let pool = measure::pool(1)?;
    let (width, height) = if opts.quick { (150, 100) } else { (600, 400) };
    let mut out = Vec::new();
    for &count in counts {
        let bench = scenes::spheres(count);
        let mut scene = parse(&bench)?;
        let settings = RenderSettings {
            width,
            height,
            aa: 1,
            ..scene.settings
        };
        let setup = best_seconds(opts.min_time, opts.max_runs.min(3), || {
            scene = parse(&bench)?;
            std::hint::black_box(Tracer::new(&scene, settings));
            Ok(())
        })?;
        let timed = measure::time_frame(
            &scene,
            RenderSettings {
                width,
                height,
                aa: 1,
                ..scene.settings
            },
            &pool,
            opts.min_time,
            opts.max_runs,
        );
        eprintln!(
            "objects: {count} spheres: load and build {:.1} ms, render {:.1} ms",
            setup * 1e3,
            timed.seconds * 1e3
        );
        out.push(Point {
            x: count as f64,
            seconds: timed.seconds,
            rays: timed.frame.rays,
            setup_seconds: Some(setup),
        });
    }
    Ok(out)
}

/// The seed scene's objects under 1 to 64 lights, 600 × 400 (150 × 100 when quick), aa
/// 1, one thread.
pub fn time_against_lights(opts: &Options) -> Result<Vec<Point>> {
    let counts: &[usize] = if opts.quick {
        &[1, 4, 16]
    } else {
        &[1, 2, 4, 8, 16, 32, 64]
    };
    let (width, height) = if opts.quick { (150, 100) } else { (600, 400) };
    let mut out = Vec::new();
    for &count in counts {
        let point = time_scene(opts, &scenes::lights(count), width, height, None)?;
        eprintln!("lights: {count}: {:.1} ms", point.seconds * 1e3);
        out.push(Point {
            x: count as f64,
            ..point
        });
    }
    Ok(out)
}

/// The hall of mirrors with a reflection depth limit of 0 to 64, 480 × 480 (120 × 120
/// when quick), aa 1, one thread.
pub fn time_against_depth(opts: &Options) -> Result<Vec<Point>> {
    let depths: &[u32] = if opts.quick {
        &[0, 1, 4, 16]
    } else {
        &[0, 1, 2, 4, 8, 16, 32, 64]
    };
    let size = if opts.quick { 120 } else { 480 };
    let mut out = Vec::new();
    for &depth in depths {
        let point = time_scene(opts, &scenes::hall_of_mirrors(), size, size, Some(depth))?;
        eprintln!("depth: {depth}: {:.1} ms", point.seconds * 1e3);
        out.push(Point {
            x: f64::from(depth),
            ..point
        });
    }
    Ok(out)
}

/// One frame of `bench` at `width` × `height`, aa 1, one thread, optionally with
/// another depth limit.
fn time_scene(
    opts: &Options,
    bench: &BenchScene,
    width: u32,
    height: u32,
    max_depth: Option<u32>,
) -> Result<Point> {
    let pool = measure::pool(1)?;
    let scene = parse(bench)?;
    let settings = RenderSettings {
        width,
        height,
        aa: 1,
        max_depth: max_depth.unwrap_or(scene.settings.max_depth),
        ..scene.settings
    };
    let timed = measure::time_frame(&scene, settings, &pool, opts.min_time, opts.max_runs);
    Ok(Point {
        x: 0.0,
        seconds: timed.seconds,
        rays: timed.frame.rays,
        setup_seconds: None,
    })
}

/// The least-squares slope of log y against log x over the points where both are
/// positive: the exponent k of y ∝ xᵏ. `None` with fewer than two such points or a
/// single x.
pub fn loglog_slope(points: &[(f64, f64)]) -> Option<f64> {
    let logs: Vec<(f64, f64)> = points
        .iter()
        .filter(|(x, y)| *x > 0.0 && *y > 0.0)
        .map(|(x, y)| (x.ln(), y.ln()))
        .collect();
    if logs.len() < 2 {
        return None;
    }
    let n = logs.len() as f64;
    let mean_x = logs.iter().map(|p| p.0).sum::<f64>() / n;
    let mean_y = logs.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = logs.iter().map(|p| (p.0 - mean_x).powi(2)).sum();
    let sxy: f64 = logs.iter().map(|p| (p.0 - mean_x) * (p.1 - mean_y)).sum();
    (sxx > 0.0).then(|| sxy / sxx)
}

/// Markdown for the two curves.
pub fn curves_markdown(pixels: &[Point], objects: &[Point]) -> String {
    let mut md = String::new();
    let _ = writeln!(
        md,
        "### Time against pixels (seed scene, aa 1, 1 thread)\n\n| pixels | time (ms) | ns per pixel | rays |\n|---:|---:|---:|---:|"
    );
    for p in pixels {
        let _ = writeln!(
            md,
            "| {:.0} | {:.1} | {:.0} | {} |",
            p.x,
            p.seconds * 1e3,
            p.seconds * 1e9 / p.x,
            p.rays
        );
    }
    let _ = writeln!(
        md,
        "\n### Time against objects (many spheres, aa 1, 1 thread)\n\n| spheres | time (ms) | × the fewest | rays |\n|---:|---:|---:|---:|"
    );
    let first = objects.first().map_or(1.0, |p| p.seconds);
    for p in objects {
        let _ = writeln!(
            md,
            "| {:.0} | {:.1} | {:.2} | {} |",
            p.x,
            p.seconds * 1e3,
            p.seconds / first,
            p.rays
        );
    }
    md
}

/// The two curves as a figure.
pub fn curves_panels(pixels: &[Point], objects: &[Point]) -> Vec<Panel> {
    let linear = |points: &[Point]| -> Vec<(f64, f64)> {
        // The straight line through the first point: what linear growth would give.
        let Some(first) = points.first() else {
            return Vec::new();
        };
        points
            .iter()
            .map(|p| (p.x, first.seconds * 1e3 * p.x / first.x))
            .collect()
    };
    vec![
        Panel {
            title: "Time against pixels (seed, aa 1, 1 thread)".into(),
            x_label: "pixels (log)".into(),
            y_label: "time (ms, log)".into(),
            log_x: true,
            log_y: true,
            series: vec![
                Series {
                    label: "measured".into(),
                    points: pixels.iter().map(|p| (p.x, p.seconds * 1e3)).collect(),
                    joined: true,
                    markers: true,
                },
                Series {
                    label: "linear".into(),
                    points: linear(pixels),
                    joined: true,
                    markers: false,
                },
            ],
        },
        Panel {
            title: "Time against objects (spheres, 600×400, aa 1)".into(),
            x_label: "spheres (log)".into(),
            y_label: "time (ms, log)".into(),
            log_x: true,
            log_y: true,
            series: vec![
                Series {
                    label: "measured".into(),
                    points: objects.iter().map(|p| (p.x, p.seconds * 1e3)).collect(),
                    joined: true,
                    markers: true,
                },
                Series {
                    label: "linear (the seed's growth)".into(),
                    points: linear(objects),
                    joined: true,
                    markers: false,
                },
            ],
        },
    ]
}

#[cfg(test)]
mod tests {
    use super::loglog_slope;

    #[test]
    fn slope_of_a_power_law_is_its_exponent() {
        let points: Vec<(f64, f64)> = [1.0, 10.0, 100.0, 1000.0]
            .iter()
            .map(|&x| (x, 3.0 * f64::powf(x, 0.75)))
            .collect();
        let slope = loglog_slope(&points).expect("four points");
        assert!((slope - 0.75).abs() < 1e-12, "{slope}");
    }

    #[test]
    fn slope_ignores_points_off_the_log_scale_and_needs_two() {
        let points = [(0.0, 5.0), (2.0, 4.0), (4.0, 8.0), (8.0, -1.0)];
        let slope = loglog_slope(&points).expect("two usable points");
        assert!((slope - 1.0).abs() < 1e-12, "{slope}");
        assert_eq!(loglog_slope(&[(1.0, 1.0)]), None);
        assert_eq!(loglog_slope(&[(3.0, 1.0), (3.0, 2.0)]), None);
    }
}
