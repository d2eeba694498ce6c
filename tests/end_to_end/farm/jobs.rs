//! Jobs on a farm started by hand: the real `tessera` binary as coordinator, workers and
//! clients, on 127.0.0.1 only.
//!
//! What is proven:
//!
//! - **Determinism.** The image a farm produces (through `submit --wait`, through
//!   `fetch`) is byte for byte the PNG `tessera render` writes for the same scene and
//!   size: several tile sizes, several jobs at once, a worker joining mid-job, a client
//!   vanishing mid-job.
//! - **Cancellation** frees the workers: no tile in flight, no tile done and no CPU
//!   burnt for the cancelled job, and the farm still serves the next job.
//! - **Handshake.** A peer with the wrong protocol version or magic gets a `Refused`
//!   that says why, and the connection is closed; the coordinator keeps serving.
//! - **Errors** are one `error: ` line: an invalid scene is reported by `submit`
//!   exactly as by `render`, an unknown job by `status`, an unreachable coordinator by
//!   every client command with the address tried.
//!
//! Every wait has a deadline and every process a test starts is killed and reaped by a
//! guard, also when an assertion fails (the daemons' logs are then printed).

use std::io::Read;
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use serde_json::Value;
use tempfile::TempDir;

use crate::support::wire::{read_frame, send_frame};
use crate::support::{
    assert_same_png, client, cpu_ticks, fetch, ok, one_error_line, path_str, poll,
    render_reference, scene_path, shared, start_coordinator_in, start_worker, status_json, submit,
    tessera, wait_for_workers, workers_json, Daemon, Run, BIN,
};

/// Longest any single client command may take (they are all small).
const CLIENT_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest a job of these tests may take to finish on the farm.
const JOB_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest a worker may take to register.
const STARTUP_TIMEOUT: Duration = Duration::from_secs(10);

/// A small frame that still has many tiles, and partial tiles at the right and bottom
/// edges for most tile sizes.
const SMALL: &[&str] = &["--width", "200", "--height", "150"];

/// A coordinator and its workers on loopback, with a fresh data directory; dropping it
/// kills them all.
struct Farm {
    /// The coordinator's address, `127.0.0.1:PORT`.
    addr: String,
    /// Held to be killed with the farm.
    _coordinator: Daemon,
    /// The workers in start order.
    workers: Vec<Daemon>,
    /// Data, logs and the tests' files; declared last so it outlives the processes.
    dir: TempDir,
}

impl Farm {
    /// A coordinator on a free port and `workers` workers of one thread each, all
    /// registered before this returns.
    fn start(workers: usize) -> Farm {
        let dir = TempDir::new().expect("cannot create a temporary directory");
        let (coordinator, addr) = start_coordinator_in(dir.path());
        let mut farm = Farm {
            addr,
            _coordinator: coordinator,
            workers: Vec::new(),
            dir,
        };
        for i in 1..=workers {
            farm.add_worker(&format!("w{i}"));
        }
        farm.wait_for_workers(workers);
        farm
    }

    fn dir(&self) -> &Path {
        self.dir.path()
    }

    /// Starts `tessera worker --threads 1 --name NAME` (without waiting for it).
    fn add_worker(&mut self, name: &str) {
        let worker = start_worker(self.dir(), &self.addr, name);
        self.workers.push(worker);
    }

    fn wait_for_workers(&self, n: usize) {
        wait_for_workers(self.dir(), &self.addr, n, STARTUP_TIMEOUT);
    }

    fn worker_pids(&self) -> Vec<u32> {
        self.workers.iter().map(Daemon::pid).collect()
    }

    /// `tessera ARGS --coordinator ADDR`.
    fn run(&self, args: &[&str]) -> Run {
        client(self.dir(), &self.addr, args)
    }

    /// Like [`Farm::run`], and it must succeed.
    fn run_ok(&self, args: &[&str]) -> Run {
        ok(self.run(args), &format!("tessera {}", args.join(" ")))
    }

    /// `submit ARGS` without `--wait`: the job id printed alone on stdout.
    fn submit(&self, args: &[&str]) -> u64 {
        submit(self.dir(), &self.addr, args)
    }

    /// `submit SCENE --wait --tile TILE SMALL` must write `tessera render`'s image.
    fn assert_submit_wait_matches_render(&self, name: &str, tile: &str) {
        let scene = scene_path(name);
        let reference = render_reference(self.dir(), &scene, &format!("ref-{name}.png"), SMALL);
        let out = self.dir().join(format!("farm-{name}-{tile}.png"));
        let submit = [
            "submit",
            &scene,
            "--wait",
            "-o",
            path_str(&out),
            "--tile",
            tile,
        ];
        self.run_ok(&[&submit[..], SMALL].concat());
        let what = format!("submit --wait {name} --tile {tile}");
        assert_same_png(&out, &reference, &what);
    }

    fn status(&self, job: u64) -> Value {
        status_json(self.dir(), &self.addr, job)
    }

    fn workers(&self) -> Vec<Value> {
        workers_json(self.dir(), &self.addr, &[])
    }

    /// Polls `status` until the job is in `state`; panics if it ends in another one.
    fn wait_for_state(&self, job: u64, state: &str) -> Value {
        poll(&format!("job {job} to be {state}"), JOB_TIMEOUT, || {
            let status = self.status(job);
            let now = status["state"].as_str().expect("state is a string");
            if now == state {
                return Some(status);
            }
            assert!(
                !matches!(now, "done" | "failed" | "cancelled"),
                "job {job} ended {now}, not {state}: {status}"
            );
            None
        })
    }

    /// `fetch JOB -o DIR/NAME`.
    fn fetch(&self, job: u64, name: &str) -> PathBuf {
        fetch(self.dir(), &self.addr, job, name)
    }
}

fn parse_json(run: &Run, what: &str) -> Value {
    serde_json::from_str(run.stdout.trim())
        .unwrap_or_else(|e| panic!("{what}: stdout is not JSON ({e}): {:?}", run.stdout))
}

/// A coordinator and two workers started by hand: `submit --wait` writes
/// `tessera render`'s image.
#[test]
fn submit_wait_on_a_hand_started_farm_gives_renders_image() {
    let _turn = shared();
    let farm = Farm::start(2);
    for (name, tile) in [("reflections.json", "16"), ("seed.json", "32")] {
        farm.assert_submit_wait_matches_render(name, tile);
    }
}

/// Three jobs submitted at the same time all complete, each with its own image.
#[test]
fn three_jobs_submitted_at_once_all_complete_with_renders_images() {
    let _turn = shared();
    let farm = Farm::start(2);
    let jobs: [(&str, &[&str]); 3] = [
        (
            "seed.json",
            &["--width", "200", "--height", "150", "--tile", "16"],
        ),
        (
            "reflections.json",
            &["--width", "240", "--height", "90", "--tile", "24"],
        ),
        (
            "tilted.json",
            &[
                "--width", "120", "--height", "200", "--aa", "1", "--tile", "32",
            ],
        ),
    ];
    let ids: Vec<u64> = thread::scope(|s| {
        let handles: Vec<_> = jobs
            .iter()
            .map(|(name, args)| {
                let farm = &farm;
                s.spawn(move || farm.submit(&[&[scene_path(name).as_str()][..], args].concat()))
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let mut distinct = ids.clone();
    distinct.sort_unstable();
    distinct.dedup();
    assert_eq!(distinct.len(), 3, "three distinct job ids: {ids:?}");
    for (&job, (name, args)) in ids.iter().zip(jobs) {
        let status = farm.wait_for_state(job, "done");
        assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
        let size: Vec<&str> = args[..args.len() - 2].to_vec();
        let reference = render_reference(
            farm.dir(),
            &scene_path(name),
            &format!("ref-{job}.png"),
            &size,
        );
        let out = farm.fetch(job, &format!("job-{job}.png"));
        assert_same_png(&out, &reference, &format!("job {job} ({name})"));
    }
}

/// A cancelled job releases its workers at once: nothing in flight, no more tiles
/// done, no more CPU burnt; and the farm renders the next job correctly.
#[test]
fn a_cancelled_job_stops_using_the_workers() {
    let _turn = shared();
    let farm = Farm::start(2);
    let big = scene_path("hall-of-mirrors.json");
    let job = farm.submit(&[&big, "--width", "1600", "--height", "1600", "--aa", "4"]);
    let status = poll("the big job to start", JOB_TIMEOUT, || {
        let status = farm.status(job);
        (status["tiles_done"].as_u64() > Some(0)).then_some(status)
    });
    assert_eq!(status["state"], "running", "{status}");
    farm.run_ok(&["cancel", &job.to_string()]);
    let status = farm.status(job);
    assert_eq!(status["state"], "cancelled", "{status}");
    assert_ne!(status["tiles_done"], status["tiles_total"], "{status}");

    let idle =
        |workers: &[Value]| workers.len() == 2 && workers.iter().all(|w| w["tiles_in_flight"] == 0);
    poll(
        "every worker to have no tile in flight",
        Duration::from_secs(2),
        || idle(&farm.workers()).then_some(()),
    );
    // A tile already being rendered may still finish; it must not count.
    thread::sleep(Duration::from_millis(300));
    let done = |workers: Vec<Value>| -> Vec<(Value, Value)> {
        workers
            .into_iter()
            .map(|w| (w["name"].clone(), w["tiles_done"].clone()))
            .collect()
    };
    let before = done(farm.workers());
    let ticks_before: Vec<u64> = farm.worker_pids().into_iter().map(cpu_ticks).collect();
    thread::sleep(Duration::from_secs(1));
    let ticks_after: Vec<u64> = farm.worker_pids().into_iter().map(cpu_ticks).collect();
    let workers = farm.workers();
    assert!(idle(&workers), "still busy: {workers:?}");
    assert_eq!(done(workers), before, "tiles_done still increases");
    for (b, a) in ticks_before.iter().zip(&ticks_after) {
        assert!(
            a - b <= 20,
            "a worker used {} ms of CPU in the second after the cancel settled",
            (a - b) * 10
        );
    }
    assert_eq!(farm.status(job)["state"], "cancelled");

    // The farm still works.
    farm.assert_submit_wait_matches_render("seed.json", "16");
}

/// A worker that connects while a job runs is given some of its tiles.
#[test]
fn a_worker_joining_mid_job_receives_tiles() {
    let _turn = shared();
    let mut farm = Farm::start(0);
    farm.add_worker("early");
    farm.wait_for_workers(1);
    let lights = scene_path("lights.json");
    // About 2 s for one thread: long enough for the late worker to join.
    let size = ["--width", "1200", "--height", "900", "--aa", "4"];
    let job = farm.submit(&[&[lights.as_str(), "--tile", "32"][..], &size].concat());
    let status = poll("the first tiles", JOB_TIMEOUT, || {
        let status = farm.status(job);
        (status["tiles_done"].as_u64() > Some(0)).then_some(status)
    });
    assert_ne!(
        status["state"], "done",
        "the job ended before the late worker could join: {status}"
    );
    farm.add_worker("late");
    farm.wait_for_state(job, "done");
    let workers = farm.workers();
    let late = workers
        .iter()
        .find(|w| w["name"] == "late")
        .unwrap_or_else(|| panic!("no worker named late: {workers:?}"));
    assert!(
        late["tiles_done"].as_u64() > Some(0),
        "the late worker rendered nothing: {workers:?}"
    );
    let reference = render_reference(farm.dir(), &lights, "ref.png", &size);
    let out = farm.fetch(job, "out.png");
    assert_same_png(&out, &reference, "the job finished by two workers");
}

/// Killing the client of `submit --wait` does not affect its job.
#[test]
fn a_client_that_disconnects_does_not_disturb_its_job() {
    let _turn = shared();
    let farm = Farm::start(2);
    let lights = scene_path("lights.json");
    // About 1 s on two workers: the client goes long before the job ends.
    let size = ["--width", "1200", "--height", "900", "--aa", "4"];
    let started = Instant::now();
    let client = Command::new(BIN)
        .args([
            "submit",
            &lights,
            "--wait",
            "--tile",
            "32",
            "--coordinator",
            &farm.addr,
        ])
        .args(size)
        .arg("-o")
        .arg(farm.dir().join("never.png"))
        .current_dir(farm.dir())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("cannot start the client");
    let mut client = Daemon {
        name: "client".into(),
        child: client,
        log: None,
    };
    let job = poll("the job to be submitted", JOB_TIMEOUT, || {
        let run = farm.run_ok(&["list", "--json"]);
        parse_json(&run, "list --json")[0]["id"].as_u64()
    });
    thread::sleep(Duration::from_millis(200).saturating_sub(started.elapsed()));
    client.child.kill().expect("cannot kill the client");
    client.child.wait().expect("cannot reap the client");
    let status = farm.status(job);
    assert!(
        matches!(status["state"].as_str(), Some("queued" | "running")),
        "the job should still run when its client goes: {status}"
    );
    farm.wait_for_state(job, "done");
    let reference = render_reference(farm.dir(), &lights, "ref.png", &size);
    let out = farm.fetch(job, "out.png");
    assert_same_png(&out, &reference, "the job whose client was killed");
}

/// Sends `hello` as the first frame and returns the refusal's reason, after checking
/// that the coordinator closes the connection.
fn refused_reason(addr: &str, hello: &[u8]) -> String {
    let mut stream = TcpStream::connect(addr).expect("cannot connect to the coordinator");
    stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .expect("cannot set a timeout");
    send_frame(&mut stream, hello);
    let reply = read_frame(&mut stream, "the answer to a foreign hello");
    let reason = match protocol::wire::decode::<protocol::Welcome>(&reply) {
        Ok(protocol::Welcome::Refused { reason }) => reason,
        other => panic!("expected Refused, got {other:?}"),
    };
    let mut rest = [0; 16];
    match stream.read(&mut rest) {
        Ok(0) => {}
        Ok(n) => panic!("{n} more bytes after the refusal instead of a close"),
        Err(e) => panic!("the connection was not closed after the refusal: {e}"),
    }
    reason
}

/// A peer of another protocol version, or no Tessera peer at all, is refused with a
/// reason and disconnected; the coordinator goes on serving.
#[test]
fn a_wrong_version_or_magic_is_refused_and_the_coordinator_still_serves() {
    let _turn = shared();
    let farm = Farm::start(1);
    // Magic, version 99, then a role (Client is variant 0, a u32).
    let mut hello = b"TSRA".to_vec();
    hello.extend(99u16.to_le_bytes());
    hello.extend(0u32.to_le_bytes());
    let reason = refused_reason(&farm.addr, &hello);
    let words: Vec<&str> = reason.split(|c: char| !c.is_ascii_alphanumeric()).collect();
    let ours = protocol::PROTOCOL_VERSION.to_string();
    assert!(
        words.contains(&ours.as_str()) && words.contains(&"99"),
        "the reason names both versions: {reason:?}"
    );

    let mut hello = b"TSRB".to_vec();
    hello.extend(1u16.to_le_bytes());
    hello.extend(0u32.to_le_bytes());
    let reason = refused_reason(&farm.addr, &hello);
    assert!(
        reason.contains("TSRA"),
        "the reason names the magic: {reason:?}"
    );

    farm.assert_submit_wait_matches_render("seed.json", "32");
}

/// Client errors are one line: an invalid scene exactly as `render` says it, an
/// unknown job, an unreachable coordinator with its address.
#[test]
fn client_errors_are_one_clear_line() {
    let _turn = shared();
    let farm = Farm::start(0);
    let bad = farm.dir().join("bad.json");
    std::fs::write(
        &bad,
        r#"{"lights": [], "objects": [{"type": "sphere", "center": "0 0 0", "radius": -1, "color": "1 1 1 0"}]}"#,
    )
    .expect("cannot write the scene");
    let bad = path_str(&bad);
    let expected = format!("error: {bad}: objects[0].radius: must be > 0, got -1");
    let submitted = one_error_line(&farm.run(&["submit", bad]), "submit of an invalid scene");
    assert_eq!(submitted, expected);
    let render = tessera(
        farm.dir(),
        &["render", bad, "-o", "bad.png"],
        CLIENT_TIMEOUT,
    );
    assert_eq!(
        one_error_line(&render, "render of an invalid scene"),
        submitted
    );
    let jobs = parse_json(&farm.run_ok(&["list", "--json"]), "list --json");
    assert_eq!(jobs, Value::Array(vec![]), "the invalid scene left no job");

    let unknown = one_error_line(&farm.run(&["status", "12345"]), "status of an unknown job");
    assert!(unknown.contains("12345"), "{unknown}");

    let nowhere = "127.0.0.1:1";
    let seed = scene_path("seed.json");
    let commands: [&[&str]; 6] = [
        &["submit", &seed],
        &["status", "1"],
        &["list"],
        &["cancel", "1"],
        &["fetch", "1", "-o", "x.png"],
        &["workers"],
    ];
    for command in commands {
        let run = client(farm.dir(), nowhere, command);
        let line = one_error_line(
            &run,
            &format!("{} --coordinator {nowhere}", command.join(" ")),
        );
        assert!(line.contains(nowhere), "names the address tried: {line}");
    }
}
