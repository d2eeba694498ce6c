//! Peers prove who they are, in both directions: the real binaries on 127.0.0.1.
//!
//! - A coordinator holds two tokens, one for workers and one for clients. A client's
//!   token cannot join as a worker (the worker is refused, exits and renders nothing,
//!   while a real worker finishes the job with `tessera render`'s exact bytes), and a
//!   worker's token cannot be used by a client.
//! - A worker or a client that holds a token refuses a coordinator that does not prove
//!   it knows that token: a listener in this test that speaks the protocol without the
//!   token (accepting at once, or challenging with a made-up proof) gets nothing past
//!   the peer's `Hello`, never a tile result, and the peer stops with one line naming
//!   the address.
//! - `--tls-auto` makes the coordinator's certificate once and keeps it; peers pinned to
//!   its fingerprint render end to end, and a wrong pin is refused with one line naming
//!   both fingerprints, by a client and by a worker, which exits instead of retrying.
//! - The coordinator refuses one shared token, two equal tokens, and a network address
//!   without both tokens, each with one line.

mod common;

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use common::Run;
use protocol::{Hello, Role, ToWorker, Welcome};
use tempfile::TempDir;

/// A quick job: the seed scene at 96 × 64, one sample per pixel.
const SMALL: &[&str] = &["--width", "96", "--height", "64", "--aa", "1"];

/// How long a peer that must give up may take to do so.
const GIVES_UP_WITHIN: Duration = Duration::from_secs(20);

fn path(p: &Path) -> &str {
    p.to_str().expect("test paths are UTF-8")
}

/// A worker token and a client token in `dir`, as an operator would make them (each
/// with a final newline, which is trimmed).
fn tokens(dir: &Path) -> (PathBuf, PathBuf) {
    let worker = dir.join("worker.token");
    let client = dir.join("client.token");
    std::fs::write(
        &worker,
        "9f1c2e7a5b3d4c6e8a0b1c2d3e4f5a6b7c8d9e0f1a2b3c4d\n",
    )
    .unwrap();
    std::fs::write(
        &client,
        "0e9d8c7b6a5f4e3d2c1b0a9f8e7d6c5b4a3f2e1d0c9b8a7f\n",
    )
    .unwrap();
    (worker, client)
}

/// The one line a failed command printed, which starts with `error: `.
fn one_error_line(run: &Run, what: &str) -> String {
    assert!(!run.status.success(), "{what} succeeded: {}", run.stdout);
    let lines: Vec<&str> = run.stderr.lines().collect();
    assert_eq!(
        lines.len(),
        1,
        "{what}: one line on stderr: {:?}",
        run.stderr
    );
    assert!(lines[0].starts_with("error: "), "{what}: {:?}", lines[0]);
    lines[0].to_owned()
}

/// The last line of a daemon's log, which must be its one `error: ` line.
fn final_error(log: &str, what: &str) -> String {
    let errors: Vec<&str> = log.lines().filter(|l| l.starts_with("error: ")).collect();
    assert_eq!(errors.len(), 1, "{what}: one error line in {log:?}");
    assert_eq!(
        log.lines().last(),
        Some(errors[0]),
        "{what}: the error is the last line"
    );
    errors[0].to_owned()
}

/// Starts a worker with `extra` arguments and waits for it to exit on its own, which it
/// must do, unsuccessfully, within [`GIVES_UP_WITHIN`]: its error line.
fn worker_that_gives_up(dir: &Path, addr: &str, name: &str, extra: &[&str]) -> String {
    let mut worker = common::start_worker_with(dir, addr, name, extra);
    let status = worker
        .wait_exit(GIVES_UP_WITHIN)
        .unwrap_or_else(|| panic!("worker {name} still running: it must give up at once"));
    assert!(!status.success(), "worker {name} exited successfully");
    final_error(&worker.log_text(), &format!("worker {name}"))
}

fn workers_json(dir: &Path, addr: &str, auth: &[&str]) -> Vec<serde_json::Value> {
    let mut args = vec!["workers", "--json"];
    args.extend(auth);
    let run = common::ok(common::client(dir, addr, &args), "workers --json");
    match serde_json::from_str(run.stdout.trim()) {
        Ok(serde_json::Value::Array(workers)) => workers,
        other => panic!("workers --json: {other:?}"),
    }
}

fn worker_names(workers: &[serde_json::Value]) -> Vec<String> {
    workers
        .iter()
        .map(|w| w["name"].as_str().expect("a name").to_owned())
        .collect()
}

/// `tessera submit SCENE --wait -o DIR/NAME SMALL AUTH...`, which must succeed.
fn submit_and_wait(dir: &Path, addr: &str, name: &str, auth: &[&str]) -> PathBuf {
    let scene = common::scene_path("seed.json");
    let out = dir.join(name);
    let mut args = vec!["submit", &scene, "--wait", "-o", path(&out)];
    args.extend(SMALL);
    args.extend(auth);
    common::ok(common::client(dir, addr, &args), "submit --wait");
    out
}

#[test]
fn a_token_of_the_other_role_is_refused_and_the_farm_still_renders_exactly() {
    let _serial = common::serial();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (worker_token, client_token) = tokens(d);
    let data = d.join("data");
    let (_coordinator, addr) = common::start_coordinator(
        d,
        &data,
        "127.0.0.1:0",
        &[
            "--worker-token-file",
            path(&worker_token),
            "--client-token-file",
            path(&client_token),
        ],
        "coordinator.log",
    );
    let as_client = ["--token-file", path(&client_token)];
    let as_worker = ["--token-file", path(&worker_token)];

    // A worker with the client's token: refused at once, for good.
    let line = worker_that_gives_up(d, &addr, "impostor", &as_client);
    assert!(
        line.contains(&addr) && line.contains("authentication failed"),
        "{line}"
    );
    assert!(line.contains("worker token"), "{line}");
    // A worker without a token is told it needs one.
    let line = worker_that_gives_up(d, &addr, "anonymous", &[]);
    assert!(
        line.contains("a token is required") && line.contains("worker token"),
        "{line}"
    );

    // A client with the workers' token, or none, is refused; with its own it works.
    let line = one_error_line(
        &common::client(d, &addr, &["list", "--token-file", path(&worker_token)]),
        "list with the worker token",
    );
    assert!(
        line.contains(&addr)
            && line.contains("authentication failed")
            && line.contains("client token"),
        "{line}"
    );
    let line = one_error_line(&common::client(d, &addr, &["list"]), "list without a token");
    assert!(line.contains("a token is required"), "{line}");
    common::ok(
        common::client(d, &addr, &["list", "--token-file", path(&client_token)]),
        "list with the client token",
    );

    // A real worker renders the job; the refused ones never joined.
    let _worker = common::start_worker_with(d, &addr, "real", &as_worker);
    common::poll("the real worker to join", Duration::from_secs(30), || {
        (worker_names(&workers_json(d, &addr, &as_client)) == ["real"]).then_some(())
    });
    let out = submit_and_wait(d, &addr, "farm.png", &as_client);
    let scene = common::scene_path("seed.json");
    let reference = common::render_reference(d, &scene, "reference.png", SMALL);
    common::assert_same_png(&out, &reference, "the job of an authenticated farm");
    assert_eq!(
        worker_names(&workers_json(d, &addr, &as_client)),
        ["real"],
        "only the real worker ever joined"
    );
    let record = std::fs::read_to_string(data.join("jobs").join("1").join("job.json"))
        .expect("the job's record");
    let record: serde_json::Value = serde_json::from_str(&record).expect("job.json is JSON");
    let tiles_by = record["tiles_per_worker"]
        .as_object()
        .expect("tiles per worker");
    assert_eq!(
        tiles_by.keys().collect::<Vec<_>>(),
        ["real"],
        "every tile came from the real worker: {record}"
    );
}

// ---------------------------------------------------------------------------------
// An impostor coordinator.
// ---------------------------------------------------------------------------------

/// How the impostor answers a `Hello`, without knowing any token.
#[derive(Clone, Copy, Debug)]
enum Impostor {
    /// `Accepted` at once, then a scene and a tile to render.
    AcceptsAnyone,
    /// A `Challenge` whose proof is made up.
    ChallengesWithoutTheToken,
}

fn read_frame(stream: &mut TcpStream) -> Option<Vec<u8>> {
    let mut prefix = [0u8; 4];
    stream.read_exact(&mut prefix).ok()?;
    let mut body = vec![0u8; u32::from_be_bytes(prefix) as usize];
    stream.read_exact(&mut body).ok()?;
    Some(body)
}

fn write_frame(stream: &mut TcpStream, body: &[u8]) {
    let mut frame = (body.len() as u32).to_be_bytes().to_vec();
    frame.extend_from_slice(body);
    // The peer may already have hung up: what it received is what the test checks.
    let _ = stream.write_all(&frame);
}

/// A listener that speaks the protocol like a coordinator but knows no token. It serves
/// one connection and returns every frame the peer sent on it, until the peer closes
/// (or 20 s pass).
fn impostor(behaviour: Impostor) -> (String, JoinHandle<Vec<Vec<u8>>>) {
    let listener = TcpListener::bind("127.0.0.1:0").expect("cannot bind the impostor");
    let addr = listener.local_addr().unwrap().to_string();
    listener.set_nonblocking(true).unwrap();
    let handle = thread::spawn(move || {
        let deadline = Instant::now() + Duration::from_secs(30);
        let mut stream = loop {
            match listener.accept() {
                Ok((stream, _)) => break stream,
                Err(_) if Instant::now() < deadline => thread::sleep(Duration::from_millis(10)),
                Err(e) => panic!("no peer came to the impostor: {e}"),
            }
        };
        stream.set_nonblocking(false).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(20)))
            .unwrap();
        let mut received = Vec::new();
        let Some(hello) = read_frame(&mut stream) else {
            return received;
        };
        received.push(hello);
        match behaviour {
            Impostor::AcceptsAnyone => {
                let accepted = Welcome::Accepted {
                    version: protocol::PROTOCOL_VERSION,
                };
                write_frame(&mut stream, &protocol::wire::encode(&accepted));
                // Bait: work to do, as a coordinator would send it.
                let bait = ToWorker::Scene {
                    hash: [0; 32],
                    scene: r#"{"lights": [], "objects": []}"#.into(),
                };
                write_frame(&mut stream, &protocol::wire::encode(&bait));
            }
            Impostor::ChallengesWithoutTheToken => {
                let challenge = Welcome::Challenge {
                    nonce: [7; 32],
                    proof: [0x5a; 32],
                };
                write_frame(&mut stream, &protocol::wire::encode(&challenge));
            }
        }
        while let Some(frame) = read_frame(&mut stream) {
            received.push(frame);
        }
        received
    });
    (addr, handle)
}

/// The impostor got the peer's `Hello` (as `role`, with a fresh nonce) and nothing else.
fn only_a_hello(frames: &[Vec<u8>], worker: bool, what: &str) {
    assert_eq!(
        frames.len(),
        1,
        "{what}: the peer sent more than its Hello (a proof or a result) to an impostor"
    );
    let hello = Hello::from_frame(&frames[0]).expect("a hello of this version");
    assert_eq!(matches!(hello.role, Role::Worker { .. }), worker, "{what}");
    assert_ne!(
        hello.nonce, [0; 32],
        "{what}: a peer with a token sends a nonce"
    );
}

#[test]
fn a_peer_with_a_token_refuses_a_coordinator_that_does_not_prove_it() {
    let _serial = common::serial();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (worker_token, client_token) = tokens(d);
    for behaviour in [Impostor::AcceptsAnyone, Impostor::ChallengesWithoutTheToken] {
        let what = format!("a worker facing an impostor that {behaviour:?}");
        let (addr, impostor_thread) = impostor(behaviour);
        let line = worker_that_gives_up(
            d,
            &addr,
            &format!("{behaviour:?}"),
            &["--token-file", path(&worker_token)],
        );
        assert!(
            line.contains(&format!("the coordinator at {addr}"))
                && line.contains("authentication failed")
                && line.contains("refusing it"),
            "{what}: {line}"
        );
        let frames = impostor_thread.join().expect("the impostor panicked");
        only_a_hello(&frames, true, &what);

        let what = format!("a client facing an impostor that {behaviour:?}");
        let (addr, impostor_thread) = impostor(behaviour);
        let line = one_error_line(
            &common::client(d, &addr, &["list", "--token-file", path(&client_token)]),
            &what,
        );
        assert!(
            line.contains(&format!("the coordinator at {addr}"))
                && line.contains("authentication failed")
                && line.contains("client token"),
            "{what}: {line}"
        );
        let frames = impostor_thread.join().expect("the impostor panicked");
        only_a_hello(&frames, false, &what);
    }
}

// ---------------------------------------------------------------------------------
// TLS with a certificate the coordinator makes, pinned by fingerprint.
// ---------------------------------------------------------------------------------

/// `tessera coordinator --data DATA --tls-auto --print-fingerprint`.
fn print_fingerprint(dir: &Path, data: &Path) -> String {
    let run = common::ok(
        common::tessera(
            dir,
            &[
                "coordinator",
                "--data",
                path(data),
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
    let _serial = common::serial();
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
        path(&worker_token),
        "--client-token-file",
        path(&client_token),
    ];
    let (mut coordinator, addr) = common::start_coordinator(
        d,
        &data,
        "127.0.0.1:0",
        &coordinator_args,
        "coordinator.log",
    );
    // Logged just after the address is printed: looked for until it is there.
    common::poll(
        "the coordinator to log its fingerprint",
        Duration::from_secs(10),
        || coordinator.log_text().contains(&fingerprint).then_some(()),
    );

    let pin = ["--tls-fingerprint", fingerprint.as_str()];
    let client_auth = [pin[0], pin[1], "--token-file", path(&client_token)];
    let worker_auth = [pin[0], pin[1], "--token-file", path(&worker_token)];
    let _worker = common::start_worker_with(d, &addr, "pinned", &worker_auth);
    common::poll("the pinned worker to join", Duration::from_secs(30), || {
        (worker_names(&workers_json(d, &addr, &client_auth)) == ["pinned"]).then_some(())
    });
    let out = submit_and_wait(d, &addr, "tls.png", &client_auth);
    let scene = common::scene_path("seed.json");
    let reference = common::render_reference(d, &scene, "reference.png", SMALL);
    common::assert_same_png(&out, &reference, "a job over pinned TLS");

    // A pin of another certificate: one line with both fingerprints, from a client and
    // from a worker, which stops instead of retrying.
    let other = "ab".repeat(32);
    let line = one_error_line(
        &common::client(
            d,
            &addr,
            &[
                "list",
                "--tls-fingerprint",
                &other,
                "--token-file",
                path(&client_token),
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
            path(&worker_token),
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
    common::ok(
        common::client(
            d,
            &addr,
            &[
                "list",
                "--tls-fingerprint",
                &openssl_form,
                "--token-file",
                path(&client_token),
            ],
        ),
        "list pinned in openssl's form",
    );
    // A bad fingerprint is a one-line usage error.
    let bad = common::client(d, &addr, &["list", "--tls-fingerprint", "12ab"]);
    assert!(!bad.status.success());
    assert_eq!(bad.stderr.lines().count(), 1, "{:?}", bad.stderr);
    assert!(bad.stderr.contains("64 hex digits"), "{}", bad.stderr);

    // A restarted coordinator serves the same certificate: the pins stay valid.
    coordinator.kill9();
    assert_eq!(print_fingerprint(d, &data), fingerprint);
    let (_coordinator, addr) =
        common::start_coordinator(d, &data, "127.0.0.1:0", &coordinator_args, "restarted.log");
    common::ok(
        common::client(
            d,
            &addr,
            &["list", pin[0], pin[1], "--token-file", path(&client_token)],
        ),
        "list after a restart, with the same pin",
    );
}

// ---------------------------------------------------------------------------------
// What the coordinator refuses to start with.
// ---------------------------------------------------------------------------------

#[test]
fn the_coordinator_refuses_one_shared_token_equal_tokens_and_an_open_network_port() {
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (worker_token, client_token) = tokens(d);
    let coordinator = |extra: &[&str]| {
        let mut args = vec!["coordinator", "--listen", "127.0.0.1:0", "--data", "data"];
        args.extend(extra);
        common::tessera(d, &args, Duration::from_secs(30))
    };

    let line = one_error_line(
        &coordinator(&["--token-file", path(&worker_token)]),
        "a coordinator given one --token-file",
    );
    assert!(
        line.contains("--worker-token-file") && line.contains("--client-token-file"),
        "{line}"
    );
    let line = one_error_line(
        &coordinator(&[
            "--worker-token-file",
            path(&worker_token),
            "--client-token-file",
            path(&worker_token),
        ]),
        "a coordinator given the same token twice",
    );
    assert!(line.contains("the same secret"), "{line}");

    // The shared token from the environment, as an old service file would set it.
    let env_run = std::process::Command::new(common::BIN)
        .args(["coordinator", "--listen", "127.0.0.1:0", "--data", "data"])
        .current_dir(d)
        .env("TESSERA_TOKEN", "one secret for everyone")
        .stdin(std::process::Stdio::null())
        .output()
        .expect("cannot run the coordinator");
    let stderr = String::from_utf8_lossy(&env_run.stderr);
    assert!(!env_run.status.success());
    assert_eq!(stderr.lines().count(), 1, "{stderr:?}");
    assert!(
        stderr.contains("TESSERA_TOKEN is set") && stderr.contains("--client-token-file"),
        "{stderr}"
    );

    let config = d.join("config.toml");
    std::fs::write(
        &config,
        format!("[coordinator]\ntoken-file = {:?}\n", path(&worker_token)),
    )
    .unwrap();
    let line = one_error_line(
        &coordinator(&["--config", path(&config)]),
        "a config file with token-file",
    );
    assert!(
        line.contains("worker-token-file") && line.contains("client-token-file"),
        "{line}"
    );

    // A network address needs both tokens (nothing is bound when it is refused).
    let open = |extra: &[&str]| {
        let mut args = vec!["coordinator", "--listen", "0.0.0.0:0", "--data", "data"];
        args.extend(extra);
        common::tessera(d, &args, Duration::from_secs(30))
    };
    let line = one_error_line(
        &open(&["--worker-token-file", path(&worker_token)]),
        "0.0.0.0 with the worker token only",
    );
    assert!(line.contains("without a token for clients"), "{line}");
    let line = one_error_line(&open(&[]), "0.0.0.0 without tokens");
    assert!(line.contains("without a token"), "{line}");
    let line = one_error_line(
        &open(&["--client-token-file", path(&client_token)]),
        "0.0.0.0 with the client token only",
    );
    assert!(line.contains("without a token for workers"), "{line}");
}
