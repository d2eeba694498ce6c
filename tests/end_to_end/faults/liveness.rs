//! Workers whose rendering hangs while the rest of them runs: the render threads alone
//! are frozen (ptrace, [`localfarm::FrozenThreads`]), so the worker keeps its
//! connection and its heartbeats, as one whose render thread is deadlocked or stuck in
//! a driver does. Heartbeats cannot tell the coordinator about such a worker; the lack
//! of results can:
//!
//! - **Frozen mid-job, sampled verification, two workers.** The frozen worker is marked
//!   `unresponsive` in `tessera workers --json` (the other never is), its tiles are
//!   rendered by the other, and results held for a confirmation it would have given are
//!   accepted without it: the job ends `done` with `tessera render`'s image. Thawed,
//!   it is responsive again and takes part in the next job.
//! - **The same with `--verify full`** and a third worker to confirm every tile.
//! - **A slow worker that makes progress** (a tenth of a core) is never marked
//!   unresponsive, however long its tiles take beside a fast worker's.
//!
//! The coordinator runs with `--progress-timeout-ms 2000` so that a frozen worker is
//! found out within seconds. Freezing threads takes ptrace, which may need privileges:
//! where it is refused these tests print `skipped: REASON` and pass, unless
//! `TESSERA_REQUIRE_PRIVILEGED=1`, where they fail (as the slow worker's cgroup does).

use std::thread;
use std::time::{Duration, Instant};

use localfarm::{Error, FrozenThreads};
use serde_json::Value;

use super::{Farm, STALL};
use crate::support::{
    assert_not_ended_badly, client, exclusive, ok, poll, render_reference, scene_path,
    start_slow_worker, tiles_done, worker_named, Daemon,
};

/// The coordinator's allowance for a worker's progress: a worker holding a tile past its
/// lease and returning nothing for this long is unresponsive.
const COORDINATOR: &[&str] = &["--progress-timeout-ms", "2000"];

// CPU-seconds of `hall-of-mirrors.json` (the heaviest shipped scene, so that the jobs
// last) measured on the project's 2-core machines. A test that needs its job to last
// checks that it did.
//
// The tiles are small (some 6 ms each) because a worker's allowance is also 16 times
// the slowest tile of the jobs it holds, timed from assignment to result (so with the
// tiles queued behind it in the worker): with tiles of a few milliseconds that stays
// under the 2 s of `--progress-timeout-ms` even on a loaded machine, and the mark
// comes when the test says.

/// Some 4 CPU-seconds in 1,102 tiles: the other worker alone still has seconds of it
/// when its peer is found unresponsive (2 s without a result, the lease of at least
/// 1 s having run out; measured, the mark 2.2 s and the job's end 5 to 6 s after the
/// freeze).
const JOB: &[&str] = &[
    "--width", "1200", "--height", "900", "--aa", "5", "--tile", "32",
];
/// Some 4 CPU-seconds in 1,102 tiles, each rendered twice under `--verify full`.
const FULL_JOB: &[&str] = &[
    "--width", "1200", "--height", "900", "--aa", "5", "--tile", "32",
];
/// The seed scene in some 400 tiles of even cost (its floor and sky are alike from row
/// to row, unlike `hall-of-mirrors.json`'s rows, which differ thirtyfold: a worker on a
/// tenth of a core handed one of its dearest tiles could return nothing while a fast
/// worker rendered the rest), each taking a worker on a tenth of a core some 0.1 s,
/// twenty times a fast worker's (at `--aa 12`, 38 of them in a job of 6.2 s, measured).
const EVEN_JOB: &[&str] = &[
    "--width", "1600", "--height", "1000", "--aa", "9", "--tile", "64",
];
/// The small job after the thaw.
const SMALL: &[&str] = &["--width", "200", "--height", "150", "--tile", "16"];

/// Tiles the worker to freeze renders first: it is busy with the job, and its tiles'
/// times are measured.
const TILES_BEFORE_FREEZE: u64 = 5;
/// Longest from the freeze to the mark: the lease (at least 1 s) and the progress
/// timeout (2 s), plus the coordinator's wake interval (1 s) and the margin of a
/// loaded machine, whose slow tiles lengthen both.
const MARK_BOUND: Duration = Duration::from_secs(25);
/// Longest from the freeze to the job's end.
const DONE_BOUND: Duration = Duration::from_secs(45);
/// Longest from the thaw to the worker's being responsive again (it only has to finish
/// the tile it was rendering and send it).
const THAW_BOUND: Duration = Duration::from_secs(10);

/// Whether the listed worker is marked unresponsive; the field must be there.
fn unresponsive(worker: &Value) -> bool {
    worker["unresponsive"]
        .as_bool()
        .unwrap_or_else(|| panic!("`unresponsive` is not a boolean in {worker}"))
}

/// Freezes the render threads of `worker` while they render, or returns `None` after
/// the skip line where tracing is refused.
///
/// A thread caught between tiles (blocked in a system call: waiting for the next tile,
/// which on the cheap tiles of a job's first rows may come after the last one is done)
/// is thawed and frozen again a moment later: these tests are about a thread hung in
/// the middle of a tile, whose result comes once it is thawed. (A worker frozen while
/// idle has no result to give after the thaw: the tiles it was sent go to the others
/// and are cancelled on it when the job ends, so it would stay unresponsive until it
/// reconnects.) A thread stopped in user code (`syscall` is `-1`) is rendering.
fn freeze_render_threads(test: &str, worker: &Daemon) -> Option<FrozenThreads> {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let frozen = match FrozenThreads::freeze(worker.pid(), "render-") {
            Ok(frozen) => frozen,
            Err(e @ Error::Freeze { .. }) => {
                localfarm::unprivileged(test, &e);
                return None;
            }
            Err(e) => panic!("{test}: freezing {}: {e}", worker.name),
        };
        let calls: Vec<String> = frozen
            .tids()
            .iter()
            .map(|tid| {
                let path = format!("/proc/{}/task/{tid}/syscall", worker.pid());
                std::fs::read_to_string(&path).unwrap_or_default()
            })
            .collect();
        if calls.iter().all(|c| c.starts_with("-1 ")) {
            return Some(frozen);
        }
        assert!(
            Instant::now() < deadline,
            "{test}: {}'s render threads were never caught rendering in 10 s: {calls:?}",
            worker.name
        );
        frozen
            .thaw()
            .expect("thawing render threads caught between tiles");
        thread::sleep(Duration::from_millis(3));
    }
}

/// What one frozen worker's run measured, from the freeze.
struct Frozen {
    /// To the first listing with the worker marked unresponsive.
    marked: Duration,
    /// To the job's `done`.
    done: Duration,
    /// From the thaw to the first listing with the worker responsive again.
    responsive_again: Duration,
    /// Audited results accepted without the confirmation the frozen worker would have
    /// given (`accepted as checked` in the coordinator's log): what waited for it.
    accepted_unconfirmed: usize,
}

/// Starts a farm of one-thread workers `names`, submits `job` with `verify` to it,
/// freezes the render threads of worker `victim` once it has rendered a few tiles, and
/// checks: the frozen worker stays connected and is marked unresponsive, the others
/// never are; the job ends `done` within [`DONE_BOUND`] with `tessera render`'s image;
/// thawed, the worker is responsive again and renders its share of a small job, whose
/// image is right too. `None` where freezing is refused (skipped).
fn frozen_worker_is_worked_around(
    test: &str,
    names: &[&str],
    victim: &str,
    job_args: &[&str],
    verify: &[&str],
) -> Option<Frozen> {
    let farm = Farm::start_with("127.0.0.1:0", names, COORDINATOR);
    let v = names.iter().position(|n| *n == victim).expect("a worker");
    let scene = scene_path("hall-of-mirrors.json");
    let job = farm.submit(&scene, &[job_args, verify].concat());
    let before = poll(
        &format!("{victim} to render {TILES_BEFORE_FREEZE} tiles"),
        STALL,
        || {
            let status = farm.status(job);
            assert_not_ended_badly(job, &status);
            assert_ne!(
                status["state"], "done",
                "job {job} ended before {victim} was frozen: make it longer"
            );
            let worker = worker_named(&farm.try_workers()?, victim)?.clone();
            (worker["tiles_done"].as_u64() >= Some(TILES_BEFORE_FREEZE)).then_some(worker)
        },
    );
    let frozen = freeze_render_threads(test, &farm.workers[v])?;
    let froze = Instant::now();

    let mut marked = None;
    let mut done = None;
    let mut last_status = Value::Null;
    loop {
        if let Some(status) = farm.try_status(job) {
            assert_not_ended_badly(job, &status);
            if status["state"] == "done" && done.is_none() {
                done = Some(froze.elapsed());
            }
            last_status = status;
        }
        let workers = farm.try_workers().unwrap_or_default();
        if !workers.is_empty() {
            let listed = worker_named(&workers, victim).unwrap_or_else(|| {
                panic!(
                    "{victim}, frozen {:?} ago, is no longer listed: its heartbeats should \
                     keep it connected; workers: {}",
                    froze.elapsed(),
                    Value::Array(workers.clone())
                )
            });
            assert_eq!(
                listed["id"], before["id"],
                "{victim} reconnected while its render threads were frozen"
            );
            for worker in workers.iter().filter(|w| w["name"] != victim) {
                assert!(
                    !unresponsive(worker),
                    "{} renders, yet is marked unresponsive {:?} after {victim} froze: {worker}",
                    worker["name"],
                    froze.elapsed()
                );
            }
            if marked.is_none() && unresponsive(listed) {
                marked = Some(froze.elapsed());
            }
        }
        let elapsed = froze.elapsed();
        if marked.is_some() && done.is_some() {
            break;
        }
        assert!(
            marked.is_some() || elapsed < MARK_BOUND,
            "{victim}, frozen with tiles in hand, is not marked unresponsive {MARK_BOUND:?} \
             after the freeze{}; workers: {}",
            done.map_or(String::new(), |d| format!(
                " (job {job} ended {:.1} s after the freeze: if the mark goes with the job, \
                 make the job longer)",
                d.as_secs_f64()
            )),
            farm.try_workers()
                .map_or("(unreachable)".to_owned(), |w| Value::Array(w).to_string()),
        );
        assert!(
            done.is_some() || elapsed < DONE_BOUND,
            "job {job} not done {DONE_BOUND:?} after {victim}'s render threads froze \
             ({}/{} tiles, state {}, eta_ms {}; marked unresponsive after {marked:?}); \
             workers: {}",
            last_status["tiles_done"],
            last_status["tiles_total"],
            last_status["state"],
            last_status["eta_ms"],
            farm.try_workers()
                .map_or("(unreachable)".to_owned(), |w| Value::Array(w).to_string()),
        );
        thread::sleep(Duration::from_millis(100));
    }
    let (marked, done) = (marked.expect("marked"), done.expect("done"));
    // Still frozen, so still marked: the text listing says so on its line alone.
    let text = ok(
        client(farm.dir(), &farm.addr, &["workers"]),
        "tessera workers",
    )
    .stdout;
    for line in text.lines() {
        assert_eq!(
            line.contains(", UNRESPONSIVE"),
            line.contains(&format!(" {victim} on ")),
            "tessera workers, {victim} frozen:\n{text}"
        );
    }
    let status = farm.status(job);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    let log = farm.coordinator_logs();
    assert!(
        log.contains("worker unresponsive"),
        "no `worker unresponsive` line in the coordinator's log"
    );
    farm.assert_job_image(
        job,
        &scene,
        job_args,
        "the job of a worker whose render threads froze",
    );

    frozen.thaw().expect("thawing the render threads");
    let thawed = Instant::now();
    let back = poll(
        &format!("{victim} to be responsive again after the thaw"),
        THAW_BOUND,
        || {
            let workers = farm.try_workers()?;
            let worker = worker_named(&workers, victim)?;
            (!unresponsive(worker)).then(|| worker.clone())
        },
    );
    let responsive_again = thawed.elapsed();
    assert!(
        farm.coordinator_logs().contains("worker responsive again"),
        "no `worker responsive again` line in the coordinator's log"
    );

    // Back in service: it takes its share of the next job, whose image is right.
    let seed = scene_path("seed.json");
    let second = farm.submit(&seed, &[SMALL, verify].concat());
    let status = farm.wait_done(second);
    assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
    let reference = render_reference(
        farm.dir(),
        &seed,
        "seed-reference.png",
        &crate::support::render_args(SMALL),
    );
    farm.assert_job_image_is(second, &reference, "a job after the thaw");
    let after = farm
        .try_workers()
        .and_then(|w| worker_named(&w, victim).cloned())
        .unwrap_or(Value::Null);
    assert!(
        after["tiles_done"].as_u64() > back["tiles_done"].as_u64(),
        "{victim}, responsive again, rendered none of the next job's tiles: {after}"
    );
    farm.assert_no_divergent_duplicates();
    let accepted_unconfirmed = farm
        .coordinator_logs()
        .matches("accepted as checked")
        .count();
    Some(Frozen {
        marked,
        done,
        responsive_again,
        accepted_unconfirmed,
    })
}

fn report(what: &str, frozen: &Frozen) {
    eprintln!(
        "{what}: marked unresponsive {:.1} s and job done {:.1} s after the freeze \
         ({} audited results accepted unconfirmed); responsive again {:.1} s after the thaw",
        frozen.marked.as_secs_f64(),
        frozen.done.as_secs_f64(),
        frozen.accepted_unconfirmed,
        frozen.responsive_again.as_secs_f64()
    );
}

/// Two workers, one whose render thread hangs mid-job while it keeps sending
/// heartbeats: marked unresponsive, worked around, the job `done` and right; thawed,
/// it works again.
#[test]
fn a_worker_whose_render_threads_hang_is_marked_unresponsive_and_worked_around() {
    let test = "a_worker_whose_render_threads_hang_is_marked_unresponsive_and_worked_around";
    let _turn = exclusive();
    if let Some(frozen) = frozen_worker_is_worked_around(test, &["w1", "w2"], "w2", JOB, &[]) {
        report("sampled verification, two workers", &frozen);
    }
}

/// The same under `--verify full`, where every tile needs two machines: the two
/// workers left confirm each other's tiles.
#[test]
fn a_hung_worker_under_full_verification_is_worked_around_by_the_two_others() {
    let test = "a_hung_worker_under_full_verification_is_worked_around_by_the_two_others";
    let _turn = exclusive();
    let names = ["w1", "w2", "w3"];
    let verify = ["--verify", "full"];
    if let Some(frozen) = frozen_worker_is_worked_around(test, &names, "w3", FULL_JOB, &verify) {
        report("full verification, three workers", &frozen);
    }
}

/// A worker on a tenth of a core, beside a fast one, renders a tile in the time the
/// other renders ten or more: slow, but it returns results, so it is never marked
/// unresponsive (every listing during the job is checked), and the job's image is
/// right.
#[test]
fn a_slow_worker_that_makes_progress_is_never_marked_unresponsive() {
    let test = "a_slow_worker_that_makes_progress_is_never_marked_unresponsive";
    let _turn = exclusive();
    let mut farm = Farm::start_with("127.0.0.1:0", &["fast"], COORDINATOR);
    let Some((slow, limit)) = start_slow_worker(test, farm.dir(), &farm.addr, "slow", 0.1, &[])
    else {
        return;
    };
    farm.workers.push(slow);
    farm.wait_for_workers(&["fast", "slow"]);

    let scene = scene_path("seed.json");
    let job = farm.submit(&scene, EVEN_JOB);
    let started = Instant::now();
    let mut listings = 0;
    let mut slow_tiles = 0;
    loop {
        let status = farm.status(job);
        assert_not_ended_badly(job, &status);
        if let Some(workers) = farm.try_workers() {
            listings += 1;
            for worker in &workers {
                assert!(
                    !unresponsive(worker),
                    "{} is marked unresponsive {:.1} s into job {job} ({}/{} tiles): {worker}",
                    worker["name"],
                    started.elapsed().as_secs_f64(),
                    status["tiles_done"],
                    status["tiles_total"]
                );
            }
            if let Some(slow) = worker_named(&workers, "slow") {
                slow_tiles = slow["tiles_done"].as_u64().unwrap_or(0);
            }
        }
        if status["state"] == "done" {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "job {job} not done after 60 s ({}/{} tiles)",
            tiles_done(&status),
            status["tiles_total"]
        );
        thread::sleep(Duration::from_millis(100));
    }
    let took = started.elapsed();
    drop(limit);
    assert!(
        slow_tiles >= 3,
        "the slow worker rendered only {slow_tiles} tiles in the {:.1} s of job {job}: make \
         the job longer",
        took.as_secs_f64()
    );
    assert!(
        !farm.coordinator_logs().contains("worker unresponsive"),
        "the coordinator logged a worker as unresponsive"
    );
    eprintln!(
        "slow worker: {slow_tiles} tiles in a job of {:.1} s, never unresponsive in \
         {listings} listings",
        took.as_secs_f64()
    );
    farm.assert_job_image(job, &scene, EVEN_JOB, "the job of a slow and a fast worker");
}
