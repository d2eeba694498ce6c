//! Worker names are unique among the connected workers of a farm of real `tessera`
//! processes: a worker that comes back under its name from the same host supersedes
//! its old connection (a restart before the old one timed out), one from another host
//! (another loopback address) joins under a suffixed name that both the coordinator's
//! log and the worker's say, and `tessera workers drain NAME` acts on exactly one
//! worker and says which.

use std::time::Duration;

use crate::support::fake_worker::{FakeWorker, Lie};
use crate::support::{
    assert_job_image, client, ok, poll, scene_path, shared, spawn_tessera, start_coordinator_in,
    start_worker, submit, wait_done, worker_named, worker_names, workers_json,
};

#[test]
fn a_worker_of_the_same_name_from_the_same_host_supersedes_the_connected_one() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (coordinator, addr) = start_coordinator_in(dir.path());
    let mut first = start_worker(dir.path(), &addr, "render-2");
    let old = poll("the first worker to join", Duration::from_secs(30), || {
        worker_named(&workers_json(dir.path(), &addr, &[]), "render-2").map(|w| w["id"].clone())
    });

    // The same name from the same host: the new process replaces the old connection.
    let second = spawn_tessera(
        dir.path(),
        &[
            "worker",
            "--coordinator",
            &addr,
            "--threads",
            "1",
            "--name",
            "render-2",
        ],
        "worker-render-2-again.log",
    );
    let exit = first
        .wait_exit(Duration::from_secs(30))
        .expect("the superseded worker did not stop");
    assert!(!exit.success(), "the superseded worker exited with {exit}");
    let said = first.log_text();
    assert!(
        said.contains("superseded by a new connection of worker render-2 from the same host"),
        "{said}"
    );
    let listed = poll("the second worker to join", Duration::from_secs(30), || {
        let listed = workers_json(dir.path(), &addr, &[]);
        listed.iter().any(|w| w["id"] != old).then_some(listed)
    });
    assert_eq!(worker_names(&listed), ["render-2"], "{listed:?}");
    assert_eq!(listed[0]["host"], "127.0.0.1");
    let log = coordinator.log_text();
    assert!(
        log.contains("worker render-2 reconnected from 127.0.0.1 while its old connection"),
        "{log}"
    );

    // The new connection serves, the image exactly `tessera render`'s.
    let scene = scene_path("seed.json");
    let args = ["--width", "32", "--height", "24", "--aa", "1"];
    let job = submit(dir.path(), &addr, &[&[scene.as_str()][..], &args].concat());
    wait_done(dir.path(), &addr, job, Duration::from_secs(60));
    assert_job_image(
        dir.path(),
        &addr,
        job,
        &scene,
        &args,
        "the superseding worker's job",
    );
    drop(second);
}

#[test]
fn a_worker_of_a_taken_name_from_another_host_is_suffixed_and_controls_act_on_one() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (coordinator, addr) = start_coordinator_in(dir.path());
    // 127.0.0.2 is another host to the coordinator (loopback on Linux).
    let far = FakeWorker::start_from(
        Some([127, 0, 0, 2].into()),
        &addr,
        "render-2",
        "fake",
        Lie::Honest,
    );
    poll(
        "the worker from 127.0.0.2 to join",
        Duration::from_secs(30),
        || far.joined_as(),
    );
    assert_eq!(far.joined_as().as_deref(), Some("render-2"));
    let near = start_worker(dir.path(), &addr, "render-2");
    let listed = poll("both workers to join", Duration::from_secs(30), || {
        let listed = workers_json(dir.path(), &addr, &[]);
        (listed.len() == 2).then_some(listed)
    });
    let mut names = worker_names(&listed);
    names.sort();
    assert_eq!(names, ["render-2", "render-2-2"]);
    assert_eq!(
        worker_named(&listed, "render-2").unwrap()["host"],
        "127.0.0.2"
    );
    assert_eq!(
        worker_named(&listed, "render-2-2").unwrap()["host"],
        "127.0.0.1"
    );
    let shown = ok(client(dir.path(), &addr, &["workers"]), "workers");
    assert!(
        shown.stdout.contains(" render-2-2 on 127.0.0.1: "),
        "{}",
        shown.stdout
    );
    // One line on the coordinator names the name and both hosts; the worker says the
    // name it got.
    let log = coordinator.log_text();
    let lines: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("worker name render-2 is already taken"))
        .collect();
    assert_eq!(lines.len(), 1, "{log}");
    assert!(
        lines[0].contains("from 127.0.0.2")
            && lines[0].contains("the worker from 127.0.0.1 joins as render-2-2"),
        "{}",
        lines[0]
    );
    let said = near.log_text();
    assert!(said.contains("joined as render-2-2"), "{said}");
    assert!(
        !far.closed(),
        "the first worker of the name was disconnected"
    );

    // A name drains exactly one worker, and says which.
    let id = worker_named(&listed, "render-2").unwrap()["id"].clone();
    let run = ok(
        client(dir.path(), &addr, &["workers", "drain", "render-2"]),
        "workers drain",
    );
    assert_eq!(
        run.stdout.trim(),
        format!(
            "worker render-2 (id {id}, host 127.0.0.2) draining: it finishes the tiles it \
             holds, then exits"
        )
    );
    let listed = workers_json(dir.path(), &addr, &[]);
    assert_eq!(worker_named(&listed, "render-2").unwrap()["draining"], true);
    assert_eq!(
        worker_named(&listed, "render-2-2").unwrap()["draining"],
        false
    );
}
