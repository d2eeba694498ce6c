//! Peers prove who they are, in both directions: the real binaries on 127.0.0.1.
//!
//! - A farm with tokens admits only peers that prove them: a client without one, or
//!   with a wrong one, and a worker without one are refused; a worker given its token
//!   through the environment renders the job, with `tessera render`'s bytes. Without
//!   tokens, only loopback addresses are served.
//! - A coordinator holds two tokens, one for workers and one for clients. A client's
//!   token cannot join as a worker (the worker is refused, exits and renders nothing,
//!   while a real worker finishes the job with `tessera render`'s exact bytes), and a
//!   worker's token cannot be used by a client.
//! - A worker or a client that holds a token refuses a coordinator that does not prove
//!   it knows that token: a listener in this test that speaks the protocol without the
//!   token (accepting at once, or challenging with a made-up proof) gets nothing past
//!   the peer's `Hello`, never a tile result, and the peer stops with one line naming
//!   the address.
//! - The coordinator refuses one shared token, two equal tokens, and a network address
//!   without both tokens, each with one line.

use std::io::Write;
use std::net::{TcpListener, TcpStream};
use std::process::{Command, Stdio};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use protocol::{Hello, Role, ToWorker, Welcome};
use tempfile::TempDir;

use super::{submit_and_wait, tokens, worker_that_gives_up, SMALL};
use crate::support::wire::{frame, read_frame_until_closed};
use crate::support::{
    assert_same_png, client, ok, one_error_line, path_str, poll, render_reference, scene_path,
    shared, start_coordinator, start_worker_with, tessera, worker_names, workers_json,
    write_token_file, Daemon, BIN,
};

#[test]
fn a_farm_with_tokens_admits_only_peers_that_prove_them() {
    let _turn = shared();
    let dir = TempDir::new().expect("cannot create a temporary directory");
    let token = dir.path().join("client-token");
    write_token_file(&token, "correct horse\n");
    let worker_token = dir.path().join("worker-token");
    write_token_file(&worker_token, "  tr0ub4dor &3\n");
    let wrong = dir.path().join("wrong");
    write_token_file(&wrong, "battery staple\n");
    let token_arg = path_str(&token);
    let worker_token_arg = path_str(&worker_token);
    let timeout = Duration::from_secs(60);

    // Without a token, only loopback addresses are served (nothing is bound here).
    let refused = tessera(
        dir.path(),
        &["coordinator", "--listen", "0.0.0.0:0", "--data", "d"],
        timeout,
    );
    let line = one_error_line(&refused, "coordinator on 0.0.0.0 without a token");
    assert!(line.contains("without a token"), "{line}");

    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &dir.path().join("data"),
        "127.0.0.1:0",
        &[
            "--client-token-file",
            token_arg,
            "--worker-token-file",
            worker_token_arg,
        ],
        "coordinator.log",
    );
    let list = |extra: &[&str]| client(dir.path(), &addr, &[&["list"][..], extra].concat());

    let anonymous = one_error_line(&list(&[]), "list without a token");
    assert!(
        anonymous.contains("a token is required") && anonymous.contains(&addr),
        "{anonymous}"
    );
    let wrong_token = one_error_line(&list(&["--token-file", path_str(&wrong)]), "wrong token");
    assert!(
        wrong_token.contains("authentication failed"),
        "{wrong_token}"
    );
    ok(list(&["--token-file", token_arg]), "list with the token");

    // A worker without the token is refused for good and exits; one with it (from the
    // environment) joins and renders.
    let anonymous_worker = tessera(
        dir.path(),
        &["worker", "--coordinator", addr.as_str(), "--threads", "1"],
        timeout,
    );
    assert!(!anonymous_worker.status.success());
    assert!(anonymous_worker.stderr.contains("a token is required"));
    let worker = Command::new(BIN)
        .args([
            "worker",
            "--coordinator",
            addr.as_str(),
            "--threads",
            "2",
            "--name",
            "trusted",
        ])
        .env("TESSERA_TOKEN", "tr0ub4dor &3")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("cannot start a worker");
    let _worker = Daemon {
        name: "worker".into(),
        child: worker,
        log: None,
    };
    let size = ["--width", "200", "--height", "150"];
    let out = dir.path().join("seed.png");
    let seed = scene_path("seed.json");
    let submit = ["submit", seed.as_str(), "--wait", "-o", path_str(&out)];
    let auth = ["--token-file", token_arg];
    ok(
        client(dir.path(), &addr, &[&submit[..], &auth, &size].concat()),
        "submit with the token",
    );
    let reference = render_reference(dir.path(), &seed, "reference.png", &size);
    assert_same_png(
        &out,
        &reference,
        "the image rendered by an authenticated farm",
    );
}

#[test]
fn a_token_of_the_other_role_is_refused_and_the_farm_still_renders_exactly() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (worker_token, client_token) = tokens(d);
    let data = d.join("data");
    let (_coordinator, addr) = start_coordinator(
        d,
        &data,
        "127.0.0.1:0",
        &[
            "--worker-token-file",
            path_str(&worker_token),
            "--client-token-file",
            path_str(&client_token),
        ],
        "coordinator.log",
    );
    let as_client = ["--token-file", path_str(&client_token)];
    let as_worker = ["--token-file", path_str(&worker_token)];

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
        &client(d, &addr, &["list", "--token-file", path_str(&worker_token)]),
        "list with the worker token",
    );
    assert!(
        line.contains(&addr)
            && line.contains("authentication failed")
            && line.contains("client token"),
        "{line}"
    );
    let line = one_error_line(&client(d, &addr, &["list"]), "list without a token");
    assert!(line.contains("a token is required"), "{line}");
    ok(
        client(d, &addr, &["list", "--token-file", path_str(&client_token)]),
        "list with the client token",
    );

    // A real worker renders the job; the refused ones never joined.
    let _worker = start_worker_with(d, &addr, "real", &as_worker);
    poll("the real worker to join", Duration::from_secs(30), || {
        (worker_names(&workers_json(d, &addr, &as_client)) == ["real"]).then_some(())
    });
    let out = submit_and_wait(d, &addr, "farm.png", &as_client);
    let scene = scene_path("seed.json");
    let reference = render_reference(d, &scene, "reference.png", SMALL);
    assert_same_png(&out, &reference, "the job of an authenticated farm");
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

/// Sends a frame to a peer that may already have hung up: what it received is what the
/// tests check.
fn offer(stream: &mut TcpStream, body: &[u8]) {
    let _ = stream.write_all(&frame(body));
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
        let Some(hello) = read_frame_until_closed(&mut stream, "a frame from the peer") else {
            return received;
        };
        received.push(hello);
        match behaviour {
            Impostor::AcceptsAnyone => {
                let accepted = Welcome::Accepted {
                    version: protocol::PROTOCOL_VERSION,
                };
                offer(&mut stream, &protocol::wire::encode(&accepted));
                // Bait: work to do, as a coordinator would send it.
                let bait = ToWorker::Scene {
                    hash: [0; 32],
                    scene: r#"{"lights": [], "objects": []}"#.into(),
                    assets: Vec::new(),
                };
                offer(&mut stream, &protocol::wire::encode(&bait));
            }
            Impostor::ChallengesWithoutTheToken => {
                let challenge = Welcome::Challenge {
                    nonce: [7; 32],
                    proof: [0x5a; 32],
                };
                offer(&mut stream, &protocol::wire::encode(&challenge));
            }
        }
        while let Some(frame) = read_frame_until_closed(&mut stream, "a frame from the peer") {
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
    let _turn = shared();
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
            &["--token-file", path_str(&worker_token)],
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
            &client(d, &addr, &["list", "--token-file", path_str(&client_token)]),
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
// What the coordinator refuses to start with.
// ---------------------------------------------------------------------------------

#[test]
fn the_coordinator_refuses_one_shared_token_equal_tokens_and_an_open_network_port() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (worker_token, client_token) = tokens(d);
    let coordinator = |extra: &[&str]| {
        let mut args = vec!["coordinator", "--listen", "127.0.0.1:0", "--data", "data"];
        args.extend(extra);
        tessera(d, &args, Duration::from_secs(30))
    };

    let line = one_error_line(
        &coordinator(&["--token-file", path_str(&worker_token)]),
        "a coordinator given one --token-file",
    );
    assert!(
        line.contains("--worker-token-file") && line.contains("--client-token-file"),
        "{line}"
    );
    let line = one_error_line(
        &coordinator(&[
            "--worker-token-file",
            path_str(&worker_token),
            "--client-token-file",
            path_str(&worker_token),
        ]),
        "a coordinator given the same token twice",
    );
    assert!(line.contains("the same secret"), "{line}");

    // The shared token from the environment, as an old service file would set it.
    let env_run = std::process::Command::new(BIN)
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
        format!(
            "[coordinator]\ntoken-file = {:?}\n",
            path_str(&worker_token)
        ),
    )
    .unwrap();
    let line = one_error_line(
        &coordinator(&["--config", path_str(&config)]),
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
        tessera(d, &args, Duration::from_secs(30))
    };
    let line = one_error_line(
        &open(&["--worker-token-file", path_str(&worker_token)]),
        "0.0.0.0 with the worker token only",
    );
    assert!(line.contains("without a token for clients"), "{line}");
    let line = one_error_line(&open(&[]), "0.0.0.0 without tokens");
    assert!(line.contains("without a token"), "{line}");
    let line = one_error_line(
        &open(&["--client-token-file", path_str(&client_token)]),
        "0.0.0.0 with the client token only",
    );
    assert!(line.contains("without a token for workers"), "{line}");
}
