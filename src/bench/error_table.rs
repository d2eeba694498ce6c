//! `tessera bench`'s speed-against-error table: every benchmark scene rendered with each
//! sampling setting, timed, and compared with a converged reference render.

use std::fmt::Write as _;
use std::path::Path;
use std::time::Duration;

use anyhow::{Context, Result};
use render::{metrics, RenderSettings, Sampling, Scene};

use super::measure::{self, Timed};
use super::scenes::{self, BenchScene};
use super::Options;
use crate::plot::{Panel, Series};

/// One sampling setting.
struct Setting {
    family: &'static str,
    aa: u32,
    sampling: Sampling,
}

impl Setting {
    fn label(&self) -> String {
        match self.sampling {
            Sampling::Adaptive { .. } => format!(
                "adaptive ≤{}², target {}",
                self.aa,
                self.sampling.target_error().unwrap_or(0.0)
            ),
            _ => format!("{} {}²", self.family, self.aa),
        }
    }
}

/// Grid aa 1 to 8, jittered 2 to 8, and adaptive with an 8 × 8 budget at several targets.
fn settings(quick: bool) -> Vec<Setting> {
    let grid: &[u32] = if quick {
        &[1, 2, 4]
    } else {
        &[1, 2, 3, 4, 6, 8]
    };
    let jittered: &[u32] = if quick { &[2] } else { &[2, 4, 8] };
    let targets: &[f64] = if quick {
        &[2.0]
    } else {
        &[8.0, 4.0, 2.0, 1.0, 0.5]
    };
    let budget = if quick { 4 } else { 8 };
    let mut out = Vec::new();
    out.extend(grid.iter().map(|&aa| Setting {
        family: "grid",
        aa,
        sampling: Sampling::Grid,
    }));
    out.extend(jittered.iter().map(|&aa| Setting {
        family: "jittered",
        aa,
        sampling: Sampling::Jittered,
    }));
    out.extend(targets.iter().map(|&t| Setting {
        family: "adaptive",
        aa: budget,
        sampling: Sampling::adaptive(t).expect("a valid target"),
    }));
    out
}

/// One line of the table.
pub struct Row {
    pub scene: &'static str,
    pub family: &'static str,
    pub setting: String,
    pub aa: u32,
    pub target: Option<f64>,
    pub ms: f64,
    pub rays: u64,
    pub samples_per_pixel: f64,
    pub estimated_error: f64,
    pub error: metrics::ImageError,
}

/// Runs the table; writes `bench.md`, `bench.csv` and `bench.png` into `out`.
pub fn run(opts: &Options, out: &Path) -> Result<Vec<Row>> {
    let pool = measure::pool(opts.threads)?;
    let mut rows = Vec::new();
    let reference_aa = opts.reference_aa;
    for bench in scenes::error_suite() {
        let scene = parse(&bench)?;
        let base = RenderSettings {
            width: opts.width,
            height: opts.height,
            ..scene.settings
        };
        eprintln!(
            "{}: reference, grid {reference_aa}×{reference_aa}",
            bench.name
        );
        let reference = measure::time_frame(
            &scene,
            RenderSettings {
                aa: reference_aa,
                sampling: Sampling::Grid,
                ..base
            },
            &pool,
            Duration::ZERO,
            1,
        );
        std::fs::write(
            out.join(format!("{}-reference.png", bench.name)),
            reference.frame.image.to_png(),
        )?;
        for setting in settings(opts.quick) {
            let timed = measure::time_frame(
                &scene,
                RenderSettings {
                    aa: setting.aa,
                    sampling: setting.sampling,
                    ..base
                },
                &pool,
                opts.min_time,
                opts.max_runs,
            );
            let row = row(&bench, &setting, &timed, &reference);
            eprintln!(
                "{}: {:<26} {:>9.1} ms  RMSE {:>6.3}",
                bench.name, row.setting, row.ms, row.error.rmse
            );
            rows.push(row);
        }
    }
    std::fs::write(out.join("bench.md"), markdown(&rows, opts))?;
    std::fs::write(out.join("bench.csv"), csv(&rows))?;
    crate::plot::write_png(&out.join("bench.png"), &panels(&rows), 2, (640, 480))?;
    Ok(rows)
}

fn parse(bench: &BenchScene) -> Result<Scene> {
    render::parse_scene(&bench.json).with_context(|| format!("benchmark scene {}", bench.name))
}

fn row(bench: &BenchScene, setting: &Setting, timed: &Timed, reference: &Timed) -> Row {
    let frame = &timed.frame;
    let pixels = (frame.image.width as f64) * (frame.image.height as f64);
    Row {
        scene: bench.name,
        family: setting.family,
        setting: setting.label(),
        aa: setting.aa,
        target: setting.sampling.target_error(),
        ms: timed.seconds * 1e3,
        rays: frame.rays,
        samples_per_pixel: frame.samples as f64 / pixels,
        estimated_error: frame.estimated_error(),
        error: metrics::compare(&reference.frame.image, &frame.image),
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

/// The fastest adaptive row at least as accurate as the most accurate grid row.
fn adaptive_against_best_grid<'r>(
    rows: &'r [Row],
    scene: &str,
) -> Option<(&'r Row, Option<&'r Row>)> {
    let best_grid = rows
        .iter()
        .filter(|r| r.scene == scene && r.family == "grid")
        .min_by(|a, b| a.error.rmse.total_cmp(&b.error.rmse))?;
    let adaptive = rows
        .iter()
        .filter(|r| r.scene == scene && r.family == "adaptive")
        .filter(|r| r.error.rmse <= best_grid.error.rmse)
        .min_by(|a, b| a.ms.total_cmp(&b.ms));
    Some((best_grid, adaptive))
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

fn markdown(rows: &[Row], opts: &Options) -> String {
    let mut md = String::new();
    let _ = writeln!(
        md,
        "Speed against error at {}×{}, {} thread(s); error against a grid {}×{} reference. \
         Time is the fastest of up to {} runs. `off>2` is the share of pixels with a channel \
         more than 2 levels off; `est.` is the renderer's own RMS error estimate (levels). \
         Rows marked ◆ are on the Pareto front (no other setting is both faster and more \
         accurate).\n",
        opts.width, opts.height, opts.threads, opts.reference_aa, opts.reference_aa, opts.max_runs
    );
    for scene in scene_names(rows) {
        let front = pareto(rows, scene);
        let what = scenes::error_suite()
            .into_iter()
            .find(|b| b.name == scene)
            .map_or("", |b| b.what);
        let _ = writeln!(md, "### {scene}\n\n{what}\n");
        let _ = writeln!(
            md,
            "| setting | time (ms) | samples/px | rays | RMSE | PSNR (dB) | off>2 | est. | |\n|---|---:|---:|---:|---:|---:|---:|---:|---|"
        );
        for (i, r) in rows.iter().enumerate().filter(|(_, r)| r.scene == scene) {
            let _ = writeln!(
                md,
                "| {} | {:.1} | {:.2} | {} | {:.3} | {} | {:.2}% | {} | {} |",
                r.setting,
                r.ms,
                r.samples_per_pixel,
                r.rays,
                r.error.rmse,
                psnr_text(r.error.psnr),
                r.error.share_off_by_more_than_2 * 100.0,
                // One sample per pixel has no spread to estimate an error from.
                if r.estimated_error.is_finite() {
                    format!("{:.2}", r.estimated_error)
                } else {
                    "—".to_owned()
                },
                if front.contains(&i) { "◆" } else { "" }
            );
        }
        md.push('\n');
        if let Some((grid, adaptive)) = adaptive_against_best_grid(rows, scene) {
            match adaptive {
                Some(a) => {
                    let _ = writeln!(
                        md,
                        "Adaptive ({}) reaches RMSE {:.3}, at least as good as the best grid \
                         ({}, RMSE {:.3}), in {:.1} ms instead of {:.1} ms: {:.0}% less time \
                         ({:.2}× faster).\n",
                        a.setting,
                        a.error.rmse,
                        grid.setting,
                        grid.error.rmse,
                        a.ms,
                        grid.ms,
                        100.0 * (1.0 - a.ms / grid.ms),
                        grid.ms / a.ms
                    );
                }
                None => {
                    let _ = writeln!(
                        md,
                        "No adaptive setting reaches the best grid's RMSE ({}, {:.3}).\n",
                        grid.setting, grid.error.rmse
                    );
                }
            }
        }
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

fn csv(rows: &[Row]) -> String {
    let mut out = String::from(
        "scene,family,aa,target_error,time_ms,rays,samples_per_pixel,rmse,psnr_db,share_off_by_more_than_2,estimated_error\n",
    );
    for r in rows {
        let _ = writeln!(
            out,
            "{},{},{},{},{:.3},{},{:.4},{:.5},{:.3},{:.6},{}",
            r.scene,
            r.family,
            r.aa,
            r.target.map_or(String::new(), |t| t.to_string()),
            r.ms,
            r.rays,
            r.samples_per_pixel,
            r.error.rmse,
            r.error.psnr,
            r.error.share_off_by_more_than_2,
            if r.estimated_error.is_finite() {
                format!("{:.4}", r.estimated_error)
            } else {
                String::new()
            }
        );
    }
    out
}

fn panels(rows: &[Row]) -> Vec<Panel> {
    scene_names(rows)
        .into_iter()
        .map(|scene| {
            let family = |f: &str| Series {
                label: f.to_owned(),
                points: rows
                    .iter()
                    .filter(|r| r.scene == scene && r.family == f)
                    .map(|r| (r.ms, r.error.rmse.max(1e-3)))
                    .collect(),
                joined: true,
                markers: true,
            };
            let front = Series {
                label: "Pareto front".into(),
                points: pareto(rows, scene)
                    .into_iter()
                    .map(|i| (rows[i].ms, rows[i].error.rmse.max(1e-3)))
                    .collect(),
                joined: true,
                markers: false,
            };
            Panel {
                title: scene.to_owned(),
                x_label: "time (ms, log)".into(),
                y_label: "RMSE (8-bit levels, log)".into(),
                log_x: true,
                log_y: true,
                series: vec![
                    family("grid"),
                    family("jittered"),
                    family("adaptive"),
                    front,
                ],
            }
        })
        .collect()
}
