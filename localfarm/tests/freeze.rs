//! [`FrozenThreads`] on a real child process: the threads named by the prefix stop (in
//! the kernel's tracing stop, using no CPU) while the process's other threads run on,
//! and run again once thawed; a process killed while frozen is reaped as usual; a
//! process without such threads is one line of error.
//!
//! The child is this test executable again (`/proc/self/exe`), running only the test
//! [`busy_threads_child`] with `FREEZE_CHILD` set in its environment: it then starts busy
//! threads with the names given there and runs until its standard input closes. Run
//! without that variable, as part of the suite, that test does nothing.
//!
//! Tracing another process may need privileges (`CAP_SYS_PTRACE`, or a seccomp profile
//! that allows ptrace): where it is refused, these tests print `skipped: REASON` and
//! pass, unless `TESSERA_REQUIRE_PRIVILEGED=1` (set in CI), where they fail.

use std::io::Read as _;
use std::process::{Child, Command, Stdio};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use localfarm::{unprivileged, Error, FrozenThreads};

/// The variable that makes this executable the child: the names of the busy threads to
/// start, separated by commas.
const CHILD: &str = "FREEZE_CHILD";

/// One test at a time: each measures the CPU time its child's threads get, which
/// another test's busy child on the same cores would cut short.
fn serial() -> MutexGuard<'static, ()> {
    static LOCK: Mutex<()> = Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// The child's body: busy threads named as `FREEZE_CHILD` says, until stdin closes.
#[test]
fn busy_threads_child() {
    let Ok(names) = std::env::var(CHILD) else {
        return;
    };
    for name in names.split(',') {
        std::thread::Builder::new()
            .name(name.to_owned())
            .spawn(|| loop {
                std::hint::spin_loop();
            })
            .expect("cannot start a busy thread");
    }
    // The parent holds the other end: its exit, or its drop of the child, ends this.
    let _ = std::io::stdin().read_to_end(&mut Vec::new());
    std::process::exit(0);
}

/// The child process with busy threads named `names`, killed and reaped however the
/// test ends.
struct Busy(Child);

impl Busy {
    fn start(names: &[&str]) -> Busy {
        let child = Command::new("/proc/self/exe")
            .args(["busy_threads_child", "--exact", "--nocapture"])
            .env(CHILD, names.join(","))
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .spawn()
            .expect("cannot start this test executable again");
        let busy = Busy(child);
        // Until every named thread exists.
        let deadline = Instant::now() + Duration::from_secs(10);
        while !names
            .iter()
            .all(|name| threads(busy.pid()).iter().any(|(_, n)| n.as_str() == *name))
        {
            assert!(
                Instant::now() < deadline,
                "the child's threads did not start"
            );
            std::thread::sleep(Duration::from_millis(5));
        }
        busy
    }

    fn pid(&self) -> u32 {
        self.0.id()
    }

    /// The thread of the child named `name`.
    fn tid(&self, name: &str) -> u32 {
        threads(self.pid())
            .into_iter()
            .find(|(_, n)| n == name)
            .unwrap_or_else(|| panic!("no thread {name}"))
            .0
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The ids and names of process `pid`'s threads.
fn threads(pid: u32) -> Vec<(u32, String)> {
    let Ok(entries) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter_map(|e| {
            let tid = e.file_name().to_str()?.parse().ok()?;
            let comm = std::fs::read_to_string(e.path().join("comm")).ok()?;
            Some((tid, comm.trim_end().to_owned()))
        })
        .collect()
}

/// A thread's state letter and CPU time so far (user and system, in ticks of 10 ms),
/// from `/proc/PID/task/TID/stat`.
fn thread_stat(pid: u32, tid: u32) -> (char, u64) {
    let path = format!("/proc/{pid}/task/{tid}/stat");
    let stat = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    // After the name, in parentheses and possibly with spaces: state, then utime and
    // stime as the 12th and 13th fields.
    let fields: Vec<&str> = stat[stat.rfind(')').expect("a stat line") + 1..]
        .split_whitespace()
        .collect();
    let ticks = fields[11].parse::<u64>().unwrap() + fields[12].parse::<u64>().unwrap();
    (fields[0].chars().next().unwrap(), ticks)
}

/// The CPU ticks each of `tids` uses over `period`.
fn ticks_over(pid: u32, tids: &[u32], period: Duration) -> Vec<u64> {
    let before: Vec<u64> = tids.iter().map(|&t| thread_stat(pid, t).1).collect();
    std::thread::sleep(period);
    tids.iter()
        .zip(before)
        .map(|(&t, b)| thread_stat(pid, t).1 - b)
        .collect()
}

/// Freezes, or returns `None` after the skip line where tracing is refused.
fn freeze_or_skip(test: &str, pid: u32, prefix: &str) -> Option<FrozenThreads> {
    match FrozenThreads::freeze(pid, prefix) {
        Ok(frozen) => Some(frozen),
        Err(e @ Error::Freeze { .. }) => {
            unprivileged(test, &e);
            None
        }
        Err(e) => panic!("{test}: {e}"),
    }
}

#[test]
fn the_named_threads_stop_while_the_others_run_and_resume_when_thawed() {
    let test = "the_named_threads_stop_while_the_others_run_and_resume_when_thawed";
    let _serial = serial();
    let busy = Busy::start(&["render-0", "render-1", "render-2", "heartbeat"]);
    let pid = busy.pid();
    let render: Vec<u32> = ["render-0", "render-1", "render-2"]
        .iter()
        .map(|n| busy.tid(n))
        .collect();
    let other = busy.tid("heartbeat");

    let Some(frozen) = freeze_or_skip(test, pid, "render-") else {
        return;
    };
    let mut sorted = render.clone();
    sorted.sort_unstable();
    assert_eq!(
        frozen.tids(),
        sorted,
        "every render-* thread, and only those"
    );
    assert_eq!(frozen.pid(), pid);
    for &tid in &render {
        assert_eq!(
            thread_stat(pid, tid).0,
            't',
            "thread {tid} is in its tracing stop"
        );
    }
    // Frozen: not one tick, while the other thread runs (a share of a core on a machine
    // shared with other work: some ticks, never none).
    let used = ticks_over(
        pid,
        &[render.clone(), vec![other]].concat(),
        Duration::from_secs(1),
    );
    assert_eq!(
        &used[..3],
        &[0, 0, 0],
        "CPU ticks of the frozen threads in 1 s"
    );
    assert!(
        used[3] >= 5,
        "the other thread got only {} ticks in 1 s",
        used[3]
    );

    frozen.thaw().expect("thaw");
    for &tid in &render {
        assert_ne!(thread_stat(pid, tid).0, 't', "thread {tid} still stopped");
    }
    let used = ticks_over(pid, &render, Duration::from_secs(1));
    assert!(
        used.iter().all(|&t| t >= 3),
        "CPU ticks of the thawed threads in 1 s: {used:?}"
    );
}

#[test]
fn dropping_the_guard_thaws_the_threads() {
    let test = "dropping_the_guard_thaws_the_threads";
    let _serial = serial();
    let busy = Busy::start(&["render-0"]);
    let tid = busy.tid("render-0");
    let Some(frozen) = freeze_or_skip(test, busy.pid(), "render-") else {
        return;
    };
    assert_eq!(thread_stat(busy.pid(), tid).0, 't');
    // As when a test panics with the guard alive (on another thread: the guard goes
    // where its owner goes).
    let unwound = std::thread::spawn(move || {
        let _frozen = frozen;
        panic!("a failing test, on purpose");
    })
    .join();
    assert!(unwound.is_err());
    assert_ne!(
        thread_stat(busy.pid(), tid).0,
        't',
        "still stopped after the drop"
    );
    let used = ticks_over(busy.pid(), &[tid], Duration::from_millis(500));
    assert!(used[0] >= 2, "{used:?} ticks in 0.5 s after the drop");
}

#[test]
fn a_process_killed_while_frozen_is_reaped_and_thawing_it_is_no_error() {
    let test = "a_process_killed_while_frozen_is_reaped_and_thawing_it_is_no_error";
    let _serial = serial();
    let mut busy = Busy::start(&["render-0", "render-1"]);
    let Some(frozen) = freeze_or_skip(test, busy.pid(), "render-") else {
        return;
    };
    assert_eq!(frozen.tids().len(), 2);
    busy.0.kill().unwrap();
    // The frozen threads die with it; their tracer reaps them, so the process's exit
    // reaches its parent while the guard is still held.
    let started = Instant::now();
    loop {
        if busy.0.try_wait().unwrap().is_some() {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(5),
            "the killed process was not reaped within 5 s of its kill"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    frozen.thaw().expect("thawing threads that are gone");
}

#[test]
fn a_process_without_such_threads_is_one_line_of_error() {
    let _serial = serial();
    let busy = Busy::start(&["heartbeat"]);
    let e = FrozenThreads::freeze(busy.pid(), "render-").unwrap_err();
    assert!(matches!(e, Error::NoSuchThreads { .. }), "{e:?}");
    let line = e.to_string();
    assert_eq!(
        line,
        format!("process {} has no thread named render-*", busy.pid())
    );
    // Nothing was stopped.
    assert_ne!(thread_stat(busy.pid(), busy.tid("heartbeat")).0, 't');

    let e = FrozenThreads::freeze(u32::MAX, "render-")
        .unwrap_err()
        .to_string();
    assert!(
        e.starts_with("cannot freeze threads of process ") && !e.contains('\n'),
        "{e}"
    );
}
