//! Frames of animated scenes on a farm, end to end: real `tessera` coordinators and
//! workers on 127.0.0.1.
//!
//! - `tessera submit seed-orbit.json --frame 17 --wait`, with two workers, writes the
//!   same PNG bytes as `tessera render seed-orbit.json --frame 17` (and not frame 1's),
//!   and `tessera status` shows the frame; without `--frame`, the submission is a
//!   sequence of every frame (`farm::sequences` follows sequences through).
//! - A frame the scene does not have is refused at submission in one `error: ` line,
//!   the loader's, and no job is made.
//! - A coordinator killed with a job of frame 17 queued, and started again on its data
//!   directory, still has the job's frame: the job it finishes is frame 17.
//!
//! (A worker that renders another frame than its tiles' is caught by the checks of the
//! job's frame: `verification`.)

use std::path::{Path, PathBuf};
use std::time::Duration;

use tempfile::TempDir;

use crate::support::{
    assert_same_png, client, fetch, ok, orbit, render_reference, restart_coordinator, scene_path,
    shared, start_coordinator_in, start_restartable_coordinator, start_worker, submit, try_status,
    try_workers, wait_done, wait_for_workers, Daemon, REGISTER_TIMEOUT,
};

/// Small, with a few dozen tiles: every worker gets some.
const JOB: &[&str] = &["--width", "160", "--height", "120", "--aa", "2"];
const TILE: &[&str] = &["--tile", "16"];
const JOB_TIMEOUT: Duration = Duration::from_secs(90);

/// `tessera render seed-orbit.json --frame K` with [`JOB`]'s settings.
fn reference(dir: &Path, frame: u32) -> PathBuf {
    let k = frame.to_string();
    let mut args = JOB.to_vec();
    args.extend(["--frame", k.as_str()]);
    render_reference(dir, &orbit(), &format!("reference-{frame}.png"), &args)
}

#[test]
fn a_frame_submitted_to_two_workers_is_the_frame_tessera_render_gives() {
    let _turn = shared();
    let dir = TempDir::new().expect("temporary directory");
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let _w1 = start_worker(dir.path(), &addr, "w1");
    let _w2 = start_worker(dir.path(), &addr, "w2");
    wait_for_workers(dir.path(), &addr, 2, REGISTER_TIMEOUT);

    let out = dir.path().join("orbit-17.png");
    let scene = orbit();
    let mut args = vec!["submit", scene.as_str(), "--frame", "17", "--wait", "-o"];
    args.push(out.to_str().expect("test paths are UTF-8"));
    args.extend(JOB);
    args.extend(TILE);
    let run = client(dir.path(), &addr, &args);
    assert!(
        run.status.success(),
        "tessera submit --frame 17 --wait failed:\n{}",
        run.stderr
    );
    let id: u64 = run
        .stderr
        .lines()
        .find_map(|l| l.strip_prefix("submitted job "))
        .and_then(|n| n.trim().parse().ok())
        .unwrap_or_else(|| panic!("no job id in:\n{}", run.stderr));
    let frame_17 = reference(dir.path(), 17);
    assert_same_png(&out, &frame_17, "submit --frame 17");
    let frame_1 = reference(dir.path(), 1);
    assert_ne!(
        std::fs::read(&frame_1).unwrap(),
        std::fs::read(&frame_17).unwrap(),
        "frames 1 and 17 differ, or this test proves nothing"
    );

    // Both workers rendered some of it, and the status names the frame.
    let workers = try_workers(dir.path(), &addr).expect("workers");
    for w in &workers {
        assert!(
            w["tiles_done"].as_u64().unwrap_or(0) >= 1,
            "a worker rendered nothing: {workers:?}"
        );
    }
    let status = try_status(dir.path(), &addr, id).expect("status of the job");
    assert_eq!(status["frame"], 17, "{status}");
    let line = client(dir.path(), &addr, &["status", &id.to_string()]);
    assert!(
        line.stdout.contains("frame 17, "),
        "tessera status does not show the frame: {}",
        line.stdout
    );

    // `--frame 1` is frame 1, as `tessera render` without --frame.
    let mut args = vec![scene.as_str(), "--frame", "1"];
    args.extend(JOB);
    args.extend(TILE);
    let job = submit(dir.path(), &addr, &args);
    let status = wait_done(dir.path(), &addr, job, JOB_TIMEOUT);
    assert_eq!(status["frame"], 1, "{status}");
    assert!(
        status["frames"].is_null(),
        "one frame is no sequence: {status}"
    );
    let image = fetch(dir.path(), &addr, job, "orbit-1.png");
    assert_same_png(&image, &frame_1, "submit --frame 1");

    // Without --frame, every frame of the animated scene, as one sequence job.
    let mut args = vec![scene.as_str()];
    args.extend(JOB);
    let job = submit(dir.path(), &addr, &args);
    let status = try_status(dir.path(), &addr, job).expect("status of the sequence");
    assert_eq!(status["frames"]["first"], 1, "{status}");
    assert_eq!(status["frames"]["last"], 121, "{status}");
    ok(
        client(dir.path(), &addr, &["cancel", &job.to_string()]),
        "cancel the sequence",
    );
}

#[test]
fn a_frame_the_scene_does_not_have_is_refused_in_one_line() {
    let _turn = shared();
    let dir = TempDir::new().expect("temporary directory");
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let orbit = orbit();
    let seed = scene_path("seed.json");
    for (scene, frame, message) in [
        (
            orbit.as_str(),
            "122",
            "frame 122 is beyond the scene's 121 frames",
        ),
        (
            seed.as_str(),
            "2",
            "frame 2: the scene has no animation, only frame 1",
        ),
    ] {
        let run = client(dir.path(), &addr, &["submit", scene, "--frame", frame]);
        assert!(!run.status.success(), "frame {frame} was accepted");
        let lines: Vec<&str> = run.stderr.lines().collect();
        assert_eq!(
            lines,
            [format!("error: {scene}: {message}")],
            "stderr is not the one line"
        );
    }
    // The last frame is accepted, and nothing was made of the refusals.
    let job = submit(dir.path(), &addr, &[orbit.as_str(), "--frame", "121"]);
    let listed = client(dir.path(), &addr, &["list", "--json"]);
    let jobs: serde_json::Value = serde_json::from_str(listed.stdout.trim())
        .unwrap_or_else(|e| panic!("list --json is not JSON ({e}): {}", listed.stdout));
    assert_eq!(
        jobs.as_array().map(Vec::len),
        Some(1),
        "refused submissions made jobs: {jobs}"
    );
    assert_eq!(try_status(dir.path(), &addr, job).unwrap()["frame"], 121);
    let run = client(
        dir.path(),
        &addr,
        &["submit", orbit.as_str(), "--frame", "0"],
    );
    assert!(!run.status.success(), "frame 0 was accepted");
}

#[test]
fn a_restarted_coordinator_keeps_the_frame_of_a_queued_job() {
    let _turn = shared();
    let dir = TempDir::new().expect("temporary directory");
    let (mut coordinator, addr) = start_restartable_coordinator(dir.path());
    let scene = orbit();
    let mut args = vec![scene.as_str(), "--frame", "17"];
    args.extend(JOB);
    args.extend(TILE);
    // No worker: the job stays queued.
    let job = submit(dir.path(), &addr, &args);
    let status = try_status(dir.path(), &addr, job).expect("status");
    assert_eq!(status["state"], "queued", "{status}");
    assert_eq!(status["frame"], 17, "{status}");
    coordinator.kill9();

    let _coordinator = restart_coordinator(dir.path(), &addr, &[]);
    let status = try_status(dir.path(), &addr, job).expect("status after the restart");
    assert_eq!(status["frame"], 17, "{status}");
    let workers: Vec<Daemon> = ["w1", "w2"]
        .iter()
        .map(|name| start_worker(dir.path(), &addr, name))
        .collect();
    wait_done(dir.path(), &addr, job, JOB_TIMEOUT);
    let image = fetch(dir.path(), &addr, job, "restarted.png");
    assert_same_png(
        &image,
        &reference(dir.path(), 17),
        "frame 17 after a restart",
    );
    drop(workers);
}
