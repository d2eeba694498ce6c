//! One run of the real `tessera` binary, with a time limit, so that a hung process fails
//! its test instead of hanging CI.

use std::ffi::{OsStr, OsString};
use std::io::Read;
use std::path::Path;
use std::process::{Command, ExitStatus, Stdio};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

/// What one run of the binary returned and printed.
pub struct Run {
    pub status: ExitStatus,
    pub stdout: String,
    pub stderr: String,
}

/// Runs `tessera ARGS` in `dir`, killing it (and failing the test) after `timeout`.
pub fn tessera<S: AsRef<OsStr>>(dir: &Path, args: &[S], timeout: Duration) -> Run {
    tessera_within(dir, args, timeout).unwrap_or_else(|| {
        let args: Vec<&OsStr> = args.iter().map(AsRef::as_ref).collect();
        panic!("tessera {args:?} still running after {timeout:?}: killed")
    })
}

/// Like [`tessera`], but a run still going after `timeout` is killed and reported as
/// `None` instead of failing the test.
///
/// stdout and stderr are drained on their own threads so that a chatty child cannot
/// block on a full pipe while we wait for it.
pub fn tessera_within<S: AsRef<OsStr>>(dir: &Path, args: &[S], timeout: Duration) -> Option<Run> {
    let args: Vec<OsString> = args.iter().map(|a| a.as_ref().to_owned()).collect();
    let mut child = Command::new(env!("CARGO_BIN_EXE_tessera"))
        .args(&args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("cannot start the tessera binary");
    let stdout = drain(child.stdout.take().expect("stdout is piped"));
    let stderr = drain(child.stderr.take().expect("stderr is piped"));
    let deadline = Instant::now() + timeout;
    let status = loop {
        if let Some(status) = child.try_wait().expect("cannot wait for tessera") {
            break status;
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            // Not waiting for the readers: a process the killed one started may still
            // hold its pipes.
            return None;
        }
        thread::sleep(Duration::from_millis(5));
    };
    Some(Run {
        status,
        stdout: stdout.join().expect("stdout reader panicked"),
        stderr: stderr.join().expect("stderr reader panicked"),
    })
}

fn drain(mut pipe: impl Read + Send + 'static) -> JoinHandle<String> {
    thread::spawn(move || {
        let mut bytes = Vec::new();
        pipe.read_to_end(&mut bytes)
            .expect("cannot read the child's output");
        String::from_utf8_lossy(&bytes).into_owned()
    })
}

/// Panics with everything the run printed unless it succeeded.
pub fn ok(run: Run, what: &str) -> Run {
    assert!(
        run.status.success(),
        "{what} failed ({}):\nstdout: {}\nstderr: {}",
        run.status,
        run.stdout,
        run.stderr
    );
    run
}
