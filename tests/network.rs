//! What crosses the network: a worker cut off mid-job, and TLS.
//!
//! The network cut runs the real binaries on 127.0.0.1 only, through a relay
//! ([`common::proxy::CutProxy`]) that stops forwarding in both directions without
//! closing anything, as a pulled cable does. (A network namespace with a veth pair would
//! cut at the kernel instead, but it needs addresses other than 127.0.0.1, which the
//! project's tests never use.) The coordinator must give the cut worker's tiles to
//! others once its heartbeats stop, and the worker must notice the silence and come
//! back once the link is restored.
//!
//! TLS: a coordinator with a certificate serves a worker and a client that trust it, the
//! image is byte-identical, the scene does not cross the wire in clear, and each
//! misconfiguration (plain peer, untrusted certificate, TLS to a plain coordinator)
//! fails with a one-line error.

mod common;

use std::path::{Path, PathBuf};
use std::time::Duration;

use common::proxy::CutProxy;
use serde_json::Value;
use tempfile::TempDir;

/// Some 6 CPU-seconds of work...
const JOB: &[&str] = &["--width", "1600", "--height", "1200", "--aa", "5"];

fn workers(dir: &Path, addr: &str, tls: &[&str]) -> Vec<Value> {
    let mut args = vec!["workers", "--json"];
    args.extend(tls);
    let run = common::ok(common::client(dir, addr, &args), "workers --json");
    match serde_json::from_str(run.stdout.trim()) {
        Ok(Value::Array(workers)) => workers,
        other => panic!("workers --json: {other:?}"),
    }
}

fn names(workers: &[Value]) -> Vec<String> {
    workers
        .iter()
        .map(|w| w["name"].as_str().expect("name").to_owned())
        .collect()
}

fn tiles_done(dir: &Path, addr: &str, job: u64) -> u64 {
    common::try_status(dir, addr, job).expect("status")["tiles_done"]
        .as_u64()
        .expect("tiles_done")
}

#[test]
fn a_worker_cut_off_mid_job_loses_its_tiles_and_comes_back() {
    let _serial = common::serial();
    let dir = TempDir::new().expect("temporary directory");
    let d = dir.path();
    let scene = common::scene_path("lights.json");
    let (_coordinator, addr) = common::start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &["--heartbeat-timeout-ms", "2000"],
        "coordinator.log",
    );
    let proxy = CutProxy::start(&addr);
    let _cut_worker = common::start_worker(d, proxy.address(), "behind-the-cut");
    common::poll("the worker to register", Duration::from_secs(20), || {
        (workers(d, &addr, &[]).len() == 1).then_some(())
    });

    // ...in small tiles, so that the first ones come back quickly.
    let mut args = vec![scene.as_str(), "--tile", "32"];
    args.extend(JOB);
    let job = common::submit(d, &addr, &args);
    common::poll("the first tiles", Duration::from_secs(30), || {
        (tiles_done(d, &addr, job) > 0).then_some(())
    });
    proxy.cut();

    // The coordinator drops the silent worker after its 2 s heartbeat timeout, and the
    // job stands still: its only worker is gone.
    common::poll(
        "the cut worker to be dropped",
        Duration::from_secs(10),
        || workers(d, &addr, &[]).is_empty().then_some(()),
    );
    let frozen = tiles_done(d, &addr, job);
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(tiles_done(d, &addr, job), frozen, "no worker, no progress");

    // Another worker finishes the job, the cut worker's leased tiles included.
    let _other = common::start_worker(d, &addr, "direct");
    let status = common::wait_done(d, &addr, job, Duration::from_secs(90));
    let reference = common::render_reference(d, &scene, "reference.png", JOB);
    let fetched = common::fetch(d, &addr, job, "fetched.png");
    common::assert_same_png(&fetched, &reference, "the job finished after a network cut");
    assert!(status["tiles_done"] == status["tiles_total"], "{status}");

    // Once the link is back, the cut worker reconnects by itself.
    proxy.restore();
    common::poll(
        "the cut worker to come back",
        Duration::from_secs(30),
        || {
            let mut now = names(&workers(d, &addr, &[]));
            now.sort();
            (now == ["behind-the-cut", "direct"]).then_some(())
        },
    );
}

#[test]
fn a_worker_behind_a_cut_that_never_ends_gives_up_on_the_connection() {
    let _serial = common::serial();
    let dir = TempDir::new().expect("temporary directory");
    let d = dir.path();
    let (_coordinator, addr) =
        common::start_coordinator(d, &d.join("data"), "127.0.0.1:0", &[], "coordinator.log");
    let proxy = CutProxy::start(&addr);
    let worker = common::start_worker(d, proxy.address(), "stranded");
    common::poll("the worker to register", Duration::from_secs(20), || {
        (workers(d, &addr, &[]).len() == 1).then_some(())
    });
    proxy.cut();
    // It hears no heartbeat from the coordinator, so it closes the connection and tries
    // again (through the same dead link) instead of waiting forever.
    common::poll(
        "the worker to notice the silence",
        Duration::from_secs(30),
        || {
            worker
                .log_text()
                .contains("nothing from the coordinator for 10 s")
                .then_some(())
        },
    );
    assert!(worker.log_text().contains("reconnecting"));
}

/// A self-signed certificate for 127.0.0.1 and localhost: (certificate, key) files.
fn certificate(dir: &Path, name: &str) -> (PathBuf, PathBuf) {
    let certified =
        rcgen::generate_simple_self_signed(vec!["127.0.0.1".to_owned(), "localhost".to_owned()])
            .expect("a certificate");
    let cert = dir.join(format!("{name}.pem"));
    let key = dir.join(format!("{name}-key.pem"));
    std::fs::write(&cert, certified.cert.pem()).expect("write the certificate");
    std::fs::write(&key, certified.signing_key.serialize_pem()).expect("write the key");
    (cert, key)
}

fn path(p: &Path) -> &str {
    p.to_str().expect("test paths are UTF-8")
}

/// The first line of a failed run's stderr, checked to be its only line.
fn one_line_error(run: common::Run, what: &str) -> String {
    assert!(!run.status.success(), "{what} should fail: {}", run.stdout);
    let lines: Vec<&str> = run.stderr.lines().collect();
    assert_eq!(
        lines.len(),
        1,
        "{what}: one line of error, got {:?}",
        run.stderr
    );
    lines[0].to_owned()
}

#[test]
fn tls_serves_trusting_peers_and_refuses_everyone_else_clearly() {
    let _serial = common::serial();
    let dir = TempDir::new().expect("temporary directory");
    let d = dir.path();
    let (cert, key) = certificate(d, "farm");
    let (stranger, _) = certificate(d, "stranger");
    let (_coordinator, addr) = common::start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &["--tls-cert", path(&cert), "--tls-key", path(&key)],
        "coordinator.log",
    );
    let tls = ["--tls-ca", path(&cert)];
    let _worker = common::start_worker_with(d, &addr, "encrypted", &tls);
    common::poll("the worker to register", Duration::from_secs(20), || {
        (workers(d, &addr, &tls).len() == 1).then_some(())
    });

    // A client through a relay that records what crosses the wire.
    let wire = CutProxy::start(&addr);
    let scene = common::scene_path("seed.json");
    let out = d.join("tls.png");
    let run = common::tessera(
        d,
        &[
            "submit",
            &scene,
            "--wait",
            "-o",
            path(&out),
            "--coordinator",
            wire.address(),
            "--tls-ca",
            path(&cert),
            "--tls-server-name",
            "localhost",
        ],
        Duration::from_secs(60),
    );
    common::ok(run, "submit --wait over TLS");
    let reference = common::render_reference(d, &scene, "reference.png", &[]);
    common::assert_same_png(&out, &reference, "a job over TLS");
    let sent = wire.upstream_bytes();
    let scene_text = std::fs::read(&scene).expect("scene");
    assert!(
        sent.len() > scene_text.len(),
        "the scene went through the relay"
    );
    assert!(
        !sent.windows(8).any(|w| w == b"\"lights\""),
        "the scene crossed the wire in clear"
    );

    // A plain client is told to use TLS.
    let plain = one_line_error(common::client(d, &addr, &["list"]), "a plain client");
    assert!(plain.contains("TLS"), "{plain}");
    // A client that trusts another certificate refuses the coordinator's.
    let untrusted = one_line_error(
        common::client(d, &addr, &["list", "--tls-ca", path(&stranger)]),
        "a client trusting another certificate",
    );
    assert!(untrusted.contains("certificate"), "{untrusted}");
    // A name the certificate does not carry is refused too.
    let wrong_name = one_line_error(
        common::client(
            d,
            &addr,
            &[
                "list",
                "--tls-ca",
                path(&cert),
                "--tls-server-name",
                "example.org",
            ],
        ),
        "a client expecting another name",
    );
    assert!(wrong_name.contains("certificate"), "{wrong_name}");
    // A worker that does not trust the certificate stops with an error at once,
    // instead of retrying forever.
    let mut lost =
        common::start_worker_with(d, &addr, "untrusting", &["--tls-ca", path(&stranger)]);
    let status = lost
        .wait_exit(Duration::from_secs(20))
        .expect("an untrusting worker exits");
    assert!(!status.success());

    // TLS to a plain coordinator fails clearly, and plain traffic is readable there
    // (the control for the check above).
    let (_plain_coordinator, plain_addr) =
        common::start_coordinator(d, &d.join("plain"), "127.0.0.1:0", &[], "plain.log");
    let tls_to_plain = one_line_error(
        common::client(d, &plain_addr, &["list", "--tls-ca", path(&cert)]),
        "TLS to a plain coordinator",
    );
    assert!(tls_to_plain.contains("TLS"), "{tls_to_plain}");
    let clear = CutProxy::start(&plain_addr);
    common::ok(
        common::tessera(
            d,
            &["submit", &scene, "--coordinator", clear.address()],
            Duration::from_secs(60),
        ),
        "plain submit",
    );
    assert!(clear
        .upstream_bytes()
        .windows(8)
        .any(|w| w == b"\"lights\""));
}
