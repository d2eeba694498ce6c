//! A farm of thousands of workers, simulated in virtual time around the real core.
//!
//! One machine cannot host a farm of thousands of workers, but the coordinator's core
//! (the tile [`Scheduler`] and the job [`Lifecycle`]) owns no socket, clock, file or
//! thread, so it can be driven by a discrete-event simulation instead: [`run`] feeds
//! both state machines the same events in the same order as the daemon (the
//! coordinator) would, from simulated clients, workers with heterogeneous speeds that
//! crash, hang, reconnect and join, over links with latency, and a simulated disk that
//! fails now and then; and it carries out their actions the way the daemon does. Time
//! is virtual (a binary heap of timed events), so a run of hours of farm time takes
//! seconds, and a seed names one run exactly.
//!
//! What is modelled, mirroring the daemon, its persistence thread, the client and the
//! worker:
//! - **Coordinator**: every event handed over with the virtual clock in milliseconds,
//!   and a `Timeout` to both machines (the tile scheduler first) when the earlier of
//!   [`Scheduler::next_deadline`] and [`Lifecycle::next_deadline`] comes (the daemon's
//!   timer, re-armed after every call); `WorkerJoined` when a worker's hello arrives
//!   (under its machine's name), its `Accepted` sent first; `Heartbeat` and `TileDone`
//!   as they arrive; `WorkerLeft` when a connection closes, and right after a
//!   `DropWorker` (the daemon closes the connection, whose task then reports it).
//!   Messages on a connection the coordinator dropped are not read.
//! - **The two machines glued as the daemon glues them**: a submission is checked by
//!   [`Lifecycle::admit`] and its row written before the tile scheduler hears of the
//!   job (`Stored` → `Acknowledge` → `JobSubmitted`); every `Assign` is reported as
//!   `TileAssigned` (the first one also writes the job's start); every accepted tile is
//!   written; the tile scheduler's `JobDone` and `JobFailed` become `TilesComplete` and
//!   `TilesFailed`; `StoreImage` encodes the frame (off the writer) and writes it, then
//!   `ImageStored`; `RecordEnd` writes the end, then `EndRecorded`; `CancelTiles`
//!   becomes `CancelJob` and `DeleteStored` a write reported as `Deleted` (retention
//!   from [`SimConfig::limits`]). A job counts as done only once the lifecycle shows
//!   it `Done`: its image and its end written.
//! - **Persistence**: one writer carrying out the writes in order, each taking its
//!   latency (consecutive tiles in batches of up to 256, as the daemon's thread
//!   batches them). A write that fails reports storage unavailable (once: the tile
//!   scheduler then the lifecycle hear `StorageUnavailable`) and is tried again every
//!   [`Limits::retry_ms`](crate::lifecycle::Limits::retry_ms) while the writes behind
//!   it wait; the first write that succeeds reports storage available again (the
//!   lifecycle then the tile scheduler hear `StorageAvailable`). A job's insert that
//!   fails is not retried: its client is answered at once (`StoreFailed`) and the
//!   writer probes the disk until it can write again.
//! - **Storage outages** (a Poisson process, off by default): for a random time every
//!   write fails at once, as on a full or read-only disk; a write under way when the
//!   outage begins fails too. The daemon learns of an outage only from a failed write.
//! - **Clients**: each job is submitted once, at its time, by the same client address;
//!   a submission refused (the lifecycle's limits on active jobs, or storage known to
//!   be unavailable) or whose insert failed is submitted again
//!   [`SimConfig::resubmit_ms`] after the answer arrives, until it is acknowledged.
//! - **Coordinator pauses** (a Poisson process, off by default): the whole daemon
//!   stops, as with `SIGSTOP` or a paused VM, for a random time. What arrives meanwhile
//!   waits in its sockets, and its persistence thread and encoder stop with it; when it
//!   runs again its timer fires first (the worst case: the tile scheduler sees the gap
//!   before any message), then it reads the backlog in order.
//! - **Links**: a one-way latency (base plus jitter) per message, in order per direction
//!   (TCP).
//! - **Network cuts** (a Poisson process per machine, off by default): for a random
//!   time nothing crosses between the machine and the coordinator in either direction;
//!   TCP delivers what was sent during the cut once it heals. A cut longer than the
//!   heartbeat timeout gets the worker dropped; it reads the close after the cut and
//!   reconnects under its name.
//! - **Workers**: `threads` rendering slots fed first-in first-out from the tiles
//!   received; a tile of a job cancelled before it starts is skipped; a heartbeat every
//!   second from the moment the handshake is accepted; when the coordinator closes the
//!   connection the worker drops its queue (the tiles being rendered finish, unsent) and
//!   reconnects after 100 ms × [0.5, 1) as a new worker under the same machine name.
//! - **Failures**: crashes (the process dies; its connection closes after a latency;
//!   with [`SimConfig::restart_after_ms`] its supervisor starts it again after that
//!   delay, under the same machine name, as systemd or Kubernetes would) and
//!   hangs (the whole process stops, as with `SIGSTOP`, for a random time: its renders
//!   pause, messages wait in its socket, no heartbeats; if the coordinator dropped it
//!   meanwhile it finds the connection closed when it wakes, and reconnects), each a
//!   Poisson process per machine; and render hangs (only the render threads stop, for
//!   a random time: renders pause and none starts, while heartbeats, messages and the
//!   queue go on, so that only the scheduler's progress check can tell), a Poisson
//!   process per machine too; new machines join as a Poisson process for the farm.
//! - **Work**: a tile's cost is its area times a per-frame cost map (smooth hot regions,
//!   like a glass object, up to `hotspot_factor` times the base cost, and a per-tile
//!   random factor); a worker renders it in cost / speed of one of its threads.
//!
//! What is not: bandwidth (scenes and results cross the network instantly whatever
//! their size), image assembly, the daemon's bookkeeping around the two machines, a
//! frozen disk (whose writes hang rather than fail, caught by the daemon's stall
//! check), restarts of the coordinator, failed tiles (`TileFailed`), draining,
//! cancellations and deletions asked by clients (deletions after the retention are
//! modelled), and priorities (every job has priority 0).

mod alloc;
mod report;
mod rng;

use std::cmp::{Ordering, Reverse};
use std::collections::{BTreeMap, BTreeSet, BinaryHeap, VecDeque};
use std::mem::Discriminant;
use std::net::IpAddr;
use std::time::{Duration, Instant};

use protocol::{JobId, JobState, SceneHash, WorkerId};

use crate::lifecycle::{self, Lifecycle, Limits};
use crate::tiles::{Action, Event, Millis, Policy, Scheduler};

pub use alloc::{counting, live_bytes, CountingAlloc};
pub use report::{EventCost, LastTile, Memory, Outcome, SimReport};

use rng::Rng;

/// A kind of machine in the farm: real farms mix laptops, desktops and servers, and the
/// spread of their speeds is what makes stragglers.
#[derive(Clone, Debug, PartialEq)]
pub struct MachineClass {
    /// Relative share of the farm's machines in this class (shares need not sum to 1).
    pub share: f64,
    /// Rendering threads; the scheduler gives the worker twice as many tiles.
    pub threads: u32,
    /// Speed of one thread, relative to the reference thread that renders a full tile in
    /// [`SimConfig::tile_ms`].
    pub speed: f64,
}

/// Everything that defines a simulated run. Two runs of the same configuration give the
/// same [`Outcome`] and [`Memory`].
#[derive(Clone, Debug, PartialEq)]
pub struct SimConfig {
    /// Names the run: every random draw derives from it.
    pub seed: u64,
    /// Machines present from the start.
    pub workers: usize,
    /// The mix of machines, for the initial ones and those that join.
    pub classes: Vec<MachineClass>,
    /// Each machine's thread speed is its class's times a factor uniform in
    /// [1 - spread, 1 + spread): no two machines are quite alike.
    pub speed_spread: f64,
    /// Jobs (frames) submitted.
    pub jobs: usize,
    /// Time between two submissions (0: all at once).
    pub job_interval_ms: u64,
    /// Frame size and tile side, as a client would ask; they give the tiles per job.
    pub width: u32,
    pub height: u32,
    pub tile_size: u32,
    /// Time of one full tile of average cost on a reference thread (speed 1).
    pub tile_ms: f64,
    /// Costly regions per frame, at random places, each a smooth bump of radius 5–20 %
    /// of the frame's smaller side.
    pub hotspots: usize,
    /// A tile at the centre of a hot region costs this many times the base.
    pub hotspot_factor: f64,
    /// Each tile's cost is also scaled by a factor uniform in [1 - noise, 1 + noise).
    pub tile_noise: f64,
    /// Crashes per machine per hour of farm time (Poisson).
    pub crashes_per_worker_hour: f64,
    /// Hangs per machine per hour of farm time (Poisson).
    pub hangs_per_worker_hour: f64,
    /// A hang lasts a time uniform in [min, max): around the heartbeat timeout, some
    /// workers come back in time and some are dropped.
    pub hang_min_ms: u64,
    pub hang_max_ms: u64,
    /// Render hangs per machine per hour of farm time (Poisson): the worker's render
    /// threads stop (a deadlock, a driver hang) while its runtime keeps heart-beating
    /// and reading, for a time uniform in [min, max). Only the scheduler's progress
    /// check ([`Policy::progress_timeout`]) tells such a worker from a working one.
    pub render_hangs_per_worker_hour: f64,
    pub render_hang_min_ms: u64,
    pub render_hang_max_ms: u64,
    /// New machines per minute (Poisson), while jobs remain.
    pub joins_per_minute: f64,
    /// One-way network latency: base plus a jitter uniform in [0, jitter).
    pub latency_ms: f64,
    pub latency_jitter_ms: f64,
    /// The worker's heartbeat period (its own constant: 1 s).
    pub heartbeat_ms: u64,
    /// A crashed machine's supervisor restarts its worker after this long, under the
    /// same name (`None`: a crashed machine stays down).
    pub restart_after_ms: Option<u64>,
    /// Pauses of the whole coordinator per hour of farm time (Poisson), each lasting a
    /// time uniform in [min, max).
    pub coordinator_pauses_per_hour: f64,
    pub coordinator_pause_min_ms: u64,
    pub coordinator_pause_max_ms: u64,
    /// Network cuts per machine per hour of farm time (Poisson), each lasting a time
    /// uniform in [min, max).
    pub cuts_per_worker_hour: f64,
    pub cut_min_ms: u64,
    pub cut_max_ms: u64,
    /// The worker's first reconnection delay (its own constant: 100 ms), scaled by a
    /// random factor in [0.5, 1).
    pub reconnect_ms: u64,
    /// The tile scheduler's policy, as the daemon would set it.
    pub policy: Policy,
    /// The lifecycle's limits, as the daemon would set them. Its `retry_ms` is also the
    /// persistence thread's pause between two attempts of a failed write (the daemon
    /// sets both to 500 ms).
    pub limits: Limits,
    /// One write of rows on the persistence thread, synced to the disk: a job's
    /// insert, a batch of tiles, a job's start, its end, a deletion.
    pub storage_write_ms: f64,
    /// Encoding a finished job's image, on the blocking pool (off the writer).
    pub image_encode_ms: f64,
    /// Writing a finished job's image files, on the persistence thread.
    pub image_write_ms: f64,
    /// Outages of the disk per hour of farm time (Poisson), each lasting a time uniform
    /// in [min, max): every write fails meanwhile.
    pub storage_outages_per_hour: f64,
    pub storage_outage_min_ms: u64,
    pub storage_outage_max_ms: u64,
    /// A client whose submission is refused submits it again this long after the
    /// answer arrives.
    pub resubmit_ms: u64,
    /// The run stops here even if jobs remain (reported as timed out).
    pub max_virtual_ms: u64,
}

impl Default for SimConfig {
    /// A thousand mixed machines rendering twenty 4K frames, with a few crashes, hangs
    /// and arrivals: a busy farm on an ordinary day.
    fn default() -> Self {
        SimConfig {
            seed: 1,
            workers: 1000,
            classes: vec![
                MachineClass {
                    share: 0.25,
                    threads: 4,
                    speed: 0.7,
                },
                MachineClass {
                    share: 0.5,
                    threads: 8,
                    speed: 1.0,
                },
                MachineClass {
                    share: 0.2,
                    threads: 16,
                    speed: 1.2,
                },
                MachineClass {
                    share: 0.05,
                    threads: 32,
                    speed: 1.5,
                },
            ],
            speed_spread: 0.2,
            jobs: 20,
            job_interval_ms: 0,
            width: 3840,
            height: 2160,
            tile_size: 32,
            tile_ms: 2_000.0,
            hotspots: 3,
            hotspot_factor: 8.0,
            tile_noise: 0.3,
            crashes_per_worker_hour: 1.0,
            hangs_per_worker_hour: 1.0,
            hang_min_ms: 1_000,
            hang_max_ms: 20_000,
            render_hangs_per_worker_hour: 0.5,
            render_hang_min_ms: 10_000,
            render_hang_max_ms: 600_000,
            joins_per_minute: 10.0,
            latency_ms: 0.5,
            latency_jitter_ms: 0.5,
            heartbeat_ms: 1_000,
            restart_after_ms: None,
            coordinator_pauses_per_hour: 0.0,
            coordinator_pause_min_ms: 3_000,
            coordinator_pause_max_ms: 10_000,
            cuts_per_worker_hour: 0.0,
            cut_min_ms: 1_000,
            cut_max_ms: 10_000,
            reconnect_ms: 100,
            policy: Policy::default(),
            limits: Limits::default(),
            storage_write_ms: 5.0,
            image_encode_ms: 300.0,
            image_write_ms: 50.0,
            storage_outages_per_hour: 0.0,
            storage_outage_min_ms: 1_000,
            storage_outage_max_ms: 30_000,
            resubmit_ms: 1_000,
            max_virtual_ms: 24 * 3_600_000,
        }
    }
}

impl SimConfig {
    /// A farm of identical single-threaded machines that never fail: the setting in
    /// which the makespan should come close to the ideal.
    pub fn uniform(workers: usize) -> Self {
        SimConfig {
            workers,
            classes: vec![MachineClass {
                share: 1.0,
                threads: 1,
                speed: 1.0,
            }],
            speed_spread: 0.0,
            hotspots: 0,
            tile_noise: 0.0,
            ..SimConfig::default()
        }
        .without_failures()
    }

    /// The same farm where nothing fails and nobody joins.
    pub fn without_failures(self) -> Self {
        SimConfig {
            crashes_per_worker_hour: 0.0,
            hangs_per_worker_hour: 0.0,
            render_hangs_per_worker_hour: 0.0,
            joins_per_minute: 0.0,
            coordinator_pauses_per_hour: 0.0,
            cuts_per_worker_hour: 0.0,
            storage_outages_per_hour: 0.0,
            ..self
        }
    }

    /// What every job asks of the lifecycle: the frame, a small scene, from one client
    /// address (a pipeline submitting the frames of an animation).
    pub fn request(&self) -> lifecycle::Request {
        lifecycle::Request {
            client: Some(IpAddr::from([10, 0, 0, 1])),
            scene_bytes: 4_096,
            objects: 16,
            width: self.width,
            height: self.height,
            aa: 1,
        }
    }

    pub fn tiles_per_job(&self) -> u32 {
        self.width.div_ceil(self.tile_size.max(1)) * self.height.div_ceil(self.tile_size.max(1))
    }

    /// Whether the run can make sense, with the reason if not.
    pub fn validate(&self) -> Result<(), String> {
        let rate = |r: f64| r.is_finite() && r >= 0.0;
        if self.jobs == 0 {
            return Err("jobs: at least one".into());
        }
        if self.width == 0 || self.height == 0 || self.tile_size == 0 {
            return Err("width, height and tile_size must be positive".into());
        }
        if self.workers == 0 && self.joins_per_minute <= 0.0 {
            return Err("no worker: give workers or a join rate".into());
        }
        if self.classes.is_empty()
            || self.classes.iter().any(|c| {
                c.threads == 0 || !(c.speed.is_finite() && c.speed > 0.0) || !rate(c.share)
            })
            || self.classes.iter().map(|c| c.share).sum::<f64>() <= 0.0
        {
            return Err(
                "classes: at least one, each with threads, a positive speed and a share".into(),
            );
        }
        if !(0.0..1.0).contains(&self.speed_spread) || !(0.0..1.0).contains(&self.tile_noise) {
            return Err("speed_spread and tile_noise must be in [0, 1)".into());
        }
        let tile_ok = self.tile_ms.is_finite() && self.tile_ms > 0.0;
        let hotspot_ok = self.hotspot_factor.is_finite() && self.hotspot_factor >= 1.0;
        if !(tile_ok && hotspot_ok) {
            return Err("tile_ms must be positive and hotspot_factor at least 1".into());
        }
        if ![
            self.crashes_per_worker_hour,
            self.hangs_per_worker_hour,
            self.render_hangs_per_worker_hour,
            self.joins_per_minute,
            self.coordinator_pauses_per_hour,
            self.cuts_per_worker_hour,
            self.latency_ms,
            self.latency_jitter_ms,
            self.storage_outages_per_hour,
            self.storage_write_ms,
            self.image_encode_ms,
            self.image_write_ms,
        ]
        .into_iter()
        .all(rate)
        {
            return Err("rates, latencies and write times must be finite and not negative".into());
        }
        if self.hang_min_ms > self.hang_max_ms
            || self.render_hang_min_ms > self.render_hang_max_ms
            || self.coordinator_pause_min_ms > self.coordinator_pause_max_ms
            || self.cut_min_ms > self.cut_max_ms
            || self.storage_outage_min_ms > self.storage_outage_max_ms
        {
            return Err("each minimum duration must not exceed its maximum".into());
        }
        if self.heartbeat_ms == 0 || self.reconnect_ms == 0 || self.restart_after_ms == Some(0) {
            return Err("heartbeat_ms, reconnect_ms and restart_after_ms must be positive".into());
        }
        if self.resubmit_ms == 0 || self.limits.retry_ms == 0 {
            return Err("resubmit_ms and limits.retry_ms must be positive".into());
        }
        // A job the lifecycle refuses on its own would be submitted again forever.
        if let Err(reason) = Lifecycle::new(self.limits, 1).admit(0, &self.request()) {
            return Err(format!("the lifecycle refuses every job: {reason}"));
        }
        Ok(())
    }
}

/// The runs of the scaling table in `docs/simulation.md`: 100, 1,000 and 5,000 mixed
/// machines on one and on twenty 4K frames, without and with failures (the defaults:
/// a crash and a hang per machine-hour, ten arrivals a minute); then the largest farm
/// without speculation, and one 8192 × 8192 frame cut into 32- and 16-pixel tiles on
/// 1,000 identical single-threaded machines.
pub fn scaling_runs() -> Vec<(String, SimConfig)> {
    let mut runs = Vec::new();
    for workers in [100, 1_000, 5_000] {
        for jobs in [1, 20] {
            for failures in [false, true] {
                let config = SimConfig {
                    workers,
                    jobs,
                    ..SimConfig::default()
                };
                let (config, trouble) = if failures {
                    (config, ", failures")
                } else {
                    (config.without_failures(), "")
                };
                runs.push((format!("{workers} w, {jobs} × 4K{trouble}"), config));
            }
        }
    }
    let mut config = SimConfig {
        workers: 5_000,
        jobs: 20,
        ..SimConfig::default()
    };
    config.policy.speculate = false;
    runs.push(("5000 w, 20 × 4K, failures, no speculation".into(), config));
    // The same frame and the same work cut finer, on identical machines: what changes
    // is only the number of tiles the scheduler tracks.
    for tile_size in [32, 16] {
        let config = SimConfig {
            jobs: 1,
            width: 8192,
            height: 8192,
            tile_size,
            tile_ms: 2_000.0 * f64::from(tile_size * tile_size) / (32.0 * 32.0),
            ..SimConfig::uniform(1_000)
        };
        runs.push((
            format!("1000 × 1 thread, 1 × 8192², {tile_size}-px tiles"),
            config,
        ));
    }
    runs
}

/// Runs the simulation. Panics if the configuration does not [validate](SimConfig::validate).
///
/// The memory figures need [`CountingAlloc`] as the program's global allocator; without
/// it the report's `memory` is `None`.
pub fn run(config: &SimConfig) -> SimReport {
    if let Err(e) = config.validate() {
        panic!("invalid simulation: {e}");
    }
    let started = Instant::now();
    let mut sim = Sim::new(config);
    let memory = counting().then(|| sim.probe_memory());
    sim.run();
    sim.into_report(memory, started.elapsed())
}

// ---------------------------------------------------------------------------------------
// Virtual time and events.

/// Virtual microseconds since the start of the run.
type Micros = u64;

const MS: Micros = 1_000;

/// Random streams, one per purpose.
const STREAM_MACHINES: u64 = 1;
const STREAM_TILES: u64 = 2;
const STREAM_FAILURES: u64 = 3;
const STREAM_NETWORK: u64 = 4;
const STREAM_JOINS: u64 = 5;
const STREAM_PAUSES: u64 = 6;
const STREAM_CUTS: u64 = 7;
const STREAM_STORAGE: u64 = 8;

/// Why a write failed, as the simulated daemon reports it.
const STORAGE_DOWN: &str = "the simulated disk takes no writes";

/// Tiles written in one transaction at most (the daemon's batch).
const TILE_BATCH: u32 = 256;

/// Worker to coordinator.
#[derive(Clone, Copy, Debug)]
enum Up {
    Hello,
    Heartbeat,
    TileDone {
        job: JobId,
        tile: u32,
        /// When the coordinator sent it and when its render began.
        sent: Micros,
        started: Micros,
    },
    /// The connection closed (the process died).
    Closed,
}

/// Coordinator to worker.
#[derive(Clone, Copy, Debug)]
enum Down {
    /// The handshake's `Accepted`.
    Welcome,
    Render {
        job: JobId,
        tile: u32,
        sent: Micros,
    },
    Cancel {
        job: JobId,
    },
    /// The coordinator closed the connection.
    Close,
}

#[derive(Clone, Copy, Debug)]
enum Ev {
    /// The daemon's timer, armed for the earlier of the two machines' next deadlines.
    Wake,
    /// A client's submission of the job (its index in the run) reaches the coordinator.
    Submit {
        job: usize,
    },
    /// The write in progress on the persistence thread ends (it succeeded unless the
    /// disk failed meanwhile).
    WriteDone,
    /// The persistence thread tries a failed write again.
    WriteRetry,
    /// A finished job's image is encoded: it goes to the writer.
    ImageEncoded {
        job: JobId,
    },
    /// A machine starts (at the beginning or joining later).
    Boot {
        machine: usize,
    },
    Reconnect {
        machine: usize,
    },
    NextJoin,
    /// A message reaches the coordinator.
    Arrival {
        conn: usize,
        msg: Up,
    },
    /// A message reaches a worker.
    Delivery {
        conn: usize,
        msg: Down,
    },
    /// After a `DropWorker`, the connection's task reports `WorkerLeft`.
    ConnectionTaskLeft {
        conn: usize,
    },
    RenderDone {
        machine: usize,
        epoch: u32,
        render: u64,
    },
    HeartbeatTimer {
        machine: usize,
        epoch: u32,
        conn: usize,
    },
    Crash {
        machine: usize,
        epoch: u32,
    },
    Hang {
        machine: usize,
        epoch: u32,
    },
    Thaw {
        machine: usize,
    },
    /// The machine's render threads stop; its runtime goes on.
    RenderHang {
        machine: usize,
        epoch: u32,
    },
    RenderThaw {
        machine: usize,
    },
    /// A crashed machine's supervisor starts its worker again.
    Restart {
        machine: usize,
    },
    /// The network between the machine and the coordinator goes down.
    Cut {
        machine: usize,
    },
    /// The whole coordinator stops, and runs again.
    CoordinatorPause,
    CoordinatorResume,
    /// The disk stops taking writes, and takes them again.
    StorageOutage,
    StorageRecovered,
}

impl Ev {
    /// Whether the coordinator's process handles it (and so, while paused, it waits).
    fn at_coordinator(&self) -> bool {
        matches!(
            self,
            Ev::Wake
                | Ev::Submit { .. }
                | Ev::Arrival { .. }
                | Ev::ConnectionTaskLeft { .. }
                | Ev::WriteDone
                | Ev::WriteRetry
                | Ev::ImageEncoded { .. }
        )
    }
}

struct Scheduled {
    at: Micros,
    seq: u64,
    ev: Ev,
}

impl PartialEq for Scheduled {
    fn eq(&self, other: &Self) -> bool {
        (self.at, self.seq) == (other.at, other.seq)
    }
}
impl Eq for Scheduled {}
impl PartialOrd for Scheduled {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Scheduled {
    /// Earliest first, and in scheduling order at equal times: a min-heap on (at, seq).
    fn cmp(&self, other: &Self) -> Ordering {
        (other.at, other.seq).cmp(&(self.at, self.seq))
    }
}

#[derive(Default)]
struct Agenda {
    heap: BinaryHeap<Scheduled>,
    seq: u64,
}

impl Agenda {
    fn push(&mut self, at: Micros, ev: Ev) {
        self.seq += 1;
        self.heap.push(Scheduled {
            at,
            seq: self.seq,
            ev,
        });
    }
}

// ---------------------------------------------------------------------------------------
// The simulated farm.

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Life {
    /// Not started yet.
    Off,
    Running,
    Frozen,
    Dead,
}

struct Task {
    conn: usize,
    job: JobId,
    tile: u32,
    sent: Micros,
}

struct Render {
    id: u64,
    conn: usize,
    job: JobId,
    tile: u32,
    /// Reference-thread microseconds of the tile.
    cost: Micros,
    sent: Micros,
    started: Micros,
    end: Micros,
    /// While frozen: what was left to render.
    remaining: Micros,
}

struct Machine {
    threads: u32,
    speed: f64,
    life: Life,
    /// Bumped on every freeze, thaw and crash: events of an older epoch are void.
    epoch: u32,
    conn: Option<usize>,
    queue: VecDeque<Task>,
    running: Vec<Render>,
    /// Messages that arrived while the process was stopped.
    inbox: Vec<(usize, Down)>,
    /// Its render threads are stopped (a render hang): renders neither progress nor
    /// start, while heartbeats and messages go on.
    renders_hung: bool,
    reconnect_on_thaw: bool,
    /// Nothing crosses the network to or from it before this time.
    cut_until: Micros,
}

impl Machine {
    fn capacity(&self) -> f64 {
        f64::from(self.threads) * self.speed
    }
}

/// One connection (one worker session), seen from both ends.
#[derive(Default)]
struct Conn {
    machine: usize,
    /// The scheduler's id, once the coordinator has the hello.
    worker: Option<WorkerId>,
    /// The coordinator no longer reads it.
    coordinator_closed: bool,
    left_reported: bool,
    /// The worker side ended this session.
    worker_closed: bool,
    welcomed: bool,
    cancelled: BTreeSet<JobId>,
    /// Arrival time of the last message each way, to keep them in order.
    up_last: Micros,
    down_last: Micros,
}

struct SimJob {
    /// Reference-thread microseconds per tile.
    costs: Vec<Micros>,
    /// When its client first sent it.
    sent: Micros,
    /// The lifecycle's id, once admitted (a new one after a failed insert).
    id: Option<JobId>,
    accepted: Vec<u8>,
    assigned: Vec<u16>,
    /// When each tile was last sent out.
    last_sent: Vec<Micros>,
    /// Whether a tile went out (its start is written then).
    started: bool,
    /// When the tile scheduler reported it done or failed.
    tiles_ended: Option<Micros>,
    /// When its end was written.
    ended: Option<Micros>,
}

// ---------------------------------------------------------------------------------------
// The scheduler, metered.

const EVENT_KINDS: [&str; 21] = [
    "Timeout",
    "WorkerJoined",
    "Heartbeat",
    "WorkerLeft",
    "WorkerDraining",
    "JobSubmitted",
    "TileDone",
    "TileFailed",
    "CancelJob",
    "StorageUnavailable",
    "StorageAvailable",
    "TileToConfirm",
    "Quarantine",
    "WorkerPace",
    "PauseJob",
    "ResumeJob",
    "SetPriority",
    "DisableMachine",
    "EnableMachine",
    "RequeueTiles",
    "Interactive",
];

fn kind_of(event: &Event) -> usize {
    match event {
        Event::Timeout => 0,
        Event::WorkerJoined { .. } => 1,
        Event::Heartbeat { .. } => 2,
        Event::WorkerLeft { .. } => 3,
        Event::WorkerDraining { .. } => 4,
        Event::JobSubmitted { .. } => 5,
        Event::TileDone { .. } => 6,
        Event::TileFailed { .. } => 7,
        Event::CancelJob { .. } => 8,
        Event::StorageUnavailable => 9,
        Event::StorageAvailable => 10,
        Event::TileToConfirm { .. } => 11,
        Event::Quarantine { .. } => 12,
        Event::WorkerPace { .. } => 13,
        Event::PauseJob { .. } => 14,
        Event::ResumeJob { .. } => 15,
        Event::SetPriority { .. } => 16,
        Event::DisableMachine { .. } => 17,
        Event::EnableMachine { .. } => 18,
        Event::RequeueTiles { .. } => 19,
        Event::Interactive { .. } => 20,
    }
}

/// Heap bytes of the actions returned: the caller's, not the scheduler's.
fn heap_of(actions: &Vec<Action>) -> i64 {
    let strings: usize = actions
        .iter()
        .map(|a| match a {
            Action::JobFailed { message, .. } => message.capacity(),
            _ => 0,
        })
        .sum();
    (actions.capacity() * std::mem::size_of::<Action>() + strings) as i64
}

#[derive(Clone, Copy, Default)]
struct Cost {
    count: u64,
    total: Duration,
    max: Duration,
}

impl Cost {
    fn add(&mut self, took: Duration) {
        self.count += 1;
        self.total += took;
        self.max = self.max.max(took);
    }

    fn report(&self, kind: &str) -> EventCost {
        EventCost {
            kind: kind.to_string(),
            count: self.count,
            total: self.total,
            max: self.max,
        }
    }
}

/// The real scheduler, with the time spent in and the heap held by it.
struct Metered {
    scheduler: Scheduler,
    bytes: i64,
    peak: i64,
    costs: [Cost; EVENT_KINDS.len()],
}

impl Metered {
    fn handle(&mut self, now: Millis, event: Event) -> Vec<Action> {
        let kind = kind_of(&event);
        let before = live_bytes();
        let start = Instant::now();
        let actions = self.scheduler.handle(now, event);
        let took = start.elapsed();
        self.bytes += live_bytes() - before - heap_of(&actions);
        self.peak = self.peak.max(self.bytes);
        self.costs[kind].add(took);
        actions
    }
}

/// The real lifecycle, with the time spent in it.
struct MeteredLife {
    lifecycle: Lifecycle,
    admit: Cost,
    /// Per kind of event, in the order first seen, named after the variant.
    costs: Vec<(Discriminant<lifecycle::Event>, String, Cost)>,
}

impl MeteredLife {
    fn admit(
        &mut self,
        now: Millis,
        request: &lifecycle::Request,
    ) -> Result<JobId, protocol::Refusal> {
        let start = Instant::now();
        let result = self.lifecycle.admit(now, request);
        self.admit.add(start.elapsed());
        result
    }

    fn handle(&mut self, now: Millis, event: lifecycle::Event) -> Vec<lifecycle::Action> {
        let kind = std::mem::discriminant(&event);
        let index = match self.costs.iter().position(|(k, _, _)| *k == kind) {
            Some(index) => index,
            None => {
                let name = format!("{event:?}")
                    .chars()
                    .take_while(char::is_ascii_alphanumeric)
                    .collect();
                self.costs.push((kind, name, Cost::default()));
                self.costs.len() - 1
            }
        };
        let start = Instant::now();
        let actions = self.lifecycle.handle(now, event);
        self.costs[index].2.add(start.elapsed());
        actions
    }

    /// Calls, the admissions included.
    fn calls(&self) -> u64 {
        self.admit.count + self.costs.iter().map(|(_, _, c)| c.count).sum::<u64>()
    }
}

// ---------------------------------------------------------------------------------------
// The persistence thread: one writer, in order.

/// One write queued on the persistence thread.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Write {
    /// A new job's row (its client waits for the answer).
    Insert(JobId),
    /// Accepted tiles (consecutive ones are one entry, written in batches).
    Tiles(u32),
    /// A job's first tile went out.
    Started(JobId),
    Image(JobId),
    End(JobId),
    Delete(JobId),
    /// Not queued: after a failed insert, checks that the disk can be written again.
    Probe,
}

#[derive(Default)]
struct Writer {
    queue: VecDeque<Write>,
    /// The write being carried out (attempted, or waiting to be tried again).
    current: Option<Write>,
    /// The disk is probed before any other write.
    probing: bool,
    /// Storage is reported unavailable, since `down_since`.
    down: bool,
    down_since: Micros,
    /// The disk's outage count when the attempt in progress began, and whether the disk
    /// was down then (the attempt fails at once).
    attempt_epoch: u64,
    attempt_doomed: bool,
}

// ---------------------------------------------------------------------------------------
// The leases, as the daemon could work them out from what it sent and received.
//
// The scheduler does not report a lease running out (the tile just goes back to the
// queue), so the simulation keeps its own account with the scheduler's documented rule,
// and checks it against every assignment and result: a tile given again while held must
// be a straggler copy (one live holder) or a requeue (every lease ran out), and a result
// is accepted exactly when its sender holds a lease. Any disagreement is counted in
// `Outcome::model_mismatches`.

struct ModelLease {
    worker: WorkerId,
    started: Millis,
    deadline: Millis,
    expired: bool,
}

enum AssignKind {
    First,
    AfterLoss,
    AfterExpiry,
    Speculative,
    Unexplained,
}

#[derive(Default)]
struct LeaseModel {
    policy: Policy,
    now: Millis,
    leases: BTreeMap<(JobId, u32), Vec<ModelLease>>,
    by_worker: BTreeMap<WorkerId, BTreeSet<(JobId, u32)>>,
    deadlines: BinaryHeap<Reverse<(Millis, JobId, u32, WorkerId)>>,
    /// Per job: accepted results measured, their total time and the slowest.
    measured: BTreeMap<JobId, (u32, Millis, Millis)>,
}

impl LeaseModel {
    fn lease_length(&self, job: JobId) -> Millis {
        match self.measured.get(&job) {
            None | Some((0, _, _)) => self.policy.initial_lease,
            Some(&(n, total, slowest)) => (slowest * self.policy.lease_factor)
                .max(total / u64::from(n) * 4)
                .max(self.policy.min_lease),
        }
    }

    /// Marks the leases that ran out by `now`; returns how many.
    fn expire(&mut self, now: Millis) -> u64 {
        self.now = self.now.max(now);
        let mut expired = 0;
        while let Some(&Reverse((deadline, job, tile, worker))) = self.deadlines.peek() {
            if deadline > self.now {
                break;
            }
            self.deadlines.pop();
            if let Some(lease) = self.leases.get_mut(&(job, tile)).and_then(|ls| {
                ls.iter_mut()
                    .find(|l| l.worker == worker && l.deadline == deadline && !l.expired)
            }) {
                lease.expired = true;
                expired += 1;
            }
        }
        expired
    }

    fn assign(&mut self, worker: WorkerId, job: JobId, tile: u32, before: bool) -> AssignKind {
        let deadline = self.now + self.lease_length(job);
        let leases = self.leases.entry((job, tile)).or_default();
        let kind = if leases.is_empty() {
            if before {
                AssignKind::AfterLoss
            } else {
                AssignKind::First
            }
        } else if leases.iter().any(|l| l.worker == worker) {
            AssignKind::Unexplained
        } else if leases.iter().all(|l| l.expired) {
            AssignKind::AfterExpiry
        } else if leases.iter().filter(|l| !l.expired).count() == 1 {
            AssignKind::Speculative
        } else {
            AssignKind::Unexplained
        };
        leases.push(ModelLease {
            worker,
            started: self.now,
            deadline,
            expired: false,
        });
        self.by_worker
            .entry(worker)
            .or_default()
            .insert((job, tile));
        self.deadlines.push(Reverse((deadline, job, tile, worker)));
        kind
    }

    fn holds(&self, worker: WorkerId, job: JobId, tile: u32) -> bool {
        self.leases
            .get(&(job, tile))
            .is_some_and(|ls| ls.iter().any(|l| l.worker == worker))
    }

    /// The first result: measured, and every lease on the tile ends (the other holders'
    /// copies are late copies now).
    fn accepted(&mut self, worker: WorkerId, job: JobId, tile: u32) {
        let Some(leases) = self.leases.remove(&(job, tile)) else {
            return;
        };
        for lease in &leases {
            if let Some(held) = self.by_worker.get_mut(&lease.worker) {
                held.remove(&(job, tile));
            }
            if lease.worker == worker {
                let took = self.now.saturating_sub(lease.started);
                let m = self.measured.entry(job).or_default();
                m.0 += 1;
                m.1 += took;
                m.2 = m.2.max(took);
            }
        }
        // The job's first measured tile: the leases given under the initial lease end
        // no later than their start plus the lease now measured (their old entries in
        // `deadlines` no longer match, and are skipped).
        if self.measured.get(&job).is_some_and(|m| m.0 == 1) {
            let length = self.lease_length(job);
            for (&(j, tile), leases) in self.leases.range_mut((job, 0)..=(job, u32::MAX)) {
                for lease in leases.iter_mut().filter(|l| !l.expired) {
                    let deadline = lease.deadline.min(lease.started + length);
                    if deadline < lease.deadline {
                        lease.deadline = deadline;
                        self.deadlines
                            .push(Reverse((deadline, j, tile, lease.worker)));
                    }
                }
            }
        }
    }

    /// The scheduler marked the worker unresponsive: its live leases run out now.
    fn expire_worker(&mut self, worker: WorkerId) -> u64 {
        let mut expired = 0;
        for key in self.by_worker.get(&worker).into_iter().flatten() {
            for lease in self.leases.get_mut(key).into_iter().flatten() {
                if lease.worker == worker && !lease.expired {
                    lease.expired = true;
                    expired += 1;
                }
            }
        }
        expired
    }

    fn remove_worker(&mut self, worker: WorkerId) {
        for key in self.by_worker.remove(&worker).unwrap_or_default() {
            if let Some(leases) = self.leases.get_mut(&key) {
                leases.retain(|l| l.worker != worker);
                if leases.is_empty() {
                    self.leases.remove(&key);
                }
            }
        }
    }

    fn end_job(&mut self, job: JobId) {
        let keys: Vec<(JobId, u32)> = self
            .leases
            .range((job, 0)..=(job, u32::MAX))
            .map(|(k, _)| *k)
            .collect();
        for key in keys {
            for lease in self.leases.remove(&key).unwrap_or_default() {
                if let Some(held) = self.by_worker.get_mut(&lease.worker) {
                    held.remove(&key);
                }
            }
        }
        self.measured.remove(&job);
    }
}

// ---------------------------------------------------------------------------------------
// The engine.

struct Sim<'a> {
    cfg: &'a SimConfig,
    now: Micros,
    agenda: Agenda,
    machines: Vec<Machine>,
    conns: Vec<Conn>,
    jobs: Vec<SimJob>,
    /// The index in `jobs` of each job id the lifecycle gave (`usize::MAX`: none).
    by_id: Vec<usize>,
    sched: Metered,
    life: MeteredLife,
    writer: Writer,
    /// The disk fails every write, and how many outages began.
    disk_down: bool,
    disk_epoch: u64,
    /// Write times, in virtual microseconds.
    row_write: Micros,
    image_encode: Micros,
    image_write: Micros,
    /// The daemon's table of connected workers.
    worker_conn: BTreeMap<WorkerId, usize>,
    next_worker: WorkerId,
    model: LeaseModel,
    machines_rng: Rng,
    failures_rng: Rng,
    network_rng: Rng,
    joins_rng: Rng,
    pauses_rng: Rng,
    cuts_rng: Rng,
    storage_rng: Rng,
    /// When the daemon's timer is armed for (the earliest wake pending), if it is.
    wake_at: Option<Micros>,
    /// The coordinator is stopped: what it should handle waits here, in order.
    paused: bool,
    backlog: Vec<Ev>,
    /// (time, change) of the farm's rendering capacity, in reference threads.
    capacity: Vec<(Micros, f64)>,
    next_render: u64,
    jobs_open: usize,
    out: Outcome,
}

impl<'a> Sim<'a> {
    fn new(cfg: &'a SimConfig) -> Sim<'a> {
        let mut tiles_rng = Rng::new(cfg.seed, STREAM_TILES);
        let jobs = (0..cfg.jobs)
            .map(|j| {
                let costs = tile_costs(cfg, &mut tiles_rng);
                SimJob {
                    accepted: vec![0; costs.len()],
                    assigned: vec![0; costs.len()],
                    last_sent: vec![0; costs.len()],
                    costs,
                    sent: j as Micros * cfg.job_interval_ms * MS,
                    id: None,
                    started: false,
                    tiles_ended: None,
                    ended: None,
                }
            })
            .collect();
        let mut sim = Sim {
            cfg,
            now: 0,
            agenda: Agenda::default(),
            machines: Vec::new(),
            conns: Vec::new(),
            jobs,
            by_id: Vec::new(),
            sched: Metered {
                scheduler: Scheduler::with_policy(cfg.policy),
                bytes: 0,
                peak: 0,
                costs: [Cost::default(); EVENT_KINDS.len()],
            },
            life: MeteredLife {
                lifecycle: Lifecycle::new(cfg.limits, 1),
                admit: Cost::default(),
                costs: Vec::new(),
            },
            writer: Writer::default(),
            disk_down: false,
            disk_epoch: 0,
            row_write: micros(cfg.storage_write_ms),
            image_encode: micros(cfg.image_encode_ms),
            image_write: micros(cfg.image_write_ms),
            worker_conn: BTreeMap::new(),
            next_worker: 1,
            model: LeaseModel {
                policy: cfg.policy,
                ..LeaseModel::default()
            },
            machines_rng: Rng::new(cfg.seed, STREAM_MACHINES),
            failures_rng: Rng::new(cfg.seed, STREAM_FAILURES),
            network_rng: Rng::new(cfg.seed, STREAM_NETWORK),
            joins_rng: Rng::new(cfg.seed, STREAM_JOINS),
            pauses_rng: Rng::new(cfg.seed, STREAM_PAUSES),
            cuts_rng: Rng::new(cfg.seed, STREAM_CUTS),
            storage_rng: Rng::new(cfg.seed, STREAM_STORAGE),
            wake_at: None,
            paused: false,
            backlog: Vec::new(),
            capacity: Vec::new(),
            next_render: 0,
            jobs_open: cfg.jobs,
            out: Outcome {
                workers_initial: cfg.workers,
                jobs: cfg.jobs,
                ..Outcome::default()
            },
        };
        for _ in 0..cfg.workers {
            let m = sim.new_machine();
            sim.agenda.push(0, Ev::Boot { machine: m });
        }
        for job in 0..cfg.jobs {
            let at = sim.jobs[job].sent + sim.latency();
            sim.agenda.push(at, Ev::Submit { job });
        }
        if cfg.joins_per_minute > 0.0 {
            let gap = sim.join_gap();
            sim.agenda.push(gap, Ev::NextJoin);
        }
        sim.arm_coordinator_pause();
        sim.arm_storage_outage();
        sim
    }

    fn new_machine(&mut self) -> usize {
        let total: f64 = self.cfg.classes.iter().map(|c| c.share).sum();
        let mut pick = self.machines_rng.unit() * total;
        let class = self
            .cfg
            .classes
            .iter()
            .find(|c| {
                pick -= c.share;
                pick < 0.0
            })
            .unwrap_or(&self.cfg.classes[self.cfg.classes.len() - 1]);
        let spread = self.cfg.speed_spread;
        let speed = class.speed * self.machines_rng.range(1.0 - spread, 1.0 + spread);
        self.machines.push(Machine {
            threads: class.threads,
            speed,
            life: Life::Off,
            epoch: 0,
            conn: None,
            queue: VecDeque::new(),
            running: Vec::new(),
            inbox: Vec::new(),
            renders_hung: false,
            reconnect_on_thaw: false,
            cut_until: 0,
        });
        self.machines.len() - 1
    }

    fn latency(&mut self) -> Micros {
        let ms = self.cfg.latency_ms + self.cfg.latency_jitter_ms * self.network_rng.unit();
        (ms * MS as f64).round() as Micros
    }

    fn join_gap(&mut self) -> Micros {
        let mean = 60_000.0 * MS as f64 / self.cfg.joins_per_minute;
        (self.joins_rng.exponential(mean).round() as Micros).max(1)
    }

    /// When a message sent now over the connection arrives: after the latency, after
    /// the messages sent before it, and not before a cut of its machine heals.
    fn arrival(&mut self, conn: usize, last: Micros) -> Micros {
        let latency = self.latency();
        let cut = self.machines[self.conns[conn].machine].cut_until;
        (self.now.max(cut) + latency).max(last)
    }

    fn send_up(&mut self, conn: usize, msg: Up) {
        let at = self.arrival(conn, self.conns[conn].up_last);
        self.conns[conn].up_last = at;
        self.agenda.push(at, Ev::Arrival { conn, msg });
    }

    fn send_down(&mut self, conn: usize, msg: Down) {
        let at = self.arrival(conn, self.conns[conn].down_last);
        self.conns[conn].down_last = at;
        self.agenda.push(at, Ev::Delivery { conn, msg });
    }

    fn run(&mut self) {
        let limit = self.cfg.max_virtual_ms * MS;
        loop {
            let Some(Scheduled { at, ev, .. }) = self.agenda.heap.pop() else {
                // Nothing can happen any more, and jobs are left.
                self.out.timed_out = true;
                break;
            };
            if at > limit {
                self.out.timed_out = true;
                self.now = limit;
                break;
            }
            self.now = at;
            if self.paused && ev.at_coordinator() {
                self.backlog.push(ev);
            } else {
                self.dispatch(ev);
            }
            if self.jobs_open == 0 {
                break;
            }
        }
    }

    /// Hands one event to the tile scheduler at the current virtual time, brings the
    /// lease account to the scheduler's clock, and re-arms the daemon's timer for the
    /// scheduler's next deadline, as the daemon does after every call.
    fn handle(&mut self, event: Event) -> Vec<Action> {
        let actions = self.sched.handle(self.now / MS, event);
        self.model.now = self.model.now.max(self.sched.scheduler.clock());
        self.arm_wake(self.sched.scheduler.next_deadline());
        actions
    }

    /// Hands one event to the lifecycle, re-arms the timer for its next deadline (which
    /// changes only when it handles something), and carries out its actions.
    fn life(&mut self, event: lifecycle::Event) {
        let actions = self.life.handle(self.now / MS, event);
        self.arm_wake(self.life.lifecycle.next_deadline());
        self.apply_life(actions);
    }

    /// The daemon's timer fires at the earliest deadline either machine gave.
    fn arm_wake(&mut self, deadline: Option<Millis>) {
        if let Some(deadline) = deadline {
            // With the daemon's timer slack.
            let at = (crate::wake_time(deadline) * MS).max(self.now);
            if self.wake_at.is_none_or(|armed| at < armed) {
                self.wake_at = Some(at);
                self.agenda.push(at, Ev::Wake);
            }
        }
    }

    /// The daemon's timer fires: a `Timeout` for the tile scheduler, then for the
    /// lifecycle. (Only the earliest armed wake counts; one superseded by an earlier
    /// deadline is void, and a later deadline is re-armed by the calls.)
    fn timeout(&mut self) {
        self.wake_at = None;
        self.out.timeouts += 1;
        // The scheduler drops silent workers before it looks at leases; the model
        // expires leases once those drops are applied (see `apply`).
        let actions = self.handle(Event::Timeout);
        let clock = self.sched.scheduler.clock();
        self.apply(actions, Some(clock));
        self.life(lifecycle::Event::Timeout);
    }

    fn dispatch(&mut self, ev: Ev) {
        match ev {
            Ev::Wake => {
                if self.wake_at == Some(self.now) {
                    self.timeout();
                }
            }
            Ev::CoordinatorPause => {
                self.paused = true;
                self.out.coordinator_pauses += 1;
                let span = self.pauses_rng.range(
                    self.cfg.coordinator_pause_min_ms as f64,
                    self.cfg.coordinator_pause_max_ms as f64,
                );
                self.agenda.push(
                    self.now + (span * MS as f64).round() as Micros,
                    Ev::CoordinatorResume,
                );
            }
            Ev::CoordinatorResume => {
                self.paused = false;
                // Its timer is long overdue and fires first; then it reads what waited.
                self.timeout();
                for ev in std::mem::take(&mut self.backlog) {
                    if !matches!(ev, Ev::Wake) {
                        self.dispatch(ev);
                    }
                }
                self.arm_coordinator_pause();
            }
            Ev::Restart { machine } => {
                let m = &mut self.machines[machine];
                if m.life == Life::Dead {
                    m.life = Life::Running;
                    m.epoch += 1;
                    self.out.restarts += 1;
                    let capacity = m.capacity();
                    self.capacity.push((self.now, capacity));
                    self.arm_failures(machine);
                    self.connect(machine);
                }
            }
            Ev::Cut { machine } => {
                if self.machines[machine].life == Life::Dead && self.cfg.restart_after_ms.is_none()
                {
                    // The machine is gone for good: its chain of cuts ends.
                    return;
                }
                let span = self
                    .cuts_rng
                    .range(self.cfg.cut_min_ms as f64, self.cfg.cut_max_ms as f64);
                let until = self.now + (span * MS as f64).round() as Micros;
                self.machines[machine].cut_until = until;
                self.out.network_cuts += 1;
                self.arm_cut(machine, until);
            }
            Ev::Submit { job } => self.submit(job),
            Ev::WriteDone => self.write_done(),
            Ev::WriteRetry => self.attempt_write(),
            Ev::ImageEncoded { job } => self.persist(Write::Image(job)),
            Ev::StorageOutage => {
                self.disk_down = true;
                self.disk_epoch += 1;
                self.out.storage_outages += 1;
                let span = self.storage_rng.range(
                    self.cfg.storage_outage_min_ms as f64,
                    self.cfg.storage_outage_max_ms as f64,
                );
                self.agenda
                    .push(self.now + micros(span), Ev::StorageRecovered);
            }
            Ev::StorageRecovered => {
                self.disk_down = false;
                self.arm_storage_outage();
            }
            Ev::Boot { machine } => {
                let m = &mut self.machines[machine];
                m.life = Life::Running;
                let capacity = m.capacity();
                self.capacity.push((self.now, capacity));
                self.arm_failures(machine);
                self.arm_cut(machine, self.now);
                self.connect(machine);
            }
            Ev::Reconnect { machine } => match self.machines[machine].life {
                Life::Running => self.connect(machine),
                Life::Frozen => self.machines[machine].reconnect_on_thaw = true,
                Life::Off | Life::Dead => {}
            },
            Ev::NextJoin => {
                let machine = self.new_machine();
                self.out.workers_joined += 1;
                self.agenda.push(self.now, Ev::Boot { machine });
                let gap = self.join_gap();
                self.agenda.push(self.now + gap, Ev::NextJoin);
            }
            Ev::Arrival { conn, msg } => self.at_coordinator(conn, msg),
            Ev::Delivery { conn, msg } => {
                let machine = self.conns[conn].machine;
                match self.machines[machine].life {
                    Life::Running => self.at_worker(conn, msg),
                    Life::Frozen => self.machines[machine].inbox.push((conn, msg)),
                    Life::Off | Life::Dead => {}
                }
            }
            Ev::ConnectionTaskLeft { conn } => self.worker_left(conn),
            Ev::RenderDone {
                machine,
                epoch,
                render,
            } => self.render_done(machine, epoch, render),
            Ev::HeartbeatTimer {
                machine,
                epoch,
                conn,
            } => {
                let m = &self.machines[machine];
                if m.life == Life::Running
                    && m.epoch == epoch
                    && m.conn == Some(conn)
                    && !self.conns[conn].worker_closed
                {
                    self.send_up(conn, Up::Heartbeat);
                    self.agenda.push(
                        self.now + self.cfg.heartbeat_ms * MS,
                        Ev::HeartbeatTimer {
                            machine,
                            epoch,
                            conn,
                        },
                    );
                }
            }
            Ev::Crash { machine, epoch } => self.crash(machine, epoch),
            Ev::Hang { machine, epoch } => self.hang(machine, epoch),
            Ev::Thaw { machine } => self.thaw(machine),
            Ev::RenderHang { machine, epoch } => self.render_hang(machine, epoch),
            Ev::RenderThaw { machine } => self.render_thaw(machine),
        }
    }

    // --- the coordinator's side ------------------------------------------------------

    fn at_coordinator(&mut self, conn: usize, msg: Up) {
        if self.conns[conn].coordinator_closed {
            if let Up::TileDone { .. } = msg {
                self.out.results_unread += 1;
            }
            return;
        }
        match msg {
            Up::Hello => {
                let worker = self.next_worker;
                self.next_worker += 1;
                self.conns[conn].worker = Some(worker);
                self.worker_conn.insert(worker, conn);
                // `Accepted` goes out before anything the scheduler sends.
                self.send_down(conn, Down::Welcome);
                let machine = self.conns[conn].machine;
                let threads = self.machines[machine].threads;
                let actions = self.handle(Event::WorkerJoined {
                    worker,
                    threads,
                    machine: Some(format!("machine-{machine}")),
                });
                self.apply(actions, None);
            }
            Up::Heartbeat => {
                let worker = self.conns[conn].worker.expect("hello first");
                let actions = self.handle(Event::Heartbeat { worker });
                self.apply(actions, None);
            }
            Up::TileDone {
                job,
                tile,
                sent,
                started,
            } => {
                let worker = self.conns[conn].worker.expect("hello first");
                let held = self.model.holds(worker, job, tile);
                let actions = self.handle(Event::TileDone { worker, job, tile });
                let accepted = actions.contains(&Action::AcceptTile { job, tile });
                let duplicate = actions.contains(&Action::DuplicateResult { job, tile });
                if held != accepted {
                    self.out.model_mismatches += 1;
                }
                if accepted {
                    self.model.accepted(worker, job, tile);
                    let j = &self.jobs[self.slot(job)];
                    self.out.last_tile = Some(LastTile {
                        job,
                        tile,
                        cost_ms: j.costs[tile as usize] as f64 / MS as f64,
                        assignments: u32::from(j.assigned[tile as usize]),
                        last_assigned_ms: j.last_sent[tile as usize] as f64 / MS as f64,
                        thread_speed: self.machines[self.conns[conn].machine].speed,
                        assigned_ms: sent as f64 / MS as f64,
                        started_ms: started as f64 / MS as f64,
                        accepted_ms: self.now as f64 / MS as f64,
                    });
                } else if !duplicate {
                    self.out.stray_results += 1;
                }
                self.apply(actions, None);
            }
            Up::Closed => {
                self.conns[conn].coordinator_closed = true;
                self.worker_left(conn);
            }
        }
    }

    /// The daemon's end of a connection: `WorkerLeft`, once.
    fn worker_left(&mut self, conn: usize) {
        if std::mem::replace(&mut self.conns[conn].left_reported, true) {
            return;
        }
        let Some(worker) = self.conns[conn].worker else {
            return;
        };
        self.worker_conn.remove(&worker);
        self.model.remove_worker(worker);
        let actions = self.handle(Event::WorkerLeft { worker });
        self.apply(actions, None);
    }

    /// Carries out the scheduler's actions as the daemon does. `timeout`: the
    /// scheduler's clock at a `Timeout` whose lease expiries the model still has to
    /// apply (before its first assignment, after its drops).
    fn apply(&mut self, actions: Vec<Action>, mut timeout: Option<Millis>) {
        for action in actions {
            match action {
                Action::SendScene { .. } => self.out.scenes_sent += 1,
                Action::Assign { worker, job, tile } => {
                    if let Some(now) = timeout.take() {
                        self.out.leases_expired += self.model.expire(now);
                    }
                    self.out.assignments += 1;
                    let slot = self.slot(job);
                    let j = &mut self.jobs[slot];
                    let first = !std::mem::replace(&mut j.started, true);
                    let before = j.assigned[tile as usize] > 0;
                    j.assigned[tile as usize] = j.assigned[tile as usize].saturating_add(1);
                    j.last_sent[tile as usize] = self.now;
                    match self.model.assign(worker, job, tile, before) {
                        AssignKind::First => {}
                        AssignKind::AfterLoss => self.out.reassigned_after_loss += 1,
                        AssignKind::AfterExpiry => self.out.reassigned_after_expiry += 1,
                        AssignKind::Speculative => self.out.speculative_copies += 1,
                        AssignKind::Unexplained => self.out.model_mismatches += 1,
                    }
                    if first {
                        self.persist(Write::Started(job));
                    }
                    match self.worker_conn.get(&worker) {
                        Some(&conn) => {
                            let sent = self.now;
                            self.send_down(conn, Down::Render { job, tile, sent });
                        }
                        None => self.out.model_mismatches += 1,
                    }
                    self.life(lifecycle::Event::TileAssigned { job });
                }
                Action::AcceptTile { job, tile } => {
                    let slot = self.slot(job);
                    let count = &mut self.jobs[slot].accepted[tile as usize];
                    *count = count.saturating_add(1);
                    if *count > 1 {
                        self.out.tiles_accepted_twice += 1;
                    }
                    self.out.tiles_accepted += 1;
                    self.persist(Write::Tiles(1));
                }
                Action::DuplicateResult { .. } => self.out.duplicate_results += 1,
                // The simulated workers are honest: no result is held for confirmation.
                Action::HoldResult { .. } | Action::AcceptHeld { .. } => {
                    self.out.model_mismatches += 1
                }
                Action::CancelOnWorker { worker, job } => {
                    if let Some(&conn) = self.worker_conn.get(&worker) {
                        self.send_down(conn, Down::Cancel { job });
                    }
                }
                Action::ForgetScene { .. } => self.out.scenes_forgotten += 1,
                Action::WorkerUnresponsive { worker, .. } => {
                    // The timeout's expiries first, as the scheduler made them.
                    if let Some(now) = timeout.take() {
                        self.out.leases_expired += self.model.expire(now);
                    }
                    self.out.unresponsive += 1;
                    self.out.leases_expired += self.model.expire_worker(worker);
                }
                Action::WorkerResponsive { .. } => self.out.responsive_again += 1,
                Action::DropWorker { worker } => {
                    self.out.drops += 1;
                    self.model.remove_worker(worker);
                    if let Some(conn) = self.worker_conn.remove(&worker) {
                        self.conns[conn].coordinator_closed = true;
                        self.agenda.push(self.now, Ev::ConnectionTaskLeft { conn });
                        self.send_down(conn, Down::Close);
                    }
                }
                Action::JobDone { job } => {
                    self.tiles_ended(job, true);
                    self.life(lifecycle::Event::TilesComplete { job });
                }
                Action::JobFailed { job, message } => {
                    self.tiles_ended(job, false);
                    self.life(lifecycle::Event::TilesFailed { job, message });
                }
            }
        }
        if let Some(now) = timeout {
            self.out.leases_expired += self.model.expire(now);
        }
    }

    /// The tile scheduler is done with the job (every tile in, or failed).
    fn tiles_ended(&mut self, job: JobId, done: bool) {
        let slot = self.slot(job);
        let j = &mut self.jobs[slot];
        if j.tiles_ended.is_some() {
            self.out.model_mismatches += 1;
            return;
        }
        j.tiles_ended = Some(self.now);
        if done {
            self.out.tiles_missing += j.accepted.iter().filter(|&&c| c == 0).count() as u64;
        }
        self.model.end_job(job);
    }

    /// The index in `jobs` of a job id the lifecycle gave.
    fn slot(&self, job: JobId) -> usize {
        self.by_id[job as usize]
    }

    // --- the clients' side and the lifecycle -----------------------------------------

    /// A submission reaches the coordinator: the lifecycle admits it (and its row is
    /// queued for writing) or refuses it (and the client submits it again later).
    fn submit(&mut self, slot: usize) {
        if self.jobs[slot].id.is_some() {
            self.out.model_mismatches += 1;
            return;
        }
        match self.life.admit(self.now / MS, &self.cfg.request()) {
            Ok(job) => {
                let i = job as usize;
                if self.by_id.len() <= i {
                    self.by_id.resize(i + 1, usize::MAX);
                }
                if self.by_id[i] != usize::MAX {
                    // An id given twice.
                    self.out.model_mismatches += 1;
                }
                self.by_id[i] = slot;
                self.jobs[slot].id = Some(job);
                self.out.jobs_admitted += 1;
                self.persist(Write::Insert(job));
            }
            Err(_) => {
                self.out.admissions_refused += 1;
                self.resubmit(slot);
            }
        }
    }

    /// The client hears its submission was refused, waits, and submits it again.
    fn resubmit(&mut self, slot: usize) {
        let answer = self.latency();
        let again = self.latency();
        let at = self.now + answer + self.cfg.resubmit_ms * MS + again;
        self.agenda.push(at, Ev::Submit { job: slot });
    }

    /// Carries out the lifecycle's actions as the daemon does.
    fn apply_life(&mut self, actions: Vec<lifecycle::Action>) {
        use lifecycle::Action as A;
        for action in actions {
            match action {
                A::Acknowledge { job } => {
                    let slot = self.slot(job);
                    let j = &self.jobs[slot];
                    let tiles = j.costs.len() as u32;
                    let waited = (self.now - j.sent) as f64 / MS as f64;
                    self.out.jobs_acknowledged += 1;
                    self.out.longest_admission_ms = self.out.longest_admission_ms.max(waited);
                    let actions = self.handle(Event::JobSubmitted {
                        job,
                        priority: 0,
                        scene: scene_of(job),
                        tiles,
                    });
                    self.apply(actions, None);
                }
                A::RefuseStored { job, .. } => {
                    let slot = self.slot(job);
                    self.by_id[job as usize] = usize::MAX;
                    self.jobs[slot].id = None;
                    self.out.stores_refused += 1;
                    self.resubmit(slot);
                }
                A::StoreImage { job } => {
                    self.agenda
                        .push(self.now + self.image_encode, Ev::ImageEncoded { job });
                }
                A::CancelTiles { job } => {
                    let actions = self.handle(Event::CancelJob { job });
                    self.apply(actions, None);
                }
                A::RecordEnd { job, state, error } => {
                    if state == JobState::Failed {
                        self.out.job_failures.push((job, error.unwrap_or_default()));
                    }
                    self.persist(Write::End(job));
                }
                A::DeleteStored { job } => self.persist(Write::Delete(job)),
                // Nobody cancels or deletes: no client waits for a reply.
                A::Reply { .. } => {}
            }
        }
    }

    /// A job's end is written: it is over for the farm, and `Done` for its client if
    /// the lifecycle says so.
    fn end_recorded(&mut self, job: JobId) {
        self.life(lifecycle::Event::EndRecorded { job });
        let state = self.life.lifecycle.job(job).map(|j| j.phase.visible());
        let now = self.now;
        let slot = self.slot(job);
        let j = &mut self.jobs[slot];
        if j.ended.is_some() {
            self.out.model_mismatches += 1;
            return;
        }
        j.ended = Some(now);
        self.jobs_open -= 1;
        match state {
            Some(JobState::Done) => {
                self.out.jobs_done += 1;
                let last_tile = j.tiles_ended.unwrap_or(now);
                let finish = (now - last_tile) as f64 / MS as f64;
                self.out.longest_finish_ms = self.out.longest_finish_ms.max(finish);
            }
            Some(JobState::Failed) => self.out.jobs_failed += 1,
            // Nobody cancels: an end written must be done or failed.
            _ => self.out.model_mismatches += 1,
        }
    }

    // --- persistence -----------------------------------------------------------------

    /// Queues a write; the writer takes it up at once if it is idle.
    fn persist(&mut self, write: Write) {
        match (write, self.writer.queue.back_mut()) {
            (Write::Tiles(n), Some(Write::Tiles(queued))) => *queued += n,
            _ => self.writer.queue.push_back(write),
        }
        self.next_write();
    }

    /// The writer, if idle, takes the next write (the probe first, after a failed
    /// insert; consecutive tiles in one batch) and attempts it.
    fn next_write(&mut self) {
        if self.writer.current.is_some() {
            return;
        }
        let write = if self.writer.probing {
            Write::Probe
        } else {
            match self.writer.queue.pop_front() {
                None => return,
                Some(Write::Tiles(n)) if n > TILE_BATCH => {
                    self.writer.queue.push_front(Write::Tiles(n - TILE_BATCH));
                    Write::Tiles(TILE_BATCH)
                }
                Some(write) => write,
            }
        };
        self.writer.current = Some(write);
        self.attempt_write();
    }

    /// One attempt of the current write: it fails at once on a disk that is down, and
    /// otherwise ends after its write time (failed if the disk went down meanwhile).
    fn attempt_write(&mut self) {
        let Some(write) = self.writer.current else {
            return;
        };
        self.writer.attempt_epoch = self.disk_epoch;
        self.writer.attempt_doomed = self.disk_down;
        let took = match write {
            Write::Image(_) => self.image_write,
            _ => self.row_write,
        };
        let at = if self.disk_down {
            self.now
        } else {
            self.now + took
        };
        self.agenda.push(at, Ev::WriteDone);
    }

    /// The attempt in progress ends: storage is reported available or not (on a
    /// change), and the write's outcome goes where the daemon's callbacks send it.
    fn write_done(&mut self) {
        let Some(write) = self.writer.current.take() else {
            return;
        };
        let ok = !self.writer.attempt_doomed && self.writer.attempt_epoch == self.disk_epoch;
        if !ok {
            self.out.write_failures += 1;
            self.storage_status(false);
            if let Write::Insert(job) = write {
                // Its client is waiting: it is answered at once, and the disk is probed
                // before anything else is written.
                self.writer.probing = true;
                self.life(lifecycle::Event::StoreFailed {
                    job,
                    message: STORAGE_DOWN.into(),
                });
                self.next_write();
            } else {
                self.writer.current = Some(write);
                self.agenda
                    .push(self.now + self.cfg.limits.retry_ms * MS, Ev::WriteRetry);
            }
            return;
        }
        self.out.writes += 1;
        self.storage_status(true);
        match write {
            Write::Probe => self.writer.probing = false,
            Write::Insert(job) => self.life(lifecycle::Event::Stored { job }),
            Write::Tiles(n) => self.out.tiles_written += u64::from(n),
            Write::Started(_) => {}
            Write::Image(job) => {
                self.out.images_stored += 1;
                self.life(lifecycle::Event::ImageStored {
                    job,
                    result: Ok(()),
                });
            }
            Write::End(job) => self.end_recorded(job),
            Write::Delete(job) => {
                self.out.jobs_deleted += 1;
                self.life(lifecycle::Event::Deleted { job });
            }
        }
        self.next_write();
    }

    /// Storage became unavailable or available again: both machines hear it, in the
    /// daemon's order (the tile scheduler stops first and resumes last).
    fn storage_status(&mut self, available: bool) {
        if self.writer.down != available {
            return;
        }
        self.writer.down = !available;
        if available {
            self.out.storage_unavailable_ms +=
                (self.now - self.writer.down_since) as f64 / MS as f64;
            self.life(lifecycle::Event::StorageAvailable);
            let actions = self.handle(Event::StorageAvailable);
            self.apply(actions, None);
        } else {
            self.writer.down_since = self.now;
            self.out.storage_unavailable += 1;
            let actions = self.handle(Event::StorageUnavailable);
            self.apply(actions, None);
            self.life(lifecycle::Event::StorageUnavailable {
                reason: STORAGE_DOWN.into(),
            });
        }
    }

    /// The disk's next outage (Poisson), while it works.
    fn arm_storage_outage(&mut self) {
        if self.cfg.storage_outages_per_hour > 0.0 {
            let hour = 3_600_000.0 * MS as f64;
            let after = self
                .storage_rng
                .exponential(hour / self.cfg.storage_outages_per_hour);
            self.agenda
                .push(self.now + after.round() as Micros, Ev::StorageOutage);
        }
    }

    // --- the workers' side -----------------------------------------------------------

    fn connect(&mut self, machine: usize) {
        self.conns.push(Conn {
            machine,
            ..Conn::default()
        });
        let conn = self.conns.len() - 1;
        self.machines[machine].conn = Some(conn);
        self.send_up(conn, Up::Hello);
    }

    fn at_worker(&mut self, conn: usize, msg: Down) {
        if self.conns[conn].worker_closed {
            return;
        }
        let machine = self.conns[conn].machine;
        match msg {
            Down::Welcome => {
                self.conns[conn].welcomed = true;
                let epoch = self.machines[machine].epoch;
                // The worker's interval fires at once, then every period.
                self.agenda.push(
                    self.now,
                    Ev::HeartbeatTimer {
                        machine,
                        epoch,
                        conn,
                    },
                );
            }
            Down::Render { job, tile, sent } => {
                self.machines[machine].queue.push_back(Task {
                    conn,
                    job,
                    tile,
                    sent,
                });
                self.start_renders(machine);
            }
            Down::Cancel { job } => {
                self.conns[conn].cancelled.insert(job);
            }
            Down::Close => {
                // The session ends: queued tiles are never rendered, the ones being
                // rendered finish unsent; the worker reconnects after its backoff.
                self.conns[conn].worker_closed = true;
                let m = &mut self.machines[machine];
                if m.conn == Some(conn) {
                    m.conn = None;
                }
                let before = m.queue.len();
                m.queue.retain(|t| t.conn != conn);
                self.out.tasks_skipped += (before - m.queue.len()) as u64;
                let delay =
                    self.cfg.reconnect_ms as f64 * MS as f64 * self.network_rng.range(0.5, 1.0);
                self.out.reconnects += 1;
                self.agenda.push(
                    self.now + delay.round() as Micros,
                    Ev::Reconnect { machine },
                );
            }
        }
    }

    fn start_renders(&mut self, machine: usize) {
        let m = &mut self.machines[machine];
        while !m.renders_hung && m.running.len() < m.threads as usize {
            let Some(task) = m.queue.pop_front() else {
                break;
            };
            let conn = &self.conns[task.conn];
            if conn.worker_closed || conn.cancelled.contains(&task.job) {
                self.out.tasks_skipped += 1;
                continue;
            }
            let cost = self.jobs[self.by_id[task.job as usize]].costs[task.tile as usize];
            let took = ((cost as f64 / m.speed).round() as Micros).max(1);
            let id = self.next_render;
            self.next_render += 1;
            m.running.push(Render {
                id,
                conn: task.conn,
                job: task.job,
                tile: task.tile,
                cost,
                sent: task.sent,
                started: self.now,
                end: self.now + took,
                remaining: 0,
            });
            self.out.renders_started += 1;
            self.agenda.push(
                self.now + took,
                Ev::RenderDone {
                    machine,
                    epoch: m.epoch,
                    render: id,
                },
            );
        }
    }

    fn render_done(&mut self, machine: usize, epoch: u32, render: u64) {
        let m = &mut self.machines[machine];
        if m.epoch != epoch || m.life != Life::Running {
            return;
        }
        if m.renders_hung {
            return;
        }
        // A render moved by a render hang has a later end: its first event is stale.
        let Some(pos) = m
            .running
            .iter()
            .position(|r| r.id == render && r.end == self.now)
        else {
            return;
        };
        let r = m.running.swap_remove(pos);
        self.out.renders_completed += 1;
        self.out.work_spent_ms += r.cost as f64 / MS as f64;
        if m.conn == Some(r.conn) && !self.conns[r.conn].worker_closed {
            self.send_up(
                r.conn,
                Up::TileDone {
                    job: r.job,
                    tile: r.tile,
                    sent: r.sent,
                    started: r.started,
                },
            );
        } else {
            self.out.renders_orphaned += 1;
        }
        self.start_renders(machine);
    }

    fn arm_failures(&mut self, machine: usize) {
        let epoch = self.machines[machine].epoch;
        let hour = 3_600_000.0 * MS as f64;
        if self.cfg.crashes_per_worker_hour > 0.0 {
            let after = self
                .failures_rng
                .exponential(hour / self.cfg.crashes_per_worker_hour);
            self.agenda.push(
                self.now + after.round() as Micros,
                Ev::Crash { machine, epoch },
            );
        }
        if self.cfg.hangs_per_worker_hour > 0.0 {
            let after = self
                .failures_rng
                .exponential(hour / self.cfg.hangs_per_worker_hour);
            self.agenda.push(
                self.now + after.round() as Micros,
                Ev::Hang { machine, epoch },
            );
        }
        if !self.machines[machine].renders_hung {
            // (A machine whose renders hang arms its next render hang when they run.)
            self.arm_render_hang(machine);
        }
    }

    /// The machine's next render hang (Poisson).
    fn arm_render_hang(&mut self, machine: usize) {
        if self.cfg.render_hangs_per_worker_hour > 0.0 {
            let hour = 3_600_000.0 * MS as f64;
            let epoch = self.machines[machine].epoch;
            let after = self
                .failures_rng
                .exponential(hour / self.cfg.render_hangs_per_worker_hour);
            self.agenda.push(
                self.now + after.round() as Micros,
                Ev::RenderHang { machine, epoch },
            );
        }
    }

    fn crash(&mut self, machine: usize, epoch: u32) {
        let now = self.now;
        let m = &mut self.machines[machine];
        if m.epoch != epoch || m.life != Life::Running {
            return;
        }
        m.life = Life::Dead;
        m.epoch += 1;
        self.out.crashes += 1;
        if !std::mem::replace(&mut m.renders_hung, false) {
            // (A render hang already took its capacity.)
            self.capacity.push((now, -m.capacity()));
        }
        for r in m.running.drain(..) {
            self.out.renders_interrupted += 1;
            self.out.work_spent_ms += (now - r.started) as f64 * m.speed / MS as f64;
        }
        m.queue.clear();
        if let Some(conn) = m.conn.take() {
            self.send_up(conn, Up::Closed);
        }
        if let Some(after) = self.cfg.restart_after_ms {
            self.agenda.push(now + after * MS, Ev::Restart { machine });
        }
    }

    /// The machine's next network cut, after `from` (Poisson).
    fn arm_cut(&mut self, machine: usize, from: Micros) {
        if self.cfg.cuts_per_worker_hour > 0.0 {
            let hour = 3_600_000.0 * MS as f64;
            let after = self
                .cuts_rng
                .exponential(hour / self.cfg.cuts_per_worker_hour);
            self.agenda
                .push(from + after.round() as Micros, Ev::Cut { machine });
        }
    }

    /// The coordinator's next pause (Poisson), while it runs.
    fn arm_coordinator_pause(&mut self) {
        if self.cfg.coordinator_pauses_per_hour > 0.0 {
            let hour = 3_600_000.0 * MS as f64;
            let after = self
                .pauses_rng
                .exponential(hour / self.cfg.coordinator_pauses_per_hour);
            self.agenda
                .push(self.now + after.round() as Micros, Ev::CoordinatorPause);
        }
    }

    fn hang(&mut self, machine: usize, epoch: u32) {
        let now = self.now;
        let m = &mut self.machines[machine];
        if m.epoch != epoch || m.life != Life::Running {
            return;
        }
        m.life = Life::Frozen;
        m.epoch += 1;
        self.out.hangs += 1;
        if !m.renders_hung {
            // (A render hang already took its capacity and froze its renders.)
            self.pause_renders(machine);
        }
        let at = now + self.failure_span(self.cfg.hang_min_ms, self.cfg.hang_max_ms);
        self.agenda.push(at, Ev::Thaw { machine });
    }

    /// A duration uniform in [min, max) ms, in µs, from the failures' generator.
    fn failure_span(&mut self, min_ms: u64, max_ms: u64) -> Micros {
        let span = self.failures_rng.range(min_ms as f64, max_ms as f64);
        (span * MS as f64).round() as Micros
    }

    /// The machine's renders stop where they are (a hang of the process or of its render
    /// threads), and its capacity leaves the farm's.
    fn pause_renders(&mut self, machine: usize) {
        let now = self.now;
        let m = &mut self.machines[machine];
        self.capacity.push((now, -m.capacity()));
        for r in &mut m.running {
            r.remaining = r.end - now;
        }
    }

    /// The machine's paused renders go on from where they stopped, and its capacity
    /// comes back.
    fn resume_renders(&mut self, machine: usize) {
        let now = self.now;
        let m = &mut self.machines[machine];
        let epoch = m.epoch;
        self.capacity.push((now, m.capacity()));
        for r in &mut m.running {
            // The pause shifts the render; its start moves with it, so that work done
            // counts only time running.
            r.started += now - (r.end - r.remaining);
            r.end = now + r.remaining;
            self.agenda.push(
                r.end,
                Ev::RenderDone {
                    machine,
                    epoch,
                    render: r.id,
                },
            );
        }
    }

    fn thaw(&mut self, machine: usize) {
        let now = self.now;
        let m = &mut self.machines[machine];
        if m.life != Life::Frozen {
            return;
        }
        m.life = Life::Running;
        m.epoch += 1;
        let epoch = m.epoch;
        if !m.renders_hung {
            self.resume_renders(machine);
        }
        let m = &mut self.machines[machine];
        let inbox = std::mem::take(&mut m.inbox);
        let reconnect = std::mem::replace(&mut m.reconnect_on_thaw, false);
        // The heartbeat resumes at once on a session already accepted; one accepted
        // while stopped starts its own when its `Welcome` is read below.
        if let Some(conn) = m.conn.filter(|&c| self.conns[c].welcomed) {
            self.agenda.push(
                now,
                Ev::HeartbeatTimer {
                    machine,
                    epoch,
                    conn,
                },
            );
        }
        for (conn, msg) in inbox {
            self.at_worker(conn, msg);
        }
        if reconnect && self.machines[machine].conn.is_none() {
            self.connect(machine);
        }
        self.arm_failures(machine);
        self.start_renders(machine);
    }

    /// The machine's render threads stop: what they render stays where it is, nothing
    /// new starts; heartbeats, messages and the queue go on.
    fn render_hang(&mut self, machine: usize, epoch: u32) {
        let now = self.now;
        let m = &mut self.machines[machine];
        if m.epoch != epoch || m.life != Life::Running || m.renders_hung {
            return;
        }
        m.renders_hung = true;
        self.out.render_hangs += 1;
        self.pause_renders(machine);
        let at = now + self.failure_span(self.cfg.render_hang_min_ms, self.cfg.render_hang_max_ms);
        self.agenda.push(at, Ev::RenderThaw { machine });
    }

    /// The render threads run again (if the process is running; a stopped one resumes
    /// them when it is thawed).
    fn render_thaw(&mut self, machine: usize) {
        let m = &mut self.machines[machine];
        if !m.renders_hung || m.life == Life::Dead {
            return;
        }
        m.renders_hung = false;
        if m.life != Life::Running {
            // Stopped meanwhile: its thaw restarts the renders (and the capacity).
            return;
        }
        self.resume_renders(machine);
        self.arm_render_hang(machine);
        self.start_renders(machine);
    }

    // --- measurements ----------------------------------------------------------------

    /// The scheduler's heap per job and per worker, measured on a separate scheduler as
    /// they are added: the jobs first (queued, nothing assigned), then the run's initial
    /// workers (each taking its credit of tiles), then the same workers alone on an
    /// empty scheduler.
    fn probe_memory(&self) -> Memory {
        let cfg = self.cfg;
        let tiles = cfg.tiles_per_job();
        let threads: Vec<u32> = self.machines.iter().map(|m| m.threads).collect();
        let join = |s: &mut Scheduler| {
            for (i, &threads) in threads.iter().enumerate() {
                drop(s.handle(
                    0,
                    Event::WorkerJoined {
                        worker: i as WorkerId + 1,
                        threads,
                        machine: None,
                    },
                ));
            }
        };
        let mut s = Scheduler::with_policy(cfg.policy);
        let start = live_bytes();
        for job in 1..=cfg.jobs as JobId {
            drop(s.handle(
                0,
                Event::JobSubmitted {
                    job,
                    priority: 0,
                    scene: scene_of(job),
                    tiles,
                },
            ));
        }
        let jobs_bytes = live_bytes() - start;
        let start = live_bytes();
        join(&mut s);
        let busy_bytes = live_bytes() - start;
        let in_flight = s.tiles_in_flight();
        drop(s);
        let mut s = Scheduler::with_policy(cfg.policy);
        let start = live_bytes();
        join(&mut s);
        let idle_bytes = live_bytes() - start;
        drop(s);
        let per = |bytes: i64, n: usize| bytes as f64 / n.max(1) as f64;
        Memory {
            per_job_queued: per(jobs_bytes, cfg.jobs),
            per_tile_queued: per(jobs_bytes, cfg.jobs * tiles as usize),
            per_worker_idle: per(idle_bytes, threads.len()),
            per_worker_busy: per(busy_bytes, threads.len()),
            per_tile_in_flight: per(busy_bytes - idle_bytes, in_flight),
            tiles_in_flight_probed: in_flight as u64,
            peak_bytes: 0,
            end_bytes: 0,
        }
    }

    /// The lower bound on the makespan (see [`Outcome::ideal_ms`]).
    fn ideal(&self) -> (f64, f64) {
        let start = self.jobs.iter().map(|j| j.sent).min().unwrap_or(0);
        // Before a job's first tile can start: its submission crosses the network, its
        // row is written, the tile crosses the network. After its last tile: the
        // result crosses the network, the image is encoded and written, the end is
        // written.
        let latency = micros(self.cfg.latency_ms);
        let before = (latency + self.row_write + latency) as f64;
        let after = (latency + self.image_encode + self.image_write + self.row_write) as f64;
        let first = start as f64 + before;
        let work: f64 = self
            .jobs
            .iter()
            .flat_map(|j| &j.costs)
            .map(|&c| c as f64)
            .sum();
        let mut changes = self.capacity.clone();
        changes.sort_by_key(|c| c.0);
        let mut capacity = 0.0;
        let mut i = 0;
        while i < changes.len() && changes[i].0 as f64 <= first {
            capacity += changes[i].1;
            i += 1;
        }
        let (mut t, mut done) = (first, 0.0);
        let mut work_bound = f64::INFINITY;
        loop {
            let next = changes.get(i).map_or(f64::INFINITY, |c| c.0 as f64);
            if capacity > 1e-9 && done + capacity * (next - t) >= work {
                work_bound = t + (work - done) / capacity + after;
                break;
            }
            if next.is_infinite() {
                break;
            }
            done += capacity.max(0.0) * (next - t);
            t = next;
            capacity += changes[i].1;
            i += 1;
        }
        let fastest = self
            .machines
            .iter()
            .filter(|m| m.life != Life::Off)
            .map(|m| m.speed)
            .fold(0.0, f64::max);
        let tile_bound = self
            .jobs
            .iter()
            .map(|j| {
                let longest = j.costs.iter().copied().max().unwrap_or(0) as f64;
                j.sent as f64 + before + longest / fastest + after
            })
            .fold(0.0, f64::max);
        let ms = |t: f64| (t - start as f64) / MS as f64;
        (ms(work_bound), ms(tile_bound))
    }

    fn into_report(mut self, memory: Option<Memory>, wall: Duration) -> SimReport {
        let start = self.jobs.iter().map(|j| j.sent).min().unwrap_or(0);
        let end = if self.out.timed_out {
            self.now
        } else {
            self.jobs
                .iter()
                .filter_map(|j| j.ended)
                .max()
                .unwrap_or(self.now)
        };
        let (work_bound, tile_bound) = self.ideal();
        let out = &mut self.out;
        out.threads_initial = self
            .machines
            .iter()
            .take(self.cfg.workers)
            .map(|m| u64::from(m.threads))
            .sum();
        out.tiles = self.jobs.iter().map(|j| j.costs.len() as u64).sum();
        out.work_ms = self
            .jobs
            .iter()
            .flat_map(|j| &j.costs)
            .map(|&c| c as f64 / MS as f64)
            .sum();
        out.makespan_ms = (end - start) as f64 / MS as f64;
        out.ideal_work_ms = work_bound;
        out.ideal_tile_ms = tile_bound;
        out.ideal_ms = work_bound.max(tile_bound);
        out.efficiency = if out.makespan_ms > 0.0 && out.ideal_ms.is_finite() {
            out.ideal_ms / out.makespan_ms
        } else {
            0.0
        };
        out.workers_at_end = self
            .machines
            .iter()
            .filter(|m| m.life == Life::Running || m.life == Life::Frozen)
            .count();
        out.events = self.sched.costs.iter().map(|c| c.count).sum();
        out.lifecycle_events = self.life.calls();
        if self.writer.down {
            out.storage_unavailable_ms += (self.now - self.writer.down_since) as f64 / MS as f64;
        }
        let memory = memory.map(|m| Memory {
            peak_bytes: self.sched.peak,
            end_bytes: self.sched.bytes,
            ..m
        });
        let costs = EVENT_KINDS
            .iter()
            .zip(self.sched.costs)
            .filter(|(_, c)| c.count > 0)
            .map(|(kind, c)| c.report(kind))
            .collect();
        let life = &self.life;
        let lifecycle_by_event: Vec<EventCost> = std::iter::once(life.admit.report("admit"))
            .filter(|c| c.count > 0)
            .chain(life.costs.iter().map(|(_, kind, c)| c.report(kind)))
            .collect();
        SimReport {
            outcome: self.out,
            memory,
            handle_time: self.sched.costs.iter().map(|c| c.total).sum(),
            by_event: costs,
            lifecycle_time: lifecycle_by_event.iter().map(|c| c.total).sum(),
            lifecycle_by_event,
            wall,
        }
    }
}

/// Virtual microseconds of a time in milliseconds.
fn micros(ms: f64) -> Micros {
    (ms * MS as f64).round() as Micros
}

/// A distinct scene per job (each frame of an animation is its own scene).
fn scene_of(job: JobId) -> SceneHash {
    let mut hash = [0u8; 32];
    hash[..8].copy_from_slice(&job.to_le_bytes());
    hash
}

/// The cost of each tile of a frame, in reference-thread microseconds, row by row like
/// the renderer's cut.
fn tile_costs(cfg: &SimConfig, rng: &mut Rng) -> Vec<Micros> {
    let (w, h, side) = (
        f64::from(cfg.width),
        f64::from(cfg.height),
        f64::from(cfg.tile_size),
    );
    let small = w.min(h);
    let spots: Vec<(f64, f64, f64)> = (0..cfg.hotspots)
        .map(|_| {
            (
                rng.range(0.0, w),
                rng.range(0.0, h),
                rng.range(0.05, 0.2) * small,
            )
        })
        .collect();
    let mut costs = Vec::with_capacity(cfg.tiles_per_job() as usize);
    for y in (0..cfg.height).step_by(cfg.tile_size as usize) {
        for x in (0..cfg.width).step_by(cfg.tile_size as usize) {
            let tw = f64::from(cfg.tile_size.min(cfg.width - x));
            let th = f64::from(cfg.tile_size.min(cfg.height - y));
            let (cx, cy) = (f64::from(x) + tw / 2.0, f64::from(y) + th / 2.0);
            // A smooth bump of compact support: (1 - d²/r²)² inside the radius.
            let bump = spots
                .iter()
                .map(|&(sx, sy, r)| {
                    let q = ((cx - sx) * (cx - sx) + (cy - sy) * (cy - sy)) / (r * r);
                    if q < 1.0 {
                        (1.0 - q) * (1.0 - q)
                    } else {
                        0.0
                    }
                })
                .fold(0.0, f64::max);
            let factor = (1.0 + (cfg.hotspot_factor - 1.0) * bump)
                * rng.range(1.0 - cfg.tile_noise, 1.0 + cfg.tile_noise);
            let cost = cfg.tile_ms * MS as f64 * (tw * th) / (side * side) * factor;
            costs.push((cost.round() as Micros).max(1));
        }
    }
    costs
}
