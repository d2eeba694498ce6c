//! What a job shows of itself, through the clients and the status page's JSON, on a
//! farm of real `tessera` processes on 127.0.0.1: a job that did not finish shows no
//! error estimate, and both JSONs agree; jobs carry a name, a submitter and their queue
//! wait, which the rate leaves out; a job's events tell what happened, survive a
//! restart and go with it; a tile past its lease is among them.

use std::time::Duration;

use crate::support::{
    assert_same_png, client, events, exclusive, fetch, http_get, ok, orbit, poll, render_reference,
    scene_path, shared, spawn_tessera, start_coordinator, start_coordinator_in,
    start_coordinator_with_http, start_slow_worker, start_worker, start_worker_with, submit,
    tiles_done, tiles_of, tiles_total, try_status, wait_done, wait_for_workers, REGISTER_TIMEOUT,
};

#[test]
fn a_job_that_did_not_finish_shows_no_error_estimate_and_both_jsons_agree() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr, http) = start_coordinator_with_http(dir.path(), &[]);
    let _worker = start_worker(dir.path(), &addr, "w1");
    let page_job = |job: u64| page_job(&http, job);
    let seed = scene_path("seed.json");
    // Long enough to be cancelled with some of its tiles in.
    let job = submit(dir.path(), &addr, &[&seed, "--aa", "8", "--tile", "16"]);
    let running = poll("a tile of the job", Duration::from_secs(60), || {
        try_status(dir.path(), &addr, job).filter(|s| tiles_done(s) > 0)
    });
    // An estimate over the first tiles is over whichever part came first: none is
    // shown until every tile is in.
    assert!(tiles_done(&running) < tiles_total(&running), "{running}");
    assert!(running["estimated_error"].is_null(), "{running}");
    ok(
        client(dir.path(), &addr, &["cancel", &job.to_string()]),
        "cancel",
    );
    let status = try_status(dir.path(), &addr, job).unwrap();
    assert_eq!(status["state"], "cancelled");
    assert!(tiles_done(&status) > 0, "{status}");
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

/// Job `job` as the status page's JSON (`/api/status` on `http`) shows it.
fn page_job(http: &str, job: u64) -> serde_json::Value {
    let (code, body) = http_get(http, "/api/status").expect("the status page");
    assert_eq!(code, 200);
    let farm: serde_json::Value = serde_json::from_slice(&body).unwrap();
    farm["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .find(|j| j["id"] == job)
        .cloned()
        .unwrap_or_else(|| panic!("job {job} not on the page: {farm}"))
}

#[test]
fn a_sequences_samples_per_pixel_are_per_pixel_of_a_frame_on_the_page_as_in_status() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr, http) = start_coordinator_with_http(dir.path(), &[]);
    let _worker = start_worker(dir.path(), &addr, "w1");
    let scene = orbit();
    // Four frames of aa 2: 4 samples in each pixel of each frame (the sum over the
    // frames would read 16).
    let job = submit(
        dir.path(),
        &addr,
        &[
            &scene, "--frames", "1-4", "--width", "32", "--height", "24", "--aa", "2", "--tile",
            "16",
        ],
    );
    let status = wait_done(dir.path(), &addr, job, Duration::from_secs(120));
    assert_eq!(status["samples_per_pixel"].as_f64(), Some(4.0), "{status}");
    let page = page_job(&http, job);
    assert!(page["frames"].is_object(), "listed as a sequence: {page}");
    assert_eq!(page["samples_per_pixel"].as_f64(), Some(4.0), "{page}");
}

#[test]
fn the_time_left_half_way_is_in_a_sane_band_of_the_time_the_job_then_takes() {
    let _turn = exclusive();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let _worker = start_worker(dir.path(), &addr, "w1");
    let seed = scene_path("seed.json");
    // 1200 tiles of a few milliseconds each: seconds of rendering, read half way.
    let job = submit(
        dir.path(),
        &addr,
        &[
            &seed, "--width", "1280", "--height", "960", "--aa", "12", "--tile", "32",
        ],
    );
    let (half_way, at) = poll("half the job's tiles", Duration::from_secs(120), || {
        let status = try_status(dir.path(), &addr, job)?;
        assert_ne!(status["state"], "done", "done before it was seen half way");
        (tiles_done(&status) * 2 >= tiles_total(&status))
            .then(|| (status, std::time::Instant::now()))
    });
    let said = half_way["eta_ms"]
        .as_u64()
        .unwrap_or_else(|| panic!("no time left half way: {half_way}"));
    wait_done(dir.path(), &addr, job, Duration::from_secs(120));
    let took = at.elapsed().as_millis() as u64;
    // A band, not a timing: a shared machine's pace varies, but an estimate off by more
    // than a factor of 3 either way is not telling the time left.
    assert!(
        said <= took * 3 && took <= said * 3,
        "{said} ms left said half way, {took} ms taken: {half_way}"
    );
}

#[test]
fn names_submitters_and_the_queue_wait_are_shown_and_the_rate_leaves_the_wait_out() {
    let _turn = exclusive();
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
    // Newest first: the first job is the last row.
    assert!(
        lines[2].contains("night shot") && lines[2].contains("ann@studio"),
        "{}",
        lines[2]
    );
    assert!(lines[2].contains("127.0.0.1"), "{}", lines[2]);

    // `submit --wait` of a job that waits: its summary leaves the wait out of the rate.
    let mut wait_args = vec!["submit", seed.as_str(), "--wait", "-o", "waited.png"];
    wait_args.extend(small);
    wait_args.extend(["--coordinator", addr.as_str()]);
    let mut waiting = spawn_tessera(dir.path(), &wait_args, "wait.log");
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
    let _turn = shared();
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
    let status = try_status(dir.path(), &addr, job).unwrap();
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

#[test]
fn a_tile_past_its_lease_is_in_the_jobs_events_and_the_image_is_unchanged() {
    let _turn = exclusive();
    let dir = tempfile::tempdir().unwrap();
    // No audits: a tile of the fast worker's chosen for one could only be confirmed by
    // the slow one, seconds a tile, and the job would wait for it (it took from 4 to 14
    // s): this test is about leases.
    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &dir.path().join("data"),
        "127.0.0.1:0",
        &["--audit-share", "0"],
        "coordinator.log",
    );
    let test = "a_tile_past_its_lease_is_in_the_jobs_events_and_the_image_is_unchanged";
    // Both workers join before there is a job; the slow one is then limited to 1/200
    // of a core (seconds a tile) before it is given anything.
    let _fast = start_worker_with(dir.path(), &addr, "fast", &["--threads", "1"]);
    let Some(_slow) = start_slow_worker(
        test,
        dir.path(),
        &addr,
        "slow",
        1.0 / 200.0,
        &["--threads", "1"],
    ) else {
        return;
    };
    wait_for_workers(dir.path(), &addr, 2, REGISTER_TIMEOUT);
    let seed = scene_path("seed.json");
    // About 20 ms of one core a tile, 3.5 s or more in all on one thread. Each worker
    // takes tiles at once under the default lease; the fast one's first results set the
    // job's lease to about a second, which cuts the slow one's leases short: it runs
    // past them (each of its tiles takes seconds) with the job still seconds from its
    // end.
    let settings = ["--width", "1600", "--height", "1200", "--aa", "8"];
    let mut args = vec![seed.as_str(), "--tile", "64"];
    args.extend(settings);
    let submitted = std::time::Instant::now();
    let job = submit(dir.path(), &addr, &args);
    // The reference renders on the core the fast worker leaves idle (scoped, so that a
    // failed assertion still waits for its process).
    let reference_args = [&settings[..], &["--threads", "1"]].concat();
    let (took, reference) = std::thread::scope(|s| {
        let reference =
            s.spawn(|| render_reference(dir.path(), &seed, "reference.png", &reference_args));
        wait_done(dir.path(), &addr, job, Duration::from_secs(120));
        let took = submitted.elapsed();
        (
            took,
            reference.join().expect("the reference render panicked"),
        )
    });
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
    eprintln!(
        "{count} leases expired on the slow worker in a job of {:.1} s",
        took.as_secs_f64()
    );

    let image = fetch(dir.path(), &addr, job, "farm.png");
    assert_same_png(&image, &reference, "the job with an expired lease");
}
