//! The error table's report: the Markdown page with its goals and findings, the CSV,
//! and the chart's panels, made from the measured rows. Reading the rows (which is
//! the fastest as accurate as another, the Pareto front of a scene) is the report's
//! alone: the measurements know nothing of how they are shown.

use std::fmt::Write as _;

use render::adaptive;

use super::{Plan, Reference, Role, Row, GOAL_ESTIMATE_FACTOR, GOAL_TARGET_RATIO, GOAL_TIME_RATIO};
use crate::plot::{Panel, Series};
use crate::scenes;
use crate::Options;

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

pub(super) fn markdown(
    rows: &[Row],
    references: &[Reference],
    plan: &Plan,
    opts: &Options,
) -> String {
    let mut md = String::new();
    let h = plan.headline_aa;
    let _ = writeln!(
        md,
        "Speed against error at {}×{}, {} thread(s); error against a grid {}×{} reference. \
         Time is the fastest of up to {} runs (each setting repeated until {} ms have \
         passed). RMSE is measured over the 8-bit channels; `est.` is the renderer's own \
         estimate of it. Adaptive rows are rendered to a target by the ladder of \
         `render::adaptive` (the path of `--target-error`); the ladder's rows have a \
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
        adaptive::sample_cap(plan.ladder_aa),
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
        adaptive::sample_cap(h),
        adaptive::sample_cap(plan.ladder_aa),
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
         `render::adaptive`.{}\n",
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

pub(super) fn csv(rows: &[Row], references: &[Reference]) -> String {
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
                adaptive::sample_cap(r.aa)
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
pub(super) fn panels(rows: &[Row]) -> Vec<Panel> {
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
