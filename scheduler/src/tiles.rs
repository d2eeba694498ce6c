//! The scheduler core: which tile goes to which worker, when a lease runs out, and when
//! a job is finished or has failed.
//!
//! A pure state machine. It owns no socket, no clock and no thread: the daemon feeds it
//! [`Event`]s (time arrives as [`Event::Tick`]) and carries out the [`Action`]s it
//! returns, and tests feed it scripted or random events with a virtual clock. Every
//! decision of the farm is made here.
//!
//! Policy:
//! - **Pull with credit.** A worker holds at most its credit of tiles (twice its
//!   threads); it is sent the next one as soon as it returns one, so faster workers
//!   render more tiles.
//! - **Priority, then fair share, then FIFO.** A free slot goes to the highest-priority
//!   job with tiles waiting; among jobs of that priority, to the one with the fewest
//!   tiles in flight; among those, to the oldest. One job alone gets the whole farm;
//!   two jobs of equal priority split it evenly, so a small job behind a huge one
//!   finishes in about twice its solo time instead of waiting for the huge one.
//! - **Leases.** Every assignment has a deadline: a few times the job's measured tile
//!   time (a generous default before the first tile is measured). A tile whose lease
//!   runs out goes back to the queue; its first holder may still deliver it.
//! - **Liveness from heartbeats.** A worker not heard from within the heartbeat
//!   timeout is dropped and its tiles go back to the queue.
//! - **Stragglers.** When a job has no tile left waiting, a worker with free credit is
//!   also given a tile still in flight elsewhere (the one out longest, at most two
//!   holders per tile). The first result wins; a later copy is checked equal.
//! - **First result wins.** A result or a failure for a tile the sender does not hold
//!   (any more) changes nothing.
//! - **Poison tiles.** A tile that fails (an error reported, or its worker dying while
//!   holding it) is retried on other workers; after [`Policy::max_attempts`] failures
//!   the job fails with the last error. A worker that fails
//!   [`Policy::block_after`] tiles of a job gets no more of that job's tiles. Both
//!   count per machine (the name a worker gives), so a worker that crashes and comes
//!   back under the same name is not handed the same tiles again.
//! - **Scenes once.** A worker is sent a scene before its first tile of it, and only
//!   then; it may forget the scene once no active job uses it.

//!
//! Cost: the farm may have thousands of workers and hundreds of thousands of tiles, and
//! the daemon holds its lock for the whole of [`Scheduler::handle`]. So no event walks
//! every tile or every lease: each job keeps its tiles' state next to its queue, its
//! straggler candidates in the order they are chosen, and its live leases by deadline;
//! the jobs are kept in the order they are served; and only workers with free credit
//! are visited to be filled. An event costs time logarithmic in the tiles, times what
//! it changes, times the workers it fills. These indexes only speed the decisions up:
//! they are the same, event for event, as a search of every tile would make.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, VecDeque};

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
    /// Failed attempts at one tile before its job fails.
    pub max_attempts: u32,
    /// Failures of one job's tiles on one worker before the worker is blocked from it.
    pub block_after: u32,
    /// Whether to duplicate stragglers near the end of a job.
    pub speculate: bool,
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
        }
    }
}

/// Something that happened, as the daemon saw it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// The clock moved on: leases and heartbeats are checked.
    Tick {
        now: Millis,
    },
    /// A worker connected. `machine` is the name it gave, if any: failures and blocks
    /// are counted per machine, so that a worker that crashes on a job's tiles and
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
    /// The worker's connection is gone; its tiles go back to their queues, and count as
    /// failed attempts (the worker may have died of them).
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
    TileDone {
        worker: WorkerId,
        job: JobId,
        tile: u32,
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

struct Job {
    priority: i32,
    scene: SceneHash,
    /// The tiles waiting, in the order they are handed out. Accepting a tile that is
    /// still queued (its lease ran out, then its holder delivered) leaves its entry
    /// here rather than searching the queue for it; entries of done tiles are skipped,
    /// and dropped when met. A done tile never waits again, so each waiting tile has
    /// exactly one entry.
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
    /// The live leases by deadline, so that a tick looks only at those that ran out.
    deadlines: BTreeSet<(Millis, u32, WorkerId)>,
    remaining: u32,
    /// Failed attempts per tile, and the workers each tile failed on.
    failures: BTreeMap<u32, (u32, BTreeSet<Machine>)>,
    /// Failures per machine, and the machines blocked from this job.
    worker_failures: BTreeMap<Machine, u32>,
    blocked: BTreeSet<Machine>,
    /// Holders of tiles already accepted, whose copies are still to come.
    late_copies: BTreeSet<(u32, WorkerId)>,
    /// Measured tile times (assignment to result).
    measured: u32,
    total_time: Millis,
    slowest: Millis,
}

impl Job {
    fn new(priority: i32, scene: SceneHash, tiles: u32) -> Job {
        Job {
            priority,
            scene,
            waiting: (0..tiles).collect(),
            queued: tiles,
            state: vec![TileState::Waiting; tiles as usize],
            in_flight: BTreeMap::new(),
            stragglers: BTreeSet::new(),
            deadlines: BTreeSet::new(),
            remaining: tiles,
            failures: BTreeMap::new(),
            worker_failures: BTreeMap::new(),
            blocked: BTreeSet::new(),
            late_copies: BTreeSet::new(),
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
    fn expire_leases(&mut self, now: Millis, counters: &mut Counters) {
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
            }
            let all_expired = leases.iter().all(|l| l.expired);
            let after = straggler_key(leases);
            self.restraggle(tile, before, after);
            if all_expired && self.requeue(tile) {
                counters.tiles_requeued += 1;
            }
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

    /// The tile to duplicate for an idle worker: in flight with one live holder that is
    /// not this worker, never failed on this worker, out the longest (earliest start
    /// among its leases, then lowest number). The candidates are kept in that order, so
    /// this skips at most the worker's own tiles and the few that failed on it.
    fn straggler_for(&self, worker: WorkerId, machine: &Machine) -> Option<u32> {
        self.stragglers.iter().map(|&(_, t)| t).find(|t| {
            self.in_flight[t].iter().all(|l| l.worker != worker)
                && self
                    .failures
                    .get(t)
                    .is_none_or(|(_, on)| !on.contains(machine))
        })
    }
}

/// Who failures are counted against: the name a worker gave, or its connection.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Machine {
    Named(String),
    Connection(WorkerId),
}

struct Worker {
    machine: Machine,
    credit: usize,
    holding: BTreeSet<(JobId, u32)>,
    scenes: BTreeSet<SceneHash>,
    draining: bool,
    last_seen: Millis,
}

/// The scheduler's whole state.
#[derive(Default)]
pub struct Scheduler {
    policy: Policy,
    now: Millis,
    /// Active jobs (queued or running), by id; ids grow with submission order.
    jobs: BTreeMap<JobId, Job>,
    /// The active jobs in the order a free slot serves them ([`Job::rank`]).
    order: BTreeSet<JobRank>,
    workers: BTreeMap<WorkerId, Worker>,
    /// Every live worker that is not draining and holds less than its credit, and
    /// perhaps some that are full again: filling a worker drops it from here once it is
    /// full, and anything that frees a slot puts it back. Filling everyone visits only
    /// these, in id order.
    hungry: BTreeSet<WorkerId>,
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

    /// Applies one event and returns what to do, in order.
    pub fn handle(&mut self, event: Event) -> Vec<Action> {
        let mut actions = Vec::new();
        match event {
            Event::Tick { now } => {
                self.now = self.now.max(now);
                self.check_heartbeats(&mut actions);
                self.check_leases();
                self.fill_all(&mut actions);
            }
            Event::WorkerJoined {
                worker,
                threads,
                machine,
            } => {
                self.workers.insert(
                    worker,
                    Worker {
                        machine: machine.map_or(Machine::Connection(worker), Machine::Named),
                        credit: 2 * threads.max(1) as usize,
                        holding: BTreeSet::new(),
                        scenes: BTreeSet::new(),
                        draining: false,
                        last_seen: self.now,
                    },
                );
                self.hungry.insert(worker);
                self.fill(worker, &mut actions);
            }
            Event::Heartbeat { worker } => {
                if let Some(w) = self.workers.get_mut(&worker) {
                    w.last_seen = self.now;
                }
            }
            Event::WorkerLeft { worker } => {
                self.remove_worker(worker, &mut actions);
                self.fill_all(&mut actions);
            }
            Event::WorkerDraining { worker } => {
                if let Some(w) = self.workers.get_mut(&worker) {
                    w.draining = true;
                    w.last_seen = self.now;
                }
            }
            Event::JobSubmitted {
                job,
                priority,
                scene,
                tiles,
            } => {
                if tiles == 0 {
                    actions.push(Action::JobDone { job });
                } else {
                    self.insert_job(job, Job::new(priority, scene, tiles));
                }
                self.fill_all(&mut actions);
            }
            Event::TileDone { worker, job, tile } => {
                self.seen(worker);
                self.tile_done(worker, job, tile, &mut actions);
                // Holders of a finished job's last copies are filled at the next tick.
                self.fill(worker, &mut actions);
            }
            Event::TileFailed {
                worker,
                job,
                tile,
                message,
            } => {
                self.seen(worker);
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
                if self.jobs.contains_key(&job) {
                    self.end_job(job, &mut actions);
                }
                self.fill_all(&mut actions);
            }
        }
        actions
    }

    /// Takes back a job found in durable storage after a restart, with the tiles
    /// already done; only the others are rendered. (A method rather than an event: it
    /// is part of rebuilding the state, not something that happens to a running farm.)
    pub fn resume_job(
        &mut self,
        job: JobId,
        priority: i32,
        scene: SceneHash,
        tiles: u32,
        done: &[u32],
    ) -> Vec<Action> {
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
            actions.push(Action::JobDone { job });
        } else {
            self.insert_job(job, j);
        }
        self.fill_all(&mut actions);
        actions
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

    /// Tiles the worker holds.
    pub fn held_by(&self, worker: WorkerId) -> usize {
        self.workers.get(&worker).map_or(0, |w| w.holding.len())
    }

    fn seen(&mut self, worker: WorkerId) {
        if let Some(w) = self.workers.get_mut(&worker) {
            w.last_seen = self.now;
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

    fn remove_job(&mut self, id: JobId) -> Option<Job> {
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

    fn remove_worker(&mut self, worker: WorkerId, actions: &mut Vec<Action>) {
        let Some(w) = self.workers.remove(&worker) else {
            return;
        };
        self.hungry.remove(&worker);
        for (job, tile) in w.holding {
            if self.release(worker, job, tile).is_some() {
                self.failed_attempt(
                    &w.machine,
                    job,
                    tile,
                    "the worker was lost while rendering it",
                    actions,
                );
            } else if let Some(j) = self.jobs.get_mut(&job) {
                j.late_copies.remove(&(tile, worker));
            }
        }
    }

    fn check_heartbeats(&mut self, actions: &mut Vec<Action>) {
        let timeout = self.policy.heartbeat_timeout;
        let silent: Vec<WorkerId> = self
            .workers
            .iter()
            .filter(|(_, w)| self.now.saturating_sub(w.last_seen) > timeout)
            .map(|(id, _)| *id)
            .collect();
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
            job.expire_leases(now, &mut self.counters);
        }
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
        let Some(lease) = self.release(worker, job_id, tile) else {
            return;
        };
        let job = self.jobs.get_mut(&job_id).expect("release checked the job");
        let took = self.now.saturating_sub(lease.started);
        job.measured += 1;
        job.total_time += took;
        job.slowest = job.slowest.max(took);
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

    /// Counts a failed attempt at a tile (already released): retry it elsewhere, block
    /// a worker that keeps failing, or fail the job.
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

    /// After a job ended: workers may drop scenes no active job uses.
    fn forget_unused_scenes(&mut self, actions: &mut Vec<Action>) {
        let in_use: BTreeSet<SceneHash> = self.jobs.values().map(|j| j.scene).collect();
        for (&worker, w) in &mut self.workers {
            let unused: Vec<SceneHash> = w.scenes.difference(&in_use).copied().collect();
            for scene in unused {
                w.scenes.remove(&scene);
                actions.push(Action::ForgetScene { worker, scene });
            }
        }
    }

    /// Fills every worker with free credit, in id order. Filling one worker changes
    /// no other worker's credit, so those full at the start are skipped, as filling
    /// them would give them nothing.
    fn fill_all(&mut self, actions: &mut Vec<Action>) {
        let ids: Vec<WorkerId> = self.hungry.iter().copied().collect();
        for worker in ids {
            self.fill(worker, actions);
        }
    }

    /// Gives the worker tiles until its credit is used or nothing is left for it.
    fn fill(&mut self, worker_id: WorkerId, actions: &mut Vec<Action>) {
        loop {
            let Some(worker) = self.workers.get(&worker_id) else {
                self.hungry.remove(&worker_id);
                return;
            };
            if worker.draining || worker.holding.len() >= worker.credit {
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
                actions.push(Action::SendScene {
                    worker: worker_id,
                    job: job_id,
                });
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
        for &(_, _, id) in &self.order {
            let job = self.jobs.get_mut(&id).expect("ordered jobs are active");
            if job.blocked.contains(machine) {
                continue;
            }
            if let Some(tile) = job.take_waiting_for(worker, machine) {
                return Some((id, tile));
            }
        }
        if !self.policy.speculate {
            return None;
        }
        let holding = &self.workers.get(&worker)?.holding;
        self.order.iter().find_map(|&(_, _, id)| {
            let job = &self.jobs[&id];
            if job.blocked.contains(machine) || job.queued > 0 {
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

    fn submit(
        s: &mut Scheduler,
        job: JobId,
        priority: i32,
        scene: SceneHash,
        tiles: u32,
    ) -> Vec<Action> {
        s.handle(Event::JobSubmitted {
            job,
            priority,
            scene,
            tiles,
        })
    }

    /// A worker that crashes on a job's tiles and comes back under the same name (a
    /// service restarted by its supervisor) is still blocked from that job and never
    /// gets the tiles it failed on; a worker of another name gets them.
    #[test]
    fn blocks_follow_the_machine_name_across_reconnections() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 6);
        let join = |s: &mut Scheduler, worker: WorkerId, name: &str| {
            s.handle(Event::WorkerJoined {
                worker,
                threads: 1,
                machine: Some(name.into()),
            })
        };
        // Two lives of "crashy", each lost with its two tiles: 4 failures.
        let first = join(&mut s, 1, "crashy");
        assert_eq!(assigns(&first), vec![(1, 1, 0), (1, 1, 1)]);
        s.handle(Event::WorkerLeft { worker: 1 });
        let second = join(&mut s, 2, "crashy");
        assert!(
            assigns(&second).is_empty(),
            "blocked after 2 failures: {second:?}"
        );
        // A healthy machine gets everything, the failed tiles first.
        let healthy = join(&mut s, 3, "healthy");
        assert_eq!(assigns(&healthy), vec![(3, 1, 1), (3, 1, 0)]);
        // Unnamed workers are each their own machine.
        s.handle(Event::WorkerLeft { worker: 2 });
        let anon = s.handle(Event::WorkerJoined {
            worker: 4,
            threads: 1,
            machine: None,
        });
        assert_eq!(assigns(&anon), vec![(4, 1, 2), (4, 1, 3)]);
    }

    #[test]
    fn a_worker_holds_its_credit_and_gets_the_next_tile_when_it_returns_one() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 10);
        let joined = s.handle(Event::WorkerJoined {
            worker: 7,
            threads: 1,
            machine: None,
        });
        assert_eq!(joined[0], Action::SendScene { worker: 7, job: 1 });
        assert_eq!(assigns(&joined), vec![(7, 1, 0), (7, 1, 1)]);
        let done = s.handle(Event::TileDone {
            worker: 7,
            job: 1,
            tile: 0,
        });
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
    fn results_are_accepted_once_and_only_from_the_holder() {
        let mut s = without_speculation();
        submit(&mut s, 1, 0, SCENE_A, 3);
        s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 1,
            machine: None,
        });
        s.handle(Event::WorkerJoined {
            worker: 2,
            threads: 1,
            machine: None,
        });
        // Tile 0 is worker 1's: worker 2's result for it is dropped.
        let stray = s.handle(Event::TileDone {
            worker: 2,
            job: 1,
            tile: 0,
        });
        assert!(!stray.iter().any(|a| matches!(a, Action::AcceptTile { .. })));
        let first = s.handle(Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        });
        assert!(first.contains(&Action::AcceptTile { job: 1, tile: 0 }));
        let again = s.handle(Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        });
        assert!(!again.iter().any(|a| matches!(a, Action::AcceptTile { .. })));
    }

    #[test]
    fn a_leaving_worker_s_tiles_go_to_another_and_the_job_finishes() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 4);
        s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 1,
            machine: None,
        });
        let joined = s.handle(Event::WorkerJoined {
            worker: 2,
            threads: 1,
            machine: None,
        });
        assert_eq!(assigns(&joined), vec![(2, 1, 2), (2, 1, 3)]);
        let left = s.handle(Event::WorkerLeft { worker: 1 });
        assert!(assigns(&left).is_empty(), "worker 2 is at its credit");
        let mut actions = Vec::new();
        for tile in [2, 3, 0, 1] {
            actions.extend(s.handle(Event::TileDone {
                worker: 2,
                job: 1,
                tile,
            }));
        }
        assert!(actions.contains(&Action::JobDone { job: 1 }));
        assert!(!s.is_active(1));
    }

    #[test]
    fn equal_priorities_share_the_farm_and_higher_priority_goes_first() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 100);
        submit(&mut s, 2, 0, SCENE_A, 4);
        let joined = s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 2,
            machine: None,
        });
        // Fewest tiles in flight first: the two jobs alternate.
        assert_eq!(
            assigns(&joined),
            vec![(1, 1, 0), (1, 2, 0), (1, 1, 1), (1, 2, 1)]
        );
        let urgent = submit(&mut s, 3, 5, SCENE_B, 2);
        assert!(assigns(&urgent).is_empty(), "the worker is at its credit");
        let next = s.handle(Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        });
        assert_eq!(assigns(&next), vec![(1, 3, 0)]);
        assert!(next.contains(&Action::SendScene { worker: 1, job: 3 }));
    }

    #[test]
    fn cancelling_tells_the_holders_and_forgets_the_scene() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 10);
        s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 1,
            machine: None,
        });
        let cancelled = s.handle(Event::CancelJob { job: 1 });
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
    fn a_draining_worker_gets_nothing_more() {
        let mut s = Scheduler::new();
        s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 1,
            machine: None,
        });
        s.handle(Event::WorkerDraining { worker: 1 });
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
        s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 1,
            machine: None,
        });
        let failed = s.handle(Event::TileFailed {
            worker: 1,
            job: 1,
            tile: 0,
            message: "boom".into(),
        });
        // Not given back to the worker it failed on.
        assert!(assigns(&failed).is_empty());
        let joined = s.handle(Event::WorkerJoined {
            worker: 2,
            threads: 1,
            machine: None,
        });
        assert_eq!(assigns(&joined), vec![(2, 1, 0)]);
        let failed = s.handle(Event::TileFailed {
            worker: 2,
            job: 1,
            tile: 0,
            message: "boom".into(),
        });
        assert!(failed.contains(&Action::JobFailed {
            job: 1,
            message: "tile 0 failed 2 times; last: boom".into()
        }));
        assert!(!s.is_active(1));
    }

    #[test]
    fn an_expired_lease_requeues_the_tile_and_a_silent_worker_is_dropped() {
        let policy = Policy::default();
        let mut s = without_speculation();
        submit(&mut s, 1, 0, SCENE_A, 1);
        s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 1,
            machine: None,
        });
        s.handle(Event::WorkerJoined {
            worker: 2,
            threads: 1,
            machine: None,
        });
        // Both stay alive; worker 1 holds the tile until its lease runs out, and then
        // the tile goes to worker 2.
        let mut expired = Vec::new();
        for now in (1_000..=policy.initial_lease).step_by(1_000) {
            s.handle(Event::Heartbeat { worker: 1 });
            s.handle(Event::Heartbeat { worker: 2 });
            expired = s.handle(Event::Tick { now });
            if !expired.is_empty() {
                break;
            }
        }
        assert_eq!(assigns(&expired), vec![(2, 1, 0)]);
        let counted = Counters {
            leases_expired: 1,
            tiles_requeued: 1,
            workers_dropped: 0,
        };
        assert_eq!(s.counters(), counted);
        // Worker 1 falls silent and is dropped at the first tick past the timeout;
        // worker 2 keeps the tile.
        let mut now = policy.initial_lease;
        let dropped = loop {
            now += 1_000;
            s.handle(Event::Heartbeat { worker: 2 });
            let actions = s.handle(Event::Tick { now });
            if !actions.is_empty() {
                break actions;
            }
        };
        assert_eq!(dropped, vec![Action::DropWorker { worker: 1 }]);
        // Its lease had run out already: dropping it requeues nothing more.
        assert_eq!(
            s.counters(),
            Counters {
                workers_dropped: 1,
                ..counted
            }
        );
        // Its last heartbeat arrived when the clock read initial_lease - 1 s.
        assert_eq!(
            now,
            policy.initial_lease - 1_000 + policy.heartbeat_timeout + 1_000
        );
        let done = s.handle(Event::TileDone {
            worker: 2,
            job: 1,
            tile: 0,
        });
        assert!(done.contains(&Action::JobDone { job: 1 }));
    }

    #[test]
    fn a_straggler_is_duplicated_and_the_first_result_wins() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 1);
        s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 1,
            machine: None,
        });
        let idle = s.handle(Event::WorkerJoined {
            worker: 2,
            threads: 1,
            machine: None,
        });
        assert_eq!(assigns(&idle), vec![(2, 1, 0)]);
        let first = s.handle(Event::TileDone {
            worker: 2,
            job: 1,
            tile: 0,
        });
        assert!(first.contains(&Action::AcceptTile { job: 1, tile: 0 }));
        assert!(first.contains(&Action::CancelOnWorker { worker: 1, job: 1 }));
        assert!(first.contains(&Action::JobDone { job: 1 }));
    }
}
