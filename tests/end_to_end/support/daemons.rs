//! Farm processes (coordinators, workers, long-running clients) under guards that kill
//! and reap them, also when a test fails.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::thread;
use std::time::{Duration, Instant};

/// The binary under test.
pub const BIN: &str = env!("CARGO_BIN_EXE_tessera");

/// A daemon (or any child) killed with SIGKILL and reaped when dropped, also when a
/// test fails; on failure the last lines of its log are printed.
pub struct Daemon {
    pub name: String,
    pub child: Child,
    pub log: Option<PathBuf>,
}

impl Daemon {
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Whether the process has not exited yet (a stopped process is still running).
    pub fn is_running(&mut self) -> bool {
        self.child
            .try_wait()
            .expect("cannot wait for a child")
            .is_none()
    }

    /// SIGKILL (`kill -9`), then reap.
    pub fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Sends `kill -SIG` (e.g. "TERM", "STOP", "CONT") to the still-running child.
    pub fn signal(&mut self, sig: &str) {
        assert!(
            self.is_running(),
            "{} is not running to get SIG{sig}",
            self.name
        );
        let status = Command::new("kill")
            .args([format!("-{sig}"), self.pid().to_string()])
            .status()
            .expect("cannot run kill");
        assert!(status.success(), "kill -{sig} {} failed", self.pid());
    }

    /// Waits for the child to exit, at most `timeout`; `None` if it is still running.
    pub fn wait_exit(&mut self, timeout: Duration) -> Option<ExitStatus> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(status) = self.child.try_wait().expect("cannot wait for a child") {
                return Some(status);
            }
            if Instant::now() >= deadline {
                return None;
            }
            thread::sleep(Duration::from_millis(5));
        }
    }

    /// The log's text (empty if none).
    pub fn log_text(&self) -> String {
        self.log
            .as_ref()
            .and_then(|l| std::fs::read_to_string(l).ok())
            .unwrap_or_default()
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        // SIGKILL also ends a stopped process.
        let _ = self.child.kill();
        let _ = self.child.wait();
        if thread::panicking() {
            let text = self.log_text();
            let tail: Vec<&str> = text.lines().rev().take(20).collect();
            if !tail.is_empty() {
                eprintln!("--- last lines of {}'s log ---", self.name);
                for line in tail.iter().rev() {
                    eprintln!("{line}");
                }
            }
        }
    }
}

/// Reads `stdout`'s first line within `timeout`; the rest is drained in the background
/// so the child never blocks on a full pipe.
pub fn first_line(stdout: impl Read + Send + 'static, timeout: Duration) -> Option<String> {
    use std::io::BufRead;
    let (tx, rx) = std::sync::mpsc::channel();
    thread::spawn(move || {
        let mut reader = std::io::BufReader::new(stdout);
        let mut line = String::new();
        let _ = reader.read_line(&mut line);
        let _ = tx.send(line);
        let _ = std::io::copy(&mut reader, &mut std::io::sink());
    });
    rx.recv_timeout(timeout)
        .ok()
        .filter(|line| !line.is_empty())
}

/// Starts `tessera ARGS` in the background in `dir`, its stderr in `DIR/LOG_NAME` and
/// its stdout in `DIR/LOG_NAME.out`, under a guard.
pub fn spawn_tessera(dir: &Path, args: &[&str], log_name: &str) -> Daemon {
    let log = dir.join(log_name);
    let child = Command::new(BIN)
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(
            std::fs::File::create(dir.join(format!("{log_name}.out")))
                .expect("cannot create the output file"),
        )
        .stderr(std::fs::File::create(&log).expect("cannot create the log"))
        .spawn()
        .expect("cannot start the tessera binary");
    Daemon {
        name: log_name.trim_end_matches(".log").to_owned(),
        child,
        log: Some(log),
    }
}

/// Starts `tessera coordinator --listen LISTEN --data DATA EXTRA...` (log in
/// `DIR/LOG_NAME`) and returns it with the address it printed.
pub fn start_coordinator(
    dir: &Path,
    data: &Path,
    listen: &str,
    extra: &[&str],
    log_name: &str,
) -> (Daemon, String) {
    try_start_coordinator(dir, data, listen, extra, log_name).unwrap_or_else(|e| panic!("{e}"))
}

/// [`start_coordinator`] on a free port of 127.0.0.1 with `DIR/data`, logging to
/// `DIR/coordinator.log`: how most tests start theirs.
pub fn start_coordinator_in(dir: &Path) -> (Daemon, String) {
    start_coordinator(
        dir,
        &dir.join("data"),
        "127.0.0.1:0",
        &[],
        "coordinator.log",
    )
}

/// [`start_coordinator`] on a free port of 127.0.0.1 with `DIR/data` and `extra`
/// flags, serving HTTP on a free port of its own, logging to `DIR/coordinator.log`: the
/// daemon, its address and its HTTP address.
pub fn start_coordinator_with_http(dir: &Path, extra: &[&str]) -> (Daemon, String, String) {
    let http = format!("127.0.0.1:{}", free_port());
    let mut args = vec!["--http", &http];
    args.extend(extra);
    let (daemon, addr) = start_coordinator(
        dir,
        &dir.join("data"),
        "127.0.0.1:0",
        &args,
        "coordinator.log",
    );
    (daemon, addr, http)
}

/// [`start_coordinator`] on a free port of 127.0.0.1 chosen now, with `DIR/data`, logging
/// to `DIR/coordinator-1.log`: for a test that kills it and starts it again on the same
/// address and data with [`restart_coordinator`].
pub fn start_restartable_coordinator(dir: &Path) -> (Daemon, String) {
    let listen = format!("127.0.0.1:{}", free_port());
    start_coordinator(dir, &dir.join("data"), &listen, &[], "coordinator-1.log")
}

/// Starts the coordinator of [`start_restartable_coordinator`] again on its address
/// `addr` and its data, with `extra` flags, logging to `DIR/coordinator-2.log`.
pub fn restart_coordinator(dir: &Path, addr: &str, extra: &[&str]) -> Daemon {
    let (daemon, again) =
        start_coordinator(dir, &dir.join("data"), addr, extra, "coordinator-2.log");
    assert_eq!(again, addr, "restarted on the same address");
    daemon
}

/// [`start_coordinator`] for a coordinator that may refuse to start: `Err` says how
/// it exited (or that it printed nothing) and what it logged.
pub fn try_start_coordinator(
    dir: &Path,
    data: &Path,
    listen: &str,
    extra: &[&str],
    log_name: &str,
) -> Result<(Daemon, String), String> {
    let log = dir.join(log_name);
    let mut child = Command::new(BIN)
        .args(["coordinator", "--listen", listen, "--data"])
        .arg(data)
        .args(extra)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log).expect("cannot create the log"))
        .spawn()
        .expect("cannot start the coordinator");
    let stdout = child.stdout.take().expect("stdout is piped");
    let mut daemon = Daemon {
        name: log_name.trim_end_matches(".log").to_owned(),
        child,
        log: Some(log),
    };
    let line = first_line(stdout, Duration::from_secs(10));
    let addr = line
        .as_deref()
        .and_then(|l| l.trim().strip_prefix("listening on "))
        .map(str::to_owned);
    match addr {
        Some(addr) => {
            assert!(addr.starts_with("127.0.0.1:"), "listening on {addr}");
            Ok((daemon, addr))
        }
        None => {
            let exit = daemon.wait_exit(Duration::from_secs(2));
            Err(format!(
                "the coordinator did not start (first line {line:?}, exit {exit:?}); its \
                 stderr:\n{}",
                daemon.log_text()
            ))
        }
    }
}

/// Starts `tessera worker --coordinator ADDR --threads 1 --name NAME` (log in
/// `DIR/worker-NAME.log`), without waiting for it to register.
pub fn start_worker(dir: &Path, addr: &str, name: &str) -> Daemon {
    start_worker_with(dir, addr, name, &[])
}

/// [`start_worker`] with more arguments.
pub fn start_worker_with(dir: &Path, addr: &str, name: &str, extra: &[&str]) -> Daemon {
    let log = dir.join(format!("worker-{name}.log"));
    let child = Command::new(BIN)
        .args([
            "worker",
            "--coordinator",
            addr,
            "--threads",
            "1",
            "--name",
            name,
        ])
        .args(extra)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).expect("cannot create the log"))
        .spawn()
        .expect("cannot start a worker");
    Daemon {
        name: format!("worker {name}"),
        child,
        log: Some(log),
    }
}

/// A port that was free a moment ago on 127.0.0.1, for a daemon the test starts on it.
///
/// Taken below the kernel's range of ephemeral ports (`ip_local_port_range`, 32768 and
/// up on Linux): a port the kernel hands out for port 0 can be given again, between our
/// check and the daemon's bind, to any outgoing connection of any process, and the
/// daemon then fails with "address in use". Below that range only an explicit bind can
/// take it; each port is handed out once per test process, whose tests all share the
/// counter.
pub fn free_port() -> u16 {
    static NEXT: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    // A start that differs between test processes run one after the other.
    let start = std::process::id() * 7919 % 12_000;
    loop {
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let port = 20_000 + (start + n) % 12_000;
        if std::net::TcpListener::bind(("127.0.0.1", port as u16)).is_ok() {
            return port as u16;
        }
    }
}

/// A worker on a slower machine: [`start_worker_with`], its process then limited to
/// `share` of one core through a cgroup, as an operator would slow it (so its runtime,
/// heartbeats included, is slowed too, not only its rendering). Needs root: where
/// cgroups cannot be written, `None` after a line saying the test is skipped, or a
/// failure where `TESSERA_REQUIRE_PRIVILEGED=1` says it must run (CI).
///
/// The worker starts and registers at full speed, and is limited as soon as the
/// coordinator lists it: its start (the canary tile included) takes some 60 ms of CPU,
/// which on a hundredth of a core is seconds, past short heartbeat timeouts and under
/// load past [`REGISTER_TIMEOUT`](super::client::REGISTER_TIMEOUT). A tile it is given
/// in the moment between the two may be rendered in part at full speed; the tests
/// that need it slow give it tiles of many milliseconds.
///
/// The kernel checks the quota at its scheduler tick (4 ms at 250 Hz), so a process may
/// run a tick past its quota each period: work of a few milliseconds can finish at
/// full speed. A test that needs the worker still busy gives it a job of many ticks,
/// or freezes it (`SIGSTOP`) instead.
pub fn start_slow_worker(
    test: &str,
    dir: &Path,
    addr: &str,
    name: &str,
    share: f64,
    extra: &[&str],
) -> Option<(Daemon, localfarm::CpuLimit)> {
    if let Err(e) = localfarm::CpuLimit::probe() {
        localfarm::unprivileged(test, &e);
        return None;
    }
    let worker = start_worker_with(dir, addr, name, extra);
    super::poll(
        &format!("worker {name} to register"),
        super::client::REGISTER_TIMEOUT,
        || {
            let workers = super::client::try_workers(dir, addr)?;
            super::client::worker_named(&workers, name).map(drop)
        },
    );
    let limit = localfarm::CpuLimit::apply(worker.pid(), share)
        .unwrap_or_else(|e| panic!("{test}: limiting worker {name}: {e}"));
    Some((worker, limit))
}

/// `n` workers `w0`, `w1`, ... each on `share` of one core ([`start_slow_worker`]).
pub fn start_slow_workers(
    test: &str,
    dir: &Path,
    addr: &str,
    n: usize,
    share: f64,
) -> Option<Vec<(Daemon, localfarm::CpuLimit)>> {
    (0..n)
        .map(|i| start_slow_worker(test, dir, addr, &format!("w{i}"), share, &[]))
        .collect()
}
