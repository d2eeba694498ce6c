//! The coordinator killed, stopped, paused and restarted mid-job, and run for many
//! jobs:
//!
//! - **Killed** (`kill -9`) and restarted on the same port and data directory: the job
//!   keeps its id and the tiles recorded before the kill, the workers come back by
//!   themselves, and only the missing tiles are rendered; every tile `status` reported
//!   done before the kill is still done after the restart.
//! - **Stopped** (`SIGTERM`): it exits 0 within 12 s, a job submitted meanwhile is
//!   refused without harm, and after a restart the job resumes.
//! - **Paused** (`SIGSTOP`) for 4.5 s, past its 3 s heartbeat timeout, then continued:
//!   it reads what the workers sent meanwhile before expiring anyone, so it drops no
//!   worker.
//! - **Killed and restarted under a `submit --wait`**: the client has printed
//!   `submitted job N` at once, rides through the restart and exits 0 with the image.
//! - **Memory over 15 sequential 1080p jobs**: the coordinator keeps no finished image
//!   in memory, so its resident set after 15 jobs is about that after 4; the database
//!   gives the tile blobs' space back.
//! - **A job restored after a restart** reports its true state (`running`), its time
//!   since the original submission, and a believable rays per second.

use std::path::Path;
use std::thread;
use std::time::{Duration, Instant};

use serde_json::Value;

use super::{Farm, JOB, JOB_TIMEOUT, MEDIUM};
use crate::support::{
    self, assert_same_png, client, connections, exclusive, ok, poll, render_args, render_reference,
    rss_kib, scene_path, spawn_tessera, tiles_done, tiles_total, Daemon, Findings,
};

/// Some 5 CPU-seconds (1,102 tiles of 64): seconds of it left on one worker when the
/// coordinator is stopped after its first tiles, whose reference takes as long on the
/// second core.
const VERY_LONG: &[&str] = &["--width", "2400", "--height", "1800", "--aa", "5"];
/// A 1080p frame in about 0.2 CPU-seconds, whose PNG is about 0.5 MB.
const FRAME_1080P: &[&str] = &["--width", "1920", "--height", "1080", "--aa", "1"];

/// Starts a farm of two workers on a fixed port, submits [`MEDIUM`], kills the
/// coordinator (SIGKILL) as soon as `status` reports a fifth of the tiles done, and
/// restarts it on the same port and data directory. Returns the farm, the job, the
/// tiles reported done just before the kill and the job's status just after the
/// restart.
fn kill_coordinator_mid_job() -> (Farm, u64, u64, Value) {
    let mut farm = Farm::restartable(&["w1", "w2"]);
    let lights = scene_path("lights.json");
    let job = farm.submit(&lights, &[&["--tile", "32"][..], MEDIUM].concat());
    let total = tiles_total(&farm.status(job));
    let before = farm.wait_for_tiles(job, total / 5)["tiles_done"]
        .as_u64()
        .expect("tiles_done");
    farm.coordinator.kill9();
    farm.restart_coordinator();
    let status = farm.status(job);
    (farm, job, before, status)
}

/// The coordinator killed with SIGKILL mid-job and restarted on the same port and
/// data directory: the job (same id) is known at once with the tiles recorded before
/// the kill, the workers reconnect by themselves, only the missing tiles are rendered,
/// and the image is `tessera render`'s.
#[test]
fn a_coordinator_killed_mid_job_resumes_it_after_a_restart() {
    let _turn = exclusive();
    let (mut farm, job, before, status) = kill_coordinator_mid_job();
    let total = tiles_total(&status);
    let resumed = status["tiles_done"].as_u64().expect("tiles_done");
    assert!(
        resumed > 0 && resumed < total,
        "the job should resume with some but not all tiles done: {status}"
    );
    assert!(
        matches!(status["state"].as_str(), Some("queued" | "running")),
        "{status}"
    );

    // The same workers (not restarted) come back by themselves.
    assert!(farm.workers.iter_mut().all(Daemon::is_running));
    farm.wait_for_workers(&["w1", "w2"]);
    let status = farm.wait_done(job);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    // Only the tiles not recorded before the kill were rendered again.
    let rendered: u64 = farm
        .wait_for_workers(&["w1", "w2"])
        .iter()
        .map(|w| w["tiles_done"].as_u64().expect("tiles_done"))
        .sum();
    assert!(
        rendered <= total - resumed,
        "{rendered} tiles rendered after the restart, but only {} were missing",
        total - resumed
    );
    eprintln!(
        "{before} tiles reported done before the kill, {resumed} after the restart, \
         {rendered} rendered since, {total} in all"
    );
    let lights = scene_path("lights.json");
    farm.assert_job_image(job, &lights, MEDIUM, "the job whose coordinator was killed");
    farm.assert_no_divergent_duplicates();
}

/// Every tile `status` reported done before a SIGKILL of the coordinator is still done
/// after its restart.
#[test]
fn tiles_reported_done_survive_a_coordinator_kill() {
    let _turn = exclusive();
    let (_farm, _job, before, status) = kill_coordinator_mid_job();
    let resumed = status["tiles_done"].as_u64().expect("tiles_done");
    assert!(
        resumed >= before,
        "{before} tiles were reported done before the kill, only {resumed} after the \
         restart: {status}"
    );
}

/// The coordinator stopped with SIGTERM mid-job exits 0 within 12 s; a job
/// submitted meanwhile is refused (no crash); restarted on the same port and data
/// directory, it resumes the job, which gives `tessera render`'s image.
#[test]
fn a_coordinator_terminated_mid_job_exits_cleanly_and_resumes_after_a_restart() {
    let _turn = exclusive();
    let mut farm = Farm::restartable(&["w1"]);
    let lights = scene_path("lights.json");
    let seed = scene_path("seed.json");
    let (dir, addr) = (farm.dir().to_owned(), farm.addr.clone());
    // Scoped threads: a failed assertion still waits for (and reaps) their processes.
    thread::scope(|s| {
        // The reference renders on the second core while the worker uses the first.
        let reference = s.spawn(|| {
            let args = [VERY_LONG, &["--threads", "1"]].concat();
            render_reference(&dir, &lights, "reference.png", &args)
        });
        let job = farm.submit(&lights, &[&["--tile", "64"][..], VERY_LONG].concat());
        let total = tiles_total(&farm.wait_for_tiles(job, 20));

        farm.coordinator.signal("TERM");
        let terminated = Instant::now();
        poll(
            "the coordinator to log its shutdown",
            Duration::from_secs(5),
            || {
                farm.coordinator
                    .log_text()
                    .contains("shutting down")
                    .then_some(())
            },
        );
        // A job submitted during the shutdown: refused, or the connection is.
        let late = s.spawn(|| client(&dir, &addr, &["submit", &seed]));
        let exit = farm
            .coordinator
            .wait_exit(Duration::from_secs(15))
            .expect("the coordinator still runs 15 s after SIGTERM");
        let took = terminated.elapsed();
        assert!(exit.success(), "the coordinator exited with {exit}");
        assert!(
            took <= Duration::from_secs(12),
            "the coordinator took {took:?} to exit after SIGTERM"
        );
        let late = late.join().expect("the late client panicked");
        assert!(
            !late.status.success(),
            "a job was accepted during the shutdown: {}",
            late.stdout
        );
        let lines: Vec<&str> = late.stderr.lines().collect();
        assert!(
            lines.len() == 1 && lines[0].starts_with("error: "),
            "the refused submit prints one error line: {:?}",
            late.stderr
        );
        eprintln!(
            "coordinator exited 0 {:.1} s after SIGTERM; submit meanwhile: {}",
            took.as_secs_f64(),
            lines[0]
        );
        // The ids reserved ahead and not issued were given back at the clean stop.
        let last_id = std::fs::read_to_string(dir.join("data").join("last-job-id"))
            .expect("the coordinator keeps DATA/last-job-id");
        assert_eq!(last_id.trim(), job.to_string(), "DATA/last-job-id");

        farm.restart_coordinator();
        let status = farm.status(job);
        let resumed = status["tiles_done"].as_u64().expect("tiles_done");
        assert!(
            resumed > 0 && resumed < total,
            "the job should resume with some but not all tiles done: {status}"
        );
        let jobs = ok(client(&dir, &addr, &["list", "--json"]), "list");
        let jobs: Value = serde_json::from_str(jobs.stdout.trim()).expect("list --json");
        assert_eq!(
            jobs.as_array().map(Vec::len),
            Some(1),
            "no job was added during the shutdown: {jobs}"
        );
        // w1 comes back by itself; a second worker helps it finish sooner.
        farm.add_worker("w2");
        farm.wait_for_workers(&["w1", "w2"]);
        let status = farm.wait_done(job);
        assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
        eprintln!("{resumed} of {total} tiles were done at the restart");
        let reference = reference.join().expect("the reference render panicked");
        farm.assert_job_image_is(job, &reference, "the job resumed after SIGTERM");
        farm.assert_no_divergent_duplicates();
    });
}

/// The heartbeat timeout of the paused coordinator: shorter than the default 5 s, so
/// that the pause past it is shorter too, and three of the workers' 1 s heartbeats, so
/// that a worker is not dropped for a heartbeat a loaded machine delays.
const PAUSED_HEARTBEAT_TIMEOUT: &[&str] = &["--heartbeat-timeout-ms", "3000"];
/// How long the coordinator is paused: half as long again as its heartbeat timeout
/// (and past the 2 s after which it counts itself paused).
const PAUSE: Duration = Duration::from_millis(4500);

/// The coordinator is stopped (`SIGSTOP`) mid-job for [`PAUSE`], past its heartbeat
/// timeout, then continued: it drops no worker (no "dropping the worker" in its log,
/// the same connections before and after), and the job ends `done` with
/// `tessera render`'s image.
#[test]
fn a_coordinator_paused_past_the_heartbeat_timeout_drops_no_worker() {
    let _turn = exclusive();
    let mut farm = Farm::start_with("127.0.0.1:0", &["w1", "w2"], PAUSED_HEARTBEAT_TIMEOUT);
    let lights = scene_path("lights.json");
    let job = farm.submit(&lights, JOB);
    let total = tiles_total(&farm.status(job));
    farm.wait_for_tiles(job, total / 6);
    let before = connections(&farm.wait_for_workers(&["w1", "w2"]));

    let dir = farm.dir().to_owned();
    // Scoped: a failed assertion still waits for (and reaps) the reference's process.
    thread::scope(|s| {
        farm.coordinator.signal("STOP");
        let paused = Instant::now();
        // The reference renders on one core meanwhile (some 3.6 s): the coordinator is
        // stopped and the workers soon idle.
        let reference = s.spawn(|| {
            let args = [&render_args(JOB)[..], &["--threads", "1"]].concat();
            render_reference(&dir, &lights, "reference.png", &args)
        });
        thread::sleep(PAUSE.saturating_sub(paused.elapsed()));
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
                "the coordinator dropped workers after a {PAUSE:?} pause:\n{}",
                dropped.join("\n")
            )
        });
        let resumed = farm.wait_progress(job, at_cont, "after SIGCONT");
        let after = connections(&farm.try_workers().unwrap_or_default());
        findings.check(after == before, || {
            format!(
                "the workers' connections changed across the pause: {before:?} before, {after:?} after"
            )
        });
        let status = farm.wait_done_progressing(job);
        assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
        eprintln!(
            "coordinator paused {PAUSE:?} at {at_cont}/{total} tiles; the job progressed {} ms \
             after SIGCONT; workers dropped: {}",
            (resumed - continued).as_millis(),
            dropped.len()
        );
        let reference = reference.join().expect("the reference render panicked");
        farm.assert_job_image_is(job, &reference, "the job whose coordinator was paused");
        findings.finish();
    });
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
    let _turn = exclusive();
    let mut farm = Farm::restartable(&["w1", "w2"]);
    let lights = scene_path("lights.json");
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
    let mut client = spawn_tessera(farm.dir(), &args, "submit-wait.log");
    let mut findings = Findings::default();

    // The job, as the coordinator lists it; the client must have printed its line by
    // then, or very soon after.
    let listed = poll("the job to be listed", Duration::from_secs(10), || {
        let run = support::client(farm.dir(), &farm.addr, &["list", "--json"]);
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
    let reference = render_reference(farm.dir(), &lights, "reference.png", &render_args(JOB));
    assert_same_png(&out, &reference, "the image written by submit --wait");
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
    let _turn = exclusive();
    let farm = Farm::restartable(&["w1", "w2"]);
    let seed = scene_path("seed.json");
    let reference = render_reference(farm.dir(), &seed, "reference.png", FRAME_1080P);
    let pid = farm.coordinator.pid();
    let mut rss = Vec::new();
    for n in 1..=15 {
        let job = farm.submit(&seed, FRAME_1080P);
        farm.wait_done_progressing(job);
        farm.assert_job_image_is(job, &reference, &format!("1080p job {n}"));
        thread::sleep(Duration::from_millis(200));
        let kib = rss_kib(pid).expect("the coordinator's RSS");
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
    let _turn = exclusive();
    let mut farm = Farm::restartable(&["w1"]);
    let lights = scene_path("lights.json");
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
    let status = farm.wait_done_progressing(job);
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
