//! Faults on the way of a scene's files, on a farm of real processes: the coordinator
//! or a worker killed (`kill -9`) while the worker downloads a file, a worker frozen
//! (`SIGSTOP`) or cut off mid-download, a worker whose cache disk is full or read-only,
//! a coordinator whose data disk fills during an upload, two clients uploading one file
//! at once, a file over the coordinator's limit, and ten thousand files in one job.
//!
//! What is proven: every job ends `done` with `tessera render`'s image byte for byte,
//! a fault of the disk or the network quarantines nobody, a download cut short leaves
//! nothing in a cache, a file is stored once however many upload it, and what cannot
//! be done is refused in one line that says why.
//!
//! A download is made to last with a throttled link ([`ThrottleRelay`]) between the
//! worker and the coordinator and a mesh of several chunks, so that a fault lands
//! mid-download; each test checks that it did (bytes relayed past the first chunk, and
//! the worker's log without `file fetched`).
//!
//! The disk tests mount a tmpfs of their own (root): where they cannot, they print
//! `skipped: …` and pass, unless `TESSERA_REQUIRE_PRIVILEGED=1` (CI), where they fail.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::thread;
use std::time::{Duration, Instant};

use tempfile::TempDir;

use crate::support::cut_proxy::CutProxy;
use crate::support::throttle_relay::ThrottleRelay;
use crate::support::{
    assert_job_image, client, exclusive, fetch, http_get_text, metric_value, one_error_line,
    path_str, poll, restart_coordinator, shared, start_coordinator, start_coordinator_with_http,
    start_restartable_coordinator, start_worker, start_worker_with, submit_scene, try_workers,
    wait_done, wait_for_workers, Daemon, REGISTER_TIMEOUT,
};

const SMALL: &[&str] = &["--width", "160", "--height", "120"];
/// Longest a job of these tests may take once its faults have stopped.
const JOB_TIMEOUT: Duration = Duration::from_secs(40);
/// The throttled link's rate each way: a mesh of [`STRIP_QUADS`] takes some 2 s.
const RATE: u64 = 2_000_000;
/// A strip of this many quads is some 4.3 MB of OBJ text: five chunks.
const STRIP_QUADS: usize = 40_000;
/// The worker log's line for a file fetched whole and checked.
const FETCHED: &str = "file fetched";

/// `DIR/NAME.obj`, a strip of `quads` quads at depth `z` (a distinct file for each
/// `z`), and `DIR/NAME.json`, a scene of it: the scene's path and the file's bytes.
fn write_strip(dir: &Path, name: &str, quads: usize, z: f64) -> (String, Vec<u8>) {
    let mut obj = String::with_capacity(quads * 110);
    for i in 0..=quads {
        let x = -2.0 + 4.0 * i as f64 / quads as f64;
        let y = 0.3 * (i as f64 * 0.01).sin();
        obj.push_str(&format!(
            "v {x:.6} {:.6} {z:.6}\nv {x:.6} {:.6} {z:.6}\n",
            y - 1.0,
            y + 1.0
        ));
    }
    for i in 0..quads {
        let a = 2 * i + 1;
        obj.push_str(&format!(
            "f {a} {} {}\nf {} {} {}\n",
            a + 2,
            a + 1,
            a + 1,
            a + 2,
            a + 3
        ));
    }
    std::fs::write(dir.join(format!("{name}.obj")), &obj).unwrap();
    let scene = format!(
        r#"{{"camera": {{"position": "0 0 -5", "look_at": "0 0 0"}},
        "lights": [{{"position": "0 3 -4", "color": "1 1 1"}}],
        "objects": [{{"type": "mesh", "file": "{name}.obj", "color": "0.4 0.8 0.5 0"}},
                    {{"type": "sphere", "center": "1.5 0.5 -1", "radius": 0.6, "color": "0.9 0.3 0.2 0.4"}}]}}"#
    );
    let path = dir.join(format!("{name}.json"));
    std::fs::write(&path, scene).unwrap();
    (path_str(&path).to_owned(), obj.into_bytes())
}

/// Times `text` holds `needle`.
fn count(text: &str, needle: &str) -> usize {
    text.matches(needle).count()
}

/// Waits until the worker behind `relay` is downloading a file of `size` bytes: more
/// than a chunk relayed to it, the file not complete yet. Returns the bytes relayed.
fn wait_mid_download(relay: &ThrottleRelay, worker: &Daemon, size: usize) -> u64 {
    let relayed = poll("the worker to be mid-download", JOB_TIMEOUT, || {
        let relayed = relay.downstream_bytes();
        (relayed > protocol::ASSET_CHUNK as u64 + 200_000).then_some(relayed)
    });
    assert!(
        relayed < size as u64 && count(&worker.log_text(), FETCHED) == 0,
        "{relayed} bytes relayed: the download of {size} was over before the fault"
    );
    relayed
}

/// The regular files under `dir`, recursively.
fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return found;
    };
    for entry in entries {
        let path = entry.unwrap().path();
        if path.is_dir() {
            found.extend(files_under(&path));
        } else {
            found.push(path);
        }
    }
    found
}

/// `metric` of the coordinator serving HTTP at `http`.
fn metric(http: &str, name: &str) -> f64 {
    metric_value(&http_get_text(http, "/metrics"), name)
        .unwrap_or_else(|| panic!("no metric {name}"))
}

/// No worker was quarantined, and the one named `name` is connected and not
/// quarantined.
fn assert_not_quarantined(dir: &Path, addr: &str, http: &str, name: &str) {
    assert_eq!(metric(http, "tessera_workers_quarantined_total"), 0.0);
    let workers = poll(
        &format!("worker {name} to be connected"),
        REGISTER_TIMEOUT,
        || try_workers(dir, addr).filter(|w| w.iter().any(|w| w["name"] == name)),
    );
    for w in &workers {
        assert!(w["quarantined"].is_null(), "quarantined: {w}");
    }
}

/// Kill -9 of the coordinator while a worker downloads a file through a slow link: the
/// restarted coordinator gives the file again from its start and the job ends exactly.
#[test]
fn the_coordinator_killed_mid_download_serves_the_file_again_after_its_restart() {
    let _turn = exclusive();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (scene, bytes) = write_strip(d, "strip", STRIP_QUADS, 0.5);
    let (mut coordinator, addr) = start_restartable_coordinator(d);
    let relay = ThrottleRelay::start(&addr, RATE);
    let worker = start_worker(d, relay.address(), "w1");
    wait_for_workers(d, &addr, 1, REGISTER_TIMEOUT);
    let job = submit_scene(d, &addr, &scene, SMALL);
    let relayed = wait_mid_download(&relay, &worker, bytes.len());
    coordinator.kill9();
    assert_eq!(
        count(&worker.log_text(), FETCHED),
        0,
        "the file was fetched whole before the kill"
    );
    eprintln!(
        "coordinator killed {relayed} bytes into a download of {}",
        bytes.len()
    );
    let _coordinator = restart_coordinator(d, &addr, &[]);
    wait_done(d, &addr, job, JOB_TIMEOUT);
    assert_job_image(d, &addr, job, &scene, SMALL, "a download across a restart");
    assert_eq!(count(&worker.log_text(), FETCHED), 1, "fetched whole once");
}

/// Kill -9 of a worker with a cache while it downloads a file: nothing of the partial
/// download is in its cache, and restarted on the same cache it fetches the file whole,
/// renders exactly and keeps the file's exact bytes.
#[test]
fn a_worker_killed_mid_download_leaves_nothing_in_its_cache_and_finishes_after_a_restart() {
    let _turn = exclusive();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (scene, bytes) = write_strip(d, "strip", STRIP_QUADS, 0.5);
    let (_coordinator, addr, http) = start_coordinator_with_http(d, &[]);
    let cache = d.join("cache");
    let cache_arg = ["--cache-dir", path_str(&cache)];
    let relay = ThrottleRelay::start(&addr, RATE);
    let mut worker = start_worker_with(d, relay.address(), "w1", &cache_arg);
    wait_for_workers(d, &addr, 1, REGISTER_TIMEOUT);
    let job = submit_scene(d, &addr, &scene, SMALL);
    wait_mid_download(&relay, &worker, bytes.len());
    worker.kill9();
    assert_eq!(
        count(&worker.log_text(), FETCHED),
        0,
        "fetched before the kill"
    );
    assert_eq!(
        files_under(&cache),
        Vec::<PathBuf>::new(),
        "the killed worker's partial download is in its cache"
    );

    let again = start_worker_with(d, &addr, "w1-again", &cache_arg);
    wait_done(d, &addr, job, JOB_TIMEOUT);
    assert_job_image(
        d,
        &addr,
        job,
        &scene,
        SMALL,
        "after a worker killed mid-download",
    );
    let log = again.log_text();
    assert_eq!(count(&log, FETCHED), 1, "{log}");
    assert_eq!(count(&log, "damaged"), 0, "{log}");
    let cached = files_under(&cache);
    assert_eq!(cached.len(), 1, "{cached:?}");
    assert!(
        std::fs::read(&cached[0]).unwrap() == bytes,
        "the cached file is not the file's bytes"
    );
    assert_not_quarantined(d, &addr, &http, "w1-again");
}

/// A worker frozen (`SIGSTOP`) mid-download past the heartbeat timeout, so that its
/// leases run out and it is dropped, then resumed: it fetches again and the job ends
/// exactly, nobody quarantined.
#[test]
fn a_worker_frozen_mid_download_past_its_leases_finishes_the_job_unquarantined() {
    let _turn = exclusive();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (scene, bytes) = write_strip(d, "strip", STRIP_QUADS, 0.5);
    let (_coordinator, addr, http) =
        start_coordinator_with_http(d, &["--heartbeat-timeout-ms", "1500"]);
    let relay = ThrottleRelay::start(&addr, RATE);
    let mut worker = start_worker(d, relay.address(), "w1");
    wait_for_workers(d, &addr, 1, REGISTER_TIMEOUT);
    let job = submit_scene(d, &addr, &scene, SMALL);
    wait_mid_download(&relay, &worker, bytes.len());
    worker.signal("STOP");
    assert_eq!(
        count(&worker.log_text(), FETCHED),
        0,
        "fetched before the freeze"
    );
    poll("the frozen worker to be dropped", JOB_TIMEOUT, || {
        try_workers(d, &addr).filter(Vec::is_empty)
    });
    worker.signal("CONT");
    wait_done(d, &addr, job, JOB_TIMEOUT);
    assert_job_image(d, &addr, job, &scene, SMALL, "a worker frozen mid-download");
    assert_not_quarantined(d, &addr, &http, "w1");
}

/// The link between a worker and the coordinator cut mid-download for longer than the
/// heartbeat timeout, then restored: the worker reconnects, fetches the file again and
/// the job ends exactly, nobody quarantined.
#[test]
fn a_worker_cut_off_mid_download_fetches_again_and_finishes_unquarantined() {
    let _turn = exclusive();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (scene, bytes) = write_strip(d, "strip", STRIP_QUADS, 0.5);
    let (_coordinator, addr, http) =
        start_coordinator_with_http(d, &["--heartbeat-timeout-ms", "1500"]);
    let relay = ThrottleRelay::start(&addr, RATE);
    let proxy = CutProxy::start(relay.address());
    let worker = start_worker(d, proxy.address(), "w1");
    wait_for_workers(d, &addr, 1, REGISTER_TIMEOUT);
    let job = submit_scene(d, &addr, &scene, SMALL);
    wait_mid_download(&relay, &worker, bytes.len());
    proxy.cut();
    assert_eq!(
        count(&worker.log_text(), FETCHED),
        0,
        "fetched before the cut"
    );
    poll("the cut worker to be dropped", JOB_TIMEOUT, || {
        try_workers(d, &addr).filter(Vec::is_empty)
    });
    proxy.restore();
    wait_done(d, &addr, job, JOB_TIMEOUT);
    assert_job_image(
        d,
        &addr,
        job,
        &scene,
        SMALL,
        "a worker cut off mid-download",
    );
    assert_not_quarantined(d, &addr, &http, "w1");
}

/// Two clients submitting at once scenes that name one file, each through a slow link
/// so that their uploads overlap: both jobs end exactly, and the store holds the file
/// once.
#[test]
fn two_jobs_uploading_one_file_at_once_store_it_once() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (a, bytes) = write_strip(d, "strip", STRIP_QUADS, 0.5);
    let b = d.join("other.json");
    std::fs::write(
        &b,
        std::fs::read_to_string(&a)
            .unwrap()
            .replace("0.4 0.8 0.5 0", "0.8 0.4 0.2 0.2"),
    )
    .unwrap();
    let b = path_str(&b).to_owned();
    let (_coordinator, addr, http) = start_coordinator_with_http(d, &[]);
    let _worker = start_worker(d, &addr, "w1");
    let relay = ThrottleRelay::start(&addr, 2 * RATE);
    let jobs: Vec<u64> = thread::scope(|s| {
        let submits: Vec<_> = [&a, &b]
            .into_iter()
            .map(|scene| {
                let relay = relay.address();
                s.spawn(move || {
                    let mut args = vec!["submit", scene.as_str()];
                    args.extend(SMALL);
                    let run = client(d, relay, &args);
                    assert!(run.status.success(), "{}", run.stderr);
                    run.stdout.trim().parse::<u64>().unwrap()
                })
            })
            .collect();
        submits.into_iter().map(|h| h.join().unwrap()).collect()
    });
    for (job, scene) in jobs.iter().zip([&a, &b]) {
        wait_done(d, &addr, *job, JOB_TIMEOUT);
        assert_job_image(d, &addr, *job, scene, SMALL, "a job sharing an upload");
    }
    let size = bytes.len() as f64;
    assert!(
        metric(&http, "tessera_asset_received_bytes_total") > size,
        "only one client uploaded: the uploads did not overlap"
    );
    assert_eq!(metric(&http, "tessera_asset_files"), 1.0);
    assert_eq!(metric(&http, "tessera_asset_bytes"), size);
    let stored = files_under(&d.join("data/assets/objects"));
    assert_eq!(stored.len(), 1, "{stored:?}");
    assert_eq!(
        files_under(&d.join("data/assets/partial")),
        Vec::<PathBuf>::new()
    );
}

/// A file over the coordinator's `--max-file-bytes`: the submission is refused in one
/// line naming the limit, exits non-zero, and nothing is stored.
#[test]
fn a_file_over_the_limit_is_refused_in_one_line_and_nothing_is_stored() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (scene, bytes) = write_strip(d, "strip", 20_000, 0.5);
    assert!(bytes.len() > 1_000_000);
    let (_coordinator, addr, http) =
        start_coordinator_with_http(d, &["--max-file-bytes", "1000000"]);
    let run = client(d, &addr, &["submit", &scene]);
    let line = one_error_line(&run, "a submission naming a file over the limit");
    assert!(
        line.contains("strip.obj") && line.contains("over the limit of 1000000 bytes"),
        "{line}"
    );
    assert_eq!(files_under(&d.join("data/assets")), Vec::<PathBuf>::new());
    assert_eq!(metric(&http, "tessera_asset_received_bytes_total"), 0.0);
    let list = client(d, &addr, &["list", "--json"]);
    assert!(list.status.success(), "{}", list.stderr);
    let jobs: serde_json::Value = serde_json::from_str(&list.stdout).unwrap();
    assert_eq!(
        jobs.as_array().map(Vec::len),
        Some(0),
        "a job was made: {jobs}"
    );
}

/// Ten thousand small files, one a mesh object, in one job: uploaded, fetched and
/// rendered exactly; the times taken are printed.
#[test]
fn ten_thousand_files_in_one_job_render_exactly() {
    let _turn = exclusive();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    const FILES: usize = 10_000;
    let meshes = d.join("m");
    std::fs::create_dir(&meshes).unwrap();
    let mut objects = Vec::with_capacity(FILES);
    for i in 0..FILES {
        let (x, y) = (
            (i % 100) as f64 * 0.06 - 3.0,
            (i / 100) as f64 * 0.045 - 2.25,
        );
        let obj = format!(
            "v {x:.4} {y:.4} 0\nv {:.4} {y:.4} 0.1\nv {x:.4} {:.4} 0.05\nf 1 2 3\n",
            x + 0.05,
            y + 0.04
        );
        std::fs::write(meshes.join(format!("{i:05}.obj")), obj).unwrap();
        objects.push(format!(
            r#"{{"type": "mesh", "file": "m/{i:05}.obj", "color": "{:.2} 0.6 {:.2} 0"}}"#,
            (i % 7) as f64 / 7.0,
            (i % 11) as f64 / 11.0
        ));
    }
    let scene = format!(
        r#"{{"camera": {{"position": "0 0 -5", "look_at": "0 0 0"}},
        "lights": [{{"position": "0 3 -4", "color": "1 1 1"}}],
        "objects": [{}]}}"#,
        objects.join(",\n")
    );
    let scene_path = d.join("many.json");
    std::fs::write(&scene_path, scene).unwrap();
    let scene = path_str(&scene_path);
    // The store flushes each file to disk as it completes (two waits on the disk, some
    // 7 ms on a virtual disk: 70 s for these files); on a tmpfs where there is one
    // (/dev/shm), so that what is timed is the farm's own work.
    let shm = Path::new("/dev/shm");
    let data_parent = if shm.is_dir() {
        tempfile::tempdir_in(shm).unwrap()
    } else {
        eprintln!(
            "no /dev/shm: the coordinator's data is on the disk, whose flushes are timed too"
        );
        TempDir::new().unwrap()
    };
    let http = format!("127.0.0.1:{}", crate::support::free_port());
    let (_coordinator, addr) = start_coordinator(
        d,
        &data_parent.path().join("data"),
        "127.0.0.1:0",
        &["--http", &http],
        "coordinator.log",
    );
    let _worker = start_worker(d, &addr, "w1");
    wait_for_workers(d, &addr, 1, REGISTER_TIMEOUT);
    let started = Instant::now();
    let job = submit_scene(d, &addr, scene, SMALL);
    let submitted = started.elapsed();
    wait_done(d, &addr, job, Duration::from_secs(60));
    let done = started.elapsed();
    assert_job_image(d, &addr, job, scene, SMALL, "ten thousand files");
    assert_eq!(metric(&http, "tessera_asset_files"), FILES as f64);
    eprintln!(
        "{FILES} files: submitted (uploaded) in {:.1} s, job done {:.1} s after the start",
        submitted.as_secs_f64(),
        done.as_secs_f64()
    );
}

/// A tmpfs mounted by the test, unmounted (lazily) when dropped.
struct Tmpfs {
    path: PathBuf,
}

impl Tmpfs {
    /// `mount -t tmpfs -o OPTIONS tmpfs PATH`; `None` after the skip line (or a failure
    /// where privileges are required) if it cannot be mounted.
    fn mount(test: &str, path: &Path, options: &str) -> Option<Tmpfs> {
        std::fs::create_dir_all(path).unwrap();
        match mount(&["-t", "tmpfs", "-o", options, "tmpfs", path_str(path)]) {
            Ok(()) => Some(Tmpfs {
                path: path.to_path_buf(),
            }),
            Err(reason) => {
                localfarm::unprivileged(test, &format!("cannot mount a tmpfs: {reason}"));
                None
            }
        }
    }

    /// `mount -o remount,OPTIONS`.
    fn remount(&self, options: &str) {
        let options = format!("remount,{options}");
        mount(&["-o", &options, path_str(&self.path)])
            .unwrap_or_else(|e| panic!("cannot remount {}: {e}", self.path.display()));
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(&self.path).status();
    }
}

/// Runs `mount ARGS`; `Err` says what it printed.
fn mount(args: &[&str]) -> Result<(), String> {
    let out = Command::new("mount")
        .args(args)
        .output()
        .map_err(|e| format!("cannot run mount: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "mount {} failed: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

/// One worker whose cache disk is full, one whose cache disk is read-only: each
/// renders from the file kept in memory, says so once in its log naming the disk's
/// condition, fetches the file once (no loop), and neither is quarantined.
#[test]
fn workers_whose_cache_disk_is_full_or_read_only_render_from_memory() {
    const TEST: &str = "workers_whose_cache_disk_is_full_or_read_only_render_from_memory";
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let Some(full) = Tmpfs::mount(TEST, &d.join("full"), "size=64k") else {
        return;
    };
    let Some(read_only) = Tmpfs::mount(TEST, &d.join("ro"), "ro,size=1m") else {
        return;
    };
    let (scene, bytes) = write_strip(d, "strip", 4_000, 0.5);
    assert!(bytes.len() > 64 << 10);
    let (_coordinator, addr, http) = start_coordinator_with_http(d, &[]);
    let workers = [
        start_worker_with(d, &addr, "full", &["--cache-dir", path_str(&full.path)]),
        start_worker_with(d, &addr, "ro", &["--cache-dir", path_str(&read_only.path)]),
    ];
    wait_for_workers(d, &addr, 2, REGISTER_TIMEOUT);
    let args = [SMALL, &["--tile", "16"]].concat();
    let job = submit_scene(d, &addr, &scene, &args);
    wait_done(d, &addr, job, JOB_TIMEOUT);
    assert_job_image(
        d,
        &addr,
        job,
        &scene,
        &args,
        "workers without a usable cache",
    );
    for (worker, condition) in workers
        .iter()
        .zip(["No space left on device", "Read-only file system"])
    {
        let log = worker.log_text();
        assert_eq!(count(&log, FETCHED), 1, "{}: {log}", worker.name);
        let warnings: Vec<&str> = log
            .lines()
            .filter(|l| l.contains("cannot be cached"))
            .collect();
        assert_eq!(warnings.len(), 1, "{}: {log}", worker.name);
        assert!(warnings[0].contains(condition), "{}", warnings[0]);
        assert_not_quarantined(d, &addr, &http, worker.name.trim_start_matches("worker "));
    }
    assert_eq!(
        metric(&http, "tessera_asset_sent_bytes_total"),
        2.0 * bytes.len() as f64,
        "each worker fetches the file once"
    );
    assert_eq!(files_under(&full.path), Vec::<PathBuf>::new());
}

/// The coordinator's data directory on a small tmpfs that an upload fills: the
/// submission is refused in one line naming the disk, the upload's bytes are given
/// back, the job done before keeps its image, and once the disk is grown the same
/// submission goes through and renders exactly.
#[test]
fn an_upload_that_fills_the_coordinators_disk_is_refused_given_back_and_retried() {
    const TEST: &str =
        "an_upload_that_fills_the_coordinators_disk_is_refused_given_back_and_retried";
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let data = d.join("data");
    let Some(disk) = Tmpfs::mount(TEST, &data, "size=6m") else {
        return;
    };
    let (_coordinator, addr) = start_coordinator(d, &data, "127.0.0.1:0", &[], "coordinator.log");
    let _worker = start_worker(d, &addr, "w1");
    wait_for_workers(d, &addr, 1, REGISTER_TIMEOUT);
    let seed = crate::support::scene_path("seed.json");
    let before = submit_scene(d, &addr, &seed, SMALL);
    wait_done(d, &addr, before, JOB_TIMEOUT);
    let first = std::fs::read(fetch(d, &addr, before, "before.png")).unwrap();

    let (scene, bytes) = write_strip(d, "strip", 2 * STRIP_QUADS, 0.5);
    assert!(bytes.len() > 6 << 20);
    let mut args = vec!["submit", scene.as_str()];
    args.extend(SMALL);
    let run = client(d, &addr, &args);
    let line = one_error_line(&run, "a submission filling the coordinator's disk");
    assert!(
        line.contains("disk is full") && line.contains(path_str(&data)),
        "{line}"
    );
    assert_eq!(
        files_under(&data.join("assets/partial")),
        Vec::<PathBuf>::new(),
        "the upload's bytes were kept"
    );
    let again = std::fs::read(fetch(d, &addr, before, "again.png")).unwrap();
    assert!(again == first, "the job done before lost its image");
    let list = client(d, &addr, &["list", "--json"]);
    let jobs: serde_json::Value = serde_json::from_str(&list.stdout).unwrap();
    assert_eq!(jobs.as_array().map(Vec::len), Some(1), "{jobs}");

    disk.remount("size=64m");
    let job = poll("a submission once the disk is grown", JOB_TIMEOUT, || {
        let run = client(d, &addr, &args);
        run.status
            .success()
            .then(|| run.stdout.trim().parse::<u64>().unwrap())
    });
    wait_done(d, &addr, job, JOB_TIMEOUT);
    assert_job_image(d, &addr, job, &scene, SMALL, "after the disk was grown");
}
