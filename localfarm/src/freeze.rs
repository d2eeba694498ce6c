//! Some threads of another process stopped while the rest of it runs: a worker whose
//! render thread hangs (a deadlock, a driver that never returns) while its runtime
//! keeps answering heartbeats, made on purpose from outside the worker.
//!
//! A signal cannot do it: SIGSTOP sent to one thread id stops the whole thread group on
//! Linux. ptrace can: [`FrozenThreads::freeze`] seizes each chosen thread
//! (`PTRACE_SEIZE`, which alone does not stop it) and stops it with `PTRACE_INTERRUPT`;
//! detaching resumes it. The threads are chosen by name (`/proc/PID/task/TID/comm`),
//! which is how a program marks its pools (the worker's are `render-0`, `render-1`,
//! ...).
//!
//! The kernel takes ptrace requests for a tracee only from the thread that seized it,
//! not from any thread of the tracing process; and a test harness runs its tests on
//! threads of its own. So every request (seizing, waiting for the stops, detaching) is
//! made by one thread that the [`FrozenThreads`] guard owns and that lives exactly as
//! long as the freeze; releasing the guard, by [`FrozenThreads::thaw`] or by dropping
//! it, also when a test panics, makes that thread detach and end.
//!
//! Tracing another process takes `CAP_SYS_PTRACE` or, under Yama's default
//! `ptrace_scope` of 1, being its ancestor; in containers a seccomp profile may forbid
//! ptrace altogether. Without, [`FrozenThreads::freeze`] fails with one line saying so.

use std::collections::BTreeSet;
use std::sync::mpsc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use nix::errno::Errno;
use nix::sys::ptrace;
use nix::sys::wait::{waitpid, WaitPidFlag, WaitStatus};
use nix::unistd::Pid;

use crate::Error;

/// Longest a seized thread may take to reach its stop: a thread in a system call that
/// cannot be interrupted stops when the call ends, which should be soon; one that
/// never does makes the freeze fail instead of hanging the test.
const STOP_TIMEOUT: Duration = Duration::from_secs(10);

/// How often the tracer thread, while the threads are frozen, reaps the ones that
/// died meanwhile: a traced thread that exits stays a zombie until its tracer waits for
/// it, and keeps its process's exit from its parent until then.
const REAP_INTERVAL: Duration = Duration::from_millis(50);

/// The threads of a process whose names start with a prefix, stopped until this is
/// thawed or dropped.
#[derive(Debug)]
pub struct FrozenThreads {
    pid: u32,
    tids: Vec<u32>,
    /// Dropping it tells the tracer thread to detach.
    release: Option<mpsc::Sender<()>>,
    tracer: Option<JoinHandle<Result<(), Error>>>,
}

impl FrozenThreads {
    /// Stops every thread of process `pid` whose name starts with `prefix` and returns
    /// once all of them are stopped. Threads that exit meanwhile are left out; a
    /// process with no such thread is an error, as is one that cannot be traced.
    pub fn freeze(pid: u32, prefix: &str) -> Result<FrozenThreads, Error> {
        let (frozen_tx, frozen_rx) = mpsc::channel();
        let (release, released) = mpsc::channel::<()>();
        let prefix = prefix.to_owned();
        let tracer = std::thread::Builder::new()
            .name(format!("freeze-{pid}"))
            .spawn(move || trace(pid, &prefix, &frozen_tx, &released))
            .map_err(|e| Error::Freeze {
                pid,
                reason: format!("cannot start the tracing thread: {e}"),
            })?;
        match frozen_rx.recv() {
            Ok(tids) => Ok(FrozenThreads {
                pid,
                tids,
                release: Some(release),
                tracer: Some(tracer),
            }),
            // The tracer ended without freezing anything: its result says why.
            Err(mpsc::RecvError) => Err(match tracer.join() {
                Ok(Err(e)) => e,
                Ok(Ok(())) => Error::Freeze {
                    pid,
                    reason: "the tracing thread ended early".into(),
                },
                Err(_) => Error::Freeze {
                    pid,
                    reason: "the tracing thread panicked".into(),
                },
            }),
        }
    }

    /// The process whose threads are frozen.
    pub fn pid(&self) -> u32 {
        self.pid
    }

    /// The ids of the threads that were stopped, in increasing order.
    pub fn tids(&self) -> &[u32] {
        &self.tids
    }

    /// Resumes the threads (those still alive) and waits until they are.
    pub fn thaw(mut self) -> Result<(), Error> {
        self.release()
    }

    fn release(&mut self) -> Result<(), Error> {
        drop(self.release.take());
        match self.tracer.take().map(JoinHandle::join) {
            None => Ok(()),
            Some(Ok(result)) => result,
            Some(Err(_)) => Err(Error::Freeze {
                pid: self.pid,
                reason: "the tracing thread panicked".into(),
            }),
        }
    }
}

impl Drop for FrozenThreads {
    fn drop(&mut self) {
        // Resuming threads that have died meanwhile is no failure worth a panic here.
        let _ = self.release();
    }
}

/// The tracer thread: seizes and stops the threads, reports their ids on `frozen`,
/// then waits for `released` to close and detaches them.
fn trace(
    pid: u32,
    prefix: &str,
    frozen: &mpsc::Sender<Vec<u32>>,
    released: &mpsc::Receiver<()>,
) -> Result<(), Error> {
    let mut seized = BTreeSet::new();
    let result = seize_all(pid, prefix, &mut seized);
    if let Err(e) = result {
        detach_all(&seized);
        return Err(e);
    }
    if frozen.send(seized.iter().copied().collect()).is_err() {
        detach_all(&seized);
        return Ok(());
    }
    // Until the guard is released (its sender dropped).
    while let Err(mpsc::RecvTimeoutError::Timeout) = released.recv_timeout(REAP_INTERVAL) {
        reap_dead(&mut seized);
    }
    detach_all(&seized);
    Ok(())
}

/// Seizes and stops every thread named `prefix*`, again until no new one appears (a
/// pool may still be starting threads while the first are seized).
fn seize_all(pid: u32, prefix: &str, seized: &mut BTreeSet<u32>) -> Result<(), Error> {
    loop {
        let fresh: Vec<u32> = named_threads(pid, prefix)?
            .into_iter()
            .filter(|tid| !seized.contains(tid))
            .collect();
        if fresh.is_empty() {
            break;
        }
        let mut stopping = Vec::new();
        for tid in fresh {
            let target = Pid::from_raw(tid as i32);
            match ptrace::seize(target, ptrace::Options::empty()) {
                Ok(()) => {}
                // Exited since it was listed.
                Err(Errno::ESRCH) => continue,
                Err(e) => return Err(ptrace_error(pid, tid, "seize", e)),
            }
            seized.insert(tid);
            match ptrace::interrupt(target) {
                Ok(()) => stopping.push(tid),
                Err(Errno::ESRCH) => {
                    seized.remove(&tid);
                }
                Err(e) => return Err(ptrace_error(pid, tid, "interrupt", e)),
            }
        }
        for tid in stopping {
            let stopped = wait_for_stop(pid, tid)?;
            // A thread id is only unique while its thread lives: one that exited after
            // the listing could have been reused by another process's thread.
            let ours = std::path::Path::new(&format!("/proc/{pid}/task/{tid}")).exists();
            if !stopped || !ours {
                seized.remove(&tid);
                if stopped {
                    let _ = ptrace::detach(Pid::from_raw(tid as i32), None);
                }
            }
        }
    }
    if seized.is_empty() {
        return Err(Error::NoSuchThreads {
            pid,
            prefix: prefix.to_owned(),
        });
    }
    Ok(())
}

/// Waits until seized thread `tid` is in its ptrace stop: `true` once it is, `false`
/// if it exited first.
fn wait_for_stop(pid: u32, tid: u32) -> Result<bool, Error> {
    let target = Pid::from_raw(tid as i32);
    let deadline = Instant::now() + STOP_TIMEOUT;
    loop {
        match waitpid(target, Some(WaitPidFlag::__WALL | WaitPidFlag::WNOHANG)) {
            // The stop PTRACE_INTERRUPT asked for (or a group stop, which leaves the
            // thread stopped just as well).
            Ok(WaitStatus::PtraceEvent(_, _, event))
                if event == ptrace::Event::PTRACE_EVENT_STOP as i32 =>
            {
                return Ok(true);
            }
            // A signal arrived first: it is the thread's, so it gets it; the interrupt
            // is still pending and stops it next.
            Ok(WaitStatus::Stopped(_, signal)) => match ptrace::cont(target, signal) {
                Ok(()) | Err(Errno::ESRCH) => {}
                Err(e) => return Err(ptrace_error(pid, tid, "resume", e)),
            },
            Ok(WaitStatus::Exited(..) | WaitStatus::Signaled(..)) | Err(Errno::ECHILD) => {
                return Ok(false);
            }
            Ok(WaitStatus::StillAlive) => {
                if Instant::now() >= deadline {
                    return Err(Error::Freeze {
                        pid,
                        reason: format!("thread {tid} did not stop within {STOP_TIMEOUT:?}"),
                    });
                }
                std::thread::sleep(Duration::from_millis(1));
            }
            Ok(_) | Err(Errno::EINTR) => {}
            Err(e) => return Err(ptrace_error(pid, tid, "wait for", e)),
        }
    }
}

/// Forgets the frozen threads that have died (their process killed, most likely),
/// reaping them so that they do not hold up their process's exit.
fn reap_dead(seized: &mut BTreeSet<u32>) {
    seized.retain(|&tid| {
        !matches!(
            waitpid(
                Pid::from_raw(tid as i32),
                Some(WaitPidFlag::__WALL | WaitPidFlag::WNOHANG),
            ),
            Ok(WaitStatus::Exited(..) | WaitStatus::Signaled(..)) | Err(Errno::ECHILD)
        )
    });
}

/// Detaches every seized thread, which resumes it; one that has died meanwhile
/// (`ESRCH`) has nothing to resume.
fn detach_all(seized: &BTreeSet<u32>) {
    for &tid in seized {
        let _ = ptrace::detach(Pid::from_raw(tid as i32), None);
    }
}

/// The ids of process `pid`'s threads whose names start with `prefix`.
fn named_threads(pid: u32, prefix: &str) -> Result<Vec<u32>, Error> {
    let dir = format!("/proc/{pid}/task");
    let entries = std::fs::read_dir(&dir).map_err(|e| Error::Freeze {
        pid,
        reason: format!("cannot list {dir}: {e}"),
    })?;
    let mut tids = Vec::new();
    for entry in entries.flatten() {
        let Some(tid) = entry.file_name().to_str().and_then(|s| s.parse().ok()) else {
            continue;
        };
        // A thread that exits between the listing and this read is simply not one.
        if let Ok(comm) = std::fs::read_to_string(entry.path().join("comm")) {
            if comm.trim_end_matches('\n').starts_with(prefix) {
                tids.push(tid);
            }
        }
    }
    tids.sort_unstable();
    Ok(tids)
}

fn ptrace_error(pid: u32, tid: u32, what: &str, errno: Errno) -> Error {
    let hint = if errno == Errno::EPERM {
        " (tracing another process takes root or CAP_SYS_PTRACE)"
    } else {
        ""
    };
    Error::Freeze {
        pid,
        reason: format!("cannot {what} thread {tid}: {}{hint}", errno.desc()),
    }
}
