// The scheduler's decisions written the plain way, without its indexes (per-tile queue
// state, the straggler, deadline and last-heard indexes, the maintained job order, the
// set of workers with free credit, the count of ready machines): every search walks
// every tile, lease or worker. It is the oracle that
// `the_indexed_scheduler_decides_as_the_reference_does` (scheduler_props.rs) compares
// the real one against, event by event. Change it when the decisions change (as for
// lost connections, stalls, pauses and storage outages), never to follow an
// optimisation of the real one: the point is that it stays obviously right.

//! The scheduler core, plainly: which tile goes to which worker, when a lease runs out,
//! and when a job is finished or has failed. See `scheduler::tiles` for the policy.

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
    /// Failed attempts at one tile before its job fails.
    pub max_attempts: u32,
    /// Failures of one job's tiles on one worker before the worker is blocked from it.
    pub block_after: u32,
    /// Whether to duplicate stragglers near the end of a job.
    pub speculate: bool,
    /// Losses of one tile with its worker before its job fails.
    pub max_losses: u32,
    /// How long a job may stay stalled (no connected worker may take any waiting tile).
    pub stall_timeout: Millis,
    /// The most tiles a worker may hold per thread (at least 2), however long its round
    /// trip.
    pub max_credit_per_thread: u32,
    /// A longer gap between two calls is a pause, counted as one wake interval.
    pub pause_threshold: Millis,
    /// The longest gap between calls the daemon is told to leave.
    pub wake_interval: Millis,
    /// A worker holding a tile late and silent (no result) for longer than this, or
    /// than `progress_factor` times its pace, is unresponsive.
    pub progress_timeout: Millis,
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
            max_credit_per_thread: 64,
            pause_threshold: 2_000,
            wake_interval: 1_000,
            progress_timeout: 20_000,
            progress_factor: 16,
        }
    }
}

impl Policy {
    fn wake(&self) -> Millis {
        self.wake_interval.clamp(1, self.pause_threshold.max(1))
    }
}

/// Something that happened, as the daemon saw it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// Time acts: heartbeats, leases and stalls are checked.
    Timeout,
    WorkerJoined {
        worker: WorkerId,
        threads: u32,
        machine: Option<String>,
    },
    /// The worker is alive (any message from it counts as much).
    Heartbeat {
        worker: WorkerId,
    },
    /// The worker's connection is gone; its tiles go back to their queues, each one
    /// loss of the tile; nothing counts against the machine.
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
    /// A result that counts: alone, or as the confirmation of a result held from
    /// another machine.
    TileDone {
        worker: WorkerId,
        job: JobId,
        tile: u32,
    },
    /// A result to be held until another machine returns the same.
    TileToConfirm {
        worker: WorkerId,
        job: JobId,
        tile: u32,
        required: bool,
    },
    /// The machine gets nothing more; its tiles and held results go back, and so do
    /// the revoked done tiles.
    Quarantine {
        machine: String,
        revoke: Vec<(JobId, u32)>,
    },
    /// The worker's round trip and time per tile: its credit follows.
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
    /// No tile goes out until `StorageAvailable`.
    StorageUnavailable,
    StorageAvailable,
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
    /// Keep this result aside until another machine's equals it.
    HoldResult {
        worker: WorkerId,
        job: JobId,
        tile: u32,
    },
    /// No ready machine may confirm the held result: accept it as it is.
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
    /// The worker holds a tile late and returned nothing for `silent` ms.
    WorkerUnresponsive {
        worker: WorkerId,
        silent: Millis,
    },
    /// An unresponsive worker returned a result.
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

struct Job {
    priority: i32,
    scene: SceneHash,
    waiting: VecDeque<u32>,
    in_flight: BTreeMap<u32, Vec<Lease>>,
    done: Vec<bool>,
    remaining: u32,
    /// Failures reported per tile, and the machines each tile failed on.
    failures: BTreeMap<u32, (u32, BTreeSet<Machine>)>,
    /// Failures per machine, and the machines blocked from this job.
    worker_failures: BTreeMap<Machine, u32>,
    blocked: BTreeSet<Machine>,
    /// Losses per tile with its worker.
    losses: BTreeMap<u32, u32>,
    /// Since when no ready machine may take any waiting tile, as seen at timeouts.
    stalled_since: Option<Millis>,
    /// Holders of tiles already accepted, whose copies are still to come.
    late_copies: BTreeSet<(u32, WorkerId)>,
    /// Tiles whose result is held: the machine it came from, and whether the
    /// confirmation is required.
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
            scene,
            waiting: (0..tiles).collect(),
            in_flight: BTreeMap::new(),
            done: vec![false; tiles as usize],
            remaining: tiles,
            failures: BTreeMap::new(),
            worker_failures: BTreeMap::new(),
            blocked: BTreeSet::new(),
            losses: BTreeMap::new(),
            stalled_since: None,
            late_copies: BTreeSet::new(),
            held: BTreeMap::new(),
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

    /// Whether the tile failed on the machine.
    fn failed_on(&self, tile: u32, machine: &Machine) -> bool {
        self.failures
            .get(&tile)
            .is_some_and(|(_, on)| on.contains(machine))
    }

    /// Whether the tile holds a result from the machine (which may then not render it).
    fn held_from(&self, tile: u32, machine: &Machine) -> bool {
        self.held.get(&tile).is_some_and(|(m, _)| m == machine)
    }

    /// Whether a worker of the machine may render the tile: it is not blocked from the
    /// job, the tile did not fail on it, and holds no result of it.
    fn open_to(&self, tile: u32, machine: &Machine) -> bool {
        !self.blocked.contains(machine)
            && !self.failed_on(tile, machine)
            && !self.held_from(tile, machine)
    }

    /// Puts the tile at the head of the queue if no live lease is on it and it is not
    /// there already. Returns whether it was put back.
    fn requeue(&mut self, tile: u32) -> bool {
        if self.live_leases(tile) == 0 && !self.waiting.contains(&tile) {
            self.waiting.push_front(tile);
            true
        } else {
            false
        }
    }

    /// The first waiting tile this worker may take: one that has not failed on its
    /// machine, holds no result from it, and that it does not still hold under an
    /// expired lease.
    fn take_waiting_for(&mut self, worker: WorkerId, machine: &Machine) -> Option<u32> {
        let pos = self.waiting.iter().position(|t| {
            !self.failed_on(*t, machine)
                && !self.held_from(*t, machine)
                && self
                    .in_flight
                    .get(t)
                    .is_none_or(|ls| ls.iter().all(|l| l.worker != worker))
        })?;
        self.waiting.remove(pos)
    }

    /// The tile to duplicate for an idle worker: in flight with one live holder that is
    /// not this worker, never failed on its machine, out the longest.
    fn straggler_for(&self, worker: WorkerId, machine: &Machine) -> Option<u32> {
        self.in_flight
            .iter()
            .filter(|(t, ls)| {
                ls.iter().all(|l| l.worker != worker)
                    && ls.iter().filter(|l| !l.expired).count() == 1
                    && !self.failed_on(**t, machine)
                    && !self.held_from(**t, machine)
            })
            .min_by_key(|(t, ls)| (ls.iter().map(|l| l.started).min(), **t))
            .map(|(t, _)| *t)
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

/// The first eight machines (control characters shown as '?'), then how many more.
fn name_list(machines: &[&Machine]) -> String {
    let mut list: Vec<String> = machines
        .iter()
        .take(8)
        .map(|m| m.to_string().replace(char::is_control, "?"))
        .collect();
    if machines.len() > 8 {
        list.push(format!("and {} more", machines.len() - 8));
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
    last_seen: Millis,
    /// Holds a tile late and was silent too long; until its next result.
    unresponsive: bool,
    /// Its last result, or when it was last given a tile while holding none.
    progress_since: Millis,
    /// The longest from its lease's start (or its previous result, if later) to a
    /// result.
    slowest_result: Millis,
}

/// The scheduler's whole state.
#[derive(Default)]
pub struct Scheduler {
    policy: Policy,
    /// The scheduler's clock: the daemon's less its pauses.
    now: Millis,
    /// The daemon's clock at the last call.
    wall: Option<Millis>,
    /// The scheduler's clock at the last `Timeout`, or at the first call.
    last_timeout: Millis,
    storage_down: bool,
    /// Active jobs (queued or running), by id; ids grow with submission order.
    jobs: BTreeMap<JobId, Job>,
    workers: BTreeMap<WorkerId, Worker>,
    /// Machines that get no tile again.
    quarantined: BTreeSet<Machine>,
}

impl Scheduler {
    pub fn with_policy(policy: Policy) -> Self {
        Scheduler {
            policy,
            ..Self::default()
        }
    }

    /// Applies one event at the daemon's time `now` and returns what to do, in order.
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
                // A quarantined machine's worker is connected but, like a draining
                // one, never given a tile.
                let draining = self.quarantined.contains(&machine);
                self.workers.insert(
                    worker,
                    Worker {
                        machine,
                        threads: threads.max(1),
                        credit: 2 * threads.max(1) as usize,
                        holding: BTreeSet::new(),
                        scenes: BTreeSet::new(),
                        draining,
                        last_seen: self.now,
                        unresponsive: false,
                        progress_since: self.now,
                        slowest_result: 0,
                    },
                );
                self.end_stalls_without_workers();
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
                self.end_stalls_without_workers();
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
                self.progressed(worker, job, tile, &mut actions);
                if self.tile_done(worker, job, tile, &mut actions) {
                    // A copy from the machine whose result the tile holds put it back
                    // in the queue: everyone may take it.
                    self.fill_all(&mut actions);
                } else {
                    // Holders of a finished job's last copies are filled at the next
                    // event that fills everyone.
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
            Event::Quarantine { machine, revoke } => {
                self.quarantine(Machine::Named(machine), &revoke);
                self.fill_all(&mut actions);
            }
            Event::WorkerPace { worker, rtt, tile } => {
                let cap = u128::from(self.policy.max_credit_per_thread.max(2));
                if let Some(w) = self.workers.get_mut(&worker) {
                    // In u128, where nothing overflows: threads × (2 + ⌈(rtt + ⌊rtt / 2⌋)
                    // / tile⌉), at most threads × cap.
                    let threads = u128::from(w.threads);
                    let span = u128::from(rtt) + u128::from(rtt / 2);
                    let cover = span.div_ceil(u128::from(tile.max(1)));
                    let credit = (threads * (2 + cover)).min(threads * cap);
                    w.credit = usize::try_from(credit).expect("within the cap");
                    self.fill(worker, &mut actions);
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
                    let machine = self
                        .workers
                        .get(&worker)
                        .map_or(Machine::Connection(worker), |w| w.machine.clone());
                    self.failed_attempt(&machine, job, tile, &message, &mut actions);
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
            Event::StorageUnavailable => self.storage_down = true,
            Event::StorageAvailable => {
                self.storage_down = false;
                self.fill_all(&mut actions);
            }
        }
        actions
    }

    /// The earliest of every heartbeat timeout, live lease deadline and stall timeout,
    /// and the last `Timeout` (or the first call) plus the wake interval while a worker
    /// or a live lease exists.
    pub fn next_deadline(&self) -> Option<Millis> {
        let wall = self.wall?;
        let mut times: Vec<Millis> = Vec::new();
        for w in self.workers.values() {
            times.push(w.last_seen + self.policy.heartbeat_timeout + 1);
        }
        let mut live_lease = false;
        for job in self.jobs.values() {
            for lease in job.in_flight.values().flatten().filter(|l| !l.expired) {
                times.push(lease.deadline);
                live_lease = true;
            }
            if let Some(since) = job.stalled_since {
                times.push(since + self.policy.stall_timeout);
            }
        }
        if !self.workers.is_empty() || live_lease {
            times.push(self.last_timeout + self.policy.wake());
        }
        let at = times.into_iter().min()?;
        Some(wall + at.saturating_sub(self.now))
    }

    /// A gap beyond the pause threshold counts as one wake interval.
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

    /// The machines of the live workers that are neither draining nor unresponsive.
    fn ready(&self) -> BTreeSet<Machine> {
        self.workers
            .values()
            .filter(|w| !w.draining && !w.unresponsive)
            .map(|w| w.machine.clone())
            .collect()
    }

    /// Without a ready machine no job is stalled: its clock starts again.
    fn end_stalls_without_workers(&mut self) {
        if self.ready().is_empty() {
            for job in self.jobs.values_mut() {
                job.stalled_since = None;
            }
        }
    }

    /// Per job, in id order: stalled if some tile waits and no ready machine may take
    /// any waiting tile; fails once stalled for the stall timeout.
    fn check_stalls(&mut self, actions: &mut Vec<Action>) {
        let ready = self.ready();
        let now = self.now;
        let mut failed = Vec::new();
        for (&id, job) in &mut self.jobs {
            let takeable = |t: u32| ready.iter().any(|m| job.open_to(t, m));
            let stalled = !ready.is_empty()
                && !job.waiting.is_empty()
                && !job.waiting.iter().any(|&t| takeable(t));
            if !stalled {
                job.stalled_since = None;
                continue;
            }
            let since = *job.stalled_since.get_or_insert(now);
            if now - since >= self.policy.stall_timeout {
                let tile = job.waiting[0];
                let (failed_here, blocked): (Vec<&Machine>, Vec<&Machine>) =
                    ready.iter().partition(|m| job.failed_on(tile, m));
                let head = format!("no connected worker may render tile {tile}");
                let k = self.policy.block_after;
                let holder = job.held.get(&tile).map(|(m, _)| m);
                let message = if let Some(holder) = holder.filter(|m| blocked.contains(m)) {
                    // The machine its result came from: neither failed nor blocked.
                    let others: Vec<&Machine> =
                        blocked.iter().copied().filter(|m| *m != holder).collect();
                    let rest = if failed_here.is_empty() && others.is_empty() {
                        "no other machine is connected".to_string()
                    } else if others.is_empty() {
                        format!("it failed on the others ({})", name_list(&failed_here))
                    } else if failed_here.is_empty() {
                        format!(
                            "the others are blocked from the job after failing {k} of its tiles \
                             ({})",
                            name_list(&others)
                        )
                    } else {
                        format!(
                            "it failed on some of the others ({}) and the rest are blocked from \
                             the job after failing {k} of its tiles ({})",
                            name_list(&failed_here),
                            name_list(&others)
                        )
                    };
                    format!(
                        "{head}: its result from {} awaits confirmation by another machine, and \
                         {rest}",
                        name_list(&[holder])
                    )
                } else if blocked.is_empty() {
                    format!(
                        "{head}: it failed on every one of them ({})",
                        name_list(&failed_here)
                    )
                } else if failed_here.is_empty() {
                    format!(
                        "{head}: every one of them is blocked from the job after failing {k} \
                         of its tiles ({})",
                        name_list(&blocked)
                    )
                } else {
                    format!(
                        "{head}: it failed on some of them ({}) and the others are blocked \
                         from the job after failing {k} of its tiles ({})",
                        name_list(&failed_here),
                        name_list(&blocked)
                    )
                };
                failed.push((id, message));
            }
        }
        // Machines with a connected worker, all of them unresponsive: named apart.
        let unresponsive: BTreeSet<&Machine> = self
            .workers
            .values()
            .filter(|w| w.unresponsive && !ready.contains(&w.machine))
            .map(|w| &w.machine)
            .collect();
        let note = if unresponsive.is_empty() {
            String::new()
        } else {
            let list: Vec<&Machine> = unresponsive.into_iter().collect();
            format!(
                "; not counted, unresponsive (leases ran out without a result): {}",
                name_list(&list)
            )
        };
        let failed: Vec<(JobId, String)> = failed
            .into_iter()
            .map(|(id, message)| (id, format!("{message}{note}")))
            .collect();
        for (job, message) in failed {
            self.end_job(job, actions);
            actions.push(Action::JobFailed { job, message });
        }
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

    /// Its tiles go back, each one loss; nothing counts against its machine.
    fn remove_worker(&mut self, worker: WorkerId, actions: &mut Vec<Action>) {
        let Some(w) = self.workers.remove(&worker) else {
            return;
        };
        self.end_stalls_without_workers();
        for (job, tile) in w.holding {
            if self.release(worker, job, tile).is_some() {
                self.lost(job, tile, actions);
            } else if let Some(j) = self.jobs.get_mut(&job) {
                j.late_copies.remove(&(tile, worker));
            }
        }
    }

    /// One more loss of the tile: retry it, or fail the job at `max_losses`.
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
        } else if job.live_leases(tile) == 0 && !job.waiting.contains(&tile) {
            job.waiting.push_front(tile);
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

    /// Every worker (in id order) not unresponsive that holds a tile late (a lease that
    /// ran out, or a copy of a tile accepted since) and returned nothing for longer
    /// than max(progress_timeout, progress_factor × its pace) is marked unresponsive:
    /// its live leases run out at once (each tile left without one waits again, at the
    /// head), and it counts as ready no more.
    fn check_progress(&mut self, actions: &mut Vec<Action>) {
        let ids: Vec<WorkerId> = self.workers.keys().copied().collect();
        for id in ids {
            let w = &self.workers[&id];
            if w.unresponsive {
                continue;
            }
            let mut late = false;
            let mut pace = w.slowest_result;
            for &(job_id, tile) in &w.holding {
                let Some(job) = self.jobs.get(&job_id) else {
                    continue;
                };
                pace = pace.max(job.slowest);
                let expired = job
                    .in_flight
                    .get(&tile)
                    .is_some_and(|ls| ls.iter().any(|l| l.worker == id && l.expired));
                late |= expired || job.late_copies.contains(&(tile, id));
            }
            let allowance = self
                .policy
                .progress_timeout
                .max(pace.saturating_mul(self.policy.progress_factor));
            let silent = self.now.saturating_sub(w.progress_since);
            if !late || silent <= allowance {
                continue;
            }
            let holding: Vec<(JobId, u32)> = w.holding.iter().copied().collect();
            self.workers.get_mut(&id).expect("listed").unresponsive = true;
            for (job_id, tile) in holding {
                let Some(job) = self.jobs.get_mut(&job_id) else {
                    continue;
                };
                let Some(leases) = job.in_flight.get_mut(&tile) else {
                    continue;
                };
                for l in leases.iter_mut().filter(|l| l.worker == id) {
                    l.expired = true;
                }
                if !job.done[tile as usize] {
                    job.requeue(tile);
                }
            }
            actions.push(Action::WorkerUnresponsive { worker: id, silent });
            self.end_stalls_without_workers();
        }
    }

    /// A result or a failure from the worker: its pace (from its lease on the tile, if
    /// it holds one) and its progress; an unresponsive worker is responsive again.
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
            w.slowest_result = w
                .slowest_result
                .max(now.saturating_sub(started.max(w.progress_since)));
        }
        w.progress_since = now;
        if w.unresponsive {
            w.unresponsive = false;
            actions.push(Action::WorkerResponsive { worker });
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

    /// The machine a worker counts as (its connection, once it has left).
    fn machine_of(&self, worker: WorkerId) -> Machine {
        self.workers
            .get(&worker)
            .map_or(Machine::Connection(worker), |w| w.machine.clone())
    }

    /// A result. Returns whether the tile went back to the queue (a copy from the
    /// machine whose result it holds, which only frees the slot).
    fn tile_done(
        &mut self,
        worker: WorkerId,
        job_id: JobId,
        tile: u32,
        actions: &mut Vec<Action>,
    ) -> bool {
        let machine = self.machine_of(worker);
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return false;
        };
        if job.late_copies.remove(&(tile, worker)) {
            if let Some(w) = self.workers.get_mut(&worker) {
                w.holding.remove(&(job_id, tile));
            }
            actions.push(Action::DuplicateResult { job: job_id, tile });
            return false;
        }
        if job.held_from(tile, &machine) {
            // A machine does not confirm its own result.
            return self.release(worker, job_id, tile).is_some()
                && self.jobs.get_mut(&job_id).expect("released").requeue(tile);
        }
        let Some(lease) = self.release(worker, job_id, tile) else {
            return false;
        };
        let job = self.jobs.get_mut(&job_id).expect("release checked the job");
        job.held.remove(&tile);
        let took = self.now.saturating_sub(lease.started);
        job.measured += 1;
        job.total_time += took;
        job.slowest = job.slowest.max(took);
        // The first measured tile: leases given under the initial lease end no later
        // than their start plus the measured lease.
        if job.measured == 1 {
            let length = job.lease_length(&self.policy);
            for lease in job.in_flight.values_mut().flatten() {
                if !lease.expired {
                    lease.deadline = lease.deadline.min(lease.started + length);
                }
            }
        }
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
        false
    }

    /// A result to be confirmed by another machine. On a tile holding another machine's
    /// result it is the confirmation; on one holding this machine's, or from a
    /// straggler of an accepted tile, it counts as a `TileDone`. Otherwise, from a
    /// holder: the result is held and the tile waits (unless someone else renders it).
    fn tile_to_confirm(
        &mut self,
        worker: WorkerId,
        job_id: JobId,
        tile: u32,
        required: bool,
        actions: &mut Vec<Action>,
    ) {
        let machine = self.machine_of(worker);
        let Some(job) = self.jobs.get(&job_id) else {
            return;
        };
        if job.held.contains_key(&tile) || job.late_copies.contains(&(tile, worker)) {
            self.tile_done(worker, job_id, tile, actions);
            return;
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
        job.requeue(tile);
    }

    /// The machine's workers get nothing more and give back what they hold (no loss),
    /// its held results are dropped, and the revoked done tiles of active jobs wait
    /// again; their late copies' holders hold them again, under leases that ran out.
    fn quarantine(&mut self, machine: Machine, revoke: &[(JobId, u32)]) {
        self.quarantined.insert(machine.clone());
        let ids: Vec<WorkerId> = self
            .workers
            .iter()
            .filter(|(_, w)| w.machine == machine)
            .map(|(&id, _)| id)
            .collect();
        for worker in ids {
            let w = self.workers.get_mut(&worker).expect("listed above");
            w.draining = true;
            let holding = std::mem::take(&mut w.holding);
            for (job, tile) in holding {
                if self.release(worker, job, tile).is_some() {
                    self.jobs.get_mut(&job).expect("released").requeue(tile);
                } else if let Some(j) = self.jobs.get_mut(&job) {
                    j.late_copies.remove(&(tile, worker));
                }
            }
        }
        self.end_stalls_without_workers();
        for job in self.jobs.values_mut() {
            job.held.retain(|_, (m, _)| *m != machine);
        }
        let now = self.now;
        for &(job_id, tile) in revoke {
            let Some(job) = self.jobs.get_mut(&job_id) else {
                continue;
            };
            if job.done.get(tile as usize) != Some(&true) {
                continue;
            }
            job.done[tile as usize] = false;
            job.remaining += 1;
            let copies: Vec<WorkerId> = job
                .late_copies
                .iter()
                .filter(|(t, _)| *t == tile)
                .map(|&(_, w)| w)
                .collect();
            for worker in copies {
                job.late_copies.remove(&(tile, worker));
                job.in_flight.entry(tile).or_default().push(Lease {
                    worker,
                    started: now,
                    deadline: now,
                    expired: true,
                });
            }
            job.requeue(tile);
        }
    }

    /// At a timeout: accepts, in job then tile order, the held results of optional
    /// confirmations that no live lease is on and that no ready machine but their own
    /// may give (each is blocked from the job or failed the tile). Holders under
    /// expired leases become late copies; a job with nothing left is done.
    fn give_up_confirmations(&mut self, actions: &mut Vec<Action>) {
        let ready = self.ready();
        let mut finished = Vec::new();
        for (&id, job) in &mut self.jobs {
            let given_up: Vec<u32> = job
                .held
                .iter()
                .filter(|&(&t, (from, required))| {
                    !required
                        && job.live_leases(t) == 0
                        && !ready
                            .iter()
                            .any(|m| m != from && !job.blocked.contains(m) && !job.failed_on(t, m))
                })
                .map(|(&t, _)| t)
                .collect();
            for tile in given_up {
                job.held.remove(&tile);
                job.waiting.retain(|t| *t != tile);
                for other in job.in_flight.remove(&tile).into_iter().flatten() {
                    job.late_copies.insert((tile, other.worker));
                }
                job.done[tile as usize] = true;
                job.remaining -= 1;
                actions.push(Action::AcceptHeld { job: id, tile });
            }
            if job.remaining == 0 {
                finished.push(id);
            }
        }
        for id in finished {
            self.end_job(id, actions);
            actions.push(Action::JobDone { job: id });
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
        if self.storage_down {
            return;
        }
        loop {
            let Some(worker) = self.workers.get(&worker_id) else {
                return;
            };
            if worker.draining || worker.unresponsive || worker.holding.len() >= worker.credit {
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
            if worker.holding.is_empty() {
                worker.progress_since = now;
            }
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
        let machine = self.workers.get(&worker)?.machine.clone();
        let mut candidates: Vec<(&JobId, &Job)> = self
            .jobs
            .iter()
            .filter(|(_, j)| !j.blocked.contains(&machine))
            .collect();
        candidates.sort_by_key(|(id, j)| (std::cmp::Reverse(j.priority), j.in_flight.len(), **id));
        let order: Vec<JobId> = candidates.iter().map(|(id, _)| **id).collect();
        for id in &order {
            let job = self.jobs.get_mut(id).expect("listed above");
            if let Some(tile) = job.take_waiting_for(worker, &machine) {
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
            job.straggler_for(worker, &machine)
                .filter(|t| !holding.contains(&(*id, *t)))
                .map(|t| (*id, t))
        })
    }
}
