//! Operating a farm, against real `tessera` processes on 127.0.0.1: one coordinator per
//! data directory; an image file that cannot be written is refused before the farm
//! spends anything on it; `tessera up` stopped by a signal cleans up and exits as a
//! shell expects; cancelling twice is no error; mistaken job ids and addresses are one
//! line saying what to give; `up` takes what `render` takes; a job that did not finish
//! shows no error estimate, and the page and `status --json` agree; a disabled machine
//! gets no tiles, across a coordinator restart, until enabled; a drained worker finishes
//! and exits 0; the clients warn when no worker can take tiles; jobs carry a name, a
//! submitter and their queue wait; a job's events tell what happened; and failed or
//! cancelled jobs are retried and tiles requeued by hand.

mod common;

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::{
    client, ok, poll, scene_path, serial, start_coordinator, start_coordinator_in, start_worker,
    submit, tessera, try_start_coordinator, wait_done, Daemon, BIN,
};

#[test]
fn a_data_directory_in_use_is_refused_with_the_holders_address() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (mut first, addr) = start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "first.log");
    let refused = try_start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "second.log")
        .map(|(_, addr)| addr)
        .expect_err("a second coordinator started on the same data directory");
    let log = std::fs::read_to_string(dir.path().join("second.log")).unwrap();
    let errors: Vec<&str> = log.lines().filter(|l| l.starts_with("error: ")).collect();
    assert_eq!(errors.len(), 1, "{refused}");
    assert!(
        errors[0].contains(&format!(
            "the data directory {} is in use by another coordinator (pid {}, listening on \
             {addr})",
            data.display(),
            first.pid()
        )),
        "{}",
        errors[0]
    );
    // The first one goes on serving.
    let listed = ok(client(dir.path(), &addr, &["list"]), "list");
    assert_eq!(listed.stdout.trim(), "no jobs");
    assert!(first.is_running());

    // Killed, it leaves its lock file behind, which does not stop a restart.
    first.kill9();
    assert!(data.join("coordinator.lock").exists());
    let (_again, again) = start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "third.log");
    ok(
        client(dir.path(), &again, &["list"]),
        "list after a restart",
    );
}

#[test]
fn submit_wait_refuses_an_image_it_cannot_write_before_submitting() {
    let _serial = serial();
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
fn up_refuses_an_image_it_cannot_write_before_starting_a_farm() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let started = Instant::now();
    let run = tessera(
        dir.path(),
        &[
            "up",
            &scene_path("seed.json"),
            "-o",
            "no-such-dir/out.png",
            "--width",
            "4000",
            "--height",
            "4000",
        ],
        Duration::from_secs(20),
    );
    assert!(!run.status.success());
    let lines: Vec<&str> = run.stderr.lines().collect();
    assert!(
        lines.len() == 1 && lines[0].starts_with("error: cannot write no-such-dir/out.png"),
        "{:?}",
        run.stderr
    );
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "{:?}",
        started.elapsed()
    );
}

#[test]
fn up_stopped_by_a_signal_removes_its_farm_and_exits_with_128_plus_the_signal() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    for (signal, code) in [("TERM", 143), ("INT", 130)] {
        // Its own temporary directory, to see what `up` leaves there.
        let tmp = dir.path().join(format!("tmp-{signal}"));
        std::fs::create_dir(&tmp).unwrap();
        let child = Command::new(BIN)
            .args([
                "up",
                &scene_path("seed.json"),
                "--aa",
                "16",
                "-o",
                "out.png",
            ])
            .args(["--width", "1200", "--height", "800"])
            .current_dir(dir.path())
            .env("TMPDIR", &tmp)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.path().join("up.log")).unwrap())
            .spawn()
            .unwrap();
        let mut up = Daemon {
            name: "up".into(),
            child,
            log: Some(dir.path().join("up.log")),
        };
        // The farm is up once its coordinator has a database.
        let farm = poll("the local farm", Duration::from_secs(30), || {
            std::fs::read_dir(&tmp)
                .ok()?
                .filter_map(Result::ok)
                .map(|e| e.path())
                .find(|p| p.join("data/tessera.db").exists())
        });
        std::thread::sleep(Duration::from_millis(500));
        up.signal(signal);
        let status = up
            .wait_exit(Duration::from_secs(20))
            .unwrap_or_else(|| panic!("up still running 20 s after SIG{signal}"));
        assert_eq!(status.code(), Some(code), "SIG{signal}: {}", up.log_text());
        let log = up.log_text();
        assert!(
            log.trim_end().ends_with(&format!(
                "error: interrupted by SIG{signal}: the local farm is stopped, no image written"
            )),
            "{log}"
        );
        assert!(!farm.exists(), "SIG{signal} left {} behind", farm.display());
        let left: Vec<_> = std::fs::read_dir(&tmp).unwrap().collect();
        assert!(left.is_empty(), "SIG{signal} left {left:?}");
        assert!(!dir.path().join("out.png").exists());
    }
}

#[test]
fn cancelling_a_cancelled_job_succeeds_and_a_done_one_says_why_not() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let small = ["--width", "64", "--height", "48", "--aa", "1"];
    let mut args = vec![scene_path("seed.json")];
    args.extend(small.iter().map(|s| s.to_string()));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    // No worker yet: the job stays queued.
    let job = submit(dir.path(), &addr, &args).to_string();
    let first = ok(client(dir.path(), &addr, &["cancel", &job]), "cancel");
    assert_eq!(first.stdout.trim(), format!("job {job} cancelled"));
    let again = ok(client(dir.path(), &addr, &["cancel", &job]), "cancel again");
    assert_eq!(
        again.stdout.trim(),
        format!("job {job} was already cancelled")
    );
    let json = ok(
        client(dir.path(), &addr, &["cancel", &job, "--json"]),
        "cancel --json",
    );
    let json: serde_json::Value = serde_json::from_str(json.stdout.trim()).unwrap();
    assert_eq!(json["state"], "cancelled");
    assert_eq!(json["already_cancelled"], true);

    let _worker = start_worker(dir.path(), &addr, "w1");
    let done = submit(dir.path(), &addr, &args);
    wait_done(dir.path(), &addr, done, Duration::from_secs(60));
    let run = client(dir.path(), &addr, &["cancel", &done.to_string()]);
    assert_eq!(run.status.code(), Some(1), "{}", run.stderr);
    assert_eq!(
        run.stderr.trim(),
        format!(
            "error: job {done} is already done: there is nothing to cancel (`tessera delete \
             {done}` removes it)"
        )
    );
    let missing = client(dir.path(), &addr, &["cancel", "999"]);
    assert!(!missing.status.success());
    assert!(missing.stderr.contains("no job 999"), "{}", missing.stderr);
}

#[test]
fn mistakes_in_addresses_and_job_ids_are_one_line_saying_what_to_give() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let one_line = |run: &common::Run| -> String {
        assert!(!run.status.success(), "accepted: {}", run.stdout);
        let lines: Vec<&str> = run.stderr.lines().collect();
        assert_eq!(lines.len(), 1, "{}", run.stderr);
        assert!(run.stdout.is_empty(), "stdout: {}", run.stdout);
        lines[0].to_owned()
    };
    let t = Duration::from_secs(20);
    let line = one_line(&tessera(dir.path(), &["status", "abc"], t));
    assert_eq!(
        line,
        "error: invalid value 'abc' for '<JOB>': a job id is a whole number, as `tessera \
         submit` and `tessera list` print it"
    );
    let line = one_line(&tessera(
        dir.path(),
        &["list", "--coordinator", "127.0.0.1"],
        t,
    ));
    assert_eq!(
        line,
        "error: invalid value '127.0.0.1' for '--coordinator <ADDR>': no port: give \
         HOST:PORT, for example 127.0.0.1:7878 (7878 is the coordinator's default port)"
    );

    // The coordinator's HTTP port given for its protocol port.
    let http = format!("127.0.0.1:{}", common::free_port());
    let (_coordinator, _addr) = start_coordinator(
        dir.path(),
        &dir.path().join("data"),
        "127.0.0.1:0",
        &["--http", &http],
        "coordinator.log",
    );
    let line = one_line(&tessera(dir.path(), &["list", "--coordinator", &http], t));
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
}

#[test]
fn up_takes_the_antialiasing_render_takes() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let args = [
        "up",
        &scene_path("seed.json"),
        "--aa",
        "20",
        "--width",
        "40",
        "--height",
        "30",
        "-o",
        "out.png",
    ];
    let run = ok(
        tessera(dir.path(), &args, Duration::from_secs(120)),
        "up --aa 20",
    );
    assert!(run.stderr.contains("out.png: 40x30"), "{}", run.stderr);
    let reference = common::render_reference(
        dir.path(),
        &scene_path("seed.json"),
        "reference.png",
        &["--aa", "20", "--width", "40", "--height", "30"],
    );
    common::assert_same_png(&dir.path().join("out.png"), &reference, "up --aa 20");
}

#[test]
fn a_job_that_did_not_finish_shows_no_error_estimate_and_both_jsons_agree() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let http = format!("127.0.0.1:{}", common::free_port());
    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &dir.path().join("data"),
        "127.0.0.1:0",
        &["--http", &http],
        "coordinator.log",
    );
    let _worker = start_worker(dir.path(), &addr, "w1");
    let page_job = |job: u64| -> serde_json::Value {
        let (code, body) = common::http_get(&http, "/api/status").expect("the status page");
        assert_eq!(code, 200);
        let farm: serde_json::Value = serde_json::from_slice(&body).unwrap();
        farm["jobs"]
            .as_array()
            .unwrap()
            .iter()
            .find(|j| j["id"] == job)
            .cloned()
            .unwrap_or_else(|| panic!("job {job} not on the page: {farm}"))
    };
    let seed = scene_path("seed.json");
    // Long enough to be cancelled with some of its tiles in.
    let job = submit(dir.path(), &addr, &[&seed, "--aa", "8", "--tile", "16"]);
    poll("a tile of the job", Duration::from_secs(60), || {
        let status = common::try_status(dir.path(), &addr, job)?;
        (common::tiles_done(&status) > 0).then_some(())
    });
    ok(
        client(dir.path(), &addr, &["cancel", &job.to_string()]),
        "cancel",
    );
    let status = common::try_status(dir.path(), &addr, job).unwrap();
    assert_eq!(status["state"], "cancelled");
    assert!(common::tiles_done(&status) > 0, "{status}");
    assert!(status["estimated_error"].is_null(), "{status}");
    assert!(status["samples_per_pixel"].is_null(), "{status}");
    let page = page_job(job);
    assert!(page["estimated_error"].is_null(), "{page}");
    assert!(page["samples_per_pixel"].is_null(), "{page}");
    let line = ok(
        client(dir.path(), &addr, &["status", &job.to_string()]),
        "status",
    );
    assert!(!line.stdout.contains("estimated error"), "{}", line.stdout);

    // A finished job: the same figures both ways.
    let done = submit(
        dir.path(),
        &addr,
        &[&seed, "--width", "64", "--height", "48", "--aa", "2"],
    );
    let status = wait_done(dir.path(), &addr, done, Duration::from_secs(60));
    let page = page_job(done);
    for key in ["samples_per_pixel", "estimated_error"] {
        assert!(status[key].is_number(), "{key}: {status}");
        assert_eq!(status[key], page[key], "{key}");
    }
}

#[test]
fn a_paused_job_gets_no_tiles_stays_paused_across_a_restart_and_resumes() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (mut coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "first.log");
    let seed = scene_path("seed.json");
    let args = [
        seed.as_str(),
        "--width",
        "64",
        "--height",
        "48",
        "--aa",
        "1",
    ];
    let job = submit(dir.path(), &addr, &args);
    let id = job.to_string();
    let paused = ok(client(dir.path(), &addr, &["pause", &id]), "pause");
    assert!(
        paused.stdout.starts_with(&format!("job {job} paused")),
        "{}",
        paused.stdout
    );
    // Pausing a paused job changes nothing and is no error.
    let again = ok(
        client(dir.path(), &addr, &["pause", &id, "--json"]),
        "pause again",
    );
    let again: serde_json::Value = serde_json::from_str(again.stdout.trim()).unwrap();
    assert_eq!(again["state"], "paused", "{again}");
    assert_eq!(again["paused"], true, "{again}");

    // The pause is stored: a restarted coordinator keeps it.
    coordinator.kill9();
    let (_coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "second.log");
    let listed = ok(client(dir.path(), &addr, &["status", &id]), "status");
    assert!(
        listed.stdout.contains(&format!("job {job}: paused, 0/")),
        "{}",
        listed.stdout
    );

    // A worker gets none of its tiles.
    let _worker = start_worker(dir.path(), &addr, "w1");
    poll("the worker to connect", Duration::from_secs(30), || {
        let run = ok(client(dir.path(), &addr, &["workers", "--json"]), "workers");
        let workers: serde_json::Value = serde_json::from_str(run.stdout.trim()).unwrap();
        (workers.as_array().map_or(0, Vec::len) == 1).then_some(())
    });
    std::thread::sleep(Duration::from_secs(2));
    let status = common::try_status(dir.path(), &addr, job).expect("status");
    assert_eq!(status["state"], "paused", "{status}");
    assert_eq!(status["tiles_done"], 0, "{status}");

    let resumed = ok(client(dir.path(), &addr, &["resume", &id]), "resume");
    assert!(
        resumed.stdout.starts_with(&format!("job {job} resumed")),
        "{}",
        resumed.stdout
    );
    let done = wait_done(dir.path(), &addr, job, Duration::from_secs(60));
    assert_eq!(done["paused"], false, "{done}");
    // Paused, restarted and resumed, the image is still `tessera render`'s, byte for
    // byte.
    let image = common::fetch(dir.path(), &addr, job, "paused.png");
    let reference = common::render_reference(dir.path(), &seed, "reference.png", &args[1..]);
    common::assert_same_png(&image, &reference, "the paused and resumed job");

    let refused = client(dir.path(), &addr, &["pause", &id]);
    assert_eq!(refused.status.code(), Some(1), "{}", refused.stderr);
    assert_eq!(
        refused.stderr.trim(),
        format!(
            "error: job {job} cannot be paused: it is done, only a queued or running job can be"
        )
    );
    let json = client(dir.path(), &addr, &["pause", &id, "--json"]);
    assert!(!json.status.success());
    let json: serde_json::Value = serde_json::from_str(json.stdout.trim()).unwrap();
    assert!(
        json["error"].as_str().unwrap().contains("cannot be paused"),
        "{json}"
    );
}

#[test]
fn a_new_priority_is_stored_and_shown_and_an_ended_job_refuses_it() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (mut coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "first.log");
    let seed = scene_path("seed.json");
    let args = [
        seed.as_str(),
        "--width",
        "64",
        "--height",
        "48",
        "--aa",
        "1",
    ];
    let job = submit(dir.path(), &addr, &args);
    let id = job.to_string();
    let set = ok(
        client(dir.path(), &addr, &["priority", &id, "-5"]),
        "priority",
    );
    assert_eq!(
        set.stdout.trim(),
        format!("job {job} now has priority -5: its next tiles go out by it")
    );
    let json = ok(
        client(dir.path(), &addr, &["priority", &id, "7", "--json"]),
        "priority --json",
    );
    let json: serde_json::Value = serde_json::from_str(json.stdout.trim()).unwrap();
    assert_eq!(json["priority"], 7, "{json}");

    // Stored: a restarted coordinator keeps it.
    coordinator.kill9();
    let (_coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "second.log");
    let status = common::try_status(dir.path(), &addr, job).expect("status");
    assert_eq!(status["priority"], 7, "{status}");

    let _worker = start_worker(dir.path(), &addr, "w1");
    wait_done(dir.path(), &addr, job, Duration::from_secs(60));
    let refused = client(dir.path(), &addr, &["priority", &id, "1"]);
    assert_eq!(refused.status.code(), Some(1), "{}", refused.stderr);
    assert_eq!(
        refused.stderr.trim(),
        format!(
            "error: job {job} cannot be given a new priority: it is done, only a queued or \
             running job can be"
        )
    );
}

/// The workers as `tessera workers --json` lists them.
fn workers_json(dir: &std::path::Path, addr: &str) -> Vec<serde_json::Value> {
    let run = ok(client(dir, addr, &["workers", "--json"]), "workers --json");
    serde_json::from_str(run.stdout.trim()).expect("workers --json is a JSON array")
}

fn worker_named<'a>(workers: &'a [serde_json::Value], name: &str) -> Option<&'a serde_json::Value> {
    workers.iter().find(|w| w["name"] == name)
}

fn status_json(dir: &std::path::Path, addr: &str, job: u64) -> serde_json::Value {
    let run = ok(
        client(dir, addr, &["status", &job.to_string(), "--json"]),
        "status --json",
    );
    serde_json::from_str(run.stdout.trim()).expect("status --json is JSON")
}

#[test]
fn a_disabled_machine_gets_no_tiles_across_a_restart_until_enabled_and_a_drained_worker_exits() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let (coordinator, addr) = common::start_restartable_coordinator(dir.path());

    // Mistaken names are one line saying what to give.
    for action in ["drain", "disable", "enable"] {
        let run = client(dir.path(), &addr, &["workers", action, "nobody"]);
        assert!(!run.status.success(), "workers {action} nobody succeeded");
        assert_eq!(
            run.stderr.trim(),
            "error: no worker \"nobody\" is connected: give an id or a name from tessera workers",
            "workers {action}"
        );
    }

    let mut worker = common::start_worker_with(dir.path(), &addr, "box", &[]);
    // A slow machine: 5 % of a core, as an operator would limit it (needs root).
    let _slow = match localfarm::CpuLimit::apply(worker.pid(), 0.05) {
        Ok(limit) => limit,
        Err(e) => {
            return localfarm::unprivileged(
                "a_disabled_machine_gets_no_tiles_across_a_restart_until_enabled_and_a_drained_worker_exits",
                &e,
            )
        }
    };
    poll("the worker to join", Duration::from_secs(30), || {
        worker_named(&workers_json(dir.path(), &addr), "box").map(drop)
    });
    let run = ok(
        client(dir.path(), &addr, &["workers", "disable", "box"]),
        "workers disable",
    );
    assert!(
        run.stdout.starts_with("worker box disabled"),
        "{}",
        run.stdout
    );
    let listed = workers_json(dir.path(), &addr);
    let boxed = worker_named(&listed, "box").unwrap();
    assert_eq!(boxed["disabled"], true);
    assert_eq!(boxed["draining"], false);
    let shown = ok(client(dir.path(), &addr, &["workers"]), "workers");
    assert!(shown.stdout.contains(", DISABLED"), "{}", shown.stdout);

    // A job waits, and every listing says why.
    let seed = scene_path("seed.json");
    let job = submit(
        dir.path(),
        &addr,
        &[
            &seed, "--width", "64", "--height", "48", "--aa", "1", "--tile", "16",
        ],
    );
    std::thread::sleep(Duration::from_millis(1500));
    let status = status_json(dir.path(), &addr, job);
    assert_eq!(
        status["tiles_done"], 0,
        "a disabled machine rendered: {status}"
    );
    let warning = status["warning"]
        .as_str()
        .expect("status --json has a warning");
    assert!(
        warning.starts_with("no worker can take tiles: all 1 connected are disabled"),
        "{warning}"
    );
    let listed = ok(client(dir.path(), &addr, &["list"]), "list");
    assert_eq!(
        listed.stderr.trim(),
        format!("warning: {warning}"),
        "list says it once"
    );
    let shown = ok(
        client(dir.path(), &addr, &["status", &job.to_string()]),
        "status",
    );
    assert_eq!(shown.stderr.trim(), format!("warning: {warning}"));

    // The disable is stored: a restarted coordinator keeps the machine disabled.
    drop(coordinator);
    let coordinator = common::restart_coordinator(dir.path(), &addr, &[]);
    let listed = poll("the worker to come back", Duration::from_secs(60), || {
        let listed = workers_json(dir.path(), &addr);
        worker_named(&listed, "box").is_some().then_some(listed)
    });
    assert_eq!(worker_named(&listed, "box").unwrap()["disabled"], true);
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(status_json(dir.path(), &addr, job)["tiles_done"], 0);

    // Enabled by name, it renders the job, and the warning is gone.
    ok(
        client(dir.path(), &addr, &["workers", "enable", "box"]),
        "workers enable",
    );
    let status = wait_done(dir.path(), &addr, job, Duration::from_secs(120));
    assert!(status["warning"].is_null(), "{status}");

    // Drained by id: it finishes and exits 0, and does not come back.
    let id = worker_named(&workers_json(dir.path(), &addr), "box").unwrap()["id"]
        .as_u64()
        .unwrap();
    let run = ok(
        client(dir.path(), &addr, &["workers", "drain", &id.to_string()]),
        "workers drain",
    );
    assert!(run.stdout.contains("draining"), "{}", run.stdout);
    let exit = worker
        .wait_exit(Duration::from_secs(30))
        .expect("the drained worker did not exit");
    assert!(exit.success(), "the drained worker exited with {exit}");
    poll("the worker to be gone", Duration::from_secs(10), || {
        workers_json(dir.path(), &addr).is_empty().then_some(())
    });

    // With no worker left, a waiting submission says so once, after a few seconds.
    let job = submit(
        dir.path(),
        &addr,
        &[&seed, "--width", "32", "--height", "32"],
    );
    let listed = ok(client(dir.path(), &addr, &["list"]), "list");
    assert_eq!(
        listed.stderr.trim(),
        "warning: no worker is connected: queued and running jobs wait until one connects"
    );
    let mut waiting = common::spawn_tessera(
        dir.path(),
        &[
            "submit",
            &seed,
            "--wait",
            "-o",
            "w.png",
            "--coordinator",
            &addr,
        ],
        "wait.log",
    );
    let said = poll("submit --wait to warn", Duration::from_secs(20), || {
        let log = waiting.log_text();
        log.contains("warning: ").then_some(log)
    });
    // Once, after a few seconds, and it keeps waiting.
    std::thread::sleep(Duration::from_millis(1500));
    assert!(waiting.is_running(), "the wait ended without a worker");
    let log = waiting.log_text();
    let warnings: Vec<&str> = log.lines().filter(|l| l.starts_with("warning: ")).collect();
    assert_eq!(
        warnings,
        vec![format!(
            "warning: job {}: no worker is connected: queued and running jobs wait until one \
             connects",
            job + 1
        )],
        "{said}"
    );
    waiting.kill9();
    drop(coordinator);
}

/// `tessera events JOB --json`, parsed: (kind, detail) of each event, in order, and
/// checks that the numbers increase.
fn events(dir: &std::path::Path, addr: &str, job: u64) -> Vec<(String, String)> {
    let run = ok(
        client(dir, addr, &["events", &job.to_string(), "--json"]),
        "events --json",
    );
    let value: serde_json::Value = serde_json::from_str(run.stdout.trim()).unwrap();
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
fn tiles_of(events: &[(String, String)], kind: &str) -> Vec<u32> {
    events
        .iter()
        .filter(|(k, _)| k == kind)
        .filter_map(|(_, d)| d.strip_prefix("tile ")?.split(' ').next()?.parse().ok())
        .collect()
}

#[test]
fn names_submitters_and_the_queue_wait_are_shown_and_the_rate_leaves_the_wait_out() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (_coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "coordinator.log");
    let seed = scene_path("seed.json");
    let small = ["--width", "64", "--height", "48", "--aa", "2"];
    let before = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64;
    let mut args = vec![seed.as_str()];
    args.extend(small);
    args.extend(["--name", "night shot", "--submitter", "ann@studio"]);
    let named = submit(dir.path(), &addr, &args);
    let mut args = vec![seed.as_str()];
    args.extend(small);
    let plain = submit(dir.path(), &addr, &args);

    // No worker yet: both wait in the queue.
    let listed = ok(
        client(dir.path(), &addr, &["list", "--json"]),
        "list --json",
    );
    let jobs: serde_json::Value = serde_json::from_str(listed.stdout.trim()).unwrap();
    let job = |id: u64| {
        jobs.as_array()
            .unwrap()
            .iter()
            .find(|j| j["id"] == id)
            .unwrap()
            .clone()
    };
    let first = job(named);
    assert_eq!(first["name"], "night shot", "{first}");
    assert_eq!(first["submitter"], "ann@studio", "{first}");
    assert_eq!(first["submitted_from"], "127.0.0.1", "{first}");
    assert!(first["queued_ms"].is_null(), "{first}");
    let at = first["submitted_unix_ms"].as_u64().unwrap();
    assert!(at >= before && at < before + 60_000, "{at} vs {before}");
    let second = job(plain);
    assert_eq!(
        second["name"], "seed",
        "the scene's stem by default: {second}"
    );
    assert!(
        second["submitter"].as_str().unwrap().contains('@'),
        "$USER@hostname by default: {second}"
    );
    let table = ok(client(dir.path(), &addr, &["list"]), "list");
    let lines: Vec<&str> = table.stdout.lines().collect();
    assert_eq!(lines.len(), 3, "{}", table.stdout);
    for column in [
        "ID",
        "STATE",
        "NAME",
        "SUBMITTER",
        "FROM",
        "SUBMITTED (UTC)",
        "QUEUED",
    ] {
        assert!(lines[0].contains(column), "{column}: {}", lines[0]);
    }
    assert!(
        lines[1].contains("night shot") && lines[1].contains("ann@studio"),
        "{}",
        lines[1]
    );
    assert!(lines[1].contains("127.0.0.1"), "{}", lines[1]);

    // `submit --wait` of a job that waits: its summary leaves the wait out of the rate.
    let mut wait_args = vec!["submit", seed.as_str(), "--wait", "-o", "waited.png"];
    wait_args.extend(small);
    wait_args.extend(["--coordinator", addr.as_str()]);
    let mut waiting = common::spawn_tessera(dir.path(), &wait_args, "wait.log");
    std::thread::sleep(Duration::from_secs(3));
    let _worker = start_worker(dir.path(), &addr, "w1");
    let exit = waiting
        .wait_exit(Duration::from_secs(60))
        .expect("submit --wait did not end");
    let said = waiting.log_text();
    assert!(exit.success(), "{said}");
    let summary = said.lines().last().unwrap_or_default();
    let queued: f64 = summary
        .split(" after ")
        .nth(1)
        .and_then(|rest| rest.split(" s in the queue").next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no queue wait in {summary:?}"));
    assert!(queued >= 2.5, "{summary}");
    let rendered: f64 = summary
        .split("rendered in ")
        .nth(1)
        .and_then(|rest| rest.split(" s").next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no render time in {summary:?}"));
    assert!(rendered < queued, "{summary}");

    let done = wait_done(dir.path(), &addr, named, Duration::from_secs(60));
    let queued_ms = done["queued_ms"].as_u64().expect("queued_ms once started");
    assert!(queued_ms >= 2_500, "{done}");
    assert!(done["elapsed_ms"].as_u64().unwrap() >= queued_ms, "{done}");
    let line = ok(
        client(dir.path(), &addr, &["status", &named.to_string()]),
        "status",
    );
    assert!(line.stdout.contains("in the queue"), "{}", line.stdout);
    assert!(
        line.stdout.contains("\"night shot\" by ann@studio"),
        "{}",
        line.stdout
    );
    // job.json's rate counts rendering time only.
    let meta: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(data.join(format!("jobs/{named}/job.json"))).unwrap(),
    )
    .unwrap();
    let rays = meta["rays"].as_f64().unwrap();
    let wall = meta["wall_time_ms"].as_f64().unwrap() / 1000.0;
    let rate = meta["rays_per_second"].as_f64().unwrap();
    assert!(rate > 2.0 * rays / wall, "{meta}");
}

#[test]
fn a_jobs_events_tell_what_happened_and_survive_a_restart() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (mut coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "first.log");
    let seed = scene_path("seed.json");
    let job = submit(
        dir.path(),
        &addr,
        &[
            &seed, "--width", "64", "--height", "48", "--aa", "1", "--tile", "16", "--name", "ev",
        ],
    );
    let id = job.to_string();
    ok(client(dir.path(), &addr, &["pause", &id]), "pause");
    ok(
        client(dir.path(), &addr, &["priority", &id, "3"]),
        "priority",
    );
    ok(client(dir.path(), &addr, &["resume", &id]), "resume");
    let _worker = start_worker(dir.path(), &addr, "w1");
    wait_done(dir.path(), &addr, job, Duration::from_secs(60));
    let seen = events(dir.path(), &addr, job);
    let kinds: Vec<&str> = seen.iter().map(|(k, _)| k.as_str()).collect();
    assert_eq!(
        kinds[..4],
        ["submitted", "paused", "priority", "resumed"],
        "{seen:?}"
    );
    assert_eq!(kinds[4], "started", "{seen:?}");
    assert_eq!(kinds.last(), Some(&"done"), "{seen:?}");
    assert!(
        seen[0].1.contains("\"ev\"") && seen[0].1.contains("127.0.0.1"),
        "{seen:?}"
    );
    assert!(
        seen[2].1.contains("0 -> 3") && seen[2].1.contains("127.0.0.1"),
        "{seen:?}"
    );
    let mut done = tiles_of(&seen, "tile_done");
    done.sort_unstable();
    assert_eq!(done, (0..12).collect::<Vec<u32>>(), "{seen:?}");
    assert!(
        seen.iter()
            .filter(|(k, _)| k == "tile_done")
            .all(|(_, d)| d.contains("by w1")),
        "{seen:?}"
    );
    assert!(tiles_of(&seen, "tile_assigned").len() >= 12, "{seen:?}");

    // Stored: a coordinator killed and restarted has the same log.
    coordinator.kill9();
    let (_coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "second.log");
    assert_eq!(events(dir.path(), &addr, job), seen);
    let status = common::try_status(dir.path(), &addr, job).unwrap();
    assert_eq!(status["name"], "ev", "{status}");
    assert_eq!(status["submitted_from"], "127.0.0.1", "{status}");
    let text = ok(client(dir.path(), &addr, &["events", &id]), "events");
    assert_eq!(text.stdout.lines().count(), seen.len(), "{}", text.stdout);
    assert!(
        text.stdout.lines().all(|l| l.starts_with("20")),
        "{}",
        text.stdout
    );
    let missing = client(dir.path(), &addr, &["events", "999"]);
    assert_eq!(missing.status.code(), Some(1));
    assert_eq!(
        missing.stderr.trim(),
        "error: no job 999 on this coordinator"
    );

    // An adaptive job's passes are in its log.
    let adaptive = submit(
        dir.path(),
        &addr,
        &[
            &seed,
            "--width",
            "64",
            "--height",
            "48",
            "--aa",
            "4",
            "--sampler",
            "adaptive",
            "--target-error",
            "2",
        ],
    );
    let _again = start_worker(dir.path(), &addr, "w2");
    wait_done(dir.path(), &addr, adaptive, Duration::from_secs(60));
    let passes = events(dir.path(), &addr, adaptive);
    assert!(
        passes
            .iter()
            .any(|(k, d)| k == "adaptive_pass" && d.contains("estimated error")),
        "{passes:?}"
    );
    assert_eq!(
        passes.last().map(|(k, _)| k.as_str()),
        Some("done"),
        "{passes:?}"
    );

    // Deleted with its job.
    ok(client(dir.path(), &addr, &["delete", &id]), "delete");
    let db = rusqlite::Connection::open(data.join("tessera.db")).unwrap();
    let left: i64 = db
        .query_row(
            "SELECT count(*) FROM events WHERE job = ?1",
            [job as i64],
            |r| r.get(0),
        )
        .unwrap();
    assert_eq!(left, 0);
}

/// The settings of the seed job the retry and requeue tests stop half way: 24 tiles.
const SMALL_JOB: [&str; 8] = [
    "--width", "96", "--height", "64", "--aa", "3", "--tile", "16",
];

/// A worker slow enough (400 times) that a job of [`SMALL_JOB`] is stopped half way:
/// returned once two of its tiles are in.
fn slow_worker_past_two_tiles(dir: &std::path::Path, addr: &str, job: u64) -> Daemon {
    let worker = common::start_worker_with(dir, addr, "slow", &["--throttle", "400"]);
    poll("tiles of the job", Duration::from_secs(60), || {
        let status = common::try_status(dir, addr, job)?;
        (common::tiles_done(&status) >= 2).then_some(())
    });
    worker
}

#[test]
fn a_cancelled_job_retried_keeps_its_tiles_and_renders_the_same_image() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (_coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "coordinator.log");
    let seed = scene_path("seed.json");
    let mut args = vec![seed.as_str()];
    args.extend(SMALL_JOB);
    let job = submit(dir.path(), &addr, &args);
    let id = job.to_string();
    let refused = client(dir.path(), &addr, &["retry", &id]);
    assert_eq!(refused.status.code(), Some(1));
    assert_eq!(
        refused.stderr.trim(),
        format!(
            "error: job {job} cannot be retried: it is queued, only a failed or cancelled \
             job can be"
        )
    );
    // A slow worker: some tiles are in when the job is cancelled, not all.
    let mut worker = slow_worker_past_two_tiles(dir.path(), &addr, job);
    ok(client(dir.path(), &addr, &["cancel", &id]), "cancel");
    worker.kill9();
    let cancelled = common::try_status(dir.path(), &addr, job).unwrap();
    assert_eq!(cancelled["state"], "cancelled");
    let kept = common::tiles_done(&cancelled);
    assert!((2..24).contains(&kept), "{cancelled}");

    let retried = ok(
        client(dir.path(), &addr, &["retry", &id, "--json"]),
        "retry",
    );
    let retried: serde_json::Value = serde_json::from_str(retried.stdout.trim()).unwrap();
    // It had started: it shows running (until it ends), though no tile is out yet.
    assert_eq!(retried["state"], "running", "{retried}");
    assert_eq!(retried["paused"], false, "{retried}");
    let back = common::tiles_done(&retried);
    assert!(back >= kept, "{back} of {kept} tiles kept: {retried}");
    let _worker = start_worker(dir.path(), &addr, "w2");
    wait_done(dir.path(), &addr, job, Duration::from_secs(120));
    let seen = events(dir.path(), &addr, job);
    let retry = seen
        .iter()
        .position(|(k, _)| k == "retried")
        .expect("a retried event");
    assert!(seen[retry].1.contains("127.0.0.1"), "{seen:?}");
    // Tiles stored before the cancel are not rendered again.
    let before: Vec<u32> = tiles_of(&seen[..retry], "tile_done");
    let after: Vec<u32> = tiles_of(&seen[retry..], "tile_done");
    assert_eq!(before.len() as u64, back, "{seen:?}");
    assert!(before.iter().all(|t| !after.contains(t)), "{seen:?}");
    assert_eq!(before.len() + after.len(), 24, "{seen:?}");
    let image = common::fetch(dir.path(), &addr, job, "retried.png");
    let reference = common::render_reference(dir.path(), &seed, "reference.png", &SMALL_JOB[..6]);
    common::assert_same_png(&image, &reference, "the cancelled and retried job");

    let again = client(dir.path(), &addr, &["retry", &id]);
    assert_eq!(again.status.code(), Some(1));
    assert_eq!(
        again.stderr.trim(),
        format!(
            "error: job {job} cannot be retried: it is done and its image is final (submit \
             the scene again to render it anew)"
        )
    );
    let unknown = client(dir.path(), &addr, &["retry", "999"]);
    assert_eq!(
        unknown.stderr.trim(),
        "error: no job 999 on this coordinator"
    );
}

#[test]
fn requeued_tiles_are_rendered_again_and_the_image_is_the_same() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (_coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "coordinator.log");
    let seed = scene_path("seed.json");
    let mut args = vec![seed.as_str()];
    args.extend(SMALL_JOB);
    let job = submit(dir.path(), &addr, &args);
    let id = job.to_string();
    let mut worker = slow_worker_past_two_tiles(dir.path(), &addr, job);
    ok(client(dir.path(), &addr, &["pause", &id]), "pause");
    // What was out when it was paused comes in; then nothing moves.
    worker.kill9();
    std::thread::sleep(Duration::from_millis(500));
    let status = common::try_status(dir.path(), &addr, job).unwrap();
    let done_before = common::tiles_done(&status);
    let seen = events(dir.path(), &addr, job);
    let done = tiles_of(&seen, "tile_done");
    assert_eq!(done.len() as u64, done_before, "{seen:?}");

    for (bad, says) in [
        (
            vec!["24"],
            format!("error: job {job} has tiles 0 to 23: there is no tile 24"),
        ),
        (
            vec!["1", "99"],
            format!("error: job {job} has tiles 0 to 23: there is no tile 99"),
        ),
    ] {
        let mut all = vec!["requeue", id.as_str()];
        all.extend(bad.iter().copied());
        let run = client(dir.path(), &addr, &all);
        assert_eq!(run.status.code(), Some(1), "{bad:?}");
        assert_eq!(run.stderr.trim(), says);
    }
    let unknown = client(dir.path(), &addr, &["requeue", "999", "0"]);
    assert_eq!(
        unknown.stderr.trim(),
        "error: no job 999 on this coordinator"
    );

    // A done tile and one never rendered.
    let again = done[0];
    let fresh = (0..24).find(|t| !done.contains(t)).unwrap();
    let run = ok(
        client(
            dir.path(),
            &addr,
            &[
                "requeue",
                &id,
                &again.to_string(),
                &fresh.to_string(),
                "--json",
            ],
        ),
        "requeue",
    );
    let status: serde_json::Value = serde_json::from_str(run.stdout.trim()).unwrap();
    assert_eq!(common::tiles_done(&status), done_before - 1, "{status}");
    ok(client(dir.path(), &addr, &["resume", &id]), "resume");
    let _worker = start_worker(dir.path(), &addr, "w2");
    wait_done(dir.path(), &addr, job, Duration::from_secs(120));
    let seen = events(dir.path(), &addr, job);
    let at = seen
        .iter()
        .position(|(k, _)| k == "requeued")
        .expect("a requeued event");
    assert!(seen[at].1.contains("127.0.0.1"), "{seen:?}");
    assert!(
        tiles_of(&seen[at..], "tile_done").contains(&again),
        "tile {again} rendered again: {seen:?}"
    );
    let image = common::fetch(dir.path(), &addr, job, "requeued.png");
    let reference = common::render_reference(dir.path(), &seed, "reference.png", &SMALL_JOB[..6]);
    common::assert_same_png(&image, &reference, "the requeued job");

    let refused = client(dir.path(), &addr, &["requeue", &id, "0"]);
    assert_eq!(refused.status.code(), Some(1));
    assert_eq!(
        refused.stderr.trim(),
        format!(
            "error: job {job} cannot be requeued: it is done, only a queued or running job \
             can be"
        )
    );
}

#[test]
fn a_tile_past_its_lease_is_in_the_jobs_events_and_the_image_is_unchanged() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let seed = scene_path("seed.json");
    let settings = ["--width", "1600", "--height", "1200", "--aa", "2"];
    let mut args = vec![seed.as_str(), "--tile", "64"];
    args.extend(settings);
    let job = submit(dir.path(), &addr, &args);
    // A fast worker first: its tiles set the job's lease to about a second...
    let _fast = common::start_worker_with(dir.path(), &addr, "fast", &["--threads", "1"]);
    poll("the first tiles", Duration::from_secs(30), || {
        let status = common::try_status(dir.path(), &addr, job)?;
        (status["tiles_done"].as_u64()? >= 20).then_some(())
    });
    // ...which a worker taking 3000 times as long (seconds a tile) runs past.
    let _slow = common::start_worker_with(
        dir.path(),
        &addr,
        "slow",
        &["--threads", "1", "--throttle", "3000"],
    );
    wait_done(dir.path(), &addr, job, Duration::from_secs(120));
    let log = events(dir.path(), &addr, job);
    let expired: Vec<&String> = log
        .iter()
        .filter(|(kind, _)| kind == "tile_lease_expired")
        .map(|(_, detail)| detail)
        .collect();
    let kinds: std::collections::BTreeSet<&str> = log.iter().map(|(k, _)| k.as_str()).collect();
    assert!(
        !expired.is_empty() && expired.iter().all(|d| d.contains(" on slow for ")),
        "expiries {expired:?} among {} events of kinds {kinds:?}",
        log.len()
    );
    // Each expiry once, though the lease stays expired over many timeouts.
    let mut tiles: Vec<u32> = tiles_of(&log, "tile_lease_expired");
    let count = tiles.len();
    tiles.sort_unstable();
    tiles.dedup();
    assert_eq!(tiles.len(), count, "{expired:?}");

    let image = common::fetch(dir.path(), &addr, job, "farm.png");
    let reference = common::render_reference(dir.path(), &seed, "reference.png", &settings);
    common::assert_same_png(&image, &reference, "the job with an expired lease");
}
