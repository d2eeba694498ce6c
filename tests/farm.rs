//! End-to-end tests of the farm: the real `tessera` binary as coordinator, workers and
//! clients, on 127.0.0.1 only.
//!
//! What is proven:
//!
//! - **Determinism.** The image a farm produces (through `tessera up`, through
//!   `submit --wait`, through `fetch`) is byte for byte the PNG `tessera render` writes
//!   for the same scene and size: every committed scene, 1 to 3 workers, several tile
//!   sizes, several jobs at once, a worker joining mid-job, a client vanishing mid-job.
//! - **Cancellation** frees the workers: no tile in flight, no tile done and no CPU
//!   burnt for the cancelled job, and the farm still serves the next job.
//! - **Handshake.** A peer with the wrong protocol version or magic gets a `Refused`
//!   that says why, and the connection is closed; the coordinator keeps serving.
//! - **Errors** are one `error: ` line: an invalid scene is reported by `submit`
//!   exactly as by `render`, an unknown job by `status`, an unreachable coordinator by
//!   every client command with the address tried.
//! - **`tessera up` leaves nothing behind**, whether it ends normally or is killed.
//!
//! Every wait has a deadline and every process a test starts is killed and reaped by a
//! guard, also when an assertion fails (the daemons' logs are then printed).

mod common;

use std::fs::File;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use common::{first_line, ok, poll, Run, POLL};
use serde_json::Value;
use tempfile::TempDir;

const BIN: &str = env!("CARGO_BIN_EXE_tessera");

/// Longest any single client command may take (they are all small).
const CLIENT_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest a job of these tests may take to finish on the farm.
const JOB_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest a daemon may take to start (print its address, or register as a worker).
const STARTUP_TIMEOUT: Duration = Duration::from_secs(10);

/// A small frame that still has many tiles, and partial tiles at the right and bottom
/// edges for most tile sizes.
const SMALL: &[&str] = &["--width", "200", "--height", "150"];

// ---------------------------------------------------------------------------------
// Helpers: paths, runs, images.
// ---------------------------------------------------------------------------------

/// `scenes/NAME` in the checkout, as an argument.
fn scene(name: &str) -> String {
    path_arg(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("scenes")
            .join(name),
    )
}

/// Every `scenes/*.json`, sorted.
fn all_scenes() -> Vec<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes");
    let mut scenes: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("cannot list scenes/")
        .map(|e| e.expect("cannot read scenes/").path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    scenes.sort();
    scenes
}

fn path_arg(path: &Path) -> String {
    path.to_str().expect("test paths are UTF-8").to_owned()
}

/// `args` followed by `more`, as owned strings.
fn cat<A: AsRef<str>, B: AsRef<str>>(args: &[A], more: &[B]) -> Vec<String> {
    let args = args.iter().map(AsRef::as_ref);
    args.chain(more.iter().map(AsRef::as_ref))
        .map(str::to_owned)
        .collect()
}

/// `tessera render SCENE -o DIR/NAME ARGS...`: the reference image.
fn render_reference(dir: &Path, scene: &str, name: &str, args: &[&str]) -> PathBuf {
    let out = dir.join(name);
    let cmd = cat(&["render", scene, "-o", &path_arg(&out)], args);
    ok(
        common::tessera(dir, &cmd, CLIENT_TIMEOUT),
        &format!("tessera {}", cmd.join(" ")),
    );
    out
}

/// The farm's image equals the reference: same pixels and same file bytes.
fn assert_same_image(actual: &Path, reference: &Path, what: &str) {
    let a_bytes = std::fs::read(actual).unwrap_or_else(|e| panic!("{what}: no image: {e}"));
    let r_bytes = std::fs::read(reference).expect("cannot read the reference image");
    let a = image::load_from_memory(&a_bytes)
        .unwrap_or_else(|e| panic!("{what}: not a PNG: {e}"))
        .to_rgb8();
    let r = image::load_from_memory(&r_bytes)
        .expect("the reference is a PNG")
        .to_rgb8();
    assert_eq!(a.dimensions(), r.dimensions(), "{what}: image size");
    if a.as_raw() != r.as_raw() {
        let differing = a.pixels().zip(r.pixels()).filter(|(p, q)| p != q).count();
        let (x, y, _) = a
            .enumerate_pixels()
            .find(|&(x, y, p)| p != r.get_pixel(x, y))
            .expect("some pixel differs");
        panic!(
            "{what}: {differing} of {} pixels differ from `tessera render`'s, the first at \
             ({x}, {y})",
            a.width() * a.height()
        );
    }
    assert!(
        a_bytes == r_bytes,
        "{what}: same pixels but the PNG files differ ({} vs {} bytes)",
        a_bytes.len(),
        r_bytes.len()
    );
}

fn parse_json(run: &Run, what: &str) -> Value {
    serde_json::from_str(run.stdout.trim())
        .unwrap_or_else(|e| panic!("{what}: stdout is not JSON ({e}): {:?}", run.stdout))
}

/// The single line of an error run's stderr, after checking it failed and printed
/// exactly one line and nothing on stdout.
fn one_error_line(run: &Run, what: &str) -> String {
    assert!(!run.status.success(), "{what} succeeded: {}", run.stdout);
    assert_eq!(run.stdout, "", "{what}: nothing on stdout");
    let lines: Vec<&str> = run.stderr.lines().collect();
    assert_eq!(
        lines.len(),
        1,
        "{what}: one line on stderr: {:?}",
        run.stderr
    );
    assert!(
        lines[0].starts_with("error: "),
        "{what}: the line starts with `error: `: {:?}",
        lines[0]
    );
    lines[0].to_owned()
}

// ---------------------------------------------------------------------------------
// Helpers: processes.
// ---------------------------------------------------------------------------------

/// A child process killed (SIGKILL) and reaped when dropped.
struct Guarded {
    name: String,
    child: Child,
    log: Option<PathBuf>,
}

impl Guarded {
    fn pid(&self) -> u32 {
        self.child.id()
    }
}

impl Drop for Guarded {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if thread::panicking() {
            if let Some(log) = &self.log {
                let text = std::fs::read_to_string(log).unwrap_or_default();
                let tail: Vec<&str> = text.lines().rev().take(20).collect();
                eprintln!("--- last lines of {}'s log ---", self.name);
                for line in tail.iter().rev() {
                    eprintln!("{line}");
                }
            }
        }
    }
}

/// A coordinator and its workers on loopback, with a fresh data directory; dropping it
/// kills them all (workers first).
struct Farm {
    /// The coordinator's address, `127.0.0.1:PORT`.
    addr: String,
    /// Coordinator first, then the workers in start order.
    procs: Vec<Guarded>,
    /// Data, logs and the tests' files; declared last so it outlives the processes.
    dir: TempDir,
}

impl Farm {
    /// A coordinator on a free port and `workers` workers of one thread each, all
    /// registered before this returns.
    fn start(workers: usize) -> Farm {
        let dir = TempDir::new().expect("cannot create a temporary directory");
        let log = dir.path().join("coordinator.log");
        let mut child = Command::new(BIN)
            .args(["coordinator", "--listen", "127.0.0.1:0", "--data"])
            .arg(dir.path().join("data"))
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(File::create(&log).expect("cannot create the log"))
            .spawn()
            .expect("cannot start the coordinator");
        let stdout = child.stdout.take().expect("stdout is piped");
        let mut farm = Farm {
            addr: String::new(),
            procs: vec![Guarded {
                name: "coordinator".into(),
                child,
                log: Some(log),
            }],
            dir,
        };
        let line = first_line(stdout, STARTUP_TIMEOUT)
            .expect("the coordinator printed no first line within the time limit");
        let addr = line
            .trim()
            .strip_prefix("listening on ")
            .unwrap_or_else(|| panic!("unexpected first line {line:?}"));
        assert!(addr.starts_with("127.0.0.1:"), "listening on {addr}");
        farm.addr = addr.to_owned();
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
        let log = self.dir().join(format!("worker-{name}.log"));
        let child = Command::new(BIN)
            .args(["worker", "--coordinator", &self.addr, "--threads", "1"])
            .args(["--name", name])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(File::create(&log).expect("cannot create the log"))
            .spawn()
            .expect("cannot start a worker");
        self.procs.push(Guarded {
            name: format!("worker {name}"),
            child,
            log: Some(log),
        });
    }

    fn wait_for_workers(&self, n: usize) {
        poll(&format!("{n} workers to register"), STARTUP_TIMEOUT, || {
            (self.workers().len() == n).then_some(())
        });
    }

    fn worker_pids(&self) -> Vec<u32> {
        self.procs[1..].iter().map(Guarded::pid).collect()
    }

    /// `tessera ARGS --coordinator ADDR`.
    fn run<S: AsRef<str>>(&self, args: &[S]) -> Run {
        let args = cat(args, &["--coordinator", &self.addr]);
        common::tessera(self.dir(), &args, CLIENT_TIMEOUT)
    }

    /// Like [`Farm::run`], and it must succeed.
    fn run_ok<S: AsRef<str>>(&self, args: &[S]) -> Run {
        let words: Vec<&str> = args.iter().map(AsRef::as_ref).collect();
        let what = format!("tessera {}", words.join(" "));
        ok(self.run(args), &what)
    }

    /// `submit ARGS` without `--wait`: the job id printed alone on stdout.
    fn submit<S: AsRef<str>>(&self, args: &[S]) -> u64 {
        let run = self.run_ok(&cat(&["submit"], args));
        parse_job_id(&run.stdout)
    }

    /// `submit SCENE --wait --tile TILE SMALL` must write `tessera render`'s image.
    fn assert_submit_wait_matches_render(&self, name: &str, tile: &str) {
        let scene = scene(name);
        let reference = render_reference(self.dir(), &scene, &format!("ref-{name}.png"), SMALL);
        let out = path_arg(&self.dir().join(format!("farm-{name}-{tile}.png")));
        let args = cat(
            &["submit", &scene, "--wait", "-o", &out, "--tile", tile],
            SMALL,
        );
        self.run_ok(&args);
        let what = format!("submit --wait {name} --tile {tile}");
        assert_same_image(Path::new(&out), &reference, &what);
    }

    fn status(&self, job: u64) -> Value {
        let run = self.run_ok(&["status", &job.to_string(), "--json"]);
        parse_json(&run, "status --json")
    }

    fn workers(&self) -> Vec<Value> {
        let run = self.run_ok(&["workers", "--json"]);
        match parse_json(&run, "workers --json") {
            Value::Array(workers) => workers,
            other => panic!("workers --json is not an array: {other}"),
        }
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
        let out = self.dir().join(name);
        self.run_ok(&["fetch", &job.to_string(), "-o", &path_arg(&out)]);
        out
    }
}

fn parse_job_id(stdout: &str) -> u64 {
    stdout
        .trim()
        .parse()
        .unwrap_or_else(|e| panic!("submit printed {stdout:?}, not a job id: {e}"))
}

/// The fields of `/proc/PID/stat` after the command name (state is index 0, ppid 1,
/// utime 11, stime 12), or `None` if there is no such process.
fn proc_stat(pid: u32) -> Option<Vec<String>> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let rest = &stat[stat.rfind(')')? + 1..];
    Some(rest.split_whitespace().map(str::to_owned).collect())
}

/// The process's arguments, empty if it is gone (or a zombie).
fn proc_cmdline(pid: u32) -> Vec<String> {
    std::fs::read(format!("/proc/{pid}/cmdline"))
        .map(|bytes| {
            bytes
                .split(|&b| b == 0)
                .filter(|a| !a.is_empty())
                .map(|a| String::from_utf8_lossy(a).into_owned())
                .collect()
        })
        .unwrap_or_default()
}

/// Every process id in `/proc`.
fn all_pids() -> Vec<u32> {
    std::fs::read_dir("/proc")
        .expect("cannot list /proc")
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse().ok())
        .collect()
}

/// CPU time used so far, in clock ticks (1/100 s).
fn cpu_ticks(pid: u32) -> u64 {
    let stat = proc_stat(pid).expect("the process is running");
    stat[11].parse::<u64>().expect("utime") + stat[12].parse::<u64>().expect("stime")
}

/// Whether `pid` is a running (not zombie) process whose arguments contain `marker`.
fn running_with(pid: u32, marker: &str) -> bool {
    proc_stat(pid).is_some_and(|s| s[0] != "Z")
        && proc_cmdline(pid).iter().any(|a| a.contains(marker))
}

/// The farm processes `tessera up` (process `up`) has started: its children started
/// with `--exit-on-stdin-eof`.
fn up_children(up: u32) -> Vec<u32> {
    all_pids()
        .into_iter()
        .filter(|&pid| {
            proc_stat(pid).is_some_and(|s| s[1] == up.to_string())
                && proc_cmdline(pid).iter().any(|a| a == "--exit-on-stdin-eof")
        })
        .collect()
}

/// Kills (SIGKILL) the still-running processes among `pids` that carry `marker`:
/// a failed test of `up` must not leave its farm behind either.
struct Reaper {
    pids: Vec<u32>,
    marker: String,
}

impl Drop for Reaper {
    fn drop(&mut self) {
        for &pid in &self.pids {
            if running_with(pid, &self.marker) {
                let _ = Command::new("kill")
                    .args(["-KILL", &pid.to_string()])
                    .status();
            }
        }
    }
}

/// Starts `tessera up ARGS` (output discarded) under a guard.
fn spawn_up(dir: &Path, args: &[&str]) -> Guarded {
    let child = Command::new(BIN)
        .arg("up")
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("cannot start tessera up");
    Guarded {
        name: "up".into(),
        child,
        log: None,
    }
}

/// Waits for `up`'s coordinator and `workers` workers to be running; returns their
/// pids and the coordinator's `--data` path.
fn watch_up_farm(up: u32, workers: usize) -> (Vec<u32>, String) {
    let pids = poll("tessera up's farm processes", STARTUP_TIMEOUT, || {
        let pids = up_children(up);
        (pids.len() == workers + 1).then_some(pids)
    });
    let data = pids
        .iter()
        .find_map(|&pid| {
            let args = proc_cmdline(pid);
            let i = args.iter().position(|a| a == "--data")?;
            args.get(i + 1).cloned()
        })
        .expect("one of up's children is a coordinator with --data");
    assert!(data.contains("tessera-up-"), "up's data path: {data}");
    (pids, data)
}

/// Waits up to 3 s for every process of `pids`, and every process of the machine
/// whose arguments contain `marker`, to be gone.
fn assert_all_gone(pids: &[u32], marker: &str, what: &str) {
    let deadline = Instant::now() + Duration::from_secs(3);
    loop {
        let left: Vec<u32> = pids
            .iter()
            .copied()
            .filter(|&pid| running_with(pid, "--exit-on-stdin-eof"))
            .chain(all_pids().into_iter().filter(|&p| running_with(p, marker)))
            .collect();
        if left.is_empty() {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{what}: processes still running 3 s later: {:?}",
            left.iter()
                .map(|&p| (p, proc_cmdline(p).join(" ")))
                .collect::<Vec<_>>()
        );
        thread::sleep(POLL);
    }
}

// ---------------------------------------------------------------------------------
// Tests.
// ---------------------------------------------------------------------------------

/// Every scene, through `tessera up` with 1, 2 and 3 workers and three tile sizes
/// (16, 32 and 48: full, and partial edge tiles), gives `tessera render`'s PNG.
#[test]
fn up_gives_renders_image_for_every_scene_worker_count_and_tile_size() {
    let dir = TempDir::new().expect("cannot create a temporary directory");
    let scenes = all_scenes();
    assert!(
        scenes.iter().any(|p| p.ends_with("seed.json")),
        "scenes/ holds the example scenes: {scenes:?}"
    );
    for path in scenes {
        let scene = path_arg(&path);
        let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
        let reference = render_reference(dir.path(), &scene, &format!("{stem}.png"), SMALL);
        for workers in ["1", "2", "3"] {
            for tile in ["16", "32", "48"] {
                let out = path_arg(&dir.path().join(format!("{stem}-w{workers}-t{tile}.png")));
                let up = [
                    "up",
                    &scene,
                    "--workers",
                    workers,
                    "--tile",
                    tile,
                    "-o",
                    &out,
                ];
                let args = cat(&up, SMALL);
                let what = format!("tessera {}", args.join(" "));
                ok(common::tessera(dir.path(), &args, JOB_TIMEOUT), &what);
                assert_same_image(Path::new(&out), &reference, &what);
            }
        }
    }
}

/// A coordinator and two workers started by hand: `submit --wait` writes
/// `tessera render`'s image.
#[test]
fn submit_wait_on_a_hand_started_farm_gives_renders_image() {
    let farm = Farm::start(2);
    for (name, tile) in [("reflections.json", "16"), ("seed.json", "32")] {
        farm.assert_submit_wait_matches_render(name, tile);
    }
}

/// Three jobs submitted at the same time all complete, each with its own image.
#[test]
fn three_jobs_submitted_at_once_all_complete_with_renders_images() {
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
                s.spawn(move || farm.submit(&cat(&[scene(name)], args)))
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
        let reference =
            render_reference(farm.dir(), &scene(name), &format!("ref-{job}.png"), &size);
        let out = farm.fetch(job, &format!("job-{job}.png"));
        assert_same_image(&out, &reference, &format!("job {job} ({name})"));
    }
}

/// A cancelled job releases its workers at once: nothing in flight, no more tiles
/// done, no more CPU burnt; and the farm renders the next job correctly.
#[test]
fn a_cancelled_job_stops_using_the_workers() {
    let farm = Farm::start(2);
    let big = scene("hall-of-mirrors.json");
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
    let mut farm = Farm::start(0);
    farm.add_worker("early");
    farm.wait_for_workers(1);
    let lights = scene("lights.json");
    // About 2 s for one thread: long enough for the late worker to join.
    let size = ["--width", "1200", "--height", "900", "--aa", "4"];
    let job = farm.submit(&cat(&[&lights, "--tile", "32"], &size));
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
    assert_same_image(&out, &reference, "the job finished by two workers");
}

/// Killing the client of `submit --wait` does not affect its job.
#[test]
fn a_client_that_disconnects_does_not_disturb_its_job() {
    let farm = Farm::start(2);
    let lights = scene("lights.json");
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
    let mut client = Guarded {
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
    assert_same_image(&out, &reference, "the job whose client was killed");
}

/// Sends one length-prefixed frame.
fn send_frame(stream: &mut TcpStream, body: &[u8]) {
    let len = u32::try_from(body.len()).expect("small frame");
    stream.write_all(&len.to_be_bytes()).expect("cannot send");
    stream.write_all(body).expect("cannot send");
}

/// Reads one length-prefixed frame.
fn read_frame(stream: &mut TcpStream) -> Vec<u8> {
    let mut len = [0; 4];
    stream
        .read_exact(&mut len)
        .expect("no reply frame from the coordinator");
    let len = u32::from_be_bytes(len) as usize;
    assert!(len < 1 << 20, "reply frame of {len} bytes");
    let mut body = vec![0; len];
    stream.read_exact(&mut body).expect("truncated reply frame");
    body
}

/// Sends `hello` as the first frame and returns the refusal's reason, after checking
/// that the coordinator closes the connection.
fn refused_reason(addr: &str, hello: &[u8]) -> String {
    let mut stream = TcpStream::connect(addr).expect("cannot connect to the coordinator");
    stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .expect("cannot set a timeout");
    send_frame(&mut stream, hello);
    let reply = read_frame(&mut stream);
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
    let farm = Farm::start(0);
    let bad = farm.dir().join("bad.json");
    std::fs::write(
        &bad,
        r#"{"lights": [], "objects": [{"type": "sphere", "center": "0 0 0", "radius": -1, "color": "1 1 1 0"}]}"#,
    )
    .expect("cannot write the scene");
    let bad = path_arg(&bad);
    let expected = format!("error: {bad}: objects[0].radius: must be > 0, got -1");
    let submitted = one_error_line(&farm.run(&["submit", &bad]), "submit of an invalid scene");
    assert_eq!(submitted, expected);
    let render = common::tessera(
        farm.dir(),
        &["render", &bad, "-o", "bad.png"],
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
    let seed = scene("seed.json");
    let commands: [&[&str]; 6] = [
        &["submit", &seed],
        &["status", "1"],
        &["list"],
        &["cancel", "1"],
        &["fetch", "1", "-o", "x.png"],
        &["workers"],
    ];
    for command in commands {
        let args = cat(command, &["--coordinator", nowhere]);
        let run = common::tessera(farm.dir(), &args, CLIENT_TIMEOUT);
        let line = one_error_line(&run, &args.join(" "));
        assert!(line.contains(nowhere), "names the address tried: {line}");
    }
}

/// `tessera up` stops its coordinator and workers when it ends, and they stop by
/// themselves when `up` is killed.
#[test]
fn up_leaves_no_process_behind() {
    let dir = TempDir::new().expect("cannot create a temporary directory");
    let out = path_arg(&dir.path().join("out.png"));

    // A normal run (about a second of rendering, to see its farm while it runs).
    let lights = scene("lights.json");
    let mut up = spawn_up(
        dir.path(),
        &[
            &lights,
            "--workers",
            "2",
            "-o",
            &out,
            "--width",
            "1200",
            "--height",
            "900",
            "--aa",
            "4",
        ],
    );
    let (pids, data) = watch_up_farm(up.pid(), 2);
    let _reaper = Reaper {
        pids: pids.clone(),
        marker: "--exit-on-stdin-eof".into(),
    };
    let exit = poll("tessera up to finish", JOB_TIMEOUT, || {
        up.child.try_wait().expect("cannot wait for up")
    });
    assert!(exit.success(), "tessera up failed: {exit}");
    assert_all_gone(&pids, &data, "after tessera up ended");
    let up_dir = Path::new(&data)
        .parent()
        .expect("data is in up's directory");
    assert!(!up_dir.exists(), "up removed {}", up_dir.display());

    // A run killed mid-render.
    let hall = scene("hall-of-mirrors.json");
    let mut up = spawn_up(
        dir.path(),
        &[
            &hall,
            "--workers",
            "2",
            "-o",
            &out,
            "--width",
            "1600",
            "--height",
            "1600",
            "--aa",
            "4",
        ],
    );
    let started = Instant::now();
    let (pids, data) = watch_up_farm(up.pid(), 2);
    let _reaper = Reaper {
        pids: pids.clone(),
        marker: "--exit-on-stdin-eof".into(),
    };
    thread::sleep(Duration::from_millis(300).saturating_sub(started.elapsed()));
    assert!(
        up.child.try_wait().expect("cannot wait for up").is_none(),
        "up ended before it could be killed"
    );
    up.child.kill().expect("cannot kill up");
    up.child.wait().expect("cannot reap up");
    assert_all_gone(&pids, &data, "after tessera up was killed");
    // A killed `up` cannot remove its temporary directory; do it for it.
    let up_dir = Path::new(&data)
        .parent()
        .expect("data is in up's directory");
    if up_dir
        .file_name()
        .is_some_and(|n| n.to_string_lossy().starts_with("tessera-up-"))
    {
        let _ = std::fs::remove_dir_all(up_dir);
    }
}

// ---------------------------------------------------------------------------------
// A farm with tokens.
// ---------------------------------------------------------------------------------

#[test]
fn a_farm_with_tokens_admits_only_peers_that_prove_them() {
    let dir = TempDir::new().expect("cannot create a temporary directory");
    let token = dir.path().join("client-token");
    std::fs::write(&token, "correct horse\n").unwrap();
    let worker_token = dir.path().join("worker-token");
    std::fs::write(&worker_token, "  tr0ub4dor &3\n").unwrap();
    let wrong = dir.path().join("wrong");
    std::fs::write(&wrong, "battery staple\n").unwrap();
    let token_arg = path_arg(&token);
    let worker_token_arg = path_arg(&worker_token);

    // Without a token, only loopback addresses are served (nothing is bound here).
    let refused = common::tessera(
        dir.path(),
        &["coordinator", "--listen", "0.0.0.0:0", "--data", "d"],
        CLIENT_TIMEOUT,
    );
    let line = one_error_line(&refused, "coordinator on 0.0.0.0 without a token");
    assert!(line.contains("without a token"), "{line}");

    let log = dir.path().join("coordinator.log");
    let mut child = Command::new(BIN)
        .args([
            "coordinator",
            "--listen",
            "127.0.0.1:0",
            "--client-token-file",
            &token_arg,
            "--worker-token-file",
            &worker_token_arg,
        ])
        .arg("--data")
        .arg(dir.path().join("data"))
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(File::create(&log).unwrap())
        .spawn()
        .expect("cannot start the coordinator");
    let stdout = child.stdout.take().unwrap();
    let _coordinator = Guarded {
        name: "coordinator".into(),
        child,
        log: Some(log),
    };
    let line = first_line(stdout, STARTUP_TIMEOUT).expect("no address from the coordinator");
    let addr = line
        .trim()
        .strip_prefix("listening on ")
        .unwrap()
        .to_owned();
    let client = |extra: &[&str]| {
        let args = cat(&["list", "--coordinator", addr.as_str()], extra);
        common::tessera(dir.path(), &args, CLIENT_TIMEOUT)
    };

    let anonymous = one_error_line(&client(&[]), "list without a token");
    assert!(
        anonymous.contains("a token is required") && anonymous.contains(&addr),
        "{anonymous}"
    );
    let wrong_token = one_error_line(&client(&["--token-file", &path_arg(&wrong)]), "wrong token");
    assert!(
        wrong_token.contains("authentication failed"),
        "{wrong_token}"
    );
    ok(client(&["--token-file", &token_arg]), "list with the token");

    // A worker without the token is refused for good and exits; one with it (from the
    // environment) joins and renders.
    let anonymous_worker = common::tessera(
        dir.path(),
        &["worker", "--coordinator", addr.as_str(), "--threads", "1"],
        CLIENT_TIMEOUT,
    );
    assert!(!anonymous_worker.status.success());
    assert!(anonymous_worker.stderr.contains("a token is required"));
    let worker = Command::new(BIN)
        .args([
            "worker",
            "--coordinator",
            addr.as_str(),
            "--threads",
            "2",
            "--name",
            "trusted",
        ])
        .env("TESSERA_TOKEN", "tr0ub4dor &3")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("cannot start a worker");
    let _worker = Guarded {
        name: "worker".into(),
        child: worker,
        log: None,
    };
    let out = dir.path().join("seed.png");
    let seed = scene("seed.json");
    let submit = cat(
        &["submit", seed.as_str(), "--wait", "-o", &path_arg(&out)],
        &["--coordinator", addr.as_str(), "--token-file", &token_arg],
    );
    ok(
        common::tessera(dir.path(), &cat(&submit, SMALL), CLIENT_TIMEOUT),
        "submit with the token",
    );
    let reference = render_reference(dir.path(), &seed, "reference.png", SMALL);
    assert_same_image(
        &out,
        &reference,
        "the image rendered by an authenticated farm",
    );
}
