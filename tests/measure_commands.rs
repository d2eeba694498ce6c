//! `tessera bench` and `tessera simulate` through the real binary: each writes what
//! docs/performance.md and docs/simulation.md are made of, and refuses bad input with
//! one line.
//!
//! The benchmark runs with `--quick` on tiny frames: these tests check that the tables,
//! the CSV and the plots are complete and well formed, never the figures (timings are
//! for the benchmark itself, on a quiet machine).

mod common;

use std::time::Duration;

use common::{ok, tessera};
use tempfile::TempDir;

const TIMEOUT: Duration = Duration::from_secs(300);

/// The four scenes of the speed-against-error suite.
const SCENES: [&str; 4] = ["seed", "spheres", "checker-horizon", "thin-features"];

#[test]
fn bench_writes_its_tables_csv_and_plots() {
    let dir = TempDir::new().unwrap();
    let run = ok(
        tessera(
            dir.path(),
            &[
                "bench",
                "--quick",
                "--out",
                "out",
                "--width",
                "48",
                "--height",
                "32",
                "--reference-aa",
                "8",
                "--max-runs",
                "1",
                "--min-time-ms",
                "0",
                "--threads",
                "2",
            ],
            TIMEOUT,
        ),
        "tessera bench --quick",
    );
    assert!(run.stderr.contains("results in out"), "{}", run.stderr);
    let out = dir.path().join("out");

    // The error table: one CSV line per scene and setting, every number finite where
    // it must be, and the Markdown naming each scene and the Pareto front.
    let csv = std::fs::read_to_string(out.join("bench.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    for column in [
        "scene", "family", "aa", "time_ms", "rays", "rmse", "psnr_db",
    ] {
        assert!(header.contains(&column), "no {column} column in {header:?}");
    }
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    for scene in SCENES {
        let of_scene: Vec<_> = rows.iter().filter(|r| r[0] == scene).collect();
        // Quick: grid 1, 2, 4; jittered 2; adaptive at one target.
        assert_eq!(of_scene.len(), 5, "rows of {scene}: {of_scene:?}");
        for row in of_scene {
            assert_eq!(row.len(), header.len(), "{row:?}");
            let rmse: f64 = row[header.iter().position(|c| *c == "rmse").unwrap()]
                .parse()
                .unwrap();
            assert!(rmse.is_finite() && rmse >= 0.0, "{row:?}");
        }
    }
    let md = std::fs::read_to_string(out.join("bench.md")).unwrap();
    for scene in SCENES {
        assert!(md.contains(&format!("### {scene}")), "{md}");
    }
    assert!(md.contains('◆'), "no Pareto front marked:\n{md}");

    // The scaling report: pixels, objects, the farm's speed-up beside the seed's table
    // 1, and the pull scheduler against a static split, measured on a real local farm.
    let scaling = std::fs::read_to_string(out.join("scaling.md")).unwrap();
    for section in [
        "Time against pixels",
        "Time against objects",
        "Farm speed-up",
        "4.42",
        "Pull scheduler against a static split",
    ] {
        assert!(scaling.contains(section), "no {section:?} in:\n{scaling}");
    }

    for png in ["bench.png", "scaling.png"] {
        let image = image::open(out.join(png)).unwrap_or_else(|e| panic!("{png}: {e}"));
        assert!(image.width() > 400 && image.height() > 300, "{png}");
    }
}

#[test]
fn simulate_reports_a_run_and_refuses_a_farm_without_jobs() {
    let dir = TempDir::new().unwrap();
    let args = [
        "simulate",
        "--workers",
        "40",
        "--jobs",
        "2",
        "--width",
        "640",
        "--height",
        "360",
        "--seed",
        "7",
    ];
    let first = ok(tessera(dir.path(), &args, TIMEOUT), "tessera simulate");
    for field in ["makespan", "ideal", "efficiency"] {
        assert!(
            first.stdout.to_lowercase().contains(field),
            "no {field} in:\n{}",
            first.stdout
        );
    }

    let empty = tessera(dir.path(), &["simulate", "--jobs", "0"], TIMEOUT);
    assert!(!empty.status.success());
    let stderr = empty.stderr.trim_end();
    assert!(
        stderr.starts_with("error: cannot simulate this farm:") && !stderr.contains('\n'),
        "{stderr}"
    );
}
