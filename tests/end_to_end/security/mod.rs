//! Who may take part in a farm, and what a hostile or broken peer can do to it: real
//! `tessera` coordinators, workers and clients on 127.0.0.1, with peers played by the
//! tests where the binaries would not misbehave.

mod authentication;
mod hostile_peers;
mod http_side;
mod rotation;
mod tls;

use std::path::{Path, PathBuf};
use std::time::Duration;

use crate::support::{client, ok, path_str, scene_path, start_worker_with, write_token_file};

/// A quick job: the seed scene at 96 × 64, one sample per pixel.
const SMALL: &[&str] = &["--width", "96", "--height", "64", "--aa", "1"];

/// How long a peer that must give up may take to do so.
const GIVES_UP_WITHIN: Duration = Duration::from_secs(20);

/// A worker token and a client token in `dir`, as an operator would make them (each
/// with a final newline, which is trimmed, readable by its owner only).
fn tokens(dir: &Path) -> (PathBuf, PathBuf) {
    let worker = dir.join("worker.token");
    let client = dir.join("client.token");
    write_token_file(
        &worker,
        "9f1c2e7a5b3d4c6e8a0b1c2d3e4f5a6b7c8d9e0f1a2b3c4d\n",
    );
    write_token_file(
        &client,
        "0e9d8c7b6a5f4e3d2c1b0a9f8e7d6c5b4a3f2e1d0c9b8a7f\n",
    );
    (worker, client)
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
    let mut worker = start_worker_with(dir, addr, name, extra);
    let status = worker
        .wait_exit(GIVES_UP_WITHIN)
        .unwrap_or_else(|| panic!("worker {name} still running: it must give up at once"));
    assert!(!status.success(), "worker {name} exited successfully");
    final_error(&worker.log_text(), &format!("worker {name}"))
}

/// `tessera submit SCENE --wait -o DIR/NAME SMALL AUTH...`, which must succeed.
fn submit_and_wait(dir: &Path, addr: &str, name: &str, auth: &[&str]) -> PathBuf {
    let scene = scene_path("seed.json");
    let out = dir.join(name);
    let mut args = vec!["submit", &scene, "--wait", "-o", path_str(&out)];
    args.extend(SMALL);
    args.extend(auth);
    ok(client(dir, addr, &args), "submit --wait");
    out
}
