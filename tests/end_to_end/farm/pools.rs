//! Pools on a farm of real `tessera` processes on 127.0.0.1: workers started with
//! `--tag`, jobs submitted with `--require`.
//!
//! What is proven:
//!
//! - **Eligibility.** Every tile of a job requiring `gpu` is rendered by a worker tagged
//!   `gpu` (the job's events name the machine of each tile), while a job that requires
//!   nothing goes to any worker; both images are `tessera render`'s. `workers --json`
//!   and `status --json` show the tags and the requirements.
//! - **Waiting, with a warning.** A job whose requirements no connected worker meets
//!   waits (it does not fail), its status saying why, until a qualifying worker joins;
//!   a `--verify full` job only one connected machine qualifies for says so. `/metrics`
//!   shows each pool's waiting tiles, estimated CPU-seconds and qualifying workers.
//! - **Bad tags** are refused in one line naming the tag, by `submit` and `worker`.
//! - **Fault: a worker's tags change across a restart while it holds tiles.** A `gpu`
//!   worker killed with SIGKILL mid-job and started again under its name tagged `cpu`
//!   renders no tile of the `gpu` job afterwards: the tiles it held go to the other
//!   `gpu` worker, and the job ends `done` with `tessera render`'s image.

use std::path::Path;
use std::time::Duration;

use serde_json::Value;
use tempfile::TempDir;

use crate::support::{
    assert_job_image, assert_same_png, client, events, fetch, http_get_text, one_error_line, poll,
    render_args, render_reference, scene_path, shared, start_coordinator_with_http,
    start_worker_with, status_json, submit_scene, tessera, wait_done, wait_for_workers,
    worker_named, workers_json, Daemon,
};

/// Longest a job of these tests may take.
const JOB_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest a state the tests wait for may take to show.
const SHOW_TIMEOUT: Duration = Duration::from_secs(20);

/// A small job of a few dozen tiles.
const SMALL: &[&str] = &["--width", "160", "--height", "120", "--tile", "16"];
/// A job of a few seconds on two one-thread workers, in hundreds of tiles: a worker
/// always holds some while it runs.
const LONG: &[&str] = &[
    "--width", "1600", "--height", "1200", "--aa", "8", "--tile", "64",
];

/// The machines whose results were accepted, tile by tile (`tile N by MACHINE in ...`),
/// in the order of the job's events.
fn renderers(dir: &Path, addr: &str, job: u64) -> Vec<(u32, String)> {
    events(dir, addr, job)
        .into_iter()
        .filter(|(kind, _)| kind == "tile_done")
        .filter_map(|(_, detail)| {
            let rest = detail.strip_prefix("tile ")?;
            let (tile, rest) = rest.split_once(" by ")?;
            let machine = rest.split(' ').next()?;
            Some((tile.parse().ok()?, machine.to_owned()))
        })
        .collect()
}

/// The value of the sample `name{pool="POOL"}` in the coordinator's `/metrics`.
fn pool_metric(http: &str, name: &str, pool: &str) -> Option<f64> {
    let text = http_get_text(http, "/metrics");
    let prefix = format!("{name}{{pool=\"{pool}\"}} ");
    text.lines()
        .find_map(|l| l.strip_prefix(&prefix))
        .map(|v| v.trim().parse().expect("a number"))
}

/// A worker's tags, as `workers --json` shows them.
fn tags_of(workers: &[Value], name: &str) -> Vec<String> {
    let w = worker_named(workers, name).unwrap_or_else(|| panic!("no worker {name}"));
    serde_json::from_value(w["tags"].clone()).expect("tags are a list of strings")
}

#[test]
fn a_job_requiring_a_tag_goes_only_to_tagged_workers_and_others_anywhere() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let dir = dir.path();
    let (_coordinator, addr, _http) = start_coordinator_with_http(dir, &[]);
    let _g = start_worker_with(dir, &addr, "g1", &["--tag", "gpu", "--tag", "avx2"]);
    let _p = start_worker_with(dir, &addr, "p1", &[]);
    wait_for_workers(dir, &addr, 2, SHOW_TIMEOUT);
    let workers = workers_json(dir, &addr, &[]);
    assert_eq!(tags_of(&workers, "g1"), ["avx2", "gpu"]);
    assert_eq!(tags_of(&workers, "p1"), Vec::<String>::new());
    let listing = client(dir, &addr, &["workers"]).stdout;
    assert!(
        listing
            .lines()
            .any(|l| l.contains(" g1 ") && l.contains(", tags avx2, gpu")),
        "{listing}"
    );

    let scene = scene_path("lights.json");
    let gpu = submit_scene(dir, &addr, &scene, &[SMALL, &["--require", "gpu"]].concat());
    let any = submit_scene(dir, &addr, &scene, SMALL);
    let status = wait_done(dir, &addr, gpu, JOB_TIMEOUT);
    assert_eq!(status["require"], serde_json::json!(["gpu"]));
    wait_done(dir, &addr, any, JOB_TIMEOUT);
    let by = renderers(dir, &addr, gpu);
    assert_eq!(
        by.len() as u64,
        status["tiles_total"].as_u64().unwrap(),
        "{by:?}"
    );
    assert!(by.iter().all(|(_, m)| m == "g1"), "{by:?}");
    // The untagged worker takes untagged work: it is the only work it may take.
    let by = renderers(dir, &addr, any);
    assert!(by.iter().any(|(_, m)| m == "p1"), "{by:?}");
    let line = client(dir, &addr, &["status", &gpu.to_string()]).stdout;
    assert!(line.contains(", requires gpu;"), "{line}");
    assert_job_image(dir, &addr, gpu, &scene, SMALL, "the gpu job");
    assert_job_image(dir, &addr, any, &scene, SMALL, "the untagged job");
}

#[test]
fn a_job_no_worker_qualifies_for_waits_with_a_warning_and_its_pool_shows_in_metrics() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let dir = dir.path();
    let (_coordinator, addr, http) = start_coordinator_with_http(dir, &[]);
    let _p = start_worker_with(dir, &addr, "p1", &[]);
    wait_for_workers(dir, &addr, 1, SHOW_TIMEOUT);

    // Bad tags: one line each, naming the tag.
    let scene = scene_path("lights.json");
    let run = client(dir, &addr, &["submit", &scene, "--require", "GPU"]);
    let line = one_error_line(&run, "submit --require GPU");
    assert!(
        line.contains("\"GPU\"") && line.contains("not a tag name"),
        "{line}"
    );
    let run = tessera(
        dir,
        &["worker", "--coordinator", &addr, "--tag", "has space"],
        Duration::from_secs(20),
    );
    let line = one_error_line(&run, "worker --tag 'has space'");
    assert!(line.contains("\"has space\""), "{line}");

    let two = ["--require", "gpu", "--require", "ssd"];
    let job = submit_scene(dir, &addr, &scene, &[SMALL, &two].concat());
    let status = status_json(dir, &addr, job);
    assert_eq!(status["state"], "queued", "{status}");
    assert_eq!(status["require"], serde_json::json!(["gpu", "ssd"]));
    assert_eq!(
        status["warning"],
        "no connected worker has every tag this job requires (gpu, ssd): it waits until \
         one connects"
    );
    let run = client(dir, &addr, &["status", &job.to_string()]);
    assert!(
        run.stderr
            .contains("warning: no connected worker has every tag"),
        "{}",
        run.stderr
    );
    let tiles = status["tiles_total"].as_f64().unwrap();
    assert_eq!(
        pool_metric(&http, "tessera_pool_waiting_tiles", "gpu,ssd"),
        Some(tiles)
    );
    let seconds = pool_metric(&http, "tessera_pool_waiting_cpu_seconds", "gpu,ssd").unwrap();
    assert!(seconds > 0.0, "{seconds}");
    assert_eq!(
        pool_metric(&http, "tessera_pool_workers", "gpu,ssd"),
        Some(0.0)
    );
    assert_eq!(pool_metric(&http, "tessera_pool_workers", ""), Some(1.0));
    assert_eq!(
        pool_metric(&http, "tessera_pool_waiting_tiles", ""),
        Some(0.0)
    );

    // A worker with both tags (and one more) joins: the job goes to it.
    let _g1 = start_worker_with(dir, &addr, "g1", &["--tag", "ssd", "--tag", "gpu,x"]);
    wait_done(dir, &addr, job, JOB_TIMEOUT);
    assert!(renderers(dir, &addr, job).iter().all(|(_, m)| m == "g1"));
    assert_eq!(
        pool_metric(&http, "tessera_pool_waiting_tiles", "gpu,ssd"),
        None
    );
    assert_eq!(pool_metric(&http, "tessera_pool_workers", "gpu"), Some(1.0));
    assert_eq!(pool_metric(&http, "tessera_pool_workers", "x"), Some(1.0));

    // Full verification with one qualifying machine: it says so, and a second one
    // lets it finish.
    let full = ["--require", "gpu", "--verify", "full"];
    let job = submit_scene(dir, &addr, &scene, &[SMALL, &full].concat());
    let warning = poll("the one-machine warning", SHOW_TIMEOUT, || {
        let status = status_json(dir, &addr, job);
        status["warning"].as_str().map(str::to_owned)
    });
    assert_eq!(
        warning,
        "only one connected machine (g1) has every tag this job requires (gpu): --verify \
         full needs a second to confirm its tiles"
    );
    let _g2 = start_worker_with(dir, &addr, "g2", &["--tag", "gpu"]);
    let status = wait_done(dir, &addr, job, JOB_TIMEOUT);
    assert_eq!(status["warning"], Value::Null);
    let machines: std::collections::BTreeSet<String> = renderers(dir, &addr, job)
        .into_iter()
        .map(|(_, m)| m)
        .collect();
    assert!(
        machines.iter().all(|m| m == "g1" || m == "g2"),
        "{machines:?}"
    );
    assert_job_image(dir, &addr, job, &scene, SMALL, "the fully verified gpu job");
}

#[test]
fn a_worker_restarted_with_other_tags_while_holding_tiles_renders_none_of_them_again() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let dir = dir.path();
    let (_coordinator, addr, _http) = start_coordinator_with_http(dir, &[]);
    let mut w1: Daemon = start_worker_with(dir, &addr, "w1", &["--tag", "gpu"]);
    let _w2 = start_worker_with(dir, &addr, "w2", &["--tag", "gpu"]);
    wait_for_workers(dir, &addr, 2, SHOW_TIMEOUT);
    let scene = scene_path("lights.json");
    let job = submit_scene(dir, &addr, &scene, &[LONG, &["--require", "gpu"]].concat());
    // Once w1 has rendered a tile it holds more (its credit is two tiles).
    poll("a tile rendered by w1", SHOW_TIMEOUT, || {
        renderers(dir, &addr, job)
            .iter()
            .any(|(_, m)| m == "w1")
            .then_some(())
    });
    w1.kill9();
    let _w1 = start_worker_with(dir, &addr, "w1", &["--tag", "cpu"]);
    poll("w1 back with its new tag", SHOW_TIMEOUT, || {
        let workers = workers_json(dir, &addr, &[]);
        (worker_named(&workers, "w1").is_some() && tags_of(&workers, "w1") == ["cpu"]).then_some(())
    });
    // From here on every tile w1 returns would be the restarted worker's. Only w2 renders
    // the rest: the reference renders on the other core meanwhile (scoped, so that a
    // failed assertion still waits for its process).
    let before = renderers(dir, &addr, job).len();
    let reference_args = [&render_args(LONG)[..], &["--threads", "1"]].concat();
    let (status, reference) = std::thread::scope(|s| {
        let reference = s.spawn(|| render_reference(dir, &scene, "reference.png", &reference_args));
        let status = wait_done(dir, &addr, job, JOB_TIMEOUT);
        (
            status,
            reference.join().expect("the reference render panicked"),
        )
    });
    let after = renderers(dir, &addr, job);
    assert_eq!(after.len() as u64, status["tiles_total"].as_u64().unwrap());
    let late: Vec<&(u32, String)> = after[before..].iter().filter(|(_, m)| m == "w1").collect();
    assert!(late.is_empty(), "the restarted w1 rendered {late:?}");
    // The tiles it held went back: the log says so.
    let taken_back = events(dir, &addr, job)
        .into_iter()
        .filter(|(kind, detail)| kind == "tile_taken_back" && detail.contains(" from w1"))
        .count();
    assert!(taken_back > 0, "no tile of w1 was taken back");
    let fetched = fetch(dir, &addr, job, "job.png");
    assert_same_png(&fetched, &reference, "the job after the restart");
}
