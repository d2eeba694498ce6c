//! The coordinator under the faults of everyday operation (the `tessera` binary as
//! coordinator, workers and clients, on 127.0.0.1 only).
//!
//! What is proven: a job always finishes, `done`, with the image `tessera render`
//! writes, byte for byte, whatever happens to the machines around it:
//!
//! - **A worker killed (`kill -9`) and restarted under the same `--name`**, five times
//!   with one worker and six times with two: the restarted worker is never kept from
//!   the job (a lost connection is not proof that a machine is bad). Each restart
//!   reports the time from the worker's registration to its next tile.
//! - **An 8 s network cut** between the workers and the coordinator, through a relay
//!   that stops forwarding without closing anything: longer than the heartbeat
//!   timeout, so the workers are dropped and come back, and the job still ends.
//! - **The coordinator stopped (`SIGSTOP`) for 7 s**, past the 5 s heartbeat timeout,
//!   then continued: it reads what the workers sent meanwhile before expiring anyone,
//!   so it drops no worker.
//! - **The coordinator killed and restarted under a `submit --wait`**: the client has
//!   printed `submitted job N` at once, rides through the restart and exits 0 with the
//!   image.
//! - **Memory over 15 sequential 1080p jobs**: the coordinator keeps no finished image
//!   in memory, so its resident set after 15 jobs is about that after 4; the database
//!   gives the tile blobs' space back.
//! - **A job restored after a restart** reports its true state (`running`), its time
//!   since the original submission, and a believable rays per second.
//!
//! Every wait has a deadline, a job that stops progressing fails its test with its
//! status instead of waiting out a long timeout, and every process is killed and reaped
//! by a guard, also when an assertion fails (the daemons' logs are then printed). The
//! tests of this file run one at a time.

mod common;

use std::path::{Path, PathBuf};
use std::thread;
use std::time::{Duration, Instant};

use common::proxy::CutProxy;
use common::{assert_not_ended_badly, render_args, tiles_done, tiles_total, Daemon, Findings};
use serde_json::Value;
use tempfile::TempDir;

/// Longest any job of these tests may take once the faults have stopped.
const JOB_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest a running job may go without a new tile while workers are connected.
const STALL: Duration = Duration::from_secs(15);
/// Longest a worker may take to register, also after a reconnection backoff.
const REGISTER_TIMEOUT: Duration = Duration::from_secs(20);

/// Some 2 CPU-seconds in 4,275 tiles of 16 pixels: the job of one restarted worker.
const ONE_WORKER_JOB: &[&str] = &[
    "--width", "1200", "--height", "900", "--aa", "5", "--tile", "16",
];
/// Some 5 CPU-seconds in 7,500 tiles of 16 pixels: the job of two restarted workers.
const TWO_WORKER_JOB: &[&str] = &[
    "--width", "1600", "--height", "1200", "--aa", "6", "--tile", "16",
];
/// Some 3.6 CPU-seconds in 1,900 tiles of 32 pixels.
const JOB: &[&str] = &[
    "--width", "1600", "--height", "1200", "--aa", "5", "--tile", "32",
];
/// A 1080p frame in about 0.2 CPU-seconds, whose PNG is about 0.5 MB.
const FRAME_1080P: &[&str] = &["--width", "1920", "--height", "1080", "--aa", "1"];

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
    /// A coordinator listening on `listen`, without workers.
    fn start(listen: &str) -> Farm {
        let dir = TempDir::new().expect("cannot create a temporary directory");
        let (coordinator, addr) = common::start_coordinator(
            dir.path(),
            &dir.path().join("data"),
            listen,
            &[],
            "coordinator-1.log",
        );
        Farm {
            coordinator,
            addr,
            workers: Vec::new(),
            starts: 1,
            dir,
        }
    }

    /// A coordinator on a port of its own (so that it can be restarted on it) and
    /// registered workers named `workers`.
    fn with_workers(workers: &[&str]) -> Farm {
        let mut farm = Farm::start(&format!("127.0.0.1:{}", common::free_port()));
        for name in workers {
            farm.add_worker(name);
        }
        farm.wait_for_workers(workers);
        farm
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
        let (coordinator, addr) = common::start_coordinator(
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
        let worker = common::start_worker(self.dir(), &self.addr, name);
        self.workers.push(worker);
    }

    fn add_worker_at(&mut self, addr: &str, name: &str) {
        let worker = common::start_worker(self.dir(), addr, name);
        self.workers.push(worker);
    }

    fn try_workers(&self) -> Option<Vec<Value>> {
        common::try_workers(self.dir(), &self.addr)
    }

    /// Waits until exactly the workers named `names` are connected.
    fn wait_for_workers(&self, names: &[&str]) -> Vec<Value> {
        let mut want: Vec<&str> = names.to_vec();
        want.sort_unstable();
        common::poll(
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
        let mut all = vec![scene];
        all.extend(args);
        common::submit(self.dir(), &self.addr, &all)
    }

    fn try_status(&self, job: u64) -> Option<Value> {
        common::try_status(self.dir(), &self.addr, job)
    }

    fn status(&self, job: u64) -> Value {
        self.try_status(job)
            .unwrap_or_else(|| panic!("status {job} failed"))
    }

    /// Waits until the job has at least `tiles` tiles done, and checks that it is
    /// still running then.
    fn wait_for_tiles(&self, job: u64, tiles: u64) -> Value {
        let status = common::poll(&format!("{tiles} tiles of job {job}"), JOB_TIMEOUT, || {
            let status = self.status(job);
            assert_not_ended_badly(job, &status);
            (tiles_done(&status) >= tiles).then_some(status)
        });
        assert_eq!(
            status["state"], "running",
            "the job should still run (make it longer): {status}"
        );
        status
    }

    /// Waits for the job to be `done`, failing at once if it ends otherwise and as soon
    /// as it goes `stall` without a new tile (a coordinator that is briefly unreachable
    /// is tolerated).
    fn wait_done(&self, job: u64, stall: Duration) -> Value {
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
            if last_change.elapsed() > stall || started.elapsed() > JOB_TIMEOUT {
                let stuck = last_change.elapsed() > stall;
                panic!(
                    "job {job} {} ({}/{} tiles, state {}, eta_ms {}); workers connected: {}",
                    if stuck {
                        format!("made no progress for {stall:?}")
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
            thread::sleep(common::POLL);
        }
    }

    /// The job's fetched image is byte for byte `reference`.
    fn assert_job_image_is(&self, job: u64, reference: &Path, what: &str) {
        let out = common::fetch(self.dir(), &self.addr, job, &format!("job-{job}.png"));
        common::assert_same_png(&out, reference, what);
    }

    /// The job's fetched image is `tessera render`'s for `scene` and `args`.
    fn assert_job_image(&self, job: u64, scene: &str, args: &[&str], what: &str) {
        let reference = common::render_reference(
            self.dir(),
            scene,
            &format!("reference-{job}.png"),
            &render_args(args),
        );
        self.assert_job_image_is(job, &reference, what);
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
}

/// Waits for the job to have more than `since` tiles done (or be done), at most
/// [`STALL`]; returns when. Fails with the job's status and the workers if it does not.
fn wait_progress(farm: &Farm, job: u64, since: u64, what: &str) -> Instant {
    let deadline = Instant::now() + STALL;
    loop {
        let status = farm.status(job);
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
            farm.try_workers()
                .map_or("(unreachable)".to_owned(), |w| Value::Array(w).to_string()),
        );
        thread::sleep(common::POLL);
    }
}

/// The connected worker named `name`.
fn worker_named(workers: &[Value], name: &str) -> Option<Value> {
    workers.iter().find(|w| w["name"] == name).cloned()
}

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
    let old = common::poll(
        &format!("{name} to render {after_tiles} tiles (round {round})"),
        STALL,
        || {
            let status = farm.status(job);
            assert_not_ended_badly(job, &status);
            if status["state"] == "done" {
                return Some(None);
            }
            let worker = worker_named(&farm.try_workers()?, name)?;
            (worker["tiles_done"].as_u64() >= Some(after_tiles)).then_some(Some(worker))
        },
    )?;
    farm.workers[i].kill9();
    let restarted = Instant::now();
    farm.workers[i] = common::start_worker(farm.dir(), &farm.addr, name);

    // Registered again: a new connection under the same name.
    let (new_id, registered) = common::poll(
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
        thread::sleep(common::POLL);
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

/// One worker, killed five times mid-job and restarted each time under its own name
/// (as systemd or Kubernetes restart it): it is never blocked from the job, which ends
/// `done` with `tessera render`'s image.
#[test]
fn a_lone_worker_restarted_under_its_name_five_times_finishes_the_job() {
    let _serial = common::serial();
    let mut farm = Farm::with_workers(&["w1"]);
    let lights = common::scene_path("lights.json");
    let job = farm.submit(&lights, ONE_WORKER_JOB);
    farm.wait_for_tiles(job, 1);

    let restarts = restart_workers_in_turn(&mut farm, &["w1"], job, 5, 40);
    let status = farm.wait_done(job, STALL);
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
    let _serial = common::serial();
    let names = ["w1", "w2"];
    let mut farm = Farm::with_workers(&names);
    let lights = common::scene_path("lights.json");
    let job = farm.submit(&lights, TWO_WORKER_JOB);
    farm.wait_for_tiles(job, 1);

    let restarts = restart_workers_in_turn(&mut farm, &names, job, 6, 25);
    let status = farm.wait_done(job, STALL);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    report_restarts("two workers", &restarts);
    farm.assert_job_image(
        job,
        &lights,
        TWO_WORKER_JOB,
        "the job of two workers restarted six times",
    );
}

/// The link between both workers and the coordinator is cut for 8 s (longer than the
/// 5 s heartbeat timeout, shorter than the workers' 10 s silence limit): the workers
/// are dropped and come back under their names, and the job ends `done` with
/// `tessera render`'s image.
#[test]
fn an_eight_second_network_cut_ends_with_the_job_done() {
    let _serial = common::serial();
    let mut farm = Farm::start("127.0.0.1:0");
    let proxy = CutProxy::start(&farm.addr);
    let relay = proxy.address().to_owned();
    farm.add_worker_at(&relay, "w1");
    farm.add_worker_at(&relay, "w2");
    farm.wait_for_workers(&["w1", "w2"]);
    let lights = common::scene_path("lights.json");
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

    let resumed = wait_progress(&farm, job, during, "after the link was restored");
    let status = farm.wait_done(job, STALL);
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

/// The coordinator is stopped (`SIGSTOP`) for 7 s mid-job, past the 5 s heartbeat
/// timeout, then continued: it drops no worker (no "dropping the worker" in its log,
/// the same connections before and after), and the job ends `done` with
/// `tessera render`'s image.
#[test]
fn a_coordinator_paused_past_the_heartbeat_timeout_drops_no_worker() {
    let _serial = common::serial();
    let mut farm = Farm::with_workers(&["w1", "w2"]);
    let lights = common::scene_path("lights.json");
    let job = farm.submit(&lights, JOB);
    let total = tiles_total(&farm.status(job));
    farm.wait_for_tiles(job, total / 6);
    let mut before: Vec<(String, u64)> = farm
        .wait_for_workers(&["w1", "w2"])
        .iter()
        .map(|w| {
            (
                w["name"].as_str().unwrap().to_owned(),
                w["id"].as_u64().unwrap(),
            )
        })
        .collect();
    before.sort();

    farm.coordinator.signal("STOP");
    thread::sleep(Duration::from_secs(7));
    farm.coordinator.signal("CONT");
    let continued = Instant::now();
    let at_cont = tiles_done(&farm.status(job));

    // Whatever happens next, the pause must not have dropped anyone.
    let mut findings = Findings::default();
    let dropped: Vec<String> = farm
        .coordinator_logs()
        .lines()
        .filter(|l| l.contains("dropping the worker"))
        .map(str::to_owned)
        .collect();
    findings.check(dropped.is_empty(), || {
        format!(
            "the coordinator dropped workers after a 7 s pause:\n{}",
            dropped.join("\n")
        )
    });
    let resumed = wait_progress(&farm, job, at_cont, "after SIGCONT");
    let mut after: Vec<(String, u64)> = farm
        .try_workers()
        .unwrap_or_default()
        .iter()
        .map(|w| {
            (
                w["name"].as_str().unwrap().to_owned(),
                w["id"].as_u64().unwrap(),
            )
        })
        .collect();
    after.sort();
    findings.check(after == before, || {
        format!(
            "the workers' connections changed across the pause: {before:?} before, {after:?} after"
        )
    });
    let status = farm.wait_done(job, STALL);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    eprintln!(
        "coordinator paused 7 s at {at_cont}/{total} tiles; the job progressed {} ms after \
         SIGCONT; workers dropped: {}",
        (resumed - continued).as_millis(),
        dropped.len()
    );
    farm.assert_job_image(job, &lights, JOB, "the job whose coordinator was paused");
    findings.finish();
}

/// The job id a `submit --wait` started at `started` printed on stderr (`submitted job
/// N`), and how long after its start it was seen; waits up to `timeout` for it.
fn submitted_line(client: &Daemon, started: Instant, timeout: Duration) -> Option<(u64, Duration)> {
    let deadline = Instant::now() + timeout;
    loop {
        let text = client.log_text();
        if let Some(id) = text
            .lines()
            .find_map(|l| l.trim().strip_prefix("submitted job "))
            .and_then(|n| n.parse().ok())
        {
            return Some((id, started.elapsed()));
        }
        if Instant::now() > deadline {
            return None;
        }
        thread::sleep(Duration::from_millis(10));
    }
}

/// A `submit --wait` follows its job while the coordinator is killed and restarted:
/// it printed `submitted job N` on stderr first, says once that it lost the
/// coordinator and is reconnecting, and exits 0 with `tessera render`'s image.
#[test]
fn submit_wait_prints_its_job_and_rides_through_a_coordinator_restart() {
    let _serial = common::serial();
    let mut farm = Farm::with_workers(&["w1", "w2"]);
    let lights = common::scene_path("lights.json");
    let out = farm.dir().join("waited.png");
    let mut args = vec!["submit", lights.as_str()];
    args.extend(JOB);
    args.extend([
        "--wait",
        "-o",
        out.to_str().expect("UTF-8 path"),
        "--coordinator",
        &farm.addr,
    ]);
    let spawned = Instant::now();
    let mut client = common::spawn_tessera(farm.dir(), &args, "submit-wait.log");
    let mut findings = Findings::default();

    // The job, as the coordinator lists it; the client must have printed its line by
    // then, or very soon after.
    let listed = common::poll("the job to be listed", Duration::from_secs(10), || {
        let run = common::client(farm.dir(), &farm.addr, &["list", "--json"]);
        let jobs: Value = serde_json::from_str(run.stdout.trim()).ok()?;
        jobs.as_array()?.first()?["id"].as_u64()
    });
    let printed = submitted_line(&client, spawned, Duration::from_secs(2));
    findings.check(printed.is_some(), || {
        format!(
            "submit --wait printed no `submitted job N` line within 2 s of the job being \
             listed; its stderr: {:?}",
            client.log_text()
        )
    });
    let job = listed;
    if let Some((id, after)) = printed {
        findings.check(id == listed, || {
            format!("submit --wait printed `submitted job {id}`, but the job is {listed}")
        });
        let first = client.log_text().lines().next().unwrap_or("").to_owned();
        findings.check(first == format!("submitted job {id}"), || {
            format!("`submitted job {id}` is not the first line on stderr: {first:?}")
        });
        eprintln!(
            "submit --wait printed `submitted job {id}` {} ms after it started",
            after.as_millis()
        );
    }
    let total = tiles_total(&farm.wait_for_tiles(job, 1));
    farm.wait_for_tiles(job, total / 5);

    farm.coordinator.kill9();
    thread::sleep(Duration::from_millis(1500));
    if !client.is_running() {
        let exit = client.wait_exit(Duration::ZERO);
        panic!(
            "submit --wait exited ({exit:?}) when the coordinator went away; its stderr: {:?}",
            client.log_text()
        );
    }
    farm.restart_coordinator();
    let restarted = Instant::now();

    let exit = client
        .wait_exit(JOB_TIMEOUT)
        .unwrap_or_else(|| panic!("submit --wait still runs {JOB_TIMEOUT:?} after the restart"));
    let stderr = client.log_text();
    assert!(
        exit.success(),
        "submit --wait exited with {exit} across a coordinator restart; its stderr: {stderr:?}"
    );
    let lost: Vec<&str> = stderr
        .lines()
        .filter(|l| l.starts_with("lost the coordinator (") && l.ends_with("): reconnecting"))
        .collect();
    findings.check(lost.len() == 1, || {
        format!("submit --wait should say once `lost the coordinator (REASON): reconnecting`; its stderr: {stderr:?}")
    });
    eprintln!(
        "submit --wait exited 0 {:.1} s after the coordinator's restart",
        restarted.elapsed().as_secs_f64()
    );
    let status = farm.status(job);
    assert_eq!(status["state"], "done", "{status}");
    let reference =
        common::render_reference(farm.dir(), &lights, "reference.png", &render_args(JOB));
    common::assert_same_png(&out, &reference, "the image written by submit --wait");
    findings.finish();
}

/// The largest growth of the coordinator's resident set allowed from its 4th to its
/// 15th job: a few frames' worth of allocator slack, far less than the 11 finished
/// images (about 0.5 MB each) it would hold if it kept them.
const RSS_GROWTH_LIMIT_KIB: u64 = 4 * 1024;
/// The largest `tessera.db` allowed once 15 jobs have ended: their rows, not their
/// tiles (a 1080p job's tile blobs take 6 MB).
const DB_LIMIT_BYTES: u64 = 2 * 1024 * 1024;

fn file_size(path: &Path) -> u64 {
    std::fs::metadata(path).map_or(0, |m| m.len())
}

/// 15 sequential 1080p jobs: the coordinator's resident set after the 15th is about
/// that after the 4th (it keeps no finished image in memory), and `tessera.db` gives
/// the tile blobs' space back. Every job ends `done` with `tessera render`'s image.
#[test]
fn memory_and_disk_stay_bounded_over_15_sequential_1080p_jobs() {
    let _serial = common::serial();
    let farm = Farm::with_workers(&["w1", "w2"]);
    let seed = common::scene_path("seed.json");
    let reference = common::render_reference(farm.dir(), &seed, "reference.png", FRAME_1080P);
    let pid = farm.coordinator.pid();
    let mut rss = Vec::new();
    for n in 1..=15 {
        let job = farm.submit(&seed, FRAME_1080P);
        farm.wait_done(job, STALL);
        farm.assert_job_image_is(job, &reference, &format!("1080p job {n}"));
        thread::sleep(Duration::from_millis(200));
        let kib = common::rss_kib(pid).expect("the coordinator's RSS");
        rss.push(kib);
    }
    let (after_4, after_15) = (rss[3], rss[14]);
    let db = farm.data().join("tessera.db");
    let wal = farm.data().join("tessera.db-wal");
    // The space of the last job's tiles is given back shortly after it ends.
    let deadline = Instant::now() + Duration::from_secs(5);
    while file_size(&db) > DB_LIMIT_BYTES && Instant::now() < deadline {
        thread::sleep(Duration::from_millis(100));
    }
    let (db_bytes, wal_bytes) = (file_size(&db), file_size(&wal));
    eprintln!(
        "coordinator RSS after 4 jobs: {:.1} MiB, after 15: {:.1} MiB ({:+.1} MiB, {:+.0} KiB \
         a job); per job: {:?} MiB; tessera.db {:.2} MiB, WAL {:.2} MiB",
        after_4 as f64 / 1024.0,
        after_15 as f64 / 1024.0,
        (after_15 as f64 - after_4 as f64) / 1024.0,
        (after_15 as f64 - after_4 as f64) / 11.0,
        rss.iter()
            .map(|k| (*k as f64 / 102.4).round() / 10.0)
            .collect::<Vec<_>>(),
        db_bytes as f64 / 1048576.0,
        wal_bytes as f64 / 1048576.0
    );
    let mut findings = Findings::default();
    findings.check(after_15 <= after_4 + RSS_GROWTH_LIMIT_KIB, || {
        format!(
            "the coordinator's RSS grew by {} KiB from job 4 to job 15 (limit {} KiB)",
            after_15.saturating_sub(after_4),
            RSS_GROWTH_LIMIT_KIB
        )
    });
    findings.check(db_bytes <= DB_LIMIT_BYTES, || {
        format!("tessera.db holds {db_bytes} bytes after 15 ended jobs (limit {DB_LIMIT_BYTES})")
    });
    findings.finish();
}

/// A job whose coordinator is killed late in the job (7/8 of its tiles done) and restarted: right after the
/// restart it reports `running` (tiles are done), its `elapsed_ms` counts from the
/// original submission, and once done its `job.json` gives the rays per second of the
/// rendering time actually spent (not of the time since the restart).
#[test]
fn a_restored_job_reports_its_true_state_time_and_speed() {
    let _serial = common::serial();
    let mut farm = Farm::with_workers(&["w1"]);
    let lights = common::scene_path("lights.json");
    let submitted = Instant::now();
    let job = farm.submit(&lights, JOB);
    let total = tiles_total(&farm.status(job));
    farm.wait_for_tiles(job, total * 7 / 8);

    farm.coordinator.kill9();
    let killed = Instant::now();
    thread::sleep(Duration::from_secs(2));
    farm.restart_coordinator();
    let status = farm.status(job);
    let since_submission = submitted.elapsed();
    let mut findings = Findings::default();
    let done_then = tiles_done(&status);
    let state_then = status["state"].clone();
    findings.check(
        done_then == 0 || done_then == total || status["state"] == "running",
        || {
            format!(
                "a restored job with {done_then}/{total} tiles done reports {}",
                status["state"]
            )
        },
    );
    let elapsed = Duration::from_millis(status["elapsed_ms"].as_u64().expect("elapsed_ms"));
    findings.check(
        elapsed + Duration::from_millis(500) >= since_submission
            && elapsed <= since_submission + Duration::from_secs(1),
        || {
            format!(
                "right after the restart the job reports elapsed_ms {} but was submitted {} \
                 ms ago",
                elapsed.as_millis(),
                since_submission.as_millis()
            )
        },
    );
    let rejoined = farm.wait_for_workers(&["w1"]);
    let rejoined_at = Instant::now();
    drop(rejoined);
    let status = farm.wait_done(job, STALL);
    let done_at = Instant::now();
    let wall = done_at - submitted;
    let final_elapsed = status["elapsed_ms"].as_u64().expect("elapsed_ms");
    findings.check(
        Duration::from_millis(final_elapsed) + Duration::from_millis(500) >= wall,
        || {
            format!(
                "the done job reports elapsed_ms {final_elapsed}, but it took {} ms from \
                 its submission",
                wall.as_millis()
            )
        },
    );

    let meta_path = farm
        .data()
        .join("jobs")
        .join(job.to_string())
        .join("job.json");
    let meta: Value = serde_json::from_slice(
        &std::fs::read(&meta_path).unwrap_or_else(|e| panic!("{}: {e}", meta_path.display())),
    )
    .expect("job.json is JSON");
    let rays = meta["rays"].as_f64().expect("rays in job.json");
    let rate = meta["rays_per_second"].as_f64().expect("rays_per_second");
    let implied = Duration::from_secs_f64(rays / rate.max(1e-9));
    // Rendering went on from the submission to the kill and from the worker's return
    // to the end; the coordinator was down in between.
    let rendering = (killed - submitted) + done_at.saturating_duration_since(rejoined_at);
    let lower = rendering
        .mul_f64(0.85)
        .saturating_sub(Duration::from_millis(300));
    // ...and the coordinator's downtime is not rendering time.
    let upper = rendering.mul_f64(1.15) + Duration::from_millis(500);
    eprintln!(
        "restored job: {done_then}/{total} tiles at the restart, state {} then; elapsed_ms {} \
         at the restart ({} ms since the submission) and {final_elapsed} when done ({} ms \
         wall); job.json: {rays} rays at {:.1} M rays/s, i.e. {:.2} s of rendering (the test \
         saw {:.2} s of rendering, {:.2} s wall), wall_time_ms {}",
        state_then,
        elapsed.as_millis(),
        since_submission.as_millis(),
        wall.as_millis(),
        rate / 1e6,
        implied.as_secs_f64(),
        rendering.as_secs_f64(),
        wall.as_secs_f64(),
        meta["wall_time_ms"]
    );
    findings.check(implied >= lower && implied <= upper, || {
        format!(
            "job.json's rays_per_second {rate:.0} implies {:.2} s of rendering, but the job \
             rendered for about {:.2} s ({:.2} s wall)",
            implied.as_secs_f64(),
            rendering.as_secs_f64(),
            wall.as_secs_f64()
        )
    });
    farm.assert_job_image(job, &lights, JOB, "the restored job");
    findings.finish();
}
