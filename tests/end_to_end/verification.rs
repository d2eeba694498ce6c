//! Verification of tile results, end to end: real `tessera` coordinators and workers on
//! 127.0.0.1, with liars among them.
//!
//! - A worker returning pure red tiles, beside an honest one: every red result is
//!   rejected by the spot checks, its machine quarantined, and the job done with
//!   `tessera render`'s exact image. Reconnecting under that name, the liar stays
//!   connected and listed as quarantined, and gets no tile.
//! - A worker changing one byte of every other tile, beside two honest ones: caught by
//!   full verification, and by sampled verification auditing every tile
//!   (`--audit-share 1`).
//! - A relay flipping a byte of every third tile result between an honest worker and
//!   the coordinator, under full verification: the relayed machine is quarantined.
//! - On an adaptive job, a worker returning red pixels with honest block states, and
//!   one returning honest pixels with every block's state a hair off: both caught,
//!   the first by its pixels disagreeing with its state, the second by advancing a
//!   block of its answer again (`--spot-pixels 1024` checks a block of every answer).
//! - A worker whose renderer differs (one pixel of every output, the canary included):
//!   refused at the canary with both builds named, it never gets a tile. Workers whose
//!   connections end during the canary are lost connections, not refusals: counted
//!   apart and logged as warnings.
//! - A machine that rendered tiles honestly before the coordinator was killed, caught
//!   returning red tiles after the restart: the tiles it rendered before, restored
//!   from the disk, are taken back and rendered again by another.
//! - A worker rendering frame 1 of an animated scene for a job of frame 17: caught by
//!   the spot checks, which render the job's frame, and the job done with
//!   `tessera render --frame 17`'s image.
//!
//! Each job ends `done` with the fetched image byte for byte that of `tessera render`,
//! and the culprit is found in `tessera workers --json`, the coordinator's /metrics
//! and its log. Every wait has a deadline, and every process is killed by a guard,
//! also when an assertion fails.

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde_json::Value;
use tempfile::TempDir;

use crate::support::fake_worker::{FakeWorker, Lie};
use crate::support::flip_relay::FlipRelay;
use crate::support::{
    assert_same_png, fetch, free_port, http_get_text, metric_value, orbit, poll, render_args,
    render_reference, restart_coordinator, scene_path, shared, start_coordinator,
    start_restartable_coordinator, start_worker, submit, tessera_within, try_status, try_workers,
    wait_done, Daemon,
};

/// The job of every test: small, 80 tiles.
const JOB: &[&str] = &[
    "--width", "320", "--height", "240", "--aa", "2", "--tile", "32",
];
const TILE: u32 = 32;
/// Longest a job may take, or a worker to show up.
const JOB_TIMEOUT: Duration = Duration::from_secs(60);
const LISTED_TIMEOUT: Duration = Duration::from_secs(20);

/// An adaptive job: small, 20 tiles on 8-pixel blocks.
const ADAPTIVE_JOB: &[&str] = &[
    "--width",
    "160",
    "--height",
    "120",
    "--aa",
    "4",
    "--tile",
    "32",
    "--sampler",
    "adaptive",
    "--target-error",
    "1",
];

/// A coordinator with its HTTP listener, in a directory of its own.
struct Farm {
    /// Dropped before the directory, so that a failing test still shows its log.
    coordinator: Daemon,
    addr: String,
    http: String,
    reference: PathBuf,
    /// The settings of the farm's jobs.
    job: &'static [&'static str],
    dir: TempDir,
}

impl Farm {
    fn start(extra: &[&str]) -> Farm {
        Farm::start_for(extra, JOB)
    }

    /// A farm whose jobs have the settings `job`.
    fn start_for(extra: &[&str], job: &'static [&'static str]) -> Farm {
        let dir = tempfile::tempdir().expect("temporary directory");
        let http = format!("127.0.0.1:{}", free_port());
        let mut args = vec!["--http", http.as_str()];
        args.extend(extra);
        let (coordinator, addr) = start_coordinator(
            dir.path(),
            &dir.path().join("data"),
            "127.0.0.1:0",
            &args,
            "coordinator.log",
        );
        let reference = render_reference(
            dir.path(),
            &scene_path("seed.json"),
            "reference.png",
            &render_args(job),
        );
        Farm {
            job,
            dir,
            coordinator,
            addr,
            http,
            reference,
        }
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }

    fn worker(&self, name: &str) -> Daemon {
        start_worker(self.path(), &self.addr, name)
    }

    /// Submits the seed scene with [`JOB`]'s settings and `extra`: the job's id.
    fn submit(&self, extra: &[&str]) -> u64 {
        let scene = scene_path("seed.json");
        let mut args = vec![scene.as_str()];
        args.extend(self.job);
        args.extend(extra);
        submit(self.path(), &self.addr, &args)
    }

    /// Waits for the job to be done, fetches its image and compares it byte for byte
    /// with `tessera render`'s; returns the fetched PNG's path.
    fn finish(&self, job: u64) -> PathBuf {
        wait_done(self.path(), &self.addr, job, JOB_TIMEOUT);
        let image = fetch(self.path(), &self.addr, job, &format!("job-{job}.png"));
        assert_same_png(&image, &self.reference, &format!("job {job}"));
        image
    }

    /// `tessera workers --json`.
    fn workers(&self) -> Vec<Value> {
        try_workers(self.path(), &self.addr).expect("tessera workers --json failed")
    }

    /// The listed workers named `name`.
    fn named(&self, name: &str) -> Vec<Value> {
        self.workers()
            .into_iter()
            .filter(|w| w["name"] == name)
            .collect()
    }

    /// Waits until every worker of `names` is listed.
    fn wait_listed(&self, names: &[&str]) {
        poll(
            &format!("workers {names:?} to join"),
            LISTED_TIMEOUT,
            || {
                let workers = self.workers();
                names
                    .iter()
                    .all(|n| workers.iter().any(|w| w["name"] == *n))
                    .then_some(())
            },
        );
    }

    /// The coordinator's /metrics.
    fn metrics(&self) -> String {
        http_get_text(&self.http, "/metrics")
    }

    fn metric(&self, name: &str) -> f64 {
        let text = self.metrics();
        metric_value(&text, name).unwrap_or_else(|| panic!("no {name} in /metrics:\n{text}"))
    }

    /// Asserts that `culprit` is quarantined (listed so, and named by the log's error
    /// line) and that none of `honest` is, and that one machine was quarantined.
    fn assert_quarantined(&self, culprit: &str, honest: &[&str]) {
        let workers = self.workers();
        let listed: Vec<&Value> = workers.iter().filter(|w| w["name"] == culprit).collect();
        assert!(!listed.is_empty(), "{culprit} is not listed: {workers:?}");
        for w in listed {
            let reason = w["quarantined"]
                .as_str()
                .unwrap_or_else(|| panic!("{culprit} is not listed as quarantined: {w}"));
            assert!(
                reason.contains("wrong pixels"),
                "{culprit}'s quarantine reason: {reason:?}"
            );
        }
        for name in honest {
            for w in workers.iter().filter(|w| w["name"] == *name) {
                assert!(
                    w["quarantined"].is_null(),
                    "the honest worker {name} is quarantined: {w}"
                );
            }
        }
        assert_eq!(
            self.metric("tessera_workers_quarantined_total"),
            1.0,
            "machines quarantined"
        );
        assert!(
            self.metric("tessera_results_rejected_total") >= 1.0,
            "no result rejected"
        );
        let log = self.coordinator.log_text();
        assert!(
            log.lines()
                .any(|l| l.contains("ERROR") && l.contains("quarantined") && l.contains(culprit)),
            "no error line naming the quarantined {culprit} in the coordinator's log:\n{log}"
        );
        for name in honest {
            assert!(
                !log.lines().any(|l| l.contains("quarantined")
                    && (l.contains(&format!("machine={name} "))
                        || l.contains(&format!("machine=\"{name}\"")))),
                "the coordinator's log quarantines the honest {name}:\n{log}"
            );
        }
    }
}

/// Whether some whole tile of the PNG is pure red.
fn has_red_tile(png: &Path) -> bool {
    let image = crate::support::decode_rgb8(png);
    let (width, height) = image.dimensions();
    (0..height.div_ceil(TILE)).any(|ty| {
        (0..width.div_ceil(TILE)).any(|tx| {
            (ty * TILE..((ty + 1) * TILE).min(height)).all(|y| {
                (tx * TILE..((tx + 1) * TILE).min(width))
                    .all(|x| image.get_pixel(x, y) == [255, 0, 0])
            })
        })
    })
}

#[test]
fn red_tiles_are_rejected_and_their_machine_stays_quarantined_after_reconnecting() {
    let _turn = shared();
    let farm = Farm::start(&[]);
    let build = render::build_identity();
    let liar = FakeWorker::start(&farm.addr, "liar", &build, Lie::Red);
    let honest = farm.worker("honest");
    farm.wait_listed(&["liar", "honest"]);

    let job = farm.submit(&[]);
    let image = farm.finish(job);
    assert!(
        liar.tiles_lied() >= 1,
        "the liar was given no tile, so nothing was tested (error: {:?})",
        liar.error()
    );
    assert!(!has_red_tile(&image), "a red tile is in the image");
    farm.assert_quarantined("liar", &["honest"]);
    // Every red result was rejected, none accepted.
    let returned = liar.tiles_returned();
    poll(
        "every red result to be rejected",
        Duration::from_secs(10),
        || (farm.metric("tessera_results_rejected_total") == returned as f64).then_some(()),
    );
    for w in farm.named("liar") {
        assert_eq!(w["tiles_done"], 0, "tiles of the liar accepted: {w}");
    }
    // The job whose tile caught it says so, though none of its tiles were taken back.
    let events = crate::support::events(farm.path(), &farm.addr, job);
    assert!(
        events
            .iter()
            .any(|(kind, detail)| kind == "quarantine"
                && detail.contains("machine liar quarantined")),
        "no quarantine of the liar in the job's events (tiles' left out): {:?}",
        events
            .iter()
            .filter(|(kind, _)| !kind.starts_with("tile_"))
            .collect::<Vec<_>>()
    );
    let listing = tessera_within(
        farm.path(),
        &["workers", "--coordinator", farm.addr.as_str()],
        Duration::from_secs(30),
    )
    .expect("tessera workers hung");
    assert!(
        listing
            .stdout
            .lines()
            .any(|l| l.contains("liar") && l.contains("QUARANTINED: ")),
        "tessera workers does not show the liar quarantined:\n{}",
        listing.stdout
    );

    // The liar comes back under the same name, honest this time, to a job waiting for
    // tiles: it stays connected, listed as quarantined, and gets none.
    drop(liar);
    drop(honest);
    poll("every worker to leave", LISTED_TIMEOUT, || {
        farm.workers().is_empty().then_some(())
    });
    let back = FakeWorker::start(&farm.addr, "liar", &build, Lie::Honest);
    farm.wait_listed(&["liar"]);
    let second = farm.submit(&[]);
    std::thread::sleep(Duration::from_secs(3));
    let status = try_status(farm.path(), &farm.addr, second).expect("status of the second job");
    assert_eq!(status["tiles_done"], 0, "tiles done by nobody: {status}");
    assert_eq!(
        back.tiles_assigned(),
        0,
        "the quarantined machine got a tile"
    );
    assert_eq!(back.canaries(), 1, "the returning liar rendered no canary");
    assert!(
        !back.closed(),
        "the returning liar was disconnected: {:?}",
        back.error()
    );
    let listed = farm.named("liar");
    assert_eq!(listed.len(), 1, "{listed:?}");
    assert!(
        listed[0]["quarantined"].is_string(),
        "the returning liar is not listed as quarantined: {}",
        listed[0]
    );

    let _again = farm.worker("honest-2");
    farm.finish(second);
    assert_eq!(
        back.tiles_assigned(),
        0,
        "the quarantined machine got a tile"
    );
    assert!(!back.closed(), "the returning liar was disconnected");
    assert!(farm.named("liar")[0]["quarantined"].is_string());
    assert_eq!(farm.metric("tessera_workers_quarantined_total"), 1.0);
}

/// Tiles a machine rendered before the coordinator was killed are taken back when it
/// is caught returning wrong pixels after the restart: the core learns who rendered
/// each tile it restores. The job is then `tessera render`'s image all the same.
#[test]
fn tiles_restored_after_a_restart_are_taken_back_when_their_machine_is_caught() {
    /// Tiles the machine renders (and the coordinator stores) before the restart.
    const BEFORE: u64 = 6;
    let _turn = shared();
    let dir = tempfile::tempdir().expect("temporary directory");
    let (mut coordinator, addr) = start_restartable_coordinator(dir.path());
    let reference = render_reference(
        dir.path(),
        &scene_path("seed.json"),
        "reference.png",
        &render_args(JOB),
    );
    let build = render::build_identity();
    let scene = scene_path("seed.json");
    let mut args = vec![scene.as_str()];
    args.extend(JOB);
    let stalls = FakeWorker::start(&addr, "m", &build, Lie::SilentAfter(BEFORE));
    let job = submit(dir.path(), &addr, &args);
    poll(
        "the machine's first tiles to be stored",
        JOB_TIMEOUT,
        || {
            let status = try_status(dir.path(), &addr, job)?;
            (status["tiles_done"].as_u64()? >= BEFORE).then_some(())
        },
    );
    coordinator.kill9();
    drop(stalls);

    let coordinator = restart_coordinator(dir.path(), &addr, &[]);
    let liar = FakeWorker::start(&addr, "m", &build, Lie::Red);
    poll("the machine to be quarantined", JOB_TIMEOUT, || {
        try_workers(dir.path(), &addr)?
            .iter()
            .any(|w| w["name"] == "m" && w["quarantined"].is_string())
            .then_some(())
    });
    assert!(
        liar.tiles_lied() >= 1,
        "caught without lying: {:?}",
        liar.error()
    );
    let _honest = start_worker(dir.path(), &addr, "honest");
    wait_done(dir.path(), &addr, job, JOB_TIMEOUT);
    let image = fetch(dir.path(), &addr, job, "job.png");
    assert_same_png(
        &image,
        &reference,
        "a job whose restored tiles were taken back",
    );
    let events = crate::support::events(dir.path(), &addr, job);
    let quarantine = events
        .iter()
        .find(|(kind, detail)| kind == "quarantine" && detail.contains("machine m quarantined"))
        .unwrap_or_else(|| panic!("no quarantine of m in the job's events: {events:?}"));
    assert!(
        quarantine
            .1
            .contains(&format!("{BEFORE} of its tiles taken back")),
        "the tiles m rendered before the restart are not all taken back: {}",
        quarantine.1
    );
    drop(coordinator);
}

#[test]
fn one_changed_byte_is_caught_by_full_verification_and_by_audits_of_every_tile() {
    let _turn = shared();
    for (coordinator, job) in [
        (&[][..], &["--verify", "full"][..]),
        (&["--audit-share", "1"][..], &["--verify", "sampled"][..]),
    ] {
        let what = format!("coordinator {coordinator:?}, job {job:?}");
        let farm = Farm::start(coordinator);
        let flipper = FakeWorker::start(
            &farm.addr,
            "flipper",
            &render::build_identity(),
            Lie::OneByteEvery(2),
        );
        let _w1 = farm.worker("w1");
        let _w2 = farm.worker("w2");
        farm.wait_listed(&["flipper", "w1", "w2"]);
        let id = farm.submit(job);
        farm.finish(id);
        assert!(
            flipper.tiles_lied() >= 1,
            "{what}: the flipper changed no tile, so nothing was tested (error: {:?})",
            flipper.error()
        );
        farm.assert_quarantined("flipper", &["w1", "w2"]);
    }
}

#[test]
fn a_worker_rendering_another_frame_is_caught_by_the_checks_of_the_jobs_frame() {
    let _turn = shared();
    let farm = Farm::start(&[]);
    let liar = FakeWorker::start(&farm.addr, "liar", &render::build_identity(), Lie::FrameOne);
    let _honest = farm.worker("honest");
    farm.wait_listed(&["liar", "honest"]);
    let orbit = orbit();
    let mut args = vec![orbit.as_str(), "--frame", "17"];
    args.extend(JOB);
    let job = submit(farm.path(), &farm.addr, &args);
    wait_done(farm.path(), &farm.addr, job, JOB_TIMEOUT);
    let image = fetch(farm.path(), &farm.addr, job, "orbit-17.png");
    let mut render = render_args(JOB);
    render.extend(["--frame", "17"]);
    let reference = render_reference(farm.path(), &orbit, "orbit-17-reference.png", &render);
    assert_same_png(&image, &reference, "frame 17");
    assert!(
        liar.tiles_lied() >= 1,
        "the liar was given no tile, so nothing was tested (error: {:?})",
        liar.error()
    );
    farm.assert_quarantined("liar", &["honest"]);
}

#[test]
fn liars_on_an_adaptive_job_are_caught_by_its_checks() {
    let _turn = shared();
    for lie in [Lie::Red, Lie::OneByteEvery(1)] {
        let farm = Farm::start_for(&["--spot-pixels", "1024"], ADAPTIVE_JOB);
        let liar = FakeWorker::start(&farm.addr, "liar", &render::build_identity(), lie);
        farm.wait_listed(&["liar"]);
        let _w1 = farm.worker("w1");
        farm.wait_listed(&["liar", "w1"]);
        let id = farm.submit(&[]);
        farm.finish(id);
        assert!(
            liar.tiles_lied() >= 1,
            "{lie:?}: the liar changed no answer, so nothing was tested (error: {:?})",
            liar.error()
        );
        farm.assert_quarantined("liar", &["w1"]);
    }
}

#[test]
fn a_relay_flipping_bytes_of_tile_results_gets_the_relayed_machine_quarantined() {
    let _turn = shared();
    let farm = Farm::start(&[]);
    let relay = FlipRelay::start(&farm.addr, 3);
    let _relayed = start_worker(farm.path(), relay.address(), "relayed");
    // Two direct machines: once the relayed one is quarantined, full verification
    // still has two machines to confirm each other.
    let _d1 = farm.worker("direct-1");
    let _d2 = farm.worker("direct-2");
    farm.wait_listed(&["relayed", "direct-1", "direct-2"]);
    let id = farm.submit(&["--verify", "full"]);
    farm.finish(id);
    assert!(
        relay.flipped() >= 1,
        "the relay flipped nothing ({} tile results relayed)",
        relay.tile_frames()
    );
    farm.assert_quarantined("relayed", &["direct-1", "direct-2"]);
}

/// A worker whose connection ends during its canary (it gave up waiting, as workers
/// reconnecting to a paused coordinator do) is a lost connection: counted apart, logged
/// as a warning, never as a refusal that operators alert on.
#[test]
fn a_connection_lost_during_the_canary_is_not_a_refusal() {
    let _turn = shared();
    let farm = Farm::start(&[]);
    let build = render::build_identity();
    for i in 0..3 {
        let gone = FakeWorker::start(
            &farm.addr,
            &format!("gone-{i}"),
            &build,
            Lie::HangsUpAtCanary,
        );
        assert!(
            gone.wait_closed(Duration::from_secs(20)),
            "the worker is still connected"
        );
        assert!(gone.refusal().is_none(), "{:?}", gone.refusal());
    }
    poll(
        "the lost canaries to be counted",
        Duration::from_secs(10),
        || (farm.metric("tessera_worker_canaries_interrupted_total") == 3.0).then_some(()),
    );
    assert_eq!(farm.metric("tessera_workers_refused_total"), 0.0);
    let log = farm.coordinator.log_text();
    assert!(
        !log.lines().any(|l| l.contains("refused")),
        "a lost connection logged as a refusal:\n{log}"
    );
    assert_eq!(
        log.lines()
            .filter(|l| l.contains("WARN") && l.contains("connection lost during the canary"))
            .count(),
        3,
        "{log}"
    );
    // The farm still renders right.
    let id = farm.submit(&[]);
    let _w1 = farm.worker("w1");
    farm.finish(id);
}

#[test]
fn a_worker_whose_renderer_differs_is_refused_at_the_canary() {
    let _turn = shared();
    let farm = Farm::start(&[]);
    // A job waits for tiles to be taken before the odd worker comes.
    let id = farm.submit(&[]);
    let build = "tessera 0.0.0 (perturbed renderer)";
    let odd = FakeWorker::start(&farm.addr, "odd", build, Lie::Perturbed);
    assert!(
        odd.wait_closed(Duration::from_secs(20)),
        "the odd worker is still connected"
    );
    assert!(odd.connected(), "the handshake failed: {:?}", odd.error());
    assert_eq!(odd.canaries(), 1, "canaries rendered");
    let reason = odd
        .refusal()
        .unwrap_or_else(|| panic!("no Refuse (the connection ended with {:?})", odd.error()));
    let ours = render::build_identity();
    assert!(
        reason.contains(build) && reason.contains(&ours),
        "the refusal names neither the worker's build {build:?} nor the coordinator's \
         {ours:?}: {reason:?}"
    );
    assert_eq!(odd.tiles_assigned(), 0, "the refused worker got a tile");
    assert!(farm.named("odd").is_empty(), "the refused worker is listed");
    assert_eq!(farm.metric("tessera_workers_refused_total"), 1.0);
    let log = farm.coordinator.log_text();
    assert!(
        log.lines()
            .any(|l| l.contains("ERROR") && l.contains("refused") && l.contains("odd")),
        "no error line naming the refused worker in the coordinator's log:\n{log}"
    );

    let _w1 = farm.worker("w1");
    farm.finish(id);
    assert_eq!(odd.tiles_assigned(), 0);
    assert_eq!(farm.metric("tessera_workers_refused_total"), 1.0);
    assert_eq!(farm.metric("tessera_workers_quarantined_total"), 0.0);
}
