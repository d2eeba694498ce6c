//! [`CpuLimit`] on this machine's cgroups, with real processes: the process is in the
//! limit's cgroup with the quota asked for, gets no more than its share of a core, and
//! is back where it was, the cgroup gone, once the limit is dropped.
//!
//! Writing cgroups needs root: without, these tests print `skipped: REASON` on stderr
//! and pass, unless `TESSERA_REQUIRE_PRIVILEGED=1` (set in CI), where they fail.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Mutex, MutexGuard};
use std::time::Duration;

use localfarm::{unprivileged, CpuLimit};

/// One test at a time: each looks for limits of this process left behind, and must not
/// find the other's, still in use.
fn serial() -> MutexGuard<'static, ()> {
    static LOCK: Mutex<()> = Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// A child process, killed and reaped however the test ends.
struct Process(Child);

impl Process {
    fn start(program: &str, args: &[&str]) -> Process {
        let child = Command::new(program)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {program}: {e}"));
        Process(child)
    }

    fn pid(&self) -> u32 {
        self.0.id()
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn read(path: impl AsRef<Path>) -> String {
    let path = path.as_ref();
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()))
}

/// The CPU time process `pid` has used, from `/proc/PID/stat` (user and system ticks,
/// at Linux's fixed 100 a second).
fn cpu_time(pid: u32) -> Duration {
    let stat = read(format!("/proc/{pid}/stat"));
    // The fields after the command name, which is in parentheses and may hold spaces:
    // state is field 3, utime 14 and stime 15.
    let after = &stat[stat.rfind(')').expect("a stat line") + 2..];
    let fields: Vec<u64> = after
        .split_whitespace()
        .skip(11)
        .take(2)
        .map(|f| f.parse().expect("a tick count"))
        .collect();
    Duration::from_millis(10 * (fields[0] + fields[1]))
}

#[test]
fn a_limited_process_is_in_a_cgroup_with_its_quota_until_the_limit_is_dropped() {
    let test = "a_limited_process_is_in_a_cgroup_with_its_quota_until_the_limit_is_dropped";
    let _serial = serial();
    let process = Process::start("sleep", &["60"]);
    let pid = process.pid();
    let before = read(format!("/proc/{pid}/cgroup"));
    let limit = match CpuLimit::apply(pid, 0.05) {
        Ok(limit) => limit,
        Err(e) => return unprivileged(test, &e),
    };
    let dir = limit.path().to_path_buf();
    let name = dir.file_name().unwrap().to_string_lossy().into_owned();

    let members: Vec<u32> = read(dir.join("cgroup.procs"))
        .lines()
        .map(|l| l.parse().unwrap())
        .collect();
    assert_eq!(members, vec![pid], "the processes of {}", dir.display());
    let during = read(format!("/proc/{pid}/cgroup"));
    assert!(during.contains(&format!("/{name}\n")), "{during}");
    // 5 % of a core: 5 ms in each period of 100 ms, in either interface.
    if dir.join("cpu.max").exists() {
        assert_eq!(read(dir.join("cpu.max")).trim(), "5000 100000");
    } else {
        assert_eq!(read(dir.join("cpu.cfs_quota_us")).trim(), "5000");
        assert_eq!(read(dir.join("cpu.cfs_period_us")).trim(), "100000");
    }

    drop(limit);
    assert!(!dir.exists(), "{} is left behind", dir.display());
    assert_eq!(read(format!("/proc/{pid}/cgroup")), before);
    // Where a limit can be applied, the check a command makes at its start passes, and
    // leaves nothing behind either.
    CpuLimit::probe().unwrap();
    let parent = dir.parent().unwrap();
    let left: Vec<_> = std::fs::read_dir(parent)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| {
            e.file_name()
                .to_string_lossy()
                .starts_with(&format!("tessera-cpu-limit-{}-", std::process::id()))
        })
        .collect();
    assert!(left.is_empty(), "{left:?}");
}

#[test]
fn a_limited_busy_process_gets_no_more_than_its_share_of_a_core() {
    let test = "a_limited_busy_process_gets_no_more_than_its_share_of_a_core";
    let _serial = serial();
    let process = Process::start("sh", &["-c", "while :; do :; done"]);
    let limit = match CpuLimit::apply(process.pid(), 0.1) {
        Ok(limit) => limit,
        Err(e) => return unprivileged(test, &e),
    };
    let start = cpu_time(process.pid());
    std::thread::sleep(Duration::from_secs(2));
    let used = cpu_time(process.pid()) - start;
    drop(limit);
    // 0.2 s at 10 % of a core; unlimited, it would take up to the whole 2 s. The
    // margin is for the period the limit started in.
    assert!(used < Duration::from_millis(600), "used {used:?} in 2 s");
}

#[test]
fn a_process_that_does_not_exist_is_one_line_of_error() {
    let e = CpuLimit::apply(u32::MAX, 0.5).unwrap_err().to_string();
    assert!(
        e.starts_with("cannot limit a process's CPU: ") && !e.contains('\n'),
        "{e}"
    );
}
