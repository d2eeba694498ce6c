//! The scheduler core: which tile goes to which worker, when a lease runs out, and when
//! a job is finished or has failed.
//!
//! A pure state machine. It owns no socket, no clock and no thread: the daemon feeds it
//! [`Event`]s, each with the time it happened, and carries out the [`Action`]s it
//! returns; tests feed it scripted or random events with a virtual clock. Every
//! decision of the farm is made here.
//!
//! Policy:
//! - **Pull with credit.** A worker holds at most its credit of tiles; it is sent the
//!   next one as soon as it returns one, so faster workers render more tiles. The
//!   credit is twice its threads, plus what covers the round trip once the daemon has
//!   measured it ([`Event::WorkerPace`]): each thread finishes a tile every tile time,
//!   so `threads × ⌈1.5 × rtt / tile time⌉` more tiles keep its threads busy while
//!   results and new assignments cross the network (the bandwidth-delay product, in
//!   tiles, with half a round trip to spare for the round trip's jitter).
//!   It is capped at [`Policy::max_credit_per_thread`] per thread, so that the tail of
//!   a job never waits behind a deep queue; stragglers are still copied.
//! - **Results confirmed by another machine.** A result the daemon wants confirmed
//!   ([`Event::TileToConfirm`]: every tile of a job in full verification, a random
//!   share of the others) is held, not accepted: the tile goes back to the queue for
//!   any machine but the one that rendered it, and is done when another machine's
//!   identical result comes ([`Event::TileDone`] on a held tile). An optional
//!   confirmation that no connected machine may give is dropped at a timeout and the
//!   held result accepted as it is ([`Action::AcceptHeld`]); a required one waits,
//!   and its job stalls like any tile no machine may take.
//! - **Quarantine.** A machine caught returning wrong pixels ([`Event::Quarantine`])
//!   gets no tile again; its tiles go back to the queue, its held results are
//!   dropped, and the tiles it had done that the daemon revokes are rendered again.
//! - **Priority, then fair share, then FIFO.** A free slot goes to the highest-priority
//!   job with tiles waiting; among jobs of that priority, to the one with the fewest
//!   tiles in flight; among those, to the oldest. One job alone gets the whole farm;
//!   two jobs of equal priority split it evenly, so a small job behind a huge one
//!   finishes in about twice its solo time instead of waiting for the huge one.
//! - **Leases.** Every assignment has a deadline: a few times the job's measured tile
//!   time (a generous default before the first tile is measured; when the first is,
//!   the leases given under the default end no later than their start plus the
//!   measured lease). A tile whose lease runs out goes back to the queue; its first
//!   holder may still deliver it.
//! - **Liveness from heartbeats.** A worker not heard from within the heartbeat
//!   timeout is dropped and its tiles go back to the queue.
//! - **Trust from results.** A heartbeat proves a connection, not progress: a worker
//!   whose render threads hang keeps talking. So a worker that holds a tile late (its
//!   lease ran out, or another worker's copy was accepted first) and has returned no
//!   result (nor reported a failure) for longer than its allowance is marked
//!   **unresponsive** ([`Action::WorkerUnresponsive`]): it gets no tile, its live
//!   leases run out at once (its tiles go to others; its results still count if they
//!   come first), and it no longer counts as a machine that may take or confirm work,
//!   so held results it was the only other machine for are accepted and stalls are
//!   seen. Its first result makes it responsive again ([`Action::WorkerResponsive`]).
//!   The allowance is the greater of [`Policy::progress_timeout`] and
//!   [`Policy::progress_factor`] times its pace: the longest it took for one result
//!   once free to work on it, or the slowest measured tile of the jobs it holds. A slow
//!   worker is slow in its own results too, so it is given the time it needs; only
//!   silence far past its own pace marks it. It stays connected: a render thread that
//!   comes back needs no reconnection, and a worker that is only slow loses nothing.
//! - **Stragglers.** When a job has no tile left waiting, a worker with free credit is
//!   also given a tile still in flight elsewhere (the one out longest, at most two
//!   holders per tile). The first result wins; a later copy is checked equal.
//! - **First result wins.** A result or a failure for a tile the sender does not hold
//!   (any more) changes nothing.
//! - **Poison tiles, reported.** A tile the worker reports failed ([`Event::TileFailed`])
//!   is retried on other machines, never on one it failed on; after
//!   [`Policy::max_attempts`] reports the job fails with the last error. A machine that
//!   reports [`Policy::block_after`] failed tiles of a job gets no more of that job's
//!   tiles. Both count per machine (the name a worker gives), so a worker that comes
//!   back under the same name is not handed again what it failed.
//! - **Lost connections are not failures.** A worker whose connection closes or that
//!   misses its heartbeats may have crashed on a tile, but just as well been restarted,
//!   cut off by the network or stopped by its host: a closed connection proves nothing
//!   about the machine. So its tiles go back to the queue and nothing counts against the
//!   machine: no block, no attempt, and the tiles may go to the same name again once it
//!   reconnects (a supervised worker restarted under its name is not locked out of the
//!   job). Poison tiles that kill their workers are still caught: each tile counts the
//!   times it was lost with its worker, and its job fails at [`Policy::max_losses`].
//!   Healthy tiles are lost with a crash or a cut only by ill luck, a few times at
//!   most; a tile that takes down every worker it reaches is lost every time.
//! - **No job waits forever.** A job with tiles waiting, while live workers are
//!   connected (not draining) and none of them may take any of its waiting tiles (each
//!   machine is blocked from the job, or the tile failed on it), fails once that has
//!   lasted [`Policy::stall_timeout`], with a message naming a tile and the machines.
//!   Without any worker connected a job just waits: a worker may come.
//! - **Storage first.** While the daemon cannot record results
//!   ([`Event::StorageUnavailable`]) no tile is handed out, copies included: a result
//!   that cannot be stored is work thrown away. Results of tiles already out are still
//!   accepted, and [`Event::StorageAvailable`] fills every worker again.
//! - **Scenes once.** A worker is sent a scene before its first tile of it, and only
//!   then; it may forget the scene once no active job uses it.
//!
//! Time: every event carries the daemon's monotonic clock, and [`Event::Timeout`] is
//! where time alone acts (silent workers are dropped, leases run out, stalled jobs
//! fail). [`Scheduler::next_deadline`] tells when the next call is due: the earliest
//! heartbeat expiry, lease deadline or stall timeout, and never later than the last
//! `Timeout` (or the first call) plus [`Policy::wake_interval`] while any worker is
//! connected: a farm whose workers talk more often than that still gets its timeouts,
//! which is where stalls are noticed and unconfirmable results accepted.
//!
//! **Pauses are not failures.** Because a running daemon calls at least every
//! `wake_interval`, a gap between two calls longer than [`Policy::pause_threshold`]
//! means the coordinator itself did not run (stopped by a signal, a paused VM, a swap
//! storm), not that its peers fell silent: their messages are waiting unread in the
//! sockets. So the scheduler keeps its own clock, which follows the daemon's except
//! that such a gap counts only as one `wake_interval`. Heartbeat timeouts, leases, tile
//! times and stall timeouts all run on that clock: after a pause the daemon reads what
//! its peers sent before anyone's silence can reach the timeout. (A `wake_interval`
//! above `pause_threshold` is taken as `pause_threshold`, so that a daemon keeping to
//! [`Scheduler::next_deadline`] is never mistaken for a paused one.)
//!
//! Cost: the farm may have thousands of workers and hundreds of thousands of tiles, and
//! the daemon holds its lock for the whole of [`Scheduler::handle`]. So no event walks
//! every tile or every lease: each job keeps its tiles' state next to its queue, its
//! straggler candidates in the order they are chosen, and its live leases by deadline;
//! the jobs are kept in the order they are served; the workers by when they were last
//! heard from, and the machines ready for work with their count of workers; and only
//! workers with free credit are visited to be filled. An event costs time logarithmic
//! in the tiles, times what it changes, times the workers it fills. The stall check at
//! a timeout looks at the jobs, and in each at most the waiting tiles that failed
//! before (a tile that never failed may go to any machine not blocked). These indexes
//! only speed the decisions up: they are the same, event for event, as a search of
//! every tile would make.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::fmt;

use protocol::{JobId, SceneHash, WorkerId};

/// Milliseconds on the daemon's monotonic clock (or a test's virtual one).
pub type Millis = u64;

/// The knobs of the policy.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Policy {
    /// A worker silent for this long is dropped.
    pub heartbeat_timeout: Millis,
    /// The lease of a job's tiles before any of them has been measured.
    pub initial_lease: Millis,
    /// No lease is shorter than this, however fast the tiles.
    pub min_lease: Millis,
    /// A lease lasts this many times the job's slowest measured tile (and at least
    /// four times its mean).
    pub lease_factor: u64,
    /// Failures of one tile reported by workers before its job fails.
    pub max_attempts: u32,
    /// Failures of one job's tiles reported by one machine before the machine is
    /// blocked from the job.
    pub block_after: u32,
    /// Whether to duplicate stragglers near the end of a job.
    pub speculate: bool,
    /// Times one tile may be lost with its worker (connection closed, or dropped for
    /// silence, while holding it) before its job fails: a tile that crashes whoever
    /// renders it, or a farm whose workers keep losing their connection.
    pub max_losses: u32,
    /// How long a job with tiles waiting may go with workers connected but none that
    /// may take any of them before it fails.
    pub stall_timeout: Millis,
    /// The most tiles a worker may hold per thread, however long its round trip.
    pub max_credit_per_thread: u32,
    /// A gap between two calls longer than this is a pause of the coordinator itself,
    /// and counts only as one `wake_interval` (see the module doc).
    pub pause_threshold: Millis,
    /// The longest the daemon may wait between two calls while a worker is connected.
    pub wake_interval: Millis,
    /// The least time a worker holding a tile whose lease ran out may go without
    /// returning any result before it is marked unresponsive (see the module doc).
    pub progress_timeout: Millis,
    /// ... or this many times its pace (its slowest time per result, or the slowest
    /// measured tile of the jobs it holds), when that is longer.
    pub progress_factor: u64,
}

impl Default for Policy {
    fn default() -> Self {
        Policy {
            heartbeat_timeout: 5_000,
            initial_lease: 60_000,
            min_lease: 1_000,
            lease_factor: 3,
            max_attempts: 5,
            block_after: 2,
            speculate: true,
            max_losses: 8,
            stall_timeout: 30_000,
            max_credit_per_thread: 256,
            pause_threshold: 2_000,
            wake_interval: 1_000,
            progress_timeout: 20_000,
            progress_factor: 16,
        }
    }
}

impl Policy {
    /// The wake interval in effect: at least 1 ms, and no more than the pause threshold,
    /// so that a daemon keeping to [`Scheduler::next_deadline`] never looks paused.
    fn wake(&self) -> Millis {
        self.wake_interval.clamp(1, self.pause_threshold.max(1))
    }
}

/// Something that happened, as the daemon saw it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// The deadline of [`Scheduler::next_deadline`] came (or the daemon looks anyway):
    /// silent workers are dropped, leases run out, stalled jobs fail.
    Timeout,
    /// A worker connected. `machine` is the name it gave, if any: reported failures and
    /// blocks are counted per machine, so that a worker that fails a job's tiles and
    /// comes back under the same name (a restarted service) is still kept from them.
    /// A worker without one is a machine of its own.
    WorkerJoined {
        worker: WorkerId,
        threads: u32,
        machine: Option<String>,
    },
    /// The worker is alive (any message from it counts as much).
    Heartbeat {
        worker: WorkerId,
    },
    /// The worker's connection is gone; its tiles go back to their queues. Nothing
    /// counts against its machine: a lost connection proves nothing about it. Each
    /// tile it held counts one loss towards [`Policy::max_losses`].
    WorkerLeft {
        worker: WorkerId,
    },
    /// The worker is shutting down: it finishes what it holds and gets nothing more.
    WorkerDraining {
        worker: WorkerId,
    },
    JobSubmitted {
        job: JobId,
        priority: i32,
        scene: SceneHash,
        tiles: u32,
    },
    /// A result from the worker that counts: either alone, or, on a tile whose result
    /// from another machine is held, as its confirmation (the daemon found the two
    /// identical).
    TileDone {
        worker: WorkerId,
        job: JobId,
        tile: u32,
    },
    /// A result that counts only once another machine returns the same bytes: it is
    /// held, and the tile goes to another machine. `required` confirmations wait for
    /// a machine; optional ones (audits) are given up when none may give them.
    TileToConfirm {
        worker: WorkerId,
        job: JobId,
        tile: u32,
        required: bool,
    },
    /// The machine returned wrong pixels: it gets no tile again, its tiles and held
    /// results go back to the queue, and so do the done tiles of `revoke` (those the
    /// daemon accepted from it in active jobs).
    Quarantine {
        machine: String,
        revoke: Vec<(JobId, u32)>,
    },
    /// The daemon measured the worker's round trip and its time per tile (on one
    /// thread): its credit follows.
    WorkerPace {
        worker: WorkerId,
        rtt: Millis,
        tile: Millis,
    },
    /// The worker could not render the tile.
    TileFailed {
        worker: WorkerId,
        job: JobId,
        tile: u32,
        message: String,
    },
    CancelJob {
        job: JobId,
    },
    /// An operator paused the job: none of its tiles is handed out (copies included)
    /// until `ResumeJob`. Tiles already out may finish and count. A paused job never
    /// stalls: waiting is what it was asked to do. The pause holds for a job not yet
    /// submitted or resumed (the daemon restores a paused job this way).
    PauseJob {
        job: JobId,
    },
    /// The job renders for an interactive view (docs/studio.md): its tiles go ahead of
    /// every batch job's, whatever their priorities, but while batch tiles wait at
    /// least one tile in every [`INTERACTIVE_RUN`] + 1 handed out is a batch tile, so
    /// that batch jobs are slowed, never starved. Holds for the job's life (a daemon
    /// that renders a job in several runs marks each run).
    Interactive {
        job: JobId,
    },
    /// The paused job's tiles are handed out again.
    ResumeJob {
        job: JobId,
    },
    /// The job's priority changed: the next free slots follow the new order.
    SetPriority {
        job: JobId,
        priority: i32,
    },
    /// Storage cannot record results: hand out no new tile (results of tiles already
    /// out are still accepted) until `StorageAvailable`.
    StorageUnavailable,
    /// Storage records results again: every worker is filled.
    StorageAvailable,
    /// An operator disabled the machine: its workers get no new tile (tiles they hold
    /// may finish and count) until `EnableMachine`. Kept by machine name, so that it
    /// holds for workers of that machine that connect later.
    DisableMachine {
        machine: String,
    },
    /// The disabled machine's workers take tiles again.
    EnableMachine {
        machine: String,
    },
    /// An operator has the job's tiles rendered again, wherever they are: waiting
    /// (nothing changes), out on workers (their results will count for nothing; their
    /// slots are free at once), held for confirmation (dropped), or done (taken back).
    /// Tile numbers past the job's are ignored (the daemon refuses them first).
    RequeueTiles {
        job: JobId,
        tiles: Vec<u32>,
    },
}

/// What the daemon must do.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Action {
    /// Send the job's scene to the worker (before the `Assign` that follows).
    SendScene {
        worker: WorkerId,
        job: JobId,
    },
    /// Send the tile to the worker.
    Assign {
        worker: WorkerId,
        job: JobId,
        tile: u32,
    },
    /// Keep this result: it is the first for the tile.
    AcceptTile {
        job: JobId,
        tile: u32,
    },
    /// A second result for a tile already accepted: it must equal the first.
    DuplicateResult {
        job: JobId,
        tile: u32,
    },
    /// Keep this result aside: it counts once another machine's result equals it.
    HoldResult {
        worker: WorkerId,
        job: JobId,
        tile: u32,
    },
    /// No connected machine may confirm the held result: accept it as it is.
    AcceptHeld {
        job: JobId,
        tile: u32,
    },
    /// Tell the worker to drop the job's tiles it still holds.
    CancelOnWorker {
        worker: WorkerId,
        job: JobId,
    },
    /// The worker may drop the scene from its cache: no active job uses it.
    ForgetScene {
        worker: WorkerId,
        scene: SceneHash,
    },
    /// The worker missed its heartbeats: close its connection.
    DropWorker {
        worker: WorkerId,
    },
    /// The worker holds tiles whose leases ran out and has returned nothing for
    /// `silent` ms: it is marked unresponsive (it stays connected; its tiles are
    /// rendered elsewhere).
    WorkerUnresponsive {
        worker: WorkerId,
        silent: Millis,
    },
    /// An unresponsive worker returned a result: it takes tiles again.
    WorkerResponsive {
        worker: WorkerId,
    },
    /// Every tile is done: assemble and store the image.
    JobDone {
        job: JobId,
    },
    JobFailed {
        job: JobId,
        message: String,
    },
}

/// One assignment of a tile to a worker.
#[derive(Clone, Copy, Debug)]
struct Lease {
    worker: WorkerId,
    started: Millis,
    deadline: Millis,
    /// Ran out: the tile was put back in the queue, but this holder may still deliver.
    expired: bool,
}

/// Where a tile of an active job stands. One byte per tile: a job of a million tiles
/// is mostly tiles waiting, and they should cost little more than their place in the
/// queue.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum TileState {
    /// In the queue (possibly also still held under leases that ran out).
    Waiting,
    /// Out of the queue and not done: held by workers.
    Out,
    /// Accepted; it never waits again.
    Done,
}

/// The earliest start among a tile's leases, if exactly one of them is live: the key
/// by which a tile is a straggler candidate, and its rank among them.
fn straggler_key(leases: &[Lease]) -> Option<Millis> {
    let mut live = leases.iter().filter(|l| !l.expired);
    match (live.next(), live.next()) {
        (Some(_), None) => leases.iter().map(|l| l.started).min(),
        _ => None,
    }
}

/// A job's rank for a free slot: highest priority, then fewest tiles in flight, then
/// oldest (ids grow with submission order).
type JobRank = (Reverse<i32>, usize, JobId);

/// At most this many tiles in a row go to interactive jobs while batch tiles wait.
pub const INTERACTIVE_RUN: u32 = 4;

struct Job {
    priority: i32,
    /// Renders for an interactive view ([`Event::Interactive`]).
    interactive: bool,
    scene: SceneHash,
    /// The tiles waiting, in the order they are handed out. Accepting a tile that is
    /// still queued (its lease ran out, then its holder delivered) leaves its entry
    /// here rather than searching the queue for it; entries of done tiles are skipped,
    /// and dropped when met. A done tile waits again only when it is revoked (a
    /// quarantine); it is then put at the head, before any stale entry of its own, so
    /// the first entry of each waiting tile is its place in the queue.
    waiting: VecDeque<u32>,
    /// The tiles waiting: the entries of `waiting` that are not stale.
    queued: u32,
    state: Vec<TileState>,
    in_flight: BTreeMap<u32, Vec<Lease>>,
    /// The tiles of `in_flight` with exactly one live lease, by [`straggler_key`] then
    /// number: the candidates for a copy, the one out longest first. Kept so that a
    /// worker with free credit finds its straggler without walking every tile in
    /// flight.
    stragglers: BTreeSet<(Millis, u32)>,
    /// The live leases by deadline, so that a timeout looks only at those that ran out.
    deadlines: BTreeSet<(Millis, u32, WorkerId)>,
    remaining: u32,
    /// Failures reported per tile, and the machines each tile failed on.
    failures: BTreeMap<u32, (u32, BTreeSet<Machine>)>,
    /// Times each tile was lost with its worker.
    losses: BTreeMap<u32, u32>,
    /// Since when (on the scheduler's clock) no connected worker may take any waiting
    /// tile, as last seen at a timeout.
    stalled_since: Option<Millis>,
    /// Failures per machine, and the machines blocked from this job.
    worker_failures: BTreeMap<Machine, u32>,
    blocked: BTreeSet<Machine>,
    /// Holders of tiles already accepted, whose copies are still to come.
    late_copies: BTreeSet<(u32, WorkerId)>,
    /// Tiles whose result is held for confirmation: the machine that rendered it (it
    /// may not confirm itself) and whether the confirmation is required.
    held: BTreeMap<u32, (Machine, bool)>,
    /// Measured tile times (assignment to result).
    measured: u32,
    total_time: Millis,
    slowest: Millis,
}

impl Job {
    fn new(priority: i32, scene: SceneHash, tiles: u32) -> Job {
        Job {
            priority,
            interactive: false,
            scene,
            waiting: (0..tiles).collect(),
            queued: tiles,
            state: vec![TileState::Waiting; tiles as usize],
            in_flight: BTreeMap::new(),
            stragglers: BTreeSet::new(),
            deadlines: BTreeSet::new(),
            remaining: tiles,
            failures: BTreeMap::new(),
            losses: BTreeMap::new(),
            stalled_since: None,
            worker_failures: BTreeMap::new(),
            blocked: BTreeSet::new(),
            late_copies: BTreeSet::new(),
            held: BTreeMap::new(),
            measured: 0,
            total_time: 0,
            slowest: 0,
        }
    }

    fn rank(&self, id: JobId) -> JobRank {
        (Reverse(self.priority), self.in_flight.len(), id)
    }

    fn is_waiting(&self, tile: u32) -> bool {
        self.state.get(tile as usize) == Some(&TileState::Waiting)
    }

    /// Whether the tile's result is held from this machine, which may then not render
    /// it again.
    fn held_from(&self, tile: u32, machine: &Machine) -> bool {
        self.held.get(&tile).is_some_and(|(m, _)| m == machine)
    }

    /// Puts a tile that is not done back at the head of the queue, unless it waits
    /// already. Returns whether it was put back.
    fn requeue(&mut self, tile: u32) -> bool {
        debug_assert_ne!(self.state[tile as usize], TileState::Done);
        if self.is_waiting(tile) {
            return false;
        }
        self.waiting.push_front(tile);
        self.state[tile as usize] = TileState::Waiting;
        self.queued += 1;
        true
    }

    fn live_leases(&self, tile: u32) -> usize {
        self.in_flight
            .get(&tile)
            .map_or(0, |ls| ls.iter().filter(|l| !l.expired).count())
    }

    fn lease_length(&self, policy: &Policy) -> Millis {
        if self.measured == 0 {
            return policy.initial_lease;
        }
        let mean = self.total_time / u64::from(self.measured);
        (self.slowest * policy.lease_factor)
            .max(mean * 4)
            .max(policy.min_lease)
    }

    /// Brings every live lease's deadline down to its start plus `length`, where that
    /// is sooner: done once, when the job's first tile is measured, so that the tiles
    /// handed out under the initial lease (a guess, 60 s by default) are held no longer
    /// than the job's measured pace allows. A worker that hung on its first tiles is
    /// then found out as soon as one on a working machine is. Walks the tiles in
    /// flight, once per job.
    fn shorten_leases(&mut self, length: Millis) {
        for (&tile, leases) in &mut self.in_flight {
            for lease in leases.iter_mut().filter(|l| !l.expired) {
                let deadline = lease.started.saturating_add(length);
                if deadline < lease.deadline {
                    self.deadlines.remove(&(lease.deadline, tile, lease.worker));
                    lease.deadline = deadline;
                    self.deadlines.insert((deadline, tile, lease.worker));
                }
            }
        }
    }

    /// Moves the tile between straggler candidates after its leases changed.
    fn restraggle(&mut self, tile: u32, before: Option<Millis>, after: Option<Millis>) {
        if before != after {
            if let Some(started) = before {
                self.stragglers.remove(&(started, tile));
            }
            if let Some(started) = after {
                self.stragglers.insert((started, tile));
            }
        }
    }

    fn add_lease(&mut self, tile: u32, lease: Lease) {
        let leases = self.in_flight.entry(tile).or_default();
        let before = straggler_key(leases);
        leases.push(lease);
        let after = straggler_key(leases);
        self.deadlines.insert((lease.deadline, tile, lease.worker));
        self.restraggle(tile, before, after);
    }

    /// Ends the worker's lease on the tile, if it has one.
    fn remove_lease(&mut self, tile: u32, worker: WorkerId) -> Option<Lease> {
        let leases = self.in_flight.get_mut(&tile)?;
        let pos = leases.iter().position(|l| l.worker == worker)?;
        let before = straggler_key(leases);
        let lease = leases.remove(pos);
        let after = straggler_key(leases);
        if leases.is_empty() {
            self.in_flight.remove(&tile);
        }
        if !lease.expired {
            self.deadlines.remove(&(lease.deadline, tile, worker));
        }
        self.restraggle(tile, before, after);
        Some(lease)
    }

    /// Ends every lease on the tile, returning them.
    fn take_leases(&mut self, tile: u32) -> Option<Vec<Lease>> {
        let leases = self.in_flight.remove(&tile)?;
        for l in leases.iter().filter(|l| !l.expired) {
            self.deadlines.remove(&(l.deadline, tile, l.worker));
        }
        self.restraggle(tile, straggler_key(&leases), None);
        Some(leases)
    }

    /// Marks the leases whose deadline has come as run out, and puts back in the queue
    /// (in increasing tile order, each at the head) the tiles left with no live lease.
    /// Marks the leases due by `now` expired and requeues the tiles all of whose leases
    /// ran out; counts both.
    /// The workers whose leases ran out join `overdue`.
    fn expire_leases(
        &mut self,
        now: Millis,
        counters: &mut Counters,
        overdue: &mut BTreeSet<WorkerId>,
    ) {
        let mut due = Vec::new();
        while let Some(&(deadline, tile, _)) = self.deadlines.first() {
            if deadline > now {
                break;
            }
            self.deadlines.pop_first();
            due.push(tile);
        }
        due.sort_unstable();
        due.dedup();
        for tile in due {
            let leases = self
                .in_flight
                .get_mut(&tile)
                .expect("a live lease is in flight");
            let before = straggler_key(leases);
            for lease in leases
                .iter_mut()
                .filter(|l| !l.expired && l.deadline <= now)
            {
                lease.expired = true;
                counters.leases_expired += 1;
                overdue.insert(lease.worker);
            }
            let all_expired = leases.iter().all(|l| l.expired);
            let after = straggler_key(leases);
            self.restraggle(tile, before, after);
            if all_expired && self.requeue(tile) {
                counters.tiles_requeued += 1;
            }
        }
    }

    /// Ends the worker's live lease on the tile now, if it has one, and puts the tile
    /// back in the queue if no live lease is left; counts both.
    fn expire_lease_of(&mut self, tile: u32, worker: WorkerId, counters: &mut Counters) {
        let Some(leases) = self.in_flight.get_mut(&tile) else {
            return;
        };
        let before = straggler_key(leases);
        let Some(lease) = leases.iter_mut().find(|l| l.worker == worker && !l.expired) else {
            return;
        };
        lease.expired = true;
        let deadline = lease.deadline;
        counters.leases_expired += 1;
        let all_expired = leases.iter().all(|l| l.expired);
        let after = straggler_key(leases);
        self.deadlines.remove(&(deadline, tile, worker));
        self.restraggle(tile, before, after);
        if all_expired && self.state[tile as usize] != TileState::Done && self.requeue(tile) {
            counters.tiles_requeued += 1;
        }
    }

    /// The first waiting tile this worker may take: one that has not failed on it and
    /// that it does not still hold under an expired lease.
    fn take_waiting_for(&mut self, worker: WorkerId, machine: &Machine) -> Option<u32> {
        if self.queued == 0 {
            // Whatever is left are entries of done tiles.
            self.waiting.clear();
            return None;
        }
        while let Some(&t) = self.waiting.front() {
            if self.state[t as usize] != TileState::Done {
                break;
            }
            self.waiting.pop_front();
        }
        let pos = self.waiting.iter().position(|t| {
            self.state[*t as usize] == TileState::Waiting
                && self
                    .failures
                    .get(t)
                    .is_none_or(|(_, on)| !on.contains(machine))
                && !self.held_from(*t, machine)
                && self
                    .in_flight
                    .get(t)
                    .is_none_or(|ls| ls.iter().all(|l| l.worker != worker))
        })?;
        let tile = self.waiting.remove(pos)?;
        self.state[tile as usize] = TileState::Out;
        self.queued -= 1;
        Some(tile)
    }

    /// The first waiting tile (in queue order) if no machine of `ready` (those with a
    /// live worker that is not draining) may take any waiting tile: each is blocked
    /// from the job or the tile failed on it. `None` while one may, or nothing waits.
    ///
    /// Cheap enough for every timeout: a tile that never failed and holds no result may
    /// go to any machine not blocked, so the walk stops at the first such tile; and a
    /// tile fails on fewer than `max_attempts` machines before its job fails, and holds
    /// the result of at most one, so with one more machine open nothing is stalled. The
    /// walk is over the waiting tiles that failed before or hold a result.
    fn stalled_tile(&self, ready: &BTreeMap<Machine, u32>, max_attempts: u32) -> Option<u32> {
        if self.queued == 0 || ready.is_empty() {
            return None;
        }
        // A waiting tile is closed to the machines it failed on (fewer than
        // `max_attempts`) and to the one whose result it holds, if any.
        let limit = (max_attempts as usize).max(1) + 1;
        let open: Vec<&Machine> = ready
            .keys()
            .filter(|m| !self.blocked.contains(*m))
            .take(limit)
            .collect();
        if open.len() >= limit {
            return None;
        }
        let mut first = None;
        for &t in &self.waiting {
            if self.state[t as usize] != TileState::Waiting {
                continue;
            }
            let takeable = match (self.failures.get(&t), self.held.get(&t)) {
                (None, None) => !open.is_empty(),
                (failures, held) => open.iter().any(|m| {
                    failures.is_none_or(|(_, on)| !on.contains(*m))
                        && held.is_none_or(|(from, _)| from != *m)
                }),
            };
            if takeable {
                return None;
            }
            first.get_or_insert(t);
            if open.is_empty() {
                break;
            }
        }
        first
    }

    /// Why no machine of `ready` may take the tile, in one line.
    fn stall_message(&self, tile: u32, ready: &BTreeMap<Machine, u32>, block_after: u32) -> String {
        let on = self.failures.get(&tile).map(|(_, on)| on);
        let (failed, blocked): (Vec<&Machine>, Vec<&Machine>) = ready
            .keys()
            .partition(|m| on.is_some_and(|on| on.contains(*m)));
        let head = format!("no connected worker may render tile {tile}");
        let holder = self.held.get(&tile).map(|(m, _)| m);
        if let Some(holder) = holder.filter(|m| blocked.contains(m)) {
            // Not blocked: the tile holds its result, which it may not confirm.
            let others: Vec<&Machine> = blocked.into_iter().filter(|m| *m != holder).collect();
            let rest = match (failed.is_empty(), others.is_empty()) {
                (true, true) => "no other machine is connected".to_string(),
                (false, true) => format!("it failed on the others ({})", name_list(&failed)),
                (true, false) => format!(
                    "the others are blocked from the job after failing {block_after} of its \
                     tiles ({})",
                    name_list(&others)
                ),
                (false, false) => format!(
                    "it failed on some of the others ({}) and the rest are blocked from the \
                     job after failing {block_after} of its tiles ({})",
                    name_list(&failed),
                    name_list(&others)
                ),
            };
            return format!(
                "{head}: its result from {} awaits confirmation by another machine, and {rest}",
                name_list(&[holder])
            );
        }
        match (failed.is_empty(), blocked.is_empty()) {
            (_, true) => format!(
                "{head}: it failed on every one of them ({})",
                name_list(&failed)
            ),
            (true, false) => format!(
                "{head}: every one of them is blocked from the job after failing \
                 {block_after} of its tiles ({})",
                name_list(&blocked)
            ),
            (false, false) => format!(
                "{head}: it failed on some of them ({}) and the others are blocked from \
                 the job after failing {block_after} of its tiles ({})",
                name_list(&failed),
                name_list(&blocked)
            ),
        }
    }

    /// The tile to duplicate for an idle worker: in flight with one live holder that is
    /// not this worker, never failed on its machine, out the longest (earliest start
    /// among its leases, then lowest number). The candidates are kept in that order, so
    /// this skips at most the worker's own tiles and the few that failed on it.
    fn straggler_for(&self, worker: WorkerId, machine: &Machine) -> Option<u32> {
        self.stragglers.iter().map(|&(_, t)| t).find(|t| {
            self.in_flight[t].iter().all(|l| l.worker != worker)
                && self
                    .failures
                    .get(t)
                    .is_none_or(|(_, on)| !on.contains(machine))
                && !self.held_from(*t, machine)
        })
    }
}

/// Who failures are counted against: the name a worker gave, or its connection.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Machine {
    Named(String),
    Connection(WorkerId),
}

impl fmt::Display for Machine {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Machine::Named(name) => f.write_str(name),
            Machine::Connection(id) => write!(f, "worker {id}"),
        }
    }
}

/// Machines named in a message: the first few, so that a farm of thousands keeps the
/// message on one readable line (and no control character a worker put in its name
/// breaks it).
fn name_list(machines: &[&Machine]) -> String {
    const SHOWN: usize = 8;
    let printable = |m: &&Machine| m.to_string().replace(char::is_control, "?");
    let mut list: Vec<String> = machines.iter().take(SHOWN).map(printable).collect();
    if machines.len() > SHOWN {
        list.push(format!("and {} more", machines.len() - SHOWN));
    }
    list.join(", ")
}

struct Worker {
    machine: Machine,
    threads: u32,
    credit: usize,
    holding: BTreeSet<(JobId, u32)>,
    scenes: BTreeSet<SceneHash>,
    draining: bool,
    /// Its machine is disabled by an operator: like draining, but undone by an enable.
    disabled: bool,
    last_seen: Millis,
    /// It holds tiles whose leases ran out and returned nothing for longer than its
    /// progress allowance: its heartbeats prove a connection, not that it renders. It
    /// gets no tile and counts for no one (see the module doc) until a result comes.
    unresponsive: bool,
    /// Since when a result is due from it: its last result, or when it was last given
    /// a tile while holding none.
    progress_since: Millis,
    /// The longest it took to return a result once it was free to work on it (since
    /// the tile's lease began or its previous result, whichever is later): its pace.
    slowest_result: Millis,
}

impl Worker {
    /// Whether it may be given new tiles.
    fn takes_tiles(&self) -> bool {
        !self.draining && !self.disabled && !self.unresponsive
    }
}

/// The scheduler's whole state.
#[derive(Default)]
pub struct Scheduler {
    policy: Policy,
    /// The scheduler's own clock: the daemon's, less the pauses (see the module doc).
    now: Millis,
    /// The daemon's clock at the last call, once there was one.
    wall: Option<Millis>,
    /// The scheduler's clock at the last `Timeout` (or the first call): the next one is
    /// due a wake interval later at the latest.
    last_timeout: Millis,
    /// Active jobs (queued or running), by id; ids grow with submission order.
    jobs: BTreeMap<JobId, Job>,
    /// The active jobs in the order a free slot serves them ([`Job::rank`]).
    order: BTreeSet<JobRank>,
    workers: BTreeMap<WorkerId, Worker>,
    /// The workers by when they were last heard from, so that a timeout looks only at
    /// those that fell silent.
    by_last_seen: BTreeSet<(Millis, WorkerId)>,
    /// The machines with a live worker that is not draining, and how many: those that
    /// could take a tile, for the stall check.
    ready: BTreeMap<Machine, u32>,
    /// Every live worker that is not draining and holds less than its credit, and
    /// perhaps some that are full again: filling a worker drops it from here once it is
    /// full, and anything that frees a slot puts it back. Filling everyone visits only
    /// these, in id order.
    hungry: BTreeSet<WorkerId>,
    /// The workers that have each scene (the index of [`Worker::scenes`]), so that the
    /// end of a job visits only those that had its scene, not every worker.
    scene_holders: BTreeMap<SceneHash, BTreeSet<WorkerId>>,
    /// Storage cannot record results: no tile goes out.
    storage_down: bool,
    /// Jobs paused by an operator: none of their tiles goes out. Kept by id, not in
    /// the job, so that a pause holds from before the job is submitted and across
    /// the passes of an adaptive job (each a [`Scheduler::resume_job`]).
    paused: BTreeSet<JobId>,
    /// Tiles handed out in a row to interactive jobs (see [`Event::Interactive`]).
    interactive_run: u32,
    /// Machines caught returning wrong pixels: they get no tile again.
    quarantined: BTreeSet<Machine>,
    /// Machines an operator disabled: they get no new tile until enabled.
    disabled: BTreeSet<Machine>,
    /// Every worker that holds a tile late (under a lease that ran out, or a copy of a
    /// tile accepted from another worker since), and perhaps some that no longer do:
    /// those whose progress a timeout checks. A worker joins when one of its leases
    /// runs out or its copy becomes late, and leaves when a timeout finds it holds
    /// nothing late.
    overdue: BTreeSet<WorkerId>,
    counters: Counters,
}

/// What the scheduler has done since it started, for monitoring.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Counters {
    /// Leases that ran out before their tile came back.
    pub leases_expired: u64,
    /// Tiles put back in the queue to be rendered again: their leases ran out, their
    /// worker was lost, or they failed.
    pub tiles_requeued: u64,
    /// Workers dropped for missing their heartbeats.
    pub workers_dropped: u64,
    /// Times a worker was marked unresponsive: leases ran out and no result came.
    pub workers_unresponsive: u64,
}

impl Scheduler {
    /// A scheduler with the default policy.
    pub fn new() -> Self {
        Self::default()
    }

    pub fn with_policy(policy: Policy) -> Self {
        Scheduler {
            policy,
            ..Self::default()
        }
    }

    /// Applies one event at time `now` (ms on a monotonic clock; never decreasing, a
    /// smaller value is taken as the last one) and returns the actions, in order.
    pub fn handle(&mut self, now: Millis, event: Event) -> Vec<Action> {
        self.advance(now);
        let mut actions = Vec::new();
        match event {
            Event::Timeout => {
                self.last_timeout = self.now;
                self.check_heartbeats(&mut actions);
                self.check_leases();
                self.check_progress(&mut actions);
                self.give_up_confirmations(&mut actions);
                self.check_stalls(&mut actions);
                self.fill_all(&mut actions);
            }
            Event::WorkerJoined {
                worker,
                threads,
                machine,
            } => {
                let machine = machine.map_or(Machine::Connection(worker), Machine::Named);
                let joined = Worker {
                    machine: machine.clone(),
                    threads: threads.max(1),
                    credit: 2 * threads.max(1) as usize,
                    holding: BTreeSet::new(),
                    scenes: BTreeSet::new(),
                    draining: false,
                    disabled: self.disabled.contains(&machine),
                    last_seen: self.now,
                    unresponsive: false,
                    progress_since: self.now,
                    slowest_result: 0,
                };
                let quarantined = self.quarantined.contains(&machine);
                // A quarantined machine's worker is kept like a draining one: connected
                // (so that listings show it), never given a tile.
                let joined = Worker {
                    draining: quarantined,
                    ..joined
                };
                if joined.takes_tiles() {
                    *self.ready.entry(machine).or_default() += 1;
                }
                // A second hello on a live id replaces the worker (a daemon bug, but
                // the indexes must stay true). The new one counts first: a worker stays
                // connected throughout, so no stall ends.
                if let Some(old) = self.workers.insert(worker, joined) {
                    self.by_last_seen.remove(&(old.last_seen, worker));
                    self.unlist_scenes(worker, &old.scenes);
                    if old.takes_tiles() {
                        self.unready(&old.machine);
                    }
                }
                self.by_last_seen.insert((self.now, worker));
                self.hungry.insert(worker);
                self.fill(worker, &mut actions);
            }
            Event::Heartbeat { worker } => self.seen(worker),
            Event::WorkerLeft { worker } => {
                self.remove_worker(worker, &mut actions);
                self.fill_all(&mut actions);
            }
            Event::WorkerDraining { worker } => {
                self.seen(worker);
                if let Some(w) = self.workers.get_mut(&worker) {
                    let was_ready = w.takes_tiles();
                    w.draining = true;
                    if was_ready {
                        let machine = w.machine.clone();
                        self.unready(&machine);
                    }
                }
            }
            Event::JobSubmitted {
                job,
                priority,
                scene,
                tiles,
            } => {
                if tiles == 0 {
                    self.paused.remove(&job);
                    actions.push(Action::JobDone { job });
                } else {
                    self.insert_job(job, Job::new(priority, scene, tiles));
                }
                self.fill_all(&mut actions);
            }
            Event::TileDone { worker, job, tile } => {
                self.seen(worker);
                self.progressed(worker, job, tile, &mut actions);
                let requeued = self.counters.tiles_requeued;
                self.tile_done(worker, job, tile, &mut actions);
                if self.counters.tiles_requeued != requeued {
                    // A copy from the machine whose result the tile holds put it back
                    // in the queue: any other machine may take it.
                    self.fill_all(&mut actions);
                } else {
                    // Holders of a finished job's last copies are filled at the next
                    // event that fills everyone (a timeout at the latest).
                    self.fill(worker, &mut actions);
                }
            }
            Event::TileToConfirm {
                worker,
                job,
                tile,
                required,
            } => {
                self.seen(worker);
                self.progressed(worker, job, tile, &mut actions);
                self.tile_to_confirm(worker, job, tile, required, &mut actions);
                self.fill_all(&mut actions);
            }
            Event::DisableMachine { machine } => {
                self.set_disabled(Machine::Named(machine), true);
            }
            Event::EnableMachine { machine } => {
                self.set_disabled(Machine::Named(machine), false);
                self.fill_all(&mut actions);
            }
            Event::Quarantine { machine, revoke } => {
                self.quarantine(Machine::Named(machine), &revoke, &mut actions);
                self.fill_all(&mut actions);
            }
            Event::WorkerPace { worker, rtt, tile } => {
                let cap = self.policy.max_credit_per_thread.max(2) as usize;
                if let Some(w) = self.workers.get_mut(&worker) {
                    let threads = w.threads as usize;
                    // Saturating: a round trip of any length (u64::MAX included) only
                    // reaches the cap.
                    let span = u128::from(rtt) + u128::from(rtt / 2);
                    let cover = usize::try_from(span.div_ceil(u128::from(tile.max(1))))
                        .unwrap_or(usize::MAX);
                    w.credit = threads
                        .saturating_mul(cover.saturating_add(2))
                        .min(threads.saturating_mul(cap));
                    if w.holding.len() < w.credit {
                        self.hungry.insert(worker);
                        self.fill(worker, &mut actions);
                    }
                }
            }
            Event::TileFailed {
                worker,
                job,
                tile,
                message,
            } => {
                self.seen(worker);
                self.progressed(worker, job, tile, &mut actions);
                // Like a result, a failure counts only from a holder of the tile. A
                // failed copy of a tile already accepted only frees the worker's slot.
                if self.release(worker, job, tile).is_some() {
                    let machine = self.workers.get(&worker).map(|w| w.machine.clone());
                    let machine = machine.unwrap_or(Machine::Connection(worker));
                    self.failed_attempt(&machine, job, tile, &message, &mut actions);
                } else if let Some(j) = self.jobs.get_mut(&job) {
                    if j.late_copies.remove(&(tile, worker)) {
                        self.drop_holding(worker, job, tile);
                    }
                }
                self.fill_all(&mut actions);
            }
            Event::CancelJob { job } => {
                self.paused.remove(&job);
                if self.jobs.contains_key(&job) {
                    self.end_job(job, &mut actions);
                }
                self.fill_all(&mut actions);
            }
            Event::PauseJob { job } => {
                self.paused.insert(job);
                if let Some(j) = self.jobs.get_mut(&job) {
                    j.stalled_since = None;
                }
            }
            Event::ResumeJob { job } => {
                self.paused.remove(&job);
                self.fill_all(&mut actions);
            }
            Event::Interactive { job } => {
                if let Some(j) = self.jobs.get_mut(&job) {
                    j.interactive = true;
                }
                self.fill_all(&mut actions);
            }
            Event::SetPriority { job, priority } => {
                if let Some(j) = self.jobs.get_mut(&job) {
                    let before = j.rank(job);
                    j.priority = priority;
                    self.rerank(job, before);
                }
                self.fill_all(&mut actions);
            }
            Event::StorageUnavailable => self.storage_down = true,
            Event::StorageAvailable => {
                self.storage_down = false;
                self.fill_all(&mut actions);
            }
            Event::RequeueTiles { job, tiles } => {
                self.requeue_tiles(job, &tiles);
                self.fill_all(&mut actions);
            }
        }
        actions
    }

    /// When the daemon must next call `handle(t, Event::Timeout)` at the latest; `None`
    /// when nothing waits on time (no worker connected and no lease live).
    ///
    /// The earliest of: a worker's heartbeat timeout, a lease's deadline, a stalled
    /// job's timeout, and the last `Timeout` (or the first call) plus the wake interval
    /// while a worker is connected or a lease live (the regular wake-up that tells a
    /// pause of the daemon from a quiet farm, and that no stream of other events can
    /// put off). Never earlier than the last call.
    pub fn next_deadline(&self) -> Option<Millis> {
        let wall = self.wall?;
        let mut at: Option<Millis> = None;
        let mut sooner = |t: Millis| at = Some(at.map_or(t, |a| a.min(t)));
        let mut waiting = !self.workers.is_empty();
        if let Some(&(seen, _)) = self.by_last_seen.first() {
            sooner(seen + self.policy.heartbeat_timeout + 1);
        }
        for job in self.jobs.values() {
            if let Some(&(deadline, _, _)) = job.deadlines.first() {
                sooner(deadline);
                waiting = true;
            }
            if let Some(since) = job.stalled_since {
                sooner(since + self.policy.stall_timeout);
            }
        }
        if waiting {
            sooner(self.last_timeout + self.policy.wake());
        }
        at.map(|t| wall + t.saturating_sub(self.now))
    }

    /// Takes back a job found in durable storage after a restart, with the tiles
    /// already done; only the others are rendered. (A method rather than an event: it
    /// is part of rebuilding the state, not something that happens to a running farm.)
    pub fn resume_job(
        &mut self,
        now: Millis,
        job: JobId,
        priority: i32,
        scene: SceneHash,
        tiles: u32,
        done: &[u32],
    ) -> Vec<Action> {
        self.advance(now);
        let mut actions = Vec::new();
        let mut j = Job::new(priority, scene, tiles);
        for &tile in done.iter().filter(|t| **t < tiles) {
            if j.state[tile as usize] != TileState::Done {
                j.state[tile as usize] = TileState::Done;
                j.remaining -= 1;
            }
        }
        let state = &j.state;
        j.waiting
            .retain(|t| state[*t as usize] == TileState::Waiting);
        j.queued = j.remaining;
        if j.remaining == 0 {
            self.paused.remove(&job);
            actions.push(Action::JobDone { job });
        } else {
            self.insert_job(job, j);
        }
        self.fill_all(&mut actions);
        actions
    }

    /// Whether an operator's pause of the job is held (from before its submission, or
    /// while it is active).
    pub fn is_paused(&self, job: JobId) -> bool {
        self.paused.contains(&job)
    }

    /// The leases that ran out while their workers still hold the tile, as (job, tile,
    /// worker, milliseconds since the tile went out), in job and tile order: what a job's
    /// event log reports as a tile put back for another worker to take.
    pub fn expired_leases(&self) -> Vec<(JobId, u32, WorkerId, Millis)> {
        let mut out = Vec::new();
        for (&id, job) in &self.jobs {
            for (&tile, leases) in &job.in_flight {
                for lease in leases.iter().filter(|l| l.expired) {
                    out.push((
                        id,
                        tile,
                        lease.worker,
                        self.now.saturating_sub(lease.started),
                    ));
                }
            }
        }
        out
    }

    /// What the scheduler has done so far.
    pub fn counters(&self) -> Counters {
        self.counters
    }

    /// Tiles in flight on all workers (for a graceful shutdown).
    pub fn tiles_in_flight(&self) -> usize {
        self.workers.values().map(|w| w.holding.len()).sum()
    }

    /// Whether the job still has tiles to render.
    pub fn is_active(&self, job: JobId) -> bool {
        self.jobs.contains_key(&job)
    }

    /// Whether any tile of the job has been sent out yet (queued vs running).
    pub fn has_started(&self, job: JobId) -> bool {
        self.jobs
            .get(&job)
            .is_some_and(|j| (j.queued as usize) < j.state.len())
    }

    /// Tiles of the job waiting to be handed out (none for a job it does not have).
    pub fn waiting(&self, job: JobId) -> u64 {
        self.jobs.get(&job).map_or(0, |j| u64::from(j.queued))
    }

    /// Tiles all workers may hold at once: what keeps the farm busy.
    pub fn total_credit(&self) -> u64 {
        self.workers.values().map(|w| w.credit as u64).sum()
    }

    /// Tiles the worker holds.
    pub fn held_by(&self, worker: WorkerId) -> usize {
        self.workers.get(&worker).map_or(0, |w| w.holding.len())
    }

    /// Tiles the worker may hold at once.
    pub fn credit_of(&self, worker: WorkerId) -> usize {
        self.workers.get(&worker).map_or(0, |w| w.credit)
    }

    /// The scheduler's own clock (the daemon's less its pauses), for the simulation's
    /// account of leases.
    pub(crate) fn clock(&self) -> Millis {
        self.now
    }

    /// Moves the clock to the daemon's time `wall`: by the time since the last call,
    /// or by one wake interval if that gap shows the daemon itself was paused.
    fn advance(&mut self, wall: Millis) {
        match self.wall {
            None => {
                self.now = self.now.max(wall);
                self.wall = Some(wall);
                self.last_timeout = self.now;
            }
            Some(last) => {
                let wall = wall.max(last);
                let gap = wall - last;
                self.now += if gap > self.policy.pause_threshold {
                    self.policy.wake()
                } else {
                    gap
                };
                self.wall = Some(wall);
            }
        }
    }

    fn seen(&mut self, worker: WorkerId) {
        if let Some(w) = self.workers.get_mut(&worker) {
            self.by_last_seen.remove(&(w.last_seen, worker));
            w.last_seen = self.now;
            self.by_last_seen.insert((self.now, worker));
        }
    }

    /// Whether some connected worker may be given tiles: none that is draining,
    /// disabled or quarantined counts. With active jobs and none, nothing renders
    /// until one connects or is enabled (what `tessera list` warns about).
    pub fn can_hand_out(&self) -> bool {
        !self.ready.is_empty()
    }

    /// Whether the worker is marked unresponsive: it holds tiles whose leases ran out
    /// and has returned nothing for longer than its allowance.
    pub fn is_unresponsive(&self, worker: WorkerId) -> bool {
        self.workers.get(&worker).is_some_and(|w| w.unresponsive)
    }

    /// Whether an operator disabled the machine.
    pub fn is_disabled(&self, machine: &str) -> bool {
        self.disabled.contains(&Machine::Named(machine.to_string()))
    }

    /// Disables or enables the machine: its connected workers stop or start taking
    /// new tiles (the ready count follows); the tiles they hold are left alone.
    fn set_disabled(&mut self, machine: Machine, disabled: bool) {
        if disabled {
            self.disabled.insert(machine.clone());
        } else {
            self.disabled.remove(&machine);
        }
        let workers: Vec<WorkerId> = self
            .workers
            .iter()
            .filter(|(_, w)| w.machine == machine && w.disabled != disabled)
            .map(|(&id, _)| id)
            .collect();
        for worker in workers {
            let w = self.workers.get_mut(&worker).expect("listed above");
            let was_ready = w.takes_tiles();
            w.disabled = disabled;
            let is_ready = w.takes_tiles();
            if was_ready && !is_ready {
                self.unready(&machine);
            } else if is_ready && !was_ready {
                *self.ready.entry(machine.clone()).or_default() += 1;
                self.hungry.insert(worker);
            }
        }
    }

    /// One worker of the machine is gone or draining. When no machine is left ready,
    /// every stall ends: a job without a worker to take its tiles just waits.
    fn unready(&mut self, machine: &Machine) {
        if let Some(count) = self.ready.get_mut(machine) {
            *count -= 1;
            if *count == 0 {
                self.ready.remove(machine);
            }
        }
        if self.ready.is_empty() {
            for job in self.jobs.values_mut() {
                job.stalled_since = None;
            }
        }
    }

    /// Adds an active job (replacing one of the same id, as a map insert does).
    fn insert_job(&mut self, id: JobId, job: Job) {
        if let Some(old) = self.jobs.get(&id) {
            self.order.remove(&old.rank(id));
        }
        self.order.insert(job.rank(id));
        self.jobs.insert(id, job);
    }

    /// Removes an active job that has ended (done, failed or cancelled). Its pause goes
    /// with it: a job that ends while paused must not leave its id behind, or a later
    /// job given the same id (a retried one) would start paused. A daemon that renders
    /// a job in several runs (adaptive passes) pauses each run again.
    fn remove_job(&mut self, id: JobId) -> Option<Job> {
        self.paused.remove(&id);
        let job = self.jobs.remove(&id)?;
        self.order.remove(&job.rank(id));
        Some(job)
    }

    /// Moves the job in the serving order after its tiles in flight changed.
    fn rerank(&mut self, id: JobId, before: JobRank) {
        if let Some(job) = self.jobs.get(&id) {
            let after = job.rank(id);
            if after != before {
                self.order.remove(&before);
                self.order.insert(after);
            }
        }
    }

    /// The worker no longer holds the tile; its slot is free again.
    fn drop_holding(&mut self, worker: WorkerId, job: JobId, tile: u32) {
        if let Some(w) = self.workers.get_mut(&worker) {
            w.holding.remove(&(job, tile));
            self.hungry.insert(worker);
        }
    }

    /// The worker is gone (its connection closed, or it was dropped): every tile it
    /// held goes back to the queue, as one loss of the tile, and nothing counts against
    /// its machine.
    fn remove_worker(&mut self, worker: WorkerId, actions: &mut Vec<Action>) {
        let Some(w) = self.workers.remove(&worker) else {
            return;
        };
        self.hungry.remove(&worker);
        self.by_last_seen.remove(&(w.last_seen, worker));
        self.unlist_scenes(worker, &w.scenes);
        if w.takes_tiles() {
            self.unready(&w.machine);
        }
        for (job, tile) in w.holding {
            if self.release(worker, job, tile).is_some() {
                self.lost(job, tile, actions);
            } else if let Some(j) = self.jobs.get_mut(&job) {
                j.late_copies.remove(&(tile, worker));
            }
        }
    }

    /// Drops the workers silent for longer than the heartbeat timeout, in id order.
    fn check_heartbeats(&mut self, actions: &mut Vec<Action>) {
        let timeout = self.policy.heartbeat_timeout;
        let mut silent: Vec<WorkerId> = self
            .by_last_seen
            .iter()
            .take_while(|(seen, _)| self.now.saturating_sub(*seen) > timeout)
            .map(|&(_, id)| id)
            .collect();
        silent.sort_unstable();
        for worker in silent {
            self.counters.workers_dropped += 1;
            actions.push(Action::DropWorker { worker });
            self.remove_worker(worker, actions);
        }
    }

    /// Puts back every tile whose only live lease has run out.
    fn check_leases(&mut self) {
        let now = self.now;
        for job in self.jobs.values_mut() {
            job.expire_leases(now, &mut self.counters, &mut self.overdue);
        }
    }

    /// Marks unresponsive, in id order, the workers that hold a tile late (under a lease
    /// that ran out, or a copy of a tile accepted from another worker since) and have
    /// returned no result for longer than their allowance: the greater of [`Policy::progress_timeout`] and
    /// [`Policy::progress_factor`] times their pace, the slowest of their own results
    /// and of the measured tiles of the jobs they hold. A slow worker's pace is slow,
    /// so it is given the time its own results show it needs; a worker that never
    /// returned anything is judged by the jobs' tiles, sixteen times over.
    fn check_progress(&mut self, actions: &mut Vec<Action>) {
        let now = self.now;
        let overdue: Vec<WorkerId> = self.overdue.iter().copied().collect();
        for id in overdue {
            let Some(w) = self.workers.get(&id) else {
                self.overdue.remove(&id);
                continue;
            };
            let mut late = false;
            let mut pace = w.slowest_result;
            for (job_id, tile) in &w.holding {
                let Some(job) = self.jobs.get(job_id) else {
                    continue;
                };
                pace = pace.max(job.slowest);
                late |= job.late_copies.contains(&(*tile, id))
                    || job
                        .in_flight
                        .get(tile)
                        .is_some_and(|ls| ls.iter().any(|l| l.worker == id && l.expired));
            }
            if !late {
                self.overdue.remove(&id);
                continue;
            }
            if w.unresponsive {
                // Marked already; it stays here, so that once a result makes it
                // responsive again, what it still holds late is watched again.
                continue;
            }
            let allowance = self
                .policy
                .progress_timeout
                .max(pace.saturating_mul(self.policy.progress_factor));
            let silent = now.saturating_sub(w.progress_since);
            if silent > allowance {
                self.set_unresponsive(id, true);
                self.counters.workers_unresponsive += 1;
                actions.push(Action::WorkerUnresponsive { worker: id, silent });
            }
        }
    }

    /// A result (or a reported failure) from the worker for a tile: it makes progress.
    /// Its pace is measured from the tile's lease, if it held one, and it takes tiles
    /// again if it was unresponsive.
    fn progressed(&mut self, worker: WorkerId, job: JobId, tile: u32, actions: &mut Vec<Action>) {
        let started = self
            .jobs
            .get(&job)
            .and_then(|j| j.in_flight.get(&tile))
            .and_then(|ls| ls.iter().find(|l| l.worker == worker))
            .map(|l| l.started);
        let now = self.now;
        let Some(w) = self.workers.get_mut(&worker) else {
            return;
        };
        if let Some(started) = started {
            let took = now.saturating_sub(started.max(w.progress_since));
            w.slowest_result = w.slowest_result.max(took);
        }
        w.progress_since = now;
        if w.unresponsive {
            self.set_unresponsive(worker, false);
            actions.push(Action::WorkerResponsive { worker });
        }
    }

    /// Marks the worker unresponsive or not; the ready count follows. An unresponsive
    /// worker's live leases run out at once: it is trusted with no work, so its tiles
    /// go back to the queue now rather than at their deadlines (its results still
    /// count if they come first).
    fn set_unresponsive(&mut self, worker: WorkerId, unresponsive: bool) {
        let Some(w) = self.workers.get_mut(&worker) else {
            return;
        };
        if w.unresponsive == unresponsive {
            return;
        }
        let was_ready = w.takes_tiles();
        w.unresponsive = unresponsive;
        let is_ready = w.takes_tiles();
        let machine = w.machine.clone();
        let holding: Vec<(JobId, u32)> = w.holding.iter().copied().collect();
        if was_ready && !is_ready {
            self.unready(&machine);
        } else if is_ready && !was_ready {
            *self.ready.entry(machine).or_default() += 1;
        }
        if unresponsive {
            self.hungry.remove(&worker);
            for (job_id, tile) in holding {
                if let Some(job) = self.jobs.get_mut(&job_id) {
                    job.expire_lease_of(tile, worker, &mut self.counters);
                }
            }
        } else {
            self.hungry.insert(worker);
        }
    }

    /// Follows each job's stall (tiles waiting that no connected worker may take), and
    /// fails the jobs stalled for the stall timeout, in id order.
    fn check_stalls(&mut self, actions: &mut Vec<Action>) {
        let now = self.now;
        let mut failed = Vec::new();
        for (&id, job) in &mut self.jobs {
            if self.paused.contains(&id) {
                job.stalled_since = None;
                continue;
            }
            match job.stalled_tile(&self.ready, self.policy.max_attempts) {
                None => job.stalled_since = None,
                Some(tile) => {
                    let since = *job.stalled_since.get_or_insert(now);
                    if now - since >= self.policy.stall_timeout {
                        let message = job.stall_message(tile, &self.ready, self.policy.block_after);
                        failed.push((id, message));
                    }
                }
            }
        }
        let unresponsive = self.unresponsive_note();
        for (job, message) in failed {
            self.end_job(job, actions);
            let message = format!("{message}{unresponsive}");
            actions.push(Action::JobFailed { job, message });
        }
    }

    /// What a stall's message adds about the machines whose workers are connected but
    /// unresponsive (and none of whose workers is ready): they are not counted among
    /// those that may take tiles, and the operator should know why. Empty without any.
    /// Walks the workers: called only when a job fails.
    fn unresponsive_note(&self) -> String {
        let machines: BTreeSet<&Machine> = self
            .workers
            .values()
            .filter(|w| w.unresponsive && !self.ready.contains_key(&w.machine))
            .map(|w| &w.machine)
            .collect();
        if machines.is_empty() {
            return String::new();
        }
        let machines: Vec<&Machine> = machines.into_iter().collect();
        format!(
            "; not counted, unresponsive (leases ran out without a result): {}",
            name_list(&machines)
        )
    }

    /// Ends the worker's lease on the tile if it holds one for an active job, and
    /// returns it. Anything else (a stray or late message) changes nothing.
    fn release(&mut self, worker: WorkerId, job_id: JobId, tile: u32) -> Option<Lease> {
        let job = self.jobs.get_mut(&job_id)?;
        let before = job.rank(job_id);
        let lease = job.remove_lease(tile, worker)?;
        self.rerank(job_id, before);
        self.drop_holding(worker, job_id, tile);
        Some(lease)
    }

    fn tile_done(&mut self, worker: WorkerId, job_id: JobId, tile: u32, actions: &mut Vec<Action>) {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return;
        };
        if job.late_copies.remove(&(tile, worker)) {
            self.drop_holding(worker, job_id, tile);
            actions.push(Action::DuplicateResult { job: job_id, tile });
            return;
        }
        let machine = self.machine_of(worker);
        if self.jobs[&job_id].held_from(tile, &machine) {
            // A machine does not confirm its own result: this copy only frees its slot.
            self.release_unconfirming(worker, job_id, tile);
            return;
        }
        let Some(lease) = self.release(worker, job_id, tile) else {
            return;
        };
        let job = self.jobs.get_mut(&job_id).expect("release checked the job");
        job.held.remove(&tile);
        let took = self.now.saturating_sub(lease.started);
        job.measured += 1;
        job.total_time += took;
        job.slowest = job.slowest.max(took);
        if job.measured == 1 {
            let length = job.lease_length(&self.policy);
            job.shorten_leases(length);
        }
        // Still queued if its lease ran out: its entry there is now stale.
        if job.state[tile as usize] == TileState::Waiting {
            job.queued -= 1;
        }
        job.state[tile as usize] = TileState::Done;
        job.remaining -= 1;
        // Other holders' copies are still to come: they will be compared.
        let before = job.rank(job_id);
        if let Some(others) = job.take_leases(tile) {
            for other in others {
                job.late_copies.insert((tile, other.worker));
                self.overdue.insert(other.worker);
            }
        }
        let finished = job.remaining == 0;
        self.rerank(job_id, before);
        actions.push(Action::AcceptTile { job: job_id, tile });
        if finished {
            let job = self.remove_job(job_id).expect("checked above");
            let holders: BTreeSet<WorkerId> = job.late_copies.iter().map(|(_, w)| *w).collect();
            for holder in holders {
                if let Some(w) = self.workers.get_mut(&holder) {
                    w.holding.retain(|(j, _)| *j != job_id);
                    self.hungry.insert(holder);
                    actions.push(Action::CancelOnWorker {
                        worker: holder,
                        job: job_id,
                    });
                }
            }
            actions.push(Action::JobDone { job: job_id });
            self.forget_unused_scenes(actions);
        }
    }

    /// Takes the tiles back from wherever they are and puts them at the head of the
    /// queue (see [`Event::RequeueTiles`]).
    fn requeue_tiles(&mut self, job_id: JobId, tiles: &[u32]) {
        for &tile in tiles {
            let Some(job) = self.jobs.get_mut(&job_id) else {
                return;
            };
            if tile as usize >= job.state.len() {
                continue;
            }
            let before = job.rank(job_id);
            // Every holder lets go: a result it still sends is a stray, which counts for
            // nothing (as after a cancel).
            let leases = job.take_leases(tile).unwrap_or_default();
            let copies: Vec<WorkerId> = job
                .late_copies
                .range((tile, WorkerId::MIN)..=(tile, WorkerId::MAX))
                .map(|&(_, w)| w)
                .collect();
            for &worker in &copies {
                job.late_copies.remove(&(tile, worker));
            }
            job.held.remove(&tile);
            if job.state[tile as usize] == TileState::Done {
                job.state[tile as usize] = TileState::Out;
                job.remaining += 1;
            }
            if job.requeue(tile) {
                self.counters.tiles_requeued += 1;
            }
            self.rerank(job_id, before);
            for worker in leases.iter().map(|l| l.worker).chain(copies) {
                self.drop_holding(worker, job_id, tile);
            }
        }
    }

    /// The machine a worker counts as (its connection, once it has left).
    fn machine_of(&self, worker: WorkerId) -> Machine {
        self.workers
            .get(&worker)
            .map_or(Machine::Connection(worker), |w| w.machine.clone())
    }

    /// A result to be confirmed by another machine: held, and the tile goes back to the
    /// queue for the others unless another machine is rendering it already.
    fn tile_to_confirm(
        &mut self,
        worker: WorkerId,
        job_id: JobId,
        tile: u32,
        required: bool,
        actions: &mut Vec<Action>,
    ) {
        let machine = self.machine_of(worker);
        match self.jobs.get(&job_id).and_then(|j| j.held.get(&tile)) {
            // Held from another machine: the daemon compares before it asks for a
            // confirmation, so this is one.
            Some((from, _)) if *from != machine => {
                return self.tile_done(worker, job_id, tile, actions);
            }
            Some(_) => return self.release_unconfirming(worker, job_id, tile),
            None => {}
        }
        if self
            .jobs
            .get(&job_id)
            .is_some_and(|j| j.late_copies.contains(&(tile, worker)))
        {
            // Already accepted: this is a straggler's copy, compared as such.
            return self.tile_done(worker, job_id, tile, actions);
        }
        if self.release(worker, job_id, tile).is_none() {
            return;
        }
        let job = self.jobs.get_mut(&job_id).expect("release checked the job");
        job.held.insert(tile, (machine, required));
        actions.push(Action::HoldResult {
            worker,
            job: job_id,
            tile,
        });
        if job.live_leases(tile) == 0 && job.requeue(tile) {
            self.counters.tiles_requeued += 1;
        }
    }

    /// Frees the slot of a copy from the machine whose result is held (it cannot
    /// confirm itself); the tile goes back to the queue if no one else renders it.
    fn release_unconfirming(&mut self, worker: WorkerId, job_id: JobId, tile: u32) {
        if self.release(worker, job_id, tile).is_some() {
            let job = self.jobs.get_mut(&job_id).expect("release checked the job");
            if job.live_leases(tile) == 0 && job.requeue(tile) {
                self.counters.tiles_requeued += 1;
            }
        }
    }

    /// Shuts the machine out: its workers get nothing more, their tiles and its held
    /// results go back to the queue, and so do the revoked done tiles.
    fn quarantine(&mut self, machine: Machine, revoke: &[(JobId, u32)], actions: &mut Vec<Action>) {
        if !self.quarantined.insert(machine.clone()) {
            // Already shut out; revoked tiles still go back.
        }
        let workers: Vec<WorkerId> = self
            .workers
            .iter()
            .filter(|(_, w)| w.machine == machine)
            .map(|(&id, _)| id)
            .collect();
        for worker in workers {
            let w = self.workers.get_mut(&worker).expect("listed above");
            let was_ready = w.takes_tiles();
            w.draining = true;
            // It holds nothing afterwards, whatever its entries are about: a tile of an
            // active job, a late copy, or a stale entry no active job knows of (its
            // job's id was submitted again, and that job has ended since).
            let holding = std::mem::take(&mut w.holding);
            if was_ready {
                self.unready(&machine);
            }
            for (job, tile) in holding {
                if self.release(worker, job, tile).is_some() {
                    if let Some(j) = self.jobs.get_mut(&job) {
                        if j.live_leases(tile) == 0 && j.requeue(tile) {
                            self.counters.tiles_requeued += 1;
                        }
                    }
                } else if let Some(j) = self.jobs.get_mut(&job) {
                    j.late_copies.remove(&(tile, worker));
                }
            }
        }
        for job in self.jobs.values_mut() {
            let dropped: Vec<u32> = job
                .held
                .iter()
                .filter(|(_, (m, _))| *m == machine)
                .map(|(&t, _)| t)
                .collect();
            for tile in dropped {
                job.held.remove(&tile);
            }
        }
        for &(job_id, tile) in revoke {
            let Some(job) = self.jobs.get_mut(&job_id) else {
                continue;
            };
            if job.state.get(tile as usize) != Some(&TileState::Done) {
                continue;
            }
            let before = job.rank(job_id);
            job.state[tile as usize] = TileState::Out;
            job.remaining += 1;
            // Copies still to come are results again: their holders hold the tile
            // under leases that ran out (the first result wins, theirs included).
            let copies: Vec<WorkerId> = job
                .late_copies
                .range((tile, WorkerId::MIN)..=(tile, WorkerId::MAX))
                .map(|&(_, w)| w)
                .collect();
            for worker in copies {
                job.late_copies.remove(&(tile, worker));
                job.in_flight.entry(tile).or_default().push(Lease {
                    worker,
                    started: self.now,
                    deadline: self.now,
                    expired: true,
                });
            }
            job.requeue(tile);
            self.counters.tiles_requeued += 1;
            self.rerank(job_id, before);
        }
        let _ = actions;
    }

    /// Accepts the held results of optional confirmations that no connected machine
    /// may give (every other machine is blocked from the job, failed the tile, or
    /// there is none), in job then tile order.
    fn give_up_confirmations(&mut self, actions: &mut Vec<Action>) {
        let mut finished = Vec::new();
        let mut reranked = Vec::new();
        for (&id, job) in &mut self.jobs {
            if job.held.is_empty() {
                continue;
            }
            let before = job.rank(id);
            let accepted: Vec<u32> = job
                .held
                .iter()
                .filter(|&(&t, (from, required))| {
                    !required
                        && job.live_leases(t) == 0
                        && !self.ready.keys().any(|m| {
                            m != from
                                && !job.blocked.contains(m)
                                && job.failures.get(&t).is_none_or(|(_, on)| !on.contains(m))
                        })
                })
                .map(|(&t, _)| t)
                .collect();
            for tile in accepted {
                job.held.remove(&tile);
                if job.state[tile as usize] == TileState::Waiting {
                    job.queued -= 1;
                }
                // Holders under leases that ran out: their copies are still to come.
                for other in job.take_leases(tile).into_iter().flatten() {
                    job.late_copies.insert((tile, other.worker));
                    self.overdue.insert(other.worker);
                }
                job.state[tile as usize] = TileState::Done;
                job.remaining -= 1;
                actions.push(Action::AcceptHeld { job: id, tile });
            }
            reranked.push((id, before));
            if job.remaining == 0 {
                finished.push(id);
            }
        }
        for (id, before) in reranked {
            self.rerank(id, before);
        }
        for id in finished {
            self.end_job(id, actions);
            actions.push(Action::JobDone { job: id });
        }
    }

    /// Counts a failure a worker reported for a tile (already released): retry it
    /// elsewhere, block a machine that keeps failing, or fail the job.
    fn failed_attempt(
        &mut self,
        machine: &Machine,
        job_id: JobId,
        tile: u32,
        message: &str,
        actions: &mut Vec<Action>,
    ) {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return;
        };
        let (attempts, on) = job.failures.entry(tile).or_default();
        *attempts += 1;
        on.insert(machine.clone());
        let attempts = *attempts;
        let worker_failures = job.worker_failures.entry(machine.clone()).or_default();
        *worker_failures += 1;
        if *worker_failures >= self.policy.block_after {
            job.blocked.insert(machine.clone());
        }
        if attempts >= self.policy.max_attempts {
            let message = format!("tile {tile} failed {attempts} times; last: {message}");
            self.end_job(job_id, actions);
            actions.push(Action::JobFailed {
                job: job_id,
                message,
            });
        } else if job.live_leases(tile) == 0 && job.requeue(tile) {
            self.counters.tiles_requeued += 1;
        }
    }

    /// Counts a loss of a tile (already released) with its worker: retry it, or fail
    /// the job when the tile has been lost too often.
    fn lost(&mut self, job_id: JobId, tile: u32, actions: &mut Vec<Action>) {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return;
        };
        let losses = job.losses.entry(tile).or_default();
        *losses += 1;
        let losses = *losses;
        if losses >= self.policy.max_losses {
            let message = format!(
                "tile {tile} was lost with its worker {losses} times (a tile that crashes \
                 workers, or workers that keep losing their connection)"
            );
            self.end_job(job_id, actions);
            actions.push(Action::JobFailed {
                job: job_id,
                message,
            });
        } else if job.live_leases(tile) == 0 && job.requeue(tile) {
            self.counters.tiles_requeued += 1;
        }
    }

    /// Removes an active job, telling the workers that hold its tiles to drop them.
    fn end_job(&mut self, job_id: JobId, actions: &mut Vec<Action>) {
        let Some(job) = self.remove_job(job_id) else {
            return;
        };
        let holders: BTreeSet<WorkerId> = job
            .in_flight
            .values()
            .flatten()
            .map(|l| l.worker)
            .chain(job.late_copies.iter().map(|(_, w)| *w))
            .collect();
        for worker in holders {
            if let Some(w) = self.workers.get_mut(&worker) {
                w.holding.retain(|(j, _)| *j != job_id);
                self.hungry.insert(worker);
                actions.push(Action::CancelOnWorker {
                    worker,
                    job: job_id,
                });
            }
        }
        self.forget_unused_scenes(actions);
    }

    /// After a job ended: workers may drop scenes no active job uses, in worker id
    /// order, each worker's in scene order. Only the workers that have such a scene
    /// are visited ([`Scheduler::scene_holders`]).
    fn forget_unused_scenes(&mut self, actions: &mut Vec<Action>) {
        let in_use: BTreeSet<SceneHash> = self.jobs.values().map(|j| j.scene).collect();
        let unused: Vec<SceneHash> = self
            .scene_holders
            .keys()
            .filter(|scene| !in_use.contains(*scene))
            .copied()
            .collect();
        let mut forget: BTreeMap<WorkerId, Vec<SceneHash>> = BTreeMap::new();
        for scene in unused {
            for worker in self.scene_holders.remove(&scene).unwrap_or_default() {
                forget.entry(worker).or_default().push(scene);
            }
        }
        for (worker, scenes) in forget {
            let w = self
                .workers
                .get_mut(&worker)
                .expect("scene holders are live");
            for scene in scenes {
                w.scenes.remove(&scene);
                actions.push(Action::ForgetScene { worker, scene });
            }
        }
    }

    /// Takes the worker out of the index of the scenes it had.
    fn unlist_scenes(&mut self, worker: WorkerId, scenes: &BTreeSet<SceneHash>) {
        for scene in scenes {
            if let Some(holders) = self.scene_holders.get_mut(scene) {
                holders.remove(&worker);
                if holders.is_empty() {
                    self.scene_holders.remove(scene);
                }
            }
        }
    }

    /// Fills every worker with free credit, in id order. Filling one worker changes
    /// no other worker's credit, so those full at the start are skipped, as filling
    /// them would give them nothing; and once no tile may go to anyone, the rest are
    /// not visited (they stay listed as hungry), so that a farm of many idle workers
    /// costs each event the number of jobs, not of workers.
    fn fill_all(&mut self, actions: &mut Vec<Action>) {
        if self.storage_down || !self.anything_to_hand_out() {
            return;
        }
        let ids: Vec<WorkerId> = self.hungry.iter().copied().collect();
        for worker in ids {
            let before = actions.len();
            self.fill(worker, actions);
            // Only a tile handed out can close the last one open.
            if actions.len() != before && !self.anything_to_hand_out() {
                return;
            }
        }
    }

    /// Whether [`Scheduler::next_tile`] may find a tile for some worker: an active job
    /// that is not paused has a tile waiting, or (with speculation) none waiting and a
    /// straggler to copy. When not, it finds none for anyone.
    fn anything_to_hand_out(&self) -> bool {
        self.order.iter().any(|&(_, _, id)| {
            let job = &self.jobs[&id];
            !self.paused.contains(&id)
                && (job.queued > 0 || (self.policy.speculate && !job.stragglers.is_empty()))
        })
    }

    /// Gives the worker tiles until its credit is used or nothing is left for it.
    fn fill(&mut self, worker_id: WorkerId, actions: &mut Vec<Action>) {
        if self.storage_down {
            // The worker stays hungry: `StorageAvailable` fills it.
            return;
        }
        loop {
            let Some(worker) = self.workers.get(&worker_id) else {
                self.hungry.remove(&worker_id);
                return;
            };
            if !worker.takes_tiles() || worker.holding.len() >= worker.credit {
                self.hungry.remove(&worker_id);
                return;
            }
            let Some((job_id, tile)) = self.next_tile(worker_id) else {
                return;
            };
            let now = self.now;
            let policy = self.policy;
            let job = self
                .jobs
                .get_mut(&job_id)
                .expect("next_tile returns an active job");
            let before = job.rank(job_id);
            let deadline = now + job.lease_length(&policy);
            job.add_lease(
                tile,
                Lease {
                    worker: worker_id,
                    started: now,
                    deadline,
                    expired: false,
                },
            );
            let scene = job.scene;
            self.rerank(job_id, before);
            let worker = self.workers.get_mut(&worker_id).expect("checked above");
            if worker.scenes.insert(scene) {
                self.scene_holders
                    .entry(scene)
                    .or_default()
                    .insert(worker_id);
                actions.push(Action::SendScene {
                    worker: worker_id,
                    job: job_id,
                });
            }
            if worker.holding.is_empty() {
                // Idle until now: a result is due from now on, not since its last one.
                worker.progress_since = now;
            }
            worker.holding.insert((job_id, tile));
            actions.push(Action::Assign {
                worker: worker_id,
                job: job_id,
                tile,
            });
        }
    }

    /// The next tile for the worker: a waiting tile of the best job (highest priority,
    /// then fewest tiles in flight, then oldest) it is not blocked from; failing that,
    /// a straggler to duplicate.
    fn next_tile(&mut self, worker: WorkerId) -> Option<(JobId, u32)> {
        let machine = &self.workers.get(&worker)?.machine;
        // Interactive jobs first; after a run of them, batch jobs first for one tile.
        let first_interactive = self.interactive_run < INTERACTIVE_RUN;
        for first in [true, false] {
            for &(_, _, id) in &self.order {
                let job = self.jobs.get_mut(&id).expect("ordered jobs are active");
                if first && job.interactive != first_interactive {
                    continue;
                }
                if self.paused.contains(&id) || job.blocked.contains(machine) {
                    continue;
                }
                if let Some(tile) = job.take_waiting_for(worker, machine) {
                    self.interactive_run = if job.interactive {
                        self.interactive_run.saturating_add(1)
                    } else {
                        0
                    };
                    return Some((id, tile));
                }
            }
        }
        if !self.policy.speculate {
            return None;
        }
        let holding = &self.workers.get(&worker)?.holding;
        self.order.iter().find_map(|&(_, _, id)| {
            let job = &self.jobs[&id];
            if self.paused.contains(&id) || job.blocked.contains(machine) || job.queued > 0 {
                return None;
            }
            job.straggler_for(worker, machine)
                .filter(|t| !holding.contains(&(id, *t)))
                .map(|t| (id, t))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SCENE_A: SceneHash = [1; 32];
    const SCENE_B: SceneHash = [2; 32];

    fn assigns(actions: &[Action]) -> Vec<(WorkerId, JobId, u32)> {
        actions
            .iter()
            .filter_map(|a| match *a {
                Action::Assign { worker, job, tile } => Some((worker, job, tile)),
                _ => None,
            })
            .collect()
    }

    fn failure(actions: &[Action], job: JobId) -> Option<&str> {
        actions.iter().find_map(|a| match a {
            Action::JobFailed { job: j, message } if *j == job => Some(message.as_str()),
            _ => None,
        })
    }

    fn submit(
        s: &mut Scheduler,
        job: JobId,
        priority: i32,
        scene: SceneHash,
        tiles: u32,
    ) -> Vec<Action> {
        s.handle(
            0,
            Event::JobSubmitted {
                job,
                priority,
                scene,
                tiles,
            },
        )
    }

    fn join_at(
        s: &mut Scheduler,
        now: Millis,
        worker: WorkerId,
        threads: u32,
        name: Option<&str>,
    ) -> Vec<Action> {
        s.handle(
            now,
            Event::WorkerJoined {
                worker,
                threads,
                machine: name.map(str::to_string),
            },
        )
    }

    fn join(s: &mut Scheduler, worker: WorkerId, threads: u32) -> Vec<Action> {
        join_at(s, 0, worker, threads, None)
    }

    fn fail(
        s: &mut Scheduler,
        now: Millis,
        worker: WorkerId,
        job: JobId,
        tile: u32,
    ) -> Vec<Action> {
        s.handle(
            now,
            Event::TileFailed {
                worker,
                job,
                tile,
                message: "boom".into(),
            },
        )
    }

    /// A machine that reports failures on a job's tiles is blocked from the job, also
    /// when it comes back under the same name (a service restarted by its supervisor),
    /// and never gets the tiles it failed on; a machine of another name gets them.
    #[test]
    fn reported_failures_block_the_machine_name_across_reconnections() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 6);
        let first = join_at(&mut s, 0, 1, 1, Some("flaky"));
        assert_eq!(assigns(&first), vec![(1, 1, 0), (1, 1, 1)]);
        fail(&mut s, 0, 1, 1, 0);
        fail(&mut s, 0, 1, 1, 1);
        s.handle(0, Event::WorkerLeft { worker: 1 });
        let second = join_at(&mut s, 0, 2, 1, Some("flaky"));
        assert!(
            assigns(&second).is_empty(),
            "blocked after 2 failures: {second:?}"
        );
        // A healthy machine gets the tiles put back first: tile 2, which "flaky" held
        // when it left, then the failed ones.
        let healthy = join_at(&mut s, 0, 3, 1, Some("healthy"));
        assert_eq!(assigns(&healthy), vec![(3, 1, 2), (3, 1, 1)]);
        // Unnamed workers are each their own machine.
        let anon = join(&mut s, 4, 1);
        assert_eq!(assigns(&anon), vec![(4, 1, 0), (4, 1, 3)]);
    }

    /// Losing a connection is not proof a worker is bad: a worker killed while holding
    /// tiles and restarted under its name, again and again, is never blocked, gets its
    /// lost tiles back, and the job finishes. With one worker and with two.
    #[test]
    fn a_worker_killed_and_rejoining_under_its_name_5_times_finishes_the_job() {
        for workers in [1, 2] {
            let mut s = Scheduler::new();
            submit(&mut s, 1, 0, SCENE_A, 12);
            let names = ["a", "b"];
            let mut next_id = 1;
            let mut ids = Vec::new();
            for name in &names[..workers] {
                join_at(&mut s, 0, next_id, 1, Some(name));
                ids.push(next_id);
                next_id += 1;
            }
            let mut now = 0;
            for _kill in 0..5 {
                now += 100;
                for i in 0..workers {
                    assert_eq!(s.held_by(ids[i]), 2, "{workers} workers");
                    let left = s.handle(now, Event::WorkerLeft { worker: ids[i] });
                    assert!(failure(&left, 1).is_none(), "{left:?}");
                    let back = join_at(&mut s, now, next_id, 1, Some(names[i]));
                    assert_eq!(assigns(&back).len(), 2, "not blocked: {back:?}");
                    ids[i] = next_id;
                    next_id += 1;
                }
            }
            // Now they render everything.
            let mut done = false;
            while !done {
                now += 100;
                for &worker in &ids {
                    let held: Vec<(JobId, u32)> =
                        s.workers[&worker].holding.iter().copied().collect();
                    for (job, tile) in held {
                        let actions = s.handle(now, Event::TileDone { worker, job, tile });
                        done |= actions.contains(&Action::JobDone { job: 1 });
                    }
                }
            }
            assert!(!s.is_active(1));
        }
    }

    /// A tile that takes down every worker it reaches is lost with each one; at
    /// `max_losses` its job fails with a message that says so.
    #[test]
    fn a_tile_lost_with_its_worker_max_losses_times_fails_its_job() {
        let max = Policy::default().max_losses;
        let mut s = Scheduler::with_policy(Policy {
            speculate: false,
            ..Policy::default()
        });
        submit(&mut s, 1, 0, SCENE_A, 1);
        for worker in 1..max as WorkerId {
            assert_eq!(assigns(&join(&mut s, worker, 1)), vec![(worker, 1, 0)]);
            let left = s.handle(0, Event::WorkerLeft { worker });
            assert!(failure(&left, 1).is_none(), "loss {worker}: {left:?}");
        }
        join(&mut s, max as WorkerId, 1);
        let left = s.handle(
            0,
            Event::WorkerLeft {
                worker: max as WorkerId,
            },
        );
        assert_eq!(
            failure(&left, 1),
            Some(
                "tile 0 was lost with its worker 8 times (a tile that crashes workers, or \
                 workers that keep losing their connection)"
            )
        );
        assert!(!s.is_active(1));
    }

    /// A worker dropped for silence loses its tiles the same way: one loss each, no
    /// block, no attempt; the same name gets the tiles back when it rejoins.
    #[test]
    fn a_network_cut_past_the_heartbeat_timeout_blocks_nobody() {
        let policy = Policy::default();
        let mut s = Scheduler::with_policy(policy);
        submit(&mut s, 1, 0, SCENE_A, 2);
        join_at(&mut s, 0, 1, 1, Some("far"));
        let mut now = 0;
        let dropped = loop {
            now += policy.wake_interval;
            let actions = s.handle(now, Event::Timeout);
            if !actions.is_empty() {
                break actions;
            }
        };
        assert_eq!(dropped, vec![Action::DropWorker { worker: 1 }]);
        assert_eq!(now, 6_000);
        let job = &s.jobs[&1];
        assert!(job.failures.is_empty() && job.blocked.is_empty());
        assert_eq!(job.losses, BTreeMap::from([(0, 1), (1, 1)]));
        let back = join_at(&mut s, now, 2, 1, Some("far"));
        assert_eq!(assigns(&back), vec![(2, 1, 1), (2, 1, 0)]);
    }

    /// The coordinator stopped for 7 s (no heartbeat read meanwhile) drops nobody: the
    /// gap counts as one wake interval, and the heartbeats waiting in the sockets are
    /// read before anyone comes near the timeout. Leases do not run out either.
    #[test]
    fn a_pause_of_7_s_drops_nobody() {
        let policy = Policy {
            initial_lease: 6_000,
            ..Policy::default()
        };
        let mut s = Scheduler::with_policy(policy);
        submit(&mut s, 1, 0, SCENE_A, 4);
        join(&mut s, 1, 1);
        join(&mut s, 2, 1);
        for now in [1_000, 2_000, 3_000] {
            for worker in [1, 2] {
                s.handle(now, Event::Heartbeat { worker });
            }
            assert!(s.handle(now, Event::Timeout).is_empty());
        }
        // Stopped at 3 s, running again at 10 s: the timer fires first.
        let woken = s.handle(10_000, Event::Timeout);
        assert!(woken.is_empty(), "{woken:?}");
        assert_eq!(s.counters(), Counters::default());
        for worker in [1, 2] {
            s.handle(10_000, Event::Heartbeat { worker });
            assert_eq!(s.held_by(worker), 2);
        }
        // The clock goes on from there: silence counts again.
        assert_eq!(s.next_deadline(), Some(11_000));
        assert!(s.handle(11_000, Event::Timeout).is_empty());
        // A real silence is still caught: 1 s counted for the pause, then 4 s of timeouts.
        let mut dropped = Vec::new();
        for now in (12_000..=20_000).step_by(1_000) {
            s.handle(now, Event::Heartbeat { worker: 2 });
            dropped.extend(s.handle(now, Event::Timeout));
        }
        assert_eq!(dropped.first(), Some(&Action::DropWorker { worker: 1 }));
    }

    /// The same pause without the coordinator's regular wake-ups would look the same to
    /// it: a gap is a pause only beyond the threshold, and at most a wake interval of
    /// it counts.
    #[test]
    fn only_gaps_beyond_the_pause_threshold_are_pauses() {
        let policy = Policy::default();
        let mut s = Scheduler::with_policy(policy);
        join(&mut s, 1, 1);
        // Gaps up to the threshold count in full: 5 s of them, then one more ms.
        s.handle(2_000, Event::Timeout);
        s.handle(4_000, Event::Timeout);
        assert!(s.handle(5_000, Event::Timeout).is_empty());
        assert_eq!(
            s.handle(5_001, Event::Timeout),
            vec![Action::DropWorker { worker: 1 }]
        );
        // A time from before is taken as the last one.
        let mut s = Scheduler::with_policy(policy);
        join_at(&mut s, 0, 1, 1, None);
        s.handle(4_000, Event::Heartbeat { worker: 1 });
        s.handle(3_000, Event::Timeout);
        assert_eq!(s.next_deadline(), Some(5_000));
    }

    /// While a worker is connected the daemon is told to call at least every wake
    /// interval, earlier for a heartbeat timeout or a lease deadline; with none,
    /// nothing waits on time.
    #[test]
    fn next_deadline_is_the_earliest_thing_that_waits_on_time() {
        let policy = Policy {
            initial_lease: 1_500,
            ..Policy::default()
        };
        let mut s = Scheduler::with_policy(policy);
        assert_eq!(s.next_deadline(), None);
        submit(&mut s, 1, 0, SCENE_A, 1);
        assert_eq!(s.next_deadline(), None, "a job without workers just waits");
        join_at(&mut s, 100, 1, 1, None);
        assert_eq!(
            s.next_deadline(),
            Some(1_000),
            "a wake interval after the first call"
        );
        s.handle(1_000, Event::Timeout);
        assert_eq!(s.next_deadline(), Some(1_600), "the lease of tile 0");
        s.handle(1_600, Event::Timeout);
        assert_eq!(s.next_deadline(), Some(2_600));
        // Messages more often than the wake interval do not put the timeout off.
        for now in (1_800..=2_400).step_by(200) {
            s.handle(now, Event::Heartbeat { worker: 1 });
            assert_eq!(s.next_deadline(), Some(2_600), "after a heartbeat at {now}");
        }
        s.handle(2_600, Event::Heartbeat { worker: 1 });
        s.handle(2_600, Event::WorkerLeft { worker: 1 });
        assert_eq!(s.next_deadline(), None);
        // A heartbeat timeout shorter than the wake interval.
        let mut s = Scheduler::with_policy(Policy {
            heartbeat_timeout: 300,
            ..policy
        });
        join_at(&mut s, 0, 1, 1, None);
        assert_eq!(s.next_deadline(), Some(301));
        assert_eq!(
            s.handle(301, Event::Timeout),
            vec![Action::DropWorker { worker: 1 }]
        );
        assert_eq!(s.next_deadline(), None);
    }

    /// A job whose waiting tiles failed on every connected machine fails after the
    /// stall timeout, with a message naming the tile and the machines; a job without
    /// any worker connected just waits; a new machine ends the stall.
    #[test]
    fn a_job_no_connected_worker_may_take_fails_after_the_stall_timeout() {
        let policy = Policy {
            speculate: false,
            ..Policy::default()
        };
        let mut s = Scheduler::with_policy(policy);
        submit(&mut s, 1, 0, SCENE_A, 1);
        join_at(&mut s, 0, 1, 1, Some("a"));
        fail(&mut s, 0, 1, 1, 0);
        join_at(&mut s, 0, 2, 1, Some("b"));
        fail(&mut s, 0, 2, 1, 0);
        // Nobody may take tile 0 now. The stall starts at the first timeout.
        let heartbeat = |s: &mut Scheduler, now| {
            for worker in [1, 2] {
                s.handle(now, Event::Heartbeat { worker });
            }
        };
        let mut now = 0;
        let failed = loop {
            now += 1_000;
            heartbeat(&mut s, now);
            let actions = s.handle(now, Event::Timeout);
            if !actions.is_empty() {
                break actions;
            }
        };
        assert_eq!(now, 1_000 + policy.stall_timeout);
        assert_eq!(
            failed,
            vec![
                Action::ForgetScene {
                    worker: 1,
                    scene: SCENE_A
                },
                Action::ForgetScene {
                    worker: 2,
                    scene: SCENE_A
                },
                Action::JobFailed {
                    job: 1,
                    message: "no connected worker may render tile 0: it failed on every one \
                              of them (a, b)"
                        .into()
                },
            ]
        );

        // Without any worker, the same job waits, however long.
        let mut s = Scheduler::with_policy(policy);
        submit(&mut s, 1, 0, SCENE_A, 1);
        join_at(&mut s, 0, 1, 1, Some("a"));
        fail(&mut s, 0, 1, 1, 0);
        s.handle(10, Event::Timeout);
        assert!(s.jobs[&1].stalled_since.is_some());
        s.handle(20, Event::WorkerLeft { worker: 1 });
        assert_eq!(s.jobs[&1].stalled_since, None);
        assert_eq!(s.next_deadline(), None);
        assert!(s.handle(100_000, Event::Timeout).is_empty());
        assert!(s.is_active(1));
        // The stall counts again from when a worker that may not take it is back...
        join_at(&mut s, 100_000, 2, 1, Some("a"));
        s.handle(101_000, Event::Timeout);
        assert!(s.jobs[&1].stalled_since.is_some());
        // ...and ends when a machine that may take it joins: it gets the tile.
        let fresh = join_at(&mut s, 101_500, 3, 1, Some("b"));
        assert_eq!(assigns(&fresh), vec![(3, 1, 0)]);
        s.handle(101_500, Event::Heartbeat { worker: 2 });
        s.handle(102_000, Event::Timeout);
        assert_eq!(s.jobs[&1].stalled_since, None);
    }

    /// Machines blocked from a job (too many of its tiles failed on them) stall it
    /// too, and the message says so.
    #[test]
    fn a_job_every_connected_machine_is_blocked_from_fails_with_the_reason() {
        let policy = Policy {
            speculate: false,
            stall_timeout: 0,
            ..Policy::default()
        };
        let done = |s: &mut Scheduler, worker, tile| {
            s.handle(
                0,
                Event::TileDone {
                    worker,
                    job: 1,
                    tile,
                },
            )
        };
        // "a" fails tiles 0 and 1 and is blocked; it leaves with tile 2, which goes
        // back to the head of the queue, and comes back.
        let mut s = Scheduler::with_policy(policy);
        submit(&mut s, 1, 0, SCENE_A, 4);
        join_at(&mut s, 0, 1, 1, Some("a"));
        assert_eq!(assigns(&fail(&mut s, 0, 1, 1, 0)), vec![(1, 1, 2)]);
        assert!(assigns(&fail(&mut s, 0, 1, 1, 1)).is_empty());
        s.handle(0, Event::WorkerLeft { worker: 1 });
        assert!(assigns(&join_at(&mut s, 0, 2, 1, Some("a"))).is_empty());
        let timeout = s.handle(0, Event::Timeout);
        assert_eq!(
            failure(&timeout, 1),
            Some(
                "no connected worker may render tile 2: every one of them is blocked from \
                 the job after failing 2 of its tiles (a)"
            )
        );

        // Tile 3 failed on "b", and the other machine (unnamed, so named by its
        // connection) is blocked.
        let mut s = Scheduler::with_policy(policy);
        submit(&mut s, 1, 0, SCENE_A, 4);
        join(&mut s, 1, 1);
        assert_eq!(assigns(&fail(&mut s, 0, 1, 1, 0)), vec![(1, 1, 2)]);
        assert!(assigns(&fail(&mut s, 0, 1, 1, 1)).is_empty());
        assert!(assigns(&done(&mut s, 1, 2)).is_empty());
        let b = join_at(&mut s, 0, 2, 1, Some("b"));
        assert_eq!(assigns(&b), vec![(2, 1, 1), (2, 1, 0)]);
        assert_eq!(assigns(&done(&mut s, 2, 1)), vec![(2, 1, 3)]);
        assert!(assigns(&fail(&mut s, 0, 2, 1, 3)).is_empty());
        let timeout = s.handle(0, Event::Timeout);
        assert_eq!(
            failure(&timeout, 1),
            Some(
                "no connected worker may render tile 3: it failed on some of them (b) and \
                 the others are blocked from the job after failing 2 of its tiles (worker 1)"
            )
        );
        assert!(timeout.contains(&Action::CancelOnWorker { worker: 2, job: 1 }));
    }

    /// However many machines, and whatever their names hold, the message is one line.
    #[test]
    fn a_stall_message_stays_on_one_line() {
        let mut s = Scheduler::with_policy(Policy {
            speculate: false,
            stall_timeout: 0,
            max_attempts: 20,
            ..Policy::default()
        });
        submit(&mut s, 1, 0, SCENE_A, 1);
        for worker in 0..10 {
            let name = format!("m\n{worker}");
            assert_eq!(
                assigns(&join_at(&mut s, 0, worker, 1, Some(&name))),
                vec![(worker, 1, 0)]
            );
            fail(&mut s, 0, worker, 1, 0);
        }
        let timeout = s.handle(0, Event::Timeout);
        assert_eq!(
            failure(&timeout, 1),
            Some(
                "no connected worker may render tile 0: it failed on every one of them (m?0, \
                 m?1, m?2, m?3, m?4, m?5, m?6, m?7, and 2 more)"
            )
        );
    }

    /// While storage cannot record results no tile goes out, results of tiles out are
    /// still accepted, and once it can every worker is filled again.
    #[test]
    fn storage_unavailable_assigns_nothing_and_resumes() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 6);
        join(&mut s, 1, 1);
        assert!(s.handle(0, Event::StorageUnavailable).is_empty());
        let done = s.handle(
            10,
            Event::TileDone {
                worker: 1,
                job: 1,
                tile: 0,
            },
        );
        assert_eq!(done, vec![Action::AcceptTile { job: 1, tile: 0 }]);
        assert!(assigns(&join(&mut s, 2, 1)).is_empty());
        assert!(assigns(&submit(&mut s, 2, 0, SCENE_B, 2)).is_empty());
        assert!(assigns(&s.handle(1_000, Event::Timeout)).is_empty());
        // No straggler copies either.
        assert_eq!((s.held_by(1), s.held_by(2)), (1, 0));
        // Tile 1's lease, given under the initial lease, ended at its start plus the
        // lease measured with tile 0 (the least, 1 s): it ran out at the timeout and
        // waits at the head of job 1's queue.
        let back = s.handle(1_500, Event::StorageAvailable);
        assert_eq!(
            assigns(&back),
            vec![(1, 2, 0), (2, 1, 1), (2, 1, 2)],
            "{back:?}"
        );
    }

    #[test]
    fn a_worker_holds_its_credit_and_gets_the_next_tile_when_it_returns_one() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 10);
        let joined = join(&mut s, 7, 1);
        assert_eq!(joined[0], Action::SendScene { worker: 7, job: 1 });
        assert_eq!(assigns(&joined), vec![(7, 1, 0), (7, 1, 1)]);
        let done = s.handle(
            0,
            Event::TileDone {
                worker: 7,
                job: 1,
                tile: 0,
            },
        );
        assert_eq!(done[0], Action::AcceptTile { job: 1, tile: 0 });
        assert_eq!(assigns(&done), vec![(7, 1, 2)]);
        assert_eq!(s.held_by(7), 2);
    }

    fn without_speculation() -> Scheduler {
        Scheduler::with_policy(Policy {
            speculate: false,
            ..Policy::default()
        })
    }

    #[test]
    fn interactive_jobs_go_first_but_batch_jobs_get_one_tile_in_five() {
        let mut s = without_speculation();
        // A batch job of the highest priority, and an interactive one of the lowest.
        submit(&mut s, 1, i32::MAX, SCENE_A, 20);
        submit(&mut s, 2, i32::MIN, SCENE_B, 20);
        s.handle(0, Event::Interactive { job: 2 });
        s.handle(0, Event::Interactive { job: 99 }); // not active: nothing to mark
                                                     // The tiles in the order they are handed out, each result freeing a slot.
        let mut out: std::collections::VecDeque<_> = assigns(&join(&mut s, 1, 1)).into();
        let mut order: Vec<JobId> = out.iter().map(|a| a.1).collect();
        while let Some((worker, job, tile)) = out.pop_front() {
            let next = assigns(&s.handle(0, Event::TileDone { worker, job, tile }));
            order.extend(next.iter().map(|a| a.1));
            out.extend(next);
        }
        assert_eq!(order.len(), 40, "{order:?}");
        let run = INTERACTIVE_RUN as usize;
        // The worker's credit is filled first, then every slot: count from the first
        // batch tile on, runs of `run` interactive tiles between single batch tiles.
        let first_batch = order.iter().position(|&j| j == 1).unwrap();
        assert!(order[..first_batch].iter().all(|&j| j == 2), "{order:?}");
        for window in order[first_batch..]
            .chunks(run + 1)
            .filter(|w| w.len() == run + 1)
        {
            if !window.contains(&2) {
                break; // the interactive job is done
            }
            assert_eq!(
                window.iter().filter(|&&j| j == 1).count(),
                1,
                "one batch tile in every {}: {order:?}",
                run + 1
            );
        }
    }

    #[test]
    fn results_are_accepted_once_and_only_from_the_holder() {
        let mut s = without_speculation();
        submit(&mut s, 1, 0, SCENE_A, 3);
        join(&mut s, 1, 1);
        join(&mut s, 2, 1);
        let done = |s: &mut Scheduler, worker| {
            s.handle(
                0,
                Event::TileDone {
                    worker,
                    job: 1,
                    tile: 0,
                },
            )
        };
        // Tile 0 is worker 1's: worker 2's result for it is dropped.
        let stray = done(&mut s, 2);
        assert!(!stray.iter().any(|a| matches!(a, Action::AcceptTile { .. })));
        let first = done(&mut s, 1);
        assert!(first.contains(&Action::AcceptTile { job: 1, tile: 0 }));
        let again = done(&mut s, 1);
        assert!(!again.iter().any(|a| matches!(a, Action::AcceptTile { .. })));
    }

    #[test]
    fn a_leaving_worker_s_tiles_go_to_another_and_the_job_finishes() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 4);
        join(&mut s, 1, 1);
        let joined = join(&mut s, 2, 1);
        assert_eq!(assigns(&joined), vec![(2, 1, 2), (2, 1, 3)]);
        let left = s.handle(0, Event::WorkerLeft { worker: 1 });
        assert!(assigns(&left).is_empty(), "worker 2 is at its credit");
        let mut actions = Vec::new();
        for tile in [2, 3, 0, 1] {
            actions.extend(s.handle(
                0,
                Event::TileDone {
                    worker: 2,
                    job: 1,
                    tile,
                },
            ));
        }
        assert!(actions.contains(&Action::JobDone { job: 1 }));
        assert!(!s.is_active(1));
    }

    #[test]
    fn equal_priorities_share_the_farm_and_higher_priority_goes_first() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 100);
        submit(&mut s, 2, 0, SCENE_A, 4);
        let joined = join(&mut s, 1, 2);
        // Fewest tiles in flight first: the two jobs alternate.
        assert_eq!(
            assigns(&joined),
            vec![(1, 1, 0), (1, 2, 0), (1, 1, 1), (1, 2, 1)]
        );
        let urgent = submit(&mut s, 3, 5, SCENE_B, 2);
        assert!(assigns(&urgent).is_empty(), "the worker is at its credit");
        let next = s.handle(
            0,
            Event::TileDone {
                worker: 1,
                job: 1,
                tile: 0,
            },
        );
        assert_eq!(assigns(&next), vec![(1, 3, 0)]);
        assert!(next.contains(&Action::SendScene { worker: 1, job: 3 }));
    }

    #[test]
    fn a_paused_job_gets_no_tile_keeps_those_out_and_resumes() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 10);
        let joined = join(&mut s, 1, 1);
        let out = assigns(&joined);
        assert!(!out.is_empty());
        assert!(s.handle(0, Event::PauseJob { job: 1 }).is_empty());
        // A tile already out counts, and frees a slot that stays empty.
        let (_, _, tile) = out[0];
        let done = s.handle(
            0,
            Event::TileDone {
                worker: 1,
                job: 1,
                tile,
            },
        );
        assert!(assigns(&done).is_empty(), "a paused job hands out nothing");
        // A paused job with no worker able to take its tiles does not fail.
        let later = s.handle(10 * 60 * 1000, Event::Timeout);
        assert_eq!(failure(&later, 1), None);
        let resumed = s.handle(10 * 60 * 1000, Event::ResumeJob { job: 1 });
        assert!(
            !assigns(&resumed).is_empty(),
            "resuming hands tiles out again"
        );
    }

    #[test]
    fn a_job_that_ends_while_paused_leaves_no_pause_behind() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 1);
        let joined = join(&mut s, 1, 1);
        assert_eq!(assigns(&joined), vec![(1, 1, 0)]);
        s.handle(0, Event::PauseJob { job: 1 });
        assert!(s.is_paused(1));
        let done = s.handle(
            0,
            Event::TileDone {
                worker: 1,
                job: 1,
                tile: 0,
            },
        );
        assert!(done.contains(&Action::JobDone { job: 1 }));
        assert!(!s.is_paused(1), "a finished job's pause is forgotten");
        // Failed while paused: the tile out fails for good.
        let mut s = Scheduler::with_policy(Policy {
            max_attempts: 1,
            ..Policy::default()
        });
        submit(&mut s, 2, 0, SCENE_A, 2);
        join(&mut s, 1, 1);
        s.handle(0, Event::PauseJob { job: 2 });
        let failed = s.handle(
            0,
            Event::TileFailed {
                worker: 1,
                job: 2,
                tile: 0,
                message: "broken".into(),
            },
        );
        assert!(failure(&failed, 2).is_some(), "{failed:?}");
        assert!(!s.is_paused(2), "a failed job's pause is forgotten");
        // Taken back with every tile done, or with none to render.
        s.handle(0, Event::PauseJob { job: 3 });
        let resumed = s.resume_job(0, 3, 0, SCENE_A, 1, &[0]);
        assert!(resumed.contains(&Action::JobDone { job: 3 }));
        assert!(!s.is_paused(3));
        s.handle(0, Event::PauseJob { job: 4 });
        submit(&mut s, 4, 0, SCENE_A, 0);
        assert!(!s.is_paused(4));
        // A pause before submission still holds once the job is in.
        s.handle(0, Event::PauseJob { job: 5 });
        submit(&mut s, 5, 0, SCENE_A, 3);
        assert!(s.is_paused(5));
    }

    #[test]
    fn requeued_tiles_are_taken_back_from_wherever_they_are() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 3);
        let out = assigns(&join(&mut s, 1, 4));
        assert_eq!(out.len(), 3, "{out:?}");
        // Tile 0 done, tile 1 still out, tile 2 out.
        let done = s.handle(
            0,
            Event::TileDone {
                worker: 1,
                job: 1,
                tile: 0,
            },
        );
        assert!(done.contains(&Action::AcceptTile { job: 1, tile: 0 }));
        let again = s.handle(
            0,
            Event::RequeueTiles {
                job: 1,
                tiles: vec![0, 1, 99],
            },
        );
        // Both go out again at once (the worker has free slots).
        let mut again = assigns(&again);
        again.sort_unstable();
        assert_eq!(again, vec![(1, 1, 0), (1, 1, 1)]);
        // The old lease of tile 1 is gone: the job ends only when the tiles come back.
        let mut finished = Vec::new();
        for tile in [2, 1, 0] {
            finished.extend(s.handle(
                0,
                Event::TileDone {
                    worker: 1,
                    job: 1,
                    tile,
                },
            ));
        }
        assert!(
            finished.contains(&Action::JobDone { job: 1 }),
            "{finished:?}"
        );
        assert_eq!(s.tiles_in_flight(), 0);
    }

    #[test]
    fn a_new_priority_orders_the_next_tiles() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 10);
        submit(&mut s, 2, 0, SCENE_A, 10);
        s.handle(
            0,
            Event::SetPriority {
                job: 2,
                priority: 3,
            },
        );
        let joined = join(&mut s, 1, 1);
        let out = assigns(&joined);
        assert!(!out.is_empty());
        assert!(out.iter().all(|&(_, job, _)| job == 2), "{out:?}");
    }

    #[test]
    fn cancelling_tells_the_holders_and_forgets_the_scene() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 10);
        join(&mut s, 1, 1);
        let cancelled = s.handle(0, Event::CancelJob { job: 1 });
        assert!(cancelled.contains(&Action::CancelOnWorker { worker: 1, job: 1 }));
        assert!(cancelled.contains(&Action::ForgetScene {
            worker: 1,
            scene: SCENE_A
        }));
        assert!(!s.is_active(1));
        assert_eq!(s.held_by(1), 0);
        // A later job of the same scene sends it again.
        let later = submit(&mut s, 2, 0, SCENE_A, 1);
        assert_eq!(later[0], Action::SendScene { worker: 1, job: 2 });
    }

    #[test]
    fn a_disabled_machine_gets_no_new_tile_until_enabled_even_after_reconnecting() {
        let mut s = without_speculation();
        join_at(&mut s, 0, 1, 1, Some("a"));
        assert!(s.can_hand_out());
        s.handle(
            0,
            Event::DisableMachine {
                machine: "a".into(),
            },
        );
        assert!(!s.can_hand_out());
        assert!(s.is_disabled("a"));
        assert!(assigns(&submit(&mut s, 1, 0, SCENE_A, 3)).is_empty());
        // A reconnect of the machine is still disabled.
        s.handle(0, Event::WorkerLeft { worker: 1 });
        assert!(assigns(&join_at(&mut s, 0, 2, 1, Some("a"))).is_empty());
        assert!(!s.can_hand_out());
        // Another machine is not.
        assert!(!assigns(&join_at(&mut s, 0, 3, 1, Some("b"))).is_empty());
        s.handle(0, Event::WorkerLeft { worker: 3 });
        let enabled = s.handle(
            0,
            Event::EnableMachine {
                machine: "a".into(),
            },
        );
        assert!(s.can_hand_out());
        assert!(assigns(&enabled).iter().all(|&(w, _, _)| w == 2));
        assert!(!assigns(&enabled).is_empty());
    }

    #[test]
    fn a_disabled_workers_tiles_still_count() {
        let mut s = without_speculation();
        join_at(&mut s, 0, 1, 1, Some("a"));
        let out = assigns(&submit(&mut s, 1, 0, SCENE_A, 3));
        assert!(!out.is_empty());
        s.handle(
            0,
            Event::DisableMachine {
                machine: "a".into(),
            },
        );
        let (w, j, t) = out[0];
        let done = s.handle(
            1,
            Event::TileDone {
                worker: w,
                job: j,
                tile: t,
            },
        );
        assert!(done.contains(&Action::AcceptTile { job: j, tile: t }));
        assert!(assigns(&done).is_empty());
    }

    #[test]
    fn a_draining_or_quarantined_farm_cannot_hand_out() {
        let mut s = Scheduler::new();
        assert!(!s.can_hand_out());
        join_at(&mut s, 0, 1, 1, Some("a"));
        join_at(&mut s, 0, 2, 1, Some("b"));
        s.handle(0, Event::WorkerDraining { worker: 1 });
        assert!(s.can_hand_out());
        s.handle(
            0,
            Event::Quarantine {
                machine: "b".into(),
                revoke: Vec::new(),
            },
        );
        assert!(!s.can_hand_out());
        // Enabling a machine that was never disabled changes nothing.
        s.handle(
            0,
            Event::EnableMachine {
                machine: "a".into(),
            },
        );
        assert!(!s.can_hand_out());
    }

    #[test]
    fn a_draining_worker_gets_nothing_more() {
        let mut s = Scheduler::new();
        join(&mut s, 1, 1);
        s.handle(0, Event::WorkerDraining { worker: 1 });
        assert!(assigns(&submit(&mut s, 1, 0, SCENE_A, 3)).is_empty());
        assert_eq!(s.held_by(1), 0);
    }

    #[test]
    fn a_failed_tile_is_retried_elsewhere_then_fails_the_job() {
        let mut s = Scheduler::with_policy(Policy {
            max_attempts: 2,
            speculate: false,
            ..Policy::default()
        });
        submit(&mut s, 1, 0, SCENE_A, 1);
        join(&mut s, 1, 1);
        let failed = fail(&mut s, 0, 1, 1, 0);
        // Not given back to the worker it failed on.
        assert!(assigns(&failed).is_empty());
        let joined = join(&mut s, 2, 1);
        assert_eq!(assigns(&joined), vec![(2, 1, 0)]);
        let failed = fail(&mut s, 0, 2, 1, 0);
        assert_eq!(
            failure(&failed, 1),
            Some("tile 0 failed 2 times; last: boom")
        );
        assert!(!s.is_active(1));
    }

    #[test]
    fn an_expired_lease_requeues_the_tile_and_a_silent_worker_is_dropped() {
        let policy = Policy::default();
        let mut s = without_speculation();
        submit(&mut s, 1, 0, SCENE_A, 1);
        join(&mut s, 1, 1);
        join(&mut s, 2, 1);
        // Both stay alive; worker 1 holds the tile until its lease runs out, and then
        // the tile goes to worker 2.
        let mut expired = Vec::new();
        for now in (1_000..=policy.initial_lease).step_by(1_000) {
            s.handle(now, Event::Heartbeat { worker: 1 });
            s.handle(now, Event::Heartbeat { worker: 2 });
            expired = s.handle(now, Event::Timeout);
            if !expired.is_empty() {
                break;
            }
        }
        assert_eq!(assigns(&expired), vec![(2, 1, 0)]);
        // Heart-beating, but 60 s without a result while holding a tile whose lease ran
        // out: worker 1 is marked unresponsive at the same timeout.
        assert!(
            expired.contains(&Action::WorkerUnresponsive {
                worker: 1,
                silent: policy.initial_lease
            }),
            "{expired:?}"
        );
        let counted = Counters {
            leases_expired: 1,
            tiles_requeued: 1,
            workers_dropped: 0,
            workers_unresponsive: 1,
        };
        assert_eq!(s.counters(), counted);
        // The expired lease is listed (worker 1 may still deliver), the fresh one not.
        let listed = s.expired_leases();
        assert_eq!(listed.len(), 1, "{listed:?}");
        let (job, tile, worker, out_for) = listed[0];
        assert_eq!((job, tile, worker), (1, 0, 1));
        assert!(out_for >= policy.initial_lease, "{out_for}");
        // Worker 1 falls silent and is dropped at the first timeout past the limit;
        // worker 2 keeps the tile.
        let mut now = policy.initial_lease;
        let dropped = loop {
            now += 1_000;
            s.handle(now, Event::Heartbeat { worker: 2 });
            let actions = s.handle(now, Event::Timeout);
            if !actions.is_empty() {
                break actions;
            }
        };
        assert_eq!(dropped, vec![Action::DropWorker { worker: 1 }]);
        assert!(
            s.expired_leases().is_empty(),
            "a dropped worker's lease is gone"
        );
        // Its lease had run out already: dropping it requeues nothing more.
        assert_eq!(
            s.counters(),
            Counters {
                workers_dropped: 1,
                ..counted
            }
        );
        // Its last heartbeat arrived at initial_lease; the first timeout more than the
        // heartbeat timeout later drops it.
        assert_eq!(now, policy.initial_lease + policy.heartbeat_timeout + 1_000);
        let done = s.handle(
            now,
            Event::TileDone {
                worker: 2,
                job: 1,
                tile: 0,
            },
        );
        assert!(done.contains(&Action::JobDone { job: 1 }));
    }

    #[test]
    fn a_straggler_is_duplicated_and_the_first_result_wins() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 1);
        join(&mut s, 1, 1);
        let idle = join(&mut s, 2, 1);
        assert_eq!(assigns(&idle), vec![(2, 1, 0)]);
        let first = s.handle(
            0,
            Event::TileDone {
                worker: 2,
                job: 1,
                tile: 0,
            },
        );
        assert!(first.contains(&Action::AcceptTile { job: 1, tile: 0 }));
        assert!(first.contains(&Action::CancelOnWorker { worker: 1, job: 1 }));
        assert!(first.contains(&Action::JobDone { job: 1 }));
    }

    fn to_confirm(
        s: &mut Scheduler,
        now: Millis,
        worker: WorkerId,
        tile: u32,
        required: bool,
    ) -> Vec<Action> {
        s.handle(
            now,
            Event::TileToConfirm {
                worker,
                job: 1,
                tile,
                required,
            },
        )
    }

    #[test]
    fn a_held_result_is_confirmed_only_by_another_machine() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 1);
        assert_eq!(
            assigns(&join_at(&mut s, 0, 1, 1, Some("a"))),
            vec![(1, 1, 0)]
        );
        // Worker 2 of the same machine takes a straggler copy.
        assert_eq!(
            assigns(&join_at(&mut s, 0, 2, 1, Some("a"))),
            vec![(2, 1, 0)]
        );
        let held = to_confirm(&mut s, 10, 1, 0, true);
        assert!(held.contains(&Action::HoldResult {
            worker: 1,
            job: 1,
            tile: 0
        }));
        // Worker 2 is the same machine: it may not confirm. A third machine joins.
        assert!(!assigns(&held).iter().any(|&(w, _, _)| w == 1 || w == 2));
        let copy = s.handle(
            15,
            Event::TileDone {
                worker: 2,
                job: 1,
                tile: 0,
            },
        );
        assert!(!copy.iter().any(|a| matches!(a, Action::AcceptTile { .. })));
        assert!(assigns(&copy).is_empty(), "machine a may not take it again");
        assert_eq!(
            assigns(&join_at(&mut s, 20, 3, 1, Some("b"))),
            vec![(3, 1, 0)]
        );
        let done = s.handle(
            30,
            Event::TileDone {
                worker: 3,
                job: 1,
                tile: 0,
            },
        );
        assert!(done.contains(&Action::AcceptTile { job: 1, tile: 0 }));
        assert!(done.contains(&Action::JobDone { job: 1 }));
    }

    #[test]
    fn an_optional_confirmation_no_machine_may_give_is_given_up_a_required_one_stalls() {
        for required in [false, true] {
            let mut s = Scheduler::new();
            submit(&mut s, 1, 0, SCENE_A, 1);
            join_at(&mut s, 0, 1, 1, Some("a"));
            to_confirm(&mut s, 10, 1, 0, required);
            let mut actions = Vec::new();
            for t in (1..=40).map(|k| k * 1_000) {
                s.handle(t, Event::Heartbeat { worker: 1 });
                actions.extend(s.handle(t, Event::Timeout));
            }
            if required {
                let message = failure(&actions, 1).expect("the job stalls and fails");
                assert!(message.contains("tile 0"), "{message}");
            } else {
                assert!(actions.contains(&Action::AcceptHeld { job: 1, tile: 0 }));
                assert!(actions.contains(&Action::JobDone { job: 1 }));
                assert!(failure(&actions, 1).is_none());
            }
        }
    }

    #[test]
    fn a_quarantined_machine_loses_its_tiles_held_results_and_revoked_tiles() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 6);
        assert_eq!(assigns(&join_at(&mut s, 0, 1, 1, Some("liar"))).len(), 2);
        let done = s.handle(
            5,
            Event::TileDone {
                worker: 1,
                job: 1,
                tile: 0,
            },
        );
        assert!(done.contains(&Action::AcceptTile { job: 1, tile: 0 }));
        to_confirm(&mut s, 6, 1, 1, false);
        assert_eq!(s.held_by(1), 2, "tiles 2 and 3");
        let q = s.handle(
            7,
            Event::Quarantine {
                machine: "liar".into(),
                revoke: vec![(1, 0)],
            },
        );
        assert!(assigns(&q).is_empty(), "nobody else is connected");
        assert_eq!(s.held_by(1), 0);
        // An honest machine gets every tile, the revoked and the held one included.
        let honest = assigns(&join_at(&mut s, 8, 2, 3, Some("honest")));
        assert_eq!(honest.len(), 6);
        let mut accepted = Vec::new();
        for &(_, _, tile) in &honest {
            let actions = s.handle(
                9,
                Event::TileDone {
                    worker: 2,
                    job: 1,
                    tile,
                },
            );
            accepted.extend(actions);
        }
        for tile in 0..6 {
            assert!(accepted.contains(&Action::AcceptTile { job: 1, tile }));
        }
        assert!(accepted.contains(&Action::JobDone { job: 1 }));
        // The liar, back under its name, is given nothing.
        assert!(assigns(&join_at(&mut s, 11, 3, 4, Some("liar"))).is_empty());
    }

    #[test]
    fn credit_covers_the_round_trip_within_its_cap() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 1000);
        assert_eq!(assigns(&join_at(&mut s, 0, 1, 2, Some("far"))).len(), 4);
        let more = s.handle(
            1,
            Event::WorkerPace {
                worker: 1,
                rtt: 200,
                tile: 20,
            },
        );
        assert_eq!(
            assigns(&more).len(),
            2 * 15,
            "two threads, fifteen tiles per round trip and a half"
        );
        assert_eq!(s.held_by(1), 34);
        s.handle(
            2,
            Event::WorkerPace {
                worker: 1,
                rtt: 10_000,
                tile: 1,
            },
        );
        assert_eq!(s.held_by(1), 2 * 256, "capped per thread");
        s.handle(
            3,
            Event::WorkerPace {
                worker: 1,
                rtt: 0,
                tile: 20,
            },
        );
        assert_eq!(s.held_by(1), 512, "a smaller credit takes nothing back");
    }

    /// An optional confirmation given up while another machine still holds the tile
    /// under a lease that ran out: that holder's copy is still to come, and it is told
    /// when the job ends. (The held result was accepted with the lease dropped and the
    /// job left ranked by its old count of tiles in flight: the holder kept the tile
    /// forever, and the next fill panicked on the job gone from the serving order.)
    #[test]
    fn a_confirmation_given_up_leaves_the_copies_out_to_come() {
        let mut s = Scheduler::with_policy(Policy {
            initial_lease: 1_000,
            ..Policy::default()
        });
        submit(&mut s, 1, 0, SCENE_A, 1);
        join_at(&mut s, 0, 1, 1, Some("a"));
        to_confirm(&mut s, 10, 1, 0, false);
        assert_eq!(
            assigns(&join_at(&mut s, 20, 2, 1, Some("b"))),
            vec![(2, 1, 0)]
        );
        // b's lease runs out, then b drains: no ready machine may confirm.
        for worker in [1, 2] {
            s.handle(1_100, Event::Heartbeat { worker });
        }
        assert!(s.handle(1_100, Event::Timeout).is_empty());
        s.handle(1_200, Event::WorkerDraining { worker: 2 });
        let given_up = s.handle(1_300, Event::Timeout);
        assert!(given_up.contains(&Action::AcceptHeld { job: 1, tile: 0 }));
        assert!(given_up.contains(&Action::CancelOnWorker { worker: 2, job: 1 }));
        assert_eq!(given_up.last(), Some(&Action::JobDone { job: 1 }));
        assert_eq!(s.held_by(2), 0);
        submit(&mut s, 2, 0, SCENE_B, 3);
        assert_eq!(assigns(&join_at(&mut s, 1_400, 3, 1, Some("c"))).len(), 2);
    }

    /// A required confirmation that only its own machine could give stalls the job
    /// however few attempts a tile has: with `max_attempts` 1, one machine connected;
    /// with 2, the tile failed on the other one. (The stall check took `max_attempts`
    /// machines open as proof that some may take every tile, forgetting the holder.)
    #[test]
    fn a_required_confirmation_stalls_with_max_attempts_machines_connected() {
        for max_attempts in [1, 2] {
            let mut s = Scheduler::with_policy(Policy {
                max_attempts,
                speculate: false,
                stall_timeout: 2_000,
                ..Policy::default()
            });
            submit(&mut s, 1, 0, SCENE_A, 1);
            let mut workers = vec![1];
            if max_attempts == 2 {
                join_at(&mut s, 0, 2, 1, Some("b"));
                fail(&mut s, 0, 2, 1, 0);
                workers.push(2);
            }
            assert_eq!(
                assigns(&join_at(&mut s, 0, 1, 1, Some("a"))),
                vec![(1, 1, 0)]
            );
            to_confirm(&mut s, 10, 1, 0, true);
            let mut actions = Vec::new();
            for t in (1..=5).map(|k| k * 1_000) {
                for &worker in &workers {
                    s.handle(t, Event::Heartbeat { worker });
                }
                actions.extend(s.handle(t, Event::Timeout));
            }
            let message = failure(&actions, 1).expect("the job stalls and fails");
            let expected = if max_attempts == 1 {
                "no connected worker may render tile 0: its result from a awaits \
                 confirmation by another machine, and no other machine is connected"
            } else {
                "no connected worker may render tile 0: its result from a awaits \
                 confirmation by another machine, and it failed on the others (b)"
            };
            assert_eq!(message, expected);
        }
    }

    /// A round trip of any length raises the credit to its cap, never wraps it around.
    #[test]
    fn a_huge_round_trip_reaches_the_cap() {
        for tile in [0, 1] {
            let mut s = Scheduler::new();
            submit(&mut s, 1, 0, SCENE_A, 1000);
            join_at(&mut s, 0, 1, 2, Some("far"));
            let rtt = Millis::MAX;
            s.handle(
                1,
                Event::WorkerPace {
                    worker: 1,
                    rtt,
                    tile,
                },
            );
            let cap = Policy::default().max_credit_per_thread as usize;
            assert_eq!(s.held_by(1), 2 * cap);
        }
    }

    /// A copy from the machine whose result is held puts the tile back: another
    /// machine's idle worker gets it at once, not at the next timeout.
    #[test]
    fn a_tile_put_back_by_its_holding_machine_s_copy_goes_to_an_idle_worker() {
        let mut s = Scheduler::with_policy(Policy {
            speculate: false,
            initial_lease: 1_000,
            ..Policy::default()
        });
        submit(&mut s, 1, 0, SCENE_A, 1);
        join_at(&mut s, 0, 1, 1, Some("a"));
        s.handle(1_000, Event::Heartbeat { worker: 1 });
        s.handle(1_000, Event::Timeout);
        assert_eq!(
            assigns(&join_at(&mut s, 1_000, 2, 1, Some("a"))),
            vec![(2, 1, 0)]
        );
        assert!(assigns(&join_at(&mut s, 1_000, 3, 1, Some("b"))).is_empty());
        assert!(assigns(&to_confirm(&mut s, 1_100, 1, 0, true)).is_empty());
        let copy = s.handle(
            1_200,
            Event::TileDone {
                worker: 2,
                job: 1,
                tile: 0,
            },
        );
        assert_eq!(assigns(&copy), vec![(3, 1, 0)]);
    }

    /// A revoked tile whose copy is still out on an honest machine: that copy is a
    /// result again (accepted, not a duplicate), and its holder is not given the tile a
    /// second time. (The copy stayed a duplicate of a tile no longer accepted, and the
    /// tile went again to the worker holding it.)
    #[test]
    fn a_revoked_tile_s_copy_still_out_counts_as_its_result() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 2);
        assert_eq!(assigns(&join_at(&mut s, 0, 1, 1, Some("liar"))).len(), 2);
        assert_eq!(
            assigns(&join_at(&mut s, 0, 2, 1, Some("honest"))),
            vec![(2, 1, 0), (2, 1, 1)]
        );
        let done = |s: &mut Scheduler, now, worker, tile| {
            s.handle(
                now,
                Event::TileDone {
                    worker,
                    job: 1,
                    tile,
                },
            )
        };
        assert!(done(&mut s, 5, 1, 0).contains(&Action::AcceptTile { job: 1, tile: 0 }));
        s.handle(
            6,
            Event::Quarantine {
                machine: "liar".into(),
                revoke: vec![(1, 0)],
            },
        );
        let one = done(&mut s, 7, 2, 1);
        assert!(one.contains(&Action::AcceptTile { job: 1, tile: 1 }));
        assert!(assigns(&one).is_empty(), "worker 2 holds tile 0: {one:?}");
        let zero = done(&mut s, 8, 2, 0);
        assert!(zero.contains(&Action::AcceptTile { job: 1, tile: 0 }));
        assert!(zero.contains(&Action::JobDone { job: 1 }));
    }

    /// A quarantined machine's workers hold nothing afterwards, even tiles of a job
    /// that is no longer active: here the job's id was submitted again while they held
    /// its tiles, then cancelled. (Those tiles stayed held, as no active job had them.)
    #[test]
    fn a_quarantined_machine_holds_nothing_even_of_a_replaced_job() {
        let mut s = without_speculation();
        assert!(join_at(&mut s, 0, 1, 1, Some("m0")).is_empty());
        assert!(join_at(&mut s, 0, 2, 1, None).is_empty());
        assert_eq!(
            assigns(&submit(&mut s, 1, 0, SCENE_A, 2)),
            vec![(1, 1, 0), (1, 1, 1)]
        );
        // The same id again (a daemon bug): the new job replaces the old one, whose
        // tiles worker 1 still holds.
        assert_eq!(assigns(&submit(&mut s, 1, 0, SCENE_A, 1)), vec![(2, 1, 0)]);
        s.handle(0, Event::CancelJob { job: 1 });
        assert_eq!(s.held_by(1), 2);
        s.handle(
            0,
            Event::Quarantine {
                machine: "m0".into(),
                revoke: vec![],
            },
        );
        assert_eq!(s.held_by(1), 0);
        assert_eq!(s.tiles_in_flight(), 0);
    }
}
