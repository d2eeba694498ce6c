//! The client commands as the tests use them to drive and inspect a farm, and the
//! reference images they compare the farm's with.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

use super::{assert_same_png, ok, poll, tessera, tessera_within, Run, BIN};

/// `tessera ARGS --coordinator ADDR` in `dir`, at most 60 s.
pub fn client(dir: &Path, addr: &str, args: &[&str]) -> Run {
    let mut all: Vec<&str> = args.to_vec();
    all.extend(["--coordinator", addr]);
    tessera(dir, &all, Duration::from_secs(60))
}

/// `tessera ARGS` in `dir` with extra environment variables, at most 20 s.
pub fn tessera_env(dir: &Path, args: &[&str], env: &[(&str, &str)]) -> std::process::Output {
    let mut child = Command::new(BIN)
        .args(args)
        .envs(env.iter().copied())
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("cannot run tessera");
    let deadline = Instant::now() + Duration::from_secs(20);
    while child.try_wait().expect("cannot wait").is_none() {
        if Instant::now() >= deadline {
            let _ = child.kill();
            panic!("tessera {args:?} still running after 20 s: killed");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    child
        .wait_with_output()
        .expect("cannot read tessera's output")
}

/// `tessera submit ARGS` (without `--wait`): the job id it printed.
pub fn submit(dir: &Path, addr: &str, args: &[&str]) -> u64 {
    let mut all = vec!["submit"];
    all.extend(args);
    let run = ok(
        client(dir, addr, &all),
        &format!("tessera {}", all.join(" ")),
    );
    run.stdout
        .trim()
        .parse()
        .unwrap_or_else(|e| panic!("submit printed {:?}, not a job id: {e}", run.stdout))
}

/// `tessera submit SCENE ARGS` (without `--wait`): the job id it printed.
pub fn submit_scene(dir: &Path, addr: &str, scene: &str, args: &[&str]) -> u64 {
    let mut all = vec![scene];
    all.extend(args);
    submit(dir, addr, &all)
}

/// `tessera status JOB --json`, parsed; `None` if the command failed (for example
/// while the coordinator is down).
pub fn try_status(dir: &Path, addr: &str, job: u64) -> Option<Value> {
    let run = client(dir, addr, &["status", &job.to_string(), "--json"]);
    if !run.status.success() {
        return None;
    }
    Some(
        serde_json::from_str(run.stdout.trim())
            .unwrap_or_else(|e| panic!("status --json is not JSON ({e}): {:?}", run.stdout)),
    )
}

/// `tessera status JOB --json`, which must succeed.
pub fn status_json(dir: &Path, addr: &str, job: u64) -> Value {
    let run = ok(
        client(dir, addr, &["status", &job.to_string(), "--json"]),
        "status --json",
    );
    serde_json::from_str(run.stdout.trim()).expect("status --json is JSON")
}

/// Polls `status` until the job is `done` (within `timeout`), tolerating a coordinator
/// that is briefly unreachable; panics if the job ends in another state.
///
/// A job that is not done in time fails the test with what the farm looked like then:
/// the job's last status, the workers, and the job's last events, so that a failure
/// seen once on a loaded machine can be understood from its log.
pub fn wait_done(dir: &Path, addr: &str, job: u64, timeout: Duration) -> Value {
    let deadline = Instant::now() + timeout;
    let mut last = None;
    loop {
        if let Some(status) = try_status(dir, addr, job) {
            assert_not_ended_badly(job, &status);
            if status["state"] == "done" {
                return status;
            }
            last = Some(status);
        }
        if Instant::now() >= deadline {
            let look = |args: &[&str]| {
                let mut all = args.to_vec();
                all.extend(["--coordinator", addr]);
                tessera_within(dir, &all, Duration::from_secs(10))
                    .map_or_else(|| "(no answer in 10 s)".to_owned(), |run| run.stdout)
            };
            let workers = look(&["workers", "--json"]);
            let events = look(&["events", &job.to_string()]);
            let tail: Vec<&str> = events.lines().rev().take(40).collect();
            let tail: Vec<&str> = tail.into_iter().rev().collect();
            panic!(
                "timed out after {timeout:?} waiting for job {job} to be done\n\
                 last status: {}\nworkers: {}\nlast events:\n{}",
                last.map_or_else(|| "none".to_owned(), |s| s.to_string()),
                workers.trim(),
                tail.join("\n")
            );
        }
        std::thread::sleep(super::POLL);
    }
}

/// Polls `status` (at most `timeout`) until job `job` has at least `tiles` tiles done,
/// failing at once if it ends failed or cancelled, and checks that it still runs then.
pub fn wait_for_tiles(
    job: u64,
    tiles: u64,
    timeout: Duration,
    status: impl Fn() -> Value,
) -> Value {
    let status = poll(&format!("{tiles} tiles of job {job}"), timeout, || {
        let status = status();
        assert_not_ended_badly(job, &status);
        (tiles_done(&status) >= tiles).then_some(status)
    });
    assert_eq!(
        status["state"], "running",
        "the job should still run (make it longer): {status}"
    );
    status
}

/// A job that failed or was cancelled fails the test at once.
pub fn assert_not_ended_badly(job: u64, status: &Value) {
    let state = status["state"].as_str().expect("state is a string");
    assert!(
        !matches!(state, "failed" | "cancelled"),
        "job {job} ended {state}: {status}"
    );
}

/// A job status's `tiles_done`.
pub fn tiles_done(status: &Value) -> u64 {
    status["tiles_done"].as_u64().expect("tiles_done")
}

/// A job status's `tiles_total`.
pub fn tiles_total(status: &Value) -> u64 {
    status["tiles_total"].as_u64().expect("tiles_total")
}

/// `workers --json`, or `None` if the coordinator cannot be reached within 30 s.
pub fn try_workers(dir: &Path, addr: &str) -> Option<Vec<Value>> {
    let run = tessera_within(
        dir,
        &["workers", "--json", "--coordinator", addr],
        Duration::from_secs(30),
    )?;
    if !run.status.success() {
        return None;
    }
    match serde_json::from_str(run.stdout.trim()) {
        Ok(Value::Array(workers)) => Some(workers),
        other => panic!("workers --json: {other:?}"),
    }
}

/// `tessera workers --json EXTRA...` (a token or TLS flags), which must succeed.
pub fn workers_json(dir: &Path, addr: &str, extra: &[&str]) -> Vec<Value> {
    let mut args = vec!["workers", "--json"];
    args.extend(extra);
    let run = ok(client(dir, addr, &args), "workers --json");
    match serde_json::from_str(run.stdout.trim()) {
        Ok(Value::Array(workers)) => workers,
        other => panic!("workers --json: {other:?}"),
    }
}

/// The names of listed workers, in the listing's order.
pub fn worker_names(workers: &[Value]) -> Vec<String> {
    workers
        .iter()
        .map(|w| w["name"].as_str().expect("a name").to_owned())
        .collect()
}

/// The listed worker named `name`.
pub fn worker_named<'a>(workers: &'a [Value], name: &str) -> Option<&'a Value> {
    workers.iter().find(|w| w["name"] == name)
}

/// Each worker's name and connection id, sorted: equal lists before and after a fault
/// mean that no worker reconnected or was dropped across it.
pub fn connections(workers: &[Value]) -> Vec<(String, u64)> {
    let mut list: Vec<(String, u64)> = workers
        .iter()
        .map(|w| {
            (
                w["name"].as_str().expect("a worker's name").to_owned(),
                w["id"].as_u64().expect("a worker's id"),
            )
        })
        .collect();
    list.sort();
    list
}

/// Longest a worker may take to register, also after a reconnection backoff.
pub const REGISTER_TIMEOUT: Duration = Duration::from_secs(20);

/// Waits (at most `timeout`) until exactly `n` workers are connected.
pub fn wait_for_workers(dir: &Path, addr: &str, n: usize, timeout: Duration) {
    poll(&format!("{n} workers to register"), timeout, || {
        try_workers(dir, addr).filter(|w| w.len() == n)
    });
}

/// `tessera fetch JOB -o DIR/NAME`.
pub fn fetch(dir: &Path, addr: &str, job: u64, name: &str) -> PathBuf {
    let out = dir.join(name);
    let out_arg = out.to_str().expect("test paths are UTF-8");
    ok(
        client(dir, addr, &["fetch", &job.to_string(), "-o", out_arg]),
        &format!("fetch {job}"),
    );
    out
}

/// `tessera events JOB --json`, parsed: (kind, detail) of each event, in order, and
/// checks that the numbers increase.
pub fn events(dir: &Path, addr: &str, job: u64) -> Vec<(String, String)> {
    let run = ok(
        client(dir, addr, &["events", &job.to_string(), "--json"]),
        "events --json",
    );
    let value: Value = serde_json::from_str(run.stdout.trim()).unwrap();
    let list = value.as_array().expect("an array of events");
    let mut last = 0;
    list.iter()
        .map(|e| {
            let seq = e["seq"].as_u64().unwrap();
            assert!(seq > last, "event numbers must increase: {value}");
            last = seq;
            (
                e["event"].as_str().unwrap().to_owned(),
                e["detail"].as_str().unwrap().to_owned(),
            )
        })
        .collect()
}

/// The tile numbers of the events of `kind` whose detail starts `tile N`.
pub fn tiles_of(events: &[(String, String)], kind: &str) -> Vec<u32> {
    events
        .iter()
        .filter(|(k, _)| k == kind)
        .filter_map(|(_, d)| d.strip_prefix("tile ")?.split(' ').next()?.parse().ok())
        .collect()
}

/// Job `job`'s fetched image (`DIR/job-JOB.png`) is `tessera render`'s for `scene` and
/// the job's `args` (`DIR/reference-JOB.png`).
pub fn assert_job_image(dir: &Path, addr: &str, job: u64, scene: &str, args: &[&str], what: &str) {
    let reference = render_reference(
        dir,
        scene,
        &format!("reference-{job}.png"),
        &render_args(args),
    );
    let out = fetch(dir, addr, job, &format!("job-{job}.png"));
    assert_same_png(&out, &reference, what);
}

/// `tessera render SCENE -o DIR/NAME ARGS...`: the reference image.
///
/// The references of the scenes shipped in `scenes/` are rendered once per test
/// process and copied for each test that asks again with the same arguments (the
/// faults tests compare a dozen jobs with the same few images, each seconds of CPU): a
/// rendering is deterministic, so the copy is the file `tessera render` would write
/// again, whatever its `--threads` (the farm's images, of any number of one-thread
/// workers, are compared with the same references). Other scenes (written by a test,
/// or beside mesh files it may change) are rendered each time.
pub fn render_reference(dir: &Path, scene: &str, name: &str, args: &[&str]) -> PathBuf {
    use std::collections::BTreeMap;
    use std::sync::Mutex;
    /// The image's bytes by scene, arguments and file type.
    type Key = (PathBuf, Vec<String>, Option<std::ffi::OsString>);
    static RENDERED: Mutex<BTreeMap<Key, Vec<u8>>> = Mutex::new(BTreeMap::new());

    let out = dir.join(name);
    let shipped = Path::new(scene)
        .canonicalize()
        .ok()
        .filter(|p| p.parent() == super::repo().join("scenes").canonicalize().ok().as_deref());
    let key = shipped.map(|scene| {
        let image_args = without_flag(args, "--threads")
            .into_iter()
            .map(str::to_owned)
            .collect();
        (scene, image_args, out.extension().map(ToOwned::to_owned))
    });
    let cached = key.as_ref().and_then(|key| {
        let rendered = RENDERED.lock().unwrap_or_else(|e| e.into_inner());
        rendered.get(key).cloned()
    });
    if let Some(bytes) = cached {
        std::fs::write(&out, bytes)
            .unwrap_or_else(|e| panic!("cannot write {}: {e}", out.display()));
        return out;
    }
    let out_arg = out.to_str().expect("test paths are UTF-8");
    let mut all = vec!["render", scene, "-o", out_arg];
    all.extend(args);
    ok(
        tessera(dir, &all, Duration::from_secs(60)),
        &format!("tessera {}", all.join(" ")),
    );
    // An output that is not a file (`--frames` into a directory) is not kept.
    if let Some((key, bytes)) = key.zip(std::fs::read(&out).ok()) {
        RENDERED
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(key, bytes);
    }
    out
}

/// A job's arguments less `--tile`, which `tessera render` does not take.
pub fn render_args<'a>(args: &[&'a str]) -> Vec<&'a str> {
    without_flag(args, "--tile")
}

/// `args` less every `flag` and the value after it.
fn without_flag<'a>(args: &[&'a str], flag: &str) -> Vec<&'a str> {
    let mut out = Vec::new();
    let mut it = args.iter();
    while let Some(&arg) = it.next() {
        if arg == flag {
            it.next();
        } else {
            out.push(arg);
        }
    }
    out
}
