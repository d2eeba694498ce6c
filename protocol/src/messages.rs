//! Every message after the handshake.

use serde::{Deserialize, Serialize};

use crate::assets::{AssetKey, AssetRef, JobAssets, WorkerCache};
use crate::settings::{Overrides, Settings, TileRect};

/// A job's identity, made by the coordinator.
pub type JobId = u64;

/// A connected worker's identity for the lifetime of its connection, made by the
/// coordinator.
pub type WorkerId = u64;

/// SHA-256 of a scene's JSON text: workers cache scenes under it.
pub type SceneHash = [u8; 32];

/// A job as submitted.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct JobSpec {
    /// The scene file's JSON text.
    pub scene: String,
    pub overrides: Overrides,
    /// Higher runs first; jobs of equal priority share the farm (see docs/protocol.md).
    pub priority: i32,
    /// How the workers' results are checked before they count.
    pub verification: Verification,
    /// Milliseconds of rendering after which an adaptive job stops at the deepest rung
    /// it has rendered, whatever its target (see docs/protocol.md); `None`: no limit.
    pub time_limit_ms: Option<u64>,
    /// What listings call the job (`tessera submit` gives the scene file's stem by
    /// default). Any text; the coordinator keeps at most 200 characters of it.
    pub name: String,
    /// Who submitted the job, as the client claims it (`tessera submit` gives
    /// `$USER@hostname` by default). Nothing checks it: the coordinator also records
    /// the address the submission came from, which the client cannot choose.
    pub submitter: String,
    /// The frame of the scene to render, from 1 (`tessera submit --frame K`; 1 for a
    /// scene without animation). A frame the scene does not have is refused.
    pub frame: u32,
    /// A sequence job instead: frames `first..=last` of an animated scene, each
    /// rendered as a frame job of its own (`frame` must then be 1). A range the scene
    /// does not have, or of more than [`MAX_SEQUENCE_FRAMES`] frames, is refused.
    pub frames: Option<FrameRange>,
    /// Every file the scene names, bound to its content (at most
    /// [`MAX_JOB_ASSETS`](crate::MAX_JOB_ASSETS)), uploaded first: a file the
    /// coordinator lacks gets [`AssetAnswer::SubmitLacking`](crate::AssetAnswer).
    pub assets: Vec<AssetRef>,
    /// Jobs that must be done before this one starts (`tessera submit --after JOB`, at
    /// most [`MAX_AFTER`]): it waits ([`JobState::Waiting`]) until every one of them
    /// is done, and fails, naming it, if one fails or is cancelled. Each must be a job
    /// the coordinator has, so a dependency always points to an older job and no cycle
    /// can form.
    pub after: Vec<JobId>,
    /// Worker tags the job requires ([`check_tags`]): its tiles, confirmations
    /// included, go only to workers that have every one of them. Empty: any worker.
    pub require: Vec<String>,
}

/// The most jobs a job may wait for.
pub const MAX_AFTER: usize = 256;

/// Frames `first..=last` of an animated scene, from 1.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameRange {
    pub first: u32,
    pub last: u32,
}

/// The most frames a sequence job may have (a scene has at most as many).
pub const MAX_SEQUENCE_FRAMES: u32 = 100_000;

/// The most frames of one sequence job rendering at once: a coordinator holds at most
/// this many frames' pixels of a sequence, and a worker keeps at most this many frames'
/// prepared scenes of one scene.
pub const MAX_ACTIVE_FRAMES: usize = 8;

/// A sequence job's frames, as reported to clients.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameProgress {
    pub first: u32,
    pub last: u32,
    /// The scene's frame count: frames are named by it (`frame_0007.png`, as
    /// `tessera render --frames` names them).
    pub scene_frames: u32,
    pub done: u32,
    /// Frames queued or running now.
    pub active: u32,
    pub pending: u32,
    pub cancelled: u32,
    /// Frames done one after another from the first: what the preview plays.
    pub done_prefix: u32,
    /// The failed frames, lowest first, each with its frame job's error (at most
    /// [`FAILED_FRAMES_LISTED`]; `failed` counts them all).
    pub failed: u32,
    pub failures: Vec<FrameFailure>,
}

/// The most failed frames a status lists with their errors.
pub const FAILED_FRAMES_LISTED: usize = 100;

/// A frame that failed, and why.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameFailure {
    pub frame: u32,
    /// The frame job that failed (its events say more).
    pub job: JobId,
    pub error: String,
}

/// How a job's tile results are checked before they count (docs/reliability.md has the
/// guarantees in numbers). Every result is spot-checked either way: the coordinator
/// renders a few of its pixels, chosen at random once the result has arrived.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Verification {
    /// Spot checks, and a small random share of tiles rendered again by another machine
    /// and compared byte for byte.
    #[default]
    Sampled,
    /// Spot checks, and every tile rendered by two different machines whose results
    /// must be identical: a corrupted tile counts only if two machines return the
    /// same wrong bytes.
    Full,
}

impl Verification {
    /// The lowercase name used on the command line and in listings.
    pub fn name(self) -> &'static str {
        match self {
            Verification::Sampled => "sampled",
            Verification::Full => "full",
        }
    }
}

/// A client's request. Each gets exactly one [`ClientResponse`], in order.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ClientRequest {
    Submit(JobSpec),
    Status {
        job: JobId,
    },
    List,
    Cancel {
        job: JobId,
    },
    /// A slice of the finished job's PNG, starting at byte `offset`.
    Fetch {
        job: JobId,
        offset: u64,
    },
    Workers,
    /// The job's status as soon as it has more than `after_tiles` tiles done (but at
    /// most every 50 ms) or has ended, or after one second at the latest: progress
    /// without polling, and the end of a job noticed at once.
    Watch {
        job: JobId,
        after_tiles: u32,
    },
    /// Forget a job that has ended: its image, scene and records are removed from the
    /// coordinator's disk. A job still queued or running must be cancelled first.
    Delete {
        job: JobId,
    },
    /// A new adaptive job from a finished one: the same scene, size, tiling and depth,
    /// with target `target_milli` (thousandths of a level), cap `aa` (the old job's if
    /// `None`) and time limit, whose tiles start from the old job's final block states
    /// instead of from nothing. Answered with `Submitted` and the new job's id; the old
    /// job stays as it was.
    Refine {
        job: JobId,
        target_milli: u32,
        aa: Option<u32>,
        time_limit_ms: Option<u64>,
    },
    /// Hand out no new tile of a queued or running job (tiles already out may finish
    /// and count) until `Resume`. Answered with the job's `Job` status once the pause
    /// is stored; pausing a paused job changes nothing and is answered the same.
    Pause {
        job: JobId,
    },
    /// Make a paused job schedulable again. Answered with the job's `Job` status once
    /// stored; resuming a job that is not paused changes nothing.
    Resume {
        job: JobId,
    },
    /// Give a queued or running job a new priority (higher runs first): the next tiles
    /// handed out follow it. Answered with the job's `Job` status once stored.
    SetPriority {
        job: JobId,
        priority: i32,
    },
    /// Have a worker finish the tiles it holds and exit without reconnecting, as it
    /// does on SIGTERM. `worker` is a connected worker's id (as `Workers` lists it) or
    /// its name (unique among connected workers). Answered with `Workers` holding that
    /// one worker once it was told, so that the client can say which.
    DrainWorker {
        worker: String,
    },
    /// Give the machine no new tile (the tiles it holds finish and count); its workers
    /// stay connected. Kept by machine name and stored: a worker of that name that
    /// connects later, even to a restarted coordinator, is disabled too, until
    /// `EnableWorker`. `worker` is an id or a name as in `DrainWorker`. Answered with
    /// `Workers` holding the worker of that name once stored.
    DisableWorker {
        worker: String,
    },
    /// Undo `DisableWorker`: the machine takes tiles again. Answered with `Workers`
    /// holding the worker of that name (none if it is not connected) once stored;
    /// enabling a machine that is not disabled changes nothing.
    EnableWorker {
        worker: String,
    },
    /// The job's event log from sequence number `after` on (exclusive; 0 for the
    /// start), at most [`EVENTS_PER_PAGE`] events: answered with `Events`. A client
    /// follows a job by asking again with the last sequence number it got.
    Events {
        job: JobId,
        after: u64,
    },
    /// Put a failed or cancelled job back in the queue under the same id: the tiles it
    /// has stored count, the others are rendered. Answered with the job's `Job` status
    /// once stored.
    Retry {
        job: JobId,
    },
    /// Render the named tiles of a queued or running job again, wherever they are
    /// (waiting, out on a worker, or done): for a machine an operator suspects.
    /// Answered with the job's `Job` status once stored.
    Requeue {
        job: JobId,
        tiles: Vec<u32>,
    },
    /// A slice of a done frame's PNG of a sequence job, starting at byte `offset`:
    /// answered with `ImageChunk` (its `job` the sequence).
    FetchFrame {
        job: JobId,
        frame: u32,
        offset: u64,
    },
    /// Render a done, failed or cancelled frame of a sequence job again, alone (a new
    /// frame job replaces the old one). Answered with the sequence's `Job` status.
    RequeueFrame {
        job: JobId,
        frame: u32,
    },
    /// About the files scenes name: which the coordinator lacks, an upload's chunk.
    Assets(crate::AssetRequest),
}

/// The most events one `Events` answer carries.
pub const EVENTS_PER_PAGE: usize = 1000;

/// One entry of a job's event log.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct JobEvent {
    /// Increasing within the job, from 1; a page is asked for after one of them.
    pub seq: u64,
    /// When it happened, in milliseconds since the Unix epoch (the coordinator's clock).
    pub unix_ms: u64,
    /// What happened, one lowercase word or two joined by `_` (`submitted`,
    /// `tile_assigned`, `tile_done`, `paused`, `done`...; docs/operations.md lists them).
    pub kind: String,
    /// The particulars, in one line of text.
    pub detail: String,
}

/// The coordinator's answer to a [`ClientRequest`].
///
/// `Job` is the largest variant by far; it is not boxed because an answer is made once
/// per request and moved straight into the codec: its size costs nothing measurable,
/// and a box would only add an allocation.
#[expect(
    clippy::large_enum_variant,
    reason = "an answer is made once per request and moved into the codec (above)"
)]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ClientResponse {
    Submitted {
        job: JobId,
    },
    Job(JobStatus),
    Jobs(Vec<JobStatus>),
    Cancelled {
        job: JobId,
    },
    /// `bytes` are the PNG's bytes `offset .. offset + bytes.len()` of `total`.
    ImageChunk {
        job: JobId,
        total: u64,
        offset: u64,
        bytes: Vec<u8>,
    },
    Workers(Vec<WorkerStatus>),
    /// The request was refused: what kind of refusal, and why in one line.
    Error(Refusal),
    Deleted {
        job: JobId,
    },
    /// A page of a job's event log, oldest first (see [`ClientRequest::Events`]); fewer
    /// than [`EVENTS_PER_PAGE`] events means the end of the log for now.
    Events {
        job: JobId,
        events: Vec<JobEvent>,
    },
    /// About files ([`ClientRequest::Assets`], or a submission naming files the
    /// coordinator lacks).
    Assets(crate::AssetAnswer),
}

/// What kind of refusal an [`ClientResponse::Error`] is: what a program decides on (to
/// retry, to skip, to report), so that no decision ever reads the message's text.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum RefusalKind {
    /// The request is not valid as sent (a scene or setting that fails its checks, a
    /// verb that does not apply to this kind of job, a malformed frame): sending it
    /// again changes nothing.
    Invalid,
    /// No such job, frame or worker on this coordinator.
    NotFound,
    /// The job or frame is not in a state that allows it: no image yet, already ended,
    /// being deleted. It may be allowed once the job has moved on.
    State,
    /// One of the coordinator's limits on what is queued or running would be passed:
    /// allowed again once some work has finished.
    Limit,
    /// The coordinator cannot do it now (shutting down, storage unavailable or slow):
    /// the same request may succeed later.
    Unavailable,
    /// The coordinator failed at it: its storage could not write or read what the
    /// request needs (a disk error, a damaged file). The message says what.
    Internal,
}

impl RefusalKind {
    /// The lowercase name used in JSON output and logs.
    pub fn as_str(self) -> &'static str {
        match self {
            RefusalKind::Invalid => "invalid",
            RefusalKind::NotFound => "not_found",
            RefusalKind::State => "state",
            RefusalKind::Limit => "limit",
            RefusalKind::Unavailable => "unavailable",
            RefusalKind::Internal => "internal",
        }
    }
}

/// A refused request: its kind, and one line of English to show a user as it is.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Refusal {
    pub kind: RefusalKind,
    pub message: String,
}

impl Refusal {
    pub fn new(kind: RefusalKind, message: impl Into<String>) -> Refusal {
        Refusal {
            kind,
            message: message.into(),
        }
    }

    /// [`RefusalKind::Invalid`].
    pub fn invalid(message: impl Into<String>) -> Refusal {
        Refusal::new(RefusalKind::Invalid, message)
    }

    /// [`RefusalKind::NotFound`].
    pub fn not_found(message: impl Into<String>) -> Refusal {
        Refusal::new(RefusalKind::NotFound, message)
    }

    /// [`RefusalKind::State`].
    pub fn state(message: impl Into<String>) -> Refusal {
        Refusal::new(RefusalKind::State, message)
    }

    /// [`RefusalKind::Limit`].
    pub fn limit(message: impl Into<String>) -> Refusal {
        Refusal::new(RefusalKind::Limit, message)
    }

    /// [`RefusalKind::Unavailable`].
    pub fn unavailable(message: impl Into<String>) -> Refusal {
        Refusal::new(RefusalKind::Unavailable, message)
    }

    /// [`RefusalKind::Internal`].
    pub fn internal(message: impl Into<String>) -> Refusal {
        Refusal::new(RefusalKind::Internal, message)
    }

    /// "no job N on this coordinator", the answer for every request on an unknown job.
    pub fn unknown_job(job: JobId) -> Refusal {
        Refusal::not_found(format!("no job {job} on this coordinator"))
    }

    /// The same refusal with `context` before its message ("cannot refine job 4: ...").
    pub fn context(self, context: impl std::fmt::Display) -> Refusal {
        Refusal {
            kind: self.kind,
            message: format!("{context}: {}", self.message),
        }
    }
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for Refusal {}

/// Where a job is in its life.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum JobState {
    Queued,
    Running,
    Done,
    Failed,
    Cancelled,
    /// Stored, waiting for the jobs it was submitted `after` to be done
    /// ([`JobStatus::waiting_for`] says which are not yet).
    Waiting,
}

impl JobState {
    /// The lowercase name used in listings and JSON output.
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Done => "done",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
            JobState::Waiting => "waiting",
        }
    }

    /// Whether the job will change no more.
    pub fn is_final(self) -> bool {
        matches!(
            self,
            JobState::Done | JobState::Failed | JobState::Cancelled
        )
    }
}

/// A job's progress, as reported to clients.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobStatus {
    pub id: JobId,
    pub state: JobState,
    pub settings: Settings,
    pub priority: i32,
    pub tiles_done: u32,
    pub tiles_total: u32,
    /// Rays traced so far.
    pub rays: u64,
    /// Since submission (or the last retry: a retry starts a new run), to now or to
    /// the job's end.
    pub elapsed_ms: u64,
    /// Estimated time left, once some tiles are done.
    pub eta_ms: Option<u64>,
    /// Why the job failed.
    pub error: Option<String>,
    /// Camera samples taken for the finished tiles: what adaptive sampling saves shows
    /// here, next to the time.
    pub samples: u64,
    /// The renderer's own estimate of the image's error, in 8-bit levels: the root mean
    /// square over the image's pixels of each pixel's standard error. `None` until
    /// every pixel has an estimate (every tile in, or an adaptive job's first pass
    /// done: an estimate over the first tiles would read better than the image will),
    /// and always with one sample per pixel (`aa` 1), where the spread of the samples
    /// cannot be measured.
    pub estimated_error: Option<f64>,
    /// The job's time limit in milliseconds of rendering, if it has one.
    pub time_limit_ms: Option<u64>,
    /// The job ended on its time limit before its image met the target: its image is
    /// the deepest rung rendered, with `estimated_error`.
    pub stopped_on_time_limit: bool,
    /// An operator paused the job: no new tile of it is handed out. `state` stays
    /// `Queued` or `Running` (tiles out when it was paused may still finish).
    pub paused: bool,
    /// Why the job cannot progress now, in one line, while it is queued or running
    /// and no connected worker may take tiles (none is connected, or all are disabled,
    /// draining or quarantined). `None` otherwise.
    pub warning: Option<String>,
    /// The job's name, as submitted.
    pub name: String,
    /// Who submitted it, as the client claimed it.
    pub submitter: String,
    /// The address the submission came from, as the coordinator saw it.
    pub submitted_from: String,
    /// When it was submitted, in milliseconds since the Unix epoch.
    pub submitted_unix_ms: u64,
    /// How long it waited in the queue before its first tile went out (of its current
    /// run, since a retry); `None` while no tile has gone out. `elapsed_ms` less this is
    /// the time it took to render.
    pub queued_ms: Option<u64>,
    /// The frame of the scene the job renders, from 1 (a sequence job's first frame).
    pub frame: u32,
    /// A sequence job's frames; `None` for a job of one frame. A sequence's `tiles_*`,
    /// `rays` and `samples` add up its frames'.
    pub frames: Option<FrameProgress>,
    /// For a frame job of a sequence: the sequence.
    pub sequence: Option<JobId>,
    /// The files its scene names.
    pub assets: JobAssets,
    /// The jobs it was submitted after ([`JobSpec::after`]).
    pub after: Vec<JobId>,
    /// Those of them not yet done, while it is [`JobState::Waiting`]; empty otherwise.
    pub waiting_for: Vec<JobId>,
    /// The worker tags it requires, sorted (see [`JobSpec::require`]).
    pub require: Vec<String>,
}

impl JobStatus {
    /// The mean camera samples per pixel of the image, known once the job is done
    /// (`None` before). For a sequence, per pixel of a frame: its `samples` add up its
    /// frames', so they are divided by the pixels of all of them, and an `aa 2` grid
    /// sequence shows 4 whatever its length.
    pub fn samples_per_pixel(&self) -> Option<f64> {
        (self.state == JobState::Done).then(|| {
            let frames = self
                .frames
                .as_ref()
                .map_or(1, |f| u64::from(f.last.saturating_sub(f.first)) + 1);
            let pixels = u64::from(self.settings.width) * u64::from(self.settings.height);
            self.samples as f64 / (pixels * frames).max(1) as f64
        })
    }
}

/// A connected worker, as reported to clients.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorkerStatus {
    pub id: WorkerId,
    pub name: String,
    pub threads: u32,
    pub tiles_in_flight: u32,
    pub tiles_done: u64,
    pub rays: u64,
    pub connected_ms: u64,
    /// Rays per second while rendering: its results' rays of the last minute over the
    /// time it spent rendering them; 0 once idle for a minute.
    pub rays_per_second: f64,
    /// The worker's renderer build, as its hello gave it.
    pub build: String,
    /// Why the worker gets no more tiles, once one of its results was found wrong.
    pub quarantined: Option<String>,
    /// The round-trip time last measured to the worker, in microseconds.
    pub rtt_us: Option<u64>,
    /// Tiles the worker may hold at once: enough to keep its threads busy across the
    /// round trip.
    pub credit: u32,
    /// The worker is finishing what it holds before it exits (told by an operator or
    /// shutting down on its own): it gets no new tile.
    pub draining: bool,
    /// An operator disabled its machine: it gets no new tile until enabled.
    pub disabled: bool,
    /// It holds tiles whose leases ran out and has returned no result for longer than
    /// its progress allowance (its heartbeats still come): it gets no new tile, and its
    /// tiles are rendered elsewhere, until it returns a result.
    pub unresponsive: bool,
    /// The worker secret it proved, if the coordinator asks workers for one.
    pub key: Option<PeerKey>,
    /// The IP address it connected from, as the coordinator saw it: what tells apart
    /// two machines that asked for one name (the second got a suffixed one).
    pub host: String,
    /// Its files, as it last reported them; `None` before its first report.
    pub cache: Option<WorkerCache>,
    /// Its tags, sorted, as its hello gave them: the jobs it may render.
    pub tags: Vec<String>,
}

/// Which of the coordinator's secrets a peer proved: after a rotation, a peer still on
/// the previous secret is the one whose token file has yet to be replaced.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PeerKey {
    pub id: crate::KeyId,
    pub standing: KeyStanding,
}

/// Where a secret stands on the coordinator.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum KeyStanding {
    /// The secret its token file holds now.
    Current,
    /// The one it held before the last reload, accepted until the overlap window
    /// closes (then the peers still using it are disconnected).
    Previous,
}

impl KeyStanding {
    /// "current" or "previous", as listings and logs name it.
    pub fn as_str(self) -> &'static str {
        match self {
            KeyStanding::Current => "current",
            KeyStanding::Previous => "previous",
        }
    }
}

impl std::fmt::Display for PeerKey {
    /// `3f2a91c0 (current)`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({})", self.id, self.standing.as_str())
    }
}

/// A file the canary scene names (its mesh), sent whole with the canary.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CanaryFile {
    /// The name the scene gives it (`file`).
    pub name: String,
    pub bytes: Vec<u8>,
}

/// One render of the canary: the settings and the rectangle of the canary scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CanaryRender {
    pub settings: Settings,
    pub rect: TileRect,
}

/// Coordinator to worker.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ToWorker {
    /// A scene the worker has not seen; sent once per worker before its first tile,
    /// with the files it names: those the worker's cache lacks it fetches
    /// ([`FromWorker::FetchAsset`]) before it renders the scene's tiles.
    Scene {
        hash: SceneHash,
        scene: String,
        assets: Vec<AssetRef>,
    },
    /// Render one tile of a job whose scene the worker has.
    Render {
        job: JobId,
        tile: u32,
        scene: SceneHash,
        /// The frame of the scene to render, from 1 (1 for a scene without animation):
        /// the worker computes it from the scene it has.
        frame: u32,
        settings: Settings,
        rect: TileRect,
    },
    /// Drop the job's tiles not yet rendered; their results are no longer wanted.
    Cancel { job: JobId },
    /// No active job uses this scene any more: the worker may drop it from its cache.
    /// A later job with the same scene sends it again.
    ForgetScene { hash: SceneHash },
    /// The coordinator is alive. Sent every second, so that a worker cut off from it
    /// notices (it hears nothing) and reconnects instead of waiting forever.
    Heartbeat,
    /// The first message to a worker, before any tile: render this small fixed scene
    /// once per entry of `renders` and answer with [`FromWorker::CanaryDone`]. The
    /// bytes must equal the coordinator's own render, or the worker is refused.
    Canary {
        scene: String,
        /// The files the canary scene names, whole: the canary comes before the worker
        /// may fetch anything by hash.
        files: Vec<CanaryFile>,
        renders: Vec<CanaryRender>,
    },
    /// The worker is refused and the connection closes: do not reconnect, `reason`
    /// says why in one line.
    Refuse { reason: String },
    /// Answer at once with [`FromWorker::Pong`] carrying the same `token`: the
    /// coordinator measures the round trip to size the worker's credit.
    Ping { token: u64 },
    /// Advance the blocks of one tile of an adaptive job to `rung` of the threshold
    /// ladder, starting from `previous` (the state the tile's last pass returned) or
    /// from nothing, and answer with [`FromWorker::Advanced`]. The worker keeps nothing
    /// between passes: the coordinator holds every tile's state, so any worker can take
    /// any pass of any tile, and a tile sent again after its worker was lost starts
    /// from the same state and gives the same bytes.
    Advance {
        job: JobId,
        tile: u32,
        scene: SceneHash,
        /// The frame of the scene, as in [`ToWorker::Render`].
        frame: u32,
        settings: Settings,
        /// Block-aligned: `x` and `y` multiples of 8, the right and bottom edges on a
        /// multiple of 8 or on the frame's edge.
        rect: TileRect,
        /// The job's pass, echoed in the answer: an answer to an earlier pass counts
        /// for nothing.
        pass: u32,
        rung: u32,
        /// The tile's block states (see [`FromWorker::Advanced`]'s `state`), or `None`
        /// to start from the first samples.
        previous: Option<Vec<u8>>,
    },
    /// An operator asked the worker to drain: finish the tiles it holds, then close
    /// the connection and exit without reconnecting, exactly as on SIGTERM (it answers
    /// with [`FromWorker::Draining`] first).
    Drain,
    /// The worker joined (its canary passed) under `name`: the name its hello gave,
    /// or, when a worker of another host is connected under that name, the name with
    /// a suffix (`NAME-2`, ...). Sent once, before any tile.
    Joined { name: String },
    /// Bytes `offset .. offset + bytes.len()` of a file a worker asked for; the last
    /// chunk ends at the key's size.
    AssetChunk {
        key: AssetKey,
        offset: u64,
        bytes: Vec<u8>,
    },
    /// A file a worker asked for that the coordinator cannot give (it lost it, or its
    /// bytes no longer match their SHA-256): `reason` in one line.
    AssetUnavailable { key: AssetKey, reason: String },
}

/// Worker to coordinator.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum FromWorker {
    /// A rendered tile: RGB8 pixels, rows top to bottom.
    TileDone {
        job: JobId,
        tile: u32,
        rgb: Vec<u8>,
        rays: u64,
        render_us: u64,
        /// Camera samples taken for the tile.
        samples: u64,
        /// The sum over the tile's pixels of the squared estimated error of each, in
        /// 8-bit levels squared (0 with one sample per pixel: no estimate). Sums, so
        /// that the coordinator can combine tiles into the image's RMS estimate.
        error_sq_sum: f64,
    },
    /// The tile could not be rendered (the scene did not load, the tile is outside the
    /// frame); `message` says why.
    TileFailed {
        job: JobId,
        tile: u32,
        message: String,
    },
    /// The worker is shutting down: send it nothing more. It finishes what it holds.
    Draining,
    /// The worker is alive. Sent every second; a worker silent for longer than the
    /// coordinator's heartbeat timeout loses its tiles.
    Heartbeat,
    /// The canary's renders, one RGB8 buffer per entry of [`ToWorker::Canary`]'s
    /// `renders`, in order; or why the worker could not render them.
    CanaryDone {
        images: Result<Vec<Vec<u8>>, String>,
    },
    /// The answer to [`ToWorker::Ping`].
    Pong { token: u64 },
    /// A rendered tile like [`FromWorker::TileDone`], its RGB8 pixels compressed as
    /// one zstd frame (about 12 to 15 times smaller for rendered images: what lets
    /// dozens of workers share a 100 Mbit/s link). It must decompress to exactly the
    /// tile's width × height × 3 bytes.
    TileDoneZstd {
        job: JobId,
        tile: u32,
        zstd: Vec<u8>,
        rays: u64,
        render_us: u64,
        samples: u64,
        error_sq_sum: f64,
    },
    /// An adaptive tile advanced to `rung` ([`ToWorker::Advance`]): its pixels at that
    /// rung and the blocks' new state, which the coordinator keeps for the next pass.
    Advanced {
        job: JobId,
        tile: u32,
        /// As in the `Advance` it answers.
        pass: u32,
        rung: u32,
        /// The tile's RGB8 pixels at `rung`, rows top to bottom, as one zstd frame; it
        /// must decompress to exactly width × height × 3 bytes.
        zstd: Vec<u8>,
        /// The blocks' state: the renderer's `Vec<BlockState>` (levels and per-pixel
        /// sums, blocks row by row) encoded like a message, then compressed as one
        /// zstd frame. It must decompress within a bound set by the tile's size and
        /// `aa` (`verify::adaptive::state_bound`).
        state: Vec<u8>,
        /// Rays traced in this pass (not before).
        rays: u64,
        render_us: u64,
    },
    /// Bytes of a file a scene names, from `offset` (at most
    /// [`ASSET_CHUNK`](crate::ASSET_CHUNK)): answered with [`ToWorker::AssetChunk`] or
    /// [`ToWorker::AssetUnavailable`].
    FetchAsset { key: AssetKey, offset: u64 },
    /// The worker's files now: sent after it joined and whenever they changed, at
    /// most once a second; listings show it.
    Cache(WorkerCache),
}
