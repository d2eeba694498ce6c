//! `tessera simulate` through the real binary: it writes what docs/simulation.md is
//! made of, and refuses bad input with one line. (The benchmarks, `tessera-bench`, are
//! tested in bench/tests/.)

use std::time::Duration;

use tempfile::TempDir;

use crate::support::{ok, shared, tessera};

const TIMEOUT: Duration = Duration::from_secs(300);

#[test]
fn simulate_reports_a_run_and_refuses_a_farm_without_jobs() {
    let _turn = shared();
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
