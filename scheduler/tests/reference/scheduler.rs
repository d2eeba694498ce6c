// The scheduler as it was before its indexes (per-tile queue state, the straggler and
// deadline indexes, the maintained job order, the set of workers with free credit):
// a verbatim copy of its decisions, kept as the oracle that
// `the_indexed_scheduler_decides_as_the_reference_does` (scheduler_props.rs) compares
// the real one against. Do not change it: the point is that it stays the old code.

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
//!   [`Policy::block_after`] tiles of a job gets no more of that job's tiles.
//! - **Scenes once.** A worker is sent a scene before its first tile of it, and only
//!   then; it may forget the scene once no active job uses it.

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
    WorkerJoined {
        worker: WorkerId,
        threads: u32,
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

struct Job {
    priority: i32,
    scene: SceneHash,
    waiting: VecDeque<u32>,
    in_flight: BTreeMap<u32, Vec<Lease>>,
    done: Vec<bool>,
    remaining: u32,
    /// Failed attempts per tile, and the workers each tile failed on.
    failures: BTreeMap<u32, (u32, BTreeSet<WorkerId>)>,
    /// Failures per worker, and the workers blocked from this job.
    worker_failures: BTreeMap<WorkerId, u32>,
    blocked: BTreeSet<WorkerId>,
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
            in_flight: BTreeMap::new(),
            done: vec![false; tiles as usize],
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

    /// The first waiting tile this worker may take: one that has not failed on it and
    /// that it does not still hold under an expired lease.
    fn take_waiting_for(&mut self, worker: WorkerId) -> Option<u32> {
        let pos = self.waiting.iter().position(|t| {
            self.failures
                .get(t)
                .is_none_or(|(_, on)| !on.contains(&worker))
                && self
                    .in_flight
                    .get(t)
                    .is_none_or(|ls| ls.iter().all(|l| l.worker != worker))
        })?;
        self.waiting.remove(pos)
    }

    /// The tile to duplicate for an idle worker: in flight with one live holder that is
    /// not this worker, never failed on this worker, out the longest.
    fn straggler_for(&self, worker: WorkerId) -> Option<u32> {
        self.in_flight
            .iter()
            .filter(|(t, ls)| {
                ls.iter().all(|l| l.worker != worker)
                    && ls.iter().filter(|l| !l.expired).count() == 1
                    && self
                        .failures
                        .get(t)
                        .is_none_or(|(_, on)| !on.contains(&worker))
            })
            .min_by_key(|(t, ls)| (ls.iter().map(|l| l.started).min(), **t))
            .map(|(t, _)| *t)
    }
}

struct Worker {
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
    workers: BTreeMap<WorkerId, Worker>,
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
            Event::WorkerJoined { worker, threads } => {
                self.workers.insert(
                    worker,
                    Worker {
                        credit: 2 * threads.max(1) as usize,
                        holding: BTreeSet::new(),
                        scenes: BTreeSet::new(),
                        draining: false,
                        last_seen: self.now,
                    },
                );
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
                    self.jobs.insert(job, Job::new(priority, scene, tiles));
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
                    self.failed_attempt(worker, job, tile, &message, &mut actions);
                } else if let Some(j) = self.jobs.get_mut(&job) {
                    if j.late_copies.remove(&(tile, worker)) {
                        if let Some(w) = self.workers.get_mut(&worker) {
                            w.holding.remove(&(job, tile));
                        }
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
            if !j.done[tile as usize] {
                j.done[tile as usize] = true;
                j.remaining -= 1;
            }
        }
        j.waiting.retain(|t| !j.done[*t as usize]);
        if j.remaining == 0 {
            actions.push(Action::JobDone { job });
        } else {
            self.jobs.insert(job, j);
        }
        self.fill_all(&mut actions);
        actions
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
            .is_some_and(|j| j.waiting.len() < j.done.len())
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

    fn remove_worker(&mut self, worker: WorkerId, actions: &mut Vec<Action>) {
        let Some(w) = self.workers.remove(&worker) else {
            return;
        };
        for (job, tile) in w.holding {
            if self.release(worker, job, tile).is_some() {
                self.failed_attempt(
                    worker,
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
            actions.push(Action::DropWorker { worker });
            self.remove_worker(worker, actions);
        }
    }

    /// Puts back every tile whose only live lease has run out.
    fn check_leases(&mut self) {
        let now = self.now;
        for job in self.jobs.values_mut() {
            let mut requeue = Vec::new();
            for (tile, leases) in &mut job.in_flight {
                let mut expired_now = false;
                for lease in leases
                    .iter_mut()
                    .filter(|l| !l.expired && l.deadline <= now)
                {
                    lease.expired = true;
                    expired_now = true;
                }
                if expired_now && leases.iter().all(|l| l.expired) {
                    requeue.push(*tile);
                }
            }
            for tile in requeue {
                if !job.waiting.contains(&tile) {
                    job.waiting.push_front(tile);
                }
            }
        }
    }

    /// Ends the worker's lease on the tile if it holds one for an active job, and
    /// returns it. Anything else (a stray or late message) changes nothing.
    fn release(&mut self, worker: WorkerId, job_id: JobId, tile: u32) -> Option<Lease> {
        let job = self.jobs.get_mut(&job_id)?;
        let leases = job.in_flight.get_mut(&tile)?;
        let pos = leases.iter().position(|l| l.worker == worker)?;
        let lease = leases.remove(pos);
        if leases.is_empty() {
            job.in_flight.remove(&tile);
        }
        if let Some(w) = self.workers.get_mut(&worker) {
            w.holding.remove(&(job_id, tile));
        }
        Some(lease)
    }

    fn tile_done(&mut self, worker: WorkerId, job_id: JobId, tile: u32, actions: &mut Vec<Action>) {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return;
        };
        if job.late_copies.remove(&(tile, worker)) {
            if let Some(w) = self.workers.get_mut(&worker) {
                w.holding.remove(&(job_id, tile));
            }
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
        job.done[tile as usize] = true;
        job.remaining -= 1;
        job.waiting.retain(|t| *t != tile);
        // Other holders' copies are still to come: they will be compared.
        if let Some(others) = job.in_flight.remove(&tile) {
            for other in others {
                job.late_copies.insert((tile, other.worker));
            }
        }
        actions.push(Action::AcceptTile { job: job_id, tile });
        if job.remaining == 0 {
            let holders: BTreeSet<WorkerId> = job.late_copies.iter().map(|(_, w)| *w).collect();
            self.jobs.remove(&job_id);
            for holder in holders {
                if let Some(w) = self.workers.get_mut(&holder) {
                    w.holding.retain(|(j, _)| *j != job_id);
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
        worker: WorkerId,
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
        on.insert(worker);
        let attempts = *attempts;
        let worker_failures = job.worker_failures.entry(worker).or_default();
        *worker_failures += 1;
        if *worker_failures >= self.policy.block_after {
            job.blocked.insert(worker);
        }
        if attempts >= self.policy.max_attempts {
            let message = format!("tile {tile} failed {attempts} times; last: {message}");
            self.end_job(job_id, actions);
            actions.push(Action::JobFailed {
                job: job_id,
                message,
            });
        } else if job.live_leases(tile) == 0 && !job.waiting.contains(&tile) {
            job.waiting.push_front(tile);
        }
    }

    /// Removes an active job, telling the workers that hold its tiles to drop them.
    fn end_job(&mut self, job_id: JobId, actions: &mut Vec<Action>) {
        let Some(job) = self.jobs.remove(&job_id) else {
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

    fn fill_all(&mut self, actions: &mut Vec<Action>) {
        let ids: Vec<WorkerId> = self.workers.keys().copied().collect();
        for worker in ids {
            self.fill(worker, actions);
        }
    }

    /// Gives the worker tiles until its credit is used or nothing is left for it.
    fn fill(&mut self, worker_id: WorkerId, actions: &mut Vec<Action>) {
        loop {
            let Some(worker) = self.workers.get(&worker_id) else {
                return;
            };
            if worker.draining || worker.holding.len() >= worker.credit {
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
            let deadline = now + job.lease_length(&policy);
            job.in_flight.entry(tile).or_default().push(Lease {
                worker: worker_id,
                started: now,
                deadline,
                expired: false,
            });
            let scene = job.scene;
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
        let mut candidates: Vec<(&JobId, &Job)> = self
            .jobs
            .iter()
            .filter(|(_, j)| !j.blocked.contains(&worker))
            .collect();
        candidates.sort_by_key(|(id, j)| (std::cmp::Reverse(j.priority), j.in_flight.len(), **id));
        let order: Vec<JobId> = candidates.iter().map(|(id, _)| **id).collect();
        for id in &order {
            let job = self.jobs.get_mut(id).expect("listed above");
            if let Some(tile) = job.take_waiting_for(worker) {
                return Some((*id, tile));
            }
        }
        if !self.policy.speculate {
            return None;
        }
        let holding = &self.workers.get(&worker)?.holding;
        order.iter().find_map(|id| {
            let job = &self.jobs[id];
            if !job.waiting.is_empty() {
                return None;
            }
            job.straggler_for(worker)
                .filter(|t| !holding.contains(&(*id, *t)))
                .map(|t| (*id, t))
        })
    }
}
