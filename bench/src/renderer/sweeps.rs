//! The scaling half: time against pixels, objects, lights and mirror depth, measured
//! in process by [`crate::scaling`], written as `renderer-scaling.{md,csv,png}` with the
//! log-log slope of each curve.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Result;

use super::{cpu_model, ms, slope_text};
use crate::plot::{Panel, Series};
use crate::scaling::{self, Point};
use crate::scenes::thousands;
use crate::Options;

/// One sweep of the scaling half.
struct Sweep {
    name: &'static str,
    title: &'static str,
    x_label: &'static str,
    points: Vec<Point>,
}

impl Sweep {
    fn render_points(&self) -> Vec<(f64, f64)> {
        self.points.iter().map(|p| (p.x, p.seconds * 1e3)).collect()
    }

    fn setup_points(&self) -> Vec<(f64, f64)> {
        self.points
            .iter()
            .filter_map(|p| Some((p.x, p.setup_seconds? * 1e3)))
            .collect()
    }
}

/// Time against pixels, objects, lights and mirror depth: renderer-scaling.{md,csv,png}.
pub(super) fn write_scaling(opts: &Options, out: &Path) -> Result<()> {
    let objects: &[usize] = if opts.quick {
        &[10, 100, 1000, 10_000]
    } else {
        &[10, 100, 1000, 10_000, 100_000, 1_000_000]
    };
    let sweeps = [
        Sweep {
            name: "pixels",
            title: "Time against pixels (seed, aa 1)",
            x_label: "pixels (log)",
            points: scaling::time_against_pixels(opts)?,
        },
        Sweep {
            name: "objects",
            title: "Time against objects (spheres, aa 1)",
            x_label: "spheres (log)",
            points: scaling::time_against_objects(opts, objects)?,
        },
        Sweep {
            name: "lights",
            title: "Time against lights (seed objects, aa 1)",
            x_label: "lights (log)",
            points: scaling::time_against_lights(opts)?,
        },
        Sweep {
            name: "depth",
            title: "Time against mirror depth (hall of mirrors)",
            x_label: "max depth (log; 0 in the table only)",
            points: scaling::time_against_depth(opts)?,
        },
    ];
    let (w, h) = if opts.quick { (150, 100) } else { (600, 400) };
    let hall = if opts.quick { 120 } else { 480 };
    let mut md = format!(
        "# How the renderer's time scales\n\n\
         Regenerated with the renderer comparison (`renderer.md`, same command). In \
         process through the `render` crate, 1 thread, each point the fastest of up to \
         {} renders within {} ms; the slope is the least-squares fit of log time against \
         log x (1: linear, 0: flat).\n\n\
         - CPU: {}\n\
         - pixels: the seed scene at aa 1 from 150 × 100 up (the seed report's figure 3)\n\
         - objects: `spheres(count)`, small spheres over a plane, at {w} × {h}, aa 1; \
         loading (JSON parsing and checking) and building the tracer timed apart from \
         rendering (the seed report's figure 2)\n\
         - lights: the seed scene's three objects under 1 to 64 equal lights on a circle \
         above, {w} × {h}, aa 1\n\
         - depth: `scenes/hall-of-mirrors.json` (facing mirrors of reflectance 0.9) at \
         {hall} × {hall}, aa 1, with its depth limit from 0 up; the fit leaves out depth 0\n\n\
         | sweep | from | to | slope (render) | slope (load + build) |\n\
         |---|---:|---:|---:|---:|\n",
        opts.max_runs,
        opts.min_time.as_millis(),
        cpu_model(),
    );
    for sweep in &sweeps {
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} |",
            sweep.name,
            thousands(sweep.points.first().map_or(0.0, |p| p.x) as u64),
            thousands(sweep.points.last().map_or(0.0, |p| p.x) as u64),
            slope_text(scaling::loglog_slope(&sweep.render_points())),
            if sweep.name == "objects" {
                slope_text(scaling::loglog_slope(&sweep.setup_points()))
            } else {
                "–".into()
            },
        );
    }
    let mut csv = String::from("sweep,x,render_s,load_build_s,rays\n");
    for sweep in &sweeps {
        let with_setup = sweep.name == "objects";
        let _ = writeln!(
            md,
            "\n### {}\n\n| {} | render | rays | ns per ray |{}\n|---:|---:|---:|---:|{}",
            sweep.title,
            sweep.name,
            if with_setup { " load + build |" } else { "" },
            if with_setup { "---:|" } else { "" },
        );
        for p in &sweep.points {
            let _ = writeln!(
                md,
                "| {} | {} | {} | {:.1} |{}",
                thousands(p.x as u64),
                ms(p.seconds),
                thousands(p.rays),
                p.seconds * 1e9 / p.rays.max(1) as f64,
                p.setup_seconds
                    .map_or(String::new(), |s| format!(" {} |", ms(s))),
            );
            let _ = writeln!(
                csv,
                "{},{},{:.6},{},{}",
                sweep.name,
                p.x,
                p.seconds,
                p.setup_seconds.map_or(String::new(), |s| format!("{s:.6}")),
                p.rays
            );
        }
    }
    std::fs::write(out.join("renderer-scaling.md"), md)?;
    std::fs::write(out.join("renderer-scaling.csv"), csv)?;
    let panels: Vec<Panel> = sweeps.iter().map(scaling_panel).collect();
    crate::plot::write_png(&out.join("renderer-scaling.png"), &panels, 2, (600, 440))
}

fn scaling_panel(sweep: &Sweep) -> Panel {
    // A log axis has no 0: the depth sweep's first point stays in the table.
    let positive = |points: Vec<(f64, f64)>| -> Vec<(f64, f64)> {
        points.into_iter().filter(|p| p.0 > 0.0).collect()
    };
    let render = positive(sweep.render_points());
    let mut series = vec![Series {
        label: format!(
            "render (slope {})",
            slope_text(scaling::loglog_slope(&render))
        ),
        points: render,
        joined: true,
        markers: true,
    }];
    let setup = positive(sweep.setup_points());
    if !setup.is_empty() {
        series.push(Series {
            label: format!(
                "load + build (slope {})",
                slope_text(scaling::loglog_slope(&setup))
            ),
            points: setup,
            joined: true,
            markers: true,
        });
    }
    Panel {
        title: sweep.title.into(),
        x_label: sweep.x_label.into(),
        y_label: "time (ms, log)".into(),
        log_x: true,
        log_y: true,
        series,
    }
}
