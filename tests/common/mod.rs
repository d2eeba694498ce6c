//! What the end-to-end tests share: running the real `tessera` binary with a time
//! limit, so that a hung process fails its test instead of hanging CI.

// Each test binary uses its own part of this module.
#![allow(dead_code)]

pub mod proxy;

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
///
/// stdout and stderr are drained on their own threads so that a chatty child cannot
/// block on a full pipe while we wait for it.
pub fn tessera<S: AsRef<OsStr>>(dir: &Path, args: &[S], timeout: Duration) -> Run {
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
            panic!("tessera {args:?} still running after {timeout:?}: killed");
        }
        thread::sleep(Duration::from_millis(10));
    };
    Run {
        status,
        stdout: stdout.join().expect("stdout reader panicked"),
        stderr: stderr.join().expect("stderr reader panicked"),
    }
}

fn drain(mut pipe: impl Read + Send + 'static) -> JoinHandle<String> {
    thread::spawn(move || {
        let mut bytes = Vec::new();
        pipe.read_to_end(&mut bytes)
            .expect("cannot read the child's output");
        String::from_utf8_lossy(&bytes).into_owned()
    })
}

// ---------------------------------------------------------------------------------
// Farm processes under guards, shared by the fault-injection and hostile-peer tests.
// ---------------------------------------------------------------------------------

/// The binary under test.
pub const BIN: &str = env!("CARGO_BIN_EXE_tessera");

/// Interval between two polls of a state.
pub const POLL: Duration = Duration::from_millis(20);

/// A daemon (or any child) killed with SIGKILL and reaped when dropped, also when a
/// test fails; on failure the last lines of its log are printed.
pub struct Daemon {
    pub name: String,
    pub child: std::process::Child,
    pub log: Option<std::path::PathBuf>,
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
/// take it; each port is handed out once per test process.
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

/// Calls `probe` every [`POLL`] until it returns a value; panics after `timeout`.
pub fn poll<T>(what: &str, timeout: Duration, mut probe: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(value) = probe() {
            return value;
        }
        assert!(
            Instant::now() < deadline,
            "timed out after {timeout:?} waiting for {what}"
        );
        thread::sleep(POLL);
    }
}

/// `scenes/NAME` in the checkout.
pub fn scene_path(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name)
        .to_str()
        .expect("test paths are UTF-8")
        .to_owned()
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

/// `tessera ARGS --coordinator ADDR` in `dir`, at most 60 s.
pub fn client(dir: &Path, addr: &str, args: &[&str]) -> Run {
    let mut all: Vec<&str> = args.to_vec();
    all.extend(["--coordinator", addr]);
    tessera(dir, &all, Duration::from_secs(60))
}

/// `tessera status JOB --json`, parsed; `None` if the command failed (for example
/// while the coordinator is down).
pub fn try_status(dir: &Path, addr: &str, job: u64) -> Option<serde_json::Value> {
    let run = client(dir, addr, &["status", &job.to_string(), "--json"]);
    if !run.status.success() {
        return None;
    }
    Some(
        serde_json::from_str(run.stdout.trim())
            .unwrap_or_else(|e| panic!("status --json is not JSON ({e}): {:?}", run.stdout)),
    )
}

/// `tessera submit ARGS` (without `--wait`): the job id it printed.
pub fn submit(dir: &Path, addr: &str, args: &[&str]) -> u64 {
    let mut all = vec!["submit"];
    all.extend(args);
    let run = ok(
        client(dir, addr, &all),
        &format!("tessera {}", all.join(" ")),
    );
    run.stdout
        .trim()
        .parse()
        .unwrap_or_else(|e| panic!("submit printed {:?}, not a job id: {e}", run.stdout))
}

/// Polls `status` until the job is `done` (within `timeout`), tolerating a coordinator
/// that is briefly unreachable; panics if the job ends in another state.
pub fn wait_done(dir: &Path, addr: &str, job: u64, timeout: Duration) -> serde_json::Value {
    poll(&format!("job {job} to be done"), timeout, || {
        let status = try_status(dir, addr, job)?;
        let state = status["state"].as_str().expect("state is a string");
        assert!(
            !matches!(state, "failed" | "cancelled"),
            "job {job} ended {state}: {status}"
        );
        (state == "done").then_some(status)
    })
}

/// `tessera render SCENE -o DIR/NAME ARGS...`: the reference image.
pub fn render_reference(dir: &Path, scene: &str, name: &str, args: &[&str]) -> std::path::PathBuf {
    let out = dir.join(name);
    let out_arg = out.to_str().expect("test paths are UTF-8");
    let mut all = vec!["render", scene, "-o", out_arg];
    all.extend(args);
    ok(
        tessera(dir, &all, Duration::from_secs(60)),
        &format!("tessera {}", all.join(" ")),
    );
    out
}

/// `tessera fetch JOB -o DIR/NAME`.
pub fn fetch(dir: &Path, addr: &str, job: u64, name: &str) -> std::path::PathBuf {
    let out = dir.join(name);
    let out_arg = out.to_str().expect("test paths are UTF-8");
    ok(
        client(dir, addr, &["fetch", &job.to_string(), "-o", out_arg]),
        &format!("fetch {job}"),
    );
    out
}

/// The two PNG files are byte for byte the same (on a mismatch, says how many pixels
/// differ).
pub fn assert_same_png(actual: &Path, reference: &Path, what: &str) {
    let a_bytes = std::fs::read(actual).unwrap_or_else(|e| panic!("{what}: no image: {e}"));
    let r_bytes = std::fs::read(reference).expect("cannot read the reference image");
    if a_bytes == r_bytes {
        return;
    }
    let a = image::load_from_memory(&a_bytes)
        .unwrap_or_else(|e| panic!("{what}: not a PNG: {e}"))
        .to_rgb8();
    let r = image::load_from_memory(&r_bytes)
        .expect("the reference is a PNG")
        .to_rgb8();
    assert_eq!(a.dimensions(), r.dimensions(), "{what}: image size");
    let differing = a.pixels().zip(r.pixels()).filter(|(p, q)| p != q).count();
    panic!(
        "{what}: the PNG differs from `tessera render`'s ({} vs {} bytes, {differing} of {} \
         pixels differ)",
        a_bytes.len(),
        r_bytes.len(),
        a.width() * a.height()
    );
}

/// The resident set of a process in KiB (`VmRSS` of `/proc/PID/status`).
pub fn rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()
}

/// Open file descriptors of a process.
pub fn open_fds(pid: u32) -> Option<usize> {
    Some(std::fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count())
}

/// A small deterministic pseudo-random generator (SplitMix64).
pub struct SplitMix(pub u64);

impl SplitMix {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// A number in `0..n`.
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
}

/// Held by a test for its whole run so that the tests of one binary run one at a time
/// (they all want every core); when dropped, prints how long the test took.
pub struct Serial {
    _lock: std::sync::MutexGuard<'static, ()>,
    started: Instant,
}

/// Waits for the other tests of this binary that called it to finish.
pub fn serial() -> Serial {
    static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());
    Serial {
        _lock: SERIAL.lock().unwrap_or_else(|e| e.into_inner()),
        started: Instant::now(),
    }
}

impl Drop for Serial {
    fn drop(&mut self) {
        eprintln!(
            "[{}: {:.1} s]",
            thread::current().name().unwrap_or("test"),
            self.started.elapsed().as_secs_f64()
        );
    }
}

/// `GET PATH` from the HTTP listener at `addr` (HTTP/1.0, so the server closes when
/// done): the status code and the body. `None` if nothing answers.
pub fn http_get(addr: &str, path: &str) -> Option<(u16, Vec<u8>)> {
    use std::io::Write;
    let mut stream = std::net::TcpStream::connect(addr).ok()?;
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .ok()?;
    write!(stream, "GET {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n").ok()?;
    let mut response = Vec::new();
    stream.read_to_end(&mut response).ok()?;
    let head_end = response.windows(4).position(|w| w == b"\r\n\r\n")?;
    let head = String::from_utf8_lossy(&response[..head_end]);
    let status = head.split_whitespace().nth(1)?.parse().ok()?;
    Some((status, response[head_end + 4..].to_vec()))
}

// ---------------------------------------------------------------------------------
// Helpers of the coordinator, storage and integrity fault tests.
// ---------------------------------------------------------------------------------

/// Like [`tessera`], but a run still going after `timeout` is killed and reported as
/// `None` instead of failing the test.
pub fn tessera_within<S: AsRef<OsStr>>(dir: &Path, args: &[S], timeout: Duration) -> Option<Run> {
    let mut child = Command::new(BIN)
        .args(args)
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
            break Some(status);
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        thread::sleep(Duration::from_millis(5));
    };
    let (stdout, stderr) = (
        stdout.join().expect("stdout reader panicked"),
        stderr.join().expect("stderr reader panicked"),
    );
    status.map(|status| Run {
        status,
        stdout,
        stderr,
    })
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

/// `workers --json`, or `None` if the coordinator cannot be reached.
pub fn try_workers(dir: &Path, addr: &str) -> Option<Vec<serde_json::Value>> {
    let run = tessera_within(
        dir,
        &["workers", "--json", "--coordinator", addr],
        Duration::from_secs(30),
    )?;
    if !run.status.success() {
        return None;
    }
    match serde_json::from_str(run.stdout.trim()) {
        Ok(serde_json::Value::Array(workers)) => Some(workers),
        other => panic!("workers --json: {other:?}"),
    }
}

/// [`http_get`] with its own limit on connecting and reading.
pub fn http_get_within(addr: &str, path: &str, timeout: Duration) -> Option<(u16, Vec<u8>)> {
    use std::io::Write;
    let socket: std::net::SocketAddr = addr.parse().ok()?;
    let mut stream = std::net::TcpStream::connect_timeout(&socket, timeout).ok()?;
    stream.set_read_timeout(Some(timeout)).ok()?;
    stream.set_write_timeout(Some(timeout)).ok()?;
    write!(stream, "GET {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n").ok()?;
    let mut response = Vec::new();
    stream.read_to_end(&mut response).ok()?;
    let head_end = response.windows(4).position(|w| w == b"\r\n\r\n")?;
    let head = String::from_utf8_lossy(&response[..head_end]);
    let status = head.split_whitespace().nth(1)?.parse().ok()?;
    Some((status, response[head_end + 4..].to_vec()))
}

/// The value of an unlabelled sample `NAME VALUE` in a Prometheus exposition.
pub fn metric_value(exposition: &str, name: &str) -> Option<f64> {
    exposition.lines().find_map(|line| {
        let rest = line.strip_prefix(name)?.strip_prefix(' ')?;
        rest.split_whitespace().next()?.parse().ok()
    })
}

/// Checks whose failure does not stop a test: each failed one is recorded (and printed
/// at once), and [`Findings::finish`] fails the test with all of them.
#[derive(Default)]
pub struct Findings(Vec<String>);

impl Findings {
    pub fn check(&mut self, ok: bool, what: impl FnOnce() -> String) {
        if !ok {
            let what = what();
            eprintln!("FAILED CHECK: {what}");
            self.0.push(what);
        }
    }

    /// Fails the test if any check failed.
    pub fn finish(self) {
        assert!(
            self.0.is_empty(),
            "{} check(s) failed:\n- {}",
            self.0.len(),
            self.0.join("\n- ")
        );
    }
}

/// A job that failed or was cancelled fails the test at once.
pub fn assert_not_ended_badly(job: u64, status: &serde_json::Value) {
    let state = status["state"].as_str().expect("state is a string");
    assert!(
        !matches!(state, "failed" | "cancelled"),
        "job {job} ended {state}: {status}"
    );
}

/// A job status's `tiles_done`.
pub fn tiles_done(status: &serde_json::Value) -> u64 {
    status["tiles_done"].as_u64().expect("tiles_done")
}

/// A job status's `tiles_total`.
pub fn tiles_total(status: &serde_json::Value) -> u64 {
    status["tiles_total"].as_u64().expect("tiles_total")
}

/// A job's arguments less `--tile`, which `tessera render` does not take.
pub fn render_args<'a>(args: &[&'a str]) -> Vec<&'a str> {
    let mut out = Vec::new();
    let mut it = args.iter();
    while let Some(&arg) = it.next() {
        if arg == "--tile" {
            it.next();
        } else {
            out.push(arg);
        }
    }
    out
}
