//! Operating a farm, against real `tessera` processes on 127.0.0.1: one coordinator per
//! data directory; an image file that cannot be written is refused before the farm
//! spends anything on it.

mod common;

use std::time::{Duration, Instant};

use common::{client, ok, scene_path, serial, start_coordinator, tessera, try_start_coordinator};

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
    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &dir.path().join("data"),
        "127.0.0.1:0",
        &[],
        "coordinator.log",
    );
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
