//! What the end-to-end tests share: running the real binaries under time limits and
//! guards, the client commands they check farms with, the turns that keep tests apart
//! that must not overlap, and the fakes that stand in for hostile or broken peers.

pub mod browser;
mod client;
pub mod cut_proxy;
mod daemons;
pub mod fake_worker;
pub mod flip_relay;
mod http;
mod images;
mod python;
mod run;
mod shapes;
pub mod throttle_relay;
mod turns;
pub mod wire;

pub use client::*;
pub use daemons::*;
pub use http::*;
pub use images::*;
pub use python::*;
pub use run::*;
pub use shapes::*;
pub use turns::*;

use std::path::{Path, PathBuf};
use std::thread;
use std::time::{Duration, Instant};

/// Interval between two polls of a state.
pub const POLL: Duration = Duration::from_millis(20);

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

/// The checkout (the root package's directory).
pub fn repo() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// `scenes/NAME` in the checkout.
pub fn scene_path(name: &str) -> String {
    path_str(&repo().join("scenes").join(name)).to_owned()
}

/// `scenes/seed-orbit.json`, the animated seed scene: 121 frames of a camera orbit.
pub fn orbit() -> String {
    scene_path("seed-orbit.json")
}

/// Every `scenes/*.json`, sorted by name.
pub fn all_scenes() -> Vec<PathBuf> {
    let mut scenes: Vec<PathBuf> = std::fs::read_dir(repo().join("scenes"))
        .expect("cannot list scenes/")
        .map(|e| e.expect("cannot read an entry of scenes/").path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    scenes.sort();
    scenes
}

/// A path as an argument (test paths are UTF-8).
pub fn path_str(path: &Path) -> &str {
    path.to_str().expect("test paths are UTF-8")
}

/// Writes a token file as a careful operator would: readable by its owner only
/// (0600), so that the binaries have nothing to warn about.
pub fn write_token_file(path: &Path, contents: &str) {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(0o600)
        .open(path)
        .and_then(|mut f| f.write_all(contents.as_bytes()))
        .unwrap_or_else(|e| panic!("cannot write the token file {}: {e}", path.display()));
}

/// The names of everything in `dir`, hidden files included, sorted.
pub fn entries(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()))
        .map(|e| {
            e.expect("cannot read a directory entry")
                .file_name()
                .to_string_lossy()
                .into_owned()
        })
        .collect();
    names.sort();
    names
}

/// The one line of a failed run: it exited non-zero, printed nothing on stdout and
/// exactly one line on stderr, which starts with `error: `.
pub fn one_error_line(run: &Run, what: &str) -> String {
    assert!(
        !run.status.success(),
        "{what} succeeded: stdout {:?}, stderr {:?}",
        run.stdout,
        run.stderr
    );
    assert_eq!(run.stdout, "", "{what}: nothing on stdout");
    let lines: Vec<&str> = run.stderr.lines().collect();
    assert_eq!(
        lines.len(),
        1,
        "{what}: one line on stderr: {:?}",
        run.stderr
    );
    assert!(
        lines[0].starts_with("error: "),
        "{what}: the line starts with `error: `: {:?}",
        lines[0]
    );
    lines[0].to_owned()
}

/// The fields of `/proc/PID/stat` after the command name (state is index 0, ppid 1,
/// utime 11, stime 12), or `None` if there is no such process.
pub fn proc_stat(pid: u32) -> Option<Vec<String>> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let rest = &stat[stat.rfind(')')? + 1..];
    Some(rest.split_whitespace().map(str::to_owned).collect())
}

/// CPU time a running process used so far, in clock ticks (1/100 s).
pub fn cpu_ticks(pid: u32) -> u64 {
    let stat = proc_stat(pid).expect("the process is running");
    stat[11].parse::<u64>().expect("utime") + stat[12].parse::<u64>().expect("stime")
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
