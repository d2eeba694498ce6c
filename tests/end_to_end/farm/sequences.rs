//! Sequence jobs (a frame range of an animated scene as one job) on a farm of real
//! `tessera` processes on 127.0.0.1, compared byte for byte with `tessera render
//! --frames` of the same range:
//!
//! - with one and with three workers (`submit --frames --wait -o DIR/`), the sequence
//!   listed as one job, its frames shown by `tessera status`;
//! - with workers killed (SIGKILL) mid-sequence and a new one joining;
//! - paused (nothing moves), reprioritised and resumed;
//! - cancelled mid-sequence (no frame starts after it), a done and a cancelled frame
//!   each rendered again alone (`tessera retry JOB --frame K`), then every cancelled
//!   frame (`tessera retry JOB`);
//! - across a coordinator killed mid-sequence and started again on its data directory;
//!   started again with a lower `--max-objects`, its frames still to start wait;
//! - a frame that fails (five machines report its first tile failed) fails alone: the
//!   other frames are done, the sequence ends failed naming it, and `tessera retry JOB
//!   --frame K` on a healthy worker renders it;
//! - deleted: its folder and frames go, also by `--retention`;
//! - ranges the scene does not have refused in one line, nothing made of them.

use std::path::{Path, PathBuf};
use std::time::Duration;

use tempfile::TempDir;

use crate::support::fake_worker::{FakeWorker, Lie};
use crate::support::{
    client, entries, exclusive, ok, one_error_line, orbit, path_str, poll, restart_coordinator,
    scene_path, shared, start_coordinator, start_coordinator_in, start_restartable_coordinator,
    start_slow_worker, start_slow_workers, start_worker, status_json, submit, tessera, try_status,
    try_workers, wait_for_workers, worker_named, Daemon, REGISTER_TIMEOUT,
};

/// Small frames of a few dozen tiles each: every worker gets some of every frame.
const JOB: &[&str] = &["--width", "96", "--height", "54", "--aa", "2"];
const TILE: &[&str] = &["--tile", "16"];
const TIMEOUT: Duration = Duration::from_secs(120);

/// `tessera render seed-orbit.json --frames A-B -o DIR/` with [`JOB`]'s settings.
fn reference(dir: &Path, range: &str) -> PathBuf {
    let out = dir.join(format!("reference-{range}"));
    let scene = orbit();
    let mut args = vec![
        "render",
        scene.as_str(),
        "--frames",
        range,
        "-o",
        path_str(&out),
    ];
    args.extend(JOB);
    ok(
        tessera(dir, &args, Duration::from_secs(120)),
        "tessera render --frames",
    );
    out
}

/// The frames of `dir`, by name.
fn frames_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("cannot read {}: {e}", dir.display()))
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("frame_") && n.ends_with(".png"))
        .collect();
    names.sort();
    names
}

/// Every frame in `actual` is the reference's frame of that name, byte for byte, and
/// `expected` frames are there.
fn assert_same_frames(actual: &Path, reference: &Path, expected: usize, what: &str) {
    let names = frames_in(actual);
    assert_eq!(names.len(), expected, "{what}: frames written: {names:?}");
    for name in names {
        let a = std::fs::read(actual.join(&name)).unwrap();
        let r = std::fs::read(reference.join(&name))
            .unwrap_or_else(|e| panic!("{what}: the reference has no {name}: {e}"));
        assert!(
            a == r,
            "{what}: {name} differs from tessera render --frames'"
        );
    }
}

fn frames_of(status: &serde_json::Value) -> &serde_json::Value {
    &status["frames"]
}

fn count(status: &serde_json::Value, key: &str) -> u64 {
    frames_of(status)[key]
        .as_u64()
        .unwrap_or_else(|| panic!("no frames.{key} in {status}"))
}

/// Polls the sequence's status until `until` holds of it.
fn wait_for(
    dir: &Path,
    addr: &str,
    job: u64,
    what: &str,
    until: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    poll(&format!("job {job}: {what}"), TIMEOUT, || {
        try_status(dir, addr, job).filter(|s| until(s))
    })
}

fn submit_sequence(dir: &Path, addr: &str, range: &str) -> u64 {
    let scene = orbit();
    let mut args = vec![scene.as_str(), "--frames", range];
    args.extend(JOB);
    args.extend(TILE);
    submit(dir, addr, &args)
}

fn fetch_frames(dir: &Path, addr: &str, job: u64, name: &str) -> PathBuf {
    let out = dir.join(name);
    ok(
        client(
            dir,
            addr,
            &["fetch", &job.to_string(), "-o", path_str(&out)],
        ),
        "tessera fetch of a sequence",
    );
    out
}

#[test]
fn a_sequence_on_one_and_on_three_workers_is_tessera_render_frames_byte_for_byte() {
    let _turn = shared();
    let dir = TempDir::new().expect("temporary directory");
    let reference = reference(dir.path(), "1-8");
    for workers in [1usize, 3] {
        let (_coordinator, addr) = start_coordinator(
            dir.path(),
            &dir.path().join(format!("data-{workers}")),
            "127.0.0.1:0",
            &[],
            &format!("coordinator-{workers}.log"),
        );
        let _workers: Vec<Daemon> = (0..workers)
            .map(|i| start_worker(dir.path(), &addr, &format!("w{i}")))
            .collect();
        wait_for_workers(dir.path(), &addr, workers, REGISTER_TIMEOUT);
        let out = dir.path().join(format!("farm-{workers}"));
        let scene = orbit();
        let mut args = vec![
            "submit",
            scene.as_str(),
            "--frames",
            "1-8",
            "--wait",
            "-o",
            path_str(&out),
        ];
        args.extend(JOB);
        args.extend(TILE);
        let run = ok(client(dir.path(), &addr, &args), "submit --frames --wait");
        assert_same_frames(
            &out,
            &reference,
            8,
            &format!("{workers} workers, submit --wait"),
        );
        let id: u64 = run
            .stderr
            .lines()
            .find_map(|l| l.strip_prefix("submitted job "))
            .and_then(|n| n.trim().parse().ok())
            .unwrap_or_else(|| panic!("no job id in:\n{}", run.stderr));

        // One job listed (its frame jobs are not), its frames shown.
        let listed = client(dir.path(), &addr, &["list", "--json"]);
        let jobs: serde_json::Value = serde_json::from_str(listed.stdout.trim()).unwrap();
        assert_eq!(jobs.as_array().map(Vec::len), Some(1), "{jobs}");
        let status = try_status(dir.path(), &addr, id).unwrap();
        assert_eq!(status["state"], "done", "{status}");
        assert_eq!(count(&status, "done"), 8, "{status}");
        assert_eq!(count(&status, "done_prefix"), 8, "{status}");
        let line = client(dir.path(), &addr, &["status", &id.to_string()]);
        assert!(
            line.stdout.contains("frames 1-8: 8/8 done"),
            "tessera status: {}",
            line.stdout
        );
        // Fetched again, into another directory: the same frames.
        let again = fetch_frames(dir.path(), &addr, id, &format!("fetched-{workers}"));
        assert_same_frames(&again, &reference, 8, "tessera fetch -o DIR/");
    }
}

#[test]
fn workers_killed_mid_sequence_change_no_frame() {
    let _turn = exclusive();
    let dir = TempDir::new().expect("temporary directory");
    let reference = reference(dir.path(), "1-16");
    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &dir.path().join("data"),
        "127.0.0.1:0",
        &["--heartbeat-timeout-ms", "1500"],
        "coordinator.log",
    );
    // Slow machines (1/150 of a core each), so that frames are still to come.
    let Some(mut workers) = start_slow_workers(
        "workers_killed_mid_sequence_change_no_frame",
        dir.path(),
        &addr,
        3,
        1.0 / 150.0,
    ) else {
        return;
    };
    let job = submit_sequence(dir.path(), &addr, "1-16");
    wait_for(dir.path(), &addr, job, "2 frames done", |s| {
        count(s, "done") >= 2
    });
    workers[0].0.kill9();
    let status = wait_for(dir.path(), &addr, job, "2 more frames done", |s| {
        count(s, "done") >= 4
    });
    assert!(count(&status, "done") < 16, "the sequence ended too soon");
    workers[1].0.kill9();
    let _w3 = start_worker(dir.path(), &addr, "w3");
    let status = wait_for(dir.path(), &addr, job, "done", |s| s["state"] == "done");
    assert_eq!(count(&status, "done"), 16, "{status}");
    let out = fetch_frames(dir.path(), &addr, job, "farm");
    assert_same_frames(&out, &reference, 16, "workers killed mid-sequence");
}

#[test]
fn a_cancelled_sequence_stops_and_its_frames_are_rendered_again_on_request() {
    let _turn = exclusive();
    let dir = TempDir::new().expect("temporary directory");
    let reference = reference(dir.path(), "1-20");
    let data = dir.path().join("data");
    let (_coordinator, addr) =
        start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "coordinator.log");
    let Some((_worker, limit)) = start_slow_worker(
        "a_cancelled_sequence_stops_and_its_frames_are_rendered_again_on_request",
        dir.path(),
        &addr,
        "w1",
        0.01,
        &[],
    ) else {
        return;
    };
    wait_for_workers(dir.path(), &addr, 1, REGISTER_TIMEOUT);
    let job = submit_sequence(dir.path(), &addr, "1-20");
    wait_for(dir.path(), &addr, job, "1 frame done", |s| {
        count(s, "done") >= 1
    });
    // Paused: no frame starts, the frame rendering gets no new tile (those out finish).
    ok(
        client(dir.path(), &addr, &["pause", &job.to_string()]),
        "tessera pause",
    );
    let paused = try_status(dir.path(), &addr, job).unwrap();
    assert_eq!(paused["paused"], true, "{paused}");
    // The tiles out when it was paused come back first: a worker on a hundredth of a
    // core holds many (its credit covers its slow round trips), of several frames, and
    // on a loaded machine returns them over seconds. Its listing counts its results as
    // they come (the job's status counts them once stored, and a frame once written).
    let w1 = || {
        let workers = try_workers(dir.path(), &addr)?;
        let w1 = worker_named(&workers, "w1")?;
        Some((w1["tiles_in_flight"].as_u64()?, w1["tiles_done"].as_u64()?))
    };
    let (_, rendered) = poll("the tiles out at the pause to come back", TIMEOUT, || {
        w1().filter(|(out, _)| *out == 0)
    });
    let still = try_status(dir.path(), &addr, job).unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    let later = try_status(dir.path(), &addr, job).unwrap();
    // No frame starts (the frames pending stay so) and the worker is given no tile and
    // renders none. A frame whose last tile came in before the pause may still be
    // written and counted done meanwhile.
    assert_eq!(
        (count(&still, "pending"), w1()),
        (count(&later, "pending"), Some((0, rendered))),
        "a paused sequence went on: {still} then {later}"
    );
    ok(
        client(dir.path(), &addr, &["priority", &job.to_string(), "5"]),
        "tessera priority",
    );
    ok(
        client(dir.path(), &addr, &["resume", &job.to_string()]),
        "tessera resume",
    );
    let resumed = wait_for(dir.path(), &addr, job, "2 frames done", |s| {
        count(s, "done") >= 2 && count(s, "done") > count(&later, "done")
    });
    assert_eq!(resumed["priority"], 5, "{resumed}");
    assert_eq!(resumed["paused"], false, "{resumed}");
    ok(
        client(dir.path(), &addr, &["cancel", &job.to_string()]),
        "tessera cancel",
    );
    let status = wait_for(dir.path(), &addr, job, "cancelled", |s| {
        s["state"] == "cancelled"
    });
    let done = count(&status, "done");
    assert!((2..20).contains(&done), "{status}");
    assert_eq!(count(&status, "active"), 0, "{status}");
    assert_eq!(count(&status, "done") + count(&status, "cancelled"), 20);
    // Nothing starts after a cancel.
    std::thread::sleep(Duration::from_millis(1500));
    let later = try_status(dir.path(), &addr, job).unwrap();
    assert_eq!(count(&later, "done"), done, "a frame ran after the cancel");
    let out = fetch_frames(dir.path(), &addr, job, "cancelled");
    assert_same_frames(&out, &reference, done as usize, "a cancelled sequence");
    // What follows is about which frames are rendered again, not about a sequence still
    // running when something happens to it: the worker goes back to full speed, as the
    // eighteen frames still to render would take it some fifteen seconds on a hundredth
    // of a core.
    drop(limit);

    // A cancelled frame rendered alone, then a done one: the others stay cancelled.
    for frame in ["20", "1"] {
        let run = ok(
            client(
                dir.path(),
                &addr,
                &["retry", &job.to_string(), "--frame", frame],
            ),
            "tessera retry --frame",
        );
        assert!(
            run.stdout
                .contains(&format!("frame {frame} is back in the queue")),
            "{}",
            run.stdout
        );
        let status = wait_for(dir.path(), &addr, job, "the frame rendered", |s| {
            s["state"] == "cancelled"
        });
        assert_eq!(
            count(&status, "done"),
            done + 1,
            "frame {frame} requeued: {status}"
        );
    }
    let out = fetch_frames(dir.path(), &addr, job, "requeued");
    assert_same_frames(&out, &reference, done as usize + 1, "requeued frames");
    assert!(frames_in(&out).contains(&"frame_0020.png".to_string()));
    // A frame still rendering cannot be requeued; one the sequence lacks is named.
    let run = client(
        dir.path(),
        &addr,
        &["retry", &job.to_string(), "--frame", "21"],
    );
    assert!(!run.status.success());
    assert_eq!(
        run.stderr.trim(),
        format!("error: job {job}: the sequence has frames 1 to 20: there is no frame 21")
    );

    // Every cancelled frame again: the sequence is done, every frame the reference's.
    ok(
        client(dir.path(), &addr, &["retry", &job.to_string()]),
        "tessera retry of a sequence",
    );
    let status = wait_for(dir.path(), &addr, job, "done", |s| s["state"] == "done");
    assert_eq!(count(&status, "done"), 20, "{status}");
    let out = fetch_frames(dir.path(), &addr, job, "all");
    assert_same_frames(&out, &reference, 20, "every frame after retry");

    // Deleted: the folder and its frames go, and the job is unknown.
    ok(
        client(dir.path(), &addr, &["delete", &job.to_string()]),
        "tessera delete of a sequence",
    );
    assert!(!data.join("jobs").join(job.to_string()).exists());
    assert!(try_status(dir.path(), &addr, job).is_none());
    assert_nothing_listed(dir.path(), &addr);
}

#[test]
fn a_sequence_survives_a_coordinator_killed_mid_way() {
    let _turn = exclusive();
    let dir = TempDir::new().expect("temporary directory");
    let reference = reference(dir.path(), "1-16");
    let (mut coordinator, addr) = start_restartable_coordinator(dir.path());
    // Two workers on 1/150 of a core, so that the coordinator is killed mid-way.
    let Some(workers) = start_slow_workers(
        "a_sequence_survives_a_coordinator_killed_mid_way",
        dir.path(),
        &addr,
        2,
        1.0 / 150.0,
    ) else {
        return;
    };
    let (_workers, limits): (Vec<Daemon>, Vec<localfarm::CpuLimit>) = workers.into_iter().unzip();
    let job = submit_sequence(dir.path(), &addr, "1-16");
    let before = wait_for(dir.path(), &addr, job, "3 frames done", |s| {
        count(s, "done") >= 3
    });
    assert!(count(&before, "done") < 16, "the sequence ended too soon");
    coordinator.kill9();

    let _coordinator = restart_coordinator(dir.path(), &addr, &[]);
    let status = try_status(dir.path(), &addr, job).expect("the sequence after a restart");
    assert!(
        count(&status, "done") >= count(&before, "done"),
        "frames done before the restart were lost: {status}"
    );
    // The rest of the sequence at full speed.
    drop(limits);
    let status = wait_for(dir.path(), &addr, job, "done", |s| s["state"] == "done");
    assert_eq!(count(&status, "done"), 16, "{status}");
    let out = fetch_frames(dir.path(), &addr, job, "farm");
    assert_same_frames(&out, &reference, 16, "a sequence across a restart");
    let listed = client(dir.path(), &addr, &["list", "--json"]);
    let jobs: serde_json::Value = serde_json::from_str(listed.stdout.trim()).unwrap();
    assert_eq!(jobs.as_array().map(Vec::len), Some(1), "{jobs}");
}

/// A sequence taken back after a restart is admitted under the coordinator's limits of
/// now: with `--max-objects` lowered below its scene's 3 objects, the frames still to
/// start wait, each refusal in the sequence's events, and none of them starts.
#[test]
fn a_limit_lowered_across_a_restart_holds_back_the_frames_still_to_start() {
    let _turn = shared();
    let dir = TempDir::new().expect("temporary directory");
    let (mut coordinator, addr) = start_restartable_coordinator(dir.path());
    // No worker: the frames beyond the first few stay pending.
    let job = submit_sequence(dir.path(), &addr, "1-16");
    wait_for(dir.path(), &addr, job, "stored", |s| {
        count(s, "pending") > 0
    });
    coordinator.kill9();

    let limited = ["--max-objects", "2"];
    let _coordinator = restart_coordinator(dir.path(), &addr, &limited);
    // The frames stored as frame jobs before the kill were admitted then, and go on.
    let restored = try_status(dir.path(), &addr, job).expect("the sequence after a restart");
    let admitted = 16 - count(&restored, "pending");
    let _worker = start_worker(dir.path(), &addr, "w0");
    let refusal = "objects: 3 objects, more than this coordinator's limit of 2";
    poll("the frames' refusal in the events", TIMEOUT, || {
        let events = client(dir.path(), &addr, &["events", &job.to_string(), "--json"]);
        let events: serde_json::Value = serde_json::from_str(events.stdout.trim()).ok()?;
        events
            .as_array()?
            .iter()
            .any(|e| {
                e["event"] == "frame_waiting"
                    && e["detail"].as_str().is_some_and(|d| d.contains(refusal))
            })
            .then_some(())
    });
    // The frames admitted before the restart are rendered; no other starts.
    let status = wait_for(dir.path(), &addr, job, "the admitted frames done", |s| {
        count(s, "active") == 0 && count(s, "done") == admitted
    });
    assert_eq!(count(&status, "pending"), 16 - admitted, "{status}");
}

/// `tessera list` shows no job: a deleted sequence leaves no frame job behind.
fn assert_nothing_listed(dir: &Path, addr: &str) {
    let listed = client(dir, addr, &["list", "--json"]);
    assert_eq!(
        listed.stdout.trim(),
        "[]",
        "frame jobs left: {}",
        listed.stdout
    );
}

#[test]
fn frame_ranges_the_scene_does_not_have_are_refused_in_one_line() {
    let _turn = shared();
    let dir = TempDir::new().expect("temporary directory");
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let orbit = orbit();
    let seed = scene_path("seed.json");
    for (scene, range, message) in [
        (
            orbit.as_str(),
            "120-130",
            format!("error: {orbit}: frame 130 is beyond the scene's 121 frames"),
        ),
        (
            seed.as_str(),
            "1-2",
            format!("error: {seed}: frame 2: the scene has no animation, only frame 1"),
        ),
        (
            orbit.as_str(),
            "5-3",
            "error: invalid value '5-3' for '--frames [<A-B>]': the range ends (frame 3) \
             before it starts (frame 5)"
                .to_string(),
        ),
    ] {
        let run = client(dir.path(), &addr, &["submit", scene, "--frames", range]);
        assert!(!run.status.success(), "--frames {range} was accepted");
        let first = run.stderr.lines().next().unwrap_or_default();
        assert_eq!(first, message, "stderr: {}", run.stderr);
        if !range.starts_with('5') {
            assert_eq!(run.stderr.lines().count(), 1, "{}", run.stderr);
        }
    }
    let listed = client(dir.path(), &addr, &["list", "--json"]);
    assert_eq!(listed.stdout.trim(), "[]", "refusals made jobs");
    // --frame and --frames together are refused by the command line.
    let run = client(
        dir.path(),
        &addr,
        &["submit", orbit.as_str(), "--frame", "2", "--frames", "1-3"],
    );
    assert!(!run.status.success());
}

#[test]
fn a_sequence_is_deleted_with_its_frames_once_its_retention_has_passed() {
    let _turn = exclusive();
    let dir = TempDir::new().expect("temporary directory");
    let data = dir.path().join("data");
    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &data,
        "127.0.0.1:0",
        &["--retention", "2s"],
        "coordinator.log",
    );
    let _worker = start_worker(dir.path(), &addr, "w1");
    wait_for_workers(dir.path(), &addr, 1, REGISTER_TIMEOUT);
    let job = submit_sequence(dir.path(), &addr, "1-3");
    let done = wait_for(dir.path(), &addr, job, "done", |s| s["state"] == "done");
    let folder = data.join("jobs").join(job.to_string());
    assert_eq!(frames_in(&folder).len(), 3, "{done}");
    // Its frames do not expire before it: the sequence keeps every frame until it goes.
    let ended = std::time::Instant::now();
    poll(
        &format!("job {job} to be deleted"),
        Duration::from_secs(20),
        || try_status(dir.path(), &addr, job).is_none().then_some(()),
    );
    assert!(
        ended.elapsed() >= Duration::from_millis(1500),
        "deleted {:?} after it ended, with a retention of 2 s",
        ended.elapsed()
    );
    assert!(!folder.exists(), "its folder is left");
    assert_nothing_listed(dir.path(), &addr);
}

#[test]
fn a_failed_frame_fails_alone_and_is_rendered_again_alone() {
    let _turn = shared();
    let dir = TempDir::new().expect("temporary directory");
    let reference = reference(dir.path(), "1-4");
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    // Five machines (the attempts a tile gets) that cannot render frame 3's first tile.
    let build = render::build_identity();
    let fakes: Vec<FakeWorker> = (0..5)
        .map(|i| FakeWorker::start(&addr, &format!("f{i}"), &build, Lie::FailFrame(3)))
        .collect();
    wait_for_workers(dir.path(), &addr, 5, REGISTER_TIMEOUT);
    let job = submit_sequence(dir.path(), &addr, "1-4");
    let status = wait_for(dir.path(), &addr, job, "failed", |s| s["state"] == "failed");
    assert_eq!(
        count(&status, "done"),
        3,
        "the other frames go on: {status}"
    );
    assert_eq!(count(&status, "failed"), 1, "{status}");
    let failure = &frames_of(&status)["failures"][0];
    assert_eq!(failure["frame"], 3, "{status}");
    assert!(
        failure["error"]
            .as_str()
            .is_some_and(|e| e.contains("cannot render frame 3")),
        "the frame's error: {status}"
    );
    let line = client(dir.path(), &addr, &["status", &job.to_string()]);
    assert!(
        line.stdout.contains("3/4 done, 1 failed (3)"),
        "tessera status: {}",
        line.stdout
    );
    // The frames done are fetched; the failed one is not there.
    let out = fetch_frames(dir.path(), &addr, job, "partial");
    assert_same_frames(&out, &reference, 3, "a sequence with a failed frame");

    // On a healthy machine, frame 3 alone is rendered again.
    drop(fakes);
    let _worker = start_worker(dir.path(), &addr, "w1");
    ok(
        client(
            dir.path(),
            &addr,
            &["retry", &job.to_string(), "--frame", "3"],
        ),
        "tessera retry --frame 3",
    );
    let status = wait_for(dir.path(), &addr, job, "done", |s| s["state"] == "done");
    assert_eq!(count(&status, "failed"), 0, "{status}");
    let out = fetch_frames(dir.path(), &addr, job, "all");
    assert_same_frames(&out, &reference, 4, "the failed frame rendered again");
}

#[test]
fn frames_alone_is_every_frame_for_submit_and_up_as_for_render() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let seed = scene_path("seed.json");
    let small = ["--width", "32", "--height", "24", "--aa", "1"];
    // `up`: a still scene is one frame, written into the directory of its frames.
    let mut args = vec!["up", seed.as_str(), "--frames", "--workers", "1"];
    args.extend(small);
    ok(tessera(d, &args, Duration::from_secs(120)), "up --frames");
    assert_eq!(entries(&d.join("seed")), ["frame_0001.png"]);
    // `submit`: a sequence job of every frame, here one.
    let (_coordinator, addr) = start_coordinator_in(d);
    let mut args = vec![seed.as_str(), "--frames"];
    args.extend(small);
    let job = submit(d, &addr, &args);
    let status = status_json(d, &addr, job);
    assert_eq!(
        (&status["frames"]["first"], &status["frames"]["last"]),
        (&serde_json::json!(1), &serde_json::json!(1)),
        "{status}"
    );
}

#[test]
fn a_sequence_refused_for_refine_names_its_frames_jobs() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (_coordinator, addr) = start_coordinator_in(d);
    let _worker = start_worker(d, &addr, "w1");
    let orbit = orbit();
    let job = submit(
        d,
        &addr,
        &[
            &orbit, "--frames", "1-3", "--width", "32", "--height", "24", "--aa", "1",
        ],
    );
    crate::support::wait_done(d, &addr, job, Duration::from_secs(60));
    let line = one_error_line(
        &client(
            d,
            &addr,
            &["refine", &job.to_string(), "--target-error", "1"],
        ),
        "refine SEQUENCE",
    );
    let (first, last) = (job + 1, job + 3);
    assert_eq!(
        line,
        format!(
            "error: job {job} is a sequence: each of its frames is a job of its own (frames \
             1-3: jobs {first}-{last}); requeue or refine one of those, or requeue a frame \
             (`tessera retry {job} --frame K`)"
        )
    );
    // What it names is there to be asked about.
    let status = status_json(d, &addr, last);
    assert_eq!(status["frame"], 3, "{status}");
}
