//! Controlling jobs and machines on a farm of real `tessera` processes on 127.0.0.1:
//! cancelling twice is no error and a done job says why it cannot be; a paused job gets
//! no tiles, stays paused across a restart and resumes; a new priority is stored; a
//! disabled machine gets no tiles, across a coordinator restart, until enabled, and a
//! drained worker finishes and exits 0, the clients warning meanwhile that no worker can
//! take tiles; failed or cancelled jobs are retried and tiles requeued by hand, with the
//! image unchanged.

use std::path::Path;
use std::time::Duration;

use crate::support::{
    assert_same_png, client, events, exclusive, fetch, free_port, http_get, ok, poll,
    render_reference, restart_coordinator, scene_path, shared, spawn_tessera, start_coordinator,
    start_coordinator_in, start_restartable_coordinator, start_slow_worker, start_worker,
    status_json, submit, tiles_done, tiles_of, try_status, wait_done, worker_named, workers_json,
    Daemon,
};

#[test]
fn cancelling_a_cancelled_job_succeeds_and_a_done_one_says_why_not() {
    let _turn = shared();
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
fn a_paused_job_gets_no_tiles_stays_paused_across_a_restart_and_resumes() {
    let _turn = shared();
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
    let status = try_status(dir.path(), &addr, job).expect("status");
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
    let image = fetch(dir.path(), &addr, job, "paused.png");
    let reference = render_reference(dir.path(), &seed, "reference.png", &args[1..]);
    assert_same_png(&image, &reference, "the paused and resumed job");

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
    let _turn = shared();
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
    let status = try_status(dir.path(), &addr, job).expect("status");
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

#[test]
fn a_disabled_machine_gets_no_tiles_across_a_restart_until_enabled_and_a_drained_worker_exits() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (coordinator, addr) = start_restartable_coordinator(dir.path());

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

    // A slow machine (5 % of a core), so that it is still working when drained.
    let Some((mut worker, _slow)) = start_slow_worker(
        "a_disabled_machine_gets_no_tiles_across_a_restart_until_enabled_and_a_drained_worker_exits",
        dir.path(),
        &addr,
        "box",
        0.05,
        &[],
    ) else {
        return;
    };
    poll("the worker to join", Duration::from_secs(30), || {
        worker_named(&workers_json(dir.path(), &addr, &[]), "box").map(drop)
    });
    let run = ok(
        client(dir.path(), &addr, &["workers", "disable", "box"]),
        "workers disable",
    );
    assert!(
        run.stdout.starts_with("worker box (id ")
            && run.stdout.contains(", host 127.0.0.1) disabled"),
        "{}",
        run.stdout
    );
    let listed = workers_json(dir.path(), &addr, &[]);
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
    let coordinator = restart_coordinator(dir.path(), &addr, &[]);
    let listed = poll("the worker to come back", Duration::from_secs(60), || {
        let listed = workers_json(dir.path(), &addr, &[]);
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
    let id = worker_named(&workers_json(dir.path(), &addr, &[]), "box").unwrap()["id"]
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
        workers_json(dir.path(), &addr, &[])
            .is_empty()
            .then_some(())
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
    let mut waiting = spawn_tessera(
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

/// The settings of the seed job the retry and requeue tests stop half way: 24 tiles of
/// a few milliseconds of one core each, well above what a CPU limit's accounting can
/// let slip through at once.
const SMALL_JOB: [&str; 8] = [
    "--width", "96", "--height", "64", "--aa", "16", "--tile", "16",
];

/// The heartbeat timeout of a coordinator with a worker on 1/400 of a core: its
/// heartbeats share that quota with its render thread and can come seconds late, which
/// the default of 5 s would take for a lost worker (these tests are about cancelling and
/// retrying, not about losing one; a killed worker is still seen at once, by its closed
/// connection).
const SLOW_HEARTBEATS: [&str; 2] = ["--heartbeat-timeout-ms", "60000"];

/// A worker slow enough (1/400 of a core) that a job of [`SMALL_JOB`] is stopped half
/// way: returned, with its limit, once two of its tiles are in; `None` where `test`
/// cannot limit a process and is skipped.
///
/// The worker starts and joins at full speed while the job is paused, and is limited
/// before the job resumes: so it renders no tile at full speed, and the seconds its
/// start would take on 1/400 of a core (more on a loaded machine) are not spent.
fn slow_worker_past_two_tiles(
    test: &str,
    dir: &Path,
    addr: &str,
    job: u64,
) -> Option<(Daemon, localfarm::CpuLimit)> {
    let id = job.to_string();
    ok(client(dir, addr, &["pause", &id]), "pause");
    let slow = start_slow_worker(test, dir, addr, "slow", 1.0 / 400.0, &[])?;
    ok(client(dir, addr, &["resume", &id]), "resume");
    poll("tiles of the job", Duration::from_secs(60), || {
        let status = try_status(dir, addr, job)?;
        (tiles_done(&status) >= 2).then_some(())
    });
    Some(slow)
}

/// A job of [`SMALL_JOB`] cancelled once a slow worker has returned two of its tiles,
/// the worker then killed: its id, or `None` where `test` is skipped
/// ([`slow_worker_past_two_tiles`]).
fn cancelled_part_way(test: &str, dir: &Path, addr: &str) -> Option<u64> {
    let seed = scene_path("seed.json");
    let mut args = vec![seed.as_str()];
    args.extend(SMALL_JOB);
    let job = submit(dir, addr, &args);
    let (mut worker, _slow) = slow_worker_past_two_tiles(test, dir, addr, job)?;
    ok(client(dir, addr, &["cancel", &job.to_string()]), "cancel");
    worker.kill9();
    Some(job)
}

#[test]
fn a_cancelled_job_retried_keeps_its_tiles_and_renders_the_same_image() {
    let _turn = exclusive();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &data,
        "127.0.0.1:0",
        &SLOW_HEARTBEATS,
        "coordinator.log",
    );
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
    let Some((mut worker, _slow)) = slow_worker_past_two_tiles(
        "a_cancelled_job_retried_keeps_its_tiles_and_renders_the_same_image",
        dir.path(),
        &addr,
        job,
    ) else {
        return;
    };
    ok(client(dir.path(), &addr, &["cancel", &id]), "cancel");
    worker.kill9();
    let cancelled = try_status(dir.path(), &addr, job).unwrap();
    assert_eq!(cancelled["state"], "cancelled");
    let kept = tiles_done(&cancelled);
    assert!((2..24).contains(&kept), "{cancelled}");

    let retried = ok(
        client(dir.path(), &addr, &["retry", &id, "--json"]),
        "retry",
    );
    let retried: serde_json::Value = serde_json::from_str(retried.stdout.trim()).unwrap();
    // It had started: it shows running (until it ends), though no tile is out yet.
    assert_eq!(retried["state"], "running", "{retried}");
    assert_eq!(retried["paused"], false, "{retried}");
    let back = tiles_done(&retried);
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
    let image = fetch(dir.path(), &addr, job, "retried.png");
    let reference = render_reference(dir.path(), &seed, "reference.png", &SMALL_JOB[..6]);
    assert_same_png(&image, &reference, "the cancelled and retried job");

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

/// Job `job`'s tiles done as `status --json`, `list --json` and the status page's JSON
/// (on `http`) show them, and `status`'s line.
fn tiles_shown(dir: &Path, addr: &str, http: &str, job: u64) -> ([u64; 3], String) {
    let status = tiles_done(&status_json(dir, addr, job));
    let listed = ok(client(dir, addr, &["list", "--json"]), "list --json");
    let listed: serde_json::Value = serde_json::from_str(listed.stdout.trim()).unwrap();
    let listed = listed
        .as_array()
        .unwrap()
        .iter()
        .find(|j| j["id"] == job)
        .map(tiles_done)
        .unwrap_or_else(|| panic!("job {job} not listed: {listed}"));
    let (code, body) = http_get(http, "/api/status").expect("the status page");
    assert_eq!(code, 200);
    let farm: serde_json::Value = serde_json::from_slice(&body).unwrap();
    let page = farm["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .find(|j| j["id"] == job)
        .map(tiles_done)
        .unwrap_or_else(|| panic!("job {job} not on the page: {farm}"));
    let line = ok(client(dir, addr, &["status", &job.to_string()]), "status");
    ([status, listed, page], line.stdout.trim().to_owned())
}

#[test]
fn a_cancelled_job_shows_its_tiles_after_a_restart_and_a_retry_keeps_them() {
    let _turn = exclusive();
    let dir = tempfile::tempdir().unwrap();
    let http = format!("127.0.0.1:{}", free_port());
    let (mut coordinator, addr) = start_coordinator(
        dir.path(),
        &dir.path().join("data"),
        &format!("127.0.0.1:{}", free_port()),
        &["--http", &http, SLOW_HEARTBEATS[0], SLOW_HEARTBEATS[1]],
        "coordinator-1.log",
    );
    let Some(job) = cancelled_part_way(
        "a_cancelled_job_shows_its_tiles_after_a_restart_and_a_retry_keeps_them",
        dir.path(),
        &addr,
    ) else {
        return;
    };
    let id = job.to_string();
    // Tiles already on their way to the disk when it was cancelled still count: the
    // figures are read once they have settled.
    std::thread::sleep(Duration::from_millis(500));
    let (before, line) = tiles_shown(dir.path(), &addr, &http, job);
    let kept = before[0];
    assert!((2..24).contains(&kept), "{line}");
    assert_eq!(before, [kept; 3], "status, list and page: {line}");
    assert!(
        line.starts_with(&format!("job {job}: cancelled, {kept}/24 tiles")),
        "{line}"
    );

    coordinator.kill9();
    let _coordinator = restart_coordinator(dir.path(), &addr, &["--http", &http]);
    let (after, line) = tiles_shown(dir.path(), &addr, &http, job);
    assert_eq!(
        after, before,
        "after the restart, status, list and page: {line}"
    );
    assert!(
        line.starts_with(&format!("job {job}: cancelled, {kept}/24 tiles")),
        "{line}"
    );
    let retried = ok(client(dir.path(), &addr, &["retry", &id]), "retry");
    assert_eq!(
        retried.stdout.trim(),
        format!("job {job} is back in the queue: {kept} of 24 tiles kept, the others are rendered")
    );
}

#[test]
fn a_retried_jobs_elapsed_time_and_wait_count_from_its_retry_across_a_restart() {
    let _turn = exclusive();
    let dir = tempfile::tempdir().unwrap();
    // As `start_restartable_coordinator`, with the slow worker's heartbeats allowed.
    let listen = format!("127.0.0.1:{}", free_port());
    let (mut coordinator, addr) = start_coordinator(
        dir.path(),
        &dir.path().join("data"),
        &listen,
        &SLOW_HEARTBEATS,
        "coordinator-1.log",
    );
    let Some(job) = cancelled_part_way(
        "a_retried_jobs_elapsed_time_and_wait_count_from_its_retry_across_a_restart",
        dir.path(),
        &addr,
    ) else {
        return;
    };
    let id = job.to_string();
    // It sits cancelled a while: that is not its time.
    std::thread::sleep(Duration::from_secs(2));
    let before_retry = std::time::Instant::now();
    let retried = ok(
        client(dir.path(), &addr, &["retry", &id, "--json"]),
        "retry",
    );
    let retried: serde_json::Value = serde_json::from_str(retried.stdout.trim()).unwrap();
    let since_retry = |status: &serde_json::Value| {
        let elapsed = status["elapsed_ms"].as_u64().unwrap();
        assert!(
            u128::from(elapsed) <= before_retry.elapsed().as_millis(),
            "elapsed {elapsed} ms, counted from before the retry: {status}"
        );
    };
    since_retry(&retried);
    // No tile out in this run yet: no wait known (the first run's is not this one's).
    assert!(retried["queued_ms"].is_null(), "{retried}");
    // Stored with the job: a restart counts from the retry too.
    coordinator.kill9();
    let _coordinator = restart_coordinator(dir.path(), &addr, &[]);
    since_retry(&status_json(dir.path(), &addr, job));
    let _worker = start_worker(dir.path(), &addr, "w2");
    let done = wait_done(dir.path(), &addr, job, Duration::from_secs(120));
    since_retry(&done);
    let queued = done["queued_ms"].as_u64().expect("the run's wait");
    assert!(queued <= done["elapsed_ms"].as_u64().unwrap(), "{done}");
}

#[test]
fn requeued_tiles_are_rendered_again_and_the_image_is_the_same() {
    let _turn = exclusive();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (_coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "coordinator.log");
    let seed = scene_path("seed.json");
    let mut args = vec![seed.as_str()];
    args.extend(SMALL_JOB);
    let job = submit(dir.path(), &addr, &args);
    let id = job.to_string();
    let Some((mut worker, _slow)) = slow_worker_past_two_tiles(
        "requeued_tiles_are_rendered_again_and_the_image_is_the_same",
        dir.path(),
        &addr,
        job,
    ) else {
        return;
    };
    ok(client(dir.path(), &addr, &["pause", &id]), "pause");
    // What was out when it was paused comes in; then nothing moves.
    worker.kill9();
    std::thread::sleep(Duration::from_millis(500));
    let status = try_status(dir.path(), &addr, job).unwrap();
    let done_before = tiles_done(&status);
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
    assert_eq!(tiles_done(&status), done_before - 1, "{status}");
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
    let image = fetch(dir.path(), &addr, job, "requeued.png");
    let reference = render_reference(dir.path(), &seed, "reference.png", &SMALL_JOB[..6]);
    assert_same_png(&image, &reference, "the requeued job");

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
