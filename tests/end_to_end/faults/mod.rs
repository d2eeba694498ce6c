//! Faults of the farm's processes and of the network between them, injected into a
//! real farm (the `tessera` binary as coordinator, workers and clients, on 127.0.0.1
//! only) while it renders.
//!
//! What is proven: whatever happens to the processes of the farm mid-job, the job ends
//! `done` and its fetched PNG is byte for byte the one `tessera render` writes.
//!
//! Every wait has a deadline, a job that stops progressing fails its test with its
//! status instead of waiting out a long timeout, and every process is killed and reaped
//! by a guard, also when an assertion fails (the daemons' logs are then printed). Each
//! of these tests has the machine to itself, so that their timing does not depend on
//! other tests.

mod assets;
mod coordinator;
mod http_api;
mod liveness;
mod network;
mod workers;

use std::path::{Path, PathBuf};
use std::thread;
use std::time::{Duration, Instant};

use serde_json::Value;
use tempfile::TempDir;

use crate::support::{
    assert_job_image, assert_not_ended_badly, assert_same_png, fetch, free_port, poll,
    start_coordinator, start_worker, submit_scene, tiles_done, try_status, try_workers,
    wait_for_tiles, Daemon, POLL, REGISTER_TIMEOUT,
};

/// Longest a job of these tests may take once the faults have stopped.
const JOB_TIMEOUT: Duration = Duration::from_secs(40);
/// Longest a running job may go without a new tile while workers are connected.
const STALL: Duration = Duration::from_secs(15);

// CPU-seconds of `lights.json` at each size, measured on the project's 2-core AMD EPYC
// machines. The renderer gets faster over time: a test that needs its job to last
// checks that it did, and these grow when one finds it did not.

/// Some 1.4 CPU-seconds of work in 1,900 tiles (with `--tile 32`).
const MEDIUM: &[&str] = &["--width", "1600", "--height", "1200", "--aa", "4"];
/// Some 3.6 CPU-seconds in 1,900 tiles of 32 pixels.
const JOB: &[&str] = &[
    "--width", "1600", "--height", "1200", "--aa", "5", "--tile", "32",
];

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
    /// A coordinator listening on `listen` and one-thread workers named `workers`,
    /// exactly those registered before this returns.
    fn start(listen: &str, workers: &[&str]) -> Farm {
        Farm::start_with(listen, workers, &[])
    }

    /// [`Farm::start`] with more arguments for the coordinator.
    fn start_with(listen: &str, workers: &[&str], coordinator_args: &[&str]) -> Farm {
        let dir = TempDir::new().expect("cannot create a temporary directory");
        let (coordinator, addr) = start_coordinator(
            dir.path(),
            &dir.path().join("data"),
            listen,
            coordinator_args,
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
        farm.wait_for_workers(workers);
        farm
    }

    /// [`Farm::start`] on a port of its own, so that the coordinator can be restarted
    /// on it.
    fn restartable(workers: &[&str]) -> Farm {
        Farm::start(&format!("127.0.0.1:{}", free_port()), workers)
    }

    fn dir(&self) -> &Path {
        self.dir.path()
    }

    fn data(&self) -> PathBuf {
        self.dir.path().join("data")
    }

    /// Starts a coordinator again on the same address and data directory.
    fn restart_coordinator(&mut self) {
        self.starts += 1;
        let (coordinator, addr) = start_coordinator(
            self.dir.path(),
            &self.data(),
            &self.addr,
            &[],
            &format!("coordinator-{}.log", self.starts),
        );
        assert_eq!(addr, self.addr, "restarted on the same address");
        self.coordinator = coordinator;
    }

    fn add_worker(&mut self, name: &str) {
        let worker = start_worker(self.dir(), &self.addr, name);
        self.workers.push(worker);
    }

    /// Starts a worker that reaches the coordinator at `addr` (a relay).
    fn add_worker_at(&mut self, addr: &str, name: &str) {
        let worker = start_worker(self.dir(), addr, name);
        self.workers.push(worker);
    }

    fn try_workers(&self) -> Option<Vec<Value>> {
        try_workers(self.dir(), &self.addr)
    }

    /// Waits until exactly the workers named `names` are connected.
    fn wait_for_workers(&self, names: &[&str]) -> Vec<Value> {
        let mut want: Vec<&str> = names.to_vec();
        want.sort_unstable();
        poll(
            &format!("the workers {want:?} to register"),
            REGISTER_TIMEOUT,
            || {
                let workers = self.try_workers()?;
                let mut now: Vec<&str> = workers
                    .iter()
                    .map(|w| w["name"].as_str().expect("name"))
                    .collect();
                now.sort_unstable();
                (now == want).then(|| workers.clone())
            },
        )
    }

    fn submit(&self, scene: &str, args: &[&str]) -> u64 {
        submit_scene(self.dir(), &self.addr, scene, args)
    }

    fn try_status(&self, job: u64) -> Option<Value> {
        try_status(self.dir(), &self.addr, job)
    }

    fn status(&self, job: u64) -> Value {
        self.try_status(job)
            .unwrap_or_else(|| panic!("status {job} failed"))
    }

    /// Waits until the job has at least `tiles` tiles done, and checks that it is
    /// still running then.
    fn wait_for_tiles(&self, job: u64, tiles: u64) -> Value {
        wait_for_tiles(job, tiles, JOB_TIMEOUT, || self.status(job))
    }

    /// Polls `status` until the job is `done` (within [`JOB_TIMEOUT`]), tolerating a
    /// coordinator that is briefly unreachable; panics if the job ends otherwise.
    fn wait_done(&self, job: u64) -> Value {
        crate::support::wait_done(self.dir(), &self.addr, job, JOB_TIMEOUT)
    }

    /// Waits for the job to be `done`, failing at once if it ends otherwise and as soon
    /// as it goes [`STALL`] without a new tile (a coordinator that is briefly
    /// unreachable is tolerated).
    fn wait_done_progressing(&self, job: u64) -> Value {
        let started = Instant::now();
        let mut last_tiles = None;
        let mut last_change = Instant::now();
        let mut last_status = Value::Null;
        loop {
            if let Some(status) = self.try_status(job) {
                assert_not_ended_badly(job, &status);
                if status["state"] == "done" {
                    return status;
                }
                let tiles = tiles_done(&status);
                if last_tiles != Some(tiles) {
                    last_tiles = Some(tiles);
                    last_change = Instant::now();
                }
                last_status = status;
            }
            if last_change.elapsed() > STALL || started.elapsed() > JOB_TIMEOUT {
                let stuck = last_change.elapsed() > STALL;
                panic!(
                    "job {job} {} ({}/{} tiles, state {}, eta_ms {}); workers connected: {}",
                    if stuck {
                        format!("made no progress for {STALL:?}")
                    } else {
                        format!("not done after {JOB_TIMEOUT:?}")
                    },
                    last_status["tiles_done"],
                    last_status["tiles_total"],
                    last_status["state"],
                    last_status["eta_ms"],
                    self.try_workers()
                        .map_or("(unreachable)".to_owned(), |w| Value::Array(w).to_string()),
                );
            }
            thread::sleep(POLL);
        }
    }

    /// Waits for the job to have more than `since` tiles done (or be done), at most
    /// [`STALL`]; returns when. Fails with the job's status and the workers if it does
    /// not.
    fn wait_progress(&self, job: u64, since: u64, what: &str) -> Instant {
        let deadline = Instant::now() + STALL;
        loop {
            let status = self.status(job);
            assert_not_ended_badly(job, &status);
            if tiles_done(&status) > since || status["state"] == "done" {
                return Instant::now();
            }
            assert!(
                Instant::now() < deadline,
                "job {job} made no progress within {STALL:?} {what} ({}/{} tiles, state {}, \
                 eta_ms {}); workers connected: {}",
                status["tiles_done"],
                status["tiles_total"],
                status["state"],
                status["eta_ms"],
                self.try_workers()
                    .map_or("(unreachable)".to_owned(), |w| Value::Array(w).to_string()),
            );
            thread::sleep(POLL);
        }
    }

    /// The job's fetched image is byte for byte `reference`.
    fn assert_job_image_is(&self, job: u64, reference: &Path, what: &str) {
        let out = fetch(self.dir(), &self.addr, job, &format!("job-{job}.png"));
        assert_same_png(&out, reference, what);
    }

    /// The job's fetched image is `tessera render`'s for `scene` and `args`.
    fn assert_job_image(&self, job: u64, scene: &str, args: &[&str], what: &str) {
        assert_job_image(self.dir(), &self.addr, job, scene, args, what);
    }

    /// Every coordinator log of this farm, concatenated.
    fn coordinator_logs(&self) -> String {
        (1..=self.starts)
            .map(|i| {
                std::fs::read_to_string(self.dir().join(format!("coordinator-{i}.log")))
                    .unwrap_or_default()
            })
            .collect::<Vec<_>>()
            .join("\n")
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
