//! The records the core keeps and the small values it passes around: what the daemon
//! keeps of a job ([`JobRecord`]) and of a connected worker ([`WorkerRecord`]), where a
//! job's event log stands, a result's pixels and cost, a job admitted and an operator's
//! controls. They stand apart from the methods that use them so that every part of
//! the core takes them from one place, and no two parts need each other for them.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use protocol::{
    JobId, JobState, JobStatus, SceneHash, Settings, TileRect, ToWorker, Verification, WorkerId,
    WorkerStatus,
};
use scheduler::lifecycle::{self, Phase};
use scheduler::Millis;
use tokio::sync::mpsc;

use super::figures;
use crate::db::{Label, Times, Totals};
use crate::server::adaptive::{AdaptiveJob, Answer};
use crate::server::keys::KeyHold;
use crate::store::JobMetadata;

/// What the daemon keeps of a job beside its lifecycle.
pub struct JobRecord {
    /// A pass of a studio view: nothing of it is stored or listed, its tiles go to
    /// the view's page, and it is forgotten once it ends (docs/studio.md).
    pub interactive: bool,
    /// The studio view and pass it renders for, known before any tile goes out.
    pub owner: Option<crate::studio::views::Owner>,
    /// The scene text, while the job is active (workers may still ask for it).
    pub scene: Option<Arc<str>>,
    /// The files the scene names, bound to their content: sent with the scene.
    pub assets: Arc<[protocol::AssetRef]>,
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
    /// The jobs it was submitted after.
    pub after: Vec<JobId>,
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
    /// The worker tags it requires, sorted: its tiles go only to workers with them all.
    pub require: Vec<String>,
    /// Its results accepted in this run of the coordinator: what its waiting work is
    /// estimated from.
    pub measured: super::pools::Measured,
}

impl JobRecord {
    /// Counts a tile of `pixels` pixels that took `samples` samples, with its sum of
    /// squared error estimates if known.
    /// Takes back what an accepted tile added to the totals.
    pub(super) fn remove_cost(&mut self, a: &Accepted, pixels: u64) {
        let t = &mut self.totals;
        t.rays = t.rays.saturating_sub(a.rays);
        t.samples = t.samples.saturating_sub(a.samples);
        if let Some(e) = a.error_sq_sum {
            t.error_sq_sum -= e;
            t.error_pixels = t.error_pixels.saturating_sub(pixels);
        }
    }

    pub(super) fn add_cost(
        &mut self,
        rays: u64,
        samples: u64,
        error_sq_sum: Option<f64>,
        pixels: u64,
    ) {
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

    pub(super) fn metadata(&self, id: JobId, ended: u64) -> JobMetadata {
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

    /// The job's status at `now` (milliseconds since the Unix epoch); `pass_rung` is
    /// the rung of an adaptive job's pass under way.
    pub(super) fn status(
        &self,
        id: JobId,
        job: &lifecycle::Job,
        pass_rung: Option<u32>,
        now: u64,
    ) -> JobStatus {
        let state = job.phase.visible();
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
                pass_rung.map_or(0, |rung| ad.tiles_done(rung))
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
            assets: protocol::JobAssets::of(&self.assets),
            after: self.after.clone(),
            waiting_for: Vec::new(),
            require: self.require.clone(),
        }
    }
}

/// A stored job's label, with what an earlier version did not record filled in: its
/// name is `job N`, and who submitted it from where is unknown.
pub(super) fn restored_label(id: JobId, stored: &Label) -> Label {
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

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
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
    pub(super) fn number(&mut self, always: bool) -> Option<u64> {
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
    pub(super) machine: Arc<str>,
    pub(super) rays: u64,
    pub(super) samples: u64,
    pub(super) error_sq_sum: Option<f64>,
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
    /// The files the scene names, bound to their content (checked present).
    pub assets: Vec<protocol::AssetRef>,
    /// The scene's frame count.
    pub frame_count: u32,
    /// The jobs it waits for (`JobSpec::after`).
    pub after: Vec<JobId>,
    /// The worker tags it requires, checked and sorted.
    pub require: Vec<String>,
}

/// A connected worker.
pub struct WorkerRecord {
    /// Unique among the connected workers ([`names`](super::names)): the name its hello
    /// gave, or that name with a suffix when a worker of another host holds it.
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
    pub(super) rtts: VecDeque<u64>,
    /// Its results of the last [`RATE_WINDOW`]: when each arrived, how long its tile
    /// took to render (µs) and its rays. Its rate is theirs while it rendered, not a
    /// lifetime average, nor one that idle time dilutes.
    pub(super) recent: VecDeque<(Instant, u64, u64)>,
    /// Its mean time per tile on one thread, in microseconds (moving average).
    pub(super) tile_us: Option<f64>,
    /// The pace last given to the scheduler: (rtt, tile time) in ms.
    pace: Option<(Millis, Millis)>,
    /// The worker secret it proved, if workers prove one: listings say which.
    pub key: Option<KeyHold>,
    /// Its files, as it last reported them.
    pub cache: Option<protocol::WorkerCache>,
    /// Its tags, sorted, as its hello gave them (checked): the pools it renders for.
    pub tags: Vec<String>,
}

/// A worker's rays per second are those of its results of this last while, over the
/// time it spent rendering them.
const RATE_WINDOW: Duration = Duration::from_secs(60);

/// Round trips kept per worker: the smallest of them is its round-trip time (the
/// others waited behind results in the socket buffers).
pub(super) const RTTS_KEPT: usize = 8;

impl WorkerRecord {
    /// A worker connected at `connected`.
    pub fn new(
        connected: Instant,
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
            connected,
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
            cache: None,
            tags: Vec::new(),
        }
    }

    fn rtt_us(&self) -> Option<u64> {
        self.rtts.iter().copied().min()
    }

    /// The pace to tell the scheduler, if it changed enough to matter (a fifth).
    pub(super) fn new_pace(&mut self) -> Option<(Millis, Millis)> {
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

impl WorkerRecord {
    /// Counts a result that arrived at `now`, its tile rendered in `render_us`,
    /// forgetting those older than [`RATE_WINDOW`].
    pub(super) fn count_result(&mut self, now: Instant, render_us: u64, rays: u64) {
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
    pub(super) fn current_rate(&self, now: Instant) -> f64 {
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

    /// The worker's status at `now`.
    pub(super) fn status(
        &self,
        id: WorkerId,
        in_flight: usize,
        credit: usize,
        now: Instant,
    ) -> WorkerStatus {
        let connected = now.saturating_duration_since(self.connected);
        WorkerStatus {
            id,
            name: self.name.clone(),
            host: self.host.to_string(),
            threads: self.threads,
            tiles_in_flight: in_flight as u32,
            tiles_done: self.tiles_done,
            rays: self.rays,
            connected_ms: connected.as_millis() as u64,
            rays_per_second: self.current_rate(now),
            build: self.build.clone(),
            quarantined: self.quarantined.clone(),
            rtt_us: self.rtt_us(),
            credit: credit as u32,
            draining: self.draining,
            disabled: false,
            unresponsive: false,
            key: self.key.as_ref().and_then(KeyHold::peer_key),
            cache: self.cache.clone(),
            tags: self.tags.clone(),
        }
    }
}

/// How the core closes a worker's connection: its session wakes up and ends, with the
/// reason.
#[derive(Default)]
pub struct Dropped {
    wake: tokio::sync::Notify,
    why: std::sync::Mutex<String>,
}

impl Dropped {
    pub(super) fn drop_with(&self, why: &str) {
        *self.why.lock().unwrap_or_else(|e| e.into_inner()) = why.to_owned();
        self.wake.notify_one();
    }

    /// Once the worker is dropped: why.
    pub async fn wait(&self) -> String {
        self.wake.notified().await;
        self.why.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

/// A result waiting for another machine's identical one.
pub struct Held {
    pub(super) worker: WorkerId,
    pub(super) machine: String,
    pub(super) pixels: TilePixels,
    pub(super) cost: Cost,
    /// An adaptive answer's state.
    pub(super) answer: Option<Answer>,
}

impl Held {
    /// Whether another result is the same: its pixels, and an adaptive answer's state.
    pub(super) fn same(&self, rgb: &[u8], answer: Option<&Answer>) -> bool {
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
pub(super) fn decompress(bytes: &[u8], capacity: usize) -> std::io::Result<Vec<u8>> {
    DECOMPRESSOR.with(|d| {
        let mut d = d.borrow_mut();
        if d.is_none() {
            *d = Some(zstd::bulk::Decompressor::new()?);
        }
        d.as_mut().expect("made above").decompress(bytes, capacity)
    })
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

pub(super) fn to_render_rect(r: TileRect) -> render::Rect {
    render::Rect {
        x: r.x,
        y: r.y,
        width: r.width,
        height: r.height,
    }
}

pub(super) fn rect_pixels(r: TileRect) -> u64 {
    u64::from(r.width) * u64::from(r.height)
}
