//! Fault injection on a real farm (the `tessera` binary as coordinator, workers and
//! clients, on 127.0.0.1 only).
//!
//! What is proven: whatever happens to the processes of the farm mid-job, the job ends
//! `done` and its fetched PNG is byte for byte the one `tessera render` writes.
//!
//! - **Workers killed** (`kill -9`) every 300 ms for 3 s, each replaced by a new one.
//! - **A worker frozen** (`SIGSTOP`) for longer than the heartbeat timeout: the other
//!   worker takes its tiles over (lease expiry), the frozen one is dropped, and after
//!   `SIGCONT` the farm still serves.
//! - **The coordinator killed** (`kill -9`) and restarted on the same port and data
//!   directory: the job keeps its id and the tiles recorded before the kill, the
//!   workers come back by themselves, and only the missing tiles are rendered; every
//!   tile `status` reported done before the kill is still done after the restart.
//! - **The coordinator stopped** (`SIGTERM`): it exits 0 within 12 s, a job submitted
//!   meanwhile is refused without harm, and after a restart the job resumes.
//! - **A worker stopped** (`SIGTERM`): it finishes its tiles and exits 0 promptly; the
//!   remaining worker completes the job.
//!
//! Every wait has a deadline, and every process is killed and reaped by a guard, also
//! when an assertion fails (the daemons' logs are then printed). The tests of this file
//! run one at a time, so that their timing does not depend on each other.

mod common;

use std::path::Path;
use std::thread;
use std::time::{Duration, Instant};

use common::{Daemon, SplitMix};
use serde_json::Value;
use tempfile::TempDir;

/// Longest a job of these tests may take once the faults have stopped.
const JOB_TIMEOUT: Duration = Duration::from_secs(40);
/// Longest a worker may take to register, also after a reconnection backoff.
const REGISTER_TIMEOUT: Duration = Duration::from_secs(20);

// CPU-seconds of `lights.json` at each size, measured on the project's 2-core AMD EPYC
// machines. The renderer gets faster over time: a test that needs its job to last
// checks that it did, and these grow when one finds it did not.

/// Some 1.4 CPU-seconds of work in 1,900 tiles.
const MEDIUM: &[&str] = &["--width", "1600", "--height", "1200", "--aa", "4"];
/// Some 7 CPU-seconds in 4,275 tiles: over 3 s on three workers sharing two cores.
const LONG: &[&str] = &["--width", "2400", "--height", "1800", "--aa", "6"];
/// Some 10 CPU-seconds (1,102 tiles of 64): longer than the shutdown grace on one
/// worker.
const VERY_LONG: &[&str] = &["--width", "2400", "--height", "1800", "--aa", "7"];

/// A coordinator with its data directory and workers; dropping it kills them all.
struct Farm {
    coordinator: Daemon,
    addr: String,
    workers: Vec<Daemon>,
    /// How many coordinators were started (for log names).
    starts: usize,
    /// Declared last: it outlives the processes.
    dir: TempDir,
}

impl Farm {
    /// A coordinator listening on `listen` and one-thread workers named `workers`, all
    /// registered before this returns.
    fn start(listen: &str, workers: &[&str]) -> Farm {
        let dir = TempDir::new().expect("cannot create a temporary directory");
        let (coordinator, addr) = common::start_coordinator(
            dir.path(),
            &dir.path().join("data"),
            listen,
            &[],
            "coordinator-1.log",
        );
        let mut farm = Farm {
            coordinator,
            addr,
            workers: Vec::new(),
            starts: 1,
            dir,
        };
        for name in workers {
            farm.add_worker(name);
        }
        farm.wait_for_workers(workers.len());
        farm
    }

    fn dir(&self) -> &Path {
        self.dir.path()
    }

    /// Starts a coordinator again on the same address and data directory.
    fn restart_coordinator(&mut self) {
        self.starts += 1;
        let (coordinator, addr) = common::start_coordinator(
            self.dir.path(),
            &self.dir.path().join("data"),
            &self.addr,
            &[],
            &format!("coordinator-{}.log", self.starts),
        );
        assert_eq!(addr, self.addr, "restarted on the same address");
        self.coordinator = coordinator;
    }

    fn add_worker(&mut self, name: &str) {
        let worker = common::start_worker(self.dir(), &self.addr, name);
        self.workers.push(worker);
    }

    /// `workers --json`, or `None` if the coordinator cannot be reached.
    fn try_workers(&self) -> Option<Vec<Value>> {
        let run = common::client(self.dir(), &self.addr, &["workers", "--json"]);
        if !run.status.success() {
            return None;
        }
        match serde_json::from_str(run.stdout.trim()) {
            Ok(Value::Array(workers)) => Some(workers),
            other => panic!("workers --json: {other:?}"),
        }
    }

    fn wait_for_workers(&self, n: usize) -> Vec<Value> {
        common::poll(
            &format!("{n} workers to register"),
            REGISTER_TIMEOUT,
            || self.try_workers().filter(|w| w.len() == n),
        )
    }

    fn submit(&self, args: &[&str]) -> u64 {
        common::submit(self.dir(), &self.addr, args)
    }

    fn status(&self, job: u64) -> Value {
        common::try_status(self.dir(), &self.addr, job)
            .unwrap_or_else(|| panic!("status {job} failed"))
    }

    /// Waits until the job has at least `tiles` tiles done, and checks that it is
    /// still running then.
    fn wait_for_tiles(&self, job: u64, tiles: u64) -> Value {
        let status = common::poll(&format!("{tiles} tiles of job {job}"), JOB_TIMEOUT, || {
            let status = self.status(job);
            (status["tiles_done"].as_u64() >= Some(tiles)).then_some(status)
        });
        assert_eq!(
            status["state"], "running",
            "the job should still run (make it longer): {status}"
        );
        status
    }

    fn wait_done(&self, job: u64) -> Value {
        common::wait_done(self.dir(), &self.addr, job, JOB_TIMEOUT)
    }

    /// The job's fetched image is `tessera render`'s for `scene` and `size`.
    fn assert_job_image(&self, job: u64, scene: &str, size: &[&str], what: &str) {
        let reference = common::render_reference(self.dir(), scene, "reference.png", size);
        self.assert_job_image_is(job, &reference, what);
    }

    fn assert_job_image_is(&self, job: u64, reference: &Path, what: &str) {
        let out = common::fetch(self.dir(), &self.addr, job, &format!("job-{job}.png"));
        common::assert_same_png(&out, reference, what);
    }

    /// No straggler's duplicate differed from the accepted tile, in any coordinator
    /// log of this farm.
    fn assert_no_divergent_duplicates(&self) {
        for i in 1..=self.starts {
            let log = std::fs::read_to_string(self.dir().join(format!("coordinator-{i}.log")))
                .unwrap_or_default();
            assert!(
                !log.contains("differs from the accepted one"),
                "a duplicate tile differed (coordinator-{i}.log)"
            );
        }
    }
}

fn tiles_total(status: &Value) -> u64 {
    status["tiles_total"].as_u64().expect("tiles_total")
}

/// `args` + `more`.
fn cat<'a>(args: &[&'a str], more: &[&'a str]) -> Vec<&'a str> {
    args.iter().chain(more).copied().collect()
}

/// (a) A random worker is killed every 300 ms for 3 s and replaced each time: the job
/// still completes with `tessera render`'s image.
#[test]
fn workers_killed_every_300_ms_do_not_change_the_image() {
    let _serial = common::serial();
    let mut farm = Farm::start("127.0.0.1:0", &["w1", "w2", "w3"]);
    let lights = common::scene_path("lights.json");
    let job = farm.submit(&cat(&[&lights, "--tile", "32"], LONG));
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
        let replacement = common::start_worker(farm.dir(), &farm.addr, &format!("r{kills}"));
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

/// (b) A worker frozen with SIGSTOP mid-job for longer than the heartbeat timeout:
/// the job completes on the other worker, the frozen one is dropped, and once it is
/// resumed the farm still serves (the worker may come back or not).
#[test]
fn a_frozen_worker_is_worked_around_and_dropped() {
    let _serial = common::serial();
    let mut farm = Farm::start("127.0.0.1:0", &["w1", "w2"]);
    let lights = common::scene_path("lights.json");
    let job = farm.submit(&cat(&[&lights, "--tile", "32"], MEDIUM));
    farm.wait_for_tiles(job, 20);

    farm.workers[1].signal("STOP");
    let stopped = Instant::now();
    // It held tiles when it froze (credit 2): they must be given to w1.
    let status = farm.wait_done(job);
    let done_after = stopped.elapsed();
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    // The heartbeat timeout (5 s) drops the frozen worker.
    let workers = common::poll("the frozen worker to be dropped", REGISTER_TIMEOUT, || {
        farm.try_workers()
            .filter(|w| w.iter().all(|w| w["name"] != "w2"))
    });
    let dropped_after = stopped.elapsed();
    assert_eq!(workers.len(), 1, "{workers:?}");
    assert!(
        dropped_after >= Duration::from_secs(3),
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

    let seed = common::scene_path("seed.json");
    let small = ["--width", "200", "--height", "150"];
    let second = farm.submit(&cat(&[&seed, "--tile", "16"], &small));
    farm.wait_done(second);
    let reference = common::render_reference(farm.dir(), &seed, "seed-reference.png", &small);
    farm.assert_job_image_is(second, &reference, "a job after the frozen worker resumed");
    farm.assert_no_divergent_duplicates();
}

/// Starts a farm of two workers on a fixed port, submits [`MEDIUM`], kills the
/// coordinator (SIGKILL) as soon as `status` reports a fifth of the tiles done, and
/// restarts it on the same port and data directory. Returns the farm, the job, the
/// tiles reported done just before the kill and the job's status just after the
/// restart.
fn kill_coordinator_mid_job() -> (Farm, u64, u64, Value) {
    let port = common::free_port();
    let mut farm = Farm::start(&format!("127.0.0.1:{port}"), &["w1", "w2"]);
    let lights = common::scene_path("lights.json");
    let job = farm.submit(&cat(&[&lights, "--tile", "32"], MEDIUM));
    let total = tiles_total(&farm.status(job));
    let before = farm.wait_for_tiles(job, total / 5)["tiles_done"]
        .as_u64()
        .expect("tiles_done");
    farm.coordinator.kill9();
    farm.restart_coordinator();
    let status = farm.status(job);
    (farm, job, before, status)
}

/// (c) The coordinator killed with SIGKILL mid-job and restarted on the same port and
/// data directory: the job (same id) is known at once with the tiles recorded before
/// the kill, the workers reconnect by themselves, only the missing tiles are rendered,
/// and the image is `tessera render`'s.
#[test]
fn a_coordinator_killed_mid_job_resumes_it_after_a_restart() {
    let _serial = common::serial();
    let (mut farm, job, before, status) = kill_coordinator_mid_job();
    let total = tiles_total(&status);
    let resumed = status["tiles_done"].as_u64().expect("tiles_done");
    assert!(
        resumed > 0 && resumed < total,
        "the job should resume with some but not all tiles done: {status}"
    );
    assert!(
        matches!(status["state"].as_str(), Some("queued" | "running")),
        "{status}"
    );

    // The same workers (not restarted) come back by themselves.
    assert!(farm.workers.iter_mut().all(Daemon::is_running));
    farm.wait_for_workers(2);
    let status = farm.wait_done(job);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    // Only the tiles not recorded before the kill were rendered again.
    let rendered: u64 = farm
        .wait_for_workers(2)
        .iter()
        .map(|w| w["tiles_done"].as_u64().expect("tiles_done"))
        .sum();
    assert!(
        rendered <= total - resumed,
        "{rendered} tiles rendered after the restart, but only {} were missing",
        total - resumed
    );
    eprintln!(
        "{before} tiles reported done before the kill, {resumed} after the restart, \
         {rendered} rendered since, {total} in all"
    );
    let lights = common::scene_path("lights.json");
    farm.assert_job_image(job, &lights, MEDIUM, "the job whose coordinator was killed");
    farm.assert_no_divergent_duplicates();
}

/// Every tile `status` reported done before a SIGKILL of the coordinator is still done
/// after its restart.
#[test]
fn tiles_reported_done_survive_a_coordinator_kill() {
    let _serial = common::serial();
    let (_farm, _job, before, status) = kill_coordinator_mid_job();
    let resumed = status["tiles_done"].as_u64().expect("tiles_done");
    assert!(
        resumed >= before,
        "{before} tiles were reported done before the kill, only {resumed} after the \
         restart: {status}"
    );
}

/// (d) The coordinator stopped with SIGTERM mid-job exits 0 within 12 s; a job
/// submitted meanwhile is refused (no crash); restarted on the same port and data
/// directory, it resumes the job, which gives `tessera render`'s image.
#[test]
fn a_coordinator_terminated_mid_job_exits_cleanly_and_resumes_after_a_restart() {
    let _serial = common::serial();
    let port = common::free_port();
    let mut farm = Farm::start(&format!("127.0.0.1:{port}"), &["w1"]);
    let lights = common::scene_path("lights.json");
    let seed = common::scene_path("seed.json");
    let (dir, addr) = (farm.dir().to_owned(), farm.addr.clone());
    // Scoped threads: a failed assertion still waits for (and reaps) their processes.
    thread::scope(|s| {
        // The reference renders on the second core while the worker uses the first.
        let reference = s.spawn(|| {
            let args = cat(VERY_LONG, &["--threads", "1"]);
            common::render_reference(&dir, &lights, "reference.png", &args)
        });
        let job = farm.submit(&cat(&[&lights, "--tile", "64"], VERY_LONG));
        let total = tiles_total(&farm.wait_for_tiles(job, 20));

        farm.coordinator.signal("TERM");
        let terminated = Instant::now();
        common::poll(
            "the coordinator to log its shutdown",
            Duration::from_secs(5),
            || {
                farm.coordinator
                    .log_text()
                    .contains("shutting down")
                    .then_some(())
            },
        );
        // A job submitted during the shutdown: refused, or the connection is.
        let late = s.spawn(|| common::client(&dir, &addr, &["submit", &seed]));
        let exit = farm
            .coordinator
            .wait_exit(Duration::from_secs(15))
            .expect("the coordinator still runs 15 s after SIGTERM");
        let took = terminated.elapsed();
        assert!(exit.success(), "the coordinator exited with {exit}");
        assert!(
            took <= Duration::from_secs(12),
            "the coordinator took {took:?} to exit after SIGTERM"
        );
        let late = late.join().expect("the late client panicked");
        assert!(
            !late.status.success(),
            "a job was accepted during the shutdown: {}",
            late.stdout
        );
        let lines: Vec<&str> = late.stderr.lines().collect();
        assert!(
            lines.len() == 1 && lines[0].starts_with("error: "),
            "the refused submit prints one error line: {:?}",
            late.stderr
        );
        eprintln!(
            "coordinator exited 0 {:.1} s after SIGTERM; submit meanwhile: {}",
            took.as_secs_f64(),
            lines[0]
        );
        // The ids reserved ahead and not issued were given back at the clean stop.
        let last_id = std::fs::read_to_string(dir.join("data").join("last-job-id"))
            .expect("the coordinator keeps DATA/last-job-id");
        assert_eq!(last_id.trim(), job.to_string(), "DATA/last-job-id");

        farm.restart_coordinator();
        let status = farm.status(job);
        let resumed = status["tiles_done"].as_u64().expect("tiles_done");
        assert!(
            resumed > 0 && resumed < total,
            "the job should resume with some but not all tiles done: {status}"
        );
        let jobs = common::ok(common::client(&dir, &addr, &["list", "--json"]), "list");
        let jobs: Value = serde_json::from_str(jobs.stdout.trim()).expect("list --json");
        assert_eq!(
            jobs.as_array().map(Vec::len),
            Some(1),
            "no job was added during the shutdown: {jobs}"
        );
        // w1 comes back by itself; a second worker helps it finish sooner.
        farm.add_worker("w2");
        farm.wait_for_workers(2);
        let status = farm.wait_done(job);
        assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
        eprintln!("{resumed} of {total} tiles were done at the restart");
        let reference = reference.join().expect("the reference render panicked");
        farm.assert_job_image_is(job, &reference, "the job resumed after SIGTERM");
        farm.assert_no_divergent_duplicates();
    });
}

/// (e) A worker stopped with SIGTERM mid-job finishes the tiles it holds and exits 0
/// promptly; the other worker completes the job.
#[test]
fn a_terminated_worker_drains_and_the_job_completes_on_the_other() {
    let _serial = common::serial();
    let mut farm = Farm::start("127.0.0.1:0", &["w1", "w2"]);
    let lights = common::scene_path("lights.json");
    let job = farm.submit(&cat(&[&lights, "--tile", "32"], MEDIUM));
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
    let workers = farm.wait_for_workers(1);
    assert_eq!(workers[0]["name"], "w1", "{workers:?}");
    eprintln!("worker drained and exited 0 in {} ms", took.as_millis());
    farm.assert_job_image(job, &lights, MEDIUM, "the job whose worker was terminated");
    farm.assert_no_divergent_duplicates();
}
