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
//! - **Bounded calls.** One call hands out at most [`Policy::handout_per_call`] tiles:
//!   a job of thousands of tiles submitted to thousands of idle threads goes out over
//!   several calls ([`Scheduler::has_more`], then [`Event::Continue`]), in the same
//!   order, and what arrives meanwhile is heard in between. Likewise one call makes at
//!   most [`Policy::checks_per_call`] checks (leases run out, entries of silent
//!   workers, workers looked at for progress, scenes forgotten): thousands of leases
//!   running out together, or a scene thousands of workers have, are taken over
//!   several calls at the same time. The earliest go first; with no bound, the
//!   decisions are those of one call. No work waits on a table that grows with the
//!   farm all at once: the leases handed out before a job's first tile is measured
//!   share one length, so bringing them down to the measured lease moves none, and the
//!   queue of last-heard times grows a millisecond's bucket at a time.
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

mod blocks;
mod confirmation;
mod events;
mod handout;
mod job;
mod liveness;
mod policy;
mod pools;
mod results;
mod sharded;
mod worker;

use std::collections::{BTreeMap, BTreeSet, VecDeque};

use protocol::{JobId, SceneHash, WorkerId};

pub use events::{Action, Event};
pub use handout::INTERACTIVE_RUN;
use job::{Job, JobRank, Lease, TileState};
pub use policy::Policy;
pub(crate) use worker::ByWorker;
use worker::{name_list, ByTile, Machine, Overdue, SeenQueue, Worker};

/// Milliseconds on the daemon's monotonic clock (or a test's virtual one).
pub type Millis = u64;

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
    workers: ByWorker<Worker>,
    /// The credit of every worker, added up as it changes: a sequence asks for it on
    /// each of its tiles handed out, which must not walk a farm of thousands.
    credit_total: u64,
    /// When each worker was heard from, oldest first, so that a timeout looks only at
    /// those that fell silent: every message appends (the clock never goes back, so
    /// the queue stays in order), and an entry older than its worker's last one is
    /// stale, dropped when it reaches the front ([`Scheduler::trim_seen`]). The front
    /// is a live worker's last time, the earliest of them, once the stale entries
    /// before it are dropped (a long run of them over several calls). Appending costs
    /// nothing like moving the worker in an ordered set, which every message of every
    /// worker did.
    by_last_seen: SeenQueue,
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
    /// nothing late; a timeout looks only at those due ([`Overdue`]).
    overdue: Overdue,
    /// Tiles this call may still hand out ([`Policy::handout_per_call`]), and whether
    /// a call stopped at that bound with tiles left to hand out.
    handout_left: usize,
    more: bool,
    /// Checks this call may still make ([`Policy::checks_per_call`]), and whether a
    /// call stopped at that bound with checks left, until a call makes them all.
    checks_left: usize,
    checks_more: bool,
    /// Scenes no active job uses, whose holders are still to be told to forget them,
    /// in the order they fell out of use ([`Scheduler::forget_unused_scenes`]).
    forgetting: VecDeque<SceneHash>,
    counters: Counters,
    /// The tags each job requires ([`Event::RequireTags`]), for the jobs that require
    /// any: kept by id like a pause, so that they hold from before the job is
    /// submitted and across its runs.
    requirements: BTreeMap<JobId, pools::Tags>,
    /// Each worker's tags ([`Event::WorkerTags`]), told before it joins; dropped when
    /// it leaves.
    worker_tags: BTreeMap<WorkerId, pools::Tags>,
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
        self.handout_left = self.policy.handout_per_call.max(1);
        self.checks_left = self.policy.checks_per_call.max(1);
        self.checks_left = self.policy.checks_per_call.max(1);
        let mut actions = Vec::new();
        match event {
            Event::Timeout => {
                self.last_timeout = self.now;
                self.checks_more = false;
                self.check_heartbeats(&mut actions);
                self.check_leases();
                self.check_progress(&mut actions);
                self.forget_pending(&mut actions);
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
                self.credit_total += joined.credit as u64;
                if let Some(old) = self.workers.insert(worker, joined) {
                    self.credit_total -= old.credit as u64;
                    self.unlist_scenes(worker, &old.scenes);
                    if old.takes_tiles() {
                        self.unready(&old.machine);
                    }
                }
                self.by_last_seen.push(self.now, worker);
                self.trim_seen();
                self.overdue.reserve(self.workers.len());
                self.hungry.insert(worker);
                self.fill(worker, &mut actions);
            }
            Event::Heartbeat { worker } => self.seen(worker),
            // Goes on with what the last calls left at their bounds: the checks, then
            // the hand-out.
            Event::Continue => {
                if std::mem::take(&mut self.checks_more) {
                    self.check_heartbeats(&mut actions);
                    self.check_leases();
                    self.check_progress(&mut actions);
                    self.forget_pending(&mut actions);
                }
                self.fill_all(&mut actions);
            }
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
                    let credit = threads
                        .saturating_mul(cover.saturating_add(2))
                        .min(threads.saturating_mul(cap));
                    self.credit_total = self.credit_total - w.credit as u64 + credit as u64;
                    w.credit = credit;
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
            Event::RequireTags { job, tags } => self.set_requirements(job, tags, &mut actions),
            Event::WorkerTags { worker, tags } => {
                self.set_worker_tags(worker, tags, &mut actions);
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
        if let Some((seen, _)) = self.by_last_seen.front() {
            sooner(seen + self.policy.heartbeat_timeout + 1);
        }
        for job in self.jobs.values() {
            if let Some(deadline) = job.first_deadline() {
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
        self.handout_left = self.policy.handout_per_call.max(1);
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
        out.sort_unstable_by_key(|&(job, tile, worker, _)| (job, tile, worker));
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
        debug_assert_eq!(
            self.credit_total,
            self.workers.values().map(|w| w.credit as u64).sum::<u64>()
        );
        self.credit_total
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

    /// Whether the last call stopped at [`Policy::handout_per_call`] with tiles left
    /// to hand out, or a call at [`Policy::checks_per_call`] with checks left: the
    /// daemon feeds [`Event::Continue`] at once, after whatever arrived meanwhile (any
    /// call that fills goes on where it stopped).
    pub fn has_more(&self) -> bool {
        self.more || self.checks_more
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
        let mut workers: Vec<WorkerId> = self
            .workers
            .iter()
            .filter(|(_, w)| w.machine == machine && w.disabled != disabled)
            .map(|(&id, _)| id)
            .collect();
        workers.sort_unstable();
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
            // The job its id named is replaced, and its pace with it: its holders'
            // allowance may be less now (as when a job ends).
            for worker in old.holders() {
                self.overdue.sooner(worker, self.now);
            }
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
        self.worker_tags.remove(&worker);
        self.credit_total -= w.credit as u64;
        self.hungry.remove(&worker);
        self.trim_seen();
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

    /// The machine a worker counts as (its connection, once it has left).
    fn machine_of(&self, worker: WorkerId) -> Machine {
        self.workers
            .get(&worker)
            .map_or(Machine::Connection(worker), |w| w.machine.clone())
    }
}

#[cfg(test)]
mod tests;
