//! The scaling report: time against pixels and against objects on one machine, the
//! farm's speed-up with 1 to N workers, and the pull scheduler against a static split.

use std::fmt::Write as _;

use anyhow::{Context, Result};
use render::{RenderSettings, Scene};

use super::measure;
use super::scenes::{self, BenchScene};
use super::Options;
use crate::plot::{Panel, Series};

/// One measured point of a curve.
pub struct Point {
    pub x: f64,
    pub seconds: f64,
    pub rays: u64,
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
        });
    }
    Ok(out)
}

/// The many-spheres scene with 10 to 10,000 spheres at 600 × 400, aa 1, on one thread.
pub fn time_against_objects(opts: &Options) -> Result<Vec<Point>> {
    let pool = measure::pool(1)?;
    let counts: &[usize] = if opts.quick {
        &[10, 100, 1000]
    } else {
        &[10, 30, 100, 300, 1000, 3000, 10_000]
    };
    let (width, height) = if opts.quick { (150, 100) } else { (600, 400) };
    let mut out = Vec::new();
    for &count in counts {
        let scene = parse(&scenes::spheres(count))?;
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
        eprintln!("objects: {count} spheres: {:.1} ms", timed.seconds * 1e3);
        out.push(Point {
            x: count as f64,
            seconds: timed.seconds,
            rays: timed.frame.rays,
        });
    }
    Ok(out)
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
