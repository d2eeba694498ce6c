//! The coordinator's data directory fails under a running job (the `tessera` binary as
//! coordinator, workers and clients, on 127.0.0.1 only; the data directory on a file
//! system of its own, mounted by the test).
//!
//! What is proven: a storage failure is visible and transient. While the data
//! directory is full, read-only or frozen, the coordinator says so (`/readyz` answers
//! 503 with `storage unavailable: …`, the gauge `tessera_storage_available` is 0, one
//! log line), hands out no new tiles, refuses new jobs with `cannot store new jobs`,
//! and keeps every acknowledged job (none turns `failed`); `/healthz`, `status` and the
//! workers' heartbeats never wait on the disk. When the disk is usable again it resumes
//! by itself, without a restart, and the job ends `done` with `tessera render`'s image.
//!
//! - **Disk full**: a small tmpfs, filled up by the test while the job runs, then grown
//!   (`mount -o remount,size=…`). The time from "space again" to "job resumed" is
//!   printed; a `submit --wait` following the job exits 0 with the image.
//! - **Read-only**: the kernel refuses to remount a file system read-only while a
//!   process holds a file on it open for writing (`EBUSY`), and the coordinator holds
//!   its database open. The test tries `mount -o remount,ro` first; when it is refused
//!   the data directory is made read-only in the two ways that do not need the files to
//!   be closed: a read-only bind mount of the directory over itself (every file created
//!   or replaced under it fails with `EROFS`) and the immutable attribute on the files
//!   already open (every write through them fails with `EPERM`; ext4 refuses those
//!   writes, tmpfs does not, hence an ext4 file system on a loop device). Undone in the
//!   reverse order. The test prints which way was used.
//! - **Frozen** (`fsfreeze` on an ext4 file system on a loop device) for 6 s, twice the
//!   coordinator's heartbeat timeout: `/healthz` answers within 1 s throughout, `status`
//!   within 2 s, no worker is dropped.
//! - **A submission on a full disk** is refused with one line, and accepted once the
//!   disk has space again.
//!
//! Mounting needs root, util-linux and e2fsprogs. When the test cannot mount, it prints
//! `skipped: REASON` on stderr and passes, unless `TESSERA_REQUIRE_PRIVILEGED=1` (set
//! in CI), where it fails. Every mount point is under the test's temporary directory;
//! a guard unmounts it, thaws it and detaches its loop device, also when the test fails
//! (thawing first, so that the coordinator can be killed). Each of these tests has the
//! machine to itself.

use std::ffi::OsStr;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use serde_json::Value;
use tempfile::TempDir;

use crate::support::{
    self, assert_not_ended_badly, path_str, tiles_done, tiles_total, Daemon, Findings,
};

/// Some 3.6 CPU-seconds in 1,900 tiles of 32 pixels (6 MB of tile blobs).
const JOB: &[&str] = &[
    "--width", "1600", "--height", "1200", "--aa", "5", "--tile", "32",
];
/// Some 5 CPU-seconds in 1,900 tiles: still running when a stall is noticed (some 2 s
/// into a freeze begun a sixth of the way; the frozen file system test checks that
/// tiles were still to come then).
const LONG_JOB: &[&str] = &[
    "--width", "1600", "--height", "1200", "--aa", "11", "--tile", "32",
];
/// Longest a job may take once the storage is back.
const JOB_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest the coordinator may take to notice that the storage fails.
const DETECT_TIMEOUT: Duration = Duration::from_secs(15);
/// Longest the coordinator may take to notice that the storage is back (it retries
/// every 500 ms).
const RECOVER_TIMEOUT: Duration = Duration::from_secs(15);
/// Longest `/healthz` may take to answer, whatever the disk does.
const HEALTHZ_LIMIT: Duration = Duration::from_secs(1);
/// Longest `tessera status` may take, whatever the disk does.
const STATUS_LIMIT: Duration = Duration::from_secs(2);
/// Longest a refused submission may take, whatever the disk does.
const SUBMIT_LIMIT: Duration = Duration::from_secs(5);

// ---------------------------------------------------------------------------------
// Privileged set-up: mounts, loop devices, freezes, under guards.
// ---------------------------------------------------------------------------------

/// Runs `setup`, a privileged step: if it fails, the test fails when privileges are
/// required, and is otherwise skipped with a line on stderr saying why (the rule of
/// [`localfarm::unprivileged`], which the CPU-limited workers follow too).
fn privileged<T>(test: &str, setup: impl FnOnce() -> Result<T, String>) -> Option<T> {
    setup()
        .inspect_err(|reason| localfarm::unprivileged(test, reason))
        .ok()
}

/// The effective user id of this process.
fn effective_uid() -> Option<u32> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("Uid:"))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

fn require_root(what: &str) -> Result<(), String> {
    match effective_uid() {
        Some(0) => Ok(()),
        Some(uid) => Err(format!("{what} needs root (running as uid {uid})")),
        None => Err(format!("{what} needs root (cannot read the user id)")),
    }
}

/// Where the system tool `name` is (also in the sbin directories, which a user's PATH
/// may lack).
fn tool(name: &str) -> Result<PathBuf, String> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .chain(["/usr/sbin", "/sbin", "/usr/bin", "/bin"].map(PathBuf::from))
        .map(|dir| dir.join(name))
        .find(|candidate| candidate.is_file())
        .ok_or_else(|| format!("the tool `{name}` is not installed"))
}

/// Runs a system tool, at most 30 s; `Err` says what it printed.
fn run<S: AsRef<OsStr>>(name: &str, args: &[S]) -> Result<(), String> {
    let program = tool(name)?;
    let shown = format!(
        "{name} {}",
        args.iter()
            .map(|a| a.as_ref().to_string_lossy().into_owned())
            .collect::<Vec<_>>()
            .join(" ")
    );
    let mut child = Command::new(&program)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| format!("cannot run `{shown}`: {e}"))?;
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if child.try_wait().map_err(|e| e.to_string())?.is_some() {
            break;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            return Err(format!("`{shown}` still ran after 30 s: killed"));
        }
        thread::sleep(Duration::from_millis(5));
    }
    let output = child.wait_with_output().map_err(|e| e.to_string())?;
    if output.status.success() {
        Ok(())
    } else {
        Err(format!(
            "`{shown}` failed ({}): {}",
            output.status,
            String::from_utf8_lossy(&output.stderr).trim()
        ))
    }
}

/// Unmounts `point`, retrying a busy mount for up to 5 s, then detaching it lazily.
fn unmount(point: &Path) -> Result<(), String> {
    let mut last = String::new();
    for _ in 0..50 {
        match run("umount", &[point]) {
            Ok(()) => return Ok(()),
            Err(e) => last = e,
        }
        thread::sleep(Duration::from_millis(100));
    }
    run("umount", &[OsStr::new("-l"), point.as_os_str()]).map_err(|e| format!("{last}; then {e}"))
}

/// A file system mounted for one test under its temporary directory; dropping it thaws
/// it (in case), unmounts it and detaches its loop device.
struct Mount {
    point: PathBuf,
    loop_device: Option<String>,
    mounted: bool,
    kind: &'static str,
}

impl Mount {
    /// A tmpfs of `size_mib` MiB at `PARENT/mnt`.
    fn tmpfs(parent: &Path, size_mib: u64) -> Result<Mount, String> {
        require_root("mounting a tmpfs")?;
        tool("mount")?;
        tool("umount")?;
        let point = parent.join("mnt");
        std::fs::create_dir_all(&point).map_err(|e| e.to_string())?;
        let mut mount = Mount {
            point,
            loop_device: None,
            mounted: false,
            kind: "tmpfs",
        };
        run(
            "mount",
            &[
                "-t",
                "tmpfs",
                "-o",
                &format!("size={size_mib}m,mode=0755"),
                "tessera-test",
                path_str(&mount.point),
            ],
        )?;
        mount.mounted = true;
        Ok(mount)
    }

    /// An ext4 file system of `size_mib` MiB in `PARENT/fs.img`, on a loop device, at
    /// `PARENT/mnt`.
    fn ext4(parent: &Path, size_mib: u64) -> Result<Mount, String> {
        require_root("mounting a loop device")?;
        for name in ["mount", "umount", "losetup", "mkfs.ext4"] {
            tool(name)?;
        }
        let image = parent.join("fs.img");
        std::fs::File::create(&image)
            .and_then(|f| f.set_len(size_mib * 1024 * 1024))
            .map_err(|e| format!("cannot create {}: {e}", image.display()))?;
        run(
            "mkfs.ext4",
            &[
                "-q",
                "-F",
                "-E",
                "lazy_itable_init=0,lazy_journal_init=0",
                path_str(&image),
            ],
        )?;
        let point = parent.join("mnt");
        std::fs::create_dir_all(&point).map_err(|e| e.to_string())?;
        let output = Command::new(tool("losetup")?)
            .args(["--find", "--show", path_str(&image)])
            .output()
            .map_err(|e| format!("cannot run losetup: {e}"))?;
        if !output.status.success() {
            return Err(format!(
                "`losetup --find --show` failed: {}",
                String::from_utf8_lossy(&output.stderr).trim()
            ));
        }
        let device = String::from_utf8_lossy(&output.stdout).trim().to_owned();
        let mut mount = Mount {
            point,
            loop_device: Some(device.clone()),
            mounted: false,
            kind: "ext4 on a loop device",
        };
        run("mount", &["-t", "ext4", &device, path_str(&mount.point)])?;
        mount.mounted = true;
        Ok(mount)
    }

    /// Gives a tmpfs a new size, without unmounting it.
    fn resize(&self, size_mib: u64) -> Result<(), String> {
        run(
            "mount",
            &[
                "-o",
                &format!("remount,size={size_mib}m"),
                path_str(&self.point),
            ],
        )
    }
}

impl Drop for Mount {
    fn drop(&mut self) {
        if self.mounted {
            let _ = run("fsfreeze", &[OsStr::new("-u"), self.point.as_os_str()]);
            if let Err(e) = unmount(&self.point) {
                eprintln!("cannot unmount {}: {e}", self.point.display());
            }
        }
        if let Some(device) = &self.loop_device {
            if let Err(e) = run("losetup", &["-d", device]) {
                eprintln!("cannot detach {device}: {e}");
            }
        }
    }
}

/// A frozen file system (`fsfreeze -f`); thawed when dropped.
struct Freeze {
    point: PathBuf,
    frozen: bool,
}

impl Freeze {
    fn new(point: &Path) -> Result<Freeze, String> {
        tool("fsfreeze")?;
        run("fsfreeze", &[OsStr::new("-f"), point.as_os_str()])?;
        Ok(Freeze {
            point: point.to_owned(),
            frozen: true,
        })
    }

    fn thaw(mut self) {
        self.frozen = false;
        run("fsfreeze", &[OsStr::new("-u"), self.point.as_os_str()]).expect("cannot thaw");
    }
}

impl Drop for Freeze {
    fn drop(&mut self) {
        if self.frozen {
            let _ = run("fsfreeze", &[OsStr::new("-u"), self.point.as_os_str()]);
        }
    }
}

/// How the data directory was made read-only.
enum ReadOnlyWay {
    /// `mount -o remount,ro` of its file system.
    Remount,
    /// A read-only bind mount over the directory, and these files made immutable.
    BindAndImmutable(Vec<PathBuf>),
}

/// A read-only data directory; writable again when dropped.
struct ReadOnly {
    fs: PathBuf,
    data: PathBuf,
    way: Option<ReadOnlyWay>,
}

/// The regular files under `dir`, except SQLite's shared-memory index (written through
/// a memory map).
fn files_under(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        match entry.file_type() {
            Ok(t) if t.is_dir() => files_under(&path, out),
            Ok(t) if t.is_file() && !path.to_string_lossy().ends_with("-shm") => out.push(path),
            _ => {}
        }
    }
}

impl ReadOnly {
    /// Makes `data`, on the file system mounted at `fs`, read-only.
    fn new(fs: &Path, data: &Path) -> Result<ReadOnly, String> {
        let mut ro = ReadOnly {
            fs: fs.to_owned(),
            data: data.to_owned(),
            way: None,
        };
        let refused = match run("mount", &["-o", "remount,ro", path_str(fs)]) {
            Ok(()) => {
                ro.way = Some(ReadOnlyWay::Remount);
                return Ok(ro);
            }
            Err(e) => e,
        };
        tool("chattr")?;
        let mut files = Vec::new();
        files_under(data, &mut files);
        let mut args: Vec<&OsStr> = vec![OsStr::new("+i")];
        args.extend(files.iter().map(|f| f.as_os_str()));
        run("chattr", &args).map_err(|e| format!("remount refused ({refused}); {e}"))?;
        ro.way = Some(ReadOnlyWay::BindAndImmutable(files));
        run("mount", &["--bind", path_str(data), path_str(data)])?;
        if let Err(e) = run("mount", &["-o", "remount,bind,ro", path_str(data)]) {
            let _ = unmount(data);
            return Err(e);
        }
        eprintln!("(remounting read-only was refused: {refused})");
        Ok(ro)
    }

    fn describe(&self) -> String {
        match &self.way {
            Some(ReadOnlyWay::Remount) => "mount -o remount,ro".to_owned(),
            Some(ReadOnlyWay::BindAndImmutable(files)) => format!(
                "a read-only bind mount over the data directory and chattr +i on its {} files",
                files.len()
            ),
            None => "nothing".to_owned(),
        }
    }

    /// Makes the directory writable again.
    fn restore(mut self) -> Result<(), String> {
        self.undo()
    }

    fn undo(&mut self) -> Result<(), String> {
        match self.way.take() {
            Some(ReadOnlyWay::Remount) => run("mount", &["-o", "remount,rw", path_str(&self.fs)]),
            Some(ReadOnlyWay::BindAndImmutable(files)) => {
                let unmounted = unmount(&self.data);
                let mut args: Vec<&OsStr> = vec![OsStr::new("-f"), OsStr::new("-i")];
                args.extend(files.iter().map(|f| f.as_os_str()));
                let _ = run("chattr", &args);
                unmounted
            }
            None => Ok(()),
        }
    }
}

impl Drop for ReadOnly {
    fn drop(&mut self) {
        if let Err(e) = self.undo() {
            eprintln!("cannot make {} writable again: {e}", self.data.display());
        }
    }
}

/// Fills the file system of `path` with the file `path`: the bytes written.
fn fill(path: &Path) -> u64 {
    let mut file = std::fs::File::create(path).expect("cannot create the filler");
    let mut written = 0;
    for chunk in [1 << 20, 4096] {
        let bytes = vec![0x5a; chunk];
        loop {
            match file.write(&bytes) {
                Ok(0) => break,
                Ok(n) => written += n as u64,
                Err(e) if e.raw_os_error() == Some(28) => break, // ENOSPC
                Err(e) => panic!("filling {}: {e}", path.display()),
            }
        }
    }
    written
}

// ---------------------------------------------------------------------------------
// A farm with its HTTP listener, whose data directory is on the test's mount.
// ---------------------------------------------------------------------------------

struct Farm<'a> {
    dir: &'a Path,
    coordinator: Daemon,
    addr: String,
    http: String,
    workers: Vec<Daemon>,
}

impl<'a> Farm<'a> {
    fn start(dir: &'a Path, data: &Path, workers: &[&str]) -> Farm<'a> {
        Farm::start_with(dir, data, workers, &[])
    }

    /// [`Farm::start`] with more arguments for the coordinator.
    fn start_with(dir: &'a Path, data: &Path, workers: &[&str], extra: &[&str]) -> Farm<'a> {
        let http = format!("127.0.0.1:{}", support::free_port());
        let mut args = vec!["--http", http.as_str()];
        args.extend(extra);
        let (coordinator, addr) =
            support::start_coordinator(dir, data, "127.0.0.1:0", &args, "coordinator.log");
        let mut farm = Farm {
            dir,
            coordinator,
            addr,
            http,
            workers: Vec::new(),
        };
        support::poll("the HTTP listener", Duration::from_secs(10), || {
            farm.get("/healthz", Duration::from_secs(2))
                .filter(|(code, _)| *code == 200)
        });
        for name in workers {
            farm.add_worker(name);
        }
        support::wait_for_workers(dir, &farm.addr, workers.len(), support::REGISTER_TIMEOUT);
        farm
    }

    fn add_worker(&mut self, name: &str) {
        self.workers
            .push(support::start_worker(self.dir, &self.addr, name));
    }

    fn get(&self, path: &str, timeout: Duration) -> Option<(u16, String)> {
        support::http_get_within(&self.http, path, timeout)
            .map(|(code, body)| (code, String::from_utf8_lossy(&body).into_owned()))
    }

    fn storage_gauge(&self) -> Option<f64> {
        let (_, text) = self.get("/metrics", Duration::from_secs(3))?;
        support::metric_value(&text, "tessera_storage_available")
    }

    /// `status JOB --json`; fails the test if it does not answer within 10 s.
    fn status(&self, job: u64) -> Value {
        let run = support::tessera_within(
            self.dir,
            &[
                "status",
                &job.to_string(),
                "--json",
                "--coordinator",
                &self.addr,
            ],
            Duration::from_secs(10),
        )
        .unwrap_or_else(|| panic!("`tessera status {job}` did not answer within 10 s"));
        assert!(run.status.success(), "status {job} failed: {}", run.stderr);
        serde_json::from_str(run.stdout.trim())
            .unwrap_or_else(|e| panic!("status --json is not JSON ({e}): {:?}", run.stdout))
    }

    /// Tiles the workers have rendered and the coordinator accepted, on their current
    /// connections.
    fn worker_tiles(&self) -> Option<u64> {
        Some(
            support::try_workers(self.dir, &self.addr)?
                .iter()
                .map(|w| w["tiles_done"].as_u64().unwrap_or(0))
                .sum(),
        )
    }

    fn submit(&self, scene: &str, args: &[&str]) -> u64 {
        support::submit_scene(self.dir, &self.addr, scene, args)
    }

    /// `tessera submit ARGS`, at most `timeout`; `None` if it was still running.
    fn try_submit(&self, args: &[&str], timeout: Duration) -> Option<support::Run> {
        let mut all = vec!["submit"];
        all.extend(args);
        all.extend(["--coordinator", &self.addr]);
        support::tessera_within(self.dir, &all, timeout)
    }

    fn wait_for_tiles(&self, job: u64, tiles: u64) -> Value {
        support::wait_for_tiles(job, tiles, JOB_TIMEOUT, || self.status(job))
    }

    fn wait_done(&self, job: u64) -> Value {
        support::wait_done(self.dir, &self.addr, job, JOB_TIMEOUT)
    }

    /// The job's fetched image is `tessera render`'s for `scene` and `args`.
    fn assert_job_image(&self, job: u64, scene: &str, args: &[&str], what: &str) {
        support::assert_job_image(self.dir, &self.addr, job, scene, args, what);
    }

    fn log(&self) -> String {
        self.coordinator.log_text()
    }
}

/// A small job to submit while the storage is down.
fn small_job(seed: &str) -> Vec<&str> {
    vec![seed, "--width", "64", "--height", "48"]
}

/// The lines of the coordinator's log that report the storage unavailable.
fn outage_lines(log: &str) -> Vec<&str> {
    log.lines()
        .filter(|l| l.contains("storage unavailable"))
        .collect()
}

/// A refused submission: non-zero exit, one line, saying it cannot store new jobs.
fn check_refused(run: Option<support::Run>, findings: &mut Findings, what: &str) -> Option<u64> {
    let Some(run) = run else {
        findings.check(false, || {
            format!("{what}: submit still ran after {SUBMIT_LIMIT:?}")
        });
        return None;
    };
    if run.status.success() {
        findings.check(false, || {
            format!(
                "{what}: a job was accepted while the storage was down: {:?}",
                run.stdout
            )
        });
        // An acknowledged job: it must still end done.
        return run.stdout.trim().parse().ok();
    }
    let lines: Vec<&str> = run
        .stderr
        .lines()
        .filter(|l| !l.trim().is_empty())
        .collect();
    findings.check(
        lines.len() == 1 && lines[0].contains("cannot store new jobs"),
        || {
            format!(
                "{what}: the refusal should be one line saying `cannot store new jobs`: {:?}",
                run.stderr
            )
        },
    );
    eprintln!("{what}: refused: {}", lines.first().unwrap_or(&""));
    None
}

/// What [`check_storage_down`] saw.
struct Down {
    /// From the failure to `/readyz` answering 503.
    detected: Option<Duration>,
    /// Jobs accepted while the storage was down (they must end done too).
    accepted: Vec<u64>,
}

/// Checks the farm while its storage is down (broken at `broken`): `/readyz` 503 with
/// the reason, the gauge at 0, one log line, the job not failed, no tiles handed out,
/// new jobs refused.
fn check_storage_down(farm: &Farm, job: u64, broken: Instant, findings: &mut Findings) -> Down {
    let seed = support::scene_path("seed.json");
    let deadline = broken + DETECT_TIMEOUT;
    let mut readyz = None;
    let detected = loop {
        assert_not_ended_badly(job, &farm.status(job));
        readyz = farm.get("/readyz", Duration::from_secs(3)).or(readyz);
        if matches!(&readyz, Some((503, _))) {
            break Some(broken.elapsed());
        }
        if Instant::now() > deadline {
            break None;
        }
        thread::sleep(Duration::from_millis(50));
    };
    findings.check(detected.is_some(), || {
        format!("/readyz did not answer 503 within {DETECT_TIMEOUT:?} of the storage failing (last answer {readyz:?})")
    });
    if let Some((503, body)) = &readyz {
        findings.check(body.starts_with("storage unavailable:"), || {
            format!("/readyz's 503 should say `storage unavailable: REASON`: {body:?}")
        });
        eprintln!("/readyz while the storage is down: 503 {}", body.trim());
    }
    let gauge = farm.storage_gauge();
    findings.check(gauge == Some(0.0), || {
        format!("tessera_storage_available should be 0 while the storage is down: {gauge:?}")
    });

    // No new tiles: what the workers render now is not accepted for long.
    thread::sleep(Duration::from_secs(1));
    let first = farm.worker_tiles();
    thread::sleep(Duration::from_secs(2));
    let second = farm.worker_tiles();
    findings.check(first.is_some() && first == second, || {
        format!("the workers kept rendering tiles while the storage was down: {first:?} then {second:?} tiles 2 s later")
    });
    let status = farm.status(job);
    assert_not_ended_badly(job, &status);
    eprintln!(
        "while the storage is down: job {job} {} at {}/{} tiles",
        status["state"], status["tiles_done"], status["tiles_total"]
    );

    let accepted = check_refused(
        farm.try_submit(&small_job(&seed), SUBMIT_LIMIT),
        findings,
        "a submission while the storage is down",
    );
    let log = farm.log();
    let lines = outage_lines(&log);
    findings.check(!lines.is_empty() && lines.len() <= 5, || {
        format!(
            "the coordinator should log the outage in one line `storage unavailable: REASON`, \
             not {} lines: {:?}",
            lines.len(),
            lines.iter().take(5).collect::<Vec<_>>()
        )
    });
    Down {
        detected,
        accepted: accepted.into_iter().collect(),
    }
}

/// What [`check_storage_back`] measured from the repair.
struct Back {
    resumed: Duration,
    ready: Option<Duration>,
    done: Duration,
}

/// Checks that the farm resumes by itself once the storage is back (at `repaired`):
/// the job progresses and ends done with `tessera render`'s image, `/readyz` answers
/// 200 again and the gauge is 1. Jobs accepted meanwhile end done too.
fn check_storage_back(
    farm: &Farm,
    job: u64,
    scene: &str,
    args: &[&str],
    down: &Down,
    repaired: Instant,
    findings: &mut Findings,
) -> Back {
    let at_repair = tiles_done(&farm.status(job));
    let resumed = support::poll(
        "the job to resume once the storage is back",
        RECOVER_TIMEOUT,
        || {
            let status = farm.status(job);
            assert_not_ended_badly(job, &status);
            (tiles_done(&status) > at_repair || status["state"] == "done")
                .then(|| repaired.elapsed())
        },
    );
    let mut last;
    let ready = loop {
        last = farm.get("/readyz", Duration::from_secs(3));
        if matches!(&last, Some((200, _))) {
            break Some(repaired.elapsed());
        }
        if repaired.elapsed() > RECOVER_TIMEOUT {
            break None;
        }
        thread::sleep(Duration::from_millis(50));
    };
    findings.check(ready.is_some(), || {
        format!(
            "/readyz did not answer 200 again within {RECOVER_TIMEOUT:?} of the repair: {last:?}"
        )
    });
    let gauge = farm.storage_gauge();
    findings.check(gauge == Some(1.0), || {
        format!("tessera_storage_available should be 1 once the storage is back: {gauge:?}")
    });
    let status = farm.wait_done(job);
    let done = repaired.elapsed();
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    farm.assert_job_image(job, scene, args, "the job through the storage outage");
    let seed = support::scene_path("seed.json");
    for &late in &down.accepted {
        farm.wait_done(late);
        farm.assert_job_image(
            late,
            &seed,
            &small_job(&seed)[1..],
            "a job accepted during the outage",
        );
    }
    Back {
        resumed,
        ready,
        done,
    }
}

fn ms(d: Option<Duration>) -> String {
    d.map_or("never".to_owned(), |d| format!("{} ms", d.as_millis()))
}

/// The data directory's file system fills up mid-job, then grows (no restart): the
/// job pauses (not `failed`), the farm says why and refuses new jobs, the job resumes
/// by itself and ends `done` with `tessera render`'s image; a `submit --wait`
/// following it exits 0 with that image. Prints the time from "space again" to "job
/// resumed".
#[test]
fn a_full_disk_pauses_the_job_until_the_disk_grows() {
    const TEST: &str = "a_full_disk_pauses_the_job_until_the_disk_grows";
    let _turn = support::exclusive();
    let dir = TempDir::new().expect("temporary directory");
    let Some(mount) = privileged(TEST, || Mount::tmpfs(dir.path(), 16)) else {
        return;
    };
    let data = mount.point.join("data");
    let farm = Farm::start(dir.path(), &data, &["w1", "w2"]);
    let lights = support::scene_path("lights.json");
    let out = dir.path().join("waited.png");
    let mut args = vec!["submit", lights.as_str()];
    args.extend(JOB);
    args.extend(["--wait", "-o", path_str(&out), "--coordinator", &farm.addr]);
    let mut client = support::spawn_tessera(dir.path(), &args, "submit-wait.log");
    let job = support::poll("the job to be listed", Duration::from_secs(10), || {
        let run = support::client(dir.path(), &farm.addr, &["list", "--json"]);
        let jobs: Value = serde_json::from_str(run.stdout.trim()).ok()?;
        jobs.as_array()?.first()?["id"].as_u64()
    });
    let total = tiles_total(&farm.wait_for_tiles(job, 1));

    let filled = fill(&mount.point.join("filler"));
    let full = Instant::now();
    let before = tiles_done(&farm.status(job));
    eprintln!(
        "disk full ({} MiB of filler) at {before}/{total} tiles",
        filled >> 20
    );
    let mut findings = Findings::default();
    let down = check_storage_down(&farm, job, full, &mut findings);
    findings.check(client.is_running(), || {
        format!(
            "submit --wait exited ({:?}) while the disk was full: {:?}",
            client.wait_exit(Duration::ZERO),
            client.log_text()
        )
    });

    mount.resize(256).expect("cannot grow the tmpfs");
    let space = Instant::now();
    let back = check_storage_back(&farm, job, &lights, JOB, &down, space, &mut findings);
    eprintln!(
        "disk full: outage seen on /readyz after {}; space again → job resumed in {} ms, \
         /readyz ready in {}, job done in {:.1} s",
        ms(down.detected),
        back.resumed.as_millis(),
        ms(back.ready),
        back.done.as_secs_f64()
    );
    match client.wait_exit(JOB_TIMEOUT) {
        Some(exit) => {
            findings.check(exit.success(), || {
                format!("submit --wait exited with {exit}: {:?}", client.log_text())
            });
            if exit.success() {
                let reference = dir.path().join(format!("reference-{job}.png"));
                support::assert_same_png(&out, &reference, "the image written by submit --wait");
            }
        }
        None => findings.check(false, || {
            "submit --wait still runs after the job ended".to_owned()
        }),
    }
    findings.finish();
}

/// The data directory becomes read-only mid-job, then writable again (no restart):
/// the job pauses (not `failed`), the farm says why, hands out no tiles and refuses new
/// jobs, then resumes by itself and ends `done` with `tessera render`'s image.
#[test]
fn a_read_only_data_directory_pauses_the_farm_until_it_is_writable() {
    const TEST: &str = "a_read_only_data_directory_pauses_the_farm_until_it_is_writable";
    let _turn = support::exclusive();
    let dir = TempDir::new().expect("temporary directory");
    let Some(mount) = privileged(TEST, || Mount::ext4(dir.path(), 64)) else {
        return;
    };
    let data = mount.point.join("data");
    let farm = Farm::start(dir.path(), &data, &["w1", "w2"]);
    let lights = support::scene_path("lights.json");
    let job = farm.submit(&lights, JOB);
    let total = tiles_total(&farm.status(job));
    farm.wait_for_tiles(job, total / 6);

    let Some(read_only) = privileged(TEST, || ReadOnly::new(&mount.point, &data)) else {
        return;
    };
    let broken = Instant::now();
    eprintln!(
        "data directory ({}) read-only at {}/{total} tiles, by {}",
        mount.kind,
        tiles_done(&farm.status(job)),
        read_only.describe()
    );
    let mut findings = Findings::default();
    let down = check_storage_down(&farm, job, broken, &mut findings);

    read_only
        .restore()
        .expect("cannot make the data directory writable");
    let writable = Instant::now();
    let back = check_storage_back(&farm, job, &lights, JOB, &down, writable, &mut findings);
    eprintln!(
        "read-only: outage seen on /readyz after {}; writable again → job resumed in {} ms, \
         /readyz ready in {}, job done in {:.1} s",
        ms(down.detected),
        back.resumed.as_millis(),
        ms(back.ready),
        back.done.as_secs_f64()
    );
    findings.finish();
}

/// How long the file system is frozen: twice [`FREEZE_HEARTBEAT_TIMEOUT`], and seconds
/// past the 2 s after which a write counts as stalled.
const FREEZE: Duration = Duration::from_secs(6);
/// The heartbeat timeout of the coordinator whose disk is frozen: shorter than the
/// default 5 s, so that the freeze past it is shorter too, and three of the workers' 1 s
/// heartbeats, so that no worker is dropped for one a loaded machine delays.
const FREEZE_HEARTBEAT_TIMEOUT: &[&str] = &["--heartbeat-timeout-ms", "3000"];

/// The data directory's file system is frozen (`fsfreeze`) for [`FREEZE`] mid-job:
/// `/healthz` answers within 1 s and `status` within 2 s throughout, the storage is
/// reported unavailable and new jobs refused, no worker is dropped, and after the thaw
/// the job resumes by itself and ends `done` with `tessera render`'s image.
#[test]
fn a_frozen_file_system_stalls_neither_health_nor_status_nor_workers() {
    const TEST: &str = "a_frozen_file_system_stalls_neither_health_nor_status_nor_workers";
    let _turn = support::exclusive();
    let dir = TempDir::new().expect("temporary directory");
    let Some(mount) = privileged(TEST, || Mount::ext4(dir.path(), 64)) else {
        return;
    };
    let data = mount.point.join("data");
    let farm = Farm::start_with(dir.path(), &data, &["w1", "w2"], FREEZE_HEARTBEAT_TIMEOUT);
    let lights = support::scene_path("lights.json");
    let seed = support::scene_path("seed.json");
    let job = farm.submit(&lights, LONG_JOB);
    let total = tiles_total(&farm.status(job));
    farm.wait_for_tiles(job, total / 6);
    let connections = |farm: &Farm| {
        support::connections(&support::try_workers(farm.dir, &farm.addr).unwrap_or_default())
    };
    let workers_before = connections(&farm);
    let at_freeze = tiles_done(&farm.status(job));

    // Declared after the farm: on a failure the file system is thawed before the
    // processes are killed.
    // Scoped: a failed assertion still waits for (and reaps) the reference's process.
    thread::scope(|s| {
        let Some(freeze) = privileged(TEST, || Freeze::new(&mount.point)) else {
            return;
        };
        let frozen = Instant::now();
        // The reference renders on one core meanwhile (some 4.5 s): the workers idle once
        // the stall is noticed, and /healthz and `status` answer in milliseconds beside it.
        let reference = s.spawn(|| {
            let args = [&support::render_args(LONG_JOB)[..], &["--threads", "1"]].concat();
            support::render_reference(dir.path(), &lights, "reference.png", &args)
        });
        let mut findings = Findings::default();
        let mut healthz_worst = Duration::ZERO;
        let mut healthz_bad = Vec::new();
        let mut status_worst = Duration::ZERO;
        let mut status_bad = 0;
        let mut unavailable: Option<(Duration, String)> = None;
        let mut gauge_seen = None;
        let mut refused = false;
        let mut tiles_while_down: Vec<u64> = Vec::new();
        // The workers' results when the stall was noticed: fewer than the job's tiles,
        // or there was nothing left to hold back.
        let mut tiles_at_notice = None;
        let mut accepted = Vec::new();
        let mut last_status = Instant::now() - Duration::from_secs(10);
        while frozen.elapsed() < FREEZE {
            let asked = Instant::now();
            let healthz = farm.get("/healthz", Duration::from_secs(3));
            let took = asked.elapsed();
            healthz_worst = healthz_worst.max(took);
            if !matches!(healthz, Some((200, _))) || took > HEALTHZ_LIMIT {
                healthz_bad.push(format!(
                    "{:.1} s: {:?} in {} ms",
                    frozen.elapsed().as_secs_f64(),
                    healthz.map(|(code, _)| code),
                    took.as_millis()
                ));
            }
            if last_status.elapsed() >= Duration::from_secs(1) {
                last_status = Instant::now();
                let run = support::tessera_within(
                    dir.path(),
                    &[
                        "status",
                        &job.to_string(),
                        "--json",
                        "--coordinator",
                        &farm.addr,
                    ],
                    Duration::from_secs(10),
                );
                let took = last_status.elapsed();
                status_worst = status_worst.max(took);
                if !run.is_some_and(|r| r.status.success()) || took > STATUS_LIMIT {
                    status_bad += 1;
                }
                if unavailable.is_some() {
                    if let Some(tiles) = farm.worker_tiles() {
                        tiles_while_down.push(tiles);
                    }
                }
            }
            if unavailable.is_none() {
                if let Some((503, body)) = farm.get("/readyz", Duration::from_secs(1)) {
                    unavailable = Some((frozen.elapsed(), body));
                    gauge_seen = farm.storage_gauge();
                    tiles_at_notice = farm.worker_tiles();
                }
            }
            if !refused && (unavailable.is_some() || frozen.elapsed() > Duration::from_secs(5)) {
                refused = true;
                let asked = Instant::now();
                let run = farm.try_submit(&small_job(&seed), SUBMIT_LIMIT);
                eprintln!(
                    "a submission while frozen answered in {} ms",
                    asked.elapsed().as_millis()
                );
                accepted.extend(check_refused(
                    run,
                    &mut findings,
                    "a submission while frozen",
                ));
            }
            thread::sleep(Duration::from_millis(200));
        }
        freeze.thaw();
        let thawed = Instant::now();

        findings.check(healthz_bad.is_empty(), || {
            format!(
                "/healthz should answer 200 within {HEALTHZ_LIMIT:?} while the disk is frozen: {}",
                healthz_bad.join("; ")
            )
        });
        findings.check(status_bad == 0, || {
            format!("{status_bad} `tessera status` calls failed or took over {STATUS_LIMIT:?} while the disk was frozen (worst {} ms)", status_worst.as_millis())
        });
        findings.check(unavailable.is_some(), || {
            format!("/readyz never answered 503 during a {FREEZE:?} freeze")
        });
        if let Some((after, body)) = &unavailable {
            findings.check(body.starts_with("storage unavailable:"), || {
                format!("/readyz's 503 should say `storage unavailable: REASON`: {body:?}")
            });
            findings.check(gauge_seen == Some(0.0), || {
                format!("tessera_storage_available should be 0 while frozen: {gauge_seen:?}")
            });
            eprintln!(
                "frozen: /readyz 503 after {} ms: {}",
                after.as_millis(),
                body.trim()
            );
        }
        findings.check(tiles_at_notice.is_some_and(|t| t < total), || {
            format!(
                "the workers had returned {tiles_at_notice:?} of the job's {total} tiles when \
                 the stall was noticed: none was left to hold back (a longer job is needed)"
            )
        });
        let grew = tiles_while_down.windows(2).any(|w| w[1] > w[0]);
        findings.check(!grew, || {
            format!("tiles were still handed out and accepted while frozen: {tiles_while_down:?}")
        });

        let at_thaw = tiles_done(&farm.status(job));
        eprintln!("frozen: {at_thaw}/{total} tiles done at the thaw");
        let resumed = support::poll("the job to resume after the thaw", RECOVER_TIMEOUT, || {
            let status = farm.status(job);
            assert_not_ended_badly(job, &status);
            (tiles_done(&status) > at_thaw || status["state"] == "done").then(|| thawed.elapsed())
        });
        let ready = support::poll("/readyz to be 200 after the thaw", RECOVER_TIMEOUT, || {
            matches!(farm.get("/readyz", Duration::from_secs(3)), Some((200, _)))
                .then(|| thawed.elapsed())
        });
        let gauge = farm.storage_gauge();
        findings.check(gauge == Some(1.0), || {
            format!("tessera_storage_available should be 1 after the thaw: {gauge:?}")
        });
        let workers_after = connections(&farm);
        findings.check(workers_after == workers_before, || {
            format!("the workers' connections changed across the freeze: {workers_before:?} before, {workers_after:?} after")
        });
        let dropped = farm
            .log()
            .lines()
            .filter(|l| l.contains("dropping the worker"))
            .count();
        findings.check(dropped == 0, || {
            format!("the coordinator dropped {dropped} workers during the freeze")
        });
        let status = farm.wait_done(job);
        assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
        eprintln!(
            "frozen {FREEZE:?} at {at_freeze}/{total} tiles: /healthz worst {} ms, status worst {} ms; \
             thawed → job resumed in {} ms, /readyz ready in {} ms, done in {:.1} s",
            healthz_worst.as_millis(),
            status_worst.as_millis(),
            resumed.as_millis(),
            ready.as_millis(),
            thawed.elapsed().as_secs_f64()
        );
        let reference = reference.join().expect("the reference render panicked");
        let out = support::fetch(dir.path(), &farm.addr, job, &format!("job-{job}.png"));
        support::assert_same_png(&out, &reference, "the job through a frozen file system");
        for late in accepted {
            farm.wait_done(late);
            farm.assert_job_image(
                late,
                &seed,
                &small_job(&seed)[1..],
                "a job accepted while frozen",
            );
        }
        findings.finish();
    });
}

/// A submission to a coordinator whose disk is full is refused with one line (and
/// nothing half-stored); the farm reports the storage unavailable; once the disk has
/// space again it is ready within seconds, without a restart, and the same submission
/// is accepted and ends `done` with `tessera render`'s image.
#[test]
fn a_submission_on_a_full_disk_is_refused_then_accepted_once_space_returns() {
    const TEST: &str = "a_submission_on_a_full_disk_is_refused_then_accepted_once_space_returns";
    let _turn = support::exclusive();
    let dir = TempDir::new().expect("temporary directory");
    let Some(mount) = privileged(TEST, || Mount::tmpfs(dir.path(), 8)) else {
        return;
    };
    let data = mount.point.join("data");
    let mut farm = Farm::start(dir.path(), &data, &[]);
    // A scene of 600 KiB (the seed, padded with blanks): storing it needs new space.
    let seed = support::scene_path("seed.json");
    let big = dir.path().join("big-scene.json");
    let mut text = std::fs::read_to_string(&seed).expect("the seed scene");
    text.push('\n');
    text.push_str(&" ".repeat(600 * 1024));
    text.push('\n');
    std::fs::write(&big, text).expect("cannot write the big scene");
    let big = path_str(&big).to_owned();
    let size = ["--width", "320", "--height", "240"];
    let mut big_job = vec![big.as_str()];
    big_job.extend(size);

    let filled = fill(&mount.point.join("filler"));
    let full = Instant::now();
    eprintln!("disk full ({} MiB of filler)", filled >> 20);
    let mut findings = Findings::default();
    let mut accepted_big = Vec::new();
    match farm.try_submit(&big_job, SUBMIT_LIMIT) {
        None => findings.check(false, || {
            format!("a submission on a full disk still ran after {SUBMIT_LIMIT:?}")
        }),
        Some(run) if run.status.success() => {
            findings.check(false, || {
                format!("a job was accepted on a full disk: {:?}", run.stdout)
            });
            accepted_big.extend(run.stdout.trim().parse::<u64>().ok());
        }
        Some(run) => {
            let lines: Vec<&str> = run
                .stderr
                .lines()
                .filter(|l| !l.trim().is_empty())
                .collect();
            findings.check(lines.len() == 1, || {
                format!(
                    "the refusal on a full disk should be one line: {:?}",
                    run.stderr
                )
            });
            eprintln!("the first submission on a full disk: {}", run.stderr.trim());
        }
    }
    let mut readyz = None;
    let detected = loop {
        readyz = farm.get("/readyz", Duration::from_secs(3)).or(readyz);
        if matches!(&readyz, Some((503, _))) {
            break Some(full.elapsed());
        }
        if full.elapsed() > Duration::from_secs(10) {
            break None;
        }
        thread::sleep(Duration::from_millis(50));
    };
    findings.check(
        matches!(&readyz, Some((503, body)) if body.starts_with("storage unavailable:")),
        || format!("/readyz should answer 503 `storage unavailable: …` after a refused submission on a full disk: {readyz:?}"),
    );
    let gauge = farm.storage_gauge();
    findings.check(gauge == Some(0.0), || {
        format!("tessera_storage_available should be 0 on a full disk: {gauge:?}")
    });
    let accepted_small = check_refused(
        farm.try_submit(&small_job(&seed), SUBMIT_LIMIT),
        &mut findings,
        "a second submission on a full disk",
    );
    let listed = support::client(dir.path(), &farm.addr, &["list", "--json"]);
    let jobs: Value = serde_json::from_str(listed.stdout.trim()).unwrap_or(Value::Null);
    findings.check(
        jobs.as_array().map(Vec::len) == Some(accepted_big.len() + accepted_small.iter().len()),
        || format!("only accepted jobs may be listed: {jobs}"),
    );

    mount.resize(64).expect("cannot grow the tmpfs");
    let space = Instant::now();
    let mut last;
    let ready = loop {
        last = farm.get("/readyz", Duration::from_secs(3));
        if matches!(&last, Some((200, _))) {
            break Some(space.elapsed());
        }
        if space.elapsed() > RECOVER_TIMEOUT {
            break None;
        }
        thread::sleep(Duration::from_millis(20));
    };
    findings.check(ready.is_some(), || {
        format!("/readyz was not 200 within {RECOVER_TIMEOUT:?} of the disk having space again: {last:?}")
    });
    let gauge = farm.storage_gauge();
    findings.check(gauge == Some(1.0), || {
        format!("tessera_storage_available should be 1 once there is space: {gauge:?}")
    });
    eprintln!(
        "full disk with no job running: /readyz 503 after {}; space again → ready in {}",
        ms(detected),
        ms(ready)
    );
    let job = farm.submit(&big, &size);
    farm.add_worker("w1");
    let status = farm.wait_done(job);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    farm.assert_job_image(job, &big, &size, "the job accepted once the disk had space");
    for late in accepted_big {
        farm.wait_done(late);
        farm.assert_job_image(late, &big, &size, "a job accepted on a full disk");
    }
    if let Some(late) = accepted_small {
        farm.wait_done(late);
        farm.assert_job_image(
            late,
            &seed,
            &small_job(&seed)[1..],
            "a job accepted on a full disk",
        );
    }
    findings.finish();
}
