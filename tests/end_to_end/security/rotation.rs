//! Rotating the farm's tokens without stopping it: the real binaries on 127.0.0.1.
//!
//! - Under load (three workers, a job running, a client following it), new token files
//!   for both roles and SIGHUP: the workers and the client, on the previous tokens, go
//!   on; a client with the old token is accepted within the overlap window and refused
//!   after it. When the window closes the peers on the old tokens are disconnected and
//!   reconnect with their files, replaced meanwhile: every worker is back, on the new
//!   key (`tessera workers --json`), and the job ends with `tessera render`'s bytes. A
//!   third, unknown token is refused, to a worker too, which gives up.
//! - A reload that fails (an empty token file) keeps the tokens in use, with one error
//!   line, and the coordinator serves on.
//! - A peer of the previous protocol version is refused with one line naming both.

use std::io::Read;
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use protocol::{KeyId, Welcome};
use serde_json::Value;
use tempfile::TempDir;

use super::{worker_that_gives_up, GIVES_UP_WITHIN};
use crate::support::wire::{read_frame, send_frame};
use crate::support::{
    assert_same_png, client, exclusive, ok, one_error_line, path_str, poll, render_reference,
    scene_path, shared, spawn_tessera, start_coordinator, start_worker_with, workers_json,
    write_token_file, Daemon,
};

/// The overlap window of these tests: long enough for a few client commands after
/// the SIGHUP, short enough to wait for.
const WINDOW: Duration = Duration::from_secs(3);

/// A job of several seconds on three one-thread workers, so that it runs through the
/// whole rotation.
const LONG: &[&str] = &["--width", "1280", "--height", "800", "--aa", "8"];

/// Writes a token file as an operator would (with a final newline, which is trimmed).
fn write_token(path: &Path, token: &str) {
    write_token_file(path, &format!("{token}\n"));
}

/// The key id `tessera` shows for `token`.
fn key(token: &str) -> String {
    KeyId::of(token.as_bytes()).to_string()
}

/// A token file in `dir` named `name`, holding `token`.
fn token_file(dir: &Path, name: &str, token: &str) -> PathBuf {
    let path = dir.join(name);
    write_token(&path, token);
    path
}

/// Each listed worker's name, key id and standing, sorted by name.
fn worker_keys(workers: &[Value]) -> Vec<(String, String, String)> {
    let mut keys: Vec<_> = workers
        .iter()
        .map(|w| {
            (
                w["name"].as_str().expect("a name").to_owned(),
                w["key"]["id"].as_str().unwrap_or("none").to_owned(),
                w["key"]["standing"].as_str().unwrap_or("none").to_owned(),
            )
        })
        .collect();
    keys.sort();
    keys
}

/// The three workers, all on `key` with `standing`.
fn all_on(key: &str, standing: &str) -> Vec<(String, String, String)> {
    ["w0", "w1", "w2"]
        .map(|name| (name.to_owned(), key.to_owned(), standing.to_owned()))
        .to_vec()
}

/// `tessera status 1 --json` with the client token in `token`; `None` if it failed (the
/// job is not stored yet).
fn try_first_job(dir: &Path, addr: &str, token: &Path) -> Option<Value> {
    let run = client(
        dir,
        addr,
        &["status", "1", "--json", "--token-file", path_str(token)],
    );
    run.status
        .success()
        .then(|| serde_json::from_str(run.stdout.trim()).expect("status --json is JSON"))
}

/// [`try_first_job`], which must succeed.
fn first_job(dir: &Path, addr: &str, token: &Path) -> Value {
    try_first_job(dir, addr, token).expect("the status of job 1")
}

/// Lines of the coordinator's log that contain `text`.
fn logged(coordinator: &Daemon, text: &str) -> usize {
    coordinator
        .log_text()
        .lines()
        .filter(|l| l.contains(text))
        .count()
}

#[test]
fn tokens_rotate_under_load_and_no_worker_is_lost() {
    // Timing matters: the overlap window is a few seconds long.
    let _turn = exclusive();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let scene = scene_path("seed.json");
    let reference = render_reference(d, &scene, "reference.png", LONG);

    // The coordinator's files, and each peer's own copy of its role's token.
    let coordinator_worker = token_file(d, "coordinator-worker.token", "worker-old-7f3a");
    let coordinator_client = token_file(d, "coordinator-client.token", "client-old-92be");
    let worker_files: Vec<PathBuf> = (0..3)
        .map(|i| token_file(d, &format!("w{i}.token"), "worker-old-7f3a"))
        .collect();
    let client_file = token_file(d, "client.token", "client-old-92be");
    let old_client = token_file(d, "old-client.token", "client-old-92be");
    let new_client = token_file(d, "new-client.token", "client-new-51c4");
    let stranger = token_file(d, "stranger.token", "nobody-knows-this-0d6e");
    let (coordinator_daemon, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &[
            "--worker-token-file",
            path_str(&coordinator_worker),
            "--client-token-file",
            path_str(&coordinator_client),
            "--token-overlap",
            "3s",
        ],
        "coordinator.log",
    );
    let mut coordinator = coordinator_daemon;
    let mut workers: Vec<Daemon> = worker_files
        .iter()
        .enumerate()
        .map(|(i, file)| {
            start_worker_with(
                d,
                &addr,
                &format!("w{i}"),
                &["--token-file", path_str(file)],
            )
        })
        .collect();
    let as_client = ["--token-file", path_str(&client_file)];
    poll(
        "three workers on the first key",
        Duration::from_secs(30),
        || {
            (worker_keys(&workers_json(d, &addr, &as_client))
                == all_on(&key("worker-old-7f3a"), "current"))
            .then_some(())
        },
    );

    // A client follows its job on one connection, with its own token file.
    let out = d.join("farm.png");
    let mut submit_args = vec!["submit", scene.as_str(), "--wait", "-o", path_str(&out)];
    submit_args.extend(LONG);
    submit_args.extend(["--coordinator", addr.as_str()]);
    submit_args.extend(as_client);
    let mut follower = spawn_tessera(d, &submit_args, "submit.log");
    poll("the job to start", Duration::from_secs(30), || {
        let status = try_first_job(d, &addr, &client_file)?;
        (status["tiles_done"].as_u64() > Some(0)).then_some(())
    });

    // New tokens on the coordinator, and SIGHUP.
    write_token(&coordinator_worker, "worker-new-c81d");
    write_token(&coordinator_client, "client-new-51c4");
    coordinator.signal("HUP");
    let reloaded = Instant::now();
    poll("the new client token to be accepted", WINDOW, || {
        client(d, &addr, &["list", "--token-file", path_str(&new_client)])
            .status
            .success()
            .then_some(())
    });
    assert_eq!(
        first_job(d, &addr, &new_client)["state"],
        "running",
        "the job runs through the rotation (make it longer)"
    );
    // Every worker is still there, on the key that is now the previous one; a client
    // with the old token is still accepted.
    assert_eq!(
        worker_keys(&workers_json(
            d,
            &addr,
            &["--token-file", path_str(&old_client)]
        )),
        all_on(&key("worker-old-7f3a"), "previous")
    );
    assert!(
        reloaded.elapsed() < WINDOW,
        "the checks within the window took {:?}: too slow a machine for this test",
        reloaded.elapsed()
    );

    // The peers' files are replaced, as an operator rolls them out.
    for file in &worker_files {
        write_token(file, "worker-new-c81d");
    }
    write_token(&client_file, "client-new-51c4");

    // The window closes: the old client token is refused, and the workers come back on
    // the new key, all three.
    std::thread::sleep(WINDOW.saturating_sub(reloaded.elapsed()) + Duration::from_millis(300));
    let line = one_error_line(
        &client(d, &addr, &["list", "--token-file", path_str(&old_client)]),
        "a client with the old token after the window",
    );
    assert!(
        line.contains(&addr)
            && line.contains(&format!("client token (key {})", key("client-old-92be")))
            && line.contains("retired by a token rotation"),
        "{line}"
    );
    poll(
        "the workers back on the new key",
        Duration::from_secs(30),
        || {
            (worker_keys(&workers_json(d, &addr, &as_client))
                == all_on(&key("worker-new-c81d"), "current"))
            .then_some(())
        },
    );
    for worker in &mut workers {
        assert!(worker.is_running(), "{} exited", worker.name);
    }

    // The followed job ends with the reference's bytes; its client reconnected with its
    // replaced file.
    let status = follower
        .wait_exit(Duration::from_secs(180))
        .expect("submit --wait still running after 3 min");
    assert!(status.success(), "submit --wait: {}", follower.log_text());
    assert_same_png(&out, &reference, "the job rendered through a rotation");
    assert_eq!(
        worker_keys(&workers_json(d, &addr, &as_client)),
        all_on(&key("worker-new-c81d"), "current"),
        "no worker lost"
    );

    // A third token nobody holds is refused, for both roles: the worker, whose file
    // still holds it, gives up at once.
    let line = one_error_line(
        &client(d, &addr, &["list", "--token-file", path_str(&stranger)]),
        "a client with an unknown token",
    );
    assert!(
        line.contains("authentication failed")
            && line.contains("is not the coordinator's client token"),
        "{line}"
    );
    let line = worker_that_gives_up(d, &addr, "stranger", &["--token-file", path_str(&stranger)]);
    assert!(
        line.contains("is not the coordinator's worker token"),
        "{line}"
    );

    // The coordinator's log says what happened, with the key ids.
    assert_eq!(logged(&coordinator, "reloaded the token files"), 1);
    assert!(logged(&coordinator, &key("worker-new-c81d")) > 0);
    assert_eq!(logged(&coordinator, "the overlap window closed"), 2);
    assert!(coordinator.is_running());
}

#[test]
fn a_reload_that_fails_keeps_the_tokens_in_use() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let coordinator_worker = token_file(d, "coordinator-worker.token", "worker-a-1111");
    let coordinator_client = token_file(d, "coordinator-client.token", "client-a-2222");
    let (mut coordinator, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &[
            "--worker-token-file",
            path_str(&coordinator_worker),
            "--client-token-file",
            path_str(&coordinator_client),
        ],
        "coordinator.log",
    );
    let old_client = token_file(d, "old.token", "client-a-2222");
    let new_client = token_file(d, "new.token", "client-b-3333");

    // An empty client token file (a write cut short): the reload changes nothing.
    std::fs::write(&coordinator_client, "").unwrap();
    write_token(&coordinator_worker, "worker-b-4444");
    coordinator.signal("HUP");
    let errors = poll("the reload's error line", GIVES_UP_WITHIN, || {
        let errors: Vec<String> = coordinator
            .log_text()
            .lines()
            .filter(|l| l.contains("ERROR"))
            .map(str::to_owned)
            .collect();
        (!errors.is_empty()).then_some(errors)
    });
    assert_eq!(errors.len(), 1, "{errors:?}");
    assert!(
        errors[0].contains("cannot reload the token files")
            && errors[0].contains(path_str(&coordinator_client))
            && errors[0].contains("empty"),
        "{}",
        errors[0]
    );
    assert!(coordinator.is_running(), "the coordinator stopped");
    ok(
        client(d, &addr, &["list", "--token-file", path_str(&old_client)]),
        "the old client token after a failed reload",
    );
    assert!(one_error_line(
        &client(d, &addr, &["list", "--token-file", path_str(&new_client)]),
        "a new client token before a good reload",
    )
    .contains("authentication failed"));

    // Fixed and signalled again: the new token works (the old one within the window).
    write_token(&coordinator_client, "client-b-3333");
    coordinator.signal("HUP");
    poll("the new client token", GIVES_UP_WITHIN, || {
        client(d, &addr, &["list", "--token-file", path_str(&new_client)])
            .status
            .success()
            .then_some(())
    });
    ok(
        client(d, &addr, &["list", "--token-file", path_str(&old_client)]),
        "the old client token within the default window",
    );
}

#[test]
fn a_peer_of_the_previous_protocol_version_is_refused_with_one_line() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (_coordinator, addr) = crate::support::start_coordinator_in(d);
    // A version 13 client hello: magic, version, role Client, a nonce, no key.
    let mut hello = b"TSRA".to_vec();
    hello.extend(13u16.to_le_bytes());
    hello.extend(0u32.to_le_bytes());
    hello.extend([0u8; 32]);
    hello.push(0);
    let mut stream = TcpStream::connect(&addr).expect("cannot connect");
    stream
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    send_frame(&mut stream, &hello);
    let reason = match protocol::wire::decode(&read_frame(&mut stream, "the answer")) {
        Ok(Welcome::Refused { reason }) => reason,
        other => panic!("expected Refused, got {other:?}"),
    };
    assert_eq!(
        reason,
        format!(
            "protocol version mismatch: this coordinator speaks version {}, the peer speaks \
             version 13",
            protocol::PROTOCOL_VERSION
        )
    );
    assert_eq!(protocol::PROTOCOL_VERSION, 14);
    let mut rest = [0; 16];
    assert_eq!(
        stream.read(&mut rest).ok(),
        Some(0),
        "closed after the refusal"
    );
    // It still serves this version.
    ok(client(d, &addr, &["list"]), "list after the refusal");
}
