//! The network between the workers and the coordinator fails, through a relay
//! ([`CutProxy`]) that stops forwarding in both directions without closing anything,
//! as a pulled cable does. (A network namespace with a veth pair would cut at the kernel
//! instead, but it needs addresses other than 127.0.0.1, which the project's tests never
//! use.)
//!
//! - **An 8 s cut** between both workers and the coordinator: longer than the 5 s
//!   heartbeat timeout, so the workers are dropped and come back under their names, and
//!   the job still ends.
//! - **A worker cut off mid-job**: the coordinator gives its tiles to others once its
//!   heartbeats stop, and the worker comes back once the link is restored.
//! - **A cut that never ends**: the worker notices the silence and gives up on the
//!   connection instead of waiting forever.

use std::path::Path;
use std::thread;
use std::time::{Duration, Instant};

use tempfile::TempDir;

use super::{Farm, JOB};
use crate::support::cut_proxy::CutProxy;
use crate::support::{
    assert_same_png, exclusive, fetch, poll, render_args, render_reference, scene_path, shared,
    start_coordinator, start_worker, submit, tiles_done, tiles_total, try_status, wait_done,
    worker_names, workers_json,
};

/// The link between both workers and the coordinator is cut for 8 s (longer than the
/// 5 s heartbeat timeout, shorter than the workers' 10 s silence limit): the workers
/// are dropped and come back under their names, and the job ends `done` with
/// `tessera render`'s image.
#[test]
fn an_eight_second_network_cut_ends_with_the_job_done() {
    let _turn = exclusive();
    let mut farm = Farm::start("127.0.0.1:0", &[]);
    let proxy = CutProxy::start(&farm.addr);
    let relay = proxy.address().to_owned();
    farm.add_worker_at(&relay, "w1");
    farm.add_worker_at(&relay, "w2");
    farm.wait_for_workers(&["w1", "w2"]);
    let lights = scene_path("lights.json");
    let job = farm.submit(&lights, JOB);
    let total = tiles_total(&farm.status(job));
    farm.wait_for_tiles(job, total / 6);

    proxy.cut();
    let cut = Instant::now();
    let before = tiles_done(&farm.status(job));
    thread::sleep(Duration::from_secs(8));
    let during = tiles_done(&farm.status(job));
    proxy.restore();
    let restored = Instant::now();

    let resumed = farm.wait_progress(job, during, "after the link was restored");
    let status = farm.wait_done_progressing(job);
    let done = restored.elapsed();
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    eprintln!(
        "network cut of {:.1} s at {before}/{total} tiles ({during} when restored); the job \
         progressed {} ms after the link was restored and was done {:.1} s after it",
        (restored - cut).as_secs_f64(),
        (resumed - restored).as_millis(),
        done.as_secs_f64()
    );
    farm.assert_job_image(job, &lights, JOB, "the job through an 8 s network cut");
    // Both workers are back under their names.
    farm.wait_for_workers(&["w1", "w2"]);
}

/// The job's `tiles_done`, as `status` reports it.
fn job_tiles_done(dir: &Path, addr: &str, job: u64) -> u64 {
    tiles_done(&try_status(dir, addr, job).expect("status"))
}

#[test]
fn a_worker_cut_off_mid_job_loses_its_tiles_and_comes_back() {
    let _turn = exclusive();
    let dir = TempDir::new().expect("temporary directory");
    let d = dir.path();
    let scene = scene_path("lights.json");
    let (_coordinator, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &["--heartbeat-timeout-ms", "2000"],
        "coordinator.log",
    );
    let proxy = CutProxy::start(&addr);
    let _cut_worker = start_worker(d, proxy.address(), "behind-the-cut");
    poll("the worker to register", Duration::from_secs(20), || {
        (workers_json(d, &addr, &[]).len() == 1).then_some(())
    });

    // In small tiles, so that the first ones come back quickly.
    let mut args = vec![scene.as_str()];
    args.extend(JOB);
    let job = submit(d, &addr, &args);
    poll("the first tiles", Duration::from_secs(30), || {
        (job_tiles_done(d, &addr, job) > 0).then_some(())
    });
    proxy.cut();

    // The coordinator drops the silent worker after its 2 s heartbeat timeout, and the
    // job stands still: its only worker is gone.
    poll(
        "the cut worker to be dropped",
        Duration::from_secs(10),
        || workers_json(d, &addr, &[]).is_empty().then_some(()),
    );
    let frozen = job_tiles_done(d, &addr, job);
    thread::sleep(Duration::from_millis(500));
    assert_eq!(
        job_tiles_done(d, &addr, job),
        frozen,
        "no worker, no progress"
    );

    // Another worker finishes the job, the cut worker's leased tiles included.
    let _other = start_worker(d, &addr, "direct");
    let status = wait_done(d, &addr, job, Duration::from_secs(90));
    let reference = render_reference(d, &scene, "reference.png", &render_args(JOB));
    let fetched = fetch(d, &addr, job, "fetched.png");
    assert_same_png(&fetched, &reference, "the job finished after a network cut");
    assert!(status["tiles_done"] == status["tiles_total"], "{status}");

    // Once the link is back, the cut worker reconnects by itself.
    proxy.restore();
    poll(
        "the cut worker to come back",
        Duration::from_secs(30),
        || {
            let mut now = worker_names(&workers_json(d, &addr, &[]));
            now.sort();
            (now == ["behind-the-cut", "direct"]).then_some(())
        },
    );
}

#[test]
fn a_worker_behind_a_cut_that_never_ends_gives_up_on_the_connection() {
    // Beside other tests: it waits out the worker's 10 s of silence, a deadline that a
    // loaded machine only makes later, never sooner, and the wait allows three times it.
    let _turn = shared();
    let dir = TempDir::new().expect("temporary directory");
    let d = dir.path();
    let (_coordinator, addr) =
        start_coordinator(d, &d.join("data"), "127.0.0.1:0", &[], "coordinator.log");
    let proxy = CutProxy::start(&addr);
    let worker = start_worker(d, proxy.address(), "stranded");
    poll("the worker to register", Duration::from_secs(20), || {
        (workers_json(d, &addr, &[]).len() == 1).then_some(())
    });
    proxy.cut();
    // It hears no heartbeat from the coordinator, so it closes the connection and tries
    // again (through the same dead link) instead of waiting forever.
    poll(
        "the worker to notice the silence",
        Duration::from_secs(30),
        || {
            worker
                .log_text()
                .contains("nothing from the coordinator for 10 s")
                .then_some(())
        },
    );
    assert!(worker.log_text().contains("reconnecting"));
}
