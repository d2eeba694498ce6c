//! TLS between the farm's peers: the real binaries on 127.0.0.1.
//!
//! - A coordinator with a certificate serves a worker and a client that trust it, the
//!   image is byte-identical, the scene does not cross the wire in clear, and each
//!   misconfiguration (plain peer, untrusted certificate, TLS to a plain coordinator)
//!   fails with a one-line error.
//! - `--tls-auto` makes the coordinator's certificate once and keeps it; peers pinned to
//!   its fingerprint render end to end, and a wrong pin is refused with one line naming
//!   both fingerprints, by a client and by a worker, which exits instead of retrying.
//! - A pinned client or worker pointed at a coordinator without TLS, or at the HTTP
//!   port, says which mistake it likely is in one line.
//! - Client commands, `submit --wait` and a worker over TLS end it properly: no side
//!   logs a connection closed without `close_notify`.

use std::path::{Path, PathBuf};
use std::time::Duration;

use tempfile::TempDir;

use super::{submit_and_wait, tokens, worker_that_gives_up, SMALL};
use crate::support::cut_proxy::CutProxy;
use crate::support::{
    assert_same_png, client, free_port, ok, one_error_line, path_str, poll, render_reference,
    scene_path, shared, start_coordinator, start_worker_with, tessera, worker_names, workers_json,
};

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

#[test]
fn tls_serves_trusting_peers_and_refuses_everyone_else_clearly() {
    let _turn = shared();
    let dir = TempDir::new().expect("temporary directory");
    let d = dir.path();
    let (cert, key) = certificate(d, "farm");
    let (stranger, _) = certificate(d, "stranger");
    let (_coordinator, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &["--tls-cert", path_str(&cert), "--tls-key", path_str(&key)],
        "coordinator.log",
    );
    let tls = ["--tls-ca", path_str(&cert)];
    let _worker = start_worker_with(d, &addr, "encrypted", &tls);
    poll("the worker to register", Duration::from_secs(20), || {
        (workers_json(d, &addr, &tls).len() == 1).then_some(())
    });

    // A client through a relay that records what crosses the wire.
    let wire = CutProxy::start(&addr);
    let scene = scene_path("seed.json");
    let out = d.join("tls.png");
    let run = tessera(
        d,
        &[
            "submit",
            &scene,
            "--wait",
            "-o",
            path_str(&out),
            "--coordinator",
            wire.address(),
            "--tls-ca",
            path_str(&cert),
            "--tls-server-name",
            "localhost",
        ],
        Duration::from_secs(60),
    );
    ok(run, "submit --wait over TLS");
    let reference = render_reference(d, &scene, "reference.png", &[]);
    assert_same_png(&out, &reference, "a job over TLS");
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
    let plain = one_error_line(&client(d, &addr, &["list"]), "a plain client");
    assert!(plain.contains("TLS"), "{plain}");
    // A client that trusts another certificate refuses the coordinator's.
    let untrusted = one_error_line(
        &client(d, &addr, &["list", "--tls-ca", path_str(&stranger)]),
        "a client trusting another certificate",
    );
    assert!(untrusted.contains("certificate"), "{untrusted}");
    // A name the certificate does not carry is refused too.
    let wrong_name = one_error_line(
        &client(
            d,
            &addr,
            &[
                "list",
                "--tls-ca",
                path_str(&cert),
                "--tls-server-name",
                "example.org",
            ],
        ),
        "a client expecting another name",
    );
    assert!(wrong_name.contains("certificate"), "{wrong_name}");
    // A worker that does not trust the certificate stops with an error at once,
    // instead of retrying forever.
    let mut lost = start_worker_with(d, &addr, "untrusting", &["--tls-ca", path_str(&stranger)]);
    let status = lost
        .wait_exit(Duration::from_secs(20))
        .expect("an untrusting worker exits");
    assert!(!status.success());

    // TLS to a plain coordinator fails clearly, and plain traffic is readable there
    // (the control for the check above).
    let (_plain_coordinator, plain_addr) =
        start_coordinator(d, &d.join("plain"), "127.0.0.1:0", &[], "plain.log");
    let tls_to_plain = one_error_line(
        &client(d, &plain_addr, &["list", "--tls-ca", path_str(&cert)]),
        "TLS to a plain coordinator",
    );
    assert!(tls_to_plain.contains("TLS"), "{tls_to_plain}");
    let clear = CutProxy::start(&plain_addr);
    ok(
        tessera(
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

// ---------------------------------------------------------------------------------
// A certificate the coordinator makes, pinned by fingerprint.
// ---------------------------------------------------------------------------------

/// `tessera coordinator --data DATA --tls-auto --print-fingerprint`.
fn print_fingerprint(dir: &Path, data: &Path) -> String {
    let run = ok(
        tessera(
            dir,
            &[
                "coordinator",
                "--data",
                path_str(data),
                "--tls-auto",
                "--print-fingerprint",
            ],
            Duration::from_secs(30),
        ),
        "--print-fingerprint",
    );
    let fingerprint = run.stdout.trim().to_owned();
    assert!(
        fingerprint.len() == 64 && fingerprint.chars().all(|c| c.is_ascii_hexdigit()),
        "a SHA-256 fingerprint in hex: {fingerprint:?}"
    );
    fingerprint
}

#[test]
fn tls_auto_serves_peers_pinned_to_its_fingerprint_and_refuses_other_pins() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (worker_token, client_token) = tokens(d);
    let data = d.join("data");

    // The certificate is made once, private to the coordinator's user.
    let fingerprint = print_fingerprint(d, &data);
    #[cfg(unix)]
    for name in ["cert.pem", "key.pem"] {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(data.join("tls").join(name))
            .unwrap_or_else(|e| panic!("{name}: {e}"))
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600, "{name}");
    }
    let coordinator_args = [
        "--tls-auto",
        "--worker-token-file",
        path_str(&worker_token),
        "--client-token-file",
        path_str(&client_token),
    ];
    let (mut coordinator, addr) = start_coordinator(
        d,
        &data,
        "127.0.0.1:0",
        &coordinator_args,
        "coordinator.log",
    );
    // Logged just after the address is printed: looked for until it is there.
    poll(
        "the coordinator to log its fingerprint",
        Duration::from_secs(10),
        || coordinator.log_text().contains(&fingerprint).then_some(()),
    );

    let pin = ["--tls-fingerprint", fingerprint.as_str()];
    let client_auth = [pin[0], pin[1], "--token-file", path_str(&client_token)];
    let worker_auth = [pin[0], pin[1], "--token-file", path_str(&worker_token)];
    let _worker = start_worker_with(d, &addr, "pinned", &worker_auth);
    poll("the pinned worker to join", Duration::from_secs(30), || {
        (worker_names(&workers_json(d, &addr, &client_auth)) == ["pinned"]).then_some(())
    });
    let out = submit_and_wait(d, &addr, "tls.png", &client_auth);
    let scene = scene_path("seed.json");
    let reference = render_reference(d, &scene, "reference.png", SMALL);
    assert_same_png(&out, &reference, "a job over pinned TLS");

    // A pin of another certificate: one line with both fingerprints, from a client and
    // from a worker, which stops instead of retrying.
    let other = "ab".repeat(32);
    let line = one_error_line(
        &client(
            d,
            &addr,
            &[
                "list",
                "--tls-fingerprint",
                &other,
                "--token-file",
                path_str(&client_token),
            ],
        ),
        "a client pinned to another certificate",
    );
    assert!(
        line.contains(&addr) && line.contains(&fingerprint) && line.contains(&other),
        "{line}"
    );
    let line = worker_that_gives_up(
        d,
        &addr,
        "mispinned",
        &[
            "--tls-fingerprint",
            &other,
            "--token-file",
            path_str(&worker_token),
        ],
    );
    assert!(
        line.contains(&fingerprint) && line.contains(&other),
        "{line}"
    );
    // The same pin in the openssl form (upper case, colons) is the same pin.
    let openssl_form = fingerprint
        .to_uppercase()
        .as_bytes()
        .chunks(2)
        .map(|pair| std::str::from_utf8(pair).unwrap())
        .collect::<Vec<_>>()
        .join(":");
    ok(
        client(
            d,
            &addr,
            &[
                "list",
                "--tls-fingerprint",
                &openssl_form,
                "--token-file",
                path_str(&client_token),
            ],
        ),
        "list pinned in openssl's form",
    );
    // A bad fingerprint is a one-line usage error.
    let bad = client(d, &addr, &["list", "--tls-fingerprint", "12ab"]);
    assert!(!bad.status.success());
    assert_eq!(bad.stderr.lines().count(), 1, "{:?}", bad.stderr);
    assert!(bad.stderr.contains("64 hex digits"), "{}", bad.stderr);

    // A restarted coordinator serves the same certificate: the pins stay valid.
    coordinator.kill9();
    assert_eq!(print_fingerprint(d, &data), fingerprint);
    let (_coordinator, addr) =
        start_coordinator(d, &data, "127.0.0.1:0", &coordinator_args, "restarted.log");
    ok(
        client(
            d,
            &addr,
            &[
                "list",
                pin[0],
                pin[1],
                "--token-file",
                path_str(&client_token),
            ],
        ),
        "list after a restart, with the same pin",
    );
}

#[test]
fn a_pinned_peer_pointed_at_plain_ports_names_the_likely_mistake_in_one_line() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    // A coordinator without TLS, and its HTTP port.
    let http = format!("127.0.0.1:{}", free_port());
    let (_coordinator, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &["--http", &http],
        "coordinator.log",
    );
    let pin = "ab".repeat(32);
    let pinned = ["--tls-fingerprint", pin.as_str()];
    let no_tls = format!(
        "{addr} does not speak TLS: is it the coordinator's HTTP port, or a coordinator \
         started without TLS?"
    );
    let http_port = format!(
        "{http} answered in HTTP: this looks like the coordinator's HTTP port (--http); give \
         the port it listens on for workers and clients (--listen, 7878 by default)"
    );
    let line = one_error_line(
        &client(d, &addr, &["list", pinned[0], pinned[1]]),
        "a pinned client at a coordinator without TLS",
    );
    assert_eq!(line, format!("error: {no_tls}"));
    let line = one_error_line(
        &client(d, &http, &["list", pinned[0], pinned[1]]),
        "a pinned client at the HTTP port",
    );
    assert_eq!(line, format!("error: {http_port}"));
    // A worker says the same, and stops instead of retrying.
    let line = worker_that_gives_up(d, &addr, "pinned-plain", &pinned);
    assert!(line.ends_with(&no_tls), "{line}");
    let line = worker_that_gives_up(d, &http, "pinned-http", &pinned);
    assert!(line.ends_with(&http_port), "{line}");
}

#[test]
fn peers_over_tls_close_it_properly_and_nobody_logs_a_missing_close_notify() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let data = d.join("data");
    let fingerprint = print_fingerprint(d, &data);
    let http = format!("127.0.0.1:{}", free_port());
    let (coordinator, addr) = start_coordinator(
        d,
        &data,
        "127.0.0.1:0",
        &["--tls-auto", "--http", &http],
        "coordinator.log",
    );
    let pin = ["--tls-fingerprint", fingerprint.as_str()];
    // Its HTTP port serves TLS with the same certificate: a peer pointed there gets
    // through the handshake, and is then told it found the HTTP port.
    let line = one_error_line(
        &client(d, &http, &["list", pin[0], pin[1]]),
        "a pinned client at the HTTPS port",
    );
    assert_eq!(
        line,
        format!(
            "error: {http} answered in HTTP: this looks like the coordinator's HTTP port \
             (--http); give the port it listens on for workers and clients (--listen, 7878 \
             by default)"
        )
    );
    let worker = start_worker_with(d, &addr, "pinned", &pin);
    poll("the pinned worker to join", Duration::from_secs(30), || {
        (worker_names(&workers_json(d, &addr, &pin)) == ["pinned"]).then_some(())
    });
    let mut said = Vec::new();
    for args in [&["list"][..], &["workers"], &["list", "--json"]] {
        let mut args = args.to_vec();
        args.extend(pin);
        let run = ok(client(d, &addr, &args), "a client command over TLS");
        said.push(format!("{}{}", run.stdout, run.stderr));
    }
    let scene = scene_path("seed.json");
    let out = d.join("out.png");
    let mut args = vec!["submit", &scene, "--wait", "-o", path_str(&out)];
    args.extend(SMALL);
    args.extend(pin);
    let run = ok(client(d, &addr, &args), "submit --wait over TLS");
    said.push(format!("{}{}", run.stdout, run.stderr));
    // The worker leaves too (a drain: it closes its connection itself).
    let mut worker = worker;
    worker.signal("TERM");
    worker
        .wait_exit(Duration::from_secs(30))
        .expect("the worker did not exit on SIGTERM");
    poll("the worker to be gone", Duration::from_secs(10), || {
        workers_json(d, &addr, &pin).is_empty().then_some(())
    });
    let mut logs = said.join("\n");
    logs.push_str(&coordinator.log_text());
    logs.push_str(&worker.log_text());
    assert!(!logs.contains("close_notify"), "{logs}");
}
