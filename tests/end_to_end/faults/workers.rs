//! Workers killed, frozen, stopped and restarted mid-job:
//!
//! - **Killed** (`kill -9`) every 300 ms for 3 s, each replaced by a new one.
//! - **Killed and restarted under the same `--name`** (as systemd or Kubernetes restart
//!   it), five times with one worker and six times with two: the restarted worker is
//!   never kept from the job (a lost connection is not proof that a machine is bad).
//!   Each restart reports the time from the worker's registration to its next tile.
//! - **Frozen** (`SIGSTOP`) for longer than the heartbeat timeout: the other worker
//!   renders the rest of the job, the frozen one is dropped, and after `SIGCONT` the
//!   farm still serves. The job ends once the frozen worker is dropped, not at its
//!   leases' expiry: the other worker's audited results wait for a second machine to
//!   confirm them, and with the frozen one gone none is left, so they are accepted
//!   (docs/reliability.md, "sampled").
//! - **Stopped** (`SIGTERM`): it finishes its tiles and exits 0 promptly; the remaining
//!   worker completes the job.

use std::thread;
use std::time::{Duration, Instant};

use serde_json::Value;

use super::{Farm, MEDIUM, STALL};
use crate::support::{
    assert_not_ended_badly, exclusive, poll, render_reference, scene_path, start_worker,
    tiles_done, tiles_total, worker_named, SplitMix, POLL, REGISTER_TIMEOUT,
};

/// Some 6 CPU-seconds in 4,275 tiles (with `--tile 32`): some 3 s on three workers
/// sharing two cores. The image of `coordinator.rs`'s `VERY_LONG`, so that the two
/// tests share one reference rendering.
const LONG: &[&str] = &["--width", "2400", "--height", "1800", "--aa", "5"];
/// Some 2 CPU-seconds in 4,275 tiles of 16 pixels: the job of one restarted worker.
const ONE_WORKER_JOB: &[&str] = &[
    "--width", "1200", "--height", "900", "--aa", "5", "--tile", "16",
];
/// Some 4 CPU-seconds in 7,500 tiles of 16 pixels: the job of two restarted workers.
/// The image of the faults tests' `JOB`, so that they share one reference rendering.
const TWO_WORKER_JOB: &[&str] = &[
    "--width", "1600", "--height", "1200", "--aa", "5", "--tile", "16",
];
/// `(min, median, max)` in milliseconds.
fn spread(times: &[Duration]) -> String {
    let mut ms: Vec<u128> = times.iter().map(Duration::as_millis).collect();
    ms.sort_unstable();
    match ms.as_slice() {
        [] => "none".to_owned(),
        _ => format!(
            "min {} ms, median {} ms, max {} ms",
            ms[0],
            ms[ms.len() / 2],
            ms[ms.len() - 1]
        ),
    }
}

/// What one kill-and-restart of a worker measured.
struct Restart {
    /// From the restart to the worker's registration.
    registered: Duration,
    /// From the registration to its first tile done.
    first_tile: Duration,
}

/// Kills worker `i` of `farm` (`kill -9`) once it has rendered `after_tiles` tiles on
/// its current connection, starts it again under the same name, and waits for it to
/// register and render a tile. `None` if the job ended first.
fn kill_and_restart(
    farm: &mut Farm,
    i: usize,
    name: &str,
    job: u64,
    after_tiles: u64,
    round: usize,
) -> Option<Restart> {
    // Wait until the worker is busy with the job, so that it dies holding tiles.
    let old = poll(
        &format!("{name} to render {after_tiles} tiles (round {round})"),
        STALL,
        || {
            let status = farm.status(job);
            assert_not_ended_badly(job, &status);
            if status["state"] == "done" {
                return Some(None);
            }
            let worker = worker_named(&farm.try_workers()?, name)?.clone();
            (worker["tiles_done"].as_u64() >= Some(after_tiles)).then_some(Some(worker))
        },
    )?;
    farm.workers[i].kill9();
    let restarted = Instant::now();
    farm.workers[i] = start_worker(farm.dir(), &farm.addr, name);

    // Registered again: a new connection under the same name.
    let (new_id, registered) = poll(
        &format!("{name} to register again (round {round})"),
        REGISTER_TIMEOUT,
        || {
            let workers = farm.try_workers()?;
            let worker = workers
                .iter()
                .find(|w| w["name"] == name && w["id"] != old["id"])?;
            Some((worker["id"].clone(), Instant::now()))
        },
    );
    // Its next tile: the restarted worker is not kept from the job.
    let deadline = registered + STALL;
    let mut left_at_registration = None;
    loop {
        let status = farm.status(job);
        assert_not_ended_badly(job, &status);
        let left = tiles_total(&status) - tiles_done(&status);
        let left_then = *left_at_registration.get_or_insert(left);
        if status["state"] == "done" {
            // Others may finish the last few tiles first; not a job's worth of them.
            assert!(
                left_then <= 50,
                "{name}, restarted under its own name (round {round}), got none of the \
                 {left_then} tiles left when it registered: the other workers rendered them \
                 all"
            );
            return None;
        }
        let worker = farm
            .try_workers()
            .and_then(|w| w.into_iter().find(|w| w["id"] == new_id))
            .unwrap_or(Value::Null);
        if worker["tiles_done"].as_u64() >= Some(1) {
            return Some(Restart {
                registered: registered - restarted,
                first_tile: registered.elapsed(),
            });
        }
        let last = status;
        assert!(
            Instant::now() < deadline,
            "{name}, restarted under its own name (round {round}), got no tile within \
             {STALL:?} of registering: job {job} at {}/{} tiles, state {}, eta_ms {}; the \
             worker: {worker}",
            last["tiles_done"],
            last["tiles_total"],
            last["state"],
            last["eta_ms"]
        );
        thread::sleep(POLL);
    }
}

/// Kills and restarts the workers of `farm` (named `names`, in turn) `rounds` times
/// while `job` runs; returns the measurements.
fn restart_workers_in_turn(
    farm: &mut Farm,
    names: &[&str],
    job: u64,
    rounds: usize,
    after_tiles: u64,
) -> Vec<Restart> {
    let mut restarts = Vec::new();
    for round in 1..=rounds {
        let i = (round - 1) % names.len();
        match kill_and_restart(farm, i, names[i], job, after_tiles, round) {
            Some(restart) => restarts.push(restart),
            None => panic!(
                "job {job} ended after only {} of {rounds} restarts: make it longer",
                round - 1
            ),
        }
    }
    restarts
}

fn report_restarts(what: &str, restarts: &[Restart]) {
    let registered: Vec<Duration> = restarts.iter().map(|r| r.registered).collect();
    let first_tile: Vec<Duration> = restarts.iter().map(|r| r.first_tile).collect();
    eprintln!(
        "{what}: {} restarts under the same name; restart to registration: {}; \
         registration to the worker's next tile: {}",
        restarts.len(),
        spread(&registered),
        spread(&first_tile)
    );
}

/// A random worker is killed every 300 ms for 3 s and replaced each time: the job
/// still completes with `tessera render`'s image.
#[test]
fn workers_killed_every_300_ms_do_not_change_the_image() {
    let _turn = exclusive();
    let mut farm = Farm::start("127.0.0.1:0", &["w1", "w2", "w3"]);
    let lights = scene_path("lights.json");
    let job = farm.submit(&lights, &[&["--tile", "32"][..], LONG].concat());
    farm.wait_for_tiles(job, 1);

    let mut rng = SplitMix(0x7e55_e7a5);
    let started = Instant::now();
    let mut kills = 0;
    let mut done_early = false;
    while started.elapsed() < Duration::from_secs(3) {
        let next = started + Duration::from_millis(300) * (kills + 1);
        thread::sleep(next.saturating_duration_since(Instant::now()));
        if farm.status(job)["state"] == "done" {
            done_early = true;
            break;
        }
        let victim = rng.below(farm.workers.len());
        farm.workers[victim].kill9();
        kills += 1;
        let replacement = start_worker(farm.dir(), &farm.addr, &format!("r{kills}"));
        // The killed worker is already reaped: dropping its guard does nothing more.
        farm.workers[victim] = replacement;
    }
    assert!(
        kills >= 5,
        "only {kills} workers were killed before the job ended (done early: {done_early}): \
         make the job longer"
    );
    let killing = started.elapsed();
    let status = farm.wait_done(job);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    eprintln!(
        "{kills} workers killed in {:.1} s; job done {:.1} s after the first kill",
        killing.as_secs_f64(),
        started.elapsed().as_secs_f64()
    );
    farm.assert_job_image(job, &lights, LONG, "the job whose workers were killed");
    farm.assert_no_divergent_duplicates();
}

/// One worker, killed five times mid-job and restarted each time under its own name
/// (as systemd or Kubernetes restart it): it is never blocked from the job, which ends
/// `done` with `tessera render`'s image.
#[test]
fn a_lone_worker_restarted_under_its_name_five_times_finishes_the_job() {
    let _turn = exclusive();
    let mut farm = Farm::restartable(&["w1"]);
    let lights = scene_path("lights.json");
    let job = farm.submit(&lights, ONE_WORKER_JOB);
    farm.wait_for_tiles(job, 1);

    let restarts = restart_workers_in_turn(&mut farm, &["w1"], job, 5, 40);
    let status = farm.wait_done_progressing(job);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    report_restarts("one worker", &restarts);
    farm.assert_job_image(
        job,
        &lights,
        ONE_WORKER_JOB,
        "the job of a worker restarted five times",
    );
}

/// Two workers, each killed three times mid-job (in turn) and restarted under its own
/// name: each restarted worker gets tiles again, and the job ends `done` with
/// `tessera render`'s image.
#[test]
fn two_workers_restarted_under_their_names_six_times_finish_the_job() {
    let _turn = exclusive();
    let names = ["w1", "w2"];
    let mut farm = Farm::restartable(&names);
    let lights = scene_path("lights.json");
    let job = farm.submit(&lights, TWO_WORKER_JOB);
    farm.wait_for_tiles(job, 1);

    let restarts = restart_workers_in_turn(&mut farm, &names, job, 6, 25);
    let status = farm.wait_done_progressing(job);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    report_restarts("two workers", &restarts);
    farm.assert_job_image(
        job,
        &lights,
        TWO_WORKER_JOB,
        "the job of two workers restarted six times",
    );
}

/// The heartbeat timeout of the farm whose worker is frozen, in milliseconds: shorter
/// than the default 5 s, which the test would wait out, and three of the workers' 1 s
/// heartbeats, so that the worker left is not dropped for a heartbeat a loaded machine
/// delays.
const FROZEN_HEARTBEAT_TIMEOUT_MS: u64 = 3000;

/// A worker frozen with SIGSTOP mid-job for longer than the heartbeat timeout:
/// the job completes on the other worker, the frozen one is dropped, and once it is
/// resumed the farm still serves (the worker may come back or not).
#[test]
fn a_frozen_worker_is_worked_around_and_dropped() {
    let _turn = exclusive();
    let timeout = FROZEN_HEARTBEAT_TIMEOUT_MS.to_string();
    let mut farm = Farm::start_with(
        "127.0.0.1:0",
        &["w1", "w2"],
        &["--heartbeat-timeout-ms", &timeout],
    );
    let lights = scene_path("lights.json");
    let job = farm.submit(&lights, &[&["--tile", "32"][..], MEDIUM].concat());
    farm.wait_for_tiles(job, 20);

    farm.workers[1].signal("STOP");
    let stopped = Instant::now();
    // It held tiles when it froze (credit 2): they must be given to w1.
    let status = farm.wait_done(job);
    let done_after = stopped.elapsed();
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    // The heartbeat timeout drops the frozen worker; its last heartbeat came up to 1 s
    // before the freeze, and a second more is allowed for the timer's slack.
    let workers = poll("the frozen worker to be dropped", REGISTER_TIMEOUT, || {
        farm.try_workers()
            .filter(|w| w.iter().all(|w| w["name"] != "w2"))
    });
    let dropped_after = stopped.elapsed();
    assert_eq!(workers.len(), 1, "{workers:?}");
    let soonest = Duration::from_millis(FROZEN_HEARTBEAT_TIMEOUT_MS) - Duration::from_secs(2);
    assert!(
        dropped_after >= soonest,
        "dropped {dropped_after:?} after it froze: sooner than the heartbeat timeout allows"
    );
    eprintln!(
        "job done {:.1} s and worker dropped {:.1} s after the freeze",
        done_after.as_secs_f64(),
        dropped_after.as_secs_f64()
    );

    farm.workers[1].signal("CONT");
    // Whether it reconnects or not, it must not crash, and the farm must go on.
    thread::sleep(Duration::from_millis(500));
    assert!(
        farm.workers[1].is_running(),
        "the resumed worker exited: {:?}",
        farm.workers[1].child.try_wait()
    );
    farm.assert_job_image(job, &lights, MEDIUM, "the job with a frozen worker");

    let seed = scene_path("seed.json");
    let small = ["--width", "200", "--height", "150"];
    let second = farm.submit(&seed, &[&["--tile", "16"][..], &small].concat());
    farm.wait_done(second);
    let reference = render_reference(farm.dir(), &seed, "seed-reference.png", &small);
    farm.assert_job_image_is(second, &reference, "a job after the frozen worker resumed");
    farm.assert_no_divergent_duplicates();
}

/// A worker stopped with SIGTERM mid-job finishes the tiles it holds and exits 0
/// promptly; the other worker completes the job.
#[test]
fn a_terminated_worker_drains_and_the_job_completes_on_the_other() {
    let _turn = exclusive();
    let mut farm = Farm::start("127.0.0.1:0", &["w1", "w2"]);
    let lights = scene_path("lights.json");
    let job = farm.submit(&lights, &[&["--tile", "32"][..], MEDIUM].concat());
    farm.wait_for_tiles(job, 20);

    farm.workers[1].signal("TERM");
    let terminated = Instant::now();
    let exit = farm.workers[1]
        .wait_exit(Duration::from_secs(10))
        .expect("the worker still runs 10 s after SIGTERM");
    let took = terminated.elapsed();
    assert!(exit.success(), "the worker exited with {exit}");
    assert!(
        took <= Duration::from_secs(3),
        "the worker took {took:?} to drain tiles of a few milliseconds"
    );
    assert_ne!(
        farm.status(job)["state"],
        "done",
        "the job ended before the worker did: make it longer"
    );
    let log = farm.workers[1].log_text();
    assert!(log.contains("drained"), "the worker's log: {log}");

    let status = farm.wait_done(job);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    let workers = farm.wait_for_workers(&["w1"]);
    assert_eq!(workers[0]["name"], "w1", "{workers:?}");
    eprintln!("worker drained and exited 0 in {} ms", took.as_millis());
    farm.assert_job_image(job, &lights, MEDIUM, "the job whose worker was terminated");
    farm.assert_no_divergent_duplicates();
}
