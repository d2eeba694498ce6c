//! What the coordinator finds on disk at startup cannot be trusted blindly (the
//! `tessera` binary as coordinator, workers and clients, on 127.0.0.1 only; the test
//! damages the data directory between two runs, editing `tessera.db` with SQLite).
//!
//! What is proven:
//!
//! - **A lost job database** (zero-length, deleted, garbage, or another program's
//!   SQLite file) in a data directory that has held jobs stops the coordinator at once:
//!   a non-zero exit and one line on stderr naming the file and `--reset-database`.
//!   With `--reset-database` it starts with an empty database whose job ids continue
//!   above every id ever issued, also those of unfinished jobs that left no folder.
//! - **Damaged tile rows** (a tile number out of range or negative, a value of the
//!   wrong type, a row of a job that does not exist) and **damaged tile blobs** (too
//!   short, too long, empty, or altered with their length kept) in a job interrupted
//!   by killing the coordinator: the restarted coordinator does not crash; it drops
//!   them and renders those tiles again, and the job ends `done` with
//!   `tessera render`'s image, byte for byte.
//! - **A damaged stored image** (truncated, or altered with its length kept): `fetch`
//!   exits 1 with one line saying `damaged` and writes no file, before and after a
//!   restart (unless the coordinator rebuilt the image, which must then be right).
//!
//! Every wait has a deadline, and every process is killed and reaped by a guard, also
//! when an assertion fails.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use rusqlite::{params, Connection};
use serde_json::Value;
use tempfile::TempDir;

use crate::support::{
    self, assert_job_image, path_str, submit_scene, wait_for_workers, Daemon, Findings, SplitMix,
    REGISTER_TIMEOUT,
};

/// Longest a job of these tests may take.
const JOB_TIMEOUT: Duration = Duration::from_secs(60);
/// A job of a few milliseconds.
const SMALL: &[&str] = &["--width", "160", "--height", "120"];
/// Some 3.6 CPU-seconds in 1,900 tiles of 32 pixels.
const JOB: &[&str] = &[
    "--width", "1600", "--height", "1200", "--aa", "5", "--tile", "32",
];

/// Stops a coordinator with SIGTERM and waits for it to exit.
fn stop(coordinator: &mut Daemon) {
    coordinator.signal("TERM");
    coordinator
        .wait_exit(Duration::from_secs(15))
        .expect("the coordinator still runs 15 s after SIGTERM");
}

// ---------------------------------------------------------------------------------
// A lost job database.
// ---------------------------------------------------------------------------------

/// A data directory that has held three jobs: 1 and 2 done (their folders exist), 3
/// still queued (no folder), left by a coordinator stopped cleanly. Returns the data
/// directory and the highest id issued.
fn data_dir_that_held_jobs(dir: &Path) -> (PathBuf, u64) {
    let data = dir.join("data");
    let seed = support::scene_path("seed.json");
    let (mut coordinator, addr) =
        support::start_coordinator(dir, &data, "127.0.0.1:0", &[], "coordinator-1.log");
    let mut worker = support::start_worker(dir, &addr, "w1");
    wait_for_workers(dir, &addr, 1, REGISTER_TIMEOUT);
    for _ in 0..2 {
        let job = submit_scene(dir, &addr, &seed, SMALL);
        support::wait_done(dir, &addr, job, JOB_TIMEOUT);
    }
    worker.kill9();
    wait_for_workers(dir, &addr, 0, REGISTER_TIMEOUT);
    let last = submit_scene(dir, &addr, &seed, SMALL);
    assert_eq!(last, 3, "the third job's id");
    stop(&mut coordinator);
    assert!(data.join("jobs").join("1").is_dir() && !data.join("jobs").join("3").exists());
    (data, last)
}

/// Removes the database's journal files (a clean stop leaves none).
fn remove_journals(data: &Path) {
    for name in ["tessera.db-wal", "tessera.db-shm"] {
        let _ = std::fs::remove_file(data.join(name));
    }
}

/// Starts a coordinator on `data`, which must refuse to start: a non-zero exit within
/// 10 s, with one line on stderr naming the database file and `--reset-database`.
/// Returns that line.
fn assert_refuses_to_start(dir: &Path, data: &Path, what: &str) -> String {
    let mut child = Command::new(support::BIN)
        .args(["coordinator", "--listen", "127.0.0.1:0", "--data"])
        .arg(data)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("cannot start the coordinator");
    let stdout = child.stdout.take().expect("stdout is piped");
    let mut stderr = child.stderr.take().expect("stderr is piped");
    let err = thread::spawn(move || {
        let mut text = String::new();
        let _ = std::io::Read::read_to_string(&mut stderr, &mut text);
        text
    });
    let mut daemon = Daemon {
        name: format!("coordinator on {what}"),
        child,
        log: None,
    };
    let Some(exit) = daemon.wait_exit(Duration::from_secs(10)) else {
        // It started: show what it would do with the next job.
        let line = support::first_line(stdout, Duration::from_secs(1)).unwrap_or_default();
        let addr = line
            .trim()
            .strip_prefix("listening on ")
            .unwrap_or("")
            .to_owned();
        let seed = support::scene_path("seed.json");
        let next = support::tessera_within(
            dir,
            &[
                "submit",
                &seed,
                "--width",
                "8",
                "--height",
                "8",
                "--coordinator",
                &addr,
            ],
            Duration::from_secs(10),
        )
        .map(|r| r.stdout.trim().to_owned());
        daemon.kill9();
        panic!(
            "the coordinator started on {what} instead of refusing (it printed {line:?}; the \
             next job would get id {next:?})"
        );
    };
    drop(stdout);
    let stderr = err.join().expect("stderr reader");
    assert!(
        !exit.success(),
        "{what}: the coordinator exited 0: {stderr:?}"
    );
    let lines: Vec<&str> = stderr.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(
        lines.len(),
        1,
        "{what}: the coordinator should print one line on stderr, not {stderr:?}"
    );
    let db = data.join("tessera.db");
    assert!(
        lines[0].contains(path_str(&db)) && lines[0].contains("--reset-database"),
        "{what}: the error should name {} and --reset-database: {:?}",
        db.display(),
        lines[0]
    );
    eprintln!("{what}: {exit}: {}", lines[0]);
    lines[0].to_owned()
}

/// With `--reset-database` the coordinator starts on a new database; the next job's id
/// is above `last`, and the job ends `done` with `tessera render`'s image.
fn assert_reset_continues_ids(dir: &Path, data: &Path, last: u64, what: &str) {
    let (_coordinator, addr) = support::try_start_coordinator(
        dir,
        data,
        "127.0.0.1:0",
        &["--reset-database"],
        "coordinator-reset.log",
    )
    .unwrap_or_else(|e| panic!("{what}: --reset-database: {e}"));
    let _worker = support::start_worker(dir, &addr, "w2");
    let seed = support::scene_path("seed.json");
    let job = submit_scene(dir, &addr, &seed, SMALL);
    assert!(
        job > last,
        "{what}: after --reset-database the new job got id {job}, but ids up to {last} were \
         issued before"
    );
    support::wait_done(dir, &addr, job, JOB_TIMEOUT);
    assert_job_image(dir, &addr, job, &seed, SMALL, "the first job after a reset");
    eprintln!("{what}: after --reset-database the next job is {job} (ids up to {last} were used)");
}

#[test]
fn a_zero_length_database_stops_the_coordinator_until_reset() {
    let _turn = support::shared();
    let dir = TempDir::new().expect("temporary directory");
    let (data, last) = data_dir_that_held_jobs(dir.path());
    std::fs::File::create(data.join("tessera.db")).expect("truncate the database");
    remove_journals(&data);
    assert_refuses_to_start(dir.path(), &data, "a zero-length database");
    assert_reset_continues_ids(dir.path(), &data, last, "a zero-length database");
}

#[test]
fn a_deleted_database_stops_the_coordinator_until_reset() {
    let _turn = support::shared();
    let dir = TempDir::new().expect("temporary directory");
    let (data, last) = data_dir_that_held_jobs(dir.path());
    std::fs::remove_file(data.join("tessera.db")).expect("delete the database");
    remove_journals(&data);
    assert_refuses_to_start(dir.path(), &data, "a deleted database");
    assert_reset_continues_ids(dir.path(), &data, last, "a deleted database");
}

#[test]
fn a_garbage_database_stops_the_coordinator_until_reset() {
    let _turn = support::shared();
    let dir = TempDir::new().expect("temporary directory");
    let (data, last) = data_dir_that_held_jobs(dir.path());
    let mut rng = SplitMix(0x0dd_ba5e);
    let noise: Vec<u8> = (0..16384).map(|_| rng.next_u64() as u8).collect();
    std::fs::write(data.join("tessera.db"), noise).expect("overwrite the database");
    remove_journals(&data);
    assert_refuses_to_start(dir.path(), &data, "a database of random bytes");
    assert_reset_continues_ids(dir.path(), &data, last, "a database of random bytes");
}

#[test]
fn another_programs_database_stops_the_coordinator_until_reset() {
    let _turn = support::shared();
    let dir = TempDir::new().expect("temporary directory");
    let (data, last) = data_dir_that_held_jobs(dir.path());
    let db = data.join("tessera.db");
    std::fs::remove_file(&db).expect("delete the database");
    remove_journals(&data);
    Connection::open(&db)
        .and_then(|c| {
            c.execute_batch(
                "CREATE TABLE notes (id INTEGER PRIMARY KEY, text TEXT);
                 INSERT INTO notes (text) VALUES ('not a render farm');",
            )
        })
        .expect("another program's database");
    assert_refuses_to_start(dir.path(), &data, "another program's SQLite database");
    assert_reset_continues_ids(dir.path(), &data, last, "another program's SQLite database");
}

// ---------------------------------------------------------------------------------
// Damaged tiles in an interrupted job.
// ---------------------------------------------------------------------------------

/// A farm of two workers whose coordinator was killed (`kill -9`) in the middle of a
/// job, not yet restarted.
struct Interrupted {
    port: u16,
    job: u64,
    total: u64,
    /// Tile numbers stored for the job when the coordinator died.
    stored: Vec<i64>,
    _workers: Vec<Daemon>,
    dir: TempDir,
}

impl Interrupted {
    fn new() -> Interrupted {
        let dir = TempDir::new().expect("temporary directory");
        let d = dir.path();
        let port = support::free_port();
        let (mut coordinator, addr) = support::start_coordinator(
            d,
            &d.join("data"),
            &format!("127.0.0.1:{port}"),
            &[],
            "coordinator-1.log",
        );
        let workers = vec![
            support::start_worker(d, &addr, "w1"),
            support::start_worker(d, &addr, "w2"),
        ];
        wait_for_workers(d, &addr, 2, REGISTER_TIMEOUT);
        let lights = support::scene_path("lights.json");
        let job = submit_scene(d, &addr, &lights, JOB);
        let status = support::poll("a third of the tiles", JOB_TIMEOUT, || {
            let status = support::try_status(d, &addr, job)?;
            let total = status["tiles_total"].as_u64()?;
            (status["tiles_done"].as_u64()? * 3 >= total).then_some(status)
        });
        assert_eq!(status["state"], "running", "make the job longer: {status}");
        coordinator.kill9();
        let total = status["tiles_total"].as_u64().expect("tiles_total");
        let mut farm = Interrupted {
            port,
            job,
            total,
            stored: Vec::new(),
            _workers: workers,
            dir,
        };
        let db = farm.open_db();
        let mut query = db
            .prepare("SELECT tile FROM tiles WHERE job = ?1 ORDER BY tile")
            .expect("query the tiles");
        farm.stored = query
            .query_map(params![job as i64], |r| r.get(0))
            .expect("read the tiles")
            .collect::<rusqlite::Result<_>>()
            .expect("read the tiles");
        assert!(
            farm.stored.len() >= 10,
            "only {} tiles were stored",
            farm.stored.len()
        );
        farm
    }

    fn dir(&self) -> &Path {
        self.dir.path()
    }

    fn open_db(&self) -> Connection {
        Connection::open(self.dir().join("data").join("tessera.db")).expect("open tessera.db")
    }

    /// Whether the tiles table has a checksum column.
    fn has_checksums(&self) -> bool {
        let db = self.open_db();
        let mut query = db.prepare("PRAGMA table_info(tiles)").expect("table_info");
        let columns: Vec<String> = query
            .query_map([], |r| r.get(1))
            .expect("table_info")
            .collect::<rusqlite::Result<_>>()
            .expect("table_info");
        columns.iter().any(|c| c == "sha256")
    }

    /// Runs `sql` on the tile `tile` of the job (`?1` is the job, `?2` the tile).
    fn damage(&self, tile: i64, sql: &str) {
        let changed = self
            .open_db()
            .execute(sql, params![self.job as i64, tile])
            .unwrap_or_else(|e| panic!("{sql}: {e}"));
        assert_eq!(changed, 1, "{sql} changed {changed} rows");
    }

    /// Changes the tile's pixels with `change`, keeping their checksum (if any) as it
    /// was.
    fn edit_pixels(&self, tile: i64, change: impl FnOnce(&mut Vec<u8>)) {
        let db = self.open_db();
        let mut rgb: Vec<u8> = db
            .query_row(
                "SELECT rgb FROM tiles WHERE job = ?1 AND tile = ?2",
                params![self.job as i64, tile],
                |r| r.get(0),
            )
            .expect("the tile's pixels");
        change(&mut rgb);
        db.execute(
            "UPDATE tiles SET rgb = ?3 WHERE job = ?1 AND tile = ?2",
            params![self.job as i64, tile, rgb],
        )
        .expect("alter the tile");
    }

    /// Flips bits of one byte in the middle of the tile's pixels, keeping the length
    /// (and any checksum) as it was.
    fn alter_pixels(&self, tile: i64) {
        self.edit_pixels(tile, |rgb| {
            let middle = rgb.len() / 2;
            rgb[middle] ^= 0x5a;
        });
    }

    /// Restarts the coordinator on the damaged data directory: it must start, resume
    /// the job with at most `kept` tiles done, and finish it with `tessera render`'s
    /// image.
    fn restart_and_finish(&self, kept: u64, what: &str) {
        let d = self.dir();
        let (coordinator, addr) = support::try_start_coordinator(
            d,
            &d.join("data"),
            &format!("127.0.0.1:{}", self.port),
            &[],
            "coordinator-2.log",
        )
        .unwrap_or_else(|e| panic!("{what}: {e}"));
        let mut findings = Findings::default();
        let status = support::try_status(d, &addr, self.job).expect("status after the restart");
        let resumed = status["tiles_done"].as_u64().expect("tiles_done");
        findings.check(resumed <= kept, || {
            format!(
                "{what}: the job resumed with {resumed} tiles done, but only {kept} of the \
                 stored tiles were intact"
            )
        });
        let restarted = Instant::now();
        let status = support::wait_done(d, &addr, self.job, JOB_TIMEOUT);
        assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
        let warnings = coordinator
            .log_text()
            .lines()
            .filter(|l| l.contains("WARN") || l.contains("warn"))
            .count();
        eprintln!(
            "{what}: {} tiles stored of {}, {kept} intact; resumed with {resumed}; done {:.1} \
             s after the restart; {warnings} warning lines in the log",
            self.stored.len(),
            self.total,
            restarted.elapsed().as_secs_f64()
        );
        let lights = support::scene_path("lights.json");
        assert_job_image(d, &addr, self.job, &lights, JOB, what);
        findings.finish();
    }
}

/// Bad tile rows in an interrupted job: a tile number out of range, a negative one, a
/// value of the wrong type, pixels stored as text, and a row of a job that does not
/// exist. The coordinator starts (no panic), renders those tiles again, and the job
/// ends `done` with `tessera render`'s image.
#[test]
fn bad_tile_rows_are_dropped_and_rendered_again() {
    let _turn = support::shared();
    let farm = Interrupted::new();
    let s = &farm.stored;
    let out_of_range = farm.total as i64 + 1000;
    farm.damage(
        s[0],
        &format!("UPDATE tiles SET tile = {out_of_range} WHERE job = ?1 AND tile = ?2"),
    );
    farm.damage(
        s[1],
        "UPDATE tiles SET tile = -7 WHERE job = ?1 AND tile = ?2",
    );
    farm.damage(
        s[2],
        "UPDATE tiles SET rays = 'very many' WHERE job = ?1 AND tile = ?2",
    );
    farm.damage(
        s[3],
        "UPDATE tiles SET rgb = 'not pixels' WHERE job = ?1 AND tile = ?2",
    );
    let (columns, values) = if farm.has_checksums() {
        (
            "job, tile, rgb, rays, worker, sha256",
            "?1, 0, x'000000', 1, 'ghost', zeroblob(32)",
        )
    } else {
        (
            "job, tile, rgb, rays, worker",
            "?1, 0, x'000000', 1, 'ghost'",
        )
    };
    farm.open_db()
        .execute(
            &format!("INSERT INTO tiles ({columns}) VALUES ({values})"),
            params![farm.job as i64 + 1000],
        )
        .expect("a tile of no job");
    farm.restart_and_finish(farm.stored.len() as u64 - 4, "bad tile rows");
}

/// Tile blobs of the wrong length in an interrupted job: half as long, two bytes too
/// long, empty. The coordinator starts, renders those tiles again, and the job ends
/// `done` with `tessera render`'s image.
#[test]
fn tile_blobs_of_the_wrong_length_are_rendered_again() {
    let _turn = support::shared();
    let farm = Interrupted::new();
    let s = &farm.stored;
    farm.damage(
        s[0],
        "UPDATE tiles SET rgb = substr(rgb, 1, length(rgb) / 2) WHERE job = ?1 AND tile = ?2",
    );
    // Edited in Rust: SQL's `||` would turn the blob into text.
    farm.edit_pixels(s[1], |rgb| rgb.extend([0, 0xff]));
    farm.edit_pixels(s[2], Vec::clear);
    farm.restart_and_finish(
        farm.stored.len() as u64 - 3,
        "tile blobs of the wrong length",
    );
}

/// Tile blobs altered with their length kept (what a flipped bit on disk does): their
/// checksum no longer matches, so the coordinator renders them again, and the job ends
/// `done` with `tessera render`'s image.
#[test]
fn altered_tile_blobs_are_caught_by_their_checksum() {
    let _turn = support::shared();
    let farm = Interrupted::new();
    let checksums = farm.has_checksums();
    let middle = farm.stored.len() / 2;
    for &tile in &farm.stored[middle..middle + 3] {
        farm.alter_pixels(tile);
    }
    farm.restart_and_finish(farm.stored.len() as u64 - 3, "altered tile blobs");
    assert!(
        checksums,
        "the tiles table has no sha256 column (the job was right all the same)"
    );
}

// ---------------------------------------------------------------------------------
// Damaged stored images.
// ---------------------------------------------------------------------------------

/// Fetches `job`: either refused with one line saying `damaged` and no file written,
/// or (if the coordinator rebuilt the image) exit 0 with `reference`'s bytes, stored
/// again on disk.
fn check_damaged_fetch(
    dir: &Path,
    addr: &str,
    data: &Path,
    job: u64,
    reference: &Path,
    what: &str,
    findings: &mut Findings,
) {
    let out = dir.join(format!("fetched-{job}-{}.png", what.replace(' ', "-")));
    let run = support::client(
        dir,
        addr,
        &["fetch", &job.to_string(), "-o", path_str(&out)],
    );
    let stored = data.join("jobs").join(job.to_string()).join("image.png");
    let expected = std::fs::read(reference).expect("the reference");
    if run.status.success() {
        let fetched = std::fs::read(&out).unwrap_or_default();
        let on_disk = std::fs::read(&stored).unwrap_or_default();
        findings.check(fetched == expected && on_disk == expected, || {
            format!(
                "{what}: fetch of job {job} exited 0 although its image.png is damaged \
                 (fetched {} bytes{}, the right image has {}, {} on disk)",
                fetched.len(),
                if crate::support::decode_png(&fetched).is_ok() {
                    ""
                } else {
                    ", not a readable PNG"
                },
                expected.len(),
                on_disk.len()
            )
        });
        eprintln!("{what}: job {job} fetched intact (the image was rebuilt or served intact)");
        return;
    }
    let lines: Vec<&str> = run
        .stderr
        .lines()
        .filter(|l| !l.trim().is_empty())
        .collect();
    findings.check(
        run.status.code() == Some(1) && lines.len() == 1 && lines[0].contains("damaged"),
        || {
            format!(
                "{what}: fetch of job {job} should exit 1 with one line saying `damaged`: \
                 exit {}, stderr {:?}",
                run.status, run.stderr
            )
        },
    );
    findings.check(!out.exists(), || {
        format!(
            "{what}: fetch of job {job} failed but wrote {}",
            out.display()
        )
    });
    eprintln!(
        "{what}: fetch of job {job}: {}: {}",
        run.status,
        run.stderr.trim()
    );
}

/// A stored image truncated to half, and another altered with its length kept: `fetch`
/// exits 1 with one line saying `damaged` and writes no file, before and after a
/// restart of the coordinator.
#[test]
fn a_damaged_stored_image_is_reported_not_served() {
    let _turn = support::shared();
    let dir = TempDir::new().expect("temporary directory");
    let d = dir.path();
    let data = d.join("data");
    let (mut coordinator, addr) = support::start_restartable_coordinator(d);
    let _worker = support::start_worker(d, &addr, "w1");
    wait_for_workers(d, &addr, 1, REGISTER_TIMEOUT);
    let seed = support::scene_path("seed.json");
    let size = ["--width", "320", "--height", "240"];
    let truncated = submit_scene(d, &addr, &seed, &size);
    let altered = submit_scene(d, &addr, &seed, &size);
    for job in [truncated, altered] {
        support::wait_done(d, &addr, job, JOB_TIMEOUT);
    }
    let reference = support::render_reference(d, &seed, "reference.png", &size);
    let image = |job: u64| data.join("jobs").join(job.to_string()).join("image.png");
    // The images were stored right (the check of the check).
    for job in [truncated, altered] {
        let stored = std::fs::read(image(job)).expect("the stored image");
        assert_eq!(
            stored,
            std::fs::read(&reference).unwrap(),
            "job {job}'s stored image"
        );
    }
    let meta: Value = serde_json::from_slice(
        &std::fs::read(
            data.join("jobs")
                .join(truncated.to_string())
                .join("job.json"),
        )
        .expect("job.json"),
    )
    .expect("job.json is JSON");

    let bytes = std::fs::read(image(truncated)).unwrap();
    std::fs::write(image(truncated), &bytes[..bytes.len() / 2]).expect("truncate the image");
    let mut bytes = std::fs::read(image(altered)).unwrap();
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x5a;
    std::fs::write(image(altered), &bytes).expect("alter the image");

    let mut findings = Findings::default();
    findings.check(
        meta["image_sha256"].as_str().is_some_and(|h| h.len() == 64),
        || format!("job.json should carry the image's image_sha256: {meta}"),
    );
    for (job, what) in [
        (truncated, "a truncated image"),
        (altered, "an altered image"),
    ] {
        check_damaged_fetch(d, &addr, &data, job, &reference, what, &mut findings);
    }
    stop(&mut coordinator);
    let _coordinator = support::restart_coordinator(d, &addr, &[]);
    for (job, what) in [
        (truncated, "a truncated image after a restart"),
        (altered, "an altered image after a restart"),
    ] {
        check_damaged_fetch(d, &addr, &data, job, &reference, what, &mut findings);
    }
    findings.finish();
}
