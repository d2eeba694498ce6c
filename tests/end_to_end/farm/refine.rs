//! End-to-end tests of refining farm jobs and of farm jobs' time limits, through the
//! real `tessera` binary on 127.0.0.1.
//!
//! What is proven:
//!
//! - **Refine, don't restart.** A finished adaptive farm job refined to a lower target
//!   and to a larger `--aa` (`tessera refine JOB`) gives, byte for byte, the image of a
//!   direct farm job and of `tessera render` with the final settings; the old job stays
//!   as it was.
//! - **Nothing stored is trusted.** Refining a job whose stored tile states were damaged
//!   on disk (one byte flipped) is one `error: ` line naming the file, and writes no
//!   image; so is refining a grid job or a job that has not finished.
//! - **A time budget.** A farm job with `--time-limit` (`submit --wait`, `up`) ends, and
//!   its summary says the time limit stopped it; on a grid job it is one `error: ` line.

use std::path::Path;
use std::time::Duration;

use tempfile::TempDir;

use crate::support::{
    assert_same_png, client, ok, one_error_line, scene_path, shared, start_coordinator,
    start_worker, submit, tessera, try_status, wait_done, Run,
};

const JOB_TIMEOUT: Duration = Duration::from_secs(120);

/// A small frame with partial tiles at the right and bottom edges.
const SIZE: &[&str] = &["--width", "96", "--height", "72"];
const TILE: &[&str] = &["--tile", "24"];

/// `tessera refine JOB ARGS --wait -o DIR/NAME`.
fn refine(dir: &Path, addr: &str, job: u64, name: &str, extra: &[&str]) -> Run {
    let out = dir.join(name);
    let job = job.to_string();
    let mut all = vec!["refine", &job, "--wait", "-o", out.to_str().unwrap()];
    all.extend(extra);
    client(dir, addr, &all)
}

/// `tessera submit SCENE ARGS --wait -o DIR/NAME`.
fn submit_wait(dir: &Path, addr: &str, scene: &str, name: &str, extra: &[&str]) -> Run {
    let out = dir.join(name);
    let mut all = vec!["submit", scene, "--wait", "-o", out.to_str().unwrap()];
    all.extend(extra);
    client(dir, addr, &all)
}

#[test]
fn a_refined_farm_job_equals_a_direct_job_and_the_local_render() {
    let _turn = shared();
    let tmp = TempDir::new().unwrap();
    let dir = tmp.path();
    let (_coordinator, addr) = start_coordinator(
        dir,
        &dir.join("data"),
        "127.0.0.1:0",
        &[],
        "coordinator.log",
    );
    let _workers = [start_worker(dir, &addr, "a"), start_worker(dir, &addr, "b")];
    let seed = scene_path("seed.json");
    let first = [
        SIZE,
        TILE,
        &["--aa", "4", "--sampler", "adaptive", "--target-error", "4"],
    ]
    .concat();
    let job = submit(dir, &addr, &[&[seed.as_str()][..], &first].concat());
    wait_done(dir, &addr, job, JOB_TIMEOUT);
    assert!(
        dir.join("data/jobs")
            .join(job.to_string())
            .join("states.bin")
            .exists(),
        "a finished adaptive job keeps its tile states"
    );

    // To a lower target, and to a lower target with a larger cap.
    for (from, name, flags) in [
        (job, "lower", &["--target-error", "1.5"][..]),
        (job, "larger", &["--target-error", "1.5", "--aa", "6"][..]),
    ] {
        let run = ok(
            refine(dir, &addr, from, &format!("refined-{name}.png"), flags),
            "refine",
        );
        assert!(
            run.stderr.contains("refining job"),
            "refine --wait says what it does: {}",
            run.stderr
        );
        let aa = if name == "larger" { "6" } else { "4" };
        let direct = [
            SIZE,
            TILE,
            &["--aa", aa, "--sampler", "adaptive", "--target-error", "1.5"],
        ]
        .concat();
        ok(
            submit_wait(dir, &addr, &seed, &format!("direct-{name}.png"), &direct),
            "a direct farm job",
        );
        let local = dir.join(format!("local-{name}.png"));
        let mut render = vec!["render", seed.as_str(), "-o", local.to_str().unwrap()];
        render.extend(
            [
                SIZE,
                &["--aa", aa, "--sampler", "adaptive", "--target-error", "1.5"],
            ]
            .concat(),
        );
        ok(tessera(dir, &render, JOB_TIMEOUT), "tessera render");
        let refined = dir.join(format!("refined-{name}.png"));
        assert_same_png(
            &refined,
            &dir.join(format!("direct-{name}.png")),
            &format!("refined ({name}) against a direct farm job"),
        );
        assert_same_png(
            &refined,
            &local,
            &format!("refined ({name}) against tessera render"),
        );
    }
    // The old job is as it was.
    let status = try_status(dir, &addr, job).expect("the old job is still there");
    assert_eq!(status["state"], "done");
    assert_eq!(status["target_error"], 4.0, "{status}");
}

#[test]
fn refining_damaged_states_grid_jobs_or_unfinished_jobs_is_one_error_line() {
    let _turn = shared();
    let tmp = TempDir::new().unwrap();
    let dir = tmp.path();
    let (_coordinator, addr) = start_coordinator(
        dir,
        &dir.join("data"),
        "127.0.0.1:0",
        &[],
        "coordinator.log",
    );
    let seed = scene_path("seed.json");

    // Not finished: no worker has joined yet, so the job waits.
    let waiting = submit(
        dir,
        &addr,
        &[
            &[seed.as_str()][..],
            SIZE,
            &["--aa", "4", "--sampler", "adaptive", "--target-error", "4"],
        ]
        .concat(),
    );
    let run = refine(dir, &addr, waiting, "waiting.png", &["--target-error", "1"]);
    let line = one_error_line(&run, "refining a queued job");
    assert!(line.contains("queued"), "{line}");
    assert!(!dir.join("waiting.png").exists(), "no image");

    let _worker = start_worker(dir, &addr, "a");
    wait_done(dir, &addr, waiting, JOB_TIMEOUT);

    // A grid job keeps no states.
    let grid = submit(
        dir,
        &addr,
        &[&[seed.as_str()][..], SIZE, &["--aa", "2"]].concat(),
    );
    wait_done(dir, &addr, grid, JOB_TIMEOUT);
    let run = refine(dir, &addr, grid, "grid.png", &["--target-error", "1"]);
    let line = one_error_line(&run, "refining a grid job");
    assert!(line.contains("grid sampling"), "{line}");
    assert!(!dir.join("grid.png").exists(), "no image");

    // Damaged states: one byte flipped in the middle of the file.
    let states = dir
        .join("data/jobs")
        .join(waiting.to_string())
        .join("states.bin");
    let mut bytes = std::fs::read(&states).expect("the job's states are stored");
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x01;
    std::fs::write(&states, &bytes).unwrap();
    let run = refine(dir, &addr, waiting, "damaged.png", &["--target-error", "1"]);
    let line = one_error_line(&run, "refining damaged states");
    assert!(
        line.contains("states.bin") && line.contains("damaged"),
        "{line}"
    );
    assert!(!dir.join("damaged.png").exists(), "no image");

    // A missing file is as clear.
    std::fs::remove_file(&states).unwrap();
    let run = refine(dir, &addr, waiting, "missing.png", &["--target-error", "1"]);
    let line = one_error_line(&run, "refining missing states");
    assert!(line.contains("missing"), "{line}");

    // An unknown job, and something that is neither a file nor a job id.
    let run = refine(dir, &addr, 999, "unknown.png", &["--target-error", "1"]);
    one_error_line(&run, "refining an unknown job");
    let run = client(
        dir,
        &addr,
        &["refine", "no-such-file", "--target-error", "1"],
    );
    let line = one_error_line(&run, "refining nothing");
    assert!(
        line.contains("no-such-file") && line.contains("cannot read render state"),
        "{line}"
    );
}

#[test]
fn a_farm_job_with_a_time_limit_says_the_limit_stopped_it() {
    let _turn = shared();
    let tmp = TempDir::new().unwrap();
    let dir = tmp.path();
    let (mut coordinator, addr) = start_coordinator(
        dir,
        &dir.join("data"),
        "127.0.0.1:0",
        &[],
        "coordinator.log",
    );
    let mut worker = start_worker(dir, &addr, "a");
    let seed = scene_path("seed.json");
    // A budget far too small for the smallest target at aa 16 (the whole ladder takes
    // about a second here): the time decides.
    const LARGER: &[&str] = &["--width", "192", "--height", "144"];
    let flags = [LARGER, TILE, &["--aa", "16", "--time-limit", "60ms"]].concat();
    let started = std::time::Instant::now();
    let run = ok(
        submit_wait(dir, &addr, &seed, "limited.png", &flags),
        "submit --time-limit",
    );
    let summary = run.stderr.lines().last().unwrap_or_default().to_owned();
    assert!(
        summary.contains("as far as the time limit allowed"),
        "{summary}"
    );
    assert!(summary.contains("estimated error"), "{summary}");
    assert!(
        started.elapsed() < Duration::from_secs(60),
        "the limit ends the job"
    );
    assert!(dir.join("limited.png").exists());
    let status = try_status(dir, &addr, 1).expect("the job's status");
    assert_eq!(status["stopped_on_time_limit"], true, "{status}");
    assert_eq!(status["time_limit_ms"], 60, "{status}");
    assert!(status["estimated_error"].as_f64().is_some(), "{status}");
    // With a target too, the summary says the limit came first.
    let flags = [
        LARGER,
        TILE,
        &[
            "--aa",
            "16",
            "--target-error",
            "0.01",
            "--time-limit",
            "60ms",
        ],
    ]
    .concat();
    let run = ok(
        submit_wait(dir, &addr, &seed, "limited-target.png", &flags),
        "submit --target-error --time-limit",
    );
    let summary = run.stderr.lines().last().unwrap_or_default().to_owned();
    assert!(
        summary.contains("stopped by the time limit before the target"),
        "{summary}"
    );
    // `tessera up` takes the limit too.
    let up_out = dir.join("up.png");
    let mut up = vec![
        "up",
        seed.as_str(),
        "--workers",
        "1",
        "-o",
        up_out.to_str().unwrap(),
    ];
    up.extend([LARGER, &["--aa", "16", "--time-limit", "60ms"]].concat());
    let run = ok(tessera(dir, &up, JOB_TIMEOUT), "up --time-limit");
    assert!(
        run.stderr.contains("as far as the time limit allowed"),
        "{}",
        run.stderr
    );
    assert!(up_out.exists());
    // What stopped the job is kept across a restart of the coordinator.
    worker.kill9();
    coordinator.kill9();
    let (_coordinator, addr) =
        start_coordinator(dir, &dir.join("data"), "127.0.0.1:0", &[], "restarted.log");
    let status = try_status(dir, &addr, 1).expect("the job is back");
    assert_eq!(status["stopped_on_time_limit"], true, "{status}");
    assert_eq!(status["time_limit_ms"], 60, "{status}");
    // A time limit on a grid job is one error line.
    let run = submit_wait(
        dir,
        &addr,
        &seed,
        "grid.png",
        &["--sampler", "grid", "--time-limit", "1s"],
    );
    one_error_line(&run, "a time limit on a grid job");
}

#[test]
fn a_job_refined_again_counts_its_refines_in_its_name() {
    let _turn = shared();
    let tmp = TempDir::new().unwrap();
    let dir = tmp.path();
    let (_coordinator, addr) = start_coordinator(
        dir,
        &dir.join("data"),
        "127.0.0.1:0",
        &[],
        "coordinator.log",
    );
    let _worker = start_worker(dir, &addr, "a");
    let seed = scene_path("seed.json");
    let flags = [SIZE, TILE, &["--aa", "4", "--target-error", "4"]].concat();
    let mut job = submit(dir, &addr, &[&[seed.as_str()][..], &flags].concat());
    wait_done(dir, &addr, job, JOB_TIMEOUT);
    let mut names = Vec::new();
    for target in ["2", "1"] {
        let run = ok(
            client(
                dir,
                &addr,
                &["refine", &job.to_string(), "--target-error", target],
            ),
            "refine",
        );
        job = run
            .stdout
            .trim()
            .parse()
            .expect("refine prints the new job's id");
        let status = wait_done(dir, &addr, job, JOB_TIMEOUT);
        names.push(status["name"].as_str().unwrap_or_default().to_owned());
    }
    assert_eq!(names, ["seed (refined)", "seed (refined 2)"]);
}
