//! End-to-end tests of the samplers through the real `tessera` binary.
//!
//! What is proven:
//!
//! - **Determinism.** A farm job with `--sampler jittered` or `--sampler adaptive
//!   --target-error 1` writes byte for byte the PNG `tessera render` writes with the
//!   same flags, whatever the tile size and the number of workers; so does `tessera up`.
//!   The samples spent are the same to the sample.
//! - **Reports.** `render`, `up` and `submit --wait` print the samples spent and the
//!   estimated error next to the time; `status --json` carries the sampler, the target,
//!   the samples and the estimate.
//! - **Adaptive passes.** An adaptive farm job gives the same bytes with one worker and
//!   with three, with tiles of 16 and of 40 pixels, and with a worker killed in the
//!   middle of a pass; a tile side off the 8-pixel blocks is one `error: ` line.
//! - **Durability.** A job's sampler survives a coordinator restart.
//! - **Limits.** An adaptive budget counts against the coordinator's `--max-aa`.
//! - **Errors.** A bad combination of `--sampler` and `--target-error` is one `error: `
//!   line, before anything is started, connected to or written.

use std::path::Path;
use std::time::Duration;

use serde_json::Value;
use tempfile::TempDir;

use crate::support::{
    assert_same_png, client, fetch, free_port, ok, one_error_line, poll, scene_path, shared,
    start_coordinator, start_slow_worker, start_worker, submit, tessera, try_status, wait_done,
    Run,
};

const JOB_TIMEOUT: Duration = Duration::from_secs(120);
const RUN_TIMEOUT: Duration = Duration::from_secs(120);

/// A small frame with partial tiles at the right and bottom edges.
const SIZE: &[&str] = &["--width", "160", "--height", "120"];
const PIXELS: u64 = 160 * 120;

const JITTERED: &[&str] = &["--aa", "3", "--sampler", "jittered"];
const ADAPTIVE: &[&str] = &["--aa", "4", "--sampler", "adaptive", "--target-error", "1"];

/// The one summary line of a successful run (on stderr), after the `submitted job N`
/// that `submit --wait` prints first.
fn summary_line(run: &Run) -> String {
    let mut lines: Vec<&str> = run.stderr.lines().collect();
    if lines
        .first()
        .is_some_and(|l| l.starts_with("submitted job "))
    {
        lines.remove(0);
    }
    assert_eq!(lines.len(), 1, "one summary line: {:?}", run.stderr);
    lines[0].to_owned()
}

/// The total samples a summary line reports: the number before " in all)".
fn summary_samples(line: &str) -> u64 {
    let head = line
        .split(" in all)")
        .next()
        .filter(|h| h.len() < line.len())
        .unwrap_or_else(|| panic!("no sample count in {line:?}"));
    head.rsplit(' ')
        .next()
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no sample count in {line:?}"))
}

/// The estimated error a summary line reports, in levels.
fn summary_error(line: &str) -> f64 {
    line.split("estimated error ")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no estimated error in {line:?}"))
}

/// `tessera render SCENE -o DIR/NAME ARGS`: the reference image and its summary line.
fn render(dir: &Path, scene: &str, name: &str, flags: &[&str]) -> (std::path::PathBuf, String) {
    let out = dir.join(name);
    let out_arg = out.to_str().expect("test paths are UTF-8");
    let mut all = vec!["render", scene, "-o", out_arg];
    all.extend(flags);
    let run = ok(tessera(dir, &all, RUN_TIMEOUT), &all.join(" "));
    (out, summary_line(&run))
}

fn as_u64(v: &Value, key: &str) -> u64 {
    v[key]
        .as_u64()
        .unwrap_or_else(|| panic!("{key} is not a number: {v}"))
}

fn as_f64(v: &Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("{key} is not a number: {v}"))
}

#[test]
fn farm_jobs_with_each_sampler_equal_local_renders() {
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

    for (name, flags, tile) in [("jittered", JITTERED, "16"), ("adaptive", ADAPTIVE, "24")] {
        let flags = [SIZE, flags].concat();
        let (reference, local) = render(dir, &seed, &format!("ref-{name}.png"), &flags);
        let local_samples = summary_samples(&local);
        let local_error = summary_error(&local);

        // submit --wait: same image, and a summary with the same samples.
        let out = dir.join(format!("farm-{name}.png"));
        let out_arg = out.to_str().unwrap();
        let mut submit_args = vec!["submit", &seed, "--wait", "-o", out_arg, "--tile", tile];
        submit_args.extend(&flags);
        let run = ok(client(dir, &addr, &submit_args), "submit --wait");
        assert_same_png(&out, &reference, &format!("{name}: submit --wait"));
        let line = summary_line(&run);
        assert_eq!(summary_samples(&line), local_samples, "{name}: {line}");
        assert!(
            (summary_error(&line) - local_error).abs() < 0.0015,
            "{name}: {line}"
        );

        // A second job, other tiles: status --json reports what was spent.
        let mut job_args = vec![seed.as_str(), "--tile", "40"];
        job_args.extend(&flags);
        let job = submit(dir, &addr, &job_args);
        let status = wait_done(dir, &addr, job, JOB_TIMEOUT);
        assert_same_png(
            &fetch(dir, &addr, job, &format!("job-{name}.png")),
            &reference,
            name,
        );
        assert_eq!(status["sampler"], name, "{status}");
        assert_eq!(as_u64(&status, "samples"), local_samples, "{status}");
        let mean = as_f64(&status, "samples_per_pixel");
        assert!((mean - local_samples as f64 / PIXELS as f64).abs() < 1e-9);
        let estimate = as_f64(&status, "estimated_error");
        assert!(
            (estimate - local_error).abs() < 0.0015,
            "{status} vs {local}"
        );
        match name {
            "jittered" => {
                assert_eq!(local_samples, PIXELS * 9, "jittered takes aa² per pixel");
                assert_eq!(status["target_error"], Value::Null);
            }
            _ => {
                assert!(
                    (PIXELS * 4..PIXELS * 16).contains(&local_samples),
                    "adaptive spends between the first pass and the budget: {local_samples}"
                );
                assert_eq!(as_f64(&status, "target_error"), 1.0);
            }
        }
    }

    // The grid reports its estimate too, and none with one sample per pixel.
    let (_, line) = render(dir, &seed, "grid2.png", &[SIZE, &["--aa", "2"]].concat());
    assert!(
        line.contains("4 samples/pixel (grid 2x2, 76800 in all)"),
        "{line}"
    );
    assert!(summary_error(&line) > 0.0, "{line}");
    let (_, line) = render(dir, &seed, "grid1.png", SIZE);
    assert!(
        line.contains("1 sample/pixel (grid 1x1, 19200 in all)"),
        "{line}"
    );
    assert!(line.contains("no error estimate"), "{line}");
    let mut wait_args = vec![
        "submit",
        seed.as_str(),
        "--wait",
        "--json",
        "-o",
        "grid.png",
    ];
    wait_args.extend(SIZE);
    let run = ok(client(dir, &addr, &wait_args), "submit --wait --json");
    let status: Value = serde_json::from_str(run.stdout.trim()).expect("JSON");
    assert_eq!(status["sampler"], "grid");
    assert_eq!(as_u64(&status, "samples"), PIXELS);
    assert_eq!(as_f64(&status, "samples_per_pixel"), 1.0);
    assert_eq!(status["estimated_error"], Value::Null, "{status}");
}

#[test]
fn up_with_adaptive_sampling_equals_the_local_render() {
    let _turn = shared();
    let tmp = TempDir::new().unwrap();
    let dir = tmp.path();
    let scene = scene_path("reflections.json");
    let flags = [SIZE, ADAPTIVE].concat();
    let (reference, local) = render(dir, &scene, "ref.png", &flags);
    let out = dir.join("up.png");
    let mut up_args = vec!["up", scene.as_str(), "--workers", "2", "-o"];
    up_args.push(out.to_str().unwrap());
    up_args.extend(["--tile", "32"]);
    up_args.extend(&flags);
    let run = ok(tessera(dir, &up_args, RUN_TIMEOUT), "tessera up");
    assert_same_png(&out, &reference, "up --sampler adaptive");
    let line = summary_line(&run);
    assert!(line.contains("(2 workers)"), "{line}");
    assert!(
        line.contains("adaptive up to 4x4, target 1 level"),
        "{line}"
    );
    assert_eq!(summary_samples(&line), summary_samples(&local), "{line}");
    assert!((summary_error(&line) - summary_error(&local)).abs() < 0.0015);

    // At aa 1 every block has one level: its state is exactly as large as the bound
    // the coordinator checks it against.
    let flags = [
        SIZE,
        &["--aa", "1", "--sampler", "adaptive", "--target-error", "1"],
    ]
    .concat();
    let (reference, _) = render(dir, &scene, "ref1.png", &flags);
    let out = dir.join("up1.png");
    let mut up_args = vec!["up", scene.as_str(), "--workers", "2", "-o"];
    up_args.push(out.to_str().unwrap());
    up_args.extend(&flags);
    ok(tessera(dir, &up_args, RUN_TIMEOUT), "tessera up --aa 1");
    assert_same_png(&out, &reference, "up --sampler adaptive --aa 1");
}

#[test]
fn the_sampler_survives_a_coordinator_restart() {
    let _turn = shared();
    let tmp = TempDir::new().unwrap();
    let dir = tmp.path();
    let data = dir.join("data");
    let seed = scene_path("seed.json");
    let flags = [SIZE, ADAPTIVE].concat();
    let (reference, local) = render(dir, &seed, "ref.png", &flags);

    // Accepted (and stored) by a coordinator without workers, which then dies.
    let (mut first, addr) = start_coordinator(dir, &data, "127.0.0.1:0", &[], "first.log");
    let mut job_args = vec![seed.as_str()];
    job_args.extend(&flags);
    let job = submit(dir, &addr, &job_args);
    first.kill9();

    let (_second, addr) = start_coordinator(dir, &data, "127.0.0.1:0", &[], "second.log");
    let queued = try_status(dir, &addr, job).expect("the job is back");
    assert_eq!(queued["sampler"], "adaptive", "{queued}");
    assert_eq!(as_f64(&queued, "target_error"), 1.0);
    let _worker = start_worker(dir, &addr, "w");
    let status = wait_done(dir, &addr, job, JOB_TIMEOUT);
    assert_same_png(
        &fetch(dir, &addr, job, "restored.png"),
        &reference,
        "after restart",
    );
    assert_eq!(as_u64(&status, "samples"), summary_samples(&local));
}

#[test]
fn adaptive_budgets_count_against_the_coordinators_aa_limit() {
    let _turn = shared();
    let tmp = TempDir::new().unwrap();
    let dir = tmp.path();
    let (_coordinator, addr) = start_coordinator(
        dir,
        &dir.join("data"),
        "127.0.0.1:0",
        &["--max-aa", "4"],
        "coordinator.log",
    );
    let seed = scene_path("seed.json");
    let run = client(
        dir,
        &addr,
        &[
            "submit",
            &seed,
            "--aa",
            "8",
            "--sampler",
            "adaptive",
            "--target-error",
            "1",
        ],
    );
    let line = one_error_line(&run, "adaptive over the limit");
    assert!(
        line.contains("image.aa: 8 is more than this coordinator's limit of 4"),
        "{line}"
    );
}

#[test]
fn bad_sampler_flags_are_one_line_errors_before_anything_runs() {
    let _turn = shared();
    let tmp = TempDir::new().unwrap();
    let dir = tmp.path();
    let seed = scene_path("seed.json");
    // A port nobody listens on: the flags must be refused before any connection.
    let nowhere = format!("127.0.0.1:{}", free_port());
    let cases: &[(&[&str], &str)] = &[
        (
            &["--sampler", "adaptive"],
            "error: --sampler adaptive needs --target-error LEVELS",
        ),
        (
            &["--sampler", "jittered", "--target-error", "1"],
            "error: --target-error applies only to --sampler adaptive",
        ),
        (
            &["--sampler", "grid", "--target-error", "0.5"],
            "error: --target-error applies only to --sampler adaptive",
        ),
        (
            &["--sampler", "adaptive", "--target-error", "0"],
            "error: --target-error: must be a number of 8-bit levels from 0.001 to 255, got 0",
        ),
        (
            &["--sampler", "adaptive", "--target-error", "-2"],
            "error: --target-error: must be a number of 8-bit levels from 0.001 to 255, got -2",
        ),
        (
            &["--sampler", "adaptive", "--target-error", "NaN"],
            "error: --target-error: must be a number of 8-bit levels from 0.001 to 255, got NaN",
        ),
        (
            &["--sampler", "adaptive", "--target-error", "1000"],
            "error: --target-error: must be a number of 8-bit levels from 0.001 to 255, got 1000",
        ),
    ];
    for &(flags, expected) in cases {
        for command in ["render", "submit", "up"] {
            let mut all = vec![command, seed.as_str(), "-o", "out.png"];
            if command == "submit" {
                all.extend(["--wait", "--coordinator", &nowhere]);
            }
            all.extend(flags);
            let run = tessera(dir, &all, RUN_TIMEOUT);
            let what = all.join(" ");
            let line = one_error_line(&run, &what);
            assert!(line.starts_with(expected), "{what}: {line:?}");
        }
    }
    let left: Vec<_> = std::fs::read_dir(dir).unwrap().collect();
    assert!(left.is_empty(), "nothing written: {left:?}");
}

#[test]
fn adaptive_jobs_give_the_same_bytes_with_any_workers_tiles_and_losses() {
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
    let flags = [SIZE, ADAPTIVE].concat();
    let (reference, local) = render(dir, &seed, "ref.png", &flags);
    let job = |tile: &str| {
        let mut job_args = vec![seed.as_str(), "--tile", tile];
        job_args.extend(&flags);
        submit(dir, &addr, &job_args)
    };

    // One worker, 16-pixel tiles.
    let mut a = start_worker(dir, &addr, "a");
    let one = job("16");
    let status = wait_done(dir, &addr, one, JOB_TIMEOUT);
    assert_same_png(
        &fetch(dir, &addr, one, "one.png"),
        &reference,
        "1 worker, tile 16",
    );
    assert_eq!(
        as_u64(&status, "samples"),
        summary_samples(&local),
        "{status}"
    );

    // Three workers, 40-pixel tiles.
    let b = start_worker(dir, &addr, "b");
    let _c = start_worker(dir, &addr, "c");
    let three = job("40");
    wait_done(dir, &addr, three, JOB_TIMEOUT);
    assert_same_png(
        &fetch(dir, &addr, three, "three.png"),
        &reference,
        "3 workers, tile 40",
    );

    // A worker killed in the middle of a pass: a larger job on slowed workers, and the
    // kill once the first pass is in (the estimate shows) and the job still runs.
    drop(b);
    let Some(_slow) = start_slow_worker(
        "adaptive_jobs_give_the_same_bytes_with_any_workers_tiles_and_losses",
        dir,
        &addr,
        "slow",
        1.0 / 3.0,
        &[],
    ) else {
        return;
    };
    let big: Vec<&str> = [
        &["--width", "320", "--height", "240"][..],
        &["--aa", "8", "--sampler", "adaptive", "--target-error", "1"],
    ]
    .concat();
    let (big_reference, _) = render(dir, &seed, "big.png", &big);
    let mut job_args = vec![seed.as_str(), "--tile", "32"];
    job_args.extend(&big);
    let lossy = submit(dir, &addr, &job_args);
    poll("a pass of the job to be in", JOB_TIMEOUT, || {
        let s = try_status(dir, &addr, lossy)?;
        (s["state"] == "running" && s["estimated_error"].is_number()).then_some(())
    });
    a.kill9();
    let status = wait_done(dir, &addr, lossy, JOB_TIMEOUT);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    assert_same_png(
        &fetch(dir, &addr, lossy, "lossy.png"),
        &big_reference,
        "a worker killed in a pass",
    );

    // A tile side off the blocks is refused in one line.
    let mut bad = vec!["submit", seed.as_str(), "--tile", "20"];
    bad.extend(&flags);
    let line = one_error_line(&client(dir, &addr, &bad), "adaptive tile 20");
    assert!(
        line.contains("tile: adaptive sampling needs tiles cut on its 8-pixel blocks: a multiple of 8 up to 256, got 20"),
        "{line}"
    );
}

#[test]
fn a_target_error_alone_chooses_adaptive_sampling_everywhere() {
    let _turn = shared();
    let tmp = TempDir::new().unwrap();
    let dir = tmp.path();
    let seed = scene_path("seed.json");
    let run = |command: &str, flags: &[&str], out: &str| {
        let mut all = vec![command, seed.as_str(), "-o", out];
        all.extend(SIZE);
        all.extend(["--aa", "4"]);
        all.extend(flags);
        if command == "up" {
            all.extend(["--workers", "1"]);
        }
        ok(tessera(dir, &all, RUN_TIMEOUT), &all.join(" "));
        std::fs::read(dir.join(out)).unwrap()
    };
    let named = run(
        "render",
        &["--sampler", "adaptive", "--target-error", "1"],
        "named.png",
    );
    for command in ["render", "up"] {
        let alone = run(command, &["--target-error", "1"], &format!("{command}.png"));
        assert!(alone == named, "{command} --target-error 1 alone differs");
    }
}
