//! The client commands against real `tessera` processes on 127.0.0.1: `submit --wait`
//! names its job at once, rides through a coordinator restart, says how to recover an
//! image it could not write and refuses one it cannot write before submitting;
//! `delete` removes an ended job, and the coordinator's `--retention` removes it by
//! itself; mistaken job ids and addresses are one line saying what to give; a command
//! whose output is closed early ends quietly.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{self, Receiver};
use std::time::{Duration, Instant};

use crate::support::{
    assert_same_png, client, exclusive, fetch, free_port, ok, one_error_line, poll,
    render_reference, restart_coordinator, scene_path, shared, start_coordinator,
    start_coordinator_in, start_coordinator_with_http, start_worker, submit, tessera, try_status,
    wait_done, wait_for_workers, Daemon, BIN,
};

/// A small frame of the seed scene: quick in a debug build, several tiles.
const SMALL: [&str; 6] = ["--width", "96", "--height", "64", "--aa", "1"];

/// `scenes/seed.json` followed by [`SMALL`] and 32-pixel tiles.
fn small_seed() -> Vec<String> {
    let mut args = vec![scene_path("seed.json")];
    args.extend(SMALL.iter().map(|s| s.to_string()));
    args.extend(["--tile".to_string(), "32".to_string()]);
    args
}

/// A running `tessera submit --wait`, its stderr lines arriving on a channel.
struct Waiting {
    daemon: Daemon,
    lines: Receiver<String>,
    seen: Vec<String>,
}

impl Waiting {
    /// Starts `tessera submit SCENE SMALL --wait -o OUT --coordinator ADDR` in `dir`.
    fn start(dir: &Path, addr: &str, out: &str) -> Waiting {
        let mut child: Child = Command::new(BIN)
            .arg("submit")
            .args(small_seed())
            .args(["--wait", "-o", out, "--coordinator", addr])
            .current_dir(dir)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("cannot start tessera submit");
        let stderr = child.stderr.take().expect("stderr is piped");
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Waiting {
            daemon: Daemon {
                name: "submit --wait".into(),
                child,
                log: None,
            },
            lines,
            seen: Vec::new(),
        }
    }

    /// Reads stderr lines until one satisfies `wanted` (returned); panics after
    /// `timeout` or if stderr ends first.
    fn line(&mut self, what: &str, timeout: Duration, wanted: impl Fn(&str) -> bool) -> String {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(line) => {
                    self.seen.push(line.clone());
                    if wanted(&line) {
                        return line;
                    }
                }
                Err(_) => panic!(
                    "no {what} on stderr of submit --wait within {timeout:?}; it printed:\n{}",
                    self.seen.join("\n")
                ),
            }
        }
    }

    /// Waits for the process to exit (at most `timeout`) and returns its stderr lines.
    fn finish(mut self, timeout: Duration) -> (std::process::ExitStatus, Vec<String>) {
        let status = self
            .daemon
            .wait_exit(timeout)
            .unwrap_or_else(|| panic!("submit --wait still running after {timeout:?}"));
        while let Ok(line) = self.lines.recv_timeout(Duration::from_secs(5)) {
            self.seen.push(line);
        }
        (status, self.seen)
    }
}

/// The job id in `submitted job N`.
fn submitted_id(line: &str) -> u64 {
    line.strip_prefix("submitted job ")
        .and_then(|id| id.parse().ok())
        .unwrap_or_else(|| panic!("not `submitted job N`: {line:?}"))
}

#[test]
fn submit_wait_names_the_job_on_stderr_before_anything_else() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let _worker = start_worker(dir.path(), &addr, "w1");
    let seed = small_seed();
    let mut args: Vec<&str> = vec!["submit"];
    args.extend(seed.iter().map(String::as_str));
    args.extend(["--wait", "-o", "out.png"]);
    let run = ok(client(dir.path(), &addr, &args), "submit --wait");
    let first = run.stderr.lines().next().unwrap_or_default();
    let job = submitted_id(first);
    assert!(job >= 1, "{first}");
    assert!(run.stdout.is_empty(), "stdout: {}", run.stdout);
    let reference = render_reference(dir.path(), &seed[0], "reference.png", &SMALL);
    assert_same_png(&dir.path().join("out.png"), &reference, "submit --wait");

    // With --json the id still comes first on stderr; stdout holds only the JSON.
    args.push("--json");
    let run = ok(client(dir.path(), &addr, &args), "submit --wait --json");
    let second = submitted_id(run.stderr.lines().next().unwrap_or_default());
    assert!(second > job, "job {second} after job {job}");
    let json: serde_json::Value = serde_json::from_str(run.stdout.trim())
        .unwrap_or_else(|e| panic!("not JSON ({e}): {}", run.stdout));
    assert_eq!(json["id"], second);
    assert_eq!(json["state"], "done");
}

#[test]
fn submit_wait_rides_through_a_coordinator_restart() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    // No worker yet: the job is still queued when the coordinator goes down.
    let (mut coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "coordinator-1.log");
    let mut waiting = Waiting::start(dir.path(), &addr, "out.png");
    let first = waiting.line("first line", Duration::from_secs(30), |_| true);
    let job = submitted_id(&first);

    coordinator.kill9();
    let lost = waiting.line(
        "`lost the coordinator (...): reconnecting`",
        Duration::from_secs(30),
        |l| l.contains("lost the coordinator"),
    );
    assert!(
        lost.starts_with("lost the coordinator (") && lost.ends_with("): reconnecting"),
        "{lost:?}"
    );
    // Down for a while: the client keeps trying meanwhile.
    std::thread::sleep(Duration::from_secs(2));
    let _coordinator = restart_coordinator(dir.path(), &addr, &[]);
    let _worker = start_worker(dir.path(), &addr, "w1");

    let (status, stderr) = waiting.finish(Duration::from_secs(120));
    assert!(
        status.success(),
        "submit --wait failed ({status}):\n{}",
        stderr.join("\n")
    );
    let losses = stderr
        .iter()
        .filter(|l| l.contains("lost the coordinator"))
        .count();
    assert_eq!(losses, 1, "one line per outage:\n{}", stderr.join("\n"));
    assert_eq!(
        try_status(dir.path(), &addr, job).expect("status after the restart")["state"],
        "done"
    );
    let reference = render_reference(dir.path(), &small_seed()[0], "reference.png", &SMALL);
    assert_same_png(&dir.path().join("out.png"), &reference, "after a restart");
}

#[test]
fn an_image_that_cannot_be_written_names_the_job_and_how_to_fetch_it() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    // The file can be written when the job is submitted (it is checked then); its
    // directory goes while the job waits for a worker.
    std::fs::create_dir(dir.path().join("out")).unwrap();
    let mut waiting = Waiting::start(dir.path(), &addr, "out/image.png");
    let job = submitted_id(&waiting.line("first line", Duration::from_secs(30), |_| true));
    std::fs::remove_dir_all(dir.path().join("out")).unwrap();
    let _worker = start_worker(dir.path(), &addr, "w1");
    let (status, lines) = waiting.finish(Duration::from_secs(120));
    assert!(!status.success(), "wrote into a missing directory");
    let error = lines.last().map(String::as_str).unwrap_or_default();
    assert!(
        error.starts_with(&format!(
            "error: job {job} is done, but cannot write out/image.png"
        )) && error.ends_with(&format!(
            "`tessera fetch {job} -o out/image.png` recovers it"
        )),
        "{error}"
    );
    // As it says.
    let out = fetch(dir.path(), &addr, job, "recovered.png");
    let reference = render_reference(dir.path(), &small_seed()[0], "reference.png", &SMALL);
    assert_same_png(&out, &reference, "fetched after the failed write");
}

#[test]
fn submit_wait_refuses_an_image_it_cannot_write_before_submitting() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let seed = scene_path("seed.json");
    for (out, says) in [
        ("no-such-dir/out.png", "cannot write no-such-dir/out.png"),
        ("out.jpg", "out.jpg: tessera writes PNG images only"),
    ] {
        // No worker: a job that was submitted would never end, and the run would be
        // killed.
        let run = client(dir.path(), &addr, &["submit", &seed, "--wait", "-o", out]);
        assert!(!run.status.success(), "-o {out} accepted");
        let lines: Vec<&str> = run.stderr.lines().collect();
        assert!(
            lines.len() == 1 && lines[0].starts_with(&format!("error: {says}")),
            "-o {out}: {:?}",
            run.stderr
        );
    }
    let listed = ok(client(dir.path(), &addr, &["list"]), "list");
    assert_eq!(listed.stdout.trim(), "no jobs", "a job was submitted");
}

#[test]
fn delete_removes_an_ended_job_and_refuses_an_active_one() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (_coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "coordinator.log");
    let mut worker = start_worker(dir.path(), &addr, "w1");
    let seed = small_seed();
    let args: Vec<&str> = seed.iter().map(String::as_str).collect();
    let done = submit(dir.path(), &addr, &args);
    wait_done(dir.path(), &addr, done, Duration::from_secs(60));
    let folder = data.join("jobs").join(done.to_string());
    assert!(folder.is_dir(), "{} before the delete", folder.display());

    let run = ok(
        client(dir.path(), &addr, &["delete", &done.to_string()]),
        "delete",
    );
    assert_eq!(run.stdout.trim(), format!("job {done} deleted"));
    let status = client(dir.path(), &addr, &["status", &done.to_string()]);
    assert!(
        !status.status.success(),
        "status of a deleted job succeeded"
    );
    assert!(
        status.stderr.contains(&format!("no job {done}")),
        "{}",
        status.stderr
    );
    assert!(!folder.exists(), "{} after the delete", folder.display());
    let list = ok(client(dir.path(), &addr, &["list", "--json"]), "list");
    let jobs: Vec<serde_json::Value> = serde_json::from_str(list.stdout.trim())
        .unwrap_or_else(|e| panic!("list --json is not JSON ({e}): {}", list.stdout));
    assert!(
        jobs.iter().all(|j| j["id"] != done),
        "listed after the delete: {}",
        list.stdout
    );

    // Unknown: one line, exit 1.
    let again = client(dir.path(), &addr, &["delete", &done.to_string()]);
    assert_eq!(again.status.code(), Some(1));
    assert_eq!(
        again.stderr.trim(),
        format!("error: no job {done} on this coordinator")
    );

    // Queued (no worker left): cancel it first.
    worker.kill9();
    let queued = submit(dir.path(), &addr, &args);
    assert!(
        queued > done,
        "job id {queued} after {done}: ids are never reused"
    );
    let refused = client(dir.path(), &addr, &["delete", &queued.to_string()]);
    assert_eq!(refused.status.code(), Some(1));
    assert_eq!(
        refused.stderr.trim(),
        format!("error: job {queued} is queued: cancel it first")
    );
    assert_eq!(
        try_status(dir.path(), &addr, queued).expect("status")["state"],
        "queued"
    );
    ok(
        client(dir.path(), &addr, &["cancel", &queued.to_string()]),
        "cancel",
    );
    let run = ok(
        client(
            dir.path(),
            &addr,
            &["delete", &queued.to_string(), "--json"],
        ),
        "delete --json",
    );
    let json: serde_json::Value = serde_json::from_str(run.stdout.trim())
        .unwrap_or_else(|e| panic!("not JSON ({e}): {}", run.stdout));
    assert_eq!(
        json,
        serde_json::json!({ "id": queued, "state": "deleted" })
    );
    assert!(!data.join("jobs").join(queued.to_string()).exists());
}

#[test]
fn a_finished_job_is_deleted_once_its_retention_has_passed() {
    let _turn = exclusive();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &data,
        "127.0.0.1:0",
        &["--retention", "2s"],
        "coordinator.log",
    );
    let _worker = start_worker(dir.path(), &addr, "w1");
    let seed = small_seed();
    let args: Vec<&str> = seed.iter().map(String::as_str).collect();
    let job = submit(dir.path(), &addr, &args);
    wait_done(dir.path(), &addr, job, Duration::from_secs(60));
    let ended = Instant::now();
    poll(
        &format!("job {job} to be deleted"),
        Duration::from_secs(60),
        || {
            let run = client(dir.path(), &addr, &["status", &job.to_string()]);
            (!run.status.success() && run.stderr.contains(&format!("no job {job}"))).then_some(())
        },
    );
    assert!(
        ended.elapsed() >= Duration::from_secs(1),
        "deleted {:?} after it ended, with a retention of 2 s",
        ended.elapsed()
    );
    assert!(!data.join("jobs").join(job.to_string()).exists());
}

#[test]
fn mistakes_in_addresses_and_job_ids_are_one_line_saying_what_to_give() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let t = Duration::from_secs(20);
    let line = one_error_line(&tessera(dir.path(), &["status", "abc"], t), "status abc");
    assert_eq!(
        line,
        "error: invalid value 'abc' for '<JOB>': a job id is a whole number, as `tessera \
         submit` and `tessera list` print it"
    );
    let line = one_error_line(
        &tessera(dir.path(), &["list", "--coordinator", "127.0.0.1"], t),
        "list --coordinator 127.0.0.1",
    );
    assert_eq!(
        line,
        "error: invalid value '127.0.0.1' for '--coordinator <ADDR>': no port: give \
         HOST:PORT, for example 127.0.0.1:7878 (7878 is the coordinator's default port)"
    );

    // The coordinator's HTTP port given for its protocol port.
    let (_coordinator, addr, http) = start_coordinator_with_http(dir.path(), &[]);
    let line = one_error_line(
        &tessera(dir.path(), &["list", "--coordinator", &http], t),
        "list --coordinator HTTP-PORT",
    );
    assert_eq!(
        line,
        format!(
            "error: {http} answered in HTTP: this looks like the coordinator's HTTP port \
             (--http); give the port it listens on for workers and clients (--listen, 7878 \
             by default)"
        )
    );

    // With --json, the error is the one JSON value on stdout, and stderr is empty.
    for args in [
        vec!["status", "abc", "--json"],
        vec!["list", "--json", "--coordinator", &http],
    ] {
        let run = tessera(dir.path(), &args, t);
        assert!(!run.status.success(), "{args:?}");
        assert!(run.stderr.is_empty(), "{args:?}: stderr {}", run.stderr);
        let value: serde_json::Value = serde_json::from_str(run.stdout.trim())
            .unwrap_or_else(|e| panic!("{args:?}: not JSON ({e}): {}", run.stdout));
        let message = value["error"].as_str().unwrap_or_default();
        assert!(
            message.contains("a job id is a whole number") || message.contains("answered in HTTP"),
            "{args:?}: {value}"
        );
        assert_eq!(value.as_object().map(|o| o.len()), Some(1), "{value}");
    }
    // A coordinator's refusal keeps its kind, for a script to act on.
    let run = tessera(
        dir.path(),
        &["status", "999", "--json", "--coordinator", &addr],
        t,
    );
    assert!(!run.status.success());
    let value: serde_json::Value = serde_json::from_str(run.stdout.trim()).unwrap();
    assert_eq!(
        value,
        serde_json::json!({ "error": "no job 999 on this coordinator", "kind": "not_found" })
    );
}

/// `tessera ARGS` in `dir` with stdout a pipe of one page (4 KiB, so that the output
/// cannot all fit in it) whose reader reads `lines` lines and then closes it, as
/// `tessera ARGS | head -LINES` does: the lines read, the exit status and stderr.
fn through_closed_pipe(
    dir: &Path,
    args: &[&str],
    lines: usize,
) -> (Vec<String>, std::process::ExitStatus, String) {
    use std::os::fd::AsRawFd;
    let (reader, writer) = std::io::pipe().expect("cannot make a pipe");
    // SAFETY: F_SETPIPE_SZ only resizes the pipe this test owns (to the minimum the
    // kernel allows, one page); its failure would only leave the pipe larger.
    let resized = unsafe { libc::fcntl(reader.as_raw_fd(), libc::F_SETPIPE_SZ, 4096) };
    assert!(resized > 0, "cannot resize the pipe");
    let child = Command::new(BIN)
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(writer)
        .stderr(Stdio::piped())
        .spawn()
        .expect("cannot start tessera");
    let mut read = Vec::new();
    // Unbuffered: what is not read stays in the pipe, which the command must fill.
    let mut reader = BufReader::with_capacity(1, reader);
    for _ in 0..lines {
        let mut line = String::new();
        reader
            .read_line(&mut line)
            .expect("cannot read tessera's stdout");
        read.push(line.trim_end().to_owned());
    }
    drop(reader);
    let mut daemon = Daemon {
        name: format!("tessera {}", args.join(" ")),
        child,
        log: None,
    };
    let status = daemon
        .wait_exit(Duration::from_secs(20))
        .unwrap_or_else(|| panic!("{} still running with its output closed", daemon.name));
    let mut stderr = String::new();
    std::io::Read::read_to_string(
        daemon.child.stderr.as_mut().expect("stderr is piped"),
        &mut stderr,
    )
    .expect("cannot read tessera's stderr");
    (read, status, stderr)
}

#[test]
fn a_command_whose_output_is_closed_ends_quietly() {
    use std::os::unix::process::ExitStatusExt;
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let _worker = start_worker(dir.path(), &addr, "w1");
    // 64 tiles: more than a hundred lines of events, several pages.
    let job = submit(
        dir.path(),
        &addr,
        &[
            &scene_path("seed.json"),
            "--width",
            "64",
            "--height",
            "64",
            "--tile",
            "8",
        ],
    );
    wait_done(dir.path(), &addr, job, Duration::from_secs(60));
    // Enough jobs for `list`'s table to be longer than a page.
    for _ in 0..60 {
        submit(
            dir.path(),
            &addr,
            &[
                &scene_path("seed.json"),
                "--width",
                "8",
                "--height",
                "8",
                "--name",
                "a-job",
            ],
        );
    }
    let table = ok(client(dir.path(), &addr, &["list"]), "list").stdout;
    assert!(table.len() > 5000, "list printed {} bytes", table.len());
    let job = job.to_string();
    for (args, lines) in [
        (vec!["events", &job, "--coordinator", &addr], 1),
        (vec!["list", "--coordinator", &addr], 1),
        // A reader gone before anything was written (`tessera simulate | true`).
        (vec!["simulate", "--workers", "20", "--jobs", "2"], 0),
    ] {
        let (read, status, stderr) = through_closed_pipe(dir.path(), &args, lines);
        assert_eq!(read.len(), lines, "{args:?}");
        assert!(read.iter().all(|l| !l.is_empty()), "{args:?}: {read:?}");
        assert_eq!(stderr, "", "{args:?}: nothing on stderr");
        // Ended by SIGPIPE, as `ls | head -1` ends `ls`: the shell's status 141.
        assert_eq!(
            status.signal(),
            Some(libc::SIGPIPE),
            "{args:?}: ended by SIGPIPE, not {status}"
        );
    }
}

#[test]
fn refusals_say_what_is_meant_and_what_to_do() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let t = Duration::from_secs(20);

    // Nothing listens on this port: the line says how the address is chosen.
    let nowhere = format!("127.0.0.1:{}", free_port());
    let line = one_error_line(
        &tessera(dir.path(), &["list", "--coordinator", &nowhere], t),
        "list --coordinator NOWHERE",
    );
    assert_eq!(
        line,
        format!(
            "error: cannot reach the coordinator at {nowhere}: Connection refused (os error \
             111); --coordinator ADDR or TESSERA_COORDINATOR chooses the coordinator"
        )
    );

    let line = one_error_line(
        &tessera(dir.path(), &["priority", "52", "abc"], t),
        "priority 52 abc",
    );
    assert_eq!(
        line,
        "error: invalid value 'abc' for '<PRIORITY>': a priority is a whole number, higher \
         runs first (for example 10 or -5)"
    );
    let line = one_error_line(
        &tessera(dir.path(), &["requeue", "52", "3", "x"], t),
        "requeue 52 3 x",
    );
    assert_eq!(
        line,
        "error: invalid value 'x' for '<TILES>...': a tile number is a whole number from 0, \
         as `tessera events` names the tiles"
    );

    // A cancelled job resumed: it is retried, not resumed.
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let job = submit(
        dir.path(),
        &addr,
        &small_seed().iter().map(String::as_str).collect::<Vec<_>>(),
    );
    let id = job.to_string();
    ok(client(dir.path(), &addr, &["cancel", &id]), "cancel");
    let line = one_error_line(&client(dir.path(), &addr, &["resume", &id]), "resume");
    assert_eq!(
        line,
        format!(
            "error: job {job} cannot be resumed: it is cancelled, only a paused job can be \
             (`tessera retry {job}` puts it back in the queue)"
        )
    );
    let line = one_error_line(&client(dir.path(), &addr, &["pause", &id]), "pause");
    assert_eq!(
        line,
        format!(
            "error: job {job} cannot be paused: it is cancelled, only a queued or running job \
             can be (`tessera retry {job}` puts it back in the queue)"
        )
    );
}

#[test]
fn ctrl_c_on_submit_wait_leaves_the_job_running_and_says_how_to_follow_it() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let mut worker = start_worker(dir.path(), &addr, "w1");
    wait_for_workers(dir.path(), &addr, 1, Duration::from_secs(30));
    // Frozen, the worker holds the job running for as long as the test needs.
    worker.signal("STOP");
    let mut waiting = Waiting::start(dir.path(), &addr, "out.png");
    let job = submitted_id(&waiting.line("the job's id", Duration::from_secs(30), |l| {
        l.starts_with("submitted job ")
    }));
    waiting.daemon.signal("INT");
    let (status, lines) = waiting.finish(Duration::from_secs(20));
    assert_eq!(status.code(), Some(130), "{status}: {lines:?}");
    assert_eq!(
        lines.last().map(String::as_str),
        Some(
            format!(
                "error: interrupted by SIGINT: job {job} keeps running on the farm: `tessera \
                 status {job}` follows it, `tessera cancel {job}` cancels it"
            )
            .as_str()
        ),
        "{lines:?}"
    );
    assert!(!dir.path().join("out.png").exists());
    let status = try_status(dir.path(), &addr, job).expect("the job is still there");
    assert!(
        status["state"] == "queued" || status["state"] == "running",
        "{status}"
    );
    // Thawed, the worker finishes it.
    worker.signal("CONT");
    wait_done(dir.path(), &addr, job, Duration::from_secs(60));
}

#[test]
fn list_shows_the_newest_job_first() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let seed = scene_path("seed.json");
    let jobs: Vec<u64> = (0..3)
        .map(|_| submit(dir.path(), &addr, &[&seed, "--width", "8", "--height", "8"]))
        .collect();
    let newest_first: Vec<u64> = jobs.iter().rev().copied().collect();
    let table = ok(client(dir.path(), &addr, &["list"]), "list").stdout;
    let ids: Vec<u64> = table
        .lines()
        .skip(1)
        .map(|row| row.split_whitespace().next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(ids, newest_first, "{table}");
    let json = ok(
        client(dir.path(), &addr, &["list", "--json"]),
        "list --json",
    )
    .stdout;
    let listed: Vec<serde_json::Value> = serde_json::from_str(json.trim()).unwrap();
    let ids: Vec<u64> = listed.iter().map(|j| j["id"].as_u64().unwrap()).collect();
    assert_eq!(ids, newest_first, "{json}");
}
