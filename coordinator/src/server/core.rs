//! The state behind the daemon's one lock: the two state machines, the data their
//! decisions are about (scenes, frames being assembled, workers' outboxes), and how
//! their actions are carried out.
//!
//! Everything here runs under the lock, so nothing here blocks: messages go to
//! per-worker channels, writes to the persistence queue, and encoding an image to the
//! blocking pool.

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use protocol::{
    ClientResponse, JobEvent, JobId, JobState, JobStatus, Refusal, SceneHash, Settings, TileRect,
    ToWorker, Verification, WorkerId, WorkerStatus,
};
use render::Tracer;
use scheduler::lifecycle::{self, Lifecycle, Phase, Reply};
use scheduler::{Action, Event, Millis, Scheduler};
use tokio::sync::{mpsc, oneshot};
use tracing::{error, info, warn};

use super::adaptive::{self, AdaptiveJob, AdaptivePlan, Answer, Evaluation, PassSnapshot};
use super::persistence::Write;
use super::verification::Verifier;
use super::{unix_ms, Shared};
use crate::db::{EventWrite, Label, StoredJob, Times, Totals};
use crate::store::JobMetadata;
use crate::tiling;

mod figures;
mod names;
mod sequences;

pub(super) use sequences::frame_jobs;
pub use sequences::SequenceRecord;

/// The state machines and their data.
pub struct Core {
    pub tiles: Scheduler,
    pub lifecycle: Lifecycle,
    pub jobs: BTreeMap<JobId, JobRecord>,
    /// Sequence jobs, whose frames are jobs of `jobs`.
    pub sequences: BTreeMap<JobId, SequenceRecord>,
    pub workers: BTreeMap<WorkerId, WorkerRecord>,
    next_worker: WorkerId,
    /// Clients waiting for their submission to be stored.
    submits: HashMap<JobId, oneshot::Sender<ClientResponse>>,
    /// Results held until another machine confirms them, by job and tile.
    held: HashMap<(JobId, u32), Held>,
    /// Machines caught returning wrong pixels, with why: they get no tile again.
    pub quarantined: BTreeMap<String, String>,
    /// The scheduler's count of expired leases when last looked at, and the expired
    /// leases already in the jobs' event logs.
    leases_expired_seen: u64,
    expiries_logged: HashSet<(JobId, u32, WorkerId)>,
}

/// A result waiting for another machine's identical one.
pub struct Held {
    worker: WorkerId,
    machine: String,
    pixels: TilePixels,
    cost: Cost,
    /// An adaptive answer's state.
    answer: Option<Answer>,
}

impl Held {
    /// Whether another result is the same: its pixels, and an adaptive answer's state.
    fn same(&self, rgb: &[u8], answer: Option<&Answer>) -> bool {
        self.pixels.rgb == rgb && self.answer.as_ref().map(|a| a.sha) == answer.map(|a| a.sha)
    }
}

thread_local! {
    /// Each thread's decompression context, made once: a new one per tile cost more
    /// than decompressing a small tile.
    static DECOMPRESSOR: std::cell::RefCell<Option<zstd::bulk::Decompressor<'static>>> =
        const { std::cell::RefCell::new(None) };
}

/// A result's pixels: decoded, and as the database stores them (one zstd frame that
/// decompresses to exactly `rgb`), both made off the lock.
pub struct TilePixels {
    pub rgb: Vec<u8>,
    pub zstd: Vec<u8>,
}

impl TilePixels {
    /// Pixels that came compressed, `zstd` checked to decompress to `rgb`: stored as
    /// they came, unless the frame is larger than any compressor makes it (padded, so
    /// as to cost the database more), then compressed again.
    pub fn received(rgb: Vec<u8>, zstd: Vec<u8>) -> TilePixels {
        if zstd.len() > zstd::zstd_safe::compress_bound(rgb.len()) {
            return TilePixels::raw(rgb);
        }
        TilePixels { rgb, zstd }
    }

    /// Pixels that came raw: compressed for the database.
    pub fn raw(rgb: Vec<u8>) -> TilePixels {
        let zstd = zstd::bulk::compress(&rgb, 1)
            .expect("compressing into a buffer of the compression bound cannot fail");
        TilePixels { rgb, zstd }
    }

    /// No pixels: a result that counts for nothing.
    pub fn none() -> TilePixels {
        TilePixels {
            rgb: Vec::new(),
            zstd: Vec::new(),
        }
    }
}

/// One zstd frame of at most `capacity` bytes, with this thread's context.
fn decompress(bytes: &[u8], capacity: usize) -> std::io::Result<Vec<u8>> {
    DECOMPRESSOR.with(|d| {
        let mut d = d.borrow_mut();
        if d.is_none() {
            *d = Some(zstd::bulk::Decompressor::new()?);
        }
        d.as_mut().expect("made above").decompress(bytes, capacity)
    })
}

/// What the daemon keeps of a job beside its lifecycle.
pub struct JobRecord {
    /// A pass of a studio view: nothing of it is stored or listed, its tiles go to
    /// the view's page, and it is forgotten once it ends (docs/studio.md).
    pub interactive: bool,
    /// The studio view and pass it renders for, known before any tile goes out.
    pub owner: Option<crate::studio::views::Owner>,
    /// The scene text, while the job is active (workers may still ask for it).
    pub scene: Option<Arc<str>>,
    pub hash: SceneHash,
    /// The frame of the scene it renders, from 1: sent with every tile, and the frame
    /// its results are checked against.
    pub frame: u32,
    /// For a frame job: the sequence it renders a frame of (it is not listed; its
    /// image goes to the sequence's folder).
    pub sequence: Option<JobId>,
    pub settings: Settings,
    pub tile_size: u32,
    /// The tiles' rectangles, while the job is active.
    pub tiles: Vec<TileRect>,
    pub tiles_total: u32,
    pub priority: i32,
    /// The frame being assembled, while the job is active: the memory a coordinator
    /// holds grows with the active jobs' pixels (3 bytes each), never with the
    /// finished ones.
    pub image: Option<render::Image>,
    /// Wall-clock times, kept across restarts.
    pub times: Times,
    /// Rendering time spent before the last restart (from its first tile handed out
    /// to its last tile recorded), and when rendering resumed in this run: the
    /// coordinator's own downtime is not rendering time.
    pub rendered_before_ms: u64,
    pub running_since: Option<u64>,
    /// When its tiles of this run were done, lately: what its time left is told from.
    pub pace: figures::Pace,
    /// Tiles written to the database: the progress reported.
    pub tiles_recorded: u32,
    pub totals: Totals,
    pub tiles_per_worker: BTreeMap<String, u64>,
    /// The SHA-256 of the stored image, once stored.
    pub image_sha256: Option<[u8; 32]>,
    /// How its results are checked.
    pub verification: Verification,
    /// Who rendered each accepted tile and what it added to the totals, while the job
    /// is active: what a quarantine takes back.
    pub accepted: HashMap<u32, Accepted>,
    /// An adaptive job's passes and its tiles' states, while it is active.
    pub adaptive: Option<AdaptiveJob>,
    /// Milliseconds of rendering after which an adaptive job stops, if limited.
    pub time_limit_ms: Option<u64>,
    /// The job ended on its time limit before its image met the target.
    pub stopped_on_time_limit: bool,
    /// An operator paused it: none of its tiles is handed out.
    pub paused: bool,
    /// Its name, its submitter as claimed and the address it came from.
    pub label: Label,
    /// Where its event log stands.
    pub log: EventLog,
}

/// The most entries a job's event log keeps before its end: a job of many tiles, or
/// of workers that keep failing, must not fill the disk with its history. Past it,
/// one entry says how many were not kept, and the job's end is still recorded.
pub const EVENT_LOG_CAP: u64 = 10_000;

/// Where a job's event log stands: the entries are on disk (written through the
/// persistence queue, never waited for), only the numbering is kept here.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EventLog {
    /// The number the next entry gets.
    pub next_seq: u64,
    /// Entries past [`EVENT_LOG_CAP`] not kept.
    pub dropped: u64,
}

impl EventLog {
    /// A new job's log: empty.
    pub fn new() -> EventLog {
        EventLog {
            next_seq: 1,
            dropped: 0,
        }
    }

    /// The log of a job found on disk whose highest entry is numbered `last` (0:
    /// none), whose marker counts `dropped` entries not kept. Those took the numbers
    /// after the cap.
    pub fn restored(last: u64, dropped: u64) -> EventLog {
        let numbered = if dropped > 0 {
            last.max(EVENT_LOG_CAP + dropped)
        } else {
            last
        };
        EventLog {
            next_seq: numbered + 1,
            dropped,
        }
    }

    /// Numbers an entry: `Some(seq)` to store it under, or `None` when it is past the
    /// cap (and the count of entries not kept, under the number [`EVENT_LOG_CAP`] + 1,
    /// is to be written again: one small row rewritten, in the batch the entry would
    /// have been written in, so that the count is exact after any restart). The end
    /// of a job is always kept.
    fn number(&mut self, always: bool) -> Option<u64> {
        let seq = self.next_seq;
        self.next_seq += 1;
        if seq <= EVENT_LOG_CAP || always {
            return Some(seq);
        }
        self.dropped += 1;
        None
    }
}

/// What an operator set of an active job, to be stored before the change is
/// acknowledged.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Controls {
    pub job: JobId,
    pub paused: bool,
    pub priority: i32,
}

/// An accepted tile's machine and cost.
pub struct Accepted {
    machine: Arc<str>,
    rays: u64,
    samples: u64,
    error_sq_sum: Option<f64>,
}

/// How the core closes a worker's connection: its session wakes up and ends, with the
/// reason.
#[derive(Default)]
pub struct Dropped {
    wake: tokio::sync::Notify,
    why: std::sync::Mutex<String>,
}

impl Dropped {
    fn drop_with(&self, why: &str) {
        *self.why.lock().unwrap_or_else(|e| e.into_inner()) = why.to_owned();
        self.wake.notify_one();
    }

    /// Once the worker is dropped: why.
    pub async fn wait(&self) -> String {
        self.wake.notified().await;
        self.why.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

/// A connected worker.
pub struct WorkerRecord {
    /// Unique among the connected workers ([`names`]): the name its hello gave, or
    /// that name with a suffix when a worker of another host holds it.
    pub name: String,
    /// The address it connected from: a worker joining under a connected worker's
    /// name from the same host supersedes it.
    pub host: std::net::IpAddr,
    /// The renderer build its hello named.
    pub build: String,
    pub threads: u32,
    pub outbox: mpsc::UnboundedSender<ToWorker>,
    /// Set when the core drops the worker: its connection is closed.
    pub dropped: Arc<Dropped>,
    pub connected: Instant,
    pub tiles_done: u64,
    pub rays: u64,
    /// When each tile it holds was handed to it, for the latency metric.
    pub assigned: HashMap<(JobId, u32), Instant>,
    /// Why it gets no tile, once its machine is quarantined.
    pub quarantined: Option<String>,
    /// It is finishing what it holds before it exits: it said so, or an operator
    /// told it to.
    pub draining: bool,
    /// The last round trips measured, in microseconds.
    rtts: VecDeque<u64>,
    /// Its results of the last [`RATE_WINDOW`]: when each arrived, how long its tile
    /// took to render (µs) and its rays. Its rate is theirs while it rendered, not a
    /// lifetime average, nor one that idle time dilutes.
    recent: VecDeque<(Instant, u64, u64)>,
    /// Its mean time per tile on one thread, in microseconds (moving average).
    tile_us: Option<f64>,
    /// The pace last given to the scheduler: (rtt, tile time) in ms.
    pace: Option<(Millis, Millis)>,
    /// The worker secret it proved, if workers prove one: listings say which.
    pub key: Option<super::keys::KeyHold>,
}

/// A worker's rays per second are those of its results of this last while, over the
/// time it spent rendering them.
const RATE_WINDOW: Duration = Duration::from_secs(60);

/// Round trips kept per worker: the smallest of them is its round-trip time (the
/// others waited behind results in the socket buffers).
const RTTS_KEPT: usize = 8;

impl WorkerRecord {
    pub fn new(
        name: String,
        host: std::net::IpAddr,
        build: String,
        threads: u32,
        outbox: mpsc::UnboundedSender<ToWorker>,
        dropped: Arc<Dropped>,
    ) -> WorkerRecord {
        WorkerRecord {
            name,
            host,
            build,
            threads,
            outbox,
            dropped,
            connected: Instant::now(),
            tiles_done: 0,
            rays: 0,
            assigned: HashMap::new(),
            quarantined: None,
            draining: false,
            rtts: VecDeque::new(),
            recent: VecDeque::new(),
            tile_us: None,
            pace: None,
            key: None,
        }
    }

    fn rtt_us(&self) -> Option<u64> {
        self.rtts.iter().copied().min()
    }

    /// The pace to tell the scheduler, if it changed enough to matter (a fifth).
    fn new_pace(&mut self) -> Option<(Millis, Millis)> {
        let rtt = self.rtt_us()?.div_ceil(1000);
        let tile = (self.tile_us? / 1000.0).ceil().max(1.0) as Millis;
        let changed = self.pace.is_none_or(|(r, t)| {
            let off = |a: Millis, b: Millis| a.abs_diff(b) * 5 > b.max(1);
            off(rtt, r) || off(tile, t)
        });
        changed.then(|| {
            self.pace = Some((rtt, tile));
            (rtt, tile)
        })
    }
}

/// What a worker reports a tile cost.
#[derive(Clone, Copy)]
pub struct Cost {
    pub rays: u64,
    pub samples: u64,
    pub error_sq_sum: f64,
    /// Its rendering time on one thread.
    pub render_us: u64,
}

/// What a result is checked against, gathered under the lock.
pub struct CheckPlan {
    hash: SceneHash,
    frame: u32,
    settings: Settings,
    scene: Arc<str>,
    rect: TileRect,
    /// For an adaptive job's answer: its pass, rung and previous state.
    adaptive: Option<AdaptivePlan>,
}

impl CheckPlan {
    /// The pixels of a compressed result: exactly the tile's bytes, or why not. The
    /// output is bounded by the tile's size, so a small frame cannot expand into a
    /// large allocation.
    pub fn decompress(&self, zstd: &[u8]) -> Result<Vec<u8>, String> {
        let expected = self.rect.width as usize * self.rect.height as usize * 3;
        match decompress(zstd, expected) {
            Ok(rgb) if rgb.len() == expected => Ok(rgb),
            Ok(rgb) => Err(format!(
                "its compressed pixels hold {} bytes, not the tile's {expected}",
                rgb.len()
            )),
            Err(e) => Err(format!("its compressed pixels do not decompress: {e}")),
        }
    }

    /// Spot-checks the result (off the lock: it renders). An adaptive answer's state
    /// comes in `state`.
    pub fn run(self, verifier: &Verifier, rgb: &[u8], state: Option<Vec<u8>>) -> Verdict {
        match verifier.tracer(self.hash, self.frame, self.settings, &self.scene) {
            Ok(tracer) => match (&self.adaptive, state) {
                (Some(plan), Some(state)) => {
                    let checked = adaptive::check_answer(
                        verifier,
                        &tracer,
                        &self.settings,
                        self.rect,
                        plan,
                        rgb,
                        state,
                    );
                    let (spot, answer) = match checked {
                        Ok(answer) => (Ok(()), Some(answer)),
                        Err(e) => (Err(e), None),
                    };
                    Verdict {
                        spot,
                        tracer: Some(tracer),
                        answer,
                        plan: self.adaptive,
                    }
                }
                _ => Verdict {
                    spot: verifier
                        .spot_check(&tracer, self.rect, rgb)
                        .map_err(|wrong| wrong.to_string()),
                    tracer: Some(tracer),
                    answer: None,
                    plan: None,
                },
            },
            // The scene was accepted at submission: it parses. Without a tracer the
            // result cannot be checked; it is held to a second machine instead.
            Err(e) => {
                error!(error = %e, "cannot prepare a spot check");
                Verdict::unchecked()
            }
        }
    }
}

/// What the spot check found (why the result is wrong, if it is), and the tracer to
/// settle a disagreement with.
pub struct Verdict {
    spot: Result<(), String>,
    tracer: Option<Arc<Tracer>>,
    /// An adaptive answer that passed its checks, and what it was checked against.
    answer: Option<Answer>,
    plan: Option<AdaptivePlan>,
}

impl Verdict {
    /// A result found wrong before any pixel was looked at (it does not decompress).
    pub fn wrong(reason: String) -> Verdict {
        Verdict {
            spot: Err(reason),
            tracer: None,
            answer: None,
            plan: None,
        }
    }

    /// The samples of an adaptive answer's pixels (0 for other results).
    pub fn samples(&self) -> u64 {
        self.answer.as_ref().map_or(0, |a| a.samples)
    }

    /// No check was possible (a result for a job no longer active).
    pub fn unchecked() -> Verdict {
        Verdict {
            spot: Ok(()),
            tracer: None,
            answer: None,
            plan: None,
        }
    }
}

/// A job admitted by the lifecycle, to be stored.
pub struct Prepared {
    /// A pass of a studio view ([`JobRecord::interactive`]).
    pub interactive: bool,
    /// The studio view and pass it renders for, known before any tile goes out.
    pub owner: Option<crate::studio::views::Owner>,
    pub scene: String,
    pub hash: SceneHash,
    /// The frame of the scene, from 1 (checked: the scene has it).
    pub frame: u32,
    pub settings: Settings,
    pub tile_size: u32,
    pub tiles: Vec<TileRect>,
    pub priority: i32,
    pub verification: Verification,
    pub request: lifecycle::Request,
    pub time_limit_ms: Option<u64>,
    /// For a refinement: the finished job's tile states the tiles start from.
    pub start: Option<crate::store::TileStates>,
    /// Its name, its submitter as claimed and the address it came from.
    pub label: Label,
    /// For a frame job: its sequence.
    pub sequence: Option<JobId>,
    /// For a sequence job: its frames (`frame` must be 1).
    pub frames: Option<protocol::FrameRange>,
    /// The scene's frame count.
    pub frame_count: u32,
}

impl Core {
    pub fn new(tiles: Scheduler, lifecycle: Lifecycle) -> Core {
        Core {
            tiles,
            lifecycle,
            jobs: BTreeMap::new(),
            workers: BTreeMap::new(),
            next_worker: 1,
            submits: HashMap::new(),
            held: HashMap::new(),
            quarantined: BTreeMap::new(),
            leases_expired_seen: 0,
            expiries_logged: HashSet::new(),
            sequences: BTreeMap::new(),
        }
    }

    /// The earliest deadline of either state machine.
    pub fn next_deadline(&self, now: Millis) -> Option<Millis> {
        // Frames refused admission are tried again every second; a sequence is deleted
        // when its retention runs out.
        let waiting = self.sequences_waiting().then_some(now + 1_000);
        let expiry = self.next_sequence_expiry().map(|ms| now + ms);
        [
            self.tiles.next_deadline(),
            self.lifecycle.next_deadline(),
            waiting,
            expiry,
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// The time has come: both state machines look at their deadlines.
    pub fn timeout(&mut self, sh: &Arc<Shared>) {
        for job in sh.studio.tick(sh.now()) {
            self.life_event(sh, lifecycle::Event::Cancel { job });
        }
        self.tiles_event(sh, Event::Timeout);
        self.log_expired_leases(sh);
        self.life_event(sh, lifecycle::Event::Timeout);
        self.fill_all(sh);
        self.expire_sequences(sh);
    }

    /// Logs, once each, the tiles whose worker ran past its lease: the scheduler has put
    /// them back for another worker (what the first one returns may still count). Looked
    /// for only when the scheduler's count of expired leases moved.
    fn log_expired_leases(&mut self, sh: &Shared) {
        let count = self.tiles.counters().leases_expired;
        if count == self.leases_expired_seen && self.expiries_logged.is_empty() {
            return;
        }
        self.leases_expired_seen = count;
        let now: HashSet<(JobId, u32, WorkerId)> = self
            .tiles
            .expired_leases()
            .into_iter()
            .map(|(job, tile, worker, out_for)| {
                if !self.expiries_logged.contains(&(job, tile, worker)) {
                    let name = self
                        .workers
                        .get(&worker)
                        .map_or_else(|| format!("worker {worker}"), |w| w.name.clone());
                    self.log(
                        sh,
                        job,
                        "tile_lease_expired",
                        format!(
                            "tile {tile} on {name} for {:.1} s, past its lease: put back for \
                             another worker (a late result still counts)",
                            out_for as f64 / 1000.0
                        ),
                    );
                }
                (job, tile, worker)
            })
            .collect();
        self.expiries_logged = now;
    }

    /// Whether tiles are out or images are being stored (a shutdown waits for them).
    pub fn is_busy(&self) -> bool {
        self.tiles.tiles_in_flight() > 0
            || self
                .lifecycle
                .jobs()
                .any(|(_, j)| matches!(j.phase, Phase::Finishing { .. }))
    }

    /// Every worker finishes what it holds and gets nothing more.
    pub fn drain_all(&mut self, sh: &Arc<Shared>) {
        let workers: Vec<WorkerId> = self.workers.keys().copied().collect();
        for worker in workers {
            self.tiles_event(sh, Event::WorkerDraining { worker });
        }
    }

    /// Hands a write about `job` to the disk, or, for a job nothing is kept of (a
    /// studio view's pass), discards it on the blocking pool, where its callback runs
    /// as if it had been stored: never under the lock the caller holds.
    pub fn store(&self, sh: &Shared, job: JobId, write: Write) {
        if self.jobs.get(&job).is_some_and(|r| r.interactive) {
            drop(sh.runtime.spawn_blocking(move || write.discard()));
        } else {
            sh.persistence.write(write);
        }
    }

    /// Adds an entry to the job's event log (queued for the disk, never waited for).
    /// `kind` is one of the words docs/operations.md lists. A studio view's pass keeps
    /// no log.
    pub fn log(&mut self, sh: &Shared, job: JobId, kind: &str, detail: String) {
        let log = match (self.jobs.get_mut(&job), self.sequences.get_mut(&job)) {
            (Some(record), _) if !record.interactive => &mut record.log,
            (None, Some(sequence)) => &mut sequence.log,
            _ => return,
        };
        let end = matches!(kind, "done" | "failed" | "cancelled");
        let unix_ms = unix_ms();
        let (seq, kind, detail) = match log.number(end) {
            Some(seq) => (seq, kind.to_owned(), detail),
            None => (
                EVENT_LOG_CAP + 1,
                "not_kept".to_owned(),
                format!("{} further events not kept", log.dropped),
            ),
        };
        sh.persistence.write(Write::Event(EventWrite {
            job,
            event: JobEvent {
                seq,
                unix_ms,
                kind,
                detail,
            },
        }));
    }

    /// A worker is gone (it left, or missed its heartbeats: then `drop` closes its
    /// connection): the tiles it held go back to the queue, each noted in its job's
    /// log.
    pub fn worker_lost(&mut self, sh: &Shared, worker: WorkerId, why: &str, drop: bool) {
        let Some(w) = self.workers.remove(&worker) else {
            return;
        };
        let mut held: Vec<(JobId, u32)> = w.assigned.keys().copied().collect();
        held.sort_unstable();
        for (job, tile) in held {
            self.log(
                sh,
                job,
                "tile_taken_back",
                format!("tile {tile} from {}: {why}", w.name),
            );
        }
        if drop {
            w.dropped.drop_with(why);
        }
    }

    pub fn tiles_event(&mut self, sh: &Arc<Shared>, event: Event) {
        let actions = self.tiles.handle(sh.now(), event);
        self.apply_tiles(sh, actions);
    }

    /// Feeds the lifecycle and carries out its actions; returns its reply to the
    /// client that caused the event, for the events that ask for one (cancel, delete,
    /// retry), and `None` for a job it does not know.
    pub fn life_event(
        &mut self,
        sh: &Arc<Shared>,
        event: lifecycle::Event,
    ) -> Option<Result<Reply, Refusal>> {
        let actions = self.lifecycle.handle(sh.now(), event);
        self.apply_life(sh, actions)
    }

    /// Enters an admitted job, waiting for its row to be written; `reply` gets the
    /// answer for the client.
    pub fn admit(
        &mut self,
        sh: &Arc<Shared>,
        prepared: Prepared,
        reply: oneshot::Sender<ClientResponse>,
    ) -> Result<StoredJob, Refusal> {
        let id = self.lifecycle.admit(sh.now(), &prepared.request)?;
        let submitted = unix_ms();
        let stored = StoredJob {
            id,
            scene: prepared.scene.clone(),
            hash: prepared.hash,
            frame: prepared.frame,
            last_frame: None,
            sequence: prepared.sequence,
            settings: prepared.settings,
            tile_size: prepared.tile_size,
            priority: prepared.priority,
            state: JobState::Queued,
            error: None,
            totals: None,
            times: Times {
                submitted: Some(submitted),
                ..Times::default()
            },
            image_sha256: None,
            verification: prepared.verification,
            time_limit_ms: prepared.time_limit_ms,
            stopped_on_time_limit: false,
            paused: false,
            label: prepared.label.clone(),
        };
        self.jobs.insert(
            id,
            JobRecord {
                interactive: prepared.interactive,
                owner: prepared.owner,
                adaptive: is_adaptive(&prepared.settings).then(|| {
                    AdaptiveJob::new(
                        &prepared.settings,
                        prepared.tiles.len(),
                        prepared.time_limit_ms,
                        prepared.start,
                    )
                }),
                time_limit_ms: prepared.time_limit_ms,
                stopped_on_time_limit: false,
                paused: false,
                label: prepared.label,
                log: EventLog::new(),
                verification: prepared.verification,
                accepted: HashMap::new(),
                scene: Some(Arc::from(prepared.scene)),
                hash: prepared.hash,
                frame: prepared.frame,
                sequence: prepared.sequence,
                settings: prepared.settings,
                tile_size: prepared.tile_size,
                tiles_total: prepared.tiles.len() as u32,
                tiles: prepared.tiles,
                priority: prepared.priority,
                image: None,
                times: stored.times,
                rendered_before_ms: 0,
                running_since: None,
                pace: figures::Pace::default(),
                tiles_recorded: 0,
                totals: Totals::default(),
                tiles_per_worker: BTreeMap::new(),
                image_sha256: None,
            },
        );
        self.submits.insert(id, reply);
        Ok(stored)
    }

    /// The write that stores an admitted job's row, and then has the lifecycle hear
    /// whether it was stored.
    pub fn insert_write(&self, sh: &Arc<Shared>, stored: StoredJob) -> Write {
        let id = stored.id;
        let shared = Arc::clone(sh);
        let label = stored.label.clone();
        Write::InsertJob {
            job: Box::new(stored),
            then: Box::new(move |result| {
                let event = match result {
                    Ok(()) => {
                        shared.lock().log(
                            &shared,
                            id,
                            "submitted",
                            format!(
                                "{:?} by {} from {}",
                                label.name, label.submitter, label.submitted_from
                            ),
                        );
                        lifecycle::Event::Stored { job: id }
                    }
                    Err(message) => lifecycle::Event::StoreFailed { job: id, message },
                };
                shared.lock().life_event(&shared, event);
            }),
        }
    }

    /// Takes back a job found on disk at startup.
    pub fn restore(&mut self, sh: &Arc<Shared>, restored: super::startup::RestoredJob) {
        self.take_back(sh, restored, false);
    }

    /// A failed or cancelled job is back in the queue on disk, read back with its
    /// stored tiles: the lifecycle takes it back (or refuses, if it changed since it
    /// was checked), and only its missing tiles are rendered. Returns its status.
    pub fn retried(
        &mut self,
        sh: &Arc<Shared>,
        mut restored: super::startup::RestoredJob,
        peer: std::net::IpAddr,
    ) -> Result<JobStatus, Refusal> {
        let id = restored.job.id;
        if restored.job.state.is_final() {
            // Found unusable when read back (its scene or settings): recorded failed.
            return Err(Refusal::state(format!(
                "job {id} cannot be retried: {}",
                restored
                    .job
                    .error
                    .as_deref()
                    .unwrap_or("it cannot be rendered")
            )));
        }
        let kept = restored.tiles.len();
        let started = kept > 0 || restored.job.times.started.is_some();
        let pixels =
            u64::from(restored.job.settings.width) * u64::from(restored.job.settings.height);
        let reply = self.life_event(
            sh,
            lifecycle::Event::Retry {
                job: id,
                started,
                pixels,
            },
        );
        if let Some(Err(message)) = reply {
            return Err(message);
        }
        restored.last_event = self.jobs.get(&id).map_or((0, 0), |r| {
            (r.log.next_seq.saturating_sub(1), r.log.dropped)
        });
        self.take_back(sh, restored, true);
        let total = self.jobs.get(&id).map_or(0, |r| r.tiles_total);
        info!(job = id, kept, total, "job retried by an operator");
        self.log(
            sh,
            id,
            "retried",
            format!("from {peer}: {kept} of {total} tiles kept, the others are rendered"),
        );
        sh.changed();
        self.status(id).ok_or_else(|| unknown(id))
    }

    /// Takes back a stored job: its record, its frame from the stored tiles, and its
    /// remaining tiles to the scheduler; the lifecycle learns of it unless it already
    /// has (`retried`).
    fn take_back(
        &mut self,
        sh: &Arc<Shared>,
        restored: super::startup::RestoredJob,
        retried: bool,
    ) {
        let stored = restored.job;
        let id = stored.id;
        // An adaptive job of an earlier version may have tiles off the blocks: it starts
        // its passes again anyway, on tiles it can use.
        let mut stored = stored;
        if is_adaptive(&stored.settings)
            && verify::adaptive::check_tile_side(stored.tile_size).is_err()
        {
            stored.tile_size = tiling::default_tile_size(&stored.settings);
        }
        let tiles = tiling::cut(&stored.settings, stored.tile_size);
        let final_state = stored.state.is_final();
        let adaptive = (!final_state && is_adaptive(&stored.settings))
            .then(|| AdaptiveJob::new(&stored.settings, tiles.len(), stored.time_limit_ms, None));
        let mut record = JobRecord {
            interactive: false,
            owner: None,
            adaptive,
            time_limit_ms: stored.time_limit_ms,
            stopped_on_time_limit: stored.stopped_on_time_limit,
            paused: stored.paused && !final_state,
            label: restored_label(id, &stored.label),
            log: EventLog::restored(restored.last_event.0, restored.last_event.1),
            verification: stored.verification,
            accepted: HashMap::new(),
            scene: (!final_state).then(|| Arc::from(stored.scene.as_str())),
            hash: stored.hash,
            frame: stored.frame,
            sequence: stored.sequence,
            settings: stored.settings,
            tile_size: stored.tile_size,
            tiles_total: tiles.len() as u32,
            tiles: if final_state { Vec::new() } else { tiles },
            priority: stored.priority,
            image: None,
            times: Times {
                submitted: stored.times.submitted.or(Some(unix_ms())),
                ..stored.times
            },
            rendered_before_ms: 0,
            running_since: None,
            pace: figures::Pace::default(),
            tiles_recorded: 0,
            totals: stored.totals.unwrap_or_default(),
            tiles_per_worker: BTreeMap::new(),
            image_sha256: stored.image_sha256,
        };
        // A retry starts a new run: its first tile out is the run's start (stored anew
        // when it goes out). What was rendered before still counts in its rate below.
        if record
            .times
            .started
            .zip(record.times.retried)
            .is_some_and(|(started, retried)| started < retried)
        {
            record.times.started = None;
        }
        if let Some(sequence) = stored.sequence {
            self.lifecycle.keep(id);
            if let Some(s) = self.sequences.get_mut(&sequence) {
                s.frames.restore(stored.frame, id, stored.state);
                // The sequence's controls are its frames'.
                record.paused = s.frames.paused() && !final_state;
                record.priority = s.priority;
            }
        }
        if final_state {
            // Its progress as it ended: all of it, or (cancelled, failed) the tiles it
            // has stored, which a retry keeps.
            record.tiles_recorded = if stored.state == JobState::Done {
                record.tiles_total
            } else {
                restored.stored_tiles.min(record.tiles_total)
            };
            self.jobs.insert(id, record);
            self.life_event(
                sh,
                lifecycle::Event::Restored {
                    job: id,
                    state: stored.state,
                    error: stored.error,
                    started: true,
                    pixels: 0,
                    ended_ago: stored
                        .times
                        .ended
                        .map_or(0, |ended| unix_ms().saturating_sub(ended)),
                },
            );
            return;
        }
        let mut image = render::Image::black(stored.settings.width, stored.settings.height);
        let mut done = Vec::new();
        let last_done = restored.tiles.iter().filter_map(|t| t.done_ms).max();
        if let (Some(started), Some(last)) = (stored.times.started, last_done) {
            record.rendered_before_ms = last.saturating_sub(started);
        }
        // An adaptive job starts its passes again: its tiles' states are not stored.
        let tiles = if record.adaptive.is_some() {
            Vec::new()
        } else {
            restored.tiles
        };
        for t in tiles {
            let rect = record.tiles[t.tile as usize];
            image.put_rect(to_render_rect(rect), &t.rgb);
            record.tiles_recorded += 1;
            // A tile recorded by an earlier version was a grid render: aa² per pixel.
            let pixels = rect_pixels(rect);
            let aa = u64::from(stored.settings.aa);
            let samples = t.samples.unwrap_or(pixels * aa * aa);
            record.add_cost(t.rays, samples, t.error_sq_sum, pixels);
            record.accepted.insert(
                t.tile,
                Accepted {
                    machine: Arc::from(t.worker.as_str()),
                    rays: t.rays,
                    samples,
                    error_sq_sum: t.error_sq_sum,
                },
            );
            *record.tiles_per_worker.entry(t.worker).or_default() += 1;
            done.push(t.tile);
        }
        record.image = Some(image);
        let total = record.tiles_total;
        let (priority, hash) = (record.priority, record.hash);
        if record.paused {
            info!(
                job = id,
                "job paused by an operator: none of its tiles goes out"
            );
            self.tiles_event(sh, Event::PauseJob { job: id });
        }
        info!(job = id, done = done.len(), total, "resuming job");
        self.jobs.insert(id, record);
        if !retried {
            self.life_event(
                sh,
                lifecycle::Event::Restored {
                    job: id,
                    state: stored.state,
                    error: None,
                    started: !done.is_empty() || stored.times.started.is_some(),
                    pixels: u64::from(stored.settings.width) * u64::from(stored.settings.height),
                    ended_ago: 0,
                },
            );
        }
        let actions = self
            .tiles
            .resume_job(sh.now(), id, priority, hash, total, &done);
        self.apply_tiles(sh, actions);
    }

    /// A worker connected: its id and the name it joins under ([`names::place`]).
    /// A connection it supersedes is told why and closed, and its tiles go back to the
    /// queue at once, as a lost worker's do.
    pub fn join(&mut self, sh: &Arc<Shared>, mut record: WorkerRecord) -> (WorkerId, String) {
        let id = self.next_worker;
        self.next_worker += 1;
        let host = record.host;
        let connected = self.workers.iter().map(|(&id, w)| names::Holder {
            id,
            name: &w.name,
            host: w.host,
        });
        let naming = names::place(connected, &record.name, host);
        match &naming {
            names::Naming::Free => {}
            names::Naming::Supersedes { name, old } => info!(
                worker = id,
                old,
                "worker {name} reconnected from {host} while its old connection (worker \
                 {old}) was open: the old connection is closed and its tiles put back"
            ),
            names::Naming::Suffixed {
                name,
                holder,
                host: held_on,
                ..
            } => warn!(
                worker = id,
                holder,
                "worker name {} is already taken by worker {holder} from {held_on}: the \
                 worker from {host} joins as {name} (give each machine its own --name)",
                record.name
            ),
        }
        if let Some(old) = naming.superseded() {
            let why = format!(
                "superseded by a new connection of worker {} from the same host ({host})",
                naming.name(&record.name)
            );
            if let Some(w) = self.workers.get(&old) {
                let _ = w.outbox.send(ToWorker::Refuse {
                    reason: format!(
                        "{why}: two workers on one machine need different names (--name)"
                    ),
                });
            }
            self.worker_lost(sh, old, &why, true);
            self.tiles_event(sh, Event::WorkerLeft { worker: old });
        }
        record.name = naming.name(&record.name).to_owned();
        let (threads, name) = (record.threads, record.name.clone());
        if let Some(reason) = self.quarantined.get(&name) {
            warn!(worker = id, %name, "a quarantined machine joined: it gets no tile");
            record.quarantined = Some(reason.clone());
        }
        // The worker logs the name it is known by (another than it asked for, when
        // suffixed).
        let _ = record.outbox.send(ToWorker::Joined { name: name.clone() });
        self.workers.insert(id, record);
        self.tiles_event(
            sh,
            Event::WorkerJoined {
                worker: id,
                threads,
                machine: Some(name.clone()),
            },
        );
        // More credit: a sequence may start another frame to keep it busy.
        self.fill_all(sh);
        (id, name)
    }

    /// Tiles are durably recorded: they count in the progress reported.
    pub fn tiles_recorded(&mut self, tiles: &[(JobId, u32)]) {
        for (job, _) in tiles {
            if let Some(record) = self.jobs.get_mut(job) {
                record.tiles_recorded = (record.tiles_recorded + 1).min(record.tiles_total);
            }
        }
    }

    /// Storage became unavailable or available again.
    pub fn storage(&mut self, sh: &Arc<Shared>, status: Result<(), String>) {
        match status {
            Err(reason) => {
                self.tiles_event(sh, Event::StorageUnavailable);
                self.life_event(sh, lifecycle::Event::StorageUnavailable { reason });
            }
            Ok(()) => {
                self.life_event(sh, lifecycle::Event::StorageAvailable);
                self.tiles_event(sh, Event::StorageAvailable);
            }
        }
    }

    /// What a result for the tile must be checked against; `None` when the job is not
    /// active (the result will count for nothing). A result of the wrong size is a
    /// broken worker: an error that closes its connection.
    pub fn check_plan(
        &self,
        job: JobId,
        tile: u32,
        bytes: Option<usize>,
    ) -> anyhow::Result<Option<CheckPlan>> {
        self.plan_for(job, tile, bytes, None)
    }

    /// What an adaptive answer for the tile must be checked against; `None` when it
    /// counts for nothing (the job is not active, or the answer is for another pass).
    /// An answer for a tile of a job that is not adaptive is a broken worker.
    pub fn advanced_plan(
        &self,
        job: JobId,
        tile: u32,
        pass: u32,
        rung: u32,
    ) -> anyhow::Result<Option<CheckPlan>> {
        let Some(record) = self.jobs.get(&job) else {
            return Ok(None);
        };
        let Some(ad) = &record.adaptive else {
            anyhow::ensure!(
                record.image.is_none(),
                "an adaptive answer for tile {tile} of job {job}, which is not adaptive"
            );
            return Ok(None);
        };
        if ad.passes.pass() != pass || ad.passes.rung() != rung || ad.evaluating {
            return Ok(None);
        }
        let Some(t) = ad.tiles.get(tile as usize) else {
            anyhow::bail!("result for tile {tile} of job {job}, which has no such tile");
        };
        let plan = AdaptivePlan {
            pass,
            rung,
            previous: t.previous.clone(),
        };
        self.plan_for(job, tile, None, Some(plan))
    }

    fn plan_for(
        &self,
        job: JobId,
        tile: u32,
        bytes: Option<usize>,
        adaptive: Option<AdaptivePlan>,
    ) -> anyhow::Result<Option<CheckPlan>> {
        let Some(record) = self.jobs.get(&job) else {
            return Ok(None);
        };
        let Some(&rect) = record.tiles.get(tile as usize) else {
            anyhow::ensure!(
                record.image.is_none(),
                "result for tile {tile} of job {job}, which has no such tile"
            );
            return Ok(None);
        };
        let expected = rect.width as usize * rect.height as usize * 3;
        if let Some(bytes) = bytes {
            anyhow::ensure!(
                bytes == expected,
                "result for tile {tile} of job {job} has {bytes} bytes, expected {expected}"
            );
        }
        anyhow::ensure!(
            record.adaptive.is_none() || adaptive.is_some() || record.image.is_none(),
            "a tile result for tile {tile} of job {job}, whose tiles are advanced in passes"
        );
        Ok(record.scene.clone().map(|scene| CheckPlan {
            hash: record.hash,
            frame: record.frame,
            settings: record.settings,
            scene,
            rect,
            adaptive,
        }))
    }

    /// A worker's result, spot-checked: a wrong one quarantines its machine; a right
    /// one confirms a held result of another machine (or proves it wrong), is held for
    /// confirmation itself (every tile of a job in full verification, a random share of
    /// the others), or counts at once. The scheduler decides whether it is the first
    /// (kept) or a copy (compared).
    #[expect(
        clippy::too_many_arguments,
        reason = "one tile result's parts, as the session received them"
    )]
    pub fn tile_done(
        &mut self,
        sh: &Arc<Shared>,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        pixels: TilePixels,
        cost: Cost,
        verdict: Verdict,
    ) -> anyhow::Result<()> {
        // Checked again: the job may have ended (or its pass changed) while the spot
        // check ran.
        let current = match &verdict.plan {
            Some(plan) => self.advanced_plan(job, tile, plan.pass, plan.rung)?,
            None => self.check_plan(job, tile, None)?,
        };
        if current.is_none() {
            // An adaptive answer to a pass that is over must not pass for an answer to
            // the pass that replaced it, which may have sent the worker the same tile.
            let event = match verdict.plan {
                Some(_) => Event::Heartbeat { worker },
                None => Event::TileDone { worker, job, tile },
            };
            let actions = self.tiles.handle(sh.now(), event);
            self.apply_tiles(sh, actions);
            return Ok(());
        }
        let Some(machine) = self.workers.get(&worker).map(|w| w.name.clone()) else {
            return Ok(());
        };
        if let Err(wrong) = verdict.spot {
            let reason = format!("returned wrong pixels for tile {tile} of job {job}: {wrong}");
            self.quarantine(sh, &machine, job, reason);
            return Ok(());
        }
        debug_assert_eq!(
            pixels.rgb.len(),
            rect_pixels(self.jobs[&job].tiles[tile as usize]) as usize * 3
        );
        if let Some(w) = self.workers.get_mut(&worker) {
            let us = cost.render_us as f64;
            w.tile_us = Some(w.tile_us.map_or(us, |m| 0.8 * m + 0.2 * us));
            if let Some((rtt, tile)) = w.new_pace() {
                self.tiles_event(sh, Event::WorkerPace { worker, rtt, tile });
            }
        }
        let answer = verdict.answer.as_ref();
        let held_from = self
            .held
            .get(&(job, tile))
            .filter(|h| h.machine != machine)
            .map(|h| (h.machine.clone(), h.same(&pixels.rgb, answer)));
        let event = match held_from {
            Some((_, true)) => Event::TileDone { worker, job, tile },
            Some((other, false)) => {
                // At least one of the two is wrong: the pixels where they differ say
                // which (a few pixels rendered here, only when a liar is about).
                let held = &self.held[&(job, tile)];
                let record = &self.jobs[&job];
                let rect = record.tiles[tile as usize];
                let verdict = match (&verdict.tracer, &verdict.plan, &held.answer, answer) {
                    (Some(tracer), Some(plan), Some(a), Some(b)) => {
                        let (first, second) = adaptive::arbitrate(
                            &sh.verifier,
                            tracer,
                            &record.settings,
                            rect,
                            plan,
                            &a.state,
                            &b.state,
                        );
                        Arbitration { first, second }
                    }
                    (Some(tracer), None, _, _) => {
                        let v =
                            verify::spot::arbitrate(tracer, rect, &held.pixels.rgb, &pixels.rgb);
                        Arbitration {
                            first: v.first.map(|w| w.to_string()),
                            second: v.second.map(|w| w.to_string()),
                        }
                    }
                    _ => Arbitration {
                        first: None,
                        second: None,
                    },
                };
                if let Some(wrong) = &verdict.first {
                    let reason = format!(
                        "returned wrong pixels for tile {tile} of job {job}: {wrong} \
                         (found comparing its result with {machine}'s)"
                    );
                    self.quarantine(sh, &other, job, reason);
                }
                if let Some(wrong) = verdict.second {
                    let reason = format!(
                        "returned wrong pixels for tile {tile} of job {job}: {wrong} \
                         (found comparing its result with {other}'s)"
                    );
                    self.quarantine(sh, &machine, job, reason);
                    return Ok(());
                }
                if verdict.first.is_none() {
                    // Neither could be shown wrong (no tracer): keep neither.
                    self.quarantine(
                        sh,
                        &machine,
                        job,
                        format!("its result for tile {tile} of job {job} differs from {other}'s"),
                    );
                    return Ok(());
                }
                self.fresh_result(sh, worker, job, tile)
            }
            None => self.fresh_result(sh, worker, job, tile),
        };
        // A quarantine above may have restarted the adaptive pass this answers.
        if let Some(plan) = &verdict.plan {
            if self
                .advanced_plan(job, tile, plan.pass, plan.rung)?
                .is_none()
            {
                return Ok(());
            }
        }
        let actions = self.tiles.handle(sh.now(), event);
        let latency = self
            .workers
            .get_mut(&worker)
            .and_then(|w| w.assigned.remove(&(job, tile)))
            .map(|at| at.elapsed());
        // A result is accepted (its pixels move on to the database), held, or a copy.
        let mut pixels = Some(pixels);
        for action in &actions {
            match *action {
                Action::AcceptTile { job, tile } => {
                    sh.metrics.tile_accepted(cost.rays, latency);
                    if self.held.remove(&(job, tile)).is_some() {
                        sh.metrics.result_confirmed();
                    }
                    if let Some(pixels) = pixels.take() {
                        let answer = verdict.answer.clone();
                        self.accept_tile(sh, worker, &machine, job, tile, pixels, &cost, answer);
                    }
                }
                Action::HoldResult { worker, job, tile } => {
                    if let Some(pixels) = pixels.take() {
                        let held = Held {
                            worker,
                            machine: machine.clone(),
                            pixels,
                            cost,
                            answer: verdict.answer.clone(),
                        };
                        self.held.insert((job, tile), held);
                    }
                }
                Action::DuplicateResult { job, tile } => {
                    if let Some(pixels) = &pixels {
                        self.settle_duplicate(sh, &machine, job, tile, &pixels.rgb, &verdict);
                    }
                }
                _ => {}
            }
        }
        self.apply_tiles(sh, actions);
        Ok(())
    }

    /// A right result with nothing held to compare it with: held for confirmation
    /// when the job wants every tile confirmed, or when it is drawn for an audit and
    /// another machine could confirm it; otherwise it counts at once.
    fn fresh_result(&self, sh: &Shared, worker: WorkerId, job: JobId, tile: u32) -> Event {
        let full = self
            .jobs
            .get(&job)
            .is_some_and(|r| r.verification == Verification::Full);
        let name = self.workers.get(&worker).map(|w| w.name.as_str());
        let confirmable = || {
            self.workers
                .values()
                .any(|w| Some(w.name.as_str()) != name && w.quarantined.is_none())
        };
        if full || (sh.verifier.audit() && confirmable()) {
            Event::TileToConfirm {
                worker,
                job,
                tile,
                required: full,
            }
        } else {
            Event::TileDone { worker, job, tile }
        }
    }

    /// The machine returned wrong pixels for a tile of job `caught_in` (said in
    /// `reason`, for people): it gets no tile again, its held results are dropped, and
    /// the tiles it rendered in active jobs are rendered again. The events of
    /// `caught_in` and of every job it had tiles in say so.
    pub fn quarantine(
        &mut self,
        sh: &Arc<Shared>,
        machine: &str,
        caught_in: JobId,
        reason: String,
    ) {
        sh.metrics.result_rejected();
        let first = !self.quarantined.contains_key(machine);
        error!(machine, reason = %reason, "quarantined");
        if first {
            sh.metrics.worker_quarantined();
            self.quarantined.insert(machine.to_string(), reason.clone());
        }
        for w in self.workers.values_mut().filter(|w| w.name == machine) {
            w.quarantined.get_or_insert_with(|| reason.clone());
        }
        self.held.retain(|_, h| h.machine != machine);
        let adaptive: Vec<JobId> = self
            .jobs
            .iter()
            .filter(|(_, r)| r.adaptive.is_some())
            .map(|(&j, _)| j)
            .collect();
        for job in adaptive {
            if !self.take_back_adaptive(sh, job, machine) {
                error!(
                    job,
                    machine,
                    "a finished adaptive job holds tiles of a quarantined machine: submit it again"
                );
            }
        }
        let mut revoke = Vec::new();
        let mut affected = Vec::new();
        for (&job, record) in &mut self.jobs {
            let tiles: Vec<u32> = record
                .accepted
                .iter()
                .filter(|(_, a)| &*a.machine == machine)
                .map(|(&t, _)| t)
                .collect();
            if tiles.is_empty() {
                continue;
            }
            if !self.tiles.is_active(job) {
                // Too late to take back: the image is stored or being stored.
                error!(
                    job,
                    machine,
                    tiles = tiles.len(),
                    "a finished job holds tiles of a quarantined machine: submit it again"
                );
                continue;
            }
            for &tile in &tiles {
                if let Some(a) = record.accepted.remove(&tile) {
                    record.remove_cost(&a, rect_pixels(record.tiles[tile as usize]));
                }
                revoke.push((job, tile));
            }
            record.tiles_recorded = record.tiles_recorded.saturating_sub(tiles.len() as u32);
            if let Some(count) = record.tiles_per_worker.get_mut(machine) {
                *count = count.saturating_sub(tiles.len() as u64);
            }
            warn!(
                job,
                machine,
                tiles = tiles.len(),
                "rendering again the tiles of a quarantined machine"
            );
            affected.push((job, tiles.clone()));
            sh.persistence.write(Write::ForgetTiles { job, tiles });
        }
        // The job of its wrong tile, and those whose tiles it had rendered.
        let mut jobs: Vec<JobId> = Some(caught_in)
            .filter(|j| self.jobs.contains_key(j))
            .into_iter()
            .collect();
        jobs.extend(affected.iter().map(|(j, _)| *j));
        jobs.sort_unstable();
        jobs.dedup();
        for job in jobs {
            let taken = affected
                .iter()
                .find(|(j, _)| *j == job)
                .map_or(String::new(), |(_, t)| {
                    format!("; {} of its tiles taken back: {t:?}", t.len())
                });
            self.log(
                sh,
                job,
                "quarantine",
                format!("machine {machine} quarantined: {reason}{taken}"),
            );
        }
        self.tiles_event(
            sh,
            Event::Quarantine {
                machine: machine.to_string(),
                revoke,
            },
        );
    }

    /// Every tile of an adaptive job's pass is in: its totals are added up off the
    /// lock, and [`Core::pass_evaluated`] decides.
    fn end_of_pass(&mut self, sh: &Arc<Shared>, job: JobId) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let (Some(ad), Some(scene)) = (record.adaptive.as_mut(), record.scene.clone()) else {
            return;
        };
        ad.evaluating = true;
        let snap = PassSnapshot {
            pass: ad.passes.pass(),
            rungs: ad.passes.to_check(),
            settings: record.settings,
            rects: record.tiles.clone(),
            states: ad.tiles.iter().map(|t| t.state.clone()).collect(),
            paint_last: record.time_limit_ms.is_some(),
        };
        let (hash, frame) = (record.hash, record.frame);
        let shared = Arc::clone(sh);
        sh.runtime.spawn_blocking(move || {
            let verifier = &shared.verifier;
            let evaluation = verifier
                .tracer(hash, frame, snap.settings, &scene)
                .and_then(|tracer| adaptive::evaluate(verifier, &tracer, snap));
            shared.lock().pass_evaluated(&shared, job, evaluation);
        });
    }

    /// A pass's totals are in: the job's image is found (the first rung that meets the
    /// target), or the next pass starts. A result for a pass that is no longer the
    /// job's (restarted, cancelled) counts for nothing.
    fn pass_evaluated(
        &mut self,
        sh: &Arc<Shared>,
        job: JobId,
        evaluation: Result<Evaluation, String>,
    ) {
        let running = self
            .lifecycle
            .job(job)
            .is_some_and(|j| matches!(j.phase, Phase::Queued | Phase::Running));
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(ad) = record.adaptive.as_mut() else {
            return;
        };
        let evaluation = match evaluation {
            Ok(e) if e.pass != ad.passes.pass() || !ad.evaluating => return,
            Ok(e) => e,
            Err(message) => {
                ad.evaluating = false;
                if !running {
                    return;
                }
                let message = format!("cannot add up the pass's tiles: {message}");
                error!(job, error = %message, "adaptive job failed");
                self.life_event(sh, lifecycle::Event::TilesFailed { job, message });
                return;
            }
        };
        ad.evaluating = false;
        if !running {
            return;
        }
        let t = evaluation.totals;
        let pixels = u64::from(record.settings.width) * u64::from(record.settings.height);
        record.totals.samples = t.samples;
        let estimate = t.estimated_error();
        if estimate.is_finite() {
            record.totals.error_sq_sum = estimate * estimate * pixels as f64;
            record.totals.error_pixels = pixels;
        }
        let first_work = ad.tiles.iter().filter_map(|t| t.next_work).min();
        // Rendering time, less the coordinator's own downtime: what a limit budgets.
        let now = unix_ms();
        let elapsed =
            record.rendered_before_ms + now.saturating_sub(record.running_since.unwrap_or(now));
        match ad
            .passes
            .pass_done_at(&evaluation.checks, first_work, elapsed, t.samples)
        {
            scheduler::passes::Decision::OutOfTime { rung } => {
                info!(
                    job,
                    passes = ad.passes.pass() + 1,
                    rung,
                    estimate,
                    elapsed_ms = elapsed,
                    "adaptive job: the time limit is reached"
                );
                let pass = ad.passes.pass() + 1;
                record.stopped_on_time_limit = true;
                record.image = evaluation.image;
                record.tiles_recorded = record.tiles_total;
                self.log(
                    sh,
                    job,
                    "adaptive_pass",
                    format!(
                        "pass {pass} at rung {rung}: estimated error {estimate:.3} levels; \
                         the time limit is reached"
                    ),
                );
                self.life_event(sh, lifecycle::Event::TilesComplete { job });
            }
            scheduler::passes::Decision::Finish { rung } => {
                info!(
                    job,
                    passes = ad.passes.pass() + 1,
                    rung,
                    estimate,
                    "adaptive job: the target is met"
                );
                let pass = ad.passes.pass() + 1;
                record.image = evaluation.image;
                record.tiles_recorded = record.tiles_total;
                self.log(
                    sh,
                    job,
                    "adaptive_pass",
                    format!(
                        "pass {pass} at rung {rung}: estimated error {estimate:.3} levels; \
                         the target is met"
                    ),
                );
                self.life_event(sh, lifecycle::Event::TilesComplete { job });
            }
            scheduler::passes::Decision::Next { rung } => {
                info!(
                    job,
                    pass = ad.passes.pass(),
                    rung,
                    estimate,
                    "adaptive job: next pass"
                );
                let pass = ad.passes.pass();
                self.log(
                    sh,
                    job,
                    "adaptive_pass",
                    format!(
                        "estimated error {estimate:.3} levels: pass {pass} goes on to rung {rung}"
                    ),
                );
                self.start_pass(sh, job);
            }
        }
        sh.changed();
    }

    /// Starts the job's pass under way: every tile with work at its rung goes out from
    /// the state it has; the others have reached the rung already.
    fn start_pass(&mut self, sh: &Arc<Shared>, job: JobId) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(ad) = record.adaptive.as_mut() else {
            return;
        };
        let rung = ad.passes.rung();
        let next_work: Vec<Option<u32>> = ad
            .tiles
            .iter()
            .map(|t| {
                if t.rung == Some(rung) {
                    None
                } else {
                    t.next_work
                }
            })
            .collect();
        let send = scheduler::passes::tiles_with_work(&next_work, rung);
        for (i, t) in ad.tiles.iter_mut().enumerate() {
            if send.binary_search(&(i as u32)).is_ok() {
                t.previous = t.state.clone();
            } else {
                t.rung = Some(rung);
            }
        }
        let done: Vec<u32> = (0..record.tiles_total)
            .filter(|t| send.binary_search(t).is_err())
            .collect();
        let (priority, hash, total) = (record.priority, record.hash, record.tiles_total);
        // The scheduler forgets a pause when a run of the job ends (each pass is one):
        // a paused job's next pass starts paused.
        if record.paused {
            self.tiles_event(sh, Event::PauseJob { job });
        }
        let actions = self
            .tiles
            .resume_job(sh.now(), job, priority, hash, total, &done);
        self.apply_tiles(sh, actions);
        self.mark_interactive(sh, job);
    }

    /// A machine of the quarantine built some of an adaptive job's tiles: they start
    /// again from nothing, and the pass under way starts again under a new number (at
    /// the same rung), so that no answer built on its states counts and every rung is
    /// added up again. `false` when the job is past its passes.
    fn take_back_adaptive(&mut self, sh: &Arc<Shared>, job: JobId, machine: &str) -> bool {
        let Some(record) = self.jobs.get_mut(&job) else {
            return false;
        };
        let Some(ad) = record.adaptive.as_mut() else {
            return false;
        };
        let tainted: Vec<usize> = (0..ad.tiles.len())
            .filter(|&t| ad.tiles[t].machines.iter().any(|m| &**m == machine))
            .collect();
        if tainted.is_empty() {
            return true;
        }
        let passing = self
            .lifecycle
            .job(job)
            .is_some_and(|j| matches!(j.phase, Phase::Queued | Phase::Running));
        if !passing {
            return false;
        }
        warn!(
            job,
            machine,
            tiles = tainted.len(),
            "rendering again the adaptive tiles a quarantined machine built"
        );
        for t in tainted {
            ad.tiles[t] = adaptive::AdaptiveTile {
                next_work: Some(0),
                ..adaptive::AdaptiveTile::default()
            };
        }
        ad.passes.restart_pass();
        ad.evaluating = false;
        self.held.retain(|(j, _), _| *j != job);
        self.tiles_event(sh, Event::CancelJob { job });
        self.start_pass(sh, job);
        true
    }

    /// A pong: the round trip to the worker, if the token was ours.
    pub fn pong(&mut self, sh: &Arc<Shared>, worker: WorkerId, rtt_us: Option<u64>) {
        let mut pace = None;
        if let (Some(w), Some(rtt)) = (self.workers.get_mut(&worker), rtt_us) {
            if w.rtts.len() == RTTS_KEPT {
                w.rtts.pop_front();
            }
            w.rtts.push_back(rtt);
            pace = w.new_pace();
        }
        self.tiles_event(sh, Event::Heartbeat { worker });
        if let Some((rtt, tile)) = pace {
            self.tiles_event(sh, Event::WorkerPace { worker, rtt, tile });
        }
    }

    /// A worker could not render a tile.
    pub fn tile_failed(
        &mut self,
        sh: &Arc<Shared>,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        message: String,
    ) {
        warn!(worker, job, tile, error = %message, "tile failed");
        let name = match self.workers.get_mut(&worker) {
            Some(w) => {
                w.assigned.remove(&(job, tile));
                w.name.clone()
            }
            None => format!("worker {worker}"),
        };
        self.log(
            sh,
            job,
            "tile_failed",
            format!("tile {tile} on {name}: {message}"),
        );
        let message = format!("tile {tile} failed on a worker: {message}");
        self.tiles_event(
            sh,
            Event::TileFailed {
                worker,
                job,
                tile,
                message,
            },
        );
    }

    /// A straggler's second copy of a tile must equal the accepted one. If it does
    /// not, one of them is wrong: the pixels where they differ, rendered here, say
    /// which, and that machine is quarantined (which takes the accepted tile back if
    /// it was the wrong one and the job is still rendering).
    fn settle_duplicate(
        &mut self,
        sh: &Arc<Shared>,
        machine: &str,
        job: JobId,
        tile: u32,
        rgb: &[u8],
        verdict: &Verdict,
    ) {
        let tracer = verdict.tracer.as_deref();
        let Some(record) = self.jobs.get(&job) else {
            return;
        };
        if let (Some(ad), Some(answer), Some(plan)) =
            (&record.adaptive, &verdict.answer, &verdict.plan)
        {
            let t = &ad.tiles[tile as usize];
            let (Some(state), Some(first)) = (&t.state, t.machines.last()) else {
                return;
            };
            if t.rung != Some(plan.rung) || t.sha == answer.sha {
                return;
            }
            let (Some(tracer), Some(&rect)) = (tracer, record.tiles.get(tile as usize)) else {
                return;
            };
            let first = first.to_string();
            let (wrong_first, wrong_second) = adaptive::arbitrate(
                &sh.verifier,
                tracer,
                &record.settings,
                rect,
                plan,
                state,
                &answer.state,
            );
            if let Some(wrong) = wrong_first {
                let reason = format!(
                    "returned wrong pixels for tile {tile} of job {job}: {wrong} (found \
                     comparing its result with {machine}'s copy)"
                );
                self.quarantine(sh, &first, job, reason);
            }
            if let Some(wrong) = wrong_second {
                let reason = format!(
                    "returned wrong pixels for tile {tile} of job {job}: {wrong} (found \
                     comparing its copy with the accepted result)"
                );
                self.quarantine(sh, machine, job, reason);
            }
            return;
        }
        let (Some(image), Some(&rect)) = (&record.image, record.tiles.get(tile as usize)) else {
            return;
        };
        let row = rect.width as usize * 3;
        let accepted: Vec<u8> = (0..rect.height as usize)
            .flat_map(|r| {
                let start = ((rect.y as usize + r) * image.width as usize + rect.x as usize) * 3;
                image.rgb[start..start + row].iter().copied()
            })
            .collect();
        if accepted == rgb {
            info!(
                machine,
                job, tile, "duplicate result equals the accepted one"
            );
            return;
        }
        let first = record.accepted.get(&tile).map(|a| a.machine.to_string());
        let Some(tracer) = tracer else {
            error!(
                machine,
                job, tile, "duplicate result differs from the accepted one"
            );
            return;
        };
        let verdict = verify::spot::arbitrate(tracer, rect, &accepted, rgb);
        if let (Some(wrong), Some(first)) = (verdict.first, first) {
            let reason = format!(
                "returned wrong pixels for tile {tile} of job {job}: {wrong} (found comparing \
                 its result with {machine}'s copy)"
            );
            self.quarantine(sh, &first, job, reason);
        }
        if let Some(wrong) = verdict.second {
            let reason = format!(
                "returned wrong pixels for tile {tile} of job {job}: {wrong} (found comparing \
                 its copy with the accepted result)"
            );
            self.quarantine(sh, machine, job, reason);
        }
    }

    #[expect(
        clippy::too_many_arguments,
        reason = "one tile result's parts, as the session received them"
    )]
    fn accept_tile(
        &mut self,
        sh: &Shared,
        worker: WorkerId,
        machine: &str,
        job: JobId,
        tile: u32,
        pixels: TilePixels,
        cost: &Cost,
        answer: Option<Answer>,
    ) {
        if let Some(w) = self.workers.get_mut(&worker) {
            w.tiles_done += 1;
            w.rays += cost.rays;
            w.count_result(Instant::now(), cost.render_us, cost.rays);
        }
        self.log(
            sh,
            job,
            "tile_done",
            format!(
                "tile {tile} by {machine} in {:.3} s ({} rays)",
                cost.render_us as f64 / 1e6,
                cost.rays
            ),
        );
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(&rect) = record.tiles.get(tile as usize) else {
            return;
        };
        let TilePixels { rgb, zstd } = pixels;
        if let Some(ad) = record.adaptive.as_mut() {
            // The tile's new state is kept for the next pass; its pixels show the pass's
            // progress. Nothing is written: a restarted coordinator starts the passes
            // again.
            let Some(answer) = answer.filter(|a| a.pass == ad.passes.pass()) else {
                return;
            };
            let t = &mut ad.tiles[tile as usize];
            t.state = Some(answer.state);
            t.rung = Some(ad.passes.rung());
            t.sha = answer.sha;
            t.next_work = answer.next_work;
            if !t.machines.iter().any(|m| &**m == machine) {
                t.machines.push(Arc::from(machine));
            }
            ad.rays += cost.rays;
            record.totals.rays = record.totals.rays.saturating_add(cost.rays);
            if let Some(image) = record.image.as_mut() {
                image.put_rect(to_render_rect(rect), &rgb);
            }
            if let Some(owner) = &record.owner {
                sh.studio.tile(owner, rect, &rgb);
            }
            *record
                .tiles_per_worker
                .entry(machine.to_string())
                .or_default() += 1;
            return;
        }
        if let Some(image) = record.image.as_mut() {
            image.put_rect(to_render_rect(rect), &rgb);
        }
        if let Some(owner) = &record.owner {
            sh.studio.tile(owner, rect, &rgb);
        }
        // An estimate that is not a sum of squares (a broken worker) counts as unknown.
        let error_sq_sum = (cost.error_sq_sum.is_finite() && cost.error_sq_sum >= 0.0)
            .then_some(cost.error_sq_sum);
        record.add_cost(cost.rays, cost.samples, error_sq_sum, rect_pixels(rect));
        record.pace.tile_done(unix_ms());
        let name = machine.to_string();
        let accepted = Accepted {
            machine: Arc::from(machine),
            rays: cost.rays,
            samples: cost.samples,
            error_sq_sum,
        };
        if let Some(earlier) = record.accepted.insert(tile, accepted) {
            // Accepted before and since revoked or re-rendered: counted once.
            record.remove_cost(&earlier, rect_pixels(rect));
        }
        *record.tiles_per_worker.entry(name.clone()).or_default() += 1;
        self.store(
            sh,
            job,
            Write::Tile(crate::db::TileWrite {
                job,
                tile,
                zstd,
                rays: cost.rays,
                worker: name,
                samples: cost.samples,
                error_sq_sum,
                done_ms: unix_ms(),
            }),
        );
    }

    /// Carries out the tile scheduler's actions.
    fn apply_tiles(&mut self, sh: &Arc<Shared>, actions: Vec<Action>) {
        for action in actions {
            match action {
                Action::SendScene { worker, job } => {
                    if let Some(scene) = self.jobs.get(&job).and_then(|r| r.scene.clone()) {
                        let hash = self.jobs[&job].hash;
                        self.send(
                            worker,
                            ToWorker::Scene {
                                hash,
                                scene: scene.to_string(),
                            },
                        );
                    }
                }
                Action::Assign { worker, job, tile } => self.assign(sh, worker, job, tile),
                Action::CancelOnWorker { worker, job } => {
                    self.send(worker, ToWorker::Cancel { job });
                    if let Some(w) = self.workers.get_mut(&worker) {
                        w.assigned.retain(|(j, _), _| *j != job);
                    }
                }
                Action::ForgetScene { worker, scene } => {
                    self.send(worker, ToWorker::ForgetScene { hash: scene })
                }
                Action::AcceptTile { .. }
                | Action::DuplicateResult { .. }
                | Action::HoldResult { .. } => {}
                Action::AcceptHeld { job, tile } => {
                    if let Some(held) = self.held.remove(&(job, tile)) {
                        info!(job, tile, machine = %held.machine, "no other machine may confirm the audited tile: accepted as checked");
                        sh.metrics.tile_accepted(held.cost.rays, None);
                        self.accept_tile(
                            sh,
                            held.worker,
                            &held.machine,
                            job,
                            tile,
                            held.pixels,
                            &held.cost,
                            held.answer,
                        );
                    }
                }
                Action::WorkerUnresponsive { worker, silent } => {
                    if let Some(w) = self.workers.get(&worker) {
                        warn!(
                            worker,
                            name = %w.name,
                            silent_ms = silent,
                            "worker unresponsive: its leases ran out and no result came; its \
                             tiles go to other workers until it returns one"
                        );
                    }
                }
                Action::WorkerResponsive { worker } => {
                    if let Some(w) = self.workers.get(&worker) {
                        info!(worker, name = %w.name, "worker responsive again");
                    }
                }
                Action::DropWorker { worker } => {
                    if let Some(w) = self.workers.get(&worker) {
                        warn!(worker, name = %w.name, "no heartbeat in time: dropping the worker");
                    }
                    self.worker_lost(sh, worker, "no heartbeat in time (timed out)", true);
                }
                Action::JobDone { job } => {
                    self.held.retain(|(j, _), _| *j != job);
                    if self.jobs.get(&job).is_some_and(|r| r.adaptive.is_some()) {
                        self.end_of_pass(sh, job);
                    } else {
                        self.life_event(sh, lifecycle::Event::TilesComplete { job });
                    }
                }
                Action::JobFailed { job, message } => {
                    self.held.retain(|(j, _), _| *j != job);
                    warn!(job, error = %message, "job failed");
                    self.life_event(sh, lifecycle::Event::TilesFailed { job, message });
                }
            }
        }
        sh.changed();
    }

    fn send(&self, worker: WorkerId, message: ToWorker) {
        if let Some(w) = self.workers.get(&worker) {
            // A closed channel means the worker is leaving; WorkerLeft follows.
            let _ = w.outbox.send(message);
        }
    }

    fn assign(&mut self, sh: &Arc<Shared>, worker: WorkerId, job: JobId, tile: u32) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(&rect) = record.tiles.get(tile as usize) else {
            return;
        };
        let message = match &record.adaptive {
            Some(ad) => ToWorker::Advance {
                job,
                tile,
                scene: record.hash,
                frame: record.frame,
                settings: record.settings,
                rect,
                pass: ad.passes.pass(),
                rung: ad.passes.rung(),
                previous: ad.tiles[tile as usize]
                    .previous
                    .as_ref()
                    .map(|p| p.to_vec()),
            },
            None => ToWorker::Render {
                job,
                tile,
                scene: record.hash,
                frame: record.frame,
                settings: record.settings,
                rect,
            },
        };
        if record.running_since.is_none() {
            record.running_since = Some(unix_ms());
        }
        let first = record.times.started.is_none();
        if first {
            let at = record.running_since.unwrap_or_else(unix_ms);
            record.times.started = Some(at);
            // The wait of this run: since the submission, or the retry.
            let queued = at.saturating_sub(
                record
                    .times
                    .retried
                    .or(record.times.submitted)
                    .unwrap_or(at),
            );
            self.store(
                sh,
                job,
                Write::Started {
                    job,
                    at_unix_ms: at,
                },
            );
            self.log(
                sh,
                job,
                "started",
                format!(
                    "first tile out after {:.1} s in the queue",
                    queued as f64 / 1000.0
                ),
            );
        }
        self.send(worker, message);
        let name = match self.workers.get_mut(&worker) {
            Some(w) => {
                w.assigned.insert((job, tile), Instant::now());
                w.name.clone()
            }
            None => format!("worker {worker}"),
        };
        self.log(sh, job, "tile_assigned", format!("tile {tile} to {name}"));
        self.life_event(sh, lifecycle::Event::TileAssigned { job });
        // Fewer tiles wait: the sequence may start its next frame.
        if let Some(sequence) = self.jobs.get(&job).and_then(|r| r.sequence) {
            self.fill(sh, sequence);
        }
    }

    /// Carries out the lifecycle's actions; returns its reply (one event asks for one
    /// at most).
    fn apply_life(
        &mut self,
        sh: &Arc<Shared>,
        actions: Vec<lifecycle::Action>,
    ) -> Option<Result<Reply, Refusal>> {
        use lifecycle::Action as A;
        let mut reply = None;
        for action in actions {
            match action {
                A::Acknowledge { job } => self.acknowledge(sh, job),
                A::RefuseStored { job, message } => {
                    if let Some(r) = self.jobs.remove(&job) {
                        if let Some(sequence) = r.sequence {
                            self.frame_refused(sequence, r.frame);
                        }
                    }
                    error!(job, error = %message, "cannot store a job");
                    if let Some(reply) = self.submits.remove(&job) {
                        let _ = reply.send(ClientResponse::Error(Refusal::internal(format!(
                            "the coordinator cannot store new jobs now: {message}"
                        ))));
                    }
                }
                A::StoreImage { job } => self.store_image(sh, job),
                A::CancelTiles { job } => {
                    self.held.retain(|(j, _), _| *j != job);
                    self.tiles_event(sh, Event::CancelJob { job })
                }
                A::RecordEnd { job, state, error } => self.record_end(sh, job, state, error),
                A::DeleteStored { job } => {
                    let shared = Arc::clone(sh);
                    self.store(
                        sh,
                        job,
                        Write::Delete {
                            job,
                            place: self.image_place(job),
                            then: Box::new(move |_| {
                                let mut core = shared.lock();
                                core.jobs.remove(&job);
                                core.life_event(&shared, lifecycle::Event::Deleted { job });
                                drop(core);
                                info!(job, "job deleted");
                                shared.changed();
                            }),
                        },
                    );
                }
                A::Reply { result, .. } => {
                    debug_assert!(reply.is_none(), "two replies to one event");
                    reply = Some(result);
                }
            }
        }
        sh.changed();
        reply
    }

    /// The job's row is written: the client hears its id, the tiles go out.
    fn acknowledge(&mut self, sh: &Arc<Shared>, job: JobId) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        record.image = Some(render::Image::black(
            record.settings.width,
            record.settings.height,
        ));
        let (priority, scene, tiles) = (record.priority, record.hash, record.tiles_total);
        let s = record.settings;
        info!(
            job,
            width = s.width,
            height = s.height,
            aa = s.aa,
            sampler = s.sampling.name(),
            target_error = ?s.sampling.target_error(),
            tiles,
            "job accepted"
        );
        if let Some(reply) = self.submits.remove(&job) {
            let _ = reply.send(ClientResponse::Submitted { job });
        }
        self.tiles_event(
            sh,
            Event::JobSubmitted {
                job,
                priority,
                scene,
                tiles,
            },
        );
        self.mark_interactive(sh, job);
        if let Some((sequence, frame)) = self
            .jobs
            .get(&job)
            .and_then(|r| Some((r.sequence?, r.frame)))
        {
            self.frame_acknowledged(sh, sequence, frame, job);
        }
    }

    /// Tells the scheduler that a studio view's pass goes ahead of batch jobs; each run
    /// of the job (an adaptive pass) is told again, as a pause is.
    fn mark_interactive(&mut self, sh: &Arc<Shared>, job: JobId) {
        if self.jobs.get(&job).is_some_and(|r| r.interactive) {
            self.tiles_event(sh, Event::Interactive { job });
        }
    }

    /// Every tile is in: encode and store the image on the blocking pool; the
    /// lifecycle hears when it is stored.
    fn store_image(&mut self, sh: &Arc<Shared>, job: JobId) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let Some(image) = record.image.take() else {
            error!(job, "no frame to store");
            return;
        };
        let ended = unix_ms();
        record.times.ended = Some(ended);
        if record.interactive {
            // Its tiles went to the view's page as they came: nothing to encode or keep.
            drop(image);
            let shared = Arc::clone(sh);
            drop(sh.runtime.spawn_blocking(move || {
                let event = lifecycle::Event::ImageStored {
                    job,
                    result: Ok(()),
                };
                shared.lock().life_event(&shared, event);
            }));
            return;
        }
        let meta = record.metadata(job, ended);
        let scene = record.scene.clone().unwrap_or_else(|| Arc::from(""));
        // An adaptive job keeps its tiles' final states beside its image: a refinement
        // goes on from them. They are at the last pass's rung (at or past the image's).
        let states = record.adaptive.as_ref().and_then(|ad| {
            let states: Option<Vec<Arc<Vec<u8>>>> =
                ad.tiles.iter().map(|t| t.state.clone()).collect();
            Some(Box::new(crate::store::TileStates {
                rung: ad.passes.rung(),
                aa: record.settings.aa,
                tile_size: record.tile_size,
                states: states?,
            }))
        });
        let place = self.image_place(job);
        let shared = Arc::clone(sh);
        sh.runtime.spawn_blocking(move || {
            let png = image.to_png();
            drop(image);
            let then_shared = Arc::clone(&shared);
            shared.persistence.write(Write::Image {
                place,
                meta: Box::new(meta),
                scene,
                png,
                states,
                then: Box::new(move |result| {
                    let sh = then_shared;
                    let mut core = sh.lock();
                    if let (Ok(sha), Some(record)) = (&result, core.jobs.get_mut(&job)) {
                        record.image_sha256 = Some(*sha);
                    }
                    core.life_event(
                        &sh,
                        lifecycle::Event::ImageStored {
                            job,
                            result: result.map(|_| ()),
                        },
                    );
                }),
            });
        });
    }

    /// The job ended: free what it held and write its end.
    fn record_end(&mut self, sh: &Arc<Shared>, job: JobId, state: JobState, error: Option<String>) {
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        record.image = None;
        record.scene = None;
        record.tiles = Vec::new();
        record.accepted = HashMap::new();
        record.adaptive = None;
        let ended = *record.times.ended.get_or_insert_with(unix_ms);
        let rays = record.totals.rays;
        match state {
            JobState::Done => info!(
                job,
                wall_ms = ended.saturating_sub(record.times.submitted.unwrap_or(ended)),
                rays,
                "job done"
            ),
            JobState::Cancelled => info!(job, "job cancelled"),
            _ => {}
        }
        let queued = record
            .times
            .started
            .map(|s| s.saturating_sub(record.times.submitted.unwrap_or(s)));
        let detail = match (state, &error) {
            (JobState::Done, _) => format!(
                "{} rays, rendered in {:.1} s after {:.1} s in the queue",
                rays,
                ended.saturating_sub(record.times.started.unwrap_or(ended)) as f64 / 1000.0,
                queued.unwrap_or(0) as f64 / 1000.0
            ),
            (_, Some(e)) => e.clone(),
            (_, None) => format!(
                "{} of {} tiles done",
                record.tiles_recorded, record.tiles_total
            ),
        };
        self.log(sh, job, state.as_str(), detail);
        let Some(record) = self.jobs.get_mut(&job) else {
            return;
        };
        let shared = Arc::clone(sh);
        // A studio view's pass is forgotten once it has ended: a long drag makes many.
        let forget = record.interactive;
        if forget {
            sh.studio.ended(sh.now(), job, state == JobState::Done);
        }
        let frame_of = record.sequence.map(|s| (s, record.frame));
        let write = Write::End {
            job,
            state,
            error,
            totals: record.totals,
            times: record.times,
            image_sha256: record.image_sha256,
            stopped_on_time_limit: record.stopped_on_time_limit,
            then: Box::new(move |_| {
                let mut core = shared.lock();
                core.life_event(&shared, lifecycle::Event::EndRecorded { job });
                if forget {
                    core.life_event(&shared, lifecycle::Event::Delete { job });
                }
                if let Some((sequence, frame)) = frame_of {
                    core.frame_ended(&shared, sequence, frame, job);
                }
                drop(core);
                shared.changed();
            }),
        };
        self.store(sh, job, write);
    }

    /// An operator pauses (`true`) or resumes a job (or a sequence: its frames, see
    /// `set_sequence_paused`): its tiles stop going out at once
    /// (those out may finish), or go out again. Returns what to store before the
    /// change is acknowledged, or why the job cannot be paused or resumed. Pausing a
    /// paused job, or resuming one that is not, changes nothing and succeeds.
    pub fn set_paused(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        paused: bool,
    ) -> Result<Controls, Refusal> {
        if self.sequences.contains_key(&id) {
            return self.set_sequence_paused(sh, id, paused);
        }
        let verb = if paused { "paused" } else { "resumed" };
        self.check_controllable(id, verb)?;
        let record = self.jobs.get_mut(&id).ok_or_else(|| unknown(id))?;
        let changed = record.paused != paused;
        record.paused = paused;
        let controls = Controls {
            job: id,
            paused,
            priority: record.priority,
        };
        if changed {
            info!(job = id, "job {verb} by an operator");
            let event = if paused {
                Event::PauseJob { job: id }
            } else {
                Event::ResumeJob { job: id }
            };
            self.tiles_event(sh, event);
        }
        Ok(controls)
    }

    /// An operator gives a job a new priority: the next tiles handed out follow it.
    /// Returns what to store before the change is acknowledged, or why not.
    pub fn set_priority(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        priority: i32,
    ) -> Result<Controls, Refusal> {
        if self.sequences.contains_key(&id) {
            return self.set_sequence_priority(sh, id, priority);
        }
        self.check_controllable(id, "given a new priority")?;
        let record = self.jobs.get_mut(&id).ok_or_else(|| unknown(id))?;
        let changed = record.priority != priority;
        record.priority = priority;
        let controls = Controls {
            job: id,
            paused: record.paused,
            priority,
        };
        if changed {
            info!(
                job = id,
                priority, "job given a new priority by an operator"
            );
            self.tiles_event(sh, Event::SetPriority { job: id, priority });
        }
        Ok(controls)
    }

    /// Whether an operator may still change the job: it must be queued or running,
    /// with tiles still to hand out.
    fn check_controllable(&self, id: JobId, verb: &str) -> Result<(), Refusal> {
        let job = self.lifecycle.job(id).ok_or_else(|| unknown(id))?;
        match &job.phase {
            Phase::Storing | Phase::Queued | Phase::Running => Ok(()),
            Phase::Finishing { .. } => Err(Refusal::state(format!(
                "job {id} cannot be {verb}: all its tiles are in and its image is being stored"
            ))),
            Phase::Ended { state, .. } => Err(ended_refusal(id, verb, *state)),
        }
    }

    /// An operator has tiles of a queued or running job rendered again, wherever they
    /// are (see [`Event::RequeueTiles`]): a done tile's result is dropped, from the
    /// frame's totals and from the disk. Returns what to store before the change is
    /// acknowledged (the stored tiles are forgotten before it, in the queue's order).
    pub fn requeue(
        &mut self,
        sh: &Arc<Shared>,
        id: JobId,
        tiles: &[u32],
        peer: std::net::IpAddr,
    ) -> Result<Controls, Refusal> {
        self.check_controllable(id, "requeued")?;
        let record = self.jobs.get_mut(&id).ok_or_else(|| unknown(id))?;
        if record.adaptive.is_some() {
            return Err(Refusal::invalid(format!(
                "job {id} cannot be requeued: an adaptive job renders in passes, whose \
                 tiles are not taken back one by one"
            )));
        }
        if tiles.is_empty() {
            return Err(Refusal::invalid(format!(
                "job {id}: name at least one tile to requeue"
            )));
        }
        let total = record.tiles_total;
        if let Some(bad) = tiles.iter().find(|&&t| t >= total) {
            return Err(Refusal::invalid(format!(
                "job {id} has tiles 0 to {}: there is no tile {bad}",
                total.saturating_sub(1)
            )));
        }
        let mut tiles = tiles.to_vec();
        tiles.sort_unstable();
        tiles.dedup();
        let mut forget = Vec::new();
        for &tile in &tiles {
            if let Some(a) = record.accepted.remove(&tile) {
                record.remove_cost(&a, rect_pixels(record.tiles[tile as usize]));
                record.tiles_recorded = record.tiles_recorded.saturating_sub(1);
                if let Some(count) = record.tiles_per_worker.get_mut(&*a.machine) {
                    *count = count.saturating_sub(1);
                }
                forget.push(tile);
            }
        }
        let controls = Controls {
            job: id,
            paused: record.paused,
            priority: record.priority,
        };
        self.held
            .retain(|&(j, t), _| j != id || tiles.binary_search(&t).is_err());
        for w in self.workers.values_mut() {
            w.assigned
                .retain(|&(j, t), _| j != id || tiles.binary_search(&t).is_err());
        }
        if !forget.is_empty() {
            sh.persistence.write(Write::ForgetTiles {
                job: id,
                tiles: forget.clone(),
            });
        }
        info!(job = id, tiles = ?tiles, "tiles requeued by an operator");
        self.log(
            sh,
            id,
            "requeued",
            format!(
                "tiles {tiles:?} from {peer} ({} of them done before)",
                forget.len()
            ),
        );
        self.tiles_event(sh, Event::RequeueTiles { job: id, tiles });
        Ok(controls)
    }

    /// A client's view of a job.
    /// None for an unknown job, and for a studio view's pass: clients and the status
    /// page see only the jobs that are kept.
    pub fn status(&self, id: JobId) -> Option<JobStatus> {
        if self.sequences.contains_key(&id) {
            return self.sequence_status(id);
        }
        let job = self.lifecycle.job(id)?;
        let record = self.jobs.get(&id).filter(|r| !r.interactive)?;
        let mut status = record.status(id, job);
        if !status.state.is_final() {
            status.warning = self.no_worker_warning();
        }
        Some(status)
    }

    /// Why no tile can go out to any worker, when that is so: the one line clients
    /// show while jobs wait (the scheduler decides who may take tiles).
    pub fn no_worker_warning(&self) -> Option<String> {
        if self.tiles.can_hand_out() {
            return None;
        }
        let connected = self.workers.len();
        Some(if connected == 0 {
            "no worker is connected: queued and running jobs wait until one connects".into()
        } else {
            format!(
                "no worker can take tiles: all {connected} connected are disabled, draining, \
                 quarantined or unresponsive (see tessera workers)"
            )
        })
    }

    pub fn worker_statuses(&self) -> Vec<WorkerStatus> {
        self.workers
            .iter()
            .map(|(&id, w)| {
                let mut status = w.status(id, self.tiles.held_by(id), self.tiles.credit_of(id));
                status.disabled = self.tiles.is_disabled(&w.name);
                status.unresponsive = self.tiles.is_unresponsive(id);
                status
            })
            .collect()
    }

    /// The connected worker an operator names: by id (as `tessera workers` lists
    /// them), or by name (unique among connected workers, [`names`]). `Err` is the
    /// one-line reason none is.
    fn named_worker(&self, key: &str) -> Result<WorkerId, Refusal> {
        if let Ok(id) = key.parse::<WorkerId>() {
            if self.workers.contains_key(&id) {
                return Ok(id);
            }
        }
        self.workers
            .iter()
            .find(|(_, w)| w.name == key)
            .map(|(&id, _)| id)
            .ok_or_else(|| {
                Refusal::not_found(format!(
                    "no worker {key:?} is connected: give an id or a name from tessera workers"
                ))
            })
    }

    /// An operator drains a worker: it is told to finish what it holds and exit (as
    /// on SIGTERM), and gets no new tile from now on. Returns its id.
    pub fn drain_worker(&mut self, sh: &Arc<Shared>, key: &str) -> Result<WorkerId, Refusal> {
        let worker = self.named_worker(key)?;
        if let Some(w) = self.workers.get_mut(&worker) {
            info!(worker, name = %w.name, host = %w.host, "worker drained by an operator");
            w.draining = true;
            let _ = w.outbox.send(ToWorker::Drain);
        }
        self.tiles_event(sh, Event::WorkerDraining { worker });
        Ok(worker)
    }

    /// An operator disables (`true`) or enables a machine, named by a connected
    /// worker's id or name, or (to enable) by the name of a disabled machine not
    /// connected now. Returns the machine's name, to be stored before the change is
    /// acknowledged.
    pub fn set_disabled(
        &mut self,
        sh: &Arc<Shared>,
        key: &str,
        disabled: bool,
    ) -> Result<String, Refusal> {
        let machine = match self.named_worker(key) {
            Ok(worker) => self.workers[&worker].name.clone(),
            Err(_) if !disabled && self.tiles.is_disabled(key) => key.to_string(),
            Err(message) => return Err(message),
        };
        if self.tiles.is_disabled(&machine) != disabled {
            let verb = if disabled { "disabled" } else { "enabled" };
            info!(%machine, "machine {verb} by an operator");
            let event = if disabled {
                Event::DisableMachine {
                    machine: machine.clone(),
                }
            } else {
                Event::EnableMachine {
                    machine: machine.clone(),
                }
            };
            self.tiles_event(sh, event);
        }
        Ok(machine)
    }
}

/// The error for a job this coordinator does not know.
fn unknown(id: JobId) -> Refusal {
    Refusal::unknown_job(id)
}

/// Which of two differing results is wrong, and why, if it could be shown.
struct Arbitration {
    first: Option<String>,
    second: Option<String>,
}

/// Whether a job's tiles are advanced in passes.
fn is_adaptive(settings: &Settings) -> bool {
    settings.sampling.target_error().is_some()
}

fn to_render_rect(r: TileRect) -> render::Rect {
    render::Rect {
        x: r.x,
        y: r.y,
        width: r.width,
        height: r.height,
    }
}

fn rect_pixels(r: TileRect) -> u64 {
    u64::from(r.width) * u64::from(r.height)
}

impl JobRecord {
    /// Counts a tile of `pixels` pixels that took `samples` samples, with its sum of
    /// squared error estimates if known.
    /// Takes back what an accepted tile added to the totals.
    fn remove_cost(&mut self, a: &Accepted, pixels: u64) {
        let t = &mut self.totals;
        t.rays = t.rays.saturating_sub(a.rays);
        t.samples = t.samples.saturating_sub(a.samples);
        if let Some(e) = a.error_sq_sum {
            t.error_sq_sum -= e;
            t.error_pixels = t.error_pixels.saturating_sub(pixels);
        }
    }

    fn add_cost(&mut self, rays: u64, samples: u64, error_sq_sum: Option<f64>, pixels: u64) {
        let t = &mut self.totals;
        t.rays = t.rays.saturating_add(rays);
        t.samples = t.samples.saturating_add(samples);
        if let Some(e) = error_sq_sum {
            t.error_sq_sum += e;
            t.error_pixels += pixels;
        }
    }

    /// The image's estimated error in levels, once every pixel has an estimate
    /// ([`figures::image_error`]).
    fn estimated_error(&self) -> Option<f64> {
        let pixels = u64::from(self.settings.width) * u64::from(self.settings.height);
        figures::image_error(self.settings.aa, &self.totals, pixels)
    }

    /// Rays per second of rendering: from the first tile handed out to the end, less
    /// the time the job waited in the queue or the coordinator was down.
    fn rays_per_second(&self, until: u64) -> f64 {
        let this_run = until.saturating_sub(self.running_since.unwrap_or(until));
        let seconds = (self.rendered_before_ms + this_run) as f64 / 1000.0;
        self.totals.rays as f64 / seconds.max(1e-3)
    }

    fn metadata(&self, id: JobId, ended: u64) -> JobMetadata {
        let submitted = self.times.submitted.unwrap_or(ended);
        let s = self.settings;
        JobMetadata {
            id,
            state: "done",
            scene_sha256: hex(&self.hash),
            frame: self.frame,
            width: s.width,
            height: s.height,
            aa: s.aa,
            max_depth: s.max_depth,
            tile_size: self.tile_size,
            tiles: self.tiles_total,
            priority: self.priority,
            wall_time_ms: ended.saturating_sub(submitted),
            rays: self.totals.rays,
            rays_per_second: self.rays_per_second(ended),
            tiles_per_worker: self.tiles_per_worker.clone(),
            sampler: s.sampling.name(),
            target_error: s.sampling.target_error(),
            samples: self.totals.samples,
            samples_per_pixel: self.totals.samples as f64
                / (u64::from(s.width) * u64::from(s.height)).max(1) as f64,
            estimated_error: self.estimated_error(),
            submitted_unix_ms: submitted,
            started_unix_ms: self.times.started.unwrap_or(submitted),
            ended_unix_ms: ended,
            // Filled in by the store, which computes it from the bytes it writes.
            image_sha256: String::new(),
        }
    }

    fn status(&self, id: JobId, job: &lifecycle::Job) -> JobStatus {
        let state = job.phase.visible();
        let now = unix_ms();
        let end = self.times.ended.filter(|_| state.is_final()).unwrap_or(now);
        let submitted = self.times.submitted.unwrap_or(end);
        let (elapsed_ms, queued_ms) =
            figures::run_times(submitted, self.times.retried, self.times.started, end);
        let total = self.tiles_total;
        let done = if state == JobState::Done {
            total
        } else if let Some(ad) = &self.adaptive {
            if self.tiles_recorded == total {
                total
            } else {
                ad.tiles_done()
            }
        } else {
            self.tiles_recorded
        };
        // An adaptive job does not know how many passes are left, a paused one when
        // it will go on. The others: at the pace of this run's recent tiles.
        let eta_ms =
            (state == JobState::Running && done < total && self.adaptive.is_none() && !self.paused)
                .then(|| self.pace.time_left(self.running_since?, now, total - done))
                .flatten();
        let error = match &job.phase {
            Phase::Ended { error, .. } if state.is_final() => error.clone(),
            _ => None,
        };
        JobStatus {
            id,
            state,
            settings: self.settings,
            priority: self.priority,
            tiles_done: done,
            tiles_total: total,
            rays: self.totals.rays,
            elapsed_ms,
            eta_ms,
            error,
            samples: self.totals.samples,
            // A job cancelled or failed has no image whose error could be estimated.
            estimated_error: self
                .estimated_error()
                .filter(|_| !matches!(state, JobState::Cancelled | JobState::Failed)),
            time_limit_ms: self.time_limit_ms,
            stopped_on_time_limit: self.stopped_on_time_limit,
            paused: self.paused && !state.is_final(),
            warning: None,
            name: self.label.name.clone(),
            submitter: self.label.submitter.clone(),
            submitted_from: self.label.submitted_from.clone(),
            submitted_unix_ms: submitted,
            queued_ms,
            frame: self.frame,
            frames: None,
            sequence: self.sequence,
        }
    }
}

/// A stored job's label, with what an earlier version did not record filled in: its
/// name is `job N`, and who submitted it from where is unknown.
fn restored_label(id: JobId, stored: &Label) -> Label {
    let or = |text: &str, default: String| {
        if text.is_empty() {
            default
        } else {
            text.to_owned()
        }
    };
    Label {
        name: or(&stored.name, format!("job {id}")),
        submitter: or(&stored.submitter, "unknown".into()),
        submitted_from: or(&stored.submitted_from, "unknown".into()),
    }
}

impl WorkerRecord {
    /// Counts a result that arrived at `now`, its tile rendered in `render_us`,
    /// forgetting those older than [`RATE_WINDOW`].
    fn count_result(&mut self, now: Instant, render_us: u64, rays: u64) {
        self.recent.push_back((now, render_us, rays));
        while self
            .recent
            .front()
            .is_some_and(|&(at, _, _)| now.duration_since(at) > RATE_WINDOW)
        {
            self.recent.pop_front();
        }
    }

    /// Rays per second while rendering, over its results of the last [`RATE_WINDOW`]
    /// ([`figures::rendering_rate`]): 0 for a worker that has been idle that long.
    fn current_rate(&self, now: Instant) -> f64 {
        let connected = self.connected;
        figures::rendering_rate(
            self.recent
                .iter()
                .filter(|&&(at, _, _)| now.duration_since(at) <= RATE_WINDOW)
                .map(|&(at, render_us, rays)| {
                    (
                        at.duration_since(connected).as_micros() as u64,
                        render_us,
                        rays,
                    )
                }),
        )
    }

    fn status(&self, id: WorkerId, in_flight: usize, credit: usize) -> WorkerStatus {
        let connected = self.connected.elapsed();
        WorkerStatus {
            id,
            name: self.name.clone(),
            host: self.host.to_string(),
            threads: self.threads,
            tiles_in_flight: in_flight as u32,
            tiles_done: self.tiles_done,
            rays: self.rays,
            connected_ms: connected.as_millis() as u64,
            rays_per_second: self.current_rate(Instant::now()),
            build: self.build.clone(),
            quarantined: self.quarantined.clone(),
            rtt_us: self.rtt_us(),
            credit: credit as u32,
            draining: self.draining,
            disabled: false,
            unresponsive: false,
            key: self.key.as_ref().and_then(super::keys::KeyHold::peer_key),
        }
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Why a job that has ended (`state`) cannot be `verb` (paused, resumed, ...): what
/// would be accepted instead, and for a failed or cancelled job the command that puts
/// it back in the queue, since resuming it is the usual mistake.
pub(super) fn ended_refusal(id: JobId, verb: &str, state: JobState) -> Refusal {
    let accepted = if verb == "resumed" {
        "only a paused job can be"
    } else {
        "only a queued or running job can be"
    };
    let mut refusal = format!(
        "job {id} cannot be {verb}: it is {}, {accepted}",
        state.as_str()
    );
    if matches!(state, JobState::Failed | JobState::Cancelled) {
        refusal.push_str(&format!(
            " (`tessera retry {id}` puts it back in the queue)"
        ));
    }
    Refusal::state(refusal)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_ended_job_refused_says_what_is_accepted_and_how_to_retry_it() {
        assert_eq!(
            ended_refusal(5, "resumed", JobState::Cancelled).message,
            "job 5 cannot be resumed: it is cancelled, only a paused job can be \
             (`tessera retry 5` puts it back in the queue)"
        );
        assert_eq!(
            ended_refusal(5, "paused", JobState::Failed).message,
            "job 5 cannot be paused: it is failed, only a queued or running job can be \
             (`tessera retry 5` puts it back in the queue)"
        );
        assert_eq!(
            ended_refusal(5, "given a new priority", JobState::Done).message,
            "job 5 cannot be given a new priority: it is done, only a queued or running \
             job can be"
        );
        assert_eq!(
            ended_refusal(5, "resumed", JobState::Done).message,
            "job 5 cannot be resumed: it is done, only a paused job can be"
        );
    }

    #[test]
    fn a_workers_compressed_pixels_are_stored_as_sent_unless_padded() {
        let rgb: Vec<u8> = (0..3 * 32 * 32).map(|i| (i % 7) as u8).collect();
        let sent = zstd::bulk::compress(&rgb, 1).unwrap();
        let kept = TilePixels::received(rgb.clone(), sent.clone());
        assert_eq!(
            (kept.rgb.as_slice(), kept.zstd.as_slice()),
            (&rgb[..], &sent[..])
        );

        // The same frame followed by a skippable frame of padding decompresses to the
        // same pixels, and would cost the database far more than the tile: it is
        // compressed again.
        let mut padded = sent.clone();
        padded.extend_from_slice(&[0x50, 0x2a, 0x4d, 0x18]);
        padded.extend_from_slice(&(1u32 << 20).to_le_bytes());
        padded.resize(padded.len() + (1 << 20), 0);
        assert_eq!(decompress(&padded, rgb.len()).unwrap(), rgb);
        let stored = TilePixels::received(rgb.clone(), padded);
        assert!(stored.zstd.len() <= zstd::zstd_safe::compress_bound(rgb.len()));
        assert_eq!(
            zstd::bulk::decompress(&stored.zstd, rgb.len()).unwrap(),
            rgb
        );

        // Raw pixels are compressed for the database.
        let raw = TilePixels::raw(rgb.clone());
        assert_eq!(zstd::bulk::decompress(&raw.zstd, rgb.len()).unwrap(), rgb);
    }

    #[test]
    fn an_event_log_keeps_its_cap_then_counts_what_it_drops_and_keeps_the_end() {
        let mut log = EventLog::new();
        for seq in 1..=EVENT_LOG_CAP {
            assert_eq!(log.number(false), Some(seq));
        }
        for _ in 0..1500 {
            assert_eq!(log.number(false), None);
        }
        assert_eq!(log.dropped, 1500);
        // The end is kept, numbered after those not kept.
        let end = EVENT_LOG_CAP + 1501;
        assert_eq!(log.number(true), Some(end));
        // After a restart the numbering and the count go on from what is stored: the
        // highest number, and the marker's count.
        let restored = EventLog::restored(end, 1500);
        assert_eq!((restored.next_seq, restored.dropped), (end + 1, 1500));
        // Past the cap without an end, the highest number stored is the marker's.
        let restored = EventLog::restored(EVENT_LOG_CAP + 1, 1500);
        assert_eq!(restored.next_seq, EVENT_LOG_CAP + 1501);
        assert_eq!(EventLog::restored(0, 0), EventLog::new());
    }

    #[test]
    fn a_workers_rate_is_while_it_rendered_in_the_last_minute() {
        let mut w = WorkerRecord::new(
            "w".into(),
            std::net::Ipv4Addr::LOCALHOST.into(),
            "build".into(),
            1,
            mpsc::unbounded_channel().0,
            Arc::default(),
        );
        let start = w.connected;
        let at = |s: u64| start + Duration::from_secs(s);
        // 10 s of work at a million rays a second, then idle.
        for s in 1..=10 {
            w.count_result(at(s), 1_000_000, 1_000_000);
        }
        let busy = w.current_rate(at(10));
        assert!((busy - 1e6).abs() < 1.0, "{busy}");
        // Within the minute, idle time does not dilute it (the minute's average would
        // say 10e6 / 60)...
        let later = w.current_rate(at(60));
        assert!((later - 1e6).abs() < 1.0, "{later}");
        // ...and a worker idle for longer than that renders nothing now, whatever it did
        // before (the lifetime average would still say 10e6 / 300).
        assert_eq!(w.current_rate(at(300)), 0.0);
        // A result of 6 M rays rendered in 2 s: 3 M rays a second.
        w.count_result(at(301), 2_000_000, 6_000_000);
        assert!((w.current_rate(at(301)) - 3e6).abs() < 1.0);
        assert_eq!(w.recent.len(), 1, "older results are forgotten");
    }
}
