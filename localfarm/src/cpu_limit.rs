//! A process slowed the way an operator would slow it: from outside, by the kernel's
//! CPU controller, not by a setting of the process itself. Benchmarks of uneven farms
//! (a worker on a machine three times slower) use it, so that no production type needs
//! a knob for them.
//!
//! A [`CpuLimit`] is a cgroup of its own, limited to a share of one core, that the
//! process is moved into:
//!
//! - cgroup v2 (when `/sys/fs/cgroup` is a cgroup2 mount whose `cgroup.controllers`
//!   lists `cpu`): `cpu.max` of a child of that root. The child hangs from the root
//!   because a cgroup that holds processes cannot give the cpu controller to children
//!   (cgroup v2's "no internal processes" rule), and the process's own cgroup does hold
//!   it.
//! - cgroup v1 otherwise: `cpu.cfs_quota_us` and `cpu.cfs_period_us` of a child of the
//!   process's cgroup under `/sys/fs/cgroup/cpu`.
//!
//! Dropping the limit moves every process in it back to the cgroup the process came
//! from (the limit's parent under v1) and removes the limit's directory. Writing
//! cgroups takes root (and a writable `/sys/fs/cgroup`); without, [`CpuLimit::apply`]
//! fails with one line saying so.

use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Duration;

use crate::Error;

/// Where cgroup v2 is mounted, when it is.
const V2_ROOT: &str = "/sys/fs/cgroup";
/// Where cgroup v1's cpu hierarchy is mounted.
const V1_CPU: &str = "/sys/fs/cgroup/cpu";
/// The kernel's default period of CFS bandwidth control.
const PERIOD_US: u64 = 100_000;
/// The kernel refuses a quota under 1 ms and a period over 1 s.
const MIN_QUOTA_US: u64 = 1_000;
const MAX_PERIOD_US: u64 = 1_000_000;

/// A process limited to a share of one core until this is dropped.
#[derive(Debug)]
pub struct CpuLimit {
    /// The limit's cgroup directory.
    dir: PathBuf,
    /// The cgroup its processes go back to.
    home: PathBuf,
}

/// Which cgroup interface the machine offers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Version {
    V1,
    V2,
}

impl CpuLimit {
    /// Moves process `pid` (all its threads, and the children it starts from then on)
    /// into a new cgroup limited to `share_of_one_core` of one core: 1/3 makes a
    /// one-thread process about three times slower.
    pub fn apply(pid: u32, share_of_one_core: f64) -> Result<CpuLimit, Error> {
        let (quota_us, period_us) = quota(share_of_one_core)?;
        let version = version()?;
        let own = own_cgroup(pid, version)?;
        let limit = CpuLimit::create(&parent(version, &own)?, own)?;
        match version {
            Version::V1 => {
                limit.write("cpu.cfs_period_us", &period_us.to_string())?;
                limit.write("cpu.cfs_quota_us", &quota_us.to_string())?;
            }
            Version::V2 => limit.write("cpu.max", &format!("{quota_us} {period_us}"))?,
        }
        limit.write("cgroup.procs", &pid.to_string())?;
        Ok(limit)
    }

    /// Checks that a limit can be applied here, by creating a limited cgroup with no
    /// process in it and removing it again: for a command that will need one late in
    /// its run to fail at its start instead.
    pub fn probe() -> Result<(), Error> {
        let version = version()?;
        let own = own_cgroup(std::process::id(), version)?;
        let limit = CpuLimit::create(&parent(version, &own)?, own)?;
        let (quota_us, period_us) = quota(1.0)?;
        match version {
            Version::V1 => limit.write("cpu.cfs_quota_us", &quota_us.to_string()),
            Version::V2 => limit.write("cpu.max", &format!("{quota_us} {period_us}")),
        }
    }

    /// The limit's cgroup directory (under `/sys/fs/cgroup`).
    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// A new cgroup under `parent`, removed again when the returned value is dropped,
    /// also when setting it up fails half way.
    fn create(parent: &Path, home: PathBuf) -> Result<CpuLimit, Error> {
        static NEXT: AtomicU32 = AtomicU32::new(0);
        let name = format!(
            "tessera-cpu-limit-{}-{}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed)
        );
        let dir = parent.join(name);
        std::fs::create_dir(&dir).map_err(|e| cannot("create", &dir, &e))?;
        Ok(CpuLimit { dir, home })
    }

    fn write(&self, file: &str, value: &str) -> Result<(), Error> {
        let path = self.dir.join(file);
        // One write each: the kernel takes a cgroup file's value from a single write.
        std::fs::write(&path, value).map_err(|e| cannot("write", &path, &e))
    }
}

impl Drop for CpuLimit {
    fn drop(&mut self) {
        let procs = self.dir.join("cgroup.procs");
        let home = self.home.join("cgroup.procs");
        // A process that forks while the others are moved can land in the limit again:
        // a few rounds, until it is empty.
        for _ in 0..10 {
            let pids = std::fs::read_to_string(&procs).unwrap_or_default();
            if pids.trim().is_empty() {
                break;
            }
            for pid in pids.lines() {
                // A process that has exited meanwhile is gone from the cgroup anyway.
                let _ = std::fs::write(&home, pid);
            }
        }
        // The kernel may take a moment to let go of a cgroup whose last process has
        // just left or exited.
        for _ in 0..50 {
            match std::fs::remove_dir(&self.dir) {
                Err(e) if e.kind() != io::ErrorKind::NotFound => {
                    std::thread::sleep(Duration::from_millis(10));
                }
                _ => break,
            }
        }
    }
}

/// The quota and period (µs) giving `share` of one core.
fn quota(share: f64) -> Result<(u64, u64), Error> {
    // The smallest share the kernel can give is its smallest quota in its longest
    // period; 1024 cores is past any machine this runs on.
    let least = MIN_QUOTA_US as f64 / MAX_PERIOD_US as f64;
    if !(share.is_finite() && (least..=1024.0).contains(&share)) {
        return Err(Error::CpuLimit(format!(
            "a share of {share} of one core: give one from {least} to 1024"
        )));
    }
    // The default period, unless the quota would then fall under the kernel's least.
    let period_us = ((MIN_QUOTA_US as f64 / share).ceil() as u64).clamp(PERIOD_US, MAX_PERIOD_US);
    let quota_us = ((share * period_us as f64).round() as u64).max(MIN_QUOTA_US);
    Ok((quota_us, period_us))
}

/// cgroup v2 when `/sys/fs/cgroup` is a cgroup2 mount with the cpu controller, else v1
/// when its cpu hierarchy is mounted.
fn version() -> Result<Version, Error> {
    let mounts = std::fs::read_to_string("/proc/self/mounts").unwrap_or_default();
    let v2 = mounts.lines().any(|line| {
        let mut fields = line.split_whitespace().skip(1);
        fields.next() == Some(V2_ROOT) && fields.next() == Some("cgroup2")
    });
    if v2 {
        let controllers = Path::new(V2_ROOT).join("cgroup.controllers");
        let listed = std::fs::read_to_string(&controllers).unwrap_or_default();
        if listed.split_whitespace().any(|c| c == "cpu") {
            return Ok(Version::V2);
        }
    }
    if Path::new(V1_CPU).join("cpu.cfs_quota_us").exists() {
        return Ok(Version::V1);
    }
    Err(Error::CpuLimit(format!(
        "this machine has neither cgroup v2 with the cpu controller at {V2_ROOT} nor \
         cgroup v1's cpu hierarchy at {V1_CPU}"
    )))
}

/// Where a limit's cgroup is made for a process in cgroup `own`: under `own` itself with
/// v1; under the root with v2, whose children are then given the cpu controller if they
/// do not have it yet.
fn parent(version: Version, own: &Path) -> Result<PathBuf, Error> {
    match version {
        Version::V1 => Ok(own.to_path_buf()),
        Version::V2 => {
            let control = Path::new(V2_ROOT).join("cgroup.subtree_control");
            let enabled = std::fs::read_to_string(&control).unwrap_or_default();
            if !enabled.split_whitespace().any(|c| c == "cpu") {
                std::fs::write(&control, "+cpu").map_err(|e| cannot("write", &control, &e))?;
            }
            Ok(PathBuf::from(V2_ROOT))
        }
    }
}

/// The directory of the cgroup process `pid` is in, in the hierarchy of `version`.
fn own_cgroup(pid: u32, version: Version) -> Result<PathBuf, Error> {
    let file = format!("/proc/{pid}/cgroup");
    let text = std::fs::read_to_string(&file)
        .map_err(|e| Error::CpuLimit(format!("cannot read {file}: {e} (no process {pid}?)")))?;
    // Lines are `ID:CONTROLLERS:PATH`; v2's is `0::PATH`, v1's cpu one lists `cpu`
    // among its controllers.
    let path = text.lines().find_map(|line| {
        let mut parts = line.splitn(3, ':');
        let (id, controllers, path) = (parts.next()?, parts.next()?, parts.next()?);
        let ours = match version {
            Version::V2 => id == "0" && controllers.is_empty(),
            Version::V1 => controllers.split(',').any(|c| c == "cpu"),
        };
        ours.then_some(path)
    });
    let root = match version {
        Version::V1 => V1_CPU,
        Version::V2 => V2_ROOT,
    };
    let dir = Path::new(root).join(path.unwrap_or("/").trim_start_matches('/'));
    // Inside a container the mount may show a part of the hierarchy only, where the
    // path from /proc (seen from the host's root) does not exist: its root is then the
    // process's cgroup as far as this machine can tell.
    Ok(if dir.is_dir() {
        dir
    } else {
        PathBuf::from(root)
    })
}

/// The one line for a cgroup file or directory that could not be made or written.
fn cannot(what: &str, path: &Path, e: &io::Error) -> Error {
    let hint = match e.kind() {
        io::ErrorKind::PermissionDenied | io::ErrorKind::ReadOnlyFilesystem => {
            ": writing cgroups needs root and a writable /sys/fs/cgroup"
        }
        _ => "",
    };
    Error::CpuLimit(format!("cannot {what} {}: {e}{hint}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_share_becomes_a_quota_in_a_period_the_kernel_accepts() {
        assert_eq!(quota(1.0 / 3.0).unwrap(), (33_333, 100_000));
        assert_eq!(quota(0.05).unwrap(), (5_000, 100_000));
        assert_eq!(quota(2.0).unwrap(), (200_000, 100_000));
        // Under 1 % of a core the period grows, so that the quota stays 1 ms or more.
        assert_eq!(quota(0.002).unwrap(), (1_000, 500_000));
        assert_eq!(quota(0.001).unwrap(), (1_000, 1_000_000));
        for share in [0.0, -1.0, 0.0005, f64::NAN, f64::INFINITY, 2000.0] {
            let e = quota(share).unwrap_err().to_string();
            assert!(
                e.starts_with("cannot limit a process's CPU: a share of ") && !e.contains('\n'),
                "{e}"
            );
        }
    }
}
