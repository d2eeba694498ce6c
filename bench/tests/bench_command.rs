//! `tessera-bench` through the real binaries: it writes what docs/performance.md is
//! made of, running the `tessera` executable beside it for the farm.
//!
//! The benchmark runs with `--quick` on tiny frames: these tests check that the tables,
//! the CSV and the plots are complete and well formed, never the figures (timings are
//! for the benchmark itself, on a quiet machine).
//!
//! `tessera` must have been built into the same directory: `cargo test --workspace`
//! builds it (the tessera package's own tests need it) before any test runs; `cargo
//! test -p tessera-bench` alone does not, and these tests then fail saying so. The
//! suite with the static split needs root for its cgroup: without, that test prints
//! `skipped: REASON` and passes, unless `TESSERA_REQUIRE_PRIVILEGED=1` (set in CI).

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use tempfile::TempDir;

const TIMEOUT: Duration = Duration::from_secs(300);

/// The benchmark under test.
const BENCH: &str = env!("CARGO_BIN_EXE_tessera-bench");

/// The `tessera` executable beside the benchmark, where it looks for it: its absence
/// fails the test, since a skipped benchmark test would pass without testing anything.
fn tessera_beside() -> PathBuf {
    let path = Path::new(BENCH).with_file_name(format!("tessera{}", std::env::consts::EXE_SUFFIX));
    assert!(
        path.is_file(),
        "{} is missing: tessera-bench runs the tessera executable beside it; build it \
         first with `cargo build --release` (or run `cargo test --workspace --release`, \
         which builds it)",
        path.display()
    );
    path
}

/// What a finished `tessera-bench` run printed.
struct Run {
    status: std::process::ExitStatus,
    stdout: String,
    stderr: String,
}

/// `tessera-bench ARGS` in `dir`; killed, and the test failed, after [`TIMEOUT`].
fn bench(dir: &Path, args: &[&str]) -> Run {
    let child = Command::new(BENCH)
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("cannot start tessera-bench");
    let pid = child.id();
    let (done, finished) = mpsc::channel::<std::io::Result<Output>>();
    std::thread::spawn(move || done.send(child.wait_with_output()));
    match finished.recv_timeout(TIMEOUT) {
        Ok(output) => {
            let output = output.expect("cannot wait for tessera-bench");
            Run {
                status: output.status,
                stdout: String::from_utf8_lossy(&output.stdout).into_owned(),
                stderr: String::from_utf8_lossy(&output.stderr).into_owned(),
            }
        }
        Err(_) => {
            let _ = Command::new("kill").args(["-9", &pid.to_string()]).status();
            panic!("tessera-bench {args:?} still running after {TIMEOUT:?}: killed");
        }
    }
}

/// The four scenes of the speed-against-error suite.
const SCENES: [&str; 4] = ["seed", "spheres", "checker-horizon", "thin-features"];

#[test]
fn bench_writes_its_tables_csv_and_plots() {
    tessera_beside();
    // The static split of the scaling suite slows a worker through a cgroup.
    if let Err(e) = localfarm::CpuLimit::probe() {
        return localfarm::unprivileged("bench_writes_its_tables_csv_and_plots", &e);
    }
    let dir = TempDir::new().unwrap();
    let run = bench(
        dir.path(),
        &[
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
            "--reference-check",
        ],
    );
    assert!(
        run.status.success(),
        "tessera-bench --quick failed ({}):\nstdout: {}\nstderr: {}",
        run.status,
        run.stdout,
        run.stderr
    );
    assert!(run.stderr.contains("results in out"), "{}", run.stderr);
    let out = dir.path().join("out");

    // The error table: one CSV line per scene and setting with every column, every
    // number finite where it must be, and the Markdown's sections: the headline, the
    // ladder against its targets, the time to each target, each sampler against the
    // grid, the reference check, and each scene with the Pareto front.
    let csv = std::fs::read_to_string(out.join("bench.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let column = |name: &str| {
        header
            .iter()
            .position(|c| *c == name)
            .unwrap_or_else(|| panic!("no {name} column in {header:?}"))
    };
    for name in [
        "scene",
        "family",
        "role",
        "aa",
        "target_error",
        "time_ms",
        "rays",
        "samples_per_pixel",
        "rmse",
        "psnr_db",
        "estimated_error",
        "estimate_over_measured",
        "measured_over_target",
        "capped_share",
        "rmse_against_check",
        "reference_check_rmse",
    ] {
        column(name);
    }
    let number = |row: &[&str], name: &str| -> f64 {
        row[column(name)]
            .parse()
            .unwrap_or_else(|e| panic!("{name} in {row:?}: {e}"))
    };
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    for scene in SCENES {
        let of_scene: Vec<_> = rows.iter().filter(|r| r[0] == scene).collect();
        // Quick: grid 1, 2, 4; jittered 2; adaptive at two targets, and at grid 4²'s
        // RMSE with its cap and with the ladder's.
        assert_eq!(of_scene.len(), 8, "rows of {scene}: {of_scene:?}");
        for row in &of_scene {
            assert_eq!(row.len(), header.len(), "{row:?}");
            let rmse = number(row, "rmse");
            assert!(rmse.is_finite() && rmse >= 0.0, "{row:?}");
            assert!(number(row, "reference_check_rmse") >= 0.0, "{row:?}");
            assert!(number(row, "rmse_against_check") >= 0.0, "{row:?}");
        }
        let adaptive: Vec<_> = of_scene.iter().filter(|r| r[1] == "adaptive").collect();
        assert_eq!(adaptive.len(), 4, "{adaptive:?}");
        for row in &adaptive {
            for name in ["target_error", "measured_over_target", "capped_share"] {
                assert!(number(row, name).is_finite(), "{name} in {row:?}");
            }
        }
        // The headline's target is the grid 4²'s measured RMSE (in thousandths).
        let grid4 = of_scene
            .iter()
            .find(|r| r[1] == "grid" && r[column("aa")] == "4")
            .expect("a grid 4² row");
        let headline = adaptive
            .iter()
            .find(|r| r[column("role")] == "headline")
            .expect("a headline row");
        assert!(
            (number(headline, "target_error") - number(grid4, "rmse")).abs() < 1e-3,
            "{headline:?} against {grid4:?}"
        );
    }
    let md = std::fs::read_to_string(out.join("bench.md")).unwrap();
    for section in [
        "## Adaptive at grid 4×4's RMSE",
        "## Adaptive against its target",
        "| measured / target |",
        "| estimate / measured |",
        "## Time to reach each target",
        "## Each sampler against grid 4×4",
        "RMSE(reference, check)",
    ] {
        assert!(md.contains(section), "no {section:?} in:\n{md}");
    }
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
        let bytes = std::fs::read(out.join(png)).unwrap_or_else(|e| panic!("{png}: {e}"));
        let image = coordinator::decode_png(&bytes).unwrap_or_else(|e| panic!("{png}: {e:#}"));
        assert!(image.width > 400 && image.height > 300, "{png}");
    }
}

#[test]
fn a_missing_tessera_executable_is_one_line_naming_it_and_how_to_build_it() {
    let dir = TempDir::new().unwrap();
    let missing = dir.path().join("no-such-dir/tessera");
    let run = bench(
        dir.path(),
        &[
            "--suite",
            "renderer",
            "--quick",
            "--tessera",
            missing.to_str().unwrap(),
        ],
    );
    assert!(!run.status.success());
    let stderr = run.stderr.trim_end();
    assert_eq!(
        stderr,
        format!(
            "error: no tessera executable at {}: build it with `cargo build --release` (or \
             give one with --tessera PATH)",
            missing.display()
        )
    );
    assert!(
        !dir.path().join("bench-results").exists(),
        "it wrote results"
    );
}
