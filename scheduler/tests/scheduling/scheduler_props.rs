//! The scheduler core against a model of the daemon that carries out its actions.
//!
//! [`Farm`] feeds events to the [`Scheduler`], each at a time of the daemon's clock, and
//! replays every returned action the way the daemon would: it tracks which tiles each
//! worker holds and under which lease (from `Assign`, `CancelOnWorker`, `DropWorker` and
//! the worker's own results), which scenes each worker has (from `SendScene` and
//! `ForgetScene`), which tiles were accepted, the failures reported per tile and per
//! machine, the losses per tile, the measured tile times that set the lease length, when
//! each worker was last heard from, the scheduler's clock, and how each job ended.
//! Before handing an event to the scheduler it works out what the event must cause
//! (which result is accepted or is a duplicate, which workers are dropped, which leases
//! run out, which jobs end and why); after it, it checks the actions against that and the
//! invariants below, so the unit tests get them for free.
//!
//! Checked after every event (a violation panics with the event that caused it):
//! - **Assignments**: only to a live, non-draining worker, under its credit (twice its
//!   threads), after the scene, and never while storage is unavailable; never a tile
//!   the worker holds already, that failed on its machine, or of a job its machine is
//!   blocked from; never an accepted tile or one of an ended job.
//! - **Policy order**: a waiting tile goes to the job the module doc names: highest
//!   priority with a tile the worker may take, then fewest tiles in flight, then oldest.
//! - **Stragglers**: a tile with a live holder is given again only with speculation on,
//!   when no job has a waiting tile the worker may take and the tile's job has none
//!   waiting at all; it is the tile out longest of the first job in policy order, with
//!   exactly one live holder; so a tile has at most two live holders (one without
//!   speculation), and never twice the same worker.
//! - **Work conservation**: while storage is available, no worker with free credit idles
//!   next to a tile it may take (except right after a `TileDone` that completed a job
//!   still out on other workers: the scheduler then fills only the sender, and the
//!   holders freed by the `CancelOnWorker` wait for the next event that fills everyone,
//!   a timeout at the latest).
//! - **Scenes once**: a `SendScene` right before the first `Assign` of a scene to a
//!   worker, never twice, and `ForgetScene` once no active job uses it.
//! - **Results**: `AcceptTile` exactly when a holder returns a tile not yet accepted
//!   (also under a lease that ran out), `DuplicateResult` exactly when a holder returns a
//!   tile already accepted; everything else is dropped.
//! - **Time**: the scheduler's clock follows the daemon's, except that a gap between two
//!   events longer than `pause_threshold` counts as one `wake_interval` (the coordinator
//!   was paused, its peers were not silent). At a `Timeout`, `DropWorker` exactly for the
//!   workers silent on that clock for more than the heartbeat timeout; leases run out at
//!   their deadline (start + lease length, which follows the job's measured tile times),
//!   and the tile waits again once every live lease on it ran out. `next_deadline` is
//!   exactly the earliest heartbeat expiry, live lease deadline or stall timeout, and the
//!   last event plus the wake interval while a worker is connected; `None` without
//!   workers or leases.
//! - **Failures**: a failure reported by a holder (`TileFailed`) counts one attempt
//!   against the tile and the worker's machine; the job fails (naming the tile and the
//!   last error) exactly when a tile reaches `max_attempts`; a machine with
//!   `block_after` reported failures in a job is blocked from it. A worker leaving or
//!   dropped counts nothing against its machine: each tile it held (not yet accepted)
//!   counts one loss, and the job fails exactly when a tile reaches `max_losses`, with
//!   the message the scheduler documents.
//! - **Stalls**: at each timeout a job is stalled when tiles wait, a live non-draining
//!   worker is connected, and no such worker's machine may take any waiting tile; it
//!   fails (the message naming a waiting tile and the machines) exactly when stalled at
//!   timeouts throughout `stall_timeout`; without a ready worker the stall ends.
//! - **Confirmations**: a holder's `TileToConfirm` on a tile holding no result is held
//!   (`HoldResult`), and the tile waits for any other machine; a holder's result on a
//!   tile holding another machine's result confirms it (`AcceptTile`); one from the
//!   machine whose result is held only frees its slot. A held tile never goes to its
//!   holding machine, copies included. At a timeout, `AcceptHeld` exactly for the
//!   optional confirmations without a live lease that no ready machine but their own
//!   may give; a required one stalls its job like any tile no machine may take, and a
//!   job with a result held is never done.
//! - **Quarantine**: the machine's workers (and those joining later under its name)
//!   drain and hold nothing, and never get a tile; its held results are dropped; the
//!   revoked tiles of active jobs that were accepted wait again (copies still out on
//!   other workers become results again, under leases that ran out).
//! - **Credit**: twice the threads, then what `WorkerPace` sets: threads × (2 + ⌈rtt /
//!   tile time⌉), at most threads × `max_credit_per_thread` (taken as at least 2); an
//!   assignment only below it, and a lower credit takes nothing back.
//! - **Endings**: `JobDone` once, when all tiles are accepted; every live worker still
//!   holding tiles of an ended job (copies included) gets `CancelOnWorker`, and only
//!   those; `is_active`, `has_started`, `held_by` and `tiles_in_flight` agree.
//!
//! The histories also restart workers under the same machine name (a supervised
//! service), cut workers off the network past the heartbeat timeout and have them
//! rejoin under their name, pause the coordinator longer than the heartbeat timeout
//! (the timer firing before any message is read), and take storage away and back.
//!
//! **Liveness**, the property the histories end on: after any history, once storage is
//! available and a healthy worker is connected that heartbeats and answers every tile it
//! gets, every job ends within a bound (the others' heartbeat timeout plus the rounds the
//! healthy worker alone needs for the tiles left): `JobDone`, or `JobFailed` with its
//! reason, never stuck. A job none of whose tiles was ever reported failed (tiles only
//! lost with their workers: crashes, restarts, cuts, pauses) ends `JobDone`, unless one
//! of its tiles was lost `max_losses` times. Without a clock the same holds with every
//! worker returning its tiles.
//!
//! The issue-3 properties run without speculation and without timeouts (no lease runs
//! out, nobody is dropped); the clocked ones with the default policy but a short stall
//! timeout. Both use tighter limits on reports and losses per tile, so that jobs fail
//! for each reason within a history. Two scheduler bugs these tests found are pinned by
//! `a_tile_is_not_duplicated_to_a_worker_it_failed_on` and
//! `a_failed_late_copy_frees_the_worker_s_slot`.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, VecDeque};

use proptest::prelude::*;
use proptest::sample::Index;
use proptest::strategy::ValueTree;
use proptest::test_runner::TestRunner;
use protocol::{JobId, SceneHash, WorkerId};
use scheduler::{Action, Event, Millis, Policy, Scheduler};

/// The scheduler's decisions written without indexes: the oracle of the equivalence
/// properties (section "The indexed scheduler against the reference").
use crate::reference;

const SCENE_A: SceneHash = [1; 32];
const SCENE_B: SceneHash = [2; 32];
const SCENE_C: SceneHash = [3; 32];
const SCENES: [SceneHash; 3] = [SCENE_A, SCENE_B, SCENE_C];
/// Machine names the histories' workers give: few, so that names come back.
const NAMES: [&str; 3] = ["m0", "m1", "m2"];

/// The issue-3 setting: no duplicates (and, with no timeouts, no lease runs out).
fn no_speculation() -> Policy {
    Policy {
        speculate: false,
        // The model knows nothing of hand-outs cut into several calls (a worker whose
        // credit a pace raises to hundreds of tiles would otherwise idle between
        // calls): continuations are the unit tests'.
        handout_per_call: usize::MAX,
        checks_per_call: usize::MAX,
        ..Policy::default()
    }
}

/// The clocked histories' policy: the default, but a stall fails its job after 4 s
/// rather than 30, so that stalls happen within a history.
fn clocked_policy() -> Policy {
    Policy {
        stall_timeout: 4_000,
        // The model's deadlines know nothing of hand-outs cut into several calls.
        handout_per_call: usize::MAX,
        checks_per_call: usize::MAX,
        ..Policy::default()
    }
}

/// The random histories' limits: a tile fails its job after 3 reports or 4 losses (8
/// and 5 by default), so that histories of a few hundred events reach both.
fn tight(policy: Policy) -> Policy {
    Policy {
        max_attempts: 3,
        max_losses: 4,
        ..policy
    }
}

/// The wake interval in effect, as the scheduler's doc states it.
fn wake(policy: &Policy) -> Millis {
    policy.wake_interval.clamp(1, policy.pause_threshold.max(1))
}

// ---------------------------------------------------------------------------------------
// The model.

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Fate {
    Active,
    Done,
    Failed,
    Cancelled,
}

/// Why a job failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Why {
    Attempts,
    Losses,
    Stall,
}

/// Who reported failures count against: the name a worker gave, or its connection.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Machine {
    Named(String),
    Connection(WorkerId),
}

impl Machine {
    fn of(worker: WorkerId, name: Option<&str>) -> Machine {
        name.map_or(Machine::Connection(worker), |n| Machine::Named(n.into()))
    }

    /// As a message names it.
    fn label(&self) -> String {
        match self {
            Machine::Named(name) => name.clone(),
            Machine::Connection(id) => format!("worker {id}"),
        }
    }
}

struct ModelJob {
    priority: i32,
    scene: SceneHash,
    tiles: u32,
    accepted: BTreeSet<u32>,
    fate: Fate,
    why: Option<Why>,
    /// Failures reported per tile, and the (tile, machine) pairs that failed.
    attempts: BTreeMap<u32, u32>,
    failed_on: BTreeSet<(u32, Machine)>,
    machine_failures: BTreeMap<Machine, u32>,
    blocked: BTreeSet<Machine>,
    /// Losses per tile with its worker.
    losses: BTreeMap<u32, u32>,
    /// Stalled at every timeout since then (on the scheduler's clock).
    stalled_since: Option<Millis>,
    /// Accepted results: how many, their total and longest time from assignment.
    measured: u32,
    total_time: Millis,
    slowest: Millis,
    /// Tiles whose result is held until another machine confirms it: the machine it
    /// came from, and whether the confirmation is required.
    held: BTreeMap<u32, (Machine, bool)>,
}

impl ModelJob {
    /// As the issue states it: the initial lease until a tile is measured, then
    /// max(slowest * factor, 4 * mean, min_lease).
    fn lease_length(&self, policy: &Policy) -> Millis {
        if self.measured == 0 {
            return policy.initial_lease;
        }
        let mean = self.total_time / u64::from(self.measured);
        (self.slowest * policy.lease_factor)
            .max(mean * 4)
            .max(policy.min_lease)
    }

    fn failed_on(&self, tile: u32, machine: &Machine) -> bool {
        self.failed_on.contains(&(tile, machine.clone()))
    }

    /// Whether the tile holds a result from the machine, which may not confirm it.
    fn held_from(&self, tile: u32, machine: &Machine) -> bool {
        self.held.get(&tile).is_some_and(|(m, _)| m == machine)
    }

    /// Whether a worker of the machine may take the waiting tile.
    fn open_to(&self, tile: u32, machine: &Machine) -> bool {
        !self.blocked.contains(machine)
            && !self.failed_on(tile, machine)
            && !self.held_from(tile, machine)
    }
}

/// One tile a worker holds, as the daemon sees it.
#[derive(Clone, Copy, Debug)]
struct Held {
    /// On the scheduler's clock.
    started: Millis,
    deadline: Millis,
    /// The lease ran out (the tile may have gone to another worker since).
    expired: bool,
}

struct ModelWorker {
    machine: Machine,
    threads: u32,
    /// Twice the threads, then what `WorkerPace` sets.
    credit: usize,
    /// What the worker held when its credit was last lowered: it may hold that many
    /// until it returns them (a lower credit takes nothing back).
    allowance: usize,
    draining: bool,
    /// Tiles held: under a live or expired lease, or a copy of a tile already accepted.
    holding: BTreeMap<(JobId, u32), Held>,
    scenes: BTreeSet<SceneHash>,
    /// On the scheduler's clock.
    last_seen: Millis,
    /// Test driver only: the worker sends nothing any more (it hung, or the network
    /// to it is cut).
    silent: bool,
}

/// Counts of what the histories exercised, to show the generators reach every case.
#[derive(Clone, Copy, Debug, Default)]
struct Stats {
    accepted_late: usize,
    reassigned_after_expiry: usize,
    duplicates_assigned: usize,
    duplicate_results: usize,
    cancels_at_completion: usize,
    dropped: usize,
    blocked: usize,
    jobs_failed: usize,
    jobs_done: usize,
    /// Jobs failed by a tile reported failed `max_attempts` times, by a tile lost
    /// `max_losses` times, and by a stall.
    failed_by_attempts: usize,
    failed_by_losses: usize,
    failed_by_stall: usize,
    /// Workers that joined under a name a worker had before.
    rejoined_under_a_name: usize,
    /// Gaps beyond the pause threshold.
    pauses: usize,
    /// Events handled while storage was unavailable.
    while_storage_down: usize,
    /// Results held for confirmation (required ones too), held results confirmed by
    /// another machine, copies from the holding machine that only freed their slot,
    /// and optional confirmations given up at a timeout (and the jobs that ended so).
    holds: usize,
    holds_required: usize,
    confirmed: usize,
    unconfirming_copies: usize,
    given_up: usize,
    done_by_giving_up: usize,
    /// Jobs failed by a stall while a required confirmation no ready machine may give
    /// was pending.
    stalled_on_confirmation: usize,
    /// Quarantines, those of a machine with live workers, the done tiles they revoked
    /// (and of those, tiles with copies still to come), held results they dropped, and
    /// workers joining later under a quarantined name.
    quarantines: usize,
    quarantined_live: usize,
    revoked: usize,
    revoked_with_copies: usize,
    holds_dropped: usize,
    joined_quarantined: usize,
    /// Credit changes: raised, capped at `max_credit_per_thread`, lowered below what
    /// the worker holds.
    paces: usize,
    credit_raised: usize,
    credit_capped: usize,
    credit_lowered_below_holding: usize,
}

impl Stats {
    fn add(&mut self, o: &Stats) {
        self.accepted_late += o.accepted_late;
        self.reassigned_after_expiry += o.reassigned_after_expiry;
        self.duplicates_assigned += o.duplicates_assigned;
        self.duplicate_results += o.duplicate_results;
        self.cancels_at_completion += o.cancels_at_completion;
        self.dropped += o.dropped;
        self.blocked += o.blocked;
        self.jobs_failed += o.jobs_failed;
        self.jobs_done += o.jobs_done;
        self.failed_by_attempts += o.failed_by_attempts;
        self.failed_by_losses += o.failed_by_losses;
        self.failed_by_stall += o.failed_by_stall;
        self.rejoined_under_a_name += o.rejoined_under_a_name;
        self.pauses += o.pauses;
        self.while_storage_down += o.while_storage_down;
        self.holds += o.holds;
        self.holds_required += o.holds_required;
        self.confirmed += o.confirmed;
        self.unconfirming_copies += o.unconfirming_copies;
        self.given_up += o.given_up;
        self.done_by_giving_up += o.done_by_giving_up;
        self.stalled_on_confirmation += o.stalled_on_confirmation;
        self.quarantines += o.quarantines;
        self.quarantined_live += o.quarantined_live;
        self.revoked += o.revoked;
        self.revoked_with_copies += o.revoked_with_copies;
        self.holds_dropped += o.holds_dropped;
        self.joined_quarantined += o.joined_quarantined;
        self.paces += o.paces;
        self.credit_raised += o.credit_raised;
        self.credit_capped += o.credit_capped;
        self.credit_lowered_below_holding += o.credit_lowered_below_holding;
    }
}

/// A `JobFailed` to come, and what its message must say.
enum Failure {
    /// A tile reached `max_attempts`: the message names it and the last error.
    Attempts { tile: u32, error: String },
    /// A tile reached `max_losses`.
    Losses { tile: u32, losses: u32 },
    /// No ready machine may take a waiting tile: the message names one of them, and the
    /// machines.
    Stall {
        tiles: Vec<u32>,
        machines: Vec<String>,
    },
}

/// What an event must cause, worked out before the scheduler sees it.
#[derive(Default)]
struct Expect {
    accept: Option<(JobId, u32)>,
    accepted: bool,
    duplicate: Option<(JobId, u32)>,
    duplicated: bool,
    /// A `HoldResult` to come, and whether it came.
    hold: Option<(WorkerId, JobId, u32)>,
    held: bool,
    /// `AcceptHeld` still to come (confirmations given up at this timeout).
    given_up: BTreeSet<(JobId, u32)>,
    /// Workers silent past the timeout at this timeout.
    drops: BTreeSet<WorkerId>,
    /// `JobDone` still to come.
    done: BTreeSet<JobId>,
    /// `JobFailed` still to come.
    failed: BTreeMap<JobId, Failure>,
    /// Jobs that ended with this event: their holders are told.
    ended: BTreeSet<JobId>,
}

/// The scheduler, and the daemon's view of the farm rebuilt from its actions.
struct Farm {
    scheduler: Scheduler,
    /// When set, every event also goes to the reference scheduler, which must return
    /// the same actions.
    reference: Option<Twin>,
    policy: Policy,
    /// Fail on the two known scheduler bugs; otherwise accept them and keep checking the
    /// rest (see the ignored tests).
    strict: bool,
    /// The daemon's clock: the time of the next event.
    now: Millis,
    /// The daemon's clock at the last event, and the scheduler's own clock.
    last: Option<Millis>,
    clock: Millis,
    /// The scheduler's clock at the last `Timeout`, or at the first event.
    last_timeout: Millis,
    storage_down: bool,
    workers: BTreeMap<WorkerId, ModelWorker>,
    /// Workers being dropped by the event at hand, until their `DropWorker` is replayed:
    /// the scheduler may still cancel or forget on them before it.
    dropping: BTreeMap<WorkerId, ModelWorker>,
    /// Workers that left or were dropped, with the tiles they held then.
    departed: Vec<(WorkerId, Vec<(JobId, u32)>)>,
    jobs: BTreeMap<JobId, ModelJob>,
    next_worker: WorkerId,
    next_job: JobId,
    /// Names workers have given so far.
    names: BTreeSet<String>,
    /// Named workers cut off the network, that may rejoin: (name, threads).
    cut_off: Vec<(String, u32)>,
    /// Tiles accepted per worker whose result was kept.
    rendered_by: BTreeMap<WorkerId, usize>,
    /// Machines quarantined: they never get a tile again.
    quarantined: BTreeSet<Machine>,
    /// A `TileDone` completed a job and freed other holders, which the scheduler fills
    /// only at the next event that fills every worker.
    unfilled: bool,
    stats: Stats,
}

/// Tiles with holders: (job, tile) to (worker, lease), tiles already accepted left out.
type Holders = BTreeMap<(JobId, u32), Vec<(WorkerId, Held)>>;

impl Farm {
    /// The issue-3 farm: no speculation, and no timeouts unless a test sends them.
    fn new() -> Self {
        Farm::with_policy(no_speculation(), true)
    }

    fn with_policy(policy: Policy, strict: bool) -> Self {
        // The model does not follow workers' progress: its histories turn the check
        // for unresponsive workers off. The reference's equivalence (random policies
        // with short progress timeouts) and the liveness tests cover it.
        let policy = Policy {
            progress_timeout: Millis::MAX,
            ..policy
        };
        Farm {
            scheduler: Scheduler::with_policy(policy),
            reference: None,
            policy,
            strict,
            now: 0,
            last: None,
            clock: 0,
            last_timeout: 0,
            storage_down: false,
            workers: BTreeMap::new(),
            dropping: BTreeMap::new(),
            departed: Vec::new(),
            jobs: BTreeMap::new(),
            next_worker: 1,
            next_job: 1,
            names: BTreeSet::new(),
            cut_off: Vec::new(),
            rendered_by: BTreeMap::new(),
            quarantined: BTreeSet::new(),
            unfilled: false,
            stats: Stats::default(),
        }
    }

    fn join(&mut self, threads: u32) -> (WorkerId, Vec<Action>) {
        self.join_as(threads, None)
    }

    fn join_as(&mut self, threads: u32, name: Option<&str>) -> (WorkerId, Vec<Action>) {
        let worker = self.next_worker;
        (
            worker,
            self.step(Event::WorkerJoined {
                worker,
                threads,
                machine: name.map(str::to_string),
            }),
        )
    }

    fn submit(&mut self, priority: i32, scene: SceneHash, tiles: u32) -> (JobId, Vec<Action>) {
        let job = self.next_job;
        let actions = self.step(Event::JobSubmitted {
            job,
            priority,
            scene,
            tiles,
        });
        (job, actions)
    }

    fn done(&mut self, worker: WorkerId, job: JobId, tile: u32) -> Vec<Action> {
        self.step(Event::TileDone { worker, job, tile })
    }

    fn fail(&mut self, worker: WorkerId, job: JobId, tile: u32, message: &str) -> Vec<Action> {
        self.step(Event::TileFailed {
            worker,
            job,
            tile,
            message: message.into(),
        })
    }

    /// The daemon's clock reads `now`: the `alive` workers heartbeat, then the timer
    /// fires.
    fn tick(&mut self, now: Millis, alive: &[WorkerId]) -> Vec<Action> {
        self.now = self.now.max(now);
        for &worker in alive {
            self.step(Event::Heartbeat { worker });
        }
        self.step(Event::Timeout)
    }

    /// The tiles the worker holds, oldest job first.
    fn held(&self, worker: WorkerId) -> Vec<(JobId, u32)> {
        self.workers
            .get(&worker)
            .map_or_else(Vec::new, |w| w.holding.keys().copied().collect())
    }

    fn active(&self, job: JobId) -> bool {
        self.jobs.get(&job).is_some_and(|j| j.fate == Fate::Active)
    }

    /// Every tile not yet accepted that some live worker holds, with its leases.
    fn holders(&self) -> Holders {
        let mut holders: Holders = BTreeMap::new();
        for (&id, w) in &self.workers {
            for (&(job, tile), &held) in &w.holding {
                if self
                    .jobs
                    .get(&job)
                    .is_some_and(|j| !j.accepted.contains(&tile))
                {
                    holders.entry((job, tile)).or_default().push((id, held));
                }
            }
        }
        holders
    }

    fn live_holders(holders: &Holders, job: JobId, tile: u32) -> Vec<WorkerId> {
        holders.get(&(job, tile)).map_or_else(Vec::new, |hs| {
            hs.iter()
                .filter(|(_, h)| !h.expired)
                .map(|&(w, _)| w)
                .collect()
        })
    }

    /// Tiles of the job neither accepted nor under a live lease.
    fn waiting(&self, holders: &Holders, job: JobId) -> Vec<u32> {
        let j = &self.jobs[&job];
        (0..j.tiles)
            .filter(|t| !j.accepted.contains(t) && Self::live_holders(holders, job, *t).is_empty())
            .collect()
    }

    /// Tiles of the job not accepted and held by someone (under any lease).
    fn in_flight(holders: &Holders, job: JobId) -> usize {
        holders.range((job, 0)..=(job, u32::MAX)).count()
    }

    fn holds(&self, worker: WorkerId, job: JobId, tile: u32) -> bool {
        self.workers
            .get(&worker)
            .is_some_and(|w| w.holding.contains_key(&(job, tile)))
    }

    /// A waiting tile the worker may take: not failed on its machine, holding no result
    /// from it, not held by it already.
    fn takeable(&self, holders: &Holders, worker: WorkerId, job: JobId) -> bool {
        let j = &self.jobs[&job];
        let machine = &self.workers[&worker].machine;
        self.waiting(holders, job).into_iter().any(|t| {
            !j.failed_on(t, machine) && !j.held_from(t, machine) && !self.holds(worker, job, t)
        })
    }

    /// Active jobs the worker's machine is not blocked from, in policy order.
    fn policy_order(&self, holders: &Holders, worker: WorkerId) -> Vec<JobId> {
        let machine = &self.workers[&worker].machine;
        let mut order: Vec<JobId> = self
            .jobs
            .iter()
            .filter(|(_, j)| j.fate == Fate::Active && !j.blocked.contains(machine))
            .map(|(&id, _)| id)
            .collect();
        order.sort_by_key(|&id| {
            (
                Reverse(self.jobs[&id].priority),
                Self::in_flight(holders, id),
                id,
            )
        });
        order
    }

    /// The job whose waiting tile the worker must get next, if any.
    fn next_by_policy(&self, holders: &Holders, worker: WorkerId) -> Option<JobId> {
        self.policy_order(holders, worker)
            .into_iter()
            .find(|&id| self.takeable(holders, worker, id))
    }

    /// The tile to duplicate for the worker: in the first job in policy order with
    /// nothing waiting, the tile with exactly one live holder, not this worker, out
    /// longest. (Leniently, a tile that failed on its machine counts too.)
    fn straggler_for(&self, holders: &Holders, worker: WorkerId) -> Option<(JobId, u32)> {
        let machine = &self.workers[&worker].machine;
        self.policy_order(holders, worker)
            .into_iter()
            .filter(|&id| self.waiting(holders, id).is_empty())
            .find_map(|id| {
                let j = &self.jobs[&id];
                holders
                    .range((id, 0)..=(id, u32::MAX))
                    .filter(|(key, hs)| {
                        hs.iter().all(|(w, _)| *w != worker)
                            && hs.iter().filter(|(_, h)| !h.expired).count() == 1
                            && (!self.strict || !j.failed_on(key.1, machine))
                            && !j.held_from(key.1, machine)
                    })
                    .min_by_key(|(key, hs)| (hs.iter().map(|(_, h)| h.started).min(), key.1))
                    .map(|(&key, _)| key)
            })
    }

    /// The machines of the live workers that are not draining.
    fn ready(&self) -> BTreeSet<Machine> {
        self.workers
            .values()
            .filter(|w| !w.draining)
            .map(|w| w.machine.clone())
            .collect()
    }

    /// With no ready worker left, no job is stalled: its stall clock starts over.
    fn end_stalls_without_workers(&mut self) {
        if self.ready().is_empty() {
            for j in self.jobs.values_mut() {
                j.stalled_since = None;
            }
        }
    }

    fn end(&mut self, job: JobId, why: Why, failure: Failure, expect: &mut Expect) {
        let j = self.jobs.get_mut(&job).expect("a known job");
        j.fate = Fate::Failed;
        j.why = Some(why);
        expect.failed.insert(job, failure);
        expect.ended.insert(job);
    }

    /// Counts a failure reported by a holder of a tile not yet accepted.
    fn count_failure(
        &mut self,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        error: &str,
        expect: &mut Expect,
    ) {
        let policy = self.policy;
        let machine = self.workers[&worker].machine.clone();
        let j = self
            .jobs
            .get_mut(&job)
            .expect("held tiles are of known jobs");
        if j.fate != Fate::Active || j.accepted.contains(&tile) {
            return;
        }
        let attempts = j.attempts.entry(tile).or_default();
        *attempts += 1;
        let attempts = *attempts;
        j.failed_on.insert((tile, machine.clone()));
        let failures = j.machine_failures.entry(machine.clone()).or_default();
        *failures += 1;
        if *failures >= policy.block_after && j.blocked.insert(machine) {
            self.stats.blocked += 1;
        }
        if attempts >= policy.max_attempts {
            let error = error.to_string();
            self.end(
                job,
                Why::Attempts,
                Failure::Attempts { tile, error },
                expect,
            );
        }
    }

    /// A worker is gone: each tile it held (not yet accepted, of an active job) is one
    /// loss of the tile; nothing counts against its machine.
    fn remove_worker(&mut self, worker: WorkerId, expect: &mut Expect) -> Option<ModelWorker> {
        let w = self.workers.remove(&worker)?;
        self.end_stalls_without_workers();
        let held: Vec<(JobId, u32)> = w.holding.keys().copied().collect();
        for &(job, tile) in &held {
            let j = self
                .jobs
                .get_mut(&job)
                .expect("held tiles are of known jobs");
            if j.fate != Fate::Active || j.accepted.contains(&tile) {
                continue;
            }
            let losses = j.losses.entry(tile).or_default();
            *losses += 1;
            let losses = *losses;
            if losses >= self.policy.max_losses {
                self.end(job, Why::Losses, Failure::Losses { tile, losses }, expect);
            }
        }
        self.departed.push((worker, held));
        Some(w)
    }

    /// At a timeout, after the drops and the leases: follows each job's stall, and
    /// fails those stalled for the stall timeout.
    fn check_stalls(&mut self, expect: &mut Expect) {
        let ready = self.ready();
        let holders = self.holders();
        let mut verdicts = Vec::new();
        for (&id, j) in self.jobs.iter().filter(|(_, j)| j.fate == Fate::Active) {
            let waiting = self.waiting(&holders, id);
            let stalled = !ready.is_empty()
                && !waiting.is_empty()
                && waiting
                    .iter()
                    .all(|&t| ready.iter().all(|m| !j.open_to(t, m)));
            verdicts.push((id, stalled.then_some(waiting)));
        }
        for (id, stalled) in verdicts {
            let j = self.jobs.get_mut(&id).expect("listed above");
            let Some(tiles) = stalled else {
                j.stalled_since = None;
                continue;
            };
            let since = *j.stalled_since.get_or_insert(self.clock);
            if self.clock - since >= self.policy.stall_timeout {
                if j.held.values().any(|&(_, required)| required) {
                    self.stats.stalled_on_confirmation += 1;
                }
                let machines = ready.iter().map(Machine::label).collect();
                self.end(id, Why::Stall, Failure::Stall { tiles, machines }, expect);
            }
        }
    }

    /// A result from a worker: `TileDone` (`to_confirm` None) or `TileToConfirm`. From a
    /// holder of the tile only: a copy of a tile accepted is a duplicate; one from the
    /// machine whose result the tile holds only frees the slot; one on a tile holding
    /// another machine's result confirms it (accepted); a `TileToConfirm` otherwise is
    /// held. Returns whether the tile went back to the queue.
    fn result(
        &mut self,
        worker: WorkerId,
        job: JobId,
        tile: u32,
        to_confirm: Option<bool>,
        expect: &mut Expect,
    ) -> bool {
        let Some(w) = self.workers.get_mut(&worker) else {
            return false;
        };
        let Some(held) = w.holding.remove(&(job, tile)) else {
            return false;
        };
        let machine = w.machine.clone();
        let j = self
            .jobs
            .get_mut(&job)
            .expect("held tiles are of known jobs");
        if j.accepted.contains(&tile) {
            expect.duplicate = Some((job, tile));
            return false;
        }
        if j.held_from(tile, &machine) {
            self.stats.unconfirming_copies += 1;
            // Back in the queue if that was the last live lease.
            let holders = self.holders();
            return !held.expired && Self::live_holders(&holders, job, tile).is_empty();
        }
        match (to_confirm, j.held.remove(&tile)) {
            (Some(required), None) => {
                j.held.insert(tile, (machine, required));
                expect.hold = Some((worker, job, tile));
                self.stats.holds += 1;
                self.stats.holds_required += usize::from(required);
                return false;
            }
            (_, Some(_)) => self.stats.confirmed += 1,
            (None, None) => {}
        }
        j.accepted.insert(tile);
        let took = self.clock - held.started;
        j.measured += 1;
        j.total_time += took;
        j.slowest = j.slowest.max(took);
        expect.accept = Some((job, tile));
        self.stats.accepted_late += usize::from(held.expired);
        if j.accepted.len() == j.tiles as usize {
            j.fate = Fate::Done;
            expect.done.insert(job);
            expect.ended.insert(job);
        }
        // The job's first measured tile: the leases given under the initial lease end
        // no later than their start plus the lease now measured.
        if j.measured == 1 {
            let length = j.lease_length(&self.policy);
            for w in self.workers.values_mut() {
                for (_, held) in w.holding.iter_mut().filter(|((j, _), _)| *j == job) {
                    if !held.expired {
                        held.deadline = held.deadline.min(held.started + length);
                    }
                }
            }
        }
        false
    }

    /// The machine gets nothing more: its workers drain and give back what they hold
    /// (no loss counted), its held results are dropped, and the revoked tiles of active
    /// jobs that were accepted are not any more; their copies still out are held again
    /// under leases that ran out.
    fn quarantine(&mut self, machine: Machine, revoke: &[(JobId, u32)]) {
        self.quarantined.insert(machine.clone());
        self.stats.quarantines += 1;
        let mut live = false;
        for w in self.workers.values_mut().filter(|w| w.machine == machine) {
            live = true;
            w.draining = true;
            w.holding.clear();
        }
        self.stats.quarantined_live += usize::from(live);
        self.end_stalls_without_workers();
        for j in self.jobs.values_mut().filter(|j| j.fate == Fate::Active) {
            let before = j.held.len();
            j.held.retain(|_, (m, _)| *m != machine);
            self.stats.holds_dropped += before - j.held.len();
        }
        let clock = self.clock;
        for &(job, tile) in revoke {
            let Some(j) = self.jobs.get_mut(&job) else {
                continue;
            };
            if j.fate != Fate::Active || !j.accepted.remove(&tile) {
                continue;
            }
            self.stats.revoked += 1;
            let mut copies = false;
            for w in self.workers.values_mut() {
                if let Some(held) = w.holding.get_mut(&(job, tile)) {
                    *held = Held {
                        started: clock,
                        deadline: clock,
                        expired: true,
                    };
                    copies = true;
                }
            }
            self.stats.revoked_with_copies += usize::from(copies);
        }
    }

    /// At a timeout, after the drops and the leases: the optional confirmations of
    /// tiles without a live lease that no ready machine but their own may give (each is
    /// blocked from the job or failed the tile) are given up, their results accepted.
    fn give_up_confirmations(&mut self, expect: &mut Expect) {
        let ready = self.ready();
        let holders = self.holders();
        for (&id, j) in self.jobs.iter_mut().filter(|(_, j)| j.fate == Fate::Active) {
            let given_up: Vec<u32> = j
                .held
                .iter()
                .filter(|&(&t, (from, required))| {
                    !required
                        && Self::live_holders(&holders, id, t).is_empty()
                        && !ready
                            .iter()
                            .any(|m| m != from && !j.blocked.contains(m) && !j.failed_on(t, m))
                })
                .map(|(&t, _)| t)
                .collect();
            for tile in given_up {
                j.held.remove(&tile);
                j.accepted.insert(tile);
                expect.given_up.insert((id, tile));
                self.stats.given_up += 1;
            }
            if j.accepted.len() == j.tiles as usize {
                j.fate = Fate::Done;
                expect.done.insert(id);
                expect.ended.insert(id);
                self.stats.done_by_giving_up += 1;
            }
        }
    }

    /// When the scheduler must be called next, by the rule its doc states, computed
    /// from the model.
    fn expected_deadline(&self) -> Option<Millis> {
        let last = self.last?;
        let mut times = Vec::new();
        let mut live_lease = false;
        for w in self.workers.values() {
            times.push(w.last_seen + self.policy.heartbeat_timeout + 1);
            for (&(job, tile), held) in &w.holding {
                let j = &self.jobs[&job];
                if !held.expired && j.fate == Fate::Active && !j.accepted.contains(&tile) {
                    times.push(held.deadline);
                    live_lease = true;
                }
            }
        }
        for j in self.jobs.values().filter(|j| j.fate == Fate::Active) {
            if let Some(since) = j.stalled_since {
                times.push(since + self.policy.stall_timeout);
            }
        }
        if !self.workers.is_empty() || live_lease {
            times.push(self.last_timeout + wake(&self.policy));
        }
        let at = times.into_iter().min()?;
        Some(last + at.saturating_sub(self.clock))
    }

    /// Applies one event to the scheduler at the daemon's time `now`, replays its
    /// actions and checks every invariant. Returns the actions.
    fn step(&mut self, event: Event) -> Vec<Action> {
        self.step_at(self.now, event)
    }

    /// The same at a time of the daemon's clock that may be earlier than the last (the
    /// scheduler takes it as the last).
    fn step_at(&mut self, now: Millis, event: Event) -> Vec<Action> {
        // The scheduler's clock: the gaps between events, but a gap beyond the pause
        // threshold counts as one wake interval.
        match self.last {
            None => {
                self.clock = self.clock.max(now);
                self.last_timeout = self.clock;
            }
            Some(last) => {
                let gap = now.max(last) - last;
                if gap > self.policy.pause_threshold {
                    self.clock += wake(&self.policy);
                    self.stats.pauses += 1;
                } else {
                    self.clock += gap;
                }
            }
        }
        let now = self.last.map_or(now, |last| now.max(last));
        self.last = Some(now);
        self.now = self.now.max(now);
        if self.storage_down {
            self.stats.while_storage_down += 1;
        }

        let mut expect = Expect::default();
        // Any message from a worker shows it alive.
        if let Event::Heartbeat { worker }
        | Event::WorkerDraining { worker }
        | Event::TileDone { worker, .. }
        | Event::TileToConfirm { worker, .. }
        | Event::TileFailed { worker, .. } = event
        {
            if let Some(w) = self.workers.get_mut(&worker) {
                w.last_seen = self.clock;
            }
        }
        match event {
            Event::PauseJob { .. }
            | Event::ResumeJob { .. }
            | Event::SetPriority { .. }
            | Event::DisableMachine { .. }
            | Event::EnableMachine { .. }
            | Event::RequeueTiles { .. }
            | Event::RequireTags { .. }
            | Event::WorkerTags { .. }
            | Event::Interactive { .. }
            | Event::Continue => {
                unreachable!(
                    "no operator control nor continuation is generated here: the unit tests \
                     cover them"
                )
            }
            Event::Timeout => {
                self.last_timeout = self.clock;
                let (clock, timeout) = (self.clock, self.policy.heartbeat_timeout);
                expect.drops = self
                    .workers
                    .iter()
                    .filter(|(_, w)| clock - w.last_seen > timeout)
                    .map(|(&id, _)| id)
                    .collect();
                // The scheduler drops them in id order, each tile lost one at a time.
                for &worker in &expect.drops.clone() {
                    let w = self.remove_worker(worker, &mut expect).expect("live");
                    self.dropping.insert(worker, w);
                }
                // Leases run out at their deadline.
                let jobs = &self.jobs;
                for w in self.workers.values_mut() {
                    for (&(job, tile), held) in &mut w.holding {
                        if !held.expired
                            && held.deadline <= clock
                            && !jobs[&job].accepted.contains(&tile)
                        {
                            held.expired = true;
                        }
                    }
                }
                self.give_up_confirmations(&mut expect);
                self.check_stalls(&mut expect);
            }
            Event::WorkerJoined {
                worker,
                threads,
                ref machine,
            } => {
                assert!(!self.workers.contains_key(&worker), "worker ids are fresh");
                self.next_worker = self.next_worker.max(worker + 1);
                if let Some(name) = machine {
                    if !self.names.insert(name.clone()) {
                        self.stats.rejoined_under_a_name += 1;
                    }
                }
                let machine = Machine::of(worker, machine.as_deref());
                // A quarantined machine's worker is connected, never given a tile.
                let quarantined = self.quarantined.contains(&machine);
                self.stats.joined_quarantined += usize::from(quarantined);
                self.workers.insert(
                    worker,
                    ModelWorker {
                        machine,
                        threads,
                        credit: 2 * threads.max(1) as usize,
                        allowance: 0,
                        draining: quarantined,
                        holding: BTreeMap::new(),
                        scenes: BTreeSet::new(),
                        last_seen: self.clock,
                        silent: false,
                    },
                );
            }
            Event::Heartbeat { .. } => {}
            Event::WorkerLeft { worker } => {
                self.remove_worker(worker, &mut expect);
            }
            Event::WorkerDraining { worker } => {
                if let Some(w) = self.workers.get_mut(&worker) {
                    w.draining = true;
                }
                self.end_stalls_without_workers();
            }
            Event::JobSubmitted {
                job,
                priority,
                scene,
                tiles,
            } => {
                assert!(!self.jobs.contains_key(&job), "job ids are fresh");
                self.next_job = self.next_job.max(job + 1);
                let fate = if tiles == 0 {
                    expect.done.insert(job);
                    expect.ended.insert(job);
                    Fate::Done
                } else {
                    Fate::Active
                };
                self.jobs.insert(
                    job,
                    ModelJob {
                        priority,
                        scene,
                        tiles,
                        accepted: BTreeSet::new(),
                        fate,
                        why: None,
                        attempts: BTreeMap::new(),
                        failed_on: BTreeSet::new(),
                        machine_failures: BTreeMap::new(),
                        blocked: BTreeSet::new(),
                        losses: BTreeMap::new(),
                        stalled_since: None,
                        measured: 0,
                        total_time: 0,
                        slowest: 0,
                        held: BTreeMap::new(),
                    },
                );
            }
            Event::TileDone { worker, job, tile } => {
                if self.result(worker, job, tile, None, &mut expect) {
                    // The scheduler fills everyone when a tile went back to the queue.
                    self.unfilled = false;
                }
            }
            Event::TileToConfirm {
                worker,
                job,
                tile,
                required,
            } => {
                self.result(worker, job, tile, Some(required), &mut expect);
            }
            Event::Quarantine {
                ref machine,
                ref revoke,
            } => self.quarantine(Machine::Named(machine.clone()), revoke),
            Event::WorkerPace { worker, rtt, tile } => {
                let cap = self.policy.max_credit_per_thread.max(2) as usize;
                if let Some(w) = self.workers.get_mut(&worker) {
                    // As the doc states it, in u128 where nothing overflows.
                    let threads = u128::from(w.threads.max(1));
                    let span = u128::from(rtt) + u128::from(rtt / 2);
                    let cover = span.div_ceil(u128::from(tile.max(1)));
                    let uncapped = threads * (2 + cover);
                    let credit = uncapped.min(threads * cap as u128) as usize;
                    self.stats.paces += 1;
                    self.stats.credit_raised += usize::from(credit > w.credit);
                    self.stats.credit_capped += usize::from(uncapped > threads * cap as u128);
                    if credit < w.holding.len() {
                        self.stats.credit_lowered_below_holding += 1;
                    }
                    w.allowance = w.holding.len();
                    w.credit = credit;
                }
            }
            Event::TileFailed {
                worker,
                job,
                tile,
                ref message,
            } => {
                let held = self
                    .workers
                    .get_mut(&worker)
                    .and_then(|w| w.holding.remove(&(job, tile)));
                // A copy of a tile already accepted: the worker is rid of it, and
                // nothing else changes.
                if held.is_some() {
                    self.count_failure(worker, job, tile, message, &mut expect);
                }
            }
            Event::CancelJob { job } => {
                if self.active(job) {
                    self.jobs.get_mut(&job).expect("active").fate = Fate::Cancelled;
                    expect.ended.insert(job);
                }
            }
            Event::StorageUnavailable => self.storage_down = true,
            Event::StorageAvailable => self.storage_down = false,
        }
        // These events end by filling every worker.
        if matches!(
            event,
            Event::Timeout
                | Event::TileToConfirm { .. }
                | Event::Quarantine { .. }
                | Event::WorkerLeft { .. }
                | Event::JobSubmitted { .. }
                | Event::TileFailed { .. }
                | Event::CancelJob { .. }
                | Event::StorageAvailable
        ) {
            self.unfilled = false;
        }

        let actions = self.scheduler.handle(now, event.clone());
        if let Some(twin) = &mut self.reference {
            twin.check(&self.scheduler, now, &event, &actions);
        }
        let context = || format!("after {event:?} at {now}\nactions: {actions:?}");

        let mut forgotten = Vec::new();
        let mut dropped = BTreeSet::new();
        for (i, action) in actions.iter().enumerate() {
            match *action {
                Action::SendScene { worker, job } => {
                    assert!(self.active(job), "scene of an ended job {}", context());
                    let scene = self.jobs[&job].scene;
                    let w = self
                        .workers
                        .get_mut(&worker)
                        .unwrap_or_else(|| panic!("SendScene to a gone worker {}", context()));
                    assert!(w.scenes.insert(scene), "scene re-sent {}", context());
                    let next = actions.get(i + 1);
                    assert!(
                        matches!(next, Some(&Action::Assign { worker: to, job: of, .. })
                            if to == worker && of == job),
                        "a scene is sent for the tile that follows {}",
                        context()
                    );
                }
                Action::Assign { worker, job, tile } => {
                    self.assign(worker, job, tile, &context);
                }
                Action::AcceptTile { job, tile } => {
                    assert_eq!(expect.accept, Some((job, tile)), "{}", context());
                    assert!(!expect.accepted, "accepted twice {}", context());
                    expect.accepted = true;
                    if let Event::TileDone { worker, .. } | Event::TileToConfirm { worker, .. } =
                        event
                    {
                        *self.rendered_by.entry(worker).or_default() += 1;
                    }
                }
                Action::DuplicateResult { job, tile } => {
                    assert_eq!(expect.duplicate, Some((job, tile)), "{}", context());
                    assert!(!expect.duplicated, "two duplicates {}", context());
                    expect.duplicated = true;
                    self.stats.duplicate_results += 1;
                }
                Action::HoldResult { worker, job, tile } => {
                    assert_eq!(expect.hold, Some((worker, job, tile)), "{}", context());
                    assert!(!expect.held, "held twice {}", context());
                    expect.held = true;
                }
                Action::AcceptHeld { job, tile } => {
                    assert!(
                        expect.given_up.remove(&(job, tile)),
                        "a held result accepted without confirmation while a machine may \
                         confirm it {}",
                        context()
                    );
                }
                Action::CancelOnWorker { worker, job } => {
                    assert!(
                        expect.ended.contains(&job),
                        "cancel of a job not ending {}",
                        context()
                    );
                    let w = match self.workers.get_mut(&worker) {
                        Some(w) => w,
                        None => self
                            .dropping
                            .get_mut(&worker)
                            .unwrap_or_else(|| panic!("cancel to a gone worker {}", context())),
                    };
                    let before = w.holding.len();
                    w.holding.retain(|&(j, _), _| j != job);
                    assert!(
                        w.holding.len() < before,
                        "cancel to a worker holding none of the job's tiles {}",
                        context()
                    );
                    if matches!(event, Event::TileDone { .. }) {
                        self.unfilled = true;
                        self.stats.cancels_at_completion += 1;
                    }
                }
                Action::ForgetScene { worker, scene } => {
                    let w = match self.workers.get_mut(&worker) {
                        Some(w) => w,
                        None => self.dropping.get_mut(&worker).unwrap_or_else(|| {
                            panic!("ForgetScene to a gone worker {}", context())
                        }),
                    };
                    assert!(
                        w.scenes.remove(&scene),
                        "forgot an unknown scene {}",
                        context()
                    );
                    forgotten.push(scene);
                }
                Action::WorkerUnresponsive { .. } | Action::WorkerResponsive { .. } => {
                    panic!(
                        "the model's histories turn the progress check off {}",
                        context()
                    )
                }
                Action::DropWorker { worker } => {
                    assert!(
                        expect.drops.contains(&worker),
                        "dropped a worker heard from in time {}",
                        context()
                    );
                    assert!(dropped.insert(worker), "dropped twice {}", context());
                    self.dropping.remove(&worker);
                    self.stats.dropped += 1;
                }
                Action::JobDone { job } => {
                    assert!(expect.done.remove(&job), "unexpected JobDone {}", context());
                    assert!(
                        self.jobs[&job].held.is_empty(),
                        "a job done with a result held for confirmation {}",
                        context()
                    );
                    self.stats.jobs_done += 1;
                }
                Action::JobFailed { job, ref message } => {
                    let failure = expect
                        .failed
                        .remove(&job)
                        .unwrap_or_else(|| panic!("unexpected JobFailed {}", context()));
                    check_failure(message, &failure, &context);
                    self.stats.jobs_failed += 1;
                    match failure {
                        Failure::Attempts { .. } => self.stats.failed_by_attempts += 1,
                        Failure::Losses { .. } => self.stats.failed_by_losses += 1,
                        Failure::Stall { .. } => self.stats.failed_by_stall += 1,
                    }
                }
            }
        }

        assert_eq!(
            expect.accept.is_some(),
            expect.accepted,
            "a holder's first result is accepted, nothing else {}",
            context()
        );
        assert_eq!(
            expect.duplicate.is_some(),
            expect.duplicated,
            "a holder's copy of an accepted tile is a duplicate, nothing else {}",
            context()
        );
        assert_eq!(
            expect.hold.is_some(),
            expect.held,
            "a holder's result to confirm is held, nothing else {}",
            context()
        );
        assert!(
            expect.given_up.is_empty(),
            "optional confirmations no ready machine may give, not given up: {:?} {}",
            expect.given_up,
            context()
        );
        assert_eq!(dropped, expect.drops, "silent workers {}", context());
        assert!(expect.done.is_empty(), "JobDone missing {}", context());
        assert!(
            expect.failed.is_empty(),
            "JobFailed missing for {:?} {}",
            expect.failed.keys().collect::<Vec<_>>(),
            context()
        );

        self.check_state(&forgotten, &context);
        actions
    }

    /// Checks an `Assign` against the state before it, then records it.
    fn assign(&mut self, worker: WorkerId, job: JobId, tile: u32, context: &dyn Fn() -> String) {
        assert!(
            !self.storage_down,
            "assigned while storage is down {}",
            context()
        );
        assert!(self.active(job), "tile of an ended job {}", context());
        let j = &self.jobs[&job];
        assert!(tile < j.tiles, "no such tile {}", context());
        assert!(
            !j.accepted.contains(&tile),
            "accepted tile again {}",
            context()
        );
        let w = self
            .workers
            .get(&worker)
            .unwrap_or_else(|| panic!("Assign to a gone worker {}", context()));
        assert!(!w.draining, "draining worker assigned {}", context());
        assert!(
            !self.quarantined.contains(&w.machine),
            "a quarantined machine got a tile {}",
            context()
        );
        assert!(
            !j.held_from(tile, &w.machine),
            "a tile went to the machine whose result it holds {}",
            context()
        );
        assert!(
            w.scenes.contains(&j.scene),
            "tile before scene {}",
            context()
        );
        assert!(
            !w.holding.contains_key(&(job, tile)),
            "assigned a tile the worker holds {}",
            context()
        );
        assert!(
            !j.blocked.contains(&w.machine),
            "a blocked machine got a tile of the job {}",
            context()
        );
        let holders = self.holders();
        let live = Self::live_holders(&holders, job, tile);
        if live.is_empty() {
            assert!(
                !j.failed_on(tile, &w.machine),
                "re-assigned to a machine it failed on {}",
                context()
            );
            assert_eq!(
                self.next_by_policy(&holders, worker),
                Some(job),
                "priority, fair share, age {}",
                context()
            );
        } else {
            assert!(self.policy.speculate, "double assignment {}", context());
            assert!(
                !self.strict || !j.failed_on(tile, &w.machine),
                "duplicated to a machine it failed on {}",
                context()
            );
            assert_eq!(
                self.next_by_policy(&holders, worker),
                None,
                "duplicate while a tile waits for the worker {}",
                context()
            );
            assert!(
                self.waiting(&holders, job).is_empty(),
                "duplicate of a job with tiles waiting {}",
                context()
            );
            assert_eq!(live.len(), 1, "a third live holder {}", context());
            assert_eq!(
                self.straggler_for(&holders, worker),
                Some((job, tile)),
                "the straggler out longest of the first job {}",
                context()
            );
            self.stats.duplicates_assigned += 1;
        }
        if holders
            .get(&(job, tile))
            .is_some_and(|hs| hs.iter().any(|(_, h)| h.expired))
        {
            self.stats.reassigned_after_expiry += 1;
        }
        let deadline = self.clock + j.lease_length(&self.policy);
        let w = self.workers.get_mut(&worker).expect("checked above");
        w.holding.insert(
            (job, tile),
            Held {
                started: self.clock,
                deadline,
                expired: false,
            },
        );
        assert!(w.holding.len() <= w.credit, "over credit {}", context());
    }

    /// Invariants of the state between events.
    fn check_state(&self, forgotten: &[SceneHash], context: &dyn Fn() -> String) {
        let in_use: BTreeSet<SceneHash> = self
            .jobs
            .values()
            .filter(|j| j.fate == Fate::Active)
            .map(|j| j.scene)
            .collect();
        for scene in forgotten {
            assert!(
                !in_use.contains(scene),
                "forgot a scene in use {}",
                context()
            );
        }

        let mut total = 0;
        for (&id, w) in &self.workers {
            assert_eq!(
                self.scheduler.held_by(id),
                w.holding.len(),
                "held by worker {id} {}",
                context()
            );
            total += w.holding.len();
            assert!(
                w.holding.len() <= w.credit.max(w.allowance),
                "over credit {}",
                context()
            );
            let threads = w.threads.max(1) as usize;
            let cap = self.policy.max_credit_per_thread.max(2) as usize;
            assert!(
                2 * threads <= w.credit && w.credit <= threads * cap,
                "worker {id} credit {} out of [2, max_credit_per_thread] per thread {}",
                w.credit,
                context()
            );
            if self.quarantined.contains(&w.machine) {
                assert!(
                    w.draining && w.holding.is_empty(),
                    "a quarantined worker holds tiles {}",
                    context()
                );
            }
            for &(job, _) in w.holding.keys() {
                assert!(
                    self.active(job),
                    "worker {id} holds a tile of an ended job {}",
                    context()
                );
            }
            assert!(
                w.scenes.is_subset(&in_use),
                "worker {id} keeps a scene no active job uses {}",
                context()
            );
        }
        assert_eq!(self.scheduler.tiles_in_flight(), total, "{}", context());

        let holders = self.holders();
        let max_live = if self.policy.speculate { 2 } else { 1 };
        for (&(job, tile), hs) in &holders {
            let live = hs.iter().filter(|(_, h)| !h.expired).count();
            assert!(
                live <= max_live,
                "tile {tile} of job {job} has {live} live holders {}",
                context()
            );
        }

        for (&id, j) in &self.jobs {
            let active = j.fate == Fate::Active;
            assert_eq!(
                self.scheduler.is_active(id),
                active,
                "job {id} {}",
                context()
            );
            if j.fate == Fate::Done {
                assert!(
                    j.held.is_empty(),
                    "job {id} done with a held result {}",
                    context()
                );
            }
            if active {
                assert!(
                    j.accepted.len() < j.tiles as usize,
                    "job {id} complete without JobDone {}",
                    context()
                );
                for (tile, (machine, _)) in &j.held {
                    assert!(
                        !j.accepted.contains(tile) && !self.quarantined.contains(machine),
                        "job {id} holds tile {tile} wrongly {}",
                        context()
                    );
                }
                assert_eq!(
                    self.scheduler.has_started(id),
                    self.waiting(&holders, id).len() < j.tiles as usize,
                    "job {id} {}",
                    context()
                );
            }
        }

        assert_eq!(
            self.scheduler.next_deadline(),
            self.expected_deadline(),
            "next deadline {}",
            context()
        );

        if !self.unfilled && !self.storage_down {
            for (&id, w) in &self.workers {
                if !w.draining && w.holding.len() < w.credit {
                    assert_eq!(
                        self.next_by_policy(&holders, id),
                        None,
                        "worker {id} idles next to a tile it may take {}",
                        context()
                    );
                }
            }
        }
    }

    /// Without a clock: one more worker that never leaves joins, and every worker
    /// returns every tile it holds, round after round. Every job must end, within
    /// `ceil(remaining tiles / 4) + 1` rounds (the new worker alone renders 4 tiles a
    /// round whenever any tile waits). Returns the number of rounds.
    fn run_to_completion(&mut self) -> usize {
        if self.storage_down {
            self.step(Event::StorageAvailable);
        }
        let (finisher, _) = self.join(2);
        let credit = self.workers[&finisher].credit;
        let remaining = self.remaining();
        let bound = remaining.div_ceil(credit) + 1;
        let mut rounds = 0;
        loop {
            let held: Vec<(WorkerId, JobId, u32)> = self
                .workers
                .iter()
                .flat_map(|(&w, mw)| mw.holding.keys().map(move |&(j, t)| (w, j, t)))
                .collect();
            if held.is_empty() {
                break;
            }
            rounds += 1;
            assert!(rounds <= bound, "{rounds} rounds for {remaining} tiles");
            for (worker, job, tile) in held {
                if self.holds(worker, job, tile) {
                    self.done(worker, job, tile);
                }
            }
        }
        self.check_liveness();
        rounds
    }

    /// With a clock: storage is available and a fresh worker joins that heartbeats
    /// and returns every tile it gets; the others fall silent; the clock moves a wake
    /// interval a round. The others are dropped within the heartbeat timeout, and then
    /// the finisher alone renders 4 tiles a round; it may take any tile (a machine of
    /// its own), so no job stalls: every job ends (done, or failed by the drops) within
    /// a bound.
    fn run_with_clock(&mut self) -> usize {
        let step = wake(&self.policy);
        if self.storage_down {
            self.step(Event::StorageAvailable);
        }
        let (finisher, _) = self.join(2);
        let credit = self.workers[&finisher].credit;
        let remaining = self.remaining();
        let bound =
            (self.policy.heartbeat_timeout / step) as usize + 2 + remaining.div_ceil(credit) + 1;
        let mut rounds = 0;
        while self.jobs.values().any(|j| j.fate == Fate::Active) {
            rounds += 1;
            assert!(rounds <= bound, "{rounds} rounds for {remaining} tiles");
            self.step(Event::Heartbeat { worker: finisher });
            for (job, tile) in self.held(finisher) {
                if self.holds(finisher, job, tile) {
                    self.done(finisher, job, tile);
                }
            }
            self.now += step;
            self.step(Event::Timeout);
        }
        self.check_liveness();
        rounds
    }

    /// The end of the liveness property: every job ended, and one whose tiles were
    /// only ever lost with their workers (never reported failed) is done unless a tile
    /// was lost `max_losses` times.
    fn check_liveness(&self) {
        for (id, j) in &self.jobs {
            assert_ne!(j.fate, Fate::Active, "job {id} never finished");
            // Without reported failures, only a required confirmation that no ready
            // machine may give stalls a job.
            let stalled_on_confirmation =
                j.why == Some(Why::Stall) && j.held.values().any(|&(_, required)| required);
            if j.attempts.is_empty() && j.fate == Fate::Failed && !stalled_on_confirmation {
                assert_eq!(j.why, Some(Why::Losses), "job {id}");
                assert!(
                    j.losses.values().any(|&n| n >= self.policy.max_losses),
                    "job {id} failed with {:?} losses",
                    j.losses
                );
            }
        }
    }

    /// Tiles of active jobs not yet accepted.
    fn remaining(&self) -> usize {
        self.jobs
            .values()
            .filter(|j| j.fate == Fate::Active)
            .map(|j| j.tiles as usize - j.accepted.len())
            .sum()
    }
}

/// Checks a `JobFailed` message against why the job had to fail.
fn check_failure(message: &str, failure: &Failure, context: &dyn Fn() -> String) {
    match failure {
        Failure::Attempts { tile, error } => {
            assert!(
                names_tile(message, *tile),
                "message does not name tile {tile} {}",
                context()
            );
            assert!(
                message.contains(error.as_str()),
                "message without the last error {}",
                context()
            );
        }
        Failure::Losses { tile, losses } => assert_eq!(
            message,
            format!(
                "tile {tile} was lost with its worker {losses} times (a tile that crashes \
                 workers, or workers that keep losing their connection)"
            ),
            "{}",
            context()
        ),
        Failure::Stall { tiles, machines } => {
            assert!(
                message.starts_with("no connected worker may render tile "),
                "{}",
                context()
            );
            assert!(
                tiles.iter().any(|&t| names_tile(message, t)),
                "message names no waiting tile of {tiles:?} {}",
                context()
            );
            if machines.len() <= 8 {
                for m in machines {
                    assert!(message.contains(m.as_str()), "{m} not named {}", context());
                }
            }
            assert!(!message.contains('\n'), "one line {}", context());
        }
    }
}

/// Whether the message names "tile {tile}" (and not a longer number).
fn names_tile(message: &str, tile: u32) -> bool {
    let needle = format!("tile {tile}");
    message
        .match_indices(&needle)
        .any(|(i, _)| !message[i + needle.len()..].starts_with(|c: char| c.is_ascii_digit()))
}

fn assigns(actions: &[Action]) -> Vec<(WorkerId, JobId, u32)> {
    actions
        .iter()
        .filter_map(|a| match *a {
            Action::Assign { worker, job, tile } => Some((worker, job, tile)),
            _ => None,
        })
        .collect()
}

fn job_done(actions: &[Action], job: JobId) -> bool {
    actions.contains(&Action::JobDone { job })
}

fn job_failed(actions: &[Action], job: JobId) -> Option<&str> {
    actions.iter().find_map(|a| match a {
        Action::JobFailed { job: j, message } if *j == job => Some(message.as_str()),
        _ => None,
    })
}

// ---------------------------------------------------------------------------------------
// Random histories.

/// A result or failure that is not the holder's own.
#[derive(Clone, Debug)]
enum Stray {
    /// Any (job, tile), also an unknown job or a tile past the end.
    Random { job: Index, tile: u32 },
    /// A tile already accepted, sent again.
    Duplicate(Index),
    /// A tile another worker holds.
    Stolen(Index),
    /// A tile a departed worker held, from that worker.
    Departed(Index),
    /// A tile whose result is held, from any worker (of the holding machine or not).
    Held(Index),
}

#[derive(Clone, Debug)]
enum Op {
    /// A worker joins, under one of [`NAMES`] or none.
    Join {
        threads: u32,
        name: Option<usize>,
    },
    /// A named worker's connection closes and it comes back at once under its name,
    /// with a new id: a service killed and restarted by its supervisor.
    Reconnect(Index),
    Leave(Index),
    Drain(Index),
    Submit {
        priority: i32,
        scene: usize,
        tiles: u32,
    },
    /// A worker returns a tile it holds.
    Return {
        worker: Index,
        tile: Index,
    },
    Stray {
        worker: Index,
        kind: Stray,
    },
    /// A worker fails a tile it holds; `worst`: the one with the most failures so far.
    Fail {
        worker: Index,
        tile: Index,
        worst: bool,
    },
    /// A worker reports a failure for a tile it does not hold.
    StrayFail {
        worker: Index,
        kind: Stray,
    },
    Cancel(Index),
    /// The clock moves on by this much (no more than the pause threshold), and the
    /// timer fires.
    Tick(Millis),
    /// A timeout at a time already past: the clock does not go back.
    StaleTick(Millis),
    Heartbeat(Index),
    /// Every worker not silent heartbeats.
    Pulse,
    /// A worker hangs: it sends nothing any more.
    Silence(Index),
    /// The coordinator stops for this long (beyond the pause threshold); when it runs
    /// again its timer fires before it reads anything.
    Pause(Millis),
    /// The network to a named worker is cut: it falls silent, and may rejoin.
    Cut(Index),
    /// A worker cut off connects again under its name (its old connection may not be
    /// dropped yet).
    Rejoin(Index),
    /// Storage becomes unavailable (true) or available again.
    Storage(bool),
    /// A worker returns a tile it holds as a result to be confirmed by another machine.
    Confirm {
        worker: Index,
        tile: Index,
        required: bool,
    },
    /// A worker returns a tile it holds whose result is held (from its own machine or
    /// another): a confirmation, or a copy that only frees its slot.
    ReturnHeld {
        worker: Index,
        confirm: Option<bool>,
    },
    /// A result to confirm that is not the holder's own (stale, stolen, of a held tile).
    StrayConfirm {
        worker: Index,
        kind: Stray,
        required: bool,
    },
    /// One of [`NAMES`] is quarantined (if `happens`: the rate is kept low, as a
    /// quarantine is for good), with these tiles revoked.
    Quarantine {
        happens: bool,
        name: usize,
        revoke: Vec<Revoke>,
    },
    /// The daemon measured a worker's round trip and tile time.
    Pace {
        worker: Index,
        rtt: Millis,
        tile: Millis,
    },
}

fn stray() -> impl Strategy<Value = Stray> {
    prop_oneof![
        (any::<Index>(), 0u32..40).prop_map(|(job, tile)| Stray::Random { job, tile }),
        any::<Index>().prop_map(Stray::Duplicate),
        any::<Index>().prop_map(Stray::Stolen),
        any::<Index>().prop_map(Stray::Departed),
        any::<Index>().prop_map(Stray::Held),
    ]
}

/// An entry of a quarantine's revoke list.
#[derive(Clone, Debug)]
enum Revoke {
    /// A tile accepted (of an active job or not).
    Accepted(Index),
    /// Any tile of a known job (mostly not done), or past its end.
    Any { job: Index, tile: u32 },
    /// A job that never existed.
    Unknown(u32),
}

fn revoke() -> impl Strategy<Value = Revoke> {
    prop_oneof![
        4 => any::<Index>().prop_map(Revoke::Accepted),
        2 => (any::<Index>(), 0u32..40).prop_map(|(job, tile)| Revoke::Any { job, tile }),
        1 => (0u32..40).prop_map(Revoke::Unknown),
    ]
}

/// Round trips and tile times of a `WorkerPace`: none, ordinary, and absurd.
fn pace() -> impl Strategy<Value = (Millis, Millis)> {
    let rtt = prop_oneof![
        2 => Just(0 as Millis),
        6 => 1..400 as Millis,
        1 => 1_000..100_000 as Millis,
        1 => Just(Millis::MAX),
    ];
    let tile = prop_oneof![
        2 => Just(0 as Millis),
        6 => 1..200 as Millis,
        1 => Just(Millis::MAX),
    ];
    (rtt, tile)
}

/// Operations of the issue-3 histories: no clock.
fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        3 => (1u32..=4, prop::option::weighted(0.6, 0..NAMES.len()))
            .prop_map(|(threads, name)| Op::Join { threads, name }),
        1 => any::<Index>().prop_map(Op::Reconnect),
        2 => any::<Index>().prop_map(Op::Leave),
        1 => any::<Index>().prop_map(Op::Drain),
        3 => (-1i32..=2, 0..SCENES.len(), 0u32..=30)
            .prop_map(|(priority, scene, tiles)| Op::Submit { priority, scene, tiles }),
        12 => (any::<Index>(), any::<Index>())
            .prop_map(|(worker, tile)| Op::Return { worker, tile }),
        3 => (any::<Index>(), stray()).prop_map(|(worker, kind)| Op::Stray { worker, kind }),
        3 => (any::<Index>(), any::<Index>(), any::<bool>())
            .prop_map(|(worker, tile, worst)| Op::Fail { worker, tile, worst }),
        1 => (any::<Index>(), stray()).prop_map(|(worker, kind)| Op::StrayFail { worker, kind }),
        1 => any::<Index>().prop_map(Op::Cancel),
        4 => (any::<Index>(), any::<Index>(), prop::bool::weighted(0.4))
            .prop_map(|(worker, tile, required)| Op::Confirm { worker, tile, required }),
        1 => (any::<Index>(), stray(), any::<bool>())
            .prop_map(|(worker, kind, required)| Op::StrayConfirm { worker, kind, required }),
        2 => (any::<Index>(), prop::option::weighted(0.3, any::<bool>()))
            .prop_map(|(worker, confirm)| Op::ReturnHeld { worker, confirm }),
        1 => (
            prop::bool::weighted(0.25),
            0..NAMES.len(),
            prop::collection::vec(revoke(), 0..6),
        )
            .prop_map(|(happens, name, revoke)| Op::Quarantine { happens, name, revoke }),
        1 => (any::<Index>(), pace()).prop_map(|(worker, (rtt, tile))| Op::Pace { worker, rtt, tile }),
    ]
}

/// Operations of the clocked histories: time, heartbeats, hangs, pauses, network cuts
/// and storage outages too. (Times fit the default pause threshold of 2 s.)
fn clocked_op() -> impl Strategy<Value = Op> {
    prop_oneof![
        25 => op(),
        6 => (0..=2_000 as Millis).prop_map(Op::Tick),
        1 => (0..3_000 as Millis).prop_map(Op::StaleTick),
        2 => any::<Index>().prop_map(Op::Heartbeat),
        4 => Just(Op::Pulse),
        1 => any::<Index>().prop_map(Op::Silence),
        1 => (2_001..12_000 as Millis).prop_map(Op::Pause),
        1 => any::<Index>().prop_map(Op::Cut),
        1 => any::<Index>().prop_map(Op::Rejoin),
        1 => any::<bool>().prop_map(Op::Storage),
    ]
}

fn pick<T: Copy>(items: &[T], index: &Index) -> Option<T> {
    (!items.is_empty()).then(|| items[index.index(items.len())])
}

fn pick_named(items: &[(WorkerId, String, u32)], index: &Index) -> Option<(WorkerId, String, u32)> {
    (!items.is_empty()).then(|| items[index.index(items.len())].clone())
}

impl Farm {
    /// Carries out an operation in the current state (if it means anything there).
    fn apply(&mut self, op: &Op) {
        match op {
            Op::Pulse => {
                for worker in self.talking() {
                    self.step(Event::Heartbeat { worker });
                }
            }
            Op::Silence(i) => {
                if let Some(worker) = pick(&self.talking(), i) {
                    self.workers.get_mut(&worker).expect("live").silent = true;
                }
            }
            Op::Reconnect(i) => {
                if let Some((worker, name, threads)) = pick_named(&self.named(false), i) {
                    self.step(Event::WorkerLeft { worker });
                    self.join_as(threads, Some(&name));
                }
            }
            Op::Cut(i) => {
                if let Some((worker, name, threads)) = pick_named(&self.named(true), i) {
                    self.workers.get_mut(&worker).expect("live").silent = true;
                    self.cut_off.push((name, threads));
                }
            }
            Op::Rejoin(i) => {
                if !self.cut_off.is_empty() {
                    let (name, threads) = self.cut_off.remove(i.index(self.cut_off.len()));
                    self.join_as(threads, Some(&name));
                }
            }
            &Op::Pause(gap) => {
                self.now += gap;
                self.step(Event::Timeout);
            }
            &Op::Tick(advance) => {
                self.now += advance;
                self.step(Event::Timeout);
            }
            &Op::StaleTick(back) => {
                self.step_at(self.now.saturating_sub(back), Event::Timeout);
            }
            _ => {
                if let Some(event) = self.event(op) {
                    self.step(event);
                }
            }
        }
    }

    /// Live named workers (only those still talking, if `talking`): id, name, threads.
    fn named(&self, talking: bool) -> Vec<(WorkerId, String, u32)> {
        self.workers
            .iter()
            .filter(|(_, w)| !(talking && w.silent))
            .filter_map(|(&id, w)| match &w.machine {
                Machine::Named(name) => Some((id, name.clone(), w.threads)),
                Machine::Connection(_) => None,
            })
            .collect()
    }

    /// Live workers that still send messages.
    fn talking(&self) -> Vec<WorkerId> {
        self.workers
            .iter()
            .filter(|(_, w)| !w.silent)
            .map(|(&id, _)| id)
            .collect()
    }

    fn stray(&self, worker: &Index, kind: &Stray) -> Option<(WorkerId, JobId, u32)> {
        let talking = self.talking();
        Some(match kind {
            Stray::Random { job, tile } => {
                // Known jobs and one that never existed.
                let ids: Vec<JobId> = (1..=self.next_job).collect();
                (pick(&talking, worker)?, pick(&ids, job)?, *tile)
            }
            Stray::Duplicate(i) => {
                let accepted: Vec<(JobId, u32)> = self
                    .jobs
                    .iter()
                    .flat_map(|(&j, mj)| mj.accepted.iter().map(move |&t| (j, t)))
                    .collect();
                let (job, tile) = pick(&accepted, i)?;
                (pick(&talking, worker)?, job, tile)
            }
            Stray::Stolen(i) => {
                let worker = pick(&talking, worker)?;
                let others: Vec<(JobId, u32)> = self
                    .workers
                    .iter()
                    .filter(|&(&id, _)| id != worker)
                    .flat_map(|(_, w)| w.holding.keys().copied())
                    .collect();
                let (job, tile) = pick(&others, i)?;
                (worker, job, tile)
            }
            Stray::Departed(i) => {
                let gone: Vec<(WorkerId, JobId, u32)> = self
                    .departed
                    .iter()
                    .flat_map(|(w, tiles)| tiles.iter().map(move |&(j, t)| (*w, j, t)))
                    .collect();
                pick(&gone, i)?
            }
            Stray::Held(i) => {
                let held: Vec<(JobId, u32)> = self
                    .jobs
                    .iter()
                    .flat_map(|(&j, mj)| mj.held.keys().map(move |&t| (j, t)))
                    .collect();
                let (job, tile) = pick(&held, i)?;
                (pick(&talking, worker)?, job, tile)
            }
        })
    }

    /// The revoke list of a quarantine.
    fn revoke_list(&self, revoke: &[Revoke]) -> Vec<(JobId, u32)> {
        let accepted: Vec<(JobId, u32)> = self
            .jobs
            .iter()
            .flat_map(|(&j, mj)| mj.accepted.iter().map(move |&t| (j, t)))
            .collect();
        let ids: Vec<JobId> = (1..self.next_job.max(2)).collect();
        revoke
            .iter()
            .filter_map(|r| match r {
                Revoke::Accepted(i) => pick(&accepted, i),
                Revoke::Any { job, tile } => Some((pick(&ids, job)?, *tile)),
                &Revoke::Unknown(tile) => Some((self.next_job + 7, tile)),
            })
            .collect()
    }

    /// The event an operation stands for in the current state, if it has one.
    fn event(&self, op: &Op) -> Option<Event> {
        let live: Vec<WorkerId> = self.workers.keys().copied().collect();
        let busy: Vec<WorkerId> = self
            .talking()
            .into_iter()
            .filter(|w| !self.workers[w].holding.is_empty())
            .collect();
        Some(match op {
            &Op::Join { threads, name } => Event::WorkerJoined {
                worker: self.next_worker,
                threads,
                machine: name.map(|n| NAMES[n].to_string()),
            },
            Op::Leave(i) => Event::WorkerLeft {
                worker: pick(&live, i)?,
            },
            Op::Drain(i) => Event::WorkerDraining {
                worker: pick(&self.talking(), i)?,
            },
            &Op::Submit {
                priority,
                scene,
                tiles,
            } => Event::JobSubmitted {
                job: self.next_job,
                priority,
                scene: SCENES[scene],
                tiles,
            },
            Op::Return { worker, tile } => {
                let worker = pick(&busy, worker)?;
                let (job, tile) = pick(&self.held(worker), tile)?;
                Event::TileDone { worker, job, tile }
            }
            Op::Stray { worker, kind } => {
                let (worker, job, tile) = self.stray(worker, kind)?;
                Event::TileDone { worker, job, tile }
            }
            Op::Fail {
                worker,
                tile,
                worst,
            } => {
                let worker = pick(&busy, worker)?;
                // Leniently, no failure of a copy already accepted (the first known bug).
                let held: Vec<(JobId, u32)> = self
                    .held(worker)
                    .into_iter()
                    .filter(|(j, t)| self.strict || !self.jobs[j].accepted.contains(t))
                    .collect();
                let (job, tile) = if *worst {
                    held.iter()
                        .copied()
                        .max_by_key(|(j, t)| (self.jobs[j].attempts.get(t).copied(), Reverse(*t)))?
                } else {
                    pick(&held, tile)?
                };
                Event::TileFailed {
                    worker,
                    job,
                    tile,
                    message: format!("tile {tile} of job {job} failed on {worker}"),
                }
            }
            Op::StrayFail { worker, kind } => {
                let (worker, job, tile) = self.stray(worker, kind)?;
                let late_copy = self.holds(worker, job, tile)
                    && self
                        .jobs
                        .get(&job)
                        .is_some_and(|j| j.accepted.contains(&tile));
                if late_copy && !self.strict {
                    return None;
                }
                Event::TileFailed {
                    worker,
                    job,
                    tile,
                    message: "stray".into(),
                }
            }
            Op::Cancel(i) => {
                let ids: Vec<JobId> = (1..=self.next_job).collect();
                Event::CancelJob {
                    job: pick(&ids, i)?,
                }
            }
            Op::Heartbeat(i) => Event::Heartbeat {
                worker: pick(&self.talking(), i)?,
            },
            &Op::Storage(down) => {
                if down {
                    Event::StorageUnavailable
                } else {
                    Event::StorageAvailable
                }
            }
            Op::Confirm {
                worker,
                tile,
                required,
            } => {
                let worker = pick(&busy, worker)?;
                let (job, tile) = pick(&self.held(worker), tile)?;
                Event::TileToConfirm {
                    worker,
                    job,
                    tile,
                    required: *required,
                }
            }
            Op::ReturnHeld { worker, confirm } => {
                let copies: Vec<(WorkerId, JobId, u32)> = self
                    .workers
                    .iter()
                    .filter(|(_, w)| !w.silent)
                    .flat_map(|(&id, w)| w.holding.keys().map(move |&(j, t)| (id, j, t)))
                    .filter(|(_, j, t)| self.jobs[j].held.contains_key(t))
                    .collect();
                let (worker, job, tile) = pick(&copies, worker)?;
                match *confirm {
                    None => Event::TileDone { worker, job, tile },
                    Some(required) => Event::TileToConfirm {
                        worker,
                        job,
                        tile,
                        required,
                    },
                }
            }
            Op::StrayConfirm {
                worker,
                kind,
                required,
            } => {
                let (worker, job, tile) = self.stray(worker, kind)?;
                Event::TileToConfirm {
                    worker,
                    job,
                    tile,
                    required: *required,
                }
            }
            Op::Quarantine {
                happens,
                name,
                revoke,
            } => {
                if !happens {
                    return None;
                }
                Event::Quarantine {
                    machine: NAMES[*name].to_string(),
                    revoke: self.revoke_list(revoke),
                }
            }
            &Op::Pace {
                ref worker,
                rtt,
                tile,
            } => Event::WorkerPace {
                worker: pick(&live, worker)?,
                rtt,
                tile,
            },
            Op::Tick(_)
            | Op::StaleTick(_)
            | Op::Pulse
            | Op::Silence(_)
            | Op::Reconnect(_)
            | Op::Cut(_)
            | Op::Rejoin(_)
            | Op::Pause(_) => return None,
        })
    }
}

fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        cases,
        // Keep the tree clean: a failure prints its minimal history, which is enough.
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

/// A clocked history, then the clocked liveness phase.
fn clocked_history(ops: &[Op], strict: bool) -> Farm {
    let mut farm = Farm::with_policy(tight(clocked_policy()), strict);
    for op in ops {
        farm.apply(op);
    }
    farm.run_with_clock();
    farm
}

proptest! {
    #![proptest_config(config(1000))]

    /// Issue 3: every invariant after every event of a random history without a clock
    /// or speculation (failures are retried, jobs fail only at `max_attempts` or
    /// `max_losses`; workers restart under their names), then every surviving job
    /// finishes once one steady worker joins and everyone returns their tiles.
    #[test]
    fn random_histories_keep_the_invariants_and_finish_every_job(
        ops in prop::collection::vec(op(), 0..150),
    ) {
        let mut farm = Farm::with_policy(tight(no_speculation()), true);
        for op in &ops {
            farm.apply(op);
        }
        farm.run_to_completion();
        for (_, j) in farm.jobs.iter().filter(|(_, j)| j.fate == Fate::Done) {
            prop_assert_eq!(j.accepted.len(), j.tiles as usize);
        }
    }

    /// Without failures, cancellations or departures, every job ends with `JobDone`
    /// even when all workers but the finisher drain.
    #[test]
    fn every_job_finishes_without_mishaps(
        jobs in prop::collection::vec((-1i32..=2, 0..SCENES.len(), 0u32..=30), 1..8),
        threads in prop::collection::vec(1u32..=4, 0..4),
        drain in any::<bool>(),
    ) {
        let mut farm = Farm::new();
        let workers: Vec<WorkerId> = threads.iter().map(|&t| farm.join(t).0).collect();
        for &(priority, scene, tiles) in &jobs {
            farm.submit(priority, SCENES[scene], tiles);
        }
        if drain {
            for worker in workers {
                farm.step(Event::WorkerDraining { worker });
            }
        }
        farm.run_to_completion();
        for (id, j) in &farm.jobs {
            prop_assert_eq!(j.fate, Fate::Done, "job {}", id);
        }
    }

}

proptest! {
    #![proptest_config(config(2000))]

    /// Issue 4 and 12: with the default policy (speculation on; a short stall
    /// timeout), random timeouts, heartbeats, hanging workers, restarts and network
    /// cuts with rejoins under the same name, coordinator pauses and storage outages,
    /// every invariant holds after every event, and the liveness property holds: every
    /// job ends once a healthy worker joins and the clock runs, and one whose tiles were
    /// only lost with workers ends done unless a tile reached `max_losses`.
    #[test]
    fn clocked_histories_keep_the_invariants_and_end_every_job(
        ops in prop::collection::vec(clocked_op(), 0..200),
    ) {
        clocked_history(&ops, true).check_liveness();
    }
}

/// The generators reach every case the properties are about: expired leases, late
/// results, duplicates, drops, blocked machines, workers back under their name,
/// coordinator pauses, storage outages, jobs failed for each reason; results held,
/// confirmed, given up and stalled on; quarantines (of machines with live workers,
/// revoking done tiles, dropping held results, machines back under their name);
/// credit raised, capped and lowered (fixed seed).
#[test]
fn the_histories_exercise_every_feature() {
    let mut runner = TestRunner::deterministic();
    let (mut plain, mut clocked) = (Stats::default(), Stats::default());
    for _ in 0..200 {
        let ops = prop::collection::vec(op(), 100..150)
            .new_tree(&mut runner)
            .expect("a history")
            .current();
        let mut farm = Farm::with_policy(tight(no_speculation()), true);
        for op in &ops {
            farm.apply(op);
        }
        farm.run_to_completion();
        plain.add(&farm.stats);

        let ops = prop::collection::vec(clocked_op(), 150..200)
            .new_tree(&mut runner)
            .expect("a history")
            .current();
        clocked.add(&clocked_history(&ops, true).stats);
    }
    println!("no clock: {plain:?}\nclocked: {clocked:?}");
    assert!(plain.blocked > 0 && plain.jobs_failed > 0 && plain.jobs_done > 0);
    assert!(plain.failed_by_attempts > 0 && plain.failed_by_losses > 0);
    assert!(plain.rejoined_under_a_name > 0);
    // Without a clock or speculation no two workers of a machine hold one tile, so no
    // copy comes from the machine whose result is held.
    assert!(plain.holds > 0 && plain.confirmed > 0);
    assert!(plain.quarantines > 0 && plain.revoked > 0 && plain.paces > 0);
    assert_eq!(plain.given_up, 0, "no timeout, nothing given up");
    assert_eq!(plain.duplicates_assigned + plain.dropped + plain.pauses, 0);
    let Stats {
        accepted_late,
        reassigned_after_expiry,
        duplicates_assigned,
        duplicate_results,
        cancels_at_completion,
        dropped,
        blocked,
        jobs_failed,
        jobs_done,
        failed_by_attempts,
        failed_by_losses,
        failed_by_stall,
        rejoined_under_a_name,
        pauses,
        while_storage_down,
        holds,
        holds_required,
        confirmed,
        unconfirming_copies,
        given_up,
        done_by_giving_up,
        stalled_on_confirmation,
        quarantines,
        quarantined_live,
        revoked,
        revoked_with_copies,
        holds_dropped,
        joined_quarantined,
        paces,
        credit_raised,
        credit_capped,
        credit_lowered_below_holding,
    } = clocked;
    for (what, count) in [
        ("accepted_late", accepted_late),
        ("reassigned_after_expiry", reassigned_after_expiry),
        ("duplicates_assigned", duplicates_assigned),
        ("duplicate_results", duplicate_results),
        ("cancels_at_completion", cancels_at_completion),
        ("dropped", dropped),
        ("blocked", blocked),
        ("jobs_failed", jobs_failed),
        ("jobs_done", jobs_done),
        ("failed_by_attempts", failed_by_attempts),
        ("failed_by_losses", failed_by_losses),
        ("failed_by_stall", failed_by_stall),
        ("rejoined_under_a_name", rejoined_under_a_name),
        ("pauses", pauses),
        ("while_storage_down", while_storage_down),
        ("holds", holds),
        ("holds_required", holds_required),
        ("confirmed", confirmed),
        ("unconfirming_copies", unconfirming_copies),
        ("given_up", given_up),
        ("done_by_giving_up", done_by_giving_up),
        ("stalled_on_confirmation", stalled_on_confirmation),
        ("quarantines", quarantines),
        ("quarantined_live", quarantined_live),
        ("revoked", revoked),
        ("revoked_with_copies", revoked_with_copies),
        ("holds_dropped", holds_dropped),
        ("joined_quarantined", joined_quarantined),
        ("paces", paces),
        ("credit_raised", credit_raised),
        ("credit_capped", credit_capped),
        ("credit_lowered_below_holding", credit_lowered_below_holding),
    ] {
        assert!(count > 0, "no {what} in the clocked histories");
    }
}

// ---------------------------------------------------------------------------------------
// Focused tests, issue 3 (no speculation, no clock).

#[test]
fn a_worker_pulls_by_credit() {
    let mut farm = Farm::new();
    let (job, _) = farm.submit(0, SCENE_A, 10);
    let (worker, joined) = farm.join(1);
    assert_eq!(
        joined,
        vec![
            Action::SendScene { worker, job },
            Action::Assign {
                worker,
                job,
                tile: 0
            },
            Action::Assign {
                worker,
                job,
                tile: 1
            },
        ]
    );
    // At its credit, a new job gives it nothing.
    let (other, submitted) = farm.submit(0, SCENE_B, 3);
    assert!(assigns(&submitted).is_empty());
    // One back, exactly one more: the other job, which has none in flight.
    let returned = farm.done(worker, job, 0);
    assert_eq!(assigns(&returned), vec![(worker, other, 0)]);
    assert_eq!(farm.scheduler.held_by(worker), 2);
}

#[test]
fn a_faster_worker_renders_more_tiles() {
    let mut farm = Farm::new();
    let (fast, _) = farm.join(1);
    let (slow, _) = farm.join(1);
    let (job, _) = farm.submit(0, SCENE_A, 300);
    // The fast worker returns a tile every tick, the slow one every fourth.
    let mut tick = 0;
    while farm.active(job) {
        tick += 1;
        for (worker, every) in [(fast, 1), (slow, 4)] {
            if tick % every == 0 {
                if let Some(&(job, tile)) = farm.held(worker).first() {
                    farm.done(worker, job, tile);
                }
            }
        }
    }
    let (f, s) = (farm.rendered_by[&fast], farm.rendered_by[&slow]);
    assert_eq!(f + s, 300);
    assert!(f >= 3 * s, "fast {f} tiles, slow {s}");
}

#[test]
fn higher_priority_tiles_go_first() {
    let mut farm = Farm::new();
    let (low, _) = farm.submit(0, SCENE_A, 6);
    let (high, _) = farm.submit(2, SCENE_B, 6);
    let (mid, _) = farm.submit(1, SCENE_A, 6);
    let (worker, joined) = farm.join(1);
    let mut order: Vec<JobId> = assigns(&joined).iter().map(|a| a.1).collect();
    while let Some(&(job, tile)) = farm.held(worker).first() {
        order.extend(assigns(&farm.done(worker, job, tile)).iter().map(|a| a.1));
    }
    let expected: Vec<JobId> = [[high; 6], [mid; 6], [low; 6]].concat();
    assert_eq!(order, expected);

    // A running low-priority job yields the next free slot to a new urgent one.
    let (background, _) = farm.submit(0, SCENE_A, 50);
    let (urgent, _) = farm.submit(1, SCENE_C, 1);
    let &(job, tile) = farm.held(worker).first().unwrap();
    assert_eq!(
        job, background,
        "the urgent job came while the worker was full"
    );
    assert_eq!(
        assigns(&farm.done(worker, job, tile)),
        vec![(worker, urgent, 0)]
    );
}

#[test]
fn a_small_job_is_not_starved_behind_a_big_one_of_equal_priority() {
    let mut farm = Farm::new();
    let (worker, _) = farm.join(2); // credit 4
    let (big, _) = farm.submit(0, SCENE_A, 100);
    let (small, _) = farm.submit(0, SCENE_A, 4);
    // The worker renders its tiles in the order it got them.
    let mut queue: VecDeque<(JobId, u32)> = farm.held(worker).into_iter().collect();
    let (mut small_done, mut big_done) = (None, None);
    let mut step = 0;
    while let Some((job, tile)) = queue.pop_front() {
        step += 1;
        let actions = farm.done(worker, job, tile);
        queue.extend(assigns(&actions).iter().map(|&(_, j, t)| (j, t)));
        if job_done(&actions, small) {
            small_done = Some(step);
        }
        if job_done(&actions, big) {
            big_done = Some(step);
        }
    }
    let (small_done, big_done) = (small_done.unwrap(), big_done.unwrap());
    // Alone it would take 4 returns; sharing evenly, about 8. Behind the big job, 104.
    assert!(small_done <= 12, "small job done after {small_done} tiles");
    assert_eq!(big_done, 104);
}

#[test]
fn equal_priorities_alternate_from_the_start() {
    let mut farm = Farm::new();
    let (big, _) = farm.submit(0, SCENE_A, 100);
    let (small, _) = farm.submit(0, SCENE_A, 4);
    let (worker, joined) = farm.join(2);
    assert_eq!(
        assigns(&joined),
        vec![
            (worker, big, 0),
            (worker, small, 0),
            (worker, big, 1),
            (worker, small, 1)
        ]
    );
}

#[test]
fn a_leaving_worker_s_tiles_go_to_another() {
    let mut farm = Farm::new();
    let (job, _) = farm.submit(0, SCENE_A, 4);
    let (first, _) = farm.join(1);
    let (second, _) = farm.join(2);
    assert_eq!(farm.held(first), vec![(job, 0), (job, 1)]);
    assert_eq!(farm.held(second), vec![(job, 2), (job, 3)]);
    let left = farm.step(Event::WorkerLeft { worker: first });
    // The second worker has the scene already and two free slots: no SendScene.
    assert_eq!(left.len(), 2, "{left:?}");
    let mut moved = assigns(&left);
    moved.sort_unstable();
    assert_eq!(moved, vec![(second, job, 0), (second, job, 1)]);
    // A late result from the departed worker is dropped.
    assert!(farm.done(first, job, 0).is_empty());
    let mut ended = false;
    for tile in 0..4 {
        ended |= job_done(&farm.done(second, job, tile), job);
    }
    assert!(ended);
    assert_eq!(farm.rendered_by.get(&first), None);
}

#[test]
fn a_worker_joining_mid_job_gets_tiles() {
    let mut farm = Farm::new();
    let (job, _) = farm.submit(0, SCENE_A, 10);
    let (first, _) = farm.join(1);
    farm.done(first, job, 0);
    assert!(farm.scheduler.has_started(job));
    let (second, joined) = farm.join(1);
    assert_eq!(
        joined,
        vec![
            Action::SendScene {
                worker: second,
                job
            },
            Action::Assign {
                worker: second,
                job,
                tile: 3
            },
            Action::Assign {
                worker: second,
                job,
                tile: 4
            },
        ]
    );
}

#[test]
fn a_scene_is_sent_once_per_worker_and_forgotten_with_its_last_job() {
    let mut farm = Farm::new();
    let mut history = Vec::new();
    let (w1, joined) = farm.join(1);
    history.push(joined);
    let (w2, joined) = farm.join(1);
    history.push(joined);
    let (short, submitted) = farm.submit(0, SCENE_A, 3);
    history.push(submitted);
    let (long, submitted) = farm.submit(0, SCENE_A, 9);
    history.push(submitted);
    while farm.active(short) || farm.active(long) {
        for worker in [w1, w2] {
            if let Some(&(job, tile)) = farm.held(worker).first() {
                history.push(farm.done(worker, job, tile));
            }
        }
    }
    for worker in [w1, w2] {
        // Both workers rendered tiles of both jobs, and got the scene once.
        assert!(farm.rendered_by[&worker] > 0);
        let sends = history
            .iter()
            .flatten()
            .filter(|a| matches!(a, Action::SendScene { worker: w, .. } if *w == worker))
            .count();
        assert_eq!(sends, 1, "worker {worker}");
        let forget = Action::ForgetScene {
            worker,
            scene: SCENE_A,
        };
        let forgets: Vec<usize> = history
            .iter()
            .enumerate()
            .filter(|(_, actions)| actions.contains(&forget))
            .map(|(i, _)| i)
            .collect();
        // Once, in the event that ended the last job using the scene, after its JobDone.
        assert_eq!(forgets.len(), 1, "worker {worker}");
        let actions = &history[forgets[0]];
        let done_at = actions
            .iter()
            .position(|a| *a == Action::JobDone { job: long });
        let forget_at = actions.iter().position(|a| *a == forget);
        assert!(done_at.is_some() && done_at < forget_at, "{actions:?}");
    }
    let short_done = history.iter().position(|a| job_done(a, short)).unwrap();
    assert!(!history[short_done]
        .iter()
        .any(|a| matches!(a, Action::ForgetScene { .. })));

    // A later job with the same scene sends it again, once per worker.
    let (again, submitted) = farm.submit(0, SCENE_A, 4);
    let sends: Vec<&Action> = submitted
        .iter()
        .filter(|a| matches!(a, Action::SendScene { .. }))
        .collect();
    assert_eq!(
        sends,
        vec![
            &Action::SendScene {
                worker: w1,
                job: again
            },
            &Action::SendScene {
                worker: w2,
                job: again
            },
        ]
    );
}

#[test]
fn cancelling_stops_assignments_and_tells_every_holder() {
    let mut farm = Farm::new();
    let (w1, _) = farm.join(1);
    let (w2, _) = farm.join(2);
    let (job, _) = farm.submit(0, SCENE_A, 20);
    let (other, _) = farm.submit(0, SCENE_B, 20);
    let cancelled = farm.step(Event::CancelJob { job });
    for worker in [w1, w2] {
        assert!(cancelled.contains(&Action::CancelOnWorker { worker, job }));
        assert!(cancelled.contains(&Action::ForgetScene {
            worker,
            scene: SCENE_A
        }));
    }
    // The freed slots go to the other job; results for the cancelled one are dropped.
    assert!(assigns(&cancelled).iter().all(|&(_, j, _)| j == other));
    assert!(farm
        .done(w1, job, 0)
        .iter()
        .all(|a| !matches!(a, Action::AcceptTile { .. })));
    farm.run_to_completion();
    assert_eq!(farm.jobs[&job].fate, Fate::Cancelled);
    assert_eq!(farm.jobs[&other].fate, Fate::Done);
}

#[test]
fn an_empty_job_is_done_at_once() {
    let mut farm = Farm::new();
    let (job, actions) = farm.submit(0, SCENE_A, 0);
    assert_eq!(actions, vec![Action::JobDone { job }]);
}

/// A failure report counts only from the holder. Job 1 (4 tiles); worker 1 (1 thread)
/// holds tiles 0 and 1, worker 2 (1 thread) tiles 2 and 3; worker 2 reports tile 0 as
/// failed: nothing happens.
#[test]
fn a_failure_from_a_worker_not_holding_the_tile_is_dropped() {
    let mut farm = Farm::new();
    let (job, _) = farm.submit(0, SCENE_A, 4);
    let (_, _) = farm.join(1);
    let (w2, _) = farm.join(1);
    let actions = farm.fail(w2, job, 0, "stale");
    assert!(actions.is_empty(), "{actions:?}");
    assert!(farm.scheduler.is_active(job));
    assert!(farm.jobs[&job].attempts.is_empty());
}

// ---------------------------------------------------------------------------------------
// Focused tests, issue 4.

/// A clocked farm with the default policy but no speculation, so that only leases
/// and heartbeats move tiles.
fn clocked_without_speculation() -> Farm {
    Farm::with_policy(no_speculation(), true)
}

#[test]
fn an_expired_lease_puts_the_tile_back_and_a_late_first_result_still_counts() {
    let lease = Policy::default().initial_lease;
    let mut farm = clocked_without_speculation();
    let (job, _) = farm.submit(0, SCENE_A, 2);
    let (slow, _) = farm.join(1);
    let (spare, joined) = farm.join(1);
    assert_eq!(farm.held(slow), vec![(job, 0), (job, 1)]);
    assert!(assigns(&joined).is_empty());
    // Both stay alive; nothing moves before the deadline.
    let mut now = 0;
    while now + 1_000 < lease {
        now += 1_000;
        assert!(farm.tick(now, &[slow, spare]).is_empty(), "at {now}");
    }
    assert!(farm.tick(lease - 1, &[slow, spare]).is_empty());
    // At the deadline both tiles go back, to the worker that has room.
    let mut expired = assigns(&farm.tick(lease, &[slow, spare]));
    expired.sort_unstable();
    assert_eq!(expired, vec![(spare, job, 0), (spare, job, 1)]);
    assert_eq!(farm.scheduler.held_by(slow), 2, "it may still deliver");
    // The slow worker's result comes first: accepted; the spare's copy is a duplicate.
    let late = farm.done(slow, job, 0);
    assert_eq!(late, vec![Action::AcceptTile { job, tile: 0 }]);
    let copy = farm.done(spare, job, 0);
    assert_eq!(copy, vec![Action::DuplicateResult { job, tile: 0 }]);
    // Tile 1 the other way round: the spare's result wins, the job is done, and the
    // slow worker is told to drop its copy.
    let first = farm.done(spare, job, 1);
    assert_eq!(
        first,
        vec![
            Action::AcceptTile { job, tile: 1 },
            Action::CancelOnWorker { worker: slow, job },
            Action::JobDone { job },
            Action::ForgetScene {
                worker: slow,
                scene: SCENE_A
            },
            Action::ForgetScene {
                worker: spare,
                scene: SCENE_A
            },
        ]
    );
    assert!(farm.done(slow, job, 1).is_empty());
}

#[test]
fn the_lease_follows_the_measured_tile_times() {
    let policy = Policy::default();
    // Fast tiles (100 ms): the lease is the minimum.
    let mut farm = clocked_without_speculation();
    let (job, _) = farm.submit(0, SCENE_A, 3);
    let (w1, _) = farm.join(1); // tiles 0 and 1 at 0 ms, with the initial lease
    farm.tick(100, &[w1]);
    let next = farm.done(w1, job, 0);
    assert_eq!(assigns(&next), vec![(w1, job, 2)]); // at 100 ms
    farm.done(w1, job, 1);
    let (w2, joined) = farm.join(1);
    assert!(assigns(&joined).is_empty());
    let deadline = 100 + policy.min_lease;
    assert!(farm.tick(deadline - 1, &[w1, w2]).is_empty());
    assert_eq!(
        assigns(&farm.tick(deadline, &[w1, w2])),
        vec![(w2, job, 2)],
        "a lease of min_lease after 100-ms tiles"
    );

    // Slow tiles: 2 s then 8 s.
    let mut farm = clocked_without_speculation();
    let (job, _) = farm.submit(0, SCENE_A, 4);
    let (w1, _) = farm.join(1); // tiles 0 and 1 at 0 ms
    farm.tick(1_000, &[w1]);
    farm.tick(2_000, &[w1]);
    // One tile of 2 s measured: max(3 * 2 s, 4 * 2 s, 1 s) = 8 s.
    assert_eq!(assigns(&farm.done(w1, job, 0)), vec![(w1, job, 2)]);
    for now in (3_000..=8_000).step_by(1_000) {
        farm.tick(now, &[w1]);
    }
    // Then 2 s and 8 s: max(3 * 8 s, 4 * 5 s, 1 s) = 24 s.
    assert_eq!(assigns(&farm.done(w1, job, 1)), vec![(w1, job, 3)]);
    let (w2, _) = farm.join(1);
    let mut moved = Vec::new();
    for now in (9_000..=40_000).step_by(500) {
        for (worker, job, tile) in assigns(&farm.tick(now, &[w1, w2])) {
            moved.push((now, worker, job, tile));
        }
    }
    assert_eq!(
        moved,
        vec![(2_000 + 8_000, w2, job, 2), (8_000 + 24_000, w2, job, 3)]
    );
}

#[test]
fn a_silent_worker_is_dropped_and_its_tiles_go_elsewhere() {
    let timeout = Policy::default().heartbeat_timeout;
    let mut farm = clocked_without_speculation();
    let (job, _) = farm.submit(0, SCENE_A, 4);
    let (silent, _) = farm.join(1); // tiles 0 and 1, last heard at 0 ms
    let (steady, _) = farm.join(1); // tiles 2 and 3
    let (spare, _) = farm.join(1); // nothing yet
    for now in (1_000..=timeout).step_by(1_000) {
        assert!(farm.tick(now, &[steady, spare]).is_empty(), "at {now}");
    }
    // Silent for exactly the timeout is not too long; a millisecond more is.
    let dropped = farm.tick(timeout + 1, &[steady, spare]);
    assert_eq!(
        dropped,
        vec![
            Action::DropWorker { worker: silent },
            Action::SendScene { worker: spare, job },
            Action::Assign {
                worker: spare,
                job,
                tile: 1
            },
            Action::Assign {
                worker: spare,
                job,
                tile: 0
            },
        ]
    );
    // Each tile counts one loss; nothing counts against the silent worker's machine.
    assert_eq!(farm.jobs[&job].losses, BTreeMap::from([(0, 1), (1, 1)]));
    assert!(farm.jobs[&job].attempts.is_empty() && farm.jobs[&job].blocked.is_empty());
    // The heartbeating worker keeps its tiles, however long it takes.
    for now in (6_000..=50_000).step_by(1_000) {
        assert!(farm.tick(now, &[steady, spare]).is_empty(), "at {now}");
    }
    assert_eq!(farm.held(steady), vec![(job, 2), (job, 3)]);
    let mut ended = false;
    for (worker, tile) in [(steady, 2), (steady, 3), (spare, 0), (spare, 1)] {
        ended |= job_done(&farm.done(worker, job, tile), job);
    }
    assert!(ended);
    assert!(
        farm.done(silent, job, 0).is_empty(),
        "dropped: nothing counts"
    );
}

#[test]
fn a_straggler_is_duplicated_to_an_idle_worker_and_the_first_result_wins() {
    let mut farm = Farm::with_policy(Policy::default(), true);
    let (job, _) = farm.submit(0, SCENE_A, 3);
    let (w1, _) = farm.join(1); // tiles 0 and 1 at 0 ms
    farm.tick(1_000, &[w1]);
    // The idle worker gets the waiting tile first, then a copy of the tile out longest
    // (both of w1's since 0 ms: the lower).
    let (w2, joined) = farm.join(1);
    assert_eq!(assigns(&joined), vec![(w2, job, 2), (w2, job, 0)]);
    // The copy comes back first and wins; w2, free again, copies the other straggler.
    assert_eq!(
        farm.done(w2, job, 0),
        vec![
            Action::AcceptTile { job, tile: 0 },
            Action::Assign {
                worker: w2,
                job,
                tile: 1
            },
        ]
    );
    // The original is a duplicate to compare; w1 copies w2's tile 2 in turn.
    assert_eq!(
        farm.done(w1, job, 0),
        vec![
            Action::DuplicateResult { job, tile: 0 },
            Action::Assign {
                worker: w1,
                job,
                tile: 2
            },
        ]
    );
    // Each tile now has two live holders: a new job waits for a free slot, and then
    // gets it rather than a copy.
    let (other, submitted) = farm.submit(0, SCENE_B, 4);
    assert!(assigns(&submitted).is_empty());
    let returned = farm.done(w2, job, 2);
    assert!(returned.contains(&Action::AcceptTile { job, tile: 2 }));
    assert_eq!(assigns(&returned), vec![(w2, other, 0)]);
    // The job ends with w1's result for tile 1: both copies still out are cancelled.
    let last = farm.done(w1, job, 1);
    assert!(last.contains(&Action::AcceptTile { job, tile: 1 }));
    for worker in [w1, w2] {
        assert!(last.contains(&Action::CancelOnWorker { worker, job }));
    }
    assert!(job_done(&last, job));
    assert_eq!(assigns(&last), vec![(w1, other, 1), (w1, other, 2)]);
    // Only the sender is filled then: w2's freed slot waits for the next tick.
    assert_eq!(farm.held(w2), vec![(other, 0)]);
    assert_eq!(assigns(&farm.tick(2_000, &[w1, w2])), vec![(w2, other, 3)]);
}

#[test]
fn a_poison_tile_fails_its_job_after_max_attempts_on_distinct_workers() {
    let max = Policy::default().max_attempts;
    let mut farm = Farm::new();
    let (job, _) = farm.submit(0, SCENE_A, 4);
    let (first, _) = farm.join(2); // all 4 tiles
    for tile in 0..3 {
        farm.done(first, job, tile);
    }
    let mut failed_on = vec![first];
    let mut actions = farm.fail(first, job, 3, "GPU fell over 1");
    for attempt in 2..=max {
        assert!(job_failed(&actions, job).is_none(), "{actions:?}");
        // Nobody it failed on gets it again, though they all have room.
        assert!(assigns(&actions).is_empty(), "{actions:?}");
        let (worker, joined) = farm.join(1);
        assert_eq!(assigns(&joined), vec![(worker, job, 3)]);
        failed_on.push(worker);
        actions = farm.fail(worker, job, 3, &format!("GPU fell over {attempt}"));
    }
    let message = job_failed(&actions, job).expect("failed at max_attempts");
    assert!(names_tile(message, 3), "{message}");
    assert!(
        message.contains(&format!("GPU fell over {max}")),
        "{message}"
    );
    assert!(!farm.scheduler.is_active(job));
    assert_eq!(failed_on.len() as u32, max);
}

#[test]
fn a_worker_failing_block_after_tiles_of_a_job_gets_none_of_it_but_others_jobs() {
    let policy = Policy::default();
    assert_eq!(policy.block_after, 2);
    let mut farm = Farm::new();
    let (job, _) = farm.submit(0, SCENE_A, 10);
    let (w, _) = farm.join(1); // tiles 0 and 1
    let once = farm.fail(w, job, 0, "oops");
    assert_eq!(
        assigns(&once),
        vec![(w, job, 2)],
        "one failure: not blocked"
    );
    let twice = farm.fail(w, job, 1, "oops");
    assert!(assigns(&twice).is_empty(), "blocked from the job");
    // It still renders the tile it holds, and gets another job's tiles.
    let (other, submitted) = farm.submit(0, SCENE_B, 10);
    assert_eq!(assigns(&submitted), vec![(w, other, 0)]);
    let returned = farm.done(w, job, 2);
    assert!(returned.contains(&Action::AcceptTile { job, tile: 2 }));
    assert_eq!(assigns(&returned), vec![(w, other, 1)]);
    // Another worker gets the failed tiles.
    let (helper, joined) = farm.join(1);
    assert_eq!(assigns(&joined), vec![(helper, job, 1), (helper, job, 0)]);
    for tile in 0..2 {
        assert_eq!(
            assigns(&farm.done(w, other, tile)),
            vec![(w, other, tile + 2)]
        );
    }
}

#[test]
fn a_worker_crashing_with_a_tile_counts_a_loss_not_an_attempt() {
    let policy = Policy::default();
    let mut farm = Farm::new();
    let (job, _) = farm.submit(0, SCENE_A, 1);
    // max - 1 failures reported, then crashes: the attempts stay one short.
    for attempt in 1..policy.max_attempts {
        let (w, _) = farm.join(1);
        assert!(job_failed(&farm.fail(w, job, 0, "bad"), job).is_none());
        assert_eq!(farm.jobs[&job].attempts[&0], attempt);
    }
    let (crash, joined) = farm.join(1);
    assert_eq!(assigns(&joined), vec![(crash, job, 0)]);
    let (next, _) = farm.join(1); // nothing waits: no tile
    let left = farm.step(Event::WorkerLeft { worker: crash });
    assert_eq!(assigns(&left), vec![(next, job, 0)]);
    assert_eq!(farm.jobs[&job].attempts[&0], policy.max_attempts - 1);
    assert_eq!(farm.jobs[&job].losses[&0], 1);
    // Crashes alone fail it only at max_losses.
    let mut holder = next;
    for loss in 2..policy.max_losses {
        let (spare, _) = farm.join(1);
        let left = farm.step(Event::WorkerLeft { worker: holder });
        assert!(job_failed(&left, job).is_none(), "loss {loss}");
        assert_eq!(assigns(&left), vec![(spare, job, 0)]);
        holder = spare;
    }
    let left = farm.step(Event::WorkerLeft { worker: holder });
    let message = job_failed(&left, job).expect("failed at max_losses");
    assert!(names_tile(message, 0), "{message}");
    assert!(
        message.contains("lost with its worker 8 times"),
        "{message}"
    );
}

// ---------------------------------------------------------------------------------------
// Focused tests, issue 12: lost connections, restarts under the same name, pauses,
// stalls and storage outages.

/// One and two workers, each killed while holding its tiles and restarted under its
/// name five times: never blocked, they get their tiles back, and the job is done.
#[test]
fn workers_killed_and_restarted_under_their_names_finish_the_job() {
    for workers in [1, 2] {
        let mut farm = Farm::with_policy(clocked_policy(), true);
        let (job, _) = farm.submit(0, SCENE_A, 20);
        let names = ["a", "b"];
        let mut ids: Vec<WorkerId> = names[..workers]
            .iter()
            .map(|name| farm.join_as(1, Some(name)).0)
            .collect();
        for _ in 0..5 {
            farm.now += 300;
            for (i, name) in names[..workers].iter().enumerate() {
                farm.step(Event::WorkerLeft { worker: ids[i] });
                let (id, back) = farm.join_as(1, Some(name));
                assert_eq!(assigns(&back).len(), 2, "{back:?}");
                ids[i] = id;
            }
        }
        assert!(farm.jobs[&job].blocked.is_empty());
        while farm.active(job) {
            farm.now += 500;
            for &worker in &ids {
                for (job, tile) in farm.held(worker) {
                    farm.done(worker, job, tile);
                }
            }
            farm.step(Event::Timeout);
        }
        assert_eq!(farm.jobs[&job].fate, Fate::Done, "{workers} workers");
    }
}

/// The coordinator stopped for 7 s, past the heartbeat timeout: its timer fires first
/// when it runs again, and nobody is dropped; the heartbeats waiting in the sockets
/// are read next. No lease runs out for the pause either.
#[test]
fn a_coordinator_paused_for_7_s_drops_nobody() {
    let mut farm = Farm::with_policy(
        Policy {
            initial_lease: 8_000,
            ..clocked_policy()
        },
        true,
    );
    let (job, _) = farm.submit(0, SCENE_A, 4);
    let (w1, _) = farm.join(1);
    let (w2, _) = farm.join(1);
    for now in [1_000, 2_000, 3_000] {
        assert!(farm.tick(now, &[w1, w2]).is_empty());
    }
    farm.now = 10_000;
    assert!(farm.step(Event::Timeout).is_empty());
    for worker in [w1, w2] {
        farm.step(Event::Heartbeat { worker });
    }
    assert_eq!(farm.scheduler.next_deadline(), Some(11_000));
    // 3 s before the pause, 1 s for it, 3 s after: 7 s of the 8-s leases.
    for now in (11_000..=13_000).step_by(1_000) {
        assert!(farm.tick(now, &[w1, w2]).is_empty(), "at {now}");
    }
    assert_eq!(farm.held(w1), vec![(job, 0), (job, 1)]);
    let counters = farm.scheduler.counters();
    assert_eq!((counters.workers_dropped, counters.leases_expired), (0, 0));
}

/// A worker cut off past the heartbeat timeout is dropped; its tiles go to another
/// machine meanwhile, and it rejoins under its name, unblocked, for the rest.
#[test]
fn a_worker_cut_off_rejoins_under_its_name_and_gets_tiles() {
    let mut farm = Farm::with_policy(
        Policy {
            speculate: false,
            ..clocked_policy()
        },
        true,
    );
    let (job, _) = farm.submit(0, SCENE_A, 8);
    let (far, _) = farm.join_as(1, Some("far"));
    let (near, _) = farm.join_as(1, Some("near"));
    let mut dropped = Vec::new();
    for now in (1_000..=8_000).step_by(1_000) {
        dropped.extend(farm.tick(now, &[near]));
    }
    assert_eq!(dropped, vec![Action::DropWorker { worker: far }]);
    assert_eq!(farm.jobs[&job].losses, BTreeMap::from([(0, 1), (1, 1)]));
    let (back, joined) = farm.join_as(1, Some("far"));
    assert_eq!(assigns(&joined), vec![(back, job, 1), (back, job, 0)]);
    let _ = near;
}

/// Every connected machine failed the job's last waiting tile: the job fails after
/// the stall timeout, naming the tile and the machines.
#[test]
fn a_job_no_connected_machine_may_take_fails_after_the_stall_timeout() {
    let policy = Policy {
        speculate: false,
        ..clocked_policy()
    };
    let mut farm = Farm::with_policy(policy, true);
    let (job, _) = farm.submit(0, SCENE_A, 1);
    let (a, _) = farm.join_as(1, Some("a"));
    farm.fail(a, job, 0, "out of memory");
    let (b, _) = farm.join_as(1, Some("b"));
    farm.fail(b, job, 0, "out of memory");
    let mut failed = None;
    for now in (1_000..=10_000).step_by(1_000) {
        let actions = farm.tick(now, &[a, b]);
        if let Some(message) = job_failed(&actions, job) {
            failed = Some((now, message.to_string()));
            break;
        }
    }
    assert_eq!(
        failed,
        Some((
            1_000 + policy.stall_timeout,
            "no connected worker may render tile 0: it failed on every one of them (a, b)"
                .to_string()
        ))
    );
}

/// While storage is unavailable nothing goes out, results still count; when it is back
/// every worker is filled.
#[test]
fn a_storage_outage_assigns_nothing_then_fills_everyone() {
    let mut farm = Farm::with_policy(clocked_policy(), true);
    let (job, _) = farm.submit(0, SCENE_A, 6);
    let (w1, _) = farm.join(1);
    assert!(farm.step(Event::StorageUnavailable).is_empty());
    assert_eq!(
        farm.done(w1, job, 0),
        vec![Action::AcceptTile { job, tile: 0 }]
    );
    let (w2, joined) = farm.join(1);
    assert!(joined.is_empty());
    assert!(assigns(&farm.tick(1_000, &[w1, w2])).is_empty());
    // Tile 1's lease ended at its start plus the lease measured with tile 0 (the least,
    // 1 s): it ran out at the tick and waits first.
    let back = farm.step(Event::StorageAvailable);
    assert_eq!(
        assigns(&back),
        vec![(w1, job, 2), (w2, job, 1), (w2, job, 3)]
    );
}

// ---------------------------------------------------------------------------------------
// Known bugs, shown on the bare scheduler.

/// The module doc: a failed tile "is retried on other workers". Straggler duplication
/// ignores that: `Job::straggler_for` does not look at the tile's failures.
/// Sequence (default policy): job 1 (1 tile); worker 1 (1 thread) gets tile 0; worker 2
/// (1 thread) gets a copy; worker 1 fails tile 0; the `TileFailed` returns
/// `Assign { worker: 1, job: 1, tile: 0 }` (worker 2 still holds it, so tile 0 is a
/// straggler for worker 1).
#[test]
fn a_tile_is_not_duplicated_to_a_worker_it_failed_on() {
    let mut s = Scheduler::new();
    s.handle(
        0,
        Event::JobSubmitted {
            job: 1,
            priority: 0,
            scene: SCENE_A,
            tiles: 1,
        },
    );
    s.handle(
        0,
        Event::WorkerJoined {
            worker: 1,
            threads: 1,
            machine: None,
        },
    );
    let joined = s.handle(
        0,
        Event::WorkerJoined {
            worker: 2,
            threads: 1,
            machine: None,
        },
    );
    assert_eq!(assigns(&joined), vec![(2, 1, 0)]);
    let failed = s.handle(
        0,
        Event::TileFailed {
            worker: 1,
            job: 1,
            tile: 0,
            message: "boom".into(),
        },
    );
    assert_eq!(assigns(&failed), vec![], "tile 0 failed on worker 1");
}

/// A worker holding a copy of a tile already accepted from another worker reports it
/// failed: `release` finds no lease (the tile left `in_flight` when accepted), so the
/// tile stays in the worker's `holding` and its slot is lost until the job ends.
/// Sequence (default policy): job 1 (2 tiles); worker 1 (1 thread) gets tiles 0 and 1;
/// worker 2 (1 thread) gets copies of both; worker 1 returns tile 0 (accepted); worker
/// 2 reports tile 0 failed; `held_by(2)` is still 2, and a new job's tile goes only to
/// worker 1.
#[test]
fn a_failed_late_copy_frees_the_worker_s_slot() {
    let mut s = Scheduler::new();
    s.handle(
        0,
        Event::JobSubmitted {
            job: 1,
            priority: 0,
            scene: SCENE_A,
            tiles: 2,
        },
    );
    s.handle(
        0,
        Event::WorkerJoined {
            worker: 1,
            threads: 1,
            machine: None,
        },
    );
    let joined = s.handle(
        0,
        Event::WorkerJoined {
            worker: 2,
            threads: 1,
            machine: None,
        },
    );
    assert_eq!(assigns(&joined), vec![(2, 1, 0), (2, 1, 1)]);
    let done = s.handle(
        0,
        Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        },
    );
    assert!(done.contains(&Action::AcceptTile { job: 1, tile: 0 }));
    s.handle(
        0,
        Event::TileFailed {
            worker: 2,
            job: 1,
            tile: 0,
            message: "out of memory".into(),
        },
    );
    assert_eq!(s.held_by(2), 1, "worker 2 renders only tile 1 now");
    let submitted = s.handle(
        0,
        Event::JobSubmitted {
            job: 2,
            priority: 0,
            scene: SCENE_A,
            tiles: 4,
        },
    );
    assert_eq!(assigns(&submitted), vec![(1, 2, 0), (2, 2, 1)]);
}

// ---------------------------------------------------------------------------------------
// The indexed scheduler against the reference.
//
// The scheduler keeps indexes (each tile's state next to the queue, the straggler
// candidates in the order they are chosen, the leases by deadline, the jobs in serving
// order, the workers by when they were last heard from and with free credit, the ready
// machines) so that no event walks every tile or every worker. They must change no
// decision: for the same events at the same times, the same actions in the same order
// as the plain scheduler of `reference/scheduler.rs` (which walks everything), and the
// same answers to every query, `next_deadline` included.

fn reference_policy(p: &Policy) -> reference::Policy {
    reference::Policy {
        heartbeat_timeout: p.heartbeat_timeout,
        initial_lease: p.initial_lease,
        min_lease: p.min_lease,
        lease_factor: p.lease_factor,
        max_attempts: p.max_attempts,
        block_after: p.block_after,
        speculate: p.speculate,
        max_losses: p.max_losses,
        stall_timeout: p.stall_timeout,
        max_credit_per_thread: p.max_credit_per_thread,
        pause_threshold: p.pause_threshold,
        wake_interval: p.wake_interval,
        progress_timeout: p.progress_timeout,
        progress_factor: p.progress_factor,
    }
}

fn reference_event(event: &Event) -> reference::Event {
    use reference::Event as R;
    match event.clone() {
        Event::PauseJob { .. }
        | Event::ResumeJob { .. }
        | Event::SetPriority { .. }
        | Event::DisableMachine { .. }
        | Event::EnableMachine { .. }
        | Event::RequeueTiles { .. }
        | Event::RequireTags { .. }
        | Event::WorkerTags { .. }
        | Event::Interactive { .. }
        | Event::Continue => {
            unreachable!(
                "no operator control nor continuation is generated here: the unit tests cover \
                 them"
            )
        }
        Event::Timeout => R::Timeout,
        Event::WorkerJoined {
            worker,
            threads,
            machine,
        } => R::WorkerJoined {
            worker,
            threads,
            machine,
        },
        Event::Heartbeat { worker } => R::Heartbeat { worker },
        Event::WorkerLeft { worker } => R::WorkerLeft { worker },
        Event::WorkerDraining { worker } => R::WorkerDraining { worker },
        Event::JobSubmitted {
            job,
            priority,
            scene,
            tiles,
        } => R::JobSubmitted {
            job,
            priority,
            scene,
            tiles,
        },
        Event::TileDone { worker, job, tile } => R::TileDone { worker, job, tile },
        Event::TileToConfirm {
            worker,
            job,
            tile,
            required,
        } => R::TileToConfirm {
            worker,
            job,
            tile,
            required,
        },
        Event::Quarantine { machine, revoke } => R::Quarantine { machine, revoke },
        Event::WorkerPace { worker, rtt, tile } => R::WorkerPace { worker, rtt, tile },
        Event::TileFailed {
            worker,
            job,
            tile,
            message,
        } => R::TileFailed {
            worker,
            job,
            tile,
            message,
        },
        Event::CancelJob { job } => R::CancelJob { job },
        Event::StorageUnavailable => R::StorageUnavailable,
        Event::StorageAvailable => R::StorageAvailable,
    }
}

fn from_reference(action: reference::Action) -> Action {
    use reference::Action as R;
    match action {
        R::SendScene { worker, job } => Action::SendScene { worker, job },
        R::Assign { worker, job, tile } => Action::Assign { worker, job, tile },
        R::AcceptTile { job, tile } => Action::AcceptTile { job, tile },
        R::DuplicateResult { job, tile } => Action::DuplicateResult { job, tile },
        R::HoldResult { worker, job, tile } => Action::HoldResult { worker, job, tile },
        R::AcceptHeld { job, tile } => Action::AcceptHeld { job, tile },
        R::CancelOnWorker { worker, job } => Action::CancelOnWorker { worker, job },
        R::ForgetScene { worker, scene } => Action::ForgetScene { worker, scene },
        R::DropWorker { worker } => Action::DropWorker { worker },
        R::WorkerUnresponsive { worker, silent } => Action::WorkerUnresponsive { worker, silent },
        R::WorkerResponsive { worker } => Action::WorkerResponsive { worker },
        R::JobDone { job } => Action::JobDone { job },
        R::JobFailed { job, message } => Action::JobFailed { job, message },
    }
}

/// The reference scheduler, fed the same events as a real one and checked against it.
struct Twin {
    scheduler: reference::Scheduler,
    /// Every job and worker id named so far, to compare the queries on.
    jobs: BTreeSet<JobId>,
    workers: BTreeSet<WorkerId>,
}

impl Twin {
    fn new(policy: &Policy) -> Twin {
        Twin {
            scheduler: reference::Scheduler::with_policy(reference_policy(policy)),
            jobs: BTreeSet::new(),
            workers: BTreeSet::new(),
        }
    }

    /// Gives the reference the event the real scheduler answered with `actions`, and
    /// checks that it answers the same and that both then agree on every query.
    fn check(&mut self, real: &Scheduler, now: Millis, event: &Event, actions: &[Action]) {
        match *event {
            Event::PauseJob { .. }
            | Event::ResumeJob { .. }
            | Event::SetPriority { .. }
            | Event::DisableMachine { .. }
            | Event::EnableMachine { .. }
            | Event::RequeueTiles { .. }
            | Event::RequireTags { .. }
            | Event::WorkerTags { .. }
            | Event::Interactive { .. }
            | Event::Continue => {
                unreachable!(
                    "no operator control nor continuation is generated here: the unit tests \
                     cover them"
                )
            }
            Event::Timeout | Event::StorageUnavailable | Event::StorageAvailable => {}
            Event::WorkerJoined { worker, .. }
            | Event::Heartbeat { worker }
            | Event::WorkerLeft { worker }
            | Event::WorkerDraining { worker }
            | Event::WorkerPace { worker, .. } => {
                self.workers.insert(worker);
            }
            Event::TileDone { worker, job, .. }
            | Event::TileToConfirm { worker, job, .. }
            | Event::TileFailed { worker, job, .. } => {
                self.workers.insert(worker);
                self.jobs.insert(job);
            }
            Event::Quarantine { ref revoke, .. } => {
                self.jobs.extend(revoke.iter().map(|&(job, _)| job));
            }
            Event::JobSubmitted { job, .. } | Event::CancelJob { job } => {
                self.jobs.insert(job);
            }
        }
        let expected: Vec<Action> = self
            .scheduler
            .handle(now, reference_event(event))
            .into_iter()
            .map(from_reference)
            .collect();
        assert_eq!(
            actions, expected,
            "the reference decides otherwise after {event:?} at {now}"
        );
        self.agree(real, &|| format!("after {event:?} at {now}"));
    }

    /// Resumes the same job on the reference and checks the answer.
    fn check_resume(
        &mut self,
        real: &Scheduler,
        now: Millis,
        (job, priority, scene, tiles, done): (JobId, i32, SceneHash, u32, &[u32]),
        actions: &[Action],
    ) {
        self.jobs.insert(job);
        let expected: Vec<Action> = self
            .scheduler
            .resume_job(now, job, priority, scene, tiles, done)
            .into_iter()
            .map(from_reference)
            .collect();
        let context = || format!("after resuming job {job} of {tiles} tiles, {done:?} done");
        assert_eq!(
            actions,
            expected,
            "the reference decides otherwise {}",
            context()
        );
        self.agree(real, &context);
    }

    fn agree(&self, real: &Scheduler, context: &dyn Fn() -> String) {
        let reference = &self.scheduler;
        assert_eq!(
            real.next_deadline(),
            reference.next_deadline(),
            "next deadline {}",
            context()
        );
        assert_eq!(
            real.tiles_in_flight(),
            reference.tiles_in_flight(),
            "tiles in flight {}",
            context()
        );
        for &job in &self.jobs {
            assert_eq!(
                (real.is_active(job), real.has_started(job)),
                (reference.is_active(job), reference.has_started(job)),
                "job {job} {}",
                context()
            );
        }
        for &worker in &self.workers {
            assert_eq!(
                real.held_by(worker),
                reference.held_by(worker),
                "worker {worker} {}",
                context()
            );
        }
    }
}

/// An event of a history with no model behind it: anything the daemon could send,
/// including what it never should (a worker id joining twice, a job id submitted twice).
#[derive(Clone, Debug)]
enum RawOp {
    /// A worker joins: a fresh id, or now and then the id of a live one; under one of
    /// [`NAMES`] or none.
    Join {
        threads: u32,
        reuse: Option<Index>,
        name: Option<usize>,
    },
    /// A named worker leaves and comes back at once under its name with a new id.
    Reconnect(Index),
    /// A worker stops heartbeating (hung, or cut off); a named one may rejoin.
    Cut(Index),
    /// A worker cut off joins again under its name.
    Rejoin(Index),
    /// Storage goes away (true) or comes back.
    Storage(bool),
    Leave(Index),
    Drain(Index),
    Heartbeat(Index),
    /// Every live worker heartbeats.
    Pulse,
    /// A job arrives: a fresh id, or now and then the id of an earlier one.
    Submit {
        priority: i32,
        scene: usize,
        tiles: u32,
        reuse: Option<Index>,
    },
    /// A job comes back from storage with some tiles (and some past its end) done.
    Resume {
        priority: i32,
        scene: usize,
        tiles: u32,
        done: Vec<u32>,
    },
    /// The result of an assignment not yet reported (its worker may be gone, its lease
    /// may have run out, its tile may be accepted already).
    Done(Index),
    /// A failure of such an assignment.
    Fail(Index),
    /// A result or failure for any (worker, job, tile), mostly meaningless.
    Stray {
        worker: WorkerId,
        job: JobId,
        tile: u32,
        fail: bool,
    },
    Cancel(Index),
    Tick(Millis),
    StaleTick(Millis),
    /// A long gap: the coordinator was stopped, and its timer fires first.
    Pause(Millis),
    /// The result of an assignment not yet reported, to be confirmed.
    Confirm {
        pick: Index,
        required: bool,
    },
    /// A result to confirm for any (worker, job, tile).
    StrayConfirm {
        worker: WorkerId,
        job: JobId,
        tile: u32,
        required: bool,
    },
    /// A name is quarantined; revoked: some of the tiles accepted so far, and any.
    Quarantine {
        name: usize,
        accepted: Vec<Index>,
        any: Vec<(JobId, u32)>,
    },
    /// A worker's round trip and tile time (a live worker or any id).
    Pace {
        worker: Option<Index>,
        rtt: Millis,
        tile: Millis,
    },
}

fn raw_op() -> impl Strategy<Value = RawOp> {
    prop_oneof![
        3 => (
            1u32..=4,
            prop::option::weighted(0.1, any::<Index>()),
            prop::option::weighted(0.6, 0..NAMES.len()),
        )
            .prop_map(|(threads, reuse, name)| RawOp::Join { threads, reuse, name }),
        1 => any::<Index>().prop_map(RawOp::Reconnect),
        1 => any::<Index>().prop_map(RawOp::Cut),
        1 => any::<Index>().prop_map(RawOp::Rejoin),
        1 => any::<bool>().prop_map(RawOp::Storage),
        1 => any::<Index>().prop_map(RawOp::Leave),
        1 => any::<Index>().prop_map(RawOp::Drain),
        1 => any::<Index>().prop_map(RawOp::Heartbeat),
        3 => Just(RawOp::Pulse),
        3 => (
            -1i32..=2,
            0..SCENES.len(),
            0u32..=40,
            prop::option::weighted(0.05, any::<Index>()),
        )
            .prop_map(|(priority, scene, tiles, reuse)| RawOp::Submit {
                priority,
                scene,
                tiles,
                reuse,
            }),
        1 => (-1i32..=2, 0..SCENES.len(), 0u32..=40, prop::collection::vec(0u32..45, 0..40))
            .prop_map(|(priority, scene, tiles, done)| RawOp::Resume {
                priority,
                scene,
                tiles,
                done,
            }),
        14 => any::<Index>().prop_map(RawOp::Done),
        2 => any::<Index>().prop_map(RawOp::Fail),
        2 => (1 as WorkerId..12, 1 as JobId..10, 0u32..45, any::<bool>())
            .prop_map(|(worker, job, tile, fail)| RawOp::Stray { worker, job, tile, fail }),
        1 => any::<Index>().prop_map(RawOp::Cancel),
        6 => (0..3_000 as Millis).prop_map(RawOp::Tick),
        1 => (0..3_000 as Millis).prop_map(RawOp::StaleTick),
        1 => (0..12_000 as Millis).prop_map(RawOp::Pause),
        5 => (any::<Index>(), any::<bool>())
            .prop_map(|(pick, required)| RawOp::Confirm { pick, required }),
        1 => (1 as WorkerId..12, 1 as JobId..10, 0u32..45, any::<bool>()).prop_map(
            |(worker, job, tile, required)| RawOp::StrayConfirm { worker, job, tile, required }
        ),
        1 => (
            0..NAMES.len(),
            prop::collection::vec(any::<Index>(), 0..5),
            prop::collection::vec((1 as JobId..12, 0u32..45), 0..3),
        )
            .prop_map(|(name, accepted, any)| RawOp::Quarantine { name, accepted, any }),
        2 => (prop::option::weighted(0.9, any::<Index>()), pace())
            .prop_map(|(worker, (rtt, tile))| RawOp::Pace { worker, rtt, tile }),
    ]
}

/// Any policy, leases and timeouts short enough to run out within a history (a wake
/// interval beyond the pause threshold included, which the scheduler clamps).
fn any_policy() -> impl Strategy<Value = Policy> {
    (
        (
            1..8_000 as Millis,
            1..20_000 as Millis,
            1..3_000 as Millis,
            1..5u64,
            1..7u32,
            1..4u32,
            prop::bool::weighted(0.75),
        ),
        (
            1..10u32,
            0..15_000 as Millis,
            1..5_000 as Millis,
            0..3_000 as Millis,
            prop_oneof![0..12u32, Just(64), Just(u32::MAX)],
        ),
        (
            prop_oneof![1..12_000 as Millis, Just(Millis::MAX)],
            prop_oneof![0..20u64, Just(u64::MAX)],
        ),
    )
        .prop_map(
            |(
                (
                    heartbeat_timeout,
                    initial_lease,
                    min_lease,
                    lease_factor,
                    max_attempts,
                    block_after,
                    speculate,
                ),
                (max_losses, stall_timeout, pause_threshold, wake_interval, max_credit_per_thread),
                (progress_timeout, progress_factor),
            )| Policy {
                heartbeat_timeout,
                initial_lease,
                min_lease,
                lease_factor,
                max_attempts,
                block_after,
                speculate,
                max_losses,
                stall_timeout,
                max_credit_per_thread,
                pause_threshold,
                wake_interval,
                progress_timeout,
                progress_factor,
                // The reference hands out everything in one call.
                handout_per_call: usize::MAX,
                checks_per_call: usize::MAX,
            },
        )
}

/// What the raw histories did, to show they reach the cases that matter.
#[derive(Debug, Default)]
struct RawStats {
    /// Assignments of a tile already assigned before (requeued, or copied).
    reassigned: usize,
    /// Results accepted from a worker other than the tile's latest assignee.
    accepted_from_earlier: usize,
    duplicates: usize,
    drops: usize,
    cancels: usize,
    jobs_done: usize,
    jobs_failed: usize,
    /// Jobs failed for a tile lost too often, and for a stall.
    failed_by_losses: usize,
    failed_by_stall: usize,
    /// Workers back under a name, and gaps beyond the pause threshold.
    rejoins: usize,
    pauses: usize,
    /// Results held, held results accepted on a confirmation, results from the holding
    /// machine on a held tile, and held results given up.
    holds: usize,
    confirmed: usize,
    from_holding_machine: usize,
    given_up: usize,
    /// Workers marked unresponsive (leases run out, no result), and back with a result.
    unresponsive: usize,
    responsive_again: usize,
    /// Quarantines, and the done tiles of active jobs they revoked.
    quarantines: usize,
    revoked: usize,
    /// `WorkerPace` events, and assignments they made at once.
    paces: usize,
    assigned_on_pace: usize,
}

/// The real scheduler and the reference fed the same raw history.
struct Pair {
    real: Scheduler,
    twin: Twin,
    policy: Policy,
    now: Millis,
    live: BTreeSet<WorkerId>,
    /// Live workers that heartbeat no more, and the names (with threads) of live named
    /// workers and of those cut off that may rejoin.
    silent: BTreeSet<WorkerId>,
    names: BTreeMap<WorkerId, (String, u32)>,
    cut_off: Vec<(String, u32)>,
    next_worker: WorkerId,
    next_job: JobId,
    /// Assignments not yet reported on.
    assigned: Vec<(WorkerId, JobId, u32)>,
    /// The latest assignee of each tile.
    assignee: BTreeMap<(JobId, u32), WorkerId>,
    /// Tiles accepted (their jobs may have ended), and results held, with the name of
    /// the worker they came from.
    accepted: Vec<(JobId, u32)>,
    held: BTreeMap<(JobId, u32), Option<String>>,
    stats: RawStats,
}

impl Pair {
    fn new(policy: &Policy) -> Pair {
        Pair {
            real: Scheduler::with_policy(*policy),
            twin: Twin::new(policy),
            policy: *policy,
            now: 0,
            live: BTreeSet::new(),
            silent: BTreeSet::new(),
            names: BTreeMap::new(),
            cut_off: Vec::new(),
            next_worker: 1,
            next_job: 1,
            assigned: Vec::new(),
            assignee: BTreeMap::new(),
            accepted: Vec::new(),
            held: BTreeMap::new(),
            stats: RawStats::default(),
        }
    }

    fn step(&mut self, event: Event) {
        self.step_at(self.now, event);
    }

    fn step_at(&mut self, now: Millis, event: Event) {
        if let Event::TileDone { worker, job, tile }
        | Event::TileToConfirm {
            worker, job, tile, ..
        } = event
        {
            if let (Some(Some(from)), Some((name, _))) =
                (self.held.get(&(job, tile)), self.names.get(&worker))
            {
                self.stats.from_holding_machine += usize::from(from == name);
            }
        }
        let actions = self.real.handle(now, event.clone());
        self.twin.check(&self.real, now, &event, &actions);
        match event {
            Event::WorkerJoined {
                worker,
                threads,
                ref machine,
            } => {
                self.live.insert(worker);
                self.silent.remove(&worker);
                match machine {
                    Some(name) => {
                        if self.names.values().any(|(n, _)| n == name) {
                            self.stats.rejoins += 1;
                        }
                        self.names.insert(worker, (name.clone(), threads));
                    }
                    None => {
                        self.names.remove(&worker);
                    }
                }
            }
            Event::WorkerLeft { worker } => {
                self.forget(worker);
            }
            Event::TileDone { worker, job, tile }
                if actions.contains(&Action::AcceptTile { job, tile })
                    && self.assignee.get(&(job, tile)) != Some(&worker) =>
            {
                self.stats.accepted_from_earlier += 1;
            }
            Event::Quarantine { ref revoke, .. } => {
                self.stats.quarantines += 1;
                let done: BTreeSet<(JobId, u32)> = self.accepted.iter().copied().collect();
                self.stats.revoked += revoke
                    .iter()
                    .collect::<BTreeSet<_>>()
                    .into_iter()
                    .filter(|&&(job, tile)| done.contains(&(job, tile)) && self.real.is_active(job))
                    .count();
                self.accepted.retain(|t| !revoke.contains(t));
            }
            Event::WorkerPace { .. } => {
                self.stats.paces += 1;
                self.stats.assigned_on_pace += assigns(&actions).len();
            }
            _ => {}
        }
        self.observe(&actions);
    }

    fn observe(&mut self, actions: &[Action]) {
        for action in actions {
            match *action {
                Action::Assign { worker, job, tile } => {
                    self.assigned.push((worker, job, tile));
                    if self.assignee.insert((job, tile), worker).is_some() {
                        self.stats.reassigned += 1;
                    }
                }
                Action::DropWorker { worker } => {
                    self.forget(worker);
                    self.stats.drops += 1;
                }
                Action::WorkerUnresponsive { .. } => self.stats.unresponsive += 1,
                Action::WorkerResponsive { .. } => self.stats.responsive_again += 1,
                Action::DuplicateResult { .. } => self.stats.duplicates += 1,
                Action::HoldResult { worker, job, tile } => {
                    self.stats.holds += 1;
                    let name = self.names.get(&worker).map(|(n, _)| n.clone());
                    self.held.insert((job, tile), name);
                }
                Action::AcceptTile { job, tile } => {
                    self.accepted.push((job, tile));
                    if self.held.remove(&(job, tile)).is_some() {
                        self.stats.confirmed += 1;
                    }
                }
                Action::AcceptHeld { job, tile } => {
                    self.accepted.push((job, tile));
                    self.held.remove(&(job, tile));
                    self.stats.given_up += 1;
                }
                Action::CancelOnWorker { .. } => self.stats.cancels += 1,
                Action::JobDone { .. } => self.stats.jobs_done += 1,
                Action::JobFailed { ref message, .. } => {
                    self.stats.jobs_failed += 1;
                    if message.contains("was lost with its worker") {
                        self.stats.failed_by_losses += 1;
                    }
                    if message.starts_with("no connected worker may render") {
                        self.stats.failed_by_stall += 1;
                    }
                }
                _ => {}
            }
        }
    }

    /// The worker is gone (left or dropped).
    fn forget(&mut self, worker: WorkerId) {
        self.live.remove(&worker);
        self.silent.remove(&worker);
        self.names.remove(&worker);
    }

    /// Live workers that still heartbeat.
    fn talking(&self) -> Vec<WorkerId> {
        self.live.difference(&self.silent).copied().collect()
    }

    fn apply(&mut self, op: &RawOp) {
        let live: Vec<WorkerId> = self.live.iter().copied().collect();
        let jobs: Vec<JobId> = (1..self.next_job.max(2)).collect();
        let named: Vec<WorkerId> = self.names.keys().copied().collect();
        let event = match op {
            RawOp::Reconnect(i) => {
                let Some(worker) = pick(&named, i) else {
                    return;
                };
                let (name, threads) = self.names[&worker].clone();
                self.step(Event::WorkerLeft { worker });
                self.next_worker += 1;
                Event::WorkerJoined {
                    worker: self.next_worker - 1,
                    threads,
                    machine: Some(name),
                }
            }
            RawOp::Cut(i) => {
                if let Some(worker) = pick(&self.talking(), i) {
                    self.silent.insert(worker);
                    if let Some(named) = self.names.get(&worker) {
                        self.cut_off.push(named.clone());
                    }
                }
                return;
            }
            RawOp::Rejoin(i) => {
                if self.cut_off.is_empty() {
                    return;
                }
                let (name, threads) = self.cut_off.remove(i.index(self.cut_off.len()));
                self.next_worker += 1;
                Event::WorkerJoined {
                    worker: self.next_worker - 1,
                    threads,
                    machine: Some(name),
                }
            }
            &RawOp::Storage(down) => {
                if down {
                    Event::StorageUnavailable
                } else {
                    Event::StorageAvailable
                }
            }
            &RawOp::Pause(gap) => {
                if gap > self.policy.pause_threshold {
                    self.stats.pauses += 1;
                }
                self.now += gap;
                Event::Timeout
            }
            RawOp::Join {
                threads,
                reuse,
                name,
            } => {
                let worker = match reuse.as_ref().and_then(|i| pick(&live, i)) {
                    Some(worker) => worker,
                    None => {
                        self.next_worker += 1;
                        self.next_worker - 1
                    }
                };
                Event::WorkerJoined {
                    worker,
                    threads: *threads,
                    machine: name.map(|n| NAMES[n].to_string()),
                }
            }
            RawOp::Leave(i) => match pick(&live, i) {
                Some(worker) => Event::WorkerLeft { worker },
                None => return,
            },
            RawOp::Drain(i) => match pick(&live, i) {
                Some(worker) => Event::WorkerDraining { worker },
                None => return,
            },
            RawOp::Heartbeat(i) => match pick(&self.talking(), i) {
                Some(worker) => Event::Heartbeat { worker },
                None => return,
            },
            RawOp::Pulse => {
                for worker in self.talking() {
                    self.step(Event::Heartbeat { worker });
                }
                return;
            }
            RawOp::Submit {
                priority,
                scene,
                tiles,
                reuse,
            } => {
                let job = match reuse.as_ref().and_then(|i| pick(&jobs, i)) {
                    Some(job) => job,
                    None => {
                        self.next_job += 1;
                        self.next_job - 1
                    }
                };
                Event::JobSubmitted {
                    job,
                    priority: *priority,
                    scene: SCENES[*scene],
                    tiles: *tiles,
                }
            }
            RawOp::Resume {
                priority,
                scene,
                tiles,
                done,
            } => {
                let job = self.next_job;
                self.next_job += 1;
                let actions =
                    self.real
                        .resume_job(self.now, job, *priority, SCENES[*scene], *tiles, done);
                self.twin.check_resume(
                    &self.real,
                    self.now,
                    (job, *priority, SCENES[*scene], *tiles, done),
                    &actions,
                );
                self.observe(&actions);
                return;
            }
            RawOp::Done(i) | RawOp::Fail(i) => {
                if self.assigned.is_empty() {
                    return;
                }
                let (worker, job, tile) = self.assigned.swap_remove(i.index(self.assigned.len()));
                if matches!(op, RawOp::Done(_)) {
                    Event::TileDone { worker, job, tile }
                } else {
                    Event::TileFailed {
                        worker,
                        job,
                        tile,
                        message: format!("tile {tile} failed on {worker}"),
                    }
                }
            }
            &RawOp::Stray {
                worker,
                job,
                tile,
                fail,
            } => {
                if fail {
                    Event::TileFailed {
                        worker,
                        job,
                        tile,
                        message: "stray".into(),
                    }
                } else {
                    Event::TileDone { worker, job, tile }
                }
            }
            RawOp::Cancel(i) => Event::CancelJob {
                job: pick(&jobs, i).expect("never empty"),
            },
            RawOp::Tick(advance) => {
                if *advance > self.policy.pause_threshold {
                    self.stats.pauses += 1;
                }
                self.now += advance;
                Event::Timeout
            }
            RawOp::StaleTick(back) => {
                self.step_at(self.now.saturating_sub(*back), Event::Timeout);
                return;
            }
            &RawOp::Confirm { ref pick, required } => {
                if self.assigned.is_empty() {
                    return;
                }
                let (worker, job, tile) =
                    self.assigned.swap_remove(pick.index(self.assigned.len()));
                Event::TileToConfirm {
                    worker,
                    job,
                    tile,
                    required,
                }
            }
            &RawOp::StrayConfirm {
                worker,
                job,
                tile,
                required,
            } => Event::TileToConfirm {
                worker,
                job,
                tile,
                required,
            },
            RawOp::Quarantine {
                name,
                accepted,
                any,
            } => {
                let mut revoke: Vec<(JobId, u32)> = accepted
                    .iter()
                    .filter_map(|i| pick(&self.accepted, i))
                    .collect();
                revoke.extend(any);
                Event::Quarantine {
                    machine: NAMES[*name].to_string(),
                    revoke,
                }
            }
            &RawOp::Pace {
                ref worker,
                rtt,
                tile,
            } => {
                let worker = match worker {
                    Some(i) => match pick(&live, i) {
                        Some(worker) => worker,
                        None => return,
                    },
                    None => self.next_worker + 3,
                };
                Event::WorkerPace { worker, rtt, tile }
            }
        };
        self.step(event);
    }

    /// Ends the history: everyone returns everything, round after round, with the
    /// clock running, until no job is left or nothing changes any more.
    fn wind_down(&mut self) {
        for _ in 0..50 {
            if self.assigned.is_empty() {
                break;
            }
            self.step(Event::StorageAvailable);
            for worker in self.live.clone() {
                self.step(Event::Heartbeat { worker });
            }
            for (worker, job, tile) in std::mem::take(&mut self.assigned) {
                self.step(Event::TileDone { worker, job, tile });
            }
            self.now += 1_000;
            self.step(Event::Timeout);
        }
    }
}

fn raw_history(policy: &Policy, ops: &[RawOp]) -> Pair {
    let mut pair = Pair::new(policy);
    for op in ops {
        pair.apply(op);
    }
    pair.wind_down();
    pair
}

proptest! {
    #![proptest_config(config(300))]

    /// Random histories of any event, under random policies: the indexed scheduler
    /// returns exactly the actions the reference does, in the same order, after every
    /// event, and both agree on every query.
    #[test]
    fn the_indexed_scheduler_decides_as_the_reference_does(
        policy in any_policy(),
        ops in prop::collection::vec(raw_op(), 0..300),
    ) {
        raw_history(&policy, &ops);
    }

    /// The same in the model's clocked histories (every event a daemon would send, the
    /// model's invariants checked too), with and without speculation.
    #[test]
    fn the_indexed_scheduler_decides_as_the_reference_does_in_the_model_s_histories(
        speculate in prop::bool::weighted(0.75),
        ops in prop::collection::vec(clocked_op(), 0..200),
    ) {
        let policy = Policy { speculate, ..tight(clocked_policy()) };
        let mut farm = Farm::with_policy(policy, true);
        farm.reference = Some(Twin::new(&farm.policy));
        for op in &ops {
            farm.apply(op);
        }
        farm.run_with_clock();
    }
}

/// The raw histories reach what the indexes are about: tiles reassigned (after their
/// leases ran out, or copied), results accepted from an earlier holder, duplicates,
/// drops, cancellations, jobs done and failed (for tiles lost too often and for stalls
/// too), workers back under a name, and pauses (fixed seed).
#[test]
fn the_raw_histories_exercise_every_feature() {
    let mut runner = TestRunner::deterministic();
    let mut stats = RawStats::default();
    for _ in 0..100 {
        let policy = any_policy()
            .new_tree(&mut runner)
            .expect("a policy")
            .current();
        let ops = prop::collection::vec(raw_op(), 200..300)
            .new_tree(&mut runner)
            .expect("a history")
            .current();
        let s = raw_history(&policy, &ops).stats;
        stats.reassigned += s.reassigned;
        stats.accepted_from_earlier += s.accepted_from_earlier;
        stats.duplicates += s.duplicates;
        stats.drops += s.drops;
        stats.unresponsive += s.unresponsive;
        stats.responsive_again += s.responsive_again;
        stats.cancels += s.cancels;
        stats.jobs_done += s.jobs_done;
        stats.jobs_failed += s.jobs_failed;
        stats.failed_by_losses += s.failed_by_losses;
        stats.failed_by_stall += s.failed_by_stall;
        stats.rejoins += s.rejoins;
        stats.pauses += s.pauses;
        stats.holds += s.holds;
        stats.confirmed += s.confirmed;
        stats.from_holding_machine += s.from_holding_machine;
        stats.given_up += s.given_up;
        stats.quarantines += s.quarantines;
        stats.revoked += s.revoked;
        stats.paces += s.paces;
        stats.assigned_on_pace += s.assigned_on_pace;
    }
    println!("{stats:?}");
    let RawStats {
        reassigned,
        accepted_from_earlier,
        duplicates,
        drops,
        unresponsive,
        responsive_again,
        cancels,
        jobs_done,
        jobs_failed,
        failed_by_losses,
        failed_by_stall,
        rejoins,
        pauses,
        holds,
        confirmed,
        from_holding_machine,
        given_up,
        quarantines,
        revoked,
        paces,
        assigned_on_pace,
    } = stats;
    for (what, count) in [
        ("reassigned", reassigned),
        ("accepted_from_earlier", accepted_from_earlier),
        ("duplicates", duplicates),
        ("drops", drops),
        ("unresponsive", unresponsive),
        ("responsive_again", responsive_again),
        ("cancels", cancels),
        ("jobs_done", jobs_done),
        ("jobs_failed", jobs_failed),
        ("failed_by_losses", failed_by_losses),
        ("failed_by_stall", failed_by_stall),
        ("rejoins", rejoins),
        ("pauses", pauses),
        ("holds", holds),
        ("confirmed", confirmed),
        ("from_holding_machine", from_holding_machine),
        ("given_up", given_up),
        ("quarantines", quarantines),
        ("revoked", revoked),
        ("paces", paces),
        ("assigned_on_pace", assigned_on_pace),
    ] {
        assert!(count > 0, "no {what} in the raw histories");
    }
}

/// A worker whose credit a pace raises above one call's hand-out still gets every tile
/// it may take (found by `random_histories_keep_the_invariants_and_finish_every_job`:
/// 263 tiles waiting, a pace raising a 2-thread worker's credit to 512).
#[test]
fn a_pace_raising_credit_past_one_call_s_hand_out_fills_the_worker() {
    let mut ops: Vec<Op> = [24u32, 1, 26, 23, 23, 28, 26, 29, 19, 16, 16]
        .into_iter()
        .map(|tiles| Op::Submit {
            priority: 0,
            scene: 0,
            tiles,
        })
        .collect();
    ops.push(Op::Submit {
        priority: 0,
        scene: 0,
        tiles: 30,
    });
    ops.push(Op::Join {
        threads: 2,
        name: None,
    });
    ops.push(Op::Join {
        threads: 1,
        name: None,
    });
    ops.push(Op::Submit {
        priority: 0,
        scene: 0,
        tiles: 2,
    });
    let mut farm = Farm::with_policy(tight(no_speculation()), true);
    for op in &ops {
        farm.apply(op);
    }
    let first = *farm.workers.keys().next().expect("two workers joined");
    farm.step(Event::WorkerPace {
        worker: first,
        rtt: 5377,
        tile: 0,
    });
    farm.run_to_completion();
}
