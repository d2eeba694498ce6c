//! The client commands against real `tessera` processes on 127.0.0.1: `submit --wait`
//! names its job at once, rides through a coordinator restart and says how to recover an
//! image it could not write; `delete` removes an ended job; the coordinator's
//! `--retention` and `--reset-database` options.

mod common;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{self, Receiver};
use std::time::{Duration, Instant};

use common::{
    assert_same_png, client, fetch, ok, poll, render_reference, restart_coordinator, scene_path,
    serial, start_coordinator, start_coordinator_in, start_worker, submit, tessera, try_status,
    wait_done, Daemon, BIN,
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
    let _serial = serial();
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
    let _serial = serial();
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
    let _serial = serial();
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
fn delete_removes_an_ended_job_and_refuses_an_active_one() {
    let _serial = serial();
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
    let _serial = serial();
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

/// `tessera ARGS` in `dir` with extra environment variables, at most 20 s.
fn tessera_env(dir: &Path, args: &[&str], env: &[(&str, &str)]) -> std::process::Output {
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

#[test]
fn a_bad_retention_is_one_line_that_names_the_option() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("bad.toml"),
        "[coordinator]\nretention = \"1h30m\"\n",
    )
    .unwrap();
    for (args, env, value) in [
        (vec!["--retention", "2w"], vec![], "2w"),
        (vec!["--retention=90"], vec![], "90"),
        (vec!["--retention", "0s"], vec![], "0s"),
        (vec![], vec![("TESSERA_RETENTION", "soon")], "soon"),
        (vec!["--config", "bad.toml"], vec![], "1h30m"),
    ] {
        let mut all = vec!["coordinator", "--listen", "127.0.0.1:0"];
        all.extend(&args);
        all.push("--print-config");
        let out = tessera_env(dir.path(), &all, &env);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} {env:?} accepted");
        assert_eq!(
            stderr.trim().lines().count(),
            1,
            "{args:?} {env:?}: {stderr}"
        );
        assert!(
            stderr.starts_with(&format!(
                "error: invalid value '{value}' for '--retention <DURATION>': "
            )),
            "{args:?} {env:?}: {stderr}"
        );
    }
}

/// The value and source `--print-config` shows for `key`, or `None` if not set.
fn setting(printed: &str, key: &str) -> Option<(String, String)> {
    if printed.lines().any(|l| l == format!("# {key}: not set")) {
        return None;
    }
    let line = printed
        .lines()
        .find(|l| l.starts_with(&format!("{key} = ")))
        .unwrap_or_else(|| panic!("no {key} in\n{printed}"));
    let (value, source) = line[key.len() + 3..]
        .split_once("  # ")
        .unwrap_or_else(|| panic!("no source in {line:?}"));
    Some((value.to_owned(), source.to_owned()))
}

#[test]
fn print_config_shows_the_retention_and_where_it_comes_from() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("tessera.toml"),
        "[coordinator]\nretention = \"12h\"\n",
    )
    .unwrap();
    let printed = |args: &[&str], env: &[(&str, &str)]| {
        let mut all = vec!["coordinator"];
        all.extend(args);
        all.push("--print-config");
        let out = tessera_env(dir.path(), &all, env);
        assert!(out.status.success(), "{args:?}: {out:?}");
        String::from_utf8(out.stdout).unwrap()
    };
    assert_eq!(setting(&printed(&[], &[]), "retention"), None);
    let pair = |v: &str, s: &str| Some((v.to_owned(), s.to_owned()));
    assert_eq!(
        setting(&printed(&["--config", "tessera.toml"], &[]), "retention"),
        pair("\"12h\"", "config file")
    );
    assert_eq!(
        setting(
            &printed(
                &["--config", "tessera.toml"],
                &[("TESSERA_RETENTION", "30m")]
            ),
            "retention"
        ),
        pair("\"30m\"", "environment")
    );
    assert_eq!(
        setting(
            &printed(
                &["--config", "tessera.toml", "--retention", "7d"],
                &[("TESSERA_RETENTION", "30m")]
            ),
            "retention"
        ),
        pair("\"7d\"", "flag")
    );
    // --reset-database acts on one start: shown when given, never read from a file.
    assert!(!printed(&[], &[]).contains("reset-database"));
    assert!(printed(&["--reset-database"], &[])
        .lines()
        .any(|l| l == "# reset-database: given, for this start only"));
    std::fs::write(
        dir.path().join("reset.toml"),
        "[coordinator]\nreset-database = true\n",
    )
    .unwrap();
    let run = tessera(
        dir.path(),
        &["coordinator", "--config", "reset.toml"],
        Duration::from_secs(20),
    );
    assert!(!run.status.success(), "reset-database taken from a file");
    assert_eq!(
        run.stderr.trim(),
        "error: reset.toml: [coordinator] reset-database: not a setting: give \
         --reset-database on the command line of the one start that needs it"
    );
}
