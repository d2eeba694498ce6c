//! The sphere half's cases: the seed frame and the sphere scenes, written once; the
//! floor program, run and read; and the tables of `renderer.md` that compare them
//! (whole process, where the time goes, against the floor, against the seed's
//! structure). Each case runs on the machinery shared with the mesh half.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{anyhow, bail, Context, Result};

use super::{median_min, ms, paired_ratio, AnchorKind, Case, CaseResult, Floor, NOT_GIVEN};
use crate::scenes::{self, thousands};
use crate::Options;

/// Writes the cases' scene files once into `dir`.
pub(super) fn write_cases(opts: &Options, dir: &Path) -> Result<Vec<Case>> {
    let write = |name: &str, json: &str| -> Result<PathBuf> {
        let path = dir.join(name);
        std::fs::write(&path, json).with_context(|| format!("cannot write {}", path.display()))?;
        Ok(path)
    };
    let seed = write("seed.json", &scenes::seed().json)?;
    let (small, large): ((u32, u32), (u32, u32)) = if opts.quick {
        ((150, 100), (480, 270))
    } else {
        ((600, 400), (1920, 1080))
    };
    let mut cases = vec![
        Case {
            name: format!("seed {}×{} aa 2", small.0, small.1),
            scene: seed.clone(),
            width: small.0,
            height: small.1,
            aa: 2,
            seed_frame: true,
            anchor: AnchorKind::Spheres,
        },
        Case {
            name: format!("seed {}×{} aa 4", large.0, large.1),
            scene: seed,
            width: large.0,
            height: large.1,
            aa: 4,
            seed_frame: false,
            anchor: AnchorKind::Spheres,
        },
    ];
    let counts: &[usize] = if opts.quick {
        &[10, 10_000]
    } else {
        &[10, 10_000, 100_000, 1_000_000]
    };
    for &count in counts {
        let scene = write(
            &format!("spheres-{count}.json"),
            &scenes::spheres(count).json,
        )?;
        let what = if count == 10 {
            "10 spheres + plane".to_owned()
        } else {
            format!("{} small spheres", thousands(count as u64))
        };
        cases.push(Case {
            name: format!("{what} {}×{} aa 1", small.0, small.1),
            scene,
            width: small.0,
            height: small.1,
            aa: 1,
            seed_frame: false,
            anchor: AnchorKind::Spheres,
        });
    }
    Ok(cases)
}

/// The best time in ms of the floor program's line named `name` (`NAME : … best of 11
/// 19.94 ms = …`).
fn limit_bench_ms(output: &str, name: &str) -> Option<f64> {
    output.lines().find_map(|line| {
        let (label, rest) = line.split_once(':')?;
        if label.trim() != name {
            return None;
        }
        let after = &rest[rest.find("best of ")? + "best of ".len()..];
        let mut words = after.split_whitespace();
        words.next()?; // the count of runs
        let ms: f64 = words.next()?.parse().ok()?;
        (words.next()? == "ms").then_some(ms)
    })
}

/// The seed frame's floor from the floor program's output.
pub(super) fn parse_floor(output: &str) -> Option<Floor> {
    let camera = limit_bench_ms(output, "double AVX2 camera rays");
    let skip = limit_bench_ms(output, "double AVX2 camera, skip");
    let intersection_ms = match (camera, skip) {
        (Some(a), Some(b)) => a.min(b),
        (a, b) => a.or(b)?,
    };
    Some(Floor {
        intersection_ms,
        shading_ms: limit_bench_ms(output, "double AVX2 shading")?,
    })
}

pub(super) fn run_limit_bench(path: &Path) -> Result<Floor> {
    eprintln!("renderer: running {}", path.display());
    let output = Command::new(path)
        .stdin(Stdio::null())
        .output()
        .with_context(|| format!("cannot run {}", path.display()))?;
    let text = String::from_utf8_lossy(&output.stdout);
    if !output.status.success() {
        bail!("{} failed: {}", path.display(), output.status);
    }
    parse_floor(&text).ok_or_else(|| {
        anyhow!(
            "{}: no \"double AVX2 camera rays\" (or \"skip\") and \"double AVX2 shading\" lines in:\n{text}",
            path.display()
        )
    })
}

/// The sphere cases: whole process, where the time goes, the floor, the seed structure.
pub(super) fn spheres_markdown(results: &[CaseResult], floor: Option<Floor>) -> String {
    let mut md = String::new();
    let _ = writeln!(
        md,
        "## Whole process\n\n\
         | case | Tessera, 1 thread | anchor, 1 thread | Tessera / anchor | Tessera, 2 threads | speed-up 2 / 1 | images identical? |\n\
         |---|---:|---:|---:|---:|---:|---|"
    );
    for r in results {
        let ratio = r.anchor.as_ref().map_or(NOT_GIVEN.to_owned(), |a| {
            paired_ratio(&r.tessera_1, a).map_or("–".into(), |x| format!("{x:.2}"))
        });
        let speedup =
            paired_ratio(&r.tessera_1, &r.tessera_2).map_or("–".into(), |x| format!("{x:.2}"));
        let mut images = r
            .anchor_image
            .map_or_else(|| format!("{NOT_GIVEN} (anchor)"), |d| d.to_string());
        if r.threads_image != "identical" {
            let _ = write!(images, "; Tessera 2 threads against 1: {}", r.threads_image);
        }
        let _ = writeln!(
            md,
            "| {} | {} | {} | {ratio} | {} | {speedup} | {images} |",
            r.case.name,
            median_min(&r.tessera_1),
            r.anchor.as_ref().map_or(NOT_GIVEN.to_owned(), median_min),
            median_min(&r.tessera_2),
        );
    }
    let _ = writeln!(
        md,
        "\nTessera / anchor (below 1: Tessera is faster) and the speed-up are medians of \
         the ratios of runs made one after the other (Tessera 1 thread to the anchor's \
         next run, to Tessera's 2-thread run), steadier than ratios of medians when the \
         machine is shared. The images are compared pixel for \
         pixel after decoding both PNGs (Tessera's 1-thread image against the anchor's; \
         Tessera's 2-thread image is also checked against its 1-thread one and only \
         mentioned if it differs).\n\n\
         ### Where the time goes (medians)\n\n\
         | case | Tessera tracing, 1 thread | Tessera tracing, 2 threads | anchor parse | anchor build | anchor tracing | Tessera peak RSS | anchor peak RSS |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|"
    );
    let opt_ms = |v: Option<f64>| v.map_or(NOT_GIVEN.to_owned(), ms);
    let mib = |v: Option<f64>| v.map_or("–".to_owned(), |m| format!("{m:.0} MiB"));
    for r in results {
        let a = r.anchor.as_ref();
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} | {} |",
            r.case.name,
            opt_ms(r.tessera_1.median_of(|x| x.tracing)),
            opt_ms(r.tessera_2.median_of(|x| x.tracing)),
            opt_ms(a.and_then(|a| a.median_of(|x| x.parse))),
            opt_ms(a.and_then(|a| a.median_of(|x| x.build))),
            opt_ms(a.and_then(|a| a.median_of(|x| x.tracing))),
            mib(r.tessera_1.peak_rss_mib()),
            a.map_or(NOT_GIVEN.to_owned(), |a| mib(a.peak_rss_mib())),
        );
    }
    let _ = writeln!(
        md,
        "\nTracing is what each program prints: for Tessera the render line of `tessera \
         render` (after loading the scene and building the tracer, before writing the \
         PNG), for the anchor the time after the BVH build. Peak RSS is the largest \
         `VmHWM` read from `/proc/PID/status` every 5 ms during the case's runs (– when \
         no run lasted 50 ms).\n"
    );

    let seed = results.iter().find(|r| r.case.seed_frame);
    let seed_name = seed.map_or("the seed frame".to_owned(), |r| r.case.name.clone());
    let _ = writeln!(md, "## Against the floor ({seed_name})\n");
    let best_tracing = seed.and_then(|r| {
        r.tessera_1
            .0
            .iter()
            .filter_map(|x| x.tracing)
            .reduce(f64::min)
    });
    match (
        floor,
        seed.and_then(|r| r.tessera_1.median_of(|x| x.tracing)),
        best_tracing,
    ) {
        (Some(f), Some(tracing), Some(best)) => {
            let _ = writeln!(
                md,
                "| intersection floor | shading floor | floor | Tessera tracing, 1 thread: median (best) | × the floor: median (best) |\n\
                 |---:|---:|---:|---:|---:|\n\
                 | {:.2} ms | {:.2} ms | {:.2} ms | {} ({}) | {:.2} ({:.2}) |\n\n\
                 The floor program's best times: intersection is the faster of its \
                 \"double AVX2 camera rays\" and \"double AVX2 camera, skip\" lines (the \
                 seed frame's camera rays against its three objects in AVX2 doubles, rays \
                 held in L1), shading its \"double AVX2 shading\" line (the two-light \
                 shading kernel on the frame's hits). Tessera's figures are the median \
                 and the best tracing time of the seed frame's 1-thread runs above (the \
                 best compares like with like: the floor is a best of 11).\n",
                f.intersection_ms,
                f.shading_ms,
                f.total_ms(),
                ms(tracing),
                ms(best),
                tracing * 1e3 / f.total_ms(),
                best * 1e3 / f.total_ms()
            );
        }
        _ => {
            let _ = writeln!(md, "Floor program {NOT_GIVEN}.\n");
        }
    }

    let _ = writeln!(md, "## Against the seed's structure in C++ ({seed_name})\n");
    match seed.and_then(|r| Some((r, r.seed_cpp.as_ref()?))) {
        Some((r, runs)) => {
            let multiple = match paired_ratio(&r.tessera_1, runs) {
                Some(x) => format!("{x:.3} (Tessera {:.1}× faster)", 1.0 / x),
                None => "–".into(),
            };
            let _ = writeln!(
                md,
                "| seed structure, whole process | its rendering | Tessera, 1 thread, whole process | Tessera ÷ seed structure | images |\n\
                 |---:|---:|---:|---:|---|\n\
                 | {} | {} | {} | {multiple} | {} |\n\n\
                 `render/benches/seed_structured.cpp` keeps the seed program's design \
                 (objects behind virtual calls, a new vector of intersections for every \
                 ray, the textbook quadratic, a fixed epsilon, double, one thread) with the \
                 shading of docs/scene-format.md. The ratio is the median of the ratios of \
                 runs in the same round, as above. Where its pixels differ from Tessera's, \
                 it is at silhouettes and shadow edges, where its fixed epsilon and \
                 quadratic round differently from Tessera's exact methods.\n",
                median_min(runs),
                opt_ms(runs.median_of(|x| x.tracing)),
                median_min(&r.tessera_1),
                r.seed_cpp_image.as_deref().unwrap_or("–"),
            );
        }
        None => {
            let _ = writeln!(md, "Seed structure in C++ {NOT_GIVEN}.\n");
        }
    }
    md
}
